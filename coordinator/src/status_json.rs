//! A job's JSON: the one shape that `tessera jobs/status/watch --json`
//! print, the web monitor's `/api/jobs` and events serve (docs/monitor.md)
//! and the coordinator's notifications (`--on-done`, `--notify`) POST.
//! Built from the wire's `pb::JobStatus` only, so the CLI (over gRPC) and
//! the monitor (from the farm's view, through `service::job_status`) give
//! the same fields with the same values. It carries both names the two
//! used to give (`job_id` and `id`; the settings flat and as `settings`).

use std::collections::BTreeMap;

use serde::Serialize;
use tessera_proto::pb;

/// A job state's name, as the CLI and the JSON write it: the one table.
pub fn state_name(state: i32) -> &'static str {
    match pb::JobState::try_from(state).unwrap_or(pb::JobState::Unspecified) {
        pb::JobState::Waiting => "waiting",
        pb::JobState::Queued => "queued",
        pb::JobState::Running => "running",
        pb::JobState::Done => "done",
        pb::JobState::Failed => "failed",
        pb::JobState::Cancelled => "cancelled",
        pb::JobState::Unspecified => "unknown",
    }
}

/// A job (docs/cli.md "JSON output", docs/monitor.md "API").
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct JobJson {
    /// The job's id, under both names (`id` is the same value).
    pub job_id: String,
    pub id: String,
    pub name: String,
    /// "waiting", "queued", "running", "done", "failed" or "cancelled".
    pub state: &'static str,
    pub priority: i32,
    /// Share of the job done, 0 to 1: its pixel-samples merged over those
    /// it will trace (the coordinator's one figure, docs/cli.md).
    pub progress: f64,
    /// The render settings, flat (as `settings` has them too).
    pub width: u32,
    pub height: u32,
    pub samples: u32,
    pub max_depth: u32,
    /// "whitted" or "path"; null for a status from a coordinator older
    /// than the path tracer.
    pub integrator: Option<&'static str>,
    pub first_frame: u32,
    pub last_frame: u32,
    pub tile_size: u32,
    pub samples_per_unit: u32,
    pub settings: SettingsJson,
    pub units_total: u64,
    pub units_done: u64,
    pub samples_total: u64,
    pub samples_done: u64,
    pub rays: RaysJson,
    pub rays_per_second: f64,
    /// Seconds left; null while unknown (no rate measured yet).
    pub eta_seconds: Option<f64>,
    pub results_accepted: u64,
    pub results_rejected: u64,
    pub results_late: u64,
    pub results_duplicate: u64,
    pub submitted_unix_ms: i64,
    /// null until the job ends.
    pub finished_unix_ms: Option<i64>,
    /// This coordinator run's timeline of the job; null until then.
    pub first_lease_unix_ms: Option<i64>,
    pub first_result_unix_ms: Option<i64>,
    pub last_result_unix_ms: Option<i64>,
    pub output_dir: String,
    /// The job's frames, or one page of them (see [`JobJson::paged`]).
    pub frames: Vec<FrameJson>,
    /// How many frames the job has.
    pub frames_total: u32,
    /// The first frame of the next page; null when `frames` runs to the
    /// job's last frame.
    pub frames_next: Option<u32>,
    /// Why the job failed or was cancelled; null otherwise.
    pub error: Option<String>,
    /// An adaptive job's targets and where it stands; null for uniform jobs.
    pub adaptive: Option<AdaptiveJson>,
    /// Labels a worker needs to lease its units (`submit --require`).
    pub requirements: Vec<String>,
    /// While no connected worker meets the requirements: why; else null.
    pub unrunnable: Option<String>,
    /// Workers kept from this job for now (docs/operations.md).
    pub blocklisted: Vec<BlockedJson>,
    /// The jobs it runs after (`submit --after`) ...
    pub after: Vec<String>,
    /// ... and, while "waiting", those of them not done yet.
    pub waiting_for: Vec<String>,
    /// Its blocklist settings: failed units before a worker is kept from
    /// it (0: never), seconds until forgiven.
    pub blocklist_after: u32,
    pub blocklist_seconds: f64,
    /// Units' failures reported by workers, by class.
    pub failure_classes: BTreeMap<String, u64>,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct SettingsJson {
    /// The scene's name as submitted.
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

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct RaysJson {
    pub primary: u64,
    pub shadow: u64,
    pub reflection: u64,
    pub refraction: u64,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct FrameJson {
    pub frame: u32,
    pub units_total: u64,
    pub units_done: u64,
    /// Share of the frame done, 0 to 1 (sample-weighted, as the job's).
    pub progress: f64,
    /// Its image's file name in the job's output directory, once written ...
    pub output: Option<String>,
    /// ... and whether it is (viewable full size and downloadable).
    pub written: bool,
}

/// An adaptive job's targets and where it stands.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct AdaptiveJson {
    pub target_error: f64,
    pub relative_error: f64,
    pub min_samples: u32,
    pub max_samples: u32,
    pub converged_share: f64,
    pub estimated_error: f64,
    /// "pixel" (each pixel's error) or "image" (the image's RMSE).
    pub mode: &'static str,
}

/// A worker on a job's blocklist.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct BlockedJson {
    pub worker_id: String,
    pub name: String,
    pub failures: u32,
    pub until_unix_ms: i64,
}

fn nonzero(ms: i64) -> Option<i64> {
    (ms > 0).then_some(ms)
}

fn non_empty(s: &str) -> Option<String> {
    (!s.is_empty()).then(|| s.to_string())
}

impl From<&pb::FrameStatus> for FrameJson {
    fn from(f: &pb::FrameStatus) -> Self {
        FrameJson {
            frame: f.frame,
            units_total: f.units_total,
            units_done: f.units_done,
            progress: f.progress,
            output: non_empty(&f.output),
            written: !f.output.is_empty(),
        }
    }
}

impl From<&pb::JobStatus> for JobJson {
    fn from(j: &pb::JobStatus) -> Self {
        use tessera_proto::convert::{integrator_from_pb, sampler_from_pb};
        let s = j.settings.unwrap_or_default();
        let r = j.rays.unwrap_or_default();
        let integrator = integrator_from_pb(s.integrator).map(|i| i.name());
        JobJson {
            job_id: j.job_id.clone(),
            id: j.job_id.clone(),
            name: j.name.clone(),
            state: state_name(j.state),
            priority: j.priority,
            progress: j.progress,
            width: s.width,
            height: s.height,
            samples: s.samples,
            max_depth: s.max_depth,
            integrator,
            first_frame: j.first_frame,
            last_frame: j.last_frame,
            tile_size: j.tile_size,
            samples_per_unit: j.samples_per_unit,
            settings: SettingsJson {
                scene: j.scene.clone(),
                width: s.width,
                height: s.height,
                samples: s.samples,
                integrator: integrator.unwrap_or("whitted").into(),
                max_depth: s.max_depth,
                sampler: sampler_from_pb(s.sampler)
                    .map_or("unknown", |s| s.name())
                    .into(),
                first_frame: j.first_frame,
                last_frame: j.last_frame,
                tile_size: j.tile_size,
                samples_per_unit: j.samples_per_unit,
                max_attempts: j.max_attempts,
            },
            units_total: j.units_total,
            units_done: j.units_done,
            samples_total: j.samples_total,
            samples_done: j.samples_done,
            rays: RaysJson {
                primary: r.primary,
                shadow: r.shadow,
                reflection: r.reflection,
                refraction: r.refraction,
            },
            rays_per_second: j.rays_per_second,
            eta_seconds: (j.eta_seconds >= 0.0 && j.eta_seconds.is_finite())
                .then_some(j.eta_seconds),
            results_accepted: j.units_accepted,
            results_rejected: j.results_rejected,
            results_late: j.results_late,
            results_duplicate: j.results_duplicate,
            submitted_unix_ms: j.submitted_unix_ms,
            finished_unix_ms: nonzero(j.finished_unix_ms),
            first_lease_unix_ms: nonzero(j.first_lease_unix_ms),
            first_result_unix_ms: nonzero(j.first_result_unix_ms),
            last_result_unix_ms: nonzero(j.last_result_unix_ms),
            output_dir: j.output_dir.clone(),
            frames: j.frames.iter().map(FrameJson::from).collect(),
            frames_total: (j.last_frame + 1).saturating_sub(j.first_frame),
            frames_next: None,
            error: non_empty(&j.error),
            adaptive: j.adaptive.as_ref().map(|a| AdaptiveJson {
                target_error: a.target_error,
                relative_error: a.relative_error,
                min_samples: a.min_samples,
                max_samples: a.max_samples,
                converged_share: a.converged_share,
                estimated_error: a.estimated_error,
                // An earlier coordinator says nothing: per pixel.
                mode: tessera_proto::convert::adaptive_mode_from_pb(a.mode)
                    .unwrap_or_default()
                    .name(),
            }),
            requirements: j.requirements.clone(),
            unrunnable: non_empty(&j.unrunnable),
            blocklisted: j
                .blocklisted
                .iter()
                .map(|b| BlockedJson {
                    worker_id: b.worker_id.clone(),
                    name: b.name.clone(),
                    failures: b.failures,
                    until_unix_ms: b.until_unix_ms,
                })
                .collect(),
            after: j.after.clone(),
            waiting_for: j.waiting_for.clone(),
            blocklist_after: j.blocklist_after,
            blocklist_seconds: j.blocklist_seconds,
            failure_classes: j
                .failure_classes
                .iter()
                .map(|(k, n)| (k.clone(), *n))
                .collect(),
        }
    }
}

impl JobJson {
    /// The job with only its frames numbered `from` on, at most `max` of
    /// them, and where the next page starts.
    pub fn paged(&self, from: u32, max: usize) -> JobJson {
        let start = self.frames.partition_point(|f| f.frame < from);
        let end = start.saturating_add(max).min(self.frames.len());
        JobJson {
            frames: self.frames[start..end].to_vec(),
            frames_next: self.frames.get(end).map(|f| f.frame),
            ..self.clone()
        }
    }
}

/// [`JobJson`] as a JSON value (what the CLI prints and notifications POST).
pub fn job_json(j: &pb::JobStatus) -> serde_json::Value {
    serde_json::to_value(JobJson::from(j)).expect("a job's JSON serializes")
}
