//! Precision-generic scalar and vector types.
//!
//! The tracer is written once over [`Real`] and instantiated twice: `f32`
//! (the fast path, glam's SIMD `Vec3A`) and `f64` (the reference, glam's
//! `DVec3`). Tests and benchmarks use the `f64` instantiation as ground truth,
//! so both must run the very same code.

use std::fmt::Debug;
use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub};

/// A floating-point scalar the tracer can run in.
pub trait Real:
    Copy
    + Send
    + Sync
    + Debug
    + PartialOrd
    + Default
    + 'static
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
{
    /// The 3-vector of this precision.
    type V3: Vector3<Self>;
    /// Four lanes of this precision, for testing four primitives at once.
    type V4: Lanes4<Self>;

    const ZERO: Self;
    const ONE: Self;
    const TWO: Self;
    const INFINITY: Self;
    /// Relative size of the offset that moves a secondary ray's origin off
    /// the surface it starts on, as a multiple of the hit point's largest
    /// coordinate (a few dozen ulps of that coordinate). See
    /// [`offset_origin`].
    const OFFSET_REL: Self;
    /// Smallest offset, for hit points at (or extremely near) the origin.
    const OFFSET_MIN: Self;
    /// Shadow rays stop this fraction short of the light, so that a light
    /// lying exactly on a surface is not shadowed by that surface.
    const SHADOW_SHORTEN: Self;
    /// Specular terms below this fraction of the light's specular colour are
    /// skipped (not computed with `powf`): 2^-24 in f32, where they cannot
    /// change the colour's value; 0 in the f64 reference, which stays exact.
    const SPECULAR_FLOOR: f64;

    fn from_f64(v: f64) -> Self;
    fn to_f64(self) -> f64;
    fn sqrt(self) -> Self;
    fn abs(self) -> Self;
    fn powf(self, e: Self) -> Self;
    fn max(self, o: Self) -> Self;
    fn min(self, o: Self) -> Self;
    fn is_finite(self) -> bool;
    fn copysign(self, sign: Self) -> Self;
    fn tan(self) -> Self;
    fn exp(self) -> Self;
    fn from_u32(v: u32) -> Self;
}

/// The vector operations the tracer uses, mirrored from glam.
pub trait Vector3<R: Real>:
    Copy
    + Send
    + Sync
    + Debug
    + Default
    + PartialEq
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<R, Output = Self>
    + Mul<Self, Output = Self>
    + Div<R, Output = Self>
    + Neg<Output = Self>
    + AddAssign
{
    fn new(x: R, y: R, z: R) -> Self;
    fn splat(v: R) -> Self;
    fn x(self) -> R;
    fn y(self) -> R;
    fn z(self) -> R;
    fn dot(self, o: Self) -> R;
    fn cross(self, o: Self) -> Self;
    fn length(self) -> R;
    fn length_squared(self) -> R;
    fn abs(self) -> Self;
    fn max_element(self) -> R;
    fn min_element(self) -> R;
    /// Component-wise minimum and maximum (bounding-box tests).
    fn min(self, o: Self) -> Self;
    fn max(self, o: Self) -> Self;
    fn is_finite(self) -> bool;

    fn zero() -> Self {
        Self::splat(R::ZERO)
    }
    fn normalize(self) -> Self {
        self * (R::ONE / self.length())
    }
    fn from_array(a: [f64; 3]) -> Self {
        Self::new(R::from_f64(a[0]), R::from_f64(a[1]), R::from_f64(a[2]))
    }
    fn to_array(self) -> [f64; 3] {
        [self.x().to_f64(), self.y().to_f64(), self.z().to_f64()]
    }
}

