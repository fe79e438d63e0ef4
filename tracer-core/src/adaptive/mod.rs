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
//! Blocks are aligned to the image (block (i, j) covers pixels 8i..8i+8,
//! 8j..8j+8, cut at the image's right and bottom edges). A rect rendered
//! adaptively must start on the block grid ([`check_rect`]).

pub mod cpu;

use crate::film::{FIXED_ONE, Film, Rect, SampleRange};
use crate::render::{PreparedFrame, Renderer, RendererError};
use crate::sampling::Sampler;
use crate::scene::{MAX_SAMPLES, RenderSettings};

/// Side of the square blocks a decision is made for. Per pixel would stop
/// single pixels whose few samples happened to agree (a penumbra pixel whose
/// first 16 light samples all hit); a block's 64 pixels rarely all do, and
/// the image stays free of isolated noisy pixels.
pub const BLOCK: u32 = 8;
/// Defaults of `--min-samples` and `--max-samples`.
pub const DEFAULT_MIN_SAMPLES: u32 = 16;
pub const DEFAULT_MAX_SAMPLES: u32 = 1024;

/// The error target and the sample bounds of an adaptive render.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdaptiveSettings {
    /// Largest standard error of a pixel's mean, per linear RGB channel
    /// (0: no absolute target).
    pub target_error: f64,
    /// Largest standard error as a share of the mean of the pixel's
    /// brightest channel, e.g. 0.02 (0: no relative target).
    pub relative_error: f64,
    pub min_samples: u32,
    pub max_samples: u32,
}

/// When a pixel is converged: its standard error in every channel is at
/// most `max(absolute, relative * m)`, `m` the largest of its three
/// channel means. An absolute target alone is exposure-dependent (the
/// same noise is invisible on a bright wall and plain in a shadow); a
/// relative one alone would sample dark noisy pixels to the maximum, so
/// the absolute target, when given, is its floor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Target {
    pub absolute: f64,
    pub relative: f64,
}

impl Target {
    /// The largest variance of the mean allowed for a pixel whose
    /// brightest channel mean is `mean`.
    pub fn limit_sq(&self, mean: f64) -> f64 {
        let l = self.absolute.max(self.relative * mean);
        l * l
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AdaptiveError {
    #[error("target_error must be a finite number above 0, got {0}")]
    TargetError(f64),
    #[error("relative_error must be a finite number above 0, got {0}")]
    RelativeError(f64),
    #[error(
        "min_samples must be at least 2 (the error estimate needs two samples of a pixel), got {0}"
    )]
    MinTooSmall(u32),
    #[error("max_samples must be at most {MAX_SAMPLES}, got {0}")]
    MaxTooLarge(u32),
    #[error("min_samples ({min}) must not exceed max_samples ({max})")]
    MinAboveMax { min: u32, max: u32 },
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

impl AdaptiveSettings {
    pub fn validate(&self) -> Result<(), AdaptiveError> {
        // Each target is off (0) or a finite number above 0, and one is on.
        let ok = |v: f64| v >= 0.0 && v.is_finite();
        if !ok(self.target_error) || (self.target_error == 0.0 && self.relative_error == 0.0) {
            return Err(AdaptiveError::TargetError(self.target_error));
        }
        if !ok(self.relative_error) {
            return Err(AdaptiveError::RelativeError(self.relative_error));
        }
        if self.min_samples < 2 {
            return Err(AdaptiveError::MinTooSmall(self.min_samples));
        }
        if self.max_samples > MAX_SAMPLES {
            return Err(AdaptiveError::MaxTooLarge(self.max_samples));
        }
        if self.min_samples > self.max_samples {
            return Err(AdaptiveError::MinAboveMax {
                min: self.min_samples,
                max: self.max_samples,
            });
        }
        Ok(())
    }

