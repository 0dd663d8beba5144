//! Typed PDUs (function code + data) in both directions, with strict decoding and encoding.
//!
//! Decoding is structural: a quantity of 0 or above a device limit decodes (the device answers it with
//! exception 03); a byte count that disagrees with its quantity or with the bytes present does not.

use super::codes::{ExceptionCode, FunctionCode, MAX_FIFO_COUNT, event, mei};
use super::error::{DecodeError, DecodeErrorKind, EncodeError};
use super::file_record::{self, FileRecordData, FileRecordRef, FileRecordWrite};
use super::mei::{CanOpenAccess, DeviceIdObject, DeviceIdResponse};
use super::reader::{Reader, mismatch};
use super::vendor::Mnemonic;

/// Largest PDU the Modbus spec allows (256-byte RTU ADU minus address and CRC).
pub const MAX_PDU_LEN: usize = 253;

/// Which side sent a frame; the same function code has different layouts per direction.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Direction {
    Request,
    Response,
}

/// A request PDU.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Request {
    ReadCoils {
        address: u16,
        quantity: u16,
    },
    ReadDiscreteInputs {
        address: u16,
        quantity: u16,
    },
    ReadHoldingRegisters {
        address: u16,
        quantity: u16,
    },
    ReadInputRegisters {
        address: u16,
        quantity: u16,
    },
    /// `value` is kept raw: only 0xFF00 and 0x0000 are legal, and devices must reject the rest.
    WriteSingleCoil {
        address: u16,
        value: u16,
    },
    WriteSingleRegister {
        address: u16,
        value: u16,
    },
    /// FC 07 (spec 6.7): the function code alone.
    ReadExceptionStatus,
    /// FC 08; `data` is the data field as sent. Spec 6.8 gives it as N x 2 bytes, 2 for every sub-function but
    /// 00, whose data of any length are echoed: the length per sub-function is the server's check (exception
    /// 03, "Data Value == OK" in figure 18), not a framing rule, so any length decodes.
    Diagnostics {
        sub_function: u16,
        data: Vec<u8>,
    },
    /// FC 0B (spec 6.9): the function code alone.
    GetCommEventCounter,
    /// FC 0C (spec 6.10): the function code alone.
    GetCommEventLog,
    /// FC 0F; `data` packs the coils LSB-first; its length must be ceil(quantity / 8).
    WriteMultipleCoils {
        address: u16,
        quantity: u16,
        data: Vec<u8>,
    },
    WriteMultipleRegisters {
        address: u16,
        values: Vec<u16>,
    },
    /// FC 11 (spec 6.13): the function code alone.
    ReportServerId,
    /// FC 14 (spec 6.14): the byte count is 7 x the sub-requests.
    ReadFileRecord {
        sub_requests: Vec<FileRecordRef>,
    },
    /// FC 15 (spec 6.15): the request data length counts every sub-request with its data.
    WriteFileRecord {
        sub_requests: Vec<FileRecordWrite>,
    },
    /// FC 16 (spec 6.16): result = (current AND and_mask) OR (or_mask AND NOT and_mask).
    MaskWriteRegister {
        address: u16,
        and_mask: u16,
        or_mask: u16,
    },
    ReadWriteMultipleRegisters {
        read_address: u16,
        read_quantity: u16,
        write_address: u16,
        values: Vec<u16>,
    },
    /// FC 18 (spec 6.18): the FIFO pointer address.
    ReadFifoQueue {
        address: u16,
    },
    /// FC 2B / MEI 0D (SD2x object dictionary access).
    CanOpen(CanOpenAccess),
    /// FC 2B / MEI 0E.
    ReadDeviceId {
        read_code: u8,
        object_id: u8,
    },
    /// FC 41.
    VendorRead {
        mnemonic: Mnemonic,
    },
    /// FC 42; `params` is the ASCII parameter string (e.g. `=0,1,0`).
    VendorWrite {
        mnemonic: Mnemonic,
        params: Vec<u8>,
    },
    /// Any other function code (or MEI type): kept as bytes.
    Raw {
        function: FunctionCode,
        data: Vec<u8>,
    },
}

