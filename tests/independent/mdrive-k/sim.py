#!/usr/bin/env python3
"""MDrive 23 Hybrid Motion Control (Ethernet) - MODBUS/TCP server simulator.

Written from the "MODBUS/TCP Fieldbus Manual, MDrive Motion Control Products" (R040611) and the public
MODBUS specifications.  Standard library only.  See DECISIONS.md for every interpretation.

Usage:  python3 sim.py --listen 127.0.0.1:0 [--state FILE]
"""
import argparse
import asyncio
import json
import os
import signal
import struct
import sys
import time

INT32_MIN, INT32_MAX = -2147483648, 2147483647
UNIT_IDS = (0x00, 0x01, 0xFF)

# exception codes
ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE = 1, 2, 3, 4

ERR_LOCKED_ROTOR = 86        # our firmware's error number for "stall / locked rotor detected"


class MbError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


MS_VALUES = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)


class Param:
    """One documented register (1 register = bytes 1 or 2, 2 registers = 4-byte value, hi word first)."""

    def __init__(self, addr, nregs, mcode, access, default=None, lo=None, hi=None,
                 signed=False, allowed=None, name=""):
        self.addr, self.nregs, self.mcode, self.access = addr, nregs, mcode, access
        self.default, self.lo, self.hi, self.signed, self.allowed = default, lo, hi, signed, allowed
        self.name = name

    def check(self, v):
        if self.allowed is not None:
            return v in self.allowed
        if self.lo is not None and v < self.lo:
            return False
        if self.hi is not None and v > self.hi:
            return False
        return True


