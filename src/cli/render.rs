//! `tessera render`: local mode, one process, no set-up.

use super::outln;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;
use tracer_core::film::WorkRegion;

use anyhow::{Result, bail};
use clap::builder::TypedValueParser as _;
use clap::{Args, ValueEnum};
use tracer_core::adaptive::{AdaptiveMode, AdaptiveSettings, AdaptiveSpec};
use tracer_core::film::{Rect, SampleRange};
use tracer_core::render::adaptive;
use tracer_core::render::cpu::MAX_THREADS;
use tracer_core::render::{Backend, Precision, PreparedFrame, Renderer};
use tracer_core::sampling::Sampler;
use tracer_core::scene::{
    Integrator, MAX_DEPTH, MAX_IMAGE_SIDE, MAX_SAMPLES, ModelSceneOptions, RenderOverrides,
    RenderSettings, SceneDesc, SettingsError,
};

/// `--threads`: 0 (all cores) up to the renderer's limit, so help and
/// errors state the real range.
pub fn threads_parser() -> clap::builder::RangedI64ValueParser<usize> {
    clap::builder::RangedI64ValueParser::<usize>::new().range(0..=MAX_THREADS as i64)
}

/// Settings that override the scene file's `[render]` table, as flags:
/// the command line's edge of [`RenderOverrides`] (clap's attributes are
/// its own). Shared by every command that renders (render, submit).
#[derive(Args, Debug, Clone, Default)]
pub struct OverrideArgs {
    /// Image width in pixels, 1..=32768; overrides the scene's [render]
    /// width [default: the scene's, else 800]
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_IMAGE_SIDE)))]
    pub width: Option<u32>,
    /// Image height in pixels, 1..=32768; overrides the scene's [render]
    /// height [default: the scene's, else 600]
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_IMAGE_SIDE)))]
    pub height: Option<u32>,
    /// Samples per pixel, 1..=65536: a square number n*n places them on an
    /// n x n grid (each moved at random within its cell with --sampler
    /// jittered), any other number on low-discrepancy points [default: the scene's, else 4]
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_SAMPLES)))]
    pub samples: Option<u32>,
    /// Generations of secondary (reflected/refracted) rays, 0..=64; 0 =
    /// primary and shadow rays only [default: the scene's, else 10]
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(0..=i64::from(MAX_DEPTH)))]
    pub max_depth: Option<u32>,
    /// Sample placement inside a pixel for square sample counts: grid (cell
    /// centres) or jittered (random within each cell, seeded by pixel,
    /// sample and frame); progressive: low-discrepancy points for every
    /// count, sample k the same whatever the count (what --target-error
    /// uses) [default: the scene's, else grid]
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(["grid", "jittered", "progressive"]).map(|s| s.parse::<Sampler>().unwrap()))]
    pub sampler: Option<Sampler>,
    /// How light is integrated: whitted (the thesis's model with
    /// distributed ray tracing) or path (unidirectional path tracing; with
    /// it --max-depth counts path segments after the camera ray's,
    /// docs/path-tracing.md) [default: the scene's, else whitted]
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(["whitted", "path"]).map(|s| s.parse::<Integrator>().unwrap()))]
    pub integrator: Option<Integrator>,
}

impl From<&OverrideArgs> for RenderOverrides {
    fn from(a: &OverrideArgs) -> Self {
        RenderOverrides {
            width: a.width,
            height: a.height,
            samples: a.samples,
            max_depth: a.max_depth,
            sampler: a.sampler,
            integrator: a.integrator,
        }
    }
}

