//! FC 14 (Read File Record) and FC 15 (Write File Record) sub-requests and sub-responses, MODBUS Application
//! Protocol v1.1b3 sections 6.14 and 6.15.
//!
//! The codec checks structure only: every byte count agrees with the bytes it counts, and sub-requests fill
//! their data length exactly. The values the spec constrains (reference type 6, file 1-0xFFFF, record
//! 0-0x270F, the 0x07-0xF5 / 0x09-0xFB data lengths) are kept as sent: a server answers them with exception
//! 02 or 03 by its state diagram, so the harness must be able to send and decode them.

use super::codes::file::SUB_REQUEST_LEN;
use super::error::{DecodeError, DecodeErrorKind, EncodeError};
use super::reader::{Reader, mismatch};

/// One FC 14 sub-request: which registers of which file to read (7 bytes on the wire).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct FileRecordRef {
    /// 6 is the only type the spec defines.
    pub reference_type: u8,
    pub file_number: u16,
    /// The first record (register) of the group, 0x0000-0x270F.
    pub record_number: u16,
    /// How many registers to read.
    pub record_length: u16,
}

/// One FC 14 sub-response: the reference type and the registers read.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct FileRecordData {
    pub reference_type: u8,
    pub values: Vec<u16>,
}

/// One FC 15 sub-request, and the same in its response (an echo): the registers to write from a record on.
/// The record length on the wire is `values.len()`.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct FileRecordWrite {
    pub reference_type: u8,
    pub file_number: u16,
    pub record_number: u16,
    pub values: Vec<u16>,
}

/// A 1-byte data length at the reader's position that must count every byte after it.
fn data_length(
    r: &mut Reader<'_>,
    field: &'static str,
    basis: &'static str,
) -> Result<(), DecodeError> {
    let at = r.pos();
    let n = r.u8(field)? as usize;
    if n != r.remaining() {
        return Err(mismatch(at, field, n, r.remaining(), basis));
    }
    Ok(())
}

/// FC 14 request after its function code: byte count, then 7-byte sub-requests filling it.
pub(crate) fn decode_read_request(r: &mut Reader<'_>) -> Result<Vec<FileRecordRef>, DecodeError> {
    let at = r.pos();
    data_length(r, "byte count", "sub-request bytes present")?;
    if r.remaining() % SUB_REQUEST_LEN != 0 {
        return Err(DecodeError::new(
            at,
            DecodeErrorKind::InvalidField {
                field: "byte count",
                value: r.remaining() as u32,
                rule: "sub-requests are 7 bytes each (spec 6.14)",
            },
        ));
    }
    let mut subs = Vec::with_capacity(r.remaining() / SUB_REQUEST_LEN);
    while r.remaining() > 0 {
        subs.push(FileRecordRef {
            reference_type: r.u8("reference type")?,
            file_number: r.u16("file number")?,
            record_number: r.u16("record number")?,
            record_length: r.u16("record length")?,
        });
    }
    Ok(subs)
}

/// FC 14 response after its function code: response data length, then sub-responses of (length, reference
/// type, registers), each length counting the reference type and the register bytes.
pub(crate) fn decode_read_response(r: &mut Reader<'_>) -> Result<Vec<FileRecordData>, DecodeError> {
    data_length(r, "response data length", "sub-response bytes present")?;
    let mut subs = Vec::new();
    while r.remaining() > 0 {
        let at = r.pos();
        let len = r.u8("file response length")?;
        if len % 2 == 0 {
            return Err(DecodeError::new(
                at,
                DecodeErrorKind::InvalidField {
                    field: "file response length",
                    value: u32::from(len),
                    rule: "a sub-response is the reference type and 2 bytes per register: an odd length",
                },
            ));
        }
        let reference_type = r.u8("reference type")?;
        let values = r.registers("record data", usize::from(len) - 1)?;
        subs.push(FileRecordData {
            reference_type,
            values,
        });
    }
    Ok(subs)
}

/// FC 15 request or response after its function code: data length, then sub-requests of 7 bytes and
/// `record length` registers each.
pub(crate) fn decode_write(
    r: &mut Reader<'_>,
    length_field: &'static str,
) -> Result<Vec<FileRecordWrite>, DecodeError> {
    data_length(r, length_field, "sub-request bytes present")?;
    let mut subs = Vec::new();
    while r.remaining() > 0 {
        let reference_type = r.u8("reference type")?;
        let file_number = r.u16("file number")?;
        let record_number = r.u16("record number")?;
        let n = r.u16("record length")?;
        let values = r.registers("record data", usize::from(n) * 2)?;
        subs.push(FileRecordWrite {
            reference_type,
            file_number,
            record_number,
            values,
        });
    }
    Ok(subs)
}

fn put_u16(out: &mut Vec<u8>, v: u16) {
    out.extend_from_slice(&v.to_be_bytes());
}

/// Append a 1-byte length placeholder, run `body`, then fill in the length (at most 255 bytes).
fn counted(
    out: &mut Vec<u8>,
    field: &'static str,
    body: impl FnOnce(&mut Vec<u8>) -> Result<(), EncodeError>,
) -> Result<(), EncodeError> {
    let at = out.len();
    out.push(0);
    body(out)?;
    let n = out.len() - at - 1;
    let Ok(b) = u8::try_from(n) else {
        return Err(EncodeError::TooLong {
            field,
            len: n,
            max: 255,
        });
    };
    out[at] = b;
    Ok(())
}

pub(crate) fn encode_read_request(
    out: &mut Vec<u8>,
    subs: &[FileRecordRef],
) -> Result<(), EncodeError> {
    counted(out, "byte count", |out| {
        for s in subs {
            out.push(s.reference_type);
            put_u16(out, s.file_number);
            put_u16(out, s.record_number);
            put_u16(out, s.record_length);
        }
        Ok(())
    })
}

pub(crate) fn encode_read_response(
    out: &mut Vec<u8>,
    subs: &[FileRecordData],
) -> Result<(), EncodeError> {
    counted(out, "response data length", |out| {
        for s in subs {
            counted(out, "file response length", |out| {
                out.push(s.reference_type);
                for v in &s.values {
                    put_u16(out, *v);
                }
                Ok(())
            })?;
        }
        Ok(())
    })
}

pub(crate) fn encode_write(
    out: &mut Vec<u8>,
    length_field: &'static str,
    subs: &[FileRecordWrite],
) -> Result<(), EncodeError> {
    counted(out, length_field, |out| {
        for s in subs {
            out.push(s.reference_type);
            put_u16(out, s.file_number);
            put_u16(out, s.record_number);
            let Ok(n) = u16::try_from(s.values.len()) else {
                return Err(EncodeError::TooLong {
                    field: "record data",
                    len: s.values.len(),
                    max: usize::from(u16::MAX),
                });
            };
            put_u16(out, n);
            for v in &s.values {
                put_u16(out, *v);
            }
        }
        Ok(())
    })
}
