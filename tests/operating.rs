//! End-to-end tests of operating the farm (issue 38): the real `tessera`
//! binary as coordinator, workers and client over real sockets.
//!
//! - `/metrics`: scraped over HTTP and parsed by the Prometheus project's
//!   Python client (`tests/python/metrics_scrape.py`, `prometheus_client`
//!   from PyPI, installed by `scripts/test`), checked before, during and
//!   after a job, and behind the client token or the scrape-only token.
//! - The per-job blocklist: a worker that reports `--blocklist-after`
//!   units of a job failed gets none of its units until forgiven, and
//!   `tessera status` says so.
//! - Dependencies (`submit --after`): a job waits, none of its units
//!   leased, until its parent is done, across a restart; it fails with its
//!   parent's cancellation.
//! - Notifications (`submit --on-done`, `coordinator --notify`): a real
//!   HTTP server in this process receives the signed POSTs, checks the
//!   HMAC with its own implementation, and fails a first attempt.
//! - Failure classes and a job's own blocklist settings: a scene error
//!   that a second worker reports fails the job at once.
//! - A worker's own `/metrics` (`tessera worker --http`), parsed by the
//!   same Prometheus client and moving as it renders.

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use serde_json::Value;
use tessera_proto::pb::worker_service_client::WorkerServiceClient;

mod support;
use support::*;

const CLIENT_TOKEN: &str = "0123456789abcdef0123456789abcdef";
const METRICS_TOKEN: &str = "fedcba9876543210fedcba9876543210";

struct Coordinator {
    proc: Proc,
    grpc: String,
    http: String,
}

fn start_coordinator(dir: &Path, extra: &[&str]) -> Coordinator {
    let client = dir.join("client.token");
    std::fs::write(&client, CLIENT_TOKEN).expect("token file");
    let metrics = dir.join("metrics.token");
    std::fs::write(&metrics, METRICS_TOKEN).expect("token file");
    let mut cmd = coordinator_command(TESSERA, dir, true);
    cmd.arg("--client-token-file")
        .arg(&client)
        .arg("--metrics-token-file")
        .arg(&metrics)
        .args(["--lease-timeout", "10", "--heartbeat-interval", "0.4"])
        .args(extra);
    let Spawned { proc, grpc, http } = spawn_coordinator(cmd, dir, true);
    Coordinator {
        proc,
        grpc: format!("http://{grpc}"),
        http: format!("http://{}", http.expect("monitor")),
    }
}

/// `tessera ARGS` as a client of `c`, with the client token.
fn client(c: &Coordinator, args: &[&str]) -> std::process::Output {
    Command::new(TESSERA)
        .args(args)
        .env("TESSERA_COORDINATOR", &c.grpc)
        .env("TESSERA_TOKEN", CLIENT_TOKEN)
        .output()
        .expect("run tessera")
}

fn job_status(c: &Coordinator, job: &str) -> Value {
    let out = ok_stdout(&client(c, &["status", job, "--json"]));
    serde_json::from_str(&out).unwrap_or_else(|e| panic!("status --json: {e}: {out}"))
}

/// The monitor's JSON of job `job` (`/api/jobs/{id}`), with the client token.
fn monitor_job(c: &Coordinator, job: &str) -> Value {
    let m = Command::new("curl")
        .args([
            "-sf",
            "-H",
            &format!("Authorization: Bearer {CLIENT_TOKEN}"),
        ])
        .arg(format!("{}/api/jobs/{job}", c.http))
        .output()
        .expect("curl");
    serde_json::from_slice(&m.stdout)
        .unwrap_or_else(|e| panic!("monitor JSON: {e}: {}", String::from_utf8_lossy(&m.stdout)))
}

