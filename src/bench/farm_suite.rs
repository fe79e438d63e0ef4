//! The `farm` suite: one frame by 1..N worker processes over loopback gRPC
//! (the machinery is in `farm.rs`), against local renders and the machine's
//! ceiling.

use std::time::Instant;
use tracer_core::film::WorkRegion;

use anyhow::{Context, Result};
// The GPU cases only.
use tracer_core::film::{Rect, SampleRange};
use tracer_core::render::{Backend, CpuRenderer, Precision, PreparedFrame};
use tracer_core::scene::RenderSettings;
#[cfg(feature = "gpu")]
use {anyhow::bail, tracer_core::scene::SceneDesc};

use super::plot::{LinePlot, Series};
use super::{Bench, Run, compare, farm, fmt_secs};

impl Bench {
    /// `farm`: one frame by 1..N worker processes over loopback gRPC,
    /// against the local render of the same settings and against the
    /// machine's own ceiling (N concurrent local renders of 1/N of the
    /// samples each, measured in the same run); then, with
    /// `--gpu-workers`, GPU workers alone and beside CPU workers. Each farm
    /// renders a small warm-up job before the timed one
    /// ([`farm::Farm::warm_up`]), as a farm in service would have.
    pub(super) fn suite_farm(&self) -> Result<Vec<Run>> {
        let exe = std::env::current_exe()
            .context("cannot find this executable to start the farm's processes")?;
        let (path, desc) = self.scene("resolution.toml")?;
        let (width, height) = if self.cfg.quick {
            (64, 48)
        } else {
            (1920, 1080)
        };
        let s = self.grid_settings(width, height, if self.cfg.quick { 4 } else { 16 }, 10);
        // Small tiles in the quick run, so that two workers both get work.
        let tile = if self.cfg.quick { 16 } else { 64 };
        let counts = self.cfg.workers.clone().unwrap_or_else(|| {
            if self.cfg.quick {
                vec![1, 2]
            } else {
                vec![1, 2, 4, 8]
            }
        });
        let threads = self.cfg.worker_threads.max(1);
        let dir = self.cfg.out.join("farm");
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;

        // The local render of the same frame with one worker's threads: the
        // image every farm run must reproduce bit for bit, and its error.
        let local = CpuRenderer::new(Some(threads))?;
        let frame = PreparedFrame::build(&desc, &s, 0, Precision::F32)?;
        let start = Instant::now();
        let film = local.render(
            &frame,
            WorkRegion::new(0, Rect::full(width, height), SampleRange::all(s.samples)),
            &|_| {},
        )?;
        let local_secs = start.elapsed().as_secs_f64();
        let linear = film.resolve();
        let local_srgb = tracer_core::film::to_srgb8(&linear);
        let reference = self.refs.get(&path, &desc, &s, self.reference_samples())?;
        let local_error = compare(&linear, &reference, width, height);
        eprintln!("  farm       local render, {threads} threads: {local_secs:.3} s");

        let mut runs: Vec<Run> = vec![];
        let mut base: Option<(usize, f64)> = None;
        for &n in &counts {
            // The machine's ceiling for n workers: n concurrent renders of
            // 1/n of the samples each, in this process (no farm).
            let ceiling = machine_ceiling(&frame, &s, n, threads)?;
            let spec = farm::FarmSpec {
                cpu_workers: n,
                threads,
                ..Default::default()
            };
            let run = farm::RunSpec {
                exe: &exe,
                dir: &dir,
                name: &n.to_string(),
                scene: &path,
                settings: &s,
                frames: (0, 0),
                tile,
            };
            let (result, diff_bytes) = farm::timed_run(&run, &spec, &local_srgb)?;
            let identical = diff_bytes == 0;
            let job_secs = result.seconds;
            let (n0, t0) = *base.get_or_insert((n, job_secs));
            // Against the smallest count, scaled by its size (1 worker when it was run).
            let speedup = t0 * n0 as f64 / job_secs;
            let efficiency = speedup / n as f64;
            eprintln!(
                "  farm       {n:>2} workers x {threads} threads  {job_secs:>8.3} s  speed-up {speedup:>5.2}  efficiency {:>5.1}%  ceiling {ceiling:.3} s: {:>5.1}% of it  vs local {:.3}x  first result {}  {}",
                efficiency * 100.0,
                100.0 * ceiling / job_secs,
                job_secs / local_secs,
                fmt_secs(result.first_result_s),
                if identical {
                    "image identical to the local render".to_string()
                } else {
                    format!("IMAGE DIFFERS from the local render ({diff_bytes} bytes)")
                }
            );
            runs.push(Run {
                suite: "farm",
                scene: "resolution".into(),
                backend: Backend::Cpu,
                device: self.cpu_name.clone(),
                threads: n * threads,
                settings: s,
                precision: Precision::F32,
                seconds: job_secs,
                gpu_seconds: None,
                // The local render's rays: the farm traced the same samples when the images are identical.
                rays: film.rays,
                error: identical.then_some(local_error),
                image: format!("farm/frames-{n}/frame_0000.png"),
                extra: farm_columns(FarmColumns {
                    workers: n,
                    gpu_workers: 0,
                    threads,
                    tile,
                    local_secs,
                    ceiling_secs: Some(ceiling),
                    speedup: Some(speedup),
                    efficiency: Some(efficiency),
                    identical: Some(identical),
                    result: &result,
                    local_rays_per_s: film.rays.total() as f64 / local_secs,
                }),
            });
        }
        // With --repeat N: one worker against the local render, N pairs
        // timed side by side on one warm farm (the 5% target can only be
        // judged that way on a noisy machine).
        if self.cfg.repeat > 1 && counts.contains(&1) {
            let spec = farm::FarmSpec {
                cpu_workers: 1,
                threads,
                ..Default::default()
            };
            let run = farm::RunSpec {
                exe: &exe,
                dir: &dir,
                name: "1-pairs",
                scene: &path,
                settings: &s,
                frames: (0, 0),
                tile,
            };
            let full = Rect::full(width, height);
            // The local render once more, cut into units of a 1-worker
            // farm's size (rows of 7 tiles, ~113 ms each at 1080p 16 spp on
            // the H200 box), one call each: what the farm's units cost
            // without a farm around them.
            let units: Vec<Rect> = (0..height)
                .step_by(tile as usize)
                .flat_map(|y| {
                    (0..width).step_by(7 * tile as usize).map(move |x| {
                        Rect::new(x, y, (7 * tile).min(width - x), tile.min(height - y))
                    })
                })
                .collect();
            let mut by_units = vec![];
            let (pairs, diff_bytes) =
                farm::interleaved_runs(&run, &spec, self.cfg.repeat as usize, &local_srgb, || {
                    let start = Instant::now();
                    local.render(
                        &frame,
                        WorkRegion::new(0, full, SampleRange::all(s.samples)),
                        &|_| {},
                    )?;
                    let whole = start.elapsed().as_secs_f64();
                    let start = Instant::now();
                    for &u in &units {
                        local.render(
                            &frame,
                            WorkRegion::new(0, u, SampleRange::all(s.samples)),
                            &|_| {},
                        )?;
                    }
                    by_units.push(start.elapsed().as_secs_f64());
                    Ok(whole)
                })?;
            let mut ratios: Vec<f64> = pairs.iter().map(|(l, f)| f.seconds / l).collect();
            let listed: Vec<String> = pairs
                .iter()
                .zip(&by_units)
                .map(|((l, f), u)| {
                    format!(
                        "{:.3}/{}/{l:.3}/{u:.3}",
                        f.seconds,
                        f.render_s.map_or("-".into(), |r| format!("{r:.3}"))
                    )
                })
                .collect();
            ratios.sort_by(f64::total_cmp);
            eprintln!(
                "  farm        1 worker against the local render, {} interleaved pairs (farm submit to done/first lease to last result/local/local in {} units s): {}; ratio median {:.3}x (range {:.3}-{:.3}x)  {}",
                pairs.len(),
                units.len(),
                listed.join(" "),
                ratios[ratios.len() / 2],
                ratios[0],
                ratios[ratios.len() - 1],
                if diff_bytes == 0 {
                    "image identical to the local render".to_string()
                } else {
                    format!("IMAGE DIFFERS from the local render ({diff_bytes} bytes)")
                }
            );
        }
        let cpu_runs = runs.len();
        let workers_vs = |f: fn(&Run) -> f64| {
            vec![Series {
                name: format!("workers of {threads} threads"),
                points: runs[..cpu_runs]
                    .iter()
                    .map(|r| (r.threads as f64 / threads as f64, f(r)))
                    .collect(),
            }]
        };
        let extra_f64 = |r: &Run, key: &str| {
            r.extra
                .iter()
                .find(|e| e.0 == key)
                .and_then(|e| e.1.parse().ok())
                .unwrap_or(f64::NAN)
        };
        LinePlot {
            title: format!(
                "Farm speed-up: one {width}x{height} frame, {} spp, over loopback",
                s.samples
            ),
            x_label: "workers".into(),
            y_label: "speed-up against 1 worker".into(),
            log_x: false,
            log_y: false,
            series: {
                let mut v = workers_vs(|r| {
                    r.extra
                        .iter()
                        .find(|e| e.0 == "speedup")
                        .and_then(|e| e.1.parse().ok())
                        .unwrap_or(f64::NAN)
                });
                v.push(Series {
                    name: "machine ceiling (against the local render)".into(),
                    points: runs[..cpu_runs]
                        .iter()
                        .map(|r| {
                            let n = r.threads as f64 / threads as f64;
                            (n, local_secs / extra_f64(r, "ceiling_s"))
                        })
                        .collect(),
                });
                v.push(Series {
                    name: "ideal".into(),
                    points: counts.iter().map(|&n| (n as f64, n as f64)).collect(),
                });
                v
            },
        }
        .write(&dir.join("speedup"))?;
        LinePlot {
            title: format!(
                "Farm wall time, submit to done ({width}x{height}, {} spp)",
                s.samples
            ),
            x_label: "workers".into(),
            y_label: "seconds".into(),
            log_x: false,
            log_y: false,
            series: {
                let mut v = workers_vs(|r| r.seconds);
                v.push(Series {
                    name: "machine ceiling".into(),
                    points: runs[..cpu_runs]
                        .iter()
                        .map(|r| (r.threads as f64 / threads as f64, extra_f64(r, "ceiling_s")))
                        .collect(),
                });
                v
            },
        }
        .write(&dir.join("time"))?;
        #[cfg(feature = "gpu")]
        if self.cfg.gpu_workers > 0 {
            runs.extend(self.farm_gpu(&exe, &path, &desc, &dir)?);
        }
        Ok(runs)
    }

