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
//!
//! In the image mode (`AdaptiveMode::Image`, the error-optimal mode of
//! issue 36) a round is frame-wide: its decision needs every block's
//! statistics and cost, so round r+1 of a frame is decided once every
//! tile of round r is merged (the barrier), by the
//! [`RmseSchedule`] that `tessera render --adaptive-mode image` runs, from
//! the frame's film and the costs its CPU workers measured (each result's
//! runs of blocks with their rays, booked as the local render books its
//! own: `Costs::book_runs`). Each block then has its own sample range; a
//! lease carries its blocks' ranges, and a tile none of whose blocks grows
//! is done for that round without work. The runs are stored with each
//! round's film, so a restart replays the rounds, in order, to the same
//! schedule and costs.

use std::collections::HashMap;

use tracer_core::adaptive::optimal::{
    Costs, RmseSchedule, RmseSettings, RmseStep, block_stats, image_mean,
};
use tracer_core::adaptive::{
    AdaptiveMode, AdaptiveSettings, BLOCK, BlockMask, Summary, block_index, check_rect,
    next_active, summarize,
};
use tracer_core::film::{FIXED_ONE, Film, MAX_SAMPLE_VALUE, Rect, SampleRange};

use super::{Job, Lease};
use crate::units::Unit;

/// An adaptive job's settings and where its tiles stand.
pub(super) struct AdaptiveJob {
    pub settings: AdaptiveSettings,
    /// Summary of each tile that has merged a round, by (frame, tile).
    tiles: HashMap<(u32, u32), Summary>,
    /// The image mode: each started frame's rounds.
    frames: HashMap<u32, ImageFrame>,
}

/// A frame of an image-mode job: its rounds' schedule and the costs booked.
struct ImageFrame {
    schedule: RmseSchedule,
    costs: Costs,
    /// The last decided round's outcome (progress).
    last: Option<RmseStep>,
    /// Pixel-samples the frame has after the pending round.
    expected: u64,
    /// Blocks the pending round leaves alone (all, once the frame is done).
    settled: u64,
    /// The schedule ended: its blocks' state is dropped (a long
    /// animation's frames would otherwise each keep it).
    ended: bool,
}

impl ImageFrame {
    fn new(settings: &AdaptiveSettings, width: u32, height: u32) -> Self {
        let rect = Rect::full(width, height);
        let costs = Costs::new(rect);
        ImageFrame {
            schedule: RmseSchedule::new(RmseSettings::from(settings), costs.rays.len()),
            costs,
            last: None,
            expected: settings.min_samples as u64 * rect.area() as u64,
            settled: 0,
            ended: false,
        }
    }
}