/// Adaptive sampling (docs/adaptive-sampling.md): samples per block of
/// 8x8 pixels until the error estimate meets a target. The flags of
/// [`AdaptiveSpec`].
#[derive(Args, Debug, Clone, Default)]
pub struct AdaptiveArgs {
    /// Adaptive sampling: stop sampling an 8x8 block once the estimated
    /// standard error of every pixel's mean, in every linear RGB channel,
    /// is at most E (e.g. 0.005); overrides the scene's [render] target_error
    #[arg(long, value_name = "E", allow_negative_numbers = true)]
    pub target_error: Option<f64>,
    /// Adaptive sampling with a relative target: a pixel is done once its
    /// standard error is at most R times the mean of its brightest channel
    /// (e.g. 0.02 for 2%), the same visible noise whatever the exposure.
    /// With --target-error too, a pixel's limit is the larger of the two
    /// (so dark noisy pixels stop at the absolute floor rather than at
    /// --max-samples); overrides the scene's [render] relative_error
    #[arg(long, value_name = "R", allow_negative_numbers = true)]
    pub relative_error: Option<f64>,
    /// Samples every pixel gets in the first round, at least 2 [default:
    /// the scene's [render] min_samples, else 16]
    #[arg(long, value_name = "N")]
    pub min_samples: Option<u32>,
    /// Most samples a pixel gets; each round doubles an unconverged
    /// block's samples up to this [default: the scene's [render]
    /// max_samples, else 1024]
    #[arg(long, value_name = "N")]
    pub max_samples: Option<u32>,
    /// Adaptive sampling: what the target bounds. `pixel`: every pixel's
    /// standard error. `image`: the image's estimated RMSE (--target-error
    /// as an RMSE, --relative-error as a share of the image's mean), with
    /// each 8x8 block's samples in proportion to its noise over the square
    /// root of its cost in rays, the cheapest way to that error
    /// (docs/adaptive-sampling.md) [default: the scene's [render]
    /// adaptive_mode, else pixel]
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(["pixel", "image"]).map(|s| s.parse::<AdaptiveMode>().unwrap()))]
    pub adaptive_mode: Option<AdaptiveMode>,
}

impl From<&AdaptiveArgs> for AdaptiveSpec {
    fn from(a: &AdaptiveArgs) -> Self {
        AdaptiveSpec {
            target_error: a.target_error,
            relative_error: a.relative_error,
            min_samples: a.min_samples,
            max_samples: a.max_samples,
            mode: a.adaptive_mode,
        }
    }
}

/// The settings a local render traces with (and its adaptive settings),
/// resolved and checked once by [`RenderOverrides::resolve`]; the errors
/// of the adaptive checks name the flags.
fn resolve(
    scene: &SceneDesc,
    overrides: &OverrideArgs,
    adaptive: &AdaptiveArgs,
) -> Result<(RenderSettings, Option<AdaptiveSettings>)> {
    RenderOverrides::from(overrides)
        .resolve(scene, &adaptive.into())
        .map_err(|e| match e {
            SettingsError::SamplesWithAdaptive => anyhow::anyhow!(
                "--samples does not apply to adaptive sampling (--target-error, --relative-error): use --min-samples and --max-samples"
            ),
            SettingsError::SamplerWithAdaptive(s) => anyhow::anyhow!(
                "--sampler {} does not apply to adaptive sampling (--target-error, --relative-error), which places samples progressively (sample k the same whatever the count)",
                s.name()
            ),
            e => e.into(),
        })
}

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum PrecisionArg {
    F32,
    F64,
}

impl From<PrecisionArg> for Precision {
    fn from(p: PrecisionArg) -> Self {
        match p {
            PrecisionArg::F32 => Precision::F32,
            PrecisionArg::F64 => Precision::F64,
        }
    }
}

/// `--backend` of `tessera render`, each value with its help. A build
/// without the `gpu` feature offers only `cpu`: clap refuses `gpu` there
/// and lists the one value it accepts.
fn backend_parser() -> impl clap::builder::TypedValueParser<Value = Backend> {
    use clap::builder::{PossibleValue, PossibleValuesParser};
    PossibleValuesParser::new([
        PossibleValue::new(Backend::Cpu.name()).help("CPU threads (rayon)"),
        #[cfg(feature = "gpu")]
        PossibleValue::new(Backend::Gpu.name())
            .help("GPU compute shaders (wgpu: Vulkan/Metal/DX12); f32 only"),
    ])
    .map(|s| s.parse::<Backend>().expect("one of the possible values"))
}

