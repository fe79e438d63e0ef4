//! import wide_int.wgsl
// An adaptive render's convergence test on the GPU (issue 36): after each
// round, one workgroup per 8x8 block tests the block's pixels against the
// target, as the host's `adaptive::block_converged` does, and retires a
// converged block from the rounds to come by setting bit 31 of its entry in
// `active_blocks` (the trace kernel skips such blocks: sums.wgsl
// grid_pixel). Rounds therefore chain without the host; what the host
// reads per round is `block_stats`, 16 bytes a block, for progress.
//
// Each channel's variance of the mean is the host's `variance_of_mean`:
// the numerator n * sum(x^2) - sum(x)^2 exactly, in 128-bit integers on
// u32 words, then scaled in f32 (the host scales in f64).

struct ConvergeParams {
    film_w: u32,
    film_h: u32,
    // Blocks per row of the film, and in all.
    cols: u32,
    blocks: u32,
    // Samples every pixel of a block active in this round has now.
    samples: u32,
    // 1: the error-optimal mode's statistics (layout.rs ConvergeParams):
    // each block at the end of its own range, none retired, with the sum
    // of its pixels' channel means.
    ranged: u32,
    // The target (scene::adaptive Target): a pixel's limit is
    // max(absolute, relative * its brightest channel mean).
    absolute: f32,
    relative: f32,
}

// Bindings: wgsl.rs CONVERGE. `sums`: 18 words a pixel (the adaptive
// layout: three 64-bit sums, then three 128-bit sums of squares).

const RETIRED: u32 = 0x80000000u;
// Stands for an infinite error ratio (fewer than 2 samples, or a zero limit).
const HUGE: f32 = 3.4e38;

var<workgroup> wg_worst: atomic<u32>;
var<workgroup> wg_variance: array<f32, 64>;
var<workgroup> wg_mean: array<f32, 64>;

// a * b for a 128-bit a (four words, least significant first) and a u32 b;
// all ones where the product does not fit (the host saturates too).
fn mul_128_32(a: array<u32, 4>, b: u32) -> array<u32, 4> {
    var out: array<u32, 4>;
    var carry = 0u;
    for (var i = 0u; i < 4u; i++) {
        let p = mul_wide(a[i], b);
        let lo = p.x + carry;
        out[i] = lo;
        carry = p.y + select(0u, 1u, lo < p.x);
    }
    if carry != 0u {
        return array<u32, 4>(0xffffffffu, 0xffffffffu, 0xffffffffu, 0xffffffffu);
    }
    return out;
}

// The square of a 64-bit s = (lo, hi) as four words.
fn square_64(s: vec2<u32>) -> array<u32, 4> {
    let ll = mul_wide(s.x, s.x);
    let lh = mul_wide(s.x, s.y);
    let hh = mul_wide(s.y, s.y);
    // s^2 = ll + 2 lh 2^32 + hh 2^64; 2 lh is up to 65 bits.
    let d0 = lh.x << 1u;
    let d1 = (lh.y << 1u) | (lh.x >> 31u);
    let d2 = lh.y >> 31u;
    var w: array<u32, 4>;
    w[0] = ll.x;
    let w1 = ll.y + d0;
    var c = select(0u, 1u, w1 < ll.y);
    w[1] = w1;
    let a2 = hh.x + d1;
    let c2a = select(0u, 1u, a2 < hh.x);
    let w2 = a2 + c;
    let c2b = select(0u, 1u, w2 < a2);
    w[2] = w2;
    w[3] = hh.y + d2 + c2a + c2b;
    return w;
}

// max(a - b, 0) of 128-bit numbers, as f32 (rounded from the words).
fn sub_sat_f32(a: array<u32, 4>, b: array<u32, 4>) -> f32 {
    var d: array<u32, 4>;
    var borrow = 0u;
    for (var i = 0u; i < 4u; i++) {
        let x = a[i] - b[i];
        let nb = select(0u, 1u, a[i] < b[i]) + select(0u, 1u, x < borrow);
        d[i] = x - borrow;
        borrow = nb;
    }
    if borrow != 0u {
        return 0.0;
    }
    return ((f32(d[3]) * 4294967296.0 + f32(d[2])) * 4294967296.0 + f32(d[1])) * 4294967296.0 + f32(d[0]);
}

