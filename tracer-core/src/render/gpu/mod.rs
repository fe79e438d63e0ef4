//! The GPU renderer: the same renders as [`super::CpuRenderer`] through a
//! wgpu compute shader (Vulkan, Metal or DX12; lavapipe in CI).
//!
//! Data flow: a [`PreparedFrame::F32`] is packed into [`layout::SceneData`]
//! (per-kind primitive arrays, materials, lights, camera) and uploaded once;
//! the compute pipeline is specialised to the scene through overridable
//! constants (primitive and light counts, `max_depth`, whether reflection or
//! refraction can happen at all) and cached with it, so tiles of the same
//! frame reuse both. A render clears a per-pixel buffer of 32.32 fixed-point
//! sums (two u32 words per channel; WGSL has no u64), splits the rectangle x
//! sample range into dispatches of bounded size, groups them into bounded
//! submissions (no single submission long enough for a driver watchdog),
//! and reads back sums and ray counters into a [`Film`] whose `u64` sums
//! merge exactly with CPU films.
//!
//! An adaptive round ([`GpuRenderer::render_round`]) traces a grid over
//! the active blocks only (their positions in a storage buffer) with the
//! same kernel compiled with `ADAPTIVE`, which also sums each pixel's
//! squared fixed-point samples (four carried u32 words a channel).
//!
//! `whitted.wgsl` mirrors `render/whitted.rs`; `sampling.wgsl` mirrors
//! `sampling.rs`; `layout.rs` mirrors the WGSL structs.

mod disk_cache;
pub mod launch;
pub mod layout;

pub use disk_cache::default_dir as default_pipeline_cache_dir;

use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use wgpu::util::DeviceExt as _;

use self::layout::{ADAPTIVE_SUM_WORDS, COUNTERS, DispatchParams, SUM_WORDS, SceneData};
use super::{PreparedFrame, RenderError};
use crate::adaptive::{BLOCK, BlockMask};
use crate::film::{Film, RayCounts, Rect, SampleRange};

const SAMPLING_WGSL: &str = include_str!("sampling.wgsl");
const WHITTED_WGSL: &str = include_str!("whitted.wgsl");
const WAVEFRONT_WGSL: &str = include_str!("wavefront.wgsl");
/// Scene queries for worlds without a tree: loops over spheres and planes.
const ANALYTIC_WGSL: &str = include_str!("analytic.wgsl");
const DISTRIBUTED_WGSL: &str = include_str!("distributed.wgsl");
/// Moving meshes' queries for distributed.wgsl (needs BVH_WGSL) ...
const MOVING_MESHES_WGSL: &str = include_str!("moving_meshes.wgsl");
/// ... and their stand-ins for worlds without moving meshes.
const NO_MOVING_MESHES_WGSL: &str = include_str!("no_moving_meshes.wgsl");
/// Sums to 8-bit sRGB on the GPU, for renders that read back only the image.
const RESOLVE_WGSL: &str = include_str!("resolve.wgsl");
/// Tree traversal, for worlds with a BVH (meshes, many spheres) or moving meshes.
const BVH_WGSL: &str = include_str!("bvh.wgsl");
/// Scene queries for worlds with a BVH, through BVH_WGSL.
const ACCEL_WGSL: &str = include_str!("accel.wgsl");

/// Dynamic uniform offsets must be multiples of this (256 is the largest
/// alignment any adapter asks for).
const PARAMS_STRIDE: u64 = 256;
/// Dispatch parameter slots per submission.
const PARAMS_SLOTS: usize = 64;
/// How long to wait for one submission before calling the device hung.
const SUBMISSION_TIMEOUT: Duration = Duration::from_secs(120);

#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error(
        "no GPU adapter found (wgpu saw no Vulkan/Metal/DX12 device; on Linux install mesa-vulkan-drivers for lavapipe)"
    )]
    NoAdapter,
    #[error("no GPU adapter matches {wanted:?}; available: {available}")]
    AdapterNotFound { wanted: String, available: String },
    #[error("cannot open GPU device on {adapter}: {message}")]
    RequestDevice { adapter: String, message: String },
    #[error("the GPU backend renders in f32 only; use --precision f32 (f64 is the CPU reference)")]
    F64Unsupported,
    #[error(
        "the scene's BVH has a node at depth {depth} whose traversal needs more than the GPU traversal stack of {stack} entries; render it with --backend cpu"
    )]
    TreeTooDeep { depth: usize, stack: usize },
    #[error("the scene's BVH cannot be traversed on the GPU: {0}")]
    BadTree(String),
    #[error(transparent)]
    Request(#[from] RenderError),
    #[error(
        "{what} needs {needed} bytes but the GPU allows at most {limit} ({limit_name}); render a smaller rectangle"
    )]
    TooLarge {
        what: &'static str,
        needed: u64,
        limit: u64,
        limit_name: &'static str,
    },
    #[error(
        "invalid workgroup shape {x}x{y}: need 1..={max} invocations and each side within the adapter's limits"
    )]
    Workgroup { x: u32, y: u32, max: u32 },
    #[error("GPU out of memory: {0}")]
    OutOfMemory(String),
    #[error("GPU device lost: {0}")]
    DeviceLost(String),
    #[error("GPU error: {0}")]
    Device(String),
    #[error(
        "GPU did not finish a submission within {0:?} (hung or far too much work per submission)"
    )]
    Timeout(Duration),
    #[error("cannot read GPU results back: {0}")]
    Readback(String),
}

/// One adapter as `tessera gpus` lists it.
#[derive(Clone, Debug)]
pub struct AdapterSummary {
    pub index: usize,
    pub name: String,
    pub device_type: String,
    pub backend: String,
    pub driver: String,
    pub driver_info: String,
}

impl std::fmt::Display for AdapterSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: {} ({}, {}, driver {} {})",
            self.index, self.name, self.device_type, self.backend, self.driver, self.driver_info
        )
    }
}

fn instance() -> wgpu::Instance {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
    // No validation layers by default (slow, and absent on most machines);
    // WGPU_DEBUG / WGPU_VALIDATION and WGPU_BACKEND still apply.
    desc.flags = wgpu::InstanceFlags::empty();
    wgpu::Instance::new(desc.with_env())
}

fn adapters(instance: &wgpu::Instance) -> Vec<wgpu::Adapter> {
    pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()))
}

fn summary(index: usize, a: &wgpu::Adapter) -> AdapterSummary {
    let i = a.get_info();
    AdapterSummary {
        index,
        name: i.name,
        device_type: format!("{:?}", i.device_type),
        backend: format!("{:?}", i.backend),
        driver: i.driver,
        driver_info: i.driver_info,
    }
}

/// Every adapter wgpu can use on this machine, in a stable order (the
/// indices `--adapter N` takes).
pub fn list_adapters() -> Vec<AdapterSummary> {
    adapters(&instance())
        .iter()
        .enumerate()
        .map(|(i, a)| summary(i, a))
        .collect()
}

fn type_rank(t: wgpu::DeviceType) -> u32 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    }
}

/// How the GPU walks each sample's ray tree (WGSL has no recursion).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Strategy {
    /// One invocation per pixel-sample walks that sample's whole ray tree with a
    /// bounded per-thread task stack (whitted.wgsl `render`).
    #[default]
    Stack,
    /// The thesis's weighted ray tasks: one dispatch per generation of rays
    /// over a queue of tasks, children appended to the next queue
    /// (wavefront.wgsl).
    Wavefront,
}

