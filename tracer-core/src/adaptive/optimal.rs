//! The error-optimal mode (issue 36): a target for the image's RMSE, not
//! for each pixel. Minimising the image's MSE, `sum_b A_b w_b / n_b`, for a
//! given cost `sum_b A_b n_b c_b` gives each block `n_b` proportional to
//! `sqrt(w_b / c_b)` (Lagrange), `w_b` the block's variance of one sample
//! (mean over its pixels and channels) and `c_b` the cost of one of its
//! pixel-samples. The per-pixel contract (`--target-error`) instead
//! equalises each pixel's error, which spends most where the noise is
//! worst even when that noise is also the dearest to remove.
//!
//! Here the statistics ([`BlockStats`], [`estimated_mse`]) and the
//! allocation ([`allocate`]), pure functions of a film and measured costs,
//! so the oracle of `tessera bench adaptive` (the same allocation from a
//! converged film) and the driver (`render::adaptive::render_rmse`) share
//! them.

use super::{AdaptiveSettings, BLOCK, BlockMask};
use crate::film::{FIXED_ONE, Film, Rect, RunCost, variance_of_mean};
use crate::sampling::Sampler;
use crate::scene::RenderSettings;
use crate::scene::adaptive::AdaptiveError;

/// The error-optimal mode's target and sample bounds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RmseSettings {
    /// Estimated RMSE of the image (over pixels and linear RGB channels)
    /// to stop at; 0: none.
    pub target_rmse: f64,
    /// The same as a share of the image's mean (over pixels and
    /// channels), e.g. 0.02; 0: none. With both, the larger applies.
    pub relative_rmse: f64,
    pub min_samples: u32,
    pub max_samples: u32,
}

impl From<&AdaptiveSettings> for RmseSettings {
    /// The image mode's reading of adaptive settings: the targets are the
    /// image's.
    fn from(a: &AdaptiveSettings) -> Self {
        RmseSettings {
            target_rmse: a.target_error,
            relative_rmse: a.relative_error,
            min_samples: a.min_samples,
            max_samples: a.max_samples,
        }
    }
}

impl RmseSettings {
    /// Most rounds a render takes, round 0 included: twice the steps of
    /// the grid from `min` to `max` ([`RmseSettings::step`]), and one.
    /// Each round after the first takes some block at least one step up,
    /// so a render whose allocation settles stops far sooner; the bound
    /// makes the number of rounds (the farm's units of a frame) finite
    /// whatever the estimates do, and local and farm renders stop alike.
    pub fn max_rounds(&self) -> u32 {
        let ratio = self.max_samples.max(1) as f64 / self.min_samples.max(1) as f64;
        let steps = (4.0 * ratio.log2()).ceil().max(0.0) as u32;
        2 * (steps + 1) + 1
    }

    pub fn validate(&self) -> Result<(), AdaptiveError> {
        super::AdaptiveSettings {
            target_error: self.target_rmse,
            relative_error: self.relative_rmse,
            min_samples: self.min_samples,
            max_samples: self.max_samples,
            mode: super::AdaptiveMode::Image,
        }
        .validate()
    }

    /// The target MSE for an image whose mean is `mean`.
    pub fn target_mse(&self, mean: f64) -> f64 {
        let t = self.target_rmse.max(self.relative_rmse * mean);
        t * t
    }

    /// The settings the render traces with (as
    /// [`super::AdaptiveSettings::render_settings`]).
    pub fn render_settings(&self, base: RenderSettings) -> RenderSettings {
        RenderSettings {
            samples: self.max_samples,
            sampler: Sampler::Progressive,
            ..base
        }
    }

    /// The count a block at `n` samples goes to next when the allocation
    /// wants `want`: at most double (so the estimates it rests on are
    /// renewed before they are trusted further), rounded up to the grid
    /// `min * 2^(k/4)` (so a round has few distinct sample ranges and
    /// neighbouring blocks share runs of the renderer), at most
    /// `max_samples`.
    pub fn step(&self, n: u32, want: u32) -> u32 {
        if want <= n || n >= self.max_samples {
            return n;
        }
        let goal = want.min(n.saturating_mul(2)).min(self.max_samples);
        let mut k = 0;
        loop {
            let g = (self.min_samples as f64 * 2f64.powf(k as f64 / 4.0)).ceil() as u32;
            if g >= goal {
                return g.min(self.max_samples).max(n + 1);
            }
            k += 1;
        }
    }
}

