//! Command-line interface: one subcommand per module.

mod bench;
mod cluster;
mod coordinator;
mod farm_common;
#[cfg(feature = "gpu")]
mod gpus;
mod jobs;
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
    /// Follow a job until it ends; exit code 0 done, 3 failed, 4 cancelled.
    Watch(jobs::JobArg),
    /// Cancel a job; workers stop its work within a heartbeat.
    Cancel(jobs::JobArg),
    /// Download a job's finished frames.
    Fetch(jobs::FetchArgs),
    /// List the workers connected to the coordinator.
    Workers(jobs::ListArgs),
    /// Run a coordinator and N workers in this terminal.
    Cluster(cluster::ClusterArgs),
    /// List the GPU adapters `--backend gpu --adapter NAME|INDEX` can use.
    #[cfg(feature = "gpu")]
    Gpus,
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
        Command::Workers(args) => jobs::workers(args),
        Command::Cluster(args) => cluster::run(args),
        #[cfg(feature = "gpu")]
        Command::Gpus => gpus::run(),
    }
}
