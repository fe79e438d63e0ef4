//! Workers as the monitor shows them: the farm forgets a worker that
//! stops sending heartbeats; the monitor remembers it a while longer and
//! shows it gone, so a worker that died is seen to have died.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use super::json::{LeaseJson, WorkerJson};
use crate::farm::{LeaseSummary, WorkerView};

/// How long a gone worker stays on the page.
const GONE_KEPT: Duration = Duration::from_secs(3600);
/// At most this many gone workers are remembered (the oldest go first).
const GONE_MAX: usize = 200;

#[derive(Default)]
pub struct Roster {
    /// Every worker seen, by id, with when it was seen gone.
    seen: Mutex<HashMap<String, (WorkerJson, Option<i64>)>>,
}

fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

impl Roster {
    /// The workers in the farm now (with their leases) and those that
    /// left, by name; records who left since the last call.
    pub fn update(
        &self,
        workers: &[WorkerView],
        leases: &[LeaseSummary],
        heartbeat: Duration,
    ) -> Vec<WorkerJson> {
        let now = now_ms();
        let silent_after = 3 * heartbeat.as_millis() as i64;
        let mut seen = self.seen.lock().expect("roster lock");
        for (_, (w, gone)) in seen.iter_mut() {
            if gone.is_none() {
                // Marked present below if it still is.
                *gone = Some(now);
                w.state = "gone";
                w.leases.clear();
                w.gone_unix_ms = Some(now);
            }
        }
        for w in workers {
            let held: Vec<LeaseJson> = leases
                .iter()
                .filter(|l| l.worker_id == w.id)
                .map(|l| LeaseJson {
                    job: l.job_id.clone(),
                    frame: l.frame,
                    rect: l.rect.into(),
                    samples: [l.samples.start, l.samples.end],
                })
                .collect();
            let state = if now - w.last_seen_unix_ms > silent_after {
                "silent"
            } else if !held.is_empty() {
                "rendering"
            } else {
                "idle"
            };
            seen.insert(w.id.clone(), (WorkerJson::new(w, state, held), None));
        }
        seen.retain(|_, (_, gone)| gone.is_none_or(|t| now - t < GONE_KEPT.as_millis() as i64));
        let mut gone: Vec<(i64, String)> = seen
            .iter()
            .filter_map(|(id, (_, g))| g.map(|t| (t, id.clone())))
            .collect();
        if gone.len() > GONE_MAX {
            gone.sort();
            for (_, id) in &gone[..gone.len() - GONE_MAX] {
                seen.remove(id);
            }
        }
        let mut v: Vec<WorkerJson> = seen.values().map(|(w, _)| w.clone()).collect();
        // Present workers first, each group by name.
        v.sort_by(|a, b| {
            (a.gone_unix_ms.is_some(), &a.name, &a.id).cmp(&(
                b.gone_unix_ms.is_some(),
                &b.name,
                &b.id,
            ))
        });
        v
    }
}
