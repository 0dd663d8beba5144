//! The SIEB & MEYER SD2x reference model: PDO registers, the DS402 state machine, the RxPDO watchdog and
//! FC 43 / MEI 0x0D object access, on a virtual clock.
//!
//! Line numbers refer to the manual, `shared/seeds/004_944d9845497d8808.txt`. The station (station.rs) has
//! already done addressing, CRC, function-code support, decoding and quantity limits (1..=48) by the time
//! `handle` runs. Where the manual is silent or contradicts itself the model has to choose; every choice is
//! listed here and repeated at the code that makes it:
//!
//! - **Power-on state**: switch on disabled, speed 0, watchdog off. Example 6.1 writes "shutdown" right after
//!   boot and the drive is then ready to switch on (lines 1189, 1224), which DS402 only allows from switch on
//!   disabled. The 6.3 status value 0x7038 (line 1407) is a *fault* state (bits 0-3 = 1000); booting into it
//!   would make 6.1 impossible (fault needs a fault reset first). The model reproduces 0x7038 where it fits
//!   the manual: after the 6.1 telegrams stop and the 500 ms watchdog they armed expires (line 1228: "Else the
//!   drive switches to the error status"). A fresh model answers the 6.3 read with 0x7070.
//! - **Status word**: the DS402 state bits, plus bit 4 (voltage enabled: the simulated DC link is always
//!   powered), bit 5 (quick stop *not* active; cleared only in quick stop active), bit 10 (target reached:
//!   operation enabled and actual speed = ramp target) and bits 12-14 (0x7000). The manual documents bits 0, 2
//!   and 3 only (lines 894-897) and defers the rest to a document not at hand (line 890). Bits 12-14 and bit 9
//!   (remote) are taken from the one printed status word, 0x7038: 12-14 set, 9 clear, so the model sets 12-14
//!   always and never sets remote. Oracles comparing real drives should mask with [`status::STATE_MASK`].
//! - **Quick stop** follows option code 2 (CiA 402 default): ramp to 0, then switch on disabled.
//!   **Fault reaction**: ramp to 0, then fault. **Halt** (control bit 8) ramps to 0 in operation enabled.
//! - **Ramp** [`RAMP_PER_SECOND`]: 100 Hz/s for every speed change (the manual gives none).
//! - **Watchdog** (lines 856-870): only a write to register 3003 restarts it (line 870 "the register must be
//!   rewritten"; line 1228 "the watchdog register must be rewritten"); writes to 3000-3002 alone do not.
//!   It trips when more than the timeout has passed since that write (a rewrite exactly at the timeout is in
//!   time), in any state but fault (line 1228), and then disarms until 3003 is written again. The error code
//!   in 2005 is the profile's `[watchdog] fault_error_code`, else [`DEFAULT_WATCHDOG_ERROR_CODE`] (0x8130,
//!   CiA 301 "life guard error or heartbeat error", the name the manual gives at line 870; no code is printed).
//! - **Registers**: FC 03 and FC 04 read the same map (line 327). An address outside the profile's registers
//!   is exception 02 (lines 672, 723-759). Single words of a 32-bit pair may be read (registers are 16-bit,
//!   line 286). A write to the TxPDO is exception 02: it is the "Input Register" image (line 726), so the
//!   address is not a valid write address (line 672); 03 is for values (line 673). Writes are atomic: any bad
//!   address or value rejects the whole request. FC 23 validates both parts, writes, then reads.
//! - **FC 43**: node-ID must equal the slave address and lie in 01h..7Fh (lines 546, 613), else exception 02
//!   (it addresses the object dictionary, like a register address). Control bits 0-6 not zero (line 608) →
//!   SDO FFFF0003h; address offset not zero (line 627) → FFFF0008h; the reserved byte is ignored and answered
//!   as 00h. Byte count above 4 (line 550) → FFFF0011h; otherwise longer than the object → FFFF0012h,
//!   shorter (including 0) → FFFF0013h. A write response echoes the header with the byte count written and no
//!   data (data only in read responses, line 636). Any MEI but 0Dh → exception 01 (line 603).
//! - **Simulated values**: the manual's table default is 0 for every TxPDO entry; the model reports plausible
//!   live values instead ([`SIMULATED`]), with 17.0 °C at the power stage to agree with example 6.2.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use super::DriveModel;
use super::data_model::{self, DataModel, RegTable, range_end};
use crate::choices::{Choices, Decision, Freedoms, Rejection, ids};
use crate::faults::Fault;
use crate::faults::FaultSet;
use crate::profile::{Access, ObjectType, Profile, WordOrder};
use codec::{CanOpenAccess, ExceptionCode, FunctionCode, Request, Response};