    /// The farm's GPU cases (each on a warm farm, as the CPU ones): GPU
    /// workers alone, then beside CPU workers,
    /// against a local GPU render of the same frame (in this process, warm,
    /// and as a whole `tessera render --backend gpu` process).
    #[cfg(feature = "gpu")]
    fn farm_gpu(
        &self,
        exe: &std::path::Path,
        path: &std::path::Path,
        desc: &SceneDesc,
        dir: &std::path::Path,
    ) -> Result<Vec<Run>> {
        let g = self.cfg.gpu_workers;
        let threads = self.cfg.worker_threads.max(1);
        let (width, height) = if self.cfg.quick {
            (64, 48)
        } else {
            (1920, 1080)
        };
        let s = self.grid_settings(width, height, if self.cfg.quick { 4 } else { 64 }, 10);
        let tile = if self.cfg.quick { 16 } else { 64 };
        let owned;
        let gpu = match &self.gpu {
            Some(g) => g,
            None => {
                owned = tracer_core::render::GpuRenderer::new(
                    self.cfg.adapter.as_deref(),
                    Default::default(),
                )?;
                &owned
            }
        };
        let frame = PreparedFrame::build(desc, &s, 0, Precision::F32)?;
        let full = Rect::full(width, height);
        // Warm-up (pipelines, buffers), then the timed call.
        gpu.render(
            &frame,
            WorkRegion::new(0, full, SampleRange::all(s.samples)),
            &|_| {},
        )?;
        let start = Instant::now();
        let film = gpu.render(
            &frame,
            WorkRegion::new(0, full, SampleRange::all(s.samples)),
            &|_| {},
        )?;
        let local_secs = start.elapsed().as_secs_f64();
        let local_rays_per_s = film.rays.total() as f64 / local_secs;
        let local_srgb = tracer_core::film::to_srgb8(&film.resolve());
        // A whole local process: start-up, scene, pipelines, render, PNG.
        let out_png = dir.join("local-gpu.png");
        let mut cmd = std::process::Command::new(exe);
        cmd.arg("render")
            .arg(path)
            .args([
                "--backend",
                Backend::Gpu.name(),
                "--width",
                &width.to_string(),
            ])
            .args([
                "--height",
                &height.to_string(),
                "--samples",
                &s.samples.to_string(),
            ])
            .args([
                "--max-depth",
                &s.max_depth.to_string(),
                "--sampler",
                s.sampler.name(),
            ])
            .arg("-o")
            .arg(&out_png)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null());
        if let Some(a) = &self.cfg.adapter {
            cmd.args(["--adapter", a]);
        }
        let start = Instant::now();
        let status = cmd
            .status()
            .context("cannot run tessera render --backend gpu")?;
        let process_secs = start.elapsed().as_secs_f64();
        if !status.success() {
            bail!("tessera render --backend gpu failed ({status})");
        }
        eprintln!(
            "  farm       local GPU render: {local_secs:.3} s in this process ({:.1} Mrays/s), {process_secs:.3} s as a whole process",
            local_rays_per_s / 1e6
        );
        let mixed_cpu = self.cfg.mixed_cpu_workers;
        // The GPU workers alone, then beside the CPU workers.
        let cpu_counts = if mixed_cpu == 0 {
            vec![0]
        } else {
            vec![0, mixed_cpu]
        };
        let spec_of = |cpu_workers| farm::FarmSpec {
            cpu_workers,
            threads,
            gpu_workers: g,
            adapter: self.cfg.adapter.clone(),
            gpu_adapters: vec![],
        };
        let run = farm::RunSpec {
            exe,
            dir,
            name: "",
            scene: path,
            settings: &s,
            frames: (0, 0),
            tile,
        };
        let mut runs = vec![];
        let mut gpu_alone = None;
        for &cpu_workers in &cpu_counts {
            let name = format!("gpu{g}-cpu{cpu_workers}");
            let named = farm::RunSpec { name: &name, ..run };
            let (result, diff_bytes) = farm::timed_run(&named, &spec_of(cpu_workers), &local_srgb)?;
            let secs = result.seconds;
            let throughput = result.rays_per_second() / local_rays_per_s;
            let identical = diff_bytes == 0;
            let alone = *gpu_alone.get_or_insert(secs);
            eprintln!(
                "  farm       {g} GPU + {cpu_workers} CPU workers  {secs:>8.3} s  ({:.2}x the local process, {:.2}x the GPU workers alone)  GPU farm throughput {:.1}% of local  first result {}  {}",
                secs / process_secs,
                secs / alone,
                100.0 * throughput,
                fmt_secs(result.first_result_s),
                if cpu_workers > 0 {
                    "mixed: CPU and GPU samples".to_string()
                } else if identical {
                    "image identical to the local GPU render".to_string()
                } else {
                    format!("IMAGE DIFFERS from the local GPU render ({diff_bytes} bytes)")
                }
            );
            runs.push(Run {
                suite: "farm",
                scene: "resolution".into(),
                backend: Backend::Gpu,
                device: gpu.adapter().name.clone(),
                threads: cpu_workers * threads,
                settings: s,
                precision: Precision::F32,
                seconds: secs,
                gpu_seconds: None,
                rays: film.rays,
                error: None,
                image: format!("farm/frames-{name}/frame_0000.png"),
                extra: farm_columns(FarmColumns {
                    workers: cpu_workers,
                    gpu_workers: g,
                    threads,
                    tile,
                    local_secs: process_secs,
                    ceiling_secs: None,
                    speedup: Some(alone / secs),
                    efficiency: None,
                    identical: (cpu_workers == 0).then_some(identical),
                    result: &result,
                    local_rays_per_s,
                }),
            });
        }
        // With --repeat N: each farm renders the job N times, each right
        // after the local GPU render of it, so that one run's noise does
        // not decide whether the mixed farm kept up with the GPU alone.
        if self.cfg.repeat > 1 {
            let mut medians = vec![];
            for &cpu_workers in &cpu_counts {
                let name = format!("gpu{g}-cpu{cpu_workers}-repeat");
                let (run, spec) = (farm::RunSpec { name: &name, ..run }, spec_of(cpu_workers));
                let (jobs, diff_bytes) = farm::interleaved_runs(
                    &run,
                    &spec,
                    self.cfg.repeat as usize,
                    &local_srgb,
                    || {
                        let start = Instant::now();
                        gpu.render(
                            &frame,
                            WorkRegion::new(0, full, SampleRange::all(s.samples)),
                            &|_| {},
                        )?;
                        Ok(start.elapsed().as_secs_f64())
                    },
                )?;
                let mut secs: Vec<f64> = jobs.iter().map(|(_, j)| j.seconds).collect();
                let listed: Vec<String> = jobs
                    .iter()
                    .map(|(l, j)| {
                        format!(
                            "{:.3}/{}/{l:.3}",
                            j.seconds,
                            j.render_s.map_or("-".into(), |r| format!("{r:.3}"))
                        )
                    })
                    .collect();
                secs.sort_by(f64::total_cmp);
                let median = secs[secs.len() / 2];
                medians.push(median);
                // The GPU workers' throughput against the local render
                // timed just before each job (rays over first lease to last
                // result, against rays over the local call).
                let mut throughput: Vec<f64> = jobs
                    .iter()
                    .map(|(l, j)| j.rays_per_second() * l / film.rays.total() as f64)
                    .collect();
                throughput.sort_by(f64::total_cmp);
                eprintln!(
                    "  farm       {g} GPU + {cpu_workers} CPU workers, {} jobs on one warm farm (submit to done/first lease to last result/local GPU render s): {}; median {median:.3} s, {:.2}x the GPU workers alone, GPU farm throughput median {:.1}% of local{}",
                    jobs.len(),
                    listed.join(" "),
                    median / medians[0],
                    100.0 * throughput[throughput.len() / 2],
                    if cpu_workers > 0 {
                        String::new()
                    } else if diff_bytes == 0 {
                        "  image identical to the local GPU render".to_string()
                    } else {
                        format!("  IMAGE DIFFERS from the local GPU render ({diff_bytes} bytes)")
                    }
                );
            }
        }
        Ok(runs)
    }
}

