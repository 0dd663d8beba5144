//! The drives' tests: golden frames and errata, the reference drive models, the wire-level station.

extern crate modbus_harness_drives as drives;

mod clone;
mod generic;
mod golden;
mod golden_readme;
mod mdrive;
mod sd2x;
mod support;

/// Every table of tests/data/exchanges.toml is run by the test of its name.
#[test]
fn every_exchange_table_is_run() {
    assert_eq!(
        support::exchange_table_names(),
        [
            "quantities_values_and_functions",         // generic.rs
            "outside_the_map_gives_02",                // generic.rs
            "reserved_and_unmapped_addresses_give_02", // mdrive.rs
        ]
    );
}
