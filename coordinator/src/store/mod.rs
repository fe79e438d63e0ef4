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
//! done as soon as the intake pauses ([`writer::IDLE_SYNC`]), so that it runs in
//! gaps, a few results at a time, not in the frame's durable record. A crash
//! then loses at most that window of results, never a job, a frame record
//! or a state change (those commit durably, taking any results before them
//! along); the lost units are simply pending again after the restart.

mod film_files;
mod schema;
#[cfg(test)]
mod tests;
mod writer;

use std::collections::{BTreeMap, HashSet};
use std::path::Path;
use std::sync::{Arc, RwLock, mpsc};

use redb::{Database, ReadableDatabase, ReadableTable};
use tokio::sync::oneshot;
use tracer_core::film::Film;

use schema::{ASSETS, COUNTERS, FRAMES_WRITTEN, JOBS, UNIT_FILMS};
pub use schema::{Counters, JobRecord, JobStateRec};
pub use tessera_proto::film_codec::{EncodedFilm, decode_film, encode_film, encode_film_part};
pub use writer::{Op, RESULTS_DURABLE_WITHIN, StorageHealth, StoredFilm};
use writer::{Request, Shared};

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
            .spawn(move || writer::writer(&wdb, &path, rx, &wfaults, &whealth, &wfilms))
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
            let rec = match JobRecord::from_json(v.value()) {
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
