//! import shade.wgsl
//! import bsdf.wgsl
//! import sums.wgsl
//! import stack.wgsl
// The path integrator on the GPU (`--integrator path`): render/step.rs
// `path`, one invocation per pixel-sample looping over its segments, with
// the same random numbers as the CPU (vertex k at key ROOT_KEY followed by
// k child_key(key, 1) steps, slots SLOT_PATH_*), the same light choice by
// power, next-event estimation with the power heuristic, Russian roulette
// after RR_DEPTH segments and the environment (a colour, and an image
// light-sampled as a light: environment.rs). A path scene is
// always a distributed one (World::dist): its lights, lens and motion are
// distributed.wgsl's. The lights' selection and the materials' BSDFs
// follow the distributed words at PATH_BASE (layout.rs `PathData`);
// textured model materials and cut-outs are pbr.wgsl's (`bsdf_at`).

override PATH_BASE: u32 = 0u;
// Some light emits: next-event estimation (PathScene's light_cdf not empty).
override PATH_NEE: bool = false;
// Emissive triangles selected after the lights (emitters.rs), 4 words each
// from PATH_EMIT_BASE (layout.rs `PathData`).
override PATH_EMITTERS: u32 = 0u;
override PATH_EMIT_BASE: u32 = 0u;

// The environment image's words (layout.rs `PathData`; 0: none).
override PATH_ENV_BASE: u32 = 0u;

const SLOT_PATH_LIGHT: u32 = 0u;
const SLOT_PATH_LOBE: u32 = 3u;
const SLOT_PATH_RR: u32 = 6u;
// step.rs RR_DEPTH.
const RR_DEPTH: u32 = 5u;

// dist[PATH_BASE]: environment (w: the image's selection probability); then per light (probability, first 24-bit
// number that picks past it); then PATH_MATERIAL_WORDS words per material
// (layout.rs `PathData::MATERIAL_WORDS`).
const PATH_MATERIAL_WORDS: u32 = 5u;
fn path_bsdf(material: u32) -> Bsdf {
    let base = PATH_BASE + 1u + N_DLIGHTS + PATH_MATERIAL_WORDS * material;
    let a = dist[base];
    let b = dist[base + 1u];
    let c = dist[base + 2u];
    let d = dist[base + 3u];
    return Bsdf(a.xyz, a.w, b.xyz, b.w, c.xyz, c.w, d.x, d.y, d.z, dist[base + 4u].xyz);
}

// render/step.rs `material_at`'s BSDF: the material's, or where a model
// file's textures or vertex colours vary over it, material.rs `Pbr::bsdf`
// (an MTL material: `Bsdf::from_material` of the tinted diffuse) of
// pbr.wgsl's lookup at p.
fn bsdf_at(id: u32, p: vec3<f32>, material: u32) -> Bsdf {
    var b = path_bsdf(material);
    let pi = pbr_index(id, material);
    if (pi == NONE) {
        return b;
    }
    let pb = pbrs[pi];
    if ((pb.flags & PBR_VARIES) == 0u) {
        return b;
    }
    let at = pbr_at(pb, id, p);
    b.emission = at.emission;
    if ((pb.flags & PBR_MTL) != 0u) {
        if (!(b.transmission > 0.0)) {
            b.base = clamp(materials[material].diffuse * at.base.xyz, vec3<f32>(0.0), vec3<f32>(1.0));
        }
        return b;
    }
    var blend = 0.0;
    if ((pb.flags & PBR_BLEND) != 0u) {
        blend = clamp(1.0 - at.base.w, 0.0, 1.0);
    }
    b.base = clamp(at.base.xyz, vec3<f32>(0.0), vec3<f32>(1.0));
    b.metallic = clamp(at.metallic, 0.0, 1.0);
    b.roughness = clamp(at.roughness, 0.0, 1.0);
    b.transmission = max(clamp(pb.transmission, 0.0, 1.0), blend);
    return b;
}

fn light_prob(li: u32) -> f32 {
    return dist[PATH_BASE + 1u + li].x;
}

