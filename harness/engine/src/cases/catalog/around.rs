//! The steps around a case's own: the precondition it establishes first, and the writes that put back
//! everything it changed (or could have changed, on a drive that wrongly accepts a request it must refuse).
//!
//! Every catalog case that writes reads what it will change first and writes it back after, so that its
//! verdict depends neither on what an earlier case left behind nor on the order of the cases, and a run
//! leaves the drive as it found it. What is read is the target's own state: the reference drive receives the
//! same restoring bytes and so follows the target. What cannot be put back is said where the case is built.

use super::mcode::{self, IoPoints};
use super::{Ctx, capture, exchange, pdu};
use crate::cases::{Compare, Outgoing, Step, Tag};
use codec::{CanOpenAccess, FunctionCode, Mnemonic, Request};
use drives::profile::{Access, Object, Register, Table};

/// The steps before and after a case's own; the restores run in the reverse order of what was kept.
#[derive(Default)]
pub(super) struct Around {
    before: Vec<Step>,
    /// In run order: new undo steps go first (the last change is the first undone).
    after: Vec<Step>,
    /// After `after`, in the order added ([`Around::finally`]).
    last: Vec<Step>,
    next_slot: usize,
}

impl Around {
    pub(super) fn new() -> Self {
        Self::default()
    }

    /// Around a case that uses capture slots below `slot` itself.
    pub(super) fn from_slot(slot: usize) -> Self {
        Self {
            next_slot: slot,
            ..Self::default()
        }
    }

    /// A fresh capture slot.
    pub(super) fn slot(&mut self) -> usize {
        self.next_slot += 1;
        self.next_slot - 1
    }

    /// A step of the precondition (after what was kept so far).
    pub(super) fn set(&mut self, step: Step) {
        self.before.push(step);
    }

    /// Steps that undo what the case does, run before every restore kept so far.
    pub(super) fn undo(&mut self, steps: Vec<Step>) {
        self.after.splice(0..0, steps);
    }

    /// A step after every undo and restore: what the case must wait for once everything is back (a calibration
    /// the restores started). Steps added later run later.
    pub(super) fn finally(&mut self, step: Step) {
        self.last.push(step);
    }

    /// Read `what` with `read`, keep the answer, and put it back after with `restore` (built from the slot).
    fn keep(
        &mut self,
        read: Request,
        compare: Compare,
        what: String,
        restore: impl FnOnce(usize) -> (Outgoing, Compare),
    ) -> usize {
        let slot = self.slot();
        self.before.push(capture(
            Outgoing::Pdu(pdu(&read)),
            compare,
            slot,
            format!("read {what} first"),
        ));
        let (send, cmp) = restore(slot);
        self.undo(vec![exchange(send, cmp, format!("put back {what}"))]);
        slot
    }

    /// Keep one register entry at its width (read with `compare`) and write it back after; its slot.
    pub(super) fn keep_register(&mut self, cx: &Ctx, r: &Register, compare: Compare) -> usize {
        let table = if r.table == Table::Input {
            Table::Input
        } else {
            Table::Holding
        };
        let read = cx.read_request(r.address, u16::from(r.width), table);
        let address = r.address;
        self.keep(
            read,
            compare,
            format!("{} (0x{address:04X})", r.name),
            |slot| (Outgoing::Restore { address, slot }, Compare::Exact),
        )
    }

    /// Keep every register that a write of `count` registers at `address` could change (the readable,
    /// writable holding registers of the profile in that span), in reads the drive accepts, and write them
    /// back after. Nothing when the profile has no register there or no function to read or write them.
    pub(super) fn keep_registers(&mut self, cx: &Ctx, address: u16, count: u16) {
        let Some(limit) = register_chunk_limit(cx) else {
            return;
        };
        for (start, quantity) in register_chunks(cx, address, count, limit) {
            let read = cx.read_request(start, quantity, Table::Holding);
            self.keep(
                read,
                Compare::Structure,
                format!("registers 0x{start:04X}..+{quantity}"),
                |slot| (Outgoing::RestoreRead { slot }, Compare::Exact),
            );
        }
    }

