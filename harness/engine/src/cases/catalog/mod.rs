//! The case catalog: golden replay, generic Modbus cases from the specs, and cases derived from the
//! profile. Expected answers are not written here: the reference model (the oracle) gives them.
//!
//! One module per suite; [`build`] runs them in a fixed order, which is the order of the report.

mod canopen;
mod ds402;
mod golden;
mod profile;
mod rtu;
mod spec;
mod tcp;

use crate::cases::{Case, Compare, Level, Outgoing, Step, Tag};
use codec::FunctionCode;
use codec::{Framing, Request};
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
    cases: Vec<Case>,
}

impl Ctx<'_> {
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
        let fc = fc.into();
        self.p
            .function(fc)
            .and_then(|f| f.max_quantity)
            .or(fc.max_quantity())
            .unwrap_or(125)
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
    let mut cx = Ctx {
        p,
        unit,
        cases: Vec::new(),
    };
    if let Some(g) = golden {
        golden::cases(&mut cx, g);
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
    cx.cases
}

/// The shrunk reproducers of a profile, `corpus/regressions/<profile>/*.toml`, as cases
/// `regression/<profile>/<file name>` (see [`crate::cases::regressions`] for the file format).
pub fn regressions(
    corpus: &drives::corpus::Corpus,
    p: &Profile,
) -> Result<Vec<Case>, crate::cases::regressions::RegressionError> {
    crate::cases::regressions::load_regressions(corpus, &p.device.id)
}
