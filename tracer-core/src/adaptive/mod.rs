//! Adaptive sampling with an error target (issue 17): more samples only
//! where the estimated error of a pixel's mean is still above the target.
//!
//! A render runs in *rounds*: round 0 gives every pixel `min_samples`;
//! round r gives each still *active* block of [`BLOCK`] x [`BLOCK`] pixels
//! the samples `min * 2^(r-1) .. min * 2^r` (capped at `max_samples`), so
//! each round doubles an active block's samples. After a round a block
//! stays active only while some pixel of it has a standard error of its
//! mean above the target in some linear RGB channel ([`block_converged`]).
//! The target is absolute (`target_error`, in linear radiance), relative
//! (`relative_error`, a share of the pixel's brightest channel mean), or
//! both: a pixel's limit is the larger of the two ([`Target`]).
//!
//! Determinism: a decision uses only the samples of earlier rounds, held
//! as exact fixed-point sums and sums of squares ([`Film::squares`]); the
//! rule is a pure function of a block's own pixels ([`next_active`]), and
//! samples are placed by [`Sampler::Progressive`], so sample k of a pixel
//! is the same sample as in a uniform render of any count. The image
//! therefore depends neither on tiling, nor on threads, nor on which
//! machine rendered which round, and a render in which every block reaches
//! `max_samples` equals the uniform render at `max_samples`.
//!
//! Here the blocks, masks and statistics, which the scene, the renderers,
//! the farm's coordinator and the CLI share; the settings are the scene's
//! (`scene::adaptive`, re-exported here), and the rounds are a renderer's
//! (`render::adaptive`). Nothing here imports a renderer.
//!
//! Blocks are aligned to the image (block (i, j) covers pixels 8i..8i+8,
//! 8j..8j+8, cut at the image's right and bottom edges). A rect rendered
//! adaptively must start on the block grid ([`check_rect`]).

use crate::film::{FIXED_ONE, Film, Rect, SampleRange};

pub mod optimal;

pub use crate::scene::adaptive::{
    AdaptiveError, AdaptiveMode, AdaptiveSettings, AdaptiveSpec, DEFAULT_MAX_SAMPLES,
    DEFAULT_MIN_SAMPLES, Target,
};

/// Side of the square blocks a decision is made for. Per pixel would stop
/// single pixels whose few samples happened to agree (a penumbra pixel whose
/// first 16 light samples all hit); a block's 64 pixels rarely all do, and
/// the image stays free of isolated noisy pixels.
pub const BLOCK: u32 = 8;
/// Why a rect or a mask does not fit the block grid.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BlockError {
    #[error(
        "rect {rect:?} is not on the {BLOCK}x{BLOCK} block grid of the {width}x{height} image: adaptive rects start at multiples of {BLOCK} and end at one or at the image's edge"
    )]
    Unaligned { rect: Rect, width: u32, height: u32 },
    #[error("active-block mask of rect {rect:?} has {got} bytes, expected {expected}")]
    MaskSize {
        rect: Rect,
        expected: usize,
        got: usize,
    },
}

/// Checks that `rect` starts on the block grid and ends on it or at the
/// image's edge, so its blocks are the image's blocks.
pub fn check_rect(rect: Rect, width: u32, height: u32) -> Result<(), BlockError> {
    let edge_ok = |start: u32, len: u32, side: u32| {
        start.is_multiple_of(BLOCK) && ((start + len).is_multiple_of(BLOCK) || start + len == side)
    };
    if edge_ok(rect.x, rect.width, width) && edge_ok(rect.y, rect.height, height) {
        Ok(())
    } else {
        Err(BlockError::Unaligned {
            rect,
            width,
            height,
        })
    }
}

/// Which blocks of a block-aligned rect a round samples.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BlockMask {
    pub rect: Rect,
    /// One flag per block of `rect`, row-major.
    pub active: Vec<bool>,
}

