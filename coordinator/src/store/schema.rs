//! The store's schema: its tables and the serde records kept in them.

use std::collections::BTreeMap;

use redb::{ReadableTable, TableDefinition};
use serde::{Deserialize, Serialize};
use tessera_proto::placement::Requirement;
use tracer_core::adaptive::{AdaptiveMode, AdaptiveSettings};
use tracer_core::sampling::Sampler;
use tracer_core::scene::{Integrator, RenderSettings};

use super::StoreError;

/// job id -> JSON [`JobRecord`]
pub(super) const JOBS: TableDefinition<&str, &[u8]> = TableDefinition::new("jobs");
/// job id -> JSON [`Counters`]
pub(super) const COUNTERS: TableDefinition<&str, &[u8]> = TableDefinition::new("counters");
/// sha256 hex -> file content: where releases before the asset store
/// (`crate::assets`) kept job files; read only, for their jobs.
pub(super) const ASSETS: TableDefinition<&str, &[u8]> = TableDefinition::new("assets");
/// (job id, unit index) -> encoded film of the finished unit, or a
/// reference to the file that holds it ([`film_files`])
pub(super) const UNIT_FILMS: TableDefinition<(&str, u32), &[u8]> =
    TableDefinition::new("unit_films");
/// Scratch space the writer's health probe writes and removes.
pub(super) const PROBE: TableDefinition<&str, &[u8]> = TableDefinition::new("probe");
/// (job id, frame) -> output file name
pub(super) const FRAMES_WRITTEN: TableDefinition<(&str, u32), &str> =
    TableDefinition::new("frames_written");

/// A job as accepted: everything needed to render it again after a restart.
/// `Farm::submit` makes it, in one place, from the job's
/// [`tessera_proto::JobSpec`] resolved against its scene and the
/// coordinator's defaults: the overrides become the settings it renders
/// with, each `None` the default it took.
///
/// Stored as JSON through the store's own record type (`JobRecordJson`,
/// converted by [`JobRecord::to_json`] and [`JobRecord::from_json`]), so
/// that no renderer type is the store's schema.
#[derive(Clone, Debug, PartialEq)]
pub struct JobRecord {
    pub id: String,
    pub name: String,
    pub scene_name: String,
    pub scene_sha256: String,
    /// Referenced files: name -> sha256.
    pub assets: BTreeMap<String, String>,
    /// The settings every frame renders with (an adaptive job's `samples`
    /// is its `max_samples`). Checked where read back (`Farm::open`).
    pub settings: RenderSettings,
    pub first_frame: u32,
    pub last_frame: u32,
    pub priority: i32,
    pub tile_size: u32,
    pub samples_per_unit: u32,
    pub max_attempts: u32,
    pub state: JobStateRec,
    pub error: String,
    pub submitted_unix_ms: i64,
    pub finished_unix_ms: i64,
    pub output_dir: String,
    /// Adaptive sampling's settings; `None`: a uniform job.
    pub adaptive: Option<AdaptiveSettings>,
    /// Labels a worker needs to lease the job's units (issue 38).
    pub requirements: Vec<Requirement>,
    /// Jobs it runs after (`submit --after`): it waits until all are done.
    pub after: Vec<String>,
    /// URLs told when it ends (`submit --on-done`).
    pub on_done: Vec<String>,
    /// Its blocklist (`submit --blocklist-after`, `--blocklist-forgive`):
    /// set at submit (or, for older records, from the coordinator's
    /// settings when read back).
    pub blocklist_after: Option<u32>,
    pub blocklist_seconds: Option<f64>,
    /// It ended and its notifications (`--on-done`, `--notify`) are not
    /// all delivered or given up yet: a coordinator that restarts sends
    /// them again (at least once, never lost).
    pub notify_pending: bool,
}

impl JobRecord {
    /// The record as the store writes it.
    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec(&JobRecordJson::from(self)).expect("records serialise")
    }

    /// A stored record, of this release or an earlier one.
    pub fn from_json(bytes: &[u8]) -> Result<JobRecord, String> {
        let json: JobRecordJson = serde_json::from_slice(bytes).map_err(|e| e.to_string())?;
        JobRecord::try_from(json)
    }
}

