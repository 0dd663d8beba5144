//! libFuzzer entry point of `modbus_harness_fuzz::response_validation` (the input format is documented in src/response_validation.rs).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| modbus_harness_fuzz::response_validation(data));
