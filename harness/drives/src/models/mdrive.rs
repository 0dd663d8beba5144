//! MDrive Plus2 / MDrive Hybrid and Lexium MDrive (LMD) Ethernet: one model for both, driven by the profile.
//!
//! Manuals: MDrive `000_b25109cd5b573b4c.txt` ("000"), LMD `001_aafa6838846abfce.txt` ("001"); line numbers
//! below are lines of those files. The two drives share the register map layout, the motion variables and the
//! vendor function codes; where they differ (I/O addresses, the LMD's optional output 4, word order, mnemonics,
//! VM maximum) the difference is data in `corpus/profiles/{mdrive,lmd}.toml`, not code here.
//!
//! Behaviour and the choices made where the manuals are silent:
//!
//! - **Registers** (FC 03/06/10/17, 04 if listed) go through `bank::RegisterBank`; see there for partial 32-bit
//!   reads (allowed), partial writes (02), read-only writes (02) and ranges (03). On top of the static ranges
//!   the model enforces the dependent ones: VI < VM (000 lines 1123-1124: VI "1 to max. velocity – 1", VM
//!   "Initial velocity +1 to 5000000"), the microstep table of MS (000 lines 1081-1087), HT ≠ 1 and
//!   HT + MT ≤ 65535 (000 lines 1056, 1088). A violation is exception 03; `range-unchecked` lifts them all.
//! - **I/O**: FC 01/05 act on the profile's coils and FC 02 on its discrete inputs; coil k (in address order)
//!   is output k+1 and mirrors register Ok+1, input k mirrors register Ik+1, and IN/IL (inputs) and OT/OL
//!   (outputs) hold the group as a binary-weighted value. The drive starts with inputs 1-4 = 1,1,0,1 and outputs
//!   1-4 = 1,0,1,0 (the LMD's output 4, freedom `lmd-output-4`, has no register O4) so that the manuals' FC 02
//!   and FC 01 examples (000 lines 515-525, 557-567; 001 lines 751-767, 816-832) read back as printed on a
//!   fresh drive. The I/O point setup (S1-S4, IS/OS) is stored but does not gate reads (FC 01/02, the mirrors): on the MDrive (I/O points
//!   shared between inputs and outputs, inputs by default, 000 line 1263) the two examples could not both hold
//!   otherwise. A write of an MDrive output (FC 05, O1-O4, OT/OL) while its point is configured as an input
//!   (S1-S4 type below 16) is taken, as the freedom `mdrive-output-write-while-input` lets a drive do (000
//!   lines 532, 579 say the outputs must be configured, not what a drive answers otherwise), or refused with
//!   the code chosen for it; either way the answer is that freedom's decision.
//! - **Motion**: writing MA (move absolute), MR (move relative) or SL (slew) starts a move over virtual time.
//!   Point moves start at VI, accelerate at A to VM (or less, for a short move: triangular profile), cruise,
//!   decelerate at D to VI and stop exactly on the target; slews ramp from the present velocity to the SL
//!   velocity (at A when speeding up, D when slowing down, through VI/0 on a reversal) and run until SL 0, which
//!   ramps down to VI and stops on the nearest whole step. During a move reads of P and C1 return the
//!   interpolated position (both count motor steps, C1 being the clock-pulse counter of 000 line 1027),
//!   V the velocity, MV = 1, VC = 1 while accelerating or decelerating and MP = 1 during MA/MR moves. A new
//!   MA/MR while the axis moves, or any move while the drive is disabled (DE = 0), is refused with exception 04
//!   (slave device failure, the only one of the manual's four codes, 000 lines 427-430, that means "cannot do
//!   it now"); SL is accepted during any move and turns it into a slew, as SL is MCode's way to change speed or
//!   stop. DE = 0 stops the axis at once. Writing P or C1 sets the counter without moving. The 32-bit counters
//!   wrap like the drive's registers. HM (homing) and the hybrid calibration instructions are stored, not
//!   simulated (no switches or encoder are modelled).
//! - **Save** (S, 0x0076) and other destructive writes are counted (`nvm_writes`), nothing else.
//! - **Device identification** (FC 2B/0E): `generic::read_device_id` over the profile's objects; conformity 0x82
//!   (regular, individual access), as the golden frames adopt (ERRATA-mdrive.md item 11).
//! - **Vendor FC 0x41/0x42** (000 section 4.3; 001 sections 4.3-4.4): the mnemonic (reversed, space padded on
//!   the wire) must be one of the profile's; an unknown mnemonic is exception 02, because the mnemonic plays the
//!   role of the data address (like a reserved register, 000 line 618). Reading a write-only mnemonic (E, EX,
//!   PS, RS, ...) or writing a read-only one (IT, VT, AV) is exception 02 for the same reason (the address does
//!   not allow that access; `read-only-writable` accepts the write). Bad parameters are exception 03: more than
//!   28 bytes (000 line 985), non-printable bytes (those a text parser reads as blanks, a tab, are a drive's
//!   choice: `parameter-blank-controls`), a setting without the leading '=' (000 line 1006: "the data string
//!   includes all of the characters, including the equal sign"; a drive may take the values without it:
//!   `setting-equals-sign`), non-numeric values, too many values,
//!   and values outside the parameter tables the manuals print (S1-S4, S5, S7/S8, S13, MU, IS, OS, AO, RD, BE,
//!   FL; see `RULES`). A write may give fewer values than the setting has; the rest keep their values.
//!   A read returns the values without '=' and separated by ", ", as the only printed read-back does
//!   (TR → "0, 0, 0", 000 lines 964-975, ERRATA-mdrive.md table row "FC 0x41 response '='"); the parameter of
//!   a mnemonic that mirrors a register (MU → 0x00A0) is that register's value in decimal. Read-only status
//!   mnemonics (IT, VT, AV) read back the profile's example as a fixed measurement. The write response is
//!   0x42, "bytes written" = 0x04 and the echoed mnemonic, as both manuals print it (000 line 1010, 001
//!   line 1208; ERRATA-mdrive.md item 20: the field counts the 4 mnemonic characters returned).
//!   Program commands (E, EX, PS, RS, ESC, CP) change a recorded program state; ESC also stops the axis.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use super::DriveModel;
use super::bank::{BitIndex, Change, RegIndex, RegisterBank};
use super::data_model::{self, BitTable, DataModel, RegTable};
use super::generic::read_device_id;
use crate::choices::{Choices, Decision, Freedoms, Rejection, ids};
use crate::faults::{Fault, FaultSet};
use crate::profile::{Profile, VendorMnemonic};
use codec::{ExceptionCode, FunctionCode, Mnemonic, Request, Response};

/// The longest FC 0x42 parameter string: "1-n bytes (28 max)" (000 line 985, 001 line 1174).
const MAX_PARAM_BYTES: usize = 28;

/// The FC 0x42 response's "bytes written" field: the 4 mnemonic characters returned (see the module notes).
const BYTES_WRITTEN: u8 = 4;

/// Inputs 1-4 at power-up, chosen so the FC 02 examples (I1=1, I2=1, I3=0, I4=1) hold.
const INITIAL_INPUTS: [bool; 4] = [true, true, false, true];

/// Outputs 1-4 at power-up, chosen so the FC 01 examples (O1=1, O2=0, O3=1, O4=0) hold.
const INITIAL_OUTPUTS: [bool; 4] = [true, false, true, false];

/// Valid microstep resolutions (000 lines 1084-1087, 001 lines 2246-2248).
const MICROSTEPS: &[i64] = &[
    1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127,
];

/// What one parameter of a vendor setting may be.
#[derive(Clone, Copy, Debug)]
enum Allowed {
    /// Any decimal number (integer or with a fraction, e.g. CR "1.500").
    Any,
    /// One of these integers.
    Set(&'static [i64]),
    /// An integer in this inclusive range.
    Range(i64, i64),
}

/// What the manuals print about a vendor setting's parameters.
struct Rule {
    names: &'static [&'static str],
    params: &'static [Allowed],
    /// Power-up values where the manual gives them.
    default: Option<&'static [&'static str]>,
    /// A check across parameters (on the integers, after merging with the stored values).
    check: Option<fn(&[i64]) -> bool>,
}

const BOOL: &[i64] = &[0, 1];

/// I/O types of S1-S4 (000 lines 743-759): inputs 0-11, outputs 16-25.
const MDRIVE_IO_TYPES: &[i64] = &[0, 1, 2, 3, 5, 7, 8, 11, 16, 17, 18, 20, 21, 23, 24, 25];

/// Digital input types of IS lines 1-4 (001 lines 1417-1433).
const LMD_INPUT_TYPES: &[i64] = &[0, 1, 2, 3, 5, 7, 8, 11, 12];

/// LMD IS: lines 1-4 take the digital input types, line 5 (analog) 9 voltage / 10 current (001 lines 1437-1484).
/// The error code `Fault::ErrorRecordKept` leaves in ER (any non-zero code would do).
const PAST_ERROR_CODE: i64 = 86;

fn lmd_input_setup_ok(v: &[i64]) -> bool {
    match v {
        [5, mode, ..] => *mode == 9 || *mode == 10,
        [_, ty, ..] => LMD_INPUT_TYPES.contains(ty),
        _ => true,
    }
}

/// LMD OS: function 28 (trip) is for output 3 only (001 line 1597).
fn lmd_output_setup_ok(v: &[i64]) -> bool {
    match v {
        [line, 28, ..] => *line == 3,
        _ => true,
    }
}

