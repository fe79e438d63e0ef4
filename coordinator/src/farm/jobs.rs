//! Clients' requests: submit (a scene checked, its files stored, its cost
//! probed), cancel, delete, the job and worker views, watch, outputs,
//! progress logs, and the jobs' stored files.

use std::collections::{BTreeMap, HashSet};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use tokio::sync::watch;
use tracer_core::adaptive::{AdaptiveMode, AdaptiveSettings};
use tracer_core::assets::Bundle;
use tracer_core::scene::{RenderSettings, SceneDesc};

use crate::assets::{AssetStoreError, sha256_hex};
use crate::store::{Counters, JobRecord, JobStateRec, Op};
use crate::units::{
    DEFAULT_MAX_ATTEMPTS, DEFAULT_SAMPLES_PER_UNIT, DEFAULT_TILE_SIZE, RESULT_BYTES_PER_PIXEL,
    unit_count,
};

use super::{
    Farm, FarmError, Job, JobState, JobView, MAX_UNITS, Submission, WorkerView, asset_error,
    check_name, now_ms,
};

impl Farm {
    /// Validates and queues a job. Bad scenes are refused with the message
    /// `tessera render` prints for them. Nothing is stored before every
    /// check has passed; the job is queued once its record is committed.
    pub async fn submit(self: &Arc<Self>, s: Submission) -> Result<String, FarmError> {
        let spec = &s.spec;
        let text = std::str::from_utf8(&s.scene).map_err(|e| {
            FarmError::InvalidArgument(format!("{}: scene is not UTF-8 text: {e}", spec.scene_name))
        })?;
        self.check_storage()?;
        let checked = self.check_spec(spec)?;
        let files = self.store_files(&s)?;
        let scene = self.parse_scene(text, &spec.scene_name, &files).await?;
        // The job's settings, parsed from the request: checked here, once.
        let (settings, adaptive) = spec
            .overrides
            .resolve(&scene, &spec.adaptive)
            .map_err(|e| FarmError::InvalidArgument(e.to_string()))?;
        let plan = self.plan(spec, settings, adaptive.as_ref())?;
        // Off the async threads: it traces a few rays of every tile.
        let tile_rays = {
            let layout = plan.layout.clone();
            tokio::task::spawn_blocking(move || crate::cost::probe(&scene, &settings, &layout))
                .await
                .map_err(|e| FarmError::Internal(format!("cost probe: {e}")))?
        };
        let scene_sha256 = self.hold_job_files(spec, &s.scene, &files)?;
        let id = self.new_job_id(&scene_sha256);
        let output_dir = self.config.data_dir.join("outputs").join(&id);
        std::fs::create_dir_all(&output_dir).map_err(|e| {
            FarmError::Internal(format!("cannot create {}: {e}", output_dir.display()))
        })?;
        // The spec, resolved: what the job renders, kept across restarts.
        let rec = JobRecord {
            id: id.clone(),
            name: job_name(spec),
            scene_name: spec.scene_name.clone(),
            scene_sha256,
            assets: files,
            settings,
            first_frame: plan.frames.0,
            last_frame: plan.frames.1,
            priority: spec.priority,
            tile_size: plan.tile_size,
            samples_per_unit: plan.samples_per_unit,
            max_attempts: plan.max_attempts,
            state: JobStateRec::Active,
            error: String::new(),
            submitted_unix_ms: now_ms(),
            finished_unix_ms: 0,
            output_dir: output_dir.to_string_lossy().into_owned(),
            adaptive,
            requirements: checked.requirements,
            after: checked.after,
            on_done: spec.on_done.clone(),
            blocklist_after: Some(checked.blocklist_after),
            blocklist_seconds: Some(checked.blocklist_seconds),
            notify_pending: false,
        };
        self.commit(vec![
            Op::PutJob(rec.clone()),
            Op::PutCounters {
                job: id.clone(),
                counters: Counters::default(),
            },
        ])
        .await?;
        tracing::info!(
            job = %id, name = %rec.name, scene = %rec.scene_name,
            width = settings.width, height = settings.height, samples = settings.samples,
            frames = %format!("{}..{}", plan.frames.0, plan.frames.1), units = plan.layout.total(),
            priority = rec.priority,
            target_error = rec.adaptive.map_or(0.0, |a| a.target_error),
            relative_error = rec.adaptive.map_or(0.0, |a| a.relative_error),
            min_samples = rec.adaptive.map_or(0, |a| a.min_samples),
            max_samples = rec.adaptive.map_or(0, |a| a.max_samples),
            "job accepted"
        );
        let mut job = Job::with_layout(rec, Counters::default(), plan.layout);
        job.set_tile_rays(tile_rays);
        self.enqueue(id.clone(), job).await?;
        Ok(id)
    }

