//! The wire side of a simulated drive, sans-IO: bytes in, bytes out with a delay.
//!
//! The station applies what the Modbus specs require of any server before the model sees a request
//! (MBAP checks, unit/slave addressing, broadcast, supported function codes, quantity limits, FC 05 values,
//! the FC 08 serial-line counters) and applies the wire-level faults to what goes out.

use std::time::Duration;

use crate::faults::{Fault, FaultSet};
use crate::models::DriveModel;
use crate::profile::{DiagCounter, Profile};
use codec::framer::{DiscardReason, FramerEvent, RtuFramer, RtuTiming};
use codec::{Direction, ExceptionCode, FunctionCode, Request, Response, rtu, tcp};

/// Bytes to send, `delay` after the request was complete.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Wire {
    pub bytes: Vec<u8>,
    pub delay: Duration,
}

/// How late the `late-response` fault answers.
pub const LATE_RESPONSE_DELAY: Duration = Duration::from_millis(1500);

/// The serial-line diagnostic counters of FC 08 (Modbus over serial line spec, 6.1.x).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counters {
    /// Messages with a valid CRC seen on the line, for any address (sub-function 0x0B).
    pub bus_message: u16,
    /// Frames dropped for a CRC error or a framing error (0x0C).
    pub crc_error: u16,
    /// Exception responses sent (0x0D).
    pub exception: u16,
    /// Messages addressed to this drive, broadcasts included (0x0E).
    pub slave_message: u16,
    /// Messages addressed to this drive that got no response, broadcasts included (0x0F).
    pub no_response: u16,
}

/// One Modbus/TCP connection's receive buffer: cuts the stream into ADUs by the MBAP length field.
#[derive(Clone, Debug, Default)]
pub struct TcpConn {
    buf: Vec<u8>,
}

/// What a TCP connection produced.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct TcpOutput {
    /// Replies in request order.
    pub replies: Vec<Wire>,
    /// The stream cannot be resynchronised (an MBAP length below 2 or above 254): close the connection.
    pub close: bool,
}

/// One RTU line's receive side (serial port, or an RTU-over-TCP connection).
#[derive(Clone, Debug)]
pub struct RtuPort {
    framer: RtuFramer,
}

impl RtuPort {
    /// A port receiving requests on a line with `timing`.
    pub fn new(timing: RtuTiming) -> Self {
        Self {
            framer: RtuFramer::new(Direction::Request, timing, Vec::new()),
        }
    }

    /// When the station should be polled for silence-delimited frames.
    pub fn deadline(&self) -> Option<Duration> {
        self.framer.deadline()
    }

    /// The line timing.
    pub fn timing(&self) -> RtuTiming {
        self.framer.timing()
    }
}

/// A simulated drive on the wire. A clone is an independent copy in the same state (see
/// [`DriveModel::box_clone`]).
#[derive(Clone)]
pub struct Station {
    model: Box<dyn DriveModel>,
    faults: FaultSet,
    unit: u8,
    counters: Counters,
    dead: bool,
}

impl Station {
    /// A station answering as unit `unit` (RTU slave address; on TCP the unit ids of the profile are answered too).
    pub fn new(model: Box<dyn DriveModel>, faults: FaultSet, unit: u8) -> Self {
        Self {
            model,
            faults,
            unit,
            counters: Counters::default(),
            dead: false,
        }
    }

    /// The drive model.
    pub fn model(&self) -> &dyn DriveModel {
        self.model.as_ref()
    }

    /// The drive model, mutably (tests and the in-process target advance its clock).
    pub fn model_mut(&mut self) -> &mut dyn DriveModel {
        self.model.as_mut()
    }

    /// The profile of the drive.
    pub fn profile(&self) -> &Profile {
        self.model.profile()
    }

    /// The FC 08 counters.
    pub fn counters(&self) -> Counters {
        self.counters
    }

    /// True once `stop-after-malformed` has silenced the drive.
    pub fn is_dead(&self) -> bool {
        self.dead
    }

    fn count(&mut self, f: impl FnOnce(&mut Counters)) {
        if !self.faults.has(Fault::CountersFrozen) {
            f(&mut self.counters);
        }
    }

