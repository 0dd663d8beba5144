#!/usr/bin/env python3
"""MDrive Plus2 Motion Control (Ethernet, internal encoder fitted) -- MODBUS/TCP server.

Written from the "MODBUS/TCP Fieldbus Manual, MDrive Motion Control Products"
(rev R040611) and the public MODBUS specifications.  Standard library only.

    python3 sim.py --listen 127.0.0.1:0 [--state FILE]

See DECISIONS.md for every place where the manual was silent or wrong.
"""
import argparse
import asyncio
import json
import math
import os
import random
import signal
import struct
import sys
import time

# ---------------------------------------------------------------------------
# constants
# ---------------------------------------------------------------------------
EX_ILLEGAL_FUNCTION = 0x01
EX_ILLEGAL_ADDRESS = 0x02
EX_ILLEGAL_VALUE = 0x03
EX_DEVICE_FAILURE = 0x04

ENCODER_LINES = 512                 # internal encoder, 512 lines
ENCODER_CPR = ENCODER_LINES * 4     # 2048 counts / revolution (quadrature)

MS_TABLE = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250,
            256, 180, 108, 127)

DEVICE_ID = {
    0x00: b"SEM USA",
    0x01: b"MDI1FRD23A7-EQ",
    0x02: b"4.0.0.0",
    0x03: b"www.imshome.com",
    0x04: b"MDrive Ethernet",
    0x05: b"110433217",
    0x06: b"ASI 4.0.1.2",
}

INPUT_FUNCS = {0, 1, 2, 3, 5, 7, 8, 11}
OUTPUT_FUNCS = {16, 17, 18, 20, 21, 23}          # 24, 25 are Hybrid only
HYBRID_ONLY_OUTPUT_FUNCS = {24, 25}
UNIQUE_INPUT_FUNCS = {1, 2, 3, 5, 7, 8, 11}      # only one point may carry these
CLOCK_IN_FUNCS = {33, 34, 35}
CLOCK_OUT_FUNCS = {49, 50, 51}

S32_MIN, S32_MAX = -2147483648, 2147483647


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# ---------------------------------------------------------------------------
# register map (MDrive Plus2; the Hybrid block 0x008E-0x00A7 is absent)
# kind: rw = read/write setting, ro = read only, cmd = write triggers an action,
#       mot = motion command (write triggers motion, read returns last command)
# ---------------------------------------------------------------------------
class Item:
    __slots__ = ("addr", "n", "name", "kind", "signed", "lo", "hi", "allowed")

    def __init__(self, addr, n, name, kind, signed=False, lo=0, hi=0xFFFF,
                 allowed=None):
        self.addr, self.n, self.name, self.kind = addr, n, name, kind
        self.signed, self.lo, self.hi, self.allowed = signed, lo, hi, allowed


ITEMS = [
    Item(0x0000, 2, "A", "rw", False, 91, 1525878997),
    Item(0x0005, 2, "C1", "rw", True, S32_MIN, S32_MAX),
    Item(0x0007, 2, "C2", "rw", True, S32_MIN, S32_MAX),
    Item(0x0009, 1, "CE", "rw", False, 0, 1),
    Item(0x000B, 1, "CM", "rw", False, 0, 1),
    Item(0x000F, 1, "D1", "rw", False, 0, 255),
    Item(0x0010, 1, "D2", "rw", False, 0, 255),
    Item(0x0011, 1, "D3", "rw", False, 0, 255),
    Item(0x0012, 1, "D4", "rw", False, 0, 255),
    Item(0x0013, 1, "D5", "rw", False, 0, 255),
    Item(0x0018, 2, "D", "rw", False, 91, 1525878997),
    Item(0x001A, 1, "DB", "rw", False, 0, 65000),
    Item(0x001B, 1, "DC", "cmd", False, 1, 12),
    Item(0x001C, 1, "DE", "rw", False, 0, 1),
    Item(0x001E, 1, "EE", "rw", False, 0, 1),
    Item(0x001F, 1, "EF", "ro"),
    Item(0x0021, 1, "ER", "rw", False, 0, 0),
    Item(0x0029, 1, "HC", "rw", False, 0, 100),
    Item(0x002B, 1, "HM", "rw", False, 1, 4),
    Item(0x002C, 1, "HT", "rw", False, 0, 65535),
    Item(0x002D, 1, "I1", "ro"),
    Item(0x002E, 1, "I2", "ro"),
    Item(0x002F, 1, "I3", "ro"),
    Item(0x0030, 1, "I4", "ro"),
    Item(0x0031, 1, "I5", "ro"),
    Item(0x0032, 1, "I6", "ro"),
    Item(0x0037, 1, "IC", "cmd", False, 1, 12),
    Item(0x003A, 1, "IL", "ro"),
    Item(0x003B, 1, "IN", "ro"),
    Item(0x003F, 1, "JE", "rw", False, 0, 1),
    Item(0x0042, 1, "LM", "rw", False, 1, 6),
    Item(0x0043, 2, "MA", "mot", True, S32_MIN, S32_MAX),
    Item(0x0045, 1, "MP", "ro"),
    Item(0x0046, 2, "MR", "mot", True, S32_MIN, S32_MAX),
    Item(0x0048, 1, "MS", "rw", False, 1, 256, MS_TABLE),
    Item(0x0049, 1, "MT", "rw", False, 0, 65000),
    Item(0x004A, 1, "MV", "ro"),
    Item(0x004B, 1, "O1", "rw", False, 0, 1),
    Item(0x004C, 1, "O2", "rw", False, 0, 1),
    Item(0x004D, 1, "O3", "rw", False, 0, 1),
    Item(0x004E, 1, "O4", "rw", False, 0, 1),
    Item(0x0055, 1, "OL", "rw", False, 0, 15),
    Item(0x0056, 1, "OT", "rw", False, 0, 15),
    Item(0x0057, 2, "P", "rw", True, S32_MIN, S32_MAX),
    Item(0x0059, 2, "PC", "ro", True),
    Item(0x005C, 1, "PM", "rw", False, 0, 1),
    Item(0x005F, 2, "R1", "rw", True, S32_MIN, S32_MAX),
    Item(0x0061, 2, "R2", "rw", True, S32_MIN, S32_MAX),
    Item(0x0063, 2, "R3", "rw", True, S32_MIN, S32_MAX),
    Item(0x0065, 2, "R4", "rw", True, S32_MIN, S32_MAX),
    Item(0x0067, 1, "RC", "rw", False, 1, 100),
    Item(0x0076, 1, "S", "cmd", False, 0, 0xFFFF),
    Item(0x0077, 1, "SF", "rw", False, 0, 65000),
    Item(0x0078, 2, "SL", "mot", True, -5000000, 5000000),
    Item(0x007A, 1, "SM", "rw", False, 0, 1),
    Item(0x007B, 1, "ST", "rw", False, 0, 0),
    Item(0x007D, 1, "TE", "rw", False, 0, 16, (0, 16)),
    Item(0x0085, 2, "V", "ro", True),
    Item(0x0088, 1, "VC", "ro"),
    Item(0x0089, 2, "VI", "rw", False, 1, 4999999),
    Item(0x008B, 2, "VM", "rw", False, 2, 5000000),
] + [Item(0x00A8 + 2 * i, 2, "V%d" % (i + 1), "rw", True, S32_MIN, S32_MAX)
     for i in range(8)]

