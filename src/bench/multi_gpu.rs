//! The `multi-gpu` suite (issue 21): the farm's scaling over several GPUs
//! of one host. One GPU worker per GPU (`tessera worker --backend gpu
//! --adapter INDEX`, the adapters of `--gpu-adapters`; an index may repeat,
//! so `0,0` runs two workers sharing one GPU), for 1..N GPUs, on two
//! workloads of the resolution scene:
//!
//! - **frame**: one 1920x1080 frame at 256 spp (`resolution.toml`);
//! - **animation**: 24 frames of `animation.toml` (the resolution scene
//!   with a camera dolly over frames 1-5, held after) at 1920x1080, 64 spp.
//!
//! Each farm job (submit to done, on a warm farm as the farm suite's) is
//! set against one GPU worker (speed-up, efficiency) and against the
//! machine's ceiling measured just before it: N concurrent local renders
//! in this process, one [`GpuRenderer`] per adapter on a thread of its
//! own, of 1/N of the work (1/N of the samples of the frame, 1/N of the
//! animation's frames). The GPU-only farm's frames must equal the local
//! GPU render's byte for byte. Then the same N GPU workers beside CPU
//! workers filling the remaining cores (niced, as the farm suite's mixed
//! run): the mixed farm must not be slower than the GPU workers alone.
//! CPU workers alone are the farm suite's (`tessera bench farm`).
//!
//! Built with the `gpu` feature only; without it the suite is an error.

use std::path::{Path, PathBuf};
use std::time::Instant;
use tracer_core::film::WorkRegion;

use anyhow::{Context, Result, bail};
use tracer_core::film::{RayCounts, Rect, SampleRange};
use tracer_core::render::{Backend, GpuRenderer, Precision, PreparedFrame};
use tracer_core::scene::{RenderSettings, SceneDesc};

use super::plot::{LinePlot, Series};
use super::{Bench, Run, farm, fmt_secs};

/// One job of the suite: what the farm renders and the local GPU renders
/// reproduce.
struct Workload {
    /// `frame` or `animation`: the CSV's `workload`, the files' prefix.
    name: &'static str,
    /// The scene's file stem: the CSV's `scene`.
    scene_name: &'static str,
    scene: PathBuf,
    desc: SceneDesc,
    settings: RenderSettings,
    /// First and last frame, inclusive.
    frames: (u32, u32),
    tile: u32,
}

impl Workload {
    fn frame_count(&self) -> usize {
        (self.frames.1 - self.frames.0 + 1) as usize
    }
}

/// Where the suite runs and what it shares between workloads.
struct Setup<'a> {
    exe: PathBuf,
    dir: PathBuf,
    /// `--gpu-adapters`, one GPU worker each.
    adapters: &'a [String],
    /// One renderer per entry of `adapters` (up to the largest count), as
    /// each worker opens its own device.
    gpus: Vec<GpuRenderer>,
    counts: Vec<usize>,
    threads: usize,
    /// Cores the mixed runs fill (0: no mixed runs).
    cores: usize,
}

/// One GPU's part of a workload: the frames (indices into the prepared
/// frames) it renders, each over `samples`.
struct Share {
    frames: std::ops::Range<usize>,
    samples: SampleRange,
}

/// The work of `frames` frames of `samples` samples split over `n` GPUs:
/// the frames when there are several (1/n of them each, in runs), else
/// the samples of the one frame. Empty shares are left out.
fn shares(frames: usize, samples: u32, n: usize) -> Vec<Share> {
    (0..n)
        .map(|k| {
            if frames > 1 {
                Share {
                    frames: k * frames / n..(k + 1) * frames / n,
                    samples: SampleRange::all(samples),
                }
            } else {
                let s = samples as usize;
                Share {
                    frames: 0..frames,
                    samples: SampleRange::new((k * s / n) as u32, ((k + 1) * s / n) as u32),
                }
            }
        })
        .filter(|s| !s.frames.is_empty() && !s.samples.is_empty())
        .collect()
}