/// The vendor settings whose parameter tables the manuals print.
const RULES: &[Rule] = &[
    // 000 lines 743-759; default "general purpose input, active low, sinking" (000 line 1263).
    Rule {
        names: &["S1", "S2", "S3", "S4"],
        params: &[
            Allowed::Set(MDRIVE_IO_TYPES),
            Allowed::Set(BOOL),
            Allowed::Set(BOOL),
        ],
        default: Some(&["0", "0", "0"]),
        check: None,
    },
    // 000 lines 824-829: 9 voltage, 10 current; range 0/1.
    Rule {
        names: &["S5"],
        params: &[Allowed::Set(&[9, 10]), Allowed::Set(BOOL)],
        default: None,
        check: None,
    },
    // 000 lines 783-789: 33-35 inputs, 49-51 outputs; active 0/1.
    Rule {
        names: &["S7", "S8"],
        params: &[Allowed::Set(&[33, 34, 35, 49, 50, 51]), Allowed::Set(BOOL)],
        default: None,
        check: None,
    },
    // 000 lines 852-853: 60 capture input, 61 trip output; active 0/1.
    Rule {
        names: &["S13"],
        params: &[Allowed::Set(&[60, 61]), Allowed::Set(BOOL)],
        default: None,
        check: None,
    },
    // 000 lines 936-938, 001 lines 1535-1541: mode 0-2, lead/lag 0/1.
    Rule {
        names: &["MU"],
        params: &[Allowed::Set(&[0, 1, 2]), Allowed::Set(BOOL)],
        default: None,
        check: None,
    },
    // Three values, read back "0, 0, 0" (000 lines 964-975, 001 lines 1141-1163); their meaning is not given.
    Rule {
        names: &["TR"],
        params: &[Allowed::Any, Allowed::Any, Allowed::Any],
        default: Some(&["0", "0", "0"]),
        check: None,
    },
    // 001 lines 1411-1484: line 1-5, type, active 0/1.
    Rule {
        names: &["IS"],
        params: &[Allowed::Range(1, 5), Allowed::Any, Allowed::Set(BOOL)],
        default: None,
        check: Some(lmd_input_setup_ok),
    },
    // 001 lines 1573-1599: line 1-3, function 16-29 without the reserved 26/27 and the undefined 19/22.
    Rule {
        names: &["OS"],
        params: &[
            Allowed::Range(1, 3),
            Allowed::Set(&[16, 17, 18, 20, 21, 23, 24, 25, 28, 29]),
            Allowed::Set(BOOL),
        ],
        default: None,
        check: Some(lmd_output_setup_ok),
    },
    // 001 lines 1283-1315: a mask of 16 condition bits.
    Rule {
        names: &["AO"],
        params: &[Allowed::Range(0, 65535)],
        default: None,
        check: None,
    },
    // 001 sections 4.4.14, 4.4.17, 4.4.25: flags.
    Rule {
        names: &["RD", "BE", "FL"],
        params: &[Allowed::Set(BOOL)],
        default: None,
        check: None,
    },
];

fn rule_for(name: &str) -> Option<&'static Rule> {
    RULES
        .iter()
        .find(|r| r.names.iter().any(|n| n.eq_ignore_ascii_case(name)))
}

/// The state of the stored MCode program, as the program commands leave it (nothing is executed).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Program {
    /// No program running.
    Idle,
    /// Started with EX at this label or address.
    Running(String),
    /// Paused with PS.
    Paused(String),
}

/// How a vendor mnemonic behaves, from its profile entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum VendorKind {
    /// Write-only: an action; `takes_params` when its format names a parameter (EX label, HF "=n").
    Command { takes_params: bool },
    /// Read and write: a setting with up to `count` values.
    Setting { count: usize },
    /// Read-only: a measurement.
    Status,
}

fn vendor_kind(m: &VendorMnemonic) -> VendorKind {
    if !m.read {
        let none = m.format.as_deref().is_none_or(|f| {
            let f = f.trim();
            f.is_empty() || f.to_ascii_lowercase().contains("no parameters")
        });
        VendorKind::Command {
            takes_params: !none,
        }
    } else if !m.write {
        VendorKind::Status
    } else {
        let count = rule_for(&m.name)
            .map(|r| r.params.len())
            .unwrap_or_else(|| {
                m.format
                    .as_deref()
                    .map(|f| f.trim_start().trim_start_matches('=').split(',').count())
                    .unwrap_or(1)
            });
        VendorKind::Setting {
            count: count.max(1),
        }
    }
}

/// A decimal number as MCode parameters carry them: optional sign, digits, optional fraction.
fn is_number(s: &str) -> bool {
    let s = s.strip_prefix(['+', '-']).unwrap_or(s);
    let (int, frac) = s.split_once('.').unwrap_or((s, ""));
    !(int.is_empty() && frac.is_empty())
        && int.bytes().all(|b| b.is_ascii_digit())
        && frac.bytes().all(|b| b.is_ascii_digit())
}

/// Split a read-back or example string ("=1,0,0", "0, 0, 0") into trimmed values.
fn split_values(s: &str) -> Vec<String> {
    let s = s.trim().strip_prefix('=').unwrap_or(s.trim());
    s.split(',').map(|v| v.trim().to_string()).collect()
}

/// Registers the model drives or reacts to, by mnemonic; `None` where the profile lacks one.
#[derive(Clone, Debug, Default)]
struct Addrs {
    p: Option<u16>,
    c1: Option<u16>,
    v: Option<u16>,
    mv: Option<u16>,
    vc: Option<u16>,
    mp: Option<u16>,
    /// The hybrid (hMTechnology) status AF and the hybrid mode AS it reports on.
    af: Option<u16>,
    as_: Option<u16>,
    vi: Option<u16>,
    vm: Option<u16>,
    a: Option<u16>,
    d: Option<u16>,
    ma: Option<u16>,
    mr: Option<u16>,
    sl: Option<u16>,
    de: Option<u16>,
    ms: Option<u16>,
    ht: Option<u16>,
    mt: Option<u16>,
    hm: Option<u16>,
    /// Encoder enable and position maintenance (`encoder_function_freedom`).
    ee: Option<u16>,
    pm: Option<u16>,
    /// Registers mirroring outputs 1.. (O1, O2, ...).
    outputs: Vec<Option<u16>>,
    /// Registers mirroring inputs 1.. (I1, I2, ...).
    inputs: Vec<Option<u16>>,
    /// Registers holding all outputs as a binary-weighted value (OT, OL).
    output_groups: Vec<u16>,
    /// Registers holding all inputs as a binary-weighted value (IN, IL).
    input_groups: Vec<u16>,
}

/// Where `refresh` writes, found once in the bank (its register map never changes): the status registers
/// and the I/O mirrors of [`Addrs`].
#[derive(Debug)]
struct StatusSlots {
    p: Option<RegIndex>,
    c1: Option<RegIndex>,
    v: Option<RegIndex>,
    mv: Option<RegIndex>,
    vc: Option<RegIndex>,
    mp: Option<RegIndex>,
    af: Option<RegIndex>,
    as_: Option<RegIndex>,
    de: Option<RegIndex>,
    /// Each input's bit and the register mirroring it, in input order.
    inputs: Vec<(Option<BitIndex>, Option<RegIndex>)>,
    input_groups: Vec<RegIndex>,
    /// Each output's bit and the register mirroring it, in output order.
    outputs: Vec<(Option<BitIndex>, Option<RegIndex>)>,
    output_groups: Vec<RegIndex>,
}

impl StatusSlots {
    fn new(bank: &RegisterBank, addrs: &Addrs, inputs: &[u16], outputs: &[u16]) -> Self {
        let reg = |a: Option<u16>| a.and_then(|a| bank.index_of(a));
        let bits = |table: BitTable, bits: &[u16], mirrors: &[Option<u16>]| {
            bits.iter()
                .enumerate()
                .map(|(i, &a)| {
                    (
                        bank.bit_index(table, a),
                        reg(mirrors.get(i).copied().flatten()),
                    )
                })
                .collect()
        };
        let groups = |g: &[u16]| g.iter().filter_map(|&a| bank.index_of(a)).collect();
        Self {
            p: reg(addrs.p),
            c1: reg(addrs.c1),
            v: reg(addrs.v),
            mv: reg(addrs.mv),
            vc: reg(addrs.vc),
            mp: reg(addrs.mp),
            af: reg(addrs.af),
            as_: reg(addrs.as_),
            de: reg(addrs.de),
            inputs: bits(BitTable::DiscreteInputs, inputs, &addrs.inputs),
            input_groups: groups(&addrs.input_groups),
            outputs: bits(BitTable::Coils, outputs, &addrs.outputs),
            output_groups: groups(&addrs.output_groups),
        }
    }
}

/// One piece of a velocity profile: constant acceleration from a starting velocity.
#[derive(Clone, Debug)]
struct Segment {
    /// Seconds.
    duration: f64,
    /// Steps/s at the start of the segment (signed).
    v0: f64,
    /// Steps/s² (signed).
    accel: f64,
}

/// What kind of move is running.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum MoveKind {
    /// MA/MR: ends on a target.
    Point,
    /// SL: runs until told otherwise.
    Slew,
}

