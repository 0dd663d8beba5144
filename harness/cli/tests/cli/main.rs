//! The command line: decode, run (exit codes, reports, safety), generated-run snapshots.

mod decode;
mod generated_snapshots;
mod run;
