//! The case catalog: golden replay, generic Modbus cases from the specs, and cases derived from the
//! profile. Expected answers are not written here: the reference model (the oracle) gives them.
//!
//! One module per suite; [`build`] runs them in a fixed order, which is the order of the report. No case
//! depends on that order: each establishes its own precondition and puts back what it changed (`around`),
//! and the few that leave the drive changed for good ([`Tag::Irreversible`]) come last.

mod around;
mod canopen;
mod ds402;
mod golden;
mod mcode;
mod profile;
pub mod public_fc;
pub mod rtu;
mod spec;
mod tcp;

use std::time::Duration;

use crate::cases::{Case, Compare, Level, Outgoing, Step, Tag};
use codec::FunctionCode;
use codec::{Framing, Request, Response};
use drives::FaultSet;
use drives::golden::GoldenFile;
use drives::profile::{Profile, Table};

/// The references the spec suites cite.
const APP: &str = "Modbus Application Protocol Specification V1.1b3";
const TCPG: &str = "Modbus Messaging on TCP/IP Implementation Guide V1.0b";
const SER: &str = "Modbus over Serial Line Specification V1.02";

/// The PDU of a request; empty if the codec refuses it.
fn pdu(r: &Request) -> Vec<u8> {
    r.to_bytes().unwrap_or_default()
}

/// A step that sends and compares.
fn exchange(send: Outgoing, compare: Compare, note: impl Into<String>) -> Step {
    Step::Exchange {
        send,
        compare,
        capture: None,
        note: note.into(),
    }
}

/// A step that sends, compares, and keeps the response's registers in `slot`.
fn capture(send: Outgoing, compare: Compare, slot: usize, note: impl Into<String>) -> Step {
    Step::Exchange {
        send,
        compare,
        capture: Some(slot),
        note: note.into(),
    }
}

/// What the suites build from (the profile, the unit id) and the cases built so far, in report order.
struct Ctx<'a> {
    p: &'a Profile,
    unit: u8,
    /// The slave address the cases send another slave's frames to (see [`rtu::other_slave`]).
    foreign: u8,
    cases: Vec<Case>,
    /// A reference drive fresh from power-up, built at the first [`Ctx::reference_accepts`]: each check
    /// asks a copy of it. Building one per check (a copy of the profile, a register bank) took a quarter of
    /// the time a one-case run of the MDrive or LMD took to start.
    fresh: std::cell::OnceCell<Box<dyn drives::DriveModel>>,
}

impl<'a> Ctx<'a> {
    /// A context that builds requests for `p` and `unit`, no cases.
    fn bare(p: &'a Profile, unit: u8) -> Self {
        Ctx {
            p,
            unit,
            foreign: rtu::other_slave(unit),
            cases: Vec::new(),
            fresh: std::cell::OnceCell::new(),
        }
    }

    /// Add a case checking a MUST-level requirement (every catalog case is one; SHOULD-level deviations
    /// are found inside steps, e.g. RTU timing).
    fn push(
        &mut self,
        id: String,
        title: impl Into<String>,
        reference: impl Into<String>,
        requirement: impl Into<String>,
        tags: Vec<Tag>,
        steps: Vec<Step>,
    ) {
        self.cases.push(Case {
            id,
            title: title.into(),
            reference: reference.into(),
            requirement: requirement.into(),
            level: Level::Must,
            tags,
            steps,
            requirements: Vec::new(),
            freedoms: Vec::new(),
        });
    }

    fn supports(&self, fc: impl Into<FunctionCode>) -> bool {
        self.p.function(fc).is_some()
    }

    fn max_quantity(&self, fc: impl Into<FunctionCode>) -> u16 {
        self.p.max_quantity(fc)
    }

    /// A read that every healthy drive of the profile answers: the liveness probe after malformed input.
    fn liveness(&self) -> Step {
        exchange(
            Outgoing::Pdu(known_good_read(self.p)),
            Compare::Structure,
            "liveness: a valid read is still answered",
        )
    }