/// Four lanes of scalars (glam's `Vec4`, SSE2 on x86-64, and `DVec4`).
pub trait Lanes4<R: Real>:
    Copy
    + Send
    + Sync
    + Debug
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    type Mask: Copy + std::ops::BitAnd<Output = Self::Mask> + std::ops::BitOr<Output = Self::Mask>;
    fn splat(v: R) -> Self;
    fn from_array(a: [R; 4]) -> Self;
    fn to_array(self) -> [R; 4];
    fn sqrt(self) -> Self;
    fn min(self, o: Self) -> Self;
    fn max(self, o: Self) -> Self;
    fn copysign(self, sign: Self) -> Self;
    fn cmpge(self, o: Self) -> Self::Mask;
    fn cmpgt(self, o: Self) -> Self::Mask;
    fn cmplt(self, o: Self) -> Self::Mask;
    fn select(mask: Self::Mask, a: Self, b: Self) -> Self;
    /// Bit i set when lane i of the mask is.
    fn bitmask(mask: Self::Mask) -> u32;
    /// Mask with only lane `i` set (none when i >= 4).
    fn lane(i: usize) -> Self::Mask;
}

macro_rules! impl_lanes {
    ($t:ty, $v:ty, $m:ty) => {
        impl Lanes4<$t> for $v {
            type Mask = $m;
            #[inline(always)]
            fn splat(v: $t) -> Self {
                <$v>::splat(v)
            }
            #[inline(always)]
            fn from_array(a: [$t; 4]) -> Self {
                <$v>::from_array(a)
            }
            #[inline(always)]
            fn to_array(self) -> [$t; 4] {
                <$v>::to_array(&self)
            }
            #[inline(always)]
            fn sqrt(self) -> Self {
                <$v>::sqrt(self)
            }
            #[inline(always)]
            fn min(self, o: Self) -> Self {
                <$v>::min(self, o)
            }
            #[inline(always)]
            fn max(self, o: Self) -> Self {
                <$v>::max(self, o)
            }
            #[inline(always)]
            fn copysign(self, sign: Self) -> Self {
                <$v>::copysign(self, sign)
            }
            #[inline(always)]
            fn cmpge(self, o: Self) -> $m {
                <$v>::cmpge(self, o)
            }
            #[inline(always)]
            fn cmpgt(self, o: Self) -> $m {
                <$v>::cmpgt(self, o)
            }
            #[inline(always)]
            fn cmplt(self, o: Self) -> $m {
                <$v>::cmplt(self, o)
            }
            #[inline(always)]
            fn select(mask: $m, a: Self, b: Self) -> Self {
                <$v>::select(mask, a, b)
            }
            #[inline(always)]
            fn bitmask(mask: $m) -> u32 {
                mask.bitmask()
            }
            #[inline(always)]
            fn lane(i: usize) -> $m {
                <$m>::new(i == 0, i == 1, i == 2, i == 3)
            }
        }
    };
}
impl_lanes!(f32, glam::Vec4, glam::BVec4A);
impl_lanes!(f64, glam::DVec4, glam::BVec4);

