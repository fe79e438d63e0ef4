//! Materials: the thesis's Blinn-Phong surface with mirror reflection and
//! Snell refraction, and distributed ray tracing's gloss and translucency
//! cones. [`Material`] is render-ready (one precision, cosines precomputed);
//! the shading step (`render::step`) asks it for a light's term
//! ([`Material::blinn_phong`]) and the directions of its secondary rays
//! ([`Material::refract`], [`reflect`]). The lane-wise twin
//! (`render::cpu::shade`) and the WGSL kernels do the same arithmetic.

use std::any::TypeId;

use crate::bsdf::Bsdf;
use crate::math::{Real, Vector3};
use crate::scene::MaterialDesc;
use crate::texture::{SurfaceAttrs, TextureRef};

/// Index of no [`Pbr`] (`Material::pbr` of a TOML material).
pub const NO_PBR: u32 = u32::MAX;

#[derive(Clone, Copy, Debug)]
pub struct Material<R: Real> {
    pub ambient: R::V3,
    pub diffuse: R::V3,
    pub specular: R::V3,
    pub shininess: R,
    pub reflectivity: R,
    pub transparency: R,
    pub ior: R,
    /// N.H below which max(N.H,0)^shininess < `Real::SPECULAR_FLOOR`.
    pub specular_cos_min: R,
    /// Cosines of the gloss and translucency half-angles (1: a perfect
    /// mirror and a perfect refraction).
    pub gloss_cos: R,
    pub translucency_cos: R,
    /// Radiance the surface emits (glTF emissiveFactor x emissiveStrength,
    /// OBJ `Ke`): added where the colour starts, in every integrator.
    pub emission: R::V3,
    /// Index of the material's textures and glTF parameters in
    /// `World::pbr`, or [`NO_PBR`].
    pub pbr: u32,
}

/// `alphaMode` of a glTF material.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum AlphaMode {
    #[default]
    Opaque,
    /// Cut out where alpha < `alpha_cutoff`, for every ray.
    Mask,
    /// Blended: Whitted renders it as transparency 1 - alpha (no refraction
    /// of the ray's direction when ior is 1).
    Blend,
}

/// A model file's material as authored, with glTF 2.0's names (OBJ/MTL
/// maps onto the same): the factors, the textures (each an image with its
/// sampler, UV set and transform) and the extensions read. The Whitted
/// mapping of the factors is made when the file is read (the
/// [`MaterialDesc`] beside it, docs/meshes.md "Materials and textures");
/// the textures are looked up at each hit by the shading step
/// (`render::step`). A path tracer's BSDF reads these same parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct Pbr {
    /// baseColorFactor (linear RGBA).
    pub base_color: [f64; 4],
    pub base_color_texture: Option<TextureRef>,
    pub metallic: f64,
    pub roughness: f64,
    /// Blue: metallic, green: roughness (multiplying the factors).
    pub metallic_roughness_texture: Option<TextureRef>,
    /// emissiveFactor x KHR_materials_emissive_strength.
    pub emissive: [f64; 3],
    pub emissive_texture: Option<TextureRef>,
    pub normal_texture: Option<TextureRef>,
    pub normal_scale: f64,
    pub occlusion_texture: Option<TextureRef>,
    pub occlusion_strength: f64,
    pub alpha_mode: AlphaMode,
    pub alpha_cutoff: f64,
    pub double_sided: bool,
    /// KHR_materials_ior (1.5 by default).
    pub ior: f64,
    /// KHR_materials_transmission.
    pub transmission: f64,
    /// KHR_materials_volume: light travelling `attenuation_distance`
    /// inside keeps `attenuation_color` (infinite: nothing absorbed; the
    /// thickness is the ray's own distance, so `thicknessFactor` is not read).
    pub attenuation_color: [f64; 3],
    pub attenuation_distance: f64,
    /// KHR_materials_specular.
    pub specular_factor: f64,
    pub specular_color: [f64; 3],
    /// Whether COLOR_0 multiplies the base colour (the primitive has it).
    pub vertex_colors: bool,
    /// An MTL material: its textures multiply the Blinn-Phong colours
    /// read from the MTL (map_Kd: Kd and Ka; map_Ke: Ke) rather than
    /// going through [`Pbr::whitted`].
    pub mtl: bool,
    /// MTL `map_d`: its first channel times its alpha multiplies alpha.
    pub alpha_texture: Option<TextureRef>,
    /// MTL `bump`/`map_Bump`: a height field (its first channel) that
    /// displaces the surface along its normal by `bump_scale` (`-bm`, 1 by
    /// default) times its value, in the surface's units; the shading
    /// normal is the displaced surface's (`render::step::shading_normal`),
    /// as Mitsuba's `bumpmap` makes it. Never set beside `normal_texture`.
    pub bump_texture: Option<TextureRef>,
    pub bump_scale: f64,
}

