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
    watchdog(cx, &pd, w);
}

/// The RxPDO block from the control word up to the watchdog register, and the words that show the state.
struct ProcessData {
    /// The control word's address: the first of the block.
    base: u16,
    /// Registers in the block; the watchdog is the last.
    n: usize,
    status: u16,
    error_code: u16,
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
        Some(Self {
            base,
            n,
            status,
            error_code,
        })
    }

    /// The whole block in one FC 16: control word `cw`, watchdog time `wd` (ms), zeros between.
    fn write(&self, cw: u16, wd: u16) -> Outgoing {
        let n = self.n;
        let mut v = vec![0u16; n];
        v[0] = cw;
        v[n - 1] = wd;
        Outgoing::Pdu(pdu(&Request::WriteMultipleRegisters {
            address: self.base,
            values: v,
        }))
    }

    /// Fault reset, watchdog off, back to switch on disabled.
    fn reset(&self) -> Vec<Step> {
        vec![
            exchange(
                self.write(CMD_FAULT_RESET, 0),
                Compare::Exact,
                "fault reset (0x80), watchdog off",
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