/// CPU workers of `threads` threads beside `gpu_workers` GPU workers on
/// `cores` cores: a core feeds each GPU worker, one is the coordinator's,
/// CPU workers take the rest.
fn mixed_cpu_workers(cores: usize, gpu_workers: usize, threads: usize) -> usize {
    cores.saturating_sub(gpu_workers + 1) / threads.max(1)
}

/// The frames of `w` rendered on one GPU, one after the other.
struct LocalRender {
    seconds: f64,
    /// Each frame's 8-bit sRGB image.
    images: Vec<Vec<u8>>,
    rays: RayCounts,
}

impl Bench {
    pub(super) fn suite_multi_gpu(&self) -> Result<Vec<Run>> {
        let exe = std::env::current_exe()
            .context("cannot find this executable to start the farm's processes")?;
        let listed: Vec<String>;
        let adapters: &[String] = if self.cfg.gpu_adapters.is_empty() {
            listed = tracer_core::render::gpu::list_adapters()
                .iter()
                .map(|a| a.index.to_string())
                .collect();
            if listed.is_empty() {
                return Err(tracer_core::render::GpuError::NoAdapter.into());
            }
            &listed
        } else {
            &self.cfg.gpu_adapters
        };
        if let Some(a) = adapters.iter().find(|a| a.trim().is_empty()) {
            bail!(
                "--gpu-adapters: an empty adapter ({a:?}); give an index or a name from `tessera gpus`"
            );
        }
        let counts = match &self.cfg.gpu_counts {
            Some(c) => {
                if let Some(&n) = c.iter().find(|&&n| n == 0 || n > adapters.len()) {
                    bail!(
                        "--gpu-counts: {n} GPU workers, but --gpu-adapters lists {} adapter(s) ({}): each count must be 1..={}",
                        adapters.len(),
                        adapters.join(","),
                        adapters.len()
                    );
                }
                c.clone()
            }
            None => (1..=adapters.len()).collect(),
        };
        let most = counts.iter().copied().max().unwrap_or(1);
        let gpus = adapters[..most]
            .iter()
            .map(|a| GpuRenderer::new(Some(a), Default::default()))
            .collect::<Result<Vec<_>, _>>()?;
        for (a, g) in adapters.iter().zip(&gpus) {
            eprintln!(
                "  multi-gpu  adapter {a}: {} ({})",
                g.adapter().name,
                g.adapter().device_type
            );
        }
        let dir = self.cfg.out.join("multi-gpu");
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        let setup = Setup {
            exe,
            dir,
            adapters,
            gpus,
            counts,
            threads: self.cfg.worker_threads.max(1),
            cores: self.cfg.mixed_cores.unwrap_or_else(|| {
                std::thread::available_parallelism().map_or(1, std::num::NonZero::get)
            }),
        };
        let mut runs = vec![];
        for w in self.multi_gpu_workloads()? {
            runs.extend(self.multi_gpu_workload(&setup, &w)?);
        }
        Ok(runs)
    }

    /// The frame and the animation; small with `--quick`.
    fn multi_gpu_workloads(&self) -> Result<Vec<Workload>> {
        let quick = self.cfg.quick;
        let (width, height) = if quick { (64, 48) } else { (1920, 1080) };
        // Small tiles in the quick run, so that two workers both get work.
        let tile = if quick { 16 } else { 64 };
        let settings = |samples| self.grid_settings(width, height, samples, 10);
        let (scene, desc) = self.scene("resolution.toml")?;
        let frame = Workload {
            name: "frame",
            scene_name: "resolution",
            scene,
            desc,
            settings: settings(if quick { 8 } else { 256 }),
            frames: (0, 0),
            tile,
        };
        let (scene, desc) = self.scene("animation.toml")?;
        let animation = Workload {
            name: "animation",
            scene_name: "animation",
            scene,
            desc,
            settings: settings(if quick { 4 } else { 64 }),
            frames: (1, if quick { 3 } else { 24 }),
            tile,
        };
        Ok(vec![frame, animation])
    }