    /// The spec's fields beside its scene and settings, checked before
    /// anything is stored (an unknown parent job is refused at once), with
    /// the coordinator's defaults for what it leaves out.
    fn check_spec(&self, spec: &tessera_proto::JobSpec) -> Result<CheckedSpec, FarmError> {
        check_name("job name", &spec.name, 200)?;
        check_name("scene name", &spec.scene_name, 4096)?;
        let requirements = tessera_proto::placement::Requirement::parse_all(&spec.requirements)
            .map_err(|e| FarmError::InvalidArgument(e.to_string()))?;
        let after = self.check_after(&spec.after)?;
        self.check_on_done(&spec.on_done)?;
        let blocklist_seconds = match spec.blocklist_seconds {
            Some(s) if !(s.is_finite() && s > 0.0) => {
                return Err(FarmError::InvalidArgument(format!(
                    "blocklist_seconds must be a positive number of seconds, got {s}"
                )));
            }
            Some(s) => s,
            None => self.config.blocklist_for.as_secs_f64(),
        };
        Ok(CheckedSpec {
            requirements,
            after,
            blocklist_after: spec.blocklist_after.unwrap_or(self.config.blocklist_after),
            blocklist_seconds,
        })
    }

    /// The job's scene, parsed (off the async threads) from its stored
    /// files alone, as a worker will parse it; its warnings logged.
    async fn parse_scene(
        self: &Arc<Self>,
        text: &str,
        scene_name: &str,
        files: &BTreeMap<String, String>,
    ) -> Result<SceneDesc, FarmError> {
        let bundle = {
            let farm = self.clone();
            let files = files.clone();
            tokio::task::spawn_blocking(move || farm.bundle(&files))
                .await
                .map_err(|e| FarmError::Internal(format!("reading the job's files: {e}")))??
        };
        let scene = {
            let text = text.to_string();
            let scene_name = scene_name.to_string();
            tokio::task::spawn_blocking(move || SceneDesc::parse_from(&text, &scene_name, &bundle))
                .await
                .map_err(|e| FarmError::Internal(format!("scene validation: {e}")))?
                .map_err(|e| FarmError::InvalidArgument(e.to_string()))?
        };
        for w in &scene.warnings {
            tracing::warn!(scene = %scene_name, "{w}");
        }
        Ok(scene)
    }

    /// Stores the scene file and holds it and the job's `files` again, now
    /// that the job is about to name them: a retention shorter than this
    /// submit took must not leave a job whose files are gone. The scene's
    /// hash.
    fn hold_job_files(
        &self,
        spec: &tessera_proto::JobSpec,
        scene: &[u8],
        files: &BTreeMap<String, String>,
    ) -> Result<String, FarmError> {
        let scene_sha256 = self.assets.put(scene).map_err(asset_error)?;
        for (name, sha256) in files.iter().chain([(&spec.scene_name, &scene_sha256)]) {
            if self.assets.hold(sha256).is_none() {
                return Err(FarmError::FailedPrecondition(format!(
                    "files[{name:?}]: asset {sha256} was collected while the job was submitted \
                     (--asset-retention is shorter than the submit took); upload it again"
                )));
            }
        }
        Ok(scene_sha256)
    }

    /// A new job's id: unique to this coordinator's run and its data.
    fn new_job_id(&self, scene_sha256: &str) -> String {
        let mut st = self.state.lock().expect("state lock");
        st.next_id += 1;
        format!(
            "j{}",
            &sha256_hex(
                format!("{scene_sha256}{}{}{}", self.boot, st.next_id, now_ms()).as_bytes()
            )[..10]
        )
    }

    /// A committed job joins the farm: waiting for its parents (queued at
    /// once by `jobs_ended` if they are done by now), else queued; idle
    /// workers are woken.
    async fn enqueue(&self, id: String, mut job: Job) -> Result<(), FarmError> {
        if !job.rec.after.is_empty() {
            job.state = JobState::Waiting;
        }
        let failed = {
            let mut st = self.state.lock().expect("state lock");
            st.jobs.insert(id, job);
            // A parent may have ended while this submit ran.
            self.jobs_ended(&mut st)
        };
        if !failed.is_empty() {
            self.commit(failed.into_iter().map(Op::PutJob).collect())
                .await?;
        }
        self.work_ready.notify_waiters();
        Ok(())
    }

