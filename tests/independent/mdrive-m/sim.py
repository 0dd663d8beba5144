#!/usr/bin/env python3
"""MDrive Plus2 Motion Control, Ethernet (MODBUS/TCP) drive simulator.

Written from the IMS/SEM "MODBUS/TCP Fieldbus manual" rev. R040611 and the public
MODBUS specifications only.  Standard library only.  See DECISIONS.md.

Usage: python3 sim.py --listen 127.0.0.1:0 [--state FILE] [--seed N] [--glitch-rate R]
"""
import argparse
import asyncio
import json
import os
import random
import signal
import socket
import struct
import sys
import time

# ----------------------------------------------------------------------------
# Link model defaults (our field experience, see DECISIONS.md)
DEFAULT_SEED = 502013
DEFAULT_GLITCH_RATE = 5.0          # link events per 1000 received requests
EVENT_WEIGHTS = (("reset-before-exec", 40), ("reset-after-exec", 35), ("link-drop", 25))
LINK_DROP_MIN_S = 0.3
LINK_DROP_MAX_S = 2.0
MAX_CONNECTIONS = 4
MAX_ADU = 260

# ----------------------------------------------------------------------------
# Register map.  kind: rw (read/write), ro (read only), cmd (write-only command)
# words: 1 or 2 (32-bit, high word first).  signed: two's complement.


class Item:
    def __init__(self, addr, mc, words, kind, default=0, lo=None, hi=None,
                 signed=False, allowed=None, name=""):
        self.addr = addr
        self.mc = mc
        self.words = words
        self.kind = kind
        self.default = default
        self.lo = lo
        self.hi = hi
        self.signed = signed
        self.allowed = allowed
        self.name = name


MS_ALLOWED = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)
I32 = (-2147483648, 2147483647)

