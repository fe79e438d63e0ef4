//! The CPU renderer of distributed ray tracing: scenes whose `World::dist`
//! is set (area lights, gloss or translucency cones, a lens, motion over
//! the shutter) trace here, one sample at a time, with `whitted.rs`'s
//! arithmetic for everything the scene format did not change. Scenes
//! without these effects never come here, so their renders stay what they
//! were, bit for bit, and as fast.
//!
//! Random numbers: a sample draws its pixel position (dimensions 0, 1), its
//! lens point (`DIM_LENS`, two) and its time (`DIM_TIME`) once; each node
//! of its ray tree has a key (`ROOT_KEY` for the camera ray's hit,
//! `child_key(key, 0)` for the refracted and `child_key(key, 1)` for the
//! reflected ray below it) and draws the cone directions and light samples
//! of that hit from `node_dim(key, slot)`. All are `sampling::uniform` of
//! (pixel seed, sample index, dimension): the same wherever it is traced.

use crate::distributed::{Distributed, Light, LightGeom, ray_meets_box};
use crate::film::{Film, RayCounts, Rect, SampleRange};
use crate::geometry::PrimId;
use crate::math::{Ray, Real, Vector3, offset_origin};
use crate::render::whitted::specular_pow;
use crate::sampling::{
    DIM_LENS, DIM_TIME, ROOT_KEY, SLOT_GLOSS, SLOT_LIGHTS, SLOT_TRANSLUCENCY, child_key, node_dim,
    pixel_seed, sample_offset, sin_cos_turns, stratified, uniform,
};
use crate::world::{Material, World};

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

/// What stays fixed along one sample's ray tree.
#[derive(Clone, Copy)]
struct Sample<R: Real> {
    seed: u32,
    index: u32,
    /// Fraction of the shutter, in [0, 1).
    tau: R,
}

impl<R: Real> Sample<R> {
    #[inline]
    fn u(&self, dim: u32) -> f32 {
        uniform(self.seed, self.index, dim)
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
    for y in tile.y..tile.y + tile.height {
        for x in tile.x..tile.x + tile.width {
            let i = ((y - tile.y) * tile.width + (x - tile.x)) as usize;
            let seed = pixel_seed(x, y, frame);
            for index in samples.start..samples.end {
                let c = sample_colour(world, dist, x, y, seed, index, &mut rays);
                film.add_sample::<R>(i, [c.x(), c.y(), c.z()]);
            }
        }
    }
    film.rays = rays;
    film
}

/// The colour of sample `index` of pixel (x, y).
pub fn sample_colour<R: Real>(
    world: &World<R>,
    dist: &Distributed<R>,
    x: u32,
    y: u32,
    seed: u32,
    index: u32,
    rays: &mut RayCounts,
) -> R::V3 {
    let s = &world.settings;
    let (u, v) = sample_offset(s.sampler, s.samples, seed, index);
    let sx = R::from_u32(x) + R::from_f64(u as f64);
    let sy = R::from_u32(y) + R::from_f64(v as f64);
    let sample = Sample {
        seed,
        index,
        tau: if dist.blur {
            R::from_f64(uniform(seed, index, DIM_TIME) as f64)
        } else {
            R::ZERO
        },
    };
    let ray = camera_ray(world, dist, sx, sy, &sample);
    rays.primary += 1;
    let hit = closest(world, dist, &ray, NO_PRIM, sample.tau);
    shade(world, dist, &ray, hit, 0, ROOT_KEY, &sample, rays)
}

/// The camera ray through raster point (sx, sy) at the sample's time,
/// through its lens point.
fn camera_ray<R: Real>(
    world: &World<R>,
    dist: &Distributed<R>,
    sx: R,
    sy: R,
    sample: &Sample<R>,
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
    let x1 = sample.u(DIM_LENS) as f64;
    let x2 = sample.u(DIM_LENS + 1) as f64;
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

/// A hit, as `whitted::Surface` has it.
struct Surf<'a, R: Real> {
    prim: Prim,
    p: R::V3,
    n: R::V3,
    ns: R::V3,
    v: R::V3,
    entering: bool,
    cos_i: R,
    m: &'a Material<R>,
    above: R::V3,
}

fn surface<'a, R: Real>(
    world: &'a World<R>,
    dist: &'a Distributed<R>,
    ray: &Ray<R>,
    (t, prim): (R, Prim),
    tau: R,
) -> Surf<'a, R> {
    let v = -ray.dir;
    let facing = |n_out: R::V3| {
        let entering = n_out.dot(v) >= R::ZERO;
        (entering, if entering { n_out } else { -n_out })
    };
    let (p, n, ns, entering, m) = match prim.src {
        Src::Static => {
            let (p, n_out, mat) = world.surface(prim.id, ray.at(t));
            let (entering, n) = facing(n_out);
            let ns = world.shading_normal(prim.id, p, n, v);
            (p, n, ns, entering, &world.materials[mat as usize])
        }
        Src::Sphere(i) => {
            let s = dist.moving_spheres[i].at(tau);
            let (p, n_out) = s.surface(ray.at(t));
            let (entering, n) = facing(n_out);
            (p, n, n, entering, &world.materials[s.material as usize])
        }
        Src::Mesh(k) => {
            let mesh = &dist.moving_meshes[k];
            let off = mesh.delta * tau;
            let (p, n_out, mat) = mesh.world.surface(prim.id, ray.at(t) - off);
            let (entering, n) = facing(n_out);
            let ns = mesh.world.shading_normal(prim.id, p, n, v);
            (
                p + off,
                n,
                ns,
                entering,
                &mesh.world.materials[mat as usize],
            )
        }
    };
    Surf {
        prim,
        p,
        n,
        ns,
        v,
        entering,
        cos_i: ns.dot(v),
        m,
        above: offset_origin::<R>(p, n),
    }
}

