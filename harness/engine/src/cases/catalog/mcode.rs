//! What the MCode drives (MDrive, LMD: profiles with the MCode mnemonics and registers) need around a case
//! before it can be judged against the reference, from their manuals: MDrive `000_b25109cd5b573b4c.txt`
//! ("000"), LMD `001_aafa6838846abfce.txt` ("001"); line numbers are lines of those files. Everything here is
//! keyed by mnemonic and does nothing for a profile without it.

use std::time::Duration;

use super::around::Around;
use super::{Ctx, exchange, pdu};
use crate::cases::{Compare, Outgoing, Step, Tag};
use codec::{FunctionCode, Mnemonic, Request};
use drives::profile::{Access, Profile, Register};

/// FC 0x42 setup of an I/O point as a general purpose output, active low, sinking (000 lines 743-759).
const OUTPUT_SETUP: &str = "=16,0,0";

/// FC 0x42 setup of an I/O point as a general purpose input, active low, sinking: the default (000 line 1263).
const INPUT_SETUP: &str = "=0,0,0";

/// How long a one-step move (or the stop of a slew) is given to end before the next move command: a drive
/// refuses a move while one runs. One step takes 1 ms at the reference's initial velocity (VI = 1000).
const MOVE_SETTLE: Duration = Duration::from_millis(250);

/// The MDrive's I/O points, shared between inputs and outputs and configured with S1-S4 (FC 0x42): "The
/// outputs must be configured as such" (000 lines 532, 579), "By default the I/O points are configured as
/// general purpose inputs" (000 line 1263). Point k is coil k and discrete input k in address order, and
/// registers Ik / Ok. A profile has them when it says so (`device.shared_io_points`) and has a setup mnemonic
/// S1..Sn for its n coils and n discrete inputs (the LMD's outputs are outputs of their own, set up per line
/// with OS, which FC 0x41 cannot read back line by line: they are not reconfigured; its S1-S4 set up inputs).
pub(super) struct IoPoints {
    coils: Vec<u16>,
}

impl IoPoints {
    /// The profile's I/O points, if it has shared ones (and FC 0x41 / 0x42 to set them up and back).
    pub(super) fn of(p: &Profile) -> Option<Self> {
        let mut coils: Vec<u16> = p.coils.iter().map(|c| c.get_ref().address).collect();
        coils.sort_unstable();
        let n = coils.len();
        let shared = n > 0
            && p.device.shared_io_points
            && p.function(FunctionCode::VENDOR_READ).is_some()
            && p.function(FunctionCode::VENDOR_WRITE).is_some()
            && p.discrete_inputs.len() == n
            && (1..=n).all(|k| {
                p.mnemonic(&format!("S{k}"))
                    .is_some_and(|m| m.read && m.write)
            });
        shared.then_some(Self { coils })
    }

    /// The points (1-based) a coil write at `address` of `count` coils drives.
    pub(super) fn of_coils(&self, address: u16, count: u16) -> Vec<usize> {
        let end = u32::from(address) + u32::from(count);
        self.coils
            .iter()
            .enumerate()
            .filter(|(_, a)| u32::from(**a) >= u32::from(address) && u32::from(**a) < end)
            .map(|(i, _)| i + 1)
            .collect()
    }

    /// The points a register write drives: Ok → point k; OT and OL (all outputs as a group) → every point.
    pub(super) fn of_register(&self, r: &Register) -> Vec<usize> {
        let Some(m) = r.mnemonic.as_deref() else {
            return vec![];
        };
        let m = m.to_ascii_uppercase();
        if m == "OT" || m == "OL" {
            return (1..=self.coils.len()).collect();
        }
        m.strip_prefix('O')
            .and_then(|k| k.parse::<usize>().ok())
            .filter(|k| (1..=self.coils.len()).contains(k))
            .map_or_else(Vec::new, |k| vec![k])
    }

