//! Property-generated requests for a profile: proptest strategies (and, with the `arbitrary` feature,
//! `arbitrary` inputs for the fuzz targets) describing requests of every function code the profile
//! supports, drawn from its map, at its boundaries, and altered on purpose. [`Spec::build`] turns a
//! description into a [`Case`] that the runner sends and the oracle judges like any catalog case.
//!
//! A [`Spec`] holds no profile data: indices into the profile's lists are taken modulo the lists' lengths
//! when the case is built, so every value (from a strategy, from `arbitrary`, from a shrink) builds a case.
//! Strategies put the simplest choice first (index 0, quantity 1, the first alternative of a union), so
//! proptest's shrinking moves toward the first register, the smallest quantity, the plainest request.
//!
//! Safety: every PDU a built case sends is tagged by what it would do on a drive ([`pdu_tags`]): writes
//! `write`, writes to motion registers, coils, objects or mnemonics `motion`, to destructive ones or to the
//! watchdog `destructive`. A write addressed to another unit is `destructive` (it may reach another drive
//! on the bus), and so is a malformed write whose address is no longer the generated one.

use std::collections::BTreeSet;

use proptest::prelude::*;
use proptest::strategy::{BoxedStrategy, Union};

use crate::cases::catalog::probe_pdu;
use crate::{Case, Compare, Level, Mutation, Send, Step, Tag};
use codec::{CanOpenAccess, MAX_PDU_LEN, Mnemonic, Request};
use drives::profile::{Bit, Object, Profile, Register, Table, VendorMnemonic};

/// At most this many operations in one generated case.
pub const MAX_OPS: usize = 3;
/// At most this many extra requests in one [`Alter::Batch`].
pub const MAX_BATCH_EXTRA: usize = 3;
/// At most this many bytes appended by [`Alter::Extend`].
pub const MAX_EXTEND: usize = 4;
/// Gap between the two pieces of a split request, at most (µs): well inside t1.5 at 19200 baud (859 µs).
pub const MAX_SPLIT_GAP_US: u64 = 100;

/// One generated case: a short sequence of operations.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Spec {
    /// The operations, in order (1 to [`MAX_OPS`] are built; more are ignored).
    pub ops: Vec<Op>,
}

/// One request, how it is altered, and whether a liveness probe follows.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Op {
    /// The request as a conforming client would send it.
    pub req: Req,
    /// What is done to it on purpose.
    pub alter: Alter,
    /// After an altered request: check with a valid read that the drive still answers.
    pub probe: bool,
}

/// An address choice: the first or last mapped address of a table, or the address of one entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Edge {
    First,
    Last,
    Entry(u16),
}

/// A quantity choice: the boundaries of the function's limit, or any value in 1..=limit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Quantity {
    One,
    Max,
    Zero,
    AboveMax,
    Any(u16),
}

/// A value choice for a register or object: its range's boundaries, just outside them, or any value.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Value {
    Min,
    Max,
    BelowMin,
    AboveMax,
    /// A value within the range (taken modulo its size).
    InRange(u32),
    /// Any value the register's width can carry.
    Raw(u32),
}

/// A request drawn from the profile. Indices pick entries of the profile's lists (modulo their length).
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Req {
    /// FC 03/04: one register (or pair) at its width.
    ReadRegister { reg: u16, input: bool },
    /// FC 03/04: one half of a 32-bit register.
    ReadHalf { reg: u16, second: bool },
    /// FC 03/04: a block from a boundary address with a boundary quantity.
    ReadSpan {
        at: Edge,
        quantity: Quantity,
        input: bool,
    },
    /// FC 16 (or FC 06): one register (or pair) at its width; `check` reads first, reads back and restores.
    WriteRegister {
        reg: u16,
        value: Value,
        fc06: bool,
        check: bool,
    },
    /// FC 06 or FC 16: one half of a 32-bit register.
    WriteHalf {
        reg: u16,
        second: bool,
        word: u16,
        fc06: bool,
    },
    /// FC 16: a block of registers, every one set to `word`.
    WriteSpan {
        at: Edge,
        quantity: Quantity,
        word: u16,
    },
    /// FC 01 (coils) or FC 02 (discrete inputs).
    ReadBits {
        discrete: bool,
        at: Edge,
        quantity: Quantity,
    },
    /// FC 05: one coil ON or OFF; `check` reads first, reads back and restores.
    WriteCoil { coil: u16, on: bool, check: bool },
    /// FC 15: a block of coils.
    WriteCoils {
        at: Edge,
        quantity: Quantity,
        bits: u32,
    },
    /// FC 23: read a block, write one register at its width.
    ReadWrite {
        at: Edge,
        quantity: Quantity,
        reg: u16,
        value: Value,
    },
    /// FC 08: a sub-function of the profile (or one it does not list).
    Diagnostic { sub: u16, data: u16 },
    /// FC 43/14: read device identification.
    DeviceId { code: u8, object: u8 },
    /// FC 43/13: read an object, with its size or another byte count.
    ObjectRead { obj: u16, count: Option<u8> },
    /// FC 43/13: write an object.
    ObjectWrite { obj: u16, value: Value },
    /// FC 65: read a vendor mnemonic (the last index: one the drive does not know).
    VendorRead { mnemonic: u16 },
    /// FC 66: write a vendor mnemonic with its manual example.
    VendorWrite { mnemonic: u16 },
    /// A function code the profile does not support, with a few data bytes.
    Unsupported { fc: u16, len: u8 },
}