/// `tessera ARGS` as a client of `c` must fail, saying `expected`.
fn refused(c: &Coordinator, args: &[&str], expected: &str) {
    let o = client(c, args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{args:?} succeeded: {err}");
    assert!(err.contains(expected), "{err}");
}

/// A scrape of `c`'s `/metrics` with `token`, parsed by prometheus_client:
/// Ok(the parsed samples and types) or Err((HTTP status, body)).
fn scrape(c: &Coordinator, token: Option<&str>) -> Result<Value, (u64, String)> {
    scrape_url(&format!("{}/metrics", c.http), token)
}

/// [`scrape`] of any `/metrics` URL (a worker's).
fn scrape_url(url: &str, token: Option<&str>) -> Result<Value, (u64, String)> {
    let mut cmd = Command::new("python3");
    cmd.arg(repo("tests/python/metrics_scrape.py")).arg(url);
    cmd.args(token);
    let o = cmd
        .output()
        .expect("python3 (tests/python/metrics_scrape.py)");
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    match o.status.code() {
        Some(0) => Ok(serde_json::from_str(&out).expect("scrape JSON")),
        Some(3) => {
            let v: Value = serde_json::from_str(&out).expect("refusal JSON");
            Err((
                v["status"].as_u64().expect("status"),
                v["body"].as_str().unwrap_or("").to_string(),
            ))
        }
        _ => panic!(
            "metrics_scrape.py failed ({:?}): {}{}",
            o.status,
            out,
            String::from_utf8_lossy(&o.stderr)
        ),
    }
}

/// The value of the sample `name` with exactly `labels`.
fn sample(m: &Value, name: &str, labels: &[(&str, &str)]) -> f64 {
    let want: serde_json::Map<String, Value> = labels
        .iter()
        .map(|(k, v)| (k.to_string(), Value::from(*v)))
        .collect();
    let hits: Vec<f64> = m["samples"]
        .as_array()
        .expect("samples")
        .iter()
        .filter(|s| s["name"] == name && s["labels"].as_object() == Some(&want))
        .map(|s| s["value"].as_f64().expect("value"))
        .collect();
    assert_eq!(
        hits.len(),
        1,
        "one sample {name}{labels:?} in the scrape, found {hits:?}"
    );
    hits[0]
}

#[test]
fn metrics_are_prometheus_text_behind_the_tokens_and_move_as_a_job_runs() {
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), &[]);

    // The gate: nothing without a token, the scrape-only token opens
    // /metrics and not the API, the client token opens both.
    let (status, body) = scrape(&c, None).expect_err("a scrape without a token is refused");
    assert_eq!(status, 401, "{body}");
    assert!(body.contains("Authorization: Bearer"), "{body}");
    let (status, body) = scrape(&c, Some("not-the-token")).expect_err("a wrong token is refused");
    assert_eq!(status, 401);
    assert!(
        body.contains("neither this coordinator's client token nor its metrics token"),
        "{body}"
    );
    let api = Command::new("python3")
        .args([
            "-c",
            "import sys, urllib.request, urllib.error\n\
             r = urllib.request.Request(sys.argv[1], headers={'Authorization': 'Bearer ' + sys.argv[2]})\n\
             try:\n    print(urllib.request.urlopen(r).status)\n\
             except urllib.error.HTTPError as e:\n    print(e.code)",
        ])
        .arg(format!("{}/api/jobs", c.http))
        .arg(METRICS_TOKEN)
        .output()
        .expect("python3");
    assert_eq!(
        String::from_utf8_lossy(&api.stdout).trim(),
        "401",
        "the metrics token must not open the job API"
    );

    let idle = scrape(&c, Some(METRICS_TOKEN)).expect("scrape with the metrics token");
    assert!(
        idle["content_type"]
            .as_str()
            .unwrap()
            .starts_with("application/openmetrics-text"),
        "{}",
        idle["content_type"]
    );
    for (name, kind) in [
        ("tessera_jobs", "gauge"),
        ("tessera_units", "gauge"),
        ("tessera_workers", "gauge"),
        ("tessera_results", "counter"),
        ("tessera_lease_seconds", "histogram"),
        ("tessera_samples", "counter"),
        ("tessera_store_healthy", "gauge"),
        ("tessera_store_commit_seconds", "histogram"),
        ("tessera_asset_bytes", "gauge"),
    ] {
        assert_eq!(
            idle["types"][name], kind,
            "family {name}: {}",
            idle["types"]
        );
    }
    for state in [
        "waiting",
        "queued",
        "running",
        "done",
        "failed",
        "cancelled",
    ] {
        assert_eq!(sample(&idle, "tessera_jobs", &[("state", state)]), 0.0);
    }
    assert_eq!(sample(&idle, "tessera_store_healthy", &[]), 1.0);
    assert_eq!(sample(&idle, "tessera_samples_total", &[]), 0.0);
    assert_eq!(
        sample(&idle, "tessera_results_total", &[("outcome", "accepted")]),
        0.0
    );
    assert_eq!(sample(&idle, "tessera_lease_seconds_count", &[]), 0.0);

    // A job with no worker yet: queued, every unit waiting.
    let scene = repo("examples/resolution.toml");
    let o = client(
        &c,
        &[
            "submit",
            scene.to_str().unwrap(),
            "--width",
            "64",
            "--height",
            "48",
            "--samples",
            "4",
            "--tile-size",
            "16",
            "--samples-per-unit",
            "2",
        ],
    );
    let job = ok_stdout(&o).trim().to_string();
    let st = job_status(&c, &job);
    let units_total = st["units_total"].as_f64().unwrap();
    assert!(units_total >= 24.0, "{st}");
    let queued = scrape(&c, Some(CLIENT_TOKEN)).expect("scrape with the client token");
    assert_eq!(sample(&queued, "tessera_jobs", &[("state", "queued")]), 1.0);
    assert_eq!(
        sample(&queued, "tessera_units", &[("state", "waiting")]),
        units_total
    );
    assert_eq!(
        sample(&queued, "tessera_units", &[("state", "leased")]),
        0.0
    );
    assert!(
        sample(&queued, "tessera_asset_bytes", &[]) > 0.0,
        "the scene is stored"
    );
    assert!(sample(&queued, "tessera_store_commit_seconds_count", &[]) >= 1.0);

    // A worker runs it to the end.
    let _w = start_worker(dir.path(), &c.grpc, "metered");
    wait_for("the job to finish", Duration::from_secs(120), || {
        job_status(&c, &job)["state"] == "done"
    });
    let done = scrape(&c, Some(METRICS_TOKEN)).expect("scrape");
    assert_eq!(sample(&done, "tessera_jobs", &[("state", "done")]), 1.0);
    assert_eq!(sample(&done, "tessera_jobs", &[("state", "queued")]), 0.0);
    assert_eq!(sample(&done, "tessera_units", &[("state", "waiting")]), 0.0);
    assert_eq!(sample(&done, "tessera_units", &[("state", "leased")]), 0.0);
    // Every pixel-sample of the job, counted once.
    assert_eq!(
        sample(&done, "tessera_samples_total", &[]),
        64.0 * 48.0 * 4.0
    );
    // A result may carry several units (a fast worker leases a run of
    // tiles): between one and one per unit.
    let accepted = sample(&done, "tessera_results_total", &[("outcome", "accepted")]);
    assert!(
        (1.0..=units_total).contains(&accepted),
        "{accepted} results accepted for {units_total} units"
    );
    assert_eq!(
        sample(&done, "tessera_results_total", &[("outcome", "rejected")]),
        0.0
    );
    let leases = sample(&done, "tessera_lease_seconds_count", &[]);
    assert!(leases >= 1.0, "leases granted: {leases}");
    assert_eq!(
        sample(&done, "tessera_lease_seconds_bucket", &[("le", "+Inf")]),
        leases
    );
    assert_eq!(
        sample(
            &done,
            "tessera_workers",
            &[("backend", "cpu"), ("state", "idle")]
        ) + sample(
            &done,
            "tessera_workers",
            &[("backend", "cpu"), ("state", "busy")]
        ),
        1.0
    );
    assert_eq!(
        sample(
            &done,
            "tessera_workers",
            &[("backend", "gpu"), ("state", "idle")]
        ),
        0.0
    );
    drop(c.proc);
}

/// Worker-API calls as one session (a worker whose units fail at will).
struct Session {
    client: WorkerServiceClient<tonic::transport::Channel>,
    id: String,
}

