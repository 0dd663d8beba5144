//! Property tests of the sans-IO codec: typed round trips over every framing, no panics on arbitrary bytes,
//! the RTU stream framer's cutting, discarding and memory bound, and the CRC catching every single-bit error.
//!
//! Seeds: proptest prints the failing seed and persists it under `proptest-regressions/`; rerun replays it.

use std::time::Duration;

use codec::framer::{DiscardReason, FrameLen, LengthRule, VendorRule, expected_len};
use codec::pdu::{Direction, MAX_PDU_LEN, Pdu, Request, Response};
use codec::tcp::{self, Mbap};
use codec::{
    CanOpenAccess, CharFormat, DecodeError, DeviceIdObject, DeviceIdResponse, ExceptionCode,
    FileRecordData, FileRecordRef, FileRecordWrite, FramerEvent, Framing, FunctionCode, Mnemonic,
    Parity, RtuFramer, RtuTiming, decode_any, rtu,
};
use proptest::collection::vec;
use proptest::prelude::*;
use proptest::sample::select;

/// Function codes the codec decodes into a typed variant (in either direction).
const TYPED: &[u8] = &[
    0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x0B, 0x0C, 0x0F, 0x10, 0x11, 0x14, 0x15, 0x16,
    0x17, 0x18, 0x2B, 0x41, 0x42,
];

// ---------------------------------------------------------------------------------------------------------------
// Strategies: valid typed values only (every one must encode, and decode back to itself).
// ---------------------------------------------------------------------------------------------------------------

fn mnemonic() -> impl Strategy<Value = Mnemonic> {
    any::<[u8; 4]>().prop_map(Mnemonic)
}

/// A function code below 0x80 that the codec keeps as `Raw`.
fn untyped_fc() -> impl Strategy<Value = FunctionCode> {
    (0u8..0x80)
        .prop_filter("typed function code", |f| !TYPED.contains(f))
        .prop_map(FunctionCode)
}

/// FC 2B with an MEI type other than 0x0D/0x0E: also kept as `Raw` (the MEI byte is the first data byte).
fn raw_mei() -> impl Strategy<Value = Vec<u8>> {
    (
        any::<u8>().prop_filter("typed MEI", |m| *m != 0x0D && *m != 0x0E),
        vec(any::<u8>(), 0..=MAX_PDU_LEN - 2),
    )
        .prop_map(|(m, mut rest)| {
            rest.insert(0, m);
            rest
        })
}

/// CANopen fixed header fields (control without its write bit).
fn canopen_header() -> impl Strategy<Value = (u8, u8, u8, u16, u8, u16)> {
    (
        0u8..0x80,
        any::<u8>(),
        any::<u8>(),
        any::<u16>(),
        any::<u8>(),
        any::<u16>(),
    )
}

/// Largest CANopen data field: 253 - (FC, MEI, control, reserved, node, index 2, subindex, offset 2, count 2).
const CANOPEN_MAX_DATA: usize = MAX_PDU_LEN - 12;

fn canopen(
    (control, reserved, node_id, index, subindex, offset): (u8, u8, u8, u16, u8, u16),
    byte_count: u16,
    data: Vec<u8>,
) -> CanOpenAccess {
    CanOpenAccess {
        control,
        reserved,
        node_id,
        index,
        subindex,
        offset,
        byte_count,
        data,
    }
}

/// Read request: no data, any byte count. Write request: data of exactly `byte_count` bytes.
fn canopen_request() -> impl Strategy<Value = CanOpenAccess> {
    prop_oneof![
        (canopen_header(), any::<u16>()).prop_map(|(h, n)| canopen(h, n, Vec::new())),
        (canopen_header(), vec(any::<u8>(), 0..=CANOPEN_MAX_DATA)).prop_map(|(mut h, d)| {
            h.0 |= CanOpenAccess::WRITE;
            canopen(h, d.len() as u16, d)
        }),
    ]
}

/// Read response: data of exactly `byte_count` bytes. Write response: no data (any count) or the data echoed.
fn canopen_response() -> impl Strategy<Value = CanOpenAccess> {
    prop_oneof![
        (canopen_header(), vec(any::<u8>(), 0..=CANOPEN_MAX_DATA)).prop_map(|(h, d)| canopen(
            h,
            d.len() as u16,
            d
        )),
        (canopen_header(), any::<u16>()).prop_map(|(mut h, n)| {
            h.0 |= CanOpenAccess::WRITE;
            canopen(h, n, Vec::new())
        }),
        (canopen_header(), vec(any::<u8>(), 0..=CANOPEN_MAX_DATA)).prop_map(|(mut h, d)| {
            h.0 |= CanOpenAccess::WRITE;
            canopen(h, d.len() as u16, d)
        }),
    ]
}