ITEMS = [
    Item(0x0000, "A", 2, "rw", 1000000, 91, 1525878997, name="Acceleration"),
    Item(0x0005, "C1", 2, "rw", 0, *I32, signed=True, name="Counter 1"),
    Item(0x0007, "C2", 2, "rw", 0, *I32, signed=True, name="Counter 2"),
    Item(0x0009, "CE", 1, "rw", 1, 0, 1, name="Software reset enable"),
    Item(0x000B, "CM", 1, "rw", 0, 0, 1, name="Clock mode enable"),
    Item(0x000F, "D1", 1, "rw", 0, 0, 255, name="Input 1 debounce"),
    Item(0x0010, "D2", 1, "rw", 0, 0, 255, name="Input 2 debounce"),
    Item(0x0011, "D3", 1, "rw", 0, 0, 255, name="Input 3 debounce"),
    Item(0x0012, "D4", 1, "rw", 0, 0, 255, name="Input 4 debounce"),
    Item(0x0013, "D5", 1, "rw", 0, 0, 255, name="Analog input filter"),
    Item(0x0018, "D", 2, "rw", 1000000, 91, 1525878997, name="Deceleration"),
    Item(0x001A, "DB", 1, "rw", 10, 0, 65000, name="Deadband"),
    Item(0x001B, "DC", 1, "cmd", name="Decrement variable"),
    Item(0x001C, "DE", 1, "rw", 1, 0, 1, name="Drive enable"),
    Item(0x001E, "EE", 1, "rw", 0, 0, 1, name="Encoder enable"),
    Item(0x001F, "EF", 1, "ro", 0, name="Error flag"),
    Item(0x0021, "ER", 1, "rw", 0, 0, 0, name="Error"),
    Item(0x0029, "HC", 1, "rw", 5, 0, 100, name="Holding current"),
    Item(0x002B, "HM", 1, "rw", 1, 1, 4, name="Homing mode"),
    Item(0x002C, "HT", 1, "rw", 500, 0, 65535, name="Hold current delay time"),
    Item(0x002D, "I1", 1, "ro", name="Read input 1"),
    Item(0x002E, "I2", 1, "ro", name="Read input 2"),
    Item(0x002F, "I3", 1, "ro", name="Read input 3"),
    Item(0x0030, "I4", 1, "ro", name="Read input 4"),
    Item(0x0031, "I5", 1, "ro", name="Read analog input"),
    Item(0x0032, "I6", 1, "ro", name="Read index mark"),
    Item(0x0037, "IC", 1, "cmd", name="Increment variable"),
    Item(0x003A, "IL", 1, "ro", name="Read inputs 1-4 as BCD"),
    Item(0x003B, "IN", 1, "ro", name="Read all inputs as BCD"),
    Item(0x003F, "JE", 1, "rw", 0, 0, 1, name="Jog enable"),
    Item(0x0042, "LM", 1, "rw", 1, 1, 6, name="Limit stop mode"),
    Item(0x0043, "MA", 2, "cmd", 0, *I32, signed=True, name="Move to absolute position"),
    Item(0x0045, "MP", 1, "ro", name="Moving to position"),
    Item(0x0046, "MR", 2, "cmd", 0, *I32, signed=True, name="Move to relative position"),
    Item(0x0048, "MS", 1, "rw", 256, allowed=MS_ALLOWED, name="Microstep resolution"),
    Item(0x0049, "MT", 1, "rw", 0, 0, 65000, name="Motor settling delay time"),
    Item(0x004A, "MV", 1, "ro", name="Moving"),
    Item(0x004B, "O1", 1, "rw", 0, 0, 1, name="Write output 1"),
    Item(0x004C, "O2", 1, "rw", 0, 0, 1, name="Write output 2"),
    Item(0x004D, "O3", 1, "rw", 0, 0, 1, name="Write output 3"),
    Item(0x004E, "O4", 1, "rw", 0, 0, 1, name="Write output 4"),
    Item(0x0055, "OL", 1, "rw", 0, 0, 15, name="Set outputs 1-4 as a group (OL)"),
    Item(0x0056, "OT", 1, "rw", 0, 0, 15, name="Set outputs 1-4 as a group (OT)"),
    Item(0x0057, "P", 2, "rw", 0, *I32, signed=True, name="Position counter"),
    Item(0x0059, "PC", 2, "ro", 0, signed=True, name="Position capture at trip"),
    Item(0x005C, "PM", 1, "rw", 0, 0, 1, name="Position maintenance"),
    Item(0x005F, "R1", 2, "rw", 0, *I32, signed=True, name="User register 1"),
    Item(0x0061, "R2", 2, "rw", 0, *I32, signed=True, name="User register 2"),
    Item(0x0063, "R3", 2, "rw", 0, *I32, signed=True, name="User register 3"),
    Item(0x0065, "R4", 2, "rw", 0, *I32, signed=True, name="User register 4"),
    Item(0x0067, "RC", 1, "rw", 25, 1, 100, name="Run current"),
    Item(0x0076, "S", 1, "cmd", name="Save"),
    Item(0x0077, "SF", 1, "rw", 15, 0, 65000, name="Stall factor"),
    Item(0x0078, "SL", 2, "cmd", 0, -5000000, 5000000, signed=True, name="Slew axis"),
    Item(0x007A, "SM", 1, "rw", 0, 0, 1, name="Stall mode"),
    Item(0x007B, "ST", 1, "rw", 0, 0, 0, name="Stall flag"),
    Item(0x007D, "TE", 1, "rw", 0, allowed=(0, 16), name="Trip enable"),
    Item(0x0085, "V", 2, "ro", 0, signed=True, name="Read axis velocity"),
    Item(0x0088, "VC", 1, "ro", name="Velocity is changing"),
    Item(0x0089, "VI", 2, "rw", 1000, 1, 4999999, name="Initial velocity"),
    Item(0x008B, "VM", 2, "rw", 768000, 2, 5000000, name="Maximum velocity"),
    # 5.1 hybrid specific
    Item(0x008E, "AS", 1, "rw", 2, 0, 3, name="Hybrid mode"),
    Item(0x008F, "AF", 1, "ro", name="Hybrid status"),
    Item(0x0090, "CA", 1, "rw", 1, 0, 1, name="Calibration mode"),
    Item(0x0091, "CB", 1, "rw", 1, 0, 3, name="Control bounds"),
    Item(0x0092, "CC", 1, "rw", 100, 1, 100, name="Calibration current"),
    Item(0x0093, "CF", 1, "cmd", name="Clear locked rotor"),
    Item(0x0094, "CT", 1, "rw", 200, 2, 65535, name="Calibration time"),
    Item(0x0095, "LD", 2, "rw", 102400, 0, 2147483647, name="Lead limit"),
    Item(0x0097, "LG", 2, "rw", 102400, 0, 2147483647, name="Lag limit"),
    Item(0x0099, "LL", 2, "ro", 0, signed=True, name="Position lead/lag"),
    Item(0x009B, "LR", 1, "ro", 0, name="Locked rotor"),
    Item(0x009C, "LT", 2, "rw", 2000, 2, 65535, name="Locked rotor timeout"),
    Item(0x009E, "MF", 2, "rw", 768000, 306, 5000000, name="Make up frequency"),
    Item(0x00A0, "MU", 1, "rw", 0, 0, 2, name="Make up"),
    Item(0x00A1, "SC", 1, "cmd", name="Start calibration"),
    Item(0x00A2, "SS", 1, "rw", 0, 0, 255, name="System speed"),
    Item(0x00A5, "TD", 1, "rw", 1, 0, 1, name="Torque direction"),
    Item(0x00A6, "TQ", 1, "rw", 25, 1, 100, name="Torque"),
    Item(0x00A7, "TS", 1, "rw", 0, 0, 255, name="Torque speed"),
]
for _i, _a in enumerate(range(0x00A8, 0x00B8, 2)):
    ITEMS.append(Item(_a, "V%d" % (_i + 1), 2, "rw", 0, *I32, signed=True,
                      name="User variable %d" % (_i + 1)))

