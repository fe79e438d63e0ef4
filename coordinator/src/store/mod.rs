//! Durable state in redb: job specs, assets (content-addressed), finished
//! units' films, written frames and per-job counters. Films of a megabyte
//! or more are kept in files of their own, the database holding a
//! reference ([`film_files`]).
//!
//! Invariant: a unit is finished iff a film in `UNIT_FILMS` covers it or its
//! whole frame is in `FRAMES_WRITTEN`. A result's film is stored as it came
//! (one record for all the units its lease joined, keyed by the first; the
//! units are the layout's tiles inside its rect); the film, its units'
//! "done" mark and the job's accepted-result counter are written in one
//! transaction, so a crash can never count a finished unit twice nor keep
//! half of one. Writes go through one thread that commits whatever is
//! queued in a single transaction (group commit). A commit of results
//! alone is made durable within [`RESULTS_DURABLE_WITHIN`], not at once: a
//! GPU worker's tens of megabytes a frame would otherwise wait on an fsync
//! each, which bounded the farm's intake below the GPU's speed. The sync is
//! done as soon as the intake pauses ([`IDLE_SYNC`]), so that it runs in
//! gaps, a few results at a time, not in the frame's durable record. A crash
//! then loses at most that window of results, never a job, a frame record
//! or a state change (those commit durably, taking any results before them
//! along); the lost units are simply pending again after the restart.

mod film_files;

use std::collections::{BTreeMap, HashSet};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, RwLock, mpsc};
use std::time::{Duration, Instant};

use redb::{Database, Durability, ReadableDatabase, ReadableTable, TableDefinition};
use serde::{Deserialize, Serialize};
use tessera_proto::film_codec;
use tokio::sync::oneshot;
use tracer_core::adaptive::AdaptiveSettings;
use tracer_core::film::{Film, RayCounts, Rect};
use tracer_core::scene::RenderSettings;

/// job id -> JSON [`JobRecord`]
const JOBS: TableDefinition<&str, &[u8]> = TableDefinition::new("jobs");
/// job id -> JSON [`Counters`]
const COUNTERS: TableDefinition<&str, &[u8]> = TableDefinition::new("counters");
/// sha256 hex -> file content: where releases before the asset store
/// (`crate::assets`) kept job files; read only, for their jobs.
const ASSETS: TableDefinition<&str, &[u8]> = TableDefinition::new("assets");
/// (job id, unit index) -> encoded film of the finished unit, or a
/// reference to the file that holds it ([`film_files`])
const UNIT_FILMS: TableDefinition<(&str, u32), &[u8]> = TableDefinition::new("unit_films");
/// Scratch space the writer's health probe writes and removes.
const PROBE: TableDefinition<&str, &[u8]> = TableDefinition::new("probe");
/// (job id, frame) -> output file name
const FRAMES_WRITTEN: TableDefinition<(&str, u32), &str> = TableDefinition::new("frames_written");

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("database: {0}")]
    Db(#[from] redb::Error),
    #[error("corrupt record {what}: {message}")]
    Corrupt { what: String, message: String },
    #[error("the database writer has stopped")]
    WriterGone,
    /// A commit failed (a full disk, an I/O error): nothing of it was
    /// recorded. The writer reopens the database and probes it until
    /// writes succeed again.
    #[error("cannot write the database: {0}")]
    Commit(String),
    /// Another process (a second coordinator on the same `--data`) holds
    /// the database's lock.
    #[error("the database {} is in use by another process", .0.display())]
    InUse(std::path::PathBuf),
}

macro_rules! db_err {
    ($($t:ty),*) => {$(impl From<$t> for StoreError { fn from(e: $t) -> Self { StoreError::Db(e.into()) } })*};
}
db_err!(
    redb::DatabaseError,
    redb::TransactionError,
    redb::TableError,
    redb::StorageError,
    redb::CommitError
);

/// A job as accepted: everything needed to render it again after a restart.
/// `Farm::submit` makes it, in one place, from the job's
/// [`tessera_proto::JobSpec`] resolved against its scene and the
/// coordinator's defaults: the overrides become the settings it renders
/// with, each `None` the default it took.
///
/// Stored as JSON; records written by earlier releases must keep loading,
/// so field names stay as they were: the settings are flattened into
/// `width`, `height`, `samples`, `max_depth` and `sampler` (its name,
/// "grid", "jittered" or "progressive"), and the adaptive fields, which
/// records before adaptive sampling lack, default to a uniform job.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct JobRecord {
    pub id: String,
    pub name: String,
    pub scene_name: String,
    pub scene_sha256: String,
    /// Referenced files: name -> sha256.
    pub assets: BTreeMap<String, String>,
    /// The settings every frame renders with (an adaptive job's `samples`
    /// is its `max_samples`). Checked where read back (`Farm::open`).
    #[serde(flatten)]
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
    #[serde(flatten)]
    pub adaptive: AdaptiveRec,
}

impl JobRecord {
    /// The job's adaptive settings, if it is adaptive.
    pub fn adaptive(&self) -> Option<AdaptiveSettings> {
        self.adaptive.settings()
    }
}

/// Adaptive sampling (issue 17) as a record keeps it: the error targets,
/// absolute and relative (both 0: a uniform job), and the sample bounds.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct AdaptiveRec {
    #[serde(default)]
    pub target_error: f64,
    #[serde(default)]
    pub min_samples: u32,
    #[serde(default)]
    pub max_samples: u32,
    #[serde(default)]
    pub relative_error: f64,
}

