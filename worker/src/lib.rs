//! The worker: registers with a coordinator, leases work units, renders them
//! with tracer-core and sends back the per-pixel sums.
//!
//! Lifecycle: connect (with backoff while the coordinator is away) ->
//! register -> loop { lease -> fetch the scene by hash (cached) -> render
//! (the prepared frame is cached per job and frame) -> submit }. A
//! heartbeat task extends held leases and learns which are gone (expired,
//! cancelled): their render stops at the next band of rows and nothing is
//! sent. Draining (SIGTERM) finishes the current unit and exits.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tessera_proto::pb::worker_service_client::WorkerServiceClient;
use tessera_proto::{film_codec, pb, VersionStamp};
use tokio::sync::watch;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};
use tracer_core::film::{Film, Rect, SampleRange};
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::scene::{RenderSettings, SceneDesc};

/// Rows rendered between checks that the lease is still held.
const BAND_ROWS: u32 = 16;
/// Prepared frames kept (a worker usually serves one or two frames at a time).
const PREPARED_CACHE: usize = 4;
/// Largest message the worker accepts or sends.
const MAX_MESSAGE_BYTES: usize = 256 << 20;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    Cpu,
    Gpu,
}

#[derive(Clone, Debug)]
pub struct WorkerConfig {
    pub coordinator: String,
    pub name: String,
    pub threads: Option<usize>,
    pub backend: Backend,
}

#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    #[error("the GPU backend is not built yet; run workers with --backend cpu")]
    GpuNotBuilt,
    #[error("invalid coordinator URL {url:?}: {message}")]
    Url { url: String, message: String },
    #[error("cannot start the renderer: {0}")]
    Renderer(String),
    #[error("the coordinator refused this worker: {0}")]
    Refused(String),
}

type Client = WorkerServiceClient<InterceptedService<Channel, VersionStamp>>;

/// Work in progress, as the heartbeat sees it.
struct Held {
    cancel: Arc<AtomicBool>,
    samples_done: Arc<AtomicU64>,
}

struct Session {
    client: Client,
    worker_id: String,
    heartbeat: Duration,
}

pub struct Worker {
    config: WorkerConfig,
    renderer: Arc<CpuRenderer>,
    held: Arc<Mutex<HashMap<String, Held>>>,
    scenes: HashMap<String, Arc<SceneDesc>>,
    prepared: VecDeque<((String, u32), Arc<PreparedFrame>)>,
    units_done: u64,
}

/// Why a unit produced no result to send.
enum UnitEnd {
    Film(Film, f64),
    Failed(String),
    Abandoned,
}

impl Worker {
    pub fn new(config: WorkerConfig) -> Result<Self, WorkerError> {
        if config.backend == Backend::Gpu {
            return Err(WorkerError::GpuNotBuilt);
        }
        Endpoint::from_shared(config.coordinator.clone())
            .map_err(|e| WorkerError::Url { url: config.coordinator.clone(), message: e.to_string() })?;
        let renderer = CpuRenderer::new(config.threads).map_err(|e| WorkerError::Renderer(e.to_string()))?;
        Ok(Worker {
            config,
            renderer: Arc::new(renderer),
            held: Arc::default(),
            scenes: HashMap::new(),
            prepared: VecDeque::new(),
            units_done: 0,
        })
    }

    /// Runs until `drain` becomes true (then finishes the current unit) or a
    /// fatal error. Connection losses are retried with backoff.
    pub async fn run(mut self, mut drain: watch::Receiver<bool>) -> Result<(), WorkerError> {
        let mut backoff = Duration::from_millis(100);
        while !*drain.borrow() {
            let session = match self.connect().await {
                Ok(s) => {
                    backoff = Duration::from_millis(100);
                    s
                }
                Err(e) => {
                    if let Some(fatal) = e {
                        return Err(fatal);
                    }
                    tracing::warn!(coordinator = %self.config.coordinator, retry_in_ms = backoff.as_millis() as u64, "coordinator unreachable");
                    tokio::select! {
                        _ = tokio::time::sleep(backoff) => {}
                        _ = drain.changed() => {}
                    }
                    backoff = (backoff * 2).min(Duration::from_secs(5));
                    continue;
                }
            };
            tracing::info!(worker = %session.worker_id, coordinator = %self.config.coordinator, threads = self.renderer.threads(), "registered");
            let lost = Arc::new(AtomicBool::new(false));
            let beat = tokio::spawn(heartbeat(session.client.clone(), session.worker_id.clone(), session.heartbeat, self.held.clone(), lost.clone()));
            let end = self.work(&session, &mut drain, &lost).await;
            beat.abort();
            for (_, h) in self.held.lock().expect("held lock").drain() {
                h.cancel.store(true, Ordering::Relaxed);
            }
            match end {
                Ok(()) => break,
                Err(e) => tracing::warn!(error = %e, "lost the coordinator; reconnecting"),
            }
        }
        tracing::info!(units_done = self.units_done, "worker stopped");
        Ok(())
    }