/// `--camera` of a model file given as the scene and `--environment`,
/// shared by render and submit.
#[derive(Args, Debug, Clone, Default)]
pub struct ModelArgs {
    /// For a model file given as the scene: the glTF camera to render
    /// through, by index in the file's cameras or by name; "auto" frames
    /// the model (docs/scene-format.md, "Model files as scenes") [default:
    /// the default scene's first camera, else auto]
    #[arg(long, value_name = "NAME|INDEX")]
    pub camera: Option<String>,
    /// An equirectangular environment image (EXR, HDR, PNG or JPEG) that
    /// lights the scene under --integrator path, in place of the scene's
    /// environment (`[world] environment`; docs/path-tracing.md,
    /// "Environment"). On the farm it travels with the job: keep it in
    /// the scene's folder, or pass --allow-outside
    #[arg(long, value_name = "FILE")]
    pub environment: Option<PathBuf>,
}

impl ModelArgs {
    /// The options of `scene` given as the scene, with the size flags
    /// (they decide the image's size before a camera's aspect ratio does).
    pub fn options(&self, scene: &Path, overrides: &OverrideArgs) -> ModelSceneOptions {
        ModelSceneOptions {
            camera: self.camera.clone(),
            width: overrides.width,
            height: overrides.height,
            environment: self
                .environment
                .as_deref()
                .map(|file| environment_name(scene, file)),
        }
    }
}

/// The name a scene at `scene` would give the file `file` (a path as
/// typed, relative to the working directory): relative to the scene's
/// folder where the file lies in it, else its absolute path.
fn environment_name(scene: &Path, file: &Path) -> String {
    let absolute = |p: &Path| std::fs::canonicalize(p).ok();
    let folder = scene.parent().filter(|f| !f.as_os_str().is_empty());
    let folder = absolute(folder.unwrap_or(Path::new(".")));
    let Some(path) = absolute(file) else {
        // Missing: the read fails and names it as typed.
        return std::path::absolute(file)
            .unwrap_or_else(|_| file.to_owned())
            .to_string_lossy()
            .into_owned();
    };
    match folder.as_deref().and_then(|f| path.strip_prefix(f).ok()) {
        Some(inside) => inside
            .components()
            .map(|c| c.as_os_str().to_string_lossy())
            .collect::<Vec<_>>()
            .join("/"),
        None => path.to_string_lossy().into_owned(),
    }
}

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Scene file (TOML; see docs/scene-format.md), or a model file
    /// rendered as a scene: .gltf, .glb, .obj, .obj.gz
    pub scene: PathBuf,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Output image: .png (8-bit sRGB) or .exr (linear float) [default: SCENE with .png]
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    #[command(flatten)]
    pub overrides: OverrideArgs,
    #[command(flatten)]
    pub adaptive: AdaptiveArgs,
    /// Adaptive renders: also write a heat map of samples per pixel (PNG,
    /// dark blue at --min-samples to yellow at --max-samples, log scale)
    #[arg(long, value_name = "FILE.png")]
    pub sample_map: Option<PathBuf>,
    /// CPU threads for --backend cpu, 0..=4096; 0 means all cores [default: all cores]
    #[arg(long, allow_negative_numbers = true, value_parser = threads_parser())]
    pub threads: Option<usize>,
    /// Arithmetic precision: f32 (fast) or f64 (reference)
    #[arg(long, value_enum, default_value_t = PrecisionArg::F32)]
    pub precision: PrecisionArg,
    /// Where to trace
    #[arg(long, value_parser = backend_parser(), default_value_t = Backend::Cpu)]
    pub backend: Backend,
    /// GPU adapter for --backend gpu: index or part of the name as `tessera gpus` lists it [default: the best one]
    #[cfg(feature = "gpu")]
    #[arg(long, value_name = "NAME|INDEX")]
    pub adapter: Option<String>,
    /// Frame number: picks the camera's pose from the scene's
    /// [[camera.keyframes]] (interpolated between them) and seeds the
    /// jittered sampler
    #[arg(long, default_value_t = 0)]
    pub frame: u32,
    #[command(flatten)]
    pub format: super::output::Format,
}

pub use tracer_core::film::image::{ImageFormat, write_image};

/// One line per adaptive round, for the log above the progress bar.
fn round_line(r: &adaptive::RoundReport) -> String {
    let s = &r.summary;
    format!(
        "round {} (samples {}..{}): {} blocks active, {:.1} s; {:.1}% converged, estimated RMS error {:.2e}, {:.0}% of expected samples done",
        r.round,
        r.samples.start,
        r.samples.end,
        r.active_blocks,
        r.seconds,
        100.0 * s.converged_share(),
        s.rms_error,
        100.0 * s.samples_done as f64 / s.samples_expected.max(1) as f64
    )
}