/// Launch shape and work split. The defaults are the best of the
/// launch-shape sweep (see docs/benchmarks.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuOptions {
    /// Workgroup size in pixels (x, y).
    pub workgroup: (u32, u32),
    /// Upper bound on pixel-samples one dispatch traces.
    pub dispatch_pixel_samples: u64,
    /// Upper bound on pixel-samples one submission traces: bounds the time
    /// of a submission, so no driver watchdog kills it.
    pub submit_pixel_samples: u64,
    pub strategy: Strategy,
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions {
            workgroup: (8, 8),
            dispatch_pixel_samples: 1 << 24,
            submit_pixel_samples: 1 << 24,
            strategy: Strategy::Stack,
        }
    }
}

/// Timings of the last render.
#[derive(Clone, Copy, Debug, Default)]
pub struct GpuStats {
    /// GPU time of the tracing passes from timestamp queries, if the adapter has them.
    pub gpu_time: Option<Duration>,
    /// Host wall time from the first submission to the last trace
    /// submission's completion, read-back excluded.
    pub trace_wall: Duration,
    /// Host wall time of the whole render call (upload of parameters,
    /// tracing, read-back, conversion into a Film).
    pub total_wall: Duration,
    /// Host wall time of the read-back: copy, map, conversion into the Film.
    pub readback: Duration,
    pub dispatches: u32,
    pub submissions: u32,
    /// Times the wavefront's queues overflowed and the render was redone in smaller dispatches.
    pub overflow_retries: u32,
}

/// Scene state kept between renders: buffers and the specialised pipeline.
struct SceneState {
    data: SceneData,
    options: GpuOptions,
    pipeline: wgpu::ComputePipeline,
    /// The module and constants `pipeline` was made from, and the same
    /// kernel for adaptive rounds (`ADAPTIVE`), made on first use.
    module: wgpu::ShaderModule,
    constants: Vec<(&'static str, f64)>,
    adaptive: Option<wgpu::ComputePipeline>,
    frame: wgpu::Buffer,
    spheres: wgpu::Buffer,
    planes: wgpu::Buffer,
    materials: wgpu::Buffer,
    lights: wgpu::Buffer,
    /// BVH nodes, leaf references, triangles, triangle shading (one-element
    /// placeholders for scenes without a tree, whose kernel never reads them).
    tree: [wgpu::Buffer; 4],
    /// `DistData::words` (a placeholder for scenes without distributed effects).
    dist: wgpu::Buffer,
    wave: Option<WavePipelines>,
}

struct WavePipelines {
    primary: wgpu::ComputePipeline,
    swap: wgpu::ComputePipeline,
    shade: wgpu::ComputePipeline,
    /// Tasks one queue holds.
    queue_cap: u64,
}

/// The wavefront's task queues and state, grown on demand.
struct WaveBuffers {
    queue_cap: u64,
    a: wgpu::Buffer,
    b: wgpu::Buffer,
    state: wgpu::Buffer,
    state_read: wgpu::Buffer,
    args: wgpu::Buffer,
    args_group: wgpu::BindGroup,
}

/// Output buffers, grown on demand and reused.
struct Outputs {
    /// Capacity of `sums` in u32 words.
    sum_words: usize,
    sums: wgpu::Buffer,
    sums_read: wgpu::Buffer,
    counters: wgpu::Buffer,
    counters_read: wgpu::Buffer,
    params: wgpu::Buffer,
}

/// A render resolved to 8-bit sRGB on the GPU ([`GpuRenderer::render_srgb8`]).
pub struct Srgb8Image {
    pub rect: Rect,
    /// RGB bytes, row-major: exactly `Film::srgb8` of the film that
    /// [`GpuRenderer::render`] returns for the same call.
    pub rgb: Vec<u8>,
    pub rays: RayCounts,
    pub nonfinite: u64,
}

/// What a render traces and reads back.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Readout<'a> {
    /// The fixed-point sums: a [`Film`] that merges exactly (farm results).
    Sums,
    /// Only the image, resolved on the GPU.
    Srgb8,
    /// An adaptive round: only the blocks of the mask, each pixel's sums
    /// and sums of squares (a [`Film::with_squares`]).
    Adaptive(&'a BlockMask),
}

enum Rendered {
    Film(Film),
    Srgb8(Srgb8Image),
}

/// The resolve pipeline and its buffers, made on first use (farm workers
/// never resolve).
struct Resolver {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    params: wgpu::Buffer,
    thresholds: wgpu::Buffer,
    /// The sample count whose thresholds `thresholds` holds.
    samples: Option<u32>,
    pixels: usize,
    image: wgpu::Buffer,
    image_read: wgpu::Buffer,
}

/// Bytes of a resolved image of `pixels`: 3 words per 4 pixels, rounded to
/// whole 8-byte words so that it maps (`wgpu::MAP_ALIGNMENT`).
fn image_bytes(pixels: usize) -> u64 {
    pixels.div_ceil(8) as u64 * 24
}

/// Errors reported by wgpu outside any call's return value.
#[derive(Default)]
struct Fault {
    lost: Option<String>,
    error: Option<GpuError>,
}

pub struct GpuRenderer {
    info: AdapterSummary,
    device: wgpu::Device,
    queue: wgpu::Queue,
    layout: wgpu::BindGroupLayout,
    pipeline_layout: wgpu::PipelineLayout,
    wave_layout: wgpu::BindGroupLayout,
    wave_args_layout: wgpu::BindGroupLayout,
    wave_pipeline_layout: wgpu::PipelineLayout,
    wave_swap_layout: wgpu::PipelineLayout,
    timestamps: bool,
    options: GpuOptions,
    fault: Arc<Mutex<Fault>>,
    scene: Mutex<Option<SceneState>>,
    outputs: Mutex<Option<Outputs>>,
    wave: Mutex<Option<WaveBuffers>>,
    resolver: Mutex<Option<Resolver>>,
    /// Compiled pipelines on disk, where the device has a pipeline cache.
    disk_cache: Option<disk_cache::DiskCache>,
    stats: Mutex<GpuStats>,
}

impl GpuRenderer {
    /// Opens the adapter named by `adapter` (an index into [`list_adapters`]
    /// or a case-insensitive part of its name), else the best one (discrete
    /// over integrated over software).
    pub fn new(adapter: Option<&str>, options: GpuOptions) -> Result<Self, GpuError> {
        Self::with_pipeline_cache(adapter, options, disk_cache::default_dir().as_deref())
    }