impl Session {
    async fn register(url: &str, name: &str) -> Session {
        let (client, id) = raw_worker(url, name).await;
        Session { client, id }
    }

    /// One lease of one unit, without waiting: its lease id, if any.
    async fn lease(&mut self) -> Option<String> {
        raw_lease(&self.client, &self.id)
            .await
            .units
            .into_iter()
            .next()
            .map(|u| u.lease_id)
    }

    async fn fail(&mut self, lease_id: String, message: &str) {
        raw_fail(&self.client, &self.id, lease_id, message).await
    }
}

#[test]
fn a_worker_failing_units_of_a_job_is_blocklisted_from_it_until_forgiven() {
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(
        dir.path(),
        &["--blocklist-after", "2", "--blocklist-seconds", "4"],
    );
    let scene = repo("examples/resolution.toml");
    let job = ok_stdout(&client(
        &c,
        &[
            "submit",
            scene.to_str().unwrap(),
            "--width",
            "64",
            "--height",
            "48",
            "--samples",
            "1",
            "--tile-size",
            "16",
            "--max-attempts",
            "5",
        ],
    ))
    .trim()
    .to_string();
    let rt = rt();
    let mut broken = rt.block_on(Session::register(&c.grpc, "broken"));
    let mut good = rt.block_on(Session::register(&c.grpc, "good"));
    let blocked_at = rt.block_on(async {
        for _ in 0..2 {
            let l = broken.lease().await.expect("a unit for the broken worker");
            broken.fail(l, "GPU lost: device removed").await;
        }
        std::time::Instant::now()
    });
    // Kept from the job: no lease although 12 units wait, while another
    // worker gets one at once.
    assert_eq!(
        rt.block_on(broken.lease()),
        None,
        "a blocklisted worker got a lease"
    );
    assert!(
        rt.block_on(good.lease()).is_some(),
        "the good worker got no lease"
    );
    let st = job_status(&c, &job);
    // Not failed: its units go to other workers.
    assert_eq!(st["state"], "running", "{st}");
    let listed = st["blocklisted"].as_array().expect("blocklisted");
    assert_eq!(listed.len(), 1, "{st}");
    assert_eq!(listed[0]["name"], "broken");
    assert_eq!(listed[0]["failures"], 2);
    let text = ok_stdout(&client(&c, &["status", &job]));
    assert!(
        text.contains("blocklist: worker broken (")
            && text.contains("failed 2 unit(s); kept from this job for"),
        "{text}"
    );
    let m = scrape(&c, Some(METRICS_TOKEN)).expect("scrape");
    assert_eq!(
        sample(&m, "tessera_results_total", &[("outcome", "failed")]),
        2.0
    );
    // Still kept a moment before the forgive time...
    while blocked_at.elapsed() < Duration::from_secs(3) {
        assert_eq!(
            rt.block_on(broken.lease()),
            None,
            "leased before being forgiven"
        );
        std::thread::sleep(Duration::from_millis(500));
    }
    // ... and forgiven after it.
    wait_for(
        "the broken worker to be forgiven",
        Duration::from_secs(5),
        || rt.block_on(broken.lease()).is_some(),
    );
    assert!(
        blocked_at.elapsed() >= Duration::from_secs(4),
        "forgiven after {:?}, before --blocklist-seconds 4",
        blocked_at.elapsed()
    );
    let st = job_status(&c, &job);
    assert_eq!(st["blocklisted"], serde_json::json!([]), "{st}");
}

/// Issue 37's gap: one bad worker cannot fail a job. Its failure reports
/// of a unit do not count against the job's attempts until a second
/// worker fails the same unit; then they all do.
#[test]
fn one_worker_alone_cannot_fail_a_job_a_second_failing_the_unit_does() {
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    // No blocklist: the bad worker keeps leasing the one unit.
    let c = start_coordinator(dir.path(), &["--blocklist-after", "0"]);
    let scene = repo("examples/resolution.toml");
    let job = ok_stdout(&client(
        &c,
        &[
            "submit",
            scene.to_str().unwrap(),
            "--width",
            "32",
            "--height",
            "24",
            "--samples",
            "1",
            "--tile-size",
            "32",
            "--max-attempts",
            "2",
        ],
    ))
    .trim()
    .to_string();
    let rt = rt();
    let mut bad = rt.block_on(Session::register(&c.grpc, "bad"));
    rt.block_on(async {
        for _ in 0..3 {
            let l = bad.lease().await.expect("the job's one unit, again");
            bad.fail(l, "out of memory").await;
        }
    });
    let st = job_status(&c, &job);
    assert_eq!(
        st["state"], "running",
        "three failures by one worker, max-attempts 2: {st}"
    );
    let mut other = rt.block_on(Session::register(&c.grpc, "other"));
    rt.block_on(async {
        let l = other.lease().await.expect("the unit for a second worker");
        other.fail(l, "out of memory").await;
    });
    let st = job_status(&c, &job);
    assert_eq!(st["state"], "failed", "{st}");
    let error = st["error"].as_str().expect("error");
    assert!(
        error.starts_with("work unit 0 (frame 0,")
            && error.ends_with(
                "failed 4 times: worker bad: out of memory; worker bad: out of memory; \
                 worker bad: out of memory; worker other: out of memory"
            ),
        "{error}"
    );
}

/// `tessera workers --json` of `c`.
fn workers_json(c: &Coordinator) -> Vec<Value> {
    let out = ok_stdout(&client(c, &["workers", "--json"]));
    let v: Value =
        serde_json::from_str(&out).unwrap_or_else(|e| panic!("workers --json: {e}: {out}"));
    v.as_array().expect("a list of workers").clone()
}

