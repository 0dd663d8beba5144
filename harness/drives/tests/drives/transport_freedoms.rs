//! The station takes the freedoms of the wire side as chosen (`--choose`): the Modbus/TCP unit ids it
//! ignores or refuses, the order and the Server Busy of pipelined answers, MBAP lengths that disagree with the
//! PDU, PDUs over 253 bytes, truncated PDUs, the exception check order and the answers of a gateway in front
//! of a drive without Modbus/TCP. Each test compares the chosen drive with the reference drive on the same
//! bytes, and checks the freedom is recorded as the decision.

use std::time::Duration;

use codec::{hex_spaced, rtu, tcp};
use drives::choices::{ChoiceError, ids};
use drives::corpus::Corpus;
use drives::station::TcpOutput;
use drives::{Choices, Station, TcpConn};

use super::support::profile;

/// A station of the corpus profile `stem` taking `choose` (`FREEDOM=VALUE`).
fn station(stem: &str, choose: &[&str]) -> Station {
    super::support::chosen_station(stem, choose)
}

/// `bytes` served once by the reference drive, which refuses them (exception 03), and by drives choosing
/// `FREEDOM=silence` (no answer) and `FREEDOM=close` (no answer, the connection closed): the three stations,
/// for what the test looks at next.
fn refused_silent_or_closed(freedom: &str, bytes: &[u8]) -> (Station, Station, Station) {
    let mut reference = station("mdrive", &[]);
    assert_eq!(
        serve(&mut reference, bytes),
        (vec![(1, "83 03".into())], false)
    );
    let mut silent = station("mdrive", &[&format!("{freedom}=silence")]);
    assert_eq!(serve(&mut silent, bytes), (vec![], false));
    let mut closing = station("mdrive", &[&format!("{freedom}=close")]);
    assert_eq!(serve(&mut closing, bytes), (vec![], true));
    (reference, silent, closing)
}

/// A Modbus/TCP ADU.
fn adu(tid: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    tcp::encode_adu(tid, unit, pdu, &mut out).expect("encodes");
    out
}

/// An ADU whose MBAP length is off by `delta`.
fn adu_length(tid: u16, unit: u8, pdu: &[u8], delta: i16) -> Vec<u8> {
    let mut out = adu(tid, unit, pdu);
    let len = u16::from_be_bytes([out[4], out[5]]).wrapping_add_signed(delta);
    out[4..6].copy_from_slice(&len.to_be_bytes());
    out
}

/// Feed `bytes` on `conn`: the replies (transaction id, PDU as hex) and whether the connection was closed.
fn feed(s: &mut Station, conn: &mut TcpConn, bytes: &[u8]) -> (Vec<(u16, String)>, bool) {
    let TcpOutput { replies, close } = s.serve_tcp(Duration::ZERO, conn, bytes);
    let replies = replies
        .iter()
        .map(|w| {
            (
                u16::from_be_bytes([w.bytes[0], w.bytes[1]]),
                hex_spaced(&w.bytes[tcp::MBAP_LEN..]),
            )
        })
        .collect();
    (replies, close)
}

/// Feed `bytes` on a new connection.
fn serve(s: &mut Station, bytes: &[u8]) -> (Vec<(u16, String)>, bool) {
    feed(s, &mut TcpConn::default(), bytes)
}

/// A read of the MDrive's holding registers 0x008B-0x008C (VM, a 32-bit register).
const READ: &[u8] = &[0x03, 0x00, 0x8B, 0x00, 0x02];

fn unit(stem: &str) -> u8 {
    profile(stem).device.default_unit
}

