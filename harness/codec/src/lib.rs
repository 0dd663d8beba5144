//! The sans-IO Modbus codec: PDUs, Modbus/TCP and RTU ADUs, CRC, RTU stream framing.
//!
//! No sockets, no tokio, no clock: callers hand in bytes (and, for the framer, arrival times).
//! Decoding never panics and allocates at most the size of its input.

pub mod bits;
pub mod codes;
pub mod error;
pub mod fields;
pub mod file_record;
pub mod framer;
pub mod lenient;
pub mod mei;
pub mod pdu;
mod reader;
pub mod rtu;
pub mod tcp;
pub mod vendor;

pub use codes::{ExceptionCode, FunctionCode};
pub use error::{DecodeError, DecodeErrorKind, EncodeError};
pub use fields::{Field, FieldValue, describe, hex_spaced};
pub use file_record::{FileRecordData, FileRecordRef, FileRecordWrite};
pub use framer::{
    CharFormat, FrameLen, FramerEvent, LengthRule, Parity, RtuFramer, RtuTiming, VendorRule,
};
pub use lenient::{Decoded, Framing, Lenient, decode_any};
pub use mei::{
    CanOpenAccess, DeviceIdObject, DeviceIdResponse, canopen_with_reserved,
    canopen_without_reserved,
};
pub use pdu::{Direction, MAX_PDU_LEN, Pdu, Request, Response};
pub use vendor::Mnemonic;

/// Parse hex as users and manuals write it: spaces, `0x` prefixes, `:`/`,`/`-` separators and `_h` suffixes allowed.
pub fn parse_hex(s: &str) -> Result<Vec<u8>, hex::FromHexError> {
    let cleaned: String = s
        .split(|c: char| c.is_whitespace() || c == ',' || c == ':' || c == '-')
        .map(|t| {
            let t = t.trim_start_matches("0x").trim_start_matches("0X");
            t.trim_end_matches("_h").trim_end_matches('h')
        })
        .collect();
    hex::decode(cleaned)
}
