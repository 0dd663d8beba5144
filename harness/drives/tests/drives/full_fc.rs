//! The full public function code set (MODBUS Application Protocol v1.1b3 section 6) on the generic model and the
//! station, over tests/data/full_fc.toml: the exchange tables of tests/data/exchanges.toml (FC 07, 08, 0B, 0C,
//! 11, 14, 15, 16, 18 over Modbus/TCP), what only an RTU line shows (listen only mode, the restart, broadcast and
//! overrun events, the FC 08 data checks), the faults of these functions against the healthy drive, and a
//! property test that no request to them panics or gets an undecodable answer.
//!
//! Proptest prints the failing seed and persists it under `proptest-regressions/`; rerunning replays it.

use std::time::Duration;

use codec::framer::{CharFormat, Parity, RtuTiming};
use codec::{Response, hex_spaced, parse_hex, rtu};
use drives::profile::Profile;
use drives::{self, Fault, FaultSet, RtuPort, Station};
use proptest::collection::vec;
use proptest::prelude::*;
use proptest::sample::{select, subsequence};

use crate::support::{Sim, ascii_hex, both, profile, run_exchanges};

fn full_fc() -> Profile {
    profile("data/full_fc")
}

#[test]
fn full_fc_read_exception_status() {
    run_exchanges("full_fc_read_exception_status");
}

#[test]
fn full_fc_mask_write_register() {
    run_exchanges("full_fc_mask_write_register");
}

#[test]
fn full_fc_read_fifo_queue() {
    run_exchanges("full_fc_read_fifo_queue");
}

#[test]
fn full_fc_file_records() {
    run_exchanges("full_fc_file_records");
}

#[test]
fn full_fc_report_server_id() {
    let sims = run_exchanges("full_fc_report_server_id");
    let (_, s) = &sims[0];
    let resp = Response::ReportServerId {
        data: parse_hex(&format!("42 FF {}", ascii_hex("full-fc"))).unwrap(),
    };
    assert_eq!(
        resp.report_server_id_parts(1),
        Some((&[0x42][..], 0xFF, &b"full-fc"[..]))
    );
    assert_eq!(s.station.profile().device.id, "full-fc");
}

#[test]
fn full_fc_diagnostics_over_tcp() {
    run_exchanges("full_fc_diagnostics_over_tcp");
}

#[test]
fn full_fc_comm_event_counter_and_log() {
    run_exchanges("full_fc_comm_event_counter_and_log");
}

/// The two largest answers: a FIFO of 31 registers (6.18) and a file read of 124 registers, a 252-byte PDU
/// (6.14: the response must fit 253 bytes).
#[test]
fn largest_fifo_and_file_answers() {
    let mut s = Sim::with(full_fc(), &[]);
    let values: Vec<String> = (1..=31).map(|v| format!("00 {v:02X}")).collect();
    assert_eq!(
        s.ask("18 03 00"),
        format!("18 00 40 00 1F {}", values.join(" "))
    );
    let answer = s.ask("14 07 06 00 06 00 00 00 7C");
    assert_eq!(answer, format!("14 FA F9 06 {}", vec!["00"; 248].join(" ")));
    assert_eq!(parse_hex(&answer).unwrap().len(), 252);
}

// ---------------------------------------------------------------------------------------------------------------
// RTU: what a serial line adds.
// ---------------------------------------------------------------------------------------------------------------

fn rtu_station(faults: &[Fault]) -> Station {
    let f = FaultSet::of(faults);
    Station::new(drives::build(full_fc(), f.clone()), f, 1)
}

/// Send `pdu` (hex) to `address` as one RTU frame; the response PDU as hex, or `None` for silence.
fn rtu_ask(st: &mut Station, address: u8, pdu: &str) -> Option<String> {
    let mut frame = Vec::new();
    rtu::encode_adu(address, &parse_hex(pdu).expect("hex"), &mut frame).expect("encodes");
    let w = st.rtu_frame(Duration::ZERO, &frame)?;
    let adu = rtu::decode_adu(&w.bytes).expect("a valid RTU answer");
    assert_eq!(adu.address, address, "address echoed");
    Some(hex_spaced(adu.pdu))
}