/// A move in progress, as a displacement profile over time.
#[derive(Clone, Debug)]
struct Motion {
    kind: MoveKind,
    /// When the move started (virtual time).
    start: Duration,
    /// Displacement (steps) at the start.
    base: f64,
    segments: Vec<Segment>,
    /// After the segments: keep slewing at this velocity (`Some`), or stop (`None`).
    cruise: Option<f64>,
    /// Where a point move ends, exactly (floating-point sums must not leave it a step off).
    end: Option<f64>,
}

/// Position, velocity and flags at one instant.
#[derive(Clone, Copy, Debug)]
struct Kinematics {
    disp: f64,
    vel: f64,
    changing: bool,
    /// The move still running, if any.
    moving: Option<MoveKind>,
}

impl Motion {
    fn at(&self, elapsed: f64) -> Kinematics {
        let mut disp = self.base;
        let mut rem = elapsed.max(0.0);
        for s in &self.segments {
            if rem < s.duration {
                let mut x = disp + s.v0 * rem + 0.5 * s.accel * rem * rem;
                if let Some(end) = self.end {
                    // Never past the target on the way there.
                    x = if end >= self.base {
                        x.clamp(self.base, end)
                    } else {
                        x.clamp(end, self.base)
                    };
                }
                return Kinematics {
                    disp: x,
                    vel: s.v0 + s.accel * rem,
                    changing: s.accel != 0.0,
                    moving: Some(self.kind),
                };
            }
            disp += s.v0 * s.duration + 0.5 * s.accel * s.duration * s.duration;
            rem -= s.duration;
        }
        match self.cruise {
            Some(v) => Kinematics {
                disp: disp + v * rem,
                vel: v,
                changing: false,
                moving: Some(self.kind),
            },
            None => Kinematics {
                // A stopped axis stands on a whole step.
                disp: self.end.unwrap_or(disp).round(),
                vel: 0.0,
                changing: false,
                moving: None,
            },
        }
    }
}

/// Velocity-profile parameters, guarded so that faulted-in values (0, VI ≥ VM) cannot divide by zero.
#[derive(Clone, Copy, Debug)]
struct Ramp {
    vi: f64,
    vm: f64,
    accel: f64,
    decel: f64,
}

/// Plan a point move of `dist` steps from rest (trapezoid, or triangle when VM is not reached).
fn plan_point(r: Ramp, dist: f64) -> Vec<Segment> {
    let s = dist.signum();
    let d = dist.abs();
    let peak = (r.vi * r.vi + 2.0 * d * r.accel * r.decel / (r.accel + r.decel))
        .sqrt()
        .min(r.vm)
        .max(r.vi);
    let t_acc = (peak - r.vi) / r.accel;
    let d_acc = (peak * peak - r.vi * r.vi) / (2.0 * r.accel);
    let t_dec = (peak - r.vi) / r.decel;
    let d_dec = (peak * peak - r.vi * r.vi) / (2.0 * r.decel);
    let t_cruise = if peak > 0.0 {
        (d - d_acc - d_dec).max(0.0) / peak
    } else {
        0.0
    };
    [
        Segment {
            duration: t_acc,
            v0: s * r.vi,
            accel: s * r.accel,
        },
        Segment {
            duration: t_cruise,
            v0: s * peak,
            accel: 0.0,
        },
        Segment {
            duration: t_dec,
            v0: s * peak,
            accel: -s * r.decel,
        },
    ]
    .into_iter()
    .filter(|seg| seg.duration > 0.0 && seg.duration.is_finite())
    .collect()
}

/// Plan a slew from velocity `v0` to `target` (0 = stop).
fn plan_slew(r: Ramp, v0: f64, target: f64) -> (Vec<Segment>, Option<f64>) {
    let mut segs = Vec::new();
    let mut v = v0;
    if v != 0.0 && (target == 0.0 || target.signum() != v.signum()) {
        // Ramp down to the start/stop speed, then stop (a stepper stops from VI at once).
        let speed = v.abs();
        if speed > r.vi {
            segs.push(Segment {
                duration: (speed - r.vi) / r.decel,
                v0: v,
                accel: -v.signum() * r.decel,
            });
        }
        v = 0.0;
    }
    if target == 0.0 {
        return (segs, None);
    }
    let s = target.signum();
    if v == 0.0 {
        v = s * r.vi.min(target.abs());
    }
    let (from, to) = (v.abs(), target.abs());
    if to > from {
        segs.push(Segment {
            duration: (to - from) / r.accel,
            v0: v,
            accel: s * r.accel,
        });
    } else if to < from {
        segs.push(Segment {
            duration: (from - to) / r.decel,
            v0: v,
            accel: -s * r.decel,
        });
    }
    segs.retain(|seg| seg.duration > 0.0 && seg.duration.is_finite());
    (segs, Some(target))
}

/// Round a displacement to whole steps (saturating; NaN counts as 0).
fn steps(x: f64) -> i64 {
    x.round() as i64
}

/// The MDrive/LMD reference model.
#[derive(Clone)]
pub struct Mdrive {
    profile: Arc<Profile>,
    bank: RegisterBank,
    addrs: Arc<Addrs>,
    /// Coil addresses in order: output 1, 2, ...
    outputs: Arc<[u16]>,
    /// Discrete-input addresses in order: input 1, 2, ...
    inputs: Arc<[u16]>,
    status: Arc<StatusSlots>,
    now: Duration,
    motion: Option<Motion>,
    /// Displacement (steps) while no move runs.
    rest: f64,
    /// P = p_origin + displacement.
    p_origin: i64,
    /// C1 = c1_origin + displacement.
    c1_origin: i64,
    /// Stored vendor parameters by upper-case mnemonic.
    /// Shared with clones until one of them stores a parameter.
    params: Arc<BTreeMap<String, Vec<String>>>,
    program: Program,
    nvm_writes: u32,
    /// `Fault::WriteOnlyReadable`: FC 0x41 of a write-only mnemonic is answered.
    write_only_readable: bool,
    /// `Fault::LetterCaseBusy`: a known mnemonic in lower case is answered with exception 06.
    letter_case_busy: bool,
    /// `Fault::NulPaddingBusy`: a known mnemonic padded with NUL is answered with exception 06.
    padding_busy: bool,
    /// `Fault::EqualsSignBusy`: a setting written without its '=' is answered with exception 06.
    equals_busy: bool,
    /// `Fault::BlankControlBusy`: a parameter string with a blank control character is answered with 06.
    blank_busy: bool,
    /// `Fault::GroupWriteClears`: OT/OL written while a point is an input clears every output.
    group_write_clears: bool,
    /// `Fault::HomingNeverEnds`: a write of HM starts a homing that never ends (`homing`).
    homing_never_ends: bool,
    /// MV reads 1 for good: a homing started under `Fault::HomingNeverEnds`.
    homing: bool,
    /// `Fault::MnemonicParamsUnchecked`: FC 0x42 parameters the mnemonic does not take are "written".
    params_unchecked: bool,
    /// `Fault::VendorWriteNotApplied`: an FC 0x42 write of a setting is acknowledged but not stored.
    write_not_applied: bool,
    /// `Fault::ErrorRecordKept`: the error record (ER) starts with a past error's code, and writes to it are
    /// acknowledged but not applied.
    error_record_kept: Option<u16>,
    /// The I/O points are shared between inputs and outputs and set up with S1..Sn (the MDrive): output k
    /// (coil k, register Ok) is point k, and OT/OL set them all.
    shared_io: bool,
}

impl Mdrive {
    /// Build the model from its profile (`mdrive` or `lmd`); model-level faults act through the register bank.
    pub fn new(profile: Profile, faults: FaultSet, choices: Choices) -> Self {
        let mut bank = RegisterBank::new(&profile, &faults, &choices);
        let outputs = bank.bit_addresses(BitTable::Coils);
        let inputs = bank.bit_addresses(BitTable::DiscreteInputs);
        let at = |m: &str| bank.address_of(m);
        let addrs = Addrs {
            p: at("P"),
            c1: at("C1"),
            v: at("V"),
            mv: at("MV"),
            vc: at("VC"),
            mp: at("MP"),
            af: at("AF"),
            as_: at("AS"),
            vi: at("VI"),
            vm: at("VM"),
            a: at("A"),
            d: at("D"),
            ma: at("MA"),
            mr: at("MR"),
            sl: at("SL"),
            de: at("DE"),
            ms: at("MS"),
            ht: at("HT"),
            mt: at("MT"),
            hm: at("HM"),
            ee: at("EE"),
            pm: at("PM"),
            outputs: (1..=outputs.len()).map(|k| at(&format!("O{k}"))).collect(),
            inputs: (1..=inputs.len()).map(|k| at(&format!("I{k}"))).collect(),
            output_groups: ["OT", "OL"].iter().filter_map(|m| at(m)).collect(),
            input_groups: ["IN", "IL"].iter().filter_map(|m| at(m)).collect(),
        };
        for (a, on) in inputs.iter().zip(INITIAL_INPUTS) {
            bank.set_bit(BitTable::DiscreteInputs, *a, on);
        }
        for (a, on) in outputs.iter().zip(INITIAL_OUTPUTS) {
            bank.set_bit(BitTable::Coils, *a, on);
        }
        let p_origin = addrs.p.and_then(|a| bank.value(a)).unwrap_or(0);
        let c1_origin = addrs.c1.and_then(|a| bank.value(a)).unwrap_or(0);
        let mut params = BTreeMap::new();
        for m in profile.mnemonics.iter().map(|m| m.get_ref()) {
            if let VendorKind::Setting { count } = vendor_kind(m) {
                params.insert(m.name.to_ascii_uppercase(), Self::initial_params(m, count));
            }
        }
        let status = StatusSlots::new(&bank, &addrs, &inputs, &outputs);
        let shared_io = profile.device.shared_io_points
            && !outputs.is_empty()
            && outputs.len() == inputs.len()
            && (1..=outputs.len()).all(|k| params.contains_key(&format!("S{k}")));
        let mut model = Self {
            profile: Arc::new(profile),
            bank,
            addrs: Arc::new(addrs),
            outputs: outputs.into(),
            inputs: inputs.into(),
            status: Arc::new(status),
            now: Duration::ZERO,
            motion: None,
            rest: 0.0,
            p_origin,
            c1_origin,
            params: Arc::new(params),
            program: Program::Idle,
            nvm_writes: 0,
            write_only_readable: faults.has(Fault::WriteOnlyReadable),
            letter_case_busy: faults.has(Fault::LetterCaseBusy),
            padding_busy: faults.has(Fault::NulPaddingBusy),
            equals_busy: faults.has(Fault::EqualsSignBusy),
            blank_busy: faults.has(Fault::BlankControlBusy),
            group_write_clears: faults.has(Fault::GroupWriteClears),
            homing_never_ends: faults.has(Fault::HomingNeverEnds),
            homing: false,
            params_unchecked: faults.has(Fault::MnemonicParamsUnchecked),
            write_not_applied: faults.has(Fault::VendorWriteNotApplied),
            error_record_kept: None,
            shared_io,
        };
        if faults.has(Fault::ErrorRecordKept)
            && let Some(er) = model.bank.address_of("ER")
        {
            // A past error's code (EF, which the model keeps at 0, says no error condition exists now).
            model.bank.set_value(er, PAST_ERROR_CODE);
            model.error_record_kept = Some(er);
        }
        model.refresh();
        model
    }

