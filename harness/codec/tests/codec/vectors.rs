//! Hand-written codec vectors with exact expectations (in the manner of h2's raw_codec tests): well-formed frames
//! from the manuals, and malformed ones that must fail with a named rule at a named byte.

use std::time::Duration;

use codec::framer::DiscardReason;
use codec::pdu::{Direction, Pdu, Request, Response};
use codec::{
    CanOpenAccess, CharFormat, DecodeError, DecodeErrorKind, DeviceIdObject, DeviceIdResponse,
    ExceptionCode, FieldValue, FramerEvent, FunctionCode, Mnemonic, Parity, RtuFramer, RtuTiming,
    describe, parse_hex, rtu, tcp,
};

/// Bytes written out by hand: `raw![0x01, 0x03, ...]` (a byte array).
macro_rules! raw {
    ($($b:expr),* $(,)?) => {
        [$($b as u8),*]
    };
}

fn err(offset: usize, kind: DecodeErrorKind) -> DecodeError {
    DecodeError { offset, kind }
}

fn mismatch(
    offset: usize,
    field: &'static str,
    declared: usize,
    expected: usize,
    basis: &'static str,
) -> DecodeError {
    err(
        offset,
        DecodeErrorKind::ByteCountMismatch {
            field,
            declared,
            expected,
            basis,
        },
    )
}

fn truncated(offset: usize, field: &'static str, needed: usize, available: usize) -> DecodeError {
    err(
        offset,
        DecodeErrorKind::Truncated {
            field,
            needed,
            available,
        },
    )
}

/// An RTU ADU around `pdu` with its correct CRC (computed independently of the codec's encoder).
fn rtu_frame(address: u8, pdu: &[u8]) -> Vec<u8> {
    let mut v = vec![address];
    v.extend_from_slice(pdu);
    let crc = rtu::crc16(&v);
    v.push(crc as u8);
    v.push((crc >> 8) as u8);
    v
}

/// A Modbus/TCP ADU around `pdu` with the given protocol id and length field.
fn mbap(tid: u16, protocol: u16, length: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut v = Vec::new();
    v.extend_from_slice(&tid.to_be_bytes());
    v.extend_from_slice(&protocol.to_be_bytes());
    v.extend_from_slice(&length.to_be_bytes());
    v.push(unit);
    v.extend_from_slice(pdu);
    v
}

// ---------------------------------------------------------------------------------------------------------------
// SD2x section 6.3: the status read and its CRC
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn sd2x_status_read_request() {
    let frame = raw![0x01, 0x03, 0x07, 0xD0, 0x00, 0x01, 0x84, 0x87];
    assert_eq!(rtu::crc16(&frame[..6]), 0x8784);
    assert!(rtu::crc_ok(&frame));
    let adu = rtu::decode_adu(&frame).unwrap();
    assert_eq!((adu.address, adu.pdu, adu.crc), (1, &frame[1..6], 0x8784));
    let req = Request::ReadHoldingRegisters {
        address: 2000,
        quantity: 1,
    };
    assert_eq!(
        rtu::decode(&frame, Direction::Request),
        Ok((1, Pdu::Request(req.clone())))
    );
    assert_eq!(rtu::encode(1, &Pdu::Request(req.clone())).unwrap(), frame);
    let fields = describe(&Pdu::Request(req));
    let names: Vec<(&str, FieldValue)> = fields.into_iter().map(|f| (f.name, f.value)).collect();
    assert_eq!(
        names,
        vec![
            ("function", FieldValue::Int(3)),
            ("address", FieldValue::Int(2000)),
            ("quantity", FieldValue::Int(1)),
        ]
    );
}

#[test]
fn sd2x_status_read_response() {
    let frame = raw![0x01, 0x03, 0x02, 0x70, 0x38, 0x9C, 0x56];
    assert_eq!(rtu::crc16(&frame[..5]), 0x569C);
    let resp = Response::ReadHoldingRegisters {
        values: vec![0x7038],
    };
    assert_eq!(
        rtu::decode(&frame, Direction::Response),
        Ok((1, Pdu::Response(resp.clone())))
    );
    assert_eq!(rtu::encode(1, &Pdu::Response(resp)).unwrap(), frame);
    // The same bytes are not a valid request: FC 03 requests carry address + quantity, 4 bytes.
    assert_eq!(
        rtu::decode(&frame, Direction::Request),
        Err(truncated(4, "quantity", 2, 1))
    );
}

#[test]
fn crc_mismatch_names_both_values_at_the_crc_offset() {
    let frame = raw![0x01, 0x03, 0x07, 0xD0, 0x00, 0x01, 0x84, 0x88];
    let e = rtu::decode(&frame, Direction::Request).unwrap_err();
    assert_eq!(
        e,
        err(
            6,
            DecodeErrorKind::Crc {
                expected: 0x8784,
                received: 0x8884
            }
        )
    );
    let text = e.to_string();
    assert!(text.contains("at byte 6"), "{text}");
    assert!(text.contains("0x8784"), "{text}");
    assert!(text.contains("bytes 84 87"), "{text}");
    assert!(text.contains("0x8884"), "{text}");
    assert_eq!(rtu::decode_adu(&frame).unwrap_err(), e);
    assert!(!rtu::crc_ok(&frame));
}

