//! Turning a generated description into a [`Case`]: [`GenContext`] holds the profile data the
//! descriptions index into, [`Spec::build`] builds the steps that the runner sends and the oracle judges
//! like any catalog case.
//!
//! Safety: every PDU a built case sends is tagged by what it would do on a drive ([`pdu_tags`]): writes
//! `write`, writes to motion registers, coils, objects or mnemonics `motion`, to destructive ones or to the
//! watchdog `destructive`. A write addressed to another unit is `destructive` (it may reach another drive
//! on the bus), and so is a malformed write whose address is no longer the generated one.

use std::collections::BTreeSet;

use super::spec::{
    Alter, Edge, FileGroup, MAX_BATCH_EXTRA, MAX_EXTEND, MAX_FILE_GROUP, MAX_SPLIT_GAP_US, Op,
    Quantity, Req, Spec, Value,
};
use crate::cases::catalog::known_good_read;
use crate::cases::catalog::public_fc::{self, Exercise, Prelude};
use crate::cases::catalog::rtu::sd2x_partner;
use crate::{Case, Compare, Level, Mutation, Outgoing, Step, Tag};
use codec::FunctionCode;
use codec::codes::diag;
use codec::{CanOpenAccess, MAX_PDU_LEN, Mnemonic, Request};
use drives::profile::{Bit, Object, Profile, Register, Table, VendorMnemonic};

/// The profile data the generators draw from, for one run (profile and unit id).
#[derive(Clone, Debug)]
pub struct GenContext {
    profile: Profile,
    unit: u8,
    /// An address the line survey found no device answering (or the user's `--foreign-address`): where set,
    /// the frames for "another unit" that may reach another device on the line go to it.
    foreign: Option<u8>,
    pub(super) regs: Vec<Register>,
    pub(super) wide: Vec<Register>,
    pub(super) holding: Vec<u16>,
    pub(super) input: Vec<u16>,
    pub(super) coils: Vec<Bit>,
    pub(super) discretes: Vec<Bit>,
    pub(super) read_mnemonics: Vec<VendorMnemonic>,
    pub(super) write_mnemonics: Vec<VendorMnemonic>,
    pub(super) objects: Vec<Object>,
    pub(super) diagnostics: Vec<u16>,
    pub(super) id_objects: Vec<u8>,
    functions: Vec<u8>,
    pub(super) unsupported: Vec<u8>,
    /// The profile's files: (number, records, writable).
    pub(super) files: Vec<(u16, u16, bool)>,
    /// The holding registers FC 16 may be tried on.
    pub(super) mask_regs: Vec<u16>,
    /// The profile's queues (pointer addresses).
    pub(super) fifos: Vec<u16>,
    known_good: Vec<u8>,
    /// The profile has motion registers, coils or mnemonics: values may change by themselves.
    can_move: bool,
}

/// Entry `i` of `list`, modulo its length; `None` for an empty list.
fn pick<T>(list: &[T], i: impl Into<usize>) -> Option<&T> {
    if list.is_empty() {
        None
    } else {
        list.get(i.into() % list.len())
    }
}

impl GenContext {
    /// The same lists, with the frames for another unit sent to `foreign` where it is set (see
    /// [`wrong_unit`]).
    pub fn on_line(mut self, foreign: Option<u8>) -> Self {
        self.foreign = foreign;
        self
    }

    /// The lists a profile's generators draw from, for requests to `unit`.
    pub fn new(profile: &Profile, unit: u8) -> Self {
        let mut regs: Vec<Register> = profile
            .registers
            .iter()
            .map(|r| r.get_ref().clone())
            .collect();
        regs.sort_by_key(|r| (r.address, r.table == Table::Input));
        let wide = regs.iter().filter(|r| r.width == 2).cloned().collect();
        let addrs = |input: bool| {
            let mut a: Vec<u16> = regs
                .iter()
                .filter(|r| match r.table {
                    Table::Both => true,
                    Table::Input => input,
                    Table::Holding => !input,
                })
                .flat_map(|r| (0..u16::from(r.width)).map(move |i| r.address.wrapping_add(i)))
                .collect();
            a.sort_unstable();
            a.dedup();
            a
        };
        let holding = addrs(false);
        let input = addrs(true);
        let bits = |list: &[toml::Spanned<Bit>]| {
            let mut v: Vec<Bit> = list.iter().map(|b| b.get_ref().clone()).collect();
            v.sort_by_key(|b| b.address);
            v
        };
        let mnemonics: Vec<VendorMnemonic> = profile
            .mnemonics
            .iter()
            .map(|m| m.get_ref().clone())
            .filter(|m| Mnemonic::from_name(&m.name).is_some())
            .collect();
        let functions: Vec<u8> = profile.functions.iter().map(|f| f.code.0).collect();
        let unsupported = (0x01u8..=0x7F)
            .filter(|fc| !functions.contains(fc))
            .collect();
        Self {
            profile: profile.clone(),
            unit,
            foreign: None,
            wide,
            holding,
            input,
            coils: bits(&profile.coils),
            discretes: bits(&profile.discrete_inputs),
            read_mnemonics: mnemonics.iter().filter(|m| m.read).cloned().collect(),
            write_mnemonics: mnemonics
                .iter()
                .filter(|m| m.write && m.example.is_some())
                .cloned()
                .collect(),
            objects: profile
                .objects
                .iter()
                .map(|o| o.get_ref().clone())
                .collect(),
            diagnostics: profile.diagnostics.iter().map(|d| d.sub_function).collect(),
            id_objects: profile.identification.iter().map(|o| o.object_id).collect(),
            functions,
            unsupported,
            files: public_fc::files(profile)
                .into_iter()
                .filter(|f| f.1 > 0)
                .collect(),
            mask_regs: public_fc::mask_registers(profile),
            fifos: public_fc::fifos(profile).into_iter().map(|q| q.0).collect(),
            known_good: known_good_read(profile),
            can_move: profile.registers.iter().any(|r| r.get_ref().motion)
                || profile.coils.iter().any(|c| c.get_ref().motion)
                || profile.mnemonics.iter().any(|m| m.get_ref().motion)
                || profile.objects.iter().any(|o| o.get_ref().motion),
            regs,
        }
    }

    /// The profile.
    pub fn profile(&self) -> &Profile {
        &self.profile
    }