/// A response PDU.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Response {
    /// FC 01; packed bits, LSB = first coil.
    ReadCoils {
        data: Vec<u8>,
    },
    ReadDiscreteInputs {
        data: Vec<u8>,
    },
    ReadHoldingRegisters {
        values: Vec<u16>,
    },
    ReadInputRegisters {
        values: Vec<u16>,
    },
    WriteSingleCoil {
        address: u16,
        value: u16,
    },
    WriteSingleRegister {
        address: u16,
        value: u16,
    },
    /// FC 07 (spec 6.7): the eight exception status outputs, output 0 in bit 0.
    ReadExceptionStatus {
        status: u8,
    },
    Diagnostics {
        sub_function: u16,
        data: Vec<u8>,
    },
    /// FC 0B (spec 6.9): `status` is 0xFFFF while a program command is in progress, else 0.
    GetCommEventCounter {
        status: u16,
        event_count: u16,
    },
    /// FC 0C (spec 6.10): status and event count as FC 0B gives them, the bus message count, and up to 64
    /// event bytes, the most recent first. The byte count is 6 + the events.
    GetCommEventLog {
        status: u16,
        event_count: u16,
        message_count: u16,
        events: Vec<u8>,
    },
    WriteMultipleCoils {
        address: u16,
        quantity: u16,
    },
    WriteMultipleRegisters {
        address: u16,
        quantity: u16,
    },
    /// FC 11 (spec 6.13): the bytes the byte count counts: the server id (device specific length), the run
    /// indicator status (0x00 off, 0xFF on) and device specific additional data. Only the device knows where
    /// its id ends; [`Response::report_server_id_parts`] splits them given the id's length.
    ReportServerId {
        data: Vec<u8>,
    },
    /// FC 14 (spec 6.14): one sub-response per sub-request.
    ReadFileRecord {
        sub_responses: Vec<FileRecordData>,
    },
    /// FC 15 (spec 6.15): an echo of the request.
    WriteFileRecord {
        sub_requests: Vec<FileRecordWrite>,
    },
    /// FC 16 (spec 6.16): an echo of the request.
    MaskWriteRegister {
        address: u16,
        and_mask: u16,
        or_mask: u16,
    },
    ReadWriteMultipleRegisters {
        values: Vec<u16>,
    },
    /// FC 18 (spec 6.18): the queued registers (at most 31), preceded on the wire by a 2-byte byte count and
    /// the FIFO count.
    ReadFifoQueue {
        values: Vec<u16>,
    },
    CanOpen(CanOpenAccess),
    /// SD2x extended exception: AB FF 00 06 0D CE + 4-byte SDO error code (little-endian on the wire).
    CanOpenError {
        sdo_code: u32,
    },
    ReadDeviceId(DeviceIdResponse),
    /// FC 41: 1-byte count + ASCII parameter string.
    VendorRead {
        params: Vec<u8>,
    },
    /// FC 42: bytes written + mnemonic.
    VendorWrite {
        written: u8,
        mnemonic: Mnemonic,
    },
    /// 0x80|FC + exception code.
    Exception {
        function: FunctionCode,
        code: ExceptionCode,
    },
    Raw {
        function: FunctionCode,
        data: Vec<u8>,
    },
}

fn bits_len(quantity: u16) -> usize {
    super::bits::byte_count(quantity)
}

fn put_u16(out: &mut Vec<u8>, v: u16) {
    out.extend_from_slice(&v.to_be_bytes());
}

fn put_regs(out: &mut Vec<u8>, field: &'static str, values: &[u16]) -> Result<(), EncodeError> {
    let bc = values.len() * 2;
    if bc > 255 {
        return Err(EncodeError::TooLong {
            field,
            len: values.len(),
            max: 127,
        });
    }
    out.push(bc as u8);
    for v in values {
        put_u16(out, *v);
    }
    Ok(())
}

fn put_counted(out: &mut Vec<u8>, field: &'static str, data: &[u8]) -> Result<(), EncodeError> {
    if data.len() > 255 {
        return Err(EncodeError::TooLong {
            field,
            len: data.len(),
            max: 255,
        });
    }
    out.push(data.len() as u8);
    out.extend_from_slice(data);
    Ok(())
}

fn encode_canopen(out: &mut Vec<u8>, a: &CanOpenAccess) {
    out.extend_from_slice(&[
        FunctionCode::ENCAPSULATED_INTERFACE.0,
        mei::CANOPEN,
        a.control,
        a.reserved,
        a.node_id,
    ]);
    put_u16(out, a.index);
    out.push(a.subindex);
    put_u16(out, a.offset);
    put_u16(out, a.byte_count);
    out.extend_from_slice(&a.data);
}

fn decode_canopen(r: &mut Reader<'_>, dir: Direction) -> Result<CanOpenAccess, DecodeError> {
    let control = r.u8("control code")?;
    let reserved = r.u8("reserved")?;
    let node_id = r.u8("node id")?;
    let index = r.u16("index")?;
    let subindex = r.u8("subindex")?;
    let offset = r.u16("address offset")?;
    let bc_at = r.pos();
    let byte_count = r.u16("byte count")?;
    let data_at = r.pos();
    let data = r.rest().to_vec();
    let write = control & CanOpenAccess::WRITE != 0;
    // Which lengths the data field may have, per direction and access.
    let (ok, expected, basis) = match (dir, write) {
        (Direction::Request, false) => (data.is_empty(), 0, "read request (no data)"),
        (Direction::Request, true) => (
            data.len() == byte_count as usize,
            byte_count as usize,
            "write request data",
        ),
        (Direction::Response, false) => (
            data.len() == byte_count as usize,
            byte_count as usize,
            "read response data",
        ),
        (Direction::Response, true) => (
            data.is_empty() || data.len() == byte_count as usize,
            byte_count as usize,
            "write response data (none or echoed)",
        ),
    };
    if !ok {
        let _ = bc_at;
        return Err(mismatch(data_at, "data", data.len(), expected, basis));
    }
    Ok(CanOpenAccess {
        control,
        reserved,
        node_id,
        index,
        subindex,
        offset,
        byte_count,
        data,
    })
}

fn check_len(pdu: &[u8]) -> Result<(), DecodeError> {
    if pdu.is_empty() {
        return Err(DecodeError::new(0, DecodeErrorKind::Empty));
    }
    if pdu.len() > MAX_PDU_LEN {
        return Err(DecodeError::new(
            MAX_PDU_LEN,
            DecodeErrorKind::PduTooLong { len: pdu.len() },
        ));
    }
    Ok(())
}

