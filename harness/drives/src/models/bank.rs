//! The data model of a simulated drive, built from its profile: every holding/input register at its width,
//! every coil and discrete input, with the Modbus address, access and range rules applied on each access.
//!
//! Models (`generic`, `mdrive`) answer the plain data-model function codes through this bank and add their own
//! behaviour around it (motion, cross-register limits, I/O mirroring).
//!
//! Choices where the manuals are silent (line numbers of the MDrive manual 000_b25109cd5b573b4c.txt; the LMD
//! manual 001_aafa6838846abfce.txt has the same text):
//!
//! - **A read may start or end inside a 32-bit register** and returns the halves it covers, in the word order.
//!   The manual only says values are "1, 2 or 4 bytes" so "you will not need to read more than two consecutive
//!   registers" (line 616), which is advice, not a rule; and its own FC 03 example reads 0x008A-0x008B (line 644),
//!   a range that in the register map (lines 1123-1124) straddles VI's low word and VM's high word, so the manual's
//!   authors expected such a read to be answered. Every address of the range must still belong to a readable
//!   register: reserved and unmapped addresses give exception 02 (lines 618, 662), as do write-only registers.
//! - **A write must cover whole registers**: a range that starts or ends inside a 32-bit register gives
//!   exception 02. A half-written value would be neither the old nor the new value, and the Modbus application
//!   protocol spec defines 02 for exactly this case: "the combination of reference number and transfer length is
//!   invalid" (MODBUS Application Protocol v1.1b3, section 7, code 02).
//! - **A write to a read-only register gives exception 02**, like a reserved register (lines 618, 662): the
//!   address is not a writable address, whatever the value. Exception 03 would blame the value, which is not
//!   what is wrong. The manual has no access column at all (see the profile's device note).
//! - **Out-of-range values give exception 03** (illegal data value, line 429). All address/access checks of a
//!   request run before any value check, and a request is applied all or nothing.
//! - Registers without a default start at 0, or at their minimum when 0 is outside their range.

use std::collections::BTreeMap;
use std::sync::Arc;

pub use super::data_model::{BitTable, RegTable};
use super::data_model::{DataModel, range_end};
use crate::choices::{Choices, Decision, Freedoms, Rejection, ids};
use crate::faults::{Fault, FaultSet};
use crate::profile::{Access, Profile, Register, Table, WordOrder};
use codec::ExceptionCode;

/// One register value a validated write will store.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Change {
    /// First address of the register.
    pub address: u16,
    /// The value as an integer (sign applied).
    pub value: i64,
}

/// A register of the map and its value.
#[derive(Clone, Copy, Debug)]
struct Slot<'a> {
    reg: &'a Register,
    value: i64,
}

/// Where the value of a register is kept, found once with [`RegisterBank::index_of`] so that
/// [`RegisterBank::set_value_at`] skips the address lookup (a model refreshing the same status registers on
/// every request). Valid for the bank it came from and its clones.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RegIndex(usize);

/// Where the state of a coil or discrete input is kept, found once with [`RegisterBank::bit_index`].
#[derive(Clone, Copy, Debug)]
pub(crate) struct BitIndex(usize);

/// One coil or discrete input of the map: its access, and where its state is kept.
#[derive(Clone, Copy, Debug)]
struct BitCell {
    access: Access,
    /// Index into the bank's state vector of the bit's table.
    state: usize,
}

/// What a bank's profile fixes: the registers and bits, their addresses and access modes. It never changes
/// after the bank is built, so clones of a bank share it.
#[derive(Debug)]
struct Layout {
    /// Every register of the profile; `RegisterBank::values` holds their values at the same indices.
    regs: Vec<Register>,
    /// Every address a holding-visible register covers → its index.
    holding: BTreeMap<u16, usize>,
    /// Every address an input-visible register covers → its index.
    input: BTreeMap<u16, usize>,
    coils: BTreeMap<u16, BitCell>,
    discrete: BTreeMap<u16, BitCell>,
}