    /// The unit id requests are framed for (FC 43/13 node ids use it too).
    pub fn unit(&self) -> u8 {
        self.unit
    }

    /// True if the profile supports function code `fc`.
    pub(super) fn supports(&self, fc: impl Into<FunctionCode>) -> bool {
        self.functions.contains(&fc.into().0)
    }

    /// The quantity limit of `fc`: the profile's, else the spec's.
    fn max_quantity(&self, fc: impl Into<FunctionCode>) -> u16 {
        self.profile.max_quantity(fc)
    }

    /// The read function for a table choice: FC 04 for input registers where supported, else FC 03.
    fn read_fc(&self, table: Table, input: bool) -> u8 {
        let (r3, r4) = (
            self.supports(FunctionCode::READ_HOLDING_REGISTERS),
            self.supports(FunctionCode::READ_INPUT_REGISTERS),
        );
        match table {
            Table::Input if r4 || !r3 => 0x04,
            Table::Holding if r3 || !r4 => 0x03,
            Table::Both if input && r4 => 0x04,
            Table::Both if r3 => 0x03,
            Table::Both => 0x04,
            Table::Input => 0x03,
            Table::Holding => 0x04,
        }
    }

    fn edge(&self, list: &[u16], e: Edge) -> u16 {
        match e {
            Edge::First => list.first().copied().unwrap_or(0),
            Edge::Last => list.last().copied().unwrap_or(0),
            Edge::Entry(i) => pick(list, i).copied().unwrap_or(0),
        }
    }

    fn quantity(&self, q: Quantity, max: u16) -> u16 {
        match q {
            Quantity::One => 1,
            Quantity::Max => max,
            Quantity::Zero => 0,
            Quantity::AboveMax => max.saturating_add(1),
            Quantity::Any(n) => 1 + n % max.max(1),
        }
    }

    fn coil_addresses(&self, discrete: bool) -> Vec<u16> {
        let list = if discrete {
            &self.discretes
        } else {
            &self.coils
        };
        list.iter().map(|b| b.address).collect()
    }
}

/// A value for a range `min..=max` within the natural range `lo..=hi` of a register or object.
fn value_in(v: Value, (min, max): (i64, i64), (lo, hi): (i64, i64)) -> i64 {
    let span = |a: i64, b: i64| (b - a + 1).max(1);
    match v {
        Value::Min => min,
        Value::Max => max,
        Value::BelowMin => min - 1,
        Value::AboveMax => max + 1,
        Value::InRange(x) => min + i64::from(x) % span(min, max),
        Value::Raw(x) => lo + i64::from(x) % span(lo, hi),
    }
}

fn value_label(v: Value) -> &'static str {
    match v {
        Value::Min => " (min)",
        Value::Max => " (max)",
        Value::BelowMin => " (below min)",
        Value::AboveMax => " (above max)",
        Value::InRange(_) => "",
        Value::Raw(_) => " (any)",
    }
}

fn reg_name(r: &Register) -> String {
    match &r.mnemonic {
        Some(m) => format!("0x{:04X} {m}", r.address),
        None => format!("0x{:04X} {}", r.address, r.name),
    }
}

fn to_pdu(r: &Request) -> Vec<u8> {
    match r.to_bytes() {
        Ok(b) => b,
        // Too long for the codec (a quantity above the limit): the fields as they would be, unchecked.
        Err(_) => match r {
            Request::WriteMultipleRegisters { address, values } => {
                let mut b = vec![0x10];
                b.extend_from_slice(&address.to_be_bytes());
                b.extend_from_slice(&(values.len() as u16).to_be_bytes());
                b.push((values.len() * 2) as u8);
                b.extend(values.iter().flat_map(|v| v.to_be_bytes()));
                b
            }
            Request::WriteMultipleCoils {
                address,
                quantity,
                data,
            } => {
                let mut b = vec![0x0F];
                b.extend_from_slice(&address.to_be_bytes());
                b.extend_from_slice(&quantity.to_be_bytes());
                b.push(data.len() as u8);
                b.extend_from_slice(data);
                b
            }
            _ => vec![r.function().0],
        },
    }
}

/// A register read with function code `fc`: FC 04 for 0x04, FC 03 otherwise.
fn read_request(fc: u8, address: u16, quantity: u16) -> Request {
    if fc == 0x04 {
        Request::ReadInputRegisters { address, quantity }
    } else {
        Request::ReadHoldingRegisters { address, quantity }
    }
}

/// A request built from a [`Req`]: the PDU, how it is judged, and the steps of a read-write-restore check;
/// for the function codes the catalog builds (`public_fc`), the steps around the request and what its
/// answers may choose.
struct Built {
    pdu: Vec<u8>,
    compare: Compare,
    kind: &'static str,
    note: String,
    check: Option<Check>,
    /// Steps before the request (its precondition, what it changes kept), sent whatever the alteration.
    before: Vec<Step>,
    /// Steps after it (read back, put back), sent whatever the alteration.
    after: Vec<Step>,
    /// Transport tags the request needs.
    tags: Vec<Tag>,
    /// Freedoms its answers may use.
    freedoms: Vec<String>,
}

/// Read first into slot 0, read back after the write, restore from slot 0.
struct Check {
    read: Vec<u8>,
    address: u16,
}

impl Built {
    /// A request without a read-write-restore check.
    fn plain(pdu: Vec<u8>, compare: Compare, kind: &'static str, note: String) -> Self {
        Built {
            pdu,
            compare,
            kind,
            note,
            check: None,
            before: Vec::new(),
            after: Vec::new(),
            tags: Vec::new(),
            freedoms: Vec::new(),
        }
    }

    /// A request of the catalog's public function code family, with what it needs around it.
    fn exercise(e: Exercise, kind: &'static str) -> Self {
        Built {
            pdu: e.pdu,
            compare: e.compare,
            kind,
            note: e.note,
            check: None,
            before: e.before,
            after: e.after,
            tags: e.tags,
            freedoms: e.freedoms,
        }
    }
}

