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
//! Modules: [`session`] (register, lease, return leases), [`render`] (the
//! render loop), [`scenes`] (parsed scenes and prepared frames), [`sender`],
//! [`heartbeat`], [`cache`] (job files on disk), [`unit`] (a leased unit).
//!
//! A worker renders on CPU threads or, with [`Backend::Gpu`] (feature `gpu`),
//! on one GPU adapter through tracer-core's wgpu renderer. Either way a unit
//! yields the same fixed-point [`Film`] sums, so the coordinator merges
//! results from both kinds of worker alike.

pub mod cache;
mod heartbeat;
mod metrics;
mod render;
mod scenes;
mod sender;
mod session;
mod unit;

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use cache::AssetCache;
use heartbeat::{HeldMap, heartbeat};
use session::capabilities;
use tessera_proto::VersionStamp;
use tessera_proto::pb::worker_service_client::WorkerServiceClient;
use tessera_proto::transport::endpoint;
use tokio::sync::watch;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tracer_core::render::{Backend, PreparedFrame, Renderer, RendererError};
use tracer_core::scene::SceneDesc;

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
    /// `--label KEY=VALUE` (issue 38), already checked; the automatic
    /// labels (`session::automatic_labels`) are added to them.
    pub labels: std::collections::BTreeMap<String, String>,
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
    #[error("cannot serve metrics on --http {addr}: {message}")]
    Http { addr: String, message: String },
}

type Client = WorkerServiceClient<InterceptedService<Channel, VersionStamp>>;

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

impl Worker {
    pub fn new(mut config: WorkerConfig) -> Result<Self, WorkerError> {
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
        // Given labels win: `--label host=render07` names a machine whose
        // host name says little, `--label gpu_memory_gb=80` one whose GPU
        // memory cannot be read here.
        for (k, v) in session::automatic_labels(&renderer) {
            config.labels.entry(k).or_insert(v);
        }
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
            let caps = capabilities(&self.renderer, &self.config.labels);
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
}

// The one rule on missing prerequisites, shared with the test crates.
#[cfg(all(test, feature = "gpu"))]
#[path = "../../tests/support/prereq.rs"]
mod prereq;
