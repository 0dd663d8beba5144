//! libFuzzer entry point of `modbus_harness_fuzz::rtu_framer` (the input format is documented in src/rtu_framer.rs).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| modbus_harness_fuzz::rtu_framer(data));
