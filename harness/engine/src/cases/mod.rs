//! Test cases: stable ids tied to spec sections, the requirement they check, their steps and tags.

pub mod catalog;
pub mod generated;
pub mod regressions;
pub mod safety;
pub mod shrink;

use std::collections::BTreeSet;
use std::fmt;
use std::time::Duration;

use serde::{Deserialize, Serialize};

/// A tag that the safety policy acts on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Tag {
    /// The case writes to the drive.
    Write,
    /// The case can move the motor or enable the power stage.
    Motion,
    /// The case changes non-volatile state, resets the drive, or leaves it faulted.
    Destructive,
    /// The case needs a transport feature (e.g. TCP segments, RTU silences) and is skipped on others.
    TcpOnly,
    RtuOnly,
    /// The case leaves the drive in a state that no later case can undo and that later cases would see (the
    /// stored program cleared, firmware-upgrade mode): it runs after every other case, in catalog order, also
    /// with `--shuffle`.
    Irreversible,
    /// The case judges what the whole run measured so far (the silence before every RTU answer, see
    /// [`crate::timing`]): it runs after the other cases (before the irreversible ones), also with `--shuffle`.
    RunTiming,
}

/// How a response is compared with what the reference model answers.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Compare {
    /// Byte for byte (after framing): deterministic values.
    Exact,
    /// Same function code, same exception code if any, same byte counts/lengths; data values free.
    Structure,
    /// As `Structure`, and each register value of the response lies within the profile's range.
    InRange,
    /// As `Structure`, and each register value of the response (a 32-bit register of the profile as one
    /// value, in the drive's word order, signed where the profile says) lies within `tolerance` of the
    /// reference's: a value the drive measures (an actual speed, an encoder count on a drive with its motor
    /// attached), which jitters by a few counts where the reference reads it exact.
    Near { tolerance: u32 },
    /// Anything but silence or a malformed frame (informational reads).
    Any,
    /// The request is invalid: it may be rejected with the reference's exception, ignored (silence), or,
    /// on TCP, end the connection; it must never be answered as a valid request.
    RejectOrIgnore,
}

/// How the bytes of a step are put on the wire.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Outgoing {
    /// A PDU, framed for the target's transport with the run's unit id (and a fresh transaction id).
    Pdu(Vec<u8>),
    /// A PDU framed with a specific unit id / slave address.
    PduToUnit { pdu: Vec<u8>, unit: u8 },
    /// A PDU framed, then altered on purpose; the pcap marks these frames as malformed by intent.
    Mutated { pdu: Vec<u8>, mutation: Mutation },
    /// Several PDUs framed and sent in one write (pipelining / one TCP segment).
    Batch(Vec<Vec<u8>>),
    /// Restore registers captured by an earlier step into `slot` with FC 16 at `address` (FC 06 for one
    /// register when the profile has no FC 16); a captured coil with FC 05 at `address`.
    Restore { address: u16, slot: usize },
    /// Write back what an earlier step captured into `slot`, where it was read from: registers with FC 16
    /// (FC 06), coils with FC 05 / FC 15, a vendor setting read with FC 0x41 with FC 0x42 (`=` and its
    /// values), an FC 43 object with an FC 43 write. See [`crate::capture`].
    RestoreRead { slot: usize },
}

/// A deliberate alteration of a request: of the framed bytes, or (the PDU-level ones, see
/// [`Mutation::apply_to_pdu`]) of the PDU before it is framed with a correct header and CRC.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mutation {
    /// Modbus/TCP: protocol id set to this value.
    ProtocolId(u16),
    /// Modbus/TCP: MBAP length field changed by this amount.
    LengthDelta(i16),
    /// RTU: CRC inverted.
    BadCrc,
    /// Send the frame in two writes, split after this many bytes, with this gap between.
    Split { at: usize, gap_us: u64 },
    /// PDU: invert bit `bit` (bit 0 = most significant bit of the function code; wraps at the PDU's end).
    BitFlip { bit: usize },
    /// PDU: keep only the first `len` bytes.
    Truncate { len: usize },
    /// PDU: append these bytes.
    Extend(Vec<u8>),
    /// PDU: set byte `at` to `value` (a function-code swap, a byte count that disagrees); no-op past the end.
    SetByte { at: usize, value: u8 },
}