/// Adaptive sampling (issue 17) as a record keeps it: the error targets,
/// absolute and relative (both 0: a uniform job), and the sample bounds.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq)]
pub(super) struct AdaptiveRec {
    #[serde(default)]
    pub target_error: f64,
    #[serde(default)]
    pub min_samples: u32,
    #[serde(default)]
    pub max_samples: u32,
    #[serde(default)]
    pub relative_error: f64,
    /// Absent in records of earlier releases: per pixel.
    #[serde(default, skip_serializing_if = "is_pixel_mode")]
    pub mode: AdaptiveMode,
}

fn is_pixel_mode(m: &AdaptiveMode) -> bool {
    *m == AdaptiveMode::Pixel
}

impl AdaptiveRec {
    /// The settings, if adaptive (a target, absolute or relative, above 0).
    pub fn settings(&self) -> Option<AdaptiveSettings> {
        (self.target_error > 0.0 || self.relative_error > 0.0).then_some(AdaptiveSettings {
            target_error: self.target_error,
            relative_error: self.relative_error,
            min_samples: self.min_samples,
            max_samples: self.max_samples,
            mode: self.mode,
        })
    }
}

impl From<Option<AdaptiveSettings>> for AdaptiveRec {
    fn from(a: Option<AdaptiveSettings>) -> Self {
        a.map_or_else(AdaptiveRec::default, |a| AdaptiveRec {
            target_error: a.target_error,
            min_samples: a.min_samples,
            max_samples: a.max_samples,
            relative_error: a.relative_error,
            mode: a.mode,
        })
    }
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub enum JobStateRec {
    Active,
    Done,
    Failed,
    Cancelled,
}

/// Per-job counters. `units_accepted` is written with each result.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq, Eq)]
pub struct Counters {
    pub units_accepted: u64,
    pub results_rejected: u64,
    pub results_late: u64,
    pub results_duplicate: u64,
    pub rays: [u64; 4],
}

pub(super) fn read_counters(
    t: &redb::Table<&str, &[u8]>,
    job: &str,
) -> Result<Counters, StoreError> {
    match t.get(job)? {
        Some(v) => serde_json::from_slice(v.value()).map_err(|e| StoreError::Corrupt {
            what: format!("counters of {job}"),
            message: e.to_string(),
        }),
        None => Ok(Counters::default()),
    }
}

/// The job record version this release writes and the newest it reads.
/// Version 1, every record so far, is written without a `version` key:
/// its JSON is the object earlier releases wrote and read. A later
/// version names itself, and this release refuses it by name.
pub(super) const JOB_RECORD_VERSION: u32 = 1;

/// A job record as JSON: the store's own serde type, never a renderer
/// type. Records written by earlier releases must keep loading, so field
/// names stay as they were: the settings are flattened into `width`,
/// `height`, `samples`, `max_depth` and `sampler` (its name, "grid",
/// "jittered" or "progressive"), and the adaptive fields, which records
/// before adaptive sampling lack, default to a uniform job.
#[derive(Serialize, Deserialize)]
pub(super) struct JobRecordJson {
    #[serde(
        default = "record_version_1",
        skip_serializing_if = "is_record_version_1"
    )]
    pub version: u32,
    pub id: String,
    pub name: String,
    pub scene_name: String,
    pub scene_sha256: String,
    pub assets: BTreeMap<String, String>,
    #[serde(flatten)]
    pub settings: SettingsRec,
    pub first_frame: u32,
    pub last_frame: u32,
    pub priority: i32,
    pub tile_size: u32,
    pub samples_per_unit: u32,
    pub max_attempts: u32,
    pub state: JobStateRec,
    pub error: String,
    pub submitted_unix_ms: i64,
    pub finished_unix_ms: i64,
    pub output_dir: String,
    #[serde(flatten)]
    pub adaptive: AdaptiveRec,
    /// As `tessera submit --require` writes them; absent in earlier
    /// releases' records and left out when empty, so such records keep
    /// their shape.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub requirements: Vec<String>,
    /// `tessera submit --after` and `--on-done` (issue 38): absent in
    /// earlier records, left out when empty, as `requirements`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub after: Vec<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub on_done: Vec<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub blocklist_after: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub blocklist_seconds: Option<f64>,
    /// Absent in earlier records, left out when false.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub notify_pending: bool,
}

fn record_version_1() -> u32 {
    1
}

fn is_record_version_1(v: &u32) -> bool {
    *v == 1
}

