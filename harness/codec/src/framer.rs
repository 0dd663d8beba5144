//! RTU stream framing: cut a timestamped byte stream into ADUs by the per-function-code length rules of
//! the direction, confirm each cut with the CRC, fall back on inter-frame silence (t3.5), and report every
//! byte discarded with the reason. Sans-IO: the caller supplies arrival times and polls on silence.

use std::time::Duration;

use super::pdu::Direction;
use super::rtu::{MAX_ADU_LEN, MIN_ADU_LEN, crc_ok, crc16};

/// Parity of a serial character.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Parity {
    None,
    Even,
    Odd,
}

/// Character format of an RTU line (always 8 data bits in RTU mode).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct CharFormat {
    pub parity: Parity,
    pub stop_bits: u8,
}

impl CharFormat {
    /// Bits on the wire per character: start + 8 data + parity + stop.
    pub fn bits(&self) -> u32 {
        1 + 8 + u32::from(self.parity != Parity::None) + u32::from(self.stop_bits.max(1))
    }
}

/// Inter-character (t1.5) and inter-frame (t3.5) silences of an RTU line.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RtuTiming {
    pub baud: u32,
    pub char_time: Duration,
    pub t1_5: Duration,
    pub t3_5: Duration,
}

impl RtuTiming {
    /// Timing per the serial line spec: 1.5 and 3.5 character times, fixed at 750 µs and 1.75 ms above 19200 baud.
    pub fn new(baud: u32, format: CharFormat) -> Self {
        let baud = baud.max(1);
        let char_ns = u64::from(format.bits()) * 1_000_000_000 / u64::from(baud);
        let char_time = Duration::from_nanos(char_ns);
        let (t1_5, t3_5) = if baud > 19_200 {
            (Duration::from_micros(750), Duration::from_micros(1750))
        } else {
            (
                Duration::from_nanos(char_ns * 3 / 2),
                Duration::from_nanos(char_ns * 7 / 2),
            )
        };
        Self {
            baud,
            char_time,
            t1_5,
            t3_5,
        }
    }

    /// Timing for RTU frames carried over TCP (gateways, `simulate --rtu-over-tcp`). A TCP stream has no
    /// line silence: segments of one frame may arrive milliseconds apart. Frames are cut by the length
    /// rules and the CRC; silence only ends frames of unknown length, after 50 ms.
    pub fn tcp_carrier() -> Self {
        Self {
            baud: 0,
            char_time: Duration::ZERO,
            t1_5: Duration::from_millis(20),
            t3_5: Duration::from_millis(50),
        }
    }

    /// True for a serial line; false for [`RtuTiming::tcp_carrier`], where there is no line (baud 0).
    pub fn is_line(&self) -> bool {
        self.baud != 0
    }

    /// Time to transmit `n` characters.
    pub fn transmit_time(&self, n: usize) -> Duration {
        self.char_time * n as u32
    }
}

/// How long a frame of a function code is, in one direction.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LengthRule {
    /// The whole ADU (address to CRC) has this many bytes.
    Fixed(usize),
    /// A byte count of `width` (1 or 2, big-endian) bytes at ADU offset `offset` gives the bytes that follow it
    /// before `trailer` more bytes (the CRC, usually 2).
    ByteCountAt {
        offset: usize,
        width: usize,
        trailer: usize,
    },
}

/// A length rule for a vendor function code, from a profile.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct VendorRule {
    pub function: u8,
    pub request: LengthRule,
    pub response: LengthRule,
}

/// What the rules say about the frame at the start of a buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameLen {
    /// More bytes are needed before a length is known.
    NeedMore,
    /// One of these lengths (second is 0 when there is only one); the CRC decides.
    Known(usize, usize),
    /// No rule for this function code: silence delimits the frame.
    Unknown,
}

fn apply(rule: LengthRule, buf: &[u8]) -> FrameLen {
    match rule {
        LengthRule::Fixed(n) => FrameLen::Known(n, 0),
        LengthRule::ByteCountAt {
            offset,
            width,
            trailer,
        } => {
            let Some(b) = buf.get(offset..offset + width) else {
                return FrameLen::NeedMore;
            };
            let n = b.iter().fold(0usize, |acc, x| (acc << 8) | *x as usize);
            FrameLen::Known(offset + width + n + trailer, 0)
        }
    }
}

const fn count_at(offset: usize) -> LengthRule {
    LengthRule::ByteCountAt {
        offset,
        width: 1,
        trailer: 2,
    }
}

