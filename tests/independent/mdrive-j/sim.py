#!/usr/bin/env python3
"""MDrive Plus2 Motion Control (Modbus/TCP, no encoder) -- clean-room firmware simulator.

Model: an Ethernet controller (Modbus/TCP server, lwIP-like stack) in front of a motion
processor (MCode engine).  See DECISIONS.md for the timing model and every choice made.
Standard library only.
"""
import argparse
import asyncio
import json
import math
import os
import random
import signal
import socket
import struct
import sys
import time

# ----------------------------------------------------------------------------------------------
# constants
MAX_CONN = 4
IDLE_TIMEOUT = 60.0
TX_BUF = 32
QUEUE_HIGH = 16
QUEUE_LOW = 8
PROCESS_DEADLINE = 0.300       # processing done at most this long after arrival
MOTION_TICK = 0.005

MS_SET = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)

DEVICE_ID = {
    0: b"SEM USA",
    1: b"MDI1PRD23A7-EQ",
    2: b"4.0.0.0",
    3: b"www.imshome.com",
    4: b"MDrive Ethernet",
    5: b"0312A0001",
    6: b"ASI 4.0.0.0",
}

INPUT_FUNCS = (0, 1, 2, 3, 5, 7, 8, 11)
OUTPUT_FUNCS = (16, 17, 18, 20, 23)          # 21, 24, 25 are hybrid-only


def wrap32(v):
    v = int(v) & 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


