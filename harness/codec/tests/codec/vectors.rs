//! Codec vectors with exact expectations (in the manner of h2's raw_codec tests and rustls' test data): the
//! well-formed frames from the manuals and the malformed ones that must fail with a named rule at a named byte
//! are data, `tests/vectors/*.toml` (schema: tests/vectors/README.md), each file checked by one table-driven
//! test here that names every failing vector. What stays in Rust is behaviour rather than vectors: the RTU
//! stream framer over time, and the encoder's limits.

use std::time::Duration;

use codec::framer::DiscardReason;
use codec::pdu::{Direction, Pdu, Request, Response};
use codec::{CharFormat, FramerEvent, Parity, RtuFramer, RtuTiming, rtu, tcp};

use crate::data;

/// Bytes written out by hand: `raw![0x01, 0x03, ...]` (a byte array).
macro_rules! raw {
    ($($b:expr),* $(,)?) => {
        [$($b as u8),*]
    };
}

/// One test per vector file (the old test names are the vectors' name prefixes), and the list of files,
/// so that a file without a test fails `every_vector_file_is_checked`.
macro_rules! vector_files {
    ($($test:ident => $file:literal,)*) => {
        $(
            #[test]
            fn $test() {
                data::check_file($file);
            }
        )*
        const FILES: &[&str] = &[$($file),*];
    };
}

vector_files! {
    // SD2x 6.3 status read and its CRC, RTU length limits
    rtu_vectors => "rtu.toml",
    // MBAP strict checks
    mbap_vectors => "mbap.toml",
    // FC 10 / FC 0F / read response byte counts
    byte_count_vectors => "byte_counts.toml",
    // truncation and trailing bytes
    truncation_vectors => "truncation.toml",
    // FC 2B: SD2x CANopen access, its extended exception, device identification
    fc2b_vectors => "fc2b.toml",
    // FC 07, 08, 0B, 0C, 11: the serial-line-only functions
    serial_line_vectors => "serial_line.toml",
    // FC 14 / FC 15: file records
    file_record_vectors => "file_records.toml",
    // FC 16 mask write, FC 18 FIFO queue
    mask_write_fifo_vectors => "mask_write_fifo.toml",
    // IMS vendor codes 0x41/0x42 and mnemonics
    vendor_vectors => "vendor.toml",
    // RTU character formats and timing
    rtu_timing_vectors => "rtu_timing.toml",
    // hex as users write it (parse_hex)
    hex_input_vectors => "hex_input.toml",
}

