//! The SD2x reference model through the RTU station: golden replay, DS402, speed ramp, watchdog, FC 43 object
//! access and SDO errors, addressing, FC 08 counters, and a no-panic / strict-reply property.
//!
//! Every exchange goes through `Station::rtu_frame` with frames built by `frame::rtu`, on a virtual clock:
//! `now` is passed in, nothing sleeps. Seeds: proptest prints the failing seed and persists it under
//! `proptest-regressions/`; rerunning replays it.

use std::time::Duration;

use codec::{
    CanOpenAccess, Direction, ExceptionCode, FunctionCode, Pdu, Request, Response, hex_spaced,
    parse_hex, rtu,
};
use drives::corpus::Corpus;
use drives::golden::{GoldenDirection, GoldenFile};
use drives::models::sd2x::{DEFAULT_WATCHDOG_ERROR_CODE, RAMP_PER_SECOND, sdo, status};
use drives::profile::Profile;
use drives::{self, Fault, FaultSet, Station};
use proptest::collection::vec;
use proptest::prelude::*;
use proptest::sample::select;

use crate::support;

// Status words as the model composes them (see sim/sd2x.rs): DS402 state bits | voltage enabled (0x0010)
// | quick stop not active (0x0020) | bits 12-14 (0x7000) | target reached (0x0400).
const SWITCH_ON_DISABLED: u16 = 0x7070;
const READY_TO_SWITCH_ON: u16 = 0x7031;
const SWITCHED_ON: u16 = 0x7033;
const OPERATION_ENABLED: u16 = 0x7037;
const OPERATION_ENABLED_AT_TARGET: u16 = 0x7437;
const QUICK_STOP_ACTIVE: u16 = 0x7017;
const FAULT_REACTION_ACTIVE: u16 = 0x703F;
const FAULT: u16 = 0x7038;

const UNIT: u8 = 1;

fn profile() -> Profile {
    support::profile("sd2x")
}

fn station_with(profile: Profile, faults: &[Fault]) -> Station {
    let faults = FaultSet::of(faults);
    // `drives::build` also checks that the sd2x profile selects this model.
    Station::new(drives::build(profile, faults.clone()), faults, UNIT)
}

fn station() -> Station {
    station_with(profile(), &[])
}

fn ms(n: u64) -> Duration {
    Duration::from_millis(n)
}

/// Send `req` to `address` at `t_ms`; the reply, strictly decoded, or `None` for silence.
fn send_to(st: &mut Station, t_ms: u64, address: u8, req: Request) -> Option<Response> {
    let bytes = rtu::encode(address, &Pdu::Request(req)).expect("request encodes");
    let wire = st.rtu_frame(ms(t_ms), &bytes)?;
    match rtu::decode(&wire.bytes, Direction::Response) {
        Ok((a, Pdu::Response(r))) => {
            assert_eq!(a, address, "reply address");
            Some(r)
        }
        other => panic!(
            "reply {} does not decode: {other:?}",
            hex_spaced(&wire.bytes)
        ),
    }
}

fn send(st: &mut Station, t_ms: u64, req: Request) -> Response {
    send_to(st, t_ms, UNIT, req).expect("a reply")
}

fn read(st: &mut Station, t_ms: u64, address: u16, quantity: u16) -> Vec<u16> {
    match send(
        st,
        t_ms,
        Request::ReadHoldingRegisters { address, quantity },
    ) {
        Response::ReadHoldingRegisters { values } => values,
        r => panic!("read {address}: {r:?}"),
    }
}

fn read1(st: &mut Station, t_ms: u64, address: u16) -> u16 {
    read(st, t_ms, address, 1)[0]
}

fn status(st: &mut Station, t_ms: u64) -> u16 {
    read1(st, t_ms, 2000)
}

fn speed(st: &mut Station, t_ms: u64) -> i16 {
    read1(st, t_ms, 2001) as i16
}

fn write(st: &mut Station, t_ms: u64, address: u16, value: u16) {
    let r = send(st, t_ms, Request::WriteSingleRegister { address, value });
    assert_eq!(r, Response::WriteSingleRegister { address, value });
}

/// The RxPDO telegram of example 6.1 (FC 16 to 3000..3003) with control word `cw`.
fn telegram(st: &mut Station, t_ms: u64, cw: u16, speed: u16, watchdog: u16) {
    let r = send(
        st,
        t_ms,
        Request::WriteMultipleRegisters {
            address: 3000,
            values: vec![cw, speed, 100, watchdog],
        },
    );
    assert_eq!(
        r,
        Response::WriteMultipleRegisters {
            address: 3000,
            quantity: 4
        }
    );
}

fn exception(fc: u8, code: ExceptionCode) -> Response {
    Response::exception(FunctionCode(fc), code)
}

fn sdo_error(code: u32) -> Response {
    Response::CanOpenError { sdo_code: code }
}

// ---------------------------------------------------------------------------------------------------------------
// Golden replay
// ---------------------------------------------------------------------------------------------------------------

