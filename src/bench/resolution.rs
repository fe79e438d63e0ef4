//! The `resolution` suite: time and error against image size (the thesis's
//! resolution scene).

use anyhow::Result;
use tracer_core::render::Precision;

use super::plot::LinePlot;
use super::{Bench, Run};

impl Bench {
    pub(super) fn suite_resolution(&self) -> Result<Vec<Run>> {
        let (path, desc) = self.scene("resolution.toml")?;
        let sizes: &[(u32, u32)] = if self.cfg.quick {
            &[(64, 48), (128, 96)]
        } else {
            &[
                (640, 480),
                (800, 600),
                (1024, 768),
                (1280, 720),
                (1920, 1080),
            ]
        };
        let mut runs = vec![];
        for &(width, height) in sizes {
            let s = self.grid_settings(width, height, 4, 10);
            let reference = self.refs.get(&path, &desc, &s, self.reference_samples())?;
            for &b in &self.cfg.backends {
                runs.push(self.measure(
                    "resolution",
                    "resolution",
                    b,
                    &desc,
                    &s,
                    Precision::F32,
                    Some(&reference),
                )?);
            }
        }
        let series = self.series_by_backend(&runs, |r| {
            (
                r.settings.width as f64 * r.settings.height as f64 / 1e6,
                r.seconds,
            )
        });
        LinePlot {
            title: "Render time against resolution (resolution scene, 4 spp, depth 10)".into(),
            x_label: "megapixels".into(),
            y_label: "time per frame (s)".into(),
            log_x: false,
            log_y: false,
            series,
        }
        .write(&self.cfg.out.join("resolution/time_vs_pixels"))?;
        Ok(runs)
    }
}
