#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet, MODBUS/TCP server simulator (closed-loop hMTechnology unit).

Standard library only.  See DECISIONS.md for every interpretation of the manual.
Usage: python3 sim.py --listen 127.0.0.1:0 [--state FILE]
"""
import argparse
import asyncio
import copy
import json
import os
import random
import signal
import socket
import struct
import sys
import threading
import time

# --------------------------------------------------------------------------------------------
# Device constants
# --------------------------------------------------------------------------------------------
MAX_CONNECTIONS = 4          # total simultaneous Modbus/TCP connections (HMI takes one)
SERVICE_TIME = 0.001         # seconds of "CPU" per request, one request at a time for all
TICK = 0.005                 # motion update period
FULL_STEPS_PER_REV = 200
ENCODER_COUNTS_PER_REV = 4096  # internal hMT encoder, counts per revolution
UPGRADE_KEY = " 2956102"

DEVICE_ID = {
    0: "IMS USA",
    1: "LMDCE572",
    2: "4.0.0.0",
    3: "https://novantaims.com/",
    4: "LMD Ethernet",
    5: "LMD0000123456",
    6: "LMDCM 6.010, Hw: 1.0",
}

MS_ALLOWED = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)

# Register map ---------------------------------------------------------------------------------
# name: (address, n_regs, kind, signed, lo, hi, default)
#   kind: 'rw' read/write setting, 'ro' read only, 'wo' write-only command, 'er' error (read clears)
#   'st' stall flag (read, write 0 only)
S32_MIN, S32_MAX = -2147483648, 2147483647
REGS = [
    # name  addr  n  kind  signed lo  hi  default
    ("A",   0x0000, 2, "rw", False, 91, 1525878997, 1000000),
    ("BY",  0x0004, 1, "ro", False, 0, 1, 0),
    ("C1",  0x0005, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("C2",  0x0007, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("CE",  0x0009, 1, "rw", False, 0, 1, 1),
    ("CW",  0x000E, 1, "rw", False, 0, 255, 10),
    ("D1",  0x000F, 1, "rw", False, 0, 255, 0),
    ("D2",  0x0010, 1, "rw", False, 0, 255, 0),
    ("D3",  0x0011, 1, "rw", False, 0, 255, 0),
    ("D4",  0x0012, 1, "rw", False, 0, 255, 0),
    ("D5",  0x0013, 1, "rw", False, 0, 255, 0),
    ("D",   0x0018, 2, "rw", False, 91, 1525878997, 1000000),
    ("DB",  0x001A, 1, "rw", False, 0, 65000, 10),
    ("DC",  0x001B, 1, "wo", False, 0, 65535, None),
    ("DE",  0x001C, 1, "rw", False, 0, 1, 1),
    ("EE",  0x001E, 1, "rw", False, 0, 1, 0),
    ("EF",  0x001F, 1, "ro", False, 0, 1, 0),
    ("ER",  0x0021, 1, "er", False, 0, 0, 0),
    ("FC",  0x0024, 1, "rw", False, 0, 9, 0),
    ("HC",  0x0029, 1, "rw", False, 0, 100, 5),
    ("HI",  0x002A, 1, "wo", False, 1, 4, None),
    ("HM",  0x002B, 1, "wo", False, 1, 4, None),
    ("HT",  0x002C, 1, "rw", False, 0, 65535, 500),
    ("I1",  0x002D, 1, "ro", False, 0, 1, 0),
    ("I2",  0x002E, 1, "ro", False, 0, 1, 0),
    ("I3",  0x002F, 1, "ro", False, 0, 1, 0),
    ("I4",  0x0030, 1, "ro", False, 0, 1, 0),
    ("I5",  0x0031, 1, "ro", False, 0, 1023, 0),
    ("I6",  0x0032, 1, "ro", False, 0, 1, 0),
    ("IC",  0x0037, 1, "wo", False, 0, 65535, None),
    ("IN",  0x003B, 1, "ro", False, 0, 15, 0),
    ("IP",  0x003C, 1, "wo", False, 0, 65535, None),
    ("JE",  0x003F, 1, "rw", False, 0, 1, 0),
    ("LM",  0x0042, 1, "rw", False, 1, 6, 1),
    ("MA",  0x0043, 2, "wo", True, S32_MIN, S32_MAX, None),
    ("MP",  0x0045, 1, "ro", False, 0, 1, 0),
    ("MR",  0x0046, 2, "wo", True, S32_MIN, S32_MAX, None),
    ("MS",  0x0048, 1, "rw", False, 1, 256, 256),
    ("MT",  0x0049, 1, "rw", False, 0, 65000, 0),
    ("MV",  0x004A, 1, "ro", False, 0, 1, 0),
    ("O1",  0x004B, 1, "rw", False, 0, 1, 0),
    ("O2",  0x004C, 1, "rw", False, 0, 1, 0),
    ("O3",  0x004D, 1, "rw", False, 0, 1, 0),
    ("OF",  0x004E, 1, "ro", False, 0, 1, 0),
    ("OT",  0x0056, 1, "rw", False, 0, 15, 0),
    ("P",   0x0057, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("PC",  0x0059, 2, "ro", True, S32_MIN, S32_MAX, 0),
    ("PM",  0x005C, 1, "rw", False, 0, 1, 0),
    ("R1",  0x005F, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("R2",  0x0061, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("R3",  0x0063, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("R4",  0x0065, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("RC",  0x0067, 1, "rw", False, 1, 100, 25),
    ("S",   0x0076, 1, "wo", False, 0, 65535, None),
    ("SF",  0x0077, 1, "rw", False, 0, 65000, 15),
    ("SL",  0x0078, 2, "wo", True, -5000000, 5000000, None),
    ("SM",  0x007A, 1, "rw", False, 0, 1, 0),
    ("ST",  0x007B, 1, "st", False, 0, 0, 0),
    ("TE",  0x007D, 1, "rw", False, 0, 43, 0),
    ("V",   0x0085, 2, "ro", True, S32_MIN, S32_MAX, 0),
    ("VC",  0x0088, 1, "ro", False, 0, 1, 0),
    ("VI",  0x0089, 2, "rw", False, 1, 2559999, 1000),
    ("VM",  0x008B, 2, "rw", False, 2, 2560000, 768000),
    ("WT",  0x008D, 1, "rw", False, 0, 84, 80),
    # 5.1 hMTechnology (closed loop)
    ("AS",  0x008E, 1, "rw", False, 0, 3, 2),
    ("AF",  0x008F, 1, "ro", False, 0, 255, 0),
    ("CB",  0x0091, 1, "rw", False, 0, 3, 1),
    ("CF",  0x0093, 1, "wo", False, 0, 65535, None),
    ("LD",  0x0095, 2, "rw", False, 0, 2147483647, 102400),
    ("LG",  0x0097, 2, "rw", False, 0, 2147483647, 102400),
    ("LL",  0x0099, 2, "ro", True, -2147483647, 2147483647, 0),
    ("LR",  0x009B, 1, "ro", False, 0, 1, 0),
    ("LT",  0x009C, 2, "rw", False, 2, 65535, 2000),
    ("MF",  0x009E, 2, "rw", False, 306, 2560000, 768000),
    ("MU",  0x00A0, 1, "rw", False, 0, 2, 0),
    ("SC",  0x00A1, 1, "wo", False, 0, 65535, None),
    ("TS",  0x00A3, 2, "rw", False, 0, 255, 0),
    ("TD",  0x00A5, 1, "rw", False, 0, 1, 1),
    ("TQ",  0x00A6, 1, "rw", False, 1, 100, 25),
    ("VF",  0x00A7, 1, "rw", False, 0, 1000, 0),
    # 5.2 user variables
    ("V1",  0x00A8, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("V2",  0x00AA, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("V3",  0x00AC, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("V4",  0x00AE, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("V5",  0x00B0, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("V6",  0x00B2, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("V7",  0x00B4, 2, "rw", True, S32_MIN, S32_MAX, 0),
    ("V8",  0x00B6, 2, "rw", True, S32_MIN, S32_MAX, 0),
]
REG_BY_ADDR = {r[1]: r for r in REGS}
REG_BY_NAME = {r[0]: r for r in REGS}

# Parameters (kept in NVM by S, reset by IP): all 'rw' registers except live data
DATA_REGS = {"C1", "C2", "P", "O1", "O2", "O3", "OT", "R1", "R2", "R3", "R4",
             "V1", "V2", "V3", "V4", "V5", "V6", "V7", "V8"}
PARAM_REGS = [r[0] for r in REGS if r[3] == "rw" and r[0] not in DATA_REGS]
SAVED_USER = ["R1", "R2", "R3", "R4"]

# Increment/decrement targets (by register address)
INCDEC_TARGETS = {0x0005: "C1", 0x0007: "C2", 0x005F: "R1", 0x0061: "R2", 0x0063: "R3",
                  0x0065: "R4", 0x00A8: "V1", 0x00AA: "V2", 0x00AC: "V3", 0x00AE: "V4",
                  0x00B0: "V5", 0x00B2: "V6", 0x00B4: "V7", 0x00B6: "V8"}

INPUT_TYPES = (0, 1, 2, 3, 5, 7, 8, 11, 12)
OUTPUT_TYPES = (16, 17, 18, 20, 21, 23, 24, 25, 28, 29)


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


def wrap32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


# --------------------------------------------------------------------------------------------
# Drive model
# --------------------------------------------------------------------------------------------
def factory_params():
    p = {name: REG_BY_NAME[name][7] for name in PARAM_REGS}
    p["mfg"] = {
        "AO": 0,
        "IS": {"1": [0, 1], "2": [0, 1], "3": [0, 1], "4": [0, 1]},   # type, active (1=Hi)
        "SNK": {"1": 0, "2": 0, "3": 0, "4": 0},                       # S<n> 3rd field: 0 sink, 1 source
        "AIN": [9, 0],                                                 # mode 9=voltage, range 0=0-5V
        "OS": {"1": [16, 1], "2": [16, 1], "3": [16, 1]},
        "MU_B": 0,
        "RD": 0, "AJ": 128, "AT": 0, "BE": 0, "BL": 0, "BM": 0, "DJ": 128, "DT": 0,
        "FS": 0, "FL": 0,
        "LS": {"0": [0, 0], "1": [0, 0]},                              # dir -> [position, enabled]
        "TR": [0, 0, 0],
    }
    return p


class Drive:
    def __init__(self):
        self.params = factory_params()
        self.nvm = copy.deepcopy(self.params)
        for n in SAVED_USER:
            self.nvm[n] = 0
        self.data = {n: 0 for n in ("C1", "C2", "P", "R1", "R2", "R3", "R4",
                                    "V1", "V2", "V3", "V4", "V5", "V6", "V7", "V8", "PC")}
        self.outputs = [0, 0, 0]          # logical state of GP outputs 1..3
        self.inputs_level = [0, 0, 0, 0]  # electrical level of inputs 1..4 (nothing wired)
        self.er = 0
        self.ef = 0
        self.stall = 0
        self.locked_rotor = 0
        self.upgrade_mode = False
        self.calib_until = 0.0
        # motion
        self.pos = 0.0          # float position in steps
        self.vel = 0.0          # signed steps/s
        self.mode = None        # None | 'move' | 'slew' | 'home' | 'index'
        self.target = 0
        self.slew_v = 0.0
        self.vchanging = 0
        self.enc_acc = 0
        self.last_t = time.monotonic()
        # live values
        self.t_bridge = 34.0
        self.t_cpu = 39.0
        self.v_aux = 24
        self.v_plus = 48
        # traffic counters
        self.counters = {"requests": 0, "responses": 0, "exceptions": 0, "dropped_frames": 0,
                         "connections_accepted": 0, "connections_refused": 0}

    # ---------------------------------------------------------------- derived values
    def moving(self):
        return 1 if self.mode is not None else 0

    def moving_to_pos(self):
        return 1 if self.mode in ("move", "index") else 0

    def af(self):
        v = 0
        if self.params["AS"] != 0:
            v |= 16
        if self.locked_rotor:
            v |= 8
        if self.data.get("LL", 0) == 0:
            v |= 64
        if time.monotonic() >= self.calib_until:
            v |= 128
        return v

    def input_logic(self, i):
        typ, act = self.params["mfg"]["IS"][str(i + 1)]
        return 1 if self.inputs_level[i] == act else 0

    def output_logic(self, i):
        typ, act = self.params["mfg"]["OS"][str(i + 1)]
        if typ == 16:
            return self.outputs[i]
        if typ == 17:
            return self.moving()
        if typ == 18:
            return self.ef
        if typ == 20:
            return self.vchanging
        if typ == 21:
            return self.locked_rotor
        if typ == 23:
            return self.moving_to_pos()
        if typ == 24:
            return 1 if self.params["AS"] != 0 else 0
        if typ == 25:
            return 0
        if typ == 28:
            return 0
        if typ == 29:
            return 1 if (self.attention_flags() & self.params["mfg"]["AO"]) else 0
        return 0

    def attention_flags(self):
        f = 0
        if self.ef:
            f |= 1
        if self.locked_rotor:
            f |= 2
        if self.params["AS"] != 0:
            f |= 16
        if time.monotonic() < self.calib_until:
            f |= 32
        if self.params["DE"] == 0:
            f |= 2048
        if self.t_bridge >= self.params["WT"]:
            f |= 4096
        if self.moving():
            f |= 16384
        if self.stall:
            f |= 32768
        return f

    def steps_per_rev(self):
        return FULL_STEPS_PER_REV * self.params["MS"]

    # ---------------------------------------------------------------- motion
    def _set_pos(self, newpos):
        oldp = int(round(self.pos))
        self.pos = newpos
        newp = int(round(self.pos))
        d = newp - oldp
        if d:
            self.data["P"] = wrap32(self.data["P"] + d)
            self.data["C1"] = wrap32(self.data["C1"] + d)
            total = self.enc_acc + d * ENCODER_COUNTS_PER_REV
            spr = self.steps_per_rev()
            ed = total // spr
            self.enc_acc = total - ed * spr
            if ed:
                self.data["C2"] = wrap32(self.data["C2"] + ed)

    def stop_now(self):
        self.mode = None
        self.vel = 0.0
        self.vchanging = 0

    def soft_limit(self, direction):
        lim = self.params["mfg"]["LS"]["1" if direction > 0 else "0"]
        return lim[0] if lim[1] else None

    def update(self):
        now = time.monotonic()
        dt = now - self.last_t
        self.last_t = now
        if dt <= 0:
            return
        dt = min(dt, 0.05)
        # live drift
        self.t_bridge += random.uniform(-0.02, 0.02) + (34.0 - self.t_bridge) * 0.001
        self.t_cpu += random.uniform(-0.02, 0.02) + (39.0 - self.t_cpu) * 0.001
        if self.mode is None:
            self.vchanging = 0
            return
        A = float(self.params["A"])
        D = float(self.params["D"])
        VI = float(self.params["VI"])
        VM = float(self.params["VM"])
        if self.mode in ("move", "index"):
            vmax = VM
            rem = self.target - self.pos
            direction = 1 if rem > 0 else -1
            dist = abs(rem)
            speed = abs(self.vel)
            if dist < 0.5:
                self._set_pos(float(self.target))
                self._finish_move()
                return
            decel_dist = (speed * speed - VI * VI) / (2 * D) if speed > VI else 0.0
            old = speed
            if dist <= decel_dist:
                speed = max(VI, speed - D * dt)
            else:
                speed = min(vmax, max(VI, speed + A * dt))
            step = speed * dt
            self.vchanging = 1 if abs(speed - old) > 1e-9 else 0
            if step >= dist:
                self._set_pos(float(self.target))
                self._finish_move()
                return
            self.vel = direction * speed
            self._set_pos(self.pos + direction * step)
        else:  # slew or home
            tv = self.slew_v
            v = self.vel
            if v == 0.0 and tv != 0.0:
                v = VI if tv > 0 else -VI
                if abs(v) > abs(tv):
                    v = tv
            if v == tv:
                self.vchanging = 0
            else:
                if abs(tv) > abs(v) and (v == 0 or (tv > 0) == (v > 0)):
                    rate = A
                else:
                    rate = D
                if tv > v:
                    v = min(tv, v + rate * dt)
                else:
                    v = max(tv, v - rate * dt)
                self.vchanging = 1
            if tv == 0.0 and abs(v) <= VI:
                self.stop_now()
                return
            self.vel = v
            newpos = self.pos + v * dt
            lim = self.soft_limit(1 if v > 0 else -1)
            if lim is not None and ((v > 0 and newpos >= lim) or (v < 0 and newpos <= lim)):
                self._set_pos(float(lim))
                self.stop_now()
                return
            self._set_pos(newpos)

    def _finish_move(self):
        was_index = self.mode == "index"
        self.stop_now()
        if was_index:
            self.data["P"] = 0
            self.pos = 0.0

    # ---------------------------------------------------------------- commands
    def can_move(self):
        if self.params["DE"] == 0 or self.locked_rotor or self.upgrade_mode:
            raise ModbusError(4)

    def cmd_move(self, target):
        self.can_move()
        if self.mode is not None:
            raise ModbusError(4)
        target = int(target)
        cur = self.data["P"]
        lim = self.soft_limit(1 if target > cur else -1)
        if lim is not None:
            if (target > cur and target > lim) or (target < cur and target < lim):
                target = lim
        # work in a coordinate where pos == P
        self.pos = float(cur)
        if target == cur:
            return
        self.target = target
        self.mode = "move"
        self.vel = 0.0

    def cmd_slew(self, v):
        if v == 0:
            if self.mode in ("slew", "home"):
                self.slew_v = 0.0
                self.mode = "slew"
            return
        self.can_move()
        if self.mode in ("move", "index"):
            raise ModbusError(4)
        if self.mode is None:
            self.pos = float(self.data["P"])
            self.vel = 0.0
        self.mode = "slew"
        self.slew_v = float(v)

    def cmd_home(self, m):
        self.can_move()
        if self.mode is not None:
            raise ModbusError(4)
        homes = [k for k, (t, a) in self.params["mfg"]["IS"].items() if t == 1]
        if not homes:
            raise ModbusError(4)
        # Home switch never becomes active on an unwired bench: the axis slews at VM
        self.pos = float(self.data["P"])
        self.vel = 0.0
        self.mode = "home"
        vm = float(self.params["VM"])
        self.slew_v = -vm if m in (1, 2) else vm
        if self.params["mfg"]["RD"]:
            self.slew_v = -self.slew_v

    def cmd_index(self, m, offset=0):
        self.can_move()
        if self.mode is not None:
            raise ModbusError(4)
        spr = self.steps_per_rev()
        cur = self.data["P"]
        direction = -1 if m in (1, 2) else 1
        r = cur % spr
        dist = (spr - r) if direction > 0 else r
        if dist == 0:
            dist = spr
        self.pos = float(cur)
        self.target = cur + direction * dist + offset
        if self.target == cur:
            self.data["P"] = 0
            self.pos = 0.0
            return
        self.mode = "index"
        self.vel = 0.0

    def reset_params(self):
        self.params = factory_params()
        self.outputs = [0, 0, 0]

    def save(self):
        self.nvm = copy.deepcopy(self.params)
        for n in SAVED_USER:
            self.nvm[n] = self.data[n]

    # ---------------------------------------------------------------- register access
    def read_item(self, name):
        kind = REG_BY_NAME[name][3]
        if kind == "wo":
            raise ModbusError(2)
        if name in self.params:
            return self.params[name]
        if name in self.data:
            return self.data[name]
        if name == "BY":
            return 0
        if name == "EF":
            return self.ef
        if name == "ER":
            v = self.er
            self.er = 0
            self.ef = 0
            return v
        if name in ("I1", "I2", "I3", "I4"):
            return self.input_logic(int(name[1]) - 1)
        if name == "I5":
            return 0
        if name == "I6":
            spr = self.steps_per_rev()
            return 1 if self.data["P"] % spr == 0 else 0
        if name == "IN":
            return sum(self.input_logic(i) << i for i in range(4))
        if name == "MP":
            return self.moving_to_pos()
        if name == "MV":
            return self.moving()
        if name in ("O1", "O2", "O3"):
            return self.output_logic(int(name[1]) - 1)
        if name == "OT":
            return sum(self.output_logic(i) << i for i in range(3))
        if name == "OF":
            return 0
        if name == "ST":
            return self.stall
        if name == "V":
            return int(round(self.vel))
        if name == "VC":
            return self.vchanging
        if name == "AF":
            return self.af()
        if name == "LL":
            return 0
        if name == "LR":
            return self.locked_rotor
        raise ModbusError(4)

    def write_item(self, name, value):
        r = REG_BY_NAME[name]
        kind, lo, hi = r[3], r[5], r[6]
        if kind == "ro":
            raise ModbusError(2)
        if self.upgrade_mode:
            raise ModbusError(4)
        if kind == "er":
            if value != 0:
                raise ModbusError(3)
            self.er = 0
            self.ef = 0
            return
        if kind == "st":
            if value != 0:
                raise ModbusError(3)
            self.stall = 0
            return
        if not (lo <= value <= hi):
            raise ModbusError(3)
        p = self.params
        if name == "MS":
            if value not in MS_ALLOWED:
                raise ModbusError(3)
            if self.mode is not None:
                raise ModbusError(4)
            self.enc_acc = 0
        if name == "VI" and value >= p["VM"]:
            raise ModbusError(3)
        if name == "VM" and value <= p["VI"]:
            raise ModbusError(3)
        if name == "HT":
            if value == 1 or value + p["MT"] > 65535:
                raise ModbusError(3)
        if name == "MT" and value + p["HT"] > 65535:
            raise ModbusError(3)
        if name in p:
            p[name] = value
            if name == "DE" and value == 0:
                self.stop_now()
            return
        if name == "P":
            if self.mode is not None:
                raise ModbusError(4)
            self.data["P"] = value
            self.pos = float(value)
            return
        if name in self.data:
            self.data[name] = value
            return
        if name in ("O1", "O2", "O3"):
            i = int(name[1]) - 1
            if p["mfg"]["OS"][str(i + 1)][0] != 16:
                raise ModbusError(4)
            self.outputs[i] = value
            return
        if name == "OT":
            for i in range(3):
                if p["mfg"]["OS"][str(i + 1)][0] == 16:
                    self.outputs[i] = (value >> i) & 1
            return
        # write-only commands
        if name in ("DC", "IC"):
            t = INCDEC_TARGETS.get(value)
            if t is None:
                raise ModbusError(3)
            self.data[t] = wrap32(self.data[t] + (1 if name == "IC" else -1))
            return
        if name == "HI":
            self.cmd_index(value)
            return
        if name == "HM":
            self.cmd_home(value)
            return
        if name == "IP":
            if self.mode is not None:
                raise ModbusError(4)
            self.reset_params()
            return
        if name == "MA":
            self.cmd_move(value)
            return
        if name == "MR":
            self.cmd_move(self.data["P"] + value)
            return
        if name == "S":
            if self.mode is not None:
                raise ModbusError(4)
            self.save()
            return
        if name == "SL":
            self.cmd_slew(value)
            return
        if name == "CF":
            self.locked_rotor = 0
            self.calib_until = time.monotonic() + 0.5
            return
        if name == "SC":
            if self.mode is not None:
                raise ModbusError(4)
            self.calib_until = time.monotonic() + 1.0
            return
        raise ModbusError(4)

    # ---------------------------------------------------------------- state dump
    def dump(self):
        regs = {}
        for (name, addr, n, kind, signed, lo, hi, dflt) in REGS:
            if kind == "wo":
                continue
            if name == "ER":
                val = self.er
            else:
                val = self.read_item(name)
            regs["0x%04X" % addr] = {"name": name, "registers": n, "value": val}
        m = self.params["mfg"]
        return {
            "device": "Lexium MDrive LMD Ethernet (closed loop, hMTechnology) MODBUS/TCP",
            "identification": {str(k): v for k, v in DEVICE_ID.items()},
            "holding_registers": regs,
            "coils": {"%d" % i: self.output_logic(i) for i in range(3)},
            "discrete_inputs": {"%d" % i: self.input_logic(i) for i in range(4)},
            "manufacturer_specific": {
                "AO": m["AO"],
                "IS": {k: list(v) for k, v in m["IS"].items()},
                "IS5_analog": list(m["AIN"]),
                "S_sink_source": dict(m["SNK"]),
                "OS": {k: list(v) for k, v in m["OS"].items()},
                "MU": [self.params["MU"], m["MU_B"]],
                "RD": m["RD"], "AJ": m["AJ"], "AT": m["AT"], "BE": m["BE"], "BL": m["BL"],
                "BM": m["BM"], "DJ": m["DJ"], "DT": m["DT"], "FS": m["FS"], "FL": m["FL"],
                "LS": {k: list(v) for k, v in m["LS"].items()},
                "TR": list(m["TR"]),
                "program_space": "empty",
                "program_running": False,
            },
            "upgrade_mode": self.upgrade_mode,
            "nvm": copy.deepcopy(self.nvm),
            "live": {"IT_bridge_C": round(self.t_bridge, 2), "IT_cpu_C": round(self.t_cpu, 2),
                     "VT_aux_V": self.v_aux, "VT_plus_V": self.v_plus},
            "diagnostic_counters": dict(self.counters),
        }


# --------------------------------------------------------------------------------------------
# Manufacturer specific functions (FC 65 / 66)
# --------------------------------------------------------------------------------------------
def parse_mnemonic(b4):
    return bytes(reversed(b4)).decode("latin-1").replace(" ", "")


def parse_ints(s, count_lo, count_hi=None):
    if count_hi is None:
        count_hi = count_lo
    if not s.startswith("="):
        raise ModbusError(3)
    parts = s[1:].split(",")
    if not (count_lo <= len(parts) <= count_hi):
        raise ModbusError(3)
    out = []
    for p in parts:
        p = p.strip()
        if not p or not (p.lstrip("+-").isdigit()) or len(p) > 11:
            raise ModbusError(3)
        out.append(int(p))
    return out


def fmt(vals):
    return ", ".join(str(v) for v in vals)


MFG_READ = {"AO", "EL", "IS", "IT", "MU", "OS", "RD", "AJ", "AT", "BE", "BL", "BM", "DJ", "DT",
            "FS", "AV", "FL", "LS", "VT", "TR"}
MFG_WRITE = {"\x1b", "AO", "CP", "EL", "EX", "IS", "MU", "OS", "PS", "RS", "E", "RD", "AJ", "AT",
             "BE", "BL", "BM", "DJ", "DT", "FS", "HF", "FL", "LS", "UG", "TR"}
SIMPLE_MFG = {"RD": (0, 1), "AJ": (1, 255), "AT": (0, 1), "BE": (0, 1), "BL": (0, 2147483647),
              "BM": (0, 1), "DJ": (1, 255), "DT": (0, 1), "FS": (0, 65535), "FL": (0, 1),
              "AO": (0, 65535)}


def split_point(name):
    """'IS3' -> ('IS', 3); 'S1' -> ('IS', 1); 'OS2' -> ('OS', 2)."""
    if len(name) == 2 and name[0] == "S" and name[1] in "12345":
        return "IS", int(name[1])
    if len(name) == 3 and name[:2] in ("IS", "OS", "TR") and name[2] in "12345":
        return name[:2], int(name[2])
    return name, None


def mfg_read(drv, name):
    m = drv.params["mfg"]
    base, point = split_point(name)
    if base not in MFG_READ or (point is not None and base == "TR" and point != 3):
        raise ModbusError(1)
    if base == "EL":
        raise ModbusError(1)          # not applicable to integrated LMD products
    if base in SIMPLE_MFG:
        return str(m[base])
    if base == "IT":
        return "%d,%d" % (round(drv.t_bridge), round(drv.t_cpu))
    if base == "VT":
        return "%d,%d" % (drv.v_aux, drv.v_plus)
    if base == "AV":
        return str(int(round(drv.vel)) if drv.params["AS"] != 0 else 0)
    if base == "MU":
        return fmt([drv.params["MU"], m["MU_B"]])
    if base == "TR":
        return fmt(m["TR"])
    if base == "LS":
        return fmt([0] + m["LS"]["0"] + [1] + m["LS"]["1"])
    if base == "IS":
        lines = []
        for i in range(1, 6):
            if point is not None and i != point:
                continue
            if i == 5:
                lines.append(fmt([5] + m["AIN"]))
            else:
                lines.append(fmt([i] + m["IS"][str(i)]))
        return ", ".join(lines)
    if base == "OS":
        if point is not None and point > 3:
            raise ModbusError(3)
        lines = []
        for i in range(1, 4):
            if point is not None and i != point:
                continue
            lines.append(fmt([i] + m["OS"][str(i)]))
        return ", ".join(lines)
    raise ModbusError(1)


def mfg_write(drv, name, data):
    m = drv.params["mfg"]
    base, point = split_point(name)
    if base not in MFG_WRITE or (point is not None and base not in ("IS",)):
        raise ModbusError(1)
    if base == "EL":
        raise ModbusError(1)
    s = data.decode("latin-1")
    if base == "\x1b":
        if data:
            raise ModbusError(3)
        drv.stop_now()
        return
    if drv.upgrade_mode:
        raise ModbusError(4)
    if base in ("CP", "PS", "RS", "E"):
        if data:
            raise ModbusError(3)
        return                          # no program stored / running: nothing to do
    if base == "EX":
        lbl = s.strip()
        if not lbl or len(data) > 4:
            raise ModbusError(3)
        raise ModbusError(3)            # program space is empty: no such address/label
    if base == "UG":
        if s != UPGRADE_KEY:
            raise ModbusError(3)
        drv.stop_now()
        drv.upgrade_mode = True
        return
    if base in SIMPLE_MFG:
        (v,) = parse_ints(s, 1)
        lo, hi = SIMPLE_MFG[base]
        if not lo <= v <= hi:
            raise ModbusError(3)
        m[base] = v
        return
    if base == "MU":
        a, b = parse_ints(s, 2)
        if a not in (0, 1, 2) or b not in (0, 1):
            raise ModbusError(3)
        drv.params["MU"] = a
        m["MU_B"] = 0                    # B=1 is a one-shot "clear lead/lag"
        return
    if base == "HF":
        (v,) = parse_ints(s, 1)
        if v not in (1, 2, 3, 4):
            raise ModbusError(3)
        drv.cmd_index(v, m["FS"])
        return
    if base == "LS":
        d, pos, en = parse_ints(s, 3)
        if d not in (0, 1) or en not in (0, 1) or not S32_MIN <= pos <= S32_MAX:
            raise ModbusError(3)
        m["LS"][str(d)] = [pos, en]
        return
    if base == "TR":
        a, b, c = parse_ints(s, 3)
        if not S32_MIN <= a <= S32_MAX or b not in (0, 1) or c not in (0, 1):
            raise ModbusError(3)
        m["TR"] = [a, b, c]
        return
    if base == "IS":
        snk = None
        if point is None:
            a, b, c = parse_ints(s, 3)
        else:
            vals = parse_ints(s, 2, 3)
            a, b, c = point, vals[0], vals[1]
            if len(vals) == 3:
                snk = vals[2]
                if a == 5 or snk not in (0, 1):
                    raise ModbusError(3)
        if a == 5:
            if b not in (9, 10) or c not in (0, 1):
                raise ModbusError(3)
            m["AIN"] = [b, c]
            return
        if a not in (1, 2, 3, 4) or b not in INPUT_TYPES or c not in (0, 1):
            raise ModbusError(3)
        if b == 12 and a != 1:
            raise ModbusError(3)
        if drv.mode is not None:
            raise ModbusError(4)
        m["IS"][str(a)] = [b, c]
        if snk is not None:
            m["SNK"][str(a)] = snk
        return
    if base == "OS":
        a, b, c = parse_ints(s, 3)
        if a not in (1, 2, 3) or b not in OUTPUT_TYPES or c not in (0, 1):
            raise ModbusError(3)
        if b == 28 and a != 3:
            raise ModbusError(3)
        m["OS"][str(a)] = [b, c]
        return
    raise ModbusError(1)


# --------------------------------------------------------------------------------------------
# PDU processing
# --------------------------------------------------------------------------------------------
def u16(b, i):
    return (b[i] << 8) | b[i + 1]


def encode_value(r, v):
    if r[2] == 1:
        return struct.pack(">H", v & 0xFFFF)
    v &= 0xFFFFFFFF
    return struct.pack(">HH", v & 0xFFFF, v >> 16)   # low word first


def process_pdu(drv, pdu):
    fc = pdu[0]
    if drv.upgrade_mode and fc != 0x2B:
        raise ModbusError(4)
    if fc == 0x03:
        if len(pdu) != 5:
            raise ModbusError(3)
        addr, qty = u16(pdu, 1), u16(pdu, 3)
        if qty < 1 or qty > 2:
            raise ModbusError(3)
        r = REG_BY_ADDR.get(addr)
        if r is None or qty != r[2]:
            raise ModbusError(2)
        v = drv.read_item(r[0])
        data = encode_value(r, v)
        return bytes([0x03, len(data)]) + data
    if fc == 0x10:
        if len(pdu) < 6:
            raise ModbusError(3)
        addr, qty, bc = u16(pdu, 1), u16(pdu, 3), pdu[5]
        if qty < 1 or qty > 2 or bc != 2 * qty or len(pdu) != 6 + bc:
            raise ModbusError(3)
        r = REG_BY_ADDR.get(addr)
        if r is None or qty != r[2]:
            raise ModbusError(2)
        if qty == 1:
            raw = u16(pdu, 6)
            val = raw - 0x10000 if (r[4] and raw & 0x8000) else raw
        else:
            raw = u16(pdu, 6) | (u16(pdu, 8) << 16)
            val = wrap32(raw) if r[4] else raw
        drv.write_item(r[0], val)
        return pdu[:5]
    if fc == 0x01:
        if len(pdu) != 5:
            raise ModbusError(3)
        addr, qty = u16(pdu, 1), u16(pdu, 3)
        if qty < 1 or qty > 4:
            raise ModbusError(3)
        if addr + qty > 3:
            raise ModbusError(2)
        bits = 0
        for i in range(qty):
            bits |= drv.output_logic(addr + i) << i
        return bytes([0x01, 1, bits])
    if fc == 0x02:
        if len(pdu) != 5:
            raise ModbusError(3)
        addr, qty = u16(pdu, 1), u16(pdu, 3)
        if qty < 1 or qty > 4:
            raise ModbusError(3)
        if addr + qty > 4:
            raise ModbusError(2)
        bits = 0
        for i in range(qty):
            bits |= drv.input_logic(addr + i) << i
        return bytes([0x02, 1, bits])
    if fc == 0x05:
        if len(pdu) != 5:
            raise ModbusError(3)
        addr, val = u16(pdu, 1), u16(pdu, 3)
        if val not in (0x0000, 0xFF00):
            raise ModbusError(3)
        if addr > 2:
            raise ModbusError(2)
        drv.write_item("O%d" % (addr + 1), 1 if val else 0)
        return bytes(pdu)
    if fc == 0x2B:
        return read_device_id(pdu)
    if fc == 0x41:
        if len(pdu) != 5:
            raise ModbusError(3)
        name = parse_mnemonic(pdu[1:5])
        txt = mfg_read(drv, name).encode("latin-1")
        return bytes([0x41, len(txt)]) + txt
    if fc == 0x42:
        if len(pdu) < 6:
            raise ModbusError(3)
        bc = pdu[5]
        if bc > 28 or len(pdu) != 6 + bc:
            raise ModbusError(3)
        name = parse_mnemonic(pdu[1:5])
        mfg_write(drv, name, bytes(pdu[6:]))
        return bytes([0x42, 4]) + bytes(pdu[1:5])
    raise ModbusError(1)


def read_device_id(pdu):
    if len(pdu) < 2:
        raise ModbusError(3)
    if pdu[1] != 0x0E:
        raise ModbusError(1)
    if len(pdu) != 4:
        raise ModbusError(3)
    code, oid = pdu[2], pdu[3]
    if code not in (1, 2, 3, 4):
        raise ModbusError(3)
    if code == 4:
        if oid not in DEVICE_ID:
            raise ModbusError(2)
        objs = [oid]
    else:
        last = 2 if code == 1 else 6
        if oid > last:
            oid = 0
        objs = list(range(oid, last + 1))
    body = b""
    for o in objs:
        v = DEVICE_ID[o].encode("latin-1")
        body += bytes([o, len(v)]) + v
    return bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(objs)]) + body


# --------------------------------------------------------------------------------------------
# Server
# --------------------------------------------------------------------------------------------
class Server:
    def __init__(self, state_file):
        self.drv = Drive()
        self.state_file = state_file
        self.cpu = None
        self.conns = set()
        self.server = None
        self.stopping = False

    def write_state(self):
        if not self.state_file:
            return
        try:
            self.drv.update()
            tmp = self.state_file + ".tmp"
            with open(tmp, "w") as f:
                json.dump(self.drv.dump(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except Exception as e:  # never let a dump kill the drive
            print("state dump failed: %s" % e, file=sys.stderr)

    async def motion_task(self):
        while True:
            self.drv.update()
            await asyncio.sleep(TICK)

    async def handle(self, reader, writer):
        drv = self.drv
        if len(self.conns) >= MAX_CONNECTIONS:
            drv.counters["connections_refused"] += 1
            writer.close()
            return
        drv.counters["connections_accepted"] += 1
        self.conns.add(writer)
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid, pid, length, uid = struct.unpack(">HHHB", hdr)
                if length < 2 or length > 254:
                    drv.counters["dropped_frames"] += 1
                    break                           # framing lost: close the connection
                pdu = await reader.readexactly(length - 1)
                if pid != 0:
                    drv.counters["dropped_frames"] += 1
                    continue                        # not MODBUS: discard silently
                async with self.cpu:
                    drv.counters["requests"] += 1
                    drv.update()
                    try:
                        resp = process_pdu(drv, pdu)
                    except ModbusError as e:
                        resp = bytes([(pdu[0] | 0x80) & 0xFF, e.code])
                        drv.counters["exceptions"] += 1
                    except Exception as e:  # defensive: a bug must not kill the drive
                        print("internal error: %r" % e, file=sys.stderr)
                        resp = bytes([(pdu[0] | 0x80) & 0xFF, 4])
                        drv.counters["exceptions"] += 1
                    await asyncio.sleep(SERVICE_TIME)
                    writer.write(struct.pack(">HHHB", tid, 0, len(resp) + 1, uid) + resp)
                    drv.counters["responses"] += 1
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            self.conns.discard(writer)
            try:
                writer.close()
            except Exception:
                pass

    async def main(self, host, port):
        self.cpu = asyncio.Lock()
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        loop.add_signal_handler(signal.SIGTERM, stop.set)
        loop.add_signal_handler(signal.SIGINT, stop.set)
        loop.add_signal_handler(signal.SIGUSR1, self.write_state)
        self.server = await asyncio.start_server(self.handle, host, port, backlog=8)
        port = self.server.sockets[0].getsockname()[1]
        mt = asyncio.create_task(self.motion_task())
        print("listening tcp %s:%d" % (host, port), flush=True)
        hmi = HMI(host, port)
        hmi.start()
        await stop.wait()
        self.write_state()
        mt.cancel()
        self.server.close()
        for w in list(self.conns):
            try:
                w.close()
            except Exception:
                pass


# --------------------------------------------------------------------------------------------
# HMI: operator panel polling the drive over a real loopback connection (read only)
# --------------------------------------------------------------------------------------------
class HMI(threading.Thread):
    UNIT = 1
    PERIOD = 0.05           # 20 requests / second
    POLL = [
        bytes([0x03, 0x00, 0x57, 0x00, 0x02]),   # P position counter
        bytes([0x03, 0x00, 0x85, 0x00, 0x02]),   # V axis velocity
        bytes([0x03, 0x00, 0x4A, 0x00, 0x01]),   # MV moving
        bytes([0x03, 0x00, 0x45, 0x00, 0x01]),   # MP moving to position
        bytes([0x03, 0x00, 0x1F, 0x00, 0x01]),   # EF error flag
        bytes([0x03, 0x00, 0x57, 0x00, 0x02]),   # P again (panel refreshes position often)
        bytes([0x03, 0x00, 0x85, 0x00, 0x02]),   # V again
        bytes([0x03, 0x00, 0x7B, 0x00, 0x01]),   # ST stall flag
        bytes([0x03, 0x00, 0x8F, 0x00, 0x01]),   # AF hMT status
        bytes([0x02, 0x00, 0x00, 0x00, 0x04]),   # inputs 1-4
        bytes([0x01, 0x00, 0x00, 0x00, 0x03]),   # outputs 1-3
        bytes([0x03, 0x00, 0x9B, 0x00, 0x01]),   # LR locked rotor
        bytes([0x03, 0x00, 0x07, 0x00, 0x02]),   # C2 encoder counts
        bytes([0x03, 0x00, 0x1C, 0x00, 0x01]),   # DE drive enable
        bytes([0x03, 0x00, 0x04, 0x00, 0x01]),   # BY busy
        bytes([0x03, 0x00, 0x4E, 0x00, 0x01]),   # OF output fault
        bytes([0x03, 0x00, 0x88, 0x00, 0x01]),   # VC velocity changing
        bytes([0x41, 0x20, 0x20, 0x54, 0x49]),   # IT temperatures (read only, no effect)
        bytes([0x03, 0x00, 0x57, 0x00, 0x02]),   # P
        bytes([0x41, 0x20, 0x20, 0x54, 0x56]),   # VT voltages (read only, no effect)
    ]

    def __init__(self, host, port):
        super().__init__(daemon=True, name="hmi")
        self.addr = (host, port)
        self.values = {}

    def run(self):
        tid = 0
        i = 0
        while True:
            try:
                s = socket.create_connection(self.addr, timeout=2.0)
            except OSError:
                time.sleep(1.0)
                continue
            try:
                s.settimeout(1.0)
                nxt = time.monotonic()
                while True:
                    pdu = self.POLL[i % len(self.POLL)]
                    i += 1
                    tid = (tid + 1) & 0xFFFF
                    s.sendall(struct.pack(">HHHB", tid, 0, len(pdu) + 1, self.UNIT) + pdu)
                    hdr = self._recv(s, 7)
                    rtid, pid, ln, uid = struct.unpack(">HHHB", hdr)
                    body = self._recv(s, ln - 1)
                    if rtid != tid:
                        raise OSError("transaction mismatch")
                    self.values[pdu] = body
                    nxt += self.PERIOD
                    d = nxt - time.monotonic()
                    if d > 0:
                        time.sleep(d)
                    else:
                        nxt = time.monotonic()
            except (OSError, ValueError, struct.error):
                pass
            finally:
                try:
                    s.close()
                except OSError:
                    pass
            time.sleep(1.0)

    @staticmethod
    def _recv(s, n):
        b = b""
        while len(b) < n:
            c = s.recv(n - len(b))
            if not c:
                raise OSError("closed")
            b += c
        return b


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", required=True)
    ap.add_argument("--state", default=None)
    a = ap.parse_args()
    host, _, port = a.listen.rpartition(":")
    srv = Server(a.state)
    try:
        asyncio.run(srv.main(host, int(port)))
    except KeyboardInterrupt:
        srv.write_state()
    os._exit(0)


if __name__ == "__main__":
    main()
