//! A round of adaptive sampling on the CPU: the active blocks (or every
//! block over its own range, [`render_blocks`]), in runs of up to
//! four along a row (a run's range cut into pieces of at most
//! [`PIECE`] pixel-samples, each a task of its own), are rendered one sample index at a time by the ordinary tile renderer
//! ([`super::render_tile`], so the stream, recursive and
//! distributed paths all apply unchanged), and each single-sample film's
//! fixed-point values are added to the block's sums and, squared, to its
//! sums of squares. Sums, counts and rays are those of a uniform render of
//! the same samples, bit for bit.

use rayon::prelude::*;

use super::{TASKS_PER_THREAD, render_tile};
use crate::adaptive::{BLOCK, BlockMask};
use crate::film::{Film, Rect, RunCost, SampleRange};
use crate::math::Real;
use crate::render::{CpuRenderer, PreparedFrame, RenderError};
use crate::world::World;

/// Renders the blocks of `mask` over `samples` (see
/// [`crate::render::adaptive::render_round`]); the film's `runs` are the
/// runs of blocks it rendered with the rays each traced: the cost the
/// error-optimal mode allocates by (rays, not seconds, so the allocation
/// is the same on every machine).
pub fn render_round(
    renderer: &CpuRenderer,
    prepared: &PreparedFrame,
    frame: u32,
    mask: &BlockMask,
    samples: SampleRange,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Film, RenderError> {
    prepared.check_request(mask.rect, samples)?;
    let ranges: Vec<Option<SampleRange>> =
        mask.active.iter().map(|&a| a.then_some(samples)).collect();
    let mut film = Film::with_squares(mask.rect);
    film.runs = add_ranges(renderer, prepared, frame, &ranges, &mut film, progress);
    Ok(film)
}

/// Renders each block `i` of `rect` (block-aligned) over its own range
/// `from[i]..to[i]` (none where equal), all in one parallel pass: what
/// [`render_round`] per distinct range would give, merged, bit for
/// bit, with the same runs (a run joins neighbours of one range), each
/// with its rays and samples per pixel in the film's `runs`.
pub fn render_blocks(
    renderer: &CpuRenderer,
    prepared: &PreparedFrame,
    frame: u32,
    rect: Rect,
    from: &[u32],
    to: &[u32],
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Film, RenderError> {
    let mut film = Film::with_squares(rect);
    film.runs = add_blocks(renderer, prepared, frame, from, to, &mut film, progress)?;
    Ok(film)
}

/// [`render_blocks`] over the whole of `film` (an adaptive film), added
/// to it in place: the runs it rendered are returned, not put in `film`.
/// The local error-optimal driver's round, which would otherwise merge a
/// second whole-frame film into its own each round, on one thread.
pub fn add_blocks(
    renderer: &CpuRenderer,
    prepared: &PreparedFrame,
    frame: u32,
    from: &[u32],
    to: &[u32],
    film: &mut Film,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Vec<RunCost>, RenderError> {
    let ranges = prepared.block_ranges(film.rect, from, to)?;
    Ok(add_ranges(
        renderer, prepared, frame, &ranges, film, progress,
    ))
}

fn add_ranges(
    renderer: &CpuRenderer,
    prepared: &PreparedFrame,
    frame: u32,
    ranges: &[Option<SampleRange>],
    film: &mut Film,
    progress: &(dyn Fn(u64) + Sync),
) -> Vec<RunCost> {
    match prepared {
        PreparedFrame::F32(w) => blocks_world(renderer, w, frame, ranges, film, progress),
        PreparedFrame::F64(w) => blocks_world(renderer, w, frame, ranges, film, progress),
    }
}

/// Renders block `i` of `out.rect` over `ranges[i]` and adds it to `out`;
/// returns the runs rendered, with their rays.
fn blocks_world<R: Real>(
    renderer: &CpuRenderer,
    world: &World<R>,
    frame: u32,
    ranges: &[Option<SampleRange>],
    out: &mut Film,
    progress: &(dyn Fn(u64) + Sync),
) -> Vec<RunCost> {
    let rect = out.rect;
    let blocks = runs(rect, ranges);
    // A run's samples in pieces of at most PIECE pixel-samples (fewer in
    // a small round: about 32 pieces a thread, so that a round's last
    // pieces leave the other threads idle for little, which the
    // error-optimal mode's many rounds pay for each), each its own task: the
    // error-optimal mode gives a few blocks hundreds of samples in a round
    // where most get a few, and a run rendered whole would leave the other
    // threads idle at the round's end. Sums are integers, so a run's
    // pieces merge into what the run renders whole, bit for bit, whatever
    // the pieces.
    let work: usize = blocks
        .iter()
        .map(|(b, s)| b.area() * s.len() as usize)
        .sum();
    let piece = (work / (TASKS_PER_THREAD * renderer.threads())).clamp(1, PIECE);
    let pieces: Vec<(usize, SampleRange)> = blocks
        .iter()
        .enumerate()
        .flat_map(|(i, &(b, samples))| {
            samples
                .batches((piece / b.area()) as u32)
                .map(move |s| (i, s))
        })
        .collect();
    // Runs, and so pieces, come in row order: the pieces of each band of
    // one block row, which are added to that band of `out` by one task.
    let band_of = |piece: &(usize, SampleRange)| ((blocks[piece.0].0.y - rect.y) / BLOCK) as usize;
    let bands = rect.height.div_ceil(BLOCK) as usize;
    let band_starts: Vec<usize> = (0..=bands)
        .map(|band| pieces.partition_point(|p| band_of(p) < band))
        .collect();
    let w = rect.width as usize;
    let band_pixels = BLOCK as usize * w;
    let films: Vec<Film> = renderer.pool().install(|| {
        let films: Vec<Film> = pieces
            .par_iter()
            // One piece a task, as the renderer's tiles (render/cpu): no
            // thread waits on another's last few pieces.
            .with_max_len(1)
            .map(|&(i, samples)| {
                let b = blocks[i].0;
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
            .collect();
        // Into `out` band by band, in parallel: a round's thousand pieces
        // added on one thread cost the other threads' time too.
        let squares = out.squares.as_mut().expect("adaptive film");
        out.sums
            .par_chunks_mut(band_pixels)
            .zip(out.counts.par_chunks_mut(band_pixels))
            .zip(squares.par_chunks_mut(band_pixels))
            .enumerate()
            .for_each(|(band, ((sums, counts), squares))| {
                for f in &films[band_starts[band]..band_starts[band + 1]] {
                    let r = f.rect;
                    let f_squares = f.squares.as_ref().expect("adaptive film");
                    for row in 0..r.height as usize {
                        let dst = (r.y - rect.y) as usize % BLOCK as usize * w
                            + row * w
                            + (r.x - rect.x) as usize;
                        let src = row * r.width as usize;
                        for col in 0..r.width as usize {
                            for c in 0..3 {
                                sums[dst + col][c] += f.sums[src + col][c];
                                squares[dst + col][c] += f_squares[src + col][c];
                            }
                            counts[dst + col] += f.counts[src + col];
                        }
                    }
                }
            });
        films
    });
    let mut rays = vec![0u64; blocks.len()];
    for (f, &(i, _)) in films.iter().zip(&pieces) {
        out.rays.add(&f.rays);
        out.nonfinite += f.nonfinite;
        rays[i] += f.rays.total();
    }
    blocks
        .iter()
        .zip(rays)
        .map(|(&(rect, s), rays)| RunCost {
            rect,
            rays,
            samples: s.len(),
        })
        .collect()
}

/// Most pixel-samples of a piece of a run (16 samples of a run of four blocks).
const PIECE: usize = 16 * (RUN_BLOCKS * BLOCK * BLOCK) as usize;

/// Most blocks rendered together: 4 blocks of 8x8 are 256 pixels, one
/// batch of the stream renderer (a lone block would be a quarter batch).
const RUN_BLOCKS: u32 = 4;
/// Runs never cross a multiple of this many pixels of the image's columns,
/// so that any rect whose columns start and end on such multiples (or at
/// the image's edge) is cut into the same runs as the whole frame: the
/// farm's tiles of the error-optimal mode book the costs a local render
/// books.
pub const RUN_ALIGN: u32 = RUN_BLOCKS * BLOCK;

/// The blocks of `rect` that have a range joined into runs of
/// neighbours of one range along a row of blocks, within one
/// [`RUN_ALIGN`]-pixel column of the image: the rects (and ranges) each
/// call renders.
fn runs(rect: Rect, ranges: &[Option<SampleRange>]) -> Vec<(Rect, SampleRange)> {
    let mask = BlockMask::none(rect);
    let mut out: Vec<(Rect, SampleRange)> = Vec::new();
    for (i, range) in ranges.iter().enumerate() {
        let Some(range) = *range else { continue };
        let b = mask.block_rect(i);
        match out.last_mut() {
            Some((r, s))
                if *s == range
                    && r.y == b.y
                    && r.x + r.width == b.x
                    && !b.x.is_multiple_of(RUN_ALIGN) =>
            {
                r.width += b.width;
            }
            _ => out.push((b, range)),
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
