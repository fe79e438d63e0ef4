//! Where in a pixel each sample goes, deterministically.
//!
//! Every random number is a pure function of (pixel, sample index, frame,
//! dimension; and the sample count, for stratified ones), computed with
//! 32-bit integer hashing only, so the CPU (f32 and f64) and the GPU (WGSL
//! has `u32` but no `u64`) produce the same positions, and any tile or
//! sample range traced anywhere gives the same values.
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

/// Division and remainder by a number fixed for a whole render, as
/// multiplications (Lemire, Kaser and Kurz 2019, "Faster remainder by
/// direct computation"): exact for every `u32` numerator. The path
/// integrator deals a stratified cell at every vertex, two pairs a vertex,
/// and an integer division costs it ~25 cycles where this costs ~4.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Divisor {
    d: u32,
    /// ceil(2^64 / d); 0 for d = 1 (2^64 does not fit, and 0 gives the
    /// remainder 0).
    m: u64,
}

impl Divisor {
    /// `d` > 0.
    pub fn new(d: u32) -> Self {
        assert!(d > 0, "a divisor is positive");
        let m = if d == 1 { 0 } else { u64::MAX / d as u64 + 1 };
        Divisor { d, m }
    }
    #[inline(always)]
    pub fn get(self) -> u32 {
        self.d
    }
    /// `a / d`.
    #[inline(always)]
    pub fn quotient(self, a: u32) -> u32 {
        if self.d == 1 {
            a
        } else {
            ((self.m as u128 * a as u128) >> 64) as u32
        }
    }
    /// `a % d`.
    #[inline(always)]
    pub fn remainder(self, a: u32) -> u32 {
        let low = self.m.wrapping_mul(a as u64);
        ((low as u128 * self.d as u128) >> 64) as u32
    }
}

/// Element `i` of the permutation of [0, n) that `seed` picks (Kensler
/// 2013, "Correlated Multi-Jittered Sampling", `permute`): integer hashing
/// of i within the next power of two, repeated until it lands below n.
#[inline]
pub fn permute(i: u32, n: Divisor, seed: u32) -> u32 {
    let mut w = n.get() - 1;
    w |= w >> 1;
    w |= w >> 2;
    w |= w >> 4;
    w |= w >> 8;
    w |= w >> 16;
    let mut i = i;
    loop {
        i ^= seed;
        i = i.wrapping_mul(0xe170_893d);
        i ^= seed >> 16;
        i ^= (i & w) >> 4;
        i ^= seed >> 8;
        i = i.wrapping_mul(0x0929_eb3f);
        i ^= seed >> 23;
        i ^= (i & w) >> 1;
        i = i.wrapping_mul(1 | seed >> 27);
        i = i.wrapping_mul(0x6935_fa69);
        i ^= (i & w) >> 11;
        i = i.wrapping_mul(0x74dc_b303);
        i ^= (i & w) >> 2;
        i = i.wrapping_mul(0x9e50_1cc3);
        i ^= (i & w) >> 2;
        i = i.wrapping_mul(0xc860_a3df);
        i &= w;
        i ^= i >> 5;
        if i < n.get() {
            break;
        }
    }
    n.remainder(i.wrapping_add(seed))
}

/// The grid a render's pairs are stratified over ([`uniform_pair`]): its
/// side (`strata_side`) and its cell count as [`Divisor`]s, set up once a
/// tile rather than at every pair; `None`: no strata.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Strata(Option<(Divisor, Divisor)>);

impl Strata {
    /// The side x side grid; 0: none.
    pub fn new(side: u32) -> Self {
        Strata((side > 0).then(|| (Divisor::new(side), Divisor::new(side * side))))
    }
}

/// The side of the grid a render's samples are stratified over (pixel
/// positions, [`sample_offset`]; the path integrator's pairs,
/// [`uniform_pair`]): the square root of a square sample count, except for
/// the progressive sampler (whose counts are open-ended); 0: no strata.
/// The GPU's `FrameUniform::grid_n`.
pub fn strata_side(sampler: Sampler, count: u32) -> u32 {
    match sampler {
        Sampler::Progressive => 0,
        Sampler::Grid | Sampler::Jittered => exact_sqrt(count).unwrap_or(0),
    }
}

/// The largest f32 below 1.
const BELOW_ONE: f32 = 1.0 - 1.0 / 16_777_216.0;

