//! Live updates: server-sent events on `GET /api/events`, each an event
//! `farm` whose data is a [`SnapshotJson`] (every job and worker).
//!
//! One task builds the snapshot, at most every [`TICK`] and only while
//! someone watches, and shares the one string with every viewer; ten
//! viewers cost the farm what one does. An unchanged snapshot is not sent
//! again.

use std::convert::Infallible;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use tokio::sync::{Notify, mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt as _};

use super::Monitor;
use super::api::worker_rows;
use super::json::{JobJson, SnapshotJson};

/// How often the snapshot is rebuilt while someone watches.
const TICK: Duration = Duration::from_millis(500);

pub struct Hub {
    /// The latest snapshot, serialised ("" before the first).
    tx: watch::Sender<Arc<str>>,
    /// Rebuild now (a change made through the monitor, a new viewer).
    wake: Notify,
    pub built: AtomicU64,
}

impl Hub {
    pub fn new() -> Self {
        Hub {
            tx: watch::channel(Arc::from("")).0,
            wake: Notify::new(),
            built: AtomicU64::new(0),
        }
    }

    /// Rebuilds the snapshot at once, not at the next tick.
    pub fn poke(&self) {
        self.wake.notify_one();
    }

    pub fn viewers(&self) -> usize {
        self.tx.receiver_count()
    }
}

fn snapshot(m: &Monitor) -> Arc<str> {
    m.events.built.fetch_add(1, Ordering::Relaxed);
    let snap = SnapshotJson {
        jobs: m.farm.jobs().iter().map(JobJson::from).collect(),
        workers: worker_rows(m),
    };
    Arc::from(serde_json::to_string(&snap).unwrap_or_default())
}

/// The snapshot builder; also keeps the roster current while nobody
/// watches, so a worker that leaves unwatched is still seen gone.
pub async fn run(m: Arc<Monitor>) {
    let mut tick = tokio::time::interval(TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = m.events.wake.notified() => {}
        }
        if m.events.viewers() == 0 {
            worker_rows(&m);
            continue;
        }
        let snap = snapshot(&m);
        m.events.tx.send_if_modified(|cur| {
            if **cur == *snap {
                false
            } else {
                *cur = snap;
                true
            }
        });
    }
}

pub async fn sse(
    State(m): State<Arc<Monitor>>,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let mut rx = m.events.tx.subscribe();
    // The builder may have been idle: the last snapshot at once (if any),
    // then a fresh one as soon as it differs.
    m.events.poke();
    let (out, events) = mpsc::channel::<Event>(2);
    tokio::spawn(async move {
        loop {
            let snap = rx.borrow_and_update().clone();
            if !snap.is_empty()
                && out
                    .send(Event::default().event("farm").data(&*snap))
                    .await
                    .is_err()
            {
                return;
            }
            tokio::select! {
                changed = rx.changed() => if changed.is_err() { return },
                // The viewer left: stop now, not at the next change.
                _ = out.closed() => return,
            }
        }
    });
    Sse::new(ReceiverStream::new(events).map(Ok)).keep_alive(KeepAlive::default())
}
