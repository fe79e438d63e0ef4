//! The heartbeat: extends every held lease and cancels those the
//! coordinator says are gone.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tessera_proto::pb;

use crate::Client;

/// A lease this worker holds (queued, rendering or being sent), as the
/// heartbeat sees it.
pub(crate) struct Held {
    pub(crate) cancel: Arc<AtomicBool>,
    pub(crate) samples_done: Arc<AtomicU64>,
}

pub(crate) type HeldMap = Arc<Mutex<HashMap<String, Held>>>;

/// Sends heartbeats for held leases; cancels those the coordinator says are
/// gone. When no heartbeat has been answered for `lease_timeout`, every
/// lease has expired at the coordinator and gone to another worker: their
/// work stops, and the session ends (`lost`) to register again once the
/// coordinator answers. The time is this machine's, from the last answer,
/// so clocks that differ between machines do not matter.
pub(crate) async fn heartbeat(
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
