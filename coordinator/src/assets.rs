//! The coordinator's content-addressed file store: every scene TOML and
//! every file a scene references, once, under `--data/assets/` as
//! `ab/abcdef…` (the SHA-256 in hex), shared by all jobs.
//!
//! Invariants: a file under its hash holds exactly the bytes of that hash
//! (an upload is written to `tmp/`, checked against the size and hash it
//! declared, synced, then renamed into place, so a crash or a full disk
//! leaves at most a stray temporary file, removed at the next start); a
//! file stays while an unfinished job references it, and is collected
//! once none has for `retention` (each submit that names it, each
//! `FindMissingAssets` that finds it and each upload of it start the clock
//! again, so a re-submit of the same model uploads nothing).
//!
//! Collection cannot race a submit: a file's clock is restarted
//! ([`AssetStore::hold`]) and a file is removed ([`AssetStore::collect`],
//! which reads its clock again first) under one lock, the `gate`. So a file
//! that `FindMissingAssets` reported held stays for `retention` after that
//! answer, and one a submit has named stays while its job is unfinished
//! (the submit holds it before the job's record names it, and the
//! collector keeps what unfinished jobs name).

use std::collections::HashSet;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, SystemTime};

use sha2::{Digest, Sha256};

/// Configurable bounds on what clients may store.
#[derive(Clone, Copy, Debug)]
pub struct AssetLimits {
    /// Largest single file.
    pub max_asset_bytes: u64,
    /// Largest sum of a job's files (scene included).
    pub max_job_bytes: u64,
    /// Largest sum of all stored files.
    pub max_store_bytes: u64,
    /// How long a file no unfinished job references is kept.
    pub retention: Duration,
    /// Longest wait for an upload's next chunk.
    pub upload_idle_timeout: Duration,
    /// Most uploads at once, in all and on one connection.
    pub max_uploads: u32,
    pub max_uploads_per_connection: u32,
}

impl Default for AssetLimits {
    fn default() -> Self {
        AssetLimits {
            max_asset_bytes: 2 << 30,
            max_job_bytes: 4 << 30,
            max_store_bytes: 64 << 30,
            retention: Duration::from_secs(24 * 3600),
            upload_idle_timeout: Duration::from_secs(30),
            max_uploads: 64,
            max_uploads_per_connection: 4,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum AssetStoreError {
    #[error("{0:?} is not a SHA-256 (64 lowercase hex digits)")]
    BadHash(String),
    #[error(
        "asset {sha256} is {size} bytes, over the coordinator's limit of {limit} bytes a file (--max-asset-bytes)"
    )]
    TooLarge {
        sha256: String,
        size: u64,
        limit: u64,
    },
    #[error(
        "storing {size} more bytes would take the asset store over its limit of {limit} bytes (--max-store-bytes; {stored} bytes stored, {reserved} being uploaded)"
    )]
    StoreFull {
        size: u64,
        stored: u64,
        reserved: u64,
        limit: u64,
    },
    #[error(
        "the coordinator is receiving {busy} uploads already{scope}, its limit ({flag}); send this one when one of them ends"
    )]
    Busy {
        busy: u32,
        scope: &'static str,
        flag: &'static str,
    },
    #[error("the upload of {sha256} {message}")]
    BadUpload { sha256: String, message: String },
    #[error("asset {0} is not on the coordinator")]
    NotFound(String),
    #[error("cannot store asset {sha256}: {message}; nothing was stored")]
    Io { sha256: String, message: String },
}

impl AssetStoreError {
    /// A full or failing disk, as opposed to a bad request.
    pub fn is_storage(&self) -> bool {
        matches!(self, AssetStoreError::Io { .. })
    }
}

/// Counters since start, for `GetFarmStats`.
#[derive(Debug, Default)]
pub struct AssetStats {
    pub uploads: AtomicU64,
    pub bytes_uploaded: AtomicU64,
    pub uploads_skipped: AtomicU64,
    pub fetches: AtomicU64,
    pub bytes_served: AtomicU64,
    pub collected: AtomicU64,
}

