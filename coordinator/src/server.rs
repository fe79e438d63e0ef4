//! Serving the farm: both services, gRPC health and reflection, the
//! protocol-version check, message-size limits and the periodic tasks.

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use tessera_proto::pb::job_service_server::JobServiceServer;
use tessera_proto::pb::worker_service_server::WorkerServiceServer;
use tokio::net::TcpListener;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Identity, ServerTlsConfig};
use tonic::{Request, Status};

use crate::edge::{Edge, EdgeLimits, TrackLayer};
use crate::farm::{Farm, FarmError};
use crate::service::Api;

/// HTTP/2 flow-control windows (bytes in flight before an acknowledgement).
const H2_STREAM_WINDOW: u32 = 8 << 20;
const H2_CONNECTION_WINDOW: u32 = 32 << 20;
/// Largest HTTP/2 frame a client may send. At the default 16 KiB a GPU
/// worker's 15 MB result is ~1,000 frames, each handled on its own; 1 MiB
/// frames still hold a small request behind a result for only ~8 ms at
/// 1 Gbit/s.
const H2_MAX_FRAME: u32 = 1 << 20;

/// HTTP/2 keepalive: a ping after this long without a frame from the
/// peer, and the connection closed if the ping is not answered in
/// [`H2_KEEPALIVE_TIMEOUT`] (a peer gone without a FIN).
const H2_KEEPALIVE_INTERVAL: Duration = Duration::from_secs(30);
const H2_KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(10);
/// Largest header block of one request (hyper's default is 16 MiB).
const H2_MAX_HEADER_LIST: u32 = 64 << 10;

/// How the coordinator meets the network: TLS, the two tokens, and the
/// connection limits of its port.
#[derive(Clone, Debug, Default)]
pub struct Security {
    /// PEM certificate chain and private key: serve TLS.
    pub tls: Option<(Vec<u8>, Vec<u8>)>,
    /// Needed by the job service (submit, list, watch, cancel, fetch).
    pub client_token: Option<String>,
    /// Needed by the worker service (register, lease, results, heartbeat, assets).
    pub worker_token: Option<String>,
    /// Connection limits of the gRPC port.
    pub edge: EdgeLimits,
}

/// Which token a service wants.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Client,
    Worker,
}

/// Checks the protocol version and the bearer token of every request to
/// one service. Health and reflection are not behind it: probes and
/// generic tools see them without a token.
#[derive(Clone)]
struct Gate {
    kind: Kind,
    /// The token this service takes, and the other kind's (to tell a
    /// wrong kind of token from a wrong token).
    expected: Option<Arc<str>>,
    other: Option<Arc<str>>,
}

/// Equal in time independent of where the bytes differ.
pub(crate) fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |d, (x, y)| d | (x ^ y)) == 0
}

impl tonic::service::Interceptor for Gate {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        tessera_proto::check_protocol_version(req.metadata())?;
        let Some(expected) = &self.expected else {
            return Ok(req);
        };
        use tessera_proto::transport::{CLIENT_TOKEN_ENV, WORKER_TOKEN_ENV};
        let (this, env, other) = match self.kind {
            Kind::Client => ("client", CLIENT_TOKEN_ENV, "worker"),
            Kind::Worker => ("worker", WORKER_TOKEN_ENV, "client"),
        };
        let given = req
            .metadata()
            .get(tessera_proto::transport::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .map(|v| v.strip_prefix("Bearer ").unwrap_or(v).trim().to_string());
        match given {
            None => Err(Status::unauthenticated(format!(
                "this coordinator needs a {this} token for this call; none was sent (give it with --token-file or {env})"
            ))),
            Some(t) if same(t.as_bytes(), expected.as_bytes()) => Ok(req),
            Some(t)
                if self
                    .other
                    .as_ref()
                    .is_some_and(|o| same(t.as_bytes(), o.as_bytes())) =>
            {
                Err(Status::permission_denied(format!(
                    "a {other} token was sent, but this call needs the {this} token"
                )))
            }
            Some(_) => Err(Status::unauthenticated(format!(
                "the {this} token sent is not this coordinator's {this} token"
            ))),
        }
    }
}

/// Least time between two returns of freed memory.
const TRIM_INTERVAL: Duration = Duration::from_secs(1);