/// Register addresses the model gives a meaning to (section 4, lines 731-759).
pub mod reg {
    /// RxPDO: control word (object 68, DS402 0x6040).
    pub const CONTROL_WORD: u16 = 3000;
    /// RxPDO: target speed in 0.1 Hz (object 210).
    pub const TARGET_SPEED: u16 = 3001;
    /// RxPDO: torque (current) limit Iq in 0.1 A (object 209).
    pub const TORQUE_LIMIT: u16 = 3002;
    /// RxPDO: watchdog timeout in ms (no object).
    pub const WATCHDOG: u16 = 3003;
    /// TxPDO: status word (object 67, DS402 0x6041).
    pub const STATUS_WORD: u16 = 2000;
    /// TxPDO: actual speed in 0.1 Hz (object 168).
    pub const ACTUAL_SPEED: u16 = 2001;
    /// TxPDO: the torque limit in force, in 0.1 A.
    pub const TORQUE_LIMIT_ACTUAL: u16 = 2002;
    /// TxPDO: apparent current in 0.1 A (object 431).
    pub const APPARENT_CURRENT: u16 = 2003;
    /// TxPDO: output power in 0.1 kW (object 390).
    pub const OUTPUT_POWER: u16 = 2004;
    /// TxPDO: error code (object 70, DS402 0x603F).
    pub const ERROR_CODE: u16 = 2005;
    /// TxPDO: power stage temperature in 0.1 °C (object 41).
    pub const TEMP_POWER_STAGE: u16 = 2006;
    /// TxPDO: motor temperature in 0.1 °C (object 63).
    pub const TEMP_MOTOR: u16 = 2007;
    /// TxPDO: output voltage in 0.1 V (object 434).
    pub const OUTPUT_VOLTAGE: u16 = 2008;
    /// TxPDO: DC link voltage in 0.1 V (object 33).
    pub const DC_VOLTAGE: u16 = 2009;
    /// TxPDO: hardware id, 32-bit (object 2).
    pub const HARDWARE_ID: u16 = 2010;
    /// TxPDO: hardware version, 32-bit (object 5).
    pub const HARDWARE_VERSION: u16 = 2012;
    /// TxPDO: software id, 32-bit (object 16).
    pub const SOFTWARE_ID: u16 = 2014;
    /// TxPDO: software version, 32-bit (object 17).
    pub const SOFTWARE_VERSION: u16 = 2016;
    /// TxPDO: maximum current Iq in 0.1 A (object 171).
    pub const MAX_IQ_CURRENT: u16 = 2018;
    /// TxPDO: maximum speed, 0x3FFF = speed scaling (object 120).
    pub const MAX_SPEED: u16 = 2019;
    /// TxPDO: speed scaling in 0.001 rpm, 32-bit (object 177).
    pub const SPEED_SCALING: u16 = 2020;
    /// TxPDO: current scaling in 0.001 A, 32-bit (object 182).
    pub const CURRENT_SCALING: u16 = 2022;
}

/// Status word bits (DS402 0x6041) as the model sets them.
pub mod status {
    /// Bit 0: ready to switch on.
    pub const READY_TO_SWITCH_ON: u16 = 1 << 0;
    /// Bit 1: switched on.
    pub const SWITCHED_ON: u16 = 1 << 1;
    /// Bit 2: operation enabled.
    pub const OPERATION_ENABLED: u16 = 1 << 2;
    /// Bit 3: fault.
    pub const FAULT: u16 = 1 << 3;
    /// Bit 4: voltage enabled (the simulated DC link is always powered).
    pub const VOLTAGE_ENABLED: u16 = 1 << 4;
    /// Bit 5: quick stop; 0 means a quick stop is active.
    pub const QUICK_STOP: u16 = 1 << 5;
    /// Bit 6: switch on disabled.
    pub const SWITCH_ON_DISABLED: u16 = 1 << 6;
    /// Bit 10: target reached (actual speed equals the ramp target in operation enabled).
    pub const TARGET_REACHED: u16 = 1 << 10;
    /// Bits 12-14: not documented in this manual; set as in the only printed status word (0x7038, line 1407).
    pub const UNDOCUMENTED: u16 = 0x7000;
    /// The bits that tell the DS402 state apart (CiA 402 state table).
    pub const STATE_MASK: u16 = 0x006F;
    /// Bit 9: remote (the drive takes its commands over the bus). Set only by a drive that chose
    /// `sd2x-status-word-bits=0x006F` (the reference never sets it, as the printed 0x7038 has it clear).
    pub const REMOTE: u16 = 1 << 9;
}

pub use crate::ds402::control;

/// SDO error codes the model sends (section 3.8, lines 683-712).
pub mod sdo {
    /// Client/server command not valid or unknown (control bits 0-6 not zero).
    pub const COMMAND_INVALID: u32 = 0xFFFF_0003;
    /// Unsupported access to an object (address offset not zero).
    pub const UNSUPPORTED_ACCESS: u32 = 0xFFFF_0008;
    /// Attempt to read a write-only object.
    pub const READ_WRITE_ONLY: u32 = 0xFFFF_0009;
    /// Attempt to write a read-only object.
    pub const WRITE_READ_ONLY: u32 = 0xFFFF_000A;
    /// Object does not exist.
    pub const NO_OBJECT: u32 = 0xFFFF_000B;
    /// Length not correct (byte count above 4, outside the layout's 0..4, line 550).
    pub const LENGTH_WRONG: u32 = 0xFFFF_0011;
    /// Length too long for the object.
    pub const LENGTH_TOO_LONG: u32 = 0xFFFF_0012;
    /// Length too short for the object.
    pub const LENGTH_TOO_SHORT: u32 = 0xFFFF_0013;
    /// Subindex does not exist.
    pub const NO_SUBINDEX: u32 = 0xFFFF_0014;
    /// Written value above the object's maximum.
    pub const VALUE_TOO_HIGH: u32 = 0xFFFF_0016;
    /// Written value below the object's minimum.
    pub const VALUE_TOO_LOW: u32 = 0xFFFF_0017;
}

/// Speed ramp in 0.1 Hz per second for every speed change: 100 Hz/s. The manual gives none; 0 to the 100 Hz
/// of example 6.1 takes one second, long enough to observe and short enough for tests.
pub const RAMP_PER_SECOND: i64 = 1000;

/// Error code (register 2005) after a watchdog trip when the profile names none: CiA 301 emergency code 0x8130
/// "life guard error or heartbeat error", matching the message "Heartbeat/Watchdog" (line 870).
pub const DEFAULT_WATCHDOG_ERROR_CODE: u16 = 0x8130;

/// Error code after a watchdog trip of a drive that chose `sd2x-watchdog-error-code=any-nonzero`: 0xFF00, the
/// first code of CiA 301's device-specific range (the manual prints no number, line 870).
pub const OTHER_WATCHDOG_ERROR_CODE: u16 = 0xFF00;

/// How long the fault reaction lasts at least for a drive that chose
/// `sd2x-watchdog-trip-state=fault-reaction-active` (the reference's ends at standstill).
pub const FAULT_REACTION_TIME: Duration = Duration::from_millis(250);

/// Freedoms of the SD2x manual the model acts on (`corpus/freedoms/sd2x.toml`).
pub const STATUS_WORD_BITS: &str = "sd2x-status-word-bits";
/// See [`STATUS_WORD_BITS`].
pub const WATCHDOG_ERROR_CODE: &str = "sd2x-watchdog-error-code";
/// See [`STATUS_WORD_BITS`].
pub const WATCHDOG_TRIP_STATE: &str = "sd2x-watchdog-trip-state";
/// See [`STATUS_WORD_BITS`].
pub const FC43_RESERVED_BYTE: &str = "sd2x-fc43-reserved-byte";