# access: rw = read/write setting, ro = read-only status, wo = write-only command
PARAMS = [
    Param(0x0000, 2, "A", "rw", 1000000, 91, 1525878997, name="Acceleration"),
    Param(0x0005, 2, "C1", "rw", 0, INT32_MIN, INT32_MAX, signed=True, name="Counter 1"),
    Param(0x0007, 2, "C2", "rw", 0, INT32_MIN, INT32_MAX, signed=True, name="Counter 2"),
    Param(0x0009, 1, "CE", "rw", 1, 0, 1, name="Software reset enable"),
    Param(0x000F, 1, "D1", "rw", 0, 0, 255, name="Input 1 debounce"),
    Param(0x0010, 1, "D2", "rw", 0, 0, 255, name="Input 2 debounce"),
    Param(0x0011, 1, "D3", "rw", 0, 0, 255, name="Input 3 debounce"),
    Param(0x0012, 1, "D4", "rw", 0, 0, 255, name="Input 4 debounce"),
    Param(0x0013, 1, "D5", "rw", 0, 0, 255, name="Analog input filter"),
    Param(0x0018, 2, "D", "rw", 1000000, 91, 1525878997, name="Deceleration"),
    Param(0x001B, 1, "DC", "wo", None, 1, 4, name="Decrement variable"),
    Param(0x001C, 1, "DE", "rw", 1, 0, 1, name="Drive enable"),
    Param(0x001E, 1, "EE", "rw", 0, 0, 1, name="Encoder enable"),
    Param(0x001F, 1, "EF", "ro", name="Error flag"),
    Param(0x0021, 1, "ER", "rw", 0, 0, 0, name="Error"),
    Param(0x0029, 1, "HC", "rw", 5, 0, 100, name="Holding current"),
    Param(0x002B, 1, "HM", "rw", 1, 1, 4, name="Homing mode"),
    Param(0x002C, 1, "HT", "rw", 500, 0, 65535, name="Hold current delay time"),
    Param(0x002D, 1, "I1", "ro", name="Read input 1"),
    Param(0x002E, 1, "I2", "ro", name="Read input 2"),
    Param(0x002F, 1, "I3", "ro", name="Read input 3"),
    Param(0x0030, 1, "I4", "ro", name="Read input 4"),
    Param(0x0031, 1, "I5", "ro", name="Read analog input"),
    Param(0x0037, 1, "IC", "wo", None, 1, 4, name="Increment variable"),
    Param(0x003A, 1, "IL", "ro", name="Read inputs 1-4 as BCD"),
    Param(0x003B, 1, "IN", "ro", name="Read all inputs as BCD"),
    Param(0x003F, 1, "JE", "rw", 0, 0, 1, name="Jog enable"),
    Param(0x0042, 1, "LM", "rw", 1, 1, 6, name="Limit stop mode"),
    Param(0x0043, 2, "MA", "wo", None, INT32_MIN, INT32_MAX, signed=True, name="Move to absolute position"),
    Param(0x0045, 1, "MP", "ro", name="Moving to position"),
    Param(0x0046, 2, "MR", "wo", None, INT32_MIN, INT32_MAX, signed=True, name="Move to relative position"),
    Param(0x0048, 1, "MS", "rw", 256, allowed=MS_VALUES, name="Microstep resolution"),
    Param(0x0049, 1, "MT", "rw", 0, 0, 65000, name="Motor settling delay time"),
    Param(0x004A, 1, "MV", "ro", name="Moving"),
    Param(0x004B, 1, "O1", "rw", None, 0, 1, name="Write output 1"),
    Param(0x004C, 1, "O2", "rw", None, 0, 1, name="Write output 2"),
    Param(0x004D, 1, "O3", "rw", None, 0, 1, name="Write output 3"),
    Param(0x004E, 1, "O4", "rw", None, 0, 1, name="Write output 4"),
    Param(0x0055, 1, "OL", "rw", None, 0, 15, name="Set outputs 1-4 as a group"),
    Param(0x0056, 1, "OT", "rw", None, 0, 15, name="Set outputs 1-4 as a group"),
    Param(0x0057, 2, "P", "rw", 0, INT32_MIN, INT32_MAX, signed=True, name="Position counter"),
    Param(0x0059, 2, "PC", "ro", signed=True, name="Position capture at trip"),
    Param(0x005F, 2, "R1", "rw", 0, INT32_MIN, INT32_MAX, signed=True, name="User register 1"),
    Param(0x0061, 2, "R2", "rw", 0, INT32_MIN, INT32_MAX, signed=True, name="User register 2"),
    Param(0x0063, 2, "R3", "rw", 0, INT32_MIN, INT32_MAX, signed=True, name="User register 3"),
    Param(0x0065, 2, "R4", "rw", 0, INT32_MIN, INT32_MAX, signed=True, name="User register 4"),
    Param(0x0067, 1, "RC", "rw", 25, 1, 100, name="Run current"),
    Param(0x0076, 1, "S", "wo", None, 0, 65535, name="Save"),
    Param(0x0078, 2, "SL", "wo", None, -5000000, 5000000, signed=True, name="Slew axis"),
    Param(0x007D, 1, "TE", "rw", 0, allowed=(0, 16), name="Trip enable"),
    Param(0x0085, 2, "V", "ro", signed=True, name="Read axis velocity"),
    Param(0x0088, 1, "VC", "ro", name="Velocity is changing"),
    Param(0x0089, 2, "VI", "rw", 1000, 1, 4999999, name="Set initial velocity"),
    Param(0x008B, 2, "VM", "rw", 768000, 2, 5000000, name="Set maximum velocity"),
    # 5.1 Hybrid specific registers
    Param(0x008E, 1, "AS", "rw", 2, 0, 3, name="Set hybrid mode"),
    Param(0x008F, 1, "AF", "ro", name="Read hybrid status"),
    Param(0x0090, 1, "CA", "rw", 1, 0, 1, name="Calibration mode"),
    Param(0x0091, 1, "CB", "rw", 1, 0, 3, name="Set control bounds"),
    Param(0x0092, 1, "CC", "rw", 100, 1, 100, name="Set calibration current"),
    Param(0x0093, 1, "CF", "wo", None, 0, 65535, name="Clear locked rotor"),
    Param(0x0094, 1, "CT", "rw", 200, 2, 65535, name="Calibration time"),
    Param(0x0095, 2, "LD", "rw", 102400, 0, INT32_MAX, name="Lead limits"),
    Param(0x0097, 2, "LG", "rw", 102400, 0, INT32_MAX, name="Lag limits"),
    Param(0x0099, 2, "LL", "ro", signed=True, name="Position lead/lag"),
    Param(0x009B, 1, "LR", "ro", name="Locked rotor"),
    Param(0x009C, 2, "LT", "rw", 2000, 2, 65535, name="Locked rotor timeout"),
    Param(0x009E, 2, "MF", "rw", 768000, 306, 5000000, name="Make up frequency"),
    Param(0x00A0, 1, "MU", "rw", 0, 0, 2, name="Make up"),
    Param(0x00A1, 1, "SC", "wo", None, 0, 65535, name="Start calibration"),
    Param(0x00A2, 1, "SS", "rw", 0, 0, 255, name="Set system speed"),
    Param(0x00A5, 1, "TD", "rw", 1, 0, 1, name="Torque direction"),
    Param(0x00A6, 1, "TQ", "rw", 25, 1, 100, name="Set torque"),
    Param(0x00A7, 1, "TS", "rw", 0, 0, 255, name="Set torque speed"),
]
BY_NAME = {p.mcode: p for p in PARAMS}
ADDR_MAP = {}
for _p in PARAMS:
    for _i in range(_p.nregs):
        ADDR_MAP[_p.addr + _i] = (_p, _i)

