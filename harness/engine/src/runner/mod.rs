//! The runner: applies the safety policy, puts each step's bytes on the wire, feeds the same bytes to the
//! reference drive in lockstep (the oracle), and judges what came back.

use std::time::{Duration, Instant};

use crate::capture::{self, Captured};
use crate::cases::{Case, Compare, Mutation, Outgoing, Step, Tag, Verdict};
use crate::expect::Expectations;
use crate::observe::{CaseResult, Dir, StepResult, WireEvent};
use crate::oracle::freedoms::Shown;
use crate::oracle::{self, ChoiceLog, Finding, Sent, Severity, StepContext};
use crate::targets::sim::SimTarget;
use crate::targets::{Received, Target, TargetError};
use codec::{Framing, Request, rtu, tcp};
use drives::profile::{Profile, Table, WordOrder};
use drives::requirements::{FreedomKind, Requirements};
use std::sync::Arc;

mod pipeline;

pub use pipeline::{MAX_IN_FLIGHT, Pipelining};

/// How long the runner waits.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Timing {
    /// How long to wait for an expected answer.
    pub timeout: Duration,
    /// How long to listen to confirm that nothing comes.
    pub silence: Duration,
    /// Modbus/TCP: prove a silence with a sentinel request sent right behind the request that must go
    /// unanswered (see [`Runner`]'s `prove_silence`) instead of listening for all of `silence`.
    pub sentinel: bool,
    /// How long a request the drive answers Server Busy (06) is sent again before that answer is judged
    /// (App 7: "the client should retransmit the message later"); zero: never sent again.
    pub busy_wait: Duration,
    /// How many times more a case is run where it FAILed in a way a damaged link gives as well as a faulty
    /// drive (see [`crate::observe::StepResult::link_damage`]), real targets only; zero: a FAIL stands at the
    /// first attempt. See [`crate::link::LINK_PAUSES`].
    pub link_retries: u32,
}

impl Default for Timing {
    /// 1 s for an answer, 300 ms of listening for one that must not come, sentinels on, 5 s for a busy drive,
    /// six more attempts of a case the link may have damaged.
    fn default() -> Self {
        Self {
            timeout: Duration::from_millis(1000),
            silence: Duration::from_millis(300),
            sentinel: true,
            busy_wait: BUSY_WITHIN,
            link_retries: 6,
        }
    }
}

pub use crate::cases::safety::Safety;

/// How a run behaves.
#[derive(Clone, Debug)]
pub struct RunConfig {
    /// Unit id / slave address of the drive.
    pub unit: u8,
    pub timing: Timing,
    pub safety: Safety,
    /// The target is the in-process simulator: the safety policy does not apply.
    pub is_sim: bool,
}

/// Why a case is skipped by the safety policy or the transport, if it is.
pub fn skip_reason(case: &Case, cfg: &RunConfig, framing: Framing) -> Option<String> {
    if case.has(Tag::TcpOnly) && framing != Framing::Tcp {
        return Some("needs Modbus/TCP framing".into());
    }
    if case.has(Tag::RtuOnly) && framing != Framing::Rtu {
        return Some("needs RTU framing".into());
    }
    if cfg.safety.read_only && case.has(Tag::Write) {
        return Some("writes, and --read-only is set".into());
    }
    if !cfg.is_sim {
        if case.has(Tag::Motion) && !cfg.safety.allow_motion {
            return Some(
                "can move the motor or enable the power stage: pass --allow-motion to run it"
                    .into(),
            );
        }
        if case.has(Tag::Destructive) && !cfg.safety.allow_destructive {
            return Some("changes non-volatile state or leaves the drive faulted: pass --allow-destructive to run it".into());
        }
        // A generated target, distance or velocity tests no axis, and a move it starts outlives the case (a
        // random MA runs for minutes, and the writes behind it meet a drive busy with it); the catalog's
        // motion cases start short moves and wait for the axis to come to rest.
        let generated = crate::cases::generated::parse_id(&case.id).is_some();
        if case.has(Tag::Motion) && generated {
            return Some(
                "a generated case that can move the motor: on a real drive generated and fuzz cases start no move and enable no power stage, whatever the flags (the catalog's motion cases run with --allow-motion)"
                    .into(),
            );
        }
        // CP and UG leave the drive changed for good: mid-run, every case after them would meet a drive
        // without its program or in upgrade mode (an LMD refuses every vendor request then).
        let irreversible = case.steps.iter().any(|s| match s {
            Step::Exchange { send, .. } | Step::Persist { send, .. } => match send {
                Outgoing::Pdu(p) | Outgoing::PduToUnit { pdu: p, .. } => {
                    crate::cases::safety::irreversible(p)
                }
                Outgoing::Mutated { pdu, mutation } => crate::cases::safety::irreversible(
                    &mutation.apply_to_pdu(pdu).unwrap_or_else(|| pdu.clone()),
                ),
                Outgoing::Batch(ps) => ps.iter().any(|p| crate::cases::safety::irreversible(p)),
                _ => false,
            },
            _ => false,
        });
        if irreversible && generated {
            return Some(
                "a generated case that sends CP or UG, which leave the drive changed for good (the stored program cleared, firmware-upgrade mode): generated and fuzz cases never send them to a real drive (the catalog runs its cases of them last, with --allow-destructive)"
                    .into(),
            );
        }
    }
    None
}

/// One write of a step and the idle time after it.
type Piece = (Vec<u8>, Duration);

/// A framed request ready to send.
/// Who sent a request of the harness's own outside the cases, for a late answer to it.
const OWN_REQUESTS: &str =
    "the harness's own requests outside the cases (learning the drive's choices, leave as found)";

/// An I/O point whose output no case writes ([`Runner::learn_output_setup`]).
#[derive(Clone, Debug)]
struct SetupPoint {
    line: u16,
    /// Its type in the setup (OS for an output, IS for an input).
    kind: i64,
    /// Set up as an input (and as no output).
    input: bool,
    coil: Option<u16>,
    /// The registers that write its output (its own, and the group registers).
    registers: Vec<u16>,
    /// The setting that sets the point up, where no case may write it (the MDrive's S1-S4).
    setup: Option<codec::Mnemonic>,
}

struct Framed {
    bytes: Vec<u8>,
    sent: Sent,
    malformed: bool,
    /// The ADU around the PDU was altered on purpose (a protocol id, an MBAP length, a CRC).
    adu_altered: bool,
}

impl Framed {
    /// A Modbus/TCP ADU whose MBAP length announces more bytes than it carries (an RTU frame has no
    /// length field: always false).
    fn short_of_length(&self) -> bool {
        self.sent.tid.is_some()
            && self.bytes.len() >= tcp::MBAP_LEN
            && usize::from(u16::from_be_bytes([self.bytes[4], self.bytes[5]]))
                > self.bytes.len() - 6
    }
}

/// Drives cases against a target with the reference drive in lockstep.
pub struct Runner {
    target: Box<dyn Target>,
    shadow: SimTarget,
    cfg: RunConfig,
    profile: Profile,
    next_tid: u16,
    slots: Vec<Option<Captured>>,
    /// `--max-rate`: when the next request may go out.
    next_send: Option<Instant>,
    expectations: Expectations,
    /// The freedoms the oracle applies (empty: judged by the reference drive alone).
    requirements: Arc<Requirements>,
    /// The choices the target showed so far, held against later ones.
    choices: ChoiceLog,
    /// The case being run: its id and the freedoms it cites.
    case_id: String,
    case_freedoms: Vec<String>,
    /// The case's tags: every request is rated again before it is sent and must not exceed them.
    case_tags: Vec<Tag>,
    /// A request of the case was refused by that check: the case stops there.
    refused: bool,
    /// The request PDUs of the case's steps that the target answered with an exception response and
    /// nothing else: writes it did not take (see [`Runner::refused_writes`]).
    refused_writes: Vec<Vec<u8>>,
    /// The reference as it was before the last [`Runner::exchange`], where that step made a copy of it (any
    /// request but a plain read): put back where the drive answered the step Server Busy (06) and the step
    /// is sent again ([`Runner::exchange_patiently`]).
    pre_step: Option<SimTarget>,
    /// Function codes the drive answered with exception 01 where the reference serves them (UNIMPLEMENTED):
    /// a later 01 to the same function is that again, whatever the reference answers to the request (silence
    /// for a request it learned to ignore, say).
    lacking: std::collections::BTreeSet<u8>,
    /// Function codes the drive served (a normal response) in this run.
    served_functions: std::collections::BTreeSet<u8>,
    /// The keeper's last request got no frame at all (silence, or the connection closed).
    restore_unheard: bool,
    /// See [`Runner::mark_choices`]: marking, and the reference's choices as they were at the mark once they
    /// changed since.
    marking: bool,
    learned_before: Option<drives::Choices>,
    /// New connections the keeper opened after a request of its got no frame at all.
    pub restore_reconnects: u32,
    /// The case being run sends an FC 15 (Write File Record): its FC 14 reads read back what it wrote.
    case_writes_files: bool,
    /// Outputs the drive has set up for a drive function, or whose point it has set up as an input, learned
    /// before the cases ([`Runner::learn_output_setup`]).
    function_outputs: Vec<SetupPoint>,
    /// Holding registers seen to change by themselves before the first write (the keeper's two reads, see
    /// [`crate::restore::Account::live`]: an encoder count, a lead/lag on a drive with its motor attached),
    /// with the tolerance an exact read of them is compared with ([`Runner::learn_live`]).
    live: Vec<(u16, u16, u32)>,
    /// Transaction ids of the restore's traffic: a sequence of its own, so that the cases' ids (and the
    /// snapshots of their observations) are the same with or without leaving the drive as found.
    restore_tid: u16,
    /// The word order the cases encode 32-bit values in (the profile's). Where a freedom leaves the order
    /// open, `profile.device.word_order` becomes the drive's own once [`Runner::learn_word_order`] has seen
    /// it, and whole 32-bit values the cases write are sent in that order.
    case_order: WordOrder,
    /// How far the drive's discrete inputs lie from the profile's addresses (0, or 0x002D once
    /// [`Runner::learn_input_addressing`] found an LMD following its manual's example).
    input_offset: u16,
    /// The drive follows the SD2x example's FC 43 / MEI 0x0D form, without the layout's Reserved byte, as
    /// [`Runner::learn_fc43_form`] found: the cases' requests go out in that form and the answers are read
    /// back into the layout's before they are judged.
    fc43_without_reserved: bool,
    /// The request PDUs sent before the cases to learn the drive's choices (word order, input addressing,
    /// FC 43 form), as sent, which a rebuilt reference drive is given again, and the choices learned so far.
    learning_reads: Vec<Vec<u8>>,
    learned: drives::Choices,
    /// Modbus/TCP: the transaction ids of the latest requests sent (with the case that sent them, or the
    /// liveness probe, and when), so that a late answer is attributed to its request instead of being
    /// taken for a later step's.
    recent: std::collections::VecDeque<(u16, String, Duration)>,
    /// Modbus/TCP: the transaction ids of the running case's requests whose answer came late, during a later
    /// step of the case (see [`Runner::answered_late`]).
    late_in_case: Vec<u16>,
    /// The requests of the cases sent since the target last answered one (case id, bytes; the first few):
    /// the first of them is the one that preceded a silence.
    unanswered: Vec<(String, Vec<u8>)>,
    /// Modbus/TCP: transaction ids of silence sentinels whose answers have not come yet (dropped unjudged
    /// when they do).
    sentinels: std::collections::VecDeque<u16>,
    /// A sentinel the reference answered went unanswered by the target (a target that drops what follows a
    /// bad frame, say): no more sentinels on this target, the window is listened out.
    sentinel_given_up: bool,
    /// How long the target took to answer its last single requests (Modbus/TCP): the half-close waits twice
    /// the slowest first (see `prove_silence_by_close`).
    latencies: RecentLatencies,
    /// The step's request to another unit id was ignored (or refused as a gateway refuses it, 0A or 0B) by
    /// the drive as the `unit-ids` freedom allows: it took no effect.
    unit_ignored: bool,
    /// Choices the drive showed in the step that the reference drive does not take yet and follows from
    /// now on (see [`follows`]).
    follow: Vec<(
        drives::requirements::Freedom,
        drives::requirements::FreedomValue,
    )>,
    /// How the silences due on Modbus/TCP to a real target were settled, for the run's log.
    silences: Silences,
    /// Requests sent to the target: the cases', the sentinels, the liveness probes, the restore's.
    requests: u64,
    /// The restore's requests for several parameters at once (reads, writes) that the target did not take as
    /// asked (see [`crate::restore::read_all`], [`crate::restore::restore`]): those go one parameter a request.
    blocks_refused: Vec<crate::restore::Block>,
    /// The step being run is followed by a new connection (`Step::Reconnect`): its connection may be
    /// half-closed to prove a silence (see `prove_silence_by_close`).
    reconnect_next: bool,
    /// Real targets of a run: the known-good read and its bound, sent after a step whose due answer did not
    /// come while the case has requests left (see [`Runner::watch_mid_case`]).
    mid_case: Option<(Vec<u8>, Duration)>,
    /// The case being run was stopped there, and why.
    stalled: Option<Stall>,
    /// The request the stall began after (see [`Runner::stalled_by`]).
    stalled_by: Option<(String, Vec<u8>)>,
    /// RTU on a real target: a malformed frame went out, so the next one waits for the line's t3.5 first
    /// (see `send_pieces`).
    resync_rtu: bool,
    /// The silences before the answers (RTU on a line), judged once by the run's timing case, and whether
    /// the target's line can be measured at all (asked once: a serial target looks at its device path).
    gaps: crate::timing::AnswerGaps,
    gaps_measurable: Result<(), String>,
    /// The profile leaves open whether a read of half a 32-bit register is served (`partial-register-read`):
    /// a plain read may then take the drive's own way, and the reference follows it (see [`follows`]).
    reads_decided: bool,
    /// The freedoms of `requirements` a request to this profile can touch (see
    /// [`oracle::freedoms::touchable`]), found once.
    touchable: Vec<usize>,
    /// The items whose write starts a long-duration command (`busy-after-long-command`: an NVM save), and
    /// when the drive last took such a write (the target's clock): a request of a batch refused Server Busy
    /// (06) within [`Timing::busy_wait`] of it is busy with that command, not with the batch.
    long_commands: Vec<drives::requirements::Item>,
    long_command_at: Option<Duration>,
    /// For a step that sends several requests in one write: the freedoms that decided each one's answer,
    /// found by sending them one by one to a copy of the reference (see [`decisions_one_by_one`]).
    frame_decisions: Vec<Vec<drives::Decision>>,
    /// Modbus/TCP, pipelined cases (see [`pipeline`]): the requests of the cases to come that are on the
    /// wire already, in case order, and the answers to them that arrived while an earlier case listened.
    ahead: std::collections::VecDeque<pipeline::Ahead>,
    stash: Vec<Received>,
    /// The target closed the connection while requests were ahead: they are lost and go out again, one at
    /// a time, when their cases' turns come.
    ahead_lost: bool,
    /// A pipelined case went unanswered and was asked again alone (its id): pipelining is over.
    pipeline_failed: Option<String>,
    /// The step's request went out before the step began (pipelined), at this time of the target's.
    presented: Option<Duration>,
}

/// The freedoms that decide the answer to each of `frames` when `reference` gets them one at a time, in
/// order: what a batch's answers are each about (the reference's decisions for the whole batch do not say
/// which request they were for, and a half-register write first must not make the write beside it look
/// like a half write too).
fn decisions_one_by_one(mut reference: SimTarget, frames: &[Framed]) -> Vec<Vec<drives::Decision>> {
    frames
        .iter()
        .map(|f| {
            if reference.send(&f.bytes).is_err() {
                return Vec::new();
            }
            let _ = reference.settle();
            let _ = reference.take_counter_alternatives();
            reference.take_decisions()
        })
        .collect()
}

/// The answer times of a target's last 32 single requests.
#[derive(Clone, Copy, Debug, Default)]
struct RecentLatencies {
    ring: [Duration; 32],
    next: usize,
}

impl RecentLatencies {
    fn note(&mut self, d: Duration) {
        self.ring[self.next % self.ring.len()] = d;
        self.next = self.next.wrapping_add(1);
    }

    /// The slowest of them (zero before the first).
    fn slowest(&self) -> Duration {
        self.ring.iter().copied().max().unwrap_or_default()
    }
}

/// Why a case was stopped before its last step: a step's due answer did not come, and a known-good read
/// after it (see [`Runner::watch_mid_case`]) showed more than that one request going unanswered.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stall {
    /// The connection no longer answers, a new one does (a drive that leaves a connection hung after a
    /// request: jsmodbus 5 did after an unsupported function and after a request with a byte too many). The
    /// case's remaining requests would have gone to the hung connection, or to a drive whose state after the
    /// unanswered request nobody knows.
    Connection,
    /// Nothing answers, on this connection or a new one: the run's watch waits for the target.
    Target,
}

/// How the silences due from a real target were settled (on RTU every one is listened out).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Silences {
    /// Proven by a sentinel request's answer with nothing before it.
    pub sentinel: u64,
    /// Proven by the target closing the connection after the harness half-closed it, with nothing before.
    pub close: u64,
    /// Listened out for the whole window.
    pub listened: u64,
}

/// Whether the reference drive follows the drive under test where it shows a value of `f` other than the
/// reference's: the outcome freedoms, which decide at run time whether and how a request is answered, and
/// so whether it takes effect (a half of a 32-bit register written, a request refused as busy in a
/// pipeline) and what the drive counts (an FC 08 no-response count grows where a truncated PDU goes
/// unanswered). Otherwise the reference keeps a state the drive admissibly does not have (the drive took a
/// half write of SL and moves, the reference refused it and stands), and later cases FAIL for it or take
/// its counts for another reading of a counter. A `close` is not followed (the connection is gone either
/// way). Not the optional groups nor the functions served beyond the profile: a drive may lack some items
/// of a group and have others, and the reference could not answer as a drive having one that it took for
/// lacking (the state it keeps for items the drive refuses is never seen). The freedoms that shape the
/// model (access, word order, addressing) are learned before the cases instead.
fn follows(f: &drives::requirements::Freedom) -> bool {
    f.kind == FreedomKind::Outcome
}

/// Requests remembered for attributing late answers.
const RECENT_REQUESTS: usize = 256;

/// A request the drive answered Server Busy (06) is sent again after this pause, doubled each time up to
/// [`BUSY_PAUSE_MAX`], for [`Timing::busy_wait`] at most ([`Runner::exchange_patiently`], and the keeper's
/// reads and writes); by default [`BUSY_WITHIN`]. Drives written independently from the manuals were busy
/// for up to 3 s (an LMD's upgrade mode, UG).
const BUSY_FIRST_PAUSE: Duration = Duration::from_millis(20);
/// How many more reads tell a register that changes by itself after an exact read of it FAILed
/// ([`Runner::recheck_live`]), and the pause before each.
const LIVE_RECHECKS: usize = 4;
const LIVE_RECHECK_GAP: Duration = Duration::from_millis(8);
const BUSY_PAUSE_MAX: Duration = Duration::from_millis(100);
pub const BUSY_WITHIN: Duration = Duration::from_secs(5);

/// How many register pairs that read in range in only one word order settle it (all of them must agree).
const WORD_ORDER_VOTES: usize = 3;

impl Runner {
    /// A runner for `target`, judged by `shadow` (a fault-free reference drive of the same profile).
    pub fn new(
        target: Box<dyn Target>,
        shadow: SimTarget,
        profile: Profile,
        cfg: RunConfig,
        expectations: Expectations,
    ) -> Self {
        let case_order = profile.device.word_order;
        let gaps_measurable = target.answer_gap_measurable();
        Self {
            target,
            shadow,
            cfg,
            profile,
            next_tid: 1,
            slots: Vec::new(),
            next_send: None,
            expectations,
            requirements: Arc::default(),
            choices: ChoiceLog::default(),
            case_id: String::new(),
            case_freedoms: Vec::new(),
            case_tags: Vec::new(),
            refused: false,
            refused_writes: Vec::new(),
            pre_step: None,
            lacking: std::collections::BTreeSet::new(),
            served_functions: std::collections::BTreeSet::new(),
            restore_unheard: false,
            marking: false,
            learned_before: None,
            restore_reconnects: 0,
            case_writes_files: false,
            function_outputs: Vec::new(),
            live: Vec::new(),
            restore_tid: 0xA000,
            case_order,
            input_offset: 0,
            fc43_without_reserved: false,
            learning_reads: Vec::new(),
            learned: drives::Choices::reference(),
            recent: std::collections::VecDeque::new(),
            late_in_case: Vec::new(),
            unanswered: Vec::new(),
            sentinels: std::collections::VecDeque::new(),
            sentinel_given_up: false,
            latencies: RecentLatencies::default(),
            gaps: crate::timing::AnswerGaps::default(),
            gaps_measurable,
            reads_decided: false,
            touchable: Vec::new(),
            long_commands: Vec::new(),
            long_command_at: None,
            frame_decisions: Vec::new(),
            unit_ignored: false,
            follow: Vec::new(),
            silences: Silences::default(),
            requests: 0,
            blocks_refused: Vec::new(),
            reconnect_next: false,
            mid_case: None,
            stalled: None,
            stalled_by: None,
            resync_rtu: false,
            ahead: std::collections::VecDeque::new(),
            stash: Vec::new(),
            ahead_lost: false,
            pipeline_failed: None,
            presented: None,
        }
    }

