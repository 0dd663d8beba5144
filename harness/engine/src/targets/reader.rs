//! Cutting received bytes into frames, shared by every target: MBAP length for Modbus/TCP, the RTU
//! framer (length rules + CRC, silence as the fallback) for RTU on any carrier.

use std::collections::VecDeque;
use std::time::Duration;

use super::Received;
use codec::framer::{FramerEvent, RtuFramer};
use codec::{Direction, RtuTiming, tcp};

/// A receive-side frame cutter.
#[derive(Clone, Debug)]
pub enum FrameReader {
    /// Modbus/TCP: the MBAP length field delimits.
    Mbap {
        buf: Vec<u8>,
        first_at: Duration,
        last_at: Duration,
    },
    /// RTU: the framer delimits.
    Rtu {
        framer: RtuFramer,
        ready: VecDeque<Received>,
    },
}

impl FrameReader {
    /// A Modbus/TCP reader.
    pub fn mbap() -> Self {
        FrameReader::Mbap {
            buf: Vec::new(),
            first_at: Duration::ZERO,
            last_at: Duration::ZERO,
        }
    }

    /// An RTU reader for responses on a line with `timing`.
    pub fn rtu(timing: RtuTiming) -> Self {
        FrameReader::Rtu {
            framer: RtuFramer::new(Direction::Response, timing, Vec::new()),
            ready: VecDeque::new(),
        }
    }

    /// An RTU reader for answers read through a host's serial port on a line with `timing`: a frame the
    /// length rules say is not complete waits `wait` for its next byte (see
    /// [`RtuFramer::with_incomplete_wait`]).
    pub fn rtu_through_host(timing: RtuTiming, wait: Duration) -> Self {
        FrameReader::Rtu {
            framer: RtuFramer::new(Direction::Response, timing, Vec::new())
                .with_incomplete_wait(wait),
            ready: VecDeque::new(),
        }
    }

    fn take_events(ready: &mut VecDeque<Received>, evs: Vec<FramerEvent>) {
        for ev in evs {
            ready.push_back(match ev {
                FramerEvent::Frame {
                    bytes,
                    start,
                    end,
                    max_gap,
                } => Received::Frame {
                    bytes,
                    first_at: start,
                    last_at: end,
                    max_gap,
                },
                FramerEvent::Discarded { bytes, at, reason } => Received::Garbage {
                    bytes,
                    at,
                    reason: reason.to_string(),
                },
            });
        }
    }

    /// Bytes arrived at `now`.
    pub fn push(&mut self, now: Duration, bytes: &[u8]) {
        match self {
            FrameReader::Mbap {
                buf,
                first_at,
                last_at,
            } => {
                if buf.is_empty() {
                    *first_at = now;
                }
                *last_at = now;
                buf.extend_from_slice(bytes);
            }
            FrameReader::Rtu { framer, ready } => {
                let evs = framer.push(now, bytes);
                Self::take_events(ready, evs);
            }
        }
    }

    /// Let silence up to `now` delimit RTU frames.
    pub fn poll(&mut self, now: Duration) {
        if let FrameReader::Rtu { framer, ready } = self {
            let evs = framer.poll(now);
            Self::take_events(ready, evs);
        }
    }

    /// The next complete frame or garbage, if any.
    pub fn next(&mut self) -> Option<Received> {
        match self {
            FrameReader::Mbap {
                buf,
                first_at,
                last_at,
            } => {
                let len = tcp::adu_len(buf)?;
                let declared = len - 6;
                if !(2..=254).contains(&declared) {
                    // No way to find the next frame boundary: everything buffered is garbage.
                    return Some(Received::Garbage {
                        bytes: std::mem::take(buf),
                        at: *last_at,
                        reason: format!(
                            "MBAP length field {declared} is outside 2..=254; the stream cannot be resynchronised"
                        ),
                    });
                }
                if buf.len() < len {
                    return None;
                }
                let bytes: Vec<u8> = buf.drain(..len).collect();
                let r = Received::Frame {
                    bytes,
                    first_at: *first_at,
                    last_at: *last_at,
                    max_gap: Duration::ZERO,
                };
                *first_at = *last_at;
                Some(r)
            }
            FrameReader::Rtu { ready, .. } => ready.pop_front(),
        }
    }

    /// When silence would complete what the RTU framer holds.
    pub fn deadline(&self) -> Option<Duration> {
        match self {
            FrameReader::Mbap { .. } => None,
            FrameReader::Rtu { framer, .. } => framer.deadline(),
        }
    }

    /// Bytes of an incomplete frame.
    pub fn partial(&self) -> Vec<u8> {
        match self {
            FrameReader::Mbap { buf, .. } => buf.clone(),
            FrameReader::Rtu { framer, .. } => framer.pending().to_vec(),
        }
    }

    /// Forget everything buffered.
    pub fn clear(&mut self) {
        match self {
            FrameReader::Mbap { buf, .. } => buf.clear(),
            FrameReader::Rtu { framer, ready } => {
                framer.finish();
                ready.clear();
            }
        }
    }
}