impl Default for Pbr {
    fn default() -> Self {
        Pbr {
            base_color: [1.0; 4],
            base_color_texture: None,
            metallic: 1.0,
            roughness: 1.0,
            metallic_roughness_texture: None,
            emissive: [0.0; 3],
            emissive_texture: None,
            normal_texture: None,
            normal_scale: 1.0,
            occlusion_texture: None,
            occlusion_strength: 1.0,
            alpha_mode: AlphaMode::Opaque,
            alpha_cutoff: 0.5,
            double_sided: false,
            ior: 1.5,
            transmission: 0.0,
            attenuation_color: [1.0; 3],
            attenuation_distance: f64::INFINITY,
            specular_factor: 1.0,
            specular_color: [1.0; 3],
            vertex_colors: false,
            mtl: false,
            alpha_texture: None,
            bump_texture: None,
            bump_scale: 1.0,
        }
    }
}

impl Pbr {
    /// Every texture it reads, in one order (the GPU's texel pack and
    /// reports walk them alike).
    pub fn textures(&self) -> impl Iterator<Item = &TextureRef> {
        [
            &self.base_color_texture,
            &self.metallic_roughness_texture,
            &self.emissive_texture,
            &self.occlusion_texture,
            &self.alpha_texture,
            &self.normal_texture,
            &self.bump_texture,
        ]
        .into_iter()
        .flatten()
    }

