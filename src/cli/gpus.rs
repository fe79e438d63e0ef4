//! `tessera gpus`: the adapters `--backend gpu --adapter NAME|INDEX` can pick.

use super::outln;
use std::process::ExitCode;

use anyhow::Result;

/// Points `XDG_RUNTIME_DIR` at a private empty folder when it is unset (or
/// not absolute), before any GPU instance exists, so listing GPUs stays
/// quiet on headless machines.
///
/// Why: Mesa's Vulkan device-select layer (installed with every Mesa
/// driver, lavapipe included) asks the Wayland compositor which GPU drives
/// the display each time an instance that enabled the Wayland surface
/// extension lists its devices, and wgpu enables every surface extension
/// the loader offers. With no `XDG_RUNTIME_DIR`, libwayland then prints
/// "error: XDG_RUNTIME_DIR is invalid or not set in the environment." for
/// each listing, which reads like an error of Tessera's. Tessera never
/// opens a window; without the variable there is no session to ask anyway.
/// In an empty folder libwayland finds no compositor and says nothing, and
/// the layer orders the devices as it would have (no display to ask either
/// way).
///
/// Must run before any other thread exists (it sets an environment
/// variable); `main` calls it first thing.
pub fn quiet_display_probe() {
    let key = "XDG_RUNTIME_DIR";
    if std::env::var_os(key).is_some_and(|v| std::path::Path::new(&v).is_absolute()) {
        return;
    }
    // SAFETY: getuid has no preconditions and cannot fail.
    let uid = unsafe { libc::getuid() };
    let dir = std::env::temp_dir().join(format!("tessera-{uid}-runtime"));
    if !private_dir(&dir, uid) {
        // Someone else's folder, or none could be made: keep the noise
        // rather than hand libwayland a folder another user controls.
        return;
    }
    // SAFETY: called from `main` before any thread is started, so no other
    // thread can read or write the environment meanwhile.
    unsafe { std::env::set_var(key, &dir) };
}

/// Whether `dir` is (or now is) a directory of `uid`'s that only it can use.
fn private_dir(dir: &std::path::Path, uid: u32) -> bool {
    use std::os::unix::fs::{DirBuilderExt as _, MetadataExt as _};
    let _ = std::fs::DirBuilder::new().mode(0o700).create(dir);
    // symlink_metadata: a link planted in /tmp is not followed.
    std::fs::symlink_metadata(dir)
        .is_ok_and(|m| m.is_dir() && m.uid() == uid && m.mode() & 0o077 == 0)
}

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
