//! Partial results and their resolution into an image.
//!
//! A render of a rectangle over a range of sample indices returns, per pixel,
//! the *sum* of its samples and how many there were. Sums are kept in fixed
//! point (unsigned 64-bit, 32 fractional bits): integer addition is exact and
//! associative, so results from any split of the work into tiles and sample
//! batches, added in any order on any machine, give bit-identical images.

use crate::math::Real;

/// Fixed-point scale of film sums: 2^32 units per unit of radiance.
pub const FIXED_ONE: f64 = 4_294_967_296.0;
/// Largest radiance one sample may carry; with [`crate::scene::MAX_SAMPLES`]
/// samples the sum stays far below `u64::MAX`.
pub const MAX_SAMPLE_VALUE: f64 = 65_504.0;

/// A rectangle of pixels: columns `x..x+width`, rows `y..y+height` (row 0 on top).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Rect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl Rect {
    pub fn new(x: u32, y: u32, width: u32, height: u32) -> Self {
        Rect {
            x,
            y,
            width,
            height,
        }
    }
    pub fn full(width: u32, height: u32) -> Self {
        Rect {
            x: 0,
            y: 0,
            width,
            height,
        }
    }
    pub fn area(&self) -> usize {
        self.width as usize * self.height as usize
    }
    pub fn contains(&self, o: &Rect) -> bool {
        o.x >= self.x
            && o.y >= self.y
            && o.x + o.width <= self.x + self.width
            && o.y + o.height <= self.y + self.height
    }
    /// Splits into tiles of at most `size` x `size`, row by row.
    pub fn tiles(&self, size: u32) -> Vec<Rect> {
        let size = size.max(1);
        let mut out = Vec::new();
        let mut y = self.y;
        while y < self.y + self.height {
            let h = size.min(self.y + self.height - y);
            let mut x = self.x;
            while x < self.x + self.width {
                let w = size.min(self.x + self.width - x);
                out.push(Rect::new(x, y, w, h));
                x += w;
            }
            y += h;
        }
        out
    }
}

/// Sample indices `start..end` of a pixel's `samples`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct SampleRange {
    pub start: u32,
    pub end: u32,
}

impl SampleRange {
    pub fn new(start: u32, end: u32) -> Self {
        SampleRange { start, end }
    }
    pub fn all(samples: u32) -> Self {
        SampleRange {
            start: 0,
            end: samples,
        }
    }
    pub fn len(&self) -> u32 {
        self.end.saturating_sub(self.start)
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Rays traced, by kind.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RayCounts {
    pub primary: u64,
    pub shadow: u64,
    pub reflection: u64,
    pub refraction: u64,
}

impl RayCounts {
    /// Saturating: counts that arrived over the network must not wrap.
    pub fn total(&self) -> u64 {
        self.primary
            .saturating_add(self.shadow)
            .saturating_add(self.reflection)
            .saturating_add(self.refraction)
    }
    pub fn add(&mut self, o: &RayCounts) {
        self.primary += o.primary;
        self.shadow += o.shadow;
        self.reflection += o.reflection;
        self.refraction += o.refraction;
    }
}

/// Per-pixel fixed-point sums and sample counts over a rectangle.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Film {
    pub rect: Rect,
    /// RGB sums, row-major over `rect`, in units of 1/[`FIXED_ONE`].
    pub sums: Vec<[u64; 3]>,
    pub counts: Vec<u32>,
    pub rays: RayCounts,
    /// Samples whose value was NaN or infinite and was replaced by 0 (or clamped).
    /// Always 0 for a correct tracer; tests assert it.
    pub nonfinite: u64,
}

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum FilmError {
    #[error("tile {tile:?} does not lie inside film {film:?}")]
    OutOfBounds { tile: Rect, film: Rect },
    #[error("tile {rect:?} has {got} pixels of data, expected {expected}")]
    WrongSize {
        rect: Rect,
        expected: usize,
        got: usize,
    },
    #[error("pixel sum overflow at ({x}, {y})")]
    Overflow { x: u32, y: u32 },
}

/// Converts one sample's radiance to fixed point, sanitising non-finite values.
#[inline(always)]
pub fn to_fixed(v: f64, nonfinite: &mut u64) -> u64 {
    if v.is_nan() {
        *nonfinite += 1;
        return 0;
    }
    if v > MAX_SAMPLE_VALUE {
        if v.is_infinite() {
            *nonfinite += 1;
        }
        return (MAX_SAMPLE_VALUE * FIXED_ONE) as u64;
    }
    // Radiance is never negative in this model; clamp guards rounding of -0.
    // `x.round()` for 0 <= x < 2^52 (here x < 2^48), where x + 0.5 is exact
    // and the cast truncates: the same integer, without a libm call (x86-64
    // has no instruction for round-half-away-from-zero).
    ((v.max(0.0) * FIXED_ONE) + 0.5) as u64
}

impl Film {
    pub fn new(rect: Rect) -> Self {
        Film {
            rect,
            sums: vec![[0; 3]; rect.area()],
            counts: vec![0; rect.area()],
            rays: RayCounts::default(),
            nonfinite: 0,
        }
    }

