// The error-optimal mode's decision between rounds, on the GPU (issue 36):
// adaptive/optimal.rs `RmseSchedule::after_round` from the blocks'
// statistics (converge.wgsl, ranged), so that its rounds chain without
// the host. One workgroup: the image's estimated MSE and mean, the stop
// test, the allocation n_b = clamp(ceil(lambda sqrt(w_b / c_b))) with
// lambda by the host's bracket and bisection, each block's next count on the
// host's grid (`RmseSettings::step`), then the next round's listed items
// (sums.wgsl listed_work) and its slices' indirect dispatch arguments.
// What the host reads back is one RoundLog a round. Sums are f32 where
// the host's are f64. A block's cost is its rays a pixel-sample, counted
// by the trace kernel (stack.wgsl, `block_rays`) as the host books a
// ranged GPU render's runs (optimal.rs Costs::per_block).

struct AllocateParams {
    film_w: u32,
    film_h: u32,
    // Blocks per row of the film, and in all.
    cols: u32,
    blocks: u32,
    min_samples: u32,
    max_samples: u32,
    // RmseSettings::max_rounds, and the round this dispatch ends.
    max_rounds: u32,
    round: u32,
    // Samples a listed item (plan.rs LISTED_CHUNK).
    chunk: u32,
    // The trace's slices: how many a round, items each, and invocations
    // a workgroup of the trace kernel.
    slices: u32,
    slice_items: u32,
    group_invocations: u32,
    target_rmse: f32,
    relative_rmse: f32,
}

// layout.rs RoundLog: what a round ended with.
struct RoundLog {
    // Blocks the round sampled.
    active_blocks: u32,
    // Pixel-samples of the image after it, (low, high).
    samples_lo: u32,
    samples_hi: u32,
    // Items of the next round: 0 once the render is done.
    next_items: u32,
    estimated_mse: f32,
    target_mse: f32,
    // Pixel-samples the render is expected to take in all: the
    // allocation meeting the target, at least the next round's counts.
    expected_samples: f32,
    _pad: u32,
}

// Bindings: wgsl.rs ALLOCATE.

const T: u32 = 256u;

var<workgroup> red_f: array<f32, 256>;
// Costs::per_block's cost of a block nothing was measured for: the mean
// over the measured ones, 1 where none was. The same in every invocation.
var<private> fallback_cost: f32 = 1.0;
var<workgroup> red_u: array<u32, 256>;
var<workgroup> wg_total: u32;

// The pixels of block `b` inside the film.
fn block_area(b: u32) -> u32 {
    let x = (b % params.cols) * 8u;
    let y = (b / params.cols) * 8u;
    return min(8u, params.film_w - x) * min(8u, params.film_h - y);
}

// Block `b`'s variance of one sample, mean over its pixels and channels
// (optimal.rs BlockStats::w), at its count now.
fn block_w(b: u32) -> f32 {
    let n = ranges[b].y;
    return bitcast<f32>(block_stats[b].x) * f32(n) / (3.0 * f32(block_area(b)));
}

// Block `b`'s rays so far and its pixel-samples (the samples of each of
// its pixels now, as the host books each round's).
fn rays_of(b: u32) -> f32 {
    return f32(block_rays[2u * b]) + f32(block_rays[2u * b + 1u]) * 4294967296.0;
}

fn pixel_samples_of(b: u32) -> f32 {
    return f32(block_area(b)) * f32(ranges[b].y);
}

// Block `b`'s cost of one pixel-sample (Costs::per_block).
fn cost_of(b: u32) -> f32 {
    let rays = rays_of(b);
    let samples = pixel_samples_of(b);
    return select(fallback_cost, rays / samples, rays > 0.0 && samples > 0.0);
}

