//! A user's drive in process: a [`Device`] answers request PDUs with response PDUs, and [`DeviceTarget`]
//! frames them as Modbus/TCP or RTU on a virtual clock, so that every case of the catalog (transport cases
//! included) runs against it as against a drive on a wire. No sockets, no threads.

use std::time::Duration;

use super::line::{DriveEnd, TCP_LATENCY, VirtualLine};
use super::{Received, Target, TargetError};
use codec::framer::{FramerEvent, RtuFramer};
use codec::{CharFormat, Direction, Framing, Parity, RtuTiming, rtu, tcp};

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
    end: DeviceEnd,
    /// Modbus/TCP: bytes received not yet cut into an ADU.
    tcp_buf: Vec<u8>,
    line: VirtualLine,
}

/// The device's end of the line: the device and its RTU receiver.
struct DeviceEnd {
    device: Box<dyn Device>,
    /// RTU: the device's receive side.
    framer: RtuFramer,
}

impl DriveEnd for DeviceEnd {
    fn deadline(&self) -> Option<Duration> {
        self.framer.deadline()
    }

    fn poll(&mut self, line: &mut VirtualLine) {
        let events = self.framer.poll(line.now);
        self.answer_rtu(line, events);
    }
}

impl DeviceEnd {
    fn answer_rtu(&mut self, line: &mut VirtualLine, events: Vec<FramerEvent>) {
        for ev in events {
            // Discarded bytes (bad CRC, too short) get no answer, as on a line.
            let bytes = match ev {
                FramerEvent::Frame { bytes, .. } => bytes,
                FramerEvent::Discarded { bytes, .. } => {
                    self.device.advance(line.now);
                    self.device.rtu_discarded(&bytes);
                    continue;
                }
            };
            let Ok(adu) = rtu::decode_adu(&bytes) else {
                continue;
            };
            self.device.advance(line.now);
            if let Some(pdu) = self.device.handle(adu.address, adu.pdu) {
                let mut out = Vec::with_capacity(pdu.len() + 3);
                out.push(adu.address);
                out.extend_from_slice(&pdu);
                let crc = rtu::crc16(&out);
                out.extend_from_slice(&crc.to_le_bytes());
                line.queue(line.now, out);
            }
        }
    }
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
        Self {
            end: DeviceEnd {
                device,
                framer: RtuFramer::new(Direction::Request, timing, Vec::new()),
            },
            tcp_buf: Vec::new(),
            line: VirtualLine::new(framing, timing),
        }
    }

    fn serve_tcp(&mut self) {
        let line = &mut self.line;
        // Bounded by the buffer: each turn takes at least one whole ADU out of it.
        while let Some(len) = tcp::adu_len(&self.tcp_buf) {
            if !(8..=260).contains(&len) {
                self.tcp_buf.clear();
                line.closed = true;
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
            let device = &mut self.end.device;
            device.advance(line.now);
            if let Some(pdu) = device.handle(header.unit_id, &adu[tcp::MBAP_LEN..]) {
                // Framed as it is, even when the device's answer is too long for an ADU.
                let mut out = Vec::with_capacity(tcp::MBAP_LEN + pdu.len());
                out.extend_from_slice(&header.transaction_id.to_be_bytes());
                out.extend_from_slice(&[0, 0]);
                out.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
                out.push(header.unit_id);
                out.extend_from_slice(&pdu);
                line.queue(line.now, out);
            }
        }
    }
}

impl Target for DeviceTarget {
    fn framing(&self) -> Framing {
        self.line.framing
    }

    fn now(&self) -> Duration {
        self.line.now
    }

    fn send(&mut self, bytes: &[u8]) -> Result<(), TargetError> {
        if self.line.is_rtu() {
            // Bytes arrive one character time apart, as on a line: a chunk is not a silence.
            for b in bytes {
                let line = &mut self.line;
                line.now += line.timing.char_time;
                let events = self.end.framer.push(line.now, std::slice::from_ref(b));
                self.end.answer_rtu(line, events);
            }
        } else {
            if self.line.closed {
                // The runner reconnects after a close; bytes sent on the old connection are lost.
                self.line.closed = false;
                self.tcp_buf.clear();
            }
            self.line.now += TCP_LATENCY;
            self.tcp_buf.extend_from_slice(bytes);
            self.serve_tcp();
        }
        Ok(())
    }

    fn recv(&mut self, timeout: Duration) -> Result<Received, TargetError> {
        self.line.recv(&mut self.end, timeout)
    }

    fn idle(&mut self, d: Duration) {
        self.line.now += d;
        self.line.poll(&mut self.end);
        self.end.device.advance(self.line.now);
    }

    fn reconnect(&mut self) -> Result<(), TargetError> {
        self.tcp_buf.clear();
        self.line.reconnect();
        Ok(())
    }

    fn drain(&mut self) {
        self.line.drain();
    }

    fn describe(&self) -> String {
        let framing = if self.line.is_rtu() {
            "RTU"
        } else {
            "Modbus/TCP"
        };
        format!("an in-process device ({framing}, virtual clock)")
    }

    fn rtu_timing(&self) -> Option<RtuTiming> {
        self.line.rtu_timing()
    }

    fn answer_gap_measurable(&self) -> Result<(), String> {
        Err(
            "the harness frames an in-process device's answers: their timing is the harness's"
                .into(),
        )
    }
}