    /// Learn the drive's word order, where a freedom of the profile leaves it open (the LMD's, freedom
    /// `lmd-word-order`), before the first case, so that no case's verdict depends on the cases run before it:
    /// read the readable 32-bit registers and take the order in which their values lie in the profile's
    /// range where only one order does (a value such as 0 settles nothing). When the drive's order is not
    /// the profile's, the reference drive is rebuilt in the drive's order (and given the same reads), the
    /// oracle reads 32-bit values in it first, and the whole 32-bit values the cases write are sent in it
    /// (the cases' values stay the same numbers). The order learned is recorded as the drive's choice, so
    /// that an answer in the other order later is a change of mind (freedom note: "A drive must use one
    /// order consistently", ERRATA-lmd.md C.1). Reads only, through the restore's transaction ids, so that
    /// the cases' observations do not change; best effort: a target that does not answer is left to the cases.
    pub fn learn_word_order(&mut self) {
        let requirements = Arc::clone(&self.requirements);
        let id = self.profile.device.id.clone();
        let Some(freedom) = requirements
            .freedoms_for(&id)
            .find(|f| f.kind == FreedomKind::WordOrder)
        else {
            return;
        };
        let pairs: Vec<(u16, String)> = self
            .profile
            .registers
            .iter()
            .map(|r| r.get_ref())
            .filter(|r| {
                r.width == 2 && r.confirmed && r.access.readable() && r.table != Table::Input
            })
            .map(|r| (r.address, r.name.clone()))
            .collect();
        let profile_order = self.profile.device.word_order;
        let other = flip(profile_order);
        let mut votes: Vec<(WordOrder, u16, String)> = Vec::new();
        for (address, name) in pairs {
            let read = Request::ReadHoldingRegisters {
                address,
                quantity: 2,
            };
            let answer = crate::restore::Link::transact(self, &read);
            self.learning_reads.extend(read.to_bytes().ok());
            let answer = match answer {
                Ok(Some(a)) => a,
                // Silence or an error: the cases will meet it; nothing more is learned here.
                _ => break,
            };
            let codec::Response::ReadHoldingRegisters { values } = answer else {
                continue;
            };
            let [a, b] = values[..] else { continue };
            let fits = |order: WordOrder| {
                self.profile.register_at(address, false).is_some_and(|r| {
                    let raw = order.join(a, b);
                    let v = if r.signed {
                        i64::from(raw as i32)
                    } else {
                        i64::from(raw)
                    };
                    let (min, max) = r.range();
                    (min..=max).contains(&v)
                })
            };
            match (fits(profile_order), fits(other)) {
                (true, false) => votes.push((profile_order, address, name)),
                (false, true) => votes.push((other, address, name)),
                _ => {}
            }
            if votes.len() >= WORD_ORDER_VOTES && votes.iter().all(|v| v.0 == votes[0].0) {
                break;
            }
        }
        let count = |o: WordOrder| votes.iter().filter(|v| v.0 == o).count();
        let drive_order = if count(other) > count(profile_order) {
            other
        } else {
            profile_order
        };
        let Some((_, address, name)) = votes.iter().find(|v| v.0 == drive_order) else {
            return;
        };
        let shown = crate::oracle::freedoms::shown_value(freedom, "", order_name(drive_order));
        let origin = format!("(word order learned before the cases: 0x{address:04X} {name})");
        let _ = self.choices.record(&shown, &origin, &requirements);
        if drive_order == profile_order {
            return;
        }
        self.profile.device.word_order = drive_order;
        self.rebuild_reference();
    }

    /// Learn where the drive serves its discrete inputs, where a reading of its manual leaves that open
    /// (the LMD's, freedom `lmd-discrete-input-addressing`: the request table's 0x0000-0x0003 or the
    /// example's 0x002D), before the first case: read the first input at the profile's address and, when
    /// the drive refuses it, at the example's. A drive that serves only the latter follows the example: it
    /// is recorded as the drive's choice, the reference drive is rebuilt to serve its inputs there too, and
    /// the cases' FC 02 reads of the inputs are sent there, so that the inputs' checks (values, padding
    /// bits) still look at the inputs instead of being refused. Reads only, through the restore's
    /// transaction ids; best effort, like [`Runner::learn_word_order`].
    pub fn learn_input_addressing(&mut self) {
        const FREEDOM: &str = "lmd-discrete-input-addressing";
        const EXAMPLE: &str = "inputs-at-0x002D";
        const OFFSET: u16 = crate::oracle::freedoms::LMD_EXAMPLE_INPUT_OFFSET;
        let requirements = Arc::clone(&self.requirements);
        let id = self.profile.device.id.clone();
        let Some(freedom) = requirements.freedom(FREEDOM).filter(|f| f.applies_to(&id)) else {
            return;
        };
        if !freedom.admits(EXAMPLE) {
            return;
        }
        let Some(first) = self
            .profile
            .discrete_inputs
            .iter()
            .map(|b| b.get_ref().address)
            .min()
        else {
            return;
        };
        let read = |address: u16| Request::ReadDiscreteInputs {
            address,
            quantity: 1,
        };
        let sent = [read(first), read(first.wrapping_add(OFFSET))];
        let first_answer = crate::restore::Link::transact(self, &sent[0]);
        self.learning_reads.extend(sent[0].to_bytes().ok());
        match first_answer {
            Ok(Some(r)) if r.is_exception() => {}
            _ => return,
        }
        let second_answer = crate::restore::Link::transact(self, &sent[1]);
        self.learning_reads.extend(sent[1].to_bytes().ok());
        match second_answer {
            Ok(Some(r)) if !r.is_exception() => {}
            _ => return,
        }
        let origin = format!(
            "(input addressing learned before the cases: FC 02 refused at 0x{first:04X}, served at 0x{:04X})",
            first.wrapping_add(OFFSET)
        );
        self.input_offset = OFFSET;
        self.follow_reading(freedom, "", EXAMPLE, &origin);
    }

    /// Learn before the cases whether the drive serves a read of one half of a 32-bit holding register
    /// (freedom `partial-register-read`): one FC 03 of the first half of the profile's first readable
    /// 32-bit register whose width the manual does not give two ways. A refusal (02, 03 or 04) is followed
    /// from then on. Generated cases combine a half read with another freedom in one step (a request one
    /// byte longer than its layout that the drive serves as the layout's request, `trailing-bytes =
    /// response`); judged before the drive showed its choice for halves, the pair read as a FAIL
    /// (tests/independent/lmd-g, seed 1, the first case). Over Modbus/TCP only: there a late answer to
    /// the read is told by its transaction id; on an RTU line it would be taken for the first case's.
    pub fn learn_partial_register_read(&mut self) {
        if self.target.framing() != Framing::Tcp {
            return;
        }
        let requirements = Arc::clone(&self.requirements);
        let id = self.profile.device.id.clone();
        let Some(freedom) = requirements
            .freedom(drives::choices::ids::PARTIAL_REGISTER_READ)
            .filter(|f| f.applies_to(&id))
        else {
            return;
        };
        if self.profile.function(0x03u8).is_none() {
            return;
        }
        let Some(address) = self
            .profile
            .registers
            .iter()
            .map(|r| r.get_ref())
            .filter(|r| {
                r.width == 2
                    && r.table != Table::Input
                    && !r.width_disputed
                    && !r.read_clears
                    && r.access.readable()
            })
            .map(|r| r.address)
            .min()
        else {
            return;
        };
        let read = Request::ReadHoldingRegisters {
            address,
            quantity: 1,
        };
        let answer = crate::restore::Link::transact(self, &read);
        self.learning_reads.extend(read.to_bytes().ok());
        let Ok(Some(codec::Response::Exception { code, .. })) = answer else {
            return;
        };
        let value = format!("exception-{:02X}", code.0);
        if !freedom.admits(&value) {
            return;
        }
        let origin = format!(
            "(learned before the cases: FC 03 of one register at 0x{address:04X}, the first half of a 32-bit register, refused with {:02X})",
            code.0
        );
        // Held as the drive's choice for reads from a 32-bit register's first register (a read from inside one
        // is a choice of its own: see `oracle::freedoms::about_of`).
        self.follow_reading(freedom, "from its first register", &value, &origin);
    }

    /// The drive follows the other reading `value` of `freedom`, learned before the cases: recorded as its
    /// choice (about `about` within the freedom, from `origin`), taken by the reference drive, which is
    /// rebuilt with it.
    fn follow_reading(
        &mut self,
        freedom: &drives::requirements::Freedom,
        about: &str,
        value: &str,
        origin: &str,
    ) {
        let Some(v) = freedom.values.iter().find(|v| v.matches(value)).cloned() else {
            return;
        };
        let shown = crate::oracle::freedoms::shown_value(freedom, about, value);
        let requirements = Arc::clone(&self.requirements);
        let _ = self.choices.record(&shown, origin, &requirements);
        self.before_learning();
        self.learned.choose(freedom, v);
        self.rebuild_reference();
    }

    /// A new reference drive for what was learned before the cases (the profile's word order, the choices
    /// in `learned`), given the reads the old one got then (its counters and event log agree with the
    /// target's again).
    fn rebuild_reference(&mut self) {
        let learned = self.learned.clone();
        self.shadow =
            SimTarget::reference(&self.profile, self.cfg.unit, learned, self.target.as_ref());
        let tid = self.next_tid;
        // As they were sent: in the form they had then, whatever was learned since.
        let fc43 = std::mem::take(&mut self.fc43_without_reserved);
        for pdu in self.learning_reads.clone() {
            let f = self.frame(&pdu, self.cfg.unit, None);
            if self.shadow.send(&f.bytes).is_ok() {
                let _ = self.shadow.settle();
                let _ = self.shadow.take_decisions();
            }
        }
        self.fc43_without_reserved = fc43;
        self.next_tid = tid;
    }

    /// Learn the form of the drive's FC 43 / MEI 0x0D telegrams, where a reading of its manual leaves it open
    /// (the SD2x's, freedom `sd2x-fc43-reserved-byte`: the section 3.6 layout has a Reserved byte after the
    /// control code, line 545 and 561; the only example, lines 1302-1304 and 1324-1326, has none), before
    /// the first case: read the first readable object in the layout's form and, when the drive does not
    /// answer it with the object, in the example's. A drive that answers only the latter (with an answer
    /// that is well-formed in that form) follows the example: that is recorded as the drive's choice, the
    /// reference drive is rebuilt to take that form too, the cases' FC 43 requests go out in it and the
    /// answers are read back into the layout's before they are judged, so that the object checks (values,
    /// SDO errors, the views of a register pair) look at the objects instead of at refusals. A drive that
    /// answers the layout's form is recorded as keeping to it. Reads only, through the restore's
    /// transaction ids; best effort, like [`Runner::learn_word_order`].
    pub fn learn_fc43_form(&mut self) {
        const FREEDOM: &str = drives::models::sd2x::FC43_RESERVED_BYTE;
        const EXAMPLE: &str = "without-reserved-byte";
        const LAYOUT: &str = "with-reserved-byte";
        let requirements = Arc::clone(&self.requirements);
        let id = self.profile.device.id.clone();
        let Some(freedom) = requirements.freedom(FREEDOM).filter(|f| f.applies_to(&id)) else {
            return;
        };
        let Some(o) = self.profile.first_readable_object() else {
            return;
        };
        let (index, subindex) = (o.index, o.subindex);
        let Ok(layout) = Request::CanOpen(codec::CanOpenAccess::read(
            self.cfg.unit,
            index,
            subindex,
            o.ty.size() as u16,
        ))
        .to_bytes() else {
            return;
        };
        let is_object = |pdu: &[u8]| {
            matches!(codec::Response::decode(pdu), Ok(codec::Response::CanOpen(a))
                if !a.is_write() && a.index == index && a.subindex == subindex)
        };
        let answer = self.transact_pdu(&layout);
        self.learning_reads.push(layout.clone());
        let origin = |form: &str| {
            format!(
                "(FC 43 form learned before the cases: object {index}.{subindex} read in the {form} form)"
            )
        };
        match answer {
            Ok(Some(r)) if is_object(&r) => {
                let shown = crate::oracle::freedoms::shown_value(freedom, "", LAYOUT);
                let _ = self
                    .choices
                    .record(&shown, &origin("layout's"), &requirements);
                return;
            }
            Ok(Some(_)) => {}
            // Silence or an error: the cases will meet it; nothing more is learned here.
            _ => return,
        }
        let Some(example) = codec::canopen_without_reserved(&layout) else {
            return;
        };
        let answer = self.transact_pdu(&example);
        self.learning_reads.push(example);
        let Ok(Some(r)) = answer else { return };
        if !codec::canopen_with_reserved(&r).is_some_and(|long| is_object(&long)) {
            return;
        }
        if !freedom.admits(EXAMPLE) {
            return;
        }
        self.fc43_without_reserved = true;
        self.follow_reading(freedom, "", EXAMPLE, &origin("example's"));
    }

    /// An answer frame of the target or the reference drive in the form the cases are judged in: a
    /// well-formed FC 43 / MEI 0x0D answer of a drive that follows the SD2x example's form (see
    /// [`Runner::learn_fc43_form`]) with the layout's Reserved byte put back; an FC 0x41 answer with the
    /// one byte after its counted string that the MDrive and LMD manuals allow left out
    /// ([`vendor_read_unpadded`]); framing rebuilt. `None` for every other frame, which is judged as it came
    /// (a malformed answer stays malformed).
    fn in_case_form(&self, frame: &[u8]) -> Option<Vec<u8>> {
        let judged = |pdu: &[u8]| {
            if self.fc43_without_reserved
                && let Some(long) = canopen_answer_with_reserved(pdu)
            {
                return Some(long);
            }
            vendor_read_unpadded(pdu)
        };
        // Every answer passes here: nothing is allocated unless it changes.
        let mut out = Vec::new();
        match self.target.framing() {
            Framing::Tcp => {
                let (header, pdu) = tcp_adu_parts(frame)?;
                let pdu = judged(pdu)?;
                tcp::encode_adu(header.0, header.1, &pdu, &mut out).ok()?;
            }
            _ => {
                let adu = rtu::decode_adu(frame).ok()?;
                let pdu = judged(adu.pdu)?;
                rtu::encode_adu(adu.address, &pdu, &mut out).ok()?;
            }
        }
        Some(out)
    }

    /// [`Runner::in_case_form`] for what the target or the reference gave.
    fn received_in_case_form(&self, got: &Received) -> Option<Received> {
        match got {
            Received::Frame {
                bytes,
                first_at,
                last_at,
                max_gap,
            } => Some(Received::Frame {
                bytes: self.in_case_form(bytes)?,
                first_at: *first_at,
                last_at: *last_at,
                max_gap: *max_gap,
            }),
            _ => None,
        }
    }

    /// An FC 02 read of the profile's discrete inputs moved to where the drive serves them, once
    /// [`Runner::learn_input_addressing`] found them elsewhere; `None` for every other request.
    fn in_drive_input_addressing(&self, pdu: &[u8]) -> Option<Vec<u8>> {
        if self.input_offset == 0 {
            return None;
        }
        let Ok(Request::ReadDiscreteInputs { address, quantity }) = Request::decode(pdu) else {
            return None;
        };
        let inputs = || {
            self.profile
                .discrete_inputs
                .iter()
                .map(|b| b.get_ref().address)
        };
        let (lo, hi) = (inputs().min()?, inputs().max()?);
        (lo..=hi).contains(&address).then(|| {
            Request::ReadDiscreteInputs {
                address: address.wrapping_add(self.input_offset),
                quantity,
            }
            .to_bytes()
            .unwrap_or_else(|_| pdu.to_vec())
        })
    }

    /// The word order the oracle reads the drive's 32-bit values in (the profile's, or the drive's own
    /// where a freedom leaves it open and [`Runner::learn_word_order`] saw it).
    pub fn word_order(&self) -> WordOrder {
        self.profile.device.word_order
    }

    /// `pdu` with each whole 32-bit register value it writes (FC 16, FC 23) put in the drive's word order,
    /// when that is not the order the cases encode values in. Halves of a value and other requests are
    /// sent as they are.
    fn in_drive_order(&self, pdu: &[u8]) -> Vec<u8> {
        let moved = self.in_drive_input_addressing(pdu);
        let pdu = moved.as_deref().unwrap_or(pdu);
        if self.profile.device.word_order == self.case_order {
            return pdu.to_vec();
        }
        let mut req = match Request::decode(pdu) {
            Ok(r) => r,
            Err(_) => return pdu.to_vec(),
        };
        let (address, values) = match &mut req {
            Request::WriteMultipleRegisters { address, values } => (*address, values),
            Request::ReadWriteMultipleRegisters {
                write_address,
                values,
                ..
            } => (*write_address, values),
            _ => return pdu.to_vec(),
        };
        let mut i = 0usize;
        while i + 1 < values.len() {
            let a = address.wrapping_add(i as u16);
            if self
                .profile
                .register_at(a, false)
                .is_some_and(|r| r.width == 2 && r.address == a)
            {
                values.swap(i, i + 1);
                i += 2;
            } else {
                i += 1;
            }
        }
        req.to_bytes().unwrap_or_else(|_| pdu.to_vec())
    }

    /// Whether `req` writes an item whose write starts a long-duration command (`busy-after-long-command`).
    fn starts_long_command(&self, req: &Request) -> bool {
        !self.long_commands.is_empty()
            && drives::requirements::registers_written(req).is_some()
            && self
                .long_commands
                .iter()
                .any(|i| i.touched_by(req, &self.profile))
    }

    /// Whether the drive took a long-duration command within [`Timing::busy_wait`] (see `long_commands`).
    fn busy_with_long_command(&self) -> bool {
        self.long_command_at
            .is_some_and(|at| self.target.now().saturating_sub(at) <= self.cfg.timing.busy_wait)
    }

    /// Judge with the freedoms of `requirements`: an answer another admissible choice gives passes.
    pub fn with_requirements(mut self, requirements: Arc<Requirements>) -> Self {
        self.reads_decided = requirements
            .freedom(drives::choices::ids::PARTIAL_REGISTER_READ)
            .is_some_and(|f| f.applies_to(&self.profile.device.id));
        self.touchable = oracle::freedoms::touchable(&requirements, &self.profile.device.id);
        self.long_commands = requirements
            .freedom(drives::choices::ids::BUSY_AFTER_LONG_COMMAND)
            .filter(|f| f.applies_to(&self.profile.device.id))
            .map(|f| f.items.clone())
            .unwrap_or_default();
        self.requirements = requirements;
        self
    }

    /// The choices the target showed so far.
    pub fn choices(&self) -> &ChoiceLog {
        &self.choices
    }

    /// Remember the choices the target showed so far and those the reference follows, to put back with
    /// [`Runner::forget_attempt`] where a case's attempt is not judged (nothing is copied until one changes).
    pub fn mark_choices(&mut self) {
        self.choices.mark();
        self.learned_before = None;
        self.marking = true;
    }

    /// An attempt of a case that the link damaged is not judged: what it showed of the drive's choices is
    /// forgotten (a request damaged on its way is not answered, which is no choice of the drive), back to
    /// [`Runner::mark_choices`], and the link is known to lose frames from now on (see
    /// [`ChoiceLog::link_loses_frames`]).
    pub fn forget_attempt(&mut self) {
        self.choices.rewind();
        self.choices.link_loses_frames();
        if let Some(learned) = self.learned_before.take() {
            self.learned = learned;
            self.shadow.adopt(self.learned.clone());
        }
    }

    /// Before the reference follows another choice: the choices as they were at [`Runner::mark_choices`].
    fn before_learning(&mut self) {
        if self.marking && self.learned_before.is_none() {
            self.learned_before = Some(self.learned.clone());
        }
    }

    /// How frames are delimited on the target.
    pub fn framing(&self) -> Framing {
        self.target.framing()
    }

    /// The target (for reports).
    pub fn target(&self) -> &dyn Target {
        self.target.as_ref()
    }

    /// Frame `pdu` for the unit with the restore's sequence of transaction ids: the traffic beside the cases
    /// (restores, liveness probes, silence sentinels). Once the two sequences have wrapped (after 65,536
    /// requests of a long campaign), the restore sequence's next id may be that of a recent request of the
    /// cases, the step's own included (`send_pieces` remembered them): a late answer to that request would
    /// then be taken for this one's (a wrong value "restored", an answer where silence was due). This takes
    /// the next id that is none of them.
    fn frame_aside(&mut self, pdu: &[u8]) -> Framed {
        for _ in 0..=RECENT_REQUESTS {
            let t = self.restore_tid;
            if !self.recent.iter().any(|r| r.0 == t) {
                break;
            }
            self.restore_tid = t.wrapping_add(1);
        }
        let case_tid = std::mem::replace(&mut self.next_tid, self.restore_tid);
        let f = self.frame(pdu, self.cfg.unit, None);
        self.restore_tid = std::mem::replace(&mut self.next_tid, case_tid);
        f
    }

    /// Send the known-good read `pdu` (the pre-flight, a liveness probe) and listen up to `bound`. Its
    /// transaction ids are the restore's sequence, so the cases' own ids do not depend on how many probes
    /// were sent; the reference drive gets the request too, so that it follows what the target counted.
    pub fn known_good(
        &mut self,
        pdu: &[u8],
        bound: Duration,
    ) -> Result<(crate::liveness::Heard, Vec<u8>), TargetError> {
        let f = self.frame_aside(pdu);
        self.resync_if_due();
        self.target.drain();
        self.probe_to_reference(&f)?;
        let asked = self.target.now();
        let heard = crate::liveness::ask(self.target.as_mut(), &f.bytes, bound)?;
        if heard == crate::liveness::Heard::Modbus {
            self.unanswered.clear();
            if self.target.framing() == Framing::Tcp {
                // Until its answer is complete: a little over the answer's time.
                self.latencies.note(self.target.now().saturating_sub(asked));
            }
        }
        Ok((heard, f.bytes))
    }

    /// A liveness probe `f` about to go to the target: paced, remembered for a late answer, counted, and
    /// given to the reference drive, so that it counts what the target counts.
    fn probe_to_reference(&mut self, f: &Framed) -> Result<(), TargetError> {
        self.sync_shadow();
        self.pace();
        self.remember(f.sent.tid, "the liveness probe".into());
        self.shadow.send(&f.bytes)?;
        let _ = self.shadow.settle();
        let _ = self.shadow.take_decisions();
        self.requests += 1;
        Ok(())
    }

    /// The known-good read `pdu` after a step whose due answer did not come (see [`Runner::watch_mid_case`]),
    /// listening up to `bound`: whether its own answer came (Modbus/TCP: the frame with its transaction id;
    /// on RTU, which has none, any Modbus answer), and notes on the late answers to earlier requests that
    /// came before it or instead (stale ones included): a drive still holding an earlier frame may answer
    /// that one when the read's bytes complete it, and swallow the read.
    fn probe_mid_case(
        &mut self,
        pdu: &[u8],
        bound: Duration,
    ) -> Result<(bool, Vec<String>), TargetError> {
        let f = self.frame_aside(pdu);
        self.resync_if_due();
        let when = "during the known-good read after this step";
        let tcp = self.target.framing() == Framing::Tcp;
        let mut late = if tcp {
            self.target.drain_stale()
        } else {
            self.target.drain();
            Vec::new()
        };
        self.probe_to_reference(&f)?;
        self.target.send(&f.bytes)?;
        let start = self.target.now();
        let mut own = false;
        // Bounded by `bound` on the target's clock and by 32 receives.
        for _ in 0..32 {
            let left = bound.saturating_sub(self.target.now().saturating_sub(start));
            if left.is_zero() {
                break;
            }
            match self.target.recv(left)? {
                Received::Frame { bytes, .. } => {
                    let answer =
                        crate::readings::decode_response(self.target.framing(), &bytes).is_some();
                    if answer && (!tcp || bytes.get(..2) == f.bytes.get(..2)) {
                        own = true;
                        break;
                    }
                    late.extend_from_slice(&bytes);
                }
                Received::Garbage { .. } => {}
                Received::Silence { .. } | Received::Closed { .. } => break,
            }
        }
        if own {
            self.unanswered.clear();
        }
        let notes = if tcp {
            self.late_in(&late, when)
        } else {
            Vec::new()
        };
        Ok((own, notes))
    }

