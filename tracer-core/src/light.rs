//! Lights: the thesis's point lights and distributed ray tracing's area
//! lights (quads and spheres, sampled by stratified points). The shading
//! step (`render::step`) takes either through [`Emitter`]: a point light's
//! term is taken once, an area light's is the mean over its samples.

use crate::math::{Real, Vector3};

/// What the shading step asks of a light.
pub trait Emitter<R: Real> {
    /// The diffuse and the specular colour.
    fn colours(&self) -> [R::V3; 2];
    /// Where a point light is; `None` for an area light, whose term is the
    /// mean over [`Self::samples`] points ([`Self::point`]).
    fn position(&self) -> Option<R::V3>;
    /// How many points of an area light a hit samples.
    fn samples(&self) -> u32 {
        1
    }
    /// The sum of the samples of the lights before this one: its first
    /// slot among a ray-tree node's random numbers.
    fn first_sample(&self) -> u32 {
        0
    }
    /// The point of the light for the stratified numbers (u, v) in [0, 1)^2.
    fn point(&self, u: f64, v: f64) -> R::V3;
}

/// A point light of a scene without area lights (`World::lights`).
#[derive(Clone, Copy, Debug)]
pub struct PointLight<R: Real> {
    pub position: R::V3,
    pub diffuse: R::V3,
    pub specular: R::V3,
}

impl<R: Real> Emitter<R> for PointLight<R> {
    #[inline(always)]
    fn colours(&self) -> [R::V3; 2] {
        [self.diffuse, self.specular]
    }
    #[inline(always)]
    fn position(&self) -> Option<R::V3> {
        Some(self.position)
    }
    #[inline(always)]
    fn point(&self, _u: f64, _v: f64) -> R::V3 {
        self.position
    }
}

/// A light of a scene with distributed effects (`Distributed::lights`), in
/// file order, point lights too. Positions are camera-relative.
#[derive(Clone, Copy, Debug)]
pub enum LightGeom<R: Real> {
    Point(R::V3),
    Quad {
        corner: R::V3,
        edge_u: R::V3,
        edge_v: R::V3,
    },
    Sphere {
        center: R::V3,
        radius: R,
    },
    /// The path integrator's spot light (a model file's): a point light
    /// whose intensity on a direction at cosine cd from unit `direction`
    /// is scaled by glTF's smooth falloff clamp(cd scale + offset, 0, 1)²
    /// (scale = 1 / max(0.001, cos inner - cos outer), offset = -cos
    /// outer x scale: `KHR_lights_punctual`).
    Spot {
        position: R::V3,
        direction: R::V3,
        scale: R,
        offset: R,
    },
    /// The path integrator's directional light: `diffuse` is the
    /// irradiance it gives a surface facing it, arriving along unit
    /// `direction` from no distance; `radius` (of the scene) sizes its
    /// power.
    Directional {
        direction: R::V3,
        radius: R,
    },
}

/// How far a directional light's shadow rays reach: beyond any scene.
pub const DIRECTIONAL_REACH: f32 = 1e30;

#[derive(Clone, Copy, Debug)]
pub struct Light<R: Real> {
    pub geom: LightGeom<R>,
    pub diffuse: R::V3,
    pub specular: R::V3,
    pub samples: u32,
    /// Sum of the samples of the lights before this one (its first slot).
    pub first_sample: u32,
}

impl<R: Real> Light<R> {
    /// The point of the light for the stratified numbers (u, v) in [0, 1)^2:
    /// uniform by area over the light.
    #[inline]
    pub fn point(&self, u: f64, v: f64) -> R::V3 {
        match self.geom {
            LightGeom::Point(p) | LightGeom::Spot { position: p, .. } => p,
            // Whitted's step never sees one (path only): a point far away.
            LightGeom::Directional { direction, .. } => {
                direction * -R::from_f64(DIRECTIONAL_REACH as f64)
            }
            LightGeom::Quad {
                corner,
                edge_u,
                edge_v,
            } => corner + edge_u * R::from_f64(u) + edge_v * R::from_f64(v),
            LightGeom::Sphere { center, radius } => {
                // Archimedes: z uniform in [-1, 1] and the azimuth uniform
                // give points uniform by area.
                let z = 1.0 - 2.0 * u;
                let rho = (1.0 - z * z).max(0.0).sqrt();
                let (s, c) = crate::sampling::sin_cos_turns(v);
                let d = R::V3::from_array([rho * c, rho * s, z]);
                center + d * radius
            }
        }
    }
}

