//! The path integrator's environment image: the radiance arriving from
//! each direction no surface or light is met in, read from an
//! equirectangular (latitude-longitude) EXR, Radiance HDR, PNG or JPEG
//! file (docs/path-tracing.md, "Environment").
//!
//! The mapping is Mitsuba 3's `envmap` emitter's, so that one file lights
//! both renderers alike (the tests compare them): a direction is
//! d = (sin phi sin theta, cos theta, -cos phi sin theta) with
//! phi = 2 pi u and theta = pi v. The image's top row is straight up (+Y),
//! u = 0 looks along -Z, u = 1/4 along +X. Texel columns are centred at
//! u = (x + 1/2) / W, rows lie at v = y / (H - 1) (the first and last
//! rows are the poles), and radiance is bilinear between them, wrapping
//! in u. A rotation turns the image about +Y.
//!
//! Importance sampling follows the radiance as it is looked up: the
//! W x (H - 1) cells between four neighbouring texels are chosen in
//! proportion to their corners' mean luminance (the mean of R, G and B)
//! times sin theta at the cell's centre (a marginal CDF over cell rows, a
//! conditional CDF per row), then a point in the cell with the bilinear
//! density of its corners' luminances (pbrt-v4's `SampleBilinear`). The
//! density over (u, v) is the cell's times the bilinear luminance at the
//! point over the corners' mean; over solid angle, that over
//! 2 pi^2 sin theta. Where the density is 0 the radiance is 0 too, so
//! light sampling alone is unbiased, and MIS with BSDF sampling only
//! lowers the variance.
//!
//! The GPU reads the same arrays (render/gpu/layout.rs `PathData`,
//! path.wgsl `env_*`); the host computes in f64 from them.

use std::f64::consts::PI;

/// Largest side of an environment image read (a file declaring more is
/// refused, not allocated): an 8192 x 4096 EXR peaks at about 1.3 GB
/// while it is decoded and its sampling tables built (6.8 s on the 2-core
/// VM), and then holds 0.64 GB.
pub const MAX_SIDE: u32 = 8_192;

/// An environment image ready to light a render.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvironmentMap {
    /// The file it came from (for messages).
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Linear RGB radiance of each texel, times the scene's scale, rows
    /// from the top.
    pub texels: Vec<[f32; 3]>,
    /// The rotation about +Y, in turns of u (`environment_rotation` / 360).
    pub u_offset: f64,
    /// Per cell (W x (H - 1), rows from the top): its sampling density
    /// over the unit square of (u, v).
    pub density: Vec<f32>,
    /// Per cell: the running sum of its row's weights over the row's
    /// total (the row's last is 1).
    pub row_cdf: Vec<f32>,
    /// Per row of cells: the running sum of the rows' totals over the
    /// whole (the last is 1).
    pub marginal_cdf: Vec<f32>,
    /// The integral over the sphere of the mean of R, G and B: its power
    /// over r^2 in `Light::power`'s units (flux over pi).
    pub integral: f64,
}

/// A direction drawn from the environment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EnvironmentSample {
    pub dir: [f64; 3],
    pub radiance: [f32; 3],
    /// Solid-angle density of the draw.
    pub pdf: f64,
}

