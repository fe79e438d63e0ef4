//! [`LeasedUnit`]: a piece of a job as the coordinator leases it and a
//! worker renders it, the one Rust shape of a `pb::WorkUnit` at both ends
//! (as tray_rust declares each master-worker message once). The
//! coordinator's farm makes it (`Farm::lease`), its service sends it
//! (`pb::WorkUnit::from`), a worker reads it back
//! (`LeasedUnit::try_from(pb::WorkUnit)`, in `convert.rs`).

use std::collections::BTreeMap;

use tracer_core::adaptive::BlockMask;
use tracer_core::film::{SampleRange, WorkRegion};
use tracer_core::scene::RenderSettings;

/// A unit of work held under a lease: which pixels and samples of which
/// job's frame, and what rendering them needs.
#[derive(Clone, Debug, PartialEq)]
pub struct LeasedUnit {
    /// The lease, as its result and heartbeats name it.
    pub lease_id: String,
    pub job: LeasedJob,
    /// The frame, pixels and samples to render.
    pub region: WorkRegion,
    /// Adaptive jobs: the 8x8 blocks of `region.rect` this round samples
    /// (the result then carries sums of squares). `None`: every pixel.
    pub active: Option<BlockMask>,
    /// Adaptive jobs in the image mode: per block of `region.rect`, the
    /// sample indices it takes (empty where `active` has it off), all
    /// inside `region.samples`. `None`: every active block takes
    /// `region.samples`.
    pub ranges: Option<Vec<SampleRange>>,
    /// How many of the job's work units (tiles by sample batches) the
    /// lease covers, at least 1: what an accepted result counts as done.
    pub units: u32,
}

/// The job a leased unit belongs to, as a worker needs it to render.
#[derive(Clone, Debug, PartialEq)]
pub struct LeasedJob {
    pub job_id: String,
    /// The scene file's name, for messages.
    pub scene_name: String,
    /// SHA-256 (hex) of the scene file: fetched and cached by it.
    pub scene_sha256: String,
    /// Name -> SHA-256 of the files the scene references, in name order.
    pub files: BTreeMap<String, String>,
    pub settings: RenderSettings,
}

/// A `pb::WorkUnit` that does not make a [`LeasedUnit`]: what a worker
/// still needs to report it as the unit's failure (the coordinator counts
/// it like any other).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{why}")]
pub struct MalformedUnit {
    pub lease_id: String,
    pub region: WorkRegion,
    pub units: u32,
    pub why: String,
}
