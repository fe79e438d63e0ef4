//! Helpers shared by the end-to-end test files (each `mod support;`s it).
#![allow(dead_code)]

pub mod sky;

use std::io::{BufRead as _, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

pub mod prereq;
#[allow(unused_imports)]
pub use prereq::{require, shared};

use tessera_proto::pb;
use tessera_proto::pb::worker_service_client::WorkerServiceClient;
use tonic::transport::Channel;

pub const TESSERA: &str = env!("CARGO_BIN_EXE_tessera");

/// Holds the tests of one file that must not run at once (farms that
/// watch their own timing, shared ports); a panicked holder does not
/// poison it for the rest.
pub fn serial() -> std::sync::MutexGuard<'static, ()> {
    static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}
pub fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

/// A child process killed when dropped.
pub struct Proc {
    pub child: Child,
    pub log: PathBuf,
}

impl Proc {
    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
    pub fn sigkill(&mut self) {
        self.child.kill().expect("kill");
        self.child.wait().expect("reap");
    }
    pub fn sigterm(&self) {
        self.signal("TERM");
    }
    /// Sends the signal `name` (TERM, STOP, CONT, ...).
    pub fn signal(&self, name: &str) {
        let ok = Command::new("kill")
            .args([&format!("-{name}"), &self.child.id().to_string()])
            .status()
            .expect("kill")
            .success();
        assert!(ok, "kill -{name} failed");
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A 32 x 16 [`sky`] as an EXR file at `path`.
pub fn write_sky_exr(path: &Path) {
    let (w, h) = (32u32, 16u32);
    let texels = sky::texels(w, h, (9, 4), [30.0, 25.0, 18.0]);
    image::Rgb32FImage::from_fn(w, h, |x, y| image::Rgb(texels[(y * w + x) as usize]))
        .save(path)
        .expect("write the sky");
}

pub fn rand_suffix() -> u128 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos())
}

pub fn ok_stdout(o: &Output) -> String {
    assert!(
        o.status.success(),
        "tessera failed: {}\n{}",
        o.status,
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8(o.stdout.clone()).expect("utf-8")
}

pub fn pixels(path: &Path) -> Vec<u8> {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8()
        .into_raw()
}

/// `tessera render` of the same scene and settings, as the reference.
pub fn reference(dir: &Path, scene: &Path, frame: u32, settings: &[&str]) -> Vec<u8> {
    let out = dir.join(format!("reference_{frame}.png"));
    let f = frame.to_string();
    let mut args = vec![
        "render",
        scene.to_str().expect("path"),
        "-o",
        out.to_str().expect("path"),
        "--frame",
        &f,
    ];
    args.extend_from_slice(settings);
    ok_stdout(&Command::new(TESSERA).args(&args).output().expect("render"));
    pixels(&out)
}

pub fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime")
}

