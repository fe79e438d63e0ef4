//! The render loop: takes the next leased unit, renders it (CPU in one
//! pass, GPU band by band, adaptive rounds by their active blocks) while
//! leasing the next, and queues the result for the sender.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use tessera_proto::pb;
use tokio::sync::{mpsc, watch};
use tracer_core::adaptive::BlockMask;
use tracer_core::film::{Film, Rect, SampleRange, WorkRegion};
use tracer_core::render::{Output, PreparedFrame, Rendered, Renderer};

use crate::sender::Outgoing;
use crate::session::{Session, lease};
use crate::unit::{self, Queued, UnitFilm};
use crate::{GPU_BAND_PIXEL_SAMPLES, IDLE_LEASE_WAIT, MAX_MESSAGE_BYTES, PREFETCH, Worker};

/// Why a unit's rectangle is refused: its result would not fit one
/// message, or its film (28 bytes a pixel) not this machine's memory.
pub(crate) fn too_large(rect: Rect) -> Option<String> {
    let bytes = rect.area() as u64 * 28;
    if bytes > MAX_MESSAGE_BYTES as u64 {
        return Some(format!(
            "a lease of {}x{} pixels makes a {bytes}-byte result, over this worker's {MAX_MESSAGE_BYTES}-byte message limit",
            rect.width, rect.height
        ));
    }
    let mut probe: Vec<u8> = Vec::new();
    if probe.try_reserve_exact(2 * bytes as usize).is_err() {
        return Some(format!(
            "a lease of {}x{} pixels needs {bytes} bytes twice over, more than this worker can allocate",
            rect.width, rect.height
        ));
    }
    None
}

/// How rendering a unit ended: its film and render seconds, a failure
/// (its message and class), or nothing (the lease went away).
pub(crate) enum UnitEnd {
    Film(UnitFilm, f64),
    Failed(String, pb::FailureClass),
    Abandoned,
}

/// A renderer's failure, its class read from its message: the GPU
/// backend's errors (tracer-core, wgpu) carry no kind a caller can match,
/// but name an exhausted memory or a lost device in their text.
fn render_failed(message: String) -> UnitEnd {
    let m = message.to_ascii_lowercase();
    let class = if m.contains("out of memory") || m.contains("outofmemory") {
        pb::FailureClass::OutOfMemory
    } else if m.contains("device lost") || m.contains("devicelost") || m.contains("device was lost")
    {
        pb::FailureClass::GpuLost
    } else {
        pb::FailureClass::Unspecified
    };
    UnitEnd::Failed(message, class)
}

