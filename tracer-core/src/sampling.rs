//! Where in a pixel each sample goes, deterministically.
//!
//! Every random number is a pure function of (pixel, sample index, frame,
//! dimension), computed with 32-bit integer hashing only, so the CPU (f32 and
//! f64) and the GPU (WGSL has `u32` but no `u64`) produce the same positions,
//! and any tile or sample range traced anywhere gives the same values.
//! Keep in sync with `render/gpu/sampling.wgsl`.

use serde::{Deserialize, Serialize};

use crate::math::{Real, Vector3};

/// How sample positions are placed inside a pixel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Sampler {
    /// The thesis's regular n x n grid: sample (i, j) at ((i+0.5)/n, (j+0.5)/n).
    /// Needs a square sample count; other counts fall back to [`Sampler::Jittered`]'s
    /// low-discrepancy pattern.
    #[default]
    Grid,
    /// Stratified jitter: one uniformly random point in each cell of the
    /// n x n grid for square counts; a per-pixel rotated R2 sequence otherwise.
    Jittered,
    /// Low-discrepancy points (a per-pixel rotated R2 sequence) for every
    /// count: sample k of a pixel does not depend on the sample count, so
    /// the first k samples of a render are a well-spread set of their own.
    /// Adaptive sampling (`crate::adaptive`) places samples this way.
    Progressive,
}

impl Sampler {
    pub fn name(self) -> &'static str {
        match self {
            Sampler::Grid => "grid",
            Sampler::Jittered => "jittered",
            Sampler::Progressive => "progressive",
        }
    }
}

impl std::str::FromStr for Sampler {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "grid" => Ok(Sampler::Grid),
            "jittered" => Ok(Sampler::Jittered),
            "progressive" => Ok(Sampler::Progressive),
            _ => Err(format!(
                "unknown sampler {s:?}: expected \"grid\", \"jittered\" or \"progressive\""
            )),
        }
    }
}

/// A 32-bit integer mixer (Chris Wellons' "lowbias32"): good avalanche, cheap, and
/// identical on every backend.
#[inline(always)]
pub fn hash_u32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

/// The per-pixel, per-frame seed all of a pixel's random numbers derive from.
#[inline(always)]
pub fn pixel_seed(x: u32, y: u32, frame: u32) -> u32 {
    hash_u32(x ^ hash_u32(y ^ hash_u32(frame.wrapping_add(0x9e37_79b9))))
}

/// Uniform number in [0, 1) for (pixel seed, sample index, dimension), with 24
/// bits so it is exact in `f32` and `f64` alike.
#[inline(always)]
pub fn uniform(seed: u32, sample: u32, dim: u32) -> f32 {
    let h = hash_u32(seed ^ hash_u32(sample.wrapping_mul(0x68e3_1da4) ^ hash_u32(dim)));
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// Random-number dimensions of distributed ray tracing (see
/// `docs/scene-format.md`, "Random numbers"). 0 and 1 place the sample in
/// its pixel; the camera takes [`DIM_LENS`] (two) and [`DIM_TIME`]; every
/// node of a sample's ray tree has a key ([`ROOT_KEY`] for the camera ray's
/// hit, [`child_key`] below it) and draws its own numbers from
/// [`node_dim`]`(key, slot)`.
pub const DIM_LENS: u32 = 2;
pub const DIM_TIME: u32 = 4;
/// Key of the camera ray's hit.
pub const ROOT_KEY: u32 = 1;
/// Slots of a node: the glossy reflection's two numbers, the translucent
/// refraction's two, then two per light sample (lights in file order, each
/// light's samples in order).
pub const SLOT_GLOSS: u32 = 0;
pub const SLOT_TRANSLUCENCY: u32 = 2;
pub const SLOT_LIGHTS: u32 = 4;
/// Slots of a path vertex (the path integrator's; a vertex's key is its
/// predecessor's `child_key(key, 1)`): the light chosen, the two numbers
/// of its point, the BSDF lobe, the two of its direction, Russian roulette.
pub const SLOT_PATH_LIGHT: u32 = 0;
pub const SLOT_PATH_LOBE: u32 = 3;
pub const SLOT_PATH_RR: u32 = 6;
/// Child of a node: `which` 0 for the refracted ray, 1 for the reflected one.
#[inline(always)]
pub fn child_key(key: u32, which: u32) -> u32 {
    hash_u32(key.wrapping_mul(2).wrapping_add(which) ^ 0x2c1b_3c6d)
}
/// Dimension of `slot` at the node with key `key`.
#[inline(always)]
pub fn node_dim(key: u32, slot: u32) -> u32 {
    hash_u32(key ^ 0x297a_2d39).wrapping_add(slot)
}

/// Sample `i` of `n` stratified over the unit square, from two uniform
/// numbers: the cell (i mod m, i div m) of an m x m grid when n = m^2,
/// else the i-th of n strips in the first coordinate.
#[inline]
pub fn stratified(i: u32, n: u32, u1: f32, u2: f32) -> (f64, f64) {
    let (u1, u2) = (u1 as f64, u2 as f64);
    match exact_sqrt(n) {
        Some(m) => (
            ((i % m) as f64 + u1) / m as f64,
            ((i / m) as f64 + u2) / m as f64,
        ),
        None => ((i as f64 + u1) / n as f64, u2),
    }
}

/// (sin, cos) of 2 pi x from + - * / only (no libm), so every machine gets
/// the same bits; absolute error below 1e-15.
pub fn sin_cos_turns(x: f64) -> (f64, f64) {
    // Reduce to [0, 1) turns, then to an eighth of a turn.
    let x = x - x.floor();
    let x8 = x * 8.0;
    let oct = (x8.floor() as i32).clamp(0, 7);
    let r = (x8 - oct as f64) * 0.125; // [0, 1/8) turns
    // angle in [0, pi/4): Taylor series to order 17 and 18.
    let a = r * std::f64::consts::TAU;
    let a2 = a * a;
    let (mut s, mut c) = (0.0f64, 0.0f64);
    for k in (0..9).rev() {
        // s = sum (-1)^k a^(2k+1)/(2k+1)!, c = sum (-1)^k a^(2k)/(2k)!
        let sk = (2 * k + 2) as f64 * (2 * k + 3) as f64;
        let ck = (2 * k + 1) as f64 * (2 * k + 2) as f64;
        s = 1.0 - a2 / sk * s;
        c = 1.0 - a2 / ck * c;
    }
    let s = s * a;
    // Octant symmetries: angle = oct * pi/4 + a.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    match oct {
        0 => (s, c),
        1 => (h * (s + c), h * (c - s)),
        2 => (c, -s),
        3 => (h * (c - s), -h * (s + c)),
        4 => (-s, -c),
        5 => (-h * (s + c), h * (s - c)),
        6 => (-c, s),
        _ => (h * (s - c), h * (s + c)),
    }
}

