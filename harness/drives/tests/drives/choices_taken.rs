//! The reference models taking the freedoms' other values (`simulate --choose`): each test fails if the model
//! answers as the reference drive instead.

use std::time::Duration;

use codec::{Mnemonic, Request, Response, tcp};
use drives::corpus::Corpus;
use drives::models::sd2x::{Ds402State, Sd2x};
use drives::{Choices, DriveModel, FaultSet, Station};

use super::support::profile;

fn choices(stem: &str, specs: &[&str]) -> Choices {
    let requirements = Corpus::Embedded.requirements().expect("requirements");
    Choices::parse_all(specs, &requirements, &profile(stem)).expect("choices")
}

/// A station of the corpus profile `stem` taking `specs`.
fn station(stem: &str, specs: &[&str]) -> Station {
    let p = profile(stem);
    let unit = p.device.default_unit;
    let c = choices(stem, specs);
    Station::new(
        drives::build_with(p, FaultSet::none(), c.clone()),
        FaultSet::none(),
        unit,
    )
    .with_choices(c)
}

/// One request PDU (any bytes) over Modbus/TCP; the response PDU.
fn ask(s: &mut Station, pdu: &[u8]) -> Vec<u8> {
    let unit = s.profile().device.default_unit;
    let mut adu = Vec::new();
    tcp::encode_adu(1, unit, pdu, &mut adu).expect("encodes");
    let wire = s.tcp_adu(Duration::ZERO, &adu).expect("answers");
    wire.bytes[tcp::MBAP_LEN..].to_vec()
}

fn sd2x(specs: &[&str]) -> Sd2x {
    Sd2x::new(profile("sd2x"), FaultSet::none(), choices("sd2x", specs))
}

fn read_one(m: &mut Sd2x, ms: u64, address: u16) -> u16 {
    match m.handle(
        Duration::from_millis(ms),
        1,
        &Request::ReadHoldingRegisters {
            address,
            quantity: 1,
        },
    ) {
        Some(Response::ReadHoldingRegisters { values }) => values[0],
        other => panic!("read {address}: {other:?}"),
    }
}

/// Shutdown with a 100 ms watchdog at t = 0, never rewritten.
fn trip_watchdog(m: &mut Sd2x) {
    let r = m.handle(
        Duration::ZERO,
        1,
        &Request::WriteMultipleRegisters {
            address: 3000,
            values: vec![0x0006, 0, 0, 100],
        },
    );
    assert!(
        matches!(r, Some(Response::WriteMultipleRegisters { .. })),
        "{r:?}"
    );
}

#[test]
fn sd2x_status_word_bits_outside_the_ds402_state_bits_are_the_drives_own() {
    let reference = read_one(&mut sd2x(&[]), 0, 2000);
    let own = read_one(&mut sd2x(&["sd2x-status-word-bits=0x006F"]), 0, 2000);
    assert_eq!(reference, 0x7070);
    assert_eq!(own, 0x0260, "state bits kept, 4 and 12-14 cleared, 9 set");
    assert_eq!(reference & 0x006F, own & 0x006F);
}

#[test]
fn sd2x_watchdog_error_code_any_nonzero() {
    let mut r = sd2x(&[]);
    trip_watchdog(&mut r);
    assert_eq!(read_one(&mut r, 200, 2005), 0x8130);
    let mut m = sd2x(&["sd2x-watchdog-error-code=any-nonzero"]);
    trip_watchdog(&mut m);
    assert_eq!(read_one(&mut m, 200, 2005), 0xFF00);
}

#[test]
fn sd2x_watchdog_trip_state_fault_reaction_active_lasts_a_while() {
    let mut r = sd2x(&[]);
    trip_watchdog(&mut r);
    assert_eq!(read_one(&mut r, 200, 2000) & 0x004F, 0x0008, "fault");
    let mut m = sd2x(&["sd2x-watchdog-trip-state=fault-reaction-active"]);
    trip_watchdog(&mut m);
    assert_eq!(
        read_one(&mut m, 200, 2000) & 0x004F,
        0x000F,
        "fault reaction active"
    );
    m.advance(Duration::from_millis(400));
    assert_eq!(m.state(), Ds402State::Fault, "then fault");
}

fn mnemonic(name: &str) -> Vec<u8> {
    Mnemonic::from_name(name).expect("mnemonic").0.to_vec()
}

