//! Attacks on the coordinator's network edge that need no token (issue
//! 37): idle sockets, cross-site requests to the monitor, stalled and
//! concurrent uploads, weak tokens. Real processes on 127.0.0.1; every
//! loop is bounded in count and time.

use std::io::{Read as _, Write as _};
use std::net::TcpStream;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use tessera_proto::pb;
use tessera_proto::transport::sha256_hex;

mod support;
use support::*;

struct Coordinator {
    proc: Proc,
    grpc: String,
    http: Option<String>,
}

/// A coordinator started through `sh -c '...; exec tessera coordinator'`
/// (`prefix` may set a ulimit), with the monitor when `http`.
fn start(dir: &Path, prefix: &str, http: bool, extra: &[&str]) -> Coordinator {
    let mut cmd = format!(
        "{prefix} exec '{TESSERA}' coordinator --listen 127.0.0.1:0 --data '{}'",
        dir.join("data").display()
    );
    if http {
        cmd += " --http 127.0.0.1:0";
    }
    for a in extra {
        cmd += &format!(" '{a}'");
    }
    let mut sh = Command::new("sh");
    sh.args(["-c", &cmd]);
    let Spawned { proc, grpc, http } = spawn_coordinator(sh, dir, http);
    Coordinator { proc, grpc, http }
}

/// Lets this test process hold thousands of sockets.
fn raise_own_descriptor_limit() {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: the struct is the only memory touched.
    unsafe {
        assert_eq!(libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim), 0);
        lim.rlim_cur = lim.rlim_max;
        assert_eq!(libc::setrlimit(libc::RLIMIT_NOFILE, &lim), 0);
    }
    assert!(
        lim.rlim_cur >= 4096,
        "this test opens 2,200 sockets: the hard open-files limit is {}",
        lim.rlim_cur
    );
}

/// One HTTP/1.1 request; (status, body).
fn http(addr: &str, request: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).expect("connect monitor");
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s.write_all(request.as_bytes()).expect("send");
    let mut out = String::new();
    s.read_to_string(&mut out).expect("read answer");
    let status = out
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no status in {out:?}"));
    let body = out.split("\r\n\r\n").nth(1).unwrap_or("").to_string();
    (status, body)
}

fn rss_kib(pid: u32) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("proc status");
    s.lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS")
}

fn register(url: &str) -> Result<String, String> {
    rt().block_on(async {
        let ch = tessera_proto::transport::endpoint(url, None)
            .map_err(|e| e.to_string())?
            .connect()
            .await
            .map_err(|e| format!("connect: {e:?}"))?;
        let stamp = tessera_proto::VersionStamp::with_token(None).expect("stamp");
        let mut c = pb::worker_service_client::WorkerServiceClient::with_interceptor(ch, stamp);
        c.register(pb::RegisterRequest {
            name: "edge-test".into(),
            capabilities: Some(pb::Capabilities {
                threads: 1,
                ..Default::default()
            }),
        })
        .await
        .map(|r| r.into_inner().worker_id)
        .map_err(|e| e.to_string())
    })
}

#[test]
fn idle_sockets_under_a_1024_descriptor_limit_do_not_lock_clients_out() {
    let _g = serial();
    raise_own_descriptor_limit();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start(dir.path(), "ulimit -n 1024;", true, &[]);
    let http_addr = c.http.clone().expect("monitor");
    let url = format!("http://{}", c.grpc);
    // 1,100 sockets to each port that never send a byte.
    let mut idle = Vec::new();
    let start_open = Instant::now();
    for addr in [&c.grpc, &http_addr] {
        let a = addr.parse().expect("address");
        for _ in 0..1100 {
            if let Ok(s) = TcpStream::connect_timeout(&a, Duration::from_secs(1)) {
                idle.push(s);
            }
            assert!(
                start_open.elapsed() < Duration::from_secs(60),
                "opening sockets took over 60 s"
            );
        }
    }
    assert!(
        idle.len() >= 2000,
        "only {} of 2200 sockets connected",
        idle.len()
    );

    let t = Instant::now();
    let o = Command::new(TESSERA)
        .args(["jobs", "--coordinator", &url])
        .output()
        .expect("tessera jobs");
    let jobs_s = t.elapsed().as_secs_f64();
    ok_stdout(&o);
    let t = Instant::now();
    let worker = register(&url).expect("a worker registers");
    let register_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (status, body) = http(
        &http_addr,
        &format!("GET /api/info HTTP/1.1\r\nHost: {http_addr}\r\nConnection: close\r\n\r\n"),
    );
    let monitor_s = t.elapsed().as_secs_f64();
    assert_eq!(status, 200, "{body}");
    eprintln!(
        "with {} idle sockets: tessera jobs {jobs_s:.2} s, register {register_s:.2} s ({worker}), monitor {monitor_s:.2} s",
        idle.len()
    );
    for (what, s) in [
        ("tessera jobs", jobs_s),
        ("register", register_s),
        ("monitor", monitor_s),
    ] {
        assert!(s < 3.0, "{what} took {s:.2} s with idle sockets open");
    }
    let log = c.proc.log();
    assert!(
        log.contains("open_files=1024"),
        "the descriptor limit is logged: {log}"
    );
    assert!(
        log.contains("connection limits: closed connections"),
        "{log}"
    );
    drop(idle);
}

