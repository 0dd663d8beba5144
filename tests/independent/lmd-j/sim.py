#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet, closed loop (hMTechnology) -- Modbus/TCP drive simulator.

Written from the LMD MODBUS/TCP Fieldbus manual (LMD-MODBUS-REV-D) and the Modbus specs.
Standard library only.  See DECISIONS.md for every choice made where the manual is silent
or wrong, and for the timing model.
"""
import argparse
import asyncio
import json
import math
import os
import random
import re
import signal
import socket
import struct
import sys
import time

# --------------------------------------------------------------------------------------
# Register map (manual section 5).  (addr, mnemonic, nregs, access, lo, hi, default, signed)
# access: RW / RO / WO.  lo/hi None = no range check beyond the width.
# --------------------------------------------------------------------------------------
S32_MIN, S32_MAX = -2147483648, 2147483647
MS_VALUES = {1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127}

REG_TABLE = [
    (0x0000, "A", 2, "RW", 91, 1525878997, 1000000, False),
    (0x0004, "BY", 1, "RO", 0, 1, 0, False),
    (0x0005, "C1", 2, "RW", S32_MIN, S32_MAX, 0, True),
    (0x0007, "C2", 2, "RW", S32_MIN, S32_MAX, 0, True),
    (0x0009, "CE", 1, "RW", 0, 1, 1, False),
    (0x000E, "CW", 1, "RW", 0, 255, 10, False),
    (0x000F, "D1", 1, "RW", 0, 255, 0, False),
    (0x0010, "D2", 1, "RW", 0, 255, 0, False),
    (0x0011, "D3", 1, "RW", 0, 255, 0, False),
    (0x0012, "D4", 1, "RW", 0, 255, 0, False),
    (0x0013, "D5", 1, "RW", 0, 255, 0, False),
    (0x0018, "D", 2, "RW", 91, 1525878997, 1000000, False),
    (0x001A, "DB", 1, "RW", 0, 65000, 10, False),
    (0x001B, "DC", 1, "WO", 0, 65535, None, False),
    (0x001C, "DE", 1, "RW", 0, 1, 1, False),
    (0x001E, "EE", 1, "RW", 0, 1, 0, False),
    (0x001F, "EF", 1, "RO", 0, 1, 0, False),
    (0x0021, "ER", 1, "RW", 0, 0, 0, False),
    (0x0024, "FC", 1, "RW", 0, 9, 0, False),
    (0x0029, "HC", 1, "RW", 0, 100, 5, False),
    (0x002A, "HI", 1, "WO", 1, 4, None, False),
    (0x002B, "HM", 1, "WO", 1, 4, None, False),
    (0x002C, "HT", 1, "RW", 0, 65535, 500, False),
    (0x002D, "I1", 1, "RO", 0, 1, 0, False),
    (0x002E, "I2", 1, "RO", 0, 1, 0, False),
    (0x002F, "I3", 1, "RO", 0, 1, 0, False),
    (0x0030, "I4", 1, "RO", 0, 1, 0, False),
    (0x0031, "I5", 1, "RO", 0, 1023, 0, False),
    (0x0032, "I6", 1, "RO", 0, 1, 0, False),
    (0x0037, "IC", 1, "WO", 0, 65535, None, False),
    (0x003B, "IN", 1, "RO", 0, 15, 0, False),
    (0x003C, "IP", 1, "WO", 0, 65535, None, False),
    (0x003F, "JE", 1, "RW", 0, 1, 0, False),
    (0x0042, "LM", 1, "RW", 1, 6, 1, False),
    (0x0043, "MA", 2, "WO", S32_MIN, S32_MAX, None, True),
    (0x0045, "MP", 1, "RO", 0, 1, 0, False),
    (0x0046, "MR", 2, "WO", S32_MIN, S32_MAX, None, True),
    (0x0048, "MS", 1, "RW", 1, 256, 256, False),
    (0x0049, "MT", 1, "RW", 0, 65000, 0, False),
    (0x004A, "MV", 1, "RO", 0, 1, 0, False),
    (0x004B, "O1", 1, "RW", 0, 1, 0, False),
    (0x004C, "O2", 1, "RW", 0, 1, 0, False),
    (0x004D, "O3", 1, "RW", 0, 1, 0, False),
    (0x004E, "OF", 1, "RO", 0, 1, 0, False),
    (0x0056, "OT", 1, "RW", 0, 15, 0, False),
    (0x0057, "P", 2, "RW", S32_MIN, S32_MAX, 0, True),
    (0x0059, "PC", 2, "RO", S32_MIN, S32_MAX, 0, True),
    (0x005C, "PM", 1, "RW", 0, 1, 0, False),
    (0x005F, "R1", 2, "RW", S32_MIN, S32_MAX, 0, True),
    (0x0061, "R2", 2, "RW", S32_MIN, S32_MAX, 0, True),
    (0x0063, "R3", 2, "RW", S32_MIN, S32_MAX, 0, True),
    (0x0065, "R4", 2, "RW", S32_MIN, S32_MAX, 0, True),
    (0x0067, "RC", 1, "RW", 1, 100, 25, False),
    (0x0076, "S", 1, "WO", 0, 65535, None, False),
    (0x0077, "SF", 1, "RW", 0, 65000, 15, False),
    (0x0078, "SL", 2, "WO", -5000000, 5000000, None, True),
    (0x007A, "SM", 1, "RW", 0, 1, 0, False),
    (0x007B, "ST", 1, "RW", 0, 0, 0, False),
    (0x007D, "TE", 1, "RW", 0, 43, 0, False),
    (0x0085, "V", 2, "RO", S32_MIN, S32_MAX, 0, True),
    (0x0088, "VC", 1, "RO", 0, 1, 0, False),
    (0x0089, "VI", 2, "RW", 1, 2559999, 1000, False),
    (0x008B, "VM", 2, "RW", 2, 2560000, 768000, False),
    (0x008D, "WT", 1, "RW", 0, 84, 80, False),
    (0x008E, "AS", 1, "RW", 0, 3, 2, False),
    (0x008F, "AF", 1, "RO", 0, 255, 208, False),
    (0x0091, "CB", 1, "RW", 0, 3, 1, False),
    (0x0093, "CF", 1, "WO", 0, 65535, None, False),
    (0x0095, "LD", 2, "RW", 0, 2147483647, 102400, False),
    (0x0097, "LG", 2, "RW", 0, 2147483647, 102400, False),
    (0x0099, "LL", 2, "RO", -2147483647, 2147483647, 0, True),
    (0x009B, "LR", 1, "RO", 0, 1, 0, False),
    (0x009C, "LT", 2, "RW", 2, 65535, 2000, False),
    (0x009E, "MF", 2, "RW", 306, 2560000, 768000, False),
    (0x00A0, "MU", 1, "RW", 0, 2, 0, False),
    (0x00A1, "SC", 1, "WO", 0, 65535, None, False),
    (0x00A3, "TS", 2, "RW", 0, 255, 0, False),
    (0x00A5, "TD", 1, "RW", 0, 1, 1, False),
    (0x00A6, "TQ", 1, "RW", 1, 100, 25, False),
    (0x00A7, "VF", 1, "RW", 0, 1000, 0, False),
] + [(0x00A8 + 2 * i, "V%d" % (i + 1), 2, "RW", S32_MIN, S32_MAX, 0, True) for i in range(8)]

MAX_ADDR = 0x00B7
REG_BY_ADDR = {r[0]: r for r in REG_TABLE}
REG_BY_MN = {r[1]: r for r in REG_TABLE}
USER_VARS = ["R1", "R2", "R3", "R4"] + ["V%d" % i for i in range(1, 9)]
# configuration parameters that IP resets and S saves
CONFIG = [r[1] for r in REG_TABLE if r[3] == "RW" and r[6] is not None and r[1] not in
          ("P", "C1", "C2", "O1", "O2", "O3", "OT", "ER", "ST")
          and r[1] not in USER_VARS]

# Manufacturer-specific settings (FC65/66) with defaults
MFG_DEFAULTS = {
    "AO": 0, "RD": 0, "AJ": 0, "AT": 0, "BE": 0, "BL": 0, "BM": 0, "DJ": 0, "DT": 0,
    "FS": 0, "FL": 0,
    "IS": {"1": [0, 0], "2": [0, 0], "3": [0, 0], "4": [0, 0], "5": [9, 0]},
    "OS": {"1": [16, 0], "2": [16, 0], "3": [16, 0]},
    "LS": [0, 0, 0], "TR": [0, 0, 0],
}
MFG_SIMPLE_RANGES = {"AO": (0, 65535), "RD": (0, 1), "AJ": (0, 999), "AT": (0, 1),
                     "BE": (0, 1), "BL": (0, 2147483647), "BM": (0, 1), "DJ": (0, 999),
                     "DT": (0, 1), "FS": (0, 65535), "FL": (0, 1)}
IS_TYPES = {0, 1, 2, 3, 5, 7, 8, 11, 12}
OS_TYPES = {16, 17, 18, 20, 21, 23, 24, 25, 28, 29}

DEVICE_ID = {
    0: b"IMS USA",
    1: b"LMDCE571",
    2: b"4.0.0.0",
    3: b"https://novantaims.com/",
    4: b"LMD Ethernet",
    5: b"269190011",
    6: b"LMDCM 6.004, Hw: 1.0",
}


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


def deepcopy_json(x):
    return json.loads(json.dumps(x))


# --------------------------------------------------------------------------------------
# Drive model
# --------------------------------------------------------------------------------------
class Drive:
    def __init__(self):
        self.regs = {r[1]: r[6] for r in REG_TABLE if r[6] is not None}
        self.mfg = deepcopy_json(MFG_DEFAULTS)
        self.outputs = 0          # 4-bit output image (outputs 1..4)
        self.inputs = 0           # unwired inputs
        self.analog = 0
        self.pos = 0.0            # position in steps (float), P = round(pos)
        self.c1 = 0.0
        self.c2 = 0.0
        self.vel = 0.0            # signed steps/s
        self.mode = None          # None | "move" | "slew" | "home"
        self.target = 0
        self.slew_target = 0.0
        self.home_end = 0.0
        self.changing = False
        self.er = 0
        self.ef = 0
        self.stall = 0
        self.calib_until = 0.0
        self.last_update = time.monotonic()
        self.program_stored = False
        self.program_running = False
        self.nvm = {"registers": {m: self.regs[m] for m in CONFIG},
                    "mfg": deepcopy_json(MFG_DEFAULTS)}
        self.counters = {"requests": 0, "responses": 0, "exceptions": 0,
                         "discarded_frames": 0, "connections_accepted": 0,
                         "connections_refused": 0, "connections_closed_idle": 0,
                         "framing_errors": 0}

    # ---------------- motion ----------------
    @property
    def moving(self):
        return self.mode is not None

    def update(self, now=None):
        if now is None:
            now = time.monotonic()
        dt_total = now - self.last_update
        self.last_update = now
        if self.mode is None or dt_total <= 0:
            self.changing = False
            return
        dt_total = min(dt_total, 120.0)
        step = 0.001
        while dt_total > 1e-9 and self.mode is not None:
            dt = min(step, dt_total)
            dt_total -= dt
            self._step(dt, now - dt_total)

    def _move_by(self, d):
        self.pos += d
        self.c1 += d
        self.c2 += d
        # 32-bit wrap of the position counter
        if self.pos > S32_MAX or self.pos < S32_MIN:
            self.pos = ((int(self.pos) - S32_MIN) % (1 << 32)) + S32_MIN
        if self.c1 > S32_MAX or self.c1 < S32_MIN:
            self.c1 = ((int(self.c1) - S32_MIN) % (1 << 32)) + S32_MIN
        if self.c2 > S32_MAX or self.c2 < S32_MIN:
            self.c2 = ((int(self.c2) - S32_MIN) % (1 << 32)) + S32_MIN

    def _step(self, dt, t):
        A = float(self.regs["A"])
        D = float(self.regs["D"])
        VI = float(self.regs["VI"])
        VM = float(self.regs["VM"])
        if self.mode == "move":
            rem = self.target - self.pos
            if abs(rem) < 0.5:
                self.pos = float(self.target)
                self._stop()
                return
            direction = 1.0 if rem > 0 else -1.0
            speed = abs(self.vel)
            if self.vel * direction < 0:       # reversing: decelerate first
                speed = max(0.0, speed - D * dt)
                self.vel = math.copysign(speed, self.vel)
                self._move_by(self.vel * dt)
                self.changing = True
                if speed <= VI:
                    self.vel = 0.0
                return
            speed = max(speed, VI)
            stop_dist = max(0.0, (speed * speed - VI * VI) / (2.0 * D))
            if abs(rem) <= stop_dist + speed * dt:
                speed = max(VI, speed - D * dt)
                self.changing = True
            elif speed < VM:
                speed = min(VM, speed + A * dt)
                self.changing = True
            else:
                speed = VM
                self.changing = False
            d = speed * dt
            if d >= abs(rem):
                self._move_by(rem)
                self.pos = float(self.target)
                self._stop()
                return
            self.vel = direction * speed
            self._move_by(direction * d)
        elif self.mode == "slew":
            tgt = self.slew_target
            if tgt == 0 and abs(self.vel) <= VI:
                self._stop()
                return
            if abs(self.vel) < VI and tgt != 0 and self.vel * tgt >= 0:
                self.vel = math.copysign(VI, tgt)
            diff = tgt - self.vel
            if abs(diff) < 1e-6:
                self.changing = False
            else:
                # speeding up in the same direction uses A, else D
                rate = A if (abs(tgt) > abs(self.vel) and tgt * self.vel >= 0) else D
                dv = rate * dt
                if abs(diff) <= dv:
                    self.vel = tgt
                else:
                    self.vel += math.copysign(dv, diff)
                self.changing = True
            self._move_by(self.vel * dt)
        elif self.mode == "home":
            self._move_by(self.vel * dt)
            if t >= self.home_end:
                self.pos = 0.0
                self._stop()

    def _stop(self):
        self.mode = None
        self.vel = 0.0
        self.changing = False

    def start_move(self, target):
        self.update()
        self.target = int(target)
        self.mode = "move"

    def start_slew(self, v):
        self.update()
        if v == 0:
            if self.mode is None:
                return
            if self.mode == "slew":
                self.slew_target = 0.0
            else:
                # switch the running move into a controlled stop
                self.mode = "slew"
                self.slew_target = 0.0
            return
        self.mode = "slew"
        self.slew_target = float(v)

    def start_home(self, direction):
        self.update()
        self.mode = "home"
        self.vel = direction * float(self.regs["VI"])
        self.home_end = time.monotonic() + 0.35

    # ---------------- register access ----------------
    def af(self, now):
        v = 0
        if self.regs["AS"] != 0:
            v |= 16
        if not self.moving:
            v |= 64
        if now >= self.calib_until:
            v |= 128
        return v

    def read_value(self, mn, now):
        if mn == "BY":
            return 1 if self.program_running else 0
        if mn == "EF":
            return self.ef
        if mn == "ER":
            v = self.er
            self.er = 0
            self.ef = 0
            return v
        if mn in ("I1", "I2", "I3", "I4"):
            return (self.inputs >> (int(mn[1]) - 1)) & 1
        if mn == "I5":
            return self.analog
        if mn == "I6":
            return 0
        if mn == "IN":
            return self.inputs & 0xF
        if mn == "MP":
            return 1 if self.mode == "move" else 0
        if mn == "MV":
            return 1 if self.moving else 0
        if mn in ("O1", "O2", "O3"):
            return (self.outputs >> (int(mn[1]) - 1)) & 1
        if mn == "OF":
            return 0
        if mn == "OT":
            return self.outputs & 0xF
        if mn == "P":
            return int(round(self.pos))
        if mn == "C1":
            return int(round(self.c1))
        if mn == "C2":
            return int(round(self.c2))
        if mn == "PC":
            return 0
        if mn == "V":
            return 0 if self.regs["AS"] == 3 else int(round(self.vel))
        if mn == "VC":
            return 1 if (self.moving and self.changing) else 0
        if mn == "AF":
            return self.af(now)
        if mn == "LL":
            return 0
        if mn == "LR":
            return 0
        if mn == "ST":
            return self.stall
        return self.regs[mn]

    def snapshot_value(self, mn):
        """Value for the state dump (no side effects)."""
        if mn == "ER":
            return self.er
        return self.read_value(mn, time.monotonic())

    def reset_config(self):
        for r in REG_TABLE:
            if r[1] in CONFIG:
                self.regs[r[1]] = r[6]
        self.mfg = deepcopy_json(MFG_DEFAULTS)


def s32(v):
    return v - (1 << 32) if v & 0x80000000 else v


# --------------------------------------------------------------------------------------
# Modbus application layer.  Each handler returns (response_pdu, service_class)
# --------------------------------------------------------------------------------------
SVC = {
    "fast": (0.0010, 0.0030),
    "mcode": (0.006, 0.012),
    "motion": (0.012, 0.025),
    "devid": (0.015, 0.030),
    "ip": (0.120, 0.160),
    "cp": (0.200, 0.260),
    "save": (0.250, 0.320),
}


class Device:
    def __init__(self):
        self.d = Drive()

    def handle(self, pdu):
        """Return (response_pdu or None, service class)."""
        fc = pdu[0]
        try:
            if fc == 0x01:
                return self.fc01(pdu), "fast"
            if fc == 0x02:
                return self.fc02(pdu), "fast"
            if fc == 0x03:
                return self.fc03(pdu), "fast"
            if fc == 0x05:
                return self.fc05(pdu), "fast"
            if fc == 0x10:
                return self.fc16(pdu)
            if fc == 0x2B:
                return self.fc43(pdu), "devid"
            if fc == 0x41:
                return self.fc65(pdu), "mcode"
            if fc == 0x42:
                return self.fc66(pdu)
            raise ModbusError(1)
        except ModbusError as e:
            self.d.counters["exceptions"] += 1
            cls = {0x10: "fast", 0x2B: "devid", 0x41: "mcode", 0x42: "mcode"}.get(fc, "fast")
            return bytes([(fc | 0x80) & 0xFF, e.code]), cls

    # ---- bits ----
    def _bits_req(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(3)
        start, qty = struct.unpack(">HH", pdu[1:5])
        if qty < 1 or qty > 2000:
            raise ModbusError(3)
        if start + qty > 4:
            raise ModbusError(2)
        return start, qty

    def fc01(self, pdu):
        start, qty = self._bits_req(pdu)
        self.d.update()
        val = (self.d.outputs >> start) & ((1 << qty) - 1)
        return bytes([0x01, 1, val])

    def fc02(self, pdu):
        start, qty = self._bits_req(pdu)
        self.d.update()
        val = (self.d.inputs >> start) & ((1 << qty) - 1)
        return bytes([0x02, 1, val])

    def fc05(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(3)
        addr, value = struct.unpack(">HH", pdu[1:5])
        if value not in (0x0000, 0xFF00):
            raise ModbusError(3)
        if addr > 3:
            raise ModbusError(2)
        if value:
            self.d.outputs |= (1 << addr)
        else:
            self.d.outputs &= ~(1 << addr)
        return bytes(pdu)

    # ---- registers ----
    def _lookup(self, start, qty):
        r = REG_BY_ADDR.get(start)
        if r is None or start > MAX_ADDR:
            raise ModbusError(2)
        if qty != r[2]:
            raise ModbusError(2)
        return r

    def fc03(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(3)
        start, qty = struct.unpack(">HH", pdu[1:5])
        if qty < 1 or qty > 125:
            raise ModbusError(3)
        r = self._lookup(start, qty)
        if r[3] == "WO":
            raise ModbusError(2)
        now = time.monotonic()
        self.d.update(now)
        v = self.d.read_value(r[1], now)
        if r[2] == 1:
            data = struct.pack(">H", v & 0xFFFF)
        else:
            u = v & 0xFFFFFFFF
            data = struct.pack(">HH", u & 0xFFFF, u >> 16)   # low word first
        return bytes([0x03, len(data)]) + data

    def fc16(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(3)
        start, qty, bc = struct.unpack(">HHB", pdu[1:6])
        if qty < 1 or qty > 123 or bc != 2 * qty or len(pdu) != 6 + bc:
            raise ModbusError(3)
        r = self._lookup(start, qty)
        if r[3] == "RO":
            raise ModbusError(2)
        if qty == 1:
            raw = struct.unpack(">H", pdu[6:8])[0]
            val = raw
        else:
            lo, hi = struct.unpack(">HH", pdu[6:10])
            raw = (hi << 16) | lo
            val = s32(raw) if r[7] else raw
        cls = self.write_reg(r, val)
        return bytes([0x10]) + struct.pack(">HH", start, qty), cls

    def write_reg(self, r, val):
        d = self.d
        mn = r[1]
        lo, hi = r[4], r[5]
        now = time.monotonic()
        d.update(now)
        if mn == "MS":
            if val not in MS_VALUES:
                raise ModbusError(3)
        elif mn == "HT":
            if val == 1 or not (0 <= val <= 65535):
                raise ModbusError(3)
        elif lo is not None and not (lo <= val <= hi):
            raise ModbusError(3)
        cls = "fast"
        if mn == "HT" and val + d.regs["MT"] > 65535:
            raise ModbusError(3)
        if mn == "MT" and val + d.regs["HT"] > 65535:
            raise ModbusError(3)
        if mn == "VI" and val >= d.regs["VM"]:
            raise ModbusError(3)
        if mn == "VM" and val <= d.regs["VI"]:
            raise ModbusError(3)
        if mn in ("MA", "MR", "HM", "HI") or (mn == "SL" and val != 0):
            if d.regs["DE"] != 1:
                raise ModbusError(4)
        if mn == "MA":
            d.start_move(val)
            cls = "motion"
        elif mn == "MR":
            base = d.target if d.mode == "move" else int(round(d.pos))
            tgt = base + val
            if tgt > S32_MAX or tgt < S32_MIN:
                raise ModbusError(3)
            d.start_move(tgt)
            cls = "motion"
        elif mn == "SL":
            d.start_slew(val)
            cls = "motion"
        elif mn in ("HM", "HI"):
            direction = -1.0 if val in (1, 2) else 1.0
            d.start_home(direction)
            cls = "motion"
        elif mn == "P":
            if d.moving:
                raise ModbusError(4)
            d.pos = float(val)
        elif mn == "C1":
            d.c1 = float(val)
        elif mn == "C2":
            d.c2 = float(val)
        elif mn in ("O1", "O2", "O3"):
            bit = 1 << (int(mn[1]) - 1)
            d.outputs = (d.outputs | bit) if val else (d.outputs & ~bit)
        elif mn == "OT":
            d.outputs = val & 0xF
        elif mn == "ER":
            d.er = 0
            d.ef = 0
        elif mn == "ST":
            d.stall = 0
        elif mn in ("DC", "IC"):
            tr = REG_BY_ADDR.get(val)
            if tr is None or tr[1] not in USER_VARS + ["C1", "C2", "P"]:
                raise ModbusError(3)
            step = -1 if mn == "DC" else 1
            t = tr[1]
            if t == "P":
                if d.moving:
                    raise ModbusError(4)
                d.pos = float(s32((int(round(d.pos)) + step) & 0xFFFFFFFF))
            elif t == "C1":
                d.c1 = float(s32((int(round(d.c1)) + step) & 0xFFFFFFFF))
            elif t == "C2":
                d.c2 = float(s32((int(round(d.c2)) + step) & 0xFFFFFFFF))
            else:
                d.regs[t] = s32((d.regs[t] + step) & 0xFFFFFFFF)
        elif mn == "S":
            d.nvm = {"registers": {m: d.regs[m] for m in CONFIG}, "mfg": deepcopy_json(d.mfg)}
            cls = "save"
        elif mn == "IP":
            if d.moving:
                raise ModbusError(4)
            d.reset_config()
            cls = "ip"
        elif mn in ("CF", "SC"):
            d.calib_until = now + 0.5
            cls = "motion"
        elif mn == "DE":
            d.regs["DE"] = val
            if val == 0 and d.moving:
                d._stop()
        elif mn == "MU":
            d.regs["MU"] = val
        else:
            d.regs[mn] = val
        return cls

    # ---- device identification ----
    def fc43(self, pdu):
        if len(pdu) < 2:
            raise ModbusError(3)
        if pdu[1] != 0x0E:
            raise ModbusError(1)
        if len(pdu) != 4:
            raise ModbusError(3)
        code, obj = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise ModbusError(3)
        if code == 4:
            if obj not in DEVICE_ID:
                raise ModbusError(2)
            ids = [obj]
        else:
            last = 2 if code == 1 else 6
            if obj > last:
                obj = 0
            ids = list(range(obj, last + 1))
        out = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)])
        for i in ids:
            out += bytes([i, len(DEVICE_ID[i])]) + DEVICE_ID[i]
        return bytes(out)

    # ---- manufacturer specific ----
    @staticmethod
    def _mnemonic(b4):
        s = bytes(reversed(b4)).decode("latin-1").strip(" \x00")
        return s

    @staticmethod
    def _ints(s, n_min, n_max):
        if s.startswith("=") or s.startswith(" "):
            s = s[1:]
        parts = [p.strip() for p in s.split(",")]
        if not (n_min <= len(parts) <= n_max):
            raise ModbusError(3)
        out = []
        for p in parts:
            if not re.fullmatch(r"[+-]?\d{1,11}", p):
                raise ModbusError(3)
            out.append(int(p))
        return out

    def _read_mfg(self, mn):
        d = self.d
        m = d.mfg
        if mn in MFG_SIMPLE_RANGES:
            return str(m[mn])
        if mn == "IS":
            return "; ".join("%s, %d, %d" % (k, v[0], v[1]) for k, v in sorted(m["IS"].items()))
        if mn == "OS":
            return "; ".join("%s, %d, %d" % (k, v[0], v[1]) for k, v in sorted(m["OS"].items()))
        mm = re.fullmatch(r"(IS|OS)([1-5])", mn)
        if mm:
            tbl = m[mm.group(1)]
            line = mm.group(2)
            if line not in tbl:
                raise ModbusError(2)
            v = tbl[line]
            return "%s, %d, %d" % (line, v[0], v[1])
        mm = re.fullmatch(r"S([1-4])", mn)
        if mm:
            v = m["IS"][mm.group(1)]
            return "%d, %d" % (v[0], v[1])
        if mn == "MU":
            return "%d, 0" % d.regs["MU"]
        if mn in ("LS", "TR"):
            return ", ".join(str(x) for x in m[mn])
        if mn == "IT":
            return "38, 35"
        if mn == "VT":
            return "24, 48"
        if mn == "AV":
            d.update()
            return str(0 if not d.moving else int(round(d.vel)))
        if mn in ("\x1b", "CP", "EX", "PS", "RS", "E", "HF", "UG"):
            raise ModbusError(2)   # write-only
        raise ModbusError(2)

    def fc65(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(3)
        mn = self._mnemonic(pdu[1:5])
        s = self._read_mfg(mn).encode("ascii")
        return bytes([0x41, len(s)]) + s

    def fc66(self, pdu):
        try:
            if len(pdu) < 6:
                raise ModbusError(3)
            bc = pdu[5]
            if bc > 28 or len(pdu) != 6 + bc:
                raise ModbusError(3)
            mn = self._mnemonic(pdu[1:5])
            data = bytes(pdu[6:]).decode("latin-1")
            cls = self._write_mfg(mn, data)
            return bytes([0x42, bc]) + bytes(pdu[1:5]), cls
        except ModbusError as e:
            self.d.counters["exceptions"] += 1
            return bytes([0xC2, e.code]), "mcode"

    def _write_mfg(self, mn, data):
        d = self.d
        m = d.mfg
        if mn in ("\x1b", "CP", "PS", "RS", "E"):
            if data != "":
                raise ModbusError(3)
            if mn == "CP":
                d.program_stored = False
                d.program_running = False
                return "cp"
            if mn in ("\x1b", "E"):
                d.program_running = False
            return "mcode"
        if mn in MFG_SIMPLE_RANGES:
            if not data.startswith("="):
                raise ModbusError(3)
            (v,) = self._ints(data, 1, 1)
            lo, hi = MFG_SIMPLE_RANGES[mn]
            if not lo <= v <= hi:
                raise ModbusError(3)
            m[mn] = v
            return "mcode"
        mm = re.fullmatch(r"(IS|OS)([1-5])?", mn)
        if mm:
            if not data.startswith("="):
                raise ModbusError(3)
            vals = self._ints(data, 3, 3)
            if mm.group(2) is not None and int(mm.group(2)) != vals[0]:
                raise ModbusError(3)
            line, typ, act = vals
            if mm.group(1) == "IS":
                if 1 <= line <= 4:
                    if typ not in IS_TYPES or (typ == 12 and line != 1) or act not in (0, 1):
                        raise ModbusError(3)
                elif line == 5:
                    if typ not in (9, 10) or act not in (0, 1):
                        raise ModbusError(3)
                else:
                    raise ModbusError(3)
                m["IS"][str(line)] = [typ, act]
            else:
                if not 1 <= line <= 3 or typ not in OS_TYPES or act not in (0, 1):
                    raise ModbusError(3)
                if typ == 28 and line != 3:
                    raise ModbusError(3)
                m["OS"][str(line)] = [typ, act]
            return "mcode"
        mm = re.fullmatch(r"S([1-4])", mn)
        if mm:
            if not data.startswith("="):
                raise ModbusError(3)
            vals = self._ints(data, 2, 3)
            typ, act = vals[0], vals[1]
            line = int(mm.group(1))
            if typ not in IS_TYPES or (typ == 12 and line != 1) or act not in (0, 1):
                raise ModbusError(3)
            if len(vals) == 3 and vals[2] not in (0, 1):
                raise ModbusError(3)
            m["IS"][str(line)] = [typ, act]
            return "mcode"
        if mn == "MU":
            if not data.startswith("="):
                raise ModbusError(3)
            vals = self._ints(data, 1, 2)
            if not 0 <= vals[0] <= 2 or (len(vals) == 2 and vals[1] not in (0, 1)):
                raise ModbusError(3)
            d.regs["MU"] = vals[0]
            return "mcode"
        if mn == "LS":
            if not data.startswith("="):
                raise ModbusError(3)
            vals = self._ints(data, 3, 3)
            if vals[0] not in (0, 1) or vals[2] not in (0, 1) or not S32_MIN <= vals[1] <= S32_MAX:
                raise ModbusError(3)
            m["LS"] = vals
            return "mcode"
        if mn == "TR":
            if not data.startswith("="):
                raise ModbusError(3)
            vals = self._ints(data, 3, 3)
            if not all(S32_MIN <= v <= S32_MAX for v in vals):
                raise ModbusError(3)
            m["TR"] = vals
            return "mcode"
        if mn == "EX":
            lbl = data[1:] if data[:1] in (" ", "=") else data
            if not lbl or len(data) > 4 or not re.fullmatch(r"[A-Za-z0-9]{1,3}", lbl):
                raise ModbusError(3)
            # factory fresh: no program stored, so no label/address exists
            raise ModbusError(3)
        if mn == "HF":
            if not data.startswith("="):
                raise ModbusError(3)
            (v,) = self._ints(data, 1, 1)
            if v not in (0, 1):
                raise ModbusError(3)
            if d.regs["DE"] != 1:
                raise ModbusError(4)
            d.start_home(1.0 if v else -1.0)
            return "motion"
        if mn == "UG":
            if data not in (" 2956102", "=2956102", "= 2956102"):
                raise ModbusError(3)
            raise ModbusError(4)
        if mn in ("IT", "VT", "AV"):
            raise ModbusError(2)     # read-only
        raise ModbusError(2)         # unknown / EL (not applicable to integrated products)

    # ---- state dump ----
    def state(self):
        d = self.d
        d.update()
        regs = {}
        for r in REG_TABLE:
            if r[3] == "WO":
                continue
            regs["0x%04X" % r[0]] = {"mnemonic": r[1], "value": d.snapshot_value(r[1])}
        return {
            "device": "LMDCE571 (LMD Ethernet, hMTechnology closed loop)",
            "registers": regs,
            "coils": {str(i): (d.outputs >> i) & 1 for i in range(4)},
            "discrete_inputs": {str(i): (d.inputs >> i) & 1 for i in range(4)},
            "manufacturer_settings": d.mfg,
            "nvm": d.nvm,
            "program": {"stored": d.program_stored, "running": d.program_running},
            "motion": {"moving": d.moving, "mode": d.mode},
            "diagnostic_counters": dict(d.counters),
        }


# --------------------------------------------------------------------------------------
# Transport: lwIP-like Modbus/TCP server with one Modbus task and timing model
# --------------------------------------------------------------------------------------
MAX_CONNS = 4
IDLE_CLOSE = 60.0
QUEUE_DEPTH = 16
TICK = 0.002
ANSWER_BOUND = 0.330
PIECE = 32


class Conn:
    def __init__(self):
        self.last_finish = 0.0
        self.first = True
        self.queue = asyncio.Queue(QUEUE_DEPTH)


class Server:
    def __init__(self, state_file):
        self.dev = Device()
        self.state_file = state_file
        self.busy_until = 0.0
        self.t0 = time.monotonic()
        self.conns = 0
        self.rng = random.Random()

    def dump_state(self):
        if not self.state_file:
            return
        try:
            st = self.dev.state()
            tmp = self.state_file + ".tmp"
            with open(tmp, "w") as f:
                json.dump(st, f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except Exception as e:  # never crash on a dump
            print("state dump failed: %r" % e, file=sys.stderr, flush=True)

    def schedule(self, conn, arrival, cls):
        lo, hi = SVC[cls]
        service = self.rng.uniform(lo, hi)
        if self.dev.d.moving:
            service += self.rng.uniform(0.0015, 0.003)   # own behaviour 2
        if conn.first:
            service += self.rng.uniform(0.015, 0.025)    # own behaviour 3
            conn.first = False
        start = max(arrival, self.busy_until)
        finish = start + service
        # own behaviour 1: released on the 2 ms main-loop tick
        finish = self.t0 + math.ceil((finish - self.t0) / TICK) * TICK
        finish = min(finish, arrival + ANSWER_BOUND)
        finish = max(finish, conn.last_finish)
        self.busy_until = max(self.busy_until, finish)
        conn.last_finish = finish
        return finish

    async def writer_task(self, conn, writer):
        try:
            while True:
                item = await conn.queue.get()
                if item is None:
                    break
                send_at, adu = item
                delay = send_at - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                # 32-byte TX scratch buffer first, the rest (if any) as a second send
                pieces = [adu[:PIECE]] + ([adu[PIECE:]] if len(adu) > PIECE else [])
                for i, p in enumerate(pieces):
                    if i:
                        await asyncio.sleep(self.rng.uniform(0.0003, 0.0008))
                    writer.write(p)
                    await writer.drain()
                self.dev.d.counters["responses"] += 1
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass

    async def handle(self, reader, writer):
        if self.conns >= MAX_CONNS:
            self.dev.d.counters["connections_refused"] += 1
            try:
                writer.close()
            except Exception:
                pass
            return
        self.conns += 1
        self.dev.d.counters["connections_accepted"] += 1
        sock = writer.get_extra_info("socket")
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 0)  # Nagle on
        except Exception:
            pass
        conn = Conn()
        wt = asyncio.ensure_future(self.writer_task(conn, writer))
        buf = bytearray()
        try:
            while True:
                try:
                    data = await asyncio.wait_for(reader.read(2048), IDLE_CLOSE)
                except asyncio.TimeoutError:
                    self.dev.d.counters["connections_closed_idle"] += 1
                    break
                if not data:
                    break
                buf += data
                closed = False
                while len(buf) >= 7:
                    tid, proto, length = struct.unpack(">HHH", buf[:6])
                    if length < 1 or length > 254:
                        self.dev.d.counters["framing_errors"] += 1
                        closed = True
                        break
                    if len(buf) < 6 + length:
                        break
                    frame = bytes(buf[:6 + length])
                    del buf[:6 + length]
                    if proto != 0 or length < 2:
                        self.dev.d.counters["discarded_frames"] += 1
                        continue
                    unit = frame[6]
                    pdu = frame[7:]
                    arrival = time.monotonic()
                    self.dev.d.counters["requests"] += 1
                    try:
                        resp, cls = self.dev.handle(pdu)
                    except Exception as e:  # never let one frame kill the server
                        print("internal error: %r" % e, file=sys.stderr, flush=True)
                        resp, cls = bytes([(pdu[0] | 0x80) & 0xFF, 4]), "fast"
                    adu = struct.pack(">HHHB", tid, 0, len(resp) + 1, unit) + resp
                    send_at = self.schedule(conn, arrival, cls)
                    await conn.queue.put((send_at, adu))     # bounded: back-pressure
                if closed:
                    break
                if len(buf) > 2048:
                    self.dev.d.counters["framing_errors"] += 1
                    break
        except (ConnectionError, OSError):
            pass
        except asyncio.CancelledError:      # server shutting down
            wt.cancel()
            self.conns -= 1
            try:
                writer.close()
            except Exception:
                pass
            return
        self.conns -= 1
        try:
            await conn.queue.put(None)
            await asyncio.wait_for(wt, 1.0)
        except BaseException:
            wt.cancel()
        try:
            writer.close()
        except Exception:
            pass


async def main_async(args):
    host, _, port = args.listen.rpartition(":")
    srv = Server(args.state)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()

    def on_term():
        stop.set()

    loop.add_signal_handler(signal.SIGTERM, on_term)
    loop.add_signal_handler(signal.SIGINT, on_term)
    loop.add_signal_handler(signal.SIGUSR1, srv.dump_state)
    server = await asyncio.start_server(srv.handle, host, int(port), reuse_address=True)
    actual = server.sockets[0].getsockname()[1]
    print("listening tcp %s:%d" % (host, actual), flush=True)

    async def ticker():
        while True:
            await asyncio.sleep(0.010)
            srv.dev.d.update()

    tk = asyncio.ensure_future(ticker())
    await stop.wait()
    tk.cancel()
    server.close()
    srv.dump_state()


def main():
    ap = argparse.ArgumentParser(description="LMD Ethernet (hMT) Modbus/TCP simulator")
    ap.add_argument("--listen", default="127.0.0.1:502")
    ap.add_argument("--state", default=None)
    ap.add_argument("--baud", default=None, help="ignored: the LMD Ethernet has no Modbus serial port")
    ap.add_argument("--parity", default=None, help="ignored")
    args = ap.parse_args()
    try:
        asyncio.run(main_async(args))
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
