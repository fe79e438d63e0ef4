//! How a job is cut into work units.
//!
//! A unit is (frame, tile, sample batch). Units are numbered frame-major,
//! then by sample batch, then by tile in row order:
//! `index = (frame_index * batches + batch) * tiles + tile`. Numbering is a
//! pure function of the job's settings, so it survives restarts.

use tracer_core::film::{Rect, SampleRange, WorkRegion};

/// Default side of a square tile, in pixels. Leases join tiles to suit each
/// worker's speed, so the tile is the grain only at a job's end. 64x64
/// gives a 2-thread CPU worker 16 renderer tiles to balance and keeps a
/// result near 115 KB. Measured against 32x32 on the 16-vCPU benchmark
/// machine (1920x1080, 16 spp, three alternations): the same time with 8
/// workers (1.62 s), but one 2-thread worker took 10.1 s with 64 and 11.9 s
/// with 32 (docs/benchmarks.md).
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

/// Bytes of one pixel in a result on the wire (three u64 sums, one u32 count).
pub const RESULT_BYTES_PER_PIXEL: u64 = 28;

/// The number of units settings would make, in u64 (so no product wraps),
/// computed before anything is allocated.
pub fn unit_count(
    width: u32,
    height: u32,
    samples: u32,
    frames: u32,
    tile_size: u32,
    samples_per_unit: u32,
) -> u64 {
    let tile = u64::from(tile_size.max(1));
    let tiles = u64::from(width).div_ceil(tile) * u64::from(height).div_ceil(tile);
    let batches = u64::from(samples).div_ceil(u64::from(samples_per_unit.max(1)));
    tiles * batches * u64::from(frames)
}

