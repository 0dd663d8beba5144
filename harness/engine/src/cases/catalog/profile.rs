//! Cases derived from the profile: every register, reserved range, coil, discrete input, vendor mnemonic
//! and identification object of the drive's map, read and (where it is safe to undo) written.
//!
//! An entry marked `confirmed = false` (a probe saw it answer a read; nobody has said more) gets read cases
//! only: its width, access and range are not known, so nothing is written to it and nothing is judged on them.

use super::around::Around;
use super::mcode::{self, IoPoints};
use super::{APP, Ctx, capture, exchange, pdu, slug};
use crate::cases::{Compare, Outgoing, Step, Tag};
use codec::FunctionCode;
use codec::{Mnemonic, Request};
use drives::profile::{Register, Table};

/// The profile suite, family by family.
pub(super) fn cases(cx: &mut Ctx) {
    registers(cx);
    half_registers(cx);
    multi_item_read(cx);
    reserved(cx);
    coils(cx);
    outputs_of_input_points(cx);
    discrete_inputs(cx);
    mnemonics(cx);
    mnemonic_refusals(cx);
    identification(cx);
}

/// Each register read at its width, and written where the profile allows it (the watchdog is left alone:
/// writing it arms a timer that faults the drive).
fn registers(cx: &mut Ctx) {
    let p = cx.p;
    let watchdog = p.watchdog.as_ref().map(|w| w.register);
    let fc04_too = one_map(cx);
    for r in p.registers.iter().map(|r| r.get_ref()) {
        let table = if r.table == Table::Input {
            Table::Input
        } else {
            Table::Holding
        };
        let read = pdu(&cx.read_request(r.address, u16::from(r.width), table));
        if r.access.readable()
            && (cx.supports(FunctionCode::READ_HOLDING_REGISTERS)
                || cx.supports(FunctionCode::READ_INPUT_REGISTERS))
        {
            register_read(cx, r, &read);
            if fc04_too && table == Table::Holding {
                register_read_fc04(cx, r);
            }
        }
        if !r.confirmed || !cx.can_write_registers() || Some(r.address) == watchdog {
            continue;
        }
        if r.access.writable() {
            let tags = write_tags(r);
            register_write(cx, r, &read, &tags);
            register_write_out_of_range(cx, r, &read, &tags);
        } else if r.table != Table::Input {
            // An input register (its own table) is written by no function: there is no rule to check.
            register_write_read_only(cx, r);
        }
    }
}

/// The tags of a write to `r`.
fn write_tags(r: &Register) -> Vec<Tag> {
    let mut tags = vec![Tag::Write];
    if r.motion {
        tags.push(Tag::Motion);
    }
    if r.destructive {
        tags.push(Tag::Destructive);
    }
    tags
}

/// A register is readable and holds a value in its range.
fn register_read(cx: &mut Ctx, r: &Register, read: &[u8]) {
    let p = cx.p;
    let pid = &p.device.id;
    cx.push(
        format!("profile/{pid}/read/{}", reg_slug(r)),
        format!("read {} at its width", r.name),
        format!(
            "{} register map: 0x{:04X} {}",
            p.device.name, r.address, r.name
        ),
        format!(
            "Register 0x{:04X} ({} register{}) is readable and holds a value in {}..={}.",
            r.address,
            r.width,
            if r.width == 2 {
                "s, one 32-bit value"
            } else {
                ""
            },
            r.range().0,
            r.range().1
        ),
        vec![],
        vec![exchange(
            Outgoing::Pdu(read.to_vec()),
            Compare::InRange,
            "read",
        )],
    );
}

/// True where FC 03 and FC 04 read one register map: the profile lists both and has no input register of
/// its own (the SD2x: "FC 03 and FC 04 are treated identically", manual line 327).
fn one_map(cx: &Ctx) -> bool {
    cx.supports(FunctionCode::READ_HOLDING_REGISTERS)
        && cx.supports(FunctionCode::READ_INPUT_REGISTERS)
        && !cx
            .p
            .registers
            .iter()
            .any(|r| r.get_ref().table == Table::Input)
}

/// The register read with FC 04 where FC 03 and FC 04 read one map ([`one_map`]): a positive read of the
/// function the manual lists, beside the FC 03 read of `register_read`.
fn register_read_fc04(cx: &mut Ctx, r: &Register) {
    let p = cx.p;
    let pid = &p.device.id;
    cx.push(
        format!("profile/{pid}/read-fc04/{}", reg_slug(r)),
        format!("read {} with FC 04", r.name),
        format!(
            "{} register map: 0x{:04X} {}; FC 04 reads the map FC 03 reads",
            p.device.name, r.address, r.name
        ),
        format!(
            "Register 0x{:04X} is readable with Read Input Registers (FC 04), as with FC 03, and holds a value in {}..={}.",
            r.address,
            r.range().0,
            r.range().1
        ),
        vec![],
        vec![exchange(
            Outgoing::Pdu(pdu(&Request::ReadInputRegisters {
                address: r.address,
                quantity: u16::from(r.width),
            })),
            Compare::InRange,
            "read with FC 04",
        )],
    );
}

/// The precondition every write to `r` needs on the drive, whatever the value: the I/O points it drives
/// configured as outputs (MDrive), the drive enabled for a move (MCode MA, MR, SL).
fn write_precondition(cx: &Ctx, a: &mut Around, r: &Register) {
    if let Some(io) = IoPoints::of(cx.p) {
        let points = io.of_register(r);
        io.configure_outputs(cx, a, &points);
    }
    if mcode::starts_move(r) {
        mcode::enable_drive(cx, a);
    } else if r.motion {
        mcode::keep_drive_enable(cx, a);
    }
    mcode::await_calibration(cx, a, r);
}