/// Every corrected request of corpus/golden/sd2x.toml, in file order on one drive, gets its corrected response
/// byte for byte. The 6.3 status value 0x7038 is a fault state, so the read is timed after the watchdog armed by
/// the 6.1 telegrams (500 ms) has expired: the example stops sending after "enable operation" (ERRATA A16).
#[test]
fn golden_replay_gives_the_corrected_responses() {
    let (name, text) = Corpus::Embedded.file("golden", "sd2x").expect("golden");
    let golden = GoldenFile::parse(&name, &text).expect("golden parses");
    // 6.1 telegrams 200 ms apart (the manual's advice, line 1228); the watchdog expires 500 ms after the
    // last one (700 ms), the motor ramps down from 50 Hz by 1200 ms, and 6.3 reads the fault at 2000 ms.
    let schedule = [
        ("sd2x/6.1/shutdown/request", 0),
        ("sd2x/6.1/enable-operation/request", 200),
        ("sd2x/6.2/read-temperature/request", 400),
        ("sd2x/6.3/status-read/request", 2000),
    ];
    let mut st = station();
    let mut replayed = 0;
    for req in golden
        .frames
        .iter()
        .filter(|f| f.direction == GoldenDirection::Request)
    {
        let (_, t) = schedule
            .iter()
            .find(|(id, _)| *id == req.id)
            .unwrap_or_else(|| panic!("no time scheduled for golden request {}", req.id));
        let resp = golden
            .frames
            .iter()
            .find(|f| f.request.as_deref() == Some(req.id.as_str()))
            .unwrap_or_else(|| panic!("no golden response for {}", req.id));
        let bytes = |f: &drives::golden::GoldenFrame| {
            parse_hex(f.corrected.as_deref().or(f.printed.as_deref()).unwrap()).unwrap()
        };
        let got = st
            .rtu_frame(ms(*t), &bytes(req))
            .unwrap_or_else(|| panic!("{}: silence", req.id));
        assert_eq!(
            hex_spaced(&got.bytes),
            hex_spaced(&bytes(resp)),
            "{}",
            req.id
        );
        replayed += 1;
    }
    assert_eq!(replayed, schedule.len(), "every scheduled request replayed");
    // The explicit bytes the brief names, so a change to the golden file cannot hollow this test out.
    let mut st = station();
    let frames = [
        (
            0,
            "01 10 0B B8 00 04 08 00 06 03 E8 00 64 01 F4 48 FC",
            "01 10 0B B8 00 04 43 CB",
        ),
        (
            200,
            "01 10 0B B8 00 04 08 00 0F 03 E8 00 64 01 F4 D1 FC",
            "01 10 0B B8 00 04 43 CB",
        ),
        (
            400,
            "01 2B 0D 00 00 01 00 29 00 00 00 00 02 19 56",
            "01 2B 0D 00 00 01 00 29 00 00 00 00 02 AA 00 F5 0E",
        ),
        (2000, "01 03 07 D0 00 01 84 87", "01 03 02 70 38 9C 56"),
    ];
    for (t, req, resp) in frames {
        let got = st.rtu_frame(ms(t), &parse_hex(req).unwrap()).expect(req);
        assert_eq!(hex_spaced(&got.bytes), resp, "{req}");
    }
}

/// The 6.3 value depends on the drive's state: a drive fresh from power-on is in switch on disabled, and
/// a watchdog trip out of "ready to switch on" (the state 6.1 says the drive is in after shutdown) gives 0x7038.
#[test]
fn status_read_is_state_dependent() {
    let req = parse_hex("01 03 07 D0 00 01 84 87").unwrap();
    let mut st = station();
    let got = st.rtu_frame(ms(0), &req).unwrap();
    let (_, pdu) = rtu::decode(&got.bytes, Direction::Response).unwrap();
    assert_eq!(
        pdu,
        Pdu::Response(Response::ReadHoldingRegisters {
            values: vec![SWITCH_ON_DISABLED]
        })
    );

    let mut st = station();
    telegram(&mut st, 0, 0x0006, 1000, 500);
    assert_eq!(status(&mut st, 500), READY_TO_SWITCH_ON);
    let got = st.rtu_frame(ms(501), &req).unwrap();
    assert_eq!(hex_spaced(&got.bytes), "01 03 02 70 38 9C 56");
}

// ---------------------------------------------------------------------------------------------------------------
// Registers
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn fc03_and_fc04_read_the_same_map() {
    let mut st = station();
    write(&mut st, 0, 3001, 1234);
    for (address, quantity) in [(2000, 24), (3000, 4), (2010, 1), (2011, 1)] {
        let h = read(&mut st, 1, address, quantity);
        let i = match send(
            &mut st,
            1,
            Request::ReadInputRegisters { address, quantity },
        ) {
            Response::ReadInputRegisters { values } => values,
            r => panic!("{r:?}"),
        };
        assert_eq!(h, i, "{address}+{quantity}");
    }
    // The simulated constants, with 32-bit pairs high word first (section 4.3, lines 785-791).
    let tx = read(&mut st, 1, 2000, 24);
    assert_eq!(tx[6], 170, "power stage 17.0 degC, as example 6.2");
    assert_eq!(&tx[12..14], &[0x0002, 0x0010], "hardware version 2.16");
    assert_eq!(read(&mut st, 1, 3000, 4), vec![0, 1234, 0, 0]);
}

#[test]
fn unmapped_addresses_give_exception_02() {
    let mut st = station();
    let e02 = |fc| exception(fc, ExceptionCode::ILLEGAL_DATA_ADDRESS);
    for (address, quantity) in [
        (1999, 1),
        (2024, 1),
        (2020, 5),
        (3004, 1),
        (2999, 2),
        (0, 1),
    ] {
        assert_eq!(
            send(
                &mut st,
                0,
                Request::ReadHoldingRegisters { address, quantity }
            ),
            e02(0x03),
            "{address}+{quantity}"
        );
        assert_eq!(
            send(
                &mut st,
                0,
                Request::ReadInputRegisters { address, quantity }
            ),
            e02(0x04)
        );
    }
    // Running past 0xFFFF.
    assert_eq!(
        send(
            &mut st,
            0,
            Request::ReadHoldingRegisters {
                address: 0xFFF0,
                quantity: 48
            }
        ),
        e02(0x03)
    );
    // A write that runs one register past the RxPDO writes nothing.
    assert_eq!(
        send(
            &mut st,
            0,
            Request::WriteMultipleRegisters {
                address: 3002,
                values: vec![7, 8, 9]
            }
        ),
        e02(0x10)
    );
    assert_eq!(read(&mut st, 0, 3002, 2), vec![0, 0]);
}

#[test]
fn writes_to_the_txpdo_give_exception_02() {
    let mut st = station();
    let e02 = |fc| exception(fc, ExceptionCode::ILLEGAL_DATA_ADDRESS);
    assert_eq!(
        send(
            &mut st,
            0,
            Request::WriteSingleRegister {
                address: 2006,
                value: 1
            }
        ),
        e02(0x06)
    );
    assert_eq!(
        send(
            &mut st,
            0,
            Request::WriteMultipleRegisters {
                address: 2000,
                values: vec![0; 4]
            }
        ),
        e02(0x10)
    );
    assert_eq!(read1(&mut st, 0, 2006), 170);

    // Mutant: read-only-writable accepts the write, and a stored value reads back.
    let mut st = station_with(profile(), &[Fault::ReadOnlyWritable]);
    write(&mut st, 0, 2006, 999);
    assert_eq!(read1(&mut st, 0, 2006), 999);
}

