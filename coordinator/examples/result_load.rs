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
//! With VIEWERS > 0 and the coordinator's monitor URL (`--http`), that many
//! web-monitor viewers watch the job meanwhile, each doing what the page
//! does and more: the event stream held open, and every second the job's
//! JSON, the live frame's tiles and its preview, and a thumbnail every
//! three seconds (docs/monitor.md, "What a viewer costs").
//!
//!     cargo run --release -p tessera-coordinator --example result_load -- \
//!         http://127.0.0.1:7878 examples/resolution.toml [CLIENTS] [SECONDS] [BATCH] [VIEWERS MONITOR_URL]

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
    let viewers: usize = args.get(6).map_or(Ok(0), |s| s.parse())?;
    let monitor = args.get(7).cloned();
    if viewers > 0 && monitor.is_none() {
        return Err("VIEWERS needs the monitor's URL (http://HOST:PORT) after it".into());
    }

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
                        ..Default::default()
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
                            sums: vec![0; n * 24].into(),
                            counts: (s.end - s.start).to_le_bytes().repeat(n).into(),
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
    let viewed = Arc::new(AtomicU64::new(0));
    let mut watchers = Vec::new();
    if let Some(m) = &monitor {
        let host = m
            .strip_prefix("http://")
            .ok_or("the monitor URL starts with http://")?
            .trim_end_matches('/')
            .to_string();
        for _ in 0..viewers {
            watchers.push(tokio::spawn(viewer::events(host.clone(), deadline)));
            watchers.push(tokio::spawn(viewer::pages(
                host.clone(),
                job_id.clone(),
                deadline,
                viewed.clone(),
            )));
        }
    }
    let start = Instant::now();
    for t in tasks {
        if let Err(e) = t.await? {
            eprintln!("client error: {e}");
        }
    }
    let secs = start.elapsed().as_secs_f64();
    let n = accepted.load(Ordering::Relaxed);
    for w in watchers {
        w.abort();
    }
    jobs.cancel_job(pb::CancelJobRequest { job_id }).await?;
    println!(
        "clients {clients}  batch {batch}  results accepted {n} in {secs:.2} s  = {:.0} results/s  ({:.0} bytes per result on the wire)",
        n as f64 / secs,
        bytes.load(Ordering::Relaxed) as f64 / n.max(1) as f64
    );
    if viewers > 0 {
        println!(
            "  with {viewers} monitor viewers: {} monitor requests answered",
            viewed.load(Ordering::Relaxed)
        );
    }
    Ok(())
}

/// A web-monitor viewer over plain HTTP/1.1 on a TCP socket (no client
/// library: the example needs none for GETs).
mod viewer {
    use std::sync::Arc;
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::time::{Duration, Instant};

    use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
    use tokio::net::TcpStream;

    /// One GET; the body (empty on any failure: a viewer keeps going).
    async fn get(host: &str, path: &str) -> Vec<u8> {
        let Ok(mut s) = TcpStream::connect(host).await else {
            return Vec::new();
        };
        let req = format!("GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n");
        if s.write_all(req.as_bytes()).await.is_err() {
            return Vec::new();
        }
        let mut buf = Vec::new();
        let _ = s.read_to_end(&mut buf).await;
        match buf.windows(4).position(|w| w == b"\r\n\r\n") {
            Some(i) if buf.starts_with(b"HTTP/1.1 200") => buf.split_off(i + 4),
            _ => Vec::new(),
        }
    }

    /// Holds the event stream open, reading every event, until `deadline`.
    pub async fn events(host: String, deadline: Instant) {
        let Ok(mut s) = TcpStream::connect(&host).await else {
            return;
        };
        let req = format!(
            "GET /api/events HTTP/1.1\r\nHost: {host}\r\nAccept: text/event-stream\r\n\r\n"
        );
        if s.write_all(req.as_bytes()).await.is_err() {
            return;
        }
        let mut buf = vec![0u8; 64 << 10];
        while Instant::now() < deadline {
            match tokio::time::timeout_at(deadline.into(), s.read(&mut buf)).await {
                Ok(Ok(n)) if n > 0 => {}
                _ => return,
            }
        }
    }

    /// What the job page asks for: the job, the live frame's tiles and
    /// preview every second, a thumbnail every third second.
    pub async fn pages(host: String, job: String, deadline: Instant, served: Arc<AtomicU64>) {
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        let mut n = 0u64;
        while Instant::now() < deadline {
            tick.tick().await;
            let body = get(&host, &format!("/api/jobs/{job}")).await;
            let Ok(v) = serde_json::from_slice::<serde_json::Value>(&body) else {
                continue;
            };
            let frames = v["frames"].as_array().cloned().unwrap_or_default();
            let live = frames
                .iter()
                .find(|f| f["written"] == false && f["units_done"].as_u64() > Some(0))
                .or_else(|| frames.first())
                .and_then(|f| f["frame"].as_u64())
                .unwrap_or(1);
            let base = format!("/api/jobs/{job}/frames/{live}");
            get(&host, &base).await;
            get(&host, &format!("{base}/preview.png")).await;
            let mut asked = 3;
            if n.is_multiple_of(3) {
                get(&host, &format!("{base}/preview.png?max=160")).await;
                asked += 1;
            }
            n += 1;
            served.fetch_add(asked, Ordering::Relaxed);
        }
    }
}
