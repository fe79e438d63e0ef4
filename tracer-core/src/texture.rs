//! Textures of model files: decoded images (PNG, JPEG), their samplers and
//! the one filter the shading step samples them with (docs/meshes.md,
//! "Materials and textures").
//!
//! Texture space is glTF's: (0, 0) is the top-left corner of the image,
//! u to the right, v down (OBJ's v is flipped when it is read). The
//! filter is trilinear: bilinear within a mip level, with the sampler's
//! wrap modes, in linear values, and linear between the two levels around
//! the level of detail a hit's footprint asks for ([`SurfaceAttrs::lod`]);
//! a footprint under a texel reads the full-resolution image, bilinear
//! (or nearest, for a NEAREST sampler). Colour textures are decoded from
//! sRGB exactly (the IEC 61966-2-1 curve, in f64, rounded once to f32)
//! before they are blended, data textures (metallic-roughness, normal,
//! occlusion, alpha) are byte / 255. Mip levels are made once per image
//! and decoding ([`Image::levels`]), box-filtered in linear values and
//! stored as bytes like the image, so the CPU and the GPU filter the same
//! texels (render/gpu/pbr.wgsl `tex_sample`).

use std::sync::{Arc, OnceLock};

/// How a texture coordinate outside [0, 1) is brought back (glTF's
/// `wrapS`/`wrapT`; OBJ maps repeat).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Wrap {
    #[default]
    Repeat,
    ClampToEdge,
    MirroredRepeat,
}

/// A decoded image: RGBA, 8 bits a channel as stored in the file (colour
/// channels still sRGB-encoded where the texture holds colour), rows from
/// the top.
#[derive(Clone, Debug)]
pub struct Image {
    /// The file it came from (for messages).
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub texels: Vec<[u8; 4]>,
    /// Mip levels 1.. for data decoding (`[0]`) and sRGB colour (`[1]`),
    /// made on first use ([`Image::levels`]).
    mips: [OnceLock<Vec<Level>>; 2],
}

impl PartialEq for Image {
    fn eq(&self, o: &Self) -> bool {
        (&self.name, self.width, self.height, &self.texels)
            == (&o.name, o.width, o.height, &o.texels)
    }
}

/// One level of a mip chain below the image: half the level above it in
/// each side (rounded down, at least 1), texels as the image stores them.
#[derive(Clone, Debug, PartialEq)]
pub struct Level {
    pub width: u32,
    pub height: u32,
    pub texels: Vec<[u8; 4]>,
}

/// Largest image side read (a file declaring more is refused, not allocated).
pub const MAX_SIDE: u32 = 16_384;

impl Image {
    /// Decodes a PNG or JPEG file's bytes (by its content, not its name).
    /// KTX2/Basis and WebP are refused by name: the caller warns and
    /// renders the material without the texture.
    pub fn decode(name: &str, bytes: &[u8]) -> Result<Image, String> {
        if bytes.starts_with(b"\xabKTX 20\xbb") || name.to_lowercase().ends_with(".ktx2") {
            return Err("is a KTX2/Basis texture, which Tessera does not decode".into());
        }
        if bytes.len() >= 12 && &bytes[..4] == b"RIFF" && &bytes[8..12] == b"WEBP" {
            return Err("is a WebP texture, which Tessera does not decode".into());
        }
        let format =
            image::guess_format(bytes).map_err(|_| "is not a PNG or JPEG image".to_string())?;
        if !matches!(format, image::ImageFormat::Png | image::ImageFormat::Jpeg) {
            return Err(format!(
                "is a {format:?} image; Tessera decodes PNG and JPEG textures"
            ));
        }
        let img = decode_within(bytes, format, MAX_SIDE, 1 << 30)?.into_rgba8();
        let (width, height) = img.dimensions();
        if width == 0 || height == 0 {
            return Err("has no texels".into());
        }
        let texels = img.pixels().map(|p| p.0).collect();
        Ok(Image::new(name, width, height, texels))
    }

    /// An image of `width` x `height` texels, rows from the top.
    pub fn new(name: &str, width: u32, height: u32, texels: Vec<[u8; 4]>) -> Image {
        assert_eq!(texels.len(), width as usize * height as usize);
        Image {
            name: name.to_string(),
            width,
            height,
            texels,
            mips: Default::default(),
        }
    }