    /// [`GpuRenderer::new`] with compiled pipelines cached in `cache_dir`
    /// (`None`: not cached) instead of [`default_pipeline_cache_dir`].
    pub fn with_pipeline_cache(
        adapter: Option<&str>,
        options: GpuOptions,
        cache_dir: Option<&std::path::Path>,
    ) -> Result<Self, GpuError> {
        let instance = instance();
        let all = adapters(&instance);
        if all.is_empty() {
            return Err(GpuError::NoAdapter);
        }
        let chosen = match adapter {
            Some(wanted) => {
                let found = match wanted.trim().parse::<usize>() {
                    Ok(i) => all.get(i),
                    Err(_) => {
                        let w = wanted.to_lowercase();
                        all.iter()
                            .find(|a| a.get_info().name.to_lowercase().contains(&w))
                    }
                };
                found.ok_or_else(|| GpuError::AdapterNotFound {
                    wanted: wanted.to_string(),
                    available: all
                        .iter()
                        .enumerate()
                        .map(|(i, a)| format!("{i}: {}", a.get_info().name))
                        .collect::<Vec<_>>()
                        .join(", "),
                })?
            }
            None => all
                .iter()
                .min_by_key(|a| type_rank(a.get_info().device_type))
                .expect("not empty"),
        };
        let index = all
            .iter()
            .position(|a| std::ptr::eq(a, chosen))
            .unwrap_or(0);
        let info = summary(index, chosen);

        let (x, y) = options.workgroup;
        let alimits = chosen.limits();
        if x == 0
            || y == 0
            || x * y > alimits.max_compute_invocations_per_workgroup
            || x > alimits.max_compute_workgroup_size_x
            || y > alimits.max_compute_workgroup_size_y
        {
            return Err(GpuError::Workgroup {
                x,
                y,
                max: alimits.max_compute_invocations_per_workgroup,
            });
        }
        // A software adapter (lavapipe) is ~1000x slower than a discrete GPU:
        // smaller submissions keep each one far from the wait timeout.
        let mut options = options;
        if chosen.get_info().device_type == wgpu::DeviceType::Cpu {
            options.dispatch_pixel_samples = options.dispatch_pixel_samples.min(1 << 20);
            options.submit_pixel_samples = options.submit_pixel_samples.min(1 << 21);
        }
        let timestamps = chosen.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        let wanted = wgpu::Features::TIMESTAMP_QUERY
            | if cache_dir.is_some() {
                wgpu::Features::PIPELINE_CACHE
            } else {
                wgpu::Features::empty()
            };
        let (device, queue) = pollster::block_on(chosen.request_device(&wgpu::DeviceDescriptor {
            label: Some("tessera"),
            required_features: chosen.features() & wanted,
            // Everything the adapter allows: large films need large storage bindings.
            required_limits: alimits,
            ..Default::default()
        }))
        .map_err(|e| GpuError::RequestDevice {
            adapter: info.name.clone(),
            message: e.to_string(),
        })?;

        let fault = Arc::new(Mutex::new(Fault::default()));
        {
            let f = fault.clone();
            device.set_device_lost_callback(move |reason, msg| {
                if let Ok(mut f) = f.lock() {
                    f.lost = Some(format!("{reason:?}: {msg}"));
                }
            });
            // The default handler panics; record instead and fail the render.
            let f = fault.clone();
            device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
                if let Ok(mut f) = f.lock()
                    && f.error.is_none()
                {
                    f.error = Some(classify(e));
                }
            }));
        }

        let storage = |binding, read_only| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let uniform = |binding, dynamic| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: dynamic,
                min_binding_size: None,
            },
            count: None,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tessera scene"),
            entries: &[
                uniform(0, false),
                uniform(1, true),
                storage(2, true),
                storage(3, true),
                storage(4, true),
                storage(5, true),
                storage(6, false),
                storage(7, false),
                // The BVH: nodes, leaf references, triangles, triangle shading.
                storage(8, true),
                storage(9, true),
                storage(10, true),
                storage(11, true),
                // Distributed effects (distributed.wgsl; a placeholder elsewhere).
                storage(12, true),
                // An adaptive round's active blocks (a placeholder elsewhere).
                storage(13, true),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("tessera"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let wave_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tessera wavefront queues"),
            entries: &[storage(0, true), storage(1, false), storage(2, false)],
        });
        let wave_args_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tessera wavefront args"),
            entries: &[storage(0, false)],
        });
        let wave_pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("tessera wavefront"),
            bind_group_layouts: &[Some(&layout), Some(&wave_layout)],
            immediate_size: 0,
        });
        let wave_swap_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("tessera wavefront swap"),
            bind_group_layouts: &[Some(&layout), Some(&wave_layout), Some(&wave_args_layout)],
            immediate_size: 0,
        });
        let disk_cache =
            cache_dir.and_then(|d| disk_cache::DiskCache::open(&device, &chosen.get_info(), d));
        Ok(GpuRenderer {
            info,
            device,
            queue,
            layout,
            pipeline_layout,
            wave_layout,
            wave_args_layout,
            wave_pipeline_layout,
            wave_swap_layout,
            timestamps,
            options,
            fault,
            scene: Mutex::new(None),
            outputs: Mutex::new(None),
            wave: Mutex::new(None),
            resolver: Mutex::new(None),
            disk_cache,
            stats: Mutex::new(GpuStats::default()),
        })
    }

    /// An unmapped buffer (every output, queue and read-back buffer).
    fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage,
            mapped_at_creation: false,
        })
    }

    fn pipeline_cache(&self) -> Option<&wgpu::PipelineCache> {
        self.disk_cache.as_ref().map(|c| c.cache())
    }

    /// The file compiled pipelines are cached in, if they are.
    pub fn pipeline_cache_file(&self) -> Option<&std::path::Path> {
        self.disk_cache.as_ref().map(|c| c.path())
    }

    pub fn adapter(&self) -> &AdapterSummary {
        &self.info
    }

    pub fn has_timestamps(&self) -> bool {
        self.timestamps
    }

    pub fn options(&self) -> GpuOptions {
        self.options
    }

    /// Timings of the last completed render.
    pub fn last_stats(&self) -> GpuStats {
        self.stats.lock().map(|s| *s).unwrap_or_default()
    }

    fn check_fault(&self) -> Result<(), GpuError> {
        let mut f = self
            .fault
            .lock()
            .map_err(|_| GpuError::Device("fault record poisoned".into()))?;
        if let Some(msg) = &f.lost {
            return Err(GpuError::DeviceLost(msg.clone()));
        }
        match f.error.take() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// Renders `rect` of `frame` over sample indices `samples`, like
    /// [`super::CpuRenderer::render`]. `progress` gets the pixel-samples of
    /// each finished submission.
    pub fn render(
        &self,
        prepared: &PreparedFrame,
        frame: u32,
        rect: Rect,
        samples: SampleRange,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<Film, GpuError> {
        match self.render_readout(prepared, frame, rect, samples, progress, Readout::Sums)? {
            Rendered::Film(f) => Ok(f),
            Rendered::Srgb8(_) => unreachable!("asked for sums"),
        }
    }

    /// Renders like [`GpuRenderer::render`], then resolves and sRGB-encodes
    /// on the GPU and reads back only the 8-bit image: a local render to PNG
    /// moves 3 bytes a pixel over the bus instead of 24.
    pub fn render_srgb8(
        &self,
        prepared: &PreparedFrame,
        frame: u32,
        rect: Rect,
        samples: SampleRange,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<Srgb8Image, GpuError> {
        match self.render_readout(prepared, frame, rect, samples, progress, Readout::Srgb8)? {
            Rendered::Srgb8(i) => Ok(i),
            Rendered::Film(_) => unreachable!("asked for the image"),
        }
    }

    /// One round of adaptive sampling (see [`crate::adaptive`]): the blocks
    /// of `mask` over `samples`, in one grid over the active blocks only,
    /// into a film of `mask.rect` with sums of squares; pixels of inactive
    /// blocks keep zero samples. Sums and ray counts equal those of
    /// [`GpuRenderer::render`] over the same pixels and samples; each pixel's
    /// squares are the sums of its samples' squared fixed-point values.
    pub fn render_round(
        &self,
        prepared: &PreparedFrame,
        frame: u32,
        mask: &BlockMask,
        samples: SampleRange,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<Film, GpuError> {
        if mask.active_count() == 0 {
            prepared.check_request(mask.rect, samples)?;
            return Ok(Film::with_squares(mask.rect));
        }
        match self.render_readout(
            prepared,
            frame,
            mask.rect,
            samples,
            progress,
            Readout::Adaptive(mask),
        )? {
            Rendered::Film(f) => Ok(f),
            Rendered::Srgb8(_) => unreachable!("asked for sums"),
        }
    }

    fn render_readout(
        &self,
        prepared: &PreparedFrame,
        frame: u32,
        rect: Rect,
        samples: SampleRange,
        progress: &(dyn Fn(u64) + Sync),
        readout: Readout<'_>,
    ) -> Result<Rendered, GpuError> {
        prepared.check_request(rect, samples)?;
        let world = match prepared {
            PreparedFrame::F32(w) => w,
            PreparedFrame::F64(_) => return Err(GpuError::F64Unsupported),
        };
        self.check_fault()?;
        let start = Instant::now();
        // Tiles of one frame reuse the packed tree (packing a million
        // triangles costs more than tracing them).
        let packed = self
            .scene
            .lock()
            .ok()
            .and_then(|s| s.as_ref().and_then(|s| s.data.tree.clone()));
        let data = SceneData::from_world(world, packed.as_ref())?;

        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        // The wavefront's queues hold a bounded number of tasks; if a
        // generation overflows them, render again in smaller dispatches.
        let mut budget = self.options.dispatch_pixel_samples;
        let mut retries = 0;
        let result = loop {
            match self.render_inner(
                data.clone(),
                frame,
                rect,
                samples,
                progress,
                start,
                budget,
                readout,
            ) {
                Ok(None) if budget > 1 => {
                    budget = (budget / 4).max(1);
                    retries += 1;
                }
                Ok(None) => {
                    break Err(GpuError::Device(
                        "wavefront queues overflow even for tiny dispatches".into(),
                    ));
                }
                Ok(Some(film)) => {
                    if let Ok(mut s) = self.stats.lock() {
                        s.overflow_retries = retries;
                    }
                    break Ok(film);
                }
                Err(e) => break Err(e),
            }
        };
        // Scopes pop in reverse order.
        let v = pollster::block_on(validation.pop());
        let o = pollster::block_on(oom.pop());
        self.check_fault()?;
        if let Some(e) = o.or(v) {
            // A failed scene upload must not be reused.
            if let Ok(mut s) = self.scene.lock() {
                *s = None;
            }
            return Err(classify(e));
        }
        result
    }

    #[allow(clippy::too_many_arguments)]
    fn render_inner(
        &self,
        data: SceneData,
        frame: u32,
        rect: Rect,
        samples: SampleRange,
        progress: &(dyn Fn(u64) + Sync),
        start: Instant,
        budget: u64,
        readout: Readout<'_>,
    ) -> Result<Option<Rendered>, GpuError> {
        let limits = self.device.limits();
        let mut scene_guard = self
            .scene
            .lock()
            .map_err(|_| GpuError::Device("scene cache poisoned".into()))?;
        if scene_guard
            .as_ref()
            .is_none_or(|s| s.data != data || s.options != self.options)
        {
            *scene_guard = Some(self.upload_scene(data, &limits)?);
        }
        let mask = match readout {
            Readout::Adaptive(m) => Some(m),
            _ => None,
        };
        if mask.is_some() {
            let scene = scene_guard.as_mut().expect("just set");
            if scene.adaptive.is_none() {
                scene.adaptive = Some(self.adaptive_pipeline(scene));
            }
        }
        let scene = scene_guard.as_ref().expect("just set");

        let pixels = rect.area();
        let stride = if mask.is_some() {
            ADAPTIVE_SUM_WORDS
        } else {
            SUM_WORDS
        };
        let sums_bytes = (pixels * stride * 4) as u64;
        check_size(
            "the film's per-pixel sums",
            sums_bytes,
            limits.max_storage_buffer_binding_size,
            "max_storage_buffer_binding_size",
        )?;
        check_size(
            "the film's per-pixel sums",
            sums_bytes,
            limits.max_buffer_size,
            "max_buffer_size",
        )?;
        let mut out_guard = self
            .outputs
            .lock()
            .map_err(|_| GpuError::Device("output cache poisoned".into()))?;
        if out_guard
            .as_ref()
            .is_none_or(|o| o.sum_words < pixels * stride)
        {
            *out_guard = Some(self.create_outputs(pixels * stride));
        }
        let out = out_guard.as_ref().expect("just set");
        // An adaptive round's grid: 8 columns, 8 rows per active block
        // (whitted.wgsl grid_pixel), its blocks listed as column | row << 16.
        let blocks: Vec<u32> = mask.map_or_else(Vec::new, |m| {
            let cols = m.cols() as usize;
            m.active
                .iter()
                .enumerate()
                .filter(|(_, a)| **a)
                .map(|(i, _)| (i % cols) as u32 | ((i / cols) as u32) << 16)
                .collect()
        });
        let blocks_buffer = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("active blocks"),
                contents: if blocks.is_empty() {
                    &[0u8; 16]
                } else {
                    bytemuck::cast_slice(&blocks)
                },
                usage: wgpu::BufferUsages::STORAGE,
            });
        let grid = match mask {
            Some(_) => Rect::new(rect.x, rect.y, BLOCK, BLOCK * blocks.len() as u32),
            None => rect,
        };
        // Pixels of the film a band of the grid's rows holds (blocks cut by
        // the film's edge hold fewer than their 64 grid cells).
        let band_pixels = |row0: u32, rows: u32| -> u64 {
            match mask {
                None => rect.width as u64 * rows as u64,
                Some(_) => (row0..row0 + rows)
                    .map(|r| {
                        let b = blocks[(r / BLOCK) as usize];
                        let (fx, fy) = ((b & 0xffff) * BLOCK, (b >> 16) * BLOCK + r % BLOCK);
                        if fy < rect.height {
                            (rect.width - fx).min(BLOCK) as u64
                        } else {
                            0
                        }
                    })
                    .sum(),
            }
        };

        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera render"),
            layout: &self.layout,
            entries: &[
                entire(0, &scene.frame),
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &out.params,
                        offset: 0,
                        size: wgpu::BufferSize::new(size_of::<DispatchParams>() as u64),
                    }),
                },
                entire(2, &scene.spheres),
                entire(3, &scene.planes),
                entire(4, &scene.materials),
                entire(5, &scene.lights),
                wgpu::BindGroupEntry {
                    binding: 6,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &out.sums,
                        offset: 0,
                        size: wgpu::BufferSize::new(sums_bytes),
                    }),
                },
                entire(7, &out.counters),
                entire(8, &scene.tree[0]),
                entire(9, &scene.tree[1]),
                entire(10, &scene.tree[2]),
                entire(11, &scene.tree[3]),
                entire(12, &scene.dist),
                entire(13, &blocks_buffer),
            ],
        });

        let (wx, wy) = self.options.workgroup;
        // Adaptive rounds run on the stack kernel (as distributed effects do).
        let wave = match scene.wave.as_ref().filter(|_| mask.is_none()) {
            Some(p) => {
                let mut guard = self
                    .wave
                    .lock()
                    .map_err(|_| GpuError::Device("wavefront cache poisoned".into()))?;
                if guard.as_ref().is_none_or(|w| w.queue_cap < p.queue_cap) {
                    let bytes = p.queue_cap * layout::WAVE_TASK_BYTES;
                    check_size(
                        "a wavefront task queue",
                        bytes,
                        limits.max_storage_buffer_binding_size,
                        "max_storage_buffer_binding_size",
                    )?;
                    *guard = Some(self.create_wave_buffers(p.queue_cap));
                }
                Some((p, guard))
            }
            None => None,
        };
        let wave_groups = wave.as_ref().map(|(_, w)| {
            let w = w.as_ref().expect("just set");
            let group = |inq: &wgpu::Buffer, outq: &wgpu::Buffer| {
                self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("tessera wavefront queues"),
                    layout: &self.wave_layout,
                    entries: &[entire(0, inq), entire(1, outq), entire(2, &w.state)],
                })
            };
            // Primary tasks go to A; generations then alternate A->B, B->A.
            (group(&w.b, &w.a), group(&w.a, &w.b))
        });
        // Each wavefront dispatch's primary tasks must fit a queue, and a
        // queue's tasks one indirect dispatch.
        let budget = match &wave {
            Some((p, _)) => budget.min(p.queue_cap / 2).max(1),
            None => budget,
        };
        let groups = plan(
            grid,
            (rect.width, rect.height),
            samples,
            frame,
            GpuOptions {
                dispatch_pixel_samples: budget,
                ..self.options
            },
        );
        let query = self.timestamps.then(|| {
            let n = (groups.len() * 2) as u32;
            let set = self.device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("tessera timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: n,
            });
            let resolve = self.buffer(
                "timestamps",
                n as u64 * 8,
                wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            );
            let read = self.buffer(
                "timestamps read",
                n as u64 * 8,
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            );
            (set, resolve, read, n)
        });

        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tessera clear"),
            });
        enc.clear_buffer(&out.sums, 0, Some(sums_bytes));
        enc.clear_buffer(&out.counters, 0, None);
        if let Some((_, w)) = &wave {
            enc.clear_buffer(&w.as_ref().expect("set").state, 0, None);
        }
        let mut dispatches = 0u32;
        let trace_start = Instant::now();
        self.queue.submit([enc.finish()]);
        for (g, group) in groups.iter().enumerate() {
            let mut params = vec![0u8; group.len() * PARAMS_STRIDE as usize];
            for (i, d) in group.iter().enumerate() {
                let at = i * PARAMS_STRIDE as usize;
                params[at..at + size_of::<DispatchParams>()].copy_from_slice(bytemuck::bytes_of(d));
            }
            self.queue.write_buffer(&out.params, 0, &params);
            let mut enc = self
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("tessera trace"),
                });
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("tessera trace"),
                    timestamp_writes: query.as_ref().map(|(set, ..)| {
                        wgpu::ComputePassTimestampWrites {
                            query_set: set,
                            beginning_of_pass_write_index: Some(2 * g as u32),
                            end_of_pass_write_index: Some(2 * g as u32 + 1),
                        }
                    }),
                });
                match (&wave, &wave_groups) {
                    (Some((p, w)), Some((to_a, a_to_b))) => {
                        let w = w.as_ref().expect("set");
                        let threads = wx * wy;
                        for (i, d) in group.iter().enumerate() {
                            pass.set_bind_group(
                                0,
                                &bind_group,
                                &[(i as u64 * PARAMS_STRIDE) as u32],
                            );
                            pass.set_bind_group(1, to_a, &[]);
                            pass.set_bind_group(2, &w.args_group, &[]);
                            let n = d.rect_w * d.rows * (d.sample_end - d.sample_start);
                            pass.set_pipeline(&p.primary);
                            pass.dispatch_workgroups(n.div_ceil(threads), 1, 1);
                            // Generation g reads the queue generation g-1 wrote.
                            for g in 0..=scene.data.max_depth {
                                pass.set_pipeline(&p.swap);
                                pass.dispatch_workgroups(1, 1, 1);
                                pass.set_bind_group(1, if g % 2 == 0 { a_to_b } else { to_a }, &[]);
                                pass.set_pipeline(&p.shade);
                                pass.dispatch_workgroups_indirect(&w.args, 0);
                                dispatches += 2;
                            }
                            dispatches += 1;
                        }
                    }
                    _ => {
                        pass.set_pipeline(match mask {
                            Some(_) => scene.adaptive.as_ref().expect("made above"),
                            None => &scene.pipeline,
                        });
                        for (i, d) in group.iter().enumerate() {
                            pass.set_bind_group(
                                0,
                                &bind_group,
                                &[(i as u64 * PARAMS_STRIDE) as u32],
                            );
                            // One invocation per pixel-sample.
                            pass.dispatch_workgroups(
                                d.rect_w.div_ceil(wx),
                                d.rows.div_ceil(wy),
                                d.sample_end - d.sample_start,
                            );
                            dispatches += 1;
                        }
                    }
                }
            }
            let index = self.queue.submit([enc.finish()]);
            self.wait(index)?;
            progress(
                group
                    .iter()
                    .map(|d| band_pixels(d.row0, d.rows) * (d.sample_end - d.sample_start) as u64)
                    .sum(),
            );
        }
        let trace_wall = trace_start.elapsed();
        let readback_start = Instant::now();

        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tessera read-back"),
            });
        let resolver = match readout {
            Readout::Sums | Readout::Adaptive(_) => {
                enc.copy_buffer_to_buffer(&out.sums, 0, &out.sums_read, 0, Some(sums_bytes));
                None
            }
            Readout::Srgb8 => {
                Some(self.encode_resolve(&mut enc, &out.sums, sums_bytes, pixels, samples)?)
            }
        };
        enc.copy_buffer_to_buffer(&out.counters, 0, &out.counters_read, 0, None);
        if let Some((_, w)) = &wave {
            let w = w.as_ref().expect("set");
            enc.copy_buffer_to_buffer(&w.state, 0, &w.state_read, 0, None);
        }
        if let Some((set, resolve, read, n)) = &query {
            enc.resolve_query_set(set, 0..*n, resolve, 0);
            enc.copy_buffer_to_buffer(resolve, 0, read, 0, None);
        }
        let index = self.queue.submit([enc.finish()]);
        self.wait(index)?;

        if let Some((_, w)) = &wave {
            let state: Vec<u32> = self.read(
                &w.as_ref().expect("set").state_read,
                layout::WAVE_STATE_BYTES,
            )?;
            if state[2] != 0 {
                return Ok(None);
            }
        }
        let counters: Vec<u32> = self.read(&out.counters_read, (COUNTERS * 8) as u64)?;
        let counter = |k: usize| counters[2 * k] as u64 | (counters[2 * k + 1] as u64) << 32;
        let rays = RayCounts {
            primary: counter(layout::COUNTER_PRIMARY),
            shadow: counter(layout::COUNTER_SHADOW),
            reflection: counter(layout::COUNTER_REFLECTION),
            refraction: counter(layout::COUNTER_REFRACTION),
        };
        let nonfinite = counter(layout::COUNTER_NONFINITE);
        let rendered = match &resolver {
            Some(r) => {
                let r = r.as_ref().expect("made by encode_resolve");
                let rgb = self.read_with(&r.image_read, image_bytes(pixels), |bytes| {
                    bytes[..pixels * 3].to_vec()
                })?;
                Rendered::Srgb8(Srgb8Image {
                    rect,
                    rgb,
                    rays,
                    nonfinite,
                })
            }
            None => {
                let mut film = match mask {
                    Some(_) => Film::with_squares(rect),
                    None => Film::new(rect),
                };
                // Straight from the mapped buffer into the film: no intermediate copy.
                self.read_with(&out.sums_read, sums_bytes, |bytes| {
                    let words: &[u32] = bytemuck::cast_slice(bytes);
                    for (px, w) in film.sums.iter_mut().zip(words.chunks_exact(stride)) {
                        for c in 0..3 {
                            px[c] = w[2 * c] as u64 | (w[2 * c + 1] as u64) << 32;
                        }
                    }
                    if let Some(squares) = film.squares.as_mut() {
                        for (px, w) in squares.iter_mut().zip(words.chunks_exact(stride)) {
                            for c in 0..3 {
                                let q = &w[SUM_WORDS + 4 * c..SUM_WORDS + 4 * c + 4];
                                px[c] = q.iter().rev().fold(0u128, |acc, &x| acc << 32 | x as u128);
                            }
                        }
                    }
                })?;
                match mask {
                    Some(m) => {
                        for b in m.active_rects() {
                            for y in b.y..b.y + b.height {
                                let row = ((y - rect.y) * rect.width + (b.x - rect.x)) as usize;
                                film.counts[row..row + b.width as usize].fill(samples.len());
                            }
                        }
                    }
                    None => film.counts.fill(samples.len()),
                }
                film.rays = rays;
                film.nonfinite = nonfinite;
                Rendered::Film(film)
            }
        };
        drop(resolver);
        let gpu_time = match &query {
            Some((_, _, read, n)) => {
                let ticks: Vec<u64> = self.read(read, *n as u64 * 8)?;
                let period = self.queue.get_timestamp_period() as f64;
                let ns: f64 = ticks
                    .chunks_exact(2)
                    .map(|p| p[1].saturating_sub(p[0]) as f64 * period)
                    .sum();
                Some(Duration::from_nanos(ns as u64))
            }
            None => None,
        };
        let readback = readback_start.elapsed();
        if let Ok(mut s) = self.stats.lock() {
            *s = GpuStats {
                gpu_time,
                trace_wall,
                total_wall: start.elapsed(),
                dispatches,
                submissions: groups.len() as u32,
                overflow_retries: 0,
                readback,
            };
        }
        Ok(Some(rendered))
    }

    /// Records the resolve of `sums` (a film of `pixels`, each of
    /// `samples.len()` samples) to 8-bit sRGB and the image's copy to its
    /// read-back buffer; returns the locked resolver holding that buffer.
    fn encode_resolve(
        &self,
        enc: &mut wgpu::CommandEncoder,
        sums: &wgpu::Buffer,
        sums_bytes: u64,
        pixels: usize,
        samples: SampleRange,
    ) -> Result<std::sync::MutexGuard<'_, Option<Resolver>>, GpuError> {
        let mut guard = self
            .resolver
            .lock()
            .map_err(|_| GpuError::Device("resolver cache poisoned".into()))?;
        if guard.as_ref().is_none_or(|r| r.pixels < pixels) {
            let old = guard.take();
            *guard = Some(self.create_resolver(pixels, old));
        }
        let r = guard.as_mut().expect("just set");
        let n = samples.len();
        if r.samples != Some(n) {
            let t: Vec<[u32; 2]> = crate::film::srgb8_thresholds(n)
                .iter()
                .map(|&s| [s as u32, (s >> 32) as u32])
                .collect();
            self.queue
                .write_buffer(&r.thresholds, 0, bytemuck::cast_slice(&t));
            r.samples = Some(n);
        }
        self.queue.write_buffer(
            &r.params,
            0,
            bytemuck::cast_slice(&[pixels as u32, 0, 0, 0]),
        );
        let group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera resolve"),
            layout: &r.layout,
            entries: &[
                entire(0, &r.params),
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: sums,
                        offset: 0,
                        size: wgpu::BufferSize::new(sums_bytes),
                    }),
                },
                entire(2, &r.thresholds),
                entire(3, &r.image),
            ],
        });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tessera resolve"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&r.pipeline);
            pass.set_bind_group(0, &group, &[]);
            // One invocation per 4 pixels, 64 a workgroup; rows of workgroups
            // past the per-dimension limit (an 8K film).
            let groups = pixels.div_ceil(4 * 64) as u32;
            let x = groups.min(self.device.limits().max_compute_workgroups_per_dimension);
            pass.dispatch_workgroups(x, groups.div_ceil(x), 1);
        }
        enc.copy_buffer_to_buffer(&r.image, 0, &r.image_read, 0, Some(image_bytes(pixels)));
        Ok(guard)
    }

    /// The resolve pipeline (kept from `old`) with image buffers for `pixels`.
    fn create_resolver(&self, pixels: usize, old: Option<Resolver>) -> Resolver {
        use wgpu::BufferUsages as U;
        let image = self.buffer(
            "resolved image",
            image_bytes(pixels),
            U::STORAGE | U::COPY_SRC,
        );
        let image_read = self.buffer(
            "resolved image read",
            image_bytes(pixels),
            U::MAP_READ | U::COPY_DST,
        );
        if let Some(old) = old {
            return Resolver {
                pixels,
                image,
                image_read,
                ..old
            };
        }
        let entry = |binding, ty| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        use wgpu::BufferBindingType as B;
        let layout = self
            .device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("tessera resolve"),
                entries: &[
                    entry(0, B::Uniform),
                    entry(1, B::Storage { read_only: true }),
                    entry(2, B::Storage { read_only: true }),
                    entry(3, B::Storage { read_only: false }),
                ],
            });
        let pipeline_layout = self
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("tessera resolve"),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("resolve.wgsl"),
                source: wgpu::ShaderSource::Wgsl(RESOLVE_WGSL.into()),
            });
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("tessera resolve"),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some("resolve_srgb8"),
                compilation_options: Default::default(),
                cache: self.pipeline_cache(),
            });
        if let Some(c) = &self.disk_cache {
            c.save();
        }
        Resolver {
            pipeline,
            layout,
            params: self.buffer("resolve params", 16, U::UNIFORM | U::COPY_DST),
            thresholds: self.buffer("sRGB thresholds", 255 * 8, U::STORAGE | U::COPY_DST),
            samples: None,
            pixels,
            image,
            image_read,
        }
    }

    fn create_wave_buffers(&self, queue_cap: u64) -> WaveBuffers {
        use wgpu::BufferUsages as U;
        let args = self.buffer(
            "wavefront args",
            layout::WAVE_ARGS_BYTES,
            U::STORAGE | U::INDIRECT,
        );
        let args_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera wavefront args"),
            layout: &self.wave_args_layout,
            entries: &[entire(0, &args)],
        });
        WaveBuffers {
            queue_cap,
            a: self.buffer(
                "wavefront queue a",
                queue_cap * layout::WAVE_TASK_BYTES,
                U::STORAGE,
            ),
            b: self.buffer(
                "wavefront queue b",
                queue_cap * layout::WAVE_TASK_BYTES,
                U::STORAGE,
            ),
            state: self.buffer(
                "wavefront state",
                layout::WAVE_STATE_BYTES,
                U::STORAGE | U::COPY_SRC | U::COPY_DST,
            ),
            state_read: self.buffer(
                "wavefront state read",
                layout::WAVE_STATE_BYTES,
                U::MAP_READ | U::COPY_DST,
            ),
            args,
            args_group,
        }
    }

    fn upload_scene(&self, data: SceneData, limits: &wgpu::Limits) -> Result<SceneState, GpuError> {
        let make = |label, bytes: &[u8], usage| {
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents: bytes,
                    usage,
                })
        };
        let st = wgpu::BufferUsages::STORAGE;
        for (what, bytes) in [
            (
                "the scene's spheres",
                std::mem::size_of_val(data.spheres.as_slice()),
            ),
            (
                "the scene's planes",
                std::mem::size_of_val(data.planes.as_slice()),
            ),
            (
                "the scene's materials",
                std::mem::size_of_val(data.materials.as_slice()),
            ),
            (
                "the scene's lights",
                std::mem::size_of_val(data.lights.as_slice()),
            ),
            (
                "the scene's BVH nodes",
                data.tree
                    .as_ref()
                    .map_or(0, |t| std::mem::size_of_val(t.data.nodes.as_slice())),
            ),
            (
                "the scene's triangles",
                data.tree
                    .as_ref()
                    .map_or(0, |t| std::mem::size_of_val(t.data.triangles.as_slice())),
            ),
            (
                "the scene's triangle shading data",
                data.tree
                    .as_ref()
                    .map_or(0, |t| std::mem::size_of_val(t.data.shading.as_slice())),
            ),
        ] {
            check_size(
                what,
                bytes as u64,
                limits.max_storage_buffer_binding_size,
                "max_storage_buffer_binding_size",
            )?;
        }
        let frame = make(
            "frame",
            bytemuck::bytes_of(&data.frame),
            wgpu::BufferUsages::UNIFORM,
        );
        let spheres = make("spheres", bytemuck::cast_slice(&data.spheres), st);
        let planes = make("planes", bytemuck::cast_slice(&data.planes), st);
        let materials = make("materials", bytemuck::cast_slice(&data.materials), st);
        let lights = make("lights", bytemuck::cast_slice(&data.lights), st);
        let tree = match &data.tree {
            Some(t) => [
                make("bvh nodes", bytemuck::cast_slice(&t.data.nodes), st),
                make("bvh prims", bytemuck::cast_slice(&t.data.prims), st),
                make("triangles", bytemuck::cast_slice(&t.data.triangles), st),
                make(
                    "triangle shading",
                    bytemuck::cast_slice(&t.data.shading),
                    st,
                ),
            ],
            None => ["bvh nodes", "bvh prims", "triangles", "triangle shading"]
                .map(|label| make(label, &[0u8; 64], st)),
        };

        let dist = match &data.dist {
            Some(d) => make("distributed", bytemuck::cast_slice(&d.words), st),
            None => make("distributed", &[0u8; 64], st),
        };
        // Generated part: the stacks' capacities must be constant
        // expressions. Only scenes with a tree (their own or a moving
        // mesh's) compile the BVH traversal.
        let (traversal, queries) = match (&data.tree, data.static_tree) {
            (Some(_), true) => (BVH_WGSL, ACCEL_WGSL),
            (Some(_), false) => (BVH_WGSL, ANALYTIC_WGSL),
            (None, _) => ("", ANALYTIC_WGSL),
        };
        // Only scenes with distributed effects compile their kernel, and
        // only those with moving meshes its moving-mesh queries.
        let n_moving_meshes = data.dist.as_ref().map_or(0, |d| d.n_moving_meshes);
        let (distributed, moving_meshes) = match &data.dist {
            Some(_) if n_moving_meshes > 0 => (DISTRIBUTED_WGSL, MOVING_MESHES_WGSL),
            Some(_) => (DISTRIBUTED_WGSL, NO_MOVING_MESHES_WGSL),
            None => ("", ""),
        };
        let source = format!(
            "const STACK_CAP: u32 = {}u;\nconst BVH_STACK: u32 = {}u;\n{SAMPLING_WGSL}\n{WHITTED_WGSL}\n{traversal}\n{queries}\n{WAVEFRONT_WGSL}\n{distributed}\n{moving_meshes}",
            data.stack_capacity(),
            // One more entry than these trees can need (checked at packing to
            // be at most bvh::STACK; see bvh.wgsl), so shallow trees keep small stacks.
            data.tree
                .as_ref()
                .map_or(crate::bvh::STACK as u32, |t| t.data.stack)
                + 1
        );
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("whitted.wgsl"),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            });
        let b = |v: bool| if v { 1.0 } else { 0.0 };
        let constants = [
            ("N_SPHERES", data.n_spheres as f64),
            ("N_PLANES", data.n_planes as f64),
            ("N_LIGHTS", data.n_lights as f64),
            ("MAX_DEPTH", data.max_depth as f64),
            ("HAS_REFLECTION", b(data.has_reflection)),
            ("HAS_REFRACTION", b(data.has_refraction)),
            ("WG_X", self.options.workgroup.0 as f64),
            ("WG_Y", self.options.workgroup.1 as f64),
        ];
        let mut all_constants = constants.to_vec();
        if let Some(d) = &data.dist {
            all_constants.extend([
                ("N_DLIGHTS", d.n_lights as f64),
                ("N_MOVING", d.n_moving as f64),
                ("HAS_LENS", b(d.has_lens)),
                ("HAS_BLUR", b(d.has_blur)),
                ("HAS_CAM_MOTION", b(d.has_camera_motion)),
            ]);
            if n_moving_meshes > 0 {
                all_constants.push(("N_MOVING_MESHES", n_moving_meshes as f64));
            }
        }
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("tessera whitted"),
                layout: Some(&self.pipeline_layout),
                module: &module,
                entry_point: Some(if data.dist.is_some() {
                    "render_dist"
                } else {
                    "render"
                }),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &all_constants,
                    // Only the ray counters live in workgroup memory, and WGSL zeroes them anyway.
                    zero_initialize_workgroup_memory: true,
                },
                cache: self.pipeline_cache(),
            });
        // Distributed effects run on the stack kernel only.
        let wave =
            (self.options.strategy == Strategy::Wavefront && data.dist.is_none()).then(|| {
                // Twice the largest dispatch's primary tasks, within one indirect dispatch.
                let (wx, wy) = self.options.workgroup;
                let max_groups = limits.max_compute_workgroups_per_dimension as u64;
                let queue_cap = (2 * self.options.dispatch_pixel_samples)
                    .min(max_groups * (wx * wy) as u64)
                    .min(limits.max_storage_buffer_binding_size / layout::WAVE_TASK_BYTES);
                let mut wave_constants = constants.to_vec();
                wave_constants.push(("QUEUE_CAP", queue_cap as f64));
                let make = |entry: &str, layout: &wgpu::PipelineLayout| {
                    self.device
                        .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                            label: Some(entry),
                            layout: Some(layout),
                            module: &module,
                            entry_point: Some(entry),
                            compilation_options: wgpu::PipelineCompilationOptions {
                                constants: &wave_constants,
                                zero_initialize_workgroup_memory: true,
                            },
                            cache: self.pipeline_cache(),
                        })
                };
                WavePipelines {
                    primary: make("wave_primary", &self.wave_pipeline_layout),
                    swap: make("wave_swap", &self.wave_swap_layout),
                    shade: make("wave_shade", &self.wave_pipeline_layout),
                    queue_cap,
                }
            });
        if let Some(c) = &self.disk_cache {
            c.save();
        }
        Ok(SceneState {
            data,
            options: self.options,
            pipeline,
            module,
            constants: all_constants,
            adaptive: None,
            frame,
            spheres,
            planes,
            materials,
            lights,
            tree,
            dist,
            wave,
        })
    }

    /// The scene's kernel for adaptive rounds: its pipeline with `ADAPTIVE`.
    fn adaptive_pipeline(&self, scene: &SceneState) -> wgpu::ComputePipeline {
        let mut constants = scene.constants.clone();
        constants.push(("ADAPTIVE", 1.0));
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("tessera adaptive"),
                layout: Some(&self.pipeline_layout),
                module: &scene.module,
                entry_point: Some(if scene.data.dist.is_some() {
                    "render_dist"
                } else {
                    "render"
                }),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &constants,
                    zero_initialize_workgroup_memory: true,
                },
                cache: self.pipeline_cache(),
            });
        if let Some(c) = &self.disk_cache {
            c.save();
        }
        pipeline
    }

    fn create_outputs(&self, sum_words: usize) -> Outputs {
        let sums_bytes = (sum_words * 4) as u64;
        let counters_bytes = (COUNTERS * 8) as u64;
        use wgpu::BufferUsages as U;
        Outputs {
            sum_words,
            sums: self.buffer("sums", sums_bytes, U::STORAGE | U::COPY_SRC | U::COPY_DST),
            sums_read: self.buffer("sums read", sums_bytes, U::MAP_READ | U::COPY_DST),
            counters: self.buffer(
                "counters",
                counters_bytes,
                U::STORAGE | U::COPY_SRC | U::COPY_DST,
            ),
            counters_read: self.buffer("counters read", counters_bytes, U::MAP_READ | U::COPY_DST),
            params: self.buffer(
                "dispatch params",
                PARAMS_STRIDE * PARAMS_SLOTS as u64,
                U::UNIFORM | U::COPY_DST,
            ),
        }
    }

    /// Blocks until submission `index` is done, with a timeout, surfacing
    /// device loss and errors instead of hanging.
    fn wait(&self, index: wgpu::SubmissionIndex) -> Result<(), GpuError> {
        let r = self.device.poll(wgpu::PollType::Wait {
            submission_index: Some(index),
            timeout: Some(SUBMISSION_TIMEOUT),
        });
        self.check_fault()?;
        match r {
            Ok(_) => Ok(()),
            Err(wgpu::PollError::Timeout) => Err(GpuError::Timeout(SUBMISSION_TIMEOUT)),
            Err(e) => Err(GpuError::Device(e.to_string())),
        }
    }

    fn read<T: bytemuck::Pod>(
        &self,
        buffer: &wgpu::Buffer,
        bytes: u64,
    ) -> Result<Vec<T>, GpuError> {
        self.read_with(buffer, bytes, |view| {
            let mut v = vec![<T as bytemuck::Zeroable>::zeroed(); view.len() / size_of::<T>()];
            bytemuck::cast_slice_mut::<T, u8>(&mut v).copy_from_slice(view);
            v
        })
    }

    /// Maps the first `bytes` of `buffer` and hands them to `f`.
    fn read_with<R>(
        &self,
        buffer: &wgpu::Buffer,
        bytes: u64,
        f: impl FnOnce(&[u8]) -> R,
    ) -> Result<R, GpuError> {
        let (tx, rx) = mpsc::channel();
        buffer.map_async(wgpu::MapMode::Read, 0..bytes, move |r| {
            let _ = tx.send(r);
        });
        let r = self.device.poll(wgpu::PollType::Wait {
            submission_index: None,
            timeout: Some(SUBMISSION_TIMEOUT),
        });
        self.check_fault()?;
        if let Err(e) = r {
            return Err(GpuError::Readback(e.to_string()));
        }
        match rx.recv_timeout(SUBMISSION_TIMEOUT) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(GpuError::Readback(e.to_string())),
            Err(_) => return Err(GpuError::Readback("mapping never completed".into())),
        }
        let out = {
            let view = buffer
                .get_mapped_range(0..bytes)
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            f(&view)
        };
        buffer.unmap();
        Ok(out)
    }
}

