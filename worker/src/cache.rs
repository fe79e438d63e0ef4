//! The worker's on-disk cache of job files, content-addressed: a file is
//! kept under its SHA-256 in `dir`, bounded by `max_bytes` (least recently
//! used out first; a file's modification time is its last use), reused
//! across jobs and restarts. Every read checks the bytes against the hash:
//! an entry that no longer matches (a flipped bit, a truncated write) is
//! removed and fetched again, never rendered from.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::SystemTime;

#[derive(Debug)]
pub struct AssetCache {
    dir: PathBuf,
    max_bytes: u64,
    next_tmp: AtomicU64,
    /// Entries found corrupt and removed (for logs and tests).
    pub corrupt: AtomicU64,
}

use tessera_proto::transport::is_sha256_hex as valid_hash;
pub use tessera_proto::transport::sha256_hex;

impl AssetCache {
    pub fn open(dir: &Path, max_bytes: u64) -> std::io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        // Leftovers of writes cut short.
        for e in std::fs::read_dir(dir)?.flatten() {
            if e.file_name().to_string_lossy().ends_with(".tmp") {
                let _ = std::fs::remove_file(e.path());
            }
        }
        Ok(AssetCache {
            dir: dir.to_owned(),
            max_bytes,
            next_tmp: AtomicU64::new(0),
            corrupt: AtomicU64::new(0),
        })
    }

    fn path(&self, sha256: &str) -> PathBuf {
        self.dir.join(sha256)
    }

    /// The cached bytes of `sha256`, checked; None when absent or corrupt
    /// (a corrupt entry is removed).
    pub fn get(&self, sha256: &str) -> Option<Vec<u8>> {
        if !valid_hash(sha256) {
            return None;
        }
        let path = self.path(sha256);
        let data = std::fs::read(&path).ok()?;
        if sha256_hex(&data) != sha256 {
            tracing::warn!(sha256, path = %path.display(), "cached file does not match its hash: fetching it again");
            self.corrupt.fetch_add(1, Ordering::Relaxed);
            let _ = std::fs::remove_file(&path);
            return None;
        }
        if let Ok(f) = std::fs::File::options().write(true).open(&path) {
            let _ = f.set_modified(SystemTime::now());
        }
        Some(data)
    }

    /// Stores `data` (already checked against `sha256`), then evicts the
    /// least recently used entries beyond the size bound. A file larger
    /// than the whole cache is not kept.
    pub fn put(&self, sha256: &str, data: &[u8]) -> std::io::Result<()> {
        if !valid_hash(sha256) || data.len() as u64 > self.max_bytes {
            return Ok(());
        }
        let n = self.next_tmp.fetch_add(1, Ordering::Relaxed);
        let tmp = self
            .dir
            .join(format!("{sha256}.{}.{n}.tmp", std::process::id()));
        let result = (|| {
            let mut f = std::fs::File::create(&tmp)?;
            f.write_all(data)?;
            f.sync_all()?;
            std::fs::rename(&tmp, self.path(sha256))
        })();
        if result.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        self.evict(sha256);
        result
    }

    fn evict(&self, keep: &str) {
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return;
        };
        let mut files: Vec<(SystemTime, u64, PathBuf)> = entries
            .flatten()
            .filter(|e| valid_hash(&e.file_name().to_string_lossy()))
            .filter_map(|e| {
                let m = e.metadata().ok()?;
                Some((m.modified().ok()?, m.len(), e.path()))
            })
            .collect();
        let mut total: u64 = files.iter().map(|f| f.1).sum();
        files.sort();
        for (_, len, path) in files {
            if total <= self.max_bytes {
                break;
            }
            if path.file_name().is_some_and(|n| n == keep) {
                continue;
            }
            if std::fs::remove_file(&path).is_ok() {
                total -= len;
                tracing::debug!(path = %path.display(), bytes = len, "evicted from the asset cache");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entries_are_checked_and_the_oldest_go_first() {
        let dir = std::env::temp_dir().join(format!("tessera-cache-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let cache = AssetCache::open(&dir, 10).unwrap();
        let (a, b, c) = (b"aaaa".as_slice(), b"bbbb".as_slice(), b"cccc".as_slice());
        let (ha, hb, hc) = (sha256_hex(a), sha256_hex(b), sha256_hex(c));
        cache.put(&ha, a).unwrap();
        let old = SystemTime::now() - std::time::Duration::from_secs(60);
        let f = std::fs::File::options()
            .write(true)
            .open(dir.join(&ha))
            .unwrap();
        f.set_modified(old).unwrap();
        cache.put(&hb, b).unwrap();
        assert_eq!(
            cache.get(&ha).as_deref(),
            Some(a),
            "a used again: b is now the oldest"
        );
        let f = std::fs::File::options()
            .write(true)
            .open(dir.join(&hb))
            .unwrap();
        f.set_modified(old).unwrap();
        cache.put(&hc, c).unwrap();
        assert!(cache.get(&hb).is_none(), "b evicted (12 bytes > 10)");
        assert_eq!(cache.get(&hc).as_deref(), Some(c));
        // A flipped byte: detected, removed, reported absent.
        std::fs::write(dir.join(&hc), b"cccC").unwrap();
        assert!(cache.get(&hc).is_none());
        assert!(!dir.join(&hc).exists());
        assert_eq!(cache.corrupt.load(Ordering::Relaxed), 1);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
