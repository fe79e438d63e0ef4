//! import sampling.wgsl
//! import wide_int.wgsl
//! uses closest_hit occluded surface shading_normal: analytic.wgsl or accel.wgsl
// The thesis's Whitted model on the GPU: one invocation per pixel-sample;
// the sample's ray tree is walked with a bounded per-thread task stack
// (WGSL has no recursion), and its radiance, converted to 32.32 fixed point
// exactly as the CPU does, is added atomically to its pixel's sums (integer
// addition: the result does not depend on the order). A pixel's colour
// is the sum over the tree of weight * local colour, the same quantity the
// CPU's recursion in `render/whitted.rs` computes; the shading below
// follows that file step by step (same self-skip, origin offsets, shadow
// shortening, skipped shadow rays, TIR rule).
//
// Prepended by the host: `const STACK_CAP: u32 = N;` (see SceneData::stack_capacity),
// `const BVH_STACK: u32 = N;` (the trees' stack need, at most bvh::STACK).

// ---- Layouts: keep in sync with layout.rs -------------------------------
struct Frame {
    forward: vec3<f32>,
    inv_width: f32,
    right: vec3<f32>,
    inv_height: f32,
    up: vec3<f32>,
    samples: u32,
    ambient: vec3<f32>,
    grid_n: u32,
    background: vec3<f32>,
    sampler: u32,
}

struct Dispatch {
    rect_x: u32,
    rect_y: u32,
    rect_w: u32,
    rect_h: u32,
    row0: u32,
    rows: u32,
    sample_start: u32,
    sample_end: u32,
    frame: u32,
    // The film's size; in an adaptive round the dispatch grid is 8 wide and
    // 8 rows per active block, not the film (see grid_pixel).
    film_w: u32,
    film_h: u32,
}

struct Sphere {
    center: vec3<f32>,
    radius: f32,
    material: u32,
}

struct Plane {
    normal: vec3<f32>,
    distance: f32,
    material: u32,
}

struct Material {
    ambient: vec3<f32>,
    shininess: f32,
    diffuse: vec3<f32>,
    reflectivity: f32,
    specular: vec3<f32>,
    transparency: f32,
    ior: f32,
    specular_cos_min: f32,
    gloss_cos: f32,
    translucency_cos: f32,
}

struct Light {
    position: vec3<f32>,
    diffuse: vec3<f32>,
    specular: vec3<f32>,
}

// Counter indices (layout.rs COUNTER_*); each is a (low, high) pair.
const C_PRIMARY: u32 = 0u;
const C_SHADOW: u32 = 1u;
const C_REFLECTION: u32 = 2u;
const C_REFRACTION: u32 = 3u;
const C_NONFINITE: u32 = 4u;
const N_COUNTERS: u32 = 5u;

// ---- Scene specialisation (pipeline-overridable constants) --------------
override N_SPHERES: u32 = 0u;
override N_PLANES: u32 = 0u;
override N_LIGHTS: u32 = 0u;
override MAX_DEPTH: u32 = 0u;
override HAS_REFLECTION: bool = true;
override HAS_REFRACTION: bool = true;
override WG_X: u32 = 8u;
override WG_Y: u32 = 8u;
// An adaptive round (adaptive/mod.rs): the grid covers the active blocks
// only, and each pixel also sums the squares of its samples.
override ADAPTIVE: bool = false;

// Group 0's bindings (frame, params, spheres, ..., active_blocks): wgsl.rs SCENE.

var<workgroup> wg_counts: array<atomic<u32>, 5>;
var<private> tally: array<u32, 5>;

