//! Decode and encode errors: each names the rule broken and the byte offset.

use thiserror::Error;

/// Strict decoding failed: `offset` is the byte (from the start of the decoded unit) where the rule broke.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
#[error("at byte {offset}: {kind}")]
pub struct DecodeError {
    pub offset: usize,
    pub kind: DecodeErrorKind,
}

/// The rule a frame broke.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
pub enum DecodeErrorKind {
    #[error("empty PDU: no function code")]
    Empty,
    #[error("truncated: field `{field}` needs {needed} byte(s), {available} left")]
    Truncated {
        field: &'static str,
        needed: usize,
        available: usize,
    },
    #[error("{extra} trailing byte(s) after a complete PDU")]
    TrailingBytes { extra: usize },
    #[error("byte count mismatch: `{field}` says {declared}, the {basis} requires {expected}")]
    ByteCountMismatch {
        field: &'static str,
        declared: usize,
        expected: usize,
        basis: &'static str,
    },
    #[error("invalid `{field}` value 0x{value:X}: {rule}")]
    InvalidField {
        field: &'static str,
        value: u32,
        rule: &'static str,
    },
    #[error("PDU of {len} bytes exceeds the 253-byte maximum")]
    PduTooLong { len: usize },
    #[error("MBAP protocol id is 0x{found:04X}, Modbus requires 0x0000")]
    ProtocolId { found: u16 },
    #[error("MBAP length field says {declared} (unit id + PDU), the frame carries {actual}")]
    MbapLength { declared: u16, actual: usize },
    #[error("MBAP header needs 7 bytes plus a function code, got {len}")]
    MbapShort { len: usize },
    #[error("RTU frame of {len} bytes is shorter than the 4-byte minimum (address, function, CRC)")]
    RtuShort { len: usize },
    #[error("RTU frame of {len} bytes exceeds the 256-byte maximum")]
    RtuTooLong { len: usize },
    #[error("CRC mismatch: expected 0x{expected:04X} (bytes {lo:02X} {hi:02X}), received 0x{received:04X}", lo = expected & 0xFF, hi = expected >> 8)]
    Crc { expected: u16, received: u16 },
}

impl DecodeError {
    /// An error at `offset` breaking `kind`.
    pub fn new(offset: usize, kind: DecodeErrorKind) -> Self {
        Self { offset, kind }
    }

    /// The same error with its offset moved by `base` (when a PDU error is reported inside an ADU).
    pub fn shifted(mut self, base: usize) -> Self {
        self.offset += base;
        self
    }
}

/// A typed value that cannot be put on the wire (a field would overflow its width).
#[derive(Clone, Debug, PartialEq, Eq, Error)]
pub enum EncodeError {
    #[error("`{field}` holds {len} items, the wire field allows at most {max}")]
    TooLong {
        field: &'static str,
        len: usize,
        max: usize,
    },
}