/// The SD2x extended exception after its function code: AB FF, length, MEI 0D, CE, SDO code (LE).
fn decode_extended_exception(r: &mut Reader<'_>) -> Result<Response, DecodeError> {
    r.u8("exception code")?;
    let at = r.pos();
    let len = r.u16("extended exception length")? as usize;
    if len != r.remaining() {
        return Err(mismatch(
            at,
            "extended exception length",
            len,
            r.remaining(),
            "bytes present",
        ));
    }
    let m_at = r.pos();
    let m = r.u8("MEI type")?;
    if m != mei::CANOPEN {
        return Err(DecodeError::new(
            m_at,
            DecodeErrorKind::InvalidField {
                field: "MEI type",
                value: m as u32,
                rule: "an extended exception carries MEI 0x0D",
            },
        ));
    }
    let c_at = r.pos();
    let c = r.u8("extended exception code")?;
    if c != 0xCE {
        return Err(DecodeError::new(
            c_at,
            DecodeErrorKind::InvalidField {
                field: "extended exception code",
                value: c as u32,
                rule: "only 0xCE (SDO error) is defined",
            },
        ));
    }
    let b = r.take("SDO error code", 4)?;
    Ok(Response::CanOpenError {
        sdo_code: u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
    })
}

/// A field that must hold one of a closed set of values.
fn one_of(
    r: &mut Reader<'_>,
    field: &'static str,
    allowed: &[u8],
    rule: &'static str,
) -> Result<u8, DecodeError> {
    let at = r.pos();
    let v = r.u8(field)?;
    if !allowed.contains(&v) {
        return Err(DecodeError::new(
            at,
            DecodeErrorKind::InvalidField {
                field,
                value: u32::from(v),
                rule,
            },
        ));
    }
    Ok(v)
}

/// FC 2B/0E response after its MEI type (spec 6.21): the read device id code, conformity level and more follows
/// fields hold one of the values the spec lists, and the next object id is 00 when no more follows.
fn decode_device_id_response(r: &mut Reader<'_>) -> Result<DeviceIdResponse, DecodeError> {
    let read_code = one_of(
        r,
        "read device id code",
        &[1, 2, 3, 4],
        "01 to 04 (spec 6.21)",
    )?;
    let conformity = one_of(
        r,
        "conformity level",
        &[0x01, 0x02, 0x03, 0x81, 0x82, 0x83],
        "0x01-0x03 or 0x81-0x83 (spec 6.21)",
    )?;
    let more_follows = one_of(r, "more follows", &[0x00, 0xFF], "0x00 or 0xFF (spec 6.21)")?;
    let at = r.pos();
    let next_object_id = r.u8("next object id")?;
    if more_follows == 0 && next_object_id != 0 {
        return Err(DecodeError::new(
            at,
            DecodeErrorKind::InvalidField {
                field: "next object id",
                value: u32::from(next_object_id),
                rule: "must be 00 when more follows is 00 (spec 6.21)",
            },
        ));
    }
    let n = r.u8("number of objects")?;
    let mut objects = Vec::with_capacity(n.min(32) as usize);
    for _ in 0..n {
        let id = r.u8("object id")?;
        let len = r.u8("object length")? as usize;
        let value = r.take("object value", len)?.to_vec();
        objects.push(DeviceIdObject { id, value });
    }
    Ok(DeviceIdResponse {
        read_code,
        conformity,
        more_follows,
        next_object_id,
        objects,
    })
}

/// FC 0C response after its function code (spec 6.10): byte count N = 6 + the event bytes, at most 64 of them.
fn decode_comm_event_log(r: &mut Reader<'_>) -> Result<Response, DecodeError> {
    let at = r.pos();
    let bc = r.u8("byte count")? as usize;
    if bc != r.remaining() {
        return Err(mismatch(
            at,
            "byte count",
            bc,
            r.remaining(),
            "data bytes present",
        ));
    }
    if bc > 6 + event::LOG_CAPACITY {
        return Err(DecodeError::new(
            at,
            DecodeErrorKind::InvalidField {
                field: "byte count",
                value: bc as u32,
                rule: "status, event count, message count (6 bytes) and 0-64 event bytes (spec 6.10)",
            },
        ));
    }
    Ok(Response::GetCommEventLog {
        status: r.u16("status")?,
        event_count: r.u16("event count")?,
        message_count: r.u16("message count")?,
        events: r.rest().to_vec(),
    })
}

/// FC 11 response after its function code (spec 6.13): a byte count over at least the run indicator status.
fn decode_report_server_id(r: &mut Reader<'_>) -> Result<Response, DecodeError> {
    let at = r.pos();
    let bc = r.u8("byte count")? as usize;
    if bc != r.remaining() {
        return Err(mismatch(
            at,
            "byte count",
            bc,
            r.remaining(),
            "data bytes present",
        ));
    }
    if bc == 0 {
        return Err(DecodeError::new(
            at,
            DecodeErrorKind::InvalidField {
                field: "byte count",
                value: 0,
                rule: "the data hold the run indicator status at least (spec 6.13)",
            },
        ));
    }
    Ok(Response::ReportServerId {
        data: r.rest().to_vec(),
    })
}

