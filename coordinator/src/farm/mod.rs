//! The coordinator's state: jobs, their units, leases and workers.
//!
//! All scheduling state lives behind one mutex, held only for short,
//! non-blocking sections; durable writes happen outside it through the
//! [`Store`]. A result moves its units from *leased* to *committing* (in
//! neither the pending queue nor a lease) under the lock, is made durable,
//! and only then is marked done and merged into its frame's film. So a
//! result is accepted at most once, and a crash during the commit leaves
//! the unit unfinished (it is rendered again), never half-counted.
//!
//! It does four jobs behind that one mutex, a file each:
//! - `jobs.rs`: the clients' requests (submit, cancel, delete, job and
//!   worker views, watch, outputs, progress logs, the jobs' stored files);
//! - `lease.rs`: the leasing policy and the workers' side (register,
//!   leases sized in expected rays, held back or backed up near a job's
//!   end, heartbeats, leases handed back, withdrawn or expired);
//! - `results.rs`: result intake (checked, taken from the lease,
//!   committed, counted, merged);
//! - `frames.rs`: frame output (each frame's film as it fills, the image
//!   written once complete, the job done once every frame is).
//!
//! Beside them, `job.rs` holds a job's own bookkeeping (`impl Job`),
//! `adaptive.rs` adaptive jobs' rounds, `inspect.rs` what the web monitor
//! reads (and its priority change), and `tests.rs` the unit tests. This
//! file holds the public types, the shared state (`State` and its `Job`,
//! `Lease` and `Worker` records), `Farm::open` and small shared helpers.
//!
//! The one-mutex rule: `Farm::state` is the only lock on scheduling state.
//! A public method takes it for a short section, with no `.await` and no
//! blocking work inside; database writes, scene parsing, the cost probe,
//! the merges of large films and image writes run outside it, and what
//! comes after them locks again and looks again (the job may be gone).
//! Functions that take `&mut State` (`take`, `finish_result`,
//! `backup_lease`, `withdraw_leases`, `State::end_lease`, ...) run with it
//! held and never lock it. The farm's only other lock, each frame's film
//! (`FrameAcc::film`), is taken alone (a merge) or inside the state lock,
//! never the other way round.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet, VecDeque};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use tessera_proto::JobSpec;
use tokio::sync::watch;
use tracer_core::adaptive::BlockMask;
use tracer_core::film::{Film, RayCounts, Rect, SampleRange, WorkRegion};
use tracer_core::render::Backend;

use crate::assets::{AssetLimits, AssetStore, AssetStoreError};
use crate::rate::{Meter, WorkerSpeed};
use crate::store::{Counters, JobRecord, Store, StoreError};
use crate::units::{Layout, RESULT_BYTES_PER_PIXEL, unit_count};

// What the web monitor reads of the farm (and its priority change).
mod inspect;
pub use inspect::{FramePreview, FrameTile, LeaseSummary, TileState, UnitFailure, preview_step};
mod adaptive;
pub use adaptive::AdaptiveProgress;

mod deps;
mod frames;
mod job;
mod jobs;
mod lease;
mod results;

use frames::{FrameAcc, new_frame_film};

/// Most work units in one job.
pub const MAX_UNITS: u64 = 10_000_000;

/// Coordinator settings (see `tessera coordinator --help`).
#[derive(Clone, Debug)]
pub struct Config {
    pub data_dir: PathBuf,
    /// A lease not extended by a heartbeat for this long expires.
    pub lease_timeout: Duration,
    /// How often workers should send heartbeats.
    pub heartbeat_interval: Duration,
    /// A unit lease should take about this long on the worker it goes to.
    pub target_unit_seconds: f64,
    /// Most tiles joined into one lease for a fast worker (a run of one
    /// row of tiles, or whole rows: a GPU worker takes many).
    pub max_tiles_per_lease: u32,
    /// Largest gRPC message accepted.
    pub max_message_bytes: usize,
    /// Cadence of progress log lines.
    pub progress_interval: Duration,
    /// Bounds on stored scene files.
    pub asset_limits: AssetLimits,
    /// Largest frame (width x height) a job may have: the coordinator
    /// holds a frame's film (28 bytes a pixel) while it fills.
    pub max_frame_pixels: u64,
    /// How often stored files no job needs are looked for.
    pub collect_interval: Duration,
    /// Malformed results in a row after which a worker is quarantined.
    pub quarantine_after: u32,
    /// How long a quarantined worker gets no lease.
    pub quarantine_for: Duration,
    /// Units of one job a worker reports failed before it is kept from
    /// that job (its blocklist); 0: never.
    pub blocklist_after: u32,
    /// How long a blocklisted worker is kept from the job.
    pub blocklist_for: Duration,
    /// URLs told of every job's end (`--notify`, `crate::notify`).
    pub notify: Vec<String>,
    /// The key notifications are signed with (`--notify-secret-file`);
    /// None: none can be sent.
    pub notify_secret: Option<Vec<u8>>,
}