/// Image mode: frame `frame`'s rounds, started if they were not (a free
/// function: its callers go on to read the job's layout).
fn image_frame<'a>(
    adaptive: &'a mut Option<AdaptiveJob>,
    layout: &crate::units::Layout,
    frame: u32,
) -> &'a mut ImageFrame {
    let a = adaptive.as_mut().expect("adaptive");
    let settings = a.settings;
    a.frames
        .entry(frame)
        .or_insert_with(|| ImageFrame::new(&settings, layout.width, layout.height))
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
            frames: HashMap::new(),
        }
    }

    pub fn image_mode(&self) -> bool {
        self.settings.mode == AdaptiveMode::Image
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
            self.skip_unit(u);
        }
        false
    }

    /// After a restart: every tile of every unwritten frame takes up where
    /// its merged rounds left it. An image-mode job's stored films (by
    /// their first unit, their units marked done, not merged) are replayed
    /// round by round instead ([`Job::image_replay`]).
    pub(super) fn adaptive_restore(&mut self, image_films: Vec<(u32, Film)>) -> Result<(), String> {
        if self.adaptive.is_none() {
            return Ok(());
        }
        self.adaptive_start();
        if self.image_mode() {
            return self.image_replay(image_films);
        }
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
        Ok(())
    }

    /// Whether this is an adaptive job in the image mode.
    pub(super) fn image_mode(&self) -> bool {
        self.adaptive.as_ref().is_some_and(AdaptiveJob::image_mode)
    }

    /// Merges a result of round `round` of an image-mode job into its
    /// frame, booking its runs first (the film's runs are taken).
    pub(super) fn image_merge(&mut self, frame: u32, film: &mut Film) -> Result<(), String> {
        let (w, h) = (self.layout.width, self.layout.height);
        let runs = std::mem::take(&mut film.runs);
        let f = image_frame(&mut self.adaptive, &self.layout, frame);
        if !f.ended {
            f.costs.book_runs(Rect::full(w, h), &runs);
        }
        let acc = self.frames.get(&frame).ok_or("frame of a unit")?;
        acc.film
            .lock()
            .expect("frame film lock")
            .get_or_insert_with(|| super::frames::new_frame_film(w, h, true))
            .merge(film)
            .map_err(|e| e.to_string())
    }

    /// After a result of round `round` of `frame` was merged (image mode):
    /// once every tile of the round is done, the frame's schedule decides
    /// the next round from the frame's film and costs; its tiles with a
    /// growing block become pending, the others are done for that round
    /// without work, and when the schedule ends every later round is.
    /// Returns whether a unit became pending.
    pub(super) fn image_advance(&mut self, frame: u32, round: u32) -> bool {
        let tiles = self.layout.tiles.len() as u32;
        let rounds = self.layout.batches.len() as u32;
        let unit =
            |layout: &crate::units::Layout, tile, batch| layout.index(Unit { frame, tile, batch });
        if (0..tiles).any(|t| !self.done[unit(&self.layout, t, round) as usize]) {
            return false;
        }
        let Some(frame_film) = self.frames.get(&frame).map(|f| f.film.clone()) else {
            return false;
        };
        let (w, h) = (self.layout.width, self.layout.height);
        let settings = self.adaptive.as_ref().expect("adaptive").settings;
        let f = image_frame(&mut self.adaptive, &self.layout, frame);
        // Decided once: a restart's replay and a late duplicate ask again.
        if f.ended || f.schedule.round() != round {
            return false;
        }
        {
            let guard = frame_film.lock().expect("frame film lock");
            let Some(film) = guard.as_ref() else {
                return false;
            };
            let stats = block_stats(film, film.rect, Some(&f.costs));
            f.last = Some(f.schedule.after_round(&stats, image_mean(film)));
        }
        let next = round + 1;
        let mut grows = vec![false; tiles as usize];
        let going_on = f.schedule.pending().is_some() && next < rounds;
        if going_on {
            let full = BlockMask::none(Rect::full(w, h));
            // The allocation meeting the target (at least the next round's
            // counts: the schedule's step says so), not only the next round.
            f.expected = f.last.map_or(0, |s| s.expected_pixel_samples);
            f.settled = (0..full.active.len())
                .filter(|&i| {
                    let (n, to) = f.schedule.block(i);
                    to <= n
                })
                .count() as u64;
            for (t, rect) in self.layout.tiles.iter().enumerate() {
                let mask = BlockMask::none(*rect);
                grows[t] = (0..mask.active.len()).any(|i| {
                    let b = mask.block_rect(i);
                    let (n, to) = f.schedule.block(block_index(full.rect, b.x, b.y));
                    to > n
                });
            }
        } else {
            f.expected = f.last.map_or(0, |s| s.pixel_samples);
            f.settled = f.costs.rays.len() as u64;
            f.ended = true;
            f.schedule = RmseSchedule::new(RmseSettings::from(&settings), 0);
            f.costs = Costs::new(Rect::full(0, 0));
        }
        let mut queued = false;
        for r in next..rounds {
            for t in 0..tiles {
                let u = unit(&self.layout, t, r);
                if going_on && r == next && grows[t as usize] {
                    queued |= !self.done[u as usize] && self.pending.insert(u);
                } else if !going_on || r == next {
                    self.skip_unit(u);
                }
            }
            if going_on {
                break;
            }
        }
        queued
    }

    /// Marks a unit done without work (no samples traced).
    fn skip_unit(&mut self, u: u32) {
        if self.done[u as usize] {
            return;
        }
        self.mark_done(u);
        let unit = self.layout.unit(u);
        self.correct_samples(unit.frame, self.layout.unit_samples(unit), 0);
    }

    /// After a restart (image mode): the stored films, merged round by
    /// round in each frame with their runs booked, and each round decided
    /// as it was: the same schedule, costs and pending tiles.
    fn image_replay(&mut self, mut films: Vec<(u32, Film)>) -> Result<(), String> {
        let key = |layout: &crate::units::Layout, u: u32| {
            let unit = layout.unit(u);
            (unit.frame, unit.batch)
        };
        films.sort_by_key(|(u, _)| (key(&self.layout, *u), *u));
        let mut i = 0;
        while i < films.len() {
            let (frame, round) = key(&self.layout, films[i].0);
            while i < films.len() && key(&self.layout, films[i].0) == (frame, round) {
                self.image_merge(frame, &mut films[i].1)?;
                i += 1;
            }
            self.image_advance(frame, round);
        }
        Ok(())
    }

    /// A lease of `rect` in `frame` (image mode, its pending round): each
    /// block's range, the blocks that take samples, and the smallest range
    /// holding them all.
    pub(super) fn image_ranges(
        &mut self,
        frame: u32,
        rect: Rect,
    ) -> (BlockMask, Vec<SampleRange>, SampleRange) {
        let full = Rect::full(self.layout.width, self.layout.height);
        let f = image_frame(&mut self.adaptive, &self.layout, frame);
        let mut mask = BlockMask::none(rect);
        let ranges: Vec<SampleRange> = (0..mask.active.len())
            .map(|i| {
                let b = mask.block_rect(i);
                let (n, to) = f.schedule.block(block_index(full, b.x, b.y));
                if to > n {
                    SampleRange::new(n, to)
                } else {
                    SampleRange::new(0, 0)
                }
            })
            .collect();
        let mut hull: Option<SampleRange> = None;
        for (on, r) in mask.active.iter_mut().zip(&ranges) {
            *on = !r.is_empty();
            if *on {
                hull = Some(hull.map_or(*r, |h| {
                    SampleRange::new(h.start.min(r.start), h.end.max(r.end))
                }));
            }
        }
        (mask, ranges, hull.unwrap_or(SampleRange::new(0, 0)))
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
        if a.image_mode() {
            let pixels = self.layout.width as u64 * self.layout.height as u64;
            return a
                .frames
                .get(&frame)
                .map_or(a.settings.min_samples as u64 * pixels, |f| f.expected);
        }
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
        // Blocks in all and settled; squared errors summed with weights.
        let (mut blocks, mut settled, mut sq, mut weight) = (0u64, 0u64, 0.0f64, 0.0f64);
        if a.image_mode() {
            // Each frame's blocks and estimated RMSE once it has decided a
            // round; the error is the RMS over those frames.
            let per_frame = BlockMask::none(Rect::full(self.layout.width, self.layout.height))
                .active
                .len() as u64;
            for f in self.frames.keys() {
                out.samples_expected += self.adaptive_frame_expected(*f);
                blocks += per_frame;
                if let Some(fr) = a.frames.get(f)
                    && let Some(last) = fr.last
                {
                    out.samples_done += last.pixel_samples;
                    settled += fr.settled;
                    sq += last.estimated_rmse * last.estimated_rmse;
                    weight += 1.0;
                }
            }
        } else {
            // Each tile's converged blocks and RMS error, by area.
            for f in self.frames.keys() {
                out.samples_expected += self.adaptive_frame_expected(*f);
                for (t, rect) in self.layout.tiles.iter().enumerate() {
                    match a.tiles.get(&(*f, t as u32)) {
                        Some(s) => {
                            blocks += s.blocks;
                            settled += s.converged_blocks;
                            out.samples_done += s.samples_done;
                            sq += s.rms_error * s.rms_error * rect.area() as f64;
                            weight += rect.area() as f64;
                        }
                        None => blocks += BlockMask::all(*rect).active.len() as u64,
                    }
                }
            }
        }
        out.converged_share = if blocks == 0 {
            0.0
        } else {
            settled as f64 / blocks as f64
        };
        out.estimated_error = if weight == 0.0 {
            0.0
        } else {
            (sq / weight).sqrt()
        };
        out
    }
}

