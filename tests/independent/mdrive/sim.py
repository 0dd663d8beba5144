#!/usr/bin/env python3
"""Clean-room simulator of the Modbus/TCP server of an IMS / Schneider Electric Motion
MDrive Plus2 (default) or MDrive Hybrid Motion Control with Ethernet.

Written from the "MODBUS/TCP Fieldbus Manual, MDrive Motion Control Products" (R040611)
and the public Modbus specifications only.  Standard library only.  See DECISIONS.md.

    python3 sim.py --listen 127.0.0.1:0 [--state FILE] [--model plus2|hybrid]
"""

import argparse
import asyncio
import json
import math
import os
import re
import signal
import sys
import time

# ---------------------------------------------------------------------------
# Modbus constants
# ---------------------------------------------------------------------------
EX_ILLEGAL_FUNCTION = 0x01
EX_ILLEGAL_ADDRESS = 0x02
EX_ILLEGAL_VALUE = 0x03
EX_DEVICE_FAILURE = 0x04

MAX_PDU = 253


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


def s32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


# ---------------------------------------------------------------------------
# Register map (manual section 5, lines 1022-1171)
# ---------------------------------------------------------------------------
# kind: "rw" read/write, "ro" read only, "wo" write only (command)
# model: "both", "plus" (MDrivePlus only, footnote 1), "hybrid" (section 5.1)
MS_VALUES = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)


class Reg:
    def __init__(self, mnem, addr, words, kind, lo=None, hi=None, default=0,
                 signed=False, model="both", allowed=None, desc=""):
        self.mnem = mnem
        self.addr = addr
        self.words = words
        self.kind = kind
        self.lo = lo
        self.hi = hi
        self.default = default
        self.signed = signed
        self.model = model
        self.allowed = allowed
        self.desc = desc


