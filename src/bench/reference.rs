//! Reference images: the f64 CPU renderer, cached on disk under a hash of the
//! scene file and the settings, so each is made once. Converged references
//! use many jittered samples; the depth suite's use the tested runs' own
//! samples (see `get_exact`).

use std::path::{Path, PathBuf};
use std::time::Instant;
use tracer_core::film::WorkRegion;

use anyhow::{Context, Result};
use tracer_core::film::{Rect, SampleRange};
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::sampling::Sampler;
use tracer_core::scene::{RenderSettings, SceneDesc};

/// Bump when a change to the tracer changes what references contain.
const CACHE_VERSION: u32 = 1;

/// Stable 64-bit FNV-1a (std's hasher may change between Rust releases).
fn fnv1a(bytes: &[u8], mut h: u64) -> u64 {
    for b in bytes {
        h ^= *b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// The FNV-1a hash of a scene file's bytes (part of reference cache keys).
pub fn scene_hash(path: &Path) -> Result<u64> {
    let text = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    Ok(fnv1a(&text, 0xcbf2_9ce4_8422_2325))
}

pub struct ReferenceCache {
    dir: PathBuf,
    renderer: CpuRenderer,
}

impl ReferenceCache {
    pub fn new(dir: PathBuf, threads: Option<usize>) -> Result<Self> {
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create reference cache {}", dir.display()))?;
        Ok(ReferenceCache {
            dir,
            renderer: CpuRenderer::new(threads)?,
        })
    }

    /// The default cache: `$XDG_CACHE_HOME/tessera/references`, else `~/.cache/...`.
    pub fn default_dir() -> PathBuf {
        std::env::var_os("XDG_CACHE_HOME")
            .map(PathBuf::from)
            .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".cache")))
            .unwrap_or_else(std::env::temp_dir)
            .join("tessera/references")
    }

    /// Linear RGB of the reference for `scene` (read from `path`) at
    /// `settings`, except that samples and sampler are the reference's own.
    pub fn get(
        &self,
        path: &Path,
        scene: &SceneDesc,
        settings: &RenderSettings,
        samples: u32,
    ) -> Result<Vec<[f32; 3]>> {
        self.get_exact(
            path,
            scene,
            &RenderSettings {
                samples,
                sampler: Sampler::Jittered,
                ..*settings
            },
        )
    }

    /// Linear RGB of the f64 CPU render of `scene` at exactly `settings`
    /// (same samples, same sampler), cached like [`Self::get`]'s.
    pub fn get_exact(
        &self,
        path: &Path,
        scene: &SceneDesc,
        settings: &RenderSettings,
    ) -> Result<Vec<[f32; 3]>> {
        let settings = *settings;
        let samples = settings.samples;
        let text =
            std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
        let key = format!(
            "v{CACHE_VERSION} {}x{} s{} d{} {}",
            settings.width,
            settings.height,
            settings.samples,
            settings.max_depth,
            settings.sampler.name()
        );
        let hash = fnv1a(key.as_bytes(), fnv1a(&text, 0xcbf2_9ce4_8422_2325));
        let stem = path
            .file_stem()
            .map_or("scene".into(), |s| s.to_string_lossy().into_owned());
        let file = self.dir.join(format!("{stem}-{hash:016x}.exr"));
        if let Ok(img) = image::open(&file) {
            let img = img.to_rgb32f();
            if img.dimensions() == (settings.width, settings.height) {
                return Ok(img.pixels().map(|p| p.0).collect());
            }
        }
        eprintln!(
            "bench: making reference {} ({}x{}, {} {} samples, f64, depth {})",
            file.display(),
            settings.width,
            settings.height,
            samples,
            settings.sampler.name(),
            settings.max_depth
        );
        let start = Instant::now();
        let frame = PreparedFrame::build(scene, &settings, 0, Precision::F64)?;
        let film = self.renderer.render(
            &frame,
            WorkRegion::new(
                0,
                Rect::full(settings.width, settings.height),
                SampleRange::all(samples),
            ),
            &|_| {},
        )?;
        let linear = film.resolve();
        // Write to a temporary name first: an interrupted run leaves no bad
        // cache entry. The error names the file.
        let tmp = file.with_extension("exr.tmp");
        tracer_core::film::image::write_exr(&tmp, settings.width, settings.height, &linear)?;
        std::fs::rename(&tmp, &file)?;
        eprintln!(
            "bench: reference made in {:.1} s",
            start.elapsed().as_secs_f64()
        );
        Ok(linear)
    }
}
