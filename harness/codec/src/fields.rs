//! A decoded PDU as named fields: what the `decode` tool prints and what golden-frame expectations check.
//! Field names are the keys of `[frame.expect]` in corpus/golden/SCHEMA.md.
//!
//! FC 14/15 sub-requests are shown column by column (`file_number = [4, 3]` for two sub-requests) and their
//! register data joined in order in `values`; `record_length` says where each sub-request's part ends.

use std::fmt;

use super::file_record::FileRecordWrite;
use super::pdu::{Pdu, Request, Response};
use crate::Mnemonic;

/// A field value.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum FieldValue {
    Int(u64),
    Ints(Vec<u64>),
    Bytes(Vec<u8>),
    Text(String),
    /// Device identification objects: (id, value as text).
    Objects(Vec<(u8, String)>),
}

/// One named field of a decoded frame.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Field {
    pub name: &'static str,
    pub value: FieldValue,
}

impl fmt::Display for FieldValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FieldValue::Int(v) => write!(f, "{v} (0x{v:X})"),
            // The lists are written element by element, not through a string per element.
            FieldValue::Ints(v) => {
                f.write_str("[")?;
                for (n, x) in v.iter().enumerate() {
                    if n > 0 {
                        f.write_str(", ")?;
                    }
                    write!(f, "0x{x:04X} ({x})")?;
                }
                f.write_str("]")
            }
            FieldValue::Bytes(b) => f.write_str(&hex_spaced(b)),
            FieldValue::Text(s) => write!(f, "{s:?}"),
            FieldValue::Objects(o) => {
                f.write_str("{")?;
                for (n, (i, v)) in o.iter().enumerate() {
                    if n > 0 {
                        f.write_str(", ")?;
                    }
                    write!(f, "0x{i:02X}={v:?}")?;
                }
                f.write_str("}")
            }
        }
    }
}

/// Upper-case hex with spaces, as the golden files print bytes.
pub fn hex_spaced(b: &[u8]) -> String {
    // Two digits per byte into a buffer of spaces, without a formatter: this runs for every byte of every
    // frame a report or a fuzz target prints.
    const DIGITS: &[u8; 16] = b"0123456789ABCDEF";
    let mut out = vec![b' '; (b.len() * 3).saturating_sub(1)];
    for (digits, x) in out.chunks_mut(3).zip(b) {
        if let [hi, lo, ..] = digits {
            *hi = DIGITS[usize::from(x >> 4)];
            *lo = DIGITS[usize::from(x & 0x0F)];
        }
    }
    String::from_utf8(out).expect("hex digits and spaces are ASCII")
}

fn int(name: &'static str, v: impl Into<u64>) -> Field {
    Field {
        name,
        value: FieldValue::Int(v.into()),
    }
}

fn ints(name: &'static str, v: &[u16]) -> Field {
    Field {
        name,
        value: FieldValue::Ints(v.iter().map(|x| *x as u64).collect()),
    }
}

fn column(name: &'static str, v: impl Iterator<Item = u64>) -> Field {
    Field {
        name,
        value: FieldValue::Ints(v.collect()),
    }
}

/// FC 15 sub-requests (request and response alike): data length, the columns, the data joined.
fn file_writes(subs: &[FileRecordWrite], f: &mut Vec<Field>) {
    let data_len: usize = subs.iter().map(|s| 7 + 2 * s.values.len()).sum();
    f.push(int("byte_count", data_len as u64));
    let refs: Vec<_> = subs
        .iter()
        .map(|s| {
            (
                s.reference_type,
                s.file_number,
                s.record_number,
                s.values.len(),
            )
        })
        .collect();
    file_refs(&refs, f);
    f.push(column(
        "values",
        subs.iter()
            .flat_map(|s| s.values.iter().map(|v| u64::from(*v))),
    ));
}

/// The columns of FC 14/15 sub-requests, each given as (reference type, file, record, record length).
fn file_refs(refs: &[(u8, u16, u16, usize)], f: &mut Vec<Field>) {
    f.push(column(
        "reference_type",
        refs.iter().map(|r| u64::from(r.0)),
    ));
    f.push(column("file_number", refs.iter().map(|r| u64::from(r.1))));
    f.push(column("record_number", refs.iter().map(|r| u64::from(r.2))));
    f.push(column("record_length", refs.iter().map(|r| r.3 as u64)));
}