impl Config {
    pub fn new(data_dir: PathBuf) -> Self {
        Config {
            data_dir,
            lease_timeout: Duration::from_secs(10),
            heartbeat_interval: Duration::from_secs(1),
            // Short, because workers lease their next unit while rendering
            // (prefetch): a lease costs them no idle time, while a long one
            // on costly pixels can leave the others idle at a job's end.
            target_unit_seconds: 0.25,
            max_tiles_per_lease: 256,
            max_message_bytes: 64 << 20,
            progress_interval: Duration::from_secs(2),
            asset_limits: AssetLimits::default(),
            // 8K UHD (7680 x 4320 = 33.2 M) fits; the film is 1.1 GB.
            max_frame_pixels: 40_000_000,
            collect_interval: Duration::from_secs(60),
            // An honest worker sends none: five in a row is a broken or
            // hostile one, caught before it costs a job much.
            quarantine_after: 5,
            quarantine_for: Duration::from_secs(60),
            // Afanasy's defaults: 3 errors, then the host is kept from the
            // job until forgiven.
            blocklist_after: 3,
            blocklist_for: Duration::from_secs(30 * 60),
            notify: Vec::new(),
            notify_secret: None,
        }
    }
}

/// Why a request was refused; maps onto gRPC status codes at the edge.
#[derive(Debug, thiserror::Error)]
pub enum FarmError {
    #[error("{0}")]
    InvalidArgument(String),
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    FailedPrecondition(String),
    /// A worker session asked for what another session holds (a lease).
    #[error("{0}")]
    PermissionDenied(String),
    /// Over a configured limit (the message names it).
    #[error("{0}")]
    ResourceExhausted(String),
    /// A storage failure that may pass (a full disk): nothing was recorded.
    #[error("{0}")]
    Unavailable(String),
    #[error("storage: {0}")]
    Store(#[from] StoreError),
    #[error("{0}")]
    Internal(String),
}

/// Everything a submit carries, already unpacked from the wire: what the
/// job asks for and the scene's files.
#[derive(Clone, Debug, Default)]
pub struct Submission {
    pub spec: JobSpec,
    /// The scene file's text.
    pub scene: Vec<u8>,
    /// Files sent inline: (name, content).
    pub assets: Vec<(String, Vec<u8>)>,
    /// Files already uploaded: name -> sha256.
    pub files: BTreeMap<String, String>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JobState {
    /// Its units are not leased until every job it runs after
    /// (`JobRecord::after`) is done (`farm/deps.rs`).
    Waiting,
    Queued,
    Running,
    Done,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobState::Done | JobState::Failed | JobState::Cancelled
        )
    }

    /// Whether its units may be leased: not ended, not waiting for others.
    pub fn leasable(self) -> bool {
        !self.is_terminal() && self != JobState::Waiting
    }
}

/// A snapshot of a job for clients.
#[derive(Clone, Debug)]
pub struct JobView {
    /// The job's progress, 0 to 1, as every client shows it (one
    /// definition: sample-weighted, see `Job::progress`).
    pub progress: f64,
    /// Each frame's progress, 0 to 1, in the order of `frames`.
    pub frames_progress: Vec<f64>,
    /// The job as accepted; its `settings` are what every frame renders
    /// with.
    pub record: JobRecord,
    pub state: JobState,
    pub counters: Counters,
    pub units_total: u64,
    pub units_done: u64,
    pub samples_total: u64,
    pub samples_done: u64,
    /// (frame, units total, units done, output file if written)
    pub frames: Vec<(u32, u64, u64, Option<String>)>,
    pub rays_per_second: f64,
    pub eta_seconds: f64,
    /// This run's first lease, first and last merged result (unix ms, 0 = not yet).
    pub first_lease_unix_ms: i64,
    pub first_result_unix_ms: i64,
    pub last_result_unix_ms: i64,
    /// Adaptive jobs: converged share, estimated error, samples expected.
    pub adaptive: AdaptiveProgress,
    /// Workers kept from this job for now (its blocklist).
    pub blocklisted: Vec<BlockedWorker>,
    /// Non-empty while the job waits and no connected worker meets its
    /// requirements (`State::unrunnable`): what they lack.
    pub unrunnable: String,
    /// While [`JobState::Waiting`]: the jobs it runs after not done yet.
    pub waiting_for: Vec<String>,
    /// Units' failures reported by workers, by class (this run).
    pub failures: BTreeMap<&'static str, u64>,
}

