//! `tessera gpus`: the adapters `--backend gpu --adapter NAME|INDEX` can pick.

use super::outln;
use std::process::ExitCode;

use anyhow::Result;

pub fn run(format: super::output::Format) -> Result<ExitCode> {
    let adapters = tracer_core::render::gpu::list_adapters();
    if format.json {
        super::output::print_json(
            &adapters
                .iter()
                .map(|a| {
                    serde_json::json!({
                        "index": a.index,
                        "name": a.name,
                        "type": a.device_type.to_string(),
                        "backend": a.backend.to_string(),
                        "driver": a.driver,
                        "driver_info": a.driver_info,
                    })
                })
                .collect(),
        );
        return Ok(if adapters.is_empty() {
            ExitCode::FAILURE
        } else {
            ExitCode::SUCCESS
        });
    }
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
