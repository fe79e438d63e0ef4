//! The path integrator's BSDF: the glTF 2.0 metallic-roughness model of
//! the specification's appendix B, with `KHR_materials_specular`,
//! `KHR_materials_ior` and `KHR_materials_transmission`, and emission.
//!
//! f = mix(dielectric, metal, metallic), where
//!   metal      = conductor_fresnel(base, specular_brdf)
//!   dielectric = fresnel_mix(ior, specular, mix(diffuse_brdf, specular_btdf, transmission), specular_brdf)
//!   diffuse_brdf  = base / pi (Lambert)
//!   specular_brdf = D * V with GGX D and the height-correlated Smith V
//!   Fresnel: Schlick, f0 = ((ior - 1) / (ior + 1))^2 (times the specular
//!   colour, clamped to 1, times the specular factor; f90 = the specular factor)
//! with alpha = roughness^2. Roughness 0 (alpha below [`DELTA_ALPHA`]) is a
//! delta lobe: a perfect mirror, and a perfect refraction for transmission.
//! Transmission refracts with `ior` (a volume boundary, as with
//! `KHR_materials_volume`), tinted by the base colour; Schlick's Fresnel at
//! a boundary from the denser side takes the refracted cosine (and is 1 at
//! total internal reflection). Refraction is always sampled, never
//! evaluated: rough transmission samples a GGX visible normal and refracts
//! about it (weight (1 - F) base G1(wi)), and light reaching a surface
//! through it comes by BSDF sampling alone.
//!
//! The thesis's Blinn-Phong materials map onto it by [`Bsdf::from_material`]
//! (docs/path-tracing.md): energy conserving by construction (every lobe's
//! weight is at most 1 and the weights sum to at most 1).
//!
//! Directions are in the shading frame (z along the shading normal on the
//! viewer's side); `wo` points to the viewer, `wi` to the light.

use crate::material::Material;
use crate::math::{Real, Vector3};
use crate::scene::BsdfDesc;

/// Below this alpha the specular lobes are deltas (a GGX of smaller alpha
/// cannot be told from a mirror at any image size, and its D overflows f32).
pub const DELTA_ALPHA: f64 = 1e-3;

const PI: f64 = std::f64::consts::PI;

/// The parameters of one material's BSDF, render-ready.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bsdf<R: Real> {
    pub base_colour: R::V3,
    pub metallic: R,
    /// Perceptual roughness; alpha = roughness^2.
    pub roughness: R,
    pub ior: R,
    pub transmission: R,
    /// `KHR_materials_specular`'s factor and colour.
    pub specular: R,
    pub specular_colour: R::V3,
    /// Emitted radiance, from the front side only.
    pub emission: R::V3,
    /// An untinted mirror layer of this weight over the rest (F = 1): what
    /// the thesis's `reflectivity` maps to. 0 for glTF materials.
    pub mirror: R,
    /// Absorption coefficient of the volume the surface bounds, per unit
    /// of distance (`KHR_materials_volume`: -ln(attenuationColor) /
    /// attenuationDistance); zero: none. A path segment that ends on the
    /// surface's back side travelled inside and is attenuated by
    /// exp(-absorption t) (Beer-Lambert).
    pub absorption: R::V3,
}

impl<R: Real> Default for Bsdf<R> {
    /// glTF's default material: white, fully metallic, fully rough.
    fn default() -> Self {
        Bsdf {
            base_colour: R::V3::splat(R::ONE),
            metallic: R::ONE,
            roughness: R::ONE,
            ior: R::from_f64(1.5),
            transmission: R::ZERO,
            specular: R::ONE,
            specular_colour: R::V3::splat(R::ONE),
            emission: R::V3::zero(),
            mirror: R::ZERO,
            absorption: R::V3::zero(),
        }
    }
}

/// The absorption coefficient of glTF's `KHR_materials_volume`: light
/// that travels `distance` inside keeps `colour` of itself (per channel),
/// so sigma = -ln(colour) / distance; an infinite distance (glTF's
/// default) absorbs nothing. A channel of 0 is taken as 1e-6 (sigma
/// finite: throughput then goes to 0 without a NaN).
pub fn absorption(colour: [f64; 3], distance: f64) -> [f64; 3] {
    if !(distance.is_finite() && distance > 0.0) {
        return [0.0; 3];
    }
    colour.map(|c| -c.clamp(1e-6, 1.0).ln() / distance)
}