impl EnvironmentMap {
    /// Decodes an image file's bytes (by content: OpenEXR, Radiance HDR,
    /// PNG, JPEG; 8- and 16-bit images are sRGB-encoded), times `scale`,
    /// turned `rotation_degrees` about +Y. The error says what is wrong,
    /// without the file's name (the caller adds where).
    pub fn decode(
        name: &str,
        bytes: &[u8],
        scale: f64,
        rotation_degrees: f64,
    ) -> Result<EnvironmentMap, String> {
        use image::ImageFormat as F;
        let format = image::guess_format(bytes)
            .map_err(|_| "is not an EXR, HDR, PNG or JPEG image".to_string())?;
        if !matches!(format, F::OpenExr | F::Hdr | F::Png | F::Jpeg) {
            return Err(format!(
                "is a {format:?} image; an environment is an EXR, HDR, PNG or JPEG file"
            ));
        }
        let decoded = crate::texture::decode_within(bytes, format, MAX_SIDE, 1 << 30)?;
        let encoded = !matches!(format, F::OpenExr | F::Hdr);
        let rgb = decoded.into_rgb32f();
        let (width, height) = rgb.dimensions();
        let texels = rgb
            .pixels()
            .map(|p| {
                p.0.map(|c| {
                    let linear = if encoded {
                        crate::texture::srgb_to_linear(c as f64)
                    } else {
                        c as f64
                    };
                    (linear * scale) as f32
                })
            })
            .collect();
        // The decoded copy goes before the tables are built.
        drop(rgb);
        Self::new(name, width, height, texels, rotation_degrees)
    }

    /// The environment of `texels` (linear RGB radiance, W x H, rows from
    /// the top), with its sampling distribution.
    pub fn new(
        name: &str,
        width: u32,
        height: u32,
        texels: Vec<[f32; 3]>,
        rotation_degrees: f64,
    ) -> Result<EnvironmentMap, String> {
        if width < 2 || height < 2 {
            return Err(format!(
                "is {width}x{height}; an environment image needs at least 2x2 texels (give a colour for a uniform one)"
            ));
        }
        if let Some(i) = texels
            .iter()
            .position(|t| t.iter().any(|c| !(c.is_finite() && *c >= 0.0)))
        {
            return Err(format!(
                "texel ({}, {}) is {:?}: radiance must be finite and >= 0",
                i % width as usize,
                i / width as usize,
                texels[i]
            ));
        }
        let (w, h) = (width as usize, height as usize);
        let rows = h - 1;
        let mut weights = vec![0.0f64; w * rows];
        let mut row_totals = vec![0.0f64; rows];
        for y in 0..rows {
            let sin = ((y as f64 + 0.5) / rows as f64 * PI).sin();
            for x in 0..w {
                let c = corner_luminances(&texels, w, x, y);
                let mean = (c[0] + c[1] + c[2] + c[3]) / 4.0;
                weights[y * w + x] = mean * sin;
                row_totals[y] += mean * sin;
            }
        }
        let total: f64 = row_totals.iter().sum();
        let cells = (w * rows) as f64;
        let mut density = vec![0.0f32; w * rows];
        let mut row_cdf = vec![0.0f32; w * rows];
        let mut marginal_cdf = vec![0.0f32; rows];
        let mut acc_rows = 0.0;
        for y in 0..rows {
            acc_rows += row_totals[y];
            marginal_cdf[y] = if total > 0.0 {
                (acc_rows / total) as f32
            } else {
                (y + 1) as f32 / rows as f32
            };
            let mut acc = 0.0;
            for x in 0..w {
                let i = y * w + x;
                acc += weights[i];
                row_cdf[i] = if row_totals[y] > 0.0 {
                    (acc / row_totals[y]) as f32
                } else {
                    (x + 1) as f32 / w as f32
                };
                if total > 0.0 {
                    density[i] = (weights[i] / total * cells) as f32;
                }
            }
            // Exactly 1, whatever the rounding: a draw always lands.
            row_cdf[y * w + w - 1] = 1.0;
        }
        marginal_cdf[rows - 1] = 1.0;
        // Each cell covers (2 pi / W) x (pi / (H - 1)) of (phi, theta).
        let integral = total * (2.0 * PI / w as f64) * (PI / rows as f64);
        Ok(EnvironmentMap {
            name: name.to_string(),
            width,
            height,
            texels,
            u_offset: rotation_degrees / 360.0,
            density,
            row_cdf,
            marginal_cdf,
            integral,
        })
    }

