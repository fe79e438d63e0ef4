//! The worker: registers with a coordinator, leases work units, renders them
//! with tracer-core and sends back the per-pixel sums.
//!
//! Lifecycle: connect (with backoff while the coordinator is away) ->
//! register -> a pipeline of three parts, so the renderer never waits on
//! the network:
//! - the render loop takes the next leased unit, renders it (the prepared
//!   frame is cached per job and frame, the scene per content hash) and,
//!   while it renders, leases the next unit (prefetch: one lease ahead);
//! - a sender task packs finished films and submits them, several at once
//!   (`SubmitResults`) when more than one is ready, retrying a submission
//!   the coordinator could not record;
//! - a heartbeat task extends every held lease (rendering, queued or being
//!   sent) and learns which are gone (expired, cancelled): a rendering unit
//!   stops (the CPU renderer before its next 16x16 tile, the GPU at the next
//!   band of rows), a queued one is skipped, nothing is sent. Unanswered
//!   for the coordinator's lease timeout (a partition), it takes every
//!   lease as expired the same way and the worker registers again.
//!
//! Draining (SIGTERM) finishes the unit being rendered, hands the prefetched
//! leases back (`ReturnLeases`) so no one waits for them to expire, sends
//! the last results and exits.
//!
//! A worker renders on CPU threads or, with [`Backend::Gpu`] (feature `gpu`),
//! on one GPU adapter through tracer-core's wgpu renderer. Either way a unit
//! yields the same fixed-point [`Film`] sums, so the coordinator merges
//! results from both kinds of worker alike.

pub mod cache;
mod unit;

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use cache::AssetCache;
use tessera_proto::pb::worker_service_client::WorkerServiceClient;
use tessera_proto::transport::endpoint;
use tessera_proto::{VersionStamp, film_codec, pb};
use tokio::sync::{mpsc, watch};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tracer_core::adaptive::BlockMask;
use tracer_core::assets::Bundle;
use tracer_core::film::{Film, Rect, SampleRange, WorkRegion};
use tracer_core::render::{Backend, Precision, PreparedFrame, Renderer, RendererError};
use tracer_core::scene::SceneDesc;
use unit::{JobInfo, LeasedUnit, UnitFilm};

/// Leases held ahead of the one being rendered.
const PREFETCH: usize = 1;
/// How long an idle worker's lease request waits at the coordinator for
/// work to appear (drain waits for it too, so keep it short).
const IDLE_LEASE_WAIT: Duration = Duration::from_millis(1000);
/// Finished results waiting for the sender before the render loop waits.
const SEND_QUEUE: usize = 4;
/// Result submissions under way at once.
const SEND_IN_FLIGHT: usize = 3;
/// Most results in one `SubmitResults`, and most bytes of film data in it:
/// batches gather small results (a CPU worker's) into one round trip and
/// one commit; results of megabytes (a GPU worker's) go one a message, so
/// that those in flight travel and are decoded side by side.
const MAX_BATCH: usize = 16;
const MAX_BATCH_BYTES: usize = 4 << 20;
/// Submissions of one batch before the session is given up: with the
/// backoff doubling to 5 s, about two minutes of a coordinator that cannot
/// record results (a full disk) before the worker starts over.
const SUBMIT_TRIES: u32 = 30;
/// How long a session that ended with an error waits for its finished
/// results to be delivered before reconnecting.
const SENDER_GRACE: Duration = Duration::from_secs(5);
const SUBMIT_BACKOFF_MAX: Duration = Duration::from_secs(5);
/// Prepared frames kept (a worker usually serves one or two frames at a time).
const PREPARED_CACHE: usize = 4;
/// Largest message the worker accepts or sends.
const MAX_MESSAGE_BYTES: usize = 256 << 20;
/// Pixel-samples in one GPU render call of a unit: the lease is checked
/// between calls, and one call of this size takes tens of milliseconds on
/// a discrete GPU (the unit's film is read back once per call, so fewer,
/// larger calls spend less on fixed costs).
const GPU_BAND_PIXEL_SAMPLES: u64 = 1 << 26;

#[derive(Clone, Debug)]
pub struct WorkerConfig {
    pub coordinator: String,
    pub name: String,
    /// CPU threads (CPU backend; the GPU backend uses the CPU only to feed the GPU).
    pub threads: Option<usize>,
    pub backend: Backend,
    /// GPU backend: adapter index or part of its name (as `tessera gpus` lists them); `None` picks the best.
    pub adapter: Option<String>,
    /// CA certificate (PEM) to trust for an https:// coordinator.
    pub ca_pem: Option<Vec<u8>>,
    /// The farm's worker token, when it uses tokens.
    pub token: Option<String>,
    /// Where job files are cached, and the most bytes kept there.
    pub cache_dir: std::path::PathBuf,
    pub cache_bytes: u64,
}

#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    #[error(
        "this tessera was built without the `gpu` feature; run workers with --backend cpu or rebuild with --features gpu"
    )]
    GpuNotBuilt,
    #[error(transparent)]
    Transport(#[from] tessera_proto::transport::TransportError),
    #[error("cannot open the asset cache {dir}: {message}")]
    Cache { dir: String, message: String },
    #[error("cannot start the renderer: {0}")]
    Renderer(String),
    #[error("the coordinator refused this worker: {0}")]
    Refused(String),
}

