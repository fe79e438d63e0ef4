//! The CPU driver of distributed ray tracing: scenes whose `World::dist`
//! is set (area lights, gloss or translucency cones, a lens, motion over
//! the shutter) trace here, one sample at a time, through the one shading
//! step (`render::step`) with the effects [`Sampled`]: the camera ray (lens
//! and time) is drawn here, hits among moving objects are found here, and
//! the step does the rest. Scenes without these effects never come here,
//! so their renders stay what they were, bit for bit, and as fast.
//!
//! Random numbers: a sample draws its pixel position (dimensions 0, 1), its
//! lens point (`DIM_LENS`, two) and its time (`DIM_TIME`) once; each node
//! of its ray tree has a key (`ROOT_KEY` for the camera ray's hit,
//! `child_key(key, 0)` for the refracted and `child_key(key, 1)` for the
//! reflected ray below it) and draws the cone directions and light samples
//! of that hit from `node_dim(key, slot)`. All are `sampling::uniform` of
//! (pixel seed, sample index, dimension): the same wherever it is traced.

use crate::distributed::{Distributed, ray_meets_box};
use crate::film::{Film, RayCounts, Rect, SampleRange};
use crate::geometry::PrimId;
use crate::light::Light;
use crate::math::{Ray, Real, Vector3};
use crate::render::step::{self, Effects, Surface};
use crate::sampling::{
    DIM_LENS, DIM_TIME, ROOT_KEY, Strata, child_key, node_dim, pixel_seed, sample_offset,
    sin_cos_turns, strata_side, uniform, uniform_pair,
};
use crate::world::World;

pub use crate::sampling::cone;

/// Where a hit primitive lives: the static world, a moving sphere, or a
/// moving mesh's own world.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Src {
    Static,
    Sphere(usize),
    Mesh(usize),
}

/// A primitive: for a hit, and for the primitive a ray starts on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Prim {
    pub src: Src,
    pub id: PrimId,
}

const NO_PRIM: Prim = Prim {
    src: Src::Static,
    id: PrimId::NONE,
};

/// Distributed ray tracing's effects for one sample: what stays fixed
/// along its ray tree (the pixel's seed, the sample's index and time), and
/// the moving objects and lights it is traced among.
#[derive(Clone, Copy)]
pub struct Sampled<'a, R: Real> {
    pub dist: &'a Distributed<R>,
    pub seed: u32,
    pub index: u32,
    /// Fraction of the shutter, in [0, 1).
    pub tau: R,
    /// The grid [`Effects::u2`]'s pairs are stratified over
    /// (`sampling::strata_side`).
    pub strata: Strata,
}

impl<R: Real> Sampled<'_, R> {
    #[inline]
    fn uniform(&self, dim: u32) -> f32 {
        uniform(self.seed, self.index, dim)
    }
}

impl<'d, R: Real> Effects<R> for Sampled<'d, R> {
    type Prim = Prim;
    type Key = u32;
    type Light = Light<R>;
    const CONES: bool = true;

