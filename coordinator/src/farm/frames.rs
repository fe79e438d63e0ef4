//! Frame output: each frame's film as it fills (`FrameAcc`, its own lock),
//! a committed result's film merged into it (`Merge`), and, once every unit
//! of a frame is done and merged, its image written and recorded; a job is
//! done once all its frames are.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tracer_core::film::{Film, Rect};

use crate::store::{JobRecord, Op, StoreError};

use super::{Farm, Job, JobState, frame_file_name};

pub(super) struct FrameAcc {
    /// The frame's sums so far, under a lock of its own: a result is merged
    /// outside the state lock (a whole-frame result takes milliseconds).
    pub(super) film: FrameFilm,
    /// Results whose units are marked done but whose films are not merged
    /// yet: the frame is complete only once none is left.
    pub(super) merging: u32,
    pub(super) units_done: u64,
    /// Pixel-samples of the frame's finished units (as traced, for an
    /// adaptive job): what its progress counts.
    pub(super) samples_done: u64,
    pub(super) written: Option<String>,
    pub(super) writing: bool,
    /// The job's `frame_seq` when this frame last changed (a unit done,
    /// its image written): a watch sends only frames changed since it
    /// last looked, never all of a long animation's frames again.
    pub(super) changed: u64,
}

pub(super) type FrameFilm = Arc<Mutex<Option<Film>>>;

/// A committed result's film, to merge into its frame outside the state lock.
pub(super) struct Merge {
    pub(super) job: String,
    pub(super) frame: u32,
    pub(super) into: FrameFilm,
    pub(super) film: Film,
    pub(super) frame_rect: Rect,
}

impl Merge {
    pub(super) fn run(&self) -> Result<(), tracer_core::film::FilmError> {
        self.into
            .lock()
            .expect("frame film lock")
            .get_or_insert_with(|| Film::new(self.frame_rect))
            .merge(&self.film)
    }
}

impl Farm {
    /// Writes a finished frame's image, then records it (dropping its units' films).
    pub(super) fn spawn_frame_write(self: Arc<Self>, job_id: String, frame: u32) {
        tokio::spawn(async move {
            let (film, dir, units) = {
                let mut st = self.state.lock().expect("state lock");
                let Some(job) = st.jobs.get_mut(&job_id) else {
                    return;
                };
                let units = job.layout.frame_units(frame);
                let (w, h) = (job.layout.width, job.layout.height);
                let adaptive = job.adaptive.is_some();
                let Some(acc) = job.frames.get_mut(&frame) else {
                    return;
                };
                (
                    acc.film
                        .lock()
                        .expect("frame film lock")
                        .take()
                        .unwrap_or_else(|| new_frame_film(w, h, adaptive)),
                    PathBuf::from(&job.rec.output_dir),
                    units,
                )
            };
            let file = frame_file_name(frame);
            let path = dir.join(&file);
            let tmp = dir.join(format!(".{file}.tmp.png"));
            // Every unit of the frame is stored: a failed write (a full
            // disk) is retried until it succeeds, never a failed job.
            let mut film = film;
            let mut backoff = Duration::from_millis(200);
            let start = std::time::Instant::now();
            // Counted in `frames_failing` (health) from its first failure
            // to its success or end.
            let failing = FailingFrame {
                farm: &self,
                counted: std::cell::Cell::new(false),
            };
            loop {
                let (dir, tmp, path) = (dir.clone(), tmp.clone(), path.clone());
                let result = tokio::task::spawn_blocking(move || {
                    let r = (|| -> Result<(), String> {
                        std::fs::create_dir_all(&dir)
                            .map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
                        tracer_core::film::image::write_image(&tmp, &film)
                            .map_err(|e| e.to_string())?;
                        std::fs::rename(&tmp, &path).map_err(|e| {
                            format!("cannot rename {} to {}: {e}", tmp.display(), path.display())
                        })
                    })();
                    if r.is_err() {
                        let _ = std::fs::remove_file(&tmp);
                    }
                    (r, film)
                })
                .await;
                match result {
                    Ok((Ok(()), _)) => {
                        if let Some(job) =
                            self.state.lock().expect("state lock").jobs.get_mut(&job_id)
                            && job.rec.error.starts_with("cannot write frame")
                        {
                            job.rec.error.clear();
                        }
                        break;
                    }
                    Ok((Err(e), f)) => {
                        film = f;
                        failing.set();
                        tracing::error!(job = %job_id, frame, error = %e, retry_in_ms = backoff.as_millis() as u64, "cannot write frame; retrying");
                        if let Some(job) =
                            self.state.lock().expect("state lock").jobs.get_mut(&job_id)
                        {
                            job.rec.error = format!("cannot write frame {frame} (retrying): {e}");
                        }
                        tokio::time::sleep(backoff).await;
                        backoff = (backoff * 2).min(Duration::from_secs(10));
                    }
                    Err(e) => {
                        tracing::error!(job = %job_id, frame, error = %e, "frame writer panicked");
                        return;
                    }
                }
            }
            drop(failing);
            let image_ms = start.elapsed().as_secs_f64() * 1e3;
            // The image is on disk; until the record is too, the job cannot
            // be done. Retry (a full disk or a transient error may pass); a
            // restart would also recover it, as the units' films stay stored
            // until the record replaces them.
            let mut backoff = Duration::from_millis(100);
            loop {
                let op = Op::FrameWritten {
                    job: job_id.clone(),
                    frame,
                    file: file.clone(),
                    units: units.clone(),
                };
                match self.commit(vec![op]).await {
                    Ok(()) => break,
                    Err(e @ StoreError::WriterGone) => {
                        tracing::error!(job = %job_id, frame, error = %e, "cannot record written frame");
                        return;
                    }
                    Err(e) => {
                        tracing::error!(job = %job_id, frame, error = %e, retry_in_ms = backoff.as_millis() as u64, "cannot record written frame; retrying");
                    }
                }
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(Duration::from_secs(10));
                let st = self.state.lock().expect("state lock");
                if st.jobs.get(&job_id).is_none_or(|j| j.state.is_terminal()) {
                    return;
                }
            }
            // The image (resolve, sRGB, encode, write) and its durable
            // record, each timed: the end of a job's critical path.
            tracing::info!(
                job = %job_id,
                frame,
                file = %file,
                image_ms,
                record_ms = start.elapsed().as_secs_f64() * 1e3 - image_ms,
                "frame written"
            );
            {
                let mut st = self.state.lock().expect("state lock");
                if let Some(job) = st.jobs.get_mut(&job_id) {
                    if let Some(acc) = job.frames.get_mut(&frame) {
                        acc.written = Some(file);
                        acc.writing = false;
                    }
                    job.frame_changed(frame);
                    job.notify();
                }
            }
            self.check_all_done();
        });
    }

