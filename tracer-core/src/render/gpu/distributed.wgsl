//! import geometry.wgsl
//! import sampling.wgsl
//! uses closest_hit occluded surface shading_normal: analytic.wgsl or accel.wgsl
//! uses moving_meshes_closest moving_meshes_occluded moving_mesh_of moving_mesh_surface: moving_meshes.wgsl or no_moving_meshes.wgsl
// Distributed ray tracing on the GPU (issue 16): area lights, gloss and
// translucency cones, the thin lens, motion over the shutter, with the same
// random numbers as `render/cpu/distributed.rs` (sampling.rs: dimensions
// 2, 3 for the lens, 4 for the time, node keys and slots for the rest).
// The effects the shading step (shade.wgsl) and the camera take from here,
// each chosen by a pipeline override: a scene without them (a Whitted
// scene) gets the defaults, under which every function below is the
// static world's query or the pinhole camera and the compiler drops the
// rest. Keep in sync with layout.rs `DistData` (the packing of `dist`).

// dist[0]: unit right, aperture; [1]: unit up, focus distance (<= 0: the
// pose's look distance); [2]: camera displacement over the shutter, look
// distance; [3]: look_at (opening), fov_y (degrees); [4]: look_at change,
// fov_y change; [5]: up (unit), aspect. Then 5 entries per light (see
// `light_point`), 2 per moving sphere and 3 per moving mesh (see
// moving_meshes.wgsl). (Binding: wgsl.rs SCENE; a placeholder without
// distributed effects.)

// The scene has distributed effects (`World::dist`): its lights are
// `dist`'s (area lights sampled), materials may have cones, rays carry
// node keys.
override DISTRIBUTED: bool = false;
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

// ---- The world at shutter fraction tau: static world, moving spheres,
// moving meshes (distributed.rs `closest`, `occluded`, `surface`).

fn closest_at(o: vec3<f32>, d: vec3<f32>, skip: u32, tau: f32) -> Hit {
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

fn occluded_at(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32, tau: f32) -> bool {
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

// A hit's surface facing the viewer: the point snapped onto the primitive,
// the geometric normal n and the shading normal ns on the viewer's side.
struct Facing {
    p: vec3<f32>,
    n: vec3<f32>,
    ns: vec3<f32>,
    material: u32,
    entering: bool,
}

// The surface at q of primitive `id` seen from v: of the static world, a
// moving sphere at the sample's time, or a moving mesh (moving_meshes.wgsl).
fn facing_at(id: u32, q: vec3<f32>, v: vec3<f32>, tau: f32) -> Facing {
    let mesh = moving_mesh_of(id);
    if (mesh != NONE) {
        return moving_mesh_surface(mesh, id, q, v, tau);
    }
    var sf: SurfacePoint;
    let moving = N_MOVING > 0u && (id >> KIND_SHIFT) == KIND_MOVING;
    if (moving) {
        sf = sphere_surface(moving_sphere(id & ((1u << KIND_SHIFT) - 1u), tau), q);
    } else {
        sf = surface(id, q);
    }
    // Entering: arriving against the outward normal.
    let entering = dot(sf.n, v) >= 0.0;
    let n = select(-sf.n, sf.n, entering);
    // Differs from n only on smoothly shaded triangles.
    var ns = n;
    if (!moving) {
        ns = shading_normal(id, sf.p, n, v);
    }
    return Facing(sf.p, n, ns, sf.material, entering);
}

// ---- Lights -------------------------------------------------------------

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

// ---- The camera ---------------------------------------------------------

// A camera ray and the shutter fraction it samples.
struct CameraRay {
    origin: vec3<f32>,
    dir: vec3<f32>,
    tau: f32,
}

// The ray of sample s of pixel (px, py) (world/mod.rs Camera::ray; with
// distributed effects, distributed.rs camera_at and the thin lens).
fn camera_ray(px: u32, py: u32, seed: u32, s: u32) -> CameraRay {
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
    return CameraRay(o, dir, tau);
}
