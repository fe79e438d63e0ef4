//! The `farm` suite's machinery: a real coordinator and real workers, child
//! processes of this executable talking gRPC over loopback, driven through
//! the same CLI a user types (`coordinator`, `worker`, `workers`, `submit
//! --wait`, `fetch`).

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use tracer_core::scene::RenderSettings;

/// How long the farm may take to come up (listen, register workers).
const START_TIMEOUT: Duration = Duration::from_secs(60);
/// How long one job may take before the suite gives up.
const JOB_TIMEOUT: Duration = Duration::from_secs(3600);
/// The niceness of CPU workers that share the host with GPU workers.
const CPU_WORKER_NICE_BESIDE_GPU: i32 = 10;

/// A child process that is killed and reaped when dropped, so that no exit
/// path of the benchmark (error, panic, Ctrl-C unwinding) leaves a
/// coordinator or worker running.
pub struct ChildGuard {
    what: String,
    log: PathBuf,
    child: Child,
}

impl ChildGuard {
    /// The process id.
    pub fn id(&self) -> u32 {
        self.child.id()
    }

    /// `Err` with the end of its log if the process has exited.
    pub fn check_alive(&mut self) -> Result<()> {
        if let Some(status) = self.child.try_wait()? {
            bail!(
                "{} exited ({status}); log {}:\n{}",
                self.what,
                self.log.display(),
                tail(&self.log)
            );
        }
        Ok(())
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn tail(log: &Path) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(20)..].join("\n")
}

/// A command for a farm process. On Linux the child is also killed by the
/// kernel if this process dies without unwinding (SIGKILL, SIGTERM), which
/// no drop guard can cover.
pub fn farm_command(exe: &Path) -> Command {
    #[allow(unused_mut)]
    let mut c = Command::new(exe);
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::process::CommandExt as _;
        // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
        unsafe {
            c.pre_exec(|| {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
    }
    c
}

fn log_file(path: &Path) -> Result<std::fs::File> {
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .with_context(|| format!("cannot open {}", path.display()))
}

/// Starts `tessera coordinator` on a free loopback port with its state in
/// `data`, its log in `log` and `extra` arguments (TLS, tokens, limits);
/// returns it with the address it bound.
pub fn start_coordinator(
    exe: &Path,
    data: &Path,
    log: &Path,
    extra: &[std::ffi::OsString],
) -> Result<(ChildGuard, String)> {
    let mut child = farm_command(exe)
        .args(["coordinator", "--listen", "127.0.0.1:0", "--data"])
        .arg(data)
        .args(extra)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(log_file(log)?)
        .spawn()
        .with_context(|| format!("cannot start {} coordinator", exe.display()))?;
    let stdout = child.stdout.take().expect("stdout is piped");
    let mut coordinator = ChildGuard {
        what: "the coordinator".into(),
        log: log.to_path_buf(),
        child,
    };
    // The coordinator prints its bound address on stdout; read it on a
    // thread so a coordinator that never prints cannot hang the bench.
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut r = BufReader::new(stdout);
        let mut line = String::new();
        let _ = r.read_line(&mut line);
        let _ = tx.send(line);
        // Keep draining so the coordinator never writes into a closed pipe.
        let _ = std::io::copy(&mut r, &mut std::io::sink());
    });
    let line = match rx.recv_timeout(START_TIMEOUT) {
        Ok(line) => line,
        Err(_) => bail!("the coordinator did not report its address within {START_TIMEOUT:?}"),
    };
    let Some(addr) = line.trim().strip_prefix("listening on ") else {
        coordinator.check_alive()?;
        bail!("unexpected first line from the coordinator: {line:?}");
    };
    Ok((coordinator, addr.to_string()))
}

/// The workers of a bench farm.
#[derive(Clone, Debug, Default)]
pub struct FarmSpec {
    pub cpu_workers: usize,
    /// CPU threads of each CPU worker.
    pub threads: usize,
    pub gpu_workers: usize,
    /// GPU adapter of the GPU workers that have none in `gpu_adapters`.
    pub adapter: Option<String>,
    /// GPU adapter (index or name, as `--adapter` takes) of each GPU
    /// worker in turn: one worker per GPU. An index may repeat (workers
    /// sharing a GPU); workers past its end take `adapter`.
    pub gpu_adapters: Vec<String>,
}

impl FarmSpec {
    /// The adapter of GPU worker `i` (from 0), if one is named.
    fn gpu_adapter(&self, i: usize) -> Option<&str> {
        self.gpu_adapters
            .get(i)
            .or(self.adapter.as_ref())
            .map(String::as_str)
    }
}