fn ask(st: &mut Station, pdu: &str) -> Option<String> {
    rtu_ask(st, 1, pdu)
}

fn hex(s: &str) -> Option<String> {
    Some(hex_spaced(&parse_hex(s).expect("hex")))
}

/// 08/04 (6.8.1): no response, and none to anything after it; messages are monitored (receive events with
/// bit 5), not processed; only 08/01 (with valid data) brings the port back, silently, keeping the log on 00 00
/// and clearing the counters (6.9: the event counter too).
#[test]
fn listen_only_until_restart() {
    let mut st = rtu_station(&[]);
    assert_eq!(ask(&mut st, "03 00 00 00 01"), hex("03 02 00 00"));
    assert_eq!(ask(&mut st, "08 00 04 00 00"), None, "no response to 08/04");
    assert!(st.comm_state().listen_only);
    assert_eq!(ask(&mut st, "03 00 00 00 01"), None);
    assert_eq!(ask(&mut st, "06 00 00 00 05"), None, "not processed");
    assert_eq!(ask(&mut st, "08 00 01 12 34"), None, "bad restart data");
    assert!(st.comm_state().listen_only, "an invalid restart is ignored");
    assert_eq!(ask(&mut st, "08 00 0B 00 00"), None);
    assert_eq!(
        ask(&mut st, "08 00 01 00 00"),
        None,
        "no response to a listening port's restart"
    );
    assert!(!st.comm_state().listen_only);
    assert_eq!(
        ask(&mut st, "03 00 00 00 01"),
        hex("03 02 00 00"),
        "the write was not applied"
    );
    // Most recent first: this request's receive event, the read's send and receive events, the restart (00),
    // five monitored messages (A0), 08/04's send event in listen only mode (60), "entered listen only" (04),
    // 08/04's receive event, the first read's send and receive events. Event count 1 and message count 2: the
    // restart cleared both.
    assert_eq!(
        ask(&mut st, "0C"),
        hex("0C 14 00 00 00 01 00 02 80 40 80 00 A0 A0 A0 A0 A0 60 04 80 40 80")
    );
    assert_eq!(ask(&mut st, "08 00 0E 00 00"), hex("08 00 0E 00 03"));
}

/// 08/01 outside listen only mode is echoed before the restart; FF 00 clears the log (6.8.1), which then holds
/// the restart event (6.10).
#[test]
fn restart_with_ff00_clears_the_log() {
    let mut st = rtu_station(&[]);
    assert_eq!(ask(&mut st, "03 00 00 00 01"), hex("03 02 00 00"));
    assert_eq!(ask(&mut st, "08 00 01 FF 00"), hex("08 00 01 FF 00"));
    assert_eq!(ask(&mut st, "0C"), hex("0C 08 00 00 00 00 00 01 80 00"));
    assert_eq!(ask(&mut st, "08 00 0B 00 00"), hex("08 00 0B 00 02"));
    assert_eq!(
        ask(&mut st, "08 00 02 00 00"),
        hex("08 00 02 12 34"),
        "power-up value"
    );
}

/// A broadcast is logged with bit 6 of its receive event, completes (the event counter counts it) and gets no
/// response.
#[test]
fn broadcast_events() {
    let mut st = rtu_station(&[]);
    assert_eq!(rtu_ask(&mut st, 0, "06 00 01 00 07"), None);
    assert_eq!(ask(&mut st, "0C"), hex("0C 09 00 00 00 01 00 02 80 40 C0"));
    assert_eq!(ask(&mut st, "03 00 01 00 01"), hex("03 02 00 07"));
    assert_eq!(
        ask(&mut st, "08 00 0F 00 00"),
        hex("08 00 0F 00 01"),
        "no response"
    );
}