/// After everything a write case keeps: a write to a `motion` register other than the move registers (whose
/// undo waits already) is given the time to come to rest, and stopped if it does not (the LMD's HI homes).
fn settle_after(cx: &Ctx, a: &mut Around, r: &Register) {
    if r.motion && !mcode::starts_move(r) {
        let homing = r.mnemonic.as_deref().is_some_and(mcode::homes);
        mcode::settle_motion(cx, a, homing);
    }
}

/// An in-range write is read back unchanged; the original value is read first and put back after (a move
/// is undone by moving back, an MCode DC/IC by its inverse).
fn register_write(cx: &mut Ctx, r: &Register, read: &[u8], tags: &[Tag]) {
    let p = cx.p;
    let pid = &p.device.id;
    let v = write_value(cx, r);
    let mut a = Around::new();
    write_precondition(cx, &mut a, r);
    mcode::free_partner(cx, &mut a, r);
    // An error record whose drive flags a present error condition (MCode ER and EF) is not kept: a read
    // clears it and only 0 is written to it, so the record cannot be put back (its `why`).
    let record = r.condition_flag.filter(|_| r.access.readable());
    if r.access.readable() && record.is_none() {
        a.keep_register(cx, r, Compare::InRange);
    }
    if mcode::starts_move(r) {
        mcode::undo_move(cx, &mut a, r);
    }
    mcode::undo_step_instruction(cx, &mut a, r, v);
    settle_after(cx, &mut a, r);
    let mut steps = vec![mcode::command(cx, r, v, format!("write {v}"))];
    if let Some(flag) = record {
        // Cleared, or recorded again while the flag says the error condition is still there.
        let (record_slot, flag_slot) = (a.slot(), a.slot());
        let flag_name =
            cx.p.register_at(flag, false)
                .map_or_else(|| format!("0x{flag:04X}"), |f| f.name.clone());
        steps.push(capture(
            Outgoing::Pdu(read.to_vec()),
            Compare::Structure,
            record_slot,
            format!("read back {v}"),
        ));
        steps.push(capture(
            Outgoing::Pdu(pdu(&cx.read_request(flag, 1, Table::Holding))),
            Compare::InRange,
            flag_slot,
            format!("read {flag_name} (0x{flag:04X})"),
        ));
        steps.push(Step::ClearedUnlessFlagged {
            record: record_slot,
            flag: flag_slot,
            note: format!(
                "{} reads {v}, or {flag_name} says an error condition still exists",
                r.name
            ),
        });
    } else if r.access.readable() {
        steps.push(exchange(
            Outgoing::Pdu(read.to_vec()),
            Compare::Exact,
            format!("read back {v}"),
        ));
    }
    let steps = a.wrap(steps);
    cx.push(
        format!("profile/{pid}/write/{}", reg_slug(r)),
        format!("write {} in range and read it back", r.name),
        format!("{} register map: 0x{:04X} {}", p.device.name, r.address, r.name),
        match record {
            Some(flag) => format!("Register 0x{:04X} accepts {v}, which clears it, and reads 0 after, unless register 0x{flag:04X} says an error condition still exists (which the drive may record again at once).", r.address),
            None => format!("Register 0x{:04X} accepts {v} and reads it back unchanged, in the device's word order.", r.address),
        },
        tags.to_vec(),
        steps,
    );
}

/// A value just outside the register's range (where its width leaves room) is rejected and not stored; the
/// value is read first and put back after, so that a drive that wrongly stores it is left as it was.
fn register_write_out_of_range(cx: &mut Ctx, r: &Register, read: &[u8], tags: &[Tag]) {
    let p = cx.p;
    let pid = &p.device.id;
    let (lo, hi) = r.natural_range();
    let (min, max) = r.range();
    let bad = if max < hi {
        Some(max + 1)
    } else if min > lo {
        Some(min - 1)
    } else {
        None
    };
    if let Some(b) = bad {
        let mut a = Around::new();
        write_precondition(cx, &mut a, r);
        if r.access.readable() {
            a.keep_register(cx, r, Compare::Structure);
        }
        if mcode::starts_move(r) {
            mcode::undo_move(cx, &mut a, r);
        }
        settle_after(cx, &mut a, r);
        let mut steps = vec![mcode::command(cx, r, b, format!("write {b}"))];
        if r.access.readable() {
            steps.push(exchange(
                Outgoing::Pdu(read.to_vec()),
                Compare::InRange,
                "the value is still in range",
            ));
        }
        let steps = a.wrap(steps);
        cx.push(
            format!("profile/{pid}/write-out-of-range/{}", reg_slug(r)),
            format!("write {} = {b}, outside {min}..={max}", r.name),
            format!(
                "{} register map: 0x{:04X} {} range",
                p.device.name, r.address, r.name
            ),
            format!("A value outside {min}..={max} is rejected with an exception and not stored."),
            tags.to_vec(),
            steps,
        );
    }
}

/// A write to a read-only register (one that FC 06 / FC 16 address: holding or both tables) is rejected;
/// the value is read first and put back after, so that a drive that wrongly accepts the write is left as it
/// was (a conforming drive refuses the restore as it refused the write).
fn register_write_read_only(cx: &mut Ctx, r: &Register) {
    let p = cx.p;
    let pid = &p.device.id;
    let v = r.default.unwrap_or(0);
    let mut a = Around::new();
    a.keep_register(cx, r, Compare::Structure);
    let steps = a.wrap(vec![exchange(
        Outgoing::Pdu(pdu(
            &cx.write_request(r.address, r.words(p.device.word_order, v))
        )),
        Compare::Exact,
        "write",
    )]);
    cx.push(
        format!("profile/{pid}/write-read-only/{}", reg_slug(r)),
        format!("write read-only {}", r.name),
        format!(
            "{} register map: 0x{:04X} {} (read-only)",
            p.device.name, r.address, r.name
        ),
        "A write to a read-only register is rejected with an exception.",
        vec![Tag::Write],
        steps,
    );
}

