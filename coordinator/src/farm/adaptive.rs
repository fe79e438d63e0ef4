//! Adaptive jobs on the farm (issue 17, docs/adaptive-sampling.md).
//!
//! An adaptive job's units are (frame, tile, round): the layout's sample
//! batches are the rounds (`0..min`, then doubling up to `max`). A tile's
//! round r is pending only once its round r-1 is merged into the frame's
//! film; its active blocks are then a pure function of that film
//! (`tracer_core::adaptive::next_active`), computed again when it is
//! leased and carried by the lease. A tile whose next round has no active
//! block has its remaining rounds marked done without work. Every decision
//! is the one `tessera render --target-error` makes for the same blocks, so
//! the farm's image is the local one bit for bit (CPU workers).
//!
//! Nothing here is stored: the rounds' films are stored as any unit's
//! (with their sums of squares), and after a restart the pending rounds
//! and skipped units are derived again from the merged films.

use std::collections::HashMap;

use tracer_core::adaptive::{AdaptiveSettings, BlockMask, Summary, next_active, summarize};
use tracer_core::film::{FIXED_ONE, Film, MAX_SAMPLE_VALUE, Rect};

use super::{Job, Lease};
use crate::units::Unit;

/// An adaptive job's settings and where its tiles stand.
pub(super) struct AdaptiveJob {
    pub settings: AdaptiveSettings,
    /// Summary of each tile that has merged a round, by (frame, tile).
    tiles: HashMap<(u32, u32), Summary>,
}

/// The whole job's standing, for progress logs and `watch`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AdaptiveProgress {
    pub settings: Option<AdaptiveSettings>,
    /// Share of blocks (all frames) whose pixels reached the target.
    pub converged_share: f64,
    /// RMS over the started pixels of the estimated standard error.
    pub estimated_error: f64,
    /// Pixel-samples traced and expected in all (unstarted tiles count
    /// `min_samples` a pixel).
    pub samples_done: u64,
    pub samples_expected: u64,
}

impl AdaptiveJob {
    pub fn new(settings: AdaptiveSettings) -> Self {
        AdaptiveJob {
            settings,
            tiles: HashMap::new(),
        }
    }
}

impl Job {
    /// A fresh adaptive job: only round 0 of every tile is pending.
    pub(super) fn adaptive_start(&mut self) {
        if self.adaptive.is_some() {
            let layout = &self.layout;
            self.pending.retain(|&u| layout.unit(u).batch == 0);
        }
    }

    /// After a round of `tile` in `frame` was merged (or after a restart):
    /// the tile's first unfinished round becomes pending if it has active
    /// blocks; otherwise it and every later round are done without work.
    /// Returns whether a unit became pending.
    pub(super) fn adaptive_advance(&mut self, frame: u32, tile: u32) -> bool {
        let Some(a) = &self.adaptive else {
            return false;
        };
        let settings = a.settings;
        let rect = self.layout.tiles[tile as usize];
        let Some(frame_film) = self.frames.get(&frame).map(|f| f.film.clone()) else {
            return false;
        };
        let guard = frame_film.lock().expect("frame film lock");
        let Some(film) = guard.as_ref() else {
            return false; // nothing merged yet: round 0 is pending already
        };
        let summary = summarize(film, rect, &settings);
        let units: Vec<u32> = (0..self.layout.batches.len() as u32)
            .map(|batch| self.layout.index(Unit { frame, tile, batch }))
            .collect();
        let Some(next) = units.iter().position(|&u| !self.done[u as usize]) else {
            drop(guard);
            self.adaptive
                .as_mut()
                .expect("adaptive")
                .tiles
                .insert((frame, tile), summary);
            return false;
        };
        let mask = next_active(film, rect, self.layout.batches[next], settings.target());
        drop(guard);
        self.adaptive
            .as_mut()
            .expect("adaptive")
            .tiles
            .insert((frame, tile), summary);
        if next == 0 || mask.active_count() > 0 {
            return self.pending.insert(units[next]);
        }
        for &u in &units[next..] {
            self.mark_done(u);
            // No samples were traced for a skipped round.
            let unit = self.layout.unit(u);
            self.correct_samples(unit.frame, self.layout.unit_samples(unit), 0);
        }
        false
    }

    /// After a restart: every tile of every unwritten frame takes up where
    /// its merged rounds left it.
    pub(super) fn adaptive_restore(&mut self) {
        if self.adaptive.is_none() {
            return;
        }
        self.adaptive_start();
        let frames: Vec<u32> = self
            .frames
            .iter()
            .filter(|(_, f)| f.written.is_none())
            .map(|(&f, _)| f)
            .collect();
        for frame in frames {
            for tile in 0..self.layout.tiles.len() as u32 {
                self.adaptive_advance(frame, tile);
            }
        }
    }