/// On a serial line an answer keeps t3.5 of silence after the request's last byte (serial line guide 2.5.1.1),
/// also when the framer cut the request by its length at once; over TCP (RTU over TCP) there is no line, and
/// the carrier's 50 ms frame-ending silence must not hold the answer back.
#[test]
fn answer_silence_on_a_line_and_none_over_tcp() {
    let mut frame = Vec::new();
    rtu::encode_adu(1, &parse_hex("03 00 00 00 01").expect("hex"), &mut frame).expect("encodes");
    let line = RtuTiming::new(
        19200,
        CharFormat {
            parity: Parity::Even,
            stop_bits: 1,
        },
    );
    for (timing, silence) in [
        (line, line.t3_5),
        (RtuTiming::tcp_carrier(), Duration::ZERO),
    ] {
        let mut st = rtu_station(&[]);
        let mut port = RtuPort::new(timing);
        let replies = st.serve_rtu(Duration::from_millis(5), &mut port, &frame);
        assert_eq!(
            replies.len(),
            1,
            "{timing:?}: one answer, cut by its length"
        );
        assert_eq!(replies[0].delay, silence, "{timing:?}");
    }
}

/// More bytes than an ADU without a boundary is a character overrun (08/12, receive event bit 4); 08/14 clears
/// the counter, not the CRC error count.
#[test]
fn overrun_counted_and_cleared() {
    let mut st = rtu_station(&[]);
    let mut port = RtuPort::new(RtuTiming::new(
        19200,
        CharFormat {
            parity: Parity::Even,
            stop_bits: 1,
        },
    ));
    assert!(
        st.serve_rtu(Duration::ZERO, &mut port, &[0u8; 257])
            .is_empty()
    );
    assert!(st.comm_state().overrun_flag);
    assert_eq!(ask(&mut st, "08 00 12 00 00"), hex("08 00 12 00 01"));
    assert_eq!(ask(&mut st, "08 00 0C 00 00"), hex("08 00 0C 00 01"));
    assert_eq!(
        ask(&mut st, "0C"),
        hex("0C 0C 00 00 00 02 00 03 80 40 80 40 80 90"),
        "the overrun's receive event (90) first in time"
    );
    assert_eq!(ask(&mut st, "08 00 14 00 00"), hex("08 00 14 00 00"));
    assert!(!st.comm_state().overrun_flag);
    assert_eq!(ask(&mut st, "08 00 12 00 00"), hex("08 00 12 00 00"));
    assert_eq!(ask(&mut st, "08 00 0C 00 00"), hex("08 00 0C 00 01"));
}

/// With `check_data`, each sub-function's data field is the one 6.8.1 gives (figure 18: else 03); 08/03 takes
/// CHAR 00.
#[test]
fn diagnostic_data_checked() {
    let mut st = rtu_station(&[]);
    assert_eq!(ask(&mut st, "08 00 01 12 34"), hex("88 03"));
    assert_eq!(ask(&mut st, "08 00 03 3A 01"), hex("88 03"));
    assert_eq!(ask(&mut st, "08 00 03 3A 00"), hex("08 00 03 3A 00"));
    assert_eq!(st.comm_state().ascii_delimiter, b':');
    assert_eq!(ask(&mut st, "08 00 04 00 01"), hex("88 03"));
    assert_eq!(
        ask(&mut st, "03 00 00 00 01"),
        hex("03 02 00 00"),
        "not listening"
    );
    assert_eq!(
        ask(&mut st, "08 00 0E 00 00 00"),
        hex("88 03"),
        "3 data bytes"
    );
    assert_eq!(
        ask(&mut st, "08 00 00 01 02 03"),
        hex("08 00 00 01 02 03"),
        "00 echoes any data"
    );
    assert_eq!(ask(&mut st, "08 00 0D 00 00"), hex("08 00 0D 00 04"));
}

// ---------------------------------------------------------------------------------------------------------------
// Faults: each changes the answer to the request that reveals it; the healthy drive gives the spec's answer.
// ---------------------------------------------------------------------------------------------------------------

