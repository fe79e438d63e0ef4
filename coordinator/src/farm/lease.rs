//! The leasing policy and the workers' side: register, leases sized in
//! expected rays by each worker's speed and held back near a job's end for
//! a faster worker, backup leases, the long-poll wait, heartbeats, leases
//! handed back, withdrawn or expired, and silent workers.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::time::{Duration, Instant};

use tessera_proto::LeasedUnit;
use tessera_proto::placement::meets;
use tracer_core::film::{Rect, WorkRegion};
use tracer_core::render::Backend;

use crate::rate::WorkerSpeed;

use super::{
    Farm, FarmError, Job, JobState, Lease, State, Worker, WorkerCaps, now_ms, public_worker_id,
    random_id,
};

/// The smallest lease, in seconds of the worker it goes to (unless the job
/// has less work left): below this a fast worker's fixed costs per lease
/// (a GPU call, read-back, a result message) outweigh its rendering.
const MIN_LEASE_SECONDS: f64 = 0.01;

/// The most pixels a lease covers. A result's way into the frame (transfer,
/// checks, commit, merge) costs about twice its rendering on a GPU (~75
/// against ~35 ns a pixel at 64 samples on the H200 box); a worker keeps
/// rendering while its results travel only if each is a few megabytes, not
/// half a frame (a 1080p frame's half is ~15 MB).
pub(super) const MAX_LEASE_PIXELS: u64 = 1 << 18;

/// How long an idle worker's lease request waits when work was held back
/// for a faster worker, before it is judged again.
const HELD_BACK_WAIT: Duration = Duration::from_millis(20);
/// A backup lease is granted only when its worker would finish it in less
/// than this share of the time the holder needs for the work it holds...
const BACKUP_GAIN: f64 = 0.5;
/// ...counting this much for the lease's fixed costs (a round trip, a
/// result message).
const BACKUP_OVERHEAD_SECONDS: f64 = 0.01;
/// Backups of one lease at most: a slow idle worker may take one before a
/// fast one asks, which must still be able to take another.
const MAX_BACKUPS: u32 = 2;
/// How long a worker's best speed of late counts for the farm's speed.
const PEAK_MEMORY_SECONDS: f64 = 60.0;
/// A unit that took this long measures its worker's speed: a GPU's fixed
/// cost per unit (a call, a read-back) is ~0.4 ms on the H200 box, so a
/// 64x64 tile there (0.4 ms in all) rates it several times too slow.
const MEASURING_UNIT_SECONDS: f64 = 0.002;
/// A GPU worker this many times as fast as a CPU worker on its machine
/// keeps that machine's cores: the CPU worker gets no work while it is
/// live. On the H200 box (16 vCPUs) the GPU worker alone beside 14 busy
/// render threads took 1.73x its time on an idle box, while seven CPU
/// workers there render 2-3% of a frame at its speed.
const SHARED_HOST_FASTER: f64 = 10.0;
/// A worker whose best speed is over this many times the asker's, but
/// measured only on small units, may be faster still: the asker takes one
/// unit at a time until it is measured.
const MUCH_FASTER: f64 = 2.0;

impl Lease {
    /// Expected rays not yet rendered, by the worker's last progress report.
    fn remaining_rays(&self) -> f64 {
        let total = self.region.pixel_samples() as f64;
        let left = 1.0 - (self.progress as f64 / total.max(1.0)).min(1.0);
        self.expected_rays * left
    }
}

impl Worker {
    /// The speed this worker adds to the farm's when others' leases are
    /// sized and held back: its best recent speed, relaxing to its
    /// smoothed speed over about [`PEAK_MEMORY_SECONDS`]. A GPU's small
    /// units (a job's tail, a warm-up) are mostly fixed cost, so its
    /// smoothed speed under-rates it, and CPU workers beside it would take
    /// leases that run past the point where it could have done their work.
    pub(super) fn farm_speed(&self) -> f64 {
        self.farm_speed_at(Instant::now())
    }

    /// [`Worker::farm_speed`] as of `now`.
    fn farm_speed_at(&self, now: Instant) -> f64 {
        if self.peak_speed <= self.ray_speed {
            return self.ray_speed;
        }
        let since = now.saturating_duration_since(self.peak_at).as_secs_f64();
        let k = (-since / PEAK_MEMORY_SECONDS).exp();
        self.ray_speed + (self.peak_speed - self.ray_speed).max(0.0) * k
    }

    /// Rates the worker from a unit it rendered: `rays` traced in
    /// `seconds`. For lease sizing the estimate drops at once and rises
    /// slowly (a lease that runs long costs the job's end more than one
    /// that runs short), except that a rise measured on a unit twice as
    /// large as the last is taken at once: small units understate a fast
    /// worker's speed (fixed costs per unit), larger ones measure it.
    pub(super) fn rate_unit(&mut self, rays: f64, seconds: f64) {
        // Times under 0.1 ms are taken as 0.1 ms, so an absurd report
        // (5e-324 s) gives a finite speed.
        let seconds = seconds.max(1e-4);
        let new = rays / seconds;
        let larger = rays >= 2.0 * self.last_rays;
        self.ray_speed = if self.ray_speed == 0.0 || new < self.ray_speed || larger {
            new
        } else {
            0.7 * self.ray_speed + 0.3 * new
        };
        self.last_rays = rays;
        self.last_seconds = seconds;
        if new >= self.farm_speed() {
            self.peak_speed = new;
            self.peak_at = Instant::now();
        }
    }

