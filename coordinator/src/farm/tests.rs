use super::*;
use crate::store::Op;
use std::future::Future as _;
use tessera_proto::LeasedUnit;
use tracer_core::scene::RenderOverrides;

const SCENE: &str = r#"
[camera]
position = [0, 1, -6]
look_at = [0, 1, 0]
[materials.red]
diffuse = [1, 0, 0]
[[objects]]
type = "sphere"
center = [0, 1, 0]
radius = 1
material = "red"
"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn submits_too_large_to_hold_or_to_count_are_refused_with_the_limit_named() {
    let dir = tempfile::tempdir().unwrap();
    let farm = Farm::open(Config::new(dir.path().to_path_buf())).unwrap();
    let submit = |w: u32, h: u32, spp: u32, tile: u32, spu: u32| {
        let farm = farm.clone();
        async move {
            farm.submit(Submission {
                spec: JobSpec {
                    scene_name: "t.toml".into(),
                    overrides: RenderOverrides {
                        width: Some(w),
                        height: Some(h),
                        samples: Some(spp),
                        max_depth: Some(1),
                        ..Default::default()
                    },
                    tile_size: Some(tile),
                    samples_per_unit: (spu != 0).then_some(spu),
                    ..Default::default()
                },
                scene: SCENE.as_bytes().to_vec(),
                ..Default::default()
            })
            .await
            .map(|_| ())
            .unwrap_err()
            .to_string()
        }
    };
    let e = submit(32768, 32768, 1, 1024, 0).await;
    assert!(
            e.starts_with("a 32768x32768 frame has 1073741824 pixels, over the coordinator's limit of 40000000 (--max-frame-pixels)"),
            "{e}"
        );
    // 256 x 256 tiles x 65536 batches: 2^32 units, 0 in u32.
    let e = submit(2048, 2048, 65536, 8, 1).await;
    assert_eq!(
        e,
        "the job would have 4294967296 work units (the limit is 10000000); use larger tiles or sample batches"
    );
    let e = submit(2048, 2048, 1, 2048, 0).await;
    assert!(
            e.starts_with("tile_size 2048 makes results of 117440512 bytes, over the coordinator's message limit of 67108864 bytes"),
            "{e}"
        );
    assert!(farm.jobs().is_empty(), "nothing was accepted");
}

/// A well-formed result for a lease, as a worker taking `seconds` would send.
fn result(worker: &str, l: &LeasedUnit, seconds: f64) -> ResultData {
    let mut film = Film::new(l.region.rect);
    film.counts
        .iter_mut()
        .for_each(|c| *c = l.region.samples.len());
    film.rays.primary = l.region.rect.area() as u64 * l.region.samples.len() as u64;
    ResultData {
        worker_id: worker.into(),
        lease_id: l.lease_id.clone(),
        rect: l.region.rect,
        samples: l.region.samples,
        film: Ok(film),
        packed: None,
        render_seconds: seconds,
        failure: None,
        failure_class: super::FailureClass::Unspecified,
    }
}

/// A farm in a fresh directory with one job of `SCENE` at `width`x`height`,
/// `samples` spp, in 16-pixel tiles.
async fn farm_with_job(
    width: u32,
    height: u32,
    samples: u32,
) -> (tempfile::TempDir, Arc<Farm>, String) {
    let dir = tempfile::tempdir().unwrap();
    let farm = Farm::open(Config::new(dir.path().to_path_buf())).unwrap();
    let job = farm
        .submit(Submission {
            spec: JobSpec {
                name: "t".into(),
                scene_name: "t.toml".into(),
                overrides: RenderOverrides {
                    width: Some(width),
                    height: Some(height),
                    samples: Some(samples),
                    ..Default::default()
                },
                tile_size: Some(16),
                ..Default::default()
            },
            scene: SCENE.as_bytes().to_vec(),
            ..Default::default()
        })
        .await
        .unwrap();
    (dir, farm, job)
}

fn register(farm: &Farm, name: &str, threads: u32) -> String {
    register_on(farm, name, threads, Backend::Cpu, "")
}

fn register_on(farm: &Farm, name: &str, threads: u32, backend: Backend, host: &str) -> String {
    farm.register(
        name.into(),
        super::WorkerCaps {
            threads,
            backend,
            gpu_name: String::new(),
            version: String::new(),
            host_id: host.into(),
            labels: Default::default(),
            block_ranges: true,
        },
    )
}