    /// Whether the target answers the read `pdu` sent to another unit id `unit` (the reference drive does not
    /// see it): a pre-flight read that got no answer at the run's unit is tried at the unit ids a Modbus/TCP
    /// device commonly answers, to say which one to use.
    pub fn answers_at_unit(
        &mut self,
        pdu: &[u8],
        unit: u8,
        bound: Duration,
    ) -> Result<bool, TargetError> {
        let f = self.frame(pdu, unit, None);
        self.target.drain();
        self.remember(f.sent.tid, format!("the read at unit {unit}"));
        self.requests += 1;
        Ok(crate::liveness::ask(self.target.as_mut(), &f.bytes, bound)?
            == crate::liveness::Heard::Modbus)
    }

    /// What the target sends back to the read `pdu` addressed to another unit id or slave address `unit`
    /// within `bound` (the reference drive does not see it): the bytes of the first frame, or of whatever
    /// came (a garbled frame: two devices answering at once), or `None` for nothing. The line survey
    /// ([`crate::session`]) asks this of the addresses it may send another slave's frames to.
    pub fn heard_at_unit(
        &mut self,
        pdu: &[u8],
        unit: u8,
        bound: Duration,
    ) -> Result<Option<Vec<u8>>, TargetError> {
        let f = self.frame(pdu, unit, None);
        self.target.drain();
        self.remember(f.sent.tid, format!("the read at unit {unit}"));
        self.requests += 1;
        self.target.send(&f.bytes)?;
        let heard = match self.target.recv(bound)? {
            Received::Frame { bytes, .. } | Received::Garbage { bytes, .. } => bytes,
            Received::Silence { partial, .. } | Received::Closed { partial, .. } => partial,
        };
        // Whatever else comes belongs to this request (a second answer, the rest of a collision).
        self.target.drain();
        Ok((!heard.is_empty()).then_some(heard))
    }

    /// Remember a request's transaction id (Modbus/TCP), to attribute a late answer to it.
    fn remember(&mut self, tid: Option<u16>, by: String) {
        if let Some(tid) = tid {
            if self.recent.len() >= RECENT_REQUESTS {
                self.recent.pop_front();
            }
            self.recent.push_back((tid, by, self.target.now()));
        }
    }

    /// The answers among `stale` bytes (Modbus/TCP ADUs, split by their MBAP lengths) whose transaction id
    /// is one of the latest requests', as notes naming the request and how late they came.
    fn late_in(&self, stale: &[u8], when: &str) -> Vec<String> {
        let mut notes = Vec::new();
        let mut rest = stale;
        // Bounded by the bytes: each round consumes at least one ADU header.
        while let Some(len) = tcp::adu_len(rest) {
            if len < 8 || rest.len() < len {
                break;
            }
            let tid = u16::from_be_bytes([rest[0], rest[1]]);
            if self.sentinels.contains(&tid) {
                rest = &rest[len..];
                continue;
            }
            if let Some((_, by, sent_at)) = self.recent.iter().rev().find(|(t, _, _)| *t == tid) {
                notes.push(format!(
                    "a late answer (transaction id {tid}) to a request of {by} arrived within {} ms after that request, {when}: noted, taken for no step's answer",
                    self.target.now().saturating_sub(*sent_at).as_millis()
                ));
            }
            rest = &rest[len..];
        }
        notes
    }

    /// Modbus/TCP: while what came is an answer to an earlier request (its transaction id is one of the
    /// latest requests' and none of this step's), note it as late, keep it in the wire log, and wait the rest
    /// of `wait` (counted from `start`, when the receive began) for this step's own answer. Bounded by a
    /// count and by `wait`.
    fn skip_late(
        &mut self,
        mut got: Received,
        frames: &[Framed],
        (start, wait): (Duration, Duration),
        findings: &mut Vec<Finding>,
        wire: &mut Vec<WireEvent>,
    ) -> Result<Received, TargetError> {
        for _ in 0..8 {
            let Received::Frame {
                bytes, first_at, ..
            } = &got
            else {
                break;
            };
            if bytes.len() < 8 {
                break;
            }
            let tid = u16::from_be_bytes([bytes[0], bytes[1]]);
            if frames.iter().any(|f| f.sent.tid == Some(tid)) {
                break;
            }
            if let Some(k) = self.sentinels.iter().position(|t| *t == tid) {
                // The late answer of a silence sentinel: expected, not this step's; dropped.
                self.sentinels.remove(k);
                let left = wait.saturating_sub(self.target.now().saturating_sub(start));
                got = self.recv_answer(frames, left)?;
                continue;
            }
            let Some((_, by, sent_at)) = self.recent.iter().rev().find(|(t, _, _)| *t == tid)
            else {
                break;
            };
            let by = if *by == self.case_id {
                self.late_in_case.push(tid);
                "an earlier step of this case".to_string()
            } else {
                by.clone()
            };
            findings.push(Finding {
                severity: Severity::Info,
                text: format!(
                    "a late answer (transaction id {tid}) to a request of {by} arrived {} ms after that request: noted, not taken for this step's answer",
                    first_at.saturating_sub(*sent_at).as_millis()
                ),
            });
            record(&got, wire);
            let left = wait.saturating_sub(self.target.now().saturating_sub(start));
            got = self.recv_answer(frames, left)?;
        }
        Ok(got)
    }

    /// Whether the silence after `frames` may be proven by a sentinel: Modbus/TCP to a real target, sentinels
    /// on (and not given up on this target), the reference kept the connection, and every frame complete by
    /// its own MBAP length (all its pieces are sent before the sentinel). A frame whose content is malformed
    /// (a foreign protocol id, an unknown function) still ends where its MBAP length says; but a target still
    /// waiting for the rest of a frame (an MBAP length above the bytes sent) would take the sentinel's bytes
    /// for it: there the window is listened out, as before.
    fn sentinel_may_prove(&self, frames: &[Framed], reference_closed: bool) -> bool {
        self.cfg.timing.sentinel
            && !self.sentinel_given_up
            && !self.cfg.is_sim
            && !reference_closed
            && self.target.framing() == Framing::Tcp
            && !frames.is_empty()
            && frames
                .iter()
                .all(|f| tcp::adu_len(&f.bytes) == Some(f.bytes.len()))
    }

    /// A silence may be proven by half-closing the connection (see `prove_silence_by_close`): Modbus/TCP to a
    /// real target, proofs not turned off, the reference keeps the connection, the case reconnects next.
    fn close_may_prove(&self, reference_closed: bool) -> bool {
        self.cfg.timing.sentinel
            && self.reconnect_next
            && !self.cfg.is_sim
            && !reference_closed
            && self.target.framing() == Framing::Tcp
    }

    /// A silence that is due, settled by a proof where one applies: a sentinel first, else the target's
    /// close; `None` where neither applies (or the target keeps a half-closed connection: then the window
    /// was listened out inside, and its observation is returned).
    fn prove_silence_if_possible(
        &mut self,
        frames: &[Framed],
        reference_closed: bool,
        findings: &mut Vec<Finding>,
        wire: &mut Vec<WireEvent>,
    ) -> Result<Option<Received>, TargetError> {
        if self.sentinel_may_prove(frames, reference_closed) {
            return self.prove_silence(frames, findings, wire).map(Some);
        }
        if self.close_may_prove(reference_closed) {
            return self.prove_silence_by_close();
        }
        Ok(None)
    }

    /// Silence proven by a sentinel (issue 17): the known-good read is sent right behind the request that
    /// must go unanswered, on the same connection, to the target and to the reference (which counts it as
    /// the target does). Its answer, with nothing for this step's request before it, proves the silence: a
    /// Modbus/TCP server takes the requests of a connection in order. (Not one seen answering out of
    /// request order, `pipelined-response-order=transaction-id`: it gets no more sentinels. A sentinel
    /// answered with exception 06, Server Busy, proves nothing: the window is listened out.) An answer of
    /// this step's request that comes first is returned (and judged, as an answer where silence was due);
    /// a late answer of an earlier request is noted as `skip_late` does. No sentinel answer within the answer timeout (a target that
    /// answers nothing now, or a reference that would not answer the sentinel either): the silence stands
    /// as when the window is listened out, and the sentinel's answer is dropped if it comes later.
    fn prove_silence(
        &mut self,
        frames: &[Framed],
        findings: &mut Vec<Finding>,
        wire: &mut Vec<WireEvent>,
    ) -> Result<Received, TargetError> {
        let pdu = crate::cases::catalog::known_good_read(&self.profile);
        let f = self.frame_aside(&pdu);
        let Some(tid) = f.sent.tid else {
            return self.target.recv(self.cfg.timing.silence);
        };
        self.shadow.send(&f.bytes)?;
        let (reference_answers, _) = self.shadow.settle();
        let _ = self.shadow.take_decisions();
        self.requests += 1;
        self.target.send(&f.bytes)?;
        if self.sentinels.len() >= 16 {
            self.sentinels.pop_front();
        }
        self.sentinels.push_back(tid);
        let bound = if reference_answers.is_empty() {
            self.cfg.timing.silence
        } else {
            self.cfg.timing.timeout.max(self.cfg.timing.silence)
        };
        let start = self.target.now();
        let got = self.recv_answer(frames, bound)?;
        let Received::Frame { bytes, .. } = &got else {
            if matches!(got, Received::Silence { .. }) && !reference_answers.is_empty() {
                self.sentinel_given_up = true;
            }
            return Ok(got);
        };
        let theirs = (bytes.len() >= 2).then(|| u16::from_be_bytes([bytes[0], bytes[1]]));
        let sentinel_busy = theirs == Some(tid) && busy_refusal(bytes);
        if frames
            .iter()
            .any(|f| f.sent.tid.is_some() && f.sent.tid == theirs)
        {
            // This step's request answered (where silence was due): judged as it came.
            return Ok(got);
        }
        // The sentinel's answer, or first late answers of earlier requests (noted by `skip_late`, which drops
        // the sentinel's answer when it follows them and then listens on).
        let after = if theirs == Some(tid) {
            None
        } else {
            Some(self.skip_late(got, frames, (start, bound), findings, wire)?)
        };
        // Anything but the sentinel's answer, or silence after it was dropped, is the step's to judge.
        let sentinel_seen = |a: &Received| match a {
            Received::Silence { .. } => !self.sentinels.contains(&tid),
            Received::Frame { bytes, .. } => bytes.get(..2) == Some(&tid.to_be_bytes()[..]),
            _ => false,
        };
        if let Some(other) = after.filter(|a| !sentinel_seen(a)) {
            return Ok(other);
        }
        // A sentinel refused with exception 06 (Server Busy: `pipelined-server-busy`) says the drive may
        // still be busy with an earlier request, not done with it: no proof; the window is listened out.
        if sentinel_busy {
            self.sentinels.retain(|t| *t != tid);
            let left = self
                .cfg
                .timing
                .silence
                .saturating_sub(self.target.now().saturating_sub(start));
            let got = self.recv_answer(frames, left)?;
            if matches!(got, Received::Silence { .. }) {
                self.silences.listened += 1;
            }
            return Ok(got);
        }
        // The sentinel's answer came with nothing for this step before it: the silence is proven.
        self.sentinels.retain(|t| *t != tid);
        self.silences.sentinel += 1;
        Ok(Received::Silence {
            partial: Vec::new(),
            at: self.target.now(),
        })
    }

    /// Modbus/TCP to a real target: how the silences due were settled.
    pub fn silences(&self) -> Silences {
        self.silences
    }

    /// The timeouts and windows this runner listens with.
    pub fn timing(&self) -> Timing {
        self.cfg.timing
    }

    /// Requests sent to the target so far: the cases', the sentinels, the liveness probes and the
    /// restore's reads and writes (a request sent in pieces counts once, requests sent together each).
    pub fn requests(&self) -> u64 {
        self.requests
    }

    /// Silence proven by the target's close, for a request no sentinel can follow (its MBAP length is not
    /// its size: the target may still be waiting for bytes, and would take a sentinel's for them) when the
    /// case opens a new connection next anyway (`Step::Reconnect`). The harness half-closes the connection
    /// (TCP FIN: nothing more comes from it) and reads on: whatever the target answers still arrives before
    /// its own FIN, so a close with nothing before it proves that nothing was or will be answered on this
    /// connection. A target that keeps a half-closed connection open is listened to for the window, as
    /// without. Only where the reference keeps its connection: where it closes, the close is what is judged.
    ///
    /// Before the half-close the target is listened to for twice the slowest of its last answers (the whole
    /// window before any answer was timed, the pre-flight read's included): a server
    /// may write its answer on a later turn of its event loop and close as soon as it reads the harness's
    /// FIN, dropping it (modbus-serial 8.0.25 does, answering a request with a foreign protocol id: with the
    /// FIN right behind the request its answer was never sent, and the request it must ignore PASSed, where
    /// a window listened out FAILs it).
    fn prove_silence_by_close(&mut self) -> Result<Option<Received>, TargetError> {
        // No answer timed yet: the whole window.
        let slowest = self.latencies.slowest();
        let grace = if slowest.is_zero() {
            self.cfg.timing.silence
        } else {
            (slowest * 2).min(self.cfg.timing.silence)
        };
        if !grace.is_zero() {
            let got = self.target.recv(grace)?;
            if !matches!(&got, Received::Silence { partial, .. } if partial.is_empty()) {
                return Ok(Some(got));
            }
        }
        if !self.target.end_sending()? {
            return Ok(None);
        }
        let got = self.target.recv(self.cfg.timing.silence)?;
        Ok(Some(match got {
            Received::Closed { partial, at } if partial.is_empty() => {
                self.silences.close += 1;
                Received::Silence { partial, at }
            }
            other => {
                if matches!(other, Received::Silence { .. }) {
                    self.silences.listened += 1;
                }
                other
            }
        }))
    }

    /// The first request of a case sent since the target last answered (case id, bytes): the one that
    /// preceded a silence.
    pub fn first_unanswered(&self) -> Option<&(String, Vec<u8>)> {
        self.unanswered.first()
    }

    /// After a step whose due answer did not come, while the case has requests left to send: send the
    /// known-good read `probe` (listening up to `bound`) before the next one. Answered: the case goes on.
    /// Not answered: on a target with connections the read is tried once more on a new one; either way the
    /// case stops there (see [`Stall`]), the step FAILs saying so, and its remaining steps are not sent.
    /// Without this (the default, and `fuzz`, which probes after each case), the remaining steps go out as
    /// they come, to a target that may no longer hear them, each FAILing for the one request that silenced
    /// it, put-back steps included.
    pub fn watch_mid_case(&mut self, probe: Vec<u8>, bound: Duration) {
        self.mid_case = Some((probe, bound));
    }

    /// Modbus/TCP: whether the answer to the last case's request `sent` (its frame) came late, during a later
    /// step of the case (noted there as a late answer, not taken for that step's): the drive answered it,
    /// after the timeout. Never on RTU, which has no transaction ids.
    pub fn answered_late(&self, sent: &[u8]) -> bool {
        // The transaction id as sent, in a frame whose header a case may have altered.
        sent.get(..2).is_some_and(|t| {
            self.late_in_case
                .contains(&u16::from_be_bytes([t[0], t[1]]))
        })
    }

    /// Let `pause` pass with nothing sent, and say whether an answer came from the target meanwhile (taken
    /// and dropped): before a case is run again after an attempt that got no answer, a frame that decodes
    /// as a response coming now is a late answer to that attempt (the drive answered, after the timeout; no
    /// frame was lost). Bytes that are no such frame (a stray byte of a noisy line, a frame whose CRC does
    /// not check) prove nothing: the case is run again.
    pub fn came_within(&mut self, pause: Duration) -> bool {
        self.target.idle(pause);
        self.sync_shadow();
        let framing = self.framing();
        let until = Instant::now() + LATE_LOOK;
        // Receives of a few milliseconds each: one of no time at all returns before it reads the socket or
        // the serial port (it never saw a late answer there); an RTU frame is whole after its silence.
        let came = loop {
            match self.target.recv(Duration::from_millis(5)) {
                Ok(Received::Frame { bytes, .. }) => {
                    break crate::readings::decode_response(framing, &bytes).is_some();
                }
                Ok(Received::Silence { partial, .. })
                    if !partial.is_empty() && Instant::now() < until => {}
                _ => break false,
            }
        };
        self.target.drain();
        came
    }

    /// Whether the last case run was stopped after a step whose due answer did not come, and why.
    pub fn stalled(&self) -> Option<Stall> {
        self.stalled
    }

    /// For a stalled case: the request the silence began after (case id, bytes), the first sent since the
    /// target last answered.
    pub fn stalled_by(&self) -> Option<&(String, Vec<u8>)> {
        self.stalled.and(self.stalled_by.as_ref())
    }

    /// Close and reopen the target's connection (a target that stopped answering may take a new one).
    pub fn reconnect(&mut self) -> Result<(), TargetError> {
        self.target.reconnect()
    }

    /// Let `d` pass with the line idle (virtual time on `sim:`).
    pub fn idle(&mut self, d: Duration) {
        self.target.idle(d);
        self.sync_shadow();
    }

    /// The target's clock.
    pub fn now(&self) -> Duration {
        self.target.now()
    }

    fn frame(&mut self, pdu: &[u8], unit: u8, mutation: Option<&Mutation>) -> Framed {
        // PDU-level mutations alter the PDU, which is then framed correctly (header and CRC match it).
        let altered = mutation.and_then(|m| m.apply_to_pdu(pdu));
        let pdu = altered.as_deref().unwrap_or(pdu);
        // A drive following the SD2x example's FC 43 form gets the cases' well-formed FC 43 requests in it
        // (the PDU the cases meant stays `sent.pdu`, the one judged); a malformed one goes as it is.
        let example = (self.fc43_without_reserved
            && altered.is_none()
            && matches!(Request::decode(pdu), Ok(Request::CanOpen(_))))
        .then(|| codec::canopen_without_reserved(pdu))
        .flatten();
        let case_pdu = pdu;
        let pdu = example.as_deref().unwrap_or(pdu);
        let framing = self.target.framing();
        let tid = (framing == Framing::Tcp).then(|| {
            // Not the id of a sentinel whose answer may still come (after the ids wrapped): that answer would
            // be taken for this request's.
            while self.sentinels.contains(&self.next_tid) {
                self.next_tid = self.next_tid.wrapping_add(1);
            }
            let t = self.next_tid;
            self.next_tid = self.next_tid.wrapping_add(1);
            t
        });
        let mut bytes = Vec::with_capacity(pdu.len() + 7);
        // Anything the strict codec refuses as a request was sent malformed on purpose; so is a request whose
        // function code is an exception response's (128-255, App 4.1), or an FC 43 whose MEI type no
        // interface has (App 6.19): no dissector takes them for requests.
        let mut malformed = case_pdu.len() > codec::MAX_PDU_LEN
            || altered.is_some()
            || case_pdu.first().is_some_and(|f| *f >= 0x80)
            || match Request::decode(case_pdu) {
                Err(_) => true,
                Ok(Request::Raw { function, .. }) => {
                    function == codec::FunctionCode::ENCAPSULATED_INTERFACE
                }
                Ok(_) => false,
            };
        match framing {
            Framing::Tcp => {
                if tcp::encode_adu(tid.unwrap_or(0), unit, pdu, &mut bytes).is_err() {
                    // Over-long on purpose: frame it by hand with the length it really has.
                    bytes.extend_from_slice(&tid.unwrap_or(0).to_be_bytes());
                    bytes.extend_from_slice(&[0, 0]);
                    bytes.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
                    bytes.push(unit);
                    bytes.extend_from_slice(pdu);
                }
            }
            _ => {
                if rtu::encode_adu(unit, pdu, &mut bytes).is_err() {
                    bytes.push(unit);
                    bytes.extend_from_slice(pdu);
                    let c = rtu::crc16(&bytes);
                    bytes.extend_from_slice(&c.to_le_bytes());
                }
            }
        }
        let mut adu_altered = false;
        match mutation {
            Some(Mutation::ProtocolId(p)) if bytes.len() >= 4 && framing == Framing::Tcp => {
                bytes[2..4].copy_from_slice(&p.to_be_bytes());
                malformed = true;
                adu_altered = true;
            }
            Some(Mutation::LengthDelta(d)) if bytes.len() >= 6 && framing == Framing::Tcp => {
                let l = u16::from_be_bytes([bytes[4], bytes[5]]).wrapping_add_signed(*d);
                bytes[4..6].copy_from_slice(&l.to_be_bytes());
                malformed = true;
                adu_altered = true;
            }
            Some(Mutation::BadCrc) if bytes.len() >= 2 && framing != Framing::Tcp => {
                let n = bytes.len();
                bytes[n - 2] ^= 0xFF;
                bytes[n - 1] ^= 0xFF;
                malformed = true;
                adu_altered = true;
            }
            _ => {}
        }
        Framed {
            bytes,
            sent: Sent {
                tid,
                unit,
                pdu: case_pdu.to_vec(),
            },
            malformed,
            adu_altered,
        }
    }

    fn pace(&mut self) {
        self.pace_requests(1);
    }

    /// `--max-rate`: wait until `requests` more requests may go out, counting from the last that went.
    /// The pieces of one request are not paced apart (that would stretch a split frame the case means to
    /// arrive as one: past t1.5 on a line, past a drive's partial-frame or idle timeout on TCP).
    fn pace_requests(&mut self, requests: usize) {
        let Some(rate) = self.cfg.safety.max_rate.filter(|_| !self.cfg.is_sim) else {
            return;
        };
        if let Some(next) = self.next_send {
            let now = Instant::now();
            if now < next {
                std::thread::sleep(next - now);
            }
        }
        let gap = Duration::from_secs_f64(1.0 / rate.max(0.001));
        // Bounded: a step sends a few requests at most.
        let n = u32::try_from(requests.clamp(1, 1000)).unwrap_or(1);
        self.next_send = Some(Instant::now() + gap * n);
    }

