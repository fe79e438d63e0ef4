//! The one shading step: a hit's surface, each light's term, and the
//! secondary rays, exactly as the scene-format contract states the thesis's
//! Whitted model:
//!
//! colour = ambient * m.ambient
//!        + sum over unblocked lights (max(N.L,0) l.diffuse m.diffuse + max(N.H,0)^shininess l.specular m.specular)
//!        + reflectivity * reflected + transparency * refracted
//!
//! with total internal reflection sending the transparency weight to the
//! reflected ray, and `max_depth` bounding the generations of secondary rays.
//! Generic over precision (`f32` the fast path, `f64` the reference) and
//! over the [`Effects`] a scene uses: [`Static`] (the thesis's scenes: point
//! lights, mirrors, no random numbers) or distributed ray tracing's
//! (`cpu::distributed::Sampled`: area lights, gloss and translucency cones,
//! moving objects, a ray-tree node's random keys). Each is monomorphised, so
//! the static step has no branch or argument of the distributed one.
//!
//! Drivers over the step: the recursive one (`cpu::render_tile_recursive`,
//! camera rays and their shadow rays in packets, then [`Surface::add_secondary`]),
//! the distributed one (`cpu::distributed`), and adaptive rounds
//! (`render::adaptive`, over either). The stream renderer's lanes
//! (`cpu::shade::shade_lanes`) are this step's one SIMD twin: the same
//! arithmetic over many hits; tests check that they agree bit for bit. The
//! light term is [`crate::material::Material::blinn_phong`]; lights are
//! [`crate::light::Emitter`]s.

use crate::bsdf::Bsdf;
use crate::bsdf::Frame;
use crate::film::RayCounts;
use crate::geometry::PrimId;
use crate::light::Emitter;
use crate::material::{Material, NO_PBR, Pbr, reflect};
use crate::math::{Ray, Real, Vector3, offset_origin};
use crate::sampling::{
    SLOT_GLOSS, SLOT_LIGHTS, SLOT_PATH_LIGHT, SLOT_PATH_LOBE, SLOT_PATH_RR, SLOT_TRANSLUCENCY,
    cone, stratified,
};
use crate::world::{PointLight, World};

/// What a scene's effects change in the step: where rays hit, which
/// lights there are, and the random numbers of area lights and cones.
pub trait Effects<R: Real> {
    /// What names a hit primitive (and the primitive a ray starts on).
    type Prim: Copy;
    /// A ray-tree node's random key (`()` where nothing is drawn).
    type Key: Copy;
    type Light: Emitter<R>;
    /// Whether materials may have gloss or translucency cones.
    const CONES: bool;
    fn lights<'a>(&'a self, world: &'a World<R>) -> &'a [Self::Light];
    /// Nearest hit of a ray starting on `skip`.
    fn closest(&self, world: &World<R>, ray: &Ray<R>, skip: Self::Prim) -> Option<(R, Self::Prim)>;
    /// Whether anything lies on the ray before `t_max`.
    fn occluded(&self, world: &World<R>, ray: &Ray<R>, t_max: R, skip: Self::Prim) -> bool;
    fn surface<'a>(
        &'a self,
        world: &'a World<R>,
        ray: &Ray<R>,
        hit: (R, Self::Prim),
    ) -> Surface<'a, R, Self::Prim>;
    /// Uniform number `slot` of the node `key` (area-light points, cones).
    fn u(&self, key: Self::Key, slot: u32) -> f32;
    /// Numbers `slot` and `slot + 1` of the node `key` as a pair: a path
    /// vertex's light point and BSDF direction, stratified over the
    /// pixel's samples where the driver stratifies
    /// ([`crate::sampling::uniform_pair`]).
    fn u2(&self, key: Self::Key, slot: u32) -> (f32, f32) {
        (self.u(key, slot), self.u(key, slot + 1))
    }
    /// The key of child `which` (0 refracted, 1 reflected) of node `key`.
    fn child(key: Self::Key, which: u32) -> Self::Key;
    /// The id of `prim` in the static world, where it is one (where
    /// emissive triangles are light-sampled: `crate::emitters`).
    fn static_prim(&self, _prim: Self::Prim) -> Option<PrimId> {
        None
    }
}