    fn malformed(&mut self) {
        if self.faults.has(Fault::StopAfterMalformed) {
            self.dead = true;
        }
    }

    /// Feed bytes received on a Modbus/TCP connection at `now`; returns the replies.
    pub fn serve_tcp(&mut self, now: Duration, conn: &mut TcpConn, bytes: &[u8]) -> TcpOutput {
        conn.buf.extend_from_slice(bytes);
        let mut out = TcpOutput::default();
        let mut answered = 0;
        while let Some(len) = tcp::adu_len(&conn.buf) {
            let declared = len - 6;
            if !(2..=254).contains(&declared) {
                self.malformed();
                conn.buf.clear();
                out.close = true;
                break;
            }
            if conn.buf.len() < len {
                break;
            }
            // Answered in place, then dropped from the buffer: no copy of the ADU.
            let reply = self.tcp_adu(now, &conn.buf[..len]);
            conn.buf.drain(..len);
            if let Some(w) = reply {
                if answered == 0 || !self.faults.has(Fault::PipelineDrop) {
                    out.replies.push(w);
                }
                answered += 1;
            }
        }
        out
    }

    /// Answer one complete Modbus/TCP ADU (`None`: no response is sent).
    pub fn tcp_adu(&mut self, now: Duration, adu: &[u8]) -> Option<Wire> {
        let header = tcp::Mbap::parse(adu)?;
        if header.protocol_id != 0 && !self.faults.has(Fault::ProtocolIdIgnored) {
            // TCP implementation guide: a frame whose protocol id is not Modbus is discarded.
            self.malformed();
            return None;
        }
        if self.dead {
            return None;
        }
        let accepted = header.unit_id == self.unit || {
            let [lo, hi] = self.profile().device.unit_ids;
            (lo..=hi).contains(&header.unit_id)
        };
        if !accepted && !self.faults.has(Fault::AnswerOtherUnit) {
            return None;
        }
        let pdu = &adu[tcp::MBAP_LEN..];
        let resp = self.answer(now, header.unit_id, pdu)?;
        let mut body = self.pdu_bytes(&resp);
        if self.faults.has(Fault::TruncatedResponse) && body.len() > 1 {
            body.pop();
        }
        let tid = if self.faults.has(Fault::TidNotEchoed) {
            header.transaction_id.wrapping_add(1)
        } else {
            header.transaction_id
        };
        let unit = if self.faults.has(Fault::UnitNotEchoed) {
            header.unit_id ^ 0x01
        } else {
            header.unit_id
        };
        let mut bytes = Vec::with_capacity(tcp::MBAP_LEN + body.len());
        tcp::encode_adu(tid, unit, &body, &mut bytes).ok()?;
        if self.faults.has(Fault::MbapLength) {
            let len = u16::from_be_bytes([bytes[4], bytes[5]]).wrapping_add(1);
            bytes[4..6].copy_from_slice(&len.to_be_bytes());
        }
        Some(self.wire(bytes))
    }

    /// Feed bytes received on an RTU line at `now`; returns replies for frames completed by them.
    pub fn serve_rtu(&mut self, now: Duration, port: &mut RtuPort, bytes: &[u8]) -> Vec<Wire> {
        let events = port.framer.push(now, bytes);
        self.rtu_events(now, events)
    }

    /// Let silence complete or discard what the port holds at `now`.
    pub fn poll_rtu(&mut self, now: Duration, port: &mut RtuPort) -> Vec<Wire> {
        let events = port.framer.poll(now);
        self.rtu_events(now, events)
    }

    fn rtu_events(&mut self, now: Duration, events: Vec<FramerEvent>) -> Vec<Wire> {
        let mut out = Vec::new();
        for ev in events {
            match ev {
                FramerEvent::Frame { bytes, .. } => {
                    if let Some(w) = self.rtu_frame(now, &bytes) {
                        out.push(w);
                    }
                }
                FramerEvent::Discarded { bytes, reason, .. } => {
                    if self.faults.has(Fault::CrcUnchecked)
                        && matches!(reason, DiscardReason::BadCrc { .. })
                        && bytes.len() >= 4
                    {
                        // The faulty drive takes the frame as if its CRC were right.
                        let mut fixed = bytes[..bytes.len() - 2].to_vec();
                        let crc = rtu::crc16(&fixed);
                        fixed.extend_from_slice(&crc.to_le_bytes());
                        if let Some(w) = self.rtu_frame(now, &fixed) {
                            out.push(w);
                        }
                        continue;
                    }
                    if matches!(
                        reason,
                        DiscardReason::BadCrc { .. }
                            | DiscardReason::TooShort
                            | DiscardReason::Overlong
                    ) {
                        self.count(|c| c.crc_error = c.crc_error.wrapping_add(1));
                        self.malformed();
                    }
                }
            }
        }
        out
    }