/// Device identification objects that fit: FC, MEI, 4 header bytes, count, then (id, len, value) each. The
/// header holds values spec 6.21 allows (read code 1-4, conformity 01-03/81-83, more follows 00 with next
/// object 00, or FF with any).
fn device_id_response() -> impl Strategy<Value = DeviceIdResponse> {
    const BUDGET: usize = MAX_PDU_LEN - 7;
    let objects = prop_oneof![
        vec((any::<u8>(), vec(any::<u8>(), 0..=48)), 0..=12),
        (any::<u8>(), vec(any::<u8>(), 0..=BUDGET - 2)).prop_map(|o| vec![o]),
    ];
    let more = prop_oneof![Just((0u8, 0u8)), any::<u8>().prop_map(|next| (0xFF, next))];
    (
        1u8..=4,
        select(vec![0x01u8, 0x02, 0x03, 0x81, 0x82, 0x83]),
        more,
        objects,
    )
        .prop_map(
            |(read_code, conformity, (more_follows, next_object_id), objs)| {
                let mut used = 0;
                let objects = objs
                    .into_iter()
                    .take_while(|(_, v)| {
                        used += 2 + v.len();
                        used <= BUDGET
                    })
                    .map(|(id, value)| DeviceIdObject { id, value })
                    .collect();
                DeviceIdResponse {
                    read_code,
                    conformity,
                    more_follows,
                    next_object_id,
                    objects,
                }
            },
        )
}

/// FC 14 sub-requests: up to 35 of 7 bytes (PDU = 2 + 7n <= 253), any values.
fn file_read_request() -> impl Strategy<Value = Vec<FileRecordRef>> {
    vec(
        (any::<u8>(), any::<u16>(), any::<u16>(), any::<u16>()).prop_map(
            |(reference_type, file_number, record_number, record_length)| FileRecordRef {
                reference_type,
                file_number,
                record_number,
                record_length,
            },
        ),
        0..=(MAX_PDU_LEN - 2) / 7,
    )
}

/// Take items while their wire sizes fit `budget` bytes.
fn fitting<T>(items: Vec<T>, budget: usize, size: impl Fn(&T) -> usize) -> Vec<T> {
    let mut used = 0;
    items
        .into_iter()
        .take_while(|i| {
            used += size(i);
            used <= budget
        })
        .collect()
}

/// FC 14 sub-responses (1 + 1 + 2n bytes each) within the PDU's 251 bytes after FC and length.
fn file_read_response() -> impl Strategy<Value = Vec<FileRecordData>> {
    vec((any::<u8>(), vec(any::<u16>(), 0..=124)), 0..=8).prop_map(|subs| {
        let subs = subs
            .into_iter()
            .map(|(reference_type, values)| FileRecordData {
                reference_type,
                values,
            })
            .collect();
        fitting(subs, MAX_PDU_LEN - 2, |s: &FileRecordData| {
            2 + 2 * s.values.len()
        })
    })
}

/// FC 15 sub-requests (7 + 2n bytes each) within 251 bytes.
fn file_write() -> impl Strategy<Value = Vec<FileRecordWrite>> {
    vec(
        (
            any::<u8>(),
            any::<u16>(),
            any::<u16>(),
            vec(any::<u16>(), 0..=122),
        ),
        0..=8,
    )
    .prop_map(|subs| {
        let subs = subs
            .into_iter()
            .map(
                |(reference_type, file_number, record_number, values)| FileRecordWrite {
                    reference_type,
                    file_number,
                    record_number,
                    values,
                },
            )
            .collect();
        fitting(subs, MAX_PDU_LEN - 2, |s: &FileRecordWrite| {
            7 + 2 * s.values.len()
        })
    })
}

/// Every request variant with valid contents. `framer_safe` limits Diagnostics to the 2 data bytes the RTU
/// length rules assume and leaves out `Raw` (no length rule: only silence delimits it).
fn request_strategy(framer_safe: bool) -> BoxedStrategy<Request> {
    let diag_len = if framer_safe {
        2..=2
    } else {
        0..=MAX_PDU_LEN - 3
    };
    let typed = prop_oneof![
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, quantity)| Request::ReadCoils { address, quantity }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, quantity)| Request::ReadDiscreteInputs { address, quantity }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, quantity)| Request::ReadHoldingRegisters { address, quantity }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, quantity)| Request::ReadInputRegisters { address, quantity }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, value)| Request::WriteSingleCoil { address, value }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, value)| Request::WriteSingleRegister { address, value }),
        (any::<u16>(), vec(any::<u8>(), diag_len))
            .prop_map(|(sub_function, data)| Request::Diagnostics { sub_function, data }),
        Just(Request::ReadExceptionStatus),
        Just(Request::GetCommEventCounter),
        Just(Request::GetCommEventLog),
        Just(Request::ReportServerId),
        file_read_request().prop_map(|sub_requests| Request::ReadFileRecord { sub_requests }),
        file_write().prop_map(|sub_requests| Request::WriteFileRecord { sub_requests }),
        (any::<u16>(), any::<u16>(), any::<u16>()).prop_map(|(address, and_mask, or_mask)| {
            Request::MaskWriteRegister {
                address,
                and_mask,
                or_mask,
            }
        }),
        any::<u16>().prop_map(|address| Request::ReadFifoQueue { address }),
        // data = ceil(quantity / 8) bytes, PDU = 6 + data <= 253
        (any::<u16>(), 0u16..=((MAX_PDU_LEN as u16 - 6) * 8)).prop_flat_map(
            |(address, quantity)| {
                vec(any::<u8>(), (quantity as usize).div_ceil(8)).prop_map(move |data| {
                    Request::WriteMultipleCoils {
                        address,
                        quantity,
                        data,
                    }
                })
            }
        ),
        (any::<u16>(), vec(any::<u16>(), 0..=(MAX_PDU_LEN - 6) / 2))
            .prop_map(|(address, values)| Request::WriteMultipleRegisters { address, values }),
        (
            any::<u16>(),
            any::<u16>(),
            any::<u16>(),
            vec(any::<u16>(), 0..=(MAX_PDU_LEN - 10) / 2)
        )
            .prop_map(|(read_address, read_quantity, write_address, values)| {
                Request::ReadWriteMultipleRegisters {
                    read_address,
                    read_quantity,
                    write_address,
                    values,
                }
            }),
        canopen_request().prop_map(Request::CanOpen),
        (any::<u8>(), any::<u8>()).prop_map(|(read_code, object_id)| Request::ReadDeviceId {
            read_code,
            object_id
        }),
        mnemonic().prop_map(|mnemonic| Request::VendorRead { mnemonic }),
        (mnemonic(), vec(any::<u8>(), 0..=MAX_PDU_LEN - 6))
            .prop_map(|(mnemonic, params)| Request::VendorWrite { mnemonic, params }),
    ];
    with_raw(typed, 22, framer_safe, |function, data| Request::Raw {
        function,
        data,
    })
}