    /// The job's files, checked and held: inline ones stored now, uploaded
    /// ones named by hash (each held, its retention clock restarted),
    /// within the coordinator's bytes a job. The scene is validated from
    /// these alone.
    fn store_files(&self, s: &Submission) -> Result<BTreeMap<String, String>, FarmError> {
        let limits = self.assets.limits;
        let mut files = BTreeMap::new();
        let mut job_bytes = s.scene.len() as u64;
        for (name, content) in &s.assets {
            check_file_name(name)?;
            let sha256 = self.assets.put(content).map_err(asset_error)?;
            job_bytes += content.len() as u64;
            files.insert(name.clone(), sha256);
        }
        for (name, sha256) in &s.files {
            check_file_name(name)?;
            crate::assets::check_hash(sha256)
                .map_err(|e| FarmError::InvalidArgument(format!("files[{name:?}]: {e}")))?;
            // Held (its retention clock restarted) before anything else:
            // the collector leaves it for the retention time from now.
            let size = self.assets.hold(sha256).ok_or_else(|| {
                FarmError::FailedPrecondition(format!(
                    "files[{name:?}]: asset {sha256} is not on the coordinator; upload it first (UploadAsset)"
                ))
            })?;
            job_bytes += size;
            files.insert(name.clone(), sha256.clone());
        }
        if job_bytes > limits.max_job_bytes {
            return Err(FarmError::ResourceExhausted(format!(
                "the job's files are {job_bytes} bytes, over the coordinator's limit of {} bytes a job (--max-job-bytes)",
                limits.max_job_bytes
            )));
        }
        Ok(files)
    }

    /// A submission's frames, tiles and sample batches, checked against
    /// the coordinator's limits (frame size, message size, units): its
    /// layout, before anything is stored.
    fn plan(
        &self,
        spec: &tessera_proto::JobSpec,
        settings: RenderSettings,
        adaptive: Option<&AdaptiveSettings>,
    ) -> Result<Plan, FarmError> {
        let (first, last) = (spec.first_frame, spec.last_frame);
        if first > last {
            return Err(FarmError::InvalidArgument(format!(
                "frame range {first}..{last} is empty (first frame after last)"
            )));
        }
        if last - first >= 100_000 {
            return Err(FarmError::InvalidArgument(format!(
                "frame range {first}..{last} has more than 100000 frames"
            )));
        }
        let tile_size = spec.tile_size.unwrap_or(DEFAULT_TILE_SIZE);
        if !(8..=4096).contains(&tile_size) {
            return Err(FarmError::InvalidArgument(format!(
                "tile_size must be in 8..=4096, got {tile_size}"
            )));
        }
        let block = tracer_core::adaptive::BLOCK;
        if adaptive.is_some() && !tile_size.is_multiple_of(block) {
            return Err(FarmError::InvalidArgument(format!(
                "tile_size must be a multiple of {block} for adaptive sampling (target_error, relative_error), which decides per {block}x{block} block; got {tile_size}"
            )));
        }
        let align = tracer_core::render::cpu::adaptive::RUN_ALIGN;
        if adaptive.is_some_and(|a| a.mode == AdaptiveMode::Image)
            && !tile_size.is_multiple_of(align)
        {
            return Err(FarmError::InvalidArgument(format!(
                "tile_size must be a multiple of {align} for the image adaptive mode, whose blocks' costs are measured in runs of {align} pixels (so that the farm measures what a local render does); got {tile_size}"
            )));
        }
        let samples_per_unit = spec.samples_per_unit.unwrap_or(DEFAULT_SAMPLES_PER_UNIT);
        // An adaptive job's sample batches are its rounds.
        let batches = adaptive.map(|a| a.rounds());
        let max_attempts = spec.max_attempts.unwrap_or(DEFAULT_MAX_ATTEMPTS);
        let pixels = u64::from(settings.width) * u64::from(settings.height);
        if pixels > self.config.max_frame_pixels {
            return Err(FarmError::InvalidArgument(format!(
                "a {}x{} frame has {pixels} pixels, over the coordinator's limit of {} (--max-frame-pixels): \
                 the coordinator holds a frame's sums while it fills, {:.1} GB for this one",
                settings.width,
                settings.height,
                self.config.max_frame_pixels,
                (pixels * RESULT_BYTES_PER_PIXEL) as f64 / 1e9
            )));
        }
        // One tile's result must fit one message.
        let tile_pixels =
            u64::from(tile_size.min(settings.width)) * u64::from(tile_size.min(settings.height));
        let max_pixels = self.max_result_pixels();
        if tile_pixels > max_pixels {
            let side = (max_pixels as f64).sqrt() as u64 / 8 * 8;
            return Err(FarmError::InvalidArgument(format!(
                "tile_size {tile_size} makes results of {} bytes, over the coordinator's message limit of {} bytes \
                 (--max-message-bytes); use tiles of at most {side} px",
                tile_pixels * RESULT_BYTES_PER_PIXEL,
                self.config.max_message_bytes
            )));
        }
        let units = match &batches {
            None => unit_count(
                settings.width,
                settings.height,
                settings.samples,
                last - first + 1,
                tile_size,
                samples_per_unit,
            ),
            Some(b) => {
                unit_count(
                    settings.width,
                    settings.height,
                    1,
                    last - first + 1,
                    tile_size,
                    1,
                ) * b.len() as u64
            }
        };
        if units == 0 || units > MAX_UNITS {
            return Err(FarmError::InvalidArgument(format!(
                "the job would have {units} work units (the limit is {MAX_UNITS}); use larger tiles or sample batches"
            )));
        }
        let layout = super::job::job_layout(
            settings,
            (first, last),
            tile_size,
            samples_per_unit,
            adaptive,
        );
        Ok(Plan {
            frames: (first, last),
            tile_size,
            samples_per_unit,
            max_attempts,
            layout,
        })
    }

