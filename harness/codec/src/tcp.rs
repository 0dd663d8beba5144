//! Modbus/TCP ADU: the 7-byte MBAP header (transaction id, protocol id, length, unit id) + PDU.

use super::error::{DecodeError, DecodeErrorKind, EncodeError};
use super::pdu::{Direction, MAX_PDU_LEN, Pdu};

/// MBAP header length, unit id included.
pub const MBAP_LEN: usize = 7;
/// Largest Modbus/TCP ADU (MBAP + 253-byte PDU).
pub const MAX_ADU_LEN: usize = MBAP_LEN + MAX_PDU_LEN;

/// The MBAP header as carried on the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Mbap {
    pub transaction_id: u16,
    pub protocol_id: u16,
    /// Byte count of unit id + PDU.
    pub length: u16,
    pub unit_id: u8,
}

impl Mbap {
    /// Parse the 7 header bytes without checking them (for logging malformed traffic).
    pub fn parse(bytes: &[u8]) -> Option<Self> {
        let b = bytes.get(..MBAP_LEN)?;
        Some(Self {
            transaction_id: u16::from_be_bytes([b[0], b[1]]),
            protocol_id: u16::from_be_bytes([b[2], b[3]]),
            length: u16::from_be_bytes([b[4], b[5]]),
            unit_id: b[6],
        })
    }
}

/// A Modbus/TCP ADU with its PDU still as bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TcpAdu<'a> {
    pub header: Mbap,
    pub pdu: &'a [u8],
}

/// Strictly decode exactly one ADU: protocol id 0, length field equal to the bytes, PDU 1..=253 bytes.
pub fn decode_adu(bytes: &[u8]) -> Result<TcpAdu<'_>, DecodeError> {
    if bytes.len() < MBAP_LEN + 1 {
        return Err(DecodeError::new(
            bytes.len(),
            DecodeErrorKind::MbapShort { len: bytes.len() },
        ));
    }
    let header = Mbap::parse(bytes).ok_or(DecodeError::new(
        0,
        DecodeErrorKind::MbapShort { len: bytes.len() },
    ))?;
    if header.protocol_id != 0 {
        return Err(DecodeError::new(
            2,
            DecodeErrorKind::ProtocolId {
                found: header.protocol_id,
            },
        ));
    }
    let actual = bytes.len() - (MBAP_LEN - 1);
    if header.length as usize != actual {
        return Err(DecodeError::new(
            4,
            DecodeErrorKind::MbapLength {
                declared: header.length,
                actual,
            },
        ));
    }
    let pdu = &bytes[MBAP_LEN..];
    if pdu.len() > MAX_PDU_LEN {
        return Err(DecodeError::new(
            MAX_ADU_LEN,
            DecodeErrorKind::PduTooLong { len: pdu.len() },
        ));
    }
    Ok(TcpAdu { header, pdu })
}

/// Strictly decode one ADU and its PDU in the given direction.
pub fn decode(bytes: &[u8], dir: Direction) -> Result<(Mbap, Pdu), DecodeError> {
    let adu = decode_adu(bytes)?;
    let pdu = Pdu::decode(adu.pdu, dir).map_err(|e| e.shifted(MBAP_LEN))?;
    Ok((adu.header, pdu))
}

/// Frame an already-encoded PDU: MBAP with protocol id 0 and the right length.
pub fn encode_adu(
    transaction_id: u16,
    unit_id: u8,
    pdu: &[u8],
    out: &mut Vec<u8>,
) -> Result<(), EncodeError> {
    if pdu.len() > MAX_PDU_LEN {
        return Err(EncodeError::TooLong {
            field: "PDU",
            len: pdu.len(),
            max: MAX_PDU_LEN,
        });
    }
    out.extend_from_slice(&transaction_id.to_be_bytes());
    out.extend_from_slice(&[0, 0]);
    out.extend_from_slice(&(pdu.len() as u16 + 1).to_be_bytes());
    out.push(unit_id);
    out.extend_from_slice(pdu);
    Ok(())
}

/// Encode a typed PDU as a Modbus/TCP ADU.
pub fn encode(transaction_id: u16, unit_id: u8, pdu: &Pdu) -> Result<Vec<u8>, EncodeError> {
    let mut body = Vec::with_capacity(16);
    pdu.encode(&mut body)?;
    let mut out = Vec::with_capacity(MBAP_LEN + body.len());
    encode_adu(transaction_id, unit_id, &body, &mut out)?;
    Ok(out)
}

/// Stream splitting: how many bytes the ADU at the start of `buf` occupies, once the header is in.
///
/// `None` until 6 bytes are buffered. The length field is trusted here (a stream has nothing else to cut on);
/// a length of 0 or beyond 254 is reported by `decode_adu` on the cut frame.
pub fn adu_len(buf: &[u8]) -> Option<usize> {
    let b = buf.get(..6)?;
    Some(6 + u16::from_be_bytes([b[4], b[5]]) as usize)
}
