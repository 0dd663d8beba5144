#!/usr/bin/env python3
"""MDrive Hybrid / MDrive Plus2 Motion Control with Ethernet -- MODBUS/TCP simulator.

Written from the IMS / Schneider Electric Motion USA "MODBUS/TCP Fieldbus manual,
MDrive Motion Control Products" (rev R040611) and the public MODBUS specifications.
Standard library only.  See DECISIONS.md for every place where the manual is
silent or wrong and what this implementation does there.

    python3 sim.py --listen 127.0.0.1:0 [--state FILE] [--model hybrid|plus2]
"""

import argparse
import asyncio
import json
import os
import re
import signal
import struct
import sys
import time

# --------------------------------------------------------------------------
# Exception codes (the manual lists exactly these four, section 4)
# --------------------------------------------------------------------------
ILLEGAL_FUNCTION = 0x01
ILLEGAL_ADDRESS = 0x02
ILLEGAL_VALUE = 0x03
DEVICE_FAILURE = 0x04


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


S32_MIN, S32_MAX = -2147483648, 2147483647

# Microstep resolutions allowed for register 0x0048 (MS), manual line 1082.
MS_VALUES = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250,
             256, 180, 108, 127)

ENCODER_COUNTS_PER_REV = 4000        # simulated internal encoder (C2), see DECISIONS
FULL_STEPS_PER_REV = 200


class Item:
    """One entry of the register map (section 5)."""

    __slots__ = ("addr", "words", "mn", "access", "signed", "lo", "hi",
                 "allowed", "default", "model", "persist")

    def __init__(self, addr, words, mn, access, lo=None, hi=None, default=None,
                 signed=False, allowed=None, model=None, persist=False):
        self.addr = addr
        self.words = words
        self.mn = mn
        self.access = access          # 'rw', 'ro', 'wo'
        self.signed = signed
        self.lo = lo
        self.hi = hi
        self.allowed = allowed
        self.default = default
        self.model = model            # None = both, 'hybrid', 'plus2'
        self.persist = persist        # saved to NVM by the S command