/// A sampled direction: `weight` is f cos / pdf (the throughput factor).
#[derive(Clone, Copy, Debug)]
pub struct BsdfSample<R: Real> {
    pub wi: R::V3,
    pub weight: R::V3,
    /// Solid-angle density of the whole mixture's non-delta lobes at `wi`
    /// (for MIS); meaningless when `delta`.
    pub pdf: R,
    /// A delta lobe (mirror, refraction): no light sampling can find it.
    pub delta: bool,
}

/// Lobe weights at one `wo`, for choosing a lobe: reflection (specular and
/// mirror), diffuse, transmission; they sum to 1 (or all 0).
struct Lobes<R: Real> {
    spec: R,
    diff: R,
    trans: R,
}

fn lum<R: Real>(c: R::V3) -> R {
    (c.x() + c.y() + c.z()) * R::from_f64(1.0 / 3.0)
}

fn pow5<R: Real>(x: R) -> R {
    let x2 = x * x;
    x2 * x2 * x
}

impl<R: Real> Bsdf<R> {
    /// The thesis's Blinn-Phong material as an energy-conserving BSDF:
    /// - `reflectivity` r becomes the untinted mirror layer (`mirror` = r),
    ///   rough by the gloss cone (roughness = sin of its half-angle);
    /// - `transparency` t becomes transmission t / (1 - r) (so the
    ///   refracted weight is t, as in Whitted's sum), with `ior`; a
    ///   transparent material's base colour is white, since Whitted's
    ///   refraction is untinted;
    /// - otherwise the base colour is `diffuse` (clamped to [0, 1]), a
    ///   dielectric (metallic 0, ior 1.5) whose specular factor is the
    ///   largest component of `specular` (clamped to 1) and whose colour is
    ///   `specular` over it, with the roughness of Blinn-Phong's exponent
    ///   s: alpha = sqrt(2 / (s + 2)) (Walter et al. 2007's equivalence);
    /// - `ambient` has no counterpart (indirect light replaces it).
    pub fn from_material(m: &Material<R>) -> Self {
        let clamp01 = |x: R| x.max(R::ZERO).min(R::ONE);
        let r = clamp01(m.reflectivity);
        let t = clamp01(m.transparency);
        let spec_max = m.specular.max_element();
        let specular = clamp01(spec_max);
        let specular_colour = if spec_max > R::ZERO {
            m.specular * (R::ONE / spec_max)
        } else {
            R::V3::splat(R::ONE)
        };
        let s = m.shininess.max(R::ZERO).to_f64();
        let alpha = (2.0 / (s + 2.0)).sqrt();
        let rest = R::ONE - r;
        let transmission = if t > R::ZERO && rest > R::ZERO {
            clamp01(t / rest)
        } else {
            R::ZERO
        };
        // sin of the gloss half-angle from its cosine.
        let gloss_sin = (R::ONE - m.gloss_cos * m.gloss_cos).max(R::ZERO).sqrt();
        Bsdf {
            base_colour: if transmission > R::ZERO {
                R::V3::splat(R::ONE)
            } else {
                m.diffuse.max(R::V3::zero()).min(R::V3::splat(R::ONE))
            },
            metallic: R::ZERO,
            roughness: if r > R::ZERO || transmission > R::ZERO {
                gloss_sin.sqrt()
            } else {
                R::from_f64(alpha.sqrt())
            },
            ior: if transmission > R::ZERO {
                m.ior
            } else {
                R::from_f64(1.5)
            },
            transmission,
            specular,
            specular_colour,
            emission: R::V3::zero(),
            mirror: r,
            absorption: R::V3::zero(),
        }
    }

    /// A `[bsdf.NAME]` table's parameters (validated by the parser).
    pub fn from_desc(b: &BsdfDesc) -> Self {
        Bsdf {
            base_colour: R::V3::from_array(b.base_colour.0),
            metallic: R::from_f64(b.metallic.0),
            roughness: R::from_f64(b.roughness.0),
            ior: R::from_f64(b.ior.0),
            transmission: R::from_f64(b.transmission.0),
            specular: R::from_f64(b.specular.0),
            specular_colour: R::V3::from_array(b.specular_colour.0),
            emission: R::V3::from_array(b.emission.0),
            mirror: R::ZERO,
            absorption: R::V3::from_array(absorption(
                b.attenuation_colour.0,
                b.attenuation_distance.map_or(f64::INFINITY, |d| d.0),
            )),
        }
    }