# S1..S4 I/O functions (lines 740-759)
IN_FUNCS = {0: "General purpose", 1: "Homing", 2: "Limit +", 3: "Limit -", 5: "Soft stop",
            7: "Jog +", 8: "Jog -", 11: "Reset"}
OUT_FUNCS = {16: "General purpose", 17: "Moving", 18: "Fault", 20: "Velocity changing",
             21: "Locked rotor", 23: "Moving to position", 24: "Hybrid circuitry active",
             25: "Make-up active"}
CLOCK_FUNCS = {33: "Step/direction in", 34: "Quadrature in", 35: "Up/down in",
               49: "Step/direction out", 50: "Quadrature out", 51: "Up/down out"}

MFG_RW = ("S1", "S2", "S3", "S4", "S7", "S8", "CR", "S5", "S13", "TR", "MU")
MFG_RO_CMDS = ("E", "EX", "PS", "RS")
MFG_MAXLEN = {"S1": 7, "S2": 7, "S3": 7, "S4": 7, "S7": 5, "S8": 5, "CR": 6, "S5": 5, "S13": 5,
              "TR": 11, "MU": 4}


def mnemonic_bytes(m):
    return m[::-1].rjust(4).encode("ascii")


MNEMONICS = {mnemonic_bytes(m): m for m in MFG_RW + MFG_RO_CMDS}

DEVICE_ID = {
    0: b"SEM USA",
    1: b"MDMEHSD23A4-EQ",
    2: b"4.0.0.0",
    3: b"www.imshome.com",
    4: b"MDrive Ethernet",
    5: b"0510200147",
    6: b"ASI 4.0.0.2",
}