    fn sync_shadow(&mut self) {
        let t = self.target.now();
        let s = self.shadow.now();
        if t > s {
            self.shadow.idle(t - s);
        }
    }

    /// The write that puts back what `slot` kept: at `address` for registers and coils (`None`: where they
    /// were read). `None` when nothing was kept.
    fn restore_pdu(&self, address: Option<u16>, slot: usize) -> Option<Vec<u8>> {
        let kept = self.slots.get(slot)?.as_ref()?;
        kept.restore(address, &self.profile)?.to_bytes().ok()
    }

    /// The request PDUs of the last case run that the target answered only with an exception response: the
    /// writes among them were not taken, so a parameter they alone would have written is unchanged by them
    /// (see [`crate::restore::Keeper::taken`]).
    pub fn refused_writes(&self) -> &[Vec<u8>] {
        &self.refused_writes
    }

    /// Run one case (already selected and allowed by the policy).
    pub fn run_case(&mut self, case: &Case) -> Result<CaseResult, TargetError> {
        // Requests of pipelined cases on the wire: what arrives is theirs, not stale.
        let (late, wire) = if self.ahead.is_empty() {
            self.take_stale()
        } else {
            (Vec::new(), Vec::new())
        };
        self.run_case_after(case, late, wire)
    }

    /// The profile's device-specific contents are the reference's own and the target is not it
    /// (`device.reference_contents`).
    fn contents_free(&self) -> bool {
        !self.cfg.is_sim && self.profile.device.reference_contents
    }

    /// A request whose answer holds device-specific contents (App 6.7 exception status outputs, 6.13 server id
    /// and additional data, 6.18 queues, 6.14 file records where the case wrote none first).
    fn device_specific(&self, fc: Option<&u8>) -> bool {
        match fc {
            Some(0x07 | 0x11 | 0x18) => true,
            Some(0x14) => !self.case_writes_files,
            _ => false,
        }
    }

    /// Why `case` may not write: it writes an output the drive has set up for a drive function.
    fn writes_function_output(&self, case: &Case) -> Option<String> {
        if self.function_outputs.is_empty() {
            return None;
        }
        // Every request the case sends: a write inside a batch, a function-code swap that makes a write, or
        // a restore writes the output as a plain write does.
        for (pdu, _) in case.wire_pdus(&self.profile, self.cfg.unit) {
            let Ok(req) = Request::decode(&pdu) else {
                continue;
            };
            let coils = match &req {
                Request::WriteSingleCoil { address, .. } => Some((*address, 1)),
                Request::WriteMultipleCoils {
                    address, quantity, ..
                } => Some((*address, *quantity)),
                _ => None,
            };
            let registers = drives::requirements::registers_written(&req);
            for p in &self.function_outputs {
                let coil_hit = matches!((coils, p.coil), (Some((a, q)), Some(c)) if drives::requirements::covers(a, q, c));
                let reg_hit = registers.is_some_and(|(a, q)| {
                    p.registers
                        .iter()
                        .any(|r| drives::requirements::covers(a, q, *r))
                });
                let setup_hit = matches!((&req, p.setup), (Request::VendorWrite { mnemonic, .. }, Some(m)) if *mnemonic == m);
                if !(coil_hit || reg_hit || setup_hit) {
                    continue;
                }
                let (line, kind) = (p.line, p.kind);
                if let Some(m) = p.setup {
                    return Some(format!(
                        "writes I/O point {line} or its setup ({}), which the drive has set up for a drive function (type {kind}, 000 lines 736-760; 0 and 16 are general purpose): a homing or limit switch, or what the function output drives, is wired to it",
                        m.name()
                    ));
                }
                return Some(if p.input {
                    format!(
                        "writes output {line}, whose point the drive has set up as an input (IS type {kind}) and not as an output (OS lists no line {line}): the manual says the outputs must be configured as such (001 line 790), and a sensor or switch is wired to an input"
                    )
                } else {
                    format!(
                        "writes output {line}, which the drive has set up for a drive function (OS type {kind}, not 16, general purpose): the manual says the outputs must be configured as such (001 line 790), and writing one the drive drives would fight the drive and whatever is wired to it"
                    )
                });
            }
        }
        None
    }

    /// Learn which outputs the drive has set up for a drive function (the LMD's OS, "Output setup": type 16
    /// is a general purpose output, 17 moving, 18 fault, ..., 001 lines 1577-1581; "the outputs must be
    /// configured as such", line 790), and which of its points it has set up as inputs (IS), before the
    /// cases: one FC 0x41 read of OS, one of IS. The cases that would write such an output are SKIPPED
    /// ([`Runner::not_applicable`]): the drive drives it, refuses the write or fights it, and a PLC, a sensor
    /// or a switch may be wired to it. The read form is "line,type,active" per line, lines apart by ';', a
    /// space or a line break (drives written independently from the manual read all lines so; the manual
    /// prints none). On a drive whose I/O points are shared (the MDrive's S1-S4), see
    /// [`Runner::learn_point_functions`]. Best effort: nothing is learned from an answer in another form.
    pub fn learn_output_setup(&mut self) {
        if self.profile.device.shared_io_points {
            self.learn_point_functions();
            return;
        }
        let Some(os) = self.profile.mnemonic("OS").filter(|m| m.read) else {
            return;
        };
        let Some(mnemonic) = codec::Mnemonic::from_name(&os.name) else {
            return;
        };
        let Some(outputs) = self.read_setup_lines(&mnemonic) else {
            return;
        };
        let inputs = self
            .profile
            .mnemonic("IS")
            .filter(|m| m.read)
            .and_then(|m| codec::Mnemonic::from_name(&m.name))
            .and_then(|m| self.read_setup_lines(&m))
            .unwrap_or_default();
        let coils = self.output_coils();
        let point = |line: u16, kind: i64, input: bool| SetupPoint {
            line,
            kind,
            input,
            coil: coils.get(usize::from(line) - 1).copied(),
            registers: self.output_registers(line),
            setup: None,
        };
        let within = |line: u16| line != 0 && usize::from(line) <= coils.len();
        let mut found: Vec<SetupPoint> = outputs
            .iter()
            .filter(|(line, kind)| within(*line) && *kind != 16)
            .map(|&(line, kind)| point(line, kind, false))
            .collect();
        // A point IS sets up as an input and OS lists as no output (a drive that reads each setup for the
        // lines it has: "1,1,0 4,0,1" from IS, "2,16,1 3,17,1" from OS) is an input: its output is not one
        // the manual lets be written (line 790), and a sensor is wired to it. Only points OS can set up as
        // outputs ("Setup output points 1 – 3", line 1070): point 4 is an input on every LMD, and what its
        // output answers is the freedoms lmd-output-4 and lmd-output-4-write.
        const OS_LINES: u16 = 3;
        found.extend(
            inputs
                .iter()
                .filter(|(line, _)| {
                    within(*line) && *line <= OS_LINES && !outputs.iter().any(|(l, _)| l == line)
                })
                .map(|&(line, kind)| point(line, kind, true)),
        );
        self.function_outputs = found;
    }

    /// The MDrive's I/O points (S1-S4, "A - I/O type", 000 lines 736-760), each read before the cases and
    /// given to the reference drive, and those set up for a drive function: an
    /// input function (homing, a limit, soft stop, jog, reset: types 1-11) or an output function (moving,
    /// fault, ...: 17-25). A commissioned drive's homing or limit switch, or the PLC input its "moving"
    /// output feeds, is wired to such a point: no case writes its setup or its output (the io-point cases
    /// reconfigure the general purpose points only: 0, inputs by default, line 1263, and 16).
    fn learn_point_functions(&mut self) {
        let coils = self.output_coils();
        let mut found = Vec::new();
        for (i, coil) in coils.iter().enumerate() {
            let line = i as u16 + 1;
            let Some(setup) = self
                .profile
                .mnemonic(&format!("S{line}"))
                .filter(|m| m.read && m.write)
                .and_then(|m| codec::Mnemonic::from_name(&m.name))
            else {
                continue;
            };
            let read = Request::VendorRead { mnemonic: setup };
            let answer = crate::restore::Link::transact(self, &read);
            self.learning_reads.extend(read.to_bytes().ok());
            let Ok(Some(codec::Response::VendorRead { params })) = answer else {
                continue;
            };
            // The reference takes the drive's setup of the point, which a run without --allow-motion does
            // not keep (writing it back is rated motion): it judges the outputs as the drive has them set up
            // (a write of an output whose point is an input is `mdrive-output-write-while-input`, of one
            // whose point is an output not).
            let own = Request::VendorWrite {
                mnemonic: setup,
                params: crate::capture::setting_params(&params),
            };
            let _ = crate::restore::Link::transact(&mut self.reference(), &own);
            let text = String::from_utf8_lossy(&params);
            let Some(kind) = text
                .trim()
                .trim_start_matches('=')
                .split(',')
                .next()
                .and_then(|x| x.trim().parse::<i64>().ok())
            else {
                continue;
            };
            if kind == 0 || kind == 16 {
                continue;
            }
            found.push(SetupPoint {
                line,
                kind,
                input: kind < 16,
                coil: Some(*coil),
                registers: self.output_registers(line),
                setup: Some(setup),
            });
        }
        self.function_outputs = found;
    }

    /// The coils of the I/O points' outputs, point 1 first.
    fn output_coils(&self) -> Vec<u16> {
        let mut coils: Vec<u16> = self
            .profile
            .coils
            .iter()
            .map(|c| c.get_ref().address)
            .collect();
        coils.sort_unstable();
        coils
    }

    /// The registers that write the output of I/O point `line`: its own (O1-O4) and the groups (OT, OL).
    fn output_registers(&self, line: u16) -> Vec<u16> {
        ["OT".to_string(), "OL".to_string(), format!("O{line}")]
            .iter()
            .filter_map(|m| self.profile.register_by_mnemonic(m).map(|r| r.address))
            .collect()
    }

    /// The lines of an I/O setup read with FC 0x41 (`mnemonic`: OS or IS), each as (line, type), in any of
    /// the forms [`crate::capture::setting_lines`] reads; `None` where the drive answers otherwise. Counted as
    /// a learning read.
    fn read_setup_lines(&mut self, mnemonic: &codec::Mnemonic) -> Option<Vec<(u16, i64)>> {
        let read = Request::VendorRead {
            mnemonic: *mnemonic,
        };
        let answer = crate::restore::Link::transact(self, &read);
        self.learning_reads.extend(read.to_bytes().ok());
        let Ok(Some(codec::Response::VendorRead { params })) = answer else {
            return None;
        };
        Some(
            crate::capture::setting_lines(&params)
                .iter()
                .filter_map(|line| {
                    let text = String::from_utf8_lossy(line);
                    let v: Vec<i64> = text
                        .trim_start_matches('=')
                        .split(',')
                        .filter_map(|x| x.trim().parse().ok())
                        .collect();
                    let (&line, &kind) = (v.first()?, v.get(1)?);
                    Some((u16::try_from(line).ok()?, kind))
                })
                .collect(),
        )
    }

    /// The holding registers the keeper saw change by themselves (`live`: each read twice with nothing
    /// written between, see [`crate::restore::Account::live`]). An exact read of one is compared within
    /// three times what it moved by (2 at least), as a measured value: a read-back of 1 written to an
    /// encoder count that jitters by 2 reads 3 on a drive with its motor attached.
    pub fn learn_live(&mut self, live: &[crate::restore::Unrestored]) {
        use crate::restore::Value;
        self.live = live
            .iter()
            .filter_map(|u| {
                let address = u16::from_str_radix(u.key.strip_prefix("holding:0x")?, 16).ok()?;
                let (Value::Words(a), Some(Value::Words(b))) = (&u.before, &u.after) else {
                    return None;
                };
                if a.len() != b.len() || a.is_empty() || a.len() > 2 {
                    return None;
                }
                let order = self.profile.device.word_order;
                let int = |w: &[u16]| -> i64 {
                    if w.len() == 2 {
                        i64::from(order.join(w[0], w[1]) as i32)
                    } else {
                        i64::from(w[0] as i16)
                    }
                };
                let spread = u32::try_from(int(a).abs_diff(int(b))).unwrap_or(u32::MAX);
                Some((address, a.len() as u16, spread.saturating_mul(3).max(2)))
            })
            .collect();
    }

    /// The tolerance of an exact read that covers a register seen to change by itself (`None`: none).
    fn live_tolerance(&self, pdu: &[u8]) -> Option<u32> {
        if self.live.is_empty() {
            return None;
        }
        let Ok(Request::ReadHoldingRegisters { address, quantity }) = Request::decode(pdu) else {
            return None;
        };
        self.live
            .iter()
            .filter(|(a, w, _)| {
                drives::requirements::covers(address, quantity, *a)
                    || drives::requirements::covers(address, quantity, a + (w - 1))
            })
            .map(|(_, _, t)| *t)
            .max()
    }

    /// Why `case` says nothing about this drive, as far as the run has learned it: an FC 43 request that sets
    /// the layout's Reserved field, to a drive that takes FC 43 in the manual's example form, which has no
    /// such field (freedom `sd2x-fc43-reserved-byte`; the request would go out as a plain one); a write of an
    /// output the drive has set up for a drive function ([`Runner::learn_output_setup`]).
    fn not_applicable(&self, case: &Case) -> Option<String> {
        if let Some(why) = self.writes_function_output(case) {
            return Some(why);
        }
        if !self.fc43_without_reserved {
            return None;
        }
        case.steps.iter().any(|s| {
            matches!(s, Step::Exchange { send: Outgoing::Pdu(p), .. }
                if matches!(Request::decode(p), Ok(Request::CanOpen(a)) if a.reserved != 0))
        })
        .then(|| {
            "sets the FC 43 Reserved field, which this drive's form of FC 43 (the manual's example, without it; sd2x-fc43-reserved-byte) does not have".to_string()
        })
    }

    /// Discard what arrived unasked before a case. Modbus/TCP: answers that came after their step gave up
    /// are attributed to their requests by transaction id, as notes for the case's first step, and kept for
    /// its wire log (on other framings they are only discarded).
    fn take_stale(&mut self) -> (Vec<String>, Vec<WireEvent>) {
        let mut wire = Vec::new();
        if self.target.framing() != Framing::Tcp {
            self.target.drain();
            return (Vec::new(), wire);
        }
        let stale = self.target.drain_stale();
        let notes = self.late_in(&stale, "between two cases");
        if !stale.is_empty() {
            wire.push(WireEvent {
                dir: Dir::Rx,
                at: self.target.now(),
                bytes: stale,
                intended_malformed: false,
            });
        }
        (notes, wire)
    }

    /// Run one case, the stale answers before it taken already (`late`: notes for its first step; `wire`:
    /// its wire log so far).
    fn run_case_after(
        &mut self,
        case: &Case,
        late: Vec<String>,
        mut wire: Vec<WireEvent>,
    ) -> Result<CaseResult, TargetError> {
        if let Some(reason) = self.not_applicable(case) {
            return Ok(CaseResult::skipped(&case.id, reason));
        }
        let started = self.target.now();
        let mut steps = Vec::new();
        // One empty slot per capture the case names; a restore of a slot nothing filled is SKIPPED.
        self.slots = vec![None; case.slots()];
        self.case_id.clone_from(&case.id);
        self.late_in_case.clear();
        self.case_freedoms.clone_from(&case.freedoms);
        self.case_tags.clone_from(&case.tags);
        self.refused = false;
        self.stalled = None;
        self.stalled_by = None;
        self.refused_writes.clear();
        self.case_writes_files = case.steps.iter().any(|s| {
            matches!(s, Step::Exchange { send: Outgoing::Pdu(p), .. } if p.first() == Some(&0x15))
        });
        for (k, step) in case.steps.iter().enumerate() {
            if self.refused {
                break;
            }
            self.reconnect_next = matches!(case.steps.get(k + 1), Some(Step::Reconnect));
            match step {
                Step::Wait(d) => {
                    self.target.idle(*d);
                    self.sync_shadow();
                }
                Step::Reconnect => {
                    self.target.reconnect()?;
                    self.shadow.reconnect()?;
                }
                Step::Until {
                    read,
                    mask,
                    value,
                    timeout,
                    stop,
                    every,
                    within,
                    note,
                } => {
                    let r = self.until_or_stop(
                        read,
                        (*mask, *value),
                        *timeout,
                        stop,
                        (*every, *within),
                        note,
                        &mut wire,
                    )?;
                    steps.push(r);
                }
                Step::Persist {
                    send,
                    compare,
                    every,
                    within,
                    note,
                } => {
                    let r = self.persist(send, compare, *every, *within, note, &mut wire)?;
                    steps.push(r);
                }
                Step::Agree {
                    registers,
                    more_registers,
                    object,
                    note,
                } => steps.push(self.agree(*registers, more_registers, *object, note)),
                Step::EventLogShifted {
                    before,
                    after,
                    max_new,
                    note,
                } => steps.push(self.event_log_shifted(*before, *after, *max_new, note)),
                Step::ClearedUnlessFlagged { record, flag, note } => {
                    steps.push(self.cleared_unless_flagged(*record, *flag, note));
                }
                Step::Exchange {
                    send,
                    compare,
                    capture,
                    note,
                } => {
                    let mut r =
                        self.exchange_patiently(send, compare, *capture, note, &mut wire)?;
                    let stop = self.stall_after(&mut r, &case.steps[k + 1..])?;
                    let uncaptured = self.uncaptured(*capture, &mut r, &case.steps[k + 1..]);
                    steps.push(r);
                    if stop || uncaptured {
                        break;
                    }
                }
            }
        }
        if let Some(first) = steps.first_mut().filter(|_| !late.is_empty()) {
            first.findings.extend(late);
            first.verdict = worse(first.verdict, Verdict::Informational);
        }
        if case.has(Tag::RunTiming) {
            steps.push(self.judge_answer_gaps());
        }
        let mut verdict = Verdict::Pass;
        for s in &steps {
            verdict = worse(verdict, s.verdict);
        }
        let verdict = match case.level {
            crate::cases::Level::Info if verdict != Verdict::Pass => Verdict::Informational,
            _ => verdict,
        };
        let mut result = CaseResult {
            id: case.id.clone(),
            verdict,
            expected_deviation: None,
            steps,
            wire,
            duration: self.target.now().saturating_sub(started),
            reason: None,
        };
        // A request refused by the safety check is a harness bug: no expectations file hides it.
        if verdict != Verdict::Pass
            && !self.refused
            && let Some((v, reason)) = self.expectations.lookup(&case.id)
        {
            result.expected_deviation = Some((verdict, reason.to_string()));
            result.verdict = v;
        }
        Ok(result)
    }

    /// See [`Runner::watch_mid_case`]: after `step`, with `rest` of the case to come, whether the case stops
    /// there (the finding is added to `step`). Not when nothing of `rest` sends, nor when the case opens a
    /// new connection next (its own design: the request may leave the old one hung).
    fn stall_after(&mut self, step: &mut StepResult, rest: &[Step]) -> Result<bool, TargetError> {
        if self.mid_case.is_none()
            || !step.unanswered()
            || matches!(rest.first(), Some(Step::Reconnect))
        {
            return Ok(false);
        }
        let sends = |s: &Step| {
            matches!(
                s,
                Step::Exchange { .. } | Step::Until { .. } | Step::Persist { .. }
            )
        };
        let left = rest.iter().filter(|s| sends(s)).count();
        // Only now, on the rare step that needs it: the read is copied out of the runner it is sent by.
        let Some((probe, bound)) = self.mid_case.clone().filter(|_| left > 0) else {
            return Ok(false);
        };
        // The request the silence began after: the first sent since the target last answered (an earlier
        // step's whose silence was admitted, say a truncated request the drive still waits on).
        let first = self.unanswered.first().cloned();
        let (answered, notes) = self.probe_mid_case(&probe, bound)?;
        step.findings.extend(notes);
        if answered {
            return Ok(false);
        }
        let after = match &first {
            Some((case, bytes)) if step.sent.as_ref() != Some(bytes) => format!(
                "the request {} ({}, no answer since)",
                crate::liveness::hex(bytes),
                if *case == self.case_id {
                    "an earlier step"
                } else {
                    case.as_str()
                }
            ),
            _ => "this request".to_string(),
        };
        self.stalled_by = first;
        let secs = bound.as_secs_f64();
        let mut stall = Stall::Target;
        if self.target.has_connections() {
            self.target.reconnect()?;
            self.shadow.reconnect()?;
            if self.known_good(&probe, bound)?.0 == crate::liveness::Heard::Modbus {
                stall = Stall::Connection;
            }
        }
        step.findings.push(match stall {
            Stall::Connection => format!(
                "the connection stopped answering after {after}: a known-good read on it got no answer within {secs:.1} s, on a new connection it is answered; the case's {left} remaining step(s) were not sent (they would have gone to a drive whose state after that request is unknown)"
            ),
            Stall::Target => format!(
                "after {after}, a known-good read got no answer within {secs:.1} s{}: the case's {left} remaining step(s) were not sent",
                if self.target.has_connections() {
                    ", on this connection or a new one"
                } else {
                    ""
                }
            ),
        });
        step.verdict = Verdict::Fail;
        self.stalled = Some(stall);
        Ok(true)
    }

    /// The silences before every answer of the run so far (see [`crate::timing`]): FAIL when one surely
    /// began inside t3.5 (a MUST of the serial line guide, 2.5.1.1); INFORMATIONAL when this target's line
    /// cannot be measured.
    fn judge_answer_gaps(&self) -> StepResult {
        let step = |verdict, note: String, findings| step_of(note, verdict, findings);
        if let Err(why) = &self.gaps_measurable {
            return step(
                Verdict::Informational,
                "the silence before the answers: not measured".into(),
                vec![format!("not measured: {why}")],
            );
        }
        match self.gaps.judge() {
            None => step(
                Verdict::Informational,
                "the silence before the answers: not measured".into(),
                vec!["not measured: no answer was received".into()],
            ),
            Some((findings, note)) if findings.is_empty() => step(Verdict::Pass, note, findings),
            Some((findings, note)) => step(Verdict::Fail, note, findings),
        }
    }

