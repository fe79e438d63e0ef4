//! Command-line interface: one subcommand per module.

#[cfg(feature = "gpu")]
mod gpus;
mod render;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// Tessera: a distributed ray-tracing render farm.
///
/// Render locally with `tessera render SCENE.toml`; scene files are
/// described in docs/scene-format.md.
#[derive(Parser, Debug)]
#[command(name = "tessera", version, about, long_about = None, propagate_version = true)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Render a scene in this process (no coordinator, no workers).
    Render(render::RenderArgs),
    /// List the GPU adapters `--backend gpu --adapter NAME|INDEX` can use.
    #[cfg(feature = "gpu")]
    Gpus,
}

pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Render(args) => render::run(args),
        #[cfg(feature = "gpu")]
        Command::Gpus => gpus::run(),
    }
}
