//! End-to-end test of the web monitor (`tessera coordinator --http`): the
//! real coordinator and workers as processes, and the page in headless
//! Chromium and in headless Firefox, each driven by Selenium
//! (`tests/python/monitor_browser.py`), which
//! signs in with the client token, reads a failed job's worker message,
//! watches a job appear, list its settings, progress and fill in, reads
//! the workers' rows, kills a worker mid-job and sees it gone, downloads
//! the frame, cancels a second job from the page, picks a frame of an
//! animation by its thumbnail and shows a textured glTF asset
//! (DamagedHelmet, submitted as it is) path-traced on the farm. This side
//! then checks what the browser showed against the farm: the last
//! preview the page drew, each thumbnail and the asset's frame equal,
//! pixel for pixel, the frames `tessera fetch` returns (the asset's also
//! equals `tessera render`'s), the downloaded PNG is the fetched file,
//! and the cancelled job is cancelled.
//!
//! Chromium, chromedriver, Firefox, geckodriver and Selenium come from
//! `scripts/test` (Debian's `chromium`, `chromium-driver` and `firefox-esr`,
//! `cargo install geckodriver`, pip's `selenium`); without them these tests
//! fail, saying what is missing. `TESSERA_MONITOR_SHOTS=DIR` copies
//! the screenshots it takes there (docs/monitor/ holds the committed ones).

use std::path::{Path, PathBuf};
use std::process::Command;

mod support;
use support::*;

const TOKEN: &str = "monitor-test-client-token";

struct Coordinator {
    proc: Proc,
    grpc: String,
    http: String,
}

fn start_coordinator(dir: &Path) -> Coordinator {
    let token = dir.join("client.token");
    std::fs::write(&token, TOKEN).expect("token file");
    let mut cmd = coordinator_command(TESSERA, dir, true);
    cmd.arg("--client-token-file")
        .arg(&token)
        // A killed worker is gone 2 s after its last heartbeat.
        .args(["--lease-timeout", "2", "--heartbeat-interval", "0.4"]);
    let Spawned { proc, grpc, http } = spawn_coordinator(cmd, dir, true);
    Coordinator {
        proc,
        grpc: format!("http://{grpc}"),
        http: format!("http://{}", http.expect("monitor")),
    }
}

/// Submits a one-unit job allowed one attempt, leases its unit as a worker
/// named `flaky` over the worker API and reports `message` as its failure,
/// then as a second worker, `flaky-too` (one worker alone cannot fail a
/// job): the job fails, carrying the message. Returns the job's id.
fn fail_a_job(c: &Coordinator, message: &str) -> String {
    use tessera_proto::pb;
    let o = Command::new(TESSERA)
        .arg("submit")
        .arg(repo("examples/resolution.toml"))
        .args([
            "--name",
            "monitor-failed",
            "--width",
            "32",
            "--height",
            "24",
        ])
        .args(["--samples", "1", "--tile-size", "32", "--max-attempts", "1"])
        .env("TESSERA_COORDINATOR", &c.grpc)
        .env("TESSERA_TOKEN", TOKEN)
        .output()
        .expect("tessera submit");
    let job = ok_stdout(&o).trim().to_string();
    rt().block_on(async {
        for name in ["flaky", "flaky-too"] {
            let (mut w, id) = raw_worker(&c.grpc, name).await;
            let unit = w
                .lease_work(pb::LeaseWorkRequest {
                    worker_id: id.clone(),
                    max_units: 1,
                    wait_ms: 5000,
                    ahead: false,
                    ..Default::default()
                })
                .await
                .expect("lease")
                .into_inner()
                .units
                .into_iter()
                .next()
                .expect("the job's unit");
            raw_fail(&w, &id, unit.lease_id, message).await;
        }
    });
    job
}

#[derive(Clone, Copy)]
enum Browser {
    Chromium,
    Firefox,
}

/// A program on `PATH`, else in cargo's bin folder (`cargo install`).
fn find_program(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    let cargo_bin = std::env::var_os("CARGO_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cargo")))
        .map(|d| d.join("bin"));
    std::env::split_paths(&path)
        .chain(cargo_bin)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

