//! A user's drive in process: a [`Device`] answers request PDUs with response PDUs, and [`DeviceTarget`]
//! frames them as Modbus/TCP or RTU on a virtual clock, so that every case of the catalog (transport cases
//! included) runs against it as against a drive on a wire. No sockets, no threads.

use std::collections::VecDeque;
use std::time::Duration;

use super::reader::FrameReader;
use super::{Received, Target, TargetError};
use codec::framer::{FramerEvent, RtuFramer};
use codec::{CharFormat, Direction, Framing, Parity, RtuTiming, rtu, tcp};

/// Virtual time per exchange on Modbus/TCP (a loopback round trip, so that timestamps move).
const TCP_LATENCY: Duration = Duration::from_micros(30);

/// A Modbus server in process: the seam a firmware's request handler plugs into.
///
/// The harness does the framing (MBAP on Modbus/TCP; address, CRC and the t3.5 silence on RTU) and hands
/// the device each request's PDU (function code first) with the unit id / slave address it was sent to.
/// The device returns the response PDU (function code first, `fc | 0x80` and the exception code for an
/// exception), or `None` to stay silent: for a unit id that is not its own, for an RTU broadcast (address
/// 0), or for a request it ignores. What it returns goes on the wire as it is: a wrong length, a wrong
/// function code or an answer to a broadcast is there for the cases to find.
///
/// A closure `FnMut(u8, &[u8]) -> Option<Vec<u8>>` is a `Device` too, and so is an
/// `Rc<RefCell<D>>` of a device `D`: keep a clone to look at the device's state after the run.
///
/// ```
/// use modbus_harness_engine::api::Device;
///
/// /// Answers every request with exception 01 (illegal function).
/// struct Refuser;
///
/// impl Device for Refuser {
///     fn handle(&mut self, _unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
///         Some(vec![pdu.first()? | 0x80, 0x01])
///     }
/// }
///
/// assert_eq!(Refuser.handle(1, &[0x03, 0, 0, 0, 1]), Some(vec![0x83, 0x01]));
/// ```
pub trait Device {
    /// Answer the request `pdu` sent to `unit`; `None` sends nothing.
    fn handle(&mut self, unit: u8, pdu: &[u8]) -> Option<Vec<u8>>;

    /// RTU only: the line dropped `bytes` before a PDU could be cut from them (a bad CRC, fewer than 4
    /// bytes before the t3.5 silence, over 256 bytes without one). For a device that keeps the FC 08 bus
    /// counters (0x0C CRC errors, 0x12 overruns); the default ignores it.
    fn rtu_discarded(&mut self, bytes: &[u8]) {
        let _ = bytes;
    }

    /// Time passed: the device's clock is now `now` (virtual time since the run started, never going
    /// back). For drives with state over time (a watchdog, a motion); the default does nothing.
    fn advance(&mut self, now: Duration) {
        let _ = now;
    }
}

impl<F: FnMut(u8, &[u8]) -> Option<Vec<u8>>> Device for F {
    fn handle(&mut self, unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
        self(unit, pdu)
    }
}

impl<D: Device> Device for std::rc::Rc<std::cell::RefCell<D>> {
    fn handle(&mut self, unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
        self.borrow_mut().handle(unit, pdu)
    }

    fn rtu_discarded(&mut self, bytes: &[u8]) {
        self.borrow_mut().rtu_discarded(bytes);
    }

    fn advance(&mut self, now: Duration) {
        self.borrow_mut().advance(now);
    }
}

impl Device for Box<dyn Device> {
    fn handle(&mut self, unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
        (**self).handle(unit, pdu)
    }

    fn rtu_discarded(&mut self, bytes: &[u8]) {
        (**self).rtu_discarded(bytes);
    }

    fn advance(&mut self, now: Duration) {
        (**self).advance(now);
    }
}

