//! One job's own bookkeeping (`impl Job`): its units done and pending, the
//! work left, failed attempts, its end, and the view clients get. Called
//! with the state lock held.

use std::collections::{BTreeSet, HashMap};
use std::time::Instant;

use tessera_proto::LeasedJob;
use tokio::sync::watch;
use tracer_core::adaptive::AdaptiveSettings;
use tracer_core::scene::RenderSettings;

use crate::rate::{JOB_WINDOW, Meter};
use crate::store::{Counters, JobRecord, JobStateRec};
use crate::units::{Layout, Unit};

use super::frames::{FrameAcc, FrameFilm};
use super::{Failure, Job, JobState, JobView, UnitIndex, adaptive, now_ms};

/// The failed attempts of a unit that count against its job: none while
/// one worker alone has failed it, all of them once a second worker has
/// failed it too. One bad worker cannot fail a job, by its reports or by
/// malformed results: the job's blocklist and the quarantine keep it away
/// instead, while a unit that fails everywhere still fails the job.
fn attempts(failures: &[Failure]) -> u32 {
    let first = failures.first().map(|f| f.worker.as_str());
    if failures.iter().any(|f| Some(f.worker.as_str()) != first) {
        failures.len() as u32
    } else {
        0
    }
}

/// How a job is cut into units: its settings, frames, tiles and sample
/// batches (an adaptive job's batches are its rounds).
pub(super) fn job_layout(
    s: RenderSettings,
    frames: (u32, u32),
    tile_size: u32,
    samples_per_unit: u32,
    adaptive: Option<&AdaptiveSettings>,
) -> Layout {
    let mut layout = Layout::new(
        s.width,
        s.height,
        s.samples,
        frames.0,
        frames.1,
        tile_size,
        samples_per_unit,
    );
    if let Some(a) = adaptive {
        layout.batches = a.rounds();
    }
    layout
}

/// A stored job's layout.
fn layout_of(rec: &JobRecord) -> Layout {
    job_layout(
        rec.settings,
        (rec.first_frame, rec.last_frame),
        rec.tile_size,
        rec.samples_per_unit,
        rec.adaptive.as_ref(),
    )
}

impl Job {
    /// What a worker leasing a unit of this job (`job_id`) needs of it.
    pub(super) fn leased(&self, job_id: &str) -> LeasedJob {
        LeasedJob {
            job_id: job_id.to_string(),
            scene_name: self.rec.scene_name.clone(),
            scene_sha256: self.rec.scene_sha256.clone(),
            files: self.rec.assets.clone(),
            settings: self.rec.settings,
        }
    }

    /// A stored job, its layout derived from its record.
    pub(super) fn new(rec: JobRecord, counters: Counters) -> Self {
        let layout = layout_of(&rec);
        Self::with_layout(rec, counters, layout)
    }

    /// A job whose layout ([`job_layout`] of its record) is already built:
    /// a submit builds it once, for its cost probe and the job.
    pub(super) fn with_layout(rec: JobRecord, counters: Counters, layout: Layout) -> Self {
        let adaptive = rec.adaptive;
        let rec_notify_pending = rec.notify_pending;
        let total = layout.total();
        let state = match rec.state {
            JobStateRec::Active => JobState::Running,
            JobStateRec::Done => JobState::Done,
            JobStateRec::Failed => JobState::Failed,
            JobStateRec::Cancelled => JobState::Cancelled,
        };
        let pending = if state.is_terminal() {
            BTreeSet::new()
        } else {
            (0..total).collect()
        };
        let frames = (rec.first_frame..=rec.last_frame)
            .map(|f| {
                (
                    f,
                    FrameAcc {
                        film: FrameFilm::default(),
                        merging: 0,
                        units_done: 0,
                        samples_done: 0,
                        written: None,
                        writing: false,
                        changed: 0,
                    },
                )
            })
            .collect();
        // Until probed: one ray a pixel-sample.
        let tile_rays = layout.tiles.iter().map(|t| t.area() as f64).collect();
        let mut job = Job {
            rec,
            layout,
            tile_rays,
            work_left: 0.0,
            meter: Meter::new(JOB_WINDOW),
            state: if state == JobState::Running {
                JobState::Queued
            } else {
                state
            },
            done: vec![false; total as usize],
            pending,
            failures: HashMap::new(),
            worker_failures: HashMap::new(),
            reroutes: HashMap::new(),
            frames,
            frame_seq: 0,
            counters,
            units_done: 0,
            samples_done: 0,
            started: None,
            stopped: None,
            first_lease_unix_ms: 0,
            first_result_unix_ms: 0,
            last_result_unix_ms: 0,
            samples_this_run: 0,
            rays_this_run: 0,
            watch: watch::channel(0).0,
            adaptive: adaptive.map(adaptive::AdaptiveJob::new),
            // Ended before this run: announced, unless its notifications
            // were still out when the last run stopped (sent again).
            announced: state.is_terminal() && !rec_notify_pending,
            failure_classes: Default::default(),
            scene_error: None,
        };
        job.adaptive_start();
        job.work_left = job.sum_work_left();
        job
    }