/// A read of a reserved range is answered with exception 02.
fn reserved(cx: &mut Ctx) {
    let p = cx.p;
    let pid = &p.device.id;
    for res in p.reserved.iter().map(|r| r.get_ref()) {
        if !(cx.supports(FunctionCode::READ_HOLDING_REGISTERS)
            || cx.supports(FunctionCode::READ_INPUT_REGISTERS))
        {
            break;
        }
        cx.push(
            format!("profile/{pid}/reserved/0x{:04X}", res.start),
            format!("read reserved 0x{:04X}..=0x{:04X}", res.start, res.end),
            format!("{} register map: reserved", p.device.name),
            "A read of a reserved address is answered with exception 02 (Illegal Data Address).",
            vec![],
            vec![exchange(
                Outgoing::Pdu(pdu(&cx.read_request(res.start, 1, Table::Holding))),
                Compare::Exact,
                "read",
            )],
        );
    }
}

/// Coils: write ON, read back, restore. On the MDrive the I/O point is configured as an output first (its
/// setup read with FC 0x41 and put back after).
fn coils(cx: &mut Ctx) {
    let p = cx.p;
    let pid = &p.device.id;
    let io = IoPoints::of(p);
    if cx.supports(FunctionCode::READ_COILS) {
        for c in p.coils.iter().map(|c| c.get_ref()).filter(|c| !c.confirmed) {
            cx.push(
                format!("profile/{pid}/coil-read/{}-{}", c.address, slug(&c.name)),
                format!("read {}", c.name),
                format!(
                    "{}: coil {} {} (unconfirmed)",
                    p.device.name, c.address, c.name
                ),
                "The coil is readable with Read Coils.",
                vec![],
                vec![exchange(
                    Outgoing::Pdu(pdu(&Request::ReadCoils {
                        address: c.address,
                        quantity: 1,
                    })),
                    Compare::Structure,
                    "read",
                )],
            );
        }
    }
    if cx.supports(FunctionCode::WRITE_SINGLE_COIL) && cx.supports(FunctionCode::READ_COILS) {
        for c in p
            .coils
            .iter()
            .map(|c| c.get_ref())
            .filter(|c| c.confirmed && c.access.writable())
        {
            let read = pdu(&Request::ReadCoils {
                address: c.address,
                quantity: 1,
            });
            let mut tags = vec![Tag::Write];
            if c.motion {
                tags.push(Tag::Motion);
            }
            let mut a = Around::new();
            if let Some(io) = &io {
                io.configure_outputs(cx, &mut a, &io.of_coils(c.address, 1));
            }
            a.keep_coils(cx, c.address, 1);
            let steps = a.wrap(vec![
                exchange(
                    Outgoing::Pdu(pdu(&Request::WriteSingleCoil {
                        address: c.address,
                        value: 0xFF00,
                    })),
                    Compare::Exact,
                    "ON",
                ),
                exchange(Outgoing::Pdu(read), Compare::Exact, "read back"),
            ]);
            cx.push(
                format!("profile/{pid}/coil/{}-{}", c.address, slug(&c.name)),
                format!("switch {} on and read it back", c.name),
                format!("{}: coil {} {}", p.device.name, c.address, c.name),
                "Write Single Coil ON is echoed and Read Coils then shows the coil on.",
                tags,
                steps,
            );
        }
    }
}

/// The MDrive's outputs while their I/O points are configured as inputs (the default, 000 line 1263): each
/// output is written the state it reads, so that nothing changes whether the drive takes the write (the
/// reference) or refuses it (04, 03 or 02: "the outputs must be configured as such", 000 lines 532, 579, and
/// no more is said; freedom `mdrive-output-write-while-input`), and read back unchanged. First, with the
/// point an output, the output is written the state it reads, so that the reference holds the drive's state
/// whatever the drive answers later; the setup and the output are put back after (the output while the
/// point is an output again).
fn outputs_of_input_points(cx: &mut Ctx) {
    let p = cx.p;
    let pid = &p.device.id;
    let Some(io) = IoPoints::of(p) else {
        return;
    };
    if !cx.supports(FunctionCode::WRITE_SINGLE_COIL) || !cx.supports(FunctionCode::READ_COILS) {
        return;
    }
    for (k, address) in io.points() {
        let Some(c) = p
            .coils
            .iter()
            .map(|c| c.get_ref())
            .find(|c| c.address == address && c.confirmed && c.access.writable() && !c.motion)
        else {
            continue;
        };
        let read = || {
            Outgoing::Pdu(pdu(&Request::ReadCoils {
                address: c.address,
                quantity: 1,
            }))
        };
        let mut a = Around::new();
        io.configure_outputs(cx, &mut a, &[k]);
        let slot = a.slot();
        a.set(capture(
            read(),
            Compare::Structure,
            slot,
            format!("read output {k} first"),
        ));
        a.set(exchange(
            Outgoing::RestoreRead { slot },
            Compare::Exact,
            format!("write output {k} the state it has, point {k} an output"),
        ));
        a.undo(vec![exchange(
            Outgoing::RestoreRead { slot },
            Compare::Exact,
            format!("put back output {k}"),
        )]);
        io.configure_inputs(cx, &mut a, &[k]);
        let steps = a.wrap(vec![
            exchange(
                Outgoing::RestoreRead { slot },
                Compare::Exact,
                format!(
                    "write output {k} the state it has, point {k} an input: taken, or refused with 04, 03 or 02"
                ),
            ),
            exchange(read(), Compare::Exact, "read back: unchanged"),
        ]);
        cx.push(
            format!("profile/{pid}/io-point/{k}/write-output-while-input"),
            format!("write {} while I/O point {k} is an input", c.name),
            format!(
                "{}: coil {} {} with S{k} an input",
                p.device.name, c.address, c.name
            ),
            "A write of an output whose I/O point is configured as an input is taken or refused (the manual leaves it open); the output reads back unchanged.",
            vec![Tag::Write],
            steps,
        );
    }
    outputs_as_a_group_of_input_points(cx, &io);
}

