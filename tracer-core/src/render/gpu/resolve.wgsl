// Resolves a film's fixed-point sums to 8-bit sRGB on the GPU, so that a
// local render reads back 3 bytes a pixel instead of 24. Its bindings are
// also those of resolve_linear.wgsl, which imports this file.
//
// Bit for bit the host's `Film::srgb8`: WGSL has no f64 to redo the host's
// `sum / (n * 2^32)` rounding, but the code of a sum only depends on which
// of 255 thresholds it reaches, and the host computes those (the smallest
// sum giving each code at this sample count) with its own arithmetic. Here
// a sum is only compared with them: a binary search over u64 pairs.

// Keep in sync with layout.rs `ResolveParams`.
struct ResolveParams {
    // Pixels of the film.
    pixels: u32,
    _pad0: u32,
    // resolve_linear only: the host's f64 scale 1 / (n * 2^32) for the
    // film's sample count n, as its (low, high) bit words; 0 when n = 0.
    scale_lo: u32,
    scale_hi: u32,
}

// Bindings: wgsl.rs RESOLVE.

fn reaches(lo: u32, hi: u32, t: vec2<u32>) -> bool {
    return hi > t.y || (hi == t.y && lo >= t.x);
}

// The number of thresholds the sum reaches: its 8-bit sRGB code.
fn code(word: u32) -> u32 {
    let lo = sums[word];
    let hi = sums[word + 1u];
    var c = 0u;
    for (var step = 128u; step > 0u; step = step >> 1u) {
        // c + step - 1 <= 254: the steps add up to 255.
        if reaches(lo, hi, thresholds[c + step - 1u]) {
            c += step;
        }
    }
    return c;
}

@compute @workgroup_size(64)
fn resolve_srgb8(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    // Rows of workgroups past the per-dimension limit continue the film.
    let k = id.x + id.y * groups.x * 64u;
    let first = k * 4u;
    if first >= params.pixels {
        return;
    }
    var words = array<u32, 3>(0u, 0u, 0u);
    for (var p = 0u; p < 4u; p++) {
        let pixel = first + p;
        if pixel >= params.pixels {
            break;
        }
        for (var c = 0u; c < 3u; c++) {
            let byte = 3u * p + c;
            words[byte / 4u] |= code(6u * pixel + 2u * c) << (8u * (byte % 4u));
        }
    }
    for (var w = 0u; w < 3u; w++) {
        image[3u * k + w] = words[w];
    }
}