#[test]
fn tcp_unit_ids_silence_ignores_the_listed_units_but_not_its_own_nor_0_and_ff() {
    let own = unit("mdrive");
    let mut reference = station("mdrive", &[]);
    let mut chosen = station("mdrive", &["tcp-unit-ids=silence"]);
    let other = if own == 247 { 1 } else { 247 };
    assert_eq!(serve(&mut reference, &adu(1, other, READ)).0.len(), 1);
    assert_eq!(serve(&mut chosen, &adu(1, other, READ)), (vec![], false));
    assert!(chosen.take_decisions().contains(&ids::TCP_UNIT_IDS));
    // Every unit id of the freedom's range (`units = [1, 254]`), not only its ends.
    let inside = if own == 100 { 101 } else { 100 };
    assert_eq!(serve(&mut reference, &adu(1, inside, READ)).0.len(), 1);
    assert_eq!(serve(&mut chosen, &adu(1, inside, READ)), (vec![], false));
    // 248-254 (reserved on a serial line) too: a drive that ignores other ids ignores those.
    assert_eq!(serve(&mut reference, &adu(1, 250, READ)).0.len(), 1);
    assert_eq!(serve(&mut chosen, &adu(1, 250, READ)), (vec![], false));
    for u in [own, 0, 0xFF] {
        assert_eq!(
            serve(&mut chosen, &adu(2, u, READ)).0.len(),
            1,
            "unit {u} answered"
        );
    }
}

#[test]
fn pipelined_response_order_transaction_id_answers_last_first() {
    let u = unit("mdrive");
    let two = [adu(1, u, READ), adu(2, u, READ)].concat();
    let mut reference = station("mdrive", &[]);
    let mut chosen = station("mdrive", &["pipelined-response-order=transaction-id"]);
    let tids = |r: (Vec<(u16, String)>, bool)| r.0.iter().map(|(t, _)| *t).collect::<Vec<_>>();
    assert_eq!(tids(serve(&mut reference, &two)), [1, 2]);
    assert_eq!(tids(serve(&mut chosen, &two)), [2, 1]);
    assert!(
        chosen
            .take_decisions()
            .contains(&ids::PIPELINED_RESPONSE_ORDER)
    );
}

#[test]
fn pipelined_server_busy_exception_06_for_the_requests_behind_the_first() {
    let u = unit("mdrive");
    let three = [adu(1, u, READ), adu(2, u, READ), adu(3, u, READ)].concat();
    let mut reference = station("mdrive", &[]);
    let mut chosen = station("mdrive", &["pipelined-server-busy=exception-06"]);
    let (r, _) = serve(&mut reference, &three);
    let (c, _) = serve(&mut chosen, &three);
    assert!(r.iter().all(|(_, pdu)| pdu.starts_with("03 04")), "{r:?}");
    assert_eq!(c[0], r[0]);
    assert_eq!(c[1..], [(2, "83 06".to_string()), (3, "83 06".to_string())]);
    assert_eq!(chosen.counters().busy, 2);
    assert!(
        chosen
            .take_decisions()
            .contains(&ids::PIPELINED_SERVER_BUSY)
    );
    // One request at a time is served.
    assert_eq!(serve(&mut chosen, &adu(4, u, READ)).0[0].1, r[0].1);
}

#[test]
fn truncated_pdu_silence_or_close_on_tcp_and_silence_on_rtu() {
    let u = unit("mdrive");
    let short = adu(1, u, &[0x03, 0x00, 0x01]);
    let (mut reference, mut silent, mut closing) =
        refused_silent_or_closed("truncated-pdu", &short);
    assert!(reference.take_decisions().contains(&ids::TRUNCATED_PDU));
    assert!(silent.take_decisions().contains(&ids::TRUNCATED_PDU));
    // An RTU line has no connection: the drive chosen `close` keeps silent there.
    let mut frame = Vec::new();
    rtu::encode_adu(u, &[0x03, 0x00, 0x01], &mut frame).expect("encodes");
    assert!(reference.rtu_frame(Duration::ZERO, &frame).is_some());
    assert!(closing.rtu_frame(Duration::ZERO, &frame).is_none());
    assert!(silent.rtu_frame(Duration::ZERO, &frame).is_none());
}

