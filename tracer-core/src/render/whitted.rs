//! The thesis's Whitted model, exactly as the scene-format contract states it:
//!
//! colour = ambient * m.ambient
//!        + sum over unblocked lights (max(N.L,0) l.diffuse m.diffuse + max(N.H,0)^shininess l.specular m.specular)
//!        + reflectivity * reflected + transparency * refracted
//!
//! with total internal reflection sending the transparency weight to the
//! reflected ray, and `max_depth` bounding the generations of secondary rays.
//! Generic over precision: `f32` is the fast path, `f64` the reference.
//!
//! This recursive form is the simple reference. The CPU stream renderer
//! (`cpu::shade`) does the same arithmetic lane-wise over many hits; tests
//! check that they agree.

use std::any::TypeId;

use crate::film::RayCounts;
use crate::geometry::PrimId;
use crate::math::{Ray, Real, Vector3, offset_origin};
use crate::world::{PointLight, World};

/// Colour seen along `ray`, which starts on primitive `skip` (or none) and
/// is of generation `depth` (primary rays are 0).
pub fn trace<R: Real>(
    world: &World<R>,
    ray: &Ray<R>,
    depth: u32,
    skip: PrimId,
    rays: &mut RayCounts,
) -> R::V3 {
    shade(world, ray, world.closest_hit(ray, skip), depth, rays)
}

/// Colour seen along `ray` of generation `depth`, given its closest hit
/// (`World::closest_hit`, or the same answer from `World::closest_hits`).
pub fn shade<R: Real>(
    world: &World<R>,
    ray: &Ray<R>,
    hit: Option<(R, PrimId)>,
    depth: u32,
    rays: &mut RayCounts,
) -> R::V3 {
    let Some(hit) = hit else {
        return world.background;
    };
    let s = Surface::at(world, ray, hit);
    let mut colour = s.ambient(world);
    for light in &world.lights {
        if let Some(l) = s.light(world, light) {
            rays.shadow += 1;
            if !world.occluded(&l.shadow, l.t_max, s.id) {
                colour += l.contrib;
            }
        }
    }
    s.add_secondary(world, depth, rays, &mut colour);
    colour
}

/// What shading needs of a hit: the point, the normals facing the viewer,
/// the material. The steps of [`shade`] are its methods, so that a caller
/// can trace the shadow rays of many hits together (the CPU renderer does,
/// for camera rays) and still add every term in `shade`'s order.
pub struct Surface<R: Real> {
    pub id: PrimId,
    p: R::V3,
    /// Geometric normal on the viewer's side, and the shading normal.
    n: R::V3,
    ns: R::V3,
    v: R::V3,
    entering: bool,
    cos_i: R,
    material: u32,
    /// Origin for rays leaving on the viewer's side.
    above: R::V3,
}

/// A light's term at a surface: what it adds unless `shadow` (which starts
/// on the surface) meets something before `t_max`.
pub struct LightTerm<R: Real> {
    pub contrib: R::V3,
    pub shadow: Ray<R>,
    pub t_max: R,
}

impl<R: Real> Surface<R> {
    #[inline]
    pub fn at(world: &World<R>, ray: &Ray<R>, (t, id): (R, PrimId)) -> Self {
        let (p, n_out, material) = world.surface(id, ray.at(t));
        let v = -ray.dir;
        let cos_out = n_out.dot(v);
        // Entering: arriving against the outward normal.
        let entering = cos_out >= R::ZERO;
        let n = if entering { n_out } else { -n_out };
        // Shading normal: differs from n only on smoothly shaded triangles.
        let ns = world.shading_normal(id, p, n, v);
        let cos_i = ns.dot(v);
        Surface {
            id,
            p,
            n,
            ns,
            v,
            entering,
            cos_i,
            material,
            above: offset_origin::<R>(p, n),
        }
    }

    /// The ambient term, where the colour starts.
    #[inline]
    pub fn ambient(&self, world: &World<R>) -> R::V3 {
        world.ambient * world.materials[self.material as usize].ambient
    }