/// Integer square root if `n` is a perfect square.
pub fn exact_sqrt(n: u32) -> Option<u32> {
    let r = (n as f64).sqrt().round() as u32;
    (r * r == n).then_some(r)
}

// R2 sequence step (Roberts 2018), as 0.32 fixed point.
const R2_A1: u32 = 3_242_174_889; // 0.7548776662466927 * 2^32
const R2_A2: u32 = 2_447_445_413; // 0.5698402909980532 * 2^32

/// Whether [`sample_offset`] ignores the pixel seed for this sampler and
/// count (the regular grid), so that a renderer may compute each sample's
/// offset once for all pixels.
pub fn same_in_every_pixel(sampler: Sampler, count: u32) -> bool {
    sampler == Sampler::Grid && exact_sqrt(count).is_some()
}

/// Offset of sample `sample` (of `count`) inside its pixel, each coordinate in [0, 1).
#[inline]
pub fn sample_offset(sampler: Sampler, count: u32, seed: u32, sample: u32) -> (f32, f32) {
    let grid = match sampler {
        Sampler::Progressive => None,
        Sampler::Grid | Sampler::Jittered => exact_sqrt(count),
    };
    match grid {
        Some(n) => {
            let (i, j) = (sample % n, sample / n);
            let (jx, jy) = match sampler {
                Sampler::Grid => (0.5, 0.5),
                Sampler::Jittered | Sampler::Progressive => {
                    (uniform(seed, sample, 0), uniform(seed, sample, 1))
                }
            };
            ((i as f32 + jx) / n as f32, (j as f32 + jy) / n as f32)
        }
        None => {
            // Low-discrepancy points, rotated per pixel so neighbours decorrelate.
            let rx = hash_u32(seed ^ 0x5bd1_e995);
            let ry = hash_u32(seed ^ 0x1b87_3593);
            let u = sample.wrapping_mul(R2_A1).wrapping_add(rx);
            let v = sample.wrapping_mul(R2_A2).wrapping_add(ry);
            (
                (u >> 8) as f32 * (1.0 / 16_777_216.0),
                (v >> 8) as f32 * (1.0 / 16_777_216.0),
            )
        }
    }
}

