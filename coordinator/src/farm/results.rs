//! Result intake: each result's pixels checked before the state lock, its
//! lease taken for commit (or the result refused as late, duplicate or
//! malformed), the accepted ones committed together, then their units
//! marked done, counted, and their films merged.

use std::sync::Arc;
use std::time::Instant;

use tracer_core::film::{FIXED_ONE, MAX_SAMPLE_VALUE, Rect};

use crate::store::{Counters, EncodedFilm, JobRecord, Op, StoredFilm};

use super::frames::{Merge, new_frame_film};
use super::{
    Farm, FarmError, Lease, Outcome, ResultData, State, adaptive, now_ms, public_worker_id,
};

/// Results of at most this many pixels in all are checked on the async
/// thread that received them (a few microseconds of work).
const INLINE_CHECK_PIXELS: u64 = 4096;

impl Farm {
    /// Takes a worker's result: accepted only from the lease's holder, only
    /// once, and only if it is exactly the leased unit's data.
    pub async fn submit_result(self: &Arc<Self>, r: ResultData) -> Result<Outcome, FarmError> {
        let mut outcomes = self.submit_results(vec![r]).await?;
        outcomes
            .pop()
            .ok_or_else(|| FarmError::Internal("no outcome for a result".into()))
    }

    /// Takes several results at once: each is judged as by
    /// [`Farm::submit_result`]; the accepted ones share one commit and one
    /// pass under the state lock. Outcomes are in the order of `rs`.
    ///
    /// The work runs in its own task because it must not be cancelled
    /// half-way: once a result's units are taken from their lease they are
    /// neither pending nor leased until the commit marks them done (or
    /// queues them again). A gRPC handler's future is dropped when its
    /// client goes away (a worker killed while its result is in flight), and
    /// a drop at the commit's await would strand those units: the job would
    /// never finish.
    pub async fn submit_results(
        self: &Arc<Self>,
        rs: Vec<ResultData>,
    ) -> Result<Vec<Outcome>, FarmError> {
        let farm = self.clone();
        let outcomes = tokio::spawn(async move { farm.take_results(rs).await })
            .await
            .map_err(|e| FarmError::Internal(format!("result task failed: {e}")))??;
        for o in &outcomes {
            self.metrics.result(o);
        }
        Ok(outcomes)
    }