impl Worker {
    pub(crate) async fn render_loop(
        &mut self,
        s: &Session,
        drain: &mut watch::Receiver<bool>,
        lost: &AtomicBool,
        tx: &mpsc::Sender<Outgoing>,
        queue: &mut VecDeque<Queued>,
        sender: &mut tokio::task::JoinHandle<Result<(), tonic::Status>>,
    ) -> Result<(), tonic::Status> {
        let mut client = s.client.clone();
        // Units rendered since the last lease request, reported with the next.
        let mut rendered = Vec::new();
        loop {
            if *drain.borrow() {
                return Ok(());
            }
            if lost.load(Ordering::Relaxed) {
                return Err(tonic::Status::unavailable(
                    "the coordinator no longer knows this worker",
                ));
            }
            if sender.is_finished() {
                return match sender.await {
                    Ok(Err(e)) => Err(e),
                    _ => Err(tonic::Status::internal("the result sender stopped")),
                };
            }
            let Some(unit) = queue.pop_front() else {
                // Idle: wait at the coordinator for work (long poll).
                let retry_after = lease(
                    &mut client,
                    &s.worker_id,
                    &self.held,
                    queue,
                    false,
                    IDLE_LEASE_WAIT,
                    &mut rendered,
                )
                .await?;
                if queue.is_empty() {
                    tokio::select! {
                        _ = tokio::time::sleep(retry_after) => {}
                        _ = drain.changed() => {}
                    }
                }
                continue;
            };
            let Some((cancel, samples_done)) = self
                .held
                .lock()
                .expect("held lock")
                .get(unit::lease_id(&unit))
                .map(|h| (h.cancel.clone(), h.samples_done.clone()))
            else {
                continue;
            };
            let (lease_id, region, units, work) = match unit {
                Ok(u) => (
                    u.lease_id,
                    u.region,
                    u.units,
                    Ok((u.job, u.active, u.ranges)),
                ),
                Err(m) => (m.lease_id, m.region, m.units, Err(m.why)),
            };
            let out = |end| Outgoing {
                lease_id: lease_id.clone(),
                region,
                end,
                units: units.into(),
            };
            if cancel.load(Ordering::Relaxed) {
                // Gone while queued (expired, cancelled): nothing to send.
                self.held.lock().expect("held lock").remove(&lease_id);
                tracing::info!(lease = %lease_id, "lease gone; abandoned its unit");
                continue;
            }
            // A lease this worker cannot hold or send back (a coordinator
            // gone wrong), or one that came malformed: a failure the
            // coordinator counts, not an abort.
            let (job, active, ranges) = match too_large(region.rect).map_or(work, Err) {
                Ok(work) => work,
                Err(why) => {
                    tracing::warn!(lease = %lease_id, "{why}");
                    if tx
                        .send(out(UnitEnd::Failed(why, pb::FailureClass::Unspecified)))
                        .await
                        .is_err()
                    {
                        return Err(tonic::Status::internal("the result sender stopped"));
                    }
                    continue;
                }
            };
            let end = match self.prepare(&mut client, &job, region.frame).await {
                Err(e)
                    if e.code() == tonic::Code::Unavailable || e.code() == tonic::Code::Unknown =>
                {
                    return Err(e);
                }
                // The job's scene or files do not load here: a scene error
                // (one a second worker reproduces fails the job at once).
                Err(e) if e.code() == tonic::Code::InvalidArgument => {
                    UnitEnd::Failed(e.message().to_string(), pb::FailureClass::Scene)
                }
                Err(e) => UnitEnd::Failed(e.message().to_string(), pb::FailureClass::Unspecified),
                Ok(prepared) => {
                    let renderer = self.renderer.clone();
                    // Adaptive jobs: the round's active blocks (in the image
                    // mode, each over its own range).
                    let render = tokio::task::spawn_blocking(move || match active {
                        None => render_unit(&renderer, &prepared, region, &cancel, &samples_done),
                        Some(mask) => render_round_unit(
                            &renderer,
                            &prepared,
                            region,
                            &mask,
                            ranges.as_deref(),
                            &cancel,
                            &samples_done,
                        ),
                    });
                    let render = async {
                        render.await.unwrap_or_else(|e| {
                            UnitEnd::Failed(
                                format!("render panicked: {e}"),
                                pb::FailureClass::WorkerCrash,
                            )
                        })
                    };
                    // Lease the next unit while this one renders, unless draining.
                    if queue.len() < PREFETCH && !*drain.borrow() {
                        // No long poll here: the result must not wait for work to appear.
                        let (end, leased) = tokio::join!(
                            render,
                            lease(
                                &mut client,
                                &s.worker_id,
                                &self.held,
                                queue,
                                true,
                                Duration::ZERO,
                                &mut rendered,
                            )
                        );
                        if let Err(e) = leased {
                            let _ = tx.send(out(end)).await;
                            return Err(e);
                        }
                        end
                    } else {
                        render.await
                    }
                }
            };
            if let UnitEnd::Film(film, seconds) = &end {
                tracing::debug!(lease = %lease_id, frame = region.frame, rect = ?region.rect, seconds, "unit rendered");
                rendered.push(pb::RenderedUnit {
                    lease_id: lease_id.clone(),
                    rays: film.rays.total(),
                    render_seconds: *seconds,
                });
            }
            if tx.send(out(end)).await.is_err() {
                return Err(tonic::Status::internal("the result sender stopped"));
            }
        }
    }
}

/// GPU bands: whole rows, about [`GPU_BAND_PIXEL_SAMPLES`] each.
pub(crate) fn gpu_band_rows(rect: Rect, samples: SampleRange) -> u32 {
    let per_row = rect.width.max(1) as u64 * samples.len().max(1) as u64;
    (GPU_BAND_PIXEL_SAMPLES / per_row).clamp(1, rect.height.max(1) as u64) as u32
}

