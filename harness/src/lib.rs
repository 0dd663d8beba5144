//! modbus-harness: a conformance and fuzz test harness for Modbus drive implementations.
pub mod corpus;
pub mod frame;
pub mod golden;
pub mod profile;
pub mod report;
pub mod run;
pub mod server;
pub mod sim;
pub mod target;
