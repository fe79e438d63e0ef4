//! Workers as the monitor shows them: the farm forgets a worker that
//! stops sending heartbeats; the monitor remembers it a while longer and
//! shows it gone, so a worker that died is seen to have died.

use std::collections::{BTreeMap, HashMap};
use std::sync::Mutex;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use super::json::{HeldJson, WorkerJson};
use crate::farm::{LeaseSummary, WorkerView};

/// How long a gone worker stays on the page.
const GONE_KEPT: Duration = Duration::from_secs(3600);
/// At most this many gone workers are remembered (the oldest go first).
const GONE_MAX: usize = 200;

/// One worker's leases by (job, frame): (leases, pixels).
type Holding<'a> = BTreeMap<(&'a str, u32), (u32, u64)>;

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
                w.leases = 0;
                w.holding.clear();
                w.gone_unix_ms = Some(now);
            }
        }
        // worker -> (job, frame) -> (leases, pixels), in one pass.
        let mut by_worker: HashMap<&str, Holding> = HashMap::new();
        for l in leases {
            let e = by_worker
                .entry(l.worker_id.as_str())
                .or_default()
                .entry((l.job_id.as_str(), l.region.frame))
                .or_default();
            e.0 += 1;
            e.1 += l.region.rect.area() as u64;
        }
        for w in workers {
            let held: Vec<HeldJson> = by_worker
                .get(w.id.as_str())
                .into_iter()
                .flatten()
                .map(|(&(job, frame), &(leases, pixels))| HeldJson {
                    job: job.to_string(),
                    frame,
                    leases,
                    pixels,
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

#[cfg(test)]
mod tests {
    use super::*;
    use tracer_core::film::{Rect, SampleRange, WorkRegion};

    fn worker(id: &str, last_seen_unix_ms: i64) -> WorkerView {
        WorkerView {
            quarantined_until_unix_ms: 0,
            id: id.into(),
            name: format!("name-{id}"),
            threads: 1,
            backend: tracer_core::render::Backend::Cpu,
            gpu_name: String::new(),
            version: "0".into(),
            host_id: String::new(),
            leases: 0,
            units_done: 3,
            units_failed: 0,
            samples_per_second: 0.0,
            rays_per_second: 0.0,
            last_seen_unix_ms,
            labels: Default::default(),
            block_ranges: true,
        }
    }

    #[test]
    fn a_worker_the_farm_dropped_is_kept_as_gone_and_leases_are_summed_by_frame() {
        let r = Roster::default();
        let hb = Duration::from_secs(1);
        let now = now_ms();
        let lease = |frame, x| LeaseSummary {
            worker_id: "a".into(),
            job_id: "j".into(),
            region: WorkRegion::new(frame, Rect::new(x, 0, 8, 8), SampleRange::new(0, 4)),
            progress: 0,
        };
        let leases = [lease(1, 0), lease(1, 8), lease(2, 0)];
        let v = r.update(&[worker("a", now), worker("b", now - 10_000)], &leases, hb);
        let states: Vec<_> = v.iter().map(|w| (w.id.as_str(), w.state)).collect();
        assert_eq!(states, [("a", "rendering"), ("b", "silent")]);
        assert_eq!(v[0].leases, 3);
        let held: Vec<_> = v[0]
            .holding
            .iter()
            .map(|h| (h.frame, h.leases, h.pixels))
            .collect();
        assert_eq!(held, [(1, 2, 128), (2, 1, 64)]);

        let v = r.update(&[worker("a", now)], &[], hb);
        let states: Vec<_> = v.iter().map(|w| (w.id.as_str(), w.state)).collect();
        assert_eq!(states, [("a", "idle"), ("b", "gone")]);
        assert!(v[1].gone_unix_ms.is_some());
        assert_eq!(v[1].units_done, 3, "a gone worker keeps its last figures");
    }
}