#[test]
fn truncated_pdu_close_is_refused_for_a_drive_without_modbus_tcp() {
    let requirements = Corpus::Embedded.requirements().expect("requirements");
    let sd2x = profile("sd2x");
    assert!(matches!(
        Choices::parse_all(&["truncated-pdu=close"], &requirements, &sd2x),
        Err(ChoiceError::NotSimulated { .. })
    ));
    assert!(Choices::parse_all(&["truncated-pdu=silence"], &requirements, &sd2x).is_ok());
}

#[test]
fn mbap_length_short_refused_ignored_or_closed() {
    let u = unit("mdrive");
    // The MBAP length one short, the PDU's last byte right behind it.
    let bytes = adu_length(1, u, READ, -1);
    let (mut reference, _, _) = refused_silent_or_closed("mbap-length-short", &bytes);
    assert!(reference.take_decisions().contains(&ids::MBAP_LENGTH_SHORT));
    // The MBAP length's freedom decides there, not the truncated PDU's.
    let mut truncated_silent = station("mdrive", &["truncated-pdu=silence"]);
    assert_eq!(
        serve(&mut truncated_silent, &bytes),
        (vec![(1, "83 03".into())], false)
    );
    let decided = truncated_silent.take_decisions();
    assert!(decided.contains(&ids::MBAP_LENGTH_SHORT));
    assert!(!decided.contains(&ids::TRUNCATED_PDU));
}

#[test]
fn mbap_length_long_waits_closes_or_refuses_and_skips_the_bytes_announced() {
    let u = unit("mdrive");
    let bytes = adu_length(1, u, READ, 1);
    let next = adu(2, u, READ);
    let mut reference = station("mdrive", &[]);
    assert_eq!(serve(&mut reference, &bytes), (vec![], false));
    assert!(reference.take_decisions().contains(&ids::MBAP_LENGTH_LONG));
    let mut closing = station("mdrive", &["mbap-length-long=close"]);
    assert_eq!(serve(&mut closing, &bytes), (vec![], true));
    let mut refusing = station("mdrive", &["mbap-length-long=exception-03"]);
    let mut conn = TcpConn::default();
    assert_eq!(
        feed(&mut refusing, &mut conn, &bytes),
        (vec![(1, "83 03".into())], false)
    );
    // The byte the MBAP length still announced is skipped; the next request is served.
    let (replies, _) = feed(&mut refusing, &mut conn, &[&[0xAA][..], &next].concat());
    assert_eq!(replies.len(), 1);
    assert_eq!(replies[0].0, 2);
    assert!(replies[0].1.starts_with("03 04"), "{replies:?}");
}

#[test]
fn pdu_over_253_closed_skipped_or_refused() {
    let u = unit("mdrive");
    // MBAP length 255: a 254-byte PDU, framed by hand.
    let mut big = vec![0x00, 0x01, 0x00, 0x00, 0x00, 0xFF, u];
    big.extend(std::iter::repeat_n(0x03, 254));
    let next = adu(2, u, READ);
    let mut reference = station("mdrive", &[]);
    assert_eq!(serve(&mut reference, &big), (vec![], true));
    assert!(reference.take_decisions().contains(&ids::PDU_OVER_253));
    let mut silent = station("mdrive", &["pdu-over-253=silence"]);
    let (replies, close) = serve(&mut silent, &[big.clone(), next.clone()].concat());
    assert!(!close);
    assert_eq!(replies.iter().map(|r| r.0).collect::<Vec<_>>(), [2]);
    let mut refusing = station("mdrive", &["pdu-over-253=exception-03"]);
    let (replies, close) = serve(&mut refusing, &[big, next].concat());
    assert!(!close);
    assert_eq!(replies[0], (1, "83 03".to_string()));
    assert_eq!(replies[1].0, 2);
}