type Client = WorkerServiceClient<InterceptedService<Channel, VersionStamp>>;

/// A lease this worker holds (queued, rendering or being sent), as the
/// heartbeat sees it.
struct Held {
    cancel: Arc<AtomicBool>,
    samples_done: Arc<AtomicU64>,
}

type HeldMap = Arc<Mutex<HashMap<String, Held>>>;

struct Session {
    client: Client,
    worker_id: String,
    heartbeat: Duration,
    /// How long the coordinator keeps a lease without a heartbeat (`None`:
    /// it did not say).
    lease_timeout: Option<Duration>,
}

/// What this worker tells the coordinator it is.
fn capabilities(renderer: &Renderer) -> pb::Capabilities {
    pb::Capabilities {
        threads: renderer.threads() as u32,
        backend: pb::Backend::from(renderer.backend()) as i32,
        gpu_name: renderer.adapter_name().unwrap_or_default().to_string(),
        version: env!("CARGO_PKG_VERSION").into(),
        host_id: host_id(),
    }
}

/// This machine, for the coordinator to tell workers that share one:
/// systemd's machine id, else the host name, else unknown (empty).
fn host_id() -> String {
    [
        "/etc/machine-id",
        "/var/lib/dbus/machine-id",
        "/etc/hostname",
    ]
    .iter()
    .filter_map(|p| std::fs::read_to_string(p).ok())
    .map(|s| s.trim().chars().take(200).collect::<String>())
    .find(|s| !s.is_empty() && s.chars().all(|c| c.is_ascii_graphic()))
    .unwrap_or_default()
}

/// Why a unit's rectangle is refused: its result would not fit one
/// message, or its film (28 bytes a pixel) not this machine's memory.
fn too_large(rect: Rect) -> Option<String> {
    let bytes = rect.area() as u64 * 28;
    if bytes > MAX_MESSAGE_BYTES as u64 {
        return Some(format!(
            "a lease of {}x{} pixels makes a {bytes}-byte result, over this worker's {MAX_MESSAGE_BYTES}-byte message limit",
            rect.width, rect.height
        ));
    }
    let mut probe: Vec<u8> = Vec::new();
    if probe.try_reserve_exact(2 * bytes as usize).is_err() {
        return Some(format!(
            "a lease of {}x{} pixels needs {bytes} bytes twice over, more than this worker can allocate",
            rect.width, rect.height
        ));
    }
    None
}

pub struct Worker {
    config: WorkerConfig,
    renderer: Arc<Renderer>,
    held: HeldMap,
    /// Parsed scenes by (scene hash, files), most recent last.
    scenes: VecDeque<(String, Arc<SceneDesc>)>,
    cache: Arc<AssetCache>,
    stamp: VersionStamp,
    prepared: VecDeque<((String, u32), Arc<PreparedFrame>)>,
    units_done: Arc<AtomicU64>,
}

/// How rendering a unit ended: its film and render seconds, a failure, or
/// nothing (the lease went away).
enum UnitEnd {
    Film(UnitFilm, f64),
    Failed(String),
    Abandoned,
}

/// A finished unit on its way to the coordinator.
struct Outgoing {
    lease_id: String,
    region: WorkRegion,
    end: UnitEnd,
    /// The job's work units the lease covers.
    units: u64,
}

impl Worker {
    pub fn new(config: WorkerConfig) -> Result<Self, WorkerError> {
        endpoint(&config.coordinator, config.ca_pem.as_deref())?;
        let stamp = VersionStamp::with_token(config.token.as_deref())?;
        let cache = AssetCache::open(&config.cache_dir, config.cache_bytes).map_err(|e| {
            WorkerError::Cache {
                dir: config.cache_dir.display().to_string(),
                message: e.to_string(),
            }
        })?;
        let renderer = Renderer::open(config.backend, config.threads, config.adapter.as_deref())
            .map_err(|e| match e {
                RendererError::GpuNotBuilt => WorkerError::GpuNotBuilt,
                e => WorkerError::Renderer(e.to_string()),
            })?;
        Ok(Worker {
            config,
            renderer: Arc::new(renderer),
            held: Arc::default(),
            scenes: VecDeque::new(),
            cache: Arc::new(cache),
            stamp,
            prepared: VecDeque::new(),
            units_done: Arc::default(),
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
            let caps = capabilities(&self.renderer);
            // The public id: the session itself speaks for the leases.
            let public_id = tessera_proto::transport::public_worker_id(&session.worker_id);
            tracing::info!(worker = %public_id, coordinator = %self.config.coordinator, threads = caps.threads, gpu = %caps.gpu_name, "registered");
            let lost = Arc::new(AtomicBool::new(false));
            let beat = tokio::spawn(heartbeat(
                session.client.clone(),
                session.worker_id.clone(),
                session.heartbeat,
                session.lease_timeout,
                self.held.clone(),
                lost.clone(),
            ));
            let end = self.work(&session, &mut drain, &lost).await;
            beat.abort();
            // Whatever is still held belongs to a session that is over.
            for (_, h) in self.held.lock().expect("held lock").drain() {
                h.cancel.store(true, Ordering::Relaxed);
            }
            match end {
                Ok(()) => break,
                Err(e) => tracing::warn!(error = %e, "lost the coordinator; reconnecting"),
            }
        }
        tracing::info!(
            units_done = self.units_done.load(Ordering::Relaxed),
            "worker stopped"
        );
        Ok(())
    }

    /// `Err(None)`: transient, retry. `Err(Some)`: fatal.
    async fn connect(&self) -> Result<Session, Option<WorkerError>> {
        let endpoint = endpoint(&self.config.coordinator, self.config.ca_pem.as_deref())
            .map_err(|e| Some(e.into()))?
            .connect_timeout(Duration::from_secs(3));
        let channel = endpoint.connect().await.map_err(|e| {
            tracing::debug!(error = %tessera_proto::transport::error_chain(&e), "cannot connect");
            None
        })?;
        let mut client = WorkerServiceClient::with_interceptor(channel, self.stamp.clone())
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES);
        let caps = capabilities(&self.renderer);
        let resp = client
            .register(pb::RegisterRequest {
                name: self.config.name.clone(),
                capabilities: Some(caps),
            })
            .await
            .map_err(|s| match s.code() {
                tonic::Code::FailedPrecondition
                | tonic::Code::InvalidArgument
                | tonic::Code::Unauthenticated
                | tonic::Code::PermissionDenied => {
                    Some(WorkerError::Refused(s.message().to_string()))
                }
                _ => None,
            })?
            .into_inner();
        Ok(Session {
            client,
            worker_id: resp.worker_id,
            heartbeat: Duration::from_millis(resp.heartbeat_interval_ms.clamp(50, 60_000) as u64),
            lease_timeout: (resp.lease_timeout_ms > 0)
                .then(|| Duration::from_millis(resp.lease_timeout_ms.max(100) as u64)),
        })
    }