class ModbusExc(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# ----------------------------------------------------------------------------------------------
# register map: name, address, number of registers, access, signed, default
# access: rw, ro, cmd (write-only command)
ITEMS = [
    ("A", 0x0000, 2, "rw", False, 1000000),
    ("C1", 0x0005, 2, "rw", True, 0),
    ("C2", 0x0007, 2, "rw", True, 0),
    ("CE", 0x0009, 1, "rw", False, 1),
    ("CM", 0x000B, 1, "rw", False, 0),
    ("D1", 0x000F, 1, "rw", False, 0),
    ("D2", 0x0010, 1, "rw", False, 0),
    ("D3", 0x0011, 1, "rw", False, 0),
    ("D4", 0x0012, 1, "rw", False, 0),
    ("D5", 0x0013, 1, "rw", False, 0),
    ("D", 0x0018, 2, "rw", False, 1000000),
    ("DB", 0x001A, 1, "rw", False, 10),
    ("DC", 0x001B, 1, "cmd", False, None),
    ("DE", 0x001C, 1, "rw", False, 1),
    ("EE", 0x001E, 1, "rw", False, 0),
    ("EF", 0x001F, 1, "ro", False, 0),
    ("ER", 0x0021, 1, "rw", False, 0),
    ("HC", 0x0029, 1, "rw", False, 5),
    ("HM", 0x002B, 1, "rw", False, 1),
    ("HT", 0x002C, 1, "rw", False, 500),
    ("I1", 0x002D, 1, "ro", False, None),
    ("I2", 0x002E, 1, "ro", False, None),
    ("I3", 0x002F, 1, "ro", False, None),
    ("I4", 0x0030, 1, "ro", False, None),
    ("I5", 0x0031, 1, "ro", False, None),
    ("I6", 0x0032, 1, "ro", False, None),
    ("IC", 0x0037, 1, "cmd", False, None),
    ("IL", 0x003A, 1, "ro", False, None),
    ("IN", 0x003B, 1, "ro", False, None),
    ("JE", 0x003F, 1, "rw", False, 0),
    ("LM", 0x0042, 1, "rw", False, 1),
    ("MA", 0x0043, 2, "cmd", True, None),
    ("MP", 0x0045, 1, "ro", False, None),
    ("MR", 0x0046, 2, "cmd", True, None),
    ("MS", 0x0048, 1, "rw", False, 256),
    ("MT", 0x0049, 1, "rw", False, 0),
    ("MV", 0x004A, 1, "ro", False, None),
    ("O1", 0x004B, 1, "rw", False, None),
    ("O2", 0x004C, 1, "rw", False, None),
    ("O3", 0x004D, 1, "rw", False, None),
    ("O4", 0x004E, 1, "rw", False, None),
    ("OL", 0x0055, 1, "rw", False, None),
    ("OT", 0x0056, 1, "rw", False, None),
    ("P", 0x0057, 2, "rw", True, None),
    ("PC", 0x0059, 2, "ro", True, 0),
    ("PM", 0x005C, 1, "rw", False, 0),
    ("R1", 0x005F, 2, "rw", True, 0),
    ("R2", 0x0061, 2, "rw", True, 0),
    ("R3", 0x0063, 2, "rw", True, 0),
    ("R4", 0x0065, 2, "rw", True, 0),
    ("RC", 0x0067, 1, "rw", False, 25),
    ("S", 0x0076, 1, "cmd", False, None),
    ("SF", 0x0077, 1, "rw", False, 15),
    ("SL", 0x0078, 2, "cmd", True, None),
    ("SM", 0x007A, 1, "rw", False, 0),
    ("ST", 0x007B, 1, "rw", False, 0),
    ("TE", 0x007D, 1, "rw", False, 0),
    ("V", 0x0085, 2, "ro", True, None),
    ("VC", 0x0088, 1, "ro", False, None),
    ("VI", 0x0089, 2, "rw", False, 1000),
    ("VM", 0x008B, 2, "rw", False, 768000),
] + [("V%d" % (i + 1), 0x00A8 + 2 * i, 2, "rw", True, 0) for i in range(8)]

ITEM_BY_NAME = {it[0]: it for it in ITEMS}
ADDR_MAP = {}          # address -> (item, word index)
for _it in ITEMS:
    for _w in range(_it[2]):
        ADDR_MAP[_it[1] + _w] = (_it, _w)

# plain stored settings (those with a default value that live in the value table)
STORED = [it[0] for it in ITEMS if it[5] is not None]
# settings a Save writes to NVM
NVM_ITEMS = [it[0] for it in ITEMS if it[3] == "rw" and it[5] is not None
             and it[0] not in ("C1", "C2", "ER", "ST")]

RANGES = {
    "A": (91, 1525878997), "D": (91, 1525878997),
    "CE": (0, 1), "CM": (0, 1), "DE": (0, 1), "JE": (0, 1), "SM": (0, 1),
    "D1": (0, 255), "D2": (0, 255), "D3": (0, 255), "D4": (0, 255), "D5": (0, 255),
    "DB": (0, 65000), "SF": (0, 65000), "MT": (0, 65000),
    "HC": (0, 100), "RC": (1, 100), "HM": (1, 4), "LM": (1, 6),
    "EE": (0, 0), "PM": (0, 0), "ER": (0, 0), "ST": (0, 0),
    "O1": (0, 1), "O2": (0, 1), "O3": (0, 1), "O4": (0, 1),
    "OL": (0, 15), "OT": (0, 15),
    "SL": (-5000000, 5000000),
    "DC": (1, 12), "IC": (1, 12),
}

VENDOR_RW = ("S1", "S2", "S3", "S4", "S5", "S7", "S8", "S13", "CR", "TR")
VENDOR_PROG = ("E", "EX", "PS", "RS")


# ----------------------------------------------------------------------------------------------
class Drive:
    def __init__(self):
        self.v = {}
        for it in ITEMS:
            if it[5] is not None:
                self.v[it[0]] = it[5]
        self.io = {1: [0, 0, 0], 2: [0, 0, 0], 3: [0, 0, 0], 4: [0, 0, 0]}
        self.out_latch = {1: 0, 2: 0, 3: 0, 4: 0}
        self.s5 = [9, 0]
        self.s7 = [33, 0]
        self.s8 = [33, 0]
        self.s13 = [60, 0]
        self.cr_milli = 1000
        self.tr = [0, 0, 0]
        self.program = "idle"          # no program stored on a factory-fresh drive
        # motion
        self.pos = 0.0
        self.vel = 0.0
        self.mode = None               # None | 'pos' | 'slew'
        self.target = 0
        self.slew_v = 0.0
        self.changing = False
        self.last_t = time.monotonic()
        self.trip_ref = 0
        self.nvm = self.nvm_image()
        self.counters = {"requests": 0, "responses": 0, "exceptions": 0, "discarded_frames": 0,
                         "connections_accepted": 0, "connections_refused": 0}

    # ---------------- NVM
    def nvm_image(self):
        img = {k: self.v[k] for k in NVM_ITEMS}
        img.update({"S1": list(self.io[1]), "S2": list(self.io[2]), "S3": list(self.io[3]),
                    "S4": list(self.io[4]), "S5": list(self.s5), "S7": list(self.s7),
                    "S8": list(self.s8), "S13": list(self.s13), "CR": self.cr_milli,
                    "TR": list(self.tr)})
        return img

    # ---------------- motion
    @property
    def moving(self):
        return self.mode is not None

    def P(self):
        return wrap32(round(self.pos))

    def update(self, now=None):
        if now is None:
            now = time.monotonic()
        dt_total = now - self.last_t
        self.last_t = now
        if self.mode is None or dt_total <= 0:
            return
        while dt_total > 0 and self.mode is not None:
            dt = min(dt_total, 0.002)
            dt_total -= dt
            self._step(dt)

    def _step(self, dt):
        A = float(self.v["A"]); D = float(self.v["D"])
        VI = float(self.v["VI"]); VM = float(self.v["VM"])
        old = round(self.pos)
        speed = abs(self.vel)
        if self.mode == "pos":
            rem = self.target - self.pos
            direction = 1.0 if rem >= 0 else -1.0
            rem = abs(rem)
            dec_dist = (speed * speed - VI * VI) / (2 * D) if speed > VI else 0.0
            if rem <= dec_dist + speed * dt:
                ns = max(VI, speed - D * dt)
            else:
                ns = min(VM, max(VI, speed + A * dt))
            self.changing = ns != speed
            step = ns * dt
            if step >= rem:
                self.pos = float(self.target)
                self._stop()
            else:
                self.pos += direction * step
                self.vel = direction * ns
        else:  # slew
            tv = self.slew_v
            if tv == 0 or (self.vel != 0 and (tv > 0) != (self.vel > 0)):
                # decelerate towards stop (possibly to reverse)
                ns = speed - D * dt
                if ns <= VI:
                    if tv == 0:
                        self.pos += math.copysign(max(speed, 0) * dt, self.vel) if self.vel else 0
                        self._apply_counter(old)
                        self._stop()
                        return
                    self.vel = math.copysign(min(VI, abs(tv)), tv)
                    self.changing = True
                else:
                    self.vel = math.copysign(ns, self.vel)
                    self.changing = True
            else:
                ta = abs(tv)
                if speed == 0:
                    speed = min(VI, ta)
                if speed < ta:
                    ns = min(ta, speed + A * dt)
                elif speed > ta:
                    ns = max(ta, speed - D * dt)
                else:
                    ns = speed
                self.changing = ns != speed
                self.vel = math.copysign(ns, tv)
            self.pos += self.vel * dt
            if abs(self.pos) > 2 ** 31 + 2 ** 20:
                self.pos = float(wrap32(round(self.pos)))
        self._apply_counter(old)

    def _apply_counter(self, old):
        delta = round(self.pos) - old
        if delta:
            self.v["C1"] = wrap32(self.v["C1"] + delta)
            if self.v["TE"] & 16 and self.tr[0] != 0:
                if abs(round(self.pos) - self.trip_ref) >= abs(self.tr[0]):
                    self.v["TE"] = 0     # trip fired; must be re-enabled via 0x007D

    def _stop(self):
        self.mode = None
        self.vel = 0.0
        self.changing = False

    # ---------------- I/O
    def point_state(self, n):
        t = self.io[n][0]
        if t < 16:
            return 0                   # inputs: nothing wired -> inactive
        if t == 16:
            return self.out_latch[n]
        if t == 17:
            return 1 if self.moving else 0
        if t == 18:
            return self.v["EF"]
        if t == 20:
            return 1 if self.changing else 0
        if t == 23:
            return 1 if self.mode == "pos" else 0
        return 0

    def is_output(self, n):
        return self.io[n][0] >= 16

    def out_group(self):
        return sum((self.point_state(n) << (n - 1)) for n in range(1, 5) if self.is_output(n))

    # ---------------- register read
    def item_value(self, name):
        v = self.v
        if name in ("I1", "I2", "I3", "I4"):
            return self.point_state(int(name[1]))
        if name in ("I5", "I6"):
            return 0
        if name in ("IL", "IN"):
            return sum(self.point_state(n) << (n - 1) for n in range(1, 5))
        if name == "MP":
            return 1 if self.mode == "pos" else 0
        if name == "MV":
            return 1 if self.moving else 0
        if name == "VC":
            return 1 if self.changing else 0
        if name == "V":
            return wrap32(round(self.vel))
        if name == "P":
            return self.P()
        if name in ("O1", "O2", "O3", "O4"):
            return self.point_state(int(name[1]))
        if name in ("OL", "OT"):
            return self.out_group()
        return v[name]

    # ---------------- register write (motion-processor side)
    def check_value(self, name, val, tmp):
        """Return exception code (3) if value not acceptable, else None."""
        if name in RANGES:
            lo, hi = RANGES[name]
            if not lo <= val <= hi:
                return 3
        if name == "MS" and val not in MS_SET:
            return 3
        if name == "HT":
            if val == 1 or not 0 <= val <= 65535:
                return 3
            if val + tmp["MT"] > 65535:
                return 3
        if name == "MT" and val + tmp["HT"] > 65535:
            return 3
        if name == "VI" and not 1 <= val <= tmp["VM"] - 1:
            return 3
        if name == "VM" and not tmp["VI"] + 1 <= val <= 5000000:
            return 3
        if name == "TE" and val not in (0, 16):
            return 3
        return None

    def check_feasible(self, name, val):
        """Conditions the motion processor refuses -> 4."""
        if name in ("O1", "O2", "O3", "O4") and not self.is_output(int(name[1])):
            return 4
        if name in ("MA", "MR"):
            if self.v["DE"] == 0 or self.moving:
                return 4
        if name == "SL":
            if self.v["DE"] == 0 and val != 0:
                return 4
            if self.mode == "pos" and val != 0:
                return 4
        if name == "P" and self.moving:
            return 4
        if name in ("DC", "IC"):
            var = ("R%d" % val) if val <= 4 else ("V%d" % (val - 4))
            nv = self.v[var] + (1 if name == "IC" else -1)
            if not -2 ** 31 <= nv <= 2 ** 31 - 1:
                return 4
        return None

    def apply(self, name, val):
        if name in ("O1", "O2", "O3", "O4"):
            n = int(name[1])
            if self.io[n][0] == 16:
                self.out_latch[n] = val
            return
        if name in ("OL", "OT"):
            for n in range(1, 5):
                if self.io[n][0] == 16:
                    self.out_latch[n] = (val >> (n - 1)) & 1
            return
        if name == "P":
            self.pos = float(val)
            return
        if name == "MA":
            self._start_pos(val)
            return
        if name == "MR":
            self._start_pos(round(self.pos) + val)
            return
        if name == "SL":
            if val == 0:
                if self.moving:
                    self.mode = "slew"
                    self.slew_v = 0.0
                return
            self.mode = "slew"
            self.slew_v = float(val)
            return
        if name == "S":
            self.nvm = self.nvm_image()
            return
        if name in ("DC", "IC"):
            var = ("R%d" % val) if val <= 4 else ("V%d" % (val - 4))
            self.v[var] += (1 if name == "IC" else -1)
            return
        if name == "ER":
            self.v["ER"] = 0
            self.v["EF"] = 0
            return
        if name == "TE":
            self.v["TE"] = val
            self.trip_ref = self.P()
            return
        if name == "DE":
            self.v["DE"] = val
            if val == 0 and self.moving:
                self._stop()
            return
        self.v[name] = val

    def _start_pos(self, target):
        self.target = int(target)
        if self.target == round(self.pos):
            return
        self.mode = "pos"
        self.vel = 0.0
        self.last_t = time.monotonic()

    # ---------------- vendor parameters
    def vendor_read(self, mn):
        if mn in ("S1", "S2", "S3", "S4"):
            vals = self.io[int(mn[1])]
        elif mn == "S5":
            vals = self.s5
        elif mn == "S7":
            vals = self.s7
        elif mn == "S8":
            vals = self.s8
        elif mn == "S13":
            vals = self.s13
        elif mn == "TR":
            vals = self.tr
        elif mn == "CR":
            return ("%d.%03d" % divmod(self.cr_milli, 1000)).encode()
        else:
            raise ModbusExc(2)
        return ", ".join(str(x) for x in vals).encode()

    def vendor_write(self, mn, data):
        try:
            s = data.decode("ascii")
        except UnicodeDecodeError:
            raise ModbusExc(3)
        if not s.startswith("="):
            raise ModbusExc(3)
        body = s[1:]
        if mn == "CR":
            if len(data) > 6 or not body:
                raise ModbusExc(3)
            parts = body.split(".")
            if len(parts) > 2 or not all(p.isdigit() for p in parts if p != "") or parts[0] == "":
                raise ModbusExc(3)
            frac = (parts[1] if len(parts) == 2 else "")
            if len(frac) > 3:
                raise ModbusExc(3)
            milli = int(parts[0]) * 1000 + int((frac + "000")[:3] or 0)
            if milli <= 0:
                raise ModbusExc(3)
            self.cr_milli = milli
            return
        fields = body.split(",")
        try:
            nums = [int(f) for f in fields if f.strip() == f and f != ""]
        except ValueError:
            raise ModbusExc(3)
        if len(nums) != len(fields):
            raise ModbusExc(3)
        if any(f.startswith("+") for f in fields):
            raise ModbusExc(3)
        if mn == "TR":
            if len(data) > 11 or not 1 <= len(nums) <= 3:
                raise ModbusExc(3)
            nums = nums + [0] * (3 - len(nums))
            if not -2 ** 31 <= nums[0] <= 2 ** 31 - 1 or not 0 <= nums[1] <= 65535 or nums[2] != 0:
                raise ModbusExc(3)
            self.tr = nums
            return
        if mn in ("S1", "S2", "S3", "S4"):
            if len(nums) != 3 or not (6 <= len(data) <= 7):
                raise ModbusExc(3)
            if nums[0] not in INPUT_FUNCS + OUTPUT_FUNCS or nums[1] not in (0, 1) or nums[2] not in (0, 1):
                raise ModbusExc(3)
            if any(f.startswith("-") for f in fields):
                raise ModbusExc(3)
            n = int(mn[1])
            if nums[0] != 16:
                self.out_latch[n] = 0
            self.io[n] = nums
            return
        if len(nums) != 2 or not (4 <= len(data) <= 5) or any(f.startswith("-") for f in fields):
            raise ModbusExc(3)
        if mn == "S5":
            if nums[0] not in (9, 10) or nums[1] not in (0, 1):
                raise ModbusExc(3)
            self.s5 = nums
        elif mn in ("S7", "S8"):
            if nums[0] not in (33, 34, 35, 49, 50, 51) or nums[1] not in (0, 1):
                raise ModbusExc(3)
            setattr(self, mn.lower(), nums)
        elif mn == "S13":
            if nums[0] not in (60, 61) or nums[1] not in (0, 1):
                raise ModbusExc(3)
            self.s13 = nums

    def program_cmd(self, mn, data):
        if mn == "EX":
            lab = data.decode("ascii", "replace")
            ok = 1 <= len(lab) <= 4 and (lab.isdigit() or (lab[0].isalpha() and lab.isalnum()))
            if not ok:
                raise ModbusExc(3)
            raise ModbusExc(4)         # no program stored at that label/address
        if data:
            raise ModbusExc(3)
        if mn == "E":
            self.program = "idle"
        elif mn == "PS":
            if self.program == "running":
                self.program = "paused"
        elif mn == "RS":
            if self.program == "paused":
                self.program = "running"

    # ---------------- state dump
    def dump(self):
        self.update()
        regs = {}
        for addr in sorted(ADDR_MAP):
            it, w = ADDR_MAP[addr]
            if it[3] == "cmd":
                continue
            regs["0x%04X" % addr] = self.words(it)[w]
        items = {}
        for it in ITEMS:
            if it[3] != "cmd":
                items[it[0]] = self.item_value(it[0])
        return {
            "device": "MDrive Plus2 Motion Control, Modbus/TCP, no encoder",
            "holding_registers": regs,
            "items": items,
            "coils": {"0x%04X" % (0x004B + n - 1): self.point_state(n) for n in range(1, 5)},
            "discrete_inputs": {"0x%04X" % (0x002D + n - 1): self.point_state(n) for n in range(1, 5)},
            "output_latches": {str(n): self.out_latch[n] for n in range(1, 5)},
            "vendor_parameters": {
                "S1": self.io[1], "S2": self.io[2], "S3": self.io[3], "S4": self.io[4],
                "S5": self.s5, "S7": self.s7, "S8": self.s8, "S13": self.s13,
                "CR": "%d.%03d" % divmod(self.cr_milli, 1000), "TR": self.tr},
            "program": self.program,
            "motion": {"mode": self.mode or "stopped", "target": self.target if self.mode == "pos" else None},
            "nvm": self.nvm,
            "device_identification": {str(k): v.decode() for k, v in DEVICE_ID.items()},
            "diagnostic_counters": dict(self.counters),
        }

    def words(self, it):
        val = self.item_value(it[0])
        if it[2] == 1:
            return [val & 0xFFFF]
        u = val & 0xFFFFFFFF
        return [u >> 16, u & 0xFFFF]


# ----------------------------------------------------------------------------------------------
# request preparation (Ethernet-controller side: pure checks on the request) -> (ms, executor)

def jitter(a, b):
    return random.uniform(a, b)


def decode_mnemonic(b4):
    try:
        s = bytes(reversed(b4)).decode("ascii")
    except UnicodeDecodeError:
        return None
    s = s.rstrip(" ")
    if not s or " " in s:
        return None
    return s


def prepare(drive, pdu):
    """Returns (service_ms, kind, executor) where executor() -> response PDU (may raise ModbusExc).
    A gateway-level exception is returned as an executor that raises immediately with a short time."""
    fc = pdu[0]
    data = pdu[1:]

    def gw(code):
        def ex():
            raise ModbusExc(code)
        return (jitter(1.0, 2.0), "gateway", ex)

    if fc in (0x01, 0x02):
        if len(data) != 4:
            return gw(3)
        start, qty = struct.unpack(">HH", data)
        if not 1 <= qty <= 2000:
            return gw(3)
        base = 0x004B if fc == 1 else 0x002D
        if start < base or start + qty > base + 4:
            return gw(2)

        def ex():
            bits = 0
            for i in range(qty):
                bits |= drive.point_state(start - base + 1 + i) << i
            return bytes([fc, 1, bits])
        return (2.0 + 0.6 * qty + jitter(0, 1.5), "read", ex)

    if fc == 0x03:
        if len(data) != 4:
            return gw(3)
        start, qty = struct.unpack(">HH", data)
        if not 1 <= qty <= 4:
            return gw(3)
        items = []
        for a in range(start, start + qty):
            m = ADDR_MAP.get(a)
            if m is None or m[0][3] == "cmd":
                return gw(2)
            if m[0] not in items:
                items.append(m[0])

        def ex():
            out = bytearray([3, 2 * qty])
            snap = {it[0]: drive.words(it) for it in items}
            for it in items:
                if it[0] == "ER":
                    drive.apply("ER", 0)      # reading ER clears it (L1047)
            for a in range(start, start + qty):
                it, w = ADDR_MAP[a]
                out += struct.pack(">H", snap[it[0]][w])
            return bytes(out)
        return (2.0 + 0.6 * len(items) + jitter(0, 1.5), "read", ex)

    if fc == 0x05:
        if len(data) != 4:
            return gw(3)
        addr, val = struct.unpack(">HH", data)
        if val not in (0x0000, 0xFF00):
            return gw(3)
        if not 0x004B <= addr <= 0x004E:
            return gw(2)
        name = "O%d" % (addr - 0x004B + 1)

        def ex():
            v = 1 if val == 0xFF00 else 0
            c = drive.check_feasible(name, v)
            if c:
                raise ModbusExc(c)
            drive.apply(name, v)
            return bytes(pdu[:5])
        return (5.5 + jitter(0, 2.0), "write", ex)

    if fc == 0x10:
        if len(data) < 5:
            return gw(3)
        start, qty, bc = struct.unpack(">HHB", data[:5])
        if not 1 <= qty <= 4 or bc != 2 * qty or len(data) != 5 + bc:
            return gw(3)
        regs = struct.unpack(">%dH" % qty, data[5:])
        writes = []          # (item, value)
        a = start
        i = 0
        while i < qty:
            m = ADDR_MAP.get(a)
            if m is None:
                return gw(2)
            it, w = m
            if it[3] == "ro" or w != 0 or i + it[2] > qty:
                return gw(2)
            if it[2] == 2:
                u = (regs[i] << 16) | regs[i + 1]
                val = wrap32(u) if it[4] else u
            else:
                val = regs[i]
            writes.append((it, val))
            a += it[2]
            i += it[2]
        names = [it[0] for it, _ in writes]
        if "S" in names:
            ms, kind = jitter(160, 220), "save"
        elif any(n in ("MA", "MR", "SL", "P", "DC", "IC") for n in names):
            ms, kind = jitter(14, 24), "motion"
        else:
            ms, kind = 4.0 + 1.5 * len(writes) + jitter(0, 2.0), "write"

        def ex():
            tmp = dict(drive.v)
            for it, val in writes:
                c = drive.check_value(it[0], val, tmp)
                if c:
                    raise ModbusExc(c)
                if it[0] in tmp:
                    tmp[it[0]] = val
            for it, val in writes:
                c = drive.check_feasible(it[0], val)
                if c:
                    raise ModbusExc(c)
            for it, val in writes:
                drive.apply(it[0], val)
            return bytes([0x10]) + struct.pack(">HH", start, qty)
        return (ms, kind, ex)

    if fc in (0x41, 0x42):
        if len(data) < 4:
            return gw(3)
        mn = decode_mnemonic(data[:4])
        if mn is None or mn not in VENDOR_RW + VENDOR_PROG:
            if len(data) >= 4:
                return gw(2)
        rest = data[4:]
        if fc == 0x41:
            if mn == "EX":
                if len(rest) < 1 or len(rest) != 1 + rest[0] or rest[0] == 0:
                    return gw(3)
                payload = bytes(rest[1:])
            else:
                if rest:
                    return gw(3)
                payload = b""
            if mn in VENDOR_PROG:
                def ex():
                    drive.program_cmd(mn, payload)
                    return bytes([0x41, 0])
                return (jitter(18, 30), "program", ex)

            def ex():
                r = drive.vendor_read(mn)
                return bytes([0x41, len(r)]) + r
            return (jitter(5, 9), "vread", ex)
        # 0x42
        if len(rest) < 1 or len(rest) != 1 + rest[0]:
            return gw(3)
        bc = rest[0]
        payload = bytes(rest[1:])
        if bc > 28:
            return gw(3)
        if mn in VENDOR_PROG:
            def ex():
                drive.program_cmd(mn, payload)
                return bytes([0x42, bc]) + bytes(data[:4])
            return (jitter(18, 30), "program", ex)
        if bc == 0:
            return gw(3)

        def ex():
            drive.vendor_write(mn, payload)
            return bytes([0x42, bc]) + bytes(data[:4])
        return (jitter(12, 22), "vwrite", ex)

    if fc == 0x2B:
        if len(data) < 1:
            return gw(3)
        if data[0] != 0x0E:
            return gw(1)
        if len(data) != 3:
            return gw(3)
        code, oid = data[1], data[2]
        if code not in (1, 2, 3, 4):
            return gw(3)
        if code == 4:
            if oid not in DEVICE_ID:
                return gw(2)
            objs = [oid]
        else:
            last = 2 if code == 1 else 6
            if oid > last:
                oid = 0
            objs = list(range(oid, last + 1))

        def ex():
            out = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(objs)])
            for o in objs:
                out += bytes([o, len(DEVICE_ID[o])]) + DEVICE_ID[o]
            return bytes(out)
        return (18.0 + 3.0 * len(objs), "devid", ex)

    return gw(1)