    /// Transmittance over `t` units of the volume inside (1 where nothing absorbs).
    pub fn transmittance(&self, t: R) -> R::V3 {
        let a = self.absorption;
        R::V3::new((-a.x() * t).exp(), (-a.y() * t).exp(), (-a.z() * t).exp())
    }

    pub fn alpha(&self) -> R {
        self.roughness * self.roughness
    }

    fn is_delta(&self) -> bool {
        self.alpha() < R::from_f64(DELTA_ALPHA)
    }

    /// Whether the Lambert lobe is all there is (no specular layer, metal,
    /// mirror or transmission): then f = base / pi, sampled by the cosine
    /// alone. The general formulas ([`Self::eval_lobes`],
    /// [`Self::sample_lobes`]) give the same, every other lobe's weight
    /// being 0, at several times the cost (`tessera bench path`'s Cornell
    /// box is all Lambert).
    #[inline]
    fn is_lambert(&self) -> bool {
        self.specular == R::ZERO
            && self.metallic == R::ZERO
            && self.mirror == R::ZERO
            && self.transmission == R::ZERO
    }

    /// Whether some lobe is not a delta (light sampling can help).
    pub fn has_smooth_lobe(&self) -> bool {
        let diffuse = (R::ONE - self.mirror)
            * (R::ONE - self.metallic)
            * (R::ONE - self.transmission)
            * self.base_colour.max_element();
        diffuse > R::ZERO || !self.is_delta()
    }

    /// Dielectric Schlick Fresnel (KHR_materials_specular) at `cos` between
    /// the viewer and the (micro)normal, on the side with relative index
    /// `eta` = n_transmitted / n_incident: from the denser side it takes
    /// the refracted cosine, and is 1 at total internal reflection.
    fn f_dielectric(&self, cos: R, eta: R) -> R::V3 {
        let f0 = (self.ior - R::ONE) / (self.ior + R::ONE);
        let f0 = f0 * f0;
        let f0c = (self.specular_colour * f0).min(R::V3::splat(R::ONE)) * self.specular;
        let f90 = R::V3::splat(self.specular);
        let c = if eta < R::ONE {
            let sin2_t = (R::ONE - cos * cos) / (eta * eta);
            if sin2_t >= R::ONE {
                return f90;
            }
            (R::ONE - sin2_t).sqrt()
        } else {
            cos
        };
        f0c + (f90 - f0c) * pow5(R::ONE - c.max(R::ZERO).min(R::ONE))
    }

    /// conductor_fresnel: Schlick with f0 = base colour.
    fn f_metal(&self, cos: R) -> R::V3 {
        let b = self.base_colour;
        b + (R::V3::splat(R::ONE) - b) * pow5(R::ONE - cos.max(R::ZERO).min(R::ONE))
    }

    /// Reflection Fresnel of the whole (mirror layer, metal, dielectric) at `cos`.
    fn f_reflect(&self, cos: R, eta: R) -> R::V3 {
        let f = self.f_dielectric(cos, eta) * (R::ONE - self.metallic)
            + self.f_metal(cos) * self.metallic;
        R::V3::splat(self.mirror) + f * (R::ONE - self.mirror)
    }

    fn lobes(&self, cos_o: R, eta: R) -> Lobes<R> {
        let fd = self.f_dielectric(cos_o, eta);
        let keep = R::ONE - self.mirror;
        let spec = lum::<R>(self.f_reflect(cos_o, eta));
        let dielectric = keep
            * (R::ONE - self.metallic)
            * (R::ONE - fd.max_element())
            * lum::<R>(self.base_colour);
        let diff = dielectric * (R::ONE - self.transmission);
        let trans = dielectric * self.transmission;
        let sum = spec + diff + trans;
        if !(sum > R::ZERO) {
            return Lobes {
                spec: R::ZERO,
                diff: R::ZERO,
                trans: R::ZERO,
            };
        }
        let k = R::ONE / sum;
        Lobes {
            spec: spec * k,
            diff: diff * k,
            trans: trans * k,
        }
    }