ITEM_AT = {}          # every register address -> (item, word index)
ITEM_BY_NAME = {}
for _it in ITEMS:
    ITEM_BY_NAME[_it.name] = _it
    for _k in range(_it.n):
        ITEM_AT[_it.addr + _k] = (_it, _k)

LIVE_NAMES = ("C2", "P", "I5", "I6")      # measured values that move by themselves
CONFIG_NAMES = [it.name for it in ITEMS if it.kind == "rw"
                and it.name not in ("ER", "ST", "O1", "O2", "O3", "O4", "OL", "OT",
                                    "C1", "C2", "P")]

# ---------------------------------------------------------------------------
# the drive
# ---------------------------------------------------------------------------
# Stored MCode programs of the customer (simulated).  Ops:
#   ("MR", counts) relative move, ("WAIT",) wait for motion end,
#   ("DELAY", s), ("IC", var-index)
PROGRAMS = {
    "A1": [("MR", 4096), ("WAIT",), ("DELAY", 0.25), ("MR", -4096), ("WAIT",)],
    "A3": [("MR", 2048), ("WAIT",), ("DELAY", 0.1), ("MR", -2048), ("WAIT",),
           ("IC", 4)],
}
PROGRAM_ADDR = {"1": "A1", "64": "A3"}


class Drive:
    def __init__(self):
        rnd = random.Random()
        self.rnd = rnd
        # --- commissioned configuration (customer's machine) -----------------
        self.v = {
            "A": 250000, "D": 400000, "CE": 1, "CM": 0,
            "D1": 5, "D2": 5, "D3": 2, "D4": 0, "D5": 10,
            "DB": 5, "DE": 1, "EE": 1, "EF": 0, "ER": 0,
            "HC": 10, "HM": 3, "HT": 250, "JE": 0, "LM": 2,
            "MS": 128, "MT": 100, "PM": 1, "RC": 60, "SF": 25, "SM": 0,
            "ST": 0, "TE": 0, "VI": 1500, "VM": 150000,
            "R1": 1200, "R2": -35000, "R3": 0, "R4": 17,
            "V1": 25600, "V2": -12800, "V3": 3, "V4": 0,
            "V5": 0, "V6": 0, "V7": 0, "V8": 0,
            "MA": 0, "MR": 0, "SL": 0, "PC": 0,
        }
        # manufacturer specific parameters (stored as parsed tuples)
        self.mfg = {
            "S1": (1, 0, 0),      # home input, active low, sinking
            "S2": (0, 0, 0),      # general purpose input, active low, sinking
            "S3": (17, 1, 0),     # "moving" output, active high, sinking
            "S4": (16, 1, 0),     # general purpose output, active high, sinking
            "S7": (33, 1),        # step/direction clock input
            "S8": (33, 1),
            "CR": 2.5,            # clock ratio
            "S5": (9, 1),         # analog input: voltage 0-10 V
            "S13": (60, 0),       # capture input, active low
            "TR": 12800,          # trip on relative position
        }
        self.out_latch = {1: 0, 2: 0, 3: 0, 4: 1}   # O4 was left ON by the machine
        # bench wiring: physical level of each point when used as input
        # point 2 is jumpered to ground on the bench, the others are open
        self.bench_jumper_low = {1: False, 2: True, 3: False, 4: False}
        # --- motion / position model ----------------------------------------
        self.c1 = 1310720.0          # clock pulses generated so far
        self.shaft_rev = 51.2        # absolute shaft angle [rev]
        self.c2_off = -104858 + 3    # encoder counter offset
        self.p_enc_off = 0           # P = encoder counts + offset when EE=1
        self.p_steps = 0.0           # P in steps when EE=0
        self.p_enc_off = 10240 - round(self.shaft_rev * ENCODER_CPR)
        self.mode = None             # None | "pos" | "slew" | "stop"
        self.vel = 0.0               # signed profile velocity [steps/s]
        self.accel_state = 0         # 1 accelerating, -1 decelerating, 0 const
        self.target_steps = 0.0
        self.slew_target = 0.0
        self.trip_ref = None
        # --- live values -------------------------------------------------------
        self.enc_jit = 0
        self.analog = 502.0
        self.analog_drift_phase = rnd.random() * 6.28
        self.i5 = 502
        # --- program -----------------------------------------------------------
        self.prog = None             # dict(name, ops, pc, paused, delay_until)
        # NVM image (what S saved)
        self.nvm = self.config_snapshot()
        self.t_last = time.monotonic()
        self.t0 = self.t_last

    # ------------------------------------------------------------------ helpers
    def spr(self):
        return self.v["MS"] * 200

    def enc_exact(self):
        return round(self.shaft_rev * ENCODER_CPR)

    def config_snapshot(self):
        d = {k: self.v[k] for k in CONFIG_NAMES}
        for k, val in self.mfg.items():
            d[k] = self.mfg_format(k, val)
        return d

    def point_cfg(self, pt):
        return self.mfg["S%d" % pt]

    def point_is_output(self, pt):
        return self.point_cfg(pt)[0] >= 16

    def point_state(self, pt):
        """logic state (1 = active) of an I/O point."""
        func, act_hi, source = self.point_cfg(pt)
        if func >= 16:
            if func == 16:
                return self.out_latch[pt]
            if func == 17:
                return 1 if self.mode else 0
            if func == 18:
                return self.v["EF"]
            if func == 20:
                return 1 if self.accel_state else 0
            if func == 23:
                return 1 if self.mode == "pos" else 0
            return 0
        if self.bench_jumper_low[pt]:
            level_high = False
        else:
            level_high = not source    # open sinking input is pulled up
        return 1 if (level_high == bool(act_hi)) else 0

    def inputs_bcd(self):
        return sum(self.point_state(p) << (p - 1) for p in range(1, 5))

    def outputs_bcd(self):
        return sum((self.point_state(p) if self.point_is_output(p) else 0) << (p - 1)
                   for p in range(1, 5))

    def p_value(self, noisy=True):
        if self.v["EE"]:
            return self.enc_exact() + self.p_enc_off + (self.enc_jit if noisy else 0)
        return int(round(self.p_steps))

    # ------------------------------------------------------------------ values
    def get(self, name, consume=True):
        v = self.v
        if name == "C1":
            return int(round(self.c1))
        if name == "C2":
            return self.enc_exact() + self.c2_off + self.enc_jit
        if name == "P":
            return self.p_value()
        if name in ("I1", "I2", "I3", "I4"):
            return self.point_state(int(name[1]))
        if name == "I5":
            return self.i5
        if name == "I6":
            return 1 if ((self.enc_exact() + self.enc_jit) % ENCODER_CPR) in (0, 1) else 0
        if name in ("IL", "IN"):
            return self.inputs_bcd()
        if name == "MP":
            return 1 if self.mode == "pos" else 0
        if name == "MV":
            return 1 if self.mode else 0
        if name == "VC":
            return 1 if self.accel_state else 0
        if name == "V":
            return int(round(self.vel))
        if name in ("O1", "O2", "O3", "O4"):
            pt = int(name[1])
            return self.point_state(pt) if self.point_is_output(pt) else 0
        if name in ("OL", "OT"):
            return self.outputs_bcd()
        if name in ("DC", "IC", "S"):
            return 0
        if name == "ER":
            val = v["ER"]
            if consume and val:
                v["ER"] = 0          # reading ER clears it (and the error flag)
                v["EF"] = 0
            return val
        return v[name]

    def set_error(self, code):
        self.v["ER"] = code
        self.v["EF"] = 1

    # ------------------------------------------------------------------ writes
    def check_write(self, it, val, pending):
        """Validate a write of decoded value val; pending holds other values of
        the same request (for cross-checks).  Raises ModbusError."""
        name = it.name
        if it.kind == "ro":
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        if name in ("O1", "O2", "O3", "O4"):
            pt = int(name[1])
            if self.point_cfg(pt)[0] != 16:
                raise ModbusError(EX_ILLEGAL_ADDRESS)
        if val < it.lo or val > it.hi:
            raise ModbusError(EX_ILLEGAL_VALUE)
        if it.allowed is not None and val not in it.allowed:
            raise ModbusError(EX_ILLEGAL_VALUE)

        def cur(n):
            return pending.get(n, self.v[n])
        if name in ("VI", "VM"):
            if not cur("VI") < cur("VM"):
                raise ModbusError(EX_ILLEGAL_VALUE)
        if name == "HT" and val == 1:
            raise ModbusError(EX_ILLEGAL_VALUE)
        if name in ("HT", "MT"):
            if cur("HT") + cur("MT") > 65535:
                raise ModbusError(EX_ILLEGAL_VALUE)
        if name in ("C1", "C2", "P", "MS", "EE") and self.mode:
            raise ModbusError(EX_DEVICE_FAILURE)   # not while the axis moves
        if it.kind == "mot":
            if not cur("DE"):
                raise ModbusError(EX_DEVICE_FAILURE)
            if name in ("MA", "MR") and self.mode is not None:
                raise ModbusError(EX_DEVICE_FAILURE)
            if name == "SL" and self.mode in ("pos", "stop"):
                raise ModbusError(EX_DEVICE_FAILURE)
            if self.prog is not None:
                raise ModbusError(EX_DEVICE_FAILURE)

    def apply_write(self, it, val):
        name = it.name
        v = self.v
        if name == "C1":
            self.c1 = float(val)
        elif name == "C2":
            self.c2_off = val - self.enc_exact()
        elif name == "P":
            if v["EE"]:
                self.p_enc_off = val - self.enc_exact()
            else:
                self.p_steps = float(val)
            self.enc_jit = 0
        elif name == "EE":
            if val != v["EE"]:
                pv = self.p_value(noisy=False)
                v["EE"] = val
                if val:
                    self.p_enc_off = pv - self.enc_exact()
                else:
                    self.p_steps = float(pv)
        elif name in ("O1", "O2", "O3", "O4"):
            self.out_latch[int(name[1])] = val
        elif name in ("OL", "OT"):
            for pt in range(1, 5):
                if self.point_cfg(pt)[0] == 16:
                    self.out_latch[pt] = (val >> (pt - 1)) & 1
        elif name in ("DC", "IC"):
            var = ("R%d" % val) if val <= 4 else ("V%d" % (val - 4))
            nv = v[var] + (1 if name == "IC" else -1)
            if nv > S32_MAX:
                nv = S32_MIN
            if nv < S32_MIN:
                nv = S32_MAX
            v[var] = nv
        elif name == "S":
            self.nvm = self.config_snapshot()
        elif name == "ER":
            v["ER"] = 0
            v["EF"] = 0
        elif name == "DE":
            v["DE"] = val
            if not val and self.mode:
                self.abort_motion()
        elif name == "TE":
            v["TE"] = val
            self.trip_ref = self.p_value(noisy=False) if val & 16 else None
        elif name == "MA":
            v["MA"] = val
            self.start_move(val - self.p_value(noisy=False))
        elif name == "MR":
            v["MR"] = val
            self.start_move(val)
        elif name == "SL":
            v["SL"] = val
            self.start_slew(val)
        else:
            v[name] = val

    # ------------------------------------------------------------------ motion
    def units_to_steps(self, units):
        if self.v["EE"]:
            return units * self.spr() / ENCODER_CPR
        return float(units)

    def start_move(self, delta_units):
        if delta_units == 0:
            return
        self.target_steps = self.c1 + self.units_to_steps(delta_units)
        self.mode = "pos"
        self.vel = math.copysign(float(self.v["VI"]), delta_units)
        self.accel_state = 1

    def start_slew(self, vel):
        if vel == 0:
            if self.mode == "slew":
                self.slew_target = 0.0
            return
        self.slew_target = float(vel)
        if self.mode is None:
            self.mode = "slew"
            self.vel = math.copysign(min(float(self.v["VI"]), abs(vel)), vel)

    def stop_decel(self):
        if self.mode in ("pos", "slew"):
            self.mode = "stop"

    def abort_motion(self):
        self.mode = None
        self.vel = 0.0
        self.accel_state = 0

    def advance(self, dsteps):
        self.c1 += dsteps
        self.p_steps += dsteps
        self.shaft_rev += dsteps / self.spr()

    def tick_motion(self, dt):
        if self.mode is None:
            return
        A, D = float(self.v["A"]), float(self.v["D"])
        VI, VM = float(self.v["VI"]), float(self.v["VM"])
        if self.mode == "pos":
            rem = self.target_steps - self.c1
            sgn = 1.0 if rem >= 0 else -1.0
            remabs = abs(rem)
            spd = abs(self.vel)
            dec_dist = max(0.0, (spd * spd - VI * VI) / (2 * D))
            if remabs <= dec_dist + spd * dt:
                spd = max(VI, spd - D * dt)
                self.accel_state = -1 if spd > VI else 0
            elif spd < VM:
                spd = min(VM, spd + A * dt)
                self.accel_state = 1
            else:
                spd = VM
                self.accel_state = 0
            step = spd * dt
            if step >= remabs:
                self.advance(rem)
                self.c1 = self.target_steps
                self.mode = None
                self.vel = 0.0
                self.accel_state = 0
                return
            self.advance(sgn * step)
            self.vel = sgn * spd
        elif self.mode == "slew":
            tgt = self.slew_target
            cur = self.vel
            if tgt == 0.0 or (cur != 0 and math.copysign(1, tgt) != math.copysign(1, cur)):
                # decelerate towards zero
                spd = abs(cur) - D * dt
                if spd <= VI:
                    if tgt == 0.0:
                        self.mode = None
                        self.vel = 0.0
                        self.accel_state = 0
                        return
                    cur = math.copysign(min(VI, abs(tgt)), tgt)
                    self.accel_state = 1
                else:
                    cur = math.copysign(spd, cur)
                    self.accel_state = -1
            else:
                if abs(cur) < abs(tgt):
                    cur = math.copysign(min(abs(tgt), abs(cur) + A * dt), tgt)
                    self.accel_state = 1 if abs(cur) < abs(tgt) else 0
                elif abs(cur) > abs(tgt):
                    cur = math.copysign(max(abs(tgt), abs(cur) - D * dt), tgt)
                    self.accel_state = -1 if abs(cur) > abs(tgt) else 0
                else:
                    self.accel_state = 0
            self.vel = cur
            self.advance(cur * dt)
        elif self.mode == "stop":
            spd = abs(self.vel) - D * dt
            if spd <= VI:
                self.advance(math.copysign(VI * dt, self.vel) if self.vel else 0.0)
                self.mode = None
                self.vel = 0.0
                self.accel_state = 0
                return
            self.accel_state = -1
            self.vel = math.copysign(spd, self.vel)
            self.advance(self.vel * dt)

    def tick_trip(self):
        if self.trip_ref is None or not (self.v["TE"] & 16):
            return
        tr = self.mfg["TR"]
        if tr == 0:
            return
        moved = self.p_value(noisy=False) - self.trip_ref
        if (tr > 0 and moved >= tr) or (tr < 0 and moved <= tr):
            self.v["TE"] &= ~16        # trip fired; must be re-enabled via 0x007D
            self.trip_ref = None

    def tick_program(self, now):
        pr = self.prog
        if pr is None or pr["paused"]:
            return
        while pr["pc"] < len(pr["ops"]):
            op = pr["ops"][pr["pc"]]
            if op[0] == "MR":
                if self.mode is not None:
                    return
                if not self.v["DE"]:
                    self.prog = None
                    return
                self.v["MR"] = op[1]
                self.start_move(op[1])
                pr["pc"] += 1
                return
            if op[0] == "WAIT":
                if self.mode is not None:
                    return
                pr["pc"] += 1
                continue
            if op[0] == "DELAY":
                if pr["delay_until"] is None:
                    pr["delay_until"] = now + op[1]
                if now < pr["delay_until"]:
                    return
                pr["delay_until"] = None
                pr["pc"] += 1
                continue
            if op[0] == "IC":
                var = "R%d" % op[1]
                self.v[var] = self.v[var] + 1 if self.v[var] < S32_MAX else S32_MIN
                pr["pc"] += 1
                continue
        self.prog = None

    def tick_live(self, now, dt):
        rnd = self.rnd
        # encoder jitter: a few counts around the true shaft position
        if rnd.random() < 0.3:
            self.enc_jit += rnd.choice((-1, 1))
            self.enc_jit = max(-2, min(2, self.enc_jit))
        # analog input: slow drift + noise, filtered by D5
        mode, rng = self.mfg["S5"]
        t = now - self.t0
        if mode == 9:
            volts = 4.905 + 0.03 * math.sin(t / 40.0 + self.analog_drift_phase)
            full = 5.0 if rng == 0 else 10.0
            raw = volts / full * 1023.0
        else:
            raw = 0.0 if rng == 1 else 1.2   # no current loop on the bench
        raw += rnd.gauss(0.0, 1.5)
        x = self.v["D5"]
        if x > 1:
            self.analog = ((x - 1) * self.analog + raw) / x
        else:
            self.analog = raw
        self.i5 = int(max(0, min(1023, round(self.analog))))

    def tick(self):
        now = time.monotonic()
        dt = min(0.1, max(0.0, now - self.t_last))
        self.t_last = now
        self.tick_motion(dt)
        self.tick_trip()
        self.tick_program(now)
        self.tick_live(now, dt)

    # ------------------------------------------------------------------ mfg
    @staticmethod
    def mfg_format(key, val):
        if key == "CR":
            return "%.3f" % val
        if key == "TR":
            return "%d" % val
        return ", ".join(str(x) for x in val)

    def mfg_read(self, key):
        return self.mfg_format(key, self.mfg[key]).encode("ascii")

    @staticmethod
    def parse_fields(data, nfields):
        try:
            s = data.decode("ascii")
        except UnicodeDecodeError:
            raise ModbusError(EX_ILLEGAL_VALUE)
        s = s.strip()
        if not s.startswith("="):
            raise ModbusError(EX_ILLEGAL_VALUE)
        parts = [p.strip() for p in s[1:].split(",")]
        if len(parts) != nfields:
            raise ModbusError(EX_ILLEGAL_VALUE)
        out = []
        for p in parts:
            if not p or not (p.isdigit() or (p[0] in "+-" and p[1:].isdigit())):
                raise ModbusError(EX_ILLEGAL_VALUE)
            out.append(int(p))
        return out

    def mfg_write(self, key, data):
        if key in ("S1", "S2", "S3", "S4"):
            a, b, c = self.parse_fields(data, 3)
            pt = int(key[1])
            if a in HYBRID_ONLY_OUTPUT_FUNCS:
                raise ModbusError(EX_ILLEGAL_VALUE)
            if a not in INPUT_FUNCS and a not in OUTPUT_FUNCS:
                raise ModbusError(EX_ILLEGAL_VALUE)
            if b not in (0, 1) or c not in (0, 1):
                raise ModbusError(EX_ILLEGAL_VALUE)
            if a in UNIQUE_INPUT_FUNCS:
                for other in range(1, 5):
                    if other != pt and self.point_cfg(other)[0] == a:
                        raise ModbusError(EX_ILLEGAL_VALUE)
            was_out = self.point_cfg(pt)[0] == 16
            self.mfg[key] = (a, b, c)
            if a != 16 or not was_out:
                self.out_latch[pt] = 0
        elif key in ("S7", "S8"):
            a, b = self.parse_fields(data, 2)
            if a not in CLOCK_IN_FUNCS and a not in CLOCK_OUT_FUNCS:
                raise ModbusError(EX_ILLEGAL_VALUE)
            if b not in (0, 1):
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.mfg[key] = (a, b)
        elif key == "S5":
            a, b = self.parse_fields(data, 2)
            if a not in (9, 10) or b not in (0, 1):
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.mfg[key] = (a, b)
        elif key == "S13":
            a, b = self.parse_fields(data, 2)
            if a not in (60, 61) or b not in (0, 1):
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.mfg[key] = (a, b)
        elif key == "CR":
            try:
                s = data.decode("ascii").strip()
            except UnicodeDecodeError:
                raise ModbusError(EX_ILLEGAL_VALUE)
            if not s.startswith("=") or len(s) > 7:
                raise ModbusError(EX_ILLEGAL_VALUE)
            body = s[1:].strip()
            ok = body and all(ch in "0123456789." for ch in body) and body.count(".") <= 1 \
                and any(ch.isdigit() for ch in body)
            if not ok:
                raise ModbusError(EX_ILLEGAL_VALUE)
            val = float(body)
            if "." in body and len(body.split(".")[1]) > 3:
                raise ModbusError(EX_ILLEGAL_VALUE)
            if not (0.001 <= val <= 9999.0):
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.mfg["CR"] = val
        elif key == "TR":
            (a,) = self.parse_fields(data, 1)
            if a < S32_MIN or a > S32_MAX:
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.mfg["TR"] = a
        else:
            raise ModbusError(EX_ILLEGAL_ADDRESS)

    def program_cmd(self, key, data):
        if key == "E":
            if data:
                raise ModbusError(EX_ILLEGAL_VALUE)
            if self.prog is not None:
                self.prog = None
                self.stop_decel()
        elif key == "PS":
            if data:
                raise ModbusError(EX_ILLEGAL_VALUE)
            if self.prog is not None:
                self.prog["paused"] = True
        elif key == "RS":
            if data:
                raise ModbusError(EX_ILLEGAL_VALUE)
            if self.prog is not None:
                self.prog["paused"] = False
        elif key == "EX":
            try:
                lab = data.decode("ascii").strip().upper()
            except UnicodeDecodeError:
                raise ModbusError(EX_ILLEGAL_VALUE)
            if lab.startswith("="):
                lab = lab[1:].strip()
            if not lab or len(lab) > 4:
                raise ModbusError(EX_ILLEGAL_VALUE)
            lab = PROGRAM_ADDR.get(lab, lab)
            if lab not in PROGRAMS:
                raise ModbusError(EX_ILLEGAL_VALUE)
            if self.prog is not None or self.mode is not None or not self.v["DE"]:
                raise ModbusError(EX_DEVICE_FAILURE)
            self.prog = {"name": lab, "ops": PROGRAMS[lab], "pc": 0,
                         "paused": False, "delay_until": None}

    # ------------------------------------------------------------------ state
    def state_dict(self):
        regs = {}
        live = {}
        for it in ITEMS:
            val = self.get(it.name, consume=False)
            entry = {"mcode": it.name, "value": val,
                     "access": {"rw": "rw", "ro": "ro", "cmd": "wo",
                                "mot": "rw"}[it.kind]}
            key = "0x%04X" % it.addr
            if it.name in LIVE_NAMES:
                live[key] = entry
            else:
                regs[key] = entry
        coils = {"0x%04X" % (0x4B + i): self.get("O%d" % (i + 1)) for i in range(4)}
        dins = {"0x%04X" % (0x2D + i): self.get("I%d" % (i + 1)) for i in range(4)}
        mfg = {k: self.mfg_format(k, v) for k, v in self.mfg.items()}
        prog = None
        if self.prog is not None:
            prog = {"label": self.prog["name"], "step": self.prog["pc"],
                    "paused": self.prog["paused"]}
        return {
            "device": "MDrive Plus2 Motion Control, Ethernet (MODBUS/TCP), internal encoder",
            "device_identification": {"0x%02X" % k: v.decode() for k, v in DEVICE_ID.items()},
            "holding_registers": regs,
            "coils": coils,
            "discrete_inputs": dins,
            "manufacturer_specific": mfg,
            "output_latches": {str(k): v for k, v in self.out_latch.items()},
            "program": prog,
            "nvm": self.nvm,
            "live": live,
            "diagnostic_counters": {},
        }


