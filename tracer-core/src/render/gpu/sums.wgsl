//! import scene.wgsl
//! import wide_int.wgsl
// A pixel's sums: each sample's radiance converted to 32.32 fixed point
// exactly as the CPU does (film/mod.rs) and added atomically (integer
// addition: the result does not depend on the order), with its squares in
// an adaptive round. Shared by the stack and wavefront drivers.

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

// The square of a fixed-point sample f = hi * 2^32 + lo as its three low
// words (exactly the CPU's `s as u128 * s as u128`). hi is at most 65504
// (to_fixed's clamp), so the square fits 96 bits:
// lo^2 + 2 hi lo 2^32 + hi^2 2^64, with 2 hi lo below 2^49.
fn square_words(f: vec2<u32>) -> vec3<u32> {
    let l = mul_wide(f.x, f.x);
    let m = mul_wide(f.y, f.x);
    let d0 = m.x << 1u;
    let d1 = (m.y << 1u) | (m.x >> 31u);
    let w1 = l.y + d0;
    let carry = select(0u, 1u, w1 < l.y);
    // hi^2 + d1 + carry < 65504^2 + 2^17 + 1 < 2^32: no carry out.
    let w2 = f.y * f.y + d1 + carry;
    return vec3<u32>(l.x, w1, w2);
}

// Adds one sample's colour to the pixel whose sums start at sums[word]
// (and its squares, in an adaptive round).
fn add_sample(word: u32, c: vec3<f32>) {
    add_sums(word, accumulate(PixelSums(), c));
}

// A pixel's sums over some of its samples, kept in registers before they
// go to the film in one go (a listed dispatch's invocation: several
// samples of one pixel). Integer sums: the film's are the same bits as
// with one atomic addition a sample.
struct PixelSums {
    // Per channel the 64-bit sum (low, high) and the 128-bit sum of squares.
    sum: array<vec2<u32>, 3>,
    squares: array<vec4<u32>, 3>,
}

fn add_64(a: vec2<u32>, b: vec2<u32>) -> vec2<u32> {
    let lo = a.x + b.x;
    return vec2<u32>(lo, a.y + b.y + select(0u, 1u, lo < a.x));
}

// a (four words) plus b (three low words), modulo 2^128.
fn add_128(a: vec4<u32>, b: vec3<u32>) -> vec4<u32> {
    var out = a;
    var carry = 0u;
    for (var i = 0u; i < 3u; i++) {
        let s = a[i] + b[i];
        let t = s + carry;
        carry = select(0u, 1u, s < a[i]) + select(0u, 1u, t < s);
        out[i] = t;
    }
    out[3] = a[3] + carry;
    return out;
}

// `acc` with one more sample of colour `c`.
fn accumulate(acc: PixelSums, c: vec3<f32>) -> PixelSums {
    var out = acc;
    for (var ch = 0u; ch < 3u; ch++) {
        let f = to_fixed(c[ch]);
        out.sum[ch] = add_64(out.sum[ch], f);
        if (ADAPTIVE) {
            out.squares[ch] = add_128(out.squares[ch], square_words(f));
        }
    }
    return out;
}

// Adds `acc` to the pixel whose sums start at sums[word].
fn add_sums(word: u32, acc: PixelSums) {
    for (var ch = 0u; ch < 3u; ch++) {
        add_fixed_pair(word + 2u * ch, acc.sum[ch]);
        if (ADAPTIVE) {
            for (var k = 0u; k < 4u; k++) {
                add_carrying(word + 6u + 4u * ch, k, acc.squares[ch][k]);
            }
        }
    }
}

// What one invocation of a listed dispatch traces: its pixel (as
// grid_pixel's), its samples first..end, and its listed block.
struct ListedWork {
    pixel: vec4<u32>,
    first: u32,
    end: u32,
    block: u32,
}

// Invocation `t` of a listed dispatch (params.ranged: an adaptive render
// whose blocks each take their own range). The items are (listed block,
// chunk of `params.chunk` samples of its range), block by block:
// block_ranges[b] = (first, end, its first item), and entry `blocks` (past
// the last listed block) holds the items in all. 64 invocations an item,
// one a pixel of the block; the dispatch traces items
// sample_start..sample_end.
fn listed_work(t: u32) -> ListedWork {
    let item = params.sample_start + t / 64u;
    let blocks = params.rect_h / 8u;
    if (item >= params.sample_end || item >= block_ranges[blocks].z) {
        return ListedWork(vec4<u32>(0u), 0u, 0u, 0u);
    }
    // The last block whose first item is at most `item` (blocks with no
    // items share their first item with the next).
    var lo = 0u;
    var hi = blocks;
    while (hi - lo > 1u) {
        let mid = (lo + hi) / 2u;
        if (block_ranges[mid].z <= item) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let r = block_ranges[lo];
    let first = r.x + (item - r.z) * params.chunk;
    let pixel = t % 64u;
    return ListedWork(grid_pixel(pixel % 8u, 8u * lo + pixel / 8u), first, min(first + params.chunk, r.y), lo);
}

// The pixel that column `col`, row `row` of the dispatch grid traces:
// (x, y, its first sums word, 1), or w = 0 for none (an adaptive round's
// block cut by the film's edge). Uniform renders: the grid is the film.
// Adaptive rounds: 8 columns, and rows 8b..8b+8 are active block b's
// (none where the block is retired: bit 31, converge.wgsl).
fn grid_pixel(col: u32, row: u32) -> vec4<u32> {
    if (!ADAPTIVE) {
        return vec4<u32>(params.rect_x + col, params.rect_y + row, (row * params.rect_w + col) * 6u, 1u);
    }
    let b = active_blocks[row / 8u];
    // A block the GPU's convergence test retired (converge.wgsl).
    if ((b & 0x80000000u) != 0u) {
        return vec4<u32>(0u);
    }
    let fx = (b & 0xffffu) * 8u + col;
    let fy = ((b >> 16u) & 0x7fffu) * 8u + row % 8u;
    if (fx >= params.film_w || fy >= params.film_h) {
        return vec4<u32>(0u);
    }
    return vec4<u32>(params.rect_x + fx, params.rect_y + fy, (fy * params.film_w + fx) * sum_stride(), 1u);
}
