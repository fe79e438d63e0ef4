//! The `complexity` suite: time against scene complexity (object count).

use anyhow::Result;
use tracer_core::render::Precision;

use super::plot::{LinePlot, Series};
use super::{Bench, Run};

impl Bench {
    pub(super) fn suite_complexity(&self) -> Result<Vec<Run>> {
        let (width, height) = self.size((800, 600));
        let mut runs = vec![];
        for material in ["plastic", "chrome", "glass", "emerald"] {
            for n in [1, 3, 6, 9] {
                let name = format!("{material}-{n}");
                let (path, desc) = self.scene(&format!("complexity/{name}.toml"))?;
                let s = self.grid_settings(width, height, 4, 10);
                let reference = self.refs.get(&path, &desc, &s, self.reference_samples())?;
                for &b in &self.cfg.backends {
                    runs.push(self.measure(
                        "complexity",
                        &name,
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
            for material in ["plastic", "chrome", "glass", "emerald"] {
                let pts = runs
                    .iter()
                    .filter(|r| r.backend == b && r.scene.starts_with(material))
                    .map(|r| {
                        (
                            r.scene
                                .rsplit('-')
                                .next()
                                .and_then(|n| n.parse::<f64>().ok())
                                .unwrap_or(0.0),
                            r.rays.total() as f64 / 1e6,
                        )
                    })
                    .collect();
                series.push(Series {
                    name: format!("{} {material}", b.name()),
                    points: pts,
                });
            }
        }
        LinePlot {
            title: format!("Rays per frame against spheres ({width}x{height}, 4 spp, depth 10)"),
            x_label: "spheres".into(),
            y_label: "million rays per frame".into(),
            log_x: false,
            log_y: true,
            series,
        }
        .write(&self.cfg.out.join("complexity/rays_vs_spheres"))?;
        Ok(runs)
    }
}