    /// The FC 0C log read second must be the one read first with at most `max_new` events entered in front
    /// (see [`Step::EventLogShifted`]).
    fn event_log_shifted(
        &self,
        before: usize,
        after: usize,
        max_new: usize,
        note: &str,
    ) -> StepResult {
        let kept = |slot: usize| {
            self.slots
                .get(slot)
                .and_then(Option::as_ref)
                .and_then(Captured::events)
        };
        let findings = match (kept(before), kept(after)) {
            (Some(first), Some(second)) => match oracle::event_log_shift(first, second, max_new) {
                Some(_) => vec![],
                None => vec![format!(
                    "the event log read after the requests ({}) is not the log read before them ({}) with at most {max_new} new event(s) in front: byte 0 must be the most recent event and each new event must push the older ones back by one (6.10)",
                    codec::hex_spaced(second),
                    codec::hex_spaced(first),
                )],
            },
            // The read's own step is judged already (exception 01 from a drive without FC 0C:
            // UNIMPLEMENTED); nothing to compare here.
            _ => {
                return step_of(
                    format!(
                        "{note}: not compared, one of the two FC 0C reads gave no event log (see its step)"
                    ),
                    Verdict::Skipped,
                    vec![],
                );
            }
        };
        comparison(note, findings)
    }

    /// See [`Step::ClearedUnlessFlagged`]: the record read after its clear is 0, or the flag says an error
    /// condition still exists (then the clear is not seen: INFORMATIONAL).
    fn cleared_unless_flagged(&self, record: usize, flag: usize, note: &str) -> StepResult {
        let kept = |slot: usize| {
            self.slots
                .get(slot)
                .and_then(Option::as_ref)
                .and_then(Captured::registers)
                .and_then(|r| r.first().copied())
        };
        match (kept(record), kept(flag)) {
            (Some(0), _) => comparison(note, vec![]),
            (Some(code), Some(0)) => comparison(
                note,
                vec![format!(
                    "the error record reads {code} after the write of 0 that clears it, and the error flag reads 0: no error condition exists that it could record again"
                )],
            ),
            (Some(code), Some(f)) => step_of(
                note.to_string(),
                Verdict::Informational,
                vec![format!(
                    "the error record reads {code} again after the write of 0 that clears it, and the error flag reads {f}: an error condition still exists, which the drive may record again at once; the clear is not seen"
                )],
            ),
            // A read refused or unanswered is judged by its own step.
            _ => step_of(
                format!("{note}: not compared, a read gave no register (see its step)"),
                Verdict::Skipped,
                vec![],
            ),
        }
    }

    /// A register pair and its mirroring object must hold the same value; registers that mirror discrete
    /// inputs one each (the MDrive/LMD I1-I4) must hold the inputs' states.
    fn agree(&self, registers: usize, more: &[usize], object: usize, note: &str) -> StepResult {
        let order = self.profile.device.word_order;
        let kept = |slot: usize| self.slots.get(slot).and_then(Option::as_ref);
        let regs = kept(registers).and_then(Captured::registers);
        if let Some(inputs) = kept(object).and_then(Captured::inputs) {
            // Every register slot filled, in order (one read's refusal leaves nothing to compare).
            let all: Option<Vec<u16>> = std::iter::once(registers)
                .chain(more.iter().copied())
                .map(|s| kept(s).and_then(Captured::registers).map(<[u16]>::to_vec))
                .collect::<Option<Vec<_>>>()
                .map(|v| v.concat());
            if let Some(r) = all {
                return inputs_agree(&r, inputs, note);
            }
        }
        let obj = kept(object).and_then(Captured::object_value);
        let findings = match (regs, obj) {
            (Some(r), Some(o)) => {
                let v = match r {
                    [a, b] => order.join(*a, *b),
                    [a] => u32::from(*a),
                    _ => u32::MAX,
                };
                if v == o {
                    vec![]
                } else {
                    let swapped = matches!(r, [a, b] if order.join(*b, *a) == o);
                    // The object's data bytes taken big-endian: the SD2x example's byte order (lines
                    // 1334-1335), against the rule stated twice with its own worked example (little-endian,
                    // lines 638-650 and 771), which the harness holds to (freedom `sd2x-fc43-reserved-byte`'s
                    // note: that reading is not admitted).
                    let width = if matches!(r, [_]) { 2 } else { 4 };
                    let big = o.to_le_bytes()[..width]
                        .iter()
                        .fold(0u32, |acc, b| acc << 8 | u32::from(*b));
                    vec![format!(
                        "the registers read 0x{v:08X} ({order:?}) but the object reads 0x{o:08X}{}",
                        if swapped {
                            ": the two views disagree on the word order"
                        } else if big == v {
                            ": the object's data bytes read big-endian would agree (as in the example at lines 1334-1335); FC 43 data are little-endian (lines 638-650, 771)"
                        } else {
                            ""
                        }
                    )]
                }
            }
            // Refused or unanswered: the read's own step judges that (a refusal a freedom admits, such as an
            // FC 43 read by a drive of the other reading of its manual, passes there); nothing to compare.
            _ => {
                return step_of(
                    note.to_string(),
                    Verdict::Informational,
                    vec!["not compared: one of the two reads gave no value (its own step judges why)".into()],
                );
            }
        };
        comparison(note, findings)
    }

    /// True when a read that was to capture a value for the case to put back filled nothing (refused, not
    /// answered, or answered in a form no reading of the manual gives) and a later step of the case writes:
    /// the case stops there, saying so in `r`, because a write whose old value was not read could not be
    /// undone. An eighth-wave MDrive answering a setting's read in a form the harness did not read yet had
    /// that setting changed and left so; an LMD refusing a read of one coil took its write. The step's own
    /// verdict judges the read.
    fn uncaptured(&self, capture: Option<usize>, r: &mut StepResult, rest: &[Step]) -> bool {
        let Some(slot) = capture else {
            return false;
        };
        if self.slots.get(slot).is_some_and(Option::is_some) {
            return false;
        }
        let writes_later = rest.iter().any(|s| {
            matches!(s, Step::Exchange { send: Outgoing::Pdu(p), .. } if crate::cases::safety::is_write(p))
        });
        if !writes_later {
            return false;
        }
        r.findings.push(
            "nothing was captured to restore: the case stops before its write, which could not be undone"
                .into(),
        );
        true
    }

    fn exchange(
        &mut self,
        send: &Outgoing,
        compare: &Compare,
        capture: Option<usize>,
        note: &str,
        wire: &mut Vec<WireEvent>,
    ) -> Result<StepResult, TargetError> {
        self.pre_step = None;
        let Some((frames, pieces)) = self.outgoing(send) else {
            return Ok(StepResult {
                note: note.to_string(),
                sent: None,
                expected: None,
                observed: vec![],
                verdict: Verdict::Skipped,
                findings: vec!["nothing was captured to restore".into()],
            });
        };
        if let Some(refusal) = self.refusal(&frames) {
            self.refused = true;
            return Ok(refusal);
        }
        // The device-specific contents of a profile that declares the reference's own
        // (`device.reference_contents`): in format only against any other target.
        let in_format;
        let near;
        let compare = match (frames.as_slice(), compare) {
            // A register seen to change by itself (an encoder count on a drive with its motor attached):
            // read within its jitter.
            ([f], Compare::Exact) if let Some(tolerance) = self.live_tolerance(&f.sent.pdu) => {
                near = Compare::Near { tolerance };
                &near
            }
            ([f], Compare::Exact | Compare::InRange | Compare::Structure)
                if self.contents_free() && self.device_specific(f.sent.pdu.first()) =>
            {
                // FC 11 and 18 answer as many bytes as the device has (its id and data, its queue); FC 07
                // and 14 as many as the request asks.
                in_format = if matches!(f.sent.pdu.first(), Some(0x11 | 0x18)) {
                    Compare::Any
                } else {
                    Compare::Structure
                };
                &in_format
            }
            _ => compare,
        };
        self.sync_shadow();
        // The reference as it was before the step, to do it again the drive's way where the drive admissibly
        // did otherwise: a request to another unit id, which a drive may ignore (`tcp-unit-ids`), and any
        // request but a plain read, which a choice the drive shows may make it take, refuse or ignore (see
        // [`follows`]). A plain read of the data tables changes no state a choice decides, but for the counts
        // of a drive that may serve or refuse a read of half a register (`partial-register-read`).
        let reads_decided = self.reads_decided;
        let before = frames
            .iter()
            .any(|f| {
                f.sent.unit != self.cfg.unit
                    || frames.len() > 1
                    || f.malformed
                    || reads_decided
                    || !matches!(f.sent.pdu.first(), Some(0x01..=0x04))
            })
            .then(|| self.shadow.clone());
        self.unit_ignored = false;
        self.follow.clear();
        self.frame_decisions = match &before {
            Some(b) if frames.len() > 1 => decisions_one_by_one(b.clone(), &frames),
            _ => Vec::new(),
        };
        let sentinels = self.silences.sentinel;
        let sent = self.send_pieces(&frames, &pieces, wire)?;
        let result =
            self.receive_and_judge(&frames, &pieces, sent, compare, capture, note, wire)?;
        // A well-formed frame no length rule sizes was ended by the drive if it answered it, unless a shorter
        // part of it is a frame too (its last two bytes the CRC of the rest): a drive that ends such frames
        // at the first CRC that fits (as independent SD2x tests/independent/sd2x-i does, FC 0x7C 00 00 00 00
        // 50 00 cut after 0x50) answered that part and holds the rest, which the silence must clear.
        let cut_short = |f: &Framed| (4..f.bytes.len()).any(|n| codec::rtu::crc_ok(&f.bytes[..n]));
        if self.resync_rtu
            && !frames.iter().any(|f| f.malformed || cut_short(f))
            && result
                .observed
                .iter()
                .any(|o| matches!(o, Received::Frame { .. }))
        {
            self.resync_rtu = false;
        }
        if let [f] = frames.as_slice()
            && refused_only(self.target.framing(), &result.observed)
        {
            self.refused_writes.push(f.sent.pdu.clone());
        }
        let follow = std::mem::take(&mut self.follow);
        for (f, v) in &follow {
            self.before_learning();
            self.learned.choose(f, v.clone());
        }
        let ignored = std::mem::take(&mut self.unit_ignored);
        if !follow.is_empty() {
            self.shadow.adopt(self.learned.clone());
        }
        if !ignored && follow.is_empty() {
            // Kept for a step the drive answered Server Busy, which is sent again on the reference as it was.
            self.pre_step = before;
            return Ok(result);
        }
        let Some(mut before) = before else {
            return Ok(result);
        };
        // Do the step again on the reference as it was before it: not at all where the drive ignored it (a
        // write not taken, no counts), else taking the choices the drive showed (a half register taken).
        before.adopt(self.learned.clone());
        self.shadow = before;
        if !ignored {
            for (bytes, gap) in &pieces {
                self.shadow.send(bytes)?;
                if !gap.is_zero() {
                    self.shadow.idle(*gap);
                }
            }
            let _ = self.shadow.settle();
            let _ = self.shadow.take_decisions();
            let _ = self.shadow.take_counter_alternatives();
        }
        self.sync_shadow();
        if self.silences.sentinel > sentinels {
            // The sentinel read that proved the silence reached both drives: the reference gets it again.
            let pdu = crate::cases::catalog::known_good_read(&self.profile);
            let f = self.frame_aside(&pdu);
            self.shadow.send(&f.bytes)?;
            let _ = self.shadow.settle();
            let _ = self.shadow.take_decisions();
        }
        Ok(result)
    }

    /// [`Runner::exchange`], and while the drive answers exception 06 (Server Device Busy) where the reference
    /// answers otherwise, the same request again after a pause (growing from [`BUSY_FIRST_PAUSE`] to
    /// [`BUSY_PAUSE_MAX`], [`Timing::busy_wait`] in all). App 7, exception 06: "The server is engaged in
    /// processing a long-duration program command. The client should retransmit the message later when the
    /// server is free." Drives written independently from the manuals are busy so for 250 ms to 3 s after
    /// an NVM save (S), a program cleared (CP) or an upgrade (UG), for every request or for writes only. The
    /// refused attempt did nothing, so the reference is put back to where it was before it (where the step
    /// copied it: any request but a plain read) and the write is not counted as refused. The answer after
    /// the drive is free is the step's result, with a note of the refusals; a drive still busy after
    /// [`Timing::busy_wait`] has its last answer judged (FAIL), with a finding that says so. Requests sent together
    /// (a batch) are not sent again: their 06 is judged as it is (`pipelined-server-busy`).
    fn exchange_patiently(
        &mut self,
        send: &Outgoing,
        compare: &Compare,
        capture: Option<usize>,
        note: &str,
        wire: &mut Vec<WireEvent>,
    ) -> Result<StepResult, TargetError> {
        let framing = self.target.framing();
        let started = self.target.now();
        let mut pause = BUSY_FIRST_PAUSE;
        let mut refusals = 0usize;
        loop {
            let refused_before = self.refused_writes.len();
            let mut r = self.exchange(send, compare, capture, note, wire)?;
            if let Some(told) = self.recheck_live(send, compare, &r)? {
                let again = self.exchange(send, compare, capture, note, wire)?;
                r = StepResult {
                    note: format!("{}: {told}", again.note),
                    ..again
                };
            }
            let busy = r.verdict == Verdict::Fail
                && !matches!(send, Outgoing::Batch(_))
                && answered_exception(framing, &r, &[codec::ExceptionCode::SERVER_DEVICE_BUSY]);
            let waited = self.target.now().saturating_sub(started);
            if !busy || waited >= self.cfg.timing.busy_wait {
                if refusals > 0 {
                    let told = format!(
                        "answered Server Busy (exception 06) {refusals} time(s) over {} ms before this answer; sent again each time (App 7: the client retransmits later)",
                        waited.as_millis()
                    );
                    if busy {
                        r.findings.push(format!(
                            "still Server Busy (exception 06) after {} attempts over {} ms: App 7 lets a drive be busy with a long-duration program command and has the client retransmit later; the harness waits {} ms (--busy-wait)",
                            refusals + 1,
                            waited.as_millis(),
                            self.cfg.timing.busy_wait.as_millis()
                        ));
                    }
                    r.note = format!("{}: {told}", r.note);
                }
                return Ok(r);
            }
            refusals += 1;
            // The drive did nothing with it: neither does the reference, and the write is not one it refused.
            self.refused_writes.truncate(refused_before);
            if let Some(before) = self.pre_step.take() {
                self.shadow = before;
            }
            self.sync_shadow();
            self.busy_pause(&mut pause);
        }
    }

    /// Where an exact read of holding registers FAILed with values (no exception, as many as asked) on a
    /// drive that is not the reference: read them [`LIVE_RECHECKS`] more times, [`LIVE_RECHECK_GAP`] apart,
    /// nothing written between. Registers that read otherwise between those reads change by themselves: a
    /// measured value on a drive with its motor attached (an encoder count jittering at standstill) that
    /// the keeper's reads before the first write happened to read the same each time (a count toggling
    /// between two values does so once in 128, see [`crate::restore`]). From then on an exact read of them is
    /// compared within three times what they moved, as for those the keeper found ([`Runner::learn_live`]),
    /// and the step is done again: what the reason is, `None` where nothing moved (the FAIL stands: a value
    /// read wrong the same way every time, a word order mixed up, is no measurement).
    fn recheck_live(
        &mut self,
        send: &Outgoing,
        compare: &Compare,
        r: &StepResult,
    ) -> Result<Option<String>, TargetError> {
        if r.verdict != Verdict::Fail || self.cfg.is_sim || !matches!(compare, Compare::Exact) {
            return Ok(None);
        }
        let Outgoing::Pdu(pdu) = send else {
            return Ok(None);
        };
        let Ok(Request::ReadHoldingRegisters { address, quantity }) = Request::decode(pdu) else {
            return Ok(None);
        };
        let framing = self.target.framing();
        let values_of = |a: Option<codec::Response>| match a {
            Some(codec::Response::ReadHoldingRegisters { values })
                if values.len() == usize::from(quantity) =>
            {
                Some(values)
            }
            _ => None,
        };
        let [Received::Frame { bytes, .. }] = r.observed.as_slice() else {
            return Ok(None);
        };
        let Some(first) = values_of(crate::readings::decode_response(framing, bytes)) else {
            return Ok(None);
        };
        let mut reads = vec![first];
        for _ in 0..LIVE_RECHECKS {
            self.idle(LIVE_RECHECK_GAP);
            let answer = self.transact_pdu(pdu)?;
            let Some(values) =
                values_of(answer.and_then(|a| crate::readings::decode_response_pdu(&a)))
            else {
                return Ok(None);
            };
            reads.push(values);
        }
        let order = self.profile.device.word_order;
        let mut moved = Vec::new();
        let mut i = 0usize;
        while i < usize::from(quantity) {
            let a = address.wrapping_add(i as u16);
            let reg = self
                .profile
                .register_at(a, false)
                .filter(|r| r.address == a);
            let (w, signed) = match reg {
                Some(r) if r.width == 2 && i + 1 < usize::from(quantity) => (2, r.signed),
                Some(r) => (1, r.signed),
                None => (1, false),
            };
            let ints: Vec<i64> = reads
                .iter()
                .map(|v| match (w, signed) {
                    (2, true) => i64::from(order.join(v[i], v[i + 1]) as i32),
                    (2, false) => i64::from(order.join(v[i], v[i + 1])),
                    (_, true) => i64::from(v[i] as i16),
                    _ => i64::from(v[i]),
                })
                .collect();
            let (lo, hi) = (
                ints.iter().copied().min().unwrap_or(0),
                ints.iter().copied().max().unwrap_or(0),
            );
            if hi > lo {
                let seen: Vec<String> = ints.iter().map(i64::to_string).collect();
                moved.push((a, w as u16, hi.abs_diff(lo), seen.join(", ")));
            }
            i += w;
        }
        if moved.is_empty() {
            return Ok(None);
        }
        let mut told = Vec::new();
        for (a, w, spread, seen) in moved {
            let tolerance = u32::try_from(spread.saturating_mul(3))
                .unwrap_or(u32::MAX)
                .max(2);
            match self.live.iter_mut().find(|(x, _, _)| *x == a) {
                Some(e) => e.2 = e.2.max(tolerance),
                None => self.live.push((a, w, tolerance)),
            }
            told.push(format!("0x{a:04X} read {seen}"));
        }
        Ok(Some(format!(
            "the first read did not match, and {} more reads with nothing written between showed {} changing by itself (a measured value): read again, compared within three times what it moved",
            LIVE_RECHECKS,
            told.join("; ")
        )))
    }

    /// Wait `pause` for a drive that answered Server Busy, and double it for the next time (up to
    /// [`BUSY_PAUSE_MAX`]).
    fn busy_pause(&mut self, pause: &mut Duration) {
        self.target.idle(*pause);
        self.sync_shadow();
        *pause = (*pause * 2).min(BUSY_PAUSE_MAX);
    }

    /// [`Step::Persist`]: send `send` until the drive takes it (no exception 04 or 06 where the reference
    /// answers otherwise), every `every`, `within` at most; the reference is put back to its state before each
    /// refused attempt. The last attempt is the step's result, with a note of the refusals before it.
    fn persist(
        &mut self,
        send: &Outgoing,
        compare: &Compare,
        every: Duration,
        within: Duration,
        note: &str,
        wire: &mut Vec<WireEvent>,
    ) -> Result<StepResult, TargetError> {
        let framing = self.target.framing();
        let tries = within.as_micros() / every.as_micros().max(1) + 1;
        let mut k = 0u128;
        let mut codes: Vec<u8> = Vec::new();
        loop {
            let before = self.shadow.clone();
            let mut r = self.exchange(send, compare, None, note, wire)?;
            k += 1;
            let busy = r.verdict == Verdict::Fail
                && answered_exception(
                    framing,
                    &r,
                    &[
                        codec::ExceptionCode::SERVER_DEVICE_FAILURE,
                        codec::ExceptionCode::SERVER_DEVICE_BUSY,
                    ],
                );
            if busy && k >= tries {
                // Refused as busy all along: the drive cannot move now (no motor, no home switch set up, a
                // fault or a limit the harness cannot see or clear). Nothing was done; the reference does
                // not do it either, and the refusal is worth saying, not a FAIL of the protocol.
                self.shadow = before;
                self.sync_shadow();
                r.findings = vec![format!(
                    "refused as busy (exception 04 or 06) at every one of {k} attempts over {} ms: the drive cannot do it now (no motor, no home switch set up, a fault or a limit the run cannot see); nothing was done",
                    every.as_micros() * (k - 1) / 1000
                )];
                r.verdict = Verdict::Informational;
                return Ok(r);
            }
            if !busy {
                if !codes.is_empty() {
                    codes.dedup();
                    let codes: Vec<String> = codes.iter().map(|c| format!("{c:02X}")).collect();
                    r.note = format!(
                        "{note}: refused as busy ({}) {} time(s) over {} ms before this answer",
                        codes.join(", "),
                        k - 1,
                        (every.as_micros() * (k - 1) / 1000)
                    );
                }
                return Ok(r);
            }
            codes.extend(r.observed.iter().filter_map(|o| match o {
                Received::Frame { bytes, .. } => {
                    match crate::readings::decode_response(framing, bytes) {
                        Some(codec::Response::Exception { code, .. }) => Some(code.0),
                        _ => None,
                    }
                }
                _ => None,
            }));
            // The drive did not take it: neither does the reference.
            self.shadow = before;
            self.sync_shadow();
            self.target.idle(every);
            self.sync_shadow();
        }
    }

    /// [`Step::Until`], and where the value never came and `stop` is not empty, the requests of `stop` sent
    /// and the register read again for `within`: nothing is put back on a moving axis. A drive that does not
    /// come to the value after the stop FAILs.
    #[allow(clippy::too_many_arguments)]
    fn until_or_stop(
        &mut self,
        read: &[u8],
        mask_value: (u16, u16),
        timeout: Verdict,
        stop: &[Vec<u8>],
        timing: (Duration, Duration),
        note: &str,
        wire: &mut Vec<WireEvent>,
    ) -> Result<StepResult, TargetError> {
        let mut r = self.until(read, mask_value, timeout, timing, note, wire)?;
        if r.verdict != timeout || timeout == Verdict::Pass || stop.is_empty() {
            return Ok(r);
        }
        for pdu in stop {
            let s = self.exchange(
                &Outgoing::Pdu(pdu.clone()),
                &Compare::Structure,
                None,
                "stop",
                wire,
            )?;
            let answers: Vec<String> = s
                .observed
                .iter()
                .map(|o| match o {
                    Received::Frame { bytes, .. } => codec::hex_spaced(bytes),
                    _ => "no answer".to_string(),
                })
                .collect();
            r.findings.push(format!(
                "sent {} to stop it: {}",
                codec::hex_spaced(pdu),
                answers.join(", ")
            ));
        }
        let again = self.until(read, mask_value, timeout, timing, note, wire)?;
        r.findings.extend(again.findings);
        if again.verdict == timeout {
            r.findings.push("it did not stop".into());
            r.verdict = worse(r.verdict, Verdict::Fail);
        }
        Ok(r)
    }

