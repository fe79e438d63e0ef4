//! Renderers: any [`WorkRegion`] (a rectangle of a frame over a range of
//! sample indices), returning a [`Film`] of per-pixel sums and counts, or
//! what [`Output`] asks for ([`Renderer::render_as`]: the image resolved,
//! or the farm's result).
//!
//! Backends share the scene contract ([`World`]) and the sampling
//! ([`crate::sampling`]), so a sample traced anywhere has the same value
//! (bit for bit on the CPU; within a stated tolerance on the GPU).

pub mod adaptive;
pub mod cpu;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod step;

use crate::film::{Film, RayCounts, Rect, SampleRange, WorkRegion};
use crate::scene::{RenderSettings, SceneDesc};
use crate::world::World;

pub use cpu::CpuRenderer;
#[cfg(feature = "gpu")]
pub use gpu::{GpuError, GpuOptions, GpuRenderer};

/// Arithmetic precision of a render.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Precision {
    /// Fast path.
    #[default]
    F32,
    /// Reference: ground truth for tests and benchmarks.
    F64,
}

impl Precision {
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::F64 => "f64",
        }
    }
}

impl std::str::FromStr for Precision {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "f32" => Ok(Precision::F32),
            "f64" => Ok(Precision::F64),
            _ => Err(format!(
                "unknown precision {s:?}: expected \"f32\" or \"f64\""
            )),
        }
    }
}

/// Where a render is traced: the one backend type of the CLI, the workers
/// and the benchmarks; tessera-proto converts it to and from the wire's
/// `Backend`. Both variants exist in every build: opening a GPU
/// [`Renderer`] in a build without the `gpu` feature is an error
/// ([`RendererError::GpuNotBuilt`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Backend {
    /// CPU threads ([`CpuRenderer`]).
    Cpu,
    /// GPU compute shaders (`GpuRenderer`, feature `gpu`).
    Gpu,
}

impl Backend {
    /// `cpu` or `gpu`: the name on the command line, in output and in files.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Cpu => "cpu",
            Backend::Gpu => "gpu",
        }
    }
}

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // `pad`, so widths in format strings (`{:<4}`) apply.
        f.pad(self.name())
    }
}

impl std::str::FromStr for Backend {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cpu" => Ok(Backend::Cpu),
            "gpu" => Ok(Backend::Gpu),
            _ => Err(format!(
                "unknown backend {s:?}: expected \"cpu\" or \"gpu\""
            )),
        }
    }
}

/// Render-ready state of one frame of a scene at one precision. Build once
/// per frame, render many tiles from it.
#[derive(Clone, Debug)]
pub enum PreparedFrame {
    F32(World<f32>),
    F64(World<f64>),
}

impl PreparedFrame {
    /// `settings` are valid ([`RenderSettings::validate`]): they were
    /// checked where they were parsed (the scene file, the overrides'
    /// `apply`, the wire's conversion), not again here.
    pub fn build(
        desc: &SceneDesc,
        settings: &RenderSettings,
        frame: u32,
        precision: Precision,
    ) -> Result<Self, RenderError> {
        Self::build_from(desc, desc.models(), settings, frame, precision)
    }

    /// As [`PreparedFrame::build`] for a scene rendered once: `desc` is
    /// consumed, and its models are freed as soon as their triangles are
    /// placed, so a big mesh's peak memory (the tree's build) does not
    /// also hold the file as loaded (about 28 bytes a triangle).
    pub fn build_owned(
        mut desc: SceneDesc,
        settings: &RenderSettings,
        frame: u32,
        precision: Precision,
    ) -> Result<Self, RenderError> {
        let models = desc.take_models();
        Self::build_from(&desc, models, settings, frame, precision)
    }

    fn build_from(
        desc: &SceneDesc,
        models: Vec<Option<std::sync::Arc<crate::mesh::Mesh>>>,
        settings: &RenderSettings,
        frame: u32,
        precision: Precision,
    ) -> Result<Self, RenderError> {
        debug_assert_eq!(
            settings.validate(),
            Ok(()),
            "settings are validated where parsed"
        );
        Ok(match precision {
            Precision::F32 => PreparedFrame::F32(World::build_from(desc, models, settings, frame)),
            Precision::F64 => PreparedFrame::F64(World::build_from(desc, models, settings, frame)),
        })
    }

    pub fn stats(&self) -> crate::world::WorldStats {
        match self {
            PreparedFrame::F32(w) => w.stats(),
            PreparedFrame::F64(w) => w.stats(),
        }
    }

    pub fn settings(&self) -> &RenderSettings {
        match self {
            PreparedFrame::F32(w) => &w.settings,
            PreparedFrame::F64(w) => &w.settings,
        }
    }

