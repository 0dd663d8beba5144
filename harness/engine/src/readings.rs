//! How the harness reads a drive's response frame: as the codec decodes it, or else as another reading of a
//! manual writes it (FC 0x41 with a 2-byte byte count, freedom `fc41-byte-count-width`). The oracle, the
//! captures for a restore, the probe and the liveness check all read answers through here.

use codec::{Direction, Framing, FunctionCode, Pdu, Response, decode_any};

/// A response frame as the codec decodes it, or else as another reading of a manual writes it (FC 0x41 with
/// a 2-byte byte count): what every place that takes a drive's answer apart (captures for a restore, the
/// probe, the liveness check) must read, so that a drive following the other reading is understood.
pub fn decode_response(framing: Framing, bytes: &[u8]) -> Option<Response> {
    match decode_any(bytes, framing, Direction::Response).map(|d| d.pdu) {
        Ok(Pdu::Response(r)) => Some(r),
        Ok(Pdu::Request(_)) => None,
        Err(_) => other_reading(framing, bytes),
    }
}

/// A response frame that only another reading of a manual decodes (FC 0x41 with a 2-byte byte count).
pub(crate) fn other_reading(framing: Framing, bytes: &[u8]) -> Option<Response> {
    let pdu = match framing {
        Framing::Tcp => bytes.get(codec::tcp::MBAP_LEN..)?,
        _ => bytes.get(1..bytes.len().checked_sub(2)?)?,
    };
    let one_byte = fc41_two_byte_count(pdu)?;
    Response::decode(&one_byte).ok()
}

/// FC 0x41 responses with a 2-byte byte count (the other reading of `fc41-byte-count-width`), as the
/// 1-byte form the codec decodes: `None` when the bytes are not such a response.
pub fn fc41_two_byte_count(pdu: &[u8]) -> Option<Vec<u8>> {
    let (&fc, rest) = pdu.split_first()?;
    if fc != FunctionCode::VENDOR_READ.0 || rest.len() < 2 {
        return None;
    }
    let count = usize::from(u16::from_be_bytes([rest[0], rest[1]]));
    let params = &rest[2..];
    (count == params.len() && count <= 255).then(|| {
        let mut out = vec![fc, count as u8];
        out.extend_from_slice(params);
        out
    })
}