#[test]
fn fc23_writes_then_reads_and_is_atomic() {
    let mut st = station();
    let r = send(
        &mut st,
        0,
        Request::ReadWriteMultipleRegisters {
            read_address: 3000,
            read_quantity: 4,
            write_address: 3001,
            values: vec![500, 42],
        },
    );
    assert_eq!(
        r,
        Response::ReadWriteMultipleRegisters {
            values: vec![0, 500, 42, 0]
        }
    );
    // A bad read address rejects the request before anything is written.
    let r = send(
        &mut st,
        0,
        Request::ReadWriteMultipleRegisters {
            read_address: 2024,
            read_quantity: 1,
            write_address: 3001,
            values: vec![1],
        },
    );
    assert_eq!(r, exception(0x17, ExceptionCode::ILLEGAL_DATA_ADDRESS));
    // And a write into the TxPDO is 02 too.
    let r = send(
        &mut st,
        0,
        Request::ReadWriteMultipleRegisters {
            read_address: 3000,
            read_quantity: 1,
            write_address: 2000,
            values: vec![1],
        },
    );
    assert_eq!(r, exception(0x17, ExceptionCode::ILLEGAL_DATA_ADDRESS));
    assert_eq!(read1(&mut st, 0, 3001), 500);
}

#[test]
fn quantity_limits_are_the_stations() {
    let mut st = station();
    let e03 = exception(0x03, ExceptionCode::ILLEGAL_DATA_VALUE);
    for quantity in [0, 49] {
        assert_eq!(
            send(
                &mut st,
                0,
                Request::ReadHoldingRegisters {
                    address: 2000,
                    quantity
                }
            ),
            e03
        );
    }
}

#[test]
fn word_order_fault_flips_32_bit_pairs() {
    let mut st = station_with(profile(), &[Fault::WordOrder]);
    assert_eq!(read(&mut st, 0, 2012, 2), vec![0x0010, 0x0002]);
    assert_eq!(
        read(&mut st, 0, 2006, 1),
        vec![170],
        "16-bit registers unchanged"
    );
    let mut st = station();
    assert_eq!(read(&mut st, 0, 2012, 2), vec![0x0002, 0x0010]);
}

#[test]
fn reserved_readable_fault_reads_unmapped_as_zero() {
    let mut st = station_with(profile(), &[Fault::ReservedReadable]);
    assert_eq!(read(&mut st, 0, 2022, 4), vec![0, 15_000, 0, 0]);
}

/// The shipped profile's RxPDO ranges are the full 16-bit ranges, so range checks only show with a narrower
/// range; the model takes ranges from the profile.
#[test]
fn range_checks_follow_the_profile() {
    let mut p = profile();
    for r in &mut p.registers {
        if r.get_ref().address == 3001 {
            r.get_mut().min = Some(-1000);
            r.get_mut().max = Some(1000);
        }
    }
    for o in &mut p.objects {
        if o.get_ref().index == 210 {
            o.get_mut().min = Some(-1000);
            o.get_mut().max = Some(1000);
        }
    }
    let mut st = station_with(p.clone(), &[]);
    assert_eq!(
        send(
            &mut st,
            0,
            Request::WriteSingleRegister {
                address: 3001,
                value: 1001
            }
        ),
        exception(0x06, ExceptionCode::ILLEGAL_DATA_VALUE)
    );
    write(&mut st, 0, 3001, (-1000i16) as u16);
    let w = |v: i16| Request::CanOpen(CanOpenAccess::write(1, 210, 0, v.to_le_bytes().to_vec()));
    assert_eq!(send(&mut st, 0, w(1001)), sdo_error(sdo::VALUE_TOO_HIGH));
    assert_eq!(send(&mut st, 0, w(-1001)), sdo_error(sdo::VALUE_TOO_LOW));

    let mut st = station_with(p, &[Fault::RangeUnchecked]);
    write(&mut st, 0, 3001, 1001);
    assert!(matches!(send(&mut st, 0, w(2000)), Response::CanOpen(_)));
    assert_eq!(read1(&mut st, 0, 3001), 2000);
}

// ---------------------------------------------------------------------------------------------------------------
// DS402
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn ds402_sequence() {
    let mut st = station();
    assert_eq!(status(&mut st, 0), SWITCH_ON_DISABLED, "power-on state");
    // Only "shutdown" leaves switch on disabled.
    write(&mut st, 0, 3000, 0x000F);
    assert_eq!(status(&mut st, 0), SWITCH_ON_DISABLED);
    write(&mut st, 0, 3000, 0x0007);
    assert_eq!(status(&mut st, 0), SWITCH_ON_DISABLED);

    write(&mut st, 0, 3001, 1000);
    write(&mut st, 0, 3000, 0x0006);
    assert_eq!(status(&mut st, 0), READY_TO_SWITCH_ON);
    write(&mut st, 0, 3000, 0x0007);
    assert_eq!(status(&mut st, 0), SWITCHED_ON);
    write(&mut st, 0, 3000, 0x000F);
    assert_eq!(status(&mut st, 0), OPERATION_ENABLED);
    assert_eq!(status(&mut st, 1000), OPERATION_ENABLED_AT_TARGET);
    // Disable operation, shutdown, disable voltage.
    write(&mut st, 1000, 3000, 0x0007);
    assert_eq!(status(&mut st, 1000), SWITCHED_ON);
    write(&mut st, 1000, 3000, 0x0006);
    assert_eq!(status(&mut st, 1000), READY_TO_SWITCH_ON);
    write(&mut st, 1000, 3000, 0x0000);
    assert_eq!(status(&mut st, 1000), SWITCH_ON_DISABLED);

    // Example 6.1's shortcut: "enable operation" straight from ready to switch on.
    write(&mut st, 3000, 3000, 0x0006);
    write(&mut st, 3000, 3000, 0x000F);
    assert_eq!(status(&mut st, 3000), OPERATION_ENABLED);
    // Quick stop: ramp down in quick stop active, then switch on disabled (option code 2).
    assert_eq!(speed(&mut st, 3500), 500);
    write(&mut st, 3500, 3000, 0x0002);
    assert_eq!(status(&mut st, 3500), QUICK_STOP_ACTIVE);
    assert_eq!(status(&mut st, 3999), QUICK_STOP_ACTIVE);
    assert_eq!(status(&mut st, 4000), SWITCH_ON_DISABLED);
    // Quick stop out of ready to switch on goes straight to switch on disabled.
    write(&mut st, 4000, 3000, 0x0006);
    write(&mut st, 4000, 3000, 0x0002);
    assert_eq!(status(&mut st, 4000), SWITCH_ON_DISABLED);
}

