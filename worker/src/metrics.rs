//! A worker's own Prometheus metrics (`tessera worker --http ADDR`, issue
//! 38): `GET /metrics` in the OpenMetrics text format, written by the
//! same client crate as the coordinator's (`prometheus-client`). Read from
//! the worker's state at each scrape, so they cannot drift from it:
//! - `tessera_worker_units_total` (counter): units whose results the
//!   coordinator accepted;
//! - `tessera_worker_leases` (gauge): leases held now (rendering, queued
//!   or being sent);
//! - `tessera_worker_threads` (gauge): render threads;
//! - `tessera_worker_info{name,backend,gpu}` (gauge, 1).
//!
//! No token: bind it to an address only the monitoring stack reaches.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;

use crate::heartbeat::HeldMap;
use crate::{Worker, WorkerError};

/// The media type of the text served.
const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

type InfoLabels = [(&'static str, String); 3];

struct Metrics {
    registry: Registry,
    units: Counter,
    leases: Gauge,
    units_done: Arc<AtomicU64>,
    held: HeldMap,
}

impl Metrics {
    fn encode(&mut self) -> String {
        // The counter follows the worker's own count.
        let done = self.units_done.load(Ordering::Relaxed);
        self.units.inc_by(done.saturating_sub(self.units.get()));
        self.leases
            .set(self.held.lock().expect("held lock").len() as i64);
        let mut out = String::new();
        encode(&mut out, &self.registry).expect("writing to a String cannot fail");
        out
    }
}

impl Worker {
    /// Serves `/metrics` on `addr` (port 0: any free one) on a task of its
    /// own; the address bound.
    pub async fn serve_metrics(&self, addr: SocketAddr) -> Result<SocketAddr, WorkerError> {
        let http_err = |e: std::io::Error| WorkerError::Http {
            addr: addr.to_string(),
            message: e.to_string(),
        };
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .map_err(http_err)?;
        let bound = listener.local_addr().map_err(http_err)?;
        let mut registry = Registry::with_prefix("tessera_worker");
        let units = Counter::default();
        registry.register(
            "units",
            "Units whose results the coordinator accepted",
            units.clone(),
        );
        let leases = Gauge::default();
        registry.register(
            "leases",
            "Leases held now: rendering, queued or being sent",
            leases.clone(),
        );
        let threads = Gauge::<i64>::default();
        threads.set(self.renderer.threads() as i64);
        registry.register("threads", "Render threads", threads);
        let info = Family::<InfoLabels, Gauge>::default();
        info.get_or_create(&[
            ("name", self.config.name.clone()),
            ("backend", self.config.backend.name().to_string()),
            (
                "gpu",
                self.renderer.adapter_name().unwrap_or_default().to_string(),
            ),
        ])
        .set(1);
        registry.register("info", "The worker's name, backend and GPU", info);
        let metrics = Arc::new(Mutex::new(Metrics {
            registry,
            units,
            leases,
            units_done: self.units_done.clone(),
            held: self.held.clone(),
        }));
        let app = axum::Router::new().route(
            "/metrics",
            axum::routing::get(move || {
                let metrics = metrics.clone();
                async move {
                    let body = metrics.lock().expect("metrics lock").encode();
                    ([(axum::http::header::CONTENT_TYPE, CONTENT_TYPE)], body)
                }
            }),
        );
        tokio::spawn(async move {
            if let Err(e) = axum::serve(listener, app).await {
                tracing::error!(error = %e, "the metrics endpoint stopped");
            }
        });
        tracing::info!(addr = %bound, "metrics on http://{bound}/metrics");
        Ok(bound)
    }
}
