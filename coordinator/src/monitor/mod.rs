//! The web monitor (`tessera coordinator --http ADDR`): a page of jobs,
//! workers and the frame as it fills in, and the JSON API it is built on
//! (docs/monitor.md), served over HTTP/1 by axum on the coordinator's own
//! runtime.
//!
//! Map: [`origin`] (Host and Origin checks: DNS rebinding and cross-site
//! requests), [`auth`] (the client token, as the gRPC job service takes it),
//! [`api`] (JSON: jobs, frames, workers, cancel, priority), [`events`]
//! (server-sent events: one snapshot shared by every viewer), [`roster`]
//! (workers seen, and which of them left), [`preview`] (partial and
//! finished frames as PNG, throttled per frame), [`json`] (the API's
//! shapes), [`web`] (the page, its script and style, embedded at build
//! time).
//!
//! What a viewer costs the farm does not grow with the number of viewers:
//! the snapshot is built at most twice a second and shared, and a frame's
//! preview at most once a second per size and shared.

mod api;
mod auth;
mod events;
mod json;
mod origin;
mod preview;
mod roster;
mod web;

use std::future::Future;
use std::sync::Arc;

use axum::Router;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use tokio::net::TcpListener;

use crate::edge::{Edge, EdgeInfo, EdgeLimits, EdgeListener, TrackLayer};
use crate::farm::{Farm, FarmError};

/// Why an API request was refused: a status and a message for a person.
#[derive(Debug, thiserror::Error)]
#[error("{message}")]
pub struct ApiError {
    pub status: StatusCode,
    pub message: String,
}

impl ApiError {
    fn new(status: StatusCode, message: impl Into<String>) -> Self {
        ApiError {
            status,
            message: message.into(),
        }
    }
    fn bad_request(message: impl Into<String>) -> Self {
        ApiError::new(StatusCode::BAD_REQUEST, message)
    }
}

impl From<FarmError> for ApiError {
    fn from(e: FarmError) -> Self {
        let status = match &e {
            FarmError::InvalidArgument(_) => StatusCode::BAD_REQUEST,
            FarmError::NotFound(_) => StatusCode::NOT_FOUND,
            FarmError::FailedPrecondition(_) => StatusCode::CONFLICT,
            FarmError::PermissionDenied(_) => StatusCode::FORBIDDEN,
            FarmError::ResourceExhausted(_) => StatusCode::TOO_MANY_REQUESTS,
            FarmError::Unavailable(_) | FarmError::Store(_) => StatusCode::SERVICE_UNAVAILABLE,
            FarmError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        };
        ApiError::new(status, e.to_string())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = serde_json::json!({ "error": self.message }).to_string();
        (
            self.status,
            [(axum::http::header::CONTENT_TYPE, "application/json")],
            body,
        )
            .into_response()
    }
}

/// Why the monitor could not be served.
#[derive(Debug, thiserror::Error)]
pub enum MonitorError {
    #[error("web monitor: {0}")]
    Serve(#[from] std::io::Error),
}

/// What every handler shares.
pub struct Monitor {
    farm: Arc<Farm>,
    /// The client token; `None`: the monitor is open, as the job service is.
    token: Option<Arc<str>>,
    /// A token that opens `/metrics` only (`--metrics-token-file`).
    metrics_token: Option<Arc<str>>,
    /// Which Host headers are answered.
    hosts: origin::Hosts,
    events: events::Hub,
    roster: roster::Roster,
    previews: preview::Previews,
    frames: api::FrameCache,
}

/// How the monitor is served.
#[derive(Clone, Debug, Default)]
pub struct MonitorConfig {
    /// The job service's: the same token opens both.
    pub client_token: Option<String>,
    /// Opens `/metrics` and nothing else: for a Prometheus server, which
    /// then cannot read jobs or frames. The client token opens it too.
    pub metrics_token: Option<String>,
    /// Names answered besides the listen address and localhost
    /// (`--http-allow-host`).
    pub allow_hosts: Vec<String>,
    /// Connection limits of the monitor's port.
    pub edge: EdgeLimits,
}

/// Serves the monitor of `farm` on `listener` until `shutdown` resolves.
pub async fn serve(
    farm: Arc<Farm>,
    listener: TcpListener,
    config: MonitorConfig,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), MonitorError> {
    let local = listener.local_addr()?;
    let monitor = Arc::new(Monitor {
        farm,
        token: config.client_token.map(Arc::from),
        metrics_token: config.metrics_token.map(Arc::from),
        hosts: origin::Hosts::new(local, &config.allow_hosts),
        events: events::Hub::new(),
        roster: roster::Roster::default(),
        previews: preview::Previews::default(),
        frames: api::FrameCache::default(),
    });
    let ticker = tokio::spawn(events::run(monitor.clone()));
    // The gRPC port's accept loop and limits (crate::edge).
    let listener = EdgeListener::new(Edge::new("monitor", config.edge), listener)?;
    let app = router(monitor).layer(TrackLayer);
    let result = axum::serve(
        listener,
        app.into_make_service_with_connect_info::<EdgeInfo>(),
    )
    .with_graceful_shutdown(shutdown)
    .await;
    ticker.abort();
    Ok(result?)
}

/// `GET /metrics`: the farm's Prometheus metrics (crate::metrics).
async fn metrics(axum::extract::State(m): axum::extract::State<Arc<Monitor>>) -> Response {
    (
        [(
            axum::http::header::CONTENT_TYPE,
            crate::metrics::CONTENT_TYPE,
        )],
        m.farm.metrics_text(),
    )
        .into_response()
}

fn router(monitor: Arc<Monitor>) -> Router {
    // Everything with data behind the token; the page, its script and
    // style (no data in them) and `/api/info` (whether a token is needed)
    // open, so the page can ask for the token.
    let api = Router::new()
        .route("/api/jobs", get(api::jobs))
        .route("/api/jobs/{id}", get(api::job))
        .route("/api/jobs/{id}/cancel", post(api::cancel))
        .route("/api/jobs/{id}/priority", post(api::priority))
        .route("/api/jobs/{id}/frames/{frame}", get(api::frame))
        .route(
            "/api/jobs/{id}/frames/{frame}/preview.png",
            get(preview::preview),
        )
        .route(
            "/api/jobs/{id}/frames/{frame}/image.png",
            get(preview::image),
        )
        .route("/api/workers", get(api::workers))
        .route("/api/events", get(events::sse))
        .route("/api/monitor", get(api::monitor_stats))
        .route_layer(axum::middleware::from_fn_with_state(
            monitor.clone(),
            auth::require_token,
        ));
    Router::new()
        .route("/", get(web::index))
        .route("/app.js", get(web::script))
        .route("/style.css", get(web::style))
        .route("/favicon.svg", get(web::icon))
        .route("/api/info", get(api::info))
        .merge(api)
        .route(
            "/metrics",
            get(metrics).route_layer(axum::middleware::from_fn_with_state(
                monitor.clone(),
                auth::require_metrics_token,
            )),
        )
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "no such page") })
        // Before everything, the token included: a rebound or cross-site
        // request is refused whether or not a token is needed.
        .layer(axum::middleware::from_fn_with_state(
            monitor.clone(),
            origin::guard,
        ))
        .with_state(monitor)
}