// ---- Numerics: the f32 constants of math.rs -----------------------------
const OFFSET_REL: f32 = 3.8146973e-6;
const OFFSET_MIN: f32 = 1.0e-30;
const SHADOW_SHORTEN: f32 = 1.0e-4;
const BIG: f32 = 3.4028235e38; // stands in for +inf (WGSL has no literal)
const MISS: f32 = -1.0;
const NONE: u32 = 0xffffffffu;
const KIND_SHIFT: u32 = 28u;
const KIND_SPHERE: u32 = 0u;
const KIND_PLANE: u32 = 1u;
const KIND_TRIANGLE: u32 = 2u;

fn offset_origin(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let a = abs(p);
    let scale = max(a.x, max(a.y, a.z)) * OFFSET_REL + OFFSET_MIN;
    return p + n * scale;
}

fn sign_bit(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x80000000u) != 0u;
}

// geometry.rs Sphere::intersect: nearest t in (0, t_max) or MISS.
fn hit_sphere(s: Sphere, o: vec3<f32>, d: vec3<f32>, t_max: f32, from_surface: bool) -> f32 {
    let f = o - s.center;
    let b = dot(f, d);
    if (from_surface) {
        let t = -2.0 * b;
        return select(MISS, t, t > 0.0 && t < t_max);
    }
    let l = f - d * b;
    let ll = length(l);
    let r = s.radius;
    let disc = (r - ll) * (r + ll);
    if (!(disc >= 0.0)) {
        return MISS;
    }
    let c = dot(f, f) - r * r;
    let sq = sqrt(disc);
    let q = -b - select(sq, -sq, sign_bit(b));
    // q = 0 only for a ray tangent at its own origin: both roots are 0.
    if (q == 0.0) {
        return MISS;
    }
    let a = c / q;
    let t0 = select(q, a, a < q);
    let t1 = select(a, q, a < q);
    if (t0 > 0.0 && t0 < t_max) {
        return t0;
    }
    return select(MISS, t1, t1 > 0.0 && t1 < t_max);
}

// geometry.rs Plane::intersect.
fn hit_plane(p: Plane, o: vec3<f32>, d: vec3<f32>, t_max: f32, from_surface: bool) -> f32 {
    if (from_surface) {
        return MISS;
    }
    let denom = dot(p.normal, d);
    // Parallel: the CPU gets +-inf or NaN, which fail its test; WGSL
    // leaves x/0 undefined, so test it.
    if (denom == 0.0) {
        return MISS;
    }
    let t = (p.distance - dot(p.normal, o)) / denom;
    return select(MISS, t, t > 0.0 && t < t_max);
}

struct Hit {
    t: f32,
    id: u32,
}

// The scene queries `closest_hit`, `occluded`, `surface` and
// `shading_normal` come from analytic.wgsl (no tree: the loops below over
// every sphere and plane) or accel.wgsl (a tree over spheres and triangles
// traversed by bvh.wgsl, planes by loop), whichever the host compiles in.

// world/query.rs closest_hit, sphere part: strictly nearer than h.t wins.
fn spheres_closest(o: vec3<f32>, d: vec3<f32>, skip: u32, h: Hit) -> Hit {
    var best = h;
    for (var i = 0u; i < N_SPHERES; i++) {
        let pid = (KIND_SPHERE << KIND_SHIFT) | i;
        let t = hit_sphere(spheres[i], o, d, best.t, pid == skip);
        if (t > 0.0) {
            best = Hit(t, pid);
        }
    }
    return best;
}

fn planes_closest(o: vec3<f32>, d: vec3<f32>, skip: u32, h: Hit) -> Hit {
    var best = h;
    for (var i = 0u; i < N_PLANES; i++) {
        let pid = (KIND_PLANE << KIND_SHIFT) | i;
        let t = hit_plane(planes[i], o, d, best.t, pid == skip);
        if (t > 0.0) {
            best = Hit(t, pid);
        }
    }
    return best;
}

fn spheres_occlude(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32) -> bool {
    for (var i = 0u; i < N_SPHERES; i++) {
        let pid = (KIND_SPHERE << KIND_SHIFT) | i;
        if (hit_sphere(spheres[i], o, d, t_max, pid == skip) > 0.0) {
            return true;
        }
    }
    return false;
}

