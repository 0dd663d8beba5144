//! The in-process reference drive: no sockets, a virtual clock. Replies go through the same frame
//! readers as on real transports, so verdicts do not depend on where the drive runs.

use std::collections::VecDeque;
use std::time::Duration;

use super::reader::FrameReader;
use super::{Received, Target, TargetError};
use crate::frame::{CharFormat, Framing, Parity, RtuTiming};
use crate::profile::Transport;
use crate::sim::{RtuPort, Station, TcpConn};

/// Virtual line time per exchange on TCP (a loopback round trip, so timestamps move).
const TCP_LATENCY: Duration = Duration::from_micros(30);

/// A reference drive in process.
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
        }
    }

    /// The station (tests inspect counters and model state).
    pub fn station(&self) -> &Station {
        &self.station
    }

    fn enqueue(&mut self, replies: Vec<crate::sim::Wire>) {
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
                // The bytes take their transmit time; the last one arrives at the end.
                self.now += self.timing.transmit_time(bytes.len());
                let replies = self.station.serve_rtu(self.now, &mut self.port, bytes);
                self.enqueue(replies);
            }
            _ => {
                if self.closed {
                    self.conn = TcpConn::default();
                    self.closed = false;
                }
                self.now += TCP_LATENCY;
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
                _ => {}
            }
            if self.closed && self.framing != Framing::Rtu {
                self.now = self.now.max(self.now + TCP_LATENCY);
                return Ok(Received::Closed {
                    partial: self.reader.partial(),
                    at: self.now,
                });
            }
            self.now = deadline;
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
}
