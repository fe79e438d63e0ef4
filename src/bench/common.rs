//! What every suite shares: the bench state ([`Bench`]), one measured
//! render ([`Run`]) and the render-compare-save step ([`Bench::measure`]).

use std::path::PathBuf;
use std::time::Instant;
use tracer_core::film::WorkRegion;

use anyhow::Result;
use tracer_core::film::{Film, RayCounts, Rect, SampleRange};
use tracer_core::render::{Backend, CpuRenderer, Precision, PreparedFrame};
use tracer_core::sampling::Sampler;
use tracer_core::scene::{RenderSettings, SceneDesc};

use super::plot::Series;
use super::reference::ReferenceCache;
use super::{Config, ErrorMetrics, compare};

/// One measured render.
#[derive(Clone, Debug)]
pub struct Run {
    pub suite: &'static str,
    pub scene: String,
    pub backend: Backend,
    pub device: String,
    pub threads: usize,
    pub settings: RenderSettings,
    pub precision: Precision,
    pub seconds: f64,
    /// GPU time alone (timestamp queries), for GPU runs on adapters that have them.
    pub gpu_seconds: Option<f64>,
    pub rays: RayCounts,
    pub error: Option<ErrorMetrics>,
    pub image: String,
    /// Suite-specific columns (launch shape, worker count...), appended to
    /// the CSV after the common ones; every run of a suite has the same.
    pub extra: Vec<(&'static str, String)>,
}

impl Run {
    pub(super) fn mrays_per_s(&self) -> f64 {
        self.rays.total() as f64 / self.seconds / 1e6
    }
    pub(super) fn pixels_per_s(&self) -> f64 {
        (self.settings.width as f64 * self.settings.height as f64) / self.seconds
    }
}

pub(super) fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| std::env::consts::ARCH.to_string())
}

pub(super) struct Bench {
    pub(super) cfg: Config,
    pub(super) cpu: CpuRenderer,
    #[cfg(feature = "gpu")]
    pub(super) gpu: Option<tracer_core::render::GpuRenderer>,
    pub(super) cpu_name: String,
    pub(super) refs: ReferenceCache,
}

impl Bench {
    /// Settings of the suites that fix their own: the grid sampler and the
    /// bench's `--integrator`.
    pub(super) fn grid_settings(
        &self,
        width: u32,
        height: u32,
        samples: u32,
        max_depth: u32,
    ) -> RenderSettings {
        RenderSettings {
            width,
            height,
            samples,
            max_depth,
            sampler: Sampler::Grid,
            integrator: self.cfg.integrator,
        }
    }

    pub(super) fn scene(&self, rel: &str) -> Result<(PathBuf, SceneDesc)> {
        let path = self.cfg.examples.join(rel);
        let desc = SceneDesc::load(&path)?;
        Ok((path, desc))
    }

    /// Renders a whole frame, timing only the render itself (best of
    /// `repeat`). Returns the film, the wall time, and the GPU time alone.
    pub(super) fn render(
        &self,
        backend: Backend,
        desc: &SceneDesc,
        settings: &RenderSettings,
        precision: Precision,
    ) -> Result<(Film, f64, Option<f64>)> {
        let frame = PreparedFrame::build(desc, settings, 0, precision)?;
        let (rect, samples) = (
            Rect::full(settings.width, settings.height),
            SampleRange::all(settings.samples),
        );
        let once = || -> Result<(Film, Option<f64>)> {
            Ok(match backend {
                Backend::Cpu => (
                    self.cpu
                        .render(&frame, WorkRegion::new(0, rect, samples), &|_| {})?,
                    None,
                ),
                #[cfg(feature = "gpu")]
                Backend::Gpu => {
                    let gpu = self
                        .gpu
                        .as_ref()
                        .expect("GPU renderer made when the GPU backend is selected");
                    let film = gpu.render(&frame, WorkRegion::new(0, rect, samples), &|_| {})?;
                    (film, gpu.last_stats().gpu_time.map(|d| d.as_secs_f64()))
                }
                #[cfg(not(feature = "gpu"))]
                Backend::Gpu => return Err(tracer_core::render::RendererError::GpuNotBuilt.into()),
            })
        };
        // The GPU compiles its pipeline for each new scene on first use: leave that out.
        if backend == Backend::Gpu {
            once()?;
        }
        let mut best: Option<(Film, f64, Option<f64>)> = None;
        for _ in 0..self.cfg.repeat.max(1) {
            let start = Instant::now();
            let (film, gpu_secs) = once()?;
            let secs = start.elapsed().as_secs_f64();
            if best.as_ref().is_none_or(|b| secs < b.1) {
                best = Some((film, secs, gpu_secs));
            }
        }
        Ok(best.expect("at least one repetition"))
    }

