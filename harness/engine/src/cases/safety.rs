//! The one safety classifier: what a request PDU would do to a drive of a profile, as safety tags.
//!
//! Every case source (catalog, generated, regressions, the fuzz campaign, the probe) tags its cases with
//! [`classify`], and the runner rates the bytes again immediately before it sends them: a request rated more
//! dangerous than its case says is not sent (see `runner`).
//!
//! The rules, worst case first, on the raw bytes (a drive that does not check what it receives acts on
//! malformed, over-long or truncated requests too):
//! - `write`: every write function code (05, 06, 0F, 10, 16, 17 whatever its write quantity, 15, the vendor
//!   write 0x42, an FC 43/MEI 0x0D access with the write bit) and the FC 08 sub-functions that change the
//!   serial line's state (restart, ASCII delimiter, listen only, clear counters, clear overrun).
//! - `motion`: a write whose reach touches a register, coil, object or mnemonic the profile marks `motion`.
//! - `destructive`: a write whose reach touches one marked `destructive` (actions, Save/NVM, factory reset,
//!   counter resets, increment/decrement variables, program control, clock mode: nothing the harness can
//!   read back and put back), the RxPDO watchdog (it faults the drive when it runs out), FC 08 state changes,
//!   file records.
//!
//! The reach of a write is every address its fields could designate: from the start address, the largest of
//! the quantity field, the byte count and the data actually carried. A write whose address is missing
//! reaches everything of its kind in the profile; an unknown mnemonic or object may do anything.

use std::collections::BTreeSet;

use codec::Mnemonic;
use drives::profile::Profile;

use crate::cases::Tag;

/// What the safety policy lets a run do to a real drive (the in-process simulator is not protected).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Safety {
    /// Cases that can move the motor or enable the power stage run.
    pub allow_motion: bool,
    /// Cases that change non-volatile state or leave the drive faulted run.
    pub allow_destructive: bool,
    /// No case that writes runs.
    pub read_only: bool,
    /// Requests per second at most.
    pub max_rate: Option<f64>,
}

/// The safety tags (`Write`, `Motion`, `Destructive`) of a request PDU sent to a drive of profile `p`.
pub fn classify(p: &Profile, pdu: &[u8]) -> BTreeSet<Tag> {
    let mut r = Rating::default();
    let Some(&fc) = pdu.first() else {
        return BTreeSet::new();
    };
    let be16 =
        |at: usize| -> Option<u16> { Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?])) };
    let data_len = |from: usize| pdu.len().saturating_sub(from);
    // How many items a multiple write whose address is at `at` (quantity, byte count and data after it) may
    // touch: the most its quantity, its byte count and its data say (`per_bytes`: items in that many bytes).
    let written = |at: usize, per_bytes: fn(usize) -> usize| {
        let quantity = be16(at + 2).map_or(0, usize::from);
        let count = pdu.get(at + 4).map_or(0, |b| per_bytes(usize::from(*b)));
        quantity.max(count).max(per_bytes(data_len(at + 5))).max(1)
    };
    // A read that clears what it reads (the MCode error code ER, "must be read or set to 0 to clear"): the
    // drive's record of its last error is gone once read, so the read is destructive.
    let read = |at: usize| -> Option<(u16, u16)> { Some((be16(at)?, be16(at + 2)?)) };
    let clears = |(address, quantity): (u16, u16)| {
        let end = u32::from(address) + u32::from(quantity.max(1));
        p.registers
            .iter()
            .map(|x| x.get_ref())
            .any(|x| x.read_clears && u32::from(x.address) < end && x.end() > u32::from(address))
    };
    if matches!(fc, 0x03 | 0x04) && read(1).is_some_and(clears)
        || fc == 0x17 && read(1).is_some_and(clears)
    {
        r.destructive = true;
    }
    match fc {
        0x05 => r.coils(p, be16(1), 1),
        0x06 | 0x16 => r.registers(p, be16(1), 1),
        0x0F => r.coils(p, be16(1), written(1, |bytes| bytes * 8)),
        0x10 => r.registers(p, be16(1), written(1, |bytes| bytes.div_ceil(2))),
        // FC 17 writes even with a write quantity of 0: a drive that does not check it writes what follows.
        0x17 => r.registers(p, be16(5), written(5, |bytes| bytes.div_ceil(2))),
        // File records are outside the register map: what a write to them does is unknown (often
        // non-volatile storage), and the harness does not read them back.
        0x15 => r.all(),
        0x08 => {
            // Sub-functions that change the line's state or clear what cannot be put back.
            match be16(1) {
                Some(0x01 | 0x03 | 0x04 | 0x0A | 0x14) | None => {
                    r.write = true;
                    r.destructive = true;
                }
                Some(0x00 | 0x02 | 0x0B..=0x12) => {}
                // A sub-function the spec does not define may do anything.
                Some(_) => {
                    r.write = true;
                    r.destructive = true;
                }
            }
        }
        0x42 => {
            r.write = true;
            let m = pdu
                .get(1..5)
                .map(|b| Mnemonic([b[0], b[1], b[2], b[3]]).name());
            match m.as_deref().and_then(|n| p.mnemonic(n)) {
                Some(m) => r.item(p, m.motion, m.destructive, m.register),
                // A mnemonic the profile does not know (or a missing one) may do anything.
                None => r.all(),
            }
        }
        0x2B if pdu.get(1) == Some(&0x0D) => {
            let Some(control) = pdu.get(2) else {
                // No control byte: a drive cannot tell a read from a write, assume the worst.
                r.all();
                return r.tags();
            };
            if control & codec::CanOpenAccess::WRITE != 0 {
                r.write = true;
                let index = be16(5);
                let sub = pdu.get(7).copied();
                match (index, sub) {
                    (Some(i), Some(s)) => match p.object(i, s) {
                        Some(o) => r.item(p, o.motion, o.destructive, o.register),
                        None => r.all(),
                    },
                    _ => r.all(),
                }
            }
        }
        _ => {}
    }
    r.tags()
}