    #[inline(always)]
    fn lights<'a>(&'a self, _world: &'a World<R>) -> &'a [Light<R>] {
        &self.dist.lights
    }
    #[inline]
    fn closest(&self, world: &World<R>, ray: &Ray<R>, skip: Prim) -> Option<(R, Prim)> {
        closest(world, self.dist, ray, skip, self.tau)
    }
    #[inline]
    fn occluded(&self, world: &World<R>, ray: &Ray<R>, t_max: R, skip: Prim) -> bool {
        occluded(world, self.dist, ray, t_max, skip, self.tau)
    }
    #[inline]
    fn surface<'a>(
        &'a self,
        world: &'a World<R>,
        ray: &Ray<R>,
        (t, prim): (R, Prim),
    ) -> Surface<'a, R, Prim> {
        match prim.src {
            Src::Static => {
                let (p, n_out, mat) = world.surface(prim.id, ray.at(t));
                let (m, bsdf) = step::material_at(world, prim.id, p, mat);
                Surface::new(prim, p, n_out, ray, m, bsdf, |n, v| {
                    step::shading_normal(world, prim.id, p, mat, n, v)
                })
            }
            Src::Sphere(i) => {
                let s = self.dist.moving_spheres[i].at(self.tau);
                let (p, n_out) = s.surface(ray.at(t));
                Surface::new(
                    prim,
                    p,
                    n_out,
                    ray,
                    world.materials[s.material as usize],
                    world.bsdfs[s.material as usize],
                    |n, _| n,
                )
            }
            Src::Mesh(k) => {
                // The mesh's own world is at the shutter's opening: the hit
                // moves back into it, the point out again.
                let mesh = &self.dist.moving_meshes[k];
                let off = mesh.delta * self.tau;
                let (p, n_out, mat) = mesh.world.surface(prim.id, ray.at(t) - off);
                let (m, bsdf) = step::material_at(&mesh.world, prim.id, p, mat);
                Surface::new(prim, p + off, n_out, ray, m, bsdf, |n, v| {
                    step::shading_normal(&mesh.world, prim.id, p, mat, n, v)
                })
            }
        }
    }
    #[inline]
    fn u(&self, key: u32, slot: u32) -> f32 {
        self.uniform(node_dim(key, slot))
    }
    #[inline]
    fn u2(&self, key: u32, slot: u32) -> (f32, f32) {
        uniform_pair(self.seed, self.index, self.strata, node_dim(key, slot))
    }
    #[inline(always)]
    fn child(key: u32, which: u32) -> u32 {
        child_key(key, which)
    }
    #[inline(always)]
    fn static_prim(&self, prim: Prim) -> Option<PrimId> {
        (prim.src == Src::Static).then_some(prim.id)
    }
}

/// Renders one tile of a scene with distributed effects.
pub fn render_tile<R: Real>(
    world: &World<R>,
    dist: &Distributed<R>,
    frame: u32,
    tile: Rect,
    samples: SampleRange,
) -> Film {
    let mut film = Film::new(tile);
    let mut rays = RayCounts::default();
    let strata = Strata::new(strata_side(world.settings.sampler, world.settings.samples));
    for y in tile.y..tile.y + tile.height {
        for x in tile.x..tile.x + tile.width {
            let i = ((y - tile.y) * tile.width + (x - tile.x)) as usize;
            let seed = pixel_seed(x, y, frame);
            for index in samples.start..samples.end {
                let c = sample_colour(world, dist, strata, (x, y), seed, index, &mut rays);
                film.add_sample::<R>(i, [c.x(), c.y(), c.z()]);
            }
        }
    }
    film.rays = rays;
    film
}

/// The colour of sample `index` of pixel (x, y); `strata` are the
/// render's (`strata_side` of its sampler and count).
pub fn sample_colour<R: Real>(
    world: &World<R>,
    dist: &Distributed<R>,
    strata: Strata,
    (x, y): (u32, u32),
    seed: u32,
    index: u32,
    rays: &mut RayCounts,
) -> R::V3 {
    let s = &world.settings;
    let (u, v) = sample_offset(s.sampler, s.samples, seed, index);
    let sx = R::from_u32(x) + R::from_f64(u as f64);
    let sy = R::from_u32(y) + R::from_f64(v as f64);
    let sample = Sampled {
        dist,
        seed,
        index,
        tau: if dist.blur {
            R::from_f64(uniform(seed, index, DIM_TIME) as f64)
        } else {
            R::ZERO
        },
        strata,
    };
    let ray = camera_ray(world, dist, sx, sy, &sample);
    rays.primary += 1;
    if let Some(path) = &dist.path {
        return step::path(world, &sample, path, &ray, ROOT_KEY, NO_PRIM, rays);
    }
    step::trace(world, &sample, &ray, 0, ROOT_KEY, NO_PRIM, rays)
}

