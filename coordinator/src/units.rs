//! How a job is cut into work units.
//!
//! A unit is (frame, tile, sample batch). Units are numbered frame-major,
//! then by sample batch, then by tile in row order:
//! `index = (frame_index * batches + batch) * tiles + tile`. Numbering is a
//! pure function of the job's settings, so it survives restarts.

use tracer_core::film::{Rect, SampleRange};

/// Default side of a square tile, in pixels. 64x64 gives a 2-thread CPU
/// worker 16 renderer tiles to balance and keeps a result near 115 KB.
pub const DEFAULT_TILE_SIZE: u32 = 64;
/// Default samples per pixel in one unit: whole pixels for the usual sample
/// counts, so a frame is one pass over its tiles.
pub const DEFAULT_SAMPLES_PER_UNIT: u32 = 64;
/// Default failed attempts of one unit before its job fails.
pub const DEFAULT_MAX_ATTEMPTS: u32 = 3;

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Layout {
    pub first_frame: u32,
    pub frames: u32,
    pub width: u32,
    pub height: u32,
    pub tile_size: u32,
    pub tiles: Vec<Rect>,
    pub tiles_per_row: u32,
    pub batches: Vec<SampleRange>,
}

/// One unit's place in the job.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Unit {
    pub frame: u32,
    pub tile: u32,
    pub batch: u32,
}

impl Layout {
    pub fn new(width: u32, height: u32, samples: u32, first_frame: u32, last_frame: u32, tile_size: u32, samples_per_unit: u32) -> Self {
        let tiles = Rect::full(width, height).tiles(tile_size);
        let tiles_per_row = width.div_ceil(tile_size.max(1));
        let per = samples_per_unit.max(1);
        let batches = (0..samples.div_ceil(per)).map(|b| SampleRange::new(b * per, ((b + 1) * per).min(samples))).collect();
        Layout { first_frame, frames: last_frame - first_frame + 1, width, height, tile_size, tiles, tiles_per_row, batches }
    }

    pub fn units_per_frame(&self) -> u32 {
        self.tiles.len() as u32 * self.batches.len() as u32
    }

    pub fn total(&self) -> u32 {
        self.units_per_frame() * self.frames
    }

    pub fn unit(&self, index: u32) -> Unit {
        let nt = self.tiles.len() as u32;
        let nb = self.batches.len() as u32;
        Unit { frame: self.first_frame + index / (nt * nb), batch: (index / nt) % nb, tile: index % nt }
    }

    pub fn index(&self, u: Unit) -> u32 {
        let nt = self.tiles.len() as u32;
        ((u.frame - self.first_frame) * self.batches.len() as u32 + u.batch) * nt + u.tile
    }

    /// Unit indices of one frame.
    pub fn frame_units(&self, frame: u32) -> std::ops::Range<u32> {
        let start = (frame - self.first_frame) * self.units_per_frame();
        start..start + self.units_per_frame()
    }

    /// Pixel-samples of a unit.
    pub fn unit_samples(&self, u: Unit) -> u64 {
        self.tiles[u.tile as usize].area() as u64 * self.batches[u.batch as usize].len() as u64
    }

    /// Whether unit `b` directly follows `a` in the same tile row, frame and batch
    /// (so their rects join into one rectangle).
    pub fn joins(&self, a: u32, b: u32) -> bool {
        let (ua, ub) = (self.unit(a), self.unit(b));
        b == a + 1 && ua.frame == ub.frame && ua.batch == ub.batch && ua.tile / self.tiles_per_row == ub.tile / self.tiles_per_row
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn indices_round_trip_and_cover_every_sample_once() {
        let l = Layout::new(100, 70, 10, 3, 5, 32, 4);
        assert_eq!(l.tiles.len(), 4 * 3);
        assert_eq!(l.batches, vec![SampleRange::new(0, 4), SampleRange::new(4, 8), SampleRange::new(8, 10)]);
        assert_eq!(l.total(), 3 * 12 * 3);
        let mut per_frame = std::collections::BTreeMap::<u32, u64>::new();
        for i in 0..l.total() {
            let u = l.unit(i);
            assert_eq!(l.index(u), i);
            assert!(l.frame_units(u.frame).contains(&i));
            *per_frame.entry(u.frame).or_default() += l.unit_samples(u);
        }
        assert_eq!(per_frame, (3..=5).map(|f| (f, 100 * 70 * 10)).collect());
        // Tiles 3 and 4 are in different rows (4 tiles per row).
        assert!(l.joins(2, 3) && !l.joins(3, 4));
    }
}