/// Two numbers in [0, 1) for dimensions `dim` and `dim + 1` of sample
/// `sample`: over a grid (`strata`, of side^2 cells, the sample count
/// being side^2: [`strata_side`]) the pixel's samples take one cell each,
/// dealt out by a permutation drawn per pixel and pair ([`permute`]), at a
/// uniform point inside it (stratified sampling, as Mitsuba's `stratified`
/// sampler); without, `uniform` of each dimension.
#[inline]
pub fn uniform_pair(seed: u32, sample: u32, strata: Strata, dim: u32) -> (f32, f32) {
    let (u, v) = (uniform(seed, sample, dim), uniform(seed, sample, dim + 1));
    let Strata(Some((side, cells))) = strata else {
        return (u, v);
    };
    let cell = permute(sample, cells, hash_u32(seed ^ hash_u32(dim ^ 0x0b5c_9d2f)));
    let n = side.get() as f32;
    (
        ((side.remainder(cell) as f32 + u) / n).min(BELOW_ONE),
        ((side.quotient(cell) as f32 + v) / n).min(BELOW_ONE),
    )
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

/// Taylor coefficients (-1)^k / (2k+1)! of sin a / a and (-1)^k / (2k)!
/// of cos a, as powers of a^2: on [-pi/4, pi/4] the first terms left out
/// are below 1e-16.
const SIN_TAYLOR: [f64; 8] = taylor(1);
const COS_TAYLOR: [f64; 9] = taylor(0);

const fn taylor<const N: usize>(first: u64) -> [f64; N] {
    let mut c = [0.0; N];
    // fact = n! for n = first + 2k.
    let (mut k, mut fact, mut n) = (0, 1.0f64, first);
    while k < N {
        c[k] = if k % 2 == 0 { 1.0 / fact } else { -1.0 / fact };
        fact *= ((n + 1) * (n + 2)) as f64;
        n += 2;
        k += 1;
    }
    c
}

/// (sin, cos) of 2 pi x from + - * only (no libm), so every machine gets
/// the same bits; absolute error below 1e-15. Branch-free (the path
/// integrator calls it at every bounce with a random `x`, where a jump on
/// the quadrant would be mispredicted): the nearest quarter turn q, then
/// polynomials of the remaining angle in [-pi/4, pi/4], swapped and
/// negated by q.
#[inline]
pub fn sin_cos_turns(x: f64) -> (f64, f64) {
    // Quarter turns to the nearest multiple; |x| below 2^60 turns.
    let q4 = x * 4.0;
    let t = q4 as i64;
    let f = q4 - t as f64; // in (-1, 1)
    let q = t + (f >= 0.5) as i64 - (f < -0.5) as i64;
    let a = (q4 - q as f64) * std::f64::consts::FRAC_PI_2;
    let a2 = a * a;
    let mut s = SIN_TAYLOR[7];
    for &k in SIN_TAYLOR[..7].iter().rev() {
        s = s * a2 + k;
    }
    let mut c = COS_TAYLOR[8];
    for &k in COS_TAYLOR[..8].iter().rev() {
        c = c * a2 + k;
    }
    let s = s * a;
    // angle = q pi/2 + a: quadrant 1 (sin, cos) = (c, -s), 2 (-s, -c), 3 (-c, s).
    let q = q & 3;
    let (sin, cos) = if q & 1 == 1 { (c, s) } else { (s, c) };
    let sin = if q >= 2 { -sin } else { sin };
    let cos = if q == 1 || q == 2 { -cos } else { cos };
    (sin, cos)
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
    match strata_side(sampler, count) {
        n if n > 0 => {
            let (i, j) = (sample % n, sample / n);
            let (jx, jy) = match sampler {
                Sampler::Grid => (0.5, 0.5),
                Sampler::Jittered | Sampler::Progressive => {
                    (uniform(seed, sample, 0), uniform(seed, sample, 1))
                }
            };
            ((i as f32 + jx) / n as f32, (j as f32 + jy) / n as f32)
        }
        _ => {
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

    /// A divisor's multiplications give `/` and `%` exactly: every divisor
    /// up to 2^12 and some large ones, against numerators at the edges and
    /// hashed ones.
    #[test]
    fn a_divisor_divides_as_the_operators_do() {
        let big = [
            65_535,
            65_536,
            65_537,
            1 << 31,
            (1 << 31) + 1,
            u32::MAX - 1,
            u32::MAX,
        ];
        for d in (1..=4096u32).chain(big) {
            let div = Divisor::new(d);
            let edges = [0, 1, d - 1, d, d.wrapping_add(1), u32::MAX - 1, u32::MAX];
            for a in edges.into_iter().chain((0..64).map(|k| hash_u32(d ^ k))) {
                assert_eq!(div.quotient(a), a / d, "{a} / {d}");
                assert_eq!(div.remainder(a), a % d, "{a} % {d}");
            }
        }
    }

    #[test]
    fn permute_is_a_permutation_for_any_count() {
        for n in 1..=70u32 {
            for seed in [0, 1, 0x9e37_79b9, hash_u32(n)] {
                let mut seen = vec![false; n as usize];
                for i in 0..n {
                    let p = permute(i, Divisor::new(n), seed) as usize;
                    assert!(p < n as usize && !seen[p], "n {n} seed {seed}: {i} -> {p}");
                    seen[p] = true;
                }
            }
        }
    }

    /// A pixel's side^2 samples take one cell each of the side x side
    /// grid, in an order that differs between pixels and between pairs;
    /// without strata the pair is `uniform`'s two numbers.
    #[test]
    fn uniform_pair_puts_one_sample_in_each_cell() {
        for side in [1u32, 2, 4, 16] {
            let n = side * side;
            let mut orders = std::collections::HashSet::new();
            for (seed, dim) in [
                (pixel_seed(3, 5, 0), 100),
                (pixel_seed(4, 5, 0), 100),
                (pixel_seed(3, 5, 0), 200),
            ] {
                let mut seen = vec![false; n as usize];
                let mut order = vec![];
                for k in 0..n {
                    let (u, v) = uniform_pair(seed, k, Strata::new(side), dim);
                    assert!((0.0..1.0).contains(&u) && (0.0..1.0).contains(&v));
                    let cell = (v * side as f32) as u32 * side + (u * side as f32) as u32;
                    assert!(
                        !seen[cell as usize],
                        "side {side}: two samples in cell {cell}"
                    );
                    seen[cell as usize] = true;
                    order.push(cell);
                }
                orders.insert(order);
            }
            if side >= 4 {
                assert_eq!(orders.len(), 3, "side {side}: orders repeat");
            }
            assert_eq!(
                uniform_pair(7, 3, Strata::new(0), 40),
                (uniform(7, 3, 40), uniform(7, 3, 41))
            );
        }
        assert_eq!(strata_side(Sampler::Jittered, 64), 8);
        assert_eq!(strata_side(Sampler::Grid, 16), 4);
        assert_eq!(strata_side(Sampler::Jittered, 32), 0);
        assert_eq!(strata_side(Sampler::Progressive, 64), 0);
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