/// Length of the ADU starting at `buf[0]` per the Modbus rules of `dir` (and `vendor` rules first).
pub fn expected_len(dir: Direction, buf: &[u8], vendor: &[VendorRule]) -> FrameLen {
    let Some(&fc) = buf.get(1) else {
        return FrameLen::NeedMore;
    };
    if let Some(v) = vendor.iter().find(|v| v.function == fc) {
        return apply(
            match dir {
                Direction::Request => v.request,
                Direction::Response => v.response,
            },
            buf,
        );
    }
    use LengthRule::Fixed;
    let rule = match dir {
        // Request layouts of MODBUS Application Protocol v1.1b3 section 6 (ADU = address + PDU + CRC).
        Direction::Request => match fc {
            // FC 08: sub-function and one data word, as every sub-function but 00 carries (6.8.1); a 00
            // with other data fails the CRC at 8 bytes and silence ends it.
            0x01..=0x06 | 0x08 | 0x41 => Fixed(8),
            // 6.7, 6.9, 6.10, 6.13: the function code alone.
            0x07 | 0x0B | 0x0C | 0x11 => Fixed(4),
            0x0F | 0x10 => count_at(6),
            // 6.14, 6.15: byte count / request data length right after the function code.
            0x14 | 0x15 => count_at(2),
            // 6.16: address, AND mask, OR mask.
            0x16 => Fixed(10),
            0x17 => count_at(10),
            // 6.18: the FIFO pointer address.
            0x18 => Fixed(6),
            0x42 => count_at(6),
            0x2B => match (buf.get(2), buf.get(3)) {
                (None, _) => return FrameLen::NeedMore,
                (Some(0x0E), _) => Fixed(7),
                (Some(0x0D), None) => return FrameLen::NeedMore,
                (Some(0x0D), Some(ctrl)) if ctrl & 0x80 == 0 => Fixed(15),
                (Some(0x0D), Some(_)) => LengthRule::ByteCountAt {
                    offset: 11,
                    width: 2,
                    trailer: 2,
                },
                _ => return FrameLen::Unknown,
            },
            _ => return FrameLen::Unknown,
        },
        Direction::Response => match fc {
            0xAB => match buf.get(2) {
                None => return FrameLen::NeedMore,
                Some(0xFF) => LengthRule::ByteCountAt {
                    offset: 3,
                    width: 2,
                    trailer: 2,
                },
                Some(_) => Fixed(5),
            },
            f if f & 0x80 != 0 => Fixed(5),
            // A 1-byte count after the function code: 6.10 (FC 0C), 6.13 (FC 11), 6.14 (FC 14), 6.15 (FC 15's
            // echo of the request data length).
            0x01..=0x04 | 0x0C | 0x11 | 0x14 | 0x15 | 0x17 | 0x41 => count_at(2),
            // FC 0B (6.9): status and event count.
            0x05 | 0x06 | 0x08 | 0x0B | 0x0F | 0x10 => Fixed(8),
            // FC 07 (6.7): one output data byte.
            0x07 => Fixed(5),
            // FC 16 (6.16): the echo of the request.
            0x16 => Fixed(10),
            // FC 18 (6.18): a 2-byte byte count.
            0x18 => LengthRule::ByteCountAt {
                offset: 2,
                width: 2,
                trailer: 2,
            },
            0x42 => Fixed(9),
            0x2B => match (buf.get(2), buf.get(3)) {
                (None, _) => return FrameLen::NeedMore,
                (Some(0x0E), _) => return device_id_len(buf),
                (Some(0x0D), None) => return FrameLen::NeedMore,
                (Some(0x0D), Some(ctrl)) => {
                    let Some(b) = buf.get(11..13) else {
                        return FrameLen::NeedMore;
                    };
                    let n = u16::from_be_bytes([b[0], b[1]]) as usize;
                    // A write response may echo the data or carry none: the CRC picks.
                    return if ctrl & 0x80 == 0 {
                        FrameLen::Known(15 + n, 0)
                    } else {
                        FrameLen::Known(15 + n, 15)
                    };
                }
                _ => return FrameLen::Unknown,
            },
            _ => return FrameLen::Unknown,
        },
    };
    apply(rule, buf)
}

