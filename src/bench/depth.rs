//! The `depth` suite: time and error against max_depth, against an f64
//! reference at [`super::DEPTH_REFERENCE`].

use anyhow::Result;
use tracer_core::render::{Backend, Precision};
use tracer_core::scene::RenderSettings;

use super::plot::{LinePlot, Series};
use super::{Bench, Run};

impl Bench {
    pub(super) fn suite_depth(&self) -> Result<Vec<Run>> {
        let (path, desc) = self.scene("depth.toml")?;
        let (width, height) = self.size((800, 600));
        let depths: &[u32] = if self.cfg.quick {
            &[0, 1, 4]
        } else {
            &[0, 1, 2, 4, 8, 12, 16]
        };
        // Reference: the f64 render with the same samples (4, grid) at depth
        // `--depth-reference`, so sampling error cancels and what remains is
        // what the missing generations cost. The CPU also runs f64 at each
        // depth: its curve is truncation alone, while the f32 curves level
        // off at the f32 rounding error (docs/benchmarks.md has the figures).
        let base = self.grid_settings(width, height, 4, self.cfg.depth_reference);
        let reference = self.refs.get_exact(&path, &desc, &base)?;
        let mut runs = vec![];
        for &d in depths {
            let s = RenderSettings {
                max_depth: d,
                ..base
            };
            for &b in &self.cfg.backends {
                let precisions: &[Precision] = if b == Backend::Cpu {
                    &[Precision::F32, Precision::F64]
                } else {
                    &[Precision::F32]
                };
                for &p in precisions {
                    runs.push(self.measure("depth", "depth", b, &desc, &s, p, Some(&reference))?);
                }
            }
        }
        let by_backend_and_precision = |f: fn(&Run) -> (f64, f64)| {
            let mut series = vec![];
            for &b in &self.cfg.backends {
                for p in [Precision::F32, Precision::F64] {
                    let points: Vec<(f64, f64)> = runs
                        .iter()
                        .filter(|r| r.backend == b && r.precision == p)
                        .map(f)
                        .collect();
                    if !points.is_empty() {
                        series.push(Series {
                            name: format!("{} {}", b.name(), p.name()),
                            points,
                        });
                    }
                }
            }
            series
        };
        LinePlot {
            title: "Time against max_depth (5 emerald spheres)".into(),
            x_label: "max_depth".into(),
            y_label: "time per frame (s)".into(),
            log_x: false,
            log_y: false,
            series: by_backend_and_precision(|r| (r.settings.max_depth as f64, r.seconds)),
        }
        .write(&self.cfg.out.join("depth/time_vs_depth"))?;
        LinePlot {
            title: format!(
                "Error against max_depth (reference: f64, depth {}, same 4 grid samples)",
                self.cfg.depth_reference
            ),
            x_label: "max_depth".into(),
            y_label: "RMSE".into(),
            log_x: false,
            log_y: true,
            series: by_backend_and_precision(|r| {
                (
                    r.settings.max_depth as f64,
                    r.error.map_or(f64::NAN, |e| e.rmse),
                )
            }),
        }
        .write(&self.cfg.out.join("depth/error_vs_depth"))?;
        Ok(runs)
    }
}