REGS = [
    Reg("A", 0x0000, 2, "rw", 91, 1525878997, 1000000, desc="Acceleration"),
    Reg("C1", 0x0005, 2, "rw", -2**31, 2**31 - 1, 0, True, desc="Counter 1 (clock pulses)"),
    Reg("C2", 0x0007, 2, "rw", -2**31, 2**31 - 1, 0, True, desc="Counter 2 (encoder counts)"),
    Reg("CE", 0x0009, 1, "rw", 0, 1, 1, desc="Software reset enable"),
    Reg("CM", 0x000B, 1, "rw", 0, 1, 0, model="plus", desc="Clock mode enable"),
    Reg("D1", 0x000F, 1, "rw", 0, 255, 0, desc="Input 1 debounce"),
    Reg("D2", 0x0010, 1, "rw", 0, 255, 0, desc="Input 2 debounce"),
    Reg("D3", 0x0011, 1, "rw", 0, 255, 0, desc="Input 3 debounce"),
    Reg("D4", 0x0012, 1, "rw", 0, 255, 0, desc="Input 4 debounce"),
    Reg("D5", 0x0013, 1, "rw", 0, 255, 0, desc="Analog input filter"),
    Reg("D", 0x0018, 2, "rw", 91, 1525878997, 1000000, desc="Deceleration"),
    Reg("DB", 0x001A, 1, "rw", 0, 65000, 10, model="plus", desc="Encoder deadband"),
    Reg("DC", 0x001B, 1, "wo", desc="Decrement variable"),
    Reg("DE", 0x001C, 1, "rw", 0, 1, 1, desc="Drive enable"),
    Reg("EE", 0x001E, 1, "rw", 0, 1, 0, desc="Encoder enable"),
    Reg("EF", 0x001F, 1, "ro", desc="Error flag"),
    Reg("ER", 0x0021, 1, "rw", 0, 0, 0, desc="Error (write 0 to clear)"),
    Reg("HC", 0x0029, 1, "rw", 0, 100, 5, desc="Holding current %"),
    Reg("HM", 0x002B, 1, "wo", 1, 4, desc="Home (homing mode)"),
    Reg("HT", 0x002C, 1, "rw", 0, 65535, 500, desc="Hold current delay time"),
    Reg("I1", 0x002D, 1, "ro", desc="Read input 1"),
    Reg("I2", 0x002E, 1, "ro", desc="Read input 2"),
    Reg("I3", 0x002F, 1, "ro", desc="Read input 3"),
    Reg("I4", 0x0030, 1, "ro", desc="Read input 4"),
    Reg("I5", 0x0031, 1, "ro", desc="Read analog input"),
    Reg("I6", 0x0032, 1, "ro", model="plus", desc="Read index mark"),
    Reg("IC", 0x0037, 1, "wo", desc="Increment variable"),
    Reg("IL", 0x003A, 1, "ro", desc="Read inputs 1-4 as BCD"),
    Reg("IN", 0x003B, 1, "ro", desc="Read all inputs as BCD"),
    Reg("JE", 0x003F, 1, "rw", 0, 1, 0, desc="Jog enable"),
    Reg("LM", 0x0042, 1, "rw", 1, 6, 1, desc="Limit stop mode"),
    Reg("MA", 0x0043, 2, "wo", -2**31, 2**31 - 1, signed=True, desc="Move to absolute position"),
    Reg("MP", 0x0045, 1, "ro", desc="Moving to position"),
    Reg("MR", 0x0046, 2, "wo", -2**31, 2**31 - 1, signed=True, desc="Move to relative position"),
    Reg("MS", 0x0048, 1, "rw", default=256, allowed=MS_VALUES, desc="Microstep resolution"),
    Reg("MT", 0x0049, 1, "rw", 0, 65000, 0, desc="Motor settling delay time"),
    Reg("MV", 0x004A, 1, "ro", desc="Moving"),
    Reg("O1", 0x004B, 1, "rw", 0, 1, 0, desc="Write output 1"),
    Reg("O2", 0x004C, 1, "rw", 0, 1, 0, desc="Write output 2"),
    Reg("O3", 0x004D, 1, "rw", 0, 1, 0, desc="Write output 3"),
    Reg("O4", 0x004E, 1, "rw", 0, 1, 0, desc="Write output 4"),
    Reg("OL", 0x0055, 1, "rw", 0, 15, 0, desc="Set outputs 1-4 as a group"),
    Reg("OT", 0x0056, 1, "rw", 0, 15, 0, desc="Set outputs (all) as a group"),
    Reg("P", 0x0057, 2, "rw", -2**31, 2**31 - 1, 0, True, desc="Position counter"),
    Reg("PC", 0x0059, 2, "ro", signed=True, desc="Position capture at trip"),
    Reg("PM", 0x005C, 1, "rw", 0, 1, 0, model="plus", desc="Position maintenance"),
    Reg("R1", 0x005F, 2, "rw", -2**31, 2**31 - 1, 0, True, desc="User register 1"),
    Reg("R2", 0x0061, 2, "rw", -2**31, 2**31 - 1, 0, True, desc="User register 2"),
    Reg("R3", 0x0063, 2, "rw", -2**31, 2**31 - 1, 0, True, desc="User register 3"),
    Reg("R4", 0x0065, 2, "rw", -2**31, 2**31 - 1, 0, True, desc="User register 4"),
    Reg("RC", 0x0067, 1, "rw", 1, 100, 25, desc="Run current %"),
    Reg("S", 0x0076, 1, "wo", desc="Save to NVM"),
    Reg("SF", 0x0077, 1, "rw", 0, 65000, 15, model="plus", desc="Stall factor"),
    Reg("SL", 0x0078, 2, "wo", -5000000, 5000000, signed=True, desc="Slew axis"),
    Reg("SM", 0x007A, 1, "rw", 0, 1, 0, model="plus", desc="Stall mode"),
    Reg("ST", 0x007B, 1, "rw", 0, 0, 0, model="plus", desc="Stall flag (write 0 to clear)"),
    Reg("TE", 0x007D, 1, "rw", default=0, allowed=(0, 16), desc="Trip enable"),
    Reg("V", 0x0085, 2, "ro", signed=True, desc="Read axis velocity"),
    Reg("VC", 0x0088, 1, "ro", desc="Velocity changing"),
    Reg("VI", 0x0089, 2, "rw", 1, 4999999, 1000, desc="Initial velocity"),
    Reg("VM", 0x008B, 2, "rw", 2, 5000000, 768000, desc="Maximum velocity"),
    # 5.1 Hybrid specific registers
    Reg("AS", 0x008E, 1, "rw", 0, 3, 2, model="hybrid", desc="Hybrid mode"),
    Reg("AF", 0x008F, 1, "ro", model="hybrid", desc="Hybrid status"),
    Reg("CA", 0x0090, 1, "rw", 0, 1, 1, model="hybrid", desc="Calibration mode"),
    Reg("CB", 0x0091, 1, "rw", 0, 3, 1, model="hybrid", desc="Control bounds"),
    Reg("CC", 0x0092, 1, "rw", 1, 100, 100, model="hybrid", desc="Calibration current %"),
    Reg("CF", 0x0093, 1, "wo", model="hybrid", desc="Clear locked rotor"),
    Reg("CT", 0x0094, 1, "rw", 2, 65535, 200, model="hybrid", desc="Calibration time"),
    Reg("LD", 0x0095, 2, "rw", 0, 2147483647, 102400, model="hybrid", desc="Lead limit"),
    Reg("LG", 0x0097, 2, "rw", 0, 2147483647, 102400, model="hybrid", desc="Lag limit"),
    Reg("LL", 0x0099, 2, "ro", signed=True, model="hybrid", desc="Position lead/lag"),
    Reg("LR", 0x009B, 1, "ro", model="hybrid", desc="Locked rotor"),
    Reg("LT", 0x009C, 2, "rw", 2, 65535, 2000, model="hybrid", desc="Locked rotor timeout"),
    Reg("MF", 0x009E, 2, "rw", 306, 5000000, 768000, model="hybrid", desc="Make up frequency"),
    Reg("MU", 0x00A0, 1, "rw", 0, 2, 0, model="hybrid", desc="Make up mode"),
    Reg("SC", 0x00A1, 1, "wo", model="hybrid", desc="Start calibration"),
    Reg("SS", 0x00A2, 1, "rw", 0, 255, 0, model="hybrid", desc="System speed"),
    Reg("TD", 0x00A5, 1, "rw", 0, 1, 1, model="hybrid", desc="Torque direction"),
    Reg("TQ", 0x00A6, 1, "rw", 1, 100, 25, model="hybrid", desc="Torque %"),
    Reg("TS", 0x00A7, 1, "rw", 0, 255, 0, model="hybrid", desc="Torque speed"),
]
# 5.2 User variable registers V1-V8
for _i in range(8):
    REGS.append(Reg("V%d" % (_i + 1), 0x00A8 + 2 * _i, 2, "rw", -2**31, 2**31 - 1, 0, True,
                    desc="User variable %d" % (_i + 1)))

BY_MNEM = {r.mnem: r for r in REGS}

# Variables DC / IC may address (value written = start address of the variable)
INCDEC_TARGETS = ("C1", "C2", "P", "R1", "R2", "R3", "R4") + tuple("V%d" % i for i in range(1, 9))