/// A direction uniformly distributed by solid angle in the cone of
/// cosine `cos_max` around the unit `axis`, from two uniform numbers.
pub fn cone<R: Real>(axis: R::V3, cos_max: R, u1: f32, u2: f32) -> R::V3 {
    let cos_t = R::ONE - R::from_f64(u1 as f64) * (R::ONE - cos_max);
    let sin_t = (R::ONE - cos_t * cos_t).max(R::ZERO).sqrt();
    let (sp, cp) = sin_cos_turns(u2 as f64);
    // Orthonormal basis around the axis (Duff et al. 2017), branch-free.
    let [x, y, z] = axis.to_array().map(R::from_f64);
    let sign = R::ONE.copysign(z);
    let a = -R::ONE / (sign + z);
    let b = x * y * a;
    let t1 = R::V3::new(R::ONE + sign * x * x * a, sign * b, -sign * x);
    let t2 = R::V3::new(b, sign + y * y * a, -y);
    (t1 * (sin_t * R::from_f64(cp)) + t2 * (sin_t * R::from_f64(sp)) + axis * cos_t).normalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_matches_thesis_layout() {
        // 2x2 grid: (0.25,0.25), (0.75,0.25), (0.25,0.75), (0.75,0.75)
        let pts: Vec<_> = (0..4)
            .map(|s| sample_offset(Sampler::Grid, 4, 7, s))
            .collect();
        assert_eq!(
            pts,
            vec![(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)]
        );
        assert_eq!(sample_offset(Sampler::Grid, 1, 7, 0), (0.5, 0.5));
    }

    #[test]
    fn same_in_every_pixel_means_seed_ignored() {
        for (sampler, count) in [
            (Sampler::Grid, 4),
            (Sampler::Grid, 9),
            (Sampler::Grid, 8),
            (Sampler::Jittered, 4),
            (Sampler::Jittered, 8),
        ] {
            let same = (0..count).all(|s| {
                (0..50).all(|p| {
                    sample_offset(sampler, count, pixel_seed(p, 3 * p, 0), s)
                        == sample_offset(sampler, count, 0, s)
                })
            });
            assert_eq!(
                same_in_every_pixel(sampler, count),
                same,
                "{sampler:?} {count}"
            );
        }
    }

    #[test]
    fn jitter_stays_in_its_stratum_and_is_deterministic() {
        for s in 0..9 {
            let (u, v) = sample_offset(Sampler::Jittered, 9, pixel_seed(3, 4, 0), s);
            let (i, j) = (s % 3, s / 3);
            assert!(
                u >= i as f32 / 3.0 && u < (i + 1) as f32 / 3.0,
                "{u} not in column {i}"
            );
            assert!(
                v >= j as f32 / 3.0 && v < (j + 1) as f32 / 3.0,
                "{v} not in row {j}"
            );
            assert_eq!(
                (u, v),
                sample_offset(Sampler::Jittered, 9, pixel_seed(3, 4, 0), s)
            );
        }
        // A different frame moves the jitter.
        assert_ne!(
            sample_offset(Sampler::Jittered, 9, pixel_seed(3, 4, 0), 0),
            sample_offset(Sampler::Jittered, 9, pixel_seed(3, 4, 1), 0)
        );
    }

    #[test]
    fn non_square_counts_cover_the_pixel() {
        let pts: Vec<_> = (0..8)
            .map(|s| sample_offset(Sampler::Grid, 8, pixel_seed(1, 2, 0), s))
            .collect();
        for &(u, v) in &pts {
            assert!((0.0..1.0).contains(&u) && (0.0..1.0).contains(&v));
        }
        // R2 points are well spread: every quadrant gets at least one of eight.
        for q in 0..4 {
            let (qx, qy) = ((q % 2) as f32 * 0.5, (q / 2) as f32 * 0.5);
            assert!(
                pts.iter()
                    .any(|&(u, v)| u >= qx && u < qx + 0.5 && v >= qy && v < qy + 0.5),
                "quadrant {q} empty: {pts:?}"
            );
        }
    }

    #[test]
    fn progressive_samples_do_not_depend_on_the_count() {
        let seed = pixel_seed(5, 9, 2);
        for count in [1, 2, 4, 16, 64, 1000, 1024] {
            for k in 0..count.min(64) {
                assert_eq!(
                    sample_offset(Sampler::Progressive, count, seed, k),
                    sample_offset(Sampler::Progressive, 65_536, seed, k),
                    "count {count} sample {k}"
                );
            }
        }
        // The non-square fallback of the other samplers is the same sequence.
        assert_eq!(
            sample_offset(Sampler::Progressive, 16, seed, 3),
            sample_offset(Sampler::Grid, 8, seed, 3)
        );
    }

    #[test]
    fn sin_cos_turns_matches_libm() {
        for k in 0..=100_000 {
            let x = k as f64 / 100_000.0 * 3.0 - 1.0;
            let (s, c) = sin_cos_turns(x);
            let a = x * std::f64::consts::TAU;
            assert!((s - a.sin()).abs() < 1e-14, "sin {x}: {s} vs {}", a.sin());
            assert!((c - a.cos()).abs() < 1e-14, "cos {x}: {c} vs {}", a.cos());
        }
    }

    #[test]
    fn stratified_points_stay_in_their_cells() {
        for n in [1, 2, 4, 5, 9] {
            for i in 0..n {
                let (u, v) = stratified(i, n, 0.999, 0.0);
                assert!((0.0..1.0).contains(&u) && (0.0..1.0).contains(&v));
                let (u0, _) = stratified(i, n, 0.0, 0.0);
                assert!(u0 <= u);
            }
        }
    }

    #[test]
    fn uniform_is_roughly_uniform() {
        let n = 100_000;
        let mean: f64 = (0..n).map(|s| uniform(12345, s, 0) as f64).sum::<f64>() / n as f64;
        assert!((mean - 0.5).abs() < 0.005, "mean {mean}");
    }
}