impl Req {
    /// The request as sent as is, for `cx`'s profile.
    fn build(&self, cx: &GenContext) -> Built {
        match *self {
            Req::ReadRegister { reg, input } => read_register(cx, reg, input),
            Req::ReadHalf { reg, second } => read_half(cx, reg, second),
            Req::ReadSpan {
                at,
                quantity,
                input,
            } => read_span(cx, at, quantity, input),
            Req::WriteRegister {
                reg,
                value,
                fc06,
                check,
            } => write_register(cx, reg, value, fc06, check),
            Req::WriteHalf {
                reg,
                second,
                word,
                fc06,
            } => write_half(cx, reg, second, word, fc06),
            Req::WriteSpan { at, quantity, word } => write_span(cx, at, quantity, word),
            Req::ReadBits {
                discrete,
                at,
                quantity,
            } => read_bits(cx, discrete, at, quantity),
            Req::WriteCoil { coil, on, check } => write_coil(cx, coil, on, check),
            Req::WriteCoils { at, quantity, bits } => write_coils(cx, at, quantity, bits),
            Req::ReadWrite {
                at,
                quantity,
                reg,
                value,
            } => read_write(cx, at, quantity, reg, value),
            Req::Diagnostic { sub, data } => diagnostic(cx, sub, data),
            Req::DeviceId { code, object } => device_id(cx, code, object),
            Req::ObjectRead { obj, count } => object_read(cx, obj, count),
            Req::ObjectWrite { obj, value } => object_write(cx, obj, value),
            Req::VendorRead { mnemonic } => vendor_read(cx, mnemonic),
            Req::VendorWrite { mnemonic } => vendor_write(cx, mnemonic),
            Req::Unsupported { fc, len } => unsupported(cx, fc, len),
            Req::ExceptionStatus { pattern } => exercise(
                cx,
                0x07,
                public_fc::exception_status(&cx.profile, cx.unit, pattern),
                "exception-status",
            ),
            Req::CommEvent { log, prelude } => comm_event(cx, log, prelude),
            Req::ServerId => exercise(
                cx,
                0x11,
                public_fc::report_server_id(&cx.profile),
                "server-id",
            ),
            Req::FileRead { first, second } => file_read(cx, first, second),
            Req::FileWrite {
                first,
                second,
                word,
            } => file_write(cx, first, second, word),
            Req::MaskWrite {
                reg,
                current,
                and,
                or,
            } => mask_write(cx, reg, current, and, or),
            Req::Fifo { queue } => {
                let e = pick(&cx.fifos, queue).and_then(|q| public_fc::read_fifo(&cx.profile, *q));
                exercise(cx, 0x18, e, "fifo")
            }
        }
    }
}

/// A request of the catalog's public function code family as built, or, where the profile lacks function
/// code `fc` (or what it acts on), `fc` sent as a function code the profile does not support.
fn exercise(cx: &GenContext, fc: u8, e: Option<Exercise>, kind: &'static str) -> Built {
    match e {
        Some(e) => Built::exercise(e, kind),
        None => {
            let i = cx.unsupported.iter().position(|c| *c == fc).unwrap_or(0);
            unsupported(cx, i as u16, 0)
        }
    }
}

/// FC 0B or FC 0C after a prelude. Spec 6.9 fixes the count after a clear and 6.10 the log after a restart
/// (`public_fc::comm_event`); without a prelude they are the drive's history, compared in format only. A
/// prelude the profile cannot send (an FC 08 sub-function it lacks) is left out.
fn comm_event(cx: &GenContext, log: bool, prelude: u8) -> Built {
    let fc = if (log && cx.supports(0x0Cu8)) || !cx.supports(0x0Bu8) {
        0x0C
    } else {
        0x0B
    };
    let prelude = [Prelude::None, Prelude::Clear, Prelude::Restart][usize::from(prelude % 3)];
    let e = public_fc::comm_event(&cx.profile, cx.unit, fc, prelude)
        .or_else(|| public_fc::comm_event(&cx.profile, cx.unit, fc, Prelude::None));
    exercise(
        cx,
        fc,
        e,
        if fc == 0x0C {
            "comm-event-log"
        } else {
            "comm-event-counter"
        },
    )
}

/// A group of file records of `files` (file, first record, length): records inside the file, at most
/// [`MAX_FILE_GROUP`].
fn file_group(files: &[(u16, u16, bool)], g: FileGroup) -> Option<(u16, u16, u16)> {
    let &(file, records, _) = pick(files, g.file)?;
    let record = g.record % records.max(1);
    let room = (records - record).clamp(1, MAX_FILE_GROUP);
    Some((file, record, 1 + u16::from(g.len) % room))
}

/// FC 14 of one or two groups inside the profile's files (spec 6.14).
fn file_read(cx: &GenContext, first: FileGroup, second: Option<FileGroup>) -> Built {
    let groups: Vec<(u16, u16, u16)> = [Some(first), second]
        .into_iter()
        .flatten()
        .filter_map(|g| file_group(&cx.files, g))
        .collect();
    let e = (!groups.is_empty())
        .then(|| public_fc::read_file_records(&cx.profile, &groups))
        .flatten();
    exercise(cx, 0x14, e, "file-read")
}

/// FC 15 of one or two groups inside the profile's writable files (spec 6.15), read back and put back.
fn file_write(cx: &GenContext, first: FileGroup, second: Option<FileGroup>, word: u16) -> Built {
    let writable: Vec<(u16, u16, bool)> = cx.files.iter().filter(|f| f.2).copied().collect();
    let mut next = word;
    let groups: Vec<(u16, u16, Vec<u16>)> = [Some(first), second]
        .into_iter()
        .flatten()
        .filter_map(|g| file_group(&writable, g))
        .map(|(file, record, len)| {
            let values = (0..len).map(|i| next.wrapping_add(i)).collect();
            next = next.wrapping_add(len);
            (file, record, values)
        })
        .collect();
    let e = (!groups.is_empty())
        .then(|| public_fc::write_file_records(&cx.profile, cx.unit, &groups))
        .flatten();
    exercise(cx, 0x15, e, "file-write")
}

/// FC 16 on a register FC 16 may be tried on (spec 6.16), first set to `current`, read back, put back.
fn mask_write(cx: &GenContext, reg: u16, current: u16, and: u16, or: u16) -> Built {
    let e = pick(&cx.mask_regs, reg)
        .and_then(|a| public_fc::mask_write_register(&cx.profile, cx.unit, *a, current, and, or));
    exercise(cx, 0x16, e, "mask-write")
}