    pub fn job(&self, id: &str) -> Result<JobView, FarmError> {
        let st = self.state.lock().expect("state lock");
        st.jobs
            .get(id)
            .map(|j| st.view_of(j, j.view()))
            .ok_or_else(|| FarmError::NotFound(format!("no job {id:?}")))
    }

    /// A job's view with at most `limit` of its frames, from frame `from`
    /// on, and the frame the next page starts at (None: no more).
    pub fn job_page(
        &self,
        id: &str,
        from: u32,
        limit: usize,
    ) -> Result<(JobView, Option<u32>), FarmError> {
        let st = self.state.lock().expect("state lock");
        st.jobs
            .get(id)
            .map(|j| {
                let (v, next) = j.view_page(from, limit);
                (st.view_of(j, v), next)
            })
            .ok_or_else(|| FarmError::NotFound(format!("no job {id:?}")))
    }

    /// A job's view with only the frames that changed after `since` (what
    /// an earlier call returned; `u64::MAX` for none), and the mark to
    /// pass next time. What a watch sends costs the changes, not the job.
    pub fn job_delta(&self, id: &str, since: u64) -> Result<(JobView, u64), FarmError> {
        let st = self.state.lock().expect("state lock");
        st.jobs
            .get(id)
            .map(|j| {
                let (v, mark) = j.view_since(since);
                (st.view_of(j, v), mark)
            })
            .ok_or_else(|| FarmError::NotFound(format!("no job {id:?}")))
    }

    /// Whether the job is done, failed or cancelled (or gone): a cheap
    /// look, without building its view.
    pub fn job_ended(&self, id: &str) -> bool {
        let st = self.state.lock().expect("state lock");
        st.jobs.get(id).is_none_or(|j| j.state.is_terminal())
    }

    pub fn jobs(&self) -> Vec<JobView> {
        let st = self.state.lock().expect("state lock");
        let mut v: Vec<_> = st.jobs.values().map(|j| st.view_of(j, j.view())).collect();
        v.sort_by_key(|j| (j.record.submitted_unix_ms, j.record.id.clone()));
        v
    }

    /// A receiver that changes whenever the job does.
    pub fn watch(&self, id: &str) -> Result<watch::Receiver<u64>, FarmError> {
        let st = self.state.lock().expect("state lock");
        st.jobs
            .get(id)
            .map(|j| j.watch.subscribe())
            .ok_or_else(|| FarmError::NotFound(format!("no job {id:?}")))
    }

