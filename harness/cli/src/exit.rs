//! The one mapping from how a command ended to the process exit code (README, "Exit codes"). Every command
//! returns an [`Exit`]; nothing else in the CLI names a number.

use std::process::ExitCode;

/// How a command ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Exit {
    /// Done, and nothing failed: 0.
    Ok,
    /// A check failed (a FAIL verdict, a drifted snapshot, a fuzz finding, a bad golden frame) or serving
    /// stopped on an error: 1.
    Failed,
    /// The command could not do its job: unusable arguments, profile, target or corpus, or a run cut short
    /// by an interruption: 2.
    Unusable,
    /// The drive was not left as found (a parameter could not be put back and verified): 3.
    NotRestored,
}

impl From<Exit> for ExitCode {
    fn from(e: Exit) -> Self {
        match e {
            Exit::Ok => ExitCode::SUCCESS,
            Exit::Failed => ExitCode::from(1),
            Exit::Unusable => ExitCode::from(2),
            Exit::NotRestored => ExitCode::from(engine::restore::EXIT_NOT_RESTORED),
        }
    }
}

/// Say why the command could not do its job, and exit 2.
pub fn unusable(why: impl std::fmt::Display) -> ExitCode {
    eprintln!("error: {why}");
    Exit::Unusable.into()
}