#[test]
fn rtu_length_limits() {
    assert_eq!(
        rtu::decode(&raw![0x01, 0x03, 0x84], Direction::Request),
        Err(err(3, DecodeErrorKind::RtuShort { len: 3 }))
    );
    assert_eq!(
        rtu::decode(&[], Direction::Request),
        Err(err(0, DecodeErrorKind::RtuShort { len: 0 }))
    );
    // 257 bytes with a valid CRC: the length rule fires first.
    let long = rtu_frame(1, &[0x65; 254]);
    assert_eq!(long.len(), 257);
    assert_eq!(
        rtu::decode(&long, Direction::Request),
        Err(err(256, DecodeErrorKind::RtuTooLong { len: 257 }))
    );
    // 256 bytes (a 253-byte PDU) is the largest legal ADU.
    let max = rtu_frame(1, &[0x65; 253]);
    assert_eq!(max.len(), 256);
    assert!(rtu::decode(&max, Direction::Request).is_ok());
    // An address and CRC around nothing is below the 4-byte minimum.
    assert_eq!(
        rtu::decode(&rtu_frame(1, &[]), Direction::Request),
        Err(err(3, DecodeErrorKind::RtuShort { len: 3 }))
    );
    assert_eq!(
        rtu::encode_adu(1, &[0; 254], &mut Vec::new()),
        Err(codec::EncodeError::TooLong {
            field: "PDU",
            len: 254,
            max: 253
        })
    );
}

// ---------------------------------------------------------------------------------------------------------------
// MBAP strict checks
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn mbap_valid_frame() {
    let pdu = raw![0x03, 0x07, 0xD0, 0x00, 0x01];
    let frame = mbap(0x1234, 0, 6, 0x11, &pdu);
    let (h, p) = tcp::decode(&frame, Direction::Request).unwrap();
    assert_eq!(
        h,
        tcp::Mbap {
            transaction_id: 0x1234,
            protocol_id: 0,
            length: 6,
            unit_id: 0x11
        }
    );
    assert_eq!(
        p,
        Pdu::Request(Request::ReadHoldingRegisters {
            address: 2000,
            quantity: 1
        })
    );
    assert_eq!(tcp::encode(0x1234, 0x11, &p).unwrap(), frame);
    assert_eq!(tcp::adu_len(&frame[..5]), None);
    assert_eq!(tcp::adu_len(&frame[..6]), Some(12));
}

#[test]
fn mbap_protocol_id_must_be_zero() {
    let frame = mbap(1, 1, 6, 1, &raw![0x03, 0x07, 0xD0, 0x00, 0x01]);
    assert_eq!(
        tcp::decode(&frame, Direction::Request),
        Err(err(2, DecodeErrorKind::ProtocolId { found: 1 }))
    );
    let e = tcp::decode(&frame, Direction::Request)
        .unwrap_err()
        .to_string();
    assert!(e.contains("0x0001"), "{e}");
}

#[test]
fn mbap_length_must_match_the_bytes() {
    let pdu = raw![0x03, 0x07, 0xD0, 0x00, 0x01];
    // says 7 (unit id + 6 PDU bytes), carries 6
    assert_eq!(
        tcp::decode(&mbap(1, 0, 7, 1, &pdu), Direction::Request),
        Err(err(
            4,
            DecodeErrorKind::MbapLength {
                declared: 7,
                actual: 6
            }
        ))
    );
    // says 5, carries 6
    assert_eq!(
        tcp::decode(&mbap(1, 0, 5, 1, &pdu), Direction::Request),
        Err(err(
            4,
            DecodeErrorKind::MbapLength {
                declared: 5,
                actual: 6
            }
        ))
    );
    // says 0
    assert_eq!(
        tcp::decode(&mbap(1, 0, 0, 1, &pdu), Direction::Request),
        Err(err(
            4,
            DecodeErrorKind::MbapLength {
                declared: 0,
                actual: 6
            }
        ))
    );
}

#[test]
fn mbap_too_short() {
    // header only, no function code
    let frame = mbap(1, 0, 1, 1, &[]);
    assert_eq!(frame.len(), 7);
    assert_eq!(
        tcp::decode(&frame, Direction::Request),
        Err(err(7, DecodeErrorKind::MbapShort { len: 7 }))
    );
    assert_eq!(
        tcp::decode(&raw![0x00, 0x01], Direction::Request),
        Err(err(2, DecodeErrorKind::MbapShort { len: 2 }))
    );
}

#[test]
fn mbap_pdu_of_254_bytes_is_too_long() {
    let pdu = vec![0x65u8; 254];
    let frame = mbap(1, 0, 255, 1, &pdu);
    assert_eq!(
        tcp::decode(&frame, Direction::Request),
        Err(err(260, DecodeErrorKind::PduTooLong { len: 254 }))
    );
    // 253 bytes is the limit and passes
    let frame = mbap(1, 0, 254, 1, &pdu[..253]);
    assert_eq!(
        tcp::decode(&frame, Direction::Request).map(|(_, p)| p),
        Ok(Pdu::Request(Request::Raw {
            function: FunctionCode(0x65),
            data: vec![0x65; 252]
        }))
    );
    // the bare PDU check agrees
    assert_eq!(
        Request::decode(&pdu),
        Err(err(253, DecodeErrorKind::PduTooLong { len: 254 }))
    );
    assert_eq!(Request::decode(&[]), Err(err(0, DecodeErrorKind::Empty)));
    assert_eq!(Response::decode(&[]), Err(err(0, DecodeErrorKind::Empty)));
}