// Pixel `pixel`'s largest variance of the mean over its squared limit (0
// where its samples all agree), and the sum of its three finite variances.
fn pixel_error(pixel: u32, n: u32) -> vec2<f32> {
    let base = pixel * 18u;
    if n < 2u {
        return vec2<f32>(HUGE, 0.0);
    }
    let nf = f32(n);
    // 1 / (n^2 (n - 1) 2^64), with 2^-64 applied apart (exact).
    let scale = 1.0 / (nf * nf * (nf - 1.0));
    var worst = 0.0;
    var total = 0.0;
    var brightest = 0.0;
    for (var c = 0u; c < 3u; c++) {
        let s = vec2<u32>(sums[base + 2u * c], sums[base + 2u * c + 1u]);
        let q = base + 6u + 4u * c;
        let sq = array<u32, 4>(sums[q], sums[q + 1u], sums[q + 2u], sums[q + 3u]);
        let num = sub_sat_f32(mul_128_32(sq, n), square_64(s));
        let v = num * 5.421010862427522e-20 * scale;
        worst = max(worst, v);
        total += v;
        brightest = max(brightest, (f32(s.y) + f32(s.x) * 2.3283064365386963e-10) / nf);
    }
    if worst == 0.0 {
        return vec2<f32>(0.0, total);
    }
    let limit = max(params.absolute, params.relative * brightest);
    let limit_sq = limit * limit;
    if limit_sq == 0.0 {
        return vec2<f32>(HUGE, total);
    }
    return vec2<f32>(min(worst / limit_sq, HUGE), total);
}

// The sum of pixel `pixel`'s three channel means at `n` samples
// (adaptive::optimal `image_mean`'s terms); 0 without samples.
fn pixel_mean_sum(pixel: u32, n: u32) -> f32 {
    if n == 0u {
        return 0.0;
    }
    let base = pixel * 18u;
    var sum = 0.0;
    for (var c = 0u; c < 3u; c++) {
        sum += f32(sums[base + 2u * c + 1u]) + f32(sums[base + 2u * c]) * 2.3283064365386963e-10;
    }
    return sum / f32(n);
}

// One workgroup per block (workgroups in rows past the per-dimension
// limit continue the list), one invocation per pixel of it.
@compute @workgroup_size(64)
fn converge(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let block = wg.x + wg.y * groups.x;
    if block >= params.blocks {
        return;
    }
    if local == 0u {
        atomicStore(&wg_worst, 0u);
    }
    workgroupBarrier();
    let x = (block % params.cols) * 8u + local % 8u;
    let y = (block / params.cols) * 8u + local / 8u;
    var n = params.samples;
    if params.ranged != 0u {
        n = count_ranges[block].y;
    }
    var e = vec2<f32>(0.0);
    var mean = 0.0;
    if x < params.film_w && y < params.film_h {
        e = pixel_error(y * params.film_w + x, n);
        if params.ranged != 0u {
            mean = pixel_mean_sum(y * params.film_w + x, n);
        }
    }
    // Non-negative floats order as their bits do.
    atomicMax(&wg_worst, bitcast<u32>(e.x));
    wg_variance[local] = e.y;
    wg_mean[local] = mean;
    workgroupBarrier();
    if local == 0u {
        let entry = active_blocks[block];
        if params.ranged == 0u && (entry & RETIRED) != 0u {
            return;
        }
        // A fixed order: the sums are the same on every run.
        var total = 0.0;
        var means = 0.0;
        for (var i = 0u; i < 64u; i++) {
            total += wg_variance[i];
            means += wg_mean[i];
        }
        let worst = bitcast<f32>(atomicLoad(&wg_worst));
        let mean_bits = select(0u, bitcast<u32>(means), params.ranged != 0u);
        block_stats[block] = vec4<u32>(bitcast<u32>(total), bitcast<u32>(worst), n, mean_bits);
        if params.ranged == 0u && worst <= 1.0 {
            active_blocks[block] = entry | RETIRED;
        }
    }
}
