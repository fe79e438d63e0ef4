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
    /// GPU adapter for --backend gpu: index or part of the name as `tessera
    /// gpus` lists it, or `all`: one worker per GPU in this process, each
    /// named NAME-gpuINDEX and labelled with its GPU (software adapters
    /// such as lavapipe count only where there is no other) [default: the
    /// best one]
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
    /// worker reports backend, cores, host, memory_gb (the host's) and, on
    /// a GPU, gpu (the adapter's name) and gpu_memory_gb (where nvidia-smi
    /// tells it; give it here elsewhere). A given host, memory_gb or
    /// gpu_memory_gb wins over the automatic one; backend and cores cannot
    /// be given
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

/// `--adapter all`.
const ALL_ADAPTERS: &str = "all";

/// `--adapter all`: one worker per GPU adapter, each with its own name
/// (`NAME-gpuINDEX`), cache folder (`CACHE/gpuINDEX`) and adapter (so its
/// `gpu` label). Software adapters (lavapipe) are left out where a
/// hardware one exists: they would take work at a fraction of its speed.
fn every_gpu(config: WorkerConfig) -> Result<Vec<Worker>> {
    #[cfg(feature = "gpu")]
    {
        let all = tracer_core::render::gpu::list_adapters();
        let hardware: Vec<_> = all.iter().filter(|a| a.device_type != "Cpu").collect();
        let chosen = if hardware.is_empty() {
            all.iter().collect()
        } else {
            hardware
        };
        if chosen.is_empty() {
            anyhow::bail!("--adapter all: no GPU adapter found (`tessera gpus` lists them)");
        }
        chosen
            .into_iter()
            .map(|a| {
                tracing::info!(adapter = a.index, name = %a.name, "a worker for this GPU");
                Worker::new(WorkerConfig {
                    name: format!("{}-gpu{}", config.name, a.index),
                    adapter: Some(a.index.to_string()),
                    cache_dir: config.cache_dir.join(format!("gpu{}", a.index)),
                    ..config.clone()
                })
                .map_err(Into::into)
            })
            .collect()
    }
    #[cfg(not(feature = "gpu"))]
    Err(tracer_core::render::RendererError::GpuNotBuilt.into())
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
    let cache_dir = args.cache.clone().unwrap_or_else(default_cache);
    let config = WorkerConfig {
        coordinator: args.coordinator.url.clone(),
        name,
        threads: args.threads,
        adapter: args.adapter.clone(),
        ca_pem: args.coordinator.ca_pem()?,
        token: args.coordinator.token(WORKER_TOKEN_ENV)?,
        cache_dir,
        cache_bytes: args.cache_size,
        backend: args.backend,
        labels: args.labels.iter().cloned().collect(),
    };
    let workers = if args.adapter.as_deref() == Some(ALL_ADAPTERS) {
        every_gpu(config)?
    } else {
        vec![Worker::new(config)?]
    };
    if args.http.is_some() && workers.len() > 1 {
        // One registry a worker: several on one address would need a label
        // per worker in every metric.
        anyhow::bail!(
            "--http serves one worker's /metrics; with --adapter all ({} GPUs) run a worker process per GPU (--adapter N) with its own --http",
            workers.len()
        );
    }
    runtime()?.block_on(async move {
        if let (Some(addr), Some(worker)) = (args.http, workers.first()) {
            worker.serve_metrics(addr).await?;
        }
        let (drain_tx, drain) = tokio::sync::watch::channel(false);
        let mut running = tokio::task::JoinSet::new();
        for worker in workers {
            running.spawn(worker.run(drain.clone()));
        }
        // Until a signal, or until a worker stops by itself (refused by
        // the coordinator, say): that ends them all.
        tokio::select! {
            r = running.join_next() => {
                r.expect("at least one worker")??;
                running.abort_all();
                return Ok(ExitCode::SUCCESS);
            }
            _ = shutdown_signal() => {}
        }
        tracing::info!("draining: finishing the current unit (signal again to stop now)");
        let _ = drain_tx.send(true);
        tokio::select! {
            r = async {
                while let Some(r) = running.join_next().await {
                    r??;
                }
                anyhow::Ok(())
            } => r?,
            _ = shutdown_signal() => tracing::warn!("stopped without finishing the current unit"),
        }
        Ok(ExitCode::SUCCESS)
    })
}
