//! The JSON API (docs/monitor.md): what the page reads and does, open to
//! scripts too.

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use serde::Serialize;

use super::json::{
    FRAMES_PAGE, FRAMES_PAGE_MAX, FailureJson, FrameDetailJson, FrameJson, JobDetailJson, JobJson,
    WorkerJson, tile_runs,
};
use super::preview::param;
use super::{ApiError, Monitor};
use crate::farm::TileState;

/// Serialises `v` as the response body.
pub fn json_response<T: Serialize>(v: &T) -> Response {
    match serde_json::to_vec(v) {
        Ok(body) => ([(header::CONTENT_TYPE, "application/json")], body).into_response(),
        Err(e) => ApiError::new(
            axum::http::StatusCode::INTERNAL_SERVER_ERROR,
            format!("cannot encode the answer: {e}"),
        )
        .into_response(),
    }
}

/// `GET /api/info`, open: whether the monitor wants a token.
pub async fn info(State(m): State<Arc<Monitor>>) -> Response {
    json_response(&serde_json::json!({
        "service": "tessera-monitor",
        "version": env!("CARGO_PKG_VERSION"),
        "token_required": m.token.is_some(),
    }))
}

/// `?frames_from=F&frames_max=N`: which page of a job's frames to show
/// (from frame F, default the first; N frames at most, default
/// [`FRAMES_PAGE`]).
fn frame_page(query: &Option<String>) -> Result<(u32, usize), ApiError> {
    let from = match param(query, "frames_from") {
        None => 0,
        Some(v) => v.parse().map_err(|_| {
            ApiError::bad_request(format!("frames_from must be a frame number, got {v:?}"))
        })?,
    };
    let max = match param(query, "frames_max") {
        None => FRAMES_PAGE,
        Some(v) => v
            .parse()
            .ok()
            .filter(|n| (1..=FRAMES_PAGE_MAX).contains(n))
            .ok_or_else(|| {
                ApiError::bad_request(format!(
                    "frames_max must be a whole number in 1..={FRAMES_PAGE_MAX}, got {v:?}"
                ))
            })?,
    };
    Ok((from, max))
}

/// `GET /api/jobs[?frames_max=N]`: every job with its first page of frames.
pub async fn jobs(
    State(m): State<Arc<Monitor>>,
    RawQuery(query): RawQuery,
) -> Result<Response, ApiError> {
    let (_, max) = frame_page(&query)?;
    let jobs: Vec<JobJson> = m
        .farm
        .jobs()
        .iter()
        .map(|v| JobJson::from(v).paged(0, max))
        .collect();
    Ok(json_response(&jobs))
}

/// `GET /api/jobs/{id}[?frames_from=F&frames_max=N]`: the job with the
/// page of its frames from frame F, and its failures.
pub async fn job(
    State(m): State<Arc<Monitor>>,
    Path(id): Path<String>,
    RawQuery(query): RawQuery,
) -> Result<Response, ApiError> {
    let (from, max) = frame_page(&query)?;
    let job = JobJson::from(&m.farm.job(&id)?).paged(from, max);
    let failures = m
        .farm
        .job_failures(&id)?
        .into_iter()
        .map(FailureJson::from)
        .collect();
    Ok(json_response(&JobDetailJson { job, failures }))
}

pub async fn cancel(
    State(m): State<Arc<Monitor>>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let v = m.farm.cancel(&id).await?;
    Ok(json_response(&JobJson::from(&v)))
}

/// `POST /api/jobs/{id}/priority` with `{"priority": N}`.
pub async fn priority(
    State(m): State<Arc<Monitor>>,
    Path(id): Path<String>,
    body: Bytes,
) -> Result<Response, ApiError> {
    #[derive(serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Body {
        priority: i32,
    }
    let b: Body = serde_json::from_slice(&body).map_err(|e| {
        ApiError::bad_request(format!(
            "the body must be {{\"priority\": N}} with N a 32-bit integer: {e}"
        ))
    })?;
    let v = m.farm.set_priority(&id, b.priority).await?;
    m.events.poke();
    Ok(json_response(&JobJson::from(&v)))
}

