//! Partial results and their resolution into an image.
//!
//! A render of a rectangle over a range of sample indices returns, per pixel,
//! the *sum* of its samples and how many there were. Sums are kept in fixed
//! point (unsigned 64-bit, 32 fractional bits): integer addition is exact and
//! associative, so results from any split of the work into tiles and sample
//! batches, added in any order on any machine, give bit-identical images.

use crate::math::Real;

#[cfg(feature = "image-io")]
pub mod image;

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
    /// Consecutive batches of at most `per` (at least 1) indices covering
    /// the range in order: a job's sample batches, a tile's slices.
    pub fn batches(self, per: u32) -> impl Iterator<Item = SampleRange> {
        let per = per.max(1);
        (self.start..self.end)
            .step_by(per as usize)
            .map(move |k| SampleRange::new(k, k.saturating_add(per).min(self.end)))
    }
}

/// The pixels and samples of one frame that a piece of work covers: the
/// sample indices `samples` of each pixel of `rect` in frame `frame`. A
/// farm's lease, a worker's unit and a unit's failure each cover one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct WorkRegion {
    pub frame: u32,
    pub rect: Rect,
    pub samples: SampleRange,
}

impl WorkRegion {
    pub fn new(frame: u32, rect: Rect, samples: SampleRange) -> Self {
        WorkRegion {
            frame,
            rect,
            samples,
        }
    }
    /// Pixel-samples it covers.
    pub fn pixel_samples(&self) -> u64 {
        self.rect.area() as u64 * u64::from(self.samples.len())
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
    /// Adaptive renders only: per pixel, the sum of each sample's squared
    /// fixed-point value (exact: a sample is below 2^48 units, its square
    /// below 2^96, and 2^16 of them below 2^112), from which
    /// [`crate::adaptive`] estimates the error of the mean. `None` for
    /// uniform renders, which stay as they were on the wire and on disk.
    pub squares: Option<Vec<[u128; 3]>>,
    /// Renders by blocks over their own ranges (the error-optimal mode's
    /// rounds, on the CPU): each run of blocks rendered together, with the
    /// rays it traced, what the mode books as the blocks' cost. Empty
    /// otherwise. Describes this film's own render: [`Film::merge`] does
    /// not carry it (a caller books each film's runs as it merges it).
    pub runs: Vec<RunCost>,
}

/// A run of blocks rendered together, the rays it traced and its samples
/// per pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RunCost {
    pub rect: Rect,
    pub rays: u64,
    pub samples: u32,
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
    #[error(
        "film {rect:?} {what} sums of squares (an adaptive film merges only with adaptive films)"
    )]
    SquaresMismatch { rect: Rect, what: &'static str },
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
            squares: None,
            runs: Vec::new(),
        }
    }

    /// An empty film that also keeps sums of squares (adaptive renders).
    pub fn with_squares(rect: Rect) -> Self {
        Film {
            squares: Some(vec![[0; 3]; rect.area()]),
            ..Film::new(rect)
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
        let squares = self.squares.as_ref().map_or(expected, Vec::len);
        for got in [self.sums.len(), self.counts.len(), squares] {
            if got != expected {
                return Err(FilmError::WrongSize {
                    rect: self.rect,
                    expected,
                    got,
                });
            }
        }
        if let Some(r) = self.runs.iter().find(|r| !self.rect.contains(&r.rect)) {
            return Err(FilmError::OutOfBounds {
                tile: r.rect,
                film: self.rect,
            });
        }
        Ok(())
    }

    /// Adds another film whose rect lies inside this one's. Either all of
    /// it is added or, on an overflow, none of it (the sums are unchanged).
    /// Large films merge in parallel, row by row: the coordinator merges
    /// whole-frame results from GPU workers.
    pub fn merge(&mut self, other: &Film) -> Result<(), FilmError> {
        use rayon::prelude::*;
        other.validate()?;
        if !self.rect.contains(&other.rect) {
            return Err(FilmError::OutOfBounds {
                tile: other.rect,
                film: self.rect,
            });
        }
        match (&self.squares, &other.squares) {
            (Some(_), Some(_)) | (None, None) => {}
            (Some(_), None) => {
                return Err(FilmError::SquaresMismatch {
                    rect: other.rect,
                    what: "lacks",
                });
            }
            (None, Some(_)) => {
                return Err(FilmError::SquaresMismatch {
                    rect: other.rect,
                    what: "has",
                });
            }
        }
        // Sums of squares (adaptive films only) are checked before anything
        // is added, so an overflow there leaves the film unchanged too.
        if let (Some(a), Some(b)) = (&self.squares, &other.squares) {
            let w = self.rect.width as usize;
            for row in 0..other.rect.height as usize {
                let src = row * other.rect.width as usize;
                let dst = (other.rect.y - self.rect.y) as usize * w
                    + row * w
                    + (other.rect.x - self.rect.x) as usize;
                for col in 0..other.rect.width as usize {
                    if (0..3).any(|c| a[dst + col][c].checked_add(b[src + col][c]).is_none()) {
                        return Err(FilmError::Overflow {
                            x: other.rect.x + col as u32,
                            y: other.rect.y + row as u32,
                        });
                    }
                }
            }
        }
        let (w, ow) = (self.rect.width as usize, other.rect.width as usize);
        if ow == 0 || other.rect.height == 0 {
            self.rays.add(&other.rays);
            self.nonfinite += other.nonfinite;
            return Ok(());
        }
        let first = (other.rect.y - self.rect.y) as usize * w;
        let x0 = (other.rect.x - self.rect.x) as usize;
        let rows = other.rect.height as usize;
        let span = first..first + rows * w;
        // Wrapping adds that remember whether any wrapped: no branch per
        // pixel, so the loop vectorises; an overflow is undone below.
        let add_row = |(s, c): (&mut [[u64; 3]], &mut [u32]), (os, oc): (&[[u64; 3]], &[u32])| {
            let mut wrapped = false;
            for (a, b) in s[x0..x0 + ow].iter_mut().zip(os) {
                for ch in 0..3 {
                    let (v, o) = a[ch].overflowing_add(b[ch]);
                    a[ch] = v;
                    wrapped |= o;
                }
            }
            for (a, &b) in c[x0..x0 + ow].iter_mut().zip(oc) {
                let (v, o) = a.overflowing_add(b);
                *a = v;
                wrapped |= o;
            }
            wrapped
        };
        let src = other.sums.chunks(ow).zip(other.counts.chunks(ow));
        const PARALLEL_PIXELS: usize = 1 << 16;
        let wrapped = if other.sums.len() >= PARALLEL_PIXELS {
            let src: Vec<_> = src.collect();
            let dst: Vec<_> = self.sums[span.clone()]
                .chunks_mut(w)
                .zip(self.counts[span.clone()].chunks_mut(w))
                .collect();
            dst.into_par_iter()
                .zip(src)
                .map(|(d, s)| add_row(d, s))
                .reduce(|| false, |a, b| a | b)
        } else {
            self.sums[span.clone()]
                .chunks_mut(w)
                .zip(self.counts[span.clone()].chunks_mut(w))
                .zip(src)
                .fold(false, |acc, (d, s)| add_row(d, s) | acc)
        };
        if wrapped {
            // Undo (wrapping subtraction is the exact inverse) and name the
            // first pixel that overflowed.
            let mut at = None;
            for (row, ((s, c), (os, oc))) in self.sums[span.clone()]
                .chunks_mut(w)
                .zip(self.counts[span].chunks_mut(w))
                .zip(other.sums.chunks(ow).zip(other.counts.chunks(ow)))
                .enumerate()
            {
                for col in 0..ow {
                    let (a, b) = (&mut s[x0 + col], &os[col]);
                    let mut o = false;
                    for ch in 0..3 {
                        a[ch] = a[ch].wrapping_sub(b[ch]);
                        o |= a[ch].checked_add(b[ch]).is_none();
                    }
                    c[x0 + col] = c[x0 + col].wrapping_sub(oc[col]);
                    o |= c[x0 + col].checked_add(oc[col]).is_none();
                    if o && at.is_none() {
                        at = Some((other.rect.x + col as u32, other.rect.y + row as u32));
                    }
                }
            }
            let (x, y) = at.expect("a wrapped add has a pixel that overflows");
            return Err(FilmError::Overflow { x, y });
        }
        if let (Some(a), Some(b)) = (&mut self.squares, &other.squares) {
            for (d, s) in a[span].chunks_mut(w).zip(b.chunks(ow)) {
                for (a, b) in d[x0..x0 + ow].iter_mut().zip(s) {
                    for ch in 0..3 {
                        a[ch] += b[ch]; // checked above
                    }
                }
            }
        }
        self.rays.add(&other.rays);
        self.nonfinite += other.nonfinite;
        Ok(())
    }

    /// Mean of each pixel's samples, linear RGB, row-major (black where no
    /// sample landed). In parallel: a frame's end waits for it.
    pub fn resolve(&self) -> Vec<[f32; 3]> {
        use rayon::prelude::*;
        self.sums
            .par_iter()
            .zip(&self.counts)
            .with_min_len(4096)
            .map(|(s, &n)| resolve_pixel(s, n))
            .collect()
    }

    /// The resolved film as 8-bit sRGB, in one parallel pass: equal to
    /// `to_srgb8(&self.resolve())`.
    pub fn srgb8(&self) -> Vec<u8> {
        use rayon::prelude::*;
        let mut out = vec![0u8; self.sums.len() * 3];
        out.par_chunks_mut(3)
            .zip(&self.sums)
            .zip(&self.counts)
            .with_min_len(4096)
            .for_each(|((o, s), &n)| {
                let p = resolve_pixel(s, n);
                for c in 0..3 {
                    o[c] = srgb8(p[c]);
                }
            });
        out
    }
}