pub fn run(args: RenderArgs) -> Result<ExitCode> {
    let output = args
        .output
        .clone()
        .unwrap_or_else(|| args.scene.with_extension("png"));
    // Fail on a bad output name before spending time rendering.
    ImageFormat::of(&output)?;
    let load_start = Instant::now();
    let scene = SceneDesc::load_input(
        &args.scene,
        &args.model.options(&args.scene, &args.overrides),
    )?;
    for w in &scene.warnings {
        eprintln!("warning: {w}");
    }
    let (settings, adaptive) = resolve(&scene, &args.overrides, &args.adaptive)?;
    if let Some(env) = &scene.world.environment_map
        && settings.integrator == Integrator::Whitted
    {
        eprintln!(
            "warning: the environment image {} lights the path integrator only; this render is whitted (give --integrator path)",
            env.name
        );
    }
    if let Some(map) = &args.sample_map {
        if adaptive.is_none() {
            bail!("--sample-map applies to adaptive renders: give --target-error too");
        }
        if ImageFormat::of(map)? != ImageFormat::Png {
            bail!("--sample-map {}: the sample map is a PNG", map.display());
        }
    }
    let precision: Precision = args.precision.into();
    let load_seconds = load_start.elapsed().as_secs_f64();

    #[cfg(feature = "gpu")]
    if args.backend != Backend::Gpu && args.adapter.is_some() {
        bail!("--adapter only applies to --backend gpu");
    }
    if args.backend == Backend::Gpu && precision != Precision::F32 {
        bail!("--backend gpu renders in f32 only; use --precision f32 (f64 is the CPU reference)");
    }
    #[cfg(feature = "gpu")]
    let adapter = args.adapter.as_deref();
    #[cfg(not(feature = "gpu"))]
    let adapter = None;
    let open_start = Instant::now();
    let renderer = Renderer::open(args.backend, args.threads, adapter)?;
    let open_seconds = open_start.elapsed().as_secs_f64();
    let prepare_start = Instant::now();
    // The scene is not read again: its models are freed before the tree's build.
    let prepared = PreparedFrame::build_owned(scene, &settings, args.frame, precision)?;
    let setup = Setup {
        load_seconds,
        open_seconds,
        prepare_seconds: prepare_start.elapsed().as_secs_f64(),
        stats: prepared.stats(),
    };
    let total = settings.width as u64 * settings.height as u64 * settings.samples as u64;
    let progress = super::output::Progress::new("render", total, false);
    let start = Instant::now();
    let rect = Rect::full(settings.width, settings.height);
    let samples = SampleRange::all(settings.samples);
    let mut last_round = None;
    let mut image_round = None;
    // A uniform render asks for the image itself: the GPU resolves it on
    // the device and reads back only it, 8-bit for PNG, f32 for EXR (an
    // adaptive render's EXR also has per-pixel samples and errors, from the
    // sums); the CPU resolves its film.
    let Some(a) = adaptive.as_ref() else {
        use tracer_core::film::image::{write_exr, write_png};
        use tracer_core::render::{Output, Rendered};
        let inc = |n| progress.inc(n);
        let region = WorkRegion::new(args.frame, rect, samples);
        let never = std::sync::atomic::AtomicBool::new(false);
        let format = ImageFormat::of(&output)?;
        let out = match format {
            ImageFormat::Png => Output::Srgb8,
            ImageFormat::Exr => Output::Linear,
        };
        let image = renderer
            .render_as(&prepared, region, out, &inc, &never)?
            .expect("never cancelled");
        // The time is the render's, the file's writing left out (as below).
        let secs = start.elapsed().as_secs_f64();
        progress.finish();
        let (rays, nonfinite) = match image {
            Rendered::Srgb8(i) => {
                write_png(&output, rect.width, rect.height, &i.rgb)?;
                (i.rays, i.nonfinite)
            }
            Rendered::Linear(i) => {
                write_exr(&output, rect.width, rect.height, &i.rgb)?;
                (i.rays, i.nonfinite)
            }
            _ => unreachable!("asked for an image"),
        };
        let summary = Summary {
            secs,
            rays,
            nonfinite,
            pixel_samples: rect.area() as u64 * samples.len() as u64,
            image_round: None,
        };
        return report(
            &args, &settings, precision, &renderer, &output, &setup, summary, None, None,
        );
    };
    let film = if a.mode == AdaptiveMode::Image {
        adaptive::render_rmse(
            &renderer,
            &prepared,
            args.frame,
            &tracer_core::adaptive::optimal::RmseSettings::from(a),
            &|n| progress.inc(n),
            &mut |r| {
                progress.note(&format!(
                    "round {}: {} blocks active, {:.1} s; estimated image RMSE {:.2e} (target {:.2e})",
                    r.round, r.active_blocks, r.seconds, r.estimated_rmse, r.target_rmse
                ));
                progress.set_total(r.expected_pixel_samples);
                image_round = Some(*r);
            },
        )?
    } else {
        adaptive::render(
            &renderer,
            &prepared,
            args.frame,
            a,
            &|n| progress.inc(n),
            &mut |r| {
                progress.note(&round_line(r));
                progress.set_total(r.summary.samples_expected);
                last_round = Some(*r);
            },
        )?
    };
    let secs = start.elapsed().as_secs_f64();
    progress.finish();
    write_image(&output, &film)?;
    if let (Some(map), Some(a)) = (&args.sample_map, &adaptive) {
        tracer_core::film::image::write_sample_map(map, &film, a.min_samples, a.max_samples)?;
    }
    let summary = Summary {
        secs,
        rays: film.rays,
        nonfinite: film.nonfinite,
        pixel_samples: film.counts.iter().map(|&n| n as u64).sum(),
        image_round,
    };
    report(
        &args,
        &settings,
        precision,
        &renderer,
        &output,
        &setup,
        summary,
        adaptive.as_ref(),
        last_round,
    )
}