// ---------------------------------------------------------------------------------------------------------------
// Byte counts
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn fc10_byte_count_must_match_quantity() {
    // quantity 2 needs 4 bytes; the count says 3
    let pdu = raw![0x10, 0x00, 0x01, 0x00, 0x02, 0x03, 0x00, 0x0A, 0x01];
    let want = mismatch(5, "byte count", 3, 4, "quantity of registers");
    assert_eq!(Request::decode(&pdu), Err(want.clone()));
    assert_eq!(
        rtu::decode(&rtu_frame(1, &pdu), Direction::Request),
        Err(want.clone().shifted(1))
    );
    assert_eq!(
        tcp::decode(
            &mbap(1, 0, pdu.len() as u16 + 1, 1, &pdu),
            Direction::Request
        ),
        Err(want.shifted(7))
    );
    let text = Request::decode(&pdu).unwrap_err().to_string();
    assert!(
        text.contains("at byte 5") && text.contains("says 3") && text.contains("requires 4"),
        "{text}"
    );
    // the consistent frame decodes
    assert_eq!(
        Request::decode(&raw![
            0x10, 0x00, 0x01, 0x00, 0x02, 0x04, 0x00, 0x0A, 0x01, 0x02
        ]),
        Ok(Request::WriteMultipleRegisters {
            address: 1,
            values: vec![0x000A, 0x0102]
        })
    );
    // the count agrees with the quantity, but the data are short
    assert_eq!(
        Request::decode(&raw![0x10, 0x00, 0x01, 0x00, 0x02, 0x04, 0x00, 0x0A, 0x01]),
        Err(truncated(6, "register values", 4, 3))
    );
}

#[test]
fn fc0f_byte_count_must_be_ceil_quantity_over_8() {
    // Modbus spec example: 10 coils from 20 (address 0x13), 2 data bytes CD 01
    assert_eq!(
        Request::decode(&raw![0x0F, 0x00, 0x13, 0x00, 0x0A, 0x02, 0xCD, 0x01]),
        Ok(Request::WriteMultipleCoils {
            address: 0x13,
            quantity: 10,
            data: vec![0xCD, 0x01]
        })
    );
    assert_eq!(
        Request::decode(&raw![0x0F, 0x00, 0x13, 0x00, 0x0A, 0x01, 0xCD]),
        Err(mismatch(5, "byte count", 1, 2, "quantity of outputs"))
    );
    assert_eq!(
        Request::decode(&raw![0x0F, 0x00, 0x13, 0x00, 0x08, 0x02, 0xCD, 0x01]),
        Err(mismatch(5, "byte count", 2, 1, "quantity of outputs"))
    );
    assert!(Request::decode(&raw![0x0F, 0x00, 0x13, 0x00, 0x08, 0x01, 0xCD]).is_ok());
    assert_eq!(
        Request::decode(&raw![0x0F, 0x00, 0x13, 0x00, 0x09, 0x01, 0xCD]),
        Err(mismatch(5, "byte count", 1, 2, "quantity of outputs"))
    );
    assert_eq!(
        Request::decode(&raw![0x0F, 0x00, 0x13, 0x00, 0x00, 0x00]),
        Ok(Request::WriteMultipleCoils {
            address: 0x13,
            quantity: 0,
            data: vec![]
        })
    );
}

#[test]
fn read_response_byte_counts() {
    assert_eq!(
        Response::decode(&raw![0x03, 0x04, 0x70, 0x38]),
        Err(mismatch(1, "byte count", 4, 2, "data bytes present"))
    );
    assert_eq!(
        Response::decode(&raw![0x03, 0x03, 0x70, 0x38, 0x00]),
        Err(err(
            1,
            DecodeErrorKind::InvalidField {
                field: "byte count",
                value: 3,
                rule: "register data must be an even number of bytes"
            }
        ))
    );
    // coils need not be even
    assert_eq!(
        Response::decode(&raw![0x01, 0x01, 0x05]),
        Ok(Response::ReadCoils { data: vec![0x05] })
    );
}

