//! What the farm's subcommands share: the coordinator URL, logging set-up,
//! the gRPC client and error mapping.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, ValueEnum};
use tessera_proto::VersionStamp;
use tessera_proto::pb::job_service_client::JobServiceClient;
use tessera_proto::transport::endpoint;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

pub const DEFAULT_COORDINATOR: &str = "http://127.0.0.1:7878";

#[derive(Args, Debug, Clone)]
pub struct CoordinatorUrl {
    /// Coordinator to talk to (https://HOST:PORT for a coordinator serving TLS)
    #[arg(long = "coordinator", env = "TESSERA_COORDINATOR", default_value = DEFAULT_COORDINATOR)]
    pub url: String,
    /// CA certificate (PEM) to trust for an https:// coordinator, e.g. the
    /// ca.pem of `tessera cert` [default: the public web roots]
    #[arg(long, env = "TESSERA_CA", value_name = "FILE")]
    pub ca: Option<PathBuf>,
    /// File holding the token to present: the client token for client
    /// commands, the worker token for `tessera worker` [default: the
    /// environment variable TESSERA_TOKEN, or TESSERA_WORKER_TOKEN for workers]
    #[arg(long, value_name = "FILE")]
    pub token_file: Option<PathBuf>,
}

pub use tessera_proto::transport::{CLIENT_TOKEN_ENV, WORKER_TOKEN_ENV};

/// The line that opens a certificate in a PEM file.
const CERT_PEM_LINE: &str = "-----BEGIN CERTIFICATE-----";

impl CoordinatorUrl {
    /// The CA certificate's PEM, if one was given.
    pub fn ca_pem(&self) -> Result<Option<Vec<u8>>> {
        let Some(p) = &self.ca else { return Ok(None) };
        let pem = std::fs::read(p).with_context(|| format!("cannot read --ca {}", p.display()))?;
        // Without this, a token or key file given by mistake reads as an
        // empty trust store, and the handshake fails later as UnknownIssuer.
        if !pem
            .windows(CERT_PEM_LINE.len())
            .any(|w| w == CERT_PEM_LINE.as_bytes())
        {
            bail!(
                "--ca {} is not a PEM certificate (it has no {CERT_PEM_LINE} line); \
                 give the CA's certificate, e.g. the ca.pem of `tessera cert`",
                p.display()
            );
        }
        Ok(Some(pem))
    }

    /// The token from --token-file, else from the environment variable `env`.
    pub fn token(&self, env: &str) -> Result<Option<String>> {
        read_token(self.token_file.as_deref(), "--token-file", env)
    }
}

/// A token from `file` (its first line), else from the environment
/// variable `env`; None when neither is set. `flag` names the file's flag
/// in messages.
pub fn read_token(file: Option<&Path>, flag: &str, env: &str) -> Result<Option<String>> {
    let token = match file {
        Some(p) => std::fs::read_to_string(p)
            .with_context(|| format!("cannot read {flag} {}", p.display()))?
            .lines()
            .next()
            .unwrap_or("")
            .trim()
            .to_string(),
        None => match std::env::var(env) {
            Ok(v) => v.trim().to_string(),
            Err(_) => return Ok(None),
        },
    };
    let source = || file.map_or(format!("${env}"), |p| p.display().to_string());
    if token.is_empty() {
        bail!("the token in {} is empty", source());
    }
    if !token.bytes().all(|b| b.is_ascii_graphic()) {
        bail!(
            "the token in {} has characters other than printable ASCII",
            source()
        );
    }
    Ok(Some(token))
}

/// A new random token (32 bytes of the OS's randomness, as hex).
pub fn new_token() -> Result<String> {
    use std::io::Read as _;
    let mut b = [0u8; 32];
    std::fs::File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut b))
        .context("cannot read /dev/urandom for a token")?;
    Ok(b.iter().map(|x| format!("{x:02x}")).collect())
}

#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines
    #[default]
    Text,
    /// One JSON object per line
    Json,
}

/// Logs to stderr; `RUST_LOG` filters (default `info`).
pub fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        // Colour codes only on a terminal, never into log files.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()));
    // A second init (tests, nested use) keeps the first subscriber.
    let _ = match format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    };
}

pub type JobClient = JobServiceClient<InterceptedService<Channel, VersionStamp>>;

/// Largest message a client accepts (fetched frames can be large).
pub const CLIENT_MAX_MESSAGE_BYTES: usize = 1 << 30;

