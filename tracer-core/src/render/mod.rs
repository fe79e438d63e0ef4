//! Renderers: any rectangle of any frame for any range of sample indices,
//! returning a [`Film`] of per-pixel sums and counts.
//!
//! Backends share the scene contract ([`World`]) and the sampling
//! ([`crate::sampling`]), so a sample traced anywhere has the same value
//! (bit for bit on the CPU; within a stated tolerance on the GPU).

pub mod cpu;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod whitted;

use crate::film::{Film, Rect, SampleRange};
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

/// Render-ready state of one frame of a scene at one precision. Build once
/// per frame, render many tiles from it.
#[derive(Clone, Debug)]
pub enum PreparedFrame {
    F32(World<f32>),
    F64(World<f64>),
}

impl PreparedFrame {
    pub fn build(
        desc: &SceneDesc,
        settings: &RenderSettings,
        frame: u32,
        precision: Precision,
    ) -> Result<Self, RenderError> {
        settings.validate().map_err(RenderError::Settings)?;
        Ok(match precision {
            Precision::F32 => PreparedFrame::F32(World::build(desc, settings, frame)),
            Precision::F64 => PreparedFrame::F64(World::build(desc, settings, frame)),
        })
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
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("invalid render settings: {0}")]
    Settings(String),
    #[error("rectangle {rect:?} is empty or outside the {width}x{height} image")]
    RectOutside { rect: Rect, width: u32, height: u32 },
    #[error("sample range {}..{} is empty or outside 0..{count}", .samples.start, .samples.end)]
    SamplesOutside { samples: SampleRange, count: u32 },
    #[error("cannot start render threads: {0}")]
    Threads(String),
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
    #[error("{0}")]
    Unsupported(&'static str),
}

impl Renderer {
    /// Renders `rect` of `frame` over `samples`, as [`CpuRenderer::render`].
    pub fn render(
        &self,
        prepared: &PreparedFrame,
        frame: u32,
        rect: Rect,
        samples: SampleRange,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<Film, RendererError> {
        Ok(match self {
            Renderer::Cpu(r) => r.render(prepared, frame, rect, samples, progress)?,
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => r.render(prepared, frame, rect, samples, progress)?,
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

    /// `cpu:Nt` or `gpu:ADAPTER`, for summaries and logs.
    pub fn describe(&self) -> String {
        match self.adapter_name() {
            None => format!("cpu:{}t", self.threads()),
            Some(name) => format!("gpu:{name}"),
        }
    }
}
