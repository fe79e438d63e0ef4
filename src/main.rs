//! `tessera`: the one binary. Thin glue over the library crates; each
//! subcommand lives in its own module under `cli/`.

mod bench;
mod cli;

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
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