    /// The image's (u, v) of unit direction `d`.
    fn uv_of(&self, d: [f64; 3]) -> (f64, f64) {
        let u = d[0].atan2(-d[2]) / (2.0 * PI) - self.u_offset;
        let v = d[1].clamp(-1.0, 1.0).acos() / PI;
        (u - u.floor(), v)
    }

    /// Radiance arriving along -`d` (seen looking along unit direction `d`).
    pub fn radiance(&self, d: [f64; 3]) -> [f32; 3] {
        let (u, v) = self.uv_of(d);
        self.lookup(u, v)
    }

    /// Bilinear radiance at (u, v) of the image.
    fn lookup(&self, u: f64, v: f64) -> [f32; 3] {
        let w = self.width as usize;
        let (x0, y0, fx, fy) = self.cell_at(u, v);
        let x1 = (x0 + 1) % w;
        let t = |x: usize, y: usize| self.texels[y * w + x];
        let (a, b, c, d) = (t(x0, y0), t(x1, y0), t(x0, y0 + 1), t(x1, y0 + 1));
        std::array::from_fn(|k| {
            let top = a[k] as f64 * (1.0 - fx) + b[k] as f64 * fx;
            let bottom = c[k] as f64 * (1.0 - fx) + d[k] as f64 * fx;
            (top * (1.0 - fy) + bottom * fy) as f32
        })
    }

    /// The cell holding (u, v) (its top-left texel, the cell's column and
    /// row; the texel columns are centred, the rows at the poles) and
    /// where (u, v) lies in it, in [0, 1) each: the one place radiance
    /// lookups and densities find their cell.
    fn cell_at(&self, u: f64, v: f64) -> (usize, usize, f64, f64) {
        let (w, rows) = (self.width as usize, self.height as usize - 1);
        let mut xf = u - 0.5 / w as f64;
        xf = (xf - xf.floor()) * w as f64;
        let x = (xf.floor() as usize).min(w - 1);
        let yf = v.clamp(0.0, 1.0) * rows as f64;
        let y = (yf.floor() as usize).min(rows - 1);
        (x, y, xf - x as f64, yf - y as f64)
    }

    /// The solid-angle density of [`Self::sample`] drawing unit direction `d`.
    pub fn pdf(&self, d: [f64; 3]) -> f64 {
        let (u, v) = self.uv_of(d);
        let sin = (d[0] * d[0] + d[2] * d[2]).sqrt();
        if !(sin > 0.0) {
            return 0.0;
        }
        let (x, y, fx, fy) = self.cell_at(u, v);
        self.density_at(x, y, fx, fy) / (2.0 * PI * PI * sin)
    }

    fn corners(&self, x: usize, y: usize) -> [f64; 4] {
        corner_luminances(&self.texels, self.width as usize, x, y)
    }

    /// The density over (u, v) at (fx, fy) within cell (x, y).
    fn density_at(&self, x: usize, y: usize, fx: f64, fy: f64) -> f64 {
        let cell = self.density[y * self.width as usize + x] as f64;
        if !(cell > 0.0) {
            return 0.0;
        }
        let c = self.corners(x, y);
        let mean = (c[0] + c[1] + c[2] + c[3]) / 4.0;
        cell * bilerp(fx, fy, c) / mean
    }

    /// A direction drawn for uniform numbers `(a, b)`, or `None` where the
    /// image is black or the draw lands on a pole.
    pub fn sample(&self, a: f32, b: f32) -> Option<EnvironmentSample> {
        let (w, rows) = (self.width as usize, self.height as usize - 1);
        let (y, ry) = pick(&self.marginal_cdf, a);
        let row = &self.row_cdf[y * w..(y + 1) * w];
        let (x, rx) = pick(row, b);
        let c = self.corners(x, y);
        let fy = sample_linear(ry, c[0] + c[1], c[2] + c[3]);
        let fx = sample_linear(rx, lerp(fy, c[0], c[2]), lerp(fy, c[1], c[3]));
        let density = self.density_at(x, y, fx, fy);
        if !(density > 0.0) {
            return None;
        }
        let u = (x as f64 + 0.5 + fx) / w as f64;
        let v = (y as f64 + fy) / rows as f64;
        let (sin_t, cos_t) = (v * PI).sin_cos();
        if !(sin_t > 0.0) {
            return None;
        }
        let phi = 2.0 * PI * (u + self.u_offset);
        let dir = [phi.sin() * sin_t, cos_t, -phi.cos() * sin_t];
        Some(EnvironmentSample {
            dir,
            radiance: self.lookup(u - u.floor(), v),
            pdf: density / (2.0 * PI * PI * sin_t),
        })
    }