/// Renders a unit, stopping early when `cancel` is set: on the CPU in one
/// pass, on the GPU band by band (one dispatch each).
// Without the `gpu` feature the CPU is the only renderer.
#[cfg_attr(not(feature = "gpu"), allow(irrefutable_let_patterns))]
pub(crate) fn render_unit(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    region: WorkRegion,
    cancel: &AtomicBool,
    samples_done: &AtomicU64,
) -> UnitEnd {
    let WorkRegion {
        frame,
        rect,
        samples,
    } = region;
    let start = Instant::now();
    let progress = |n| {
        samples_done.fetch_add(n, Ordering::Relaxed);
    };
    // The whole unit in one call: on the CPU one parallel pass that checks
    // `cancel` before each of its tiles (bands would each end in a barrier
    // where one thread waits for another's last tile); on the GPU a unit
    // of one band, packed there, only its bytes read back.
    #[cfg(feature = "gpu")]
    let whole = matches!(renderer, Renderer::Cpu(_)) || gpu_band_rows(rect, samples) >= rect.height;
    #[cfg(not(feature = "gpu"))]
    let whole = true;
    if whole {
        return match renderer.render_as(prepared, region, Output::FarmResult, &progress, cancel) {
            Ok(Some(Rendered::Film(film))) => rendered(&film, start),
            #[cfg(feature = "gpu")]
            Ok(Some(Rendered::Packed(p))) => {
                UnitEnd::Film(UnitFilm::of_gpu(p), start.elapsed().as_secs_f64())
            }
            Ok(Some(_)) => unreachable!("asked for the farm's result"),
            Ok(None) => UnitEnd::Abandoned,
            Err(e) => render_failed(e.to_string()),
        };
    }
    let rows = gpu_band_rows(rect, samples);
    let mut film = Film::new(rect);
    let mut y = rect.y;
    while y < rect.y + rect.height {
        if cancel.load(Ordering::Relaxed) {
            return UnitEnd::Abandoned;
        }
        let band = Rect::new(rect.x, y, rect.width, rows.min(rect.y + rect.height - y));
        match renderer.render(prepared, WorkRegion::new(frame, band, samples), &progress) {
            // The whole unit in one call: no copy into the unit's film.
            Ok(part) if band == rect => {
                film = part;
            }
            Ok(part) => {
                if let Err(e) = film.merge(&part) {
                    return render_failed(e.to_string());
                }
            }
            Err(e) => return render_failed(e.to_string()),
        }
        y += band.height;
    }
    rendered(&film, start)
}

/// A rendered film, packed for the wire, with its render seconds (packing
/// not counted: the coordinator's speed model reads rendering alone).
pub(crate) fn rendered(film: &Film, start: Instant) -> UnitEnd {
    let seconds = start.elapsed().as_secs_f64();
    let pack_start = Instant::now();
    let film = UnitFilm::of_film(film);
    tracing::debug!(
        pack_ms = pack_start.elapsed().as_secs_f64() * 1e3,
        "unit packed"
    );
    UnitEnd::Film(film, seconds)
}

