//! The adaptive driver: a render in rounds ([`render`]), each round
//! ([`render_round`]) the active blocks of a [`BlockMask`] over a range of
//! sample indices, on the CPU ([`super::cpu::adaptive`], over the ordinary
//! tile renderer and so the one shading step) or the GPU (its adaptive
//! kernel). On the GPU, [`render`] chains the rounds there, a kernel
//! deciding between them (`GpuRenderer::render_adaptive`). The blocks, masks and the rule that picks them are
//! [`crate::adaptive`]'s.

use crate::adaptive::optimal::{
    BlockStats, Costs, RmseSettings, allocate, block_stats, estimated_mse, image_mean,
};
use crate::adaptive::{AdaptiveSettings, BlockMask, Summary, next_active, summarize};
use crate::film::{Film, Rect, SampleRange};
use crate::render::{PreparedFrame, Renderer, RendererError};

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
    render_round_costed(renderer, prepared, frame, mask, samples, progress).map(|(film, _)| film)
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

/// [`render_round`], also returning the runs of blocks rendered with the
/// rays each traced (the CPU's; none from the GPU, whose blocks then all
/// cost the same).
pub fn render_round_costed(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    frame: u32,
    mask: &BlockMask,
    samples: SampleRange,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<(Film, Vec<(Rect, u64)>), RendererError> {
    match renderer {
        Renderer::Cpu(r) => Ok(super::cpu::adaptive::render_round_costed(
            r, prepared, frame, mask, samples, progress,
        )?),
        #[cfg(feature = "gpu")]
        Renderer::Gpu(r) => Ok((
            r.render_round(prepared, frame, mask, samples, progress)?,
            vec![],
        )),
    }
}

/// Takes each block `i` of the frame from `from[i]` to `to[i]` samples
/// in one renderer call (every block over its own range), adding to
/// `film` and booking the CPU's costs in `costs`.
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
    let rect = film.rect;
    // Every block over its own range in one call (the GPU reports no
    // per-block cost).
    let (f, runs) = match renderer {
        Renderer::Cpu(r) => super::cpu::adaptive::render_blocks_costed(
            r, prepared, frame, rect, from, to, progress,
        )?,
        #[cfg(feature = "gpu")]
        Renderer::Gpu(r) => (
            r.render_blocks(prepared, frame, rect, from, to, progress)?,
            vec![],
        ),
    };
    film.merge(&f)
        .expect("the blocks' film lies inside the frame and sums cannot overflow");
    for (run, rays, samples) in runs {
        costs.book(rect, run, rays, samples);
    }
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
}

/// The error-optimal mode's decisions, one for its CPU and GPU drivers:
/// `min_samples` everywhere first; after each round, from the blocks'
/// statistics, the round's report and either the end (the estimated image
/// RMSE is at most the target, or no block may grow) or each block's next
/// count, towards its share of the cheapest allocation meeting the
/// target.
pub struct RmseRounds<'a> {
    settings: &'a RmseSettings,
    /// Each block's samples so far, and after the next round.
    n: Vec<u32>,
    next: Vec<u32>,
    round: usize,
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
            settings,
            n: vec![0; blocks],
            next: vec![settings.min_samples; blocks],
            round: 0,
            started: std::time::Instant::now(),
            on_round,
        }
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

    /// [`RmseRounds::pending`] as each block's (from, to).
    pub fn pending_ranges(&self) -> Option<Vec<[u32; 2]>> {
        self.pending()
            .map(|(from, to)| from.iter().zip(to).map(|(&a, &b)| [a, b]).collect())
    }

    /// After the pending round: the blocks' statistics (at their new
    /// counts) and the image's mean decide the next one, and the round is
    /// reported.
    pub fn after_round(&mut self, stats: &[BlockStats], image_mean: f64) {
        let active_blocks = self.n.iter().zip(&self.next).filter(|(a, b)| b > a).count();
        self.n.clone_from(&self.next);
        let o = self.settings;
        let mse = estimated_mse(stats);
        let target = o.target_mse(image_mean);
        let now = std::time::Instant::now();
        (self.on_round)(&RmseRound {
            round: self.round,
            active_blocks,
            seconds: (now - self.started).as_secs_f64(),
            pixel_samples: stats
                .iter()
                .map(|s| s.rect.area() as u64 * s.n as u64)
                .sum(),
            estimated_rmse: mse.sqrt(),
            target_rmse: target.sqrt(),
        });
        self.started = now;
        self.round += 1;
        if mse > target {
            // Aim a little below the target: a round that lands just above
            // it would cost a whole further round for a few samples.
            let want = allocate(stats, &self.n, 0.9 * target, o.max_samples);
            self.next = self
                .n
                .iter()
                .zip(&want)
                .map(|(&n, &w)| o.step(n, w))
                .collect();
        }
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
        let measured = costs.rays.iter().any(|&r| r > 0.0);
        let stats = block_stats(&film, rect, measured.then_some(&costs));
        rounds.after_round(&stats, image_mean(&film));
    }
    Ok(film)
}