#[derive(Debug)]
pub struct AssetStore {
    dir: PathBuf,
    pub limits: AssetLimits,
    pub stats: AssetStats,
    /// Bytes and files held (kept in step with the directory).
    held: Mutex<(u64, u64)>,
    /// Bytes of uploads in flight: counted against the store's limit from
    /// their start, so concurrent uploads cannot pass it together.
    reserved: Mutex<u64>,
    /// Uploads in flight.
    uploading: std::sync::atomic::AtomicU32,
    /// Uploads ended since start (memory may be returned after them).
    pub uploads_ended: AtomicU64,
    next_tmp: AtomicU64,
    /// Taken to restart a file's clock and to remove a file, so that the
    /// collector's second look at a file's clock and its removal are one
    /// step no `hold` can fall between.
    gate: Mutex<()>,
}

pub use tessera_proto::transport::sha256_hex;
use tessera_proto::transport::{hex, is_sha256_hex};

pub fn check_hash(sha256: &str) -> Result<(), AssetStoreError> {
    if is_sha256_hex(sha256) {
        Ok(())
    } else {
        Err(AssetStoreError::BadHash(sha256.chars().take(80).collect()))
    }
}

impl AssetStore {
    /// Opens (or creates) the store in `dir`, removing unfinished uploads.
    pub fn open(dir: &Path, limits: AssetLimits) -> std::io::Result<Self> {
        let tmp = dir.join("tmp");
        let _ = std::fs::remove_dir_all(&tmp);
        std::fs::create_dir_all(&tmp)?;
        let store = AssetStore {
            dir: dir.to_owned(),
            limits,
            stats: AssetStats::default(),
            held: Mutex::new((0, 0)),
            reserved: Mutex::new(0),
            uploading: std::sync::atomic::AtomicU32::new(0),
            uploads_ended: AtomicU64::new(0),
            next_tmp: AtomicU64::new(0),
            gate: Mutex::new(()),
        };
        let (mut bytes, mut files) = (0, 0);
        for (_, meta) in store.entries() {
            bytes += meta.len();
            files += 1;
        }
        *store.held.lock().expect("asset lock") = (bytes, files);
        Ok(store)
    }

    fn path(&self, sha256: &str) -> PathBuf {
        self.dir.join(&sha256[..2]).join(sha256)
    }

    /// Every stored file: (hash, metadata).
    fn entries(&self) -> Vec<(String, std::fs::Metadata)> {
        let mut out = Vec::new();
        let Ok(dirs) = std::fs::read_dir(&self.dir) else {
            return out;
        };
        for d in dirs.flatten() {
            if d.file_name().len() != 2 {
                continue;
            }
            let Ok(files) = std::fs::read_dir(d.path()) else {
                continue;
            };
            for f in files.flatten() {
                let name = f.file_name().to_string_lossy().into_owned();
                if let (Ok(()), Ok(meta)) = (check_hash(&name), f.metadata()) {
                    out.push((name, meta));
                }
            }
        }
        out
    }

    /// (files, bytes) held.
    pub fn held(&self) -> (u64, u64) {
        let (bytes, files) = *self.held.lock().expect("asset lock");
        (files, bytes)
    }

    /// The size of a stored file, or None.
    pub fn size(&self, sha256: &str) -> Option<u64> {
        check_hash(sha256).ok()?;
        std::fs::metadata(self.path(sha256))
            .ok()
            .filter(|m| m.is_file())
            .map(|m| m.len())
    }

