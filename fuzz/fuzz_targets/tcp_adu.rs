//! libFuzzer entry point of `modbus_harness_fuzz::tcp_adu` (the input format is documented in src/tcp_adu.rs).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| modbus_harness_fuzz::tcp_adu(data));