macro_rules! impl_real {
    ($t:ty, $v:ty, $v4:ty, $rel:expr, $min:expr, $shadow:expr, $spec:expr) => {
        impl Real for $t {
            type V3 = $v;
            type V4 = $v4;
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
            const TWO: Self = 2.0;
            const INFINITY: Self = <$t>::INFINITY;
            const OFFSET_REL: Self = $rel;
            const OFFSET_MIN: Self = $min;
            const SHADOW_SHORTEN: Self = $shadow;
            const SPECULAR_FLOOR: f64 = $spec;
            #[inline(always)]
            fn from_f64(v: f64) -> Self {
                v as $t
            }
            #[inline(always)]
            fn to_f64(self) -> f64 {
                self as f64
            }
            #[inline(always)]
            fn sqrt(self) -> Self {
                <$t>::sqrt(self)
            }
            #[inline(always)]
            fn abs(self) -> Self {
                <$t>::abs(self)
            }
            #[inline(always)]
            fn powf(self, e: Self) -> Self {
                <$t>::powf(self, e)
            }
            #[inline(always)]
            fn max(self, o: Self) -> Self {
                <$t>::max(self, o)
            }
            #[inline(always)]
            fn min(self, o: Self) -> Self {
                <$t>::min(self, o)
            }
            #[inline(always)]
            fn is_finite(self) -> bool {
                <$t>::is_finite(self)
            }
            #[inline(always)]
            fn copysign(self, sign: Self) -> Self {
                <$t>::copysign(self, sign)
            }
            #[inline(always)]
            fn tan(self) -> Self {
                <$t>::tan(self)
            }
            #[inline(always)]
            fn exp(self) -> Self {
                <$t>::exp(self)
            }
            #[inline(always)]
            fn from_u32(v: u32) -> Self {
                v as $t
            }
        }

        impl Vector3<$t> for $v {
            #[inline(always)]
            fn new(x: $t, y: $t, z: $t) -> Self {
                <$v>::new(x, y, z)
            }
            #[inline(always)]
            fn splat(v: $t) -> Self {
                <$v>::splat(v)
            }
            #[inline(always)]
            fn x(self) -> $t {
                self.x
            }
            #[inline(always)]
            fn y(self) -> $t {
                self.y
            }
            #[inline(always)]
            fn z(self) -> $t {
                self.z
            }
            #[inline(always)]
            fn dot(self, o: Self) -> $t {
                <$v>::dot(self, o)
            }
            #[inline(always)]
            fn cross(self, o: Self) -> Self {
                <$v>::cross(self, o)
            }
            #[inline(always)]
            fn length(self) -> $t {
                <$v>::length(self)
            }
            #[inline(always)]
            fn length_squared(self) -> $t {
                <$v>::length_squared(self)
            }
            #[inline(always)]
            fn abs(self) -> Self {
                <$v>::abs(self)
            }
            #[inline(always)]
            fn max_element(self) -> $t {
                <$v>::max_element(self)
            }
            #[inline(always)]
            fn min_element(self) -> $t {
                <$v>::min_element(self)
            }
            #[inline(always)]
            fn min(self, o: Self) -> Self {
                <$v>::min(self, o)
            }
            #[inline(always)]
            fn max(self, o: Self) -> Self {
                <$v>::max(self, o)
            }
            #[inline(always)]
            fn is_finite(self) -> bool {
                <$v>::is_finite(self)
            }
        }
    };
}

// f32: offsets of 2^-18 of the coordinate (32 ulps); f64: 2^-44 (512 ulps).
impl_real!(
    f32,
    glam::Vec3A,
    glam::Vec4,
    3.814_697_3e-6,
    1.0e-30,
    1.0e-4,
    5.960_464_477_539_063e-8
);
impl_real!(
    f64,
    glam::DVec3,
    glam::DVec4,
    5.684_341_886_080_802e-14,
    1.0e-290,
    1.0e-9,
    0.0
);

/// Moves a point that lies on a surface off it, to the side `n` points to.
///
/// The offset scales with the point's magnitude: a fixed epsilon is either
/// too small far from the origin (acne) or too large near it (light leaks,
/// tiny objects lost). Scenes are built camera-relative, so points near the
/// camera have small coordinates and get small offsets.
#[inline(always)]
pub fn offset_origin<R: Real>(p: R::V3, n: R::V3) -> R::V3 {
    let scale = p.abs().max_element() * R::OFFSET_REL + R::OFFSET_MIN;
    p + n * scale
}

/// A ray with a unit-length direction.
#[derive(Clone, Copy, Debug)]
pub struct Ray<R: Real> {
    pub origin: R::V3,
    pub dir: R::V3,
}

impl<R: Real> Ray<R> {
    #[inline(always)]
    pub fn new(origin: R::V3, dir: R::V3) -> Self {
        Self { origin, dir }
    }
    #[inline(always)]
    pub fn at(&self, t: R) -> R::V3 {
        self.origin + self.dir * t
    }
}
