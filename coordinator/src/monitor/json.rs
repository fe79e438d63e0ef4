//! The JSON API's shapes (docs/monitor.md lists every field). Built from
//! the farm's views at this edge; nothing else in the coordinator knows
//! them.

use serde::Serialize;
use tracer_core::film::Rect;

pub use crate::status_json::{FrameJson, JobJson};

use crate::farm::{FrameTile, JobView, TileState, UnitFailure, WorkerView};

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct RectJson {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl From<Rect> for RectJson {
    fn from(r: Rect) -> Self {
        RectJson {
            x: r.x,
            y: r.y,
            width: r.width,
            height: r.height,
        }
    }
}

/// Most frames a job shows in `/api/jobs` and the events' `farm`
/// snapshot, and by default in `/api/jobs/{id}`: a job's JSON no longer
/// grows with its frame count (a 100k-frame job was 6.3 MB), as GetJob's
/// frame pages.
pub const FRAMES_PAGE: usize = 1000;
/// The largest page `?frames_max=` may ask for.
pub const FRAMES_PAGE_MAX: usize = 10_000;

/// A job as the monitor serves it: the one job JSON of the CLI and the
/// notifications (`status_json::JobJson`), from the farm's view through
/// the wire's status (`service::job_status`), converted at this edge only.
impl From<&JobView> for JobJson {
    fn from(v: &JobView) -> Self {
        JobJson::from(&crate::service::job_status(v))
    }
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct FailureJson {
    pub unit: u32,
    pub frame: u32,
    pub rect: RectJson,
    pub samples: [u32; 2],
    /// One per failed attempt, naming the worker.
    pub messages: Vec<String>,
}

impl From<UnitFailure> for FailureJson {
    fn from(f: UnitFailure) -> Self {
        FailureJson {
            unit: f.unit,
            frame: f.region.frame,
            rect: f.region.rect.into(),
            samples: [f.region.samples.start, f.region.samples.end],
            messages: f.messages,
        }
    }
}

/// `GET /api/jobs/{id}`: the job and its failures.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct JobDetailJson {
    #[serde(flatten)]
    pub job: JobJson,
    pub failures: Vec<FailureJson>,
}

/// A run of neighbouring tiles of one tile row in the same state.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct TileRunJson {
    #[serde(flatten)]
    pub rect: RectJson,
    /// "done", "leased", "partial" or "pending".
    pub state: &'static str,
    /// Tiles in the run.
    pub tiles: u32,
}

fn tile_state_name(s: TileState) -> &'static str {
    match s {
        TileState::Done => "done",
        TileState::Leased => "leased",
        TileState::Partial => "partial",
        TileState::Pending => "pending",
    }
}

/// Joins tiles (in row order) into runs: a frame of 8 px tiles has tens
/// of thousands of tiles but a few hundred runs.
pub fn tile_runs(tiles: &[FrameTile]) -> Vec<TileRunJson> {
    let mut runs: Vec<TileRunJson> = Vec::new();
    for t in tiles {
        let state = tile_state_name(t.state);
        if let Some(r) = runs.last_mut()
            && r.state == state
            && r.rect.y == t.rect.y
            && r.rect.height == t.rect.height
            && r.rect.x + r.rect.width == t.rect.x
        {
            r.rect.width += t.rect.width;
            r.tiles += 1;
            continue;
        }
        runs.push(TileRunJson {
            rect: t.rect.into(),
            state,
            tiles: 1,
        });
    }
    runs
}

/// `GET /api/jobs/{id}/frames/{frame}`.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct FrameDetailJson {
    pub job: String,
    #[serde(flatten)]
    pub frame: FrameJson,
    pub width: u32,
    pub height: u32,
    /// The frame's tiles as runs along each tile row, in row order.
    pub tiles: Vec<TileRunJson>,
    /// Tiles done, leased, partial and pending.
    pub tiles_done: u32,
    pub tiles_leased: u32,
    pub tiles_partial: u32,
    pub tiles_pending: u32,
}

/// What a worker holds of one frame: its leases there, summed (a fast
/// worker may hold dozens of small leases; the page needs where, not each).
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct HeldJson {
    pub job: String,
    pub frame: u32,
    pub leases: u32,
    /// Pixels of the leased rectangles.
    pub pixels: u64,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct WorkerJson {
    pub id: String,
    pub name: String,
    /// "cpu" or "gpu".
    pub backend: &'static str,
    /// The GPU adapter's name ("" for a CPU worker).
    pub adapter: String,
    pub threads: u32,
    pub version: String,
    /// "rendering" (holds leases), "idle", "silent" (no heartbeat for
    /// three intervals) or "gone" (left the farm: no heartbeat for a
    /// lease timeout).
    pub state: &'static str,
    /// Leases held now, and where (by job and frame).
    pub leases: u32,
    pub holding: Vec<HeldJson>,
    pub samples_per_second: f64,
    pub rays_per_second: f64,
    pub last_seen_unix_ms: i64,
    pub units_done: u64,
    pub units_failed: u64,
    /// When the monitor saw it gone; null while in the farm.
    pub gone_unix_ms: Option<i64>,
    /// Until when it is quarantined (its results failed validation again
    /// and again: it gets no lease); null when it is not.
    pub quarantined_until_unix_ms: Option<i64>,
}

impl WorkerJson {
    pub fn new(w: &WorkerView, state: &'static str, holding: Vec<HeldJson>) -> Self {
        WorkerJson {
            id: w.id.clone(),
            name: w.name.clone(),
            backend: w.backend.name(),
            adapter: w.gpu_name.clone(),
            threads: w.threads,
            version: w.version.clone(),
            state,
            leases: holding.iter().map(|h| h.leases).sum(),
            holding,
            samples_per_second: w.samples_per_second,
            rays_per_second: w.rays_per_second,
            last_seen_unix_ms: w.last_seen_unix_ms,
            units_done: w.units_done,
            units_failed: w.units_failed,
            gone_unix_ms: None,
            quarantined_until_unix_ms: (w.quarantined_until_unix_ms > 0)
                .then_some(w.quarantined_until_unix_ms),
        }
    }
}

/// What the event stream sends: everything the jobs and workers pages show.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct SnapshotJson {
    pub jobs: Vec<JobJson>,
    pub workers: Vec<WorkerJson>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tile(x: u32, y: u32, state: TileState) -> FrameTile {
        FrameTile {
            rect: Rect::new(x, y, 16, 16),
            state,
            batches_done: 0,
            batches: 1,
        }
    }

    #[test]
    fn tiles_join_into_runs_along_a_row_only() {
        use TileState::*;
        let tiles = [
            tile(0, 0, Done),
            tile(16, 0, Done),
            tile(32, 0, Leased),
            tile(0, 16, Leased),
            tile(16, 16, Pending),
            tile(32, 16, Pending),
        ];
        let runs: Vec<(u32, u32, u32, &str, u32)> = tile_runs(&tiles)
            .iter()
            .map(|r| (r.rect.x, r.rect.y, r.rect.width, r.state, r.tiles))
            .collect();
        // The leased tile ending row 0 does not join the one starting row 1.
        assert_eq!(
            runs,
            [
                (0, 0, 32, "done", 2),
                (32, 0, 16, "leased", 1),
                (0, 16, 16, "leased", 1),
                (16, 16, 32, "pending", 2),
            ]
        );
    }
}