/// FC 2B/0E response: walk the object list (address, fc, mei, code, conformity, more, next, n, objects..., CRC).
fn device_id_len(buf: &[u8]) -> FrameLen {
    let Some(&n) = buf.get(7) else {
        return FrameLen::NeedMore;
    };
    let mut at = 8usize;
    for _ in 0..n {
        let Some(&len) = buf.get(at + 1) else {
            return FrameLen::NeedMore;
        };
        at += 2 + len as usize;
        if at > MAX_ADU_LEN {
            return FrameLen::Known(at + 2, 0);
        }
    }
    FrameLen::Known(at + 2, 0)
}

/// Why the framer dropped bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DiscardReason {
    /// Silence ended a frame whose CRC does not match (expected over all but the last two bytes).
    BadCrc { expected: u16, received: u16 },
    /// Silence ended a frame shorter than address + function + CRC.
    TooShort,
    /// More than 256 bytes arrived without a silence or a valid cut.
    Overlong,
}

impl std::fmt::Display for DiscardReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DiscardReason::BadCrc { expected, received } => write!(
                f,
                "CRC mismatch: expected 0x{expected:04X}, received 0x{received:04X}"
            ),
            DiscardReason::TooShort => write!(f, "fewer than 4 bytes before a silence"),
            DiscardReason::Overlong => write!(f, "over 256 bytes without a frame boundary"),
        }
    }
}

/// What the framer produced.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum FramerEvent {
    /// A frame with a valid CRC. `max_gap` is the largest silence between its bytes (over t1.5 breaks the
    /// serial line spec, which the caller may report).
    Frame {
        bytes: Vec<u8>,
        start: Duration,
        end: Duration,
        max_gap: Duration,
    },
    /// Bytes dropped, and why.
    Discarded {
        bytes: Vec<u8>,
        at: Duration,
        reason: DiscardReason,
    },
}

/// Cuts a timestamped RTU byte stream into frames. Memory is bounded by the 256-byte ADU limit.
#[derive(Clone, Debug)]
pub struct RtuFramer {
    direction: Direction,
    timing: RtuTiming,
    vendor: Vec<VendorRule>,
    buf: Vec<u8>,
    start: Duration,
    last: Duration,
    max_gap: Duration,
    /// What the rules say about `buf`, once they say more than [`FrameLen::NeedMore`]: every rule reads fixed
    /// positions, so a known length (or its absence) stays what it is as bytes are added. `NeedMore` until
    /// then, and again whenever bytes leave `buf`.
    rule: FrameLen,
    /// The length `buf` must reach before `cut` could emit or drop anything (see [`next_cut`]): bytes that
    /// keep it shorter are appended without looking.
    next_cut: usize,
    /// The silence that ends a frame the rules say is not complete yet (at least t3.5; see
    /// [`RtuFramer::with_incomplete_wait`]).
    incomplete_wait: Duration,
    /// A slave's own address ([`RtuFramer::listen_as`]): a request it sees for another slave is followed on
    /// the line by that slave's reply, which it hears too.
    own: Option<u8>,
    /// The slave whose reply may come next: the address of the last request seen for another slave.
    reply_from: Option<u8>,
}

/// The length after `len` at which a cut could next happen, given what the rules say about the buffer at
/// `len`. While the rules need more bytes to know the length, that is the next byte, or the 4th (no frame is
/// shorter); once they know it (or know there is no rule), the next candidate length (4..=256) or over 256
/// bytes (the overlong drop). `cut` has already run at `len`, so candidates up to it failed their CRC and
/// would fail it again on the same bytes.
fn next_cut(rule: FrameLen, len: usize) -> usize {
    const OVERLONG: usize = MAX_ADU_LEN + 1;
    match rule {
        FrameLen::NeedMore => MIN_ADU_LEN.max(len + 1),
        FrameLen::Unknown => OVERLONG,
        FrameLen::Known(a, b) => {
            let candidate = |n: usize| n > len && (MIN_ADU_LEN..=MAX_ADU_LEN).contains(&n);
            match (candidate(a), candidate(b)) {
                (true, true) => a.min(b),
                (true, false) => a,
                (false, true) => b,
                (false, false) => OVERLONG,
            }
        }
    }
}

impl RtuFramer {
    /// A framer for frames travelling in `direction` on a line with `timing`.
    pub fn new(direction: Direction, timing: RtuTiming, vendor: Vec<VendorRule>) -> Self {
        Self {
            direction,
            timing,
            vendor,
            buf: Vec::with_capacity(MAX_ADU_LEN),
            start: Duration::ZERO,
            last: Duration::ZERO,
            max_gap: Duration::ZERO,
            rule: FrameLen::NeedMore,
            next_cut: next_cut(FrameLen::NeedMore, 0),
            incomplete_wait: timing.t3_5,
            own: None,
            reply_from: None,
        }
    }