    /// The Whitted material of base colour `base` (linear RGBA), `metallic`
    /// and `roughness` (the factors, or at a hit the factors times the
    /// textures): a mirror in Whitted's model is perfectly sharp, so only
    /// smooth metals reflect: reflectivity = metallic * (1 - roughness)^2;
    /// the base colour is the diffuse colour (and ambient) for the rest,
    /// times 1 - transmission (1 - metallic), and tints the specular
    /// colour by metallic (the dielectric's is 0.04 specularFactor
    /// specularColor); roughness maps to a Phong exponent 2/r^4 - 2 (the
    /// Beckmann match); transmission (1 - metallic) and, for BLEND,
    /// 1 - alpha, whichever is larger, is the transparency, refracted with
    /// the material's ior.
    pub fn whitted(&self, base: [f64; 4], metallic: f64, roughness: f64) -> MaterialDesc {
        use crate::scene::{Num, Vec3};
        let [r, g, b, a] = base;
        let metallic = metallic.clamp(0.0, 1.0);
        let rough = roughness.clamp(0.0, 1.0);
        let reflectivity = metallic * (1.0 - rough) * (1.0 - rough);
        let transmission = self.transmission.clamp(0.0, 1.0) * (1.0 - metallic);
        let base = [r, g, b];
        let diffuse = base.map(|c| c * (1.0 - reflectivity) * (1.0 - transmission));
        let blend = if self.alpha_mode == AlphaMode::Blend {
            (1.0 - a).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let f0 = self.specular_color.map(|c| 0.04 * self.specular_factor * c);
        MaterialDesc {
            ambient: Vec3(diffuse),
            diffuse: Vec3(diffuse),
            specular: Vec3(std::array::from_fn(|i| {
                f0[i] + (base[i] - f0[i]) * metallic
            })),
            shininess: Num((2.0 / rough.max(0.05).powi(4) - 2.0).max(1.0)),
            reflectivity: Num(reflectivity),
            transparency: Num(blend.max(transmission)),
            ior: Num(self.ior),
            gloss: Num(0.0),
            translucency: Num(0.0),
        }
    }

    /// The material at a point with texture coordinates, vertex colour and
    /// footprint `at`, for both integrators, the textures sampled once
    /// (trilinear: `TextureRef::sample_at`): Whitted's [`Material`], the factors times the textures
    /// through [`Pbr::whitted`], the ambient term darkened by the
    /// occlusion texture (glTF's occlusion darkens indirect light, which
    /// the ambient term stands for), the emission times the emissive
    /// texture; and the path integrator's [`Bsdf`] ([`Pbr::bsdf`]). `m` is
    /// the material of the factors alone.
    pub fn at<R: Real>(&self, m: &Material<R>, at: &SurfaceAttrs) -> (Material<R>, Bsdf<R>) {
        let base = self.base_color_at(at);
        let emission = match &self.emissive_texture {
            Some(t) => {
                let e = t.sample_at(at);
                R::V3::from_array(std::array::from_fn(|i| self.emissive[i] * e[i] as f64))
            }
            None => m.emission,
        };
        if self.mtl {
            let tint = R::V3::from_array([0, 1, 2].map(|i| base[i] as f64));
            let out = Material {
                ambient: m.ambient * tint,
                diffuse: m.diffuse * tint,
                emission,
                ..*m
            };
            return (out, Self::mtl_bsdf(&out));
        }
        let (mut metallic, mut roughness) = (self.metallic, self.roughness);
        if let Some(t) = &self.metallic_roughness_texture {
            let s = t.sample_at(at);
            roughness *= s[1] as f64;
            metallic *= s[2] as f64;
        }
        let base = base.map(f64::from);
        let mut desc = self.whitted(base, metallic, roughness);
        if let Some(t) = &self.occlusion_texture {
            let o = t.sample_at(at)[0] as f64;
            let k = 1.0 + self.occlusion_strength * (o - 1.0);
            desc.ambient.0 = desc.ambient.0.map(|c| c * k);
        }
        let mut out = Material::from_desc(&desc);
        out.pbr = m.pbr;
        out.emission = emission;
        (out, self.bsdf(base, metallic, roughness, emission))
    }

    /// The path integrator's BSDF of base colour `base` (linear RGBA),
    /// `metallic`, `roughness` and emitted radiance `emission` (the
    /// factors, or at a hit the factors times the textures): glTF's
    /// parameters as they are, with `KHR_materials_specular`, `_ior` and
    /// `_transmission` (docs/path-tracing.md). BLEND's 1 - alpha, where
    /// larger, is the transmission, as in [`Pbr::whitted`]; the occlusion
    /// texture has no part (indirect light is computed). An MTL material
    /// is Blinn-Phong, mapped by [`Bsdf::from_material`].
    pub fn bsdf<R: Real>(
        &self,
        base: [f64; 4],
        metallic: f64,
        roughness: f64,
        emission: R::V3,
    ) -> Bsdf<R> {
        let [r, g, b, a] = base;
        let blend = if self.alpha_mode == AlphaMode::Blend {
            (1.0 - a).clamp(0.0, 1.0)
        } else {
            0.0
        };
        Bsdf {
            base_colour: R::V3::from_array([r, g, b].map(|c| c.clamp(0.0, 1.0))),
            metallic: R::from_f64(metallic.clamp(0.0, 1.0)),
            roughness: R::from_f64(roughness.clamp(0.0, 1.0)),
            ior: R::from_f64(self.ior),
            transmission: R::from_f64(self.transmission.clamp(0.0, 1.0).max(blend)),
            specular: R::from_f64(self.specular_factor.clamp(0.0, 1.0)),
            specular_colour: R::V3::from_array(self.specular_color.map(|c| c.max(0.0))),
            emission,
            mirror: R::ZERO,
            absorption: R::V3::from_array(crate::bsdf::absorption(
                self.attenuation_color,
                self.attenuation_distance,
            )),
        }
    }

    /// The BSDF of the whole material `m` (of this `Pbr`), its factors
    /// alone: what hits where nothing varies over the surface get.
    pub fn bsdf_of<R: Real>(&self, m: &Material<R>) -> Bsdf<R> {
        if self.mtl {
            Self::mtl_bsdf(m)
        } else {
            self.bsdf(self.base_color, self.metallic, self.roughness, m.emission)
        }
    }

    /// An MTL material's BSDF: Blinn-Phong's mapping, with its emission.
    fn mtl_bsdf<R: Real>(m: &Material<R>) -> Bsdf<R> {
        Bsdf {
            emission: m.emission,
            ..Bsdf::from_material(m)
        }
    }

    /// Base colour (linear RGBA) at a point: factor x texture x vertex colour.
    pub fn base_color_at(&self, at: &SurfaceAttrs) -> [f32; 4] {
        let t = match &self.base_color_texture {
            Some(t) => t.sample_at(at),
            None => [1.0; 4],
        };
        let mut c: [f32; 4] =
            std::array::from_fn(|i| self.base_color[i] as f32 * t[i] * at.colour[i]);
        if let Some(a) = &self.alpha_texture {
            let s = a.sample_at(at);
            c[3] *= s[0] * s[3];
        }
        c
    }

    /// Whether a point is cut away (alphaMode MASK, alpha below the cutoff):
    /// every ray passes through it.
    pub fn cut_away(&self, at: &SurfaceAttrs) -> bool {
        self.alpha_mode == AlphaMode::Mask && (self.base_color_at(at)[3] as f64) < self.alpha_cutoff
    }

    /// Whether its back faces are cut away for every ray (glTF's
    /// `doubleSided` false, the default): a single-sided surface seen
    /// from behind is not there, as a rasterizer culls it. Transmissive
    /// surfaces keep both faces: a ray refracted inside must meet the
    /// far side to leave.
    pub fn culls_back_faces(&self) -> bool {
        !self.double_sided && self.transmission == 0.0
    }

    /// Whether anything of it varies over the surface (a texture or vertex
    /// colours): then hits on it need their texture coordinates.
    pub fn varies(&self) -> bool {
        self.vertex_colors
            || self.base_color_texture.is_some()
            || self.alpha_texture.is_some()
            || self.emissive_texture.is_some()
            || self.metallic_roughness_texture.is_some()
            || self.occlusion_texture.is_some()
            || self.normal_texture.is_some()
            || self.bump_texture.is_some()
    }
}

impl<R: Real> Material<R> {
    pub fn from_desc(m: &MaterialDesc) -> Self {
        Material {
            ambient: R::V3::from_array(m.ambient.0),
            diffuse: R::V3::from_array(m.diffuse.0),
            specular: R::V3::from_array(m.specular.0),
            shininess: R::from_f64(m.shininess.0),
            reflectivity: R::from_f64(m.reflectivity.0),
            transparency: R::from_f64(m.transparency.0),
            ior: R::from_f64(m.ior.0),
            specular_cos_min: R::from_f64(if m.shininess.0 > 0.0 {
                R::SPECULAR_FLOOR.powf(1.0 / m.shininess.0)
            } else {
                0.0
            }),
            gloss_cos: R::from_f64(cos_deg(m.gloss.0)),
            translucency_cos: R::from_f64(cos_deg(m.translucency.0)),
            emission: R::V3::zero(),
            pbr: NO_PBR,
        }
    }