    /// f(wo, wi) cos(wi) of the non-delta reflection lobes, and the
    /// mixture's solid-angle pdf of sampling `wi` by [`Self::sample`]
    /// (`eta`: n on the far side over n on the viewer's).
    pub fn eval(&self, wo: R::V3, wi: R::V3, eta: R) -> (R::V3, R) {
        let (co, ci) = (wo.z(), wi.z());
        if !(co > R::ZERO && ci > R::ZERO) {
            return (R::V3::zero(), R::ZERO);
        }
        if !self.is_lambert() {
            return self.eval_lobes(wo, wi, eta);
        }
        let pdf = ci * R::from_f64(1.0 / PI);
        if lum::<R>(self.base_colour) > R::ZERO {
            (self.base_colour * pdf, pdf)
        } else {
            (R::V3::zero(), R::ZERO)
        }
    }

    /// [`Self::eval`] by every lobe's formula, for `wo` and `wi` above.
    fn eval_lobes(&self, wo: R::V3, wi: R::V3, eta: R) -> (R::V3, R) {
        let (co, ci) = (wo.z(), wi.z());
        let inv_pi = R::from_f64(1.0 / PI);
        let lobes = self.lobes(co, eta);
        let h = (wo + wi).normalize();
        let vh = wo.dot(h).max(R::ZERO);
        let fd = self.f_dielectric(vh, eta);
        let keep = R::ONE - self.mirror;
        let diffuse = self.base_colour
            * (keep
                * (R::ONE - self.metallic)
                * (R::ONE - self.transmission)
                * (R::ONE - fd.max_element())
                * inv_pi
                * ci);
        let mut f = diffuse;
        let mut pdf = lobes.diff * ci * inv_pi;
        if !self.is_delta() {
            let a = self.alpha();
            let d = ggx_d(h.z(), a);
            let v = smith_v(co, ci, a);
            f += self.f_reflect(vh, eta) * (d * v * ci);
            pdf += lobes.spec * smith_g1(co, a) * d / (R::from_f64(4.0) * co);
        }
        (f, pdf)
    }

    /// Samples `wi` for `wo` with uniform numbers `u` (lobe choice, then
    /// two for the direction); `eta` as in [`Self::eval`]. `None`: the
    /// path ends (no lobe, or a direction below the surface).
    pub fn sample(&self, wo: R::V3, eta: R, u: [f32; 3]) -> Option<BsdfSample<R>> {
        let co = wo.z();
        if !(co > R::ZERO) {
            return None;
        }
        if !self.is_lambert() {
            return self.sample_lobes(wo, eta, u);
        }
        // f cos / pdf = base exactly.
        let wi = cosine_hemisphere::<R>(u[1] as f64, u[2] as f64);
        let pdf = wi.z() * R::from_f64(1.0 / PI);
        (pdf > R::ZERO && lum::<R>(self.base_colour) > R::ZERO).then_some(BsdfSample {
            wi,
            weight: self.base_colour,
            pdf,
            delta: false,
        })
    }

    /// [`Self::sample`] by choosing among every lobe, for `wo` above.
    fn sample_lobes(&self, wo: R::V3, eta: R, u: [f32; 3]) -> Option<BsdfSample<R>> {
        let co = wo.z();
        let lobes = self.lobes(co, eta);
        let pick = R::from_f64(u[0] as f64);
        let (u1, u2) = (u[1] as f64, u[2] as f64);
        let delta = self.is_delta();
        if pick < lobes.trans {
            return self.sample_transmission(wo, eta, u1, u2, lobes.trans);
        }
        let wi = if pick < lobes.trans + lobes.spec {
            if delta {
                let wi = R::V3::new(-wo.x(), -wo.y(), wo.z());
                let weight = self.f_reflect(co, eta) * (R::ONE / lobes.spec);
                return Some(BsdfSample {
                    wi,
                    weight,
                    pdf: R::ZERO,
                    delta: true,
                });
            }
            let h = sample_vndf(wo, self.alpha(), u1, u2);
            (h * (R::TWO * wo.dot(h)) - wo).normalize()
        } else {
            cosine_hemisphere::<R>(u1, u2)
        };
        let (f, pdf) = self.eval(wo, wi, eta);
        if !(pdf > R::ZERO) {
            return None;
        }
        Some(BsdfSample {
            wi,
            weight: f * (R::ONE / pdf),
            pdf,
            delta: false,
        })
    }

