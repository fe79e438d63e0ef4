//! Writing resolved films as image files (shared by `tessera render` and the
//! coordinator, which writes each finished frame).

use std::path::{Path, PathBuf};

use tracer_core::film::Film;

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
        error: image::ImageError,
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

/// Writes a resolved film as PNG (8-bit sRGB) or EXR (linear float), by extension.
pub fn write_image(path: &Path, film: &Film) -> Result<(), ImageError> {
    let (w, h) = (film.rect.width, film.rect.height);
    match ImageFormat::of(path)? {
        ImageFormat::Png => {
            use image::ImageEncoder as _;
            use image::codecs::png::{CompressionType, FilterType, PngEncoder};
            let bytes = film.srgb8();
            // Fast deflate: a farm's last frame is written while every
            // worker waits for the job to end (1920x1080: ~25 ms instead
            // of ~100 ms with the default level, files ~30% larger).
            std::fs::File::create(path)
                .map_err(image::ImageError::IoError)
                .and_then(|f| {
                    let mut out = std::io::BufWriter::new(f);
                    PngEncoder::new_with_quality(
                        &mut out,
                        CompressionType::Fast,
                        FilterType::Adaptive,
                    )
                    .write_image(
                        &bytes,
                        w,
                        h,
                        image::ExtendedColorType::Rgb8,
                    )?;
                    std::io::Write::flush(&mut out).map_err(image::ImageError::IoError)
                })
        }
        ImageFormat::Exr => {
            let linear = film.resolve();
            let data: Vec<f32> = linear.iter().flatten().copied().collect();
            image::Rgb32FImage::from_raw(w, h, data)
                .expect("buffer matches size")
                .save_with_format(path, image::ImageFormat::OpenExr)
        }
    }
    .map_err(|error| ImageError::Write {
        path: path.to_owned(),
        error,
    })
}
