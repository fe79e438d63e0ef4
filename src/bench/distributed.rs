//! The `distributed` suite: distributed ray tracing (issue 16).

use anyhow::Result;
use tracer_core::render::Precision;
use tracer_core::sampling::Sampler;
use tracer_core::scene::RenderSettings;

use super::plot::{LinePlot, Series};
use super::{Bench, Run};

impl Bench {
    /// Distributed ray tracing (issue 16): the distributed-effects scene and
    /// the resolution scene under a quad light, time and error (against a
    /// converged f64 CPU reference) against samples per pixel, CPU and GPU.
    pub(super) fn suite_distributed(&self) -> Result<Vec<Run>> {
        let (width, height) = self.size((400, 300));
        let counts: &[u32] = if self.cfg.quick {
            &[1, 4]
        } else {
            &[1, 4, 16, 64]
        };
        let ref_samples = if self.cfg.quick { 64 } else { 256 };
        let mut runs = vec![];
        for (name, file) in [
            ("distributed", "distributed.toml"),
            ("resolution-quad", "resolution-quad.toml"),
        ] {
            let (path, desc) = self.scene(file)?;
            let base = RenderSettings {
                width,
                height,
                samples: 1,
                sampler: Sampler::Jittered,
                ..desc.render
            };
            let reference = self.refs.get(&path, &desc, &base, ref_samples)?;
            for &samples in counts {
                let s = RenderSettings { samples, ..base };
                for &b in &self.cfg.backends {
                    runs.push(self.measure(
                        "distributed",
                        name,
                        b,
                        &desc,
                        &s,
                        Precision::F32,
                        Some(&reference),
                    )?);
                }
            }
        }
        let series = |f: fn(&Run) -> (f64, f64)| -> Vec<Series> {
            let mut out = vec![];
            for name in ["distributed", "resolution-quad"] {
                for &b in &self.cfg.backends {
                    let points: Vec<(f64, f64)> = runs
                        .iter()
                        .filter(|r| r.scene == name && r.backend == b)
                        .map(f)
                        .collect();
                    if !points.is_empty() {
                        out.push(Series {
                            name: format!("{name} {}", b.name()),
                            points,
                        });
                    }
                }
            }
            out
        };
        let dir = self.cfg.out.join("distributed");
        LinePlot {
            title: format!(
                "Error against samples per pixel ({width}x{height}, f64 reference at {ref_samples} spp)"
            ),
            x_label: "samples per pixel".into(),
            y_label: "RMSE against f64 reference".into(),
            log_x: true,
            log_y: true,
            series: series(|r| (r.settings.samples as f64, r.error.map_or(f64::NAN, |e| e.rmse))),
        }
        .write(&dir.join("error_vs_samples"))?;
        LinePlot {
            title: format!("Time against samples per pixel ({width}x{height})"),
            x_label: "samples per pixel".into(),
            y_label: "time per frame (s)".into(),
            log_x: true,
            log_y: true,
            series: series(|r| (r.settings.samples as f64, r.seconds)),
        }
        .write(&dir.join("time_vs_samples"))?;
        LinePlot {
            title: format!("Error against time, distributed effects ({width}x{height})"),
            x_label: "time per frame (s)".into(),
            y_label: "RMSE against f64 reference".into(),
            log_x: true,
            log_y: true,
            series: series(|r| (r.seconds, r.error.map_or(f64::NAN, |e| e.rmse))),
        }
        .write(&dir.join("error_vs_time"))?;
        Ok(runs)
    }
}