    /// Whether its last result measured its speed (see
    /// [`MEASURING_UNIT_SECONDS`]), not mostly its fixed cost per unit.
    fn speed_measured(&self) -> bool {
        self.last_seconds >= MEASURING_UNIT_SECONDS
    }

    /// Whether this worker, beside one whose best speed is `best`, may be
    /// much faster than its rating says: not measured yet while it renders
    /// (`holds_work`), or much faster already on units too small to
    /// measure it.
    fn may_be_much_faster(&self, best: f64, holds_work: bool) -> bool {
        if self.ray_speed == 0.0 {
            holds_work
        } else {
            !self.speed_measured() && self.farm_speed() > MUCH_FASTER * best
        }
    }
}

impl State {
    /// Whether the CPU worker `worker_id`, at its best speed `best`, gets
    /// no work because a GPU worker [`SHARED_HOST_FASTER`] times as fast,
    /// live (seen within `live`), runs on its machine. Only once measured:
    /// rated against nothing, any GPU would look ten times as fast.
    fn cedes_machine_to_a_gpu(&self, worker_id: &str, best: f64, live: Duration) -> bool {
        let Some(me) = self.workers.get(worker_id) else {
            return false;
        };
        me.backend == Backend::Cpu
            && !me.host_id.is_empty()
            && best > 0.0
            && self.workers.iter().any(|(id, w)| {
                id.as_str() != worker_id
                    && w.backend == Backend::Gpu
                    && w.host_id == me.host_id
                    && w.last_seen.elapsed() < live
                    && w.ray_speed > 0.0
                    && w.farm_speed() >= SHARED_HOST_FASTER * best
            })
    }
}

/// The work a lease gets, in expected rays: `want` (the worker's target
/// seconds of work at its `speed` in rays a second, or its ramp), except
/// near a job's end. A lease ends by half the farm's remaining time
/// (`farm_end` seconds; infinite while the farm is far from the end),
/// after the `busy` seconds of work the worker holds, so that the last
/// leases are small and finish together; never below MIN_LEASE_SECONDS of
/// work, which keeps a fast worker's fixed costs per lease small.
fn lease_budget(want: f64, speed: f64, busy: f64, farm_end: f64) -> f64 {
    let until_end = (0.5 * farm_end - busy).max(MIN_LEASE_SECONDS);
    want.min(speed * until_end)
}

/// What the leasing policy decides for one unit of a job.
enum Pick {
    /// Lease these units (the first, joined with neighbours).
    Units(Vec<u32>),
    /// Leave the unit to a faster worker, expected to finish it sooner.
    HoldBack,
    /// The asker is not measured yet: the caller decides (one tile, or
    /// nothing while measured workers exist).
    Wait,
}

/// A measured live other worker near a job's end: its speed, the seconds
/// of work it holds, its labels.
type Held<'a> = (f64, f64, &'a BTreeMap<String, String>);

/// What the leasing policy reads of the farm for one lease request,
/// taken once under the farm's lock: the asker's speeds and labels, the
/// live others, the work in flight per job. Read only: `Farm::grant`
/// makes the state changes.
struct Policy<'a> {
    worker_id: &'a str,
    labels: &'a BTreeMap<String, String>,
    /// The asker's smoothed speed (rays a second; 0 until measured), its
    /// best of late (never below it) and its ramp: while its last lease
    /// took under a quarter of the target, the next may be eight times as
    /// large (0: no ramp).
    speed: f64,
    best: f64,
    ramp: f64,
    /// The sum of the live workers' measured speeds (a worker not yet
    /// measured adds nothing until its first result; one gone silent
    /// adds nothing either).
    farm_speed: f64,
    /// A live other may be much faster than its rating: one unit at a time.
    one_at_a_time: bool,
    /// Per job: rays still to trace in its leases, and the leases' whole
    /// expected rays.
    in_flight_of: HashMap<String, (f64, f64)>,
    /// The measured live others as (speed, worker).
    others: Vec<(f64, &'a Worker)>,
    leases: &'a HashMap<String, Lease>,
    /// (speed, seconds of work held, labels) of each of `others`: read
    /// only near a job's end (the hold-back rule).
    others_held: std::cell::OnceCell<Vec<Held<'a>>>,
    /// Workers registered, live or not.
    workers: usize,
    target_unit_seconds: f64,
    max_tiles_per_lease: u32,
}