/// `n` concurrent CPU renders of `threads` threads, each of 1/n of the
/// frame's samples: the best time a farm of n such workers could reach on
/// this machine (shared cores, memory bandwidth, turbo), with no farm.
fn machine_ceiling(
    frame: &PreparedFrame,
    s: &RenderSettings,
    n: usize,
    threads: usize,
) -> Result<f64> {
    let renderers = (0..n)
        .map(|_| CpuRenderer::new(Some(threads)))
        .collect::<Result<Vec<_>, _>>()?;
    let full = Rect::full(s.width, s.height);
    let total = s.samples as usize;
    let start = Instant::now();
    std::thread::scope(|scope| -> Result<()> {
        let handles: Vec<_> = renderers
            .iter()
            .enumerate()
            .filter_map(|(k, r)| {
                let range = SampleRange::new((k * total / n) as u32, ((k + 1) * total / n) as u32);
                (!range.is_empty()).then(|| {
                    scope.spawn(move || r.render(frame, WorkRegion::new(0, full, range), &|_| {}))
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
}

/// The farm suite's columns, the same set for every run.
struct FarmColumns<'a> {
    workers: usize,
    gpu_workers: usize,
    threads: usize,
    tile: u32,
    local_secs: f64,
    ceiling_secs: Option<f64>,
    speedup: Option<f64>,
    efficiency: Option<f64>,
    identical: Option<bool>,
    result: &'a farm::JobResult,
    local_rays_per_s: f64,
}

fn farm_columns(c: FarmColumns) -> Vec<(&'static str, String)> {
    // Ratios to 4 decimals; times to the microsecond, as `wall_s` (a quick
    // run's ceiling of a few ms at 4 decimals put its ratio 1.6% off).
    let f = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.4}"));
    let secs = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.6}"));
    vec![
        ("workers", c.workers.to_string()),
        ("gpu_workers", c.gpu_workers.to_string()),
        ("worker_threads", c.threads.to_string()),
        ("tile_size", c.tile.to_string()),
        ("local_wall_s", format!("{:.6}", c.local_secs)),
        ("ceiling_s", secs(c.ceiling_secs)),
        (
            "of_ceiling",
            f(c.ceiling_secs.map(|t| t / c.result.seconds)),
        ),
        ("speedup", f(c.speedup)),
        ("efficiency", f(c.efficiency)),
        (
            "bit_identical",
            c.identical.map_or(String::new(), |b| b.to_string()),
        ),
        ("first_result_s", secs(c.result.first_result_s)),
        ("render_s", secs(c.result.render_s)),
        (
            "throughput_vs_local",
            f((c.result.render_s.is_some())
                .then(|| c.result.rays_per_second() / c.local_rays_per_s)),
        ),
    ]
}