impl Layout {
    /// Callers check [`unit_count`] against their limit first: the unit
    /// numbers are u32.
    pub fn new(
        width: u32,
        height: u32,
        samples: u32,
        first_frame: u32,
        last_frame: u32,
        tile_size: u32,
        samples_per_unit: u32,
    ) -> Self {
        let tiles = Rect::full(width, height).tiles(tile_size);
        let tiles_per_row = width.div_ceil(tile_size.max(1));
        let batches = SampleRange::all(samples)
            .batches(samples_per_unit)
            .collect();
        Layout {
            first_frame,
            frames: last_frame - first_frame + 1,
            width,
            height,
            tile_size,
            tiles,
            tiles_per_row,
            batches,
        }
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
        Unit {
            frame: self.first_frame + index / (nt * nb),
            batch: (index / nt) % nb,
            tile: index % nt,
        }
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

    /// The units a stored result covers: those of `first`'s frame and
    /// sample batch whose tiles lie in `rect`, which must be exactly a
    /// rectangle of whole tiles starting at `first`'s (`None` otherwise:
    /// a damaged record).
    pub fn units_in(&self, first: u32, rect: Rect) -> Option<Vec<u32>> {
        if first >= self.total() || rect.width == 0 || rect.height == 0 {
            return None;
        }
        let ts = self.tile_size.max(1);
        let u0 = self.unit(first);
        let t0 = self.tiles[u0.tile as usize];
        let (right, bottom) = (
            rect.x.checked_add(rect.width)?,
            rect.y.checked_add(rect.height)?,
        );
        let on_grid = |v: u32, limit: u32| v == limit || v.is_multiple_of(ts);
        if (t0.x, t0.y) != (rect.x, rect.y)
            || right > self.width
            || bottom > self.height
            || !on_grid(right, self.width)
            || !on_grid(bottom, self.height)
        {
            return None;
        }
        let base = first - u0.tile;
        let (cols, rows) = (
            rect.x / ts..right.div_ceil(ts),
            rect.y / ts..bottom.div_ceil(ts),
        );
        Some(
            rows.flat_map(|ty| {
                cols.clone()
                    .map(move |tx| base + ty * self.tiles_per_row + tx)
            })
            .collect(),
        )
    }

    /// The frame, pixels and samples a unit covers.
    pub fn region(&self, u: Unit) -> WorkRegion {
        WorkRegion::new(
            u.frame,
            self.tiles[u.tile as usize],
            self.batches[u.batch as usize],
        )
    }

    /// Pixel-samples of a unit.
    pub fn unit_samples(&self, u: Unit) -> u64 {
        self.region(u).pixel_samples()
    }

    /// Whether unit `b` directly follows `a` in the same tile row, frame and batch
    /// (so their rects join into one rectangle).
    pub fn joins(&self, a: u32, b: u32) -> bool {
        let (ua, ub) = (self.unit(a), self.unit(b));
        b == a + 1
            && ua.frame == ub.frame
            && ua.batch == ub.batch
            && ua.tile / self.tiles_per_row == ub.tile / self.tiles_per_row
    }

    /// Units from `first` on, all `pending`, whose tiles make one
    /// rectangle: a run along `first`'s row of tiles, and when that run is
    /// the whole row, further whole rows below it (same frame and sample
    /// batch); at most `max` units whose `cost` adds up to at most `budget`
    /// (but always `first`). Unit numbers are row-major, so the result is
    /// consecutive.
    pub fn join(
        &self,
        first: u32,
        max: u32,
        pending: impl Fn(u32) -> bool,
        cost: impl Fn(u32) -> f64,
        budget: f64,
    ) -> Vec<u32> {
        let mut units = vec![first];
        let mut spent = cost(first);
        while (units.len() as u32) < max {
            let next = *units.last().expect("non-empty") + 1;
            if next < self.total()
                && self.joins(next - 1, next)
                && pending(next)
                && spent + cost(next) <= budget
            {
                units.push(next);
                spent += cost(next);
            } else {
                break;
            }
        }
        let tpr = self.tiles_per_row;
        if units.len() as u32 != tpr {
            return units;
        }
        let u0 = self.unit(first);
        while units.len() as u32 + tpr <= max {
            let start = first + units.len() as u32;
            let row_ok = start + tpr <= self.total() && {
                let u = self.unit(start);
                u.frame == u0.frame
                    && u.batch == u0.batch
                    && u.tile.is_multiple_of(tpr)
                    && (start..start + tpr).all(&pending)
            };
            let row_cost: f64 = (start..start + tpr).map(&cost).sum();
            if !row_ok || spent + row_cost > budget {
                break;
            }
            units.extend(start..start + tpr);
            spent += row_cost;
        }
        units
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stored_result_covers_the_units_its_lease_joined() {
        // 100x70 in 32-pixel tiles: 4 a row (the last 4 wide), 3 rows (the
        // last 6 high); 10 samples in batches of 4: 3 batches; frames 3-5.
        let l = Layout::new(100, 70, 10, 3, 5, 32, 4);
        let join = |first: u32, max: u32| l.join(first, max, |_| true, |_| 1.0, f64::INFINITY);
        let rect_of = |units: &[u32]| {
            let (a, b) = (
                l.tiles[l.unit(units[0]).tile as usize],
                l.tiles[l.unit(*units.last().unwrap()).tile as usize],
            );
            Rect::new(a.x, a.y, b.x + b.width - a.x, b.y + b.height - a.y)
        };
        // A run inside a row, whole rows, the frame's last tile, another frame and batch.
        let second_frame_batch_2 = l.index(Unit {
            frame: 4,
            batch: 2,
            tile: 5,
        });
        for (first, max) in [(1, 2), (0, 12), (4, 8), (11, 1), (second_frame_batch_2, 3)] {
            let units = join(first, max);
            assert_eq!(l.units_in(first, rect_of(&units)), Some(units));
        }
        // Not a rectangle of whole tiles from the first unit's: damaged.
        assert_eq!(l.units_in(0, Rect::new(0, 0, 33, 32)), None);
        assert_eq!(l.units_in(1, Rect::new(0, 0, 64, 32)), None);
        assert_eq!(l.units_in(0, Rect::new(0, 0, 100, 71)), None);
        assert_eq!(l.units_in(l.total(), Rect::new(0, 0, 32, 32)), None);
        assert_eq!(l.units_in(0, Rect::new(0, 0, 0, 32)), None);
    }

    #[test]
    fn indices_round_trip_and_cover_every_sample_once() {
        let l = Layout::new(100, 70, 10, 3, 5, 32, 4);
        assert_eq!(l.tiles.len(), 4 * 3);
        assert_eq!(
            l.batches,
            vec![
                SampleRange::new(0, 4),
                SampleRange::new(4, 8),
                SampleRange::new(8, 10)
            ]
        );
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

    #[test]
    fn joined_units_form_a_rectangle_of_pending_tiles() {
        // 4 tiles a row, 3 rows, 2 sample batches: units 0..12 are batch 0.
        let l = Layout::new(64, 48, 8, 0, 0, 16, 4);
        assert_eq!(l.tiles_per_row, 4);
        let all = |_| true;
        let one = |_| 1.0;
        // Within a row, stopping at its end.
        assert_eq!(l.join(1, 10, all, one, 1e9), vec![1, 2, 3]);
        assert_eq!(l.join(0, 3, all, one, 1e9), vec![0, 1, 2]);
        // From a row's start: whole rows, never past the batch.
        assert_eq!(l.join(0, 9, all, one, 1e9), (0..8).collect::<Vec<_>>());
        assert_eq!(l.join(4, 100, all, one, 1e9), (4..12).collect::<Vec<_>>());
        // A row with a unit taken is not joined.
        assert_eq!(
            l.join(0, 12, |u| u != 9, one, 1e9),
            (0..8).collect::<Vec<_>>()
        );
        assert_eq!(l.join(0, 12, |u| u != 2, one, 1e9), vec![0, 1]);
        // The budget: units along the row while they fit, whole rows only
        // when the whole row fits; the first unit always.
        assert_eq!(l.join(0, 12, all, one, 2.5), vec![0, 1]);
        assert_eq!(l.join(0, 12, all, one, 7.0), vec![0, 1, 2, 3]);
        assert_eq!(
            l.join(0, 12, all, |u| if u == 1 { 10.0 } else { 1.0 }, 5.0),
            vec![0]
        );
        assert_eq!(l.join(0, 12, all, one, 0.0), vec![0]);
    }
}