/// Render settings as a record keeps them.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub(super) struct SettingsRec {
    pub width: u32,
    pub height: u32,
    pub samples: u32,
    pub max_depth: u32,
    pub sampler: SamplerRec,
    /// Absent (Whitted) in records older than the path integrator, and
    /// left out for Whitted so such records keep their shape.
    #[serde(default, skip_serializing_if = "IntegratorRec::is_whitted")]
    pub integrator: IntegratorRec,
}

/// An integrator as a record names it.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub(super) enum IntegratorRec {
    #[default]
    Whitted,
    Path,
}

impl IntegratorRec {
    fn is_whitted(&self) -> bool {
        *self == IntegratorRec::Whitted
    }
}

/// A sampler as a record names it.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub(super) enum SamplerRec {
    Grid,
    Jittered,
    Progressive,
}

impl From<RenderSettings> for SettingsRec {
    fn from(s: RenderSettings) -> Self {
        SettingsRec {
            width: s.width,
            height: s.height,
            samples: s.samples,
            max_depth: s.max_depth,
            sampler: match s.sampler {
                Sampler::Grid => SamplerRec::Grid,
                Sampler::Jittered => SamplerRec::Jittered,
                Sampler::Progressive => SamplerRec::Progressive,
            },
            integrator: match s.integrator {
                Integrator::Whitted => IntegratorRec::Whitted,
                Integrator::Path => IntegratorRec::Path,
            },
        }
    }
}

impl From<SettingsRec> for RenderSettings {
    fn from(s: SettingsRec) -> Self {
        RenderSettings {
            width: s.width,
            height: s.height,
            samples: s.samples,
            max_depth: s.max_depth,
            sampler: match s.sampler {
                SamplerRec::Grid => Sampler::Grid,
                SamplerRec::Jittered => Sampler::Jittered,
                SamplerRec::Progressive => Sampler::Progressive,
            },
            integrator: match s.integrator {
                IntegratorRec::Whitted => Integrator::Whitted,
                IntegratorRec::Path => Integrator::Path,
            },
        }
    }
}

impl From<&JobRecord> for JobRecordJson {
    fn from(r: &JobRecord) -> Self {
        JobRecordJson {
            version: JOB_RECORD_VERSION,
            id: r.id.clone(),
            name: r.name.clone(),
            scene_name: r.scene_name.clone(),
            scene_sha256: r.scene_sha256.clone(),
            assets: r.assets.clone(),
            settings: r.settings.into(),
            first_frame: r.first_frame,
            last_frame: r.last_frame,
            priority: r.priority,
            tile_size: r.tile_size,
            samples_per_unit: r.samples_per_unit,
            max_attempts: r.max_attempts,
            state: r.state,
            error: r.error.clone(),
            submitted_unix_ms: r.submitted_unix_ms,
            finished_unix_ms: r.finished_unix_ms,
            output_dir: r.output_dir.clone(),
            adaptive: r.adaptive.into(),
            requirements: r.requirements.iter().map(ToString::to_string).collect(),
            after: r.after.clone(),
            on_done: r.on_done.clone(),
            blocklist_after: r.blocklist_after,
            blocklist_seconds: r.blocklist_seconds,
            notify_pending: r.notify_pending,
        }
    }
}

impl TryFrom<JobRecordJson> for JobRecord {
    type Error = String;
    fn try_from(r: JobRecordJson) -> Result<Self, String> {
        if r.version > JOB_RECORD_VERSION {
            return Err(format!(
                "job record version {} is newer than the {JOB_RECORD_VERSION} this release reads",
                r.version
            ));
        }
        Ok(JobRecord {
            id: r.id,
            name: r.name,
            scene_name: r.scene_name,
            scene_sha256: r.scene_sha256,
            assets: r.assets,
            settings: r.settings.into(),
            first_frame: r.first_frame,
            last_frame: r.last_frame,
            priority: r.priority,
            tile_size: r.tile_size,
            samples_per_unit: r.samples_per_unit,
            max_attempts: r.max_attempts,
            state: r.state,
            error: r.error,
            submitted_unix_ms: r.submitted_unix_ms,
            finished_unix_ms: r.finished_unix_ms,
            output_dir: r.output_dir,
            adaptive: r.adaptive.settings(),
            requirements: Requirement::parse_all(&r.requirements).map_err(|e| e.to_string())?,
            after: r.after,
            on_done: r.on_done,
            blocklist_after: r.blocklist_after,
            blocklist_seconds: r.blocklist_seconds,
            notify_pending: r.notify_pending,
        })
    }
}