#[test]
fn fault_and_fault_reset() {
    let mut st = station();
    telegram(&mut st, 0, 0x000F, 1000, 0);
    telegram(&mut st, 0, 0x0006, 1000, 0); // ready to switch on
    telegram(&mut st, 0, 0x000F, 1000, 300); // operation enabled, watchdog 300 ms
    assert_eq!(status(&mut st, 300), OPERATION_ENABLED);
    // Trips at 300 ms with the motor at 30 Hz: fault reaction ramps it down, then fault.
    assert_eq!(status(&mut st, 301), FAULT_REACTION_ACTIVE);
    assert_eq!(read1(&mut st, 301, 2005), DEFAULT_WATCHDOG_ERROR_CODE);
    assert_eq!(status(&mut st, 599), FAULT_REACTION_ACTIVE);
    assert_eq!(speed(&mut st, 599), 1);
    assert_eq!(status(&mut st, 600), FAULT);
    // Fault reset is the rising edge of bit 7; other commands do nothing in fault.
    write(&mut st, 700, 3000, 0x0006);
    assert_eq!(status(&mut st, 700), FAULT);
    write(&mut st, 700, 3000, 0x0080);
    assert_eq!(status(&mut st, 700), SWITCH_ON_DISABLED);
    assert_eq!(read1(&mut st, 700, 2005), 0, "error code cleared");
    // Bit 7 held high blocks every other command.
    write(&mut st, 700, 3000, 0x0086);
    assert_eq!(status(&mut st, 700), SWITCH_ON_DISABLED);
    write(&mut st, 700, 3000, 0x0006);
    assert_eq!(status(&mut st, 700), READY_TO_SWITCH_ON);
}

#[test]
fn fault_reset_needs_a_rising_edge() {
    let mut st = station();
    telegram(&mut st, 0, 0x0006, 0, 100);
    // Bit 7 already high when the fault comes: no edge, still in fault.
    write(&mut st, 50, 3000, 0x0080);
    assert_eq!(status(&mut st, 101), FAULT);
    write(&mut st, 101, 3000, 0x0080);
    assert_eq!(status(&mut st, 101), FAULT);
    write(&mut st, 102, 3000, 0x0000);
    write(&mut st, 103, 3000, 0x0080);
    assert_eq!(status(&mut st, 103), SWITCH_ON_DISABLED);
}

// ---------------------------------------------------------------------------------------------------------------
// Speed ramp
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn actual_speed_ramps_over_virtual_time() {
    assert_eq!(RAMP_PER_SECOND, 1000, "the figures below assume 100 Hz/s");
    let mut st = station();
    // Target written outside operation enabled: nothing moves.
    telegram(&mut st, 0, 0x0006, 1000, 0);
    assert_eq!(speed(&mut st, 500), 0);
    telegram(&mut st, 1000, 0x000F, 1000, 0);
    assert_eq!(speed(&mut st, 1000), 0);
    assert_eq!(speed(&mut st, 1250), 250);
    assert_eq!(speed(&mut st, 1999), 999);
    assert_eq!(status(&mut st, 1999), OPERATION_ENABLED);
    assert_eq!(speed(&mut st, 2000), 1000);
    assert_eq!(speed(&mut st, 5000), 1000, "holds the target");
    assert_eq!(status(&mut st, 5000), OPERATION_ENABLED_AT_TARGET);
    // Reverse: through zero to -50 Hz.
    write(&mut st, 5000, 3001, (-500i16) as u16);
    assert_eq!(speed(&mut st, 6000), 0);
    assert_eq!(speed(&mut st, 6250), -250);
    assert_eq!(speed(&mut st, 9000), -500);
    // Halt (bit 8) ramps to zero while staying in operation enabled.
    write(&mut st, 9000, 3000, 0x010F);
    assert_eq!(speed(&mut st, 9400), -100);
    assert_eq!(speed(&mut st, 9600), 0);
    assert_eq!(status(&mut st, 9600), OPERATION_ENABLED_AT_TARGET);
    write(&mut st, 9600, 3000, 0x000F);
    assert_eq!(speed(&mut st, 9700), -100);
    // Leaving operation enabled ramps to zero.
    write(&mut st, 10_000, 3000, 0x0007);
    assert_eq!(speed(&mut st, 10_000), -400);
    assert_eq!(status(&mut st, 10_000), SWITCHED_ON);
    assert_eq!(speed(&mut st, 10_300), -100);
    assert_eq!(speed(&mut st, 11_000), 0);
    // Current and power follow the speed only while the power stage is on.
    assert_eq!(read(&mut st, 11_000, 2003, 2), vec![0, 0]);
}

#[test]
fn speed_object_and_register_agree() {
    let mut st = station();
    telegram(&mut st, 0, 0x0006, 700, 0);
    telegram(&mut st, 0, 0x000F, 700, 0);
    let obj = |st: &mut Station, t, index| match send(
        st,
        t,
        Request::CanOpen(CanOpenAccess::read(1, index, 0, 2)),
    ) {
        Response::CanOpen(a) => u16::from_le_bytes([a.data[0], a.data[1]]),
        r => panic!("{r:?}"),
    };
    assert_eq!(obj(&mut st, 300, 168), 300);
    assert_eq!(speed(&mut st, 300), 300);
    assert_eq!(obj(&mut st, 300, 67), status(&mut st, 300));
    assert_eq!(obj(&mut st, 300, 41), read1(&mut st, 300, 2006));
    assert_eq!(obj(&mut st, 300, 210), 700);
}

// ---------------------------------------------------------------------------------------------------------------
// Watchdog
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn watchdog_trips_after_the_timeout_and_not_before() {
    let mut st = station();
    telegram(&mut st, 0, 0x0006, 1000, 500);
    assert_eq!(
        status(&mut st, 500),
        READY_TO_SWITCH_ON,
        "exactly at the timeout"
    );
    assert_eq!(read1(&mut st, 500, 2005), 0);
    assert_eq!(status(&mut st, 501), FAULT);
    assert_eq!(read1(&mut st, 501, 2005), DEFAULT_WATCHDOG_ERROR_CODE);
    // Tripped once, the watchdog is off until 3003 is written again: a fault reset holds.
    write(&mut st, 600, 3000, 0x0080);
    assert_eq!(status(&mut st, 5000), SWITCH_ON_DISABLED);
}