// PathScene::pick: the first light (then emissive triangle) whose running
// sum exceeds u, compared exactly as 24-bit integers (u has 24 bits; the
// host rounded each sum up); the triangles' sums by bisection.
fn pick_light(u: f32) -> u32 {
    let k = u32(u * 16777216.0);
    var i = 0u;
    for (var j = 0u; j < N_DLIGHTS; j++) {
        if (bitcast<u32>(dist[PATH_BASE + 1u + j].y) <= k) {
            i = j + 1u;
        }
    }
    // The environment image's entry follows the lights.
    let first_emitter = path_first_emitter();
    if (PATH_EMITTERS == 0u) {
        return min(i, first_emitter - 1u);
    }
    if (i < N_DLIGHTS) {
        return i;
    }
    if (PATH_ENV_BASE != 0u && bitcast<u32>(dist[PATH_ENV_BASE].x) > k) {
        return N_DLIGHTS;
    }
    var lo = 0u;
    var hi = PATH_EMITTERS;
    while (lo < hi) {
        let mid = (lo + hi) / 2u;
        if (bitcast<u32>(dist[PATH_EMIT_BASE + 4u * mid].w) <= k) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return first_emitter + min(lo, max(PATH_EMITTERS, 1u) - 1u);
}

// PathScene::first_emitter: the selection index of the first emissive triangle.
fn path_first_emitter() -> u32 {
    return N_DLIGHTS + select(0u, 1u, PATH_ENV_BASE != 0u);
}

// ---- The environment image: environment.rs, line for line ----------------

fn env_w() -> u32 {
    return bitcast<u32>(dist[PATH_ENV_BASE].y);
}

fn env_h() -> u32 {
    return bitcast<u32>(dist[PATH_ENV_BASE].z);
}

// Float i of the floats packed 4 to a word from word `start`.
fn env_float(start: u32, i: u32) -> f32 {
    return dist[start + i / 4u][i % 4u];
}

fn env_row_cdf_start() -> u32 {
    return PATH_ENV_BASE + 1u + env_w() * env_h();
}

fn env_marginal_start() -> u32 {
    return env_row_cdf_start() + (env_w() * (env_h() - 1u) + 3u) / 4u;
}

// EnvironmentMap::uv_of.
fn env_uv(d: vec3<f32>) -> vec2<f32> {
    var u = atan2(d.x, -d.z) / BSDF_TWO_PI - dist[PATH_ENV_BASE].w;
    u = u - floor(u);
    return vec2<f32>(u, acos(clamp(d.y, -1.0, 1.0)) / BSDF_PI);
}

// EnvironmentMap::lookup: bilinear, columns centred, rows at the poles.
fn env_lookup(uv: vec2<f32>) -> vec3<f32> {
    let w = env_w();
    let h = env_h();
    var xf = uv.x - 0.5 / f32(w);
    xf = (xf - floor(xf)) * f32(w);
    let x0 = min(u32(floor(xf)), w - 1u);
    let x1 = (x0 + 1u) % w;
    let fx = xf - f32(x0);
    let yf = clamp(uv.y, 0.0, 1.0) * f32(h - 1u);
    let y0 = min(u32(floor(yf)), h - 2u);
    let fy = yf - f32(y0);
    let t = PATH_ENV_BASE + 1u;
    let top = mix(dist[t + y0 * w + x0].xyz, dist[t + y0 * w + x1].xyz, fx);
    let bottom = mix(dist[t + (y0 + 1u) * w + x0].xyz, dist[t + (y0 + 1u) * w + x1].xyz, fx);
    return mix(top, bottom, fy);
}

fn env_radiance(d: vec3<f32>) -> vec3<f32> {
    return env_lookup(env_uv(d));
}

// EnvironmentMap::pdf: the density at d over 2 pi^2 sin theta.
fn env_pdf(d: vec3<f32>) -> f32 {
    let uv = env_uv(d);
    let sin_t = sqrt(d.x * d.x + d.z * d.z);
    if (!(sin_t > 0.0)) {
        return 0.0;
    }
    let w = env_w();
    let rows = env_h() - 1u;
    var xf = uv.x - 0.5 / f32(w);
    xf = (xf - floor(xf)) * f32(w);
    let x = min(u32(floor(xf)), w - 1u);
    let yf = clamp(uv.y, 0.0, 1.0) * f32(rows);
    let y = min(u32(floor(yf)), rows - 1u);
    return env_density_at(x, y, xf - f32(x), yf - f32(y)) / (2.0 * BSDF_PI * BSDF_PI * sin_t);
}

// EnvironmentMap::corners: the luminances of cell (x, y)'s corners.
fn env_corners(x: u32, y: u32) -> vec4<f32> {
    let w = env_w();
    let t = PATH_ENV_BASE + 1u;
    let x1 = (x + 1u) % w;
    let third = vec3<f32>(1.0 / 3.0);
    return vec4<f32>(
        dot(dist[t + y * w + x].xyz, third),
        dot(dist[t + y * w + x1].xyz, third),
        dot(dist[t + (y + 1u) * w + x].xyz, third),
        dot(dist[t + (y + 1u) * w + x1].xyz, third),
    );
}

// EnvironmentMap::density_at: the density over (u, v) within cell (x, y).
fn env_density_at(x: u32, y: u32, fx: f32, fy: f32) -> f32 {
    let cell = dist[PATH_ENV_BASE + 1u + y * env_w() + x].w;
    if (!(cell > 0.0)) {
        return 0.0;
    }
    let c = env_corners(x, y);
    let mean = (c.x + c.y + c.z + c.w) / 4.0;
    return cell * mix(mix(c.x, c.y, fx), mix(c.z, c.w, fx), fy) / mean;
}

// environment.rs `sample_linear`.
fn env_linear(u: f32, a: f32, b: f32) -> f32 {
    if (!(a + b > 0.0) || (u == 0.0 && a == 0.0)) {
        return u;
    }
    let x = u * (a + b) / (a + sqrt(mix(a * a, b * b, u)));
    return min(x, 0.99999994);
}

// environment.rs `pick`: the first of n running sums from float `first` of
// the floats at `start` above u, and where u lies in its step.
fn env_pick(start: u32, first: u32, n: u32, u: f32) -> vec2<f32> {
    var lo = 0u;
    var hi = n;
    while (lo < hi) {
        let mid = (lo + hi) / 2u;
        if (env_float(start, first + mid) <= u) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    let i = min(lo, n - 1u);
    var below = 0.0;
    if (i > 0u) {
        below = env_float(start, first + i - 1u);
    }
    let above = env_float(start, first + i);
    var f = 0.5;
    if (above > below) {
        f = clamp((u - below) / (above - below), 0.0, 0.99999994);
    }
    return vec2<f32>(f32(i), f);
}

// EnvironmentMap::sample: a cell by the CDFs, a point in it by its
// corners' bilinear luminance.
fn env_sample(a: f32, b: f32) -> LightSample {
    var ls: LightSample;
    ls.ok = false;
    let w = env_w();
    let rows = env_h() - 1u;
    let ry = env_pick(env_marginal_start(), 0u, rows, a);
    let y = u32(ry.x);
    let rx = env_pick(env_row_cdf_start(), y * w, w, b);
    let x = u32(rx.x);
    let c = env_corners(x, y);
    let fy = env_linear(ry.y, c.x + c.y, c.z + c.w);
    let fx = env_linear(rx.y, mix(c.x, c.z, fy), mix(c.y, c.w, fy));
    let density = env_density_at(x, y, fx, fy);
    if (!(density > 0.0)) {
        return ls;
    }
    let u = (f32(x) + 0.5 + fx) / f32(w);
    let v = (f32(y) + fy) / f32(rows);
    let theta = v * BSDF_PI;
    let sin_t = sin(theta);
    if (!(sin_t > 0.0)) {
        return ls;
    }
    let phi = BSDF_TWO_PI * (u + dist[PATH_ENV_BASE].w);
    ls.wi = vec3<f32>(sin(phi) * sin_t, cos(theta), -cos(phi) * sin_t);
    ls.dist = DIRECTIONAL_REACH;
    ls.li = env_lookup(vec2<f32>(u - floor(u), v));
    ls.pdf = density / (2.0 * BSDF_PI * BSDF_PI * sin_t);
    ls.ok = true;
    return ls;
}

// PathScene::emit_density of a GPU material (0: not light-sampled).
fn emit_density(material: u32) -> f32 {
    return dist[PATH_BASE + 1u + N_DLIGHTS + PATH_MATERIAL_WORDS * material + 3u].w;
}

// emitters.rs `TriEmitter::sample_li` of emissive triangle k: a point
// uniform by area, its pdf the selection's and the point's together.
fn emitter_sample(k: u32, p: vec3<f32>, u: f32, v: f32) -> LightSample {
    let base = PATH_EMIT_BASE + 4u * k;
    let e1 = dist[base + 1u];
    let e2 = dist[base + 2u].xyz;
    let n = dist[base + 3u].xyz;
    let material = bitcast<u32>(e1.w);
    var out = LightSample(vec3<f32>(0.0), 0.0, vec3<f32>(0.0), 0.0, false);
    let su = sqrt(u);
    let b2 = v * su;
    let x = dist[base].xyz + e1.xyz * (su - b2) + e2 * b2;
    let d = x - p;
    let dd = length(d);
    if (!(dd > 0.0)) {
        return out;
    }
    let wi = d * (1.0 / dd);
    let cos_l = -dot(n, wi);
    if (!(cos_l > 0.0)) {
        return out;
    }
    let pdf = emit_density(material) * dd * dd / cos_l;
    // The emission at the sampled point, as a hit there reads it (a
    // textured one from its texel: emitters.rs `sample_li`).
    let id = bitcast<u32>(dist[base + 2u].w);
    return LightSample(wi, dd, bsdf_at(id, x, material).emission, pdf, true);
}

// step.rs POWER_HEURISTIC_RATIO_ABOVE: past it the squares could overflow.
const POWER_HEURISTIC_RATIO_ABOVE: f32 = 1e18;

fn power_heuristic(a: f32, b: f32) -> f32 {
    if (a > POWER_HEURISTIC_RATIO_ABOVE || b > POWER_HEURISTIC_RATIO_ABOVE) {
        if (a >= b) {
            let r = b / a;
            return 1.0 / (1.0 + r * r);
        }
        let r = a / b;
        return r * r / (1.0 + r * r);
    }
    let a2 = a * a;
    let b2 = b * b;
    if (a2 + b2 > 0.0) {
        return a2 / (a2 + b2);
    }
    return 0.0;
}

fn sphere_t(o: vec3<f32>, d: vec3<f32>, c: vec3<f32>, r: f32) -> f32 {
    let oc = o - c;
    let b = dot(oc, d);
    let disc = b * b - (dot(oc, oc) - r * r);
    if (disc < 0.0) {
        return -1.0;
    }
    let s = sqrt(disc);
    let t0 = -b - s;
    let t1 = -b + s;
    if (t0 > 0.0) {
        return t0;
    }
    if (t1 > 0.0) {
        return t1;
    }
    return -1.0;
}

// light.rs `Light::hit`: (t, solid-angle pdf of sampling the light there),
// t < 0 where the ray does not meet it before t_max.
fn path_light_hit(li: u32, o: vec3<f32>, d: vec3<f32>, t_max: f32) -> vec2<f32> {
    let base = DIST_LIGHTS + 5u * li;
    let e0 = dist[base];
    let e1 = dist[base + 1u];
    let kind = bitcast<u32>(e0.w);
    if (kind == 1u) {
        let corner = e0.xyz;
        let eu = e1.xyz;
        let ev = dist[base + 2u].xyz;
        let n = cross(eu, ev);
        let denom = dot(n, d);
        if (denom == 0.0) {
            return vec2<f32>(-1.0, 0.0);
        }
        let t = dot(n, corner - o) / denom;
        if (!(t > 0.0 && t < t_max)) {
            return vec2<f32>(-1.0, 0.0);
        }
        let q = o + d * t - corner;
        let nn = dot(n, n);
        let a = dot(cross(q, ev), n) / nn;
        let b = dot(cross(eu, q), n) / nn;
        if (!(a >= 0.0 && a <= 1.0 && b >= 0.0 && b <= 1.0)) {
            return vec2<f32>(-1.0, 0.0);
        }
        let area = sqrt(nn);
        let cos_l = abs(denom) / area;
        return vec2<f32>(t, t * t / (area * cos_l));
    }
    if (kind == 2u) {
        let c = e0.xyz;
        let r = e1.w;
        let t = sphere_t(o, d, c, r);
        if (!(t > 0.0) || !(t < t_max)) {
            return vec2<f32>(-1.0, 0.0);
        }
        let dc = length(c - o);
        if (!(dc > r)) {
            return vec2<f32>(t, 0.0);
        }
        return vec2<f32>(t, cone_pdf(r * r / (dc * dc)));
    }
    return vec2<f32>(-1.0, 0.0);
}

// light.rs `LightSample`; ok false where sample_li gives None.
struct LightSample {
    wi: vec3<f32>,
    dist: f32,
    li: vec3<f32>,
    pdf: f32,
    ok: bool,
}

// light.rs DIRECTIONAL_REACH: a directional light's shadow rays' length.
const DIRECTIONAL_REACH: f32 = 1e30;

// light.rs `Light::sample_li`.
fn path_sample_li(li: u32, p: vec3<f32>, u: f32, v: f32) -> LightSample {
    let base = DIST_LIGHTS + 5u * li;
    let e0 = dist[base];
    let e1 = dist[base + 1u];
    let radiance = dist[base + 3u].xyz;
    let kind = bitcast<u32>(e0.w);
    var out = LightSample(vec3<f32>(0.0), 0.0, vec3<f32>(0.0), 0.0, false);
    if (kind == 0u) {
        let d = e0.xyz - p;
        let dd = length(d);
        if (dd > 0.0) {
            out = LightSample(d * (1.0 / dd), dd, radiance * (1.0 / (dd * dd)), 0.0, true);
        }
        return out;
    }
    if (kind == 1u) {
        let eu = e1.xyz;
        let ev = dist[base + 2u].xyz;
        let x = e0.xyz + eu * u + ev * v;
        let d = x - p;
        let dd = length(d);
        let n = cross(eu, ev);
        let area = length(n);
        if (!(dd > 0.0 && area > 0.0)) {
            return out;
        }
        let wi = d * (1.0 / dd);
        let cos_l = abs(dot(n, wi)) / area;
        if (cos_l > 0.0) {
            out = LightSample(wi, dd, radiance, dd * dd / (area * cos_l), true);
        }
        return out;
    }
    if (kind == 3u) {
        // A spot: a point light times glTF's cone falloff (scale, offset).
        let sc = dist[base + 2u].xyz;
        let d = e0.xyz - p;
        let dd = length(d);
        if (!(dd > 0.0)) {
            return out;
        }
        let wi = d * (1.0 / dd);
        let a = min(-dot(e1.xyz, wi) * sc.x + sc.y, 1.0);
        if (a > 0.0) {
            out = LightSample(wi, dd, radiance * (a * a / (dd * dd)), 0.0, true);
        }
        return out;
    }
    if (kind == 4u) {
        // Directional: the irradiance along its direction, from no distance.
        return LightSample(-e1.xyz, DIRECTIONAL_REACH, radiance, 0.0, true);
    }
    let c = e0.xyz;
    let r = e1.w;
    let d = c - p;
    let dc = length(d);
    if (!(dc > r)) {
        return out;
    }
    let axis = d * (1.0 / dc);
    let sin2 = r * r / (dc * dc);
    let cos_max = sqrt(max(1.0 - sin2, 0.0));
    let wi = cone(axis, cos_max, u, v);
    var t = sphere_t(p, wi, c, r);
    if (!(t > 0.0)) {
        t = dc;
    }
    return LightSample(wi, t, radiance, cone_pdf(sin2), true);
}

// The density of a direction uniform in a sphere's cone, from sin² of its
// half-angle, with 1 - cos as sin² / (1 + cos) (light.rs `cone_pdf`: the
// difference is 0 in f32 for a small, far light).
fn cone_pdf(sin2: f32) -> f32 {
    let cos_max = sqrt(max(1.0 - sin2, 0.0));
    return (1.0 + cos_max) / (BSDF_TWO_PI * sin2);
}

fn path_u(seed: u32, s: u32, key: u32, slot: u32) -> f32 {
    return uniform01(seed, s, node_dim(key, slot));
}

// step.rs `Effects::u2` as `Sampled` draws it: slots slot and slot + 1
// stratified over frame.grid_n (sampling.rs `strata_side`).
fn path_u2(seed: u32, s: u32, key: u32, slot: u32) -> vec2<f32> {
    return uniform_pair(seed, s, frame.grid_n, node_dim(key, slot));
}

// A path between segments: render/step.rs `path`'s loop state.
struct PathState {
    o: vec3<f32>,
    // Negative: no density (the camera ray, a delta lobe).
    bsdf_pdf: f32,
    d: vec3<f32>,
    key: u32,
    throughput: vec3<f32>,
    skip: u32,
    radiance: vec3<f32>,
    segments: u32,
}

fn path_start(origin: vec3<f32>, dir: vec3<f32>) -> PathState {
    return PathState(origin, -1.0, dir, ROOT_KEY, vec3<f32>(1.0), NONE, vec3<f32>(0.0), 1u);
}

// One segment of a path: render/step.rs `path`'s loop body, line for line.
// Returns whether the path goes on; either way `st.radiance` holds what it
// has gathered. The stack driver (`radiance`) loops over it, the
// wavefront driver (path_wave.wgsl) runs it once a generation.
fn path_step(st: ptr<function, PathState>, seed: u32, s: u32, tau: f32) -> bool {
    let hit = closest_through(st.o, st.d, st.skip, tau);
    var t_near = BIG;
    if (hit.id != NONE) {
        t_near = hit.t;
    }
    var light_hit = NONE;
    var light_pdf = 0.0;
    for (var li = 0u; li < N_DLIGHTS; li++) {
        let lh = path_light_hit(li, st.o, st.d, t_near);
        if (lh.x > 0.0) {
            t_near = lh.x;
            light_hit = li;
            light_pdf = lh.y;
        }
    }
    if (light_hit != NONE) {
        var w = 1.0;
        if (st.bsdf_pdf >= 0.0) {
            w = power_heuristic(st.bsdf_pdf, light_prob(light_hit) * light_pdf);
        }
        st.radiance += st.throughput * dist[DIST_LIGHTS + 5u * light_hit + 3u].xyz * w;
        return false;
    }
    if (hit.id == NONE) {
        st.radiance += st.throughput * dist[PATH_BASE].xyz;
        if (PATH_ENV_BASE != 0u) {
            var w = 1.0;
            let pe = dist[PATH_BASE].w;
            if (st.bsdf_pdf >= 0.0 && pe > 0.0) {
                w = power_heuristic(st.bsdf_pdf, pe * env_pdf(st.d));
            }
            st.radiance += st.throughput * env_radiance(st.d) * w;
        }
        return false;
    }
    let sf = surface_at(Ray(st.o, 1.0, st.d, 0u, st.skip, st.key), hit, tau);
    let b = bsdf_at(sf.id, sf.p, sf.material);
    // step.rs: a back side ends a segment that ran inside its volume.
    if (!sf.entering && bsdf_max3(b.absorption) > 0.0) {
        st.throughput = st.throughput * exp(-b.absorption * hit.t);
    }
    if (sf.entering) {
        // A light-sampled triangle found by a BSDF sample (step.rs
        // `emitter_density`): MIS against its point's light pdf.
        var density = 0.0;
        let kind = hit.id >> KIND_SHIFT;
        if (PATH_EMITTERS > 0u && ((kind == KIND_TRIANGLE && moving_mesh_of(hit.id) == NONE) || kind == KIND_INSTANCE_TRIANGLE)) {
            density = emit_density(sf.material);
        }
        if (density > 0.0 && st.bsdf_pdf >= 0.0) {
            let pl = density * hit.t * hit.t / dot(sf.n, sf.v);
            st.radiance += st.throughput * b.emission * power_heuristic(st.bsdf_pdf, pl);
        } else {
            st.radiance += st.throughput * b.emission;
        }
    }
    if (st.segments >= MAX_DEPTH) {
        return false;
    }
    let fr = shading_frame(sf.ns);
    let wo = to_local(fr, sf.v);
    let eta = select(1.0 / b.ior, b.ior, sf.entering);
    if (PATH_NEE && has_smooth_lobe(b)) {
        let i = pick_light(path_u(seed, s, st.key, SLOT_PATH_LIGHT));
        let luv = path_u2(seed, s, st.key, SLOT_PATH_LIGHT + 1u);
        let lu = luv.x;
        let lv = luv.y;
        // A light's sample and selection probability; an emissive
        // triangle's pdf includes its selection already.
        var ls: LightSample;
        var p_light = 1.0;
        if (i < N_DLIGHTS) {
            ls = path_sample_li(i, sf.p, lu, lv);
            p_light = light_prob(i);
        } else if (PATH_ENV_BASE != 0u && i == N_DLIGHTS) {
            ls = env_sample(lu, lv);
            p_light = dist[PATH_BASE].w;
        } else {
            ls = emitter_sample(i - path_first_emitter(), sf.p, lu, lv);
        }
        if (ls.ok && dot(ls.wi, sf.n) > 0.0) {
            let e = bsdf_eval(b, wo, to_local(fr, ls.wi), eta);
            if (bsdf_max3(e.xyz) > 0.0) {
                tally[C_SHADOW] += 1u;
                let t_max = ls.dist * (1.0 - SHADOW_SHORTEN);
                var blocked = occluded_through(sf.above, ls.wi, t_max, sf.id, tau);
                for (var j = 0u; j < N_DLIGHTS; j++) {
                    if (!blocked && j != i && path_light_hit(j, sf.above, ls.wi, t_max).x > 0.0) {
                        blocked = true;
                    }
                }
                if (!blocked) {
                    var c: vec3<f32>;
                    if (ls.pdf > 0.0) {
                        let pl = p_light * ls.pdf;
                        c = e.xyz * ls.li * (power_heuristic(pl, e.w) / pl);
                    } else {
                        c = e.xyz * ls.li * (1.0 / p_light);
                    }
                    st.radiance += st.throughput * c;
                }
            }
        }
    }
    let u = vec3<f32>(
        path_u(seed, s, st.key, SLOT_PATH_LOBE),
        path_u2(seed, s, st.key, SLOT_PATH_LOBE + 1u),
    );
    let bs = bsdf_sample(b, wo, eta, u);
    if (!bs.ok) {
        return false;
    }
    let wi = to_world(fr, bs.wi);
    // A direction on the wrong side of the geometric surface (shading
    // normals) carries nothing.
    let reflected = bs.wi.z > 0.0;
    let side = dot(wi, sf.n);
    if ((reflected && !(side > 0.0)) || (!reflected && !(side < 0.0))) {
        return false;
    }
    st.throughput = st.throughput * bs.weight;
    st.bsdf_pdf = select(bs.pdf, -1.0, bs.delta);
    st.segments += 1u;
    if (st.segments > RR_DEPTH) {
        let q = min(bsdf_max3(st.throughput), 0.95);
        if (!(path_u(seed, s, st.key, SLOT_PATH_RR) < q)) {
            return false;
        }
        st.throughput = st.throughput * (1.0 / q);
    }
    if (reflected) {
        tally[C_REFLECTION] += 1u;
        st.o = sf.above;
    } else {
        tally[C_REFRACTION] += 1u;
        st.o = offset_origin(sf.p, -sf.n);
    }
    st.d = wi;
    st.skip = sf.id;
    st.key = child_key(st.key, 1u);
    return true;
}

// Radiance along the camera ray (stack.wgsl's `radiance`): render/step.rs
// `path`.
fn radiance(origin: vec3<f32>, dir: vec3<f32>, seed: u32, s: u32, tau: f32) -> vec3<f32> {
    var st = path_start(origin, dir);
    if (MAX_DEPTH == 0u) {
        return st.radiance;
    }
    loop {
        if (!path_step(&st, seed, s, tau)) {
            break;
        }
    }
    return st.radiance;
}
