//! The adaptive driver: a render in rounds ([`render`]), each round
//! ([`render_round`]) the active blocks of a [`BlockMask`] over a range of
//! sample indices, on the CPU ([`super::cpu::adaptive`], over the ordinary
//! tile renderer and so the one shading step) or the GPU (its adaptive
//! kernel). On the GPU, [`render`] chains the rounds there, a kernel
//! deciding between them (`GpuRenderer::render_adaptive`). The blocks, masks and the rule that picks them are
//! [`crate::adaptive`]'s.

use crate::adaptive::optimal::{
    BlockStats, Costs, RmseSchedule, RmseSettings, RmseStep, block_stats, image_mean,
};
use crate::adaptive::{AdaptiveSettings, BlockMask, Summary, next_active, summarize};
use crate::film::{Film, Rect, SampleRange};
use crate::render::{PreparedFrame, Renderer, RendererError};

/// Renders one round: the blocks of `mask` over the sample indices
/// `samples`, into a film of `mask.rect` with sums of squares (pixels of
/// inactive blocks stay at zero samples), and on the CPU the runs of
/// blocks it rendered with their rays ([`Film::runs`]; the GPU reports
/// none, its blocks then all costing the same). `progress` gets
/// pixel-samples.
pub fn render_round(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    frame: u32,
    mask: &BlockMask,
    samples: SampleRange,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Film, RendererError> {
    match renderer {
        Renderer::Cpu(r) => Ok(super::cpu::adaptive::render_round(
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
    // The GPU decides between its rounds itself (render::gpu converge.rs):
    // no read-back of the film per round.
    #[cfg(feature = "gpu")]
    if let Renderer::Gpu(r) = renderer {
        let on_round = std::sync::Mutex::new(on_round);
        return Ok(r.render_adaptive(prepared, frame, a, progress, &|report| {
            if let Ok(mut f) = on_round.lock() {
                f(report)
            }
        })?);
    }
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

/// Takes each block `i` of `rect` (block-aligned) from `from[i]` to
/// `to[i]` samples in one renderer call (every block over its own range):
/// the film of `rect` with sums of squares, and on the CPU its runs
/// ([`Film::runs`]). A round of the error-optimal mode, locally or on a
/// farm's worker.
#[allow(clippy::too_many_arguments)]
pub fn render_ranges(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    frame: u32,
    rect: Rect,
    from: &[u32],
    to: &[u32],
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Film, RendererError> {
    match renderer {
        Renderer::Cpu(r) => Ok(super::cpu::adaptive::render_blocks(
            r, prepared, frame, rect, from, to, progress,
        )?),
        #[cfg(feature = "gpu")]
        Renderer::Gpu(r) => Ok(r.render_blocks(prepared, frame, rect, from, to, progress)?),
    }
}

/// [`render_ranges`] over the whole of `film`, added to it, its runs
/// booked in `costs`.
#[allow(clippy::too_many_arguments)]
pub fn render_blocks(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    frame: u32,
    from: &[u32],
    to: &[u32],
    film: &mut Film,
    costs: &mut Costs,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<(), RendererError> {
    let runs = match renderer {
        // Added to `film` in place: no second whole-frame film a round.
        Renderer::Cpu(r) => {
            super::cpu::adaptive::add_blocks(r, prepared, frame, from, to, film, progress)?
        }
        #[cfg(feature = "gpu")]
        Renderer::Gpu(r) => {
            let mut f = r.render_blocks(prepared, frame, film.rect, from, to, progress)?;
            film.merge(&f)
                .expect("the blocks' film lies inside the frame and sums cannot overflow");
            std::mem::take(&mut f.runs)
        }
    };
    costs.book_runs(film.rect, &runs);
    Ok(())
}

/// A round's report of the error-optimal mode.
#[derive(Clone, Copy, Debug)]
pub struct RmseRound {
    pub round: usize,
    pub active_blocks: usize,
    pub seconds: f64,
    /// Pixel-samples so far.
    pub pixel_samples: u64,
    /// The image's estimated RMSE after this round, and the target.
    pub estimated_rmse: f64,
    pub target_rmse: f64,
    /// Pixel-samples the render is expected to take in all
    /// (`RmseStep::expected_pixel_samples`).
    pub expected_pixel_samples: u64,
}

/// The error-optimal mode's rounds as its local drivers (CPU and GPU) run
/// them: the decisions of an [`RmseSchedule`], each round timed and
/// reported.
pub struct RmseRounds<'a> {
    schedule: RmseSchedule,
    started: std::time::Instant,
    // Shared, not `FnMut`, so that the GPU's driver can hold these rounds
    // for a shorter borrow than their own.
    on_round: &'a dyn Fn(&RmseRound),
}

impl<'a> RmseRounds<'a> {
    pub fn new(
        settings: &'a RmseSettings,
        blocks: usize,
        on_round: &'a dyn Fn(&RmseRound),
    ) -> Self {
        RmseRounds {
            schedule: RmseSchedule::new(*settings, blocks),
            started: std::time::Instant::now(),
            on_round,
        }
    }

    /// The next round, block `i` from `from[i]` to `to[i]` samples; `None`
    /// once the render is done.
    pub fn pending(&self) -> Option<(&[u32], &[u32])> {
        self.schedule.pending()
    }

    /// [`RmseRounds::pending`] as each block's (from, to).
    pub fn pending_ranges(&self) -> Option<Vec<[u32; 2]>> {
        self.pending()
            .map(|(from, to)| from.iter().zip(to).map(|(&a, &b)| [a, b]).collect())
    }

    pub fn settings(&self) -> &RmseSettings {
        self.schedule.settings()
    }

    /// After the pending round: the blocks' statistics (at their new
    /// counts) and the image's mean decide the next one, and the round is
    /// reported.
    pub fn after_round(&mut self, stats: &[BlockStats], image_mean: f64) {
        let step = self.schedule.after_round(stats, image_mean);
        self.report(&step);
    }

    /// Reports a round decided elsewhere (on the GPU: allocate.wgsl), timed
    /// from the last report.
    pub fn report(&mut self, step: &RmseStep) {
        let now = std::time::Instant::now();
        (self.on_round)(&RmseRound {
            round: step.round as usize,
            active_blocks: step.active_blocks,
            seconds: (now - self.started).as_secs_f64(),
            pixel_samples: step.pixel_samples,
            estimated_rmse: step.estimated_rmse,
            target_rmse: step.target_rmse,
            expected_pixel_samples: step.expected_pixel_samples,
        });
        self.started = now;
    }
}

/// Renders a whole frame in the error-optimal mode (see
/// [`crate::adaptive::optimal`] and [`RmseRounds`]). On the GPU the
/// film stays there between rounds, and only each block's statistics come
/// back (`GpuRenderer::render_rmse`).
/// `prepared` must have been built with [`RmseSettings::render_settings`].
pub fn render_rmse(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    frame: u32,
    o: &RmseSettings,
    progress: &(dyn Fn(u64) + Sync),
    on_round: &mut dyn FnMut(&RmseRound),
) -> Result<Film, RendererError> {
    let s = prepared.settings();
    let rect = Rect::full(s.width, s.height);
    let mut costs = Costs::new(rect);
    let on_round = std::sync::Mutex::new(on_round);
    let report = |r: &RmseRound| {
        if let Ok(mut f) = on_round.lock() {
            f(r)
        }
    };
    let rounds = RmseRounds::new(o, costs.rays.len(), &report);
    #[cfg(feature = "gpu")]
    if let Renderer::Gpu(r) = renderer {
        return Ok(r.render_rmse(prepared, frame, rounds, progress)?);
    }
    let mut rounds = rounds;
    let mut film = Film::with_squares(rect);
    while let Some((from, to)) = rounds.pending() {
        let (from, to) = (from.to_vec(), to.to_vec());
        render_blocks(
            renderer, prepared, frame, &from, &to, &mut film, &mut costs, progress,
        )?;
        // The statistics on the renderer's threads (they are idle between
        // rounds), not on a pool of every core.
        let (stats, mean) =
            renderer.install(|| (block_stats(&film, rect, Some(&costs)), image_mean(&film)));
        rounds.after_round(&stats, mean);
    }
    Ok(film)
}