    /// Runs the render loop and the sender until drained (`Ok`) or the
    /// session breaks (`Err`).
    async fn work(
        &mut self,
        s: &Session,
        drain: &mut watch::Receiver<bool>,
        lost: &AtomicBool,
    ) -> Result<(), tonic::Status> {
        let (tx, rx) = mpsc::channel(SEND_QUEUE);
        let mut sender = tokio::spawn(send_results(
            s.client.clone(),
            s.worker_id.clone(),
            rx,
            self.held.clone(),
            self.units_done.clone(),
        ));
        let mut queue = VecDeque::new();
        let end = self
            .render_loop(s, drain, lost, &tx, &mut queue, &mut sender)
            .await;
        drop(tx);
        match end {
            Ok(()) => {
                // Drained: hand the prefetched leases back, then let the
                // sender deliver what is finished.
                return_leases(&mut s.client.clone(), &s.worker_id, &mut queue, &self.held).await;
                match sender.await {
                    Ok(r) => r,
                    Err(e) => Err(tonic::Status::internal(format!(
                        "result sender failed: {e}"
                    ))),
                }
            }
            Err(e) => {
                // Finished films still go out: the coordinator accepts those
                // whose leases still hold (a short outage loses no work) and
                // counts the others as late. The sender retries while the
                // coordinator is unreachable, for a while. A sender that
                // has ended was already joined by the render loop (its
                // error is `e`): a join handle may not be polled again.
                if !sender.is_finished()
                    && tokio::time::timeout(SENDER_GRACE, &mut sender)
                        .await
                        .is_err()
                {
                    sender.abort();
                }
                Err(e)
            }
        }
    }