BY_MC = {it.mc: it for it in ITEMS}
WORD_MAP = {}          # register address -> (item, word index)
for _it in ITEMS:
    for _w in range(_it.words):
        WORD_MAP[_it.addr + _w] = (_it, _w)
REG_LAST = 0x00B7

# variables that DC/IC may name (by their register address)
INCDEC_TARGETS = {BY_MC[m].addr: m for m in
                  ("C1", "C2", "P", "R1", "R2", "R3", "R4",
                   "V1", "V2", "V3", "V4", "V5", "V6", "V7", "V8")}

# parameters kept in NVM by Save (S)
NVM_PARAMS = [it.mc for it in ITEMS if it.kind == "rw" and it.mc not in
              ("C1", "C2", "P", "ER", "ST", "O1", "O2", "O3", "O4", "OL", "OT",
               "V1", "V2", "V3", "V4", "V5", "V6", "V7", "V8")]

IO_IN_FUNCS = (0, 1, 2, 3, 5, 7, 8, 11)
IO_OUT_FUNCS = (16, 17, 18, 20, 21, 23, 24, 25)

ID_OBJECTS = [
    b"SEM USA",
    b"MDI1PRL23B7-EQ",
    b"4.0.0.0",
    b"www.imshome.com",
    b"MDrive Ethernet",
    b"0312100457",
    b"ASI 1.0.0.2",
]


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


def to_words(value, words, signed):
    if words == 1:
        return [value & 0xFFFF]
    v = value & 0xFFFFFFFF
    return [(v >> 16) & 0xFFFF, v & 0xFFFF]


def from_words(ws, signed):
    if len(ws) == 1:
        v = ws[0]
        return v
    v = (ws[0] << 16) | ws[1]
    if signed and v & 0x80000000:
        v -= 1 << 32
    return v


def wrap32(v):
    v &= 0xFFFFFFFF
    return v - (1 << 32) if v & 0x80000000 else v