impl<R: Real> Emitter<R> for Light<R> {
    #[inline(always)]
    fn colours(&self) -> [R::V3; 2] {
        [self.diffuse, self.specular]
    }
    #[inline(always)]
    fn position(&self) -> Option<R::V3> {
        match self.geom {
            LightGeom::Point(_) | LightGeom::Spot { .. } | LightGeom::Directional { .. } => {
                Some(self.point(0.0, 0.0))
            }
            _ => None,
        }
    }
    #[inline(always)]
    fn samples(&self) -> u32 {
        self.samples
    }
    #[inline(always)]
    fn first_sample(&self) -> u32 {
        self.first_sample
    }
    #[inline]
    fn point(&self, u: f64, v: f64) -> R::V3 {
        Light::point(self, u, v)
    }
}

/// A light's point sampled for the path integrator's next-event estimation.
#[derive(Clone, Copy, Debug)]
pub struct LightSample<R: Real> {
    /// Unit direction from the shaded point to the light.
    pub wi: R::V3,
    pub dist: R,
    /// Radiance arriving (a point light: intensity / dist^2).
    pub li: R::V3,
    /// Solid-angle density of this light's sampling at `wi` (0: a point light, a delta).
    pub pdf: R,
}

/// The path integrator's lights (docs/path-tracing.md): a point light's
/// `diffuse` colour is its intensity (W/sr, falling off as 1/d^2), an area
/// light's its radiance, emitted from both sides of a quad and outwards
/// from a sphere. `specular` and `samples` are Whitted's only.
impl<R: Real> Light<R> {
    /// Emitted power over pi (the constant is the same for every kind,
    /// so selection by it is selection by power), by luminance.
    pub fn power(&self) -> f64 {
        let c = self.diffuse.to_array();
        let lum = (c[0] + c[1] + c[2]) / 3.0;
        match self.geom {
            LightGeom::Point(_) => 4.0 * lum,
            LightGeom::Quad { edge_u, edge_v, .. } => {
                2.0 * edge_u.cross(edge_v).length().to_f64() * std::f64::consts::PI * lum
            }
            LightGeom::Sphere { radius, .. } => {
                let r = radius.to_f64();
                4.0 * r * r * std::f64::consts::PI * lum
            }
            // 2 pi (1 - cos) over pi, the cone halfway through the falloff.
            LightGeom::Spot { scale, offset, .. } => {
                let (scale, offset) = (scale.to_f64(), offset.to_f64());
                let cos_mid = (0.5 - offset) / scale;
                2.0 * (1.0 - cos_mid).clamp(0.0, 2.0) * lum
            }
            // The irradiance over the scene's cross-section, pi r², over pi.
            LightGeom::Directional { radius, .. } => {
                let r = radius.to_f64();
                r * r * lum
            }
        }
    }