/// The mean of an image (over pixels with samples and channels), linear.
/// Summed in parallel over fixed chunks, then the chunks in order: the
/// same bits whatever the threads, as the farm's coordinator and a local
/// render must decide alike.
pub fn image_mean(film: &Film) -> f64 {
    use rayon::prelude::*;
    const CHUNK: usize = 4096;
    let (sum, pixels) = film
        .sums
        .par_chunks(CHUNK)
        .zip(film.counts.par_chunks(CHUNK))
        .map(|(sums, counts)| {
            let mut sum = 0.0;
            let mut pixels = 0usize;
            for (s, &n) in sums.iter().zip(counts) {
                if n > 0 {
                    sum += (s[0] + s[1] + s[2]) as f64 / (n as f64 * FIXED_ONE);
                    pixels += 1;
                }
            }
            (sum, pixels)
        })
        .collect::<Vec<_>>()
        .into_iter()
        .fold((0.0, 0), |(s, p), (cs, cp)| (s + cs, p + cp));
    sum / (3 * pixels.max(1)) as f64
}

/// One block's statistics.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BlockStats {
    pub rect: Rect,
    /// Samples each of its pixels has.
    pub n: u32,
    /// Variance of one sample, mean over its pixels and three channels.
    pub w: f64,
    /// Cost of one pixel-sample (rays, or 1 where unmeasured).
    pub cost: f64,
}

/// Per-block cost bookkeeping: work done (rays) and pixel-samples, summed
/// over the rounds, so a block's cost is its measured mean.
#[derive(Clone, Debug)]
pub struct Costs {
    pub rays: Vec<f64>,
    pub pixel_samples: Vec<f64>,
}

impl Costs {
    pub fn new(rect: Rect) -> Self {
        let n = BlockMask::none(rect).active.len();
        Costs {
            rays: vec![0.0; n],
            pixel_samples: vec![0.0; n],
        }
    }

    /// Books `rays` traced for `pixel_samples` over `run` (a rect of whole
    /// blocks in one row, as the CPU renders them), shared among its blocks
    /// by area.
    pub fn book(&mut self, frame: Rect, run: Rect, rays: u64, samples_per_pixel: u32) {
        let cols = frame.width.div_ceil(BLOCK);
        let by = (run.y - frame.y) / BLOCK;
        let mut x = run.x;
        while x < run.x + run.width {
            let bx = (x - frame.x) / BLOCK;
            let w = BLOCK.min(run.x + run.width - x);
            let share = (w * run.height) as f64 / run.area() as f64;
            let i = (by * cols + bx) as usize;
            self.rays[i] += rays as f64 * share;
            self.pixel_samples[i] += (w * run.height) as f64 * samples_per_pixel as f64;
            x += w;
        }
    }

    /// Books a film's runs ([`Film::runs`]) over the blocks of `frame`.
    pub fn book_runs(&mut self, frame: Rect, runs: &[RunCost]) {
        for r in runs {
            self.book(frame, r.rect, r.rays, r.samples);
        }
    }

    /// Each block's cost of one pixel-sample: its measured mean, or where
    /// nothing was measured for it (a block of a worker that sends no
    /// runs) the mean over the blocks that were; 1 where none was.
    /// allocate.wgsl computes the same on the GPU.
    pub fn per_block(&self) -> Vec<f64> {
        let measured = |i: usize| self.pixel_samples[i] > 0.0 && self.rays[i] > 0.0;
        let (mut rays, mut samples) = (0.0, 0.0);
        for i in (0..self.rays.len()).filter(|&i| measured(i)) {
            rays += self.rays[i];
            samples += self.pixel_samples[i];
        }
        let fallback = if samples > 0.0 { rays / samples } else { 1.0 };
        (0..self.rays.len())
            .map(|i| {
                if measured(i) {
                    self.rays[i] / self.pixel_samples[i]
                } else {
                    fallback
                }
            })
            .collect()
    }
}

/// The statistics of each block of `rect` (block-aligned, inside
/// `film.rect`, every block's pixels at one count), costs from `costs`
/// (`None`: every block costs 1).
pub fn block_stats(film: &Film, rect: Rect, costs: Option<&Costs>) -> Vec<BlockStats> {
    use rayon::prelude::*;
    let squares = film.squares.as_ref().expect("adaptive film");
    let mask = BlockMask::none(rect);
    let costs = costs.map(Costs::per_block);
    // Each block on its own, so in parallel (a whole frame's pixels
    // between two rounds, while the renderer's threads wait).
    (0..mask.active.len())
        .into_par_iter()
        .map(|i| {
            let b = mask.block_rect(i);
            let mut sum = 0.0;
            let mut n = 0;
            for y in b.y..b.y + b.height {
                for x in b.x..b.x + b.width {
                    let j = ((y - film.rect.y) * film.rect.width + (x - film.rect.x)) as usize;
                    n = film.counts[j];
                    let v = variance_of_mean(n, &film.sums[j], &squares[j]);
                    for v in v {
                        sum += if v.is_finite() { v * n as f64 } else { 0.0 };
                    }
                }
            }
            BlockStats {
                rect: b,
                n,
                w: sum / (3 * b.area()) as f64,
                cost: costs.as_ref().map_or(1.0, |c| c[i]),
            }
        })
        .collect()
}

