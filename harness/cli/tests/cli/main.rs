//! The command line: decode, run (exit codes, reports, safety), generated-run snapshots, profile files and
//! drafts.

mod ci_examples;
mod dead_target;
mod decode;
mod echo_line;
mod edges;
mod generated_snapshots;
mod html_browser;
mod junit_schema;
mod leave_as_found;
mod multi_drop;
mod noisy_link;
mod pipeline;
mod profiles;
mod rtu_resync;
mod run;
mod safety;
mod sentinel;