/// The thesis's scenes: the static world, point lights, perfect mirrors
/// and refraction, nothing drawn at random.
#[derive(Clone, Copy, Debug, Default)]
pub struct Static;

impl<R: Real> Effects<R> for Static {
    type Prim = PrimId;
    type Key = ();
    type Light = PointLight<R>;
    const CONES: bool = false;

    #[inline(always)]
    fn lights<'a>(&'a self, world: &'a World<R>) -> &'a [PointLight<R>] {
        &world.lights
    }
    #[inline(always)]
    fn closest(&self, world: &World<R>, ray: &Ray<R>, skip: PrimId) -> Option<(R, PrimId)> {
        world.closest_hit(ray, skip)
    }
    #[inline(always)]
    fn occluded(&self, world: &World<R>, ray: &Ray<R>, t_max: R, skip: PrimId) -> bool {
        world.occluded(ray, t_max, skip)
    }
    #[inline(always)]
    fn surface<'a>(
        &'a self,
        world: &'a World<R>,
        ray: &Ray<R>,
        hit: (R, PrimId),
    ) -> Surface<'a, R, PrimId> {
        Surface::at(world, ray, hit)
    }
    fn u(&self, _key: (), _slot: u32) -> f32 {
        unreachable!(
            "a static scene draws nothing: its lights are points, its materials have no cones"
        )
    }
    #[inline(always)]
    fn child(_key: (), _which: u32) {}
}

/// Colour seen along `ray`, which starts on primitive `skip` and is of
/// generation `depth` (primary rays are 0) at ray-tree node `key`.
pub fn trace<R: Real, E: Effects<R>>(
    world: &World<R>,
    fx: &E,
    ray: &Ray<R>,
    depth: u32,
    key: E::Key,
    skip: E::Prim,
    rays: &mut RayCounts,
) -> R::V3 {
    let hit = fx.closest(world, ray, skip);
    shade(world, fx, ray, hit, depth, key, rays)
}

/// Colour seen along `ray` of generation `depth`, given its closest hit
/// (`Effects::closest`, or the same answer from `World::closest_hits`).
pub fn shade<R: Real, E: Effects<R>>(
    world: &World<R>,
    fx: &E,
    ray: &Ray<R>,
    hit: Option<(R, E::Prim)>,
    depth: u32,
    key: E::Key,
    rays: &mut RayCounts,
) -> R::V3 {
    let Some(hit) = hit else {
        return world.background;
    };
    let s = fx.surface(world, ray, hit);
    let mut colour = s.ambient(world);
    add_lights(world, fx, &s, key, rays, &mut colour);
    s.add_secondary(world, fx, depth, key, rays, &mut colour);
    colour
}

/// Path segments after which Russian roulette may end a path (Mitsuba's
/// default too: short paths are never cut).
pub const RR_DEPTH: u32 = 5;

/// The power heuristic's weight of a strategy of density `a` against one of `b`.
#[inline]
fn power_heuristic<R: Real>(a: R, b: R) -> R {
    // Densities past 1e18 square past f32's range (a quad light seen
    // edge-on from a grazing camera ray: 2e19 and 3e23 on
    // examples/distributed.toml), and inf / inf made the sample NaN: there
    // the same weight as a ratio, which cannot overflow. Below it the
    // squares as they always were (path.wgsl the same).
    let big = R::from_f64(POWER_HEURISTIC_RATIO_ABOVE);
    if a > big || b > big {
        return if a >= b {
            let r = b / a;
            R::ONE / (R::ONE + r * r)
        } else {
            let r = a / b;
            r * r / (R::ONE + r * r)
        };
    }
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > R::ZERO {
        a2 / (a2 + b2)
    } else {
        R::ZERO
    }
}

/// Where [`power_heuristic`] takes its ratio form (path.wgsl
/// POWER_HEURISTIC_RATIO_ABOVE).
const POWER_HEURISTIC_RATIO_ABOVE: f64 = 1e18;

