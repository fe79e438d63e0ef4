//! The gRPC edge: protobuf messages in, [`Farm`] calls, protobuf out.

use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use tessera_proto::JobSpec;
use tessera_proto::convert::backend_from_pb;
use tessera_proto::film_codec;
use tessera_proto::pb;
use tessera_proto::pb::job_service_server::JobService;
use tessera_proto::pb::worker_service_server::WorkerService;
use tokio_stream::Stream;
use tonic::{Request, Response, Status};
use tracer_core::render::Backend;

use std::sync::atomic::Ordering;

use tessera_proto::transport::ASSET_CHUNK_BYTES;

use crate::assets::{AssetStoreError, check_hash};
use crate::farm::{
    FailureClass, Farm, FarmError, JobState, JobView, Outcome, ResultData, Submission,
};
use crate::store::Counters;

impl From<FarmError> for Status {
    fn from(e: FarmError) -> Self {
        match e {
            FarmError::InvalidArgument(m) => Status::invalid_argument(m),
            FarmError::NotFound(m) => Status::not_found(m),
            FarmError::FailedPrecondition(m) => Status::failed_precondition(m),
            FarmError::PermissionDenied(m) => Status::permission_denied(m),
            FarmError::ResourceExhausted(m) => Status::resource_exhausted(m),
            FarmError::Unavailable(m) => Status::unavailable(m),
            // Nothing was recorded; the same request may be sent again.
            FarmError::Store(e) => Status::unavailable(format!(
                "storage: {e}; nothing was recorded, send the request again"
            )),
            FarmError::Internal(m) => Status::internal(m),
        }
    }
}

/// The farm's job state on the wire (the one conversion; its names are
/// `status_json::state_name`'s).
pub(crate) fn state_pb(s: JobState) -> pb::JobState {
    match s {
        JobState::Waiting => pb::JobState::Waiting,
        JobState::Queued => pb::JobState::Queued,
        JobState::Running => pb::JobState::Running,
        JobState::Done => pb::JobState::Done,
        JobState::Failed => pb::JobState::Failed,
        JobState::Cancelled => pb::JobState::Cancelled,
    }
}

fn rays_pb(c: &Counters) -> pb::RayCounts {
    crate::farm::rays_of(c).into()
}

pub fn job_status(v: &JobView) -> pb::JobStatus {
    let r = &v.record;
    pb::JobStatus {
        job_id: r.id.clone(),
        name: r.name.clone(),
        state: state_pb(v.state) as i32,
        priority: r.priority,
        settings: Some(v.record.settings.into()),
        first_frame: r.first_frame,
        last_frame: r.last_frame,
        units_total: v.units_total,
        units_done: v.units_done,
        samples_total: v.samples_total,
        samples_done: v.samples_done,
        progress: v.progress,
        frames: v
            .frames
            .iter()
            .zip(&v.frames_progress)
            .map(|((f, total, done, out), progress)| pb::FrameStatus {
                frame: *f,
                units_total: *total,
                units_done: *done,
                output: out.clone().unwrap_or_default(),
                progress: *progress,
            })
            .collect(),
        error: r.error.clone(),
        rays: Some(rays_pb(&v.counters)),
        rays_per_second: v.rays_per_second,
        eta_seconds: v.eta_seconds,
        units_accepted: v.counters.units_accepted,
        results_rejected: v.counters.results_rejected,
        results_late: v.counters.results_late,
        results_duplicate: v.counters.results_duplicate,
        submitted_unix_ms: r.submitted_unix_ms,
        finished_unix_ms: r.finished_unix_ms,
        output_dir: r.output_dir.clone(),
        tile_size: r.tile_size,
        samples_per_unit: r.samples_per_unit,
        first_lease_unix_ms: v.first_lease_unix_ms,
        first_result_unix_ms: v.first_result_unix_ms,
        last_result_unix_ms: v.last_result_unix_ms,
        adaptive: v.adaptive.settings.map(|a| pb::AdaptiveStatus {
            target_error: a.target_error,
            relative_error: a.relative_error,
            min_samples: a.min_samples,
            max_samples: a.max_samples,
            converged_share: v.adaptive.converged_share,
            estimated_error: v.adaptive.estimated_error,
            mode: tessera_proto::convert::adaptive_mode_to_pb(a.mode) as i32,
        }),
        blocklisted: v
            .blocklisted
            .iter()
            .map(|b| pb::BlockedWorker {
                worker_id: b.id.clone(),
                name: b.name.clone(),
                failures: b.failures,
                until_unix_ms: b.until_unix_ms,
            })
            .collect(),
        requirements: r.requirements.iter().map(ToString::to_string).collect(),
        unrunnable: v.unrunnable.clone(),
        after: r.after.clone(),
        waiting_for: v.waiting_for.clone(),
        blocklist_after: r.blocklist_after.unwrap_or(0),
        blocklist_seconds: r.blocklist_seconds.unwrap_or(0.0),
        failure_classes: v
            .failures
            .iter()
            .map(|(k, n)| (k.to_string(), *n))
            .collect(),
        scene: r.scene_name.clone(),
        max_attempts: r.max_attempts,
        // Set by the callers that page or send deltas.
        next_frame_page_token: String::new(),
        delta: false,
        keepalive: false,
    }
}