#[test]
fn exception_check_order_2_checks_the_address_before_the_quantity() {
    let u = unit("mdrive");
    // FC 01 at address 0 (no MDrive output there) with quantity 0: both wrong.
    let both = adu(1, u, &[0x01, 0x00, 0x00, 0x00, 0x00]);
    // Quantity 0 at an output (0x004B): only the quantity wrong.
    let quantity = adu(2, u, &[0x01, 0x00, 0x4B, 0x00, 0x00]);
    let mut reference = station("mdrive", &[]);
    let mut chosen = station("mdrive", &["exception-check-order=2"]);
    assert_eq!(serve(&mut reference, &both).0, [(1, "81 03".to_string())]);
    assert!(
        reference
            .take_decisions()
            .contains(&ids::EXCEPTION_CHECK_ORDER)
    );
    assert_eq!(serve(&mut chosen, &both).0, [(1, "81 02".to_string())]);
    assert!(
        chosen
            .take_decisions()
            .contains(&ids::EXCEPTION_CHECK_ORDER)
    );
    assert_eq!(serve(&mut chosen, &quantity).0, [(2, "81 03".to_string())]);
    assert!(
        !chosen
            .take_decisions()
            .contains(&ids::EXCEPTION_CHECK_ORDER)
    );
}

/// FC 05 with a value neither 0xFF00 nor 0x0000 to an address that is no coil: 6.5's diagram tests the value
/// first (03, the reference), 4.5 the address (02; libmodbus 3.1.6 does, and an LMD built on it answered 02).
#[test]
fn exception_check_order_2_checks_a_coil_address_before_the_value() {
    let u = unit("lmd");
    // FC 05 at 0x0100 (the LMD's outputs are 0x0000-0x0003) with the value 0x1234: both wrong.
    let both = adu(1, u, &[0x05, 0x01, 0x00, 0x12, 0x34]);
    // The same value at output 1: only the value wrong.
    let value = adu(2, u, &[0x05, 0x00, 0x00, 0x12, 0x34]);
    let mut reference = station("lmd", &[]);
    let mut chosen = station("lmd", &["exception-check-order=2"]);
    assert_eq!(serve(&mut reference, &both).0, [(1, "85 03".to_string())]);
    assert!(
        reference
            .take_decisions()
            .contains(&ids::EXCEPTION_CHECK_ORDER)
    );
    assert_eq!(serve(&mut chosen, &both).0, [(1, "85 02".to_string())]);
    assert!(
        chosen
            .take_decisions()
            .contains(&ids::EXCEPTION_CHECK_ORDER)
    );
    assert_eq!(serve(&mut chosen, &value).0, [(2, "85 03".to_string())]);
    assert!(
        !chosen
            .take_decisions()
            .contains(&ids::EXCEPTION_CHECK_ORDER)
    );
}

/// FC 23 carries two ranges (App 6.17): a read range past the map with a write quantity of 0 is wrong in
/// both, and the order of the checks is the drive's as for the other functions; a write range past the map
/// with a read quantity over 125 too. Only the quantity wrong: 03 whatever the order.
#[test]
fn exception_check_order_covers_both_ranges_of_fc_23() {
    let u = unit("generic");
    // Read 1 register at 200 (past the generic map's 100), write none at 0.
    let read_past = adu(
        1,
        u,
        &[0x17, 0x00, 0xC8, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00],
    );
    // Read 126 registers at 0, write 1 at 200.
    let write_past = adu(
        2,
        u,
        &[
            0x17, 0x00, 0x00, 0x00, 0x7E, 0x00, 0xC8, 0x00, 0x01, 0x02, 0x00, 0x01,
        ],
    );
    // Read 1 at 0, write none at 0: the quantity alone.
    let quantity = adu(
        3,
        u,
        &[0x17, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00],
    );
    for (bytes, tid) in [(&read_past, 1), (&write_past, 2)] {
        let mut reference = station("generic", &[]);
        let mut chosen = station("generic", &["exception-check-order=2"]);
        assert_eq!(serve(&mut reference, bytes).0, [(tid, "97 03".to_string())]);
        assert!(
            reference
                .take_decisions()
                .contains(&ids::EXCEPTION_CHECK_ORDER)
        );
        assert_eq!(serve(&mut chosen, bytes).0, [(tid, "97 02".to_string())]);
        assert!(
            chosen
                .take_decisions()
                .contains(&ids::EXCEPTION_CHECK_ORDER)
        );
    }
    let mut chosen = station("generic", &["exception-check-order=2"]);
    assert_eq!(serve(&mut chosen, &quantity).0, [(3, "97 03".to_string())]);
    assert!(
        !chosen
            .take_decisions()
            .contains(&ids::EXCEPTION_CHECK_ORDER)
    );
}