pub fn wait_for(what: &str, timeout: Duration, mut f: impl FnMut() -> bool) {
    let start = Instant::now();
    while !f() {
        assert!(
            start.elapsed() < timeout,
            "timed out after {timeout:?} waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

pub type SecureJobClient = tessera_proto::pb::job_service_client::JobServiceClient<
    tonic::service::interceptor::InterceptedService<
        tonic::transport::Channel,
        tessera_proto::VersionStamp,
    >,
>;

/// A job-service client as `tessera` makes one: TLS trusting `ca` for an
/// https:// URL, and the token in `token_file`.
pub async fn secure_jobs_client(
    url: &str,
    ca: Option<&Path>,
    token_file: Option<&Path>,
) -> SecureJobClient {
    let ca = ca.map(|p| std::fs::read(p).expect("read CA"));
    let token = token_file.map(|p| {
        std::fs::read_to_string(p)
            .expect("read token")
            .trim()
            .to_string()
    });
    let channel = tessera_proto::transport::endpoint(url, ca.as_deref())
        .expect("endpoint")
        .connect()
        .await
        .unwrap_or_else(|e| panic!("connect {url}: {e:?}"));
    let stamp = tessera_proto::VersionStamp::with_token(token.as_deref()).expect("token");
    tessera_proto::pb::job_service_client::JobServiceClient::with_interceptor(channel, stamp)
        .max_decoding_message_size(1 << 30)
}

/// `tessera cert --tokens` for a farm whose coordinator is reached as `names`:
/// dir/ca.pem, coordinator.pem, coordinator.key, client.token, worker.token.
pub fn make_tls(dir: &Path, names: &[&str]) {
    let mut args = vec!["cert", "--tokens", "--out", dir.to_str().expect("path")];
    for n in names {
        args.extend(["--name", n]);
    }
    ok_stdout(
        &Command::new(TESSERA)
            .args(&args)
            .output()
            .expect("tessera cert"),
    );
}

/// `tessera gpus`'s table, when it finds an adapter (the prerequisite
/// `gpu`: its absence fails the test, see [`prereq`]).
pub fn gpus() -> Option<String> {
    let o = Command::new(TESSERA)
        .arg("gpus")
        .output()
        .expect("tessera gpus");
    require(
        "gpu",
        if o.status.success() {
            Ok(String::from_utf8_lossy(&o.stdout).into_owned())
        } else {
            Err(format!(
                "`tessera gpus` found no adapter: {}",
                String::from_utf8_lossy(&o.stderr).trim()
            ))
        },
    )
}

/// A coordinator a test started: its process, its gRPC address and its
/// monitor's (`host:port`, no scheme), when it has one.
pub struct Spawned {
    pub proc: Proc,
    pub grpc: String,
    pub http: Option<String>,
}

/// `BIN coordinator` on free loopback ports, with its monitor when `http`,
/// its data under `dir` (for [`spawn_coordinator`]; more flags may follow).
pub fn coordinator_command(bin: &str, dir: &Path, http: bool) -> Command {
    let mut cmd = Command::new(bin);
    cmd.args(["coordinator", "--listen", "127.0.0.1:0"]);
    if http {
        cmd.args(["--http", "127.0.0.1:0"]);
    }
    cmd.arg("--data").arg(dir.join("data"));
    cmd
}

/// Runs `cmd`, a `tessera coordinator` (perhaps under `sh -c`, which then
/// must `exec` it) listening on port 0, with its log in `dir`, and reads
/// the addresses it prints: the gRPC one, then the monitor's when `http`.
pub fn spawn_coordinator(mut cmd: Command, dir: &Path, http: bool) -> Spawned {
    let log = dir.join(format!("coordinator-{}.log", rand_suffix()));
    let mut child = cmd
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log).expect("log file"))
        .spawn()
        .expect("start coordinator");
    let mut out = BufReader::new(child.stdout.take().expect("stdout"));
    let mut line = |prefix: &str| {
        let mut l = String::new();
        out.read_line(&mut l).expect("read stdout");
        l.trim()
            .strip_prefix(prefix)
            .unwrap_or_else(|| panic!("coordinator did not start: {l:?} (log {})", log.display()))
            .to_string()
    };
    let grpc = line("listening on ");
    let http = http.then(|| line("monitor on http://"));
    Spawned {
        proc: Proc { child, log },
        grpc,
        http,
    }
}

/// `tessera worker` of one render thread named `name`, on `url`, with its
/// log in `dir`.
pub fn start_worker(dir: &Path, url: &str, name: &str) -> Proc {
    start_worker_with(dir, url, name, &[])
}

/// [`start_worker`] with more flags.
pub fn start_worker_with(dir: &Path, url: &str, name: &str, extra: &[&str]) -> Proc {
    let log = dir.join(format!("worker-{name}-{}.log", rand_suffix()));
    let child = Command::new(TESSERA)
        .args(["worker", "--coordinator", url, "--threads", "1"])
        .args(["--name", name])
        .args(extra)
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).expect("log file"))
        .spawn()
        .expect("start worker");
    Proc { child, log }
}

/// A worker session speaking the protocol by hand (a real gRPC client, not
/// a mock): its client and its session id.
pub async fn raw_worker(url: &str, name: &str) -> (WorkerServiceClient<Channel>, String) {
    raw_worker_with(url, name, None).await
}

/// [`raw_worker`] registering with `capabilities` (backend, labels).
pub async fn raw_worker_with(
    url: &str,
    name: &str,
    capabilities: Option<pb::Capabilities>,
) -> (WorkerServiceClient<Channel>, String) {
    let mut w = WorkerServiceClient::connect(url.to_string())
        .await
        .expect("connect");
    let id = w
        .register(pb::RegisterRequest {
            name: name.into(),
            capabilities,
        })
        .await
        .expect("register")
        .into_inner()
        .worker_id;
    (w, id)
}

/// One lease request of at most one unit, as session `id`.
pub async fn raw_lease(w: &WorkerServiceClient<Channel>, id: &str) -> pb::LeaseWorkResponse {
    w.clone()
        .lease_work(pb::LeaseWorkRequest {
            worker_id: id.to_string(),
            max_units: 1,
            ..Default::default()
        })
        .await
        .expect("lease")
        .into_inner()
}

/// The lease id of [`raw_lease`]'s one unit, if it got one.
pub async fn raw_lease_id(w: &WorkerServiceClient<Channel>, id: &str) -> Option<String> {
    raw_lease(w, id)
        .await
        .units
        .into_iter()
        .next()
        .map(|u| u.lease_id)
}

/// Reports lease `lease_id` of session `id` failed with `message`, which
/// the coordinator must record as a failure.
pub async fn raw_fail(w: &WorkerServiceClient<Channel>, id: &str, lease_id: String, message: &str) {
    raw_fail_class(w, id, lease_id, message, pb::FailureClass::Unspecified).await
}

/// [`raw_fail`] with the failure's class (issue 38).
pub async fn raw_fail_class(
    w: &WorkerServiceClient<Channel>,
    id: &str,
    lease_id: String,
    message: &str,
    class: pb::FailureClass,
) {
    let r = w
        .clone()
        .submit_result(pb::SubmitResultRequest {
            worker_id: id.to_string(),
            lease_id,
            failure: message.into(),
            failure_class: class as i32,
            ..Default::default()
        })
        .await
        .expect("submit the failure")
        .into_inner();
    assert_eq!(r.outcome, pb::ResultOutcome::FailureRecorded as i32);
}

/// Waits for a child to exit (killing it after `timeout`); its exit code.
pub fn wait_exit(child: &mut std::process::Child, timeout: Duration) -> Option<i32> {
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            return status.code();
        }
        if start.elapsed() > timeout {
            let _ = child.kill();
            let _ = child.wait();
            panic!("process still running after {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}