/// Labels and requirements: of two real workers, labelled pool=night and
/// pool=day, only the night one renders a job that requires pool=night
/// (every unit of it), and a job that no connected worker meets waits and
/// says why in `status`, `status --json`, `watch` and the monitor's JSON.
#[test]
fn a_requirement_routes_a_job_to_the_matching_worker_only_and_a_job_nobody_can_run_says_so() {
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), &[]);
    let _night = start_worker_with(
        dir.path(),
        &c.grpc,
        "night",
        &["--label", "pool=night", "--label", "gpu_memory_gb=80"],
    );
    let _day = start_worker_with(dir.path(), &c.grpc, "day", &["--label", "pool=day"]);
    wait_for("both workers", Duration::from_secs(60), || {
        workers_json(&c).len() == 2
    });
    let ws = workers_json(&c);
    let night = ws.iter().find(|w| w["name"] == "night").expect("night");
    // Given and automatic labels, backend and cores from the worker itself.
    assert_eq!(night["labels"]["pool"], "night", "{night}");
    assert_eq!(night["labels"]["gpu_memory_gb"], "80", "{night}");
    assert_eq!(night["labels"]["backend"], "cpu", "{night}");
    assert_eq!(night["labels"]["cores"], "1", "{night}");
    assert!(night["labels"]["host"].is_string(), "{night}");

    let scene = repo("examples/resolution.toml");
    let small = [
        "--width",
        "64",
        "--height",
        "48",
        "--samples",
        "2",
        "--tile-size",
        "16",
        "--samples-per-unit",
        "1",
    ];
    let mut args = vec!["submit", scene.to_str().unwrap()];
    args.extend(small);
    args.extend([
        "--require",
        "pool=night",
        "--require",
        "gpu_memory_gb>=40",
        "--wait",
    ]);
    let out = client(&c, &args);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let job = String::from_utf8_lossy(&out.stdout).trim().to_string();
    let st = job_status(&c, &job);
    assert_eq!(st["state"], "done", "{st}");
    assert_eq!(
        st["requirements"],
        serde_json::json!(["pool=night", "gpu_memory_gb>=40"])
    );
    // 12 tiles by 2 sample batches: all rendered by the night worker.
    assert_eq!(st["units_total"], 24, "{st}");
    let ws = workers_json(&c);
    let done = |name: &str| {
        ws.iter().find(|w| w["name"] == name).expect("worker")["units_done"]
            .as_u64()
            .expect("units_done")
    };
    assert_eq!((done("night"), done("day")), (24, 0), "{ws:?}");

    // Nobody has pool=gpu-farm: the job waits and says so.
    let mut args = vec!["submit", scene.to_str().unwrap()];
    args.extend(small);
    args.extend(["--require", "pool=gpu-farm"]);
    let stuck = ok_stdout(&client(&c, &args)).trim().to_string();
    let why = "no connected worker meets its requirements (pool=gpu-farm): of 2 connected, 2 lack pool=gpu-farm";
    let st = job_status(&c, &stuck);
    assert_eq!(st["state"], "queued", "{st}");
    assert_eq!(st["unrunnable"], why, "{st}");
    let text = ok_stdout(&client(&c, &["status", &stuck]));
    assert!(text.contains("requires:  pool=gpu-farm\n"), "{text}");
    assert!(text.contains(&format!("waiting:   {why}\n")), "{text}");
    // `watch` says it (on stderr) instead of waiting silently.
    let mut watch = Command::new(TESSERA)
        .args(["watch", &stuck])
        .env("TESSERA_COORDINATOR", &c.grpc)
        .env("TESSERA_TOKEN", CLIENT_TOKEN)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("watch");
    std::thread::sleep(Duration::from_secs(3));
    watch.kill().expect("stop watch");
    let o = watch.wait_with_output().expect("watch output");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains(&format!("job {stuck}: {why}")), "{err}");
    // The monitor's job JSON carries it too.
    let mj = monitor_job(&c, &stuck);
    assert_eq!(mj["unrunnable"], why, "{mj}");
    assert_eq!(mj["requirements"], serde_json::json!(["pool=gpu-farm"]));
    // Nothing of it was leased, to either worker.
    assert_eq!(job_status(&c, &stuck)["units_done"], 0);

    // A requirement that is not one is refused before anything is sent.
    refused(
        &c,
        &["submit", scene.to_str().unwrap(), "--require", "pool"],
        "requirement \"pool\" is neither KEY=VALUE nor KEY>=N",
    );
}

/// A submit of the small resolution scene with `extra` flags: its job id.
fn submit_small(c: &Coordinator, samples: &str, extra: &[&str]) -> String {
    submit_sized(c, ["64", "48"], samples, extra)
}

/// [`submit_small`] of `size` pixels (16x16 is one unit a sample).
fn submit_sized(c: &Coordinator, size: [&str; 2], samples: &str, extra: &[&str]) -> String {
    let scene = repo("examples/resolution.toml");
    let mut args = vec![
        "submit",
        scene.to_str().unwrap(),
        "--width",
        size[0],
        "--height",
        size[1],
        "--samples",
        samples,
        "--tile-size",
        "16",
        "--samples-per-unit",
        "1",
    ];
    args.extend(extra);
    ok_stdout(&client(c, &args)).trim().to_string()
}

