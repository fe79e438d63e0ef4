//! `tessera worker`: render work units for a coordinator.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::Args;
use tessera_worker::{Worker, WorkerConfig};
use tracer_core::render::Backend;

use super::coordinator::shutdown_signal;
use super::farm_common::{CoordinatorUrl, LogFormat, WORKER_TOKEN_ENV, init_logging, runtime};

/// `--backend` of `tessera worker` and `tessera cluster`, each value with
/// its help. Both values in every build: a worker built without the `gpu`
/// feature refuses `gpu` when it opens its renderer.
pub fn backend_parser() -> impl clap::builder::TypedValueParser<Value = Backend> {
    use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser as _};
    PossibleValuesParser::new([
        PossibleValue::new(Backend::Cpu.name()).help("CPU threads"),
        PossibleValue::new(Backend::Gpu.name())
            .help("One GPU through wgpu compute shaders (Vulkan/Metal/DX12; f32)"),
    ])
    .map(|s| s.parse::<Backend>().expect("one of the possible values"))
}

#[derive(Args, Debug, Clone)]
pub struct WorkerArgs {
    #[command(flatten)]
    pub coordinator: CoordinatorUrl,
    /// Where to trace
    #[arg(long, value_parser = backend_parser(), default_value_t = Backend::Cpu)]
    pub backend: Backend,
    /// CPU threads for --backend cpu, 0..=4096; 0 means all cores [default: all cores]
    #[arg(long, allow_negative_numbers = true, value_parser = super::render::threads_parser())]
    pub threads: Option<usize>,
    /// GPU adapter for --backend gpu: index or part of the name as `tessera gpus` lists it [default: the best one]
    #[arg(long)]
    pub adapter: Option<String>,
    /// Name shown by `tessera workers` [default: host name and process id]
    #[arg(long)]
    pub name: Option<String>,
    /// Log format
    #[arg(long, value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,
    /// Where job files (scenes, models) are cached by hash, across jobs and
    /// restarts [default: $XDG_CACHE_HOME/tessera/assets, or ~/.cache/tessera/assets]
    #[arg(long, value_name = "DIR", env = "TESSERA_CACHE")]
    pub cache: Option<PathBuf>,
    /// Most bytes the cache keeps (least recently used files go first)
    #[arg(long, value_name = "BYTES", default_value_t = 10 << 30)]
    pub cache_size: u64,
    /// Niceness to add to the worker's own, 0..=19, as `nice -n N` does
    /// (the sum is capped at 19; a worker started under `nice -n 10` with
    /// `--nice 7` runs at 17): a CPU worker beside a GPU worker or the
    /// coordinator on one host, niced, leaves them the cores they need to
    /// feed the GPU and take in results
    #[arg(long, value_name = "N", default_value_t = 0,
          value_parser = clap::value_parser!(i32).range(0..=19))]
    pub nice: i32,
    /// A label jobs' requirements (`tessera submit --require`) are matched
    /// against, repeatable: `--label pool=night`. Beside these, every
    /// worker reports backend, cores, host and, on a GPU, gpu (the
    /// adapter's name) and gpu_memory_gb (where nvidia-smi tells it; give
    /// it here elsewhere). A given host or gpu_memory_gb wins over the
    /// automatic one; backend and cores cannot be given
    #[arg(long = "label", value_name = "KEY=VALUE", value_parser = label_parser)]
    pub labels: Vec<(String, String)>,
    /// Serve this worker's Prometheus metrics (`GET /metrics`, no token)
    /// on ADDR, e.g. 127.0.0.1:9100 (port 0: any free one, logged)
    #[arg(long, value_name = "ADDR")]
    pub http: Option<std::net::SocketAddr>,
}

/// `--label`: KEY=VALUE, with a key the worker does not set from itself.
fn label_parser(s: &str) -> Result<(String, String), String> {
    let (k, v) = tessera_proto::placement::parse_label(s).map_err(|e| e.to_string())?;
    if k == "backend" || k == "cores" {
        return Err(format!(
            "label {k:?} is set from the worker itself (--backend, --threads); it cannot be given"
        ));
    }
    Ok((k, v))
}

/// The default cache folder: the XDG cache, else ./tessera-cache.
fn default_cache() -> PathBuf {
    let base = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .filter(|p| p.is_absolute())
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")));
    match base {
        Some(b) => b.join("tessera").join("assets"),
        None => PathBuf::from("tessera-cache"),
    }
}

pub fn run(args: WorkerArgs) -> Result<ExitCode> {
    init_logging(args.log_format);
    if args.nice > 0 {
        // Linux's nice is per thread, inherited by threads created later:
        // this runs before the runtime and the render threads exist.
        // Relative, as nice(1): an absolute setpriority would fail (or,
        // as root, raise the priority) when started under `nice -n 10`.
        // nice(3) fails only for a negative increment (EPERM), and -1 is
        // a valid niceness, so its result is not an error to check.
        // SAFETY: nice only reads its integer argument.
        unsafe { libc::nice(args.nice) };
    }
    if args.backend != Backend::Gpu && args.adapter.is_some() {
        anyhow::bail!("--adapter only applies to --backend gpu");
    }
    let name = args.name.clone().unwrap_or_else(|| {
        let host = std::env::var("HOSTNAME")
            .ok()
            .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
            .unwrap_or_default();
        format!("{}-{}", host.trim(), std::process::id())
    });
    let worker = Worker::new(WorkerConfig {
        coordinator: args.coordinator.url.clone(),
        name,
        threads: args.threads,
        adapter: args.adapter.clone(),
        ca_pem: args.coordinator.ca_pem()?,
        token: args.coordinator.token(WORKER_TOKEN_ENV)?,
        cache_dir: args.cache.clone().unwrap_or_else(default_cache),
        cache_bytes: args.cache_size,
        backend: args.backend,
        labels: args.labels.iter().cloned().collect(),
    })?;
    runtime()?.block_on(async move {
        if let Some(addr) = args.http {
            worker.serve_metrics(addr).await?;
        }
        let (drain_tx, drain) = tokio::sync::watch::channel(false);
        let mut run = tokio::spawn(worker.run(drain));
        tokio::select! {
            r = &mut run => {
                r??;
                return Ok(ExitCode::SUCCESS);
            }
            _ = shutdown_signal() => {}
        }
        tracing::info!("draining: finishing the current unit (signal again to stop now)");
        let _ = drain_tx.send(true);
        tokio::select! {
            r = run => r??,
            _ = shutdown_signal() => tracing::warn!("stopped without finishing the current unit"),
        }
        Ok(ExitCode::SUCCESS)
    })
}