    /// Its mip levels below the image (level 1 first, down to 1 x 1) for
    /// colour channels decoded as sRGB (`srgb`) or as data: each texel of
    /// a level is the mean of the texels of the level above that it
    /// covers (2 x 2, or 3 along an odd side's last texel), in linear
    /// values, encoded back to a byte (sRGB or linear) rounded to nearest.
    /// Made once, on first use.
    pub fn levels(&self, srgb: bool) -> &[Level] {
        let cell = &self.mips[srgb as usize];
        if let Some(levels) = cell.get() {
            return levels;
        }
        // Made outside the cell's initialiser, which must not wait on
        // rayon: a task waiting there may steal another that asks for the
        // same levels, a re-entrant initialisation that deadlocks (the
        // likely cause of a CPU render of Sibenik on 16 threads that hung
        // once in 56 runs). Two threads that ask at once may both make
        // them; one is kept.
        let levels = mip_chain(self, srgb);
        let _ = cell.set(levels);
        cell.get().expect("set above")
    }
}

/// [`Image::levels`], made: each level's rows in parallel (never inside a
/// `OnceLock` initialiser: see there), decoding by table and encoding sRGB
/// by a search of the bytes' midpoints (what rounding [`linear_to_srgb`]
/// to a byte gives, without a power a texel: DamagedHelmet's five
/// 2048-texel maps took 0.5 s with one), data bytes averaged as integers.
fn mip_chain(img: &Image, srgb: bool) -> Vec<Level> {
    use rayon::prelude::*;
    // The mean of texels: sRGB channels' decoded values summed in f64 and
    // encoded by the midpoints; data channels' bytes summed as integers,
    // rounded half up (the f64 rounding of their mean).
    fn mean(srgb: bool, texels: impl Iterator<Item = [u8; 4]>) -> [u8; 4] {
        let (table, mids) = (srgb_table(), srgb_midpoints());
        let (mut lin, mut bytes, mut n) = ([0.0f64; 3], [0u32; 4], 0u32);
        for t in texels {
            for k in 0..4 {
                bytes[k] += t[k] as u32;
            }
            if srgb {
                for k in 0..3 {
                    lin[k] += table[t[k] as usize] as f64;
                }
            }
            n += 1;
        }
        std::array::from_fn(|k| {
            if srgb && k < 3 {
                mids.partition_point(|&m| m <= lin[k] / n as f64) as u8
            } else {
                ((2 * bytes[k] + n) / (2 * n)) as u8
            }
        })
    }
    let mut out: Vec<Level> = Vec::new();
    let (mut w, mut h) = (img.width as usize, img.height as usize);
    while w > 1 || h > 1 {
        let (nw, nh) = ((w / 2).max(1), (h / 2).max(1));
        let above = out.last().map_or(&img.texels[..], |l| &l.texels[..]);
        let mut texels = vec![[0u8; 4]; nw * nh];
        texels.par_chunks_mut(nw).enumerate().for_each(|(y, row)| {
            let rows = y * h / nh..(y + 1) * h / nh;
            for (x, texel) in row.iter_mut().enumerate() {
                let cols = x * w / nw..(x + 1) * w / nw;
                *texel = mean(
                    srgb,
                    rows.clone().flat_map(|yy| {
                        above[yy * w + cols.start..yy * w + cols.end]
                            .iter()
                            .copied()
                    }),
                );
            }
        });
        out.push(Level {
            width: nw as u32,
            height: nh as u32,
            texels,
        });
        (w, h) = (nw, nh);
    }
    out
}

/// The linear values half way between neighbouring sRGB bytes' (255 of
/// them, rising): a linear value encodes to the byte of how many lie at or
/// below it.
fn srgb_midpoints() -> &'static [f64; 255] {
    static M: OnceLock<[f64; 255]> = OnceLock::new();
    M.get_or_init(|| std::array::from_fn(|k| srgb_to_linear((k as f64 + 0.5) / 255.0)))
}

