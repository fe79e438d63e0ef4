//! import whitted.wgsl
//! uses moving_meshes_closest moving_meshes_occluded moving_mesh_of moving_mesh_surface: moving_meshes.wgsl or no_moving_meshes.wgsl
// Distributed ray tracing on the GPU (issue 16): area lights, gloss and
// translucency cones, the thin lens, motion over the shutter. The port of
// `render/cpu/distributed.rs`, step by step, with the same random numbers
// (sampling.rs: dimensions 2, 3 for the lens, 4 for the time, node keys
// and slots for the rest). Compiled in only for worlds with `World::dist`; entry point `render_dist`.
// Moving meshes' queries come from moving_meshes.wgsl (after bvh.wgsl),
// compiled in only for worlds that have them, else from
// no_moving_meshes.wgsl, where they do nothing.
// Keep in sync with layout.rs `DistData` (the packing of `dist`).

// dist[0]: unit right, aperture; [1]: unit up, focus distance (<= 0: the
// pose's look distance); [2]: camera displacement over the shutter, look
// distance; [3]: look_at (opening), fov_y (degrees); [4]: look_at change,
// fov_y change; [5]: up (unit), aspect. Then 5 entries per light (see
// `light_point`), 2 per moving sphere and 3 per moving mesh (see
// moving_meshes.wgsl). The binding (`dist`, 12): wgsl.rs SCENE.

override N_DLIGHTS: u32 = 0u;
override N_MOVING: u32 = 0u;
override HAS_LENS: bool = false;
override HAS_BLUR: bool = false;
override HAS_CAM_MOTION: bool = false;

const DIST_LIGHTS: u32 = 6u;
const KIND_MOVING: u32 = 8u;
const TWO_PI: f32 = 6.2831853;
const DIM_LENS: u32 = 2u;
const DIM_TIME: u32 = 4u;
const ROOT_KEY: u32 = 1u;
const SLOT_GLOSS: u32 = 0u;
const SLOT_TRANSLUCENCY: u32 = 2u;
const SLOT_LIGHTS: u32 = 4u;

fn child_key(key: u32, which: u32) -> u32 {
    return hash_u32((key * 2u + which) ^ 0x2c1b3c6du);
}

fn node_dim(key: u32, slot: u32) -> u32 {
    return hash_u32(key ^ 0x297a2d39u) + slot;
}

// sampling.rs stratified.
fn stratified(i: u32, n: u32, u1: f32, u2: f32) -> vec2<f32> {
    let m = u32(round(sqrt(f32(n))));
    if (m * m == n) {
        return vec2<f32>((f32(i % m) + u1) / f32(m), (f32(i / m) + u2) / f32(m));
    }
    return vec2<f32>((f32(i) + u1) / f32(n), u2);
}

fn moving_sphere(i: u32, tau: f32) -> Sphere {
    let base = DIST_LIGHTS + 5u * N_DLIGHTS + 2u * i;
    let a = dist[base];
    let b = dist[base + 1u];
    return Sphere(a.xyz + b.xyz * tau, a.w, bitcast<u32>(b.w));
}

fn d_closest(o: vec3<f32>, d: vec3<f32>, skip: u32, tau: f32) -> Hit {
    var h = closest_hit(o, d, skip);
    for (var i = 0u; i < N_MOVING; i++) {
        let pid = (KIND_MOVING << KIND_SHIFT) | i;
        let t = hit_sphere(moving_sphere(i, tau), o, d, h.t, pid == skip);
        if (t > 0.0) {
            h = Hit(t, pid);
        }
    }
    return moving_meshes_closest(o, d, skip, tau, h);
}

fn d_occluded(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32, tau: f32) -> bool {
    if (occluded(o, d, t_max, skip)) {
        return true;
    }
    for (var i = 0u; i < N_MOVING; i++) {
        let pid = (KIND_MOVING << KIND_SHIFT) | i;
        if (hit_sphere(moving_sphere(i, tau), o, d, t_max, pid == skip) > 0.0) {
            return true;
        }
    }
    return moving_meshes_occluded(o, d, t_max, skip, tau);
}

