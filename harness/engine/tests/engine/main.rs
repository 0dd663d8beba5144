//! The engine's tests: the fault matrix, generated cases, campaigns, transports, reports and snapshots
//! (the replay of the committed fuzz corpus is fuzz/tests/fuzz_corpus.rs).

extern crate modbus_harness_engine as engine;

mod api;
mod disputed;
mod fault_matrix;
mod freedom_space;
mod fuzz_campaign;
mod gateway;
mod generated_cases;
mod probe;
mod public_fc;
mod report_files;
mod requirements_cited;
mod run_transports;
mod safety;
mod shuffle;
mod station_streams;
mod unused_fields;