/// The checks of an adaptive result beyond a uniform one's: sums of
/// squares present exactly when the lease is adaptive, none where a pixel
/// has no samples, and each within what `n` samples can reach.
pub(super) fn check_result(lease: &Lease, film: &Film) -> Result<(), String> {
    let (Some(_), Some(squares)) = (&lease.active, &film.squares) else {
        return match (&lease.active, &film.squares) {
            (Some(_), None) => Err("the adaptive unit's result has no sums of squares".into()),
            (None, Some(_)) => Err("the uniform unit's result has sums of squares".into()),
            _ => Ok(()),
        };
    };
    let one = (MAX_SAMPLE_VALUE * FIXED_ONE) as u128;
    for (i, s) in squares.iter().enumerate() {
        let (x, y) = (
            lease.region.rect.x + i as u32 % lease.region.rect.width,
            lease.region.rect.y + i as u32 / lease.region.rect.width,
        );
        let limit = one * one * expected_count(lease, x, y) as u128;
        if s.iter().any(|&v| v > limit) {
            return Err(format!(
                "pixel ({x}, {y}) has a sum of squares beyond what its samples can reach"
            ));
        }
    }
    Ok(())
}

/// Samples a pixel of the lease must have: the round's count in active
/// blocks (in the image mode, its block's own), none elsewhere.
pub(super) fn expected_count(lease: &Lease, x: u32, y: u32) -> u32 {
    match (&lease.active, &lease.ranges) {
        (Some(m), _) if !m.covers(x, y) => 0,
        (Some(m), Some(ranges)) => ranges[block_index(m.rect, x, y)].len(),
        _ => lease.region.samples.len(),
    }
}