/// `typed`; unless `framer_safe`, also (1 in `typed_weight + 2` each) a PDU of an untyped function code and
/// a raw MEI PDU, made by `raw` from the function code and the data.
fn with_raw<T: std::fmt::Debug + 'static>(
    typed: impl Strategy<Value = T> + 'static,
    typed_weight: u32,
    framer_safe: bool,
    raw: fn(FunctionCode, Vec<u8>) -> T,
) -> BoxedStrategy<T> {
    if framer_safe {
        typed.boxed()
    } else {
        prop_oneof![
            typed_weight => typed,
            1 => (untyped_fc(), vec(any::<u8>(), 0..=MAX_PDU_LEN - 1))
                .prop_map(move |(function, data)| raw(function, data)),
            1 => raw_mei().prop_map(move |data| raw(FunctionCode::ENCAPSULATED_INTERFACE, data)),
        ]
        .boxed()
    }
}

/// Every response variant with valid contents (`framer_safe` as for requests).
fn response_strategy(framer_safe: bool) -> BoxedStrategy<Response> {
    let diag_len = if framer_safe {
        2..=2
    } else {
        0..=MAX_PDU_LEN - 3
    };
    let exception = (0x80u8..=0xFF, any::<u8>())
        // AB FF is the SD2x extended exception, a different layout.
        .prop_filter("AB FF is CanOpenError", |(f, c)| {
            !(*f == 0xAB && *c == 0xFF)
        })
        .prop_map(|(f, c)| Response::Exception {
            function: FunctionCode(f),
            code: ExceptionCode(c),
        });
    let typed = prop_oneof![
        vec(any::<u8>(), 0..=MAX_PDU_LEN - 2).prop_map(|data| Response::ReadCoils { data }),
        vec(any::<u8>(), 0..=MAX_PDU_LEN - 2)
            .prop_map(|data| Response::ReadDiscreteInputs { data }),
        vec(any::<u16>(), 0..=(MAX_PDU_LEN - 2) / 2)
            .prop_map(|values| Response::ReadHoldingRegisters { values }),
        vec(any::<u16>(), 0..=(MAX_PDU_LEN - 2) / 2)
            .prop_map(|values| Response::ReadInputRegisters { values }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, value)| Response::WriteSingleCoil { address, value }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, value)| Response::WriteSingleRegister { address, value }),
        (any::<u16>(), vec(any::<u8>(), diag_len))
            .prop_map(|(sub_function, data)| Response::Diagnostics { sub_function, data }),
        any::<u8>().prop_map(|status| Response::ReadExceptionStatus { status }),
        (any::<u16>(), any::<u16>()).prop_map(|(status, event_count)| {
            Response::GetCommEventCounter {
                status,
                event_count,
            }
        }),
        (
            any::<u16>(),
            any::<u16>(),
            any::<u16>(),
            vec(any::<u8>(), 0..=64)
        )
            .prop_map(|(status, event_count, message_count, events)| {
                Response::GetCommEventLog {
                    status,
                    event_count,
                    message_count,
                    events,
                }
            }),
        vec(any::<u8>(), 1..=MAX_PDU_LEN - 2).prop_map(|data| Response::ReportServerId { data }),
        file_read_response().prop_map(|sub_responses| Response::ReadFileRecord { sub_responses }),
        file_write().prop_map(|sub_requests| Response::WriteFileRecord { sub_requests }),
        (any::<u16>(), any::<u16>(), any::<u16>()).prop_map(|(address, and_mask, or_mask)| {
            Response::MaskWriteRegister {
                address,
                and_mask,
                or_mask,
            }
        }),
        vec(any::<u16>(), 0..=31).prop_map(|values| Response::ReadFifoQueue { values }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, quantity)| Response::WriteMultipleCoils { address, quantity }),
        (any::<u16>(), any::<u16>()).prop_map(|(address, quantity)| {
            Response::WriteMultipleRegisters { address, quantity }
        }),
        vec(any::<u16>(), 0..=(MAX_PDU_LEN - 2) / 2)
            .prop_map(|values| Response::ReadWriteMultipleRegisters { values }),
        canopen_response().prop_map(Response::CanOpen),
        any::<u32>().prop_map(|sdo_code| Response::CanOpenError { sdo_code }),
        device_id_response().prop_map(Response::ReadDeviceId),
        vec(any::<u8>(), 0..=MAX_PDU_LEN - 2).prop_map(|params| Response::VendorRead { params }),
        (any::<u8>(), mnemonic())
            .prop_map(|(written, mnemonic)| Response::VendorWrite { written, mnemonic }),
        exception,
    ];
    with_raw(typed, 24, framer_safe, |function, data| Response::Raw {
        function,
        data,
    })
}