#[test]
fn watchdog_rewritten_every_200_ms_never_trips() {
    let mut st = station();
    telegram(&mut st, 0, 0x0006, 1000, 500);
    for t in (200..=10_000).step_by(200) {
        telegram(&mut st, t, 0x000F, 1000, 500);
        let s = status(&mut st, t + 199);
        assert_eq!(s & status::FAULT, 0, "fault at {t} ms");
    }
    assert_eq!(status(&mut st, 10_199), OPERATION_ENABLED_AT_TARGET);
    assert_eq!(speed(&mut st, 10_199), 1000);
    // The master stops: trip 500 ms after the last telegram.
    assert_eq!(status(&mut st, 10_500) & status::FAULT, 0);
    assert_eq!(status(&mut st, 10_501), FAULT_REACTION_ACTIVE);
}

#[test]
fn watchdog_restarts_only_on_a_write_to_3003() {
    let mut st = station();
    telegram(&mut st, 0, 0x0006, 0, 500);
    // Control word and target speed rewritten, watchdog register not.
    send(
        &mut st,
        400,
        Request::WriteMultipleRegisters {
            address: 3000,
            values: vec![0x0006, 0],
        },
    );
    assert_eq!(status(&mut st, 501), FAULT);
    // FC 06 to 3003 alone restarts it.
    let mut st = station();
    telegram(&mut st, 0, 0x0006, 0, 500);
    write(&mut st, 400, 3003, 500);
    assert_eq!(status(&mut st, 900), READY_TO_SWITCH_ON);
    assert_eq!(status(&mut st, 901), FAULT);
}

#[test]
fn watchdog_zero_disables() {
    let mut st = station();
    telegram(&mut st, 0, 0x0006, 0, 500);
    write(&mut st, 100, 3003, 0);
    assert_eq!(status(&mut st, 60_000), READY_TO_SWITCH_ON);
}

#[test]
fn watchdog_disabled_fault_never_trips() {
    let mut st = station_with(profile(), &[Fault::WatchdogDisabled]);
    telegram(&mut st, 0, 0x0006, 1000, 500);
    telegram(&mut st, 0, 0x000F, 1000, 500);
    assert_eq!(status(&mut st, 60_000), OPERATION_ENABLED_AT_TARGET);
    assert_eq!(read1(&mut st, 60_000, 2005), 0);
}

#[test]
fn ds402_enable_from_switch_on_disabled_fault_skips_shutdown() {
    // Healthy: 0x000F in switch on disabled is no transition (CiA 402 leaves it by shutdown only).
    let mut st = station();
    telegram(&mut st, 0, 0x000F, 0, 0);
    assert_eq!(status(&mut st, 1) & 0x006F, 0x0060);
    let mut st = station_with(profile(), &[Fault::Ds402EnableFromSwitchOnDisabled]);
    telegram(&mut st, 0, 0x000F, 0, 0);
    assert_eq!(status(&mut st, 1) & 0x006F, 0x0027);
}

#[test]
fn speed_without_enable_fault_turns_the_motor_before_enable() {
    for faults in [&[][..], &[Fault::SpeedWithoutEnable][..]] {
        let mut st = station_with(profile(), faults);
        telegram(&mut st, 0, 0x0006, 1000, 0);
        let expected = if faults.is_empty() { 0 } else { 1000 };
        assert_eq!(speed(&mut st, 2000), expected, "faults {faults:?}");
    }
}

#[test]
fn watchdog_from_first_write_fault_trips_although_rewritten() {
    let mut st = station_with(profile(), &[Fault::WatchdogFromFirstWrite]);
    for t in (0..=800).step_by(200) {
        telegram(&mut st, t, 0x0006, 0, 500);
    }
    assert_eq!(read1(&mut st, 801, 2005), 0x8130);
    assert_eq!(status(&mut st, 801) & 0x0008, 0x0008);
}

#[test]
fn watchdog_error_code_comes_from_the_profile_when_given() {
    let mut p = profile();
    if let Some(w) = p.watchdog.as_mut() {
        w.fault_error_code = Some(0x1234);
    }
    let mut st = station_with(p, &[]);
    telegram(&mut st, 0, 0x0006, 0, 10);
    assert_eq!(read1(&mut st, 11, 2005), 0x1234);
}

// ---------------------------------------------------------------------------------------------------------------
// FC 43 / MEI 0x0D
// ---------------------------------------------------------------------------------------------------------------

fn canopen(st: &mut Station, a: CanOpenAccess) -> Response {
    send(st, 0, Request::CanOpen(a))
}

#[test]
fn object_41_reads_170_little_endian() {
    let mut st = station();
    let r = canopen(&mut st, CanOpenAccess::read(1, 41, 0, 2));
    let Response::CanOpen(a) = r else {
        panic!("{r:?}")
    };
    assert_eq!(a.data, vec![0xAA, 0x00]);
    assert_eq!(a.byte_count, 2);
    // 32-bit objects: little-endian four bytes.
    let r = canopen(&mut st, CanOpenAccess::read(1, 5, 0, 4));
    let Response::CanOpen(a) = r else {
        panic!("{r:?}")
    };
    assert_eq!(a.data, vec![0x10, 0x00, 0x02, 0x00]);
}