    /// Keep every writable coil of the profile in `count` coils from `address`, and write them back after.
    pub(super) fn keep_coils(&mut self, cx: &Ctx, address: u16, count: u16) {
        if !cx.supports(FunctionCode::READ_COILS) {
            return;
        }
        let limit = if cx.supports(FunctionCode::WRITE_MULTIPLE_COILS) {
            cx.max_quantity(FunctionCode::READ_COILS)
                .min(cx.max_quantity(FunctionCode::WRITE_MULTIPLE_COILS))
        } else if cx.supports(FunctionCode::WRITE_SINGLE_COIL) {
            1
        } else {
            return;
        };
        let mut coils: Vec<u16> =
            cx.p.coils
                .iter()
                .map(|c| c.get_ref())
                .filter(|c| c.access.writable() && in_span(c.address, 1, address, count))
                .map(|c| c.address)
                .collect();
        coils.sort_unstable();
        for (start, quantity) in runs(coils.iter().map(|a| (*a, 1)), limit.max(1)) {
            self.keep(
                Request::ReadCoils {
                    address: start,
                    quantity,
                },
                Compare::Structure,
                format!("coils {start}..+{quantity}"),
                |slot| (Outgoing::RestoreRead { slot }, Compare::Exact),
            );
        }
    }

    /// Keep a vendor setting (FC 0x41) and write it back after (FC 0x42, `=` and the values read). Nothing for
    /// a mnemonic that cannot be read: a command, or a profile without FC 0x41.
    pub(super) fn keep_setting(&mut self, cx: &Ctx, name: &str) {
        let readable = cx.p.mnemonic(name).is_some_and(|m| m.read);
        let Some(mnemonic) = Mnemonic::from_name(name) else {
            return;
        };
        if !readable
            || !cx.supports(FunctionCode::VENDOR_READ)
            || !cx.supports(FunctionCode::VENDOR_WRITE)
        {
            return;
        }
        self.keep(
            Request::VendorRead { mnemonic },
            Compare::Structure,
            format!("setting {} (FC 0x41)", name.trim()),
            // The bytes-written field of an FC 0x42 answer is a freedom: structure only.
            |slot| (Outgoing::RestoreRead { slot }, Compare::Structure),
        );
    }

    /// Keep an FC 43 object and write it back after.
    pub(super) fn keep_object(&mut self, cx: &Ctx, o: &Object) {
        let read = Request::CanOpen(CanOpenAccess::read(
            cx.unit,
            o.index,
            o.subindex,
            o.ty.size() as u16,
        ));
        self.keep(
            read,
            Compare::Structure,
            format!("object {} {}", o.index, o.name),
            |slot| (Outgoing::RestoreRead { slot }, Compare::Exact),
        );
    }

    /// The steps before and the steps after a case's own.
    pub(super) fn split(self) -> (Vec<Step>, Vec<Step>) {
        let mut after = self.after;
        after.extend(self.last);
        (self.before, after)
    }

    /// The case's steps with the precondition before them and the restores after.
    pub(super) fn wrap(self, body: Vec<Step>) -> Vec<Step> {
        let (mut steps, after) = self.split();
        steps.extend(body);
        steps.extend(after);
        steps
    }
}

