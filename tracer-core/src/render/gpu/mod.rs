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
//! squared fixed-point samples (four carried u32 words a channel). A whole
//! adaptive render ([`GpuRenderer::render_adaptive`], `converge.rs`)
//! chains its rounds on the GPU, a kernel retiring converged blocks
//! between them.
//!
//! WGSL: `wgsl.rs` assembles each module from the .wgsl files' explicit
//! `//! import` lines and declares every bind group layout once (build.rs
//! validates every module with naga). `shade.wgsl` is the one shading
//! step (`render/step.rs`, `render/cpu/distributed.rs`), driven by
//! `whitted.wgsl` (stack) and `wavefront.wgsl`; `sampling.wgsl` mirrors
//! `sampling.rs`; `layout.rs` mirrors the WGSL structs.
//!
//! Files: this one has the renderer's types, the device it opens and the
//! public calls; `adapter.rs` finds and names adapters; `pipelines.rs`
//! assembles the WGSL for a scene and builds its pipelines and buffers;
//! `plan.rs` splits a render into bounded dispatches and submissions;
//! `grid.rs` is what a render's grid covers (the film, or an adaptive
//! render's listed blocks);
//! `converge.rs` runs an adaptive render's rounds without the host;
//! `trace.rs` runs one render (the dispatches, then the read-back into a
//! film or image); `readback.rs` waits, maps buffers and resolves on the
//! GPU (to 8-bit sRGB for PNG, to f32 for EXR); `disk_cache.rs` keeps
//! compiled pipelines on disk; `launch.rs` is the launch-shape sweep the
//! benches share.

mod adapter;
mod converge;
mod disk_cache;
mod grid;
pub mod launch;
pub mod layout;
mod pack;
mod pipelines;
mod plan;
mod readback;
mod trace;
mod wgsl;

pub use adapter::{AdapterSummary, list_adapters};
pub use disk_cache::default_dir as default_pipeline_cache_dir;
pub use pack::PackedSums;

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use self::adapter::{adapters, instance, summary, type_rank};
use self::layout::SceneData;
use super::{LinearImage, Output, PreparedFrame, RenderError, Rendered, Srgb8Image};
use crate::adaptive::BlockMask;
use crate::film::{Film, Rect, SampleRange, WorkRegion};

/// Dynamic uniform offsets must be multiples of this (256 is the largest
/// alignment any adapter asks for).
const PARAMS_STRIDE: u64 = 256;
/// Dispatch parameter slots per submission.
const PARAMS_SLOTS: usize = 64;
/// The params buffer's bytes for one submission's dispatches, each at its
/// slot ([`PARAMS_STRIDE`] apart).
fn params_bytes(group: &[layout::DispatchParams]) -> Vec<u8> {
    let mut bytes = vec![0u8; group.len() * PARAMS_STRIDE as usize];
    for (i, d) in group.iter().enumerate() {
        let at = i * PARAMS_STRIDE as usize;
        bytes[at..at + size_of::<layout::DispatchParams>()].copy_from_slice(bytemuck::bytes_of(d));
    }
    bytes
}

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
        "the scene's model materials use {0}, which the GPU backend does not render yet; render it with --backend cpu"
    )]
    Materials(String),
    #[error(
        "the scene's textures need {needed} bytes on the GPU, over the texture budget of {budget} bytes ({budget_name}); render it with --backend cpu or with smaller textures"
    )]
    TextureBudget {
        needed: u64,
        budget: u64,
        budget_name: &'static str,
    },
    #[error(
        "the scene's BVH has a node at depth {depth} whose traversal needs more than the GPU traversal stack of {stack} entries; render it with --backend cpu"
    )]
    TreeTooDeep { depth: usize, stack: usize },
    #[error("the scene's BVH cannot be traversed on the GPU: {0}")]
    BadTree(String),
    #[error(transparent)]
    Request(#[from] RenderError),
    #[error(
        "{what} needs {needed} bytes but the GPU allows at most {limit} ({limit_name}); {advice}"
    )]
    TooLarge {
        what: &'static str,
        needed: u64,
        limit: u64,
        limit_name: &'static str,
        /// What to do instead (a smaller rectangle, or the CPU backend).
        advice: &'static str,
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
    /// Bytes of the scene's buffers on the device (`SceneData::device_bytes`).
    pub scene_bytes: u64,
}