/// How long a frame's tiles are answered from the last look (as its
/// preview is): every viewer of a frame shares one look a second.
const FRAME_INTERVAL: Duration = Duration::from_secs(1);
/// Frames remembered (the least recently made go first).
const FRAMES_KEPT: usize = 256;

/// The last answer for each (job, frame).
#[derive(Default)]
pub struct FrameCache(Mutex<HashMap<(String, u32), (Instant, Bytes)>>);

/// `GET /api/jobs/{id}/frames/{frame}`: the frame's tiles, for the
/// preview's overlay.
pub async fn frame(
    State(m): State<Arc<Monitor>>,
    Path((id, frame)): Path<(String, u32)>,
) -> Result<Response, ApiError> {
    let key = (id.clone(), frame);
    if let Some((made, body)) = m.frames.0.lock().expect("frame cache").get(&key)
        && made.elapsed() < FRAME_INTERVAL
    {
        return Ok(json_bytes(body.clone()));
    }
    let body = Bytes::from(frame_json(&m, id, frame)?);
    let mut cache = m.frames.0.lock().expect("frame cache");
    if cache.len() >= FRAMES_KEPT
        && let Some(oldest) = cache
            .iter()
            .min_by_key(|(_, (made, _))| *made)
            .map(|(k, _)| k.clone())
    {
        cache.remove(&oldest);
    }
    cache.insert(key, (Instant::now(), body.clone()));
    Ok(json_bytes(body))
}

fn json_bytes(body: Bytes) -> Response {
    ([(header::CONTENT_TYPE, "application/json")], body).into_response()
}

fn frame_json(m: &Monitor, id: String, frame: u32) -> Result<Vec<u8>, ApiError> {
    let tiles = m.farm.frame_tiles(&id, frame)?;
    let count = |s: TileState| tiles.iter().filter(|t| t.state == s).count() as u32;
    let v = m.farm.job(&id)?;
    let i = v.frames.iter().position(|f| f.0 == frame).ok_or_else(|| {
        ApiError::new(
            axum::http::StatusCode::NOT_FOUND,
            format!("job {id} has no frame {frame}"),
        )
    })?;
    let f = &v.frames[i];
    serde_json::to_vec(&FrameDetailJson {
        job: id,
        frame: FrameJson {
            frame,
            units_total: f.1,
            units_done: f.2,
            progress: v.frames_progress[i],
            output: f.3.clone(),
            written: f.3.is_some(),
        },
        width: v.record.settings.width,
        height: v.record.settings.height,
        tiles: tile_runs(&tiles),
        tiles_done: count(TileState::Done),
        tiles_leased: count(TileState::Leased),
        tiles_partial: count(TileState::Partial),
        tiles_pending: count(TileState::Pending),
    })
    .map_err(|e| {
        ApiError::new(
            axum::http::StatusCode::INTERNAL_SERVER_ERROR,
            format!("cannot encode the answer: {e}"),
        )
    })
}

/// The workers page's rows: the farm's workers and those gone.
pub fn worker_rows(m: &Monitor) -> Vec<WorkerJson> {
    let workers = m.farm.workers();
    let leases = m.farm.lease_summaries();
    m.roster
        .update(&workers, &leases, m.farm.config.heartbeat_interval)
}

pub async fn workers(State(m): State<Arc<Monitor>>) -> Response {
    json_response(&worker_rows(&m))
}

/// `GET /api/monitor`: what the monitor itself costs (its preview work,
/// its viewers).
pub async fn monitor_stats(State(m): State<Arc<Monitor>>) -> Response {
    let p = &m.previews.stats;
    let made = p.made.load(Ordering::Relaxed);
    json_response(&serde_json::json!({
        "event_viewers": m.events.viewers(),
        "snapshots_built": m.events.built.load(Ordering::Relaxed),
        "previews_made": made,
        "previews_served": p.served.load(Ordering::Relaxed),
        "preview_lock_us_max": p.lock_us_max.load(Ordering::Relaxed),
        "preview_lock_us_mean": p.lock_us_sum.load(Ordering::Relaxed) / made.max(1),
        "preview_encode_us_mean": p.encode_us_sum.load(Ordering::Relaxed) / made.max(1),
    }))
}