# ---------------------------------------------------------------------------
# protocol
# ---------------------------------------------------------------------------
def decode_mnemonic(b4):
    try:
        s = bytes(reversed(b4)).decode("ascii")
    except UnicodeDecodeError:
        return None
    return s.strip(" ")


MFG_PARAM_KEYS = ("S1", "S2", "S3", "S4", "S7", "S8", "CR", "S5", "S13", "TR")
MFG_PROG_KEYS = ("E", "EX", "PS", "RS")


class Server:
    def __init__(self, drive):
        self.d = drive

    # -- function handlers ----------------------------------------------------
    def handle(self, pdu):
        fc = pdu[0]
        try:
            if fc in (0x01, 0x02):
                return self.fc_read_bits(fc, pdu)
            if fc == 0x03:
                return self.fc03(pdu)
            if fc == 0x05:
                return self.fc05(pdu)
            if fc == 0x10:
                return self.fc16(pdu)
            if fc == 0x2B:
                return self.fc43(pdu)
            if fc == 0x41:
                return self.fc41(pdu)
            if fc == 0x42:
                return self.fc42(pdu)
            raise ModbusError(EX_ILLEGAL_FUNCTION)
        except ModbusError as e:
            return bytes([(fc | 0x80) & 0xFF, e.code])
        except Exception:                       # never let one frame kill us
            return bytes([(fc | 0x80) & 0xFF, EX_DEVICE_FAILURE])

    def fc_read_bits(self, fc, pdu):
        if len(pdu) != 5:
            raise ModbusError(EX_ILLEGAL_VALUE)
        start, qty = struct.unpack(">HH", pdu[1:5])
        if qty < 1 or qty > 2000:
            raise ModbusError(EX_ILLEGAL_VALUE)
        base = 0x002D if fc == 0x02 else 0x004B
        if start < base or start + qty > base + 4:
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        bits = 0
        for i in range(qty):
            pt = start - base + 1 + i
            if fc == 0x02:
                val = self.d.get("I%d" % pt)
            else:
                val = self.d.get("O%d" % pt)
            bits |= (val & 1) << i
        return bytes([fc, 1, bits])

    def fc03(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(EX_ILLEGAL_VALUE)
        start, qty = struct.unpack(">HH", pdu[1:5])
        if qty < 1 or qty > 125:
            raise ModbusError(EX_ILLEGAL_VALUE)
        for a in range(start, start + qty):
            if a not in ITEM_AT:
                raise ModbusError(EX_ILLEGAL_ADDRESS)
        if qty > 4:
            raise ModbusError(EX_ILLEGAL_VALUE)
        words = []
        cache = {}
        for a in range(start, start + qty):
            it, k = ITEM_AT[a]
            if it.name not in cache:
                cache[it.name] = self.d.get(it.name)
            val = cache[it.name]
            if it.n == 2:
                u = val & 0xFFFFFFFF
                words.append((u >> 16) if k == 0 else (u & 0xFFFF))
            else:
                words.append(val & 0xFFFF)
        return bytes([0x03, 2 * qty]) + struct.pack(">%dH" % qty, *words)

    def fc05(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(EX_ILLEGAL_VALUE)
        addr, val = struct.unpack(">HH", pdu[1:5])
        if val not in (0x0000, 0xFF00):
            raise ModbusError(EX_ILLEGAL_VALUE)
        if addr < 0x004B or addr > 0x004E:
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        it = ITEM_AT[addr][0]
        v = 1 if val == 0xFF00 else 0
        self.d.check_write(it, v, {})
        self.d.apply_write(it, v)
        return bytes(pdu)

    def fc16(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(EX_ILLEGAL_VALUE)
        start, qty, bc = struct.unpack(">HHB", pdu[1:6])
        if qty < 1 or qty > 123 or bc != 2 * qty or len(pdu) != 6 + bc:
            raise ModbusError(EX_ILLEGAL_VALUE)
        for a in range(start, start + qty):
            if a not in ITEM_AT:
                raise ModbusError(EX_ILLEGAL_ADDRESS)
        if qty > 4:
            raise ModbusError(EX_ILLEGAL_VALUE)
        words = struct.unpack(">%dH" % qty, pdu[6:6 + bc])
        # the request must cover whole items
        writes = []
        a = start
        i = 0
        while a < start + qty:
            it, k = ITEM_AT[a]
            if k != 0 or a + it.n > start + qty:
                raise ModbusError(EX_ILLEGAL_ADDRESS)
            if it.n == 2:
                u = (words[i] << 16) | words[i + 1]
                if it.signed and u & 0x80000000:
                    u -= 1 << 32
            else:
                u = words[i]
            writes.append((it, u))
            a += it.n
            i += it.n
        for it, _ in writes:
            if it.kind == "ro":
                raise ModbusError(EX_ILLEGAL_ADDRESS)
            if it.name in ("O1", "O2", "O3", "O4") and \
                    self.d.point_cfg(int(it.name[1]))[0] != 16:
                raise ModbusError(EX_ILLEGAL_ADDRESS)
        pending = {it.name: u for it, u in writes}
        for it, u in writes:
            self.d.check_write(it, u, pending)
        for it, u in writes:
            self.d.apply_write(it, u)
        return bytes([0x10]) + struct.pack(">HH", start, qty)

    def fc43(self, pdu):
        if len(pdu) < 2:
            raise ModbusError(EX_ILLEGAL_VALUE)
        if pdu[1] != 0x0E:
            raise ModbusError(EX_ILLEGAL_FUNCTION)
        if len(pdu) != 4:
            raise ModbusError(EX_ILLEGAL_VALUE)
        code, obj = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise ModbusError(EX_ILLEGAL_VALUE)
        if code == 4:
            if obj not in DEVICE_ID:
                raise ModbusError(EX_ILLEGAL_ADDRESS)
            ids = [obj]
        else:
            last = 0x02 if code == 1 else 0x06
            if obj > last:
                obj = 0
            ids = list(range(obj, last + 1))
        out = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)])
        for i in ids:
            val = DEVICE_ID[i]
            out += bytes([i, len(val)]) + val
        return bytes(out)

    def fc41(self, pdu):
        if len(pdu) < 5:
            raise ModbusError(EX_ILLEGAL_VALUE)
        key = decode_mnemonic(pdu[1:5])
        if key in MFG_PROG_KEYS:
            data = b""
            if len(pdu) > 5:
                bc = pdu[5]
                if len(pdu) != 6 + bc:
                    raise ModbusError(EX_ILLEGAL_VALUE)
                data = bytes(pdu[6:])
            if key == "EX" and not data:
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.d.program_cmd(key, data)
            return bytes([0x41, 0x00])
        if len(pdu) != 5:
            raise ModbusError(EX_ILLEGAL_VALUE)
        if key not in MFG_PARAM_KEYS:
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        s = self.d.mfg_read(key)
        return bytes([0x41, len(s)]) + s

    def fc42(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(EX_ILLEGAL_VALUE)
        key = decode_mnemonic(pdu[1:5])
        bc = pdu[5]
        if len(pdu) != 6 + bc or bc > 28:
            raise ModbusError(EX_ILLEGAL_VALUE)
        data = bytes(pdu[6:])
        if key in MFG_PROG_KEYS:
            self.d.program_cmd(key, data)
        elif key in MFG_PARAM_KEYS:
            if bc == 0:
                raise ModbusError(EX_ILLEGAL_VALUE)
            self.d.mfg_write(key, data)
        else:
            raise ModbusError(EX_ILLEGAL_ADDRESS)
        return bytes([0x42, bc]) + bytes(pdu[1:5])

    # -- transport ------------------------------------------------------------
    async def client(self, reader, writer):
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid, pid, length, uid = struct.unpack(">HHHB", hdr)
                if length < 2 or length > 254:
                    break                       # framing lost: drop the connection
                body = await reader.readexactly(length - 1)
                if pid != 0:
                    continue                    # not MODBUS: ignore silently
                self.d.tick()
                resp = self.handle(body)
                writer.write(struct.pack(">HHHB", tid, 0, len(resp) + 1, uid) + resp)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError,
                asyncio.CancelledError):
            pass
        finally:
            try:
                writer.close()
            except Exception:
                pass


