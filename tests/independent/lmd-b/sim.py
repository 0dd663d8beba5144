#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet -- Modbus/TCP server simulator.

Clean-room implementation from the "MODBUS/TCP Fieldbus manual" (LMD-MODBUS-REV-D)
and the public Modbus specifications.  Standard library only.

Simulated product: closed-loop (hMTechnology) NEMA 23 LMD Ethernet, "LMDCE572".

    python3 sim.py --listen 127.0.0.1:0 [--state FILE]

See DECISIONS.md for every place where the manual was wrong or silent.
"""

import argparse
import asyncio
import json
import os
import signal
import sys
import time

# --------------------------------------------------------------------------------------
# Exception codes (the manual lists only 01..04)
# --------------------------------------------------------------------------------------
ILLEGAL_FUNCTION = 0x01
ILLEGAL_ADDRESS = 0x02
ILLEGAL_VALUE = 0x03
DEVICE_FAILURE = 0x04


class MbError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# --------------------------------------------------------------------------------------
# Register map (section 5).  Addresses are 0-based PDU addresses.
#   (addr, mnemonic, nregs, access, lo, hi, signed, default, kind)
#   access: rw / ro / wo ;  kind: param (IP/S), user, status, cmd, counter
# 32-bit items: low word at the lower address (manual examples 4.2.4 / 4.2.5).
# --------------------------------------------------------------------------------------
S32_MIN, S32_MAX = -2147483648, 2147483647

REG_TABLE = [
    (0x0000, "A", 2, "rw", 91, 1525878997, False, 1000000, "param"),
    (0x0004, "BY", 1, "ro", 0, 1, False, 0, "status"),
    (0x0005, "C1", 2, "rw", S32_MIN, S32_MAX, True, 0, "counter"),
    (0x0007, "C2", 2, "rw", S32_MIN, S32_MAX, True, 0, "counter"),
    (0x0009, "CE", 1, "rw", 0, 1, False, 1, "param"),
    (0x000E, "CW", 1, "rw", 0, 255, False, 10, "param"),
    (0x000F, "D1", 1, "rw", 0, 255, False, 0, "param"),
    (0x0010, "D2", 1, "rw", 0, 255, False, 0, "param"),
    (0x0011, "D3", 1, "rw", 0, 255, False, 0, "param"),
    (0x0012, "D4", 1, "rw", 0, 255, False, 0, "param"),
    (0x0013, "D5", 1, "rw", 0, 255, False, 0, "param"),
    (0x0018, "D", 2, "rw", 91, 1525878997, False, 1000000, "param"),
    (0x001A, "DB", 1, "rw", 0, 65000, False, 10, "param"),
    (0x001B, "DC", 1, "wo", 0, 255, False, None, "cmd"),
    (0x001C, "DE", 1, "rw", 0, 1, False, 1, "param"),
    (0x001E, "EE", 1, "rw", 0, 1, False, 0, "param"),
    (0x001F, "EF", 1, "ro", 0, 1, False, 0, "status"),
    (0x0021, "ER", 1, "rw", 0, 0, False, 0, "status"),      # only 0 may be written
    (0x0024, "FC", 1, "rw", 0, 9, False, 0, "param"),
    (0x0029, "HC", 1, "rw", 0, 100, False, 5, "param"),
    (0x002A, "HI", 1, "wo", 1, 4, False, None, "cmd"),
    (0x002B, "HM", 1, "wo", 1, 4, False, None, "cmd"),
    (0x002C, "HT", 1, "rw", 0, 65535, False, 500, "param"),
    (0x002D, "I1", 1, "ro", 0, 1, False, 0, "status"),
    (0x002E, "I2", 1, "ro", 0, 1, False, 0, "status"),
    (0x002F, "I3", 1, "ro", 0, 1, False, 0, "status"),
    (0x0030, "I4", 1, "ro", 0, 1, False, 0, "status"),
    (0x0031, "I5", 1, "ro", 0, 1023, False, 0, "status"),
    (0x0032, "I6", 1, "ro", 0, 1, False, 0, "status"),
    (0x0037, "IC", 1, "wo", 0, 255, False, None, "cmd"),
    (0x003B, "IN", 1, "ro", 0, 15, False, 0, "status"),
    (0x003C, "IP", 1, "wo", 0, 65535, False, None, "cmd"),
    (0x003F, "JE", 1, "rw", 0, 1, False, 0, "param"),
    (0x0042, "LM", 1, "rw", 1, 6, False, 1, "param"),
    (0x0043, "MA", 2, "wo", S32_MIN, S32_MAX, True, None, "cmd"),
    (0x0045, "MP", 1, "ro", 0, 1, False, 0, "status"),
    (0x0046, "MR", 2, "wo", S32_MIN, S32_MAX, True, None, "cmd"),
    (0x0048, "MS", 1, "rw", 1, 256, False, 256, "param"),
    (0x0049, "MT", 1, "rw", 0, 65000, False, 0, "param"),
    (0x004A, "MV", 1, "ro", 0, 1, False, 0, "status"),
    (0x004B, "O1", 1, "rw", 0, 1, False, 0, "output"),
    (0x004C, "O2", 1, "rw", 0, 1, False, 0, "output"),
    (0x004D, "O3", 1, "rw", 0, 1, False, 0, "output"),
    (0x004E, "OF", 1, "ro", 0, 1, False, 0, "status"),
    (0x0056, "OT", 1, "rw", 0, 15, False, 0, "output"),
    (0x0057, "P", 2, "rw", S32_MIN, S32_MAX, True, 0, "counter"),
    (0x0059, "PC", 2, "ro", S32_MIN, S32_MAX, True, 0, "status"),
    (0x005C, "PM", 1, "rw", 0, 1, False, 0, "param"),
    (0x005F, "R1", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x0061, "R2", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x0063, "R3", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x0065, "R4", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x0067, "RC", 1, "rw", 1, 100, False, 25, "param"),
    (0x0076, "S", 1, "wo", 0, 65535, False, None, "cmd"),
    (0x0077, "SF", 1, "rw", 0, 65000, False, 15, "param"),
    (0x0078, "SL", 2, "wo", -5000000, 5000000, True, None, "cmd"),
    (0x007A, "SM", 1, "rw", 0, 1, False, 0, "param"),
    (0x007B, "ST", 1, "rw", 0, 0, False, 0, "status"),      # only 0 may be written
    (0x007D, "TE", 1, "rw", 0, 43, False, 0, "param"),
    (0x0085, "V", 2, "ro", S32_MIN, S32_MAX, True, 0, "status"),
    (0x0088, "VC", 1, "ro", 0, 1, False, 0, "status"),
    (0x0089, "VI", 2, "rw", 1, 2559999, False, 1000, "param"),
    (0x008B, "VM", 2, "rw", 2, 2560000, False, 768000, "param"),
    (0x008D, "WT", 1, "rw", 0, 84, False, 80, "param"),
    # 5.1 hMTechnology registers (closed loop)
    (0x008E, "AS", 1, "rw", 0, 3, False, 2, "param"),
    (0x008F, "AF", 1, "ro", 0, 255, False, 0, "status"),
    (0x0091, "CB", 1, "rw", 0, 3, False, 1, "param"),
    (0x0093, "CF", 1, "wo", 0, 65535, False, None, "cmd"),
    (0x0095, "LD", 2, "rw", 0, 2147483647, False, 102400, "param"),
    (0x0097, "LG", 2, "rw", 0, 2147483647, False, 102400, "param"),
    (0x0099, "LL", 2, "ro", -2147483647, 2147483647, True, 0, "status"),
    (0x009B, "LR", 1, "ro", 0, 1, False, 0, "status"),
    (0x009C, "LT", 2, "rw", 2, 65535, False, 2000, "param"),
    (0x009E, "MF", 2, "rw", 306, 2560000, False, 768000, "param"),
    (0x00A0, "MU", 1, "rw", 0, 2, False, 0, "param"),
    (0x00A1, "SC", 1, "wo", 0, 65535, False, None, "cmd"),
    (0x00A3, "TS", 2, "rw", 0, 255, False, 0, "param"),
    (0x00A5, "TD", 1, "rw", 0, 1, False, 1, "param"),
    (0x00A6, "TQ", 1, "rw", 1, 100, False, 25, "param"),
    (0x00A7, "VF", 1, "rw", 0, 1000, False, 0, "param"),
    # 5.2 user variable registers
    (0x00A8, "V1", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x00AA, "V2", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x00AC, "V3", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x00AE, "V4", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x00B0, "V5", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x00B2, "V6", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x00B4, "V7", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
    (0x00B6, "V8", 2, "rw", S32_MIN, S32_MAX, True, 0, "user"),
]


class Reg:
    __slots__ = ("addr", "name", "n", "access", "lo", "hi", "signed", "default", "kind")

    def __init__(self, t):
        (self.addr, self.name, self.n, self.access, self.lo, self.hi,
         self.signed, self.default, self.kind) = t


REGS = [Reg(t) for t in REG_TABLE]
REG_BY_NAME = {r.name: r for r in REGS}
ADDR_MAP = {}            # address -> (Reg, offset)
for _r in REGS:
    for _i in range(_r.n):
        ADDR_MAP[_r.addr + _i] = (_r, _i)
MAX_ADDR = 0x00B7

MS_ALLOWED = {1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127}
# Variables that IC / DC may act on: the value written is the register address of the variable.
INCDEC_TARGETS = {0x0005: "C1", 0x0007: "C2",
                  0x005F: "R1", 0x0061: "R2", 0x0063: "R3", 0x0065: "R4",
                  0x00A8: "V1", 0x00AA: "V2", 0x00AC: "V3", 0x00AE: "V4",
                  0x00B0: "V5", 0x00B2: "V6", 0x00B4: "V7", 0x00B6: "V8"}

INPUT_TYPES = {0, 1, 2, 3, 5, 7, 8, 11, 12}     # 4.4.6
ANALOG_MODES = {9, 10}
OUTPUT_TYPES = {16, 17, 18, 20, 21, 23, 24, 25, 28, 29}   # 26/27 reserved; 28 = output 3 only

ENC_COUNTS_PER_REV = 4000      # integrated encoder: 1000 lines, quadrature
UPGRADE_KEY = "2956102"        # 4.4.27
UPGRADE_WINDOW_S = 5.0

DEVICE_ID = {
    0x00: b"IMS USA",
    0x01: b"LMDCE572",
    0x02: b"4.0.0.0",
    0x03: b"https://novantaims.com/",
    0x04: b"LMD Ethernet",
    0x05: b"120870301",
    0x06: b"LMDCM 6.012, Hw: 1.0",
}


def factory_mfg():
    return {
        "AO": 0,
        "IS": {1: [0, 0], 2: [0, 0], 3: [0, 0], 4: [0, 0], 5: [9, 0]},   # [type|mode, active|range]
        "SS": {1: 0, 2: 0, 3: 0, 4: 0},                  # sink(0)/source(1) via S1..S4 alias
        "OS": {1: [16, 1], 2: [16, 1], 3: [16, 1]},      # [type, active]
        "MU_B": 0,
        "RD": 0, "AJ": 128, "AT": 0, "BE": 0, "BL": 0, "BM": 0,
        "DJ": 128, "DT": 0, "FS": 0, "FL": 0,
        "LS": {1: [2147483647, 0], 0: [-2147483648, 0]},  # direction -> [position, enabled]
        "TR": [0, 0, 0],
    }


def to_u32(v):
    return v & 0xFFFFFFFF


def from_u32(u, signed):
    if signed and u & 0x80000000:
        return u - 0x100000000
    return u


# --------------------------------------------------------------------------------------
# Drive model
# --------------------------------------------------------------------------------------
class Drive:
    def __init__(self):
        self.params = {r.name: r.default for r in REGS if r.kind in ("param",)}
        self.user = {r.name: 0 for r in REGS if r.kind == "user"}
        self.mfg = factory_mfg()
        self.nvm = self._settings_snapshot()
        self.c1 = 0
        self.c2_frac = 0.0
        self.c2 = 0
        self.pos = 0.0             # float axis position (steps)
        self.vel = 0.0             # signed velocity, steps/s
        self.mode = None           # None / 'pos' / 'slew' / 'home'
        self.target = 0
        self.slew_target = 0.0
        self.home_phases = []
        self.home_t = 0.0
        self.vc = 0
        self.ef = 0
        self.er = 0
        self.st = 0
        self.lr = 0
        self.pc = 0
        self.out_image = [0, 0, 0, 0]
        self.calib_until = 0.0
        self.upgrade_until = 0.0
        self.trip_ref = 0
        self.program = {"stored": False, "running": False, "paused": False}
        self.last = time.monotonic()
        self.counters = {"requests": 0, "responses": 0, "exception_responses": 0,
                         "frames_discarded": 0, "connections_accepted": 0,
                         "connections_evicted": 0, "connections_closed_on_error": 0}

    # ---------------- persistence helpers ----------------
    def _settings_snapshot(self):
        return json.loads(json.dumps({"params": self.params, "mfg": self.mfg}))

    def initialize_parameters(self):
        self.params = {r.name: r.default for r in REGS if r.kind == "param"}
        self.mfg = factory_mfg()
        self.out_image = [0, 0, 0, 0]

    # ---------------- motion simulation ----------------
    def update(self, now=None):
        if now is None:
            now = time.monotonic()
        dt_total = now - self.last
        self.last = now
        if dt_total <= 0:
            return
        dt_total = min(dt_total, 5.0)
        if self.mode is None:
            self.vc = 0
            return
        steps = max(1, int(dt_total / 0.002) + 1)
        dt = dt_total / steps
        for _ in range(steps):
            if self.mode is None:
                break
            self._step(dt)

    def _accel(self):
        return float(self.params["A"])

    def _decel(self):
        return float(self.params["D"])

    def _advance(self, dp):
        old = int(round(self.pos))
        self.pos += dp
        # software limits
        for d, (lim, en) in self.mfg["LS"].items():
            if not en:
                continue
            if d == 1 and self.pos > lim and dp > 0:
                self.pos = float(lim)
                self._halt()
            elif d == 0 and self.pos < lim and dp < 0:
                self.pos = float(lim)
                self._halt()
        # 32-bit wrap of the position counter
        if self.pos > S32_MAX or self.pos < S32_MIN:
            self.pos = float(from_u32(to_u32(int(round(self.pos))), True))
            self.target = from_u32(to_u32(self.target), True)
        new = int(round(self.pos))
        delta = new - old
        if delta:
            self.c1 = from_u32(to_u32(self.c1 + delta), True)
            ms = self.params["MS"]
            self.c2_frac += delta * ENC_COUNTS_PER_REV / (200.0 * ms)
            whole = int(self.c2_frac)
            self.c2_frac -= whole
            self.c2 = from_u32(to_u32(self.c2 + whole), True)
            self._trip_check()

    def _trip_check(self):
        te = self.params["TE"]
        if te & 16:
            dist = abs(self.mfg["TR"][0])
            if dist and abs(int(round(self.pos)) - self.trip_ref) >= dist:
                self.params["TE"] = te & ~16      # one-shot: must be re-enabled

    def _halt(self):
        self.mode = None
        self.vel = 0.0
        self.vc = 0
        self.home_phases = []

    def _step(self, dt):
        vi = float(self.params["VI"])
        vm = float(self.params["VM"])
        A = self._accel()
        D = self._decel()
        if self.mode == "pos":
            rem = self.target - self.pos
            if abs(rem) < 0.5:
                self.pos = float(self.target)
                self._halt()
                return
            direction = 1.0 if rem > 0 else -1.0
            speed = abs(self.vel)
            if speed < vi:
                speed = vi
            stop_d = (speed * speed - vi * vi) / (2.0 * D) if speed > vi else 0.0
            before = speed
            if abs(rem) <= stop_d + speed * dt:
                speed = max(vi, speed - D * dt)
            elif speed < vm:
                speed = min(vm, speed + A * dt)
            elif speed > vm:
                speed = max(vm, speed - D * dt)
            self.vc = 1 if speed != before else 0
            step = speed * dt
            if step >= abs(rem):
                self._advance(rem)
                self.pos = float(self.target) if self.mode == "pos" else self.pos
                self._halt()
                return
            self.vel = direction * speed
            self._advance(direction * step)
        elif self.mode in ("slew", "home"):
            if self.mode == "home":
                if not self.home_phases:
                    self._finish_home()
                    return
                ph = self.home_phases[0]
                self.slew_target = ph[0]
                if ph[1] is not None:
                    ph[1] -= dt
                    if ph[1] <= 0:
                        self.home_phases.pop(0)
                        if ph[2]:        # instant stop at end of creep phase
                            self.vel = 0.0
                        return
            tgt = self.slew_target
            v = self.vel
            before = v
            if v == 0.0 and tgt != 0.0:
                v = vi if tgt > 0 else -vi
                if abs(tgt) < vi:
                    v = tgt
            elif tgt == 0.0 or (v > 0) != (tgt > 0):
                # decelerate towards zero (then reverse if needed)
                mag = abs(v) - D * dt
                if mag <= vi or mag <= 0:
                    v = 0.0
                else:
                    v = mag if v > 0 else -mag
            else:
                if abs(v) < abs(tgt):
                    mag = min(abs(tgt), abs(v) + A * dt)
                else:
                    mag = max(abs(tgt), abs(v) - D * dt)
                v = mag if tgt > 0 else -mag
            self.vc = 1 if v != before else 0
            self.vel = v
            if v == 0.0 and tgt == 0.0:
                if self.mode == "slew":
                    self._halt()
                    return
                if self.mode == "home" and self.home_phases and self.home_phases[0][1] is None:
                    self.home_phases.pop(0)
                    return
            self._advance(v * dt)

    def _finish_home(self):
        self._halt()
        self.pos = 0.0
        self.target = 0

    def start_home(self, mode):
        vm = float(self.params["VM"])
        vi = float(self.params["VI"])
        slew_dir, creep_dir = {1: (-1, 1), 2: (-1, -1), 3: (1, -1), 4: (1, 1)}[mode]
        # [velocity target, remaining time or None (= until stopped), hard stop at end]
        self.home_phases = [[slew_dir * vm, 0.25, False], [0.0, None, False],
                            [creep_dir * vi, 0.15, True]]
        self.mode = "home"
        self.vel = 0.0

    # ---------------- derived status ----------------
    def moving(self):
        return 1 if self.mode is not None else 0

    def P(self):
        return int(round(self.pos))

    def calibrating(self):
        return time.monotonic() < self.calib_until

    def af(self):
        v = 0
        if self.lr:
            v |= 8
        if self.params["AS"] != 0 and self.params["DE"] and not self.calibrating():
            v |= 16
        v |= 64                           # lead/lag is always zero in the simulation
        if not self.calibrating():
            v |= 128
        return v

    def attention_status(self):
        s = 0
        if self.ef:
            s |= 1
        if self.lr:
            s |= 2
        if self.af() & 16:
            s |= 16
        if self.calibrating():
            s |= 32
        if not self.params["DE"]:
            s |= 2048
        if self.moving():
            s |= 16384
        if self.st:
            s |= 32768
        if not self.moving():
            s |= 512                       # current reduction active when stopped
        return s

    def output_state(self, i):
        """Logical state of output i (0-based). Output 4 (i=3) has no OS setup."""
        if i == 3:
            return self.out_image[3]
        t = self.mfg["OS"][i + 1][0]
        if t == 16:
            return self.out_image[i]
        if t == 17:
            return self.moving()
        if t == 18:
            return self.ef
        if t == 20:
            return self.vc
        if t == 21:
            return self.lr
        if t == 23:
            return 1 if self.mode == "pos" else 0
        if t == 24:
            return 1 if self.af() & 16 else 0
        if t == 29:
            return 1 if self.attention_status() & self.mfg["AO"] else 0
        return 0

    def input_state(self, i):
        return 0          # nothing wired to the simulated inputs

    # ---------------- register access ----------------
    def reg_value(self, r):
        n = r.name
        if r.kind in ("param",):
            return self.params[n]
        if r.kind == "user":
            return self.user[n]
        if n == "C1":
            return self.c1
        if n == "C2":
            return self.c2
        if n == "P":
            return self.P()
        if n == "BY":
            return 1 if self.program["running"] else 0
        if n == "EF":
            return self.ef
        if n == "ER":
            return self.er
        if n in ("I1", "I2", "I3", "I4"):
            return self.input_state(int(n[1]) - 1)
        if n in ("I5", "I6"):
            return 0
        if n == "IN":
            return sum(self.input_state(i) << i for i in range(4))
        if n == "MP":
            return 1 if self.mode == "pos" else 0
        if n == "MV":
            return self.moving()
        if n in ("O1", "O2", "O3"):
            return self.output_state(int(n[1]) - 1)
        if n == "OT":
            return sum(self.output_state(i) << i for i in range(4))
        if n == "OF":
            return 0
        if n == "PC":
            return self.pc
        if n == "ST":
            return self.st
        if n == "V":
            return int(round(self.vel))
        if n == "VC":
            return self.vc if self.moving() else 0
        if n == "AF":
            return self.af()
        if n == "LL":
            return 0
        if n == "LR":
            return self.lr
        raise MbError(DEVICE_FAILURE)

    def read_regs(self, start, qty):
        if qty < 1 or qty > 2:
            raise MbError(ILLEGAL_VALUE)
        items = self._items(start, qty)
        for r in items:
            if r.access == "wo":
                raise MbError(ILLEGAL_ADDRESS)
        self.update()
        words = []
        for r in items:
            v = self.reg_value(r)
            if r.n == 2:
                u = to_u32(v)
                words += [u & 0xFFFF, u >> 16]
            else:
                words.append(v & 0xFFFF)
            if r.name == "ER":          # reading ER clears the error (manual 0x0021)
                self.er = 0
                self.ef = 0
        return words

    def _items(self, start, qty):
        end = start + qty - 1
        if end > MAX_ADDR:
            raise MbError(ILLEGAL_ADDRESS)
        items = []
        a = start
        while a <= end:
            ent = ADDR_MAP.get(a)
            if ent is None:
                raise MbError(ILLEGAL_ADDRESS)
            r, off = ent
            if off != 0 or a + r.n - 1 > end:
                raise MbError(ILLEGAL_ADDRESS)   # would split a 32-bit item
            items.append(r)
            a += r.n
        return items

    def write_regs(self, start, words):
        items = self._items(start, len(words))
        for r in items:
            if r.access == "ro":
                raise MbError(ILLEGAL_ADDRESS)
        self.update()
        vals = []
        i = 0
        for r in items:
            if r.n == 2:
                u = words[i] | (words[i + 1] << 16)
                v = from_u32(u, r.signed)
            else:
                v = words[i]
            i += r.n
            vals.append((r, v))
        # validate everything first, then apply (no partial writes)
        for r, v in vals:
            self._validate(r, v)
        for r, v in vals:
            self._apply(r, v)

    def _validate(self, r, v):
        n = r.name
        if v < r.lo or v > r.hi:
            raise MbError(ILLEGAL_VALUE)
        if n == "MS" and v not in MS_ALLOWED:
            raise MbError(ILLEGAL_VALUE)
        if n == "HT":
            if v == 1 or v + self.params["MT"] > 65535:
                raise MbError(ILLEGAL_VALUE)
        if n == "MT" and v + self.params["HT"] > 65535:
            raise MbError(ILLEGAL_VALUE)
        if n == "VI" and v >= self.params["VM"]:
            raise MbError(ILLEGAL_VALUE)
        if n == "VM" and v <= self.params["VI"]:
            raise MbError(ILLEGAL_VALUE)
        if n in ("IC", "DC") and v not in INCDEC_TARGETS:
            raise MbError(ILLEGAL_VALUE)
        if n in ("O1", "O2", "O3"):
            if self.mfg["OS"][int(n[1])][0] != 16:
                raise MbError(DEVICE_FAILURE)    # output is not configured general purpose
        if n in ("MA", "MR", "HI", "HM"):
            if not self.params["DE"] or self.mode is not None or self.upgrading():
                raise MbError(DEVICE_FAILURE)
        if n == "SL":
            if not self.params["DE"] or self.mode not in (None, "slew") or self.upgrading():
                raise MbError(DEVICE_FAILURE)
        if n == "P" and self.mode is not None:
            raise MbError(DEVICE_FAILURE)
        if n in ("S", "IP", "SC", "CF") and self.mode is not None:
            raise MbError(DEVICE_FAILURE)

    def _apply(self, r, v):
        n = r.name
        if r.kind == "param":
            self.params[n] = v
            if n == "DE" and v == 0 and self.mode is not None:
                self._halt()               # bridge disabled: motion stops at once
            if n == "TE" and v & 16:
                self.trip_ref = self.P()
            return
        if r.kind == "user":
            self.user[n] = v
            return
        if n == "C1":
            self.c1 = v
        elif n == "C2":
            self.c2 = v
            self.c2_frac = 0.0
        elif n == "P":
            self.pos = float(v)
            self.target = v
        elif n == "ER":
            self.er = 0
            self.ef = 0
        elif n == "ST":
            self.st = 0
        elif n in ("O1", "O2", "O3"):
            self.out_image[int(n[1]) - 1] = v
        elif n == "OT":
            for i in range(4):
                if i < 3 and self.mfg["OS"][i + 1][0] != 16:
                    continue                 # function outputs are driven by the drive
                self.out_image[i] = (v >> i) & 1
        elif n in ("IC", "DC"):
            name = INCDEC_TARGETS[v]
            d = 1 if n == "IC" else -1
            if name in self.user:
                self.user[name] = from_u32(to_u32(self.user[name] + d), True)
            elif name == "C1":
                self.c1 = from_u32(to_u32(self.c1 + d), True)
            elif name == "C2":
                self.c2 = from_u32(to_u32(self.c2 + d), True)
        elif n == "MA":
            self._start_move(v)
        elif n == "MR":
            self._start_move(from_u32(to_u32(self.P() + v), True))
        elif n == "SL":
            if v == 0:
                if self.mode == "slew":
                    self.slew_target = 0.0
            else:
                self.slew_target = float(v)
                if self.mode is None:
                    self.mode = "slew"
                    self.vel = 0.0
        elif n in ("HM", "HI"):
            self.start_home(v)
        elif n == "S":
            self.nvm = self._settings_snapshot()
        elif n == "IP":
            self.initialize_parameters()
        elif n == "CF":
            self.lr = 0
            self.calib_until = time.monotonic() + 0.5
        elif n == "SC":
            self.calib_until = time.monotonic() + 1.0

    def _start_move(self, target):
        ls = self.mfg["LS"]
        if ls[1][1] and target > ls[1][0]:
            target = ls[1][0]
        if ls[0][1] and target < ls[0][0]:
            target = ls[0][0]
        self.target = target
        if target == self.P():
            return
        self.mode = "pos"
        self.vel = 0.0

    def upgrading(self):
        return time.monotonic() < self.upgrade_until

    # ---------------- coils / inputs ----------------
    def read_coils(self, start, qty):
        if qty < 1 or qty > 4:
            raise MbError(ILLEGAL_VALUE)
        if start > 3 or start + qty > 4:
            raise MbError(ILLEGAL_ADDRESS)
        self.update()
        return [self.output_state(i) for i in range(start, start + qty)]

    def read_inputs(self, start, qty):
        if qty < 1 or qty > 4:
            raise MbError(ILLEGAL_VALUE)
        if start > 3 or start + qty > 4:
            raise MbError(ILLEGAL_ADDRESS)
        return [self.input_state(i) for i in range(start, start + qty)]

    def write_coil(self, addr, value):
        if value not in (0x0000, 0xFF00):
            raise MbError(ILLEGAL_VALUE)
        if addr > 3:
            raise MbError(ILLEGAL_ADDRESS)
        if addr < 3 and self.mfg["OS"][addr + 1][0] != 16:
            raise MbError(DEVICE_FAILURE)
        self.out_image[addr] = 1 if value == 0xFF00 else 0

    # ---------------- manufacturer specific (MCode mnemonics) ----------------
    def mfg_read(self, mn):
        self.update()
        if self.upgrading():
            raise MbError(DEVICE_FAILURE)
        m = self.mfg
        simple = ("AO", "RD", "AJ", "AT", "BE", "BL", "BM", "DJ", "DT", "FS", "FL")
        if mn in simple:
            return str(m[mn])
        if mn == "EL":
            return str(ENC_COUNTS_PER_REV // 4)
        if mn == "IS":
            return "; ".join(self._fmt_is(k) for k in range(1, 6))
        if len(mn) == 3 and mn[:2] == "IS" and mn[2] in "12345":
            return self._fmt_is(int(mn[2]))
        if len(mn) == 2 and mn[0] == "S" and mn[1] in "1234":
            k = int(mn[1])
            t, a = m["IS"][k]
            return "%d, %d, %d" % (t, a, m["SS"][k])
        if mn == "OS":
            return "; ".join(self._fmt_os(k) for k in range(1, 4))
        if len(mn) == 3 and mn[:2] == "OS" and mn[2] in "123":
            return self._fmt_os(int(mn[2]))
        if mn == "IT":
            bridge = 38 + (3 if self.params["DE"] else 0)
            return "%d,%d" % (bridge, 36)
        if mn == "VT":
            return "24,48"
        if mn == "MU":
            return "%d, %d" % (self.params["MU"], m["MU_B"])
        if mn == "AV":
            return str(int(round(self.vel)) if self.params["AS"] else 0)
        if mn == "LS":
            return "; ".join(self._fmt_ls(d) for d in (1, 0))
        if len(mn) == 3 and mn[:2] == "LS" and mn[2] in "01":
            return self._fmt_ls(int(mn[2]))
        if mn == "TR":
            return "%d, %d, %d" % tuple(m["TR"])
        if mn in WO_MNEMONICS:
            raise MbError(ILLEGAL_ADDRESS)
        raise MbError(ILLEGAL_ADDRESS)

    def _fmt_is(self, k):
        t, a = self.mfg["IS"][k]
        return "%d, %d, %d" % (k, t, a)

    def _fmt_os(self, k):
        t, a = self.mfg["OS"][k]
        return "%d, %d, %d" % (k, t, a)

    def _fmt_ls(self, d):
        p, e = self.mfg["LS"][d]
        return "%d, %d, %d" % (d, p, e)

    def mfg_write(self, mn, data):
        self.update()
        if mn in RO_MNEMONICS:
            raise MbError(ILLEGAL_ADDRESS)
        try:
            text = data.decode("ascii")
        except UnicodeDecodeError:
            raise MbError(ILLEGAL_VALUE)
        if any(ord(c) < 0x20 or ord(c) > 0x7E for c in text):
            raise MbError(ILLEGAL_VALUE)
        if mn == "UG":
            arg = text.strip().lstrip("=").strip()
            if arg.replace(" ", "") != UPGRADE_KEY:
                raise MbError(ILLEGAL_VALUE)
            if self.mode is not None:
                raise MbError(DEVICE_FAILURE)
            self.upgrade_until = time.monotonic() + UPGRADE_WINDOW_S
            return
        if self.upgrading():
            raise MbError(DEVICE_FAILURE)
        if mn in ("\x1b", "E", "PS", "RS", "CP"):
            if text.strip():
                raise MbError(ILLEGAL_VALUE)
            if mn == "\x1b":
                self.program.update(running=False, paused=False)
                if self.mode is not None:
                    self.mode = "slew"
                    self.home_phases = []
                    self.slew_target = 0.0
            elif mn == "E":
                self.program.update(running=False, paused=False)
            elif mn == "PS":
                if self.program["running"]:
                    self.program["paused"] = True
            elif mn == "RS":
                if self.program["paused"]:
                    self.program["paused"] = False
            elif mn == "CP":
                if self.program["running"]:
                    raise MbError(DEVICE_FAILURE)
                self.program["stored"] = False
            return
        if mn == "EX":
            arg = text.strip().lstrip("=").strip().upper()
            ok = (len(arg) == 2 and arg[0].isalpha() and arg.isalnum()) or \
                 (arg.isdigit() and 1 <= int(arg) <= 8191)
            if not ok:
                raise MbError(ILLEGAL_VALUE)
            # factory state: program space empty -> label/address cannot be found
            if not self.program["stored"]:
                raise MbError(DEVICE_FAILURE)
            return
        vals = parse_args(text)
        m = self.mfg

        def need(count):
            if len(vals) != count:
                raise MbError(ILLEGAL_VALUE)

        def rng(v, lo, hi):
            if v < lo or v > hi:
                raise MbError(ILLEGAL_VALUE)

        if mn == "AO":
            need(1); rng(vals[0], 0, 65535); m["AO"] = vals[0]
        elif mn in ("RD", "BE", "BM", "FL", "AT", "DT"):
            need(1); rng(vals[0], 0, 1); m[mn] = vals[0]
        elif mn in ("AJ", "DJ"):
            need(1); rng(vals[0], 1, 255); m[mn] = vals[0]
        elif mn == "BL":
            need(1); rng(vals[0], 0, 2147483647); m["BL"] = vals[0]
        elif mn == "FS":
            need(1); rng(vals[0], 0, 65535); m["FS"] = vals[0]
        elif mn == "IS":
            need(3)
            k, t, a = vals
            rng(k, 1, 5)
            if k == 5:
                if t not in ANALOG_MODES:
                    raise MbError(ILLEGAL_VALUE)
            elif t not in INPUT_TYPES:
                raise MbError(ILLEGAL_VALUE)
            rng(a, 0, 1)
            m["IS"][k] = [t, a]
        elif len(mn) == 2 and mn[0] == "S" and mn[1] in "1234":
            need(3)
            t, a, s = vals
            if t not in INPUT_TYPES:
                raise MbError(ILLEGAL_VALUE)
            rng(a, 0, 1); rng(s, 0, 1)
            k = int(mn[1])
            m["IS"][k] = [t, a]
            m["SS"][k] = s
        elif mn == "OS":
            need(3)
            k, t, a = vals
            rng(k, 1, 3)
            if t not in OUTPUT_TYPES or (t == 28 and k != 3):
                raise MbError(ILLEGAL_VALUE)
            rng(a, 0, 1)
            m["OS"][k] = [t, a]
        elif mn == "MU":
            need(2)
            rng(vals[0], 0, 2); rng(vals[1], 0, 1)
            self.params["MU"] = vals[0]
            m["MU_B"] = vals[1]
        elif mn == "LS":
            need(3)
            d, p, e = vals
            rng(d, 0, 1); rng(p, S32_MIN, S32_MAX); rng(e, 0, 1)
            m["LS"][d] = [p, e]
        elif mn == "TR":
            need(3)
            rng(vals[0], S32_MIN, S32_MAX); rng(vals[1], 0, 3); rng(vals[2], 0, 1)
            m["TR"] = list(vals)
            self.trip_ref = self.P()
        elif mn == "HF":
            need(1); rng(vals[0], 1, 4)
            if not self.params["DE"] or self.mode is not None:
                raise MbError(DEVICE_FAILURE)
            self.start_home(vals[0])
        else:
            raise MbError(ILLEGAL_ADDRESS)

    # ---------------- state dump ----------------
    def state(self):
        self.update()
        regs = {}
        for r in REGS:
            key = "0x%04X" % r.addr
            ent = {"name": r.name, "access": r.access, "registers": r.n}
            if r.access != "wo":
                v = self.reg_value(r)
                ent["value"] = v
                if r.n == 2:
                    u = to_u32(v)
                    ent["words"] = [u & 0xFFFF, u >> 16]
                else:
                    ent["words"] = [v & 0xFFFF]
            regs[key] = ent
        m = self.mfg
        return {
            "device": {"product": DEVICE_ID[1].decode(), "unit_ids": "any (ignored)"},
            "holding_registers": regs,
            "coils": {str(i): self.output_state(i) for i in range(4)},
            "output_image": list(self.out_image),
            "discrete_inputs": {str(i): self.input_state(i) for i in range(4)},
            "mfg_functions": {
                "AO": m["AO"],
                "EL": ENC_COUNTS_PER_REV // 4,
                "IS": {str(k): {"type_or_mode": v[0], "active_or_range": v[1]} for k, v in m["IS"].items()},
                "S1-S4_sink_source": {str(k): v for k, v in m["SS"].items()},
                "OS": {str(k): {"type": v[0], "active": v[1]} for k, v in m["OS"].items()},
                "MU": [self.params["MU"], m["MU_B"]],
                "RD": m["RD"], "AJ": m["AJ"], "AT": m["AT"], "BE": m["BE"], "BL": m["BL"],
                "BM": m["BM"], "DJ": m["DJ"], "DT": m["DT"], "FS": m["FS"], "FL": m["FL"],
                "LS": {str(d): {"position": v[0], "enabled": v[1]} for d, v in m["LS"].items()},
                "TR": list(m["TR"]),
            },
            "program": dict(self.program),
            "upgrade_mode": self.upgrading(),
            "motion": {"mode": self.mode, "position": self.P(), "velocity": int(round(self.vel)),
                       "target": self.target if self.mode == "pos" else None},
            "nvm": self.nvm,
            "diagnostic_counters": dict(self.counters),
        }


RO_MNEMONICS = {"IT", "VT", "AV", "EL"}
WO_MNEMONICS = {"\x1b", "CP", "EX", "PS", "RS", "E", "HF", "UG"}


def parse_args(text):
    s = text.strip()
    if s.startswith("="):
        s = s[1:]
    if not s.strip():
        raise MbError(ILLEGAL_VALUE)
    out = []
    for part in s.split(","):
        p = part.strip()
        if p.startswith("+"):
            p = p[1:]
        neg = p.startswith("-")
        digits = p[1:] if neg else p
        if not digits.isdigit() or len(digits) > 10:
            raise MbError(ILLEGAL_VALUE)
        out.append(-int(digits) if neg else int(digits))
    return out


def decode_mnemonic(b4):
    """The mnemonic is sent reversed: bytes [hi0 hi1 lo0 lo1] -> reversed string."""
    s = bytes(reversed(b4)).decode("latin-1").strip(" \x00")
    if s == "\x1b":
        return s
    if not s or not all(c.isalnum() for c in s):
        return None
    return s.upper()


# --------------------------------------------------------------------------------------
# PDU processing
# --------------------------------------------------------------------------------------
def exc(fc, code):
    return bytes([(fc | 0x80) & 0xFF, code])


def pack_bits(bits):
    out = bytearray((len(bits) + 7) // 8)
    for i, b in enumerate(bits):
        if b:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def handle_pdu(drive, pdu):
    fc = pdu[0]
    try:
        if fc in (0x05, 0x10, 0x41, 0x42) and drive.upgrading():
            raise MbError(DEVICE_FAILURE)      # upgrade mode: only reads are served
        if fc in (0x01, 0x02):
            if len(pdu) != 5:
                raise MbError(ILLEGAL_VALUE)
            start = int.from_bytes(pdu[1:3], "big")
            qty = int.from_bytes(pdu[3:5], "big")
            bits = drive.read_coils(start, qty) if fc == 1 else drive.read_inputs(start, qty)
            pb = pack_bits(bits)
            return bytes([fc, len(pb)]) + pb
        if fc == 0x03:
            if len(pdu) != 5:
                raise MbError(ILLEGAL_VALUE)
            start = int.from_bytes(pdu[1:3], "big")
            qty = int.from_bytes(pdu[3:5], "big")
            words = drive.read_regs(start, qty)
            body = b"".join(w.to_bytes(2, "big") for w in words)
            return bytes([3, len(body)]) + body
        if fc == 0x05:
            if len(pdu) != 5:
                raise MbError(ILLEGAL_VALUE)
            addr = int.from_bytes(pdu[1:3], "big")
            val = int.from_bytes(pdu[3:5], "big")
            drive.write_coil(addr, val)
            return bytes(pdu)
        if fc == 0x10:
            if len(pdu) < 6:
                raise MbError(ILLEGAL_VALUE)
            start = int.from_bytes(pdu[1:3], "big")
            qty = int.from_bytes(pdu[3:5], "big")
            bc = pdu[5]
            if qty < 1 or qty > 2 or bc != 2 * qty or len(pdu) != 6 + bc:
                raise MbError(ILLEGAL_VALUE)
            words = [int.from_bytes(pdu[6 + 2 * i:8 + 2 * i], "big") for i in range(qty)]
            drive.write_regs(start, words)
            return bytes(pdu[0:5])
        if fc == 0x2B:
            if len(pdu) < 2:
                raise MbError(ILLEGAL_VALUE)
            if pdu[1] != 0x0E:
                raise MbError(ILLEGAL_FUNCTION)
            if len(pdu) != 4:
                raise MbError(ILLEGAL_VALUE)
            return read_device_id(pdu[2], pdu[3])
        if fc == 0x41:
            if len(pdu) != 5:
                raise MbError(ILLEGAL_VALUE)
            mn = decode_mnemonic(pdu[1:5])
            if mn is None:
                raise MbError(ILLEGAL_ADDRESS)
            s = drive.mfg_read(mn).encode("ascii")
            return bytes([0x41, len(s)]) + s
        if fc == 0x42:
            if len(pdu) < 6:
                raise MbError(ILLEGAL_VALUE)
            bc = pdu[5]
            if bc > 28 or len(pdu) != 6 + bc:
                raise MbError(ILLEGAL_VALUE)
            mn = decode_mnemonic(pdu[1:5])
            if mn is None:
                raise MbError(ILLEGAL_ADDRESS)
            if mn not in KNOWN_WRITE and not (len(mn) == 2 and mn[0] == "S" and mn[1] in "1234"):
                raise MbError(ILLEGAL_ADDRESS)
            drive.mfg_write(mn, bytes(pdu[6:6 + bc]))
            return bytes([0x42, 4]) + bytes(pdu[1:5])
        raise MbError(ILLEGAL_FUNCTION)
    except MbError as e:
        drive.counters["exception_responses"] += 1
        return exc(fc, e.code)


KNOWN_WRITE = {"\x1b", "AO", "CP", "EL", "EX", "IS", "IT", "MU", "OS", "PS", "RS", "E",
               "RD", "AJ", "AT", "BE", "BL", "BM", "DJ", "DT", "FS", "HF", "AV", "FL",
               "LS", "UG", "VT", "TR"}


def read_device_id(code, obj):
    if code not in (1, 2, 3, 4):
        raise MbError(ILLEGAL_VALUE)
    if code == 4:
        if obj not in DEVICE_ID:
            raise MbError(ILLEGAL_ADDRESS)
        ids = [obj]
    else:
        last = 0x02 if code == 1 else 0x06
        if obj > last:
            obj = 0
        ids = list(range(obj, last + 1))
    body = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)])
    for i in ids:
        v = DEVICE_ID[i]
        body += bytes([i, len(v)]) + v
    return bytes(body)


# --------------------------------------------------------------------------------------
# TCP server
# --------------------------------------------------------------------------------------
MAX_CONNECTIONS = 16
MAX_MBAP_LEN = 254           # unit id + max PDU (253)


class Server:
    def __init__(self, drive):
        self.drive = drive
        self.active = 0
        self.writers = {}          # writer -> time of last activity

    async def handle(self, reader, writer):
        d = self.drive
        if len(self.writers) >= MAX_CONNECTIONS:
            # Implementation Guide connection management: close the oldest unused connection
            oldest = min(self.writers, key=self.writers.get)
            self.writers.pop(oldest, None)
            d.counters["connections_evicted"] += 1
            try:
                oldest.close()
            except Exception:
                pass
        self.active += 1
        self.writers[writer] = time.monotonic()
        d.counters["connections_accepted"] += 1
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid = hdr[0:2]
                pid = int.from_bytes(hdr[2:4], "big")
                ln = int.from_bytes(hdr[4:6], "big")
                uid = hdr[6]
                if ln > MAX_MBAP_LEN or ln < 1:
                    # framing cannot be trusted any more: drop the connection
                    d.counters["connections_closed_on_error"] += 1
                    break
                body = await reader.readexactly(ln - 1) if ln > 1 else b""
                if writer in self.writers:
                    self.writers[writer] = time.monotonic()
                d.counters["requests"] += 1
                if pid != 0 or len(body) == 0:
                    d.counters["frames_discarded"] += 1
                    continue
                try:
                    resp = handle_pdu(d, body)
                except Exception:                      # never let one frame kill the server
                    resp = exc(body[0], DEVICE_FAILURE)
                    d.counters["exception_responses"] += 1
                adu = tid + b"\x00\x00" + (len(resp) + 1).to_bytes(2, "big") + bytes([uid]) + resp
                writer.write(adu)
                d.counters["responses"] += 1
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            self.active -= 1
            self.writers.pop(writer, None)
            try:
                writer.close()
            except Exception:
                pass


def dump_state(drive, path):
    if not path:
        return
    try:
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(drive.state(), f, indent=1, sort_keys=True)
        os.replace(tmp, path)
    except Exception as e:          # pragma: no cover
        print("state dump failed: %s" % e, file=sys.stderr)


async def ticker(drive):
    while True:
        await asyncio.sleep(0.02)
        try:
            drive.update()
        except Exception as e:      # pragma: no cover
            print("tick error: %s" % e, file=sys.stderr)


async def main_async(args):
    host, _, port = args.listen.rpartition(":")
    if host not in ("127.0.0.1", "localhost", "::1", "[::1]"):
        print("refusing to bind to non-loopback address %s" % host, file=sys.stderr)
        sys.exit(2)
    host = host.strip("[]")
    drive = Drive()
    srv = Server(drive)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, lambda: dump_state(drive, args.state))
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    server = await asyncio.start_server(srv.handle, host, int(port))
    sock = server.sockets[0].getsockname()
    print("listening tcp %s:%d" % (sock[0], sock[1]), flush=True)
    tick = asyncio.create_task(ticker(drive))
    await stop.wait()
    tick.cancel()
    server.close()
    dump_state(drive, args.state)
    for w in list(srv.writers):
        try:
            w.close()
        except Exception:
            pass
    await asyncio.sleep(0.05)


def main():
    ap = argparse.ArgumentParser(description="Lexium MDrive Ethernet Modbus/TCP simulator")
    ap.add_argument("--listen", required=True, help="127.0.0.1:PORT (0 = any free port)")
    ap.add_argument("--state", default=None, help="JSON state file (SIGUSR1 / exit)")
    args = ap.parse_args()
    asyncio.run(main_async(args))


if __name__ == "__main__":
    main()