    /// Checks that a request lies inside the image and the sample count.
    pub fn check_request(&self, rect: Rect, samples: SampleRange) -> Result<(), RenderError> {
        let s = self.settings();
        if rect.area() == 0 || !Rect::full(s.width, s.height).contains(&rect) {
            return Err(RenderError::RectOutside {
                rect,
                width: s.width,
                height: s.height,
            });
        }
        if samples.is_empty() || samples.end > s.samples {
            return Err(RenderError::SamplesOutside {
                samples,
                count: s.samples,
            });
        }
        Ok(())
    }

    /// Each block `i` of `rect` (block-aligned) over `from[i]..to[i]`:
    /// its range, checked as a request, or none where `to[i] <= from[i]`.
    /// What both backends' `render_blocks` take.
    pub fn block_ranges(
        &self,
        rect: Rect,
        from: &[u32],
        to: &[u32],
    ) -> Result<Vec<Option<SampleRange>>, RenderError> {
        let blocks = crate::adaptive::BlockMask::none(rect).active.len();
        assert_eq!(
            (from.len(), to.len()),
            (blocks, blocks),
            "a range per block"
        );
        from.iter()
            .zip(to)
            .map(|(&a, &b)| {
                let r = SampleRange::new(a, b.max(a));
                if r.is_empty() {
                    return Ok(None);
                }
                self.check_request(rect, r)?;
                Ok(Some(r))
            })
            .collect()
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("rectangle {rect:?} is empty or outside the {width}x{height} image")]
    RectOutside { rect: Rect, width: u32, height: u32 },
    #[error("sample range {}..{} is empty or outside 0..{count}", .samples.start, .samples.end)]
    SamplesOutside { samples: SampleRange, count: u32 },
    #[error("cannot start render threads: {0}")]
    Threads(String),
}

/// What a render hands back ([`Renderer::render_as`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Output {
    /// The film's fixed-point sums: what merges exactly (tiles, bands).
    Sums,
    /// The image resolved and sRGB-encoded to 8 bits (a PNG's bytes):
    /// exactly `Film::srgb8` of the sums; the GPU resolves it on the
    /// device and reads back 3 bytes a pixel instead of 24.
    Srgb8,
    /// The image resolved to linear f32 RGB (an EXR's), exactly
    /// `Film::resolve` of the sums, on the GPU resolved on the device.
    Linear,
    /// A farm unit's result: on the GPU the sums packed on the device
    /// into the wire's compact layout (`Rendered::Packed`); on the CPU the
    /// film, which the worker encodes.
    FarmResult,
}

/// A render as [`Output`] asked for it.
pub enum Rendered {
    Film(Film),
    Srgb8(Srgb8Image),
    Linear(LinearImage),
    #[cfg(feature = "gpu")]
    Packed(gpu::PackedSums),
}

/// A render resolved to 8-bit sRGB ([`Output::Srgb8`]).
pub struct Srgb8Image {
    pub rect: Rect,
    /// RGB bytes, row-major: exactly `Film::srgb8` of the render's film.
    pub rgb: Vec<u8>,
    pub rays: RayCounts,
    pub nonfinite: u64,
}

/// A render resolved to linear f32 RGB ([`Output::Linear`]).
pub struct LinearImage {
    pub rect: Rect,
    /// Row-major: exactly `Film::resolve` of the render's film, bit for bit.
    pub rgb: Vec<[f32; 3]>,
    pub rays: RayCounts,
    pub nonfinite: u64,
}

impl Rendered {
    /// `film` as `output` asks for it, resolved on the host (what the CPU
    /// backend returns; the GPU's are these, made on the device).
    pub fn of_film(film: Film, output: Output) -> Rendered {
        match output {
            Output::Sums | Output::FarmResult => Rendered::Film(film),
            Output::Srgb8 => Rendered::Srgb8(Srgb8Image {
                rect: film.rect,
                rgb: film.srgb8(),
                rays: film.rays,
                nonfinite: film.nonfinite,
            }),
            Output::Linear => Rendered::Linear(LinearImage {
                rect: film.rect,
                rgb: film.resolve(),
                rays: film.rays,
                nonfinite: film.nonfinite,
            }),
        }
    }
}

/// A renderer of either backend, chosen at run time: the one interface
/// `tessera render` and farm workers render through.
pub enum Renderer {
    Cpu(CpuRenderer),
    #[cfg(feature = "gpu")]
    Gpu(Box<GpuRenderer>),
}

/// Why a [`Renderer`] could not render.
#[derive(Debug, thiserror::Error)]
pub enum RendererError {
    #[error(transparent)]
    Cpu(#[from] RenderError),
    #[cfg(feature = "gpu")]
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("this tessera was built without the GPU backend (cargo feature `gpu`)")]
    GpuNotBuilt,
}