/// Pixel-samples the lease traces (its primary rays).
pub(super) fn sampled_pixel_samples(lease: &Lease) -> u64 {
    match (&lease.active, &lease.ranges) {
        (Some(m), Some(ranges)) => (0..m.active.len())
            .map(|i| m.block_rect(i).area() as u64 * ranges[i].len() as u64)
            .sum(),
        (Some(m), None) => m.active_pixels() * lease.region.samples.len() as u64,
        (None, _) => lease.region.rect.area() as u64 * lease.region.samples.len() as u64,
    }
}

/// The runs of an image-mode result: whole blocks of the lease's rect in
/// one row, each block's range as long as the run's samples, their rays
/// adding up to the film's (a GPU worker's runs are a block each; a worker
/// that measures nothing sends none). A result of any other
/// unit has none.
pub(super) fn check_runs(lease: &Lease, film: &Film) -> Result<(), String> {
    let Some(ranges) = &lease.ranges else {
        return match film.runs.is_empty() {
            true => Ok(()),
            false => Err("the result has runs of blocks, which only image-mode units take".into()),
        };
    };
    if film.runs.is_empty() {
        return Ok(());
    }
    let rect = lease.region.rect;
    let mut rays = 0u64;
    // A block is booked by one run at most.
    let mut booked = vec![false; ranges.len()];
    for r in &film.runs {
        // On the block grid and ending on it or at the rect's edge.
        let (right, bottom) = (rect.x + rect.width, rect.y + rect.height);
        if !rect.contains(&r.rect)
            || r.rect.width == 0
            || r.rect.height == 0
            || check_rect(r.rect, right, bottom).is_err()
            || r.rect.height > BLOCK
        {
            return Err(format!(
                "run {:?} is not a row of whole blocks of the leased rect {rect:?}",
                r.rect
            ));
        }
        let mut x = r.rect.x;
        while x < r.rect.x + r.rect.width {
            let i = block_index(rect, x, r.rect.y);
            if std::mem::replace(&mut booked[i], true) {
                return Err(format!(
                    "run {:?} covers the block at ({x}, {}) that another run covers",
                    r.rect, r.rect.y
                ));
            }
            if r.samples == 0 || ranges[i].len() != r.samples {
                return Err(format!(
                    "run {:?} has {} samples a pixel, its block at ({x}, {}) takes {}",
                    r.rect,
                    r.samples,
                    r.rect.y,
                    ranges[i].len()
                ));
            }
            x += BLOCK;
        }
        rays = rays.saturating_add(r.rays);
    }
    if rays != film.rays.total() {
        return Err(format!(
            "the runs count {rays} rays, the result {}",
            film.rays.total()
        ));
    }
    Ok(())
}