/// The same for the outputs written as a group (OT, OL), every point an input: the group register is written
/// the value it reads, taken or refused (freedom `mdrive-output-group-write-while-input`, a choice of its
/// own), and read back unchanged.
fn outputs_as_a_group_of_input_points(cx: &mut Ctx, io: &IoPoints) {
    let p = cx.p;
    let pid = &p.device.id;
    if !cx.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS) {
        return;
    }
    let Some(r) = p.registers.iter().map(|r| r.get_ref()).find(|r| {
        r.mnemonic
            .as_deref()
            .is_some_and(|m| m.eq_ignore_ascii_case("OT"))
            && r.access.writable()
            && !r.motion
    }) else {
        return;
    };
    let all: Vec<usize> = io.points().map(|(k, _)| k).collect();
    let read = || {
        Outgoing::Pdu(pdu(&Request::ReadHoldingRegisters {
            address: r.address,
            quantity: 1,
        }))
    };
    let mut a = Around::new();
    io.configure_outputs(cx, &mut a, &all);
    let slot = a.slot();
    a.set(capture(
        read(),
        Compare::Structure,
        slot,
        format!("read {} first", r.name),
    ));
    a.set(exchange(
        Outgoing::RestoreRead { slot },
        Compare::Exact,
        "write the outputs the states they have, every point an output",
    ));
    a.undo(vec![exchange(
        Outgoing::RestoreRead { slot },
        Compare::Exact,
        format!("put back {}", r.name),
    )]);
    io.configure_inputs(cx, &mut a, &all);
    let steps = a.wrap(vec![
        exchange(
            Outgoing::RestoreRead { slot },
            Compare::Exact,
            "write the outputs as a group the states they have, every point an input: taken, or refused with 04, 03 or 02",
        ),
        exchange(read(), Compare::Exact, "read back: unchanged"),
    ]);
    cx.push(
        format!("profile/{pid}/io-point/group/write-outputs-while-inputs"),
        format!("write {} while every I/O point is an input", r.name),
        format!(
            "{}: register {:#06X} {} with S1-S{} inputs",
            p.device.name,
            r.address,
            r.name,
            all.len()
        ),
        "A write of the outputs as a group while the I/O points are configured as inputs is taken or refused (the manual leaves it open); the outputs read back unchanged.",
        vec![Tag::Write],
        steps,
    );
}

/// Each discrete input is readable.
fn discrete_inputs(cx: &mut Ctx) {
    let p = cx.p;
    let pid = &p.device.id;
    if cx.supports(FunctionCode::READ_DISCRETE_INPUTS) {
        for d in p.discrete_inputs.iter().map(|c| c.get_ref()) {
            cx.push(
                format!(
                    "profile/{pid}/discrete-input/{}-{}",
                    d.address,
                    slug(&d.name)
                ),
                format!("read {}", d.name),
                format!("{}: discrete input {} {}", p.device.name, d.address, d.name),
                "The input is readable with Read Discrete Inputs.",
                vec![],
                vec![exchange(
                    Outgoing::Pdu(pdu(&Request::ReadDiscreteInputs {
                        address: d.address,
                        quantity: 1,
                    })),
                    Compare::Structure,
                    "read",
                )],
            );
        }
        inputs_agree_with_registers(cx);
    }
}

/// The discrete inputs read with FC 02 and the registers that mirror them one each (the MDrive's and LMD's
/// I1-I4: "Read input 1" ...) hold the same states: an input in the wrong bit of the FC 02 byte shows. Only
/// where every input has its register, at consecutive addresses.
fn inputs_agree_with_registers(cx: &mut Ctx) {
    let p = cx.p;
    let pid = &p.device.id;
    let mut inputs: Vec<u16> = p
        .discrete_inputs
        .iter()
        .map(|d| d.get_ref().address)
        .collect();
    inputs.sort_unstable();
    let (Some(&first), n) = (inputs.first(), inputs.len()) else {
        return;
    };
    let mirror = |k: usize| {
        p.registers.iter().map(|r| r.get_ref()).find(|r| {
            r.width == 1
                && r.access.readable()
                && r.mnemonic
                    .as_deref()
                    .is_some_and(|m| m.eq_ignore_ascii_case(&format!("I{k}")))
        })
    };
    let Some(regs) = (1..=n).map(mirror).collect::<Option<Vec<_>>>() else {
        return;
    };
    let start = regs[0].address;
    if n < 2
        || inputs.windows(2).any(|w| w[1] != w[0] + 1)
        || regs
            .iter()
            .enumerate()
            .any(|(i, r)| r.address != start + i as u16)
    {
        return;
    }
    // Two inputs at a time, each register read alone: both manuals' prose says a parameter needs no more than
    // one request (MDrive lines 616 and 660, LMD lines 898-902), and a drive may refuse a read over two
    // (`multi-item-access`); the FC 02 read of the same two inputs is compared with both registers, so that
    // the two inputs' order is seen.
    let mut steps = Vec::new();
    let mut slot = 0;
    for k in (0..n).step_by(2) {
        let quantity = (n - k).min(2);
        let regs: Vec<usize> = (slot..slot + quantity).collect();
        let bits = slot + quantity;
        slot = bits + 1;
        for (j, &s) in regs.iter().enumerate() {
            steps.push(capture(
                Outgoing::Pdu(pdu(&cx.read_request(
                    start + (k + j) as u16,
                    1,
                    Table::Holding,
                ))),
                Compare::InRange,
                s,
                format!("read I{}", k + j + 1),
            ));
        }
        steps.push(capture(
            Outgoing::Pdu(pdu(&Request::ReadDiscreteInputs {
                address: first + k as u16,
                quantity: quantity as u16,
            })),
            Compare::Structure,
            bits,
            format!("read inputs {}-{}", k + 1, k + quantity),
        ));
        steps.push(Step::Agree {
            registers: regs[0],
            more_registers: regs[1..].to_vec(),
            object: bits,
            note: "each input has its register's state".into(),
        });
    }
    cx.push(
        format!("profile/{pid}/discrete-input/agree-with-registers"),
        format!("inputs 1-{n} read with FC 02 and as registers I1-I{n} agree"),
        format!(
            "{}: discrete inputs {first:#06X}.. and registers I1-I{n} at {start:#06X}..",
            p.device.name
        ),
        "Input k read with Read Discrete Inputs (bit k-1 of the answer, spec 6.2) has the state register Ik reads (0 off, 1 on).",
        vec![],
        steps,
    );
}