impl<'a> Policy<'a> {
    /// The policy's view for `worker_id` (registered) among `workers`,
    /// those seen within `live` counting as live.
    fn new(
        workers: &'a HashMap<String, Worker>,
        leases: &'a HashMap<String, Lease>,
        worker_id: &'a str,
        live: Duration,
        config: &super::Config,
    ) -> Self {
        let worker = &workers[worker_id];
        let speed = worker.ray_speed;
        // This worker at its best (never below `speed`), as the others are
        // rated when it is held back for them: rated on one scale, the
        // worker that would finish first is never held back, so not all
        // of them are.
        let best = worker.farm_speed();
        // A worker's speed is measured on small leases first, where fixed
        // costs (a GPU call, a result message) weigh most: while its last
        // lease took under a quarter of the target, the next may be eight
        // times as large, so a GPU reaches frame-sized leases within a few.
        let ramp = if worker.last_seconds > 0.0
            && worker.last_seconds < 0.25 * config.target_unit_seconds
        {
            8.0 * worker.last_rays
        } else {
            0.0
        };
        // Per job: rays still to trace in its leases, and the leases'
        // whole expected rays (one pass, compared with the few jobs' ids).
        let mut in_flight: Vec<(&str, f64, f64)> = Vec::new();
        for l in leases.values().filter(|l| !l.backup) {
            // A backup's units are in flight under the original.
            let left = l.remaining_rays();
            match in_flight.iter_mut().find(|e| e.0 == l.job) {
                Some(e) => {
                    e.1 += left;
                    e.2 += l.expected_rays;
                }
                None => in_flight.push((l.job.as_str(), left, l.expected_rays)),
            }
        }
        let in_flight_of = in_flight
            .into_iter()
            .map(|(j, a, b)| (j.to_string(), (a, b)))
            .collect();
        // One pass over the workers, with one clock reading: the measured
        // live others as (speed, worker), and whether one of them may be
        // much faster than its rating. Leases sized against a worker that
        // may be much faster than its rating would run past the point
        // where it could have done their work. The first leases of a job
        // beside a GPU measured only on a warm-up's small tiles (rated ~8x
        // low) made a mixed farm 1.3-1.6x slower than the GPU alone: while
        // such a worker exists, this one takes one unit at a time (the
        // other measures itself within its first lease or two).
        let now = Instant::now();
        let mut others: Vec<(f64, &Worker)> = Vec::with_capacity(workers.len());
        let mut one_at_a_time = false;
        for w in workers.values() {
            if std::ptr::eq(w, worker) || now.saturating_duration_since(w.last_seen) >= live {
                continue;
            }
            one_at_a_time = one_at_a_time || w.may_be_much_faster(best, !w.leases.is_empty());
            if w.ray_speed > 0.0 {
                others.push((w.farm_speed_at(now), w));
            }
        }
        Policy {
            worker_id,
            labels: &worker.labels,
            speed,
            best,
            ramp,
            farm_speed: speed + others.iter().map(|&(v, _)| v).sum::<f64>(),
            one_at_a_time,
            in_flight_of,
            others,
            leases,
            others_held: std::cell::OnceCell::new(),
            workers: workers.len(),
            target_unit_seconds: config.target_unit_seconds,
            max_tiles_per_lease: config.max_tiles_per_lease,
        }
    }

    /// Rays still to trace in a worker's leases (those it renders or has
    /// queued), from its own lease set. This runs for every lease under
    /// the farm's lock: a pass over every lease into maps keyed by worker
    /// cost about 0.3 ms a lease at 2,000 workers (`tessera bench scale`),
    /// so the others' are summed only where a rule reads them.
    fn held_rays_of(w: &Worker, leases: &HashMap<String, Lease>) -> f64 {
        w.leases
            .iter()
            .filter_map(|id| leases.get(id))
            .map(Lease::remaining_rays)
            .sum()
    }

    fn others_held(&self) -> &[Held<'a>] {
        self.others_held.get_or_init(|| {
            self.others
                .iter()
                .map(|&(v, w)| (v, Self::held_rays_of(w, self.leases) / v, &w.labels))
                .collect()
        })
    }

    /// The units of `job` to lease from its pending unit `first`, for an
    /// asker holding `busy` seconds of work: about the target seconds of
    /// work at its speed (or its ramp), neighbouring tiles joined, less
    /// near the job's end, where a unit another worker would finish sooner
    /// is held back for it.
    fn units(&self, farm: &Farm, job_id: &str, job: &Job, first: u32, busy: f64) -> Pick {
        let (speed, farm_speed) = (self.speed, self.farm_speed);
        if !(speed > 0.0 && farm_speed > 0.0) {
            return Pick::Wait;
        }
        // Rays of the job's leases still being rendered, by anyone.
        let (in_flight, leased) = self.in_flight_of.get(job_id).copied().unwrap_or((0.0, 0.0));
        let rays = |u: u32| job.unit_work(u);
        let want = (speed * self.target_unit_seconds).max(self.ramp);
        // When the farm, every worker at its measured speed, would finish
        // the job (pending and in-flight work). Beyond `enough` no rule
        // below can bind. This runs for every lease, under the lock, and a
        // long animation has millions of pending units: no pass over them.
        let enough = farm_speed * (2.0 * (want / speed + busy) + rays(first) / speed);
        let remaining = if job.adaptive.is_none() {
            // A uniform job's units not done are pending or leased: its
            // pending work without a pass over them.
            in_flight + (job.work_left - leased).max(0.0)
        } else {
            // Later rounds are not pending yet: only the pending.
            let mut r = in_flight;
            for &u in &job.pending {
                r += rays(u);
                if r >= enough {
                    break;
                }
            }
            r
        };
        let farm_end = if remaining < enough {
            remaining / farm_speed
        } else {
            f64::INFINITY
        };
        // Leases go by expected finish time: near a job's end (when the
        // farm would finish before this worker could finish the next unit)
        // a unit goes to this worker only if no other would finish it
        // sooner, after the work it holds. Otherwise it waits for that
        // worker.
        let finish = busy + rays(first) / speed;
        let finish_at_best = (busy * speed + rays(first)) / self.best;
        // Held back only for a worker that may take the job.
        if finish > farm_end
            && self.others_held().iter().any(|&(v, b, l)| {
                b + rays(first) / v < finish_at_best && meets(&job.rec.requirements, l)
            })
        {
            return Pick::HoldBack;
        }
        let budget = lease_budget(want, speed, busy, farm_end);
        // A lease's result must fit one message, and be small enough to
        // travel while the next is rendered.
        let tile = u64::from(job.layout.tile_size).pow(2).max(1);
        let fit = (farm.max_result_pixels().min(MAX_LEASE_PIXELS) / tile)
            .clamp(1, u64::from(u32::MAX)) as u32;
        let max_tiles = if self.one_at_a_time {
            1
        } else {
            self.max_tiles_per_lease.min(fit)
        };
        let worker_id = self.worker_id;
        Pick::Units(job.layout.join(
            first,
            max_tiles,
            |u| job.pending.contains(&u) && job.admits(u, worker_id, self.labels),
            rays,
            budget,
        ))
    }
}