    /// The points, 1-based, with their coils.
    pub(super) fn points(&self) -> impl Iterator<Item = (usize, u16)> + '_ {
        self.coils.iter().enumerate().map(|(i, a)| (i + 1, *a))
    }

    /// Configure `points` as general purpose outputs for the case: keep each setup (FC 0x41), write the
    /// output setup (FC 0x42), and put the setups back after.
    pub(super) fn configure_outputs(&self, cx: &Ctx, a: &mut Around, points: &[usize]) {
        self.configure(cx, a, points, OUTPUT_SETUP, "output");
    }

    /// Configure `points` as general purpose inputs (the default), kept and put back as
    /// [`configure_outputs`](Self::configure_outputs) does.
    pub(super) fn configure_inputs(&self, cx: &Ctx, a: &mut Around, points: &[usize]) {
        self.configure(cx, a, points, INPUT_SETUP, "input");
    }

    fn configure(&self, cx: &Ctx, a: &mut Around, points: &[usize], setup: &str, what: &str) {
        for k in points {
            let name = format!("S{k}");
            let Some(mnemonic) = Mnemonic::from_name(&name) else {
                continue;
            };
            a.keep_setting(cx, &name);
            a.set(exchange(
                Outgoing::Pdu(pdu(&Request::VendorWrite {
                    mnemonic,
                    params: setup.as_bytes().to_vec(),
                })),
                Compare::Structure,
                format!("configure I/O point {k} as a general purpose {what} ({name}{setup})"),
            ));
        }
    }
}

/// The register entry with mnemonic `m`.
fn register<'a>(p: &'a Profile, m: &str) -> Option<&'a Register> {
    p.registers.iter().map(|r| r.get_ref()).find(|r| {
        r.mnemonic
            .as_deref()
            .is_some_and(|x| x.eq_ignore_ascii_case(m))
    })
}

fn is(r: &Register, m: &str) -> bool {
    r.mnemonic
        .as_deref()
        .is_some_and(|x| x.eq_ignore_ascii_case(m))
}

/// A write of `value` to `r`, in the profile's word order.
fn write(cx: &Ctx, r: &Register, value: i64, note: impl Into<String>) -> Step {
    exchange(
        Outgoing::Pdu(pdu(
            &cx.write_request(r.address, r.words(cx.p.device.word_order, value))
        )),
        Compare::Exact,
        note,
    )
}

/// True for a register whose write starts a move: MA, MR, SL (000 lines 1072, 1074, 1114), and HM, which
/// may (freedom `mdrive-inferred-read-write`: "Sets the behavior of the axis for homing routines", no
/// default, and the MCode homing instruction; 000 line 1055, 001 line 2104).
pub(super) fn starts_move(r: &Register) -> bool {
    ["MA", "MR", "SL", "HM"].iter().any(|m| is(r, m))
}

/// How long a move command refused as busy (exception 04 or 06) is sent again, every [`REST_POLL`]: a
/// drive may refuse a move while it still moves or calibrates (an MDrive Hybrid calibrates for CT ms after its
/// bridge is re-enabled, its microstep resolution changed or hybrid mode enabled, 000 line 1134; CT's default
/// is 200 ms, 000 line 1142), and the manuals leave it free to (exception 04, 000 lines 427-430).
const BUSY_WITHIN: Duration = Duration::from_secs(5);

/// The write of `value` to `r` as a case sends it: a command that starts a move ([`starts_move`]) is sent
/// again while the drive refuses it as busy ([`Step::Persist`], [`BUSY_WITHIN`] at most); any other write
/// once, compared exactly.
pub(super) fn command(cx: &Ctx, r: &Register, value: i64, note: impl Into<String>) -> Step {
    let step = write(cx, r, value, note);
    match step {
        Step::Exchange {
            send,
            compare,
            capture: None,
            note,
        } if starts_move(r) => Step::Persist {
            send,
            compare,
            every: REST_POLL,
            within: BUSY_WITHIN,
            note,
        },
        other => other,
    }
}

/// How long the axis is given to come to rest after a move a case started, read every [`REST_POLL`]: a
/// homing runs until its switch is found (000 line 1055), longer than any move of the catalog.
const REST_WITHIN: Duration = Duration::from_secs(10);
const REST_POLL: Duration = Duration::from_millis(50);

