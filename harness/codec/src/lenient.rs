//! The lenient view: raw bytes kept beside the strict decode result, so malformed traffic can be logged.

use super::error::DecodeError;
use super::pdu::{Direction, Pdu};
use super::{rtu, tcp};

/// Which ADU framing a byte string uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Framing {
    /// Modbus/TCP: MBAP + PDU.
    Tcp,
    /// RTU: address + PDU + CRC (also RTU over TCP).
    Rtu,
    /// A bare PDU.
    Pdu,
}

/// The unit address of a decoded ADU (MBAP unit id or RTU slave address), absent for a bare PDU.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Decoded {
    pub unit: Option<u8>,
    pub transaction_id: Option<u16>,
    pub pdu: Pdu,
}

/// Raw bytes and what strict decoding made of them.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Lenient {
    pub raw: Vec<u8>,
    pub framing: Framing,
    pub direction: Direction,
    pub result: Result<Decoded, DecodeError>,
}

impl Lenient {
    /// Decode `raw` strictly, keeping the bytes whatever the outcome.
    pub fn decode(raw: &[u8], framing: Framing, direction: Direction) -> Self {
        let result = decode_any(raw, framing, direction);
        Self {
            raw: raw.to_vec(),
            framing,
            direction,
            result,
        }
    }

    /// True when the bytes decoded strictly.
    pub fn is_valid(&self) -> bool {
        self.result.is_ok()
    }
}

/// Strictly decode one ADU (or bare PDU) of the given framing and direction.
pub fn decode_any(
    raw: &[u8],
    framing: Framing,
    direction: Direction,
) -> Result<Decoded, DecodeError> {
    match framing {
        Framing::Tcp => tcp::decode(raw, direction).map(|(h, pdu)| Decoded {
            unit: Some(h.unit_id),
            transaction_id: Some(h.transaction_id),
            pdu,
        }),
        Framing::Rtu => rtu::decode(raw, direction).map(|(a, pdu)| Decoded {
            unit: Some(a),
            transaction_id: None,
            pdu,
        }),
        Framing::Pdu => Pdu::decode(raw, direction).map(|pdu| Decoded {
            unit: None,
            transaction_id: None,
            pdu,
        }),
    }
}