    /// `Err(None)`: transient, retry. `Err(Some)`: fatal.
    async fn connect(&self) -> Result<Session, Option<WorkerError>> {
        let endpoint = Endpoint::from_shared(self.config.coordinator.clone())
            .map_err(|e| Some(WorkerError::Url { url: self.config.coordinator.clone(), message: e.to_string() }))?
            .connect_timeout(Duration::from_secs(3))
            .tcp_nodelay(true);
        let channel = endpoint.connect().await.map_err(|_| None)?;
        let mut client = WorkerServiceClient::with_interceptor(channel, VersionStamp)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES);
        let caps = pb::Capabilities {
            threads: self.renderer.threads() as u32,
            backend: pb::Backend::Cpu as i32,
            gpu_name: String::new(),
            version: env!("CARGO_PKG_VERSION").into(),
        };
        let resp = client
            .register(pb::RegisterRequest { name: self.config.name.clone(), capabilities: Some(caps) })
            .await
            .map_err(|s| match s.code() {
                tonic::Code::FailedPrecondition | tonic::Code::InvalidArgument => Some(WorkerError::Refused(s.message().to_string())),
                _ => None,
            })?
            .into_inner();
        Ok(Session {
            client,
            worker_id: resp.worker_id,
            heartbeat: Duration::from_millis(resp.heartbeat_interval_ms.clamp(50, 60_000) as u64),
        })
    }

    /// Leases and renders until drained (`Ok`) or the session breaks (`Err`).
    async fn work(&mut self, s: &Session, drain: &mut watch::Receiver<bool>, lost: &AtomicBool) -> Result<(), tonic::Status> {
        let mut client = s.client.clone();
        loop {
            if *drain.borrow() {
                return Ok(());
            }
            if lost.load(Ordering::Relaxed) {
                return Err(tonic::Status::unavailable("the coordinator no longer knows this worker"));
            }
            let resp = client.lease_work(pb::LeaseWorkRequest { worker_id: s.worker_id.clone(), max_units: 1 }).await?.into_inner();
            if resp.units.is_empty() {
                tokio::select! {
                    _ = tokio::time::sleep(Duration::from_millis(resp.retry_after_ms.clamp(10, 5000) as u64)) => {}
                    _ = drain.changed() => {}
                }
                continue;
            }
            for unit in resp.units {
                self.unit(&mut client, &s.worker_id, unit).await?;
            }
        }
    }

    async fn unit(&mut self, client: &mut Client, worker_id: &str, unit: pb::WorkUnit) -> Result<(), tonic::Status> {
        let lease_id = unit.lease_id.clone();
        let cancel = Arc::new(AtomicBool::new(false));
        let samples_done = Arc::new(AtomicU64::new(0));
        self.held
            .lock()
            .expect("held lock")
            .insert(lease_id.clone(), Held { cancel: cancel.clone(), samples_done: samples_done.clone() });
        let rect: Rect = unit.rect.unwrap_or_default().into();
        let samples: SampleRange = unit.samples.unwrap_or_default().into();
        let end = match self.prepare(client, &unit).await {
            Err(e) if e.code() == tonic::Code::Unavailable || e.code() == tonic::Code::Unknown => {
                self.held.lock().expect("held lock").remove(&lease_id);
                return Err(e);
            }
            Err(e) => UnitEnd::Failed(e.message().to_string()),
            Ok(prepared) => {
                let renderer = self.renderer.clone();
                let frame = unit.frame;
                let cancel = cancel.clone();
                tokio::task::spawn_blocking(move || render_unit(&renderer, &prepared, frame, rect, samples, &cancel, &samples_done))
                    .await
                    .unwrap_or_else(|e| UnitEnd::Failed(format!("render panicked: {e}")))
            }
        };
        self.held.lock().expect("held lock").remove(&lease_id);
        let mut req = pb::SubmitResultRequest {
            worker_id: worker_id.to_string(),
            lease_id: lease_id.clone(),
            rect: Some(rect.into()),
            samples: Some(samples.into()),
            ..Default::default()
        };
        match end {
            UnitEnd::Abandoned => {
                tracing::info!(lease = %lease_id, "lease gone; abandoned its unit");
                return Ok(());
            }
            UnitEnd::Failed(msg) => {
                tracing::warn!(lease = %lease_id, error = %msg, "unit failed");
                req.failure = msg;
            }
            UnitEnd::Film(film, secs) => {
                req.sums = film_codec::pack_sums(&film);
                req.counts = film_codec::pack_counts(&film);
                req.rays = Some(film.rays.into());
                req.nonfinite = film.nonfinite;
                req.render_seconds = secs;
            }
        }
        let resp = client.submit_result(req).await?.into_inner();
        match pb::ResultOutcome::try_from(resp.outcome).unwrap_or(pb::ResultOutcome::Unspecified) {
            pb::ResultOutcome::Accepted => {
                self.units_done += 1;
                tracing::debug!(lease = %lease_id, frame = unit.frame, ?rect, "result accepted");
            }
            pb::ResultOutcome::FailureRecorded => {}
            other => tracing::warn!(lease = %lease_id, outcome = ?other, reason = %resp.reason, "result not accepted"),
        }
        Ok(())
    }

    /// The prepared frame of a unit's job, from cache or built from the
    /// (cached, content-addressed) scene.
    async fn prepare(&mut self, client: &mut Client, unit: &pb::WorkUnit) -> Result<Arc<PreparedFrame>, tonic::Status> {
        let job = unit.job.clone().ok_or_else(|| tonic::Status::invalid_argument("work unit without job context"))?;
        let key = (job.job_id.clone(), unit.frame);
        if let Some((_, p)) = self.prepared.iter().find(|(k, _)| *k == key) {
            return Ok(p.clone());
        }
        let scene = match self.scenes.get(&job.scene_sha256) {
            Some(s) => s.clone(),
            None => {
                let content = client.get_asset(pb::GetAssetRequest { sha256: job.scene_sha256.clone() }).await?.into_inner().content;
                let text = String::from_utf8(content).map_err(|e| tonic::Status::invalid_argument(format!("{}: scene is not UTF-8: {e}", job.scene_name)))?;
                let scene = SceneDesc::parse(&text, &job.scene_name).map_err(|e| tonic::Status::invalid_argument(e.to_string()))?;
                let scene = Arc::new(scene);
                self.scenes.insert(job.scene_sha256.clone(), scene.clone());
                scene
            }
        };
        let settings = RenderSettings::try_from(job.settings.unwrap_or_default()).map_err(|e| tonic::Status::invalid_argument(e.to_string()))?;
        let frame = unit.frame;
        let prepared = tokio::task::spawn_blocking(move || PreparedFrame::build(&scene, &settings, frame, Precision::F32))
            .await
            .map_err(|e| tonic::Status::internal(e.to_string()))?
            .map_err(|e| tonic::Status::invalid_argument(e.to_string()))?;
        let prepared = Arc::new(prepared);
        self.prepared.push_back((key, prepared.clone()));
        if self.prepared.len() > PREPARED_CACHE {
            self.prepared.pop_front();
        }
        Ok(prepared)
    }
}

