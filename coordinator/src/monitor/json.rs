//! The JSON API's shapes (docs/monitor.md lists every field). Built from
//! the farm's views at this edge; nothing else in the coordinator knows
//! them.

use serde::Serialize;
use tracer_core::film::Rect;

use crate::farm::{FrameTile, JobState, JobView, TileState, UnitFailure, WorkerView};

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

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct FrameJson {
    pub frame: u32,
    pub units_total: u64,
    pub units_done: u64,
    /// Share of the frame done, 0 to 1 (sample-weighted, as the job's).
    pub progress: f64,
    /// The frame's image is written (viewable full size and downloadable).
    pub written: bool,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct SettingsJson {
    pub scene: String,
    pub width: u32,
    pub height: u32,
    pub samples: u32,
    /// "whitted" or "path".
    pub integrator: String,
    pub max_depth: u32,
    pub sampler: String,
    pub first_frame: u32,
    pub last_frame: u32,
    pub tile_size: u32,
    pub samples_per_unit: u32,
    pub max_attempts: u32,
}

/// An adaptive job's targets and where it stands (`null` for uniform jobs).
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct AdaptiveJson {
    pub target_error: f64,
    pub relative_error: f64,
    pub min_samples: u32,
    pub max_samples: u32,
    pub converged_share: f64,
    pub estimated_error: f64,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct JobJson {
    pub id: String,
    pub name: String,
    /// "waiting", "queued", "running", "done", "failed" or "cancelled".
    pub state: &'static str,
    pub priority: i32,
    /// Share of the job done, 0 to 1: its pixel-samples merged over those
    /// it will trace, the figure `tessera status` and `watch` show.
    pub progress: f64,
    pub units_total: u64,
    pub units_done: u64,
    pub samples_total: u64,
    pub samples_done: u64,
    pub rays_per_second: f64,
    /// Seconds left; null while unknown (no rate measured yet).
    pub eta_seconds: Option<f64>,
    pub submitted_unix_ms: i64,
    /// null until the job ends.
    pub finished_unix_ms: Option<i64>,
    pub first_result_unix_ms: Option<i64>,
    pub error: String,
    pub results_rejected: u64,
    pub results_late: u64,
    pub results_duplicate: u64,
    pub settings: SettingsJson,
    pub adaptive: Option<AdaptiveJson>,
    /// One page of the job's frames (see [`JobJson::paged`]).
    pub frames: Vec<FrameJson>,
    /// How many frames the job has.
    pub frames_total: u32,
    /// The first frame of the next page (`?frames_from=` of
    /// `/api/jobs/{id}`); null when `frames` runs to the job's last frame.
    pub frames_next: Option<u32>,
    /// Workers kept from this job for now (docs/operations.md).
    pub blocklisted: Vec<BlockedJson>,
    /// Labels a worker needs to lease its units (`submit --require`).
    pub requirements: Vec<String>,
    /// Non-empty while no connected worker meets the requirements: why.
    pub unrunnable: String,
    /// The jobs it runs after (`submit --after`).
    pub after: Vec<String>,
    /// While "waiting": those of them not done yet.
    pub waiting_for: Vec<String>,
    /// Its blocklist settings: failed units before a worker is kept from
    /// it (0: never), seconds until forgiven.
    pub blocklist_after: u32,
    pub blocklist_seconds: f64,
    /// Units' failures reported by workers, by class.
    pub failure_classes: std::collections::BTreeMap<&'static str, u64>,
}

/// Most frames a job shows in `/api/jobs` and the events' `farm`
/// snapshot, and by default in `/api/jobs/{id}`: a job's JSON no longer
/// grows with its frame count (a 100k-frame job was 6.3 MB), as GetJob's
/// frame pages.
pub const FRAMES_PAGE: usize = 1000;
/// The largest page `?frames_max=` may ask for.
pub const FRAMES_PAGE_MAX: usize = 10_000;

impl JobJson {
    /// The job with only its frames numbered `from` on, at most `max` of
    /// them, and where the next page starts.
    pub fn paged(&self, from: u32, max: usize) -> JobJson {
        let start = self.frames.partition_point(|f| f.frame < from);
        let end = start.saturating_add(max).min(self.frames.len());
        // Every field but the frames copied (they are what is paged).
        JobJson {
            frames: self.frames[start..end].to_vec(),
            frames_next: self.frames.get(end).map(|f| f.frame),
            id: self.id.clone(),
            name: self.name.clone(),
            error: self.error.clone(),
            settings: self.settings.clone(),
            adaptive: self.adaptive.clone(),
            blocklisted: self.blocklisted.clone(),
            requirements: self.requirements.clone(),
            unrunnable: self.unrunnable.clone(),
            after: self.after.clone(),
            waiting_for: self.waiting_for.clone(),
            failure_classes: self.failure_classes.clone(),
            ..*self
        }
    }
}

/// A worker on a job's blocklist.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct BlockedJson {
    pub worker_id: String,
    pub name: String,
    pub failures: u32,
    pub until_unix_ms: i64,
}

pub fn state_name(s: JobState) -> &'static str {
    match s {
        JobState::Waiting => "waiting",
        JobState::Queued => "queued",
        JobState::Running => "running",
        JobState::Done => "done",
        JobState::Failed => "failed",
        JobState::Cancelled => "cancelled",
    }
}