#[test]
fn sdo_errors() {
    let mut st = station();
    // Exact bytes of one: AB FF 00 06 0D CE + code little-endian (lines 586-597; ERRATA A12).
    let bytes = rtu::encode(
        1,
        &Pdu::Request(Request::CanOpen(CanOpenAccess::read(1, 1000, 0, 2))),
    )
    .unwrap();
    let got = st.rtu_frame(ms(0), &bytes).unwrap();
    assert!(
        hex_spaced(&got.bytes).starts_with("01 AB FF 00 06 0D CE 0B 00 FF FF"),
        "{}",
        hex_spaced(&got.bytes)
    );

    let cases = [
        (
            CanOpenAccess::read(1, 1000, 0, 2),
            sdo_error(sdo::NO_OBJECT),
        ),
        (
            CanOpenAccess::read(1, 0x6041, 0, 2),
            sdo_error(sdo::NO_OBJECT),
        ),
        (
            CanOpenAccess::read(1, 41, 1, 2),
            sdo_error(sdo::NO_SUBINDEX),
        ),
        (
            CanOpenAccess::write(1, 41, 0, vec![0, 0]),
            sdo_error(sdo::WRITE_READ_ONLY),
        ),
        (
            CanOpenAccess::read(1, 41, 0, 4),
            sdo_error(sdo::LENGTH_TOO_LONG),
        ),
        (
            CanOpenAccess::read(1, 41, 0, 1),
            sdo_error(sdo::LENGTH_TOO_SHORT),
        ),
        (
            CanOpenAccess::read(1, 41, 0, 0),
            sdo_error(sdo::LENGTH_TOO_SHORT),
        ),
        (
            CanOpenAccess::read(1, 177, 0, 2),
            sdo_error(sdo::LENGTH_TOO_SHORT),
        ),
        (
            CanOpenAccess::read(1, 41, 0, 5),
            sdo_error(sdo::LENGTH_WRONG),
        ),
        (
            CanOpenAccess::write(1, 68, 0, vec![6, 0, 0, 0]),
            sdo_error(sdo::LENGTH_TOO_LONG),
        ),
        (
            CanOpenAccess::write(1, 68, 0, vec![6]),
            sdo_error(sdo::LENGTH_TOO_SHORT),
        ),
        (
            CanOpenAccess {
                control: 0x01,
                ..CanOpenAccess::read(1, 41, 0, 2)
            },
            sdo_error(sdo::COMMAND_INVALID),
        ),
        (
            CanOpenAccess {
                offset: 1,
                ..CanOpenAccess::read(1, 41, 0, 2)
            },
            sdo_error(sdo::UNSUPPORTED_ACCESS),
        ),
        // Node-ID other than the slave address.
        (
            CanOpenAccess::read(2, 41, 0, 2),
            exception(0x2B, ExceptionCode::ILLEGAL_DATA_ADDRESS),
        ),
    ];
    for (req, want) in cases {
        assert_eq!(canopen(&mut st, req.clone()), want, "{req:?}");
    }
    // Nothing was written by the failed writes.
    assert_eq!(read1(&mut st, 0, 3000), 0);
}

#[test]
fn object_writes_drive_the_pdo() {
    let mut st = station();
    let r = canopen(&mut st, CanOpenAccess::write(1, 68, 0, vec![0x06, 0x00]));
    let Response::CanOpen(a) = r else {
        panic!("{r:?}")
    };
    assert_eq!((a.control, a.byte_count, a.data.len()), (0x80, 2, 0));
    assert_eq!(status(&mut st, 0), READY_TO_SWITCH_ON);
    canopen(
        &mut st,
        CanOpenAccess::write(1, 210, 0, (-300i16).to_le_bytes().to_vec()),
    );
    assert_eq!(read1(&mut st, 0, 3001) as i16, -300);
    // The reserved byte is ignored and answered as 00.
    let r = canopen(
        &mut st,
        CanOpenAccess {
            reserved: 0x55,
            ..CanOpenAccess::read(1, 41, 0, 2)
        },
    );
    assert!(matches!(r, Response::CanOpen(ref a) if a.reserved == 0 && a.data == [0xAA, 0]));
}

#[test]
fn read_only_writable_fault_applies_to_objects() {
    let mut st = station_with(profile(), &[Fault::ReadOnlyWritable]);
    let r = canopen(&mut st, CanOpenAccess::write(1, 41, 0, vec![0x2C, 0x01]));
    assert!(matches!(r, Response::CanOpen(_)), "{r:?}");
    assert_eq!(read1(&mut st, 0, 2006), 300);
}

#[test]
fn mei_other_than_0d_is_exception_01() {
    let mut st = station();
    let r = send(
        &mut st,
        0,
        Request::ReadDeviceId {
            read_code: 1,
            object_id: 0,
        },
    );
    assert_eq!(r, exception(0x2B, ExceptionCode::ILLEGAL_FUNCTION));
    let r = send(
        &mut st,
        0,
        Request::Raw {
            function: FunctionCode(0x2B),
            data: vec![0x0C, 0, 0],
        },
    );
    assert_eq!(r, exception(0x2B, ExceptionCode::ILLEGAL_FUNCTION));
}

// ---------------------------------------------------------------------------------------------------------------
// Addressing, CRC, FC 08
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn broadcast_write_is_applied_without_reply() {
    // The shipped profile has broadcast = false (the manual never mentions it, ERRATA A10): address 0 is
    // not this drive's, so nothing happens.
    let mut st = station();
    let req = Request::WriteSingleRegister {
        address: 3001,
        value: 321,
    };
    assert_eq!(send_to(&mut st, 0, 0, req.clone()), None);
    assert_eq!(read1(&mut st, 0, 3001), 0);
    // With broadcast enabled the write is applied and the drive stays silent.
    let mut p = profile();
    p.device.broadcast = true;
    let mut st = station_with(p, &[]);
    assert_eq!(send_to(&mut st, 0, 0, req.clone()), None);
    assert_eq!(read1(&mut st, 0, 3001), 321);
    let mut shutdown = telegram_request(0x0006);
    assert_eq!(send_to(&mut st, 0, 0, shutdown.clone()), None);
    assert_eq!(status(&mut st, 0), READY_TO_SWITCH_ON);
    // Mutant: broadcast-answered replies.
    let mut p = profile();
    p.device.broadcast = true;
    let mut st = station_with(p, &[Fault::BroadcastAnswered]);
    shutdown = telegram_request(0x0006);
    assert!(send_to(&mut st, 0, 0, shutdown).is_some());
}

fn telegram_request(cw: u16) -> Request {
    Request::WriteMultipleRegisters {
        address: 3000,
        values: vec![cw, 1000, 100, 0],
    }
}

#[test]
fn other_address_is_silent() {
    let mut st = station();
    for address in [2, 3, 247, 255] {
        assert_eq!(
            send_to(&mut st, 0, address, telegram_request(0x0006)),
            None,
            "{address}"
        );
    }
    assert_eq!(status(&mut st, 0), SWITCH_ON_DISABLED, "nothing applied");
    let c = st.counters();
    assert_eq!((c.bus_message, c.slave_message), (5, 1));
}