    async fn take_results(self: Arc<Self>, rs: Vec<ResultData>) -> Result<Vec<Outcome>, FarmError> {
        let mut outcomes: Vec<Option<Outcome>> = Vec::with_capacity(rs.len());
        let mut taken: Vec<(ResultData, Taken)> = Vec::new();
        let mut ops: Vec<Op> = Vec::new();
        // Every pixel of a result is checked before the state lock is
        // taken: a large result off the async threads (see
        // `decode_results` in service.rs), a small one here, where handing
        // it to the blocking pool would cost more than checking it (two
        // thread wake-ups for a tile of 64 pixels: `tessera bench scale`).
        let check_start = Instant::now();
        let pixels: u64 = rs.iter().map(|r| r.rect.area() as u64).sum();
        let (rs, checks) = if pixels <= INLINE_CHECK_PIXELS {
            let checks: Vec<Result<(), String>> = rs.iter().map(check_film).collect();
            (rs, checks)
        } else {
            tokio::task::spawn_blocking(move || {
                let checks: Vec<Result<(), String>> = rs.iter().map(check_film).collect();
                (rs, checks)
            })
            .await
            .map_err(|e| FarmError::Internal(format!("result check failed: {e}")))?
        };
        let lock_start = Instant::now();
        {
            let mut st = self.state.lock().expect("state lock");
            // A lease is its session's: a request naming another session's
            // lease is refused whole, before any of it is taken (no honest
            // worker sends one; lease ids are unique to their session).
            if let Some((r, l)) = rs.iter().find_map(|r| {
                st.leases
                    .get(&r.lease_id)
                    .filter(|l| l.worker != r.worker_id)
                    .map(|l| (r, l))
            }) {
                tracing::warn!(worker = %public_worker_id(&r.worker_id), lease = %r.lease_id,
                    holder = %public_worker_id(&l.worker), job = %l.job,
                    "result for another worker's lease refused");
                return Err(FarmError::PermissionDenied(format!(
                    "lease {} was granted to another worker session: a result is taken only from the session \
                     that leased the unit (the worker_id its Register returned); nothing of this request was taken",
                    r.lease_id
                )));
            }
            for (r, check) in rs.into_iter().zip(checks) {
                match self.take(&mut st, &r, check) {
                    Ok(t) => {
                        outcomes.push(None);
                        taken.push((r, t));
                    }
                    Err((outcome, rec, counters)) => {
                        // A failed or malformed result queued its units again.
                        if matches!(outcome, Outcome::Rejected(_) | Outcome::FailureRecorded) {
                            self.work_ready.notify_waiters();
                        }
                        outcomes.push(Some(outcome));
                        if rec.is_some() {
                            // A job failed: the jobs after it fail too.
                            ops.extend(self.jobs_ended(&mut st).into_iter().map(Op::PutJob));
                        }
                        ops.extend(rec.map(Op::PutJob));
                        ops.extend(
                            counters.map(|(job, counters)| Op::PutCounters { job, counters }),
                        );
                    }
                }
            }
        }
        // A result's film is stored as one record for all its units, in
        // the bytes it came in (outside the lock); a large one is written
        // to its own file first, on the blocking pool.
        let encode_start = Instant::now();
        let pixels: usize = taken.iter().map(|(r, _)| r.rect.area()).sum();
        let films: Vec<(String, u32, EncodedFilm)> = taken
            .iter_mut()
            .map(|(r, t)| {
                let film = r.film.as_ref().expect("validated");
                let bytes = match r.packed.take() {
                    Some(p) => EncodedFilm::new(film.rect, film.rays, film.nonfinite, p, None),
                    None => EncodedFilm::of_film(film),
                };
                (t.job.clone(), t.units[0], bytes)
            })
            .collect();
        // Small films only: nothing to write before the commit.
        let stored = if films.iter().any(|(_, _, f)| self.store.keeps_in_file(f)) {
            let farm = self.clone();
            tokio::task::spawn_blocking(move || farm.store.store_films(films))
                .await
                .map_err(|e| FarmError::Internal(format!("film write failed: {e}")))?
        } else {
            self.store.store_films(films)
        };
        let commit_start = Instant::now();
        let write = match stored {
            Err(e) => Err(e),
            Ok(stored) => {
                // The films in files, removed again if the commit fails.
                let files: Vec<Vec<u8>> = stored
                    .iter()
                    .filter_map(StoredFilm::file_reference)
                    .map(<[u8]>::to_vec)
                    .collect();
                for ((r, t), film) in taken.iter().zip(stored) {
                    let rays = r.film.as_ref().expect("validated").rays;
                    ops.push(Op::AcceptUnits {
                        job: t.job.clone(),
                        first_unit: t.units[0],
                        film,
                        units: t.units.len() as u64,
                        rays: [rays.primary, rays.shadow, rays.reflection, rays.refraction],
                    });
                }
                let w = if ops.is_empty() {
                    Ok(())
                } else {
                    self.commit(ops).await
                };
                if w.is_err() {
                    self.store.discard_films(files.iter().map(Vec::as_slice));
                }
                w
            }
        };
        let merge_start = Instant::now();
        let mut to_write = Vec::new();
        let mut merges = Vec::new();
        {
            let mut st = self.state.lock().expect("state lock");
            let st = &mut *st;
            if let Err(e) = write {
                // Nothing of these results is recorded. Each lease goes back
                // to its holder, as if the result had never come: the worker
                // sends it again (or the lease expires and the unit is
                // queued), and the resend is not mistaken for a duplicate.
                let deadline = Instant::now() + self.config.lease_timeout;
                for (_, t) in taken {
                    st.consumed.remove(&t.lease_id);
                    if st.jobs.get(&t.job).is_some_and(|j| !j.state.is_terminal()) {
                        if let Some(w) = st.workers.get_mut(&t.lease.worker) {
                            w.leases.insert(t.lease_id.clone());
                        }
                        st.leases.insert(
                            t.lease_id,
                            Lease {
                                deadline,
                                ..t.lease
                            },
                        );
                    } else {
                        st.gone.insert(t.lease_id, t.job);
                    }
                }
                return Err(e.into());
            }
            let mut taken = taken.into_iter();
            for outcome in outcomes.iter_mut().filter(|o| o.is_none()) {
                let (r, t) = taken.next().expect("one taken result per open outcome");
                *outcome = Some(self.finish_result(st, r, t, &mut to_write, &mut merges)?);
            }
        }
        // Films merge into their frames outside the state lock, in parallel
        // (rayon) and off the async threads; each frame is complete only
        // once its last merge is in.
        let merged = if merges.is_empty() {
            Vec::new()
        } else {
            tokio::task::spawn_blocking(move || {
                merges
                    .into_iter()
                    .map(|m| (m.run(), m.job, m.frame))
                    .collect::<Vec<_>>()
            })
            .await
            .map_err(|e| FarmError::Internal(format!("merge task failed: {e}")))?
        };
        let mut merge_error = None;
        if !merged.is_empty() {
            let mut st = self.state.lock().expect("state lock");
            for (result, job_id, frame) in merged {
                if let Err(e) = result {
                    tracing::error!(job = %job_id, frame, error = %e, "cannot merge a result into its frame");
                    merge_error = Some(FarmError::Internal(e.to_string()));
                }
                let Some(job) = st.jobs.get_mut(&job_id) else {
                    continue;
                };
                if let Some(acc) = job.frames.get_mut(&frame) {
                    acc.merging -= 1;
                }
                if !job.state.is_terminal() {
                    to_write.extend(job.complete_frames());
                }
            }
        }
        tracing::debug!(
            results = outcomes.len(),
            pixels,
            check_ms = (lock_start - check_start).as_secs_f64() * 1e3,
            take_ms = (encode_start - lock_start).as_secs_f64() * 1e3,
            encode_ms = (commit_start - encode_start).as_secs_f64() * 1e3,
            commit_ms = (merge_start - commit_start).as_secs_f64() * 1e3,
            merge_ms = merge_start.elapsed().as_secs_f64() * 1e3,
            "results committed"
        );
        for (job, frame) in to_write {
            self.clone().spawn_frame_write(job, frame);
        }
        if let Some(e) = merge_error {
            return Err(e);
        }
        Ok(outcomes
            .into_iter()
            .map(|o| o.expect("every result judged"))
            .collect())
    }