# ----------------------------------------------------------------------------
class Drive:
    """Everything the motion controller and its Ethernet firmware hold."""

    def __init__(self):
        self.v = {it.mc: it.default for it in ITEMS if it.kind != "cmd"}
        # I/O points 1-4: (function, active hi/lo, sink/source); default GP input, active low, sinking
        self.io = {n: [0, 0, 0] for n in (1, 2, 3, 4)}
        self.out_state = {1: 0, 2: 0, 3: 0, 4: 0}
        self.mfg = {
            "S7": [33, 0],
            "S8": [33, 0],
            "CR": "1.000",
            "S5": [9, 0],
            "S13": [60, 0],
            "TR": [0, 0, 0],
            "MU_B": 0,
        }
        self.program = "idle"      # no MCode program stored in a factory drive
        self.nvm = None
        self.nvm = self.nvm_snapshot()
        # motion
        self.pos_f = 0.0
        self.speed = 0.0           # signed steps/s
        self.mode = None           # None | "pos" | "slew"
        self.target = 0
        self.slew_v = 0.0
        self.vchanging = False
        self.motion_task = None
        self.counters = {"requests_processed": 0, "normal_responses": 0,
                         "exception_responses": 0, "illegal_function": 0,
                         "illegal_data_address": 0, "illegal_data_value": 0,
                         "slave_device_failure": 0, "frames_discarded": 0}

    # ---------------------------------------------------------------- values
    def nvm_snapshot(self):
        d = {m: self.v[m] for m in NVM_PARAMS}
        d["io"] = {str(k): list(v) for k, v in self.io.items()}
        d["mfg"] = json.loads(json.dumps(self.mfg))
        return d

    def input_state(self, n):
        f = self.io[n][0]
        if f >= 16:
            return self.out_state[n]
        return 0           # nothing wired to the inputs: all inactive

    def out_group(self):
        g = 0
        for n in (1, 2, 3, 4):
            if self.io[n][0] >= 16 and self.out_state[n]:
                g |= 1 << (n - 1)
        return g

    def value(self, mc):
        if mc in ("I1", "I2", "I3", "I4"):
            return self.input_state(int(mc[1]))
        if mc in ("IL", "IN"):
            return sum(self.input_state(n) << (n - 1) for n in (1, 2, 3, 4))
        if mc in ("O1", "O2", "O3", "O4"):
            return self.input_state(int(mc[1]))
        if mc in ("OL", "OT"):
            return self.out_group()
        if mc == "I5":
            return 0
        if mc == "I6":
            return 0
        if mc == "MV":
            return 1 if self.mode else 0
        if mc == "MP":
            return 1 if self.mode == "pos" else 0
        if mc == "VC":
            return 1 if (self.mode and self.vchanging) else 0
        if mc == "V":
            return int(round(self.speed))
        if mc == "P":
            return wrap32(int(round(self.pos_f)))
        if mc == "MU":
            return self.v["MU"]
        if mc == "AF":
            af = 128 | 64           # calibration complete, at zero
            if self.v["AS"] != 0:
                af |= 16
            return af
        return self.v[mc]

    def read_regs(self, start, qty):
        out = []
        for a in range(start, start + qty):
            ent = WORD_MAP.get(a)
            if ent is None or ent[0].kind == "cmd":
                raise ModbusError(2)
        for a in range(start, start + qty):
            it, w = WORD_MAP[a]
            val = self.value(it.mc)
            out.append(to_words(val, it.words, it.signed)[w])
        # reading the error code clears it (manual: "must be read or set to 0 to clear")
        if start <= 0x0021 < start + qty:
            self.v["ER"] = 0
            self.v["EF"] = 0
        return out

    # ---------------------------------------------------------------- writes
    def write_regs(self, start, words):
        qty = len(words)
        # access check: whole items only, no read-only / reserved registers
        plan = []
        a = start
        while a < start + qty:
            ent = WORD_MAP.get(a)
            if ent is None:
                raise ModbusError(2)
            it, w = ent
            if it.kind == "ro" or w != 0 or a + it.words > start + qty:
                raise ModbusError(2)
            plan.append((it, from_words(words[a - start:a - start + it.words], it.signed)))
            a += it.words
        # value check (all before anything is applied)
        newv = {it.mc: val for it, val in plan}
        for it, val in plan:
            self.check_value(it, val, newv)
        # state check
        for it, val in plan:
            self.check_state(it, val)
        for it, val in plan:
            self.apply(it, val)

    def check_value(self, it, val, newv):
        mc = it.mc
        if it.kind == "cmd":
            if mc in ("DC", "IC") and val not in INCDEC_TARGETS:
                raise ModbusError(3)
            if mc == "SL" and not (-5000000 <= val <= 5000000):
                raise ModbusError(3)
            return
        if it.allowed is not None:
            if val not in it.allowed:
                raise ModbusError(3)
        elif not (it.lo <= val <= it.hi):
            raise ModbusError(3)
        if mc == "HT" and val == 1:
            raise ModbusError(3)
        if mc in ("HT", "MT"):
            ht = newv.get("HT", self.v["HT"])
            mt = newv.get("MT", self.v["MT"])
            if ht + mt > 65535:
                raise ModbusError(3)
        if mc in ("VI", "VM"):
            vi = newv.get("VI", self.v["VI"])
            vm = newv.get("VM", self.v["VM"])
            if not (1 <= vi < vm <= 5000000):
                raise ModbusError(3)

    def check_state(self, it, val):
        mc = it.mc
        if mc in ("O1", "O2", "O3", "O4"):
            if self.io[int(mc[1])][0] < 16:
                raise ModbusError(4)      # point is not configured as an output
        if mc in ("MA", "MR") and self.mode is not None:
            raise ModbusError(4)
        if mc == "SL" and self.mode == "pos":
            raise ModbusError(4)
        if mc == "P" and self.mode is not None:
            raise ModbusError(4)
        if mc in ("DC", "IC") and INCDEC_TARGETS.get(val) == "P" and self.mode is not None:
            raise ModbusError(4)

    def apply(self, it, val):
        mc = it.mc
        if mc in ("O1", "O2", "O3", "O4"):
            self.out_state[int(mc[1])] = val
        elif mc in ("OL", "OT"):
            for n in (1, 2, 3, 4):
                if self.io[n][0] >= 16:
                    self.out_state[n] = (val >> (n - 1)) & 1
        elif mc == "P":
            self.pos_f = float(val)
        elif mc in ("DC", "IC"):
            tgt = INCDEC_TARGETS[val]
            cur = self.value(tgt)
            nv = wrap32(cur + (1 if mc == "IC" else -1))
            if tgt == "P":
                if self.mode is not None:
                    raise ModbusError(4)
                self.pos_f = float(nv)
            else:
                self.v[tgt] = nv
        elif mc == "MA":
            self.start_move(val)
        elif mc == "MR":
            self.start_move(wrap32(self.value("P") + val))
        elif mc == "SL":
            self.start_slew(val)
        elif mc == "S":
            self.nvm = self.nvm_snapshot()
        elif mc in ("CF", "SC"):
            pass                          # locked rotor already clear; calibration is instantaneous here
        elif mc == "MS":
            self.v[mc] = val              # (real drive recalibrates the hybrid circuitry)
        else:
            self.v[mc] = val

    # ---------------------------------------------------------------- motion
    def start_move(self, target):
        if target == self.value("P"):
            return
        self.mode = "pos"
        self.target = target
        self.speed = 0.0
        self.ensure_task()

    def start_slew(self, vel):
        if vel == 0:
            if self.mode == "slew":
                self.slew_v = 0.0
            return
        self.slew_v = float(vel)
        if self.mode is None:
            self.mode = "slew"
            self.speed = 0.0
        self.ensure_task()

    def ensure_task(self):
        if self.motion_task is None or self.motion_task.done():
            self.motion_task = asyncio.get_running_loop().create_task(self.motion_loop())

    async def motion_loop(self):
        dt = 0.01
        last = time.monotonic()
        while self.mode is not None:
            await asyncio.sleep(dt)
            now = time.monotonic()
            step_dt = min(now - last, 0.1)
            last = now
            self.tick(step_dt)

    def tick(self, dt):
        A = float(self.v["A"])
        D = float(self.v["D"])
        VI = float(self.v["VI"])
        VM = float(self.v["VM"])
        old = self.pos_f
        if self.mode == "pos":
            rem = self.target - self.pos_f
            direction = 1.0 if rem > 0 else -1.0
            sp = abs(self.speed)
            if sp < VI:
                sp = VI
            stop_dist = (sp * sp - VI * VI) / (2 * D) if sp > VI else 0.0
            if abs(rem) <= stop_dist + sp * dt:
                nsp = max(VI, sp - D * dt)
            else:
                nsp = min(VM, sp + A * dt)
            self.vchanging = nsp != sp or sp == VI
            step = nsp * dt
            if step >= abs(rem):
                self.pos_f = float(self.target)
                self.speed = 0.0
                self.mode = None
                self.vchanging = False
            else:
                self.pos_f += direction * step
                self.speed = direction * nsp
        elif self.mode == "slew":
            tgt = self.slew_v
            sp = self.speed
            if tgt == 0 or (sp != 0 and (sp > 0) != (tgt > 0)):
                # ramp down (stop or reverse)
                mag = abs(sp) - D * dt
                if mag <= VI:
                    if tgt == 0:
                        self.speed = 0.0
                        self.mode = None
                        self.vchanging = False
                    else:
                        self.speed = 0.0
                        self.vchanging = True
                else:
                    self.speed = mag if sp > 0 else -mag
                    self.vchanging = True
            else:
                direction = 1.0 if tgt > 0 else -1.0
                mag = max(abs(sp), min(VI, abs(tgt)))
                if mag < abs(tgt):
                    mag = min(abs(tgt), mag + A * dt)
                elif mag > abs(tgt):
                    mag = max(abs(tgt), mag - D * dt)
                self.vchanging = mag != abs(sp)
                self.speed = direction * mag
            self.pos_f += self.speed * dt
        if self.pos_f > 2147483647.0 or self.pos_f < -2147483648.0:
            self.pos_f = float(wrap32(int(self.pos_f)))
        moved = int(round(self.pos_f)) - int(round(old))
        self.v["C1"] = wrap32(self.v["C1"] + moved)

    # ---------------------------------------------------------------- mfg (FC 65/66)
    def mfg_read(self, mn):
        if mn in ("S1", "S2", "S3", "S4"):
            vals = self.io[int(mn[1])]
        elif mn in ("S7", "S8", "S5", "S13", "TR"):
            vals = self.mfg[mn]
        elif mn == "CR":
            return self.mfg["CR"].encode()
        elif mn == "MU":
            vals = [self.v["MU"], self.mfg["MU_B"]]
        else:
            raise ModbusError(2)
        return ", ".join(str(x) for x in vals).encode()

    def mfg_command(self, mn, param):
        if mn == "E":
            if param:
                raise ModbusError(3)
            self.program = "idle"
            return
        if mn in ("PS", "RS"):
            if param:
                raise ModbusError(3)
            if self.program == "idle":
                return
            self.program = "paused" if mn == "PS" else "running"
            return
        if mn == "EX":
            lab = param.decode("ascii", "replace")
            if not (1 <= len(lab) <= 4) or not lab.isalnum():
                raise ModbusError(3)
            # factory drive: no MCode program stored, label/address not found
            raise ModbusError(4)
        raise ModbusError(2)

    def mfg_write(self, mn, param):
        try:
            s = param.decode("ascii")
        except UnicodeDecodeError:
            raise ModbusError(3)
        if not s.startswith("="):
            raise ModbusError(3)
        body = s[1:]
        if mn == "CR":
            if len(param) > 6 or not body:
                raise ModbusError(3)
            try:
                if not all(c in "0123456789." for c in body) or body.count(".") > 1:
                    raise ValueError
                f = float(body)
            except ValueError:
                raise ModbusError(3)
            if f <= 0 or ("." in body and len(body.split(".")[1]) > 3):
                raise ModbusError(3)
            self.mfg["CR"] = "%.3f" % f
            return
        parts = [p.strip() for p in body.split(",")]
        try:
            if any(not p or not p.lstrip("+-").isdigit() for p in parts):
                raise ValueError
            nums = [int(p) for p in parts]
        except ValueError:
            raise ModbusError(3)
        if mn in ("S1", "S2", "S3", "S4"):
            if len(nums) != 3 or nums[0] not in IO_IN_FUNCS + IO_OUT_FUNCS \
                    or nums[1] not in (0, 1) or nums[2] not in (0, 1):
                raise ModbusError(3)
            n = int(mn[1])
            if self.io[n][0] != nums[0] and (self.io[n][0] >= 16) != (nums[0] >= 16):
                self.out_state[n] = 0
            self.io[n] = nums
        elif mn in ("S7", "S8"):
            if len(nums) != 2 or nums[0] not in (33, 34, 35, 49, 50, 51) or nums[1] not in (0, 1):
                raise ModbusError(3)
            self.mfg[mn] = nums
        elif mn == "S5":
            if len(nums) != 2 or nums[0] not in (9, 10) or nums[1] not in (0, 1):
                raise ModbusError(3)
            self.mfg[mn] = nums
        elif mn == "S13":
            if len(nums) != 2 or nums[0] not in (60, 61) or nums[1] not in (0, 1):
                raise ModbusError(3)
            self.mfg[mn] = nums
        elif mn == "TR":
            if not (1 <= len(nums) <= 3) or any(not (I32[0] <= x <= I32[1]) for x in nums):
                raise ModbusError(3)
            self.mfg["TR"] = nums + [0] * (3 - len(nums))
        elif mn == "MU":
            if len(nums) != 2 or nums[0] not in (0, 1, 2) or nums[1] not in (0, 1):
                raise ModbusError(3)
            self.v["MU"] = nums[0]
            self.mfg["MU_B"] = nums[1]
        else:
            raise ModbusError(2)

    # ---------------------------------------------------------------- dump
    def dump(self):
        regs = {}
        params = {}
        for it in ITEMS:
            if it.kind == "cmd":
                continue
            val = self.value(it.mc)
            params[it.mc] = {"address": "0x%04X" % it.addr, "value": val,
                             "access": it.kind, "name": it.name}
            for w, word in enumerate(to_words(val, it.words, it.signed)):
                regs["0x%04X" % (it.addr + w)] = word
        return {
            "device": "MDrive Plus2 Motion Control, Ethernet, MODBUS/TCP (simulated)",
            "holding_registers": regs,
            "parameters": params,
            "coils": {"0x%04X" % (0x004B + n - 1): self.input_state(n) for n in (1, 2, 3, 4)},
            "discrete_inputs": {"0x%04X" % (0x002D + n - 1): self.input_state(n) for n in (1, 2, 3, 4)},
            "manufacturer_specific": {
                "S1": list(self.io[1]), "S2": list(self.io[2]),
                "S3": list(self.io[3]), "S4": list(self.io[4]),
                "S7": list(self.mfg["S7"]), "S8": list(self.mfg["S8"]),
                "CR": self.mfg["CR"], "S5": list(self.mfg["S5"]),
                "S13": list(self.mfg["S13"]), "TR": list(self.mfg["TR"]),
                "MU": [self.v["MU"], self.mfg["MU_B"]],
            },
            "program_state": self.program,
            "nvm": self.nvm,
            "device_identification": {"0x%02X" % i: o.decode() for i, o in enumerate(ID_OBJECTS)},
            "diagnostic_counters": dict(self.counters),
            "live": {},
        }

    # ---------------------------------------------------------------- PDU
    def process(self, pdu):
        """Return the response PDU (bytes)."""
        self.counters["requests_processed"] += 1
        fc = pdu[0]
        try:
            resp = self._process(fc, pdu[1:])
            self.counters["normal_responses"] += 1
            return resp
        except ModbusError as e:
            self.counters["exception_responses"] += 1
            key = {1: "illegal_function", 2: "illegal_data_address",
                   3: "illegal_data_value", 4: "slave_device_failure"}[e.code]
            self.counters[key] += 1
            return bytes([(fc | 0x80) & 0xFF, e.code])
        except Exception:  # never let one frame kill the server
            self.counters["exception_responses"] += 1
            self.counters["slave_device_failure"] += 1
            return bytes([(fc | 0x80) & 0xFF, 4])

    def _process(self, fc, d):
        if fc in (0x01, 0x02):
            if len(d) != 4:
                raise ModbusError(3)
            start, qty = struct.unpack(">HH", d)
            if not 1 <= qty <= 4:
                raise ModbusError(3)
            base = 0x004B if fc == 0x01 else 0x002D
            if start < base or start + qty > base + 4:
                raise ModbusError(2)
            bits = 0
            for i in range(qty):
                if self.input_state(start - base + 1 + i):
                    bits |= 1 << i
            return bytes([fc, 1, bits])
        if fc == 0x03:
            if len(d) != 4:
                raise ModbusError(3)
            start, qty = struct.unpack(">HH", d)
            if not 1 <= qty <= 4:
                raise ModbusError(3)
            if start + qty - 1 > REG_LAST:
                raise ModbusError(2)
            words = self.read_regs(start, qty)
            return bytes([3, 2 * qty]) + struct.pack(">%dH" % qty, *words)
        if fc == 0x05:
            if len(d) != 4:
                raise ModbusError(3)
            addr, val = struct.unpack(">HH", d)
            if val not in (0x0000, 0xFF00):
                raise ModbusError(3)
            if not 0x004B <= addr <= 0x004E:
                raise ModbusError(2)
            n = addr - 0x004B + 1
            if self.io[n][0] < 16:
                raise ModbusError(4)
            self.out_state[n] = 1 if val else 0
            return bytes([5]) + d
        if fc == 0x10:
            if len(d) < 5:
                raise ModbusError(3)
            start, qty, bc = struct.unpack(">HHB", d[:5])
            if not 1 <= qty <= 4 or bc != 2 * qty or len(d) != 5 + bc:
                raise ModbusError(3)
            if start + qty - 1 > REG_LAST:
                raise ModbusError(2)
            words = list(struct.unpack(">%dH" % qty, d[5:]))
            self.write_regs(start, words)
            return bytes([0x10]) + struct.pack(">HH", start, qty)
        if fc == 0x2B:
            return self.read_device_id(d)
        if fc in (0x41, 0x42):
            return self.mfg_pdu(fc, d)
        raise ModbusError(1)

    def read_device_id(self, d):
        if len(d) < 1:
            raise ModbusError(3)
        if d[0] != 0x0E:
            raise ModbusError(1)
        if len(d) != 3:
            raise ModbusError(3)
        code, oid = d[1], d[2]
        if code not in (1, 2, 3, 4):
            raise ModbusError(3)
        if code == 4:
            if oid >= len(ID_OBJECTS):
                raise ModbusError(2)
            objs = [oid]
        else:
            last = 2 if code == 1 else 6
            if oid > last:
                oid = 0
            objs = list(range(oid, last + 1))
        body = b""
        for o in objs:
            body += bytes([o, len(ID_OBJECTS[o])]) + ID_OBJECTS[o]
        return bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(objs)]) + body

    def mfg_pdu(self, fc, d):
        if len(d) < 4:
            raise ModbusError(3)
        raw = d[:4]
        try:
            mn = raw[::-1].decode("ascii").strip(" ")
        except UnicodeDecodeError:
            raise ModbusError(2)
        rest = d[4:]
        known_data = ("S1", "S2", "S3", "S4", "S7", "S8", "CR", "S5", "S13", "TR", "MU")
        known_cmd = ("E", "EX", "PS", "RS")
        if mn not in known_data and mn not in known_cmd:
            raise ModbusError(2)
        if mn in known_cmd:
            param = b""
            if rest:
                bc = rest[0]
                if bc > 28 or len(rest) != 1 + bc:
                    raise ModbusError(3)
                param = rest[1:]
            if mn == "EX" and not param:
                raise ModbusError(3)
            self.mfg_command(mn, param)
            if fc == 0x41:
                return bytes([0x41, 0])
            return bytes([0x42, len(param)]) + raw
        if fc == 0x41:
            if rest:
                raise ModbusError(3)
            txt = self.mfg_read(mn)
            return bytes([0x41, len(txt)]) + txt
        if len(rest) < 1:
            raise ModbusError(3)
        bc = rest[0]
        if not 1 <= bc <= 28 or len(rest) != 1 + bc:
            raise ModbusError(3)
        self.mfg_write(mn, rest[1:])
        return bytes([0x42, bc]) + raw


