//! `tessera coordinator`: serve the farm.

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Args;
use tessera_coordinator::assets::AssetLimits;
use tessera_coordinator::edge::{EdgeLimits, raise_descriptor_limit};
use tessera_coordinator::monitor::MonitorConfig;
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
    /// File holding a token that opens only the monitor's /metrics (for a
    /// Prometheus server; the client token opens it too) [default: the
    /// environment variable TESSERA_METRICS_TOKEN]
    #[arg(long, value_name = "FILE", requires = "http")]
    pub metrics_token_file: Option<PathBuf>,
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
    /// Also answer the monitor under this name (a `Host` header, NAME or
    /// NAME:PORT; repeatable). The listen address, localhost, 127.0.0.1 and
    /// [::1] are always answered; other names are refused (DNS rebinding)
    #[arg(long, value_name = "NAME")]
    pub http_allow_host: Vec<String>,
    /// Most open connections a port (gRPC, monitor) [default: from the
    /// open-files limit: (limit - 256) / ports, at most 16384]; over it the
    /// connection idle the longest is closed
    #[arg(long, value_name = "N")]
    pub max_connections: Option<usize>,
    /// Most open connections from one IP address a port [default: a quarter
    /// of --max-connections, at least 32]
    #[arg(long, value_name = "N")]
    pub max_connections_per_peer: Option<usize>,
    /// Seconds a new connection has to send its first request (TLS
    /// handshake and HTTP/2 preface included)
    #[arg(long, default_value_t = 10.0)]
    pub handshake_timeout: f64,
    /// Seconds a connection may stay without a request in flight
    #[arg(long, default_value_t = 300.0)]
    pub idle_timeout: f64,
    /// Seconds an asset upload may go without sending a chunk
    #[arg(long, default_value_t = 30.0)]
    pub upload_idle_timeout: f64,
    /// Most asset uploads at once
    #[arg(long, default_value_t = 64)]
    pub max_uploads: u32,
    /// Most asset uploads at once on one connection
    #[arg(long, default_value_t = 4)]
    pub max_uploads_per_connection: u32,
    /// Seconds between looks for files to collect (tests make it short)
    #[arg(long, default_value_t = 60.0, hide = true)]
    pub asset_collect_interval: f64,
    /// Malformed results in a row after which a worker is quarantined:
    /// its leases go to others and it gets none for --quarantine-seconds
    #[arg(long, default_value_t = 5)]
    pub quarantine_after: u32,
    /// Seconds a quarantined worker gets no lease
    #[arg(long, default_value_t = 60.0)]
    pub quarantine_seconds: f64,
    /// Units of one job a worker may report failed before it is kept
    /// from that job (its blocklist, shown by `tessera status`); 0: never
    #[arg(long, default_value_t = 3)]
    pub blocklist_after: u32,
    /// Seconds a blocklisted worker is kept from the job (then forgiven)
    #[arg(long, default_value_t = 1800.0)]
    pub blocklist_seconds: f64,
    /// POST every job's JSON (as `tessera status JOB --json` prints it) to
    /// this http:// URL when the job ends (done, failed, cancelled),
    /// signed and retried; repeatable. Needs --notify-secret-file
    #[arg(long, value_name = "URL")]
    pub notify: Vec<String>,
    /// File holding the secret (at least 16 bytes; surrounding whitespace
    /// dropped) job-end notifications are signed with: the header
    /// `X-Tessera-Signature: sha256=HEX` is the HMAC-SHA256 of the body
    /// under it. Needed for --notify and for jobs' `submit --on-done`
    #[arg(long, value_name = "PATH")]
    pub notify_secret_file: Option<PathBuf>,
}