    /// Takes a result's lease for commit, or says why not (counting late,
    /// duplicate and rejected results, and recording failures).
    #[allow(clippy::result_large_err)] // internal, short-lived: the refusal is consumed by the caller at once
    fn take(
        &self,
        st: &mut State,
        r: &ResultData,
        film_check: Result<(), String>,
    ) -> Result<Taken, Refused> {
        if let Some(w) = st.workers.get_mut(&r.worker_id) {
            w.last_seen = Instant::now();
        }
        let Some(lease) = st.leases.get(&r.lease_id) else {
            let (outcome, job) = if let Some(job) = st.consumed.get(&r.lease_id) {
                (
                    Outcome::Duplicate(format!(
                        "lease {} was already completed; result dropped",
                        r.lease_id
                    )),
                    Some(job.clone()),
                )
            } else if let Some(job) = st.gone.get(&r.lease_id) {
                (
                    Outcome::Late(format!(
                        "lease {} expired or was withdrawn; result dropped",
                        r.lease_id
                    )),
                    Some(job.clone()),
                )
            } else {
                self.results_unknown_lease
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                (
                    Outcome::Late(format!(
                        "lease {} is unknown (expired before a coordinator restart, or never granted); result dropped",
                        r.lease_id
                    )),
                    None,
                )
            };
            let mut snapshot = None;
            if let Some(job) = job.and_then(|j| st.jobs.get_mut(&j)) {
                match outcome {
                    Outcome::Duplicate(_) => job.counters.results_duplicate += 1,
                    _ => job.counters.results_late += 1,
                }
                snapshot = Some((job.rec.id.clone(), job.counters.clone()));
            }
            tracing::warn!(worker = %public_worker_id(&r.worker_id), lease = %r.lease_id, outcome = ?outcome, "result dropped");
            return Err((outcome, None, snapshot));
        };
        if lease.worker != r.worker_id {
            // Refused for the whole request by `take_results` already.
            return Err((
                Outcome::Rejected(format!("lease {} is another worker's", r.lease_id)),
                None,
                None,
            ));
        }
        let lease = st.leases.remove(&r.lease_id).expect("present");
        if let Some(w) = st.workers.get_mut(&r.worker_id) {
            w.leases.remove(&r.lease_id);
        }
        let Some(job) = st.jobs.get_mut(&lease.job) else {
            return Err((Outcome::Late("the job no longer exists".into()), None, None));
        };
        if let Some(msg) = &r.failure {
            let worker_name = st.workers.get_mut(&r.worker_id).map_or_else(
                || public_worker_id(&r.worker_id),
                |w| {
                    w.units_failed += lease.units.len() as u64;
                    w.name.clone()
                },
            );
            tracing::warn!(job = %lease.job, worker = %worker_name, frame = lease.region.frame, rect = ?lease.region.rect, error = %msg, "unit failed on worker");
            let mut scene_failed = None;
            if let Some(job) = st.jobs.get_mut(&lease.job) {
                // The job's own blocklist settings (set at submit), else the
                // coordinator's.
                let after = job
                    .rec
                    .blocklist_after
                    .unwrap_or(self.config.blocklist_after);
                let for_ = job
                    .rec
                    .blocklist_seconds
                    .map_or(self.config.blocklist_for, |s| {
                        std::time::Duration::try_from_secs_f64(s)
                            .unwrap_or(self.config.blocklist_for)
                    });
                job.count_failure(
                    &r.worker_id,
                    &worker_name,
                    lease.units.len() as u32,
                    after,
                    for_,
                );
                scene_failed = job.count_class(r.failure_class, &r.worker_id, &worker_name, msg);
                if let Some(w) = st.workers.get(&r.worker_id) {
                    job.reroute(
                        &lease.units,
                        r.failure_class,
                        &r.worker_id,
                        &worker_name,
                        &w.labels,
                    );
                }
            }
            if let Some(rec) = scene_failed {
                st.end_lease(r.lease_id.clone(), lease.job.clone(), false);
                self.withdraw_leases(st, &rec.id);
                return Err((Outcome::FailureRecorded, Some(rec), None));
            }
            let rec = if st.partner_keeps(&r.lease_id, &lease) {
                None
            } else {
                let job = st.jobs.get_mut(&lease.job).expect("checked");
                job.fail_units(
                    &lease.units,
                    &r.worker_id,
                    format!("worker {worker_name}: {msg}"),
                )
            };
            st.end_lease(r.lease_id.clone(), lease.job.clone(), false);
            if let Some(rec) = &rec {
                self.withdraw_leases(st, &rec.id);
            }
            return Err((Outcome::FailureRecorded, rec, None));
        }
        if let Err(reason) = validate_result(&lease, r, film_check) {
            let mut strikes = 0;
            let worker_name = st.workers.get_mut(&r.worker_id).map_or_else(
                || public_worker_id(&r.worker_id),
                |w| {
                    w.units_failed += lease.units.len() as u64;
                    w.malformed_in_a_row += 1;
                    strikes = w.malformed_in_a_row;
                    w.name.clone()
                },
            );
            job.counters.results_rejected += 1;
            let snapshot = Some((job.rec.id.clone(), job.counters.clone()));
            tracing::warn!(job = %lease.job, worker = %worker_name, lease = %r.lease_id, malformed_in_a_row = strikes, %reason, "result rejected");
            let rec = if st.partner_keeps(&r.lease_id, &lease) {
                None
            } else {
                let job = st.jobs.get_mut(&lease.job).expect("checked");
                job.fail_units(
                    &lease.units,
                    &r.worker_id,
                    format!("worker {worker_name} sent a malformed result: {reason}"),
                )
            };
            st.end_lease(r.lease_id.clone(), lease.job.clone(), false);
            if let Some(rec) = &rec {
                self.withdraw_leases(st, &rec.id);
            }
            if strikes >= self.config.quarantine_after {
                self.quarantine(st, &r.worker_id);
            }
            return Err((Outcome::Rejected(reason), rec, snapshot));
        }
        let units = lease.units.clone();
        st.withdraw_partners(&lease);
        st.end_lease(r.lease_id.clone(), lease.job.clone(), true);
        Ok(Taken {
            job: lease.job.clone(),
            units,
            frame: lease.region.frame,
            lease_id: r.lease_id.clone(),
            lease,
        })
    }

