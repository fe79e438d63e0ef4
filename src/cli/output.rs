//! How commands report: machine-readable JSON (`--json`, one convention for
//! every command; field names are a contract, see docs/cli.md) and progress
//! (a bar on a terminal, one plain line at a steady cadence elsewhere, so a
//! log file or CI output shows a long render moving).

use std::io::IsTerminal as _;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::{Value, json};
use tessera_proto::pb;

use super::outln;

#[derive(Args, Debug, Clone, Copy, Default)]
pub struct Format {
    /// Print JSON instead of text (one document; `watch` and `submit --wait`
    /// print one object a line per progress event). Field names are stable:
    /// see docs/cli.md
    #[arg(long)]
    pub json: bool,
}

/// Prints one JSON document on a line of its own.
pub fn print_json(v: &Value) {
    outln!("{v}");
}

/// A process's resident set and its peak, in KiB.
pub fn rss_kib(pid: u32) -> (u64, u64) {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next()?.parse().ok())
            .unwrap_or(0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// A worker's backend (`Capabilities.backend`) as `tessera workers` prints
/// it; UNSPECIFIED reads as `cpu`, as the coordinator registers it.
pub fn backend_name(backend: i32) -> &'static str {
    tessera_proto::convert::backend_from_pb(backend)
        .unwrap_or(tracer_core::render::Backend::Cpu)
        .name()
}

pub use tessera_coordinator::status_json::job_json;

/// A worker as `tessera workers --json` prints it.
pub fn worker_json(w: &pb::WorkerInfo) -> Value {
    let c = w.capabilities.clone().unwrap_or_default();
    json!({
        "worker_id": w.worker_id,
        "name": w.name,
        "backend": backend_name(c.backend),
        "gpu": (!c.gpu_name.is_empty()).then_some(&c.gpu_name),
        "threads": c.threads,
        "host_id": (!c.host_id.is_empty()).then_some(&c.host_id),
        "labels": c.labels.iter().collect::<std::collections::BTreeMap<_, _>>(),
        "version": c.version,
        "leases": w.leases,
        "units_done": w.units_done,
        "samples_per_second": w.samples_per_second,
        "rays_per_second": w.rays_per_second,
        "last_seen_unix_ms": w.last_seen_unix_ms,
        "quarantined_until_unix_ms": (w.quarantined_until_unix_ms > 0).then_some(w.quarantined_until_unix_ms),
    })
}

/// Off a terminal, a progress line every this long (and at the end).
const PLAIN_EVERY: Duration = Duration::from_secs(5);

/// How far back a local render's rate looks for its ETA: recent enough
/// that a slow start (a GPU's pipelines built in the first chunk) or a
/// costlier part of the frame (glass below sky) soon shows, as a farm
/// job's ETA does (`tessera_coordinator::rate`).
const ETA_WINDOW: Duration = Duration::from_secs(10);

/// Progress of one long piece of work, safe to advance from many threads.
pub struct Progress {
    what: String,
    bar: Option<ProgressBar>,
    /// Units of work in all (0: quiet); an adaptive render re-estimates it.
    total: AtomicU64,
    done: AtomicU64,
    start: Instant,
    /// The work done over time, for the ETA's recent rate.
    meter: Mutex<tessera_coordinator::rate::Meter>,
    /// When the last plain line was printed, its message and the progress
    /// it showed.
    last: Mutex<(Instant, String, u64)>,
}

impl Progress {
    /// A bar on a terminal; plain lines (`WHAT: 42.0% ...`) otherwise.
    /// `quiet`: nothing at all (JSON output, say).
    pub fn new(what: &str, total: u64, quiet: bool) -> Progress {
        let bar = (!quiet && std::io::stderr().is_terminal()).then(|| {
            ProgressBar::new(total.max(1)).with_style(
                ProgressStyle::with_template(
                    "{spinner} [{elapsed_precise}] {wide_bar} {percent:>3}% {msg}",
                )
                .expect("valid template"),
            )
        });
        let start = Instant::now();
        Progress {
            what: what.to_string(),
            bar,
            total: AtomicU64::new(if quiet { 0 } else { total.max(1) }),
            done: AtomicU64::new(0),
            start,
            meter: Mutex::new({
                // The rate counts from the start, not from the first chunk.
                let mut m = tessera_coordinator::rate::Meter::new(ETA_WINDOW);
                m.start(start);
                m
            }),
            last: Mutex::new((start, String::new(), u64::MAX)),
        }
    }

    fn total(&self) -> u64 {
        self.total.load(Ordering::Relaxed)
    }

    /// A new estimate of the work in all: an adaptive render's, which its
    /// rounds revise as they learn where the image is noisy (its bound,
    /// every pixel at `--max-samples`, would make the ETA many times too
    /// long). Never below the work done; nothing for quiet progress.
    pub fn set_total(&self, total: u64) {
        if self.total() == 0 {
            return;
        }
        let total = total.max(self.done.load(Ordering::Relaxed)).max(1);
        self.total.store(total, Ordering::Relaxed);
        if let Some(bar) = &self.bar {
            bar.set_length(total);
        }
    }