    /// Answer one RTU ADU whose CRC is valid (`None`: silence).
    pub fn rtu_frame(&mut self, now: Duration, frame: &[u8]) -> Option<Wire> {
        let Ok(adu) = rtu::decode_adu(frame) else {
            self.count(|c| c.crc_error = c.crc_error.wrapping_add(1));
            self.malformed();
            return None;
        };
        self.count(|c| c.bus_message = c.bus_message.wrapping_add(1));
        let broadcast = adu.address == rtu::BROADCAST && self.profile().device.broadcast;
        let ours = adu.address == self.unit || broadcast;
        if !ours && !self.faults.has(Fault::AnswerOtherUnit) {
            return None;
        }
        if self.dead {
            return None;
        }
        self.count(|c| c.slave_message = c.slave_message.wrapping_add(1));
        let pdu = adu.pdu.to_vec();
        let resp = self.answer(now, adu.address, &pdu);
        let resp = match resp {
            Some(r) if !broadcast || self.faults.has(Fault::BroadcastAnswered) => r,
            _ => {
                self.count(|c| c.no_response = c.no_response.wrapping_add(1));
                return None;
            }
        };
        let mut body = self.pdu_bytes(&resp);
        if self.faults.has(Fault::TruncatedResponse) && body.len() > 1 {
            body.pop();
        }
        let address = if self.faults.has(Fault::UnitNotEchoed) {
            adu.address ^ 0x01
        } else {
            adu.address
        };
        let mut bytes = Vec::with_capacity(body.len() + 3);
        rtu::encode_adu(address, &body, &mut bytes).ok()?;
        if self.faults.has(Fault::WrongCrc) {
            let n = bytes.len();
            bytes[n - 2] ^= 0xFF;
        }
        Some(self.wire(bytes))
    }

    fn wire(&self, bytes: Vec<u8>) -> Wire {
        let delay = if self.faults.has(Fault::LateResponse) {
            LATE_RESPONSE_DELAY
        } else {
            Duration::ZERO
        };
        Wire { bytes, delay }
    }

    /// The response PDU bytes with the PDU-level faults applied.
    fn pdu_bytes(&self, resp: &Response) -> Vec<u8> {
        let mut b = resp.to_bytes().unwrap_or_else(|_| {
            Response::exception(
                resp.function().without_exception_bit(),
                ExceptionCode::SERVER_DEVICE_FAILURE,
            )
            .to_bytes()
            .unwrap_or_default()
        });
        if b.is_empty() {
            return b;
        }
        if resp.is_exception() {
            if self.faults.has(Fault::ExceptionWithoutFc) {
                b[0] = 0x80;
            }
            if self.faults.has(Fault::WrongExceptionCode) && b.len() == 2 {
                b[1] = match b[1] {
                    1 => 2,
                    2 => 3,
                    3 => 4,
                    _ => 1,
                };
            }
        } else if self.faults.has(Fault::WrongFunctionCode) {
            b[0] ^= 0x01;
        }
        b
    }

