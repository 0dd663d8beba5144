//! The `modbus-harness` command line.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod cli;

/// Conformance and fuzz test harness for Modbus drive implementations.
#[derive(Parser)]
#[command(name = "modbus-harness", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Decode one frame given as hex and print it field by field (or the exact error).
    Decode(cli::decode::DecodeArgs),
    /// Check every golden frame from the manuals: decode, expectations, errata.
    Golden {
        /// Corpus directory (default: the corpus built into the binary).
        #[arg(long)]
        corpus: Option<PathBuf>,
        /// Print every frame, not only the errata and failures.
        #[arg(short, long)]
        verbose: bool,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Decode(args) => cli::decode::run(&args),
        Command::Golden { corpus, verbose } => cli::golden::run(corpus.as_deref(), verbose),
    }
}