/// Vendor mnemonics: each readable one read, each writable one written with the manual's example, and
/// an unknown one refused.
fn mnemonics(cx: &mut Ctx) {
    let p = cx.p;
    let pid = &p.device.id;
    for m in p.mnemonics.iter().map(|m| m.get_ref()) {
        let Some(w) = Mnemonic::from_name(&m.name) else {
            continue;
        };
        if m.read && cx.supports(FunctionCode::VENDOR_READ) {
            cx.push(
                format!("profile/{pid}/mnemonic/{}/read", slug(&m.name)),
                format!("FC 0x41 read of {}", m.name),
                format!("{}: vendor FC 0x41, mnemonic {}", p.device.name, m.name),
                "A readable mnemonic is answered with its parameter string.",
                vec![],
                vec![exchange(
                    Outgoing::Pdu(pdu(&Request::VendorRead { mnemonic: w })),
                    Compare::Structure,
                    "read",
                )],
            );
        }
        if m.write
            && cx.supports(FunctionCode::VENDOR_WRITE)
            && let Some(ex) = &m.example
        {
            let mut tags = vec![Tag::Write];
            if m.motion {
                tags.push(Tag::Motion);
            }
            if m.destructive {
                tags.push(Tag::Destructive);
            }
            // A setting is read first and put back after; a program command starts from no program running
            // and ends the program it started.
            let mut a = Around::new();
            if m.motion {
                mcode::keep_drive_enable(cx, &mut a);
            }
            a.keep_setting(cx, &m.name);
            mcode::program_command(cx, &mut a, &mut tags, &m.name);
            // A write that can move the motor (the LMD's HF homes) is given the time to come to rest, and
            // stopped if it does not, before anything is put back.
            if m.motion {
                mcode::settle_motion(cx, &mut a, mcode::homes(&m.name));
            }
            let mut steps = vec![exchange(
                Outgoing::Pdu(pdu(&Request::VendorWrite {
                    mnemonic: w,
                    params: ex.as_bytes().to_vec(),
                })),
                Compare::Exact,
                "write",
            )];
            // A setting (R/W in the manual's table) reads back what was written: the values, compared with
            // the reference's after the same write (their formatting is the freedom
            // `fc41-read-back-format`; numbers compare as numbers). Not the program commands, which FC 0x41
            // may run (`mdrive-program-control-function`).
            let setting = m.read
                && cx.supports(FunctionCode::VENDOR_READ)
                && ex.trim_start().starts_with('=')
                && !mcode::is_program_command(&m.name);
            if setting {
                steps.push(exchange(
                    Outgoing::Pdu(pdu(&Request::VendorRead { mnemonic: w })),
                    Compare::Exact,
                    "read back",
                ));
            }
            let steps = a.wrap(steps);
            cx.push(
                format!("profile/{pid}/mnemonic/{}/write", slug(&m.name)),
                format!("FC 0x42 write of {}{}", m.name, ex),
                format!("{}: vendor FC 0x42, mnemonic {}", p.device.name, m.name),
                if setting {
                    "A writable mnemonic accepts the manual's example parameters and echoes the mnemonic; the setting then reads back (FC 0x41) with the values written."
                } else {
                    "A writable mnemonic accepts the manual's example parameters and echoes the mnemonic."
                },
                tags,
                steps,
            );
        }
    }
    let unknown = Mnemonic::from_name("QQ").expect("2 ASCII bytes");
    // Only a profile that lists mnemonics says what the drive does with one it does not know; a draft
    // knows no mnemonics, and what the generic model answers to FC 0x41 is not the drive's.
    if cx.supports(FunctionCode::VENDOR_READ) && !p.mnemonics.is_empty() {
        cx.push(
            format!("profile/{pid}/mnemonic/unknown/read"),
            "FC 0x41 read of an unknown mnemonic",
            format!("{}: vendor FC 0x41", p.device.name),
            "A mnemonic the drive does not know is answered with an exception.",
            vec![],
            vec![exchange(
                Outgoing::Pdu(pdu(&Request::VendorRead { mnemonic: unknown })),
                Compare::Exact,
                "QQ",
            )],
        );
    }
    // A known mnemonic in lower case: served, or refused as unknown (`mnemonic-letter-case`). A read of
    // a setting: nothing changes.
    let lower = p
        .mnemonics
        .iter()
        .map(|m| m.get_ref())
        .filter(|m| m.read && !m.motion && !m.destructive)
        .find_map(|m| Mnemonic::from_name(&m.name.to_ascii_lowercase()).map(|w| (m, w)));
    // A known mnemonic padded with NUL where the manuals print spaces: refused as unknown, or read as the
    // mnemonic it pads (`mnemonic-padding`). A read of a setting of fewer than four letters: nothing changes.
    let padded = p
        .mnemonics
        .iter()
        .map(|m| m.get_ref())
        .filter(|m| m.read && !m.motion && !m.destructive && m.name.len() < 4)
        .find_map(|m| {
            let mut w = Mnemonic::from_name(&m.name)?;
            w.0[0] = 0;
            Some((m, w))
        });
    if let Some((m, w)) = padded.filter(|_| cx.supports(FunctionCode::VENDOR_READ)) {
        cx.push(
            format!("profile/{pid}/mnemonic/nul-padding/read"),
            format!("FC 0x41 read of {} padded with NUL", m.name),
            format!("{}: vendor FC 0x41, mnemonic {}", p.device.name, m.name),
            "A known mnemonic padded with NUL instead of spaces is refused as an unknown one, or read as the mnemonic it pads, the same way each time.",
            vec![],
            vec![exchange(
                Outgoing::Pdu(pdu(&Request::VendorRead { mnemonic: w })),
                Compare::Structure,
                format!("{} with a NUL in its padding", m.name),
            )],
        );
    }
    if let Some((m, w)) = lower.filter(|_| cx.supports(FunctionCode::VENDOR_READ)) {
        cx.push(
            format!("profile/{pid}/mnemonic/letter-case/read"),
            format!("FC 0x41 read of {} in lower case", m.name),
            format!("{}: vendor FC 0x41, mnemonic {}", p.device.name, m.name),
            "A known mnemonic named in lower case is read as in upper case, or refused as an unknown one, the same way each time.",
            vec![],
            vec![exchange(
                Outgoing::Pdu(pdu(&Request::VendorRead { mnemonic: w })),
                Compare::Structure,
                format!("{} in lower case", m.name),
            )],
        );
    }
}