fn planes_occlude(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32) -> bool {
    for (var i = 0u; i < N_PLANES; i++) {
        let pid = (KIND_PLANE << KIND_SHIFT) | i;
        if (hit_plane(planes[i], o, d, t_max, pid == skip) > 0.0) {
            return true;
        }
    }
    return false;
}

struct Surface {
    p: vec3<f32>,
    n: vec3<f32>,
    material: u32,
}

// world/query.rs surface for spheres and planes: the point snapped onto the
// primitive, outward normal.
fn analytic_surface(id: u32, p: vec3<f32>) -> Surface {
    let index = id & ((1u << KIND_SHIFT) - 1u);
    if ((id >> KIND_SHIFT) == KIND_SPHERE) {
        let s = spheres[index];
        let d = p - s.center;
        let n = d * (1.0 / length(d));
        return Surface(s.center + n * s.radius, n, s.material);
    }
    let pl = planes[index];
    let off = dot(pl.normal, p) - pl.distance;
    return Surface(p - pl.normal * off, pl.normal, pl.material);
}

// Ambient plus every unblocked light at surface point p (render/whitted.rs):
// n (the geometric normal) faces the viewer v, ns is the shading normal
// (n except on smooth triangles), `above` is p offset to the viewer's side,
// `id` the primitive p lies on.
fn shade_local(p: vec3<f32>, n: vec3<f32>, ns: vec3<f32>, v: vec3<f32>, m: Material, above: vec3<f32>, id: u32) -> vec3<f32> {
    var local = frame.ambient * m.ambient;
    for (var li = 0u; li < N_LIGHTS; li++) {
        let light = lights[li];
        let to_light = light.position - p;
        let dist = length(to_light);
        if (!(dist > 0.0)) {
            continue;
        }
        let l = to_light * (1.0 / dist);
        let ndotl = max(dot(ns, l), 0.0);
        let h = l + v;
        let h_len = length(h);
        var ndoth = 0.0;
        if (h_len > 0.0) {
            ndoth = max(dot(ns, h) / h_len, 0.0);
        }
        var spec = 0.0;
        // Same cut-off as the CPU's f32 path: terms below 2^-24 are skipped.
        if (ndoth > m.specular_cos_min) {
            spec = pow(ndoth, m.shininess);
        }
        let contrib = light.diffuse * m.diffuse * ndotl + light.specular * m.specular * spec;
        // A light that can add nothing needs no shadow ray.
        if (max(contrib.x, max(contrib.y, contrib.z)) <= 0.0) {
            continue;
        }
        // Leave on the light's side of the surface.
        var o = above;
        if (dot(n, l) < 0.0) {
            o = offset_origin(p, -n);
        }
        tally[C_SHADOW] += 1u;
        if (!occluded(o, l, dist * (1.0 - SHADOW_SHORTEN), id)) {
            local += contrib;
        }
    }
    return local;
}

// A ray still to trace: its contribution is weight * (colour it sees).
struct Task {
    origin: vec3<f32>,
    weight: f32,
    dir: vec3<f32>,
    depth: u32,
    skip: u32,
}