impl AdaptiveRec {
    /// The settings, if adaptive (a target, absolute or relative, above 0).
    pub fn settings(&self) -> Option<AdaptiveSettings> {
        (self.target_error > 0.0 || self.relative_error > 0.0).then_some(AdaptiveSettings {
            target_error: self.target_error,
            relative_error: self.relative_error,
            min_samples: self.min_samples,
            max_samples: self.max_samples,
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

/// One write of a group commit.
#[derive(Debug)]
pub enum Op {
    PutJob(JobRecord),
    /// Updates the result counters that are not tied to accepted units
    /// (rejected, late, duplicate); keeps the stored accepted count and rays.
    PutCounters {
        job: String,
        counters: Counters,
    },
    /// A result: its film, keyed by the first of the `units` units it
    /// covers, and the job's accepted count and rays incremented with them.
    /// The film comes encoded ([`EncodedFilm`]) so that the writer thread
    /// only copies bytes, once, into the database, or already in its file.
    AcceptUnits {
        job: String,
        first_unit: u32,
        film: StoredFilm,
        units: u64,
        rays: [u64; 4],
    },
    /// A job is deleted: its record, counters, unit films and written frames.
    DeleteJob(String),
    /// A frame's image is written: remember it and drop its units' films.
    FrameWritten {
        job: String,
        frame: u32,
        file: String,
        units: std::ops::Range<u32>,
    },
}

impl Op {
    /// A result taken in or counted: may wait [`RESULTS_DURABLE_WITHIN`]
    /// for durability (a crash before then only makes its units pending
    /// again). Every other op is durable when its commit returns.
    pub fn is_result(&self) -> bool {
        matches!(self, Op::AcceptUnits { .. } | Op::PutCounters { .. })
    }

    /// Bytes of the films this op stores in the database.
    fn film_bytes(&self) -> usize {
        match self {
            Op::AcceptUnits {
                film: StoredFilm::Inline(film),
                ..
            } => film.len(),
            _ => 0,
        }
    }
}

/// A result's film as [`Op::AcceptUnits`] stores it.
#[derive(Debug)]
pub enum StoredFilm {
    /// In the database record itself.
    Inline(EncodedFilm),
    /// Already in a file of its own, synced; the record is this reference.
    File(Vec<u8>),
}

impl StoredFilm {
    /// The reference of a film in a file.
    pub fn file_reference(&self) -> Option<&[u8]> {
        match self {
            StoredFilm::File(r) => Some(r),
            StoredFilm::Inline(_) => None,
        }
    }
}

struct Request {
    ops: Vec<Op>,
    /// Commit durably whatever `ops` are ([`Store::sync`]).
    durable: bool,
    reply: oneshot::Sender<Result<(), String>>,
}

/// The database as the writer last (re)opened it; None while it reopens.
type Shared = Arc<RwLock<Option<Arc<Database>>>>;

/// Whether commits succeed, and why not, for health checks and messages.
#[derive(Debug, Default)]
pub struct StorageHealth {
    failing: AtomicBool,
    last_error: Mutex<String>,
}

impl StorageHealth {
    pub fn ok(&self) -> bool {
        !self.failing.load(Ordering::Relaxed)
    }
    pub fn last_error(&self) -> String {
        self.last_error.lock().expect("health lock").clone()
    }
    fn fail(&self, e: &str) {
        *self.last_error.lock().expect("health lock") = e.to_string();
        if !self.failing.swap(true, Ordering::Relaxed) {
            tracing::error!(error = %e, "storage failing: refusing new work until writes succeed again");
        }
    }
    fn recover(&self) {
        if self.failing.swap(false, Ordering::Relaxed) {
            tracing::info!("storage recovered: writes succeed again");
        }
    }
}

/// Handle to the database: reads directly, writes through the writer thread.
pub struct Store {
    db: Shared,
    films: Arc<film_files::FilmFiles>,
    tx: mpsc::Sender<Request>,
    pub health: Arc<StorageHealth>,
    // Set only by tests (`fail_commits`); the writer thread reads its clone.
    #[cfg_attr(not(test), allow(dead_code))]
    faults: Faults,
}

/// Commits to fail on purpose (tests of what a failed write does): a
/// commit whose ops include one matching the predicate fails, `n` times.
type Faults = std::sync::Arc<std::sync::Mutex<Option<(fn(&Op) -> bool, u32)>>>;

/// What is on disk at start-up.
#[derive(Debug, Default)]
pub struct Snapshot {
    pub jobs: Vec<(JobRecord, Counters)>,
    /// job -> (first unit covered, film): a film covers the units whose
    /// tiles lie in its rect
    pub unit_films: BTreeMap<String, Vec<(u32, Film)>>,
    /// job -> (frame, file)
    pub frames_written: BTreeMap<String, Vec<(u32, String)>>,
}

impl Store {
    /// The database at `path`, its large films in the directory beside
    /// it (`path` with the extension `films`).
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        let db = Database::create(path).map_err(|e| match e {
            redb::DatabaseError::DatabaseAlreadyOpen => StoreError::InUse(path.to_owned()),
            e => e.into(),
        })?;
        let path = path.to_owned();
        {
            // Create the tables so that reads of a fresh database succeed.
            let w = db.begin_write()?;
            w.open_table(JOBS)?;
            w.open_table(COUNTERS)?;
            w.open_table(ASSETS)?;
            w.open_table(UNIT_FILMS)?;
            w.open_table(FRAMES_WRITTEN)?;
            w.commit()?;
        }
        let films_dir = path.with_extension("films");
        let films = film_files::FilmFiles::open(&films_dir).map_err(|e| StoreError::Corrupt {
            what: format!("film directory {}", films_dir.display()),
            message: e.to_string(),
        })?;
        {
            // Files of results whose commit failed or was lost in a crash.
            let r = db.begin_read()?;
            let mut keep = HashSet::new();
            for entry in r.open_table(UNIT_FILMS)?.iter()? {
                let (_, v) = entry?;
                keep.extend(film_files::FilmFiles::name_of(v.value()).map(str::to_owned));
            }
            let removed = films.sweep(&keep);
            if removed > 0 {
                tracing::info!(files = removed, dir = %films_dir.display(), "removed film files of results never recorded");
            }
        }
        let films = Arc::new(films);
        let db: Shared = Arc::new(RwLock::new(Some(Arc::new(db))));
        let (tx, rx) = mpsc::channel::<Request>();
        let wdb = db.clone();
        let faults = Faults::default();
        let wfaults = faults.clone();
        let health = Arc::new(StorageHealth::default());
        let whealth = health.clone();
        let wfilms = films.clone();
        std::thread::Builder::new()
            .name("tessera-db-writer".into())
            .spawn(move || writer(&wdb, &path, rx, &wfaults, &whealth, &wfilms))
            .map_err(|e| StoreError::Corrupt {
                what: "writer thread".into(),
                message: e.to_string(),
            })?;
        Ok(Store {
            db,
            films,
            tx,
            health,
            faults,
        })
    }

    /// Whether `film` is kept in a file of its own ([`Store::store_film`]
    /// writes it there).
    pub fn keeps_in_file(&self, film: &EncodedFilm) -> bool {
        self.films.wants(film)
    }

    /// Films as [`Op::AcceptUnits`] stores them, in order: large ones
    /// written to their files now (blocking: call it off the async threads
    /// when [`Store::keeps_in_file`] says any is). A film that cannot be
    /// written is a storage outage like a failed commit, and the files
    /// written before it are removed.
    pub fn store_films(
        &self,
        films: Vec<(String, u32, EncodedFilm)>,
    ) -> Result<Vec<StoredFilm>, StoreError> {
        let mut stored = Vec::with_capacity(films.len());
        for (job, first_unit, film) in films {
            match self.store_film(&job, first_unit, film) {
                Ok(f) => stored.push(f),
                Err(e) => {
                    self.discard_films(stored.iter().filter_map(StoredFilm::file_reference));
                    return Err(e);
                }
            }
        }
        Ok(stored)
    }

    /// One film of [`Store::store_films`].
    fn store_film(
        &self,
        job: &str,
        first_unit: u32,
        film: EncodedFilm,
    ) -> Result<StoredFilm, StoreError> {
        if !self.films.wants(&film) {
            return Ok(StoredFilm::Inline(film));
        }
        if !self.health.ok() {
            return Err(StoreError::Commit(self.health.last_error()));
        }
        self.films
            .write(job, first_unit, &film)
            .map(StoredFilm::File)
            .map_err(|e| {
                self.health.fail(&e);
                // Wake the writer, which heals a failing store (it may be
                // waiting for a request that a failing store never gets).
                let (reply, _) = oneshot::channel();
                let _ = self.tx.send(Request {
                    ops: Vec::new(),
                    durable: false,
                    reply,
                });
                StoreError::Commit(e)
            })
    }

    /// Removes the files of films whose commit failed (their references,
    /// [`StoredFilm::file_reference`]).
    pub fn discard_films<'a>(&self, references: impl IntoIterator<Item = &'a [u8]>) {
        self.films.remove(
            references
                .into_iter()
                .filter_map(film_files::FilmFiles::name_of),
        );
    }

    /// Films of `len` bytes or more go to files (tests of the file path).
    #[cfg(test)]
    pub(crate) fn set_min_file_film(&self, len: usize) {
        self.films.set_min_len(len);
    }

    /// The open database, for a read.
    fn db(&self) -> Result<Arc<Database>, StoreError> {
        self.db
            .read()
            .expect("db lock")
            .clone()
            .ok_or_else(|| StoreError::Commit("the database is being reopened".into()))
    }

    /// Makes the next `times` commits that include an op matching `when` fail.
    #[cfg(test)]
    pub(crate) fn fail_commits(&self, when: fn(&Op) -> bool, times: u32) {
        *self.faults.lock().expect("faults lock") = Some((when, times));
    }

    /// Applies `ops` atomically (with whatever else is queued); returns once
    /// committed: durable at once, or within [`RESULTS_DURABLE_WITHIN`] if
    /// `ops` only accept results and count ([`Op::is_result`]).
    pub async fn write(&self, ops: Vec<Op>) -> Result<(), StoreError> {
        self.request(ops, false).await
    }

    /// Makes every commit so far durable: the results of the last
    /// [`RESULTS_DURABLE_WITHIN`] too (a coordinator stopping on purpose
    /// keeps them).
    pub async fn sync(&self) -> Result<(), StoreError> {
        self.request(Vec::new(), true).await
    }

    async fn request(&self, ops: Vec<Op>, durable: bool) -> Result<(), StoreError> {
        let (reply, rx) = oneshot::channel();
        self.tx
            .send(Request {
                ops,
                durable,
                reply,
            })
            .map_err(|_| StoreError::WriterGone)?;
        rx.await
            .map_err(|_| StoreError::WriterGone)?
            .map_err(StoreError::Commit)
    }

    pub fn asset(&self, sha256: &str) -> Result<Option<Vec<u8>>, StoreError> {
        let r = self.db()?.begin_read()?;
        let t = r.open_table(ASSETS)?;
        Ok(t.get(sha256)?.map(|v| v.value().to_vec()))
    }

    pub fn load(&self) -> Result<Snapshot, StoreError> {
        let r = self.db()?.begin_read()?;
        let mut snap = Snapshot::default();
        let jobs = r.open_table(JOBS)?;
        let counters = r.open_table(COUNTERS)?;
        for entry in jobs.iter()? {
            let (k, v) = entry?;
            let id = k.value().to_string();
            // A record this release cannot read (written by a newer one,
            // say with a sampler it does not know) is left out with an
            // error, not allowed to stop every other job from resuming.
            let rec: JobRecord = match serde_json::from_slice(v.value()) {
                Ok(rec) => rec,
                Err(e) => {
                    tracing::error!(job = %id, error = %e, "job not resumed: its stored record cannot be read");
                    continue;
                }
            };
            let c = match counters.get(id.as_str())? {
                Some(v) => serde_json::from_slice(v.value()).map_err(|e| StoreError::Corrupt {
                    what: format!("counters of {id}"),
                    message: e.to_string(),
                })?,
                None => Counters::default(),
            };
            snap.jobs.push((rec, c));
        }
        let films = r.open_table(UNIT_FILMS)?;
        for entry in films.iter()? {
            let (k, v) = entry?;
            let (job, unit) = k.value();
            let corrupt = |message| StoreError::Corrupt {
                what: format!("film of unit {unit} of {job}"),
                message,
            };
            let film = if film_files::FilmFiles::is_reference(v.value()) {
                decode_film(&self.films.read(v.value()).map_err(corrupt)?)
            } else {
                decode_film(v.value())
            }
            .map_err(corrupt)?;
            snap.unit_films
                .entry(job.to_string())
                .or_default()
                .push((unit, film));
        }
        let frames = r.open_table(FRAMES_WRITTEN)?;
        for entry in frames.iter()? {
            let (k, v) = entry?;
            let (job, frame) = k.value();
            snap.frames_written
                .entry(job.to_string())
                .or_default()
                .push((frame, v.value().to_string()));
        }
        Ok(snap)
    }
}

/// How often a failing database is reopened and probed.
const HEAL_INTERVAL: Duration = Duration::from_secs(1);

/// The longest a committed result waits for the fsync that makes it
/// durable: what a crash can cost in re-rendered units.
pub const RESULTS_DURABLE_WITHIN: Duration = Duration::from_millis(250);
/// Results not yet durable are made so as soon as the intake pauses this
/// long: the fsync (and redb's write of the buffered pages before it) then
/// runs in a gap, a few results at a time, instead of every 250 ms in the
/// middle of a frame's results, or all at once in the frame's record at
/// its end (which took 28-48 ms for a 1080p frame's 30-50 MB).
const IDLE_SYNC: Duration = Duration::from_millis(5);

fn writer(
    db: &Shared,
    path: &Path,
    rx: mpsc::Receiver<Request>,
    faults: &Faults,
    health: &StorageHealth,
    films: &Arc<film_files::FilmFiles>,
) {
    // When the oldest commit not yet durable was made.
    let mut unsynced: Option<Instant> = None;
    loop {
        let first = if let (true, Some(since)) = (health.ok(), unsynced) {
            let wait = IDLE_SYNC.min(RESULTS_DURABLE_WITHIN.saturating_sub(since.elapsed()));
            match rx.recv_timeout(wait) {
                Ok(r) => r,
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    sync(db, health, films);
                    unsynced = None;
                    continue;
                }
                Err(mpsc::RecvTimeoutError::Disconnected) => {
                    sync(db, health, films);
                    return;
                }
            }
        } else if health.ok() {
            match rx.recv() {
                Ok(r) => r,
                Err(_) => return,
            }
        } else {
            match rx.recv_timeout(HEAL_INTERVAL) {
                Ok(r) => r,
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    heal(db, path, health, films);
                    continue;
                }
                Err(mpsc::RecvTimeoutError::Disconnected) => return,
            }
        };
        let mut batch = vec![first];
        while batch.len() < 512 {
            match rx.try_recv() {
                Ok(r) => batch.push(r),
                Err(_) => break,
            }
        }
        if !health.ok() {
            heal(db, path, health, films);
            // Reopening dropped whatever was not durable yet.
            unsynced = None;
        }
        let durable = unsynced.is_some_and(|t| t.elapsed() >= RESULTS_DURABLE_WITHIN)
            || batch.iter().any(|r| r.durable)
            || !batch.iter().flat_map(|r| r.ops.iter()).all(Op::is_result);
        // Still failing after the probe: nothing commits. (A commit that
        // fits in the database's own free pages would otherwise report a
        // full disk healthy, while films and growth still fail.)
        let result = if !health.ok() {
            Err(health.last_error())
        } else if let Some(e) = injected_fault(faults, &batch) {
            Err(e)
        } else {
            let current = db.read().expect("db lock").clone();
            let durability = if durable {
                Durability::Immediate
            } else {
                Durability::None
            };
            let start = Instant::now();
            let r = match current {
                Some(d) => commit(
                    &d,
                    batch.iter().flat_map(|r| r.ops.iter()),
                    durability,
                    films,
                )
                .map_err(|e| e.to_string()),
                None => Err(health.last_error()),
            };
            // Every commit, for the writer's busy time (one thread: the
            // bound on how fast results can be taken in).
            tracing::debug!(
                requests = batch.len(),
                film_bytes = batch
                    .iter()
                    .flat_map(|r| r.ops.iter())
                    .map(Op::film_bytes)
                    .sum::<usize>(),
                durable,
                commit_ms = start.elapsed().as_secs_f64() * 1e3,
                "commit"
            );
            match &r {
                Ok(()) => health.recover(),
                Err(e) => health.fail(e),
            }
            r
        };
        if result.is_ok() {
            if durable {
                unsynced = None;
            } else {
                unsynced.get_or_insert_with(Instant::now);
            }
        }
        if let Err(e) = &result {
            tracing::error!(error = %e, "database commit failed");
        }
        for r in batch {
            let _ = r.reply.send(result.clone());
        }
    }
}