impl BlockMask {
    pub fn all(rect: Rect) -> Self {
        BlockMask {
            rect,
            active: vec![true; blocks_of(rect)],
        }
    }

    pub fn none(rect: Rect) -> Self {
        BlockMask {
            rect,
            active: vec![false; blocks_of(rect)],
        }
    }

    pub fn cols(&self) -> u32 {
        self.rect.width.div_ceil(BLOCK)
    }

    /// The pixels of block `i` (row-major over the rect's blocks).
    pub fn block_rect(&self, i: usize) -> Rect {
        block_rect(self.rect, self.cols(), i)
    }

    pub fn active_count(&self) -> usize {
        self.active.iter().filter(|&&a| a).count()
    }

    /// Pixels of the active blocks.
    pub fn active_pixels(&self) -> u64 {
        self.active_rects().map(|b| b.area() as u64).sum()
    }

    pub fn active_rects(&self) -> impl Iterator<Item = Rect> + '_ {
        let cols = self.cols();
        self.active
            .iter()
            .enumerate()
            .filter(|(_, a)| **a)
            .map(move |(i, _)| block_rect(self.rect, cols, i))
    }

    /// Whether pixel `(x, y)` (image coordinates, inside the rect) is active.
    pub fn covers(&self, x: u32, y: u32) -> bool {
        self.active[block_index(self.rect, x, y)]
    }

    /// One bit per block, row-major, least significant bit first: how a mask
    /// travels with a farm unit.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = vec![0u8; self.active.len().div_ceil(8)];
        for (i, _) in self.active.iter().enumerate().filter(|(_, a)| **a) {
            out[i / 8] |= 1 << (i % 8);
        }
        out
    }

    pub fn from_bytes(rect: Rect, bytes: &[u8]) -> Result<Self, BlockError> {
        let n = blocks_of(rect);
        if bytes.len() != n.div_ceil(8) {
            return Err(BlockError::MaskSize {
                rect,
                expected: n.div_ceil(8),
                got: bytes.len(),
            });
        }
        Ok(BlockMask {
            rect,
            active: (0..n).map(|i| bytes[i / 8] & (1 << (i % 8)) != 0).collect(),
        })
    }
}

/// The index (row-major over the blocks of block-aligned `rect`) of the
/// block holding pixel `(x, y)` (image coordinates, inside the rect).
pub fn block_index(rect: Rect, x: u32, y: u32) -> usize {
    let (bx, by) = ((x - rect.x) / BLOCK, (y - rect.y) / BLOCK);
    (by * rect.width.div_ceil(BLOCK) + bx) as usize
}

fn blocks_of(rect: Rect) -> usize {
    rect.width.div_ceil(BLOCK) as usize * rect.height.div_ceil(BLOCK) as usize
}

fn block_rect(rect: Rect, cols: u32, i: usize) -> Rect {
    let (bx, by) = (i as u32 % cols, i as u32 / cols);
    let (x, y) = (rect.x + bx * BLOCK, rect.y + by * BLOCK);
    Rect::new(
        x,
        y,
        BLOCK.min(rect.x + rect.width - x),
        BLOCK.min(rect.y + rect.height - y),
    )
}

pub use crate::film::variance_of_mean;

/// The largest of a pixel's three standard errors (what the target bounds).
pub fn pixel_error(film: &Film, i: usize) -> f64 {
    film.pixel_error(i)
}

/// The largest of a pixel's three channel means (linear radiance), from
/// its exact sums: the scale of [`Target::relative`].
pub fn brightest_mean(n: u32, sums: &[u64; 3]) -> f64 {
    if n == 0 {
        return 0.0;
    }
    sums.iter().copied().max().unwrap_or(0) as f64 / (n as f64 * FIXED_ONE)
}