/// Register, coil and discrete-input storage with the profile's map, access modes and ranges.
///
/// Cloning is cheap: the map is shared, only the values are copied.
#[derive(Clone, Debug)]
pub struct RegisterBank {
    layout: Arc<Layout>,
    /// The value of each register of `layout.regs`.
    values: Vec<i64>,
    /// The state of each coil (`BitCell::state` of `layout.coils` indexes it).
    coil_states: Vec<bool>,
    /// The state of each discrete input (`BitCell::state` of `layout.discrete` indexes it).
    discrete_states: Vec<bool>,
    order: WordOrder,
    reserved_readable: bool,
    read_only_writable: bool,
    range_unchecked: bool,
    /// `Fault::RangeCodeInconsistent`: the range error's code by the register's address, 03 or 04.
    range_code_inconsistent: bool,
    /// The exception codes chosen where the freedoms leave a choice, and the freedoms that decided the
    /// answer being given.
    freedoms: Freedoms,
    /// FC 07: the status byte and the coils that drive outputs 0, 1, ...
    exception_status: (u8, Vec<u16>),
    exception_status_reversed: bool,
    mask_write_wrong: bool,
}

/// The value a register starts with: its default, else 0 moved into its range.
fn initial_value(reg: &Register) -> i64 {
    let (lo, hi) = reg.range();
    reg.default.unwrap_or(0).clamp(lo, hi)
}

/// Reduce `value` to what a register of this width and sign can hold (two's complement wrap, like the drive's
/// own 16/32-bit variables).
fn wrap_to_width(reg: &Register, value: i64) -> i64 {
    match (reg.width, reg.signed) {
        (1, true) => i64::from(value as i16),
        (1, false) => i64::from(value as u16),
        (_, true) => i64::from(value as i32),
        (_, false) => i64::from(value as u32),
    }
}

impl RegisterBank {
    /// Build the bank: every register at its default, every bit off; faults that change the data model apply.
    pub fn new(profile: &Profile, faults: &FaultSet, choices: &Choices) -> Self {
        let mut regs = Vec::with_capacity(profile.registers.len());
        let mut values = Vec::with_capacity(profile.registers.len());
        let mut holding = BTreeMap::new();
        let mut input = BTreeMap::new();
        for r in &profile.registers {
            let reg = r.get_ref().clone();
            let idx = regs.len();
            for a in u32::from(reg.address)..reg.end().min(0x1_0000) {
                let a = a as u16;
                if matches!(reg.table, Table::Holding | Table::Both) {
                    holding.insert(a, idx);
                }
                if matches!(reg.table, Table::Input | Table::Both) {
                    input.insert(a, idx);
                }
            }
            values.push(initial_value(&reg));
            regs.push(reg);
        }
        // By address (a later entry for the same address replaces an earlier one), each bit's state at the
        // index of its address in ascending order.
        let bits = |list: &[toml::Spanned<crate::profile::Bit>]| {
            let mut map = list
                .iter()
                .map(|b| {
                    let b = b.get_ref();
                    (
                        b.address,
                        BitCell {
                            access: b.access,
                            state: 0,
                        },
                    )
                })
                .collect::<BTreeMap<_, _>>();
            for (i, cell) in map.values_mut().enumerate() {
                cell.state = i;
            }
            map
        };
        let coils = bits(&profile.coils);
        let discrete = bits(&profile.discrete_inputs);
        let order = if faults.has(Fault::WordOrder) {
            match profile.device.word_order {
                WordOrder::HighFirst => WordOrder::LowFirst,
                WordOrder::LowFirst => WordOrder::HighFirst,
            }
        } else {
            profile.device.word_order
        };
        Self {
            values,
            coil_states: vec![false; coils.len()],
            discrete_states: vec![false; discrete.len()],
            layout: Arc::new(Layout {
                regs,
                holding,
                input,
                coils,
                discrete,
            }),
            order,
            reserved_readable: faults.has(Fault::ReservedReadable),
            read_only_writable: faults.has(Fault::ReadOnlyWritable),
            range_unchecked: faults.has(Fault::RangeUnchecked),
            range_code_inconsistent: faults.has(Fault::RangeCodeInconsistent),
            freedoms: Freedoms::new(choices.clone()),
            exception_status: profile
                .exception_status
                .as_ref()
                .map(|e| (e.get_ref().value, e.get_ref().coils.clone()))
                .unwrap_or_default(),
            exception_status_reversed: faults.has(Fault::ExceptionStatusReversed),
            mask_write_wrong: faults.has(Fault::MaskWriteWrong),
        }
    }