/// TxPDO values the model holds constant (raw bits by register address). The manual's defaults are all 0.
pub const SIMULATED: &[(u16, u32)] = &[
    // 17.0 °C: example 6.2 reads object 41 as 170 (lines 1334, 1339).
    (reg::TEMP_POWER_STAGE, 170),
    // 25.0 °C.
    (reg::TEMP_MOTOR, 250),
    // 565.0 V: a rectified 400 V mains.
    (reg::DC_VOLTAGE, 5650),
    // "SD2X" in ASCII: plainly a simulator.
    (reg::HARDWARE_ID, 0x5344_3258),
    // 2.16, the manual's own coding example (lines 1065-1067).
    (reg::HARDWARE_VERSION, 0x0002_0010),
    // "SD2S" in ASCII.
    (reg::SOFTWARE_ID, 0x5344_3253),
    // 1.20.
    (reg::SOFTWARE_VERSION, 0x0001_0014),
    // 15.0 A.
    (reg::MAX_IQ_CURRENT, 150),
    // Full scale: max speed = speed scaling (line 1137).
    (reg::MAX_SPEED, 0x3FFF),
    // 12000 rpm in 0.001 rpm.
    (reg::SPEED_SCALING, 12_000_000),
    // 15 A in 0.001 A, agreeing with max Iq.
    (reg::CURRENT_SCALING, 15_000),
];

/// Speed is kept in 1/FINE of 0.1 Hz so that ramps over sub-millisecond steps lose nothing to rounding.
const FINE: i64 = 1000;
/// Magnetising current with the power stage on, 0.1 A (2.0 A).
const NO_LOAD_CURRENT: i64 = 20;
/// Speed (0.1 Hz) per 0.1 A of load current: 100 Hz adds 4.0 A.
const SPEED_PER_CURRENT: i64 = 25;
/// V/f characteristic: 0.1 V of output per 0.1 Hz (400 V at 100 Hz) ...
const VOLTS_PER_SPEED: i64 = 4;
/// ... up to 400.0 V, then field weakening.
const MAX_OUTPUT_VOLTAGE: i64 = 4000;
/// √3 · cos φ (0.8) · 1000, for P = √3 · U · I · cos φ.
const POWER_FACTOR_MILLI: i64 = 1386;

/// A state of the CiA 402 (DS402) drive state machine. "Not ready to switch on" is passed during boot and
/// never observable, so it has no variant.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ds402State {
    SwitchOnDisabled,
    ReadyToSwitchOn,
    SwitchedOn,
    OperationEnabled,
    QuickStopActive,
    FaultReactionActive,
    Fault,
}

impl Ds402State {
    /// The state-coding bits of the status word (bits 0-3 and 6; bit 5 is added by the model).
    pub fn state_bits(self) -> u16 {
        use status::*;
        match self {
            Ds402State::SwitchOnDisabled => SWITCH_ON_DISABLED,
            Ds402State::ReadyToSwitchOn => READY_TO_SWITCH_ON,
            Ds402State::SwitchedOn => READY_TO_SWITCH_ON | SWITCHED_ON,
            Ds402State::OperationEnabled | Ds402State::QuickStopActive => {
                READY_TO_SWITCH_ON | SWITCHED_ON | OPERATION_ENABLED
            }
            Ds402State::FaultReactionActive => {
                READY_TO_SWITCH_ON | SWITCHED_ON | OPERATION_ENABLED | FAULT
            }
            Ds402State::Fault => FAULT,
        }
    }

    /// True while the power stage drives the motor.
    pub fn power_stage_on(self) -> bool {
        matches!(
            self,
            Ds402State::OperationEnabled
                | Ds402State::QuickStopActive
                | Ds402State::FaultReactionActive
        )
    }
}

/// A device control command decoded from the control word (bit 7 clear), CiA 402 command table.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Command {
    DisableVoltage,
    QuickStop,
    Shutdown,
    SwitchOn,
    EnableOperation,
}

impl Command {
    fn decode(cw: u16) -> Self {
        use control::*;
        if cw & ENABLE_VOLTAGE == 0 {
            Command::DisableVoltage
        } else if cw & QUICK_STOP == 0 {
            Command::QuickStop
        } else if cw & SWITCH_ON == 0 {
            Command::Shutdown
        } else if cw & ENABLE_OPERATION == 0 {
            Command::SwitchOn
        } else {
            Command::EnableOperation
        }
    }
}

/// What a register offers to reads and writes, copied out of the profile so that `self` can be mutated.
#[derive(Clone, Copy, Debug)]
struct Slot {
    address: u16,
    width: u8,
    access: Access,
    signed: bool,
    range: (i64, i64),
}

/// What an object offers, copied out of the profile.
#[derive(Clone, Copy, Debug)]
struct ObjectSlot {
    ty: ObjectType,
    access: Access,
    min: Option<i64>,
    max: Option<i64>,
    /// The PDO register the object mirrors, if the profile has it.
    register: Option<u16>,
}

/// Why an object access failed: a plain Modbus exception or an SDO error.
enum ObjectError {
    Exception(ExceptionCode),
    Sdo(u32),
}

/// The SD2x drive model.
#[derive(Clone)]
pub struct Sd2x {
    profile: Arc<Profile>,
    faults: FaultSet,
    now: Duration,
    state: Ds402State,
    /// Raw bits of every register by start address: RxPDO as written, TxPDO constants.
    regs: BTreeMap<u16, u32>,
    /// Objects that mirror no register, by (index, subindex).
    objects: BTreeMap<(u16, u8), u32>,
    /// Actual speed in 1/FINE of 0.1 Hz.
    speed_fine: i64,
    error_code: u16,
    /// When the watchdog expires; `None` when it is off or has tripped.
    watchdog_deadline: Option<Duration>,
    /// The values taken where the freedoms leave a choice, and the freedoms that decided the answer being given.
    freedoms: Freedoms,
    /// Until when a fault reaction lasts at least (`sd2x-watchdog-trip-state=fault-reaction-active`).
    reaction_until: Duration,
}