/// (fault, requests before, the revealing request, healthy answer, faulty answer).
const WITNESSES: &[(Fault, &[&str], &str, &str, &str)] = &[
    (Fault::ExceptionStatusReversed, &[], "07", "07 60", "07 06"),
    (
        Fault::EventCounterCountsExceptions,
        &["03 00 64 00 01"],
        "0B",
        "0B 00 00 00 00",
        "0B 00 00 00 01",
    ),
    (
        Fault::EventLogOldestFirst,
        &["03 00 00 00 01", "03 00 64 00 01"],
        "0C",
        "0C 0B 00 00 00 01 00 00 80 41 80 40 80",
        "0C 0B 00 00 00 01 00 00 80 40 80 41 80",
    ),
    (
        Fault::RunIndicatorOne,
        &[],
        "11",
        "11 09 42 FF 66 75 6C 6C 2D 66 63",
        "11 09 42 01 66 75 6C 6C 2D 66 63",
    ),
    (
        Fault::FileRecordLengthWrong,
        &[],
        "14 07 06 00 04 00 01 00 02",
        "14 06 05 06 0D FE 00 20",
        "14 06 04 06 0D FE 00 20",
    ),
    (
        Fault::FileWriteFirstOnly,
        &["15 14 06 00 03 00 00 00 01 AA AA 06 00 04 00 05 00 02 BB BB CC CC"],
        "14 07 06 00 04 00 05 00 02",
        "14 06 05 06 BB BB CC CC",
        "14 06 05 06 00 00 00 00",
    ),
    (
        Fault::MaskWriteWrong,
        &["06 00 04 00 12", "16 00 04 00 F2 00 25"],
        "03 00 04 00 01",
        "03 02 00 17",
        "03 02 00 37",
    ),
    (
        Fault::FifoOffByOne,
        &[],
        "18 04 DE",
        "18 00 06 00 02 01 B8 12 84",
        "18 00 04 00 01 01 B8",
    ),
];

#[test]
fn each_fault_changes_the_answer_that_reveals_it() {
    let p = full_fc();
    let mut wrong = Vec::new();
    for (fault, before, reveal, healthy, faulty) in WITNESSES {
        let pdus: Vec<&str> = before.iter().copied().chain([*reveal]).collect();
        let (ok, bad) = both(&p, *fault, &pdus);
        let (ok, bad) = (ok.last().unwrap(), bad.last().unwrap());
        if ok != &crate::support::hex(healthy) || bad != &crate::support::hex(faulty) {
            wrong.push(format!(
                "{fault}: {reveal} answered {ok} healthy (want {healthy}), {bad} faulty (want {faulty})"
            ));
        }
    }
    assert!(wrong.is_empty(), "{wrong:#?}");
}

/// The faulty FC 14 answer is malformed: an even file response length (the strict decoder says where).
#[test]
fn file_record_length_fault_is_malformed() {
    let (ok, bad) = both(
        &full_fc(),
        Fault::FileRecordLengthWrong,
        &["14 0E 06 00 04 00 01 00 02 06 00 03 00 09 00 02"],
    );
    assert!(Response::decode(&parse_hex(&ok[0]).unwrap()).is_ok());
    let e = Response::decode(&parse_hex(&bad[0]).unwrap()).unwrap_err();
    assert_eq!(e.offset, 2, "{e}");
}

/// `listen-only-ignored`: 08/04 is echoed and the drive keeps answering (only a serial line shows it).
#[test]
fn listen_only_ignored_fault() {
    let mut ok = rtu_station(&[]);
    let mut bad = rtu_station(&[Fault::ListenOnlyIgnored]);
    assert_eq!(ask(&mut ok, "08 00 04 00 00"), None);
    assert_eq!(ask(&mut bad, "08 00 04 00 00"), hex("08 00 04 00 00"));
    assert_eq!(ask(&mut ok, "03 00 00 00 01"), None);
    assert_eq!(ask(&mut bad, "03 00 00 00 01"), hex("03 02 00 00"));
}

