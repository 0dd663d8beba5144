//! modbus-harness: a conformance and fuzz test harness for Modbus drive implementations.
/// Benchmark drivers for bench/run.sh and harness/benches/ (BENCHMARKS.md); not a stable API.
#[doc(hidden)]
pub mod bench;
pub mod corpus;
pub mod frame;
#[cfg(feature = "fuzzing")]
pub mod fuzzing;
// `gen` is a reserved keyword in edition 2024: the generators live in gen/ under this name.
#[path = "gen/mod.rs"]
pub mod generate;
pub mod golden;
pub mod profile;
pub mod report;
pub mod run;
pub mod server;
pub mod sim;
pub mod target;
