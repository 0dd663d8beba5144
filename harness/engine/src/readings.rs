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

/// A response PDU as the codec decodes it, or else as another reading of a manual writes it (FC 0x41 with a
/// 2-byte byte count): [`decode_response`] for an answer already taken out of its frame (the keeper's reads).
pub fn decode_response_pdu(pdu: &[u8]) -> Option<Response> {
    Response::decode(pdu)
        .ok()
        .or_else(|| Response::decode(&fc41_two_byte_count(pdu)?).ok())
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
/// 1-byte form the codec decodes: `None` when the bytes are not such a response. One byte after the counted
/// characters is the pad both manuals allow ("Response n bytes n=N or N+1", MDrive manual line 956, LMD
/// manual line 1129) and is left out, as it is in the 1-byte form (`Runner::in_case_form`).
pub fn fc41_two_byte_count(pdu: &[u8]) -> Option<Vec<u8>> {
    let (&fc, rest) = pdu.split_first()?;
    if fc != FunctionCode::VENDOR_READ.0 || rest.len() < 2 {
        return None;
    }
    let count = usize::from(u16::from_be_bytes([rest[0], rest[1]]));
    let params = &rest[2..];
    ((count == params.len() || count + 1 == params.len()) && count <= 255).then(|| {
        let mut out = vec![fc, count as u8];
        out.extend_from_slice(&params[..count]);
        out
    })
}

#[cfg(test)]
mod tests {
    use super::fc41_two_byte_count;

    /// The table's 2-byte count, with or without the pad byte its count leaves out (an eighth-wave MDrive
    /// sends `41 00 07 '0, 0, 0' 00`); with two bytes after the characters, or a count that is not theirs, it
    /// is no such answer.
    #[test]
    fn a_two_byte_count_is_read_with_or_without_the_pad_byte() {
        let chars = b"0, 0, 0";
        let mut one = vec![0x41, 0x07];
        one.extend_from_slice(chars);
        let mut two = vec![0x41, 0x00, 0x07];
        two.extend_from_slice(chars);
        assert_eq!(fc41_two_byte_count(&two), Some(one.clone()));
        let mut padded = two.clone();
        padded.push(0x00);
        assert_eq!(fc41_two_byte_count(&padded), Some(one));
        padded.push(0x00);
        assert_eq!(fc41_two_byte_count(&padded), None);
        assert_eq!(fc41_two_byte_count(&[0x41, 0x00, 0x08, 0x30]), None);
        assert_eq!(fc41_two_byte_count(&[0x42, 0x00, 0x01, 0x30]), None);
    }
}
