//! The `scale` suite (issue 38): N virtual workers against a real
//! coordinator process, to measure the coordinator, not rendering.
//!
//! Each virtual worker is what a real one is to the coordinator: its own
//! TLS connection (its own HTTP/2 session), the worker token, `Register`,
//! a heartbeat every interval naming its held leases, long-polled
//! `LeaseWork` and `SubmitResult`. It does not render: a result is the
//! leased tile at the leased sample count with black pixels (valid, and
//! the smallest encoding), sent back at once or after `--virtual-unit-ms`.
//! The job is a real `tessera submit` of a 1024x1024 frame in 8x8 tiles
//! of one sample each (1 M units), so the run is bounded by time, not by
//! the job, and cancelled at the end.
//!
//! Measured, from the bench's side (client-side lease latency includes
//! the bench process's own scheduling: it shares the machine):
//! - the time from the submit command's start until 99% and 100% of the
//!   workers have received a unit;
//! - leases granted and units completed per second in the steady phase
//!   (from 99% busy to the vanishing);
//! - lease latency p50/p99 (request to answer, of requests granted units);
//! - the coordinator's CPU (cores) in the steady phase and its RSS per
//!   connected worker (connected and idle, less the RSS before any);
//! - 10% of the workers vanishing at once (connections dropped, leases
//!   held): units per second in the lease timeout after, and once their
//!   leases have expired and gone to the others.

use std::collections::HashSet;
use std::ffi::OsString;
use std::path::Path;
use std::process::Stdio;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use serde_json::json;
use tessera_proto::VersionStamp;
use tessera_proto::pb;
use tessera_proto::pb::worker_service_client::WorkerServiceClient;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

use super::farm::{farm_command, start_coordinator};
use super::{Bench, Run};
use crate::cli::output::rss_kib;

/// The coordinator's lease timeout in the run: a vanished worker's leases
/// go to the others this long after its last heartbeat.
const LEASE_TIMEOUT_S: f64 = 5.0;
/// The job: a frame this size in tiles of TILE pixels, one sample a unit.
const FRAME: u32 = 1024;
const TILE: u32 = 8;
const SAMPLES: u32 = 64;
/// Connections opened at once while the workers connect.
const CONNECT_CONCURRENCY: usize = 64;

type Client = WorkerServiceClient<InterceptedService<Channel, VersionStamp>>;

/// One size's figures.
#[derive(Clone, Debug)]
pub struct ScaleReport {
    pub workers: usize,
    pub connect_s: f64,
    pub busy_99_s: Option<f64>,
    pub busy_all_s: Option<f64>,
    pub leases_per_s: f64,
    pub units_per_s: f64,
    pub results_per_s: f64,
    pub lease_p50_ms: f64,
    pub lease_p99_ms: f64,
    pub coordinator_cores: f64,
    pub bench_cores: f64,
    pub rss_before_kib: u64,
    pub rss_connected_kib: u64,
    pub rss_peak_kib: u64,
    pub rss_per_worker_kib: f64,
    pub vanished: usize,
    /// Units per second in the lease timeout after the vanishing, and after it.
    pub units_per_s_during_timeout: f64,
    pub units_per_s_after_timeout: f64,
    pub results_rejected: u64,
}

impl ScaleReport {
    fn json(&self) -> serde_json::Value {
        json!({
            "workers": self.workers,
            "connect_s": self.connect_s,
            "busy_99_s": self.busy_99_s,
            "busy_all_s": self.busy_all_s,
            "leases_per_s": self.leases_per_s,
            "units_per_s": self.units_per_s,
            "results_per_s": self.results_per_s,
            "lease_p50_ms": self.lease_p50_ms,
            "lease_p99_ms": self.lease_p99_ms,
            "coordinator_cores": self.coordinator_cores,
            "bench_cores": self.bench_cores,
            "rss_before_kib": self.rss_before_kib,
            "rss_connected_kib": self.rss_connected_kib,
            "rss_peak_kib": self.rss_peak_kib,
            "rss_per_worker_kib": self.rss_per_worker_kib,
            "vanished": self.vanished,
            "units_per_s_during_timeout": self.units_per_s_during_timeout,
            "units_per_s_after_timeout": self.units_per_s_after_timeout,
            "results_rejected": self.results_rejected,
        })
    }
}

/// What the workers count, shared.
#[derive(Default)]
struct Counters {
    leases: AtomicU64,
    units: AtomicU64,
    results: AtomicU64,
    rejected: AtomicU64,
    /// Workers that have received a unit.
    busy: AtomicU64,
    /// Lease latencies (µs) of requests granted units, while `recording`.
    latencies: Mutex<Vec<u32>>,
    recording: AtomicBool,
}