/// Device identification: the basic and regular streams, and an object the device does not have (only when
/// every object is confirmed: a probe cannot tell which objects a device lacks, nor how it refuses them).
fn identification(cx: &mut Ctx) {
    let p = cx.p;
    let pid = &p.device.id;
    if cx.supports(FunctionCode::ENCAPSULATED_INTERFACE) && !p.identification.is_empty() {
        for (code, label) in [(1u8, "basic"), (2, "regular")] {
            cx.push(
                format!("profile/{pid}/identification/{label}"),
                format!("read device identification, {label} stream"),
                format!("{APP}, section 6.21; {} device id", p.device.name),
                "Read Device Identification returns the objects of the requested category with a consistent object list.",
                vec![],
                vec![exchange(
                    Outgoing::Pdu(pdu(&Request::ReadDeviceId { read_code: code, object_id: 0 })),
                    Compare::Structure,
                    label,
                )],
            );
        }
        if p.identification.iter().any(|o| !o.confirmed) {
            return;
        }
        cx.push(
            format!("profile/{pid}/identification/individual-missing"),
            "read an individual identification object that does not exist",
            format!("{APP}, section 6.21"),
            "An individual access to an object id the device does not have is answered with exception 02.",
            vec![],
            vec![exchange(
                Outgoing::Pdu(pdu(&Request::ReadDeviceId { read_code: 4, object_id: 0x7F })),
                Compare::Exact,
                "object 0x7F",
            )],
        );
    }
}

/// The id segment of a register: its address and its mnemonic (or name).
fn reg_slug(r: &Register) -> String {
    match &r.mnemonic {
        Some(m) => format!("0x{:04X}-{}", r.address, slug(m)),
        None => format!("0x{:04X}-{}", r.address, slug(&r.name)),
    }
}

/// The in-range value a write case uses: the smallest change from the default that a conforming drive
/// accepts (some registers take only some values of their range: the MDrive's microstep resolution MS
/// takes those of its table, so 255 next to the default 256 is refused); the reference drive says which.
pub(super) fn write_value(cx: &Ctx, r: &Register) -> i64 {
    let (min, max) = r.range();
    // Where the manual gives the range two ways, only a value every reading takes.
    let candidates: Vec<i64> = match r.default {
        _ if !r.safe_values.is_empty() => r.safe_values.clone(),
        Some(d) => vec![d + 1, d - 1, d / 2, d.saturating_mul(2), min, max, d],
        None => vec![min + (max - min) / 2, min, max],
    };
    let accepted = |v: &i64| {
        (min..=max).contains(v)
            && cx.reference_accepts(
                &cx.write_request(r.address, r.words(cx.p.device.word_order, *v)),
            )
    };
    candidates
        .iter()
        .copied()
        .find(|v| accepted(v) && Some(*v) != r.default)
        .or(r.default.filter(|d| (min..=max).contains(d)))
        .unwrap_or(candidates[0])
}

/// True when a freedom of the corpus for profile `pid` is about this register or mnemonic (a product may
/// lack it, or give it another access): the cases below use entries every admissible drive has, as the
/// manual gives them. A freedom of another profile is not about this one's entries (the LMD's S5, which an
/// LMD may refuse, is a documented MDrive setting).
fn freedom_item(pid: &str, register: Option<u16>, mnemonic: Option<&str>) -> bool {
    let Ok(requirements) = drives::corpus::Corpus::Embedded.requirements_shared() else {
        return true;
    };
    requirements
        .freedoms()
        .iter()
        .filter(|f| f.applies_to(pid))
        .any(|f| {
            f.items.iter().any(|i| {
                (register.is_some() && i.register == register)
                    || mnemonic.is_some_and(|m| i.mnemonic.as_deref() == Some(m))
            })
        })
}

