//! The generic Modbus server model through the `Station`: every function code of `corpus/profiles/generic.toml`
//! against the MODBUS Application Protocol v1.1b3 (normal answers, 02 outside the map, 01 for what is not
//! implemented), device identification with paging, the model serving a profile it has never seen, the
//! model-level faults, RTU broadcast, and a property test that no request panics or gets an undecodable answer.
//!
//! Proptest prints the failing seed and persists it under `proptest-regressions/`; rerunning replays it.

use std::time::Duration;

use codec::{Request, Response, parse_hex, rtu};
use drives::models::generic::Generic;
use drives::profile::Profile;
use drives::{self, DriveModel, Fault, FaultSet, Station};
use proptest::collection::vec;
use proptest::prelude::*;
use proptest::sample::{select, subsequence};

use crate::support::{
    MODEL_FAULTS, Sim, ascii_hex, assert_fault_shows, both, profile, run_exchanges,
};

fn generic_profile() -> Profile {
    profile("generic")
}

/// A drive the project has no model for (tests/data/other_profile.toml): 32-bit registers, low word first, a
/// reserved hole, a read-only register, ranges, and identification objects too long for one PDU.
fn other_profile() -> Profile {
    Profile::parse("other (test)", include_str!("../data/other_profile.toml"))
        .unwrap_or_else(|e| panic!("{e}"))
}

fn zeros(n: usize) -> String {
    vec!["00"; n].join(" ")
}

#[test]
fn build_picks_the_generic_model() {
    let m = drives::build(generic_profile(), FaultSet::none());
    assert_eq!(m.profile().device.id, "generic");
    let m = drives::build(other_profile(), FaultSet::none());
    assert_eq!(m.profile().device.id, "other");
}

#[test]
fn bits() {
    let mut s = Sim::new("generic", &[]);
    assert_eq!(s.ask("01 00 00 00 0A"), "01 02 00 00");
    assert_eq!(s.ask("05 00 03 FF 00"), "05 00 03 FF 00");
    assert_eq!(s.ask("01 00 00 00 0A"), "01 02 08 00");
    assert_eq!(s.ask("0F 00 08 00 0A 02 FF 03"), "0F 00 08 00 0A");
    assert_eq!(s.ask("01 00 00 00 18"), "01 03 08 FF 03");
    assert_eq!(s.ask("05 00 03 00 00"), "05 00 03 00 00");
    assert_eq!(s.ask("01 00 03 00 01"), "01 01 00");
    assert_eq!(
        s.ask("01 00 00 00 64"),
        format!("01 0D 00 FF 03 {}", zeros(10))
    );
    assert_eq!(s.ask("02 00 00 00 64"), format!("02 0D {}", zeros(13)));
}

#[test]
fn registers() {
    let mut s = Sim::new("generic", &[]);
    assert_eq!(s.ask("03 00 00 00 03"), "03 06 00 00 00 00 00 00");
    assert_eq!(s.ask("06 00 01 12 34"), "06 00 01 12 34");
    assert_eq!(s.ask("03 00 00 00 03"), "03 06 00 00 12 34 00 00");
    assert_eq!(
        s.ask("10 00 61 00 03 06 00 01 00 02 FF FF"),
        "10 00 61 00 03"
    );
    assert_eq!(s.ask("03 00 61 00 03"), "03 06 00 01 00 02 FF FF");
    assert_eq!(
        s.ask("04 00 0A 00 02"),
        "04 04 00 0A 00 0B",
        "input registers"
    );
    assert_eq!(
        s.ask("04 00 01 00 01"),
        "04 02 00 01",
        "FC 04 does not see holding 1"
    );
    // FC 17: the write happens before the read.
    assert_eq!(
        s.ask("17 00 00 00 02 00 00 00 01 02 AB CD"),
        "17 04 AB CD 12 34"
    );
    let all = s.ask("03 00 00 00 64");
    assert!(all.starts_with("03 C8 AB CD 12 34 00 00"), "{all}");
    assert!(all.ends_with("00 01 00 02 FF FF"), "{all}");
    assert_eq!(
        parse_hex(&all).expect("hex").len(),
        2 + 200,
        "the whole map in one read"
    );
}

