//! The DS402 (CiA 402) state machine over the drive's process data, and its RxPDO watchdog (SD2x).

use std::time::Duration;

use super::around::Around;
use super::{Ctx, exchange, pdu};
use crate::cases::{Compare, Outgoing, Step, Tag};
use codec::Request;
use drives::ds402::control::{
    CMD_DISABLE_VOLTAGE, CMD_ENABLE_OPERATION, CMD_FAULT_RESET, CMD_SHUTDOWN, CMD_SWITCH_ON,
};
use drives::profile::{Access, Profile, Register, Watchdog};

const MANUAL: &str =
    "SD2x manual, section 4 (process data), 6.1 (drive operation); CiA 402 state machine";

/// The DS402 suite, for a profile with a watchdog register and a writable control word below it.
pub(super) fn cases(cx: &mut Ctx) {
    let p = cx.p;
    let Some(w) = p.watchdog.as_ref() else { return };
    let Some(pd) = ProcessData::find(p, w) else {
        return;
    };
    enable_sequence(cx, &pd);
    enable_from_switch_on_disabled(cx, &pd);
    speed_zero_when_not_enabled(cx, &pd);
    watchdog(cx, &pd, w);
    watchdog_refreshed(cx, &pd, w);
}

/// The RxPDO block from the control word up to the watchdog register, and the words that show the state.
struct ProcessData {
    /// The control word's address: the first of the block.
    base: u16,
    /// Registers in the block; the watchdog is the last.
    n: usize,
    status: u16,
    error_code: u16,
    /// The target speed (a writable register of the block named for speed or velocity), if any.
    target_speed: Option<u16>,
    /// The actual speed (a read-only register named for speed but not for a limit or a scaling), if any.
    actual_speed: Option<u16>,
}

impl ProcessData {
    /// The block of a profile whose watchdog is `w`, if a writable register lies at most 3 below it.
    fn find(p: &Profile, w: &Watchdog) -> Option<Self> {
        let ctrl = p.registers.iter().map(|r| r.get_ref()).find(|r| {
            r.access.writable() && r.address < w.register && w.register - r.address <= 3
        })?;
        let base = ctrl.address;
        let n = (w.register - base + 1) as usize;
        let ro = |pred: &dyn Fn(&Register) -> bool| {
            p.registers
                .iter()
                .map(|r| r.get_ref())
                .find(|r| r.access == Access::Ro && r.width == 1 && pred(r))
                .map(|r| r.address)
        };
        let status = ro(&|_| true).unwrap_or(2000);
        let error_code = ro(&|r| r.name.to_ascii_lowercase().contains("error")).unwrap_or(status);
        let speedy = |r: &Register| {
            let name = r.name.to_ascii_lowercase();
            name.contains("speed") || name.contains("velocity")
        };
        let target_speed = p
            .registers
            .iter()
            .map(|r| r.get_ref())
            .find(|r| {
                r.access.writable()
                    && r.width == 1
                    && r.address > base
                    && r.address < w.register
                    && speedy(r)
            })
            .map(|r| r.address);
        let actual_speed = ro(&|r| {
            let name = r.name.to_ascii_lowercase();
            speedy(r) && !name.contains("max") && !name.contains("scaling")
        });
        Some(Self {
            base,
            n,
            status,
            error_code,
            target_speed,
            actual_speed,
        })
    }

    /// The whole block in one FC 16: control word `cw`, watchdog time `wd` (ms), zeros between.
    fn write(&self, cw: u16, wd: u16) -> Outgoing {
        self.write_with_speed(cw, 0, wd)
    }

    /// As [`Self::write`], with `speed` in the target speed register (when the block has one).
    fn write_with_speed(&self, cw: u16, speed: u16, wd: u16) -> Outgoing {
        let n = self.n;
        let mut v = vec![0u16; n];
        v[0] = cw;
        if let Some(t) = self.target_speed {
            v[usize::from(t - self.base)] = speed;
        }
        v[n - 1] = wd;
        Outgoing::Pdu(pdu(&Request::WriteMultipleRegisters {
            address: self.base,
            values: v,
        }))
    }