    /// What a light of colours `diffuse` and `specular` in the unit
    /// direction `l` adds, seen from `v` with shading normal `ns`:
    /// max(N.L,0) l.diffuse m.diffuse + max(N.H,0)^shininess l.specular m.specular.
    #[inline]
    pub fn blinn_phong(
        &self,
        ns: R::V3,
        v: R::V3,
        l: R::V3,
        diffuse: R::V3,
        specular: R::V3,
    ) -> R::V3 {
        let ndotl = ns.dot(l).max(R::ZERO);
        let h = l + v;
        let h_len = h.length();
        let ndoth = if h_len > R::ZERO {
            (ns.dot(h) / h_len).max(R::ZERO)
        } else {
            R::ZERO
        };
        let spec = if ndoth > self.specular_cos_min {
            specular_pow(ndoth, self.shininess)
        } else {
            R::ZERO
        };
        diffuse * self.diffuse * ndotl + specular * self.specular * spec
    }

    /// The refracted direction of a ray arriving along `-v` at shading
    /// normal `ns` (on the viewer's side, `cos_i` = ns.v), or `None` at
    /// total internal reflection. Snell: eta = n1/n2; entering from
    /// outside goes 1 -> ior.
    #[inline]
    pub fn refract(&self, v: R::V3, ns: R::V3, cos_i: R, entering: bool) -> Option<R::V3> {
        let eta = if entering {
            R::ONE / self.ior
        } else {
            self.ior
        };
        let k = R::ONE - eta * eta * (R::ONE - cos_i * cos_i);
        if k < R::ZERO {
            None
        } else {
            Some((-v * eta + ns * (eta * cos_i - k.sqrt())).normalize())
        }
    }
}

/// The mirror direction R = 2(V.N)N - V, for `cos_i` = ns.v.
#[inline]
pub fn reflect<R: Real>(v: R::V3, ns: R::V3, cos_i: R) -> R::V3 {
    (ns * (R::TWO * cos_i) - v).normalize()
}

/// cos of an angle in degrees, exactly 1 at 0 and the same bits on every machine.
fn cos_deg(deg: f64) -> f64 {
    if deg == 0.0 {
        1.0
    } else {
        crate::sampling::sin_cos_turns(deg / 360.0).1
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

    /// glTF's default is single-sided; `doubleSided` and transmission (a
    /// refracted ray must leave through the far side) keep back faces.
    #[test]
    fn back_faces_are_culled_for_opaque_single_sided_materials_only() {
        let single = Pbr::default();
        assert!(single.culls_back_faces());
        let double = Pbr {
            double_sided: true,
            ..Pbr::default()
        };
        assert!(!double.culls_back_faces());
        let glass = Pbr {
            transmission: 1.0,
            ..Pbr::default()
        };
        assert!(!glass.culls_back_faces());
    }

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