/// Radiance along the camera ray `ray` (starting on `skip`) by
/// unidirectional path tracing (docs/path-tracing.md): at each vertex,
/// emission (once the path meets an emitting surface or light, weighted by
/// MIS against light sampling), next-event estimation of one light chosen
/// by power, then a BSDF sample to continue; the environment where the path
/// leaves the scene. A path has at most `max_depth` segments, the camera
/// ray being the first (Mitsuba's `max_depth`): 1 sees emitters, 2 adds
/// direct light. Vertex k draws its numbers at key `ROOT_KEY` followed
/// by k `child(key, 1)` steps, slots `SLOT_PATH_*`.
pub fn path<R: Real, E: Effects<R, Light = crate::light::Light<R>>>(
    world: &World<R>,
    fx: &E,
    scene: &crate::distributed::PathScene<R>,
    ray: &Ray<R>,
    key: E::Key,
    skip: E::Prim,
    rays: &mut RayCounts,
) -> R::V3 {
    let max = world.settings.max_depth;
    let lights = fx.lights(world);
    let mut radiance = R::V3::zero();
    let mut throughput = R::V3::splat(R::ONE);
    let (mut ray, mut key, mut skip) = (*ray, key, skip);
    let mut segments = 1u32;
    // Density of the BSDF sample that made this segment; None for the
    // camera ray and delta lobes (nothing else could have found it).
    let mut bsdf_pdf: Option<R> = None;
    if max == 0 {
        return radiance;
    }
    loop {
        let hit = fx.closest(world, &ray, skip);
        let mut t_near = hit.map_or(R::INFINITY, |h| h.0);
        let mut light_hit = None;
        for (i, l) in lights.iter().enumerate() {
            if let Some((t, pdf)) = l.hit(ray.origin, ray.dir, t_near) {
                t_near = t;
                light_hit = Some((i, pdf));
            }
        }
        if let Some((i, pdf)) = light_hit {
            let w = bsdf_pdf.map_or(R::ONE, |b| power_heuristic(b, scene.light_prob[i] * pdf));
            radiance += throughput * lights[i].diffuse * w;
            break;
        }
        let Some(hit) = hit else {
            radiance += throughput * scene.environment;
            if let Some(env) = &scene.environment_map {
                let d = ray.dir.to_array();
                let l = R::V3::from_array(env.radiance(d).map(f64::from));
                let w = match bsdf_pdf {
                    Some(b) if scene.env_prob > R::ZERO => {
                        power_heuristic(b, scene.env_prob * R::from_f64(env.pdf(d)))
                    }
                    _ => R::ONE,
                };
                radiance += throughput * l * w;
            }
            break;
        };
        let s = fx.surface(world, &ray, hit);
        let b = s.bsdf;
        // Arriving at a back side: the segment ran inside this surface's
        // volume (closed, not nested: `Bsdf::absorption`).
        if !s.entering && b.absorption.max_element() > R::ZERO {
            throughput = throughput * b.transmittance(hit.0);
        }
        if s.entering {
            match emitter_density(world, fx, scene, &s) {
                // A light-sampled triangle found by a BSDF sample: MIS
                // against the light pdf of its point (`crate::emitters`).
                Some(density) if let Some(bp) = bsdf_pdf => {
                    let t = hit.0;
                    let pl = density * t * t / s.n.dot(s.v);
                    radiance += throughput * b.emission * power_heuristic(bp, pl);
                }
                _ => radiance += throughput * b.emission,
            }
        }
        if segments >= max {
            break;
        }
        let frame = Frame::<R>::new(s.ns);
        let wo = frame.to_local(s.v);
        // n on the far side over n on the viewer's.
        let eta = if s.entering { b.ior } else { R::ONE / b.ior };
        if !scene.light_cdf.is_empty() && b.has_smooth_lobe() {
            let i = scene.pick(fx.u(key, SLOT_PATH_LIGHT));
            let (u, v) = fx.u2(key, SLOT_PATH_LIGHT + 1);
            // A light's sample and its selection probability; an emissive
            // triangle's density includes its selection already.
            let sample = match lights.get(i) {
                Some(l) => l
                    .sample_li(s.p, u as f64, v as f64)
                    .map(|ls| (ls, scene.light_prob[i])),
                None if scene.env_index() == Some(i) => scene
                    .environment_map
                    .as_ref()
                    .and_then(|env| env.sample(u, v))
                    .map(|es| {
                        let ls = crate::light::LightSample {
                            wi: R::V3::from_array(es.dir),
                            dist: R::from_f64(crate::light::DIRECTIONAL_REACH as f64),
                            li: R::V3::from_array(es.radiance.map(f64::from)),
                            pdf: R::from_f64(es.pdf),
                        };
                        (ls, scene.env_prob)
                    }),
                None => {
                    let e = &scene.emitters[i - scene.first_emitter()];
                    let density = scene.emit_density[e.material as usize];
                    e.sample_li(world, s.p, u, v, density)
                        .map(|ls| (ls, R::ONE))
                }
            };
            if let Some((ls, p_light)) = sample
                && ls.wi.dot(s.n) > R::ZERO
            {
                let (f, pdf_b) = b.eval(wo, frame.to_local(ls.wi), eta);
                if f.max_element() > R::ZERO {
                    rays.shadow += 1;
                    let shadow = Ray::new(s.above, ls.wi);
                    let t_max = ls.dist * (R::ONE - R::SHADOW_SHORTEN);
                    let blocked = fx.occluded(world, &shadow, t_max, s.prim)
                        || lights.iter().enumerate().any(|(j, l)| {
                            j != i && l.hit(shadow.origin, shadow.dir, t_max).is_some()
                        });
                    if !blocked {
                        let c = if ls.pdf > R::ZERO {
                            let pl = p_light * ls.pdf;
                            f * ls.li * (power_heuristic(pl, pdf_b) / pl)
                        } else {
                            f * ls.li * (R::ONE / p_light)
                        };
                        radiance += throughput * c;
                    }
                }
            }
        }
        let (u1, u2) = fx.u2(key, SLOT_PATH_LOBE + 1);
        let u = [fx.u(key, SLOT_PATH_LOBE), u1, u2];
        let Some(bs) = b.sample(wo, eta, u) else {
            break;
        };
        let wi: R::V3 = frame.to_world(bs.wi);
        // A direction on the wrong side of the geometric surface (shading
        // normals) carries nothing.
        let reflected = bs.wi.z() > R::ZERO;
        let side = wi.dot(s.n);
        if (reflected && !(side > R::ZERO)) || (!reflected && !(side < R::ZERO)) {
            break;
        }
        throughput = throughput * bs.weight;
        bsdf_pdf = (!bs.delta).then_some(bs.pdf);
        segments += 1;
        if segments > RR_DEPTH {
            let q = throughput.max_element().min(R::from_f64(0.95));
            if !(R::from_f64(fx.u(key, SLOT_PATH_RR) as f64) < q) {
                break;
            }
            throughput = throughput * (R::ONE / q);
        }
        let origin = if reflected {
            rays.reflection += 1;
            s.above
        } else {
            rays.refraction += 1;
            offset_origin::<R>(s.p, -s.n)
        };
        ray = Ray::new(origin, wi);
        skip = s.prim;
        key = E::child(key, 1);
    }
    radiance
}

