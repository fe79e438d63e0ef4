//! The coordinator's Prometheus metrics (`GET /metrics` on `--http`,
//! docs/operations.md). The names are a contract (issue 38): dashboards,
//! alerts and autoscalers are written against them.
//!
//! Counters and histograms move where the event happens (a result taken,
//! a lease granted, a store commit); the gauges (jobs, units, workers,
//! store health, asset bytes) are read from the farm when scraped, so
//! they cannot drift from what `tessera status` shows.
//!
//! Encoded by `prometheus-client` (the Prometheus project's Rust client)
//! in the OpenMetrics text format, which Prometheus scrapes natively.

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

use crate::farm::Outcome;

/// The media type of [`Metrics::encode`]'s text.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

type StateLabel = [(&'static str, &'static str); 1];
type WorkerLabels = [(&'static str, &'static str); 2];

/// Job states as `tessera_jobs{state}` names them.
pub const JOB_STATES: [&str; 6] = [
    "queued",
    "running",
    "done",
    "failed",
    "cancelled",
    "waiting",
];
/// Unit states as `tessera_units{state}` names them.
pub const UNIT_STATES: [&str; 2] = ["waiting", "leased"];
/// Worker states as `tessera_workers{backend,state}` names them: busy
/// (holds a lease), idle, quarantined.
pub const WORKER_STATES: [&str; 3] = ["busy", "idle", "quarantined"];

/// What the gauges read from the farm at a scrape.
#[derive(Clone, Debug, Default)]
pub struct Gauges {
    /// Jobs per state, in the order of [`JOB_STATES`].
    pub jobs: [i64; 6],
    /// Units per state, in the order of [`UNIT_STATES`].
    pub units: [i64; 2],
    /// Workers per (backend, state): backend "cpu" or "gpu", state from
    /// [`WORKER_STATES`].
    pub workers: Vec<(&'static str, &'static str)>,
    pub store_healthy: bool,
    pub asset_bytes: u64,
}

pub struct Metrics {
    registry: Registry,
    jobs: Family<StateLabel, Gauge>,
    units: Family<StateLabel, Gauge>,
    workers: Family<WorkerLabels, Gauge>,
    results: Family<[(&'static str, &'static str); 1], Counter>,
    lease_seconds: Histogram,
    samples: Counter,
    store_healthy: Gauge,
    store_commit_seconds: Histogram,
    asset_bytes: Gauge,
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix("tessera");
        let jobs = Family::<StateLabel, Gauge>::default();
        let units = Family::<StateLabel, Gauge>::default();
        let workers = Family::<WorkerLabels, Gauge>::default();
        let results = Family::<[(&'static str, &'static str); 1], Counter>::default();
        // Every outcome from the start, at 0: a rate over a series that
        // appears only with its first event misses that event.
        for outcome in ["accepted", "late", "duplicate", "rejected", "failed"] {
            drop(results.get_or_create(&[("outcome", outcome)]));
        }
        // 1 ms to about 65 s: a lease is granted at once when work is
        // queued, and a worker's long poll waits up to its timeout.
        let lease_seconds = Histogram::new(exponential_buckets(0.001, 2.0, 17));
        let samples = Counter::default();
        let store_healthy = Gauge::default();
        // 0.1 ms to about 3 s: a batched commit with fsync.
        let store_commit_seconds = Histogram::new(exponential_buckets(0.0001, 2.0, 16));
        let asset_bytes = Gauge::default();
        registry.register("jobs", "Jobs by state", jobs.clone());
        registry.register(
            "units",
            "Work units of unfinished jobs: waiting (queued) or leased",
            units.clone(),
        );
        registry.register(
            "workers",
            "Connected workers by backend and state",
            workers.clone(),
        );
        // The client appends `_total` to counters.
        registry.register(
            "results",
            "Results received, by outcome (failed: the worker reported the unit failed)",
            results.clone(),
        );
        registry.register(
            "lease_seconds",
            "Seconds from a worker's lease request to the lease granted",
            lease_seconds.clone(),
        );
        registry.register(
            "samples",
            "Pixel-samples of accepted results",
            samples.clone(),
        );
        registry.register(
            "store_healthy",
            "1 while the database takes writes, 0 during an outage",
            store_healthy.clone(),
        );
        registry.register(
            "store_commit_seconds",
            "Seconds a write to the database took to become durable",
            store_commit_seconds.clone(),
        );
        registry.register(
            "asset_bytes",
            "Bytes of scene files and models held in the asset store",
            asset_bytes.clone(),
        );
        Metrics {
            registry,
            jobs,
            units,
            workers,
            results,
            lease_seconds,
            samples,
            store_healthy,
            store_commit_seconds,
            asset_bytes,
        }
    }

    /// A result's outcome, as `tessera_results_total{outcome}` counts it.
    pub fn result(&self, outcome: &Outcome) {
        let name = match outcome {
            Outcome::Accepted => "accepted",
            Outcome::Late(_) => "late",
            Outcome::Duplicate(_) => "duplicate",
            Outcome::Rejected(_) => "rejected",
            Outcome::FailureRecorded => "failed",
        };
        self.results.get_or_create(&[("outcome", name)]).inc();
    }

    pub fn samples(&self, n: u64) {
        self.samples.inc_by(n);
    }

    pub fn lease_granted(&self, seconds: f64) {
        self.lease_seconds.observe(seconds);
    }

    pub fn store_commit(&self, seconds: f64) {
        self.store_commit_seconds.observe(seconds);
    }

    /// The text of a scrape, with `gauges` as read from the farm now.
    pub fn encode(&self, gauges: &Gauges) -> String {
        for (state, n) in JOB_STATES.iter().zip(gauges.jobs) {
            self.jobs.get_or_create(&[("state", state)]).set(n);
        }
        for (state, n) in UNIT_STATES.iter().zip(gauges.units) {
            self.units.get_or_create(&[("state", state)]).set(n);
        }
        // Every (backend, state) pair is present, at 0 when empty, so a
        // query over them never sees a series vanish.
        for backend in ["cpu", "gpu"] {
            for state in WORKER_STATES {
                let n = gauges
                    .workers
                    .iter()
                    .filter(|&&(b, s)| b == backend && s == state)
                    .count();
                self.workers
                    .get_or_create(&[("backend", backend), ("state", state)])
                    .set(n as i64);
            }
        }
        self.store_healthy.set(i64::from(gauges.store_healthy));
        self.asset_bytes
            .set(i64::try_from(gauges.asset_bytes).unwrap_or(i64::MAX));
        let mut out = String::new();
        encode(&mut out, &self.registry).expect("writing to a String cannot fail");
        out
    }
}
