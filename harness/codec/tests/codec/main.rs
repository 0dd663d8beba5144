//! The codec's tests: hand-written vectors (valid and malformed) and properties over arbitrary bytes.

extern crate modbus_harness_codec as codec;

mod props;
mod vectors;