/// Implements both services over one [`Farm`].
#[derive(Clone)]
pub struct Api {
    pub farm: Arc<Farm>,
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl JobService for Api {
    async fn submit_job(
        &self,
        req: Request<pb::SubmitJobRequest>,
    ) -> Result<Response<pb::SubmitJobResponse>, Status> {
        let spec = req
            .into_inner()
            .spec
            .ok_or_else(|| Status::invalid_argument("missing field `spec`"))?;
        // API boundary: the message becomes the one JobSpec here; the farm
        // checks what it asks for against its scene.
        let s = Submission {
            spec: JobSpec::from(&spec),
            scene: spec.scene,
            assets: spec
                .assets
                .into_iter()
                .map(|a| (a.name, a.content))
                .collect(),
            files: spec.files.into_iter().collect(),
        };
        let job_id = self.farm.submit(s).await?;
        Ok(Response::new(pb::SubmitJobResponse { job_id }))
    }

    async fn get_job(
        &self,
        req: Request<pb::GetJobRequest>,
    ) -> Result<Response<pb::JobStatus>, Status> {
        let r = req.into_inner();
        if r.frame_limit == 0 {
            return Ok(Response::new(job_status(&self.farm.job(&r.job_id)?)));
        }
        let from = if r.frame_page_token.is_empty() {
            0
        } else {
            r.frame_page_token.parse::<u32>().map_err(|_| {
                Status::invalid_argument(format!(
                    "frame_page_token {:?} is not one this coordinator gave (a JobStatus.next_frame_page_token)",
                    r.frame_page_token.chars().take(40).collect::<String>()
                ))
            })?
        };
        let limit = r.frame_limit.min(MAX_FRAME_PAGE) as usize;
        let (view, next) = self.farm.job_page(&r.job_id, from, limit)?;
        let mut status = job_status(&view);
        status.next_frame_page_token = next.map(|f| f.to_string()).unwrap_or_default();
        Ok(Response::new(status))
    }

    async fn list_jobs(
        &self,
        _req: Request<pb::ListJobsRequest>,
    ) -> Result<Response<pb::ListJobsResponse>, Status> {
        Ok(Response::new(pb::ListJobsResponse {
            jobs: self.farm.jobs().iter().map(job_status).collect(),
        }))
    }

    type WatchJobStream = BoxStream<pb::JobStatus>;

    async fn watch_job(
        &self,
        req: Request<pb::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let r = req.into_inner();
        let rx = self.farm.watch(&r.job_id)?;
        let (tx, out) = tokio::sync::mpsc::channel(4);
        tokio::spawn(watch(self.farm.clone(), r.job_id, r.deltas, rx, tx));
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(out),
        )))
    }

    async fn cancel_job(
        &self,
        req: Request<pb::CancelJobRequest>,
    ) -> Result<Response<pb::JobStatus>, Status> {
        Ok(Response::new(job_status(
            &self.farm.cancel(&req.into_inner().job_id).await?,
        )))
    }

    type FetchResultsStream = BoxStream<pb::FrameImage>;

    async fn fetch_results(
        &self,
        req: Request<pb::FetchResultsRequest>,
    ) -> Result<Response<Self::FetchResultsStream>, Status> {
        let outputs = self.farm.outputs(&req.into_inner().job_id)?;
        let (tx, out) = tokio::sync::mpsc::channel(2);
        tokio::spawn(async move {
            for (frame, file_name, path) in outputs {
                let msg = match tokio::fs::read(&path).await {
                    Ok(data) => Ok(pb::FrameImage {
                        frame,
                        file_name,
                        data,
                    }),
                    Err(e) => Err(Status::internal(format!(
                        "cannot read {}: {e}",
                        path.display()
                    ))),
                };
                let stop = msg.is_err();
                if tx.send(msg).await.is_err() || stop {
                    return;
                }
            }
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(out),
        )))
    }

    async fn list_workers(
        &self,
        _req: Request<pb::ListWorkersRequest>,
    ) -> Result<Response<pb::ListWorkersResponse>, Status> {
        let workers = self
            .farm
            .workers()
            .into_iter()
            .map(|w| pb::WorkerInfo {
                worker_id: w.id,
                name: w.name,
                capabilities: Some(pb::Capabilities {
                    threads: w.threads,
                    backend: pb::Backend::from(w.backend) as i32,
                    gpu_name: w.gpu_name,
                    version: w.version,
                    host_id: w.host_id,
                    labels: w.labels.into_iter().collect(),
                    block_ranges: w.block_ranges,
                }),
                leases: w.leases,
                units_done: w.units_done,
                samples_per_second: w.samples_per_second,
                rays_per_second: w.rays_per_second,
                last_seen_unix_ms: w.last_seen_unix_ms,
                quarantined_until_unix_ms: w.quarantined_until_unix_ms,
            })
            .collect();
        Ok(Response::new(pb::ListWorkersResponse { workers }))
    }

    async fn delete_job(
        &self,
        req: Request<pb::DeleteJobRequest>,
    ) -> Result<Response<pb::DeleteJobResponse>, Status> {
        self.farm.delete(&req.into_inner().job_id).await?;
        Ok(Response::new(pb::DeleteJobResponse {}))
    }

    async fn find_missing_assets(
        &self,
        req: Request<pb::FindMissingAssetsRequest>,
    ) -> Result<Response<pb::FindMissingAssetsResponse>, Status> {
        let assets = req.into_inner().assets;
        if assets.len() > 100_000 {
            return Err(Status::invalid_argument("at most 100000 assets a request"));
        }
        let mut missing = Vec::new();
        for a in assets {
            check_hash(&a.sha256).map_err(|e| Status::invalid_argument(e.to_string()))?;
            // A file reported held is held: its retention clock restarts, so
            // the collector keeps it for the SubmitJob that names it.
            if self.farm.assets.hold(&a.sha256).is_none() {
                missing.push(a.sha256);
            }
        }
        Ok(Response::new(pb::FindMissingAssetsResponse { missing }))
    }

    async fn upload_asset(
        &self,
        req: Request<tonic::Streaming<pb::AssetChunk>>,
    ) -> Result<Response<pb::UploadAssetResponse>, Status> {
        let store = &self.farm.assets;
        // Bounded in number (in all and per connection) and in time: a
        // stalled upload holds a slot, a temporary file and a small buffer
        // for at most the idle timeout.
        let conn = crate::edge::EdgeInfo::of(req.extensions()).cloned();
        let _slot = store
            .upload_slot(conn.as_ref().map(|c| &c.uploads))
            .map_err(asset_status)?;
        let idle = store.limits.upload_idle_timeout;
        let mut chunks = req.into_inner();
        let mut next_chunk = async || {
            tokio::time::timeout(idle, chunks.message())
                .await
                .map_err(|_| {
                    Status::deadline_exceeded(format!(
                        "UploadAsset: no chunk for {} s (--upload-idle-timeout); the upload was dropped",
                        idle.as_secs_f64()
                    ))
                })?
        };
        let first = next_chunk()
            .await?
            .ok_or_else(|| Status::invalid_argument("UploadAsset: the stream sent no chunk"))?;
        let sha256 = first.sha256.clone();
        let stats = &store.stats;
        let Some(mut upload) = store.begin(&sha256, first.size).map_err(asset_status)? else {
            stats.uploads_skipped.fetch_add(1, Ordering::Relaxed);
            return Ok(Response::new(pb::UploadAssetResponse {
                sha256,
                bytes_stored: 0,
                already_stored: true,
            }));
        };
        let mut offset = 0u64;
        let mut next = Some(first);
        while let Some(chunk) = next {
            if chunk.data.len() > ASSET_CHUNK_BYTES {
                return Err(Status::invalid_argument(format!(
                    "UploadAsset: a chunk of {} bytes is over the {ASSET_CHUNK_BYTES}-byte chunk limit",
                    chunk.data.len()
                )));
            }
            if chunk.offset != offset {
                return Err(Status::invalid_argument(format!(
                    "UploadAsset: a chunk at offset {} where {offset} was expected",
                    chunk.offset
                )));
            }
            upload.write(&chunk.data).map_err(asset_status)?;
            offset += chunk.data.len() as u64;
            next = next_chunk().await?;
        }
        let bytes_stored = tokio::task::block_in_place(|| upload.finish()).map_err(asset_status)?;
        stats.uploads.fetch_add(1, Ordering::Relaxed);
        stats
            .bytes_uploaded
            .fetch_add(bytes_stored, Ordering::Relaxed);
        tracing::info!(sha256 = %sha256, bytes = bytes_stored, "asset stored");
        Ok(Response::new(pb::UploadAssetResponse {
            sha256,
            bytes_stored,
            already_stored: false,
        }))
    }

    async fn get_farm_stats(
        &self,
        _req: Request<pb::GetFarmStatsRequest>,
    ) -> Result<Response<pb::FarmStats>, Status> {
        let a = &self.farm.assets;
        let (files, bytes) = a.held();
        let n = |c: &std::sync::atomic::AtomicU64| c.load(Ordering::Relaxed);
        Ok(Response::new(pb::FarmStats {
            assets_stored: files,
            asset_bytes_stored: bytes,
            asset_uploads: n(&a.stats.uploads),
            asset_bytes_uploaded: n(&a.stats.bytes_uploaded),
            asset_uploads_skipped: n(&a.stats.uploads_skipped),
            asset_fetches: n(&a.stats.fetches),
            asset_bytes_served: n(&a.stats.bytes_served),
            assets_collected: n(&a.stats.collected),
            results_unknown_lease: n(&self.farm.results_unknown_lease),
        }))
    }
}