    /// [`Step::Until`]: read with `read` every `every` until the register reads `value`, `within` at most.
    /// The last read is the step's result; FAIL when the value never came.
    fn until(
        &mut self,
        read: &[u8],
        (mask, value): (u16, u16),
        timeout: Verdict,
        (every, within): (Duration, Duration),
        note: &str,
        wire: &mut Vec<WireEvent>,
    ) -> Result<StepResult, TargetError> {
        let framing = self.target.framing();
        let tries = within.as_micros() / every.as_micros().max(1) + 1;
        let send = Outgoing::Pdu(read.to_vec());
        let mut read_at = Duration::ZERO;
        let mut k = 0u128;
        loop {
            let mut r = self.exchange(&send, &Compare::Structure, None, note, wire)?;
            k += 1;
            let got = r.observed.iter().rev().find_map(|o| match o {
                Received::Frame { bytes, .. } => crate::readings::decode_response(framing, bytes),
                _ => None,
            });
            let got = match got {
                Some(
                    codec::Response::ReadHoldingRegisters { values }
                    | codec::Response::ReadInputRegisters { values },
                ) => values.first().copied(),
                _ => None,
            };
            match got {
                // No value to wait on (refused, silent): the exchange judged it.
                None => return Ok(r),
                Some(v) if v & mask == value => {
                    if k > 1 {
                        r.note = format!("{note}: {value} at read {k}, {} ms", read_at.as_millis());
                    }
                    return Ok(r);
                }
                Some(v) if k >= tries => {
                    let wanted = if mask == 0xFFFF {
                        format!("{value}")
                    } else {
                        format!("{value} in the bits 0x{mask:04X}")
                    };
                    r.findings.push(format!(
                        "still {v} (not {wanted}) after {k} reads over {} ms: the case went on with it so",
                        read_at.as_millis()
                    ));
                    r.verdict = worse(r.verdict, timeout);
                    return Ok(r);
                }
                Some(_) => {
                    self.target.idle(every);
                    self.sync_shadow();
                    read_at += every;
                }
            }
        }
    }

    /// The safety assertion, immediately before sending: every frame is rated by the classifier on the bytes
    /// that will go out (after mutations, restores filled in), and a frame rated more dangerous than the case's
    /// tags is not sent. The policy decided on the tags, so such a case is a harness bug: it is reported as a
    /// FAIL with the reason, never sent, never silent. The in-process simulator is held to it too, so that the
    /// catalog's tags are checked on every CI run.
    fn refusal(&self, frames: &[Framed]) -> Option<StepResult> {
        for f in frames {
            let rated = crate::cases::safety::classify_to_unit(
                &self.profile,
                &f.sent.pdu,
                f.sent.unit,
                self.cfg.unit,
            );
            let missing = crate::cases::safety::exceeds(&rated, &self.case_tags);
            if !missing.is_empty() {
                let names: Vec<String> = missing
                    .iter()
                    .map(|t| format!("{t:?}").to_lowercase())
                    .collect();
                return Some(StepResult {
                    note: "safety check before sending".into(),
                    sent: None,
                    expected: None,
                    observed: vec![],
                    verdict: Verdict::Fail,
                    findings: vec![format!(
                        "harness bug, request NOT sent: the classifier rates {} as {} but case {} is tagged {:?}; fix the case's tags",
                        hex::encode(&f.sent.pdu),
                        names.join("+"),
                        self.case_id,
                        self.case_tags
                    )],
                });
            }
        }
        None
    }

    /// What a step puts on the wire: its frames, and the writes (pieces, each with a gap after it).
    /// `None` for a restore with nothing captured.
    fn outgoing(&mut self, send: &Outgoing) -> Option<(Vec<Framed>, Vec<Piece>)> {
        let unit = self.cfg.unit;
        self.presented = None;
        // A pipelined case's request went out ahead of it (see [`pipeline`]).
        if self.ahead.front().is_some_and(|a| a.case == self.case_id) {
            let a = self.ahead.pop_front()?;
            // Lost with a closed connection: sent again, now.
            self.presented = (!self.ahead_lost).then_some(a.at);
            let piece = vec![(a.frame.bytes.clone(), Duration::ZERO)];
            return Some((vec![a.frame], piece));
        }
        Some(match send {
            Outgoing::Pdu(p) => {
                let f = self.frame(&self.in_drive_order(p), unit, None);
                let piece = vec![(f.bytes.clone(), Duration::ZERO)];
                (vec![f], piece)
            }
            Outgoing::PduToUnit { pdu, unit } => {
                let f = self.frame(&self.in_drive_order(pdu), *unit, None);
                let piece = vec![(f.bytes.clone(), Duration::ZERO)];
                (vec![f], piece)
            }
            Outgoing::Mutated { pdu, mutation } => {
                let f = self.frame(pdu, unit, Some(mutation));
                let pieces = match mutation {
                    Mutation::Split { at, gap_us } if *at < f.bytes.len() => vec![
                        (f.bytes[..*at].to_vec(), Duration::from_micros(*gap_us)),
                        (f.bytes[*at..].to_vec(), Duration::ZERO),
                    ],
                    _ => vec![(f.bytes.clone(), Duration::ZERO)],
                };
                (vec![f], pieces)
            }
            Outgoing::Batch(pdus) => {
                let frames: Vec<Framed> = pdus
                    .iter()
                    .map(|p| {
                        let p = self.in_drive_order(p);
                        self.frame(&p, unit, None)
                    })
                    .collect();
                let all = frames
                    .iter()
                    .flat_map(|f| f.bytes.iter().copied())
                    .collect();
                (frames, vec![(all, Duration::ZERO)])
            }
            Outgoing::Restore { address, slot } => {
                let p = self.restore_pdu(Some(*address), *slot)?;
                let f = self.frame(&p, unit, None);
                let piece = vec![(f.bytes.clone(), Duration::ZERO)];
                (vec![f], piece)
            }
            Outgoing::RestoreRead { slot } => {
                let p = self.restore_pdu(None, *slot)?;
                let f = self.frame(&p, unit, None);
                let piece = vec![(f.bytes.clone(), Duration::ZERO)];
                (vec![f], piece)
            }
        })
    }

    /// RTU on a real target: after a frame the drive may still hold (see `send_pieces`), the line's t3.5
    /// before the next one. Over TCP, where no line sets it, the gap the target URL gives (`?gap=MS`), else
    /// twice the carrier's 50 ms: a drive or device server that ends frames after a silence of its own
    /// choosing may well choose the same 50 ms, and then a request sent after exactly that long races its
    /// timer (independent SD2x tests/independent/sd2x-i lost the liveness read sent 50.2 ms after the answer
    /// to a frame with a byte after its CRC).
    fn resync_if_due(&mut self) {
        if std::mem::take(&mut self.resync_rtu) {
            let silence = match (self.target.rtu_timing(), self.target.resync_gap()) {
                (Some(t), _) if t.is_line() => t.t3_5,
                (_, Some(gap)) => gap,
                _ => codec::RtuTiming::tcp_carrier().t3_5 * 2,
            };
            self.target.idle(silence);
            self.sync_shadow();
        }
    }

    /// Write the pieces to the target and to the reference drive. Returns what the harness could not
    /// guarantee (a split frame's pieces too far apart) and the target's time just before the last write.
    fn send_pieces(
        &mut self,
        frames: &[Framed],
        pieces: &[Piece],
        wire: &mut Vec<WireEvent>,
    ) -> Result<(Vec<Finding>, Duration), TargetError> {
        let malformed = frames.iter().any(|f| f.malformed);
        // RTU: a malformed frame may leave bytes that the drive's framer holds until the line falls silent for
        // t3.5 (a frame one byte longer than its function's length rule whose first bytes make a valid frame,
        // say: the rest waits). The reference drops them at that silence, so the target must have it too
        // before the next frame, or the leftovers would corrupt it. (Real targets: on `sim:` the reference
        // and the drive share the clock.) A master resynchronising a slave does the same.
        self.resync_if_due();
        // So does a frame no length rule sizes (an unknown function code, say): only silence ends it, and a
        // frame sent sooner would be read as part of it (unless its answer came: see `exchange`).
        let no_length_rule = frames.iter().any(|f| {
            !matches!(
                codec::framer::expected_len(codec::Direction::Request, &f.bytes, &[]),
                codec::FrameLen::Known(a, b) if a == f.bytes.len() || b == f.bytes.len()
            )
        });
        self.resync_rtu = (malformed || no_length_rule)
            && !self.cfg.is_sim
            && self.target.framing() == Framing::Rtu;
        let mut precondition = Vec::new();
        // On the target's clock: virtual on `sim:`, where a stall of the harness is not a gap on the line.
        let mut last_write: Option<Duration> = None;
        let mut before_last_write = self.target.now();
        for (bytes, gap) in pieces {
            // On a real line, pieces meant to be one frame must follow within t1.5: check the harness did.
            if let (Some(t), Some(prev)) = (self.target.rtu_timing(), last_write) {
                let took = self.target.now().saturating_sub(prev);
                if took > t.t1_5 {
                    precondition.push(Finding {
                        severity: Severity::Inconclusive,
                        text: format!(
                            "inconclusive: the harness paused {} µs between the pieces of one frame (t1.5 = {} µs); the machine is too busy for this step",
                            took.as_micros(),
                            t.t1_5.as_micros()
                        ),
                    });
                }
            }
            if let Some(at) = self.presented {
                // Pipelined: on the wire already, with the requests of the cases after it.
                wire.push(WireEvent {
                    dir: Dir::Tx,
                    at,
                    bytes: bytes.clone(),
                    intended_malformed: malformed,
                });
                before_last_write = at;
                last_write = Some(at);
                self.shadow.send(bytes)?;
                continue;
            }
            if last_write.is_none() {
                self.pace_requests(frames.len());
            }
            wire.push(WireEvent {
                dir: Dir::Tx,
                at: self.target.now(),
                bytes: bytes.clone(),
                intended_malformed: malformed,
            });
            // Taken before the write: a stall of the harness can then only make the early-answer check
            // more lenient, never blame the drive.
            before_last_write = self.target.now();
            self.target.send(bytes)?;
            last_write = Some(self.target.now());
            self.shadow.send(bytes)?;
            if !gap.is_zero() {
                self.target.idle(*gap);
                self.shadow.idle(*gap);
            }
        }
        if self.presented.is_none() {
            // (Pipelined requests were counted when they went out.)
            self.requests += frames.len() as u64;
        }
        for f in frames {
            let by = self.case_id.clone();
            self.remember(f.sent.tid, by);
            if self.unanswered.len() < 16 {
                self.unanswered
                    .push((self.case_id.clone(), f.bytes.clone()));
            }
        }
        Ok((precondition, before_last_write))
    }

    /// Receive every answer the reference gives (or the silence it keeps) and judge each.
    #[allow(clippy::too_many_arguments)]
    fn receive_and_judge(
        &mut self,
        frames: &[Framed],
        pieces: &[Piece],
        (precondition, sent_at): (Vec<Finding>, Duration),
        compare: &Compare,
        capture: Option<usize>,
        note: &str,
        wire: &mut Vec<WireEvent>,
    ) -> Result<StepResult, TargetError> {
        // The reference answers: every frame it sends before it falls silent, and which freedoms decided them.
        let (expected, reference_closed) = self.shadow.settle();
        // Judged in the cases' form (reported as they came).
        let expected_judged: Option<Vec<Vec<u8>>> = self.fc43_without_reserved.then(|| {
            expected
                .iter()
                .map(|e| self.in_case_form(e).unwrap_or_else(|| e.clone()))
                .collect()
        });
        let judged_expected = expected_judged.as_deref().unwrap_or(&expected);
        let decisions = self.shadow.take_decisions();
        let counter_alternatives = self.shadow.take_counter_alternatives();
        let choice_alternatives = self.shadow.take_choice_alternatives();
        let mut observed = Vec::new();
        let mut findings: Vec<Finding> = precondition;
        let unit = self.cfg.unit;
        let framing = self.target.framing();
        let n = expected.len().max(1);
        // Modbus/TCP pairs answers with requests by transaction id, in any order (guide 4.2.1.1): which
        // requests and which of the reference's answers were paired already.
        let mut paired = vec![false; frames.len()];
        let mut used = vec![false; expected.len()];
        for i in 0..n {
            let wait = if expected.is_empty() {
                // An RTU request cut short on purpose leaves a drive that frames by length (libmodbus)
                // waiting for its missing bytes until its own byte timeout: the next request must not go
                // out before that, or both are lost. Listened as long as for an answer.
                if framing != Framing::Tcp && !self.cfg.is_sim && frames.iter().any(|f| f.malformed)
                {
                    self.cfg.timing.silence.max(self.cfg.timing.timeout)
                } else {
                    self.cfg.timing.silence
                }
            } else {
                self.cfg.timing.timeout
            };
            let start = self.target.now();
            // Pipelined: no sentinel, which would go out behind the requests ahead (the window is listened
            // out).
            let proven = if expected.is_empty() && self.ahead.is_empty() {
                self.prove_silence_if_possible(frames, reference_closed, &mut findings, wire)?
            } else {
                None
            };
            let mut got = match proven {
                Some(got) => got,
                None => {
                    let got = self.recv_answer(frames, wait)?;
                    // Counted where the window ran out: not where the target closed the connection or
                    // answered after all.
                    if expected.is_empty()
                        && !self.cfg.is_sim
                        && matches!(got, Received::Silence { .. })
                    {
                        self.silences.listened += 1;
                    }
                    got
                }
            };
            if framing == Framing::Tcp {
                got = self.skip_late(got, frames, (start, wait), &mut findings, wire)?;
            }
            if matches!(got, Received::Frame { .. }) {
                self.unanswered.clear();
            }
            if let Received::Frame { first_at, .. } = &got
                && framing == Framing::Tcp
                && frames.len() == 1
                && !expected.is_empty()
            {
                self.latencies.note(first_at.saturating_sub(sent_at));
            }
            let stop = !matches!(got, Received::Frame { .. } | Received::Garbage { .. });
            record(&got, wire);
            // Judged in the cases' form (recorded and reported as it came).
            let got_judged = self.received_in_case_form(&got);
            let seen = got_judged.as_ref().unwrap_or(&got);
            let (j, out_of_order) = pair(framing, &got, frames, &paired, i);
            if let Some(p) = paired.get_mut(j) {
                *p = true;
            }
            let e = framing
                .eq(&Framing::Tcp)
                .then(|| {
                    let tid = frames.get(j)?.sent.tid?;
                    (0..expected.len())
                        .find(|&k| !used[k] && expected[k].get(..2) == Some(&tid.to_be_bytes()[..]))
                })
                .flatten()
                .or_else(|| (0..expected.len()).find(|&k| !used[k]))
                .unwrap_or(i);
            if let Some(u) = used.get_mut(e) {
                *u = true;
            }
            let frame = frames.get(j).or(frames.last());
            let sent = frame.map(|f| f.sent.clone()).unwrap_or(Sent {
                tid: None,
                unit,
                pdu: vec![],
            });
            // A request longer than its layout is judged as the request the layout reads (a drive may serve
            // it, `trailing-bytes`), so that what it touches (an item a product may lack) is known.
            let request = Request::decode(&sent.pdu)
                .ok()
                .or_else(|| Request::decode_layout_prefix(&sent.pdu).map(|(r, _)| r));
            // In a batch, the freedoms that decided this frame's answer (and those about the batch).
            let mut decided: Vec<drives::Decision> = match self.frame_decisions.get(j) {
                Some(own) => own
                    .iter()
                    .chain(decisions.iter().filter(|d| d.starts_with("pipelined")))
                    .copied()
                    .collect(),
                None => decisions.clone(),
            };
            // A request sent with others in flight and refused Server Busy: the freedom decided it (see
            // `pipeline`). Only then: the freedom's other value would admit any served answer.
            let mut decisions = std::borrow::Cow::Borrowed(&decisions);
            let busy = matches!(&got, Received::Frame { bytes, .. } if busy_refusal(bytes));
            // (A request sent alone is sent again while the drive is busy: `exchange_patiently`.)
            let together = frames.len() > 1 || self.presented.is_some();
            // Refused Server Busy after the drive took a long-duration command (an NVM save earlier in the
            // batch, or just before it): busy with that (App 7, 06: "engaged in processing a long-duration
            // program command"), not short of transactions. Not the pipelining freedom, which the reference
            // would follow and refuse every request after the first of a batch.
            let busy_by = if busy && together && self.busy_with_long_command() {
                Some(drives::choices::ids::BUSY_AFTER_LONG_COMMAND)
            } else {
                (busy && self.presented.is_some()).then_some(pipeline::SERVER_BUSY)
            };
            if let Some(id) = busy_by {
                for d in [&mut decided, decisions.to_mut()] {
                    d.retain(|d| *d != pipeline::SERVER_BUSY || id == pipeline::SERVER_BUSY);
                    d.push(id);
                }
            }
            if !busy
                && let (Some(req), Received::Frame { bytes, .. }) = (request.as_ref(), &got)
                && self.starts_long_command(req)
                && crate::readings::decode_response(framing, bytes)
                    .is_some_and(|r| !r.is_exception())
            {
                self.long_command_at = Some(self.target.now());
            }
            let cx = StepContext {
                request: request.as_ref(),
                pdu: &sent.pdu,
                unit: sent.unit,
                run_unit: self.cfg.unit,
                profile: &self.profile,
                malformed: frame.is_some_and(|f| f.malformed),
                batch: frames.len() > 1,
                decided: &decided,
                counter_alternatives: &counter_alternatives,
                choice_alternatives: &choice_alternatives,
                closed: matches!(got, Received::Closed { .. }),
                short_of_length: frame.is_some_and(|f| f.short_of_length()),
                gateway: framing == Framing::Tcp
                    && !self.profile.speaks_tcp()
                    && frame.is_some_and(|f| f.bytes.get(2..4) == Some(&[0, 0][..])),
            };
            let requirements = Arc::clone(&self.requirements);
            let applicable = oracle::freedoms::applicable_among(
                &requirements,
                &self.touchable,
                &cx,
                &decisions,
                &self.case_freedoms,
            );
            let observation = oracle::Observation {
                framing,
                sent: &sent,
                expected: judged_expected.get(e).map(|v| v.as_slice()),
                observed: seen,
                compare,
                profile: &self.profile,
                reference_closed,
            };
            let judged = oracle::judge_admitting(&observation, &applicable, &cx);
            // Where several admissible answers explain the drive's (its answer is not the reference's), a
            // freedom whose every explanation contradicts what the drive showed before (an item it read,
            // refused now as if it lacked it) is no reason for the answer, if another explanation agrees with
            // everything the drive showed: the answer is that one's (PM refused while EE is off, after PM was
            // read, tests/independent/lmd-i). Where the drive's answer is the reference's, or no explanation
            // agrees, nothing is set aside: a drive changing its mind is found.
            let agrees_all = |j: &oracle::Judged| j.shown.iter().all(|s| self.choices.agrees(s));
            let contradicted: Vec<&str> = if judged.others.is_empty() {
                Vec::new()
            } else {
                let explanations: Vec<&oracle::Judged> = std::iter::once(&judged)
                    .chain(judged.others.iter())
                    .collect();
                applicable
                    .iter()
                    .map(|f| f.id.as_str())
                    .filter(|id| {
                        let of = |j: &oracle::Judged| j.shown.iter().any(|s| s.freedom == *id);
                        let mut mine = explanations.iter().filter(|j| of(j)).peekable();
                        mine.peek().is_some()
                            && mine.all(|j| !agrees_all(j))
                            && explanations.iter().any(|j| !of(j) && agrees_all(j))
                    })
                    .collect()
            };
            let reasons: Vec<&drives::requirements::Freedom> = applicable
                .iter()
                .copied()
                .filter(|f| !contradicted.contains(&f.id.as_str()))
                .collect();
            // Where several freedoms explain the answer, the one that agrees with the drive's earlier choices.
            let judged = judged.agreeing(|s| self.choices.agrees(s));
            let kind = oracle::outcome_kind(framing, seen);
            let mut judged = judged;
            judged.shown = oracle::freedoms::unambiguous(
                judged.shown,
                &reasons,
                &cx,
                kind.as_deref(),
                &requirements,
            );
            // Requests sent together: whether one is refused Server Busy depends on how many a server holds
            // at once (NumberMaxOfServerTransaction, "a value from 1 to 16", TCP guide 4.4.2.1): one with two
            // serves the second of a batch and refuses the third. A choice per place in the batch, so that
            // the one is not held against the other; the reference follows a refusal of the second only
            // (the one transaction it models), see `follow_busy`.
            if frames.len() > 1 {
                for s in judged
                    .shown
                    .iter_mut()
                    .filter(|s| s.freedom == pipeline::SERVER_BUSY)
                {
                    s.about = format!("request {} of those sent together", j + 1);
                }
            }
            let follow_busy = frames.len() == 1 || j == 1;
            // A freedom the reference follows the drive in (see [`follows`]) decided an answer the drive gave
            // alike: the drive keeps its choice there, shown as the choice it is.
            let passed = frames.len() == 1
                && !judged
                    .findings
                    .iter()
                    .any(|f| matches!(f.severity, Severity::Must | Severity::Unimplemented));
            let kept: Vec<Shown> = decisions
                .iter()
                .filter(|_| passed)
                .filter_map(|id| requirements.freedom(id))
                .filter(|f| follows(f) && !judged.shown.iter().any(|s| s.freedom == f.id))
                .filter_map(|f| {
                    let v = self.learned.get(&f.id)?;
                    (f.values.first() != Some(v) && kind.as_deref().is_some_and(|k| v.matches(k)))
                        .then(|| {
                            oracle::freedoms::shown_value(
                                f,
                                oracle::freedoms::about_of(&f.id, &cx),
                                &v.to_string(),
                            )
                        })
                })
                .collect();
            // Held to the same evidence as what the judgement showed: a learned choice whose answer here is
            // the reference's own answer too (an FC 08 counter refusing a data field of another size with 03
            // after the drive refused one of Return Query Data so) shows nothing.
            let kept = oracle::freedoms::unambiguous(
                kept,
                &applicable,
                &cx,
                kind.as_deref(),
                &requirements,
            );
            // Exception 01 to a function the drive showed it lacks: UNIMPLEMENTED again, not a FAIL because the
            // reference would have answered this request otherwise.
            // The drive's answer, decoded once: what the 01 rule and the functions served look at.
            let answer = match seen {
                Received::Frame { bytes, .. } => crate::readings::decode_response(framing, bytes),
                _ => None,
            };
            let refused_01 = |r: &codec::Response, fc: u8| {
                matches!(r, codec::Response::Exception { function, code }
                    if function.0 == fc | 0x80 && *code == codec::ExceptionCode::ILLEGAL_FUNCTION)
            };
            let illegal_function = match (&answer, sent.pdu.first()) {
                (Some(r), Some(&fc)) if fc < 0x80 => refused_01(r, fc),
                _ => false,
            };
            // Not where the drive's manual lists the function: refusing it is a FAIL every time.
            let listed = |fc: u8| {
                self.profile
                    .function(codec::FunctionCode(fc))
                    .is_some_and(|f| f.line.is_some())
            };
            // Nor where it never served the function in this run: 01 is what a drive lacking it answers to
            // any request of it (App 4.5, Figure 9: the function code is checked first), whatever else the
            // reference found wrong with the request or chose to do with it (a PDU longer than its layout
            // ignored, say).
            // (Where the reference answers the same 01, what was found is about something else: a unit id, a
            // transaction id.)
            let served_before = sent
                .pdu
                .first()
                .is_some_and(|fc| self.served_functions.contains(fc));
            let reference_refuses = |x: Option<&Vec<u8>>, fc: u8| {
                x.and_then(|b| crate::readings::decode_response(framing, b))
                    .is_some_and(|r| refused_01(&r, fc))
            };
            if let (Some(r), Some(&fc)) = (&answer, sent.pdu.first())
                && frames.len() == 1
                && !r.is_exception()
                && r.function().0 == fc
            {
                self.served_functions.insert(fc);
            }
            if illegal_function
                && let Some(&fc) = sent.pdu.first()
                && !listed(fc)
            {
                let mut judged_findings = std::mem::take(&mut judged.findings);
                if judged_findings
                    .iter()
                    .any(|f| f.severity == Severity::Unimplemented)
                {
                    self.lacking.insert(fc);
                } else if self.lacking.contains(&fc)
                    || !served_before
                        && !reference_refuses(judged_expected.get(e), fc)
                        && !frames
                            .get(j)
                            .or(frames.last())
                            .is_some_and(|f| f.adu_altered)
                {
                    let why = if self.lacking.contains(&fc) {
                        "the drive answered 01 to function 0x{fc:02X} before: it lacks it"
                    } else {
                        "exception 01: the drive lacks function 0x{fc:02X}, which its manual does not list and which it served nowhere in this run"
                    }
                    .replace("{fc:02X}", &format!("{fc:02X}"));
                    self.lacking.insert(fc);
                    for f in &mut judged_findings {
                        if f.severity == Severity::Must {
                            f.severity = Severity::Unimplemented;
                            f.text = format!("{} ({why})", f.text);
                        }
                    }
                }
                judged.findings = judged_findings;
            }
            // A queue or file the device does not have (its contents are its own, App 6.14, 6.15, 6.18):
            // refused with 02 or 03 where the reference serves the profile's own.
            // Or served where the reference refuses the profile's (a queue of more than 31, a file it lacks).
            let refusal = |r: &codec::Response| matches!(r, codec::Response::Exception { code, .. } if (2..=3).contains(&code.0));
            if self.contents_free()
                && matches!(sent.pdu.first(), Some(0x14 | 0x15 | 0x18))
                && judged.findings.iter().any(|f| f.severity == Severity::Must)
                && let Received::Frame { bytes, .. } = seen
                && let Some(o) = crate::readings::decode_response(framing, bytes)
                && let Some(x) = judged_expected
                    .get(e)
                    .and_then(|b| crate::readings::decode_response(framing, b))
                && o.function().without_exception_bit() == x.function().without_exception_bit()
                && (refusal(&o) && !x.is_exception() || refusal(&x) && !o.is_exception())
            {
                judged.findings = vec![oracle::Finding {
                    severity: Severity::Info,
                    text: if o.is_exception() {
                        "refused with 02 or 03 where the reference serves its own: this device has no such queue or file (device.reference_contents)".to_string()
                    } else {
                        "served where the reference refuses its own: this device has a queue or file there (device.reference_contents)".to_string()
                    },
                }];
            }
            findings.extend(judged.findings);
            // An answer ahead of an earlier request's shows the drive pairing by transaction id only.
            let order = requirements
                .freedoms()
                .iter()
                .find(|f| {
                    f.kind == FreedomKind::PipelineOrder && f.applies_to(&self.profile.device.id)
                })
                .filter(|_| out_of_order)
                .map(|f| oracle::freedoms::shown_value(f, "", "transaction-id"));
            if out_of_order {
                // A drive that pairs answers by transaction id only may answer a sentinel before the
                // request it follows: a sentinel's answer proves nothing about that request any more.
                self.sentinel_given_up = true;
            }
            if judged.shown.iter().any(|s| {
                (s.value == "silence" || s.value.starts_with("exception-"))
                    && requirements
                        .freedom(&s.freedom)
                        .is_some_and(|f| f.kind == FreedomKind::UnitIds)
            }) {
                self.unit_ignored = true;
            }
            for s in judged.shown.iter().chain(&order).chain(&kept) {
                if let Some(text) = self.choices.record(s, &self.case_id, &requirements) {
                    findings.push(Finding {
                        severity: Severity::Should,
                        text,
                    });
                }
                if let Some(f) = requirements
                    .freedom(&s.freedom)
                    .filter(|f| follows(f) && (follow_busy || f.id != pipeline::SERVER_BUSY))
                    && let Some(v) = f
                        .values
                        .iter()
                        .find(|v| v.matches(&s.value) && !v.matches("close"))
                    && self.learned.get(&f.id).or(f.values.first()) != Some(v)
                {
                    self.follow.push((f.clone(), v.clone()));
                }
            }
            // A request the drive refused where the reference took it, with no freedom the reference follows
            // in: the drive did not perform it (App 7: 01, 02, 03 report a request not carried out), so the
            // reference does not either. A function the drive lacks (01, UNIMPLEMENTED) leaves its
            // registers as they were, and a refusal that FAILs is judged once, not again in every read after
            // it; a drive that refuses yet performs the request shows it in those reads.
            if frames.len() == 1
                && self.follow.is_empty()
                && let Received::Frame { bytes, .. } = seen
                && let Some(codec::Response::Exception { code, .. }) =
                    crate::readings::decode_response(framing, bytes)
                && (1..=3).contains(&code.0)
                && judged_expected
                    .get(e)
                    .and_then(|b| crate::readings::decode_response(framing, b))
                    .is_some_and(|r| !r.is_exception())
            {
                self.unit_ignored = true;
            }
            // The silence before the answer, measured for the run's timing case (see `crate::timing`).
            if let (Some(t), Received::Frame { first_at, .. }, Some((last, _))) =
                (self.target.rtu_timing(), &got, pieces.last())
                && self.gaps_measurable.is_ok()
            {
                self.gaps
                    .record(&self.case_id, t, sent_at, last.len(), *first_at);
            }
            if let (Some(slot), Received::Frame { bytes, .. }) = (capture, seen)
                && let Some(c) = capture::captured(framing, &sent.pdu, bytes)
                && let Some(s) = self.slots.get_mut(slot)
            {
                *s = Some(c);
            }
            observed.push(got);
            if stop {
                break;
            }
        }
        let verdict = oracle::verdict(&findings, crate::cases::Level::Must);
        Ok(StepResult {
            note: note.to_string(),
            sent: Some(pieces.iter().flat_map(|p| p.0.iter().copied()).collect()),
            expected: if expected.is_empty() {
                None
            } else {
                Some(expected.concat())
            },
            observed,
            verdict,
            findings: findings.into_iter().map(|f| f.text).collect(),
        })
    }
}