// Sums of every invocation's `v`, in a fixed order; every invocation gets
// it. Call from uniform control flow.
fn sum_f32(lid: u32, v: f32) -> f32 {
    red_f[lid] = v;
    workgroupBarrier();
    for (var s = T / 2u; s > 0u; s >>= 1u) {
        if (lid < s) {
            red_f[lid] += red_f[lid + s];
        }
        workgroupBarrier();
    }
    let total = workgroupUniformLoad(&red_f[0]);
    workgroupBarrier();
    return total;
}

fn sum_u32(lid: u32, v: u32) -> u32 {
    red_u[lid] = v;
    workgroupBarrier();
    for (var s = T / 2u; s > 0u; s >>= 1u) {
        if (lid < s) {
            red_u[lid] += red_u[lid + s];
        }
        workgroupBarrier();
    }
    let total = workgroupUniformLoad(&red_u[0]);
    workgroupBarrier();
    return total;
}

// optimal.rs `allocate`'s count for block `b` at multiplier `lambda`:
// ceil(lambda sqrt(w / cost)) within [its count, max].
fn count_at(b: u32, lambda: f32) -> u32 {
    let lo = ranges[b].y;
    let want = lambda * sqrt(max(block_w(b), 0.0) / max(cost_of(b), 1e-12));
    let n = u32(min(ceil(want), f32(params.max_samples)));
    return min(max(n, lo), max(params.max_samples, lo));
}

// The image's estimated MSE were every block at `count_at(lambda)`
// (optimal.rs mse_at).
fn mse_at(lid: u32, lambda: f32, pixels: f32) -> f32 {
    var part = 0.0;
    for (var b = lid; b < params.blocks; b += T) {
        part += f32(block_area(b)) * block_w(b) / f32(max(count_at(b, lambda), 1u));
    }
    return sum_f32(lid, part) / pixels;
}

// Step k of the grid min * 2^(k/4), rounded up (RmseSettings::step): the
// power of two exact, the quarter powers as constants.
fn grid_count(k: u32) -> u32 {
    let quarter = array<f32, 4>(1.0, 1.189207115002721, 1.4142135623730951, 1.681792830507429);
    return u32(ceil(f32(params.min_samples) * exp2(f32(k / 4u)) * quarter[k % 4u]));
}

// RmseSettings::step: the count a block at `n` goes to when the
// allocation wants `want`.
fn step_to(n: u32, want: u32) -> u32 {
    if (want <= n || n >= params.max_samples) {
        return n;
    }
    let goal = min(min(want, n * 2u), params.max_samples);
    // The grid reaches any u32 within 4 * 32 steps from min >= 1.
    for (var k = 0u; k < 160u; k++) {
        let g = grid_count(k);
        if (g >= goal) {
            return max(min(g, params.max_samples), n + 1u);
        }
    }
    return max(goal, n + 1u);
}

fn items_of(n: u32, next: u32) -> u32 {
    return (next - n + params.chunk - 1u) / params.chunk;
}