#[test]
fn a_job_after_another_waits_unleased_until_it_is_done_across_a_restart_and_fails_with_its_cancellation()
 {
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), &[]);

    // An unknown parent is refused at submit, by name.
    let scene = repo("examples/resolution.toml");
    refused(
        &c,
        &["submit", scene.to_str().unwrap(), "--after", "jnosuchjob"],
        r#"--after jnosuchjob: no job "jnosuchjob" on this coordinator"#,
    );

    // Notifications need the coordinator's secret (this one has none).
    refused(
        &c,
        &[
            "submit",
            scene.to_str().unwrap(),
            "--on-done",
            "http://127.0.0.1:9/hook",
        ],
        "--on-done: this coordinator has no --notify-secret-file, so it cannot sign notifications",
    );

    // No worker yet: the parent is queued, the child waits for it.
    let parent = submit_small(&c, "400", &["--name", "parent"]);
    let child = submit_small(&c, "2", &["--name", "child", "--after", &parent]);
    let st = job_status(&c, &child);
    assert_eq!(st["state"], "waiting", "{st}");
    assert_eq!(st["after"], serde_json::json!([parent]), "{st}");
    assert_eq!(st["waiting_for"], serde_json::json!([parent]), "{st}");
    let text = ok_stdout(&client(&c, &["status", &child]));
    assert!(text.contains("state:     waiting\n"), "{text}");
    assert!(
        text.contains(&format!(
            "waiting:   for job(s) {parent} to be done (--after)\n"
        )),
        "{text}"
    );
    let m = scrape(&c, Some(METRICS_TOKEN)).expect("scrape");
    assert_eq!(sample(&m, "tessera_jobs", &[("state", "waiting")]), 1.0);
    assert_eq!(sample(&m, "tessera_jobs", &[("state", "queued")]), 1.0);
    // Only the parent's 12 tiles x 400 batches wait for a worker.
    assert_eq!(
        sample(&m, "tessera_units", &[("state", "waiting")]),
        4800.0,
        "the waiting job's units are not work a worker could take"
    );

    // The dependency is stored: after a restart the child still waits.
    drop(c);
    let c = start_coordinator(dir.path(), &[]);
    let st = job_status(&c, &child);
    assert_eq!(st["state"], "waiting", "{st}");
    assert_eq!(st["waiting_for"], serde_json::json!([parent]), "{st}");
    let mj = monitor_job(&c, &child);
    assert_eq!(mj["state"], "waiting", "{mj}");
    assert_eq!(mj["waiting_for"], serde_json::json!([parent]), "{mj}");

    // A worker: the parent runs; while it does, none of the child's
    // units is leased.
    let _w = start_worker(dir.path(), &c.grpc, "w");
    let mut seen_running = false;
    loop {
        // The child first: the parent not done after it means it was
        // not done when the child was read either.
        let ch = job_status(&c, &child);
        let p = job_status(&c, &parent);
        if p["state"] == "done" {
            break;
        }
        assert!(
            ["queued", "running"].contains(&p["state"].as_str().unwrap()),
            "{p}"
        );
        seen_running |= p["state"] == "running";
        assert_eq!(ch["state"], "waiting", "{ch}");
        assert_eq!(ch["units_done"], 0, "{ch}");
        assert!(ch["first_lease_unix_ms"].is_null(), "{ch}");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(seen_running, "the parent was never seen running");
    // Then the child runs, its first lease after the parent ended.
    let out = client(&c, &["watch", &child]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let p = job_status(&c, &parent);
    let ch = job_status(&c, &child);
    assert_eq!(ch["state"], "done", "{ch}");
    assert_eq!(ch["waiting_for"], serde_json::json!([]), "{ch}");
    assert!(
        ch["first_lease_unix_ms"].as_i64().unwrap() >= p["finished_unix_ms"].as_i64().unwrap(),
        "child leased before its parent ended: {ch} {p}"
    );

    // A parent cancelled: its child fails, naming it, and so does the
    // child's own child.
    drop(_w);
    let p2 = submit_small(&c, "2", &["--name", "doomed"]);
    let c2 = submit_small(&c, "2", &["--after", &p2]);
    let g2 = submit_small(&c, "2", &["--after", &c2, "--after", &parent]);
    assert_eq!(job_status(&c, &g2)["waiting_for"], serde_json::json!([c2]));
    ok_stdout(&client(&c, &["cancel", &p2]));
    let st = job_status(&c, &c2);
    assert_eq!(st["state"], "failed", "{st}");
    assert_eq!(
        st["error"],
        format!("job {p2} (doomed), which this job runs after (--after), was cancelled"),
        "{st}"
    );
    let st = job_status(&c, &g2);
    assert_eq!(st["state"], "failed", "{st}");
    assert!(
        st["error"].as_str().unwrap().starts_with(&format!(
            "job {c2} (resolution), which this job runs after (--after), failed: job {p2} (doomed)"
        )),
        "{st}"
    );
    // A failed or cancelled job cannot be a new job's parent.
    refused(
        &c,
        &["submit", scene.to_str().unwrap(), "--after", &p2],
        &format!(
            "--after {p2}: job {p2} (doomed) has been cancelled, so a job after it would never run"
        ),
    );
}

/// HMAC-SHA256 (RFC 2104) written here from SHA-256 alone: the receiver
/// checks the coordinator's signature (ring's) with its own code.
fn hmac_sha256(key: &[u8], msg: &[u8]) -> String {
    use sha2::{Digest, Sha256};
    let mut k = [0u8; 64];
    if key.len() > 64 {
        k[..32].copy_from_slice(&Sha256::digest(key));
    } else {
        k[..key.len()].copy_from_slice(key);
    }
    let pad = |b: u8| k.iter().map(|x| x ^ b).collect::<Vec<u8>>();
    let inner = Sha256::new()
        .chain_update(pad(0x36))
        .chain_update(msg)
        .finalize();
    let outer = Sha256::new()
        .chain_update(pad(0x5c))
        .chain_update(inner)
        .finalize();
    outer.iter().map(|b| format!("{b:02x}")).collect()
}

/// A request the receiver got: its path, headers (lower-case names), body.
#[derive(Clone, Debug)]
struct Received {
    path: String,
    headers: std::collections::HashMap<String, String>,
    body: Vec<u8>,
}

/// A real HTTP/1.1 server on a loopback port, in a thread of this test:
/// it records every request and answers 200, except the first request to
/// `/flaky`, which gets 500.
fn webhook_receiver() -> (String, std::sync::Arc<std::sync::Mutex<Vec<Received>>>) {
    webhook_receiver_at("127.0.0.1:0")
}

/// [`webhook_receiver`] listening on `addr`.
fn webhook_receiver_at(addr: &str) -> (String, std::sync::Arc<std::sync::Mutex<Vec<Received>>>) {
    use std::io::{BufRead, BufReader, Read, Write};
    let listener = std::net::TcpListener::bind(addr).expect("bind");
    let addr = listener.local_addr().expect("addr");
    let got = std::sync::Arc::new(std::sync::Mutex::new(Vec::<Received>::new()));
    let seen = got.clone();
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut stream) = stream else { continue };
            let mut r = BufReader::new(stream.try_clone().expect("clone"));
            let mut line = String::new();
            r.read_line(&mut line).expect("request line");
            let mut parts = line.split_whitespace();
            assert_eq!(parts.next(), Some("POST"), "{line}");
            let path = parts.next().expect("path").to_string();
            let mut headers = std::collections::HashMap::new();
            loop {
                let mut h = String::new();
                r.read_line(&mut h).expect("header");
                let h = h.trim_end();
                if h.is_empty() {
                    break;
                }
                let (k, v) = h.split_once(':').expect("header line");
                headers.insert(k.trim().to_ascii_lowercase(), v.trim().to_string());
            }
            let len: usize = headers["content-length"].parse().expect("length");
            let mut body = vec![0; len];
            r.read_exact(&mut body).expect("body");
            let first_flaky = {
                let mut g = seen.lock().unwrap();
                let first = path == "/flaky" && !g.iter().any(|x| x.path == "/flaky");
                g.push(Received {
                    path: path.clone(),
                    headers,
                    body,
                });
                first
            };
            let status = if first_flaky {
                "500 Internal Server Error"
            } else {
                "200 OK"
            };
            let _ = write!(
                stream,
                "HTTP/1.1 {status}\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"
            );
        }
    });
    (format!("http://{addr}"), got)
}