    /// Power-up values of a setting: the manual's default, else the profile's example, else zeros.
    fn initial_params(m: &VendorMnemonic, count: usize) -> Vec<String> {
        if let Some(d) = rule_for(&m.name).and_then(|r| r.default) {
            return d.iter().map(|s| s.to_string()).collect();
        }
        if let Some(ex) = m.example.as_deref() {
            let v = split_values(ex);
            if v.len() == count && v.iter().all(|x| is_number(x)) {
                return v;
            }
        }
        vec!["0".to_string(); count]
    }

    /// The register bank (tests inspect values through it).
    pub fn bank(&self) -> &RegisterBank {
        &self.bank
    }

    /// How many writes reached non-volatile memory (Save, and other destructive registers and mnemonics).
    pub fn nvm_writes(&self) -> u32 {
        self.nvm_writes
    }

    /// The recorded program state.
    pub fn program(&self) -> &Program {
        &self.program
    }

    /// Set a digital input level (tests and the in-process target play the outside world); false if absent.
    pub fn set_input(&mut self, input: usize, on: bool) -> bool {
        let ok = match input.checked_sub(1).and_then(|i| self.inputs.get(i)) {
            Some(&a) => self.bank.set_bit(BitTable::DiscreteInputs, a, on),
            None => false,
        };
        self.refresh();
        ok
    }

    fn reg(&self, addr: Option<u16>) -> Option<i64> {
        addr.and_then(|a| self.bank.value(a))
    }

    fn ramp(&self) -> Ramp {
        let get = |a: Option<u16>, dflt: f64| self.reg(a).map_or(dflt, |v| v as f64);
        let vm = get(self.addrs.vm, 768_000.0).max(1.0);
        Ramp {
            vi: get(self.addrs.vi, 1_000.0).clamp(0.0, vm),
            vm,
            accel: get(self.addrs.a, 1_000_000.0).max(1.0),
            decel: get(self.addrs.d, 1_000_000.0).max(1.0),
        }
    }

    fn kinematics(&self) -> Kinematics {
        match &self.motion {
            Some(m) => m.at(self.now.saturating_sub(m.start).as_secs_f64()),
            None => Kinematics {
                disp: self.rest,
                vel: 0.0,
                changing: false,
                moving: None,
            },
        }
    }

    fn position(&self, disp: f64) -> i64 {
        // Through i32: P is a 32-bit register and wraps like one.
        i64::from(self.p_origin.wrapping_add(steps(disp)) as i32)
    }

    /// Bring the status registers up to date: position, velocity, motion flags, I/O mirrors.
    fn refresh(&mut self) {
        // Through the slots found at construction: this runs three times per request (the station advances
        // the model, which advances itself again in `handle` and refreshes after answering).
        let k = self.kinematics();
        let d = steps(k.disp);
        let s = &*self.status;
        let bank = &mut self.bank;
        let mut set = |at: Option<RegIndex>, value: i64| {
            if let Some(at) = at {
                bank.set_value_at(at, value);
            }
        };
        set(s.p, self.p_origin.wrapping_add(d));
        set(s.c1, self.c1_origin.wrapping_add(d));
        set(s.v, steps(k.vel));
        set(s.mv, i64::from(k.moving.is_some() || self.homing));
        set(s.vc, i64::from(k.changing));
        set(s.mp, i64::from(k.moving == Some(MoveKind::Point)));
        // AF, additive (000 line 1133): the model has no rotor to lead or lag and calibrates at once, so it
        // is at zero (64) with its calibration complete (128), and hybrid mode is active (16) while AS is
        // not 0 and the bridge enabled.
        if let Some(af) = s.af {
            let on = |at: Option<RegIndex>| at.is_none_or(|i| bank.value_at(i) != 0);
            let active = s.as_.is_some() && on(s.as_) && on(s.de);
            bank.set_value_at(af, 128 + 64 + if active { 16 } else { 0 });
        }
        for (table, bits, groups) in [
            (BitTable::DiscreteInputs, &s.inputs, &s.input_groups),
            (BitTable::Coils, &s.outputs, &s.output_groups),
        ] {
            let mut group = 0i64;
            for (i, &(bit, mirror)) in bits.iter().enumerate() {
                let on = bit.is_some_and(|b| bank.bit_at(table, b));
                group |= i64::from(on) << i.min(62);
                if let Some(at) = mirror {
                    bank.set_value_at(at, i64::from(on));
                }
            }
            for &at in groups {
                bank.set_value_at(at, group);
            }
        }
    }

    /// Stop the axis where it is (DE = 0, ESC).
    fn halt(&mut self) {
        let k = self.kinematics();
        self.rest = k.disp.round();
        self.motion = None;
    }

    /// True when a write setting the outputs of `points` (1-based) sets one whose I/O point is configured as
    /// an input: S1-S4 type 0-11, the default (000 line 1263); outputs are types 16-25 (000 lines 743-759).
    /// Never on a drive whose outputs are outputs of their own (the LMD).
    fn sets_input_point(&self, points: impl IntoIterator<Item = usize>) -> bool {
        self.shared_io
            && points.into_iter().any(|k| {
                self.params
                    .get(&format!("S{k}"))
                    .and_then(|v| v.first())
                    .and_then(|t| t.parse::<f64>().ok())
                    .is_none_or(|t| t < 16.0)
            })
    }

    /// True when a coil write of `points` (1-based) sets an output of a drive whose outputs are their own (the
    /// LMD) that has no register of its own: the LMD's output 4, which FC 05 and OT name but the output setup
    /// OS (lines 1-3, 001 line 1070) and the registers O1-O3 do not (`lmd-output-4-write`).
    fn sets_unset_up_output(&self, points: Vec<usize>) -> bool {
        !self.shared_io
            && !self.addrs.outputs.is_empty()
            && points
                .into_iter()
                .any(|k| self.addrs.outputs.get(k - 1).is_some_and(Option::is_none))
    }

    /// The points (1-based) a coil write of `count` coils from `address` sets.
    fn coil_points(&self, address: u16, count: usize) -> Vec<usize> {
        let end = u32::from(address) + u32::try_from(count).unwrap_or(u32::MAX);
        self.outputs
            .iter()
            .enumerate()
            .filter(|(_, a)| (u32::from(address)..end).contains(&u32::from(**a)))
            .map(|(i, _)| i + 1)
            .collect()
    }

    /// The points (1-based) a register write sets one by one (Ok → point k), and whether it sets them all
    /// as a group (OT/OL).
    fn register_points(&self, changes: &[Change]) -> (Vec<usize>, bool) {
        let mut points = Vec::new();
        let mut group = false;
        for c in changes {
            if self.addrs.output_groups.contains(&c.address) {
                group = true;
            } else if let Some(i) = self
                .addrs
                .outputs
                .iter()
                .position(|o| *o == Some(c.address))
            {
                points.push(i + 1);
            }
        }
        (points, group)
    }

    /// The freedoms a register write decides that sets the output of a point configured as an input: one
    /// output (`mdrive-output-write-while-input`), all of them as a group
    /// (`mdrive-output-group-write-while-input`).
    fn input_point_freedoms(&self, changes: &[Change]) -> Vec<Decision> {
        let (points, group) = self.register_points(changes);
        let mut out = Vec::new();
        if self.sets_input_point(points) {
            out.push(ids::MDRIVE_OUTPUT_WRITE_WHILE_INPUT);
        }
        if group && self.sets_input_point(1..=self.outputs.len()) {
            out.push(ids::MDRIVE_OUTPUT_GROUP_WRITE_WHILE_INPUT);
        }
        out
    }

