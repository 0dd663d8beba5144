//! The engine's tests: the fault matrix, generated cases, campaigns, transports, reports, snapshots,
//! and the replay of the committed fuzz corpus.

extern crate modbus_harness_engine as engine;

mod fault_matrix;
mod fuzz_campaign;
mod fuzz_corpus;
mod generated_cases;
mod report_files;
mod run_transports;
mod station_streams;
