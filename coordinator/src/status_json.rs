//! A job's JSON as `tessera status --json` (and `jobs --json`, `watch
//! --json`) prints it: one shape, here so that the coordinator's
//! notifications (`--on-done`, `--notify`) POST exactly what the CLI prints.

use serde_json::{Value, json};
use tessera_proto::pb;

/// A job state's name, as the CLI and the JSON write it.
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

/// A job as `tessera jobs --json`, `status --json` and `watch --json` print it.
pub fn job_json(j: &pb::JobStatus) -> Value {
    let s = j.settings.unwrap_or_default();
    let r = j.rays.unwrap_or_default();
    let mut v = json!({
        "job_id": j.job_id,
        "name": j.name,
        "state": state_name(j.state),
        "priority": j.priority,
        // The coordinator's one figure (sample-weighted, docs/cli.md).
        "progress": j.progress,
        "width": s.width,
        "height": s.height,
        "samples": s.samples,
        "max_depth": s.max_depth,
        "first_frame": j.first_frame,
        "last_frame": j.last_frame,
        "tile_size": j.tile_size,
        "samples_per_unit": j.samples_per_unit,
        "units_total": j.units_total,
        "units_done": j.units_done,
        "samples_total": j.samples_total,
        "samples_done": j.samples_done,
        "rays": {
            "primary": r.primary,
            "shadow": r.shadow,
            "reflection": r.reflection,
            "refraction": r.refraction,
        },
        "rays_per_second": j.rays_per_second,
        "eta_seconds": (j.eta_seconds >= 0.0).then_some(j.eta_seconds),
        "results_accepted": j.units_accepted,
        "results_rejected": j.results_rejected,
        "results_late": j.results_late,
        "results_duplicate": j.results_duplicate,
        "submitted_unix_ms": j.submitted_unix_ms,
        "finished_unix_ms": (j.finished_unix_ms > 0).then_some(j.finished_unix_ms),
        "first_lease_unix_ms": (j.first_lease_unix_ms > 0).then_some(j.first_lease_unix_ms),
        "first_result_unix_ms": (j.first_result_unix_ms > 0).then_some(j.first_result_unix_ms),
        "last_result_unix_ms": (j.last_result_unix_ms > 0).then_some(j.last_result_unix_ms),
        "output_dir": j.output_dir,
        "frames": j.frames.iter().map(|f| json!({
            "frame": f.frame,
            "units_total": f.units_total,
            "units_done": f.units_done,
            "progress": f.progress,
            "output": (!f.output.is_empty()).then_some(&f.output),
        })).collect::<Vec<_>>(),
        "error": (!j.error.is_empty()).then_some(&j.error),
        "adaptive": j.adaptive.as_ref().map(|a| json!({
            "target_error": a.target_error,
            "relative_error": a.relative_error,
            "min_samples": a.min_samples,
            "max_samples": a.max_samples,
            "converged_share": a.converged_share,
            "estimated_error": a.estimated_error,
        })),
        "requirements": j.requirements,
        "unrunnable": (!j.unrunnable.is_empty()).then_some(&j.unrunnable),
        "blocklisted": j.blocklisted.iter().map(|b| json!({
            "worker_id": b.worker_id,
            "name": b.name,
            "failures": b.failures,
            "until_unix_ms": b.until_unix_ms,
        })).collect::<Vec<_>>(),
    });
    // Issue 38's dependencies (beside the rest: one `json!` this long
    // passes the macro's recursion limit).
    v["integrator"] =
        json!(tessera_proto::convert::integrator_from_pb(s.integrator).map(|i| i.name()));
    v["after"] = json!(j.after);
    v["waiting_for"] = json!(j.waiting_for);
    v["blocklist_after"] = json!(j.blocklist_after);
    v["blocklist_seconds"] = json!(j.blocklist_seconds);
    v["failure_classes"] = json!(
        j.failure_classes
            .iter()
            .collect::<std::collections::BTreeMap<_, _>>()
    );
    v
}
