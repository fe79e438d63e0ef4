//! import resolve.wgsl
//! import wide_int.wgsl
// Resolves a film's fixed-point sums to linear f32 RGB on the GPU, so that
// a local render to EXR reads back 12 bytes a pixel instead of 24.
// Uses resolve.wgsl's bindings.
//
// Bit for bit the host's `resolve_pixel` (film/mod.rs):
//     (s as f64 * scale) as f32,  scale = 1 / (n * 2^32) as f64,
// three roundings to nearest, ties to even: the u64 sum to 53 bits, the
// product to 53 bits, that to 24 bits. WGSL has no f64 (nor a 64-bit
// integer), so each is done here on u32 words; the host passes `scale`'s
// bits rather than the GPU dividing.
//
// No f32 subnormal or overflow can occur: 1 <= s < 2^64 and
// 1 <= n < 2^32 give 2^-64 < s * scale <= 2^32, far inside f32's normal
// range (2^-126 .. 2^128), and the f64 product is normal too.

// a + b as (sum, carry).
fn add_carry(a: u32, b: u32) -> vec2<u32> {
    let s = a + b;
    return vec2<u32>(s, select(0u, 1u, s < a));
}

// Round to nearest, ties to even: whether to add 1 to a kept value whose
// lowest bit is `odd`, given the first dropped bit and whether any bit
// below it is set.
fn round_up(odd: bool, round_bit: bool, sticky: bool) -> bool {
    return round_bit && (sticky || odd);
}

// A 53-bit significand (low, high words; high < 2^21) and its power of 2:
// the value is m * 2^e, with bit 52 of m set.
struct Sig {
    m: vec2<u32>,
    e: i32,
}

// The kept 53 bits m (a power of 2: e) rounded to nearest, ties to even,
// by the dropped bits (the first, and whether any below it is set); a
// carry out of 53 bits moves to the next binade.
fn round_sig(m_in: vec2<u32>, e_in: i32, round_bit: bool, sticky: bool) -> Sig {
    var m = m_in;
    var e = e_in;
    if round_up((m.x & 1u) != 0u, round_bit, sticky) {
        let c = add_carry(m.x, 1u);
        m = vec2<u32>(c.x, m.y + c.y);
        if m.y == (1u << 21u) {
            // Rounded up to 2^53.
            m = vec2<u32>(0u, 1u << 20u);
            e += 1;
        }
    }
    return Sig(m, e);
}

// The u64 sum (lo, hi) != 0 as an f64: exact below 2^53, else rounded.
fn u64_to_f64(lo: u32, hi: u32) -> Sig {
    var bits: u32;
    if hi != 0u {
        bits = 64u - countLeadingZeros(hi);
    } else {
        bits = 32u - countLeadingZeros(lo);
    }
    if bits <= 53u {
        // Shift left by 53 - bits: normalised, exact.
        let s = 53u - bits;
        var m: vec2<u32>;
        if s == 0u {
            m = vec2<u32>(lo, hi);
        } else if s >= 32u {
            m = vec2<u32>(0u, lo << (s - 32u));
        } else {
            m = vec2<u32>(lo << s, (hi << s) | (lo >> (32u - s)));
        }
        return Sig(m, -i32(s));
    }
    // Drop s = bits - 53 bits (1..11, all in the low word).
    let s = bits - 53u;
    let m = vec2<u32>((lo >> s) | (hi << (32u - s)), hi >> s);
    let round_bit = ((lo >> (s - 1u)) & 1u) != 0u;
    let sticky = (lo & ((1u << (s - 1u)) - 1u)) != 0u;
    return round_sig(m, i32(s), round_bit, sticky);
}

// The f64 product a * b of two normalised significands, rounded to 53 bits.
fn mul_f64(a: Sig, b: Sig) -> Sig {
    // The exact product, 4 words w0..w3 (under 2^106: w3 < 2^10).
    let p00 = mul_wide(a.m.x, b.m.x);
    let p01 = mul_wide(a.m.x, b.m.y);
    let p10 = mul_wide(a.m.y, b.m.x);
    let p11 = mul_wide(a.m.y, b.m.y);
    let w0 = p00.x;
    let s1 = add_carry(p00.y, p01.x);
    let s2 = add_carry(s1.x, p10.x);
    let w1 = s2.x;
    let t1 = add_carry(p11.x, p01.y);
    let t2 = add_carry(t1.x, p10.y);
    let t3 = add_carry(t2.x, s1.y + s2.y);
    let w2 = t3.x;
    let w3 = p11.y + t1.y + t2.y + t3.y;
    // Keep 53 bits below the top one, bit 105 or 104: drop 52 + top bits,
    // i.e. shift word 1 onwards by r = 20 + top.
    let top = (w3 >> 9u) & 1u;
    let r = 20u + top;
    let m = vec2<u32>((w1 >> r) | (w2 << (32u - r)), (w2 >> r) | (w3 << (32u - r)));
    let round_bit = ((w1 >> (r - 1u)) & 1u) != 0u;
    let sticky = w0 != 0u || (w1 & ((1u << (r - 1u)) - 1u)) != 0u;
    return round_sig(m, a.e + b.e + 52 + i32(top), round_bit, sticky);
}

// The f32 bits of an f64 in the f32 normal range, rounded to 24 bits.
fn f64_to_f32_bits(x: Sig) -> u32 {
    // Drop the low 29 of the 53 bits.
    var f = (x.m.x >> 29u) | (x.m.y << 3u);
    let round_bit = ((x.m.x >> 28u) & 1u) != 0u;
    let sticky = (x.m.x & 0x0fffffffu) != 0u;
    // The value is f * 2^(e + 29), f in [2^23, 2^24): exponent e + 29 + 23.
    var exponent = x.e + 52;
    if round_up((f & 1u) != 0u, round_bit, sticky) {
        f += 1u;
        if f == (1u << 24u) {
            f = 1u << 23u;
            exponent += 1;
        }
    }
    return (u32(exponent + 127) << 23u) | (f & 0x7fffffu);
}

// The host's `(s as f64 * scale) as f32` for one channel's sum.
fn resolve_channel(lo: u32, hi: u32) -> u32 {
    // A zero scale (no samples) and a zero sum resolve to +0.0.
    let scale_exp = (params.scale_hi >> 20u) & 0x7ffu;
    if (lo == 0u && hi == 0u) || scale_exp == 0u {
        return 0u;
    }
    // The scale is normal (>= 2^-64): its significand with the hidden bit.
    let scale = Sig(
        vec2<u32>(params.scale_lo, (params.scale_hi & 0xfffffu) | (1u << 20u)),
        i32(scale_exp) - 1075,
    );
    return f64_to_f32_bits(mul_f64(u64_to_f64(lo, hi), scale));
}

@compute @workgroup_size(64)
fn resolve_linear(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    // Rows of workgroups past the per-dimension limit continue the film.
    let pixel = id.x + id.y * groups.x * 64u;
    if pixel >= params.pixels {
        return;
    }
    for (var c = 0u; c < 3u; c++) {
        let word = 6u * pixel + 2u * c;
        image[3u * pixel + c] = resolve_channel(sums[word], sums[word + 1u]);
    }
}