/// The image's estimated MSE (mean over pixels and channels of each
/// pixel's variance of the mean), were block `b` at `n[b]` samples.
pub fn mse_at(stats: &[BlockStats], n: &[u32]) -> f64 {
    let pixels: usize = stats.iter().map(|s| s.rect.area()).sum();
    let sum: f64 = stats
        .iter()
        .zip(n)
        .map(|(s, &n)| s.rect.area() as f64 * s.w / n.max(1) as f64)
        .sum();
    sum / pixels.max(1) as f64
}

/// The image's estimated MSE at the blocks' current counts.
pub fn estimated_mse(stats: &[BlockStats]) -> f64 {
    let n: Vec<u32> = stats.iter().map(|s| s.n).collect();
    mse_at(stats, &n)
}

/// The cheapest counts (each at least `lo[b]`, at most `max`) whose
/// estimated MSE is at most `target_mse`: `n_b = clamp(lambda *
/// sqrt(w_b / c_b))`, `lambda` found by bisection. Every block at `max`
/// when even that misses the target.
pub fn allocate(stats: &[BlockStats], lo: &[u32], target_mse: f64, max: u32) -> Vec<u32> {
    let at = |lambda: f64| -> Vec<u32> {
        stats
            .iter()
            .zip(lo)
            .map(|(s, &lo)| {
                let want = lambda * (s.w / s.cost.max(1e-12)).sqrt();
                (want.ceil().min(max as f64) as u32)
                    .max(lo)
                    .min(max.max(lo))
            })
            .collect()
    };
    let (mut a, mut b) = (0.0f64, 1.0f64);
    // Grow the bracket until the target is met or every block is at max.
    while mse_at(stats, &at(b)) > target_mse {
        if b > 1e30 {
            return at(b);
        }
        b *= 4.0;
    }
    for _ in 0..64 {
        let m = 0.5 * (a + b);
        if mse_at(stats, &at(m)) > target_mse {
            a = m;
        } else {
            b = m;
        }
    }
    at(b)
}

/// The error-optimal mode's rounds as decisions alone, one for the local
/// drivers (`render::adaptive::render_rmse`, CPU and GPU) and the farm's
/// coordinator: `min_samples` everywhere first; after each round, from the
/// blocks' statistics and the image's mean, either the end (the estimated
/// image RMSE is at most the target, no block may grow, or
/// [`RmseSettings::max_rounds`] were taken) or each block's next count,
/// towards its share of the cheapest allocation meeting the target.
#[derive(Clone, Debug, PartialEq)]
pub struct RmseSchedule {
    settings: RmseSettings,
    /// Each block's samples so far, and after the pending round.
    n: Vec<u32>,
    next: Vec<u32>,
    /// The pending round's index.
    round: u32,
}

/// What a round of [`RmseSchedule`] ended with.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RmseStep {
    pub round: u32,
    /// Blocks the round sampled.
    pub active_blocks: usize,
    /// Pixel-samples of the image after the round.
    pub pixel_samples: u64,
    /// The image's estimated RMSE after the round, and the target.
    pub estimated_rmse: f64,
    pub target_rmse: f64,
    /// Pixel-samples the render is expected to take in all: the cheapest
    /// allocation meeting the target from this round's statistics (what
    /// progress and its ETA are measured against), or `pixel_samples`
    /// once the render ends.
    pub expected_pixel_samples: u64,
}

impl RmseSchedule {
    pub fn new(settings: RmseSettings, blocks: usize) -> Self {
        RmseSchedule {
            settings,
            n: vec![0; blocks],
            next: vec![settings.min_samples; blocks],
            round: 0,
        }
    }

    pub fn settings(&self) -> &RmseSettings {
        &self.settings
    }

    /// The pending round's index (the rounds taken so far).
    pub fn round(&self) -> u32 {
        self.round
    }