    /// `n` more units of work done; the ETA comes from the measured rate.
    pub fn inc(&self, n: u64) {
        let done = self.done.fetch_add(n, Ordering::Relaxed) + n;
        if self.total() > 0 {
            self.meter
                .lock()
                .expect("progress meter")
                .add(Instant::now(), n as f64);
        }
        if let Some(bar) = &self.bar {
            bar.set_position(done);
            bar.set_message(self.eta_text(done));
        } else {
            self.plain(done, None, false);
        }
    }

    /// Absolute progress with a message of the caller's (watching a job:
    /// the coordinator's rate and ETA).
    pub fn set(&self, done: u64, message: &str) {
        self.done.store(done, Ordering::Relaxed);
        if let Some(bar) = &self.bar {
            bar.set_position(done);
            bar.set_message(message.to_string());
        } else {
            self.plain(done, Some(message), false);
        }
    }

    /// A line of its own (above the bar on a terminal).
    pub fn note(&self, line: &str) {
        match &self.bar {
            Some(bar) => bar.println(line),
            None if self.total() > 0 => eprintln!("{line}"),
            None => {}
        }
    }

    pub fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        } else {
            self.plain(self.done.load(Ordering::Relaxed), None, true);
        }
    }

    /// Stops where it is (Ctrl-C): the bar stays as it was, ended by a
    /// newline, so what follows starts on a line of its own.
    pub fn abandon(&self) {
        if let Some(bar) = &self.bar {
            bar.abandon();
        }
    }

    /// The work left over the recent rate (the last [`ETA_WINDOW`]).
    fn eta_text(&self, done: u64) -> String {
        // Too early for a rate worth extrapolating.
        if done == 0 || self.start.elapsed() < Duration::from_secs(1) {
            return String::new();
        }
        let rate = self
            .meter
            .lock()
            .expect("progress meter")
            .rate(Instant::now());
        match tessera_coordinator::rate::eta(self.total().saturating_sub(done) as f64, rate) {
            Some(left) => format!("eta {left:.0} s"),
            None => String::new(),
        }
    }

    fn plain(&self, done: u64, message: Option<&str>, last: bool) {
        if self.total() == 0 {
            return;
        }
        let mut l = self.last.lock().expect("progress lock");
        // The end, already shown by the last line (a watched job's `done`
        // or `cancelled`): nothing more to say.
        if last && l.2 == done && !l.1.is_empty() {
            return;
        }
        let message = message.map_or_else(|| self.eta_text(done), str::to_string);
        // Every PLAIN_EVERY, and whenever the state in the message changes
        // (a job going from queued to running says so at once).
        let changed = message.split(' ').next() != l.1.split(' ').next();
        if !(last || changed || l.0.elapsed() >= PLAIN_EVERY) {
            return;
        }
        *l = (Instant::now(), message.clone(), done);
        let pct = 100.0 * done as f64 / self.total() as f64;
        eprintln!(
            "{}: {pct:.1}% {message} ({:.0} s)",
            self.what,
            self.start.elapsed().as_secs_f64()
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The ETA is the work left over the recent rate: nothing in the
    /// first second, then (100 - 20) units at about 20 units in 1.2 s.
    #[test]
    fn eta_is_the_work_left_over_the_recent_rate() {
        let p = Progress::new("test", 100, true);
        // Quiet progress keeps no total; this one measures.
        let p = Progress {
            total: AtomicU64::new(100),
            ..p
        };
        p.inc(10);
        assert_eq!(p.eta_text(10), "");
        std::thread::sleep(Duration::from_millis(1200));
        p.inc(10);
        let eta: f64 = p
            .eta_text(20)
            .strip_prefix("eta ")
            .and_then(|t| t.strip_suffix(" s"))
            .and_then(|t| t.parse().ok())
            .expect("an ETA");
        // 80 units at 20 / 1.2 s: 4.8 s (a loaded machine sleeps longer).
        assert!((4.0..=12.0).contains(&eta), "{eta}");
        // An adaptive render's revised total: 20 units left, a quarter of
        // the ETA; never below the work done.
        let eta_of = |p: &Progress| -> f64 {
            p.eta_text(20)
                .strip_prefix("eta ")
                .and_then(|t| t.strip_suffix(" s"))
                .and_then(|t| t.parse().ok())
                .expect("an ETA")
        };
        p.set_total(40);
        let revised = eta_of(&p);
        assert!(
            (revised - eta / 4.0).abs() <= 0.25 * eta / 4.0 + 1.0,
            "{revised} against {eta} / 4"
        );
        p.set_total(5);
        assert_eq!(p.total(), 20);
        let quiet = Progress::new("quiet", 100, true);
        quiet.set_total(40);
        assert_eq!(quiet.total(), 0, "quiet progress stays quiet");
    }
}