/// FC 18 response after its function code (spec 6.18): a 2-byte byte count of the bytes that follow, the FIFO
/// count (at most 31), then that many registers.
fn decode_fifo_response(r: &mut Reader<'_>) -> Result<Response, DecodeError> {
    let at = r.pos();
    let bc = r.u16("byte count")? as usize;
    if bc != r.remaining() {
        return Err(mismatch(
            at,
            "byte count",
            bc,
            r.remaining(),
            "data bytes present",
        ));
    }
    let count_at = r.pos();
    let count = r.u16("FIFO count")?;
    if count > MAX_FIFO_COUNT {
        return Err(DecodeError::new(
            count_at,
            DecodeErrorKind::InvalidField {
                field: "FIFO count",
                value: u32::from(count),
                rule: "at most 31 queued registers (spec 6.18)",
            },
        ));
    }
    let expected = 2 + 2 * usize::from(count);
    if bc != expected {
        return Err(mismatch(at, "byte count", bc, expected, "FIFO count"));
    }
    Ok(Response::ReadFifoQueue {
        values: r.registers("FIFO value registers", 2 * usize::from(count))?,
    })
}

/// A normal (non-exception) response after its function code.
fn decode_normal_response(fc: FunctionCode, r: &mut Reader<'_>) -> Result<Response, DecodeError> {
    Ok(match fc.0 {
        0x01..=0x04 | 0x17 => {
            let at = r.pos();
            let bc = r.u8("byte count")? as usize;
            if bc != r.remaining() {
                return Err(mismatch(
                    at,
                    "byte count",
                    bc,
                    r.remaining(),
                    "data bytes present",
                ));
            }
            if fc.0 >= 0x03 && bc % 2 != 0 {
                return Err(DecodeError::new(
                    at,
                    DecodeErrorKind::InvalidField {
                        field: "byte count",
                        value: bc as u32,
                        rule: "register data must be an even number of bytes",
                    },
                ));
            }
            match fc.0 {
                0x01 => Response::ReadCoils {
                    data: r.take("coil status", bc)?.to_vec(),
                },
                0x02 => Response::ReadDiscreteInputs {
                    data: r.take("input status", bc)?.to_vec(),
                },
                0x03 => Response::ReadHoldingRegisters {
                    values: r.registers("register values", bc)?,
                },
                0x04 => Response::ReadInputRegisters {
                    values: r.registers("register values", bc)?,
                },
                _ => Response::ReadWriteMultipleRegisters {
                    values: r.registers("register values", bc)?,
                },
            }
        }
        0x05 => Response::WriteSingleCoil {
            address: r.u16("output address")?,
            value: r.u16("output value")?,
        },
        0x06 => Response::WriteSingleRegister {
            address: r.u16("register address")?,
            value: r.u16("register value")?,
        },
        0x07 => Response::ReadExceptionStatus {
            status: r.u8("output data")?,
        },
        0x08 => Response::Diagnostics {
            sub_function: r.u16("sub-function")?,
            data: r.rest().to_vec(),
        },
        0x0B => Response::GetCommEventCounter {
            status: r.u16("status")?,
            event_count: r.u16("event count")?,
        },
        0x0C => decode_comm_event_log(r)?,
        0x0F => Response::WriteMultipleCoils {
            address: r.u16("starting address")?,
            quantity: r.u16("quantity of outputs")?,
        },
        0x10 => Response::WriteMultipleRegisters {
            address: r.u16("starting address")?,
            quantity: r.u16("quantity of registers")?,
        },
        0x11 => decode_report_server_id(r)?,
        0x14 => Response::ReadFileRecord {
            sub_responses: file_record::decode_read_response(r)?,
        },
        0x15 => Response::WriteFileRecord {
            sub_requests: file_record::decode_write(r, "response data length")?,
        },
        0x16 => Response::MaskWriteRegister {
            address: r.u16("reference address")?,
            and_mask: r.u16("AND mask")?,
            or_mask: r.u16("OR mask")?,
        },
        0x18 => decode_fifo_response(r)?,
        0x2B => {
            let m = r.u8("MEI type")?;
            match m {
                mei::CANOPEN => Response::CanOpen(decode_canopen(r, Direction::Response)?),
                mei::DEVICE_ID => Response::ReadDeviceId(decode_device_id_response(r)?),
                _ => {
                    let mut data = vec![m];
                    data.extend_from_slice(r.rest());
                    Response::Raw { function: fc, data }
                }
            }
        }
        0x41 => {
            let at = r.pos();
            let bc = r.u8("byte count")? as usize;
            if bc != r.remaining() {
                return Err(mismatch(
                    at,
                    "byte count",
                    bc,
                    r.remaining(),
                    "parameter bytes present",
                ));
            }
            Response::VendorRead {
                params: r.rest().to_vec(),
            }
        }
        0x42 => Response::VendorWrite {
            written: r.u8("bytes written")?,
            mnemonic: Mnemonic(r.take("mnemonic", 4)?.try_into().unwrap_or([0; 4])),
        },
        _ => Response::Raw {
            function: fc,
            data: r.rest().to_vec(),
        },
    })
}

