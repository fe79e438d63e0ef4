//! Transfer probe: one large `SubmitResult` over loopback gRPC, 30 times,
//! timed at the client, against a server that only answers: the transport's
//! own cost for a GPU worker's result (issue 15). `MB` (default 15) sets the
//! message's size, `WIN` the server's HTTP/2 stream window, `FRAME` its
//! largest frame; `NODELAY` set turns TCP_NODELAY on for the accepted
//! connection, as the coordinator does.
//!
//!     cargo run --release -p tessera-coordinator --example xfer
use std::time::Instant;
use tessera_proto::pb;
use tessera_proto::pb::worker_service_server::{WorkerService, WorkerServiceServer};
use tonic::{Request, Response, Status};

struct S;
type R<T> = Result<Response<T>, Status>;
#[tonic::async_trait]
impl WorkerService for S {
    async fn register(&self, _: Request<pb::RegisterRequest>) -> R<pb::RegisterResponse> {
        Err(Status::unimplemented(""))
    }
    async fn lease_work(&self, _: Request<pb::LeaseWorkRequest>) -> R<pb::LeaseWorkResponse> {
        Err(Status::unimplemented(""))
    }
    async fn submit_result(
        &self,
        r: Request<pb::SubmitResultRequest>,
    ) -> R<pb::SubmitResultResponse> {
        let r = r.into_inner();
        Ok(Response::new(pb::SubmitResultResponse {
            outcome: 1,
            reason: r.sums.len().to_string(),
        }))
    }
    async fn submit_results(
        &self,
        _: Request<pb::SubmitResultsRequest>,
    ) -> R<pb::SubmitResultsResponse> {
        Err(Status::unimplemented(""))
    }
    async fn heartbeat(&self, _: Request<pb::HeartbeatRequest>) -> R<pb::HeartbeatResponse> {
        Err(Status::unimplemented(""))
    }
    async fn return_leases(
        &self,
        _: Request<pb::ReturnLeasesRequest>,
    ) -> R<pb::ReturnLeasesResponse> {
        Err(Status::unimplemented(""))
    }
    async fn get_asset(&self, _: Request<pb::GetAssetRequest>) -> R<pb::GetAssetResponse> {
        Err(Status::unimplemented(""))
    }
    type FetchAssetStream = tokio_stream::wrappers::ReceiverStream<Result<pb::AssetChunk, Status>>;
    async fn fetch_asset(&self, _: Request<pb::GetAssetRequest>) -> R<Self::FetchAssetStream> {
        Err(Status::unimplemented(""))
    }
}

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mb: usize = std::env::var("MB")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(15);
    let frame: u32 = std::env::var("FRAME")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1 << 20);
    let win: u32 = std::env::var("WIN")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(8 << 20);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let addr = listener.local_addr()?;
    tokio::spawn(async move {
        tonic::transport::Server::builder()
            .tcp_nodelay(true)
            .initial_stream_window_size(Some(win))
            .initial_connection_window_size(Some(32 << 20))
            .max_frame_size(Some(frame))
            .add_service(WorkerServiceServer::new(S).max_decoding_message_size(1 << 30))
            .serve_with_incoming(if std::env::var("NODELAY").is_ok() {
                tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true))
            } else {
                tonic::transport::server::TcpIncoming::from(listener)
            })
            .await
            .unwrap();
    });
    let ep = tessera_proto::transport::endpoint(&format!("http://{addr}"), None)?;
    let ch = ep.connect().await?;
    let mut c =
        pb::worker_service_client::WorkerServiceClient::new(ch).max_encoding_message_size(1 << 30);
    let sums = vec![7u8; mb << 20];
    for i in 0..30 {
        let t = Instant::now();
        let req = pb::SubmitResultRequest {
            sums: sums.clone().into(),
            ..Default::default()
        };
        let t1 = t.elapsed();
        let _ = c.submit_result(req).await?;
        let el = t.elapsed();
        println!(
            "{i}: {mb} MB clone {:.1} ms, total {:.1} ms, {:.0} MB/s",
            t1.as_secs_f64() * 1e3,
            el.as_secs_f64() * 1e3,
            mb as f64 * 1.048576 / (el - t1).as_secs_f64()
        );
    }
    Ok(())
}