#[test]
fn a_job_that_ends_is_posted_signed_to_its_on_done_and_the_notify_urls_and_a_failed_post_is_retried()
 {
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let (url, got) = webhook_receiver();
    let secret = "a-notification-secret-of-32-bytes";
    std::fs::write(dir.path().join("notify.secret"), format!("{secret}\n")).expect("secret");
    let all = format!("{url}/all");
    let c = start_coordinator(
        dir.path(),
        &[
            "--notify",
            &all,
            "--notify-secret-file",
            dir.path().join("notify.secret").to_str().unwrap(),
        ],
    );
    let _w = start_worker(dir.path(), &c.grpc, "w");

    // An https receiver is refused at submit, by name.
    let scene = repo("examples/resolution.toml");
    refused(
        &c,
        &[
            "submit",
            scene.to_str().unwrap(),
            "--on-done",
            "https://example.com/hook",
        ],
        r#"--on-done "https://example.com/hook": https is not supported"#,
    );

    // A job done: its own receiver fails the first POST, the retry lands.
    let flaky = format!("{url}/flaky");
    let done = submit_small(&c, "2", &["--on-done", &flaky, "--wait"]);
    // A job cancelled (nobody can run it): told to --notify only.
    let stuck = submit_small(&c, "2", &["--require", "pool=none"]);
    ok_stdout(&client(&c, &["cancel", &stuck]));

    wait_for("the notifications", Duration::from_secs(30), || {
        let g = got.lock().unwrap();
        g.iter().filter(|r| r.path == "/flaky").count() >= 2
            && g.iter().filter(|r| r.path == "/all").count() >= 2
    });
    // Nothing more comes: each was delivered once (the flaky one twice).
    std::thread::sleep(Duration::from_secs(2));
    let got = got.lock().unwrap().clone();
    let count = |p: &str| got.iter().filter(|r| r.path == p).count();
    assert_eq!((count("/flaky"), count("/all")), (2, 2), "{got:?}");
    let status_done = job_status(&c, &done);
    let status_stuck = job_status(&c, &stuck);
    for r in &got {
        // The signature is the HMAC-SHA256 of the body under the secret
        // (the file's trailing newline dropped).
        assert_eq!(
            r.headers["x-tessera-signature"],
            format!("sha256={}", hmac_sha256(secret.as_bytes(), &r.body)),
            "{r:?}"
        );
        assert_eq!(r.headers["content-type"], "application/json");
        let body: Value = serde_json::from_slice(&r.body).expect("JSON body");
        // The body is the job's `tessera status --json`, whole.
        let (expected, state) = if body["job_id"] == done.as_str() {
            (&status_done, "done")
        } else {
            (&status_stuck, "cancelled")
        };
        assert_eq!(body["state"], state, "{body}");
        assert_eq!(r.headers["x-tessera-event"], format!("job.{state}"));
        assert_eq!(r.headers["x-tessera-job"], body["job_id"].as_str().unwrap());
        assert_eq!(
            &body, expected,
            "the POSTed JSON differs from status --json"
        );
    }
    let on_all: Vec<&str> = got
        .iter()
        .filter(|r| r.path == "/all")
        .map(|r| r.headers["x-tessera-job"].as_str())
        .collect();
    assert!(
        on_all.contains(&done.as_str()) && on_all.contains(&stuck.as_str()),
        "{on_all:?}"
    );
    assert!(
        got.iter()
            .filter(|r| r.path == "/flaky")
            .all(|r| r.headers["x-tessera-job"] == done),
        "{got:?}"
    );
    // The retry is in the coordinator's log.
    let log = c.proc.log();
    assert!(
        log.contains("job notification not delivered; retrying"),
        "{log}"
    );
}