    /// True when `changes` switch on an encoder function (EE, encoder enable, 0x001E; PM, position
    /// maintenance, 0x005C: "MDrivePlus only", lines 1044 and 1100) of an MDrive: a unit built without the
    /// optional encoder may refuse it (`mdrive-encoder-absent`).
    /// The freedom that decides a write switching on an encoder function: PM switched on while EE stays 0
    /// (`position-maintenance-without-encoder`, both products: EE "Enable encoder functions", PM "position
    /// maintenance functions"), else EE or PM switched on in an MDrive (`mdrive-encoder-absent`); `None`
    /// for any other write.
    fn encoder_function_freedom(&self, changes: &[Change]) -> Option<Decision> {
        let (ee, pm) = (self.addrs.ee?, self.addrs.pm?);
        let sets = |address: u16| changes.iter().find(|c| c.address == address);
        let ee_after = sets(ee).map_or_else(|| self.bank.value(ee).unwrap_or(0), |c| c.value);
        if sets(pm).is_some_and(|c| c.value != 0) && ee_after == 0 {
            return Some(ids::POSITION_MAINTENANCE_WITHOUT_ENCODER);
        }
        (self.profile.device.id == "mdrive"
            && [ee, pm]
                .into_iter()
                .any(|a| sets(a).is_some_and(|c| c.value != 0)))
        .then_some(ids::MDRIVE_ENCODER_ABSENT)
    }

    /// The refusal this drive chose under `freedom` for a write of an output whose point is an input
    /// (`=exception-XX`); `None` where it takes the write (the reference).
    fn input_point_refusal(&self, freedom: Decision) -> Option<Rejection> {
        let v = self.bank.choices().get(freedom)?;
        Choices::exception_value(v).map(|code| Rejection::by(freedom, code))
    }

    /// The points (1-based) whose output registers (O1-O4, not the groups) `quantity` registers from
    /// `address` cover.
    fn output_register_points(&self, address: u16, quantity: usize) -> Vec<usize> {
        let end = u32::from(address) + u32::try_from(quantity).unwrap_or(u32::MAX);
        self.addrs
            .outputs
            .iter()
            .enumerate()
            .filter(|(_, a)| a.is_some_and(|a| (u32::from(address)..end).contains(&u32::from(a))))
            .map(|(i, _)| i + 1)
            .collect()
    }

    /// True when a read the bank serves covers the output of a point configured as an input: FC 01 of its
    /// coil, a register read of its O register (`mdrive-output-read-while-input`; OT/OL are served).
    fn reads_input_point(&self, request: &Request) -> bool {
        let (points, served) = match request {
            Request::ReadCoils { address, quantity } => (
                self.coil_points(*address, usize::from(*quantity)),
                self.bank
                    .read_bits(BitTable::Coils, *address, *quantity)
                    .is_ok(),
            ),
            Request::ReadHoldingRegisters { address, quantity }
            | Request::ReadWriteMultipleRegisters {
                read_address: address,
                read_quantity: quantity,
                ..
            } => (
                self.output_register_points(*address, usize::from(*quantity)),
                self.bank
                    .read(RegTable::Holding, *address, *quantity)
                    .is_ok(),
            ),
            Request::ReadInputRegisters { address, quantity } => (
                self.output_register_points(*address, usize::from(*quantity)),
                self.bank.read(RegTable::Input, *address, *quantity).is_ok(),
            ),
            _ => return false,
        };
        served && self.sets_input_point(points)
    }

    /// The answer to a read of outputs (FC 01 of the coils, a register read of O1-O4) with the output of
    /// each point configured as an input read as 0: what that point drives (nothing), where the reference
    /// reads the output latch as stored. The manual says neither (`mdrive-output-read-while-input`; an
    /// MDrive written independently from the manual reads 0, tests/independent/mdrive-f): both are the
    /// freedom's `response`. `None` for another request.
    fn outputs_off_where_inputs(&self, request: &Request) -> Option<codec::Response> {
        let input = |k: usize| self.sets_input_point([k]);
        match request {
            Request::ReadCoils { address, quantity } => {
                let mut data = self
                    .bank
                    .read_bits(BitTable::Coils, *address, *quantity)
                    .ok()?;
                for k in self.coil_points(*address, usize::from(*quantity)) {
                    if input(k) {
                        let i = usize::from(self.outputs[k - 1].wrapping_sub(*address));
                        if let Some(b) = data.get_mut(i / 8) {
                            *b &= !(1 << (i % 8));
                        }
                    }
                }
                Some(codec::Response::ReadCoils { data })
            }
            Request::ReadHoldingRegisters { address, quantity }
            | Request::ReadInputRegisters { address, quantity } => {
                let table = if matches!(request, Request::ReadInputRegisters { .. }) {
                    RegTable::Input
                } else {
                    RegTable::Holding
                };
                let mut values = self.bank.read(table, *address, *quantity).ok()?;
                for k in self.output_register_points(*address, usize::from(*quantity)) {
                    if input(k)
                        && let Some(a) = self.addrs.outputs.get(k - 1).copied().flatten()
                        && let Some(v) = values.get_mut(usize::from(a.wrapping_sub(*address)))
                    {
                        *v = 0;
                    }
                }
                Some(if table == RegTable::Input {
                    codec::Response::ReadInputRegisters { values }
                } else {
                    codec::Response::ReadHoldingRegisters { values }
                })
            }
            _ => None,
        }
    }

    /// The refusal this drive chose for a read of an output whose point is an input; `None` where it serves
    /// it (the reference).
    fn output_read_refusal(&self, points: Vec<usize>) -> Option<Rejection> {
        if !self.sets_input_point(points) {
            return None;
        }
        self.input_point_refusal(ids::MDRIVE_OUTPUT_READ_WHILE_INPUT)
    }

    /// The freedoms of a register write of `words` at `address` that sets the output of a point configured
    /// as an input, where the write's value is out of range (03): a drive refusing such writes with 02 checks
    /// the address first (app 4.5, Figure 9) and refuses it for the point.
    fn refused_value_freedoms(&self, address: u16, words: &[u16]) -> Vec<Decision> {
        let value_refused = matches!(
            self.bank.plan_write(address, words),
            Err(e) if e.code == ExceptionCode::ILLEGAL_DATA_VALUE
        );
        if !value_refused {
            return Vec::new();
        }
        let end = u32::from(address) + u32::try_from(words.len()).unwrap_or(u32::MAX);
        let group = self
            .addrs
            .output_groups
            .iter()
            .any(|g| (u32::from(address)..end).contains(&u32::from(*g)));
        let mut out = Vec::new();
        if self.sets_input_point(self.output_register_points(address, words.len())) {
            out.push(ids::MDRIVE_OUTPUT_WRITE_WHILE_INPUT);
        }
        if group && self.sets_input_point(1..=self.outputs.len()) {
            out.push(ids::MDRIVE_OUTPUT_GROUP_WRITE_WHILE_INPUT);
        }
        out
    }

    /// The dependent limits a register write must respect (exception 03), beyond each register's own range.
    fn check_limits(&self, changes: &[Change]) -> Result<(), Rejection> {
        if self.bank.range_unchecked() {
            return Ok(());
        }
        // A dependent limit is a range too: the value is outside what the drive accepts now.
        let out_of_range = self
            .bank
            .choices()
            .reject(ids::VALUE_OUT_OF_RANGE, ExceptionCode::ILLEGAL_DATA_VALUE);
        let new = |addr: Option<u16>| {
            let a = addr?;
            changes
                .iter()
                .find(|c| c.address == a)
                .map(|c| c.value)
                .or_else(|| self.bank.value(a))
        };
        let touched =
            |addr: Option<u16>| addr.is_some_and(|a| changes.iter().any(|c| c.address == a));
        if (touched(self.addrs.vi) || touched(self.addrs.vm))
            && let (Some(vi), Some(vm)) = (new(self.addrs.vi), new(self.addrs.vm))
            && vi >= vm
        {
            return Err(out_of_range);
        }
        if touched(self.addrs.ms) && new(self.addrs.ms).is_some_and(|m| !MICROSTEPS.contains(&m)) {
            return Err(out_of_range);
        }
        if touched(self.addrs.ht) || touched(self.addrs.mt) {
            let ht = new(self.addrs.ht).unwrap_or(0);
            let mt = new(self.addrs.mt).unwrap_or(0);
            if (touched(self.addrs.ht) && ht == 1) || ht.saturating_add(mt) > 65_535 {
                return Err(out_of_range);
            }
        }
        Ok(())
    }

    /// Whether the motion commands in `changes` can run now (exception 04 if not).
    fn check_motion(&self, changes: &[Change]) -> Result<(), ExceptionCode> {
        let moving = self.kinematics().moving.is_some();
        let enabled = self.reg(self.addrs.de).is_none_or(|v| v != 0)
            && !changes
                .iter()
                .any(|c| Some(c.address) == self.addrs.de && c.value == 0);
        for c in changes {
            let a = Some(c.address);
            let point = a == self.addrs.ma || a == self.addrs.mr;
            let slew = a == self.addrs.sl && c.value != 0;
            if (point && (moving || !enabled)) || (slew && !enabled) {
                return Err(ExceptionCode::SERVER_DEVICE_FAILURE);
            }
        }
        Ok(())
    }