/// A valid PDU of either direction, with its direction.
fn any_pdu(framer_safe: bool) -> impl Strategy<Value = (Direction, Pdu)> {
    prop_oneof![
        request_strategy(framer_safe).prop_map(|r| (Direction::Request, Pdu::Request(r))),
        response_strategy(framer_safe).prop_map(|r| (Direction::Response, Pdu::Response(r))),
    ]
}

fn pdu_bytes(p: &Pdu) -> Vec<u8> {
    let mut v = Vec::new();
    p.encode(&mut v).expect("a valid PDU encodes");
    v
}

// ---------------------------------------------------------------------------------------------------------------
// Round trips
// ---------------------------------------------------------------------------------------------------------------

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn request_pdu_round_trip(req in request_strategy(false)) {
        let bytes = req.to_bytes().expect("valid request encodes");
        prop_assert!(!bytes.is_empty() && bytes.len() <= MAX_PDU_LEN, "PDU length {}", bytes.len());
        prop_assert_eq!(bytes[0], req.function().0);
        prop_assert_eq!(Request::decode(&bytes), Ok(req.clone()));
        prop_assert_eq!(
            Pdu::decode(&bytes, Direction::Request),
            Ok(Pdu::Request(req.clone()))
        );
        // encode appends: existing bytes stay, the PDU follows them unchanged
        let mut out = vec![0xEE, 0xEE];
        req.encode(&mut out).unwrap();
        prop_assert_eq!(&out[..2], &[0xEE, 0xEE]);
        prop_assert_eq!(&out[2..], &bytes[..]);
    }

    #[test]
    fn response_pdu_round_trip(resp in response_strategy(false)) {
        let bytes = resp.to_bytes().expect("valid response encodes");
        prop_assert!(!bytes.is_empty() && bytes.len() <= MAX_PDU_LEN, "PDU length {}", bytes.len());
        prop_assert_eq!(bytes[0], resp.function().0);
        prop_assert_eq!(resp.is_exception(), bytes[0] & 0x80 != 0);
        prop_assert_eq!(Response::decode(&bytes), Ok(resp.clone()));
        prop_assert_eq!(
            Pdu::decode(&bytes, Direction::Response),
            Ok(Pdu::Response(resp.clone()))
        );
    }

    #[test]
    fn tcp_round_trip((dir, pdu) in any_pdu(false), tid in any::<u16>(), unit in any::<u8>()) {
        let body = pdu_bytes(&pdu);
        let adu = tcp::encode(tid, unit, &pdu).expect("valid PDU frames");
        prop_assert_eq!(adu.len(), tcp::MBAP_LEN + body.len());
        prop_assert_eq!(&adu[tcp::MBAP_LEN..], &body[..]);
        prop_assert_eq!(tcp::adu_len(&adu), Some(adu.len()));
        let (header, decoded) = tcp::decode(&adu, dir).expect("own ADU decodes");
        prop_assert_eq!(
            header,
            Mbap { transaction_id: tid, protocol_id: 0, length: body.len() as u16 + 1, unit_id: unit }
        );
        prop_assert_eq!(&decoded, &pdu);
        let any = decode_any(&adu, Framing::Tcp, dir).expect("decode_any agrees");
        prop_assert_eq!((any.unit, any.transaction_id), (Some(unit), Some(tid)));
        prop_assert_eq!(any.pdu, pdu);
    }

    #[test]
    fn rtu_round_trip((dir, pdu) in any_pdu(false), address in any::<u8>()) {
        let body = pdu_bytes(&pdu);
        let adu = rtu::encode(address, &pdu).expect("valid PDU frames");
        prop_assert_eq!(adu.len(), body.len() + 3);
        prop_assert!(adu.len() <= rtu::MAX_ADU_LEN);
        prop_assert_eq!(adu[0], address);
        prop_assert_eq!(&adu[1..adu.len() - 2], &body[..]);
        prop_assert!(rtu::crc_ok(&adu));
        let crc = rtu::crc16(&adu[..adu.len() - 2]);
        prop_assert_eq!(&adu[adu.len() - 2..], &crc.to_le_bytes()[..], "CRC goes low byte first");
        let (a, decoded) = rtu::decode(&adu, dir).expect("own ADU decodes");
        prop_assert_eq!(a, address);
        prop_assert_eq!(&decoded, &pdu);
        let any = decode_any(&adu, Framing::Rtu, dir).expect("decode_any agrees");
        prop_assert_eq!((any.unit, any.transaction_id), (Some(address), None));
        prop_assert_eq!(any.pdu, pdu);
    }
}

// ---------------------------------------------------------------------------------------------------------------
// Arbitrary bytes: no panic, errors inside the input, and whatever decodes re-encodes to the same bytes
// ---------------------------------------------------------------------------------------------------------------

/// Random bytes, a third of them starting with a typed function code (or an exception) to reach deeper rules.
fn pdu_like() -> impl Strategy<Value = Vec<u8>> {
    let mut heads: Vec<u8> = TYPED.to_vec();
    heads.extend([0x81, 0x83, 0xAB, 0x90, 0x94, 0x98]);
    prop_oneof![
        2 => vec(any::<u8>(), 0..=300),
        1 => (select(heads), vec(any::<u8>(), 0..=299)).prop_map(|(h, mut rest)| {
            rest.insert(0, h);
            rest
        }),
    ]
}