/// After a failed commit redb refuses every later one until the database
/// is closed and opened again: reopen it (readers hold it only briefly)
/// and probe with a real write, and one in the films' directory; healthy
/// again once both succeed.
fn heal(db: &Shared, path: &Path, health: &StorageHealth, films: &film_files::FilmFiles) {
    let old = db.write().expect("db lock").take();
    if let Some(old) = old {
        // Wait out readers (each holds its clone for one read).
        let start = std::time::Instant::now();
        while Arc::strong_count(&old) > 1 && start.elapsed() < Duration::from_secs(5) {
            std::thread::sleep(Duration::from_millis(5));
        }
        drop(old);
    }
    // The probe writes (and then removes) 4 MiB: room for real commits,
    // not just for a header update in pages already free.
    let probe = Database::create(path)
        .map_err(|e| e.to_string())
        .and_then(|d| {
            let room = vec![0u8; 4 << 20];
            for put in [true, false] {
                let w = d.begin_write().map_err(|e| e.to_string())?;
                {
                    let mut t = w.open_table(PROBE).map_err(|e| e.to_string())?;
                    if put {
                        t.insert("room", room.as_slice())
                            .map_err(|e| e.to_string())?;
                    } else {
                        t.remove("room").map_err(|e| e.to_string())?;
                    }
                }
                w.commit().map_err(|e| e.to_string())?;
            }
            Ok(d)
        });
    match probe {
        Ok(d) => {
            *db.write().expect("db lock") = Some(Arc::new(d));
            // The films' directory too: redb may have room in its own file
            // on a disk with none left.
            match films.probe() {
                Ok(()) => health.recover(),
                Err(e) => health.fail(&e),
            }
        }
        Err(e) => {
            health.fail(&e);
            // Keep a handle for readers if the file opens at all.
            if let Ok(d) = Database::create(path) {
                *db.write().expect("db lock") = Some(Arc::new(d));
            }
        }
    }
}