/// Raw bits of `value` at `bytes` bytes (two's complement for negatives).
fn raw_bits(value: i64, bytes: usize) -> u32 {
    if bytes >= 4 {
        value as u32
    } else {
        (value as u32) & 0xFFFF
    }
}

/// The integer a register or object holds, from its raw bits.
fn signed_value(raw: u32, bytes: usize, signed: bool) -> i64 {
    match (bytes >= 4, signed) {
        (true, true) => i64::from(raw as i32),
        (true, false) => i64::from(raw),
        (false, true) => i64::from(raw as u16 as i16),
        (false, false) => i64::from(raw as u16),
    }
}

fn clamp_i16(v: i64) -> i16 {
    v.clamp(i64::from(i16::MIN), i64::from(i16::MAX)) as i16
}

impl Sd2x {
    /// Build the model from its profile, at power-on (time zero, switch on disabled).
    pub fn new(profile: Profile, faults: FaultSet, choices: Choices) -> Self {
        let mut regs = BTreeMap::new();
        for r in profile.registers.iter().map(|r| r.get_ref()) {
            let bytes = 2 * usize::from(r.width);
            regs.insert(r.address, raw_bits(r.default.unwrap_or(0), bytes));
        }
        // Only registers the profile maps get a simulated value: the profile decides what exists.
        for &(address, value) in SIMULATED {
            if let Some(v) = regs.get_mut(&address) {
                *v = value;
            }
        }
        let mut model = Self {
            profile: Arc::new(profile),
            faults,
            now: Duration::ZERO,
            state: Ds402State::SwitchOnDisabled,
            regs,
            objects: BTreeMap::new(),
            speed_fine: 0,
            error_code: 0,
            watchdog_deadline: None,
            freedoms: Freedoms::new(choices),
            reaction_until: Duration::ZERO,
        };
        let unmapped: Vec<((u16, u8), u32)> = model
            .profile
            .objects
            .iter()
            .map(|o| o.get_ref())
            .filter(|o| model.object_register(o.index, o.subindex).is_none())
            .map(|o| {
                (
                    (o.index, o.subindex),
                    raw_bits(o.default.unwrap_or(0), o.ty.size()),
                )
            })
            .collect();
        model.objects.extend(unmapped);
        model
    }

    /// The DS402 state.
    pub fn state(&self) -> Ds402State {
        self.state
    }

    /// The model's clock: the latest time it was advanced to.
    pub fn now(&self) -> Duration {
        self.now
    }

    /// The error code register (2005).
    pub fn error_code(&self) -> u16 {
        self.error_code
    }

    /// Actual speed in 0.1 Hz (register 2001).
    pub fn actual_speed(&self) -> i16 {
        // Truncation toward zero: a speed is only reported once it is fully reached.
        clamp_i16(self.speed_fine / FINE)
    }

    /// The status word (register 2000), composed as the module documentation describes.
    ///
    /// A drive that chose `sd2x-status-word-bits=0x006F` keeps the DS402 state bits (0x006F) and sets the
    /// bits the manual leaves to another document its own way: bits 4, 10 and 12-14 clear, bit 9 (remote)
    /// set.
    pub fn status_word(&self) -> u16 {
        let mut s = self.state.state_bits() | status::VOLTAGE_ENABLED | status::UNDOCUMENTED;
        if self.state != Ds402State::QuickStopActive {
            s |= status::QUICK_STOP;
        }
        if self.state == Ds402State::OperationEnabled
            && self.speed_fine == i64::from(self.ramp_target()).saturating_mul(FINE)
        {
            s |= status::TARGET_REACHED;
        }
        match self.status_bits_own() {
            Some(status::STATE_MASK) => s = (s & status::STATE_MASK) | status::REMOTE,
            // As a drive written independently from the manual does: bit 5 set only in the states whose
            // bit 5 the DS402 state table gives (switch on disabled reads 0x0650).
            Some(crate::ds402::status::BIT5_OPEN_MASK) => {
                s = (s & status::STATE_MASK) | status::REMOTE | status::VOLTAGE_ENABLED;
                if crate::ds402::status::bit5_open(s) {
                    s &= !status::QUICK_STOP;
                }
            }
            _ => {}
        }
        if self.has(Fault::QuickStopBitClear) && self.state == Ds402State::OperationEnabled {
            s &= !status::QUICK_STOP;
        }
        s
    }

    /// The mask of the status-word bits the drive keeps as the reference does, where it sets the others its
    /// own way (`sd2x-status-word-bits`: 0x006F or 0x004F); `None` for the reference's word.
    fn status_bits_own(&self) -> Option<u16> {
        match self.freedoms.choices().get(STATUS_WORD_BITS) {
            Some(crate::requirements::FreedomValue::Int(m))
                if *m == i64::from(status::STATE_MASK)
                    || *m == i64::from(crate::ds402::status::BIT5_OPEN_MASK) =>
            {
                Some(*m as u16)
            }
            _ => None,
        }
    }

    fn has(&self, f: Fault) -> bool {
        self.faults.has(f)
    }

    fn stored(&self, address: u16) -> u32 {
        self.regs.get(&address).copied().unwrap_or(0)
    }

    fn control_word(&self) -> u16 {
        self.stored(reg::CONTROL_WORD) as u16
    }

    /// The speed the motor ramps towards: the target speed in operation enabled without halt, else 0.
    fn ramp_target(&self) -> i16 {
        // The fault: the setpoint is followed in every state where the power stage should be off (the
        // stopping states still ramp to 0, so that they complete).
        let follows = self.state == Ds402State::OperationEnabled
            || (self.has(Fault::SpeedWithoutEnable)
                && matches!(
                    self.state,
                    Ds402State::SwitchOnDisabled
                        | Ds402State::ReadyToSwitchOn
                        | Ds402State::SwitchedOn
                ));
        if follows && self.control_word() & control::HALT == 0 {
            self.stored(reg::TARGET_SPEED) as u16 as i16
        } else {
            0
        }
    }