/// The restore's reads and writes (leave as found): sent to the target and to the reference drive, so that the
/// reference follows what the target is put back to; not judged, not in the case reports.
impl crate::restore::Link for Runner {
    fn blocks(&self, kind: crate::restore::Block) -> bool {
        !self.blocks_refused.contains(&kind)
    }

    fn refuse_blocks(&mut self, kind: crate::restore::Block) {
        if !self.blocks_refused.contains(&kind) {
            self.blocks_refused.push(kind);
        }
    }

    fn idle(&mut self, d: Duration) {
        self.target.idle(d);
        self.sync_shadow();
    }

    fn transact(&mut self, req: &Request) -> Result<Option<codec::Response>, TargetError> {
        let Ok(pdu) = req.to_bytes() else {
            return Ok(None);
        };
        let mut answer = self.transact_pdu(&pdu)?;
        // Server Busy (06): the drive did nothing with it and asks to be asked again later (App 7), as after
        // an NVM save; the same request again, as a case's step is ([`Runner::exchange_patiently`]).
        let started = self.target.now();
        let mut pause = BUSY_FIRST_PAUSE;
        while answer.as_deref().is_some_and(busy_pdu)
            && self.target.now().saturating_sub(started) < self.cfg.timing.busy_wait
        {
            self.busy_pause(&mut pause);
            answer = self.transact_pdu(&pdu)?;
        }
        // Nothing came at all (no frame, or the connection closed), or no frame that decodes: a drive may
        // leave a connection hung after a malformed request and still answer on a new one (jsmodbus did,
        // after a truncated FC 15), a link may drop a connection, a noisy line damage the request or the
        // answer (the serial line spec's CRC catches it, 2.5.1.2). What the keeper sends puts values back
        // or reads them (the same request twice does no harm): once more (on Modbus/TCP on a new
        // connection) before the request counts as unanswered.
        if answer.is_none() && self.restore_unheard {
            if self.target.framing() == Framing::Tcp {
                self.target.reconnect()?;
                self.restore_reconnects += 1;
            }
            answer = self.transact_pdu(&pdu)?;
        }
        Ok(answer.and_then(|r| crate::readings::decode_response_pdu(&r)))
    }
}

impl Runner {
    /// Send `pdu` (in the cases' form) to the target and the reference drive with the restore's transaction
    /// ids, and take the target's answer to it: its PDU, in the cases' form. `None`: no answer of its own
    /// (silence, another unit, function code or transaction id, a frame that does not decode).
    fn transact_pdu(&mut self, pdu: &[u8]) -> Result<Option<Vec<u8>>, TargetError> {
        let fc = pdu.first().copied().unwrap_or(0);
        let f = self.frame_aside(pdu);
        // A late answer of an earlier request must never be taken for this one's (a wrong snapshot value
        // would be "restored" into the drive): stale bytes are dropped, and on Modbus/TCP the transaction id
        // and on every framing the unit and the function code must match.
        self.target.drain();
        self.sync_shadow();
        self.pace();
        self.requests += 1;
        // Its late answer, should one come during a case, is noted as late, not taken for a step's.
        self.remember(f.sent.tid, OWN_REQUESTS.into());
        self.target.send(&f.bytes)?;
        self.shadow.send(&f.bytes)?;
        let _ = self.shadow.settle();
        let _ = self.shadow.take_decisions();
        self.restore_unheard = false;
        for _ in 0..3 {
            let got = self.target.recv(self.cfg.timing.timeout)?;
            let Received::Frame { bytes, .. } = got else {
                self.restore_unheard = true;
                return Ok(None);
            };
            let bytes = self.in_case_form(&bytes).unwrap_or(bytes);
            let (tid, unit, answer) = match self.target.framing() {
                Framing::Tcp => match tcp::decode_adu(&bytes) {
                    Ok(a) => (Some(a.header.transaction_id), a.header.unit_id, a.pdu),
                    Err(_) => {
                        self.restore_unheard = true;
                        return Ok(None);
                    }
                },
                _ => match rtu::decode_adu(&bytes) {
                    Ok(a) => (None, a.address, a.pdu),
                    Err(_) => {
                        self.restore_unheard = true;
                        return Ok(None);
                    }
                },
            };
            if f.sent.tid.is_some() && tid != f.sent.tid {
                continue;
            }
            let ours = answer.first().is_some_and(|b| b & 0x7F == fc & 0x7F);
            return Ok((unit == f.sent.unit && ours).then(|| answer.to_vec()));
        }
        Ok(None)
    }
}

impl Runner {
    /// The reference drive alone, as a [`crate::restore::Link`]: requests go to it and not to the target.
    /// Used to bring the reference to the state the target was found in (its parameters as read before the
    /// first write), so that a drive found off its factory values is judged against a reference holding the
    /// same values.
    pub fn reference(&mut self) -> ReferenceLink<'_> {
        ReferenceLink { runner: self }
    }
}

/// See [`Runner::reference`].
pub struct ReferenceLink<'a> {
    runner: &'a mut Runner,
}

impl crate::restore::Link for ReferenceLink<'_> {
    fn transact(&mut self, req: &Request) -> Result<Option<codec::Response>, TargetError> {
        let r = &mut *self.runner;
        let Ok(pdu) = req.to_bytes() else {
            return Ok(None);
        };
        let f = r.frame_aside(&pdu);
        r.sync_shadow();
        r.shadow.send(&f.bytes)?;
        let (answers, _) = r.shadow.settle();
        let _ = r.shadow.take_decisions();
        let framing = r.shadow.framing();
        Ok(answers.iter().find_map(|bytes| {
            let bytes = &r.in_case_form(bytes).unwrap_or_else(|| bytes.clone());
            match codec::decode_any(bytes, framing, codec::Direction::Response) {
                Ok(codec::Decoded {
                    pdu: codec::Pdu::Response(resp),
                    ..
                }) => Some(resp),
                _ => None,
            }
        }))
    }
}

/// True when the target answered the step with an exception response of one of `codes`.
fn answered_exception(framing: Framing, r: &StepResult, codes: &[codec::ExceptionCode]) -> bool {
    r.observed.iter().any(|o| match o {
        Received::Frame { bytes, .. } => matches!(
            crate::readings::decode_response(framing, bytes),
            Some(codec::Response::Exception { code, .. }) if codes.contains(&code)
        ),
        _ => false,
    })
}

/// True when a Modbus/TCP answer is exception 06, Server Busy.
pub(crate) fn busy_refusal(adu: &[u8]) -> bool {
    adu.get(tcp::MBAP_LEN..).is_some_and(busy_pdu)
}

/// True when a response PDU is exception 06, Server Busy.
fn busy_pdu(pdu: &[u8]) -> bool {
    matches!(pdu, [fc, code] if fc & 0x80 != 0 && *code == codec::ExceptionCode::SERVER_DEVICE_BUSY.0)
}

/// The request an answer belongs to: on Modbus/TCP the unpaired one with the answer's transaction id (and
/// whether an earlier request is still unpaired: the answer came out of request order), else the first
/// unpaired one, else the `i`-th.
fn pair(
    framing: Framing,
    got: &Received,
    frames: &[Framed],
    paired: &[bool],
    i: usize,
) -> (usize, bool) {
    let first_unpaired = (0..frames.len()).find(|&k| !paired[k]);
    if framing == Framing::Tcp
        && let Received::Frame { bytes, .. } = got
        && let Some(tid) = bytes.get(..2).map(|b| u16::from_be_bytes([b[0], b[1]]))
        && let Some(j) = (0..frames.len()).find(|&k| !paired[k] && frames[k].sent.tid == Some(tid))
    {
        return (j, first_unpaired.is_some_and(|k| k < j));
    }
    (first_unpaired.unwrap_or(i), false)
}

fn record(r: &Received, wire: &mut Vec<WireEvent>) {
    let (bytes, at) = match r {
        Received::Frame {
            bytes, first_at, ..
        } => (bytes, *first_at),
        Received::Garbage { bytes, at, .. } => (bytes, *at),
        Received::Silence { partial, at } | Received::Closed { partial, at } => (partial, *at),
    };
    if !bytes.is_empty() {
        wire.push(WireEvent {
            dir: Dir::Rx,
            at,
            bytes: bytes.clone(),
            intended_malformed: false,
        });
    }
}

fn flip(order: WordOrder) -> WordOrder {
    match order {
        WordOrder::HighFirst => WordOrder::LowFirst,
        WordOrder::LowFirst => WordOrder::HighFirst,
    }
}

/// The value of a `word-order` freedom that stands for `order`.
pub(crate) fn order_name(order: WordOrder) -> &'static str {
    match order {
        WordOrder::HighFirst => "high-first",
        WordOrder::LowFirst => "low-first",
    }
}

fn rank(v: Verdict) -> u8 {
    match v {
        Verdict::Pass | Verdict::Skipped => 0,
        Verdict::Informational => 1,
        Verdict::NonStrict => 2,
        Verdict::Unimplemented => 3,
        Verdict::Fail => 4,
    }
}

/// The worse of two verdicts.
pub fn worse(a: Verdict, b: Verdict) -> Verdict {
    if rank(b) > rank(a) { b } else { a }
}

/// A step that judged what earlier steps kept (no bytes of its own on the wire).
/// True when the answers to one request were exception responses and nothing else (at least one): the
/// target did not take the request.
fn refused_only(framing: Framing, observed: &[Received]) -> bool {
    !observed.is_empty()
        && observed.iter().all(|o| {
            matches!(o, Received::Frame { bytes, .. }
            if matches!(
                crate::readings::decode_response(framing, bytes),
                Some(codec::Response::Exception { .. })
            ))
        })
}

fn step_of(note: String, verdict: Verdict, findings: Vec<String>) -> StepResult {
    StepResult {
        note,
        sent: None,
        expected: None,
        observed: vec![],
        verdict,
        findings,
    }
}

/// [`step_of`] for a comparison: PASS without findings, FAIL with them.
fn comparison(note: &str, findings: Vec<String>) -> StepResult {
    let verdict = if findings.is_empty() {
        Verdict::Pass
    } else {
        Verdict::Fail
    };
    step_of(note.to_string(), verdict, findings)
}

/// Registers that mirror discrete inputs one each (0 off, anything else on) against the inputs read with FC
/// 02. Inputs are live: one input that differs may have changed between the two reads, and is reported
/// (INFORMATIONAL), not failed; two or more that differ (inputs in the wrong order within the FC 02 byte, or
/// shifted) FAIL.
fn inputs_agree(registers: &[u16], inputs: &[bool], note: &str) -> StepResult {
    let step =
        |verdict: Verdict, findings: Vec<String>| step_of(note.to_string(), verdict, findings);
    if registers.len() != inputs.len() {
        return step(
            Verdict::Informational,
            vec![format!(
                "not compared: {} registers, {} inputs",
                registers.len(),
                inputs.len()
            )],
        );
    }
    let bits = |v: &mut dyn Iterator<Item = bool>| -> String {
        v.map(|b| if b { '1' } else { '0' }).collect()
    };
    let from_registers = bits(&mut registers.iter().map(|&r| r != 0));
    let from_inputs = bits(&mut inputs.iter().copied());
    let differ = registers
        .iter()
        .zip(inputs)
        .filter(|(r, i)| (**r != 0) != **i)
        .count();
    let text = format!(
        "the inputs read {from_inputs} with FC 02 (first input first) but {from_registers} as the registers that mirror them"
    );
    match differ {
        0 => step(Verdict::Pass, vec![]),
        1 => step(
            Verdict::Informational,
            vec![format!(
                "{text}: one input differs, it may have changed between the reads"
            )],
        ),
        _ => step(Verdict::Fail, vec![text]),
    }
}

/// An FC 0x41 answer PDU whose parameter string is followed by one byte its count leaves out, without that
/// byte: "Response n bytes n=N or N+1" (MDrive manual line 956, LMD manual line 1129; an independent LMD pads
/// a string of odd length with 0x00, tests/independent/lmd-g). `None` for any other PDU. The codec stays
/// strict (a decoded answer re-encodes to its bytes): the pad is left out where answers are judged.
fn vendor_read_unpadded(pdu: &[u8]) -> Option<Vec<u8>> {
    match pdu {
        [0x41, count, rest @ ..] if rest.len() == usize::from(*count) + 1 => {
            Some(pdu[..pdu.len() - 1].to_vec())
        }
        _ => None,
    }
}

/// The transaction id and unit id of a Modbus/TCP ADU, and its PDU, where the MBAP header is well-formed
/// and its length counts the bytes that follow it (whatever the PDU holds).
fn tcp_adu_parts(frame: &[u8]) -> Option<((u16, u8), &[u8])> {
    let header = frame.get(..tcp::MBAP_LEN)?;
    let tid = u16::from_be_bytes([header[0], header[1]]);
    let protocol = u16::from_be_bytes([header[2], header[3]]);
    let length = usize::from(u16::from_be_bytes([header[4], header[5]]));
    let pdu = frame.get(tcp::MBAP_LEN..)?;
    (protocol == 0 && length == pdu.len() + 1).then_some(((tid, header[6]), pdu))
}

/// An FC 43 / MEI 0x0D answer PDU in the SD2x example's form (no Reserved byte) in the layout's form, when it
/// is a well-formed answer in it.
fn canopen_answer_with_reserved(pdu: &[u8]) -> Option<Vec<u8>> {
    let long = codec::canopen_with_reserved(pdu)?;
    matches!(
        codec::Response::decode(&long),
        Ok(codec::Response::CanOpen(_))
    )
    .then_some(long)
}

/// How long [`Runner::came_within`] waits at most for a frame begun during its pause to end (an RTU frame
/// ends with a silence of 3.5 characters: 32 ms at 1200 baud).
const LATE_LOOK: Duration = Duration::from_millis(50);

#[cfg(test)]
pub(super) mod tests {