/// A worker on a job's blocklist.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BlockedWorker {
    /// Its public id ([`public_worker_id`]).
    pub id: String,
    pub name: String,
    /// Units of the job it reported failed.
    pub failures: u32,
    /// When it is forgiven (unix ms).
    pub until_unix_ms: i64,
}

/// What a worker says of itself when it registers.
#[derive(Clone, Debug)]
pub struct WorkerCaps {
    pub threads: u32,
    pub backend: Backend,
    pub gpu_name: String,
    pub version: String,
    /// The machine it runs on (empty: unknown).
    pub host_id: String,
    /// Its labels (`tessera worker --label` and the automatic ones),
    /// already checked (`tessera_proto::placement::check_labels`).
    pub labels: BTreeMap<String, String>,
    /// Whether it renders units whose blocks have their own ranges (the
    /// image mode's rounds); an older worker gets none of them.
    pub block_ranges: bool,
}

#[derive(Clone, Debug)]
pub struct WorkerView {
    /// Its public id ([`public_worker_id`] of its session): never the
    /// session itself, which is what lets a worker speak for its leases.
    pub id: String,
    pub name: String,
    pub threads: u32,
    pub backend: Backend,
    pub gpu_name: String,
    pub version: String,
    /// The machine it runs on, as it says (empty: unknown).
    pub host_id: String,
    pub leases: u32,
    pub units_done: u64,
    /// Units it reported failed, sent malformed or let expire.
    pub units_failed: u64,
    pub samples_per_second: f64,
    pub rays_per_second: f64,
    pub last_seen_unix_ms: i64,
    /// Until when it is quarantined (unix ms; 0: it is not).
    pub quarantined_until_unix_ms: i64,
    /// The labels jobs' requirements are matched against.
    pub labels: BTreeMap<String, String>,
    /// See [`WorkerCaps::block_ranges`].
    pub block_ranges: bool,
}

/// A worker's result, unpacked from the wire (sizes already checked against `rect`).
#[derive(Debug)]
pub struct ResultData {
    pub worker_id: String,
    pub lease_id: String,
    pub rect: Rect,
    pub samples: SampleRange,
    /// `Err` holds why the packed data did not decode.
    pub film: Result<Film, String>,
    /// The film's fields as they came over the wire (they decoded to
    /// `film`): stored as they are, not encoded again.
    pub packed: Option<tessera_proto::film_codec::Packed>,
    pub render_seconds: f64,
    pub failure: Option<String>,
    /// With `failure`: its kind, as the worker says.
    pub failure_class: FailureClass,
}

/// Why a unit failed on a worker (issue 38): a scene error reported by a
/// second worker fails the job at once (`Job::scene_error`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum FailureClass {
    Unspecified,
    Scene,
    OutOfMemory,
    GpuLost,
    WorkerCrash,
    Timeout,
}

impl FailureClass {
    /// As `status` and the JSON name it.
    pub fn name(self) -> &'static str {
        match self {
            FailureClass::Unspecified => "unspecified",
            FailureClass::Scene => "scene",
            FailureClass::OutOfMemory => "out_of_memory",
            FailureClass::GpuLost => "gpu_lost",
            FailureClass::WorkerCrash => "worker_crash",
            FailureClass::Timeout => "timeout",
        }
    }
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Outcome {
    Accepted,
    Rejected(String),
    Late(String),
    Duplicate(String),
    FailureRecorded,
}