    /// Refraction (always treated as a delta for MIS): about the normal
    /// when smooth, about a GGX visible normal when rough; total internal
    /// reflection reflects. `p` is the lobe's probability.
    fn sample_transmission(
        &self,
        wo: R::V3,
        eta: R,
        u1: f64,
        u2: f64,
        p: R,
    ) -> Option<BsdfSample<R>> {
        let h = if self.is_delta() {
            R::V3::new(R::ZERO, R::ZERO, R::ONE)
        } else {
            sample_vndf(wo, self.alpha(), u1, u2)
        };
        let c = wo.dot(h);
        if !(c > R::ZERO) {
            return None;
        }
        let inv_eta = R::ONE / eta;
        let sin2_t = inv_eta * inv_eta * (R::ONE - c * c);
        if sin2_t >= R::ONE {
            // Total internal reflection: F = 1 and the reflection lobes
            // carry it all; nothing refracts.
            return None;
        }
        let fd = self.f_dielectric(c, eta).max_element();
        let cos_t = (R::ONE - sin2_t).sqrt();
        let wi = (-wo * inv_eta + h * (inv_eta * c - cos_t)).normalize();
        // The refracted share (1 - metallic)(1 - mirror) transmission
        // (1 - F) base over the lobe's probability; radiance is scaled by
        // (n_i / n_t)^2 crossing the boundary; a rough boundary's visible
        // normal leaves G1(wi) of the microfacet BTDF's weight.
        let scale =
            (R::ONE - self.mirror) * (R::ONE - self.metallic) * self.transmission * (R::ONE - fd)
                / p
                * inv_eta
                * inv_eta;
        let scale = if self.is_delta() {
            scale
        } else {
            scale * smith_g1(wi.z().abs(), self.alpha())
        };
        let weight = self.base_colour * scale;
        Some(BsdfSample {
            wi,
            weight,
            pdf: R::ZERO,
            delta: true,
        })
    }
}

/// GGX normal distribution D(h) for cos(theta_h) = `c`.
fn ggx_d<R: Real>(c: R, a: R) -> R {
    let a2 = a * a;
    let k = c * c * (a2 - R::ONE) + R::ONE;
    a2 / (R::from_f64(PI) * k * k)
}

/// Smith G1 for GGX at cos = `c`.
fn smith_g1<R: Real>(c: R, a: R) -> R {
    let a2 = a * a;
    R::TWO * c / (c + (a2 + (R::ONE - a2) * c * c).sqrt())
}

/// Height-correlated Smith visibility V = G2 / (4 |n.l| |n.v|).
fn smith_v<R: Real>(co: R, ci: R, a: R) -> R {
    let a2 = a * a;
    let gv = ci * (co * co * (R::ONE - a2) + a2).sqrt();
    let gl = co * (ci * ci * (R::ONE - a2) + a2).sqrt();
    let s = gv + gl;
    if s > R::ZERO {
        R::from_f64(0.5) / s
    } else {
        R::ZERO
    }
}

/// A GGX visible normal for `wo` (Heitz 2018), in the shading frame.
fn sample_vndf<R: Real>(wo: R::V3, a: R, u1: f64, u2: f64) -> R::V3 {
    let vh = R::V3::new(a * wo.x(), a * wo.y(), wo.z()).normalize();
    let lensq = vh.x() * vh.x() + vh.y() * vh.y();
    let t1 = if lensq > R::ZERO {
        R::V3::new(-vh.y(), vh.x(), R::ZERO) * (R::ONE / lensq.sqrt())
    } else {
        R::V3::new(R::ONE, R::ZERO, R::ZERO)
    };
    let t2 = vh.cross(t1);
    let r = R::from_f64(u1.sqrt());
    let (sn, cs) = crate::sampling::sin_cos_turns(u2);
    let p1 = r * R::from_f64(cs);
    let p2 = r * R::from_f64(sn);
    let s = R::from_f64(0.5) * (R::ONE + vh.z());
    let p2 = (R::ONE - s) * (R::ONE - p1 * p1).max(R::ZERO).sqrt() + s * p2;
    let nh = t1 * p1 + t2 * p2 + vh * (R::ONE - p1 * p1 - p2 * p2).max(R::ZERO).sqrt();
    R::V3::new(a * nh.x(), a * nh.y(), nh.z().max(R::ZERO)).normalize()
}