impl Mutation {
    /// The altered PDU for a PDU-level mutation; `None` for those that act on the framed bytes.
    pub fn apply_to_pdu(&self, pdu: &[u8]) -> Option<Vec<u8>> {
        let mut out = pdu.to_vec();
        match self {
            Mutation::BitFlip { bit } => {
                if !out.is_empty() {
                    let bit = bit % (out.len() * 8);
                    out[bit / 8] ^= 0x80 >> (bit % 8);
                }
            }
            Mutation::Truncate { len } => out.truncate(*len),
            Mutation::Extend(extra) => out.extend_from_slice(extra),
            Mutation::SetByte { at, value } => {
                if let Some(b) = out.get_mut(*at) {
                    *b = *value;
                }
            }
            Mutation::ProtocolId(_)
            | Mutation::LengthDelta(_)
            | Mutation::BadCrc
            | Mutation::Split { .. } => return None,
        }
        Some(out)
    }
}

/// One step of a case.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Step {
    /// Send and observe the answer(s); compare with the reference model.
    Exchange {
        send: Outgoing,
        compare: Compare,
        /// Keep what the response read (registers, coils, a vendor setting, an object) in this slot, for
        /// `Outgoing::Restore`, `Outgoing::RestoreRead` and `Step::Agree`.
        capture: Option<usize>,
        /// What this step is about, for the report.
        note: String,
    },
    /// Let time pass (virtual on `sim:`, real elsewhere) with the line idle.
    Wait(Duration),
    /// Read one register with `read` (FC 03 or 04 of one register) every `every` until it reads `value` in
    /// the bits of `mask`, for at most `within`: a drive that may still be moving (a homing its manual leaves
    /// it free to start) is given the time to come to rest before the case goes on and puts back what it
    /// changed. The reads reach the reference too, as every request does, and are judged as a structure; when
    /// the register never reads `value` the step gets the verdict `timeout` (FAIL where the case would go on
    /// with the axis moving; INFORMATIONAL where the manual leaves it open whether the drive reports the end).
    ///
    /// Where the value never comes and `stop` is not empty, the requests of `stop` are sent (each judged as a
    /// structure) and the register is read again for `within` more: a move that does not end by itself is
    /// stopped before the case puts anything back, and the step keeps its `timeout` verdict.
    Until {
        read: Vec<u8>,
        mask: u16,
        value: u16,
        timeout: Verdict,
        stop: Vec<Vec<u8>>,
        every: Duration,
        within: Duration,
        note: String,
    },
    /// Send `send` (a command a drive may refuse while it is busy: a move while it calibrates or still moves)
    /// and, while the drive answers exception 04 (server device failure) or 06 (server device busy) where the
    /// reference takes the request, wait `every` and send it again, `within` at most: a refused request
    /// changed nothing, and the manuals leave a drive free to refuse a move it cannot start now. The
    /// reference is put back to where it was before each refused attempt. The last answer is judged as an
    /// [`Step::Exchange`] with `compare` would judge it.
    Persist {
        send: Outgoing,
        compare: Compare,
        every: Duration,
        within: Duration,
        note: String,
    },
    /// Close and reopen the connection.
    Reconnect,
    /// The 32-bit value captured as a register pair (in the profile's word order) in slot `registers`
    /// equals the FC 43 object value (little-endian) captured in slot `object`; or the registers of slot
    /// `registers` and then of slots `more_registers` (each read alone: a drive may take one item a request)
    /// mirror the discrete inputs captured in slot `object`, one each.
    Agree {
        registers: usize,
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        more_registers: Vec<usize>,
        object: usize,
        note: String,
    },
    /// The FC 0C event log captured in slot `after` is the one captured in slot `before` with at most
    /// `max_new` events entered in front of it (spec 6.10: byte 0 is the most recent event, each new byte
    /// flushes the oldest): `after[n..] == before[..after.len() - n]` for some `n <= max_new`, the log no
    /// shorter than before and no longer than 64 bytes or `before.len() + n`. Which events and how many were
    /// entered (none at all, where the device logs no Modbus/TCP traffic) is the device's.
    EventLogShifted {
        before: usize,
        after: usize,
        max_new: usize,
        note: String,
    },
    /// The error record captured in slot `record` (read right after the write of 0 that clears it) reads 0,
    /// or the error flag captured in slot `flag` reads non-zero: an error condition still exists, and the
    /// drive may record it again at once (MCode ER, "must be read or set to 0 to clear", and EF, "indicates
    /// whether an error condition exists": MDrive lines 1045-1047, LMD 2075-2087). A record that survives its
    /// clear while the flag says no error exists fails.
    ClearedUnlessFlagged {
        record: usize,
        flag: usize,
        note: String,
    },
}