    /// Renders, compares with `reference` if given, saves the image, and records the run.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn measure(
        &self,
        suite: &'static str,
        name: &str,
        backend: Backend,
        desc: &SceneDesc,
        settings: &RenderSettings,
        precision: Precision,
        reference: Option<&[[f32; 3]]>,
    ) -> Result<Run> {
        let (film, seconds, gpu_seconds) = self.render(backend, desc, settings, precision)?;
        let linear = film.resolve();
        let error = reference.map(|r| compare(&linear, r, settings.width, settings.height));
        let image = format!(
            "{suite}/{name}-{}x{}-s{}-{}-d{}-{}-{}.png",
            settings.width,
            settings.height,
            settings.samples,
            settings.sampler.name(),
            settings.max_depth,
            precision.name(),
            backend.name()
        );
        let path = self.cfg.out.join(&image);
        std::fs::create_dir_all(path.parent().expect("has a parent"))?;
        // The error names the file.
        tracer_core::film::image::write_png(
            &path,
            settings.width,
            settings.height,
            &tracer_core::film::to_srgb8(&linear),
        )?;
        let run = Run {
            suite,
            scene: name.to_string(),
            backend,
            device: match backend {
                Backend::Cpu => self.cpu_name.clone(),
                #[cfg(feature = "gpu")]
                Backend::Gpu => self
                    .gpu
                    .as_ref()
                    .map_or(String::new(), |g| g.adapter().name.clone()),
                #[cfg(not(feature = "gpu"))]
                Backend::Gpu => String::new(),
            },
            threads: if backend == Backend::Cpu {
                self.cpu.threads()
            } else {
                0
            },
            settings: *settings,
            precision,
            seconds,
            gpu_seconds,
            rays: film.rays,
            error,
            image,
            extra: vec![],
        };
        eprintln!(
            "  {suite:<10} {name:<14} {:<4} {:>4}x{:<4} {:>2} spp {:<8} d{:<2} {}  {:>8.3} s  {:>7.1} Mrays/s  {}",
            run.backend,
            settings.width,
            settings.height,
            settings.samples,
            settings.sampler.name(),
            settings.max_depth,
            precision.name(),
            seconds,
            run.mrays_per_s(),
            error.map_or(String::new(), |e| format!(
                "RMSE {:.2e}  PSNR {:.1} dB  FLIP {:.4}",
                e.rmse, e.psnr_db, e.flip_mean
            ))
        );
        Ok(run)
    }

    /// Reference samples for suites whose point is speed, not error: 4x the
    /// tested 4 spp is enough to rank runs and keeps the references cheap.
    pub(super) fn reference_samples(&self) -> u32 {
        16
    }

    pub(super) fn size(&self, full: (u32, u32)) -> (u32, u32) {
        if self.cfg.quick {
            (full.0 / 10, full.1 / 10)
        } else {
            full
        }
    }

    pub(super) fn series_by_backend(
        &self,
        runs: &[Run],
        f: impl Fn(&Run) -> (f64, f64),
    ) -> Vec<Series> {
        self.cfg
            .backends
            .iter()
            .map(|&b| Series {
                name: b.name().to_string(),
                points: runs.iter().filter(|r| r.backend == b).map(&f).collect(),
            })
            .collect()
    }
}

pub(super) fn fmt_secs(s: Option<f64>) -> String {
    s.map_or_else(|| "-".into(), |s| format!("{s:.3} s"))
}
