//! The in-process reference drive: no sockets, a virtual clock. Replies go through the same frame
//! readers as on real transports, so verdicts do not depend on where the drive runs.

use std::collections::VecDeque;
use std::time::Duration;

use super::reader::FrameReader;
use super::{Received, Target, TargetError};
use codec::{CharFormat, Framing, Parity, RtuTiming};
use drives::profile::Transport;
use drives::{RtuPort, Station, TcpConn};

/// Virtual line time per exchange on TCP (a loopback round trip, so timestamps move).
const TCP_LATENCY: Duration = Duration::from_micros(30);

/// A reference drive in process. A clone is an independent copy in the same state (the runner keeps one to
/// undo a request the drive was free to ignore).
#[derive(Clone)]
pub struct SimTarget {
    station: Station,
    framing: Framing,
    now: Duration,
    conn: TcpConn,
    port: RtuPort,
    timing: RtuTiming,
    /// Replies not yet received, with the virtual time they arrive.
    queued: VecDeque<(Duration, Vec<u8>)>,
    reader: FrameReader,
    closed: bool,
    /// Model the line's character times (a simulated target), or take time only from `idle`
    /// (the oracle, which mirrors a target whose clock is the truth).
    line_time: bool,
}

impl SimTarget {
    /// Wrap a station; RTU-only profiles use RTU framing (19200 8E1 timing, the Modbus default), others TCP.
    pub fn new(station: Station) -> Self {
        let rtu = !station
            .profile()
            .device
            .transports
            .contains(&Transport::Tcp);
        Self::with_framing(station, if rtu { Framing::Rtu } else { Framing::Tcp }, None)
    }

    /// Wrap a station speaking `framing` (Tcp or Rtu); RTU `timing` defaults to the profile's line, 8E1.
    pub fn with_framing(station: Station, framing: Framing, timing: Option<RtuTiming>) -> Self {
        let rtu = framing == Framing::Rtu;
        let baud = station
            .profile()
            .serial
            .as_ref()
            .map_or(19_200, |s| s.default_baud);
        let timing = timing.unwrap_or_else(|| {
            RtuTiming::new(
                baud,
                CharFormat {
                    parity: Parity::Even,
                    stop_bits: 1,
                },
            )
        });
        Self {
            station,
            framing: if rtu { Framing::Rtu } else { Framing::Tcp },
            now: Duration::ZERO,
            conn: TcpConn::default(),
            port: RtuPort::new(timing),
            timing,
            queued: VecDeque::new(),
            reader: if rtu {
                FrameReader::rtu(timing)
            } else {
                FrameReader::mbap()
            },
            closed: false,
            line_time: true,
        }
    }

    /// The oracle's mode: time moves only when told (`idle`), never by modelled transmit times, so the
    /// mirror keeps the target's clock.
    pub fn mirror(mut self) -> Self {
        self.line_time = false;
        self
    }

    /// Take `choices` from now on, keeping the state (see [`Station::adopt`]).
    pub fn adopt(&mut self, choices: drives::Choices) {
        self.station.adopt(choices);
    }

    /// The freedoms that decided the drive's answers since the last call.
    pub fn take_decisions(&mut self) -> Vec<drives::Decision> {
        self.station.take_decisions()
    }

    /// The counter values other admissible readings of the FC 08 counters would have given, since the last
    /// call (see [`Station::take_counter_alternatives`]).
    pub fn take_counter_alternatives(&mut self) -> Vec<(u16, &'static str, u16)> {
        self.station.take_counter_alternatives()
    }

    /// The station (tests inspect counters and model state).
    pub fn station(&self) -> &Station {
        &self.station
    }

    /// Everything the drive answers to what it has received, without waiting for more: the line's
    /// t3.5 silence and the answers' transmit time pass, nothing else. Returns the frames and whether the
    /// drive closed the connection. The oracle uses this so that its clock never runs ahead of the target's.
    pub fn settle(&mut self) -> (Vec<Vec<u8>>, bool) {
        let mut station_now = self.now;
        if self.framing == Framing::Rtu
            && let Some(d) = self.port.deadline()
        {
            self.now = self.now.max(d);
            station_now = self.now;
            self.poll_station();
        }
        let mut frames = Vec::new();
        let mut closed = false;
        // An RTU answer waits out the t3.5 silence after the request: that much is not waiting for more.
        let wait = if self.framing == Framing::Rtu {
            self.timing.t3_5
        } else {
            Duration::ZERO
        };
        // Bounded: a drive answers at most one frame per request, and a step sends at most a few.
        for _ in 0..64 {
            match self.recv(wait) {
                Ok(Received::Frame { bytes, .. }) => frames.push(bytes),
                Ok(Received::Closed { .. }) => {
                    closed = true;
                    break;
                }
                _ => break,
            }
        }
        // Reading the answers off the line took time only on the reader's side; the drive has seen
        // nothing after `station_now`, so the oracle's clock goes back there and never leads the target's.
        self.now = station_now;
        (frames, closed)
    }