/// What is done on purpose to a request.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Alter {
    /// Sent as is.
    None,
    /// One bit of the PDU inverted.
    BitFlip { bit: u16 },
    /// The PDU cut short.
    Truncate { keep: u8 },
    /// Bytes appended to the PDU.
    Extend { bytes: Vec<u8> },
    /// The byte count field off by `delta` (one byte too many where the PDU has none).
    ByteCount { delta: i8 },
    /// The function code replaced by another one the profile supports.
    FunctionSwap { to: u8 },
    /// Addressed to another unit id / slave address (0 = broadcast).
    WrongUnit { unit: u8 },
    /// RTU: the CRC inverted.
    BadCrc,
    /// Modbus/TCP: the MBAP length field off by `delta`; the connection is reopened after.
    MbapLength { delta: i8 },
    /// Modbus/TCP: a non-zero protocol id; the connection is reopened after.
    ProtocolId { id: u16 },
    /// The frame in two writes, split after `at` bytes, `gap_us` apart.
    Split { at: u8, gap_us: u16 },
    /// Modbus/TCP: more requests in the same write.
    Batch { extra: Vec<Req> },
}

/// The profile data the generators draw from, for one run (profile and unit id).
#[derive(Clone, Debug)]
pub struct GenContext {
    profile: Profile,
    unit: u8,
    regs: Vec<Register>,
    wide: Vec<Register>,
    holding: Vec<u16>,
    input: Vec<u16>,
    coils: Vec<Bit>,
    discretes: Vec<Bit>,
    read_mnemonics: Vec<VendorMnemonic>,
    write_mnemonics: Vec<VendorMnemonic>,
    objects: Vec<Object>,
    diagnostics: Vec<u16>,
    id_objects: Vec<u8>,
    functions: Vec<u8>,
    unsupported: Vec<u8>,
    probe: Vec<u8>,
    /// The profile has motion registers, coils or mnemonics: values may change by themselves.
    can_move: bool,
}

fn pick<T>(list: &[T], i: impl Into<usize>) -> Option<&T> {
    if list.is_empty() {
        None
    } else {
        list.get(i.into() % list.len())
    }
}

impl GenContext {
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
            probe: probe_pdu(profile),
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

    fn supports(&self, fc: u8) -> bool {
        self.functions.contains(&fc)
    }

    fn max_quantity(&self, fc: u8) -> u16 {
        self.profile
            .function(fc)
            .and_then(|f| f.max_quantity)
            .unwrap_or(match fc {
                0x01 | 0x02 => 2000,
                0x0F => 0x7B0,
                0x10 => 123,
                _ => 125,
            })
    }