// A hit as distributed.rs `Surf` has it: the point snapped onto the
// primitive, the geometric normal n and the shading normal ns facing the
// viewer.
struct DSurface {
    p: vec3<f32>,
    n: vec3<f32>,
    ns: vec3<f32>,
    material: u32,
    entering: bool,
}

// distributed.rs surface: of the static world, a moving sphere at the
// sample's time, or a moving mesh (moving_meshes.wgsl).
fn d_surface(id: u32, q: vec3<f32>, v: vec3<f32>, tau: f32) -> DSurface {
    let mesh = moving_mesh_of(id);
    if (mesh != NONE) {
        return moving_mesh_surface(mesh, id, q, v, tau);
    }
    var sf: Surface;
    let moving = (id >> KIND_SHIFT) == KIND_MOVING;
    if (moving) {
        let ms = moving_sphere(id & ((1u << KIND_SHIFT) - 1u), tau);
        let dd = q - ms.center;
        let nn = dd * (1.0 / length(dd));
        sf = Surface(ms.center + nn * ms.radius, nn, ms.material);
    } else {
        sf = surface(id, q);
    }
    let entering = dot(sf.n, v) >= 0.0;
    let n = select(-sf.n, sf.n, entering);
    var ns = n;
    if (!moving) {
        ns = shading_normal(id, sf.p, n, v);
    }
    return DSurface(sf.p, n, ns, sf.material, entering);
}

// A point of light `li` for (u, v) in [0, 1)^2, uniform by area.
// Entries: (a, kind) (b, radius) (c, samples) (diffuse, first sample) (specular, -).
// kind 0: point at a; 1: quad a + u b + v c; 2: sphere centre a.
fn light_point(li: u32, uv: vec2<f32>) -> vec3<f32> {
    let base = DIST_LIGHTS + 5u * li;
    let e0 = dist[base];
    let e1 = dist[base + 1u];
    let kind = bitcast<u32>(e0.w);
    if (kind == 1u) {
        return e0.xyz + e1.xyz * uv.x + dist[base + 2u].xyz * uv.y;
    }
    if (kind == 2u) {
        let z = 1.0 - 2.0 * uv.x;
        let rho = sqrt(max(1.0 - z * z, 0.0));
        let phi = TWO_PI * uv.y;
        return e0.xyz + vec3<f32>(rho * cos(phi), rho * sin(phi), z) * e1.w;
    }
    return e0.xyz;
}

// Today's point-light term with the light at `pos` (shade_local's
// arithmetic), shadow ray included; zero when blocked or nothing to add.
fn d_light_term(pos: vec3<f32>, diffuse: vec3<f32>, specular: vec3<f32>, p: vec3<f32>, n: vec3<f32>, ns: vec3<f32>, v: vec3<f32>, m: Material, above: vec3<f32>, id: u32, tau: f32) -> vec3<f32> {
    let to_light = pos - p;
    let dl = length(to_light);
    if (!(dl > 0.0)) {
        return vec3<f32>(0.0);
    }
    let l = to_light * (1.0 / dl);
    let ndotl = max(dot(ns, l), 0.0);
    let h = l + v;
    let h_len = length(h);
    var ndoth = 0.0;
    if (h_len > 0.0) {
        ndoth = max(dot(ns, h) / h_len, 0.0);
    }
    var spec = 0.0;
    if (ndoth > m.specular_cos_min) {
        spec = pow(ndoth, m.shininess);
    }
    let contrib = diffuse * m.diffuse * ndotl + specular * m.specular * spec;
    if (!(max(contrib.x, max(contrib.y, contrib.z)) > 0.0)) {
        return vec3<f32>(0.0);
    }
    var o = above;
    if (dot(n, l) < 0.0) {
        o = offset_origin(p, -n);
    }
    tally[C_SHADOW] += 1u;
    if (d_occluded(o, l, dl * (1.0 - SHADOW_SHORTEN), id, tau)) {
        return vec3<f32>(0.0);
    }
    return contrib;
}