    /// Frame requests as the slave at `own` hears them on a multi-drop line (serial line spec 2.1: up to 247
    /// slaves on one bus): after a request for another slave comes that slave's reply, which the request
    /// layouts do not size (an FC 03 reply is shorter than an FC 03 request), so that the reply and the
    /// master's next request, when it follows within the carrier's wait, would be cut as one run of bytes and
    /// discarded. A frame from the slave just addressed is sized by the response layouts as well as the
    /// request layouts, and the CRC picks (a slave that takes the next frame after a request for another
    /// slave as its reply, as libmodbus's does).
    pub fn listen_as(&mut self, own: u8) {
        self.own = Some(own);
    }

    /// Wait `wait` (if longer than t3.5) before silence ends a frame that the length rules say has more bytes
    /// to come. For a master reading answers through a host's serial port: a USB adapter hands over the
    /// bytes it received when its latency timer runs out (16 ms by default on FTDI chips), so the host sees
    /// pauses inside a frame the line carried whole. A frame the rules size is cut as soon as it is complete,
    /// and one no rule sizes still ends at t3.5.
    pub fn with_incomplete_wait(mut self, wait: Duration) -> Self {
        self.incomplete_wait = wait.max(self.timing.t3_5);
        self
    }

    /// The silence that ends the bytes held: [`RtuFramer::with_incomplete_wait`]'s wait while the rules say
    /// more are to come (they need more to tell the length, or a length they give is not reached), else t3.5.
    fn silence(&self) -> Duration {
        let len = self.buf.len();
        let incomplete = match self.rule {
            FrameLen::NeedMore => true,
            FrameLen::Known(a, b) => a.max(b) > len,
            FrameLen::Unknown => false,
        };
        if incomplete {
            self.incomplete_wait
        } else {
            self.timing.t3_5
        }
    }

    /// The line timing this framer cuts on.
    pub fn timing(&self) -> RtuTiming {
        self.timing
    }

    /// Bytes held waiting for more data or for silence.
    pub fn pending(&self) -> &[u8] {
        &self.buf
    }

    /// When `poll` should next be called (the end of the t3.5 silence after the last byte), if bytes are held.
    /// Saturates at `Duration::MAX` for a clock that far on (a caller's time base is its own).
    pub fn deadline(&self) -> Option<Duration> {
        (!self.buf.is_empty()).then(|| self.last.saturating_add(self.silence()))
    }

    /// Feed bytes that arrived at `now` (one timestamp per chunk).
    ///
    /// The outcome is that of taking the bytes one at a time and looking for a cut after each. The bytes after
    /// which no cut can happen (see [`next_cut`]) go in together instead; later bytes of a chunk add no gap,
    /// since they share its timestamp.
    pub fn push(&mut self, now: Duration, bytes: &[u8]) -> Vec<FramerEvent> {
        let mut events = Vec::new();
        self.push_into(now, bytes, &mut events);
        events
    }

    /// [`push`](Self::push), appending the events to `events` (which the caller may reuse).
    pub fn push_into(&mut self, now: Duration, bytes: &[u8], events: &mut Vec<FramerEvent>) {
        if !self.buf.is_empty() {
            // One gap for the chunk: it ends the held bytes by silence, or it is the gap before their next byte.
            let gap = now.saturating_sub(self.last);
            if gap >= self.silence() {
                self.end_by_silence(events);
            } else if !bytes.is_empty() {
                self.max_gap = self.max_gap.max(gap);
            }
        }
        if bytes.is_empty() {
            return;
        }
        self.last = now;
        let mut rest = bytes;
        loop {
            if self.buf.is_empty() {
                self.start = now;
                self.max_gap = Duration::ZERO;
            }
            let room = self.next_cut - self.buf.len();
            if rest.len() < room {
                self.buf.extend_from_slice(rest);
                return;
            }
            let (taken, left) = rest.split_at(room);
            self.buf.extend_from_slice(taken);
            self.cut(events);
            if left.is_empty() {
                return;
            }
            rest = left;
        }
    }

    /// Report what silence has delimited by `now`.
    pub fn poll(&mut self, now: Duration) -> Vec<FramerEvent> {
        let mut events = Vec::new();
        self.poll_into(now, &mut events);
        events
    }

    /// [`poll`](Self::poll), appending the events to `events`.
    pub fn poll_into(&mut self, now: Duration, events: &mut Vec<FramerEvent>) {
        if !self.buf.is_empty() && now.saturating_sub(self.last) >= self.silence() {
            self.end_by_silence(events);
        }
    }