/// Today's point-light term with the light at `pos`, and its shadow ray
/// (`whitted::Surface::light`'s arithmetic); `None` when it adds nothing.
#[inline]
fn light_term<R: Real>(s: &Surf<R>, pos: R::V3, light: &Light<R>) -> Option<(R::V3, Ray<R>, R)> {
    let (p, n, ns, v, m) = (s.p, s.n, s.ns, s.v, s.m);
    let to_light = pos - p;
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
    if !(contrib.max_element() > R::ZERO) {
        return None;
    }
    let origin = if n.dot(l) >= R::ZERO {
        s.above
    } else {
        offset_origin::<R>(p, -n)
    };
    Some((
        contrib,
        Ray::new(origin, l),
        dist * (R::ONE - R::SHADOW_SHORTEN),
    ))
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

#[allow(clippy::too_many_arguments)]
fn trace<R: Real>(
    world: &World<R>,
    dist: &Distributed<R>,
    ray: &Ray<R>,
    depth: u32,
    key: u32,
    skip: Prim,
    sample: &Sample<R>,
    rays: &mut RayCounts,
) -> R::V3 {
    let hit = closest(world, dist, ray, skip, sample.tau);
    shade(world, dist, ray, hit, depth, key, sample, rays)
}

/// `whitted::shade` with area lights sampled and the secondary rays drawn
/// from their cones.
#[allow(clippy::too_many_arguments)]
fn shade<R: Real>(
    world: &World<R>,
    dist: &Distributed<R>,
    ray: &Ray<R>,
    hit: Option<(R, Prim)>,
    depth: u32,
    key: u32,
    sample: &Sample<R>,
    rays: &mut RayCounts,
) -> R::V3 {
    let Some(hit) = hit else {
        return world.background;
    };
    let tau = sample.tau;
    let s = surface(world, dist, ray, hit, tau);
    let m = s.m;
    let mut colour = world.ambient * m.ambient;
    for light in &dist.lights {
        if let LightGeom::Point(pos) = light.geom {
            if let Some((contrib, shadow, t_max)) = light_term(&s, pos, light) {
                rays.shadow += 1;
                if !occluded(world, dist, &shadow, t_max, s.prim, tau) {
                    colour += contrib;
                }
            }
            continue;
        }
        // The mean over `samples` stratified points of the light.
        let n = light.samples;
        let mut sum = R::V3::zero();
        for i in 0..n {
            let slot = SLOT_LIGHTS + 2 * (light.first_sample + i);
            let u1 = sample.u(node_dim(key, slot));
            let u2 = sample.u(node_dim(key, slot + 1));
            let (u, v) = stratified(i, n, u1, u2);
            if let Some((contrib, shadow, t_max)) = light_term(&s, light.point(u, v), light) {
                rays.shadow += 1;
                if !occluded(world, dist, &shadow, t_max, s.prim, tau) {
                    sum += contrib;
                }
            }
        }
        colour += sum * (R::ONE / R::from_u32(n));
    }
    if depth >= world.settings.max_depth {
        return colour;
    }
    let (p, n, ns, v, cos_i) = (s.p, s.n, s.ns, s.v, s.cos_i);
    let mut reflect_w = m.reflectivity;
    if m.transparency > R::ZERO {
        let eta = if s.entering { R::ONE / m.ior } else { m.ior };
        let k = R::ONE - eta * eta * (R::ONE - cos_i * cos_i);
        if k < R::ZERO {
            reflect_w += m.transparency; // total internal reflection
        } else {
            let mut dir = (-v * eta + ns * (eta * cos_i - k.sqrt())).normalize();
            let mut below = true;
            if m.translucency_cos < R::ONE {
                dir = cone(
                    dir,
                    m.translucency_cos,
                    sample.u(node_dim(key, SLOT_TRANSLUCENCY)),
                    sample.u(node_dim(key, SLOT_TRANSLUCENCY + 1)),
                );
                // A refraction above the surface contributes black.
                below = dir.dot(n) < R::ZERO;
            }
            if below {
                rays.refraction += 1;
                let refr = Ray::new(offset_origin::<R>(p, -n), dir);
                colour += trace(
                    world,
                    dist,
                    &refr,
                    depth + 1,
                    child_key(key, 0),
                    s.prim,
                    sample,
                    rays,
                ) * m.transparency;
            }
        }
    }
    if reflect_w > R::ZERO {
        let mut dir = (ns * (R::TWO * cos_i) - v).normalize();
        let mut above = true;
        if m.gloss_cos < R::ONE {
            dir = cone(
                dir,
                m.gloss_cos,
                sample.u(node_dim(key, SLOT_GLOSS)),
                sample.u(node_dim(key, SLOT_GLOSS + 1)),
            );
            // A reflection below the surface contributes black.
            above = dir.dot(n) > R::ZERO;
        }
        if above {
            rays.reflection += 1;
            let refl = Ray::new(s.above, dir);
            colour += trace(
                world,
                dist,
                &refl,
                depth + 1,
                child_key(key, 1),
                s.prim,
                sample,
                rays,
            ) * reflect_w;
        }
    }
    colour
}