fn asset_status(e: AssetStoreError) -> Status {
    crate::farm::asset_error(e).into()
}

/// Most frames of one page of `GetJob`.
const MAX_FRAME_PAGE: u32 = 10_000;
/// A watch of a quiet job (`deltas`) sends a keepalive this often.
const WATCH_KEEPALIVE: Duration = Duration::from_secs(15);

/// Sends a watched job's events until it ends or the client leaves: an
/// event whenever the job changed (at most five a second; its rates and
/// ETA looked at once a second), none while it does not. With `deltas`
/// an event holds only the frames that changed since the last (none in
/// the first) and a quiet job gets a keepalive every
/// [`WATCH_KEEPALIVE`]; without it (clients of earlier releases) every
/// event holds every frame. Each event used to be the whole job, once a
/// second even when nothing changed: 50 watchers of a queued 100k-frame
/// job received 783 KB each a second.
async fn watch(
    farm: Arc<Farm>,
    id: String,
    deltas: bool,
    mut rx: tokio::sync::watch::Receiver<u64>,
    tx: tokio::sync::mpsc::Sender<Result<pb::JobStatus, Status>>,
) {
    // The frames changed since this mark are sent next; u64::MAX: none
    // (the first delta event carries no frame).
    let mut since = u64::MAX;
    // What the last event said, its frames left out.
    let mut last: Option<pb::JobStatus> = None;
    let mut quiet_since = tokio::time::Instant::now();
    loop {
        rx.borrow_and_update();
        let (view, mark) = match farm.job_delta(&id, since) {
            Ok(v) => v,
            Err(e) => {
                let _ = tx.send(Err(e.into())).await;
                return;
            }
        };
        let terminal = view.state.is_terminal();
        let mut status = job_status(&view);
        let frames = std::mem::take(&mut status.frames);
        let changed = !frames.is_empty() || last.as_ref() != Some(&status);
        if changed {
            last = Some(status.clone());
            since = mark;
            quiet_since = tokio::time::Instant::now();
            let event = if deltas {
                pb::JobStatus {
                    frames,
                    delta: true,
                    ..status
                }
            } else {
                match farm.job(&id) {
                    Ok(v) => job_status(&v),
                    Err(e) => {
                        let _ = tx.send(Err(e.into())).await;
                        return;
                    }
                }
            };
            if tx.send(Ok(event)).await.is_err() || terminal {
                return;
            }
        } else if deltas && quiet_since.elapsed() >= WATCH_KEEPALIVE {
            quiet_since = tokio::time::Instant::now();
            let keepalive = pb::JobStatus {
                job_id: id.clone(),
                keepalive: true,
                ..Default::default()
            };
            if tx.send(Ok(keepalive)).await.is_err() {
                return;
            }
        }
        // At most 5 events a second, a look at least once a second (rates,
        // ETA); the job's end at once (a short job's client should not
        // wait out the throttle).
        let looked = tokio::time::Instant::now();
        tokio::select! {
            _ = tokio::time::timeout(Duration::from_secs(1), rx.changed()) => {}
            // The client left: stop now, not at the next change.
            _ = tx.closed() => return,
        }
        let calm = looked + Duration::from_millis(200);
        while tokio::time::Instant::now() < calm && !farm.job_ended(&id) {
            if let Ok(Err(_)) = tokio::time::timeout_at(calm, rx.changed()).await {
                break; // the job is gone: the next look says so
            }
        }
    }
}

