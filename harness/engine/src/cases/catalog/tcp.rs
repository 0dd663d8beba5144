//! Modbus/TCP cases: the MBAP header, requests across and within segments, unit ids, the PDU size limit.

use super::{APP, Ctx, TCPG, exchange, known_good_read};
use crate::cases::{Compare, Mutation, Outgoing, Step, Tag};

/// The Modbus/TCP suite, family by family.
pub(super) fn cases(cx: &mut Ctx) {
    mbap_header(cx);
    segments(cx);
    unit_ids(cx);
    oversized_pdu(cx);
}

/// The MBAP header: transaction ids echoed, a foreign protocol id and a wrong length not served.
fn mbap_header(cx: &mut Ctx) {
    let read = known_good_read(cx.p);
    cx.push(
        "tcp/mbap/transaction-id-echo".into(),
        "transaction ids 0x0000, 0x1234 and 0xFFFF are echoed",
        format!("{TCPG}, section 3.1.3 (MBAP header)"),
        "The server copies the transaction identifier of the request into the response, and answers with protocol identifier 0 and a length field equal to the bytes that follow it.",
        vec![Tag::TcpOnly],
        vec![
            exchange(Outgoing::Pdu(read.clone()), Compare::Structure, "first request"),
            exchange(Outgoing::Pdu(read.clone()), Compare::Structure, "second request"),
            exchange(Outgoing::Pdu(read.clone()), Compare::Structure, "third request"),
        ],
    );
    cx.push(
        "tcp/mbap/request-protocol-id-nonzero".into(),
        "a request with protocol id 1 is not answered",
        format!("{TCPG}, section 3.1.3 and 4.4.2.2 (MBAP checks)"),
        "A request whose protocol identifier is not 0 (Modbus) is discarded; the server keeps serving the connection.",
        vec![Tag::TcpOnly],
        vec![
            exchange(
                Outgoing::Mutated { pdu: read.clone(), mutation: Mutation::ProtocolId(1) },
                Compare::Exact,
                "protocol id 1",
            ),
            Step::Reconnect,
            cx.liveness(),
        ],
    );
    for (label, delta) in [("length-plus-1", 1i16), ("length-minus-1", -1)] {
        cx.push(
            format!("tcp/mbap/request-{label}"),
            format!("a request whose MBAP length is off by {delta}"),
            format!("{TCPG}, section 3.1.2 and 3.1.3 (the MBAP length field)"),
            "A request whose MBAP length disagrees with its PDU is not answered as a valid request, and the server recovers on a new connection.",
            vec![Tag::TcpOnly],
            vec![
                exchange(
                    Outgoing::Mutated { pdu: read.clone(), mutation: Mutation::LengthDelta(delta) },
                    Compare::RejectOrIgnore,
                    format!("length field {delta:+}"),
                ),
                Step::Reconnect,
                cx.liveness(),
            ],
        );
    }
}

/// A TCP stream has no message boundaries: several requests in one segment, one request in two.
fn segments(cx: &mut Ctx) {
    let read = known_good_read(cx.p);
    for k in [2usize, 4] {
        cx.push(
            format!("tcp/pipeline/{k}-requests-one-segment"),
            format!("{k} requests in one TCP segment"),
            format!("{TCPG}, section 4.2.1.1 (several transactions may be active on one connection)"),
            "Requests that arrive together in one segment are all answered, each with its own transaction id, in any order (they are paired by transaction id); a server with a single transaction may answer the ones behind the first with exception 06, Server Busy.",
            vec![Tag::TcpOnly],
            vec![exchange(Outgoing::Batch(vec![read.clone(); k]), Compare::Structure, format!("{k} requests"))],
        );
    }
    cx.push(
        "tcp/segment/request-split".into(),
        "one request split across two TCP segments 5 ms apart",
        format!("{TCPG}, section 3.1.2 (the MBAP length marks message boundaries)"),
        "A request whose bytes arrive in two segments is answered once, as if it had arrived whole.",
        vec![Tag::TcpOnly],
        vec![exchange(
            Outgoing::Mutated { pdu: read.clone(), mutation: Mutation::Split { at: 4, gap_us: 5_000 } },
            Compare::Structure,
            "split after 4 bytes",
        )],
    );
}

/// The unit ids a drive answers on TCP, and those it ignores.
fn unit_ids(cx: &mut Ctx) {
    let read = known_good_read(cx.p);
    for unit in [0u8, 1, 247, 255] {
        cx.push(
            format!("tcp/unit-id/{unit}"),
            format!("a request to unit id {unit}"),
            format!("{TCPG}, section 4.4.1.2 (unit identifier)"),
            "The server answers the unit ids its profile says it answers, echoing the unit id, and ignores the others.",
            vec![Tag::TcpOnly],
            vec![exchange(Outgoing::PduToUnit { pdu: read.clone(), unit }, Compare::Structure, format!("unit {unit}"))],
        );
    }
}

/// A frame past the 253-byte PDU limit.
fn oversized_pdu(cx: &mut Ctx) {
    cx.push(
        "tcp/pdu/over-253-bytes".into(),
        "a request with a 254-byte PDU (MBAP length 255)",
        format!("{APP}, section 4.1 (PDU size limit: TCP ADU at most 260 bytes)"),
        "A frame longer than the 253-byte PDU limit is not answered as a valid request; the server recovers on a new connection.",
        vec![Tag::TcpOnly],
        vec![
            exchange(Outgoing::Pdu(vec![0x03; 254]), Compare::RejectOrIgnore, "254-byte PDU"),
            Step::Reconnect,
            cx.liveness(),
        ],
    );
}