    /// Marks a committed result's units done and merges its film into its frame.
    fn finish_result(
        &self,
        st: &mut State,
        r: ResultData,
        t: Taken,
        to_write: &mut Vec<(String, u32)>,
        merges: &mut Vec<Merge>,
    ) -> Result<Outcome, FarmError> {
        let Some(job) = st.jobs.get_mut(&t.job) else {
            return Ok(Outcome::Late("the job no longer exists".into()));
        };
        let mut film = r.film.expect("validated");
        job.counters.units_accepted += t.units.len() as u64;
        let mut samples = 0;
        let work_before = job.work_left;
        for &u in &t.units {
            let unit = job.layout.unit(u);
            let nominal = job.layout.unit_samples(unit);
            let tile = job.layout.tiles[unit.tile as usize];
            job.mark_done(u);
            // An adaptive round samples only its active blocks.
            let traced = job.adaptive_samples(&film, tile).unwrap_or(nominal);
            job.correct_samples(unit.frame, nominal, traced);
            samples += traced;
        }
        job.meter.add(Instant::now(), work_before - job.work_left);
        job.samples_this_run += samples;
        self.metrics.samples(samples);
        let now = now_ms();
        if job.first_result_unix_ms == 0 {
            job.first_result_unix_ms = now;
        }
        job.last_result_unix_ms = now;
        job.rays_this_run = job.rays_this_run.saturating_add(film.rays.total());
        let rays = [
            film.rays.primary,
            film.rays.shadow,
            film.rays.reflection,
            film.rays.refraction,
        ];
        for (a, b) in job.counters.rays.iter_mut().zip(rays) {
            *a = a.saturating_add(b);
        }
        let result_rays = film.rays.total();
        if !job.state.is_terminal() {
            let (w, h) = (job.layout.width, job.layout.height);
            if job.image_mode() {
                // The image mode: its runs booked and merged under the
                // lock, and the frame's next round decided once every tile
                // of this one is in (the barrier).
                job.image_merge(t.frame, &mut film)
                    .map_err(FarmError::Internal)?;
                let round = job.layout.unit(t.units[0]).batch;
                if job.image_advance(t.frame, round) {
                    self.work_ready.notify_waiters();
                }
            } else if job.adaptive.is_some() {
                let acc = job.frames.get_mut(&t.frame).expect("frame of a unit");
                // Adaptive jobs merge now, under the state lock: a tile's
                // next round is decided from its merged film (tiles are
                // small, so this holds the lock briefly).
                acc.film
                    .lock()
                    .expect("frame film lock")
                    .get_or_insert_with(|| new_frame_film(w, h, true))
                    .merge(&film)
                    .map_err(|e| FarmError::Internal(e.to_string()))?;
                let mut queued = false;
                for &u in &t.units {
                    queued |= job.adaptive_advance(t.frame, job.layout.unit(u).tile);
                }
                if queued {
                    self.work_ready.notify_waiters();
                }
            } else {
                let acc = job.frames.get_mut(&t.frame).expect("frame of a unit");
                acc.merging += 1;
                merges.push(Merge {
                    job: t.job.clone(),
                    frame: t.frame,
                    into: acc.film.clone(),
                    film,
                    frame_rect: Rect::full(w, h),
                });
            }
            to_write.extend(job.complete_frames());
        }
        job.notify();
        if let Some(w) = st.workers.get_mut(&r.worker_id) {
            w.malformed_in_a_row = 0;
            w.units_done += t.units.len() as u64;
            if r.render_seconds > 0.0 {
                // Times under 0.1 ms are taken as 0.1 ms, so an absurd
                // report (5e-324 s) gives a finite speed.
                let seconds = r.render_seconds.max(1e-4);
                w.speed.add(Instant::now(), samples, result_rays, seconds);
                if !t.lease.rated {
                    w.rate_unit(result_rays as f64, seconds);
                }
            }
        }
        Ok(Outcome::Accepted)
    }
}