/// What the browser test needs (python, the browser, its WebDriver), or a
/// panic naming what is missing (the test never skips: a monitor untested
/// is not done).
fn browser_tools(browser: Browser) -> (String, String, String) {
    let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
    let mut missing = Vec::new();
    let (binary, driver) = match browser {
        Browser::Chromium => {
            let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
            let driver =
                std::env::var("CHROMEDRIVER").unwrap_or_else(|_| "/usr/bin/chromedriver".into());
            if !Path::new(&chromium).exists() {
                missing.push(format!("Chromium ({chromium}; Debian package `chromium`)"));
            }
            if !Path::new(&driver).exists() {
                missing.push(format!(
                    "chromedriver ({driver}; Debian package `chromium-driver`)"
                ));
            }
            (chromium, driver)
        }
        Browser::Firefox => {
            let firefox =
                std::env::var("FIREFOX").unwrap_or_else(|_| "/usr/bin/firefox-esr".into());
            if !Path::new(&firefox).exists() {
                missing.push(format!("Firefox ({firefox}; Debian package `firefox-esr`)"));
            }
            let driver = std::env::var("GECKODRIVER")
                .ok()
                .map(PathBuf::from)
                .or_else(|| find_program("geckodriver"));
            if driver.is_none() {
                missing.push(
                    "geckodriver (on PATH or in ~/.cargo/bin: `cargo install geckodriver --locked`)"
                        .to_string(),
                );
            }
            (
                firefox,
                driver.map_or(String::new(), |d| d.display().to_string()),
            )
        }
    };
    let selenium = Command::new(&python)
        .args(["-c", "import selenium"])
        .status()
        .is_ok_and(|s| s.success());
    if !selenium {
        missing.push(format!(
            "Selenium for {python} (`{python} -m pip install selenium`)"
        ));
    }
    assert!(
        missing.is_empty(),
        "the monitor's browser test needs: {} (scripts/test installs them when run as root)",
        missing.join(", ")
    );
    (python, binary, driver)
}

#[test]
fn the_monitor_in_chromium_shows_jobs_progress_the_live_preview_a_dead_worker_and_cancels() {
    monitor_test(Browser::Chromium);
}

#[test]
fn the_monitor_in_firefox_shows_jobs_progress_the_live_preview_a_dead_worker_and_cancels() {
    monitor_test(Browser::Firefox);
}