/// Longest long poll of `LeaseWork` (`wait_ms`).
const MAX_LEASE_WAIT_MS: u32 = 5_000;
/// Most `rendered` reports of one `LeaseWork` request that are read.
const MAX_RENDERED_REPORTS: usize = 64;

#[tonic::async_trait]
impl WorkerService for Api {
    async fn register(
        &self,
        req: Request<pb::RegisterRequest>,
    ) -> Result<Response<pb::RegisterResponse>, Status> {
        let r = req.into_inner();
        let caps = r.capabilities.unwrap_or_default();
        // UNSPECIFIED (a worker that does not say, or a value this build does
        // not know) counts as a CPU worker.
        let backend = backend_from_pb(caps.backend).unwrap_or(Backend::Cpu);
        let name = if r.name.is_empty() {
            "worker".to_string()
        } else {
            r.name
        };
        crate::farm::check_name("worker name", &name, 200)?;
        crate::farm::check_name("GPU name", &caps.gpu_name, 200)?;
        crate::farm::check_name("version", &caps.version, 200)?;
        crate::farm::check_name("host id", &caps.host_id, 200)?;
        let labels: std::collections::BTreeMap<String, String> = caps.labels.into_iter().collect();
        tessera_proto::placement::check_labels(&labels)
            .map_err(|e| Status::invalid_argument(e.to_string()))?;
        let worker_id = self.farm.register(
            name,
            crate::farm::WorkerCaps {
                threads: caps.threads,
                backend,
                gpu_name: caps.gpu_name,
                version: caps.version,
                host_id: caps.host_id,
                labels,
                block_ranges: caps.block_ranges,
            },
        );
        Ok(Response::new(pb::RegisterResponse {
            worker_id,
            heartbeat_interval_ms: self.farm.config.heartbeat_interval.as_millis() as u32,
            lease_timeout_ms: self.farm.config.lease_timeout.as_millis() as u32,
        }))
    }

