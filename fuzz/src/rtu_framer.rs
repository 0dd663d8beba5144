//! `rtu_framer`: a timed RTU byte stream through a request framer and a response framer.

use std::time::Duration;

use codec::framer::{FramerEvent, LengthRule, RtuFramer, RtuTiming, VendorRule};
use codec::{CharFormat, Direction, Parity, hex_spaced, rtu};

use crate::input::Input;

const BAUDS: [u32; 4] = [9_600, 19_200, 38_400, 115_200];
/// `rtu_framer` config byte: 19200 baud, even parity, one stop bit, no vendor rule.
pub(crate) const RTU_19200_8E1: u8 = 0x05;
/// `rtu_framer` step control: push after a silence of t3.5 (16/16), so the chunk starts a new frame.
pub(crate) const RTU_AFTER_SILENCE: u8 = 16;

/// t3.5 of `timing` in nanoseconds.
fn t3_5_nanos(timing: RtuTiming) -> u64 {
    u64::try_from(timing.t3_5.as_nanos()).expect("t3.5 fits in u64 nanoseconds")
}

fn length_rule(b: u8) -> LengthRule {
    if b & 0x80 != 0 {
        LengthRule::Fixed(usize::from(b & 0x7F))
    } else {
        LengthRule::ByteCountAt {
            offset: usize::from(b & 0x0F),
            width: 1 + usize::from(b >> 4 & 1),
            trailer: usize::from(b >> 5 & 3),
        }
    }
}

/// One framer and the byte accounting its invariants check.
struct CountedFramer {
    framer: RtuFramer,
    direction: Direction,
    fed: usize,
    framed: usize,
    discarded: usize,
    /// The events of the last call, checked and emptied by `account` (one buffer for every call).
    events: Vec<FramerEvent>,
}

impl CountedFramer {
    fn push(&mut self, now: Duration, bytes: &[u8]) {
        self.fed += bytes.len();
        self.framer.push_into(now, bytes, &mut self.events);
        self.account();
    }

    fn poll(&mut self, now: Duration) {
        self.framer.poll_into(now, &mut self.events);
        self.account();
    }

    fn finish(&mut self) {
        self.framer.finish_into(&mut self.events);
        self.account();
        assert!(
            self.framer.pending().is_empty(),
            "bytes held after the end of the stream"
        );
    }

    fn account(&mut self) {
        if !self.events.is_empty() {
            self.check_events();
        }
        let pending = self.framer.pending().len();
        assert!(
            pending <= rtu::MAX_ADU_LEN,
            "{pending} bytes pending, over the 256-byte ADU limit"
        );
        assert_eq!(
            self.fed,
            self.framed + self.discarded + pending,
            "bytes in != framed + discarded + pending"
        );
    }

    /// Check every event of the last call and count its bytes; leaves `events` empty.
    fn check_events(&mut self) {
        let Self {
            direction,
            framed,
            discarded,
            events,
            ..
        } = self;
        for event in events.drain(..) {
            match event {
                FramerEvent::Frame {
                    bytes,
                    start,
                    end,
                    max_gap,
                } => {
                    assert!(
                        (rtu::MIN_ADU_LEN..=rtu::MAX_ADU_LEN).contains(&bytes.len()),
                        "a frame of {} bytes: {}",
                        bytes.len(),
                        hex_spaced(&bytes)
                    );
                    assert!(
                        rtu::crc_ok(&bytes),
                        "a frame with a bad CRC: {}",
                        hex_spaced(&bytes)
                    );
                    assert!(
                        start <= end && max_gap <= end - start,
                        "frame times out of order: start {start:?}, end {end:?}, max gap {max_gap:?}"
                    );
                    if let Ok((address, pdu)) = rtu::decode(&bytes, *direction) {
                        let again = rtu::encode(address, &pdu)
                            .unwrap_or_else(|e| panic!("decoded {pdu:?} does not encode: {e}"));
                        assert_eq!(again, bytes, "{pdu:?} re-encodes differently");
                    }
                    *framed += bytes.len();
                }
                FramerEvent::Discarded { bytes, .. } => *discarded += bytes.len(),
            }
        }
    }
}

/// The line of a config byte: bits 0-1 the baud rate, bits 2-3 the parity, bit 4 two stop bits.
fn line_timing(config: u8) -> RtuTiming {
    let format = CharFormat {
        parity: match config >> 2 & 3 {
            1 => Parity::Even,
            2 => Parity::Odd,
            _ => Parity::None,
        },
        stop_bits: 1 + (config >> 4 & 1),
    };
    RtuTiming::new(BAUDS[usize::from(config & 3)], format)
}

/// `rtu_framer`: a timed RTU byte stream fed to a request framer and a response framer. Input: a config byte
/// (bits 0-1 baud 9600/19200/38400/115200, bits 2-3 parity none/even/odd/none, bit 4 two stop bits, bit 5 a
/// vendor length rule follows as three bytes: function, request rule, response rule), then steps of
/// `[control, length, bytes...]`: control bits 0-5 are the silence before the chunk in sixteenths of t3.5,
/// bit 6 polls at that time before pushing, bit 7 ends the stream after the chunk. Invariants: at most 256
/// bytes pending, every frame is 4..=256 bytes with a valid CRC (and re-encodes if it decodes), bytes in =
/// framed + discarded + pending, nothing pending after the end.
pub fn rtu_framer(data: &[u8]) {
    let mut input = Input(data);
    let config = input.u8();
    let timing = line_timing(config);
    let vendor = if config & 0x20 != 0 {
        vec![VendorRule {
            function: input.u8(),
            request: length_rule(input.u8()),
            response: length_rule(input.u8()),
        }]
    } else {
        Vec::new()
    };
    let mut framers = [Direction::Request, Direction::Response].map(|direction| CountedFramer {
        framer: RtuFramer::new(direction, timing, vendor.clone()),
        direction,
        fed: 0,
        framed: 0,
        discarded: 0,
        events: Vec::new(),
    });
    // Time in nanoseconds: `timing.t3_5 * k / 16` exactly, as t3.5 is under a second at these speeds (see the
    // test below), with no `Duration` arithmetic per step.
    let t3_5 = t3_5_nanos(timing);
    let mut now_ns = 0u64;
    while !input.is_empty() {
        let control = input.u8();
        let chunk = input.counted();
        now_ns += t3_5 * u64::from(control & 0x3F) / 16;
        let now = Duration::from_nanos(now_ns);
        for f in &mut framers {
            if control & 0x40 != 0 {
                f.poll(now);
            }
            f.push(now, chunk);
            if control & 0x80 != 0 {
                f.finish();
            }
        }
    }
    for f in &mut framers {
        f.finish();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The silence before a step, computed in nanoseconds, is the `Duration` arithmetic it replaced, for every
    /// line format and silence an input can choose; and so is the time after many steps.
    #[test]
    fn step_time_in_nanoseconds_is_duration_arithmetic() {
        for config in 0..=0x1Fu8 {
            let timing = line_timing(config);
            let t3_5 = t3_5_nanos(timing);
            let (mut now, mut now_ns) = (Duration::ZERO, 0u64);
            for step in 0..10_000u32 {
                let k = step % 64;
                now += timing.t3_5 * k / 16;
                now_ns += t3_5 * u64::from(k) / 16;
                assert_eq!(
                    Duration::from_nanos(now_ns),
                    now,
                    "config {config:#04x}, step {step}"
                );
            }
        }
    }
}