/// What stops an axis that does not come to rest by itself (a homing whose switch or index mark is never
/// found runs on, 000 line 1055): SL 0, which ramps a slew down (000 line 1114); MCode's escape, where the
/// profile has it (the LMD's <ESC>, 001 line 1245: in MCode it ends motion and any program, and a drive may
/// keep moving with its bridge disabled); then DE = 0, which disables the output bridge (000 line 1042). The
/// case keeps DE and puts it back after.
fn stop_requests(cx: &Ctx) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    if let Some(sl) = register(cx.p, "SL").filter(|r| r.access.writable()) {
        out.push(pdu(
            &cx.write_request(sl.address, sl.words(cx.p.device.word_order, 0))
        ));
    }
    if let Some(esc) = escape(cx.p) {
        out.push(esc);
    }
    if let Some(de) = register(cx.p, "DE").filter(|r| r.access == Access::Rw) {
        out.push(pdu(
            &cx.write_request(de.address, de.words(cx.p.device.word_order, 0))
        ));
    }
    out
}

/// FC 0x42 <ESC> (no parameters) where the profile has the escape mnemonic, in the form its name encodes to.
fn escape(p: &Profile) -> Option<Vec<u8>> {
    let m = p.mnemonic("\u{1b}").filter(|m| m.write)?;
    let mnemonic = Mnemonic::from_name(&m.name)?;
    Request::VendorWrite {
        mnemonic,
        params: Vec::new(),
    }
    .to_bytes()
    .ok()
}

/// Before a write that can start motion without being one of the move registers (a vendor function such as
/// the LMD's HF, "home to index"): DE kept, so that the stop of [`settle_motion`] can be put back.
pub(super) fn keep_drive_enable(cx: &Ctx, a: &mut Around) {
    if let Some(de) = register(cx.p, "DE").filter(|r| r.access == Access::Rw) {
        a.keep_register(cx, de, Compare::Structure);
    }
}

/// After everything else is kept: the axis given the time to come to rest before anything is put back
/// ([`await_rest`], stopping it if it does not). `homing`: the write may start a homing, which ends only
/// where its switch or index mark is found.
pub(super) fn settle_motion(cx: &Ctx, a: &mut Around, homing: bool) {
    if let Some(rest) = await_rest(cx, homing) {
        a.undo(vec![rest]);
    }
}

/// True for a register or mnemonic whose write starts a homing: HM and HI ("home to index", 001 line 2101),
/// HF ("home to index offset", 001 line 1843). A homing runs until its switch or the encoder's index mark
/// is found (000 line 1055): a drive without one wired homes until it is stopped.
pub(super) fn homes(name: &str) -> bool {
    ["HM", "HI", "HF"]
        .iter()
        .any(|m| name.eq_ignore_ascii_case(m))
}

/// Wait for the axis to come to rest: MV ("Moving", 000 line 1089) read until it is 0, [`REST_WITHIN`] at
/// most. None where the profile has no readable MV.
///
/// Where it does not, the axis is stopped ([`stop_requests`]) and the step FAILs, except after a homing
/// (`homing`), which ends only where its switch or index mark is found: INFORMATIONAL then. A drive that
/// does not stop when told to FAILs either way.
fn await_rest(cx: &Ctx, homing: bool) -> Option<Step> {
    let mv = register(cx.p, "MV").filter(|r| r.access.readable() && r.width == 1)?;
    let table = if mv.table == drives::profile::Table::Input {
        drives::profile::Table::Input
    } else {
        drives::profile::Table::Holding
    };
    Some(Step::Until {
        read: pdu(&cx.read_request(mv.address, 1, table)),
        mask: 0xFFFF,
        value: 0,
        timeout: if homing {
            crate::cases::Verdict::Informational
        } else {
            crate::cases::Verdict::Fail
        },
        stop: stop_requests(cx),
        every: REST_POLL,
        within: REST_WITHIN,
        note: format!(
            "the axis at rest: MV (0x{:04X}) reads 0 (read every {} ms, {} s at most)",
            mv.address,
            REST_POLL.as_millis(),
            REST_WITHIN.as_secs()
        ),
    })
}

/// True for a register whose write may start a hybrid calibration: "Calibration [...] will occur
/// automatically following these conditions: [...] Hybrid functionality enabled, Bridge re-enabled after
/// being disabled, Microstep resolution is changed" (000 line 1134; 001 the same for hMTechnology): AS, DE,
/// MS; and the instructions CF ("initiate a timed calibration", 000 line 1141) and SC ("Start calibration",
/// 000 line 1150).
fn starts_calibration(r: &Register) -> bool {
    ["AS", "DE", "MS", "CF", "SC"].iter().any(|m| is(r, m))
}