fn nonzero(ms: i64) -> Option<i64> {
    (ms != 0).then_some(ms)
}

impl From<&JobView> for JobJson {
    fn from(v: &JobView) -> Self {
        let r = &v.record;
        JobJson {
            id: r.id.clone(),
            name: r.name.clone(),
            state: state_name(v.state),
            priority: r.priority,
            progress: v.progress,
            units_total: v.units_total,
            units_done: v.units_done,
            samples_total: v.samples_total,
            samples_done: v.samples_done,
            rays_per_second: v.rays_per_second,
            eta_seconds: (v.eta_seconds >= 0.0 && v.eta_seconds.is_finite())
                .then_some(v.eta_seconds),
            submitted_unix_ms: r.submitted_unix_ms,
            finished_unix_ms: nonzero(r.finished_unix_ms),
            first_result_unix_ms: nonzero(v.first_result_unix_ms),
            error: r.error.clone(),
            results_rejected: v.counters.results_rejected,
            results_late: v.counters.results_late,
            results_duplicate: v.counters.results_duplicate,
            settings: SettingsJson {
                scene: r.scene_name.clone(),
                width: v.settings.width,
                height: v.settings.height,
                samples: v.settings.samples,
                integrator: v.settings.integrator.name().into(),
                max_depth: v.settings.max_depth,
                sampler: v.settings.sampler.name().into(),
                first_frame: r.first_frame,
                last_frame: r.last_frame,
                tile_size: r.tile_size,
                samples_per_unit: r.samples_per_unit,
                max_attempts: r.max_attempts,
            },
            blocklisted: v
                .blocklisted
                .iter()
                .map(|b| BlockedJson {
                    worker_id: b.id.clone(),
                    name: b.name.clone(),
                    failures: b.failures,
                    until_unix_ms: b.until_unix_ms,
                })
                .collect(),
            requirements: r.requirements.iter().map(ToString::to_string).collect(),
            unrunnable: v.unrunnable.clone(),
            after: r.after.clone(),
            waiting_for: v.waiting_for.clone(),
            blocklist_after: r.blocklist_after.unwrap_or(0),
            blocklist_seconds: r.blocklist_seconds.unwrap_or(0.0),
            failure_classes: v.failures.clone(),
            adaptive: v.adaptive.settings.map(|a| AdaptiveJson {
                target_error: a.target_error,
                relative_error: a.relative_error,
                min_samples: a.min_samples,
                max_samples: a.max_samples,
                converged_share: v.adaptive.converged_share,
                estimated_error: v.adaptive.estimated_error,
            }),
            frames: v
                .frames
                .iter()
                .zip(&v.frames_progress)
                .map(|((frame, total, done, out), progress)| FrameJson {
                    frame: *frame,
                    units_total: *total,
                    units_done: *done,
                    progress: *progress,
                    written: out.is_some(),
                })
                .collect(),
            frames_total: v.frames.len() as u32,
            frames_next: None,
        }
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