/// A cosine-weighted direction about +z.
fn cosine_hemisphere<R: Real>(u1: f64, u2: f64) -> R::V3 {
    let r = u1.sqrt();
    let (sn, cs) = crate::sampling::sin_cos_turns(u2);
    R::V3::from_array([r * cs, r * sn, (1.0 - u1).max(0.0).sqrt()])
}

/// An orthonormal frame with `n` as z (Duff et al. 2017).
#[derive(Clone, Copy, Debug)]
pub struct Frame<R: Real> {
    pub t1: R::V3,
    pub t2: R::V3,
    pub n: R::V3,
}

impl<R: Real> Frame<R> {
    pub fn new(n: R::V3) -> Self {
        let (x, y, z) = (n.x(), n.y(), n.z());
        let sign = R::ONE.copysign(z);
        let a = -R::ONE / (sign + z);
        let b = x * y * a;
        Frame {
            t1: R::V3::new(R::ONE + sign * x * x * a, sign * b, -sign * x),
            t2: R::V3::new(b, sign + y * y * a, -y),
            n,
        }
    }
    pub fn to_local(&self, v: R::V3) -> R::V3 {
        R::V3::new(v.dot(self.t1), v.dot(self.t2), v.dot(self.n))
    }
    pub fn to_world(&self, v: R::V3) -> R::V3 {
        self.t1 * v.x() + self.t2 * v.y() + self.n * v.z()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    type V = <f64 as Real>::V3;

    fn lambert(c: f64) -> Bsdf<f64> {
        Bsdf {
            base_colour: V::splat(c),
            metallic: 0.0,
            roughness: 1.0,
            specular: 0.0,
            ..Bsdf::default()
        }
    }

    /// The weights sampling returns average to the directional albedo the
    /// evaluation integrates to (checks sample, eval and pdf agree).
    fn albedo_by_sampling(b: &Bsdf<f64>, wo: V, n: u32) -> [f64; 3] {
        let mut sum = V::zero();
        for i in 0..n {
            let u = [
                crate::sampling::uniform(1, i, 0),
                crate::sampling::uniform(1, i, 1),
                crate::sampling::uniform(1, i, 2),
            ];
            if let Some(s) = b.sample(wo, 1.5, u) {
                sum += s.weight;
            }
        }
        (sum * (1.0 / n as f64)).to_array()
    }

    fn albedo_by_eval(b: &Bsdf<f64>, wo: V, n: u32) -> [f64; 3] {
        // Uniform hemisphere quadrature over a stratified grid.
        let mut sum = V::zero();
        for i in 0..n {
            for j in 0..n {
                let z = (i as f64 + 0.5) / n as f64;
                let phi = 2.0 * PI * (j as f64 + 0.5) / n as f64;
                let r = (1.0 - z * z).sqrt();
                let wi = V::new(r * phi.cos(), r * phi.sin(), z);
                sum += b.eval(wo, wi, 1.5).0;
            }
        }
        (sum * (2.0 * PI / (n * n) as f64)).to_array()
    }

    #[test]
    fn lambert_albedo_is_its_colour() {
        let b = lambert(0.8);
        let wo = V::new(0.3, 0.0, 0.9539392014169456);
        for c in albedo_by_sampling(&b, wo, 4096) {
            assert!((c - 0.8).abs() < 1e-9, "{c}");
        }
        for c in albedo_by_eval(&b, wo, 400) {
            assert!((c - 0.8).abs() < 2e-3, "{c}");
        }
    }

    /// The Lambert shortcut gives what every lobe's formula gives for a
    /// Lambert material: the same directions from the same numbers, the
    /// same values and densities to rounding; black ends the path.
    #[test]
    fn the_lambert_shortcut_matches_the_general_formulas() {
        for base in [V::new(0.72, 0.4, 0.1), V::splat(1.0)] {
            let b = Bsdf {
                base_colour: base,
                ..lambert(0.0)
            };
            assert!(b.is_lambert());
            for k in 0..64u32 {
                let u = [
                    0.37,
                    (k as f32 + 0.5) / 64.0,
                    ((k * 29) % 64) as f32 / 64.0 + 0.007,
                ];
                let wo = V::new(0.2, -0.1, 0.9746794344808963);
                let fast = b.sample(wo, 1.5, u).unwrap();
                let slow = b.sample_lobes(wo, 1.5, u).unwrap();
                assert_eq!(fast.wi, slow.wi);
                assert!((fast.pdf - slow.pdf).abs() <= 1e-12 * slow.pdf, "{k}");
                for c in 0..3 {
                    let (f, s) = (fast.weight.to_array()[c], slow.weight.to_array()[c]);
                    assert!((f - s).abs() <= 1e-12 * s, "{k}: {f} vs {s}");
                }
                let (fe, pe) = b.eval(wo, fast.wi, 1.5);
                let (fs, ps) = b.eval_lobes(wo, fast.wi, 1.5);
                assert!((pe - ps).abs() <= 1e-12 * ps);
                for c in 0..3 {
                    let (f, s) = (fe.to_array()[c], fs.to_array()[c]);
                    assert!((f - s).abs() <= 1e-12 * s);
                }
            }
        }
        let black = lambert(0.0);
        let wo = V::new(0.0, 0.0, 1.0);
        assert!(black.sample(wo, 1.5, [0.5, 0.5, 0.5]).is_none());
        assert!(black.sample_lobes(wo, 1.5, [0.5, 0.5, 0.5]).is_none());
        assert_eq!(black.eval(wo, wo, 1.5), black.eval_lobes(wo, wo, 1.5));
    }

    #[test]
    fn rough_metal_sampling_matches_evaluation() {
        for roughness in [0.3, 0.6, 1.0] {
            let b = Bsdf {
                base_colour: V::new(0.9, 0.6, 0.3),
                roughness,
                ..Bsdf::default()
            };
            let wo = V::new(0.6, 0.0, 0.8);
            let s = albedo_by_sampling(&b, wo, 200_000);
            let e = albedo_by_eval(&b, wo, 1000);
            for k in 0..3 {
                // Monte Carlo error of 2e5 samples with weights below ~1.
                assert!(
                    (s[k] - e[k]).abs() < 0.01,
                    "roughness {roughness}: {s:?} vs {e:?}"
                );
                // Single scattering loses energy (at roughness 1 about
                // 60%), never gains any.
                assert!(s[k] <= 1.0 && s[k] > 0.05, "{s:?}");
            }
        }
    }

    #[test]
    fn smooth_mirror_reflects_everything() {
        let b = Bsdf::<f64> {
            roughness: 0.0,
            ..Bsdf::default()
        };
        let wo = V::new(0.6, 0.0, 0.8);
        let s = b.sample(wo, 1.5, [0.5, 0.5, 0.5]).unwrap();
        assert!(s.delta);
        assert_eq!(s.wi.to_array(), [-0.6, -0.0, 0.8]);
        assert_eq!(s.weight.to_array(), [1.0; 3]);
    }

    #[test]
    fn smooth_glass_reflects_plus_refracts_to_one() {
        let b = Bsdf::<f64> {
            metallic: 0.0,
            roughness: 0.0,
            transmission: 1.0,
            ..Bsdf::default()
        };
        // From outside (eta = 1.5) and from inside (1 / 1.5): expected
        // weight reflected + refracted (with the radiance scale undone) = 1.
        for eta in [1.5, 1.0 / 1.5] {
            let wo = V::new(0.5, 0.0, 0.75f64.sqrt());
            let mut sum = 0.0;
            let n = 10_000;
            for i in 0..n {
                let u = [(i as f32 + 0.5) / n as f32, 0.5, 0.5];
                let s = b.sample(wo, eta, u).unwrap();
                let scale = if s.wi.z() < 0.0 { eta * eta } else { 1.0 };
                sum += s.weight.x() * scale;
            }
            let mean = sum / n as f64;
            assert!((mean - 1.0).abs() < 1e-3, "eta {eta}: {mean}");
        }
    }
}