/// An FC 0x41 one byte too long is refused (03) by the reference; where its mnemonic is one the drive may not
/// know (none of the profile's, or MU, which an MDrive Plus2 lacks), a drive that looks the mnemonic up first
/// answers as to an unknown mnemonic: the freedom `unknown-mnemonic-exception` decides the code. Not for a
/// mnemonic every product has (S1).
#[test]
fn a_malformed_vendor_read_of_a_mnemonic_the_drive_may_lack_leaves_the_code_open() {
    let u = unit("mdrive");
    for (mnemonic, open) in [(b"  UM", true), (b"  QQ", true), (b"  1S", false)] {
        let mut s = station("mdrive", &[]);
        let mut pdu = vec![0x41];
        pdu.extend_from_slice(mnemonic);
        pdu.push(0x00);
        let (replies, _) = serve(&mut s, &adu(1, u, &pdu));
        assert_eq!(replies[0].1, "C1 03", "{mnemonic:?}");
        assert_eq!(
            s.take_decisions().contains(&ids::UNKNOWN_MNEMONIC),
            open,
            "{mnemonic:?}"
        );
    }
}

/// A station whose decisions nobody takes (`simulate`'s, the drive under test of a `sim:` target) drops
/// them input by input, its model's too; an observed one (the oracle's reference) keeps every one until
/// taken. Before, the served station kept them all: `simulate` grew without bound under a long campaign.
#[test]
fn a_station_whose_decisions_nobody_takes_keeps_only_the_last_inputs() {
    use codec::{Mnemonic, Request};
    let own = unit("mdrive");
    let other = if own == 100 { 101 } else { 100 };
    let vendor_read = Request::VendorRead {
        mnemonic: Mnemonic::from_name("P").expect("mnemonic"),
    }
    .to_bytes()
    .expect("encodes");
    let mut observed = station("mdrive", &["tcp-unit-ids=silence"]);
    let mut served = station("mdrive", &["tcp-unit-ids=silence"]).forgetting_decisions();
    for tid in 0..500 {
        for s in [&mut observed, &mut served] {
            serve(s, &adu(tid, other, READ));
            serve(s, &adu(tid, own, &vendor_read));
        }
    }
    let kept = observed.take_decisions();
    assert_eq!(
        kept.iter().filter(|d| **d == ids::TCP_UNIT_IDS).count(),
        500
    );
    // The model's own decisions (the FC 0x41 read's fields) are kept too.
    assert!(kept.len() > 1000, "{}", kept.len());
    let last = served.take_decisions();
    assert!(!last.is_empty() && last.len() < 10, "{last:?}");
    assert!(!last.contains(&ids::TCP_UNIT_IDS), "{last:?}");
}