fn injected_fault(faults: &Faults, batch: &[Request]) -> Option<String> {
    let mut f = faults.lock().expect("faults lock");
    let (when, times) = f.as_mut()?;
    if *times == 0 || !batch.iter().flat_map(|r| r.ops.iter()).any(when) {
        return None;
    }
    *times -= 1;
    Some("injected commit failure".into())
}

/// Makes every commit so far durable (an empty durable commit).
fn sync(db: &Shared, health: &StorageHealth, films: &Arc<film_files::FilmFiles>) {
    let start = Instant::now();
    let current = db.read().expect("db lock").clone();
    let r = match current {
        Some(d) => {
            commit(&d, std::iter::empty(), Durability::Immediate, films).map_err(|e| e.to_string())
        }
        None => Err(health.last_error()),
    };
    tracing::debug!(
        sync_ms = start.elapsed().as_secs_f64() * 1e3,
        "results made durable"
    );
    if let Err(e) = r {
        tracing::error!(error = %e, "cannot make committed results durable");
        health.fail(&e);
    }
}

/// Commits `ops` in one transaction; then removes the film files whose
/// references it dropped.
fn commit<'a>(
    db: &Database,
    ops: impl Iterator<Item = &'a Op>,
    durability: Durability,
    film_files: &Arc<film_files::FilmFiles>,
) -> Result<(), StoreError> {
    // Files of the films this commit drops.
    let mut dropped: Vec<String> = Vec::new();
    let mut drop_film = |v: &[u8]| {
        dropped.extend(film_files::FilmFiles::name_of(v).map(str::to_owned));
        false
    };
    let mut w = db.begin_write()?;
    w.set_durability(durability)
        .map_err(|e| StoreError::Commit(e.to_string()))?;
    {
        let mut jobs = w.open_table(JOBS)?;
        let mut counters = w.open_table(COUNTERS)?;
        let mut films = w.open_table(UNIT_FILMS)?;
        let mut frames = w.open_table(FRAMES_WRITTEN)?;
        // Counter changes of the whole batch, applied once per job at the end.
        let mut updates: BTreeMap<&str, (Option<&Counters>, u64, [u64; 4])> = BTreeMap::new();
        for op in ops {
            match op {
                Op::PutJob(rec) => {
                    let json = serde_json::to_vec(rec).expect("records serialise");
                    jobs.insert(rec.id.as_str(), json.as_slice())?;
                }
                Op::PutCounters { job, counters: c } => {
                    updates.entry(job.as_str()).or_default().0 = Some(c);
                }
                Op::AcceptUnits {
                    job,
                    first_unit,
                    film,
                    units,
                    rays,
                } => {
                    match film {
                        StoredFilm::Inline(film) => {
                            let mut value =
                                films.insert_reserve((job.as_str(), *first_unit), film.len())?;
                            film.write_to(value.as_mut());
                        }
                        StoredFilm::File(reference) => {
                            films.insert((job.as_str(), *first_unit), reference.as_slice())?;
                        }
                    }
                    let u = updates.entry(job.as_str()).or_default();
                    u.1 += units;
                    for (a, b) in u.2.iter_mut().zip(rays) {
                        *a += b;
                    }
                }
                Op::DeleteJob(job) => {
                    jobs.remove(job.as_str())?;
                    counters.remove(job.as_str())?;
                    let j = job.as_str();
                    films.retain_in((j, 0)..=(j, u32::MAX), |_, v| drop_film(v))?;
                    frames.retain_in((j, 0)..=(j, u32::MAX), |_, _| false)?;
                }
                Op::FrameWritten {
                    job,
                    frame,
                    file,
                    units,
                } => {
                    frames.insert((job.as_str(), *frame), file.as_str())?;
                    // Every film of the frame is keyed by one of its units.
                    let j = job.as_str();
                    films.retain_in((j, units.start)..(j, units.end), |_, v| drop_film(v))?;
                }
            }
        }
        for (job, (set, accepted, rays)) in updates {
            let mut stored = read_counters(&counters, job)?;
            if let Some(c) = set {
                // Counters not tied to accepted units; the accepted count and
                // rays are only ever incremented with the units' films.
                stored.results_rejected = c.results_rejected;
                stored.results_late = c.results_late;
                stored.results_duplicate = c.results_duplicate;
            }
            stored.units_accepted = stored.units_accepted.saturating_add(accepted);
            for (a, b) in stored.rays.iter_mut().zip(rays) {
                *a = a.saturating_add(b);
            }
            let json = serde_json::to_vec(&stored).expect("counters serialise");
            counters.insert(job, json.as_slice())?;
        }
    }
    w.commit()?;
    // Only ops that commit durably drop films (they are not results).
    if !dropped.is_empty() {
        // Unlinking a frame's tens of megabytes takes milliseconds, which
        // would hold up the next commits: a thread of its own does it.
        let files = film_files.clone();
        let remove = move || files.remove(dropped.iter().map(String::as_str));
        if let Err(e) = std::thread::Builder::new()
            .name("tessera-film-remover".into())
            .spawn(remove.clone())
        {
            tracing::warn!(error = %e, "no thread to remove film files: removing them here");
            remove();
        }
    }
    Ok(())
}

