//! The harness's end of an in-process line on a virtual clock: what a drive in process (the reference drive,
//! a user's [`Device`](super::device::Device)) answers is queued with the virtual time it arrives and read
//! through the frame readers of the real transports, so that verdicts do not depend on where the drive runs.

use std::collections::VecDeque;
use std::time::Duration;

use super::reader::FrameReader;
use super::{Received, TargetError};
use codec::{Framing, RtuTiming};

/// Virtual line time per exchange on Modbus/TCP (a loopback round trip, so that timestamps move).
pub(super) const TCP_LATENCY: Duration = Duration::from_micros(30);

/// The drive's end of the line: its RTU receiver, which answers once it has seen the t3.5 silence.
pub(super) trait DriveEnd {
    /// When the drive's RTU receiver next acts on silence, if it waits for one.
    fn deadline(&self) -> Option<Duration>;
    /// The line has been silent up to `line.now`: the drive acts on it, queueing its answers on `line`.
    fn poll(&mut self, line: &mut VirtualLine);
}

/// The harness's end: Modbus/TCP or RTU framing, the clock, and the answers on their way.
#[derive(Clone)]
pub(super) struct VirtualLine {
    pub framing: Framing,
    pub now: Duration,
    pub timing: RtuTiming,
    /// Answers not yet received, with the virtual time they arrive.
    queued: VecDeque<(Duration, Vec<u8>)>,
    reader: FrameReader,
    /// Modbus/TCP: the drive closed the connection.
    pub closed: bool,
}

impl VirtualLine {
    /// A line with `framing` (RTU, or Modbus/TCP for anything else) and RTU character `timing`.
    pub fn new(framing: Framing, timing: RtuTiming) -> Self {
        let rtu = framing == Framing::Rtu;
        Self {
            framing: if rtu { Framing::Rtu } else { Framing::Tcp },
            now: Duration::ZERO,
            timing,
            queued: VecDeque::new(),
            reader: if rtu {
                FrameReader::rtu(timing)
            } else {
                FrameReader::mbap()
            },
            closed: false,
        }
    }

    pub fn is_rtu(&self) -> bool {
        self.framing == Framing::Rtu
    }

    /// The drive sends `bytes`, arriving at `at`.
    pub fn queue(&mut self, at: Duration, bytes: Vec<u8>) {
        self.queued.push_back((at, bytes));
    }

    /// Let the drive see the silence up to now (RTU).
    pub fn poll(&mut self, end: &mut impl DriveEnd) {
        if self.is_rtu() {
            end.poll(self);
        }
    }

    /// The next frame, close or silence within `timeout`, time moving as on the line.
    pub fn recv(
        &mut self,
        end: &mut impl DriveEnd,
        timeout: Duration,
    ) -> Result<Received, TargetError> {
        let deadline = self.now + timeout;
        // Bounded: each turn consumes a queued answer or the drive's deadline, or returns.
        loop {
            if let Some(r) = self.reader.next() {
                return Ok(r);
            }
            // An RTU drive answers after t3.5 of silence following the request.
            if self.is_rtu()
                && let Some(d) = end.deadline()
                && d <= deadline
            {
                self.now = self.now.max(d);
                end.poll(self);
                continue;
            }
            if let Some((at, _)) = self.queued.front()
                && *at <= deadline
            {
                let (at, bytes) = self.queued.pop_front().unwrap_or_default();
                self.now = self.now.max(at);
                self.arrive(&bytes);
                continue;
            }
            if self.closed && !self.is_rtu() {
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

    /// An answer reaches the reader, sent at `now`.
    fn arrive(&mut self, bytes: &[u8]) {
        if !self.is_rtu() || bytes.is_empty() {
            self.reader.push(self.now, bytes);
        } else {
            // On the line, the first character is in after one character time: the answer's start is what
            // the inter-frame silence is measured to. The rest follows without a gap. (The rest is stamped one
            // character later, not at its end: the framer would take the span for a gap.)
            let c = self.timing.char_time;
            let start = self.now;
            self.reader.push(start + c, &bytes[..1]);
            self.reader.push(start + c + c, &bytes[1..]);
            self.now += self.timing.transmit_time(bytes.len());
        }
        if self.is_rtu() {
            // Nothing else is on the line: the frame ends with silence.
            self.now += self.timing.t3_5;
            self.reader.poll(self.now);
        }
    }

    /// A new connection: nothing half read is kept.
    pub fn reconnect(&mut self) {
        self.closed = false;
        self.reader.clear();
    }

    /// Answers that would have arrived by now are stale; later ones stay queued (a late drive).
    pub fn drain(&mut self) {
        let now = self.now;
        self.queued.retain(|(at, _)| *at > now);
        self.reader.clear();
    }

    pub fn rtu_timing(&self) -> Option<RtuTiming> {
        self.is_rtu().then_some(self.timing)
    }
}