    /// The size of a stored file, its retention clock restarted (a
    /// client learned that it is held, or a job names it): it is not
    /// collected for `retention` from now. None when it is not held.
    pub fn hold(&self, sha256: &str) -> Option<u64> {
        check_hash(sha256).ok()?;
        let _gate = self.gate.lock().expect("asset gate");
        let f = std::fs::File::options()
            .write(true)
            .open(self.path(sha256))
            .ok()?;
        let meta = f.metadata().ok().filter(|m| m.is_file())?;
        if let Err(e) = f.set_modified(SystemTime::now()) {
            // Still held; it may go after `retention` from its last use.
            tracing::warn!(sha256 = %sha256, error = %e, "cannot restart a stored file's retention clock");
        }
        Some(meta.len())
    }

    pub fn read(&self, sha256: &str) -> Result<Vec<u8>, AssetStoreError> {
        check_hash(sha256)?;
        std::fs::read(self.path(sha256)).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => AssetStoreError::NotFound(sha256.into()),
            _ => AssetStoreError::Io {
                sha256: sha256.into(),
                message: e.to_string(),
            },
        })
    }

    /// Opens a stored file for streaming.
    pub fn open_file(&self, sha256: &str) -> Result<(std::fs::File, u64), AssetStoreError> {
        check_hash(sha256)?;
        let f = std::fs::File::open(self.path(sha256))
            .map_err(|_| AssetStoreError::NotFound(sha256.into()))?;
        let len = f.metadata().map(|m| m.len()).unwrap_or(0);
        Ok((f, len))
    }

    /// Starts receiving a file of `size` bytes that should hash to
    /// `sha256`; None when it is already stored.
    pub fn begin(&self, sha256: &str, size: u64) -> Result<Option<Upload<'_>>, AssetStoreError> {
        check_hash(sha256)?;
        if self.hold(sha256).is_some() {
            return Ok(None);
        }
        if size > self.limits.max_asset_bytes {
            return Err(AssetStoreError::TooLarge {
                sha256: sha256.into(),
                size,
                limit: self.limits.max_asset_bytes,
            });
        }
        {
            // Lock order: reserved, then held (finish takes them one at a time).
            let mut reserved = self.reserved.lock().expect("asset lock");
            let (stored, _) = *self.held.lock().expect("asset lock");
            if stored.saturating_add(*reserved).saturating_add(size) > self.limits.max_store_bytes {
                return Err(AssetStoreError::StoreFull {
                    size,
                    stored,
                    reserved: *reserved,
                    limit: self.limits.max_store_bytes,
                });
            }
            *reserved += size;
        }
        let reservation = Reservation { store: self, size };
        let io = |e: std::io::Error| AssetStoreError::Io {
            sha256: sha256.into(),
            message: e.to_string(),
        };
        let n = self.next_tmp.fetch_add(1, Ordering::Relaxed);
        let tmp = self.dir.join("tmp").join(format!("{sha256}.{n}"));
        let file = std::fs::File::create(&tmp).map_err(io)?;
        Ok(Some(Upload {
            store: self,
            sha256: sha256.into(),
            size,
            tmp,
            // Small: a stalled upload holds this much (chunks of 1 MiB
            // are written straight through).
            file: Some(std::io::BufWriter::with_capacity(UPLOAD_BUFFER, file)),
            hasher: Sha256::new(),
            written: 0,
            reservation: Some(reservation),
        }))
    }

    /// A place among the uploads in flight (in all, and on the
    /// connection whose count is `on_connection`), held until dropped.
    pub fn upload_slot<'a>(
        &'a self,
        on_connection: Option<&'a std::sync::atomic::AtomicU32>,
    ) -> Result<UploadSlot<'a>, AssetStoreError> {
        let take = |n: &'a std::sync::atomic::AtomicU32, limit: u32, scope, flag| {
            n.fetch_update(Ordering::AcqRel, Ordering::Acquire, |b| {
                (b < limit).then_some(b + 1)
            })
            .map(|_| n)
            .map_err(|busy| AssetStoreError::Busy { busy, scope, flag })
        };
        let all = take(
            &self.uploading,
            self.limits.max_uploads,
            "",
            "--max-uploads",
        )?;
        let conn = match on_connection {
            Some(c) => match take(
                c,
                self.limits.max_uploads_per_connection,
                " on this connection",
                "--max-uploads-per-connection",
            ) {
                Ok(c) => Some(c),
                Err(e) => {
                    all.fetch_sub(1, Ordering::AcqRel);
                    return Err(e);
                }
            },
            None => None,
        };
        Ok(UploadSlot {
            store: self,
            counts: [Some(all), conn],
        })
    }

    /// Stores a whole file at once (inline job files, the scene TOML).
    pub fn put(&self, content: &[u8]) -> Result<String, AssetStoreError> {
        let sha256 = sha256_hex(content);
        if let Some(mut up) = self.begin(&sha256, content.len() as u64)? {
            up.write(content)?;
            up.finish()?;
        }
        Ok(sha256)
    }

    /// Removes the files that no unfinished job names (`keep`) and that
    /// nothing has held ([`AssetStore::hold`]) for `retention`. Returns
    /// how many went. Each file's clock is read again under the gate just
    /// before it goes: the listing is old by then, and a submit or
    /// `FindMissingAssets` may have held the file since.
    pub fn collect(&self, keep: &HashSet<String>) -> u64 {
        self.collect_listed(keep, || {})
    }

    /// [`AssetStore::collect`], calling `after_listing` between the listing
    /// and the removals (tests put a racing `hold` there).
    fn collect_listed(&self, keep: &HashSet<String>, after_listing: impl FnOnce()) -> u64 {
        let old = |meta: &std::fs::Metadata| {
            let age = meta
                .modified()
                .ok()
                .and_then(|m| SystemTime::now().duration_since(m).ok())
                .unwrap_or_default();
            age >= self.limits.retention
        };
        let listed = self.entries();
        after_listing();
        let mut removed = 0;
        for (sha256, meta) in listed {
            if keep.contains(&sha256) || !old(&meta) {
                continue;
            }
            let _gate = self.gate.lock().expect("asset gate");
            let path = self.path(&sha256);
            if !std::fs::metadata(&path).is_ok_and(|m| old(&m)) {
                continue;
            }
            if std::fs::remove_file(&path).is_ok() {
                let mut held = self.held.lock().expect("asset lock");
                held.0 = held.0.saturating_sub(meta.len());
                held.1 = held.1.saturating_sub(1);
                removed += 1;
                tracing::info!(sha256 = %sha256, bytes = meta.len(), "asset collected");
            }
        }
        self.stats.collected.fetch_add(removed, Ordering::Relaxed);
        removed
    }
}

