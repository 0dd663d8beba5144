//! The wire side of a simulated drive, sans-IO: bytes in, bytes out with a delay.
//!
//! The station applies what the Modbus specs require of any server before the model sees a request
//! (MBAP checks, unit/slave addressing, broadcast, supported function codes, quantity limits, FC 05 values),
//! keeps the communication state the serial line functions report (the FC 08 diagnostic counters and
//! sub-functions, the FC 0B event counter, the FC 0C event log, listen only mode) and applies the wire-level
//! faults to what goes out.
//!
//! Where the specs leave the wire side a choice (a freedom of `corpus/freedoms/`), the station takes the
//! drive's [`Choices`] and records the freedom as a [`Decision`]: the Modbus/TCP unit ids it ignores, the
//! order and Server Busy of pipelined answers, MBAP lengths that disagree with the PDU, PDUs over 253 bytes
//! (see [`Station::serve_tcp`]), the answer to a truncated PDU and the exception check order.
//!
//! On Modbus/TCP, FC 08 answers every sub-function the profile lists except those that act on a serial port
//! itself (01 restart, 03 ASCII delimiter, 04 listen only, 12 character overruns, 14 clear overrun: exception
//! 01, see [`DiagCounter::serial_line_only`]); the bus counters (0B, 0C, 0E, 0F) only count RTU traffic, the
//! exception, NAK and busy counts, the event counter and the event log count every transport's.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::Duration;

use crate::choices::{Choices, Decision, Rejection, ids};
use crate::faults::{Fault, FaultSet};
use crate::models::DriveModel;
use crate::profile::{DiagCounter, Profile};
use crate::requirements::{FreedomKind, FreedomValue, quantity_asked};
use crate::tell::{self, WriteRecord, WriteSink, Written};
use codec::codes::{diag, event};
use codec::framer::{DiscardReason, FramerEvent, RtuFramer, RtuTiming};
use codec::{DecodeErrorKind, Direction, ExceptionCode, FunctionCode, Request, Response, rtu, tcp};

/// Bytes to send, `delay` after the request was complete.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Wire {
    pub bytes: Vec<u8>,
    pub delay: Duration,
}

/// How late the `late-response` fault answers.
pub const LATE_RESPONSE_DELAY: Duration = Duration::from_millis(1500);

/// The serial-line diagnostic counters of FC 08 (MODBUS Application Protocol v1.1b3 section 6.8.1; Modbus over
/// Serial Line v1.02 section 6.1). Cleared by 08/0A and 08/01; a listening-only drive counts only bus messages.
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
    /// Messages answered with exception 07, negative acknowledge (0x10).
    pub nak: u16,
    /// Messages answered with exception 06, server device busy (0x11).
    pub busy: u16,
    /// Frames lost to a character overrun (0x12): here, more than 256 bytes without a frame boundary, more than
    /// the receive buffer stores.
    pub overrun: u16,
    /// Not an FC 08 counter: frames with a good CRC for another slave (what a drive whose no-response count
    /// includes them adds; the freedom `diagnostic-counter-semantics`).
    pub other_slave: u16,
    /// Not an FC 08 counter: responses sent (normal and exception), what a drive whose slave message count
    /// is "messages sent by the system" (SD2x manual) reports.
    pub responses_sent: u16,
}

/// The readings of the FC 08 counters the sources admit (the freedom `diagnostic-counter-semantics`), by
/// the name its data gives each: what each counts, from the counters a station keeps.
pub mod counter_semantics {
    use codec::codes::diag;

    use super::Counters;

    /// The reference: the serial line guide's and the application protocol's common reading.
    pub const STANDARD: &str = "standard";
    /// 0x0B counts bad-CRC frames too (application protocol 6.8.1: every message "detected").
    pub const BUS_COUNT_INCLUDES_BAD_CRC: &str = "bus-count-includes-bad-crc";
    /// 0x0F counts frames for other slaves too (serial line guide 6.1.1: messages "received").
    pub const NO_RESPONSE_INCLUDES_OTHER_SLAVES: &str = "no-response-includes-other-slaves";
    /// 0x0E counts the responses sent before this one (SD2x manual: messages "sent by the system").
    pub const SLAVE_COUNT_IS_RESPONSES_SENT: &str = "slave-count-is-responses-sent";
    /// 0x0B and 0x0E do not count the request that reads them.
    pub const EXCLUDES_CURRENT_REQUEST: &str = "excludes-current-request";

    /// Every reading but the reference's.
    pub const OTHERS: &[&str] = &[
        BUS_COUNT_INCLUDES_BAD_CRC,
        NO_RESPONSE_INCLUDES_OTHER_SLAVES,
        SLAVE_COUNT_IS_RESPONSES_SENT,
        EXCLUDES_CURRENT_REQUEST,
    ];

    /// The value sub-function `sub` reports under the reading `semantics`, read by the request being
    /// answered (counted already in `c` as the standard reading counts it). `None`: not a counter the
    /// reading is about, or an unknown reading.
    pub fn value(semantics: &str, sub: u16, c: &Counters) -> Option<u16> {
        Some(match (semantics, sub) {
            (STANDARD, diag::BUS_MESSAGE_COUNT) => c.bus_message,
            (STANDARD, diag::SERVER_MESSAGE_COUNT) => c.slave_message,
            (STANDARD, diag::SERVER_NO_RESPONSE_COUNT) => c.no_response,
            (BUS_COUNT_INCLUDES_BAD_CRC, diag::BUS_MESSAGE_COUNT) => {
                c.bus_message.wrapping_add(c.crc_error)
            }
            (NO_RESPONSE_INCLUDES_OTHER_SLAVES, diag::SERVER_NO_RESPONSE_COUNT) => {
                c.no_response.wrapping_add(c.other_slave)
            }
            (SLAVE_COUNT_IS_RESPONSES_SENT, diag::SERVER_MESSAGE_COUNT) => c.responses_sent,
            (EXCLUDES_CURRENT_REQUEST, diag::BUS_MESSAGE_COUNT) => c.bus_message.wrapping_sub(1),
            (EXCLUDES_CURRENT_REQUEST, diag::SERVER_MESSAGE_COUNT) => {
                c.slave_message.wrapping_sub(1)
            }
            _ => return None,
        })
    }

    /// The other readings' values of sub-function `sub` where they differ from the reference's.
    pub fn alternatives(sub: u16, c: &Counters) -> Vec<(&'static str, u16)> {
        let standard = value(STANDARD, sub, c);
        OTHERS
            .iter()
            .filter_map(|s| value(s, sub, c).map(|v| (*s, v)))
            .filter(|(_, v)| Some(*v) != standard)
            .collect()
    }
}

/// The communication state the serial line functions report beyond the FC 08 counters (MODBUS Application
/// Protocol v1.1b3 sections 6.8.1, 6.9, 6.10).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CommState {
    /// FC 0B's event counter: incremented once per successful message completion, not for exception responses
    /// nor for FC 0B itself (6.9); cleared by 08/01 and 08/0A.
    pub event_count: u16,
    /// FC 0C's event log, the most recent event first, at most 64 (6.10).
    pub events: VecDeque<u8>,
    /// Listen only mode (08/04): the drive monitors the line, answers nothing and processes only 08/01.
    pub listen_only: bool,
    /// The diagnostic register (08/02): the profile's value at power-up and restart, 0 after 08/0A.
    pub diagnostic_register: u16,
    /// The ASCII input delimiter (08/03): LF until changed; RTU framing does not use it.
    pub ascii_delimiter: u8,
    /// The overrun error flag, set with the overrun counter and reset by 08/14.
    pub overrun_flag: bool,
    /// The event counter was last cleared by 08/0A (not by a restart): whether that request counted is the
    /// freedom `event-counter-clear-counted`.
    pub cleared_by_0a: bool,
}

impl CommState {
    fn power_up(profile: &Profile) -> Self {
        Self {
            event_count: 0,
            events: VecDeque::with_capacity(event::LOG_CAPACITY),
            listen_only: false,
            cleared_by_0a: false,
            diagnostic_register: power_up_diagnostic_register(profile),
            ascii_delimiter: b'\n',
            overrun_flag: false,
        }
    }
}

/// The diagnostic register's content at power-up: the profile's `value` of sub-function 02, else 0.
fn power_up_diagnostic_register(profile: &Profile) -> u16 {
    profile
        .diagnostic(diag::RETURN_DIAGNOSTIC_REGISTER)
        .and_then(|d| d.value)
        .unwrap_or(0)
}

/// Which port a request came in on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Via {
    Tcp,
    Rtu { broadcast: bool },
}

/// What FC 08 did: its response (none for 08/04), and whether the message counts as a completion for the event
/// counter (not when it cleared that counter itself, 08/0A).
struct DiagOutcome {
    resp: Option<Response>,
    counted: bool,
}

impl DiagOutcome {
    fn reply(resp: Response) -> Self {
        let counted = !resp.is_exception();
        Self {
            resp: Some(resp),
            counted,
        }
    }
}

/// One Modbus/TCP connection's receive buffer: cuts the stream into ADUs by the MBAP length field.
#[derive(Clone, Debug, Default)]
pub struct TcpConn {
    buf: Vec<u8>,
    /// Bytes still to come of an ADU refused before it was complete (`mbap-length-long=exception-03`):
    /// dropped as they arrive.
    skip: usize,
}

/// What a drive does with an ADU whose MBAP length disagrees with its function's layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Disagreement {
    /// Exception 03.
    Refuse,
    /// No answer (or, for a longer MBAP length, wait for the bytes it announces).
    Ignore,
    /// Close the connection.
    Close,
}

/// The length of the Modbus/TCP ADU at the start of `buf` by its function code's request layout (the RTU
/// rules: unit id and PDU are an RTU frame without its CRC), when the bytes received tell it.
fn layout_len(buf: &[u8]) -> Option<usize> {
    match codec::framer::expected_len(Direction::Request, buf.get(6..)?, &[]) {
        codec::framer::FrameLen::Known(n, _) => Some(6 + n - 2),
        _ => None,
    }
}

/// [`layout_len`] where the layout gives one length only.
fn layout_len_only(buf: &[u8]) -> Option<usize> {
    match codec::framer::expected_len(Direction::Request, buf.get(6..)?, &[]) {
        codec::framer::FrameLen::Known(n, 0) => Some(6 + n - 2),
        _ => None,
    }
}

/// What a TCP connection produced.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct TcpOutput {
    /// Replies in request order (last first for a drive chosen `pipelined-response-order=transaction-id`).
    pub replies: Vec<Wire>,
    /// Close the connection after the replies: the stream cannot be resynchronised (an MBAP length below 2,
    /// or above 254 where the drive takes `pdu-over-253=close`, the reference's choice), or the drive chose to
    /// close (`truncated-pdu`, `mbap-length-short`, `mbap-length-long`).
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

    /// The silence an answer keeps after the request's last byte: t3.5 on a serial line (serial line guide
    /// 2.5.1.1); none over TCP, where there is no line and the carrier's long t3.5 only ends frames of
    /// unknown length ([`RtuTiming::tcp_carrier`]): a gateway's drive answers after its own line's t3.5.
    pub fn answer_silence(&self) -> Duration {
        let timing = self.timing();
        if timing.is_line() {
            timing.t3_5
        } else {
            Duration::ZERO
        }
    }
}

/// How a Modbus/TCP request to a unit id is taken (see `Station::tcp_unit_answered`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum UnitAnswer {
    Answer,
    Ignore,
    /// Refused as a gateway refuses a unit with no device behind it (0A, 0B).
    Refuse(ExceptionCode),
}