/// How long a calibration a case started is waited for: CT, "the time in milliseconds which the hybrid
/// circuitry will calibrate", defaults to 200 ms (000 line 1142); a drive whose CT was set longer is left
/// calibrating, with a note.
const CALIBRATION_WITHIN: Duration = Duration::from_secs(5);

/// After a case that writes `r` (where it may start a calibration, [`starts_calibration`]) and has put
/// everything back: read AF until its bit 7, "Calibration complete" (128, 000 line 1133), is set, so that the
/// next case does not meet a drive busy calibrating (which refuses a move, as the manuals leave it free to)
/// and the run does not end with one running. INFORMATIONAL, not FAIL, where the bit does not come: neither
/// manual says that a drive without hybrid mode enabled sets it. Nothing where the profile has no readable AF
/// (a drive that lacks it refuses the read, and the step goes on).
pub(super) fn await_calibration(cx: &Ctx, a: &mut Around, r: &Register) {
    if !starts_calibration(r) {
        return;
    }
    let Some(af) = register(cx.p, "AF").filter(|r| r.access.readable() && r.width == 1) else {
        return;
    };
    a.finally(Step::Until {
        read: pdu(&cx.read_request(af.address, 1, drives::profile::Table::Holding)),
        mask: 0x0080,
        value: 0x0080,
        timeout: crate::cases::Verdict::Informational,
        stop: Vec::new(),
        every: REST_POLL,
        within: CALIBRATION_WITHIN,
        note: format!(
            "calibration complete: AF (0x{:04X}) bit 7 (128) set (read every {} ms, {} s at most)",
            af.address,
            REST_POLL.as_millis(),
            CALIBRATION_WITHIN.as_secs()
        ),
    });
}

/// A move needs the drive enabled: the reference refuses MA/MR/SL while DE = 0 (exception 04). Keep DE,
/// write DE = 1, and put DE back after.
pub(super) fn enable_drive(cx: &Ctx, a: &mut Around) {
    if let Some(de) = register(cx.p, "DE").filter(|r| r.access == Access::Rw) {
        a.keep_register(cx, de, Compare::Structure);
        a.set(write(cx, de, 1, "enable the drive (DE = 1)"));
    }
}

/// Around a write of `value` to a move register (after [`enable_drive`]): a point move (MA, MR) starts from a
/// known position (P kept, then set to 0, the reference point of moves, 000 line 1097: the move is short on any
/// drive) and moves back to it with MA 0, an absolute move that cannot add to any error of the first;
/// SL stops (SL 0). The position counter is put back after. A homing (HM, where the drive takes it as the
/// instruction) ends by itself when its switch is found, and sets the position reference there: P is not
/// written by the case (a write of P is destructive, 000 line 1097, and would make the case so); the keeper
/// puts it back at the end of a run that allows destructive writes, and lists it as left out otherwise. After
/// each, the case waits for the axis to come to rest (MV = 0) before it puts anything back: a drive refuses
/// to change P or MS while it moves (exception 04), and the next case must not start with the axis moving.
pub(super) fn undo_move(cx: &Ctx, a: &mut Around, r: &Register) {
    let settle = Step::Wait(MOVE_SETTLE);
    let rest = await_rest(cx, is(r, "HM"));
    if is(r, "HM") {
        a.undo(rest.into_iter().collect());
    } else if is(r, "MA") || is(r, "MR") {
        let (Some(pos), Some(ma)) = (
            register(cx.p, "P").filter(|p| p.access == Access::Rw),
            register(cx.p, "MA").filter(|m| m.access.writable()),
        ) else {
            return;
        };
        a.keep_register(cx, pos, Compare::Structure);
        a.set(write(
            cx,
            pos,
            0,
            "position counter P = 0 (the move is short)",
        ));
        let mut back = vec![
            settle.clone(),
            command(cx, ma, 0, "move back to position 0 (MA 0)"),
            settle,
        ];
        back.extend(rest);
        a.undo(back);
    } else if is(r, "SL") {
        let mut stop = vec![command(cx, r, 0, "stop the slew (SL 0)")];
        match register(cx.p, "DE").filter(|d| d.access == Access::Rw) {
            Some(de) => stop.push(write(cx, de, 0, "stop the axis at once (DE = 0)")),
            None => stop.push(settle),
        }
        stop.extend(rest);
        a.undo(stop);
    }
}