/// A result's lease, taken for commit.
struct Taken {
    job: String,
    /// The lease's units.
    units: Vec<u32>,
    frame: u32,
    /// The lease, to give back to its holder if the commit fails.
    lease_id: String,
    lease: Lease,
}
/// A result not taken: its outcome, and a job record and counters to persist.
type Refused = (Outcome, Option<JobRecord>, Option<(String, Counters)>);

/// Checks every pixel of a result against the rect and samples it claims:
/// exactly that many samples each, sums in range (before the state lock:
/// [`validate_result`] then checks the claims against the lease).
/// Pixels a task checks: large enough that a CPU worker's small result is
/// one task.
const CHECK_CHUNK: usize = 1 << 16;

fn check_film(r: &ResultData) -> Result<(), String> {
    let Ok(film) = &r.film else {
        return Ok(()); // Judged by validate_result.
    };
    if film.squares.is_some() {
        // Adaptive: which pixels have samples depends on the lease's
        // active blocks, so validate_result checks them under the lock.
        return Ok(());
    }
    let n = r.samples.len();
    let max_sum = (MAX_SAMPLE_VALUE * FIXED_ONE) as u64 * n as u64;
    // One pass without branches, in parallel chunks (a GPU worker's result
    // is a million pixels); the offending pixel is looked for only when
    // there is one.
    use rayon::prelude::*;
    let bad = film
        .counts
        .par_chunks(CHECK_CHUNK)
        .zip(film.sums.par_chunks(CHECK_CHUNK))
        .any(|(counts, sums)| {
            counts.iter().zip(sums).fold(false, |bad, (&c, s)| {
                bad | (c != n) | (s[0] > max_sum) | (s[1] > max_sum) | (s[2] > max_sum)
            })
        });
    if !bad {
        return Ok(());
    }
    let width = film.rect.width.max(1);
    for (i, (&c, s)) in film.counts.iter().zip(&film.sums).enumerate() {
        let (x, y) = (
            film.rect.x + i as u32 % width,
            film.rect.y + i as u32 / width,
        );
        if c != n {
            return Err(format!("pixel ({x}, {y}) has {c} samples, expected {n}"));
        }
        if s.iter().any(|&v| v > max_sum) {
            return Err(format!(
                "pixel ({x}, {y}) has a sum beyond the largest radiance of {n} samples"
            ));
        }
    }
    Ok(())
}