    /// Watchdog off, fault reset, back to switch on disabled. The watchdog goes off in a write of its own
    /// first: a drive may apply the registers of one FC 16 in any order, and take the fault reset while the
    /// watchdog that tripped it is still set and expired, which it may refuse to reset, the cause still
    /// being there (tests/independent/sd2x-k); control word 0 there also makes the reset's bit 7 a rising
    /// edge, whatever was written before.
    fn reset(&self) -> Vec<Step> {
        vec![
            exchange(
                self.write(CMD_DISABLE_VOLTAGE, 0),
                Compare::Exact,
                "watchdog off, control word 0",
            ),
            exchange(
                self.write(CMD_FAULT_RESET, 0),
                Compare::Exact,
                "fault reset (0x80)",
            ),
            exchange(
                self.write(CMD_DISABLE_VOLTAGE, 0),
                Compare::Exact,
                "control word 0",
            ),
            exchange(
                read(self.status),
                Compare::Exact,
                "status: switch on disabled",
            ),
        ]
    }
}

/// One state word. Only the state words are read: speeds and currents depend on the exact time of the read.
fn read(address: u16) -> Outgoing {
    Outgoing::Pdu(pdu(&Request::ReadHoldingRegisters {
        address,
        quantity: 1,
    }))
}

/// The RxPDO block kept before a case and written back after it (the case starts with a reset, so nothing
/// that ran before matters; the write-back leaves the control word, speed, torque limit and watchdog as they
/// were, the state machine where that control word leads from switch on disabled).
fn kept_block(cx: &Ctx, pd: &ProcessData) -> Around {
    let mut a = Around::new();
    a.keep_registers(cx, pd.base, pd.n as u16);
    a
}

/// The enable sequence and back: shutdown, switch on, enable operation, shutdown.
fn enable_sequence(cx: &mut Ctx, pd: &ProcessData) {
    let around = kept_block(cx, pd);
    let mut steps = pd.reset();
    steps.extend([
        exchange(pd.write(CMD_SHUTDOWN, 0), Compare::Exact, "shutdown (0x06)"),
        exchange(
            read(pd.status),
            Compare::Exact,
            "status: ready to switch on",
        ),
        exchange(
            pd.write(CMD_SWITCH_ON, 0),
            Compare::Exact,
            "switch on (0x07)",
        ),
        exchange(read(pd.status), Compare::Exact, "status: switched on"),
        exchange(
            pd.write(CMD_ENABLE_OPERATION, 0),
            Compare::Exact,
            "enable operation (0x0F)",
        ),
        exchange(read(pd.status), Compare::Exact, "status: operation enabled"),
        exchange(pd.write(CMD_SHUTDOWN, 0), Compare::Exact, "shutdown again"),
        exchange(
            read(pd.status),
            Compare::Exact,
            "status: ready to switch on",
        ),
    ]);
    let steps = around.wrap(steps);
    cx.push(
        format!("profile/{}/ds402/enable-sequence", cx.p.device.id),
        "DS402: fault reset, shutdown, switch on, enable operation, disable",
        MANUAL,
        "The status word follows the control word through the DS402 states: switch on disabled, ready to switch on, switched on, operation enabled, and back.",
        vec![Tag::Write, Tag::Motion],
        steps,
    );
}