#[test]
fn bad_crc_is_silent_and_counted() {
    let mut st = station();
    let mut bytes = rtu::encode(1, &Pdu::Request(telegram_request(0x0006))).unwrap();
    let n = bytes.len();
    bytes[n - 1] ^= 0x01;
    assert!(st.rtu_frame(ms(0), &bytes).is_none());
    assert_eq!(status(&mut st, 0), SWITCH_ON_DISABLED, "not applied");
    let r = send(
        &mut st,
        0,
        Request::Diagnostics {
            sub_function: 0x0C,
            data: vec![0, 0],
        },
    );
    assert_eq!(
        r,
        Response::Diagnostics {
            sub_function: 0x0C,
            data: vec![0, 1]
        }
    );
}

/// The frames the counter tests count: a normal read, an exception, a frame for slave 2, a broadcast write
/// and a bad CRC.
fn counted_sequence(st: &mut Station) {
    read(st, 0, 2000, 1);
    send(
        st,
        0,
        Request::ReadHoldingRegisters {
            address: 2024,
            quantity: 1,
        },
    );
    send_to(st, 0, 2, telegram_request(0x0006));
    send_to(st, 0, 0, telegram_request(0x0006));
    st.rtu_frame(ms(0), &[0x01, 0x03, 0x07, 0xD0, 0x00, 0x01, 0x00, 0x00]);
}

#[test]
fn fc08_counters_move_as_specified() {
    let mut p = profile();
    p.device.broadcast = true;
    let mut st = station_with(p, &[]);
    let diag = |st: &mut Station, sub: u16| -> u16 {
        match send(
            st,
            0,
            Request::Diagnostics {
                sub_function: sub,
                data: vec![0, 0],
            },
        ) {
            Response::Diagnostics { data, .. } => u16::from_be_bytes([data[0], data[1]]),
            r => panic!("{r:?}"),
        }
    };
    // 1: a normal read; 2: an exception; 3: another slave's frame; 4: a broadcast write; then a bad CRC.
    counted_sequence(&mut st);
    // Each FC 08 request counts itself as a bus and slave message before it answers.
    assert_eq!(diag(&mut st, 0x0B), 5, "bus messages: 4 + this one");
    assert_eq!(diag(&mut st, 0x0C), 1, "CRC errors");
    assert_eq!(diag(&mut st, 0x0D), 1, "exceptions");
    assert_eq!(
        diag(&mut st, 0x0E),
        7,
        "slave messages: 1, 2, broadcast, 0B, 0C, 0D, this"
    );
    assert_eq!(diag(&mut st, 0x0F), 1, "no response: the broadcast");
    // An SDO error is an exception response too.
    canopen(&mut st, CanOpenAccess::read(1, 1000, 0, 2));
    assert_eq!(diag(&mut st, 0x0D), 2);
    // Clear, then only the clear and this request are counted.
    diag(&mut st, 0x0A);
    assert_eq!(diag(&mut st, 0x0B), 1);
    assert_eq!(diag(&mut st, 0x0D), 0);
    // Mutant: frozen counters.
    let mut st = station_with(profile(), &[Fault::CountersFrozen]);
    read(&mut st, 0, 2000, 1);
    assert_eq!(diag(&mut st, 0x0B), 0);
}

#[test]
fn fault_write_quantity_over_limit_dropped() {
    let rw = |m: usize| Request::ReadWriteMultipleRegisters {
        read_address: 3000,
        read_quantity: 1,
        write_address: 3000,
        values: vec![0; m],
    };
    // Healthy: 49 registers to write (one above the manual's 48) are refused with 03.
    let mut st = station();
    assert!(matches!(
        send(&mut st, 0, rw(49)),
        Response::Exception { code, .. } if code.0 == 3
    ));
    // The fault drops it; the device's own range and the quantity to read are still answered.
    let mut st = station_with(profile(), &[Fault::WriteQuantityOverLimitDropped]);
    assert_eq!(send_to(&mut st, 0, UNIT, rw(49)), None);
    assert!(matches!(
        send(&mut st, 100, rw(1)),
        Response::ReadWriteMultipleRegisters { .. }
    ));
    let over_read = Request::ReadWriteMultipleRegisters {
        read_address: 3000,
        read_quantity: 49,
        write_address: 3000,
        values: vec![0],
    };
    assert!(matches!(
        send(&mut st, 200, over_read),
        Response::Exception { code, .. } if code.0 == 3
    ));
}

// ---------------------------------------------------------------------------------------------------------------
// No panics, strict replies
// ---------------------------------------------------------------------------------------------------------------

/// Faults that act on the model or on what reaches it, none of which breaks the reply's framing.
const MODEL_FAULTS: &[Fault] = &[
    Fault::ReservedReadable,
    Fault::ReadOnlyWritable,
    Fault::RangeUnchecked,
    Fault::WordOrder,
    Fault::WatchdogDisabled,
    Fault::QuantityUnchecked,
    Fault::QuantityLowByte,
    Fault::QuantityOverSpecDropped,
    Fault::WriteQuantityOverLimitDropped,
    Fault::AnswerOtherUnit,
    Fault::BroadcastAnswered,
];

fn near_map() -> impl Strategy<Value = u16> {
    prop_oneof![1990u16..2030, 2990u16..3010, any::<u16>()]
}

fn object_index() -> impl Strategy<Value = u16> {
    prop_oneof![
        select(vec![
            2u16, 5, 16, 17, 33, 41, 63, 67, 68, 70, 120, 168, 171, 177, 182, 209, 210, 390, 431,
            434
        ]),
        any::<u16>()
    ]
}