fn read_counters(t: &redb::Table<&str, &[u8]>, job: &str) -> Result<Counters, StoreError> {
    match t.get(job)? {
        Some(v) => serde_json::from_slice(v.value()).map_err(|e| StoreError::Corrupt {
            what: format!("counters of {job}"),
            message: e.to_string(),
        }),
        None => Ok(Counters::default()),
    }
}

/// Marks a stored film in the compact layout: its first four bytes. In the
/// original layout they are the film's x, far below this (images are at
/// most `MAX_IMAGE_SIDE` = 32768 wide), so films stored by earlier versions
/// still decode.
const COMPACT_MAGIC: [u8; 4] = *b"TFC2";
/// The compact layout of an adaptive film: one more header byte, the
/// squares' width, and the sums of squares after the counts.
const ADAPTIVE_MAGIC: [u8; 4] = *b"TFA1";
/// Bytes before the pixels: the magic, the rect, ray counts and the
/// non-finite count, then the encoding (sum bytes, uniform flag, count).
const COMPACT_HEADER: usize = 4 + 16 + 40 + 1 + 1 + 4;

/// A film for the store, in the compact layout of [`film_codec::pack`].
pub fn encode_film(f: &Film) -> Vec<u8> {
    EncodedFilm::of_film(f).to_vec()
}