    /// What a stored register write does besides storing.
    fn apply(&mut self, c: &Change) {
        let a = Some(c.address);
        let here = self.kinematics();
        if self.homing_never_ends && a.is_some() && a == self.addrs.hm {
            self.homing = true;
        }
        if a == self.addrs.ma || a == self.addrs.mr {
            let dist = if a == self.addrs.ma {
                c.value.wrapping_sub(self.position(here.disp))
            } else {
                c.value
            };
            if dist != 0 {
                let base = here.disp.round();
                self.motion = Some(Motion {
                    kind: MoveKind::Point,
                    start: self.now,
                    base,
                    segments: plan_point(self.ramp(), dist as f64),
                    cruise: None,
                    end: Some(base + dist as f64),
                });
            }
        } else if a == self.addrs.sl {
            if here.moving.is_some() || c.value != 0 {
                let (segments, cruise) = plan_slew(self.ramp(), here.vel, c.value as f64);
                self.motion = Some(Motion {
                    kind: MoveKind::Slew,
                    start: self.now,
                    base: here.disp,
                    segments,
                    cruise,
                    end: None,
                });
            }
        } else if a == self.addrs.p {
            self.p_origin = c.value.wrapping_sub(steps(here.disp));
        } else if a == self.addrs.c1 {
            self.c1_origin = c.value.wrapping_sub(steps(here.disp));
        } else if a == self.addrs.de && c.value == 0 {
            self.halt();
        } else if let Some(k) = self.addrs.outputs.iter().position(|o| *o == a) {
            if let Some(&coil) = self.outputs.get(k) {
                self.bank.set_bit(BitTable::Coils, coil, c.value != 0);
            }
        } else if self.addrs.output_groups.contains(&c.address) {
            for (i, &coil) in Arc::clone(&self.outputs).iter().enumerate() {
                let on = i < 63 && (c.value >> i) & 1 == 1;
                self.bank.set_bit(BitTable::Coils, coil, on);
            }
        }
        if self.bank.register(c.address).is_some_and(|r| r.destructive) {
            self.nvm_writes = self.nvm_writes.saturating_add(1);
        }
    }

    fn vendor_entry(&self, mnemonic: &Mnemonic) -> Option<VendorMnemonic> {
        self.profile.mnemonic(&mnemonic.name()).cloned()
    }

    /// A known mnemonic named in lower or mixed case: served (the reference), or refused as unknown by a
    /// drive that compares the bytes (`mnemonic-letter-case`).
    fn letter_case_refusal(&mut self, fc: FunctionCode, mnemonic: &Mnemonic) -> Option<Response> {
        let name = mnemonic.name();
        if !name.bytes().any(|b| b.is_ascii_lowercase()) || self.vendor_entry(mnemonic).is_none() {
            return None;
        }
        if self.letter_case_busy {
            return Some(Response::exception(fc, ExceptionCode::SERVER_DEVICE_BUSY));
        }
        self.decided(ids::MNEMONIC_LETTER_CASE);
        let code = Choices::exception_value(self.bank.choices().get(ids::MNEMONIC_LETTER_CASE)?)?;
        Some(Response::exception(fc, code))
    }

    /// A known mnemonic padded with NUL (0x00) where the manuals print spaces (0x20): refused as unknown (the
    /// reference: the mnemonic as sent is none the drive knows), or read as the mnemonic it pads by a drive that
    /// strips both (`mnemonic-padding`). `Ok`: the mnemonic to go on with.
    fn padding(&mut self, fc: FunctionCode, mnemonic: &Mnemonic) -> Result<Mnemonic, Response> {
        let Some(padded) = nul_padded(mnemonic).filter(|m| self.vendor_entry(m).is_some()) else {
            return Ok(*mnemonic);
        };
        if self.padding_busy {
            return Err(Response::exception(fc, ExceptionCode::SERVER_DEVICE_BUSY));
        }
        self.decided(ids::MNEMONIC_PADDING);
        match self.bank.choices().get(ids::MNEMONIC_PADDING) {
            Some(v) if v.matches("response") => Ok(padded),
            Some(v) => match Choices::exception_value(v) {
                // The reference's own: as an unknown mnemonic, whose code is `unknown-mnemonic`'s.
                Some(ExceptionCode::ILLEGAL_DATA_ADDRESS) | None => Ok(*mnemonic),
                Some(code) => Err(Response::exception(fc, code)),
            },
            None => Ok(*mnemonic),
        }
    }

    /// FC 0x41: read a mnemonic's parameters.
    fn vendor_read(&mut self, mnemonic: &Mnemonic) -> Response {
        let fc = FunctionCode::VENDOR_READ;
        // The width of the byte count is the station's (it encodes the response).
        self.decided(ids::FC41_BYTE_COUNT_WIDTH);
        if let Some(key) = self.program_control(mnemonic) {
            // A drive following the sections (000 line 873): FC 0x41 runs E, EX, PS, RS; nothing is read.
            self.decided(ids::MDRIVE_PROGRAM_CONTROL_FUNCTION);
            let _ = self.run_command(&key, "", false);
            return Response::VendorRead { params: Vec::new() };
        }
        if let Some(r) = self.letter_case_refusal(fc, mnemonic) {
            return r;
        }
        let mnemonic = &match self.padding(fc, mnemonic) {
            Ok(m) => m,
            Err(r) => return r,
        };
        let Some(m) = self.vendor_entry(mnemonic) else {
            return self.refuse(
                fc,
                ids::UNKNOWN_MNEMONIC,
                ExceptionCode::ILLEGAL_DATA_ADDRESS,
            );
        };
        if !m.read && !self.write_only_readable {
            return self.refuse(
                fc,
                ids::MNEMONIC_ACCESS,
                ExceptionCode::ILLEGAL_DATA_ADDRESS,
            );
        }
        let key = m.name.to_ascii_uppercase();
        let mut values = match (vendor_kind(&m), self.params.get(&key)) {
            (_, Some(v)) => v.clone(),
            (VendorKind::Status, None) => {
                // A measurement: the manual's printed reading stands in for the sensor.
                return Response::VendorRead {
                    params: m
                        .example
                        .as_deref()
                        .unwrap_or("0")
                        .trim_start_matches('=')
                        .as_bytes()
                        .to_vec(),
                };
            }
            (_, None) => vec!["0".to_string()],
        };
        if let (Some(reg), Some(first)) = (m.register, values.first_mut())
            && let Some(v) = self.bank.value(reg)
        {
            *first = v.to_string();
        }
        // A setting whose write format has fewer values than it reads back (the MDrive's TR: written
        // "=position", read back "0, 0, 0" in the manual's example): a drive may answer the format's values
        // only (`fc41-read-back-fields`).
        let format_fields = m
            .format
            .as_deref()
            .filter(|f| f.trim_start().starts_with('='))
            .map(|f| f.split(',').count());
        if let Some(n) = format_fields.filter(|&n| n < values.len())
            && self.profile.device.id == "mdrive"
        {
            self.decided(ids::FC41_READ_BACK_FIELDS);
            if self.bank.choices().name(ids::FC41_READ_BACK_FIELDS) == Some("format-count") {
                values.truncate(n);
            }
        }
        // The LMD's S1-S4 (MDrive syntax, its example's three values): a drive taking them for its input
        // setting may keep two (`lmd-input-setup-fields`).
        if self.profile.device.id == "lmd"
            && matches!(key.as_str(), "S1" | "S2" | "S3" | "S4")
            && values.len() == 3
        {
            self.decided(ids::LMD_INPUT_SETUP_FIELDS);
            if self.bank.choices().name(ids::LMD_INPUT_SETUP_FIELDS) == Some("two") {
                values.truncate(2);
            }
        }
        self.decided(ids::FC41_READ_BACK_FORMAT);
        let params = if self.bank.choices().name(ids::FC41_READ_BACK_FORMAT) == Some("as-written") {
            // "Written or read in normal sequence" (000 line 727): as a setting is written, "=0,1,0".
            format!("={}", values.join(","))
        } else {
            values.join(", ")
        };
        Response::VendorRead {
            params: params.into_bytes(),
        }
    }