def build_map():
    S = True
    it = [
        Item(0x0000, 2, "A", "rw", 91, 1525878997, 1000000, persist=True),
        Item(0x0005, 2, "C1", "rw", S32_MIN, S32_MAX, 0, signed=S),
        Item(0x0007, 2, "C2", "rw", S32_MIN, S32_MAX, 0, signed=S),
        Item(0x0009, 1, "CE", "rw", 0, 1, 1, persist=True),
        Item(0x000B, 1, "CM", "rw", 0, 1, 0, model="plus2", persist=True),
        Item(0x000F, 1, "D1", "rw", 0, 255, 0, persist=True),
        Item(0x0010, 1, "D2", "rw", 0, 255, 0, persist=True),
        Item(0x0011, 1, "D3", "rw", 0, 255, 0, persist=True),
        Item(0x0012, 1, "D4", "rw", 0, 255, 0, persist=True),
        Item(0x0013, 1, "D5", "rw", 0, 255, 0, persist=True),
        Item(0x0018, 2, "D", "rw", 91, 1525878997, 1000000, persist=True),
        Item(0x001A, 1, "DB", "rw", 0, 65000, 10, model="plus2", persist=True),
        Item(0x001B, 1, "DC", "wo"),
        Item(0x001C, 1, "DE", "rw", 0, 1, 1, persist=True),
        Item(0x001E, 1, "EE", "rw", 0, 1, 0, persist=True),
        Item(0x001F, 1, "EF", "ro"),
        Item(0x0021, 1, "ER", "rw", 0, 0, 0),
        Item(0x0029, 1, "HC", "rw", 0, 100, 5, persist=True),
        Item(0x002B, 1, "HM", "rw", 1, 4, 1, persist=True),
        Item(0x002C, 1, "HT", "rw", 0, 65535, 500, persist=True),
        Item(0x002D, 1, "I1", "ro"),
        Item(0x002E, 1, "I2", "ro"),
        Item(0x002F, 1, "I3", "ro"),
        Item(0x0030, 1, "I4", "ro"),
        Item(0x0031, 1, "I5", "ro"),
        Item(0x0032, 1, "I6", "ro", model="plus2"),
        Item(0x0037, 1, "IC", "wo"),
        Item(0x003A, 1, "IL", "ro"),
        Item(0x003B, 1, "IN", "ro"),
        Item(0x003F, 1, "JE", "rw", 0, 1, 0, persist=True),
        Item(0x0042, 1, "LM", "rw", 1, 6, 1, persist=True),
        Item(0x0043, 2, "MA", "wo", S32_MIN, S32_MAX, signed=S),
        Item(0x0045, 1, "MP", "ro"),
        Item(0x0046, 2, "MR", "wo", S32_MIN, S32_MAX, signed=S),
        Item(0x0048, 1, "MS", "rw", default=256, allowed=MS_VALUES, persist=True),
        Item(0x0049, 1, "MT", "rw", 0, 65000, 0, persist=True),
        Item(0x004A, 1, "MV", "ro"),
        Item(0x004B, 1, "O1", "rw", 0, 1),
        Item(0x004C, 1, "O2", "rw", 0, 1),
        Item(0x004D, 1, "O3", "rw", 0, 1),
        Item(0x004E, 1, "O4", "rw", 0, 1),
        Item(0x0055, 1, "OL", "rw", 0, 15),
        Item(0x0056, 1, "OT", "rw", 0, 15),
        Item(0x0057, 2, "P", "rw", S32_MIN, S32_MAX, 0, signed=S),
        Item(0x0059, 2, "PC", "ro", signed=S),
        Item(0x005C, 1, "PM", "rw", 0, 1, 0, model="plus2", persist=True),
        Item(0x005F, 2, "R1", "rw", S32_MIN, S32_MAX, 0, signed=S, persist=True),
        Item(0x0061, 2, "R2", "rw", S32_MIN, S32_MAX, 0, signed=S, persist=True),
        Item(0x0063, 2, "R3", "rw", S32_MIN, S32_MAX, 0, signed=S, persist=True),
        Item(0x0065, 2, "R4", "rw", S32_MIN, S32_MAX, 0, signed=S, persist=True),
        Item(0x0067, 1, "RC", "rw", 1, 100, 25, persist=True),
        Item(0x0076, 1, "S", "wo"),
        Item(0x0077, 1, "SF", "rw", 0, 65000, 15, model="plus2", persist=True),
        Item(0x0078, 2, "SL", "wo", -5000000, 5000000, signed=S),
        Item(0x007A, 1, "SM", "rw", 0, 1, 0, model="plus2", persist=True),
        Item(0x007B, 1, "ST", "rw", 0, 0, 0, model="plus2"),
        Item(0x007D, 1, "TE", "rw", default=0, allowed=(0, 16)),
        Item(0x0085, 2, "V", "ro", signed=S),
        Item(0x0088, 1, "VC", "ro"),
        Item(0x0089, 2, "VI", "rw", 1, 4999999, 1000, persist=True),
        Item(0x008B, 2, "VM", "rw", 2, 5000000, 768000, persist=True),
        # 5.1 Hybrid specific registers
        Item(0x008E, 1, "AS", "rw", 0, 3, 2, model="hybrid", persist=True),
        Item(0x008F, 1, "AF", "ro", model="hybrid"),
        Item(0x0090, 1, "CA", "rw", 0, 1, 1, model="hybrid", persist=True),
        Item(0x0091, 1, "CB", "rw", 0, 3, 1, model="hybrid", persist=True),
        Item(0x0092, 1, "CC", "rw", 1, 100, 100, model="hybrid", persist=True),
        Item(0x0093, 1, "CF", "wo", model="hybrid"),
        Item(0x0094, 1, "CT", "rw", 2, 65535, 200, model="hybrid", persist=True),
        Item(0x0095, 2, "LD", "rw", 0, 2147483647, 102400, model="hybrid", persist=True),
        Item(0x0097, 2, "LG", "rw", 0, 2147483647, 102400, model="hybrid", persist=True),
        Item(0x0099, 2, "LL", "ro", signed=S, model="hybrid"),
        Item(0x009B, 1, "LR", "ro", model="hybrid"),
        Item(0x009C, 2, "LT", "rw", 2, 65535, 2000, model="hybrid", persist=True),
        Item(0x009E, 2, "MF", "rw", 306, 5000000, 768000, model="hybrid", persist=True),
        Item(0x00A0, 1, "MU", "rw", 0, 2, 0, model="hybrid", persist=True),
        Item(0x00A1, 1, "SC", "wo", model="hybrid"),
        Item(0x00A2, 1, "SS", "rw", 0, 255, 0, model="hybrid", persist=True),
        Item(0x00A5, 1, "TD", "rw", 0, 1, 1, model="hybrid", persist=True),
        Item(0x00A6, 1, "TQ", "rw", 1, 100, 25, model="hybrid", persist=True),
        Item(0x00A7, 1, "TS", "rw", 0, 255, 0, model="hybrid", persist=True),
    ]
    # 5.2 User variable registers V1..V8
    for i in range(8):
        it.append(Item(0x00A8 + 2 * i, 2, "V%d" % (i + 1), "rw", S32_MIN, S32_MAX, 0,
                       signed=S))
    return it


# 32-bit signed variables that DC / IC may address (value written = Modbus start address)
INCDEC_TARGETS = ("C1", "C2", "P", "R1", "R2", "R3", "R4",
                  "V1", "V2", "V3", "V4", "V5", "V6", "V7", "V8")

# I/O point functions (section 4.3.1)
IN_FUNCS = (0, 1, 2, 3, 5, 7, 8, 11)
OUT_FUNCS_COMMON = (16, 17, 18, 20, 21, 23)
OUT_FUNCS_HYBRID = (24, 25)
CLOCK_FUNCS = (33, 34, 35, 49, 50, 51)

AF_LEAD = 1
AF_LAG = 2
AF_LEADLAG = 4
AF_LOCKED = 8
AF_ACTIVE = 16
AF_HWFAULT = 32
AF_ZERO = 64
AF_CALDONE = 128


def wrap32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


