//! The `samples` suite: time and error against samples per pixel.

use anyhow::Result;
use tracer_core::render::Precision;
use tracer_core::sampling::Sampler;
use tracer_core::scene::RenderSettings;

use super::plot::{LinePlot, Series};
use super::{Bench, Run};

impl Bench {
    pub(super) fn suite_samples(&self) -> Result<Vec<Run>> {
        let (path, desc) = self.scene("resolution.toml")?;
        let (width, height) = self.size((800, 600));
        let counts: &[u32] = if self.cfg.quick {
            &[1, 4, 9]
        } else {
            &[1, 4, 9, 16, 25, 36]
        };
        let base = self.grid_settings(width, height, 1, 10);
        // The samples suite is the headline error curve: a finer reference than the others.
        let reference =
            self.refs
                .get(&path, &desc, &base, if self.cfg.quick { 36 } else { 256 })?;
        let mut runs = vec![];
        for sampler in [Sampler::Grid, Sampler::Jittered] {
            for &samples in counts {
                let s = RenderSettings {
                    samples,
                    sampler,
                    ..base
                };
                for &b in &self.cfg.backends {
                    runs.push(self.measure(
                        "samples",
                        "resolution",
                        b,
                        &desc,
                        &s,
                        Precision::F32,
                        Some(&reference),
                    )?);
                }
            }
        }
        let mut series = vec![];
        for &b in &self.cfg.backends {
            for sampler in [Sampler::Grid, Sampler::Jittered] {
                let pts = runs
                    .iter()
                    .filter(|r| r.backend == b && r.settings.sampler == sampler)
                    .map(|r| (r.seconds, r.error.map_or(f64::NAN, |e| e.rmse)))
                    .collect();
                series.push(Series {
                    name: format!(
                        "{} {} (1..{} spp)",
                        b.name(),
                        sampler.name(),
                        counts.last().unwrap()
                    ),
                    points: pts,
                });
            }
        }
        LinePlot {
            title: format!("Error against time: resolution scene {width}x{height}, depth 10"),
            x_label: "time per frame (s)".into(),
            y_label: "RMSE against f64 reference".into(),
            log_x: true,
            log_y: true,
            series,
        }
        .write(&self.cfg.out.join("samples/error_vs_time"))?;
        Ok(runs)
    }
}