    /// The target in words: "target error E", "relative error R", or both.
    pub fn describe_target(&self) -> String {
        let abs = (self.target_error > 0.0).then(|| format!("target error {}", self.target_error));
        let rel =
            (self.relative_error > 0.0).then(|| format!("relative error {}", self.relative_error));
        [abs, rel]
            .into_iter()
            .flatten()
            .collect::<Vec<_>>()
            .join(", ")
    }

    pub fn target(&self) -> Target {
        Target {
            absolute: self.target_error,
            relative: self.relative_error,
        }
    }

    /// The sample range of each round: `0..min`, then doubling up to `max`.
    pub fn rounds(&self) -> Vec<SampleRange> {
        let mut out = vec![SampleRange::new(0, self.min_samples)];
        let mut end = self.min_samples;
        while end < self.max_samples {
            let next = end.saturating_mul(2).min(self.max_samples);
            out.push(SampleRange::new(end, next));
            end = next;
        }
        out
    }

    /// The settings an adaptive render traces with: `samples` is the most a
    /// pixel can get, and samples are placed progressively (sample k is the
    /// same whatever the count).
    pub fn render_settings(&self, base: RenderSettings) -> RenderSettings {
        RenderSettings {
            samples: self.max_samples,
            sampler: Sampler::Progressive,
            ..base
        }
    }
}

/// The adaptive keys as given (scene file or command line), before defaults.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AdaptiveSpec {
    pub target_error: Option<f64>,
    pub relative_error: Option<f64>,
    pub min_samples: Option<u32>,
    pub max_samples: Option<u32>,
}

impl AdaptiveSpec {
    /// Checks each given value on its own terms (and min against max when
    /// both are given); `Err` names the key and what is wrong with it.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        let full = AdaptiveSettings {
            target_error: self.target_error.unwrap_or(1.0),
            relative_error: self.relative_error.unwrap_or(0.0),
            min_samples: self.min_samples.unwrap_or(2),
            max_samples: self.max_samples.unwrap_or(MAX_SAMPLES),
        };
        check_given_relative(self.relative_error)
            .and_then(|()| full.validate())
            .map_err(|e| {
                let key = match e {
                    AdaptiveError::TargetError(_) => "target_error",
                    AdaptiveError::RelativeError(_) => "relative_error",
                    AdaptiveError::MinTooSmall(_) | AdaptiveError::MinAboveMax { .. } => {
                        "min_samples"
                    }
                    _ => "max_samples",
                };
                let m = e.to_string();
                let what = m.split_once(' ').map_or(m.clone(), |(_, w)| w.to_string());
                (key, what)
            })
    }

    /// `over` (the command line) over `self` (the scene file), defaults
    /// for what neither gives. `None` without a target error, absolute or
    /// relative (a uniform render); then giving sample bounds on the
    /// command line is an error.
    pub fn resolve(&self, over: &AdaptiveSpec) -> Result<Option<AdaptiveSettings>, String> {
        let target_error = over.target_error.or(self.target_error);
        let relative_error = over.relative_error.or(self.relative_error);
        check_given_relative(relative_error).map_err(|e| e.to_string())?;
        if target_error.is_none() && relative_error.is_none() {
            if over.min_samples.is_some() || over.max_samples.is_some() {
                return Err(
                    "--min-samples and --max-samples apply to adaptive sampling: \
                            give --target-error or --relative-error (or [render] target_error or relative_error) too"
                        .into(),
                );
            }
            return Ok(None);
        }
        let min_samples = over
            .min_samples
            .or(self.min_samples)
            .unwrap_or(DEFAULT_MIN_SAMPLES);
        let a = AdaptiveSettings {
            target_error: target_error.unwrap_or(0.0),
            relative_error: relative_error.unwrap_or(0.0),
            min_samples,
            max_samples: over
                .max_samples
                .or(self.max_samples)
                .unwrap_or(DEFAULT_MAX_SAMPLES.max(min_samples)),
        };
        a.validate().map_err(|e| e.to_string())?;
        Ok(Some(a))
    }
}