    async fn lease_work(
        &self,
        req: Request<pb::LeaseWorkRequest>,
    ) -> Result<Response<pb::LeaseWorkResponse>, Status> {
        let r = req.into_inner();
        let wait = Duration::from_millis(u64::from(r.wait_ms.min(MAX_LEASE_WAIT_MS)));
        // A worker holds few leases: more reports than that are not read.
        let rendered: Vec<(String, u64, f64)> = r
            .rendered
            .into_iter()
            .take(MAX_RENDERED_REPORTS)
            .map(|u| (u.lease_id, u.rays, u.render_seconds))
            .collect();
        if !rendered.is_empty() {
            self.farm.rate_rendered(&r.worker_id, &rendered);
        }
        if let Some(left) = self.farm.quarantined_for(&r.worker_id) {
            // Not an error: a worker retries after retry_after_ms, with
            // its session (re-registering would not lift it either way).
            return Ok(Response::new(pb::LeaseWorkResponse {
                units: Vec::new(),
                retry_after_ms: left.as_millis().min(u128::from(u32::MAX)) as u32,
                refused: format!(
                    "this worker is quarantined for another {:.0} s: its results failed validation {} times in a row (see the coordinator's log)",
                    left.as_secs_f64().ceil(),
                    self.farm.config.quarantine_after
                ),
            }));
        }
        let leases = self
            .farm
            .lease_or_wait(&r.worker_id, r.max_units.clamp(1, 64), r.ahead, wait)
            .await?;
        // A worker that waited may ask again at once; one that did not, later.
        let retry_after_ms = if !leases.is_empty() {
            0
        } else if wait.is_zero() {
            250
        } else {
            10
        };
        let units = leases.into_iter().map(pb::WorkUnit::from).collect();
        Ok(Response::new(pb::LeaseWorkResponse {
            units,
            retry_after_ms,
            refused: String::new(),
        }))
    }

