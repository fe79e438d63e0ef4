//! [`JobSpec`]: what a farm job asks for, the one Rust shape of a job
//! request.
//!
//! It lives in this crate, not in the coordinator, because both ends of
//! the wire build or read it and this is the crate they share: `tessera
//! submit` builds it from its flags and sends it (`pb::JobSpec::from`), the
//! coordinator's service receives it (`JobSpec::from(&pb::JobSpec)`) and
//! hands it to the farm inside a `Submission`. The conversions live in
//! `convert.rs`, the one place the wire's messages meet Rust types; a client
//! need not link the coordinator to speak to it. The coordinator resolves a
//! spec (the scene's `[render]` table under `overrides` and `adaptive`, its
//! defaults for what is `None`) into the settings it stores in its job
//! record.

use tracer_core::adaptive::AdaptiveSpec;
use tracer_core::scene::RenderOverrides;

/// A job as a client asks for it: its scene's name and everything beside
/// the scene's files. `None` (and an empty name) take the defaults: the
/// scene's for settings, the coordinator's for the work-unit shape.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct JobSpec {
    /// The job's name; empty: the scene's file stem.
    pub name: String,
    /// The scene file's name, as its errors name it and its files are
    /// named relative to.
    pub scene_name: String,
    /// Applied to the scene's `[render]` table.
    pub overrides: RenderOverrides,
    /// Adaptive sampling's keys given with the job (over the scene's).
    pub adaptive: AdaptiveSpec,
    /// Inclusive frame range; both 0: the single frame 0.
    pub first_frame: u32,
    pub last_frame: u32,
    /// Higher runs first.
    pub priority: i32,
    /// Tile side in pixels: the smallest piece of a frame leased.
    pub tile_size: Option<u32>,
    /// Samples per pixel in one work unit.
    pub samples_per_unit: Option<u32>,
    /// Failed attempts of one unit before the job fails.
    pub max_attempts: Option<u32>,
    /// Labels a worker needs to lease the job's units, as given
    /// (`crate::placement::Requirement` parses them; the coordinator
    /// refuses the job if one does not).
    pub requirements: Vec<String>,
    /// Jobs this one runs after (`tessera submit --after`): it waits until
    /// every one is done, and fails if one fails or is cancelled.
    pub after: Vec<String>,
    /// URLs POSTed the job's JSON when it ends (`tessera submit --on-done`).
    pub on_done: Vec<String>,
    /// This job's blocklist: failed units before a worker is kept from it
    /// (0: never), and seconds until forgiven. None: the coordinator's.
    pub blocklist_after: Option<u32>,
    pub blocklist_seconds: Option<f64>,
}
