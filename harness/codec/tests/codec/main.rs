//! The codec's tests: vectors (valid and malformed) kept as data in tests/vectors/, the framer and encoder
//! behaviour they do not cover, and properties over arbitrary bytes.

extern crate modbus_harness_codec as codec;

mod data;
mod props;
mod vectors;