    async fn submit_result(
        &self,
        req: Request<pb::SubmitResultRequest>,
    ) -> Result<Response<pb::SubmitResultResponse>, Status> {
        let result = decode_results(vec![req.into_inner()])
            .await?
            .pop()
            .expect("one request, one result");
        let outcome = self.farm.submit_result(result).await?;
        Ok(Response::new(outcome_pb(outcome)))
    }

    async fn submit_results(
        &self,
        req: Request<pb::SubmitResultsRequest>,
    ) -> Result<Response<pb::SubmitResultsResponse>, Status> {
        let results = decode_results(req.into_inner().results).await?;
        let outcomes = self.farm.submit_results(results).await?;
        Ok(Response::new(pb::SubmitResultsResponse {
            outcomes: outcomes.into_iter().map(outcome_pb).collect(),
        }))
    }

    async fn heartbeat(
        &self,
        req: Request<pb::HeartbeatRequest>,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let r = req.into_inner();
        let leases: Vec<(String, u64)> = r
            .leases
            .into_iter()
            .map(|l| (l.lease_id, l.samples_done))
            .collect();
        match self.farm.heartbeat(&r.worker_id, &leases) {
            Ok(gone_leases) => Ok(Response::new(pb::HeartbeatResponse {
                gone_leases,
                reregister: false,
            })),
            Err(FarmError::NotFound(_)) => Ok(Response::new(pb::HeartbeatResponse {
                gone_leases: leases.into_iter().map(|l| l.0).collect(),
                reregister: true,
            })),
            Err(e) => Err(e.into()),
        }
    }