    /// The term of `light`, or `None` when it can add nothing (then it needs no shadow ray).
    #[inline]
    pub fn light(&self, world: &World<R>, light: &PointLight<R>) -> Option<LightTerm<R>> {
        let m = &world.materials[self.material as usize];
        let (p, n, ns, v) = (self.p, self.n, self.ns, self.v);
        let to_light = light.position - p;
        let dist = to_light.length();
        if !(dist > R::ZERO) {
            return None;
        }
        let l = to_light * (R::ONE / dist);
        let ndotl = ns.dot(l).max(R::ZERO);
        let h = l + v;
        let h_len = h.length();
        let ndoth = if h_len > R::ZERO {
            (ns.dot(h) / h_len).max(R::ZERO)
        } else {
            R::ZERO
        };
        let spec = if ndoth > m.specular_cos_min {
            specular_pow(ndoth, m.shininess)
        } else {
            R::ZERO
        };
        let contrib = light.diffuse * m.diffuse * ndotl + light.specular * m.specular * spec;
        if contrib.max_element() <= R::ZERO {
            return None;
        }
        // Leave on the light's side of the surface.
        let origin = if n.dot(l) >= R::ZERO {
            self.above
        } else {
            offset_origin::<R>(p, -n)
        };
        Some(LightTerm {
            contrib,
            shadow: Ray::new(origin, l),
            t_max: dist * (R::ONE - R::SHADOW_SHORTEN),
        })
    }

    /// Adds the refracted and reflected light (rays of generation
    /// `depth + 1`, traced recursively), if `depth` allows.
    #[inline]
    pub fn add_secondary(
        &self,
        world: &World<R>,
        depth: u32,
        rays: &mut RayCounts,
        colour: &mut R::V3,
    ) {
        if depth >= world.settings.max_depth {
            return;
        }
        let m = &world.materials[self.material as usize];
        let (p, n, ns, v, cos_i, id) = (self.p, self.n, self.ns, self.v, self.cos_i, self.id);
        let mut reflect_w = m.reflectivity;
        if m.transparency > R::ZERO {
            // Snell: eta = n1/n2; entering from outside goes 1 -> ior.
            let eta = if self.entering { R::ONE / m.ior } else { m.ior };
            let k = R::ONE - eta * eta * (R::ONE - cos_i * cos_i);
            if k < R::ZERO {
                reflect_w += m.transparency; // total internal reflection
            } else {
                let dir = (-v * eta + ns * (eta * cos_i - k.sqrt())).normalize();
                rays.refraction += 1;
                let refr = Ray::new(offset_origin::<R>(p, -n), dir);
                *colour += trace(world, &refr, depth + 1, id, rays) * m.transparency;
            }
        }
        if reflect_w > R::ZERO {
            // R = 2(V.N)N - V
            let dir = (ns * (R::TWO * cos_i) - v).normalize();
            rays.reflection += 1;
            let refl = Ray::new(self.above, dir);
            *colour += trace(world, &refl, depth + 1, id, rays) * reflect_w;
        }
    }
}

/// max(N.H,0)^shininess for `x` in (0, 1]. In f32 this avoids libm's
/// `powf` (a tenth of the render time, not vectorisable, and its result
/// may differ between libm builds and CPU-specific variants): exp2(e log2 x)
/// from IEEE + - * / and bit manipulation only, branch-free, so the stream
/// renderer's lanes compute it too and every machine and SIMD path gets the
/// same bits. Relative error below 5e-6 where shading uses it (tested):
/// no more than the rounding of x itself causes, since x^e multiplies a
/// relative error of x by e (76.8 * 2^-24 = 4.6e-6).
/// The f64 reference keeps the exact `powf`.
#[inline(always)]
pub fn specular_pow<R: Real>(x: R, e: R) -> R {
    if TypeId::of::<R>() == TypeId::of::<f32>() {
        R::from_f64(pow_f32(x.to_f64() as f32, e.to_f64() as f32) as f64)
    } else {
        x.powf(e)
    }
}

/// x^e for x > 0 and e >= 0 (shading asks only for results above 2^-24,
/// where |e log2 x| <= 24 and the error stays below 5e-6).
#[inline(always)]
pub fn pow_f32(x: f32, e: f32) -> f32 {
    exp2_f32(e * log2_f32(x))
}

