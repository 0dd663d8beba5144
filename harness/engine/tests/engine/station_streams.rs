//! Arbitrary byte streams into every reference drive over every transport path (Modbus/TCP stream,
//! RTU line with timing, RTU over TCP): no panic, every answer decodes strictly, and the drive is still in
//! service afterwards (a valid read on a fresh connection / after line silence is answered).

use std::time::Duration;

use codec::{CharFormat, Direction, Parity, RtuTiming, rtu, tcp};
use drives::{RtuPort, TcpConn};
use engine::cases::catalog::known_good_read;
use proptest::prelude::*;
use test_support::{profile, station};

const PROFILES: [&str; 4] = ["sd2x", "mdrive", "lmd", "generic"];

fn chunks() -> impl Strategy<Value = Vec<(Vec<u8>, u16)>> {
    // (bytes, gap in µs before them): garbage, valid-looking MBAP headers, RTU-looking frames alike.
    prop::collection::vec(
        (prop::collection::vec(any::<u8>(), 0..40), 0u16..5000),
        0..24,
    )
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn tcp_streams(stream in chunks(), which in 0usize..4) {
        let p = profile(PROFILES[which]);
        let mut s = station(PROFILES[which], &[]);
        let mut conn = TcpConn::default();
        let mut now = Duration::ZERO;
        for (bytes, gap) in &stream {
            now += Duration::from_micros(u64::from(*gap));
            let out = s.serve_tcp(now, &mut conn, bytes);
            for w in &out.replies {
                prop_assert!(tcp::decode(&w.bytes, Direction::Response).is_ok(), "undecodable answer {:02X?}", w.bytes);
            }
            if out.close {
                conn = TcpConn::default();
            }
        }
        // Still in service: a fresh connection's valid read is answered.
        let mut fresh = TcpConn::default();
        let mut adu = Vec::new();
        tcp::encode_adu(7, p.device.default_unit, &known_good_read(&p), &mut adu).unwrap();
        let out = s.serve_tcp(now + Duration::from_millis(1), &mut fresh, &adu);
        prop_assert_eq!(out.replies.len(), 1, "no answer after the stream");
        let (h, _) = tcp::decode(&out.replies[0].bytes, Direction::Response).expect("decodes");
        prop_assert_eq!(h.transaction_id, 7);
    }

    #[test]
    fn rtu_streams(stream in chunks(), which in 0usize..4, over_tcp in any::<bool>()) {
        let p = profile(PROFILES[which]);
        let mut s = station(PROFILES[which], &[]);
        let timing = if over_tcp {
            RtuTiming::tcp_carrier()
        } else {
            RtuTiming::new(19_200, CharFormat { parity: Parity::Even, stop_bits: 1 })
        };
        let mut port = RtuPort::new(timing);
        let mut now = Duration::ZERO;
        for (bytes, gap) in &stream {
            now += Duration::from_micros(u64::from(*gap));
            let mut replies = s.poll_rtu(now, &mut port);
            replies.extend(s.serve_rtu(now, &mut port, bytes));
            for w in &replies {
                prop_assert!(rtu::decode(&w.bytes, Direction::Response).is_ok(), "undecodable answer {:02X?}", w.bytes);
            }
        }
        // Silence ends whatever is pending; then a valid read is answered.
        now += timing.t3_5 * 2;
        let _ = s.poll_rtu(now, &mut port);
        let mut frame = Vec::new();
        rtu::encode_adu(p.device.default_unit, &known_good_read(&p), &mut frame).unwrap();
        let mut replies = s.serve_rtu(now, &mut port, &frame);
        replies.extend(s.poll_rtu(now + timing.t3_5 * 2, &mut port));
        prop_assert_eq!(replies.len(), 1, "no answer after the stream");
        let (addr, _) = rtu::decode(&replies[0].bytes, Direction::Response).expect("decodes");
        prop_assert_eq!(addr, p.device.default_unit);
    }
}