@compute @workgroup_size(256)
fn allocate(@builtin(local_invocation_index) lid: u32) {
    // The image after the round.
    var mse_part = 0.0;
    var mean_part = 0.0;
    var pixels_part = 0u;
    var active_part = 0u;
    var rays_part = 0.0;
    var measured_part = 0.0;
    // Pixel-samples (a block's at most 64 x max_samples) as (low, high).
    var samples_lo = 0u;
    var samples_hi = 0u;
    for (var b = lid; b < params.blocks; b += T) {
        let r = ranges[b];
        let area = block_area(b);
        mse_part += f32(area) * block_w(b) / f32(max(r.y, 1u));
        mean_part += bitcast<f32>(block_stats[b].w);
        pixels_part += area;
        active_part += select(0u, 1u, r.y > r.x);
        let rays = rays_of(b);
        let samples = pixel_samples_of(b);
        if (rays > 0.0 && samples > 0.0) {
            rays_part += rays;
            measured_part += samples;
        }
        let lo = samples_lo + area * r.y;
        samples_hi += select(0u, 1u, lo < samples_lo);
        samples_lo = lo;
    }
    let pixels = f32(sum_u32(lid, pixels_part));
    let mse = sum_f32(lid, mse_part) / pixels;
    let mean = sum_f32(lid, mean_part) / (3.0 * pixels);
    let active_blocks = sum_u32(lid, active_part);
    let measured = sum_f32(lid, measured_part);
    let rays = sum_f32(lid, rays_part);
    fallback_cost = select(1.0, rays / measured, measured > 0.0);
    // The low words' 16-bit halves sum without overflow.
    let lo_lo = sum_u32(lid, samples_lo & 0xffffu);
    let lo_hi = sum_u32(lid, samples_lo >> 16u);
    let hi = sum_u32(lid, samples_hi);
    let t = max(params.target_rmse, params.relative_rmse * mean);
    let target_mse = t * t;

    // The next counts: towards the cheapest allocation meeting 0.9 of the
    // target (the host's margin), unless the image is there or the rounds
    // are spent.
    let go = mse > target_mse && params.round + 1u < params.max_rounds;
    var lambda = 0.0;
    if (go) {
        let goal = 0.9 * target_mse;
        var a = 0.0;
        var b = 1.0;
        var capped = false;
        loop {
            if (mse_at(lid, b, pixels) <= goal) {
                break;
            }
            if (b > 1e30) {
                capped = true;
                break;
            }
            b *= 4.0;
        }
        if (!capped) {
            for (var i = 0u; i < 64u; i++) {
                let m = 0.5 * (a + b);
                if (mse_at(lid, m, pixels) > goal) {
                    a = m;
                } else {
                    b = m;
                }
            }
        }
        lambda = b;
    }

    // Each invocation a run of neighbouring blocks: their items, a scan,
    // then each block's next range and first item.
    let per = (params.blocks + T - 1u) / T;
    let first = min(lid * per, params.blocks);
    let end = min(first + per, params.blocks);
    var items = 0u;
    var expected_part = 0.0;
    var next_part = 0.0;
    for (var b = first; b < end; b++) {
        let n = ranges[b].y;
        let want = select(n, count_at(b, lambda), go);
        let next = select(n, step_to(n, want), go);
        items += items_of(n, next);
        expected_part += f32(block_area(b)) * f32(want);
        next_part += f32(block_area(b)) * f32(next);
    }
    let expected = max(sum_f32(lid, expected_part), sum_f32(lid, next_part));
    red_u[lid] = items;
    workgroupBarrier();
    if (lid == 0u) {
        var run = 0u;
        for (var i = 0u; i < T; i++) {
            let v = red_u[i];
            red_u[i] = run;
            run += v;
        }
        // Past the last block: the round's items in all.
        ranges[params.blocks] = vec4<u32>(0u, 0u, run, 0u);
        wg_total = run;
    }
    let total = workgroupUniformLoad(&wg_total);
    var item = red_u[lid];
    for (var b = first; b < end; b++) {
        let n = ranges[b].y;
        let next = select(n, step_to(n, count_at(b, lambda)), go);
        ranges[b] = vec4<u32>(n, next, item, 0u);
        item += items_of(n, next);
    }
    for (var s = lid; s < params.slices; s += T) {
        let start = min(s * params.slice_items, total);
        let n = min(params.slice_items, total - start);
        let groups = (n * 64u + params.group_invocations - 1u) / params.group_invocations;
        let gx = min(groups, 65535u);
        dispatch_args[3u * s] = gx;
        dispatch_args[3u * s + 1u] = select(0u, (groups + gx - 1u) / max(gx, 1u), gx > 0u);
        dispatch_args[3u * s + 2u] = 1u;
    }
    if (lid == 0u) {
        let samples = vec2<u32>(lo_lo + (lo_hi << 16u), hi + (lo_hi >> 16u));
        // The carry out of the low word.
        let carry = select(0u, 1u, samples.x < lo_lo);
        round_log[params.round] = RoundLog(
            active_blocks,
            samples.x,
            samples.y + carry,
            total,
            mse,
            target_mse,
            expected,
            0u,
        );
    }
}