#[test]
fn outside_the_map_gives_02() {
    let mut drives = run_exchanges("outside_the_map_gives_02");
    let (_, s) = &mut drives[0];
    assert_eq!(
        s.ask("03 00 00 00 01"),
        "03 02 00 00",
        "the refused FC 17 wrote nothing"
    );
    assert_eq!(
        s.ask("03 00 63 00 01"),
        "03 02 00 00",
        "nor did the refused FC 10"
    );
}

#[test]
fn quantities_values_and_functions() {
    run_exchanges("quantities_values_and_functions");
}

#[test]
fn device_identification() {
    let mut s = Sim::new("generic", &[]);
    let basic = format!(
        "00 0E {} 01 07 {} 02 03 {}",
        ascii_hex("modbus-harness"),
        ascii_hex("GENERIC"),
        ascii_hex("1.0")
    );
    assert_eq!(
        s.ask("2B 0E 01 00"),
        format!("2B 0E 01 82 00 00 03 {basic}")
    );
    assert_eq!(
        s.ask("2B 0E 02 00"),
        format!(
            "2B 0E 02 82 00 00 05 {basic} 04 15 {} 05 09 {}",
            ascii_hex("Generic Modbus server"),
            ascii_hex("simulator")
        )
    );
    assert_eq!(
        s.ask("2B 0E 04 05"),
        format!("2B 0E 04 82 00 00 01 05 09 {}", ascii_hex("simulator"))
    );
    assert_eq!(s.ask("2B 0E 04 03"), "AB 02", "no object 3");
    assert_eq!(s.ask("2B 0E 06 00"), "AB 03", "no read code 6");
}

#[test]
fn device_identification_pages_with_more_follows() {
    let mut s = Sim::with(other_profile(), &[]);
    let first = s.ask("2B 0E 03 00");
    let a = ascii_hex(&"A".repeat(120));
    assert_eq!(
        first,
        format!(
            "2B 0E 03 83 FF 81 04 00 04 {} 01 01 58 02 03 {} 80 78 {a}",
            ascii_hex("ACME"),
            ascii_hex("1.0")
        ),
        "objects 0-0x80 fit; more follow from 0x81"
    );
    let second = s.ask("2B 0E 03 81");
    assert_eq!(
        second,
        format!(
            "2B 0E 03 83 00 00 02 81 78 {} 82 78 {}",
            ascii_hex(&"B".repeat(120)),
            ascii_hex(&"C".repeat(120))
        )
    );
    assert_eq!(
        s.ask("2B 0E 02 00"),
        format!(
            "2B 0E 02 83 00 00 03 00 04 {} 01 01 58 02 03 {}",
            ascii_hex("ACME"),
            ascii_hex("1.0")
        ),
        "a regular read stops at 0x7F"
    );
}

#[test]
fn any_other_profile_is_served() {
    let mut s = Sim::with(other_profile(), &[]);
    assert_eq!(
        s.ask("03 00 10 00 02"),
        "03 04 FF FE FF FF",
        "-2, low word first"
    );
    assert_eq!(
        s.ask("10 00 10 00 02 04 86 A0 00 01"),
        "10 00 10 00 02",
        "100000"
    );
    assert_eq!(s.ask("03 00 10 00 03"), "03 06 86 A0 00 01 55 AA");
    assert_eq!(s.ask("10 00 10 00 02 04 86 A1 00 01"), "90 03", "100001");
    assert_eq!(s.ask("10 00 12 00 01 02 00 00"), "90 02", "read-only");
    assert_eq!(s.ask("03 00 13 00 01"), "83 02", "reserved");
    assert_eq!(s.ask("03 00 11 00 01"), "03 02 00 01", "high word alone");
    assert_eq!(
        s.ask("10 00 11 00 01 02 00 00"),
        "90 02",
        "half a 32-bit register"
    );
    assert_eq!(s.ask("10 00 14 00 01 02 00 04"), "90 03", "Mode 4");
    assert_eq!(
        s.ask("01 00 00 00 01"),
        "81 01",
        "not in the profile's functions"
    );
}