/// Whether `id` is a triangle: the world's or an instance's.
#[inline]
fn is_triangle(id: PrimId) -> bool {
    id.kind() == PrimId::TRIANGLE || id.kind() == PrimId::INSTANCE_TRIANGLE
}

/// The selection probability per unit area of the light-sampled emissive
/// triangle under `s`, or `None` where `s` is no such triangle.
#[inline]
fn emitter_density<R: Real, E: Effects<R>>(
    world: &World<R>,
    fx: &E,
    scene: &crate::distributed::PathScene<R>,
    s: &Surface<'_, R, E::Prim>,
) -> Option<R> {
    if scene.emit_density.is_empty() {
        return None;
    }
    let id = fx.static_prim(s.prim)?;
    if !is_triangle(id) {
        return None;
    }
    let material = world.surface(id, s.p).2;
    let d = scene.emit_density[material as usize];
    (d > R::ZERO).then_some(d)
}

/// Adds each light's term at `s` in the lights' order, unless its shadow
/// ray is blocked: a point light's once, an area light's as the mean over
/// its stratified points.
#[inline]
pub fn add_lights<R: Real, E: Effects<R>>(
    world: &World<R>,
    fx: &E,
    s: &Surface<'_, R, E::Prim>,
    key: E::Key,
    rays: &mut RayCounts,
    colour: &mut R::V3,
) {
    for light in fx.lights(world) {
        if let Some(pos) = light.position() {
            if let Some(l) = s.light_term(pos, light) {
                rays.shadow += 1;
                if !fx.occluded(world, &l.shadow, l.t_max, s.prim) {
                    *colour += l.contrib;
                }
            }
            continue;
        }
        let n = light.samples();
        let mut sum = R::V3::zero();
        for i in 0..n {
            let slot = SLOT_LIGHTS + 2 * (light.first_sample() + i);
            let (u, v) = stratified(i, n, fx.u(key, slot), fx.u(key, slot + 1));
            if let Some(l) = s.light_term(light.point(u, v), light) {
                rays.shadow += 1;
                if !fx.occluded(world, &l.shadow, l.t_max, s.prim) {
                    sum += l.contrib;
                }
            }
        }
        *colour += sum * (R::ONE / R::from_u32(n));
    }
}

