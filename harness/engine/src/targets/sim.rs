//! The in-process reference drive: no sockets, a virtual clock. Replies go through the same frame
//! readers as on real transports, so verdicts do not depend on where the drive runs.

use std::time::Duration;

use super::line::{DriveEnd, TCP_LATENCY, VirtualLine};
use super::{Received, Target, TargetError};
use codec::{CharFormat, Framing, Parity, RtuTiming};
use drives::profile::{Profile, Transport};
use drives::{Choices, FaultSet, RtuPort, Station, TcpConn};

/// A reference drive in process. A clone is an independent copy in the same state (the runner keeps one to
/// undo a request the drive was free to ignore).
#[derive(Clone)]
pub struct SimTarget {
    end: SimEnd,
    conn: TcpConn,
    line: VirtualLine,
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
            end: SimEnd {
                station,
                port: RtuPort::new(timing),
            },
            conn: TcpConn::default(),
            line: VirtualLine::new(if rtu { Framing::Rtu } else { Framing::Tcp }, timing),
            line_time: true,
        }
    }

    /// The reference drive a runner judges `target` by: the profile's healthy model taking `choices`, on
    /// `unit`, answering in the target's framing and RTU timing, in the oracle's mode ([`SimTarget::mirror`]).
    pub fn reference(profile: &Profile, unit: u8, choices: Choices, target: &dyn Target) -> Self {
        let station = Station::new(
            drives::build_with(profile.clone(), FaultSet::none(), choices.clone()),
            FaultSet::none(),
            unit,
        )
        .with_choices(choices);
        Self::with_framing(station, target.framing(), target.rtu_timing()).mirror()
    }

    /// The oracle's mode: time moves only when told (`idle`), never by modelled transmit times, so the
    /// mirror keeps the target's clock.
    pub fn mirror(mut self) -> Self {
        self.line_time = false;
        self
    }

    /// Take `choices` from now on, keeping the state (see [`Station::adopt`]).
    pub fn adopt(&mut self, choices: drives::Choices) {
        self.end.station.adopt(choices);
    }

    /// The freedoms that decided the drive's answers since the last call.
    pub fn take_decisions(&mut self) -> Vec<drives::Decision> {
        self.end.station.take_decisions()
    }

    /// The counter values other admissible readings of the FC 08 counters would have given, since the last
    /// call (see [`Station::take_counter_alternatives`]).
    pub fn take_counter_alternatives(&mut self) -> Vec<(u16, &'static str, u16)> {
        self.end.station.take_counter_alternatives()
    }

    /// See [`Station::take_choice_alternatives`].
    pub fn take_choice_alternatives(&mut self) -> Vec<drives::choices::ModelledAlternative> {
        self.end.station.take_choice_alternatives()
    }

    /// The station (tests inspect counters and model state).
    pub fn station(&self) -> &Station {
        &self.end.station
    }

    /// Everything the drive answers to what it has received, without waiting for more: the line's
    /// t3.5 silence and the answers' transmit time pass, nothing else. Returns the frames and whether the
    /// drive closed the connection. The oracle uses this so that its clock never runs ahead of the target's.
    pub fn settle(&mut self) -> (Vec<Vec<u8>>, bool) {
        let mut station_now = self.line.now;
        if let Some(d) = self.end.deadline().filter(|_| self.line.is_rtu()) {
            self.line.now = self.line.now.max(d);
            station_now = self.line.now;
            self.line.poll(&mut self.end);
        }
        let mut frames = Vec::new();
        let mut closed = false;
        // An RTU answer waits out the t3.5 silence after the request: that much is not waiting for more.
        let wait = if self.line.is_rtu() {
            self.line.timing.t3_5
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
        self.line.now = station_now;
        (frames, closed)
    }
}

/// The reference drive's end of the line: the station and its RTU receiver.
#[derive(Clone)]
struct SimEnd {
    station: Station,
    port: RtuPort,
}

impl DriveEnd for SimEnd {
    fn deadline(&self) -> Option<Duration> {
        self.port.deadline()
    }

    fn poll(&mut self, line: &mut VirtualLine) {
        let replies = self.station.poll_rtu(line.now, &mut self.port);
        enqueue(line, replies);
    }
}

/// The drive's replies go on the line, each after its delay.
fn enqueue(line: &mut VirtualLine, replies: Vec<drives::Wire>) {
    for w in replies {
        line.queue(line.now + w.delay, w.bytes);
    }
}

impl Target for SimTarget {
    fn framing(&self) -> Framing {
        self.line.framing
    }

    fn now(&self) -> Duration {
        self.line.now
    }

    fn send(&mut self, bytes: &[u8]) -> Result<(), TargetError> {
        let line = &mut self.line;
        if line.is_rtu() {
            // Bytes arrive one character time apart, as on a line: a chunk is not a silence.
            for b in bytes {
                if self.line_time {
                    line.now += line.timing.char_time;
                }
                let end = &mut self.end;
                let replies =
                    end.station
                        .serve_rtu(line.now, &mut end.port, std::slice::from_ref(b));
                enqueue(line, replies);
            }
        } else {
            if line.closed {
                self.conn = TcpConn::default();
                line.closed = false;
            }
            if self.line_time {
                line.now += TCP_LATENCY;
            }
            let out = self.end.station.serve_tcp(line.now, &mut self.conn, bytes);
            enqueue(line, out.replies);
            if out.close {
                line.closed = true;
            }
        }
        Ok(())
    }

    fn recv(&mut self, timeout: Duration) -> Result<Received, TargetError> {
        self.line.recv(&mut self.end, timeout)
    }

    fn idle(&mut self, d: Duration) {
        self.line.now += d;
        self.line.poll(&mut self.end);
        self.end.station.model_mut().advance(self.line.now);
    }

    fn reconnect(&mut self) -> Result<(), TargetError> {
        self.conn = TcpConn::default();
        self.line.reconnect();
        Ok(())
    }

    fn drain(&mut self) {
        self.line.drain();
    }

    fn describe(&self) -> String {
        format!(
            "sim:{} (in-process, virtual clock)",
            self.end.station.profile().device.id
        )
    }

    fn rtu_timing(&self) -> Option<RtuTiming> {
        self.line.rtu_timing()
    }

    fn answer_gap_measurable(&self) -> Result<(), String> {
        if self.line.is_rtu() {
            Ok(())
        } else {
            Err("no serial line on this transport".into())
        }
    }
}