    fn enqueue(&mut self, replies: Vec<drives::Wire>) {
        for w in replies {
            let at = self.now + w.delay;
            self.queued.push_back((at, w.bytes));
        }
    }

    /// Let the station see silence (RTU) up to `now`.
    fn poll_station(&mut self) {
        if self.framing == Framing::Rtu {
            let replies = self.station.poll_rtu(self.now, &mut self.port);
            self.enqueue(replies);
        }
    }
}

impl Target for SimTarget {
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
                    if self.line_time {
                        self.now += self.timing.char_time;
                    }
                    let replies =
                        self.station
                            .serve_rtu(self.now, &mut self.port, std::slice::from_ref(b));
                    self.enqueue(replies);
                }
            }
            _ => {
                if self.closed {
                    self.conn = TcpConn::default();
                    self.closed = false;
                }
                if self.line_time {
                    self.now += TCP_LATENCY;
                }
                let out = self.station.serve_tcp(self.now, &mut self.conn, bytes);
                self.enqueue(out.replies);
                if out.close {
                    self.closed = true;
                }
            }
        }
        Ok(())
    }

    fn recv(&mut self, timeout: Duration) -> Result<Received, TargetError> {
        let deadline = self.now + timeout;
        loop {
            if let Some(r) = self.reader.next() {
                return Ok(r);
            }
            // An RTU drive answers after t3.5 of silence following the request.
            if self.framing == Framing::Rtu && self.port.deadline().is_some_and(|d| d <= deadline) {
                self.now = self.now.max(self.port.deadline().unwrap_or(self.now));
                self.poll_station();
                continue;
            }
            match self.queued.front() {
                Some((at, _)) if *at <= deadline => {
                    let (at, bytes) = self.queued.pop_front().unwrap_or_default();
                    self.now = self.now.max(at);
                    if self.framing == Framing::Rtu && !bytes.is_empty() {
                        // On the line, the first character is in after one character time: the answer's
                        // start is what the inter-frame silence is measured to. The rest follows without a gap.
                        let c = self.timing.char_time;
                        let start = self.now;
                        // (The rest is stamped one character later, not at its end: the framer would take the
                        // span for a gap.)
                        self.reader.push(start + c, &bytes[..1]);
                        self.reader.push(start + c + c, &bytes[1..]);
                        self.now += self.timing.transmit_time(bytes.len());
                    } else {
                        self.reader.push(self.now, &bytes);
                    }
                    if self.framing == Framing::Rtu {
                        // Nothing else is on the line: the frame ends with silence.
                        self.now += self.timing.t3_5;
                        self.reader.poll(self.now);
                    }
                    continue;
                }
                _ => {}
            }
            if self.closed && self.framing != Framing::Rtu {
                self.now = self.now.max(self.now + TCP_LATENCY);
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
        self.poll_station();
        self.station.model_mut().advance(self.now);
    }

    fn reconnect(&mut self) -> Result<(), TargetError> {
        self.conn = TcpConn::default();
        self.closed = false;
        self.reader.clear();
        Ok(())
    }

    fn drain(&mut self) {
        // Replies that would have arrived by now are stale; later ones stay queued (a late drive).
        let now = self.now;
        self.queued.retain(|(at, _)| *at > now);
        self.reader.clear();
    }

    fn describe(&self) -> String {
        format!(
            "sim:{} (in-process, virtual clock)",
            self.station.profile().device.id
        )
    }

    fn rtu_timing(&self) -> Option<RtuTiming> {
        (self.framing == Framing::Rtu).then_some(self.timing)
    }

    fn answer_gap_measurable(&self) -> Result<(), String> {
        if self.framing == Framing::Rtu {
            Ok(())
        } else {
            Err("no serial line on this transport".into())
        }
    }
}