impl Farm {
    /// A worker joins: its session (128 random bits that only it learns).
    /// Its labels are what it sent, `backend` and `cores` set from its
    /// capabilities (what leases rely on cannot be misnamed by hand) and
    /// `gpu` from its adapter when it sent none.
    pub fn register(&self, name: String, caps: WorkerCaps) -> String {
        let WorkerCaps {
            threads,
            backend,
            gpu_name,
            version,
            host_id,
            mut labels,
            block_ranges,
        } = caps;
        labels.insert("backend".into(), backend.name().into());
        labels.insert("cores".into(), threads.to_string());
        if !gpu_name.is_empty() {
            labels
                .entry("gpu".into())
                .or_insert_with(|| gpu_name.clone());
        }
        let id = random_id("w");
        let mut st = self.state.lock().expect("state lock");
        tracing::info!(worker = %public_worker_id(&id), name = %name, threads, backend = %backend,
            labels = %labels.iter().map(|(k, v)| format!("{k}={v}")).collect::<Vec<_>>().join(","),
            "worker joined");
        st.workers.insert(
            id.clone(),
            Worker {
                name,
                threads,
                backend,
                gpu_name,
                version,
                host_id,
                labels,
                block_ranges,
                last_seen: Instant::now(),
                leases: HashSet::new(),
                units_done: 0,
                units_failed: 0,
                speed: WorkerSpeed::default(),
                ray_speed: 0.0,
                last_rays: 0.0,
                last_seconds: 0.0,
                peak_speed: 0.0,
                peak_at: Instant::now(),
                malformed_in_a_row: 0,
                quarantined_until: None,
            },
        );
        // Jobs that waited for a worker like it say so no more.
        for j in st.jobs.values().filter(|j| !j.rec.requirements.is_empty()) {
            j.notify();
        }
        id
    }

    /// How much longer worker session `worker_id` is quarantined (None:
    /// it is not, or not known).
    pub fn quarantined_for(&self, worker_id: &str) -> Option<Duration> {
        let st = self.state.lock().expect("state lock");
        let until = st.workers.get(worker_id)?.quarantined_until?;
        let left = until.saturating_duration_since(Instant::now());
        (!left.is_zero()).then_some(left)
    }

    /// Quarantines a worker whose results failed validation
    /// `quarantine_after` times in a row: every lease it holds goes back
    /// to the queue (no failed attempt counted: its work was never
    /// checked) and it gets no lease for `quarantine_for`. A broken or
    /// hostile worker so costs the farm a few leases, not a job.
    pub(super) fn quarantine(&self, st: &mut State, worker_id: &str) {
        let Some(w) = st.workers.get_mut(worker_id) else {
            return;
        };
        let strikes = w.malformed_in_a_row;
        w.malformed_in_a_row = 0;
        w.quarantined_until = Some(Instant::now() + self.config.quarantine_for);
        let leases: Vec<String> = w.leases.drain().collect();
        tracing::warn!(
            worker = %public_worker_id(worker_id), name = %w.name, malformed_in_a_row = strikes,
            seconds = self.config.quarantine_for.as_secs_f64(), leases_revoked = leases.len(),
            "worker quarantined: its results failed validation {strikes} times in a row; its leases go to other workers and it gets none until the quarantine ends"
        );
        for id in leases {
            let Some(l) = st.leases.remove(&id) else {
                continue;
            };
            if !st.partner_keeps(&id, &l)
                && let Some(job) = st.jobs.get_mut(&l.job).filter(|j| !j.state.is_terminal())
            {
                job.pending.extend(l.units.iter().copied());
            }
            st.end_lease(id, l.job, false);
        }
        self.work_ready.notify_waiters();
    }

    /// Rates a worker from units it reports rendered with its lease
    /// request (lease id, rays, render seconds), before their results are
    /// taken in: a GPU worker's results took 20-60 ms to be taken in on a
    /// busy coordinator, while CPU workers' leases were sized against its
    /// rating of the job before. Units of leases it does not hold, and
    /// units rated already, are ignored; the result of a rated unit does
    /// not rate it again.
    pub fn rate_rendered(&self, worker_id: &str, units: &[(String, u64, f64)]) {
        let mut st = self.state.lock().expect("state lock");
        let st = &mut *st;
        let Some(w) = st.workers.get_mut(worker_id) else {
            return;
        };
        for (lease_id, rays, seconds) in units {
            let Some(l) = st.leases.get_mut(lease_id) else {
                continue;
            };
            if l.worker != worker_id || l.rated || !(*seconds > 0.0) {
                continue;
            }
            l.rated = true;
            // Rendered: none of its work is left for the worker, which is
            // free for more (and is no longer busy to the others' leases).
            l.progress = l.region.pixel_samples();
            w.rate_unit(*rays as f64, *seconds);
        }
    }