impl Request {
    /// A read of `quantity` items from `address` with one of the four read codes (FC 01-04); `None` for
    /// another code.
    pub fn read(function: FunctionCode, address: u16, quantity: u16) -> Option<Self> {
        Some(match function {
            FunctionCode::READ_COILS => Request::ReadCoils { address, quantity },
            FunctionCode::READ_DISCRETE_INPUTS => Request::ReadDiscreteInputs { address, quantity },
            FunctionCode::READ_HOLDING_REGISTERS => {
                Request::ReadHoldingRegisters { address, quantity }
            }
            FunctionCode::READ_INPUT_REGISTERS => Request::ReadInputRegisters { address, quantity },
            _ => return None,
        })
    }

    /// The function code this request carries.
    pub fn function(&self) -> FunctionCode {
        use Request::*;
        match self {
            ReadCoils { .. } => FunctionCode::READ_COILS,
            ReadDiscreteInputs { .. } => FunctionCode::READ_DISCRETE_INPUTS,
            ReadHoldingRegisters { .. } => FunctionCode::READ_HOLDING_REGISTERS,
            ReadInputRegisters { .. } => FunctionCode::READ_INPUT_REGISTERS,
            WriteSingleCoil { .. } => FunctionCode::WRITE_SINGLE_COIL,
            WriteSingleRegister { .. } => FunctionCode::WRITE_SINGLE_REGISTER,
            ReadExceptionStatus => FunctionCode::READ_EXCEPTION_STATUS,
            Diagnostics { .. } => FunctionCode::DIAGNOSTICS,
            GetCommEventCounter => FunctionCode::GET_COMM_EVENT_COUNTER,
            GetCommEventLog => FunctionCode::GET_COMM_EVENT_LOG,
            WriteMultipleCoils { .. } => FunctionCode::WRITE_MULTIPLE_COILS,
            WriteMultipleRegisters { .. } => FunctionCode::WRITE_MULTIPLE_REGISTERS,
            ReportServerId => FunctionCode::REPORT_SERVER_ID,
            ReadFileRecord { .. } => FunctionCode::READ_FILE_RECORD,
            WriteFileRecord { .. } => FunctionCode::WRITE_FILE_RECORD,
            MaskWriteRegister { .. } => FunctionCode::MASK_WRITE_REGISTER,
            ReadWriteMultipleRegisters { .. } => FunctionCode::READ_WRITE_MULTIPLE_REGISTERS,
            ReadFifoQueue { .. } => FunctionCode::READ_FIFO_QUEUE,
            CanOpen(_) | ReadDeviceId { .. } => FunctionCode::ENCAPSULATED_INTERFACE,
            VendorRead { .. } => FunctionCode::VENDOR_READ,
            VendorWrite { .. } => FunctionCode::VENDOR_WRITE,
            Raw { function, .. } => *function,
        }
    }

    /// Strictly decode one request PDU occupying all of `pdu`.
    pub fn decode(pdu: &[u8]) -> Result<Self, DecodeError> {
        check_len(pdu)?;
        let mut r = Reader::new(pdu);
        let fc = FunctionCode(r.u8("function code")?);
        let req = match fc.0 {
            0x01..=0x04 => {
                let address = r.u16("starting address")?;
                let quantity = r.u16("quantity")?;
                match fc.0 {
                    0x01 => Request::ReadCoils { address, quantity },
                    0x02 => Request::ReadDiscreteInputs { address, quantity },
                    0x03 => Request::ReadHoldingRegisters { address, quantity },
                    _ => Request::ReadInputRegisters { address, quantity },
                }
            }
            0x05 => Request::WriteSingleCoil {
                address: r.u16("output address")?,
                value: r.u16("output value")?,
            },
            0x06 => Request::WriteSingleRegister {
                address: r.u16("register address")?,
                value: r.u16("register value")?,
            },
            0x07 => Request::ReadExceptionStatus,
            0x08 => Request::Diagnostics {
                sub_function: r.u16("sub-function")?,
                data: r.rest().to_vec(),
            },
            0x0B => Request::GetCommEventCounter,
            0x0C => Request::GetCommEventLog,
            0x0F => {
                let address = r.u16("starting address")?;
                let quantity = r.u16("quantity of outputs")?;
                let at = r.pos();
                let bc = r.u8("byte count")? as usize;
                if bc != bits_len(quantity) {
                    return Err(mismatch(
                        at,
                        "byte count",
                        bc,
                        bits_len(quantity),
                        "quantity of outputs",
                    ));
                }
                let data = r.take("output values", bc)?.to_vec();
                Request::WriteMultipleCoils {
                    address,
                    quantity,
                    data,
                }
            }
            0x10 => {
                let address = r.u16("starting address")?;
                let quantity = r.u16("quantity of registers")?;
                let at = r.pos();
                let bc = r.u8("byte count")? as usize;
                if bc != quantity as usize * 2 {
                    return Err(mismatch(
                        at,
                        "byte count",
                        bc,
                        quantity as usize * 2,
                        "quantity of registers",
                    ));
                }
                let values = r.registers("register values", bc)?;
                Request::WriteMultipleRegisters { address, values }
            }
            0x11 => Request::ReportServerId,
            0x14 => Request::ReadFileRecord {
                sub_requests: file_record::decode_read_request(&mut r)?,
            },
            0x15 => Request::WriteFileRecord {
                sub_requests: file_record::decode_write(&mut r, "request data length")?,
            },
            0x16 => Request::MaskWriteRegister {
                address: r.u16("reference address")?,
                and_mask: r.u16("AND mask")?,
                or_mask: r.u16("OR mask")?,
            },
            0x17 => {
                let read_address = r.u16("read starting address")?;
                let read_quantity = r.u16("quantity to read")?;
                let write_address = r.u16("write starting address")?;
                let wq = r.u16("quantity to write")?;
                let at = r.pos();
                let bc = r.u8("write byte count")? as usize;
                if bc != wq as usize * 2 {
                    return Err(mismatch(
                        at,
                        "write byte count",
                        bc,
                        wq as usize * 2,
                        "quantity to write",
                    ));
                }
                let values = r.registers("write register values", bc)?;
                Request::ReadWriteMultipleRegisters {
                    read_address,
                    read_quantity,
                    write_address,
                    values,
                }
            }
            0x18 => Request::ReadFifoQueue {
                address: r.u16("FIFO pointer address")?,
            },
            0x2B => {
                let m = r.u8("MEI type")?;
                match m {
                    mei::CANOPEN => Request::CanOpen(decode_canopen(&mut r, Direction::Request)?),
                    mei::DEVICE_ID => Request::ReadDeviceId {
                        read_code: r.u8("read device id code")?,
                        object_id: r.u8("object id")?,
                    },
                    _ => {
                        let mut data = vec![m];
                        data.extend_from_slice(r.rest());
                        Request::Raw { function: fc, data }
                    }
                }
            }
            0x41 => Request::VendorRead {
                mnemonic: Mnemonic(r.take("mnemonic", 4)?.try_into().unwrap_or([0; 4])),
            },
            0x42 => {
                let mnemonic = Mnemonic(r.take("mnemonic", 4)?.try_into().unwrap_or([0; 4]));
                let at = r.pos();
                let bc = r.u8("byte count")? as usize;
                if bc != r.remaining() {
                    return Err(mismatch(
                        at,
                        "byte count",
                        bc,
                        r.remaining(),
                        "parameter bytes present",
                    ));
                }
                Request::VendorWrite {
                    mnemonic,
                    params: r.rest().to_vec(),
                }
            }
            _ => Request::Raw {
                function: fc,
                data: r.rest().to_vec(),
            },
        };
        r.finish()?;
        Ok(req)
    }