    /// Every GPU count of one workload: the ceiling, the GPU workers alone,
    /// then beside CPU workers.
    fn multi_gpu_workload(&self, setup: &Setup, w: &Workload) -> Result<Vec<Run>> {
        let s = &w.settings;
        let prepared = (w.frames.0..=w.frames.1)
            .map(|f| Ok((f, PreparedFrame::build(&w.desc, s, f, Precision::F32)?)))
            .collect::<Result<Vec<_>>>()?;
        let local = local_render(&setup.gpus[0], &prepared, s)?;
        let describe = format!(
            "{} {}x{} {} spp, {} frame(s)",
            w.name,
            s.width,
            s.height,
            s.samples,
            w.frame_count()
        );
        eprintln!(
            "  multi-gpu  {describe}: local render on adapter {}: {:.3} s",
            setup.adapters[0], local.seconds
        );
        let expected: Vec<&[u8]> = local.images.iter().map(Vec::as_slice).collect();
        let threads = setup.threads;
        let mut runs: Vec<Run> = vec![];
        let mut base: Option<(usize, f64)> = None;
        for &n in &setup.counts {
            let adapters = &setup.adapters[..n];
            // The local render is the ceiling of one GPU.
            let ceiling = if n == 1 {
                local.seconds
            } else {
                gpu_ceiling(&setup.gpus[..n], &prepared, s)?
            };
            let device = setup.gpus[..n]
                .iter()
                .map(|g| g.adapter().name.as_str())
                .collect::<Vec<_>>()
                .join(" + ");
            let mut alone = None;
            for cpu_workers in [0, mixed_cpu_workers(setup.cores, n, threads)] {
                if cpu_workers == 0 && alone.is_some() {
                    eprintln!(
                        "  multi-gpu  {describe}: no mixed run beside {n} GPU worker(s): {} core(s) leave none for a CPU worker of {threads} threads (--mixed-cores)",
                        setup.cores
                    );
                    break;
                }
                let name = format!("{}-gpu{n}-cpu{cpu_workers}", w.name);
                let spec = farm::FarmSpec {
                    cpu_workers,
                    threads,
                    gpu_workers: n,
                    adapter: None,
                    gpu_adapters: adapters.to_vec(),
                };
                let run = farm::RunSpec {
                    exe: &setup.exe,
                    dir: &setup.dir,
                    name: &name,
                    scene: &w.scene,
                    settings: s,
                    frames: w.frames,
                    tile: w.tile,
                };
                let (result, diffs) = farm::timed_frames_run(&run, &spec, &expected)?;
                let secs = result.seconds;
                let gpu_alone = *alone.get_or_insert(secs);
                let (n0, t0) = *base.get_or_insert((n, secs));
                // Against the smallest count, scaled by it (1 GPU worker when it was run).
                let speedup = t0 * n0 as f64 / secs;
                let efficiency = speedup / n as f64;
                let identical = diffs.iter().all(|&d| d == 0);
                let check = if cpu_workers > 0 {
                    format!(
                        "{:.3}x the GPU workers alone{}",
                        secs / gpu_alone,
                        if secs > gpu_alone {
                            " (SLOWER than the GPU workers alone)"
                        } else {
                            ""
                        }
                    )
                } else if identical {
                    "frames identical to the local GPU render".to_string()
                } else {
                    format!(
                        "FRAMES DIFFER from the local GPU render ({} bytes in {} of {} frames)",
                        diffs.iter().sum::<usize>(),
                        diffs.iter().filter(|&&d| d > 0).count(),
                        diffs.len()
                    )
                };
                eprintln!(
                    "  multi-gpu  {:<9} {n:>2} GPU + {cpu_workers:>2} CPU workers  {secs:>8.3} s  speed-up {speedup:>5.2}  efficiency {:>5.1}%  ceiling {ceiling:.3} s: {:>5.1}% of it  first result {}  {check}",
                    w.name,
                    efficiency * 100.0,
                    100.0 * ceiling / secs,
                    fmt_secs(result.first_result_s),
                );
                let f = |v: f64| format!("{v:.4}");
                runs.push(Run {
                    suite: "multi-gpu",
                    scene: w.scene_name.into(),
                    backend: Backend::Gpu,
                    device: device.clone(),
                    threads: cpu_workers * threads,
                    settings: *s,
                    precision: Precision::F32,
                    seconds: secs,
                    gpu_seconds: None,
                    // The local render's: a GPU-only farm with identical frames traced the same samples.
                    rays: local.rays,
                    error: None,
                    image: format!("multi-gpu/frames-{name}/frame_{:04}.png", w.frames.0),
                    extra: vec![
                        ("workload", w.name.to_string()),
                        ("frames", w.frame_count().to_string()),
                        ("gpu_workers", n.to_string()),
                        ("adapters", adapters.join(";")),
                        ("cpu_workers", cpu_workers.to_string()),
                        ("worker_threads", threads.to_string()),
                        ("tile_size", w.tile.to_string()),
                        ("local_wall_s", format!("{:.6}", local.seconds)),
                        ("ceiling_s", format!("{ceiling:.6}")),
                        ("of_ceiling", f(ceiling / secs)),
                        ("ceiling_speedup", f(local.seconds / ceiling)),
                        ("speedup", f(speedup)),
                        ("efficiency", f(efficiency)),
                        (
                            "vs_gpu_alone",
                            if cpu_workers > 0 {
                                f(secs / gpu_alone)
                            } else {
                                String::new()
                            },
                        ),
                        (
                            "bit_identical",
                            if cpu_workers > 0 {
                                String::new()
                            } else {
                                identical.to_string()
                            },
                        ),
                        ("first_result_s", fmt_opt(result.first_result_s)),
                        ("render_s", fmt_opt(result.render_s)),
                    ],
                });
            }
        }
        write_speedup_plot(&setup.dir, w, &describe, &runs, &setup.counts)?;
        Ok(runs)
    }
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map_or(String::new(), |v| format!("{v:.4}"))
}

