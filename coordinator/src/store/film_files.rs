//! Large films (a GPU worker's results, megabytes each) in files of their
//! own beside the database. They are written and synced on the blocking
//! pool, many at once, while the database's one writer thread commits only
//! a reference to each. Through redb, a 1080p 64-spp frame's 31 MB of films
//! kept that thread busy 64-98 ms of the 62-119 ms its GPU worker took
//! (H200 box, 2026-12-03), and results queued behind it.
//!
//! Invariants: a reference is committed only after its file and the
//! file's directory entry are synced, so a durable reference always finds
//! its file. A file is removed only after the commit that drops its
//! reference. Files that no reference names (a result whose commit failed,
//! or one lost in a crash before it was durable) are removed at open.

use std::collections::HashSet;
use std::fs::File;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

use super::EncodedFilm;

/// Films at least this long go to files; smaller ones (CPU tiles, tens of
/// kilobytes) stay in the database, where one commit takes many at once.
pub const MIN_FILE_FILM: usize = 1 << 20;

/// How a stored reference starts; film records never do (they start with
/// a layout's magic, or with a rect's x in the original layout, which is
/// below the frame limit).
const REF_MAGIC: [u8; 8] = *b"TSFREF01";

/// The directory of film files, and how their names are made unique.
#[derive(Debug)]
pub struct FilmFiles {
    dir: PathBuf,
    /// A counter seeded from the clock: names never repeat, across
    /// restarts too, so a file is never overwritten.
    next: AtomicU64,
    /// Films at least this long go to files ([`MIN_FILE_FILM`]; tests
    /// lower it).
    min_len: AtomicUsize,
}

impl FilmFiles {
    pub fn open(dir: &Path) -> std::io::Result<FilmFiles> {
        std::fs::create_dir_all(dir)?;
        let seed = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0);
        Ok(FilmFiles {
            dir: dir.to_owned(),
            next: AtomicU64::new(seed),
            min_len: AtomicUsize::new(MIN_FILE_FILM),
        })
    }

    #[cfg(test)]
    pub fn set_min_len(&self, n: usize) {
        self.min_len.store(n, Ordering::Relaxed);
    }

    /// Whether `film` goes to a file of its own.
    pub fn wants(&self, film: &EncodedFilm) -> bool {
        film.len() >= self.min_len.load(Ordering::Relaxed)
    }

    /// Writes `film` to a new file, synced with its directory entry;
    /// returns the reference to store in its place. On an error nothing
    /// is left behind.
    pub fn write(&self, job: &str, first_unit: u32, film: &EncodedFilm) -> Result<Vec<u8>, String> {
        // Job ids are the coordinator's own; kept to safe characters anyway.
        let job: String = job
            .chars()
            .filter(char::is_ascii_alphanumeric)
            .take(64)
            .collect();
        let n = self.next.fetch_add(1, Ordering::Relaxed);
        let name = format!("{job}-{first_unit}-{n:016x}.film");
        let path = self.dir.join(&name);
        let written = (|| {
            let mut f = File::create(&path)?;
            for part in film.parts() {
                f.write_all(part)?;
            }
            f.sync_data()?;
            File::open(&self.dir)?.sync_all()
        })();
        if let Err(e) = written {
            let _ = std::fs::remove_file(&path);
            return Err(format!("cannot write the film {}: {e}", path.display()));
        }
        let mut reference = Vec::with_capacity(REF_MAGIC.len() + 8 + name.len());
        reference.extend_from_slice(&REF_MAGIC);
        reference.extend_from_slice(&(film.len() as u64).to_le_bytes());
        reference.extend_from_slice(name.as_bytes());
        Ok(reference)
    }

    /// Whether films can be written now: 4 MiB written, synced and
    /// removed (the store's health probe; the database's probe writes as
    /// much).
    pub fn probe(&self) -> Result<(), String> {
        let path = self.dir.join("probe.tmp");
        let written = (|| {
            let mut f = File::create(&path)?;
            f.write_all(&vec![0u8; 4 << 20])?;
            f.sync_data()
        })();
        let _ = std::fs::remove_file(&path);
        written.map_err(|e| format!("cannot write films to {}: {e}", self.dir.display()))
    }

    /// The file name a stored record refers to; None for a film stored
    /// in the record itself.
    pub fn name_of(record: &[u8]) -> Option<&str> {
        let rest = record.strip_prefix(&REF_MAGIC)?;
        let name = std::str::from_utf8(rest.get(8..)?).ok()?;
        // Only names `write` makes: no path can be smuggled in.
        let safe = name.ends_with(".film")
            && name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '.')
            && !name.starts_with('.');
        safe.then_some(name)
    }

    /// The film a stored record refers to, checked against its length.
    pub fn read(&self, record: &[u8]) -> Result<Vec<u8>, String> {
        let name = Self::name_of(record).ok_or("a malformed film reference")?;
        let len = u64::from_le_bytes(record[REF_MAGIC.len()..][..8].try_into().expect("8 bytes"));
        let path = self.dir.join(name);
        let bytes =
            std::fs::read(&path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        if bytes.len() as u64 != len {
            return Err(format!(
                "{} holds {} bytes, its reference says {len}",
                path.display(),
                bytes.len()
            ));
        }
        Ok(bytes)
    }

    /// Whether `record` refers to a file.
    pub fn is_reference(record: &[u8]) -> bool {
        record.starts_with(&REF_MAGIC)
    }

    /// Removes these files (their references are gone), as far as it can:
    /// one left behind is removed at the next open.
    pub fn remove<'a>(&self, names: impl IntoIterator<Item = &'a str>) {
        for name in names {
            if let Err(e) = std::fs::remove_file(self.dir.join(name))
                && e.kind() != std::io::ErrorKind::NotFound
            {
                tracing::warn!(file = name, error = %e, "cannot remove a film file no longer needed");
            }
        }
    }

    /// Removes the film files not in `keep`; returns how many.
    pub fn sweep(&self, keep: &HashSet<String>) -> usize {
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return 0;
        };
        let orphans: Vec<String> = entries
            .filter_map(|e| e.ok()?.file_name().into_string().ok())
            .filter(|n| n.ends_with(".film") && !keep.contains(n))
            .collect();
        self.remove(orphans.iter().map(String::as_str));
        orphans.len()
    }
}