# Values whose ranges are copied to NVM by S (save)
NVM_REGS = ("A", "CE", "CM", "D1", "D2", "D3", "D4", "D5", "D", "DB", "DE", "EE", "HC", "HT",
            "JE", "LM", "MS", "MT", "PM", "R1", "R2", "R3", "R4", "RC", "SF", "SM", "TE", "VI",
            "VM", "AS", "CA", "CB", "CC", "CT", "LD", "LG", "LT", "MF", "MU", "SS", "TD", "TQ", "TS")

# ---------------------------------------------------------------------------
# Manufacturer specific (FC 0x41 / 0x42) - manual 4.3, lines 706-1020
# ---------------------------------------------------------------------------
IO_INPUT_TYPES = (0, 1, 2, 3, 5, 7, 8, 11)
IO_OUTPUT_TYPES = (16, 17, 18, 20, 21, 23, 24, 25)
IO_HYBRID_ONLY_TYPES = (24, 25)
CLOCK_TYPES = (33, 34, 35, 49, 50, 51)
CONFIG_MNEMS = ("S1", "S2", "S3", "S4", "S7", "S8", "CR", "S5", "S13", "TR", "MU")
ACTION_MNEMS = ("E", "EX", "PS", "RS")
CR_RE = re.compile(r"^[0-9]{1,5}(\.[0-9]{1,3})?$")
LABEL_RE = re.compile(r"^([A-Za-z][A-Za-z0-9]|[0-9]{1,4})$")

DEVICE_IDS = {
    "plus2": {
        0: "SEM USA",
        1: "MDI1PRD23A7-EQ",
        2: "4.0.0.0",
        3: "www.imshome.com",
        4: "MDrive Ethernet",
        5: "SN0000110406",
        6: "ASI 4.0.0.0",
    },
    "hybrid": {
        0: "SEM USA",
        1: "MAI1PRD23A7-EQ",
        2: "4.0.0.0",
        3: "www.imshome.com",
        4: "MDrive Ethernet",
        5: "SN0000110407",
        6: "ASI 4.0.0.0",
    },
}


# ---------------------------------------------------------------------------
# Motion engine (no motor: closed-form kinematics)
# ---------------------------------------------------------------------------
class Profile:
    """Point-to-point trapezoidal (or triangular) move, VI -> VM -> VI."""

    def __init__(self, t0, dist, vi, vm, acc, dec):
        self.t0 = t0
        self.sign = 1 if dist >= 0 else -1
        d = abs(float(dist))
        self.d = d
        vi = float(min(vi, vm))
        self.vi = vi
        ta = (vm - vi) / acc
        td = (vm - vi) / dec
        da = (vi + vm) / 2.0 * ta
        dd = (vi + vm) / 2.0 * td
        if da + dd <= d:
            self.vp = float(vm)
        else:
            self.vp = math.sqrt(vi * vi + 2.0 * d * acc * dec / (acc + dec))
            ta = (self.vp - vi) / acc
            td = (self.vp - vi) / dec
            da = (vi + self.vp) / 2.0 * ta
            dd = (vi + self.vp) / 2.0 * td
            if da + dd > d:  # very short move, run entirely at VI
                self.vp = vi
                ta = td = da = dd = 0.0
        self.acc, self.dec = acc, dec
        self.ta, self.td, self.da, self.dd = ta, td, da, dd
        self.tc = (d - da - dd) / self.vp if self.vp > 0 else 0.0
        self.total = ta + self.tc + td

    def state(self, t):
        """Return (displacement, velocity, velocity_changing, done)."""
        dt = t - self.t0
        if dt >= self.total:
            return self.sign * self.d, 0.0, False, True
        if dt < self.ta:
            v = self.vi + self.acc * dt
            x = self.vi * dt + 0.5 * self.acc * dt * dt
            return self.sign * x, self.sign * v, True, False
        dt2 = dt - self.ta
        if dt2 < self.tc:
            return self.sign * (self.da + self.vp * dt2), self.sign * self.vp, False, False
        dt3 = dt2 - self.tc
        v = self.vp - self.dec * dt3
        x = self.da + self.vp * self.tc + self.vp * dt3 - 0.5 * self.dec * dt3 * dt3
        return self.sign * min(x, self.d), self.sign * v, True, False


class Slew:
    """Constant-velocity slew with linear ramp from the current velocity to a target."""

    def __init__(self, t0, v0, vt, acc, dec):
        self.t0 = t0
        self.v0 = float(v0)
        self.vt = float(vt)
        speeding_up = abs(vt) > abs(v0) and (v0 == 0 or (v0 > 0) == (vt > 0))
        rate = acc if speeding_up else dec
        self.rate = rate if vt >= v0 else -rate
        self.tr = abs(vt - v0) / rate if rate > 0 else 0.0

    def state(self, t):
        dt = t - self.t0
        if dt < self.tr:
            v = self.v0 + self.rate * dt
            x = self.v0 * dt + 0.5 * self.rate * dt * dt
            return x, v, True, False
        xr = self.v0 * self.tr + 0.5 * self.rate * self.tr * self.tr
        x = xr + self.vt * (dt - self.tr)
        return x, self.vt, False, self.vt == 0.0


class Homing:
    """Simulated homing: creep for a short time, then the home switch is found and P = 0."""
    DURATION = 0.25

    def __init__(self, t0, velocity):
        self.t0 = t0
        self.v = float(velocity)

    def state(self, t):
        dt = t - self.t0
        if dt >= self.DURATION:
            return self.v * self.DURATION, 0.0, False, True
        return self.v * dt, self.v, False, False