#[test]
fn a_socket_that_sends_nothing_is_closed_after_the_handshake_timeout() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start(dir.path(), "", true, &["--handshake-timeout", "1"]);
    for addr in [c.grpc.clone(), c.http.clone().expect("monitor")] {
        let mut s = TcpStream::connect(&addr).expect("connect");
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let t = Instant::now();
        // The gRPC port sends its HTTP/2 settings at once; then EOF or a
        // reset, either way closed by the coordinator.
        let mut buf = [0u8; 256];
        while let Ok(n @ 1..) = s.read(&mut buf) {
            assert!(n <= 64, "{addr}: {n} bytes sent to a silent client");
        }
        let took = t.elapsed();
        assert!(
            took >= Duration::from_millis(900) && took < Duration::from_secs(4),
            "{addr}: closed after {took:?}, not about 1 s"
        );
    }
}

/// A queued job on a coordinator with the monitor and no token.
fn queued_job(dir: &Path, extra: &[&str]) -> (Coordinator, String) {
    let c = start(dir, "", true, extra);
    let o = Command::new(TESSERA)
        .args([
            "submit",
            repo("examples/resolution.toml").to_str().expect("path"),
            "--coordinator",
            &format!("http://{}", c.grpc),
            "--width",
            "32",
            "--height",
            "32",
        ])
        .output()
        .expect("submit");
    let job = ok_stdout(&o).trim().to_string();
    (c, job)
}

#[test]
fn the_monitor_refuses_cross_site_writes_and_foreign_hosts() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let (c, job) = queued_job(dir.path(), &["--http-allow-host", "farm.example"]);
    let m = c.http.clone().expect("monitor");
    let post = |path: &str, headers: &str, body: &str| {
        http(
            &m,
            &format!(
                "POST {path} HTTP/1.1\r\nHost: {m}\r\n{headers}Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            ),
        )
    };
    let cancel = format!("/api/jobs/{job}/cancel");
    let priority = format!("/api/jobs/{job}/priority");
    // What a page on another site can send without a preflight.
    let (s, b) = post(
        &cancel,
        "Origin: http://evil.example\r\nContent-Type: text/plain\r\n",
        "{}",
    );
    assert_eq!(s, 403, "{b}");
    assert!(b.contains("another origin"), "{b}");
    let (s, b) = post(
        &priority,
        "Origin: http://evil.example\r\nContent-Type: text/plain\r\n",
        "{\"priority\": 2147483647}",
    );
    assert_eq!(s, 403, "{b}");
    let (s, b) = post(
        &cancel,
        "Sec-Fetch-Site: cross-site\r\nContent-Type: application/json\r\n",
        "{}",
    );
    assert_eq!(s, 403, "{b}");
    let (s, b) = post(
        &priority,
        "Content-Type: text/plain\r\n",
        "{\"priority\": 7}",
    );
    assert_eq!(s, 403, "{b}");
    assert!(b.contains("needs Content-Type: application/json"), "{b}");
    // JSON that does not say where it comes from, without a token.
    let (s, b) = post(
        &priority,
        "Content-Type: application/json\r\n",
        "{\"priority\": 9}",
    );
    assert_eq!(s, 403, "{b}");
    assert!(b.contains(&format!("needs Origin: http://{m}")), "{b}");
    // A rebound name, even for reading.
    let (s, b) = http(
        &m,
        "GET /api/jobs HTTP/1.1\r\nHost: evil.example:7880\r\nConnection: close\r\n\r\n",
    );
    assert_eq!(s, 403, "{b}");
    assert!(
        b.contains("evil.example:7880") && b.contains("is not this monitor's"),
        "{b}"
    );
    assert!(!b.contains(&job), "no job data in the refusal: {b}");

    // The job is untouched.
    let (s, b) = http(
        &m,
        &format!("GET /api/jobs/{job} HTTP/1.1\r\nHost: {m}\r\nConnection: close\r\n\r\n"),
    );
    assert_eq!(s, 200, "{b}");
    let v: serde_json::Value = serde_json::from_str(&b).expect("json");
    assert_eq!(v["state"], "queued", "{b}");
    assert_eq!(v["priority"], 0, "{b}");

    // The page's own requests, and an allowed name, still work.
    let (s, b) = post(
        &priority,
        &format!("Origin: http://{m}\r\nContent-Type: application/json\r\n"),
        "{\"priority\": 5}",
    );
    assert_eq!(s, 200, "{b}");
    let (s, b) = http(
        &m,
        "GET /api/jobs HTTP/1.1\r\nHost: farm.example:7880\r\nConnection: close\r\n\r\n",
    );
    assert_eq!(s, 200, "{b}");
    assert!(b.contains(&job) && b.contains("\"priority\":5"), "{b}");
}