/// A relative target, when given, must be on: in the settings 0 means
/// "none", but nobody asks for none by giving 0.
fn check_given_relative(r: Option<f64>) -> Result<(), AdaptiveError> {
    match r {
        Some(r) if !(r > 0.0 && r.is_finite()) => Err(AdaptiveError::RelativeError(r)),
        _ => Ok(()),
    }
}

/// Checks that `rect` starts on the block grid and ends on it or at the
/// image's edge, so its blocks are the image's blocks.
pub fn check_rect(rect: Rect, width: u32, height: u32) -> Result<(), AdaptiveError> {
    let edge_ok = |start: u32, len: u32, side: u32| {
        start.is_multiple_of(BLOCK) && ((start + len).is_multiple_of(BLOCK) || start + len == side)
    };
    if edge_ok(rect.x, rect.width, width) && edge_ok(rect.y, rect.height, height) {
        Ok(())
    } else {
        Err(AdaptiveError::Unaligned {
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
        let (bx, by) = ((x - self.rect.x) / BLOCK, (y - self.rect.y) / BLOCK);
        self.active[(by * self.cols() + bx) as usize]
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

    pub fn from_bytes(rect: Rect, bytes: &[u8]) -> Result<Self, AdaptiveError> {
        let n = blocks_of(rect);
        if bytes.len() != n.div_ceil(8) {
            return Err(AdaptiveError::MaskSize {
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

/// Estimated variance of the mean of one pixel, per channel, in radiance
/// squared: the sample variance over `n`. Computed from the exact integers
/// (`n * sum_sq - sum^2`, never negative by Cauchy-Schwarz, in u128), so
/// every machine gets the same value. Infinite below two samples.
pub fn variance_of_mean(n: u32, sums: &[u64; 3], squares: &[u128; 3]) -> [f64; 3] {
    if n < 2 {
        return [f64::INFINITY; 3];
    }
    let nf = n as f64;
    let scale = 1.0 / (nf * nf * (nf - 1.0) * FIXED_ONE * FIXED_ONE);
    std::array::from_fn(|c| {
        let s = sums[c] as u128;
        // Saturating: counts and squares from outside must not wrap.
        let num = (n as u128)
            .checked_mul(squares[c])
            .map_or(u128::MAX, |v| v.saturating_sub(s * s));
        num as f64 * scale
    })
}

/// The largest of a pixel's three standard errors (what the target bounds).
pub fn pixel_error(film: &Film, i: usize) -> f64 {
    let squares = film.squares.as_ref().expect("adaptive film");
    let v = variance_of_mean(film.counts[i], &film.sums[i], &squares[i]);
    v[0].max(v[1]).max(v[2]).sqrt()
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

/// Summarises `film` (which must cover `rect`, a block-aligned rect with
/// every pixel past round 0 or not started at all).
pub fn summarize(film: &Film, rect: Rect, a: &AdaptiveSettings) -> Summary {
    let mut out = Summary::default();
    let mask = BlockMask::none(rect);
    let mut sq_err = 0.0f64;
    let mut pixels = 0u64;
    for i in 0..mask.active.len() {
        let b = mask.block_rect(i);
        out.blocks += 1;
        let first = ((b.y - film.rect.y) * film.rect.width + (b.x - film.rect.x)) as usize;
        let n = film.counts[first];
        let area = b.area() as u64;
        out.samples_done += n as u64 * area;
        if n == 0 {
            out.samples_expected += a.min_samples as u64 * area;
            continue;
        }
        // The largest variance over its limit, over the block's pixels.
        let mut worst = 0.0f64;
        for y in b.y..b.y + b.height {
            for x in b.x..b.x + b.width {
                let j = ((y - film.rect.y) * film.rect.width + (x - film.rect.x)) as usize;
                let squares = film.squares.as_ref().expect("adaptive film");
                let v = variance_of_mean(film.counts[j], &film.sums[j], &squares[j]);
                let v = v.map(|v| if v.is_finite() { v } else { 0.0 });
                sq_err += v[0] + v[1] + v[2];
                pixels += 1;
                worst = worst.max(error_ratio(
                    film.counts[j],
                    &film.sums[j],
                    &squares[j],
                    a.target(),
                ));
            }
        }
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

/// Renders one round: the blocks of `mask` over the sample indices
/// `samples`, into a film of `mask.rect` with sums of squares (pixels of
/// inactive blocks stay at zero samples). `progress` gets pixel-samples.
pub fn render_round(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    frame: u32,
    mask: &BlockMask,
    samples: SampleRange,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Film, RendererError> {
    match renderer {
        Renderer::Cpu(r) => Ok(cpu::render_round(
            r, prepared, frame, mask, samples, progress,
        )?),
        #[cfg(feature = "gpu")]
        Renderer::Gpu(r) => Ok(r.render_round(prepared, frame, mask, samples, progress)?),
    }
}

/// A round's report to [`render`]'s caller.
#[derive(Clone, Copy, Debug)]
pub struct RoundReport {
    pub round: usize,
    pub samples: SampleRange,
    pub active_blocks: usize,
    pub seconds: f64,
    /// The whole image after this round.
    pub summary: Summary,
}

/// Renders a whole frame adaptively, round after round: what `tessera
/// render --target-error` does. `prepared` must have been built with
/// [`AdaptiveSettings::render_settings`]. `on_round` is told after each
/// round; `progress` gets pixel-samples as they finish.
pub fn render(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    frame: u32,
    a: &AdaptiveSettings,
    progress: &(dyn Fn(u64) + Sync),
    on_round: &mut dyn FnMut(&RoundReport),
) -> Result<Film, RendererError> {
    let s = prepared.settings();
    let rect = Rect::full(s.width, s.height);
    let mut film = Film::with_squares(rect);
    for (round, samples) in a.rounds().into_iter().enumerate() {
        let mask = next_active(&film, rect, samples, a.target());
        if mask.active_count() == 0 {
            break;
        }
        let start = std::time::Instant::now();
        let f = render_round(renderer, prepared, frame, &mask, samples, progress)?;
        film.merge(&f)
            .expect("a round's film lies inside the frame and sums cannot overflow");
        on_round(&RoundReport {
            round,
            samples,
            active_blocks: mask.active_count(),
            seconds: start.elapsed().as_secs_f64(),
            summary: summarize(&film, rect, a),
        });
    }
    Ok(film)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(min: u32, max: u32) -> AdaptiveSettings {
        AdaptiveSettings {
            target_error: 0.01,
            relative_error: 0.0,
            min_samples: min,
            max_samples: max,
        }
    }

    #[test]
    fn rounds_double_up_to_max() {
        let r = |min, max| {
            settings(min, max)
                .rounds()
                .iter()
                .map(|r| (r.start, r.end))
                .collect::<Vec<_>>()
        };
        assert_eq!(r(16, 128), vec![(0, 16), (16, 32), (32, 64), (64, 128)]);
        assert_eq!(r(4, 4), vec![(0, 4)]);
        assert_eq!(r(3, 20), vec![(0, 3), (3, 6), (6, 12), (12, 20)]);
    }

    #[test]
    fn bad_settings_are_named() {
        let mut s = settings(16, 1024);
        s.target_error = 0.0;
        assert_eq!(s.validate(), Err(AdaptiveError::TargetError(0.0)));
        s.target_error = f64::NAN;
        assert!(matches!(s.validate(), Err(AdaptiveError::TargetError(_))));
        assert_eq!(
            settings(1, 4).validate(),
            Err(AdaptiveError::MinTooSmall(1))
        );
        assert_eq!(
            settings(64, 32).validate(),
            Err(AdaptiveError::MinAboveMax { min: 64, max: 32 })
        );
        assert_eq!(
            settings(2, 70_000).validate(),
            Err(AdaptiveError::MaxTooLarge(70_000))
        );
        let e = settings(64, 32).validate().unwrap_err().to_string();
        assert_eq!(e, "min_samples (64) must not exceed max_samples (32)");
    }

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
            Err(AdaptiveError::MaskSize { .. })
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