/// A job that ends while its receiver is down, and a coordinator killed
/// while it retries: the restarted coordinator sends the notification
/// (the job's record says it is pending), once; a further restart sends
/// nothing (delivered, the record says so).
#[test]
fn a_notification_not_yet_delivered_when_the_coordinator_dies_is_sent_after_the_restart() {
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    // A loopback port with nobody on it (yet): every POST is refused.
    let addr = std::net::TcpListener::bind("127.0.0.1:0")
        .expect("bind")
        .local_addr()
        .expect("addr")
        .to_string();
    let secret = dir.path().join("notify.secret");
    std::fs::write(&secret, "a-notification-secret-of-32-bytes").expect("secret");
    let url = format!("http://{addr}/late");
    let args = [
        "--notify",
        url.as_str(),
        "--notify-secret-file",
        secret.to_str().unwrap(),
    ];
    let mut c = start_coordinator(dir.path(), &args);
    // Ends at once: cancelled, nobody could run it.
    let job = submit_small(&c, "2", &["--require", "pool=none"]);
    ok_stdout(&client(&c, &["cancel", &job]));
    wait_for("a refused delivery", Duration::from_secs(10), || {
        c.proc
            .log()
            .contains("job notification not delivered; retrying")
    });
    c.proc.sigkill();

    let (_, got) = webhook_receiver_at(&addr);
    let c = start_coordinator(dir.path(), &args);
    wait_for(
        "the notification after the restart",
        Duration::from_secs(20),
        || !got.lock().unwrap().is_empty(),
    );
    wait_for("its settling", Duration::from_secs(10), || {
        c.proc.log().contains("job notification delivered")
    });
    // Settled means stored: give the writer its commit, then restart again.
    std::thread::sleep(Duration::from_secs(1));
    drop(c);
    let c = start_coordinator(dir.path(), &args);
    std::thread::sleep(Duration::from_secs(2));
    let got = got.lock().unwrap().clone();
    assert_eq!(got.len(), 1, "{got:?}");
    assert_eq!(got[0].path, "/late");
    assert_eq!(got[0].headers["x-tessera-job"], job);
    assert_eq!(got[0].headers["x-tessera-event"], "job.cancelled");
    let body: Value = serde_json::from_slice(&got[0].body).expect("JSON body");
    assert_eq!(
        body,
        job_status(&c, &job),
        "the POST is the job's status --json"
    );
}

#[test]
fn a_jobs_own_blocklist_setting_applies_failures_are_counted_by_class_and_a_scene_error_on_a_second_worker_fails_the_job()
 {
    use tessera_proto::pb::FailureClass;
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    // The coordinator's default is 3 failures; the job says 1.
    let c = start_coordinator(dir.path(), &[]);
    let job = submit_small(
        &c,
        "1",
        &[
            "--blocklist-after",
            "1",
            "--blocklist-forgive",
            "120",
            "--max-attempts",
            "9",
        ],
    );
    let st = job_status(&c, &job);
    assert_eq!(
        (
            st["blocklist_after"].as_u64(),
            st["blocklist_seconds"].as_f64()
        ),
        (Some(1), Some(120.0)),
        "{st}"
    );
    let rt = rt();
    let (gpu, gpu_id) = rt.block_on(raw_worker(&c.grpc, "gpu-box"));
    let (a, a_id) = rt.block_on(raw_worker(&c.grpc, "a"));
    let (b, b_id) = rt.block_on(raw_worker(&c.grpc, "b"));
    let lease = |w, id| rt.block_on(raw_lease_id(w, id));
    // One lost GPU: blocklisted from this job after its 1 failure.
    let l = lease(&gpu, &gpu_id).expect("a unit for gpu-box");
    rt.block_on(raw_fail_class(
        &gpu,
        &gpu_id,
        l,
        "device lost",
        FailureClass::GpuLost,
    ));
    assert_eq!(
        lease(&gpu, &gpu_id),
        None,
        "blocklisted after the job's 1 failure"
    );
    // A scene error on one worker: the job goes on (it may be that worker's).
    let l = lease(&a, &a_id).expect("a unit for a");
    rt.block_on(raw_fail_class(
        &a,
        &a_id,
        l,
        "texture wood.png: unsupported format",
        FailureClass::Scene,
    ));
    let st = job_status(&c, &job);
    assert_eq!(st["state"], "running", "{st}");
    assert_eq!(
        st["failure_classes"],
        serde_json::json!({"gpu_lost": 1, "scene": 1}),
        "{st}"
    );
    // Both kept from the job after their one failure (the job's setting).
    let names: Vec<&str> = st["blocklisted"]
        .as_array()
        .expect("blocklisted")
        .iter()
        .map(|b| b["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["a", "gpu-box"], "{st}");
    let text = ok_stdout(&client(&c, &["status", &job]));
    assert!(
        text.contains("failures:  gpu_lost 1, scene 1 (units reported failed by workers, by class); blocklist after 1 of them, forgiven after 120 s\n"),
        "{text}"
    );
    // The monitor shows the classes and the settings too.
    let mj = monitor_job(&c, &job);
    assert_eq!(
        mj["failure_classes"],
        serde_json::json!({"gpu_lost": 1, "scene": 1}),
        "{mj}"
    );
    assert_eq!(mj["blocklist_after"], 1, "{mj}");
    // The same scene error on a second worker: failed at once, with the
    // message (9 attempts were allowed).
    let l = lease(&b, &b_id).expect("a unit for b");
    rt.block_on(raw_fail_class(
        &b,
        &b_id,
        l,
        "texture wood.png: unsupported format",
        FailureClass::Scene,
    ));
    let st = job_status(&c, &job);
    assert_eq!(st["state"], "failed", "{st}");
    assert_eq!(
        st["error"],
        "scene error reproduced on a second worker (a, b): texture wood.png: unsupported format",
        "{st}"
    );
    // Nothing of it is leased any more.
    assert_eq!(lease(&a, &a_id), None);
}

/// Out of memory on a 24 GB GPU: the unit goes to a bigger GPU, not to
/// another 24 GB one; its GPU lost there: to a CPU worker, and while none
/// is connected the job says what it waits for.
#[test]
fn units_that_run_out_of_memory_or_lose_their_gpu_go_where_they_can_run() {
    use tessera_proto::pb::{Backend, Capabilities, FailureClass};
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), &[]);
    // One unit: 16x16 pixels, one sample.
    let job = submit_sized(&c, ["16", "16"], "1", &["--max-attempts", "9"]);
    let rt = rt();
    let gpu = |gb: &str| {
        Some(Capabilities {
            backend: Backend::Gpu as i32,
            threads: 1,
            labels: [("gpu_memory_gb".to_string(), gb.to_string())].into(),
            ..Default::default()
        })
    };
    let (g24a, a_id) = rt.block_on(raw_worker_with(&c.grpc, "g24-a", gpu("24")));
    let (g24b, b_id) = rt.block_on(raw_worker_with(&c.grpc, "g24-b", gpu("24")));
    let (g80, big_id) = rt.block_on(raw_worker_with(&c.grpc, "g80", gpu("80")));
    let lease = |w, id| rt.block_on(raw_lease_id(w, id));
    let l = lease(&g24a, &a_id).expect("the unit for g24-a");
    rt.block_on(raw_fail_class(
        &g24a,
        &a_id,
        l,
        "render: out of memory allocating the tree",
        FailureClass::OutOfMemory,
    ));
    assert_eq!(lease(&g24b, &b_id), None, "a GPU of as much memory");
    let l = lease(&g80, &big_id).expect("the bigger GPU takes it");
    rt.block_on(raw_fail_class(
        &g80,
        &big_id,
        l,
        "Parent device is lost",
        FailureClass::GpuLost,
    ));
    assert_eq!(lease(&g80, &big_id), None, "its GPU was lost");
    assert_eq!(lease(&g24b, &b_id), None, "a GPU");
    let st = job_status(&c, &job);
    assert_eq!(
        st["failure_classes"],
        serde_json::json!({"gpu_lost": 1, "out_of_memory": 1}),
        "{st}"
    );
    assert_eq!(
        st["unrunnable"],
        "1 unit(s) that failed for want of memory or a GPU wait for a CPU worker: no connected worker is one",
        "{st}"
    );
    let (cpu, cpu_id) = rt.block_on(raw_worker(&c.grpc, "cpu"));
    assert!(lease(&cpu, &cpu_id).is_some(), "a CPU worker takes it");
    let log = c.proc.log();
    assert!(
        log.contains("units rerouted after out_of_memory")
            && log.contains("units rerouted after gpu_lost"),
        "{log}"
    );
}