    /// Bytes held (for `render --json`'s stats).
    pub fn bytes(&self) -> usize {
        self.texels.len() * 12 + (self.density.len() + self.row_cdf.len()) * 4
    }
}

/// The luminances (the mean of R, G and B) of the corners of cell (x, y)
/// of `texels` (`w` wide): (x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1),
/// wrapping in x. The cells' weights and densities both come from these
/// (path.wgsl `env_corners` is its mirror).
fn corner_luminances(texels: &[[f32; 3]], w: usize, x: usize, y: usize) -> [f64; 4] {
    let lum = |x: usize, y: usize| {
        let t = texels[y * w + x % w];
        (t[0] as f64 + t[1] as f64 + t[2] as f64) / 3.0
    };
    [lum(x, y), lum(x + 1, y), lum(x, y + 1), lum(x + 1, y + 1)]
}

fn lerp(t: f64, a: f64, b: f64) -> f64 {
    (1.0 - t) * a + t * b
}

/// The bilinear blend at (fx, fy) of corners (0, 0), (1, 0), (0, 1), (1, 1).
fn bilerp(fx: f64, fy: f64, c: [f64; 4]) -> f64 {
    lerp(fy, lerp(fx, c[0], c[1]), lerp(fx, c[2], c[3]))
}

/// A point of [0, 1) drawn for uniform `u` with density proportional to
/// the line from `a` at 0 to `b` at 1 (pbrt-v4's `SampleLinear`).
/// path.wgsl `env_linear` is its mirror.
pub fn sample_linear(u: f64, a: f64, b: f64) -> f64 {
    if !(a + b > 0.0) || (u == 0.0 && a == 0.0) {
        return u;
    }
    let x = u * (a + b) / (a + lerp(u, a * a, b * b).sqrt());
    x.min(1.0 - f64::EPSILON)
}

