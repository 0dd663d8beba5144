//! libFuzzer entry point of `modbus_harness_engine::fuzzing::tcp_adu` (the input format is documented there).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| modbus_harness_engine::fuzzing::tcp_adu(data));