// ---------------------------------------------------------------------------------------------------------------
// Truncation and trailing bytes
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn truncated_pdus_name_the_field() {
    assert_eq!(
        Request::decode(&raw![0x03, 0x07, 0xD0, 0x00]),
        Err(truncated(3, "quantity", 2, 1))
    );
    assert_eq!(
        Request::decode(&raw![0x03]),
        Err(truncated(1, "starting address", 2, 0))
    );
    assert_eq!(
        Request::decode(&raw![0x06, 0x00, 0x01, 0x00]),
        Err(truncated(3, "register value", 2, 1))
    );
    assert_eq!(
        Response::decode(&raw![0x05, 0x00, 0x01, 0xFF]),
        Err(truncated(3, "output value", 2, 1))
    );
    assert_eq!(
        Request::decode(&raw![0x41, 0x20, 0x20]),
        Err(truncated(1, "mnemonic", 4, 2))
    );
    assert_eq!(
        Request::decode(&raw![0x0F, 0x00, 0x13, 0x00, 0x0A, 0x02, 0xCD]),
        Err(truncated(6, "output values", 2, 1))
    );
    assert_eq!(
        Response::decode(&raw![0x83]),
        Err(truncated(1, "exception code", 1, 0))
    );
    // FC 2B/0E: the object claims 5 bytes, 2 follow
    assert_eq!(
        Response::decode(&raw![
            0x2B, 0x0E, 0x01, 0x01, 0x00, 0x00, 0x01, 0x00, 0x05, b'I', b'M'
        ]),
        Err(truncated(9, "object value", 5, 2))
    );
    // FC 2B/0D: the header stops inside the index
    assert_eq!(
        Request::decode(&raw![0x2B, 0x0D, 0x00, 0x00, 0x01, 0x00]),
        Err(truncated(5, "index", 2, 1))
    );
    let text = Request::decode(&raw![0x03, 0x07, 0xD0, 0x00])
        .unwrap_err()
        .to_string();
    assert!(
        text.contains("`quantity`") && text.contains("at byte 3"),
        "{text}"
    );
}

#[test]
fn trailing_bytes_are_rejected() {
    assert_eq!(
        Request::decode(&raw![0x03, 0x07, 0xD0, 0x00, 0x01, 0xFF]),
        Err(err(5, DecodeErrorKind::TrailingBytes { extra: 1 }))
    );
    assert_eq!(
        Response::decode(&raw![0x83, 0x02, 0x00, 0x00]),
        Err(err(2, DecodeErrorKind::TrailingBytes { extra: 2 }))
    );
    // FC 10 response: function, address, quantity, nothing more (MDrive 4.2.5 prints a stray byte count)
    assert_eq!(
        Response::decode(&raw![0x10, 0x00, 0x8A, 0x00, 0x02, 0x04]),
        Err(err(5, DecodeErrorKind::TrailingBytes { extra: 1 }))
    );
    assert_eq!(
        Request::decode(&raw![0x2B, 0x0E, 0x01, 0x00, 0x00]),
        Err(err(4, DecodeErrorKind::TrailingBytes { extra: 1 }))
    );
}

// ---------------------------------------------------------------------------------------------------------------
// FC 2B: SD2x CANopen access, its extended exception, device identification
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn sd2x_extended_exception() {
    let pdu = raw![0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE, 0x0B, 0x00, 0xFF, 0xFF];
    let want = Response::CanOpenError {
        sdo_code: 0xFFFF_000B,
    };
    assert_eq!(Response::decode(&pdu), Ok(want.clone()));
    assert_eq!(want.to_bytes().unwrap(), pdu);
    assert_eq!(want.function(), FunctionCode(0xAB));
    assert!(want.is_exception());
    // over RTU too
    let frame = rtu_frame(1, &pdu);
    assert_eq!(
        rtu::decode(&frame, Direction::Response),
        Ok((1, Pdu::Response(want)))
    );
    // A plain exception to FC 2B is still a plain exception.
    assert_eq!(
        Response::decode(&raw![0xAB, 0x01]),
        Ok(Response::Exception {
            function: FunctionCode(0xAB),
            code: ExceptionCode::ILLEGAL_FUNCTION
        })
    );
}

#[test]
fn sd2x_extended_exception_malformed() {
    // length says 7, 6 bytes follow
    assert_eq!(
        Response::decode(&raw![
            0xAB, 0xFF, 0x00, 0x07, 0x0D, 0xCE, 0x0B, 0x00, 0xFF, 0xFF
        ]),
        Err(mismatch(
            2,
            "extended exception length",
            7,
            6,
            "bytes present"
        ))
    );
    // MEI 0E
    assert_eq!(
        Response::decode(&raw![
            0xAB, 0xFF, 0x00, 0x06, 0x0E, 0xCE, 0x0B, 0x00, 0xFF, 0xFF
        ]),
        Err(err(
            4,
            DecodeErrorKind::InvalidField {
                field: "MEI type",
                value: 0x0E,
                rule: "an extended exception carries MEI 0x0D"
            }
        ))
    );
    // code other than CE
    assert_eq!(
        Response::decode(&raw![
            0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCF, 0x0B, 0x00, 0xFF, 0xFF
        ]),
        Err(err(
            5,
            DecodeErrorKind::InvalidField {
                field: "extended exception code",
                value: 0xCF,
                rule: "only 0xCE (SDO error) is defined"
            }
        ))
    );
    // consistent length, but the SDO code is cut short
    assert_eq!(
        Response::decode(&raw![0xAB, 0xFF, 0x00, 0x05, 0x0D, 0xCE, 0x0B, 0x00, 0xFF]),
        Err(truncated(6, "SDO error code", 4, 3))
    );
}