fn d_shade_local(p: vec3<f32>, n: vec3<f32>, ns: vec3<f32>, v: vec3<f32>, m: Material, above: vec3<f32>, id: u32, key: u32, seed: u32, s: u32, tau: f32) -> vec3<f32> {
    var local = frame.ambient * m.ambient;
    for (var li = 0u; li < N_DLIGHTS; li++) {
        let base = DIST_LIGHTS + 5u * li;
        let kind = bitcast<u32>(dist[base].w);
        let diffuse = dist[base + 3u].xyz;
        let specular = dist[base + 4u].xyz;
        if (kind == 0u) {
            local += d_light_term(dist[base].xyz, diffuse, specular, p, n, ns, v, m, above, id, tau);
            continue;
        }
        let count = bitcast<u32>(dist[base + 2u].w);
        let first = bitcast<u32>(dist[base + 3u].w);
        var sum = vec3<f32>(0.0);
        for (var i = 0u; i < count; i++) {
            let slot = SLOT_LIGHTS + 2u * (first + i);
            let u1 = uniform01(seed, s, node_dim(key, slot));
            let u2 = uniform01(seed, s, node_dim(key, slot + 1u));
            let y = light_point(li, stratified(i, count, u1, u2));
            sum += d_light_term(y, diffuse, specular, p, n, ns, v, m, above, id, tau);
        }
        local += sum * (1.0 / f32(count));
    }
    return local;
}

// A direction uniform by solid angle in the cone of cosine cos_max around axis.
fn cone(axis: vec3<f32>, cos_max: f32, u1: f32, u2: f32) -> vec3<f32> {
    let cos_t = 1.0 - u1 * (1.0 - cos_max);
    let sin_t = sqrt(max(1.0 - cos_t * cos_t, 0.0));
    let phi = TWO_PI * u2;
    let sign = select(1.0, -1.0, sign_bit(axis.z));
    let a = -1.0 / (sign + axis.z);
    let b = axis.x * axis.y * a;
    let t1 = vec3<f32>(1.0 + sign * axis.x * axis.x * a, sign * b, -sign * axis.x);
    let t2 = vec3<f32>(b, sign + axis.y * axis.y * a, -axis.y);
    return normalize(t1 * (sin_t * cos(phi)) + t2 * (sin_t * sin(phi)) + axis * cos_t);
}

struct DTask {
    origin: vec3<f32>,
    weight: f32,
    dir: vec3<f32>,
    depth: u32,
    skip: u32,
    key: u32,
}

// trace() with the node keys, moving objects, sampled lights and cones.
fn trace_dist(origin: vec3<f32>, dir: vec3<f32>, seed: u32, s: u32, tau: f32) -> vec3<f32> {
    var stack: array<DTask, STACK_CAP>;
    var top = 0u;
    var task = DTask(origin, 1.0, dir, 0u, NONE, ROOT_KEY);
    var colour = vec3<f32>(0.0);
    loop {
        var have_next = false;
        var next: DTask;
        let hit = d_closest(task.origin, task.dir, task.skip, tau);
        if (hit.id == NONE) {
            colour += frame.background * task.weight;
        } else {
            let v = -task.dir;
            let sf = d_surface(hit.id, task.origin + task.dir * hit.t, v, tau);
            let p = sf.p;
            let n = sf.n;
            let ns = sf.ns;
            let entering = sf.entering;
            let m = materials[sf.material];
            let cos_i = dot(ns, v);
            let above = offset_origin(p, n);
            colour += d_shade_local(p, n, ns, v, m, above, hit.id, task.key, seed, s, tau) * task.weight;

            if (task.depth < MAX_DEPTH) {
                var reflect_w = m.reflectivity;
                if (HAS_REFRACTION && m.transparency > 0.0) {
                    let eta = select(m.ior, 1.0 / m.ior, entering);
                    let k = 1.0 - eta * eta * (1.0 - cos_i * cos_i);
                    if (k < 0.0) {
                        reflect_w += m.transparency; // total internal reflection
                    } else {
                        var rdir = normalize(-v * eta + ns * (eta * cos_i - sqrt(k)));
                        var below = true;
                        if (m.translucency_cos < 1.0) {
                            rdir = cone(rdir, m.translucency_cos,
                                uniform01(seed, s, node_dim(task.key, SLOT_TRANSLUCENCY)),
                                uniform01(seed, s, node_dim(task.key, SLOT_TRANSLUCENCY + 1u)));
                            below = dot(rdir, n) < 0.0;
                        }
                        if (below) {
                            tally[C_REFRACTION] += 1u;
                            next = DTask(offset_origin(p, -n), task.weight * m.transparency, rdir, task.depth + 1u, hit.id, child_key(task.key, 0u));
                            have_next = true;
                        }
                    }
                }
                if (HAS_REFLECTION && reflect_w > 0.0) {
                    var rdir = normalize(ns * (2.0 * cos_i) - v);
                    var up = true;
                    if (m.gloss_cos < 1.0) {
                        rdir = cone(rdir, m.gloss_cos,
                            uniform01(seed, s, node_dim(task.key, SLOT_GLOSS)),
                            uniform01(seed, s, node_dim(task.key, SLOT_GLOSS + 1u)));
                        up = dot(rdir, n) > 0.0;
                    }
                    if (up) {
                        tally[C_REFLECTION] += 1u;
                        let child = DTask(above, task.weight * reflect_w, rdir, task.depth + 1u, hit.id, child_key(task.key, 1u));
                        if (have_next) {
                            if (top < STACK_CAP) {
                                stack[top] = next;
                                top += 1u;
                            }
                        }
                        next = child;
                        have_next = true;
                    }
                }
            }
        }
        if (have_next) {
            task = next;
        } else if (top > 0u) {
            top -= 1u;
            task = stack[top];
        } else {
            break;
        }
    }
    return colour;
}

