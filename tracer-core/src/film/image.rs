//! Films and 8-bit images as files: the one PNG and EXR writer of the
//! workspace, for `tessera render`, the coordinator (finished frames and
//! the monitor's previews) and the benchmarks.
//!
//! Behind the `image-io` feature, so that processes that never write an
//! image (workers, the wire) do not build the codecs.

use std::path::{Path, PathBuf};

use super::Film;

/// Image formats chosen by the output's extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    Png,
    Exr,
}

#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("{}: unsupported output extension {ext}; use .png (8-bit sRGB) or .exr (linear float)", path.display())]
    Extension { path: PathBuf, ext: String },
    /// The cause is in the message, not a `source()`, so a chain prints it once.
    #[error("cannot write {}: {error}", path.display())]
    Write {
        path: PathBuf,
        error: ::image::ImageError,
    },
    #[error("cannot write {}: {error}", path.display())]
    WriteExr {
        path: PathBuf,
        error: ::exr::error::Error,
    },
    /// Encoding to memory ([`encode_png`]): the encoder's own message.
    #[error("{0}")]
    Encode(::image::ImageError),
    #[error("{}: {error}", path.display())]
    Read {
        path: PathBuf,
        error: ::image::ImageError,
    },
}

impl ImageFormat {
    pub fn of(path: &Path) -> Result<Self, ImageError> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase())
            .as_deref()
        {
            Some("png") => Ok(ImageFormat::Png),
            Some("exr") => Ok(ImageFormat::Exr),
            other => Err(ImageError::Extension {
                path: path.to_owned(),
                ext: other.map_or("(none)".to_string(), |e| format!(".{e}")),
            }),
        }
    }
}

/// Writes a resolved film as PNG (8-bit sRGB) or EXR (linear float), by
/// extension. The EXR of an adaptive film ([`Film::squares`]) has two more
/// channels: `samples` (per pixel) and `error` (the estimated standard
/// error of the pixel's mean, the largest of its three channels').
pub fn write_image(path: &Path, film: &Film) -> Result<(), ImageError> {
    let (w, h) = (film.rect.width, film.rect.height);
    match ImageFormat::of(path)? {
        ImageFormat::Exr if film.squares.is_some() => write_adaptive_exr(path, film),
        ImageFormat::Exr => write_exr(path, w, h, &film.resolve()),
        ImageFormat::Png => write_png(path, w, h, &film.srgb8()),
    }
}

/// Which PNG row filter the encoder uses: the one choice that differs
/// between a file and a preview (both deflate fast).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PngFilter {
    /// The best of five filters, chosen row by row: files that are kept.
    Adaptive,
    /// `Sub` on every row: several times less work than adaptive, for a
    /// preview that lives a second.
    Sub,
}

/// The one PNG encoder: 8-bit sRGB RGB bytes (row-major, `width` x
/// `height`), fast deflate. Fast because a farm's last frame is written
/// while every worker waits for the job to end (1920x1080: ~25 ms instead
/// of ~100 ms with the default level, files ~30% larger).
fn encode(
    out: impl std::io::Write,
    width: u32,
    height: u32,
    rgb: &[u8],
    filter: PngFilter,
) -> Result<(), ::image::ImageError> {
    use ::image::ImageEncoder as _;
    use ::image::codecs::png::{CompressionType, FilterType, PngEncoder};
    let filter = match filter {
        PngFilter::Adaptive => FilterType::Adaptive,
        PngFilter::Sub => FilterType::Sub,
    };
    PngEncoder::new_with_quality(out, CompressionType::Fast, filter).write_image(
        rgb,
        width,
        height,
        ::image::ExtendedColorType::Rgb8,
    )
}

/// Writes 8-bit sRGB RGB bytes (row-major, `width` x `height`) as a PNG
/// file, rows filtered adaptively.
pub fn write_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<(), ImageError> {
    std::fs::File::create(path)
        .map_err(::image::ImageError::IoError)
        .and_then(|f| {
            let mut out = std::io::BufWriter::new(f);
            encode(&mut out, width, height, rgb, PngFilter::Adaptive)?;
            std::io::Write::flush(&mut out).map_err(::image::ImageError::IoError)
        })
        .map_err(|error| ImageError::Write {
            path: path.to_owned(),
            error,
        })
}