/// What shading needs of a hit: the point, the normals facing the viewer,
/// the material. The steps of [`shade`] are its methods, so that a driver
/// can trace the shadow rays of many hits together (the recursive CPU
/// driver does, for camera rays) and still add every term in `shade`'s order.
pub struct Surface<'a, R: Real, P> {
    pub prim: P,
    pub p: R::V3,
    /// Geometric normal on the viewer's side, and the shading normal.
    pub n: R::V3,
    pub ns: R::V3,
    pub v: R::V3,
    pub entering: bool,
    pub cos_i: R,
    /// The material at this point (textures looked up: [`material_at`]).
    pub m: Material<R>,
    /// The path integrator's BSDF of the same material at this point.
    pub bsdf: Bsdf<R>,
    /// Origin for rays leaving on the viewer's side.
    pub above: R::V3,
    _world: std::marker::PhantomData<&'a World<R>>,
}

/// A light's term at a surface: what it adds unless `shadow` (which starts
/// on the surface) meets something before `t_max`.
pub struct LightTerm<R: Real> {
    pub contrib: R::V3,
    pub shadow: Ray<R>,
    pub t_max: R,
}

impl<'a, R: Real> Surface<'a, R, PrimId> {
    /// The surface of a hit in the static world.
    #[inline]
    pub fn at(world: &'a World<R>, ray: &Ray<R>, (t, id): (R, PrimId)) -> Self {
        let (p, n_out, material) = world.surface(id, ray.at(t));
        let (m, bsdf) = material_at(world, id, p, material);
        Surface::new(id, p, n_out, ray, m, bsdf, |n, v| {
            shading_normal(world, id, p, material, n, v)
        })
    }
}

/// The material of primitive `id` (of material index `material`) at the
/// point `p`, and its BSDF: the material itself, or, where a model file's
/// textures or vertex colours vary over it, the glTF parameters times the
/// textures there, mapped to Whitted's model and to the BSDF (`Pbr::at`;
/// docs/meshes.md, docs/path-tracing.md).
#[inline]
pub fn material_at<R: Real>(
    world: &World<R>,
    id: PrimId,
    p: R::V3,
    material: u32,
) -> (Material<R>, Bsdf<R>) {
    let m = &world.materials[material as usize];
    match varying_pbr(world, id, material) {
        Some(pbr) => pbr.at(m, &world.attrs_at(id, p)),
        None => (*m, world.bsdfs[material as usize]),
    }
}

/// The emitted radiance of primitive `id` at `p`: [`material_at`]'s
/// emission, without copying a material where nothing varies over it
/// (light sampling asks at every path vertex).
#[inline]
pub fn emission_at<R: Real>(world: &World<R>, id: PrimId, p: R::V3, material: u32) -> R::V3 {
    match varying_pbr(world, id, material) {
        Some(_) => material_at(world, id, p, material).1.emission,
        None => world.bsdfs[material as usize].emission,
    }
}