// Colour of one primary ray: render/whitted.rs `trace`, unrolled.
fn trace(origin: vec3<f32>, dir: vec3<f32>) -> vec3<f32> {
    var stack: array<Task, STACK_CAP>;
    var top = 0u;
    var task = Task(origin, 1.0, dir, 0u, NONE);
    var colour = vec3<f32>(0.0);
    loop {
        var have_next = false;
        var next: Task;
        let hit = closest_hit(task.origin, task.dir, task.skip);
        if (hit.id == NONE) {
            colour += frame.background * task.weight;
        } else {
            let sf = surface(hit.id, task.origin + task.dir * hit.t);
            let p = sf.p;
            let m = materials[sf.material];
            let v = -task.dir;
            let cos_out = dot(sf.n, v);
            let entering = cos_out >= 0.0;
            let n = select(-sf.n, sf.n, entering);
            // Differs from n only on smoothly shaded triangles.
            let ns = shading_normal(hit.id, p, n, v);
            let cos_i = dot(ns, v);

            let above = offset_origin(p, n);
            colour += shade_local(p, n, ns, v, m, above, hit.id) * task.weight;

            if (task.depth < MAX_DEPTH) {
                var reflect_w = m.reflectivity;
                if (HAS_REFRACTION && m.transparency > 0.0) {
                    let eta = select(m.ior, 1.0 / m.ior, entering);
                    let k = 1.0 - eta * eta * (1.0 - cos_i * cos_i);
                    if (k < 0.0) {
                        reflect_w += m.transparency; // total internal reflection
                    } else {
                        let rdir = normalize(-v * eta + ns * (eta * cos_i - sqrt(k)));
                        tally[C_REFRACTION] += 1u;
                        next = Task(offset_origin(p, -n), task.weight * m.transparency, rdir, task.depth + 1u, hit.id);
                        have_next = true;
                    }
                }
                if (HAS_REFLECTION && reflect_w > 0.0) {
                    let rdir = normalize(ns * (2.0 * cos_i) - v);
                    tally[C_REFLECTION] += 1u;
                    let child = Task(above, task.weight * reflect_w, rdir, task.depth + 1u, hit.id);
                    if (have_next) {
                        // Both children: keep one pending (at most one per generation).
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

// One sample's radiance in 32.32 fixed point as (low, high): film/mod.rs to_fixed.
fn to_fixed(v: f32) -> vec2<u32> {
    let bits = bitcast<u32>(v);
    if ((bits & 0x7f800000u) == 0x7f800000u) {
        if ((bits & 0x007fffffu) != 0u) {
            tally[C_NONFINITE] += 1u; // NaN -> 0
            return vec2<u32>(0u, 0u);
        }
        if ((bits >> 31u) != 0u) {
            return vec2<u32>(0u, 0u); // -inf -> clamped to 0, as on the CPU
        }
        tally[C_NONFINITE] += 1u; // +inf -> the largest value
        return vec2<u32>(0u, 65504u);
    }
    if (v > 65504.0) {
        return vec2<u32>(0u, 65504u);
    }
    let x = max(v, 0.0);
    let hi = floor(x);
    // x - hi is exact in f32, and scaling by 2^32 is exact.
    let lo = round((x - hi) * 4294967296.0);
    if (lo >= 4294967296.0) {
        return vec2<u32>(0u, u32(hi) + 1u);
    }
    return vec2<u32>(u32(lo), u32(hi));
}

// Adds v in fixed point to the (low, high) pair at sums[word], carrying.
fn add_fixed(word: u32, v: f32) {
    add_fixed_pair(word, to_fixed(v));
}

fn add_fixed_pair(word: u32, f: vec2<u32>) {
    if (f.x != 0u) {
        let old = atomicAdd(&sums[word], f.x);
        if (old + f.x < old) {
            atomicAdd(&sums[word + 1u], 1u);
        }
    }
    if (f.y != 0u) {
        atomicAdd(&sums[word + 1u], f.y);
    }
}

// Words a pixel's sums take: 6 (three 64-bit sums), or 18 in an adaptive
// round (then three 128-bit sums of squares). layout.rs SUM_WORDS, ADAPTIVE_SUM_WORDS.
fn sum_stride() -> u32 {
    return select(6u, 18u, ADAPTIVE);
}

// Adds v at word k of the 128-bit sum at sums[base..base + 4], carrying upward.
fn add_carrying(base: u32, k: u32, v: u32) {
    var i = k;
    var x = v;
    loop {
        if (x == 0u || i >= 4u) {
            break;
        }
        let old = atomicAdd(&sums[base + i], x);
        if (old + x >= old) {
            break;
        }
        x = 1u;
        i += 1u;
    }
}

// Adds the square of a fixed-point sample f = hi * 2^32 + lo to the 128-bit
// sum at sums[base]: exactly the CPU's `s as u128 * s as u128`. hi is at
// most 65504 (to_fixed's clamp), so the square fits 96 bits:
// lo^2 + 2 hi lo 2^32 + hi^2 2^64, with 2 hi lo below 2^49.
fn add_square(base: u32, f: vec2<u32>) {
    let l = mul_wide(f.x, f.x);
    let m = mul_wide(f.y, f.x);
    let d0 = m.x << 1u;
    let d1 = (m.y << 1u) | (m.x >> 31u);
    let w1 = l.y + d0;
    let carry = select(0u, 1u, w1 < l.y);
    // hi^2 + d1 + carry < 65504^2 + 2^17 + 1 < 2^32: no carry out.
    let w2 = f.y * f.y + d1 + carry;
    add_carrying(base, 0u, l.x);
    add_carrying(base, 1u, w1);
    add_carrying(base, 2u, w2);
}

// Adds one sample's colour to the pixel whose sums start at sums[word]
// (and its squares, in an adaptive round).
fn add_sample(word: u32, c: vec3<f32>) {
    for (var ch = 0u; ch < 3u; ch++) {
        let f = to_fixed(c[ch]);
        add_fixed_pair(word + 2u * ch, f);
        if (ADAPTIVE) {
            add_square(word + 6u + 4u * ch, f);
        }
    }
}

// The pixel that column `col`, row `row` of the dispatch grid traces:
// (x, y, its first sums word, 1), or w = 0 for none (an adaptive round's
// block cut by the film's edge). Uniform renders: the grid is the film.
// Adaptive rounds: 8 columns, and rows 8b..8b+8 are active block b's.
fn grid_pixel(col: u32, row: u32) -> vec4<u32> {
    if (!ADAPTIVE) {
        return vec4<u32>(params.rect_x + col, params.rect_y + row, (row * params.rect_w + col) * 6u, 1u);
    }
    let b = active_blocks[row / 8u];
    let fx = (b & 0xffffu) * 8u + col;
    let fy = (b >> 16u) * 8u + row % 8u;
    if (fx >= params.film_w || fy >= params.film_h) {
        return vec4<u32>(0u);
    }
    return vec4<u32>(params.rect_x + fx, params.rect_y + fy, (fy * params.film_w + fx) * sum_stride(), 1u);
}

// Ray counts: per workgroup first, then one (carrying) global add per
// counter. Call from uniform control flow (it has a barrier).
fn flush_tally(lid: u32) {
    for (var k = 0u; k < N_COUNTERS; k++) {
        if (tally[k] != 0u) {
            atomicAdd(&wg_counts[k], tally[k]);
        }
    }
    workgroupBarrier();
    if (lid < N_COUNTERS) {
        let v = atomicLoad(&wg_counts[lid]);
        if (v != 0u) {
            let old = atomicAdd(&counters[2u * lid], v);
            if (old + v < old) {
                atomicAdd(&counters[2u * lid + 1u], 1u);
            }
        }
    }
}

@compute @workgroup_size(WG_X, WG_Y, 1)
fn render(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
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
        let off = sample_offset(frame.sampler, frame.grid_n, pixel_seed(px, py, params.frame), s);
        let sx = f32(px) + off.x;
        let sy = f32(py) + off.y;
        // world/mod.rs Camera::ray
        let a = 2.0 * sx * frame.inv_width - 1.0;
        let b = 1.0 - 2.0 * sy * frame.inv_height;
        let d = normalize(frame.forward + frame.right * a + frame.up * b);
        tally[C_PRIMARY] += 1u;
        add_sample(p.z, trace(vec3<f32>(0.0), d));
    }
    flush_tally(lid);
}