    async fn render_loop(
        &mut self,
        s: &Session,
        drain: &mut watch::Receiver<bool>,
        lost: &AtomicBool,
        tx: &mpsc::Sender<Outgoing>,
        queue: &mut VecDeque<LeasedUnit>,
        sender: &mut tokio::task::JoinHandle<Result<(), tonic::Status>>,
    ) -> Result<(), tonic::Status> {
        let mut client = s.client.clone();
        // Units rendered since the last lease request, reported with the next.
        let mut rendered = Vec::new();
        loop {
            if *drain.borrow() {
                return Ok(());
            }
            if lost.load(Ordering::Relaxed) {
                return Err(tonic::Status::unavailable(
                    "the coordinator no longer knows this worker",
                ));
            }
            if sender.is_finished() {
                return match sender.await {
                    Ok(Err(e)) => Err(e),
                    _ => Err(tonic::Status::internal("the result sender stopped")),
                };
            }
            let Some(unit) = queue.pop_front() else {
                // Idle: wait at the coordinator for work (long poll).
                let retry_after = lease(
                    &mut client,
                    &s.worker_id,
                    &self.held,
                    queue,
                    false,
                    IDLE_LEASE_WAIT,
                    &mut rendered,
                )
                .await?;
                if queue.is_empty() {
                    tokio::select! {
                        _ = tokio::time::sleep(retry_after) => {}
                        _ = drain.changed() => {}
                    }
                }
                continue;
            };
            let Some((cancel, samples_done)) = self
                .held
                .lock()
                .expect("held lock")
                .get(&unit.lease_id)
                .map(|h| (h.cancel.clone(), h.samples_done.clone()))
            else {
                continue;
            };
            let LeasedUnit {
                lease_id,
                region,
                work,
                units,
            } = unit;
            let out = |end| Outgoing {
                lease_id: lease_id.clone(),
                region,
                end,
                units,
            };
            if cancel.load(Ordering::Relaxed) {
                // Gone while queued (expired, cancelled): nothing to send.
                self.held.lock().expect("held lock").remove(&lease_id);
                tracing::info!(lease = %lease_id, "lease gone; abandoned its unit");
                continue;
            }
            // A lease this worker cannot hold or send back (a coordinator
            // gone wrong), or one that came malformed: a failure the
            // coordinator counts, not an abort.
            let work = match too_large(region.rect).map_or(work, Err) {
                Ok(work) => work,
                Err(why) => {
                    tracing::warn!(lease = %lease_id, "{why}");
                    if tx.send(out(UnitEnd::Failed(why))).await.is_err() {
                        return Err(tonic::Status::internal("the result sender stopped"));
                    }
                    continue;
                }
            };
            let end = match self.prepare(&mut client, &work.job, region.frame).await {
                Err(e)
                    if e.code() == tonic::Code::Unavailable || e.code() == tonic::Code::Unknown =>
                {
                    return Err(e);
                }
                Err(e) => UnitEnd::Failed(e.message().to_string()),
                Ok(prepared) => {
                    let renderer = self.renderer.clone();
                    // Adaptive jobs: the round's active blocks.
                    let render = tokio::task::spawn_blocking(move || match work.active {
                        None => render_unit(&renderer, &prepared, region, &cancel, &samples_done),
                        Some(mask) => render_round_unit(
                            &renderer,
                            &prepared,
                            region.frame,
                            &mask,
                            region.samples,
                            &cancel,
                            &samples_done,
                        ),
                    });
                    let render = async {
                        render
                            .await
                            .unwrap_or_else(|e| UnitEnd::Failed(format!("render panicked: {e}")))
                    };
                    // Lease the next unit while this one renders, unless draining.
                    if queue.len() < PREFETCH && !*drain.borrow() {
                        // No long poll here: the result must not wait for work to appear.
                        let (end, leased) = tokio::join!(
                            render,
                            lease(
                                &mut client,
                                &s.worker_id,
                                &self.held,
                                queue,
                                true,
                                Duration::ZERO,
                                &mut rendered,
                            )
                        );
                        if let Err(e) = leased {
                            let _ = tx.send(out(end)).await;
                            return Err(e);
                        }
                        end
                    } else {
                        render.await
                    }
                }
            };
            if let UnitEnd::Film(film, seconds) = &end {
                tracing::debug!(lease = %lease_id, frame = region.frame, rect = ?region.rect, seconds, "unit rendered");
                rendered.push(pb::RenderedUnit {
                    lease_id: lease_id.clone(),
                    rays: film.rays.total(),
                    render_seconds: *seconds,
                });
            }
            if tx.send(out(end)).await.is_err() {
                return Err(tonic::Status::internal("the result sender stopped"));
            }
        }
    }