/// A pixel's largest variance of the mean over its limit (at most 1:
/// converged); 0 for a pixel whose samples all agree, even at a zero limit.
fn error_ratio(n: u32, sums: &[u64; 3], squares: &[u128; 3], target: Target) -> f64 {
    let v = variance_of_mean(n, sums, squares);
    let worst = v[0].max(v[1]).max(v[2]);
    if worst == 0.0 {
        return 0.0;
    }
    worst / target.limit_sq(brightest_mean(n, sums))
}

/// Whether every pixel of `block` (inside `film.rect`) has a standard error
/// within `target` in every channel.
pub fn block_converged(film: &Film, block: Rect, target: Target) -> bool {
    let squares = film.squares.as_ref().expect("adaptive film");
    (block.y..block.y + block.height).all(|y| {
        (block.x..block.x + block.width).all(|x| {
            let i = ((y - film.rect.y) * film.rect.width + (x - film.rect.x)) as usize;
            error_ratio(film.counts[i], &film.sums[i], &squares[i], target) <= 1.0
        })
    })
}

/// The blocks of `rect` that round `round` samples, from `film` (which
/// holds every earlier round of those pixels): a block takes part iff it
/// took part in every earlier round (its pixels have exactly `round.start`
/// samples) and is not converged. Round 0 samples every block. A pure
/// function of the blocks' own pixels, so the coordinator computes it per
/// tile and `tessera render` for the whole image, with the same answer.
pub fn next_active(film: &Film, rect: Rect, round: SampleRange, target: Target) -> BlockMask {
    let mut mask = BlockMask::none(rect);
    let cols = mask.cols();
    for (i, a) in mask.active.iter_mut().enumerate() {
        let b = block_rect(rect, cols, i);
        let first = ((b.y - film.rect.y) * film.rect.width + (b.x - film.rect.x)) as usize;
        *a = round.start == 0
            || (film.counts[first] == round.start && !block_converged(film, b, target));
    }
    mask
}

/// Where an adaptive render of `rect` stands, for progress logs and `watch`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Summary {
    pub blocks: u64,
    /// Blocks whose every pixel has reached the target.
    pub converged_blocks: u64,
    /// Blocks at `max_samples` still above the target.
    pub capped_blocks: u64,
    /// Root mean square over pixels and channels of the estimated standard
    /// error: the expected RMSE of the image against the converged one.
    pub rms_error: f64,
    /// Pixel-samples traced so far.
    pub samples_done: u64,
    /// Pixel-samples the render is expected to take in all: each
    /// unconverged block continues (doubling) until its error, falling as
    /// one over the square root of its samples, reaches the target.
    pub samples_expected: u64,
}

impl Summary {
    /// Share of blocks converged, 0..=1.
    pub fn converged_share(&self) -> f64 {
        if self.blocks == 0 {
            0.0
        } else {
            self.converged_blocks as f64 / self.blocks as f64
        }
    }
}

/// One block's error, what a [`Summary`] is made of: from a film on the
/// host ([`summarize`]) or from the GPU's convergence test.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BlockStatus {
    /// Pixels of the block.
    pub area: u64,
    /// Samples each of its pixels has (0: not started).
    pub samples: u32,
    /// Sum over its pixels and channels of the finite variances of the mean.
    pub variance_sum: f64,
    /// Its pixels' largest variance of the mean over their limit (at most
    /// 1: converged).
    pub worst: f64,
}

