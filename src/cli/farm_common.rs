//! What the farm's subcommands share: the coordinator URL, logging set-up,
//! the gRPC client and error mapping.

use std::time::Duration;

use anyhow::{Context, Result, anyhow};
use clap::{Args, ValueEnum};
use tessera_proto::VersionStamp;
use tessera_proto::pb::job_service_client::JobServiceClient;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};

pub const DEFAULT_COORDINATOR: &str = "http://127.0.0.1:7878";

#[derive(Args, Debug, Clone)]
pub struct CoordinatorUrl {
    /// Coordinator to talk to
    #[arg(long = "coordinator", env = "TESSERA_COORDINATOR", default_value = DEFAULT_COORDINATOR)]
    pub url: String,
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
        .with_writer(std::io::stderr);
    // A second init (tests, nested use) keeps the first subscriber.
    let _ = match format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    };
}

pub type JobClient = JobServiceClient<InterceptedService<Channel, VersionStamp>>;

/// Largest message a client accepts (fetched frames can be large).
pub const CLIENT_MAX_MESSAGE_BYTES: usize = 1 << 30;

pub async fn connect(url: &str) -> Result<JobClient> {
    let channel = Endpoint::from_shared(url.to_string())
        .with_context(|| format!("invalid coordinator URL {url:?}"))?
        .connect_timeout(Duration::from_secs(5))
        .connect()
        .await
        .with_context(|| format!("cannot reach the coordinator at {url}"))?;
    Ok(JobServiceClient::with_interceptor(channel, VersionStamp)
        .max_decoding_message_size(CLIENT_MAX_MESSAGE_BYTES)
        .max_encoding_message_size(CLIENT_MAX_MESSAGE_BYTES))
}

/// A failed call as a readable error: the coordinator's message, with the
/// status code when it adds something.
pub fn rpc(s: tonic::Status) -> anyhow::Error {
    match s.code() {
        tonic::Code::InvalidArgument | tonic::Code::NotFound | tonic::Code::FailedPrecondition => {
            anyhow!("{}", s.message())
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