    /// The values taken where the freedoms leave a choice.
    pub fn choices(&self) -> &Choices {
        self.freedoms.choices()
    }

    /// The choices taken and the freedoms that decided answers; a model over the bank keeps its own there.
    pub fn freedoms(&mut self) -> &mut Freedoms {
        &mut self.freedoms
    }

    /// The word order 32-bit registers travel in (the profile's, or the opposite under `Fault::WordOrder`).
    pub fn word_order(&self) -> WordOrder {
        self.order
    }

    /// True when out-of-range values are accepted (`Fault::RangeUnchecked`); models apply it to their own limits.
    pub fn range_unchecked(&self) -> bool {
        self.range_unchecked
    }

    /// True when read-only items accept writes (`Fault::ReadOnlyWritable`).
    pub fn read_only_writable(&self) -> bool {
        self.read_only_writable
    }

    fn map(&self, table: RegTable) -> &BTreeMap<u16, usize> {
        match table {
            RegTable::Holding => &self.layout.holding,
            RegTable::Input => &self.layout.input,
        }
    }

    fn words(&self, reg: &Register, value: i64) -> [u16; 2] {
        if reg.width == 1 {
            [value as u16, 0]
        } else {
            self.order.split(value as u32)
        }
    }

    fn value_of_words(&self, reg: &Register, words: &[u16]) -> i64 {
        match (reg.width, words) {
            (1, [w, ..]) => {
                if reg.signed {
                    i64::from(*w as i16)
                } else {
                    i64::from(*w)
                }
            }
            (_, [a, b, ..]) => {
                let raw = self.order.join(*a, *b);
                if reg.signed {
                    i64::from(raw as i32)
                } else {
                    i64::from(raw)
                }
            }
            _ => 0,
        }
    }

