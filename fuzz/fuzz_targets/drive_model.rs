//! libFuzzer entry point of `modbus_harness_fuzz::drive_model` (the input format is documented in src/drive_model.rs).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| modbus_harness_fuzz::drive_model(data));