/// The answer to an FC 0x41 read of TR by an MDrive taking `choose`.
fn read_tr(choose: &[&str]) -> Vec<u8> {
    let read_tr = [vec![0x41], mnemonic("TR")].concat();
    ask(&mut station("mdrive", choose), &read_tr)
}

#[test]
fn fc41_two_byte_count() {
    let one = read_tr(&[]);
    let two = read_tr(&["fc41-byte-count-width=2-byte"]);
    assert_eq!(one[1] as usize, one.len() - 2);
    assert_eq!(two[..3], [0x41, 0x00, one[1]]);
    assert_eq!(two[3..], one[2..]);
}

#[test]
fn fc41_read_back_as_written() {
    let reference = read_tr(&[]);
    let own = read_tr(&["fc41-read-back-format=as-written"]);
    assert_eq!(&reference[2..], b"0, 0, 0");
    assert_eq!(&own[2..], b"=0,0,0");
}

#[test]
fn fc42_parameterless_command_without_count_byte() {
    let six = [vec![0x42], mnemonic("E"), vec![0x00]].concat();
    let five = [vec![0x42], mnemonic("E")].concat();
    assert_eq!(ask(&mut station("mdrive", &[]), &six)[0], 0x42);
    let mut s = station("mdrive", &["fc42-parameterless-byte-count=no-count-byte"]);
    assert_eq!(
        ask(&mut s, &six),
        [0xC2, 0x03],
        "the count 0 is a parameter byte E does not take"
    );
    assert_eq!(
        ask(&mut s, &five),
        [vec![0x42, 0x04], mnemonic("E")].concat()
    );
}

#[test]
fn lmd_esc_as_printed() {
    let rule = [vec![0x42], mnemonic("\u{1b}"), vec![0x00]].concat();
    let printed = [0x42, 0x20, 0x20, 0x1B, 0x20, 0x00];
    assert_eq!(ask(&mut station("lmd", &[]), &rule)[0], 0x42);
    let mut s = station("lmd", &["lmd-esc-wire-form=20 20 1B 20"]);
    assert_eq!(ask(&mut s, &rule), [0xC2, 0x02], "an unknown mnemonic");
    assert_eq!(ask(&mut s, &printed), [0x42, 0x04, 0x20, 0x20, 0x1B, 0x20]);
}

#[test]
fn mdrive_program_control_by_fc41() {
    let write_e = [vec![0x42], mnemonic("E"), vec![0x00]].concat();
    let read_e = [vec![0x41], mnemonic("E")].concat();
    assert_eq!(ask(&mut station("mdrive", &[]), &read_e), [0xC1, 0x02]);
    let mut s = station("mdrive", &["mdrive-program-control-function=fc41"]);
    assert_eq!(ask(&mut s, &write_e), [0xC2, 0x02]);
    assert_eq!(ask(&mut s, &read_e), [0x41, 0x00]);
}

#[test]
fn lmd_discrete_inputs_at_0x002d() {
    let at = |a: u16| [0x02, (a >> 8) as u8, a as u8, 0x00, 0x04];
    let mut r = station("lmd", &[]);
    assert_eq!(ask(&mut r, &at(0x0000))[..2], [0x02, 0x01]);
    assert_eq!(ask(&mut r, &at(0x002D)), [0x82, 0x02]);
    let mut s = station("lmd", &["lmd-discrete-input-addressing=inputs-at-0x002D"]);
    assert_eq!(ask(&mut s, &at(0x0000)), [0x82, 0x02]);
    assert_eq!(ask(&mut s, &at(0x002D)), ask(&mut r, &at(0x0000)));
}

