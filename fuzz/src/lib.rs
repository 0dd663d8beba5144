//! Fuzz targets as library functions: each takes the fuzzer's bytes and panics when an invariant breaks,
//! which is how libFuzzer reports a finding.
//!
//! `fuzz_targets/*.rs` run them under libFuzzer (`cargo fuzz run -s none <target>`);
//! `tests/fuzz_corpus.rs` replays every file of `fuzz/corpus/` through them on stable Rust. Each target
//! documents its input format; [`seeds`] writes inputs in those formats from the golden frames and the
//! case catalog. Every format reads zeros past the end of the input, so every byte string is a valid input.

mod differential;
mod drive_model;
mod input;
mod reference;
mod response_validation;
mod rtu_framer;
mod seeds;
mod tcp_adu;

pub use differential::differential_tokio_modbus;
pub use drive_model::{drive_model, drive_model_with_faults};
pub use reference::DRIVES;
pub use response_validation::response_validation;
pub use rtu_framer::rtu_framer;
pub use seeds::{Seed, seeds};
pub use tcp_adu::tcp_adu;

/// The fuzz targets, by the names of their `fuzz/fuzz_targets/*.rs` and `fuzz/corpus/*` directories.
pub const TARGETS: [&str; 5] = [
    "tcp_adu",
    "rtu_framer",
    "response_validation",
    "drive_model",
    "differential",
];

/// The target function of a target name.
pub fn target(name: &str) -> Option<fn(&[u8])> {
    Some(match name {
        "tcp_adu" => tcp_adu,
        "rtu_framer" => rtu_framer,
        "response_validation" => response_validation,
        "drive_model" => drive_model,
        "differential" => differential_tokio_modbus,
        _ => return None,
    })
}