class Drive:
    def __init__(self, model):
        self.model = model
        self.hybrid = model == "hybrid"
        self.items = [i for i in build_map() if i.model in (None, model)]
        self.by_mn = {i.mn: i for i in self.items}
        self.word_map = {}                   # word address -> (item, offset)
        for i in self.items:
            for k in range(i.words):
                self.word_map[i.addr + k] = (i, k)
        # stored values of settings / variables
        self.val = {}
        for i in self.items:
            if i.access != "wo" and i.default is not None:
                self.val[i.mn] = i.default
        for mn in ("P", "C1", "C2", "ST", "PC"):
            self.val.pop(mn, None)             # live values, kept elsewhere
        self.val["ER"] = 0
        # manufacturer specific settings (strings of ints stored as tuples)
        self.mfg = {
            "S1": [0, 0, 0], "S2": [0, 0, 0], "S3": [0, 0, 0], "S4": [0, 0, 0],
            "S7": [33, 0], "S8": [33, 0],
            "S5": [9, 0],
            "S13": [60, 0],
            "CR": 1000,              # clock ratio in thousandths
            "TR": 0,
        }
        self.mu_param = 0            # MU second parameter (0 use / 1 clear lead/lag)
        self.out_latch = [0, 0, 0, 0]
        self.in_state = [0, 0, 0, 0]  # nothing wired to the simulated inputs
        self.analog_counts = 0
        self.pc = 0
        self.ef = 0
        self.stall = 0
        self.lead_lag = 0
        self.locked_rotor = 0
        self.trip_ref = 0
        self.tripped = 0
        # motion
        self.pos = 0.0               # steps, float
        self.c1 = 0.0
        self.c2 = 0.0
        self.vel = 0.0               # signed steps/s
        self.mode = "idle"           # idle | move | slew
        self.target = 0
        self.slew_v = 0.0
        self.last_t = time.monotonic()
        # hybrid calibration
        self.cal_until = 0.0
        # program (MCode/TCP) execution state
        self.program = {"running": False, "paused": False, "label": None}
        self.nvm = self.persistent_image()

    # ------------------------------------------------------------------
    # persistence
    # ------------------------------------------------------------------
    def persistent_image(self):
        img = {i.mn: self.val[i.mn] for i in self.items if i.persist}
        img["mfg"] = json.loads(json.dumps(self.mfg))
        if self.hybrid:
            img["mfg"]["MU"] = [self.val["MU"], self.mu_param]
        return img

    # ------------------------------------------------------------------
    # simulation
    # ------------------------------------------------------------------
    def calibrating(self, now=None):
        return self.hybrid and (now or time.monotonic()) < self.cal_until

    def start_calibration(self):
        if self.hybrid and self.val["AS"] != 0:
            self.cal_until = time.monotonic() + self.val["CT"] / 1000.0

    def tick(self, now=None):
        now = time.monotonic() if now is None else now
        elapsed = now - self.last_t
        self.last_t = now
        if self.mode == "idle" or elapsed <= 0:
            return
        elapsed = min(elapsed, 120.0)
        t = 0.0
        while t < elapsed and self.mode != "idle":
            dt = min(0.001, elapsed - t)
            t += dt
            self._step(dt)

    def _step(self, dt):
        vi = float(self.val["VI"])
        acc = float(self.val["A"])
        dec = float(self.val["D"])
        old = self.pos
        if self.mode == "move":
            rem = self.target - self.pos
            d = 1.0 if rem >= 0 else -1.0
            sp = abs(self.vel)
            if sp < vi:
                sp = vi
            stop = (sp * sp - vi * vi) / (2.0 * dec) if sp > vi else 0.0
            if abs(rem) <= stop + sp * dt:
                sp = max(vi, sp - dec * dt)
            else:
                sp = min(float(self.val["VM"]), sp + acc * dt)
            step = sp * dt
            if step >= abs(rem):
                self.pos = float(self.target)
                self.vel = 0.0
                self.mode = "idle"
            else:
                self.pos += d * step
                self.vel = d * sp
        elif self.mode == "slew":
            tv = self.slew_v
            v = self.vel
            if v == 0.0 and tv != 0.0:
                v = (1.0 if tv > 0 else -1.0) * min(vi, abs(tv))
            if tv == 0.0 or (v != 0.0 and (tv > 0) != (v > 0)):
                # decelerating to stop (SL=0 or direction reversal)
                sp = abs(v) - dec * dt
                if sp <= vi:
                    if tv == 0.0:
                        v = 0.0
                        self.mode = "idle"
                    else:
                        v = (1.0 if tv > 0 else -1.0) * min(vi, abs(tv))
                else:
                    v = (1.0 if v > 0 else -1.0) * sp
            else:
                sp = abs(v)
                if sp < abs(tv):
                    sp = min(abs(tv), sp + acc * dt)
                elif sp > abs(tv):
                    sp = max(abs(tv), sp - dec * dt)
                v = (1.0 if tv > 0 else -1.0) * sp
            self.vel = v
            self.pos += v * dt
        delta = self.pos - old
        if delta:
            self.c1 += delta
            self.c2 += delta * ENCODER_COUNTS_PER_REV / (FULL_STEPS_PER_REV * self.val["MS"])
            # keep position counter inside 32 bits (wraps like the real counter)
            if self.pos > S32_MAX or self.pos < S32_MIN:
                w = wrap32(int(self.pos))
                self.target += w - int(self.pos)
                self.pos = float(w) + (self.pos - int(self.pos))
            if abs(self.c1) > 2 ** 31:
                self.c1 = float(wrap32(int(self.c1)))
            if abs(self.c2) > 2 ** 31:
                self.c2 = float(wrap32(int(self.c2)))
            self._check_trip()

    def _check_trip(self):
        if not (self.val["TE"] & 16):
            return
        dist = self.mfg["TR"]
        if dist == 0:
            return
        moved = int(round(self.pos)) - self.trip_ref
        if (dist > 0 and moved >= dist) or (dist < 0 and moved <= dist):
            self.val["TE"] &= ~16
            self.tripped = 1

    def ramping(self):
        if self.mode == "idle":
            return 0
        if self.mode == "slew":
            return 1 if abs(abs(self.vel) - abs(self.slew_v)) > 0.5 else 0
        return 1 if abs(abs(self.vel) - self.val["VM"]) > 0.5 else 0

    # ------------------------------------------------------------------
    # I/O
    # ------------------------------------------------------------------
    def point_is_input(self, n):
        return self.mfg["S%d" % (n + 1)][0] < 16

    def output_state(self, n):
        f = self.mfg["S%d" % (n + 1)][0]
        if f < 16:
            return 0
        if f == 16:
            return self.out_latch[n]
        if f == 17:
            return 1 if self.mode != "idle" else 0
        if f == 18:
            return self.ef
        if f == 20:
            return self.ramping()
        if f == 21:
            return self.locked_rotor
        if f == 23:
            return 1 if self.mode == "move" else 0
        if f == 24:
            return 1 if self.af() & AF_ACTIVE else 0
        if f == 25:
            return 1 if (self.val.get("MU", 0) and self.lead_lag) else 0
        return 0

    def input_state(self, n):
        # logic state of the line: configured inputs read the (unwired) input,
        # points configured as outputs read back the output they drive
        if self.point_is_input(n):
            return self.in_state[n]
        return self.output_state(n)

    def inputs_bcd(self):
        return sum(self.input_state(n) << n for n in range(4))

    def outputs_bcd(self):
        return sum(self.output_state(n) << n for n in range(4))

    def af(self):
        if not self.hybrid:
            return 0
        v = 0
        if self.val["AS"] != 0 and self.val["DE"] and not self.locked_rotor:
            v |= AF_ACTIVE
        if self.locked_rotor:
            v |= AF_LOCKED
        if self.lead_lag == 0:
            v |= AF_ZERO
        if not self.calibrating():
            v |= AF_CALDONE
        return v

    # ------------------------------------------------------------------
    # register read
    # ------------------------------------------------------------------
    def get(self, mn, side_effects=True):
        if mn in self.val and mn != "ER":
            return self.val[mn]
        if mn == "P":
            return wrap32(int(round(self.pos)))
        if mn == "C1":
            return wrap32(int(round(self.c1)))
        if mn == "C2":
            return wrap32(int(round(self.c2)))
        if mn == "ER":
            v = self.val["ER"]
            if side_effects and v:
                # manual line 1047: must be read or set to 0 to clear
                self.val["ER"] = 0
                self.ef = 0
            return v
        if mn == "EF":
            return self.ef
        if mn in ("I1", "I2", "I3", "I4"):
            return self.input_state(int(mn[1]) - 1)
        if mn == "I5":
            return self.analog_counts
        if mn == "I6":
            return 0
        if mn in ("IL", "IN"):
            return self.inputs_bcd()
        if mn == "MP":
            return 1 if self.mode == "move" else 0
        if mn == "MV":
            return 1 if self.mode != "idle" else 0
        if mn in ("O1", "O2", "O3", "O4"):
            return self.output_state(int(mn[1]) - 1)
        if mn in ("OL", "OT"):
            return self.outputs_bcd()
        if mn == "PC":
            return self.pc
        if mn == "ST":
            return self.stall
        if mn == "V":
            if self.hybrid and self.val["AS"] == 3:
                return 0
            return int(round(self.vel))
        if mn == "VC":
            return self.ramping()
        if mn == "AF":
            return self.af()
        if mn == "LL":
            return self.lead_lag
        if mn == "LR":
            return self.locked_rotor
        raise KeyError(mn)

    # ------------------------------------------------------------------
    # register write -- validate() raises, apply() performs
    # ------------------------------------------------------------------
    def validate(self, item, v, pending):
        """v is the decoded value; pending = dict of other values in the same request."""
        mn = item.mn
        if item.allowed is not None:
            if v not in item.allowed:
                raise ModbusError(ILLEGAL_VALUE)
        elif item.lo is not None and not (item.lo <= v <= item.hi):
            raise ModbusError(ILLEGAL_VALUE)
        if mn == "HT":
            if v == 1:
                raise ModbusError(ILLEGAL_VALUE)
            if v + pending.get("MT", self.val["MT"]) > 65535:
                raise ModbusError(ILLEGAL_VALUE)
        elif mn == "MT":
            if pending.get("HT", self.val["HT"]) + v > 65535:
                raise ModbusError(ILLEGAL_VALUE)
        elif mn == "VI":
            if v >= pending.get("VM", self.val["VM"]):
                raise ModbusError(ILLEGAL_VALUE)
        elif mn == "VM":
            if v <= pending.get("VI", self.val["VI"]):
                raise ModbusError(ILLEGAL_VALUE)
        elif mn in ("DC", "IC"):
            tgt = self.word_map.get(v)
            if tgt is None or tgt[1] != 0 or tgt[0].mn not in INCDEC_TARGETS:
                raise ModbusError(ILLEGAL_VALUE)
            if tgt[0].mn == "P" and self.mode != "idle":
                raise ModbusError(DEVICE_FAILURE)
        elif mn in ("O1", "O2", "O3", "O4"):
            n = int(mn[1]) - 1
            if self.mfg["S%d" % (n + 1)][0] != 16:
                raise ModbusError(DEVICE_FAILURE)
        elif mn in ("P", "MS"):
            if self.mode != "idle":
                raise ModbusError(DEVICE_FAILURE)
        elif mn in ("MA", "MR"):
            self.check_can_move()
            if self.mode != "idle":
                raise ModbusError(DEVICE_FAILURE)
        elif mn == "SL":
            if v != 0:
                self.check_can_move()
            if self.mode == "move":
                raise ModbusError(DEVICE_FAILURE)

    def check_can_move(self):
        if not self.val["DE"]:
            raise ModbusError(DEVICE_FAILURE)
        if self.hybrid and (self.locked_rotor or self.calibrating()):
            raise ModbusError(DEVICE_FAILURE)

    def apply(self, item, v):
        mn = item.mn
        if mn == "P":
            self.pos = float(v)
            self.target = v
        elif mn == "C1":
            self.c1 = float(v)
        elif mn == "C2":
            self.c2 = float(v)
        elif mn == "ER":
            self.val["ER"] = 0
            self.ef = 0
        elif mn == "ST":
            self.stall = 0
        elif mn in ("O1", "O2", "O3", "O4"):
            self.out_latch[int(mn[1]) - 1] = v
        elif mn in ("OL", "OT"):
            for n in range(4):
                if self.mfg["S%d" % (n + 1)][0] == 16:
                    self.out_latch[n] = (v >> n) & 1
        elif mn == "MA":
            self.start_move(v)
        elif mn == "MR":
            self.start_move(wrap32(int(round(self.pos)) + v))
        elif mn == "SL":
            if v == 0 and self.mode == "idle":
                return
            self.slew_v = float(v)
            self.mode = "slew"
        elif mn in ("DC", "IC"):
            tgt = self.word_map[v][0].mn
            d = -1 if mn == "DC" else 1
            if tgt == "P":
                self.pos = float(wrap32(self.get("P") + d))
                self.target = int(self.pos)
            elif tgt == "C1":
                self.c1 = float(wrap32(self.get("C1") + d))
            elif tgt == "C2":
                self.c2 = float(wrap32(self.get("C2") + d))
            else:
                self.val[tgt] = wrap32(self.val[tgt] + d)
        elif mn == "S":
            self.nvm = self.persistent_image()
        elif mn == "TE":
            old = self.val["TE"]
            self.val["TE"] = v
            if v & 16:
                self.trip_ref = self.get("P")
                self.tripped = 0
            elif old & 16:
                self.tripped = 0
        elif mn == "MS":
            old = self.val["MS"]
            self.val["MS"] = v
            if v != old:
                self.start_calibration()
        elif mn == "DE":
            old = self.val["DE"]
            self.val["DE"] = v
            if v == 0 and self.mode != "idle":
                # bridge disabled: motion stops immediately
                self.mode = "idle"
                self.vel = 0.0
                self.target = int(round(self.pos))
            if v == 1 and old == 0:
                self.start_calibration()
        elif mn == "AS":
            old = self.val["AS"]
            self.val["AS"] = v
            if old == 0 and v != 0:
                self.start_calibration()
        elif mn == "CF":
            self.locked_rotor = 0
            self.start_calibration()
        elif mn == "SC":
            self.start_calibration()
        else:
            self.val[mn] = v

    def start_move(self, target):
        self.target = target
        if target == int(round(self.pos)):
            self.pos = float(target)
            return
        self.vel = 0.0
        self.mode = "move"

    # ------------------------------------------------------------------
    # manufacturer specific (FC 65 / 66)
    # ------------------------------------------------------------------
    def mfg_names(self):
        names = ["S1", "S2", "S3", "S4", "S7", "S8", "CR", "S5", "S13", "TR",
                 "E", "EX", "PS", "RS"]
        if self.hybrid:
            names.append("MU")
        return names

    def mfg_read_string(self, mn):
        if mn in ("S1", "S2", "S3", "S4", "S7", "S8", "S5", "S13"):
            return ", ".join(str(x) for x in self.mfg[mn])
        if mn == "CR":
            r = self.mfg["CR"]
            return "%d.%03d" % (r // 1000, r % 1000)
        if mn == "TR":
            armed = 1 if self.val["TE"] & 16 else 0
            return "%d, %d, %d" % (self.mfg["TR"], armed, self.tripped)
        if mn == "MU":
            return "%d, %d" % (self.val["MU"], self.mu_param)
        raise KeyError(mn)

    def mfg_execute(self, mn, param):
        """E / EX / PS / RS.  param: bytes (only EX takes one)."""
        if mn == "EX":
            s = param.decode("ascii", "replace").strip()
            if not re.fullmatch(r"[A-Z][A-Z0-9]|[0-9]{1,4}", s):
                raise ModbusError(ILLEGAL_VALUE)
            # no MCode program is stored in the simulated device's memory
            raise ModbusError(DEVICE_FAILURE)
        if param:
            raise ModbusError(ILLEGAL_VALUE)
        if mn == "E":
            self.program.update(running=False, paused=False, label=None)
        elif mn == "PS":
            if self.program["running"]:
                self.program["paused"] = True
        elif mn == "RS":
            if self.program["running"]:
                self.program["paused"] = False

    def mfg_write(self, mn, data):
        s = data.decode("ascii", "replace")
        if mn in ("E", "EX", "PS", "RS"):
            self.mfg_execute(mn, data)
            return
        if not s.startswith("="):
            raise ModbusError(ILLEGAL_VALUE)
        body = s[1:]
        if mn == "CR":
            m = re.fullmatch(r"\s*([0-9]{1,3})(?:\.([0-9]{0,3}))?\s*", body)
            if not m:
                raise ModbusError(ILLEGAL_VALUE)
            frac = (m.group(2) or "").ljust(3, "0")
            r = int(m.group(1)) * 1000 + int(frac)
            if r <= 0:
                raise ModbusError(ILLEGAL_VALUE)
            self.mfg["CR"] = r
            return
        if mn == "TR":
            m = re.fullmatch(r"\s*([+-]?[0-9]{1,10})\s*", body)
            if not m:
                raise ModbusError(ILLEGAL_VALUE)
            v = int(m.group(1))
            if not S32_MIN <= v <= S32_MAX:
                raise ModbusError(ILLEGAL_VALUE)
            self.mfg["TR"] = v
            return
        parts = body.split(",")
        try:
            vals = [int(p.strip()) for p in parts]
        except ValueError:
            raise ModbusError(ILLEGAL_VALUE)
        if any(not re.fullmatch(r"\s*[0-9]{1,2}\s*", p) for p in parts):
            raise ModbusError(ILLEGAL_VALUE)
        if mn in ("S1", "S2", "S3", "S4"):
            allowed = IN_FUNCS + OUT_FUNCS_COMMON + (OUT_FUNCS_HYBRID if self.hybrid else ())
            if len(vals) != 3 or vals[0] not in allowed or vals[1] not in (0, 1) \
                    or vals[2] not in (0, 1):
                raise ModbusError(ILLEGAL_VALUE)
            n = int(mn[1]) - 1
            self.mfg[mn] = vals
            if vals[0] != 16:
                self.out_latch[n] = 0
        elif mn in ("S7", "S8"):
            if len(vals) != 2 or vals[0] not in CLOCK_FUNCS or vals[1] not in (0, 1):
                raise ModbusError(ILLEGAL_VALUE)
            self.mfg[mn] = vals
        elif mn == "S5":
            if len(vals) != 2 or vals[0] not in (9, 10) or vals[1] not in (0, 1):
                raise ModbusError(ILLEGAL_VALUE)
            self.mfg[mn] = vals
        elif mn == "S13":
            if len(vals) != 2 or vals[0] not in (60, 61) or vals[1] not in (0, 1):
                raise ModbusError(ILLEGAL_VALUE)
            self.mfg[mn] = vals
        elif mn == "MU":
            if len(vals) != 2 or vals[0] not in (0, 1, 2) or vals[1] not in (0, 1):
                raise ModbusError(ILLEGAL_VALUE)
            self.val["MU"] = vals[0]
            self.mu_param = vals[1]
            if vals[1] == 1:
                self.lead_lag = 0
        else:
            raise ModbusError(ILLEGAL_ADDRESS)

    # ------------------------------------------------------------------
    # state dump
    # ------------------------------------------------------------------
    def state(self, counters):
        self.tick()
        regs = {}
        for i in self.items:
            entry = {"mcode": i.mn, "words": i.words, "access": i.access}
            entry["value"] = None if i.access == "wo" else self.get(i.mn, side_effects=False)
            regs["0x%04X" % i.addr] = entry
        return {
            "device": "MDrive Hybrid" if self.hybrid else "MDrive Plus2",
            "model": self.model,
            "holding_registers": regs,
            "coils": {"0x%04X" % (0x004B + n): self.output_state(n) for n in range(4)},
            "discrete_inputs": {"0x%04X" % (0x002D + n): self.input_state(n) for n in range(4)},
            "output_latches": list(self.out_latch),
            "manufacturer_functions": {m: self.mfg_read_string(m) for m in self.mfg_names()
                                       if m not in ("E", "EX", "PS", "RS")},
            "program": dict(self.program),
            "motion": {"mode": self.mode, "target": self.target,
                       "slew_velocity": self.slew_v, "velocity": self.vel,
                       "trip_reference": self.trip_ref, "tripped": self.tripped},
            "hybrid": ({"calibrating": self.calibrating(), "locked_rotor": self.locked_rotor,
                        "lead_lag": self.lead_lag} if self.hybrid else None),
            "nvm": self.nvm,
            "diagnostic_counters": dict(counters),
        }


# --------------------------------------------------------------------------
# Modbus application layer
# --------------------------------------------------------------------------
VENDOR = b"SEM USA"
URL = b"www.imshome.com"
PRODUCT_NAME = b"MDrive Ethernet"
FIRMWARE = b"4.0.0.0"
APP_NAME = b"ASI 4.0.0.0"
PART_NUMBERS = {"hybrid": b"MAI3CRL23C4-EQ", "plus2": b"MDI3PRL23C4-EQ"}
SERIALS = {"hybrid": b"0410A0312", "plus2": b"0410B0207"}


class Server:
    def __init__(self, model):
        self.drive = Drive(model)
        self.counters = {"connections_accepted": 0, "connections_open": 0,
                         "frames_received": 0, "responses_sent": 0,
                         "exceptions_sent": 0, "frames_discarded": 0,
                         "connections_closed_bad_header": 0, "internal_errors": 0}
        self.devid = {
            0: VENDOR,
            1: PART_NUMBERS[model],
            2: FIRMWARE,
            3: URL,
            4: PRODUCT_NAME,
            5: SERIALS[model],
            6: APP_NAME,
        }

    # ---------------- register helpers ----------------
    def _resolve_range(self, start, qty):
        """Return list of items exactly covered by [start, start+qty)."""
        dm = self.drive.word_map
        items = []
        a = start
        end = start + qty
        while a < end:
            ent = dm.get(a)
            if ent is None:
                raise ModbusError(ILLEGAL_ADDRESS)
            item, off = ent
            if off != 0 or a + item.words > end:
                raise ModbusError(ILLEGAL_ADDRESS)     # split multi-word item
            items.append(item)
            a += item.words
        return items

    def fc_read_holding(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        start, qty = struct.unpack(">HH", pdu[1:5])
        if not 1 <= qty <= 4:
            raise ModbusError(ILLEGAL_VALUE)
        items = self._resolve_range(start, qty)
        for it in items:
            if it.access == "wo":
                raise ModbusError(ILLEGAL_ADDRESS)
        out = b""
        for it in items:
            v = self.drive.get(it.mn)
            if it.words == 2:
                out += struct.pack(">I", v & 0xFFFFFFFF)
            else:
                out += struct.pack(">H", v & 0xFFFF)
        return bytes([0x03, len(out)]) + out

    def fc_write_multiple(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(ILLEGAL_VALUE)
        start, qty, bc = struct.unpack(">HHB", pdu[1:6])
        if not 1 <= qty <= 4 or bc != 2 * qty or len(pdu) != 6 + bc:
            raise ModbusError(ILLEGAL_VALUE)
        items = self._resolve_range(start, qty)
        for it in items:
            if it.access == "ro":
                raise ModbusError(ILLEGAL_ADDRESS)
        data = pdu[6:]
        vals = []
        off = 0
        for it in items:
            if it.words == 2:
                raw = struct.unpack(">I", data[off:off + 4])[0]
                v = wrap32(raw) if it.signed else raw
            else:
                v = struct.unpack(">H", data[off:off + 2])[0]
            off += 2 * it.words
            vals.append(v)
        pending = {it.mn: v for it, v in zip(items, vals)}
        # motion commands in the same request as other items: validate each
        for it, v in zip(items, vals):
            self.drive.validate(it, v, pending)
        for it, v in zip(items, vals):
            self.drive.apply(it, v)
        return struct.pack(">BHH", 0x10, start, qty)

    def fc_read_bits(self, pdu, fc):
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        start, qty = struct.unpack(">HH", pdu[1:5])
        if not 1 <= qty <= 4:
            raise ModbusError(ILLEGAL_VALUE)
        base = 0x002D if fc == 0x02 else 0x004B
        if start < base or start + qty > base + 4:
            raise ModbusError(ILLEGAL_ADDRESS)
        bits = 0
        for k in range(qty):
            n = start - base + k
            s = self.drive.input_state(n) if fc == 0x02 else self.drive.output_state(n)
            bits |= s << k
        return bytes([fc, 1, bits])

    def fc_write_coil(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        addr, value = struct.unpack(">HH", pdu[1:5])
        if value not in (0x0000, 0xFF00):
            raise ModbusError(ILLEGAL_VALUE)
        if not 0x004B <= addr <= 0x004E:
            raise ModbusError(ILLEGAL_ADDRESS)
        item = self.drive.by_mn["O%d" % (addr - 0x004B + 1)]
        v = 1 if value == 0xFF00 else 0
        self.drive.validate(item, v, {})
        self.drive.apply(item, v)
        return bytes(pdu)

    def fc_device_id(self, pdu):
        if len(pdu) < 2:
            raise ModbusError(ILLEGAL_VALUE)
        if pdu[1] != 0x0E:
            raise ModbusError(ILLEGAL_FUNCTION)
        if len(pdu) != 4:
            raise ModbusError(ILLEGAL_VALUE)
        code, oid = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise ModbusError(ILLEGAL_VALUE)
        if code == 4:
            if oid not in self.devid:
                raise ModbusError(ILLEGAL_ADDRESS)
            objs = [oid]
        else:
            last = 2 if code == 1 else 6
            if oid > last or oid not in self.devid:
                oid = 0
            objs = list(range(oid, last + 1))
        body = b""
        for o in objs:
            v = self.devid[o]
            body += bytes([o, len(v)]) + v
        return bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(objs)]) + body

    @staticmethod
    def _mnemonic(raw):
        """4 request bytes (ASCII, reversed, space padded) -> mnemonic or None."""
        s = bytes(reversed(raw))
        try:
            txt = s.decode("ascii")
        except UnicodeDecodeError:
            return None
        name = txt.rstrip(" ")
        if not name or " " in name:
            return None
        return name

    def fc_mfg_read(self, pdu):
        d = self.drive
        if len(pdu) < 5:
            raise ModbusError(ILLEGAL_VALUE)
        mn = self._mnemonic(pdu[1:5])
        if mn not in d.mfg_names():
            raise ModbusError(ILLEGAL_ADDRESS)
        if mn == "EX":
            # EX carries the label: byte count + label, same layout as FC 66
            if len(pdu) < 6 or pdu[5] < 1 or pdu[5] > 4 or len(pdu) != 6 + pdu[5]:
                raise ModbusError(ILLEGAL_VALUE)
            d.mfg_execute("EX", bytes(pdu[6:]))
            return bytes([0x41, 0])
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        if mn in ("E", "PS", "RS"):
            d.mfg_execute(mn, b"")
            return bytes([0x41, 0])
        s = d.mfg_read_string(mn).encode("ascii")
        return bytes([0x41, len(s)]) + s

    def fc_mfg_write(self, pdu):
        d = self.drive
        if len(pdu) < 6:
            raise ModbusError(ILLEGAL_VALUE)
        mn = self._mnemonic(pdu[1:5])
        bc = pdu[5]
        if bc > 28 or len(pdu) != 6 + bc:
            raise ModbusError(ILLEGAL_VALUE)
        if mn not in d.mfg_names():
            raise ModbusError(ILLEGAL_ADDRESS)
        if bc == 0 and mn not in ("E", "PS", "RS"):
            raise ModbusError(ILLEGAL_VALUE)
        d.mfg_write(mn, bytes(pdu[6:]))
        return bytes([0x42, bc]) + bytes(pdu[1:5])

    def handle_pdu(self, pdu):
        fc = pdu[0]
        self.drive.tick()
        try:
            if fc == 0x01 or fc == 0x02:
                return self.fc_read_bits(pdu, fc)
            if fc == 0x03:
                return self.fc_read_holding(pdu)
            if fc == 0x05:
                return self.fc_write_coil(pdu)
            if fc == 0x10:
                return self.fc_write_multiple(pdu)
            if fc == 0x2B:
                return self.fc_device_id(pdu)
            if fc == 0x41:
                return self.fc_mfg_read(pdu)
            if fc == 0x42:
                return self.fc_mfg_write(pdu)
            raise ModbusError(ILLEGAL_FUNCTION)
        except ModbusError as e:
            self.counters["exceptions_sent"] += 1
            return bytes([(fc | 0x80) & 0xFF, e.code])
        except Exception:                                  # never let one frame kill us
            self.counters["exceptions_sent"] += 1
            self.counters["internal_errors"] += 1
            return bytes([(fc | 0x80) & 0xFF, DEVICE_FAILURE])

    # ---------------- transport ----------------
    async def client(self, reader, writer):
        self.counters["connections_accepted"] += 1
        self.counters["connections_open"] += 1
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid, pid, length, uid = struct.unpack(">HHHB", hdr)
                if length < 1 or length > 254:
                    # cannot resynchronise a TCP stream with a bogus length field
                    self.counters["connections_closed_bad_header"] += 1
                    break
                body = await reader.readexactly(length - 1)
                self.counters["frames_received"] += 1
                if pid != 0 or length < 2:
                    self.counters["frames_discarded"] += 1
                    continue
                resp = self.handle_pdu(body)
                writer.write(struct.pack(">HHHB", tid, 0, len(resp) + 1, uid) + resp)
                self.counters["responses_sent"] += 1
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError):
            pass
        finally:
            self.counters["connections_open"] -= 1
            try:
                writer.close()
            except Exception:
                pass

    async def ticker(self):
        while True:
            await asyncio.sleep(0.02)
            try:
                self.drive.tick()
            except Exception:
                pass

    def dump(self, path):
        if not path:
            return
        try:
            st = self.drive.state(self.counters)
            tmp = path + ".tmp"
            with open(tmp, "w") as f:
                json.dump(st, f, indent=1, sort_keys=True)
            os.replace(tmp, path)
        except Exception as e:
            print("state dump failed: %s" % e, file=sys.stderr, flush=True)


async def main_async(args):
    host, _, port = args.listen.rpartition(":")
    host = host.strip("[]")
    if host not in ("127.0.0.1", "localhost", "::1"):
        print("refusing to bind to non-loopback address %s" % host, file=sys.stderr)
        sys.exit(2)
    srv = Server(args.model)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    loop.add_signal_handler(signal.SIGUSR1, lambda: srv.dump(args.state))
    server = await asyncio.start_server(srv.client, host, int(port))
    tick = asyncio.create_task(srv.ticker())
    sock = server.sockets[0].getsockname()
    print("listening tcp %s:%d" % (sock[0], sock[1]), flush=True)
    await stop.wait()
    server.close()
    tick.cancel()
    srv.dump(args.state)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)          # do not wait for / cancel open client connections


def main():
    ap = argparse.ArgumentParser(description="MDrive Hybrid / Plus2 Ethernet MODBUS/TCP simulator")
    ap.add_argument("--listen", default="127.0.0.1:502")
    ap.add_argument("--state", default=None)
    ap.add_argument("--model", choices=("hybrid", "plus2"), default="hybrid")
    args = ap.parse_args()
    asyncio.run(main_async(args))
    os._exit(0)


if __name__ == "__main__":
    main()