/// The part of `film` inside `rect` (which lies inside it), with these ray
/// counts, for the store: no intermediate film.
pub fn encode_film_part(film: &Film, rect: Rect, rays: RayCounts, nonfinite: u64) -> Vec<u8> {
    EncodedFilm::of_part(film, rect, rays, nonfinite).to_vec()
}

/// A film in the store's compact layout, kept as its parts: the store's
/// writer copies them straight into the database's page (a GPU result is
/// tens of megabytes, and one more copy of it cost ~10 ms).
#[derive(Debug)]
pub struct EncodedFilm {
    header: Vec<u8>,
    packed: film_codec::Packed,
    squares: Vec<u8>,
}

impl EncodedFilm {
    /// A film already in the compact layout (a result's fields as they came
    /// over the wire, checked by decoding them): a header, no re-encoding.
    /// `squares` (width, bytes) for adaptive films.
    pub fn new(
        rect: Rect,
        rays: RayCounts,
        nonfinite: u64,
        packed: film_codec::Packed,
        squares: Option<(u8, Vec<u8>)>,
    ) -> EncodedFilm {
        let mut header = Vec::with_capacity(COMPACT_HEADER + 1);
        // Adaptive films (sums of squares) are the compact layout with one
        // more header byte (the squares' width) and the squares at the end.
        header.extend_from_slice(if squares.is_some() {
            &ADAPTIVE_MAGIC
        } else {
            &COMPACT_MAGIC
        });
        for v in [rect.x, rect.y, rect.width, rect.height] {
            header.extend_from_slice(&v.to_le_bytes());
        }
        for v in [
            rays.primary,
            rays.shadow,
            rays.reflection,
            rays.refraction,
            nonfinite,
        ] {
            header.extend_from_slice(&v.to_le_bytes());
        }
        header.push(packed.sum_bytes);
        header.push(u8::from(packed.uniform_count.is_some()));
        header.extend_from_slice(&packed.uniform_count.unwrap_or(0).to_le_bytes());
        let squares = match squares {
            Some((n, bytes)) => {
                header.push(n);
                bytes
            }
            None => Vec::new(),
        };
        EncodedFilm {
            header,
            packed,
            squares,
        }
    }

    /// The part of `film` inside `rect` (which lies inside it), packed,
    /// with these ray counts: no intermediate film.
    pub fn of_part(film: &Film, rect: Rect, rays: RayCounts, nonfinite: u64) -> EncodedFilm {
        EncodedFilm::new(
            rect,
            rays,
            nonfinite,
            film_codec::pack_part(film, rect),
            film_codec::pack_squares_part(film, rect),
        )
    }

    /// A whole film, packed (with its sums of squares if it has them).
    pub fn of_film(f: &Film) -> EncodedFilm {
        EncodedFilm::of_part(f, f.rect, f.rays, f.nonfinite)
    }

    /// Bytes of the encoded film.
    pub fn len(&self) -> usize {
        self.header.len() + self.packed.sums.len() + self.packed.counts.len() + self.squares.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The encoded film's bytes, in four parts.
    pub fn parts(&self) -> [&[u8]; 4] {
        [
            &self.header,
            &self.packed.sums,
            &self.packed.counts,
            &self.squares,
        ]
    }

    /// Writes the encoded film into `out`, which is [`EncodedFilm::len`] long.
    pub fn write_to(&self, out: &mut [u8]) {
        let mut at = 0;
        for part in self.parts() {
            out[at..at + part.len()].copy_from_slice(part);
            at += part.len();
        }
        debug_assert_eq!(at, out.len());
    }

    pub fn to_vec(&self) -> Vec<u8> {
        let mut out = vec![0u8; self.len()];
        self.write_to(&mut out);
        out
    }
}

/// A stored film, in the compact layout or in the original one (56-byte
/// header, then 28 bytes a pixel) that earlier versions stored.
pub fn decode_film(b: &[u8]) -> Result<Film, String> {
    let adaptive = b.starts_with(&ADAPTIVE_MAGIC);
    let compact = adaptive || b.starts_with(&COMPACT_MAGIC);
    let header = match (compact, adaptive) {
        (_, true) => COMPACT_HEADER + 1,
        (true, false) => COMPACT_HEADER,
        (false, _) => 56,
    };
    if b.len() < header {
        return Err(format!(
            "{} bytes is shorter than the {header}-byte header",
            b.len()
        ));
    }
    let at = if compact { 4 } else { 0 };
    let u32_at = |i: usize| u32::from_le_bytes(b[at + i..at + i + 4].try_into().expect("4 bytes"));
    let u64_at = |i: usize| u64::from_le_bytes(b[at + i..at + i + 8].try_into().expect("8 bytes"));
    let rect = Rect::new(u32_at(0), u32_at(4), u32_at(8), u32_at(12));
    let rays = RayCounts {
        primary: u64_at(16),
        shadow: u64_at(24),
        reflection: u64_at(32),
        refraction: u64_at(40),
    };
    let nonfinite = u64_at(48);
    let encoding = if compact {
        film_codec::Encoding {
            sum_bytes: b[at + 56],
            uniform_count: (b[at + 57] != 0).then(|| u32_at(58)),
        }
    } else {
        film_codec::Encoding::ORIGINAL
    };
    let sums_len = encoding
        .sums_len(rect.area())
        .filter(|&n| n <= b.len() - header)
        .ok_or_else(|| {
            format!(
                "{} bytes is too short for a {}x{} film",
                b.len(),
                rect.width,
                rect.height
            )
        })?;
    let split = header + sums_len;
    if !adaptive {
        return film_codec::unpack_with(
            rect,
            encoding,
            &b[header..split],
            &b[split..],
            rays,
            nonfinite,
        )
        .map_err(|e| e.to_string());
    }
    let counts_end = encoding
        .counts_len(rect.area())
        .map(|n| split + n)
        .filter(|&end| end <= b.len())
        .ok_or_else(|| format!("{} bytes is too short for the counts", b.len()))?;
    let mut film = film_codec::unpack_with(
        rect,
        encoding,
        &b[header..split],
        &b[split..counts_end],
        rays,
        nonfinite,
    )
    .map_err(|e| e.to_string())?;
    film_codec::unpack_squares(&mut film, b[COMPACT_HEADER], &b[counts_end..])
        .map_err(|e| e.to_string())?;
    Ok(film)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tracer_core::sampling::Sampler;

    /// A job record as releases before `JobSpec` wrote it (with the
    /// adaptive fields of issue 17), field for field.
    const RECORD: &str = r#"{"id":"j0123456789","name":"glass","scene_name":"examples/glass.toml",
        "scene_sha256":"ab","assets":{"m.obj":"cd"},"width":320,"height":240,"samples":1024,
        "max_depth":6,"sampler":"progressive","first_frame":1,"last_frame":3,"priority":-2,
        "tile_size":64,"samples_per_unit":64,"max_attempts":3,"state":"Active","error":"",
        "submitted_unix_ms":1700000000000,"finished_unix_ms":0,"output_dir":"/data/outputs/j0123456789",
        "target_error":0.01,"min_samples":16,"max_samples":1024,"relative_error":0.0}"#;