/// A simulated drive on the wire. A clone is an independent copy in the same state (see
/// [`BoxClone::box_clone`](crate::models::BoxClone::box_clone)).
#[derive(Clone)]
pub struct Station {
    model: Box<dyn DriveModel>,
    faults: FaultSet,
    unit: u8,
    counters: Counters,
    comm: CommState,
    /// An 08/01 restart to execute once the current message is done (true: clear the event log too).
    pending_restart: Option<bool>,
    dead: bool,
    /// The values taken where the freedoms leave the wire side a choice.
    choices: Choices,
    /// Freedoms that decided answers since the last [`Station::take_decisions`].
    decisions: Vec<Decision>,
    /// The FC 08 counter values the other readings of `diagnostic-counter-semantics` would have reported
    /// since the last [`Station::take_counter_alternatives`]: (sub-function, reading, value), for every
    /// reading about the counter but the station's own, whether or not it gives the same value.
    counter_alternatives: Vec<(u16, &'static str, u16)>,
    /// What the model would have answered under other values of the freedoms that decided the answers
    /// taken with the last [`Station::take_decisions`] (dropped by the next one).
    choice_alternatives: Vec<crate::choices::ModelledAlternative>,
    /// Those the station itself computed since the last [`Station::take_decisions`] (the layout's request
    /// of a PDU longer than its layout, served: `trailing-bytes = response`).
    own_alternatives: Vec<crate::choices::ModelledAlternative>,
    /// Where each accepted write is reported (`simulate --journal`).
    sink: Option<WriteSink>,
    /// Holding registers that keep the first value written to them (`simulate --latch`), and those of them
    /// written once already.
    latched: BTreeSet<u16>,
    latched_taken: BTreeSet<u16>,
    /// Holding registers that read off their value by a few counts (`simulate --jitter`): the amplitude, the
    /// reads before the jitter starts, and the reads so far.
    jitter: BTreeMap<u16, Jitter>,
    /// The exception the ADU being answered gets whatever its PDU holds (see [`Station::refuse`]).
    forced: Option<ExceptionCode>,
    /// The ADU just answered asks for the connection to be closed (`truncated-pdu=close`).
    close_requested: bool,
    /// The ADU being answered is short by its MBAP length's freedom (`mbap-length-short`), not by
    /// `truncated-pdu`'s.
    length_decided: bool,
    /// Until when requests are answered Server Busy (06) after a long-duration command
    /// (`busy-after-long-command`), and whether writes only.
    busy_until: Option<(Duration, bool)>,
    /// Someone takes the decisions and counter alternatives ([`Station::take_decisions`]); when not (see
    /// [`Station::forgetting_decisions`]) they are dropped as each new input arrives.
    observed: bool,
}

/// See [`Station::with_jitter`].
#[derive(Clone, Debug)]
struct Jitter {
    amplitude: u16,
    after: u32,
    reads: u32,
}

impl Station {
    /// A station answering as unit `unit` (RTU slave address; on TCP the unit ids of the profile are answered too).
    pub fn new(model: Box<dyn DriveModel>, faults: FaultSet, unit: u8) -> Self {
        let comm = CommState::power_up(model.profile());
        Self {
            model,
            faults,
            unit,
            counters: Counters::default(),
            comm,
            pending_restart: None,
            dead: false,
            choices: Choices::reference(),
            decisions: Vec::new(),
            counter_alternatives: Vec::new(),
            choice_alternatives: Vec::new(),
            own_alternatives: Vec::new(),
            sink: None,
            latched: BTreeSet::new(),
            latched_taken: BTreeSet::new(),
            jitter: BTreeMap::new(),
            forced: None,
            close_requested: false,
            length_decided: false,
            busy_until: None,
            observed: true,
        }
    }

    /// The same station for a caller that never takes its decisions (a server, the drive under test of a
    /// `sim:` target): what answering one input decided is dropped when the next input arrives, so memory
    /// and the time per request stay flat however long the station serves. (Kept, they grew without bound:
    /// a `simulate` fuzzed for 30 s grew by 400 KB a second, and served more slowly as the list it cloned
    /// with the model for every request grew.)
    pub fn forgetting_decisions(mut self) -> Self {
        self.observed = false;
        self
    }

    /// Drop what the last input decided when nobody takes it.
    fn forget_unobserved(&mut self) {
        if !self.observed {
            self.decisions.clear();
            self.counter_alternatives.clear();
            let _ = self.model.take_decisions();
            let _ = self.model.take_alternatives();
            self.choice_alternatives.clear();
            self.own_alternatives.clear();
        }
    }

    /// The same station reporting every write it accepts to `sink`: what it wrote, the value before and
    /// after (read from the model, not counted as traffic).
    pub fn with_write_sink(mut self, sink: WriteSink) -> Self {
        self.sink = Some(sink);
        self
    }

    /// The same station whose holding registers at `addresses` keep the first value written to them that
    /// changes them after start-up: later writes are acknowledged and not taken (a drive that latches a setting until power
    /// cycle; what a restore must notice).
    pub fn with_latched(mut self, addresses: impl IntoIterator<Item = u16>) -> Self {
        self.latched.extend(addresses);
        self
    }

    /// The same station whose holding register `address` reads off its value by up to `amplitude` counts
    /// (+1, -1, +2, -2, 0, ... capped at `amplitude`) from its `after`-th read on (a 16-bit register: the
    /// word is offset): a measured value on a drive with its motor attached, an encoder count jittering at
    /// standstill, that starts to move only after the reads a run makes before its first write (what
    /// `Runner::recheck_live` must tell apart from a wrong value). The stored value does not change.
    pub fn with_jitter(mut self, address: u16, amplitude: u16, after: u32) -> Self {
        self.jitter.insert(
            address,
            Jitter {
                amplitude,
                after,
                reads: 0,
            },
        );
        self
    }

    /// A read answer with the jittering registers it covers offset (see [`Station::with_jitter`]).
    fn jittered(&mut self, req: &Request, resp: Option<Response>) -> Option<Response> {
        let Request::ReadHoldingRegisters { address, quantity } = req else {
            return resp;
        };
        let Some(Response::ReadHoldingRegisters { mut values }) = resp else {
            return resp;
        };
        let end = u32::from(*address) + u32::from(*quantity);
        for (a, j) in self
            .jitter
            .range_mut(*address..)
            .take_while(|(a, _)| u32::from(**a) < end)
        {
            j.reads = j.reads.saturating_add(1);
            if j.reads <= j.after {
                continue;
            }
            const STEPS: [i32; 5] = [1, -1, 2, -2, 0];
            let amp = i32::from(j.amplitude);
            let step = STEPS[(j.reads - j.after) as usize % STEPS.len()].clamp(-amp, amp);
            if let Some(v) = values.get_mut(usize::from(a - address)) {
                *v = (i32::from(*v) + step) as u16;
            }
        }
        Some(Response::ReadHoldingRegisters { values })
    }

    /// Answer `req` through the model, reporting an accepted write and honouring latched registers.
    fn handle_model(&mut self, now: Duration, unit: u8, req: &Request) -> Option<Response> {
        let resp = self.handle_model_plain(now, unit, req);
        if self.jitter.is_empty() {
            return resp;
        }
        self.jittered(req, resp)
    }

    fn handle_model_plain(&mut self, now: Duration, unit: u8, req: &Request) -> Option<Response> {
        let written = Written::of(req);
        let latched = match &written {
            Some(Written::Holding { address, quantity }) if !self.latched.is_empty() => (*address
                ..address.saturating_add(*quantity))
                .filter(|a| self.latched.contains(a))
                .collect(),
            _ => Vec::new(),
        };
        if latched.iter().any(|a| self.latched_taken.contains(a)) {
            // Acknowledged as the drive would, on a copy: the latched value stays.
            let mut scratch = self.model.clone();
            return scratch.handle(now, unit, req);
        }
        let before = match (&self.sink, &written) {
            (Some(_), Some(w)) => Some(tell::peek(self.model.as_mut(), now, unit, w)),
            (None, Some(w)) if !latched.is_empty() => {
                Some(tell::peek(self.model.as_mut(), now, unit, w))
            }
            _ => None,
        };
        let resp = self.model.handle(now, unit, req);
        if resp.as_ref().is_some_and(|r| !r.is_exception())
            && let (Some(w), Some((address, old))) = (written, before)
        {
            let (_, new) = tell::peek(self.model.as_mut(), now, unit, &w);
            // Latched once the value changed (a write of the value it holds latches nothing).
            if new != old {
                self.latched_taken.extend(latched);
            }
            if let Some(sink) = &self.sink {
                sink(&WriteRecord {
                    at: now,
                    unit,
                    function: req.function(),
                    written: w,
                    address,
                    old,
                    new,
                });
            }
        }
        resp
    }

    /// The same station taking `choices` where the freedoms leave the wire side one (the model takes its
    /// own from [`crate::build_with`]).
    pub fn with_choices(mut self, choices: Choices) -> Self {
        self.choices = choices;
        self
    }

    /// Take `choices` from now on, the model too, keeping the state (see [`DriveModel::adopt`]).
    pub fn adopt(&mut self, choices: Choices) {
        self.model.adopt(&choices);
        self.choices = choices;
    }

    /// The freedoms that decided the answers given since the last call, the model's included: where an
    /// oracle must accept any admissible value, not only this drive's.
    pub fn take_decisions(&mut self) -> Vec<Decision> {
        let mut alternatives = std::mem::take(&mut self.own_alternatives);
        alternatives.extend(self.model.take_alternatives());
        self.choice_alternatives = alternatives;
        self.decisions.extend(self.model.take_decisions());
        std::mem::take(&mut self.decisions)
    }

    /// The FC 08 counter values the other admissible readings of the counters (the freedom
    /// `diagnostic-counter-semantics`) would have given where they differ from this drive's, for the counter
    /// reads answered since the last call: (sub-function, reading, value).
    pub fn take_counter_alternatives(&mut self) -> Vec<(u16, &'static str, u16)> {
        std::mem::take(&mut self.counter_alternatives)
    }