    /// The prepared frame `frame` of a unit's job, from cache or built
    /// from the (cached, content-addressed) scene.
    async fn prepare(
        &mut self,
        client: &mut Client,
        job: &JobInfo,
        frame: u32,
    ) -> Result<Arc<PreparedFrame>, tonic::Status> {
        let key = (job.job_id.clone(), frame);
        if let Some((_, p)) = self.prepared.iter().find(|(k, _)| *k == key) {
            return Ok(p.clone());
        }
        // The scene and its files, by hash, from the cache or the
        // coordinator; parsed from those bytes only (never from this disk).
        let scene_key = std::iter::once(job.scene_sha256.as_str())
            .chain(job.files.iter().flat_map(|(n, h)| [n.as_str(), h.as_str()]))
            .collect::<Vec<_>>()
            .join("\n");
        let scene = match self.scenes.iter().find(|(k, _)| *k == scene_key) {
            Some((_, s)) => s.clone(),
            None => {
                let content = self.fetch(client, &job.scene_sha256).await?;
                let text = String::from_utf8(content).map_err(|e| {
                    tonic::Status::invalid_argument(format!(
                        "{}: scene is not UTF-8: {e}",
                        job.scene_name
                    ))
                })?;
                let mut bundle = Bundle::new();
                for (name, sha256) in &job.files {
                    bundle.insert(name.clone(), self.fetch(client, sha256).await?);
                }
                let scene_name = job.scene_name.clone();
                let scene = tokio::task::spawn_blocking(move || {
                    SceneDesc::parse_from(&text, &scene_name, &bundle)
                })
                .await
                .map_err(|e| tonic::Status::internal(e.to_string()))?
                .map_err(|e| tonic::Status::invalid_argument(e.to_string()))?;
                let scene = Arc::new(scene);
                self.scenes.push_back((scene_key, scene.clone()));
                if self.scenes.len() > PREPARED_CACHE {
                    self.scenes.pop_front();
                }
                scene
            }
        };
        let settings = job.settings;
        let prepared = tokio::task::spawn_blocking(move || {
            PreparedFrame::build(&scene, &settings, frame, Precision::F32)
        })
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

impl Worker {
    /// A job file by hash: from the cache when its bytes still match,
    /// else streamed from the coordinator, checked and cached.
    async fn fetch(&self, client: &mut Client, sha256: &str) -> Result<Vec<u8>, tonic::Status> {
        let cache = self.cache.clone();
        let key = sha256.to_string();
        if let Some(data) = tokio::task::spawn_blocking(move || cache.get(&key))
            .await
            .map_err(|e| tonic::Status::internal(e.to_string()))?
        {
            return Ok(data);
        }
        let start = Instant::now();
        let mut stream = client
            .fetch_asset(pb::GetAssetRequest {
                sha256: sha256.to_string(),
            })
            .await?
            .into_inner();
        let mut data = Vec::new();
        let mut size = None;
        while let Some(chunk) = stream.message().await? {
            let declared = *size.get_or_insert(chunk.size);
            if chunk.offset != data.len() as u64
                || data.len() as u64 + chunk.data.len() as u64 > declared
            {
                return Err(tonic::Status::data_loss(format!(
                    "asset {sha256}: the coordinator sent a chunk out of order or past the declared {declared} bytes"
                )));
            }
            if data.is_empty() {
                // Bounded by what this machine can hold: an error, not an abort.
                data.try_reserve_exact(declared as usize).map_err(|_| {
                    tonic::Status::resource_exhausted(format!(
                        "asset {sha256} of {declared} bytes does not fit in this worker's memory"
                    ))
                })?;
            }
            data.extend_from_slice(&chunk.data);
        }
        let got = cache::sha256_hex(&data);
        if got != sha256 {
            // Transient as far as the worker can tell: the unit is retried.
            return Err(tonic::Status::data_loss(format!(
                "asset {sha256}: the {} bytes received hash to {got}",
                data.len()
            )));
        }
        tracing::info!(
            sha256,
            bytes = data.len(),
            seconds = start.elapsed().as_secs_f64(),
            "asset fetched"
        );
        let cache = self.cache.clone();
        let key = sha256.to_string();
        let data = tokio::task::spawn_blocking(move || {
            if let Err(e) = cache.put(&key, &data) {
                tracing::warn!(sha256 = %key, error = %e, "cannot cache a job file (rendering from memory)");
            }
            data
        })
        .await
        .map_err(|e| tonic::Status::internal(e.to_string()))?;
        Ok(data)
    }
}

/// Leases more work into `queue`, registering each lease with the heartbeat
/// before anything else can happen to it, each unit converted from the
/// wire's `WorkUnit`. Returns how long to wait when the coordinator had
/// nothing.
/// `ahead`: asked while a unit renders (the coordinator may say no at a
/// job's very end, to leave the last units to idle workers).
/// `rendered`: units finished since the last request, reported (and
/// taken) with it.
async fn lease(
    client: &mut Client,
    worker_id: &str,
    held: &HeldMap,
    queue: &mut VecDeque<LeasedUnit>,
    ahead: bool,
    wait: Duration,
    rendered: &mut Vec<pb::RenderedUnit>,
) -> Result<Duration, tonic::Status> {
    let req = pb::LeaseWorkRequest {
        worker_id: worker_id.to_string(),
        max_units: 1,
        wait_ms: wait.as_millis() as u32,
        ahead,
        rendered: std::mem::take(rendered),
    };
    let resp = client.lease_work(req).await?.into_inner();
    if !resp.refused.is_empty() {
        tracing::warn!(reason = %resp.refused, "the coordinator grants no lease");
    }
    let mut h = held.lock().expect("held lock");
    for unit in resp.units {
        h.insert(
            unit.lease_id.clone(),
            Held {
                cancel: Arc::default(),
                samples_done: Arc::default(),
            },
        );
        queue.push_back(LeasedUnit::from(unit));
    }
    Ok(Duration::from_millis(
        resp.retry_after_ms.clamp(10, 5000) as u64
    ))
}

/// Hands leased but unstarted units back on drain, so they are leased
/// again at once instead of after their leases expire.
async fn return_leases(
    client: &mut Client,
    worker_id: &str,
    queue: &mut VecDeque<LeasedUnit>,
    held: &HeldMap,
) {
    if queue.is_empty() {
        return;
    }
    let lease_ids: Vec<String> = queue.drain(..).map(|u| u.lease_id).collect();
    {
        let mut h = held.lock().expect("held lock");
        for id in &lease_ids {
            h.remove(id);
        }
    }
    let n = lease_ids.len();
    match client
        .return_leases(pb::ReturnLeasesRequest {
            worker_id: worker_id.to_string(),
            lease_ids,
        })
        .await
    {
        Ok(_) => tracing::info!(leases = n, "handed unstarted leases back"),
        // They expire on the coordinator instead.
        Err(e) => {
            tracing::warn!(leases = n, error = %e, "cannot hand leases back; they will expire")
        }
    }
}

/// Packs finished units and submits them, batching whatever is ready, with
/// up to [`SEND_IN_FLIGHT`] submissions at once: the coordinator records
/// queued results in one commit, so a fast worker's results do not wait
/// for each other's round trips (and its renderer for the queue).
/// A submission the coordinator could not record (`Unavailable`: its
/// database write failed, or the connection broke) is sent again with
/// backoff; the leases stay held (heartbeated) meanwhile.
async fn send_results(
    client: Client,
    worker_id: String,
    mut rx: mpsc::Receiver<Outgoing>,
    held: HeldMap,
    units_done: Arc<AtomicU64>,
) -> Result<(), tonic::Status> {
    let mut sending = tokio::task::JoinSet::new();
    let mut open = true;
    while open || !sending.is_empty() {
        tokio::select! {
            Some(done) = sending.join_next(), if !sending.is_empty() => {
                done.map_err(|e| tonic::Status::internal(format!("result submission failed: {e}")))??;
            }
            next = rx.recv(), if open && sending.len() < SEND_IN_FLIGHT => {
                let Some(first) = next else {
                    open = false;
                    continue;
                };
                // Film bytes in the original layout: an upper bound.
                let bytes_of = |o: &Outgoing| o.region.rect.area() * (film_codec::SUM_BYTES + film_codec::COUNT_BYTES);
                let mut bytes = bytes_of(&first);
                let mut batch = vec![first];
                while batch.len() < MAX_BATCH && bytes < MAX_BATCH_BYTES {
                    match rx.try_recv() {
                        Ok(o) => {
                            bytes += bytes_of(&o);
                            batch.push(o);
                        }
                        Err(_) => break,
                    }
                }
                sending.spawn(send_batch(
                    client.clone(),
                    worker_id.clone(),
                    batch,
                    held.clone(),
                    units_done.clone(),
                ));
            }
        }
    }
    Ok(())
}

/// Packs and submits one batch of finished units, then settles their leases.
async fn send_batch(
    mut client: Client,
    worker_id: String,
    batch: Vec<Outgoing>,
    held: HeldMap,
    units_done: Arc<AtomicU64>,
) -> Result<(), tonic::Status> {
    let mut sent = Vec::with_capacity(batch.len());
    for o in batch {
        match &o.end {
            UnitEnd::Abandoned => {
                tracing::info!(lease = %o.lease_id, "lease gone; abandoned its unit");
                held.lock().expect("held lock").remove(&o.lease_id);
            }
            UnitEnd::Failed(msg) => {
                tracing::warn!(lease = %o.lease_id, error = %msg, "unit failed");
                sent.push(o);
            }
            UnitEnd::Film(..) => sent.push(o),
        }
    }
    if sent.is_empty() {
        return Ok(());
    }
    let send_start = Instant::now();
    let outcomes = submit_with_retry(&mut client, sent.len(), || {
        sent.iter().map(|o| result_request(&worker_id, o)).collect()
    })
    .await?;
    let mut h = held.lock().expect("held lock");
    for (o, resp) in sent.iter().zip(outcomes) {
        h.remove(&o.lease_id);
        match pb::ResultOutcome::try_from(resp.outcome).unwrap_or(pb::ResultOutcome::Unspecified) {
            pb::ResultOutcome::Accepted => {
                // The job's units, as the coordinator counts them for
                // `tessera workers`: a lease may span several.
                units_done.fetch_add(o.units, Ordering::Relaxed);
                tracing::debug!(
                    lease = %o.lease_id,
                    frame = o.region.frame,
                    rect = ?o.region.rect,
                    batch = sent.len(),
                    // Transfer and the coordinator's intake.
                    send_ms = send_start.elapsed().as_secs_f64() * 1e3,
                    "result accepted"
                );
            }
            pb::ResultOutcome::FailureRecorded => {}
            other => {
                tracing::warn!(lease = %o.lease_id, outcome = ?other, reason = %resp.reason, "result not accepted")
            }
        }
    }
    Ok(())
}

/// A finished unit (a film or a failure) as a result request.
fn result_request(worker_id: &str, o: &Outgoing) -> pb::SubmitResultRequest {
    let mut req = pb::SubmitResultRequest {
        worker_id: worker_id.to_string(),
        lease_id: o.lease_id.clone(),
        rect: Some(o.region.rect.into()),
        samples: Some(o.region.samples.into()),
        ..Default::default()
    };
    match &o.end {
        UnitEnd::Abandoned => {}
        UnitEnd::Failed(msg) => req.failure = msg.clone(),
        UnitEnd::Film(film, secs) => {
            film.fill(&mut req);
            req.render_seconds = *secs;
        }
    }
    req
}

/// One result as `SubmitResult`, several as one `SubmitResults`; retried
/// while the coordinator answers `Unavailable`.
async fn submit_with_retry(
    client: &mut Client,
    count: usize,
    requests: impl Fn() -> Vec<pb::SubmitResultRequest>,
) -> Result<Vec<pb::SubmitResultResponse>, tonic::Status> {
    let mut backoff = Duration::from_millis(100);
    let mut tries = 0;
    loop {
        tries += 1;
        let mut reqs = requests();
        let sent = if count == 1 {
            client
                .submit_result(reqs.pop().expect("one request"))
                .await
                .map(|r| vec![r.into_inner()])
        } else {
            client
                .submit_results(pb::SubmitResultsRequest { results: reqs })
                .await
                .map(|r| r.into_inner().outcomes)
        };
        match sent {
            Ok(outcomes) if outcomes.len() == count => return Ok(outcomes),
            Ok(outcomes) => {
                return Err(tonic::Status::internal(format!(
                    "the coordinator answered {} outcomes for {count} results",
                    outcomes.len(),
                )));
            }
            Err(e) if e.code() == tonic::Code::Unavailable && tries < SUBMIT_TRIES => {
                tracing::warn!(results = count, error = %e.message(), retry_in_ms = backoff.as_millis() as u64, "results not recorded; sending them again");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(SUBMIT_BACKOFF_MAX);
            }
            Err(e) => return Err(e),
        }
    }
}

/// GPU bands: whole rows, about [`GPU_BAND_PIXEL_SAMPLES`] each.
fn gpu_band_rows(rect: Rect, samples: SampleRange) -> u32 {
    let per_row = rect.width.max(1) as u64 * samples.len().max(1) as u64;
    (GPU_BAND_PIXEL_SAMPLES / per_row).clamp(1, rect.height.max(1) as u64) as u32
}

/// Renders a unit, stopping early when `cancel` is set: on the CPU in one
/// pass, on the GPU band by band (one dispatch each).
// Without the `gpu` feature the CPU is the only renderer.
#[cfg_attr(not(feature = "gpu"), allow(irrefutable_let_patterns))]
fn render_unit(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    region: WorkRegion,
    cancel: &AtomicBool,
    samples_done: &AtomicU64,
) -> UnitEnd {
    let WorkRegion {
        frame,
        rect,
        samples,
    } = region;
    let start = Instant::now();
    let progress = |n| {
        samples_done.fetch_add(n, Ordering::Relaxed);
    };
    // The CPU renderer takes the whole unit in one parallel pass and
    // checks `cancel` before each of its tiles: bands would each end in a
    // barrier where one thread waits for another's last tile.
    if let Renderer::Cpu(r) = renderer {
        return match r.render_until(prepared, frame, rect, samples, &progress, cancel) {
            Ok(Some(film)) => rendered(&film, start),
            Ok(None) => UnitEnd::Abandoned,
            Err(e) => UnitEnd::Failed(e.to_string()),
        };
    }
    let rows = gpu_band_rows(rect, samples);
    // A unit of one band: packed on the GPU, only its bytes read back.
    #[cfg(feature = "gpu")]
    if let Renderer::Gpu(gpu) = renderer
        && rows >= rect.height
    {
        if cancel.load(Ordering::Relaxed) {
            return UnitEnd::Abandoned;
        }
        return match gpu.render_packed(prepared, frame, rect, samples, &progress) {
            Ok(p) => UnitEnd::Film(UnitFilm::of_gpu(p), start.elapsed().as_secs_f64()),
            Err(e) => UnitEnd::Failed(e.to_string()),
        };
    }
    let mut film = Film::new(rect);
    let mut y = rect.y;
    while y < rect.y + rect.height {
        if cancel.load(Ordering::Relaxed) {
            return UnitEnd::Abandoned;
        }
        let band = Rect::new(rect.x, y, rect.width, rows.min(rect.y + rect.height - y));
        match renderer.render(prepared, frame, band, samples, &progress) {
            // The whole unit in one call: no copy into the unit's film.
            Ok(part) if band == rect => {
                film = part;
            }
            Ok(part) => {
                if let Err(e) = film.merge(&part) {
                    return UnitEnd::Failed(e.to_string());
                }
            }
            Err(e) => return UnitEnd::Failed(e.to_string()),
        }
        y += band.height;
    }
    rendered(&film, start)
}

/// A rendered film, packed for the wire, with its render seconds (packing
/// not counted: the coordinator's speed model reads rendering alone).
fn rendered(film: &Film, start: Instant) -> UnitEnd {
    let seconds = start.elapsed().as_secs_f64();
    let pack_start = Instant::now();
    let film = UnitFilm::of_film(film);
    tracing::debug!(
        pack_ms = pack_start.elapsed().as_secs_f64() * 1e3,
        "unit packed"
    );
    UnitEnd::Film(film, seconds)
}

/// Renders a round of an adaptive unit: its active blocks, in one call
/// (`tracer_core::render::adaptive::render_round`), unless the lease is gone before
/// it starts (a round is short, so it is not cancelled midway).
fn render_round_unit(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    frame: u32,
    mask: &BlockMask,
    samples: SampleRange,
    cancel: &AtomicBool,
    samples_done: &AtomicU64,
) -> UnitEnd {
    if cancel.load(Ordering::Relaxed) {
        return UnitEnd::Abandoned;
    }
    let start = Instant::now();
    match tracer_core::render::adaptive::render_round(
        renderer,
        prepared,
        frame,
        mask,
        samples,
        &|n| {
            samples_done.fetch_add(n, Ordering::Relaxed);
        },
    ) {
        Ok(film) => rendered(&film, start),
        Err(e) => UnitEnd::Failed(e.to_string()),
    }
}

/// Sends heartbeats for held leases; cancels those the coordinator says are
/// gone. When no heartbeat has been answered for `lease_timeout`, every
/// lease has expired at the coordinator and gone to another worker: their
/// work stops, and the session ends (`lost`) to register again once the
/// coordinator answers. The time is this machine's, from the last answer,
/// so clocks that differ between machines do not matter.
async fn heartbeat(
    mut client: Client,
    worker_id: String,
    every: Duration,
    lease_timeout: Option<Duration>,
    held: HeldMap,
    lost: Arc<AtomicBool>,
) {
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut answered = Instant::now();
    loop {
        tick.tick().await;
        let leases: Vec<pb::LeaseProgress> = held
            .lock()
            .expect("held lock")
            .iter()
            .map(|(id, h)| pb::LeaseProgress {
                lease_id: id.clone(),
                samples_done: h.samples_done.load(Ordering::Relaxed),
            })
            .collect();
        let call = client.heartbeat(pb::HeartbeatRequest {
            worker_id: worker_id.clone(),
            leases,
        });
        // Across a partition a call gets no answer at all (no reset): bound
        // the wait so that the outage is noticed.
        match tokio::time::timeout(every.max(Duration::from_secs(1)), call).await {
            Err(_) => tracing::debug!("heartbeat got no answer"),
            Ok(Err(e)) => tracing::debug!(error = %e, "heartbeat failed"),
            Ok(Ok(resp)) => {
                answered = Instant::now();
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
        }
        if let Some(timeout) = lease_timeout
            && answered.elapsed() >= timeout
        {
            let held = held.lock().expect("held lock");
            tracing::warn!(
                silent_s = format!("{:.1}", answered.elapsed().as_secs_f64()),
                leases = held.len(),
                "no heartbeat answered for longer than the lease timeout: the leases have expired; stopping their work and registering again"
            );
            for h in held.values() {
                h.cancel.store(true, Ordering::Relaxed);
            }
            lost.store(true, Ordering::Relaxed);
            return;
        }
    }
}

// The one rule on missing prerequisites, shared with the test crates.
#[cfg(all(test, feature = "gpu"))]
#[path = "../../tests/support/prereq.rs"]
mod prereq;

#[cfg(test)]
mod tests {
    use super::*;
    use tracer_core::render::CpuRenderer;

    #[test]
    fn leases_too_large_to_send_back_are_refused_as_failures() {
        assert_eq!(too_large(Rect::new(0, 0, 1024, 1024)), None);
        let e = too_large(Rect::new(0, 0, 5000, 5000)).unwrap();
        assert_eq!(
            e,
            "a lease of 5000x5000 pixels makes a 700000000-byte result, over this worker's 268435456-byte message limit"
        );
    }

    /// A GPU unit is packed on the GPU ([`UnitFilm::of_gpu`]) into exactly
    /// the bytes the host packs from the same render's film: every sum
    /// width the sample counts give (4 to 6 bytes here), rects off the
    /// origin whose pixel count is not a multiple of the kernel's 4.
    #[cfg(feature = "gpu")]
    #[test]
    fn a_gpu_unit_is_packed_on_the_gpu_as_the_host_packs_its_film() {
        use tracer_core::render::{GpuOptions, GpuRenderer};
        let Some(gpu) = crate::prereq::require(
            "gpu",
            GpuRenderer::new(
                std::env::var("TESSERA_TEST_ADAPTER").ok().as_deref(),
                GpuOptions::default(),
            ),
        ) else {
            return;
        };
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../examples/resolution.toml");
        let desc = SceneDesc::load(path).unwrap();
        let mut settings = desc.render;
        (settings.width, settings.height, settings.samples) = (97, 61, 4000);
        let prepared = PreparedFrame::build(&desc, &settings, 0, Precision::F32).unwrap();
        let renderer = Renderer::Gpu(Box::new(gpu));
        let Renderer::Gpu(gpu) = &renderer else {
            unreachable!()
        };
        let mut widths = std::collections::BTreeSet::new();
        for (rect, samples) in [
            (Rect::new(0, 0, 97, 61), SampleRange { start: 0, end: 1 }),
            (Rect::new(3, 5, 31, 7), SampleRange { start: 2, end: 9 }),
            (Rect::new(10, 1, 13, 13), SampleRange { start: 0, end: 300 }),
            (
                Rect::new(40, 20, 9, 9),
                SampleRange {
                    start: 0,
                    end: 4000,
                },
            ),
        ] {
            let region = WorkRegion::new(0, rect, samples);
            let film = gpu.render(&prepared, 0, rect, samples, &|_| {}).unwrap();
            let want = UnitFilm::of_film(&film);
            let done = AtomicU64::new(0);
            match render_unit(&renderer, &prepared, region, &AtomicBool::new(false), &done) {
                UnitEnd::Film(got, _) => assert_eq!(got, want, "{rect:?} {samples:?}"),
                _ => panic!("the unit did not render"),
            }
            assert_eq!(
                done.load(Ordering::Relaxed),
                rect.area() as u64 * samples.len() as u64
            );
            widths.insert(want.packed.sum_bytes);
        }
        assert!(widths.len() >= 3, "sum widths covered: {widths:?}");
    }

    #[test]
    fn a_cpu_unit_renders_in_one_pass_and_stops_when_cancelled() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../examples/resolution.toml");
        let desc = SceneDesc::load(path).unwrap();
        let mut settings = desc.render;
        (settings.width, settings.height) = (96, 64);
        let prepared = PreparedFrame::build(&desc, &settings, 0, Precision::F32).unwrap();
        let renderer = Renderer::Cpu(CpuRenderer::new(Some(2)).unwrap());
        // A unit off the origin, not a whole number of renderer tiles.
        let rect = Rect::new(8, 4, 70, 50);
        let samples = SampleRange { start: 1, end: 3 };
        let want = renderer
            .render(&prepared, 0, rect, samples, &|_| {})
            .unwrap();
        let done = AtomicU64::new(0);
        let never = AtomicBool::new(false);
        let region = WorkRegion::new(0, rect, samples);
        match render_unit(&renderer, &prepared, region, &never, &done) {
            UnitEnd::Film(film, _) => assert_eq!(film, UnitFilm::of_film(&want)),
            _ => panic!("the unit did not render"),
        }
        assert_eq!(done.load(Ordering::Relaxed), rect.area() as u64 * 2);
        let cancelled = AtomicBool::new(true);
        let done = AtomicU64::new(0);
        assert!(matches!(
            render_unit(&renderer, &prepared, region, &cancelled, &done),
            UnitEnd::Abandoned
        ));
        assert_eq!(
            done.load(Ordering::Relaxed),
            0,
            "no tile rendered after the cancel"
        );
    }
}