    pub async fn cancel(self: &Arc<Self>, id: &str) -> Result<JobView, FarmError> {
        let rec = {
            let mut st = self.state.lock().expect("state lock");
            let job = st
                .jobs
                .get_mut(id)
                .ok_or_else(|| FarmError::NotFound(format!("no job {id:?}")))?;
            if job.state.is_terminal() {
                return Ok(job.view());
            }
            job.finish(JobState::Cancelled, "cancelled by request".into());
            let rec = job.rec.clone();
            self.withdraw_leases(&mut st, id);
            // Jobs after it fail with it.
            let mut recs = vec![rec];
            recs.extend(self.jobs_ended(&mut st));
            recs
        };
        tracing::info!(job = %id, "job cancelled");
        self.commit(rec.into_iter().map(Op::PutJob).collect())
            .await?;
        self.job(id)
    }

    /// Forgets a finished (done, failed or cancelled) job: its record,
    /// stored films and output images. Its files go with the next asset
    /// collection once no other job needs them.
    pub async fn delete(self: &Arc<Self>, id: &str) -> Result<(), FarmError> {
        let dir = {
            let st = self.state.lock().expect("state lock");
            let job = st
                .jobs
                .get(id)
                .ok_or_else(|| FarmError::NotFound(format!("no job {id:?}")))?;
            if !job.state.is_terminal() {
                return Err(FarmError::FailedPrecondition(format!(
                    "job {id} is {}; cancel it first (tessera cancel {id})",
                    crate::status_json::state_name(crate::service::state_pb(job.state) as i32)
                )));
            }
            PathBuf::from(&job.rec.output_dir)
        };
        self.store
            .write(vec![Op::DeleteJob(id.to_string())])
            .await?;
        self.state.lock().expect("state lock").jobs.remove(id);
        // Only a folder of this store's outputs, never a path a record could name elsewhere.
        if dir.starts_with(self.config.data_dir.join("outputs")) {
            let _ = tokio::fs::remove_dir_all(&dir).await;
        }
        tracing::info!(job = %id, "job deleted");
        Ok(())
    }

    /// Finished frames: (frame, file name, path).
    pub fn outputs(&self, id: &str) -> Result<Vec<(u32, String, PathBuf)>, FarmError> {
        let st = self.state.lock().expect("state lock");
        let job = st
            .jobs
            .get(id)
            .ok_or_else(|| FarmError::NotFound(format!("no job {id:?}")))?;
        Ok(job
            .frames
            .iter()
            .filter_map(|(&f, acc)| {
                acc.written
                    .as_ref()
                    .map(|n| (f, n.clone(), PathBuf::from(&job.rec.output_dir).join(n)))
            })
            .collect())
    }

    pub fn workers(&self) -> Vec<WorkerView> {
        let st = self.state.lock().expect("state lock");
        let now = Instant::now();
        let mut v: Vec<_> = st
            .workers
            .iter()
            .map(|(id, w)| WorkerView {
                id: super::public_worker_id(id),
                name: w.name.clone(),
                threads: w.threads,
                backend: w.backend,
                gpu_name: w.gpu_name.clone(),
                host_id: w.host_id.clone(),
                version: w.version.clone(),
                leases: w.leases.len() as u32,
                units_done: w.units_done,
                units_failed: w.units_failed,
                samples_per_second: w.speed.samples_per_second(),
                rays_per_second: w.speed.rays_per_second(),
                last_seen_unix_ms: now_ms() - now.duration_since(w.last_seen).as_millis() as i64,
                quarantined_until_unix_ms: w
                    .quarantined_until
                    .filter(|&t| t > now)
                    .map_or(0, |t| now_ms() + t.duration_since(now).as_millis() as i64),
                labels: w.labels.clone(),
                block_ranges: w.block_ranges,
            })
            .collect();
        v.sort_by(|a, b| a.name.cmp(&b.name).then(a.id.cmp(&b.id)));
        v
    }

    /// A stored file (from the asset store, or the database of an older
    /// release, which kept files there).
    pub fn asset(&self, sha256: &str) -> Result<Vec<u8>, FarmError> {
        match self.assets.read(sha256) {
            Ok(b) => Ok(b),
            Err(AssetStoreError::NotFound(_)) => self
                .store
                .asset(sha256)?
                .ok_or_else(|| FarmError::NotFound(format!("no asset with sha256 {sha256}"))),
            Err(e) => Err(asset_error(e)),
        }
    }