    fn read_request(&self, address: u16, quantity: u16, table: Table) -> Request {
        let fc04 = table == Table::Input
            || (!self.supports(FunctionCode::READ_HOLDING_REGISTERS)
                && self.supports(FunctionCode::READ_INPUT_REGISTERS));
        if fc04 {
            Request::ReadInputRegisters { address, quantity }
        } else {
            Request::ReadHoldingRegisters { address, quantity }
        }
    }

    fn write_request(&self, address: u16, values: Vec<u16>) -> Request {
        if values.len() == 1
            && !self.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS)
            && self.supports(FunctionCode::WRITE_SINGLE_REGISTER)
        {
            Request::WriteSingleRegister {
                address,
                value: values[0],
            }
        } else {
            Request::WriteMultipleRegisters { address, values }
        }
    }

    fn can_write_registers(&self) -> bool {
        self.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS)
            || self.supports(FunctionCode::WRITE_SINGLE_REGISTER)
    }

    /// True when a reference drive fresh from power-up answers `req` normally (not with an exception): used to
    /// pick values a conforming drive accepts (e.g. a microstep resolution from the MDrive's table), never to
    /// write an expected answer into a case.
    fn reference_accepts(&self, req: &Request) -> bool {
        let mut drive = self
            .fresh
            .get_or_init(|| drives::build(self.p.clone(), FaultSet::none()))
            .box_clone();
        drive
            .handle(Duration::ZERO, self.unit, req)
            .is_some_and(|r| !matches!(r, Response::Exception { .. }))
    }
}

/// A read of the first readable register: the liveness probe.
pub fn known_good_read(p: &Profile) -> Vec<u8> {
    let reg = p
        .registers
        .iter()
        .map(|r| r.get_ref())
        .find(|r| r.access.readable());
    let (address, width, input) = reg.map_or((0, 1, false), |r| {
        (r.address, r.width, r.table == Table::Input)
    });
    let req = if input
        || p.function(FunctionCode::READ_HOLDING_REGISTERS).is_none()
            && p.function(FunctionCode::READ_INPUT_REGISTERS).is_some()
    {
        Request::ReadInputRegisters {
            address,
            quantity: u16::from(width),
        }
    } else {
        Request::ReadHoldingRegisters {
            address,
            quantity: u16::from(width),
        }
    };
    pdu(&req)
}

/// A name as an id segment: lowercase ASCII letters and digits, dashes between, at most 40 characters.
fn slug(s: &str) -> String {
    slug_of_length(s, 40)
}

/// A name as an id or file-name segment of at most `max` characters (lowercase letters, digits, dashes).
pub fn slug_of_length(s: &str, max: usize) -> String {
    let mut out = String::new();
    for c in s.chars() {
        if c.is_ascii_alphanumeric() {
            out.push(c.to_ascii_lowercase());
        } else if !out.ends_with('-') {
            out.push('-');
        }
    }
    out.trim_matches('-').chars().take(max).collect()
}

/// Build the catalog for a profile on a transport.
pub fn build(p: &Profile, golden: Option<&GoldenFile>, framing: Framing, unit: u8) -> Vec<Case> {
    build_on_line(p, golden, framing, unit, None)
}

/// [`build`], with the cases that send a frame for another slave sending it to `foreign` (an address the
/// line survey found no device answering, or the user's `--foreign-address`); `None`: the address next but
/// one to the drive's ([`rtu::other_slave`]).
pub fn build_on_line(
    p: &Profile,
    golden: Option<&GoldenFile>,
    framing: Framing,
    unit: u8,
    foreign: Option<u8>,
) -> Vec<Case> {
    let mut cx = Ctx::bare(p, unit);
    if let Some(f) = foreign {
        cx.foreign = f;
    }
    if let Some(g) = golden {
        golden::cases(&mut cx, g, framing);
    }
    spec::cases(&mut cx);
    match framing {
        Framing::Tcp => tcp::cases(&mut cx),
        Framing::Rtu => rtu::cases(&mut cx),
        Framing::Pdu => {}
    }
    profile::cases(&mut cx);
    if p.device.id == "sd2x" || !p.objects.is_empty() {
        canopen::cases(&mut cx);
    }
    if p.watchdog.is_some() {
        ds402::cases(&mut cx);
    }
    // The safety tags are the classifier's rating of each case's own bytes, not what the case's code wrote.
    let cases = cx
        .cases
        .into_iter()
        .map(|c| c.classified(p, unit))
        .collect();
    irreversible_last(cases)
}

