//! The `precision` suite: f32 against f64, time and error.

use anyhow::Result;
use tracer_core::render::{Backend, Precision};
use tracer_core::scene::RenderSettings;

use super::{Bench, Run};

impl Bench {
    pub(super) fn suite_precision(&self) -> Result<Vec<Run>> {
        let mut runs = vec![];
        for name in ["tiny-far", "huge-floor", "grazing-plane", "nested-glass"] {
            let (_, desc) = self.scene(&format!("hard/{name}.toml"))?;
            let (width, height) = if self.cfg.quick {
                (64, 48)
            } else {
                (desc.render.width, desc.render.height)
            };
            let s = RenderSettings {
                width,
                height,
                ..desc.render
            };
            // Error of each precision against the f64 CPU render of the same settings.
            let (f64_film, _, _) = self.render(Backend::Cpu, &desc, &s, Precision::F64)?;
            let reference = f64_film.resolve();
            for &b in &self.cfg.backends {
                let precisions: &[Precision] = if b == Backend::Cpu {
                    &[Precision::F32, Precision::F64]
                } else {
                    &[Precision::F32]
                };
                for &p in precisions {
                    runs.push(self.measure(
                        "precision",
                        name,
                        b,
                        &desc,
                        &s,
                        p,
                        Some(&reference),
                    )?);
                }
            }
        }
        Ok(runs)
    }
}
