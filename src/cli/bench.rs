//! `tessera bench`: speed against error.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::{Args, ValueEnum};

use crate::bench::{self, BackendKind, Config};

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum BenchBackend {
    Cpu,
}

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Suites to run [default: all]: resolution, samples, complexity, depth, precision
    pub suites: Vec<String>,
    /// Where to trace
    #[arg(long, value_enum, default_value_t = BenchBackend::Cpu)]
    pub backend: BenchBackend,
    /// Output directory: one CSV per suite, the images, and plots (PNG and SVG)
    #[arg(long, default_value = "bench-out")]
    pub out: PathBuf,
    /// Tiny images and few settings: a smoke test that finishes in seconds
    #[arg(long)]
    pub quick: bool,
    /// CPU threads [default: all cores]
    #[arg(long)]
    pub threads: Option<usize>,
    /// Cache of converged f64 reference images [default: $XDG_CACHE_HOME/tessera/references]
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Directory of the example scenes
    #[arg(long, default_value = "examples")]
    pub examples: PathBuf,
    /// Timed repetitions of each run; the fastest is reported
    #[arg(long, default_value_t = 1)]
    pub repeat: u32,
}

pub fn run(args: BenchArgs) -> Result<ExitCode> {
    let backends = match args.backend {
        BenchBackend::Cpu => vec![BackendKind::Cpu],
    };
    let runs = bench::run(Config {
        suites: args.suites,
        backends,
        out: args.out.clone(),
        quick: args.quick,
        threads: args.threads,
        cache: args.cache.unwrap_or_else(bench::reference_dir),
        examples: args.examples,
        repeat: args.repeat,
    })?;
    eprintln!("bench: {} runs written under {}", runs.len(), args.out.display());
    Ok(ExitCode::SUCCESS)
}