/// Reads and a write of one half of a 32-bit register (freedoms `partial-register-read`,
/// `partial-register-write`: the manuals map 4-byte items to two registers and say nothing of halves; the
/// spec allows 02, 03 or 04 for "the combination of reference number and transfer length is invalid").
/// Any admissible answer passes, and the choice log holds the drive to one answer for both halves. The
/// write uses a parameter register (no motion, nothing non-volatile), read first and put back after.
fn half_registers(cx: &mut Ctx) {
    let p = cx.p;
    let pid = &p.device.id;
    let plain = |r: &&Register| {
        r.width == 2
            && r.confirmed
            && r.table != Table::Input
            && r.access.readable()
            && !freedom_item(pid, Some(r.address), None)
    };
    if cx.supports(FunctionCode::READ_HOLDING_REGISTERS)
        && let Some(r) = p.registers.iter().map(|r| r.get_ref()).find(plain)
    {
        let half = |address: u16| {
            Outgoing::Pdu(pdu(&Request::ReadHoldingRegisters {
                address,
                quantity: 1,
            }))
        };
        cx.push(
            format!("profile/{pid}/half-register/read/{}", reg_slug(r)),
            format!("read each half of {} alone", r.name),
            format!(
                "{} register map: 0x{:04X} {} (two registers, one 32-bit value); spec §7 exception 02",
                p.device.name, r.address, r.name
            ),
            format!(
                "A read of one register of the 32-bit pair 0x{:04X}-0x{:04X} is answered with that register, \
                 or refused with 02, 03 or 04; the drive gives the same answer for either half.",
                r.address,
                r.address + 1
            ),
            vec![],
            vec![
                exchange(half(r.address), Compare::Structure, "the first half"),
                exchange(half(r.address + 1), Compare::Structure, "the second half"),
            ],
        );
    }
    let watchdog = p.watchdog.as_ref().map(|w| w.register);
    if cx.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS)
        && let Some(r) = p.registers.iter().map(|r| r.get_ref()).find(|r| {
            plain(r)
                && r.access.writable()
                && !r.motion
                && !r.destructive
                && Some(r.address) != watchdog
                && !super::mcode::starts_move(r)
        })
    {
        let words = r.words(p.device.word_order, r.default.unwrap_or(r.range().0));
        let mut a = Around::new();
        a.keep_register(cx, r, Compare::InRange);
        let read = pdu(&cx.read_request(r.address, 2, Table::Holding));
        let steps = a.wrap(vec![
            exchange(
                Outgoing::Pdu(pdu(&Request::WriteMultipleRegisters {
                    address: r.address,
                    values: vec![words[0]],
                })),
                Compare::Exact,
                "write the first half alone",
            ),
            exchange(
                Outgoing::Pdu(pdu(&Request::WriteMultipleRegisters {
                    address: r.address + 1,
                    values: vec![words[1]],
                })),
                Compare::Exact,
                "write the second half alone",
            ),
            exchange(
                Outgoing::Pdu(read),
                Compare::InRange,
                "the pair still holds a value in range",
            ),
        ]);
        cx.push(
            format!("profile/{pid}/half-register/write/{}", reg_slug(r)),
            format!("write each half of {} alone", r.name),
            format!(
                "{} register map: 0x{:04X} {} (two registers, one 32-bit value); spec §7 exception 02",
                p.device.name, r.address, r.name
            ),
            format!(
                "A write of one register of the 32-bit pair 0x{:04X}-0x{:04X} is refused with 02, 03 or 04 \
                 (or taken and echoed as written); the drive gives the same answer for either half, and the \
                 pair holds a value in range after.",
                r.address,
                r.address + 1
            ),
            write_tags(r),
            steps,
        );
    }
}

/// A read over two items of the register map in one request (freedom `multi-item-access`: both manuals say
/// a parameter needs no more than one request, MDrive line 616, LMD lines 898-902; the spec allows 02, 03 or
/// 04 for "the combination of reference number and transfer length is invalid"). Two adjacent plain
/// parameters, within the device's quantity limit; any admissible answer passes, and the choice log holds
/// the drive to it for every other such read or write.
fn multi_item_read(cx: &mut Ctx) {
    let p = cx.p;
    let pid = &p.device.id;
    let applies = drives::corpus::Corpus::Embedded
        .freedom_applies(drives::choices::ids::MULTI_ITEM_ACCESS, pid);
    let limit = p
        .function(FunctionCode::READ_HOLDING_REGISTERS)
        .and_then(|f| f.max_quantity)
        .unwrap_or(125);
    if !applies || !cx.supports(FunctionCode::READ_HOLDING_REGISTERS) {
        return;
    }
    let plain = |r: &Register| {
        r.confirmed
            && r.table != Table::Input
            && r.access.readable()
            && !r.read_clears
            && !r.width_disputed
            && !freedom_item(pid, Some(r.address), None)
    };
    let regs: Vec<&Register> = p.registers.iter().map(|r| r.get_ref()).collect();
    let Some((a, b)) = regs.iter().find_map(|a| {
        let b = regs.iter().find(|b| u32::from(b.address) == a.end())?;
        (plain(a) && plain(b) && u16::from(a.width) + u16::from(b.width) <= limit)
            .then_some((*a, *b))
    }) else {
        return;
    };
    let quantity = u16::from(a.width) + u16::from(b.width);
    cx.push(
        format!("profile/{pid}/multi-item/read/{}-{}", reg_slug(a), reg_slug(b)),
        format!("read {} and {} in one request", a.name, b.name),
        format!(
            "{} register map: 0x{:04X} {} and 0x{:04X} {}; spec §7 exception 02",
            p.device.name, a.address, a.name, b.address, b.name
        ),
        format!(
            "A read of the two parameters 0x{:04X}-0x{:04X} in one request is answered with both, or refused \
             with 02, 03 or 04; the drive gives the same answer to every read or write over several parameters.",
            a.address,
            u32::from(a.address) + u32::from(quantity) - 1
        ),
        vec![],
        vec![exchange(
            Outgoing::Pdu(pdu(&cx.read_request(a.address, quantity, Table::Holding))),
            Compare::Structure,
            "both parameters",
        )],
    );
}