impl Bench {
    /// `scale`: a real coordinator (TLS, tokens) against each
    /// `--virtual-workers` count in turn. Writes scale.json; no render runs.
    pub(super) fn suite_scale(&self) -> Result<Vec<Run>> {
        let exe = std::env::current_exe().context("cannot find this executable")?;
        let dir = self.cfg.out.join("scale");
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        raise_open_files_limit();
        let (scene, _) = self.scene("resolution.toml")?;
        let mut reports = vec![];
        for &n in &self.cfg.virtual_workers {
            let r = run_one(&exe, &dir.join(format!("n{n}")), &scene, n, &self.cfg)?;
            eprintln!(
                "  scale      {n:>5} workers: connect {:.1} s; busy 99% {} / all {}; {:.0} leases/s, {:.0} units/s ({:.0} results/s); lease p50 {:.1} ms p99 {:.1} ms; coordinator {:.2} cores, bench {:.2} cores; RSS {:.0} MiB before, {:.0} MiB connected ({:.1} KiB a worker), peak {:.0} MiB; {} vanish: {:.0} units/s within the lease timeout, {:.0} after",
                r.connect_s,
                secs_or_never(r.busy_99_s),
                secs_or_never(r.busy_all_s),
                r.leases_per_s,
                r.units_per_s,
                r.results_per_s,
                r.lease_p50_ms,
                r.lease_p99_ms,
                r.coordinator_cores,
                r.bench_cores,
                r.rss_before_kib as f64 / 1024.0,
                r.rss_connected_kib as f64 / 1024.0,
                r.rss_per_worker_kib,
                r.rss_peak_kib as f64 / 1024.0,
                r.vanished,
                r.units_per_s_during_timeout,
                r.units_per_s_after_timeout,
            );
            reports.push(r);
        }
        let file = self.cfg.out.join("scale.json");
        let body = json!({
            "cpu": self.cpu_name,
            "cores": std::thread::available_parallelism().map_or(0, |n| n.get()),
            "lease_timeout_s": LEASE_TIMEOUT_S,
            "unit_ms": self.cfg.virtual_unit_ms,
            "runs": reports.iter().map(ScaleReport::json).collect::<Vec<_>>(),
        });
        std::fs::write(&file, serde_json::to_string_pretty(&body)?)
            .with_context(|| format!("cannot write {}", file.display()))?;
        eprintln!("  scale      figures in {}", file.display());
        Ok(vec![])
    }
}

fn secs_or_never(s: Option<f64>) -> String {
    s.map_or_else(|| "never".into(), |s| format!("{s:.2} s"))
}

/// Each virtual worker holds a socket, and the coordinator one per worker:
/// the default soft limit (often 1,024) is too few.
fn raise_open_files_limit() {
    // SAFETY: getrlimit/setrlimit with a valid pointer to a local.
    unsafe {
        let mut l = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut l) == 0 && l.rlim_cur < l.rlim_max {
            l.rlim_cur = l.rlim_max;
            libc::setrlimit(libc::RLIMIT_NOFILE, &l);
        }
    }
}

/// A process's CPU time (user + system), in seconds.
fn cpu_seconds(pid: &str) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    // Fields after the command name, which is in parentheses.
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // SAFETY: sysconf has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64;
    // utime and stime are fields 14 and 15 (1-based), 12 and 13 here.
    (ticks(11) + ticks(12)) / hz
}