# ---------------------------------------------------------------------------
# The device
# ---------------------------------------------------------------------------
class MDrive:
    def __init__(self, model="plus2"):
        self.model = model
        self.hybrid = model == "hybrid"
        self.vals = {}
        for r in REGS:
            if r.kind != "wo" and self.present(r):
                self.vals[r.mnem] = r.default
        # position-like quantities are kept as floats while moving
        self.pos = 0.0
        self.c1 = 0.0
        self.c2 = 0.0
        self.motion = None        # Profile / Slew / Homing
        self.motion_kind = None   # "move" / "slew" / "home"
        self.motion_applied = 0.0
        self.velocity = 0.0
        self.vchanging = False
        self.out_latch = [0, 0, 0, 0]
        # manufacturer specific configuration
        self.io = [[0, 0, 0] for _ in range(4)]     # S1..S4: type, active hi/lo, sink/source
        self.clock = {"S7": [33, 1], "S8": [33, 1]}
        self.clock_ratio = "1.000"
        self.analog = [9, 0]
        self.capture = [60, 0]
        self.trip_rel = [0, 0, 0]
        self.trip_arm = 0.0
        self.program = {"state": "stopped", "label": None}
        self.calib_until = 0.0
        self.nvm = None
        self.nvm = self.snapshot_nvm()
        self.reg_at = {}
        for r in REGS:
            if self.present(r):
                for i in range(r.words):
                    self.reg_at[r.addr + i] = (r, i)

    # -- helpers --------------------------------------------------------
    def present(self, r):
        if r.model == "plus":
            return not self.hybrid
        if r.model == "hybrid":
            return self.hybrid
        return True

    def snapshot_nvm(self):
        return {
            "registers": {m: self.vals[m] for m in NVM_REGS if m in self.vals},
            "io": [list(x) for x in self.io],
            "clock": {k: list(v) for k, v in self.clock.items()},
            "clock_ratio": self.clock_ratio,
            "analog": list(self.analog),
            "capture": list(self.capture),
            "trip_rel": list(self.trip_rel),
        }

    # -- motion ---------------------------------------------------------
    def update(self, now=None):
        if now is None:
            now = time.monotonic()
        if self.motion is not None:
            x, v, vc, done = self.motion.state(now)
            dx = x - self.motion_applied
            self.motion_applied = x
            self.pos += dx
            self.c1 += dx
            if self.vals["EE"]:
                self.c2 += dx
            self.velocity = v
            self.vchanging = vc
            if done:
                if self.motion_kind == "home":
                    self.pos = 0.0          # home switch found: position reference = 0
                else:
                    self.pos = float(round(self.pos))
                self.motion = None
                self.motion_kind = None
                self.velocity = 0.0
                self.vchanging = False
            # trip on relative position (TE bit 16, TR)
            if self.vals["TE"] & 16 and self.trip_rel[0] != 0:
                if abs(self.pos - self.trip_arm) >= abs(self.trip_rel[0]):
                    self.vals["TE"] &= ~16
        if self.calib_until and now >= self.calib_until:
            self.calib_until = 0.0

    def start_calibration(self):
        if self.hybrid:
            self.calib_until = time.monotonic() + self.vals["CT"] / 1000.0

    def moving(self):
        return self.motion is not None

    def p_int(self):
        return s32(int(round(self.pos)))

    # -- I/O ------------------------------------------------------------
    def output_state(self, i):
        t = self.io[i][0]
        if t == 16:
            return self.out_latch[i]
        if t == 17:
            return 1 if self.moving() else 0
        if t == 18:
            return self.vals["EF"]
        if t == 20:
            return 1 if self.vchanging else 0
        if t == 21:
            return self.vals.get("LR", 0)
        if t == 23:
            return 1 if self.motion_kind == "move" else 0
        if t == 24:
            return 1 if self.hybrid and self.vals["AS"] != 0 else 0
        if t == 25:
            return 0
        return 0          # configured as an input: output not driven

    def input_state(self, i):
        # Nothing is wired to the simulated inputs; an input reads inactive (0).
        # A point configured as an output reads back the state it drives.
        if self.io[i][0] in IO_OUTPUT_TYPES:
            return self.output_state(i)
        return 0

    def is_gp_output(self, i):
        return self.io[i][0] == 16

    # -- register read ----------------------------------------------------
    def read_value(self, r):
        m = r.mnem
        if m == "P":
            return self.p_int()
        if m == "C1":
            return s32(int(round(self.c1)))
        if m == "C2":
            return s32(int(round(self.c2)))
        if m in ("I1", "I2", "I3", "I4"):
            return self.input_state(int(m[1]) - 1)
        if m in ("I5", "I6"):
            return 0
        if m in ("IL", "IN"):
            return sum(self.input_state(i) << i for i in range(4))
        if m in ("O1", "O2", "O3", "O4"):
            return self.output_state(int(m[1]) - 1)
        if m in ("OL", "OT"):
            return sum(self.output_state(i) << i for i in range(4)
                       if self.io[i][0] in IO_OUTPUT_TYPES)
        if m == "MV":
            return 1 if self.moving() else 0
        if m == "MP":
            return 1 if self.motion_kind == "move" else 0
        if m == "VC":
            return 1 if self.vchanging else 0
        if m == "V":
            if self.hybrid and self.vals["AS"] == 3:
                return 0
            return s32(int(round(self.velocity)))
        if m == "PC":
            return 0
        if m == "LL":
            return 0
        if m == "LR":
            return 0
        if m == "AF":
            af = 0
            if self.vals["AS"] != 0:
                af |= 16
            af |= 64                      # lead/lag at zero
            if not self.calib_until:
                af |= 128                 # calibration complete
            return af
        return self.vals[m]

    def read_registers(self, start, qty):
        words = []
        cache = {}
        for a in range(start, start + qty):
            ent = self.reg_at.get(a)
            if ent is None or ent[0].kind == "wo":
                raise ModbusError(EX_ILLEGAL_ADDRESS)
        clear_er = False
        for a in range(start, start + qty):
            r, i = self.reg_at[a]
            if r.mnem not in cache:
                cache[r.mnem] = self.read_value(r)
                if r.mnem == "ER":
                    clear_er = True
            v = cache[r.mnem] & ((1 << (16 * r.words)) - 1)
            shift = 16 * (r.words - 1 - i)          # high word first
            words.append((v >> shift) & 0xFFFF)
        if clear_er:
            # manual line 1047: ER "must be read or set to 0 to clear"
            self.vals["ER"] = 0
            self.vals["EF"] = 0
        return words

    # -- register write ---------------------------------------------------
    def write_registers(self, start, words):
        qty = len(words)
        items = []
        a = start
        end = start + qty
        while a < end:
            ent = self.reg_at.get(a)
            if ent is None:
                raise ModbusError(EX_ILLEGAL_ADDRESS)
            r, i = ent
            if r.kind == "ro" or i != 0 or a + r.words > end:
                raise ModbusError(EX_ILLEGAL_ADDRESS)
            raw = 0
            for k in range(r.words):
                raw = (raw << 16) | words[a - start + k]
            val = s32(raw) if (r.signed and r.words == 2) else raw
            items.append((r, val))
            a += r.words
        new = {r.mnem: v for r, v in items}
        # value validation (everything is checked before anything is applied)
        for r, v in items:
            self.validate(r, v, new)
        # state validation
        for r, v in items:
            self.check_state(r, v)
        for r, v in items:
            self.apply(r, v)

    def validate(self, r, v, new):
        m = r.mnem
        if r.kind == "wo":
            if m in ("MA", "MR"):
                return
            if m == "SL":
                if not (r.lo <= v <= r.hi):
                    raise ModbusError(EX_ILLEGAL_VALUE)
                return
            if m == "HM":
                if not (1 <= v <= 4):
                    raise ModbusError(EX_ILLEGAL_VALUE)
                return
            if m in ("DC", "IC"):
                ent = self.reg_at.get(v)
                if ent is None or ent[1] != 0 or ent[0].mnem not in INCDEC_TARGETS:
                    raise ModbusError(EX_ILLEGAL_VALUE)
                return
            return  # S, CF, SC: any value triggers the command
        if r.allowed is not None:
            if v not in r.allowed:
                raise ModbusError(EX_ILLEGAL_VALUE)
        elif not (r.lo <= v <= r.hi):
            raise ModbusError(EX_ILLEGAL_VALUE)
        if m == "HT" and v == 1:
            raise ModbusError(EX_ILLEGAL_VALUE)           # 0 or 2-65535
        if m in ("HT", "MT"):
            ht = new.get("HT", self.vals["HT"])
            mt = new.get("MT", self.vals["MT"])
            if ht + mt > 65535:
                raise ModbusError(EX_ILLEGAL_VALUE)
        if m in ("VI", "VM"):
            vi = new.get("VI", self.vals["VI"])
            vm = new.get("VM", self.vals["VM"])
            if not vi < vm:
                raise ModbusError(EX_ILLEGAL_VALUE)

    def check_state(self, r, v):
        m = r.mnem
        if m in ("O1", "O2", "O3", "O4"):
            if not self.is_gp_output(int(m[1]) - 1):
                raise ModbusError(EX_DEVICE_FAILURE)
        if m in ("MA", "MR", "HM") and self.moving():
            raise ModbusError(EX_DEVICE_FAILURE)
        if m == "SL" and self.moving() and self.motion_kind != "slew":
            raise ModbusError(EX_DEVICE_FAILURE)
        if m in ("P", "MS") and self.moving():
            raise ModbusError(EX_DEVICE_FAILURE)
        if m in ("DC", "IC") and self.reg_at[v][0].mnem == "P" and self.moving():
            raise ModbusError(EX_DEVICE_FAILURE)

    def set_var(self, mnem, val):
        if mnem == "P":
            self.pos = float(val)
        elif mnem == "C1":
            self.c1 = float(val)
        elif mnem == "C2":
            self.c2 = float(val)
        else:
            self.vals[mnem] = val

    def apply(self, r, v):
        m = r.mnem
        now = time.monotonic()
        if m == "MA" or m == "MR":
            dist = (v - self.p_int()) if m == "MA" else v
            if dist != 0:
                self.start_motion("move", Profile(now, dist, self.vals["VI"], self.vals["VM"],
                                                  self.vals["A"], self.vals["D"]))
            return
        if m == "SL":
            if self.motion_kind == "slew":
                self.update(now)
                self.start_motion("slew", Slew(now, self.velocity, v, self.vals["A"], self.vals["D"]))
            elif v != 0:
                self.start_motion("slew", Slew(now, 0.0, v, self.vals["A"], self.vals["D"]))
            return
        if m == "HM":
            vi = self.vals["VI"]
            direction = -1 if v in (1, 2) else 1       # slew direction of the mode
            self.start_motion("home", Homing(now, direction * vi))
            return
        if m in ("DC", "IC"):
            tr = self.reg_at[v][0]
            cur = self.read_value(tr)
            self.set_var(tr.mnem, s32(cur + (1 if m == "IC" else -1)))
            return
        if m == "S":
            self.nvm = self.snapshot_nvm()
            return
        if m == "CF":
            self.start_calibration()
            return
        if m == "SC":
            self.start_calibration()
            return
        if m in ("P", "C1", "C2"):
            self.set_var(m, v)
            return
        if m in ("O1", "O2", "O3", "O4"):
            self.out_latch[int(m[1]) - 1] = v
            return
        if m in ("OL", "OT"):
            for i in range(4):
                if self.is_gp_output(i):
                    self.out_latch[i] = (v >> i) & 1
            return
        if m == "ER":
            self.vals["ER"] = 0
            self.vals["EF"] = 0
            return
        old = self.vals.get(m)
        self.vals[m] = v
        if m == "TE" and v & 16:
            self.trip_arm = self.pos
        if self.hybrid:
            if (m == "DE" and old == 0 and v == 1) or (m == "MS" and old != v) or \
               (m == "AS" and old == 0 and v != 0):
                self.start_calibration()

    def start_motion(self, kind, prof):
        self.update()
        self.motion = prof
        self.motion_kind = kind
        self.motion_applied = 0.0
        self.update()

    # -- manufacturer specific ------------------------------------------
    def mfg_known(self, mnem):
        if mnem == "MU":
            return self.hybrid
        return mnem in CONFIG_MNEMS or mnem in ACTION_MNEMS

    def mfg_read(self, mnem):
        if mnem in ("S1", "S2", "S3", "S4"):
            p = self.io[int(mnem[1]) - 1]
            return ", ".join(str(x) for x in p)
        if mnem in ("S7", "S8"):
            return ", ".join(str(x) for x in self.clock[mnem])
        if mnem == "CR":
            return self.clock_ratio
        if mnem == "S5":
            return ", ".join(str(x) for x in self.analog)
        if mnem == "S13":
            return ", ".join(str(x) for x in self.capture)
        if mnem == "TR":
            return ", ".join(str(x) for x in self.trip_rel)
        if mnem == "MU":
            return "%d, 0" % self.vals["MU"]
        raise ModbusError(EX_ILLEGAL_ADDRESS)

    @staticmethod
    def parse_params(text, nmax):
        if not text.startswith("="):
            raise ModbusError(EX_ILLEGAL_VALUE)
        fields = text[1:].split(",")
        if len(fields) > nmax:
            raise ModbusError(EX_ILLEGAL_VALUE)
        out = []
        for f in fields:
            f = f.strip(" ")
            if not re.fullmatch(r"[+-]?[0-9]{1,10}", f):
                raise ModbusError(EX_ILLEGAL_VALUE)
            out.append(int(f))
        return out

    def mfg_action(self, mnem, param):
        if mnem == "EX":
            if param.startswith("="):
                param = param[1:]
            if not LABEL_RE.fullmatch(param):
                raise ModbusError(EX_ILLEGAL_VALUE)
            if self.program["state"] != "stopped":
                raise ModbusError(EX_DEVICE_FAILURE)
            self.program = {"state": "running", "label": param}
            return
        if param != "":
            raise ModbusError(EX_ILLEGAL_VALUE)
        if mnem == "E":
            self.program = {"state": "stopped", "label": None}
        elif mnem == "PS":
            if self.program["state"] == "running":
                self.program["state"] = "paused"
        elif mnem == "RS":
            if self.program["state"] == "paused":
                self.program["state"] = "running"

    def mfg_write(self, mnem, text):
        if mnem in ACTION_MNEMS:
            self.mfg_action(mnem, text)
            return
        if mnem == "CR":
            if not text.startswith("=") or len(text) > 6:
                raise ModbusError(EX_ILLEGAL_VALUE)
            s = text[1:].strip(" ")
            if not CR_RE.fullmatch(s):
                raise ModbusError(EX_ILLEGAL_VALUE)
            val = float(s)
            if val <= 0:
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.clock_ratio = "%.3f" % val
            return
        if mnem in ("S1", "S2", "S3", "S4"):
            i = int(mnem[1]) - 1
            p = self.parse_params(text, 3)
            new = list(self.io[i])
            new[:len(p)] = p
            allowed = IO_INPUT_TYPES + IO_OUTPUT_TYPES
            if new[0] not in allowed or (not self.hybrid and new[0] in IO_HYBRID_ONLY_TYPES):
                raise ModbusError(EX_ILLEGAL_VALUE)
            if new[1] not in (0, 1) or new[2] not in (0, 1):
                raise ModbusError(EX_ILLEGAL_VALUE)
            if new[0] != 16:
                self.out_latch[i] = 0
            self.io[i] = new
            return
        if mnem in ("S7", "S8"):
            p = self.parse_params(text, 2)
            new = list(self.clock[mnem])
            new[:len(p)] = p
            if new[0] not in CLOCK_TYPES or new[1] not in (0, 1):
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.clock[mnem] = new
            return
        if mnem == "S5":
            p = self.parse_params(text, 2)
            new = list(self.analog)
            new[:len(p)] = p
            if new[0] not in (9, 10) or new[1] not in (0, 1):
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.analog = new
            return
        if mnem == "S13":
            p = self.parse_params(text, 2)
            new = list(self.capture)
            new[:len(p)] = p
            if new[0] not in (60, 61) or new[1] not in (0, 1):
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.capture = new
            return
        if mnem == "TR":
            p = self.parse_params(text, 3)
            new = list(self.trip_rel)
            new[:len(p)] = p
            if not (-2**31 <= new[0] <= 2**31 - 1):
                raise ModbusError(EX_ILLEGAL_VALUE)
            if not (0 <= new[1] <= 65535 and 0 <= new[2] <= 65535):
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.trip_rel = new
            self.trip_arm = self.pos
            return
        if mnem == "MU":
            p = self.parse_params(text, 2)
            if p[0] not in (0, 1, 2):
                raise ModbusError(EX_ILLEGAL_VALUE)
            if len(p) > 1 and p[1] not in (0, 1):
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.vals["MU"] = p[0]
            return  # B=1 "clear lead/lag": lead/lag is always 0 in the simulation
        raise ModbusError(EX_ILLEGAL_ADDRESS)

    # -- state dump ---------------------------------------------------------
    def state(self):
        self.update()
        regs = {}
        params = {}
        for r in REGS:
            if not self.present(r):
                continue
            entry = {"address": "0x%04X" % r.addr, "registers": r.words, "access": r.kind,
                     "description": r.desc}
            if r.kind == "wo":
                entry["value"] = None
            else:
                v = self.read_value(r)
                entry["value"] = v
                raw = v & ((1 << (16 * r.words)) - 1)
                for i in range(r.words):
                    regs["0x%04X" % (r.addr + i)] = (raw >> (16 * (r.words - 1 - i))) & 0xFFFF
            params[r.mnem] = entry
        mfg = {}
        for m in CONFIG_MNEMS:
            if self.mfg_known(m):
                mfg[m] = self.mfg_read(m)
        return {
            "device": {"model": self.model, "device_identification":
                       {"0x%02X" % k: v for k, v in DEVICE_IDS[self.model].items()}},
            "holding_registers": dict(sorted(regs.items())),
            "parameters": params,
            "coils": {"0x%04X" % (0x4B + i): self.output_state(i) for i in range(4)},
            "discrete_inputs": {"0x%04X" % (0x2D + i): self.input_state(i) for i in range(4)},
            "output_latches": list(self.out_latch),
            "manufacturer_specific": mfg,
            "program": dict(self.program),
            "motion": {"kind": self.motion_kind, "velocity": self.velocity},
            "nvm": self.nvm,
        }


