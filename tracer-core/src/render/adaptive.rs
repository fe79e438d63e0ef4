//! The adaptive driver: a render in rounds ([`render`]), each round
//! ([`render_round`]) the active blocks of a [`BlockMask`] over a range of
//! sample indices, on the CPU ([`super::cpu::adaptive`], over the ordinary
//! tile renderer and so the one shading step) or the GPU (its adaptive
//! kernel). The blocks, masks and the rule that picks them are
//! [`crate::adaptive`]'s.

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
