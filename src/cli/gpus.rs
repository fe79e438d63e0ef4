//! `tessera gpus`: the adapters `--backend gpu --adapter NAME|INDEX` can pick.

use super::outln;
use std::process::ExitCode;

use anyhow::Result;

pub fn run() -> Result<ExitCode> {
    let adapters = tracer_core::render::gpu::list_adapters();
    if adapters.is_empty() {
        eprintln!(
            "no GPU adapters found (on Linux, install mesa-vulkan-drivers for lavapipe, or a GPU driver with Vulkan)"
        );
        return Ok(ExitCode::FAILURE);
    }
    outln!(
        "{:<5} {:<40} {:<14} {:<8} driver",
        "index",
        "name",
        "type",
        "backend"
    );
    for a in adapters {
        outln!(
            "{:<5} {:<40} {:<14} {:<8} {} {}",
            a.index,
            a.name,
            a.device_type,
            a.backend,
            a.driver,
            a.driver_info
        );
    }
    Ok(ExitCode::SUCCESS)
}