/// Hands the allocator's free pages back to the system.
fn return_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only releases free memory of the allocator.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Serves `farm` on `listener` until `shutdown` resolves.
pub async fn serve(
    farm: Arc<Farm>,
    listener: TcpListener,
    security: Security,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), FarmError> {
    let limit = farm.config.max_message_bytes;
    let api = Api { farm: farm.clone() };
    let jobs = JobServiceServer::new(api.clone())
        .max_decoding_message_size(limit)
        .max_encoding_message_size(limit);
    let workers = WorkerServiceServer::new(api)
        .max_decoding_message_size(limit)
        .max_encoding_message_size(limit);

    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<JobServiceServer<Api>>().await;
    health.set_serving::<WorkerServiceServer<Api>>().await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(tessera_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()
        .map_err(|e| FarmError::Internal(format!("reflection: {e}")))?;
    let reflection_alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(tessera_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()
        .map_err(|e| FarmError::Internal(format!("reflection: {e}")))?;

    let ticker = {
        let farm = farm.clone();
        let health = health.clone();
        tokio::spawn(async move {
            let mut serving = true;
            let mut tick = tokio::time::interval(Duration::from_millis(100));
            let mut last_progress = tokio::time::Instant::now();
            let (mut trimmed_at, mut last_trim) = (0, tokio::time::Instant::now());
            // At start too: files of jobs that ended before a restart.
            let collect_interval = farm.config.collect_interval;
            let mut last_collect = tokio::time::Instant::now() - collect_interval;
            loop {
                tick.tick().await;
                farm.expire();
                farm.check_workers();
                // Health follows the database and the frame writes:
                // NOT_SERVING while either fails.
                let ok = farm.storage_ok() && farm.frames_ok();
                if ok != serving {
                    serving = ok;
                    if ok {
                        health.set_serving::<JobServiceServer<Api>>().await;
                        health.set_serving::<WorkerServiceServer<Api>>().await;
                        health
                            .set_service_status("", tonic_health::ServingStatus::Serving)
                            .await;
                    } else {
                        health.set_not_serving::<JobServiceServer<Api>>().await;
                        health.set_not_serving::<WorkerServiceServer<Api>>().await;
                        health
                            .set_service_status("", tonic_health::ServingStatus::NotServing)
                            .await;
                    }
                }
                if last_collect.elapsed() >= collect_interval {
                    last_collect = tokio::time::Instant::now();
                    let farm = farm.clone();
                    tokio::task::spawn_blocking(move || farm.collect_assets());
                }
                // Memory a burst of uploads freed goes back to the system
                // (glibc keeps freed blocks in its arenas otherwise).
                let ended = farm
                    .assets
                    .uploads_ended
                    .load(std::sync::atomic::Ordering::Relaxed);
                if ended != trimmed_at && last_trim.elapsed() >= TRIM_INTERVAL {
                    trimmed_at = ended;
                    last_trim = tokio::time::Instant::now();
                    tokio::task::spawn_blocking(return_freed_memory);
                }
                if last_progress.elapsed() >= farm.config.progress_interval {
                    last_progress = tokio::time::Instant::now();
                    farm.log_progress();
                }
            }
        })
    };

    let token = |t: &Option<String>| t.as_deref().map(Arc::<str>::from);
    let client_gate = Gate {
        kind: Kind::Client,
        expected: token(&security.client_token),
        other: token(&security.worker_token),
    };
    let worker_gate = Gate {
        kind: Kind::Worker,
        expected: token(&security.worker_token),
        other: token(&security.client_token),
    };
    // Our own accept loop (crate::edge): connection caps and timeouts that
    // hold without a token, and TCP_NODELAY on every accepted connection
    // (without it a small frame, a response or an HTTP/2 window update,
    // waits for the ACK of the last one, which the peer delays by 40 ms: a
    // result of megabytes took 50 ms instead of 10 in one transfer of three).
    let edge = Edge::new("grpc", security.edge);
    tracing::info!(
        max_connections = security.edge.max_connections,
        max_per_peer = security.edge.max_per_peer,
        handshake_timeout_s = security.edge.handshake_timeout.as_secs_f64(),
        idle_timeout_s = security.edge.idle_timeout.as_secs_f64(),
        "gRPC connection limits"
    );
    let incoming = tokio_stream::wrappers::ReceiverStream::new(edge.incoming(listener));
    let mut builder = tonic::transport::Server::builder();
    if let Some((cert, key)) = &security.tls {
        builder = builder
            .tls_config(ServerTlsConfig::new().identity(Identity::from_pem(cert, key)))
            .map_err(|e| FarmError::Internal(format!("TLS: {e}")))?;
    }
    let result = builder
        // HTTP/2's default 64 KiB windows hold a result to 64 KiB per round
        // trip: 1.3 MB/s at 50 ms. Results and asset chunks are megabytes.
        .initial_stream_window_size(Some(H2_STREAM_WINDOW))
        .initial_connection_window_size(Some(H2_CONNECTION_WINDOW))
        .max_frame_size(Some(H2_MAX_FRAME))
        .http2_keepalive_interval(Some(H2_KEEPALIVE_INTERVAL))
        .http2_keepalive_timeout(Some(H2_KEEPALIVE_TIMEOUT))
        .http2_max_header_list_size(Some(H2_MAX_HEADER_LIST))
        .layer(TrackLayer)
        .add_service(health_service)
        .add_service(reflection)
        .add_service(reflection_alpha)
        .add_service(InterceptedService::new(jobs, client_gate))
        .add_service(InterceptedService::new(workers, worker_gate))
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await
        .map_err(|e| FarmError::Internal(format!("gRPC server: {e}")));
    ticker.abort();
    // Results wait up to RESULTS_DURABLE_WITHIN for their fsync: a
    // coordinator stopped on purpose keeps them.
    if let Err(e) = farm.sync_store().await {
        tracing::error!(error = %e, "cannot make the last results durable");
    }
    result
}