/// What the render cost before its first ray: reading the scene (model
/// files and textures decoded), opening the backend, building the frame
/// (placement and the BVH), and what the frame holds.
struct Setup {
    load_seconds: f64,
    open_seconds: f64,
    prepare_seconds: f64,
    stats: tracer_core::world::WorldStats,
}

/// What a finished render reports, whichever way its image came back.
struct Summary {
    secs: f64,
    rays: tracer_core::film::RayCounts,
    nonfinite: u64,
    pixel_samples: u64,
    /// The last round of an `--adaptive-mode image` render.
    image_round: Option<adaptive::RmseRound>,
}

/// Prints a finished render's summary (text or `--json`) and warnings.
#[allow(clippy::too_many_arguments)]
fn report(
    args: &RenderArgs,
    settings: &RenderSettings,
    precision: Precision,
    renderer: &Renderer,
    output: &std::path::Path,
    setup: &Setup,
    summary: Summary,
    adaptive: Option<&AdaptiveSettings>,
    last_round: Option<adaptive::RoundReport>,
) -> Result<ExitCode> {
    let Summary {
        secs,
        rays: r,
        nonfinite,
        pixel_samples,
        image_round,
    } = summary;
    let rect = Rect::full(settings.width, settings.height);
    if args.format.json {
        super::output::print_json(&serde_json::json!({
            "width": settings.width,
            "height": settings.height,
            "samples": settings.samples,
            "max_depth": settings.max_depth,
            "frame": args.frame,
            "precision": precision.name(),
            "renderer": renderer.describe(),
            "seconds": secs,
            "rays": {
                "primary": r.primary,
                "shadow": r.shadow,
                "reflection": r.reflection,
                "refraction": r.refraction,
            },
            "rays_per_second": r.total() as f64 / secs,
            "integrator": settings.integrator.name(),
            // One path per camera ray (the path integrator's figure).
            "paths_per_second": r.primary as f64 / secs,
            "nonfinite_samples": nonfinite,
            "output": output.display().to_string(),
            "load_seconds": setup.load_seconds,
            "open_seconds": setup.open_seconds,
            "prepare_seconds": setup.prepare_seconds,
            "tree_seconds": setup.stats.tree_build_time.as_secs_f64(),
            // The process's peak resident set so far (Linux; 0 elsewhere).
            "peak_rss_bytes": 1024 * super::output::rss_kib(std::process::id()).1,
            // The scene's buffers on the GPU (null on the CPU).
            "gpu_scene_bytes": renderer.device_scene_bytes(),
            "scene": {
                "spheres": setup.stats.spheres,
                "planes": setup.stats.planes,
                "triangles": setup.stats.triangles,
                "placed_triangles": setup.stats.placed_triangles,
                "instances": setup.stats.instances,
                "textures": setup.stats.textures,
                "texture_bytes": setup.stats.texture_bytes,
                "environment": setup.stats.environment.as_ref().map(|(name, w, h, bytes)| {
                    serde_json::json!({ "name": name, "width": w, "height": h, "bytes": bytes })
                }),
            },
            "adaptive": adaptive.map(|a| {
                // The keys both modes report, then each mode's own.
                let mut o = serde_json::json!({
                    "target_error": a.target_error,
                    "relative_error": a.relative_error,
                    "min_samples": a.min_samples,
                    "max_samples": a.max_samples,
                    "pixel_samples": pixel_samples,
                    "mean_samples": pixel_samples as f64 / rect.area() as f64,
                    "sample_map": args.sample_map.as_ref().map(|p| p.display().to_string()),
                });
                let own = if let Some(r) = image_round {
                    serde_json::json!({
                        "mode": "image",
                        "rounds": r.round + 1,
                        "estimated_rms_error": r.estimated_rmse,
                        "target_rms_error": r.target_rmse,
                    })
                } else {
                    let s = last_round.map(|r| r.summary).unwrap_or_default();
                    serde_json::json!({
                        "mode": "pixel",
                        "rounds": last_round.map_or(0, |r| r.round + 1),
                        "converged_share": s.converged_share(),
                        "capped_blocks": s.capped_blocks,
                        "estimated_rms_error": s.rms_error,
                    })
                };
                if let (Some(o), serde_json::Value::Object(own)) = (o.as_object_mut(), own) {
                    o.extend(own);
                }
                o
            }),
        }));
    } else {
        if let (Some(a), Some(r)) = (&adaptive, image_round) {
            outln!(
                "adaptive: image RMSE at most {:.2e} ({}..{} spp): mean {:.1} spp, estimated image RMSE {:.2e} after {} rounds",
                r.target_rmse,
                a.min_samples,
                a.max_samples,
                pixel_samples as f64 / rect.area() as f64,
                r.estimated_rmse,
                r.round + 1
            );
        } else if let Some(a) = &adaptive {
            let s = last_round.map(|r| r.summary).unwrap_or_default();
            outln!(
                "adaptive: {} ({}..{} spp): mean {:.1} spp, {:.1}% of blocks converged, estimated RMS error {:.2e}",
                a.describe_target(),
                a.min_samples,
                a.max_samples,
                pixel_samples as f64 / rect.area() as f64,
                100.0 * s.converged_share(),
                s.rms_error
            );
        }
        outln!(
            "{}x{} {} spp depth {} {} {}  {:.3} s  {} rays (primary {}, shadow {}, reflection {}, refraction {})  {:.1} Mrays/s  -> {}",
            settings.width,
            settings.height,
            settings.samples,
            settings.max_depth,
            precision.name(),
            renderer.describe(),
            secs,
            r.total(),
            r.primary,
            r.shadow,
            r.reflection,
            r.refraction,
            r.total() as f64 / secs / 1e6,
            output.display()
        );
        if settings.integrator == Integrator::Path {
            // One path per camera ray.
            outln!(
                "path: {:.3} Mpaths/s, {:.2} rays per path",
                r.primary as f64 / secs / 1e6,
                r.total() as f64 / r.primary.max(1) as f64
            );
        }
    }
    if nonfinite > 0 {
        // Sanitised to 0 before reaching the image; still a tracer bug worth reporting.
        tracing::warn!(samples = nonfinite, "non-finite samples were replaced");
        eprintln!("warning: {nonfinite} non-finite samples were replaced by 0");
    }
    Ok(ExitCode::SUCCESS)
}