    fn max_iq(&self) -> i64 {
        i64::from(self.stored(reg::MAX_IQ_CURRENT) as u16 as i16).abs()
    }

    /// The word order of 32-bit pairs on the wire: the profile's, flipped by the word-order fault.
    fn word_order(&self) -> WordOrder {
        let order = self.profile.device.word_order;
        if !self.has(Fault::WordOrder) {
            return order;
        }
        match order {
            WordOrder::HighFirst => WordOrder::LowFirst,
            WordOrder::LowFirst => WordOrder::HighFirst,
        }
    }

    fn watchdog_register(&self) -> Option<u16> {
        self.profile.watchdog.as_ref().map(|w| w.register)
    }

    // -----------------------------------------------------------------------------------------------------
    // Time
    // -----------------------------------------------------------------------------------------------------

    /// Move the speed ramp from `self.now` to `to` (no events in between).
    fn step(&mut self, to: Duration) {
        if to <= self.now {
            return;
        }
        let elapsed_us = i128::try_from((to - self.now).as_micros()).unwrap_or(i128::MAX);
        let target = i64::from(self.ramp_target()).saturating_mul(FINE);
        let max_delta = elapsed_us
            .saturating_mul(i128::from(RAMP_PER_SECOND) * i128::from(FINE))
            .checked_div(1_000_000)
            .unwrap_or(0);
        let gap = i128::from(target) - i128::from(self.speed_fine);
        let delta = gap.clamp(-max_delta, max_delta);
        // |delta| <= |gap|, so the sum lies between the old speed and the target: it fits an i64.
        self.speed_fine = (i128::from(self.speed_fine) + delta) as i64;
        self.now = to;
        self.settle();
    }

    /// The automatic transitions that wait for standstill: quick stop (option code 2) and fault reaction.
    fn settle(&mut self) {
        if self.speed_fine != 0
            || (self.state == Ds402State::FaultReactionActive && self.now < self.reaction_until)
        {
            return;
        }
        self.state = match self.state {
            Ds402State::QuickStopActive => Ds402State::SwitchOnDisabled,
            Ds402State::FaultReactionActive => Ds402State::Fault,
            s => s,
        };
    }

    fn trip_watchdog(&mut self) {
        self.watchdog_deadline = None;
        if matches!(
            self.state,
            Ds402State::Fault | Ds402State::FaultReactionActive
        ) {
            // Already faulted: the first fault's code stays.
            return;
        }
        self.error_code =
            if self.freedoms.choices().name(WATCHDOG_ERROR_CODE) == Some("any-nonzero") {
                // Another non-zero code: the first of CiA 301's device-specific range.
                OTHER_WATCHDOG_ERROR_CODE
            } else {
                self.profile
                    .watchdog
                    .as_ref()
                    .and_then(|w| w.fault_error_code)
                    .unwrap_or(DEFAULT_WATCHDOG_ERROR_CODE)
            };
        self.state = Ds402State::FaultReactionActive;
        if self.freedoms.choices().name(WATCHDOG_TRIP_STATE) == Some("fault-reaction-active") {
            // A drive whose fault reaction takes its time even from standstill (a brake to apply, the
            // power stage to switch off): the manual gives no stopping time (line 870).
            self.reaction_until = self.now.saturating_add(FAULT_REACTION_TIME);
        }
        self.settle();
    }

    /// Start (non-zero) or stop (0) the watchdog at the model's clock.
    fn arm_watchdog(&mut self, value: u16) {
        let unit_ms = self.profile.watchdog.as_ref().map_or(1, |w| w.unit_ms);
        self.watchdog_deadline = if value == 0 {
            None
        } else if self.has(Fault::WatchdogFromFirstWrite) && self.watchdog_deadline.is_some() {
            // The fault: a rewrite while armed leaves the deadline of the write that armed it.
            self.watchdog_deadline
        } else {
            let ms = u64::from(value).saturating_mul(u64::from(unit_ms));
            // An overflowing deadline is one that never comes.
            self.now.checked_add(Duration::from_millis(ms))
        };
    }

    // -----------------------------------------------------------------------------------------------------
    // DS402
    // -----------------------------------------------------------------------------------------------------

    /// Evaluate a newly written control word against the state machine (CiA 402 transitions 2-12, 15).
    fn apply_control_word(&mut self, old: u16, new: u16) {
        use Ds402State::*;
        if new & control::FAULT_RESET != 0 {
            // Bit 7 set: only its rising edge acts, and only in fault; while it stays high no other command
            // is taken (every command pattern of the CiA 402 table has bit 7 clear).
            if old & control::FAULT_RESET == 0 && self.state == Fault {
                self.state = SwitchOnDisabled;
                self.error_code = 0;
            }
            return;
        }
        let cmd = Command::decode(new);
        self.state = match (self.state, cmd) {
            (SwitchOnDisabled, Command::Shutdown) => ReadyToSwitchOn,
            // The fault: CiA 402 has no transition from switch on disabled but shutdown (transition 2).
            (SwitchOnDisabled, Command::EnableOperation)
                if self.has(crate::faults::Fault::Ds402EnableFromSwitchOnDisabled) =>
            {
                OperationEnabled
            }
            (ReadyToSwitchOn, Command::SwitchOn) => SwitchedOn,
            // "Switch on + enable operation" from ready to switch on: transitions 3 and 4 at once, which
            // example 6.1 relies on (shutdown, then 0x000F, then the motor runs: lines 1224-1267).
            (ReadyToSwitchOn | SwitchedOn, Command::EnableOperation) => OperationEnabled,
            (SwitchedOn | OperationEnabled, Command::Shutdown) => ReadyToSwitchOn,
            (OperationEnabled, Command::SwitchOn) => SwitchedOn,
            (OperationEnabled, Command::QuickStop) => QuickStopActive,
            (
                ReadyToSwitchOn | SwitchedOn | OperationEnabled | QuickStopActive,
                Command::DisableVoltage,
            ) => SwitchOnDisabled,
            (ReadyToSwitchOn | SwitchedOn, Command::QuickStop) => SwitchOnDisabled,
            (s, _) => s,
        };
    }