struct Job {
    /// The job as stored, its settings among it.
    rec: JobRecord,
    layout: Layout,
    /// Expected rays of one pixel-sample pass over each tile (`cost::probe`):
    /// leases are sized in rays. Set through [`Job::set_tile_rays`].
    tile_rays: Vec<f64>,
    /// Expected rays of the units not done yet: the work the ETA divides.
    work_left: f64,
    /// Expected rays done over time in this coordinator's run: the rate
    /// the ETA divides by.
    meter: Meter,
    state: JobState,
    done: Vec<bool>,
    pending: BTreeSet<u32>,
    /// Failed attempts per unit.
    failures: HashMap<u32, Vec<Failure>>,
    frames: BTreeMap<u32, FrameAcc>,
    /// Counts frame changes; see `FrameAcc::changed`.
    frame_seq: u64,
    counters: Counters,
    units_done: u64,
    samples_done: u64,
    /// Pixel-samples and rays finished in this coordinator's lifetime, and since when.
    started: Option<Instant>,
    /// When it ended (done, failed, cancelled): its rate stops there.
    stopped: Option<Instant>,
    /// This run's first lease and first and last merged results, unix ms
    /// (0: not yet), taken when they happen so every view says the same.
    first_lease_unix_ms: i64,
    first_result_unix_ms: i64,
    last_result_unix_ms: i64,
    samples_this_run: u64,
    rays_this_run: u64,
    watch: watch::Sender<u64>,
    /// Adaptive jobs only (`farm/adaptive.rs`).
    adaptive: Option<adaptive::AdaptiveJob>,
    /// Failure reports per worker session, and the blocklist they lead
    /// to (see `Job::count_failure`).
    worker_failures: HashMap<String, WorkerFailures>,
    /// Whether its end was handed to the notifier (`Farm::jobs_ended`);
    /// a job that had ended before this run is not announced again.
    announced: bool,
    /// Failure reports by class (`FailureClass::name`), this run.
    failure_classes: BTreeMap<&'static str, u64>,
    /// The first scene error reported: (worker session, its name, the message).
    scene_error: Option<(String, String, String)>,
    /// Units that ran out of memory or lost their GPU, and where they may
    /// go next (`Job::reroute`); the lease loop skips them for a worker
    /// that does not qualify. Not persisted.
    reroutes: HashMap<u32, tessera_proto::placement::Reroute>,
}

/// One worker's failures of one job's units.
#[derive(Clone, Debug, Default)]
struct WorkerFailures {
    name: String,
    /// Failure reports since it was last forgiven.
    count: u32,
    /// Kept from the job until then.
    blocked_until: Option<Instant>,
}

/// One failed attempt of a unit.
#[derive(Clone, Debug)]
struct Failure {
    /// The session that failed it.
    worker: String,
    message: String,
}

struct Lease {
    /// The session it was granted to: only that session's results and
    /// returns are taken for it.
    worker: String,
    job: String,
    units: Vec<u32>,
    region: WorkRegion,
    deadline: Instant,
    /// Pixel-samples the worker reports done (heartbeats).
    progress: u64,
    /// The cost probe's expected rays of the whole lease.
    expected_rays: f64,
    /// Adaptive jobs: the blocks of `region.rect` this round samples.
    active: Option<BlockMask>,
    /// Image-mode adaptive jobs: each block's own range (see
    /// `LeasedUnit::ranges`).
    ranges: Option<Vec<tracer_core::film::SampleRange>>,
    /// The other leases of the same units, when backups duplicate a lease
    /// (faster idle workers taking a slower worker's lease at a job's end):
    /// the first result wins and the others are withdrawn.
    partners: Vec<String>,
    /// Whether this lease is a backup (its work is counted in flight once,
    /// under the original).
    backup: bool,
    /// Backups of this lease granted so far: at most [`lease::MAX_BACKUPS`] (a
    /// worker whose backups fail must not take them again and again).
    backups: u32,
    /// Whether the worker's speed was rated from this lease's unit already
    /// (reported rendered with a lease request, before its result came).
    rated: bool,
}

struct Worker {
    name: String,
    threads: u32,
    backend: Backend,
    gpu_name: String,
    version: String,
    /// The machine it runs on, as it says (empty: unknown).
    host_id: String,
    /// What jobs' requirements are matched against (see `Farm::register`).
    labels: BTreeMap<String, String>,
    /// See [`WorkerCaps::block_ranges`].
    block_ranges: bool,
    last_seen: Instant,
    leases: HashSet<String>,
    units_done: u64,
    units_failed: u64,
    /// Samples and rays per busy second over its recent results (shown to users).
    speed: WorkerSpeed,
    /// Smoothed rays per second, from its results (sizes its leases).
    ray_speed: f64,
    /// Rays and render seconds of its last result: a worker whose leases
    /// render in a fraction of the target gets larger ones at once.
    last_rays: f64,
    last_seconds: f64,
    /// Its best rays per second of late, and when it was measured: the
    /// speed the *other* workers' leases are sized against (see
    /// [`Worker::farm_speed`]).
    peak_speed: f64,
    peak_at: Instant,
    /// Results of its in a row that failed validation.
    malformed_in_a_row: u32,
    /// Quarantined until then: no lease (see `Farm::quarantine`).
    quarantined_until: Option<Instant>,
}