/// Scene state kept between renders: buffers and the specialised pipeline.
struct SceneState {
    data: SceneData,
    options: GpuOptions,
    pipeline: wgpu::ComputePipeline,
    /// The module and constants `pipeline` was made from, and the same
    /// kernel for adaptive rounds (`ADAPTIVE`), made on first use.
    module: wgpu::ShaderModule,
    /// The WGSL `module` was made from: with `constants`, what decides
    /// whether the next scene can keep the pipelines.
    source: String,
    constants: Vec<(&'static str, f64)>,
    adaptive: Option<wgpu::ComputePipeline>,
    frame: wgpu::Buffer,
    spheres: wgpu::Buffer,
    planes: wgpu::Buffer,
    materials: wgpu::Buffer,
    lights: wgpu::Buffer,
    /// BVH nodes, leaf references, triangles, triangle shading, instances
    /// (placeholders for scenes without a tree, whose kernel never reads them).
    tree: [wgpu::Buffer; 5],
    /// `DistData::words` (a placeholder for scenes without distributed effects).
    dist: wgpu::Buffer,
    /// `PbrData`'s mat_pbr, pbrs, tri_attrs, vertices, texels (placeholders without).
    pbr: [wgpu::Buffer; 5],
    wave: Option<WavePipelines>,
}

struct WavePipelines {
    primary: wgpu::ComputePipeline,
    swap: wgpu::ComputePipeline,
    shade: wgpu::ComputePipeline,
    /// Tasks one queue holds.
    queue_cap: u64,
    /// Bytes of one task (Whitted's rays or the path integrator's paths).
    task_bytes: u64,
}

/// The wavefront's task queues and state, grown on demand.
struct WaveBuffers {
    /// Bytes of each queue.
    queue_bytes: u64,
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

/// What the GPU resolves a film's sums to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Resolve {
    /// 8-bit sRGB, 3 bytes a pixel (resolve.wgsl `resolve_srgb8`): PNG.
    Srgb8,
    /// Linear f32 RGB, 12 bytes a pixel (resolve_linear.wgsl): EXR.
    Linear,
}

/// What a render traces and reads back.
#[derive(Clone, Copy)]
enum Readout<'a> {
    /// The fixed-point sums: a [`Film`] that merges exactly (farm results).
    Sums,
    /// Only the image, resolved on the GPU.
    Image(Resolve),
    /// The sums packed on the GPU in the farm's compact layout.
    Packed,
    /// An adaptive round: only the blocks of the mask, each pixel's sums
    /// and sums of squares (a [`Film::with_squares`]).
    Adaptive(&'a BlockMask),
    /// A whole adaptive render, its rounds chained on the GPU
    /// (`converge.rs`): the film with sums of squares, each block at the
    /// samples it stopped at.
    Resident(&'a converge::Resident<'a>),
    /// Blocks each over their own range of samples, in one grid: the
    /// blocks of the mask, block i (of the mask's rect) from `ranges[i].0`
    /// to `ranges[i].1`.
    Ranged(&'a BlockMask, &'a [Option<SampleRange>]),
    /// A whole error-optimal render (`converge.rs`): every block over its
    /// own range a round, the film kept on the GPU and each round decided
    /// there (allocate.wgsl), as `rounds`' schedule decides on the host.
    Rmse(&'a converge::RmseResident<'a>),
}

/// The resolve pipelines and their buffers, made on first use (farm
/// workers never resolve).
struct Resolver {
    /// resolve.wgsl and resolve_linear.wgsl: both kernels, one binding layout.
    module: wgpu::ShaderModule,
    pipeline_layout: wgpu::PipelineLayout,
    layout: wgpu::BindGroupLayout,
    srgb8: Option<wgpu::ComputePipeline>,
    linear: Option<wgpu::ComputePipeline>,
    params: wgpu::Buffer,
    thresholds: wgpu::Buffer,
    /// The sample count whose thresholds `thresholds` holds.
    samples: Option<u32>,
    /// Capacity of `image` and `image_read`.
    image_bytes: u64,
    image: wgpu::Buffer,
    image_read: wgpu::Buffer,
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
    packer: Mutex<Option<pack::Packer>>,
    converger: Mutex<Option<converge::Converger>>,
    /// Scene kernels compiled so far ([`GpuRenderer::pipelines_built`]).
    pipelines_built: std::sync::atomic::AtomicU64,
    /// Texels packed on the host and uploaded ([`GpuRenderer::texel_work`]).
    texel_packs: std::sync::atomic::AtomicU64,
    texel_uploads: std::sync::atomic::AtomicU64,
    /// Distributed words uploaded ([`GpuRenderer::dist_uploads`]).
    dist_uploads: std::sync::atomic::AtomicU64,
    /// Trees written to the device ([`GpuRenderer::tree_uploads`]).
    tree_uploads: std::sync::atomic::AtomicU64,
    /// Compiled pipelines on disk, where the device has a pipeline cache.
    disk_cache: Option<disk_cache::DiskCache>,
    stats: Mutex<GpuStats>,
    /// Bound at binding 13 (an adaptive round's active blocks) by every
    /// render that is not one: made once, not per render.
    no_blocks: wgpu::Buffer,
    /// `block_rays` where the grid has none: a buffer of its own, as it is
    /// written where `no_blocks` is read.
    no_rays: wgpu::Buffer,
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

        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tessera scene"),
            entries: &layout_entries(&wgsl::SCENE),
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("tessera"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let wave_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tessera wavefront queues"),
            entries: &layout_entries(&wgsl::WAVE_QUEUES),
        });
        let wave_args_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tessera wavefront args"),
            entries: &layout_entries(&wgsl::WAVE_ARGS),
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
        let no_blocks = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("no active blocks"),
            size: 16,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
        });
        let no_rays = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("no block rays"),
            size: 16,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
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
            packer: Mutex::new(None),
            converger: Mutex::new(None),
            pipelines_built: Default::default(),
            texel_packs: Default::default(),
            texel_uploads: Default::default(),
            dist_uploads: Default::default(),
            tree_uploads: Default::default(),
            disk_cache,
            stats: Mutex::new(GpuStats::default()),
            no_blocks,
            no_rays,
        })
    }

    /// An unmapped buffer (every output, queue and read-back buffer).
    /// How many scene kernels this renderer has compiled: one per kind of
    /// scene, not per frame of an animation.
    pub fn pipelines_built(&self) -> u64 {
        self.pipelines_built
            .load(std::sync::atomic::Ordering::Relaxed)
    }

    /// How many times this renderer has packed model textures' texels on
    /// the host and uploaded them, in that order: once per world's set of
    /// images, not per tile or frame (`layout::TexelPack`).
    pub fn texel_work(&self) -> (u64, u64) {
        use std::sync::atomic::Ordering::Relaxed;
        (
            self.texel_packs.load(Relaxed),
            self.texel_uploads.load(Relaxed),
        )
    }

    /// How many times this renderer has uploaded a scene's distributed
    /// words (lights, materials and an environment image of the path
    /// integrator): once per world, not per tile.
    pub fn dist_uploads(&self) -> u64 {
        self.dist_uploads.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// How many times this renderer has written a scene's trees (BVH
    /// nodes, triangles and their shading) to the device: once per world,
    /// not per tile.
    pub fn tree_uploads(&self) -> u64 {
        self.tree_uploads.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// A post-processing kernel's bind group layout (`bindings`), its
    /// pipeline layout and its module: the GPU resolve and the GPU packing
    /// share this shape.
    fn compute_kernel(
        &self,
        label: &str,
        bindings: &wgsl::Layout,
        module: wgsl::Module,
    ) -> (
        wgpu::BindGroupLayout,
        wgpu::PipelineLayout,
        wgpu::ShaderModule,
    ) {
        let entries = layout_entries(bindings);
        let layout = self
            .device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(label),
                entries: &entries,
            });
        let pipeline_layout = self
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(label),
                source: wgpu::ShaderSource::Wgsl(module.text.into()),
            });
        (layout, pipeline_layout, module)
    }

    /// Dispatches `groups` workgroups of a post-processing kernel, in rows
    /// of at most the per-dimension limit (an 8K film has more); the
    /// kernels index them as `id.x + id.y * num_workgroups.x * 64`.
    fn dispatch_groups(&self, pass: &mut wgpu::ComputePass<'_>, groups: u32) {
        let x = groups.min(self.device.limits().max_compute_workgroups_per_dimension);
        pass.dispatch_workgroups(x, groups.div_ceil(x), 1);
    }

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

    /// Renders `region`'s sums, like [`super::CpuRenderer::render`].
    /// `progress` gets the pixel-samples of each finished submission.
    pub fn render(
        &self,
        prepared: &PreparedFrame,
        region: WorkRegion,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<Film, GpuError> {
        self.render_film(prepared, region, progress, Readout::Sums)
    }

    /// Renders `region` as `output` asks, made on the GPU: the sums; the
    /// image resolved (and sRGB-encoded) on the device, read back at 3 or
    /// 12 bytes a pixel instead of 24 (a local render to PNG or EXR); or
    /// the sums packed on the device into the farm's compact layout
    /// (`Rendered::Packed`: 15 bytes a pixel at 64 samples, no packing on
    /// the host). Each is exactly what the host makes of [`Self::render`]'s
    /// film (`Film::srgb8`, `Film::resolve`, the wire's `pack`).
    pub fn render_as(
        &self,
        prepared: &PreparedFrame,
        region: WorkRegion,
        output: Output,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<Rendered, GpuError> {
        let readout = match output {
            Output::Sums => Readout::Sums,
            Output::Srgb8 => Readout::Image(Resolve::Srgb8),
            Output::Linear => Readout::Image(Resolve::Linear),
            Output::FarmResult => Readout::Packed,
        };
        self.render_readout(prepared, region, progress, readout)
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
        self.render_film(
            prepared,
            WorkRegion::new(frame, mask.rect, samples),
            progress,
            Readout::Adaptive(mask),
        )
    }

    /// A whole adaptive render (see [`crate::adaptive`]) with its rounds
    /// chained on the GPU: after each round a kernel tests every active
    /// block against the target and retires the converged ones, and the
    /// next round is queued at once. `on_round` is told after each round,
    /// one round behind the GPU; `progress` gets pixel-samples. `prepared`
    /// must have been built with [`AdaptiveSettings::render_settings`].
    /// Each block's pixels equal [`GpuRenderer::render`]'s at the samples
    /// the block stopped at.
    pub fn render_adaptive(
        &self,
        prepared: &PreparedFrame,
        frame: u32,
        settings: &crate::adaptive::AdaptiveSettings,
        progress: &(dyn Fn(u64) + Sync),
        on_round: &dyn Fn(&super::adaptive::RoundReport),
    ) -> Result<Film, GpuError> {
        let s = prepared.settings();
        let rect = Rect::full(s.width, s.height);
        let resident = converge::Resident {
            settings,
            mask: BlockMask::all(rect),
            on_round,
        };
        let samples = SampleRange::new(0, settings.max_samples);
        self.render_film(
            prepared,
            WorkRegion::new(frame, rect, samples),
            progress,
            Readout::Resident(&resident),
        )
    }

    /// A whole frame in the error-optimal mode
    /// (`render::adaptive::render_rmse`), its rounds chained on the GPU:
    /// the film stays there, allocate.wgsl takes `rounds`' decisions
    /// between rounds, and only a log a round comes back, for `rounds`'
    /// reports (`converge.rs` `run_rmse_rounds`). Each block's pixels equal
    /// [`GpuRenderer::render`]'s at the samples the block stopped at.
    pub fn render_rmse(
        &self,
        prepared: &PreparedFrame,
        frame: u32,
        rounds: super::adaptive::RmseRounds<'_>,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<Film, GpuError> {
        let s = prepared.settings();
        let rect = Rect::full(s.width, s.height);
        let resident = converge::RmseResident {
            mask: BlockMask::all(rect),
            rounds: std::cell::RefCell::new(rounds),
        };
        let longest = resident
            .rounds
            .borrow()
            .pending()
            .map_or(0, |(_, to)| to.iter().copied().max().unwrap_or(0));
        if longest == 0 {
            return Ok(Film::with_squares(rect));
        }
        self.render_film(
            prepared,
            WorkRegion::new(frame, rect, SampleRange::new(0, longest)),
            progress,
            Readout::Rmse(&resident),
        )
    }

    /// Each block `i` of `rect` (block-aligned) over its own sample indices
    /// `from[i]..to[i]`, all in one grid: into a film of `rect` with sums of
    /// squares, each pixel of block `i` at `to[i] - from[i]` samples. Sums
    /// equal [`GpuRenderer::render`]'s over the same pixels and samples.
    pub fn render_blocks(
        &self,
        prepared: &PreparedFrame,
        frame: u32,
        rect: Rect,
        from: &[u32],
        to: &[u32],
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<Film, GpuError> {
        let ranges = prepared.block_ranges(rect, from, to)?;
        let mask = BlockMask {
            rect,
            active: ranges.iter().map(Option::is_some).collect(),
        };
        let longest = ranges.iter().flatten().map(|r| r.len()).max().unwrap_or(0);
        if longest == 0 {
            return Ok(Film::with_squares(rect));
        }
        self.render_film(
            prepared,
            WorkRegion::new(frame, rect, SampleRange::new(0, longest)),
            progress,
            Readout::Ranged(&mask, &ranges),
        )
    }

    /// [`GpuRenderer::render_readout`] of a readout that comes back as
    /// sums: the film.
    fn render_film(
        &self,
        prepared: &PreparedFrame,
        region: WorkRegion,
        progress: &(dyn Fn(u64) + Sync),
        readout: Readout<'_>,
    ) -> Result<Film, GpuError> {
        match self.render_readout(prepared, region, progress, readout)? {
            Rendered::Film(f) => Ok(f),
            _ => unreachable!("asked for sums"),
        }
    }

    fn render_readout(
        &self,
        prepared: &PreparedFrame,
        region: WorkRegion,
        progress: &(dyn Fn(u64) + Sync),
        readout: Readout<'_>,
    ) -> Result<Rendered, GpuError> {
        let WorkRegion {
            frame,
            rect,
            samples,
        } = region;
        prepared.check_request(rect, samples)?;
        let world = match prepared {
            PreparedFrame::F32(w) => w,
            PreparedFrame::F64(_) => return Err(GpuError::F64Unsupported),
        };
        if let Some(what) = cpu_only_materials(world) {
            return Err(GpuError::Materials(what));
        }
        self.check_fault()?;
        let start = Instant::now();
        // Tiles of one frame reuse the packed tree (packing a million
        // triangles costs more than tracing them) and the packed texels.
        let (packed, texels) = self
            .scene
            .lock()
            .ok()
            .and_then(|s| {
                s.as_ref().map(|s| {
                    (
                        s.data.tree.clone(),
                        s.data.pbr.as_ref().map(|p| p.texels.clone()),
                    )
                })
            })
            .unwrap_or_default();
        // The textures' mip levels, each image's on its own thread (the
        // texel pack reads them).
        world.make_texture_levels();
        let data = SceneData::from_world(world, packed.as_ref(), texels.as_ref())?;
        if let Some(p) = &data.pbr
            && !texels.is_some_and(|t| std::sync::Arc::ptr_eq(&t, &p.texels))
        {
            self.texel_packs
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }

        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        // The wavefront's queues hold a bounded number of tasks; if a
        // generation overflows them, render again in smaller dispatches.
        let mut budget = self.options.dispatch_pixel_samples;
        let mut retries = 0;
        let result = loop {
            match self.render_inner(
                data.clone(),
                world,
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
}

/// The bind group layout entries of `layout` (declared once, in wgsl.rs).
fn layout_entries(layout: &wgsl::Layout) -> Vec<wgpu::BindGroupLayoutEntry> {
    use wgpu::BufferBindingType as B;
    use wgsl::Access;
    (0u32..)
        .zip(layout.bindings)
        .map(|(binding, b)| {
            let (ty, has_dynamic_offset) = match b.access {
                Access::Uniform => (B::Uniform, false),
                Access::UniformDynamic => (B::Uniform, true),
                Access::Read => (B::Storage { read_only: true }, false),
                Access::ReadWrite => (B::Storage { read_only: false }, false),
            };
            wgpu::BindGroupLayoutEntry {
                binding,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty,
                    has_dynamic_offset,
                    min_binding_size: None,
                },
                count: None,
            }
        })
        .collect()
}

fn entire(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

/// The first `bytes` of `buffer` at `binding` (buffers are reused at their
/// largest size; a binding sees only what this render uses).
fn sized(binding: u32, buffer: &wgpu::Buffer, bytes: u64) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer,
            offset: 0,
            size: wgpu::BufferSize::new(bytes),
        }),
    }
}

fn check_size(
    what: &'static str,
    needed: u64,
    limit: u64,
    limit_name: &'static str,
    advice: &'static str,
) -> Result<(), GpuError> {
    if needed > limit {
        Err(GpuError::TooLarge {
            what,
            needed,
            limit,
            limit_name,
            advice,
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

/// What of a world's model-file materials the WGSL step does not have yet,
/// named for the error; `None` when it renders as on the CPU. Textures,
/// vertex colours, emission and cut-outs of the static world are
/// pbr.wgsl's, under both integrators (path.wgsl `bsdf_at`); a moving
/// mesh's model materials keep only their factors on the GPU, so those
/// that vary, emit or cut out (a single-sided one cuts its back faces
/// away) are refused.
fn cpu_only_materials(world: &crate::world::World<f32>) -> Option<String> {
    let moving = world
        .dist
        .iter()
        .flat_map(|d| d.moving_meshes.iter())
        .flat_map(|m| m.world.pbr.iter())
        .any(|p| {
            p.varies()
                || p.emissive.iter().any(|&e| e != 0.0)
                || p.alpha_mode == crate::material::AlphaMode::Mask
                || p.culls_back_faces()
        });
    moving.then(|| {
        "textures, vertex colours, emission, cut-outs or single-sided surfaces (glTF doubleSided false) on a moving mesh (distributed effects)"
            .to_string()
    })
}

/// Default bytes of texels a scene may hold on the GPU (`GpuRenderer`'s
/// texture budget, also bounded by the adapter's largest storage binding):
/// 1 GiB, e.g. 64 textures of 2048x2048.
pub const TEXTURE_BUDGET: u64 = 1 << 30;