#[test]
fn sd2x_read_temperature_corrected() {
    // corpus/golden/sd2x.toml, 6.2, corrected bytes (reserved byte inserted)
    let req = raw![
        0x01, 0x2B, 0x0D, 0x00, 0x00, 0x01, 0x00, 0x29, 0x00, 0x00, 0x00, 0x00, 0x02, 0x19, 0x56
    ];
    assert_eq!(
        rtu::decode(&req, Direction::Request),
        Ok((
            1,
            Pdu::Request(Request::CanOpen(CanOpenAccess::read(1, 0x0029, 0, 2)))
        ))
    );
    let resp = raw![
        0x01, 0x2B, 0x0D, 0x00, 0x00, 0x01, 0x00, 0x29, 0x00, 0x00, 0x00, 0x00, 0x02, 0xAA, 0x00,
        0xF5, 0x0E
    ];
    let (_, p) = rtu::decode(&resp, Direction::Response).unwrap();
    let Pdu::Response(Response::CanOpen(a)) = &p else {
        panic!("not a CANopen response: {p:?}");
    };
    assert_eq!(a.data, vec![0xAA, 0x00]);
    assert_eq!(a.value_le(), Some(0xAA), "FC 43 data are little-endian");
    // as printed (reserved byte missing): the header runs one byte short
    let printed = raw![
        0x2B, 0x0D, 0x00, 0x01, 0x00, 0x29, 0x00, 0x00, 0x00, 0x00, 0x02
    ];
    assert_eq!(
        Request::decode(&printed),
        Err(truncated(10, "byte count", 2, 1))
    );
}

#[test]
fn canopen_data_length_rules_per_direction() {
    let head = |control: u8, count: u16| {
        let mut v = raw![
            0x2B, 0x0D, control, 0x00, 0x01, 0x60, 0x40, 0x00, 0x00, 0x00
        ]
        .to_vec();
        v.extend_from_slice(&count.to_be_bytes());
        v
    };
    let with = |mut v: Vec<u8>, data: &[u8]| {
        v.extend_from_slice(data);
        v
    };
    // read request: no data allowed
    assert_eq!(
        Request::decode(&with(head(0x00, 2), &[0x0F, 0x00])),
        Err(mismatch(12, "data", 2, 0, "read request (no data)"))
    );
    // write request: exactly byte_count
    assert_eq!(
        Request::decode(&with(head(0x80, 2), &[0x0F])),
        Err(mismatch(12, "data", 1, 2, "write request data"))
    );
    assert_eq!(
        Request::decode(&with(head(0x80, 2), &[0x0F, 0x00])),
        Ok(Request::CanOpen(CanOpenAccess::write(
            1,
            0x6040,
            0,
            vec![0x0F, 0x00]
        )))
    );
    // read response: exactly byte_count
    assert_eq!(
        Response::decode(&head(0x00, 2)),
        Err(mismatch(12, "data", 0, 2, "read response data"))
    );
    // write response: none, or the data echoed
    assert!(Response::decode(&head(0x80, 2)).is_ok());
    assert!(Response::decode(&with(head(0x80, 2), &[0x0F, 0x00])).is_ok());
    assert_eq!(
        Response::decode(&with(head(0x80, 2), &[0x0F])),
        Err(mismatch(
            12,
            "data",
            1,
            2,
            "write response data (none or echoed)"
        ))
    );
}

#[test]
fn device_identification() {
    assert_eq!(
        Request::decode(&raw![0x2B, 0x0E, 0x01, 0x00]),
        Ok(Request::ReadDeviceId {
            read_code: 1,
            object_id: 0
        })
    );
    let pdu = raw![
        0x2B, 0x0E, 0x01, 0x01, 0x00, 0x00, 0x02, 0x00, 0x03, b'I', b'M', b'S', 0x01, 0x00
    ];
    let want = Response::ReadDeviceId(DeviceIdResponse {
        read_code: 1,
        conformity: 1,
        more_follows: 0,
        next_object_id: 0,
        objects: vec![
            DeviceIdObject {
                id: 0,
                value: b"IMS".to_vec(),
            },
            DeviceIdObject {
                id: 1,
                value: vec![],
            },
        ],
    });
    assert_eq!(Response::decode(&pdu), Ok(want.clone()));
    assert_eq!(want.to_bytes().unwrap(), pdu);
    // another MEI type is kept raw, MEI byte first
    assert_eq!(
        Request::decode(&raw![0x2B, 0x0F, 0x01]),
        Ok(Request::Raw {
            function: FunctionCode(0x2B),
            data: vec![0x0F, 0x01]
        })
    );
}

