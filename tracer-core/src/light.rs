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
}

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
            LightGeom::Point(p) => p,
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
            LightGeom::Point(p) => Some(p),
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
