//! The `modbus-harness` command line.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod commands;
mod exit;

/// Conformance and fuzz test harness for Modbus drive implementations.
#[derive(Parser)]
#[command(name = "modbus-harness", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the conformance catalog (golden frames, spec cases, profile cases) against a target.
    Run(Box<commands::run::RunArgs>),
    /// Discover what a target answers, with read requests only, beside a profile or as a draft profile
    /// (--write-profile).
    Probe(commands::probe::ProbeArgs),
    /// A live fuzz campaign: generated and mutated requests, liveness probes, reproducers for findings.
    Fuzz(Box<commands::fuzz::FuzzArgs>),
    /// Decode one frame given as hex and print it field by field (or the exact error).
    Decode(commands::decode::DecodeArgs),
    /// Check every golden frame from the manuals: decode, expectations, errata.
    Golden {
        /// Corpus directory (default: the corpus built into the binary).
        #[arg(long)]
        corpus: Option<PathBuf>,
        /// Print every frame, not only the errata and failures.
        #[arg(short, long)]
        verbose: bool,
        /// Print the errata index as Markdown (corpus/golden/README.md is this output).
        #[arg(long)]
        markdown: bool,
    },
    /// Put a drive back as a run's state journal found it (after a run that was killed), and verify.
    Restore(commands::restore::RestoreArgs),
    /// Serve a reference drive over Modbus/TCP, RTU over TCP and/or a serial line, until Ctrl-C or SIGTERM.
    Simulate(commands::simulate::SimulateArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Run(args) => commands::run::run(&args),
        Command::Probe(args) => commands::probe::run(&args),
        Command::Fuzz(args) => commands::fuzz::run(&args),
        Command::Decode(args) => commands::decode::run(&args),
        Command::Golden {
            corpus,
            verbose,
            markdown,
        } => {
            if markdown {
                commands::golden::markdown(corpus.as_deref())
            } else {
                commands::golden::run(corpus.as_deref(), verbose)
            }
        }
        Command::Restore(args) => commands::restore::run(&args),
        Command::Simulate(args) => commands::simulate::run(args),
    }
}