    /// Expected rays of unit `u` (its tile's, times its samples).
    pub(super) fn unit_work(&self, u: UnitIndex) -> f64 {
        let unit = self.layout.unit(u);
        self.tile_rays[unit.tile as usize] * self.layout.batches[unit.batch as usize].len() as f64
    }

    fn sum_work_left(&self) -> f64 {
        (0..self.layout.total())
            .filter(|&u| !self.done[u as usize])
            .map(|u| self.unit_work(u))
            .sum()
    }

    /// The cost probe's expected rays per tile (replacing the uniform guess).
    pub(super) fn set_tile_rays(&mut self, tile_rays: Vec<f64>) {
        self.tile_rays = tile_rays;
        self.work_left = self.sum_work_left();
    }

    pub(super) fn notify(&self) {
        self.watch.send_modify(|v| *v += 1);
    }

    pub(super) fn mark_done(&mut self, u: UnitIndex) {
        if self.done[u as usize] {
            return;
        }
        self.done[u as usize] = true;
        self.pending.remove(&u);
        self.units_done += 1;
        self.work_left = (self.work_left - self.unit_work(u)).max(0.0);
        let unit: Unit = self.layout.unit(u);
        let samples = self.layout.unit_samples(unit);
        self.samples_done += samples;
        if let Some(f) = self.frames.get_mut(&unit.frame) {
            f.units_done += 1;
            f.samples_done += samples;
        }
        self.frame_changed(unit.frame);
        if self.state == JobState::Queued {
            self.state = JobState::Running;
        }
    }

    pub(super) fn finish(&mut self, state: JobState, error: String) {
        self.state = state;
        self.rec.state = match state {
            JobState::Done => JobStateRec::Done,
            JobState::Failed => JobStateRec::Failed,
            JobState::Cancelled => JobStateRec::Cancelled,
            _ => JobStateRec::Active,
        };
        self.rec.error = error;
        self.rec.finished_unix_ms = now_ms();
        self.stopped = Some(Instant::now());
        self.pending.clear();
        // A new lock: merges still in flight finish into the old film,
        // which goes with them.
        for f in self.frames.values_mut() {
            f.film = FrameFilm::default();
        }
        self.notify();
    }

    /// Records a failed attempt of `units` by worker session `worker`
    /// (its failure report or a malformed result); fails the job
    /// (returning its record to persist) when a unit's attempts that
    /// count (see [`attempts`]) reach `max_attempts`.
    pub(super) fn fail_units(
        &mut self,
        units: &[u32],
        worker: &str,
        message: String,
    ) -> Option<JobRecord> {
        if self.state.is_terminal() {
            return None;
        }
        let mut exhausted = None;
        for &u in units {
            let f = self.failures.entry(u).or_default();
            f.push(Failure {
                worker: worker.to_string(),
                message: message.clone(),
            });
            if attempts(f) >= self.rec.max_attempts && exhausted.is_none() {
                exhausted = Some((u, f.iter().map(|f| f.message.clone()).collect::<Vec<_>>()));
            }
            self.pending.insert(u);
        }
        self.notify();
        let (u, messages) = exhausted?;
        let r = self.layout.region(self.layout.unit(u));
        let error = format!(
            "work unit {u} (frame {}, tile {:?}, samples {}..{}) failed {} times: {}",
            r.frame,
            r.rect,
            r.samples.start,
            r.samples.end,
            messages.len(),
            messages.join("; ")
        );
        tracing::error!(job = %self.rec.id, %error, "job failed");
        self.finish(JobState::Failed, error);
        Some(self.rec.clone())
    }

    /// Sends `units`, which failed of `class` on worker session `worker`
    /// (of `labels`), where that failure may not recur: out of memory to
    /// a worker with more, a lost GPU to the CPU where the job allows it
    /// (`placement::Reroute`). Other classes change nothing.
    pub(super) fn reroute(
        &mut self,
        units: &[u32],
        class: super::FailureClass,
        worker: &str,
        name: &str,
        labels: &std::collections::BTreeMap<String, String>,
    ) {
        use tessera_proto::placement::Reroute;
        let r = match class {
            super::FailureClass::OutOfMemory => Reroute::out_of_memory(worker, labels),
            super::FailureClass::GpuLost => {
                Reroute::gpu_lost(worker, labels, &self.rec.requirements)
            }
            _ => return,
        };
        tracing::warn!(job = %self.rec.id, worker = %name, units = units.len(), to = %r, "units rerouted after {}", class.name());
        for &u in units {
            self.reroutes.insert(u, r.clone());
        }
    }

