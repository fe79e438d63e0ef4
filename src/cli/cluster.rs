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
    #[arg(long, allow_negative_numbers = true, default_value_t = 2, value_parser = clap::builder::RangedI64ValueParser::<usize>::new().range(1..))]
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
    if args.workers == 0 {
        bail!("--workers must be at least 1");
    }
    let exe = std::env::current_exe().context("cannot find the tessera executable")?;
    // The cluster's own workers share a fresh worker token, so no other
    // process on this machine can register and receive its jobs' scenes.
    let worker_token = super::farm_common::new_token()?;
    let mut coordinator = Command::new(&exe)
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
        let child = Command::new(&exe)
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
    // Ctrl-C on a terminal reaches every process of the group: the workers
    // drain and the coordinator stops by themselves. A signal sent to this
    // process alone gives them a few seconds, then they are killed (the
    // coordinator's state is safe either way).
    let rt = super::farm_common::runtime()?;
    let stopped = rt.block_on(async {
        tokio::select! {
            _ = super::coordinator::shutdown_signal() => true,
            _ = wait_exit(&mut children.0[0]) => false,
        }
    });
    let deadline =
        std::time::Instant::now() + std::time::Duration::from_secs(if stopped { 5 } else { 0 });
    let mut ok = true;
    for c in children.0.iter_mut() {
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
                    break;
                }
            }
        }
    }
    children.0.clear();
    Ok(if ok || stopped {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

async fn wait_exit(c: &mut Child) {
    while let Ok(None) = c.try_wait() {
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
}