# ---------------------------------------------------------------------------
def write_state(drive, path):
    if not path:
        return
    try:
        drive.tick()
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(drive.state_dict(), f, indent=1, sort_keys=True)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except Exception as e:                      # pragma: no cover
        print("state write failed: %s" % e, file=sys.stderr)


async def main_async(args):
    host, _, port = args.listen.rpartition(":")
    drive = Drive()
    srv_obj = Server(drive)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()

    loop.add_signal_handler(signal.SIGUSR1, lambda: write_state(drive, args.state))
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)

    server = await asyncio.start_server(srv_obj.client, host, int(port),
                                        reuse_address=True)
    sock = server.sockets[0]
    print("listening tcp %s:%d" % (host, sock.getsockname()[1]), flush=True)

    async def ticker():
        while True:
            await asyncio.sleep(0.01)
            try:
                drive.tick()
            except Exception as e:              # pragma: no cover
                print("tick error: %s" % e, file=sys.stderr)

    tk = asyncio.create_task(ticker())
    await stop.wait()
    tk.cancel()
    server.close()
    write_state(drive, args.state)
    sys.stdout.flush()
    os._exit(0)                 # prompt exit; open connections are simply dropped


def main():
    ap = argparse.ArgumentParser(description="MDrive Plus2 MODBUS/TCP simulator")
    ap.add_argument("--listen", required=True, help="127.0.0.1:PORT")
    ap.add_argument("--state", default=None, help="JSON state file")
    args = ap.parse_args()
    try:
        asyncio.run(main_async(args))
    except KeyboardInterrupt:
        pass
    os._exit(0)


if __name__ == "__main__":
    main()