/// A [`Device`] as a [`Target`]: Modbus/TCP or RTU framing on a virtual clock.
///
/// Modbus/TCP: the stream is cut by the MBAP length; an ADU whose protocol id is not 0 is discarded and one
/// whose length field cannot be a Modbus ADU (under 2 or over 254) closes the connection (Modbus Messaging
/// on TCP/IP Implementation Guide v1.0b, 4.4.1); the answer echoes the transaction id and the unit id.
/// RTU: the request framer of the codec cuts frames by length rules, CRC and the t3.5 silence at 19200 baud
/// 8E1; a frame with a bad CRC is dropped (the device hears of it through [`Device::rtu_discarded`]); the answer carries the request's address and its CRC.
pub struct DeviceTarget {
    device: Box<dyn Device>,
    framing: Framing,
    now: Duration,
    timing: RtuTiming,
    /// Modbus/TCP: bytes received not yet cut into an ADU.
    tcp_buf: Vec<u8>,
    /// RTU: the device's receive side.
    framer: RtuFramer,
    /// Answers not yet received, with the virtual time they arrive.
    queued: VecDeque<(Duration, Vec<u8>)>,
    reader: FrameReader,
    closed: bool,
}

impl DeviceTarget {
    /// Frame `device` with `framing` (`Framing::Tcp` or `Framing::Rtu`).
    pub fn new(device: Box<dyn Device>, framing: Framing) -> Self {
        let timing = RtuTiming::new(
            19_200,
            CharFormat {
                parity: Parity::Even,
                stop_bits: 1,
            },
        );
        let rtu = framing == Framing::Rtu;
        Self {
            device,
            framing: if rtu { Framing::Rtu } else { Framing::Tcp },
            now: Duration::ZERO,
            timing,
            tcp_buf: Vec::new(),
            framer: RtuFramer::new(Direction::Request, timing, Vec::new()),
            queued: VecDeque::new(),
            reader: if rtu {
                FrameReader::rtu(timing)
            } else {
                FrameReader::mbap()
            },
            closed: false,
        }
    }

    fn answer_rtu(&mut self, events: Vec<FramerEvent>) {
        for ev in events {
            // Discarded bytes (bad CRC, too short) get no answer, as on a line.
            let bytes = match ev {
                FramerEvent::Frame { bytes, .. } => bytes,
                FramerEvent::Discarded { bytes, .. } => {
                    self.device.advance(self.now);
                    self.device.rtu_discarded(&bytes);
                    continue;
                }
            };
            let Ok(adu) = rtu::decode_adu(&bytes) else {
                continue;
            };
            self.device.advance(self.now);
            if let Some(pdu) = self.device.handle(adu.address, adu.pdu) {
                let mut out = Vec::with_capacity(pdu.len() + 3);
                out.push(adu.address);
                out.extend_from_slice(&pdu);
                let crc = rtu::crc16(&out);
                out.extend_from_slice(&crc.to_le_bytes());
                self.queued.push_back((self.now, out));
            }
        }
    }

    fn serve_tcp(&mut self) {
        // Bounded by the buffer: each turn takes at least one whole ADU out of it.
        while let Some(len) = tcp::adu_len(&self.tcp_buf) {
            if !(8..=260).contains(&len) {
                self.tcp_buf.clear();
                self.closed = true;
                return;
            }
            if self.tcp_buf.len() < len {
                return;
            }
            let adu: Vec<u8> = self.tcp_buf.drain(..len).collect();
            let Some(header) = tcp::Mbap::parse(&adu) else {
                continue;
            };
            if header.protocol_id != 0 {
                continue;
            }
            self.device.advance(self.now);
            if let Some(pdu) = self.device.handle(header.unit_id, &adu[tcp::MBAP_LEN..]) {
                // Framed as it is, even when the device's answer is too long for an ADU.
                let mut out = Vec::with_capacity(tcp::MBAP_LEN + pdu.len());
                out.extend_from_slice(&header.transaction_id.to_be_bytes());
                out.extend_from_slice(&[0, 0]);
                out.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
                out.push(header.unit_id);
                out.extend_from_slice(&pdu);
                self.queued.push_back((self.now, out));
            }
        }
    }