/// Renders every frame of `prepared` whole on `gpu`, one after the other,
/// after an untimed first frame (pipelines, scene, buffers): the time of
/// the render calls, each frame's sRGB image and the rays.
fn local_render(
    gpu: &GpuRenderer,
    prepared: &[(u32, PreparedFrame)],
    s: &RenderSettings,
) -> Result<LocalRender> {
    let full = Rect::full(s.width, s.height);
    let samples = SampleRange::all(s.samples);
    let (f0, p0) = &prepared[0];
    gpu.render(p0, WorkRegion::new(*f0, full, samples), &|_| {})?;
    let mut out = LocalRender {
        seconds: 0.0,
        images: Vec::with_capacity(prepared.len()),
        rays: RayCounts::default(),
    };
    for (f, p) in prepared {
        let start = Instant::now();
        let film = gpu.render(p, WorkRegion::new(*f, full, samples), &|_| {})?;
        out.seconds += start.elapsed().as_secs_f64();
        // Resolved outside the timing, and kept 8-bit: 24 films of sums
        // at 1080p would take gigabytes.
        out.rays.add(&film.rays);
        out.images
            .push(tracer_core::film::to_srgb8(&film.resolve()));
    }
    Ok(out)
}

/// The machine's ceiling for `gpus.len()` GPU workers: each renderer, on a
/// thread of its own, renders its share of the work ([`shares`]) at the
/// same time as the others, in this process (no farm). Each first renders
/// the first frame of its share untimed (pipelines, scene, buffers), all
/// at once.
fn gpu_ceiling(
    gpus: &[GpuRenderer],
    prepared: &[(u32, PreparedFrame)],
    s: &RenderSettings,
) -> Result<f64> {
    let full = Rect::full(s.width, s.height);
    let shares = shares(prepared.len(), s.samples, gpus.len());
    let concurrently = |warm_up: bool| -> Result<f64> {
        let start = Instant::now();
        std::thread::scope(|scope| -> Result<()> {
            let handles: Vec<_> = gpus
                .iter()
                .zip(&shares)
                .map(|(gpu, share)| {
                    scope.spawn(move || -> Result<()> {
                        let frames = if warm_up {
                            share.frames.start..share.frames.start + 1
                        } else {
                            share.frames.clone()
                        };
                        for (f, p) in &prepared[frames] {
                            gpu.render(p, WorkRegion::new(*f, full, share.samples), &|_| {})?;
                        }
                        Ok(())
                    })
                })
                .collect();
            for h in handles {
                h.join()
                    .map_err(|_| anyhow::anyhow!("a ceiling render panicked"))??;
            }
            Ok(())
        })?;
        Ok(start.elapsed().as_secs_f64())
    };
    concurrently(true)?;
    concurrently(false)
}