/// `tcp-unit-ids=exception-0B` (`exception-0A`): a request to another unit id is refused as a gateway
/// refuses a unit with no device behind it (App 7), with the request's function code and the unit id
/// echoed; the station's own unit, 0 and 0xFF are still answered. The refusal is not the drive's: it changes
/// nothing a later request of the drive's own unit sees.
#[test]
fn tcp_unit_ids_exception_refuses_other_units_as_a_gateway_does() {
    let own = unit("mdrive");
    let other = if own == 247 { 1 } else { 247 };
    for (choice, code) in [("exception-0B", "0B"), ("exception-0A", "0A")] {
        let mut chosen = station("mdrive", &[&format!("tcp-unit-ids={choice}")]);
        let TcpOutput { replies, close } = chosen.serve_tcp(
            Duration::ZERO,
            &mut TcpConn::default(),
            &adu(9, other, READ),
        );
        assert!(!close);
        let [reply] = replies.as_slice() else {
            panic!("{choice}: one reply expected, got {replies:?}");
        };
        assert_eq!(
            hex_spaced(&reply.bytes),
            format!("00 09 00 00 00 03 {other:02X} 83 {code}"),
            "{choice}: the gateway's exception, transaction and unit id echoed"
        );
        assert!(chosen.take_decisions().contains(&ids::TCP_UNIT_IDS));
        for u in [own, 0, 0xFF] {
            let (r, _) = serve(&mut chosen, &adu(2, u, READ));
            assert_eq!(r.len(), 1, "{choice}: unit {u} answered");
            assert!(!r[0].1.starts_with("83"), "{choice}: unit {u}: {:?}", r[0]);
        }
    }
}

/// A drive that speaks only Modbus RTU (the SD2x) reached over Modbus/TCP is behind a gateway. Where the
/// drive is silent (a unit id that is no serial address, a broadcast, a truncated PDU it chose to ignore),
/// `gateway-no-response=exception-0B` (`exception-0A`) answers with the request's function code; the
/// reference (silence) answers nothing; every such silence is recorded as the freedom's decision. Where the
/// drive answers, the drive's answer goes out; a foreign protocol id is still discarded (the gateway's own
/// MBAP check); and a drive with Modbus/TCP (the MDrive) is no gateway: its silences stay silent.
#[test]
fn a_drive_without_modbus_tcp_answers_its_silences_as_its_gateway_chose() {
    let own = unit("sd2x");
    let echo: &[u8] = &[0x08, 0x00, 0x00, 0x12, 0x34];
    let truncated: &[u8] = &[0x03, 0x00];
    for (choice, code) in [("exception-0B", "0B"), ("exception-0A", "0A")] {
        let mut reference = station("sd2x", &["truncated-pdu=silence"]);
        let mut chosen = station(
            "sd2x",
            &[
                "truncated-pdu=silence",
                &format!("gateway-no-response={choice}"),
            ],
        );
        for (u, pdu, fc) in [(0xFF, READ, "83"), (0, echo, "88"), (own, truncated, "83")] {
            assert_eq!(serve(&mut reference, &adu(3, u, pdu)), (vec![], false));
            assert!(
                reference
                    .take_decisions()
                    .contains(&ids::GATEWAY_NO_RESPONSE),
                "unit {u}: the reference's silence is the freedom's decision"
            );
            assert_eq!(
                serve(&mut chosen, &adu(3, u, pdu)),
                (vec![(3, format!("{fc} {code}"))], false),
                "{choice}, unit {u}"
            );
            assert!(chosen.take_decisions().contains(&ids::GATEWAY_NO_RESPONSE));
        }
        assert_eq!(
            serve(&mut chosen, &adu(4, own, echo)),
            (vec![(4, "08 00 00 12 34".into())], false),
            "{choice}: the drive's own answer"
        );
        let mut foreign = adu(5, own, truncated);
        foreign[3] = 1;
        assert_eq!(
            serve(&mut chosen, &foreign),
            (vec![], false),
            "protocol id 1"
        );
    }
    let mut mdrive = station("mdrive", &["truncated-pdu=silence"]);
    assert_eq!(
        serve(&mut mdrive, &adu(6, unit("mdrive"), truncated)),
        (vec![], false)
    );
    assert!(!mdrive.take_decisions().contains(&ids::GATEWAY_NO_RESPONSE));
}