    // -----------------------------------------------------------------------------------------------------
    // Registers
    // -----------------------------------------------------------------------------------------------------

    /// The profile register covering `address`. FC 03 and FC 04 see one map (line 327), so either table.
    fn slot(&self, address: u16) -> Option<Slot> {
        let r = self
            .profile
            .register_at(address, false)
            .or_else(|| self.profile.register_at(address, true))?;
        Some(Slot {
            address: r.address,
            width: r.width,
            access: r.access,
            signed: r.signed,
            range: r.range(),
        })
    }

    /// The raw bits of the register starting at `address`: live values for the TxPDO actual values.
    fn register_raw(&self, address: u16) -> u32 {
        let on = self.state.power_stage_on();
        let speed = i64::from(self.actual_speed()).abs();
        let current = if on {
            NO_LOAD_CURRENT
                .saturating_add(speed / SPEED_PER_CURRENT)
                .min(self.max_iq())
        } else {
            0
        };
        let voltage = if on {
            speed
                .saturating_mul(VOLTS_PER_SPEED)
                .min(MAX_OUTPUT_VOLTAGE)
        } else {
            0
        };
        let as_raw = |v: i64| u32::from(clamp_i16(v) as u16);
        match address {
            reg::STATUS_WORD => u32::from(self.status_word()),
            reg::ACTUAL_SPEED => u32::from(self.actual_speed() as u16),
            reg::TORQUE_LIMIT_ACTUAL => {
                // "It is limited by the drive peak current" (line 854).
                let max = self.max_iq();
                as_raw(i64::from(self.stored(reg::TORQUE_LIMIT) as u16 as i16).clamp(-max, max))
            }
            reg::APPARENT_CURRENT => as_raw(current),
            // U in 0.1 V times I in 0.1 A is in 0.01 W; 0.1 kW is 10^4 of those, and the factor is milli.
            reg::OUTPUT_POWER => as_raw(
                voltage
                    .saturating_mul(current)
                    .saturating_mul(POWER_FACTOR_MILLI)
                    / 10_000_000,
            ),
            reg::OUTPUT_VOLTAGE => as_raw(voltage),
            reg::ERROR_CODE => u32::from(self.error_code),
            a => self.stored(a),
        }
    }

    /// One register word as read on the wire.
    fn read_word(&self, address: u16) -> Result<u16, ExceptionCode> {
        match self.slot(address) {
            Some(s) if s.access.readable() => {
                let raw = self.register_raw(s.address);
                if s.width == 2 {
                    let words = self.word_order().split(raw);
                    let i = usize::from(address.wrapping_sub(s.address)).min(1);
                    Ok(words[i])
                } else {
                    Ok(raw as u16)
                }
            }
            _ if self.has(Fault::ReservedReadable) => Ok(0),
            _ => Err(ExceptionCode::ILLEGAL_DATA_ADDRESS),
        }
    }

    /// Read `quantity` registers from `address`; any unreadable one fails the whole read with 02.
    fn read_block(&self, address: u16, quantity: u16) -> Result<Vec<u16>, ExceptionCode> {
        let end = range_end(address, usize::from(quantity))?;
        (u32::from(address)..end)
            .map(|a| self.read_word(a as u16))
            .collect()
    }

    /// Validate a write of `values` from `address` and return the new raw value of every register touched.
    /// Nothing is changed: a request is written whole or not at all.
    fn stage_write(&self, address: u16, values: &[u16]) -> Result<Vec<(u16, u32)>, Rejection> {
        let end = range_end(address, values.len())?;
        let order = self.word_order();
        let mut staged: BTreeMap<u16, (Slot, u32)> = BTreeMap::new();
        for (a, &v) in (u32::from(address)..end).zip(values) {
            let a = a as u16;
            let slot = self.slot(a).ok_or(ExceptionCode::ILLEGAL_DATA_ADDRESS)?;
            if !slot.access.writable() && !self.has(Fault::ReadOnlyWritable) {
                // The TxPDO is the input-register image (line 726): not a valid address to write (line 672).
                return Err(self
                    .freedoms
                    .choices()
                    .reject(ids::WRITE_READ_ONLY, ExceptionCode::ILLEGAL_DATA_ADDRESS));
            }
            let entry = staged
                .entry(slot.address)
                .or_insert((slot, self.stored(slot.address)));
            entry.1 = if slot.width == 2 {
                let mut words = order.split(entry.1);
                words[usize::from(a.wrapping_sub(slot.address)).min(1)] = v;
                order.join(words[0], words[1])
            } else {
                u32::from(v)
            };
        }
        if !self.has(Fault::RangeUnchecked) {
            for (slot, raw) in staged.values() {
                // A read-only register written under the read-only-writable fault has no range to check.
                if !slot.access.writable() {
                    continue;
                }
                let v = signed_value(*raw, 2 * usize::from(slot.width), slot.signed);
                if v < slot.range.0 || v > slot.range.1 {
                    return Err(ExceptionCode::ILLEGAL_DATA_VALUE.into());
                }
            }
        }
        Ok(staged.into_iter().map(|(a, (_, raw))| (a, raw)).collect())
    }

    /// Store validated register values and apply their effects (watchdog restart, control word).
    fn commit(&mut self, staged: Vec<(u16, u32)>) {
        let old_control = self.control_word();
        let mut control_written = false;
        let mut watchdog_written = None;
        let watchdog = self.watchdog_register();
        for (address, raw) in staged {
            self.regs.insert(address, raw);
            control_written |= address == reg::CONTROL_WORD;
            if Some(address) == watchdog {
                watchdog_written = Some(raw as u16);
            }
        }
        if let Some(v) = watchdog_written {
            self.arm_watchdog(v);
        }
        if control_written {
            self.apply_control_word(old_control, self.control_word());
        }
        // A quick stop or a fault from standstill completes at once.
        self.settle();
    }