/// Buffer of an upload's file.
const UPLOAD_BUFFER: usize = 64 << 10;

/// Bytes counted against the store's limit while an upload runs.
#[derive(Debug)]
struct Reservation<'a> {
    store: &'a AssetStore,
    size: u64,
}

impl Drop for Reservation<'_> {
    fn drop(&mut self) {
        let mut r = self.store.reserved.lock().expect("asset lock");
        *r = r.saturating_sub(self.size);
    }
}

/// An upload's place among those in flight.
#[derive(Debug)]
pub struct UploadSlot<'a> {
    store: &'a AssetStore,
    counts: [Option<&'a std::sync::atomic::AtomicU32>; 2],
}

impl Drop for UploadSlot<'_> {
    fn drop(&mut self) {
        for c in self.counts.iter().flatten() {
            c.fetch_sub(1, Ordering::AcqRel);
        }
        self.store.uploads_ended.fetch_add(1, Ordering::Relaxed);
    }
}

/// A file being received; dropped unfinished, it leaves nothing behind.
#[derive(Debug)]
pub struct Upload<'a> {
    store: &'a AssetStore,
    sha256: String,
    size: u64,
    tmp: PathBuf,
    file: Option<std::io::BufWriter<std::fs::File>>,
    hasher: Sha256,
    written: u64,
    reservation: Option<Reservation<'a>>,
}

