// The scene kernel's shared declarations: the layouts of the scene's
// buffers (keep in sync with layout.rs), its specialisation, the ray
// counters and the f32 constants of math.rs. Every other file of the
// scene kernel imports this one.
//
// Prepended by the host: `const STACK_CAP: u32 = N;` (see
// SceneData::stack_capacity) and `const BVH_STACK: u32 = N;` (the trees'
// stack need, at most bvh::STACK). Group 0's bindings are generated from
// wgsl.rs SCENE (the one declaration of that layout).

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
    // 1: a listed dispatch, an adaptive render's blocks each over their
    // own range of samples (block_ranges, sums.wgsl listed_work); the
    // dispatch's "samples" are then items, each a block's chunk of `chunk`
    // samples.
    ranged: u32,
    chunk: u32,
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
const KIND_INSTANCE: u32 = 3u;
const KIND_INSTANCE_TRIANGLE: u32 = 4u;

fn offset_origin(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let a = abs(p);
    let scale = max(a.x, max(a.y, a.z)) * OFFSET_REL + OFFSET_MIN;
    return p + n * scale;
}

fn sign_bit(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x80000000u) != 0u;
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

