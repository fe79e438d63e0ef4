//! The sender: packs finished units and submits them, batched, several
//! submissions at once, retrying what the coordinator could not record.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use tessera_proto::{film_codec, pb};
use tokio::sync::mpsc;
use tracer_core::film::WorkRegion;

use crate::heartbeat::HeldMap;
use crate::render::UnitEnd;
use crate::{Client, MAX_BATCH, MAX_BATCH_BYTES, SEND_IN_FLIGHT, SUBMIT_BACKOFF_MAX, SUBMIT_TRIES};

/// A finished unit on its way to the coordinator.
pub(crate) struct Outgoing {
    pub(crate) lease_id: String,
    pub(crate) region: WorkRegion,
    pub(crate) end: UnitEnd,
    /// The job's work units the lease covers.
    pub(crate) units: u64,
}

/// Packs finished units and submits them, batching whatever is ready, with
/// up to [`SEND_IN_FLIGHT`] submissions at once: the coordinator records
/// queued results in one commit, so a fast worker's results do not wait
/// for each other's round trips (and its renderer for the queue).
/// A submission the coordinator could not record (`Unavailable`: its
/// database write failed, or the connection broke) is sent again with
/// backoff; the leases stay held (heartbeated) meanwhile.
pub(crate) async fn send_results(
    client: Client,
    worker_id: String,
    mut rx: mpsc::Receiver<Outgoing>,
    held: HeldMap,
    units_done: Arc<AtomicU64>,
) -> Result<(), tonic::Status> {
    let mut sending = tokio::task::JoinSet::new();
    let mut open = true;
    while open || !sending.is_empty() {
        tokio::select! {
            Some(done) = sending.join_next(), if !sending.is_empty() => {
                done.map_err(|e| tonic::Status::internal(format!("result submission failed: {e}")))??;
            }
            next = rx.recv(), if open && sending.len() < SEND_IN_FLIGHT => {
                let Some(first) = next else {
                    open = false;
                    continue;
                };
                // Film bytes in the original layout: an upper bound.
                let bytes_of = |o: &Outgoing| o.region.rect.area() * (film_codec::SUM_BYTES + film_codec::COUNT_BYTES);
                let mut bytes = bytes_of(&first);
                let mut batch = vec![first];
                while batch.len() < MAX_BATCH && bytes < MAX_BATCH_BYTES {
                    match rx.try_recv() {
                        Ok(o) => {
                            bytes += bytes_of(&o);
                            batch.push(o);
                        }
                        Err(_) => break,
                    }
                }
                sending.spawn(send_batch(
                    client.clone(),
                    worker_id.clone(),
                    batch,
                    held.clone(),
                    units_done.clone(),
                ));
            }
        }
    }
    Ok(())
}

/// Packs and submits one batch of finished units, then settles their leases.
pub(crate) async fn send_batch(
    mut client: Client,
    worker_id: String,
    batch: Vec<Outgoing>,
    held: HeldMap,
    units_done: Arc<AtomicU64>,
) -> Result<(), tonic::Status> {
    let mut sent = Vec::with_capacity(batch.len());
    for o in batch {
        match &o.end {
            UnitEnd::Abandoned => {
                tracing::info!(lease = %o.lease_id, "lease gone; abandoned its unit");
                held.lock().expect("held lock").remove(&o.lease_id);
            }
            UnitEnd::Failed(msg, _) => {
                tracing::warn!(lease = %o.lease_id, error = %msg, "unit failed");
                sent.push(o);
            }
            UnitEnd::Film(..) => sent.push(o),
        }
    }
    if sent.is_empty() {
        return Ok(());
    }
    let send_start = Instant::now();
    let outcomes = submit_with_retry(&mut client, sent.len(), || {
        sent.iter().map(|o| result_request(&worker_id, o)).collect()
    })
    .await?;
    let mut h = held.lock().expect("held lock");
    for (o, resp) in sent.iter().zip(outcomes) {
        h.remove(&o.lease_id);
        match pb::ResultOutcome::try_from(resp.outcome).unwrap_or(pb::ResultOutcome::Unspecified) {
            pb::ResultOutcome::Accepted => {
                // The job's units, as the coordinator counts them for
                // `tessera workers`: a lease may span several.
                units_done.fetch_add(o.units, Ordering::Relaxed);
                tracing::debug!(
                    lease = %o.lease_id,
                    frame = o.region.frame,
                    rect = ?o.region.rect,
                    batch = sent.len(),
                    // Transfer and the coordinator's intake.
                    send_ms = send_start.elapsed().as_secs_f64() * 1e3,
                    "result accepted"
                );
            }
            pb::ResultOutcome::FailureRecorded => {}
            other => {
                tracing::warn!(lease = %o.lease_id, outcome = ?other, reason = %resp.reason, "result not accepted")
            }
        }
    }
    Ok(())
}

/// A finished unit (a film or a failure) as a result request.
pub(crate) fn result_request(worker_id: &str, o: &Outgoing) -> pb::SubmitResultRequest {
    let mut req = pb::SubmitResultRequest {
        worker_id: worker_id.to_string(),
        lease_id: o.lease_id.clone(),
        rect: Some(o.region.rect.into()),
        samples: Some(o.region.samples.into()),
        ..Default::default()
    };
    match &o.end {
        UnitEnd::Abandoned => {}
        UnitEnd::Failed(msg, class) => {
            req.failure = msg.clone();
            req.failure_class = *class as i32;
        }
        UnitEnd::Film(film, secs) => {
            film.fill(&mut req);
            req.render_seconds = *secs;
        }
    }
    req
}

/// One result as `SubmitResult`, several as one `SubmitResults`; retried
/// while the coordinator answers `Unavailable`.
pub(crate) async fn submit_with_retry(
    client: &mut Client,
    count: usize,
    requests: impl Fn() -> Vec<pb::SubmitResultRequest>,
) -> Result<Vec<pb::SubmitResultResponse>, tonic::Status> {
    let mut backoff = Duration::from_millis(100);
    let mut tries = 0;
    loop {
        tries += 1;
        let mut reqs = requests();
        let sent = if count == 1 {
            client
                .submit_result(reqs.pop().expect("one request"))
                .await
                .map(|r| vec![r.into_inner()])
        } else {
            client
                .submit_results(pb::SubmitResultsRequest { results: reqs })
                .await
                .map(|r| r.into_inner().outcomes)
        };
        match sent {
            Ok(outcomes) if outcomes.len() == count => return Ok(outcomes),
            Ok(outcomes) => {
                return Err(tonic::Status::internal(format!(
                    "the coordinator answered {} outcomes for {count} results",
                    outcomes.len(),
                )));
            }
            Err(e) if e.code() == tonic::Code::Unavailable && tries < SUBMIT_TRIES => {
                tracing::warn!(results = count, error = %e.message(), retry_in_ms = backoff.as_millis() as u64, "results not recorded; sending them again");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(SUBMIT_BACKOFF_MAX);
            }
            Err(e) => return Err(e),
        }
    }
}