/// A texture as a material uses it: an image, its sampler, whether its
/// colour channels are sRGB, the UV set and the `KHR_texture_transform`.
#[derive(Clone, Debug, PartialEq)]
pub struct TextureRef {
    pub image: Arc<Image>,
    pub wrap: [Wrap; 2],
    /// Magnification filter NEAREST (else linear).
    pub nearest: bool,
    /// Colour channels are sRGB-encoded (base colour, emissive).
    pub srgb: bool,
    /// Which TEXCOORD set (0 or 1).
    pub uv_set: u32,
    /// uv' = [a b c; d e f] (u, v, 1): `KHR_texture_transform` (offset,
    /// rotation, scale) or an OBJ map's `-o`/`-s`; identity by default.
    pub transform: [[f32; 3]; 2],
}

pub const IDENTITY_UV: [[f32; 3]; 2] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];

/// The linear value of an sRGB-encoded channel `c` in [0, 1] (the
/// IEC 61966-2-1 curve).
pub fn srgb_to_linear(c: f64) -> f64 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Decodes an image file's bytes in `format`, refusing (before
/// allocating) a side over `max_side` or more than `max_alloc` bytes: a
/// hostile header cannot exhaust memory. The error says why.
pub(crate) fn decode_within(
    bytes: &[u8],
    format: image::ImageFormat,
    max_side: u32,
    max_alloc: u64,
) -> Result<image::DynamicImage, String> {
    let mut reader = image::ImageReader::with_format(std::io::Cursor::new(bytes), format);
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(max_side);
    limits.max_image_height = Some(max_side);
    limits.max_alloc = Some(max_alloc);
    reader.limits(limits);
    reader.decode().map_err(|e| match e {
        image::ImageError::Limits(_) => format!(
            "is over the limits of {max_side} texels a side and {} MiB decoded ({e})",
            max_alloc >> 20
        ),
        e => format!("cannot be decoded: {e}"),
    })
}

/// The sRGB encoding of a linear channel `c` in [0, 1] (the inverse of
/// [`srgb_to_linear`]).
pub fn linear_to_srgb(c: f64) -> f64 {
    if c <= 0.0031308 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

/// byte -> linear value of an sRGB-encoded channel, exactly rounded.
fn srgb_table() -> &'static [f32; 256] {
    static T: OnceLock<[f32; 256]> = OnceLock::new();
    T.get_or_init(|| std::array::from_fn(|i| srgb_to_linear(i as f64 / 255.0) as f32))
}

/// The decode tables the GPU filters with (render/gpu/pbr.wgsl): byte ->
/// linear for sRGB-encoded colour channels, then byte / 255 for data
/// channels and alpha, the values [`TextureRef::sample`] blends.
pub fn decode_tables() -> [f32; 512] {
    let s = srgb_table();
    std::array::from_fn(|i| {
        if i < 256 {
            s[i]
        } else {
            linear_byte((i - 256) as u8)
        }
    })
}

#[inline]
fn linear_byte(c: u8) -> f32 {
    c as f32 * (1.0 / 255.0)
}

/// The texel index of integer coordinate `i` in a side of `n` texels.
#[inline]
fn wrap_index(i: i64, n: u32, wrap: Wrap) -> u32 {
    let n = n as i64;
    (match wrap {
        Wrap::Repeat => i.rem_euclid(n),
        Wrap::ClampToEdge => i.clamp(0, n - 1),
        Wrap::MirroredRepeat => {
            let m = i.rem_euclid(2 * n);
            if m < n { m } else { 2 * n - 1 - m }
        }
    }) as u32
}

impl TextureRef {
    /// The texture coordinate after the transform.
    #[inline]
    pub fn transform_uv(&self, uv: [f32; 2]) -> [f32; 2] {
        let [a, b] = self.transform;
        [
            a[0] * uv[0] + a[1] * uv[1] + a[2],
            b[0] * uv[0] + b[1] * uv[1] + b[2],
        ]
    }

    /// One texel of `texels` (a level `width` wide), decoded to linear values.
    #[inline]
    fn texel(&self, texels: &[[u8; 4]], width: u32, x: u32, y: u32) -> [f32; 4] {
        let t = texels[(y as usize) * width as usize + x as usize];
        let lin = linear_byte;
        if self.srgb {
            let s = srgb_table();
            [
                s[t[0] as usize],
                s[t[1] as usize],
                s[t[2] as usize],
                lin(t[3]),
            ]
        } else {
            t.map(lin)
        }
    }