fn run_one(
    exe: &Path,
    dir: &Path,
    scene: &Path,
    n: usize,
    cfg: &super::Config,
) -> Result<ScaleReport> {
    std::fs::create_dir_all(dir)?;
    let tls = dir.join("tls");
    let cert = farm_command(exe)
        .args(["cert", "--tokens", "--name", "127.0.0.1", "--out"])
        .arg(&tls)
        .stdin(Stdio::null())
        .output()
        .context("cannot run tessera cert")?;
    if !cert.status.success() {
        bail!(
            "tessera cert failed ({}): {}",
            cert.status,
            String::from_utf8_lossy(&cert.stderr)
        );
    }
    let lease_timeout = LEASE_TIMEOUT_S.to_string();
    // Room for every worker's connection from one address (the bench's).
    let connections = (2 * n + 256).to_string();
    let args: Vec<OsString> = vec![
        "--tls-cert".into(),
        tls.join("coordinator.pem").into(),
        "--tls-key".into(),
        tls.join("coordinator.key").into(),
        "--client-token-file".into(),
        tls.join("client.token").into(),
        "--worker-token-file".into(),
        tls.join("worker.token").into(),
        "--lease-timeout".into(),
        lease_timeout.into(),
        "--max-connections".into(),
        connections.clone().into(),
        "--max-connections-per-peer".into(),
        connections.into(),
    ];
    let (mut coordinator, addr) =
        start_coordinator(exe, &dir.join("data"), &dir.join("coordinator.log"), &args)?;
    let url = format!("https://{addr}");
    let pid = coordinator.id();
    let ca = std::fs::read(tls.join("ca.pem"))?;
    let token = std::fs::read_to_string(tls.join("worker.token"))?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let submit = |coordinator: &mut super::farm::ChildGuard| -> Result<String> {
        coordinator.check_alive()?;
        let out = farm_command(exe)
            .arg("submit")
            .arg(scene)
            .args(["--coordinator", &url, "--ca"])
            .arg(tls.join("ca.pem"))
            .arg("--token-file")
            .arg(tls.join("client.token"))
            .args([
                "--width",
                &FRAME.to_string(),
                "--height",
                &FRAME.to_string(),
            ])
            .args(["--samples", &SAMPLES.to_string(), "--samples-per-unit", "1"])
            .args(["--tile-size", &TILE.to_string(), "--json"])
            .stdin(Stdio::null())
            .output()
            .context("cannot run tessera submit")?;
        if !out.status.success() {
            bail!(
                "tessera submit failed: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        let v: serde_json::Value =
            serde_json::from_slice(&out.stdout).context("tessera submit --json printed no JSON")?;
        Ok(v["job_id"].as_str().unwrap_or_default().to_string())
    };
    let cancel = |job: &str| {
        let _ = farm_command(exe)
            .args(["cancel", job, "--coordinator", &url, "--ca"])
            .arg(tls.join("ca.pem"))
            .arg("--token-file")
            .arg(tls.join("client.token"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status();
    };
    rt.block_on(drive(
        Drive {
            url: url.clone(),
            ca,
            token: token.trim().to_string(),
            n,
            pid,
            seconds: cfg.scale_seconds,
            unit_ms: cfg.virtual_unit_ms,
        },
        || submit(&mut coordinator),
        cancel,
    ))
}

struct Drive {
    url: String,
    ca: Vec<u8>,
    token: String,
    n: usize,
    pid: u32,
    seconds: f64,
    unit_ms: u64,
}

async fn drive(
    d: Drive,
    submit: impl FnOnce() -> Result<String>,
    cancel: impl FnOnce(&str),
) -> Result<ScaleReport> {
    let stamp = VersionStamp::with_token(Some(&d.token))?;
    let endpoint = tessera_proto::transport::endpoint(&d.url, Some(&d.ca))?;
    let (rss_before, _) = rss_kib(d.pid);

    // Connect and register every worker (a few at a time: a burst of
    // thousands of handshakes would only measure the accept queue).
    let start = Instant::now();
    let gate = Arc::new(tokio::sync::Semaphore::new(CONNECT_CONCURRENCY));
    let mut joins = tokio::task::JoinSet::new();
    for i in 0..d.n {
        let (endpoint, stamp, gate) = (endpoint.clone(), stamp.clone(), gate.clone());
        joins.spawn(async move {
            let _permit = gate.acquire_owned().await?;
            let channel = endpoint.connect().await.map_err(|e| {
                anyhow::anyhow!(
                    "virtual worker {i} cannot connect: {}",
                    tessera_proto::transport::error_chain(&e)
                )
            })?;
            let mut client: Client = WorkerServiceClient::with_interceptor(channel, stamp);
            let r = client
                .register(pb::RegisterRequest {
                    name: format!("virtual-{i}"),
                    capabilities: Some(pb::Capabilities {
                        threads: 1,
                        backend: pb::Backend::Cpu as i32,
                        version: env!("CARGO_PKG_VERSION").into(),
                        // Each its own host, as a farm's workers are.
                        host_id: format!("virtual-host-{i}"),
                        ..Default::default()
                    }),
                })
                .await
                .with_context(|| format!("virtual worker {i} cannot register"))?
                .into_inner();
            anyhow::Ok((client, r))
        });
    }
    let mut sessions = vec![];
    while let Some(j) = joins.join_next().await {
        sessions.push(j??);
    }
    let connect_s = start.elapsed().as_secs_f64();
    // Let the registrations' first heartbeats settle before reading RSS.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let (rss_connected, _) = rss_kib(d.pid);

    let counters = Arc::new(Counters::default());
    let stop = Arc::new(AtomicBool::new(false));
    let mut handles = vec![];
    let mut first_units = vec![];
    for (client, reg) in sessions {
        let first = Arc::new(Mutex::new(None::<Instant>));
        first_units.push(first.clone());
        let held = Arc::new(Mutex::new(HashSet::<String>::new()));
        let heartbeat = Duration::from_millis(reg.heartbeat_interval_ms.clamp(50, 60_000) as u64);
        let hb = tokio::spawn(heartbeats(
            client.clone(),
            reg.worker_id.clone(),
            held.clone(),
            heartbeat,
            stop.clone(),
        ));
        let work = tokio::spawn(work(
            client,
            reg.worker_id,
            held,
            first,
            counters.clone(),
            stop.clone(),
            d.unit_ms,
        ));
        handles.push((hb, work));
    }

    let submitted = Instant::now();
    let job = tokio::task::block_in_place(submit)?;
    let since = |t: Instant| t.saturating_duration_since(submitted).as_secs_f64();
    let busy_at = |share: f64| -> Option<f64> {
        let mut times: Vec<Instant> = first_units
            .iter()
            .filter_map(|f| *f.lock().expect("first-unit lock"))
            .collect();
        let need = (share * d.n as f64).ceil() as usize;
        if times.len() < need {
            return None;
        }
        times.sort();
        Some(since(times[need - 1]))
    };

    // Until 99% are busy (or a third of the run), then the steady phase.
    let deadline = submitted + Duration::from_secs_f64(d.seconds);
    let steady_from = loop {
        let busy = counters.busy.load(Ordering::Relaxed) as f64;
        if busy >= 0.99 * d.n as f64 || submitted.elapsed().as_secs_f64() > d.seconds / 3.0 {
            break Instant::now();
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    counters.recording.store(true, Ordering::Relaxed);
    let snapshot = |c: &Counters| {
        (
            Instant::now(),
            c.leases.load(Ordering::Relaxed),
            c.units.load(Ordering::Relaxed),
            c.results.load(Ordering::Relaxed),
            cpu_seconds(&d.pid.to_string()),
            cpu_seconds("self"),
        )
    };
    let s0 = snapshot(&counters);
    // The steady phase: until 60% of the run is over.
    let vanish_at = submitted + Duration::from_secs_f64(0.6 * d.seconds);
    tokio::time::sleep_until(vanish_at.max(steady_from + Duration::from_secs(2)).into()).await;
    let s1 = snapshot(&counters);
    counters.recording.store(false, Ordering::Relaxed);
    let dt = s1.0.duration_since(s0.0).as_secs_f64().max(1e-9);
    let rate = |a: u64, b: u64, dt: f64| (b - a) as f64 / dt;

    // A tenth of the workers vanish: their tasks end mid-lease, dropping
    // their connections; their leases expire after the lease timeout.
    let vanished = d.n / 10;
    for (hb, work) in handles.drain(..vanished) {
        hb.abort();
        work.abort();
    }
    let v0 = snapshot(&counters);
    tokio::time::sleep(Duration::from_secs_f64(LEASE_TIMEOUT_S + 1.0)).await;
    let v1 = snapshot(&counters);
    let after = deadline.max(Instant::now() + Duration::from_secs(3));
    tokio::time::sleep_until(after.into()).await;
    let v2 = snapshot(&counters);
    let (_, rss_peak) = rss_kib(d.pid);

    stop.store(true, Ordering::Relaxed);
    tokio::task::block_in_place(|| cancel(&job));
    for (hb, work) in handles {
        hb.abort();
        work.abort();
    }
    let mut lat = std::mem::take(&mut *counters.latencies.lock().expect("latency lock"));
    lat.sort_unstable();
    let pct = |p: f64| {
        lat.get(((p * lat.len() as f64) as usize).min(lat.len().saturating_sub(1)))
            .map_or(f64::NAN, |&us| us as f64 / 1e3)
    };
    Ok(ScaleReport {
        workers: d.n,
        connect_s,
        busy_99_s: busy_at(0.99),
        busy_all_s: busy_at(1.0),
        leases_per_s: rate(s0.1, s1.1, dt),
        units_per_s: rate(s0.2, s1.2, dt),
        results_per_s: rate(s0.3, s1.3, dt),
        lease_p50_ms: pct(0.5),
        lease_p99_ms: pct(0.99),
        coordinator_cores: (s1.4 - s0.4) / dt,
        bench_cores: (s1.5 - s0.5) / dt,
        rss_before_kib: rss_before,
        rss_connected_kib: rss_connected,
        rss_peak_kib: rss_peak,
        rss_per_worker_kib: rss_connected.saturating_sub(rss_before) as f64 / d.n.max(1) as f64,
        vanished,
        units_per_s_during_timeout: rate(v0.2, v1.2, v1.0.duration_since(v0.0).as_secs_f64()),
        units_per_s_after_timeout: rate(
            v1.2,
            v2.2,
            v2.0.duration_since(v1.0).as_secs_f64().max(1e-9),
        ),
        results_rejected: counters.rejected.load(Ordering::Relaxed),
    })
}

/// A virtual worker's heartbeats: its held leases, every interval.
async fn heartbeats(
    mut client: Client,
    worker_id: String,
    held: Arc<Mutex<HashSet<String>>>,
    every: Duration,
    stop: Arc<AtomicBool>,
) {
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    while !stop.load(Ordering::Relaxed) {
        tick.tick().await;
        let leases = held
            .lock()
            .expect("held lock")
            .iter()
            .map(|l| pb::LeaseProgress {
                lease_id: l.clone(),
                samples_done: 0,
            })
            .collect();
        let _ = client
            .heartbeat(pb::HeartbeatRequest {
                worker_id: worker_id.clone(),
                leases,
            })
            .await;
    }
}

/// A virtual worker's loop: lease one unit (long poll), answer it with a
/// black tile at the leased sample count, again.
async fn work(
    mut client: Client,
    worker_id: String,
    held: Arc<Mutex<HashSet<String>>>,
    first: Arc<Mutex<Option<Instant>>>,
    c: Arc<Counters>,
    stop: Arc<AtomicBool>,
    unit_ms: u64,
) {
    while !stop.load(Ordering::Relaxed) {
        let asked = Instant::now();
        let Ok(r) = client
            .lease_work(pb::LeaseWorkRequest {
                worker_id: worker_id.clone(),
                max_units: 1,
                wait_ms: 1000,
                ..Default::default()
            })
            .await
        else {
            tokio::time::sleep(Duration::from_millis(100)).await;
            continue;
        };
        let r = r.into_inner();
        if r.units.is_empty() {
            if r.retry_after_ms > 0 {
                tokio::time::sleep(Duration::from_millis(r.retry_after_ms.min(1000) as u64)).await;
            }
            continue;
        }
        if c.recording.load(Ordering::Relaxed) {
            let us = asked.elapsed().as_micros().min(u32::MAX as u128) as u32;
            c.latencies.lock().expect("latency lock").push(us);
        }
        c.leases.fetch_add(1, Ordering::Relaxed);
        {
            let mut f = first.lock().expect("first-unit lock");
            if f.is_none() {
                *f = Some(Instant::now());
                c.busy.fetch_add(1, Ordering::Relaxed);
            }
        }
        for u in r.units {
            held.lock().expect("held lock").insert(u.lease_id.clone());
            if unit_ms > 0 {
                tokio::time::sleep(Duration::from_millis(unit_ms)).await;
            }
            let rect = u.rect.unwrap_or_default();
            let samples = u.samples.unwrap_or_default();
            let pixels = rect.width as u64 * rect.height as u64;
            let spp = samples.end.saturating_sub(samples.start);
            let answer = client
                .submit_result(pb::SubmitResultRequest {
                    worker_id: worker_id.clone(),
                    lease_id: u.lease_id.clone(),
                    rect: Some(rect),
                    samples: Some(samples),
                    // Black pixels, each sum one byte, every pixel `spp` samples.
                    sums: vec![0u8; 3 * pixels as usize].into(),
                    sum_bytes: 1,
                    uniform_count: Some(spp),
                    rays: Some(pb::RayCounts {
                        primary: pixels * spp as u64,
                        ..Default::default()
                    }),
                    ..Default::default()
                })
                .await;
            held.lock().expect("held lock").remove(&u.lease_id);
            match answer.map(|a| a.into_inner().outcome()) {
                Ok(pb::ResultOutcome::Accepted) => {
                    c.results.fetch_add(1, Ordering::Relaxed);
                    c.units.fetch_add(u.units.max(1) as u64, Ordering::Relaxed);
                }
                _ => {
                    c.rejected.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
    }
}
