//! `tessera bench`: the thesis's experiments redone, reporting speed *and*
//! error against a converged f64 reference, as CSV, images and plots.

mod metrics;
mod plot;
mod reference;

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use tracer_core::film::{Film, RayCounts, Rect, SampleRange};
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::sampling::Sampler;
use tracer_core::scene::{RenderSettings, SceneDesc};

pub use metrics::{compare, ErrorMetrics};

/// The default reference cache directory.
pub fn reference_dir() -> PathBuf {
    ReferenceCache::default_dir()
}
use plot::{LinePlot, Series};
use reference::ReferenceCache;

/// The named suites, in the order `tessera bench` runs them.
pub const SUITES: &[&str] = &["resolution", "samples", "complexity", "depth", "precision"];

/// Where a run was traced.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackendKind {
    Cpu,
}

pub struct Config {
    pub suites: Vec<String>,
    pub backends: Vec<BackendKind>,
    pub out: PathBuf,
    pub quick: bool,
    pub threads: Option<usize>,
    pub cache: PathBuf,
    pub examples: PathBuf,
    /// Timed repetitions per run; the fastest counts.
    pub repeat: u32,
}

/// One measured render.
#[derive(Clone, Debug)]
pub struct Run {
    pub suite: &'static str,
    pub scene: String,
    pub backend: &'static str,
    pub device: String,
    pub threads: usize,
    pub settings: RenderSettings,
    pub precision: Precision,
    pub seconds: f64,
    pub rays: RayCounts,
    pub error: Option<ErrorMetrics>,
    pub image: String,
}

impl Run {
    fn mrays_per_s(&self) -> f64 {
        self.rays.total() as f64 / self.seconds / 1e6
    }
    fn pixels_per_s(&self) -> f64 {
        (self.settings.width as f64 * self.settings.height as f64) / self.seconds
    }
}

/// Column names of every suite's CSV (tests/bench_quick.rs checks them).
const CSV_HEADER: &str = "suite,scene,backend,device,threads,width,height,samples,sampler,max_depth,precision,wall_s,rays_primary,rays_shadow,rays_reflection,rays_refraction,rays_total,mrays_per_s,pixels_per_s,rmse,psnr_db,rel_mse,flip_mean,image";

fn csv_row(r: &Run) -> String {
    let e = r.error;
    let f = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.6e}"));
    format!(
        "{},{},{},\"{}\",{},{},{},{},{},{},{},{:.6},{},{},{},{},{},{:.3},{:.1},{},{},{},{},{}",
        r.suite,
        r.scene,
        r.backend,
        r.device.replace('"', "'"),
        r.threads,
        r.settings.width,
        r.settings.height,
        r.settings.samples,
        r.settings.sampler.name(),
        r.settings.max_depth,
        r.precision.name(),
        r.seconds,
        r.rays.primary,
        r.rays.shadow,
        r.rays.reflection,
        r.rays.refraction,
        r.rays.total(),
        r.mrays_per_s(),
        r.pixels_per_s(),
        f(e.map(|e| e.rmse)),
        f(e.map(|e| e.psnr_db)),
        f(e.map(|e| e.rel_mse)),
        f(e.map(|e| e.flip_mean)),
        r.image
    )
}

fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("model name")).and_then(|l| l.split(':').nth(1)).map(|s| s.trim().to_string()))
        .unwrap_or_else(|| std::env::consts::ARCH.to_string())
}

struct Bench {
    cfg: Config,
    cpu: CpuRenderer,
    cpu_name: String,
    refs: ReferenceCache,
}

impl Bench {
    fn scene(&self, rel: &str) -> Result<(PathBuf, SceneDesc)> {
        let path = self.cfg.examples.join(rel);
        let desc = SceneDesc::load(&path)?;
        Ok((path, desc))
    }

