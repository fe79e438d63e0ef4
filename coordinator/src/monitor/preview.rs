//! Frames as images: the live preview of a frame being rendered (its
//! partial sums resolved, subsampled to fit a size), thumbnails (the same
//! at a small size), and finished frames full size.
//!
//! Throttle: a preview of one (job, frame, size) is made at most once per
//! [`INTERVAL`] and only when units of the frame were merged since; every
//! viewer in between gets the same bytes. Making one holds the farm's lock
//! only to copy the subsampled pixels' sums (at most `max` x `max`), and
//! resolves and encodes them after, on a blocking thread; one preview is
//! made at a time. `GET /api/monitor` reports the lock times measured.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use tracer_core::film::image;

use super::{ApiError, Monitor};
use crate::farm::{FramePreview, preview_step};

/// Least time between two previews of the same frame at the same size.
const INTERVAL: Duration = Duration::from_secs(1);
/// Longest side of a preview unless `?max=` says otherwise, and the bounds of `max`.
const DEFAULT_SIDE: u32 = 512;
const SIDES: std::ops::RangeInclusive<u32> = 16..=1024;
/// Previews kept (the least recently made go first).
const KEPT: usize = 256;

#[derive(Default)]
pub struct Stats {
    pub made: AtomicU64,
    pub served: AtomicU64,
    /// Time in the farm's lock (waiting for it included), microseconds.
    pub lock_us_max: AtomicU64,
    pub lock_us_sum: AtomicU64,
    /// Resolving and PNG encoding, off the lock.
    pub encode_us_sum: AtomicU64,
}

struct Entry {
    png: Bytes,
    made: Instant,
    /// The frame's merged units when made; `None` once the frame is written.
    units_done: Option<u64>,
}

#[derive(Default)]
pub struct Previews {
    /// (job, frame, size) -> preview. An async lock held while one is made:
    /// the throttle for all viewers together.
    cache: tokio::sync::Mutex<HashMap<(String, u32, u32), Entry>>,
    pub stats: Stats,
}

/// The value of `key` in a query string (no escapes: the API's values are numbers).
pub(super) fn param<'a>(query: &'a Option<String>, key: &str) -> Option<&'a str> {
    query
        .as_deref()?
        .split('&')
        .find_map(|kv| kv.strip_prefix(key)?.strip_prefix('='))
}

/// The preview, saying what it shows: `X-Tessera-Units-Done` is how many
/// of the frame's units it holds, or `written` (the frame's final image).
fn png_response(e: &Entry) -> Response {
    let shows = e
        .units_done
        .map_or_else(|| "written".to_string(), |n| n.to_string());
    (
        [
            (header::CONTENT_TYPE, "image/png"),
            // A preview is current only now.
            (header::CACHE_CONTROL, "no-store"),
        ],
        [(UNITS_DONE, shows)],
        e.png.clone(),
    )
        .into_response()
}

const UNITS_DONE: &str = "x-tessera-units-done";

fn internal(what: &str, e: impl std::fmt::Display) -> ApiError {
    ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, format!("{what}: {e}"))
}

/// 8-bit RGB as a preview PNG: the `Sub` filter only, since the frame
/// writer's adaptive filtering tries five filters a row, several times the
/// work for a preview that lives a second.
fn encode_png(rgb: &[u8], width: u32, height: u32) -> Result<Vec<u8>, image::ImageError> {
    image::encode_png(width, height, rgb, image::PngFilter::Sub)
}

/// A written frame subsampled exactly as [`crate::farm::Farm::frame_preview`]
/// subsamples the sums, so a preview does not jump when its frame is written.
fn subsample_written(path: &std::path::Path, side: u32) -> Result<Vec<u8>, String> {
    let (w, h, img) = image::read_rgb8(path).map_err(|e| e.to_string())?;
    let step = preview_step(w, h, side);
    if step == 1 {
        return encode_png(&img, w, h).map_err(|e| e.to_string());
    }
    let (ow, oh) = (w.div_ceil(step), h.div_ceil(step));
    let off = step / 2;
    let mut rgb = Vec::with_capacity((ow * oh * 3) as usize);
    for oy in 0..oh {
        let y = (oy * step + off).min(h - 1);
        for ox in 0..ow {
            let x = (ox * step + off).min(w - 1);
            let i = (y * w + x) as usize * 3;
            rgb.extend_from_slice(&img[i..i + 3]);
        }
    }
    encode_png(&rgb, ow, oh).map_err(|e| e.to_string())
}