#[test]
fn every_vector_file_is_checked() {
    data::assert_files_are(FILES);
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

/// The decoding side of the RTU length limits is vectors `rtu_length_limits/*` of tests/vectors/rtu.toml;
/// framing a PDU over 253 bytes is refused.
#[test]
fn rtu_length_limits() {
    assert_eq!(
        rtu::encode_adu(1, &[0; 254], &mut Vec::new()),
        Err(codec::EncodeError::TooLong {
            field: "PDU",
            len: 254,
            max: 253
        })
    );
}

fn fmt(parity: Parity, stop_bits: u8) -> CharFormat {
    CharFormat { parity, stop_bits }
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

/// (start, end, largest gap) of a frame event.
fn span(event: &FramerEvent) -> (Duration, Duration, Duration) {
    let FramerEvent::Frame {
        start,
        end,
        max_gap,
        ..
    } = event
    else {
        panic!("not a frame: {event:?}")
    };
    (*start, *end, *max_gap)
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
    assert_eq!(span(&ev[0]), (t0, t0, Duration::ZERO));

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
    let (start, end, max_gap) = span(&ev[0]);
    assert_eq!(start, Duration::ZERO);
    assert_eq!(end, gap * 7);
    assert_eq!(max_gap, gap);
}

/// A slave on a multi-drop line hears the master's request to another slave, that slave's reply and the
/// master's next request, here in one run of bytes (the reply followed within the carrier's wait). Sized by
/// the request layouts alone, the 7-byte FC 03 reply and the request after it are one run of bytes that no
/// length cuts, discarded at the silence: the request for this slave is lost. Listening as slave 3
/// (`listen_as`), the frame after a request for slave 1 is sized by the response layouts too, and all three
/// are cut.
#[test]
fn a_slave_on_a_line_hears_another_slaves_reply_and_the_request_after_it() {
    let to_1 = rtu_frame(1, &raw![0x03, 0x0B, 0xB8, 0x00, 0x01]);
    let reply_1 = rtu_frame(1, &raw![0x03, 0x02, 0x00, 0x00]);
    let to_3 = rtu_frame(3, &raw![0x03, 0x0B, 0xB8, 0x00, 0x01]);
    let stream = [to_1.clone(), reply_1.clone(), to_3.clone()].concat();
    let t0 = Duration::from_millis(5);
    let mut plain = RtuFramer::new(Direction::Request, timing(), Vec::new());
    let mut ev = plain.push(t0, &stream);
    ev.extend(plain.poll(t0 + timing().t3_5));
    assert_eq!(frames(&ev[..1]), vec![to_1.clone()]);
    assert!(
        matches!(&ev[1..], [FramerEvent::Discarded { bytes, .. }] if bytes.len() == 15),
        "{ev:?}"
    );
    let mut slave = RtuFramer::new(Direction::Request, timing(), Vec::new());
    slave.listen_as(3);
    assert_eq!(frames(&slave.push(t0, &stream)), vec![to_1, reply_1, to_3]);
    assert!(slave.pending().is_empty());
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

/// Reading answers through a host's port (`with_incomplete_wait`): a frame the rules say is incomplete
/// waits the longer wait for its next byte, a complete one is cut at once, and bytes no rule sizes (or past
/// every length the rules give) still end at t3.5.
#[test]
fn framer_waits_longer_for_the_rest_of_a_frame_its_rules_size() {
    let wait = Duration::from_millis(20);
    let t35 = timing().t3_5;
    let answer = rtu_frame(1, &raw![0x03, 0x04, 0x00, 0x50, 0x12, 0x34]);
    let mut f =
        RtuFramer::new(Direction::Response, timing(), Vec::new()).with_incomplete_wait(wait);
    assert!(f.push(Duration::ZERO, &answer[..5]).is_empty());
    assert_eq!(f.deadline(), Some(wait), "incomplete: the longer wait");
    assert!(f.poll(t35 * 3).is_empty(), "past t3.5, within the wait");
    let later = Duration::from_millis(15);
    assert_eq!(frames(&f.push(later, &answer[5..])), vec![answer.clone()]);
    assert_eq!(f.deadline(), None);
    // Cut short: discarded once the wait is out, not at t3.5.
    assert!(f.push(later * 2, &answer[..5]).is_empty());
    assert!(f.poll(later * 2 + t35 * 2).is_empty());
    let ev = f.poll(later * 2 + wait);
    assert!(
        matches!(&ev[..], [FramerEvent::Discarded { bytes, .. }] if bytes == &answer[..5]),
        "{ev:?}"
    );
    // A function code no rule sizes: t3.5, as without the wait.
    let unknown = rtu_frame(1, &raw![0x64, 0x01, 0x02]);
    assert!(f.push(later * 4, &unknown).is_empty());
    assert_eq!(f.deadline(), Some(later * 4 + t35));
    assert_eq!(frames(&f.poll(later * 4 + t35)), vec![unknown]);
    // Without the wait: t3.5 for an incomplete frame too.
    let mut plain = RtuFramer::new(Direction::Response, timing(), Vec::new());
    assert!(plain.push(Duration::ZERO, &answer[..5]).is_empty());
    assert_eq!(plain.deadline(), Some(t35));
}

/// A caller's clock is its own: bytes held at a time near `Duration::MAX` give a deadline that saturates
/// instead of overflowing (it panicked in `last + t3_5`), and silence still ends them.
#[test]
fn framer_deadline_saturates_at_the_end_of_the_clock() {
    let bad = raw![0x01, 0x03, 0x07, 0xD0, 0x00, 0x01, 0x84, 0x88].to_vec();
    let mut f = RtuFramer::new(Direction::Request, timing(), Vec::new());
    let late = Duration::MAX - Duration::from_nanos(1);
    assert!(f.push(late, &bad).is_empty());
    assert_eq!(f.deadline(), Some(Duration::MAX));
    assert_eq!(frames(&f.poll(Duration::MAX)), Vec::<Vec<u8>>::new());
    assert_eq!(f.pending(), &bad[..], "1 ns is not t3.5");
    assert_eq!(f.finish().len(), 1, "the held bytes end with the stream");
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

/// The length rules of FC 07, 0B, 0C, 11, 14, 15, 16, 18 (spec section 6) in both directions: the spec's example
/// frames back to back are cut by length and CRC alone, with no silence between them.
#[test]
fn framer_cuts_the_serial_line_file_and_fifo_functions_without_silence() {
    let requests: Vec<Vec<u8>> = [
        &raw![0x07][..],
        &raw![0x08, 0x00, 0x00, 0xA5, 0x37],
        &raw![0x0B],
        &raw![0x0C],
        &raw![0x11],
        &raw![
            0x14, 0x0E, 0x06, 0x00, 0x04, 0x00, 0x01, 0x00, 0x02, 0x06, 0x00, 0x03, 0x00, 0x09,
            0x00, 0x02
        ],
        &raw![
            0x15, 0x0D, 0x06, 0x00, 0x04, 0x00, 0x07, 0x00, 0x03, 0x06, 0xAF, 0x04, 0xBE, 0x10,
            0x0D
        ],
        &raw![0x16, 0x00, 0x04, 0x00, 0xF2, 0x00, 0x25],
        &raw![0x18, 0x04, 0xDE],
    ]
    .iter()
    .map(|pdu| rtu_frame(0x11, pdu))
    .collect();
    let responses: Vec<Vec<u8>> = [
        &raw![0x07, 0x6D][..],
        &raw![0x08, 0x00, 0x00, 0xA5, 0x37],
        &raw![0x0B, 0xFF, 0xFF, 0x01, 0x08],
        &raw![0x0C, 0x08, 0x00, 0x00, 0x01, 0x08, 0x01, 0x21, 0x20, 0x00],
        &raw![0x11, 0x03, 0x42, 0xFF, 0x31],
        &raw![
            0x14, 0x0C, 0x05, 0x06, 0x0D, 0xFE, 0x00, 0x20, 0x05, 0x06, 0x33, 0xCD, 0x00, 0x40
        ],
        &raw![
            0x15, 0x0D, 0x06, 0x00, 0x04, 0x00, 0x07, 0x00, 0x03, 0x06, 0xAF, 0x04, 0xBE, 0x10,
            0x0D
        ],
        &raw![0x16, 0x00, 0x04, 0x00, 0xF2, 0x00, 0x25],
        &raw![0x18, 0x00, 0x06, 0x00, 0x02, 0x01, 0xB8, 0x12, 0x84],
        &raw![0x94, 0x02],
    ]
    .iter()
    .map(|pdu| rtu_frame(0x11, pdu))
    .collect();
    for (dir, adus) in [
        (Direction::Request, requests),
        (Direction::Response, responses),
    ] {
        let mut f = RtuFramer::new(dir, timing(), Vec::new());
        let ev = f.push(Duration::ZERO, &adus.concat());
        assert_eq!(frames(&ev), adus, "{dir:?}");
        assert!(f.pending().is_empty(), "{dir:?}: {:02X?}", f.pending());
        for adu in &adus {
            assert!(rtu::decode(adu, dir).is_ok(), "{dir:?} {adu:02X?}");
        }
    }
}

/// Frames of the shortest and the longest length a rule may give (4 and 256 bytes) are cut as their last byte
/// arrives, whether the rest of the chunk follows at once or only later.
#[test]
fn framer_cuts_at_the_extreme_lengths_as_the_last_byte_arrives() {
    use codec::{LengthRule, VendorRule};
    for len in [rtu::MIN_ADU_LEN, rtu::MAX_ADU_LEN] {
        let body: Vec<u8> = (0..len - 4).map(|i| i as u8).collect();
        let frame = rtu_frame(1, &[&[0x65][..], &body].concat());
        assert_eq!(frame.len(), len);
        let rule = VendorRule {
            function: 0x65,
            request: LengthRule::Fixed(len),
            response: LengthRule::Fixed(len),
        };
        let t = timing().t1_5 / 2;
        // alone: the frame is out when its last byte is in, nothing is pending
        let mut f = RtuFramer::new(Direction::Request, timing(), vec![rule]);
        assert_eq!(frames(&f.push(Duration::ZERO, &frame)), vec![frame.clone()]);
        assert!(f.pending().is_empty());
        // a byte more in the same chunk starts the next frame, at the same instant
        let mut f = RtuFramer::new(Direction::Request, timing(), vec![rule]);
        let ev = f.push(Duration::ZERO, &[&frame[..], &[0x01]].concat());
        assert_eq!(frames(&ev), vec![frame.clone()]);
        assert_eq!(f.pending(), &[0x01]);
        // the last byte late: the frame ends then
        let mut f = RtuFramer::new(Direction::Request, timing(), vec![rule]);
        assert!(f.push(Duration::ZERO, &frame[..len - 1]).is_empty());
        let ev = f.push(t, &frame[len - 1..]);
        assert!(
            matches!(&ev[..], [FramerEvent::Frame { bytes, start, end, max_gap }]
                if *bytes == frame && *start == Duration::ZERO && *end == t && *max_gap == t),
            "{ev:?}"
        );
    }
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

/// The FIFO count (spec 6.18: at most 31) and the event log (6.10: at most 64 events) are limits of the encoder
/// too: what it refuses, a strict decoder would refuse.
#[test]
fn encode_refuses_32_fifo_registers_and_65_events() {
    use codec::EncodeError;
    assert!(
        Response::ReadFifoQueue {
            values: vec![0; 31]
        }
        .to_bytes()
        .is_ok()
    );
    assert_eq!(
        Response::ReadFifoQueue {
            values: vec![0; 32]
        }
        .to_bytes(),
        Err(EncodeError::TooLong {
            field: "FIFO values",
            len: 32,
            max: 31
        })
    );
    let log = |n| Response::GetCommEventLog {
        status: 0,
        event_count: 0,
        message_count: 0,
        events: vec![0; n],
    };
    assert!(log(64).to_bytes().is_ok());
    assert_eq!(
        log(65).to_bytes(),
        Err(EncodeError::TooLong {
            field: "events",
            len: 65,
            max: 64
        })
    );
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

/// FC 0x41's response: "Response n bytes n=N or N+1" (MDrive manual line 956, LMD manual line 1129). The codec
/// stays strict, so that a decoded answer re-encodes to its bytes (the fuzz target `tcp_adu` holds it to
/// that): a byte after the counted string is a trailing byte here; the runner leaves it out where it judges
/// answers (`vendor_read_unpadded`).
#[test]
fn a_vendor_read_answer_with_a_byte_after_its_count_is_strictly_a_trailing_byte() {
    let exact = Response::decode(&[0x41, 0x01, 0x30]).expect("N bytes");
    assert_eq!(
        exact,
        Response::VendorRead {
            params: b"0".to_vec()
        }
    );
    assert!(Response::decode(&[0x41, 0x01, 0x30, 0x00]).is_err());
    assert!(Response::decode(&[0x41, 0x02, 0x30]).is_err());
}