/// An upload of `content` on its own connection that sends its first
/// `chunks` chunks and then (`stall`) waits without ending.
async fn upload(
    url: &str,
    content: std::sync::Arc<Vec<u8>>,
    chunks: usize,
    go: Option<std::sync::Arc<tokio::sync::Barrier>>,
) -> Result<pb::UploadAssetResponse, tonic::Status> {
    let mut c = secure_jobs_client(url, None, None).await;
    let sha256 = sha256_hex(&content);
    let size = content.len() as u64;
    let (tx, rx) = tokio::sync::mpsc::channel(2);
    let sender = tokio::spawn(async move {
        let step = tessera_proto::transport::ASSET_CHUNK_BYTES;
        for (i, part) in content.chunks(step).enumerate() {
            if i == chunks {
                // Stalls: holds the stream open without sending.
                tokio::time::sleep(Duration::from_secs(120)).await;
                return;
            }
            if i == 1
                && let Some(g) = &go
            {
                // Every upload has begun before any goes on.
                g.wait().await;
                tokio::time::sleep(Duration::from_millis(300)).await;
            }
            let chunk = pb::AssetChunk {
                sha256: if i == 0 {
                    sha256.clone()
                } else {
                    String::new()
                },
                size: if i == 0 { size } else { 0 },
                offset: (i * step) as u64,
                data: part.to_vec(),
            };
            if tx.send(chunk).await.is_err() {
                return;
            }
        }
    });
    let r = c
        .upload_asset(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .map(|r| r.into_inner());
    sender.abort();
    r
}

#[test]
fn stalled_uploads_are_closed_after_the_idle_timeout_and_their_memory_returned() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start(
        dir.path(),
        "",
        false,
        &["--upload-idle-timeout", "3", "--max-uploads", "256"],
    );
    let url = format!("http://{}", c.grpc);
    let pid = c.proc.child.id();
    std::thread::sleep(Duration::from_millis(500));
    let before = rss_kib(pid);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let t = Instant::now();
    let (results, during) = runtime.block_on(async {
        let mut tasks = Vec::new();
        for i in 0..200u32 {
            let mut content = vec![(i % 251) as u8; 2 << 20];
            content[..4].copy_from_slice(&i.to_le_bytes());
            tasks.push(tokio::spawn(upload_owned(url.clone(), content, 1)));
        }
        tokio::time::sleep(Duration::from_secs(2)).await;
        let during = rss_kib(pid);
        let mut results = Vec::new();
        for t in tasks {
            results.push(tokio::time::timeout(Duration::from_secs(20), t).await);
        }
        (results, during)
    });
    let closed_after = t.elapsed();
    for r in &results {
        let e = r
            .as_ref()
            .expect("closed within 20 s")
            .as_ref()
            .expect("task")
            .as_ref()
            .expect_err("a stalled upload fails");
        assert_eq!(e.code(), tonic::Code::DeadlineExceeded, "{e:?}");
        assert!(
            e.message()
                .contains("no chunk for 3 s (--upload-idle-timeout)"),
            "{e:?}"
        );
    }
    drop(runtime);
    std::thread::sleep(Duration::from_secs(3));
    let after = rss_kib(pid);
    eprintln!(
        "RSS: {} MB at start, {} MB with 200 stalled uploads, {} MB after (all closed after {:.1} s)",
        before / 1024,
        during / 1024,
        after / 1024,
        closed_after.as_secs_f64()
    );
    assert!(closed_after < Duration::from_secs(10), "{closed_after:?}");
    assert!(
        after < before + 40 * 1024,
        "RSS {after} KiB after the uploads, {before} KiB before"
    );
    let tmp = std::fs::read_dir(dir.path().join("data/assets/tmp"))
        .expect("tmp")
        .count();
    assert_eq!(tmp, 0, "no temporary file is left");
}