#[derive(Default)]
struct State {
    jobs: BTreeMap<String, Job>,
    leases: HashMap<String, Lease>,
    /// Leases that ended without a result (expired, withdrawn): lease -> job.
    gone: HashMap<String, String>,
    /// Leases whose result was accepted: lease -> job.
    consumed: HashMap<String, String>,
    ended_order: VecDeque<String>,
    /// By session (the id `Register` returned, which the worker sends).
    workers: HashMap<String, Worker>,
    next_id: u64,
    /// Since when jobs have waited with no worker connected, and whether
    /// that was logged (once per such stretch, not every tick).
    unserved_since: Option<Instant>,
    unserved_warned: bool,
}

impl State {
    /// Why no connected worker can run `job` (empty: one can, or the job
    /// has no requirements or has ended): a job nobody can run says so
    /// instead of waiting silently.
    fn unrunnable(&self, job: &Job) -> String {
        let reqs = &job.rec.requirements;
        if !job.state.is_terminal() {
            // Rerouted units that no connected worker (meeting the job's
            // requirements) may take: the job cannot finish until one comes.
            let stuck = job
                .reroutes
                .iter()
                .filter(|(u, _)| job.pending.contains(u))
                .filter(|(_, r)| {
                    !self.workers.iter().any(|(id, w)| {
                        tessera_proto::placement::meets(reqs, &w.labels) && r.admits(id, &w.labels)
                    })
                })
                .map(|(_, r)| r)
                .collect::<Vec<_>>();
            if let Some(r) = stuck.first() {
                return format!(
                    "{} unit(s) that failed for want of memory or a GPU wait for {r}: no connected worker is one",
                    stuck.len()
                );
            }
        }
        if reqs.is_empty()
            || job.state.is_terminal()
            || self
                .workers
                .values()
                .any(|w| tessera_proto::placement::meets(reqs, &w.labels))
        {
            return String::new();
        }
        let all = reqs
            .iter()
            .map(ToString::to_string)
            .collect::<Vec<_>>()
            .join(", ");
        let n = self.workers.len();
        if n == 0 {
            return format!(
                "no worker is connected; the job needs one with {all} (tessera worker --label KEY=VALUE)"
            );
        }
        let lacking = reqs
            .iter()
            .map(|r| {
                let lack = self
                    .workers
                    .values()
                    .filter(|w| !r.met_by(&w.labels))
                    .count();
                format!("{lack} lack {r}")
            })
            .collect::<Vec<_>>()
            .join(", ");
        format!("no connected worker meets its requirements ({all}): of {n} connected, {lacking}")
    }

    /// A job's view with what only the whole state knows (its placement).
    fn view_of(&self, job: &Job, mut v: JobView) -> JobView {
        v.unrunnable = self.unrunnable(job);
        v.waiting_for = self.waiting_for(job);
        v
    }
}

/// Remembered ended leases, to tell late and duplicate results from unknown ones.
const REMEMBERED_LEASES: usize = 100_000;

impl State {
    /// After a lease's result was taken: its partner's work is not needed
    /// any more, so that lease is withdrawn (its holder stops at its next
    /// heartbeat; a result it still sends is dropped as late).
    fn withdraw_partners(&mut self, l: &Lease) {
        for id in &l.partners {
            if let Some(p) = self.leases.remove(id) {
                if let Some(w) = self.workers.get_mut(&p.worker) {
                    w.leases.remove(id);
                }
                self.end_lease(id.clone(), p.job, false);
            }
        }
    }

    /// After a lease ended without a result (failed, rejected, expired or
    /// handed back): whether its partner still holds the units, which then
    /// stay with it instead of being queued again or failed.
    fn partner_keeps(&mut self, id: &str, l: &Lease) -> bool {
        let mut kept = false;
        for p in &l.partners {
            if let Some(p) = self.leases.get_mut(p) {
                p.partners.retain(|q| q != id);
                kept = true;
            }
        }
        kept
    }