    #[test]
    fn job_records_of_earlier_releases_still_load_and_keep_their_shape() {
        let rec: JobRecord = serde_json::from_str(RECORD).unwrap();
        assert_eq!(
            rec.settings,
            RenderSettings {
                width: 320,
                height: 240,
                samples: 1024,
                max_depth: 6,
                sampler: Sampler::Progressive,
                integrator: Default::default(),
            }
        );
        assert_eq!((rec.first_frame, rec.last_frame, rec.priority), (1, 3, -2));
        assert_eq!(rec.state, JobStateRec::Active);
        assert_eq!(
            rec.adaptive(),
            Some(AdaptiveSettings {
                target_error: 0.01,
                relative_error: 0.0,
                min_samples: 16,
                max_samples: 1024,
            })
        );
        // Written back, it is the same JSON object: same names, the
        // sampler still a string.
        let old: serde_json::Value = serde_json::from_str(RECORD).unwrap();
        assert_eq!(serde_json::to_value(&rec).unwrap(), old);

        // Before adaptive sampling: no adaptive fields, a "grid" or
        // "jittered" sampler; a uniform job.
        let mut before: serde_json::Map<String, serde_json::Value> =
            serde_json::from_str(RECORD).unwrap();
        for k in [
            "target_error",
            "min_samples",
            "max_samples",
            "relative_error",
        ] {
            before.remove(k);
        }
        before.insert("sampler".into(), "jittered".into());
        let rec: JobRecord = serde_json::from_value(before.into()).unwrap();
        assert_eq!(rec.settings.sampler, Sampler::Jittered);
        assert_eq!(rec.adaptive(), None);
        for s in ["grid", "jittered", "progressive"] {
            let v = serde_json::to_value(RenderSettings {
                sampler: s.parse().unwrap(),
                ..rec.settings
            })
            .unwrap();
            assert_eq!(v["sampler"], s);
        }
    }