// ---------------------------------------------------------------------------------------------------------------
// IMS vendor codes 0x41/0x42 and mnemonics
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn mnemonic_wire_form() {
    assert_eq!(
        Mnemonic::from_name("TR"),
        Some(Mnemonic([0x20, 0x20, 0x52, 0x54]))
    );
    assert_eq!(
        Mnemonic::from_name("S13"),
        Some(Mnemonic([0x20, 0x33, 0x31, 0x53]))
    );
    assert_eq!(
        Mnemonic::from_name("E"),
        Some(Mnemonic([0x20, 0x20, 0x20, 0x45]))
    );
    assert_eq!(Mnemonic::from_name("ABCD"), Some(Mnemonic(*b"DCBA")));
    assert_eq!(Mnemonic::from_name(""), None);
    assert_eq!(Mnemonic::from_name("ABCDE"), None);
    for name in ["TR", "S13", "E", "S1", "MU", "ABCD"] {
        let m = Mnemonic::from_name(name).unwrap();
        assert_eq!(m.name(), name);
        assert_eq!(m.to_string(), name);
    }
    assert_eq!(Mnemonic([0x20, 0x20, 0x52, 0x54]).name(), "TR");
}

#[test]
fn vendor_read_and_write() {
    // FC 41 read TR, and its response "0, 0, 0"
    assert_eq!(
        Request::decode(&raw![0x41, 0x20, 0x20, 0x52, 0x54]),
        Ok(Request::VendorRead {
            mnemonic: Mnemonic::from_name("TR").unwrap()
        })
    );
    assert_eq!(
        Response::decode(&raw![0x41, 0x07, b'0', b',', b' ', b'0', b',', b' ', b'0']),
        Ok(Response::VendorRead {
            params: b"0, 0, 0".to_vec()
        })
    );
    // FC 42 write S1 "=0,1,0"
    let pdu = raw![
        0x42, 0x20, 0x20, 0x31, 0x53, 0x06, b'=', b'0', b',', b'1', b',', b'0'
    ];
    let want = Request::VendorWrite {
        mnemonic: Mnemonic::from_name("S1").unwrap(),
        params: b"=0,1,0".to_vec(),
    };
    assert_eq!(Request::decode(&pdu), Ok(want.clone()));
    assert_eq!(want.to_bytes().unwrap(), pdu);
    // count says 5, 6 follow
    let mut bad = pdu;
    bad[5] = 5;
    assert_eq!(
        Request::decode(&bad),
        Err(mismatch(5, "byte count", 5, 6, "parameter bytes present"))
    );
    // The MDrive 4.3.3 misprint: FC 41 carrying a write's count and parameters.
    let mut misprint = pdu;
    misprint[0] = 0x41;
    assert_eq!(
        Request::decode(&misprint),
        Err(err(5, DecodeErrorKind::TrailingBytes { extra: 7 }))
    );
    assert_eq!(
        Response::decode(&raw![0x42, 0x06, 0x20, 0x20, 0x31, 0x53]),
        Ok(Response::VendorWrite {
            written: 6,
            mnemonic: Mnemonic::from_name("S1").unwrap()
        })
    );
}

// ---------------------------------------------------------------------------------------------------------------
// RTU timing
// ---------------------------------------------------------------------------------------------------------------

fn fmt(parity: Parity, stop_bits: u8) -> CharFormat {
    CharFormat { parity, stop_bits }
}

fn assert_near(d: Duration, micros: u64, tolerance_us: u64) {
    let lo = Duration::from_micros(micros - tolerance_us);
    let hi = Duration::from_micros(micros + tolerance_us);
    assert!(
        lo <= d && d <= hi,
        "{d:?} not within {micros} ± {tolerance_us} µs"
    );
}

#[test]
fn rtu_timing() {
    assert_eq!(fmt(Parity::Even, 1).bits(), 11);
    assert_eq!(fmt(Parity::None, 1).bits(), 10);
    assert_eq!(fmt(Parity::None, 2).bits(), 11);
    assert_eq!(fmt(Parity::Odd, 2).bits(), 12);

    // 9600 8E1: 11 bits = 1145.8 µs per character; t3.5 = 4010.4 µs, t1.5 = 1718.75 µs
    let t = RtuTiming::new(9600, fmt(Parity::Even, 1));
    assert_near(t.t3_5, 4010, 1);
    assert_near(t.t1_5, 1719, 1);
    assert_near(t.char_time, 1146, 1);
    assert_near(t.transmit_time(8), 9167, 1);

    // 19200 8N1: 10 bits = 520.8 µs; t3.5 = 1822.9 µs
    let t = RtuTiming::new(19200, fmt(Parity::None, 1));
    assert_near(t.t3_5, 1823, 1);
    assert_near(t.t1_5, 781, 1);

    // above 19200 baud the spec fixes 750 µs and 1750 µs
    for baud in [38400, 115200] {
        for f in [fmt(Parity::None, 1), fmt(Parity::Even, 1)] {
            let t = RtuTiming::new(baud, f);
            assert_eq!(t.t3_5, Duration::from_micros(1750), "{baud}");
            assert_eq!(t.t1_5, Duration::from_micros(750), "{baud}");
        }
    }
}

// ---------------------------------------------------------------------------------------------------------------
// RTU stream framer
// ---------------------------------------------------------------------------------------------------------------

const STATUS_READ: [u8; 8] = [0x01, 0x03, 0x07, 0xD0, 0x00, 0x01, 0x84, 0x87];

fn timing() -> RtuTiming {
    RtuTiming::new(19200, fmt(Parity::Even, 1))
}