    /// The read function for a table choice: FC 04 for input registers where supported, else FC 03.
    fn read_fc(&self, table: Table, input: bool) -> u8 {
        let (r3, r4) = (self.supports(0x03), self.supports(0x04));
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

fn encode_register(p: &Profile, r: &Register, v: i64) -> Vec<u16> {
    if r.width == 2 {
        p.device.word_order.split(v as u32).to_vec()
    } else {
        vec![v as u16]
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

/// A request built from a [`Req`]: the PDU, how it is judged, and the steps of a read-write-restore check.
struct Built {
    pdu: Vec<u8>,
    compare: Compare,
    kind: &'static str,
    note: String,
    check: Option<Check>,
}

/// Read first into slot 0, read back after the write, restore from slot 0.
struct Check {
    read: Vec<u8>,
    address: u16,
}

impl Req {
    fn build(&self, cx: &GenContext) -> Built {
        let p = &cx.profile;
        let plain = |pdu: Vec<u8>, compare, kind, note: String| Built {
            pdu,
            compare,
            kind,
            note,
            check: None,
        };
        let read_req = |fc: u8, address: u16, quantity: u16| {
            if fc == 0x04 {
                Request::ReadInputRegisters { address, quantity }
            } else {
                Request::ReadHoldingRegisters { address, quantity }
            }
        };
        match *self {
            Req::ReadRegister { reg, input } => {
                let Some(r) = pick(&cx.regs, reg) else {
                    return Req::ReadSpan {
                        at: Edge::First,
                        quantity: Quantity::One,
                        input,
                    }
                    .build(cx);
                };
                let fc = cx.read_fc(r.table, input);
                plain(
                    to_pdu(&read_req(fc, r.address, u16::from(r.width))),
                    Compare::InRange,
                    "read-reg",
                    format!(
                        "FC {fc:02X} read of {} at its width ({})",
                        reg_name(r),
                        r.width
                    ),
                )
            }
            Req::ReadHalf { reg, second } => {
                let Some(r) = pick(&cx.wide, reg) else {
                    return Req::ReadRegister { reg, input: second }.build(cx);
                };
                let fc = cx.read_fc(r.table, false);
                let a = r.address.wrapping_add(u16::from(second));
                plain(
                    to_pdu(&read_req(fc, a, 1)),
                    Compare::InRange,
                    "read-half",
                    format!(
                        "FC {fc:02X} read of the {} half of 32-bit {}",
                        if second { "second" } else { "first" },
                        reg_name(r)
                    ),
                )
            }
            Req::ReadSpan {
                at,
                quantity,
                input,
            } => {
                let fc = cx.read_fc(Table::Both, input);
                let list = if fc == 0x04 { &cx.input } else { &cx.holding };
                let address = cx.edge(list, at);
                let q = cx.quantity(quantity, cx.max_quantity(fc));
                plain(
                    to_pdu(&read_req(fc, address, q)),
                    Compare::InRange,
                    "read-span",
                    format!(
                        "FC {fc:02X} read of {q} register(s) from 0x{address:04X} ({at:?}, {quantity:?})"
                    ),
                )
            }
            Req::WriteRegister {
                reg,
                value,
                fc06,
                check,
            } => {
                let Some(r) = pick(&cx.regs, reg) else {
                    return Req::WriteSpan {
                        at: Edge::First,
                        quantity: Quantity::One,
                        word: 0,
                    }
                    .build(cx);
                };
                let v = value_in(value, r.range(), r.natural_range());
                let values = encode_register(p, r, v);
                let single =
                    values.len() == 1 && ((fc06 && cx.supports(0x06)) || !cx.supports(0x10));
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
                    && (cx.supports(0x03) || cx.supports(0x04));
                Built {
                    pdu: to_pdu(&req),
                    compare: Compare::Exact,
                    kind: "write-reg",
                    note: format!(
                        "FC {:02X} write of {} = {v}{}",
                        req.function().0,
                        reg_name(r),
                        value_label(value)
                    ),
                    check: checked.then(|| Check {
                        read: to_pdu(&read_req(
                            cx.read_fc(r.table, false),
                            r.address,
                            u16::from(r.width),
                        )),
                        address: r.address,
                    }),
                }
            }
            Req::WriteHalf {
                reg,
                second,
                word,
                fc06,
            } => {
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
                let req = if (fc06 && cx.supports(0x06)) || !cx.supports(0x10) {
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
                plain(
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
            Req::WriteSpan { at, quantity, word } => {
                let address = cx.edge(&cx.holding, at);
                let q = cx.quantity(quantity, cx.max_quantity(0x10));
                plain(
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
            Req::ReadBits {
                discrete,
                at,
                quantity,
            } => {
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
                plain(
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
            Req::WriteCoil { coil, on, check } => {
                let c = pick(&cx.coils, coil);
                let address = c.map_or(0, |c| c.address);
                let value = if on { 0xFF00 } else { 0x0000 };
                Built {
                    pdu: to_pdu(&Request::WriteSingleCoil { address, value }),
                    compare: Compare::Exact,
                    kind: "write-coil",
                    note: format!(
                        "FC 05 coil {address}{} {}",
                        c.map_or(String::new(), |c| format!(" {}", c.name)),
                        if on { "ON" } else { "OFF" }
                    ),
                    check: (check && c.is_some_and(|c| !c.motion) && cx.supports(0x01)).then(
                        || Check {
                            read: to_pdu(&Request::ReadCoils {
                                address,
                                quantity: 1,
                            }),
                            address,
                        },
                    ),
                }
            }
            Req::WriteCoils { at, quantity, bits } => {
                let address = cx.edge(&cx.coil_addresses(false), at);
                let q = cx.quantity(quantity, cx.max_quantity(0x0F));
                let data = (0..usize::from(q).div_ceil(8))
                    .map(|i| (bits >> (8 * (i % 4))) as u8)
                    .collect();
                plain(
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
            Req::ReadWrite {
                at,
                quantity,
                reg,
                value,
            } => {
                let read_address = cx.edge(&cx.holding, at);
                let read_quantity = cx.quantity(quantity, cx.max_quantity(0x17));
                let (write_address, values, label) = match pick(&cx.regs, reg) {
                    Some(r) => {
                        let v = value_in(value, r.range(), r.natural_range());
                        (
                            r.address,
                            encode_register(p, r, v),
                            format!("{} = {v}{}", reg_name(r), value_label(value)),
                        )
                    }
                    None => (0, vec![0], "0x0000 = 0".to_string()),
                };
                plain(
                    to_pdu(&Request::ReadWriteMultipleRegisters {
                        read_address,
                        read_quantity,
                        write_address,
                        values,
                    }),
                    Compare::Structure,
                    "read-write",
                    format!(
                        "FC 17 read of {read_quantity} from 0x{read_address:04X}, write {label}"
                    ),
                )
            }
            Req::Diagnostic { sub, data } => {
                let n = cx.diagnostics.len() + 1;
                // The last choice is a sub-function the profile does not list.
                let sub_function = cx
                    .diagnostics
                    .get(usize::from(sub) % n)
                    .copied()
                    .unwrap_or(0x0012);
                let data = if sub_function == 0 { data } else { 0 };
                plain(
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
            Req::DeviceId { code, object } => {
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
                plain(
                    to_pdu(&Request::ReadDeviceId {
                        read_code,
                        object_id,
                    }),
                    Compare::Structure,
                    "device-id",
                    format!("FC 2B/0E read code {read_code} object 0x{object_id:02X}"),
                )
            }
            Req::ObjectRead { obj, count } => {
                let (index, sub, size, name) = pick(&cx.objects, obj)
                    .map_or((0x7FFF, 0, 2, "(none)".to_string()), |o| {
                        (o.index, o.subindex, o.ty.size() as u16, o.name.clone())
                    });
                let byte_count = count.map_or(size, |c| u16::from(c % 6));
                plain(
                    to_pdu(&Request::CanOpen(CanOpenAccess::read(
                        cx.unit, index, sub, byte_count,
                    ))),
                    Compare::Structure,
                    "object-read",
                    format!("FC 2B/0D read of object {index}.{sub} {name}, {byte_count} byte(s)"),
                )
            }
            Req::ObjectWrite { obj, value } => {
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
                plain(
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
            Req::VendorRead { mnemonic } => {
                let n = cx.read_mnemonics.len() + 1;
                let name = cx
                    .read_mnemonics
                    .get(usize::from(mnemonic) % n)
                    .map_or("QQ", |m| m.name.as_str());
                let m = Mnemonic::from_name(name).unwrap_or(Mnemonic(*b"  QQ"));
                plain(
                    to_pdu(&Request::VendorRead { mnemonic: m }),
                    Compare::Structure,
                    "vendor-read",
                    format!("FC 41 read of mnemonic {name}"),
                )
            }
            Req::VendorWrite { mnemonic } => {
                let Some(m) = pick(&cx.write_mnemonics, mnemonic) else {
                    return Req::VendorRead { mnemonic }.build(cx);
                };
                let params = m.example.clone().unwrap_or_default();
                plain(
                    to_pdu(&Request::VendorWrite {
                        mnemonic: Mnemonic::from_name(&m.name).unwrap_or(Mnemonic(*b"  QQ")),
                        params: params.as_bytes().to_vec(),
                    }),
                    Compare::Exact,
                    "vendor-write",
                    format!("FC 42 write of {}{params}", m.name),
                )
            }
            Req::Unsupported { fc, len } => {
                let code = pick(&cx.unsupported, fc).copied().unwrap_or(0x7F);
                let mut pdu = vec![code];
                pdu.resize(1 + usize::from(len % 5), 0);
                plain(
                    pdu,
                    Compare::Exact,
                    "unsupported-fc",
                    format!(
                        "FC {code:02X}, which the profile does not support, with {} data byte(s)",
                        len % 5
                    ),
                )
            }
        }
    }
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

fn is_write_fc(fc: u8) -> bool {
    matches!(fc, 0x05 | 0x06 | 0x0F | 0x10 | 0x15 | 0x16 | 0x17 | 0x42)
}

/// Safety tags of a request PDU, from what it would do on a drive of profile `p`.
pub fn pdu_tags(p: &Profile, pdu: &[u8]) -> BTreeSet<Tag> {
    let mut tags = BTreeSet::new();
    let regs = |tags: &mut BTreeSet<Tag>, address: u16, n: usize| {
        tags.insert(Tag::Write);
        for i in 0..n.min(0x1_0000) {
            let a = address.wrapping_add(i as u16);
            if let Some(r) = p.register_at(a, false) {
                if r.motion {
                    tags.insert(Tag::Motion);
                }
                if r.destructive {
                    tags.insert(Tag::Destructive);
                }
            }
            // A watchdog left armed faults the drive when it runs out.
            if p.watchdog.as_ref().is_some_and(|w| w.register == a) {
                tags.insert(Tag::Destructive);
            }
        }
    };
    let coils = |tags: &mut BTreeSet<Tag>, address: u16, n: u16| {
        tags.insert(Tag::Write);
        let end = u32::from(address) + u32::from(n);
        if p.coils.iter().map(|c| c.get_ref()).any(|c| {
            c.motion && u32::from(c.address) >= u32::from(address) && u32::from(c.address) < end
        }) {
            tags.insert(Tag::Motion);
        }
    };
    match Request::decode(pdu) {
        Ok(Request::WriteSingleCoil { address, .. }) => coils(&mut tags, address, 1),
        Ok(Request::WriteMultipleCoils {
            address, quantity, ..
        }) => coils(&mut tags, address, quantity),
        Ok(Request::WriteSingleRegister { address, .. }) => regs(&mut tags, address, 1),
        Ok(Request::WriteMultipleRegisters { address, values }) => {
            regs(&mut tags, address, values.len())
        }
        Ok(Request::ReadWriteMultipleRegisters {
            write_address,
            values,
            ..
        }) => regs(&mut tags, write_address, values.len()),
        Ok(Request::CanOpen(a)) if a.is_write() => {
            tags.insert(Tag::Write);
            match p.object(a.index, a.subindex) {
                Some(o) => {
                    if o.motion {
                        tags.insert(Tag::Motion);
                    }
                    if let Some(r) = o.register {
                        regs(&mut tags, r, 1);
                    }
                }
                None => {
                    tags.insert(Tag::Motion);
                    tags.insert(Tag::Destructive);
                }
            }
        }
        Ok(Request::VendorWrite { mnemonic, .. }) => {
            tags.insert(Tag::Write);
            match p.mnemonic(&mnemonic.name()) {
                Some(m) => {
                    if m.motion {
                        tags.insert(Tag::Motion);
                    }
                    if m.destructive {
                        tags.insert(Tag::Destructive);
                    }
                }
                // A mnemonic the profile does not know may do anything.
                None => {
                    tags.insert(Tag::Motion);
                    tags.insert(Tag::Destructive);
                }
            }
        }
        // Restart communications and listen-only mode take the drive off the bus.
        Ok(Request::Diagnostics {
            sub_function: 0x01 | 0x04,
            ..
        }) => {
            tags.insert(Tag::Destructive);
        }
        Ok(Request::Raw { function, .. }) if is_write_fc(function.0) => {
            tags.extend([Tag::Write, Tag::Motion, Tag::Destructive]);
        }
        Ok(_) => {}
        // Malformed: a lenient drive might still act on it; what it would write is unknown.
        Err(_) => {
            let write = match pdu {
                [fc, ..] if is_write_fc(*fc) => true,
                [0x2B, 0x0D, control, ..] => control & CanOpenAccess::WRITE != 0,
                _ => false,
            };
            if write {
                tags.extend([Tag::Write, Tag::Motion, Tag::Destructive]);
            }
        }
    }
    tags
}

/// The tags of an altered PDU: what the alteration left intact keeps the original's tags; a malformed
/// write whose function code and address are unchanged is tagged like the original, not as unknown.
fn altered_tags(p: &Profile, original: &[u8], altered: &[u8]) -> BTreeSet<Tag> {
    let mut tags = pdu_tags(p, original);
    let keeps_address = altered.len() >= 3 && original.len() >= 3 && altered[..3] == original[..3];
    if Request::decode(altered).is_err() && keeps_address && is_write_fc(altered[0]) {
        tags.insert(Tag::Write);
    } else {
        tags.extend(pdu_tags(p, altered));
    }
    tags
}

fn exchange(send: Send, compare: Compare, capture: Option<usize>, note: impl Into<String>) -> Step {
    Step::Exchange {
        send,
        compare,
        capture,
        note: note.into(),
    }
}

impl Alter {
    fn label(&self) -> &'static str {
        match self {
            Alter::None => "",
            Alter::BitFlip { .. } => "-bitflip",
            Alter::Truncate { .. } => "-truncated",
            Alter::Extend { .. } => "-extended",
            Alter::ByteCount { .. } => "-bytecount",
            Alter::FunctionSwap { .. } => "-fcswap",
            Alter::WrongUnit { .. } => "-unit",
            Alter::BadCrc => "-badcrc",
            Alter::MbapLength { .. } => "-mbaplen",
            Alter::ProtocolId { .. } => "-protoid",
            Alter::Split { .. } => "-split",
            Alter::Batch { .. } => "-batch",
        }
    }
}

impl Op {
    /// A short name: the request's kind and the alteration (`write-reg`, `read-reg-bitflip`).
    pub fn kind(&self, cx: &GenContext) -> String {
        format!("{}{}", self.req.build(cx).kind, self.alter.label())
    }

    fn build(&self, cx: &GenContext, steps: &mut Vec<Step>, tags: &mut BTreeSet<Tag>) -> String {
        let p = &cx.profile;
        let b = self.req.build(cx);
        let mut tail = Vec::new();
        let mutated = |m: Mutation, tags: &mut BTreeSet<Tag>| {
            if let Some(altered) = m.apply_to_pdu(&b.pdu) {
                tags.extend(altered_tags(p, &b.pdu, &altered));
            } else {
                tags.extend(pdu_tags(p, &b.pdu));
            }
            Send::Mutated {
                pdu: b.pdu.clone(),
                mutation: m,
            }
        };
        let (send, compare, what) = match &self.alter {
            Alter::None => {
                tags.extend(pdu_tags(p, &b.pdu));
                if let Some(c) = &b.check {
                    steps.push(exchange(
                        Send::Pdu(c.read.clone()),
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
                        Send::Pdu(c.read.clone()),
                        readback,
                        None,
                        "read back",
                    ));
                    tail.push(exchange(
                        Send::Restore {
                            address: c.address,
                            slot: 0,
                        },
                        Compare::Exact,
                        None,
                        "restore the value read first",
                    ));
                }
                (Send::Pdu(b.pdu.clone()), b.compare.clone(), String::new())
            }
            Alter::BitFlip { bit } => {
                let bit = usize::from(*bit) % (b.pdu.len() * 8).max(1);
                (
                    mutated(Mutation::BitFlip { bit }, tags),
                    Compare::Structure,
                    format!(", bit {bit} of the PDU inverted"),
                )
            }
            Alter::Truncate { keep } => {
                let len = usize::from(*keep) % b.pdu.len().max(1);
                (
                    mutated(Mutation::Truncate { len }, tags),
                    Compare::Structure,
                    format!(", PDU cut to {len} byte(s)"),
                )
            }
            Alter::Extend { bytes } => {
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
                        mutated(Mutation::Truncate { len }, tags),
                        Compare::Structure,
                        ", PDU at its size limit cut by one byte".to_string(),
                    )
                } else {
                    (
                        mutated(Mutation::Extend(extra), tags),
                        Compare::Structure,
                        format!(", {n} byte(s) appended to the PDU"),
                    )
                }
            }
            Alter::ByteCount { delta } => match byte_count_offset(&b.pdu) {
                Some(at) => {
                    let d = if *delta == 0 { 1 } else { *delta };
                    let value = b.pdu[at].wrapping_add(d as u8);
                    (
                        mutated(Mutation::SetByte { at, value }, tags),
                        Compare::Structure,
                        format!(", byte count {value} instead of {}", b.pdu[at]),
                    )
                }
                None if b.pdu.len() < MAX_PDU_LEN => (
                    mutated(Mutation::Extend(vec![0]), tags),
                    Compare::Structure,
                    ", one byte more than its length".to_string(),
                ),
                None => (
                    mutated(
                        Mutation::Truncate {
                            len: b.pdu.len() - 1,
                        },
                        tags,
                    ),
                    Compare::Structure,
                    ", one byte less than its length".to_string(),
                ),
            },
            Alter::FunctionSwap { to } => {
                let others: Vec<u8> = cx
                    .functions
                    .iter()
                    .copied()
                    .filter(|f| Some(f) != b.pdu.first())
                    .collect();
                let value = pick(&others, *to).copied().unwrap_or(0x7F);
                (
                    mutated(Mutation::SetByte { at: 0, value }, tags),
                    Compare::Structure,
                    format!(", function code swapped for 0x{value:02X}"),
                )
            }
            Alter::WrongUnit { unit } => {
                let choices = [0u8, cx.unit.wrapping_add(1), 255, 247];
                let mut u = if *unit < 4 {
                    choices[usize::from(*unit)]
                } else {
                    *unit
                };
                if u == cx.unit {
                    u = u.wrapping_add(1);
                }
                let t = pdu_tags(p, &b.pdu);
                if t.contains(&Tag::Write) {
                    // Another drive on the bus (all of them, for a broadcast) may act on it.
                    tags.insert(Tag::Destructive);
                }
                tags.extend(t);
                (
                    Send::PduToUnit {
                        pdu: b.pdu.clone(),
                        unit: u,
                    },
                    b.compare.clone(),
                    format!(", to unit {u}"),
                )
            }
            Alter::BadCrc => {
                tags.insert(Tag::RtuOnly);
                (
                    mutated(Mutation::BadCrc, tags),
                    Compare::Exact,
                    ", CRC inverted".to_string(),
                )
            }
            Alter::MbapLength { delta } => {
                tags.insert(Tag::TcpOnly);
                let d = if *delta == 0 { 1 } else { i16::from(*delta) };
                tail.push(Step::Reconnect);
                (
                    mutated(Mutation::LengthDelta(d), tags),
                    Compare::Structure,
                    format!(", MBAP length {d:+}, then a new connection"),
                )
            }
            Alter::ProtocolId { id } => {
                tags.insert(Tag::TcpOnly);
                let id = if *id == 0 { 1 } else { *id };
                tail.push(Step::Reconnect);
                (
                    mutated(Mutation::ProtocolId(id), tags),
                    Compare::Exact,
                    format!(", protocol id {id}, then a new connection"),
                )
            }
            Alter::Split { at, gap_us } => {
                let at = 1 + usize::from(*at) % 7;
                let gap_us = u64::from(*gap_us) % (MAX_SPLIT_GAP_US + 1);
                (
                    mutated(Mutation::Split { at, gap_us }, tags),
                    b.compare.clone(),
                    format!(", split after {at} bytes, {gap_us} µs apart"),
                )
            }
            Alter::Batch { extra } => {
                tags.insert(Tag::TcpOnly);
                tags.extend(pdu_tags(p, &b.pdu));
                let mut pdus = vec![b.pdu.clone()];
                for r in extra.iter().take(MAX_BATCH_EXTRA) {
                    let e = r.build(cx).pdu;
                    tags.extend(pdu_tags(p, &e));
                    pdus.push(e);
                }
                if pdus.len() == 1 {
                    pdus.push(cx.probe.clone());
                }
                let n = pdus.len();
                (
                    Send::Batch(pdus),
                    Compare::Structure,
                    format!(", with {} more request(s) in the same write", n - 1),
                )
            }
        };
        let note = format!("{}{what}", b.note);
        steps.push(exchange(send, compare, None, note.clone()));
        steps.extend(tail);
        if self.probe && self.alter != Alter::None {
            steps.push(exchange(
                Send::Pdu(cx.probe.clone()),
                Compare::Structure,
                None,
                "liveness: a valid read is still answered",
            ));
        }
        note
    }
}

impl Spec {
    /// The operations that are built (at most [`MAX_OPS`]).
    pub fn ops(&self) -> &[Op] {
        &self.ops[..self.ops.len().min(MAX_OPS)]
    }

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
        for op in self.ops() {
            notes.push(op.build(cx, &mut steps, &mut tags));
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
        }
    }
}

// ---- strategies ----

fn edge(n: usize) -> BoxedStrategy<Edge> {
    let n = n.clamp(1, usize::from(u16::MAX)) as u16;
    prop_oneof![
        Just(Edge::First),
        Just(Edge::Last),
        (0..n).prop_map(Edge::Entry)
    ]
    .boxed()
}

fn quantity() -> BoxedStrategy<Quantity> {
    prop_oneof![
        2 => Just(Quantity::One),
        2 => Just(Quantity::Max),
        1 => Just(Quantity::Zero),
        1 => Just(Quantity::AboveMax),
        3 => any::<u16>().prop_map(Quantity::Any),
    ]
    .boxed()
}

fn value() -> BoxedStrategy<Value> {
    prop_oneof![
        1 => Just(Value::Min),
        1 => Just(Value::Max),
        1 => Just(Value::BelowMin),
        1 => Just(Value::AboveMax),
        4 => any::<u32>().prop_map(Value::InRange),
        1 => any::<u32>().prop_map(Value::Raw),
    ]
    .boxed()
}

fn index(n: usize) -> BoxedStrategy<u16> {
    (0..n.clamp(1, usize::from(u16::MAX)) as u16).boxed()
}

impl GenContext {
    /// Requests of every function code the profile supports, weighted toward the map's registers.
    pub fn req_strategy(&self) -> BoxedStrategy<Req> {
        let mut arms: Vec<(u32, BoxedStrategy<Req>)> = Vec::new();
        let reads = self.supports(0x03) || self.supports(0x04);
        let (nr, nw) = (self.regs.len(), self.wide.len());
        if reads && nr > 0 {
            arms.push((
                4,
                (index(nr), any::<bool>())
                    .prop_map(|(reg, input)| Req::ReadRegister { reg, input })
                    .boxed(),
            ));
            arms.push((
                2,
                (
                    edge(self.holding.len().max(self.input.len())),
                    quantity(),
                    any::<bool>(),
                )
                    .prop_map(|(at, quantity, input)| Req::ReadSpan {
                        at,
                        quantity,
                        input,
                    })
                    .boxed(),
            ));
            if nw > 0 {
                arms.push((
                    1,
                    (index(nw), any::<bool>())
                        .prop_map(|(reg, second)| Req::ReadHalf { reg, second })
                        .boxed(),
                ));
            }
        }
        if (self.supports(0x06) || self.supports(0x10)) && nr > 0 {
            arms.push((
                4,
                (index(nr), value(), any::<bool>(), any::<bool>())
                    .prop_map(|(reg, value, fc06, check)| Req::WriteRegister {
                        reg,
                        value,
                        fc06,
                        check,
                    })
                    .boxed(),
            ));
            if nw > 0 {
                arms.push((
                    1,
                    (index(nw), any::<bool>(), any::<u16>(), any::<bool>())
                        .prop_map(|(reg, second, word, fc06)| Req::WriteHalf {
                            reg,
                            second,
                            word,
                            fc06,
                        })
                        .boxed(),
                ));
            }
        }
        if self.supports(0x10) && nr > 0 {
            arms.push((
                1,
                (edge(self.holding.len()), quantity(), any::<u16>())
                    .prop_map(|(at, quantity, word)| Req::WriteSpan { at, quantity, word })
                    .boxed(),
            ));
        }
        for (fc, discrete, n) in [
            (0x01, false, self.coils.len()),
            (0x02, true, self.discretes.len()),
        ] {
            if self.supports(fc) {
                arms.push((
                    1,
                    (edge(n), quantity())
                        .prop_map(move |(at, quantity)| Req::ReadBits {
                            discrete,
                            at,
                            quantity,
                        })
                        .boxed(),
                ));
            }
        }
        if self.supports(0x05) {
            arms.push((
                1,
                (index(self.coils.len()), any::<bool>(), any::<bool>())
                    .prop_map(|(coil, on, check)| Req::WriteCoil { coil, on, check })
                    .boxed(),
            ));
        }
        if self.supports(0x0F) {
            arms.push((
                1,
                (edge(self.coils.len()), quantity(), any::<u32>())
                    .prop_map(|(at, quantity, bits)| Req::WriteCoils { at, quantity, bits })
                    .boxed(),
            ));
        }
        if self.supports(0x17) && nr > 0 {
            arms.push((
                1,
                (edge(self.holding.len()), quantity(), index(nr), value())
                    .prop_map(|(at, quantity, reg, value)| Req::ReadWrite {
                        at,
                        quantity,
                        reg,
                        value,
                    })
                    .boxed(),
            ));
        }
        if self.supports(0x08) {
            arms.push((
                1,
                (index(self.diagnostics.len() + 1), any::<u16>())
                    .prop_map(|(sub, data)| Req::Diagnostic { sub, data })
                    .boxed(),
            ));
        }
        if self.supports(0x2B) && !self.id_objects.is_empty() {
            arms.push((
                1,
                (0u8..6, any::<u8>())
                    .prop_map(|(code, object)| Req::DeviceId { code, object })
                    .boxed(),
            ));
        }
        if self.supports(0x2B) && !self.objects.is_empty() {
            let n = self.objects.len();
            arms.push((
                2,
                (index(n), proptest::option::weighted(0.25, 0u8..6))
                    .prop_map(|(obj, count)| Req::ObjectRead { obj, count })
                    .boxed(),
            ));
            arms.push((
                1,
                (index(n), value())
                    .prop_map(|(obj, value)| Req::ObjectWrite { obj, value })
                    .boxed(),
            ));
        }
        if self.supports(0x41) {
            arms.push((
                1,
                index(self.read_mnemonics.len() + 1)
                    .prop_map(|mnemonic| Req::VendorRead { mnemonic })
                    .boxed(),
            ));
        }
        if self.supports(0x42) && !self.write_mnemonics.is_empty() {
            arms.push((
                1,
                index(self.write_mnemonics.len())
                    .prop_map(|mnemonic| Req::VendorWrite { mnemonic })
                    .boxed(),
            ));
        }
        if !self.unsupported.is_empty() {
            arms.push((
                1,
                (index(self.unsupported.len()), 0u8..5)
                    .prop_map(|(fc, len)| Req::Unsupported { fc, len })
                    .boxed(),
            ));
        }
        if arms.is_empty() {
            return Just(Req::Unsupported { fc: 0, len: 0 }).boxed();
        }
        Union::new_weighted(arms).boxed()
    }

    /// Alterations: PDU-level ones on every transport, frame-level ones tagged for their transport.
    pub fn alter_strategy(&self) -> BoxedStrategy<Alter> {
        let extra = proptest::collection::vec(self.req_strategy(), 1..=MAX_BATCH_EXTRA);
        prop_oneof![
            3 => any::<u16>().prop_map(|bit| Alter::BitFlip { bit }),
            2 => any::<u8>().prop_map(|keep| Alter::Truncate { keep }),
            2 => proptest::collection::vec(any::<u8>(), 1..=MAX_EXTEND)
                .prop_map(|bytes| Alter::Extend { bytes }),
            2 => prop_oneof![Just(1i8), Just(-1i8), any::<i8>()]
                .prop_map(|delta| Alter::ByteCount { delta }),
            1 => any::<u8>().prop_map(|to| Alter::FunctionSwap { to }),
            2 => any::<u8>().prop_map(|unit| Alter::WrongUnit { unit }),
            1 => Just(Alter::BadCrc),
            1 => prop_oneof![Just(1i8), Just(-1i8), any::<i8>()]
                .prop_map(|delta| Alter::MbapLength { delta }),
            1 => any::<u16>().prop_map(|id| Alter::ProtocolId { id }),
            1 => (any::<u8>(), any::<u16>()).prop_map(|(at, gap_us)| Alter::Split { at, gap_us }),
            1 => extra.prop_map(|extra| Alter::Batch { extra }),
        ]
        .boxed()
    }

    /// One operation: a request, sent as is 3 times in 5, altered otherwise.
    pub fn op_strategy(&self) -> BoxedStrategy<Op> {
        let alter = prop_oneof![3 => Just(Alter::None), 2 => self.alter_strategy()];
        (self.req_strategy(), alter, any::<bool>())
            .prop_map(|(req, alter, probe)| Op { req, alter, probe })
            .boxed()
    }

    /// Generated cases: one operation 4 times in 5, else up to [`MAX_OPS`].
    pub fn spec_strategy(&self) -> BoxedStrategy<Spec> {
        let op = self.op_strategy();
        prop_oneof![
            4 => op.clone().prop_map(|o| vec![o]),
            1 => proptest::collection::vec(op, 1..=MAX_OPS),
        ]
        .prop_map(|ops| Spec { ops })
        .boxed()
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
