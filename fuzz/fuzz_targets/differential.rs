//! libFuzzer entry point of `modbus_harness_engine::fuzzing::differential_tokio_modbus` (the input format is documented there).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| modbus_harness_engine::fuzzing::differential_tokio_modbus(data));