    /// FC 0x42: write a setting or run a command.
    fn vendor_write(&mut self, mnemonic: &Mnemonic, params: &[u8]) -> Response {
        let fc = FunctionCode::VENDOR_WRITE;
        let echo = mnemonic;
        if self.program_control(mnemonic).is_some() {
            // A drive following the sections runs E, EX, PS, RS by FC 0x41 and refuses them by 0x42, as it
            // refuses any other FC 0x42 of a mnemonic it reads (the access freedom decides the code).
            self.decided(ids::MDRIVE_PROGRAM_CONTROL_FUNCTION);
            return self.refuse(
                fc,
                ids::MNEMONIC_ACCESS,
                ExceptionCode::ILLEGAL_DATA_ADDRESS,
            );
        }
        let escape = Mnemonic::from_name("\u{1b}");
        let printed_escape = Mnemonic([0x20, 0x20, 0x1B, 0x20]);
        if self.profile.device.id == "lmd"
            && (Some(*mnemonic) == escape || *mnemonic == printed_escape)
        {
            self.decided(ids::LMD_ESC_WIRE_FORM);
        }
        let mnemonic = &match self.bank.choices().name(ids::LMD_ESC_WIRE_FORM) {
            // A drive that knows ESC as printed (001 lines 1054, 1256) takes 20 20 1B 20 for it, and the
            // reversal rule's 20 20 20 1B for no mnemonic it knows.
            Some("20 20 1B 20") if Some(*mnemonic) == escape => {
                return self.refuse(
                    fc,
                    ids::UNKNOWN_MNEMONIC,
                    ExceptionCode::ILLEGAL_DATA_ADDRESS,
                );
            }
            Some("20 20 1B 20") if *mnemonic == printed_escape => escape.unwrap_or(*mnemonic),
            _ => *mnemonic,
        };
        if let Some(r) = self.letter_case_refusal(fc, mnemonic) {
            return r;
        }
        let mnemonic = &match self.padding(fc, mnemonic) {
            Ok(m) => m,
            Err(r) => return r,
        };
        let Some(m) = self.vendor_entry(mnemonic) else {
            return self.refuse(
                fc,
                ids::UNKNOWN_MNEMONIC,
                ExceptionCode::ILLEGAL_DATA_ADDRESS,
            );
        };
        let kind = vendor_kind(&m);
        if kind
            == (VendorKind::Command {
                takes_params: false,
            })
        {
            // With or without a byte count (the station reads the request as the drive does).
            self.decided(ids::FC42_PARAMETERLESS_BYTE_COUNT);
        }
        let writable = m.write || (kind == VendorKind::Status && self.bank.read_only_writable());
        if !writable {
            return self.refuse(
                fc,
                ids::MNEMONIC_ACCESS,
                ExceptionCode::ILLEGAL_DATA_ADDRESS,
            );
        }
        let blanked;
        let params = match self.blank_controls(params) {
            Ok(Some(b)) => {
                blanked = b;
                blanked.as_slice()
            }
            Ok(None) => params,
            Err(busy) => return Response::exception(fc, busy),
        };
        if params.len() > MAX_PARAM_BYTES || !params.iter().all(|b| (0x20..=0x7E).contains(b)) {
            return self.refuse(
                fc,
                ids::MNEMONIC_BAD_PARAMETER,
                ExceptionCode::ILLEGAL_DATA_VALUE,
            );
        }
        // Printable ASCII only, so this cannot fail; an empty string stands in if it ever did.
        let text = std::str::from_utf8(params).unwrap_or_default();
        let key = m.name.to_ascii_uppercase();
        // An encoder function switched on (see `enables_encoder_function`): decided, and refused by a drive
        // that chose so.
        let switched_on = matches!(kind, VendorKind::Setting { .. })
            && split_values(text)
                .first()
                .is_some_and(|v| v.parse::<i64>().is_ok_and(|v| v != 0));
        let register = match key.as_str() {
            "EE" => self.addrs.ee,
            "PM" => self.addrs.pm,
            _ => None,
        };
        if let Some(freedom) = register
            .filter(|_| switched_on)
            .and_then(|address| self.encoder_function_freedom(&[Change { address, value: 1 }]))
        {
            self.decided(freedom);
            if let Some(refusal) = self.input_point_refusal(freedom) {
                return Response::exception(fc, refusal.code);
            }
        }
        let result = match kind {
            VendorKind::Command { takes_params } => self.run_command(&key, text, takes_params),
            // The faulty drive checks the parameters as a setting's but does not store them.
            VendorKind::Setting { count } if self.write_not_applied => {
                let kept = self.clone();
                let checked = self.write_setting(&m, &key, text, count);
                *self = kept;
                checked
            }
            VendorKind::Setting { count } => self.write_setting(&m, &key, text, count),
            VendorKind::Status => {
                // Only under `read-only-writable`: the "measurement" takes whatever was written.
                Arc::make_mut(&mut self.params).insert(key, split_values(text));
                Ok(())
            }
        };
        match result {
            Ok(()) => {
                if m.destructive {
                    self.nvm_writes = self.nvm_writes.saturating_add(1);
                }
                self.refresh();
                self.decided(ids::FC42_BYTES_WRITTEN);
                let written = match self.bank.choices().name(ids::FC42_BYTES_WRITTEN) {
                    Some("parameter-bytes") => u8::try_from(params.len()).unwrap_or(u8::MAX),
                    _ => BYTES_WRITTEN,
                };
                Response::VendorWrite {
                    written,
                    mnemonic: *echo,
                }
            }
            // The faulty drive answers as if it had written the parameters it cannot take.
            Err(_) if self.params_unchecked => Response::VendorWrite {
                written: BYTES_WRITTEN,
                mnemonic: *echo,
            },
            // `Fault::EqualsSignBusy`, whatever code the drive refuses bad parameters with.
            Err(ExceptionCode::SERVER_DEVICE_BUSY) => {
                Response::exception(fc, ExceptionCode::SERVER_DEVICE_BUSY)
            }
            Err(code) => self.refuse(fc, ids::MNEMONIC_BAD_PARAMETER, code),
        }
    }

    /// The command key when `mnemonic` is one of E, EX, PS, RS and the drive runs them by FC 0x41
    /// (`mdrive-program-control-function=fc41`).
    fn program_control(&self, mnemonic: &Mnemonic) -> Option<String> {
        if self
            .bank
            .choices()
            .name(ids::MDRIVE_PROGRAM_CONTROL_FUNCTION)
            != Some("fc41")
        {
            return None;
        }
        let key = mnemonic.name().to_ascii_uppercase();
        ["E", "EX", "PS", "RS"]
            .contains(&key.as_str())
            .then_some(key)
    }

    /// Refuse a vendor request whose exception code the freedom `freedom` decides (`reference` by default).
    fn refuse(
        &mut self,
        fc: FunctionCode,
        freedom: Decision,
        reference: ExceptionCode,
    ) -> Response {
        self.decided(freedom);
        Response::exception(fc, self.bank.choices().code(freedom, reference))
    }

    fn run_command(
        &mut self,
        key: &str,
        text: &str,
        takes_params: bool,
    ) -> Result<(), ExceptionCode> {
        if takes_params == text.is_empty() {
            return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
        }
        let label = text.trim().to_string();
        self.program = match (key, std::mem::replace(&mut self.program, Program::Idle)) {
            ("E" | "CP", _) => Program::Idle,
            ("\u{1b}", _) => {
                // ESC aborts the program and any motion (MCode's escape).
                self.halt();
                Program::Idle
            }
            ("EX", _) => Program::Running(label),
            ("PS", Program::Running(l)) => Program::Paused(l),
            ("RS", Program::Paused(l)) => Program::Running(l),
            (_, other) => other,
        };
        Ok(())
    }

    /// A parameter string holding ASCII control characters a text parser reads as blanks (HT, LF, VT, FF, CR,
    /// FS, GS, RS, US; C's `isspace` and Python's `str.strip` take them so) and otherwise printable: refused as
    /// a bad parameter (the reference: the manuals give the string as ASCII text, 000 line 986, 001 line
    /// 1176, and print none), or read with each of them as a space by a drive whose parser strips blanks
    /// (`parameter-blank-controls`). `Ok(Some)`: the string to go on with; `Ok(None)`: as sent; `Err`: the
    /// code of `Fault::BlankControlBusy`.
    fn blank_controls(&mut self, params: &[u8]) -> Result<Option<Vec<u8>>, ExceptionCode> {
        let blank = |b: &u8| matches!(b, 0x09..=0x0D | 0x1C..=0x1F);
        if params.len() > MAX_PARAM_BYTES
            || !params.iter().any(blank)
            || !params.iter().all(|b| blank(b) || (0x20..=0x7E).contains(b))
        {
            return Ok(None);
        }
        if self.blank_busy {
            return Err(ExceptionCode::SERVER_DEVICE_BUSY);
        }
        self.decided(ids::PARAMETER_BLANK_CONTROLS);
        match self.bank.choices().get(ids::PARAMETER_BLANK_CONTROLS) {
            Some(v) if v.matches("response") => Ok(Some(
                params
                    .iter()
                    .map(|b| if blank(b) { b' ' } else { *b })
                    .collect(),
            )),
            _ => Ok(None),
        }
    }

