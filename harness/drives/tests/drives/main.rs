//! The drives' tests: golden frames and errata, the reference drive models, the wire-level station.

extern crate modbus_harness_drives as drives;

mod choices_taken;
mod clone;
mod full_fc;
mod generic;
mod golden;
mod golden_readme;
mod mdrive;
mod profile_function_data;
mod profiles;
mod requirements;
mod safety_flags;
mod sd2x;
mod support;
mod transport_freedoms;

/// Every table of tests/data/exchanges.toml is run by the test of its name.
#[test]
fn every_exchange_table_is_run() {
    assert_eq!(
        support::exchange_table_names(),
        [
            "quantities_values_and_functions",         // generic.rs
            "outside_the_map_gives_02",                // generic.rs
            "reserved_and_unmapped_addresses_give_02", // mdrive.rs
            "full_fc_read_exception_status",           // full_fc.rs
            "full_fc_mask_write_register",             // full_fc.rs
            "full_fc_read_fifo_queue",                 // full_fc.rs
            "full_fc_file_records",                    // full_fc.rs
            "full_fc_report_server_id",                // full_fc.rs
            "full_fc_diagnostics_over_tcp",            // full_fc.rs
            "full_fc_comm_event_counter_and_log",      // full_fc.rs
        ]
    );
}
