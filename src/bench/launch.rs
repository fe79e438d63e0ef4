//! The `launch` suite: the GPU launch-shape sweep.

use anyhow::Result;

use super::{Bench, Run};
// The sweep is GPU-only.
#[cfg(feature = "gpu")]
use {
    super::plot::{LinePlot, Series},
    anyhow::bail,
    tracer_core::film::Rect,
    tracer_core::render::{Backend, Precision, PreparedFrame},
};

impl Bench {
    /// `launch`: the GPU launch-shape sweep (see `launch.rs`) on the
    /// resolution scene and a deep glass scene. `None` (skipped, with a
    /// message) without a GPU backend.
    pub(super) fn suite_launch(&self) -> Result<Option<Vec<Run>>> {
        #[cfg(feature = "gpu")]
        if let Some(gpu) = self
            .gpu
            .as_ref()
            .filter(|_| self.cfg.backends.contains(&Backend::Gpu))
        {
            return self.launch_sweep(gpu).map(Some);
        }
        eprintln!(
            "bench: suite launch skipped: it sweeps GPU launch shapes and needs a GPU backend (--backend gpu or both)"
        );
        Ok(None)
    }

    #[cfg(feature = "gpu")]
    fn launch_sweep(&self, gpu: &tracer_core::render::GpuRenderer) -> Result<Vec<Run>> {
        use tracer_core::render::gpu::{Strategy, launch};
        let adapter = gpu.adapter().index.to_string();
        let (width, height) = self.size((1920, 1080));
        let reps = if self.cfg.quick {
            1
        } else {
            self.cfg.repeat.max(3) as usize
        };
        let shapes = launch::sweep_shapes(self.cfg.quick);
        let mut runs = vec![];
        for (name, file) in [
            ("resolution", "resolution.toml"),
            ("glass-9", "complexity/glass-9.toml"),
        ] {
            let (_, desc) = self.scene(file)?;
            let s = self.grid_settings(width, height, 4, 10);
            let frame = PreparedFrame::build(&desc, &s, 0, Precision::F32)?;
            let rect = Rect::full(width, height);
            // Every shape must give the default options' image.
            let baseline = launch::run_interleaved(&[gpu], &frame, rect, s.samples, 1)?
                .pop()
                .expect("one timing")
                .film;
            let r = launch::readout_timing(gpu, &frame, rect, s.samples, reps.max(5))?;
            let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
            let differ = if r.identical { "" } else { "  IMAGES DIFFER" };
            eprintln!(
                "  launch     {name:<14} {width}x{height} {} spp whole call: sums read back {:>8.3} ms; 8-bit (PNG): sums resolved on the host {:>8.3} ms, resolved on the GPU {:>8.3} ms ({:.1}x){differ}",
                s.samples,
                ms(r.sums),
                ms(r.sums_then_host),
                ms(r.resolved_on_gpu),
                ms(r.sums_then_host) / ms(r.resolved_on_gpu),
            );
            eprintln!(
                "  launch     {name:<14} {width}x{height} {} spp whole call: f32 (EXR): sums resolved on the host {:>8.3} ms, resolved on the GPU {:>8.3} ms ({:.1}x){differ}",
                s.samples,
                ms(r.sums_then_host_linear),
                ms(r.linear_on_gpu),
                ms(r.sums_then_host_linear) / ms(r.linear_on_gpu),
            );
            if !r.identical {
                bail!("{name}: the GPU's resolve differs from the host's");
            }
            let points = launch::sweep(
                &adapter,
                &frame,
                rect,
                s.samples,
                reps,
                &shapes,
                &baseline,
                |p| {
                    let sh = &p.shape;
                    match &p.result {
                        Ok(t) => eprintln!(
                            "  launch     {name:<14} {:<9} wg {:>3}x{:<2} dispatch {:>8}  GPU {:>8.3} ms  trace {:>8.3} ms  call {:>8.3} ms  max diff {:.1e}",
                            sh.strategy_name(),
                            sh.workgroup.0,
                            sh.workgroup.1,
                            sh.dispatch_pixel_samples,
                            t.gpu.as_secs_f64() * 1e3,
                            t.trace.as_secs_f64() * 1e3,
                            t.total.as_secs_f64() * 1e3,
                            t.max_abs_diff
                        ),
                        Err(e) => eprintln!(
                            "  launch     {name:<14} {:<9} wg {:>3}x{:<2} dispatch {:>8}  not run: {e}",
                            sh.strategy_name(),
                            sh.workgroup.0,
                            sh.workgroup.1,
                            sh.dispatch_pixel_samples
                        ),
                    }
                },
            );
            for p in &points {
                let Ok(t) = &p.result else { continue };
                let sh = &p.shape;
                runs.push(Run {
                    suite: "launch",
                    scene: name.to_string(),
                    backend: Backend::Gpu,
                    device: gpu.adapter().name.clone(),
                    threads: 0,
                    settings: s,
                    precision: Precision::F32,
                    seconds: t.total.as_secs_f64(),
                    gpu_seconds: Some(t.gpu.as_secs_f64()),
                    rays: t.rays,
                    // Speed only: the image is checked against the default shape's instead.
                    error: None,
                    image: String::new(),
                    extra: vec![
                        ("strategy", sh.strategy_name().to_string()),
                        ("workgroup_x", sh.workgroup.0.to_string()),
                        ("workgroup_y", sh.workgroup.1.to_string()),
                        (
                            "dispatch_pixel_samples",
                            sh.dispatch_pixel_samples.to_string(),
                        ),
                        ("dispatches", t.dispatches.to_string()),
                        ("trace_wall_s", format!("{:.6}", t.trace.as_secs_f64())),
                        ("readback_s", format!("{:.6}", t.readback.as_secs_f64())),
                        ("first_render_s", format!("{:.6}", t.first.as_secs_f64())),
                        ("max_abs_diff_vs_default", format!("{:.3e}", t.max_abs_diff)),
                    ],
                });
            }
            let mut series = vec![];
            for strategy in [Strategy::Stack, Strategy::Wavefront] {
                let mut wgs: Vec<(u32, u32)> = vec![];
                for p in points.iter().filter(|p| p.shape.strategy == strategy) {
                    if !wgs.contains(&p.shape.workgroup) {
                        wgs.push(p.shape.workgroup);
                    }
                }
                for wg in wgs {
                    let pts = points
                        .iter()
                        .filter(|p| p.shape.strategy == strategy && p.shape.workgroup == wg)
                        .filter_map(|p| {
                            p.result.as_ref().ok().map(|t| {
                                (
                                    p.shape.dispatch_pixel_samples as f64,
                                    t.gpu.as_secs_f64() * 1e3,
                                )
                            })
                        })
                        .collect();
                    series.push(Series {
                        name: format!("{} {}x{}", launch::strategy_name(strategy), wg.0, wg.1),
                        points: pts,
                    });
                }
            }
            LinePlot {
                title: format!(
                    "GPU time against dispatch size: {name} {width}x{height}, 4 spp, depth 10"
                ),
                x_label: "pixel-samples per dispatch".into(),
                y_label: if gpu.has_timestamps() {
                    "GPU time per frame (ms, timestamps)"
                } else {
                    "trace time per frame (ms, host)"
                }
                .into(),
                log_x: true,
                log_y: true,
                series,
            }
            .write(&self.cfg.out.join(format!("launch/{name}_gpu_time")))?;
        }
        Ok(runs)
    }
}