// ---------------------------------------------------------------------------------------------------------------
// Model-level faults: the faulted server answers differently.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn fault_reserved_readable() {
    assert_fault_shows(
        &generic_profile(),
        Fault::ReservedReadable,
        &["03 00 63 00 02", "01 00 64 00 01", "06 00 64 00 01"],
        &["83 02", "81 02", "86 02"],
        &["03 04 00 00 00 00", "01 01 00", "86 02"],
    );
}

#[test]
fn fault_quantity_unchecked() {
    let (ok, bad) = both(
        &generic_profile(),
        Fault::QuantityUnchecked,
        &["03 00 00 00 00", "03 00 00 00 7E"],
    );
    assert_eq!(ok, ["83 03", "83 03"]);
    assert_eq!(bad, ["03 00", "83 02"], "126 registers run past the map");
}

#[test]
fn fault_word_order() {
    assert_fault_shows(
        &other_profile(),
        Fault::WordOrder,
        &["03 00 10 00 02"],
        &["03 04 FF FE FF FF"],
        &["03 04 FF FF FF FE"],
    );
}

#[test]
fn fault_read_only_writable() {
    assert_fault_shows(
        &other_profile(),
        Fault::ReadOnlyWritable,
        &["10 00 12 00 01 02 00 07", "03 00 12 00 01"],
        &["90 02", "03 02 55 AA"],
        &["10 00 12 00 01", "03 02 00 07"],
    );
}

#[test]
fn fault_range_unchecked() {
    assert_fault_shows(
        &other_profile(),
        Fault::RangeUnchecked,
        &["10 00 14 00 01 02 00 09", "03 00 14 00 01"],
        &["90 03", "03 02 00 01"],
        &["10 00 14 00 01", "03 02 00 09"],
    );
}

// ---------------------------------------------------------------------------------------------------------------
// RTU: addressing and broadcast through the same model.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn rtu_broadcast_writes_silently() {
    let p = generic_profile();
    let mut st = Station::new(drives::build(p, FaultSet::none()), FaultSet::none(), 1);
    let frame = |addr: u8, pdu: &str| {
        let mut f = Vec::new();
        rtu::encode_adu(addr, &parse_hex(pdu).expect("hex"), &mut f).expect("encodes");
        f
    };
    assert_eq!(
        st.rtu_frame(Duration::ZERO, &frame(0, "06 00 05 00 2A")),
        None
    );
    assert_eq!(
        st.rtu_frame(Duration::ZERO, &frame(2, "03 00 05 00 01")),
        None
    );
    let w = st
        .rtu_frame(Duration::ZERO, &frame(1, "03 00 05 00 01"))
        .expect("answer");
    assert_eq!(w.bytes, frame(1, "03 02 00 2A"));
}

#[test]
fn model_alone_answers_without_a_station() {
    let mut g = Generic::new(
        generic_profile(),
        FaultSet::none(),
        drives::Choices::reference(),
    );
    assert_eq!(
        g.handle(
            Duration::ZERO,
            1,
            &Request::ReadInputRegisters {
                address: 99,
                quantity: 1
            }
        ),
        Some(Response::ReadInputRegisters { values: vec![99] })
    );
    assert_eq!(g.bank().value(99), Some(0), "holding register 99");
}

// ---------------------------------------------------------------------------------------------------------------
// No request makes the station panic, and every answer decodes strictly.
// ---------------------------------------------------------------------------------------------------------------

