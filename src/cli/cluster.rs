//! `tessera cluster`: a coordinator and N workers as child processes of one
//! terminal, for trying the farm out.

use std::io::{BufRead as _, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, ExitCode, Stdio};

use anyhow::{Context, Result, bail};
use clap::Args;

use tracer_core::render::Backend;

#[derive(Args, Debug)]
pub struct ClusterArgs {
    /// Number of local worker processes, at least 1
    #[arg(long, allow_negative_numbers = true, default_value_t = 2, value_parser = workers_parser)]
    pub workers: usize,
    /// Where the workers trace
    #[arg(long, value_parser = super::worker::backend_parser(), default_value_t = Backend::Cpu)]
    pub backend: Backend,
    /// CPU threads per worker, 0..=4096; 0 means the default [default: all cores / workers]
    #[arg(long, allow_negative_numbers = true, value_parser = super::render::threads_parser())]
    pub threads: Option<usize>,
    /// Coordinator address
    #[arg(long, default_value = "127.0.0.1:7878")]
    pub listen: String,
    /// Coordinator state directory
    #[arg(long, default_value = "tessera-data")]
    pub data: PathBuf,
    /// Serve the web monitor on this address too (e.g. 127.0.0.1:7880)
    #[arg(long, value_name = "ADDR")]
    pub http: Option<String>,
}

/// `--workers`: a count of at least 1, said in those words (clap's range
/// check printed `0 is not in 1..9223372036854775807`).
fn workers_parser(s: &str) -> Result<usize, String> {
    match s.parse::<i64>() {
        Ok(n) if n >= 1 => usize::try_from(n).map_err(|e| e.to_string()),
        Ok(_) => Err("a cluster needs at least 1 worker".to_string()),
        Err(e) => Err(format!("{e} (a number of workers, at least 1)")),
    }
}

struct Children(Vec<Child>);

impl Drop for Children {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

pub fn run(args: ClusterArgs) -> Result<ExitCode> {
    let exe = std::env::current_exe().context("cannot find the tessera executable")?;
    // The cluster's own workers share a fresh worker token, so no other
    // process on this machine can register and receive its jobs' scenes.
    let worker_token = super::farm_common::new_token()?;
    let mut coordinator = child_command(&exe)
        .env(super::farm_common::WORKER_TOKEN_ENV, &worker_token)
        .args(["coordinator", "--listen", &args.listen, "--data"])
        .arg(&args.data)
        .args(args.http.iter().flat_map(|a| ["--http", a.as_str()]))
        .stdout(Stdio::piped())
        .spawn()
        .context("cannot start the coordinator")?;
    let stdout = coordinator.stdout.take().context("coordinator stdout")?;
    let mut children = Children(vec![coordinator]);
    let mut stdout = BufReader::new(stdout);
    let mut line = String::new();
    stdout
        .read_line(&mut line)
        .context("reading the coordinator's address")?;
    let Some(addr) = line.trim().strip_prefix("listening on ") else {
        bail!("the coordinator did not start (see its messages above)");
    };
    let url = format!("http://{addr}");
    let mut monitor = String::new();
    if args.http.is_some() {
        stdout
            .read_line(&mut monitor)
            .context("reading the monitor's address")?;
    }
    let monitor = monitor
        .trim()
        .strip_prefix("monitor on ")
        .map(str::to_string);
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let threads = args
        .threads
        .filter(|&n| n > 0)
        .unwrap_or((cores / args.workers).max(1));
    for i in 0..args.workers {
        let child = child_command(&exe)
            .env(super::farm_common::WORKER_TOKEN_ENV, &worker_token)
            .args([
                "worker",
                "--coordinator",
                &url,
                "--backend",
                args.backend.name(),
                "--threads",
                &threads.to_string(),
                "--name",
                &format!("local-{i}"),
            ])
            .spawn()
            .with_context(|| format!("cannot start worker {i}"))?;
        children.0.push(child);
    }
    eprintln!(
        "cluster: coordinator at {url} with {} worker(s) of {threads} thread(s); Ctrl-C stops everything",
        args.workers
    );
    eprintln!("try:     TESSERA_COORDINATOR={url} tessera submit examples/resolution.toml --wait");
    if let Some(m) = &monitor {
        eprintln!("monitor: {m}/");
    }
    // The children run in a process group of their own, so Ctrl-C on the
    // terminal reaches only this process, which stops them in order: the
    // workers first (each finishes its unit, sends its results and hands
    // its leases back while the coordinator still listens), then the
    // coordinator. Stopped all at once, draining workers found the
    // coordinator gone and warned for seconds.
    let rt = super::farm_common::runtime()?;
    let stopped = rt.block_on(async {
        tokio::select! {
            _ = super::coordinator::shutdown_signal() => true,
            _ = wait_exit(&mut children.0[0]) => false,
        }
    });
    let mut ok = true;
    if stopped {
        eprintln!("cluster: stopping the workers (each finishes its unit), then the coordinator");
        let (coordinator, workers) = children.0.split_at_mut(1);
        ok &= stop(workers, WORKER_GRACE);
        ok &= stop(coordinator, COORDINATOR_GRACE);
    } else {
        ok = false;
        stop(&mut children.0[1..], std::time::Duration::ZERO);
    }
    children.0.clear();
    Ok(if ok || stopped {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

/// How long stopped workers may take to finish their units before they
/// are killed (their leases then expire on the coordinator, nothing lost).
const WORKER_GRACE: std::time::Duration = std::time::Duration::from_secs(20);
/// How long the coordinator may take to store what it holds and exit.
const COORDINATOR_GRACE: std::time::Duration = std::time::Duration::from_secs(10);

/// A child of the cluster: in a process group of its own (a terminal's
/// Ctrl-C reaches the cluster only, which stops the children in order)
/// and, on Linux, sent SIGTERM if the cluster dies without stopping it.
fn child_command(exe: &std::path::Path) -> Command {
    let mut cmd = Command::new(exe);
    #[cfg(unix)]
    {
        use std::os::unix::process::CommandExt as _;
        cmd.process_group(0);
        #[cfg(target_os = "linux")]
        // SAFETY: prctl is async-signal-safe and touches only this child.
        unsafe {
            cmd.pre_exec(|| {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
    }
    cmd
}

/// Sends SIGTERM to every child of `children`, waits up to `grace` for
/// them all, kills those still running; true when all exited successfully.
fn stop(children: &mut [Child], grace: std::time::Duration) -> bool {
    for c in children.iter() {
        #[cfg(unix)]
        // SAFETY: kill only reads its integer arguments; the child is not
        // reaped yet, so its pid is still its own.
        unsafe {
            libc::kill(c.id() as libc::pid_t, libc::SIGTERM);
        }
    }
    let deadline = std::time::Instant::now() + grace;
    let mut ok = true;
    for c in children.iter_mut() {
        loop {
            match c.try_wait() {
                Ok(Some(s)) => {
                    ok &= s.success();
                    break;
                }
                Ok(None) if std::time::Instant::now() < deadline => {
                    std::thread::sleep(std::time::Duration::from_millis(50))
                }
                _ => {
                    let _ = c.kill();
                    let _ = c.wait();
                    ok = false;
                    break;
                }
            }
        }
    }
    ok
}

async fn wait_exit(c: &mut Child) {
    while let Ok(None) = c.try_wait() {
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
}