@compute @workgroup_size(WG_X, WG_Y, 1)
fn render_dist(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let col = gid.x;
    let row = params.row0 + gid.y;
    let s = params.sample_start + gid.z;
    var p = vec4<u32>(0u);
    if (col < params.rect_w && gid.y < params.rows && row < params.rect_h && s < params.sample_end) {
        p = grid_pixel(col, row);
    }
    if (p.w != 0u) {
        let px = p.x;
        let py = p.y;
        let seed = pixel_seed(px, py, params.frame);
        let off = sample_offset(frame.sampler, frame.grid_n, seed, s);
        let sx = f32(px) + off.x;
        let sy = f32(py) + off.y;
        var tau = 0.0;
        if (HAS_BLUR) {
            tau = uniform01(seed, s, DIM_TIME);
        }
        // The camera at the sample's time (distributed.rs camera_at).
        var origin = vec3<f32>(0.0);
        var fwd = frame.forward;
        var right = frame.right;
        var up = frame.up;
        var unit_r = dist[0].xyz;
        var unit_u = dist[1].xyz;
        var look_d = dist[2].w;
        if (HAS_CAM_MOTION) {
            origin = dist[2].xyz * tau;
            let look = dist[3].xyz + dist[4].xyz * tau;
            let fv = look - origin;
            look_d = length(fv);
            let f = fv * (1.0 / look_d);
            let r = normalize(cross(f, dist[5].xyz));
            let u = cross(r, f);
            let t = tan(radians(dist[3].w + dist[4].w * tau) * 0.5);
            fwd = f;
            right = r * (t * dist[5].w);
            up = u * t;
            unit_r = r;
            unit_u = u;
        }
        let a = 2.0 * sx * frame.inv_width - 1.0;
        let b = 1.0 - 2.0 * sy * frame.inv_height;
        let d = normalize(fwd + right * a + up * b);
        var o = origin;
        var dir = d;
        if (HAS_LENS) {
            var focus = dist[1].w;
            if (focus <= 0.0) {
                focus = look_d;
            }
            let pf = origin + d * (focus / dot(d, fwd));
            let x1 = uniform01(seed, s, DIM_LENS);
            let x2 = uniform01(seed, s, DIM_LENS + 1u);
            let phi = TWO_PI * x2;
            let l = origin + (unit_r * cos(phi) + unit_u * sin(phi)) * (dist[0].w * sqrt(x1));
            let dd = pf - l;
            let len = length(dd);
            if (len > 0.0) {
                dir = dd * (1.0 / len);
            }
            o = l;
        }
        tally[C_PRIMARY] += 1u;
        add_sample(p.z, trace_dist(o, dir, seed, s, tau));
    }
    flush_tally(lid);
}
