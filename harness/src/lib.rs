//! modbus-harness: a conformance and fuzz test harness for Modbus drive implementations.
/// Benchmark drivers for bench/run.sh and harness/benches/ (BENCHMARKS.md); not a stable API.
#[doc(hidden)]
pub mod corpus;
pub mod frame;
pub mod golden;
pub mod profile;
pub mod report;
pub mod run;
pub mod server;
pub mod sim;
pub mod target;