/// FC 03/04 of one register at its width (a span read when the profile has no registers).
fn read_register(cx: &GenContext, reg: u16, input: bool) -> Built {
    let Some(r) = pick(&cx.regs, reg) else {
        return Req::ReadSpan {
            at: Edge::First,
            quantity: Quantity::One,
            input,
        }
        .build(cx);
    };
    let fc = cx.read_fc(r.table, input);
    Built::plain(
        to_pdu(&read_request(fc, r.address, u16::from(r.width))),
        Compare::InRange,
        "read-reg",
        format!(
            "FC {fc:02X} read of {} at its width ({})",
            reg_name(r),
            r.width
        ),
    )
}

/// FC 03/04 of one half of a 32-bit register (a plain register read when there is none).
fn read_half(cx: &GenContext, reg: u16, second: bool) -> Built {
    let Some(r) = pick(&cx.wide, reg) else {
        return Req::ReadRegister { reg, input: second }.build(cx);
    };
    let fc = cx.read_fc(r.table, false);
    let a = r.address.wrapping_add(u16::from(second));
    Built::plain(
        to_pdu(&read_request(fc, a, 1)),
        Compare::InRange,
        "read-half",
        format!(
            "FC {fc:02X} read of the {} half of 32-bit {}",
            if second { "second" } else { "first" },
            reg_name(r)
        ),
    )
}

/// FC 03/04 of a block from a boundary address with a boundary quantity.
fn read_span(cx: &GenContext, at: Edge, quantity: Quantity, input: bool) -> Built {
    let fc = cx.read_fc(Table::Both, input);
    let list = if fc == 0x04 { &cx.input } else { &cx.holding };
    let address = cx.edge(list, at);
    let q = cx.quantity(quantity, cx.max_quantity(fc));
    Built::plain(
        to_pdu(&read_request(fc, address, q)),
        Compare::InRange,
        "read-span",
        format!("FC {fc:02X} read of {q} register(s) from 0x{address:04X} ({at:?}, {quantity:?})"),
    )
}

/// FC 06/16 of one register at its width, with the read-write-restore check where it is safe.
fn write_register(cx: &GenContext, reg: u16, value: Value, fc06: bool, check: bool) -> Built {
    let p = &cx.profile;
    let Some(r) = pick(&cx.regs, reg) else {
        return Req::WriteSpan {
            at: Edge::First,
            quantity: Quantity::One,
            word: 0,
        }
        .build(cx);
    };
    let v = r.undisputed(value_in(value, r.range(), r.natural_range()));
    let values = r.words(p.device.word_order, v);
    let single = values.len() == 1
        && ((fc06 && cx.supports(FunctionCode::WRITE_SINGLE_REGISTER))
            || !cx.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS));
    let req = if single {
        Request::WriteSingleRegister {
            address: r.address,
            value: values[0],
        }
    } else {
        Request::WriteMultipleRegisters {
            address: r.address,
            values,
        }
    };
    let checked = check
        && r.access.readable()
        && r.access.writable()
        && !r.motion
        && (cx.supports(FunctionCode::READ_HOLDING_REGISTERS)
            || cx.supports(FunctionCode::READ_INPUT_REGISTERS));
    Built {
        check: checked.then(|| Check {
            read: to_pdu(&read_request(
                cx.read_fc(r.table, false),
                r.address,
                u16::from(r.width),
            )),
            address: r.address,
        }),
        ..Built::plain(
            to_pdu(&req),
            Compare::Exact,
            "write-reg",
            format!(
                "FC {:02X} write of {} = {v}{}",
                req.function().0,
                reg_name(r),
                value_label(value)
            ),
        )
    }
}

/// FC 06/16 of one half of a 32-bit register (a whole-register write when there is none).
fn write_half(cx: &GenContext, reg: u16, second: bool, word: u16, fc06: bool) -> Built {
    let Some(r) = pick(&cx.wide, reg) else {
        return Req::WriteRegister {
            reg,
            value: Value::Raw(u32::from(word)),
            fc06,
            check: false,
        }
        .build(cx);
    };
    let address = r.address.wrapping_add(u16::from(second));
    let req = if (fc06 && cx.supports(FunctionCode::WRITE_SINGLE_REGISTER))
        || !cx.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS)
    {
        Request::WriteSingleRegister {
            address,
            value: word,
        }
    } else {
        Request::WriteMultipleRegisters {
            address,
            values: vec![word],
        }
    };
    Built::plain(
        to_pdu(&req),
        Compare::Exact,
        "write-half",
        format!(
            "FC {:02X} write of 0x{word:04X} to the {} half of 32-bit {}",
            req.function().0,
            if second { "second" } else { "first" },
            reg_name(r)
        ),
    )
}

/// FC 16 of a block, every register set to one word; cut to fit the PDU limit.
fn write_span(cx: &GenContext, at: Edge, quantity: Quantity, word: u16) -> Built {
    let address = cx.edge(&cx.holding, at);
    let q = cx.quantity(
        quantity,
        cx.max_quantity(FunctionCode::WRITE_MULTIPLE_REGISTERS),
    );
    Built::plain(
        fit(
            to_pdu(&Request::WriteMultipleRegisters {
                address,
                values: vec![word; usize::from(q)],
            }),
            q,
        ),
        Compare::Exact,
        "write-span",
        format!(
            "FC 10 write of {q} register(s) = 0x{word:04X} from 0x{address:04X} ({at:?}, {quantity:?})"
        ),
    )
}

/// FC 01/02 of a block of bits.
fn read_bits(cx: &GenContext, discrete: bool, at: Edge, quantity: Quantity) -> Built {
    let fc = if discrete { 0x02 } else { 0x01 };
    let address = cx.edge(&cx.coil_addresses(discrete), at);
    let q = cx.quantity(quantity, cx.max_quantity(fc));
    let req = if discrete {
        Request::ReadDiscreteInputs {
            address,
            quantity: q,
        }
    } else {
        Request::ReadCoils {
            address,
            quantity: q,
        }
    };
    Built::plain(
        to_pdu(&req),
        Compare::Structure,
        if discrete {
            "read-inputs"
        } else {
            "read-coils"
        },
        format!("FC {fc:02X} read of {q} bit(s) from {address} ({at:?}, {quantity:?})"),
    )
}