/// The new faults change nothing for a profile that does not declare these functions (the generic profile
/// with its declarations of FC 07-18 and their tables taken out).
#[test]
fn new_faults_leave_the_plain_generic_server_alone() {
    let mut p = profile("generic");
    p.functions
        .retain(|f| ![0x07u8, 0x08, 0x0B, 0x0C, 0x11, 0x14, 0x15, 0x16, 0x18].contains(&f.code.0));
    p.diagnostics.clear();
    p.exception_status = None;
    p.server_id = None;
    p.files.clear();
    p.fifos.clear();
    for fault in [
        Fault::ExceptionStatusReversed,
        Fault::ListenOnlyIgnored,
        Fault::EventCounterCountsExceptions,
        Fault::EventLogOldestFirst,
        Fault::RunIndicatorOne,
        Fault::FileRecordLengthWrong,
        Fault::FileWriteFirstOnly,
        Fault::MaskWriteWrong,
        Fault::FifoOffByOne,
    ] {
        let pdus = [
            "07",
            "0B",
            "0C",
            "11",
            "14 07 06 00 04 00 01 00 02",
            "16 00 04 00 F2 00 25",
            "18 04 DE",
            "03 00 00 00 02",
        ];
        let (ok, bad) = both(&p, fault, &pdus);
        assert_eq!(ok, bad, "{fault}");
    }
}

// ---------------------------------------------------------------------------------------------------------------
// No request to these functions makes the station panic, and every answer decodes strictly.
// ---------------------------------------------------------------------------------------------------------------

/// The new faults except `file-record-length-wrong`, whose answers are malformed on purpose.
const DECODABLE_FAULTS: &[Fault] = &[
    Fault::ExceptionStatusReversed,
    Fault::ListenOnlyIgnored,
    Fault::EventCounterCountsExceptions,
    Fault::EventLogOldestFirst,
    Fault::RunIndicatorOne,
    Fault::FileWriteFirstOnly,
    Fault::MaskWriteWrong,
    Fault::FifoOffByOne,
    Fault::ReadOnlyWritable,
    Fault::QuantityUnchecked,
];

fn request() -> impl Strategy<Value = Vec<u8>> {
    let sub_request = (select(vec![6u8, 6, 6, 7]), 0u16..8, 0u16..12, 0u16..14);
    prop_oneof![
        select(vec![0x07u8, 0x0B, 0x0C, 0x11]).prop_map(|fc| vec![fc]),
        (
            select(vec![
                0x00u16, 0x01, 0x02, 0x03, 0x04, 0x0A, 0x0B, 0x0D, 0x10, 0x12, 0x14, 0x15
            ]),
            any::<u16>()
        )
            .prop_map(|(sub, data)| {
                let mut p = vec![0x08];
                p.extend_from_slice(&sub.to_be_bytes());
                p.extend_from_slice(&data.to_be_bytes());
                p
            }),
        (0u16..16, any::<u16>(), any::<u16>()).prop_map(|(a, and, or)| {
            let mut p = vec![0x16];
            for v in [a, and, or] {
                p.extend_from_slice(&v.to_be_bytes());
            }
            p
        }),
        select(vec![0x04DEu16, 0x0100, 0x0200, 0x0300, 0x0000]).prop_map(|a| {
            let mut p = vec![0x18];
            p.extend_from_slice(&a.to_be_bytes());
            p
        }),
        vec(sub_request.clone(), 0..5).prop_map(|subs| {
            let mut p = vec![0x14, (7 * subs.len()) as u8];
            for (t, f, r, n) in subs {
                p.push(t);
                for v in [f, r, n] {
                    p.extend_from_slice(&v.to_be_bytes());
                }
            }
            p
        }),
        vec(sub_request, 0..4).prop_map(|subs| {
            let mut body = Vec::new();
            for (t, f, r, n) in subs {
                body.push(t);
                for v in [f, r, n] {
                    body.extend_from_slice(&v.to_be_bytes());
                }
                for i in 0..n {
                    body.extend_from_slice(&i.to_be_bytes());
                }
            }
            let mut p = vec![0x15, body.len() as u8];
            p.extend(body);
            p
        }),
        vec(any::<u8>(), 0..40).prop_map(|mut tail| {
            tail.insert(0, 0x14);
            tail
        }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]
    #[test]
    fn random_requests_to_the_new_functions_never_panic_and_answers_decode(
        faults in subsequence(DECODABLE_FAULTS.to_vec(), 0..=3),
        pdus in vec(request(), 1..16),
    ) {
        let mut s = Sim::with(full_fc(), &faults);
        for (i, pdu) in pdus.iter().enumerate() {
            s.answer_decodes(i, Duration::ZERO, pdu)?;
        }
    }
}