/// An MDrive output read while its point is configured as an input: the reference serves the latch as
/// stored (`mdrive-output-read-while-input` = response), and offers the oracle the same read with that
/// output as 0, what the point drives, which a drive may answer instead (the manual says neither; an
/// independent MDrive, tests/independent/mdrive-f, reads 0).
#[test]
fn an_mdrive_output_read_while_its_point_is_an_input_may_read_the_latch_or_zero() {
    let mut s = station("mdrive", &[]);
    let setup = |s: &mut Station, params: &[u8]| {
        let req = Request::VendorWrite {
            mnemonic: Mnemonic::from_name("S4").expect("S4"),
            params: params.to_vec(),
        };
        let r = ask(s, &req.to_bytes().expect("pdu"));
        assert_eq!(r[0], 0x42, "{r:02X?}");
    };
    setup(&mut s, b"=16,0,0");
    assert_eq!(
        ask(&mut s, &[0x05, 0x00, 0x4E, 0xFF, 0x00]),
        [0x05, 0x00, 0x4E, 0xFF, 0x00]
    );
    setup(&mut s, b"=0,0,0");
    let _ = s.take_decisions();
    let _ = s.take_choice_alternatives();
    // FC 01 of outputs 3 and 4 (0x004D-0x004E): output 4 latched on, its point an input; output 3 as the
    // reference holds it (on, as the manual's example reads it, line 557; its point an input too).
    assert_eq!(
        ask(&mut s, &[0x01, 0x00, 0x4D, 0x00, 0x02]),
        [0x01, 0x01, 0x03]
    );
    let decided = s.take_decisions();
    assert!(
        decided.contains(&"mdrive-output-read-while-input"),
        "{decided:?}"
    );
    let alternatives = s.take_choice_alternatives();
    assert_eq!(
        alternatives,
        [(
            "mdrive-output-read-while-input",
            "response",
            Response::ReadCoils { data: vec![0x00] }
        )],
    );
    // The register read of O4 (0x004E) likewise.
    let _ = ask(&mut s, &[0x03, 0x00, 0x4E, 0x00, 0x01]);
    let _ = s.take_decisions();
    assert_eq!(
        s.take_choice_alternatives(),
        [(
            "mdrive-output-read-while-input",
            "response",
            Response::ReadHoldingRegisters { values: vec![0] }
        )],
    );
}

/// An SDO error code sent in the order the code is printed (FF FF 00 0B for 0xFFFF000B,
/// `sd2x-sdo-error-byte-order=printed-order`), where the reference sends it little-endian (0B 00 FF FF).
#[test]
fn sd2x_sdo_error_code_in_printed_order() {
    // A read of object 534, which the dictionary does not have.
    let read = Request::CanOpen(codec::CanOpenAccess::read(1, 534, 0, 2))
        .to_bytes()
        .expect("encodes");
    let reference = ask(&mut station("sd2x", &[]), &read);
    let printed = ask(
        &mut station("sd2x", &["sd2x-sdo-error-byte-order=printed-order"]),
        &read,
    );
    assert_eq!(reference.first(), Some(&0xAB), "{reference:02X?}");
    assert_eq!(reference[reference.len() - 4..], [0x0B, 0x00, 0xFF, 0xFF]);
    assert_eq!(
        printed[..printed.len() - 4],
        reference[..reference.len() - 4]
    );
    assert_eq!(printed[printed.len() - 4..], [0xFF, 0xFF, 0x00, 0x0B]);
}

/// PM (0x005C) switched on while EE (0x001E) is off, refused by a drive taking
/// `position-maintenance-without-encoder=exception-04` (an independent closed-loop LMD does): refused only while
/// EE reads 0, taken once EE is 1, and taken by the reference either way.
#[test]
fn position_maintenance_refused_while_the_encoder_is_off() {
    // FC 16 of one register (the MDrive and the LMD have no FC 06); its echo: 10, address, quantity 1.
    let write = |address: u16, value: u16| {
        Request::WriteMultipleRegisters {
            address,
            values: vec![value],
        }
        .to_bytes()
        .expect("encodes")
    };
    let echo = |address: u16| {
        let [hi, lo] = address.to_be_bytes();
        vec![0x10, hi, lo, 0x00, 0x01]
    };
    let pm_on = write(0x005C, 1);
    for stem in ["lmd", "mdrive"] {
        let mut reference = station(stem, &[]);
        assert_eq!(
            ask(&mut reference, &pm_on),
            echo(0x005C),
            "{stem}: the reference takes PM = 1 with EE = 0"
        );
        let mut s = station(stem, &["position-maintenance-without-encoder=exception-04"]);
        assert_eq!(
            ask(&mut s, &pm_on),
            [0x90, 0x04],
            "{stem}: PM = 1 with EE = 0"
        );
        assert_eq!(
            ask(&mut s, &write(0x005C, 0)),
            echo(0x005C),
            "{stem}: PM = 0"
        );
        assert_eq!(
            ask(&mut s, &write(0x001E, 1)),
            echo(0x001E),
            "{stem}: EE = 1"
        );
        assert_eq!(
            ask(&mut s, &pm_on),
            echo(0x005C),
            "{stem}: PM = 1 with EE = 1"
        );
    }
}

