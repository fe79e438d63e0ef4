//! The adaptive suite (issue 17): RMSE against a converged f64 reference,
//! against time, for uniform sampling and adaptive sampling, on the
//! thesis's resolution scene and the distributed-effects scene.
//!
//! Both modes place samples with the progressive sampler, so they trace
//! the same samples where they trace the same counts; the reference uses
//! the same sequence from sample 2^15 on, so its samples are independent
//! of every tested sample (a reference sharing them would understate the
//! error of the render it shares the most with). Headline: the time
//! adaptive sampling takes to reach the RMSE of the uniform render at the
//! top count (1024 spp, 64 with --quick), against that uniform render's
//! time; the adaptive time is read off its error-time curve (log-log
//! interpolation between the two runs that bracket the RMSE).

use std::time::Instant;

use anyhow::Result;
use tracer_core::adaptive::AdaptiveSettings;
use tracer_core::film::image::{write_exr, write_png, write_sample_map};
use tracer_core::film::{Film, Rect, SampleRange};
use tracer_core::render::adaptive;
use tracer_core::render::{Backend, Precision, PreparedFrame, Renderer};
use tracer_core::scene::{MAX_SAMPLES, RenderSettings, SceneDesc};

use super::plot::{LinePlot, Series};
use super::{Bench, Run, compare};

/// First sample index of the reference (see the module doc).
const REFERENCE_OFFSET: u32 = 1 << 15;

/// One scene's headline.
#[derive(Clone, Debug)]
pub struct Headline {
    pub scene: String,
    pub backend: Backend,
    pub uniform_spp: u32,
    pub uniform_rmse: f64,
    pub uniform_seconds: f64,
    /// `None`: no adaptive run reached the uniform RMSE.
    pub adaptive_seconds: Option<f64>,
}

impl Headline {
    pub fn speedup(&self) -> Option<f64> {
        self.adaptive_seconds.map(|a| self.uniform_seconds / a)
    }
}

impl Bench {
    pub(super) fn suite_adaptive(&self) -> Result<Vec<Run>> {
        let (width, height) = if self.cfg.quick {
            (64, 48)
        } else {
            self.cfg.adaptive_size
        };
        let top = if self.cfg.quick { 64 } else { 1024 };
        let uniform_counts: Vec<u32> = [4, 16, 64, 256, 1024]
            .into_iter()
            .filter(|&n| n <= top)
            .collect();
        let min = 16.min(top / 4);
        let targets: &[f64] = if self.cfg.quick {
            &[0.04, 0.01]
        } else {
            &[0.04, 0.02, 0.01, 0.005, 0.0025, 0.00125, 0.000625]
        };
        let ref_samples = if self.cfg.quick {
            256
        } else {
            self.cfg.adaptive_reference
        };
        let mut runs = vec![];
        let mut headlines = vec![];
        for (name, file) in [
            ("resolution", "resolution.toml"),
            ("distributed", "distributed.toml"),
        ] {
            if !self.cfg.adaptive_scenes.iter().any(|s| s == name) {
                continue;
            }
            let (_, desc) = self.scene(file)?;
            let base = RenderSettings {
                width,
                height,
                samples: MAX_SAMPLES,
                sampler: tracer_core::sampling::Sampler::Progressive,
                ..desc.render
            };
            let reference = self.offset_reference(name, &desc, &base, ref_samples)?;
            for &b in &self.cfg.backends {
                let renderer = self.renderer(b)?;
                let mut uniform_top = None;
                for &n in &uniform_counts {
                    let r =
                        self.adaptive_run(&renderer, b, name, &desc, &base, None, n, &reference)?;
                    if n == top {
                        uniform_top = Some((r.error.map_or(f64::NAN, |e| e.rmse), r.seconds));
                    }
                    runs.push(r);
                }
                let mut curve = vec![];
                for &e in targets {
                    let a = AdaptiveSettings {
                        target_error: e,
                        relative_error: 0.0,
                        min_samples: min,
                        max_samples: 4 * top,
                    };
                    let r = self.adaptive_run(
                        &renderer,
                        b,
                        name,
                        &desc,
                        &base,
                        Some(a),
                        0,
                        &reference,
                    )?;
                    curve.push((r.seconds, r.error.map_or(f64::NAN, |e| e.rmse)));
                    runs.push(r);
                }
                let (rmse, seconds) = uniform_top.expect("the top count is among the counts");
                headlines.push(Headline {
                    scene: name.to_string(),
                    backend: b,
                    uniform_spp: top,
                    uniform_rmse: rmse,
                    uniform_seconds: seconds,
                    adaptive_seconds: time_to_reach(&curve, rmse),
                });
            }
        }
        let dir = self.cfg.out.join("adaptive");
        let mut series = vec![];
        for name in ["resolution", "distributed"] {
            for &b in &self.cfg.backends {
                for mode in ["uniform", "adaptive"] {
                    let points: Vec<(f64, f64)> = runs
                        .iter()
                        .filter(|r| r.scene == name && r.backend == b && r.extra[0].1 == mode)
                        .map(|r| (r.seconds, r.error.map_or(f64::NAN, |e| e.rmse)))
                        .collect();
                    if !points.is_empty() {
                        series.push(Series {
                            name: format!("{name} {} {mode}", b.name()),
                            points,
                        });
                    }
                }
            }
        }
        LinePlot {
            title: format!(
                "Error against time, uniform and adaptive sampling ({width}x{height}, f64 reference at {ref_samples} spp)"
            ),
            x_label: "time per frame (s)".into(),
            y_label: "RMSE against f64 reference".into(),
            log_x: true,
            log_y: true,
            series,
        }
        .write(&dir.join("error_vs_time"))?;
        let mut text = String::new();
        for h in &headlines {
            let line = match (h.adaptive_seconds, h.speedup()) {
                (Some(a), Some(x)) => format!(
                    "{} {}: uniform {} spp RMSE {:.3e} in {:.3} s; adaptive reaches it in {:.3} s: {:.2}x",
                    h.scene, h.backend, h.uniform_spp, h.uniform_rmse, h.uniform_seconds, a, x
                ),
                _ => format!(
                    "{} {}: uniform {} spp RMSE {:.3e} in {:.3} s; no adaptive run reached it (lower the smallest target)",
                    h.scene, h.backend, h.uniform_spp, h.uniform_rmse, h.uniform_seconds
                ),
            };
            eprintln!("  adaptive headline: {line}");
            text.push_str(&line);
            text.push('\n');
        }
        std::fs::create_dir_all(&dir)?;
        std::fs::write(dir.join("headline.txt"), text)?;
        Ok(runs)
    }

