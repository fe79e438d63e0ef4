//! A session with the coordinator: registering, then leasing units and
//! handing unstarted ones back on drain.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use tessera_proto::pb;
use tessera_proto::pb::worker_service_client::WorkerServiceClient;
use tessera_proto::transport::endpoint;
use tokio::sync::{mpsc, watch};
use tracer_core::render::Renderer;

use crate::heartbeat::{Held, HeldMap};
use crate::sender::send_results;
use tessera_proto::LeasedUnit;

use crate::unit::{self, Queued};
use crate::{Client, MAX_MESSAGE_BYTES, SEND_QUEUE, SENDER_GRACE, Worker, WorkerError};

pub(crate) struct Session {
    pub(crate) client: Client,
    pub(crate) worker_id: String,
    pub(crate) heartbeat: Duration,
    /// How long the coordinator keeps a lease without a heartbeat (`None`:
    /// it did not say).
    pub(crate) lease_timeout: Option<Duration>,
}

/// What this worker tells the coordinator it is.
pub(crate) fn capabilities(
    renderer: &Renderer,
    labels: &BTreeMap<String, String>,
) -> pb::Capabilities {
    pb::Capabilities {
        threads: renderer.threads() as u32,
        backend: pb::Backend::from(renderer.backend()) as i32,
        gpu_name: renderer.adapter_name().unwrap_or_default().to_string(),
        version: env!("CARGO_PKG_VERSION").into(),
        host_id: host_id(),
        labels: labels.clone().into_iter().collect(),
        block_ranges: true,
    }
}

/// The labels a worker reports of itself beside `backend` and `cores`
/// (which the coordinator sets from its capabilities): `host` (the host
/// name), `memory_gb` (the host's memory), and for a GPU worker `gpu` (the adapter's name) and, where
/// `nvidia-smi` reports the adapter, `gpu_memory_gb` (whole GiB). wgpu
/// does not tell an adapter's memory; elsewhere give it with `--label`.
pub(crate) fn automatic_labels(renderer: &Renderer) -> BTreeMap<String, String> {
    let mut labels = BTreeMap::new();
    let host = std::env::var("HOSTNAME")
        .ok()
        .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| tessera_proto::placement::check_label("host", h).is_ok());
    if let Some(h) = host {
        labels.insert("host".into(), h);
    }
    if let Some(gb) = host_memory_gb() {
        labels.insert("memory_gb".into(), gb.to_string());
    }
    if let Some(name) = renderer.adapter_name() {
        labels.insert("gpu".into(), name.to_string());
        if let Some(gb) = nvidia_memory_gb(name) {
            labels.insert("gpu_memory_gb".into(), gb.to_string());
        }
    }
    labels
}

/// This host's memory in whole GiB (`MemTotal` of /proc/meminfo; None
/// elsewhere): where a unit that ran out of memory may go next.
fn host_memory_gb() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let kib: u64 = info
        .lines()
        .find_map(|l| l.strip_prefix("MemTotal:"))?
        .split_whitespace()
        .next()?
        .parse()
        .ok()?;
    Some(kib >> 20)
}

/// The memory of the NVIDIA GPU named `adapter`, in whole GiB, as
/// `nvidia-smi` lists it (None without it, or when no row names it).
fn nvidia_memory_gb(adapter: &str) -> Option<u64> {
    let out = std::process::Command::new("nvidia-smi")
        .args([
            "--query-gpu=name,memory.total",
            "--format=csv,noheader,nounits",
        ])
        .stderr(std::process::Stdio::null())
        .output()
        .ok()
        .filter(|o| o.status.success())?;
    String::from_utf8_lossy(&out.stdout).lines().find_map(|l| {
        let (name, mib) = l.rsplit_once(',')?;
        let name = name.trim();
        (!name.is_empty() && (adapter.contains(name) || name.contains(adapter)))
            .then(|| mib.trim().parse::<u64>().ok().map(|m| m / 1024))
            .flatten()
    })
}

/// This machine, for the coordinator to tell workers that share one:
/// systemd's machine id, else the host name, else unknown (empty).
pub(crate) fn host_id() -> String {
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

impl Worker {
    /// `Err(None)`: transient, retry. `Err(Some)`: fatal.
    pub(crate) async fn connect(&self) -> Result<Session, Option<WorkerError>> {
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
        let caps = capabilities(&self.renderer, &self.config.labels);
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
    pub(crate) async fn work(
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
}

/// Leases more work into `queue`, registering each lease with the heartbeat
/// before anything else can happen to it, each unit converted from the
/// wire's `WorkUnit`. Returns how long to wait when the coordinator had
/// nothing.
/// `ahead`: asked while a unit renders (the coordinator may say no at a
/// job's very end, to leave the last units to idle workers).
/// `rendered`: units finished since the last request, reported (and
/// taken) with it.
pub(crate) async fn lease(
    client: &mut Client,
    worker_id: &str,
    held: &HeldMap,
    queue: &mut VecDeque<Queued>,
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
        queue.push_back(LeasedUnit::try_from(unit));
    }
    Ok(Duration::from_millis(
        resp.retry_after_ms.clamp(10, 5000) as u64
    ))
}

/// Hands leased but unstarted units back on drain, so they are leased
/// again at once instead of after their leases expire.
pub(crate) async fn return_leases(
    client: &mut Client,
    worker_id: &str,
    queue: &mut VecDeque<Queued>,
    held: &HeldMap,
) {
    if queue.is_empty() {
        return;
    }
    let lease_ids: Vec<String> = queue
        .drain(..)
        .map(|u| unit::lease_id(&u).to_string())
        .collect();
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