/// What a pixel's sums of `n` > 0 samples are multiplied by to resolve it:
/// the one definition, which the GPU's resolve to f32 is given rather than
/// computing its own (it has no f64).
#[inline]
pub fn resolve_scale(n: u32) -> f64 {
    1.0 / (n as f64 * FIXED_ONE)
}

/// The mean of one pixel's samples (black without samples).
#[inline]
fn resolve_pixel(s: &[u64; 3], n: u32) -> [f32; 3] {
    if n == 0 {
        [0.0; 3]
    } else {
        let k = resolve_scale(n);
        [
            (s[0] as f64 * k) as f32,
            (s[1] as f64 * k) as f32,
            (s[2] as f64 * k) as f32,
        ]
    }
}

/// For a pixel of `n` samples, the smallest sum (one channel's, in units of
/// 1/[`FIXED_ONE`]) whose 8-bit sRGB code is k + 1, k < 255: a sum's code is
/// how many of these it reaches (the resolve and the encoding are both
/// monotonic). Lets a GPU resolve to exactly [`Film::srgb8`]'s bytes with
/// integer comparisons only.
pub fn srgb8_thresholds(n: u32) -> [u64; 255] {
    assert!(n > 0, "a pixel without samples is black");
    let code = |s: u64| srgb8(resolve_pixel(&[s, 0, 0], n)[0]);
    let mut out = [u64::MAX; 255];
    for (k, t) in out.iter_mut().enumerate() {
        let want = k as u8 + 1;
        if code(u64::MAX) < want {
            break; // unreachable at this n; u64::MAX is never reached either
        }
        let (mut lo, mut hi) = (0u64, u64::MAX);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            if code(mid) >= want {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        *t = lo;
    }
    out
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

/// One linear value as 8-bit sRGB: clamped to [0, 1], encoded, rounded.
/// The definition; [`srgb8`] is the same function through a table.
pub fn srgb8_exact(c: f32) -> u8 {
    (srgb_encode(c) * 255.0 + 0.5) as u8
}

/// Buckets of the sRGB table: the bit pattern of a value in (0, 1) shifted
/// right by this. Each bucket holds at most one of the 255 steps of the
/// 8-bit code (checked when the table is built), so a lookup is one load
/// and one comparison instead of a `powf`.
const SRGB_BUCKET_SHIFT: u32 = 16;

struct SrgbTable {
    /// The code at each bucket's first value.
    base: Vec<u8>,
    /// The first value of the bucket whose code is `base + 1` (infinity
    /// when the code is the same across the bucket).
    step: Vec<f32>,
}

fn srgb_table() -> &'static SrgbTable {
    static TABLE: std::sync::OnceLock<SrgbTable> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let buckets = (1.0f32.to_bits() >> SRGB_BUCKET_SHIFT) as usize;
        let mut base = Vec::with_capacity(buckets);
        let mut step = Vec::with_capacity(buckets);
        for b in 0..buckets as u32 {
            let lo = b << SRGB_BUCKET_SHIFT;
            let hi = ((b + 1) << SRGB_BUCKET_SHIFT) - 1;
            let code = srgb8_exact(f32::from_bits(lo));
            let last = srgb8_exact(f32::from_bits(hi));
            assert!(
                last == code || last == code + 1,
                "sRGB table bucket {b} spans more than one step"
            );
            base.push(code);
            if last == code {
                step.push(f32::INFINITY);
            } else {
                // The first bit pattern of the bucket with the higher code
                // (the encoding is monotonic in the value).
                let (mut a, mut z) = (lo, hi);
                while a < z {
                    let m = a + (z - a) / 2;
                    if srgb8_exact(f32::from_bits(m)) > code {
                        z = m;
                    } else {
                        a = m + 1;
                    }
                }
                step.push(f32::from_bits(a));
            }
        }
        SrgbTable { base, step }
    })
}