/// Whether this process talks plain HTTP/2 (for the hint in [`rpc`]).
static PLAINTEXT: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// A client of the job service, with TLS and the client token as given.
pub async fn connect(c: &CoordinatorUrl) -> Result<JobClient> {
    let url = &c.url;
    PLAINTEXT.store(
        url.starts_with("http://"),
        std::sync::atomic::Ordering::Relaxed,
    );
    let stamp = VersionStamp::with_token(c.token(CLIENT_TOKEN_ENV)?.as_deref())?;
    let channel = endpoint(url, c.ca_pem()?.as_deref())?
        .connect()
        .await
        .map_err(|e| unreachable(url, e))?;
    Ok(JobServiceClient::with_interceptor(channel, stamp)
        .max_decoding_message_size(CLIENT_MAX_MESSAGE_BYTES)
        .max_encoding_message_size(CLIENT_MAX_MESSAGE_BYTES))
}

/// Why a coordinator could not be reached, with the likely cause when the
/// error says which: a name that did not resolve, nothing listening, TLS
/// spoken to a plaintext server, or plaintext to a TLS one.
pub fn unreachable(url: &str, e: tonic::transport::Error) -> anyhow::Error {
    let detail = tessera_proto::transport::error_chain(&e);
    let hint = if detail.contains("dns error") || detail.contains("failed to lookup address") {
        let host = url
            .split_once("://")
            .map_or(url, |(_, rest)| rest)
            .split(['/', '?'])
            .next()
            .unwrap_or_default();
        let host = host.rsplit_once(':').map_or(host, |(h, _)| h);
        format!(
            "; the host name {host:?} did not resolve (check its spelling, or use an IP address)"
        )
    } else if detail.contains("tcp connect error") {
        "; is a coordinator running at that address (and reachable from here)?".to_string()
    } else if url.starts_with("http://") {
        "; if the coordinator serves TLS, use an https:// URL (and --ca for its certificate)"
            .to_string()
    } else if detail.contains("InvalidContentType") || detail.contains("corrupt message") {
        // rustls reads a plaintext HTTP/2 server's first frame as a
        // malformed TLS record.
        format!(
            "; the coordinator answered without TLS: use {} (or give it --tls-cert and --tls-key)",
            url.replacen("https://", "http://", 1)
        )
    } else {
        "; check the URL's host name against the certificate's names and --ca".to_string()
    };
    anyhow!("cannot reach the coordinator at {url}: {detail}{hint}")
}

/// The hint for a gRPC call answered by the web monitor (`--http`): its
/// JSON 404 reads to a gRPC client as a message with compression flag
/// 123, the `{` that opens the JSON.
const MONITOR_PORT_HINT: &str = "this looks like the web monitor's HTTP port (it answered \
    with HTTP and JSON, not gRPC); point --coordinator at the coordinator's gRPC address, \
    the one it listens on with --listen (port 7878 by default), not its --http address";

fn answered_by_monitor(s: &tonic::Status) -> bool {
    let m = s.message();
    m.contains("invalid compression flag: 123") || (m.contains("404") && m.contains("Not Found"))
}

/// A failed call as a readable error: the coordinator's message, with the
/// status code when it adds something.
pub fn rpc(s: tonic::Status) -> anyhow::Error {
    if answered_by_monitor(&s) {
        return anyhow!("{MONITOR_PORT_HINT}");
    }
    match s.code() {
        tonic::Code::InvalidArgument
        | tonic::Code::NotFound
        | tonic::Code::FailedPrecondition
        | tonic::Code::Unauthenticated
        | tonic::Code::PermissionDenied
        | tonic::Code::ResourceExhausted => {
            anyhow!("{}", s.message())
        }
        // What a plain-text client reads from a TLS port (which one
        // depends on timing).
        tonic::Code::Internal
        | tonic::Code::Cancelled
        | tonic::Code::Unknown
        | tonic::Code::Unavailable
            if PLAINTEXT.load(std::sync::atomic::Ordering::Relaxed)
                && [
                    "h2 protocol error",
                    "operation was canceled",
                    "connection",
                    "transport error",
                ]
                .iter()
                .any(|m| s.message().contains(m)) =>
        {
            anyhow!(
                "{} ({:?}); if the coordinator serves TLS, use an https:// URL (and --ca for its certificate)",
                s.message(),
                s.code()
            )
        }
        code => anyhow!("{} ({code:?})", s.message()),
    }
}

pub fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")
}