    /// A point of the light seen from `p` for uniform numbers (u, v):
    /// uniform by area on a quad, uniform in the cone a sphere subtends.
    pub fn sample_li(&self, p: R::V3, u: f64, v: f64) -> Option<LightSample<R>> {
        match self.geom {
            LightGeom::Spot {
                position,
                direction,
                scale,
                offset,
            } => {
                let d = position - p;
                let dist = d.length();
                if !(dist > R::ZERO) {
                    return None;
                }
                let wi = d * (R::ONE / dist);
                let a = (-(direction.dot(wi)) * scale + offset).min(R::ONE);
                // Outside the outer cone it lights nothing: no shadow ray.
                (a > R::ZERO).then(|| LightSample {
                    wi,
                    dist,
                    li: self.diffuse * (a * a / (dist * dist)),
                    pdf: R::ZERO,
                })
            }
            LightGeom::Directional { direction, .. } => Some(LightSample {
                wi: -direction,
                dist: R::from_f64(DIRECTIONAL_REACH as f64),
                li: self.diffuse,
                pdf: R::ZERO,
            }),
            LightGeom::Point(pos) => {
                let d = pos - p;
                let dist = d.length();
                (dist > R::ZERO).then(|| LightSample {
                    wi: d * (R::ONE / dist),
                    dist,
                    li: self.diffuse * (R::ONE / (dist * dist)),
                    pdf: R::ZERO,
                })
            }
            LightGeom::Quad {
                corner,
                edge_u,
                edge_v,
            } => {
                let x = corner + edge_u * R::from_f64(u) + edge_v * R::from_f64(v);
                let d = x - p;
                let dist = d.length();
                let n = edge_u.cross(edge_v);
                let area = n.length();
                if !(dist > R::ZERO && area > R::ZERO) {
                    return None;
                }
                let wi = d * (R::ONE / dist);
                let cos_l = n.dot(wi).abs() / area;
                (cos_l > R::ZERO).then(|| LightSample {
                    wi,
                    dist,
                    li: self.diffuse,
                    pdf: dist * dist / (area * cos_l),
                })
            }
            LightGeom::Sphere { center, radius } => {
                let d = center - p;
                let dc = d.length();
                if !(dc > radius) {
                    // Inside the sphere: it is no light source to sample.
                    return None;
                }
                let axis = d * (R::ONE / dc);
                let sin2 = radius * radius / (dc * dc);
                let cos_max = (R::ONE - sin2).max(R::ZERO).sqrt();
                let wi = crate::sampling::cone(axis, cos_max, u as f32, v as f32);
                let t = sphere_hit(p, wi, center, radius).unwrap_or(dc);
                Some(LightSample {
                    wi,
                    dist: t,
                    li: self.diffuse,
                    pdf: cone_pdf(sin2),
                })
            }
        }
    }

    /// Where a ray from `o` along unit `d` meets the light before `t_max`
    /// (never a point light): its distance and the solid-angle density
    /// [`Self::sample_li`] has of that direction from `o`.
    pub fn hit(&self, o: R::V3, d: R::V3, t_max: R) -> Option<(R, R)> {
        match self.geom {
            LightGeom::Point(_) | LightGeom::Spot { .. } | LightGeom::Directional { .. } => None,
            LightGeom::Quad {
                corner,
                edge_u,
                edge_v,
            } => {
                let n = edge_u.cross(edge_v);
                let denom = n.dot(d);
                if denom == R::ZERO {
                    return None;
                }
                let t = n.dot(corner - o) / denom;
                if !(t > R::ZERO && t < t_max) {
                    return None;
                }
                let q = o + d * t - corner;
                // Coordinates along the edges (the dual basis).
                let nn = n.dot(n);
                let a = q.cross(edge_v).dot(n) / nn;
                let b = edge_u.cross(q).dot(n) / nn;
                if !(a >= R::ZERO && a <= R::ONE && b >= R::ZERO && b <= R::ONE) {
                    return None;
                }
                let area = nn.sqrt();
                let cos_l = denom.abs() / area;
                Some((t, t * t / (area * cos_l)))
            }
            LightGeom::Sphere { center, radius } => {
                let t = sphere_hit(o, d, center, radius)?;
                if !(t < t_max) {
                    return None;
                }
                let dc = (center - o).length();
                if !(dc > radius) {
                    return Some((t, R::ZERO));
                }
                Some((t, cone_pdf(radius * radius / (dc * dc))))
            }
        }
    }
}

/// The solid-angle density of a direction drawn uniformly in the cone a
/// sphere subtends, from sin² of its half-angle: 1 / (2π (1 - cos)),
/// with 1 - cos written as sin² / (1 + cos). Subtracted directly, it is 0
/// in f32 once sin² is below 2^-24 (a small light seen from a point far
/// along a plane), and the density infinite made the path's MIS weights
/// NaN.
fn cone_pdf<R: Real>(sin2: R) -> R {
    let cos_max = (R::ONE - sin2).max(R::ZERO).sqrt();
    (R::ONE + cos_max) / (R::from_f64(2.0 * std::f64::consts::PI) * sin2)
}

/// Nearest positive distance along unit `d` from `o` to the sphere.
fn sphere_hit<R: Real>(o: R::V3, d: R::V3, c: R::V3, r: R) -> Option<R> {
    let oc = o - c;
    let b = oc.dot(d);
    let disc = b * b - (oc.dot(oc) - r * r);
    if disc < R::ZERO {
        return None;
    }
    let s = disc.sqrt();
    let t0 = -b - s;
    let t1 = -b + s;
    if t0 > R::ZERO {
        Some(t0)
    } else if t1 > R::ZERO {
        Some(t1)
    } else {
        None
    }
}
