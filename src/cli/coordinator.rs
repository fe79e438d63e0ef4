//! `tessera coordinator`: serve the farm.

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Args;
use tessera_coordinator::{Config, Farm};

use super::farm_common::{LogFormat, init_logging, runtime};

#[derive(Args, Debug)]
pub struct CoordinatorArgs {
    /// Address to listen on (port 0 picks a free port; the address is printed on stdout)
    #[arg(long, default_value = "127.0.0.1:7878")]
    pub listen: String,
    /// Directory for the database and the finished frames
    #[arg(long, default_value = "tessera-data")]
    pub data: PathBuf,
    /// Seconds without a heartbeat after which a lease expires and its unit is queued again
    #[arg(long, default_value_t = 10.0)]
    pub lease_timeout: f64,
    /// Seconds between worker heartbeats
    #[arg(long, default_value_t = 1.0)]
    pub heartbeat_interval: f64,
    /// Largest gRPC request accepted, in bytes
    #[arg(long, default_value_t = 64 << 20)]
    pub max_message_bytes: usize,
    /// Seconds between progress log lines
    #[arg(long, default_value_t = 2.0)]
    pub progress_interval: f64,
    /// Log format
    #[arg(long, value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,
}

fn secs(name: &str, v: f64) -> Result<Duration> {
    Duration::try_from_secs_f64(v)
        .ok()
        .filter(|d| !d.is_zero())
        .with_context(|| format!("--{name} must be a positive number of seconds, got {v}"))
}

pub fn run(args: CoordinatorArgs) -> Result<ExitCode> {
    init_logging(args.log_format);
    let mut config = Config::new(args.data.clone());
    config.lease_timeout = secs("lease-timeout", args.lease_timeout)?;
    config.heartbeat_interval = secs("heartbeat-interval", args.heartbeat_interval)?;
    config.progress_interval = secs("progress-interval", args.progress_interval)?;
    config.max_message_bytes = args.max_message_bytes;
    runtime()?.block_on(async move {
        let listener = tokio::net::TcpListener::bind(&args.listen)
            .await
            .with_context(|| format!("cannot listen on {}", args.listen))?;
        let addr = listener.local_addr()?;
        let farm = Farm::open(config).with_context(|| {
            format!(
                "cannot open the coordinator state in {}",
                args.data.display()
            )
        })?;
        tracing::info!(%addr, data = %args.data.display(), "coordinator listening");
        // Scripts and tests read the bound address from stdout.
        println!("listening on {addr}");
        std::io::stdout().flush().ok();
        tessera_coordinator::server::serve(farm, listener, shutdown_signal()).await?;
        tracing::info!("coordinator stopped");
        Ok(ExitCode::SUCCESS)
    })
}

/// Resolves on SIGINT or SIGTERM.
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}