    /// Marks jobs whose every frame is written as done.
    pub(super) fn check_all_done(self: Arc<Self>) {
        let recs: Vec<JobRecord> = {
            let mut st = self.state.lock().expect("state lock");
            let mut recs: Vec<JobRecord> = st
                .jobs
                .values_mut()
                .filter(|j| j.state.leasable() && j.frames.values().all(|f| f.written.is_some()))
                .map(|j| {
                    j.finish(JobState::Done, String::new());
                    tracing::info!(job = %j.rec.id, name = %j.rec.name, units = j.layout.total(), rays = j.counters.rays.iter().sum::<u64>(), "job done");
                    j.rec.clone()
                })
                .collect();
            if !recs.is_empty() {
                // Jobs after them may start now.
                recs.extend(self.jobs_ended(&mut st));
            }
            recs
        };
        if !recs.is_empty() {
            let farm = self.clone();
            tokio::spawn(async move {
                if let Err(e) = farm
                    .store
                    .write(recs.into_iter().map(Op::PutJob).collect())
                    .await
                {
                    tracing::error!(error = %e, "cannot record finished jobs");
                }
            });
        }
    }
}

impl Job {
    /// Frames with every unit done and no image yet; marks them as being written.
    pub(super) fn complete_frames(&mut self) -> Vec<(String, u32)> {
        let per = self.layout.units_per_frame() as u64;
        let mut out = Vec::new();
        for (&f, acc) in self.frames.iter_mut() {
            if acc.units_done == per && acc.merging == 0 && acc.written.is_none() && !acc.writing {
                acc.writing = true;
                tracing::info!(job = %self.rec.id, frame = f, "frame complete");
                out.push((self.rec.id.clone(), f));
            }
        }
        out
    }
}

/// A frame's film while it fills: adaptive jobs keep sums of squares.
pub(super) fn new_frame_film(width: u32, height: u32, adaptive: bool) -> Film {
    if adaptive {
        Film::with_squares(Rect::full(width, height))
    } else {
        Film::new(Rect::full(width, height))
    }
}

/// A frame whose write failed, counted until it is written or dropped.
struct FailingFrame<'a> {
    farm: &'a Farm,
    counted: std::cell::Cell<bool>,
}

impl FailingFrame<'_> {
    fn set(&self) {
        if !self.counted.replace(true) {
            self.farm
                .frames_failing
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
    }
}

impl Drop for FailingFrame<'_> {
    fn drop(&mut self) {
        if self.counted.get() {
            self.farm
                .frames_failing
                .fetch_sub(1, std::sync::atomic::Ordering::Relaxed);
        }
    }
}