    /// Whether worker session `worker` (of `labels`) may take unit `u`:
    /// any may, unless the unit was rerouted ([`Job::reroute`]).
    pub(super) fn admits(
        &self,
        u: u32,
        worker: &str,
        labels: &std::collections::BTreeMap<String, String>,
    ) -> bool {
        self.reroutes
            .get(&u)
            .is_none_or(|r| r.admits(worker, labels))
    }

    /// Counts a failure report of class `class`; for a scene error, fails
    /// the job (returning its record) when a second worker reports one:
    /// the scene fails everywhere, retrying it elsewhere is wasted work.
    pub(super) fn count_class(
        &mut self,
        class: super::FailureClass,
        worker: &str,
        name: &str,
        message: &str,
    ) -> Option<JobRecord> {
        if self.state.is_terminal() {
            return None;
        }
        *self.failure_classes.entry(class.name()).or_default() += 1;
        if class != super::FailureClass::Scene {
            return None;
        }
        match &self.scene_error {
            None => {
                self.scene_error = Some((worker.into(), name.into(), message.into()));
                None
            }
            Some((first, _, _)) if first == worker => None,
            Some((_, first_name, first_message)) => {
                let error = format!(
                    "scene error reproduced on a second worker ({first_name}, {name}): {first_message}"
                );
                tracing::error!(job = %self.rec.id, %error, "job failed");
                self.finish(JobState::Failed, error);
                Some(self.rec.clone())
            }
        }
    }

    /// Records that `frame` changed (see `FrameAcc::changed`).
    pub(super) fn frame_changed(&mut self, frame: u32) {
        self.frame_seq += 1;
        if let Some(f) = self.frames.get_mut(&frame) {
            f.changed = self.frame_seq;
        }
    }

    /// The view with every frame.
    /// Corrects the pixel-samples counted for a finished unit of `frame`
    /// from `nominal` (what [`Job::mark_done`] counted) to `traced` (an
    /// adaptive round traces only its active blocks; a skipped one none).
    pub(super) fn correct_samples(&mut self, frame: u32, nominal: u64, traced: u64) {
        self.samples_done = self.samples_done + traced - nominal;
        if let Some(f) = self.frames.get_mut(&frame) {
            f.samples_done = f.samples_done + traced - nominal;
        }
    }

    /// The job's progress and each frame's, 0 to 1: the one definition
    /// that `status`, `watch`, `jobs` and the web monitor show (through
    /// [`JobView::progress`] and [`JobView::frames_progress`]).
    /// Sample-weighted: pixel-samples merged over pixel-samples the job
    /// will trace (for an adaptive job, those expected so far), so a small
    /// edge tile or a short last sample batch counts for what it is. A
    /// finished job or a written frame is 1.
    fn progress(&self, samples_total: u64) -> f64 {
        if self.state == JobState::Done {
            1.0
        } else {
            share(self.samples_done, samples_total)
        }
    }

    /// Frame `n`'s progress, as [`Job::progress`] defines it.
    fn frame_progress(&self, n: u32, f: &FrameAcc) -> f64 {
        if f.written.is_some() {
            return 1.0;
        }
        let total = match &self.adaptive {
            Some(_) => self.adaptive_frame_expected(n).max(f.samples_done),
            None => {
                self.layout.width as u64
                    * self.layout.height as u64
                    * self.rec.settings.samples as u64
            }
        };
        share(f.samples_done, total)
    }

    pub(super) fn view(&self) -> JobView {
        self.view_with(self.frames.iter())
    }

    /// The view with at most `limit` frames from frame `from` on, and the
    /// first frame after them (None: they are the last).
    pub(super) fn view_page(&self, from: u32, limit: usize) -> (JobView, Option<u32>) {
        let mut frames = self.frames.range(from..);
        let page: Vec<_> = frames.by_ref().take(limit).collect();
        let next = frames.next().map(|(&f, _)| f);
        (self.view_with(page.into_iter()), next)
    }

    /// The view with only the frames changed after `since` (a
    /// `frame_seq` an earlier call returned; `u64::MAX`: none), and the
    /// `frame_seq` now.
    pub(super) fn view_since(&self, since: u64) -> (JobView, u64) {
        let changed = self.frames.iter().filter(|(_, f)| f.changed > since);
        (self.view_with(changed), self.frame_seq)
    }

