//! `tessera bench`: speed against error.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::builder::TypedValueParser as _;
use clap::{Args, ValueEnum};

use crate::bench::{self, Config};
use tracer_core::render::Backend;

/// `--backend` of `tessera bench`: one backend or both (a choice of which
/// to run, so not [`Backend`] itself). A build without the `gpu` feature
/// offers only `cpu`.
#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum BenchBackend {
    Cpu,
    #[cfg(feature = "gpu")]
    Gpu,
    /// CPU and GPU, side by side in every suite
    #[cfg(feature = "gpu")]
    Both,
}

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Suites to run [default: all but multi-gpu]: resolution, samples,
    /// complexity, depth, precision, distributed (issue 16's effects: time
    /// and error against samples), launch (GPU launch-shape sweep; skipped
    /// without a GPU backend), farm (1..N local worker processes on one
    /// frame), adaptive (uniform against adaptive sampling: RMSE against
    /// time, and the time adaptive takes to reach uniform 1024 spp's RMSE);
    /// and, run only when named, multi-gpu (1..N GPU workers, one per
    /// --gpu-adapters entry, alone and beside CPU workers, against N
    /// concurrent local GPU renders), and scale (the coordinator under
    /// --virtual-workers virtual workers: time to busy, leases and units
    /// per second, lease latency, CPU and RSS per worker, 10% vanishing)
    pub suites: Vec<String>,
    /// Where to trace
    #[arg(long, value_enum, default_value_t = BenchBackend::Cpu)]
    pub backend: BenchBackend,
    /// How light is integrated in the resolution, samples, complexity,
    /// depth, precision, distributed, adaptive and multi-gpu suites:
    /// whitted or path, on either backend (docs/path-tracing.md)
    #[arg(long, default_value = "whitted", value_parser = clap::builder::PossibleValuesParser::new(["whitted", "path"]).map(|s| s.parse::<tracer_core::scene::Integrator>().unwrap()))]
    pub integrator: tracer_core::scene::Integrator,
    /// Output directory: one CSV per suite, the images, and plots (PNG and SVG)
    #[arg(long, default_value = "bench-out")]
    pub out: PathBuf,
    /// Tiny images and few settings: a smoke test that finishes in seconds
    #[arg(long)]
    pub quick: bool,
    /// CPU threads of the CPU backend and the f64 references, 0..=4096; 0
    /// means all cores [default: all cores]
    #[arg(long, allow_negative_numbers = true, value_parser = super::render::threads_parser())]
    pub threads: Option<usize>,
    /// Cache of converged f64 reference images [default: $XDG_CACHE_HOME/tessera/references]
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Directory of the example scenes
    #[arg(long, default_value = "examples")]
    pub examples: PathBuf,
    /// Timed repetitions of each run, at least 1; the fastest is reported.
    /// The farm suite instead adds, with 1 in --workers, that many pairs of
    /// a local render and a 1-worker farm job timed side by side on one
    /// warm farm, and reports the median ratio
    #[arg(long, allow_negative_numbers = true, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    pub repeat: u32,
    /// GPU adapter (name substring or index from `tessera gpus`) for the GPU backend
    #[arg(long, value_name = "NAME|INDEX")]
    pub adapter: Option<String>,
    /// Farm suite: worker counts to run, e.g. 1,2,4,8 (one coordinator and
    /// N `tessera worker` processes on this machine each) [default: 1,2,4,8; with --quick 1,2]
    #[arg(long, value_name = "N,N,...", value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..))]
    pub workers: Option<Vec<u32>>,
    /// Farm suite: CPU threads of each worker (and of the local render it is compared with)
    #[arg(long, value_name = "N", default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..))]
    pub worker_threads: u32,
    /// Farm suite: also run N GPU workers (`tessera worker --backend gpu`,
    /// on --adapter) on a 64-spp frame: alone, against a local GPU render
    /// in this process and as a whole process, then beside
    /// --mixed-cpu-workers CPU workers
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub gpu_workers: u32,
    /// Farm suite: CPU workers (of --worker-threads each) beside the GPU
    /// workers in the mixed run; 0 skips it
    #[arg(long, value_name = "N", default_value_t = 7)]
    pub mixed_cpu_workers: u32,
    /// Depth suite: max_depth of the f64 reference each depth is compared
    /// with [default: 32; with --quick 12]. 24 is within RMSE 4e-6 of 32 on
    /// the emerald scene at 1/13 of the rays (docs/benchmarks.md)
    #[arg(long, value_name = "D", value_parser = clap::value_parser!(u32).range(1..=64))]
    pub depth_reference: Option<u32>,
    /// Adaptive suite: image size, WIDTHxHEIGHT [default: 320x240; with --quick 64x48]
    #[arg(long, value_name = "WxH", value_parser = parse_size, default_value = "320x240")]
    pub adaptive_size: (u32, u32),
    /// Adaptive suite: samples of its f64 reference (independent of the
    /// tested samples) [default: 4096; with --quick 256]
    #[arg(long, value_name = "N", default_value_t = 4096, value_parser = clap::value_parser!(u32).range(1..=32768))]
    pub adaptive_reference: u32,
    /// Adaptive suite: its scenes, resolution (the thesis's) and/or
    /// distributed (issue 16's effects) and/or quad (resolution-quad.toml: soft shadows)
    /// and/or gallery (showcase.toml: edges and reflections under point lights)
    #[arg(long, value_name = "SCENE,...", value_delimiter = ',', default_value = "resolution,distributed", value_parser = ["resolution", "distributed", "quad", "gallery"])]
    pub adaptive_scenes: Vec<String>,
    /// Path suite: image size, WIDTHxHEIGHT [default: 128x128; with --quick 32x32]
    #[arg(long, value_name = "WxH", value_parser = parse_size)]
    pub path_size: Option<(u32, u32)>,
    /// Path suite: the sample counts Tessera and Mitsuba each render once
    /// (the headline interpolates Tessera's runs to Mitsuba's RMSE at the
    /// largest) [default: 4,16,64,256; with --quick 4,16]
    #[arg(long, value_name = "N,N,...", value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub path_samples: Option<Vec<u32>>,
    /// Path suite: samples of its converged Tessera f64 reference
    /// [default: 2048; with --quick 256]
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub path_reference: Option<u32>,
    /// Multi-gpu suite: GPU adapters, one GPU worker on each (index or
    /// name from `tessera gpus`); an index may repeat: 0,0 runs two workers
    /// sharing one GPU [default: every adapter `tessera gpus` lists]
    #[arg(long, value_name = "A,A,...", value_delimiter = ',')]
    pub gpu_adapters: Vec<String>,
    /// Multi-gpu suite: GPU worker counts to run, each N on the first N
    /// --gpu-adapters [default: 1 to all of them]
    #[arg(long, value_name = "N,N,...", value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..))]
    pub gpu_counts: Option<Vec<u32>>,
    /// Multi-gpu suite: cores its mixed runs fill: beside N GPU workers,
    /// (C - N - 1) / --worker-threads CPU workers (a core feeds each GPU
    /// worker, one is the coordinator's); 0 skips the mixed runs [default: all cores]
    #[arg(long, value_name = "C")]
    pub mixed_cores: Option<u32>,
    /// Scale suite: virtual worker counts, one run each (each its own TLS
    /// connection and session with the worker token, against a real
    /// coordinator process) [default: 2000; --quick: 100]
    #[arg(long, value_name = "N,N,...", value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..=20000))]
    pub virtual_workers: Option<Vec<u32>>,
    /// Scale suite: seconds each run lasts from the submit (a tenth of the
    /// workers vanish at 60% of it)
    #[arg(long, default_value_t = 30.0, value_parser = clap::value_parser!(u32).range(10..=3600).map(f64::from))]
    pub scale_seconds: f64,
    /// Scale suite: milliseconds a virtual worker holds each unit before
    /// answering it (0: at once, the coordinator's ceiling)
    #[arg(long, default_value_t = 0)]
    pub virtual_unit_ms: u64,
    #[command(flatten)]
    pub format: super::output::Format,
}