/// DC and IC decrement and increment "the specified variable by one" (000 lines 1041, 1064): each is undone
/// by the other with the same value.
pub(super) fn undo_step_instruction(cx: &Ctx, a: &mut Around, r: &Register, value: i64) {
    let inverse = if is(r, "DC") {
        "IC"
    } else if is(r, "IC") {
        "DC"
    } else {
        return;
    };
    if let Some(inv) = register(cx.p, inverse).filter(|i| i.access.writable()) {
        a.undo(vec![write(
            cx,
            inv,
            value,
            format!("undo with {inverse} {value}"),
        )]);
    }
}

/// Registers whose valid values depend on another's: VI < VM (000 lines 1123-1124), HT + MT ≤ 65535 and
/// HT ≠ 1 (000 lines 1056, 1088). Before one of them is written, the other is kept and set to the end of
/// its range that leaves the written one its whole range (VM to its maximum, VI, HT and MT to their minimum),
/// so that the write does not depend on the drive's setting of the other; both are put back after, the
/// written one first.
pub(super) fn free_partner(cx: &Ctx, a: &mut Around, r: &Register) {
    const PARTNERS: &[(&str, &str, bool)] = &[
        ("VI", "VM", true),
        ("VM", "VI", false),
        ("HT", "MT", false),
        ("MT", "HT", false),
    ];
    for (m, partner, to_max) in PARTNERS {
        if !is(r, m) {
            continue;
        }
        if let Some(other) = register(cx.p, partner).filter(|o| o.access == Access::Rw) {
            let (min, max) = other.range();
            let v = if *to_max { max } else { min };
            a.keep_register(cx, other, Compare::Structure);
            a.set(write(
                cx,
                other,
                v,
                format!("{partner} = {v}, so that any {m} is valid"),
            ));
        }
    }
}

/// True for the MCode program commands and the irreversible ones (see [`program_command`]).
pub(super) fn is_program_command(name: &str) -> bool {
    matches!(
        name.trim().to_ascii_uppercase().as_str(),
        "E" | "EX" | "PS" | "RS" | "CP" | "UG"
    )
}

/// The MCode program commands (000 section 4.3, 001 sections 4.4.5, 4.4.10, 4.4.11, 4.4.13): a case that
/// pauses or resumes a program first starts one (EX with the profile's example label), every case that
/// starts one ends it (E) after, and each starts from no program running (E), so that no case depends on a
/// program another left running or paused. The program's label must exist on the drive; CP, which clears
/// the program, and UG, which stops normal operation for a firmware upgrade, are [`Tag::Irreversible`] and run
/// after every other case.
pub(super) fn program_command(cx: &Ctx, a: &mut Around, tags: &mut Vec<Tag>, name: &str) {
    let command = |m: &str, params: &[u8], what: &str| -> Option<Step> {
        cx.p.mnemonic(m)?;
        Some(exchange(
            Outgoing::Pdu(pdu(&Request::VendorWrite {
                mnemonic: Mnemonic::from_name(m)?,
                params: params.to_vec(),
            })),
            Compare::Structure,
            format!("{what} ({m}{})", String::from_utf8_lossy(params)),
        ))
    };
    if !cx.supports(FunctionCode::VENDOR_WRITE) {
        return;
    }
    let name = name.to_ascii_uppercase();
    if crate::cases::safety::irreversible_mnemonic(&name) {
        if !tags.contains(&Tag::Irreversible) {
            tags.push(Tag::Irreversible);
        }
        return;
    }
    if !matches!(name.as_str(), "EX" | "PS" | "RS") {
        return;
    }
    let label =
        cx.p.mnemonic("EX")
            .and_then(|m| m.example.clone())
            .map(String::into_bytes)
            .unwrap_or_default();
    let mut start = vec![command("E", b"", "no program running")];
    if name != "EX" {
        start.push(command("EX", &label, "a program running"));
        if !tags.contains(&Tag::Motion) {
            tags.push(Tag::Motion);
        }
    }
    if name == "RS" {
        start.push(command("PS", b"", "the program paused"));
    }
    for s in start.into_iter().flatten() {
        a.set(s);
    }
    if let Some(end) = command("E", b"", "end the program") {
        a.undo(vec![end]);
    }
}