fn mask_write(address: u16, and_mask: u16, or_mask: u16, f: &mut Vec<Field>) {
    f.push(int("address", address));
    f.push(int("and_mask", and_mask));
    f.push(int("or_mask", or_mask));
}

fn bits(data: &[u8], quantity: Option<u16>) -> Field {
    let n = quantity.map(|q| q as usize).unwrap_or(data.len() * 8);
    let v = (0..n.min(data.len() * 8))
        .map(|i| u64::from((data[i / 8] >> (i % 8)) & 1))
        .collect();
    Field {
        name: "bits",
        value: FieldValue::Ints(v),
    }
}

fn bytes(name: &'static str, b: &[u8]) -> Field {
    Field {
        name,
        value: FieldValue::Bytes(b.to_vec()),
    }
}

fn text(name: &'static str, b: &[u8]) -> Field {
    Field {
        name,
        value: FieldValue::Text(String::from_utf8_lossy(b).into_owned()),
    }
}

/// The fields of a PDU, function code first.
pub fn describe(pdu: &Pdu) -> Vec<Field> {
    let mut f = Vec::new();
    match pdu {
        Pdu::Request(r) => {
            f.push(int("function", r.function().0));
            describe_request(r, &mut f);
        }
        Pdu::Response(r) => {
            f.push(int("function", r.function().0));
            describe_response(r, &mut f);
        }
    }
    f
}

fn canopen(a: &super::mei::CanOpenAccess, f: &mut Vec<Field>) {
    f.push(int("mei", 0x0Du8));
    f.push(int("control", a.control));
    f.push(int("reserved", a.reserved));
    f.push(int("node_id", a.node_id));
    f.push(int("index", a.index));
    f.push(int("subindex", a.subindex));
    f.push(int("offset", a.offset));
    f.push(int("byte_count", a.byte_count));
    if !a.data.is_empty() {
        f.push(bytes("object_data", &a.data));
        if let Some(v) = a.value_le() {
            f.push(int("object_value", v));
        }
    }
}

fn describe_request(r: &Request, f: &mut Vec<Field>) {
    use Request::*;
    match r {
        ReadCoils { address, quantity }
        | ReadDiscreteInputs { address, quantity }
        | ReadHoldingRegisters { address, quantity }
        | ReadInputRegisters { address, quantity } => {
            f.push(int("address", *address));
            f.push(int("quantity", *quantity));
        }
        WriteSingleCoil { address, value } => single_write(*address, *value, true, f),
        WriteSingleRegister { address, value } => single_write(*address, *value, false, f),
        Diagnostics { sub_function, data } => diagnostics(*sub_function, data, f),
        ReadExceptionStatus | GetCommEventCounter | GetCommEventLog | ReportServerId => {}
        ReadFileRecord { sub_requests } => {
            f.push(int("byte_count", 7 * sub_requests.len() as u64));
            let refs: Vec<_> = sub_requests
                .iter()
                .map(|s| {
                    let length = usize::from(s.record_length);
                    (s.reference_type, s.file_number, s.record_number, length)
                })
                .collect();
            file_refs(&refs, f);
        }
        WriteFileRecord { sub_requests } => file_writes(sub_requests, f),
        MaskWriteRegister {
            address,
            and_mask,
            or_mask,
        } => mask_write(*address, *and_mask, *or_mask, f),
        ReadFifoQueue { address } => f.push(int("address", *address)),
        WriteMultipleCoils {
            address,
            quantity,
            data,
        } => {
            f.push(int("address", *address));
            f.push(int("quantity", *quantity));
            f.push(int("byte_count", data.len() as u64));
            f.push(bits(data, Some(*quantity)));
        }
        WriteMultipleRegisters { address, values } => {
            f.push(int("address", *address));
            f.push(int("quantity", values.len() as u64));
            f.push(int("byte_count", values.len() as u64 * 2));
            f.push(ints("values", values));
        }
        ReadWriteMultipleRegisters {
            read_address,
            read_quantity,
            write_address,
            values,
        } => {
            f.push(int("address", *read_address));
            f.push(int("quantity", *read_quantity));
            f.push(int("write_address", *write_address));
            f.push(int("write_quantity", values.len() as u64));
            f.push(int("byte_count", values.len() as u64 * 2));
            f.push(ints("values", values));
        }
        CanOpen(a) => canopen(a, f),
        ReadDeviceId {
            read_code,
            object_id,
        } => {
            f.push(int("mei", 0x0Eu8));
            f.push(int("read_code", *read_code));
            f.push(int("object_id", *object_id));
        }
        VendorRead { mnemonic } => mnemonic_fields(mnemonic, f),
        VendorWrite { mnemonic, params } => {
            mnemonic_fields(mnemonic, f);
            f.push(int("byte_count", params.len() as u64));
            f.push(text("params", params));
        }
        Raw { data, .. } => f.push(bytes("data", data)),
    }
}