# ----------------------------------------------------------------------------------------------
class Server:
    def __init__(self, state_file):
        self.drive = Drive()
        self.state_file = state_file
        self.conns = set()
        self.queue = asyncio.Queue()

    def dump_state(self):
        if not self.state_file:
            return
        try:
            tmp = self.state_file + ".tmp"
            with open(tmp, "w") as f:
                json.dump(self.drive.dump(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except OSError as e:
            print("state dump failed: %s" % e, file=sys.stderr)

    async def worker(self):
        d = self.drive
        while True:
            conn, frame, arrival = await self.queue.get()
            try:
                tid, _pid, _ln, uid = struct.unpack(">HHHB", frame[:7])
                pdu = frame[7:]
                d.update()
                ms, kind, ex = prepare(d, pdu)
                if kind != "gateway":
                    if d.moving:
                        ms += jitter(2.0, 4.0)           # own behaviour 2
                    if conn.first:
                        ms += jitter(8.0, 12.0)          # own behaviour 3
                conn.first = False
                ms = math.ceil(ms)                       # own behaviour 1: 1 ms tick
                now = time.monotonic()
                wait = min(ms / 1000.0, arrival + PROCESS_DEADLINE - now)
                if wait > 0:
                    await asyncio.sleep(wait)
                d.update()
                try:
                    rpdu = ex()
                except ModbusExc as e:
                    d.counters["exceptions"] += 1
                    rpdu = bytes([(pdu[0] | 0x80) & 0xFF, e.code])
                adu = struct.pack(">HHHB", tid, 0, len(rpdu) + 1, uid) + rpdu
                d.counters["responses"] += 1
                conn.send(adu)
            except Exception as e:  # never let one frame kill the task
                print("internal error: %r" % (e,), file=sys.stderr)
            finally:
                conn.pending -= 1
                conn.maybe_resume()

    async def motion_ticker(self):
        while True:
            await asyncio.sleep(MOTION_TICK)
            self.drive.update()

    async def idle_watch(self):
        while True:
            await asyncio.sleep(1.0)
            now = time.monotonic()
            for c in list(self.conns):
                if c.pending == 0 and now - c.last_rx > IDLE_TIMEOUT:
                    c.close()


class Conn(asyncio.Protocol):
    def __init__(self, server):
        self.srv = server
        self.tr = None
        self.buf = bytearray()
        self.buf_time = None
        self.first = True
        self.pending = 0
        self.paused = False
        self.closed = False
        self.last_rx = time.monotonic()
        self.txq = asyncio.Queue()
        self.txtask = None

    def connection_made(self, transport):
        self.tr = transport
        d = self.srv.drive
        if len(self.srv.conns) >= MAX_CONN:
            d.counters["connections_refused"] += 1
            self.closed = True
            transport.close()
            return
        d.counters["connections_accepted"] += 1
        self.srv.conns.add(self)
        sock = transport.get_extra_info("socket")
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 0)   # Nagle stays on
        except OSError:
            pass
        self.txtask = asyncio.get_running_loop().create_task(self.tx_loop())

    def connection_lost(self, exc):
        self.closed = True
        self.srv.conns.discard(self)
        if self.txtask:
            self.txtask.cancel()

    def close(self):
        if not self.closed:
            self.closed = True
            self.srv.conns.discard(self)
            self.tr.close()

    def data_received(self, data):
        if self.closed:
            return
        now = time.monotonic()
        self.last_rx = now
        if not self.buf:
            self.buf_time = now          # arrival time of the oldest unparsed byte
        self.buf += data
        self.parse()

    def parse(self):
        while len(self.buf) >= 7 and not self.paused and not self.closed:
            tid, pid, ln = struct.unpack(">HHH", self.buf[:6])
            if ln < 2 or ln > 254:
                self.srv.drive.counters["discarded_frames"] += 1
                self.buf.clear()
                self.close()
                return
            if len(self.buf) < 6 + ln:
                break
            frame = bytes(self.buf[:6 + ln])
            del self.buf[:6 + ln]
            if pid != 0:
                self.srv.drive.counters["discarded_frames"] += 1
                continue
            self.srv.drive.counters["requests"] += 1
            self.pending += 1
            self.srv.queue.put_nowait((self, frame, self.buf_time))
            if self.pending >= QUEUE_HIGH:
                self.paused = True
                self.tr.pause_reading()
        if not self.buf:
            self.buf_time = None

    def maybe_resume(self):
        if self.paused and self.pending <= QUEUE_LOW and not self.closed:
            self.paused = False
            self.parse()
            if not self.paused:
                try:
                    self.tr.resume_reading()
                except Exception:
                    pass

    def send(self, adu):
        if not self.closed:
            self.txq.put_nowait(adu)

    async def tx_loop(self):
        try:
            while True:
                adu = await self.txq.get()
                for i in range(0, len(adu), TX_BUF):
                    if self.closed:
                        break
                    if i:
                        await asyncio.sleep(0.0005)
                    self.tr.write(adu[i:i + TX_BUF])
        except asyncio.CancelledError:
            pass


async def main():
    ap = argparse.ArgumentParser(description="MDrive Plus2 Modbus/TCP simulator")
    ap.add_argument("--listen", default="127.0.0.1:502")
    ap.add_argument("--state", default=None)
    ap.add_argument("--baud", default=None, help="ignored (Ethernet-only product)")
    ap.add_argument("--parity", default=None, help="ignored (Ethernet-only product)")
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(":")
    srv = Server(args.state)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    loop.add_signal_handler(signal.SIGUSR1, srv.dump_state)
    server = await loop.create_server(lambda: Conn(srv), host or "127.0.0.1", int(port),
                                      reuse_address=True, backlog=8)
    tasks = [loop.create_task(srv.worker()), loop.create_task(srv.motion_ticker()),
             loop.create_task(srv.idle_watch())]
    p = server.sockets[0].getsockname()[1]
    print("listening tcp %s:%d" % (host or "127.0.0.1", p), flush=True)
    await stop.wait()
    server.close()
    for c in list(srv.conns):
        c.close()
    srv.dump_state()
    for t in tasks:
        t.cancel()


if __name__ == "__main__":
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