    /// "Response n bytes n=N or N+1" (MDrive manual line 956, LMD manual line 1129): an FC 0x41 answer with one
    /// byte after its counted string is judged without it; with none, two, or a count that does not match, it
    /// is judged as it came. A Modbus/TCP ADU is rebuilt around the PDU whatever it holds.
    #[test]
    fn a_vendor_read_answer_is_judged_without_the_byte_its_count_leaves_out() {
        assert_eq!(
            super::vendor_read_unpadded(&[0x41, 0x01, 0x30, 0x00]),
            Some(vec![0x41, 0x01, 0x30])
        );
        assert_eq!(super::vendor_read_unpadded(&[0x41, 0x01, 0x30]), None);
        assert_eq!(
            super::vendor_read_unpadded(&[0x41, 0x01, 0x30, 0x00, 0x00]),
            None
        );
        assert_eq!(super::vendor_read_unpadded(&[0x42, 0x01, 0x30, 0x00]), None);
        let adu = [0xA1, 0xCB, 0, 0, 0, 5, 0xFF, 0x41, 0x01, 0x30, 0x00];
        let ((tid, unit), pdu) = super::tcp_adu_parts(&adu).expect("an ADU");
        assert_eq!((tid, unit, pdu), (0xA1CB, 0xFF, &adu[7..]));
        assert_eq!(super::tcp_adu_parts(&adu[..10]), None);
    }

    #[test]
    fn inputs_agree_fails_two_inputs_that_differ_and_reports_one() {
        let regs = [1u16, 1, 0, 1];
        let same = [true, true, false, true];
        assert_eq!(super::inputs_agree(&regs, &same, "").verdict, Verdict::Pass);
        // One live input that changed between the two reads.
        let one = [true, true, true, true];
        assert_eq!(
            super::inputs_agree(&regs, &one, "").verdict,
            Verdict::Informational
        );
        // The inputs in reverse order.
        let reversed = [true, false, true, true];
        assert_eq!(
            super::inputs_agree(&regs, &reversed, "").verdict,
            Verdict::Fail
        );
        assert_eq!(
            super::inputs_agree(&regs[..2], &same, "").verdict,
            Verdict::Informational
        );
    }
    use super::*;

    fn framed(tid: u16) -> Framed {
        Framed {
            bytes: Vec::new(),
            sent: Sent {
                tid: Some(tid),
                unit: 1,
                pdu: vec![0x03, 0x00, 0x00, 0x00, 0x01],
            },
            malformed: false,
            adu_altered: false,
        }
    }

    fn answer(tid: u16, pdu: &[u8]) -> Received {
        let mut bytes = Vec::new();
        tcp::encode_adu(tid, 1, pdu, &mut bytes).expect("encodes");
        Received::frame(bytes)
    }

    /// A long live campaign wraps the transaction ids: the silence sentinel then drew the id of the very
    /// request whose silence it was to prove, and its answer was judged as that request's (a 30 s `fuzz
    /// --allow-writes` against `simulate --profile mdrive` FAILed `gen/1/457444/write-reg-protoid`: "expected
    /// no response, got" the sentinel's FC 03 answer). The sentinel now takes another id.
    #[test]
    fn a_sentinel_never_shares_the_transaction_id_of_the_request_it_follows() {
        let mut runner = generic_runner();
        let case = protocol_id_case();
        for _ in 0..3 {
            // The two sequences meet, as they do after wrapping.
            runner.next_tid = runner.restore_tid;
            let r = runner.run_case(&case).expect("run");
            assert_eq!(r.verdict, Verdict::Pass, "{r:#?}");
            assert_eq!(
                runner.silences().sentinel,
                1,
                "a sentinel proved the silence"
            );
            runner.silences = Silences::default();
        }
    }

    /// The runner tells the keeper which writes of a case the target refused (answered with an exception
    /// only), so that a refused write to a status flag does not make the flag one to put back.
    #[test]
    fn the_writes_a_target_refused_are_told_apart_from_those_it_took() {
        let mut runner = generic_runner();
        let taken = vec![0x06, 0x00, 0x05, 0x00, 0x07];
        let refused = vec![0x06, 0x01, 0x00, 0x00, 0x07];
        let read = vec![0x03, 0x00, 0x00, 0x00, 0x01];
        let mut case = protocol_id_case();
        case.tags = vec![Tag::Write];
        case.steps = [&taken, &refused, &read]
            .into_iter()
            .map(|pdu| Step::Exchange {
                send: Outgoing::Pdu(pdu.clone()),
                compare: Compare::Exact,
                capture: None,
                note: String::new(),
            })
            .collect();
        let r = runner.run_case(&case).expect("run");
        assert_eq!(r.verdict, Verdict::Pass, "{r:#?}");
        assert_eq!(runner.refused_writes(), std::slice::from_ref(&refused));
        case.steps.truncate(1);
        runner.run_case(&case).expect("run");
        assert!(runner.refused_writes().is_empty(), "cleared for each case");
    }

    /// A read sent with protocol id 1: the drive must not answer it (TCP guide 4.4.1).
    fn protocol_id_case() -> Case {
        Case {
            id: "test/protocol-id".into(),
            title: "a request with protocol id 1".into(),
            reference: "test".into(),
            requirement: "test".into(),
            level: crate::cases::Level::Must,
            tags: vec![Tag::TcpOnly],
            steps: vec![Step::Exchange {
                send: Outgoing::Mutated {
                    pdu: vec![0x03, 0x00, 0x00, 0x00, 0x01],
                    mutation: Mutation::ProtocolId(1),
                },
                compare: Compare::RejectOrIgnore,
                capture: None,
                note: String::new(),
            }],
            requirements: vec![],
            freedoms: vec![],
        }
    }

    /// The runner counts every request it sends the target: the cases', the sentinels, the liveness
    /// probes, the restore's (`fuzz` prints them beside the cases).
    #[test]
    fn the_requests_sent_to_the_target_are_counted() {
        let mut runner = generic_runner();
        let read = [0x03, 0x00, 0x00, 0x00, 0x01];
        let mut case = protocol_id_case();
        case.steps = vec![Step::Exchange {
            send: Outgoing::Pdu(read.to_vec()),
            compare: Compare::Exact,
            capture: None,
            note: String::new(),
        }];
        let r = runner.run_case(&case).expect("run");
        assert_eq!(r.verdict, Verdict::Pass, "{r:#?}");
        assert_eq!(runner.requests(), 1, "one read");
        let r = runner.run_case(&protocol_id_case()).expect("run");
        assert_eq!(r.verdict, Verdict::Pass, "{r:#?}");
        assert_eq!(runner.requests(), 3, "the ignored request and its sentinel");
        runner.transact_pdu(&read).expect("restore read");
        assert_eq!(runner.requests(), 4, "a restore read");
        runner
            .known_good(&read, Duration::from_millis(100))
            .expect("probe");
        assert_eq!(runner.requests(), 5, "a liveness probe");
    }

    /// A runner against the generic reference drive with a real target's rules (silences proven by a
    /// sentinel).
    fn generic_runner() -> Runner {
        generic_runner_choosing(&[])
    }

    /// As [`generic_runner`], the target's drive taking `choices` (`FREEDOM=VALUE`) where the reference
    /// takes the reference's.
    pub(super) fn generic_runner_choosing(choices: &[&str]) -> Runner {
        runner_choosing("generic", &[], choices)
    }

    /// As [`generic_runner_choosing`], for the corpus profile `name`, the target's drive with `faults` too.
    fn runner_choosing(name: &str, faults: &[drives::Fault], choices: &[&str]) -> Runner {
        let p = drives::corpus::Corpus::Embedded
            .profile(name)
            .expect("profile");
        let faults = drives::FaultSet::of(faults);
        let requirements = drives::corpus::Corpus::Embedded
            .requirements()
            .expect("requirements");
        let chosen = drives::Choices::parse_all(choices, &requirements, &p).expect("choices");
        let station = |choices: drives::Choices, faults: drives::FaultSet| {
            let unit = p.device.default_unit;
            drives::Station::new(
                drives::build_with(p.clone(), faults.clone(), choices.clone()),
                faults,
                unit,
            )
            .with_choices(choices)
        };
        let cfg = RunConfig {
            unit: p.device.default_unit,
            timing: Timing::default(),
            safety: Safety::default(),
            is_sim: false,
        };
        Runner::new(
            Box::new(SimTarget::new(station(chosen, faults))),
            SimTarget::new(station(
                drives::Choices::reference(),
                drives::FaultSet::none(),
            )),
            p.clone(),
            cfg,
            Expectations::default(),
        )
        .with_requirements(Arc::new(requirements))
    }

    /// The catalog case `id` of profile `name` (Modbus/TCP).
    fn catalog_case(name: &str, id: &str) -> Case {
        let p = drives::corpus::Corpus::Embedded
            .profile(name)
            .expect("profile");
        let golden = drives::corpus::Corpus::Embedded
            .golden(name)
            .expect("golden");
        crate::cases::catalog::build(&p, golden.as_ref(), Framing::Tcp, p.device.default_unit)
            .into_iter()
            .find(|c| c.id == id)
            .unwrap_or_else(|| panic!("no case {id}"))
    }

    /// A drive busy after an NVM save (`busy-after-long-command`, as an independent MDrive and LMD are: App 7,
    /// exception 06, "the client should retransmit the message later"): a case's request it answers 06 is
    /// sent again until the drive is free, and the answer then is judged (PASS, with a note of the
    /// refusals), for every request or for writes only. Without the retransmission these cases FAIL.
    #[test]
    fn a_request_answered_server_busy_is_sent_again_once_the_drive_is_free() {
        for (choice, next) in [
            ("all-requests", "profile/lmd/read/0x0077-sf"),
            ("writes", "profile/lmd/write/0x0077-sf"),
        ] {
            let mut runner =
                runner_choosing("lmd", &[], &[&format!("busy-after-long-command={choice}")]);
            let save = runner
                .run_case(&catalog_case("lmd", "profile/lmd/write/0x0076-s"))
                .expect("the save");
            assert_eq!(save.verdict, Verdict::Pass, "{save:#?}");
            let r = runner
                .run_case(&catalog_case("lmd", next))
                .expect("the case after it");
            assert_eq!(r.verdict, Verdict::Pass, "{choice}: {r:#?}");
            assert!(
                r.steps
                    .iter()
                    .any(|s| s.note.contains("answered Server Busy (exception 06)")),
                "{choice}: {:#?}",
                r.steps
            );
        }
    }

    /// A request of a batch refused Server Busy (06) right after an NVM save earlier in the batch is busy
    /// with the save (`busy-after-long-command`, App 7), not short of transactions: PASS, shown as that
    /// choice, and not as `pipelined-server-busy`, which the reference would follow and refuse the second
    /// request of every batch after (tests/independent/lmd-d, seed 47: a later batch of reads, served, FAILed
    /// against the reference's 06). A batch sent long after the save is answered in full and PASSes.
    #[test]
    fn a_batched_request_refused_busy_after_a_save_is_busy_with_the_save() {
        let batch = |id: &str, pdus: Vec<Vec<u8>>| Case {
            id: id.into(),
            title: id.into(),
            reference: String::new(),
            requirement: String::new(),
            level: crate::cases::Level::Must,
            tags: vec![Tag::Write, Tag::Destructive, Tag::TcpOnly],
            steps: vec![Step::Exchange {
                send: Outgoing::Batch(pdus),
                compare: Compare::Structure,
                capture: None,
                note: id.into(),
            }],
            requirements: Vec::new(),
            freedoms: Vec::new(),
        };
        let save = vec![0x10, 0x00, 0x76, 0x00, 0x01, 0x02, 0x00, 0x01];
        let read = vec![0x03, 0x00, 0x4A, 0x00, 0x01];
        let write = vec![0x10, 0x00, 0x67, 0x00, 0x01, 0x02, 0x00, 0x16];
        let mut runner = runner_choosing("lmd", &[], &["busy-after-long-command=writes"]);
        let first = runner
            .run_case(&batch(
                "save-then-write",
                vec![save, read.clone(), write.clone()],
            ))
            .expect("the batch with the save");
        assert_eq!(first.verdict, Verdict::Pass, "{first:#?}");
        let refused = first.steps[0]
            .observed
            .iter()
            .any(|o| matches!(o, Received::Frame { bytes, .. } if busy_refusal(bytes)));
        assert!(refused, "the write behind the save is refused: {first:#?}");
        let shown: Vec<&crate::oracle::choices::Choice> = runner.choices().choices().collect();
        assert!(
            shown.iter().any(|c| c.freedom == "busy-after-long-command"
                && c.about == "a write"
                && c.value == "writes"),
            "{shown:#?}"
        );
        assert!(
            !shown.iter().any(|c| c.freedom == "pipelined-server-busy"),
            "{shown:#?}"
        );
        runner.idle(Duration::from_secs(6));
        let later = runner
            .run_case(&batch("reads-later", vec![read.clone(), read, write]))
            .expect("a batch long after");
        assert_eq!(later.verdict, Verdict::Pass, "{later:#?}");
    }

    /// A drive that answers 06 for good (fault `letter-case-busy`: to a mnemonic named in lower case) is not
    /// waited for without end: after [`Timing::busy_wait`] its 06 is judged, FAIL, with a finding that says so.
    #[test]
    fn a_drive_busy_for_good_fails_after_the_wait() {
        let mut runner = runner_choosing("lmd", &[drives::Fault::LetterCaseBusy], &[]);
        let r = runner
            .run_case(&catalog_case(
                "lmd",
                "profile/lmd/mnemonic/letter-case/read",
            ))
            .expect("the case");
        assert_eq!(r.verdict, Verdict::Fail, "{r:#?}");
        let findings: Vec<&String> = r.findings().collect();
        assert!(
            findings
                .iter()
                .any(|f| f.contains("still Server Busy (exception 06)")),
            "{findings:#?}"
        );
    }

    /// The keeper's reads and writes (leave as found) are sent again to a drive that answers 06, as a case's
    /// are: a read right after an NVM save gets the value, not the refusal.
    #[test]
    fn the_keeper_asks_a_busy_drive_again() {
        use crate::restore::Link;
        let mut runner = runner_choosing("lmd", &[], &["busy-after-long-command=all-requests"]);
        let save = Request::WriteMultipleRegisters {
            address: 0x0076,
            values: vec![1],
        };
        let taken = Link::transact(&mut runner, &save).expect("the save");
        assert!(
            taken.as_ref().is_some_and(|r| !r.is_exception()),
            "{taken:?}"
        );
        let read = Request::ReadHoldingRegisters {
            address: 0x0077,
            quantity: 1,
        };
        let got = Link::transact(&mut runner, &read).expect("the read");
        assert!(
            matches!(got, Some(codec::Response::ReadHoldingRegisters { .. })),
            "{got:?}"
        );
    }

    /// The traffic beside the cases (restore reads and writes, liveness probes, sentinels) never takes the
    /// transaction id of a recent request of the cases, after the sequences wrapped: a late answer to that
    /// request would be taken for the restore read's (a wrong value put back into the drive).
    #[test]
    fn traffic_beside_the_cases_skips_the_ids_of_recent_requests() {
        let mut runner = generic_runner();
        let first = runner.restore_tid;
        // Requests of the cases took the restore sequence's next three ids (as after wrapping).
        for t in first..first + 3 {
            runner.remember(Some(t), format!("case request {t}"));
        }
        let read = [0x03, 0x00, 0x00, 0x00, 0x01];
        let f = runner.frame_aside(&read);
        assert_eq!(
            f.sent.tid,
            Some(first + 3),
            "the next id no recent request has"
        );
        let g = runner.frame_aside(&read);
        assert_eq!(g.sent.tid, Some(first + 4));
        // The restore's own transact goes the same way.
        runner.remember(Some(first + 5), "case request".into());
        let answer = runner.transact_pdu(&read).expect("transact");
        assert!(answer.is_some(), "the drive answered the restore read");
        assert_eq!(
            runner.restore_tid,
            first + 7,
            "id {} was skipped",
            first + 5
        );
    }

    /// Pipelined answers are paired with their requests by transaction id, and one ahead of an earlier
    /// request's is out of request order; on RTU, by position.
    #[test]
    fn answers_pair_by_transaction_id() {
        let frames = [framed(10), framed(11)];
        let late_first = answer(11, &[0x03, 0x02, 0x00, 0x00]);
        let early = answer(10, &[0x03, 0x02, 0x00, 0x00]);
        // A transaction id of no request (or paired already): the first unpaired request.
        let stray = answer(99, &[0x03, 0x02, 0x00, 0x00]);
        // (framing, answer, requests paired already, next in order) -> (request, out of order)
        let table = [
            (Framing::Tcp, &late_first, [false, false], 0, (1, true)),
            (Framing::Tcp, &early, [false, true], 1, (0, false)),
            (Framing::Tcp, &early, [false, false], 0, (0, false)),
            (Framing::Tcp, &stray, [true, false], 1, (1, false)),
            (Framing::Rtu, &late_first, [false, false], 0, (0, false)),
        ];
        for (i, (framing, answer, paired, next, want)) in table.into_iter().enumerate() {
            let got = pair(framing, answer, &frames, &paired, next);
            assert_eq!(got, want, "row {i}");
        }
    }

    /// A runner for profile `name` against a real TCP target (`rtu+tcp` when `rtu`) at `port` of 127.0.0.1.
    fn runner_over_tcp(name: &str, port: u16, rtu: bool) -> Runner {
        let p = drives::corpus::Corpus::Embedded
            .profile(name)
            .expect("profile");
        let target =
            crate::targets::net::TcpTarget::connect("127.0.0.1", port, Duration::from_secs(2), rtu)
                .expect("connect");
        let unit = p.device.default_unit;
        let cfg = RunConfig {
            unit,
            timing: Timing::default(),
            safety: Safety::default(),
            is_sim: false,
        };
        let shadow = drives::Station::new(
            drives::build(p.clone(), drives::FaultSet::none()),
            drives::FaultSet::none(),
            unit,
        );
        Runner::new(
            Box::new(target),
            SimTarget::new(shadow),
            p,
            cfg,
            Expectations::default(),
        )
    }

    /// The rule of a rerun: only a frame that decodes as a response, coming in the pause before the case
    /// would be run again, is a late answer (the case is then judged at its first attempt). A stray byte of
    /// a noisy line, a frame whose CRC does not check, a well-framed PDU that is no response (a byte count
    /// its data does not have), a cut frame, or nothing at all prove nothing: the case is run again. Each row: a loopback peer sends its bytes 20 ms into a 100 ms pause.
    #[test]
    fn only_a_response_frame_in_the_pause_is_a_late_answer() {
        let rtu_answer = |unit: u8, corrupt: bool| {
            let mut f = vec![unit, 0x03, 0x02, 0x00, 0x2A];
            let crc = codec::rtu::crc16(&f).to_le_bytes();
            f.extend_from_slice(&crc);
            if corrupt {
                f[6] ^= 0xFF;
            }
            f
        };
        let mut tcp_answer = Vec::new();
        tcp::encode_adu(7, 1, &[0x03, 0x02, 0x00, 0x2A], &mut tcp_answer).expect("encodes");
        // Framed well (MBAP length, CRC) but no response: a byte count the data does not have.
        let mut tcp_miscounted = Vec::new();
        tcp::encode_adu(7, 1, &[0x03, 0x05, 0x00], &mut tcp_miscounted).expect("encodes");
        let rtu_miscounted = |unit: u8| {
            let mut f = vec![unit, 0x03, 0x05, 0x00];
            let crc = codec::rtu::crc16(&f).to_le_bytes();
            f.extend_from_slice(&crc);
            f
        };
        let mut tcp_exception = Vec::new();
        tcp::encode_adu(7, 1, &[0x83, 0x02], &mut tcp_exception).expect("encodes");
        // (profile, rtu over tcp, bytes sent in the pause, a late answer?)
        let sd2x_unit = drives::corpus::Corpus::Embedded
            .profile("sd2x")
            .expect("profile")
            .device
            .default_unit;
        let rows: Vec<(&str, bool, Vec<u8>, bool)> = vec![
            ("sd2x", true, rtu_answer(sd2x_unit, false), true),
            ("sd2x", true, rtu_answer(sd2x_unit, true), false),
            ("sd2x", true, rtu_miscounted(sd2x_unit), false),
            ("sd2x", true, vec![0x00], false),
            ("sd2x", true, vec![0xFF, 0x13, 0x00], false),
            ("sd2x", true, Vec::new(), false),
            ("generic", false, tcp_answer.clone(), true),
            ("generic", false, tcp_exception, true),
            ("generic", false, tcp_miscounted, false),
            ("generic", false, tcp_answer[..5].to_vec(), false),
            ("generic", false, Vec::new(), false),
        ];
        // Each row sent at once 20 ms into the pause, and the late answers also cut in two, begun 85 ms into
        // the pause and ended 30 ms after it (a frame begun in the pause is waited for).
        let rows = rows.into_iter().flat_map(|(name, rtu, bytes, late)| {
            let split = (late, (name, rtu, bytes.clone(), late, 85, bytes.len() / 2));
            std::iter::once((name, rtu, bytes, late, 20, 0)).chain(split.0.then_some(split.1))
        });
        for (i, (name, rtu, bytes, late, at, cut)) in rows.enumerate() {
            let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
            let port = listener.local_addr().expect("addr").port();
            let peer = std::thread::spawn(move || {
                use std::io::Write;
                let (mut s, _) = listener.accept().expect("accept");
                std::thread::sleep(Duration::from_millis(at));
                if cut > 0 {
                    s.write_all(&bytes[..cut]).expect("send");
                    std::thread::sleep(Duration::from_millis(45));
                    s.write_all(&bytes[cut..]).expect("send");
                } else if !bytes.is_empty() {
                    s.write_all(&bytes).expect("send");
                }
                // Held open until the runner has looked (bounded).
                std::thread::sleep(Duration::from_millis(400));
            });
            let mut runner = runner_over_tcp(name, port, rtu);
            assert_eq!(
                runner.came_within(Duration::from_millis(100)),
                late,
                "row {i}"
            );
            drop(runner);
            peer.join().expect("peer");
        }
    }

    #[test]
    fn server_busy_is_recognised() {
        let bytes = |tid, pdu: &[u8]| {
            let mut b = Vec::new();
            tcp::encode_adu(tid, 1, pdu, &mut b).expect("encodes");
            b
        };
        assert!(busy_refusal(&bytes(1, &[0x83, 0x06])));
        assert!(!busy_refusal(&bytes(1, &[0x83, 0x03])));
        assert!(!busy_refusal(&bytes(1, &[0x03, 0x06])));
        assert!(!busy_refusal(&bytes(1, &[0x03, 0x02, 0x00, 0x06])));
    }
}