/// Mostly well-formed ADU shells around random bytes, up to 300 bytes: an MBAP header with protocol id 0 and a
/// length field that is right or off by a little, or random bytes closed by their correct CRC.
fn adu_like() -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![
        (
            any::<u16>(),
            any::<u8>(),
            -2i32..=2,
            pdu_like().prop_map(|mut p| {
                p.truncate(300 - tcp::MBAP_LEN);
                p
            })
        )
            .prop_map(|(tid, unit, skew, pdu)| {
                let len = (pdu.len() as i32 + 1 + skew).clamp(0, 0xFFFF) as u16;
                let mut v = tid.to_be_bytes().to_vec();
                v.extend_from_slice(&[0, 0]);
                v.extend_from_slice(&len.to_be_bytes());
                v.push(unit);
                v.extend_from_slice(&pdu);
                v
            }),
        (any::<u8>(), pdu_like()).prop_map(|(a, pdu)| {
            let mut v = vec![a];
            v.extend_from_slice(&pdu[..pdu.len().min(297)]);
            let crc = rtu::crc16(&v);
            v.extend_from_slice(&crc.to_le_bytes());
            v
        }),
    ]
}

fn arbitrary_input() -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![pdu_like(), adu_like()]
}

fn offset_inside<T: std::fmt::Debug>(
    r: &Result<T, DecodeError>,
    len: usize,
    what: &str,
) -> Result<(), TestCaseError> {
    if let Err(e) = r {
        prop_assert!(
            e.offset <= len,
            "{what}: error offset {} beyond the {len}-byte input: {e}",
            e.offset
        );
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2048))]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in arbitrary_input()) {
        let n = bytes.len();
        let req = Request::decode(&bytes);
        offset_inside(&req, n, "Request::decode")?;
        if let Ok(r) = &req {
            prop_assert_eq!(r.to_bytes(), Ok(bytes.clone()), "decoded request re-encodes differently");
        }
        let resp = Response::decode(&bytes);
        offset_inside(&resp, n, "Response::decode")?;
        if let Ok(r) = &resp {
            prop_assert_eq!(r.to_bytes(), Ok(bytes.clone()), "decoded response re-encodes differently");
        }
        for dir in [Direction::Request, Direction::Response] {
            let t = tcp::decode(&bytes, dir);
            offset_inside(&t, n, "tcp::decode")?;
            if let Ok((h, p)) = &t {
                prop_assert_eq!(tcp::encode(h.transaction_id, h.unit_id, p), Ok(bytes.clone()));
            }
            let r = rtu::decode(&bytes, dir);
            offset_inside(&r, n, "rtu::decode")?;
            if let Ok((a, p)) = &r {
                prop_assert_eq!(rtu::encode(*a, p), Ok(bytes.clone()));
            }
            for framing in [Framing::Tcp, Framing::Rtu, Framing::Pdu] {
                offset_inside(&decode_any(&bytes, framing, dir), n, "decode_any")?;
            }
        }
    }

    /// Random PDU bytes inside a well-formed RTU or TCP frame: the ADU layer passes them through, and a PDU error
    /// is reported at the same byte, moved by the header (1 for RTU, 7 for MBAP).
    #[test]
    fn pdu_errors_shift_by_the_header(pdu in pdu_like().prop_filter("1..=253", |p| !p.is_empty() && p.len() <= MAX_PDU_LEN),
                                      unit in any::<u8>(), tid in any::<u16>()) {
        let mut r = Vec::new();
        rtu::encode_adu(unit, &pdu, &mut r).unwrap();
        let mut t = Vec::new();
        tcp::encode_adu(tid, unit, &pdu, &mut t).unwrap();
        for dir in [Direction::Request, Direction::Response] {
            let bare = Pdu::decode(&pdu, dir);
            offset_inside(&bare, pdu.len(), "Pdu::decode")?;
            prop_assert_eq!(
                rtu::decode(&r, dir),
                bare.clone().map(|p| (unit, p)).map_err(|e| e.shifted(1))
            );
            let tcp_result = tcp::decode(&t, dir).map(|(h, p)| (h.unit_id, h.transaction_id, p));
            prop_assert_eq!(
                tcp_result,
                bare.map(|p| (unit, tid, p)).map_err(|e| e.shifted(tcp::MBAP_LEN))
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------------------------
// CRC: every single-bit error is caught
// ---------------------------------------------------------------------------------------------------------------

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1024))]

    #[test]
    fn single_bit_flip_never_decodes((dir, pdu) in any_pdu(false), address in any::<u8>(), bit in any::<usize>()) {
        let adu = rtu::encode(address, &pdu).unwrap();
        let bit = bit % (adu.len() * 8);
        let mut bad = adu.clone();
        bad[bit / 8] ^= 1 << (bit % 8);
        prop_assert!(!rtu::crc_ok(&bad));
        match rtu::decode(&bad, dir) {
            Ok(d) => prop_assert!(false, "bit {bit} flipped in {adu:02X?}, still decodes as {d:?}"),
            Err(e) => {
                prop_assert_eq!(e.offset, bad.len() - 2);
                let is_crc = matches!(e.kind, codec::DecodeErrorKind::Crc { .. });
                prop_assert!(is_crc, "not a CRC error: {e}");
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------------------------
// RTU stream framer
// ---------------------------------------------------------------------------------------------------------------

fn timing() -> impl Strategy<Value = RtuTiming> {
    (
        select(vec![1200u32, 9600, 19200, 38400, 115200]),
        select(vec![Parity::None, Parity::Even, Parity::Odd]),
        1u8..=2,
    )
        .prop_map(|(baud, parity, stop_bits)| {
            RtuTiming::new(baud, CharFormat { parity, stop_bits })
        })
}

/// How a stream is split: chunk sizes and inter-chunk gaps in thousandths of t1.5 (always below t1.5).
fn chunking() -> impl Strategy<Value = (Vec<usize>, Vec<u32>)> {
    (vec(1usize..=24, 1..=32), vec(0u32..1000, 1..=32))
}

/// A framer-cuttable ADU. Excluded: a write response echoing data whose first two data bytes happen to be the
/// CRC of the 13 bytes before them (the 15-byte "no data" reading then wins; the protocol is ambiguous there).
fn framer_adu(dir: Direction) -> BoxedStrategy<Vec<u8>> {
    let pdu = match dir {
        Direction::Request => request_strategy(true).prop_map(Pdu::Request).boxed(),
        Direction::Response => response_strategy(true).prop_map(Pdu::Response).boxed(),
    };
    (any::<u8>(), pdu)
        .prop_map(|(a, p)| rtu::encode(a, &p).unwrap())
        .prop_filter("ambiguous CANopen write-response echo", |adu| {
            !(adu[1] == 0x2B
                && adu[2] == 0x0D
                && adu[3] & 0x80 != 0
                && adu.len() > 15
                && rtu::crc_ok(&adu[..15]))
        })
        .boxed()
}

fn direction() -> impl Strategy<Value = Direction> {
    select(vec![Direction::Request, Direction::Response])
}

/// Feed `bytes` from `t` in chunks whose gaps stay below t1.5; returns the events and the time of the last chunk.
fn feed_chunked(
    framer: &mut RtuFramer,
    mut t: Duration,
    bytes: &[u8],
    (sizes, gaps): &(Vec<usize>, Vec<u32>),
    events: &mut Vec<FramerEvent>,
) -> Duration {
    let t15 = framer.timing().t1_5;
    let mut at = 0;
    let mut i = 0;
    while at < bytes.len() {
        let n = sizes[i % sizes.len()].min(bytes.len() - at);
        if at > 0 {
            t += t15 * gaps[i % gaps.len()] / 1000;
        }
        events.extend(framer.push(t, &bytes[at..at + n]));
        at += n;
        i += 1;
    }
    t
}

fn frames_of(events: &[FramerEvent]) -> Vec<Vec<u8>> {
    events
        .iter()
        .filter_map(|e| match e {
            FramerEvent::Frame { bytes, .. } => Some(bytes.clone()),
            FramerEvent::Discarded { .. } => None,
        })
        .collect()
}

fn discarded_of(events: &[FramerEvent]) -> Vec<(Vec<u8>, DiscardReason)> {
    events
        .iter()
        .filter_map(|e| match e {
            FramerEvent::Discarded { bytes, reason, .. } => Some((bytes.clone(), reason.clone())),
            FramerEvent::Frame { .. } => None,
        })
        .collect()
}

/// Garbage that no length rule or silence can take for a frame: no prefix of 4 bytes or more has a valid CRC.
fn garbage() -> impl Strategy<Value = Vec<u8>> {
    vec(any::<u8>(), 1..=64).prop_filter("a prefix has a valid CRC", |g| {
        (rtu::MIN_ADU_LEN..=g.len()).all(|k| !rtu::crc_ok(&g[..k]))
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Back-to-back frames with no silence between them are cut by the length rules and the CRC alone.
    #[test]
    fn framer_cuts_back_to_back_frames(
        (dir, adus) in direction().prop_flat_map(|d| (Just(d), vec(framer_adu(d), 1..=8))),
        timing in timing(),
        chunks in chunking(),
        t0 in 0u64..1_000_000_000,
    ) {
        let stream: Vec<u8> = adus.concat();
        let mut framer = RtuFramer::new(dir, timing, Vec::new());
        let mut events = Vec::new();
        let last = feed_chunked(&mut framer, Duration::from_nanos(t0), &stream, &chunks, &mut events);
        prop_assert!(discarded_of(&events).is_empty(), "discarded: {:?}", discarded_of(&events));
        prop_assert_eq!(frames_of(&events), adus.clone());
        prop_assert!(framer.pending().is_empty(), "left pending: {:02X?}", framer.pending());
        prop_assert_eq!(framer.deadline(), None);
        // Nothing is held back for silence to release.
        prop_assert!(framer.poll(last + timing.t3_5).is_empty());
        prop_assert!(framer.finish().is_empty());
        for e in &events {
            if let FramerEvent::Frame { start, end, max_gap, .. } = e {
                prop_assert!(start <= end);
                prop_assert!(*max_gap < timing.t1_5, "gap {max_gap:?} >= t1.5 {:?}", timing.t1_5);
            }
        }
    }

    /// Garbage between frames, set off by silences of at least t3.5: every frame still comes out, in order, and
    /// each garbage run is reported discarded, whole.
    #[test]
    fn framer_discards_garbage_between_silences(
        (dir, items) in direction().prop_flat_map(|d| {
            (Just(d), vec((proptest::option::of(garbage()), framer_adu(d)), 1..=6))
        }),
        trailing in proptest::option::of(garbage()),
        timing in timing(),
        chunks in chunking(),
        extra_silence in vec(prop_oneof![Just(0u64), 0u64..2_000_000], 1..=8),
    ) {
        let mut framer = RtuFramer::new(dir, timing, Vec::new());
        let mut events = Vec::new();
        let mut t = Duration::from_millis(1);
        let mut silence_no = 0usize;
        let mut silence = |t: Duration| {
            silence_no += 1;
            t + timing.t3_5 + Duration::from_nanos(extra_silence[silence_no % extra_silence.len()])
        };
        let mut expected_garbage = Vec::new();
        let mut started = false;
        for (g, adu) in &items {
            if let Some(g) = g {
                if started {
                    t = silence(t);
                }
                t = feed_chunked(&mut framer, t, g, &chunks, &mut events);
                t = silence(t);
                expected_garbage.push(g.clone());
            }
            t = feed_chunked(&mut framer, t, adu, &chunks, &mut events);
            started = true;
        }
        if let Some(g) = &trailing {
            t = silence(t);
            t = feed_chunked(&mut framer, t, g, &chunks, &mut events);
            expected_garbage.push(g.clone());
            prop_assert_eq!(framer.deadline(), Some(t + timing.t3_5));
            prop_assert!(framer.poll(t + timing.t3_5 - Duration::from_nanos(1)).is_empty());
        }
        events.extend(framer.poll(t + timing.t3_5));
        prop_assert!(framer.pending().is_empty());

        let adus: Vec<Vec<u8>> = items.iter().map(|(_, a)| a.clone()).collect();
        prop_assert_eq!(frames_of(&events), adus);
        let discarded = discarded_of(&events);
        let total: usize = discarded.iter().map(|(b, _)| b.len()).sum();
        prop_assert_eq!(total, expected_garbage.iter().map(Vec::len).sum::<usize>());
        prop_assert_eq!(discarded.iter().map(|(b, _)| b.clone()).collect::<Vec<_>>(), expected_garbage);
        for (b, reason) in &discarded {
            if b.len() < rtu::MIN_ADU_LEN {
                prop_assert_eq!(reason, &DiscardReason::TooShort);
            } else {
                let (body, c) = b.split_at(b.len() - 2);
                prop_assert_eq!(
                    reason,
                    &DiscardReason::BadCrc {
                        expected: rtu::crc16(body),
                        received: u16::from_le_bytes([c[0], c[1]]),
                    }
                );
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    /// 10,000 random bytes without a silence: the framer never holds more than one maximal ADU, and every byte is
    /// accounted for (framed, discarded or still pending).
    #[test]
    fn framer_memory_is_bounded(
        bytes in vec(any::<u8>(), 10_000),
        dir in direction(),
        timing in timing(),
        chunks in chunking(),
    ) {
        let mut framer = RtuFramer::new(dir, timing, Vec::new());
        let mut t = Duration::ZERO;
        let mut out = 0usize;
        let (sizes, gaps) = &chunks;
        let mut at = 0;
        let mut i = 0;
        while at < bytes.len() {
            let n = sizes[i % sizes.len()].min(bytes.len() - at);
            t += timing.t1_5 * gaps[i % gaps.len()] / 1000;
            for e in framer.push(t, &bytes[at..at + n]) {
                out += match e {
                    FramerEvent::Frame { bytes, .. } | FramerEvent::Discarded { bytes, .. } => bytes.len(),
                };
            }
            prop_assert!(framer.pending().len() <= rtu::MAX_ADU_LEN, "holding {} bytes", framer.pending().len());
            at += n;
            i += 1;
            prop_assert_eq!(out + framer.pending().len(), at, "bytes lost or invented");
        }
    }
}

/// The framer as it was first written, one byte at a time with a cut after each: `RtuFramer::push` takes the
/// bytes after which no cut can happen in one go, and must decide exactly as this does.
struct BytewiseFramer {
    direction: Direction,
    t3_5: Duration,
    vendor: Vec<VendorRule>,
    buf: Vec<u8>,
    start: Duration,
    last: Duration,
    max_gap: Duration,
}

impl BytewiseFramer {
    fn push(&mut self, now: Duration, bytes: &[u8], events: &mut Vec<FramerEvent>) {
        self.poll(now, events);
        for &b in bytes {
            if self.buf.is_empty() {
                self.start = now;
                self.max_gap = Duration::ZERO;
            } else {
                self.max_gap = self.max_gap.max(now.saturating_sub(self.last));
            }
            self.buf.push(b);
            self.last = now;
            self.cut(events);
        }
    }

    fn poll(&mut self, now: Duration, events: &mut Vec<FramerEvent>) {
        if !self.buf.is_empty() && now.saturating_sub(self.last) >= self.t3_5 {
            self.finish(events);
        }
    }

    fn emit(&mut self, n: usize, events: &mut Vec<FramerEvent>) {
        events.push(FramerEvent::Frame {
            bytes: self.buf.drain(..n).collect(),
            start: self.start,
            end: self.last,
            max_gap: self.max_gap,
        });
        self.start = self.last;
        self.max_gap = Duration::ZERO;
    }

    fn cut(&mut self, events: &mut Vec<FramerEvent>) {
        if let FrameLen::Known(a, b) = expected_len(self.direction, &self.buf, &self.vendor) {
            for n in [a, b] {
                if n >= rtu::MIN_ADU_LEN
                    && n <= self.buf.len()
                    && n <= rtu::MAX_ADU_LEN
                    && rtu::crc_ok(&self.buf[..n])
                {
                    self.emit(n, events);
                    return;
                }
            }
        }
        if self.buf.len() > rtu::MAX_ADU_LEN {
            events.push(FramerEvent::Discarded {
                bytes: std::mem::take(&mut self.buf),
                at: self.last,
                reason: DiscardReason::Overlong,
            });
        }
    }

    fn finish(&mut self, events: &mut Vec<FramerEvent>) {
        if self.buf.is_empty() {
            return;
        }
        if self.buf.len() < rtu::MIN_ADU_LEN {
            events.push(FramerEvent::Discarded {
                bytes: std::mem::take(&mut self.buf),
                at: self.last,
                reason: DiscardReason::TooShort,
            });
        } else if rtu::crc_ok(&self.buf) {
            let n = self.buf.len();
            self.emit(n, events);
        } else {
            let (body, c) = self.buf.split_at(self.buf.len() - 2);
            let reason = DiscardReason::BadCrc {
                expected: rtu::crc16(body),
                received: u16::from_le_bytes([c[0], c[1]]),
            };
            events.push(FramerEvent::Discarded {
                bytes: std::mem::take(&mut self.buf),
                at: self.last,
                reason,
            });
        }
    }
}

fn length_rule() -> impl Strategy<Value = LengthRule> {
    prop_oneof![
        (0usize..300).prop_map(LengthRule::Fixed),
        (0usize..16, 1usize..=2, 0usize..=3).prop_map(|(offset, width, trailer)| {
            LengthRule::ByteCountAt {
                offset,
                width,
                trailer,
            }
        }),
    ]
}

/// One step of a stream: what arrives (valid ADUs, random bytes, a run of one byte value), after how long a
/// silence (in hundredths of t3.5, so both sides of t1.5 and t3.5), and whether the framer is polled first
/// or the stream ends after it.
fn framer_step(dir: Direction) -> impl Strategy<Value = (Vec<u8>, u32, bool, bool)> {
    let bytes = prop_oneof![
        vec(framer_adu(dir), 1..=3).prop_map(|a| a.concat()),
        vec(any::<u8>(), 0..=40),
        (any::<u8>(), 1usize..=300).prop_map(|(b, n)| vec![b; n]),
        (framer_adu(dir), 0usize..=40).prop_map(|(a, cut)| a[..cut.min(a.len())].to_vec()),
    ];
    (
        bytes,
        0u32..=250,
        any::<bool>(),
        proptest::bool::weighted(0.1),
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// `push` taking the bytes that cannot trigger a cut in one go decides exactly as cutting after every byte
    /// does: the same events (frames, discards, reasons, times and gaps), the same bytes pending and the same
    /// deadline, after every step; through `push`/`poll`/`finish` and their `_into` forms alike.
    #[test]
    fn framer_decides_as_bytewise(
        (dir, steps) in direction().prop_flat_map(|d| (Just(d), vec(framer_step(d), 1..=24))),
        vendor in vec((any::<u8>(), length_rule(), length_rule()), 0..=2),
        timing in timing(),
        split in 1usize..=64,
        inner in prop_oneof![Just(0u32), 1u32..=60],
    ) {
        let vendor: Vec<VendorRule> = vendor
            .into_iter()
            .map(|(function, request, response)| VendorRule { function, request, response })
            .collect();
        let mut framer = RtuFramer::new(dir, timing, vendor.clone());
        let mut bytewise = BytewiseFramer {
            direction: dir,
            t3_5: timing.t3_5,
            vendor,
            buf: Vec::new(),
            start: Duration::ZERO,
            last: Duration::ZERO,
            max_gap: Duration::ZERO,
        };
        let mut t = Duration::ZERO;
        for (i, (bytes, silence, poll, end)) in steps.into_iter().enumerate() {
            t += timing.t3_5 * silence / 100;
            // Every other step through the `_into` forms, appending to a buffer that already holds events.
            let into = i % 2 == 1;
            let (mut ours, mut theirs) = (Vec::new(), Vec::new());
            if poll {
                if into {
                    framer.poll_into(t, &mut ours);
                } else {
                    ours.extend(framer.poll(t));
                }
                bytewise.poll(t, &mut theirs);
            }
            // Pushed in pieces of `split` bytes, each `inner` hundredths of t3.5 after the one before (0: at
            // the same instant; otherwise frames span gaps on both sides of t1.5, and their `max_gap` shows).
            // An empty step is an empty push (the silence before it may end the held bytes).
            let pieces: Vec<&[u8]> = if bytes.is_empty() {
                vec![&[]]
            } else {
                bytes.chunks(split).collect()
            };
            for (k, piece) in pieces.into_iter().enumerate() {
                if k > 0 {
                    t += timing.t3_5 * inner / 100;
                }
                if into {
                    framer.push_into(t, piece, &mut ours);
                } else {
                    ours.extend(framer.push(t, piece));
                }
                bytewise.push(t, piece, &mut theirs);
            }
            if end {
                if into {
                    framer.finish_into(&mut ours);
                } else {
                    ours.extend(framer.finish());
                }
                bytewise.finish(&mut theirs);
            }
            prop_assert_eq!(&ours, &theirs);
            prop_assert_eq!(framer.pending(), &bytewise.buf[..]);
            // The same last byte time: the deadline for the next poll.
            prop_assert_eq!(
                framer.deadline(),
                (!bytewise.buf.is_empty()).then(|| bytewise.last + timing.t3_5)
            );
        }
    }
}