    // -----------------------------------------------------------------------------------------------------
    // FC 43 / MEI 0x0D
    // -----------------------------------------------------------------------------------------------------

    /// The register an object mirrors, if both the mapping and the register exist.
    fn object_register(&self, index: u16, subindex: u8) -> Option<u16> {
        if subindex != 0 {
            return None;
        }
        let address = &self.profile.object(index, 0)?.register?;
        self.profile
            .registers
            .iter()
            .any(|r| r.get_ref().address == *address)
            .then_some(*address)
    }

    fn object_slot(&self, index: u16, subindex: u8) -> Result<ObjectSlot, u32> {
        match self.profile.object(index, subindex) {
            Some(o) => Ok(ObjectSlot {
                ty: o.ty,
                access: o.access,
                min: o.min,
                max: o.max,
                register: self.object_register(index, subindex),
            }),
            None if self
                .profile
                .objects
                .iter()
                .any(|o| o.get_ref().index == index) =>
            {
                Err(sdo::NO_SUBINDEX)
            }
            None => Err(sdo::NO_OBJECT),
        }
    }

    fn object_raw(&self, index: u16, subindex: u8, o: &ObjectSlot) -> u32 {
        match o.register {
            Some(address) => self.register_raw(address),
            None => self.objects.get(&(index, subindex)).copied().unwrap_or(0),
        }
    }

    /// The SDO error for a byte count `n` against an object of `size` bytes, if any. Which of the length
    /// codes a drive gives is a freedom; the reference's are the most specific ones.
    fn length_error(&mut self, n: usize, size: usize) -> Result<(), ObjectError> {
        let reference = if n > 4 {
            if self.has(Fault::ByteCountOver4Served) {
                return Ok(());
            }
            sdo::LENGTH_WRONG
        } else if n > size {
            sdo::LENGTH_TOO_LONG
        } else if n < size {
            sdo::LENGTH_TOO_SHORT
        } else {
            return Ok(());
        };
        self.decided(ids::SDO_LENGTH_ERROR);
        Err(ObjectError::Sdo(
            match self.freedoms.choices().get(ids::SDO_LENGTH_ERROR) {
                Some(crate::requirements::FreedomValue::Int(c)) => {
                    u32::try_from(*c).unwrap_or(reference)
                }
                _ => reference,
            },
        ))
    }

    /// The answer to `a` as an FC 43 response (an exception, an SDO error, or the access served).
    fn object_response(&mut self, unit: u8, a: &CanOpenAccess) -> Response {
        match self.object_access(unit, a) {
            Ok(r) => r,
            Err(ObjectError::Exception(code)) => {
                Response::exception(FunctionCode::ENCAPSULATED_INTERFACE, code)
            }
            Err(ObjectError::Sdo(sdo_code)) => Response::CanOpenError { sdo_code },
        }
    }

    /// What a drive leaving the unused field of `freedom` alone (`response`) answers to `a`: the telegram with
    /// that field zero, and with every unused field zero (a drive may leave them all alone), answered on a copy
    /// of this drive as it is (for the oracle: [`crate::choices::Freedoms::alternative`]). Not for the
    /// reserved byte, which the reference leaves alone already.
    fn unused_field_alternatives(&mut self, unit: u8, a: &CanOpenAccess, freedom: Decision) {
        let zero_control = |x: &mut CanOpenAccess| x.control &= CanOpenAccess::WRITE;
        let zero_offset = |x: &mut CanOpenAccess| x.offset = 0;
        let mut this = a.clone();
        match freedom {
            ids::SD2X_FC43_CONTROL_BITS => zero_control(&mut this),
            ids::SD2X_FC43_OFFSET_NONZERO => zero_offset(&mut this),
            _ => return,
        }
        let mut all = a.clone();
        zero_control(&mut all);
        zero_offset(&mut all);
        for zeroed in [this, all] {
            let mut copy = self.clone();
            let answer = copy.object_response(unit, &zeroed);
            self.freedoms.alternative(freedom, "response", answer);
        }
    }