    /// End of stream: whatever is held is judged as if silence followed.
    pub fn finish(&mut self) -> Vec<FramerEvent> {
        let mut events = Vec::new();
        self.finish_into(&mut events);
        events
    }

    /// [`finish`](Self::finish), appending the events to `events`.
    pub fn finish_into(&mut self, events: &mut Vec<FramerEvent>) {
        self.end_by_silence(events);
    }

    /// What the rules say about `buf`, from the cache once they have said it.
    fn rule(&mut self) -> FrameLen {
        if self.rule == FrameLen::NeedMore {
            self.rule = expected_len(self.direction, &self.buf, &self.vendor);
            if self.reply_from.is_some() && self.reply_from == self.buf.first().copied() {
                self.rule = match (
                    expected_len(Direction::Response, &self.buf, &self.vendor),
                    self.rule,
                ) {
                    (FrameLen::NeedMore, _) => FrameLen::NeedMore,
                    (FrameLen::Known(a, 0), FrameLen::Known(b, 0)) if a != b => {
                        FrameLen::Known(a, b)
                    }
                    (FrameLen::Known(a, b), FrameLen::Unknown) => FrameLen::Known(a, b),
                    (_, request) => request,
                };
            }
        }
        self.rule
    }

    /// `buf` lost bytes from its front: what the rules said no longer holds, and the next cut is computed
    /// again from what is left (no cut happens at the present length: cuts follow an arriving byte).
    fn drained(&mut self) {
        self.rule = FrameLen::NeedMore;
        self.next_cut = if self.buf.is_empty() {
            next_cut(FrameLen::NeedMore, 0)
        } else {
            let rule = self.rule();
            next_cut(rule, self.buf.len())
        };
    }

    /// All of `buf`, which is left empty (with its capacity).
    fn take_all(&mut self) -> Vec<u8> {
        let bytes = self.buf.to_vec();
        self.buf.clear();
        self.drained();
        bytes
    }

    fn emit(&mut self, n: usize, events: &mut Vec<FramerEvent>) {
        let bytes = self.buf[..n].to_vec();
        // A request for another slave (not a broadcast, not the reply just awaited): its reply may come next.
        let first = bytes[0];
        self.reply_from = match self.own {
            Some(own) if first != own && first != 0 && self.reply_from != Some(first) => {
                Some(first)
            }
            _ => None,
        };
        if n == self.buf.len() {
            self.buf.clear();
        } else {
            self.buf.drain(..n);
        }
        self.drained();
        events.push(FramerEvent::Frame {
            bytes,
            start: self.start,
            end: self.last,
            max_gap: self.max_gap,
        });
        self.start = self.last;
        self.max_gap = Duration::ZERO;
    }

    /// Look for a cut after the byte that brought `buf` to `next_cut`.
    fn cut(&mut self, events: &mut Vec<FramerEvent>) {
        let rule = self.rule();
        let len = self.buf.len();
        if let FrameLen::Known(a, b) = rule {
            for n in [a, b] {
                if n >= MIN_ADU_LEN && n <= len && n <= MAX_ADU_LEN && crc_ok(&self.buf[..n]) {
                    self.emit(n, events);
                    return;
                }
            }
        }
        if len > MAX_ADU_LEN {
            let at = self.last;
            events.push(FramerEvent::Discarded {
                bytes: self.take_all(),
                at,
                reason: DiscardReason::Overlong,
            });
        } else {
            self.next_cut = next_cut(rule, len);
        }
    }

    fn end_by_silence(&mut self, events: &mut Vec<FramerEvent>) {
        if self.buf.is_empty() {
            return;
        }
        if self.buf.len() < MIN_ADU_LEN {
            let at = self.last;
            events.push(FramerEvent::Discarded {
                bytes: self.take_all(),
                at,
                reason: DiscardReason::TooShort,
            });
        } else {
            // The CRC once, for the check and for the report (crc_ok would compute the same).
            let (body, c) = self.buf.split_at(self.buf.len() - 2);
            let (expected, received) = (crc16(body), u16::from_le_bytes([c[0], c[1]]));
            if expected == received {
                let n = self.buf.len();
                self.emit(n, events);
            } else {
                let at = self.last;
                events.push(FramerEvent::Discarded {
                    bytes: self.take_all(),
                    at,
                    reason: DiscardReason::BadCrc { expected, received },
                });
            }
        }
    }
}