    /// A renderer of backend `b` as [`adaptive::render`] takes it (a
    /// [`Renderer`] owns its backend, so it is made here, with the suite's
    /// threads and adapter).
    fn renderer(&self, b: Backend) -> Result<Renderer> {
        Ok(Renderer::open(
            b,
            self.cfg.threads,
            self.cfg.adapter.as_deref(),
        )?)
    }

    /// The f64 reference at samples `2^15 .. 2^15 + samples` of the
    /// progressive sequence, cached like the other suites' references.
    fn offset_reference(
        &self,
        name: &str,
        desc: &SceneDesc,
        base: &RenderSettings,
        samples: u32,
    ) -> Result<Vec<[f32; 3]>> {
        let file = self.cfg.cache.join(format!(
            "adaptive-{name}-{}x{}-d{}-o{REFERENCE_OFFSET}-s{samples}-{:016x}.exr",
            base.width,
            base.height,
            base.max_depth,
            super::reference::scene_hash(&desc.path)?
        ));
        if let Ok(img) = image::open(&file) {
            let img = img.to_rgb32f();
            if img.dimensions() == (base.width, base.height) {
                return Ok(img.pixels().map(|p| p.0).collect());
            }
        }
        eprintln!(
            "bench: making reference {} ({}x{}, {samples} progressive samples from {REFERENCE_OFFSET}, f64)",
            file.display(),
            base.width,
            base.height
        );
        let start = Instant::now();
        let frame = PreparedFrame::build(desc, base, 0, Precision::F64)?;
        let film = self.cpu.render(
            &frame,
            0,
            Rect::full(base.width, base.height),
            SampleRange::new(REFERENCE_OFFSET, REFERENCE_OFFSET + samples),
            &|_| {},
        )?;
        let linear = film.resolve();
        std::fs::create_dir_all(&self.cfg.cache)?;
        let tmp = file.with_extension("exr.tmp");
        write_exr(&tmp, base.width, base.height, &linear)?;
        std::fs::rename(&tmp, &file)?;
        eprintln!(
            "bench: reference made in {:.1} s",
            start.elapsed().as_secs_f64()
        );
        Ok(linear)
    }

