//! modbus-harness: a conformance and fuzz test harness for Modbus drive implementations.
pub mod frame;
