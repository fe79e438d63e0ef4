//! Looking into the farm for the web monitor: a frame's tiles and partial
//! image, a job's failures, the leases out; and the one change the monitor
//! makes that the gRPC API has no call for, a job's priority.
//!
//! Every look takes the state lock for a short, bounded section: a preview
//! copies at most `max_side` x `max_side` pixels' sums, whatever the frame's
//! size, and resolves and encodes them after the lock is released. The
//! farm's result intake waits on the same lock, so nothing here walks a
//! whole frame.

use std::path::PathBuf;
use std::sync::Arc;

use tracer_core::film::{Film, Rect, WorkRegion};

use super::{Farm, FarmError, JobView};
use crate::store::Op;
use crate::units::Unit;

/// How a tile of a frame stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TileState {
    /// Every sample batch of it is merged.
    Done,
    /// A worker holds a lease on some of it.
    Leased,
    /// Some sample batches merged, the others waiting for a worker.
    Partial,
    /// Nothing merged yet, waiting for a worker.
    Pending,
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FrameTile {
    pub rect: Rect,
    pub state: TileState,
    pub batches_done: u32,
    pub batches: u32,
}

/// A unit's failed attempts, with the workers' messages.
#[derive(Clone, Debug)]
pub struct UnitFailure {
    pub unit: u32,
    /// The unit's frame, tile and sample batch.
    pub region: WorkRegion,
    pub messages: Vec<String>,
}

#[derive(Clone, Debug)]
pub struct LeaseSummary {
    pub worker_id: String,
    pub job_id: String,
    pub region: WorkRegion,
    /// Pixel-samples the worker reported done.
    pub progress: u64,
}

/// A frame's image as the monitor can show it now.
#[derive(Debug)]
pub enum FramePreview {
    /// The partial sums at every `step`-th pixel of every `step`-th row
    /// (from `step / 2`), `frame_units_done` of the frame's units merged.
    Partial {
        film: Film,
        step: u32,
        frame_units_done: u64,
    },
    /// As before: the frame's units done are still `frame_units_done`.
    Unchanged,
    /// The frame is complete and its image is on disk.
    Written(PathBuf),
    /// Complete and being written: its sums are with the writer.
    Writing,
}

/// The pixel stride that fits a `width` x `height` frame in `max_side`.
pub fn preview_step(width: u32, height: u32, max_side: u32) -> u32 {
    width.max(height).div_ceil(max_side.max(1)).max(1)
}

impl Farm {
    /// The tiles of one frame of a job, in row order.
    pub fn frame_tiles(&self, job_id: &str, frame: u32) -> Result<Vec<FrameTile>, FarmError> {
        let st = self.state.lock().expect("state lock");
        let job = st
            .jobs
            .get(job_id)
            .ok_or_else(|| FarmError::NotFound(format!("no job {job_id:?}")))?;
        if !job.frames.contains_key(&frame) {
            return Err(FarmError::NotFound(format!(
                "job {job_id} has no frame {frame}"
            )));
        }
        let layout = &job.layout;
        let batches = layout.batches.len() as u32;
        let written = job.frames[&frame].written.is_some();
        let mut leased = vec![false; layout.tiles.len()];
        for l in st
            .leases
            .values()
            .filter(|l| l.job == job_id && l.region.frame == frame)
        {
            for &u in &l.units {
                leased[layout.unit(u).tile as usize] = true;
            }
        }
        Ok((0..layout.tiles.len() as u32)
            .map(|tile| {
                let batches_done = if written {
                    batches
                } else {
                    (0..batches)
                        .filter(|&batch| {
                            job.done[layout.index(Unit { frame, tile, batch }) as usize]
                        })
                        .count() as u32
                };
                let state = if batches_done == batches {
                    TileState::Done
                } else if leased[tile as usize] {
                    TileState::Leased
                } else if batches_done > 0 {
                    TileState::Partial
                } else {
                    TileState::Pending
                };
                FrameTile {
                    rect: layout.tiles[tile as usize],
                    state,
                    batches_done,
                    batches,
                }
            })
            .collect())
    }