    fn end_lease(&mut self, id: String, job: String, consumed: bool) {
        if consumed {
            self.consumed.insert(id.clone(), job);
        } else {
            self.gone.insert(id.clone(), job);
        }
        self.ended_order.push_back(id);
        while self.ended_order.len() > REMEMBERED_LEASES {
            if let Some(old) = self.ended_order.pop_front() {
                self.gone.remove(&old);
                self.consumed.remove(&old);
            }
        }
    }
}

pub struct Farm {
    pub config: Config,
    store: Store,
    /// The scene files, content-addressed, under `data_dir/assets`.
    pub assets: AssetStore,
    /// Results for leases this run never granted (from before a restart):
    /// dropped, and counted here since no job can count them.
    pub results_unknown_lease: std::sync::atomic::AtomicU64,
    /// Frames whose image cannot be written at the moment (retrying).
    pub(crate) frames_failing: std::sync::atomic::AtomicU32,
    state: Mutex<State>,
    /// Distinguishes this run's job ids from earlier runs'.
    boot: String,
    /// Woken whenever units become pending (a job submitted, units queued
    /// again), for workers waiting in [`Farm::lease_or_wait`].
    work_ready: tokio::sync::Notify,
    /// Prometheus counters and histograms (`crate::metrics`).
    pub metrics: crate::metrics::Metrics,
    /// Job-end notifications (`crate::notify`).
    pub notifier: crate::notify::Notifier,
    /// Jobs whose notifications are all delivered or given up: the task
    /// [`Farm::open`] starts clears their stored `notify_pending`.
    notified: tokio::sync::mpsc::UnboundedSender<String>,
}

fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// A job's or worker's name as shown in terminals and logs: printable, no
/// control characters (an escape sequence or newline in a name would
/// rewrite `tessera jobs`' output), at most `max` characters.
pub fn check_name(what: &str, name: &str, max: usize) -> Result<(), FarmError> {
    if name.chars().count() > max || name.chars().any(char::is_control) {
        return Err(FarmError::InvalidArgument(format!(
            "{what} {:?} must be printable text of at most {max} characters, without control characters",
            name.chars().take(60).collect::<String>()
        )));
    }
    Ok(())
}

/// A random id: `prefix` and 128 bits from the operating system's
/// generator, in hex. A worker's session and a lease grant something to
/// whoever names them, so they must not be guessable (they were a counter:
/// any holder of the worker token could send results for another's lease).
fn random_id(prefix: &str) -> String {
    let mut bytes = [0u8; 16];
    // The same generator TLS (ring) draws its keys from: without it the
    // coordinator could not serve TLS either.
    getrandom::getrandom(&mut bytes).expect("the operating system's random number generator");
    format!("{prefix}{}", tessera_proto::transport::hex(&bytes))
}

pub use tessera_proto::transport::public_worker_id;

pub(crate) fn asset_error(e: AssetStoreError) -> FarmError {
    match e {
        AssetStoreError::NotFound(m) => {
            FarmError::NotFound(format!("asset {m} is not on the coordinator"))
        }
        e @ (AssetStoreError::TooLarge { .. }
        | AssetStoreError::StoreFull { .. }
        | AssetStoreError::Busy { .. }) => FarmError::ResourceExhausted(e.to_string()),
        e @ AssetStoreError::Io { .. } => FarmError::Unavailable(e.to_string()),
        e => FarmError::InvalidArgument(e.to_string()),
    }
}

pub fn frame_file_name(frame: u32) -> String {
    format!("frame_{frame:04}.png")
}