/// log2 of a positive finite `x`.
#[inline(always)]
fn log2_f32(x: f32) -> f32 {
    // Subnormals: scale into the normal range first.
    let sub = x < f32::MIN_POSITIVE;
    let x = if sub { x * 16_777_216.0 } else { x };
    let bits = x.to_bits();
    let exp = ((bits >> 23) & 0xff) as i32 - if sub { 127 + 24 } else { 127 };
    let m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000); // [1, 2)
    // Mantissa in [sqrt(1/2), sqrt(2)) so that s below is small.
    let big = m > std::f32::consts::SQRT_2;
    let m = if big { m * 0.5 } else { m };
    let exp = exp + big as i32;
    // ln m = 2 atanh(s), s = (m-1)/(m+1), |s| < 0.172: the series to s^9
    // leaves a relative error below 1e-8.
    let s = (m - 1.0) / (m + 1.0);
    let s2 = s * s;
    let series = 1.0 + s2 * (1.0 / 3.0 + s2 * (1.0 / 5.0 + s2 * (1.0 / 7.0 + s2 * (1.0 / 9.0))));
    exp as f32 + (2.0 * s * series) * std::f32::consts::LOG2_E
}

/// 2^y for y < 128, flushing results below 2^-126 to 0.
#[inline(always)]
fn exp2_f32(y: f32) -> f32 {
    let tiny = !(y >= -126.0);
    let y = if tiny { 0.0 } else { y };
    // floor(y), exact, in float arithmetic only (so it vectorises): adding
    // and subtracting 1.5 * 2^23 rounds |y| < 2^22 to the nearest integer.
    const ROUND: f32 = 12_582_912.0;
    let nf = (y + ROUND) - ROUND;
    let nf = if nf > y { nf - 1.0 } else { nf };
    let f = (y - nf) * std::f32::consts::LN_2; // [0, ln 2)
    // e^f by Taylor to f^9 / 9!: relative error below 1e-8 on [0, ln 2).
    let mut p = 1.0 / 362_880.0;
    for k in [40_320.0f32, 5040.0, 720.0, 120.0, 24.0, 6.0, 2.0, 1.0, 1.0] {
        p = p * f + 1.0 / k;
    }
    // 2^nf from its biased exponent nf + 127 (in 1..=254), which the same
    // rounding trick leaves in the low mantissa bits.
    let biased = ((nf + 127.0) + ROUND).to_bits() & 0xff;
    let r = p * f32::from_bits(biased << 23);
    if tiny { 0.0 } else { r }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The f32 specular power against f64 `powf` over the whole range shading
    /// uses (x above the specular floor, integer and fractional shininess).
    #[test]
    fn pow_f32_matches_f64_powf() {
        let mut worst = 0.0f64;
        for e in [
            0.0f32, 0.5, 1.0, 2.0, 7.0, 8.0, 32.0, 76.8, 100.0, 128.0, 333.3, 1000.0, 4096.0, 1.0e5,
        ] {
            let floor = (5.960_464_477_539_063e-8f64).powf(1.0 / e as f64) as f32;
            for k in 0..=20_000 {
                let x = floor + (1.0 - floor) * (k as f32 / 20_000.0);
                if !(x > 0.0) {
                    continue;
                }
                let want = (x as f64).powf(e as f64);
                let got = pow_f32(x, e) as f64;
                if want < 1e-30 {
                    assert!(got < 1e-29, "{x}^{e} = {got}, want {want}");
                    continue;
                }
                let rel = ((got - want) / want).abs();
                worst = worst.max(rel);
                assert!(
                    rel < 5e-6,
                    "{x}^{e} = {got}, want {want} (relative error {rel})"
                );
            }
        }
        assert!(worst > 0.0, "the test should see some rounding");
        // Subnormal bases and the edges.
        assert_eq!(pow_f32(1.0, 76.8), 1.0);
        assert_eq!(pow_f32(0.5, 0.0), 1.0);
        let tiny = f32::from_bits(1000);
        assert!(
            ((pow_f32(tiny, 0.01) as f64 - (tiny as f64).powf(0.01)) / (tiny as f64).powf(0.01))
                .abs()
                < 5e-6
        );
        eprintln!("worst relative error {worst:e}");
    }
}