    /// Let the device see the silence up to `now` (RTU).
    fn poll_line(&mut self) {
        if self.framing == Framing::Rtu {
            let events = self.framer.poll(self.now);
            self.answer_rtu(events);
        }
    }
}

impl Target for DeviceTarget {
    fn framing(&self) -> Framing {
        self.framing
    }

    fn now(&self) -> Duration {
        self.now
    }

    fn send(&mut self, bytes: &[u8]) -> Result<(), TargetError> {
        match self.framing {
            Framing::Rtu => {
                // Bytes arrive one character time apart, as on a line: a chunk is not a silence.
                for b in bytes {
                    self.now += self.timing.char_time;
                    let events = self.framer.push(self.now, std::slice::from_ref(b));
                    self.answer_rtu(events);
                }
            }
            _ => {
                if self.closed {
                    // The runner reconnects after a close; bytes sent on the old connection are lost.
                    self.closed = false;
                    self.tcp_buf.clear();
                }
                self.now += TCP_LATENCY;
                self.tcp_buf.extend_from_slice(bytes);
                self.serve_tcp();
            }
        }
        Ok(())
    }

    fn recv(&mut self, timeout: Duration) -> Result<Received, TargetError> {
        let deadline = self.now + timeout;
        // Bounded: each turn consumes a queued answer or a framer deadline, or returns.
        loop {
            if let Some(r) = self.reader.next() {
                return Ok(r);
            }
            // An RTU device answers after t3.5 of silence following the request.
            if self.framing == Framing::Rtu
                && let Some(d) = self.framer.deadline()
                && d <= deadline
            {
                self.now = self.now.max(d);
                self.poll_line();
                continue;
            }
            if let Some((at, _)) = self.queued.front()
                && *at <= deadline
            {
                let (at, bytes) = self.queued.pop_front().unwrap_or_default();
                self.now = self.now.max(at);
                if self.framing == Framing::Rtu {
                    self.now += self.timing.transmit_time(bytes.len());
                }
                self.reader.push(self.now, &bytes);
                if self.framing == Framing::Rtu {
                    // Nothing else is on the line: the frame ends with silence.
                    self.now += self.timing.t3_5;
                    self.reader.poll(self.now);
                }
                continue;
            }
            if self.closed && self.framing != Framing::Rtu {
                self.now += TCP_LATENCY;
                return Ok(Received::Closed {
                    partial: self.reader.partial(),
                    at: self.now,
                });
            }
            self.now = self.now.max(deadline);
            self.reader.poll(self.now);
            if let Some(r) = self.reader.next() {
                return Ok(r);
            }
            return Ok(Received::Silence {
                partial: self.reader.partial(),
                at: self.now,
            });
        }
    }

    fn idle(&mut self, d: Duration) {
        self.now += d;
        self.poll_line();
        self.device.advance(self.now);
    }

    fn reconnect(&mut self) -> Result<(), TargetError> {
        self.tcp_buf.clear();
        self.closed = false;
        self.reader.clear();
        Ok(())
    }

    fn drain(&mut self) {
        // Answers that would have arrived by now are stale; later ones stay queued.
        let now = self.now;
        self.queued.retain(|(at, _)| *at > now);
        self.reader.clear();
    }

    fn describe(&self) -> String {
        let framing = if self.framing == Framing::Rtu {
            "RTU"
        } else {
            "Modbus/TCP"
        };
        format!("an in-process device ({framing}, virtual clock)")
    }

    fn rtu_timing(&self) -> Option<RtuTiming> {
        (self.framing == Framing::Rtu).then_some(self.timing)
    }

    fn answer_gap_measurable(&self) -> Result<(), String> {
        Err(
            "the harness frames an in-process device's answers: their timing is the harness's"
                .into(),
        )
    }
}