class Drive:
    def __init__(self):
        self.v = {p.mcode: p.default for p in PARAMS
                  if p.access == "rw" and p.default is not None and p.mcode not in ("ER", "P")}
        # I/O configuration (line 1263: general purpose inputs, active low, sinking)
        self.io = {i: [0, 0, 0] for i in (1, 2, 3, 4)}
        self.out_latch = {1: 0, 2: 0, 3: 0, 4: 0}
        self.input_active = {1: 0, 2: 0, 3: 0, 4: 0}   # physical inputs: nothing wired on the bench
        self.clock = {7: [33, 0], 8: [33, 0]}
        self.cr = "1.000"
        self.s5 = [9, 0]
        self.s13 = [60, 0]
        self.tr = [0, 0, 0]
        self.mu_param = 0
        self.analog = 0
        self.pc = 0
        # --- the not-ready state (DECISIONS.md section 2) ---
        self.lr = 1
        self.er = ERR_LOCKED_ROTOR
        self.ll = 410
        self.cal_complete = True
        self.cal_until = None
        # motion
        self.pos = 0.0
        self.moving = False
        self.mode = None          # 'pos' or 'slew'
        self.target = 0
        self.vel = 0.0            # signed steps/s
        self.slew_v = 0
        self.vel_changing = False
        # program (program memory is empty on this bench unit)
        self.program_state = "none"
        self.nvm = self.settings_snapshot()
        self.counters = {"bus_messages": 0, "exception_responses": 0, "dropped_frames": 0,
                         "connections_accepted": 0}

    # ----------------------------------------------------------------- derived state
    def bridge_on(self):
        return self.v["DE"] == 1 and not self.lr

    def calibrating(self):
        return self.cal_until is not None

    def af(self):
        b = 0
        if self.lr:
            b |= 8
        if self.bridge_on() and self.v["AS"] != 0 and not self.calibrating():
            b |= 16
        if self.ll == 0:
            b |= 64
        if self.cal_complete and not self.calibrating():
            b |= 128
        return b

    def ef(self):
        return 1 if (self.lr or self.er != 0) else 0

    def velocity(self):
        if self.v["AS"] == 3:
            return 0
        return int(round(self.vel))

    def out_state(self, i):
        f = self.io[i][0]
        if f < 16:
            return 0
        if f == 16:
            return self.out_latch[i]
        return {17: int(self.moving), 18: self.ef(), 20: int(self.vel_changing),
                21: self.lr, 23: int(self.moving and self.mode == "pos"),
                24: 1 if self.af() & 16 else 0, 25: 0}.get(f, 0)

    def in_state(self, i):
        if self.io[i][0] >= 16:
            return self.out_state(i)
        return self.input_active[i]

    def read_param(self, p):
        m = p.mcode
        if m in self.v:
            return self.v[m]
        if m == "EF":
            return self.ef()
        if m == "ER":
            return self.er
        if m in ("I1", "I2", "I3", "I4"):
            return self.in_state(int(m[1]))
        if m == "I5":
            return self.analog
        if m in ("IL", "IN"):
            return sum(self.in_state(i) << (i - 1) for i in (1, 2, 3, 4))
        if m == "MP":
            return int(self.moving and self.mode == "pos")
        if m == "MV":
            return int(self.moving)
        if m in ("O1", "O2", "O3", "O4"):
            return self.out_state(int(m[1]))
        if m in ("OL", "OT"):
            return sum(self.out_state(i) << (i - 1) for i in (1, 2, 3, 4))
        if m == "P":
            return int(round(self.pos))
        if m == "PC":
            return self.pc
        if m == "V":
            return self.velocity()
        if m == "VC":
            return int(self.vel_changing)
        if m == "AF":
            return self.af()
        if m == "LL":
            return self.ll
        if m == "LR":
            return self.lr
        return 0

    def settings_snapshot(self):
        return {"registers": dict(self.v), "io": {str(k): list(v) for k, v in self.io.items()},
                "clock_io": {str(k): list(v) for k, v in self.clock.items()}, "CR": self.cr,
                "S5": list(self.s5), "S13": list(self.s13), "TR": list(self.tr),
                "MU_param": self.mu_param}

    # ----------------------------------------------------------------- calibration / motion
    def start_calibration(self):
        self.cal_until = time.monotonic() + self.v["CT"] / 1000.0
        self.cal_complete = False

    def stop_motion_now(self):
        self.moving = False
        self.mode = None
        self.vel = 0.0
        self.vel_changing = False

    def tick(self, dt):
        now = time.monotonic()
        if self.cal_until is not None and now >= self.cal_until:
            self.cal_until = None
            self.cal_complete = True
            self.ll = 0
        if not self.moving:
            return
        if not self.bridge_on():
            self.stop_motion_now()
            return
        acc, dec = float(self.v["A"]), float(self.v["D"])
        vi, vm = float(self.v["VI"]), float(self.v["VM"])
        old = int(round(self.pos))
        if self.mode == "pos":
            rem = self.target - self.pos
            if rem == 0:
                self.stop_motion_now()
                return
            d = 1.0 if rem > 0 else -1.0
            sp = max(abs(self.vel), vi)
            stop_dist = (sp * sp - vi * vi) / (2 * dec) if sp > vi else 0.0
            if abs(rem) <= stop_dist + sp * dt:
                nsp = max(vi, sp - dec * dt)
            elif sp < vm:
                nsp = min(vm, sp + acc * dt)
            else:
                nsp = min(sp, vm) if sp <= vm else max(vm, sp - dec * dt)
            self.vel_changing = nsp != sp
            step = nsp * dt
            if step >= abs(rem):
                self.pos = float(self.target)
                self.stop_motion_now()
            else:
                self.pos += d * step
                self.vel = d * nsp
        else:  # slew
            tv = float(self.slew_v)
            cur = self.vel
            if cur == 0.0:
                if tv == 0.0:
                    self.stop_motion_now()
                    return
                cur = vi if tv > 0 else -vi
            sgn = 1.0 if cur > 0 else -1.0
            mag = abs(cur)
            if tv == 0.0 or (tv > 0) != (cur > 0):
                mag -= dec * dt
                if mag <= vi:
                    if tv == 0.0:
                        nv = 0.0
                    else:
                        nv = vi if tv > 0 else -vi
                else:
                    nv = sgn * mag
            elif mag > abs(tv):
                nv = sgn * max(abs(tv), mag - dec * dt)
            elif mag < abs(tv):
                nv = sgn * min(abs(tv), mag + acc * dt)
            else:
                nv = cur
            self.vel_changing = nv != self.vel
            self.vel = nv
            self.pos += nv * dt
            if self.pos > INT32_MAX:
                self.pos -= 2 ** 32
            elif self.pos < INT32_MIN:
                self.pos += 2 ** 32
            if nv == 0.0:
                self.stop_motion_now()
        delta = int(round(self.pos)) - old
        for c in ("C1", "C2"):
            x = self.v[c] + delta
            self.v[c] = ((x - INT32_MIN) % 2 ** 32) + INT32_MIN

    def motion_refusal(self):
        if not self.bridge_on() or self.calibrating():
            raise MbError(DEVICE_FAILURE)

    # ----------------------------------------------------------------- Modbus functions
    def fc_read_bits(self, pdu, base):
        if len(pdu) != 5:
            raise MbError(ILLEGAL_VALUE)
        start, qty = struct.unpack(">HH", pdu[1:5])
        if not 1 <= qty <= 4:
            raise MbError(ILLEGAL_VALUE)
        if start < base or start + qty - 1 > base + 3:
            raise MbError(ILLEGAL_ADDRESS)
        bits = 0
        for k in range(qty):
            i = start - base + 1 + k
            s = self.in_state(i) if base == 0x2D else self.out_state(i)
            bits |= s << k
        return bytes([pdu[0], 1, bits])

    def fc_write_coil(self, pdu):
        if len(pdu) != 5:
            raise MbError(ILLEGAL_VALUE)
        addr, val = struct.unpack(">HH", pdu[1:5])
        if val not in (0x0000, 0xFF00):
            raise MbError(ILLEGAL_VALUE)
        if not 0x4B <= addr <= 0x4E:
            raise MbError(ILLEGAL_ADDRESS)
        i = addr - 0x4A
        if self.io[i][0] != 16:
            raise MbError(DEVICE_FAILURE)
        self.out_latch[i] = 1 if val else 0
        return bytes(pdu)

    def fc_read_holding(self, pdu):
        if len(pdu) != 5:
            raise MbError(ILLEGAL_VALUE)
        start, qty = struct.unpack(">HH", pdu[1:5])
        if not 1 <= qty <= 4:
            raise MbError(ILLEGAL_VALUE)
        words = []
        cache = {}
        for a in range(start, start + qty):
            ent = ADDR_MAP.get(a)
            if ent is None or ent[0].access == "wo":
                raise MbError(ILLEGAL_ADDRESS)
        for a in range(start, start + qty):
            p, off = ADDR_MAP[a]
            if p.mcode not in cache:
                cache[p.mcode] = self.read_param(p)
            val = cache[p.mcode]
            if p.nregs == 2:
                u = val & 0xFFFFFFFF
                words.append((u >> 16) if off == 0 else (u & 0xFFFF))
            else:
                words.append(val & 0xFFFF)
        if "ER" in cache and not self.lr:
            self.er = 0      # line 1047: "must be read or set to 0 to clear"
        return bytes([3, 2 * qty]) + b"".join(struct.pack(">H", w) for w in words)

    def fc_write_multiple(self, pdu):
        if len(pdu) < 6:
            raise MbError(ILLEGAL_VALUE)
        start, qty, bc = struct.unpack(">HHB", pdu[1:6])
        if not 1 <= qty <= 4 or bc != 2 * qty or len(pdu) != 6 + bc:
            raise MbError(ILLEGAL_VALUE)
        regs = struct.unpack(">%dH" % qty, pdu[6:6 + bc])
        # address / access / alignment
        items = []
        a = start
        k = 0
        while k < qty:
            ent = ADDR_MAP.get(a)
            if ent is None:
                raise MbError(ILLEGAL_ADDRESS)
            p, off = ent
            if p.access == "ro" or off != 0 or k + p.nregs > qty:
                raise MbError(ILLEGAL_ADDRESS)
            if p.nregs == 2:
                raw = (regs[k] << 16) | regs[k + 1]
                val = raw - (1 << 32) if (p.signed and raw & 0x80000000) else raw
            else:
                raw = regs[k]
                val = raw
            items.append((p, val))
            a += p.nregs
            k += p.nregs
        # value ranges
        for p, val in items:
            if not p.check(val):
                raise MbError(ILLEGAL_VALUE)
        newv = dict(self.v)
        for p, val in items:
            if p.access == "rw" and p.mcode in newv:
                newv[p.mcode] = val
        if newv["VI"] >= newv["VM"]:
            raise MbError(ILLEGAL_VALUE)
        if newv["HT"] == 1 or newv["HT"] + newv["MT"] > 65535:
            raise MbError(ILLEGAL_VALUE)
        # state-dependent refusals (checked for all before anything is applied)
        for p, val in items:
            m = p.mcode
            if m in ("MA", "MR"):
                self.motion_refusal()
                if self.moving:
                    raise MbError(DEVICE_FAILURE)
                if m == "MR":
                    t = int(round(self.pos)) + val
                    if not INT32_MIN <= t <= INT32_MAX:
                        raise MbError(ILLEGAL_VALUE)
            elif m == "SL":
                self.motion_refusal()
                if self.moving and self.mode == "pos":
                    raise MbError(DEVICE_FAILURE)
            elif m == "SC":
                if not self.bridge_on() or self.moving:
                    raise MbError(DEVICE_FAILURE)
            elif m in ("P", "MS", "S") and self.moving:
                raise MbError(DEVICE_FAILURE)
            elif m in ("O1", "O2", "O3", "O4") and self.io[int(m[1])][0] != 16:
                raise MbError(DEVICE_FAILURE)
            elif m in ("IC", "DC"):
                r = "R%d" % val
                nv = self.v[r] + (1 if m == "IC" else -1)
                if not INT32_MIN <= nv <= INT32_MAX:
                    raise MbError(DEVICE_FAILURE)
        for p, val in items:
            self.apply_write(p.mcode, val)
        return bytes([0x10]) + struct.pack(">HH", start, qty)

    def apply_write(self, m, val):
        if m in ("O1", "O2", "O3", "O4"):
            self.out_latch[int(m[1])] = val
            return
        if m in ("OL", "OT"):
            for i in (1, 2, 3, 4):
                if self.io[i][0] == 16:
                    self.out_latch[i] = (val >> (i - 1)) & 1
            return
        if m == "ER":
            if not self.lr:
                self.er = 0
            return
        if m == "P":
            self.pos = float(val)
            return
        if m in ("IC", "DC"):
            r = "R%d" % val
            self.v[r] += 1 if m == "IC" else -1
            return
        if m == "MA" or m == "MR":
            t = val if m == "MA" else int(round(self.pos)) + val
            if t != int(round(self.pos)):
                self.target = t
                self.mode = "pos"
                self.moving = True
                self.vel = 0.0
            return
        if m == "SL":
            if val == 0 and not self.moving:
                return
            self.slew_v = val
            self.mode = "slew"
            self.moving = True
            return
        if m == "S":
            self.nvm = self.settings_snapshot()
            return
        if m == "CF":
            if self.lr:
                self.lr = 0
                if self.v["DE"] == 1:
                    self.start_calibration()
            return
        if m == "SC":
            self.start_calibration()
            return
        old = self.v.get(m)
        self.v[m] = val
        if m == "DE":
            if old == 0 and val == 1 and not self.lr:
                self.start_calibration()        # line 1134: bridge re-enabled
            if val == 0:
                self.stop_motion_now()
        elif m == "AS" and old == 0 and val != 0 and self.bridge_on():
            self.start_calibration()            # line 1134: hybrid enabled
        elif m == "MS" and old != val and self.bridge_on() and self.v["AS"] != 0:
            self.start_calibration()            # line 1134: microstep resolution changed

    # ----------------------------------------------------------------- manufacturer functions
    def mfg_read_string(self, m):
        if m in ("S1", "S2", "S3", "S4"):
            return ", ".join(str(x) for x in self.io[int(m[1])])
        if m in ("S7", "S8"):
            return ", ".join(str(x) for x in self.clock[int(m[1])])
        if m == "CR":
            return self.cr
        if m == "S5":
            return ", ".join(str(x) for x in self.s5)
        if m == "S13":
            return ", ".join(str(x) for x in self.s13)
        if m == "TR":
            return ", ".join(str(x) for x in self.tr)
        if m == "MU":
            return "%d, %d" % (self.v["MU"], self.mu_param)
        return ""

    def fc_mfg_read(self, pdu):
        if len(pdu) < 5:
            raise MbError(ILLEGAL_VALUE)
        m = MNEMONICS.get(bytes(pdu[1:5]))
        if m is None:
            raise MbError(ILLEGAL_ADDRESS)
        rest = bytes(pdu[5:])
        if m == "EX":
            if len(rest) >= 2 and rest[0] == len(rest) - 1:
                rest = rest[1:]
            if not 1 <= len(rest) <= 4 or not rest.isalnum():
                raise MbError(ILLEGAL_VALUE)
            # program memory is empty on this unit: no such label / address
            raise MbError(DEVICE_FAILURE)
        if rest:
            raise MbError(ILLEGAL_VALUE)
        if m == "E":
            self.program_state = "none"
            return bytes([0x41, 0])
        if m in ("PS", "RS"):
            raise MbError(DEVICE_FAILURE)   # no program running
        s = self.mfg_read_string(m).encode("ascii")
        return bytes([0x41, len(s)]) + s

    @staticmethod
    def parse_ints(s, n):
        if not s.startswith("="):
            raise MbError(ILLEGAL_VALUE)
        parts = [x.strip() for x in s[1:].split(",")]
        if len(parts) != n:
            raise MbError(ILLEGAL_VALUE)
        out = []
        for x in parts:
            if not x or not (x.isdigit() or (x[0] in "+-" and x[1:].isdigit())):
                raise MbError(ILLEGAL_VALUE)
            out.append(int(x))
        return out

    def fc_mfg_write(self, pdu):
        if len(pdu) < 6:
            raise MbError(ILLEGAL_VALUE)
        bc = pdu[5]
        if not 1 <= bc <= 28 or len(pdu) != 6 + bc:
            raise MbError(ILLEGAL_VALUE)
        m = MNEMONICS.get(bytes(pdu[1:5]))
        if m is None or m in MFG_RO_CMDS:
            raise MbError(ILLEGAL_ADDRESS)
        data = bytes(pdu[6:6 + bc])
        try:
            s = data.decode("ascii")
        except UnicodeDecodeError:
            raise MbError(ILLEGAL_VALUE)
        if len(data) > MFG_MAXLEN[m]:
            raise MbError(ILLEGAL_VALUE)
        if m in ("S1", "S2", "S3", "S4"):
            i = int(m[1])
            a, b, c = self.parse_ints(s, 3)
            if (a not in IN_FUNCS and a not in OUT_FUNCS) or b not in (0, 1) or c not in (0, 1):
                raise MbError(ILLEGAL_VALUE)
            if a not in (0, 16):
                for j in (1, 2, 3, 4):
                    if j != i and self.io[j][0] == a:
                        raise MbError(ILLEGAL_VALUE)   # function already assigned to another point
            self.io[i] = [a, b, c]
            if a != 16:
                self.out_latch[i] = 0
        elif m in ("S7", "S8"):
            a, b = self.parse_ints(s, 2)
            if a not in CLOCK_FUNCS or b not in (0, 1):
                raise MbError(ILLEGAL_VALUE)
            self.clock[int(m[1])] = [a, b]
        elif m == "CR":
            if not s.startswith("="):
                raise MbError(ILLEGAL_VALUE)
            t = s[1:].strip()
            try:
                if not t or t[0] in "+-" or t.count(".") > 1 or not t.replace(".", "").isdigit():
                    raise ValueError
                f = float(t)
            except ValueError:
                raise MbError(ILLEGAL_VALUE)
            if f <= 0 or ("." in t and len(t.split(".")[1]) > 3):
                raise MbError(ILLEGAL_VALUE)
            self.cr = "%.3f" % f
        elif m == "S5":
            a, b = self.parse_ints(s, 2)
            if a not in (9, 10) or b not in (0, 1):
                raise MbError(ILLEGAL_VALUE)
            self.s5 = [a, b]
        elif m == "S13":
            a, b = self.parse_ints(s, 2)
            if a not in (60, 61) or b not in (0, 1):
                raise MbError(ILLEGAL_VALUE)
            self.s13 = [a, b]
        elif m == "TR":
            n = s.count(",") + 1
            if n > 3:
                raise MbError(ILLEGAL_VALUE)
            vals = self.parse_ints(s, n)
            if not INT32_MIN <= vals[0] <= INT32_MAX or any(not 0 <= x <= 65535 for x in vals[1:]):
                raise MbError(ILLEGAL_VALUE)
            self.tr = vals + [0] * (3 - n)
        elif m == "MU":
            a, b = self.parse_ints(s, 2)
            if a not in (0, 1, 2) or b not in (0, 1):
                raise MbError(ILLEGAL_VALUE)
            self.v["MU"] = a
            self.mu_param = b
        return bytes([0x42, bc]) + bytes(pdu[1:5])

    def fc_device_id(self, pdu):
        if len(pdu) < 2:
            raise MbError(ILLEGAL_VALUE)
        if pdu[1] != 0x0E:
            raise MbError(ILLEGAL_FUNCTION)
        if len(pdu) != 4:
            raise MbError(ILLEGAL_VALUE)
        code, oid = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise MbError(ILLEGAL_VALUE)
        if code == 4:
            if oid not in DEVICE_ID:
                raise MbError(ILLEGAL_ADDRESS)
            ids = [oid]
        else:
            last = 2 if code == 1 else 6
            if oid > last:
                oid = 0
            ids = list(range(oid, last + 1))
        body = b"".join(bytes([i, len(DEVICE_ID[i])]) + DEVICE_ID[i] for i in ids)
        return bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)]) + body

    def handle_pdu(self, pdu):
        fc = pdu[0]
        try:
            if fc == 0x01:
                return self.fc_read_bits(pdu, 0x4B)
            if fc == 0x02:
                return self.fc_read_bits(pdu, 0x2D)
            if fc == 0x03:
                return self.fc_read_holding(pdu)
            if fc == 0x05:
                return self.fc_write_coil(pdu)
            if fc == 0x10:
                return self.fc_write_multiple(pdu)
            if fc == 0x41:
                return self.fc_mfg_read(pdu)
            if fc == 0x42:
                return self.fc_mfg_write(pdu)
            if fc == 0x2B:
                return self.fc_device_id(pdu)
            raise MbError(ILLEGAL_FUNCTION)
        except MbError as e:
            code = e.code
        except Exception:          # never let one frame kill the server
            code = DEVICE_FAILURE
        self.counters["exception_responses"] += 1
        return bytes([(fc | 0x80) & 0xFF, code])

    # ----------------------------------------------------------------- dump
    def dump(self):
        regs = {}
        for p in PARAMS:
            if p.access == "wo":
                continue
            regs["0x%04X" % p.addr] = {"mcode": p.mcode, "name": p.name, "access": p.access,
                                        "registers": p.nregs, "value": self.read_param(p)}
        return {
            "device": {"model": "MDrive 23 Hybrid Motion Control, Ethernet (MODBUS/TCP)",
                       "unit_ids": list(UNIT_IDS),
                       "device_identification": {str(k): v.decode() for k, v in DEVICE_ID.items()}},
            "registers": regs,
            "status": {"EF_error_flag": self.ef(), "ER_error_code": self.er,
                       "LR_locked_rotor": self.lr, "AF_hybrid_status": self.af(),
                       "LL_lead_lag": self.ll, "bridge_enabled": int(self.bridge_on()),
                       "calibrating": int(self.calibrating()),
                       "calibration_complete": int(self.cal_complete),
                       "moving": int(self.moving), "moving_to_position": int(self.moving and self.mode == "pos"),
                       "velocity": self.velocity(), "velocity_changing": int(self.vel_changing),
                       "motion_target": self.target if self.mode == "pos" else None,
                       "slew_velocity": self.slew_v if self.mode == "slew" else 0,
                       "program_state": self.program_state},
            "coils_outputs_0x004B_0x004E": {"0x%04X" % (0x4A + i): self.out_state(i) for i in (1, 2, 3, 4)},
            "output_latches": {str(i): self.out_latch[i] for i in (1, 2, 3, 4)},
            "discrete_inputs_0x002D_0x0030": {"0x%04X" % (0x2C + i): self.in_state(i) for i in (1, 2, 3, 4)},
            "manufacturer_functions": {m: self.mfg_read_string(m) for m in MFG_RW},
            "nvm": self.nvm,
            "diagnostic_counters": dict(self.counters),
        }