/// The index of the first running sum in `cdf` above `u` (the last where
/// none is, after rounding), and where `u` lies between its lower and
/// upper sums, in [0, 1). path.wgsl `env_pick` is its mirror.
pub fn pick(cdf: &[f32], u: f32) -> (usize, f64) {
    let i = cdf.partition_point(|&c| c <= u).min(cdf.len() - 1);
    let lo = if i == 0 { 0.0 } else { cdf[i - 1] as f64 };
    let hi = cdf[i] as f64;
    let f = if hi > lo {
        ((u as f64 - lo) / (hi - lo)).clamp(0.0, 1.0 - f64::EPSILON)
    } else {
        0.5
    };
    (i, f)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(d: [f64; 3]) -> [f64; 3] {
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        d.map(|x| x / l)
    }

    /// A small image with a bright patch: the densities of its draws
    /// integrate to 1 over the sphere, and each draw's pdf is what
    /// `pdf` says of its direction.
    #[test]
    fn draws_have_the_density_pdf_gives_and_it_integrates_to_one() {
        let (w, h) = (16u32, 9u32);
        let texels = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let hot = (5..8).contains(&x) && (2..4).contains(&y);
                if hot {
                    [20.0, 10.0, 5.0]
                } else {
                    [0.1, 0.2, 0.3]
                }
            })
            .collect();
        let env = EnvironmentMap::new("t", w, h, texels, 30.0).unwrap();
        let mut draws = 0;
        for i in 0..64 {
            for j in 0..64 {
                let (a, b) = ((i as f32 + 0.5) / 64.0, (j as f32 + 0.5) / 64.0);
                let s = env.sample(a, b).unwrap();
                let p = env.pdf(s.dir);
                assert!((p - s.pdf).abs() <= 1e-4 * s.pdf, "{p} vs {}", s.pdf);
                draws += 1;
            }
        }
        assert_eq!(draws, 4096);
        // Integral of the pdf over the sphere by a fine (theta, phi) grid.
        let n = 800;
        let mut sum = 0.0;
        for i in 0..n {
            let theta = (i as f64 + 0.5) / n as f64 * PI;
            for j in 0..2 * n {
                let phi = (j as f64 + 0.5) / (2 * n) as f64 * 2.0 * PI;
                let d = [
                    phi.sin() * theta.sin(),
                    theta.cos(),
                    -phi.cos() * theta.sin(),
                ];
                sum += env.pdf(d) * theta.sin() * (PI / n as f64) * (PI / n as f64);
            }
        }
        assert!((sum - 1.0).abs() < 2e-3, "the pdf integrates to {sum}");
    }

    /// Mitsuba's mapping: the top row is up, u = 1/4 looks along +X, and a
    /// texel's centre column returns exactly that texel.
    #[test]
    fn the_mapping_is_mitsubas() {
        let (w, h) = (4u32, 3u32);
        let texels = (0..w * h).map(|i| [i as f32, 0.0, 0.0]).collect();
        let env = EnvironmentMap::new("t", w, h, texels, 0.0).unwrap();
        // Straight up: row 0, between columns (bilinear in u at the pole).
        let up = env.radiance([0.0, 1.0, 0.0]);
        assert!(up[0] <= 3.0);
        // +X at the equator: u = 1/4 is column 0.5 - 0.5 = ... centre of
        // column 0 is u = 1/8, of column 1 is 3/8: u = 1/4 is halfway.
        let x = env.radiance(unit([1.0, 0.0, 0.0]));
        assert!((x[0] - 4.5).abs() < 1e-5, "{x:?}");
        // Column 2's centre (u = 5/8) at the equator (row 1).
        let phi = 2.0 * PI * 5.0 / 8.0;
        let d = [phi.sin(), 0.0, -phi.cos()];
        assert!((env.radiance(d)[0] - 6.0).abs() < 1e-5);
        // A 90 degree rotation brings column 0's centre (u = 1/8) to u = 3/8.
        let turned = EnvironmentMap::new("t", w, h, env.texels.clone(), 90.0).unwrap();
        let phi = 2.0 * PI * 3.0 / 8.0;
        let d = [phi.sin(), 0.0, -phi.cos()];
        assert!((turned.radiance(d)[0] - 4.0).abs() < 1e-5);
    }

    #[test]
    fn bad_images_are_refused_by_what_is_wrong() {
        let e = EnvironmentMap::new("t", 1, 1, vec![[1.0; 3]], 0.0).unwrap_err();
        assert!(e.contains("at least 2x2"), "{e}");
        let e = EnvironmentMap::new(
            "t",
            2,
            2,
            vec![[1.0; 3], [f32::NAN, 0.0, 0.0], [0.0; 3], [0.0; 3]],
            0.0,
        )
        .unwrap_err();
        assert!(e.starts_with("texel (1, 0)"), "{e}");
        let e = EnvironmentMap::decode("t", b"not an image", 1.0, 0.0).unwrap_err();
        assert!(e.contains("not an EXR, HDR, PNG or JPEG"), "{e}");
        // A header declaring 16384 x 8192 texels: refused before allocating.
        let hdr = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 8192 +X 16384\n".to_vec();
        let e = EnvironmentMap::decode("t", &hdr, 1.0, 0.0).unwrap_err();
        assert!(
            e.starts_with("is over the limits of 8192 texels a side"),
            "{e}"
        );
    }
}