impl Farm {
    /// Opens (or creates) the state under `config.data_dir` and resumes every unfinished job.
    pub fn open(config: Config) -> Result<Arc<Self>, FarmError> {
        std::fs::create_dir_all(&config.data_dir).map_err(|e| {
            FarmError::Internal(format!("cannot create {}: {e}", config.data_dir.display()))
        })?;
        let store = Store::open(&config.data_dir.join("tessera.redb"))?;
        let assets = AssetStore::open(&config.data_dir.join("assets"), config.asset_limits)
            .map_err(|e| {
                FarmError::Internal(format!(
                    "cannot open the asset store in {}: {e}",
                    config.data_dir.join("assets").display()
                ))
            })?;
        let notifier =
            crate::notify::Notifier::new(config.notify.clone(), config.notify_secret.clone())
                .map_err(|e| FarmError::InvalidArgument(e.to_string()))?;
        let snap = store.load()?;
        let (notified, mut settled) = tokio::sync::mpsc::unbounded_channel::<String>();
        let boot = format!("{:x}", now_ms() as u64 ^ (std::process::id() as u64) << 40);
        let farm = Arc::new(Farm {
            config,
            store,
            assets,
            results_unknown_lease: Default::default(),
            frames_failing: Default::default(),
            state: Mutex::new(State::default()),
            boot,
            work_ready: tokio::sync::Notify::new(),
            metrics: crate::metrics::Metrics::new(),
            notifier,
            notified,
        });
        if let Ok(rt) = tokio::runtime::Handle::try_current() {
            let weak = Arc::downgrade(&farm);
            rt.spawn(async move {
                while let Some(id) = settled.recv().await {
                    let Some(farm) = weak.upgrade() else { return };
                    farm.notifications_settled(&id).await;
                }
            });
        }
        let mut to_write = Vec::new();
        {
            let mut st = farm.state.lock().expect("state lock");
            let mut films = snap.unit_films;
            let mut written = snap.frames_written;
            for (rec, counters) in snap.jobs {
                // A job this coordinator cannot hold (stored by an older
                // release, or under larger limits) is left out, not allowed
                // to stop every other job from resuming.
                // Stored settings are parsed here, so checked here.
                if let Err(message) = rec.settings.validate().and_then(|()| farm.check_size(&rec)) {
                    tracing::error!(job = %rec.id, name = %rec.name, %message,
                        "job not resumed: its settings exceed what this coordinator accepts");
                    continue;
                }
                let mut rec = rec;
                // Records from before per-job blocklists: the coordinator's.
                rec.blocklist_after
                    .get_or_insert(farm.config.blocklist_after);
                rec.blocklist_seconds
                    .get_or_insert(farm.config.blocklist_for.as_secs_f64());
                let mut job = Job::new(rec, counters);
                if !job.state.is_terminal() {
                    // Derived state, not stored: probed again from the stored scene.
                    match farm.stored_scene(&job.rec) {
                        Ok(desc) => job.set_tile_rays(crate::cost::probe(
                            &desc,
                            &job.rec.settings,
                            &job.layout,
                        )),
                        Err(e) => tracing::warn!(job = %job.rec.id, error = %e,
                            "cannot read the job's scene back: leases are sized without its cost probe"),
                    }
                }
                for (frame, file) in written.remove(&job.rec.id).unwrap_or_default() {
                    for u in job.layout.frame_units(frame) {
                        job.mark_done(u);
                    }
                    if let Some(f) = job.frames.get_mut(&frame) {
                        f.written = Some(file);
                    }
                }
                // An unfinished image-mode job's rounds are replayed below;
                // an ended one's films only merge.
                let replaying = job.image_mode() && !job.state.is_terminal();
                let mut replay = Vec::new();
                for (u, film) in films.remove(&job.rec.id).unwrap_or_default() {
                    let job_id = job.rec.id.clone();
                    let corrupt = |message: String| StoreError::Corrupt {
                        what: format!("film of unit {u} of {job_id}"),
                        message,
                    };
                    let units = job.layout.units_in(u, film.rect).ok_or_else(|| {
                        corrupt(format!(
                            "its rect {:?} is not whole tiles from the unit's own",
                            film.rect
                        ))
                    })?;
                    // A frame written since holds these units already.
                    if units.iter().all(|&u| job.done[u as usize]) {
                        continue;
                    }
                    for &u in &units {
                        job.mark_done(u);
                    }
                    if replaying {
                        // Merged round by round, its runs booked, below.
                        replay.push((u, film));
                        continue;
                    }
                    let frame = job.layout.unit(u).frame;
                    let (w, h) = (job.layout.width, job.layout.height);
                    let adaptive = job.adaptive.is_some();
                    let acc = job.frames.get_mut(&frame).expect("frame of a unit");
                    let mut target = acc.film.lock().expect("frame film lock");
                    target
                        .get_or_insert_with(|| new_frame_film(w, h, adaptive))
                        .merge(&film)
                        .map_err(|e| corrupt(e.to_string()))?;
                }
                if !job.state.is_terminal() {
                    let id = job.rec.id.clone();
                    job.adaptive_restore(replay)
                        .map_err(|message| StoreError::Corrupt {
                            what: format!("rounds of {id}"),
                            message,
                        })?;
                }
                if job.state == JobState::Running && job.units_done == 0 {
                    job.state = JobState::Queued;
                }
                tracing::info!(
                    job = %job.rec.id, name = %job.rec.name, state = ?job.state,
                    units_done = job.units_done, units_total = job.layout.total(),
                    "job restored"
                );
                if !job.state.is_terminal() {
                    to_write.extend(job.complete_frames());
                }
                st.jobs.insert(job.rec.id.clone(), job);
            }
            // Dependencies are derived, not stored: a job that runs after
            // others and has not started waits again until they are done
            // (`farm/deps.rs`), and fails now if one failed meanwhile.
            for job in st.jobs.values_mut() {
                if !job.rec.after.is_empty() && job.state == JobState::Queued && job.units_done == 0
                {
                    job.state = JobState::Waiting;
                }
            }
            let failed = farm.jobs_ended(&mut st);
            if !failed.is_empty() {
                let farm = farm.clone();
                tokio::spawn(async move {
                    if let Err(e) = farm
                        .store
                        .write(failed.into_iter().map(crate::store::Op::PutJob).collect())
                        .await
                    {
                        tracing::error!(error = %e, "cannot record jobs failed with a job they run after");
                    }
                });
            }
        }
        for (job, frame) in to_write {
            farm.clone().spawn_frame_write(job, frame);
        }
        farm.clone().check_all_done();
        Ok(farm)
    }