fn entire(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

fn check_size(
    what: &'static str,
    needed: u64,
    limit: u64,
    limit_name: &'static str,
) -> Result<(), GpuError> {
    if needed > limit {
        Err(GpuError::TooLarge {
            what,
            needed,
            limit,
            limit_name,
        })
    } else {
        Ok(())
    }
}

fn classify(e: wgpu::Error) -> GpuError {
    match e {
        wgpu::Error::OutOfMemory { .. } => GpuError::OutOfMemory(e.to_string()),
        other => GpuError::Device(other.to_string()),
    }
}

/// Splits a render into dispatches (bands of rows x ranges of samples, each
/// at most `dispatch_pixel_samples`), grouped into submissions of at most
/// `submit_pixel_samples` and [`PARAMS_SLOTS`] dispatches.
/// `rect` is the grid (the film, or an adaptive round's blocks) and
/// `film` the film's size.
fn plan(
    rect: Rect,
    film: (u32, u32),
    samples: SampleRange,
    frame: u32,
    o: GpuOptions,
) -> Vec<Vec<DispatchParams>> {
    let w = rect.width as u64;
    let len = samples.len() as u64;
    let budget = o.dispatch_pixel_samples.max(1);
    // Samples are a dispatch's z dimension: at most 65535 workgroups.
    let chunk = (budget / w).clamp(1, len).min(65_535);
    let rows = (budget / (w * chunk)).clamp(1, rect.height as u64) as u32;
    let mut groups: Vec<Vec<DispatchParams>> = vec![Vec::new()];
    let mut in_group = 0u64;
    let mut row0 = 0;
    while row0 < rect.height {
        let band = rows.min(rect.height - row0);
        let mut s = samples.start;
        while s < samples.end {
            let e = (s as u64 + chunk).min(samples.end as u64) as u32;
            let work = w * band as u64 * (e - s) as u64;
            let last = groups.last_mut().expect("never empty");
            if !last.is_empty()
                && (in_group + work > o.submit_pixel_samples || last.len() == PARAMS_SLOTS)
            {
                groups.push(Vec::new());
                in_group = 0;
            }
            groups
                .last_mut()
                .expect("never empty")
                .push(DispatchParams {
                    rect_x: rect.x,
                    rect_y: rect.y,
                    rect_w: rect.width,
                    rect_h: rect.height,
                    row0,
                    rows: band,
                    sample_start: s,
                    sample_end: e,
                    frame,
                    film_w: film.0,
                    film_h: film.1,
                    _pad: 0,
                });
            in_group += work;
            s = e;
        }
        row0 += band;
    }
    groups
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plan_covers_every_pixel_sample_once_within_budgets() {
        let o = GpuOptions {
            workgroup: (8, 8),
            dispatch_pixel_samples: 1000,
            submit_pixel_samples: 5000,
            strategy: Strategy::Stack,
        };
        let rect = Rect::new(3, 7, 37, 23);
        let samples = SampleRange::new(2, 11);
        let groups = plan(rect, (rect.width, rect.height), samples, 0, o);
        let mut hits = vec![0u32; rect.area() * 16];
        for g in &groups {
            assert!(g.len() <= PARAMS_SLOTS);
            let work: u64 = g
                .iter()
                .map(|d| d.rect_w as u64 * d.rows as u64 * (d.sample_end - d.sample_start) as u64)
                .sum();
            assert!(
                work <= o.submit_pixel_samples || g.len() == 1,
                "group of {work}"
            );
            for d in g {
                for r in d.row0..d.row0 + d.rows {
                    for s in d.sample_start..d.sample_end {
                        for c in 0..d.rect_w {
                            hits[((r * rect.width + c) * 16 + s) as usize] += 1;
                        }
                    }
                }
            }
        }
        for r in 0..rect.height {
            for c in 0..rect.width {
                for s in 0..16 {
                    let want = u32::from((samples.start..samples.end).contains(&s));
                    assert_eq!(hits[((r * rect.width + c) * 16 + s) as usize], want);
                }
            }
        }
        // A row wider than the budget still gets one sample per dispatch.
        let wide = plan(Rect::full(4000, 2), (4000, 2), SampleRange::all(3), 0, o);
        assert_eq!(wide.iter().map(|g| g.len()).sum::<usize>(), 6);
    }
}