/// An RTU frame not as long as its function code's rules make it (FC 16 whose byte count says 2 where 4
/// data bytes follow), intact otherwise: the reference refuses it (03); a drive that sizes frames by the
/// byte count finds the CRC wrong where the count ends and answers nothing (`rtu-length-framing=silence`).
/// The same drive answers a frame of the right length, and Modbus/TCP frames are not its to ignore.
#[test]
fn rtu_frame_of_another_length_than_its_rules_give_is_ignored_by_a_length_framing_drive() {
    let rtu_ask = |s: &mut Station, pdu: &[u8]| {
        let mut frame = Vec::new();
        codec::rtu::encode_adu(1, pdu, &mut frame).expect("encodes");
        s.rtu_frame(Duration::ZERO, &frame).map(|w| {
            codec::rtu::decode_adu(&w.bytes)
                .expect("answer")
                .pdu
                .to_vec()
        })
    };
    let mismatched = [0x10, 0x0B, 0xB8, 0x00, 0x02, 0x02, 0x00, 0x00, 0x00, 0x00];
    let read = [0x03, 0x07, 0xD0, 0x00, 0x01];
    let mut reference = station("sd2x", &[]);
    assert_eq!(rtu_ask(&mut reference, &mismatched), Some(vec![0x90, 0x03]));
    let mut s = station("sd2x", &["rtu-length-framing=silence"]);
    assert_eq!(rtu_ask(&mut s, &mismatched), None);
    assert!(rtu_ask(&mut s, &read).is_some_and(|r| r[0] == 0x03));
    let mut tcp = station("mdrive", &["rtu-length-framing=silence"]);
    let mut m = mismatched;
    m[1..3].copy_from_slice(&[0x00, 0x89]);
    assert_eq!(ask(&mut tcp, &m), [0x90, 0x03], "Modbus/TCP");
    // The MDrive's vendor function 0x41 has a layout only where the profile lists it: an SD2x knows none, so a
    // cut-short 0x41 is no frame of another length to it (it answers 01 whatever the framing), while on a
    // profile with 0x41 it is one.
    let cut_41 = [0x41, 0x20, 0x20];
    assert_eq!(rtu_ask(&mut s, &cut_41), Some(vec![0xC1, 0x01]), "sd2x");
    let mut m = station("mdrive", &["rtu-length-framing=silence"]);
    assert_eq!(rtu_ask(&mut m, &cut_41), None, "mdrive over RTU");
}

/// `multi-item-access`: a drive taking one parameter a request refuses a read or write over two whole items
/// (with the code it chose) and serves each alone; a read over the device's quantity limit, or one cutting a
/// 32-bit item, is another freedom's, and the reference serves the two items as one block.
#[test]
fn a_one_parameter_drive_refuses_a_range_over_two_items() {
    // LMD I1-I2 (0x002D, 0x002E: one register each).
    let two = [0x03, 0x00, 0x2D, 0x00, 0x02];
    let one = [0x03, 0x00, 0x2D, 0x00, 0x01];
    let mut reference = station("lmd", &[]);
    assert_eq!(ask(&mut reference, &two)[..2], [0x03, 0x04]);
    for (value, code) in [("exception-02", 0x02), ("exception-04", 0x04)] {
        let mut s = station("lmd", &[&format!("multi-item-access={value}")]);
        assert_eq!(ask(&mut s, &two), [0x83, code], "{value}");
        assert_eq!(
            ask(&mut s, &one)[..2],
            [0x03, 0x02],
            "{value}: one item alone"
        );
        // A write over two one-register parameters (CW 0x000E, D1 0x000F) is refused alike, and changes
        // nothing.
        let before = ask(&mut s, &[0x03, 0x00, 0x0F, 0x00, 0x01]);
        let write = [0x10, 0x00, 0x0E, 0x00, 0x02, 0x04, 0x00, 0x00, 0x00, 0x05];
        assert_eq!(ask(&mut s, &write), [0x90, code], "{value}: write");
        assert_eq!(ask(&mut s, &[0x03, 0x00, 0x0F, 0x00, 0x01]), before);
    }
}
