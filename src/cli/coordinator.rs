//! `tessera coordinator`: serve the farm.

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Args;
use tessera_coordinator::assets::AssetLimits;
use tessera_coordinator::server::Security;
use tessera_coordinator::{Config, Farm};

use super::farm_common::{LogFormat, WORKER_TOKEN_ENV, init_logging, read_token, runtime};

#[derive(Args, Debug)]
pub struct CoordinatorArgs {
    /// Address to listen on (port 0 picks a free port; the address is printed on stdout)
    #[arg(long, default_value = "127.0.0.1:7878")]
    pub listen: String,
    /// Serve the web monitor on this address (e.g. 127.0.0.1:7880; off when
    /// not given; port 0 picks a free port, printed on stdout). It takes the
    /// client token, as the job service does (docs/monitor.md)
    #[arg(long, value_name = "ADDR")]
    pub http: Option<String>,
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
    /// Serve TLS with this certificate chain (PEM; `tessera cert` makes one)
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// File holding the client token, needed to submit, list, watch, cancel
    /// and fetch [default: the environment variable TESSERA_CLIENT_TOKEN; none: open]
    #[arg(long, value_name = "FILE")]
    pub client_token_file: Option<PathBuf>,
    /// File holding the worker token, needed to register, lease, send
    /// results and fetch assets [default: the environment variable
    /// TESSERA_WORKER_TOKEN; none: open]
    #[arg(long, value_name = "FILE")]
    pub worker_token_file: Option<PathBuf>,
    /// Listen on a non-loopback address without tokens (a trusted network only)
    #[arg(long)]
    pub insecure: bool,
    /// Largest frame a job may have, in pixels (width x height): the
    /// coordinator holds 28 bytes a pixel of a frame while it fills
    #[arg(long, default_value_t = 40_000_000)]
    pub max_frame_pixels: u64,
    /// Largest scene file or model a client may upload, in bytes
    #[arg(long, default_value_t = 2 << 30)]
    pub max_asset_bytes: u64,
    /// Largest sum of one job's files, in bytes
    #[arg(long, default_value_t = 4 << 30)]
    pub max_job_bytes: u64,
    /// Largest sum of all stored files, in bytes
    #[arg(long, default_value_t = 64 << 30)]
    pub max_store_bytes: u64,
    /// Seconds a stored file is kept once no unfinished job uses it (a
    /// re-submit within that time uploads nothing)
    #[arg(long, default_value_t = 86400.0)]
    pub asset_retention: f64,
}

/// Environment variables of the coordinator's tokens.
pub const COORDINATOR_CLIENT_TOKEN_ENV: &str = "TESSERA_CLIENT_TOKEN";

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
    config.max_frame_pixels = args.max_frame_pixels;
    config.asset_limits = AssetLimits {
        max_asset_bytes: args.max_asset_bytes,
        max_job_bytes: args.max_job_bytes,
        max_store_bytes: args.max_store_bytes,
        retention: Duration::try_from_secs_f64(args.asset_retention).with_context(|| {
            format!(
                "--asset-retention must be a number of seconds >= 0, got {}",
                args.asset_retention
            )
        })?,
    };
    let read = |p: &Option<PathBuf>, flag: &str| {
        p.as_ref()
            .map(|p| {
                std::fs::read(p).with_context(|| format!("cannot read {flag} {}", p.display()))
            })
            .transpose()
    };
    let security = Security {
        tls: match (
            read(&args.tls_cert, "--tls-cert")?,
            read(&args.tls_key, "--tls-key")?,
        ) {
            (Some(c), Some(k)) => Some((c, k)),
            _ => None,
        },
        client_token: read_token(
            args.client_token_file.as_deref(),
            "--client-token-file",
            COORDINATOR_CLIENT_TOKEN_ENV,
        )?,
        worker_token: read_token(
            args.worker_token_file.as_deref(),
            "--worker-token-file",
            WORKER_TOKEN_ENV,
        )?,
    };
    runtime()?.block_on(async move {
        let listener = tokio::net::TcpListener::bind(&args.listen)
            .await
            .with_context(|| format!("cannot listen on {}", args.listen))?;
        let addr = listener.local_addr()?;
        let tokens = security.client_token.is_some() && security.worker_token.is_some();
        if !addr.ip().is_loopback() {
            if !tokens && !args.insecure {
                let missing = match (&security.client_token, &security.worker_token) {
                    (Some(_), None) => "a worker token",
                    (None, Some(_)) => "a client token",
                    _ => "tokens",
                };
                anyhow::bail!(
                    "refusing to listen on {addr} without {missing}: anyone who reaches it could submit and cancel jobs, \
                     read every scene and frame, and register as a worker. Give --client-token-file and \
                     --worker-token-file (or TESSERA_CLIENT_TOKEN and TESSERA_WORKER_TOKEN), or pass --insecure \
                     on a network you trust"
                );
            }
            if tokens && security.tls.is_none() {
                tracing::warn!(%addr, "tokens without TLS travel in clear text: give --tls-cert and --tls-key");
            }
        }
        let http = match &args.http {
            Some(a) => {
                let l = tokio::net::TcpListener::bind(a)
                    .await
                    .with_context(|| format!("cannot listen on {a} (--http)"))?;
                let http_addr = l.local_addr()?;
                if !http_addr.ip().is_loopback() && security.client_token.is_none() && !args.insecure {
                    anyhow::bail!(
                        "refusing to serve the monitor on {http_addr} without a client token: anyone who reaches it \
                         could see every job and frame and cancel jobs. Give --client-token-file (or \
                         TESSERA_CLIENT_TOKEN), or pass --insecure on a network you trust"
                    );
                }
                // The monitor is plain HTTP: a browser sends the client
                // token with every request, readable on the way.
                if !http_addr.ip().is_loopback() && security.client_token.is_some() {
                    tracing::warn!(
                        addr = %http_addr,
                        "the web monitor is plain HTTP: a browser sends the client token in clear text; \
                         serve it on 127.0.0.1 and reach it through an SSH tunnel or a TLS proxy"
                    );
                }
                Some(l)
            }
            None => None,
        };
        let farm = match Farm::open(config) {
            Ok(farm) => farm,
            Err(tessera_coordinator::FarmError::Store(
                tessera_coordinator::store::StoreError::InUse(_),
            )) => anyhow::bail!(
                "the data folder {} is in use by another coordinator (its database is locked): \
                 stop that one, or give this one a folder of its own with --data DIR",
                args.data.display()
            ),
            Err(e) => {
                return Err(e).with_context(|| {
                    format!(
                        "cannot open the coordinator state in {}",
                        args.data.display()
                    )
                });
            }
        };
        tracing::info!(
            %addr, data = %args.data.display(), tls = security.tls.is_some(),
            client_token = security.client_token.is_some(), worker_token = security.worker_token.is_some(),
            "coordinator listening"
        );
        // Scripts and tests read the bound address from stdout.
        println!("listening on {addr}");
        if let Some(l) = http {
            let http_addr = l.local_addr()?;
            tracing::info!(addr = %http_addr, "web monitor listening");
            // Only with --http: scripts reading just the first line are unaffected.
            println!("monitor on http://{http_addr}");
            let (farm, token) = (farm.clone(), security.client_token.clone());
            tokio::spawn(async move {
                if let Err(e) =
                    tessera_coordinator::monitor::serve(farm, l, token, shutdown_signal()).await
                {
                    tracing::error!(error = %e, "the web monitor stopped");
                }
            });
        }
        std::io::stdout().flush().ok();
        tessera_coordinator::server::serve(farm, listener, security, shutdown_signal()).await?;
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