/// What a request that writes needs around it, whatever case sends it: the registers, coils, vendor setting
/// or object it writes read first and written back after (a register write that moves is undone by that
/// restore too); on the MDrive the I/O points it drives configured as outputs first; for an MCode move the
/// drive enabled, for VI/VM and HT/MT the partner register freed; for a program command no program running
/// first and none left running ([`mcode::program_command`], which may add `Motion` or `Irreversible` to
/// `tags`). Nothing for a request that does not write.
pub(super) fn around_write(cx: &Ctx, req: &Request, a: &mut Around, tags: &mut Vec<Tag>) {
    let p = cx.p;
    let io = IoPoints::of(p);
    match req {
        Request::WriteSingleRegister { address, .. }
        | Request::WriteMultipleRegisters { address, .. } => {
            let n = match req {
                Request::WriteMultipleRegisters { values, .. } => values.len() as u16,
                _ => 1,
            };
            let mut regs: Vec<&Register> = (0..n)
                .filter_map(|i| p.register_at(address.wrapping_add(i), false))
                .collect();
            regs.dedup_by_key(|r| r.address);
            for r in &regs {
                if let Some(io) = &io {
                    io.configure_outputs(cx, a, &io.of_register(r));
                }
                if mcode::starts_move(r) {
                    mcode::enable_drive(cx, a);
                } else if r.motion {
                    mcode::keep_drive_enable(cx, a);
                }
                mcode::free_partner(cx, a, r);
                mcode::await_calibration(cx, a, r);
            }
            a.keep_registers(cx, *address, n);
            if regs.iter().any(|r| r.motion) {
                let homing = regs
                    .iter()
                    .any(|r| r.mnemonic.as_deref().is_some_and(mcode::homes));
                mcode::settle_motion(cx, a, homing);
            }
        }
        Request::WriteSingleCoil { address, .. } | Request::WriteMultipleCoils { address, .. } => {
            let n = match req {
                Request::WriteMultipleCoils { quantity, .. } => *quantity,
                _ => 1,
            };
            if let Some(io) = &io {
                io.configure_outputs(cx, a, &io.of_coils(*address, n));
            }
            a.keep_coils(cx, *address, n);
        }
        Request::VendorWrite { mnemonic, .. } => {
            let name = mnemonic.name();
            let moves = p.mnemonic(&name).is_some_and(|m| m.motion);
            let homing = mcode::homes(&name);
            if moves {
                mcode::keep_drive_enable(cx, a);
            }
            a.keep_setting(cx, &name);
            mcode::program_command(cx, a, tags, &name);
            if moves {
                mcode::settle_motion(cx, a, homing);
            }
        }
        Request::CanOpen(o) if o.is_write() => {
            if let Some(o) = p.object(o.index, o.subindex) {
                a.keep_object(cx, o);
            }
        }
        _ => {}
    }
}

/// True when `[a, a + n)` and `[start, start + count)` overlap.
fn in_span(a: u16, n: u8, start: u16, count: u16) -> bool {
    let (a, end) = (u32::from(a), u32::from(a) + u32::from(n));
    let (s, e) = (u32::from(start), u32::from(start) + u32::from(count));
    a < e && s < end
}

/// The most registers one capture can read and one restore can write back; `None` when the profile cannot
/// do both.
fn register_chunk_limit(cx: &Ctx) -> Option<u16> {
    let read = [
        FunctionCode::READ_HOLDING_REGISTERS,
        FunctionCode::READ_INPUT_REGISTERS,
    ]
    .into_iter()
    .find(|f| cx.supports(*f))?;
    let write = if cx.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS) {
        cx.max_quantity(FunctionCode::WRITE_MULTIPLE_REGISTERS)
    } else if cx.supports(FunctionCode::WRITE_SINGLE_REGISTER) {
        1
    } else {
        return None;
    };
    Some(cx.max_quantity(read).min(write).max(1))
}

/// The reads that cover the readable, writable holding registers overlapping `count` registers at
/// `address`: (start, quantity), each at most `limit` registers, never splitting a 32-bit pair.
fn register_chunks(cx: &Ctx, address: u16, count: u16, limit: u16) -> Vec<(u16, u16)> {
    let mut regs: Vec<(u16, u8)> =
        cx.p.registers
            .iter()
            .map(|r| r.get_ref())
            .filter(|r| {
                r.table != Table::Input
                    && r.access == Access::Rw
                    && in_span(r.address, r.width, address, count)
            })
            .map(|r| (r.address, r.width))
            .collect();
    regs.sort_unstable();
    runs(regs.into_iter(), limit)
}

/// Adjacent items (address, width) joined into runs of at most `limit` (an item wider than the limit alone).
fn runs(items: impl Iterator<Item = (u16, u8)>, limit: u16) -> Vec<(u16, u16)> {
    let mut out: Vec<(u16, u16)> = Vec::new();
    for (a, w) in items {
        let w = u16::from(w);
        match out.last_mut() {
            Some((s, q)) if u32::from(*s) + u32::from(*q) == u32::from(a) && *q + w <= limit => {
                *q += w
            }
            _ => out.push((a, w)),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::runs;

    #[test]
    fn adjacent_items_join_up_to_the_limit() {
        let items = [(0, 2), (2, 1), (3, 2), (7, 1), (8, 1)];
        assert_eq!(
            runs(items.into_iter(), 4),
            vec![(0, 3), (3, 2), (7, 2)],
            "a pair is never split and a gap starts a new run"
        );
        assert_eq!(runs([(0, 1), (1, 1)].into_iter(), 1), vec![(0, 1), (1, 1)]);
    }
}