/// Requests aimed at the model: valid in shape, with addresses, objects and values around the SD2x map.
fn request() -> impl Strategy<Value = Request> {
    prop_oneof![
        (near_map(), 0u16..60)
            .prop_map(|(address, quantity)| Request::ReadHoldingRegisters { address, quantity }),
        (near_map(), 0u16..60)
            .prop_map(|(address, quantity)| Request::ReadInputRegisters { address, quantity }),
        (near_map(), any::<u16>())
            .prop_map(|(address, value)| Request::WriteSingleRegister { address, value }),
        (near_map(), vec(any::<u16>(), 0..60))
            .prop_map(|(address, values)| Request::WriteMultipleRegisters { address, values }),
        (near_map(), 0u16..60, near_map(), vec(any::<u16>(), 0..60)).prop_map(
            |(read_address, read_quantity, write_address, values)| {
                Request::ReadWriteMultipleRegisters {
                    read_address,
                    read_quantity,
                    write_address,
                    values,
                }
            }
        ),
        (
            select(vec![0u8, 0x80, 0x01, 0xFF]),
            any::<u8>(),
            prop_oneof![Just(1u8), any::<u8>()],
            object_index(),
            0u8..3,
            0u16..2,
            0u16..7,
            vec(any::<u8>(), 0..7),
        )
            .prop_map(
                |(control, reserved, node_id, index, subindex, offset, byte_count, data)| {
                    Request::CanOpen(CanOpenAccess {
                        control,
                        reserved,
                        node_id,
                        index,
                        subindex,
                        offset,
                        byte_count,
                        data,
                    })
                }
            ),
        (0u16..0x20, vec(any::<u8>(), 0..4))
            .prop_map(|(sub_function, data)| Request::Diagnostics { sub_function, data }),
    ]
}

/// One step of a session: a wait, then a frame.
#[derive(Clone, Debug)]
enum Frame {
    /// A typed request to an address (encoded with a valid CRC).
    Typed(u8, Request),
    /// Address + arbitrary PDU bytes with a valid CRC.
    Pdu(u8, Vec<u8>),
    /// Anything at all.
    Garbage(Vec<u8>),
}

fn frame() -> impl Strategy<Value = Frame> {
    let address = prop_oneof![Just(1u8), Just(0u8), any::<u8>()];
    prop_oneof![
        4 => (address.clone(), request()).prop_map(|(a, r)| Frame::Typed(a, r)),
        2 => (
            address,
            select(vec![0x03u8, 0x04, 0x06, 0x08, 0x10, 0x17, 0x2B, 0x01, 0x83]),
            vec(any::<u8>(), 0..260)
        )
            .prop_map(|(a, fc, rest)| {
                let mut pdu = vec![fc];
                pdu.extend(rest);
                Frame::Pdu(a, pdu)
            }),
        1 => vec(any::<u8>(), 0..300).prop_map(Frame::Garbage),
    ]
}

fn frame_bytes(f: &Frame) -> Vec<u8> {
    match f {
        Frame::Typed(a, r) => {
            rtu::encode(*a, &Pdu::Request(r.clone())).unwrap_or_else(|_| vec![*a, 0x03])
        }
        Frame::Pdu(a, pdu) => {
            let mut out = Vec::new();
            // A PDU too long to frame is sent as it is, CRC-less: garbage.
            if rtu::encode_adu(*a, pdu, &mut out).is_err() {
                out = pdu.clone();
            }
            out
        }
        Frame::Garbage(b) => b.clone(),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// Arbitrary sessions never panic the station, and every reply decodes strictly as a response to the
    /// request's address and function code.
    #[test]
    fn arbitrary_frames_never_panic_and_replies_decode(
        faults in proptest::sample::subsequence(MODEL_FAULTS.to_vec(), 0..=MODEL_FAULTS.len()),
        steps in vec((0u64..1500, frame()), 1..40),
    ) {
        let mut st = station_with(profile(), &faults);
        let mut t = 0u64;
        for (wait, f) in &steps {
            t += wait;
            let bytes = frame_bytes(f);
            if let Some(w) = st.rtu_frame(ms(t), &bytes) {
                let decoded = rtu::decode(&w.bytes, Direction::Response);
                prop_assert!(decoded.is_ok(), "reply {} to {} does not decode: {:?}",
                    hex_spaced(&w.bytes), hex_spaced(&bytes), decoded);
                if let Ok((address, Pdu::Response(r))) = decoded {
                    prop_assert_eq!(address, bytes[0]);
                    prop_assert_eq!(r.function().without_exception_bit().0, bytes[1] & 0x7F);
                }
            }
        }
    }
}

/// A station for the SD2x taking `choice` (FREEDOM=VALUE), broadcasts on.
fn station_choosing(choice: &str) -> Station {
    let mut p = profile();
    p.device.broadcast = true;
    let requirements = drives::corpus::Corpus::Embedded
        .requirements()
        .expect("requirements");
    let choices = drives::Choices::parse_all(&[choice], &requirements, &profile())
        .expect("a simulated choice");
    Station::new(
        drives::build_with(p, FaultSet::default(), choices.clone()),
        FaultSet::default(),
        UNIT,
    )
    .with_choices(choices)
}

/// The readings of `diagnostic-counter-semantics`, after one known sequence, counted by hand from each
/// reading's source text (corpus/freedoms/protocol.toml): a normal read, an exception, a frame for another
/// slave, a broadcast write and a bad CRC, then 0x0B, 0x0E and 0x0F read in that order.
#[test]
fn fc08_counter_readings_count_what_their_sources_say() {
    let counts = |choice: &str| -> [u16; 3] {
        let mut st = station_choosing(choice);
        counted_sequence(&mut st);
        [0x0B, 0x0E, 0x0F].map(|sub| {
            match send(
                &mut st,
                0,
                Request::Diagnostics {
                    sub_function: sub,
                    data: vec![0, 0],
                },
            ) {
                Response::Diagnostics { data, .. } => u16::from_be_bytes([data[0], data[1]]),
                r => panic!("{r:?}"),
            }
        })
    };
    // Standard: bus = 4 good-CRC frames + this read; slave = read, exception, broadcast, 0B, this;
    // no response = the broadcast.
    assert_eq!(counts("diagnostic-counter-semantics=standard"), [5, 5, 1]);
    // Application protocol 6.8.1, "detected": the bad CRC too.
    assert_eq!(
        counts("diagnostic-counter-semantics=bus-count-includes-bad-crc"),
        [6, 5, 1]
    );
    // Serial line guide 6.1.1, "received": the other slave's frame is a message left unanswered too.
    assert_eq!(
        counts("diagnostic-counter-semantics=no-response-includes-other-slaves"),
        [5, 5, 2]
    );
    // SD2x manual line 416, "sent by the system": read, exception, the 0B answer (not this one).
    assert_eq!(
        counts("diagnostic-counter-semantics=slave-count-is-responses-sent"),
        [5, 3, 1]
    );
    // Nowhere said whether a counter read counts itself: here it does not.
    assert_eq!(
        counts("diagnostic-counter-semantics=excludes-current-request"),
        [4, 4, 1]
    );
}