class Server:
    def __init__(self, drive, state_file):
        self.drive = drive
        self.state_file = state_file
        self.stop = None

    def write_state(self):
        if not self.state_file:
            return
        try:
            tmp = self.state_file + ".tmp"
            with open(tmp, "w") as f:
                json.dump(self.drive.dump(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except Exception as e:   # pragma: no cover
            print("state dump failed: %s" % e, file=sys.stderr)

    async def client(self, reader, writer):
        d = self.drive
        d.counters["connections_accepted"] += 1
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid, proto, length, unit = struct.unpack(">HHHB", hdr)
                if length == 0 or length > 254:
                    # cannot resynchronise on a stream with a bogus length: drop the connection
                    d.counters["dropped_frames"] += 1
                    break
                pdu = await reader.readexactly(length - 1)
                if proto != 0 or unit not in UNIT_IDS or not pdu:
                    d.counters["dropped_frames"] += 1
                    continue
                d.counters["bus_messages"] += 1
                resp = d.handle_pdu(pdu)
                writer.write(struct.pack(">HHHB", tid, 0, len(resp) + 1, unit) + resp)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            try:
                writer.close()
            except Exception:
                pass

    async def motion_loop(self):
        last = time.monotonic()
        while True:
            await asyncio.sleep(0.01)
            now = time.monotonic()
            try:
                self.drive.tick(now - last)
            except Exception as e:   # pragma: no cover
                print("tick error: %s" % e, file=sys.stderr)
            last = now

    async def main(self, host, port):
        loop = asyncio.get_running_loop()
        self.stop = asyncio.Event()
        loop.add_signal_handler(signal.SIGUSR1, self.write_state)
        loop.add_signal_handler(signal.SIGTERM, self.stop.set)
        loop.add_signal_handler(signal.SIGINT, self.stop.set)
        srv = await asyncio.start_server(self.client, host, port)
        mt = asyncio.create_task(self.motion_loop())
        p = srv.sockets[0].getsockname()[1]
        sys.stdout.write("listening tcp %s:%d\n" % (host, p))
        sys.stdout.flush()
        await self.stop.wait()
        srv.close()
        mt.cancel()
        self.write_state()


def main():
    ap = argparse.ArgumentParser(description="MDrive Hybrid MODBUS/TCP simulator")
    ap.add_argument("--listen", required=True, help="127.0.0.1:PORT")
    ap.add_argument("--state", default=None, help="JSON state dump file")
    a = ap.parse_args()
    host, _, port = a.listen.rpartition(":")
    if host not in ("127.0.0.1", "localhost", "::1", "[::1]"):
        ap.error("only loopback addresses are allowed")
    host = host.strip("[]")
    srv = Server(Drive(), a.state)
    try:
        asyncio.run(srv.main(host, int(port)))
    except KeyboardInterrupt:
        srv.write_state()


if __name__ == "__main__":
    main()
