//! `tcp_adu`: one Modbus/TCP ADU through the strict and lenient decoders.

use codec::{DecodeError, Direction, Framing, Lenient, Pdu, describe, tcp};

fn assert_offset(e: &DecodeError, data: &[u8]) {
    assert!(
        e.offset <= data.len(),
        "decode error offset {} lies beyond the {} input bytes: {e}",
        e.offset,
        data.len()
    );
}

fn assert_pdu_roundtrip(pdu: &Pdu, bytes: &[u8]) {
    let mut again = Vec::new();
    pdu.encode(&mut again)
        .unwrap_or_else(|e| panic!("decoded {pdu:?} does not encode: {e}"));
    assert_eq!(again, bytes, "{pdu:?} re-encodes differently");
    let _ = describe(pdu);
}

/// `tcp_adu`: the input is one Modbus/TCP ADU. Strict decoding (both directions, and of the input as a bare
/// PDU) never panics and reports an offset inside the input; what decodes re-encodes to the same bytes; the
/// stream cut (`adu_len`) agrees with the strict decoder on every ADU the decoder accepts.
pub fn tcp_adu(data: &[u8]) {
    match tcp::decode_adu(data) {
        Ok(_) => assert_eq!(
            tcp::adu_len(data),
            Some(data.len()),
            "the stream cut disagrees with the MBAP length the strict decoder accepted"
        ),
        Err(e) => assert_offset(&e, data),
    }
    for dir in [Direction::Request, Direction::Response] {
        match tcp::decode(data, dir) {
            Ok((header, pdu)) => {
                let again = tcp::encode(header.transaction_id, header.unit_id, &pdu)
                    .unwrap_or_else(|e| panic!("decoded {pdu:?} does not encode: {e}"));
                assert_eq!(again, data, "{pdu:?} re-encodes differently");
            }
            Err(e) => assert_offset(&e, data),
        }
        match Pdu::decode(data, dir) {
            Ok(pdu) => assert_pdu_roundtrip(&pdu, data),
            Err(e) => assert_offset(&e, data),
        }
        let lenient = Lenient::decode(data, Framing::Tcp, dir);
        assert_eq!(lenient.raw, data, "the lenient view lost bytes");
    }
}