fn monitor_test(browser: Browser) {
    // One browser at a time: two farms and two browsers at once on a
    // 2-core machine would slow the renders the test watches past its waits.
    let _g = serial();
    let (python, binary, driver) = browser_tools(browser);
    let name = match browser {
        Browser::Chromium => "chromium",
        Browser::Firefox => "firefox",
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path());
    // Before any real worker: a one-unit job that a worker fails, so the
    // page has a failure with the worker's message to show.
    let failed_message = "device lost (injected by the test)";
    let failed_job = fail_a_job(&c, failed_message);
    let _keep = start_worker(dir.path(), &c.grpc, "steady");
    let victim = start_worker(dir.path(), &c.grpc, "victim");
    // Many small units (16 px tiles, 32 samples each): the preview fills
    // in over dozens of results, slowly enough to watch (the page makes a
    // preview a second, and the checks mid-job need two of them). About
    // 30 M pixel-samples: ~8 s on two idle 1-thread workers on the 2-core
    // VM (7 M, the earlier size, ended before the checks once the CPU
    // workers rendered a unit in one pass), longer under load.
    let first = [
        "--width",
        "320",
        "--height",
        "240",
        "--samples",
        "384",
        "--tile-size",
        "16",
        "--samples-per-unit",
        "32",
    ];
    // Longer still: cancelled long before its end.
    let second = [
        "--width",
        "320",
        "--height",
        "240",
        "--samples",
        "2048",
        "--tile-size",
        "16",
        "--samples-per-unit",
        "8",
    ];
    // Three frames small enough that a thumbnail is the whole frame,
    // sampled adaptively (the page lists its targets).
    let anim = [
        "--width",
        "96",
        "--height",
        "72",
        "--target-error",
        "0.05",
        "--relative-error",
        "0.1",
        "--min-samples",
        "4",
        "--max-samples",
        "16",
        "--frames",
        "1..3",
    ];
    // A textured glTF asset submitted as it is (its textures travel with
    // it): the page shows the frame the farm made of it.
    let model = shared("scenes/gltf/DamagedHelmet/glTF/DamagedHelmet.gltf");
    let model_settings = [
        "--width",
        "320",
        "--height",
        "240",
        "--samples",
        "16",
        "--integrator",
        "path",
    ];
    // Named from the repository's root where it is beside it (../shared),
    // as for the other scenes.
    let model = model.canonicalize().expect("the model's path");
    let beside = repo("").canonicalize().expect("the repository's path");
    let model_arg = match model.strip_prefix(beside.parent().expect("a parent")) {
        Ok(rel) => Path::new("..").join(rel),
        Err(_) => model.clone(),
    };
    let out = dir.path().join("browser");
    std::fs::create_dir_all(&out).expect("out dir");
    let json = |a: &[&str]| serde_json::to_string(a).expect("json");
    // Scenes named from the repository's root, as a user in a checkout
    // types them: the page (and the committed screenshots) show
    // "examples/resolution.toml", not a path of the machine the test ran on.
    let status = Command::new(&python)
        .current_dir(repo(""))
        .arg(repo("tests/python/monitor_browser.py"))
        .args(["--http", &c.http, "--grpc", &c.grpc, "--token", TOKEN])
        .arg("--tessera")
        .arg(TESSERA)
        .args(["--scene", "examples/resolution.toml"])
        .args([
            "--settings",
            &json(&first),
            "--second-settings",
            &json(&second),
        ])
        .args([
            "--failed-job",
            &failed_job,
            "--failed-message",
            failed_message,
        ])
        .args(["--anim-scene", "examples/animation.toml"])
        .args(["--anim-settings", &json(&anim)])
        .arg("--model-scene")
        .arg(&model_arg)
        .args(["--model-settings", &json(&model_settings)])
        .args([
            "--victim-pid",
            &victim.child.id().to_string(),
            "--victim-name",
            "victim",
        ])
        .arg("--out")
        .arg(&out)
        .args(["--browser", name, "--binary", &binary, "--driver", &driver])
        .status()
        .expect("run the browser test");
    assert!(
        status.success(),
        "the browser test failed in {name} ({status}); coordinator log:\n{}",
        c.proc.log()
    );

    // The page's last preview is the frame the farm returns, pixel for pixel.
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("preview.json")).expect("preview.json"))
            .expect("preview.json");
    let job = meta["job"].as_str().expect("job id");
    let fetched = dir.path().join("fetched");
    let o = Command::new(TESSERA)
        .args(["fetch", job, "-o"])
        .arg(&fetched)
        .env("TESSERA_COORDINATOR", &c.grpc)
        .env("TESSERA_TOKEN", TOKEN)
        .output()
        .expect("tessera fetch");
    ok_stdout(&o);
    let frame = image::open(fetched.join("frame_0000.png"))
        .expect("fetched frame")
        .to_rgba8();
    assert_eq!(
        (meta["width"].as_u64(), meta["height"].as_u64()),
        (
            Some(u64::from(frame.width())),
            Some(u64::from(frame.height()))
        ),
        "the preview of a 320x240 frame is full size"
    );
    let shown = std::fs::read(out.join("preview.rgba")).expect("preview pixels");
    let differ = shown
        .iter()
        .zip(frame.as_raw())
        .filter(|(a, b)| a != b)
        .count();
    assert_eq!(shown.len(), frame.as_raw().len());
    assert_eq!(
        differ, 0,
        "{differ} bytes of the page's preview differ from the fetched frame"
    );

    // The downloaded PNG is the fetched frame's file, byte for byte.
    let download: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("download.json")).expect("download.json"))
            .expect("download.json");
    assert_eq!(download["job"].as_str(), Some(job));
    let saved = std::fs::read(download["path"].as_str().expect("path")).expect("downloaded file");
    assert!(
        saved == std::fs::read(fetched.join("frame_0000.png")).expect("fetched file"),
        "the downloaded PNG differs from the one `tessera fetch` wrote"
    );

    // Each thumbnail is its frame (a frame this small is shown whole).
    let thumbs: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("thumbs.json")).expect("thumbs.json"))
            .expect("thumbs.json");
    let anim_job = thumbs["job"].as_str().expect("job");
    let anim_dir = dir.path().join("fetched-animation");
    let o = Command::new(TESSERA)
        .args(["fetch", anim_job, "-o"])
        .arg(&anim_dir)
        .env("TESSERA_COORDINATOR", &c.grpc)
        .env("TESSERA_TOKEN", TOKEN)
        .output()
        .expect("tessera fetch");
    ok_stdout(&o);
    for frame in 1..=3 {
        let png = image::open(anim_dir.join(format!("frame_{frame:04}.png")))
            .expect("fetched frame")
            .to_rgba8();
        assert_eq!(
            thumbs["frames"][frame.to_string()],
            serde_json::json!([png.width(), png.height()]),
            "frame {frame}'s thumbnail size"
        );
        let shown = std::fs::read(out.join(format!("thumb_{frame}.rgba"))).expect("thumbnail");
        assert!(
            shown == png.as_raw().as_slice(),
            "frame {frame}'s thumbnail differs from the fetched frame"
        );
    }

    // The model's frame as the page showed it is the farm's frame, and
    // that is `tessera render`'s of the same file, bit for bit (the
    // textures' look is pinned by tracer-core's golden images).
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("model.json")).expect("model.json"))
            .expect("model.json");
    let model_dir = dir.path().join("fetched-model");
    let o = Command::new(TESSERA)
        .args(["fetch", meta["job"].as_str().expect("job"), "-o"])
        .arg(&model_dir)
        .env("TESSERA_COORDINATOR", &c.grpc)
        .env("TESSERA_TOKEN", TOKEN)
        .output()
        .expect("tessera fetch");
    ok_stdout(&o);
    let fetched = image::open(model_dir.join("frame_0000.png"))
        .expect("fetched frame")
        .to_rgba8();
    let shown = std::fs::read(out.join("model.rgba")).expect("model pixels");
    assert!(
        shown == fetched.as_raw().as_slice(),
        "the page's frame of the model differs from the fetched frame"
    );
    assert!(
        pixels(&model_dir.join("frame_0000.png"))
            == reference(dir.path(), &model, 0, &model_settings),
        "the farm's frame of the model differs from `tessera render`'s"
    );

    // The job cancelled from the page is cancelled in the farm.
    let cancelled: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("cancelled.json")).expect("cancelled.json"))
            .expect("cancelled.json");
    let o = Command::new(TESSERA)
        .args(["status", cancelled["job"].as_str().expect("job"), "--json"])
        .env("TESSERA_COORDINATOR", &c.grpc)
        .env("TESSERA_TOKEN", TOKEN)
        .output()
        .expect("tessera status");
    let s: serde_json::Value = serde_json::from_str(&ok_stdout(&o)).expect("status JSON");
    assert_eq!(s["state"], "cancelled", "{s}");

    // The coordinator saw the worker go.
    assert!(c.proc.log().contains("worker left"), "{}", c.proc.log());

    // The committed screenshots are Chromium's.
    if let (Ok(to), Browser::Chromium) = (std::env::var("TESSERA_MONITOR_SHOTS"), browser) {
        let to = PathBuf::from(to);
        std::fs::create_dir_all(&to).expect("shots dir");
        for f in [
            "jobs.png",
            "job-preview.png",
            "workers.png",
            "workers-gone.png",
            "jobs-phone.png",
            "job-dark.png",
            "job-model.png",
        ] {
            std::fs::copy(out.join(f), to.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
        }
    }
}