/// A finished bench job: its id, the wall time from submission to the job's
/// end as `tessera submit --wait` saw it, and the coordinator's timeline.
#[derive(Clone, Debug)]
pub struct JobResult {
    pub job: String,
    pub seconds: f64,
    /// Submission to the first merged result.
    pub first_result_s: Option<f64>,
    /// First lease to last merged result: the farm's rendering time.
    pub render_s: Option<f64>,
    pub rays: u64,
}

impl JobResult {
    /// Rays per second from the first lease to the last result.
    pub fn rays_per_second(&self) -> f64 {
        self.render_s
            .map_or(0.0, |t| self.rays as f64 / t.max(1e-9))
    }
}

/// A coordinator and its workers; dropping it stops them all.
pub struct Farm {
    exe: PathBuf,
    pub url: String,
    // Workers first: they are dropped (killed) before the coordinator.
    workers: Vec<ChildGuard>,
    coordinator: ChildGuard,
}

impl Farm {
    /// Starts a coordinator on a free loopback port with its state in
    /// `data`, and the workers of `spec`; returns once every worker is
    /// registered. Logs go to `logs`.STEM.log.
    pub fn start(exe: &Path, data: &Path, logs: &Path, spec: &FarmSpec) -> Result<Farm> {
        let (coordinator, addr) =
            start_coordinator(exe, data, &logs.with_extension("coordinator.log"), &[])?;
        let url = format!("http://{addr}");
        let mut farm = Farm {
            exe: exe.to_path_buf(),
            url,
            workers: vec![],
            coordinator,
        };
        let workers = spec.cpu_workers + spec.gpu_workers;
        for i in 1..=workers {
            let log = logs.with_extension(format!("worker-{i}.log"));
            let mut cmd = farm_command(exe);
            cmd.args(["worker", "--coordinator", &farm.url]);
            if i <= spec.gpu_workers {
                cmd.args([
                    "--backend",
                    tracer_core::render::Backend::Gpu.name(),
                    "--name",
                    &format!("bench-gpu-{i}"),
                ]);
                if let Some(a) = spec.gpu_adapter(i - 1) {
                    cmd.args(["--adapter", a]);
                }
            } else {
                cmd.args(["--threads", &spec.threads.to_string()])
                    .args(["--name", &format!("bench-{i}")]);
                if spec.gpu_workers > 0 {
                    // Beside a GPU worker on one host, as the docs advise:
                    // its feeding and the coordinator's intake come first.
                    cmd.args(["--nice", &CPU_WORKER_NICE_BESIDE_GPU.to_string()]);
                }
            }
            // A cache of its own per worker and run: nothing left from another run.
            cmd.arg("--cache")
                .arg(logs.with_extension(format!("cache-{i}")));
            // Each unit's render time in the log, for scripts/farm-timeline.py.
            cmd.args(["--log-format", "json"])
                .env("RUST_LOG", "info,tessera_worker=debug");
            let child = cmd
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(log_file(&log)?)
                .spawn()
                .with_context(|| format!("cannot start worker {i}"))?;
            farm.workers.push(ChildGuard {
                what: format!("worker {i}"),
                log,
                child,
            });
        }
        farm.wait_for_workers(workers)?;
        Ok(farm)
    }

    fn cli(&self, args: &[&str]) -> Command {
        let mut c = farm_command(&self.exe);
        c.args(args)
            .args(["--coordinator", &self.url])
            .stdin(Stdio::null());
        c
    }

