//! The command line: decode, run (exit codes, reports, safety), generated-run snapshots, profile files and
//! drafts.

mod decode;
mod generated_snapshots;
mod profiles;
mod run;
mod safety;