    /// Whether the database takes writes (false during an outage such as
    /// a full disk, until the writer's probe succeeds again).
    pub fn storage_ok(&self) -> bool {
        self.store.health.ok()
    }

    /// Whether finished frames can be written (false while one is being
    /// retried after a failed write).
    pub fn frames_ok(&self) -> bool {
        self.frames_failing
            .load(std::sync::atomic::Ordering::Relaxed)
            == 0
    }

    /// Makes every result taken in so far durable (they otherwise wait up
    /// to `store::RESULTS_DURABLE_WITHIN`): for a coordinator that stops.
    pub async fn sync_store(&self) -> Result<(), StoreError> {
        self.store.sync().await
    }

    /// Writes `ops` durably, timed for `tessera_store_commit_seconds`.
    async fn commit(&self, ops: Vec<crate::store::Op>) -> Result<(), StoreError> {
        let start = Instant::now();
        let r = self.store.write(ops).await;
        self.metrics.store_commit(start.elapsed().as_secs_f64());
        r
    }

    fn check_storage(&self) -> Result<(), FarmError> {
        if self.storage_ok() {
            return Ok(());
        }
        Err(FarmError::Unavailable(format!(
            "the coordinator cannot write its database ({}); nothing was accepted. \
             It recovers by itself once writes succeed again (free space under --data); send the request again then",
            self.store.health.last_error()
        )))
    }

    /// Most pixels of one result that fit the message limit (with room
    /// for the request's other fields).
    pub fn max_result_pixels(&self) -> u64 {
        (self.config.max_message_bytes as u64).saturating_sub(64 << 10) / RESULT_BYTES_PER_PIXEL
    }

    /// A stored job's size against this coordinator's limits.
    fn check_size(&self, rec: &JobRecord) -> Result<(), String> {
        let s = &rec.settings;
        let pixels = u64::from(s.width) * u64::from(s.height);
        if pixels > self.config.max_frame_pixels {
            return Err(format!(
                "{pixels} pixels a frame, over --max-frame-pixels {}",
                self.config.max_frame_pixels
            ));
        }
        if rec.last_frame < rec.first_frame {
            return Err("empty frame range".into());
        }
        let units = unit_count(
            s.width,
            s.height,
            s.samples,
            rec.last_frame - rec.first_frame + 1,
            rec.tile_size,
            rec.samples_per_unit,
        );
        if units == 0 || units > MAX_UNITS {
            return Err(format!("{units} work units (the limit is {MAX_UNITS})"));
        }
        Ok(())
    }
}

type UnitIndex = u32;

/// Rays of a counters record as tracer-core's type.
pub fn rays_of(c: &Counters) -> RayCounts {
    RayCounts {
        primary: c.rays[0],
        shadow: c.rays[1],
        reflection: c.rays[2],
        refraction: c.rays[3],
    }
}

#[cfg(test)]
mod tests;
