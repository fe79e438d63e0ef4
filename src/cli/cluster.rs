//! `tessera cluster`: a coordinator and N workers as child processes of one
//! terminal, for trying the farm out.

use std::io::{BufRead as _, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, ExitCode, Stdio};

use anyhow::{bail, Context, Result};
use clap::Args;

use super::worker::WorkerBackend;

#[derive(Args, Debug)]
pub struct ClusterArgs {
    /// Number of local worker processes
    #[arg(long, default_value_t = 2)]
    pub workers: usize,
    /// Where the workers trace
    #[arg(long, value_enum, default_value_t = WorkerBackend::Cpu)]
    pub backend: WorkerBackend,
    /// CPU threads per worker [default: all cores / workers]
    #[arg(long)]
    pub threads: Option<usize>,
    /// Coordinator address
    #[arg(long, default_value = "127.0.0.1:7878")]
    pub listen: String,
    /// Coordinator state directory
    #[arg(long, default_value = "tessera-data")]
    pub data: PathBuf,
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
    let mut coordinator = Command::new(&exe)
        .args(["coordinator", "--listen", &args.listen, "--data"])
        .arg(&args.data)
        .stdout(Stdio::piped())
        .spawn()
        .context("cannot start the coordinator")?;
    let stdout = coordinator.stdout.take().context("coordinator stdout")?;
    let mut children = Children(vec![coordinator]);
    let mut line = String::new();
    BufReader::new(stdout).read_line(&mut line).context("reading the coordinator's address")?;
    let Some(addr) = line.trim().strip_prefix("listening on ") else {
        bail!("the coordinator did not start (see its messages above)");
    };
    let url = format!("http://{addr}");
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let threads = args.threads.unwrap_or((cores / args.workers).max(1));
    for i in 0..args.workers {
        let backend = match args.backend {
            WorkerBackend::Cpu => "cpu",
            WorkerBackend::Gpu => "gpu",
        };
        let child = Command::new(&exe)
            .args(["worker", "--coordinator", &url, "--backend", backend, "--threads", &threads.to_string(), "--name", &format!("local-{i}")])
            .spawn()
            .with_context(|| format!("cannot start worker {i}"))?;
        children.0.push(child);
    }
    eprintln!("cluster: coordinator at {url} with {} worker(s) of {threads} thread(s); Ctrl-C stops everything", args.workers);
    eprintln!("try:     TESSERA_COORDINATOR={url} tessera submit examples/resolution.toml --wait");
    // Ctrl-C reaches the whole process group; wait for the coordinator to go.
    let status = children.0[0].wait().context("waiting for the coordinator")?;
    for c in children.0.iter_mut().skip(1) {
        let _ = c.wait();
    }
    children.0.clear();
    Ok(if status.success() { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}
