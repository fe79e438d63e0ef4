//! Textures of model files: decoded images (PNG, JPEG), their samplers and
//! the one filter the shading step samples them with (docs/meshes.md,
//! "Materials and textures").
//!
//! Texture space is glTF's: (0, 0) is the top-left corner of the image,
//! u to the right, v down (OBJ's v is flipped when it is read). The
//! filter is bilinear over the full-resolution image, with the sampler's
//! wrap modes, in linear values: colour textures are decoded from sRGB
//! exactly (the IEC 61966-2-1 curve, in f64, rounded once to f32) before
//! they are blended, data textures (metallic-roughness, normal,
//! occlusion, alpha) are byte / 255.

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
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// The file it came from (for messages).
    pub name: String,
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
        Ok(Image {
            name: name.to_string(),
            width,
            height,
            texels,
        })
    }
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

    /// One texel, decoded to linear values.
    #[inline]
    fn texel(&self, x: u32, y: u32) -> [f32; 4] {
        let img = &*self.image;
        let t = img.texels[(y as usize) * img.width as usize + x as usize];
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
        let (w, h) = (self.image.width, self.image.height);
        let mut sum = [0.0f64; 4];
        for y in 0..h {
            for x in 0..w {
                let t = self.texel(x, y);
                for k in 0..4 {
                    sum[k] += t[k] as f64;
                }
            }
        }
        let n = (w as f64 * h as f64).max(1.0);
        sum.map(|s| s / n)
    }

    /// The filtered value at texture coordinate `uv` (before the
    /// transform, which is applied here): bilinear between the four
    /// texels around it (texel centres at half-integers), or the nearest
    /// texel for a NEAREST sampler. Non-finite coordinates read texel (0, 0).
    pub fn sample(&self, uv: [f32; 2]) -> [f32; 4] {
        let [u, v] = self.transform_uv(uv);
        let (w, h) = (self.image.width, self.image.height);
        let fx = if u.is_finite() { u * w as f32 } else { 0.5 };
        let fy = if v.is_finite() { v * h as f32 } else { 0.5 };
        // Clamped far beyond any image so the integer conversion is exact.
        let fx = fx.clamp(-1e9, 1e9);
        let fy = fy.clamp(-1e9, 1e9);
        if self.nearest {
            let x = wrap_index(fx.floor() as i64, w, self.wrap[0]);
            let y = wrap_index(fy.floor() as i64, h, self.wrap[1]);
            return self.texel(x, y);
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
        let a = self.texel(xs[0], ys[0]);
        let b = self.texel(xs[1], ys[0]);
        let c = self.texel(xs[0], ys[1]);
        let d = self.texel(xs[1], ys[1]);
        std::array::from_fn(|i| {
            let top = a[i] + (b[i] - a[i]) * tx;
            let bottom = c[i] + (d[i] - c[i]) * tx;
            top + (bottom - top) * ty
        })
    }
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
            image: Arc::new(Image {
                name: "t".into(),
                width: w,
                height: h,
                texels,
            }),
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