#[test]
fn uploads_at_once_are_capped_per_connection_and_in_all() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start(
        dir.path(),
        "",
        false,
        &["--max-uploads", "3", "--upload-idle-timeout", "5"],
    );
    let url = format!("http://{}", c.grpc);
    rt().block_on(async {
        let stalled: Vec<_> = (0..3u8)
            .map(|i| tokio::spawn(upload_owned(url.clone(), vec![i; 2 << 20], 1)))
            .collect();
        tokio::time::sleep(Duration::from_millis(800)).await;
        let e = upload(&url, vec![9u8; 10].into(), 1, None)
            .await
            .expect_err("a fourth upload");
        assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e:?}");
        assert!(
            e.message()
                .contains("receiving 3 uploads already, its limit (--max-uploads)"),
            "{e:?}"
        );
        for s in stalled {
            s.abort();
        }
    });
}

async fn upload_owned(
    url: String,
    content: Vec<u8>,
    chunks: usize,
) -> Result<pb::UploadAssetResponse, tonic::Status> {
    upload(&url, content.into(), chunks, None).await
}

#[test]
fn concurrent_uploads_never_pass_the_store_limit() {
    let _g = serial();
    let dir = tempfile::tempdir().expect("tempdir");
    let c = start(dir.path(), "", false, &["--max-store-bytes", "20000000"]);
    let url = format!("http://{}", c.grpc);
    let results = rt().block_on(async {
        let go = std::sync::Arc::new(tokio::sync::Barrier::new(6));
        let tasks: Vec<_> = (0..6u8)
            .map(|i| {
                let (url, go) = (url.clone(), go.clone());
                tokio::spawn(async move {
                    upload(&url, vec![i; 7_000_000].into(), usize::MAX, Some(go)).await
                })
            })
            .collect();
        let mut out = Vec::new();
        for t in tasks {
            out.push(
                tokio::time::timeout(Duration::from_secs(60), t)
                    .await
                    .expect("upload ends")
                    .expect("task"),
            );
        }
        out
    });
    let stored = results.iter().filter(|r| r.is_ok()).count();
    for e in results.iter().filter_map(|r| r.as_ref().err()) {
        assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e:?}");
        assert!(
            e.message().contains(
                "storing 7000000 more bytes would take the asset store over its limit of 20000000 bytes (--max-store-bytes;"
            ),
            "{e:?}"
        );
    }
    let stats = rt().block_on(async {
        secure_jobs_client(&url, None, None)
            .await
            .get_farm_stats(pb::GetFarmStatsRequest {})
            .await
            .expect("stats")
            .into_inner()
    });
    eprintln!(
        "6 concurrent 7 MB uploads against 20 MB: {stored} stored, {} bytes held",
        stats.asset_bytes_stored
    );
    assert_eq!(stored, 2, "{results:?}");
    assert!(stats.asset_bytes_stored <= 20_000_000, "{stats:?}");
}

#[test]
fn weak_or_shared_tokens_are_refused_at_start() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run = |client: &str, worker: &str| {
        Command::new(TESSERA)
            .args(["coordinator", "--listen", "127.0.0.1:0", "--data"])
            .arg(dir.path().join("data"))
            .env("TESSERA_CLIENT_TOKEN", client)
            .env("TESSERA_WORKER_TOKEN", worker)
            .output()
            .expect("coordinator")
    };
    let strong = "0123456789abcdef0123456789abcdef";
    let other = "Zm9vYmFyYmF6cXV4cXV1eGNvcmdl";
    for (client, worker, want) in [
        (
            "x",
            other,
            "the client token (--client-token-file or TESSERA_CLIENT_TOKEN) is too easy to guess: 1 characters",
        ),
        (
            strong,
            "0123456789abcdef0123456789abcde",
            "the worker token (--worker-token-file or TESSERA_WORKER_TOKEN) is too easy to guess: 31 characters (124 bits",
        ),
        (
            strong,
            "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa",
            "1 different characters",
        ),
        (
            strong,
            strong,
            "the client token and the worker token are the same",
        ),
    ] {
        let o = run(client, worker);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{client} / {worker}: {err}");
        assert!(err.contains(want), "expected {want:?} in {err}");
    }
}

#[test]
fn submit_refuses_a_model_outside_the_folder_before_reading_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = dir.path().join("scene.toml");
    std::fs::write(
        &scene,
        "[camera]\nposition = [0, 1, 4]\nlook_at = [0, 1, 0]\n[materials.m]\ndiffuse = [0.8, 0.8, 0.8]\n\
         [[lights]]\nposition = [0, 1.8, 0]\n[[objects]]\ntype = \"mesh\"\npath = \"/etc/passwd\"\nmaterial = \"m\"\n",
    )
    .expect("scene");
    // No coordinator: the refusal comes before any connection.
    let o = Command::new(TESSERA)
        .args([
            "submit",
            scene.to_str().expect("path"),
            "--coordinator",
            "http://127.0.0.1:1",
        ])
        .output()
        .expect("submit");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("objects[0].path: \"/etc/passwd\" is outside the scene's folder"),
        "{err}"
    );
    assert!(!err.contains("unknown model format"), "{err}");
}
