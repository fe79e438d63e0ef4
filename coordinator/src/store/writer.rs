//! The writer thread: one thread commits whatever is queued in a single
//! transaction (group commit), makes results durable in the intake's gaps,
//! and reopens and probes a failing database until it heals.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, RwLock, mpsc};
use std::time::{Duration, Instant};

use redb::{Database, Durability};
use tokio::sync::oneshot;

use super::EncodedFilm;
use super::film_files;
use super::schema::{
    COUNTERS, Counters, FRAMES_WRITTEN, JOBS, JobRecord, PROBE, UNIT_FILMS, read_counters,
};
use super::{Faults, StoreError};

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

pub(super) struct Request {
    pub(super) ops: Vec<Op>,
    /// Commit durably whatever `ops` are ([`Store::sync`]).
    pub(super) durable: bool,
    pub(super) reply: oneshot::Sender<Result<(), String>>,
}

/// The database as the writer last (re)opened it; None while it reopens.
pub(super) type Shared = Arc<RwLock<Option<Arc<Database>>>>;

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
    pub(super) fn fail(&self, e: &str) {
        *self.last_error.lock().expect("health lock") = e.to_string();
        if !self.failing.swap(true, Ordering::Relaxed) {
            tracing::error!(error = %e, "storage failing: refusing new work until writes succeed again");
        }
    }
    pub(super) fn recover(&self) {
        if self.failing.swap(false, Ordering::Relaxed) {
            tracing::info!("storage recovered: writes succeed again");
        }
    }
}

/// How often a failing database is reopened and probed.
pub(super) const HEAL_INTERVAL: Duration = Duration::from_secs(1);

/// The longest a committed result waits for the fsync that makes it
/// durable: what a crash can cost in re-rendered units.
pub const RESULTS_DURABLE_WITHIN: Duration = Duration::from_millis(250);
/// Results not yet durable are made so as soon as the intake pauses this
/// long: the fsync (and redb's write of the buffered pages before it) then
/// runs in a gap, a few results at a time, instead of every 250 ms in the
/// middle of a frame's results, or all at once in the frame's record at
/// its end (which took 28-48 ms for a 1080p frame's 30-50 MB).
pub(super) const IDLE_SYNC: Duration = Duration::from_millis(5);

pub(super) fn writer(
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
pub(super) fn heal(
    db: &Shared,
    path: &Path,
    health: &StorageHealth,
    films: &film_files::FilmFiles,
) {
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

pub(super) fn injected_fault(faults: &Faults, batch: &[Request]) -> Option<String> {
    let mut f = faults.lock().expect("faults lock");
    let (when, times) = f.as_mut()?;
    if *times == 0 || !batch.iter().flat_map(|r| r.ops.iter()).any(when) {
        return None;
    }
    *times -= 1;
    Some("injected commit failure".into())
}

/// Makes every commit so far durable (an empty durable commit).
pub(super) fn sync(db: &Shared, health: &StorageHealth, films: &Arc<film_files::FilmFiles>) {
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
pub(super) fn commit<'a>(
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
                    let json = rec.to_json();
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
