//! `tessera worker`: render work units for a coordinator.

use std::process::ExitCode;

use anyhow::Result;
use clap::{Args, ValueEnum};
use tessera_worker::{Backend, Worker, WorkerConfig};

use super::coordinator::shutdown_signal;
use super::farm_common::{CoordinatorUrl, LogFormat, init_logging, runtime};

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum WorkerBackend {
    /// CPU threads
    Cpu,
    /// One GPU through wgpu compute shaders (Vulkan/Metal/DX12; f32)
    Gpu,
}

#[derive(Args, Debug, Clone)]
pub struct WorkerArgs {
    #[command(flatten)]
    pub coordinator: CoordinatorUrl,
    /// Where to trace
    #[arg(long, value_enum, default_value_t = WorkerBackend::Cpu)]
    pub backend: WorkerBackend,
    /// CPU threads [default: all cores]
    #[arg(long)]
    pub threads: Option<usize>,
    /// GPU adapter for --backend gpu: index or part of the name as `tessera gpus` lists it [default: the best one]
    #[arg(long)]
    pub adapter: Option<String>,
    /// Name shown by `tessera workers` [default: host name and process id]
    #[arg(long)]
    pub name: Option<String>,
    /// Log format
    #[arg(long, value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,
}

pub fn run(args: WorkerArgs) -> Result<ExitCode> {
    init_logging(args.log_format);
    if args.backend != WorkerBackend::Gpu && args.adapter.is_some() {
        anyhow::bail!("--adapter only applies to --backend gpu");
    }
    let name = args.name.clone().unwrap_or_else(|| {
        let host = std::env::var("HOSTNAME")
            .ok()
            .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
            .unwrap_or_default();
        format!("{}-{}", host.trim(), std::process::id())
    });
    let worker = Worker::new(WorkerConfig {
        coordinator: args.coordinator.url.clone(),
        name,
        threads: args.threads,
        adapter: args.adapter.clone(),
        backend: match args.backend {
            WorkerBackend::Cpu => Backend::Cpu,
            WorkerBackend::Gpu => Backend::Gpu,
        },
    })?;
    runtime()?.block_on(async move {
        let (drain_tx, drain) = tokio::sync::watch::channel(false);
        let mut run = tokio::spawn(worker.run(drain));
        tokio::select! {
            r = &mut run => {
                r??;
                return Ok(ExitCode::SUCCESS);
            }
            _ = shutdown_signal() => {}
        }
        tracing::info!("draining: finishing the current unit (signal again to stop now)");
        let _ = drain_tx.send(true);
        tokio::select! {
            r = run => r??,
            _ = shutdown_signal() => tracing::warn!("stopped without finishing the current unit"),
        }
        Ok(ExitCode::SUCCESS)
    })
}