    /// The next round, block `i` from `from[i]` to `to[i]` samples; `None`
    /// once the render is done.
    pub fn pending(&self) -> Option<(&[u32], &[u32])> {
        self.n
            .iter()
            .zip(&self.next)
            .any(|(a, b)| b > a)
            .then_some((&self.n, &self.next))
    }

    /// Block `i`'s samples so far and after the pending round.
    pub fn block(&self, i: usize) -> (u32, u32) {
        (self.n[i], self.next[i])
    }

    /// After the pending round: the blocks' statistics (at their new
    /// counts) and the image's mean decide the next one.
    pub fn after_round(&mut self, stats: &[BlockStats], image_mean: f64) -> RmseStep {
        let active_blocks = self.n.iter().zip(&self.next).filter(|(a, b)| b > a).count();
        self.n.clone_from(&self.next);
        let o = self.settings;
        let mse = estimated_mse(stats);
        let target = o.target_mse(image_mean);
        let pixel_samples = |n: &[u32]| -> u64 {
            stats
                .iter()
                .zip(n)
                .map(|(s, &n)| s.rect.area() as u64 * n as u64)
                .sum()
        };
        let mut step = RmseStep {
            round: self.round,
            active_blocks,
            pixel_samples: pixel_samples(&self.n),
            estimated_rmse: mse.sqrt(),
            target_rmse: target.sqrt(),
            expected_pixel_samples: pixel_samples(&self.n),
        };
        self.round += 1;
        if mse > target && self.round < o.max_rounds() {
            // Aim a little below the target: a round that lands just above
            // it would cost a whole further round for a few samples.
            let want = allocate(stats, &self.n, 0.9 * target, o.max_samples);
            self.next = self
                .n
                .iter()
                .zip(&want)
                .map(|(&n, &w)| o.step(n, w))
                .collect();
            // The steps round each count up to the grid: at least the
            // next round's.
            step.expected_pixel_samples = pixel_samples(&want).max(pixel_samples(&self.next));
        }
        step
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Costs booked by runs (shared by area), and blocks nothing measured
    /// (a GPU worker's beside CPU workers' on a farm) at the mean of the
    /// measured ones; all 1 when none was.
    #[test]
    fn blocks_cost_their_runs_share_and_unmeasured_ones_the_mean() {
        let frame = Rect::full(32, 8);
        let mut c = Costs::new(frame);
        assert_eq!(c.per_block(), vec![1.0; 4]);
        // Blocks 0 and 1 in one run: 1280 rays for 2 x 64 pixels x 2 samples.
        c.book_runs(
            frame,
            &[RunCost {
                rect: Rect::new(0, 0, 16, 8),
                rays: 1280,
                samples: 2,
            }],
        );
        // Block 3 alone: 64 pixels x 1 sample, 256 rays.
        c.book(frame, Rect::new(24, 0, 8, 8), 256, 1);
        // Measured: 5, 5 and 4 rays a pixel-sample; block 2 the mean,
        // (1280 + 256) / (256 + 64).
        assert_eq!(c.per_block(), vec![5.0, 5.0, 1536.0 / 320.0, 4.0]);
    }

    fn stats(w: &[f64], cost: &[f64]) -> Vec<BlockStats> {
        w.iter()
            .zip(cost)
            .enumerate()
            .map(|(i, (&w, &cost))| BlockStats {
                rect: Rect::new(8 * i as u32, 0, 8, 8),
                n: 4,
                w,
                cost,
            })
            .collect()
    }

    #[test]
    fn samples_go_as_sigma_over_root_cost_and_meet_the_target() {
        // Variances 1 and 4 at equal cost: sigma 1 and 2, so n 1:2.
        let s = stats(&[1.0, 4.0], &[1.0, 1.0]);
        let n = allocate(&s, &[1, 1], 0.01, 1 << 20);
        assert!(mse_at(&s, &n) <= 0.01);
        let r = n[1] as f64 / n[0] as f64;
        assert!((r - 2.0).abs() < 0.02, "{n:?}");
        // The same variances, the noisy block 4x dearer: n 1:1.
        let s = stats(&[1.0, 4.0], &[1.0, 4.0]);
        let n = allocate(&s, &[1, 1], 0.01, 1 << 20);
        assert!((n[1] as f64 / n[0] as f64 - 1.0).abs() < 0.02, "{n:?}");
        // Lower bounds hold, and the cap where the target is out of reach.
        let n = allocate(&s, &[50, 1], 1e-9, 64);
        assert_eq!(n, vec![64, 64]);
        let n = allocate(&s, &[500, 1], 0.5, 64);
        assert_eq!(n[0], 500);
    }
}