/// Environment variables of the coordinator's tokens.
pub const COORDINATOR_CLIENT_TOKEN_ENV: &str = "TESSERA_CLIENT_TOKEN";
/// Environment variable of the scrape-only `/metrics` token.
pub const METRICS_TOKEN_ENV: &str = "TESSERA_METRICS_TOKEN";

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
    config.collect_interval = secs("asset-collect-interval", args.asset_collect_interval)?;
    config.quarantine_for = secs("quarantine-seconds", args.quarantine_seconds)?;
    anyhow::ensure!(
        args.quarantine_after >= 1,
        "--quarantine-after must be at least 1, got 0"
    );
    config.quarantine_after = args.quarantine_after;
    config.blocklist_after = args.blocklist_after;
    config.blocklist_for = secs("blocklist-seconds", args.blocklist_seconds)?;
    config.notify = args.notify.clone();
    if let Some(path) = &args.notify_secret_file {
        let bytes = std::fs::read(path)
            .with_context(|| format!("--notify-secret-file {}", path.display()))?;
        config.notify_secret = Some(bytes.trim_ascii().to_vec());
    }
    anyhow::ensure!(
        config.notify.is_empty() || config.notify_secret.is_some(),
        "--notify needs --notify-secret-file: notifications are always signed (docs/operations.md, \"Notifications\")"
    );
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
        upload_idle_timeout: secs("upload-idle-timeout", args.upload_idle_timeout)?,
        max_uploads: args.max_uploads.max(1),
        max_uploads_per_connection: args.max_uploads_per_connection.max(1),
    };
    // Idle sockets must never take the descriptors the store needs, and a
    // low soft limit (1024 is common) should not cap a farm the hard limit
    // allows.
    let nofile = match raise_descriptor_limit() {
        Ok(n) => {
            tracing::info!(
                open_files = n,
                "open-files limit (RLIMIT_NOFILE, soft raised to hard)"
            );
            n
        }
        Err(e) => {
            tracing::warn!(error = %e, "cannot read or raise the open-files limit; assuming 1024");
            1024
        }
    };
    let ports = if args.http.is_some() { 2 } else { 1 };
    let mut edge = EdgeLimits::for_descriptors(nofile, ports);
    if let Some(n) = args.max_connections {
        edge.max_connections = n.max(1);
        edge.max_per_peer = (n / 4).max(32).min(n.max(1));
    }
    if let Some(n) = args.max_connections_per_peer {
        edge.max_per_peer = n.max(1);
    }
    edge.handshake_timeout = secs("handshake-timeout", args.handshake_timeout)?;
    edge.idle_timeout = secs("idle-timeout", args.idle_timeout)?;
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
        edge,
    };
    check_tokens(
        security.client_token.as_deref(),
        security.worker_token.as_deref(),
    )?;
    let metrics_token = read_token(
        args.metrics_token_file.as_deref(),
        "--metrics-token-file",
        METRICS_TOKEN_ENV,
    )?;
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
            let monitor = MonitorConfig {
                client_token: security.client_token.clone(),
                metrics_token: metrics_token.clone(),
                allow_hosts: args.http_allow_host.clone(),
                edge,
            };
            let farm = farm.clone();
            tokio::spawn(async move {
                if let Err(e) =
                    tessera_coordinator::monitor::serve(farm, l, monitor, shutdown_signal()).await
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

/// Least entropy of a token, in bits.
const MIN_TOKEN_BITS: f64 = 128.0;

/// Refuses guessable tokens and one token for both kinds. A token's
/// entropy is estimated as its length times the bits a character of the
/// smallest alphabet it is written in carries: 4 for hex, 6 for base64
/// (and base64url), log2(94) = 6.55 for any printable ASCII; so at least
/// 32 hex, 22 base64 or 20 other characters, of which at least 8 differ.
/// `tessera cert --tokens` writes 64 hex digits (256 bits).
fn check_tokens(client: Option<&str>, worker: Option<&str>) -> Result<()> {
    for (t, kind, flag) in [
        (
            client,
            "client",
            "--client-token-file or TESSERA_CLIENT_TOKEN",
        ),
        (
            worker,
            "worker",
            "--worker-token-file or TESSERA_WORKER_TOKEN",
        ),
    ] {
        let Some(t) = t else { continue };
        let per_char: f64 = if t.bytes().all(|b| b.is_ascii_hexdigit()) {
            4.0
        } else if t
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"+/=-_".contains(&b))
        {
            6.0
        } else {
            94f64.log2()
        };
        let bits = t.len() as f64 * per_char;
        let distinct = t.bytes().collect::<std::collections::HashSet<u8>>().len();
        if bits < MIN_TOKEN_BITS || distinct < 8 {
            anyhow::bail!(
                "the {kind} token ({flag}) is too easy to guess: {} characters ({:.0} bits; {distinct} different \
                 characters) where at least {MIN_TOKEN_BITS:.0} bits are needed (32 hex digits, 22 base64 \
                 characters, or 20 of any printable ASCII, with at least 8 different). `tessera cert --tokens` \
                 writes random 256-bit tokens",
                t.len(),
                bits.floor()
            );
        }
    }
    if let (Some(c), Some(w)) = (client, worker)
        && c == w
    {
        anyhow::bail!(
            "the client token and the worker token are the same: a worker could then submit, cancel and read \
             every job. Give each its own (`tessera cert --tokens` writes two)"
        );
    }
    Ok(())
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