/// Summarises `film` (which must cover `rect`, a block-aligned rect with
/// every pixel past round 0 or not started at all).
pub fn summarize(film: &Film, rect: Rect, a: &AdaptiveSettings) -> Summary {
    let mask = BlockMask::none(rect);
    let squares = film.squares.as_ref().expect("adaptive film");
    let blocks = (0..mask.active.len()).map(|i| {
        let b = mask.block_rect(i);
        let first = ((b.y - film.rect.y) * film.rect.width + (b.x - film.rect.x)) as usize;
        let mut e = BlockStatus {
            area: b.area() as u64,
            samples: film.counts[first],
            variance_sum: 0.0,
            worst: 0.0,
        };
        if e.samples > 0 {
            for y in b.y..b.y + b.height {
                for x in b.x..b.x + b.width {
                    let j = ((y - film.rect.y) * film.rect.width + (x - film.rect.x)) as usize;
                    let v = variance_of_mean(film.counts[j], &film.sums[j], &squares[j]);
                    e.variance_sum += v.iter().filter(|v| v.is_finite()).sum::<f64>();
                    e.worst = e.worst.max(error_ratio(
                        film.counts[j],
                        &film.sums[j],
                        &squares[j],
                        a.target(),
                    ));
                }
            }
        }
        e
    });
    summarize_blocks(blocks, a)
}

/// Summarises an image from its blocks' errors.
pub fn summarize_blocks(
    blocks: impl IntoIterator<Item = BlockStatus>,
    a: &AdaptiveSettings,
) -> Summary {
    let mut out = Summary::default();
    let mut sq_err = 0.0f64;
    let mut pixels = 0u64;
    for b in blocks {
        out.blocks += 1;
        let (n, area) = (b.samples, b.area);
        out.samples_done += n as u64 * area;
        if n == 0 {
            out.samples_expected += a.min_samples as u64 * area;
            continue;
        }
        sq_err += b.variance_sum;
        pixels += area;
        let worst = b.worst;
        let expected = if worst <= 1.0 {
            out.converged_blocks += 1;
            n
        } else if n >= a.max_samples {
            out.capped_blocks += 1;
            n
        } else {
            // Samples at which the worst pixel's error would reach the
            // target, on the doubling schedule, at most max_samples.
            let need = n as f64 * worst;
            let mut m = n;
            while (m as f64) < need && m < a.max_samples {
                m = m.saturating_mul(2).min(a.max_samples);
            }
            m
        };
        out.samples_expected += expected as u64 * area;
    }
    out.rms_error = if pixels == 0 {
        0.0
    } else {
        (sq_err / (3 * pixels) as f64).sqrt()
    };
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn masks_round_trip_and_cut_blocks_at_the_edge() {
        let rect = Rect::new(16, 8, 20, 9);
        let mut m = BlockMask::none(rect);
        assert_eq!(m.active.len(), 3 * 2);
        m.active[1] = true;
        m.active[5] = true;
        assert_eq!(BlockMask::from_bytes(rect, &m.to_bytes()).unwrap(), m);
        assert_eq!(
            m.active_rects().collect::<Vec<_>>(),
            vec![Rect::new(24, 8, 8, 8), Rect::new(32, 16, 4, 1)]
        );
        assert!(m.covers(31, 15) && !m.covers(16, 8));
        assert!(matches!(
            BlockMask::from_bytes(rect, &[0, 0]),
            Err(BlockError::MaskSize { .. })
        ));
        assert!(check_rect(rect, 36, 17).is_ok());
        assert!(check_rect(rect, 40, 17).is_err());
        assert!(check_rect(Rect::new(4, 0, 8, 8), 40, 40).is_err());
    }

    #[test]
    fn the_variance_is_exact_and_zero_for_equal_samples() {
        let q = 3u64 << 31; // 1.5 in fixed point
        let n = 16u32;
        let sums = [q * n as u64; 3];
        let squares = [(q as u128 * q as u128) * n as u128; 3];
        assert_eq!(variance_of_mean(n, &sums, &squares), [0.0; 3]);
        // Samples 0 and 1, eight of each: variance 16/15 * 0.25, of the mean / 16.
        let one = 1u64 << 32;
        let sums = [8 * one; 3];
        let squares = [8 * (one as u128 * one as u128); 3];
        let v = variance_of_mean(n, &sums, &squares);
        assert_eq!(v[0], 0.25 * 16.0 / 15.0 / 16.0);
        assert_eq!(variance_of_mean(1, &sums, &squares), [f64::INFINITY; 3]);
    }
}