/// Renders a unit band by band, stopping early when `cancel` is set.
fn render_unit(
    renderer: &CpuRenderer,
    prepared: &PreparedFrame,
    frame: u32,
    rect: Rect,
    samples: SampleRange,
    cancel: &AtomicBool,
    samples_done: &AtomicU64,
) -> UnitEnd {
    let start = Instant::now();
    let mut film = Film::new(rect);
    let mut y = rect.y;
    while y < rect.y + rect.height {
        if cancel.load(Ordering::Relaxed) {
            return UnitEnd::Abandoned;
        }
        let band = Rect::new(rect.x, y, rect.width, BAND_ROWS.min(rect.y + rect.height - y));
        match renderer.render(prepared, frame, band, samples, &|n| {
            samples_done.fetch_add(n, Ordering::Relaxed);
        }) {
            Ok(part) => {
                if let Err(e) = film.merge(&part) {
                    return UnitEnd::Failed(e.to_string());
                }
            }
            Err(e) => return UnitEnd::Failed(e.to_string()),
        }
        y += band.height;
    }
    UnitEnd::Film(film, start.elapsed().as_secs_f64())
}

/// Sends heartbeats for held leases; cancels those the coordinator says are gone.
async fn heartbeat(mut client: Client, worker_id: String, every: Duration, held: Arc<Mutex<HashMap<String, Held>>>, lost: Arc<AtomicBool>) {
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let leases: Vec<pb::LeaseProgress> = held
            .lock()
            .expect("held lock")
            .iter()
            .map(|(id, h)| pb::LeaseProgress { lease_id: id.clone(), samples_done: h.samples_done.load(Ordering::Relaxed) })
            .collect();
        match client.heartbeat(pb::HeartbeatRequest { worker_id: worker_id.clone(), leases }).await {
            Ok(resp) => {
                let resp = resp.into_inner();
                let held = held.lock().expect("held lock");
                for id in &resp.gone_leases {
                    if let Some(h) = held.get(id) {
                        tracing::info!(lease = %id, "coordinator says the lease is gone; stopping its work");
                        h.cancel.store(true, Ordering::Relaxed);
                    }
                }
                if resp.reregister {
                    lost.store(true, Ordering::Relaxed);
                }
            }
            Err(e) => tracing::debug!(error = %e, "heartbeat failed"),
        }
    }
}