impl Upload<'_> {
    fn io(&self, e: std::io::Error) -> AssetStoreError {
        AssetStoreError::Io {
            sha256: self.sha256.clone(),
            message: e.to_string(),
        }
    }

    pub fn write(&mut self, data: &[u8]) -> Result<(), AssetStoreError> {
        if self.written + data.len() as u64 > self.size {
            return Err(AssetStoreError::BadUpload {
                sha256: self.sha256.clone(),
                message: format!("sent more than the {} bytes it declared", self.size),
            });
        }
        self.hasher.update(data);
        let r = self.file.as_mut().expect("open upload").write_all(data);
        r.map_err(|e| self.io(e))?;
        self.written += data.len() as u64;
        Ok(())
    }

    /// Checks size and hash, syncs and moves the file into place.
    pub fn finish(mut self) -> Result<u64, AssetStoreError> {
        if self.written != self.size {
            return Err(AssetStoreError::BadUpload {
                sha256: self.sha256.clone(),
                message: format!(
                    "ended after {} of the {} bytes it declared",
                    self.written, self.size
                ),
            });
        }
        let got = hex(&std::mem::take(&mut self.hasher).finalize());
        if got != self.sha256 {
            return Err(AssetStoreError::BadUpload {
                sha256: self.sha256.clone(),
                message: format!("has bytes whose SHA-256 is {got}"),
            });
        }
        let file = self.file.take().expect("open upload");
        let file = file.into_inner().map_err(|e| self.io(e.into_error()))?;
        file.sync_all().map_err(|e| self.io(e))?;
        let dest = self.store.path(&self.sha256);
        let dir = dest.parent().expect("hash folder");
        std::fs::create_dir_all(dir).map_err(|e| self.io(e))?;
        std::fs::rename(&self.tmp, &dest).map_err(|e| self.io(e))?;
        if let Ok(d) = std::fs::File::open(dir) {
            let _ = d.sync_all();
        }
        // Held before the reservation goes: the two never both miss it.
        {
            let mut held = self.store.held.lock().expect("asset lock");
            held.0 += self.size;
            held.1 += 1;
        }
        self.reservation.take();
        Ok(self.size)
    }
}