    /// Read `quantity` registers from `address` (FC 03/04). Quantity 0 (only reachable when the station's
    /// quantity check is faulted off) reads nothing.
    pub fn read(
        &self,
        table: RegTable,
        address: u16,
        quantity: u16,
    ) -> Result<Vec<u16>, Rejection> {
        let end = range_end(address, usize::from(quantity))?;
        let map = self.map(table);
        let mut out = Vec::with_capacity(usize::from(quantity));
        for a in u32::from(address)..end {
            let a = a as u16;
            match map.get(&a).and_then(|&i| self.slot(i)) {
                Some(slot) if slot.reg.access.readable() => {
                    let half = usize::from(a.wrapping_sub(slot.reg.address));
                    let w = self.words(slot.reg, slot.value);
                    out.push(w.get(half).copied().unwrap_or(0));
                }
                Some(_) => {
                    return Err(self
                        .choices()
                        .reject(ids::READ_WRITE_ONLY, ExceptionCode::ILLEGAL_DATA_ADDRESS));
                }
                None if self.reserved_readable => out.push(0),
                None => return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS.into()),
            }
        }
        Ok(out)
    }

    /// True when the range starts or ends inside a 32-bit register of `table`.
    pub fn splits_register(&self, table: RegTable, address: u16, quantity: u16) -> bool {
        let map = self.map(table);
        let inside = |a: u32| {
            u16::try_from(a)
                .ok()
                .and_then(|a| map.get(&a).and_then(|&i| self.slot(i)).map(|s| (a, s)))
                .is_some_and(|(a, s)| s.reg.width == 2 && s.reg.address != a)
        };
        let end = u32::from(address) + u32::from(quantity);
        quantity > 0 && (inside(u32::from(address)) || inside(end))
    }

    /// Validate a holding-register write of `words` at `address` without applying it: address/access errors
    /// (02) first for the whole range, then value errors (03).
    pub fn plan_write(&self, address: u16, words: &[u16]) -> Result<Vec<Change>, Rejection> {
        let end = range_end(address, words.len())?;
        // Pass 1: every address belongs to a writable register that the range covers completely (or, for a
        // drive that takes half of a 32-bit register, partly: the freedom `partial-register-write`).
        let takes_halves = self
            .choices()
            .name(ids::PARTIAL_REGISTER_WRITE)
            .is_some_and(|v| v == "response");
        let mut spans = Vec::new();
        let mut a = u32::from(address);
        while a < end {
            let Some(&idx) = self.layout.holding.get(&(a as u16)) else {
                return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS.into());
            };
            let Some(slot) = self.slot(idx) else {
                return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS.into());
            };
            if (u32::from(slot.reg.address) != a || slot.reg.end() > end) && !takes_halves {
                return Err(self.choices().reject(
                    ids::PARTIAL_REGISTER_WRITE,
                    ExceptionCode::ILLEGAL_DATA_ADDRESS,
                ));
            }
            if !slot.reg.access.writable() && !self.read_only_writable {
                return Err(self
                    .choices()
                    .reject(ids::WRITE_READ_ONLY, ExceptionCode::ILLEGAL_DATA_ADDRESS));
            }
            spans.push(idx);
            a = slot.reg.end();
        }
        // Pass 2: every value within the register's range (a half written keeps the other half).
        let mut changes = Vec::with_capacity(spans.len());
        for idx in spans {
            let Some(slot) = self.slot(idx) else {
                return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS.into());
            };
            let mut reg_words = self.words(slot.reg, slot.value);
            for (i, w) in reg_words
                .iter_mut()
                .enumerate()
                .take(usize::from(slot.reg.width))
            {
                let addr = u32::from(slot.reg.address) + i as u32;
                if (u32::from(address)..end).contains(&addr) {
                    *w = words[(addr - u32::from(address)) as usize];
                }
            }
            let value = self.value_of_words(slot.reg, &reg_words);
            let (lo, hi) = slot.reg.range();
            if (value < lo || value > hi) && !self.range_unchecked {
                if self.range_code_inconsistent {
                    let code = if slot.reg.address % 2 == 0 {
                        ExceptionCode::ILLEGAL_DATA_VALUE
                    } else {
                        ExceptionCode::SERVER_DEVICE_FAILURE
                    };
                    return Err(Rejection::by(ids::VALUE_OUT_OF_RANGE, code));
                }
                return Err(self
                    .choices()
                    .reject(ids::VALUE_OUT_OF_RANGE, ExceptionCode::ILLEGAL_DATA_VALUE));
            }
            // In range, but a value whose meaning the manual leaves open (`safe_values`): a drive may refuse
            // it (`value-meaning-open`).
            if slot.reg.meaning_open(value)
                && let Some(code) = self
                    .choices()
                    .get(ids::VALUE_MEANING_OPEN)
                    .and_then(Choices::exception_value)
            {
                return Err(Rejection::by(ids::VALUE_MEANING_OPEN, code));
            }
            changes.push(Change {
                address: slot.reg.address,
                value,
            });
        }
        Ok(changes)
    }

    /// Store validated changes (from `plan_write`).
    pub fn commit(&mut self, changes: &[Change]) {
        // Taken although the manual leaves what the value means open: a drive may refuse it.
        if changes.iter().any(|c| {
            self.register(c.address)
                .is_some_and(|r| r.meaning_open(c.value))
        }) {
            self.freedoms.decided(ids::VALUE_MEANING_OPEN);
        }
        for c in changes {
            self.set_value(c.address, c.value);
        }
    }

    /// Validate and apply a holding-register write (FC 06/10/17); returns what changed.
    pub fn write(&mut self, address: u16, words: &[u16]) -> Result<Vec<Change>, Rejection> {
        let changes = self.plan_write(address, words)?;
        self.commit(&changes);
        Ok(changes)
    }

    fn slot(&self, idx: usize) -> Option<Slot<'_>> {
        Some(Slot {
            reg: self.layout.regs.get(idx)?,
            value: *self.values.get(idx)?,
        })
    }

    /// The index of the register starting at `address` (either table).
    fn index_at(&self, address: u16) -> Option<usize> {
        let layout = &*self.layout;
        let idx = *layout
            .holding
            .get(&address)
            .or_else(|| layout.input.get(&address))?;
        layout
            .regs
            .get(idx)
            .is_some_and(|r| r.address == address)
            .then_some(idx)
    }

    fn slot_at(&self, address: u16) -> Option<Slot<'_>> {
        self.slot(self.index_at(address)?)
    }

    /// The register starting at `address` (either table).
    pub fn register(&self, address: u16) -> Option<&Register> {
        self.slot_at(address).map(|s| s.reg)
    }

    /// The value of the register starting at `address` (either table).
    pub fn value(&self, address: u16) -> Option<i64> {
        self.slot_at(address).map(|s| s.value)
    }

    /// Set the register starting at `address` from inside the drive (status, counters): no access or range
    /// check; the value wraps to the register's width. False when no register starts there.
    pub fn set_value(&mut self, address: u16, value: i64) -> bool {
        let Some(idx) = self.index_at(address) else {
            return false;
        };
        match (self.layout.regs.get(idx), self.values.get_mut(idx)) {
            (Some(reg), Some(v)) => {
                *v = wrap_to_width(reg, value);
                true
            }
            _ => false,
        }
    }

    /// The register starting at `address` (either table), as [`set_value`](Self::set_value) finds it.
    pub(crate) fn index_of(&self, address: u16) -> Option<RegIndex> {
        self.index_at(address).map(RegIndex)
    }

    /// [`set_value`](Self::set_value) of the register at `at`.
    pub(crate) fn set_value_at(&mut self, at: RegIndex, value: i64) {
        if let (Some(reg), Some(v)) = (self.layout.regs.get(at.0), self.values.get_mut(at.0)) {
            *v = wrap_to_width(reg, value);
        }
    }

    /// The value of the register at `at`, as [`value`](Self::value) reads it.
    pub(crate) fn value_at(&self, at: RegIndex) -> i64 {
        self.values.get(at.0).copied().unwrap_or(0)
    }

    /// The bit at `address` of `table`, as [`bit`](Self::bit) finds it.
    pub(crate) fn bit_index(&self, table: BitTable, address: u16) -> Option<BitIndex> {
        self.bits(table).0.get(&address).map(|c| BitIndex(c.state))
    }

    /// [`bit`](Self::bit) of the bit at `at` of `table`.
    pub(crate) fn bit_at(&self, table: BitTable, at: BitIndex) -> bool {
        self.bits(table).1.get(at.0).copied().unwrap_or(false)
    }

    /// First address of the register with MCode mnemonic `mnemonic` (case-insensitive).
    pub fn address_of(&self, mnemonic: &str) -> Option<u16> {
        self.layout
            .regs
            .iter()
            .find(|r| {
                r.mnemonic
                    .as_deref()
                    .is_some_and(|m| m.eq_ignore_ascii_case(mnemonic))
            })
            .map(|r| r.address)
    }

    /// The map of a bit table and the states its cells index.
    fn bits(&self, table: BitTable) -> (&BTreeMap<u16, BitCell>, &[bool]) {
        match table {
            BitTable::Coils => (&self.layout.coils, &self.coil_states),
            BitTable::DiscreteInputs => (&self.layout.discrete, &self.discrete_states),
        }
    }

    fn bits_mut(&mut self, table: BitTable) -> (&BTreeMap<u16, BitCell>, &mut [bool]) {
        match table {
            BitTable::Coils => (&self.layout.coils, &mut self.coil_states),
            BitTable::DiscreteInputs => (&self.layout.discrete, &mut self.discrete_states),
        }
    }

    /// Read `quantity` bits from `address`, packed LSB-first as FC 01/02 carry them.
    pub fn read_bits(
        &self,
        table: BitTable,
        address: u16,
        quantity: u16,
    ) -> Result<Vec<u8>, Rejection> {
        let end = range_end(address, usize::from(quantity))?;
        let (map, states) = self.bits(table);
        let mut out = vec![0u8; usize::from(quantity).div_ceil(8)];
        for (i, a) in (u32::from(address)..end).enumerate() {
            let on = match map.get(&(a as u16)) {
                Some(c) if c.access.readable() => states.get(c.state).copied().unwrap_or(false),
                Some(_) => return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS.into()),
                None if self.reserved_readable => false,
                None => return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS.into()),
            };
            if on && let Some(byte) = out.get_mut(i / 8) {
                *byte |= 1 << (i % 8);
            }
        }
        Ok(out)
    }

    /// Write coils from `address` on (FC 05/0F): all or nothing; unmapped or read-only coils give 02.
    pub fn write_coils(&mut self, address: u16, states: &[bool]) -> Result<(), Rejection> {
        let end = self.check_coil_write(address, states.len())?;
        for (a, &s) in (u32::from(address)..end).zip(states) {
            if let Some(c) = self.layout.coils.get(&(a as u16))
                && let Some(state) = self.coil_states.get_mut(c.state)
            {
                *state = s;
            }
        }
        Ok(())
    }

    /// What [`write_coils`](Self::write_coils) would refuse of a write of `count` coils from `address`, without
    /// writing: the end (exclusive) of the coils written where it would take it.
    pub fn check_coil_write(&self, address: u16, count: usize) -> Result<u32, Rejection> {
        let end = range_end(address, count)?;
        for a in u32::from(address)..end {
            match self.layout.coils.get(&(a as u16)) {
                Some(c) if c.access.writable() || self.read_only_writable => {}
                Some(_) => {
                    return Err(self
                        .choices()
                        .reject(ids::WRITE_READ_ONLY, ExceptionCode::ILLEGAL_DATA_ADDRESS));
                }
                None => return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS.into()),
            }
        }
        Ok(end)
    }

    /// The state of one bit, if it exists.
    pub fn bit(&self, table: BitTable, address: u16) -> Option<bool> {
        let (map, states) = self.bits(table);
        map.get(&address).and_then(|c| states.get(c.state).copied())
    }

    /// Set one bit from inside the drive (input levels, outputs driven by registers); false if it does not exist.
    pub fn set_bit(&mut self, table: BitTable, address: u16, on: bool) -> bool {
        let (map, states) = self.bits_mut(table);
        match map.get(&address).and_then(|c| states.get_mut(c.state)) {
            Some(state) => {
                *state = on;
                true
            }
            None => false,
        }
    }

    /// FC 07 (spec 6.7): the profile's `[exception_status]` byte with each listed coil's state in its bit
    /// (output i in bit i); all outputs off for a profile without the table.
    pub fn exception_status(&self) -> u8 {
        let (value, coils) = &self.exception_status;
        let mut status = *value;
        for (i, c) in coils.iter().enumerate().take(8) {
            if self
                .layout
                .coils
                .get(c)
                .is_some_and(|b| self.coil_states.get(b.state).copied().unwrap_or(false))
            {
                status |= 1 << i;
            } else {
                status &= !(1 << i);
            }
        }
        if self.exception_status_reversed {
            status.reverse_bits()
        } else {
            status
        }
    }

    /// FC 16's result (spec 6.16), or the faulty one under `Fault::MaskWriteWrong`: the OR mask applied
    /// unmasked, a common slip.
    pub fn masked(&self, current: u16, and_mask: u16, or_mask: u16) -> u16 {
        if self.mask_write_wrong {
            (current & and_mask) | or_mask
        } else {
            super::data_model::mask_write(current, and_mask, or_mask)
        }
    }

    /// The addresses of a bit table in ascending order.
    pub fn bit_addresses(&self, table: BitTable) -> Vec<u16> {
        self.bits(table).0.keys().copied().collect()
    }
}

