// Where in a pixel each sample goes: an exact port of `src/sampling.rs`.
// Integer hashing only (u32 arithmetic wraps in WGSL as in Rust's
// wrapping_mul), so positions match the CPU's. Keep in sync with sampling.rs.

// Chris Wellons' lowbias32.
fn hash_u32(x0: u32) -> u32 {
    var x = x0;
    x ^= x >> 16u;
    x *= 0x7feb352du;
    x ^= x >> 15u;
    x *= 0x846ca68bu;
    x ^= x >> 16u;
    return x;
}

fn pixel_seed(x: u32, y: u32, frame: u32) -> u32 {
    return hash_u32(x ^ hash_u32(y ^ hash_u32(frame + 0x9e3779b9u)));
}

// Uniform in [0, 1) with 24 bits: exact in f32.
fn uniform01(seed: u32, sample: u32, dim: u32) -> f32 {
    let h = hash_u32(seed ^ hash_u32((sample * 0x68e31da4u) ^ hash_u32(dim)));
    return f32(h >> 8u) * (1.0 / 16777216.0);
}

// sampling.rs `permute`: element i of the permutation of [0, n) seed picks
// (Kensler 2013).
fn permute(i0: u32, n: u32, seed: u32) -> u32 {
    var w = n - 1u;
    w |= w >> 1u;
    w |= w >> 2u;
    w |= w >> 4u;
    w |= w >> 8u;
    w |= w >> 16u;
    var i = i0;
    loop {
        i ^= seed;
        i *= 0xe170893du;
        i ^= seed >> 16u;
        i ^= (i & w) >> 4u;
        i ^= seed >> 8u;
        i *= 0x0929eb3fu;
        i ^= seed >> 23u;
        i ^= (i & w) >> 1u;
        i *= 1u | (seed >> 27u);
        i *= 0x6935fa69u;
        i ^= (i & w) >> 11u;
        i *= 0x74dcb303u;
        i ^= (i & w) >> 2u;
        i *= 0x9e501cc3u;
        i ^= (i & w) >> 2u;
        i *= 0xc860a3dfu;
        i &= w;
        i ^= i >> 5u;
        if (i < n) {
            break;
        }
    }
    return (i + seed) % n;
}

// sampling.rs `uniform_pair`: dimensions dim and dim + 1 of a sample,
// stratified over side x side cells (side > 0: the sample count is side^2).
fn uniform_pair(seed: u32, sample: u32, side: u32, dim: u32) -> vec2<f32> {
    let uv = vec2<f32>(uniform01(seed, sample, dim), uniform01(seed, sample, dim + 1u));
    if (side == 0u) {
        return uv;
    }
    let cell = permute(sample, side * side, hash_u32(seed ^ hash_u32(dim ^ 0x0b5c9d2fu)));
    let n = f32(side);
    let c = vec2<f32>(f32(cell % side), f32(cell / side));
    return min((c + uv) / n, vec2<f32>(0.99999994));
}

const R2_A1: u32 = 3242174889u;
const R2_A2: u32 = 2447445413u;

// sampler: 0 grid, 1 jittered, 2 progressive; grid_n: sqrt of the sample
// count, 0 if not square or progressive (the host decides).
fn sample_offset(sampler: u32, grid_n: u32, seed: u32, sample: u32) -> vec2<f32> {
    if (grid_n != 0u) {
        let i = sample % grid_n;
        let j = sample / grid_n;
        var jit = vec2<f32>(0.5, 0.5);
        if (sampler == 1u) {
            jit = vec2<f32>(uniform01(seed, sample, 0u), uniform01(seed, sample, 1u));
        }
        let n = f32(grid_n);
        return vec2<f32>((f32(i) + jit.x) / n, (f32(j) + jit.y) / n);
    }
    let rx = hash_u32(seed ^ 0x5bd1e995u);
    let ry = hash_u32(seed ^ 0x1b873593u);
    let u = sample * R2_A1 + rx;
    let v = sample * R2_A2 + ry;
    return vec2<f32>(f32(u >> 8u), f32(v >> 8u)) * (1.0 / 16777216.0);
}