    /// A record this release cannot read (a sampler from a newer release)
    /// is left out; the other jobs still load.
    #[test]
    fn an_unreadable_job_record_does_not_stop_the_others_loading() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&dir.path().join("t.redb")).unwrap();
        let good: JobRecord = serde_json::from_str(RECORD).unwrap();
        let mut newer: serde_json::Value = serde_json::from_str(RECORD).unwrap();
        newer["id"] = "jnewer".into();
        newer["sampler"] = "blue-noise".into();
        let db = store.db().unwrap();
        let w = db.begin_write().unwrap();
        {
            let mut t = w.open_table(JOBS).unwrap();
            let newer = serde_json::to_vec(&newer).unwrap();
            t.insert("jnewer", newer.as_slice()).unwrap();
            let good = serde_json::to_vec(&good).unwrap();
            t.insert("j0123456789", good.as_slice()).unwrap();
        }
        w.commit().unwrap();
        let snap = store.load().unwrap();
        let ids: Vec<&str> = snap.jobs.iter().map(|(r, _)| r.id.as_str()).collect();
        assert_eq!(ids, ["j0123456789"]);
    }

    fn film() -> Film {
        let mut film = Film::new(Rect::new(8, 4, 5, 3));
        for (i, (s, c)) in film.sums.iter_mut().zip(film.counts.iter_mut()).enumerate() {
            *s = [i as u64, (i as u64) << 40, u64::MAX - i as u64];
            *c = 7 + i as u32;
        }
        film.rays = RayCounts {
            primary: 1,
            shadow: 2,
            reflection: 3,
            refraction: 4,
        };
        film.nonfinite = 9;
        film
    }

    #[test]
    fn adaptive_films_keep_their_squares_in_the_store() {
        let mut f = film();
        f.squares = Some((0..15u128).map(|i| [i << 90, i, 0]).collect());
        let b = encode_film(&f);
        assert!(b.starts_with(&ADAPTIVE_MAGIC));
        assert_eq!(decode_film(&b), Ok(f.clone()));
        // A uniform film's bytes do not change.
        assert!(encode_film(&film()).starts_with(&COMPACT_MAGIC));
        assert!(decode_film(&b[..b.len() - 1]).is_err());
    }

    fn block_on<F: std::future::Future>(f: F) -> F::Output {
        tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap()
            .block_on(f)
    }

    /// The store at `path` once its previous handle's writer let go of it.
    fn reopen(path: &Path) -> Store {
        let start = Instant::now();
        loop {
            match Store::open(path) {
                Ok(s) => return s,
                Err(e) if start.elapsed() < Duration::from_secs(5) => {
                    let _ = e;
                    std::thread::sleep(Duration::from_millis(10));
                }
                Err(e) => panic!("{e}"),
            }
        }
    }

    fn film_files_in(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        names.sort();
        names
    }

    fn accept(job: &str, first_unit: u32, film: StoredFilm) -> Op {
        Op::AcceptUnits {
            job: job.into(),
            first_unit,
            film,
            units: 1,
            rays: [1, 2, 3, 4],
        }
    }

    /// A large film lives in a file of its own: it loads after a restart,
    /// its file goes with its frame's record, and a file no record names
    /// (a result whose commit was lost) is removed at open.
    #[test]
    fn a_large_film_is_kept_in_a_file_until_its_frame_is_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.redb");
        let films_dir = dir.path().join("t.films");
        let store = Store::open(&path).unwrap();
        store.set_min_file_film(1);
        let stored = store
            .store_film("j1", 0, EncodedFilm::of_film(&film()))
            .unwrap();
        assert!(matches!(stored, StoredFilm::File(_)), "{stored:?}");
        let small = Store::open(&dir.path().join("u.redb")).unwrap();
        assert!(
            matches!(
                small.store_film("j1", 0, EncodedFilm::of_film(&film())),
                Ok(StoredFilm::Inline(_))
            ),
            "below a megabyte a film stays in the database"
        );
        block_on(store.write(vec![accept("j1", 0, stored)])).unwrap();
        block_on(store.sync()).unwrap();
        let [kept] = &film_files_in(&films_dir)[..] else {
            panic!("{:?}", film_files_in(&films_dir));
        };
        let kept = kept.clone();
        std::fs::write(films_dir.join("j1-1-00.film"), b"never recorded").unwrap();
        drop(store);

        let store = reopen(&path);
        assert_eq!(film_files_in(&films_dir), [kept]);
        let snap = store.load().unwrap();
        assert_eq!(snap.unit_films["j1"], [(0, film())]);
        block_on(store.write(vec![Op::FrameWritten {
            job: "j1".into(),
            frame: 0,
            file: "frame_0000.png".into(),
            units: 0..1,
        }]))
        .unwrap();
        assert!(store.load().unwrap().unit_films.is_empty());
        // (Removed on a thread of its own, after the commit.)
        let start = Instant::now();
        while !film_files_in(&films_dir).is_empty() {
            assert!(start.elapsed() < Duration::from_secs(5), "file not removed");
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// A film that cannot be written (here its directory is a file) is a
    /// storage outage like a failed commit: refused with the path named,
    /// nothing left behind, and over once writes succeed again.
    #[test]
    fn a_film_that_cannot_be_written_is_an_outage_that_heals() {
        let dir = tempfile::tempdir().unwrap();
        let films_dir = dir.path().join("t.films");
        let store = Store::open(&dir.path().join("t.redb")).unwrap();
        store.set_min_file_film(1);
        std::fs::remove_dir(&films_dir).unwrap();
        std::fs::write(&films_dir, b"in the way").unwrap();
        let e = store
            .store_film("j1", 0, EncodedFilm::of_film(&film()))
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with(&format!(
                "cannot write the database: cannot write the film {}/j1-0-",
                films_dir.display()
            )),
            "{e}"
        );
        assert!(!store.health.ok());
        std::fs::remove_file(&films_dir).unwrap();
        std::fs::create_dir(&films_dir).unwrap();
        let start = Instant::now();
        while !store.health.ok() {
            assert!(start.elapsed() < Duration::from_secs(10), "never healed");
            std::thread::sleep(Duration::from_millis(20));
        }
        let stored = store
            .store_film("j1", 0, EncodedFilm::of_film(&film()))
            .unwrap();
        block_on(store.write(vec![accept("j1", 0, stored)])).unwrap();
        assert_eq!(store.load().unwrap().unit_films["j1"], [(0, film())]);
        assert_eq!(film_files_in(&films_dir).len(), 1);
    }

    #[test]
    fn a_film_part_encodes_as_the_cropped_film() {
        let film = film();
        assert_eq!(decode_film(&encode_film(&film)), Ok(film.clone()));
        let part = Rect::new(9, 5, 3, 2);
        let mut cropped = Film::new(part);
        for row in 0..2 {
            for col in 0..3 {
                let src = ((row + 1) * 5 + col + 1) as usize;
                cropped.sums[(row * 3 + col) as usize] = film.sums[src];
                cropped.counts[(row * 3 + col) as usize] = film.counts[src];
            }
        }
        let got = decode_film(&encode_film_part(&film, part, RayCounts::default(), 0)).unwrap();
        assert_eq!(got, cropped);
    }

    /// Films stored by earlier versions (56-byte header, 28 bytes a pixel)
    /// still decode; damaged ones are errors, never panics.
    #[test]
    fn films_in_the_original_layout_still_decode() {
        let film = film();
        let mut old = Vec::new();
        for v in [8u32, 4, 5, 3] {
            old.extend_from_slice(&v.to_le_bytes());
        }
        for v in [1u64, 2, 3, 4, 9] {
            old.extend_from_slice(&v.to_le_bytes());
        }
        old.extend_from_slice(&film_codec::pack_sums(&film));
        old.extend_from_slice(&film_codec::pack_counts(&film));
        assert_eq!(decode_film(&old), Ok(film.clone()));
        let new = encode_film(&film);
        for cut in [0, 10, 60, 66, new.len() - 1] {
            assert!(decode_film(&new[..cut]).is_err(), "cut at {cut}");
        }
        let mut bad = new.clone();
        bad[60] = 9;
        assert_eq!(
            decode_film(&bad),
            Err("sum_bytes must be 1 to 8, got 9".into())
        );
    }
}