/// A conformance case.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct Case {
    /// Stable id: `suite/section/name`.
    pub id: String,
    /// What the case is, in a few words.
    pub title: String,
    /// Spec or manual reference (document and section).
    pub reference: String,
    /// The requirement sentence the case checks.
    pub requirement: String,
    /// The level of the requirement: a broken SHOULD is NON-STRICT, a broken MUST a FAIL.
    pub level: Level,
    pub tags: Vec<Tag>,
    pub steps: Vec<Step>,
    /// The requirement ids the case checks (`corpus/requirements/cases.toml`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub requirements: Vec<String>,
    /// The freedoms the case allows beyond those its answers are decided by.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub freedoms: Vec<String>,
}

/// Strength of a requirement.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum Level {
    Must,
    Should,
    /// Recorded, never failing (e.g. what a drive answers to an optional unit id).
    Info,
}

impl Case {
    /// True if the case carries `tag`.
    pub fn has(&self, tag: Tag) -> bool {
        self.tags.contains(&tag)
    }

    /// The safety classifier's rating of every request the case sends ([`crate::cases::safety::classify`]): fixed
    /// requests as they go on the wire (PDU-level mutations applied, to their unit), restores as the write of
    /// what their capture step read.
    pub fn rated(&self, p: &drives::profile::Profile, run_unit: u8) -> BTreeSet<Tag> {
        use crate::cases::safety::classify_to_unit;
        let mut out = BTreeSet::new();
        for (pdu, unit) in self.wire_pdus(p, run_unit) {
            out.extend(classify_to_unit(p, &pdu, unit, run_unit));
        }
        out
    }

    /// Every request PDU the case sends, with its unit: fixed requests as they go on the wire (PDU-level
    /// mutations applied, every request of a batch), restores as the write of what their capture step read.
    pub fn wire_pdus(&self, p: &drives::profile::Profile, run_unit: u8) -> Vec<(Vec<u8>, u8)> {
        let mut captures: Vec<Option<&[u8]>> = vec![None; self.slots()];
        let mut pdus: Vec<(Vec<u8>, u8)> = Vec::new();
        for step in &self.steps {
            let (send, capture) = match step {
                Step::Exchange { send, capture, .. } => (send, capture),
                Step::Persist { send, .. } => (send, &None),
                _ => continue,
            };
            match send {
                Outgoing::Pdu(pdu) => pdus.push((pdu.clone(), run_unit)),
                Outgoing::PduToUnit { pdu, unit } => pdus.push((pdu.clone(), *unit)),
                Outgoing::Mutated { pdu, mutation } => {
                    let altered = mutation.apply_to_pdu(pdu).unwrap_or_else(|| pdu.clone());
                    pdus.push((altered, run_unit));
                }
                Outgoing::Batch(ps) => pdus.extend(ps.iter().map(|p| (p.clone(), run_unit))),
                Outgoing::Restore { address, slot } => {
                    if let Some(w) = restore_of(captures.get(*slot), Some(*address), p) {
                        pdus.push((w, run_unit));
                    }
                }
                Outgoing::RestoreRead { slot } => {
                    if let Some(w) = restore_of(captures.get(*slot), None, p) {
                        pdus.push((w, run_unit));
                    }
                }
            }
            if let (Some(c), Step::Exchange { send, .. }) = (capture, step)
                && let Some(slot) = captures.get_mut(*c)
                && let Outgoing::Pdu(pdu) | Outgoing::PduToUnit { pdu, .. } = send
            {
                *slot = Some(pdu.as_slice());
            }
        }
        pdus
    }