    /// Leases up to `max_units` units to a worker, highest priority first,
    /// joining neighbouring tiles into one lease for fast workers. `ahead`:
    /// the worker is still rendering and asks for its next unit early.
    pub fn lease(
        &self,
        worker_id: &str,
        max_units: u32,
        ahead: bool,
    ) -> Result<Vec<LeasedUnit>, FarmError> {
        self.lease_or_hold(worker_id, max_units, ahead)
            .map(|(leases, _)| leases)
    }

    /// As [`Farm::lease`]; also says whether work was held back because a
    /// faster worker is expected to finish it sooner (the asker should ask
    /// again soon rather than wait for new work).
    pub(super) fn lease_or_hold(
        &self,
        worker_id: &str,
        max_units: u32,
        ahead: bool,
    ) -> Result<(Vec<LeasedUnit>, bool), FarmError> {
        let mut st = self.state.lock().expect("state lock");
        let st = &mut *st;
        let worker = st
            .workers
            .get_mut(worker_id)
            .ok_or_else(|| unknown_worker(worker_id))?;
        worker.last_seen = Instant::now();
        let block_ranges = worker.block_ranges;
        match worker.quarantined_until {
            Some(until) if until > Instant::now() => return Ok((Vec::new(), false)),
            Some(_) => {
                worker.quarantined_until = None;
                tracing::info!(worker = %public_worker_id(worker_id), name = %worker.name, "worker's quarantine ended");
            }
            None => {}
        }
        // No new work while results cannot be recorded: workers wait
        // instead of rendering units whose results would be refused.
        if !self.store.health.ok() {
            return Ok((Vec::new(), false));
        }
        let best = worker.farm_speed();
        // Workers silent for two heartbeats may be gone: no work waits for them.
        let live = 2 * self.config.heartbeat_interval;
        if st.cedes_machine_to_a_gpu(worker_id, best, live) {
            return Ok((Vec::new(), false));
        }
        let policy = Policy::new(&st.workers, &st.leases, worker_id, live, &self.config);
        let speed = policy.speed;
        // Seconds of work this worker holds already, at its speed.
        let mut busy = if speed > 0.0 {
            Policy::held_rays_of(&st.workers[worker_id], &st.leases) / speed
        } else {
            0.0
        };
        let mut order: Vec<(&String, &Job)> = st
            .jobs
            .iter_mut()
            .filter(|(_, j)| j.state.leasable() && !j.pending.is_empty())
            .filter(|(_, j)| meets(&j.rec.requirements, policy.labels))
            // An older worker cannot render the image mode's block ranges.
            .filter(|(_, j)| block_ranges || !j.image_mode())
            .filter_map(|(id, j)| (!j.blocks(worker_id)).then_some((id, &*j)))
            .collect();
        order.sort_by_key(|(_, j)| (-(j.rec.priority as i64), j.rec.submitted_unix_ms));
        let order: Vec<String> = order.into_iter().map(|(id, _)| id.clone()).collect();
        let max_units = if policy.one_at_a_time {
            1
        } else {
            max_units.max(1)
        };
        let mut held_back = false;
        let mut out = Vec::new();
        // Added to `st.leases` after the loop, which reads the others'.
        let mut new_leases = Vec::new();
        'jobs: for job_id in order {
            while out.len() < max_units as usize {
                let job = st.jobs.get_mut(&job_id).expect("listed job");
                // The first pending unit this worker may take (one rerouted
                // after a failure may want another: `Job::reroute`).
                let first = if job.reroutes.is_empty() {
                    job.pending.iter().next()
                } else {
                    job.pending
                        .iter()
                        .find(|&&u| job.admits(u, worker_id, policy.labels))
                };
                let Some(&first) = first else {
                    break;
                };
                let units = match policy.units(self, &job_id, job, first, busy) {
                    Pick::Units(units) => units,
                    Pick::HoldBack => {
                        held_back = true;
                        break;
                    }
                    Pick::Wait => {
                        // Not measured yet: one tile, whose result measures
                        // it. Once measured workers exist, an unmeasured one
                        // asking ahead waits (its first tile may be slow).
                        if (ahead || !out.is_empty()) && job.pending.len() < policy.workers {
                            break;
                        }
                        vec![first]
                    }
                };
                let (view, lease) = self.grant(job, &job_id, worker_id, units);
                if speed > 0.0 {
                    busy += lease.expected_rays / speed;
                }
                new_leases.push((view.lease_id.clone(), lease));
                out.push(view);
            }
            if out.len() >= max_units as usize {
                break 'jobs;
            }
        }
        st.leases.extend(new_leases);
        let held = &mut st
            .workers
            .get_mut(worker_id)
            .expect("worker checked")
            .leases;
        held.extend(out.iter().map(|l| l.lease_id.clone()));
        if out.is_empty() && !held_back && speed > 0.0 {
            // At its best: a GPU's last units (a job's tail) rate it low.
            out.extend(self.backup_lease(st, worker_id, best, busy));
        }
        Ok((out, held_back))
    }

    /// A lease of `units` (first the unit the policy picked; neighbouring
    /// tiles of one frame and batch) of job `job_id` for `worker_id`: the
    /// units leave the job's pending set, the job starts running. The state
    /// changes of leasing, apart from the policy ([`Policy::units`]).
    fn grant(
        &self,
        job: &mut Job,
        job_id: &str,
        worker_id: &str,
        units: Vec<u32>,
    ) -> (LeasedUnit, Lease) {
        let expected_rays: f64 = units.iter().map(|&u| job.unit_work(u)).sum();
        for u in &units {
            job.pending.remove(u);
        }
        let u0 = job.layout.unit(units[0]);
        let t0 = job.layout.tiles[u0.tile as usize];
        let t1 = job.layout.tiles[job.layout.unit(*units.last().expect("non-empty")).tile as usize];
        let rect = Rect::new(t0.x, t0.y, t1.x + t1.width - t0.x, t1.y + t1.height - t0.y);
        let (region, active, ranges) = if job.image_mode() {
            let (mask, ranges, hull) = job.image_ranges(u0.frame, rect);
            (
                WorkRegion::new(u0.frame, rect, hull),
                Some(mask),
                Some(ranges),
            )
        } else {
            (
                WorkRegion::new(u0.frame, rect, job.layout.batches[u0.batch as usize]),
                job.adaptive_mask(u0.frame, rect, u0.batch),
                None,
            )
        };
        if job.state == JobState::Queued {
            job.state = JobState::Running;
            job.notify();
        }
        if job.started.is_none() {
            job.started = Some(Instant::now());
        }
        if job.first_lease_unix_ms == 0 {
            job.first_lease_unix_ms = now_ms();
        }
        job.meter.start(Instant::now());
        let view = LeasedUnit {
            lease_id: random_id("l"),
            job: job.leased(job_id),
            region,
            active: active.clone(),
            ranges: ranges.clone(),
            units: units.len() as u32,
        };
        let lease = Lease {
            worker: worker_id.to_string(),
            job: job_id.to_string(),
            units,
            region,
            deadline: Instant::now() + self.config.lease_timeout,
            progress: 0,
            expected_rays,
            active,
            ranges,
            partners: Vec::new(),
            backup: false,
            backups: 0,
            rated: false,
        };
        (view, lease)
    }

    /// Nothing is pending: a lease of another worker that this one would
    /// finish in well under the time that worker needs for the work it
    /// holds (a GPU beside CPU workers at a job's end, or a worker slowed
    /// down), duplicated as a backup. The units are deterministic, so
    /// whichever result comes first is the image; the other lease is then
    /// withdrawn. A mixed farm is so never slower than its fastest worker.
    fn backup_lease(
        &self,
        st: &mut State,
        worker_id: &str,
        speed: f64,
        busy: f64,
    ) -> Option<LeasedUnit> {
        // Seconds of held work of each worker, at its measured speed.
        let mut held: HashMap<&str, f64> = HashMap::new();
        for l in st.leases.values() {
            *held.entry(l.worker.as_str()).or_default() += l.remaining_rays();
        }
        // When a worker would be through the work it holds (a holder not
        // yet measured may be of any speed).
        let through = |worker: &str| {
            let speed = st.workers.get(worker).map_or(0.0, |w| w.ray_speed);
            if speed > 0.0 {
                held.get(worker).copied().unwrap_or(0.0) / speed
            } else {
                f64::INFINITY
            }
        };
        let labels = &st.workers.get(worker_id)?.labels;
        let block_ranges = st.workers.get(worker_id)?.block_ranges;
        let mut best: Option<(f64, String)> = None;
        for (id, l) in &st.leases {
            if l.backup
                || l.backups >= MAX_BACKUPS
                || st.jobs.get(&l.job).is_none_or(|j| {
                    j.state.is_terminal()
                        || !meets(&j.rec.requirements, labels)
                        || (!block_ranges && j.image_mode())
                        || l.units.iter().any(|&u| !j.admits(u, worker_id, labels))
                        || j.worker_failures
                            .get(worker_id)
                            .and_then(|f| f.blocked_until)
                            .is_some_and(|t| t > Instant::now())
                })
            {
                continue;
            }
            // The soonest any copy of the lease is expected to be done.
            let mut theirs = through(&l.worker);
            let mut mine_already = l.worker == worker_id;
            for p in l.partners.iter().filter_map(|p| st.leases.get(p)) {
                theirs = theirs.min(through(&p.worker));
                mine_already |= p.worker == worker_id;
            }
            if mine_already {
                continue;
            }
            let mine = busy + l.expected_rays / speed + BACKUP_OVERHEAD_SECONDS;
            if mine < BACKUP_GAIN * theirs && best.as_ref().is_none_or(|(g, _)| theirs - mine > *g)
            {
                best = Some((theirs - mine, id.clone()));
            }
        }
        let (_, original) = best?;
        let lease_id = random_id("l");
        let o = st.leases.get_mut(&original).expect("listed");
        o.backups += 1;
        let mut partners = o.partners.clone();
        o.partners.push(lease_id.clone());
        for p in &partners {
            if let Some(p) = st.leases.get_mut(p) {
                p.partners.push(lease_id.clone());
            }
        }
        partners.push(original.clone());
        let o = &st.leases[&original];
        let lease = Lease {
            worker: worker_id.to_string(),
            job: o.job.clone(),
            units: o.units.clone(),
            region: o.region,
            deadline: Instant::now() + self.config.lease_timeout,
            progress: 0,
            expected_rays: o.expected_rays,
            active: o.active.clone(),
            ranges: o.ranges.clone(),
            partners,
            backup: true,
            backups: 0,
            rated: false,
        };
        let job = st.jobs.get(&lease.job).expect("checked");
        tracing::debug!(lease = %lease_id, backs_up = %original, job = %lease.job, rect = ?lease.region.rect, "backup lease");
        let view = LeasedUnit {
            lease_id: lease_id.clone(),
            job: job.leased(&lease.job),
            region: lease.region,
            active: lease.active.clone(),
            ranges: lease.ranges.clone(),
            units: lease.units.len() as u32,
        };
        st.leases.insert(lease_id.clone(), lease);
        st.workers
            .get_mut(worker_id)
            .expect("worker checked")
            .leases
            .insert(lease_id);
        Some(view)
    }

    /// As [`Farm::lease`], but when nothing is pending waits up to `wait`
    /// for work to appear (long poll): an idle worker starts on a new job at
    /// once instead of after its retry interval.
    pub async fn lease_or_wait(
        &self,
        worker_id: &str,
        max_units: u32,
        ahead: bool,
        wait: Duration,
    ) -> Result<Vec<LeasedUnit>, FarmError> {
        // Registered before looking, so a wake-up between the look and the
        // wait is not missed.
        let start = Instant::now();
        let granted = |leases: Vec<LeasedUnit>| {
            if !leases.is_empty() {
                self.metrics.lease_granted(start.elapsed().as_secs_f64());
            }
            leases
        };
        let notified = self.work_ready.notified();
        tokio::pin!(notified);
        notified.as_mut().enable();
        let (leases, held_back) = self.lease_or_hold(worker_id, max_units, ahead)?;
        // Work held back for a faster worker: the caller asks again soon
        // (the faster one may not take it after all), not after new work.
        let wait = if held_back {
            wait.min(HELD_BACK_WAIT)
        } else {
            wait
        };
        if !leases.is_empty()
            || wait.is_zero()
            || tokio::time::timeout(wait, notified).await.is_err()
        {
            return Ok(granted(leases));
        }
        self.lease(worker_id, max_units, ahead).map(granted)
    }

    /// Extends the worker's leases; returns those it no longer holds.
    pub fn heartbeat(
        &self,
        worker_id: &str,
        leases: &[(String, u64)],
    ) -> Result<Vec<String>, FarmError> {
        let mut st = self.state.lock().expect("state lock");
        let st = &mut *st;
        let worker = st
            .workers
            .get_mut(worker_id)
            .ok_or_else(|| unknown_worker(worker_id))?;
        worker.last_seen = Instant::now();
        let deadline = Instant::now() + self.config.lease_timeout;
        let mut gone = Vec::new();
        for (id, samples_done) in leases {
            match st.leases.get_mut(id) {
                Some(l) if l.worker == worker_id => {
                    l.deadline = deadline;
                    l.progress = l.progress.max(*samples_done);
                }
                _ => gone.push(id.clone()),
            }
        }
        Ok(gone)
    }

    /// Queues again the units of leases a worker hands back unstarted
    /// (drain); no failed attempt is counted. Returns how many it held.
    pub fn return_leases(&self, worker_id: &str, lease_ids: &[String]) -> Result<u32, FarmError> {
        let mut st = self.state.lock().expect("state lock");
        let st = &mut *st;
        let worker = st
            .workers
            .get_mut(worker_id)
            .ok_or_else(|| unknown_worker(worker_id))?;
        worker.last_seen = Instant::now();
        let mut returned = 0;
        for id in lease_ids {
            match st.leases.get(id) {
                None => continue,
                Some(l) if l.worker != worker_id => {
                    // Never a worker's own mistake: lease ids are unique to
                    // the session they went to.
                    tracing::warn!(worker = %public_worker_id(worker_id), lease = %id, holder = %public_worker_id(&l.worker),
                        "a worker tried to return another worker's lease; ignored");
                    continue;
                }
                Some(_) => {}
            }
            let l = st.leases.remove(id).expect("checked");
            if let Some(w) = st.workers.get_mut(worker_id) {
                w.leases.remove(id);
            }
            if st.partner_keeps(id, &l) {
                tracing::info!(lease = %id, job = %l.job, worker = %public_worker_id(worker_id), "lease returned; its backup goes on");
            } else {
                if let Some(job) = st.jobs.get_mut(&l.job).filter(|j| !j.state.is_terminal()) {
                    job.pending.extend(l.units.iter().copied());
                }
                tracing::info!(lease = %id, job = %l.job, worker = %public_worker_id(worker_id), frame = l.region.frame, rect = ?l.region.rect, "lease returned; unit queued again");
            }
            st.end_lease(id.clone(), l.job, false);
            returned += 1;
        }
        if returned > 0 {
            self.work_ready.notify_waiters();
        }
        Ok(returned)
    }

    /// Ends every lease of a job (cancelled or failed): heartbeats name them gone.
    pub(super) fn withdraw_leases(&self, st: &mut State, job_id: &str) {
        let ids: Vec<String> = st
            .leases
            .iter()
            .filter(|(_, l)| l.job == job_id)
            .map(|(id, _)| id.clone())
            .collect();
        for id in ids {
            if let Some(l) = st.leases.remove(&id) {
                if let Some(w) = st.workers.get_mut(&l.worker) {
                    w.leases.remove(&id);
                }
                st.end_lease(id, l.job, false);
            }
        }
    }

    /// Expires leases and workers past their deadlines. Called periodically.
    pub fn expire(&self) {
        let now = Instant::now();
        let mut st = self.state.lock().expect("state lock");
        let st = &mut *st;
        let expired: Vec<String> = st
            .leases
            .iter()
            .filter(|(_, l)| l.deadline <= now)
            .map(|(id, _)| id.clone())
            .collect();
        for id in expired {
            let l = st.leases.remove(&id).expect("listed");
            let name = st.workers.get_mut(&l.worker).map(|w| {
                w.leases.remove(&id);
                w.units_failed += l.units.len() as u64;
                w.name.clone()
            });
            // The job counts it as a failure of class timeout (the worker
            // neither answered nor reported progress in time).
            if let Some(job) = st.jobs.get_mut(&l.job).filter(|j| !j.state.is_terminal()) {
                *job.failure_classes
                    .entry(super::FailureClass::Timeout.name())
                    .or_default() += 1;
            }
            if st.partner_keeps(&id, &l) {
                tracing::warn!(lease = %id, job = %l.job, worker = %name.unwrap_or_else(|| public_worker_id(&l.worker)), "lease expired; its backup goes on");
            } else if let Some(job) = st.jobs.get_mut(&l.job).filter(|j| !j.state.is_terminal()) {
                tracing::warn!(lease = %id, job = %l.job, worker = %name.unwrap_or_else(|| public_worker_id(&l.worker)), frame = l.region.frame, rect = ?l.region.rect, "lease expired; unit queued again");
                job.pending.extend(l.units.iter().copied());
                self.work_ready.notify_waiters();
            }
            st.end_lease(id, l.job, false);
        }
        let silent: Vec<String> = st
            .workers
            .iter()
            .filter(|(_, w)| now.duration_since(w.last_seen) > self.config.lease_timeout)
            .map(|(id, _)| id.clone())
            .collect();
        for id in silent {
            if let Some(w) = st.workers.remove(&id) {
                tracing::info!(worker = %public_worker_id(&id), name = %w.name, units_done = w.units_done, "worker left (no heartbeat)");
                // A job it alone could run says so now.
                for j in st.jobs.values().filter(|j| !j.rec.requirements.is_empty()) {
                    j.notify();
                }
            }
        }
    }

    /// Warns, once, when jobs wait and no worker has been connected for a
    /// lease timeout (the time after which a silent worker counts as gone,
    /// so a restarted coordinator gives its workers that long to come
    /// back). Called periodically.
    pub fn check_workers(&self) {
        let mut st = self.state.lock().expect("state lock");
        let waiting = st
            .jobs
            .values()
            .filter(|j| j.state.leasable() && !j.pending.is_empty())
            .count();
        if waiting == 0 || !st.workers.is_empty() {
            if st.unserved_warned && !st.workers.is_empty() {
                tracing::info!(workers = st.workers.len(), "workers connected again");
            }
            st.unserved_since = None;
            st.unserved_warned = false;
            return;
        }
        let since = *st.unserved_since.get_or_insert_with(Instant::now);
        if !st.unserved_warned && since.elapsed() >= self.config.lease_timeout {
            st.unserved_warned = true;
            tracing::warn!(
                jobs = waiting,
                "no worker is connected: {waiting} job(s) wait for one (start `tessera worker --coordinator URL`)"
            );
        }
    }
}