/// `GET /api/jobs/{id}/frames/{frame}/preview.png?max=N`.
pub async fn preview(
    State(m): State<Arc<Monitor>>,
    Path((id, frame)): Path<(String, u32)>,
    RawQuery(query): RawQuery,
) -> Result<Response, ApiError> {
    let side = match param(&query, "max") {
        None => DEFAULT_SIDE,
        Some(v) => v
            .parse::<u32>()
            .ok()
            .filter(|s| SIDES.contains(s))
            .ok_or_else(|| {
                ApiError::bad_request(format!(
                    "max must be a whole number of pixels in {}..={}, got {v:?}",
                    SIDES.start(),
                    SIDES.end()
                ))
            })?,
    };
    let stats = &m.previews.stats;
    stats.served.fetch_add(1, Ordering::Relaxed);
    let key = (id.clone(), frame, side);
    let mut cache = m.previews.cache.lock().await;
    // A written frame's preview never changes; another is made again only
    // after INTERVAL, but a frame written meanwhile is shown at once.
    let (known, recent) = match cache.get(&key) {
        Some(e) if e.units_done.is_none() => return Ok(png_response(e)),
        Some(e) => (e.units_done, e.made.elapsed() < INTERVAL),
        None => (None, false),
    };
    let t = Instant::now();
    let look = m.farm.frame_preview(&id, frame, side, known, recent)?;
    let us = t.elapsed().as_micros() as u64;
    stats.lock_us_max.fetch_max(us, Ordering::Relaxed);
    stats.lock_us_sum.fetch_add(us, Ordering::Relaxed);
    let t = Instant::now();
    let (png, units_done) = match look {
        FramePreview::Unchanged | FramePreview::Writing => {
            return match cache.get(&key) {
                Some(e) => Ok(png_response(e)),
                // Writing, and never previewed: the sums are with the writer.
                None => Err(ApiError::new(
                    StatusCode::SERVICE_UNAVAILABLE,
                    "the frame is being written; ask again in a moment",
                )),
            };
        }
        FramePreview::Partial {
            film,
            frame_units_done,
            ..
        } => {
            let png = tokio::task::spawn_blocking(move || {
                encode_png(&film.srgb8(), film.rect.width, film.rect.height)
            })
            .await
            .map_err(|e| internal("preview", e))?
            .map_err(|e| internal("preview", e))?;
            (png, Some(frame_units_done))
        }
        FramePreview::Written(path) => {
            let png = tokio::task::spawn_blocking(move || subsample_written(&path, side))
                .await
                .map_err(|e| internal("preview", e))?
                .map_err(|e| internal("preview of the written frame", e))?;
            (png, None)
        }
    };
    stats.made.fetch_add(1, Ordering::Relaxed);
    stats
        .encode_us_sum
        .fetch_add(t.elapsed().as_micros() as u64, Ordering::Relaxed);
    if cache.len() >= KEPT
        && let Some(oldest) = cache
            .iter()
            .min_by_key(|(_, e)| e.made)
            .map(|(k, _)| k.clone())
    {
        cache.remove(&oldest);
    }
    let entry = Entry {
        png: Bytes::from(png),
        made: Instant::now(),
        units_done,
    };
    let resp = png_response(&entry);
    cache.insert(key, entry);
    Ok(resp)
}

/// `GET /api/jobs/{id}/frames/{frame}/image.png[?download=1]`: the written
/// frame as the coordinator wrote it.
pub async fn image(
    State(m): State<Arc<Monitor>>,
    Path((id, frame)): Path<(String, u32)>,
    RawQuery(query): RawQuery,
) -> Result<Response, ApiError> {
    let (_, name, path) = m
        .farm
        .outputs(&id)?
        .into_iter()
        .find(|o| o.0 == frame)
        .ok_or_else(|| {
            ApiError::new(
                StatusCode::NOT_FOUND,
                format!("frame {frame} of job {id} is not written (yet)"),
            )
        })?;
    let bytes = tokio::fs::read(&path)
        .await
        .map_err(|e| internal(&path.display().to_string(), e))?;
    let mut resp = (
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "private, max-age=3600"),
        ],
        bytes,
    )
        .into_response();
    if param(&query, "download").is_some_and(|v| v == "1") {
        // Ids and frame file names are ASCII letters, digits, '_' and '.'.
        let value = format!("attachment; filename=\"{id}_{name}\"");
        if let Ok(v) = header::HeaderValue::from_str(&value) {
            resp.headers_mut().insert(header::CONTENT_DISPOSITION, v);
        }
    }
    Ok(resp)
}
