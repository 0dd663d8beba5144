//! The modbus-harness catalog against the toy firmware, in process: `cargo test` in the firmware's repo.

use modbus_harness_engine::api::{Device, Session, SessionBuilder};
use toy_firmware::{Bug, Toy};

/// The seam: the harness frames Modbus/TCP and hands the firmware each request PDU.
struct ToyDevice(Toy);

impl Device for ToyDevice {
    fn handle(&mut self, _unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
        self.0.handle_pdu(pdu)
    }
}

/// The drive's profile, beside this crate's Cargo.toml.
const PROFILE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/toy.toml");

/// A session of the drive's profile against the toy firmware, built with `bug` when there is one.
fn toy_session(bug: Option<Bug>) -> SessionBuilder {
    let toy = Toy {
        bug,
        ..Toy::default()
    };
    Session::builder().profile(PROFILE).device(ToyDevice(toy))
}

#[test]
fn toy_firmware_passes_the_catalog() {
    let results = toy_session(None).run();
    results.assert_passes();
    println!("{results}");
}

#[test]
fn zero_quantity_read_is_caught() {
    let results = toy_session(Some(Bug::ReadsZeroRegisters))
        .cases("spec/*")
        .run();
    results.assert_fails("spec/app-6/quantity/fc-0x03/zero");
}

#[test]
fn wrong_exception_for_a_bad_address_is_caught() {
    let results = toy_session(Some(Bug::WrongExceptionForBadAddress)).run();
    assert!(!results.passed(), "the bug went unnoticed:\n{results}");
    results.assert_fails("spec/app-6/address-beyond-map/fc-0x03");
}
