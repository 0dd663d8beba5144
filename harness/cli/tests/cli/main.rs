//! The command line: decode, run (exit codes, reports, safety), generated-run snapshots, profile files and
//! drafts.

mod dead_target;
mod decode;
mod generated_snapshots;
mod leave_as_found;
mod profiles;
mod run;
mod safety;