/// Checks a result against its lease: same rect and samples, well-formed
/// data, and the outcome of [`check_film`] on its pixels.
fn validate_result(
    lease: &Lease,
    r: &ResultData,
    film_check: Result<(), String>,
) -> Result<(), String> {
    if r.rect != lease.region.rect {
        return Err(format!(
            "result rect {:?} does not match the leased rect {:?}",
            r.rect, lease.region.rect
        ));
    }
    if r.samples != lease.region.samples {
        return Err(format!(
            "result samples {}..{} do not match the leased samples {}..{}",
            r.samples.start, r.samples.end, lease.region.samples.start, lease.region.samples.end
        ));
    }
    let film = r.film.as_ref().map_err(Clone::clone)?;
    // The film's own rect is the result's (it decoded to that size).
    if film.rect != lease.region.rect {
        return Err(format!(
            "result film rect {:?} does not match the leased rect {:?}",
            film.rect, lease.region.rect
        ));
    }
    adaptive::check_result(lease, film)?;
    if lease.active.is_some() {
        // An adaptive round: its pixels are checked here, against the
        // lease's active blocks (check_film passes films with squares).
        for (i, (&c, s)) in film.counts.iter().zip(&film.sums).enumerate() {
            let (x, y) = (
                lease.region.rect.x + i as u32 % lease.region.rect.width,
                lease.region.rect.y + i as u32 / lease.region.rect.width,
            );
            // All of the round's samples in active blocks, none elsewhere.
            let n = adaptive::expected_count(lease, x, y);
            let max_sum = (MAX_SAMPLE_VALUE * FIXED_ONE) as u64 * n as u64;
            if c != n {
                return Err(format!("pixel ({x}, {y}) has {c} samples, expected {n}"));
            }
            if s.iter().any(|&v| v > max_sum) {
                return Err(format!(
                    "pixel ({x}, {y}) has a sum beyond the largest radiance of {n} samples"
                ));
            }
        }
    } else {
        film_check?;
    }
    adaptive::check_runs(lease, film)?;
    let primary = adaptive::sampled_pixel_samples(lease);
    if film.rays.primary != primary {
        return Err(format!(
            "result counts {} primary rays, the unit has {primary}",
            film.rays.primary
        ));
    }
    // Far above any real ray tree (2^32 rays a sample), far below wrapping.
    let most = primary.saturating_mul(1 << 32);
    for (kind, count) in [
        ("shadow", film.rays.shadow),
        ("reflection", film.rays.reflection),
        ("refraction", film.rays.refraction),
    ] {
        if count > most {
            return Err(format!(
                "result counts {count} {kind} rays, more than 2^32 a sample"
            ));
        }
    }
    if film.nonfinite > primary {
        return Err(format!(
            "result counts {} non-finite samples, the unit has {primary} samples",
            film.nonfinite
        ));
    }
    if !(r.render_seconds.is_finite() && r.render_seconds >= 0.0) {
        return Err(format!(
            "render_seconds must be finite and >= 0, got {}",
            r.render_seconds
        ));
    }
    Ok(())
}