impl DataModel for RegisterBank {
    type Plan = Vec<Change>;

    fn read_registers(
        &self,
        table: RegTable,
        address: u16,
        quantity: u16,
    ) -> Result<Vec<u16>, Rejection> {
        self.read(table, address, quantity)
    }

    fn splits_register(&self, table: RegTable, address: u16, quantity: u16) -> bool {
        RegisterBank::splits_register(self, table, address, quantity)
    }

    fn plan_write(&self, address: u16, words: &[u16]) -> Result<Vec<Change>, Rejection> {
        RegisterBank::plan_write(self, address, words)
    }

    fn decided(&mut self, freedom: Decision) {
        self.freedoms.decided(freedom);
    }

    fn commit(&mut self, plan: Vec<Change>) {
        RegisterBank::commit(self, &plan);
    }

    fn read_bits(
        &self,
        table: BitTable,
        address: u16,
        quantity: u16,
    ) -> Result<Vec<u8>, Rejection> {
        RegisterBank::read_bits(self, table, address, quantity)
    }

    fn write_coils(&mut self, address: u16, states: &[bool]) -> Result<(), Rejection> {
        RegisterBank::write_coils(self, address, states)
    }

    fn exception_status(&self) -> Result<u8, Rejection> {
        Ok(RegisterBank::exception_status(self))
    }

    fn masked(&self, current: u16, and_mask: u16, or_mask: u16) -> u16 {
        RegisterBank::masked(self, current, and_mask, or_mask)
    }
}