/// `WIDTHxHEIGHT`, each 1..=32768.
fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once('x')
        .ok_or_else(|| format!("{s:?} is not WIDTHxHEIGHT (e.g. 320x240)"))?;
    let side = |v: &str| {
        v.parse::<u32>()
            .ok()
            .filter(|n| (1..=32768).contains(n))
            .ok_or_else(|| format!("{v:?} in {s:?} is not a side of 1..=32768 pixels"))
    };
    Ok((side(w)?, side(h)?))
}

pub fn run(args: BenchArgs) -> Result<ExitCode> {
    let backends = match args.backend {
        BenchBackend::Cpu => vec![Backend::Cpu],
        #[cfg(feature = "gpu")]
        BenchBackend::Gpu => vec![Backend::Gpu],
        #[cfg(feature = "gpu")]
        BenchBackend::Both => vec![Backend::Cpu, Backend::Gpu],
    };
    let runs = bench::run(Config {
        suites: args.suites,
        backends,
        integrator: args.integrator,
        out: args.out.clone(),
        quick: args.quick,
        threads: args.threads,
        cache: args.cache.unwrap_or_else(bench::reference_dir),
        examples: args.examples,
        repeat: args.repeat,
        adapter: args.adapter,
        workers: args
            .workers
            .map(|v| v.into_iter().map(|n| n as usize).collect()),
        worker_threads: args.worker_threads as usize,
        gpu_workers: args.gpu_workers as usize,
        mixed_cpu_workers: args.mixed_cpu_workers as usize,
        depth_reference: args.depth_reference.unwrap_or(if args.quick {
            12
        } else {
            bench::DEPTH_REFERENCE
        }),
        adaptive_size: args.adaptive_size,
        adaptive_reference: args.adaptive_reference,
        adaptive_scenes: args.adaptive_scenes,
        path_size: args
            .path_size
            .unwrap_or(if args.quick { (32, 32) } else { (128, 128) }),
        path_samples: args.path_samples.unwrap_or_else(|| {
            if args.quick {
                vec![4, 16]
            } else {
                vec![4, 16, 64, 256]
            }
        }),
        path_reference: args
            .path_reference
            .unwrap_or(if args.quick { 256 } else { 2048 }),
        gpu_adapters: args.gpu_adapters,
        gpu_counts: args
            .gpu_counts
            .map(|v| v.into_iter().map(|n| n as usize).collect()),
        mixed_cores: args.mixed_cores.map(|n| n as usize),
        virtual_workers: args.virtual_workers.map_or_else(
            || vec![if args.quick { 100 } else { 2000 }],
            |v| v.into_iter().map(|n| n as usize).collect(),
        ),
        scale_seconds: args.scale_seconds,
        virtual_unit_ms: args.virtual_unit_ms,
    })?;
    eprintln!(
        "bench: {} runs written under {}",
        runs.len(),
        args.out.display()
    );
    if args.format.json {
        super::output::print_json(&runs.iter().map(bench::run_json).collect());
    } else if !runs.is_empty() {
        bench::print_summary(&runs);
    }
    Ok(ExitCode::SUCCESS)
}