    /// Renders a whole frame, timing only the render itself (best of `repeat`).
    fn render(&self, backend: BackendKind, desc: &SceneDesc, settings: &RenderSettings, precision: Precision) -> Result<(Film, f64)> {
        let frame = PreparedFrame::build(desc, settings, 0, precision)?;
        let mut best: Option<(Film, f64)> = None;
        for _ in 0..self.cfg.repeat.max(1) {
            let start = Instant::now();
            let film = match backend {
                BackendKind::Cpu => self.cpu.render(
                    &frame,
                    0,
                    Rect::full(settings.width, settings.height),
                    SampleRange::all(settings.samples),
                    &|_| {},
                )?,
            };
            let secs = start.elapsed().as_secs_f64();
            if best.as_ref().is_none_or(|b| secs < b.1) {
                best = Some((film, secs));
            }
        }
        Ok(best.expect("at least one repetition"))
    }

    /// Renders, compares with `reference` if given, saves the image, and records the run.
    #[allow(clippy::too_many_arguments)]
    fn measure(
        &self,
        suite: &'static str,
        name: &str,
        backend: BackendKind,
        desc: &SceneDesc,
        settings: &RenderSettings,
        precision: Precision,
        reference: Option<&[[f32; 3]]>,
    ) -> Result<Run> {
        let (film, seconds) = self.render(backend, desc, settings, precision)?;
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
            backend_name(backend)
        );
        let path = self.cfg.out.join(&image);
        std::fs::create_dir_all(path.parent().expect("has a parent"))?;
        image::RgbImage::from_raw(settings.width, settings.height, tracer_core::film::to_srgb8(&linear))
            .expect("buffer matches size")
            .save(&path)
            .with_context(|| format!("cannot write {}", path.display()))?;
        let run = Run {
            suite,
            scene: name.to_string(),
            backend: backend_name(backend),
            device: match backend {
                BackendKind::Cpu => self.cpu_name.clone(),
            },
            threads: self.cpu.threads(),
            settings: *settings,
            precision,
            seconds,
            rays: film.rays,
            error,
            image,
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
            error.map_or(String::new(), |e| format!("RMSE {:.2e}  PSNR {:.1} dB  FLIP {:.4}", e.rmse, e.psnr_db, e.flip_mean))
        );
        Ok(run)
    }

    /// Reference samples for suites whose point is speed, not error: 4x the
    /// tested 4 spp is enough to rank runs and keeps the references cheap.
    fn reference_samples(&self) -> u32 {
        16
    }

    fn size(&self, full: (u32, u32)) -> (u32, u32) {
        if self.cfg.quick { (full.0 / 10, full.1 / 10) } else { full }
    }

    fn suite_resolution(&self) -> Result<Vec<Run>> {
        let (path, desc) = self.scene("resolution.toml")?;
        let sizes: &[(u32, u32)] =
            if self.cfg.quick { &[(64, 48), (128, 96)] } else { &[(640, 480), (800, 600), (1024, 768), (1280, 720), (1920, 1080)] };
        let mut runs = vec![];
        for &(width, height) in sizes {
            let s = RenderSettings { width, height, samples: 4, max_depth: 10, sampler: Sampler::Grid };
            let reference = self.refs.get(&path, &desc, &s, self.reference_samples())?;
            for &b in &self.cfg.backends {
                runs.push(self.measure("resolution", "resolution", b, &desc, &s, Precision::F32, Some(&reference))?);
            }
        }
        let series = self.series_by_backend(&runs, |r| (r.settings.width as f64 * r.settings.height as f64 / 1e6, r.seconds));
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

    fn suite_samples(&self) -> Result<Vec<Run>> {
        let (path, desc) = self.scene("resolution.toml")?;
        let (width, height) = self.size((800, 600));
        let counts: &[u32] = if self.cfg.quick { &[1, 4, 9] } else { &[1, 4, 9, 16, 25, 36] };
        let base = RenderSettings { width, height, samples: 1, max_depth: 10, sampler: Sampler::Grid };
        // The samples suite is the headline error curve: a finer reference than the others.
        let reference = self.refs.get(&path, &desc, &base, if self.cfg.quick { 36 } else { 256 })?;
        let mut runs = vec![];
        for sampler in [Sampler::Grid, Sampler::Jittered] {
            for &samples in counts {
                let s = RenderSettings { samples, sampler, ..base };
                for &b in &self.cfg.backends {
                    runs.push(self.measure("samples", "resolution", b, &desc, &s, Precision::F32, Some(&reference))?);
                }
            }
        }
        let mut series = vec![];
        for &b in &self.cfg.backends {
            for sampler in [Sampler::Grid, Sampler::Jittered] {
                let pts = runs
                    .iter()
                    .filter(|r| r.backend == backend_name(b) && r.settings.sampler == sampler)
                    .map(|r| (r.seconds, r.error.map_or(f64::NAN, |e| e.rmse)))
                    .collect();
                series.push(Series { name: format!("{} {} (1..{} spp)", backend_name(b), sampler.name(), counts.last().unwrap()), points: pts });
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

    fn suite_complexity(&self) -> Result<Vec<Run>> {
        let (width, height) = self.size((800, 600));
        let mut runs = vec![];
        for material in ["plastic", "chrome", "glass", "emerald"] {
            for n in [1, 3, 6, 9] {
                let name = format!("{material}-{n}");
                let (path, desc) = self.scene(&format!("complexity/{name}.toml"))?;
                let s = RenderSettings { width, height, samples: 4, max_depth: 10, sampler: Sampler::Grid };
                let reference = self.refs.get(&path, &desc, &s, self.reference_samples())?;
                for &b in &self.cfg.backends {
                    runs.push(self.measure("complexity", &name, b, &desc, &s, Precision::F32, Some(&reference))?);
                }
            }
        }
        let mut series = vec![];
        for &b in &self.cfg.backends {
            for material in ["plastic", "chrome", "glass", "emerald"] {
                let pts = runs
                    .iter()
                    .filter(|r| r.backend == backend_name(b) && r.scene.starts_with(material))
                    .map(|r| (r.scene.rsplit('-').next().and_then(|n| n.parse::<f64>().ok()).unwrap_or(0.0), r.rays.total() as f64 / 1e6))
                    .collect();
                series.push(Series { name: format!("{} {material}", backend_name(b)), points: pts });
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

    fn suite_depth(&self) -> Result<Vec<Run>> {
        let (path, desc) = self.scene("depth.toml")?;
        let (width, height) = self.size((800, 600));
        let depths: &[u32] = if self.cfg.quick { &[0, 1, 4] } else { &[0, 1, 2, 4, 8, 12, 16] };
        // Reference: the same samples, depth 32, f64: isolates what depth buys.
        let base = RenderSettings { width, height, samples: 4, max_depth: 32, sampler: Sampler::Grid };
        let frame = PreparedFrame::build(&desc, &base, 0, Precision::F64)?;
        let reference =
            self.cpu.render(&frame, 0, Rect::full(width, height), SampleRange::all(4), &|_| {})?.resolve();
        let _ = &path;
        let mut runs = vec![];
        for &d in depths {
            let s = RenderSettings { max_depth: d, ..base };
            for &b in &self.cfg.backends {
                runs.push(self.measure("depth", "depth", b, &desc, &s, Precision::F32, Some(&reference))?);
            }
        }
        let time = self.series_by_backend(&runs, |r| (r.settings.max_depth as f64, r.seconds));
        LinePlot {
            title: "Time against max_depth (5 emerald spheres)".into(),
            x_label: "max_depth".into(),
            y_label: "time per frame (s)".into(),
            log_x: false,
            log_y: false,
            series: time,
        }
        .write(&self.cfg.out.join("depth/time_vs_depth"))?;
        let err = self.series_by_backend(&runs, |r| (r.settings.max_depth as f64, r.error.map_or(f64::NAN, |e| e.rmse)));
        LinePlot {
            title: "Error against max_depth (reference: depth 32, f64)".into(),
            x_label: "max_depth".into(),
            y_label: "RMSE".into(),
            log_x: false,
            log_y: true,
            series: err,
        }
        .write(&self.cfg.out.join("depth/error_vs_depth"))?;
        Ok(runs)
    }

    fn suite_precision(&self) -> Result<Vec<Run>> {
        let mut runs = vec![];
        for name in ["tiny-far", "huge-floor", "grazing-plane", "nested-glass"] {
            let (_, desc) = self.scene(&format!("hard/{name}.toml"))?;
            let (width, height) = if self.cfg.quick { (64, 48) } else { (desc.render.width, desc.render.height) };
            let s = RenderSettings { width, height, ..desc.render };
            // Error of each precision against the f64 CPU render of the same settings.
            let (f64_film, _) = self.render(BackendKind::Cpu, &desc, &s, Precision::F64)?;
            let reference = f64_film.resolve();
            for &b in &self.cfg.backends {
                for p in [Precision::F32, Precision::F64] {
                    runs.push(self.measure("precision", name, b, &desc, &s, p, Some(&reference))?);
                }
            }
        }
        Ok(runs)
    }

    fn series_by_backend(&self, runs: &[Run], f: impl Fn(&Run) -> (f64, f64)) -> Vec<Series> {
        self.cfg
            .backends
            .iter()
            .map(|&b| Series {
                name: backend_name(b).to_string(),
                points: runs.iter().filter(|r| r.backend == backend_name(b)).map(&f).collect(),
            })
            .collect()
    }
}

fn backend_name(b: BackendKind) -> &'static str {
    match b {
        BackendKind::Cpu => "cpu",
    }
}

/// Runs the configured suites; returns every run.
pub fn run(cfg: Config) -> Result<Vec<Run>> {
    for s in &cfg.suites {
        if !SUITES.contains(&s.as_str()) {
            bail!("unknown suite {s:?}; suites: {}", SUITES.join(", "));
        }
    }
    std::fs::create_dir_all(&cfg.out).with_context(|| format!("cannot create {}", cfg.out.display()))?;
    let bench = Bench {
        cpu: CpuRenderer::new(cfg.threads)?,
        cpu_name: cpu_model(),
        refs: ReferenceCache::new(cfg.cache.clone(), cfg.threads)?,
        cfg,
    };
    let mut all = vec![];
    let suites: Vec<String> = if bench.cfg.suites.is_empty() { SUITES.iter().map(|s| s.to_string()).collect() } else { bench.cfg.suites.clone() };
    for suite in &suites {
        eprintln!("bench: suite {suite}");
        let runs = match suite.as_str() {
            "resolution" => bench.suite_resolution()?,
            "samples" => bench.suite_samples()?,
            "complexity" => bench.suite_complexity()?,
            "depth" => bench.suite_depth()?,
            "precision" => bench.suite_precision()?,
            _ => unreachable!("checked above"),
        };
        let mut csv = String::from(CSV_HEADER);
        csv.push('\n');
        for r in &runs {
            writeln!(csv, "{}", csv_row(r)).expect("write to String");
        }
        let file = bench.cfg.out.join(format!("{suite}.csv"));
        std::fs::write(&file, csv).with_context(|| format!("cannot write {}", file.display()))?;
        all.extend(runs);
    }
    print_summary(&all);
    Ok(all)
}

fn print_summary(runs: &[Run]) {
    println!(
        "{:<10} {:<14} {:<4} {:>9} {:>4} {:<8} {:>3} {:<4} {:>9} {:>9} {:>10} {:>9} {:>7}",
        "suite", "scene", "back", "size", "spp", "sampler", "dep", "prec", "time_s", "Mrays/s", "RMSE", "PSNR_dB", "FLIP"
    );
    for r in runs {
        let e = r.error.unwrap_or_default();
        println!(
            "{:<10} {:<14} {:<4} {:>9} {:>4} {:<8} {:>3} {:<4} {:>9.4} {:>9.1} {:>10.3e} {:>9.2} {:>7.4}",
            r.suite,
            r.scene,
            r.backend,
            format!("{}x{}", r.settings.width, r.settings.height),
            r.settings.samples,
            r.settings.sampler.name(),
            r.settings.max_depth,
            r.precision.name(),
            r.seconds,
            r.mrays_per_s(),
            e.rmse,
            e.psnr_db,
            e.flip_mean
        );
    }
}