/// The glTF parameters of material index `material` where textures or
/// vertex colours make them vary over primitive `id` (a triangle); `None`
/// where the material is the same all over it.
#[inline]
fn varying_pbr<R: Real>(world: &World<R>, id: PrimId, material: u32) -> Option<&Pbr> {
    let m = &world.materials[material as usize];
    if m.pbr == NO_PBR || !is_triangle(id) {
        return None;
    }
    let pbr = &world.pbr[m.pbr as usize];
    pbr.varies().then_some(&**pbr)
}

/// The shading normal at `p` on primitive `id` (of material index
/// `material`), given `n`, the geometric normal facing the viewer, and `v`,
/// the direction to the viewer: `World::shading_normal`, tilted by a model
/// material's glTF `normalTexture` where it has one (docs/meshes.md,
/// "Normal maps"): the texel's tangent-space normal (2 c - 1, x and y
/// times `normalTexture.scale`) in the frame of the interpolated vertex
/// normal N, the tangent T made orthogonal to N, and B = w N x T; or by
/// an MTL bump map ([`bumped_normal`]). Reversed where the viewer is on
/// N's far side (a double-sided back face); the untilted normal where the
/// tilted one would face away from the viewer. pbr.wgsl `normal_mapped`
/// is its mirror.
#[inline]
pub fn shading_normal<R: Real>(
    world: &World<R>,
    id: PrimId,
    p: R::V3,
    material: u32,
    n: R::V3,
    v: R::V3,
) -> R::V3 {
    let ns = world.shading_normal(id, p, n, v);
    let m = &world.materials[material as usize];
    if m.pbr == NO_PBR {
        return ns;
    }
    let pbr = &world.pbr[m.pbr as usize];
    if pbr.normal_texture.is_none() && pbr.bump_texture.is_none() {
        return ns;
    }
    let Some(tri) = world.placed_triangle(id) else {
        return ns;
    };
    let normal = tri.normal_at(p);
    let tilted = if let Some(tex) = &pbr.normal_texture {
        let Some((at, t)) = world.tangent_at(id, p) else {
            return ns;
        };
        let c = tex.sample_at(&at);
        let scale = pbr.normal_scale as f32;
        let local = [
            (2.0 * c[0] - 1.0) * scale,
            (2.0 * c[1] - 1.0) * scale,
            2.0 * c[2] - 1.0,
        ]
        .map(|x| R::from_f64(x as f64));
        let tangent = R::V3::from_array([t[0], t[1], t[2]].map(f64::from));
        let along = tangent - normal * normal.dot(tangent);
        let len = along.length();
        if !(len > R::ZERO && len.is_finite()) {
            return ns;
        }
        let along = along * (R::ONE / len);
        let sign = if t[3] < 0.0 { -R::ONE } else { R::ONE };
        let across = normal.cross(along) * sign;
        along * local[0] + across * local[1] + normal * local[2]
    } else if let Some(tex) = &pbr.bump_texture {
        match bumped_normal(world, id, p, tex, pbr.bump_scale, normal) {
            Some(b) => b,
            None => return ns,
        }
    } else {
        return ns;
    };
    let len = tilted.length();
    if !(len > R::ZERO && len.is_finite()) {
        return ns;
    }
    let mut tilted = tilted * (R::ONE / len);
    if normal.dot(n) < R::ZERO {
        tilted = -tilted;
    }
    if tilted.dot(v) > R::ZERO { tilted } else { ns }
}