    /// The mean decoded texel (an emissive texture's: its light's power).
    pub fn mean(&self) -> [f64; 4] {
        let img = &*self.image;
        let (w, h) = (img.width, img.height);
        let mut sum = [0.0f64; 4];
        for y in 0..h {
            for x in 0..w {
                let t = self.texel(&img.texels, w, x, y);
                for k in 0..4 {
                    sum[k] += t[k] as f64;
                }
            }
        }
        let n = (w as f64 * h as f64).max(1.0);
        sum.map(|s| s / n)
    }

    /// The filtered value of the full-resolution image at texture
    /// coordinate `uv` (before the transform, which is applied here):
    /// bilinear between the four texels around it (texel centres at
    /// half-integers), or the nearest texel for a NEAREST sampler.
    /// Non-finite coordinates read texel (0, 0).
    pub fn sample(&self, uv: [f32; 2]) -> [f32; 4] {
        let img = &*self.image;
        self.filter(&img.texels, img.width, img.height, self.nearest, uv)
    }

    /// The trilinear filter at a hit ([`SurfaceAttrs`]): level of detail
    /// λ = the hit's `lod` for this texture's UV set + ½ log2(texels x the
    /// transform's area scale); λ ≤ 0 (or unknown) is [`Self::sample`],
    /// else the levels ⌊λ⌋ and ⌊λ⌋ + 1 of [`Image::levels`] (level 0 the
    /// image), each bilinear, blended by λ's fraction, λ clamped to the
    /// last level. pbr.wgsl `tex_sample` is its mirror.
    pub fn sample_at(&self, at: &SurfaceAttrs) -> [f32; 4] {
        let set = self.uv_set as usize;
        let uv = at.uv[set];
        let lod = at.lod[set] + self.lod_offset();
        if !(lod > 0.0) {
            return self.sample(uv);
        }
        let img = &*self.image;
        let levels = img.levels(self.srgb);
        let lod = lod.min(levels.len() as f32);
        let k = lod.floor();
        let frac = lod - k;
        let level = |k: usize| -> [f32; 4] {
            match k {
                0 => self.filter(&img.texels, img.width, img.height, false, uv),
                k => {
                    let l = &levels[k - 1];
                    self.filter(&l.texels, l.width, l.height, false, uv)
                }
            }
        };
        let k = k as usize;
        let a = level(k);
        if frac == 0.0 || k == levels.len() {
            return a;
        }
        let b = level(k + 1);
        std::array::from_fn(|i| a[i] + (b[i] - a[i]) * frac)
    }

    /// ½ log2 of the texels a unit of texture-coordinate area covers:
    /// the image's texels times the transform's area scale (-∞ where the
    /// transform collapses the plane).
    #[inline]
    pub fn lod_offset(&self) -> f32 {
        let [a, b] = self.transform;
        let det = (a[0] * b[1] - a[1] * b[0]).abs();
        0.5 * (det * self.image.width as f32 * self.image.height as f32).log2()
    }