    /// What the model would have answered under other values of the freedoms that decided the answers taken
    /// with the last [`Station::take_decisions`] (see [`crate::choices::Freedoms::alternative`]).
    pub fn take_choice_alternatives(&mut self) -> Vec<crate::choices::ModelledAlternative> {
        std::mem::take(&mut self.choice_alternatives)
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

    /// The event counter, event log, listen only mode and diagnostic register.
    pub fn comm_state(&self) -> &CommState {
        &self.comm
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

    /// Add an event to the FC 0C log (the most recent first; each new byte flushes the oldest past 64).
    fn log_event(&mut self, e: u8) {
        self.comm.events.push_front(e);
        self.comm.events.truncate(event::LOG_CAPACITY);
    }

    /// Bit 5 of receive and send events: currently in listen only mode.
    fn listen_bit(&self) -> u8 {
        if self.comm.listen_only {
            event::LISTEN_ONLY
        } else {
            0
        }
    }

    /// Execute an 08/01 restart accepted while handling the message just done (spec 6.8.1: the response goes
    /// out before the restart): the port leaves listen only mode, every counter and the event counter are
    /// cleared, the diagnostic register and the delimiter return to their power-up values, the log is cleared
    /// on FF 00 and gets the restart event (6.10: "Remote device Initiated Communication Restart", 00).
    fn finish_message(&mut self) {
        let Some(clear_log) = self.pending_restart.take() else {
            return;
        };
        self.counters = Counters::default();
        self.comm.event_count = 0;
        self.comm.listen_only = false;
        self.comm.diagnostic_register = power_up_diagnostic_register(self.model.profile());
        self.comm.ascii_delimiter = b'\n';
        self.comm.overrun_flag = false;
        self.comm.cleared_by_0a = false;
        if clear_log {
            self.comm.events.clear();
        }
        self.log_event(event::COMM_RESTART);
    }

    fn malformed(&mut self) {
        if self.faults.has(Fault::StopAfterMalformed) {
            self.dead = true;
        }
    }

    /// Feed bytes received on a Modbus/TCP connection at `now`; returns the replies.
    ///
    /// Where the stream leaves the server a choice, the station takes its [`Choices`]: an MBAP length that
    /// announces a PDU over 253 bytes (`pdu-over-253`: close, or skip the ADU silently or with 03), an MBAP
    /// length that disagrees with the function's own layout once the layout's bytes are in
    /// (`mbap-length-short`: shorter, the missing bytes right behind; `mbap-length-long`: longer, the PDU
    /// complete by its layout), several ADUs received together (`pipelined-server-busy`: the ones after
    /// the first get exception 06; `pipelined-response-order`: answered last first).
    pub fn serve_tcp(&mut self, now: Duration, conn: &mut TcpConn, bytes: &[u8]) -> TcpOutput {
        self.forget_unobserved();
        let skip = conn.skip.min(bytes.len());
        conn.skip -= skip;
        conn.buf.extend_from_slice(&bytes[skip..]);
        let mut out = TcpOutput::default();
        let mut answered = 0;
        let mut taken = 0;
        while let Some(len) = tcp::adu_len(&conn.buf) {
            let declared = len - 6;
            if declared > 254 && !self.faults.has(Fault::MbapLengthIgnored) {
                // Past the 253-byte PDU limit: how a server refuses it is its choice.
                self.decisions.push(ids::PDU_OVER_253);
                let choice = self.choices.name(ids::PDU_OVER_253).map(str::to_owned);
                if let Some(choice @ ("silence" | "exception-03")) = choice.as_deref() {
                    // Skipped as a whole (the MBAP length says where the next ADU begins), unanswered
                    // or refused.
                    if conn.buf.len() < len {
                        break;
                    }
                    self.malformed();
                    let reply = if choice == "exception-03" {
                        self.refuse(now, &conn.buf[..len], ExceptionCode::ILLEGAL_DATA_VALUE)
                    } else {
                        None
                    };
                    conn.buf.drain(..len);
                    out.replies.extend(reply);
                    taken += 1;
                    continue;
                }
            }
            if !(2..=254).contains(&declared) {
                self.malformed();
                conn.buf.clear();
                out.close = true;
                break;
            }
            if conn.buf.len() < len {
                // The fault: the ADU is cut where the function code's rules end the PDU (the RTU rules:
                // unit id and PDU are an RTU frame without its CRC), the MBAP length unheeded.
                let cut = self
                    .faults
                    .has(Fault::MbapLengthIgnored)
                    .then(|| layout_len(&conn.buf))
                    .flatten()
                    .filter(|&cut| cut > tcp::MBAP_LEN && cut <= conn.buf.len());
                if let Some(cut) = cut {
                    let reply = self.tcp_adu(now, &conn.buf[..cut]);
                    conn.buf.drain(..cut);
                    out.replies.extend(reply);
                    if std::mem::take(&mut self.close_requested) {
                        conn.buf.clear();
                        out.close = true;
                        break;
                    }
                    continue;
                }
                match self.mbap_disagrees(&conn.buf, len) {
                    Some(Disagreement::Close) => {
                        self.malformed();
                        conn.buf.clear();
                        out.close = true;
                    }
                    Some(Disagreement::Refuse) => {
                        // Refused now; the bytes the MBAP length still announces are skipped as they come.
                        self.malformed();
                        let reply = self.refuse(now, &conn.buf, ExceptionCode::ILLEGAL_DATA_VALUE);
                        out.replies.extend(reply);
                        conn.skip = len - conn.buf.len();
                        conn.buf.clear();
                    }
                    Some(Disagreement::Ignore) | None => {}
                }
                break;
            }
            let disagreement = self.mbap_disagrees(&conn.buf, len);
            if taken > 0 {
                self.decisions.push(ids::PIPELINED_SERVER_BUSY);
            }
            // Answered in place, then dropped from the buffer: no copy of the ADU.
            let reply = match disagreement {
                // Exception 06 for the ADUs after the first of one receive: a server with one transaction.
                None if taken > 0
                    && self.choices.name(ids::PIPELINED_SERVER_BUSY) == Some("exception-06") =>
                {
                    self.refuse(now, &conn.buf[..len], ExceptionCode::SERVER_DEVICE_BUSY)
                }
                None => {
                    let reply = self.tcp_adu(now, &conn.buf[..len]);
                    if std::mem::take(&mut self.close_requested) {
                        conn.buf.clear();
                        out.close = true;
                        break;
                    }
                    reply
                }
                Some(Disagreement::Refuse) => {
                    // The reference's answer: the PDU the MBAP length gives is taken and refused as any
                    // request too short for its function (03; 01 for a function it lacks), the length's
                    // freedom deciding, not `truncated-pdu`. A drive without Modbus/TCP is behind a gateway,
                    // which cuts the PDU by the MBAP length: to the drive it is a PDU too short for its
                    // function, `truncated-pdu` deciding.
                    self.length_decided = self.profile().speaks_tcp();
                    let reply = self.tcp_adu(now, &conn.buf[..len]);
                    self.length_decided = false;
                    reply
                }
                Some(Disagreement::Ignore) => {
                    self.malformed();
                    None
                }
                Some(Disagreement::Close) => {
                    self.malformed();
                    conn.buf.clear();
                    out.close = true;
                    break;
                }
            };
            conn.buf.drain(..len);
            taken += 1;
            if let Some(w) = reply {
                if answered == 0 || !self.faults.has(Fault::PipelineDrop) {
                    out.replies.push(w);
                }
                answered += 1;
            }
        }
        if out.replies.len() > 1 {
            // The guide pairs pipelined answers by transaction id only: a drive may send them in any order.
            self.decisions.push(ids::PIPELINED_RESPONSE_ORDER);
            if self.choices.name(ids::PIPELINED_RESPONSE_ORDER) == Some("transaction-id") {
                out.replies.reverse();
            }
        }
        out
    }

    /// Where the MBAP length `len` of the ADU at the start of `buf` disagrees with the length the function
    /// code's own request layout gives, and the bytes that layout needs are all there: what the drive does
    /// (`None`: it takes the MBAP length, as the reference does, or they agree).
    ///
    /// - MBAP length shorter, with the layout's missing bytes right behind it (`mbap-length-short`):
    ///   the reference refuses the short PDU with 03 and takes the rest as the next ADU; a drive may ignore
    ///   it or close the connection. (A short PDU with nothing behind it is a truncated PDU, decided in
    ///   [`Station::answer`] by `truncated-pdu`: the stream does not tell them apart otherwise.)
    /// - MBAP length longer, the PDU complete by its layout (`mbap-length-long`): the reference waits for the
    ///   bytes announced (silence); a drive may close the connection or refuse it with 03 at once (then
    ///   skipping the bytes still announced).
    fn mbap_disagrees(&mut self, buf: &[u8], len: usize) -> Option<Disagreement> {
        let by_layout = layout_len_only(buf)?;
        let (freedom, reference) = if by_layout > len && buf.len() >= by_layout {
            (ids::MBAP_LENGTH_SHORT, Disagreement::Refuse)
        } else if by_layout < len && buf.len() >= by_layout && buf.len() < len {
            (ids::MBAP_LENGTH_LONG, Disagreement::Ignore)
        } else {
            return None;
        };
        self.decisions.push(freedom);
        let chosen = match self.choices.name(freedom) {
            Some("silence") => Disagreement::Ignore,
            Some("close") => Disagreement::Close,
            Some("exception-03") => Disagreement::Refuse,
            _ => reference,
        };
        // The reference waits for an MBAP length's bytes: nothing to do yet.
        (chosen != Disagreement::Ignore || freedom != ids::MBAP_LENGTH_LONG).then_some(chosen)
    }

    /// [`Station::tcp_adu`] answering the ADU at the start of `adu` (its MBAP header and function code at
    /// least) with exception `code`, whatever its PDU holds, with the bookkeeping of any answer (events,
    /// exception and busy counts).
    fn refuse(&mut self, now: Duration, adu: &[u8], code: ExceptionCode) -> Option<Wire> {
        self.forced = Some(code);
        let reply = self.tcp_adu(now, adu);
        self.forced = None;
        reply
    }

    /// How a Modbus/TCP request to `unit` is answered: the station's unit and the profile's unit ids are,
    /// except a unit in the `tcp-unit-ids` freedom's range when the drive chose to ignore it or to refuse it
    /// as a gateway would (0A, 0B) (0 and 0xFF are always answered where the profile answers them).
    fn tcp_unit_answered(&mut self, unit: u8) -> UnitAnswer {
        let accepted = unit == self.unit || {
            let [lo, hi] = self.profile().device.unit_ids;
            (lo..=hi).contains(&unit)
        };
        if !accepted {
            return UnitAnswer::Ignore;
        }
        if unit == self.unit || matches!(unit, 0 | 0xFF) {
            return UnitAnswer::Answer;
        }
        let Some((f, value)) = self
            .choices
            .defined()
            .find(|(f, _)| f.id == ids::TCP_UNIT_IDS)
        else {
            return UnitAnswer::Answer;
        };
        if !f.covers_unit(unit) {
            return UnitAnswer::Answer;
        }
        self.decisions.push(ids::TCP_UNIT_IDS);
        if value.matches("silence") {
            UnitAnswer::Ignore
        } else if let Some(code) = Choices::exception_value(value) {
            UnitAnswer::Refuse(code)
        } else {
            UnitAnswer::Answer
        }
    }

    /// What the client of a drive without Modbus/TCP hears where the drive stays silent: a gateway is
    /// between, and answers as the `gateway-no-response` choice says (silence, 0B or 0A).
    fn gateway_silence(&mut self, header: &tcp::Mbap, function: Option<u8>) -> Option<Wire> {
        if self.profile().speaks_tcp() {
            return None;
        }
        self.decisions.push(ids::GATEWAY_NO_RESPONSE);
        let code = self
            .choices
            .get(ids::GATEWAY_NO_RESPONSE)
            .and_then(Choices::exception_value)?;
        self.gateway_refusal(header, function?, code)
    }

    /// An exception `code` to `function` sent for the unit of `header` by what routes requests to it (a
    /// gateway, or a server routing by unit id): not the drive's answer, so none of its counts. The faults
    /// of the exception's form and of the MBAP echoes are the whole box's: they apply to it too.
    fn gateway_refusal(
        &mut self,
        header: &tcp::Mbap,
        function: u8,
        code: ExceptionCode,
    ) -> Option<Wire> {
        let function = if self.faults.has(Fault::ExceptionWithoutFc) {
            0x80
        } else {
            function | 0x80
        };
        let (tid, unit) = self.echoed(header);
        let mut bytes = Vec::with_capacity(tcp::MBAP_LEN + 2);
        tcp::encode_adu(tid, unit, &[function, code.0], &mut bytes).ok()?;
        Some(self.wire(bytes))
    }

    /// The transaction and unit id an answer to `header` carries: the request's, unless a fault says otherwise.
    fn echoed(&self, header: &tcp::Mbap) -> (u16, u8) {
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
        (tid, unit)
    }

    /// Answer one complete Modbus/TCP ADU (`None`: no response is sent).
    pub fn tcp_adu(&mut self, now: Duration, adu: &[u8]) -> Option<Wire> {
        self.forget_unobserved();
        let header = tcp::Mbap::parse(adu)?;
        if header.protocol_id != 0 && !self.faults.has(Fault::ProtocolIdIgnored) {
            // TCP implementation guide: a frame whose protocol id is not Modbus is discarded.
            self.malformed();
            return None;
        }
        if self.dead {
            return None;
        }
        let pdu = &adu[tcp::MBAP_LEN..];
        let function = pdu.first().copied();
        match self.tcp_unit_answered(header.unit_id) {
            UnitAnswer::Refuse(code) if self.forced.is_none() => {
                return self.gateway_refusal(&header, function?, code);
            }
            UnitAnswer::Ignore if !self.faults.has(Fault::AnswerOtherUnit) => {
                return self.gateway_silence(&header, function);
            }
            _ => {}
        }
        let resp = self.answer(now, header.unit_id, pdu, Via::Tcp);
        self.finish_message();
        let Some(resp) = resp else {
            return self.gateway_silence(&header, function);
        };
        let mut body = self.pdu_bytes(&resp);
        if self.faults.has(Fault::TruncatedResponse) && body.len() > 1 {
            body.pop();
        }
        let (tid, unit) = self.echoed(&header);
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
        self.forget_unobserved();
        // On a multi-drop line the replies of the other slaves are heard too.
        port.framer.listen_as(self.unit);
        let events = port.framer.push(now, bytes);
        self.rtu_events(now, events, port.answer_silence())
    }

    /// Let silence complete or discard what the port holds at `now`.
    pub fn poll_rtu(&mut self, now: Duration, port: &mut RtuPort) -> Vec<Wire> {
        self.forget_unobserved();
        let events = port.framer.poll(now);
        self.rtu_events(now, events, port.answer_silence())
    }

    /// Answer the frames the port's framer delimited. An answer goes out no sooner than `t3_5` (the port's
    /// [`RtuPort::answer_silence`]) after the request's last byte (serial line guide 2.5.1.1: frames are
    /// separated by at least 3.5 character times), also when the framer cut the request by its length
    /// before that silence.
    fn rtu_events(&mut self, now: Duration, events: Vec<FramerEvent>, t3_5: Duration) -> Vec<Wire> {
        let mut out = Vec::new();
        for ev in events {
            match ev {
                FramerEvent::Frame { bytes, end, .. } => {
                    if let Some(mut w) = self.rtu_frame(now, &bytes) {
                        if !self.faults.has(Fault::AnswerInsideSilence) {
                            w.delay += (end + t3_5).saturating_sub(now);
                        }
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
                        if let Some(mut w) = self.rtu_frame(now, &fixed) {
                            if !self.faults.has(Fault::AnswerInsideSilence) {
                                w.delay += t3_5;
                            }
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
                        // A receive event with its condition (spec 6.10): more bytes than the buffer holds
                        // is a character overrun, anything else a communication error.
                        let condition = if reason == DiscardReason::Overlong {
                            self.count(|c| c.overrun = c.overrun.wrapping_add(1));
                            self.comm.overrun_flag = true;
                            event::RECEIVE_OVERRUN
                        } else {
                            event::RECEIVE_COMM_ERROR
                        };
                        self.log_event(event::RECEIVE | condition | self.listen_bit());
                        self.malformed();
                    }
                }
            }
        }
        out
    }

    /// Answer one RTU ADU whose CRC is valid (`None`: silence).
    pub fn rtu_frame(&mut self, now: Duration, frame: &[u8]) -> Option<Wire> {
        self.forget_unobserved();
        let Ok(adu) = rtu::decode_adu(frame) else {
            self.count(|c| c.crc_error = c.crc_error.wrapping_add(1));
            self.log_event(event::RECEIVE | event::RECEIVE_COMM_ERROR | self.listen_bit());
            self.malformed();
            return None;
        };
        self.count(|c| c.bus_message = c.bus_message.wrapping_add(1));
        let broadcast = adu.address == rtu::BROADCAST && self.profile().device.broadcast;
        let ours = adu.address == self.unit || broadcast;
        if !ours {
            self.count(|c| c.other_slave = c.other_slave.wrapping_add(1));
        }
        if !ours && !self.faults.has(Fault::AnswerOtherUnit) {
            return None;
        }
        if self.dead {
            return None;
        }
        if self.comm.listen_only {
            self.listening(adu.pdu, broadcast);
            return None;
        }
        self.count(|c| c.slave_message = c.slave_message.wrapping_add(1));
        let pdu = adu.pdu.to_vec();
        if broadcast
            && self.faults.has(Fault::BroadcastWriteIgnored)
            && pdu.first().is_some_and(|fc| writes_data_model(*fc))
        {
            // The firmware bug: a broadcast write is dropped unprocessed (and, a broadcast, not answered).
            self.count(|c| c.no_response = c.no_response.wrapping_add(1));
            self.finish_message();
            return None;
        }
        let resp = self.answer(now, adu.address, &pdu, Via::Rtu { broadcast });
        let resp = match resp {
            Some(r) if !broadcast || self.faults.has(Fault::BroadcastAnswered) => r,
            _ => {
                self.count(|c| c.no_response = c.no_response.wrapping_add(1));
                self.finish_message();
                return None;
            }
        };
        self.finish_message();
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
        self.count(|c| c.responses_sent = c.responses_sent.wrapping_add(1));
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
        if let Response::ReadDeviceId(_) = resp
            && self.faults.has(Fault::ConformityLevelWrong)
            && let Some(conformity) = b.get_mut(3)
        {
            // 2B 0E code conformity ...
            *conformity = 0x01;
        }
        if let Response::CanOpen(_) = resp
            && self.fc43_without_reserved()
            && let Some(short) = codec::canopen_without_reserved(&b)
        {
            b = short;
        }
        if let Response::VendorRead { params } = resp
            && self.choices.name(ids::FC41_BYTE_COUNT_WIDTH) == Some("2-byte")
        {
            // The tables' layout (000 line 955, 001 line 1127): a 2-byte byte count.
            b.splice(
                1..2,
                u16::try_from(params.len())
                    .unwrap_or(u16::MAX)
                    .to_be_bytes(),
            );
        }
        if let Response::ReadFileRecord { sub_responses } = resp
            && self.faults.has(Fault::FileRecordLengthWrong)
        {
            // Each sub-response's length byte (after FC and the response data length) loses the reference type.
            let mut at = 2;
            for s in sub_responses {
                if let Some(len) = b.get_mut(at) {
                    *len = len.wrapping_sub(1);
                }
                at += 2 + 2 * s.values.len();
            }
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

    /// A message for this drive (or a broadcast) in listen only mode (spec 6.8.1, 04): monitored, logged as a
    /// receive event with bit 5 set, not processed and not answered; only an 08/01 restart is acted on.
    fn listening(&mut self, pdu: &[u8], broadcast: bool) {
        let bcast = if broadcast {
            event::RECEIVE_BROADCAST
        } else {
            0
        };
        self.log_event(event::RECEIVE | event::LISTEN_ONLY | bcast);
        let restart = match Request::decode(pdu) {
            Ok(Request::Diagnostics { sub_function, data })
                if sub_function == diag::RESTART_COMMUNICATIONS
                    && self.profile().function(FunctionCode::DIAGNOSTICS).is_some() =>
            {
                self.profile()
                    .diagnostic(sub_function)
                    .filter(|d| !d.check_data || diag_data_ok(d.counter, &data))
                    .map(|_| data == diag::RESTART_CLEAR_LOG.to_be_bytes())
            }
            _ => None,
        };
        if restart.is_some() {
            self.pending_restart = restart;
            self.finish_message();
        }
    }

    /// The spec-level checks every server makes, then the model, with the bookkeeping of the serial line
    /// functions around them: the receive event before, the exception/NAK/busy counts, the event counter and
    /// the send event after. `None`: the drive stays silent.
    fn answer(&mut self, now: Duration, unit: u8, pdu: &[u8], via: Via) -> Option<Response> {
        let fc = FunctionCode(*pdu.first()?);
        // Spec 6.10: a receive event is stored when a query arrives, before it is processed.
        let bcast = if via == (Via::Rtu { broadcast: true }) {
            event::RECEIVE_BROADCAST
        } else {
            0
        };
        self.log_event(event::RECEIVE | bcast);
        let busy = self.forced.is_none() && self.busy_with_long_command(now, pdu);
        let (resp, completed) = match self.forced {
            Some(code) => (Some(Response::exception(fc, code)), false),
            None if busy => (
                Some(Response::exception(fc, ExceptionCode::SERVER_DEVICE_BUSY)),
                false,
            ),
            None => {
                let (resp, completed) = self.process(now, unit, fc, pdu, via)?;
                if completed {
                    self.start_long_command(now, pdu);
                }
                (self.sdo_error_in_drive_order(resp, pdu), completed)
            }
        };
        let exception = resp.as_ref().and_then(|r| match r {
            Response::Exception { code, .. } => Some(*code),
            Response::CanOpenError { .. } => Some(ExceptionCode::EXTENDED),
            _ => None,
        });
        if let Some(code) = exception {
            self.count(|c| c.exception = c.exception.wrapping_add(1));
            match code {
                ExceptionCode::SERVER_DEVICE_BUSY => {
                    self.count(|c| c.busy = c.busy.wrapping_add(1));
                }
                ExceptionCode(0x07) => self.count(|c| c.nak = c.nak.wrapping_add(1)),
                _ => {}
            }
        }
        // Spec 6.9: the event counter counts successful completions, not exception responses nor FC 0B.
        let counts = (completed
            || (exception.is_some() && self.faults.has(Fault::EventCounterCountsExceptions)))
            && fc != FunctionCode::GET_COMM_EVENT_COUNTER;
        if counts {
            self.comm.event_count = self.comm.event_count.wrapping_add(1);
        }
        // Spec 6.10: a send event when processing ends, with the kind of exception sent.
        let sent = match exception.map(|c| c.0) {
            Some(1..=3) => event::SEND_READ_EXCEPTION,
            Some(4) => event::SEND_ABORT_EXCEPTION,
            Some(5 | 6) => event::SEND_BUSY_EXCEPTION,
            Some(7) => event::SEND_NAK_EXCEPTION,
            _ => 0,
        };
        self.log_event(event::SEND | sent | self.listen_bit());
        resp
    }

    /// How long a drive that chose `busy-after-long-command` stays busy after the command.
    const BUSY_AFTER_LONG_COMMAND: Duration = Duration::from_millis(400);

    /// `busy-after-long-command`: whether the request `pdu`, arriving at `now`, is answered Server Busy (06)
    /// because a long-duration command taken before is still running (every request, or writes only).
    fn busy_with_long_command(&mut self, now: Duration, pdu: &[u8]) -> bool {
        let Some((until, writes_only)) = self.busy_until else {
            return false;
        };
        if now >= until {
            self.busy_until = None;
            return false;
        }
        !writes_only
            || Request::decode(pdu).is_ok_and(|r| {
                crate::requirements::registers_written(&r).is_some()
                    || matches!(
                        r,
                        Request::WriteSingleCoil { .. }
                            | Request::WriteMultipleCoils { .. }
                            | Request::VendorWrite { .. }
                    )
            })
    }

    /// `busy-after-long-command`: a request taken that writes one of the freedom's items (S, CP, UG) starts
    /// the busy time.
    fn start_long_command(&mut self, now: Duration, pdu: &[u8]) {
        let Some(writes_only) = (match self.choices.name(ids::BUSY_AFTER_LONG_COMMAND) {
            Some("all-requests") => Some(false),
            Some("writes") => Some(true),
            _ => None,
        }) else {
            return;
        };
        let Ok(req) = Request::decode(pdu) else {
            return;
        };
        let writes = crate::requirements::registers_written(&req).is_some()
            || matches!(req, Request::VendorWrite { .. });
        let profile = self.model.profile();
        let long = writes
            && self.choices.defined().any(|(f, _)| {
                f.id == ids::BUSY_AFTER_LONG_COMMAND
                    && f.items.iter().any(|i| i.touched_by(&req, profile))
            });
        if long {
            self.busy_until = Some((now + Self::BUSY_AFTER_LONG_COMMAND, writes_only));
        }
    }

    /// Answer one request: (the response or silence, whether the message completed normally). `None` when the
    /// drive went silent for good.
    /// An SDO error code as this drive sends it: little-endian, as the reference does, or in the order the
    /// code is printed (freedom `sd2x-sdo-error-byte-order`), the other order offered as its alternative.
    /// `Fault::SdoErrorOrderInconsistent`: the order by the request's direction (its control code's bit 7).
    fn sdo_error_in_drive_order(&mut self, resp: Option<Response>, pdu: &[u8]) -> Option<Response> {
        let Some(Response::CanOpenError { sdo_code }) = resp else {
            return resp;
        };
        let printed = if self.faults.has(Fault::SdoErrorOrderInconsistent) {
            // FC 43 / MEI 0x0D: the control code follows the MEI type; bit 7 set is a write (SD2x 5.6.1).
            pdu.get(2)
                .is_some_and(|control| control & codec::mei::CanOpenAccess::WRITE != 0)
        } else {
            self.choices.name(ids::SD2X_SDO_ERROR_BYTE_ORDER) == Some("printed-order")
        };
        let swapped = Response::CanOpenError {
            sdo_code: sdo_code.swap_bytes(),
        };
        let own = Response::CanOpenError { sdo_code };
        self.decisions.push(ids::SD2X_SDO_ERROR_BYTE_ORDER);
        let (answer, other, other_answer) = if printed {
            (swapped, "little-endian", own)
        } else {
            (own, "printed-order", swapped)
        };
        self.own_alternatives
            .push((ids::SD2X_SDO_ERROR_BYTE_ORDER, other, other_answer));
        Some(answer)
    }

    fn process(
        &mut self,
        now: Duration,
        unit: u8,
        fc: FunctionCode,
        pdu: &[u8],
        via: Via,
    ) -> Option<(Option<Response>, bool)> {
        // On a serial line, a frame whose length is not the one its function code's layout gives (a byte
        // count off, cut short, bytes after the layout): a slave that sizes frames by those rules (as RTU
        // slaves do) takes the frame to end elsewhere, where its CRC fails, or waits for bytes that never
        // come, and answers nothing (serial 2.4.2): the reference's answer, or silence
        // (`rtu-length-framing`). A function code without a length rule is ended by silence alike. Decided
        // after the freedoms of the request itself (`truncated-pdu`, `trailing-bytes`), so that where one of
        // them explains a silence too, the drive's choice is recorded as that one's.
        let length_off = matches!(via, Via::Rtu { .. })
            && !rtu_length_agrees(unit, pdu, self.profile().function(fc).is_some());
        if length_off && self.choices.name(ids::RTU_LENGTH_FRAMING) == Some("silence") {
            self.decisions.push(ids::RTU_LENGTH_FRAMING);
            return Some((None, false));
        }
        let answer = self.process_request(now, unit, fc, pdu, via);
        if length_off {
            self.decisions.push(ids::RTU_LENGTH_FRAMING);
        }
        answer
    }

    /// [`Station::process`] of a request whose frame the drive took whole.
    fn process_request(
        &mut self,
        now: Duration,
        unit: u8,
        fc: FunctionCode,
        pdu: &[u8],
        via: Via,
    ) -> Option<(Option<Response>, bool)> {
        let supported = !fc.is_exception()
            && (self.profile().function(fc).is_some()
                || (self.faults.has(Fault::UndeclaredFunctionServed)
                    && matches!(fc.0, 0x01..=0x06 | 0x0F | 0x10 | 0x16 | 0x17)));
        // A drive that serves public functions beyond its profile (the freedom's `functions`).
        let served_extra = !fc.is_exception()
            && self
                .choices
                .name(ids::SERVED_EXTRA_FUNCTION)
                .is_some_and(|v| v == "served")
            && self
                .choices
                .defined_of(FreedomKind::ServedExtra)
                .all(|(f, _)| f.functions.contains(&fc.0));
        if self.faults.has(Fault::ListedFunctionRefused) && fc == FunctionCode::READ_INPUT_REGISTERS
        {
            return Some((
                Some(Response::exception(fc, ExceptionCode::ILLEGAL_FUNCTION)),
                false,
            ));
        }
        if fc.is_exception() && self.faults.has(Fault::HighFunctionServed) {
            let mut masked = pdu.to_vec();
            masked[0] &= 0x7F;
            return self.process(now, unit, FunctionCode(masked[0]), &masked, via);
        }
        if fc.is_exception() || fc.0 == 0 {
            // 128-255 are exception responses' codes and 0 is not valid (App 4.1): 01, or no answer at all
            // (`request-fc-over-127`, `request-fc-zero`).
            let id = if fc.0 == 0 {
                ids::REQUEST_FC_ZERO
            } else {
                ids::REQUEST_FC_OVER_127
            };
            self.decisions.push(id);
            match self.choices.name(id) {
                Some("silence") => return Some((None, false)),
                Some("close") => {
                    self.close_requested = via == Via::Tcp;
                    return Some((None, false));
                }
                _ => {}
            }
        }
        if !supported && !served_extra {
            // A function the profile does not list: a drive may serve it anyway (a freedom of the spec).
            self.decisions.push(ids::SERVED_EXTRA_FUNCTION);
            return Some((
                Some(Response::exception(fc, ExceptionCode::ILLEGAL_FUNCTION)),
                false,
            ));
        }
        if self.faults.has(Fault::QuantityOverSpecDropped) && quantity_over_spec(pdu) {
            return Some((None, false));
        }
        if self.faults.has(Fault::WriteQuantityOverLimitDropped)
            && self.write_quantity_over_limit(pdu)
        {
            return Some((None, false));
        }
        let low_byte;
        let pdu = if self.faults.has(Fault::QuantityLowByte) {
            low_byte = quantity_low_byte(pdu);
            &low_byte[..]
        } else {
            pdu
        };
        let req = match self
            .read_as_chosen(pdu)
            .unwrap_or_else(|| Request::decode(pdu))
        {
            Ok(req) => req,
            // Longer than the function's layout: the drive may serve what the layout's bytes ask and ignore
            // the rest (`trailing-bytes`), as the reference does once it learned the drive does.
            Err(_)
                if !self.faults.has(Fault::TrailingBytes04)
                    && self.choices.name(ids::TRAILING_BYTES) == Some("response")
                    && Request::decode_layout_prefix(pdu).is_some() =>
            {
                self.decisions.push(ids::TRAILING_BYTES);
                Request::decode_layout_prefix(pdu)?.0
            }
            Err(e) => {
                self.malformed();
                if self.dead {
                    return None;
                }
                if Request::decode_layout_prefix(pdu).is_some() {
                    if self.faults.has(Fault::TrailingBytes04) {
                        return Some((
                            Some(Response::exception(
                                fc,
                                ExceptionCode::SERVER_DEVICE_FAILURE,
                            )),
                            false,
                        ));
                    }
                    // Longer than its function's layout: 03 (the reference), no answer, or on Modbus/TCP
                    // the connection closed.
                    self.decisions.push(ids::TRAILING_BYTES);
                    // Or the layout's request served, as this drive answers it (on a copy): a read of half
                    // a register it refuses is refused so (tests/independent/lmd-g).
                    if let Some((_, extra)) = Request::decode_layout_prefix(pdu)
                        && let Some(layout) = pdu.get(..pdu.len().saturating_sub(extra))
                    {
                        let mut scratch = self.clone();
                        scratch.sink = None;
                        scratch
                            .choices
                            .set(ids::TRAILING_BYTES, FreedomValue::Text("response".into()));
                        if let Some((Some(answer), _)) = scratch.process(now, unit, fc, layout, via)
                        {
                            self.own_alternatives
                                .push((ids::TRAILING_BYTES, "response", answer));
                        }
                    }
                    match self.choices.name(ids::TRAILING_BYTES) {
                        Some("silence") => return Some((None, false)),
                        Some("close") => {
                            self.close_requested = via == Via::Tcp;
                            return Some((None, false));
                        }
                        _ => {}
                    }
                }
                // FC 0x41/0x42 whose length is wrong and whose mnemonic the drive may not know (not in the
                // profile, or one a product may lack): refused either way, and which check comes first is the
                // drive's (a drive that looks the mnemonic up first answers as to an unknown one).
                if matches!(fc.0, 0x41 | 0x42)
                    && pdu.get(1..5).is_some_and(|m| {
                        let name = codec::Mnemonic(m.try_into().unwrap_or([0; 4])).name();
                        let named = |i: &crate::requirements::Item| {
                            i.mnemonic
                                .as_deref()
                                .is_some_and(|x| x.eq_ignore_ascii_case(name.trim()))
                        };
                        let id = &self.profile().device.id;
                        let optional = crate::corpus::Corpus::Embedded
                            .requirements_shared()
                            .is_ok_and(|r| {
                                r.freedoms().iter().any(|f| {
                                    f.kind == FreedomKind::Optional
                                        && f.applies_to(id)
                                        && f.items.iter().any(named)
                                })
                            });
                        optional || self.profile().mnemonic(&name).is_none()
                    })
                {
                    self.decisions.push(ids::UNKNOWN_MNEMONIC);
                }
                if matches!(e.kind, DecodeErrorKind::Truncated { .. }) && !self.length_decided {
                    // Too short for its function code: 03 (the reference), or no answer, or on Modbus/TCP
                    // the connection closed (an RTU line has none to close: no answer there).
                    self.decisions.push(ids::TRUNCATED_PDU);
                    match self.choices.name(ids::TRUNCATED_PDU) {
                        Some("silence") => return Some((None, false)),
                        Some("close") => {
                            self.close_requested = via == Via::Tcp;
                            return Some((None, false));
                        }
                        _ => {}
                    }
                }
                // A malformed request whose address range is wrong too (a byte count off, cut short, a byte
                // more): which check comes first is the drive's (`exception-check-order`; App 4.5, Figure 9,
                // checks the address before the data value).
                let code = header_range(pdu).map_or(ExceptionCode::ILLEGAL_DATA_VALUE, |range| {
                    self.check_order(
                        now,
                        unit,
                        &range,
                        Rejection::fixed(ExceptionCode::ILLEGAL_DATA_VALUE),
                    )
                    .code
                });
                return Some((Some(Response::exception(fc, code)), false));
            }
        };
        // FC 43 with an MEI type the codec does not know (neither 0x0D nor 0x0E): which code refuses it is the
        // drive's (`unsupported-mei-type`; the reference: 01, as for a function it does not serve).
        if matches!(&req, Request::Raw { function, .. } if *function == FunctionCode::ENCAPSULATED_INTERFACE)
        {
            if self.faults.has(Fault::MeiTypeServed) {
                return Some((
                    Some(Response::exception(
                        fc,
                        ExceptionCode::SERVER_DEVICE_FAILURE,
                    )),
                    false,
                ));
            }
            self.decisions.push(ids::UNSUPPORTED_MEI_TYPE);
            let code = self
                .choices
                .code(ids::UNSUPPORTED_MEI_TYPE, ExceptionCode::ILLEGAL_FUNCTION);
            return Some((Some(Response::exception(fc, code)), false));
        }
        // A quantity above the manual's limit but within the specification's: a drive may serve it (its limit
        // is higher than its manual says, `quantity-over-device-limit-served`), or refuse it with the code
        // `quantity-over-device-limit` gives.
        let over_limit = self.over_device_limit(&req);
        let served = over_limit
            && self.choices.name(ids::QUANTITY_OVER_DEVICE_LIMIT_SERVED) == Some("response");
        if over_limit {
            self.decisions.push(ids::QUANTITY_OVER_DEVICE_LIMIT_SERVED);
        }
        // Offered where the reference refuses the quantity only: where it serves, a refusal is judged as the
        // quantity's (`outcome`), and an answer of the served path that refuses with 02 or 03 for an address
        // is the same answer either way (tests/independent/mdrive-f serves FC 03 of 5 mapped registers and
        // refuses 5 that run into reserved addresses: no change of mind).
        if over_limit && self.observed && !served {
            // The answer served, as this drive would give it (on a copy): a drive whose own
            // limit is above the manual's takes the request to the checks after the quantity's and may refuse
            // it there, for a value out of range or a read-only register (tests/independent/mdrive-g: 04 to
            // FC 16 of 3 registers from MV, its own limit 4), which no served answer shows.
            // Only where someone takes the alternatives (the copy takes none: it asks no copy of its own).
            let other = "response";
            let mut scratch = self.clone();
            scratch.sink = None;
            scratch.observed = false;
            scratch.choices.set(
                ids::QUANTITY_OVER_DEVICE_LIMIT_SERVED,
                FreedomValue::Text(other.into()),
            );
            let answer = scratch
                .process_request(now, unit, fc, pdu, via)
                .and_then(|(answer, _)| answer);
            // Where the copy refused it for a value or an access (04 for an MDrive whose own limit is 4,
            // tests/independent/mdrive-g), the code of that refusal is the drive's choice too: the reference
            // does not follow exception codes, so its copy gives its own.
            let mut made = std::mem::take(&mut scratch.decisions);
            made.extend(scratch.model.take_decisions());
            let codes: Vec<Decision> = made
                .into_iter()
                .filter(|d| {
                    [
                        ids::VALUE_OUT_OF_RANGE,
                        ids::WRITE_READ_ONLY,
                        ids::READ_WRITE_ONLY,
                    ]
                    .contains(d)
                })
                .collect();
            for d in codes {
                if !self.decisions.contains(&d) {
                    self.decisions.push(d);
                }
            }
            // Served and then refused with 02 or 03 is no other answer than a refusal of the quantity
            // (`quantity-over-device-limit` admits both: the specification's diagrams test the quantity, then
            // address + quantity, 02 where the range runs into reserved addresses), and is taken as that: offered
            // as served, an MDrive whose limit is its manual's (tests/independent/mdrive-f, 02 to FC 03 of 5
            // registers over a write-only one) was taken to serve 5 and to change its mind at the next 03.
            let as_refused = matches!(
                answer,
                Some(Response::Exception { code, .. })
                    if code == ExceptionCode::ILLEGAL_DATA_ADDRESS
                        || code == ExceptionCode::ILLEGAL_DATA_VALUE
            );
            if let Some(answer) = answer.filter(|_| !as_refused) {
                self.own_alternatives
                    .push((ids::QUANTITY_OVER_DEVICE_LIMIT_SERVED, other, answer));
            }
        }
        let resp = if let Some(e) = (!served).then(|| self.spec_checks(&req)).flatten() {
            self.decisions.extend(e.freedom);
            let e = self.check_order(now, unit, &req, e);
            Some(Response::exception(fc, e.code))
        } else if self.faults.has(Fault::ProgramAbsentSilent)
            && matches!(&req, Request::VendorWrite { mnemonic, .. } if mnemonic.name().trim() == "EX")
        {
            // Neither runs the program nor refuses it, whatever the drive chose for the item.
            None
        } else if let Some(code) = self.lacks(&req) {
            Some(Response::exception(fc, code))
        } else if let Some(r) = self.half_register_widened(&req) {
            Some(r)
        } else if let Some(code) = self.partial_read_refused(&req) {
            self.decisions.push(ids::PARTIAL_REGISTER_READ);
            Some(Response::exception(fc, code))
        } else if let Some(code) = self.multi_item_refused(&req) {
            self.decisions.push(ids::MULTI_ITEM_ACCESS);
            Some(Response::exception(fc, code))
        } else {
            // A range over several items of the map, served: the drive's choice too (`multi-item-access`).
            if self.covers_several_items(&req) {
                self.decisions.push(ids::MULTI_ITEM_ACCESS);
            }
            // Served or refused, the answer to a read inside a 32-bit register is the drive's choice (every
            // model: the SD2x's too).
            if self.splits_pair(&req) && !self.decisions.contains(&ids::PARTIAL_REGISTER_READ) {
                self.decisions.push(ids::PARTIAL_REGISTER_READ);
            }
            // And so is the answer to a write of part of one: taken (the drive's choice may be `response`)
            // or refused (the model says so by its rejection).
            if self.splits_written_pair(&req)
                && !self.decisions.contains(&ids::PARTIAL_REGISTER_WRITE)
            {
                self.decisions.push(ids::PARTIAL_REGISTER_WRITE);
            }
            match req {
                Request::Diagnostics { .. } => {
                    let d = self.diagnostics(&req, via);
                    return Some((d.resp, d.counted));
                }
                Request::GetCommEventCounter => {
                    if self.comm.cleared_by_0a {
                        self.decisions.push(ids::EVENT_COUNTER_CLEAR_COUNTED);
                    }
                    Some(Response::GetCommEventCounter {
                        status: 0,
                        event_count: self.comm.event_count,
                    })
                }
                Request::GetCommEventLog => {
                    let mut events: Vec<u8> = self.comm.events.iter().copied().collect();
                    if self.faults.has(Fault::EventLogOldestFirst) {
                        events.reverse();
                    }
                    Some(Response::GetCommEventLog {
                        status: 0,
                        event_count: self.comm.event_count,
                        message_count: self.counters.bus_message,
                        events,
                    })
                }
                _ => {
                    self.model.advance(now);
                    let before = match &req {
                        Request::ReadWriteMultipleRegisters {
                            read_address,
                            read_quantity,
                            ..
                        } if self.faults.has(Fault::ReadBeforeWrite) => self.model.handle(
                            now,
                            unit,
                            &Request::ReadHoldingRegisters {
                                address: *read_address,
                                quantity: *read_quantity,
                            },
                        ),
                        _ => None,
                    };
                    let mut resp = self.handle_model(now, unit, &req);
                    if let (
                        Some(Response::ReadHoldingRegisters { values: old }),
                        Some(Response::ReadWriteMultipleRegisters { values }),
                    ) = (before, resp.as_mut())
                    {
                        *values = old;
                    }
                    if self.faults.has(Fault::PartialWrite)
                        && resp.as_ref().is_some_and(|r| r.is_exception())
                        && let Request::WriteMultipleRegisters { address, values } = &req
                    {
                        // Register by register, as firmware that loops over the values does, up to the
                        // first one refused.
                        for (i, v) in values.iter().enumerate() {
                            let one = Request::WriteMultipleRegisters {
                                address: address.wrapping_add(i as u16),
                                values: vec![*v],
                            };
                            if self
                                .handle_model(now, unit, &one)
                                .is_none_or(|r| r.is_exception())
                            {
                                break;
                            }
                        }
                    }
                    if let Some(Response::ReportServerId { data }) = resp.as_mut() {
                        self.run_indicator(data);
                    }
                    if self.faults.has(Fault::InputBitsReversed)
                        && let (
                            Request::ReadDiscreteInputs { quantity, .. },
                            Some(Response::ReadDiscreteInputs { data }),
                        ) = (&req, resp.as_mut())
                    {
                        let n = usize::from(*quantity);
                        let bit = |d: &[u8], i: usize| {
                            d.get(i / 8).is_some_and(|b| b >> (i % 8) & 1 == 1)
                        };
                        let old = data.clone();
                        for i in 0..n.min(old.len() * 8) {
                            let on = bit(&old, n - 1 - i);
                            if let Some(b) = data.get_mut(i / 8) {
                                if on {
                                    *b |= 1 << (i % 8);
                                } else {
                                    *b &= !(1 << (i % 8));
                                }
                            }
                        }
                    }
                    if self.faults.has(Fault::BitPaddingOnes) {
                        resp.map(|r| pad_with_ones(&req, r))
                    } else {
                        resp
                    }
                }
            }
        };
        let completed = resp.as_ref().is_some_and(|r| !r.is_exception());
        Some((resp, completed))
    }

    /// FC 11's run indicator (the byte after the profile's server id): ON or OFF is the drive's state, which
    /// the spec does not fix (the freedom `run-indicator-status`).
    fn run_indicator(&mut self, data: &mut [u8]) {
        let Some(at) = self
            .profile()
            .server_id
            .as_ref()
            .map(|s| s.get_ref().id.len())
        else {
            return;
        };
        let Some(byte) = data.get_mut(at).filter(|b| matches!(**b, 0x00 | 0xFF)) else {
            return;
        };
        self.decisions.push(ids::RUN_INDICATOR_STATUS);
        match self.choices.name(ids::RUN_INDICATOR_STATUS) {
            Some("off") => *byte = 0x00,
            Some("on") => *byte = 0xFF,
            _ => {}
        }
    }

    /// A request a drive reads otherwise than the codec, by a reading it chose: with
    /// `fc42-parameterless-byte-count=no-count-byte` an FC 0x42 without a byte count is a parameterless
    /// command, and the byte count 0 of the 6-byte form is a parameter byte (which no mnemonic takes).
    fn read_as_chosen(&self, pdu: &[u8]) -> Option<Result<Request, codec::DecodeError>> {
        if self.fc43_without_reserved() {
            // The SD2x example's form (no Reserved byte): every FC 43 / MEI 0x0D request is read that way, so a
            // request in the layout's form is read one byte off, as such a drive would.
            return codec::canopen_with_reserved(pdu).map(|long| Request::decode(&long));
        }
        if self.choices.name(ids::FC42_PARAMETERLESS_BYTE_COUNT) != Some("no-count-byte") {
            return None;
        }
        match pdu {
            [0x42, m @ ..] if m.len() == 4 => Some(Ok(Request::VendorWrite {
                mnemonic: codec::Mnemonic(m.try_into().ok()?),
                params: Vec::new(),
            })),
            [0x42, m @ .., 0x00] if m.len() == 4 => Some(Ok(Request::VendorWrite {
                mnemonic: codec::Mnemonic(m.try_into().ok()?),
                params: vec![0x00],
            })),
            _ => None,
        }
    }

    /// True for a drive that follows the SD2x example's FC 43 form, without the Reserved byte (freedom
    /// `sd2x-fc43-reserved-byte`, SD2x manual lines 1302-1304 against the layout's line 545).
    fn fc43_without_reserved(&self) -> bool {
        self.choices.name(crate::models::sd2x::FC43_RESERVED_BYTE) == Some("without-reserved-byte")
    }

    /// The exception a product that lacks an item the request touches answers with (the `optional`
    /// freedoms chosen `exception-XX`), if any.
    fn lacks(&self, req: &Request) -> Option<ExceptionCode> {
        self.choices
            .defined_of(FreedomKind::Optional)
            .find_map(|(f, value)| {
                let code = Choices::exception_value(value)?;
                f.items
                    .iter()
                    .any(|item| item.touched_by(req, self.model.profile()))
                    .then_some(code)
            })
    }

    /// Under [`Fault::HalfRegisterWidened`], the answer to a read or write (FC 03, 04, 16) that covers one
    /// half of a 32-bit holding register: served as if it covered the whole pair (one register more), the
    /// write not stored. Whatever the drive's choice for the freedoms `partial-register-read/-write`.
    fn half_register_widened(&self, req: &Request) -> Option<Response> {
        if !self.faults.has(Fault::HalfRegisterWidened) {
            return None;
        }
        let splits = |address: u16, quantity: usize| {
            let quantity = u16::try_from(quantity).unwrap_or(u16::MAX);
            self.inside_pair(false, address, quantity)
        };
        match req {
            Request::ReadHoldingRegisters { address, quantity }
                if splits(*address, usize::from(*quantity)) =>
            {
                Some(Response::ReadHoldingRegisters {
                    values: vec![0; usize::from(*quantity) + 1],
                })
            }
            Request::WriteMultipleRegisters { address, values }
                if splits(*address, values.len()) =>
            {
                Some(Response::WriteMultipleRegisters {
                    address: *address,
                    quantity: values.len() as u16 + 1,
                })
            }
            _ => None,
        }
    }

    /// The exception a drive that refuses reads starting or ending inside a 32-bit register answers with
    /// (`partial-register-read` chosen `exception-XX`), when the request is such a read.
    fn partial_read_refused(&self, req: &Request) -> Option<ExceptionCode> {
        let code = Choices::exception_value(self.choices.get(ids::PARTIAL_REGISTER_READ)?)?;
        self.splits_pair(req).then_some(code)
    }

    /// The exception a drive taking one item of the register map a request answers a range over several with
    /// (`multi-item-access` chosen `exception-XX`), when `req` is such a read or write.
    fn multi_item_refused(&self, req: &Request) -> Option<ExceptionCode> {
        let code = Choices::exception_value(self.choices.get(ids::MULTI_ITEM_ACCESS)?)?;
        self.covers_several_items(req).then_some(code)
    }

    /// True when `req` (FC 03, 04, 16) covers two or more items of the register map, each completely, within
    /// the profile's quantity limit for the function, and the profile is one `multi-item-access` applies to
    /// (the manuals that say a request needs no more than one parameter).
    fn covers_several_items(&self, req: &Request) -> bool {
        let (input, address, quantity) = match req {
            Request::ReadHoldingRegisters { address, quantity } => (false, *address, *quantity),
            Request::ReadInputRegisters { address, quantity } => (true, *address, *quantity),
            Request::WriteMultipleRegisters { address, values } => (
                false,
                *address,
                u16::try_from(values.len()).unwrap_or(u16::MAX),
            ),
            _ => return false,
        };
        let profile = self.model.profile();
        // Within the device's quantity limit: a quantity over it is `quantity-over-device-limit`'s.
        let limit = profile
            .function(req.function())
            .and_then(|f| f.max_quantity)
            .unwrap_or(u16::MAX);
        if quantity < 2 || quantity > limit {
            return false;
        }
        if !crate::corpus::Corpus::Embedded
            .freedom_applies(ids::MULTI_ITEM_ACCESS, &profile.device.id)
        {
            return false;
        }
        let end = u32::from(address) + u32::from(quantity);
        let (mut a, mut items) = (u32::from(address), 0);
        while a < end {
            let Some(r) = u16::try_from(a)
                .ok()
                .and_then(|a| profile.register_at(a, input))
            else {
                return false;
            };
            let r_end = u32::from(r.address) + u32::from(r.width);
            if u32::from(r.address) != a || r_end > end {
                return false;
            }
            items += 1;
            a = r_end;
        }
        items > 1
    }

    /// True when `req` reads (FC 03, 04, 23) a range that starts or ends inside a 32-bit register.
    fn splits_pair(&self, req: &Request) -> bool {
        let (input, address, quantity) = match req {
            Request::ReadHoldingRegisters { address, quantity } => (false, *address, *quantity),
            Request::ReadInputRegisters { address, quantity } => (true, *address, *quantity),
            Request::ReadWriteMultipleRegisters {
                read_address,
                read_quantity,
                ..
            } => (false, *read_address, *read_quantity),
            _ => return false,
        };
        self.inside_pair(input, address, quantity)
    }

    /// Whether a write covers one half of a 32-bit holding register only (see [`Station::splits_pair`]).
    fn splits_written_pair(&self, req: &Request) -> bool {
        crate::requirements::registers_written(req)
            .is_some_and(|(address, quantity)| self.inside_pair(false, address, quantity))
    }

    /// Whether the range `address`, `quantity` of the input (or holding) registers starts or ends inside a
    /// 32-bit register.
    fn inside_pair(&self, input: bool, address: u16, quantity: u16) -> bool {
        let profile = self.model.profile();
        let inside = |a: u32| {
            u16::try_from(a).ok().is_some_and(|a| {
                profile
                    .register_at(a, input)
                    .is_some_and(|r| r.width == 2 && r.address != a)
            })
        };
        let end = u32::from(address) + u32::from(quantity);
        quantity > 0 && (inside(u32::from(address)) || inside(end))
    }

    /// `Fault::WriteQuantityOverLimitDropped`: whether the PDU, as sent, is an FC 17 whose quantity to write
    /// is above the profile's own limit and within the specification's 121.
    fn write_quantity_over_limit(&self, pdu: &[u8]) -> bool {
        let fc = FunctionCode::READ_WRITE_MULTIPLE_REGISTERS;
        let spec = FunctionCode::MAX_READ_WRITE_WRITE_QUANTITY;
        let Some(limit) = self
            .profile()
            .function(fc)
            .and_then(|f| f.max_write_quantity)
        else {
            return false;
        };
        pdu.first() == Some(&fc.0)
            && pdu
                .get(7..9)
                .map(|b| u16::from_be_bytes([b[0], b[1]]))
                .is_some_and(|m| m > limit && m <= spec)
    }

    /// True when `req`'s quantity (or FC 23's quantity to write) is above the profile's limit for its function
    /// but within the specification's: the manual's limit, which a drive may not enforce.
    fn over_device_limit(&self, req: &Request) -> bool {
        if self.faults.has(Fault::QuantityUnchecked) {
            return false;
        }
        let over = |q: usize, device: Option<u16>, spec: Option<u16>| {
            let spec = usize::from(spec.unwrap_or(u16::MAX));
            let device = device.map_or(spec, usize::from);
            q > 0 && q > device && q <= spec
        };
        let limit = |fc: FunctionCode| self.profile().function(fc).and_then(|f| f.max_quantity);
        quantity_asked(req).is_some_and(|(fc, q)| over(q, limit(fc), fc.max_quantity()))
    }

    /// Quantity limits and FC 05 values, per the application protocol spec's state diagrams.
    fn spec_checks(&self, req: &Request) -> Option<Rejection> {
        if self.faults.has(Fault::QuantityUnchecked) {
            return self.coil_value_check(req);
        }
        let profile_limit =
            |fc: FunctionCode| self.profile().function(fc).and_then(|f| f.max_quantity);
        // 03 outside the spec's range; outside the device's own (stricter) limit, the code is a freedom.
        let check = |q: u16, fc: FunctionCode, spec: Option<u16>| {
            let spec = spec.unwrap_or(u16::MAX);
            let device = profile_limit(fc).unwrap_or(spec);
            if q == 0 || q > spec.max(device) {
                Some(Rejection::fixed(ExceptionCode::ILLEGAL_DATA_VALUE))
            } else if q > device {
                Some(self.choices.reject(
                    ids::QUANTITY_OVER_DEVICE_LIMIT,
                    ExceptionCode::ILLEGAL_DATA_VALUE,
                ))
            } else {
                None
            }
        };
        if let Some((fc, q)) = quantity_asked(req) {
            return check(u16::try_from(q).unwrap_or(u16::MAX), fc, fc.max_quantity());
        }
        use Request::*;
        match req {
            ReadWriteMultipleRegisters {
                read_quantity,
                values,
                ..
            } => {
                let fc = FunctionCode::READ_WRITE_MULTIPLE_REGISTERS;
                let wmax = self
                    .profile()
                    .function(fc)
                    .and_then(|f| f.max_write_quantity)
                    .unwrap_or(FunctionCode::MAX_READ_WRITE_WRITE_QUANTITY);
                // The quantity to write as the others: 03 outside the specification's 1..=121, and above
                // the device's own limit only, the code is `quantity-over-device-limit`'s.
                let spec_w = FunctionCode::MAX_READ_WRITE_WRITE_QUANTITY;
                check(*read_quantity, fc, fc.max_quantity()).or_else(|| {
                    let m = values.len();
                    if m == 0 || m > usize::from(spec_w.max(wmax)) {
                        Some(Rejection::fixed(ExceptionCode::ILLEGAL_DATA_VALUE))
                    } else if m > usize::from(wmax) {
                        Some(self.choices.reject(
                            ids::QUANTITY_OVER_DEVICE_LIMIT,
                            ExceptionCode::ILLEGAL_DATA_VALUE,
                        ))
                    } else {
                        None
                    }
                })
            }
            _ => self.coil_value_check(req),
        }
    }

    /// A quantity refused (03) by [`Station::spec_checks`] for a read (FC 01-04) or a multiple write (FC 0F,
    /// 10), or an FC 05 value refused (03), whose starting address or last address is not valid either: the state diagrams of section 6
    /// check the quantity first (03, the reference), the transaction diagram of 4.5 the address first (02);
    /// `exception-check-order` decides. The address is probed on a copy of the model with a one-item read
    /// of the table at each end of the range (for a write too: an item the model refuses to read, as a
    /// write-only one, then counts as an invalid address).
    fn check_order(
        &mut self,
        now: Duration,
        unit: u8,
        req: &Request,
        rejection: Rejection,
    ) -> Rejection {
        // A quantity within the specification's range but above the device's own limit is the freedom
        // `quantity-over-device-limit`'s (its condition has the range run past the map too): only a
        // quantity outside the specification's range is this one's.
        if rejection != Rejection::fixed(ExceptionCode::ILLEGAL_DATA_VALUE) {
            return rejection;
        }
        let one = |address: u16| -> Request {
            match req {
                Request::ReadCoils { .. }
                | Request::WriteMultipleCoils { .. }
                | Request::WriteSingleCoil { .. } => Request::ReadCoils {
                    address,
                    quantity: 1,
                },
                Request::ReadDiscreteInputs { .. } => Request::ReadDiscreteInputs {
                    address,
                    quantity: 1,
                },
                Request::ReadHoldingRegisters { .. }
                | Request::WriteMultipleRegisters { .. }
                | Request::ReadWriteMultipleRegisters { .. } => Request::ReadHoldingRegisters {
                    address,
                    quantity: 1,
                },
                _ => Request::ReadInputRegisters {
                    address,
                    quantity: 1,
                },
            }
        };
        let count = |values: &Vec<u16>| u16::try_from(values.len()).unwrap_or(u16::MAX);
        // FC 23 carries two ranges (spec 6.17): a quantity wrong in either and an address wrong in either
        // leave the order of the checks to the drive as for the other functions.
        let ranges: Vec<(u16, u16)> = match req {
            Request::ReadCoils { address, quantity }
            | Request::ReadDiscreteInputs { address, quantity }
            | Request::ReadHoldingRegisters { address, quantity }
            | Request::ReadInputRegisters { address, quantity }
            | Request::WriteMultipleCoils {
                address, quantity, ..
            } => vec![(*address, *quantity)],
            Request::WriteMultipleRegisters { address, values } => vec![(*address, count(values))],
            // FC 05 with a value other than 0xFF00 or 0x0000 (6.5's diagram tests it before the address).
            Request::WriteSingleCoil { address, .. } => vec![(*address, 1)],
            Request::ReadWriteMultipleRegisters {
                read_address,
                read_quantity,
                write_address,
                values,
            } => vec![
                (*read_address, *read_quantity),
                (*write_address, count(values)),
            ],
            _ => return rejection,
        };
        let mut scratch = self.model.clone();
        let mut invalid = |a: u16| {
            scratch.handle(now, unit, &one(a)).is_some_and(|r| {
                matches!(r, Response::Exception { code, .. } if code == ExceptionCode::ILLEGAL_DATA_ADDRESS)
            })
        };
        let address_wrong = ranges.into_iter().any(|(address, quantity)| {
            let last = u32::from(address) + u32::from(quantity.max(1)) - 1;
            invalid(address) || u16::try_from(last).map_or(true, &mut invalid)
        });
        if !address_wrong {
            return rejection;
        }
        self.decisions.push(ids::EXCEPTION_CHECK_ORDER);
        match self.choices.code(
            ids::EXCEPTION_CHECK_ORDER,
            ExceptionCode::ILLEGAL_DATA_VALUE,
        ) {
            ExceptionCode::ILLEGAL_DATA_ADDRESS => Rejection::by(
                ids::EXCEPTION_CHECK_ORDER,
                ExceptionCode::ILLEGAL_DATA_ADDRESS,
            ),
            _ => rejection,
        }
    }

    /// FC 05 takes 0xFF00 or 0x0000 only (spec 6.5): 03 for anything else.
    fn coil_value_check(&self, req: &Request) -> Option<Rejection> {
        match req {
            Request::WriteSingleCoil { value, .. }
                if *value != 0xFF00
                    && *value != 0
                    && !self.faults.has(Fault::IllegalCoilValueAccepted) =>
            {
                Some(Rejection::fixed(ExceptionCode::ILLEGAL_DATA_VALUE))
            }
            _ => None,
        }
    }

    /// FC 08 for the sub-functions the profile lists (spec 6.8.1, figure 18): an unlisted sub-function, or a
    /// serial-port one on Modbus/TCP, is exception 01; a data field of the wrong length (or, with
    /// `check_data`, of the wrong value) is 03.
    fn diagnostics(&mut self, req: &Request, via: Via) -> DiagOutcome {
        let exc = |code| DiagOutcome::reply(Response::exception(FunctionCode::DIAGNOSTICS, code));
        let Request::Diagnostics { sub_function, data } = req else {
            return exc(ExceptionCode::ILLEGAL_FUNCTION);
        };
        // A data field of another size than the manual fixes for every FC 08 telegram (the size of 00's):
        // answered as 6.8.1 has it (00 echoes any data, a counter's is refused with 03, an unlisted
        // sub-function with 01), refused with 03 whatever the sub-function, or not taken for a telegram
        // (`sd2x-diagnostic-data-size`).
        let fixed = self
            .profile()
            .diagnostic(diag::RETURN_QUERY_DATA)
            .and_then(|d| d.data_bytes)
            .map(usize::from);
        if let Some(n) = fixed.filter(|n| data.len() != *n) {
            if self.faults.has(Fault::QueryDataCut) && *sub_function == diag::RETURN_QUERY_DATA {
                let mut cut = data.clone();
                cut.resize(n, 0);
                return DiagOutcome::reply(Response::Diagnostics {
                    sub_function: *sub_function,
                    data: cut,
                });
            }
            self.decisions.push(ids::SD2X_DIAGNOSTIC_DATA_SIZE);
            match self.choices.name(ids::SD2X_DIAGNOSTIC_DATA_SIZE) {
                // A sub-function the profile does not list: the size first (03) or, as 6.8's diagram
                // orders the checks, the sub-function (01): `sd2x-diagnostic-check-order`.
                Some("exception-03") if self.profile().diagnostic(*sub_function).is_none() => {
                    self.decisions.push(ids::SD2X_DIAGNOSTIC_CHECK_ORDER);
                    return exc(self.choices.code(
                        ids::SD2X_DIAGNOSTIC_CHECK_ORDER,
                        ExceptionCode::ILLEGAL_DATA_VALUE,
                    ));
                }
                Some("exception-03") => return exc(ExceptionCode::ILLEGAL_DATA_VALUE),
                Some("silence") => {
                    return DiagOutcome {
                        resp: None,
                        counted: false,
                    };
                }
                _ => {}
            }
        }
        let Some((d, check_data)) = self
            .profile()
            .diagnostic(*sub_function)
            .map(|d| (d.counter, d.check_data))
        else {
            return exc(ExceptionCode::ILLEGAL_FUNCTION);
        };
        if via == Via::Tcp && d.serial_line_only() {
            return exc(ExceptionCode::ILLEGAL_FUNCTION);
        }
        if d != DiagCounter::Echo && data.len() != 2 {
            return exc(ExceptionCode::ILLEGAL_DATA_VALUE);
        }
        if !diag_data_ok(d, data) {
            if check_data {
                return exc(ExceptionCode::ILLEGAL_DATA_VALUE);
            }
            // Data the manual does not use, where 6.8.1 gives 00 00: ignored or refused
            // (`sd2x-diagnostic-unused-data`).
            if self.faults.has(Fault::UnusedDiagDataRefused02) {
                return exc(ExceptionCode::ILLEGAL_DATA_ADDRESS);
            }
            self.decisions.push(ids::SD2X_DIAGNOSTIC_UNUSED_DATA);
            let refuse = if self.faults.has(Fault::UnusedDiagDataInconsistent) {
                *sub_function != diag::BUS_MESSAGE_COUNT
            } else {
                self.choices.name(ids::SD2X_DIAGNOSTIC_UNUSED_DATA) == Some("exception-03")
            };
            if refuse {
                return exc(ExceptionCode::ILLEGAL_DATA_VALUE);
            }
        }
        let echo = || {
            DiagOutcome::reply(Response::Diagnostics {
                sub_function: *sub_function,
                data: data.clone(),
            })
        };
        let c = self.counters;
        let value = match d {
            DiagCounter::Echo => return echo(),
            DiagCounter::Clear => {
                // "Clear Counters and Diagnostic Register"; the event counter too (spec 6.9).
                self.counters = Counters::default();
                self.comm.event_count = 0;
                self.comm.diagnostic_register = 0;
                self.comm.cleared_by_0a = true;
                // Whether the clearing request then counts as a completion, the spec leaves open.
                let counted = self
                    .choices
                    .name(ids::EVENT_COUNTER_CLEAR_COUNTED)
                    .is_some_and(|v| v == "counted");
                return DiagOutcome { counted, ..echo() };
            }
            DiagCounter::Restart => {
                // The normal response goes out before the restart is executed.
                self.pending_restart = Some(data[..] == diag::RESTART_CLEAR_LOG.to_be_bytes());
                return echo();
            }
            DiagCounter::AsciiDelimiter => {
                self.comm.ascii_delimiter = data.first().copied().unwrap_or(b'\n');
                return echo();
            }
            DiagCounter::ListenOnly => {
                if self.faults.has(Fault::ListenOnlyIgnored) {
                    return echo();
                }
                // No response; the mode starts now (event 04, spec 6.10).
                self.comm.listen_only = true;
                self.log_event(event::ENTERED_LISTEN_ONLY);
                return DiagOutcome {
                    resp: None,
                    counted: true,
                };
            }
            DiagCounter::ClearOverrun => {
                self.counters.overrun = 0;
                self.comm.overrun_flag = false;
                return echo();
            }
            DiagCounter::DiagnosticRegister => self.comm.diagnostic_register,
            DiagCounter::BusMessage | DiagCounter::SlaveMessage | DiagCounter::NoResponse => {
                // What these count, the sources say several ways: the drive's reading decides.
                let sub = *sub_function;
                let standard = counter_semantics::value(counter_semantics::STANDARD, sub, &c)
                    .unwrap_or_default();
                let others = counter_semantics::alternatives(sub, &c);
                let reading = self
                    .choices
                    .name(ids::DIAGNOSTIC_COUNTER_SEMANTICS)
                    .filter(|s| counter_semantics::value(s, sub, &c).is_some())
                    .unwrap_or(counter_semantics::STANDARD);
                let mine = counter_semantics::value(reading, sub, &c).unwrap_or(standard);
                if !others.is_empty() {
                    // Every other reading about this counter, those giving this drive's value too: a value
                    // two readings give shows neither.
                    self.decisions.push(ids::DIAGNOSTIC_COUNTER_SEMANTICS);
                    self.counter_alternatives.extend(
                        std::iter::once(counter_semantics::STANDARD)
                            .chain(counter_semantics::OTHERS.iter().copied())
                            .filter(|s| *s != reading)
                            .filter_map(|s| {
                                counter_semantics::value(s, sub, &c).map(|v| (sub, s, v))
                            }),
                    );
                }
                mine
            }
            DiagCounter::CrcError => c.crc_error,
            DiagCounter::Exception => c.exception,
            DiagCounter::Nak => c.nak,
            DiagCounter::Busy => c.busy,
            DiagCounter::Overrun => c.overrun,
        };
        DiagOutcome::reply(Response::Diagnostics {
            sub_function: *sub_function,
            data: value.to_be_bytes().to_vec(),
        })
    }
}

/// The request data field section 6.8.1 gives a sub-function: any for 00, 00 00 or FF 00 for 01 (FF 00 also
/// clears the event log), CHAR 00 for 03, 00 00 for the others.
fn diag_data_ok(d: DiagCounter, data: &[u8]) -> bool {
    match d {
        DiagCounter::Echo => true,
        DiagCounter::Restart => data == [0x00, 0x00] || data == [0xFF, 0x00],
        DiagCounter::AsciiDelimiter => matches!(data, [_, 0x00]),
        _ => data == [0x00, 0x00],
    }
}

/// `Fault::QuantityOverSpecDropped`: whether a quantity field of the PDU, as sent, is above the
/// specification's maximum for its function (FC 01-04, 0F, 10; FC 17's quantities to read and to write).
fn quantity_over_spec(pdu: &[u8]) -> bool {
    let field = |at: usize| {
        pdu.get(at..at + 2)
            .map(|b| u16::from_be_bytes([b[0], b[1]]))
    };
    let Some(&fc) = pdu.first() else {
        return false;
    };
    let over = |at: usize, max: Option<u16>| field(at).zip(max).is_some_and(|(q, max)| q > max);
    match fc {
        0x01..=0x04 | 0x0F | 0x10 => over(3, FunctionCode(fc).max_quantity()),
        0x17 => {
            over(3, FunctionCode(fc).max_quantity())
                || over(7, Some(FunctionCode::MAX_READ_WRITE_WRITE_QUANTITY))
        }
        _ => false,
    }
}

/// `Fault::QuantityLowByte`: the PDU as firmware that reads each quantity field by its low byte sees it, the
/// high byte taken as 0 (FC 01-04, 0F, 10 at offset 3; FC 17's quantities to read and to write at 3 and 7).
fn quantity_low_byte(pdu: &[u8]) -> Vec<u8> {
    let mut v = pdu.to_vec();
    let high_bytes: &[usize] = match pdu.first() {
        Some(0x01..=0x04 | 0x0F | 0x10) => &[3],
        Some(0x17) => &[3, 7],
        _ => &[],
    };
    for &at in high_bytes {
        if let Some(b) = v.get_mut(at) {
            *b = 0;
        }
    }
    v
}

/// `Fault::BitPaddingOnes`: the bits of an FC 01/02 answer past the quantity asked for set to 1 (spec 6.1,
/// 6.2: they are padded with zeros).
fn pad_with_ones(req: &Request, resp: Response) -> Response {
    let quantity = match req {
        Request::ReadCoils { quantity, .. } | Request::ReadDiscreteInputs { quantity, .. } => {
            *quantity
        }
        _ => return resp,
    };
    let used = quantity % 8;
    let pad = |mut data: Vec<u8>| {
        if let Some(last) = data.last_mut()
            && used != 0
        {
            *last |= 0xFFu8 << used;
        }
        data
    };
    match resp {
        Response::ReadCoils { data } => Response::ReadCoils { data: pad(data) },
        Response::ReadDiscreteInputs { data } => Response::ReadDiscreteInputs { data: pad(data) },
        other => other,
    }
}

/// True for the public functions that write the data model (FC 05, 06, 0F, 10, 15, 16, 17): the writing
/// commands a broadcast carries (serial line spec 2.1).
fn writes_data_model(fc: u8) -> bool {
    matches!(fc, 0x05 | 0x06 | 0x0F | 0x10 | 0x15 | 0x16 | 0x17)
}

/// The range a malformed FC 01-04, 0F or 10 request names in its header (address and quantity, the first five
/// bytes), as the read of that range whose ends the station probes ([`Station::check_order`]); `None` where
/// the header is cut or the function has no range.
fn header_range(pdu: &[u8]) -> Option<Request> {
    let be16 = |at: usize| Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?]));
    let (address, quantity) = (be16(1)?, be16(3)?);
    Some(match pdu.first()? {
        0x01 | 0x0F => Request::ReadCoils { address, quantity },
        0x02 => Request::ReadDiscreteInputs { address, quantity },
        0x03 | 0x10 => Request::ReadHoldingRegisters { address, quantity },
        0x04 => Request::ReadInputRegisters { address, quantity },
        _ => return None,
    })
}

/// False when the RTU frame of `pdu` to `unit` is not as long as the request length rules of its function code
/// (App 6, the byte counts included) make it: shorter than they need, or of another length. True where no rule
/// sizes the function code (silence ends such a frame), and for FC 08. `listed`: the profile lists the function
/// code; the MDrive's vendor functions 0x41 and 0x42 are sized only where it does, since a drive of another
/// vendor knows no layout for them (a CRC scan or silence ends such a frame, and the drive answers 01).
fn rtu_length_agrees(unit: u8, pdu: &[u8], listed: bool) -> bool {
    match pdu.first() {
        // FC 08's Return Query Data loops back data of any size (App 6.8.1): no rule sizes it.
        Some(0x08) => return true,
        Some(0x41 | 0x42) if !listed => return true,
        _ => {}
    }
    let agrees = |pdu: &[u8]| {
        let mut adu = Vec::with_capacity(pdu.len() + 3);
        adu.push(unit);
        adu.extend_from_slice(pdu);
        adu.extend_from_slice(&[0, 0]);
        match codec::framer::expected_len(Direction::Request, &adu, &[]) {
            codec::FrameLen::Known(a, b) => a == adu.len() || b == adu.len(),
            codec::FrameLen::NeedMore => false,
            codec::FrameLen::Unknown => true,
        }
    };
    // The SD2x's FC 43 in the form its example prints, without the Reserved byte (`sd2x-fc43-reserved-byte`):
    // as long as the layout's form with that byte put back.
    let example_form = pdu.starts_with(&[0x2B, 0x0D]) && pdu.len() > 3 && {
        let mut layout = pdu[..3].to_vec();
        layout.push(0);
        layout.extend_from_slice(&pdu[3..]);
        agrees(&layout)
    };
    agrees(pdu) || example_form
}