/// The camera ray through raster point (sx, sy) at the sample's time,
/// through its lens point.
fn camera_ray<R: Real>(
    world: &World<R>,
    dist: &Distributed<R>,
    sx: R,
    sy: R,
    sample: &Sampled<R>,
) -> Ray<R> {
    let cam = dist.camera_at(world, sample.tau);
    let d = cam.camera.ray(sx, sy).dir;
    let Some(lens) = &dist.lens else {
        return Ray::new(cam.origin, d);
    };
    // Focal point P = position + d * focus / dot(d, f); lens point
    // L = position + aperture sqrt(x1) (cos(2 pi x2) r + sin(2 pi x2) u).
    let focus = lens.focus_distance.unwrap_or(cam.look_distance);
    let p = cam.origin + d * (focus / d.dot(cam.camera.forward));
    let x1 = sample.uniform(DIM_LENS) as f64;
    let x2 = sample.uniform(DIM_LENS + 1) as f64;
    let (sn, cs) = sin_cos_turns(x2);
    let l = cam.origin
        + (cam.unit_right * R::from_f64(cs) + cam.unit_up * R::from_f64(sn))
            * (lens.aperture * R::from_f64(x1.sqrt()));
    let dir = p - l;
    let len = dir.length();
    // A focal point on the lens (focus 0 cannot be: focus > 0) keeps d.
    Ray::new(
        l,
        if len > R::ZERO {
            dir * (R::ONE / len)
        } else {
            d
        },
    )
}

/// Nearest hit at shutter fraction `tau` of a ray starting on `skip`.
pub fn closest<R: Real>(
    world: &World<R>,
    dist: &Distributed<R>,
    ray: &Ray<R>,
    skip: Prim,
    tau: R,
) -> Option<(R, Prim)> {
    let skip_in = |src: Src| {
        if skip.src == src {
            skip.id
        } else {
            PrimId::NONE
        }
    };
    let mut best = world.closest_hit(ray, skip_in(Src::Static)).map(|(t, id)| {
        (
            t,
            Prim {
                src: Src::Static,
                id,
            },
        )
    });
    let mut t_best = best.map_or(R::INFINITY, |b| b.0);
    for (i, m) in dist.moving_spheres.iter().enumerate() {
        if !ray_meets_box(ray, m.lo, m.hi, t_best) {
            continue;
        }
        let src = Src::Sphere(i);
        if let Some(t) = m.at(tau).intersect(ray, t_best, skip.src == src) {
            t_best = t;
            best = Some((
                t,
                Prim {
                    src,
                    id: PrimId::new(PrimId::SPHERE, i as u32),
                },
            ));
        }
    }
    for (k, m) in dist.moving_meshes.iter().enumerate() {
        if !ray_meets_box(ray, m.lo, m.hi, t_best) {
            continue;
        }
        let local = Ray::new(ray.origin - m.delta * tau, ray.dir);
        if let Some((t, id)) = m.world.closest_hit(&local, skip_in(Src::Mesh(k)))
            && t < t_best
        {
            t_best = t;
            best = Some((
                t,
                Prim {
                    src: Src::Mesh(k),
                    id,
                },
            ));
        }
    }
    best
}

/// Whether anything lies on the ray before `t_max` at shutter fraction `tau`.
pub fn occluded<R: Real>(
    world: &World<R>,
    dist: &Distributed<R>,
    ray: &Ray<R>,
    t_max: R,
    skip: Prim,
    tau: R,
) -> bool {
    let skip_in = |src: Src| {
        if skip.src == src {
            skip.id
        } else {
            PrimId::NONE
        }
    };
    if world.occluded(ray, t_max, skip_in(Src::Static)) {
        return true;
    }
    for (i, m) in dist.moving_spheres.iter().enumerate() {
        if ray_meets_box(ray, m.lo, m.hi, t_max)
            && m.at(tau)
                .intersect(ray, t_max, skip.src == Src::Sphere(i))
                .is_some()
        {
            return true;
        }
    }
    dist.moving_meshes.iter().enumerate().any(|(k, m)| {
        ray_meets_box(ray, m.lo, m.hi, t_max)
            && m.world.occluded(
                &Ray::new(ray.origin - m.delta * tau, ray.dir),
                t_max,
                skip_in(Src::Mesh(k)),
            )
    })
}