    /// Bilinear (or nearest) filter over one level's `texels`.
    fn filter(&self, texels: &[[u8; 4]], w: u32, h: u32, nearest: bool, uv: [f32; 2]) -> [f32; 4] {
        let [u, v] = self.transform_uv(uv);
        let fx = if u.is_finite() { u * w as f32 } else { 0.5 };
        let fy = if v.is_finite() { v * h as f32 } else { 0.5 };
        // Clamped far beyond any image so the integer conversion is exact.
        let fx = fx.clamp(-1e9, 1e9);
        let fy = fy.clamp(-1e9, 1e9);
        if nearest {
            let x = wrap_index(fx.floor() as i64, w, self.wrap[0]);
            let y = wrap_index(fy.floor() as i64, h, self.wrap[1]);
            return self.texel(texels, w, x, y);
        }
        let (x, y) = (fx - 0.5, fy - 0.5);
        let (x0, y0) = (x.floor(), y.floor());
        let (tx, ty) = (x - x0, y - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let xs = [
            wrap_index(x0, w, self.wrap[0]),
            wrap_index(x0 + 1, w, self.wrap[0]),
        ];
        let ys = [
            wrap_index(y0, h, self.wrap[1]),
            wrap_index(y0 + 1, h, self.wrap[1]),
        ];
        let a = self.texel(texels, w, xs[0], ys[0]);
        let b = self.texel(texels, w, xs[1], ys[0]);
        let c = self.texel(texels, w, xs[0], ys[1]);
        let d = self.texel(texels, w, xs[1], ys[1]);
        std::array::from_fn(|i| {
            let top = a[i] + (b[i] - a[i]) * tx;
            let bottom = c[i] + (d[i] - c[i]) * tx;
            top + (bottom - top) * ty
        })
    }
}

/// What a textured surface point gives its textures: texture coordinates
/// (sets 0 and 1), the vertex colour, and per set the level of detail of
/// the pixel's footprint there, log2 of its side in texture coordinates
/// (world/query.rs `attrs_at`; -∞ where unknown: the full-resolution
/// image). pbr.wgsl `Attrs` is its mirror.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceAttrs {
    pub uv: [[f32; 2]; 2],
    pub colour: [f32; 4],
    pub lod: [f32; 2],
}

impl SurfaceAttrs {
    /// A point without attributes: zero coordinates, white, no footprint.
    pub const NONE: SurfaceAttrs = SurfaceAttrs {
        uv: [[0.0; 2]; 2],
        colour: [1.0; 4],
        lod: [f32::NEG_INFINITY; 2],
    };
}