    async fn return_leases(
        &self,
        req: Request<pb::ReturnLeasesRequest>,
    ) -> Result<Response<pb::ReturnLeasesResponse>, Status> {
        let r = req.into_inner();
        let returned = self.farm.return_leases(&r.worker_id, &r.lease_ids)?;
        Ok(Response::new(pb::ReturnLeasesResponse { returned }))
    }

    async fn get_asset(
        &self,
        req: Request<pb::GetAssetRequest>,
    ) -> Result<Response<pb::GetAssetResponse>, Status> {
        let content = self.farm.asset(&req.into_inner().sha256)?;
        let stats = &self.farm.assets.stats;
        stats.fetches.fetch_add(1, Ordering::Relaxed);
        stats
            .bytes_served
            .fetch_add(content.len() as u64, Ordering::Relaxed);
        Ok(Response::new(pb::GetAssetResponse { content }))
    }

    type FetchAssetStream = BoxStream<pb::AssetChunk>;

    async fn fetch_asset(
        &self,
        req: Request<pb::GetAssetRequest>,
    ) -> Result<Response<Self::FetchAssetStream>, Status> {
        let sha256 = req.into_inner().sha256;
        // Files of older releases live in the database: sent from memory.
        let (mut file, size) = match self.farm.assets.open_file(&sha256) {
            Ok(f) => (Some(f.0), f.1),
            Err(AssetStoreError::NotFound(_)) => (None, 0),
            Err(e) => return Err(asset_status(e)),
        };
        let legacy = match file {
            Some(_) => None,
            None => Some(self.farm.asset(&sha256)?),
        };
        let size = legacy.as_ref().map_or(size, |b| b.len() as u64);
        let farm = self.farm.clone();
        let (tx, out) = tokio::sync::mpsc::channel(4);
        tokio::task::spawn_blocking(move || {
            use std::io::Read as _;
            let stats = &farm.assets.stats;
            stats.fetches.fetch_add(1, Ordering::Relaxed);
            let mut offset = 0u64;
            loop {
                let mut data = vec![0u8; ASSET_CHUNK_BYTES.min((size - offset) as usize)];
                if let Some(f) = file.as_mut() {
                    if let Err(e) = f.read_exact(&mut data) {
                        let _ = tx.blocking_send(Err(Status::internal(format!(
                            "cannot read asset {sha256}: {e}"
                        ))));
                        return;
                    }
                } else if let Some(b) = &legacy {
                    let (o, n) = (offset as usize, data.len());
                    data.copy_from_slice(&b[o..o + n]);
                }
                let n = data.len() as u64;
                let chunk = pb::AssetChunk {
                    sha256: if offset == 0 {
                        sha256.clone()
                    } else {
                        String::new()
                    },
                    size: if offset == 0 { size } else { 0 },
                    offset,
                    data,
                };
                if tx.blocking_send(Ok(chunk)).is_err() {
                    return;
                }
                stats.bytes_served.fetch_add(n, Ordering::Relaxed);
                offset += n;
                if offset >= size {
                    return;
                }
            }
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(out),
        )))
    }
}

/// Decodes result requests (packed films unpacked, their sizes checked),
/// logging the batch's size and decode time (the first stage of the intake
/// in the debug log). Off the async threads: a GPU worker's result is a
/// quarter of a million pixels, and decoding it on a runtime thread stalled
/// the tasks queued there (the same worker's lease requests among them)
/// for up to 46 ms in a mixed farm.
async fn decode_results(reqs: Vec<pb::SubmitResultRequest>) -> Result<Vec<ResultData>, Status> {
    // A few small tiles are decoded here: on the blocking pool, the two
    // thread wake-ups would cost more than the decoding (`tessera bench
    // scale`, thousands of 8x8 tiles a second).
    let bytes: usize = reqs
        .iter()
        .map(|r| r.sums.len() + r.counts.len() + r.squares.len())
        .sum();
    let pixels: u64 = reqs
        .iter()
        .map(|r| {
            r.rect
                .map_or(0, |r| u64::from(r.width) * u64::from(r.height))
        })
        .sum();
    if bytes <= INLINE_DECODE_BYTES && pixels <= INLINE_DECODE_PIXELS {
        return Ok(reqs.into_iter().map(result_data).collect());
    }
    tokio::task::spawn_blocking(move || {
        let start = std::time::Instant::now();
        let results: Vec<ResultData> = reqs.into_iter().map(result_data).collect();
        tracing::debug!(
            results = results.len(),
            pixels = results.iter().map(|r| r.rect.area()).sum::<usize>(),
            decode_ms = start.elapsed().as_secs_f64() * 1e3,
            "results decoded"
        );
        results
    })
    .await
    .map_err(|e| Status::internal(format!("result decoding failed: {e}")))
}