/// FC 0x41 of a write-only mnemonic and FC 0x42 of a read-only one (freedom `mnemonic-access-exception`:
/// the manuals mark the access, MDrive lines 715-721 and LMD lines 1052-1108, and allow exceptions 01-04,
/// MDrive lines 958-962), and FC 0x42 with a parameter string the mnemonic does not take (freedom
/// `mnemonic-bad-parameter-exception`). Only mnemonics the profile flags neither motion nor destructive
/// (a read of an MDrive program command may act: its manual prints FC 0x41 for them), not items of a
/// freedom; the read-only one is written with the value just read from it, the setting read first and put
/// back after.
fn mnemonic_refusals(cx: &mut Ctx) {
    let p = cx.p;
    let pid = &p.device.id;
    let plain = |m: &&drives::profile::VendorMnemonic| {
        !m.motion && !m.destructive && !freedom_item(pid, None, Some(&m.name))
    };
    let mnemonics = || p.mnemonics.iter().map(|m| m.get_ref());
    if cx.supports(FunctionCode::VENDOR_READ)
        && let Some(m) = mnemonics().filter(plain).find(|m| m.write && !m.read)
        && let Some(w) = Mnemonic::from_name(&m.name)
    {
        // <ESC> (0x1B) has no letters for an id.
        let (id, shown) = match slug(&m.name) {
            s if s.is_empty() => (
                hex::encode(m.name.as_bytes()),
                format!("<{}>", m.name.escape_default()),
            ),
            s => (s, m.name.clone()),
        };
        let (id, shown) = if m.name == "\u{1b}" {
            ("esc".to_string(), "<ESC>".to_string())
        } else {
            (id, shown)
        };
        cx.push(
            format!("profile/{pid}/mnemonic/{id}/read-write-only"),
            format!("FC 0x41 of the write-only {shown} is refused"),
            format!("{}: vendor FC 0x41, mnemonic {shown} (W/O)", p.device.name),
            "A mnemonic the manual marks write-only is not read: FC 0x41 is answered with an exception (01-04).",
            vec![],
            vec![exchange(
                Outgoing::Pdu(pdu(&Request::VendorRead { mnemonic: w })),
                Compare::Exact,
                "read a write-only mnemonic",
            )],
        );
    }
    if cx.supports(FunctionCode::VENDOR_READ)
        && cx.supports(FunctionCode::VENDOR_WRITE)
        && let Some(m) = mnemonics().filter(plain).find(|m| m.read && !m.write)
        && let Some(w) = Mnemonic::from_name(&m.name)
    {
        cx.push(
            format!("profile/{pid}/mnemonic/{}/write-read-only", slug(&m.name)),
            format!("FC 0x42 of the read-only {} is refused", m.name),
            format!("{}: vendor FC 0x42, mnemonic {} (R/O)", p.device.name, m.name),
            "A mnemonic the manual marks read-only is not written: FC 0x42 (with the value it reads) is answered \
             with an exception (01-04).",
            vec![Tag::Write],
            vec![
                super::capture(
                    Outgoing::Pdu(pdu(&Request::VendorRead { mnemonic: w })),
                    Compare::Structure,
                    0,
                    "read it",
                ),
                exchange(
                    Outgoing::RestoreRead { slot: 0 },
                    Compare::Exact,
                    "write the value read back to it",
                ),
            ],
        );
    }
    if cx.supports(FunctionCode::VENDOR_READ)
        && cx.supports(FunctionCode::VENDOR_WRITE)
        && let Some(m) = mnemonics()
            .filter(plain)
            .find(|m| m.read && m.write && m.example.is_some() && m.register.is_none())
        && let Some(w) = Mnemonic::from_name(&m.name)
    {
        let mut a = Around::new();
        a.keep_setting(cx, &m.name);
        let steps = a.wrap(vec![exchange(
            Outgoing::Pdu(pdu(&Request::VendorWrite {
                mnemonic: w,
                params: b"=Q".to_vec(),
            })),
            Compare::Exact,
            "write a parameter that is no number",
        )]);
        cx.push(
            format!("profile/{pid}/mnemonic/{}/bad-parameter", slug(&m.name)),
            format!("FC 0x42 of {}=Q is refused", m.name),
            format!(
                "{}: vendor FC 0x42, mnemonic {} (parameters: {})",
                p.device.name,
                m.name,
                m.format.as_deref().unwrap_or("numbers")
            ),
            "A parameter string the mnemonic does not take (no number) is answered with an exception (02-04) \
             and nothing is written.",
            vec![Tag::Write],
            steps,
        );
    }
    // The manual's example of a setting without its leading '=': refused as a bad parameter, or taken as if
    // the '=' were there (`setting-equals-sign`); and with a tab after the '='. The setting is read first and
    // put back after each.
    if cx.supports(FunctionCode::VENDOR_READ)
        && cx.supports(FunctionCode::VENDOR_WRITE)
        && let Some((m, values)) = mnemonics()
            .filter(plain)
            .filter(|m| m.read && m.write && m.register.is_none())
            .find_map(|m| {
                let values = m.example.as_deref()?.strip_prefix('=')?;
                (!values.trim().is_empty()).then_some((m, values))
            })
        && let Some(w) = Mnemonic::from_name(&m.name)
    {
        // (the id's last part, the title, what the step sends and says, the requirement)
        let cases = [
            (
                "no-equals-sign",
                format!("FC 0x42 of {} {values} without the '='", m.name),
                values.to_string(),
                format!("write the manual's example \"{values}\" without its '='"),
                "A setting's values written without the leading '=' the manual prints are refused as a bad \
                 parameter, or taken as if the '=' were there, the same way each time.",
            ),
            // And with a tab between the '=' and the values: refused as a bad parameter, or read as a blank
            // (`parameter-blank-controls`).
            (
                "blank-control",
                format!("FC 0x42 of {}=<TAB>{values}", m.name),
                format!("=\t{values}"),
                format!("write the manual's example \"={values}\" with a tab after the '='"),
                "A parameter string with a control character a text parser reads as a blank (a tab) is refused \
                 as a bad parameter, or read with a space for it, the same way each time.",
            ),
        ];
        for (last, title, params, note, requirement) in cases {
            let mut a = Around::new();
            a.keep_setting(cx, &m.name);
            let steps = a.wrap(vec![exchange(
                Outgoing::Pdu(pdu(&Request::VendorWrite {
                    mnemonic: w,
                    params: params.into_bytes(),
                })),
                Compare::Exact,
                note,
            )]);
            cx.push(
                format!("profile/{pid}/mnemonic/{}/{last}", slug(&m.name)),
                title,
                format!(
                    "{}: vendor FC 0x42, mnemonic {} (parameters: {})",
                    p.device.name,
                    m.name,
                    m.format.as_deref().unwrap_or("numbers")
                ),
                requirement,
                vec![Tag::Write],
                steps,
            );
        }
    }
}