/// The `KHR_texture_transform` matrix: translation * rotation * scale,
/// with the rotation as the Khronos sample viewer and three.js apply it,
/// rows [cos sin; -sin cos] (counter-clockwise in a texture space whose
/// v points down): what TextureTransformTest's markers check.
pub fn uv_transform(offset: [f32; 2], rotation: f32, scale: [f32; 2]) -> [[f32; 3]; 2] {
    let (s, c) = (rotation as f64).sin_cos();
    let (s, c) = (s as f32, c as f32);
    [
        [c * scale[0], s * scale[1], offset[0]],
        [-s * scale[0], c * scale[1], offset[1]],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tex(w: u32, h: u32, texels: Vec<[u8; 4]>, srgb: bool) -> TextureRef {
        TextureRef {
            image: Arc::new(Image::new("t", w, h, texels)),
            wrap: [Wrap::Repeat; 2],
            nearest: false,
            srgb,
            uv_set: 0,
            transform: IDENTITY_UV,
        }
    }

    #[test]
    fn srgb_decode_is_the_exact_curve() {
        let s = srgb_table();
        assert_eq!(s[0], 0.0);
        assert_eq!(s[255], 1.0);
        // 10/255 is below the 0.04045 knee: linear part.
        assert_eq!(s[10], (10.0 / 255.0 / 12.92) as f32);
        assert_eq!(
            s[128],
            ((128.0 / 255.0 + 0.055f64) / 1.055).powf(2.4) as f32
        );
        assert!((s[128] - 0.215_861).abs() < 1e-6, "{}", s[128]);
    }

    #[test]
    fn srgb_encoding_by_midpoints_is_the_rounded_curve() {
        let mids = srgb_midpoints();
        for i in 0..=100_000 {
            let c = i as f64 / 100_000.0;
            let want = (linear_to_srgb(c) * 255.0).round() as usize;
            let got = mids.partition_point(|&m| m <= c);
            // Within 1e-12 of a midpoint the two roundings may differ.
            let near = mids.iter().any(|&m| (m - c).abs() < 1e-12);
            assert!(got == want || near, "{c}: {got} against {want}");
        }
        // Every byte's own value encodes back to it.
        for (b, &v) in srgb_table().iter().enumerate() {
            assert_eq!(mids.partition_point(|&m| m <= v as f64), b);
        }
    }

    #[test]
    fn mip_levels_are_the_linear_mean_of_what_they_cover() {
        // 3 x 2 texels: level 1 is 1 x 1 over all six (an odd side's last
        // texel folded in), level 2 does not exist.
        let t = tex(
            3,
            2,
            vec![
                [0, 255, 10, 0],
                [255, 0, 20, 255],
                [255, 255, 30, 255],
                [0, 0, 40, 0],
                [255, 255, 50, 255],
                [0, 255, 60, 0],
            ],
            true,
        );
        let levels = t.image.levels(true);
        assert_eq!(levels.len(), 1);
        assert_eq!((levels[0].width, levels[0].height), (1, 1));
        let s = srgb_table();
        let mean = |k: usize, srgb: bool| -> f64 {
            t.image
                .texels
                .iter()
                .map(|x| {
                    if srgb {
                        s[x[k] as usize] as f64
                    } else {
                        x[k] as f64 / 255.0
                    }
                })
                .sum::<f64>()
                / 6.0
        };
        let got = levels[0].texels[0];
        for (k, &channel) in got.iter().take(3).enumerate() {
            assert_eq!(
                channel,
                (linear_to_srgb(mean(k, true)) * 255.0).round() as u8,
                "channel {k}"
            );
        }
        assert_eq!(got[3], (mean(3, false) * 255.0).round() as u8, "alpha");
        // As data, the bytes are averaged as they are.
        let data = t.image.levels(false)[0].texels[0];
        assert_eq!(data[2], (mean(2, false) * 255.0).round() as u8);
    }

    #[test]
    fn bilinear_at_centres_and_between_with_wraps() {
        // 2x1: black, white (linear data).
        let mut t = tex(2, 1, vec![[0, 0, 0, 255], [255, 255, 255, 255]], false);
        assert_eq!(t.sample([0.25, 0.5])[0], 0.0, "centre of texel 0");
        assert_eq!(t.sample([0.75, 0.5])[0], 1.0, "centre of texel 1");
        assert_eq!(t.sample([0.5, 0.5])[0], 0.5, "half way");
        // u = 0: between texel 1 (wrapped) and texel 0.
        assert_eq!(t.sample([0.0, 0.5])[0], 0.5, "repeat");
        t.wrap = [Wrap::ClampToEdge; 2];
        assert_eq!(t.sample([0.0, 0.5])[0], 0.0, "clamp");
        assert_eq!(t.sample([7.0, 0.5])[0], 1.0, "clamp far right");
        t.wrap = [Wrap::MirroredRepeat; 2];
        assert_eq!(t.sample([1.25, 0.5])[0], 1.0, "mirror: 1.25 reads 0.75");
        t.nearest = true;
        assert_eq!(t.sample([0.49, 0.5])[0], 0.0);
        assert_eq!(t.sample([0.51, 0.5])[0], 1.0);
    }

    #[test]
    fn srgb_textures_blend_in_linear() {
        let t = tex(2, 1, vec![[0, 0, 0, 0], [255, 128, 255, 255]], true);
        let s = t.sample([0.5, 0.5]);
        assert_eq!(s[0], 0.5);
        assert_eq!(s[1], srgb_table()[128] * 0.5);
        assert_eq!(s[3], 0.5, "alpha is linear");
    }

    #[test]
    fn texture_transform_matches_the_extension() {
        // Rotation by 90 degrees maps (1, 0) to (0, -1): counter-clockwise
        // as seen on the image (v down).
        let m = uv_transform([0.5, 0.0], std::f32::consts::FRAC_PI_2, [2.0, 1.0]);
        let mut t = tex(1, 1, vec![[0; 4]], false);
        t.transform = m;
        let [u, v] = t.transform_uv([1.0, 0.0]);
        assert!((u - 0.5).abs() < 1e-6 && (v + 2.0).abs() < 1e-6, "{u} {v}");
    }

    #[test]
    fn unsupported_formats_are_refused_by_name() {
        let e = Image::decode("a.ktx2", b"\xabKTX 20\xbb\r\n\x1a\n").unwrap_err();
        assert_eq!(e, "is a KTX2/Basis texture, which Tessera does not decode");
        let e = Image::decode("a.webp", b"RIFF\0\0\0\0WEBPVP8 ").unwrap_err();
        assert_eq!(e, "is a WebP texture, which Tessera does not decode");
        let e = Image::decode("a.png", b"not an image").unwrap_err();
        assert_eq!(e, "is not a PNG or JPEG image");
    }
}