    /// A setting's parameter string without the leading '=' the manuals print (000 line 1006, 001 line 1202:
    /// "the data string includes all of the characters, including the equal sign"; 001 line 1279: AO's
    /// "Hex 3D 31 32"): refused as a bad parameter (the reference), or taken as if the '=' were there by a
    /// drive that reads the sign as optional (`setting-equals-sign`). `Ok`: the values to go on with.
    fn without_equals_sign<'t>(&mut self, text: &'t str) -> Result<&'t str, ExceptionCode> {
        if self.equals_busy {
            return Err(ExceptionCode::SERVER_DEVICE_BUSY);
        }
        self.decided(ids::SETTING_EQUALS_SIGN);
        match self.bank.choices().get(ids::SETTING_EQUALS_SIGN) {
            Some(v) if v.matches("response") => Ok(text),
            _ => Err(ExceptionCode::ILLEGAL_DATA_VALUE),
        }
    }

    fn write_setting(
        &mut self,
        m: &VendorMnemonic,
        key: &str,
        text: &str,
        count: usize,
    ) -> Result<(), ExceptionCode> {
        let bad = ExceptionCode::ILLEGAL_DATA_VALUE;
        let body = match text.strip_prefix('=') {
            Some(body) => body,
            // No value at all: nothing a '=' would make a setting of.
            None if text.trim().is_empty() => return Err(bad),
            None => self.without_equals_sign(text)?,
        };
        let given: Vec<String> = body.split(',').map(|v| v.trim().to_string()).collect();
        if given.len() > count || !given.iter().all(|v| is_number(v)) {
            return Err(bad);
        }
        let mut merged = self
            .params
            .get(key)
            .cloned()
            .unwrap_or_else(|| vec!["0".to_string(); count]);
        merged.resize(count, "0".to_string());
        for (slot, v) in merged.iter_mut().zip(&given) {
            slot.clone_from(v);
        }
        let unchecked = self.bank.range_unchecked();
        if let Some(rule) = rule_for(&m.name)
            && !unchecked
        {
            let ints: Vec<Option<i64>> = merged.iter().map(|v| v.parse::<i64>().ok()).collect();
            for (allowed, v) in rule.params.iter().zip(&ints) {
                let ok = match (allowed, v) {
                    (Allowed::Any, _) => true,
                    (Allowed::Set(s), Some(v)) => s.contains(v),
                    (Allowed::Range(lo, hi), Some(v)) => (lo..=hi).contains(&v),
                    (_, None) => false,
                };
                if !ok {
                    return Err(bad);
                }
            }
            if let Some(check) = rule.check {
                let all: Option<Vec<i64>> = ints.iter().copied().collect();
                if !all.is_some_and(|v| check(&v)) {
                    return Err(bad);
                }
            }
        }
        if let Some(reg) = m.register {
            // The first value is the register's: it must be an integer the register can hold.
            let v: i64 = merged.first().and_then(|v| v.parse().ok()).ok_or(bad)?;
            let r = self.bank.register(reg).ok_or(bad)?;
            let (lo, hi) = if unchecked {
                r.natural_range()
            } else {
                r.range()
            };
            if v < lo || v > hi {
                return Err(bad);
            }
            self.bank.set_value(reg, v);
        }
        Arc::make_mut(&mut self.params).insert(key.to_string(), merged);
        Ok(())
    }
}

/// Registers go through the bank, with the dependent limits (03) and the motion preconditions (04) checked
/// before anything is stored, and each stored change applied (moves, counters, outputs) after.
impl DataModel for Mdrive {
    type Plan = Vec<Change>;

    fn read_registers(
        &self,
        table: RegTable,
        address: u16,
        quantity: u16,
    ) -> Result<Vec<u16>, Rejection> {
        let values = self.bank.read(table, address, quantity)?;
        if let Some(refusal) =
            self.output_read_refusal(self.output_register_points(address, usize::from(quantity)))
        {
            return Err(refusal);
        }
        Ok(values)
    }

    fn splits_register(&self, table: RegTable, address: u16, quantity: u16) -> bool {
        self.bank.splits_register(table, address, quantity)
    }

    fn plan_write(&self, address: u16, words: &[u16]) -> Result<Vec<Change>, Rejection> {
        let changes = self.bank.plan_write(address, words).map_err(|e| {
            // A drive refusing writes of input points with 02 checks the address before the value.
            self.refused_value_freedoms(address, words)
                .into_iter()
                .filter_map(|f| self.input_point_refusal(f))
                .find(|r| r.code == ExceptionCode::ILLEGAL_DATA_ADDRESS)
                .unwrap_or(e)
        })?;
        self.check_limits(&changes)?;
        self.check_motion(&changes)?;
        if let Some(freedom) = self.encoder_function_freedom(&changes)
            && let Some(refusal) = self.input_point_refusal(freedom)
        {
            return Err(refusal);
        }
        // Last: a write the drive could not take anyway is refused for that (its own freedoms decide the code).
        let freedoms = self.input_point_freedoms(&changes);
        if self.group_write_clears && freedoms.contains(&ids::MDRIVE_OUTPUT_GROUP_WRITE_WHILE_INPUT)
        {
            // Acknowledged whatever the drive's choice, and every output cleared.
            let mut changes = changes;
            for c in changes
                .iter_mut()
                .filter(|c| self.addrs.output_groups.contains(&c.address))
            {
                c.value = 0;
            }
            return Ok(changes);
        }
        for freedom in &freedoms {
            if let Some(refusal) = self.input_point_refusal(freedom) {
                return Err(refusal);
            }
        }
        Ok(changes)
    }

    fn decided(&mut self, freedom: Decision) {
        self.bank.freedoms().decided(freedom);
    }

    fn note_request(&mut self, request: &Request) {
        if self.reads_input_point(request) {
            self.decided(ids::MDRIVE_OUTPUT_READ_WHILE_INPUT);
            if self
                .input_point_refusal(ids::MDRIVE_OUTPUT_READ_WHILE_INPUT)
                .is_none()
                && let Some(answer) = self.outputs_off_where_inputs(request)
            {
                self.bank.freedoms().alternative(
                    ids::MDRIVE_OUTPUT_READ_WHILE_INPUT,
                    "response",
                    answer,
                );
            }
        }
        let write = match request {
            Request::WriteSingleRegister { address, value } => Some((*address, vec![*value])),
            Request::WriteMultipleRegisters { address, values }
            | Request::ReadWriteMultipleRegisters {
                write_address: address,
                values,
                ..
            } => Some((*address, values.clone())),
            _ => None,
        };
        if let Some((address, words)) = write {
            for freedom in self.refused_value_freedoms(address, &words) {
                self.decided(freedom);
            }
            if let Some(freedom) = self
                .bank
                .plan_write(address, &words)
                .ok()
                .and_then(|changes| self.encoder_function_freedom(&changes))
            {
                self.decided(freedom);
            }
        }
    }

    fn commit(&mut self, mut changes: Vec<Change>) {
        if let Some(er) = self.error_record_kept {
            changes.retain(|c| c.address != er);
        }
        for freedom in self.input_point_freedoms(&changes) {
            // Taken although a point it sets is an input: a drive may refuse it (see `plan_write`).
            self.decided(freedom);
        }
        self.bank.commit(&changes);
        for c in &changes {
            self.apply(c);
        }
        self.refresh();
    }

    fn read_bits(
        &self,
        table: BitTable,
        address: u16,
        quantity: u16,
    ) -> Result<Vec<u8>, Rejection> {
        let bits = self.bank.read_bits(table, address, quantity)?;
        if table == BitTable::Coils
            && let Some(refusal) =
                self.output_read_refusal(self.coil_points(address, usize::from(quantity)))
        {
            return Err(refusal);
        }
        Ok(bits)
    }

    fn write_coils(&mut self, address: u16, states: &[bool]) -> Result<(), Rejection> {
        if self.sets_unset_up_output(self.coil_points(address, states.len())) {
            // Refused for the missing setup only where the bank would take it (an absent output 4 is 02 first).
            self.bank.check_coil_write(address, states.len())?;
            if let Some(refusal) = self.input_point_refusal(ids::LMD_OUTPUT_4_WRITE) {
                return Err(refusal);
            }
            self.decided(ids::LMD_OUTPUT_4_WRITE);
        }
        if self.sets_input_point(self.coil_points(address, states.len())) {
            // Refused for the setup only where the bank would take it (an unmapped coil is 02 first).
            self.bank.check_coil_write(address, states.len())?;
            if let Some(refusal) = self.input_point_refusal(ids::MDRIVE_OUTPUT_WRITE_WHILE_INPUT) {
                return Err(refusal);
            }
            self.decided(ids::MDRIVE_OUTPUT_WRITE_WHILE_INPUT);
        }
        self.bank.write_coils(address, states)
    }

    fn exception_status(&self) -> Result<u8, Rejection> {
        Ok(self.bank.exception_status())
    }

    fn masked(&self, current: u16, and_mask: u16, or_mask: u16) -> u16 {
        self.bank.masked(current, and_mask, or_mask)
    }
}

impl DriveModel for Mdrive {
    fn profile(&self) -> &Profile {
        &self.profile
    }

    fn freedoms(&mut self) -> &mut Freedoms {
        self.bank.freedoms()
    }

    fn advance(&mut self, now: Duration) {
        self.now = self.now.max(now);
        if let Some(m) = &self.motion {
            let k = m.at(self.now.saturating_sub(m.start).as_secs_f64());
            if k.moving.is_none() {
                self.rest = k.disp;
                self.motion = None;
            }
        }
        self.refresh();
    }

    fn handle(&mut self, now: Duration, _unit: u8, request: &Request) -> Option<Response> {
        self.advance(now);
        let fc = request.function();
        let exc = |e| Response::exception(fc, e);
        let resp = match request {
            Request::ReadDeviceId {
                read_code,
                object_id,
            } => read_device_id(&self.profile, *read_code, *object_id),
            Request::VendorRead { mnemonic } => self.vendor_read(mnemonic),
            Request::VendorWrite { mnemonic, params } => self.vendor_write(mnemonic, params),
            // Registers, coils and inputs; a coil write shows in O1-O4/OT at the refresh below.
            other => data_model::serve(self, other)
                .unwrap_or_else(|| exc(ExceptionCode::ILLEGAL_FUNCTION)),
        };
        self.refresh();
        Some(resp)
    }
}

/// The mnemonic `m` pads where a padding byte (the ones the manuals print as 0x20) is NUL instead: `m` with
/// NULs and spaces stripped from both ends of its reading order, in the printed wire form. `None` where `m`
/// has no NUL, or nothing is left.
fn nul_padded(m: &Mnemonic) -> Option<Mnemonic> {
    if !m.0.contains(&0) {
        return None;
    }
    let name: String = m.0.iter().rev().map(|&b| b as char).collect();
    let stripped = name.trim_matches(|c| c == ' ' || c == '\0');
    if stripped.is_empty() || stripped.contains('\0') {
        return None;
    }
    Mnemonic::from_name(stripped)
}