/// [`srgb8_exact`] through a table, bit for bit: the image writers' sRGB.
#[inline]
pub fn srgb8(c: f32) -> u8 {
    if !(c > 0.0) {
        return 0; // negative, zero and NaN, as the clamp makes them
    }
    if c >= 1.0 {
        return 255;
    }
    let t = srgb_table();
    let b = (c.to_bits() >> SRGB_BUCKET_SHIFT) as usize;
    t.base[b] + u8::from(c >= t.step[b])
}

/// 8-bit sRGB pixels of a resolved film: clamped to [0, 1], encoded, rounded.
pub fn to_srgb8(linear: &[[f32; 3]]) -> Vec<u8> {
    linear.iter().flat_map(|p| p.map(srgb8)).collect()
}

/// Estimated variance of the mean of one pixel (adaptive sampling,
/// [`crate::adaptive`]), per channel, in radiance
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

impl Film {
    /// The largest of pixel `i`'s three standard errors of the mean (what
    /// an adaptive render's target bounds); an adaptive film only.
    pub fn pixel_error(&self, i: usize) -> f64 {
        let squares = self.squares.as_ref().expect("adaptive film");
        let v = variance_of_mean(self.counts[i], &self.sums[i], &squares[i]);
        v[0].max(v[1]).max(v[2]).sqrt()
    }
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
    fn merge_adds_every_pixel_or_none_on_overflow() {
        // Small (serial) and large (parallel) merges, off the film's origin.
        for (w, h) in [(5, 3), (300, 260)] {
            let mut f = Film::new(Rect::new(10, 20, w + 7, h + 4));
            let mut t = Film::new(Rect::new(13, 22, w, h));
            for (i, (s, c)) in t.sums.iter_mut().zip(&mut t.counts).enumerate() {
                *s = [i as u64, 2 * i as u64 + 1, 7];
                *c = 1 + (i % 3) as u32;
            }
            f.merge(&t).unwrap();
            f.merge(&t).unwrap();
            for y in 0..f.rect.height {
                for x in 0..f.rect.width {
                    let i = (y * f.rect.width + x) as usize;
                    let (tx, ty) = (f.rect.x + x, f.rect.y + y);
                    let inside = (13..13 + w).contains(&tx) && (22..22 + h).contains(&ty);
                    let want = if inside {
                        let j = ((ty - 22) * w + (tx - 13)) as usize;
                        (
                            [2 * j as u64, 2 * (2 * j as u64 + 1), 14],
                            2 * (1 + (j % 3) as u32),
                        )
                    } else {
                        ([0; 3], 0)
                    };
                    assert_eq!((f.sums[i], f.counts[i]), want, "pixel ({tx}, {ty})");
                }
            }
            let before = f.clone();
            let mut big = Film::new(t.rect);
            let last = big.sums.len() - 1;
            big.sums[last][1] = u64::MAX;
            assert_eq!(
                f.merge(&big),
                Err(FilmError::Overflow {
                    x: 13 + w - 1,
                    y: 22 + h - 1
                })
            );
            assert_eq!(f, before, "an overflowing merge leaves the film as it was");
        }
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

    /// Counting the thresholds a sum reaches gives `Film::srgb8`'s code:
    /// at each threshold and one below it, for sample counts whose
    /// reciprocals round differently.
    #[test]
    fn srgb8_thresholds_give_the_resolves_codes() {
        for n in [1, 3, 7, 64, 1000, 65_537] {
            let t = srgb8_thresholds(n);
            assert!(t.windows(2).all(|w| w[0] <= w[1]), "n={n}");
            let code = |s: u64| srgb8(resolve_pixel(&[s, 0, 0], n)[0]);
            let counted = |s: u64| t.iter().filter(|&&x| s >= x).count() as u8;
            for &x in &t {
                for s in [x.saturating_sub(1), x, x.saturating_add(1)] {
                    assert_eq!(counted(s), code(s), "n={n} sum={s}");
                }
            }
            for s in [0, 1, u64::MAX, n as u64 * (1 << 32)] {
                assert_eq!(counted(s), code(s), "n={n} sum={s}");
            }
        }
    }

    #[test]
    fn srgb_endpoints() {
        assert_eq!(to_srgb8(&[[0.0, 1.0, 2.0]]), vec![0, 255, 255]);
        assert_eq!(to_srgb8(&[[0.5, 0.22, f32::NAN]]), vec![188, 129, 0]);
    }

    /// The table gives the defining function's code for every value: all
    /// bit patterns near each of the 255 steps, and a stride through the rest.
    #[test]
    fn the_srgb_table_matches_the_definition_bit_for_bit() {
        let t = srgb_table();
        let mut checked = 0u64;
        let mut check = |c: f32| {
            assert_eq!(srgb8(c), srgb8_exact(c), "value {c:e} ({:#x})", c.to_bits());
            checked += 1;
        };
        for &step in t.step.iter().filter(|s| s.is_finite()) {
            let b = step.to_bits();
            for d in b.saturating_sub(64)..=b + 64 {
                check(f32::from_bits(d));
            }
        }
        for bits in (0..=1.0f32.to_bits() + 1000).step_by(997) {
            check(f32::from_bits(bits));
        }
        for c in [
            -1.0,
            -0.0,
            0.0,
            1.0,
            2.0,
            f32::INFINITY,
            f32::NAN,
            f32::MIN_POSITIVE,
        ] {
            check(c);
        }
        assert_eq!(t.step.iter().filter(|s| s.is_finite()).count(), 255);
        assert!(checked > 1_000_000);
    }

    #[test]
    fn the_parallel_srgb_pass_equals_resolve_then_encode() {
        let mut f = Film::new(Rect::full(300, 200));
        for (i, (s, n)) in f.sums.iter_mut().zip(f.counts.iter_mut()).enumerate() {
            *n = (i % 5) as u32;
            let v = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 29;
            *s = [v, v / 3, v.wrapping_mul(7) >> 2];
        }
        assert_eq!(f.srgb8(), to_srgb8(&f.resolve()));
    }
}
