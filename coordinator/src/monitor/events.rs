//! Live updates: server-sent events on `GET /api/events`. A viewer gets
//! an event `farm` (a [`SnapshotJson`]: every job, with its first page of
//! frames, and every worker) when it
//! connects, then an event `delta` (a [`DeltaJson`]: the jobs that
//! changed, each with only its frames that changed, the jobs gone, and the
//! workers when they changed) for each change; a viewer that fell behind
//! more than one change gets a `farm` event again. Nothing is sent while
//! nothing changes (the stream's keep-alive comments only).
//!
//! One task builds both, at most every [`TICK`] and only while someone
//! watches, and shares the strings with every viewer; ten viewers cost the
//! farm what one does. Each change used to send every job whole: a change
//! to a 100k-frame job sent its 6.3 MB to every viewer.

use std::collections::HashMap;
use std::convert::Infallible;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use serde::Serialize;
use tokio::sync::{Notify, mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt as _};

use super::Monitor;
use super::api::worker_rows;
use super::json::{FRAMES_PAGE, JobJson, SnapshotJson, WorkerJson};

/// How often the snapshot is rebuilt while someone watches.
const TICK: Duration = Duration::from_millis(500);

/// One build that changed something: the whole picture and the change
/// from the build before.
#[derive(Default)]
struct Built {
    /// Counts such builds (0: none yet).
    seq: u64,
    /// The `farm` event's data.
    full: Arc<str>,
    /// The `delta` event's data: from build `seq - 1` to this one.
    delta: Arc<str>,
}

/// What changed between two builds.
#[derive(Serialize)]
pub struct DeltaJson<'a> {
    /// Jobs new or changed, each with only its new or changed frames.
    pub jobs: Vec<JobJson>,
    /// Ids of jobs gone (deleted).
    pub removed: Vec<&'a str>,
    /// Every worker, when any changed; null when none did.
    pub workers: Option<&'a [WorkerJson]>,
}

pub struct Hub {
    tx: watch::Sender<Arc<Built>>,
    /// Rebuild now (a change made through the monitor, a new viewer).
    wake: Notify,
    pub built: AtomicU64,
}

impl Hub {
    pub fn new() -> Self {
        Hub {
            tx: watch::channel(Arc::new(Built::default())).0,
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

/// The last build's jobs and workers, to tell what changed.
#[derive(Default)]
struct Previous {
    jobs: Vec<JobJson>,
    workers: Vec<WorkerJson>,
}

/// The change from `prev` to `jobs`/`workers`; None when there is none.
fn delta(prev: &Previous, jobs: &[JobJson], workers: &[WorkerJson]) -> Option<String> {
    let before: HashMap<&str, &JobJson> = prev.jobs.iter().map(|j| (j.id.as_str(), j)).collect();
    let mut changed = Vec::new();
    for j in jobs {
        match before.get(j.id.as_str()) {
            Some(p) if *p == j => {}
            Some(p) => {
                // A job's frames are fixed at submit: compared in place.
                let frames = if p.frames.len() == j.frames.len() {
                    j.frames
                        .iter()
                        .zip(&p.frames)
                        .filter(|(a, b)| a != b)
                        .map(|(a, _)| a.clone())
                        .collect()
                } else {
                    j.frames.clone()
                };
                changed.push(JobJson {
                    frames,
                    ..j.clone()
                });
            }
            // A new job: its first page of frames, as in the snapshot.
            None => changed.push(j.paged(0, FRAMES_PAGE)),
        }
    }
    let now: std::collections::HashSet<&str> = jobs.iter().map(|j| j.id.as_str()).collect();
    let removed: Vec<&str> = prev
        .jobs
        .iter()
        .map(|j| j.id.as_str())
        .filter(|id| !now.contains(id))
        .collect();
    let workers = (prev.workers != workers).then_some(workers);
    if changed.is_empty() && removed.is_empty() && workers.is_none() {
        return None;
    }
    serde_json::to_string(&DeltaJson {
        jobs: changed,
        removed,
        workers,
    })
    .ok()
}

/// The builder; also keeps the roster current while nobody watches, so
/// a worker that leaves unwatched is still seen gone.
pub async fn run(m: Arc<Monitor>) {
    let mut tick = tokio::time::interval(TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut prev = Previous::default();
    // Whether `prev` is the last build's picture (a delta has a base).
    let mut based = false;
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = m.events.wake.notified() => {}
        }
        if m.events.viewers() == 0 {
            worker_rows(&m);
            prev = Previous::default();
            based = false;
            continue;
        }
        m.events.built.fetch_add(1, Ordering::Relaxed);
        let jobs: Vec<JobJson> = m.farm.jobs().iter().map(JobJson::from).collect();
        let workers = worker_rows(&m);
        let change = delta(&prev, &jobs, &workers);
        if based && change.is_none() {
            continue;
        }
        let seq = m.events.tx.borrow().seq;
        // Each job with its first page of frames (the rest come as they
        // change, or from /api/jobs/{id}?frames_from=).
        let paged = SnapshotJson {
            jobs: jobs.iter().map(|j| j.paged(0, FRAMES_PAGE)).collect(),
            workers,
        };
        let full: Arc<str> = Arc::from(serde_json::to_string(&paged).unwrap_or_default());
        let snap = SnapshotJson {
            jobs,
            workers: paged.workers,
        };
        m.events.tx.send_replace(Arc::new(Built {
            seq: seq + 1,
            full,
            // Without a base every viewer gets the whole picture.
            delta: Arc::from(if based {
                change.unwrap_or_default()
            } else {
                String::new()
            }),
        }));
        prev = Previous {
            jobs: snap.jobs,
            workers: snap.workers,
        };
        based = true;
    }
}

pub async fn sse(
    State(m): State<Arc<Monitor>>,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let mut rx = m.events.tx.subscribe();
    // The builder may have been idle: the last picture at once (if any),
    // then the changes as they come.
    m.events.poke();
    let (out, events) = mpsc::channel::<Event>(2);
    tokio::spawn(async move {
        // The build this viewer has (0: none).
        let mut mine = 0;
        loop {
            let b = rx.borrow_and_update().clone();
            if b.seq != 0 && b.seq != mine {
                let event = if mine != 0 && b.seq == mine + 1 && !b.delta.is_empty() {
                    Event::default().event("delta").data(&*b.delta)
                } else {
                    Event::default().event("farm").data(&*b.full)
                };
                if out.send(event).await.is_err() {
                    return;
                }
                mine = b.seq;
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