fn frames(events: &[FramerEvent]) -> Vec<Vec<u8>> {
    events
        .iter()
        .map(|e| match e {
            FramerEvent::Frame { bytes, .. } => bytes.clone(),
            other => panic!("expected only frames, got {other:?}"),
        })
        .collect()
}

#[test]
fn framer_cuts_two_back_to_back_frames() {
    let second = rtu_frame(
        2,
        &raw![0x10, 0x0B, 0xB8, 0x00, 0x02, 0x04, 0x00, 0x06, 0x03, 0xE8],
    );
    let mut stream = STATUS_READ.to_vec();
    stream.extend_from_slice(&second);
    let mut f = RtuFramer::new(Direction::Request, timing(), Vec::new());
    let t0 = Duration::from_millis(5);
    let ev = f.push(t0, &stream);
    assert_eq!(frames(&ev), vec![STATUS_READ.to_vec(), second.clone()]);
    assert!(f.pending().is_empty());
    assert_eq!(f.deadline(), None);
    let FramerEvent::Frame {
        start,
        end,
        max_gap,
        ..
    } = &ev[0]
    else {
        unreachable!()
    };
    assert_eq!((*start, *end, *max_gap), (t0, t0, Duration::ZERO));

    // the same, one byte at a time with gaps just under t1.5
    let mut f = RtuFramer::new(Direction::Request, timing(), Vec::new());
    let gap = timing().t1_5 - Duration::from_nanos(1);
    let mut t = Duration::ZERO;
    let mut ev = Vec::new();
    for b in &stream {
        ev.extend(f.push(t, &[*b]));
        t += gap;
    }
    assert_eq!(frames(&ev), vec![STATUS_READ.to_vec(), second]);
    let FramerEvent::Frame {
        start,
        end,
        max_gap,
        ..
    } = &ev[0]
    else {
        unreachable!()
    };
    assert_eq!(*start, Duration::ZERO);
    assert_eq!(*end, gap * 7);
    assert_eq!(*max_gap, gap);
}

#[test]
fn framer_reports_bad_crc_after_silence() {
    let bad = raw![0x01, 0x03, 0x07, 0xD0, 0x00, 0x01, 0x84, 0x88].to_vec();
    let mut f = RtuFramer::new(Direction::Request, timing(), Vec::new());
    let t0 = Duration::from_millis(10);
    assert!(f.push(t0, &bad).is_empty(), "a bad CRC is not cut");
    assert_eq!(f.pending(), &bad[..]);
    let t35 = timing().t3_5;
    assert_eq!(f.deadline(), Some(t0 + t35));
    assert!(f.poll(t0 + t35 - Duration::from_nanos(1)).is_empty());
    assert_eq!(
        f.poll(t0 + t35),
        vec![FramerEvent::Discarded {
            bytes: bad,
            at: t0,
            reason: DiscardReason::BadCrc {
                expected: 0x8784,
                received: 0x8884
            }
        }]
    );
    assert!(f.pending().is_empty());
    // the line recovers: the next good frame is cut at once
    assert_eq!(
        frames(&f.push(t0 + t35 * 2, &STATUS_READ)),
        vec![STATUS_READ.to_vec()]
    );
}

#[test]
fn framer_emits_unknown_function_code_only_after_silence() {
    let odd = rtu_frame(1, &raw![0x65, 0x12, 0x34, 0x56]);
    let mut f = RtuFramer::new(Direction::Request, timing(), Vec::new());
    let t0 = Duration::from_millis(1);
    assert!(f.push(t0, &odd).is_empty());
    assert_eq!(f.pending(), &odd[..]);
    let t35 = timing().t3_5;
    assert!(f.poll(t0 + t35 - Duration::from_nanos(1)).is_empty());
    assert_eq!(frames(&f.poll(t0 + t35)), vec![odd.clone()]);

    // the next push after the silence releases it too, before the new bytes are taken
    let mut f = RtuFramer::new(Direction::Request, timing(), Vec::new());
    assert!(f.push(t0, &odd).is_empty());
    let ev = f.push(t0 + t35, &STATUS_READ);
    assert_eq!(frames(&ev), vec![odd, STATUS_READ.to_vec()]);
}

#[test]
fn framer_too_short_and_overlong() {
    let mut f = RtuFramer::new(Direction::Request, timing(), Vec::new());
    assert!(f.push(Duration::ZERO, &[0x01, 0x03]).is_empty());
    assert_eq!(
        f.finish(),
        vec![FramerEvent::Discarded {
            bytes: vec![0x01, 0x03],
            at: Duration::ZERO,
            reason: DiscardReason::TooShort
        }]
    );
    // 257 bytes of an unknown function code without a pause
    let mut f = RtuFramer::new(Direction::Request, timing(), Vec::new());
    let junk = vec![0x00u8; 257];
    let ev = f.push(Duration::ZERO, &junk);
    assert_eq!(
        ev,
        vec![FramerEvent::Discarded {
            bytes: junk,
            at: Duration::ZERO,
            reason: DiscardReason::Overlong
        }]
    );
    assert!(f.pending().is_empty());
}