async fn wait_done(farm: &Farm, job: &str) -> JobView {
    let start = Instant::now();
    loop {
        let v = farm.job(job).unwrap();
        if v.state == JobState::Done {
            return v;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "job not done: {} of {} units, state {:?}",
            v.units_done,
            v.units_total,
            v.state
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// A result whose database commit fails is not recorded: its lease goes
/// back to the worker, whose resend is accepted. (Before the fix the
/// lease stayed marked as consumed: the resend was dropped as a
/// duplicate and the unit was rendered again by someone else.)
#[tokio::test]
async fn a_result_whose_commit_fails_is_accepted_when_sent_again() {
    let (_dir, farm, job) = farm_with_job(16, 16, 1).await;
    let w = register(&farm, "w", 1);
    let l = farm.lease(&w, 1, false).unwrap().remove(0);
    farm.store
        .fail_commits(|op| matches!(op, Op::AcceptUnits { .. }), 1);
    let err = farm.submit_result(result(&w, &l, 0.01)).await.unwrap_err();
    assert!(
        matches!(&err, FarmError::Store(e) if e.to_string().contains("injected commit failure")),
        "{err}"
    );
    assert_eq!(farm.job(&job).unwrap().units_done, 0);
    assert_eq!(
        farm.workers()[0].leases,
        1,
        "the lease is the worker's again"
    );
    assert_eq!(
        farm.heartbeat(&w, &[(l.lease_id.clone(), 0)]).unwrap(),
        Vec::<String>::new(),
        "and heartbeats extend it"
    );
    assert_eq!(
        farm.submit_result(result(&w, &l, 0.01)).await.unwrap(),
        Outcome::Accepted
    );
    let v = wait_done(&farm, &job).await;
    assert_eq!(
        (
            v.units_done,
            v.counters.units_accepted,
            v.counters.results_duplicate
        ),
        (1, 1, 0)
    );
}

/// Results whose films go to files of their own (a GPU worker's, a
/// megabyte or more: here every film) are recorded like any other; the
/// files go once their frame is written. A result whose commit fails
/// leaves no file behind.
#[tokio::test]
async fn films_kept_in_files_are_removed_with_their_frame() {
    let (dir, farm, job) = farm_with_job(32, 16, 1).await;
    farm.store.set_min_file_film(1);
    let films_dir = dir.path().join("tessera.films");
    let files = || std::fs::read_dir(&films_dir).unwrap().count();
    let w = register(&farm, "w", 1);
    let a = farm.lease(&w, 1, false).unwrap().remove(0);
    farm.store
        .fail_commits(|op| matches!(op, Op::AcceptUnits { .. }), 1);
    assert!(farm.submit_result(result(&w, &a, 0.01)).await.is_err());
    assert_eq!(files(), 0, "the failed commit's file is removed");
    assert_eq!(
        farm.submit_result(result(&w, &a, 0.01)).await.unwrap(),
        Outcome::Accepted
    );
    assert_eq!(files(), 1);
    let b = farm.lease(&w, 1, false).unwrap().remove(0);
    assert_eq!(
        farm.submit_result(result(&w, &b, 0.01)).await.unwrap(),
        Outcome::Accepted
    );
    let v = wait_done(&farm, &job).await;
    assert_eq!(v.frames, vec![(0, 2, 2, Some(frame_file_name(0)))]);
    // Gone with the frame's record (on a thread of its own, after it).
    let start = Instant::now();
    while files() > 0 {
        assert!(start.elapsed() < Duration::from_secs(5), "file not removed");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// The image of a finished frame is written but recording that fails:
/// the record is retried and the job finishes. (Before the fix the job
/// stayed short of Done until a restart.)
#[tokio::test]
async fn a_frame_whose_written_record_fails_is_recorded_on_retry() {
    let (_dir, farm, job) = farm_with_job(16, 16, 1).await;
    let w = register(&farm, "w", 1);
    let l = farm.lease(&w, 1, false).unwrap().remove(0);
    farm.store
        .fail_commits(|op| matches!(op, Op::FrameWritten { .. }), 2);
    assert_eq!(
        farm.submit_result(result(&w, &l, 0.01)).await.unwrap(),
        Outcome::Accepted
    );
    let v = wait_done(&farm, &job).await;
    assert_eq!(v.frames, vec![(0, 1, 1, Some(frame_file_name(0)))]);
    let outputs = farm.outputs(&job).unwrap();
    assert!(outputs[0].2.is_file(), "{:?}", outputs[0].2);
}

/// A result slower than the worker's estimate (costly pixels) shrinks
/// its next lease at once; a faster one grows it only gradually.
#[tokio::test]
async fn a_slow_result_shrinks_the_next_lease_at_once() {
    let (_dir, farm, _job) = farm_with_job(1024, 64, 4).await;
    let w = register(&farm, "w", 2);
    let l1 = farm.lease(&w, 1, false).unwrap().remove(0);
    assert_eq!(l1.region.rect.width, 16, "unknown speed: one tile");
    // 16x16x4 in 1 ms: 1 M pixel-samples/s, 244 tiles in 0.25 s; the
    // end-of-job cap (255 pending / 4) and the row's end leave 63.
    assert_eq!(
        farm.submit_result(result(&w, &l1, 0.001)).await.unwrap(),
        Outcome::Accepted
    );
    let l2 = farm.lease(&w, 1, false).unwrap().remove(0);
    assert_eq!(l2.region.rect.width, 63 * 16);
    // Those 63 tiles took 1 s: 64512 pixel-samples/s, 15 tiles in 0.25 s.
    assert_eq!(
        farm.submit_result(result(&w, &l2, 1.0)).await.unwrap(),
        Outcome::Accepted
    );
    let l3 = farm.lease(&w, 1, false).unwrap().remove(0);
    assert_eq!(
        l3.region.rect.width,
        15 * 16,
        "the next lease is sized on the slow result"
    );
    // Fast again: 15 tiles in 1 ms.
    assert_eq!(
        farm.submit_result(result(&w, &l3, 0.001)).await.unwrap(),
        Outcome::Accepted
    );
    // What users see is samples over busy time of the recent results:
    // (1024 + 64512 + 15360) in 1.002 s.
    let v = &farm.workers()[0];
    let want = (1024.0 + 64512.0 + 15360.0) / 1.002;
    assert!((v.samples_per_second - want).abs() < 1e-6, "{v:?}");
    // result() reports one ray a pixel-sample.
    assert!((v.rays_per_second - want).abs() < 1e-6, "{v:?}");
}

#[tokio::test]
async fn counters_from_workers_cannot_wrap_and_names_cannot_hold_control_characters() {
    let (_dir, farm, _job) = farm_with_job(64, 64, 4).await;
    let w = register(&farm, "w", 1);
    let l = farm.lease(&w, 1, false).unwrap().remove(0);
    let mut r = result(&w, &l, 0.01);
    r.film.as_mut().unwrap().rays.shadow = u64::MAX;
    let o = farm.submit_result(r).await.unwrap();
    assert!(
        matches!(&o, Outcome::Rejected(m) if m.contains("u64::MAX") || m.contains("more than 2^32 a sample")),
        "{o:?}"
    );
    let l = farm.lease(&w, 1, false).unwrap().remove(0);
    let mut r = result(&w, &l, 0.01);
    r.film.as_mut().unwrap().nonfinite = u64::MAX;
    let o = farm.submit_result(r).await.unwrap();
    assert!(
        matches!(&o, Outcome::Rejected(m) if m.contains("non-finite samples")),
        "{o:?}"
    );
    // A result for a lease this run never granted (from before a restart).
    let l = farm.lease(&w, 1, false).unwrap().remove(0);
    let mut r = result(&w, &l, 0.01);
    r.lease_id = "l-from-an-earlier-run".into();
    assert!(matches!(
        farm.submit_result(r).await.unwrap(),
        Outcome::Late(_)
    ));
    assert_eq!(
        farm.results_unknown_lease
            .load(std::sync::atomic::Ordering::Relaxed),
        1
    );
    let e = farm
        .submit(Submission {
            spec: JobSpec {
                name: "evil\u{1b}[2J\nname".into(),
                scene_name: "t.toml".into(),
                ..Default::default()
            },
            scene: SCENE.as_bytes().to_vec(),
            ..Default::default()
        })
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.starts_with("job name \"evil\\u{1b}[2J\\nname\" must be printable text"),
        "{e}"
    );
}

/// A worker's prefetched lease handed back on drain is queued again at
/// once, with no failed attempt counted; leases it does not hold are ignored.
#[tokio::test]
async fn returned_leases_are_leased_again_at_once() {
    let (_dir, farm, job) = farm_with_job(32, 16, 1).await;
    // b registers after a took both units (with b already there, a busy
    // a would get no second unit at the job's very end).
    let a = register(&farm, "a", 1);
    let la = farm.lease(&a, 2, false).unwrap();
    assert_eq!(la.len(), 2);
    let b = register(&farm, "b", 1);
    assert!(farm.lease(&b, 1, false).unwrap().is_empty());
    let ids = [la[1].lease_id.clone(), "l-unknown".to_string()];
    assert_eq!(farm.return_leases(&b, &ids).unwrap(), 0, "b holds neither");
    assert_eq!(farm.return_leases(&a, &ids).unwrap(), 1);
    let lb = farm.lease(&b, 1, false).unwrap();
    assert_eq!(lb.len(), 1);
    assert_eq!(lb[0].region.rect, la[1].region.rect);
    assert!(
        matches!(
            farm.submit_result(result(&a, &la[1], 0.01)).await.unwrap(),
            Outcome::Late(_)
        ),
        "a returned that lease"
    );
    assert_eq!(
        farm.submit_result(result(&a, &la[0], 0.01)).await.unwrap(),
        Outcome::Accepted
    );
    assert_eq!(
        farm.submit_result(result(&b, &lb[0], 0.01)).await.unwrap(),
        Outcome::Accepted
    );
    let v = wait_done(&farm, &job).await;
    assert_eq!((v.counters.units_accepted, v.counters.results_late), (2, 1));
}

/// An idle worker's lease request waits at the coordinator and gets the
/// unit of a job submitted meanwhile, well before its wait is over.
#[tokio::test]
async fn a_waiting_lease_request_gets_work_submitted_meanwhile() {
    let dir = tempfile::tempdir().unwrap();
    let farm = Farm::open(Config::new(dir.path().to_path_buf())).unwrap();
    let w = register(&farm, "w", 1);
    let start = Instant::now();
    assert!(
        farm.lease_or_wait(&w, 1, false, Duration::from_millis(50))
            .await
            .unwrap()
            .is_empty()
    );
    assert!(start.elapsed() >= Duration::from_millis(50));
    let waiting = {
        let farm = farm.clone();
        tokio::spawn(async move {
            farm.lease_or_wait(&w, 1, false, Duration::from_secs(30))
                .await
        })
    };
    tokio::time::sleep(Duration::from_millis(50)).await;
    let start = Instant::now();
    let job = farm
        .submit(Submission {
            spec: JobSpec {
                name: "t".into(),
                scene_name: "t.toml".into(),
                overrides: RenderOverrides {
                    width: Some(16),
                    height: Some(16),
                    samples: Some(1),
                    ..Default::default()
                },
                tile_size: Some(16),
                ..Default::default()
            },
            scene: SCENE.as_bytes().to_vec(),
            ..Default::default()
        })
        .await
        .unwrap();
    let leases = waiting.await.unwrap().unwrap();
    assert!(
        start.elapsed() < Duration::from_secs(5),
        "woken by the submit, not by the timeout"
    );
    assert_eq!(leases.len(), 1);
    assert_eq!(leases[0].job.job_id, job);
}

/// A worker killed while its result is being committed makes the gRPC
/// server drop the handler's future. The unit was already taken from its
/// lease; it must still be finished (before the fix it stayed in neither
/// the queue nor a lease, and the job never completed).
#[tokio::test]
async fn a_result_whose_sender_goes_away_mid_commit_still_finishes_its_unit() {
    let (_dir, farm, job) = farm_with_job(16, 16, 1).await;
    let w = register(&farm, "w", 1);
    let l = farm.lease(&w, 1, false).unwrap().remove(0);
    // Poll the submission once (it takes the unit and waits for the
    // database), then drop it, as hyper does on a reset stream.
    {
        let mut submission = Box::pin(farm.submit_result(result(&w, &l, 0.01)));
        let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
        assert!(
            submission.as_mut().poll(&mut cx).is_pending(),
            "the commit waits for the database writer"
        );
    }
    let start = Instant::now();
    loop {
        let v = farm.job(&job).unwrap();
        if v.state == JobState::Done {
            assert_eq!((v.units_done, v.counters.units_accepted), (1, 1));
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "the unit was stranded: {} of 1 units done, state {:?}",
            v.units_done,
            v.state
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(matches!(
        farm.submit_result(result(&w, &l, 0.01)).await.unwrap(),
        Outcome::Duplicate(_)
    ));
}

/// One SubmitResults carrying accepted results, a duplicate and a
/// malformed one: each judged on its own. One that also names another
/// worker's lease is refused whole, nothing of it taken.
#[tokio::test]
async fn batched_results_are_judged_one_by_one_and_commit_together() {
    let (_dir, farm, job) = farm_with_job(64, 16, 2).await;
    let a = register(&farm, "a", 1);
    let b = register(&farm, "b", 1);
    let la = farm.lease(&a, 3, false).unwrap();
    let lb = farm.lease(&b, 3, false).unwrap();
    assert_eq!(
        (la.len(), lb.len()),
        (3, 1),
        "a takes three units in one request, b the last"
    );
    let mut bad = result(&a, &la[2], 0.01);
    bad.film.as_mut().unwrap().counts[5] = 1;
    let e = farm
        .submit_results(vec![result(&a, &la[0], 0.01), result(&a, &lb[0], 0.01)])
        .await
        .unwrap_err();
    assert!(
        matches!(&e, FarmError::PermissionDenied(m) if m.contains(&format!("lease {} was granted to another worker session", lb[0].lease_id))),
        "{e:?}"
    );
    assert_eq!(farm.job(&job).unwrap().units_done, 0, "nothing taken");
    let outcomes = farm
        .submit_results(vec![
            result(&a, &la[0], 0.01),
            result(&a, &la[1], 0.01),
            result(&a, &la[0], 0.01),
            bad,
        ])
        .await
        .unwrap();
    assert_eq!(outcomes[..2], [Outcome::Accepted, Outcome::Accepted]);
    assert!(
        matches!(outcomes[2], Outcome::Duplicate(_)),
        "{:?}",
        outcomes[2]
    );
    assert!(
        matches!(&outcomes[3], Outcome::Rejected(m) if m.contains("has 1 samples, expected 2")),
        "{:?}",
        outcomes[3]
    );
    let v = farm.job(&job).unwrap();
    assert_eq!(
        (
            v.units_done,
            v.counters.units_accepted,
            v.counters.results_duplicate,
            v.counters.results_rejected
        ),
        (2, 2, 1, 1)
    );
    // The malformed unit is queued again; b and then a finish the job.
    assert_eq!(
        farm.submit_results(vec![result(&b, &lb[0], 0.01)])
            .await
            .unwrap(),
        [Outcome::Accepted]
    );
    let again = farm.lease(&a, 4, false).unwrap();
    assert_eq!(again.len(), 1);
    assert_eq!(again[0].region.rect, la[2].region.rect);
    assert_eq!(
        farm.submit_results(vec![result(&a, &again[0], 0.01)])
            .await
            .unwrap(),
        [Outcome::Accepted]
    );
    let start = Instant::now();
    while farm.job(&job).unwrap().state != JobState::Done {
        assert!(start.elapsed() < Duration::from_secs(10), "job not done");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let v = farm.job(&job).unwrap();
    assert_eq!(
        (
            v.units_done,
            v.counters.units_accepted,
            v.counters.results_rejected
        ),
        (4, 4, 1)
    );
}

#[tokio::test]
async fn a_very_fast_worker_gets_whole_rows_of_tiles() {
    // 16 x 16 tiles of 16 px; one worker at 1024 rays (a tile) a millisecond.
    let (_dir, farm, job) = farm_with_job(256, 256, 4).await;
    let gpu = register(&farm, "gpu", 0);
    let l1 = farm.lease(&gpu, 1, false).unwrap().remove(0);
    assert_eq!(
        farm.submit_result(result(&gpu, &l1, 1e-3)).await.unwrap(),
        Outcome::Accepted
    );
    // The speed asks for hundreds of tiles; a lease ends by half the
    // farm's remaining time (the worker alone: half the pending): the
    // rest of the first row, then (once a lease starts a row) whole
    // rows only.
    let l2 = farm.lease(&gpu, 1, false).unwrap().remove(0);
    assert_eq!(
        (
            l2.region.rect.x,
            l2.region.rect.y,
            l2.region.rect.width,
            l2.region.rect.height
        ),
        (16, 0, 240, 16)
    );
    assert_eq!(
        farm.submit_result(result(&gpu, &l2, 15e-3)).await.unwrap(),
        Outcome::Accepted
    );
    let l3 = farm.lease(&gpu, 1, false).unwrap().remove(0);
    // 240 pending / 2 = 120 tiles: seven whole rows (the same speed).
    assert_eq!(
        (
            l3.region.rect.x,
            l3.region.rect.y,
            l3.region.rect.width,
            l3.region.rect.height
        ),
        (0, 16, 256, 112)
    );
    assert_eq!(
        farm.submit_result(result(&gpu, &l3, 1e-6)).await.unwrap(),
        Outcome::Accepted
    );
    assert_eq!(farm.job(&job).unwrap().units_done, 1 + 15 + 112);
}

/// Leases are sized in expected rays: where tiles cost 8x the rays
/// (glass), a worker gets an eighth of the pixels for the same time.
#[tokio::test]
async fn leases_are_sized_in_expected_rays_not_pixels() {
    // One row of 64 tiles of 16 px, 4 spp; the right half costs 8 rays a pixel-sample.
    let (_dir, farm, job) = farm_with_job(1024, 16, 4).await;
    farm.state
        .lock()
        .unwrap()
        .jobs
        .get_mut(&job)
        .unwrap()
        .set_tile_rays(
            (0..64)
                .map(|t| if t < 32 { 256.0 } else { 2048.0 })
                .collect(),
        );
    let w = register(&farm, "w", 2);
    // 65536 rays/s: 16384 rays in the 0.25 s target, 16 cheap tiles of 1024.
    let l1 = farm.lease(&w, 1, false).unwrap().remove(0);
    assert_eq!(
        farm.submit_result(result(&w, &l1, 1024.0 / 65536.0))
            .await
            .unwrap(),
        Outcome::Accepted
    );
    let l2 = farm.lease(&w, 1, false).unwrap().remove(0);
    assert_eq!((l2.region.rect.x, l2.region.rect.width), (16, 16 * 16));
    // result() reports one ray a pixel-sample, as the cheap tiles cost.
    assert_eq!(
        farm.submit_result(result(&w, &l2, 0.25)).await.unwrap(),
        Outcome::Accepted
    );
    // The rest of the cheap half (15 tiles); the next tile would not fit.
    let l3 = farm.lease(&w, 1, false).unwrap().remove(0);
    assert_eq!((l3.region.rect.x, l3.region.rect.width), (17 * 16, 15 * 16));
    assert_eq!(
        farm.submit_result(result(&w, &l3, 15.0 * 1024.0 / 65536.0))
            .await
            .unwrap(),
        Outcome::Accepted
    );
    // Costly tiles: 8192 rays each, two fit.
    let l4 = farm.lease(&w, 1, false).unwrap().remove(0);
    assert_eq!((l4.region.rect.x, l4.region.rect.width), (32 * 16, 2 * 16));
}

#[tokio::test]
async fn a_busy_worker_gets_no_second_lease_at_the_very_end() {
    // 5 units, 3 workers; a asks ahead while it renders.
    let (_dir, farm, _job) = farm_with_job(80, 16, 4).await;
    let (a, b, c) = (
        register(&farm, "a", 1),
        register(&farm, "b", 1),
        register(&farm, "c", 1),
    );
    assert_eq!(farm.lease(&a, 1, false).unwrap().len(), 1);
    // 4 pending, 3 workers: a may still take one ahead.
    assert_eq!(farm.lease(&a, 1, true).unwrap().len(), 1);
    // 3 pending: still as many as workers.
    assert_eq!(farm.lease(&a, 1, true).unwrap().len(), 1);
    // 2 pending < 3 workers: a, busy, gets none ahead; b, idle, gets
    // one, and so does a once it asks as an idle worker (the leases it
    // holds, whose results may still be on their way, do not count).
    assert!(farm.lease(&a, 1, true).unwrap().is_empty());
    assert_eq!(farm.lease(&b, 1, false).unwrap().len(), 1);
    assert_eq!(farm.lease(&a, 1, false).unwrap().len(), 1);
    assert!(
        farm.lease(&c, 1, false).unwrap().is_empty(),
        "all five leased"
    );
}

#[tokio::test]
async fn faster_workers_get_larger_units_and_results_count_once() {
    // 256 units: enough pending that the end of the job does not
    // limit the fast worker's lease.
    let (_dir, farm, job) = farm_with_job(512, 128, 4).await;
    let fast = register(&farm, "fast", 8);
    let slow = register(&farm, "slow", 1);
    // Unknown speed: one tile each.
    let (f1, s1) = (
        farm.lease(&fast, 1, false).unwrap().remove(0),
        farm.lease(&slow, 1, false).unwrap().remove(0),
    );
    assert_eq!((f1.region.rect.width, s1.region.rect.width), (16, 16));
    // A 16x16x4 unit in 10 ms vs in 1 s.
    assert_eq!(
        farm.submit_result(result(&fast, &f1, 0.01)).await.unwrap(),
        Outcome::Accepted
    );
    assert_eq!(
        farm.submit_result(result(&slow, &s1, 1.0)).await.unwrap(),
        Outcome::Accepted
    );
    let (f2, s2) = (
        farm.lease(&fast, 1, false).unwrap().remove(0),
        farm.lease(&slow, 1, false).unwrap().remove(0),
    );
    // Joined tiles along the row: the target of 0.25 s at 100 tiles a
    // second (the farm would need 2.5 s for the 254 pending).
    assert_eq!(
        (f2.region.rect.width, f2.region.rect.height),
        (16 * 25, 16),
        "the fast worker gets a row of joined tiles"
    );
    assert_eq!(
        s2.region.rect.width, 16,
        "the slow worker keeps single tiles"
    );
    // A result counts once; the same lease again is a duplicate, dropped.
    assert_eq!(
        farm.submit_result(result(&fast, &f2, 0.01)).await.unwrap(),
        Outcome::Accepted
    );
    assert!(matches!(
        farm.submit_result(result(&fast, &f2, 0.01)).await.unwrap(),
        Outcome::Duplicate(_)
    ));
    // Another worker cannot complete a lease it does not hold.
    assert!(matches!(
        farm.submit_result(result(&fast, &s2, 0.01)).await,
        Err(FarmError::PermissionDenied(_))
    ));
    let v = farm.job(&job).unwrap();
    assert_eq!(
        (
            v.units_done,
            v.counters.units_accepted,
            v.counters.results_duplicate
        ),
        (27, 27, 1)
    );
}

/// Leases go by expected finish time: at a job's end a worker 1000x
/// slower than another gets nothing (the fast one will finish the rest
/// before the slow one could finish a tile), while equal workers share
/// the last tiles.
#[tokio::test]
async fn near_the_end_a_slow_worker_is_held_back_for_a_faster_one() {
    // One row of 4 tiles.
    let (_dir, farm, _job) = farm_with_job(64, 16, 4).await;
    let fast = register(&farm, "fast", 8);
    let slow = register(&farm, "slow", 1);
    let f1 = farm.lease(&fast, 1, false).unwrap().remove(0);
    let s1 = farm.lease(&slow, 1, false).unwrap().remove(0);
    farm.submit_result(result(&fast, &f1, 0.001)).await.unwrap();
    farm.submit_result(result(&slow, &s1, 1.0)).await.unwrap();
    let (leases, held_back) = farm.lease_or_hold(&slow, 1, false).unwrap();
    assert!(leases.is_empty() && held_back, "{leases:?}");
    // Held back, an idle worker asks again soon, not after a long poll.
    let start = Instant::now();
    let leases = farm
        .lease_or_wait(&slow, 1, false, Duration::from_secs(5))
        .await
        .unwrap();
    assert!(leases.is_empty() && start.elapsed() < Duration::from_secs(1));
    let f2 = farm.lease(&fast, 1, false).unwrap().remove(0);
    assert_eq!(
        f2.region.rect,
        Rect::new(32, 0, 32, 16),
        "the fast worker takes the rest"
    );

    // Equal workers, 10 ms a tile: each gets one of the last two.
    let (_dir, farm, _job) = farm_with_job(64, 16, 4).await;
    let (a, b) = (register(&farm, "a", 2), register(&farm, "b", 2));
    let a1 = farm.lease(&a, 1, false).unwrap().remove(0);
    let b1 = farm.lease(&b, 1, false).unwrap().remove(0);
    farm.submit_result(result(&a, &a1, 0.01)).await.unwrap();
    farm.submit_result(result(&b, &b1, 0.01)).await.unwrap();
    let a2 = farm.lease(&a, 1, false).unwrap();
    let b2 = farm.lease(&b, 1, false).unwrap();
    assert_eq!((a2.len(), b2.len()), (1, 1));
    assert_eq!((a2[0].region.rect.width, b2[0].region.rect.width), (16, 16));
}

/// At a job's end an idle fast worker backs up a slow worker's lease:
/// the first result counts, the other lease is withdrawn (its holder
/// hears so at its heartbeat) and its late result is dropped.
#[tokio::test]
async fn an_idle_fast_worker_backs_up_a_slow_workers_lease_and_the_first_result_wins() {
    // One row of 8 tiles.
    let (_dir, farm, job) = farm_with_job(128, 16, 4).await;
    let slow = register(&farm, "slow", 1);
    let s1 = farm.lease(&slow, 1, false).unwrap().remove(0);
    farm.submit_result(result(&slow, &s1, 1.0)).await.unwrap();
    // Alone on the farm, the slow worker takes a lease of several tiles.
    let s2 = farm.lease(&slow, 1, false).unwrap().remove(0);
    let fast = register(&farm, "fast", 8);
    let mut backup = None;
    for _ in 0..8 {
        let Some(l) = farm.lease(&fast, 1, false).unwrap().pop() else {
            break;
        };
        if l.region.rect == s2.region.rect {
            backup = Some(l);
            break;
        }
        let r = farm.submit_result(result(&fast, &l, 0.001)).await.unwrap();
        assert_eq!(r, Outcome::Accepted);
    }
    let backup = backup.expect("the fast worker backs up the slow worker's lease");
    assert_ne!(backup.lease_id, s2.lease_id);
    assert_eq!(backup.region.samples, s2.region.samples);
    // A lease is backed up once, and the slow worker backs up nothing.
    assert!(farm.lease(&fast, 1, false).unwrap().is_empty());
    assert!(farm.lease(&slow, 1, false).unwrap().is_empty());

    let r = farm
        .submit_result(result(&fast, &backup, 0.001))
        .await
        .unwrap();
    assert_eq!(r, Outcome::Accepted);
    let gone = farm.heartbeat(&slow, &[(s2.lease_id.clone(), 10)]).unwrap();
    assert_eq!(
        gone,
        vec![s2.lease_id.clone()],
        "the slow worker is told to stop"
    );
    let late = farm.submit_result(result(&slow, &s2, 1.0)).await.unwrap();
    assert!(matches!(late, Outcome::Late(_)), "{late:?}");
    let v = wait_done(&farm, &job).await;
    assert_eq!((v.units_done, v.units_total), (8, 8));
    assert_eq!(v.counters.units_accepted, 8, "each unit counted once");
}

/// A backup that fails leaves the units with the original lease: they
/// are neither queued again nor counted as a failed attempt.
#[tokio::test]
async fn a_failed_backup_leaves_the_units_with_the_original_lease() {
    let (_dir, farm, job) = farm_with_job(64, 16, 4).await;
    let slow = register(&farm, "slow", 1);
    let s1 = farm.lease(&slow, 1, false).unwrap().remove(0);
    farm.submit_result(result(&slow, &s1, 1.0)).await.unwrap();
    let s2 = farm.lease(&slow, 1, false).unwrap().remove(0);
    let fast = register(&farm, "fast", 8);
    let mut backup = None;
    for _ in 0..8 {
        let Some(l) = farm.lease(&fast, 1, false).unwrap().pop() else {
            break;
        };
        if l.region.rect == s2.region.rect {
            backup = Some(l);
            break;
        }
        farm.submit_result(result(&fast, &l, 0.001)).await.unwrap();
    }
    let backup = backup.expect("a backup lease");
    let mut failed = result(&fast, &backup, 0.001);
    failed.failure = Some("device lost".into());
    farm.submit_result(failed).await.unwrap();
    // Nothing queued again; one more backup is tried, then no more.
    let again = farm.lease(&fast, 1, false).unwrap().remove(0);
    assert_eq!(again.region.rect, s2.region.rect);
    let mut failed = result(&fast, &again, 0.001);
    failed.failure = Some("device lost".into());
    farm.submit_result(failed).await.unwrap();
    assert!(
        farm.lease(&fast, 1, false).unwrap().is_empty(),
        "a lease is backed up at most twice"
    );
    let r = farm.submit_result(result(&slow, &s2, 1.0)).await.unwrap();
    assert_eq!(r, Outcome::Accepted);
    let v = wait_done(&farm, &job).await;
    assert_eq!(v.units_done, v.units_total);
}

/// The farm's speed, which sizes leases near a job's end, counts only
/// live workers: one gone silent neither shrinks the others' leases
/// nor (as 64 load clients of an earlier run did) slows every lease.
#[tokio::test]
async fn a_silent_worker_does_not_count_towards_the_farms_speed() {
    let mut widths = vec![];
    for silent in [false, true] {
        let (_dir, farm, _job) = farm_with_job(256, 16, 4).await;
        let (a, b) = (register(&farm, "a", 2), register(&farm, "b", 2));
        let a1 = farm.lease(&a, 1, false).unwrap().remove(0);
        let b1 = farm.lease(&b, 1, false).unwrap().remove(0);
        farm.submit_result(result(&a, &a1, 0.01)).await.unwrap();
        farm.submit_result(result(&b, &b1, 0.01)).await.unwrap();
        if silent {
            let mut st = farm.state.lock().unwrap();
            st.workers.get_mut(&b).unwrap().last_seen -= Duration::from_secs(60);
        }
        widths.push(
            farm.lease(&a, 1, false)
                .unwrap()
                .remove(0)
                .region
                .rect
                .width,
        );
    }
    assert!(
        widths[1] > widths[0],
        "alone, a worker's lease is larger than beside a live twin: {widths:?}"
    );
}

/// A lease already backed up by a worker only somewhat faster is backed
/// up again by a much faster one; its result withdraws both others.
#[tokio::test]
async fn a_much_faster_worker_backs_up_a_lease_already_backed_up() {
    let (_dir, farm, job) = farm_with_job(64, 16, 4).await;
    let slow = register(&farm, "slow", 1);
    let s1 = farm.lease(&slow, 1, false).unwrap().remove(0);
    farm.submit_result(result(&slow, &s1, 1.0)).await.unwrap();
    let s2 = farm.lease(&slow, 1, false).unwrap().remove(0);
    let mid = register(&farm, "mid", 4);
    let fast = register(&farm, "fast", 8);
    // Each measured on a tile of its own: the last two.
    let m1 = farm.lease(&mid, 1, false).unwrap().remove(0);
    farm.submit_result(result(&mid, &m1, 0.1)).await.unwrap();
    let f1 = farm.lease(&fast, 1, false).unwrap().remove(0);
    farm.submit_result(result(&fast, &f1, 0.001)).await.unwrap();
    // Out of pending work, the mid worker asks first and backs up the
    // slow worker's lease; the fast one then backs it up as well.
    let mb = farm.lease(&mid, 1, false).unwrap().remove(0);
    assert_eq!(mb.region.rect, s2.region.rect);
    let fb = farm.lease(&fast, 1, false).unwrap().remove(0);
    assert_eq!(
        fb.region.rect, s2.region.rect,
        "the fast worker backs it up too"
    );
    assert_eq!(
        farm.submit_result(result(&fast, &fb, 0.001)).await.unwrap(),
        Outcome::Accepted
    );
    for (w, l) in [(&slow, &s2), (&mid, &mb)] {
        let gone = farm.heartbeat(w, &[(l.lease_id.clone(), 1)]).unwrap();
        assert_eq!(gone, vec![l.lease_id.clone()]);
    }
    let v = wait_done(&farm, &job).await;
    assert_eq!(v.counters.units_accepted, v.units_total);
}

/// The farm's speed, against which a slow worker's lease is sized,
/// counts a fast worker's best recent speed: small units after a large
/// one (a job's tail, mostly fixed cost on a GPU) lower the fast
/// worker's own estimate, not what the slow worker may take.
#[tokio::test]
async fn a_fast_workers_best_speed_sizes_a_slow_workers_lease() {
    let mut slow_widths = vec![];
    for fast_big_unit in [false, true] {
        let (_dir, farm, _job) = farm_with_job(1024, 256, 4).await;
        let fast = register(&farm, "fast", 8);
        let f1 = farm.lease(&fast, 1, false).unwrap().remove(0);
        farm.submit_result(result(&fast, &f1, 0.001)).await.unwrap();
        let f2 = farm.lease(&fast, 1, false).unwrap().remove(0);
        assert!(f2.region.rect.width > 16, "{f2:?}");
        // The larger unit: either at the first one's speed, or (all
        // fixed cost) in the first one's time.
        let tiles = f64::from(f2.region.rect.width / 16);
        let seconds = if fast_big_unit { 0.001 } else { 0.001 * tiles };
        farm.submit_result(result(&fast, &f2, seconds))
            .await
            .unwrap();
        // A small unit, mostly fixed cost: the same low speed in both.
        let f3 = farm.lease(&fast, 1, false).unwrap().remove(0);
        let f3_tiles = f64::from(f3.region.rect.width / 16);
        farm.submit_result(result(&fast, &f3, 0.001 * f3_tiles * 4.0))
            .await
            .unwrap();
        let slow = register(&farm, "slow", 1);
        let s1 = farm.lease(&slow, 1, false).unwrap().remove(0);
        farm.submit_result(result(&slow, &s1, 0.05)).await.unwrap();
        let (l, _) = farm.lease_or_hold(&slow, 1, false).unwrap();
        slow_widths.push(l.first().map_or(0, |l| l.region.rect.width));
    }
    // Beside a worker that was 63x faster a moment ago the slow one is
    // held back (the fast one, at its best, finishes the rest sooner);
    // sized on the fast worker's last speed alone it would take work.
    assert!(slow_widths[0] > 0, "{slow_widths:?}");
    assert_eq!(slow_widths[1], 0, "{slow_widths:?}");
}

/// A fast worker ("gpu") and a slow one ("cpu") on a fresh job, each rated
/// on one tile: the fast one in 0.4 ms (its fixed cost, too short to
/// measure it), the slow one in 50 ms. Returns (fast, slow).
async fn gpu_rated_on_a_tile_beside_a_cpu(farm: &Arc<Farm>) -> (String, String) {
    let (fast, slow) = (register(farm, "gpu", 1), register(farm, "cpu", 2));
    let f1 = farm.lease(&fast, 1, false).unwrap().remove(0);
    let s1 = farm.lease(&slow, 1, false).unwrap().remove(0);
    farm.submit_result(result(&fast, &f1, 0.0004))
        .await
        .unwrap();
    farm.submit_result(result(&slow, &s1, 0.05)).await.unwrap();
    (fast, slow)
}

/// A worker rated only on units too small to measure it (a GPU after a
/// warm-up's tiles: mostly fixed cost) may be much faster than rated, so a
/// slow worker beside it takes one tile at a time until it is measured;
/// then the slow worker's leases are sized as before. Sized against the
/// low rating, the slow worker's first leases of a 1080p job outlasted the
/// GPU's whole frame (a mixed farm 1.3-1.6x slower than the GPU alone).
#[tokio::test]
async fn beside_a_much_faster_worker_not_yet_measured_a_slow_one_takes_a_tile_at_a_time() {
    let (_dir, farm, _job) = farm_with_job(1024, 256, 4).await;
    let (fast, slow) = gpu_rated_on_a_tile_beside_a_cpu(&farm).await;
    let s2 = farm.lease(&slow, 4, false).unwrap();
    assert_eq!(s2.len(), 1, "one lease at a time: {s2:?}");
    assert_eq!(s2[0].region.rect.area(), 16 * 16, "of one tile: {s2:?}");
    farm.submit_result(result(&slow, &s2[0], 0.05))
        .await
        .unwrap();
    // The fast worker's next lease is larger, and long enough to measure it.
    let f2 = farm.lease(&fast, 1, false).unwrap().remove(0);
    let tiles = (f2.region.rect.area() / (16 * 16)) as f64;
    assert!(tiles >= 8.0, "{f2:?}");
    farm.submit_result(result(&fast, &f2, 0.0005 * tiles))
        .await
        .unwrap();
    let s3 = farm.lease(&slow, 1, false).unwrap().remove(0);
    assert!(
        s3.region.rect.area() > 16 * 16,
        "measured, the fast worker no longer bounds the slow one to a tile: {s3:?}"
    );

    // A worker not measured at all while it renders may be of any speed.
    let (_dir, farm, _job) = farm_with_job(1024, 256, 4).await;
    let (a, b) = (register(&farm, "a", 2), register(&farm, "b", 2));
    let a1 = farm.lease(&a, 1, false).unwrap().remove(0);
    let _b1 = farm.lease(&b, 1, false).unwrap().remove(0);
    farm.submit_result(result(&a, &a1, 0.05)).await.unwrap();
    let a2 = farm.lease(&a, 1, false).unwrap().remove(0);
    assert_eq!(a2.region.rect.area(), 16 * 16, "{a2:?}");
}

/// A unit reported rendered with a lease request rates its worker at
/// once, before its result is taken in (a GPU's results took 20-60 ms on a
/// busy coordinator), and its result does not rate it again; a report of
/// a lease the reporter does not hold is ignored.
#[tokio::test]
async fn a_unit_reported_rendered_rates_its_worker_before_its_result_comes() {
    let (_dir, farm, _job) = farm_with_job(1024, 256, 4).await;
    let (fast, slow) = gpu_rated_on_a_tile_beside_a_cpu(&farm).await;
    let f2 = farm.lease(&fast, 1, false).unwrap().remove(0);
    let tiles = (f2.region.rect.area() / (16 * 16)) as f64;
    let rays = |l: &LeasedUnit| l.region.rect.area() as u64 * l.region.samples.len() as u64;
    let speed_of = |w: &str| {
        let st = farm.state.lock().unwrap();
        (st.workers[w].ray_speed, st.workers[w].last_seconds)
    };
    // The slow worker reporting the fast one's lease changes nothing.
    let before = (speed_of(&fast), speed_of(&slow));
    farm.rate_rendered(&slow, &[(f2.lease_id.clone(), rays(&f2), 1.0)]);
    assert_eq!((speed_of(&fast), speed_of(&slow)), before);
    let s2 = farm.lease(&slow, 1, false).unwrap().remove(0);
    assert_eq!(s2.region.rect.area(), 16 * 16, "{s2:?}");
    farm.submit_result(result(&slow, &s2, 0.05)).await.unwrap();
    // Reported rendered, long enough to measure it: the slow worker's
    // next lease is sized against the fast one's speed at once.
    farm.rate_rendered(&fast, &[(f2.lease_id.clone(), rays(&f2), 0.0005 * tiles)]);
    assert_eq!(speed_of(&fast).1, 0.0005 * tiles);
    // Its work is done as far as leasing goes: the fast worker is not busy.
    assert_eq!(
        farm.state.lock().unwrap().leases[&f2.lease_id].progress,
        f2.region.pixel_samples()
    );
    let s3 = farm.lease(&slow, 1, false).unwrap().remove(0);
    assert!(s3.region.rect.area() > 16 * 16, "{s3:?}");
    // The result (its render time said otherwise) does not rate it again.
    farm.submit_result(result(&fast, &f2, 0.5)).await.unwrap();
    assert_eq!(speed_of(&fast).1, 0.0005 * tiles);
}

/// A CPU worker on the machine of a GPU worker ten times as fast gets no
/// work while that one is live (its threads would slow the GPU worker's
/// side of the host by more than they add); a CPU worker elsewhere, or
/// beside a GPU worker gone silent, does.
#[tokio::test]
async fn a_cpu_worker_leaves_its_machine_to_a_much_faster_gpu_worker_there() {
    let (_dir, farm, _job) = farm_with_job(1024, 256, 4).await;
    let gpu = register_on(&farm, "gpu", 1, Backend::Gpu, "box-a");
    let here = register_on(&farm, "cpu-a", 2, Backend::Cpu, "box-a");
    let there = register_on(&farm, "cpu-b", 2, Backend::Cpu, "box-b");
    let g1 = farm.lease(&gpu, 1, false).unwrap().remove(0);
    // Before the GPU worker is measured, both CPU workers take a tile.
    let h1 = farm.lease(&here, 1, false).unwrap().remove(0);
    let t1 = farm.lease(&there, 1, false).unwrap().remove(0);
    farm.submit_result(result(&gpu, &g1, 0.001)).await.unwrap();
    farm.submit_result(result(&here, &h1, 0.05)).await.unwrap();
    farm.submit_result(result(&there, &t1, 0.05)).await.unwrap();
    assert_eq!(farm.lease_or_hold(&here, 1, false).unwrap().0.len(), 0);
    assert_eq!(farm.lease(&there, 1, false).unwrap().len(), 1);
    // Gone silent, the GPU worker keeps nothing.
    farm.state
        .lock()
        .unwrap()
        .workers
        .get_mut(&gpu)
        .unwrap()
        .last_seen -= Duration::from_secs(60);
    assert_eq!(farm.lease(&here, 1, false).unwrap().len(), 1);
}

/// Near a job's end a worker is held back for another that would
/// finish the unit sooner. Every worker measured at its best speed
/// (first units fast, later ones slower) must not hold all of them
/// back: that left 0.2% of a 1080p frame unleased for 199 s on the
/// benchmark machine. Each worker compares the others at their best
/// with itself at its best.
#[tokio::test]
async fn workers_rated_at_their_best_never_all_hold_back() {
    let (_dir, farm, job) = farm_with_job(1024, 64, 4).await;
    let workers = [register(&farm, "a", 2), register(&farm, "b", 2)];
    let mut results = [0u32; 2];
    for round in 0..2000 {
        let v = farm.job(&job).unwrap();
        if v.units_done == v.units_total {
            wait_done(&farm, &job).await;
            return;
        }
        for (i, w) in workers.iter().enumerate() {
            let (leases, _) = farm.lease_or_hold(w, 1, false).unwrap();
            for l in leases {
                // The first result of each is 10x faster than the rest.
                let tiles = f64::from(l.region.rect.width / 16 * (l.region.rect.height / 16));
                let per_tile = if results[i] == 0 { 0.0001 } else { 0.001 };
                results[i] += 1;
                let o = farm.submit_result(result(w, &l, tiles * per_tile)).await;
                assert_eq!(o.unwrap(), Outcome::Accepted, "round {round}");
            }
        }
    }
    let v = farm.job(&job).unwrap();
    panic!(
        "both workers held back: {} of {} units done, results {results:?}",
        v.units_done, v.units_total
    );
}

/// However fast a worker, a lease covers at most MAX_LEASE_PIXELS: a GPU
/// worker gets a 1080p frame in several leases, so that its results travel
/// while it renders the next, not half the frame in one.
#[tokio::test]
async fn a_fast_workers_leases_stop_growing_at_the_pixel_cap() {
    use super::lease::MAX_LEASE_PIXELS;
    let dir = tempfile::tempdir().unwrap();
    let farm = Farm::open(Config::new(dir.path().to_path_buf())).unwrap();
    farm.submit(Submission {
        spec: JobSpec {
            name: "t".into(),
            scene_name: "t.toml".into(),
            overrides: RenderOverrides {
                width: Some(1920),
                height: Some(1080),
                samples: Some(64),
                ..Default::default()
            },
            tile_size: Some(64),
            ..Default::default()
        },
        scene: SCENE.as_bytes().to_vec(),
        ..Default::default()
    })
    .await
    .unwrap();
    let w = register(&farm, "gpu", 1);
    let mut areas = vec![];
    while let Some(l) = farm.lease(&w, 1, false).unwrap().pop() {
        areas.push(l.region.rect.area() as u64);
        // A million pixel-samples a millisecond: a frame in well under the target.
        let seconds = l.region.pixel_samples() as f64 * 1e-9;
        assert_eq!(
            farm.submit_result(result(&w, &l, seconds)).await.unwrap(),
            Outcome::Accepted
        );
    }
    assert_eq!(areas.iter().sum::<u64>(), 1920 * 1080);
    assert!(areas.iter().all(|&a| a <= MAX_LEASE_PIXELS), "{areas:?}");
    // The cap is what bound them: the leases grew up to it.
    assert!(areas.iter().any(|&a| a > MAX_LEASE_PIXELS / 2), "{areas:?}");
}

/// Issue 37, item 6: ids are 128 random bits; a worker whose results fail
/// validation `quarantine_after` times in a row is quarantined (its other
/// leases revoked, no new lease), and its malformed results alone never
/// fail the job; a second worker's failure of the same unit counts them.
#[tokio::test]
async fn a_worker_sending_malformed_results_is_quarantined_and_cannot_fail_the_job_alone() {
    let (_dir, farm, job) = farm_with_job(64, 16, 1).await;
    assert_eq!(farm.config.quarantine_after, 5);
    let bad = register(&farm, "bad", 1);
    let good = register(&farm, "good", 1);
    let hex = |s: &str| s.len() == 33 && s[1..].bytes().all(|b| b.is_ascii_hexdigit());
    assert!(bad.starts_with('w') && hex(&bad), "{bad}");
    assert!(
        farm.workers().iter().all(|w| w.id != bad && w.id != good),
        "views show public ids, never a session"
    );
    let malformed = |l: &LeasedUnit| {
        let mut r = result(&bad, l, 0.01);
        r.film.as_mut().unwrap().counts[0] = 7;
        r
    };
    let mut first = None;
    for strike in 1..=4 {
        let l = farm.lease(&bad, 1, false).unwrap().remove(0);
        assert!(
            l.lease_id.starts_with('l') && hex(&l.lease_id),
            "{}",
            l.lease_id
        );
        first.get_or_insert(l.region);
        let o = farm.submit_result(malformed(&l)).await.unwrap();
        assert!(
            matches!(&o, Outcome::Rejected(m) if m.contains("has 7 samples")),
            "{o:?}"
        );
        // Four malformed results of one unit, 3 attempts allowed: one
        // worker's word, so the job goes on.
        assert_eq!(
            farm.job(&job).unwrap().state,
            JobState::Running,
            "strike {strike}"
        );
    }
    let held = farm.lease(&bad, 2, false).unwrap();
    assert_eq!(held.len(), 2);
    let o = farm.submit_result(malformed(&held[0])).await.unwrap();
    assert!(matches!(o, Outcome::Rejected(_)), "{o:?}");
    // Quarantined: its other lease revoked, no new one.
    assert_eq!(
        farm.heartbeat(&bad, &[(held[1].lease_id.clone(), 0)])
            .unwrap(),
        [held[1].lease_id.clone()]
    );
    assert!(farm.lease(&bad, 1, false).unwrap().is_empty());
    assert!(
        farm.quarantined_for(&bad)
            .is_some_and(|d| d > Duration::from_secs(50))
    );
    let views = farm.workers();
    let view = |name: &str| views.iter().find(|w| w.name == name).unwrap();
    assert!(view("bad").quarantined_until_unix_ms > now_ms());
    assert_eq!(view("good").quarantined_until_unix_ms, 0);
    assert_eq!(farm.job(&job).unwrap().state, JobState::Running);
    // A second worker fails the same unit: now every failure counts.
    let l = farm.lease(&good, 1, false).unwrap().remove(0);
    assert_eq!(Some(l.region), first, "the unit the bad worker failed");
    let mut r = result(&good, &l, 0.01);
    r.film.as_mut().unwrap().counts[0] = 9;
    farm.submit_result(r).await.unwrap();
    let v = farm.job(&job).unwrap();
    assert_eq!(v.state, JobState::Failed);
    assert!(
        v.record.error.contains("failed 6 times")
            && v.record
                .error
                .contains("worker good sent a malformed result"),
        "{}",
        v.record.error
    );
}

/// An image-mode adaptive job (the error-optimal mode): a lease carries
/// each block's range and goes only to workers that render ranges; a
/// result's runs of blocks are checked against those ranges (whole blocks,
/// each booked once, with the block's sample count, their rays adding up
/// to the result's) before they are booked as the blocks' costs.
#[tokio::test]
async fn image_mode_leases_carry_block_ranges_and_results_runs_are_checked() {
    use tracer_core::adaptive::{AdaptiveMode, AdaptiveSpec};
    use tracer_core::film::RunCost;
    let dir = tempfile::tempdir().unwrap();
    let farm = Farm::open(Config::new(dir.path().to_path_buf())).unwrap();
    let submit = |tile: u32| {
        farm.submit(Submission {
            spec: JobSpec {
                name: "t".into(),
                scene_name: "t.toml".into(),
                overrides: RenderOverrides {
                    width: Some(64),
                    height: Some(16),
                    ..Default::default()
                },
                adaptive: AdaptiveSpec {
                    target_error: Some(1e-9),
                    min_samples: Some(2),
                    max_samples: Some(8),
                    mode: Some(AdaptiveMode::Image),
                    ..Default::default()
                },
                tile_size: Some(tile),
                max_attempts: Some(10),
                ..Default::default()
            },
            scene: SCENE.as_bytes().to_vec(),
            ..Default::default()
        })
    };
    let e = submit(16).await.unwrap_err().to_string();
    assert!(
        e.contains("tile_size must be a multiple of 32 for the image adaptive mode"),
        "{e}"
    );
    submit(32).await.unwrap();
    // A worker of an earlier release (no block_ranges) gets none of it.
    let old = farm.register(
        "old".into(),
        super::WorkerCaps {
            threads: 1,
            backend: Backend::Cpu,
            gpu_name: String::new(),
            version: String::new(),
            host_id: String::new(),
            labels: Default::default(),
            block_ranges: false,
        },
    );
    assert!(farm.lease(&old, 1, false).unwrap().is_empty());
    let w = register(&farm, "w", 1);
    let mut l = farm.lease(&w, 1, false).unwrap().remove(0);
    let rect = l.region.rect;
    assert_eq!((rect.width, rect.height), (32, 16));
    assert_eq!(l.region.samples, SampleRange::new(0, 2));
    assert_eq!(l.ranges, Some(vec![SampleRange::new(0, 2); 8]));
    // What a CPU worker sends: its film, squares and the runs (4 blocks
    // wide, one a row of blocks) with their rays.
    let sent = |l: &LeasedUnit, runs: Vec<RunCost>| {
        let mut r = result(&w, l, 0.01);
        let film = r.film.as_mut().unwrap();
        // Sums 0, squares not: every block has a variance.
        film.squares = Some(vec![[1 << 64; 3]; rect.area()]);
        film.rays.shadow = 1000;
        film.runs = runs;
        r
    };
    let total = (rect.area() * 2) as u64 + 1000;
    let run = |y: u32, width: u32, rays: u64, samples: u32| RunCost {
        rect: Rect::new(rect.x, y, width, 8),
        rays,
        samples,
    };
    let half = total / 2;
    for (runs, why) in [
        (
            vec![run(0, 32, half, 2), run(8, 32, total - half, 3)],
            "run Rect { x: 0, y: 8, width: 32, height: 8 } has 3 samples a pixel, its block at (0, 8) takes 2",
        ),
        (
            vec![run(0, 32, half, 2), run(0, 16, total - half, 2)],
            "run Rect { x: 0, y: 0, width: 16, height: 8 } covers the block at (0, 0) that another run covers",
        ),
        (
            vec![run(0, 32, half, 2), run(8, 32, 1, 2)],
            &format!("the runs count {} rays, the result {total}", half + 1),
        ),
        (
            vec![run(0, 32, half, 2), run(4, 32, total - half, 2)],
            "run Rect { x: 0, y: 4, width: 32, height: 8 } is not a row of whole blocks",
        ),
    ] {
        let o = farm.submit_result(sent(&l, runs)).await.unwrap();
        assert!(
            matches!(&o, Outcome::Rejected(m) if m.contains(why)),
            "{o:?} lacks {why:?}"
        );
        l = farm.lease(&w, 1, false).unwrap().remove(0);
        assert_eq!(l.region.rect, rect, "the unit is leased again");
    }
    // Well-formed runs are taken; a GPU worker's result has none.
    let o = farm
        .submit_result(sent(
            &l,
            vec![run(0, 32, half, 2), run(8, 32, total - half, 2)],
        ))
        .await
        .unwrap();
    assert_eq!(o, Outcome::Accepted);
    let other = farm.lease(&w, 1, false).unwrap().remove(0);
    assert_eq!(other.region.rect.x, 32);
    assert_eq!(
        farm.submit_result(sent(&other, vec![])).await.unwrap(),
        Outcome::Accepted
    );
    // Round 0 is in for the whole frame: round 1 is decided, each block
    // from 2 towards the allocation's count (the target is out of reach:
    // doubling, on the grid 2 * 2^(k/4)).
    let next = farm.lease(&w, 1, false).unwrap().remove(0);
    let ranges = next.ranges.expect("ranges");
    assert!(
        ranges.iter().all(|r| *r == SampleRange::new(2, 4)),
        "{ranges:?}"
    );
}