    /// One timed render (best of `repeat`): uniform at `n` spp, or adaptive.
    #[allow(clippy::too_many_arguments)]
    fn adaptive_run(
        &self,
        renderer: &Renderer,
        b: Backend,
        name: &str,
        desc: &SceneDesc,
        base: &RenderSettings,
        a: Option<AdaptiveSettings>,
        n: u32,
        reference: &[[f32; 3]],
    ) -> Result<Run> {
        let frame = PreparedFrame::build(desc, base, 0, Precision::F32)?;
        let rect = Rect::full(base.width, base.height);
        let once = || -> Result<Film> {
            Ok(match &a {
                None => renderer.render(&frame, 0, rect, SampleRange::all(n), &|_| {})?,
                Some(a) => adaptive::render(renderer, &frame, 0, a, &|_| {}, &mut |_| {})?,
            })
        };
        if b != Backend::Cpu {
            once()?; // the GPU compiles its pipelines on first use
        }
        let mut best: Option<(Film, f64)> = None;
        for _ in 0..self.cfg.repeat.max(1) {
            let start = Instant::now();
            let film = once()?;
            let secs = start.elapsed().as_secs_f64();
            if best.as_ref().is_none_or(|b| secs < b.1) {
                best = Some((film, secs));
            }
        }
        let (film, seconds) = best.expect("one repetition");
        let linear = film.resolve();
        let error = compare(&linear, reference, base.width, base.height);
        let pixel_samples: u64 = film.counts.iter().map(|&c| c as u64).sum();
        let mean_spp = pixel_samples as f64 / rect.area() as f64;
        let mode = if a.is_some() { "adaptive" } else { "uniform" };
        let tag = a.map_or(format!("s{n}"), |a| format!("e{}", a.target_error));
        let image = format!("adaptive/{name}-{mode}-{tag}-{}.png", b.name());
        let path = self.cfg.out.join(&image);
        std::fs::create_dir_all(path.parent().expect("has a parent"))?;
        write_png(
            &path,
            base.width,
            base.height,
            &tracer_core::film::to_srgb8(&linear),
        )?;
        if let Some(a) = &a {
            let map = self
                .cfg
                .out
                .join(format!("adaptive/{name}-samples-{tag}-{}.png", b.name()));
            write_sample_map(&map, &film, a.min_samples, a.max_samples)?;
        }
        let run = Run {
            suite: "adaptive",
            scene: name.to_string(),
            backend: b,
            device: match b {
                Backend::Cpu => self.cpu_name.clone(),
                Backend::Gpu => renderer.adapter_name().unwrap_or_default().to_string(),
            },
            threads: renderer.threads(),
            settings: RenderSettings {
                samples: a.map_or(n, |a| a.max_samples),
                ..*base
            },
            precision: Precision::F32,
            seconds,
            gpu_seconds: None,
            rays: film.rays,
            error: Some(error),
            image,
            extra: vec![
                ("mode", mode.to_string()),
                (
                    "target_error",
                    a.map_or(String::new(), |a| a.target_error.to_string()),
                ),
                (
                    "min_samples",
                    a.map_or(String::new(), |a| a.min_samples.to_string()),
                ),
                (
                    "max_samples",
                    a.map_or(String::new(), |a| a.max_samples.to_string()),
                ),
                ("mean_spp", format!("{mean_spp:.2}")),
            ],
        };
        eprintln!(
            "  adaptive   {name:<12} {:<4} {mode:<8} {tag:<10} {:>8.3} s  mean {:>7.1} spp  RMSE {:.3e}  PSNR {:.1} dB",
            run.backend, seconds, mean_spp, error.rmse, error.psnr_db
        );
        Ok(run)
    }
}

/// The time at which a curve of (seconds, rmse) points first reaches
/// `rmse`: log-log interpolation between the last point above it and the
/// first at or below it (points in order of falling error).
pub fn time_to_reach(curve: &[(f64, f64)], rmse: f64) -> Option<f64> {
    let mut pts: Vec<(f64, f64)> = curve
        .iter()
        .copied()
        .filter(|p| p.0 > 0.0 && p.1 > 0.0 && p.1.is_finite())
        .collect();
    pts.sort_by(|a, b| b.1.total_cmp(&a.1));
    let i = pts.iter().position(|p| p.1 <= rmse)?;
    if i == 0 {
        return Some(pts[0].0);
    }
    let (t0, e0) = pts[i - 1];
    let (t1, e1) = pts[i];
    let f = (rmse.ln() - e0.ln()) / (e1.ln() - e0.ln());
    Some((t0.ln() + f * (t1.ln() - t0.ln())).exp())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_time_to_reach_an_error_interpolates_log_log() {
        let curve = [(1.0, 0.1), (4.0, 0.01), (2.0, 0.05)];
        assert_eq!(time_to_reach(&curve, 0.2), Some(1.0));
        assert_eq!(time_to_reach(&curve, 0.001), None);
        let t = time_to_reach(&curve, 0.02).unwrap();
        // Between (2, 0.05) and (4, 0.01): 0.02 is ln(2.5)/ln(5) of the way.
        let f = (2.5f64).ln() / 5f64.ln();
        assert!((t - (2f64.ln() + f * 2f64.ln()).exp()).abs() < 1e-12);
    }
}