/// The normal (not unit) of triangle `id`'s surface displaced along its
/// unit normal `normal` by `scale` x the bump map `tex` (a height field,
/// first channel) at `p`: (dp/du + h_u scale N) x (dp/dv + h_v scale N),
/// turned to N's side, with dp/du and dp/dv from the triangle's corners
/// and texture coordinates and the height's derivatives by central
/// differences one texel apart through the texture's filter (Mitsuba's
/// `bumpmap`). `None` where the triangle's texture coordinates span no
/// area. pbr.wgsl `bumped_normal` is its mirror.
fn bumped_normal<R: Real>(
    world: &World<R>,
    id: PrimId,
    p: R::V3,
    tex: &crate::texture::TextureRef,
    scale: f64,
    normal: R::V3,
) -> Option<R::V3> {
    let tri = world.placed_triangle(id)?;
    let a = tri.shading.attrs;
    if a == crate::triangle::NO_ATTRS {
        return None;
    }
    let set = tex.uv_set as usize;
    let uvs = world.attrs.tri[a as usize].map(|k| world.attrs.uv[set][k as usize]);
    let [p0, p1, p2] = tri.corners();
    let (e1, e2) = (p1 - p0, p2 - p0);
    let d1 = [uvs[1][0] - uvs[0][0], uvs[1][1] - uvs[0][1]];
    let d2 = [uvs[2][0] - uvs[0][0], uvs[2][1] - uvs[0][1]];
    let det = d1[0] * d2[1] - d2[0] * d1[1];
    if !(det != 0.0 && det.is_finite()) {
        return None;
    }
    let f = |x: f32| R::from_f64(x as f64);
    let inv = f(1.0 / det);
    let dpdu = (e1 * f(d2[1]) - e2 * f(d1[1])) * inv;
    let dpdv = (e2 * f(d1[0]) - e1 * f(d2[0])) * inv;
    let [u, v] = world.attrs_at(id, p).uv[set];
    let (du, dv) = (1.0 / tex.image.width as f32, 1.0 / tex.image.height as f32);
    let h = |u: f32, v: f32| tex.sample([u, v])[0];
    let hu = (h(u + du, v) - h(u - du, v)) / (2.0 * du);
    let hv = (h(u, v + dv) - h(u, v - dv)) / (2.0 * dv);
    let k = scale as f32;
    let pu = dpdu + normal * f(hu * k);
    let pv = dpdv + normal * f(hv * k);
    let b = pu.cross(pv);
    Some(if b.dot(normal) < R::ZERO { -b } else { b })
}

impl<'a, R: Real, P: Copy> Surface<'a, R, P> {
    /// The surface at `p` with outward normal `n_out`, seen along `ray`;
    /// `shading` gives the shading normal from the facing normal and the
    /// direction to the viewer.
    #[inline]
    pub fn new(
        prim: P,
        p: R::V3,
        n_out: R::V3,
        ray: &Ray<R>,
        m: Material<R>,
        bsdf: Bsdf<R>,
        shading: impl FnOnce(R::V3, R::V3) -> R::V3,
    ) -> Self {
        let v = -ray.dir;
        // Entering: arriving against the outward normal.
        let entering = n_out.dot(v) >= R::ZERO;
        let n = if entering { n_out } else { -n_out };
        // Shading normal: differs from n only on smoothly shaded triangles.
        let ns = shading(n, v);
        Surface {
            prim,
            p,
            n,
            ns,
            v,
            entering,
            cos_i: ns.dot(v),
            m,
            bsdf,
            above: offset_origin::<R>(p, n),
            _world: std::marker::PhantomData,
        }
    }

    /// The ambient term and the emission, where the colour starts (the
    /// emission only where there is one: adding a zero could turn a -0).
    #[inline]
    pub fn ambient(&self, world: &World<R>) -> R::V3 {
        let a = world.ambient * self.m.ambient;
        if self.m.pbr == NO_PBR {
            a
        } else {
            a + self.m.emission
        }
    }

