//! A small equirectangular sky for the environment-image tests (root and
//! tracer-core test crates both include this file): a gradient from a blue
//! zenith to a pale horizon, a dark ground below it, and a one-texel sun.

/// Linear RGB texels of a `w` x `h` sky, rows from the top, with the sun
/// of radiance `sun_rgb` at texel `sun`.
pub fn texels(w: u32, h: u32, sun: (u32, u32), sun_rgb: [f32; 3]) -> Vec<[f32; 3]> {
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let t = y as f32 / (h - 1) as f32;
            if (x, y) == sun {
                sun_rgb
            } else if t < 0.5 {
                [0.2 + 0.6 * t, 0.3 + 0.5 * t, 0.8 - 0.2 * t]
            } else {
                [0.15, 0.12, 0.1]
            }
        })
        .collect()
}