/// A watchdog time set and not rewritten: not faulted before it elapses, faulted after.
fn watchdog(cx: &mut Ctx, pd: &ProcessData, w: &Watchdog) {
    let around = kept_block(cx, pd);
    let mut steps = pd.reset();
    steps.extend([
        exchange(
            pd.write(CMD_SHUTDOWN, 100),
            Compare::Exact,
            "shutdown with watchdog 100 ms",
        ),
        Step::Wait(Duration::from_millis(50)),
        exchange(read(pd.status), Compare::Exact, "50 ms later: not faulted"),
        exchange(
            read(pd.error_code),
            Compare::Exact,
            "50 ms later: no error code",
        ),
        Step::Wait(Duration::from_millis(150)),
        exchange(
            read(pd.status),
            Compare::Exact,
            "200 ms later: faulted by the watchdog",
        ),
        exchange(
            read(pd.error_code),
            Compare::Exact,
            "200 ms later: the watchdog's error code",
        ),
        // The drive "stops" (line 870): it may still be in fault reaction active (freedom
        // sd2x-watchdog-trip-state), where a fault reset does nothing (CiA 402 takes it in fault only). The
        // manual gives no stopping time; a second lets a drive at standstill finish its reaction.
        Step::Wait(Duration::from_millis(1000)),
    ]);
    steps.extend(pd.reset());
    let steps = around.wrap(steps);
    cx.push(
        format!("profile/{}/ds402/watchdog", cx.p.device.id),
        "RxPDO watchdog: a 100 ms watchdog not rewritten trips the drive",
        format!("SD2x manual, sections 4.1, 5 (Watchdog) and 6.1 (watchdog register {})", w.register),
        "With a watchdog time set, the drive is not faulted before the time elapses and is faulted, with its error code, once the RxPDO has not been rewritten for longer than the time.",
        vec![Tag::Write, Tag::Motion, Tag::Destructive],
        steps,
    );
}

/// Enable operation (0x000F) written in switch on disabled: CiA 402 leaves that state by shutdown only
/// (transition 2), so the drive stays in switch on disabled; operation enabled would be an illegal transition.
fn enable_from_switch_on_disabled(cx: &mut Ctx, pd: &ProcessData) {
    let around = kept_block(cx, pd);
    let mut steps = pd.reset();
    steps.extend([
        exchange(
            pd.write(CMD_ENABLE_OPERATION, 0),
            Compare::Exact,
            "enable operation (0x0F) in switch on disabled, no shutdown before",
        ),
        exchange(
            read(pd.status),
            Compare::Exact,
            "status: still switch on disabled, not operation enabled",
        ),
        // Every command of the sequence is in the block written last: a shutdown now is the legal way on.
        exchange(
            pd.write(CMD_SHUTDOWN, 0),
            Compare::Exact,
            "shutdown (0x06): the transition switch on disabled allows",
        ),
        exchange(
            read(pd.status),
            Compare::Exact,
            "status: ready to switch on",
        ),
    ]);
    steps.extend(pd.reset());
    let steps = around.wrap(steps);
    cx.push(
        format!(
            "profile/{}/ds402/enable-from-switch-on-disabled",
            cx.p.device.id
        ),
        "DS402: enable operation straight from switch on disabled is not taken",
        MANUAL,
        "The control word is coded as DS402's (object 0x6040): from switch on disabled only shutdown leads on. Enable operation (0x000F) written in switch on disabled leaves the drive in switch on disabled (status word state bits), not in operation enabled; a shutdown then gives ready to switch on.",
        vec![Tag::Write, Tag::Motion, Tag::Destructive],
        steps,
    );
}