/// FC 05 of one coil, with the read-write-restore check where it is safe.
fn write_coil(cx: &GenContext, coil: u16, on: bool, check: bool) -> Built {
    let c = pick(&cx.coils, coil);
    let address = c.map_or(0, |c| c.address);
    let value = if on { 0xFF00 } else { 0x0000 };
    Built {
        check: (check && c.is_some_and(|c| !c.motion) && cx.supports(FunctionCode::READ_COILS))
            .then(|| Check {
                read: to_pdu(&Request::ReadCoils {
                    address,
                    quantity: 1,
                }),
                address,
            }),
        ..Built::plain(
            to_pdu(&Request::WriteSingleCoil { address, value }),
            Compare::Exact,
            "write-coil",
            format!(
                "FC 05 coil {address}{} {}",
                c.map_or(String::new(), |c| format!(" {}", c.name)),
                if on { "ON" } else { "OFF" }
            ),
        )
    }
}

/// FC 15 of a block of coils; cut to fit the PDU limit.
fn write_coils(cx: &GenContext, at: Edge, quantity: Quantity, bits: u32) -> Built {
    let address = cx.edge(&cx.coil_addresses(false), at);
    let q = cx.quantity(
        quantity,
        cx.max_quantity(FunctionCode::WRITE_MULTIPLE_COILS),
    );
    let data = (0..usize::from(q).div_ceil(8))
        .map(|i| (bits >> (8 * (i % 4))) as u8)
        .collect();
    Built::plain(
        fit(
            to_pdu(&Request::WriteMultipleCoils {
                address,
                quantity: q,
                data,
            }),
            q,
        ),
        Compare::Exact,
        "write-coils",
        format!("FC 0F write of {q} coil(s) from {address} ({at:?}, {quantity:?})"),
    )
}

/// FC 23: a block read and one register written.
fn read_write(cx: &GenContext, at: Edge, quantity: Quantity, reg: u16, value: Value) -> Built {
    let p = &cx.profile;
    let read_address = cx.edge(&cx.holding, at);
    let read_quantity = cx.quantity(
        quantity,
        cx.max_quantity(FunctionCode::READ_WRITE_MULTIPLE_REGISTERS),
    );
    let (write_address, values, label) = match pick(&cx.regs, reg) {
        Some(r) => {
            let v = r.undisputed(value_in(value, r.range(), r.natural_range()));
            (
                r.address,
                r.words(p.device.word_order, v),
                format!("{} = {v}{}", reg_name(r), value_label(value)),
            )
        }
        None => (0, vec![0], "0x0000 = 0".to_string()),
    };
    Built::plain(
        to_pdu(&Request::ReadWriteMultipleRegisters {
            read_address,
            read_quantity,
            write_address,
            values,
        }),
        Compare::Structure,
        "read-write",
        format!("FC 17 read of {read_quantity} from 0x{read_address:04X}, write {label}"),
    )
}

/// FC 08: a sub-function of the profile, or the one past its list that it does not have.
fn diagnostic(cx: &GenContext, sub: u16, data: u16) -> Built {
    let n = cx.diagnostics.len() + 1;
    // The last choice is a sub-function the profile does not list.
    let sub_function = cx
        .diagnostics
        .get(usize::from(sub) % n)
        .copied()
        .unwrap_or(0x0012);
    let data = if sub_function == 0 { data } else { 0 };
    Built::plain(
        to_pdu(&Request::Diagnostics {
            sub_function,
            data: data.to_be_bytes().to_vec(),
        }),
        if sub_function == 0 {
            Compare::Exact
        } else {
            Compare::Structure
        },
        "diag",
        format!("FC 08 sub-function 0x{sub_function:04X} data 0x{data:04X}"),
    )
}

/// FC 43/14 with any read code, and object ids from the profile or not.
fn device_id(cx: &GenContext, code: u8, object: u8) -> Built {
    let read_code = [1u8, 2, 4, 3, 0, 5][usize::from(code) % 6];
    let object_id = if object < 0x80 {
        pick(&cx.id_objects, object).copied().unwrap_or(0)
    } else {
        object
    };
    let object_id = if matches!(read_code, 1..=3) && object < 0x80 {
        0
    } else {
        object_id
    };
    Built::plain(
        to_pdu(&Request::ReadDeviceId {
            read_code,
            object_id,
        }),
        Compare::Structure,
        "device-id",
        format!("FC 2B/0E read code {read_code} object 0x{object_id:02X}"),
    )
}

/// FC 43/13 read of an object, with its size or another byte count.
fn object_read(cx: &GenContext, obj: u16, count: Option<u8>) -> Built {
    let (index, sub, size, name) = pick(&cx.objects, obj)
        .map_or((0x7FFF, 0, 2, "(none)".to_string()), |o| {
            (o.index, o.subindex, o.ty.size() as u16, o.name.clone())
        });
    let byte_count = count.map_or(size, |c| u16::from(c % 6));
    Built::plain(
        to_pdu(&Request::CanOpen(CanOpenAccess::read(
            cx.unit, index, sub, byte_count,
        ))),
        Compare::Structure,
        "object-read",
        format!("FC 2B/0D read of object {index}.{sub} {name}, {byte_count} byte(s)"),
    )
}

/// FC 43/13 write of an object, the value little-endian at its size (a read when there is none).
fn object_write(cx: &GenContext, obj: u16, value: Value) -> Built {
    let Some(o) = pick(&cx.objects, obj) else {
        return Req::ObjectRead { obj, count: None }.build(cx);
    };
    let size = o.ty.size();
    let signed = matches!(
        o.ty,
        drives::profile::ObjectType::I16 | drives::profile::ObjectType::I32
    );
    let bits = 8 * size as u32;
    let natural = if signed {
        (-(1i64 << (bits - 1)), (1i64 << (bits - 1)) - 1)
    } else {
        (0, (1i64 << bits) - 1)
    };
    let range = (o.min.unwrap_or(natural.0), o.max.unwrap_or(natural.1));
    let v = value_in(value, range, natural);
    let data = (v as u32).to_le_bytes()[..size].to_vec();
    Built::plain(
        to_pdu(&Request::CanOpen(CanOpenAccess::write(
            cx.unit, o.index, o.subindex, data,
        ))),
        Compare::Exact,
        "object-write",
        format!(
            "FC 2B/0D write of object {}.{} {} = {v}{}",
            o.index,
            o.subindex,
            o.name,
            value_label(value)
        ),
    )
}