    /// The request a PDU longer than its layout carries, read by the layout (its length and count fields), and
    /// how many bytes follow it: a PDU with bytes after a complete request, or an FC 0x42 whose byte count is
    /// less than the parameter bytes carried. `None` for any other PDU.
    pub fn decode_layout_prefix(pdu: &[u8]) -> Option<(Request, usize)> {
        let extra = match Self::decode(pdu) {
            Err(DecodeError {
                kind: DecodeErrorKind::TrailingBytes { extra },
                ..
            }) => extra,
            Err(DecodeError {
                kind:
                    DecodeErrorKind::ByteCountMismatch {
                        declared,
                        expected,
                        basis: "parameter bytes present",
                        ..
                    },
                ..
            }) if declared < expected => expected - declared,
            _ => return None,
        };
        let prefix = pdu.get(..pdu.len().checked_sub(extra)?)?;
        Some((Self::decode(prefix).ok()?, extra))
    }

    /// Append the PDU bytes to `out`; on error `out` is left as it was.
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        let start = out.len();
        let r = self.encode_unrestored(out);
        if r.is_err() {
            out.truncate(start);
        }
        r
    }

    fn encode_unrestored(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        use Request::*;
        let start = out.len();
        if !matches!(self, CanOpen(_)) {
            out.push(self.function().0);
        }
        match self {
            ReadCoils { address, quantity }
            | ReadDiscreteInputs { address, quantity }
            | ReadHoldingRegisters { address, quantity }
            | ReadInputRegisters { address, quantity } => {
                put_u16(out, *address);
                put_u16(out, *quantity);
            }
            WriteSingleCoil { address, value } | WriteSingleRegister { address, value } => {
                put_u16(out, *address);
                put_u16(out, *value);
            }
            ReadExceptionStatus | GetCommEventCounter | GetCommEventLog | ReportServerId => {}
            Diagnostics { sub_function, data } => {
                put_u16(out, *sub_function);
                out.extend_from_slice(data);
            }
            ReadFileRecord { sub_requests } => file_record::encode_read_request(out, sub_requests)?,
            WriteFileRecord { sub_requests } => {
                file_record::encode_write(out, "request data length", sub_requests)?
            }
            MaskWriteRegister {
                address,
                and_mask,
                or_mask,
            } => {
                put_u16(out, *address);
                put_u16(out, *and_mask);
                put_u16(out, *or_mask);
            }
            ReadFifoQueue { address } => put_u16(out, *address),
            WriteMultipleCoils {
                address,
                quantity,
                data,
            } => {
                put_u16(out, *address);
                put_u16(out, *quantity);
                put_counted(out, "output values", data)?;
            }
            WriteMultipleRegisters { address, values } => {
                put_u16(out, *address);
                put_u16(out, values.len() as u16);
                put_regs(out, "register values", values)?;
            }
            ReadWriteMultipleRegisters {
                read_address,
                read_quantity,
                write_address,
                values,
            } => {
                put_u16(out, *read_address);
                put_u16(out, *read_quantity);
                put_u16(out, *write_address);
                put_u16(out, values.len() as u16);
                put_regs(out, "write register values", values)?;
            }
            CanOpen(a) => encode_canopen(out, a),
            ReadDeviceId {
                read_code,
                object_id,
            } => out.extend_from_slice(&[mei::DEVICE_ID, *read_code, *object_id]),
            VendorRead { mnemonic } => out.extend_from_slice(&mnemonic.0),
            VendorWrite { mnemonic, params } => {
                out.extend_from_slice(&mnemonic.0);
                put_counted(out, "parameter string", params)?;
            }
            Raw { data, .. } => out.extend_from_slice(data),
        }
        if out.len() - start > MAX_PDU_LEN {
            let len = out.len() - start;
            out.truncate(start);
            return Err(EncodeError::TooLong {
                field: "PDU",
                len,
                max: MAX_PDU_LEN,
            });
        }
        Ok(())
    }

    /// The PDU as a fresh byte vector.
    pub fn to_bytes(&self) -> Result<Vec<u8>, EncodeError> {
        let mut v = Vec::with_capacity(16);
        self.encode(&mut v)?;
        Ok(v)
    }
}

