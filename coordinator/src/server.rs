//! Serving the farm: both services, gRPC health and reflection, the
//! protocol-version check, message-size limits and the periodic tasks.

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use tessera_proto::pb::job_service_server::JobServiceServer;
use tessera_proto::pb::worker_service_server::WorkerServiceServer;
use tokio::net::TcpListener;
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Status};

use crate::farm::{Farm, FarmError};
use crate::service::Api;

fn check_version(req: Request<()>) -> Result<Request<()>, Status> {
    tessera_proto::check_protocol_version(req.metadata())?;
    Ok(req)
}

/// Serves `farm` on `listener` until `shutdown` resolves.
pub async fn serve(
    farm: Arc<Farm>,
    listener: TcpListener,
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
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_millis(100));
            let mut last_progress = tokio::time::Instant::now();
            loop {
                tick.tick().await;
                farm.expire();
                if last_progress.elapsed() >= farm.config.progress_interval {
                    last_progress = tokio::time::Instant::now();
                    farm.log_progress();
                }
            }
        })
    };

    let incoming = tokio_stream::wrappers::TcpListenerStream::new(listener);
    let result = tonic::transport::Server::builder()
        .tcp_nodelay(true)
        .add_service(health_service)
        .add_service(reflection)
        .add_service(reflection_alpha)
        .add_service(InterceptedService::new(jobs, check_version))
        .add_service(InterceptedService::new(workers, check_version))
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await
        .map_err(|e| FarmError::Internal(format!("gRPC server: {e}")));
    ticker.abort();
    result
}
