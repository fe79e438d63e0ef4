//! Compiled pipelines kept on disk across processes: wgpu's pipeline cache
//! (Vulkan's `VkPipelineCache`) saved to a file per adapter, so that a new
//! process's first render skips the driver's shader compile.
//!
//! The file is a cache: any failure to read, check or write it is logged
//! and the render goes on without it. wgpu trusts the bytes it is given, so
//! they are wrapped with their length and a checksum, and a file that a
//! crash cut short or another program changed is ignored, not loaded.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// The file's first bytes: a tag and the wrapper's version.
const MAGIC: &[u8; 8] = b"TSPCv001";
/// Bytes of the wrapper before the data: magic, length, checksum.
const HEADER: usize = 8 + 8 + 8;

/// The default folder: `$TESSERA_PIPELINE_CACHE`, else
/// `$XDG_CACHE_HOME/tessera/pipelines`, else `$HOME/.cache/tessera/pipelines`.
/// `TESSERA_PIPELINE_CACHE=off` turns the cache off.
pub fn default_dir() -> Option<PathBuf> {
    let env = |k| std::env::var_os(k).filter(|v| !v.is_empty());
    if let Some(d) = env("TESSERA_PIPELINE_CACHE") {
        return (d != "off").then(|| PathBuf::from(d));
    }
    env("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| env("HOME").map(|h| Path::new(&h).join(".cache")))
        .map(|d| d.join("tessera").join("pipelines"))
}

/// A device's pipeline cache and the file it is loaded from and saved to.
pub(super) struct DiskCache {
    cache: wgpu::PipelineCache,
    path: PathBuf,
    /// Bytes of the data last loaded or saved: pipelines compiled since
    /// grow it, and only then is it worth writing again.
    saved: Mutex<usize>,
}

impl DiskCache {
    /// Opens the cache of `info`'s adapter in `dir`, or `None` where the
    /// device has no pipeline cache (`features` lacks it) or wgpu names no
    /// key for the backend.
    pub(super) fn open(
        device: &wgpu::Device,
        info: &wgpu::AdapterInfo,
        dir: &Path,
    ) -> Option<DiskCache> {
        if !device.features().contains(wgpu::Features::PIPELINE_CACHE) {
            return None;
        }
        let key = wgpu::util::pipeline_cache_key(info)?;
        let path = dir.join(format!("{key}.bin"));
        let data = match std::fs::read(&path) {
            Ok(bytes) => match unwrap(&bytes) {
                Some(d) => Some(d.to_vec()),
                None => {
                    tracing::warn!(path = %path.display(), "ignoring a damaged pipeline cache file");
                    None
                }
            },
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => {
                tracing::warn!(path = %path.display(), error = %e, "cannot read the pipeline cache");
                None
            }
        };
        let saved = data.as_ref().map_or(0, Vec::len);
        // SAFETY: the bytes are what `get_data` returned in an earlier
        // process (checked by length and checksum); `fallback` makes wgpu
        // start empty when they belong to another driver or version.
        let cache = unsafe {
            device.create_pipeline_cache(&wgpu::PipelineCacheDescriptor {
                label: Some("tessera pipelines"),
                data: data.as_deref(),
                fallback: true,
            })
        };
        Some(DiskCache {
            cache,
            path,
            saved: Mutex::new(saved),
        })
    }

    pub(super) fn cache(&self) -> &wgpu::PipelineCache {
        &self.cache
    }

    pub(super) fn path(&self) -> &Path {
        &self.path
    }

    /// Writes the cache if pipelines were compiled into it since it was
    /// loaded or last saved: to a temporary file renamed over the old, so
    /// a reader never sees half a file.
    pub(super) fn save(&self) {
        let Some(data) = self.cache.get_data() else {
            return;
        };
        let Ok(mut saved) = self.saved.lock() else {
            return;
        };
        if data.len() == *saved {
            return;
        }
        let tmp = self
            .path
            .with_extension(format!("tmp{}", std::process::id()));
        let write = || -> std::io::Result<()> {
            if let Some(dir) = self.path.parent() {
                std::fs::create_dir_all(dir)?;
            }
            std::fs::write(&tmp, wrap(&data))?;
            std::fs::rename(&tmp, &self.path)
        };
        match write() {
            Ok(()) => *saved = data.len(),
            Err(e) => {
                let _ = std::fs::remove_file(&tmp);
                tracing::warn!(path = %self.path.display(), error = %e, "cannot save the pipeline cache");
                // Do not try again for every render.
                *saved = data.len();
            }
        }
    }
}

/// FNV-1a, 64-bit: catches a cut-short or altered file (not an attacker,
/// who could write any cache file of this user's anyway).
fn checksum(data: &[u8]) -> u64 {
    data.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

fn wrap(data: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER + data.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(data.len() as u64).to_le_bytes());
    out.extend_from_slice(&checksum(data).to_le_bytes());
    out.extend_from_slice(data);
    out
}

/// The data inside a file written by [`wrap`], if it is whole and unchanged.
fn unwrap(file: &[u8]) -> Option<&[u8]> {
    let (head, data) = file.split_at_checked(HEADER)?;
    let word = |i: usize| u64::from_le_bytes(head[i..i + 8].try_into().expect("8 bytes"));
    (&head[..8] == MAGIC && word(8) == data.len() as u64 && word(16) == checksum(data))
        .then_some(data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_whole_unchanged_files_unwrap() {
        let data = b"pipeline bytes".to_vec();
        let file = wrap(&data);
        assert_eq!(unwrap(&file), Some(&data[..]));
        assert_eq!(unwrap(&wrap(&[])), Some(&[][..]));
        // Cut short anywhere, one bit changed anywhere, or a longer tail.
        for cut in 0..file.len() {
            assert_eq!(unwrap(&file[..cut]), None, "cut at {cut}");
        }
        for i in 0..file.len() {
            let mut bad = file.clone();
            bad[i] ^= 0x10;
            assert_eq!(unwrap(&bad), None, "byte {i} changed");
        }
        let mut longer = file.clone();
        longer.push(0);
        assert_eq!(unwrap(&longer), None);
    }
}