impl Response {
    /// The function code byte this response carries (0x80|FC for exceptions).
    pub fn function(&self) -> FunctionCode {
        use Response::*;
        match self {
            ReadCoils { .. } => FunctionCode::READ_COILS,
            ReadDiscreteInputs { .. } => FunctionCode::READ_DISCRETE_INPUTS,
            ReadHoldingRegisters { .. } => FunctionCode::READ_HOLDING_REGISTERS,
            ReadInputRegisters { .. } => FunctionCode::READ_INPUT_REGISTERS,
            WriteSingleCoil { .. } => FunctionCode::WRITE_SINGLE_COIL,
            WriteSingleRegister { .. } => FunctionCode::WRITE_SINGLE_REGISTER,
            ReadExceptionStatus { .. } => FunctionCode::READ_EXCEPTION_STATUS,
            Diagnostics { .. } => FunctionCode::DIAGNOSTICS,
            GetCommEventCounter { .. } => FunctionCode::GET_COMM_EVENT_COUNTER,
            GetCommEventLog { .. } => FunctionCode::GET_COMM_EVENT_LOG,
            WriteMultipleCoils { .. } => FunctionCode::WRITE_MULTIPLE_COILS,
            WriteMultipleRegisters { .. } => FunctionCode::WRITE_MULTIPLE_REGISTERS,
            ReportServerId { .. } => FunctionCode::REPORT_SERVER_ID,
            ReadFileRecord { .. } => FunctionCode::READ_FILE_RECORD,
            WriteFileRecord { .. } => FunctionCode::WRITE_FILE_RECORD,
            MaskWriteRegister { .. } => FunctionCode::MASK_WRITE_REGISTER,
            ReadWriteMultipleRegisters { .. } => FunctionCode::READ_WRITE_MULTIPLE_REGISTERS,
            ReadFifoQueue { .. } => FunctionCode::READ_FIFO_QUEUE,
            CanOpen(_) | ReadDeviceId(_) => FunctionCode::ENCAPSULATED_INTERFACE,
            CanOpenError { .. } => FunctionCode::ENCAPSULATED_INTERFACE.exception(),
            VendorRead { .. } => FunctionCode::VENDOR_READ,
            VendorWrite { .. } => FunctionCode::VENDOR_WRITE,
            Exception { function, .. } => *function,
            Raw { function, .. } => *function,
        }
    }

    /// An exception response to `request_fc` (sets the high bit).
    pub fn exception(request_fc: FunctionCode, code: ExceptionCode) -> Self {
        Response::Exception {
            function: request_fc.exception(),
            code,
        }
    }

    /// True for exception responses (including the SD2x extended one).
    pub fn is_exception(&self) -> bool {
        self.function().is_exception()
    }

    /// An FC 11 response's data split as a device with a `server_id_len`-byte server id lays them out: (server
    /// id, run indicator status, additional data); `None` for another response or data too short.
    pub fn report_server_id_parts(&self, server_id_len: usize) -> Option<(&[u8], u8, &[u8])> {
        let Response::ReportServerId { data } = self else {
            return None;
        };
        let (id, rest) = data.split_at_checked(server_id_len)?;
        let (run, additional) = rest.split_first()?;
        Some((id, *run, additional))
    }

    /// Strictly decode one response PDU occupying all of `pdu`.
    pub fn decode(pdu: &[u8]) -> Result<Self, DecodeError> {
        check_len(pdu)?;
        let mut r = Reader::new(pdu);
        let fc = FunctionCode(r.u8("function code")?);
        let resp = if fc == FunctionCode::ENCAPSULATED_INTERFACE.exception()
            && pdu.get(1) == Some(&ExceptionCode::EXTENDED.0)
        {
            decode_extended_exception(&mut r)?
        } else if fc.is_exception() {
            Response::Exception {
                function: fc,
                code: ExceptionCode(r.u8("exception code")?),
            }
        } else {
            decode_normal_response(fc, &mut r)?
        };
        r.finish()?;
        Ok(resp)
    }