    fn view_with<'a>(&'a self, frames: impl Iterator<Item = (&'a u32, &'a FrameAcc)>) -> JobView {
        let per = self.layout.units_per_frame() as u64;
        let samples_total = self.layout.width as u64
            * self.layout.height as u64
            * self.rec.settings.samples as u64
            * self.layout.frames as u64;
        let elapsed = self.started.map_or(0.0, |t| {
            self.stopped
                .map_or_else(|| t.elapsed(), |s| s.saturating_duration_since(t))
                .as_secs_f64()
        });
        let rps = if elapsed > 0.0 {
            self.rays_this_run as f64 / elapsed
        } else {
            0.0
        };
        let mut eta =
            crate::rate::eta(self.work_left, self.meter.rate(Instant::now())).unwrap_or(-1.0);
        let adaptive = self.adaptive_progress();
        let mut samples_total = samples_total;
        if adaptive.settings.is_some() {
            // The samples still expected over this run's sample rate.
            samples_total = adaptive.samples_expected.max(self.samples_done);
            eta = if self.samples_this_run > 0 && elapsed > 0.0 {
                (samples_total - self.samples_done) as f64
                    / (self.samples_this_run as f64 / elapsed)
            } else {
                -1.0
            };
        }
        let progress = self.progress(samples_total);
        let frames: Vec<_> = frames.collect();
        let frames_progress = frames
            .iter()
            .map(|&(&n, f)| self.frame_progress(n, f))
            .collect();
        JobView {
            progress,
            frames_progress,
            record: self.rec.clone(),
            state: self.state,
            counters: self.counters.clone(),
            units_total: self.layout.total() as u64,
            units_done: self.units_done,
            samples_total,
            samples_done: self.samples_done,
            frames: frames
                .into_iter()
                .map(|(&f, a)| (f, per, a.units_done, a.written.clone()))
                .collect(),
            rays_per_second: rps,
            eta_seconds: if self.state.is_terminal() { 0.0 } else { eta },
            first_lease_unix_ms: self.first_lease_unix_ms,
            first_result_unix_ms: self.first_result_unix_ms,
            last_result_unix_ms: self.last_result_unix_ms,
            adaptive,
            blocklisted: self.blocklisted(),
            // Set by `State::view_of`, which sees the workers.
            unrunnable: String::new(),
            waiting_for: Vec::new(),
            failures: self.failure_classes.clone(),
        }
    }

    /// Counts a failure report of `units` by worker session `worker`;
    /// at `after` reports it is kept from this job for `for_`. One
    /// worker that fails every unit (a broken driver, a full disk) then
    /// stops taking them, and the others render them.
    pub(super) fn count_failure(
        &mut self,
        worker: &str,
        name: &str,
        units: u32,
        after: u32,
        for_: std::time::Duration,
    ) {
        if after == 0 || self.state.is_terminal() {
            return;
        }
        let f = self.worker_failures.entry(worker.to_string()).or_default();
        f.name = name.to_string();
        f.count = f.count.saturating_add(units);
        if f.count >= after && f.blocked_until.is_none_or(|t| t <= Instant::now()) {
            f.blocked_until = Some(Instant::now() + for_);
            tracing::warn!(job = %self.rec.id, worker = %super::public_worker_id(worker), %name,
                failures = f.count, seconds = for_.as_secs_f64(),
                "worker blocklisted for the job: it gets none of its units until forgiven");
            self.notify();
        }
    }

    /// Whether worker session `worker` is kept from this job now; a
    /// forgiven worker starts counting again from zero.
    pub(super) fn blocks(&mut self, worker: &str) -> bool {
        let Some(f) = self.worker_failures.get_mut(worker) else {
            return false;
        };
        match f.blocked_until {
            Some(t) if t > Instant::now() => true,
            Some(_) => {
                tracing::info!(job = %self.rec.id, worker = %super::public_worker_id(worker),
                    name = %f.name, "worker forgiven: it may lease the job's units again");
                f.blocked_until = None;
                f.count = 0;
                false
            }
            None => false,
        }
    }

    /// The workers kept from this job now.
    fn blocklisted(&self) -> Vec<super::BlockedWorker> {
        let now = Instant::now();
        let mut v: Vec<_> = self
            .worker_failures
            .iter()
            .filter_map(|(id, f)| {
                let t = f.blocked_until.filter(|&t| t > now)?;
                Some(super::BlockedWorker {
                    id: super::public_worker_id(id),
                    name: f.name.clone(),
                    failures: f.count,
                    until_unix_ms: now_ms() + t.duration_since(now).as_millis() as i64,
                })
            })
            .collect();
        v.sort_by(|a, b| a.name.cmp(&b.name).then(a.id.cmp(&b.id)));
        v
    }
}

/// `done` over `total`, at most 1 (0 for an empty total).
fn share(done: u64, total: u64) -> f64 {
    if total == 0 {
        0.0
    } else {
        (done as f64 / total as f64).min(1.0)
    }
}