/// FC 65 read of a mnemonic, or of one the drive does not know.
fn vendor_read(cx: &GenContext, mnemonic: u16) -> Built {
    let n = cx.read_mnemonics.len() + 1;
    let name = cx
        .read_mnemonics
        .get(usize::from(mnemonic) % n)
        .map_or("QQ", |m| m.name.as_str());
    let m = Mnemonic::from_name(name).unwrap_or(Mnemonic(*b"  QQ"));
    Built::plain(
        to_pdu(&Request::VendorRead { mnemonic: m }),
        Compare::Structure,
        "vendor-read",
        format!("FC 41 read of mnemonic {name}"),
    )
}

/// FC 66 write of a mnemonic with its manual example (a read when none is writable).
fn vendor_write(cx: &GenContext, mnemonic: u16) -> Built {
    let Some(m) = pick(&cx.write_mnemonics, mnemonic) else {
        return Req::VendorRead { mnemonic }.build(cx);
    };
    let params = m.example.clone().unwrap_or_default();
    Built::plain(
        to_pdu(&Request::VendorWrite {
            mnemonic: Mnemonic::from_name(&m.name).unwrap_or(Mnemonic(*b"  QQ")),
            params: params.as_bytes().to_vec(),
        }),
        Compare::Exact,
        "vendor-write",
        format!("FC 42 write of {}{params}", m.name),
    )
}

/// A function code the profile does not support, with a few zero bytes.
fn unsupported(cx: &GenContext, fc: u16, len: u8) -> Built {
    let code = pick(&cx.unsupported, fc).copied().unwrap_or(0x7F);
    let mut pdu = vec![code];
    pdu.resize(1 + usize::from(len % 5), 0);
    Built::plain(
        pdu,
        Compare::Exact,
        "unsupported-fc",
        format!(
            "FC {code:02X}, which the profile does not support, with {} data byte(s)",
            len % 5
        ),
    )
}

/// A write PDU (FC 15/16) whose data would not fit the 253-byte PDU limit, sent with its first data bytes
/// only and the quantity field still saying `quantity` (as the catalog's quantity cases do): the quantity
/// check is what is tested, not an over-long frame, whose resynchronisation the oracle does not model.
fn fit(pdu: Vec<u8>, quantity: u16) -> Vec<u8> {
    if pdu.len() <= MAX_PDU_LEN || pdu.len() < 7 {
        return pdu;
    }
    let mut b = pdu[..8].to_vec();
    b[3..5].copy_from_slice(&quantity.to_be_bytes());
    b[5] = 2;
    b
}

/// Offset of the byte count field in a request PDU, for the function codes that have one.
fn byte_count_offset(pdu: &[u8]) -> Option<usize> {
    let at = match *pdu.first()? {
        0x0F | 0x10 | 0x42 => 5,
        0x17 => 9,
        // FC 43/13: the low byte of the 16-bit byte count.
        0x2B if pdu.get(1) == Some(&0x0D) => 11,
        _ => return None,
    };
    (at < pdu.len()).then_some(at)
}

/// Safety tags of a request PDU, from what it would do on a drive of profile `p`: the one classifier,
/// [`crate::cases::safety::classify`].
pub fn pdu_tags(p: &Profile, pdu: &[u8]) -> BTreeSet<Tag> {
    crate::cases::safety::classify(p, pdu)
}

/// The tags of an altered PDU: the original's and the altered bytes' own (a malformed write is rated by
/// the worst register it could reach).
fn altered_tags(p: &Profile, original: &[u8], altered: &[u8]) -> BTreeSet<Tag> {
    let mut tags = pdu_tags(p, original);
    tags.extend(pdu_tags(p, altered));
    tags
}

fn exchange(
    send: Outgoing,
    compare: Compare,
    capture: Option<usize>,
    note: impl Into<String>,
) -> Step {
    Step::Exchange {
        send,
        compare,
        capture,
        note: note.into(),
    }
}

impl Op {
    /// A short name: the request's kind and the alteration (`write-reg`, `read-reg-bitflip`).
    pub fn kind(&self, cx: &GenContext) -> String {
        format!("{}{}", self.req.build(cx).kind, self.alter.label())
    }

    /// Push the operation's steps, add its tags and the freedoms its answers may use; returns the note of its
    /// main exchange.
    fn build(
        &self,
        cx: &GenContext,
        steps: &mut Vec<Step>,
        tags: &mut BTreeSet<Tag>,
        freedoms: &mut Vec<String>,
    ) -> String {
        let b = self.req.build(cx);
        steps.extend(b.before.iter().cloned());
        tags.extend(b.tags.iter().copied());
        for f in &b.freedoms {
            if !freedoms.contains(f) {
                freedoms.push(f.clone());
            }
        }
        let mut tail = Vec::new();
        let (send, compare, what) = self.alter.apply(cx, &b, steps, &mut tail, tags);
        let listen_only = forces_listen_only(&send);
        let note = format!("{}{what}", b.note);
        steps.push(exchange(send, compare, None, note.clone()));
        steps.extend(tail);
        steps.extend(b.after.iter().cloned());
        if listen_only {
            // Force Listen Only Mode gets no response and silences the drive until Restart Communications
            // Option, which itself gets no response in listen only mode (spec 6.8.1): end it as a client
            // would, so that what follows is answered again (a drive that never entered the mode echoes it).
            steps.push(exchange(
                Outgoing::Pdu(
                    Request::Diagnostics {
                        sub_function: diag::RESTART_COMMUNICATIONS,
                        data: vec![0, 0],
                    }
                    .to_bytes()
                    .unwrap_or_default(),
                ),
                Compare::Exact,
                None,
                "08/01 00 00: restart communications, ending listen only mode",
            ));
        }
        if self.liveness && self.alter != Alter::None {
            steps.push(exchange(
                Outgoing::Pdu(cx.known_good.clone()),
                Compare::Structure,
                None,
                "liveness: a valid read is still answered",
            ));
        }
        note
    }
}

