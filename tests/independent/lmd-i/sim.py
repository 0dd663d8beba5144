#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet, closed-loop (hMTechnology) model -- Modbus/TCP server.

Written from LMD-MODBUS-REV-D and the public Modbus specifications only.
Standard library only.  See DECISIONS.md for every interpretation made.
"""
import argparse
import asyncio
import json
import os
import signal
import struct
import sys
import time

# --------------------------------------------------------------------------
# Exception codes (the manual: the drive uses 01..04 only, lines 615-625)
ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3
DEVICE_FAILURE = 4


class MbErr(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


I32_MIN, I32_MAX = -2147483648, 2147483647

# Microstep resolutions, manual lines 2245-2249
MS_VALUES = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)

# --------------------------------------------------------------------------
# Register map (section 5).  name: (address, words, signed, access, lo, hi, default)
#   access: 'rw' parameter, 'ro' status, 'cmd' command (writable, reads back last command),
#           'wo' trigger (reads 0)
REGS = [
    ("A",  0x0000, 2, False, 'rw', 91, 1525878997, 1000000),
    ("BY", 0x0004, 1, False, 'ro', 0, 1, 0),
    ("C1", 0x0005, 2, True,  'rw', I32_MIN, I32_MAX, 0),
    ("C2", 0x0007, 2, True,  'rw', I32_MIN, I32_MAX, 0),
    ("CE", 0x0009, 1, False, 'rw', 0, 1, 1),
    ("CW", 0x000E, 1, False, 'rw', 0, 255, 10),
    ("D1", 0x000F, 1, False, 'rw', 0, 255, 0),
    ("D2", 0x0010, 1, False, 'rw', 0, 255, 0),
    ("D3", 0x0011, 1, False, 'rw', 0, 255, 0),
    ("D4", 0x0012, 1, False, 'rw', 0, 255, 0),
    ("D5", 0x0013, 1, False, 'rw', 0, 255, 0),
    ("D",  0x0018, 2, False, 'rw', 91, 1525878997, 1000000),
    ("DB", 0x001A, 1, False, 'rw', 0, 65000, 10),
    ("DC", 0x001B, 1, False, 'wo', 0, 65535, 0),
    ("DE", 0x001C, 1, False, 'rw', 0, 1, 1),
    ("EE", 0x001E, 1, False, 'rw', 0, 1, 0),
    ("EF", 0x001F, 1, False, 'ro', 0, 1, 0),
    ("ER", 0x0021, 1, False, 'rw', 0, 0, 0),
    ("FC", 0x0024, 1, False, 'rw', 0, 9, 0),
    ("HC", 0x0029, 1, False, 'rw', 0, 100, 5),
    ("HI", 0x002A, 1, False, 'cmd', 1, 4, 0),
    ("HM", 0x002B, 1, False, 'cmd', 1, 4, 0),
    ("HT", 0x002C, 1, False, 'rw', 0, 65535, 500),
    ("I1", 0x002D, 1, False, 'ro', 0, 1, 0),
    ("I2", 0x002E, 1, False, 'ro', 0, 1, 0),
    ("I3", 0x002F, 1, False, 'ro', 0, 1, 0),
    ("I4", 0x0030, 1, False, 'ro', 0, 1, 0),
    ("I5", 0x0031, 1, False, 'ro', 0, 1023, 0),
    ("I6", 0x0032, 1, False, 'ro', 0, 1, 0),
    ("IC", 0x0037, 1, False, 'wo', 0, 65535, 0),
    ("IN", 0x003B, 1, False, 'ro', 0, 15, 0),
    ("IP", 0x003C, 1, False, 'wo', 0, 1, 0),
    ("JE", 0x003F, 1, False, 'rw', 0, 1, 0),
    ("LM", 0x0042, 1, False, 'rw', 1, 6, 1),
    ("MA", 0x0043, 2, True,  'cmd', I32_MIN, I32_MAX, 0),
    ("MP", 0x0045, 1, False, 'ro', 0, 1, 0),
    ("MR", 0x0046, 2, True,  'cmd', I32_MIN, I32_MAX, 0),
    ("MS", 0x0048, 1, False, 'rw', 1, 256, 256),
    ("MT", 0x0049, 1, False, 'rw', 0, 65000, 0),
    ("MV", 0x004A, 1, False, 'ro', 0, 1, 0),
    ("O1", 0x004B, 1, False, 'rw', 0, 1, 0),
    ("O2", 0x004C, 1, False, 'rw', 0, 1, 0),
    ("O3", 0x004D, 1, False, 'rw', 0, 1, 0),
    ("OF", 0x004E, 1, False, 'ro', 0, 1, 0),
    ("OT", 0x0056, 1, False, 'rw', 0, 15, 0),
    ("P",  0x0057, 2, True,  'rw', I32_MIN, I32_MAX, 0),
    ("PC", 0x0059, 2, True,  'ro', I32_MIN, I32_MAX, 0),
    ("PM", 0x005C, 1, False, 'rw', 0, 1, 0),
    ("R1", 0x005F, 2, True,  'rw', I32_MIN, I32_MAX, 0),
    ("R2", 0x0061, 2, True,  'rw', I32_MIN, I32_MAX, 0),
    ("R3", 0x0063, 2, True,  'rw', I32_MIN, I32_MAX, 0),
    ("R4", 0x0065, 2, True,  'rw', I32_MIN, I32_MAX, 0),
    ("RC", 0x0067, 1, False, 'rw', 1, 100, 25),
    ("S",  0x0076, 1, False, 'wo', 0, 1, 0),
    ("SF", 0x0077, 1, False, 'rw', 0, 65000, 15),
    ("SL", 0x0078, 2, True,  'cmd', -5000000, 5000000, 0),
    ("SM", 0x007A, 1, False, 'rw', 0, 1, 0),
    ("ST", 0x007B, 1, False, 'ro', 0, 1, 0),
    ("TE", 0x007D, 1, False, 'rw', 0, 43, 0),
    ("V",  0x0085, 2, True,  'ro', I32_MIN, I32_MAX, 0),
    ("VC", 0x0088, 1, False, 'ro', 0, 1, 0),
    ("VI", 0x0089, 2, False, 'rw', 1, 2560000 - 1, 1000),
    ("VM", 0x008B, 2, False, 'rw', 2, 2560000, 768000),
    ("WT", 0x008D, 1, False, 'rw', 0, 84, 80),
    # 5.1 hMTechnology (closed loop)
    ("AS", 0x008E, 1, False, 'rw', 0, 3, 2),
    ("AF", 0x008F, 1, False, 'ro', 0, 255, 0),
    ("CB", 0x0091, 1, False, 'rw', 0, 3, 1),
    ("CF", 0x0093, 1, False, 'wo', 0, 1, 0),
    ("LD", 0x0095, 2, False, 'rw', 0, I32_MAX, 102400),
    ("LG", 0x0097, 2, False, 'rw', 0, I32_MAX, 102400),
    ("LL", 0x0099, 2, True,  'ro', -I32_MAX, I32_MAX, 0),
    ("LR", 0x009B, 1, False, 'ro', 0, 1, 0),
    ("LT", 0x009C, 2, False, 'rw', 2, 65535, 2000),
    ("MF", 0x009E, 2, False, 'rw', 306, 2560000, 768000),
    ("MU", 0x00A0, 1, False, 'rw', 0, 2, 0),
    ("SC", 0x00A1, 1, False, 'wo', 0, 1, 0),
    ("TS", 0x00A3, 2, False, 'rw', 0, 255, 0),
    ("TD", 0x00A5, 1, False, 'rw', 0, 1, 1),
    ("TQ", 0x00A6, 1, False, 'rw', 1, 100, 25),
    ("VF", 0x00A7, 1, False, 'rw', 0, 1000, 0),
    # 5.2 user variables
    ("V1", 0x00A8, 2, True, 'rw', I32_MIN, I32_MAX, 0),
    ("V2", 0x00AA, 2, True, 'rw', I32_MIN, I32_MAX, 0),
    ("V3", 0x00AC, 2, True, 'rw', I32_MIN, I32_MAX, 0),
    ("V4", 0x00AE, 2, True, 'rw', I32_MIN, I32_MAX, 0),
    ("V5", 0x00B0, 2, True, 'rw', I32_MIN, I32_MAX, 0),
    ("V6", 0x00B2, 2, True, 'rw', I32_MIN, I32_MAX, 0),
    ("V7", 0x00B4, 2, True, 'rw', I32_MIN, I32_MAX, 0),
    ("V8", 0x00B6, 2, True, 'rw', I32_MIN, I32_MAX, 0),
]
REG = {r[0]: r for r in REGS}
ADDR = {}            # address -> (name, word index within item)
for _r in REGS:
    for _i in range(_r[2]):
        ADDR[_r[1] + _i] = (_r[0], _i)

# Parameters restored by IP (initialize parameters) and saved by S (save)
PARAM_NAMES = [r[0] for r in REGS if r[4] == 'rw' and r[0] not in
               ("C1", "C2", "P", "O1", "O2", "O3", "OT", "ER")]
USER_VARS = ("V1", "V2", "V3", "V4", "V5", "V6", "V7", "V8")

# Input functions (4.4.6) and output functions (4.4.9)
IN_FUNCS = (0, 1, 2, 3, 5, 7, 8, 11, 12)
OUT_FUNCS = (16, 17, 18, 20, 21, 23, 24, 25, 28, 29)

ENC_COUNTS_PER_REV = 4000      # 1000-line encoder (EL), quadrature
FULL_STEPS_PER_REV = 200
BRIDGE_TEMP, CPU_TEMP = 38, 35
AUX_V, MAIN_V = 24, 48

DEV_ID = {
    0: b"IMS USA",
    1: b"LMDCE572",
    2: b"4.0.0.0",
    3: b"https://novantaims.com/",
    4: b"LMD Ethernet",
    5: b"269100417",
    6: b"LMDCM 6.004, Hw: 1.0",
}


def mfg_defaults():
    return {
        "AO": 0,
        "IS": {1: [0, 0, 0], 2: [0, 0, 0], 3: [0, 0, 0], 4: [0, 0, 0]},  # line: [func, active, sink]
        "AI": [9, 0],                 # IS line 5: analog mode, range
        "OS": {1: [16, 0], 2: [16, 0], 3: [16, 0]},
        "RD": 0, "AJ": 128, "AT": 0, "BE": 0, "BL": 0, "BM": 0, "DJ": 128, "DT": 0,
        "FS": 0, "FL": 0, "LS": [0, 0, 0], "TR": [0, 0, 0],
    }


class Drive:
    def __init__(self):
        self.p = {r[0]: r[7] for r in REGS}
        self.m = mfg_defaults()
        self.nvm = self._snapshot()
        self.counters = {"requests": 0, "exceptions": 0, "bad_frames": 0, "connections": 0}
        # motion state
        self.mode = None          # None | 'move' | 'slew' | 'home'
        self.pos = 0.0            # precise position (steps)
        self.c1f = 0.0
        self.c2f = 0.0
        self.vel = 0.0            # signed steps/s
        self.target = 0
        self.slew_v = 0
        self.home_t = 0.0
        self.home_dir = 1
        self.accel_state = False
        self.idle_since = time.monotonic()
        self.cal_until = 0.0

    # -------------------------------------------------------------- persistence
    def _snapshot(self):
        snap = {n: self.p[n] for n in PARAM_NAMES if n not in USER_VARS}
        snap["mfg"] = json.loads(json.dumps(self.m))
        return snap

    def save(self):
        self.nvm = self._snapshot()

    def initialize(self):
        for n in PARAM_NAMES:
            self.p[n] = REG[n][7]
        self.m = mfg_defaults()
        self.p["MU"] = 0

    # -------------------------------------------------------------- derived
    def moving(self):
        return self.mode is not None

    def af(self):
        v = 64 if self.p["LL"] == 0 else 0          # at zero
        if self.p["AS"] != 0 and self.p["DE"] == 1:
            v |= 16
        if time.monotonic() >= self.cal_until and self.p["AS"] != 0:
            v |= 128
        if self.p["LR"]:
            v |= 8
        return v

    def attention_conditions(self):
        af = self.af()
        c = 0
        if self.p["EF"]: c |= 1
        if self.p["LR"]: c |= 2
        if af & 1: c |= 4
        if af & 2: c |= 8
        if af & 16: c |= 16
        if time.monotonic() < self.cal_until: c |= 32
        if BRIDGE_TEMP >= 85: c |= 64
        if af & 64: c |= 256
        if (not self.moving()) and self.p["HC"] < self.p["RC"] and \
                time.monotonic() - self.idle_since >= (self.p["HT"] + self.p["MT"]) / 1000.0:
            c |= 512
        if self.p["DE"] == 0: c |= 2048
        if BRIDGE_TEMP >= self.p["WT"]: c |= 4096
        if self.moving(): c |= 16384
        if self.p["ST"]: c |= 32768
        return c

    def output_state(self, line):
        func = self.m["OS"][line][0]
        if func == 16:
            return self.p["O%d" % line]
        if func == 17: return 1 if self.moving() else 0
        if func == 18: return self.p["EF"]
        if func == 20: return self.p["VC"]
        if func == 21: return self.p["LR"]
        if func == 23: return 1 if self.mode == 'move' else 0
        if func == 24: return 1 if self.af() & 16 else 0
        if func == 29: return 1 if (self.m["AO"] & self.attention_conditions()) else 0
        return 0        # make-up active, trip: never in this simulation

    def value(self, name):
        """Current value of an item as a client reads it (no side effects)."""
        if name == "MV": return 1 if self.moving() else 0
        if name == "MP": return 1 if self.mode == 'move' else 0
        if name == "V":
            return 0 if self.p["AS"] == 3 else int(round(self.vel))
        if name == "VC": return 1 if self.accel_state else 0
        if name == "AF": return self.af()
        if name == "EF": return 1 if self.p["ER"] else 0
        if name in ("O1", "O2", "O3"): return self.output_state(int(name[1]))
        if name == "OT":
            return sum(self.output_state(i) << (i - 1) for i in (1, 2, 3))
        if name == "IN":
            return sum(self.p["I%d" % i] << (i - 1) for i in (1, 2, 3, 4))
        if name == "CB" and self.p["AS"] == 3: return 0
        if REG[name][4] == 'wo': return 0
        return self.p[name]

    def words(self, name):
        _, _, nw, signed, _, _, _, _ = REG[name]
        v = self.value(name)
        if nw == 1:
            return [v & 0xFFFF]
        u = v & 0xFFFFFFFF
        return [u & 0xFFFF, u >> 16]          # low word first (manual 4.2.4/4.2.5 examples)

    # -------------------------------------------------------------- writes
    def write(self, name, v):
        """Write a decoded value; raises MbErr on refusal. Enforces the ties."""
        _, _, nw, signed, acc, lo, hi, _ = REG[name]
        if acc == 'ro':
            raise MbErr(ILLEGAL_ADDRESS)
        if name in USER_VARS:
            raise MbErr(DEVICE_FAILURE)
        if not (lo <= v <= hi):
            raise MbErr(ILLEGAL_VALUE)
        p = self.p
        mv = self.moving()
        if name == "VI":
            if v > p["VM"] - 1: raise MbErr(ILLEGAL_VALUE)
        elif name == "VM":
            if v < p["VI"] + 1: raise MbErr(ILLEGAL_VALUE)
        elif name == "HT":
            if v == 1 or v + p["MT"] > 65535: raise MbErr(ILLEGAL_VALUE)
        elif name == "MT":
            if v + p["HT"] > 65535: raise MbErr(ILLEGAL_VALUE)
        elif name == "MS":
            if v not in MS_VALUES: raise MbErr(ILLEGAL_VALUE)
            if mv: raise MbErr(DEVICE_FAILURE)
        elif name == "AS":
            if mv: raise MbErr(DEVICE_FAILURE)
            if v == 3:
                p["CB"] = 0
            if v != 0 and p["AS"] == 0:
                self.cal_until = time.monotonic() + 0.5     # hMT enable -> calibration
        elif name == "CB":
            if p["AS"] == 3 and v != 0: raise MbErr(DEVICE_FAILURE)
        elif name == "PM":
            if v == 1 and p["EE"] == 0: raise MbErr(DEVICE_FAILURE)
        elif name == "EE":
            if v == 0: p["PM"] = 0
        elif name in ("P", "C1", "C2"):
            if mv: raise MbErr(DEVICE_FAILURE)
            if name == "P": self.pos = float(v)
            if name == "C1": self.c1f = float(v)
            if name == "C2": self.c2f = float(v)
        elif name == "DE":
            if v == 0 and mv:
                self._stop_now()
        elif name in ("O1", "O2", "O3"):
            line = int(name[1])
            if self.m["OS"][line][0] != 16: raise MbErr(DEVICE_FAILURE)
        elif name == "OT":
            for line in (1, 2, 3):
                bit = (v >> (line - 1)) & 1
                if self.m["OS"][line][0] != 16 and bit != self.output_state(line):
                    raise MbErr(DEVICE_FAILURE)
            for line in (1, 2, 3):
                if self.m["OS"][line][0] == 16:
                    p["O%d" % line] = (v >> (line - 1)) & 1
            return
        elif name in ("MA", "MR"):
            self._check_motion_allowed()
            tgt = v if name == "MA" else int(round(self.pos)) + v
            if not (I32_MIN <= tgt <= I32_MAX): raise MbErr(ILLEGAL_VALUE)
            self._check_soft_limit(tgt)
            p[name] = v
            self.mode = 'move'
            self.target = tgt
            if tgt == int(round(self.pos)):
                self.mode = None
            return
        elif name == "SL":
            if self.mode in ('move', 'home'): raise MbErr(DEVICE_FAILURE)
            if v != 0:
                self._check_motion_allowed(allow_slew=True)
                lim = self._soft_limit_blocks(1 if v > 0 else -1)
                if lim: raise MbErr(ILLEGAL_VALUE)
                self.mode = 'slew'
            p["SL"] = v
            self.slew_v = v
            return
        elif name in ("HI", "HM"):
            self._check_motion_allowed()
            p[name] = v
            self.mode = 'home'
            self.home_t = time.monotonic() + 0.6
            self.home_dir = -1 if v in (1, 2) else 1
            return
        elif name == "ER":
            p["ER"] = 0
            return
        elif name in ("DC", "IC"):
            tgt = {REG[n][1]: n for n in ("R1", "R2", "R3", "R4")}.get(v)
            if tgt is None:
                if v in [REG[n][1] for n in USER_VARS]:
                    raise MbErr(DEVICE_FAILURE)
                raise MbErr(ILLEGAL_VALUE)
            nv = p[tgt] + (1 if name == "IC" else -1)
            if nv > I32_MAX: nv = I32_MIN
            if nv < I32_MIN: nv = I32_MAX
            p[tgt] = nv
            return
        elif name == "IP":
            if v == 1:
                if mv: raise MbErr(DEVICE_FAILURE)
                self.initialize()
            return
        elif name == "S":
            if v == 1:
                if mv: raise MbErr(DEVICE_FAILURE)
                self.save()
            return
        elif name == "CF":
            if v == 1:
                p["LR"] = 0
                p["LL"] = 0
                if p["AS"] != 0:
                    self.cal_until = time.monotonic() + 0.5
            return
        elif name == "SC":
            if v == 1:
                if mv or p["AS"] == 0 or p["DE"] == 0: raise MbErr(DEVICE_FAILURE)
                self.cal_until = time.monotonic() + 1.0
            return
        p[name] = v

    def _check_motion_allowed(self, allow_slew=False):
        if self.p["DE"] == 0 or self.p["LR"]:
            raise MbErr(DEVICE_FAILURE)
        if self.moving() and not (allow_slew and self.mode == 'slew'):
            raise MbErr(DEVICE_FAILURE)

    def _soft_limit_blocks(self, direction, tgt=None):
        dirn, lpos, en = self.m["LS"]
        if not en:
            return False
        if dirn == 1 and direction > 0:
            return (tgt if tgt is not None else self.pos) >= lpos
        if dirn == 0 and direction < 0:
            return (tgt if tgt is not None else self.pos) <= lpos
        return False

    def _check_soft_limit(self, tgt):
        dirn, lpos, en = self.m["LS"]
        if not en:
            return
        if dirn == 1 and tgt > lpos: raise MbErr(ILLEGAL_VALUE)
        if dirn == 0 and tgt < lpos: raise MbErr(ILLEGAL_VALUE)

    def _stop_now(self):
        self.mode = None
        self.vel = 0.0
        self.accel_state = False
        self.p["SL"] = 0
        self.slew_v = 0
        self.idle_since = time.monotonic()

    # -------------------------------------------------------------- motion
    def _advance_pos(self, d):
        self.pos += d
        self.c1f += d
        self.c2f += d * ENC_COUNTS_PER_REV / (FULL_STEPS_PER_REV * self.p["MS"])
        self.p["P"] = max(I32_MIN, min(I32_MAX, int(round(self.pos))))
        self.p["C1"] = ((int(round(self.c1f)) - I32_MIN) % 2**32) + I32_MIN
        self.p["C2"] = ((int(round(self.c2f)) - I32_MIN) % 2**32) + I32_MIN

    def tick(self, dt):
        if self.mode is None:
            return
        p = self.p
        A, D, VI, VM = p["A"], p["D"], p["VI"], p["VM"]
        speed = abs(self.vel)
        if self.mode == 'move':
            dist = self.target - self.pos
            if abs(dist) < 0.5:
                self._advance_pos(self.target - self.pos)
                self._stop_now(); return
            direction = 1 if dist > 0 else -1
            stop_d = speed * speed / (2.0 * D)
            if stop_d >= abs(dist):
                ns = max(VI, speed - D * dt); self.accel_state = ns != speed
            else:
                ns = min(VM, max(VI, speed + A * dt)); self.accel_state = ns != speed
            step = ns * dt
            if step >= abs(dist):
                self._advance_pos(dist); self._stop_now(); return
            self.vel = direction * ns
            self._advance_pos(direction * step)
        elif self.mode == 'slew':
            tv = float(self.slew_v)
            sgn = (1 if self.vel > 0 else -1) if self.vel else (1 if tv > 0 else -1)
            if self._soft_limit_blocks(sgn):
                self._stop_now(); return
            mag = abs(self.vel)
            if tv == 0 or (self.vel and (tv > 0) != (self.vel > 0)):
                mag -= D * dt                      # decelerate (stop or reversal)
                if mag <= min(VI, abs(tv) if tv else VI):
                    if tv == 0:
                        self._stop_now(); return
                    mag = 0.0
                nv = sgn * mag
            else:
                tmag = abs(tv)
                if mag < tmag:
                    mag = min(tmag, max(min(VI, tmag), mag + A * dt))
                elif mag > tmag:
                    mag = max(tmag, mag - D * dt)
                nv = (1 if tv > 0 else -1) * mag
            self.accel_state = nv != self.vel
            self.vel = nv
            self._advance_pos(nv * dt)
        elif self.mode == 'home':
            now = time.monotonic()
            ns = min(VM, max(VI, speed + A * dt))
            self.accel_state = ns != speed
            self.vel = self.home_dir * ns
            self._advance_pos(self.vel * dt)
            if now >= self.home_t:
                self._stop_now()
                self.pos = 0.0
                p["P"] = 0


# ==========================================================================
# Manufacturer specific functions (FC 65 / 66)
MFG_ACCESS = {
    "\x1b": 'W', "AO": 'RW', "CP": 'W', "EL": 'RW', "EX": 'W', "IS": 'RW', "IT": 'R',
    "MU": 'RW', "OS": 'RW', "PS": 'W', "RS": 'W', "E": 'W', "RD": 'RW', "AJ": 'RW',
    "AT": 'RW', "BE": 'RW', "BL": 'RW', "BM": 'RW', "DJ": 'RW', "DT": 'RW', "FS": 'RW',
    "HF": 'W', "AV": 'R', "FL": 'RW', "LS": 'RW', "UG": 'W', "VT": 'R', "TR": 'RW',
    "S1": 'RW', "S2": 'RW', "S3": 'RW', "S4": 'RW',
}
SIMPLE_MFG = {  # name: (lo, hi)
    "RD": (0, 1), "AJ": (1, 999), "AT": (0, 1), "BE": (0, 1), "BL": (0, I32_MAX),
    "BM": (0, 1), "DJ": (1, 999), "DT": (0, 1), "FS": (0, 99999), "FL": (0, 1),
    "AO": (0, 65535),
}


def decode_mnemonic(b4):
    """4 bytes: Hi word, Lo word, sent reversed.  Returns (name, line or None)."""
    raw = bytes(reversed(b4))
    s = raw.replace(b"\x00", b" ").decode("latin-1")
    s = s.strip(" ")
    if not s:
        return None, None
    line = None
    if len(s) >= 3 and s[-1].isdigit() and s[:2] in ("IS", "OS"):
        line = int(s[2:]) if s[2:].isdigit() else None
        if line is None:
            return None, None
        s = s[:2]
    return s, line


def parse_ints(text, n_min, n_max):
    t = text.strip()
    if t.startswith("="):
        t = t[1:]
    parts = [x.strip() for x in t.split(",")]
    if not (n_min <= len(parts) <= n_max):
        raise MbErr(ILLEGAL_VALUE)
    out = []
    for x in parts:
        xs = x[1:] if x[:1] in "+-" else x
        if not xs.isdigit() or len(xs) > 10:
            raise MbErr(ILLEGAL_VALUE)
        out.append(int(x))
    return out


def fmt(vals, sep=", "):
    return sep.join(str(v) for v in vals)


def mfg_read(dr, name, line):
    m = dr.m
    if name in SIMPLE_MFG:
        return str(m[name])
    if name == "EL":
        return str(ENC_COUNTS_PER_REV // 4)
    if name == "IT":
        return fmt([BRIDGE_TEMP, CPU_TEMP], ",")
    if name == "VT":
        return fmt([AUX_V, MAIN_V], ",")
    if name == "AV":
        return str(0 if dr.p["AS"] == 0 else int(round(dr.vel)))
    if name == "MU":
        return fmt([dr.p["MU"], 0])
    if name == "LS":
        return fmt(m["LS"])
    if name == "TR":
        return fmt(m["TR"])
    if name == "IS":
        if line is None:
            return "; ".join(fmt([l] + m["IS"][l][:2]) for l in (1, 2, 3, 4)) + "; " + fmt([5] + m["AI"])
        if line in (1, 2, 3, 4):
            return fmt([line] + m["IS"][line][:2])
        if line == 5:
            return fmt([5] + m["AI"])
        raise MbErr(ILLEGAL_ADDRESS)
    if name == "OS":
        if line is None:
            return "; ".join(fmt([l] + m["OS"][l]) for l in (1, 2, 3))
        if line in (1, 2, 3):
            return fmt([line] + m["OS"][line])
        raise MbErr(ILLEGAL_ADDRESS)
    if name in ("S1", "S2", "S3", "S4"):
        return fmt(m["IS"][int(name[1])])
    raise MbErr(ILLEGAL_ADDRESS)


def mfg_write(dr, name, line, data):
    m = dr.m
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        raise MbErr(ILLEGAL_VALUE)
    if any(ord(c) < 0x20 for c in text):
        raise MbErr(ILLEGAL_VALUE)
    if name in ("\x1b", "CP", "PS", "RS", "E"):
        if text.strip():
            raise MbErr(ILLEGAL_VALUE)
        if name == "\x1b" and dr.moving():
            dr._stop_now()
        return
    if name == "EX":
        label = text.strip()
        if not label or len(label) > 3 or not label.isalnum():
            raise MbErr(ILLEGAL_VALUE)
        raise MbErr(DEVICE_FAILURE)        # program space is empty: nothing to execute
    if name == "UG":
        if text.strip() != "2956102":
            raise MbErr(ILLEGAL_VALUE)
        raise MbErr(DEVICE_FAILURE)        # upgrades only via the LSS Ethernet Interface
    if name == "EL":
        parse_ints(text, 1, 1)
        raise MbErr(DEVICE_FAILURE)        # not applicable to integrated LMD
    if name == "HF":
        (mode,) = parse_ints(text, 1, 1)
        if not 1 <= mode <= 4:
            raise MbErr(ILLEGAL_VALUE)
        dr.write("HI", mode)
        return
    if name in SIMPLE_MFG:
        (v,) = parse_ints(text, 1, 1)
        lo, hi = SIMPLE_MFG[name]
        if not lo <= v <= hi:
            raise MbErr(ILLEGAL_VALUE)
        m[name] = v
        return
    if name == "MU":
        vals = parse_ints(text, 1, 2)
        if not 0 <= vals[0] <= 2:
            raise MbErr(ILLEGAL_VALUE)
        if len(vals) == 2 and vals[1] not in (0, 1):
            raise MbErr(ILLEGAL_VALUE)
        dr.p["MU"] = vals[0]
        if len(vals) == 2 and vals[1] == 1:
            dr.p["LL"] = 0
        return
    if name == "LS":
        d, pos, en = parse_ints(text, 3, 3)
        if d not in (0, 1) or en not in (0, 1) or not I32_MIN <= pos <= I32_MAX:
            raise MbErr(ILLEGAL_VALUE)
        m["LS"] = [d, pos, en]
        return
    if name == "TR":
        a, b, c = parse_ints(text, 3, 3)
        if not I32_MIN <= a <= I32_MAX or b not in (0, 1) or c not in (0, 1):
            raise MbErr(ILLEGAL_VALUE)
        m["TR"] = [a, b, c]
        return
    if name in ("S1", "S2", "S3", "S4"):
        vals = parse_ints(text, 2, 3)
        ln = int(name[1])
        if vals[0] not in IN_FUNCS or vals[1] not in (0, 1) or (len(vals) == 3 and vals[2] not in (0, 1)):
            raise MbErr(ILLEGAL_VALUE)
        m["IS"][ln] = [vals[0], vals[1], vals[2] if len(vals) == 3 else m["IS"][ln][2]]
        return
    if name == "IS":
        vals = parse_ints(text, 2, 3)
        if len(vals) == 2:
            if line is None:
                raise MbErr(ILLEGAL_VALUE)
            vals = [line] + vals
        if line is not None and vals[0] != line:
            raise MbErr(ILLEGAL_VALUE)
        ln, a, b = vals
        if ln in (1, 2, 3, 4):
            if a not in IN_FUNCS or b not in (0, 1):
                raise MbErr(ILLEGAL_VALUE)
            m["IS"][ln][0], m["IS"][ln][1] = a, b
        elif ln == 5:
            if a not in (9, 10) or b not in (0, 1):
                raise MbErr(ILLEGAL_VALUE)
            m["AI"] = [a, b]
        else:
            raise MbErr(ILLEGAL_VALUE)
        return
    if name == "OS":
        vals = parse_ints(text, 2, 3)
        if len(vals) == 2:
            if line is None:
                raise MbErr(ILLEGAL_VALUE)
            vals = [line] + vals
        if line is not None and vals[0] != line:
            raise MbErr(ILLEGAL_VALUE)
        ln, f, act = vals
        if ln not in (1, 2, 3) or f not in OUT_FUNCS or act not in (0, 1):
            raise MbErr(ILLEGAL_VALUE)
        if f == 28 and ln != 3:
            raise MbErr(ILLEGAL_VALUE)
        if f == 16 and m["OS"][ln][0] != 16:
            # back to general purpose: latch takes the state the function drove
            dr.p["O%d" % ln] = dr.output_state(ln)
        m["OS"][ln] = [f, act]
        return
    raise MbErr(ILLEGAL_ADDRESS)


# ==========================================================================
# PDU processing
def pdu_exc(fc, code):
    return bytes([(fc | 0x80) & 0xFF, code])


def handle_pdu(dr, pdu):
    fc = pdu[0]
    try:
        if fc in (0x01, 0x02):
            return fc_read_bits(dr, fc, pdu)
        if fc == 0x03:
            return fc_read_regs(dr, pdu)
        if fc == 0x05:
            return fc_write_coil(dr, pdu)
        if fc == 0x10:
            return fc_write_regs(dr, pdu)
        if fc == 0x2B:
            return fc_devid(dr, pdu)
        if fc == 0x41:
            return fc_mfg_read(dr, pdu)
        if fc == 0x42:
            return fc_mfg_write(dr, pdu)
        raise MbErr(ILLEGAL_FUNCTION)
    except MbErr as e:
        dr.counters["exceptions"] += 1
        return pdu_exc(fc, e.code)
    except Exception:
        dr.counters["exceptions"] += 1
        return pdu_exc(fc, DEVICE_FAILURE)


def fc_read_bits(dr, fc, pdu):
    if len(pdu) != 5:
        raise MbErr(ILLEGAL_VALUE)
    start, qty = struct.unpack(">HH", pdu[1:5])
    if not 1 <= qty <= 2000:
        raise MbErr(ILLEGAL_VALUE)
    if fc == 0x01:
        if start + qty > 3:
            raise MbErr(ILLEGAL_ADDRESS)
        bits = [dr.output_state(start + i + 1) for i in range(qty)]
    else:
        base = 0x002D if 0x002D <= start <= 0x0030 else 0
        if start - base + qty > 4 or (base == 0 and start > 3):
            raise MbErr(ILLEGAL_ADDRESS)
        bits = [dr.p["I%d" % (start - base + i + 1)] for i in range(qty)]
    nb = (qty + 7) // 8
    out = bytearray(nb)
    for i, b in enumerate(bits):
        if b:
            out[i // 8] |= 1 << (i % 8)
    return bytes([fc, nb]) + bytes(out)


def _span(start, qty):
    """Return list of item names covering [start, start+qty) exactly, or raise 02."""
    names = []
    a = start
    end = start + qty
    while a < end:
        ent = ADDR.get(a)
        if ent is None or ent[1] != 0:
            raise MbErr(ILLEGAL_ADDRESS)
        name = ent[0]
        nw = REG[name][2]
        if a + nw > end:
            raise MbErr(ILLEGAL_ADDRESS)
        names.append(name)
        a += nw
    return names


def fc_read_regs(dr, pdu):
    if len(pdu) != 5:
        raise MbErr(ILLEGAL_VALUE)
    start, qty = struct.unpack(">HH", pdu[1:5])
    if not 1 <= qty <= 2:
        raise MbErr(ILLEGAL_VALUE)
    names = _span(start, qty)
    words = []
    for n in names:
        words += dr.words(n)
    for n in names:
        if n in USER_VARS:
            raise MbErr(DEVICE_FAILURE)
    for n in names:                 # "must be read ... to clear" (ER)
        if n == "ER":
            dr.p["ER"] = 0
    return bytes([0x03, 2 * len(words)]) + b"".join(struct.pack(">H", w) for w in words)


def fc_write_coil(dr, pdu):
    if len(pdu) != 5:
        raise MbErr(ILLEGAL_VALUE)
    addr, val = struct.unpack(">HH", pdu[1:5])
    if val not in (0x0000, 0xFF00):
        raise MbErr(ILLEGAL_VALUE)
    if addr > 2:
        raise MbErr(ILLEGAL_ADDRESS)
    dr.write("O%d" % (addr + 1), 1 if val else 0)
    return bytes(pdu)


def fc_write_regs(dr, pdu):
    if len(pdu) < 6:
        raise MbErr(ILLEGAL_VALUE)
    start, qty, bc = struct.unpack(">HHB", pdu[1:6])
    if not 1 <= qty <= 2 or bc != 2 * qty or len(pdu) != 6 + bc:
        raise MbErr(ILLEGAL_VALUE)
    names = _span(start, qty)
    words = list(struct.unpack(">%dH" % qty, pdu[6:6 + bc]))
    vals = []
    i = 0
    for n in names:
        nw, signed = REG[n][2], REG[n][3]
        if nw == 1:
            v = words[i]
            if signed and v >= 0x8000:
                v -= 0x10000
        else:
            v = words[i] | (words[i + 1] << 16)
            if signed and v >= 0x80000000:
                v -= 0x100000000
        vals.append(v)
        i += nw
    # all-or-nothing: check every item against a trial copy first
    for n in names:
        if REG[n][4] == 'ro':
            raise MbErr(ILLEGAL_ADDRESS)
    if len(names) > 1:
        import copy
        trial = copy.deepcopy(dr)
        for n, v in zip(names, vals):
            trial.write(n, v)
    for n, v in zip(names, vals):
        dr.write(n, v)
    return bytes([0x10]) + struct.pack(">HH", start, qty)


def fc_devid(dr, pdu):
    if len(pdu) < 2:
        raise MbErr(ILLEGAL_VALUE)
    if pdu[1] != 0x0E:
        raise MbErr(ILLEGAL_FUNCTION)
    if len(pdu) != 4:
        raise MbErr(ILLEGAL_VALUE)
    code, oid = pdu[2], pdu[3]
    if code not in (1, 2, 3, 4):
        raise MbErr(ILLEGAL_VALUE)
    if code == 4:
        if oid not in DEV_ID:
            raise MbErr(ILLEGAL_ADDRESS)
        ids = [oid]
    else:
        last = 2 if code == 1 else 6
        if oid > last:
            oid = 0
        ids = list(range(oid, last + 1))
    body = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)])
    for i in ids:
        body += bytes([i, len(DEV_ID[i])]) + DEV_ID[i]
    return bytes(body)


def fc_mfg_read(dr, pdu):
    if len(pdu) != 5:
        raise MbErr(ILLEGAL_VALUE)
    name, line = decode_mnemonic(pdu[1:5])
    if name not in MFG_ACCESS:
        raise MbErr(ILLEGAL_ADDRESS)
    if 'R' not in MFG_ACCESS[name]:
        raise MbErr(ILLEGAL_ADDRESS)
    s = mfg_read(dr, name, line).encode("ascii")
    return bytes([0x41, len(s)]) + s


def fc_mfg_write(dr, pdu):
    if len(pdu) < 6:
        raise MbErr(ILLEGAL_VALUE)
    bc = pdu[5]
    if bc > 28 or len(pdu) != 6 + bc:
        raise MbErr(ILLEGAL_VALUE)
    name, line = decode_mnemonic(pdu[1:5])
    if name not in MFG_ACCESS:
        raise MbErr(ILLEGAL_ADDRESS)
    if 'W' not in MFG_ACCESS[name]:
        raise MbErr(ILLEGAL_ADDRESS)
    mfg_write(dr, name, line, bytes(pdu[6:6 + bc]))
    return bytes([0x42, bc]) + bytes(pdu[1:5])


# ==========================================================================
# State dump
def dump_state(dr):
    hr = {}
    for r in REGS:
        ws = dr.words(r[0])
        for i, w in enumerate(ws):
            hr["0x%04X" % (r[1] + i)] = w
    items = {r[0]: dr.value(r[0]) for r in REGS}
    mfg = {}
    for n, acc in MFG_ACCESS.items():
        if 'R' in acc and n not in ("IT", "VT", "AV"):
            mfg[n if n != "\x1b" else "ESC"] = mfg_read(dr, n, None)
    return {
        "device": "LMD Ethernet closed loop (hMT) Modbus/TCP",
        "holding_registers": hr,
        "items": items,
        "coils": {"0x0000": dr.output_state(1), "0x0001": dr.output_state(2), "0x0002": dr.output_state(3)},
        "discrete_inputs": {"0x%04X" % i: dr.p["I%d" % (i + 1)] for i in range(4)},
        "mfg_parameters": mfg,
        "mfg_raw": json.loads(json.dumps(dr.m)),
        "output_latches": {"O1": dr.p["O1"], "O2": dr.p["O2"], "O3": dr.p["O3"]},
        "motion": {"moving": dr.moving(), "mode": dr.mode},
        "nvm": dr.nvm,
        "diagnostic_counters": dict(dr.counters),
    }


def write_state(dr, path):
    if not path:
        return
    try:
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(dump_state(dr), f, indent=1, sort_keys=True)
        os.replace(tmp, path)
    except Exception as e:
        print("state write failed: %s" % e, file=sys.stderr)


# ==========================================================================
# TCP server
MAX_ADU = 260


async def serve_conn(dr, reader, writer):
    dr.counters["connections"] += 1
    buf = bytearray()
    try:
        while True:
            data = await reader.read(4096)
            if not data:
                break
            buf += data
            while len(buf) >= 7:
                tid, pid, length, uid = struct.unpack(">HHHB", buf[:7])
                if length < 2 or length > MAX_ADU - 6:
                    # cannot resynchronise a TCP stream after a bad length: drop the connection
                    dr.counters["bad_frames"] += 1
                    return
                if len(buf) < 6 + length:
                    break
                frame = bytes(buf[:6 + length])
                del buf[:6 + length]
                if pid != 0:
                    dr.counters["bad_frames"] += 1
                    continue            # not Modbus: silently discarded (TCP guide)
                pdu = frame[7:]
                dr.counters["requests"] += 1
                resp = handle_pdu(dr, pdu)
                writer.write(struct.pack(">HHHB", tid, 0, len(resp) + 1, uid) + resp)
            await writer.drain()
    except (ConnectionError, asyncio.IncompleteReadError, OSError, asyncio.CancelledError):
        pass
    finally:
        try:
            writer.close()
        except Exception:
            pass


async def motion_loop(dr):
    last = time.monotonic()
    while True:
        await asyncio.sleep(0.01)
        now = time.monotonic()
        try:
            dr.tick(min(now - last, 0.1))
        except Exception as e:
            print("motion error: %r" % e, file=sys.stderr)
            dr._stop_now()
        last = now


async def main_async(args):
    host, _, port = args.listen.rpartition(":")
    if host not in ("127.0.0.1", "localhost", "::1", "[::1]"):
        print("refusing to bind non-loopback address %s" % host, file=sys.stderr)
        sys.exit(2)
    host = host.strip("[]")
    dr = Drive()
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    loop.add_signal_handler(signal.SIGUSR1, lambda: write_state(dr, args.state))
    server = await asyncio.start_server(lambda r, w: serve_conn(dr, r, w), host, int(port))
    sock = server.sockets[0].getsockname()
    print("listening tcp %s:%d" % (sock[0], sock[1]), flush=True)
    mt = asyncio.create_task(motion_loop(dr))
    await stop.wait()
    server.close()
    mt.cancel()
    write_state(dr, args.state)
    sys.stdout.flush()
    os._exit(0)


def main():
    ap = argparse.ArgumentParser(description="LMD Ethernet (closed loop) Modbus/TCP simulator")
    ap.add_argument("--listen", required=True)
    ap.add_argument("--state", default=None)
    args = ap.parse_args()
    asyncio.run(main_async(args))
    os._exit(0)


if __name__ == "__main__":
    main()
