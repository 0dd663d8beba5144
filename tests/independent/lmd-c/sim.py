#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet, open-loop model -- Modbus/TCP server simulator.

Clean-room implementation written from the "MODBUS/TCP Fieldbus manual"
(LMD-MODBUS-REV-D) and the public Modbus specifications.  See DECISIONS.md
for every place where the manual was ambiguous or wrong.

Usage: python3 sim.py --listen 127.0.0.1:0 [--state FILE]
Standard library only.
"""

import argparse
import asyncio
import copy
import json
import math
import os
import signal
import sys
import time
import traceback

# ---------------------------------------------------------------------------
# Constants / product identity
# ---------------------------------------------------------------------------

VENDOR_NAME = "IMS USA"
PRODUCT_CODE = "LMDOE572"             # LMD, Open loop, Ethernet, NEMA 23, stack 2
MAJOR_MINOR_REV = "4.0.0.0"           # Ethernet communication firmware
VENDOR_URL = "https://novantaims.com/"
PRODUCT_NAME = "LMD Ethernet"
SERIAL_NUMBER = "269131147"
MCODE_OS = "6.012"                    # >= 6.004: OS-6 mnemonics are available
USER_APP_NAME = "LMDCM %s, Hw: 1.0" % MCODE_OS

MAX_CONNECTIONS = 16
TICK = 0.010          # background motion update period (s)
SUBSTEP = 0.001       # motion integration step (s)

INT32_MIN = -2 ** 31
INT32_MAX = 2 ** 31 - 1

# I/O function codes (manual 4.4.6 / 4.4.9)
INPUT_TYPES = {0, 1, 2, 3, 5, 7, 8, 11, 12}
OUTPUT_TYPES = {16, 17, 18, 20, 21, 23, 24, 25, 28, 29}   # 26/27 reserved
ANALOG_MODES = {9, 10}
MS_VALUES = {1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250,
             256, 180, 108, 127}
UPGRADE_KEY = 2956102

# MCode error codes latched in ER (0x0021) when the MCode engine refuses
ERR_UNKNOWN_LABEL = 30
ERR_ILLEGAL_PROG_ADDR = 42
ERR_SAVE_WHILE_MOVING = 73
ERR_IP_CP_WHILE_MOVING = 74
ERR_HOME_NOT_DEFINED = 80
ERR_PLUS_LIMIT = 83
ERR_MINUS_LIMIT = 84
ERR_HOME_MOTION_CONFLICT = 85


class MBException(Exception):
    """Modbus exception response; optional MCode error to latch in ER/EF."""

    def __init__(self, code, mcode_err=None):
        super().__init__(code)
        self.code = code
        self.mcode_err = mcode_err


def wrap32(v):
    return ((int(v) + 2 ** 31) % 2 ** 32) - 2 ** 31


def sgn(v):
    return (v > 0) - (v < 0)


# ---------------------------------------------------------------------------
# Factory defaults of the persistent parameter set (saved by S, reset by IP)
# ---------------------------------------------------------------------------

def factory_persistent():
    p = {
        "A": 1000000, "D": 1000000, "VI": 1000, "VM": 768000,
        "CE": 1, "CW": 10, "D1": 0, "D2": 0, "D3": 0, "D4": 0, "D5": 0,
        "DE": 1, "FC": 0, "HC": 5, "HT": 500, "JE": 0, "LM": 1, "MS": 256,
        "MT": 0, "RC": 25, "WT": 80,
        "R1": 0, "R2": 0, "R3": 0, "R4": 0,
        # manufacturer-specific (FC 65/66) settings
        "AO": 0, "RD": 0, "AJ": 128, "AT": 0, "DJ": 128, "DT": 0,
        "BE": 0, "BL": 0, "BM": 0, "FL": 0,
    }
    io = {
        1: {"type": 0, "active": 0, "sink_source": 0},
        2: {"type": 0, "active": 0, "sink_source": 0},
        3: {"type": 0, "active": 0, "sink_source": 0},
        4: {"type": 0, "active": 0, "sink_source": 0},
        5: {"mode": 9, "range": 0},      # analog input: voltage, 0-5 V
    }
    ls = {0: {"position": 0, "enabled": 0},   # minus software limit
          1: {"position": 0, "enabled": 0}}   # plus software limit
    return {"params": p, "io": io, "ls": ls}


# ---------------------------------------------------------------------------
# Register map (section 5).  (addr, nregs, name, access, signed)
#   access: rw = setting, ro = status, cmd = command (write triggers action)
# Closed-loop-only registers (C2, DB, EE, HI, I6, PM, SF, SM, ST and the whole
# hMTechnology block 0x008E-0x00A7) do not exist on this open-loop product.
# ---------------------------------------------------------------------------

REGISTERS = [
    (0x0000, 2, "A", "rw", False),
    (0x0004, 1, "BY", "ro", False),
    (0x0005, 2, "C1", "rw", True),
    (0x0009, 1, "CE", "rw", False),
    (0x000E, 1, "CW", "rw", False),
    (0x000F, 1, "D1", "rw", False),
    (0x0010, 1, "D2", "rw", False),
    (0x0011, 1, "D3", "rw", False),
    (0x0012, 1, "D4", "rw", False),
    (0x0013, 1, "D5", "rw", False),
    (0x0018, 2, "D", "rw", False),
    (0x001B, 1, "DC", "cmd", False),
    (0x001C, 1, "DE", "rw", False),
    (0x001F, 1, "EF", "ro", False),
    (0x0021, 1, "ER", "rw", False),
    (0x0024, 1, "FC", "rw", False),
    (0x0029, 1, "HC", "rw", False),
    (0x002B, 1, "HM", "cmd", False),
    (0x002C, 1, "HT", "rw", False),
    (0x002D, 1, "I1", "ro", False),
    (0x002E, 1, "I2", "ro", False),
    (0x002F, 1, "I3", "ro", False),
    (0x0030, 1, "I4", "ro", False),
    (0x0031, 1, "I5", "ro", False),
    (0x0037, 1, "IC", "cmd", False),
    (0x003B, 1, "IN", "ro", False),
    (0x003C, 1, "IP", "cmd", False),
    (0x003F, 1, "JE", "rw", False),
    (0x0042, 1, "LM", "rw", False),
    (0x0043, 2, "MA", "cmd", True),
    (0x0045, 1, "MP", "ro", False),
    (0x0046, 2, "MR", "cmd", True),
    (0x0048, 1, "MS", "rw", False),
    (0x0049, 1, "MT", "rw", False),
    (0x004A, 1, "MV", "ro", False),
    (0x004B, 1, "O1", "rw", False),
    (0x004C, 1, "O2", "rw", False),
    (0x004D, 1, "O3", "rw", False),
    (0x004E, 1, "OF", "ro", False),
    (0x0056, 1, "OT", "rw", False),
    (0x0057, 2, "P", "rw", True),
    (0x0059, 2, "PC", "ro", True),
    (0x005F, 2, "R1", "rw", True),
    (0x0061, 2, "R2", "rw", True),
    (0x0063, 2, "R3", "rw", True),
    (0x0065, 2, "R4", "rw", True),
    (0x0067, 1, "RC", "rw", False),
    (0x0076, 1, "S", "cmd", False),
    (0x0078, 2, "SL", "cmd", True),
    (0x007D, 1, "TE", "rw", False),
    (0x0085, 2, "V", "ro", True),
    (0x0088, 1, "VC", "ro", False),
    (0x0089, 2, "VI", "rw", False),
    (0x008B, 2, "VM", "rw", False),
    (0x008D, 1, "WT", "rw", False),
    (0x00A8, 2, "V1", "rw", True),
    (0x00AA, 2, "V2", "rw", True),
    (0x00AC, 2, "V3", "rw", True),
    (0x00AE, 2, "V4", "rw", True),
    (0x00B0, 2, "V5", "rw", True),
    (0x00B2, 2, "V6", "rw", True),
    (0x00B4, 2, "V7", "rw", True),
    (0x00B6, 2, "V8", "rw", True),
]

REG_BY_NAME = {r[2]: r for r in REGISTERS}
# word address -> (register tuple, word index: 0 = low word, 1 = high word)
WORD_MAP = {}
for _r in REGISTERS:
    for _i in range(_r[1]):
        WORD_MAP[_r[0] + _i] = (_r, _i)

# simple numeric ranges for settings
RANGES = {
    "A": (91, 1525878997), "D": (91, 1525878997),
    "C1": (INT32_MIN, INT32_MAX), "CE": (0, 1), "CW": (0, 255),
    "D1": (0, 255), "D2": (0, 255), "D3": (0, 255), "D4": (0, 255),
    "D5": (0, 255), "DE": (0, 1), "FC": (0, 9), "HC": (0, 100),
    "HM": (1, 4), "JE": (0, 1), "LM": (1, 6), "MT": (0, 65000),
    "O1": (0, 1), "O2": (0, 1), "O3": (0, 1), "OT": (0, 15),
    "P": (INT32_MIN, INT32_MAX), "RC": (1, 100),
    "SL": (-5000000, 5000000), "TE": (0, 63), "WT": (0, 84),
    "MA": (INT32_MIN, INT32_MAX), "MR": (INT32_MIN, INT32_MAX),
}
for _n in ("R1", "R2", "R3", "R4", "V1", "V2", "V3", "V4", "V5", "V6", "V7", "V8"):
    RANGES[_n] = (INT32_MIN, INT32_MAX)

# variables that IC/DC may target (by their Modbus register address)
INCDEC_TARGETS = {0x0005: "C1", 0x0057: "P", 0x005F: "R1", 0x0061: "R2",
                  0x0063: "R3", 0x0065: "R4", 0x00A8: "V1", 0x00AA: "V2",
                  0x00AC: "V3", 0x00AE: "V4", 0x00B0: "V5", 0x00B2: "V6",
                  0x00B4: "V7", 0x00B6: "V8"}


# ---------------------------------------------------------------------------
# The drive
# ---------------------------------------------------------------------------

class Drive:
    def __init__(self):
        self.factory = factory_persistent()
        self.nvm = copy.deepcopy(self.factory)
        self.cur = copy.deepcopy(self.nvm)          # working memory
        self.p = self.cur["params"]
        self.uservars = {"V%d" % i: 0 for i in range(1, 9)}
        self.out_latch = [0, 0, 0, 0]
        self.ef = 0
        self.er = 0
        self.pc = 0
        self.last_cmd = {"MA": 0, "MR": 0, "SL": 0, "HM": 0, "DC": 0, "IC": 0,
                         "IP": 0, "S": 0}
        self.trip = {"distance": 0, "address": 0, "option": 0}
        self.te = 0
        self.upgrade_mode = False
        self.saves = 0
        # motion
        self.x = 0.0            # position (steps, P frame)
        self.c1 = 0.0           # clock pulse counter
        self.v = 0.0            # velocity (steps/s, signed)
        self.mode = None        # None | 'pos' | 'vel'
        self.target = 0.0
        self.vmax = 0.0
        self.vt = 0.0
        self.is_posmove = False     # MP flag (MA/MR)
        self.homing = False
        self.phases = []
        self.limit_pending = None   # MCode error to latch when move completes
        self.vchanging = False
        self.mech_zero = 0.0        # simulated home switch location (P frame)
        self.trip_origin = None
        self.t_last = time.monotonic()
        self.t_stopped = self.t_last

    # ------------------------------------------------------------- helpers
    def moving(self):
        return self.mode is not None

    def latch_error(self, code):
        self.er = code
        self.ef = 1

    # ------------------------------------------------------------- motion
    def _approach(self, v, vdes, dt):
        A = float(self.p["A"])
        D = float(self.p["D"])
        VI = float(self.p["VI"])
        if v == vdes:
            return v
        if v == 0.0:
            # a stepper starts at the initial velocity (or lower target)
            return sgn(vdes) * min(VI, abs(vdes))
        if vdes == 0.0 or sgn(vdes) != sgn(v):
            # decelerate towards standstill; below VI the motor simply stops
            mag = abs(v) - D * dt
            if mag <= VI:
                return 0.0
            return sgn(v) * mag
        if abs(vdes) > abs(v):
            return sgn(v) * min(abs(vdes), abs(v) + A * dt)
        return sgn(v) * max(abs(vdes), abs(v) - D * dt)

    def _substep(self, dt):
        VI = float(self.p["VI"])
        D = float(self.p["D"])
        if self.mode == "vel":
            vnew = self._approach(self.v, self.vt, dt)
            self.vchanging = vnew != self.v or vnew != self.vt
            dx = vnew * dt
            self.x += dx
            self.c1 += dx
            self.v = vnew
            if self.vt == 0.0 and self.v == 0.0:
                self._finish_phase()
            elif abs(self.x) > 2 ** 31:
                # 32-bit position counter roll-over while slewing
                shift = -sgn(self.x) * 2 ** 32
                self.x += shift
                self.mech_zero += shift
                if self.trip_origin is not None:
                    self.trip_origin += shift
            if abs(self.c1) > 2 ** 31:
                self.c1 -= sgn(self.c1) * 2 ** 32
        elif self.mode == "pos":
            d = self.target - self.x
            if abs(d) < 1e-6:
                self.x = self.target
                self.v = 0.0
                self._finish_phase()
                return
            vdes = sgn(d) * min(self.vmax, math.sqrt(VI * VI + 2.0 * D * abs(d)))
            vnew = self._approach(self.v, vdes, dt)
            if vnew == 0.0 and self.v == 0.0:
                vnew = sgn(d) * min(VI, self.vmax)
            self.vchanging = vnew != self.v or abs(vnew) != abs(vdes)
            xnew = self.x + vnew * dt
            if sgn(self.target - xnew) != sgn(d):
                self.c1 += self.target - self.x
                self.x = self.target
                self.v = 0.0
                self._finish_phase()
                return
            self.c1 += xnew - self.x
            self.x = xnew
            self.v = vnew
        self._check_trip()

    def _check_trip(self):
        if not (self.te & 16) or self.trip_origin is None:
            return
        dist = abs(self.trip["distance"])
        if dist == 0:
            return
        moved = self.x - self.trip_origin
        if abs(moved) >= dist:
            # capture the position at which the trip distance was crossed
            self.pc = wrap32(round(self.trip_origin + sgn(moved) * dist))
            self.te &= ~16          # trip fired: must be re-enabled
            self.trip_origin = None

    def _finish_phase(self):
        self.v = 0.0
        self.mode = None
        self.vchanging = False
        if self.phases:
            nxt = self.phases.pop(0)
            nxt()
            return
        self.is_posmove = False
        self.homing = False
        if self.limit_pending:
            self.latch_error(self.limit_pending)
            self.limit_pending = None
        self.trip_origin = None
        self.t_stopped = self.t_last

    def update(self, now=None):
        if now is None:
            now = time.monotonic()
        elapsed = now - self.t_last
        if elapsed <= 0:
            return
        if self.mode is None:
            self.t_last = now
            return
        # bounded integration: at most 2 minutes of 1 ms sub-steps per call
        n = min(int(elapsed / SUBSTEP), 120000)
        for _ in range(n):
            self.t_last += SUBSTEP
            self._substep(SUBSTEP)
            if self.mode is None:
                break
        if self.mode is None:
            self.t_last = now

    def _arm_trip(self):
        if self.trip_origin is None:
            self.trip_origin = self.x

    def _limit_target(self, target):
        """Software limits (LS).  Returns (target, pending MCode error)."""
        ls = self.cur["ls"]
        if ls[1]["enabled"] and target > ls[1]["position"]:
            lim = float(ls[1]["position"])
            return (lim if self.x < lim else self.x), ERR_PLUS_LIMIT
        if ls[0]["enabled"] and target < ls[0]["position"]:
            lim = float(ls[0]["position"])
            return (lim if self.x > lim else self.x), ERR_MINUS_LIMIT
        return float(target), None

    def start_position_move(self, target):
        target, pend = self._limit_target(target)
        self.phases = []
        self.homing = False
        self.limit_pending = pend
        self.target = target
        self.vmax = float(self.p["VM"])
        self.mode = "pos"
        self.is_posmove = True
        self._arm_trip()

    def start_slew(self, vel):
        self.phases = []
        self.homing = False
        self.is_posmove = False
        ls = self.cur["ls"]
        if (vel > 0 and ls[1]["enabled"]) or (vel < 0 and ls[0]["enabled"]):
            # slewing towards an enabled software limit: stop at the limit
            self.target, self.limit_pending = self._limit_target(
                INT32_MAX * 4.0 * sgn(vel))
            self.mode = "pos"
            self.vmax = float(abs(vel))
        else:
            self.mode = "vel"
            self.vt = float(vel)
            self.limit_pending = None
        if vel != 0:
            self._arm_trip()

    def stop(self):
        """Decelerated stop (ESC, SL=0)."""
        self.phases = []
        self.limit_pending = None
        self.is_posmove = False
        self.homing = False
        if self.mode is not None:
            self.mode = "vel"
            self.vt = 0.0

    def start_homing(self, hm):
        VI = float(self.p["VI"])
        VM = float(self.p["VM"])
        creep = float(self.p["MS"] * 4)     # ~1/50 rev off the switch
        creep_dir = 1 if hm in (1, 4) else -1

        def slew_phase():
            self.mode = "pos"
            self.target = self.mech_zero
            self.vmax = VM
            if abs(self.target - self.x) < 1e-6:
                self.x = self.target
                self.phases.pop(0)()

        def creep_phase():
            self.mode = "pos"
            self.target = self.mech_zero + creep_dir * creep
            self.vmax = VI

        def set_zero():
            # home found: position counter is zeroed at the switch edge
            self.mech_zero -= self.x
            self.x = 0.0
            self.mode = "pos"
            self.target = 0.0
            self.vmax = VI

        self.limit_pending = None
        self.is_posmove = False
        self.homing = True
        self.phases = [creep_phase, set_zero]
        self._arm_trip()
        slew_phase()

    def current_reduction_active(self):
        if self.moving():
            return False
        delay = (self.p["HT"] + self.p["MT"]) / 1000.0
        return time.monotonic() - self.t_stopped >= delay and self.p["HC"] < self.p["RC"]

    # ------------------------------------------------------------- I/O
    def is_output_point(self, i):
        return 1 <= i <= 4 and self.cur["io"][i]["type"] >= 16

    def attention(self):
        status = 0
        if self.ef:
            status |= 1
        if self.current_reduction_active():
            status |= 512
        if self.temperatures()[0] >= self.p["WT"]:
            status |= 4096
        if self.moving():
            status |= 16384
        return 1 if status & self.p["AO"] else 0

    def output_state(self, i):
        """Logic state of output point i (1..4)."""
        if not self.is_output_point(i):
            return self.out_latch[i - 1]
        t = self.cur["io"][i]["type"]
        if t == 16:
            return self.out_latch[i - 1]
        if t == 17:
            return 1 if self.moving() else 0
        if t == 18:
            return self.ef
        if t == 20:
            return 1 if (self.moving() and self.vchanging) else 0
        if t == 23:
            return 1 if self.is_posmove else 0
        if t == 29:
            return self.attention()
        return 0        # 21/24/25 closed-loop conditions, 28 trip pulse

    def input_state(self, i):
        """Logic state of I/O point i as read by I1..I4 / FC 02."""
        if self.is_output_point(i):
            return self.output_state(i)
        return 0        # nothing wired to the simulated inputs: inactive

    def temperatures(self):
        bridge = 41 if self.moving() else 38
        return bridge, 36

    # ------------------------------------------------------------- registers
    def reg_value(self, name):
        """Current value of a register variable (no side effects)."""
        p = self.p
        if name in ("A", "D", "VI", "VM", "CE", "CW", "D1", "D2", "D3", "D4",
                    "D5", "DE", "FC", "HC", "HT", "JE", "LM", "MS", "MT", "RC",
                    "WT", "R1", "R2", "R3", "R4"):
            return p[name]
        if name in self.uservars:
            return self.uservars[name]
        if name == "BY":
            return 0
        if name == "C1":
            return wrap32(round(self.c1))
        if name == "EF":
            return self.ef
        if name == "ER":
            return self.er
        if name in ("I1", "I2", "I3", "I4"):
            return self.input_state(int(name[1]))
        if name == "I5":
            return 0
        if name == "IN":
            return sum(self.input_state(i) << (i - 1) for i in range(1, 5))
        if name in ("MA", "MR", "SL", "HM", "DC", "IC", "IP", "S"):
            return self.last_cmd[name]
        if name == "MP":
            return 1 if self.is_posmove else 0
        if name == "MV":
            return 1 if self.moving() else 0
        if name == "VC":
            return 1 if (self.moving() and self.vchanging) else 0
        if name == "V":
            return int(round(self.v))
        if name in ("O1", "O2", "O3"):
            return self.output_state(int(name[1]))
        if name == "OF":
            return 0
        if name == "OT":
            return sum(self.output_state(i) << (i - 1) for i in range(1, 5))
        if name == "P":
            return wrap32(round(self.x))
        if name == "PC":
            return self.pc
        if name == "TE":
            return self.te
        raise KeyError(name)

    def check_write(self, name, value, pending):
        """Validate a register write.  pending: dict of values written earlier
        in the same request.  Raises MBException(3) / MBException(4, err)."""
        if name in RANGES:
            lo, hi = RANGES[name]
            if not lo <= value <= hi:
                raise MBException(3)
        if name == "VI":
            vm = pending.get("VM", self.p["VM"])
            if not 1 <= value < vm:
                raise MBException(3)
        elif name == "VM":
            vi = pending.get("VI", self.p["VI"])
            if not vi < value <= 2560000:
                raise MBException(3)
        elif name == "HT":
            if value == 1:
                raise MBException(3)
            if value + pending.get("MT", self.p["MT"]) > 65535:
                raise MBException(3)
        elif name == "MT":
            if value + pending.get("HT", self.p["HT"]) > 65535:
                raise MBException(3)
        elif name == "MS":
            if value not in MS_VALUES:
                raise MBException(3)
        elif name == "ER":
            if value != 0:
                raise MBException(3)
        elif name in ("DC", "IC"):
            if value not in INCDEC_TARGETS:
                raise MBException(3)
        elif name in ("MA", "MR"):
            if self.homing:
                raise MBException(4, ERR_HOME_MOTION_CONFLICT)
        elif name == "SL":
            if self.homing:
                raise MBException(4, ERR_HOME_MOTION_CONFLICT)
        elif name == "HM":
            if self.moving():
                raise MBException(4, ERR_HOME_MOTION_CONFLICT)
            if not any(self.cur["io"][i]["type"] == 1 for i in range(1, 5)):
                raise MBException(4, ERR_HOME_NOT_DEFINED)
        elif name == "S":
            if self.moving():
                raise MBException(4, ERR_SAVE_WHILE_MOVING)
        elif name == "IP":
            if self.moving():
                raise MBException(4, ERR_IP_CP_WHILE_MOVING)

    def apply_write(self, name, value):
        p = self.p
        if name in ("A", "D", "VI", "VM", "CE", "CW", "D1", "D2", "D3", "D4",
                    "D5", "DE", "FC", "HC", "HT", "JE", "LM", "MS", "MT", "RC",
                    "WT", "R1", "R2", "R3", "R4"):
            p[name] = value
            if name == "VM" and self.mode == "pos" and self.is_posmove:
                self.vmax = float(value)
        elif name in self.uservars:
            self.uservars[name] = value
        elif name == "C1":
            self.c1 = float(value)
        elif name == "ER":
            self.er = 0
            self.ef = 0
        elif name == "TE":
            self.te = value
            if value & 16 and self.moving():
                self._arm_trip()
        elif name in ("O1", "O2", "O3"):
            self.out_latch[int(name[1]) - 1] = value
        elif name == "OT":
            for i in range(4):
                self.out_latch[i] = (value >> i) & 1
        elif name == "P":
            delta = value - self.x
            self.x = float(value)
            self.mech_zero += delta
            if self.mode == "pos":
                self.target += delta
            if self.trip_origin is not None:
                self.trip_origin += delta
        elif name == "MA":
            self.last_cmd["MA"] = value
            self.start_position_move(value)
        elif name == "MR":
            self.last_cmd["MR"] = value
            self.start_position_move(round(self.x) + value)
        elif name == "SL":
            self.last_cmd["SL"] = value
            if value == 0:
                self.stop()
            else:
                self.start_slew(value)
        elif name == "HM":
            self.last_cmd["HM"] = value
            self.start_homing(value)
        elif name in ("DC", "IC"):
            self.last_cmd[name] = value
            self.incdec(INCDEC_TARGETS[value], -1 if name == "DC" else 1)
        elif name == "S":
            self.nvm = copy.deepcopy(self.cur)
            self.saves += 1
        elif name == "IP":
            self.initialize_parameters()

    def incdec(self, var, delta):
        if var == "C1":
            self.c1 = float(wrap32(round(self.c1) + delta))
        elif var == "P":
            self.apply_write("P", wrap32(round(self.x) + delta))
        elif var in self.uservars:
            self.uservars[var] = wrap32(self.uservars[var] + delta)
        else:
            self.p[var] = wrap32(self.p[var] + delta)

    def initialize_parameters(self):
        self.cur = copy.deepcopy(self.factory)
        self.p = self.cur["params"]
        for k in self.last_cmd:
            self.last_cmd[k] = 0

    # ------------------------------------------------------------- state
    def snapshot(self):
        regs = {}
        for addr, n, name, access, signed in REGISTERS:
            val = self.reg_value(name)
            u = val & 0xFFFFFFFF
            words = [u & 0xFFFF, (u >> 16) & 0xFFFF][:n]
            regs["0x%04X" % addr] = {"mnemonic": name, "access": access,
                                     "registers": n, "value": val,
                                     "words": words}
        coils = {"0x%04X" % (i - 1): self.output_state(i) for i in range(1, 5)}
        dins = {"0x%04X" % (i - 1): self.input_state(i) for i in range(1, 5)}
        io = {str(k): dict(v) for k, v in self.cur["io"].items()}
        ls = {("plus" if k else "minus"): dict(v) for k, v in self.cur["ls"].items()}
        mfg = {k: self.p[k] for k in ("AO", "RD", "AJ", "AT", "DJ", "DT",
                                      "BE", "BL", "BM", "FL")}
        mfg["TR"] = dict(self.trip)
        mfg["LS"] = ls
        mfg["IS/OS"] = io
        mfg["UG"] = {"upgrade_mode": self.upgrade_mode}
        nvm = {"params": dict(self.nvm["params"]),
               "io": {str(k): dict(v) for k, v in self.nvm["io"].items()},
               "ls": {("plus" if k else "minus"): dict(v)
                      for k, v in self.nvm["ls"].items()}}
        return {
            "device": {"product": PRODUCT_CODE, "mcode_os": MCODE_OS,
                       "variant": "open loop (no encoder, no hMTechnology)",
                       "unit_ids": "all (0-255), unit id is echoed"},
            "holding_registers": regs,
            "coils": coils,
            "output_latch": {"0x%04X" % i: self.out_latch[i] for i in range(4)},
            "discrete_inputs": dins,
            "io_setup": io,
            "manufacturer_specific": mfg,
            "motion": {"moving": self.moving(), "mode": self.mode,
                       "homing": self.homing, "position": self.x,
                       "velocity": self.v, "target": self.target,
                       "trip_armed": self.trip_origin is not None},
            "program": {"running": False, "paused": False, "stored": []},
            "nvm": nvm,
            "nvm_save_count": self.saves,
            "device_identification": {str(k): v for k, v in DEVICE_ID.items()},
        }


DEVICE_ID = {
    0: VENDOR_NAME, 1: PRODUCT_CODE, 2: MAJOR_MINOR_REV, 3: VENDOR_URL,
    4: PRODUCT_NAME, 5: SERIAL_NUMBER, 6: USER_APP_NAME,
}


# ---------------------------------------------------------------------------
# Manufacturer specific functions (FC 65 / 66)
# ---------------------------------------------------------------------------

CLOSED_LOOP_MNEMONICS = {"EL", "MU", "FS", "HF", "AV"}
SIMPLE_SETTINGS = {   # mnemonic -> (min, max)
    "AO": (0, 65535), "RD": (0, 1), "AJ": (1, 999), "AT": (0, 1),
    "DJ": (1, 999), "DT": (0, 1), "BE": (0, 1), "BL": (0, INT32_MAX),
    "BM": (0, 1), "FL": (0, 1),
}


def decode_mnemonic(raw4):
    """4 request bytes, sent in reverse order -> mnemonic text."""
    rev = bytes(reversed(raw4))
    txt = rev.replace(b" ", b"").replace(b"\x00", b"")
    try:
        return txt.decode("ascii").upper()
    except UnicodeDecodeError:
        return None


def param_text(data):
    try:
        txt = data.decode("ascii")
    except UnicodeDecodeError:
        raise MBException(3)
    txt = txt.strip(" \r\n\t\x00")
    if txt.startswith("="):
        txt = txt[1:]
    return txt.strip()


def param_ints(txt, nmin, nmax):
    if txt == "":
        parts = []
    else:
        parts = [s.strip() for s in txt.split(",")]
    if not nmin <= len(parts) <= nmax:
        raise MBException(3)
    out = []
    for s in parts:
        body = s[1:] if s[:1] in "+-" else s
        if not body.isdigit():
            raise MBException(3)
        out.append(int(s))
    return out


class MfgFunctions:
    def __init__(self, drive):
        self.d = drive

    @staticmethod
    def _split_point(mn, prefixes):
        for pre, lo, hi in prefixes:
            if mn == pre:
                return pre, None
            if mn.startswith(pre) and mn[len(pre):].isdigit():
                n = int(mn[len(pre):])
                if lo <= n <= hi:
                    return pre, n
                return None, None
        return None, None

    def classify(self, mn):
        """-> (kind, point) or (None, None) for unknown mnemonic."""
        if mn is None:
            return None, None
        if mn in ("\x1b", "CP", "EX", "PS", "RS", "E", "UG"):
            return "wo", None
        if mn in ("IT", "VT"):
            return "ro", None
        if mn in SIMPLE_SETTINGS or mn in ("TR", "LS"):
            return "rw", None
        pre, n = self._split_point(mn, [("IS", 1, 5), ("OS", 1, 3)])
        if pre:
            return pre, n
        if len(mn) == 2 and mn[0] == "S" and mn[1] in "1234":
            return "S", int(mn[1])
        return None, None

    # ---------------------------------------------------------------- read
    def read(self, mn):
        d = self.d
        kind, n = self.classify(mn)
        if kind is None or kind == "wo":
            raise MBException(2)
        io = d.cur["io"]
        if mn == "IT":
            b, m = d.temperatures()
            return "%d,%d" % (b, m)
        if mn == "VT":
            return "24,48"
        if mn in SIMPLE_SETTINGS:
            return str(d.p[mn])
        if mn == "TR":
            t = d.trip
            return "%d, %d, %d" % (t["distance"], t["address"], t["option"])
        if mn == "LS":
            ls = d.cur["ls"]
            return "; ".join("%d, %d, %d" % (k, ls[k]["position"], ls[k]["enabled"])
                             for k in (0, 1))
        if kind == "IS":
            lines = [n] if n else [1, 2, 3, 4, 5]
            return "; ".join(self._fmt_line(i) for i in lines)
        if kind == "OS":
            lines = [n] if n else [1, 2, 3]
            return "; ".join(self._fmt_line(i) for i in lines)
        if kind == "S":
            c = io[n]
            return "%d, %d, %d" % (c["type"], c["active"], c["sink_source"])
        raise MBException(2)

    def _fmt_line(self, i):
        c = self.d.cur["io"][i]
        if i == 5:
            return "5, %d, %d" % (c["mode"], c["range"])
        return "%d, %d, %d" % (i, c["type"], c["active"])

    # ---------------------------------------------------------------- write
    def write(self, mn, data):
        d = self.d
        kind, n = self.classify(mn)
        if kind is None or kind == "ro":
            raise MBException(2)
        txt = param_text(data)
        if mn == "\x1b":
            d.stop()
            return
        if mn == "CP":
            if d.moving():
                raise MBException(4, ERR_IP_CP_WHILE_MOVING)
            return                      # program space is (already) empty
        if mn == "EX":
            if txt == "":
                raise MBException(3)
            if txt.isdigit():
                # no program stored at any address
                raise MBException(4, ERR_ILLEGAL_PROG_ADDR)
            if len(txt) == 2 and txt[0].isalpha() and txt.isalnum():
                raise MBException(4, ERR_UNKNOWN_LABEL)
            raise MBException(3)
        if mn in ("PS", "RS", "E"):
            return                      # no program running: no-op
        if mn == "UG":
            (key,) = param_ints(txt, 1, 1)
            if key != UPGRADE_KEY:
                raise MBException(3)
            d.upgrade_mode = True
            return
        if mn in SIMPLE_SETTINGS:
            (val,) = param_ints(txt, 1, 1)
            lo, hi = SIMPLE_SETTINGS[mn]
            if not lo <= val <= hi:
                raise MBException(3)
            d.p[mn] = val
            return
        if mn == "TR":
            vals = param_ints(txt, 1, 3)
            vals += [0] * (3 - len(vals))
            if not INT32_MIN <= vals[0] <= INT32_MAX:
                raise MBException(3)
            if not (0 <= vals[1] <= 65535 and 0 <= vals[2] <= 65535):
                raise MBException(3)
            d.trip = {"distance": vals[0], "address": vals[1], "option": vals[2]}
            return
        if mn == "LS":
            dr, pos, en = param_ints(txt, 3, 3)
            if dr not in (0, 1) or en not in (0, 1):
                raise MBException(3)
            if not INT32_MIN <= pos <= INT32_MAX:
                raise MBException(3)
            d.cur["ls"][dr] = {"position": pos, "enabled": en}
            return
        if kind in ("IS", "OS"):
            vals = param_ints(txt, 2, 3)
            if len(vals) == 3:
                line, t, a = vals
                if n is not None and line != n:
                    raise MBException(3)
            else:
                if n is None:
                    raise MBException(3)
                line = n
                t, a = vals
            if kind == "IS":
                self._set_input(line, t, a)
            else:
                self._set_output(line, t, a)
            return
        if kind == "S":
            vals = param_ints(txt, 2, 3)
            t, a = vals[0], vals[1]
            k = vals[2] if len(vals) == 3 else d.cur["io"][n]["sink_source"]
            if k not in (0, 1):
                raise MBException(3)
            if t in OUTPUT_TYPES or t in (26, 27):
                self._set_output(n, t, a)
            else:
                self._set_input(n, t, a)
            d.cur["io"][n]["sink_source"] = k
            return
        raise MBException(2)

    def _set_input(self, line, t, a):
        io = self.d.cur["io"]
        if line == 5:
            if t not in ANALOG_MODES or a not in (0, 1):
                raise MBException(3)
            io[5] = {"mode": t, "range": a}
            return
        if not 1 <= line <= 4 or t not in INPUT_TYPES or a not in (0, 1):
            raise MBException(3)
        io[line]["type"] = t
        io[line]["active"] = a

    def _set_output(self, line, t, a):
        io = self.d.cur["io"]
        if not 1 <= line <= 3 or t not in OUTPUT_TYPES or a not in (0, 1):
            raise MBException(3)
        if t == 28 and line != 3:
            raise MBException(3)
        io[line]["type"] = t
        io[line]["active"] = a


# ---------------------------------------------------------------------------
# Modbus PDU processing
# ---------------------------------------------------------------------------

class ModbusServer:
    def __init__(self, drive):
        self.d = drive
        self.mfg = MfgFunctions(drive)
        self.counters = {
            "connections_accepted": 0, "connections_refused": 0,
            "frames_received": 0, "frames_dropped": 0,
            "responses_sent": 0, "exceptions_sent": 0,
            "exceptions_by_code": {"1": 0, "2": 0, "3": 0, "4": 0},
            "requests_by_function": {},
        }
        self.active_connections = 0

    def process(self, pdu):
        """Returns response PDU bytes."""
        fc = pdu[0]
        key = "%d" % fc
        rbf = self.counters["requests_by_function"]
        rbf[key] = rbf.get(key, 0) + 1
        self.d.update()
        try:
            handler = {
                0x01: self.fc_read_coils,
                0x02: self.fc_read_inputs,
                0x03: self.fc_read_holding,
                0x05: self.fc_write_coil,
                0x10: self.fc_write_multiple,
                0x2B: self.fc_mei,
                0x41: self.fc_mfg_read,
                0x42: self.fc_mfg_write,
            }.get(fc)
            if handler is None:
                raise MBException(1)
            return handler(pdu)
        except MBException as e:
            if e.mcode_err:
                self.d.latch_error(e.mcode_err)
            self.counters["exceptions_sent"] += 1
            c = str(e.code)
            self.counters["exceptions_by_code"][c] = \
                self.counters["exceptions_by_code"].get(c, 0) + 1
            return bytes([(fc | 0x80) & 0xFF, e.code])
        except Exception:           # never let one frame kill the server
            traceback.print_exc(file=sys.stderr)
            self.counters["exceptions_sent"] += 1
            self.counters["exceptions_by_code"]["4"] += 1
            return bytes([(fc | 0x80) & 0xFF, 4])

    # ----------------------------------------------------------- bits
    def _bit_request(self, pdu):
        if len(pdu) < 5:
            raise MBException(3)
        start = int.from_bytes(pdu[1:3], "big")
        qty = int.from_bytes(pdu[3:5], "big")
        if not 1 <= qty <= 2000:
            raise MBException(3)
        return start, qty

    @staticmethod
    def _pack_bits(bits):
        out = bytearray((len(bits) + 7) // 8)
        for i, b in enumerate(bits):
            if b:
                out[i // 8] |= 1 << (i % 8)
        return bytes(out)

    def fc_read_coils(self, pdu):
        start, qty = self._bit_request(pdu)
        if start + qty > 4:
            raise MBException(2)
        bits = [self.d.output_state(start + i + 1) for i in range(qty)]
        data = self._pack_bits(bits)
        return bytes([0x01, len(data)]) + data

    def fc_read_inputs(self, pdu):
        start, qty = self._bit_request(pdu)
        if 0x002D <= start <= 0x0030:
            start -= 0x002D         # alias used by the manual's example
        if start + qty > 4:
            raise MBException(2)
        bits = [self.d.input_state(start + i + 1) for i in range(qty)]
        data = self._pack_bits(bits)
        return bytes([0x02, len(data)]) + data

    def fc_write_coil(self, pdu):
        if len(pdu) < 5:
            raise MBException(3)
        addr = int.from_bytes(pdu[1:3], "big")
        val = int.from_bytes(pdu[3:5], "big")
        if val not in (0x0000, 0xFF00):
            raise MBException(3)
        if addr > 3:
            raise MBException(2)
        self.d.out_latch[addr] = 1 if val == 0xFF00 else 0
        return bytes(pdu[:5])

    # ----------------------------------------------------------- registers
    def fc_read_holding(self, pdu):
        if len(pdu) < 5:
            raise MBException(3)
        start = int.from_bytes(pdu[1:3], "big")
        qty = int.from_bytes(pdu[3:5], "big")
        if not 1 <= qty <= 125:
            raise MBException(3)
        for a in range(start, start + qty):
            if a not in WORD_MAP:
                raise MBException(2)
        cache = {}
        out = bytearray([0x03, qty * 2])
        for a in range(start, start + qty):
            reg, wi = WORD_MAP[a]
            name = reg[2]
            if name not in cache:
                cache[name] = self.d.reg_value(name) & 0xFFFFFFFF
            word = (cache[name] >> (16 * wi)) & 0xFFFF
            out += word.to_bytes(2, "big")
        if "ER" in cache:           # reading ER clears the error (manual 5)
            self.d.er = 0
            self.d.ef = 0
        return bytes(out)

    def fc_write_multiple(self, pdu):
        if len(pdu) < 6:
            raise MBException(3)
        start = int.from_bytes(pdu[1:3], "big")
        qty = int.from_bytes(pdu[3:5], "big")
        bc = pdu[5]
        if not 1 <= qty <= 123 or bc != qty * 2 or len(pdu) < 6 + bc:
            raise MBException(3)
        words = [int.from_bytes(pdu[6 + 2 * i:8 + 2 * i], "big") for i in range(qty)]
        # split into variables: each must be entered at its first register
        writes = []
        a = start
        i = 0
        while i < qty:
            ent = WORD_MAP.get(a)
            if ent is None:
                raise MBException(2)
            reg, wi = ent
            addr, n, name, access, signed = reg
            if wi != 0 or access == "ro":
                raise MBException(2)
            take = min(n, qty - i)
            if n == 2 and take == 2:
                raw = words[i] | (words[i + 1] << 16)
                val = raw - 2 ** 32 if (signed and raw & 0x80000000) else raw
            elif n == 2:
                raw = words[i]
                val = raw - 0x10000 if (signed and raw & 0x8000) else raw
            else:
                val = words[i]
            writes.append((name, val))
            a += take
            i += take
        pending = {}
        for name, val in writes:
            self.d.check_write(name, val, pending)
            pending[name] = val
        for name, val in writes:
            self.d.apply_write(name, val)
        return bytes([0x10]) + pdu[1:5]

    # ----------------------------------------------------------- device id
    def fc_mei(self, pdu):
        if len(pdu) < 2:
            raise MBException(3)
        if pdu[1] != 0x0E:
            raise MBException(1)
        if len(pdu) < 4:
            raise MBException(3)
        code, obj = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise MBException(3)
        if code == 4:
            if obj not in DEVICE_ID:
                raise MBException(2)
            ids = [obj]
        else:
            last = 2 if code == 1 else 6
            if obj > last:
                obj = 0
            ids = list(range(obj, last + 1))
        out = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)])
        for oid in ids:
            v = DEVICE_ID[oid].encode("ascii")
            out += bytes([oid, len(v)]) + v
        return bytes(out)

    # ----------------------------------------------------------- mfg
    def fc_mfg_read(self, pdu):
        if len(pdu) < 5:
            raise MBException(3)
        mn = decode_mnemonic(pdu[1:5])
        txt = self.mfg.read(mn).encode("ascii")
        return bytes([0x41, len(txt)]) + txt

    def fc_mfg_write(self, pdu):
        if len(pdu) < 6:
            raise MBException(3)
        bc = pdu[5]
        if bc > 28 or len(pdu) < 6 + bc:
            raise MBException(3)
        mn = decode_mnemonic(pdu[1:5])
        self.mfg.write(mn, bytes(pdu[6:6 + bc]))
        return bytes([0x42, bc]) + bytes(pdu[1:5])


# ---------------------------------------------------------------------------
# TCP transport
# ---------------------------------------------------------------------------

class App:
    def __init__(self, state_file):
        self.drive = Drive()
        self.mb = ModbusServer(self.drive)
        self.state_file = state_file
        self.writers = set()

    async def handle(self, reader, writer):
        c = self.mb.counters
        if self.mb.active_connections >= MAX_CONNECTIONS:
            c["connections_refused"] += 1
            writer.close()
            return
        self.mb.active_connections += 1
        c["connections_accepted"] += 1
        self.writers.add(writer)
        try:
            while True:
                hdr = await reader.readexactly(6)
                tid = hdr[0:2]
                pid = int.from_bytes(hdr[2:4], "big")
                length = int.from_bytes(hdr[4:6], "big")
                if length == 0:
                    c["frames_dropped"] += 1
                    continue
                if length > 254:
                    c["frames_dropped"] += 1
                    break               # cannot frame this stream: close
                body = await reader.readexactly(length)
                c["frames_received"] += 1
                if pid != 0 or length < 2:
                    c["frames_dropped"] += 1
                    continue
                uid = body[0]
                resp = self.mb.process(body[1:])
                adu = tid + b"\x00\x00" + (len(resp) + 1).to_bytes(2, "big") \
                    + bytes([uid]) + resp
                writer.write(adu)
                c["responses_sent"] += 1
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            pass
        finally:
            self.mb.active_connections -= 1
            self.writers.discard(writer)
            try:
                writer.close()
            except Exception:
                pass

    def dump_state(self):
        if not self.state_file:
            return
        try:
            self.drive.update()
            st = self.drive.snapshot()
            st["diagnostic_counters"] = copy.deepcopy(self.mb.counters)
            st["diagnostic_counters"]["active_connections"] = self.mb.active_connections
            tmp = self.state_file + ".tmp"
            with open(tmp, "w") as f:
                json.dump(st, f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except Exception as e:      # pragma: no cover
            print("state dump failed: %s" % e, file=sys.stderr)

    async def ticker(self):
        while True:
            await asyncio.sleep(TICK)
            try:
                self.drive.update()
            except Exception as e:  # pragma: no cover
                print("motion update failed: %s" % e, file=sys.stderr)

    async def main(self, host, port):
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        loop.add_signal_handler(signal.SIGUSR1, self.dump_state)
        loop.add_signal_handler(signal.SIGTERM, stop.set)
        loop.add_signal_handler(signal.SIGINT, stop.set)
        server = await asyncio.start_server(self.handle, host, port)
        actual = server.sockets[0].getsockname()[1]
        sys.stdout.write("listening tcp %s:%d\n" % (host, actual))
        sys.stdout.flush()
        tick = asyncio.create_task(self.ticker())
        await stop.wait()
        server.close()
        for w in list(self.writers):
            try:
                w.close()
            except Exception:
                pass
        tick.cancel()
        self.dump_state()


def main():
    ap = argparse.ArgumentParser(description="LMD Ethernet Modbus/TCP simulator")
    ap.add_argument("--listen", required=True, help="127.0.0.1:PORT")
    ap.add_argument("--state", default=None, help="JSON state dump file")
    a = ap.parse_args()
    host, _, port = a.listen.rpartition(":")
    if host not in ("127.0.0.1", "localhost", "::1", "[::1]"):
        print("refusing to bind to non-loopback address %r" % host, file=sys.stderr)
        sys.exit(2)
    host = host.strip("[]")
    if host == "localhost":
        host = "127.0.0.1"
    app = App(a.state)
    asyncio.run(app.main(host, int(port)))


if __name__ == "__main__":
    main()