#[test]
fn a_worker_serves_its_own_metrics_which_move_as_it_renders() {
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), &[]);
    let w = start_worker_with(dir.path(), &c.grpc, "metered", &["--http", "127.0.0.1:0"]);
    // The address bound is logged.
    let mut url = String::new();
    wait_for(
        "the worker's metrics address",
        Duration::from_secs(60),
        || {
            let log = w.log();
            match log.split("metrics on ").nth(1) {
                Some(rest) => {
                    url = rest.split_whitespace().next().unwrap_or("").to_string();
                    true
                }
                None => false,
            }
        },
    );
    assert!(
        url.starts_with("http://127.0.0.1:") && url.ends_with("/metrics"),
        "{url}"
    );
    let m = scrape_url(&url, None).expect("scrape the worker");
    for (name, kind) in [
        ("tessera_worker_units", "counter"),
        ("tessera_worker_leases", "gauge"),
        ("tessera_worker_threads", "gauge"),
        ("tessera_worker_info", "gauge"),
    ] {
        assert_eq!(m["types"][name], kind, "family {name}: {}", m["types"]);
    }
    assert_eq!(sample(&m, "tessera_worker_units_total", &[]), 0.0);
    assert_eq!(sample(&m, "tessera_worker_threads", &[]), 1.0);
    assert_eq!(
        sample(
            &m,
            "tessera_worker_info",
            &[("name", "metered"), ("backend", "cpu"), ("gpu", "")]
        ),
        1.0
    );
    // A job of 24 units, all this worker's: the counter follows.
    let job = submit_small(&c, "2", &["--wait"]);
    assert_eq!(job_status(&c, &job)["state"], "done");
    let m = scrape_url(&url, None).expect("scrape the worker");
    assert_eq!(sample(&m, "tessera_worker_units_total", &[]), 24.0);
    assert_eq!(sample(&m, "tessera_worker_leases", &[]), 0.0);
}

/// `tessera worker --backend gpu --adapter all`: one worker per GPU in one
/// process, each named NAME-gpuINDEX and labelled with its adapter's name
/// (software adapters only where there is no other: lavapipe here), and
/// together they render a job to the end.
#[test]
fn adapter_all_runs_a_worker_per_gpu_each_named_and_labelled_with_it() {
    if support::gpus().is_none() {
        return;
    }
    let listed: Value = serde_json::from_str(&ok_stdout(
        &Command::new(TESSERA)
            .args(["gpus", "--json"])
            .output()
            .expect("tessera gpus --json"),
    ))
    .expect("gpus --json");
    let listed = listed.as_array().expect("a list of adapters");
    let hardware: Vec<&Value> = listed.iter().filter(|a| a["type"] != "Cpu").collect();
    let expected: Vec<&Value> = if hardware.is_empty() {
        listed.iter().collect()
    } else {
        hardware
    };
    let _serial = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start_coordinator(dir.path(), &[]);
    let _w = start_worker_with(
        dir.path(),
        &c.grpc,
        "multi",
        &["--backend", "gpu", "--adapter", "all"],
    );
    wait_for("a worker per GPU", Duration::from_secs(60), || {
        workers_json(&c).len() == expected.len()
    });
    let ws = workers_json(&c);
    for a in &expected {
        let name = format!("multi-gpu{}", a["index"]);
        let w = ws
            .iter()
            .find(|w| w["name"] == name.as_str())
            .unwrap_or_else(|| panic!("no worker {name} in {ws:?}"));
        assert_eq!(w["backend"], "gpu", "{w}");
        assert_eq!(w["labels"]["gpu"], a["name"], "{w}");
        assert_eq!(w["labels"]["backend"], "gpu", "{w}");
    }
    let scene = repo("examples/resolution.toml");
    let o = client(
        &c,
        &[
            "submit",
            scene.to_str().unwrap(),
            "--width",
            "64",
            "--height",
            "48",
            "--samples",
            "2",
            "--wait",
        ],
    );
    let job = ok_stdout(&o)
        .lines()
        .next()
        .unwrap_or_default()
        .trim()
        .to_string();
    let st = job_status(&c, &job);
    assert_eq!(st["state"], "done", "{st}");
    let done: u64 = workers_json(&c)
        .iter()
        .map(|w| w["units_done"].as_u64().unwrap())
        .sum();
    assert_eq!(done, st["units_total"].as_u64().unwrap(), "{st}");
    drop(c.proc);
}