impl Drop for Upload<'_> {
    fn drop(&mut self) {
        // Unfinished (or just renamed: then the remove finds nothing).
        self.file.take();
        let _ = std::fs::remove_file(&self.tmp);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uploads_are_checked_stored_once_and_collected_when_unreferenced() {
        let dir = tempfile::tempdir().unwrap();
        let limits = AssetLimits {
            max_asset_bytes: 10,
            max_store_bytes: 14,
            retention: Duration::ZERO,
            ..AssetLimits::default()
        };
        let store = AssetStore::open(dir.path(), limits).unwrap();
        let a = store.put(b"hello").unwrap();
        assert_eq!(a, sha256_hex(b"hello"));
        assert_eq!(store.read(&a).unwrap(), b"hello");
        assert!(store.begin(&a, 5).unwrap().is_none(), "held already");
        assert_eq!(store.held(), (1, 5));

        let b = sha256_hex(b"world");
        let mut up = store.begin(&b, 5).unwrap().unwrap();
        up.write(b"wor").unwrap();
        let e = up.write(b"ldxx").unwrap_err().to_string();
        assert!(e.contains("sent more than the 5 bytes"), "{e}");
        drop(up);
        let mut up = store.begin(&b, 5).unwrap().unwrap();
        up.write(b"WORLD").unwrap();
        let e = up.finish().unwrap_err().to_string();
        assert!(e.contains("has bytes whose SHA-256 is"), "{e}");
        assert!(store.size(&b).is_none(), "a bad upload stores nothing");
        assert_eq!(
            std::fs::read_dir(dir.path().join("tmp")).unwrap().count(),
            0
        );

        let e = store.begin(&b, 11).unwrap_err().to_string();
        assert!(
            e.contains("over the coordinator's limit of 10 bytes a file (--max-asset-bytes)"),
            "{e}"
        );
        let e = store.begin(&b, 10).unwrap_err().to_string();
        assert!(
            e.contains(
                "its limit of 14 bytes (--max-store-bytes; 5 bytes stored, 0 being uploaded)"
            ),
            "{e}"
        );
        // Uploads in flight count: two of 4 bytes do not fit in 14 - 5.
        let x = sha256_hex(b"xxxx");
        let up = store.begin(&x, 4).unwrap().unwrap();
        let e = store
            .begin(&sha256_hex(b"yyyyyy"), 6)
            .unwrap_err()
            .to_string();
        assert!(e.contains("5 bytes stored, 4 being uploaded)"), "{e}");
        drop(up);
        let up = store.begin(&sha256_hex(b"yyyyyy"), 6).unwrap().unwrap();
        drop(up);
        let e = store.begin("ABC", 1).unwrap_err().to_string();
        assert!(e.contains("is not a SHA-256"), "{e}");

        let c = store.put(b"world").unwrap();
        let keep: HashSet<String> = [c.clone()].into();
        assert_eq!(store.collect(&keep), 1);
        assert!(store.size(&a).is_none() && store.size(&c) == Some(5));
        assert_eq!(store.held(), (1, 5));
        drop(store);
        let store = AssetStore::open(dir.path(), limits).unwrap();
        assert_eq!(store.held(), (1, 5), "counted again at open");
    }

    /// Sets a stored file's clock `ago` into the past.
    fn age(store: &AssetStore, sha256: &str, ago: Duration) {
        std::fs::File::options()
            .write(true)
            .open(store.path(sha256))
            .unwrap()
            .set_modified(SystemTime::now() - ago)
            .unwrap();
    }

    #[test]
    fn a_file_held_after_the_collectors_listing_is_not_collected() {
        let dir = tempfile::tempdir().unwrap();
        let limits = AssetLimits {
            retention: Duration::from_secs(3600),
            ..AssetLimits::default()
        };
        let store = AssetStore::open(dir.path(), limits).unwrap();
        let (held, named, idle) = (
            store.put(b"found by FindMissing").unwrap(),
            store.put(b"named by a submit").unwrap(),
            store.put(b"nobody's").unwrap(),
        );
        for h in [&held, &named, &idle] {
            age(&store, h, Duration::from_secs(7200));
        }
        // The collector lists all three as past retention; then, before it
        // removes anything, FindMissingAssets finds one (held) and a submit
        // names another (its hold comes before the job's record exists, so
        // `keep` does not have it).
        let removed = store.collect_listed(&HashSet::new(), || {
            assert_eq!(store.hold(&held), Some(20));
            assert_eq!(store.hold(&named), Some(17));
        });
        assert_eq!(removed, 1);
        assert_eq!(store.size(&held), Some(20), "held by FindMissing: kept");
        assert_eq!(store.size(&named), Some(17), "named by a submit: kept");
        assert_eq!(
            store.size(&idle),
            None,
            "unheld for the retention: collected"
        );
        assert_eq!(store.held(), (2, 37));
        // An upload of a held file restarts its clock too.
        age(&store, &held, Duration::from_secs(7200));
        assert!(store.begin(&held, 20).unwrap().is_none());
        assert_eq!(store.collect(&HashSet::new()), 0);
        // Once the retention passes with nobody holding them, they go.
        age(&store, &held, Duration::from_secs(7200));
        age(&store, &named, Duration::from_secs(7200));
        assert_eq!(store.collect(&[named.clone()].into()), 1);
        assert_eq!((store.size(&held), store.size(&named)), (None, Some(17)));
    }
}