    /// A frame's image, subsampled to at most `max_side` pixels a side;
    /// `Unchanged` when `known_units_done` is how many of its units are
    /// still merged (the caller's copy is current), or when `recent` (the
    /// caller's copy is new enough) and the frame is not written: a look
    /// that copies nothing.
    pub fn frame_preview(
        &self,
        job_id: &str,
        frame: u32,
        max_side: u32,
        known_units_done: Option<u64>,
        recent: bool,
    ) -> Result<FramePreview, FarmError> {
        let st = self.state.lock().expect("state lock");
        let job = st
            .jobs
            .get(job_id)
            .ok_or_else(|| FarmError::NotFound(format!("no job {job_id:?}")))?;
        let acc = job
            .frames
            .get(&frame)
            .ok_or_else(|| FarmError::NotFound(format!("no frame {frame} in job {job_id}")))?;
        if let Some(name) = &acc.written {
            return Ok(FramePreview::Written(
                PathBuf::from(&job.rec.output_dir).join(name),
            ));
        }
        if acc.writing {
            return Ok(FramePreview::Writing);
        }
        // An ended job's unwritten frames lost their sums (`Job::finish`):
        // whatever the caller has is better than black.
        let ended = job.state.is_terminal() && known_units_done.is_some();
        if ended || recent || known_units_done == Some(acc.units_done) {
            return Ok(FramePreview::Unchanged);
        }
        let (w, h) = (job.layout.width, job.layout.height);
        let step = preview_step(w, h, max_side);
        let (ow, oh) = (w.div_ceil(step), h.div_ceil(step));
        let mut out = Film::new(Rect::full(ow, oh));
        // A frame with no result yet (or whose sums a cancel dropped) is black.
        // (The frame's film lock is held only for this copy.)
        if let Some(film) = acc.film.lock().expect("frame film lock").as_ref() {
            let off = step / 2;
            for oy in 0..oh {
                let y = (oy * step + off).min(h - 1);
                for ox in 0..ow {
                    let x = (ox * step + off).min(w - 1);
                    let src = (y * w + x) as usize;
                    let dst = (oy * ow + ox) as usize;
                    out.sums[dst] = film.sums[src];
                    out.counts[dst] = film.counts[src];
                }
            }
        }
        Ok(FramePreview::Partial {
            film: out,
            step,
            frame_units_done: acc.units_done,
        })
    }

    /// Units that failed, with every message, in unit order.
    pub fn job_failures(&self, job_id: &str) -> Result<Vec<UnitFailure>, FarmError> {
        let st = self.state.lock().expect("state lock");
        let job = st
            .jobs
            .get(job_id)
            .ok_or_else(|| FarmError::NotFound(format!("no job {job_id:?}")))?;
        let mut v: Vec<UnitFailure> = job
            .failures
            .iter()
            .map(|(&unit, failures)| {
                let u = job.layout.unit(unit);
                UnitFailure {
                    unit,
                    region: job.layout.region(u),
                    messages: failures.iter().map(|f| f.message.clone()).collect(),
                }
            })
            .collect();
        v.sort_by_key(|f| f.unit);
        Ok(v)
    }

    /// Every lease out now.
    pub fn lease_summaries(&self) -> Vec<LeaseSummary> {
        let st = self.state.lock().expect("state lock");
        st.leases
            .values()
            .map(|l| LeaseSummary {
                worker_id: super::public_worker_id(&l.worker),
                job_id: l.job.clone(),
                region: l.region,
                progress: l.progress,
            })
            .collect()
    }

    /// Changes the priority of a job that has not ended; leases follow it
    /// from the next request on.
    pub async fn set_priority(
        self: &Arc<Self>,
        job_id: &str,
        priority: i32,
    ) -> Result<JobView, FarmError> {
        let rec = {
            let mut st = self.state.lock().expect("state lock");
            let job = st
                .jobs
                .get_mut(job_id)
                .ok_or_else(|| FarmError::NotFound(format!("no job {job_id:?}")))?;
            if job.state.is_terminal() {
                return Err(FarmError::FailedPrecondition(format!(
                    "job {job_id} has ended; its priority no longer matters"
                )));
            }
            if job.rec.priority == priority {
                return Ok(job.view());
            }
            job.rec.priority = priority;
            job.notify();
            job.rec.clone()
        };
        tracing::info!(job = %job_id, priority, "job priority changed");
        self.commit(vec![Op::PutJob(rec)]).await?;
        self.job(job_id)
    }
}

impl Farm {
    /// The text of a `/metrics` scrape: the farm's gauges read now, under
    /// one short section of the state lock (counts only), with its
    /// counters and histograms.
    pub fn metrics_text(&self) -> String {
        use super::JobState;
        use crate::metrics::Gauges;
        use std::time::Instant;
        let mut g = Gauges {
            store_healthy: self.storage_ok(),
            asset_bytes: self.assets.held().1,
            ..Gauges::default()
        };
        {
            let st = self.state.lock().expect("state lock");
            for job in st.jobs.values() {
                let i = match job.state {
                    JobState::Queued => 0,
                    JobState::Running => 1,
                    JobState::Done => 2,
                    JobState::Failed => 3,
                    JobState::Cancelled => 4,
                    JobState::Waiting => 5,
                };
                g.jobs[i] += 1;
                // A job waiting for its parents has no unit a worker could
                // take: an autoscaler must not add workers for it.
                if !job.state.is_terminal() && job.state != JobState::Waiting {
                    g.units[0] += job.pending.len() as i64;
                }
            }
            // A backup lease covers units its original holds already.
            g.units[1] = st
                .leases
                .values()
                .filter(|l| !l.backup)
                .map(|l| l.units.len() as i64)
                .sum();
            let now = Instant::now();
            g.workers = st
                .workers
                .values()
                .map(|w| {
                    let backend = match w.backend {
                        tracer_core::render::Backend::Cpu => "cpu",
                        tracer_core::render::Backend::Gpu => "gpu",
                    };
                    let state = if w.quarantined_until.is_some_and(|t| t > now) {
                        "quarantined"
                    } else if w.leases.is_empty() {
                        "idle"
                    } else {
                        "busy"
                    };
                    (backend, state)
                })
                .collect();
        }
        self.metrics.encode(&g)
    }
}