    fn object_access(&mut self, unit: u8, a: &CanOpenAccess) -> Result<Response, ObjectError> {
        // A byte count outside the layout's 0..4 (line 550): the reference answers the SDO length error once
        // the other checks pass; a drive may refuse the field's value with 03 first, as the specification
        // orders a quantity check before the address (`sd2x-fc43-byte-count-over-4`).
        if a.byte_count > 4 && !self.has(Fault::ByteCountOver4Served) {
            self.decided(ids::SD2X_FC43_BYTE_COUNT_OVER_4);
            if self
                .freedoms
                .choices()
                .name(ids::SD2X_FC43_BYTE_COUNT_OVER_4)
                == Some("exception-03")
            {
                return Err(ObjectError::Exception(ExceptionCode::ILLEGAL_DATA_VALUE));
            }
        }
        // Fields the manual says to set to zero (control bits 0-6, line 608; the reserved field, line 545; the
        // address offset, line 627): the reference answers the SDO errors of the field (or ignores the
        // reserved byte) after the other checks; a drive may refuse the value with 03 first, or leave the
        // field alone, as "not used" says (`sd2x-fc43-control-bits`, `sd2x-fc43-reserved-nonzero`,
        // `sd2x-fc43-offset-nonzero`).
        let mut ignored = Vec::new();
        for (id, set) in [
            (
                ids::SD2X_FC43_CONTROL_BITS,
                a.control & !CanOpenAccess::WRITE != 0,
            ),
            (ids::SD2X_FC43_RESERVED_NONZERO, a.reserved != 0),
            (ids::SD2X_FC43_OFFSET_NONZERO, a.offset != 0),
        ] {
            if !set {
                continue;
            }
            if self.has(Fault::ZeroFieldsBusy) {
                return Err(ObjectError::Exception(ExceptionCode::SERVER_DEVICE_BUSY));
            }
            self.decided(id);
            let choice = self.freedoms.choices().name(id).map(str::to_owned);
            if choice.as_deref() != Some("response") {
                self.unused_field_alternatives(unit, a, id);
            }
            match choice.as_deref() {
                Some("exception-03") => {
                    return Err(ObjectError::Exception(ExceptionCode::ILLEGAL_DATA_VALUE));
                }
                Some("response") => ignored.push(id),
                _ => {}
            }
        }
        // The node-ID is the slave address (line 613), 01h..7Fh (line 546).
        if a.node_id != unit || !(0x01..=0x7F).contains(&a.node_id) {
            // Which code the manual does not say: 02 (no such node) or 03 (`sd2x-fc43-node-id`).
            self.decided(ids::SD2X_FC43_NODE_ID);
            let code = self
                .freedoms
                .choices()
                .code(ids::SD2X_FC43_NODE_ID, ExceptionCode::ILLEGAL_DATA_ADDRESS);
            return Err(ObjectError::Exception(code));
        }
        if a.control & !CanOpenAccess::WRITE != 0 && !ignored.contains(&ids::SD2X_FC43_CONTROL_BITS)
        {
            return Err(ObjectError::Sdo(sdo::COMMAND_INVALID));
        }
        let o = self
            .object_slot(a.index, a.subindex)
            .map_err(ObjectError::Sdo)?;
        if a.offset != 0 && !ignored.contains(&ids::SD2X_FC43_OFFSET_NONZERO) {
            return Err(ObjectError::Sdo(sdo::UNSUPPORTED_ACCESS));
        }
        let size = o.ty.size();
        let header = |control: u8, byte_count: u16, data: Vec<u8>| {
            Response::CanOpen(CanOpenAccess {
                control,
                reserved: 0,
                node_id: a.node_id,
                index: a.index,
                subindex: a.subindex,
                offset: 0,
                byte_count,
                data,
            })
        };
        if a.is_write() {
            if !o.access.writable() && !self.has(Fault::ReadOnlyWritable) {
                return Err(ObjectError::Sdo(sdo::WRITE_READ_ONLY));
            }
            self.length_error(a.data.len(), size)?;
            let raw = a.value_le().unwrap_or(0);
            let signed = matches!(o.ty, ObjectType::I16 | ObjectType::I32);
            let v = signed_value(raw, size, signed);
            if !self.has(Fault::RangeUnchecked) {
                if o.max.is_some_and(|m| v > m) {
                    return Err(ObjectError::Sdo(sdo::VALUE_TOO_HIGH));
                }
                if o.min.is_some_and(|m| v < m) {
                    return Err(ObjectError::Sdo(sdo::VALUE_TOO_LOW));
                }
            }
            match o.register {
                // Through the register path, so that a control word written here drives the state machine.
                Some(address) => {
                    let width = self.slot(address).map_or(1, |s| s.width);
                    self.commit(vec![(address, raw_bits(v, 2 * usize::from(width)))]);
                }
                None => {
                    self.objects.insert((a.index, a.subindex), raw);
                }
            }
            Ok(header(CanOpenAccess::WRITE, a.byte_count, Vec::new()))
        } else {
            if !o.access.readable() {
                return Err(ObjectError::Sdo(sdo::READ_WRITE_ONLY));
            }
            // A read of 0 bytes: the manual does not say what it answers (sd2x-fc43-read-zero-count).
            let mut count = usize::from(a.byte_count);
            if count == 0 && self.has(Fault::ZeroCountPartial) {
                let raw = self.object_raw(a.index, a.subindex, &o);
                return Ok(header(0, 1, raw.to_le_bytes()[..1].to_vec()));
            }
            if count == 0 {
                self.decided(ids::SD2X_FC43_READ_ZERO_COUNT);
                match self.freedoms.choices().name(ids::SD2X_FC43_READ_ZERO_COUNT) {
                    Some("object-size") => count = size,
                    Some("zero") => return Ok(header(0, 0, Vec::new())),
                    _ => {}
                }
            }
            self.length_error(count, size)?;
            let raw = self.object_raw(a.index, a.subindex, &o);
            // Little-endian, unlike the rest of Modbus (line 638).
            let data = raw.to_le_bytes()[..size].to_vec();
            Ok(header(0, size as u16, data))
        }
    }
}

/// One register map for FC 03 and FC 04 (line 327); writes staged whole, then committed with their effects.
impl DataModel for Sd2x {
    type Plan = Vec<(u16, u32)>;

    fn read_registers(
        &self,
        _table: RegTable,
        address: u16,
        quantity: u16,
    ) -> Result<Vec<u16>, Rejection> {
        Ok(self.read_block(address, quantity)?)
    }

    fn plan_write(&self, address: u16, words: &[u16]) -> Result<Self::Plan, Rejection> {
        self.stage_write(address, words)
    }

    fn decided(&mut self, freedom: Decision) {
        self.freedoms.decided(freedom);
    }

    fn commit(&mut self, plan: Self::Plan) {
        Sd2x::commit(self, plan);
    }
}

impl DriveModel for Sd2x {
    fn profile(&self) -> &Profile {
        &self.profile
    }

    fn freedoms(&mut self) -> &mut Freedoms {
        &mut self.freedoms
    }

    fn advance(&mut self, now: Duration) {
        if now <= self.now {
            return;
        }
        // Split the interval at the watchdog deadline so the fault reaction ramps from the right moment.
        if let Some(deadline) = self.watchdog_deadline
            && deadline < now
            && !self.has(Fault::WatchdogDisabled)
        {
            self.step(deadline);
            self.trip_watchdog();
        }
        self.step(now);
    }

    fn handle(&mut self, now: Duration, unit: u8, request: &Request) -> Option<Response> {
        self.advance(now);
        let fc = request.function();
        let result = match request {
            Request::CanOpen(a) => return Some(self.object_response(unit, a)),
            // Registers (FC 03/04/06/10/17); FC 03 and FC 04 read the same map (line 327).
            other => match data_model::serve(self, other) {
                Some(r) => return Some(r),
                // MEI 0x0E and any other MEI type: only 0Dh is supported (line 603). Anything else the station
                // let through is not a function this drive implements either.
                None => Err(ExceptionCode::ILLEGAL_FUNCTION),
            },
        };
        Some(result.unwrap_or_else(|code| Response::exception(fc, code)))
    }
}