/// Renders a round of an adaptive unit in one call: its active blocks
/// over the unit's samples (`tracer_core::render::adaptive::render_round`),
/// or in the image mode each block over its own range (`render_ranges`,
/// whose result carries the runs of blocks with their rays: the blocks'
/// costs). Not cancelled midway (a round is short), only before it starts.
pub(crate) fn render_round_unit(
    renderer: &Renderer,
    prepared: &PreparedFrame,
    region: WorkRegion,
    mask: &BlockMask,
    ranges: Option<&[SampleRange]>,
    cancel: &AtomicBool,
    samples_done: &AtomicU64,
) -> UnitEnd {
    if cancel.load(Ordering::Relaxed) {
        return UnitEnd::Abandoned;
    }
    let start = Instant::now();
    let progress = |n| {
        samples_done.fetch_add(n, Ordering::Relaxed);
    };
    use tracer_core::render::adaptive::{render_ranges, render_round};
    let film = match ranges {
        None => render_round(
            renderer,
            prepared,
            region.frame,
            mask,
            region.samples,
            &progress,
        )
        .map(|mut film| {
            // Costs are the image mode's; a per-pixel round sends none.
            film.runs.clear();
            film
        }),
        Some(ranges) => {
            let (from, to): (Vec<u32>, Vec<u32>) = ranges.iter().map(|r| (r.start, r.end)).unzip();
            render_ranges(
                renderer,
                prepared,
                region.frame,
                region.rect,
                &from,
                &to,
                &progress,
            )
        }
    };
    match film {
        Ok(film) => rendered(&film, start),
        Err(e) => render_failed(e.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tracer_core::render::CpuRenderer;
    use tracer_core::render::Precision;
    use tracer_core::scene::SceneDesc;

    #[test]
    fn leases_too_large_to_send_back_are_refused_as_failures() {
        assert_eq!(too_large(Rect::new(0, 0, 1024, 1024)), None);
        let e = too_large(Rect::new(0, 0, 5000, 5000)).unwrap();
        assert_eq!(
            e,
            "a lease of 5000x5000 pixels makes a 700000000-byte result, over this worker's 268435456-byte message limit"
        );
    }

    /// A GPU unit is packed on the GPU ([`UnitFilm::of_gpu`]) into exactly
    /// the bytes the host packs from the same render's film: every sum
    /// width the sample counts give (4 to 6 bytes here), rects off the
    /// origin whose pixel count is not a multiple of the kernel's 4.
    #[cfg(feature = "gpu")]
    #[test]
    fn a_gpu_unit_is_packed_on_the_gpu_as_the_host_packs_its_film() {
        use tracer_core::render::{GpuOptions, GpuRenderer};
        let Some(gpu) = crate::prereq::require(
            "gpu",
            GpuRenderer::new(
                std::env::var("TESSERA_TEST_ADAPTER").ok().as_deref(),
                GpuOptions::default(),
            ),
        ) else {
            return;
        };
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../examples/resolution.toml");
        let desc = SceneDesc::load(path).unwrap();
        let mut settings = desc.render;
        (settings.width, settings.height, settings.samples) = (97, 61, 4000);
        let prepared = PreparedFrame::build(&desc, &settings, 0, Precision::F32).unwrap();
        let renderer = Renderer::Gpu(Box::new(gpu));
        let Renderer::Gpu(gpu) = &renderer else {
            unreachable!()
        };
        let mut widths = std::collections::BTreeSet::new();
        for (rect, samples) in [
            (Rect::new(0, 0, 97, 61), SampleRange { start: 0, end: 1 }),
            (Rect::new(3, 5, 31, 7), SampleRange { start: 2, end: 9 }),
            (Rect::new(10, 1, 13, 13), SampleRange { start: 0, end: 300 }),
            (
                Rect::new(40, 20, 9, 9),
                SampleRange {
                    start: 0,
                    end: 4000,
                },
            ),
        ] {
            let region = WorkRegion::new(0, rect, samples);
            let film = gpu
                .render(&prepared, WorkRegion::new(0, rect, samples), &|_| {})
                .unwrap();
            let want = UnitFilm::of_film(&film);
            let done = AtomicU64::new(0);
            match render_unit(&renderer, &prepared, region, &AtomicBool::new(false), &done) {
                UnitEnd::Film(got, _) => assert_eq!(got, want, "{rect:?} {samples:?}"),
                _ => panic!("the unit did not render"),
            }
            assert_eq!(
                done.load(Ordering::Relaxed),
                rect.area() as u64 * samples.len() as u64
            );
            widths.insert(want.packed.sum_bytes);
        }
        assert!(widths.len() >= 3, "sum widths covered: {widths:?}");
    }

    #[test]
    fn a_cpu_unit_renders_in_one_pass_and_stops_when_cancelled() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../examples/resolution.toml");
        let desc = SceneDesc::load(path).unwrap();
        let mut settings = desc.render;
        (settings.width, settings.height) = (96, 64);
        let prepared = PreparedFrame::build(&desc, &settings, 0, Precision::F32).unwrap();
        let renderer = Renderer::Cpu(CpuRenderer::new(Some(2)).unwrap());
        // A unit off the origin, not a whole number of renderer tiles.
        let rect = Rect::new(8, 4, 70, 50);
        let samples = SampleRange { start: 1, end: 3 };
        let want = renderer
            .render(&prepared, WorkRegion::new(0, rect, samples), &|_| {})
            .unwrap();
        let done = AtomicU64::new(0);
        let never = AtomicBool::new(false);
        let region = WorkRegion::new(0, rect, samples);
        match render_unit(&renderer, &prepared, region, &never, &done) {
            UnitEnd::Film(film, _) => assert_eq!(film, UnitFilm::of_film(&want)),
            _ => panic!("the unit did not render"),
        }
        assert_eq!(done.load(Ordering::Relaxed), rect.area() as u64 * 2);
        let cancelled = AtomicBool::new(true);
        let done = AtomicU64::new(0);
        assert!(matches!(
            render_unit(&renderer, &prepared, region, &cancelled, &done),
            UnitEnd::Abandoned
        ));
        assert_eq!(
            done.load(Ordering::Relaxed),
            0,
            "no tile rendered after the cancel"
        );
    }
}