const FCS: &[u8] = &[
    0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x0F, 0x10, 0x17, 0x2B, 0x41, 0x81,
];

fn pdu() -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![
        vec(any::<u8>(), 0..=260),
        (select(FCS), 0u16..110, 0u16..140, vec(any::<u8>(), 0..40)).prop_map(
            |(fc, a, q, tail)| {
                let mut p = vec![fc];
                p.extend_from_slice(&a.to_be_bytes());
                p.extend_from_slice(&q.to_be_bytes());
                p.extend(tail);
                p
            }
        ),
        (0u16..110, 1u16..30, any::<u16>()).prop_map(|(a, q, v)| {
            // A well-formed FC 16 / FC 0F pair around the end of the map.
            let mut p = vec![0x10];
            p.extend_from_slice(&a.to_be_bytes());
            p.extend_from_slice(&q.to_be_bytes());
            p.push((q * 2) as u8);
            for _ in 0..q {
                p.extend_from_slice(&v.to_be_bytes());
            }
            p
        }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]
    #[test]
    fn random_requests_never_panic_and_answers_decode(
        other in any::<bool>(),
        faults in subsequence(MODEL_FAULTS.to_vec(), 0..=MODEL_FAULTS.len()),
        pdus in vec(pdu(), 1..12),
    ) {
        let mut s = if other { Sim::with(other_profile(), &faults) } else { Sim::new("generic", &faults) };
        for (i, pdu) in pdus.iter().enumerate() {
            s.answer_decodes(i, Duration::ZERO, pdu)?;
        }
    }
}

/// A generic station (Modbus/TCP view) taking the choices `specs`.
fn sim_choosing(specs: &[&str]) -> Sim {
    let requirements = drives::corpus::Corpus::Embedded
        .requirements()
        .expect("requirements");
    let choices = drives::Choices::parse_all(specs, &requirements, &profile("generic"))
        .expect("simulated choices");
    let p = profile("generic");
    let mut sim = Sim::with(p.clone(), &[]);
    sim.station = Station::new(
        drives::build_with(p, FaultSet::default(), choices.clone()),
        FaultSet::default(),
        sim.unit,
    )
    .with_choices(choices);
    sim
}

/// `run-indicator-status=off`: FC 11 reports the run indicator 0x00, the rest as the profile declares it;
/// `event-counter-clear-counted=counted`: FC 0B after 08/0A counts the clearing request.
#[test]
fn run_indicator_and_event_counter_take_the_drives_choice() {
    let ask = |sim: &mut Sim, req: Request| {
        Response::decode(&sim.pdu(&req.to_bytes().expect("encodes"))).expect("decodes")
    };
    let server_id = |sim: &mut Sim| match ask(sim, Request::ReportServerId) {
        Response::ReportServerId { data } => data,
        r => panic!("{r:?}"),
    };
    let events_after_clear = |sim: &mut Sim| {
        ask(
            sim,
            Request::Diagnostics {
                sub_function: 0x0A,
                data: vec![0, 0],
            },
        );
        match ask(sim, Request::GetCommEventCounter) {
            Response::GetCommEventCounter { event_count, .. } => event_count,
            r => panic!("{r:?}"),
        }
    };
    let mut reference = sim_choosing(&[]);
    let mut other = sim_choosing(&[
        "run-indicator-status=off",
        "event-counter-clear-counted=counted",
    ]);
    let (on, off) = (server_id(&mut reference), server_id(&mut other));
    let at = profile("generic")
        .server_id
        .expect("server id")
        .get_ref()
        .id
        .len();
    assert_eq!((on[at], off[at]), (0xFF, 0x00));
    assert_eq!(on[..at], off[..at]);
    assert_eq!(on[at + 1..], off[at + 1..]);
    assert_eq!(events_after_clear(&mut reference), 0);
    assert_eq!(events_after_clear(&mut other), 1);
}
