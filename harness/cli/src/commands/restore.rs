//! `modbus-harness restore`: put a drive back as a run's state journal found it (after a killed run).

use crate::exit::Exit;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use clap::Args;
use drives::corpus::Corpus;
use engine::runner::Timing;
use engine::session;
use engine::targets::TargetUrl;

/// Arguments of `restore`.
#[derive(Args, Debug)]
#[command(after_help = "\
Exit codes:
  0  every parameter of the journal reads as before the run's first write
  2  the journal or the target could not be used
  3  a parameter could not be restored (listed, with its value before and after)")]
pub struct RestoreArgs {
    /// The state journal a run wrote (`run --journal FILE`, or journal.json in its report directory).
    #[arg(long, value_name = "FILE")]
    journal: PathBuf,
    /// The drive to restore (default: the journal's target).
    #[arg(long, value_name = "URL")]
    target: Option<String>,
    /// Corpus directory (default: the corpus built into the binary).
    #[arg(long, value_name = "DIR")]
    corpus: Option<PathBuf>,
    /// Per-answer timeout in milliseconds.
    #[arg(long, default_value_t = 1000, value_name = "MS")]
    timeout: u64,
}

/// Run `restore`: exit 0 when every parameter reads as before, 3 when one does not, 2 on unusable input.
pub fn run(args: &RestoreArgs) -> ExitCode {
    let target = match args.target.as_deref().map(TargetUrl::parse).transpose() {
        Ok(t) => t,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(Exit::Unusable);
        }
    };
    let timing = Timing {
        timeout: Duration::from_millis(args.timeout.max(1)),
        ..Timing::default()
    };
    let mut log = std::io::stderr();
    match session::restore_journal(
        &args.journal,
        target,
        Corpus::from_option(args.corpus.as_deref()),
        timing,
        Duration::from_secs(3),
        &mut log,
    ) {
        Ok(account) => {
            for line in account.lines() {
                println!("{line}");
            }
            if account.clean() {
                println!(
                    "RESULT: RESTORED ({} parameter(s) read as before)",
                    account.kept
                );
                ExitCode::from(Exit::Ok)
            } else {
                println!(
                    "RESULT: NOT RESTORED ({} of {} parameter(s))",
                    account.unrestored.len(),
                    account.kept
                );
                ExitCode::from(Exit::NotRestored)
            }
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(Exit::Unusable)
        }
    }
}
