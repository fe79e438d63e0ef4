//! `tessera`: the one binary. Thin glue over the library crates; each
//! subcommand lives in its own module under `cli/`.

mod bench;
mod cli;

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    // Freed big arrays go back to the system at once. glibc raises its
    // mmap threshold (up to 32 MB) after each big free, so the arrays of a
    // mesh of a million triangles (a few MB each) then come from the heap,
    // whose freed pages stay in the process: the 1 M-triangle heightfield
    // peaked at 118 MB instead of 87 (docs/meshes.md, "Big scenes").
    // Fixed at 1 MB, every array from 1 MB up is mapped and unmapped.
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets an allocator parameter; called before any
    // thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 20);
    }
    let args = cli::Cli::parse();
    #[cfg(feature = "gpu")]
    if args.command.may_use_gpu() {
        cli::quiet_display_probe();
    }
    match cli::run(args) {
        Ok(code) => code,
        Err(e) => {
            // `{:#}` prints the whole context chain on one line.
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
