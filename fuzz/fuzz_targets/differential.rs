//! libFuzzer entry point of `modbus_harness_fuzz::differential_tokio_modbus` (the input format is documented in src/differential.rs).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| modbus_harness_fuzz::differential_tokio_modbus(data));
