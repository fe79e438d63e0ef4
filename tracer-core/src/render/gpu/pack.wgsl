// Packs a film's fixed-point sums into the farm's compact layout
// (tessera_proto::film_codec): each R, G, B sum as its low `width` bytes,
// little-endian, pixel after pixel, where `width` is the fewest bytes that
// every sum of the film needs (at least 1). A GPU worker reads back and
// sends these bytes as they are: 15 a pixel at 64 samples instead of 24,
// and no packing on the host.

struct PackParams {
    // Pixels of the film.
    pixels: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

// Bindings: wgsl.rs PACK.

var<workgroup> group_width: atomic<u32>;

fn bytes_of(x: u32) -> u32 {
    return (32u - countLeadingZeros(x) + 7u) / 8u;
}

// The bytes one sum needs.
fn sum_width(word: u32) -> u32 {
    let hi = sums[word + 1u];
    if hi != 0u {
        return 4u + bytes_of(hi);
    }
    return max(1u, bytes_of(sums[word]));
}

// Rows of workgroups past the per-dimension limit continue the film.
fn index(id: vec3<u32>, groups: vec3<u32>) -> u32 {
    return id.x + id.y * groups.x * 64u;
}

@compute @workgroup_size(64)
fn measure(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    if local == 0u {
        atomicStore(&group_width, 0u);
    }
    workgroupBarrier();
    let pixel = index(id, groups);
    if pixel < params.pixels {
        let w = max(sum_width(6u * pixel), max(sum_width(6u * pixel + 2u), sum_width(6u * pixel + 4u)));
        atomicMax(&group_width, w);
    }
    workgroupBarrier();
    // One global atomic a workgroup, not one a pixel.
    if local == 0u {
        atomicMax(&width, atomicLoad(&group_width));
    }
}

@compute @workgroup_size(64)
fn pack(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    // Four pixels an invocation: 12 * width bytes, whole words.
    let k = index(id, groups);
    let first = k * 4u;
    if first >= params.pixels {
        return;
    }
    let w = atomicLoad(&width);
    var words: array<u32, 24>;
    for (var i = 0u; i < 24u; i++) {
        words[i] = 0u;
    }
    for (var p = 0u; p < 4u; p++) {
        let pixel = first + p;
        if pixel >= params.pixels {
            break;
        }
        for (var c = 0u; c < 3u; c++) {
            let lo = sums[6u * pixel + 2u * c];
            let hi = sums[6u * pixel + 2u * c + 1u];
            for (var b = 0u; b < w; b++) {
                var byte: u32;
                if b < 4u {
                    byte = (lo >> (8u * b)) & 0xffu;
                } else {
                    byte = (hi >> (8u * (b - 4u))) & 0xffu;
                }
                let at = (3u * p + c) * w + b;
                words[at / 4u] |= byte << (8u * (at % 4u));
            }
        }
    }
    for (var i = 0u; i < 3u * w; i++) {
        packed[3u * w * k + i] = words[i];
    }
}
