//! Command-line interface: one subcommand per module.

mod bench;
mod bundle;
mod cert;
mod cluster;
mod coordinator;
mod farm_common;
#[cfg(feature = "gpu")]
mod gpus;
mod jobs;
pub(crate) mod output;
mod render;
mod worker;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// Tessera: a distributed ray-tracing render farm.
///
/// Render locally with `tessera render SCENE.toml`; scene files are
/// described in docs/scene-format.md.
#[derive(Parser, Debug)]
#[command(name = "tessera", version, about, long_about = None, propagate_version = true)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Render a scene in this process (no coordinator, no workers).
    Render(render::RenderArgs),
    /// Benchmark suites: speed and error against a converged reference, as CSV and plots.
    Bench(bench::BenchArgs),
    /// Run the farm's coordinator (the gRPC server that hands out work).
    Coordinator(coordinator::CoordinatorArgs),
    /// Run a worker that renders work units for a coordinator.
    Worker(worker::WorkerArgs),
    /// Submit a scene to the farm; prints the job id.
    Submit(jobs::SubmitArgs),
    /// List the farm's jobs.
    Jobs(jobs::ListArgs),
    /// Show one job in detail.
    Status(jobs::JobArg),
    /// Follow a job until it ends; exit code 0 done, 3 failed, 4 cancelled,
    /// 130 on Ctrl-C (which stops only the watch: the job goes on).
    Watch(jobs::JobArg),
    /// Cancel a job; workers stop its work within a heartbeat.
    Cancel(jobs::JobArg),
    /// Forget a finished job: its record, results and images on the coordinator.
    Delete(jobs::JobArg),
    /// Download a job's finished frames.
    Fetch(jobs::FetchArgs),
    /// List the workers connected to the coordinator.
    Workers(jobs::ListArgs),
    /// Run a coordinator and N workers in this terminal.
    Cluster(cluster::ClusterArgs),
    /// Make a CA and a coordinator certificate (and tokens) for a farm over TLS.
    Cert(cert::CertArgs),
    /// List the GPU adapters `--backend gpu --adapter NAME|INDEX` can use.
    #[cfg(feature = "gpu")]
    Gpus(output::Format),
}

#[cfg(feature = "gpu")]
pub use gpus::quiet_display_probe;

impl Command {
    /// Whether this command may open a GPU (and so load the Vulkan driver).
    #[cfg(feature = "gpu")]
    pub fn may_use_gpu(&self) -> bool {
        use tracer_core::render::Backend;
        match self {
            Command::Render(a) => a.backend == Backend::Gpu,
            Command::Bench(a) => {
                a.backend != bench::BenchBackend::Cpu
                    || a.gpu_workers > 0
                    || a.suites.iter().any(|s| s == "multi-gpu")
            }
            Command::Worker(a) => a.backend == Backend::Gpu,
            Command::Cluster(a) => a.backend == Backend::Gpu,
            Command::Gpus(_) => true,
            _ => false,
        }
    }
}

/// `println!` for a command's output. A closed pipe (`tessera jobs | head -1`)
/// ends the process quietly with status 141, as a process killed by
/// SIGPIPE ends (`ls | head`), instead of println!'s panic. SIGPIPE itself
/// stays ignored: the client's own sockets must see EPIPE as an error, not
/// die of it.
macro_rules! outln {
    ($($arg:tt)*) => { $crate::cli::out_line(format_args!($($arg)*)) };
}
pub(crate) use outln;

pub fn out_line(line: std::fmt::Arguments) {
    use std::io::Write as _;
    let mut out = std::io::stdout().lock();
    let written = out
        .write_fmt(line)
        .and_then(|()| out.write_all(b"\n"))
        .and_then(|()| out.flush());
    match written {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => std::process::exit(141),
        Err(e) => {
            eprintln!("error: cannot write to standard output: {e}");
            std::process::exit(1);
        }
    }
}

pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Render(args) => render::run(args),
        Command::Bench(args) => bench::run(args),
        Command::Coordinator(args) => coordinator::run(args),
        Command::Worker(args) => worker::run(args),
        Command::Submit(args) => jobs::submit(args),
        Command::Jobs(args) => jobs::jobs(args),
        Command::Status(args) => jobs::status(args),
        Command::Watch(args) => jobs::watch(args),
        Command::Cancel(args) => jobs::cancel(args),
        Command::Fetch(args) => jobs::fetch(args),
        Command::Delete(args) => jobs::delete(args),
        Command::Workers(args) => jobs::workers(args),
        Command::Cluster(args) => cluster::run(args),
        Command::Cert(args) => cert::run(args),
        #[cfg(feature = "gpu")]
        Command::Gpus(format) => gpus::run(format),
    }
}