    /// The active blocks of a lease of `rect` in `frame` at round `batch`
    /// (`None` for uniform jobs).
    pub(super) fn adaptive_mask(&self, frame: u32, rect: Rect, batch: u32) -> Option<BlockMask> {
        let a = self.adaptive.as_ref()?;
        let round = self.layout.batches[batch as usize];
        let frame_film = self.frames.get(&frame).map(|f| f.film.clone());
        let guard = frame_film
            .as_ref()
            .map(|f| f.lock().expect("frame film lock"));
        Some(match guard.as_ref().and_then(|g| g.as_ref()) {
            Some(film) => next_active(film, rect, round, a.settings.target()),
            None => BlockMask::all(rect),
        })
    }

    /// Pixel-samples a finished unit really traced, for an adaptive unit
    /// whose blocks were not all active (`None`: the unit's nominal count).
    pub(super) fn adaptive_samples(&self, film: &Film, tile: Rect) -> Option<u64> {
        self.adaptive.as_ref()?;
        let mut n = 0u64;
        for y in tile.y..tile.y + tile.height {
            let row = ((y - film.rect.y) * film.rect.width + (tile.x - film.rect.x)) as usize;
            n += film.counts[row..row + tile.width as usize]
                .iter()
                .map(|&c| c as u64)
                .sum::<u64>();
        }
        Some(n)
    }

    /// Pixel-samples expected of `frame`'s tile `t` (an unstarted tile
    /// counts `min_samples` a pixel).
    fn tile_expected(a: &AdaptiveJob, frame: u32, t: usize, rect: &Rect) -> u64 {
        match a.tiles.get(&(frame, t as u32)) {
            Some(s) => s.samples_expected,
            None => a.settings.min_samples as u64 * rect.area() as u64,
        }
    }

    /// Pixel-samples expected of `frame` in all (0 for a uniform job).
    pub(super) fn adaptive_frame_expected(&self, frame: u32) -> u64 {
        let Some(a) = &self.adaptive else { return 0 };
        (self.layout.tiles.iter().enumerate())
            .map(|(t, rect)| Self::tile_expected(a, frame, t, rect))
            .sum()
    }

    /// The job's adaptive standing (default for uniform jobs).
    pub(super) fn adaptive_progress(&self) -> AdaptiveProgress {
        let Some(a) = &self.adaptive else {
            return AdaptiveProgress::default();
        };
        let mut out = AdaptiveProgress {
            settings: Some(a.settings),
            ..Default::default()
        };
        let (mut blocks, mut converged, mut sq, mut pixels) = (0u64, 0u64, 0.0f64, 0u64);
        for f in self.frames.keys() {
            out.samples_expected += self.adaptive_frame_expected(*f);
            for (t, rect) in self.layout.tiles.iter().enumerate() {
                match a.tiles.get(&(*f, t as u32)) {
                    Some(s) => {
                        blocks += s.blocks;
                        converged += s.converged_blocks;
                        out.samples_done += s.samples_done;
                        sq += s.rms_error * s.rms_error * rect.area() as f64;
                        pixels += rect.area() as u64;
                    }
                    None => {
                        let b = BlockMask::all(*rect).active.len() as u64;
                        blocks += b;
                    }
                }
            }
        }
        out.converged_share = if blocks == 0 {
            0.0
        } else {
            converged as f64 / blocks as f64
        };
        out.estimated_error = if pixels == 0 {
            0.0
        } else {
            (sq / pixels as f64).sqrt()
        };
        out
    }
}

/// The checks of an adaptive result beyond a uniform one's: sums of
/// squares present exactly when the lease is adaptive, none where a pixel
/// has no samples, and each within what `n` samples can reach.
pub(super) fn check_result(lease: &Lease, film: &Film) -> Result<(), String> {
    let (Some(mask), Some(squares)) = (&lease.active, &film.squares) else {
        return match (&lease.active, &film.squares) {
            (Some(_), None) => Err("the adaptive unit's result has no sums of squares".into()),
            (None, Some(_)) => Err("the uniform unit's result has sums of squares".into()),
            _ => Ok(()),
        };
    };
    let one = (MAX_SAMPLE_VALUE * FIXED_ONE) as u128;
    let most = one * one * lease.region.samples.len() as u128;
    for (i, s) in squares.iter().enumerate() {
        let (x, y) = (
            lease.region.rect.x + i as u32 % lease.region.rect.width,
            lease.region.rect.y + i as u32 / lease.region.rect.width,
        );
        let limit = if mask.covers(x, y) { most } else { 0 };
        if s.iter().any(|&v| v > limit) {
            return Err(format!(
                "pixel ({x}, {y}) has a sum of squares beyond what its samples can reach"
            ));
        }
    }
    Ok(())
}

/// Samples a pixel of the lease must have: the round's count in active
/// blocks, none elsewhere.
pub(super) fn expected_count(lease: &Lease, x: u32, y: u32) -> u32 {
    match &lease.active {
        Some(m) if !m.covers(x, y) => 0,
        _ => lease.region.samples.len(),
    }
}

/// Pixels the lease samples.
pub(super) fn sampled_pixels(lease: &Lease) -> u64 {
    lease
        .active
        .as_ref()
        .map_or(lease.region.rect.area() as u64, BlockMask::active_pixels)
}
