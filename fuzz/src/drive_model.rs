//! `drive_model`: sequences of requests and raw bytes against each reference drive, over TCP and RTU.

use std::borrow::Cow;
use std::time::Duration;

use arbitrary::{Arbitrary, Unstructured};
use codec::framer::RtuTiming;
use codec::{Framing, Request, Response, hex_spaced};
use drives::profile::Profile;
use drives::{FaultSet, RtuPort, Station, TcpConn};

use crate::input::Input;
use crate::reference::{
    check_reply, frame_request, fresh_station, line_timing, liveness_probe, profiles,
};

/// `drive_model` operation tags (the tag byte is taken modulo `OPS`).
const OP_TYPED: u8 = 0;
pub(crate) const OP_PDU: u8 = 1;
pub(crate) const OP_TCP: u8 = 2;
pub(crate) const OP_RTU: u8 = 3;
pub(crate) const OP_WAIT: u8 = 4;
const OPS: u8 = 5;
/// At most this many operations of an input are run.
const MAX_OPS: usize = 64;

/// One operation of a `drive_model` input.
pub(crate) enum Op<'a> {
    /// A request to unit `default + unit` (mod 256), sent framed over TCP and over RTU.
    Request { unit: u8, pdu: Cow<'a, [u8]> },
    /// Bytes on the persistent Modbus/TCP connection.
    TcpStream(&'a [u8]),
    /// Bytes on the RTU line after a silence of `gap` sixteenths of t3.5.
    RtuStream { gap: u8, bytes: &'a [u8] },
    /// Idle time in milliseconds.
    Wait(u16),
}

pub(crate) fn parse_ops(data: &[u8]) -> Vec<Op<'_>> {
    let mut input = Input(data);
    let mut ops = Vec::new();
    while !input.is_empty() && ops.len() < MAX_OPS {
        ops.push(match input.u8() % OPS {
            OP_TYPED => {
                let unit = input.u8();
                let u = Unstructured::new(input.counted());
                let Ok(pdu) = Request::arbitrary_take_rest(u).map(|r| r.to_bytes()) else {
                    continue;
                };
                // A typed request too long for the wire is sent as far as it encodes: not at all.
                let Ok(pdu) = pdu else { continue };
                Op::Request {
                    unit,
                    pdu: Cow::Owned(pdu),
                }
            }
            OP_PDU => Op::Request {
                unit: input.u8(),
                pdu: Cow::Borrowed(input.counted()),
            },
            OP_TCP => Op::TcpStream(input.counted()),
            OP_RTU => Op::RtuStream {
                gap: input.u8(),
                bytes: input.counted(),
            },
            _ => Op::Wait(input.u16()),
        });
    }
    ops
}

/// One reference drive under a `drive_model` input, with its connection, line and clock.
struct DriveRun<'p> {
    /// The index of the drive in `DRIVES`.
    drive: usize,
    profile: &'p Profile,
    station: Station,
    conn: TcpConn,
    port: RtuPort,
    timing: RtuTiming,
    now: Duration,
}

impl<'p> DriveRun<'p> {
    fn new(drive: usize, profile: &'p Profile, faults: &FaultSet) -> Self {
        let timing = line_timing();
        Self {
            drive,
            profile,
            station: fresh_station(drive, faults),
            conn: TcpConn::default(),
            port: RtuPort::new(timing),
            timing,
            now: Duration::ZERO,
        }
    }

    fn apply(&mut self, op: &Op<'_>) {
        match op {
            Op::Request { unit, pdu } => {
                let unit = self.profile.device.default_unit.wrapping_add(*unit);
                self.request(unit, pdu);
            }
            Op::TcpStream(bytes) => {
                let out = self.station.serve_tcp(self.now, &mut self.conn, bytes);
                for w in &out.replies {
                    check_reply(Framing::Tcp, w, None, Duration::ZERO);
                }
            }
            Op::RtuStream { gap, bytes } => {
                self.now += self.timing.t3_5 * u32::from(*gap) / 16;
                for w in self.station.serve_rtu(self.now, &mut self.port, bytes) {
                    check_reply(Framing::Rtu, &w, None, self.timing.t3_5);
                }
            }
            Op::Wait(ms) => self.wait(Duration::from_millis((*ms).into())),
        }
    }

    fn wait(&mut self, d: Duration) {
        self.now += d;
        for w in self.station.poll_rtu(self.now, &mut self.port) {
            check_reply(Framing::Rtu, &w, None, self.timing.t3_5);
        }
    }