#[test]
fn framer_canopen_write_response_without_echo() {
    // 2B/0D write response, byte count 2, no data: 15 bytes, although the count alone suggests 17
    let resp = rtu_frame(
        1,
        &raw![
            0x2B, 0x0D, 0x80, 0x00, 0x01, 0x60, 0x40, 0x00, 0x00, 0x00, 0x00, 0x02
        ],
    );
    assert_eq!(resp.len(), 15);
    let mut f = RtuFramer::new(Direction::Response, timing(), Vec::new());
    let ev = f.push(
        Duration::ZERO,
        &[resp.clone(), STATUS_READ.to_vec()].concat(),
    );
    assert_eq!(frames(&ev), vec![resp]);
    // read as a response, 01 03 07 .. announces 7 data bytes: the framer waits for them
    assert_eq!(f.pending(), &STATUS_READ[..]);
}

#[test]
fn framer_vendor_rule_cuts_without_silence() {
    use codec::{LengthRule, VendorRule};
    let odd = rtu_frame(1, &raw![0x65, 0x12, 0x34, 0x56]);
    let rule = VendorRule {
        function: 0x65,
        request: LengthRule::Fixed(7),
        response: LengthRule::ByteCountAt {
            offset: 2,
            width: 1,
            trailer: 2,
        },
    };
    let mut f = RtuFramer::new(Direction::Request, timing(), vec![rule]);
    let ev = f.push(
        Duration::ZERO,
        &[odd.clone(), STATUS_READ.to_vec()].concat(),
    );
    assert_eq!(frames(&ev), vec![odd, STATUS_READ.to_vec()]);
    // the response rule of the same code: a 1-byte count at ADU offset 2
    let resp = rtu_frame(1, &raw![0x65, 0x03, 0xAA, 0xBB, 0xCC]);
    let mut f = RtuFramer::new(Direction::Response, timing(), vec![rule]);
    assert_eq!(frames(&f.push(Duration::ZERO, &resp)), vec![resp]);
}

// ---------------------------------------------------------------------------------------------------------------
// Encoding limits
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn encode_refuses_a_pdu_over_253_bytes() {
    use codec::EncodeError;
    // 123 registers: 6 + 246 = 252 bytes, fine; 124: 254 bytes, one too many
    let ok = Request::WriteMultipleRegisters {
        address: 0,
        values: vec![0; 123],
    };
    assert_eq!(ok.to_bytes().unwrap().len(), 252);
    let long = Request::WriteMultipleRegisters {
        address: 0,
        values: vec![0; 124],
    };
    let mut out = vec![0xEE];
    assert_eq!(
        long.encode(&mut out),
        Err(EncodeError::TooLong {
            field: "PDU",
            len: 254,
            max: 253
        })
    );
    assert_eq!(out, vec![0xEE], "a refused PDU leaves the buffer as it was");
    assert_eq!(
        rtu::encode(1, &Pdu::Request(long.clone())).map(|_| ()),
        Err(EncodeError::TooLong {
            field: "PDU",
            len: 254,
            max: 253
        })
    );
    assert!(tcp::encode(1, 1, &Pdu::Request(long)).is_err());
    let resp = Response::ReadHoldingRegisters {
        values: vec![0; 126],
    };
    assert_eq!(
        resp.to_bytes(),
        Err(EncodeError::TooLong {
            field: "PDU",
            len: 254,
            max: 253
        })
    );
}

// ---------------------------------------------------------------------------------------------------------------
// Hex input
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn parse_hex_forms() {
    assert_eq!(
        parse_hex("01 03 07D0"),
        Ok(raw![0x01, 0x03, 0x07, 0xD0].to_vec())
    );
    assert_eq!(parse_hex("0x01,0x03"), Ok(raw![0x01, 0x03].to_vec()));
    assert_eq!(parse_hex("01:03"), Ok(raw![0x01, 0x03].to_vec()));
    assert_eq!(parse_hex("01-03"), Ok(raw![0x01, 0x03].to_vec()));
    assert_eq!(parse_hex("0X2B 0Eh"), Ok(raw![0x2B, 0x0E].to_vec()));
    assert_eq!(parse_hex("010307d000018487"), Ok(STATUS_READ.to_vec()));
    assert_eq!(parse_hex(""), Ok(vec![]));
    assert!(parse_hex("0G").is_err());
    assert!(parse_hex("01 0").is_err(), "an odd digit count is an error");
    assert!(parse_hex("01 03 zz").is_err());
}

/// On an encode error the output buffer is left exactly as it was.
#[test]
fn encode_error_leaves_buffer_unchanged() {
    use codec::{Mnemonic, Request, Response};
    let mut out = vec![0xEE];
    let r = Request::VendorWrite {
        mnemonic: Mnemonic::from_name("TR").unwrap(),
        params: vec![b'1'; 300],
    };
    assert!(r.encode(&mut out).is_err());
    assert_eq!(out, vec![0xEE]);
    let r = Request::WriteMultipleRegisters {
        address: 0,
        values: vec![0; 128],
    };
    assert!(r.encode(&mut out).is_err());
    assert_eq!(out, vec![0xEE]);
    let r = Response::ReadHoldingRegisters {
        values: vec![0; 128],
    };
    assert!(r.encode(&mut out).is_err());
    assert_eq!(out, vec![0xEE]);
}