/// True when a request `send` sends (as altered) is 08/04, Force Listen Only Mode.
fn forces_listen_only(send: &Outgoing) -> bool {
    let is = |pdu: &[u8]| pdu.starts_with(&[0x08, 0x00, 0x04]);
    match send {
        Outgoing::Pdu(p) | Outgoing::PduToUnit { pdu: p, .. } => is(p),
        Outgoing::Mutated { pdu, mutation } => {
            is(&mutation.apply_to_pdu(pdu).unwrap_or_else(|| pdu.clone()))
        }
        Outgoing::Batch(pdus) => pdus.iter().any(|p| is(p)),
        Outgoing::Restore { .. } | Outgoing::RestoreRead { .. } => false,
    }
}

/// How an operation's main exchange is sent, how its answer is judged, and what its note adds.
type Sent = (Outgoing, Compare, String);

impl Alter {
    /// The main exchange of request `b` altered so; steps that go before it are pushed to `steps`, those
    /// that go after it to `tail`, and the safety tags of what is sent are added to `tags`.
    fn apply(
        &self,
        cx: &GenContext,
        b: &Built,
        steps: &mut Vec<Step>,
        tail: &mut Vec<Step>,
        tags: &mut BTreeSet<Tag>,
    ) -> Sent {
        let p = &cx.profile;
        match self {
            Alter::None => {
                tags.extend(pdu_tags(p, &b.pdu));
                if let Some(c) = &b.check {
                    check_steps(cx, c, steps, tail);
                }
                (
                    Outgoing::Pdu(b.pdu.clone()),
                    b.compare.clone(),
                    String::new(),
                )
            }
            Alter::BitFlip { bit } => {
                let bit = usize::from(*bit) % (b.pdu.len() * 8).max(1);
                (
                    mutated(p, b, Mutation::BitFlip { bit }, tags),
                    Compare::Structure,
                    format!(", bit {bit} of the PDU inverted"),
                )
            }
            Alter::Truncate { keep } => {
                let len = usize::from(*keep) % b.pdu.len().max(1);
                (
                    mutated(p, b, Mutation::Truncate { len }, tags),
                    Compare::Structure,
                    format!(", PDU cut to {len} byte(s)"),
                )
            }
            Alter::Extend { bytes } => extend(p, b, bytes, tags),
            Alter::ByteCount { delta } => byte_count(p, b, *delta, tags),
            Alter::FunctionSwap { to } => function_swap(cx, b, *to, tags),
            Alter::WrongUnit { unit } => wrong_unit(cx, b, *unit, tags),
            Alter::BadCrc => {
                tags.insert(Tag::RtuOnly);
                (
                    mutated(p, b, Mutation::BadCrc, tags),
                    Compare::Exact,
                    ", CRC inverted".to_string(),
                )
            }
            Alter::MbapLength { delta } => {
                tags.insert(Tag::TcpOnly);
                let d = if *delta == 0 { 1 } else { i16::from(*delta) };
                tail.push(Step::Reconnect);
                (
                    mutated(p, b, Mutation::LengthDelta(d), tags),
                    Compare::Structure,
                    format!(", MBAP length {d:+}, then a new connection"),
                )
            }
            Alter::ProtocolId { id } => {
                tags.insert(Tag::TcpOnly);
                let id = if *id == 0 { 1 } else { *id };
                tail.push(Step::Reconnect);
                (
                    mutated(p, b, Mutation::ProtocolId(id), tags),
                    Compare::Exact,
                    format!(", protocol id {id}, then a new connection"),
                )
            }
            Alter::Split { at, gap_us } => {
                let at = 1 + usize::from(*at) % 7;
                let gap_us = u64::from(*gap_us) % (MAX_SPLIT_GAP_US + 1);
                (
                    mutated(p, b, Mutation::Split { at, gap_us }, tags),
                    b.compare.clone(),
                    format!(", split after {at} bytes, {gap_us} µs apart"),
                )
            }
            Alter::Batch { extra } => batch(cx, b, extra, tags),
        }
    }
}

/// The read-write-restore check around an unaltered write: read into slot 0 before, read back and
/// restore after.
fn check_steps(cx: &GenContext, c: &Check, steps: &mut Vec<Step>, tail: &mut Vec<Step>) {
    steps.push(exchange(
        Outgoing::Pdu(c.read.clone()),
        Compare::Structure,
        Some(0),
        "read the value the write will change",
    ));
    // On a drive that can move, a value may change by itself between the write and the read
    // (counters, positions): the read-back is then held to the structure and the range.
    let readback = if cx.can_move {
        Compare::InRange
    } else {
        Compare::Exact
    };
    tail.push(exchange(
        Outgoing::Pdu(c.read.clone()),
        readback,
        None,
        "read back",
    ));
    tail.push(exchange(
        Outgoing::Restore {
            address: c.address,
            slot: 0,
        },
        Compare::Exact,
        None,
        "restore the value read first",
    ));
}

/// Request `b` sent with mutation `m`, its tags those of what the mutation leaves of it.
fn mutated(p: &Profile, b: &Built, m: Mutation, tags: &mut BTreeSet<Tag>) -> Outgoing {
    if let Some(altered) = m.apply_to_pdu(&b.pdu) {
        tags.extend(altered_tags(p, &b.pdu, &altered));
    } else {
        tags.extend(pdu_tags(p, &b.pdu));
    }
    Outgoing::Mutated {
        pdu: b.pdu.clone(),
        mutation: m,
    }
}

/// Bytes appended, as many as the PDU limit leaves room for.
fn extend(p: &Profile, b: &Built, bytes: &[u8], tags: &mut BTreeSet<Tag>) -> Sent {
    let room = MAX_PDU_LEN.saturating_sub(b.pdu.len());
    let mut extra: Vec<u8> = bytes.iter().copied().take(MAX_EXTEND.min(room)).collect();
    if extra.is_empty() && room > 0 {
        extra.push(0);
    }
    let n = extra.len();
    if n == 0 {
        // No room under the PDU limit: the length is off the other way.
        let len = b.pdu.len() - 1;
        (
            mutated(p, b, Mutation::Truncate { len }, tags),
            Compare::Structure,
            ", PDU at its size limit cut by one byte".to_string(),
        )
    } else {
        (
            mutated(p, b, Mutation::Extend(extra), tags),
            Compare::Structure,
            format!(", {n} byte(s) appended to the PDU"),
        )
    }
}