/// True for an MCode command that leaves the drive changed for good, beyond what any restore can put back:
/// CP clears the stored program space, UG puts the drive in firmware-upgrade mode (LMD 001 sections 4.4.3,
/// 4.4.27). The catalog runs its cases of them last (`Tag::Irreversible`); generated and fuzz cases never send
/// them to a real drive.
pub fn irreversible_mnemonic(name: &str) -> bool {
    matches!(name.trim().to_ascii_uppercase().as_str(), "CP" | "UG")
}

/// True when `pdu` is an FC 0x42 write of an [`irreversible_mnemonic`].
pub fn irreversible(pdu: &[u8]) -> bool {
    pdu.first() == Some(&0x42)
        && pdu
            .get(1..5)
            .is_some_and(|m| irreversible_mnemonic(&Mnemonic([m[0], m[1], m[2], m[3]]).name()))
}

/// [`classify`], and `destructive` for a write addressed to another unit than the run's: it may reach another
/// drive on the bus (all of them, for a broadcast).
pub fn classify_to_unit(p: &Profile, pdu: &[u8], unit: u8, run_unit: u8) -> BTreeSet<Tag> {
    let mut tags = classify(p, pdu);
    if unit != run_unit && tags.contains(&Tag::Write) {
        tags.insert(Tag::Destructive);
    }
    tags
}

/// The safety tags in `rated` that `tags` lacks: what a case would do beyond what it says.
pub fn exceeds(rated: &BTreeSet<Tag>, tags: &[Tag]) -> Vec<Tag> {
    rated
        .iter()
        .filter(|t| matches!(t, Tag::Write | Tag::Motion | Tag::Destructive))
        .filter(|t| !tags.contains(t))
        .copied()
        .collect()
}

/// True when `pdu` writes on any drive: the `write` part of [`classify`], which needs no profile (used where
/// none is known, as in `probe`).
pub fn is_write(pdu: &[u8]) -> bool {
    match pdu {
        [] => false,
        [fc, ..] if is_write_fc(*fc) => true,
        [0x08, rest @ ..] => !matches!(rest, [0x00, 0x00 | 0x02 | 0x0B..=0x12, ..]),
        [0x2B, 0x0D] => true,
        [0x2B, 0x0D, control, ..] => control & codec::CanOpenAccess::WRITE != 0,
        _ => false,
    }
}

/// True when `fc` is a function code that can write (the FC 08 and FC 43 ones depend on their fields).
pub fn is_write_fc(fc: u8) -> bool {
    matches!(fc, 0x05 | 0x06 | 0x0F | 0x10 | 0x15 | 0x16 | 0x17 | 0x42)
}

#[derive(Default)]
struct Rating {
    write: bool,
    motion: bool,
    destructive: bool,
}

impl Rating {
    /// A write of a profile item (an FC 0x41 setting, an object) with its flags, and of the register it
    /// mirrors, if any.
    fn item(&mut self, p: &Profile, motion: bool, destructive: bool, register: Option<u16>) {
        self.motion |= motion;
        self.destructive |= destructive;
        if let Some(reg) = register {
            self.registers(p, Some(reg), 1);
        }
    }

    fn all(&mut self) {
        self.write = true;
        self.motion = true;
        self.destructive = true;
    }

    fn tags(&self) -> BTreeSet<Tag> {
        let mut t = BTreeSet::new();
        if self.write {
            t.insert(Tag::Write);
        }
        if self.motion {
            t.insert(Tag::Motion);
        }
        if self.destructive {
            t.insert(Tag::Destructive);
        }
        t
    }

    /// A write to `n` items from `address` (`None`: any): the span `start..end` it may touch.
    fn write_span(&mut self, address: Option<u16>, n: usize) -> (u32, u32) {
        self.write = true;
        match address {
            Some(a) => (u32::from(a), u32::from(a) + n as u32),
            None => (0, 0x1_0000),
        }
    }

    /// A write to `n` holding registers from `address` (`None`: any register).
    fn registers(&mut self, p: &Profile, address: Option<u16>, n: usize) {
        let (start, end) = self.write_span(address, n);
        for r in p.registers.iter().map(|r| r.get_ref()) {
            let holding = !matches!(r.table, drives::profile::Table::Input);
            if holding && u32::from(r.address) < end && r.end() > start {
                self.motion |= r.motion;
                self.destructive |= r.destructive;
            }
        }
        // A watchdog left armed faults the drive when it runs out.
        if let Some(w) = &p.watchdog
            && (start..end).contains(&u32::from(w.register))
        {
            self.destructive = true;
        }
        // Registers an object mirrors carry the object's flags too.
        for o in p.objects.iter().map(|o| o.get_ref()) {
            if let Some(reg) = o.register
                && (start..end).contains(&u32::from(reg))
            {
                self.motion |= o.motion;
                self.destructive |= o.destructive;
            }
        }
    }

    /// A write to `n` coils from `address` (`None`: any coil).
    fn coils(&mut self, p: &Profile, address: Option<u16>, n: usize) {
        let (start, end) = self.write_span(address, n);
        for c in p.coils.iter().map(|c| c.get_ref()) {
            if (start..end).contains(&u32::from(c.address)) {
                self.motion |= c.motion;
                self.destructive |= c.destructive;
            }
        }
    }
}