/// 8-bit sRGB RGB bytes as a PNG in memory (a response body).
pub fn encode_png(
    width: u32,
    height: u32,
    rgb: &[u8],
    filter: PngFilter,
) -> Result<Vec<u8>, ImageError> {
    let mut out = Vec::new();
    encode(&mut out, width, height, rgb, filter).map_err(ImageError::Encode)?;
    Ok(out)
}

/// Writes linear RGB (row-major, `width` x `height`) as an f32 EXR.
pub fn write_exr(
    path: &Path,
    width: u32,
    height: u32,
    linear: &[[f32; 3]],
) -> Result<(), ImageError> {
    let data: Vec<f32> = linear.iter().flatten().copied().collect();
    ::image::Rgb32FImage::from_raw(width, height, data)
        .expect("buffer matches size")
        .save_with_format(path, ::image::ImageFormat::OpenExr)
        .map_err(|error| ImageError::Write {
            path: path.to_owned(),
            error,
        })
}

/// An adaptive film as EXR: R, G, B, `samples` and `error`, all f32.
fn write_adaptive_exr(path: &Path, film: &Film) -> Result<(), ImageError> {
    use ::exr::prelude::*;
    let linear = film.resolve();
    let w = film.rect.width as usize;
    let error: Vec<f32> = (0..film.sums.len())
        .map(|i| film.pixel_error(i) as f32)
        .collect();
    let channels = SpecificChannels::build()
        .with_channel("R")
        .with_channel("G")
        .with_channel("B")
        .with_channel("samples")
        .with_channel("error")
        .with_pixel_fn(|p: Vec2<usize>| {
            let i = p.y() * w + p.x();
            let [r, g, b] = linear[i];
            (r, g, b, film.counts[i] as f32, error[i])
        });
    Image::from_channels((w, film.rect.height as usize), channels)
        .write()
        .to_file(path)
        .map_err(|error| ImageError::WriteExr {
            path: path.to_owned(),
            error,
        })
}

/// A heat map of samples per pixel as PNG: log2 of the count from `min`
/// (dark blue) to `max` (yellow) through magenta and orange; black where a
/// pixel has no samples.
pub fn write_sample_map(path: &Path, film: &Film, min: u32, max: u32) -> Result<(), ImageError> {
    let (lo, hi) = ((min.max(1) as f32).log2(), (max.max(1) as f32).log2());
    let bytes: Vec<u8> = film
        .counts
        .iter()
        .flat_map(|&n| {
            if n == 0 {
                return [0, 0, 0];
            }
            let t = if hi > lo {
                (((n as f32).log2() - lo) / (hi - lo)).clamp(0.0, 1.0)
            } else {
                1.0
            };
            heat(t)
        })
        .collect();
    write_png(path, film.rect.width, film.rect.height, &bytes)
}

/// A perceptually ordered ramp (after matplotlib's plasma): t in [0, 1].
fn heat(t: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 5] = [
        [13.0, 8.0, 135.0],
        [126.0, 3.0, 168.0],
        [204.0, 71.0, 120.0],
        [248.0, 149.0, 64.0],
        [240.0, 249.0, 33.0],
    ];
    let x = t * (STOPS.len() - 1) as f32;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f32;
    std::array::from_fn(|c| (STOPS[i][c] + (STOPS[i + 1][c] - STOPS[i][c]) * f + 0.5) as u8)
}

/// An image file (PNG or EXR, by extension) as 8-bit RGB: `(width, height,
/// bytes)`, row-major. The coordinator reads its written frames back with
/// it for the monitor.
pub fn read_rgb8(path: &Path) -> Result<(u32, u32, Vec<u8>), ImageError> {
    let img = ::image::open(path)
        .map_err(|error| ImageError::Read {
            path: path.to_owned(),
            error,
        })?
        .to_rgb8();
    let (w, h) = img.dimensions();
    Ok((w, h, img.into_raw()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_heat_ramp_runs_from_blue_to_yellow() {
        assert_eq!(heat(0.0), [13, 8, 135]);
        assert_eq!(heat(1.0), [240, 249, 33]);
        assert_eq!(heat(0.5), [204, 71, 120]);
    }
}