/// The byte count field off by `delta` (never 0); a PDU without one is one byte off in length instead.
fn byte_count(p: &Profile, b: &Built, delta: i8, tags: &mut BTreeSet<Tag>) -> Sent {
    match byte_count_offset(&b.pdu) {
        Some(at) => {
            let d = if delta == 0 { 1 } else { delta };
            let value = b.pdu[at].wrapping_add(d as u8);
            (
                mutated(p, b, Mutation::SetByte { at, value }, tags),
                Compare::Structure,
                format!(", byte count {value} instead of {}", b.pdu[at]),
            )
        }
        None if b.pdu.len() < MAX_PDU_LEN => (
            mutated(p, b, Mutation::Extend(vec![0]), tags),
            Compare::Structure,
            ", one byte more than its length".to_string(),
        ),
        None => (
            mutated(
                p,
                b,
                Mutation::Truncate {
                    len: b.pdu.len() - 1,
                },
                tags,
            ),
            Compare::Structure,
            ", one byte less than its length".to_string(),
        ),
    }
}

/// The function code replaced by another one the profile supports.
fn function_swap(cx: &GenContext, b: &Built, to: u8, tags: &mut BTreeSet<Tag>) -> Sent {
    let others: Vec<u8> = cx
        .functions
        .iter()
        .copied()
        .filter(|f| Some(f) != b.pdu.first())
        .collect();
    let value = pick(&others, to).copied().unwrap_or(0x7F);
    (
        mutated(&cx.profile, b, Mutation::SetByte { at: 0, value }, tags),
        Compare::Structure,
        format!(", function code swapped for 0x{value:02X}"),
    )
}

/// Addressed to another unit: broadcast, the next one, 255, 247 for the first choices, else `unit` itself.
/// Where the line survey found an address no device answers ([`GenContext::on_line`]), every unicast
/// address but 255 (no device's: 248-255 are reserved, serial line spec 2.2) is that one: another device on
/// the line would answer the others.
fn wrong_unit(cx: &GenContext, b: &Built, unit: u8, tags: &mut BTreeSet<Tag>) -> Sent {
    let choices = [0u8, cx.unit.wrapping_add(1), 255, 247];
    let mut u = if unit < 4 {
        choices[usize::from(unit)]
    } else {
        unit
    };
    if u == cx.unit {
        u = u.wrapping_add(1);
    }
    // A double-axis SD2x owns two addresses, ID switch x 2 + 1 (axis A) and + 2 (axis B) (its manual, line
    // 183): the other axis of the run's may answer. The same axis of the next device does not.
    if cx.profile.device.id == "sd2x" && cx.unit != 0 && u == sd2x_partner(cx.unit) {
        u = u.wrapping_add(2);
    }
    if let Some(f) = cx.foreign {
        if u != 0 && u != 255 {
            u = f;
        }
    }
    let t = pdu_tags(&cx.profile, &b.pdu);
    if t.contains(&Tag::Write) {
        // Another drive on the bus (all of them, for a broadcast) may act on it.
        tags.insert(Tag::Destructive);
    }
    tags.extend(t);
    (
        Outgoing::PduToUnit {
            pdu: b.pdu.clone(),
            unit: u,
        },
        b.compare.clone(),
        format!(", to unit {u}"),
    )
}

/// More requests in the same write (the liveness probe when none is given).
fn batch(cx: &GenContext, b: &Built, extra: &[Req], tags: &mut BTreeSet<Tag>) -> Sent {
    let p = &cx.profile;
    tags.insert(Tag::TcpOnly);
    tags.extend(pdu_tags(p, &b.pdu));
    let mut pdus = vec![b.pdu.clone()];
    for r in extra.iter().take(MAX_BATCH_EXTRA) {
        let e = r.build(cx).pdu;
        tags.extend(pdu_tags(p, &e));
        pdus.push(e);
    }
    if pdus.len() == 1 {
        pdus.push(cx.known_good.clone());
    }
    let n = pdus.len();
    (
        Outgoing::Batch(pdus),
        Compare::Structure,
        format!(", with {} more request(s) in the same write", n - 1),
    )
}

impl Spec {
    /// A short name of the case: its first operation's kind, prefixed `seqN-` for N > 1 operations.
    pub fn kind(&self, cx: &GenContext) -> String {
        let ops = self.ops();
        match ops {
            [] => "empty".into(),
            [one] => one.kind(cx),
            [first, ..] => format!("seq{}-{}", ops.len(), first.kind(cx)),
        }
    }

    /// The case, with id `<prefix>/<kind>`.
    pub fn build(&self, cx: &GenContext, prefix: &str) -> Case {
        let mut steps = Vec::new();
        let mut tags = BTreeSet::new();
        let mut notes = Vec::new();
        let mut freedoms = Vec::new();
        for op in self.ops() {
            notes.push(op.build(cx, &mut steps, &mut tags, &mut freedoms));
        }
        let title = match notes.as_slice() {
            [] => "no request".to_string(),
            [one] => one.clone(),
            [first, rest @ ..] => format!("{first} (+{} more)", rest.len()),
        };
        Case {
            id: format!("{prefix}/{}", self.kind(cx)),
            title,
            reference: format!(
                "Modbus Application Protocol Specification V1.1b3, sections 6 and 7; {} map (generated)",
                cx.profile.device.name
            ),
            requirement: "The drive answers each generated request as the reference drive does: the same structure always, the same values where they are deterministic, silence where the reference is silent; and it keeps answering after malformed input.".into(),
            level: Level::Must,
            tags: tags.into_iter().collect(),
            steps,
            requirements: Vec::new(),
            freedoms,
        }
        // Restores and the whole of each request rated again by the classifier.
        .retagged(&cx.profile, cx.unit)
    }
}

/// A case from fuzzer bytes (`arbitrary`): the fuzz targets' way into the generators.
#[cfg(feature = "arbitrary")]
pub fn case_from_bytes(cx: &GenContext, bytes: &[u8]) -> Option<Case> {
    use arbitrary::Arbitrary;
    let mut u = arbitrary::Unstructured::new(bytes);
    let spec = Spec::arbitrary(&mut u).ok()?;
    (!spec.ops.is_empty()).then(|| spec.build(cx, "fuzz"))
}