/// `multi-gpu/WORKLOAD_speedup`: speed-up against GPU workers, of the GPU
/// workers alone and beside CPU workers, with the machine's ceiling and
/// the ideal line.
fn write_speedup_plot(
    dir: &Path,
    w: &Workload,
    describe: &str,
    runs: &[Run],
    counts: &[usize],
) -> Result<()> {
    let col = |r: &Run, key: &str| {
        r.extra
            .iter()
            .find(|e| e.0 == key)
            .and_then(|e| e.1.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    let series_of = |name: &str, mixed: bool, key: &str| Series {
        name: name.into(),
        points: runs
            .iter()
            .filter(|r| (col(r, "cpu_workers") > 0.0) == mixed)
            .map(|r| (col(r, "gpu_workers"), col(r, key)))
            .collect(),
    };
    let mut series = vec![series_of("GPU workers", false, "speedup")];
    let mixed = series_of(
        "GPU workers + CPU workers on the other cores",
        true,
        "speedup",
    );
    if !mixed.points.is_empty() {
        series.push(mixed);
    }
    series.push(series_of(
        "machine ceiling (N local GPU renders of 1/N of the work)",
        false,
        "ceiling_speedup",
    ));
    series.push(Series {
        name: "ideal".into(),
        points: counts.iter().map(|&n| (n as f64, n as f64)).collect(),
    });
    LinePlot {
        title: format!("Farm speed-up over GPUs: {describe}"),
        x_label: "GPU workers (one per GPU)".into(),
        y_label: "speed-up against 1 GPU worker".into(),
        log_x: false,
        log_y: false,
        series,
    }
    .write(&dir.join(format!("{}_speedup", w.name)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_frame_is_split_by_samples_and_an_animation_by_frames() {
        let s = shares(1, 256, 4);
        assert_eq!(s.len(), 4);
        assert!(
            s.iter()
                .all(|s| s.frames == (0..1) && s.samples.len() == 64)
        );
        assert_eq!(s[3].samples, SampleRange::new(192, 256));
        let s = shares(24, 64, 5);
        let frames: Vec<_> = s.iter().map(|s| s.frames.clone()).collect();
        assert_eq!(frames, [0..4, 4..9, 9..14, 14..19, 19..24]);
        assert!(s.iter().all(|s| s.samples == SampleRange::all(64)));
        // More GPUs than work: the empty shares are left out.
        assert_eq!(shares(3, 4, 4).len(), 3);
        assert_eq!(shares(1, 2, 4).len(), 2);
    }

    #[test]
    fn cpu_workers_fill_the_cores_left_by_the_gpu_workers_and_the_coordinator() {
        assert_eq!(mixed_cpu_workers(16, 1, 2), 7);
        assert_eq!(mixed_cpu_workers(32, 2, 2), 14);
        assert_eq!(mixed_cpu_workers(16, 2, 2), 6);
        assert_eq!(mixed_cpu_workers(2, 1, 2), 0);
        assert_eq!(mixed_cpu_workers(0, 4, 2), 0);
    }
}
