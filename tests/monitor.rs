//! End-to-end test of the web monitor (`tessera coordinator --http`): the
//! real coordinator and workers as processes, and the page in headless
//! Chromium driven by Selenium (`tests/python/monitor_browser.py`), which
//! signs in with the client token, watches a job appear, progress and fill
//! in, kills a worker mid-job and sees it gone, and cancels a second job
//! from the page. This side then checks what the browser showed against
//! the farm: the last preview the page drew equals, pixel for pixel, the
//! frame `tessera fetch` returns, and the cancelled job is cancelled.
//!
//! Chromium, chromedriver and Selenium come from `scripts/test` (Debian's
//! `chromium` and `chromium-driver`, pip's `selenium`); without them this
//! test fails, saying what is missing. `TESSERA_MONITOR_SHOTS=DIR` copies
//! the screenshots it takes there (docs/monitor/ holds the committed ones).

use std::io::{BufRead as _, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

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
    let log = dir.join("coordinator.log");
    let mut child = Command::new(TESSERA)
        .args([
            "coordinator",
            "--listen",
            "127.0.0.1:0",
            "--http",
            "127.0.0.1:0",
        ])
        .arg("--data")
        .arg(dir.join("data"))
        .arg("--client-token-file")
        .arg(&token)
        // A killed worker is gone 2 s after its last heartbeat.
        .args(["--lease-timeout", "2", "--heartbeat-interval", "0.4"])
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log).expect("log file"))
        .spawn()
        .expect("start coordinator");
    let mut out = BufReader::new(child.stdout.take().expect("stdout"));
    let mut line = |prefix: &str| {
        let mut l = String::new();
        out.read_line(&mut l).expect("read address");
        l.trim()
            .strip_prefix(prefix)
            .unwrap_or_else(|| panic!("coordinator did not start: {l:?}"))
            .to_string()
    };
    let grpc = format!("http://{}", line("listening on "));
    let http = line("monitor on ");
    Coordinator {
        proc: Proc { child, log },
        grpc,
        http,
    }
}

fn start_worker(dir: &Path, url: &str, name: &str) -> Proc {
    let log = dir.join(format!("worker-{name}.log"));
    let child = Command::new(TESSERA)
        .args([
            "worker",
            "--coordinator",
            url,
            "--threads",
            "1",
            "--name",
            name,
        ])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).expect("log file"))
        .spawn()
        .expect("start worker");
    Proc { child, log }
}

/// What the browser test needs, or a panic naming what is missing (the
/// test never skips: a monitor untested is not done).
fn browser_tools() -> (String, String, String) {
    let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    let driver = std::env::var("CHROMEDRIVER").unwrap_or_else(|_| "/usr/bin/chromedriver".into());
    let mut missing = Vec::new();
    if !Path::new(&chromium).exists() {
        missing.push(format!("Chromium ({chromium}; Debian package `chromium`)"));
    }
    if !Path::new(&driver).exists() {
        missing.push(format!(
            "chromedriver ({driver}; Debian package `chromium-driver`)"
        ));
    }
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
    (python, chromium, driver)
}

#[test]
fn the_monitor_in_chromium_shows_jobs_progress_the_live_preview_a_dead_worker_and_cancels() {
    let (python, chromium, driver) = browser_tools();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path());
    let _keep = start_worker(dir.path(), &c.grpc, "steady");
    let victim = start_worker(dir.path(), &c.grpc, "victim");
    let scene = repo("examples/resolution.toml");
    // Many small units (16 px tiles, 8 samples each): the preview fills
    // in over dozens of results, slowly enough to watch.
    // About 7 M pixel-samples: 10-20 s on two 1-thread workers here.
    let first = [
        "--width",
        "320",
        "--height",
        "240",
        "--samples",
        "96",
        "--tile-size",
        "16",
        "--samples-per-unit",
        "16",
    ];
    // Five times as long: cancelled long before its end.
    let second = [
        "--width",
        "320",
        "--height",
        "240",
        "--samples",
        "512",
        "--tile-size",
        "16",
        "--samples-per-unit",
        "8",
    ];
    let out = dir.path().join("browser");
    std::fs::create_dir_all(&out).expect("out dir");
    let json = |a: &[&str]| serde_json::to_string(a).expect("json");
    let status = Command::new(&python)
        .arg(repo("tests/python/monitor_browser.py"))
        .args(["--http", &c.http, "--grpc", &c.grpc, "--token", TOKEN])
        .arg("--tessera")
        .arg(TESSERA)
        .arg("--scene")
        .arg(&scene)
        .args([
            "--settings",
            &json(&first),
            "--second-settings",
            &json(&second),
        ])
        .args([
            "--victim-pid",
            &victim.child.id().to_string(),
            "--victim-name",
            "victim",
        ])
        .arg("--out")
        .arg(&out)
        .args(["--chromium", &chromium, "--chromedriver", &driver])
        .status()
        .expect("run the browser test");
    assert!(
        status.success(),
        "the browser test failed ({status}); coordinator log:\n{}",
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

    if let Ok(to) = std::env::var("TESSERA_MONITOR_SHOTS") {
        let to = PathBuf::from(to);
        std::fs::create_dir_all(&to).expect("shots dir");
        for f in [
            "jobs.png",
            "job-preview.png",
            "workers.png",
            "workers-gone.png",
            "jobs-phone.png",
            "job-dark.png",
        ] {
            std::fs::copy(out.join(f), to.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
        }
    }
}