/// FC 05 and 06, request and echo alike: the address and the value (and, for a coil, its state where the
/// value is one of the two the spec allows).
fn single_write(address: u16, value: u16, coil: bool, f: &mut Vec<Field>) {
    f.push(int("address", address));
    f.push(ints("values", &[value]));
    if coil && (value == 0xFF00 || value == 0) {
        f.push(Field {
            name: "bits",
            value: FieldValue::Ints(vec![u64::from(value == 0xFF00)]),
        });
    }
}

fn mnemonic_fields(mnemonic: &Mnemonic, f: &mut Vec<Field>) {
    f.push(bytes("mnemonic_bytes", &mnemonic.0));
    f.push(Field {
        name: "mnemonic",
        value: FieldValue::Text(mnemonic.name()),
    });
}

fn diagnostics(sub_function: u16, data: &[u8], f: &mut Vec<Field>) {
    f.push(int("sub_function", sub_function));
    if data.len() == 2 {
        f.push(int("data", u16::from_be_bytes([data[0], data[1]])));
    } else {
        f.push(bytes("data_bytes", data));
    }
}

fn describe_response(r: &Response, f: &mut Vec<Field>) {
    use Response::*;
    match r {
        ReadCoils { data } | ReadDiscreteInputs { data } => {
            f.push(int("byte_count", data.len() as u64));
            f.push(bits(data, None));
        }
        ReadHoldingRegisters { values }
        | ReadInputRegisters { values }
        | ReadWriteMultipleRegisters { values } => {
            f.push(int("byte_count", values.len() as u64 * 2));
            f.push(ints("values", values));
        }
        WriteSingleCoil { address, value } => single_write(*address, *value, true, f),
        WriteSingleRegister { address, value } => single_write(*address, *value, false, f),
        Diagnostics { sub_function, data } => diagnostics(*sub_function, data, f),
        WriteMultipleCoils { address, quantity } | WriteMultipleRegisters { address, quantity } => {
            f.push(int("address", *address));
            f.push(int("quantity", *quantity));
        }
        ReadExceptionStatus { status } => {
            f.push(int("status", *status));
            f.push(bits(&[*status], None));
        }
        GetCommEventCounter {
            status,
            event_count,
        } => {
            f.push(int("status", *status));
            f.push(int("event_count", *event_count));
        }
        GetCommEventLog {
            status,
            event_count,
            message_count,
            events,
        } => {
            f.push(int("byte_count", 6 + events.len() as u64));
            f.push(int("status", *status));
            f.push(int("event_count", *event_count));
            f.push(int("message_count", *message_count));
            f.push(bytes("events", events));
        }
        ReportServerId { data } => {
            f.push(int("byte_count", data.len() as u64));
            f.push(bytes("server_id_data", data));
        }
        ReadFileRecord { sub_responses } => {
            let len: usize = sub_responses.iter().map(|s| 2 + 2 * s.values.len()).sum();
            f.push(int("byte_count", len as u64));
            f.push(column(
                "reference_type",
                sub_responses.iter().map(|s| u64::from(s.reference_type)),
            ));
            f.push(column(
                "record_length",
                sub_responses.iter().map(|s| s.values.len() as u64),
            ));
            f.push(column(
                "values",
                sub_responses
                    .iter()
                    .flat_map(|s| s.values.iter().map(|v| u64::from(*v))),
            ));
        }
        WriteFileRecord { sub_requests } => file_writes(sub_requests, f),
        MaskWriteRegister {
            address,
            and_mask,
            or_mask,
        } => mask_write(*address, *and_mask, *or_mask, f),
        ReadFifoQueue { values } => {
            f.push(int("byte_count", 2 + 2 * values.len() as u64));
            f.push(int("fifo_count", values.len() as u64));
            f.push(ints("values", values));
        }
        CanOpen(a) => canopen(a, f),
        CanOpenError { sdo_code } => {
            f.push(int("exception", 0xFFu8));
            f.push(int("mei", 0x0Du8));
            f.push(int("sdo_error", *sdo_code));
        }
        ReadDeviceId(d) => {
            f.push(int("mei", 0x0Eu8));
            f.push(int("read_code", d.read_code));
            f.push(int("conformity", d.conformity));
            f.push(int("more_follows", d.more_follows));
            f.push(int("object_id", d.next_object_id));
            f.push(int("object_count", d.objects.len() as u64));
            f.push(Field {
                name: "objects",
                value: FieldValue::Objects(
                    d.objects
                        .iter()
                        .map(|o| (o.id, String::from_utf8_lossy(&o.value).into_owned()))
                        .collect(),
                ),
            });
        }
        VendorRead { params } => {
            f.push(int("byte_count", params.len() as u64));
            f.push(text("params", params));
        }
        VendorWrite { written, mnemonic } => {
            f.push(int("byte_count", *written));
            mnemonic_fields(mnemonic, f);
        }
        Exception { code, .. } => f.push(int("exception", code.0)),
        Raw { data, .. } => f.push(bytes("data", data)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hex_spaced_prints_every_byte_as_two_upper_case_digits() {
        assert_eq!(hex_spaced(&[]), "");
        assert_eq!(hex_spaced(&[0xFF]), "FF");
        assert_eq!(hex_spaced(&[0x01, 0xAB, 0x0F]), "01 AB 0F");
        let all: Vec<u8> = (0..=255).collect();
        let expected: Vec<String> = all.iter().map(|x| format!("{x:02X}")).collect();
        assert_eq!(hex_spaced(&all), expected.join(" "));
    }

    #[test]
    fn lists_print_as_their_elements_joined() {
        // What the values printed as when each element went through its own string, joined.
        let ints = |v: &[u64]| {
            let parts: Vec<String> = v.iter().map(|x| format!("0x{x:04X} ({x})")).collect();
            format!("[{}]", parts.join(", "))
        };
        for v in [vec![], vec![7], vec![0, 0xFFFF, 65_536, u64::MAX]] {
            assert_eq!(FieldValue::Ints(v.clone()).to_string(), ints(&v));
        }
        assert_eq!(
            FieldValue::Ints(vec![1, 0xBEEF]).to_string(),
            "[0x0001 (1), 0xBEEF (48879)]"
        );
        let objects = |o: &[(u8, String)]| {
            let parts: Vec<String> = o.iter().map(|(i, v)| format!("0x{i:02X}={v:?}")).collect();
            format!("{{{}}}", parts.join(", "))
        };
        for o in [
            vec![],
            vec![(0, "IMS".to_string())],
            vec![(1, "a\"b".to_string()), (0x80, String::new())],
        ] {
            assert_eq!(FieldValue::Objects(o.clone()).to_string(), objects(&o));
        }
        assert_eq!(
            FieldValue::Objects(vec![(0, "IMS".into()), (2, "1.0".into())]).to_string(),
            r#"{0x00="IMS", 0x02="1.0"}"#
        );
        assert_eq!(FieldValue::Bytes(vec![0x01, 0xAB]).to_string(), "01 AB");
        assert_eq!(FieldValue::Bytes(vec![]).to_string(), "");
    }
}