impl Renderer {
    /// Opens a renderer of `backend`: the CPU one with `threads` (`None`:
    /// all cores), the GPU one on `adapter` (index or part of its name;
    /// `None`: the best) with default options. A GPU in a build without
    /// the `gpu` feature is [`RendererError::GpuNotBuilt`].
    pub fn open(
        backend: Backend,
        threads: Option<usize>,
        adapter: Option<&str>,
    ) -> Result<Self, RendererError> {
        Ok(match backend {
            Backend::Cpu => Renderer::Cpu(CpuRenderer::new(threads)?),
            #[cfg(feature = "gpu")]
            Backend::Gpu => Renderer::Gpu(Box::new(GpuRenderer::new(adapter, Default::default())?)),
            #[cfg(not(feature = "gpu"))]
            Backend::Gpu => {
                let _ = adapter;
                return Err(RendererError::GpuNotBuilt);
            }
        })
    }

    /// The backend this renderer traces on.
    pub fn backend(&self) -> Backend {
        match self {
            Renderer::Cpu(_) => Backend::Cpu,
            #[cfg(feature = "gpu")]
            Renderer::Gpu(_) => Backend::Gpu,
        }
    }

    /// Runs `f` on the CPU renderer's threads (its rayon pool), so that
    /// host work between a render's rounds uses the threads the user gave
    /// it; on the GPU's, on the caller's pool.
    pub fn install<T: Send>(&self, f: impl FnOnce() -> T + Send) -> T {
        match self {
            Renderer::Cpu(r) => r.pool().install(f),
            #[cfg(feature = "gpu")]
            Renderer::Gpu(_) => f(),
        }
    }

    /// Renders `region`'s sums, as [`CpuRenderer::render`].
    pub fn render(
        &self,
        prepared: &PreparedFrame,
        region: WorkRegion,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<Film, RendererError> {
        Ok(match self {
            Renderer::Cpu(r) => r.render(prepared, region, progress)?,
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => r.render(prepared, region, progress)?,
        })
    }

    /// Renders `region` as `output` asks: the one entry point of `tessera
    /// render` and the farm's workers. `None` once `cancel` is set (the CPU
    /// checks it before each tile; a GPU submission, once queued, runs to
    /// its end).
    pub fn render_as(
        &self,
        prepared: &PreparedFrame,
        region: WorkRegion,
        output: Output,
        progress: &(dyn Fn(u64) + Sync),
        cancel: &std::sync::atomic::AtomicBool,
    ) -> Result<Option<Rendered>, RendererError> {
        Ok(match self {
            Renderer::Cpu(r) => r
                .render_until(prepared, region, progress, cancel)?
                .map(|film| Rendered::of_film(film, output)),
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => {
                if cancel.load(std::sync::atomic::Ordering::Relaxed) {
                    return Ok(None);
                }
                Some(r.render_as(prepared, region, output, progress)?)
            }
        })
    }

    /// CPU threads that trace (0 for the GPU backend).
    pub fn threads(&self) -> usize {
        match self {
            Renderer::Cpu(r) => r.threads(),
            #[cfg(feature = "gpu")]
            Renderer::Gpu(_) => 0,
        }
    }

    /// The GPU adapter's name (`None` for the CPU backend).
    pub fn adapter_name(&self) -> Option<&str> {
        match self {
            Renderer::Cpu(_) => None,
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => Some(&r.adapter().name),
        }
    }

    /// Bytes of the last rendered scene's buffers on the GPU (`None` for
    /// the CPU backend).
    pub fn device_scene_bytes(&self) -> Option<u64> {
        match self {
            Renderer::Cpu(_) => None,
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => Some(r.last_stats().scene_bytes),
        }
    }

    /// `cpu:Nt` or `gpu:ADAPTER`, for summaries and logs.
    pub fn describe(&self) -> String {
        match self.adapter_name() {
            None => format!("{}:{}t", self.backend(), self.threads()),
            Some(name) => format!("{}:{name}", self.backend()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backend_names_parse_back_and_others_are_refused() {
        for b in [Backend::Cpu, Backend::Gpu] {
            assert_eq!(b.name().parse::<Backend>(), Ok(b));
            assert_eq!(b.to_string(), b.name());
        }
        assert_eq!(
            "GPU".parse::<Backend>(),
            Err("unknown backend \"GPU\": expected \"cpu\" or \"gpu\"".to_string())
        );
    }

    #[test]
    fn a_cpu_renderer_opens_as_the_cpu_backend() {
        let r = Renderer::open(Backend::Cpu, Some(1), None).unwrap();
        assert_eq!((r.backend(), r.threads()), (Backend::Cpu, 1));
    }

    #[cfg(not(feature = "gpu"))]
    #[test]
    fn a_gpu_renderer_without_the_gpu_feature_is_a_clear_error() {
        let e = Renderer::open(Backend::Gpu, None, None).err().unwrap();
        assert!(matches!(e, RendererError::GpuNotBuilt));
        assert!(e.to_string().contains("cargo feature `gpu`"), "{e}");
    }
}