# ---------------------------------------------------------------------------
# Modbus PDU processing
# ---------------------------------------------------------------------------
class Server:
    def __init__(self, dev):
        self.dev = dev

    def process(self, pdu):
        fc = pdu[0]
        try:
            self.dev.update()
            return self.dispatch(fc, pdu)
        except ModbusError as e:
            return bytes([(fc | 0x80) & 0xFF, e.code])
        except Exception:  # never let one frame kill the server
            return bytes([(fc | 0x80) & 0xFF, EX_DEVICE_FAILURE])

    def dispatch(self, fc, pdu):
        if fc in (0x01, 0x02):
            return self.read_bits(fc, pdu)
        if fc == 0x03:
            return self.read_holding(pdu)
        if fc == 0x05:
            return self.write_coil(pdu)
        if fc == 0x10:
            return self.write_multiple(pdu)
        if fc == 0x2B:
            return self.read_device_id(pdu)
        if fc == 0x41:
            return self.mfg_read(pdu)
        if fc == 0x42:
            return self.mfg_write(pdu)
        raise ModbusError(EX_ILLEGAL_FUNCTION)

    def read_bits(self, fc, pdu):
        if len(pdu) != 5:
            raise ModbusError(EX_ILLEGAL_VALUE)
        start = int.from_bytes(pdu[1:3], "big")
        qty = int.from_bytes(pdu[3:5], "big")
        if not 1 <= qty <= 4:
            raise ModbusError(EX_ILLEGAL_VALUE)
        base = 0x002D if fc == 0x02 else 0x004B
        if start < base or start + qty > base + 4:
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        bits = 0
        for k in range(qty):
            i = start - base + k
            s = self.dev.input_state(i) if fc == 0x02 else self.dev.output_state(i)
            bits |= (s & 1) << k
        return bytes([fc, 1, bits])

    def read_holding(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(EX_ILLEGAL_VALUE)
        start = int.from_bytes(pdu[1:3], "big")
        qty = int.from_bytes(pdu[3:5], "big")
        if not 1 <= qty <= 4:
            raise ModbusError(EX_ILLEGAL_VALUE)
        words = self.dev.read_registers(start, qty)
        out = bytearray([0x03, 2 * qty])
        for w in words:
            out += w.to_bytes(2, "big")
        return bytes(out)

    def write_coil(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(EX_ILLEGAL_VALUE)
        addr = int.from_bytes(pdu[1:3], "big")
        val = int.from_bytes(pdu[3:5], "big")
        if val not in (0x0000, 0xFF00):
            raise ModbusError(EX_ILLEGAL_VALUE)
        if not 0x004B <= addr <= 0x004E:
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        i = addr - 0x004B
        if not self.dev.is_gp_output(i):
            raise ModbusError(EX_DEVICE_FAILURE)
        self.dev.out_latch[i] = 1 if val == 0xFF00 else 0
        return bytes(pdu)

    def write_multiple(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(EX_ILLEGAL_VALUE)
        start = int.from_bytes(pdu[1:3], "big")
        qty = int.from_bytes(pdu[3:5], "big")
        bc = pdu[5]
        if not 1 <= qty <= 4 or bc != 2 * qty or len(pdu) != 6 + bc:
            raise ModbusError(EX_ILLEGAL_VALUE)
        words = [int.from_bytes(pdu[6 + 2 * k:8 + 2 * k], "big") for k in range(qty)]
        self.dev.write_registers(start, words)
        return bytes(pdu[0:5])

    def read_device_id(self, pdu):
        if len(pdu) < 2:
            raise ModbusError(EX_ILLEGAL_VALUE)
        if pdu[1] != 0x0E:
            raise ModbusError(EX_ILLEGAL_FUNCTION)
        if len(pdu) != 4:
            raise ModbusError(EX_ILLEGAL_VALUE)
        code, obj = pdu[2], pdu[3]
        ids = DEVICE_IDS[self.dev.model]
        if code == 4:
            if obj not in ids:
                raise ModbusError(EX_ILLEGAL_ADDRESS)
            objs = [obj]
        elif code in (1, 2, 3):
            last = 2 if code == 1 else 6
            if obj > last:
                obj = 0
            objs = list(range(obj, last + 1))
        else:
            raise ModbusError(EX_ILLEGAL_VALUE)
        out = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(objs)])
        for o in objs:
            v = ids[o].encode("ascii")
            out += bytes([o, len(v)]) + v
        return bytes(out)

    @staticmethod
    def mnemonic(b4):
        try:
            s = bytes(reversed(b4)).decode("ascii")
        except UnicodeDecodeError:
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        s = s.rstrip(" ")
        if not s or not s.isalnum():
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        return s

    @staticmethod
    def param_text(data):
        try:
            text = bytes(data).decode("ascii")
        except UnicodeDecodeError:
            raise ModbusError(EX_ILLEGAL_VALUE)
        if any(not (0x20 <= ord(c) < 0x7F) for c in text):
            raise ModbusError(EX_ILLEGAL_VALUE)
        return text

    def mfg_read(self, pdu):
        if len(pdu) < 5:
            raise ModbusError(EX_ILLEGAL_VALUE)
        mnem = self.mnemonic(pdu[1:5])
        if not self.dev.mfg_known(mnem):
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        if mnem == "EX":
            # EX carries the label: byte count + label as in the 0x42 request
            if len(pdu) < 6 or len(pdu) != 6 + pdu[5] or not 1 <= pdu[5] <= 28:
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.dev.mfg_action(mnem, self.param_text(pdu[6:]))
            return bytes([0x41, 0])
        if len(pdu) != 5:
            raise ModbusError(EX_ILLEGAL_VALUE)
        if mnem in ACTION_MNEMS:
            self.dev.mfg_action(mnem, "")
            return bytes([0x41, 0])
        text = self.dev.mfg_read(mnem).encode("ascii")
        return bytes([0x41, len(text)]) + text

    def mfg_write(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(EX_ILLEGAL_VALUE)
        bc = pdu[5]
        if len(pdu) != 6 + bc or bc > 28:
            raise ModbusError(EX_ILLEGAL_VALUE)
        mnem = self.mnemonic(pdu[1:5])
        if not self.dev.mfg_known(mnem):
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        if bc == 0 and mnem not in ("E", "PS", "RS"):
            raise ModbusError(EX_ILLEGAL_VALUE)
        self.dev.mfg_write(mnem, self.param_text(pdu[6:]))
        return bytes([0x42, bc]) + bytes(pdu[1:5])


# ---------------------------------------------------------------------------
# Modbus/TCP transport
# ---------------------------------------------------------------------------
async def handle_client(reader, writer, server):
    try:
        while True:
            try:
                hdr = await reader.readexactly(7)
            except (asyncio.IncompleteReadError, ConnectionError):
                break
            tid = hdr[0:2]
            proto = int.from_bytes(hdr[2:4], "big")
            length = int.from_bytes(hdr[4:6], "big")
            unit = hdr[6]
            if length < 1 or length > MAX_PDU + 1:
                break  # framing lost: close the connection
            try:
                pdu = await reader.readexactly(length - 1)
            except (asyncio.IncompleteReadError, ConnectionError):
                break
            if proto != 0:
                continue  # not Modbus: silently discarded (TCP implementation guide)
            if not pdu:
                continue  # no function code: nothing to answer
            resp = server.process(pdu)
            adu = tid + b"\x00\x00" + (len(resp) + 1).to_bytes(2, "big") + bytes([unit]) + resp
            writer.write(adu)
            try:
                await writer.drain()
            except ConnectionError:
                break
    except Exception:
        pass
    finally:
        try:
            writer.close()
        except Exception:
            pass


def write_state(dev, path):
    if not path:
        return
    try:
        data = json.dumps(dev.state(), indent=1, sort_keys=False)
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except Exception as e:  # pragma: no cover
        print("state write failed: %s" % e, file=sys.stderr, flush=True)


async def main_async(args):
    host, _, port = args.listen.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    dev = MDrive(args.model)
    srv_logic = Server(dev)
    # signal handlers are installed before the "listening" line is printed
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, lambda: write_state(dev, args.state))
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    srv = await asyncio.start_server(lambda r, w: handle_client(r, w, srv_logic),
                                     host=host, port=int(port), reuse_address=True)
    sock = srv.sockets[0]
    print("listening tcp %s:%d" % (host, sock.getsockname()[1]), flush=True)
    await stop.wait()
    srv.close()
    write_state(dev, args.state)
    sys.stdout.flush()
    os._exit(0)   # exit promptly, without waiting for open client connections


def main():
    ap = argparse.ArgumentParser(description="MDrive Plus2/Hybrid Modbus/TCP simulator")
    ap.add_argument("--listen", required=True, help="HOST:PORT (loopback), port 0 = any")
    ap.add_argument("--state", default=None, help="JSON state file (SIGUSR1 and exit)")
    ap.add_argument("--model", choices=("plus2", "hybrid"), default="plus2")
    args = ap.parse_args()
    try:
        asyncio.run(main_async(args))
    except KeyboardInterrupt:
        pass
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
