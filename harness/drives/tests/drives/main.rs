//! The drives' tests: golden frames and errata, the reference drive models, the wire-level station.

extern crate modbus_harness_drives as drives;

mod generic;
mod golden;
mod golden_readme;
mod mdrive;
mod sd2x;