    /// A job's files (name -> hash) read into a bundle.
    fn bundle(&self, files: &BTreeMap<String, String>) -> Result<Bundle, FarmError> {
        let mut bundle = Bundle::new();
        for (name, sha256) in files {
            bundle.insert(name.clone(), self.asset(sha256)?);
        }
        Ok(bundle)
    }

    /// A stored job's scene, parsed from its stored files.
    pub(super) fn stored_scene(&self, rec: &JobRecord) -> Result<SceneDesc, FarmError> {
        let text = String::from_utf8(self.asset(&rec.scene_sha256)?)
            .map_err(|e| FarmError::Internal(format!("stored scene is not UTF-8: {e}")))?;
        SceneDesc::parse_from(&text, &rec.scene_name, &self.bundle(&rec.assets)?)
            .map_err(|e| FarmError::Internal(e.to_string()))
    }

    /// Removes stored files that no unfinished job names and none has
    /// named for the retention time.
    pub fn collect_assets(&self) -> u64 {
        let keep: HashSet<String> = {
            let st = self.state.lock().expect("state lock");
            st.jobs
                .values()
                .filter(|j| !j.state.is_terminal())
                .flat_map(|j| j.rec.assets.values().chain([&j.rec.scene_sha256]).cloned())
                .collect()
        };
        self.assets.collect(&keep)
    }

    /// Logs progress of running jobs. Called at the progress cadence.
    pub fn log_progress(&self) {
        let st = self.state.lock().expect("state lock");
        for job in st.jobs.values().filter(|j| j.state == JobState::Running) {
            let v = job.view();
            let pct = 100.0 * v.progress;
            let frames: Vec<String> = v
                .frames
                .iter()
                .zip(&v.frames_progress)
                .filter(|(f, _)| f.3.is_none())
                .take(8)
                .map(|(f, p)| format!("{}:{:.0}%", f.0, 100.0 * p))
                .collect();
            if let Some(a) = v.adaptive.settings {
                tracing::info!(
                    job = %job.rec.id,
                    mode = a.mode.name(),
                    target_error = a.target_error,
                    relative_error = a.relative_error,
                    converged = format!("{:.1}%", 100.0 * v.adaptive.converged_share),
                    estimated_error = format!("{:.3e}", v.adaptive.estimated_error),
                    samples_done = v.samples_done,
                    samples_expected = v.adaptive.samples_expected,
                    "adaptive progress"
                );
            }
            tracing::info!(
                job = %job.rec.id,
                percent = format!("{pct:.1}"),
                frames = %frames.join(" "),
                rays_per_s = format!("{:.3e}", v.rays_per_second),
                eta_s = if v.eta_seconds >= 0.0 { format!("{:.1}", v.eta_seconds) } else { "unknown".into() },
                leases = st.leases.values().filter(|l| l.job == job.rec.id).count(),
                in_flight_samples = st.leases.values().filter(|l| l.job == job.rec.id).map(|l| l.progress).sum::<u64>(),
                "progress"
            );
        }
    }
}

/// A job file's name: the path the scene writes, relative to its folder.
/// It is only ever a key (files are stored by hash), but it must be one a
/// loader can produce.
fn check_file_name(name: &str) -> Result<(), FarmError> {
    if name.is_empty() || name.len() > 4096 || name.contains('\0') {
        return Err(FarmError::InvalidArgument(format!(
            "file name {:?} must be a non-empty path of at most 4096 bytes",
            name.chars().take(100).collect::<String>()
        )));
    }
    Ok(())
}

/// What [`Farm::check_spec`] makes of a spec's fields beside its scene.
struct CheckedSpec {
    requirements: Vec<tessera_proto::placement::Requirement>,
    after: Vec<String>,
    blocklist_after: u32,
    blocklist_seconds: f64,
}

/// The job's name: as given, else its scene file's stem.
fn job_name(spec: &tessera_proto::JobSpec) -> String {
    if spec.name.is_empty() {
        std::path::Path::new(&spec.scene_name)
            .file_stem()
            .map_or("job".into(), |n| n.to_string_lossy().into_owned())
    } else {
        spec.name.clone()
    }
}

/// What [`Farm::plan`] makes of a submission: its frame range, tiles,
/// samples per unit, attempts per unit and the unit layout.
struct Plan {
    frames: (u32, u32),
    tile_size: u32,
    samples_per_unit: u32,
    max_attempts: u32,
    layout: crate::units::Layout,
}