    /// Append the PDU bytes to `out`; on error `out` is left as it was.
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        let start = out.len();
        let r = self.encode_unrestored(out);
        if r.is_err() {
            out.truncate(start);
        }
        r
    }

    fn encode_unrestored(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        use Response::*;
        let start = out.len();
        match self {
            CanOpen(a) => encode_canopen(out, a),
            CanOpenError { sdo_code } => {
                out.extend_from_slice(&[
                    FunctionCode::ENCAPSULATED_INTERFACE.exception().0,
                    ExceptionCode::EXTENDED.0,
                    0x00,
                    0x06,
                    mei::CANOPEN,
                    0xCE,
                ]);
                out.extend_from_slice(&sdo_code.to_le_bytes());
            }
            _ => {
                out.push(self.function().0);
                match self {
                    ReadCoils { data } | ReadDiscreteInputs { data } => {
                        put_counted(out, "status bytes", data)?
                    }
                    ReadHoldingRegisters { values }
                    | ReadInputRegisters { values }
                    | ReadWriteMultipleRegisters { values } => {
                        put_regs(out, "register values", values)?
                    }
                    WriteSingleCoil { address, value } | WriteSingleRegister { address, value } => {
                        put_u16(out, *address);
                        put_u16(out, *value);
                    }
                    Diagnostics { sub_function, data } => {
                        put_u16(out, *sub_function);
                        out.extend_from_slice(data);
                    }
                    WriteMultipleCoils { address, quantity }
                    | WriteMultipleRegisters { address, quantity } => {
                        put_u16(out, *address);
                        put_u16(out, *quantity);
                    }
                    ReadExceptionStatus { status } => out.push(*status),
                    GetCommEventCounter {
                        status,
                        event_count,
                    } => {
                        put_u16(out, *status);
                        put_u16(out, *event_count);
                    }
                    GetCommEventLog {
                        status,
                        event_count,
                        message_count,
                        events,
                    } => {
                        if events.len() > event::LOG_CAPACITY {
                            return Err(EncodeError::TooLong {
                                field: "events",
                                len: events.len(),
                                max: event::LOG_CAPACITY,
                            });
                        }
                        out.push(6 + events.len() as u8);
                        put_u16(out, *status);
                        put_u16(out, *event_count);
                        put_u16(out, *message_count);
                        out.extend_from_slice(events);
                    }
                    // Empty data encode (11 00) but do not decode: spec 6.13 always has the run indicator.
                    ReportServerId { data } => put_counted(out, "server id data", data)?,
                    ReadFileRecord { sub_responses } => {
                        file_record::encode_read_response(out, sub_responses)?
                    }
                    WriteFileRecord { sub_requests } => {
                        file_record::encode_write(out, "response data length", sub_requests)?
                    }
                    MaskWriteRegister {
                        address,
                        and_mask,
                        or_mask,
                    } => {
                        put_u16(out, *address);
                        put_u16(out, *and_mask);
                        put_u16(out, *or_mask);
                    }
                    ReadFifoQueue { values } => {
                        if values.len() > usize::from(MAX_FIFO_COUNT) {
                            return Err(EncodeError::TooLong {
                                field: "FIFO values",
                                len: values.len(),
                                max: usize::from(MAX_FIFO_COUNT),
                            });
                        }
                        put_u16(out, 2 + 2 * values.len() as u16);
                        put_u16(out, values.len() as u16);
                        for v in values {
                            put_u16(out, *v);
                        }
                    }
                    ReadDeviceId(d) => {
                        out.extend_from_slice(&[
                            mei::DEVICE_ID,
                            d.read_code,
                            d.conformity,
                            d.more_follows,
                            d.next_object_id,
                        ]);
                        if d.objects.len() > 255 {
                            return Err(EncodeError::TooLong {
                                field: "objects",
                                len: d.objects.len(),
                                max: 255,
                            });
                        }
                        out.push(d.objects.len() as u8);
                        for o in &d.objects {
                            out.push(o.id);
                            put_counted(out, "object value", &o.value)?;
                        }
                    }
                    VendorRead { params } => put_counted(out, "parameter string", params)?,
                    VendorWrite { written, mnemonic } => {
                        out.push(*written);
                        out.extend_from_slice(&mnemonic.0);
                    }
                    Exception { code, .. } => out.push(code.0),
                    Raw { data, .. } => out.extend_from_slice(data),
                    CanOpen(_) | CanOpenError { .. } => unreachable!("handled above"),
                }
            }
        }
        if out.len() - start > MAX_PDU_LEN {
            let len = out.len() - start;
            out.truncate(start);
            return Err(EncodeError::TooLong {
                field: "PDU",
                len,
                max: MAX_PDU_LEN,
            });
        }
        Ok(())
    }

    /// The PDU as a fresh byte vector.
    pub fn to_bytes(&self) -> Result<Vec<u8>, EncodeError> {
        let mut v = Vec::with_capacity(16);
        self.encode(&mut v)?;
        Ok(v)
    }
}

/// A decoded PDU of either direction.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Pdu {
    Request(Request),
    Response(Response),
}

impl Pdu {
    /// Strictly decode a PDU of the given direction.
    pub fn decode(pdu: &[u8], dir: Direction) -> Result<Self, DecodeError> {
        Ok(match dir {
            Direction::Request => Pdu::Request(Request::decode(pdu)?),
            Direction::Response => Pdu::Response(Response::decode(pdu)?),
        })
    }

    /// Append the PDU bytes to `out`.
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        match self {
            Pdu::Request(r) => r.encode(out),
            Pdu::Response(r) => r.encode(out),
        }
    }
}