/// A target speed written while operation is not enabled: the actual speed stays 0 (within 1 Hz: a measured
/// value, which jitters at standstill) in switch on disabled, ready to switch on and switched on (example 6.1 writes the setpoint with the shutdown, and the motor runs
/// only after enable operation).
fn speed_zero_when_not_enabled(cx: &mut Ctx, pd: &ProcessData) {
    let (Some(_), Some(actual)) = (pd.target_speed, pd.actual_speed) else {
        return;
    };
    // 100 Hz in 0.1 Hz, example 6.1's setpoint (line 1203).
    const SPEED: u16 = 1000;
    // The actual speed is measured ("Speed in 0.1 Hz", line 745): at standstill with a motor attached it
    // jitters by a count or two. 1 Hz (1 % of the setpoint) is standstill here.
    const STANDSTILL: u32 = 10;
    // Long enough for a drive following the setpoint to show it (at any ramp above 4 Hz/s, twice the
    // standstill band in 500 ms), short enough for a run.
    let settle = Duration::from_millis(500);
    let around = kept_block(cx, pd);
    let mut steps = pd.reset();
    let states: [(u16, &str, &str); 3] = [
        (
            CMD_DISABLE_VOLTAGE,
            "disable voltage (0x00)",
            "switch on disabled",
        ),
        (CMD_SHUTDOWN, "shutdown (0x06)", "ready to switch on"),
        (CMD_SWITCH_ON, "switch on (0x07)", "switched on"),
    ];
    for (cw, command, state) in states {
        steps.extend([
            exchange(
                pd.write_with_speed(cw, SPEED, 0),
                Compare::Exact,
                format!("{command} with target speed 100 Hz"),
            ),
            exchange(read(pd.status), Compare::Exact, format!("status: {state}")),
            Step::Wait(settle),
            exchange(
                read(actual),
                Compare::Near {
                    tolerance: STANDSTILL,
                },
                format!("500 ms later, {state}: actual speed 0 (within 1 Hz)"),
            ),
        ]);
    }
    steps.extend(pd.reset());
    let steps = around.wrap(steps);
    cx.push(
        format!("profile/{}/ds402/speed-zero-when-not-enabled", cx.p.device.id),
        "DS402: a target speed written while operation is not enabled does not turn the motor",
        format!("{MANUAL}; example 6.1 (setpoint written with shutdown, motor running after enable operation)"),
        "With a non-zero target speed written, the actual speed stays 0 (within 1 Hz, 1 % of the setpoint: a measured speed jitters at standstill) in switch on disabled, ready to switch on and switched on: only operation enabled drives the motor (DS402 state machine; example 6.1 runs the motor only once enable operation is sent).",
        vec![Tag::Write, Tag::Motion, Tag::Destructive],
        steps,
    );
}

/// A watchdog rewritten in time, as example 6.1 advises (every 200 ms against 500 ms), does not trip: the
/// time counts from the last rewrite, not from the first.
fn watchdog_refreshed(cx: &mut Ctx, pd: &ProcessData, w: &Watchdog) {
    // Example 6.1's values (lines 1207, 1228).
    const TIMEOUT_MS: u16 = 500;
    let every = Duration::from_millis(200);
    const REWRITES: usize = 5;
    let around = kept_block(cx, pd);
    let mut steps = pd.reset();
    steps.push(exchange(
        pd.write(CMD_SHUTDOWN, TIMEOUT_MS),
        Compare::Exact,
        "shutdown with watchdog 500 ms",
    ));
    for i in 1..=REWRITES {
        steps.extend([
            Step::Wait(every),
            exchange(
                pd.write(CMD_SHUTDOWN, TIMEOUT_MS),
                Compare::Exact,
                format!("rewrite {i} of the RxPDO with the watchdog, 200 ms after the last"),
            ),
            exchange(
                read(pd.status),
                Compare::Exact,
                format!("after rewrite {i}: not faulted (ready to switch on)"),
            ),
        ]);
    }
    steps.extend([
        exchange(
            read(pd.error_code),
            Compare::Exact,
            "after more than twice the watchdog time, refreshed: no error code",
        ),
        exchange(
            pd.write(CMD_SHUTDOWN, 0),
            Compare::Exact,
            "watchdog off (0)",
        ),
        // A drive that tripped anyway may still be stopping (freedom sd2x-watchdog-trip-state): let it reach
        // fault so that the reset below puts it back.
        Step::Wait(Duration::from_millis(1000)),
    ]);
    steps.extend(pd.reset());
    let steps = around.wrap(steps);
    cx.push(
        format!("profile/{}/ds402/watchdog-refreshed", cx.p.device.id),
        "RxPDO watchdog: a 500 ms watchdog rewritten every 200 ms does not trip",
        format!(
            "SD2x manual, sections 5 (Watchdog) and 6.1 (watchdog register {}, rewritten every 200 ms)",
            w.register
        ),
        "With a watchdog time set and the register rewritten within that time, again and again for more than twice the time, the drive is not faulted and has no error code: the timeout counts from the last rewrite.",
        vec![Tag::Write, Tag::Motion, Tag::Destructive],
        steps,
    );
}
