//! Load generator: how many result messages per second a coordinator
//! accepts on loopback. K clients speak the worker protocol (register,
//! lease, submit) with well-formed results fabricated without rendering
//! (every pixel of the unit with its sample count, zero radiance), so the
//! coordinator, not the tracer, is the bottleneck. Each result is validated,
//! committed to redb and merged like a real one.
//!
//! With BATCH > 1 each client leases BATCH units per LeaseWork and returns
//! them in one SubmitResults; BATCH = 1 uses LeaseWork + SubmitResult per
//! unit, as the worker does.
//!
//!     cargo run --release -p tessera-coordinator --example result_load -- \
//!         http://127.0.0.1:7878 examples/resolution.toml [CLIENTS] [SECONDS] [BATCH]

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use tessera_proto::pb;
use tessera_proto::pb::job_service_client::JobServiceClient;
use tessera_proto::pb::worker_service_client::WorkerServiceClient;

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let url = args
        .get(1)
        .cloned()
        .unwrap_or_else(|| "http://127.0.0.1:7878".into());
    let scene_path = args
        .get(2)
        .cloned()
        .unwrap_or_else(|| "examples/resolution.toml".into());
    let clients: usize = args.get(3).map_or(Ok(64), |s| s.parse())?;
    let seconds: f64 = args.get(4).map_or(Ok(5.0), |s| s.parse())?;
    let batch: u32 = args.get(5).map_or(Ok(1), |s| s.parse())?;

    let mut jobs = JobServiceClient::connect(url.clone()).await?;
    let spec = pb::JobSpec {
        name: "result-load".into(),
        scene_name: scene_path.clone(),
        scene: std::fs::read(&scene_path)?,
        overrides: Some(pb::RenderOverrides {
            width: Some(1920),
            height: Some(1080),
            samples: Some(1),
            ..Default::default()
        }),
        first_frame: 1,
        last_frame: 100,
        tile_size: 8,
        samples_per_unit: 1,
        ..Default::default()
    };
    let job_id = jobs
        .submit_job(pb::SubmitJobRequest { spec: Some(spec) })
        .await?
        .into_inner()
        .job_id;

    let accepted = Arc::new(AtomicU64::new(0));
    let bytes = Arc::new(AtomicU64::new(0));
    let deadline = Instant::now() + Duration::from_secs_f64(seconds);
    let mut tasks = Vec::new();
    for i in 0..clients {
        let (url, accepted, bytes) = (url.clone(), accepted.clone(), bytes.clone());
        tasks.push(tokio::spawn(async move {
            let mut w = WorkerServiceClient::connect(url)
                .await
                .map_err(|e| tonic::Status::unavailable(e.to_string()))?;
            let id = w
                .register(pb::RegisterRequest {
                    name: format!("load-{i}"),
                    capabilities: None,
                })
                .await?
                .into_inner()
                .worker_id;
            while Instant::now() < deadline {
                let units = w
                    .lease_work(pb::LeaseWorkRequest {
                        worker_id: id.clone(),
                        max_units: batch,
                        wait_ms: 0,
                        ahead: false,
                    })
                    .await?
                    .into_inner()
                    .units;
                if units.is_empty() {
                    continue;
                }
                let results: Vec<pb::SubmitResultRequest> = units
                    .into_iter()
                    .map(|u| {
                        let r = u.rect.unwrap_or_default();
                        let s = u.samples.unwrap_or_default();
                        let n = (r.width * r.height) as usize;
                        pb::SubmitResultRequest {
                            worker_id: id.clone(),
                            lease_id: u.lease_id,
                            rect: Some(r),
                            samples: Some(s),
                            sums: vec![0; n * 24],
                            counts: (s.end - s.start).to_le_bytes().repeat(n),
                            rays: Some(pb::RayCounts {
                                primary: n as u64 * (s.end - s.start) as u64,
                                ..Default::default()
                            }),
                            // Slow enough that the coordinator keeps units at one 8x8 tile.
                            render_seconds: 1.0,
                            ..Default::default()
                        }
                    })
                    .collect();
                let outcomes = if batch == 1 {
                    let req = results.into_iter().next().expect("one unit");
                    bytes.fetch_add(prost::Message::encoded_len(&req) as u64, Ordering::Relaxed);
                    vec![w.submit_result(req).await?.into_inner()]
                } else {
                    let req = pb::SubmitResultsRequest { results };
                    bytes.fetch_add(prost::Message::encoded_len(&req) as u64, Ordering::Relaxed);
                    w.submit_results(req).await?.into_inner().outcomes
                };
                let n = outcomes
                    .iter()
                    .filter(|o| o.outcome == pb::ResultOutcome::Accepted as i32)
                    .count();
                accepted.fetch_add(n as u64, Ordering::Relaxed);
            }
            Ok::<_, tonic::Status>(())
        }));
    }
    let start = Instant::now();
    for t in tasks {
        if let Err(e) = t.await? {
            eprintln!("client error: {e}");
        }
    }
    let secs = start.elapsed().as_secs_f64();
    let n = accepted.load(Ordering::Relaxed);
    jobs.cancel_job(pb::CancelJobRequest { job_id }).await?;
    println!(
        "clients {clients}  batch {batch}  results accepted {n} in {secs:.2} s  = {:.0} results/s  ({:.0} bytes per result on the wire)",
        n as f64 / secs,
        bytes.load(Ordering::Relaxed) as f64 / n.max(1) as f64
    );
    Ok(())
}