    /// The term of `light` with its point at `pos`, or `None` when it can
    /// add nothing (then it needs no shadow ray).
    #[inline]
    pub fn light_term(&self, pos: R::V3, light: &impl Emitter<R>) -> Option<LightTerm<R>> {
        let (p, n) = (self.p, self.n);
        let to_light = pos - p;
        let dist = to_light.length();
        if !(dist > R::ZERO) {
            return None;
        }
        let l = to_light * (R::ONE / dist);
        let [diffuse, specular] = light.colours();
        let contrib = self.m.blinn_phong(self.ns, self.v, l, diffuse, specular);
        // Not `<= 0`: an all-NaN term adds nothing either, as in the lanes.
        if !(contrib.max_element() > R::ZERO) {
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
    /// `depth + 1`, traced recursively), if `depth` allows. With cones, each
    /// direction is drawn from its cone, and one that leaves on the wrong
    /// side of the surface contributes black.
    #[inline]
    pub fn add_secondary<E: Effects<R, Prim = P>>(
        &self,
        world: &World<R>,
        fx: &E,
        depth: u32,
        key: E::Key,
        rays: &mut RayCounts,
        colour: &mut R::V3,
    ) {
        if depth >= world.settings.max_depth {
            return;
        }
        let m = &self.m;
        let (p, n) = (self.p, self.n);
        let mut reflect_w = m.reflectivity;
        if m.transparency > R::ZERO {
            match m.refract(self.v, self.ns, self.cos_i, self.entering) {
                None => reflect_w += m.transparency, // total internal reflection
                Some(dir) => {
                    let cos = m.translucency_cos;
                    if let Some(dir) = in_cone(fx, key, SLOT_TRANSLUCENCY, dir, cos, n, false) {
                        rays.refraction += 1;
                        let refr = Ray::new(offset_origin::<R>(p, -n), dir);
                        let c = trace(
                            world,
                            fx,
                            &refr,
                            depth + 1,
                            E::child(key, 0),
                            self.prim,
                            rays,
                        );
                        *colour += c * m.transparency;
                    }
                }
            }
        }
        if reflect_w > R::ZERO {
            let dir = reflect::<R>(self.v, self.ns, self.cos_i);
            if let Some(dir) = in_cone(fx, key, SLOT_GLOSS, dir, m.gloss_cos, n, true) {
                rays.reflection += 1;
                let refl = Ray::new(self.above, dir);
                *colour += trace(
                    world,
                    fx,
                    &refl,
                    depth + 1,
                    E::child(key, 1),
                    self.prim,
                    rays,
                ) * reflect_w;
            }
        }
    }
}

/// `dir`, or, where the effects have cones and the material's is wider
/// than a point (`cos_max` < 1), a direction drawn from the cone around it
/// with the numbers at `slot` of node `key`; `None` when the drawn one
/// leaves on the wrong side of the surface (below it for a reflection,
/// `above`; above it for a refraction): that ray contributes black.
#[inline]
fn in_cone<R: Real, E: Effects<R>>(
    fx: &E,
    key: E::Key,
    slot: u32,
    dir: R::V3,
    cos_max: R,
    n: R::V3,
    above: bool,
) -> Option<R::V3> {
    if !(E::CONES && cos_max < R::ONE) {
        return Some(dir);
    }
    let d = cone(dir, cos_max, fx.u(key, slot), fx.u(key, slot + 1));
    let side = d.dot(n);
    let ok = if above {
        side > R::ZERO
    } else {
        side < R::ZERO
    };
    ok.then_some(d)
}

#[cfg(test)]
mod tests {
    use super::power_heuristic;

    #[test]
    fn the_power_heuristic_holds_for_densities_whose_squares_overflow_f32() {
        // The NaN examples/distributed.toml made with --integrator path: a
        // quad light's density 2.1e19 seen edge-on against a BSDF's 0.0127.
        let (light, bsdf) = (2.121_869_9e19f32, 0.012_712_306f32);
        assert!((light * light).is_infinite(), "the case overflows f32");
        assert_eq!(power_heuristic(light, bsdf), 1.0);
        let w = power_heuristic(bsdf, light);
        assert!((0.0..1e-40).contains(&w), "{w}");
        assert_eq!(power_heuristic(3e23f32, 3e23), 0.5);
        assert_eq!(power_heuristic(f32::INFINITY, 1.0), 1.0);
        // Below the switch the squares as before, bit for bit.
        for (a, b) in [(3.0f32, 4.0f32), (0.25, 1e9), (9e17, 2.0), (0.0, 0.0)] {
            let (a2, b2) = (a * a, b * b);
            let old = if a2 + b2 > 0.0 { a2 / (a2 + b2) } else { 0.0 };
            assert_eq!(power_heuristic(a, b).to_bits(), old.to_bits(), "{a}, {b}");
        }
        assert_eq!(power_heuristic(3.0f64, 4.0), 9.0 / 25.0);
    }
}
