//! Error of a render against a reference: RMSE, PSNR, relative MSE, mean FLIP.

/// Error figures of one image against its reference.
#[derive(Clone, Copy, Debug, Default)]
pub struct ErrorMetrics {
    /// Root mean squared error of linear RGB clamped to [0, 1] (what a display shows).
    pub rmse: f64,
    /// 20 log10(1 / rmse), in dB; infinite for identical images.
    pub psnr_db: f64,
    /// Mean of (x - r)^2 / (r^2 + 0.01): weighs dark regions where the absolute error says little.
    pub rel_mse: f64,
    /// Mean NVIDIA FLIP error of the 8-bit sRGB images (0 = identical, 1 = maximal).
    pub flip_mean: f64,
}

/// Pixels per degree of visual angle for FLIP: a 0.7 m viewing distance from a
/// 0.7 m wide 3840-pixel monitor (FLIP's own default).
const FLIP_PPD: f32 = 67.0;

/// Compares two linear RGB images of `width` x `height`.
pub fn compare(test: &[[f32; 3]], reference: &[[f32; 3]], width: u32, height: u32) -> ErrorMetrics {
    assert_eq!(test.len(), reference.len());
    let n = (test.len() * 3) as f64;
    let (mut se, mut rel) = (0.0f64, 0.0f64);
    for (a, b) in test.iter().zip(reference) {
        for c in 0..3 {
            let (x, r) = (a[c].clamp(0.0, 1.0) as f64, b[c].clamp(0.0, 1.0) as f64);
            se += (x - r) * (x - r);
            rel += (x - r) * (x - r) / (r * r + 0.01);
        }
    }
    let rmse = (se / n).sqrt();
    let flip_mean = {
        let r8 = tracer_core::film::to_srgb8(reference);
        let t8 = tracer_core::film::to_srgb8(test);
        let map = nv_flip::flip(
            nv_flip::FlipImageRgb8::with_data(width, height, &r8),
            nv_flip::FlipImageRgb8::with_data(width, height, &t8),
            FLIP_PPD,
        );
        nv_flip::FlipPool::from_image(&map).mean() as f64
    };
    ErrorMetrics {
        rmse,
        psnr_db: 20.0 * (1.0 / rmse).log10(),
        rel_mse: rel / n,
        flip_mean,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_images_have_zero_error() {
        let img = vec![[0.2, 0.5, 0.9]; 64];
        let m = compare(&img, &img, 8, 8);
        assert_eq!(m.rmse, 0.0);
        assert!(m.psnr_db.is_infinite());
        assert_eq!(m.flip_mean, 0.0);
    }

    #[test]
    fn known_offset_gives_known_rmse_and_psnr() {
        let a = vec![[0.5f32; 3]; 64];
        let b = vec![[0.6f32; 3]; 64];
        let m = compare(&a, &b, 8, 8);
        assert!((m.rmse - 0.1).abs() < 1e-6, "{}", m.rmse);
        assert!((m.psnr_db - 20.0).abs() < 1e-4, "{}", m.psnr_db);
        assert!(m.flip_mean > 0.0 && m.flip_mean < 1.0);
        // Values above 1 are clamped as a display would: no error between 2 and 3.
        assert_eq!(compare(&[[2.0; 3]], &[[3.0; 3]], 1, 1).rmse, 0.0);
    }
}