# ----------------------------------------------------------------------------
class Conn:
    def __init__(self, cid, reader, writer):
        self.cid = cid
        self.reader = reader
        self.writer = writer
        self.peer = writer.get_extra_info("peername")
        self.closed = False


class Server:
    def __init__(self, args):
        self.drive = Drive()
        self.state_file = args.state
        self.rate = args.glitch_rate
        self.rng = random.Random(args.seed)
        self.t0 = time.monotonic()
        self.conns = {}
        self.next_cid = 1
        self.link_down = False
        self.outage_conns = set()
        self.event_no = 0
        self.stop_event = None

    def log(self, msg):
        sys.stderr.write("[%9.3fs] %s\n" % (time.monotonic() - self.t0, msg))
        sys.stderr.flush()

    def rst(self, conn):
        if conn.closed:
            return
        conn.closed = True
        try:
            sock = conn.writer.get_extra_info("socket")
            if sock is not None:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        except OSError:
            pass
        try:
            conn.writer.transport.abort()
        except Exception:
            pass

    def draw_event(self):
        """Decide, for one request that reached the drive, whether the link misbehaves."""
        if self.rate <= 0:
            return None
        if self.rng.random() >= self.rate / 1000.0:
            return None
        total = sum(w for _, w in EVENT_WEIGHTS)
        x = self.rng.random() * total
        for kind, w in EVENT_WEIGHTS:
            if x < w:
                break
            x -= w
        if kind == "link-drop":
            dur = self.rng.uniform(LINK_DROP_MIN_S, LINK_DROP_MAX_S)
            executed = self.rng.random() < 0.5
            return (kind, dur, executed)
        return (kind, 0.0, kind == "reset-after-exec")

    def start_outage(self, dur):
        self.link_down = True
        self.outage_conns = set(c.cid for c in self.conns.values() if not c.closed)
        asyncio.get_running_loop().call_later(dur, self.end_outage, self.event_no)

    def end_outage(self, evno):
        self.link_down = False
        victims = sorted(self.outage_conns)
        for cid in victims:
            c = self.conns.get(cid)
            if c is not None:
                self.rst(c)
        self.outage_conns = set()
        self.log("link-event #%d end: link up, stack resets connections %s" %
                 (evno, ",".join("#%d" % c for c in victims) or "(none)"))

    async def handle(self, reader, writer):
        cid = self.next_cid
        self.next_cid += 1
        conn = Conn(cid, reader, writer)
        live = sum(1 for c in self.conns.values() if not c.closed)
        if live >= MAX_CONNECTIONS:
            self.rst(conn)
            return
        self.conns[cid] = conn
        if self.link_down:
            self.outage_conns.add(cid)
        buf = b""
        try:
            while not conn.closed:
                data = await reader.read(4096)
                if not data:
                    break
                if self.link_down:
                    self.outage_conns.add(cid)
                    buf = b""
                    continue            # frames lost on the dead link
                buf += data
                while len(buf) >= 7 and not conn.closed:
                    tid, pid, ln, uid = struct.unpack(">HHHB", buf[:7])
                    if ln < 2 or ln > MAX_ADU - 6:
                        # not Modbus; the stack cannot resynchronise: drop the connection
                        self.drive.counters["frames_discarded"] += 1
                        conn.closed = True
                        writer.close()
                        break
                    if len(buf) < 6 + ln:
                        break
                    frame = buf[:6 + ln]
                    buf = buf[6 + ln:]
                    if pid != 0:
                        self.drive.counters["frames_discarded"] += 1
                        continue
                    if self.link_down:
                        buf = b""
                        break
                    pdu = frame[7:]
                    ev = self.draw_event()
                    resp = None
                    if ev is None or ev[2]:
                        resp = self.drive.process(pdu)
                    if ev is not None:
                        self.event_no += 1
                        kind, dur, executed = ev
                        what = "executed, answer lost" if executed else "not executed"
                        if kind == "link-drop":
                            self.log("link-event #%d link-drop: link down %.0f ms, all connections silent "
                                     "(trigger conn #%d tid=0x%04X fc=0x%02X %s)" %
                                     (self.event_no, dur * 1000, cid, tid, pdu[0], what))
                            self.start_outage(dur)
                            buf = b""
                            break
                        self.log("link-event #%d %s: conn #%d reset (tid=0x%04X fc=0x%02X %s)" %
                                 (self.event_no, kind, cid, tid, pdu[0], what))
                        self.rst(conn)
                        break
                    writer.write(struct.pack(">HHHB", tid, 0, len(resp) + 1, uid) + resp)
                    await writer.drain()
        except (ConnectionError, OSError, asyncio.IncompleteReadError):
            pass
        except asyncio.CancelledError:
            pass
        finally:
            if not conn.closed:
                conn.closed = True
                try:
                    writer.close()
                except Exception:
                    pass
            self.conns.pop(cid, None)

    def write_state(self):
        if not self.state_file:
            return
        tmp = self.state_file + ".tmp"
        try:
            with open(tmp, "w") as f:
                json.dump(self.drive.dump(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except OSError as e:
            self.log("state dump failed: %s" % e)

    async def run(self, host, port):
        loop = asyncio.get_running_loop()
        self.stop_event = asyncio.Event()
        loop.add_signal_handler(signal.SIGTERM, self.stop_event.set)
        loop.add_signal_handler(signal.SIGINT, self.stop_event.set)
        loop.add_signal_handler(signal.SIGUSR1, self.write_state)
        srv = await asyncio.start_server(self.handle, host, port, reuse_address=True, backlog=8)
        p = srv.sockets[0].getsockname()[1]
        sys.stdout.write("listening tcp %s:%d\n" % (host, p))
        sys.stdout.flush()
        self.log("MDrive Plus2 MODBUS/TCP sim: seed=%s glitch-rate=%.3g/1000 requests" %
                 (self.seed_txt, self.rate))
        await self.stop_event.wait()
        srv.close()
        for c in list(self.conns.values()):
            self.rst(c)
        self.write_state()


def main():
    ap = argparse.ArgumentParser(description="MDrive Plus2 MODBUS/TCP simulator")
    ap.add_argument("--listen", default="127.0.0.1:0")
    ap.add_argument("--state", default=None)
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED)
    ap.add_argument("--glitch-rate", type=float, default=DEFAULT_GLITCH_RATE)
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(":")
    if host not in ("127.0.0.1", "localhost"):
        sys.exit("only the loopback address 127.0.0.1 is allowed")
    host = "127.0.0.1"
    if args.glitch_rate < 0:
        sys.exit("--glitch-rate must be >= 0")
    s = Server(args)
    s.seed_txt = str(args.seed)
    try:
        asyncio.run(s.run(host, int(port)))
    except KeyboardInterrupt:
        s.write_state()


if __name__ == "__main__":
    main()
