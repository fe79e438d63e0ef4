//! A round of adaptive sampling on the CPU: the active blocks, in runs of
//! up to four along a row, are rendered one sample index at a time by the ordinary tile renderer
//! ([`super::render_tile`], so the stream, recursive and
//! distributed paths all apply unchanged), and each single-sample film's
//! fixed-point values are added to the block's sums and, squared, to its
//! sums of squares. Sums, counts and rays are those of a uniform render of
//! the same samples, bit for bit.

use rayon::prelude::*;

use super::render_tile;
use crate::adaptive::BlockMask;
use crate::film::{Film, Rect, SampleRange};
use crate::math::Real;
use crate::render::{CpuRenderer, PreparedFrame, RenderError};
use crate::world::World;

/// Renders the blocks of `mask` over `samples` (see
/// [`crate::render::adaptive::render_round`]), also returning each run of
/// blocks it rendered with the rays it traced: the cost the error-optimal
/// mode allocates by (rays, not seconds, so the allocation is the same on
/// every machine).
pub fn render_round_costed(
    renderer: &CpuRenderer,
    prepared: &PreparedFrame,
    frame: u32,
    mask: &BlockMask,
    samples: SampleRange,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<(Film, Vec<(Rect, u64)>), RenderError> {
    prepared.check_request(mask.rect, samples)?;
    Ok(match prepared {
        PreparedFrame::F32(w) => round_world(renderer, w, frame, mask, samples, progress),
        PreparedFrame::F64(w) => round_world(renderer, w, frame, mask, samples, progress),
    })
}

fn round_world<R: Real>(
    renderer: &CpuRenderer,
    world: &World<R>,
    frame: u32,
    mask: &BlockMask,
    samples: SampleRange,
    progress: &(dyn Fn(u64) + Sync),
) -> (Film, Vec<(Rect, u64)>) {
    let blocks = runs(mask);
    let films: Vec<Film> = renderer.pool().install(|| {
        blocks
            .par_iter()
            // One run a piece, as the renderer's tiles (render/cpu): no
            // thread waits on another's last few runs.
            .with_max_len(1)
            .map(|&b| {
                let mut acc = Film::with_squares(b);
                for k in samples.start..samples.end {
                    add_single(
                        &mut acc,
                        &render_tile(world, frame, b, SampleRange::new(k, k + 1)),
                    );
                }
                progress(b.area() as u64 * samples.len() as u64);
                acc
            })
            .collect()
    });
    let mut out = Film::with_squares(mask.rect);
    for f in &films {
        out.merge(f)
            .expect("blocks lie inside their rect and sums cannot overflow");
    }
    let costs = films.iter().map(|f| (f.rect, f.rays.total())).collect();
    (out, costs)
}

/// Most blocks rendered together: 4 blocks of 8x8 are 256 pixels, one
/// batch of the stream renderer (a lone block would be a quarter batch).
const RUN_BLOCKS: usize = 4;

/// The active blocks of `mask` joined into runs of up to [`RUN_BLOCKS`]
/// neighbours along a row of blocks: the rects each call renders.
fn runs(mask: &BlockMask) -> Vec<Rect> {
    let mut out: Vec<Rect> = Vec::new();
    let mut len = 0;
    for b in mask.active_rects() {
        match out.last_mut() {
            Some(r) if len < RUN_BLOCKS && r.y == b.y && r.x + r.width == b.x => {
                r.width += b.width;
                len += 1;
            }
            _ => {
                out.push(b);
                len = 1;
            }
        }
    }
    out
}

/// Adds a film of one sample per pixel (same rect) to `acc`, squares included.
fn add_single(acc: &mut Film, one: &Film) {
    let squares = acc.squares.as_mut().expect("adaptive film");
    for (i, s) in one.sums.iter().enumerate() {
        for c in 0..3 {
            acc.sums[i][c] += s[c];
            squares[i][c] += s[c] as u128 * s[c] as u128;
        }
        acc.counts[i] += one.counts[i];
    }
    acc.rays.add(&one.rays);
    acc.nonfinite += one.nonfinite;
}