    /// Adds one sample to pixel `i` (row-major index within the rect).
    #[inline(always)]
    pub fn add_sample<R: Real>(&mut self, i: usize, rgb: [R; 3]) {
        let s = &mut self.sums[i];
        for c in 0..3 {
            s[c] += to_fixed(rgb[c].to_f64(), &mut self.nonfinite);
        }
        self.counts[i] += 1;
    }

    /// Checks that data from elsewhere (a worker, a file) is self-consistent.
    pub fn validate(&self) -> Result<(), FilmError> {
        let expected = self.rect.area();
        for got in [self.sums.len(), self.counts.len()] {
            if got != expected {
                return Err(FilmError::WrongSize {
                    rect: self.rect,
                    expected,
                    got,
                });
            }
        }
        Ok(())
    }

    /// Adds another film whose rect lies inside this one's.
    pub fn merge(&mut self, other: &Film) -> Result<(), FilmError> {
        other.validate()?;
        if !self.rect.contains(&other.rect) {
            return Err(FilmError::OutOfBounds {
                tile: other.rect,
                film: self.rect,
            });
        }
        for row in 0..other.rect.height {
            let src = (row * other.rect.width) as usize;
            let dst = ((other.rect.y - self.rect.y + row) * self.rect.width
                + (other.rect.x - self.rect.x)) as usize;
            for col in 0..other.rect.width as usize {
                let (a, b) = (&mut self.sums[dst + col], &other.sums[src + col]);
                for c in 0..3 {
                    a[c] = a[c].checked_add(b[c]).ok_or(FilmError::Overflow {
                        x: other.rect.x + col as u32,
                        y: other.rect.y + row,
                    })?;
                }
                self.counts[dst + col] += other.counts[src + col];
            }
        }
        self.rays.add(&other.rays);
        self.nonfinite += other.nonfinite;
        Ok(())
    }

    /// Mean of each pixel's samples, linear RGB, row-major (black where no sample landed).
    pub fn resolve(&self) -> Vec<[f32; 3]> {
        self.sums
            .iter()
            .zip(&self.counts)
            .map(|(s, &n)| {
                if n == 0 {
                    [0.0; 3]
                } else {
                    let k = 1.0 / (n as f64 * FIXED_ONE);
                    [
                        (s[0] as f64 * k) as f32,
                        (s[1] as f64 * k) as f32,
                        (s[2] as f64 * k) as f32,
                    ]
                }
            })
            .collect()
    }
}

/// sRGB transfer function of a linear value in [0, 1].
pub fn srgb_encode(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0);
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// 8-bit sRGB pixels of a resolved film: clamped to [0, 1], encoded, rounded.
pub fn to_srgb8(linear: &[[f32; 3]]) -> Vec<u8> {
    linear
        .iter()
        .flat_map(|p| p.map(|c| (srgb_encode(c) * 255.0 + 0.5) as u8))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_cover_the_rect_exactly_once() {
        let r = Rect::new(3, 5, 70, 33);
        let tiles = r.tiles(16);
        assert_eq!(tiles.iter().map(|t| t.area()).sum::<usize>(), r.area());
        assert!(
            tiles
                .iter()
                .all(|t| r.contains(t) && t.width <= 16 && t.height <= 16)
        );
    }

    #[test]
    fn merge_rejects_bad_tiles() {
        let mut f = Film::new(Rect::full(8, 8));
        let mut t = Film::new(Rect::new(4, 4, 8, 2));
        assert_eq!(
            f.merge(&t),
            Err(FilmError::OutOfBounds {
                tile: t.rect,
                film: f.rect
            })
        );
        t.rect = Rect::new(0, 0, 8, 2);
        t.counts.pop();
        assert_eq!(
            f.merge(&t),
            Err(FilmError::WrongSize {
                rect: t.rect,
                expected: 16,
                got: 15
            })
        );
    }

    #[test]
    fn fixed_point_sanitises() {
        let mut bad = 0;
        assert_eq!(to_fixed(f64::NAN, &mut bad), 0);
        assert_eq!(
            to_fixed(f64::INFINITY, &mut bad),
            (MAX_SAMPLE_VALUE * FIXED_ONE) as u64
        );
        assert_eq!(bad, 2);
        assert_eq!(to_fixed(1.0, &mut bad), 1 << 32);
        assert_eq!(to_fixed(-0.0, &mut bad), 0);
        assert_eq!(bad, 2);
    }

    #[test]
    fn srgb_endpoints() {
        assert_eq!(to_srgb8(&[[0.0, 1.0, 2.0]]), vec![0, 255, 255]);
        assert_eq!(to_srgb8(&[[0.5, 0.22, f32::NAN]]), vec![188, 129, 0]);
    }
}