    /// The case with the classifier's rating of its own bytes added to its tags (never removing one).
    pub fn retagged(mut self, p: &drives::profile::Profile, run_unit: u8) -> Self {
        for t in self.rated(p, run_unit) {
            if !self.tags.contains(&t) {
                self.tags.push(t);
            }
        }
        self
    }

    /// The case with its safety tags (`write`, `motion`, `destructive`) exactly the classifier's rating of its
    /// own bytes: what the catalog and the regressions carry, whatever their authors wrote.
    pub fn classified(mut self, p: &drives::profile::Profile, run_unit: u8) -> Self {
        let rated = self.rated(p, run_unit);
        self.tags
            .retain(|t| !matches!(t, Tag::Write | Tag::Motion | Tag::Destructive));
        self.tags.extend(rated);
        self
    }

    /// How many capture slots the case uses: one more than the highest it names, 0 for none.
    pub fn slots(&self) -> usize {
        self.steps
            .iter()
            .filter_map(|s| match s {
                Step::Exchange {
                    capture: Some(c), ..
                } => Some(c + 1),
                Step::Agree {
                    registers,
                    more_registers,
                    object,
                    ..
                } => more_registers
                    .iter()
                    .fold(*registers.max(object), |m, r| m.max(*r))
                    .checked_add(1),
                Step::EventLogShifted { before, after, .. } => Some(before.max(after) + 1),
                Step::ClearedUnlessFlagged { record, flag, .. } => Some(record.max(flag) + 1),
                _ => None,
            })
            .max()
            .unwrap_or(0)
    }
}

/// The graded outcome of a case.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, serde::Deserialize,
)]
#[serde(rename_all = "SCREAMING-KEBAB-CASE")]
pub enum Verdict {
    Pass,
    NonStrict,
    Informational,
    Fail,
    Unimplemented,
    Skipped,
}

impl Verdict {
    /// Every verdict in report order.
    pub const ALL: [Verdict; 6] = [
        Verdict::Pass,
        Verdict::NonStrict,
        Verdict::Informational,
        Verdict::Fail,
        Verdict::Unimplemented,
        Verdict::Skipped,
    ];

    /// The report label.
    pub fn label(self) -> &'static str {
        match self {
            Verdict::Pass => "PASS",
            Verdict::NonStrict => "NON-STRICT",
            Verdict::Informational => "INFORMATIONAL",
            Verdict::Fail => "FAIL",
            Verdict::Unimplemented => "UNIMPLEMENTED",
            Verdict::Skipped => "SKIPPED",
        }
    }
}

impl fmt::Display for Verdict {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.label())
    }
}

impl std::str::FromStr for Verdict {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Verdict::ALL
            .into_iter()
            .find(|v| v.label().eq_ignore_ascii_case(s))
            .ok_or_else(|| format!("unknown verdict `{s}` (PASS, NON-STRICT, INFORMATIONAL, FAIL, UNIMPLEMENTED, SKIPPED)"))
    }
}

/// The write that restores what a capture of `read` kept (placeholder values), as a PDU.
fn restore_of(
    read: Option<&Option<&[u8]>>,
    at: Option<u16>,
    p: &drives::profile::Profile,
) -> Option<Vec<u8>> {
    let read = (*read?)?;
    crate::capture::placeholder(read)?
        .restore(at, p)?
        .to_bytes()
        .ok()
}
