//! The farm across hosts of their own: the coordinator, three workers and
//! the client each run in a Linux network namespace with its own address
//! (veth pairs on a bridge in a "switch" namespace) and its own working
//! directory holding only what that host would have. TLS and tokens are on.
//! Taking a worker's link down is a real partition.
//!
//! Needs root and iproute2 (CI runs as root): the prerequisite `netns`,
//! optional outside CI (tests/optional.txt, tests/support/prereq.rs).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use tessera_proto::pb;

mod support;
use support::*;

/// Runs `ip ARGS`, panicking with its message on failure.
fn ip(args: &[&str]) {
    let out = Command::new("ip").args(args).output().expect("run ip");
    assert!(
        out.status.success(),
        "ip {}: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Why namespaces cannot be used here, if they cannot.
fn netns_unavailable() -> Option<String> {
    let root = Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0");
    if !root {
        return Some("network namespaces need root".into());
    }
    let probe = format!("tsprobe{}", std::process::id());
    match Command::new("ip").args(["netns", "add", &probe]).output() {
        Err(e) => Some(format!("cannot run ip (install iproute2): {e}")),
        Ok(o) if !o.status.success() => Some(format!(
            "ip netns add failed: {}",
            String::from_utf8_lossy(&o.stderr).trim()
        )),
        Ok(_) => {
            let _ = Command::new("ip").args(["netns", "del", &probe]).status();
            None
        }
    }
}

/// Hosts on one switch: host i has address 10.213.S.i (S from the pid, so
/// parallel runs do not meet). This test's own process reaches them from
/// the root namespace through one more port, address .100.
struct Lan {
    tag: String,
    subnet: String,
    hosts: Vec<String>,
}

impl Lan {
    fn new(n: usize) -> Lan {
        let pid = std::process::id();
        let tag = format!("ts{}", pid % 100_000);
        let subnet = format!("10.213.{}", pid % 250);
        let lan = Lan {
            subnet,
            hosts: (1..=n).map(|i| format!("{tag}h{i}")).collect(),
            tag,
        };
        let sw = lan.switch();
        ip(&["netns", "add", &sw]);
        ip(&["-n", &sw, "link", "add", "br0", "type", "bridge"]);
        ip(&["-n", &sw, "link", "set", "br0", "up"]);
        for (i, h) in lan.hosts.iter().enumerate() {
            ip(&["netns", "add", h]);
            let port = lan.port(i + 1);
            ip(&[
                "link", "add", &port, "netns", &sw, "type", "veth", "peer", "name", "eth0",
                "netns", h,
            ]);
            ip(&["-n", &sw, "link", "set", &port, "master", "br0", "up"]);
            ip(&[
                "-n",
                h,
                "addr",
                "add",
                &format!("{}/24", lan.addr(i + 1)),
                "dev",
                "eth0",
            ]);
            ip(&["-n", h, "link", "set", "eth0", "up"]);
            ip(&["-n", h, "link", "set", "lo", "up"]);
        }
        // The test's port, in the root namespace.
        let here = format!("{}t", lan.tag);
        ip(&[
            "link",
            "add",
            &here,
            "type",
            "veth",
            "peer",
            "name",
            &lan.port(100),
            "netns",
            &sw,
        ]);
        ip(&[
            "-n",
            &sw,
            "link",
            "set",
            &lan.port(100),
            "master",
            "br0",
            "up",
        ]);
        ip(&[
            "addr",
            "add",
            &format!("{}.100/24", lan.subnet),
            "dev",
            &here,
        ]);
        ip(&["link", "set", &here, "up"]);
        lan
    }
    fn switch(&self) -> String {
        format!("{}sw", self.tag)
    }
    fn port(&self, i: usize) -> String {
        format!("{}p{i}", self.tag)
    }
    /// Address of host `i` (1-based).
    fn addr(&self, i: usize) -> String {
        format!("{}.{i}", self.subnet)
    }
    /// Takes host i's link down (true) or up (false) at the switch.
    fn cut(&self, i: usize, down: bool) {
        let state = if down { "down" } else { "up" };
        ip(&["-n", &self.switch(), "link", "set", &self.port(i), state]);
    }
    /// A `tessera` command on host i, in `dir`.
    fn tessera(&self, i: usize, dir: &Path) -> Command {
        let mut c = Command::new("ip");
        c.args(["netns", "exec", &self.hosts[i - 1], TESSERA])
            .current_dir(dir)
            .env_remove("TESSERA_COORDINATOR")
            .env("RUST_LOG", "info");
        c
    }
}

impl Drop for Lan {
    fn drop(&mut self) {
        // Deleting a namespace deletes its ends of the veth pairs, and the peers with them.
        for h in self.hosts.iter().chain([&self.switch()]) {
            let _ = Command::new("ip").args(["netns", "del", h]).status();
        }
        let _ = Command::new("ip")
            .args(["link", "del", &format!("{}t", self.tag)])
            .stderr(Stdio::null())
            .status();
    }
}

/// A fresh working directory for a host, holding only `files` (copied).
fn host_dir(root: &Path, name: &str, files: &[(&Path, &str)]) -> PathBuf {
    let d = root.join(name);
    std::fs::create_dir_all(&d).expect("mkdir");
    for (src, dst) in files {
        let to = d.join(dst);
        std::fs::create_dir_all(to.parent().expect("parent")).expect("mkdir");
        std::fs::copy(src, &to).unwrap_or_else(|e| panic!("copy {}: {e}", src.display()));
    }
    d
}

fn spawn_logged(mut c: Command, dir: &Path, name: &str) -> Proc {
    let log = dir.join(format!("{name}.log"));
    let child = c
        .stdout(std::fs::File::create(dir.join(format!("{name}.out"))).expect("out"))
        .stderr(std::fs::File::create(&log).expect("log"))
        .spawn()
        .expect("spawn");
    Proc { child, log }
}

#[test]
fn a_farm_of_separate_hosts_with_tls_and_tokens_renders_meshes_and_animations_bit_identical_and_survives_a_partition()
 {
    if require("netns", netns_unavailable().map_or(Ok(()), Err)).is_none() {
        return;
    }
    let tmp = tempfile::tempdir().expect("tempdir");
    let root = tmp.path();
    let lan = Lan::new(5); // 1 coordinator, 2-4 workers, 5 client
    let coord_addr = format!("{}:7878", lan.addr(1));
    let url = format!("https://{coord_addr}");
    let tls = root.join("tls");
    make_tls(&tls, &[&lan.addr(1)]);

    let coord_dir = host_dir(
        root,
        "coordinator",
        &[
            (&tls.join("coordinator.pem"), "coordinator.pem"),
            (&tls.join("coordinator.key"), "coordinator.key"),
            (&tls.join("client.token"), "client.token"),
            (&tls.join("worker.token"), "worker.token"),
        ],
    );
    let mut c = lan.tessera(1, &coord_dir);
    c.args([
        "coordinator",
        "--listen",
        &coord_addr,
        "--data",
        "data",
        "--tls-cert",
        "coordinator.pem",
        "--tls-key",
        "coordinator.key",
        "--client-token-file",
        "client.token",
        "--worker-token-file",
        "worker.token",
        "--lease-timeout",
        "2",
        "--heartbeat-interval",
        "0.5",
    ]);
    let coordinator = spawn_logged(c, &coord_dir, "coordinator");
    wait_for("the coordinator to listen", Duration::from_secs(20), || {
        std::fs::read_to_string(coord_dir.join("coordinator.out"))
            .is_ok_and(|o| o.contains("listening on"))
    });
    let mut workers = Vec::new();
    for i in 2..=4 {
        let name = format!("worker{i}");
        let d = host_dir(
            root,
            &name,
            &[
                (&tls.join("ca.pem"), "ca.pem"),
                (&tls.join("worker.token"), "worker.token"),
            ],
        );
        let mut w = lan.tessera(i, &d);
        w.args([
            "worker",
            "--coordinator",
            &url,
            "--ca",
            "ca.pem",
            "--token-file",
            "worker.token",
            "--threads",
            "1",
            "--name",
            &name,
            "--cache",
            "cache",
        ]);
        w.env("RUST_LOG", "info");
        workers.push(spawn_logged(w, &d, "worker"));
    }
    // The client has the scenes (with their models) and its token, nothing else.
    let client_dir = host_dir(
        root,
        "client",
        &[
            (&tls.join("ca.pem"), "ca.pem"),
            (&tls.join("client.token"), "client.token"),
            (&repo("examples/cornell.toml"), "scenes/cornell.toml"),
            (
                &repo("examples/models/cornell_box.obj"),
                "scenes/models/cornell_box.obj",
            ),
            (
                &repo("examples/models/cornell_box.mtl"),
                "scenes/models/cornell_box.mtl",
            ),
            (&repo("examples/animation.toml"), "scenes/animation.toml"),
        ],
    );
    // A client command on the client's host, with its CA and token.
    let client_cmd = |args: &[&str]| {
        let mut c = lan.tessera(5, &client_dir);
        c.args(args).args([
            "--coordinator",
            &url,
            "--ca",
            "ca.pem",
            "--token-file",
            "client.token",
        ]);
        c
    };
    let submit = |scene: &str, args: &[&str]| -> String {
        let mut c = client_cmd(&["submit", scene]);
        c.args(args);
        let out = c.output().expect("submit");
        assert!(
            out.status.success(),
            "submit {scene}: {}\ncoordinator log:\n{}",
            String::from_utf8_lossy(&out.stderr),
            coordinator.log()
        );
        String::from_utf8_lossy(&out.stdout).trim().to_string()
    };
    // The test watches from its own port, as a client would.
    let rt = rt();
    let mut client = rt.block_on(secure_jobs_client(
        &url,
        Some(&tls.join("ca.pem")),
        Some(&tls.join("client.token")),
    ));
    let mut status = |job: &str| -> pb::JobStatus {
        rt.block_on(client.get_job(pb::GetJobRequest {
            job_id: job.into(),
            ..Default::default()
        }))
        .expect("get job")
        .into_inner()
    };
    let wait_done = |status: &mut dyn FnMut(&str) -> pb::JobStatus, job: &str| {
        let start = Instant::now();
        loop {
            let s = status(job);
            assert!(
                s.state != pb::JobState::Failed as i32,
                "job failed: {}",
                s.error
            );
            if s.state == pb::JobState::Done as i32 {
                return s;
            }
            assert!(
                start.elapsed() < Duration::from_secs(180),
                "job {job} not done in 180 s: {s:?}\ncoordinator log:\n{}",
                coordinator.log()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    };
    let fetch_and_compare =
        |job: &str, scene: &Path, frames: std::ops::RangeInclusive<u32>, settings: &[&str]| {
            let out = format!("out-{job}");
            ok_stdout(
                &client_cmd(&["fetch", job, "-o", &out])
                    .output()
                    .expect("fetch"),
            );
            for f in frames {
                let got = pixels(&client_dir.join(&out).join(format!("frame_{f:04}.png")));
                let want = reference(root, scene, f, settings);
                assert_eq!(got.len(), want.len(), "frame {f}: size");
                let diff = got.iter().zip(&want).filter(|(a, b)| a != b).count();
                assert_eq!(
                    diff, 0,
                    "{job} frame {f}: {diff} bytes differ from tessera render"
                );
            }
        };

    // A mesh scene: its OBJ and MTL travel with it.
    let mesh_settings = ["--width", "96", "--height", "72", "--samples", "4"];
    let mesh_job = submit("scenes/cornell.toml", &mesh_settings);
    wait_done(&mut status, &mesh_job);
    fetch_and_compare(
        &mesh_job,
        &repo("examples/cornell.toml"),
        0..=0,
        &mesh_settings,
    );

    // A three-frame animation; one worker's link goes down for longer than
    // its lease while it renders, and comes back.
    let anim_settings = ["--width", "128", "--height", "96", "--samples", "1024"];
    let mut args = anim_settings.to_vec();
    args.extend([
        "--frames",
        "1..3",
        "--tile-size",
        "32",
        "--samples-per-unit",
        "64",
    ]);
    let anim_job = submit("scenes/animation.toml", &args);
    let start = Instant::now();
    while status(&anim_job).samples_done * 10 < status(&anim_job).samples_total {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "animation made no progress"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    lan.cut(2, true);
    // Down past its lease (2 s): the worker's heartbeats go unanswered, so
    // it takes its leases as expired (they went to the other workers),
    // stops their work and, once the link is back, registers again.
    let cut = Instant::now();
    let expired = "the leases have expired";
    wait_for(
        "worker2 to give up its leases while cut off",
        Duration::from_secs(30),
        || workers[0].log().contains(expired),
    );
    let gave_up = cut.elapsed();
    assert!(
        gave_up >= Duration::from_secs(2),
        "worker2 gave its leases up after {gave_up:?}, before the 2 s lease timeout"
    );
    let during = status(&anim_job);
    assert_ne!(
        during.state,
        pb::JobState::Done as i32,
        "the job outlasts the partition"
    );
    let registered = || workers[0].log().matches("registered").count();
    let before = registered();
    lan.cut(2, false);
    wait_for(
        "worker2 to register again after the partition",
        Duration::from_secs(60),
        || registered() > before,
    );
    let done = wait_done(&mut status, &anim_job);
    fetch_and_compare(
        &anim_job,
        &repo("examples/animation.toml"),
        1..=3,
        &anim_settings,
    );
    assert_eq!(done.units_done, done.units_total);
    // Every worker fetched the model by hash into its own cache.
    for i in 2..=4 {
        let cache = root.join(format!("worker{i}/cache"));
        let n = std::fs::read_dir(&cache).map_or(0, |d| d.count());
        assert!(n >= 1, "worker{i} cached nothing in {}", cache.display());
    }
}
