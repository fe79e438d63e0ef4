//! Job dependencies (`tessera submit --after`, issue 38): a job that runs
//! after others is [`JobState::Waiting`] (none of its units leased) until
//! every one of them is done, and fails, naming the parent, when one fails
//! or is cancelled. Nothing of it is stored beyond `JobRecord::after`: the
//! state is derived from the parents' states, at submit, whenever a job
//! ends, and again when the coordinator restarts. Called with the state
//! lock held.

use crate::store::JobRecord;

use super::{Farm, FarmError, Job, JobState, State};

/// What a waiting job's parents say of it.
enum Verdict {
    /// A parent has not ended yet.
    Wait,
    /// Every parent is done (or deleted, which only an ended job can be;
    /// one that failed took its dependents with it).
    Ready,
    /// A parent failed or was cancelled: why.
    Fail(String),
}

impl State {
    fn verdict(&self, job: &Job) -> Verdict {
        let mut wait = false;
        for p in &job.rec.after {
            let Some(parent) = self.jobs.get(p) else {
                continue;
            };
            match parent.state {
                JobState::Done => {}
                JobState::Failed => {
                    return Verdict::Fail(format!(
                        "job {p} ({}), which this job runs after (--after), failed: {}",
                        parent.rec.name, parent.rec.error
                    ));
                }
                JobState::Cancelled => {
                    return Verdict::Fail(format!(
                        "job {p} ({}), which this job runs after (--after), was cancelled",
                        parent.rec.name
                    ));
                }
                JobState::Waiting | JobState::Queued | JobState::Running => wait = true,
            }
        }
        if wait { Verdict::Wait } else { Verdict::Ready }
    }

    /// While `job` waits: the jobs it runs after that are not done yet.
    pub(super) fn waiting_for(&self, job: &Job) -> Vec<String> {
        if job.state != JobState::Waiting {
            return Vec::new();
        }
        job.rec
            .after
            .iter()
            .filter(|p| self.jobs.get(*p).is_some_and(|j| j.state != JobState::Done))
            .cloned()
            .collect()
    }

    /// Moves waiting jobs on after others ended (or were added): a job
    /// whose parents are all done is queued, one whose parent failed or
    /// was cancelled fails (and so, in turn, its own dependents). Returns
    /// the records of the jobs failed (to store) and whether one was queued.
    pub(super) fn settle_dependents(&mut self) -> (Vec<JobRecord>, bool) {
        let mut failed = Vec::new();
        let mut released = false;
        loop {
            let waiting: Vec<String> = self
                .jobs
                .iter()
                .filter(|(_, j)| j.state == JobState::Waiting)
                .map(|(id, _)| id.clone())
                .collect();
            let mut more = false;
            for id in waiting {
                let verdict = self.verdict(&self.jobs[&id]);
                let job = self.jobs.get_mut(&id).expect("listed");
                match verdict {
                    Verdict::Wait => {}
                    Verdict::Ready => {
                        tracing::info!(job = %id, name = %job.rec.name, after = ?job.rec.after,
                            "every job it runs after is done: queued");
                        job.state = JobState::Queued;
                        job.notify();
                        released = true;
                    }
                    Verdict::Fail(reason) => {
                        tracing::warn!(job = %id, name = %job.rec.name, %reason, "job failed");
                        job.finish(JobState::Failed, reason);
                        failed.push(job.rec.clone());
                        // Its own dependents are looked at again.
                        more = true;
                    }
                }
            }
            if !more {
                return (failed, released);
            }
        }
    }
}

impl Farm {
    /// Checks a submit's `--after` ids before anything is stored: each
    /// must name a job here that has not failed or been cancelled.
    pub(super) fn check_after(&self, after: &[String]) -> Result<Vec<String>, FarmError> {
        let st = self.state.lock().expect("state lock");
        let mut ids: Vec<String> = Vec::new();
        for p in after {
            let Some(parent) = st.jobs.get(p) else {
                return Err(FarmError::InvalidArgument(format!(
                    "--after {p}: no job {p:?} on this coordinator (`tessera jobs` lists them)"
                )));
            };
            if matches!(parent.state, JobState::Failed | JobState::Cancelled) {
                return Err(FarmError::FailedPrecondition(format!(
                    "--after {p}: job {p} ({}) has {}, so a job after it would never run",
                    parent.rec.name,
                    if parent.state == JobState::Failed {
                        "failed"
                    } else {
                        "been cancelled"
                    }
                )));
            }
            if !ids.contains(p) {
                ids.push(p.clone());
            }
        }
        Ok(ids)
    }

    /// Checks a submit's `--on-done` URLs: well formed, and a secret to
    /// sign their notifications with.
    pub(super) fn check_on_done(&self, urls: &[String]) -> Result<(), FarmError> {
        for u in urls {
            crate::notify::check_url("--on-done", u)
                .map_err(|e| FarmError::InvalidArgument(e.to_string()))?;
        }
        if !urls.is_empty() && self.notifier.secret.is_none() {
            return Err(FarmError::FailedPrecondition(
                "--on-done: this coordinator has no --notify-secret-file, so it cannot sign notifications; \
                 start it with one (docs/operations.md, \"Notifications\")"
                    .into(),
            ));
        }
        Ok(())
    }

    /// After jobs ended or were added under the lock: their dependents
    /// moved on ([`State::settle_dependents`]) and every job that ended
    /// handed to the notifier (`crate::notify`, which returns at once);
    /// the records to store.
    pub(super) fn jobs_ended(&self, st: &mut State) -> Vec<JobRecord> {
        let (failed, released) = st.settle_dependents();
        if released {
            self.work_ready.notify_waiters();
        }
        let ended: Vec<String> = st
            .jobs
            .iter()
            .filter(|(_, j)| j.state.is_terminal() && !j.announced)
            .map(|(id, _)| id.clone())
            .collect();
        let mut recs = failed;
        for id in ended {
            let job = st.jobs.get(&id).expect("listed");
            if self.notifier.wanted(&job.rec.on_done) {
                let status = crate::service::job_status(&st.view_of(job, job.view()));
                let notified = self.notified.clone();
                let job_id = id.clone();
                self.notifier.send(status, &job.rec.on_done, move || {
                    let _ = notified.send(job_id);
                });
                // Stored with its end: a restart before every delivery is
                // settled sends them again.
                let job = st.jobs.get_mut(&id).expect("listed");
                if !job.rec.notify_pending {
                    job.rec.notify_pending = true;
                    recs.push(job.rec.clone());
                }
            }
            st.jobs.get_mut(&id).expect("listed").announced = true;
        }
        recs
    }

    /// Every notification of job `id` delivered or given up: its record no
    /// longer asks a restart to send them.
    pub(super) async fn notifications_settled(&self, id: &str) {
        let rec = {
            let Ok(mut st) = self.state.lock() else {
                return;
            };
            let Some(job) = st.jobs.get_mut(id) else {
                return;
            };
            if !job.rec.notify_pending {
                return;
            }
            job.rec.notify_pending = false;
            job.rec.clone()
        };
        if let Err(e) = self.store.write(vec![crate::store::Op::PutJob(rec)]).await {
            tracing::error!(job = id, error = %e, "cannot record that the job's notifications are settled; a restart sends them again");
        }
    }
}