    /// The spec-level checks every server makes, then the model. `None`: the drive stays silent.
    fn answer(&mut self, now: Duration, unit: u8, pdu: &[u8]) -> Option<Response> {
        let fc = FunctionCode(*pdu.first()?);
        let supported = !fc.is_exception() && self.profile().function(fc).is_some();
        let resp = if !supported {
            Some(Response::exception(fc, ExceptionCode::ILLEGAL_FUNCTION))
        } else {
            match Request::decode(pdu) {
                Err(_) => {
                    self.malformed();
                    if self.dead {
                        return None;
                    }
                    Some(Response::exception(fc, ExceptionCode::ILLEGAL_DATA_VALUE))
                }
                Ok(req) => match self.spec_checks(&req) {
                    Some(e) => Some(Response::exception(fc, e)),
                    None if fc == FunctionCode::DIAGNOSTICS => Some(self.diagnostics(&req)),
                    None => {
                        self.model.advance(now);
                        self.model.handle(now, unit, &req)
                    }
                },
            }
        };
        if resp.as_ref().is_some_and(|r| r.is_exception()) {
            self.count(|c| c.exception = c.exception.wrapping_add(1));
        }
        resp
    }

    /// Quantity limits and FC 05 values, per the application protocol spec's state diagrams.
    fn spec_checks(&self, req: &Request) -> Option<ExceptionCode> {
        let limit = |fc: FunctionCode| {
            self.profile()
                .function(fc)
                .and_then(|f| f.max_quantity)
                .or(fc.max_quantity())
                .unwrap_or(u16::MAX)
        };
        let bad =
            |q: u16, max: u16| (q == 0 || q > max) && !self.faults.has(Fault::QuantityUnchecked);
        use Request::*;
        let illegal = match req {
            ReadCoils { quantity, .. }
            | ReadDiscreteInputs { quantity, .. }
            | ReadHoldingRegisters { quantity, .. }
            | ReadInputRegisters { quantity, .. }
            | WriteMultipleCoils { quantity, .. } => bad(*quantity, limit(req.function())),
            WriteMultipleRegisters { values, .. } => bad(
                values.len() as u16,
                limit(FunctionCode::WRITE_MULTIPLE_REGISTERS),
            ),
            ReadWriteMultipleRegisters {
                read_quantity,
                values,
                ..
            } => {
                let wmax = self
                    .profile()
                    .function(FunctionCode::READ_WRITE_MULTIPLE_REGISTERS)
                    .and_then(|f| f.max_write_quantity)
                    .unwrap_or(FunctionCode::MAX_READ_WRITE_WRITE_QUANTITY);
                bad(
                    *read_quantity,
                    limit(FunctionCode::READ_WRITE_MULTIPLE_REGISTERS),
                ) || bad(values.len() as u16, wmax)
            }
            WriteSingleCoil { value, .. } => {
                *value != 0xFF00 && *value != 0 && !self.faults.has(Fault::IllegalCoilValueAccepted)
            }
            _ => false,
        };
        illegal.then_some(ExceptionCode::ILLEGAL_DATA_VALUE)
    }

    /// FC 08 over the counters, for the sub-functions the profile lists.
    fn diagnostics(&mut self, req: &Request) -> Response {
        let Request::Diagnostics { sub_function, data } = req else {
            return Response::exception(FunctionCode::DIAGNOSTICS, ExceptionCode::ILLEGAL_FUNCTION);
        };
        let Some(d) = self
            .profile()
            .diagnostics
            .iter()
            .find(|d| d.sub_function == *sub_function)
            .map(|d| d.counter)
        else {
            return Response::exception(FunctionCode::DIAGNOSTICS, ExceptionCode::ILLEGAL_FUNCTION);
        };
        if d != DiagCounter::Echo && data.len() != 2 {
            return Response::exception(
                FunctionCode::DIAGNOSTICS,
                ExceptionCode::ILLEGAL_DATA_VALUE,
            );
        }
        let c = self.counters;
        let value = match d {
            DiagCounter::Echo => {
                return Response::Diagnostics {
                    sub_function: *sub_function,
                    data: data.clone(),
                };
            }
            DiagCounter::Clear => {
                self.counters = Counters::default();
                return Response::Diagnostics {
                    sub_function: *sub_function,
                    data: data.clone(),
                };
            }
            DiagCounter::BusMessage => c.bus_message,
            DiagCounter::CrcError => c.crc_error,
            DiagCounter::Exception => c.exception,
            DiagCounter::SlaveMessage => c.slave_message,
            DiagCounter::NoResponse => c.no_response,
        };
        Response::Diagnostics {
            sub_function: *sub_function,
            data: value.to_be_bytes().to_vec(),
        }
    }
}