    /// Send a request PDU over TCP and over RTU; check who may answer and what.
    fn request(&mut self, unit: u8, pdu: &[u8]) -> Vec<Response> {
        let device = &self.profile.device;
        let [lo, hi] = device.unit_ids;
        let mut responses = Vec::new();
        let fc = pdu.first().copied().unwrap_or(0);
        if let Some(adu) = frame_request(Framing::Tcp, unit, pdu) {
            let out = self
                .station
                .serve_tcp(self.now, &mut TcpConn::default(), &adu);
            assert_eq!(
                out.close,
                pdu.is_empty(),
                "connection closed after a well-framed request"
            );
            let accepted = unit == device.default_unit || (lo..=hi).contains(&unit);
            assert!(
                out.replies.len() <= usize::from(accepted && !pdu.is_empty()),
                "{} replies over TCP to unit {unit}",
                out.replies.len()
            );
            for w in &out.replies {
                responses.push(check_reply(
                    Framing::Tcp,
                    w,
                    Some((unit, fc)),
                    Duration::ZERO,
                ));
            }
        }
        if let Some(frame) = frame_request(Framing::Rtu, unit, pdu) {
            let reply = self.station.rtu_frame(self.now, &frame);
            if let Some(w) = reply {
                assert_eq!(
                    unit, device.default_unit,
                    "RTU reply to address {unit}, not the drive's"
                );
                responses.push(check_reply(
                    Framing::Rtu,
                    &w,
                    Some((unit, fc)),
                    Duration::ZERO,
                ));
            }
        }
        // Reads have no side effects: the same read at the same instant gets the same answer on both transports.
        let read = matches!(pdu, [0x01..=0x04, ..] | [0x2B, 0x0E, ..]);
        if let [over_tcp, over_rtu] = &responses[..]
            && read
        {
            assert_eq!(
                over_tcp,
                over_rtu,
                "{}: the read {} is answered differently over TCP and RTU",
                device.id,
                hex_spaced(pdu)
            );
        }
        responses
    }

    /// After the sequence: the drive still answers a valid read on both transports, and its state holds.
    fn finish(&mut self) {
        self.wait(Duration::from_secs(1));
        let probe = liveness_probe(self.drive);
        let unit = self.profile.device.default_unit;
        // A sequence that forced listen only mode (08/04) left a drive that rightly answers nothing on the
        // serial line until an 08/01 restart (spec 6.8.1): restart it first, as a client would.
        if self.station.comm_state().listen_only {
            self.request(unit, &[0x08, 0x00, 0x01, 0x00, 0x00]);
            assert!(
                !self.station.comm_state().listen_only,
                "{}: 08/01 did not end listen only mode",
                self.profile.device.id
            );
        }
        let responses = self.request(unit, probe);
        assert_eq!(
            responses.len(),
            2,
            "{}: the liveness probe {} is not answered on both transports",
            self.profile.device.id,
            hex_spaced(probe)
        );
        for r in responses {
            assert!(
                !r.is_exception(),
                "{}: the liveness probe {} is answered with {r:?}",
                self.profile.device.id,
                hex_spaced(probe)
            );
        }
        assert!(!self.station.is_dead(), "the drive went silent for good");
        let c = self.station.counters();
        assert!(
            c.bus_message >= c.slave_message && c.slave_message >= c.no_response,
            "FC 08 counters out of order: {c:?}"
        );
    }
}

/// `drive_model`: any sequence of requests to each reference drive of [`DRIVES`], fault-free, over Modbus/TCP
/// and RTU. Input: operations, each a tag byte (mod 5) and its fields: 0 a typed request (unit offset, counted
/// bytes for `Arbitrary`), 1 a request PDU (unit offset, counted PDU), 2 counted bytes on the TCP stream,
/// 3 counted bytes on the RTU line (a gap byte first, in sixteenths of t3.5), 4 a wait (u16 ms, big-endian).
/// Requests go to unit `default_unit + offset`, framed over TCP and over RTU. Invariants: no panic; every
/// reply comes at once, decodes strictly as a response, echoes transaction id and unit, carries the request's
/// function code or its exception form; only the drive's units are answered; at the end the drive still
/// answers a valid read normally on both transports and its FC 08 counters are consistent.
///
/// [`DRIVES`]: crate::DRIVES
pub fn drive_model(data: &[u8]) {
    drive_model_with_faults(data, &FaultSet::none());
}

/// `drive_model` against drives with `faults` injected: the corpus test shows that the invariants catch
/// the wire-level faults (a check that cannot fail is a defect).
pub fn drive_model_with_faults(data: &[u8], faults: &FaultSet) {
    let ops = parse_ops(data);
    for (drive, profile) in profiles().iter().enumerate() {
        let mut run = DriveRun::new(drive, profile, faults);
        for op in &ops {
            run.apply(op);
        }
        run.finish();
    }
}