/// The cases with the [`Tag::RunTiming`] ones (which judge what the run measured) and then the
/// [`Tag::Irreversible`] ones moved after all others, each group in its own order.
///
/// An irreversible case that sends what an earlier one sent (the LMD's UG, once as the manual's golden frame
/// and once as the mnemonic's example) is left out: it would meet the state the first left (a drive in
/// firmware-upgrade mode refusing every vendor request with 04), not the one it was written for.
pub fn irreversible_last(cases: Vec<Case>) -> Vec<Case> {
    let (cases, last): (Vec<Case>, Vec<Case>) =
        cases.into_iter().partition(|c| !c.has(Tag::Irreversible));
    let mut sent: Vec<Vec<crate::cases::Outgoing>> = Vec::new();
    let last: Vec<Case> = last
        .into_iter()
        .filter(|c| {
            let steps: Vec<crate::cases::Outgoing> = c
                .steps
                .iter()
                .filter_map(|s| match s {
                    crate::cases::Step::Exchange { send, .. }
                    | crate::cases::Step::Persist { send, .. } => Some(send.clone()),
                    _ => None,
                })
                .collect();
            if sent.contains(&steps) {
                return false;
            }
            sent.push(steps);
            true
        })
        .collect();
    let (mut cases, timing): (Vec<Case>, Vec<Case>) =
        cases.into_iter().partition(|c| !c.has(Tag::RunTiming));
    cases.extend(timing);
    cases.extend(last);
    cases
}

/// The shrunk reproducers of a profile, `corpus/regressions/<profile>/*.toml`, as cases
/// `regression/<profile>/<file name>` (see [`crate::cases::regressions`] for the file format). A
/// reproducer is kept as shrunk; what its writes need is put around it as around a catalog write (what they
/// write read first and put back after, their precondition established), so that it depends on no other case
/// and leaves the drive as it found it even where it FAILs.
pub fn regressions(
    corpus: &drives::corpus::Corpus,
    p: &Profile,
    unit: u8,
) -> Result<Vec<Case>, crate::cases::regressions::RegressionError> {
    let cases = crate::cases::regressions::load_regressions(corpus, &p.device.id)?;
    let cx = Ctx::bare(p, unit);
    Ok(cases
        .into_iter()
        .map(|c| around_writes(&cx, c).classified(p, unit))
        .collect())
}

/// `case` with [`around::around_write`] applied to every request it sends, its own capture slots left alone.
fn around_writes(cx: &Ctx, mut case: Case) -> Case {
    let mut a = around::Around::from_slot(case.slots());
    let requests: Vec<Request> = case
        .steps
        .iter()
        .filter_map(|s| match s {
            Step::Exchange { send, .. } => Some(send),
            _ => None,
        })
        .flat_map(|send| match send {
            Outgoing::Pdu(p) | Outgoing::PduToUnit { pdu: p, .. } => vec![p.clone()],
            Outgoing::Mutated { pdu, mutation } => {
                vec![mutation.apply_to_pdu(pdu).unwrap_or_else(|| pdu.clone())]
            }
            Outgoing::Batch(ps) => ps.clone(),
            Outgoing::Restore { .. } | Outgoing::RestoreRead { .. } => vec![],
        })
        .filter_map(|p| Request::decode(&p).ok())
        .collect();
    for r in &requests {
        around::around_write(cx, r, &mut a, &mut case.tags);
    }
    case.steps = a.wrap(std::mem::take(&mut case.steps));
    case
}