    /// Polls `tessera workers` until `n` workers are listed.
    fn wait_for_workers(&mut self, n: usize) -> Result<()> {
        let start = Instant::now();
        loop {
            self.coordinator.check_alive()?;
            for w in &mut self.workers {
                w.check_alive()?;
            }
            let out = self
                .cli(&["workers"])
                .output()
                .context("cannot run tessera workers")?;
            // A header line, then one line per worker.
            let listed = String::from_utf8_lossy(&out.stdout)
                .lines()
                .count()
                .saturating_sub(1);
            if out.status.success() && listed >= n {
                return Ok(());
            }
            if start.elapsed() > START_TIMEOUT {
                bail!("only {listed} of {n} workers registered within {START_TIMEOUT:?}");
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Renders a small job first, as a farm that has been running has: its
    /// workers' speeds are measured and the scene is in their caches, so
    /// the timed job sees a warm farm. A quarter of the frame's width and
    /// height, at most 16 samples.
    pub fn warm_up(
        &mut self,
        scene: &Path,
        settings: &RenderSettings,
        tile_size: u32,
        log: &Path,
    ) -> Result<()> {
        let small = RenderSettings {
            width: (settings.width / 4).max(1),
            height: (settings.height / 4).max(1),
            samples: settings.samples.min(16),
            ..*settings
        };
        self.submit_and_wait(scene, &small, (0, 0), tile_size, log)
            .map(|_| ())
            .context("the warm-up job failed")
    }

    /// Submits `scene`'s `frames` (first, last, inclusive) with `settings`
    /// as overrides and waits for the job (`tessera submit --wait`);
    /// returns the job id and the wall time from submission to the job's
    /// end. Fails, rather than hangs, if the coordinator or a worker dies
    /// or the job outlasts `JOB_TIMEOUT`.
    pub fn submit_and_wait(
        &mut self,
        scene: &Path,
        settings: &RenderSettings,
        frames: (u32, u32),
        tile_size: u32,
        log: &Path,
    ) -> Result<JobResult> {
        let scene_arg = scene.to_string_lossy();
        let (w, h, s, d) = (
            settings.width.to_string(),
            settings.height.to_string(),
            settings.samples.to_string(),
            settings.max_depth.to_string(),
        );
        let tile = tile_size.to_string();
        let frames = format!("{}..{}", frames.0, frames.1);
        let args = [
            "submit",
            &scene_arg,
            "--frames",
            &frames,
            "--width",
            &w,
            "--height",
            &h,
            "--samples",
            &s,
            "--max-depth",
            &d,
            "--sampler",
            settings.sampler.name(),
            "--tile-size",
            &tile,
            "--wait",
        ];
        let start = Instant::now();
        // stdout (the job id) is a few bytes; progress goes to the log, so no pipe can fill up.
        let child = self
            .cli(&args)
            .stdout(Stdio::piped())
            .stderr(log_file(log)?)
            .spawn()
            .context("cannot run tessera submit")?;
        let mut submit = ChildGuard {
            what: "tessera submit --wait".into(),
            log: log.to_path_buf(),
            child,
        };
        let mut last_check = Instant::now();
        let status = loop {
            if let Some(status) = submit.child.try_wait()? {
                break status;
            }
            if last_check.elapsed() > Duration::from_millis(100) {
                self.coordinator.check_alive()?;
                for w in &mut self.workers {
                    w.check_alive()?;
                }
                if start.elapsed() > JOB_TIMEOUT {
                    bail!("the job did not finish within {JOB_TIMEOUT:?}");
                }
                last_check = Instant::now();
            }
            std::thread::sleep(Duration::from_millis(2));
        };
        let secs = start.elapsed().as_secs_f64();
        let mut stdout = String::new();
        if let Some(mut out) = submit.child.stdout.take() {
            std::io::Read::read_to_string(&mut out, &mut stdout)
                .context("cannot read tessera submit's output")?;
        }
        if !status.success() {
            bail!(
                "tessera submit --wait failed ({status}): {stdout}\n{}",
                tail(log)
            );
        }
        let id = stdout
            .lines()
            .next()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .context("tessera submit printed no job id")?;
        let status = self
            .cli(&["status", id, "--json"])
            .output()
            .context("cannot run tessera status")?;
        if !status.status.success() {
            bail!(
                "tessera status failed ({}): {}",
                status.status,
                String::from_utf8_lossy(&status.stderr)
            );
        }
        let j: serde_json::Value = serde_json::from_slice(&status.stdout)
            .context("tessera status --json printed no JSON")?;
        let ms = |k: &str| j[k].as_i64();
        let between = |a: Option<i64>, b: Option<i64>| match (a, b) {
            (Some(a), Some(b)) => Some((b - a).max(0) as f64 / 1000.0),
            _ => None,
        };
        let rays = ["primary", "shadow", "reflection", "refraction"]
            .iter()
            .map(|k| j["rays"][k].as_u64().unwrap_or(0))
            .sum();
        Ok(JobResult {
            job: id.to_string(),
            seconds: secs,
            first_result_s: between(ms("submitted_unix_ms"), ms("first_result_unix_ms")),
            render_s: between(ms("first_lease_unix_ms"), ms("last_result_unix_ms")),
            rays,
        })
    }

    /// Fetches the job's frames into `dir`; returns, for each frame from
    /// `first` on, how many of its 8-bit sRGB bytes differ from the image
    /// in `expected` (all of them if the size differs).
    pub fn frames_differ(
        &self,
        job: &str,
        dir: &Path,
        first: u32,
        size: (u32, u32),
        expected: &[&[u8]],
    ) -> Result<Vec<usize>> {
        let out = self
            .cli(&["fetch", job, "-o", &dir.to_string_lossy()])
            .output()
            .context("cannot run tessera fetch")?;
        if !out.status.success() {
            bail!(
                "tessera fetch failed ({}): {}",
                out.status,
                String::from_utf8_lossy(&out.stderr)
            );
        }
        let mut diffs = Vec::with_capacity(expected.len());
        for (frame, expected) in (first..).zip(expected) {
            let file = dir.join(format!("frame_{frame:04}.png"));
            let img = image::open(&file)
                .with_context(|| format!("cannot read the fetched frame {}", file.display()))?
                .to_rgb8();
            diffs.push(if img.dimensions() != size {
                img.as_raw().len().max(expected.len())
            } else {
                img.as_raw()
                    .iter()
                    .zip(*expected)
                    .filter(|(a, b)| a != b)
                    .count()
            });
        }
        Ok(diffs)
    }
}

/// One timed farm run of the bench: where and what.
pub struct RunSpec<'a> {
    pub exe: &'a Path,
    /// The suite's folder: `data-NAME` (removed after), `run-NAME.*.log`,
    /// `frames-NAME/`.
    pub dir: &'a Path,
    pub name: &'a str,
    pub scene: &'a Path,
    pub settings: &'a RenderSettings,
    /// First and last frame, inclusive: (0, 0) is the still frame.
    pub frames: (u32, u32),
    pub tile: u32,
}

/// One warm farm of `spec`, the same job submitted `pairs` times, each
/// right after `local` timed the local render of it: each ratio is taken
/// seconds apart, so the machine's drift between runs (a local render
/// took 4.3-5.7 s across calls on the H200 box) cancels. Returns (local
/// seconds, farm seconds) per pair and how many 8-bit bytes of the last
/// job's frame differ from `expected`.
pub fn interleaved_runs(
    run: &RunSpec,
    spec: &FarmSpec,
    pairs: usize,
    expected: &[u8],
    mut local: impl FnMut() -> Result<f64>,
) -> Result<(Vec<(f64, JobResult)>, usize)> {
    with_warm_farm(run, spec, |farm, logs| {
        let mut times = Vec::with_capacity(pairs);
        let mut last = None;
        for i in 0..pairs {
            let local_secs = local()?;
            let result = farm.submit_and_wait(
                run.scene,
                run.settings,
                run.frames,
                run.tile,
                &logs.with_extension(format!("submit-{i}.log")),
            )?;
            last = Some(result.job.clone());
            times.push((local_secs, result));
        }
        let job = last.context("no pair was run")?;
        Ok((times, frames_diff(run, farm, &job, &[expected])?[0]))
    })
}

/// Starts the farm of `spec`, renders the warm-up job, then the timed job,
/// and fetches its frame; returns the job and how many 8-bit bytes of its
/// first frame differ from `expected`.
pub fn timed_run(run: &RunSpec, spec: &FarmSpec, expected: &[u8]) -> Result<(JobResult, usize)> {
    let (result, diffs) = timed_frames_run(run, spec, &[expected])?;
    Ok((result, diffs[0]))
}

/// [`timed_run`] for a job of several frames: `expected` has an image per
/// frame of `run.frames`, and each frame's count of differing bytes is
/// returned.
pub fn timed_frames_run(
    run: &RunSpec,
    spec: &FarmSpec,
    expected: &[&[u8]],
) -> Result<(JobResult, Vec<usize>)> {
    with_warm_farm(run, spec, |farm, logs| {
        let result = farm.submit_and_wait(
            run.scene,
            run.settings,
            run.frames,
            run.tile,
            &logs.with_extension("submit.log"),
        )?;
        let diffs = frames_diff(run, farm, &result.job, expected)?;
        Ok((result, diffs))
    })
}

/// Starts the farm of `spec` and renders the warm-up job (as a farm in
/// service would have), then runs `f` on it with the logs' base path. The
/// farm's processes are stopped on success and on error alike (drop); its
/// data folder is removed after a success (kept to look at after a
/// failure).
fn with_warm_farm<T>(
    run: &RunSpec,
    spec: &FarmSpec,
    f: impl FnOnce(&mut Farm, &Path) -> Result<T>,
) -> Result<T> {
    let data = run.dir.join(format!("data-{}", run.name));
    let _ = std::fs::remove_dir_all(&data);
    let logs = run.dir.join(format!("run-{}", run.name));
    let outcome = {
        let mut farm = Farm::start(run.exe, &data, &logs, spec)?;
        farm.warm_up(
            run.scene,
            run.settings,
            run.tile,
            &logs.with_extension("warm-up.log"),
        )?;
        f(&mut farm, &logs)?
    };
    let _ = std::fs::remove_dir_all(&data);
    Ok(outcome)
}

/// How many 8-bit bytes of each of `job`'s frames, fetched, differ from
/// its image in `expected` (the first frames of the job, as many as there
/// are images).
fn frames_diff(run: &RunSpec, farm: &Farm, job: &str, expected: &[&[u8]]) -> Result<Vec<usize>> {
    let fetched = run.dir.join(format!("frames-{}", run.name));
    let s = run.settings;
    farm.frames_differ(job, &fetched, run.frames.0, (s.width, s.height), expected)
}