/// Results decoded on the async thread that received them: at most this
/// many bytes of film and pixels in all (a few microseconds of work).
const INLINE_DECODE_BYTES: usize = 64 << 10;
const INLINE_DECODE_PIXELS: u64 = 4096;

/// A result from the wire, its packed film unpacked and its size checked.
fn result_data(r: pb::SubmitResultRequest) -> ResultData {
    let rect = r.rect.unwrap_or_default().into();
    let samples = r.samples.unwrap_or_default().into();
    let encoding = film_codec::Encoding::from_wire(r.sum_bytes, r.uniform_count);
    let decoded_as = encoding.as_ref().ok().copied();
    let film = encoding
        .and_then(|encoding| {
            film_codec::unpack_film(
                rect,
                encoding,
                &r.sums,
                &r.counts,
                (r.square_bytes != 0).then_some((r.square_bytes, &r.squares[..])),
                r.rays.unwrap_or_default().into(),
                r.nonfinite,
            )
        })
        .map(|mut f| {
            // Checked against the lease's blocks (farm::adaptive::check_runs).
            f.runs = r.runs.iter().map(Into::into).collect();
            f
        })
        .map_err(|e| e.to_string());
    // The fields decoded: they are the film in the store's layout too
    // (adaptive films, with squares, are encoded again with them).
    let packed = match (&film, decoded_as) {
        (Ok(f), Some(e)) if f.squares.is_none() => Some(film_codec::Packed {
            sum_bytes: e.sum_bytes,
            uniform_count: e.uniform_count,
            sums: r.sums,
            counts: r.counts,
        }),
        _ => None,
    };
    ResultData {
        worker_id: r.worker_id,
        lease_id: r.lease_id,
        rect,
        samples,
        film,
        packed,
        render_seconds: r.render_seconds,
        failure: (!r.failure.is_empty()).then_some(r.failure),
        failure_class: match pb::FailureClass::try_from(r.failure_class)
            .unwrap_or(pb::FailureClass::Unspecified)
        {
            pb::FailureClass::Unspecified => FailureClass::Unspecified,
            pb::FailureClass::Scene => FailureClass::Scene,
            pb::FailureClass::OutOfMemory => FailureClass::OutOfMemory,
            pb::FailureClass::GpuLost => FailureClass::GpuLost,
            pb::FailureClass::WorkerCrash => FailureClass::WorkerCrash,
            pb::FailureClass::Timeout => FailureClass::Timeout,
        },
    }
}

fn outcome_pb(o: Outcome) -> pb::SubmitResultResponse {
    let (outcome, reason) = match o {
        Outcome::Accepted => (pb::ResultOutcome::Accepted, String::new()),
        Outcome::Rejected(m) => (pb::ResultOutcome::Rejected, m),
        Outcome::Late(m) => (pb::ResultOutcome::Late, m),
        Outcome::Duplicate(m) => (pb::ResultOutcome::Duplicate, m),
        Outcome::FailureRecorded => (pb::ResultOutcome::FailureRecorded, String::new()),
    };
    pb::SubmitResultResponse {
        outcome: outcome as i32,
        reason,
    }
}