fn unknown_worker(id: &str) -> FarmError {
    // Named by its public id: the message may be logged.
    FarmError::NotFound(format!(
        "unknown worker {}: register again (the coordinator restarted or timed the worker out)",
        public_worker_id(id)
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn far_from_a_jobs_end_a_lease_is_the_work_the_worker_wants() {
        // 4000 rays a second; 1000 rays wanted (0.25 s).
        assert_eq!(lease_budget(1000.0, 4000.0, 0.0, f64::INFINITY), 1000.0);
        assert_eq!(lease_budget(1000.0, 4000.0, 5.0, f64::INFINITY), 1000.0);
        // The end far enough off: half of it, after the held work, is more.
        assert_eq!(lease_budget(1000.0, 4000.0, 0.25, 2.0), 1000.0);
    }

    #[test]
    fn near_a_jobs_end_a_lease_ends_by_half_the_farms_time_but_not_below_the_minimum() {
        // The farm ends in 1 s; the worker holds 0.25 s of work: its lease
        // ends by 0.5 s, so 0.25 s of work at 4000 rays a second.
        assert_eq!(lease_budget(2000.0, 4000.0, 0.25, 1.0), 1000.0);
        // Holding more than half the farm's time: the smallest lease.
        let least = 4000.0 * MIN_LEASE_SECONDS;
        assert_eq!(lease_budget(2000.0, 4000.0, 0.75, 1.0), least);
        assert_eq!(lease_budget(2000.0, 4000.0, 0.0, 0.0), least);
        // ... but never more than the worker wants.
        assert_eq!(lease_budget(10.0, 4000.0, 0.75, 1.0), 10.0);
    }
}
