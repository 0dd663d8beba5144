#!/usr/bin/env python3
"""MDrive Plus2 (no encoder) MODBUS/TCP drive simulator.

Clean-room implementation from the MODBUS/TCP Fieldbus Manual (R040611) and the public
Modbus specifications.  Standard library only.  See DECISIONS.md for every choice made.
"""
import argparse
import asyncio
import json
import os
import re
import signal
import sys
import time

# ---------------------------------------------------------------------------
# exception codes
ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3
DEVICE_FAILURE = 4


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


MAX_QTY = 4            # our firmware's largest quantity per request (manual "1 to 4")
MAX_CONNECTIONS = 8
ANSWERED_UNITS = (0x00, 0xFF)
INT32_MIN, INT32_MAX = -2147483648, 2147483647

MS_VALUES = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)

# I/O type codes (manual 4.3.1)
IN_TYPES = (0, 1, 2, 3, 5, 7, 8, 11)
OUT_TYPES = (16, 17, 18, 20, 21, 23)          # 24, 25 are Hybrid only
CLOCK_TYPES = (33, 34, 35, 49, 50, 51)


class Item:
    """One register-map entry."""

    def __init__(self, name, addr, nregs, access, lo=None, hi=None, default=0, signed=False,
                 desc=""):
        self.name = name
        self.addr = addr
        self.nregs = nregs
        self.access = access      # rw, ro, wo (command), var (user variable)
        self.lo = lo
        self.hi = hi
        self.default = default
        self.signed = signed
        self.desc = desc


def build_map():
    items = []

    def add(*a, **k):
        items.append(Item(*a, **k))

    add("A", 0x0000, 2, "rw", 91, 1525878997, 1000000, desc="Acceleration")
    add("C1", 0x0005, 2, "rw", INT32_MIN, INT32_MAX, 0, True, "Counter 1")
    add("C2", 0x0007, 2, "rw", INT32_MIN, INT32_MAX, 0, True, "Counter 2 (encoder)")
    add("CE", 0x0009, 1, "rw", 0, 1, 1, desc="Software reset enable")
    add("CM", 0x000B, 1, "rw", 0, 1, 0, desc="Clock mode enable")
    for i in range(4):
        add("D%d" % (i + 1), 0x000F + i, 1, "rw", 0, 255, 0, desc="Input %d debounce" % (i + 1))
    add("D5", 0x0013, 1, "rw", 0, 255, 0, desc="Analog input filter")
    add("D", 0x0018, 2, "rw", 91, 1525878997, 1000000, desc="Deceleration")
    add("DB", 0x001A, 1, "rw", 0, 65000, 10, desc="Encoder deadband")
    add("DC", 0x001B, 1, "wo", 1, 4, desc="Decrement variable")
    add("DE", 0x001C, 1, "rw", 0, 1, 1, desc="Drive enable")
    add("EE", 0x001E, 1, "rw", 0, 1, 0, desc="Encoder enable")
    add("EF", 0x001F, 1, "ro", desc="Error flag")
    add("ER", 0x0021, 1, "rw", 0, 0, 0, desc="Error code")
    add("HC", 0x0029, 1, "rw", 0, 100, 5, desc="Holding current")
    add("HM", 0x002B, 1, "rw", 1, 4, 1, desc="Homing mode")
    add("HT", 0x002C, 1, "rw", 0, 65535, 500, desc="Hold current delay time")
    for i in range(4):
        add("I%d" % (i + 1), 0x002D + i, 1, "ro", desc="Read input %d" % (i + 1))
    add("I5", 0x0031, 1, "ro", desc="Analog input")
    add("I6", 0x0032, 1, "ro", desc="Index mark")
    add("IC", 0x0037, 1, "wo", 1, 4, desc="Increment variable")
    add("IL", 0x003A, 1, "ro", desc="Inputs 1-4 as BCD")
    add("IN", 0x003B, 1, "ro", desc="All inputs as BCD")
    add("JE", 0x003F, 1, "rw", 0, 1, 0, desc="Jog enable")
    add("LM", 0x0042, 1, "rw", 1, 6, 1, desc="Limit stop mode")
    add("MA", 0x0043, 2, "wo", INT32_MIN, INT32_MAX, signed=True, desc="Move absolute")
    add("MP", 0x0045, 1, "ro", desc="Moving to position")
    add("MR", 0x0046, 2, "wo", INT32_MIN, INT32_MAX, signed=True, desc="Move relative")
    add("MS", 0x0048, 1, "rw", 1, 256, 256, desc="Microstep resolution")
    add("MT", 0x0049, 1, "rw", 0, 65000, 0, desc="Motor settling delay time")
    add("MV", 0x004A, 1, "ro", desc="Moving")
    for i in range(4):
        add("O%d" % (i + 1), 0x004B + i, 1, "rw", 0, 1, 0, desc="Output %d" % (i + 1))
    add("OL", 0x0055, 1, "rw", 0, 15, 0, desc="Outputs 1-4 as group")
    add("OT", 0x0056, 1, "rw", 0, 15, 0, desc="Outputs 1-4 as group")
    add("P", 0x0057, 2, "rw", INT32_MIN, INT32_MAX, 0, True, "Position counter")
    add("PC", 0x0059, 2, "ro", signed=True, desc="Position capture at trip")
    add("PM", 0x005C, 1, "rw", 0, 1, 0, desc="Position maintenance")
    for i in range(4):
        add("R%d" % (i + 1), 0x005F + 2 * i, 2, "rw", INT32_MIN, INT32_MAX, 0, True,
            "User register %d" % (i + 1))
    add("RC", 0x0067, 1, "rw", 1, 100, 25, desc="Run current")
    add("S", 0x0076, 1, "wo", 0, 255, desc="Save to NVM")
    add("SF", 0x0077, 1, "rw", 0, 65000, 15, desc="Stall factor")
    add("SL", 0x0078, 2, "wo", -5000000, 5000000, signed=True, desc="Slew axis")
    add("SM", 0x007A, 1, "rw", 0, 1, 0, desc="Stall mode")
    add("ST", 0x007B, 1, "rw", 0, 0, 0, desc="Stall flag")
    add("TE", 0x007D, 1, "rw", 0, 16, 0, desc="Trip enable")
    add("V", 0x0085, 2, "ro", signed=True, desc="Axis velocity")
    add("VC", 0x0088, 1, "ro", desc="Velocity changing")
    add("VI", 0x0089, 2, "rw", 1, 4999999, 1000, desc="Initial velocity")
    add("VM", 0x008B, 2, "rw", 2, 5000000, 768000, desc="Maximum velocity")
    for i in range(8):
        add("V%d" % (i + 1), 0x00A8 + 2 * i, 2, "var", signed=True, desc="User variable %d" % (i + 1))
    return items


ITEMS = build_map()
BY_NAME = {it.name: it for it in ITEMS}
REG_INDEX = {}
for _it in ITEMS:
    for _k in range(_it.nregs):
        REG_INDEX[_it.addr + _k] = (_it, _k)

COIL_BASE = 0x004B       # FC01 / FC05 outputs 1-4
INPUT_BASE = 0x002D      # FC02 inputs 1-4

# manufacturer-specific mnemonics: 4 wire bytes = mnemonic reversed, left padded with spaces
MFG_NAMES = ("S1", "S2", "S3", "S4", "S7", "S8", "CR", "S5", "S13", "TR", "E", "EX", "PS", "RS", "MU")
MFG_BY_BYTES = {m[::-1].rjust(4).encode("ascii"): m for m in MFG_NAMES}
MFG_ACTIONS = ("E", "EX", "PS", "RS")

DEVICE_ID = {
    0x00: b"SEM USA",
    0x01: b"MDI1PRD23A7-EQ",
    0x02: b"4.0.0.0".ljust(8, b"\0"),
    0x03: b"www.imshome.com".ljust(32, b"\0"),
    0x04: b"MDrive Ethernet",
    0x05: b"1041100001",
    0x06: b"ASI 4.0.0.2".ljust(12, b"\0"),
}
CONFORMITY = 0x82


def to_regs(value, nregs):
    if nregs == 1:
        return [value & 0xFFFF]
    v = value & 0xFFFFFFFF
    return [(v >> 16) & 0xFFFF, v & 0xFFFF]


def from_regs(words, signed):
    if len(words) == 1:
        return words[0]
    v = (words[0] << 16) | words[1]
    if signed and v & 0x80000000:
        v -= 0x100000000
    return v


# ---------------------------------------------------------------------------
class Drive:
    TICK = 0.005

    def __init__(self):
        self.params = {it.name: it.default for it in ITEMS if it.access == "rw"}
        # I/O configuration (S1-S4): type, active level, sink/source
        self.io = {n: [0, 0, 0] for n in (1, 2, 3, 4)}
        self.latch = {n: 0 for n in (1, 2, 3, 4)}
        self.mfg = {"S7": [33, 0], "S8": [33, 0], "S5": [9, 0], "S13": [60, 0],
                    "CR": "1.000", "TR": [0, 0, 0]}
        self.pc = 0
        self.ef = 0
        # motion
        self.mode = None         # None, "move", "slew"
        self.pos_f = 0.0
        self.vel = 0.0           # signed steps/s
        self.target = 0
        self.slew_v = 0.0
        self.vchanging = 0
        self.last_tick = time.monotonic()
        self.nvm = self.settings_snapshot()
        self.counters = {"requests": 0, "responses": 0, "exceptions": 0, "ignored_unit": 0,
                         "discarded": 0, "connections_closed_bad_frame": 0}

    # ---------------- state helpers
    def settings_snapshot(self):
        return {"params": dict((k, v) for k, v in self.params.items()
                               if k not in ("ER", "ST", "C1", "C2", "P", "O1", "O2", "O3", "O4",
                                            "OL", "OT")),
                "io": {str(k): list(v) for k, v in self.io.items()},
                "mfg": json.loads(json.dumps(self.mfg))}

    # ---------------- motion
    def moving(self):
        return self.mode is not None

    def tick(self):
        now = time.monotonic()
        dt = now - self.last_tick
        self.last_tick = now
        if self.mode is None:
            return
        dt = min(dt, 0.05)
        A = float(self.params["A"])
        D = float(self.params["D"])
        VI = float(self.params["VI"])
        VM = float(self.params["VM"])
        old = round(self.pos_f)
        if self.mode == "move":
            rem = self.target - self.pos_f
            direction = 1.0 if rem > 0 else -1.0
            dist = abs(rem)
            speed = abs(self.vel)
            stop_dist = max(0.0, (speed * speed - VI * VI) / (2 * D))
            if dist <= stop_dist + speed * dt * 0.5 and speed > VI:
                speed = max(VI, speed - D * dt)
                self.vchanging = 1
            elif speed < VM:
                speed = min(VM, speed + A * dt)
                self.vchanging = 1
            else:
                speed = VM
                self.vchanging = 0
            step = speed * dt
            if step >= dist:
                self.pos_f = float(self.target)
                self._stop()
            else:
                self.pos_f += direction * step
                self.vel = direction * speed
        else:  # slew
            vt = self.slew_v
            v = self.vel
            if vt == 0.0:
                speed = abs(v) - D * dt
                if speed <= VI:
                    self.pos_f += v * dt
                    self._stop()
                else:
                    self.vel = speed if v > 0 else -speed
                    self.vchanging = 1
                    self.pos_f += self.vel * dt
            else:
                if v != 0 and (v > 0) != (vt > 0):
                    # reversing: decelerate first
                    speed = abs(v) - D * dt
                    if speed <= VI:
                        v = VI if vt > 0 else -VI
                    else:
                        v = speed if v > 0 else -speed
                    self.vchanging = 1
                elif abs(v) < abs(vt):
                    speed = min(abs(vt), abs(v) + A * dt)
                    v = speed if vt > 0 else -speed
                    self.vchanging = 1 if speed != abs(vt) else 0
                elif abs(v) > abs(vt):
                    speed = max(abs(vt), abs(v) - D * dt)
                    v = speed if vt > 0 else -speed
                    self.vchanging = 1 if speed != abs(vt) else 0
                else:
                    self.vchanging = 0
                self.vel = v
                self.pos_f += v * dt
                if self.pos_f > INT32_MAX or self.pos_f < INT32_MIN:
                    # counter wraps like a 32 bit register
                    self.pos_f = float(((int(self.pos_f) - INT32_MIN) % 2 ** 32) + INT32_MIN)
                    old = round(self.pos_f)
        new = round(self.pos_f)
        delta = new - old
        if delta:
            self.params["P"] = new
            self.params["C1"] = self._wrap(self.params["C1"] + delta)

    @staticmethod
    def _wrap(v):
        return ((v - INT32_MIN) % 2 ** 32) + INT32_MIN

    def _stop(self):
        self.mode = None
        self.vel = 0.0
        self.vchanging = 0
        self.pos_f = float(round(self.pos_f))
        self.params["P"] = int(self.pos_f)

    def start_move(self, target):
        self.pos_f = float(self.params["P"])
        self.target = target
        if target == self.params["P"]:
            return
        self.mode = "move"
        self.vel = float(self.params["VI"]) * (1 if target > self.params["P"] else -1)
        self.vchanging = 1
        self.last_tick = time.monotonic()

    def start_slew(self, v):
        if v == 0:
            if self.mode == "slew":
                self.slew_v = 0.0
            elif self.mode == "move":
                # stop request during a point move: decelerate as a slew to 0
                self.mode = "slew"
                self.slew_v = 0.0
            return
        if self.mode is None:
            self.pos_f = float(self.params["P"])
            vi = float(self.params["VI"])
            self.vel = min(vi, abs(v)) * (1 if v > 0 else -1)
            self.last_tick = time.monotonic()
        self.mode = "slew"
        self.slew_v = float(v)
        self.vchanging = 1

    # ---------------- I/O
    def out_state(self, n):
        t = self.io[n][0]
        if t == 16:
            return self.latch[n]
        if t == 17:
            return 1 if self.moving() else 0
        if t == 18:
            return self.ef
        if t == 20:
            return self.vchanging if self.moving() else 0
        if t == 23:
            return 1 if self.mode == "move" else 0
        return 0

    def in_state(self, n):
        if self.io[n][0] in OUT_TYPES:
            return self.out_state(n)
        return 0   # nothing wired: inputs inactive

    def inputs_bcd(self):
        return sum(self.in_state(n) << (n - 1) for n in (1, 2, 3, 4))

    def outputs_bcd(self):
        return sum(self.out_state(n) << (n - 1) for n in (1, 2, 3, 4))

    # ---------------- register access
    def read_item(self, it):
        """Value of an item for FC03; raises ModbusError(4) when refused."""
        n = it.name
        if it.access == "wo" or it.access == "var":
            raise ModbusError(DEVICE_FAILURE)
        if n in ("I1", "I2", "I3", "I4"):
            return self.in_state(int(n[1]))
        if n in ("IL", "IN"):
            return self.inputs_bcd()
        if n in ("I5", "I6"):
            return 0
        if n == "EF":
            return self.ef
        if n == "MP":
            return 1 if self.mode == "move" else 0
        if n == "MV":
            return 1 if self.moving() else 0
        if n == "VC":
            return self.vchanging if self.moving() else 0
        if n == "V":
            return int(round(self.vel))
        if n == "PC":
            return self.pc
        if n in ("O1", "O2", "O3", "O4"):
            return self.out_state(int(n[1]))
        if n in ("OL", "OT"):
            return self.outputs_bcd()
        return self.params[n]

    def check_write(self, it, value, pending):
        """Validate a write; raises ModbusError(4) when the motion processor refuses it."""
        n = it.name
        if it.access in ("ro", "var"):
            raise ModbusError(DEVICE_FAILURE)
        if value < it.lo or value > it.hi:
            raise ModbusError(DEVICE_FAILURE)
        if n == "MS" and value not in MS_VALUES:
            raise ModbusError(DEVICE_FAILURE)
        if n == "HT" and value == 1:
            raise ModbusError(DEVICE_FAILURE)
        if n in ("HT", "MT"):
            ht = pending.get("HT", self.params["HT"])
            mt = pending.get("MT", self.params["MT"])
            if ht + mt > 65535:
                raise ModbusError(DEVICE_FAILURE)
        if n in ("VI", "VM"):
            vi = pending.get("VI", self.params["VI"])
            vm = pending.get("VM", self.params["VM"])
            if vi >= vm:
                raise ModbusError(DEVICE_FAILURE)
        if n == "TE" and value not in (0, 16):
            raise ModbusError(DEVICE_FAILURE)
        if n in ("EE", "PM") and value == 1:
            raise ModbusError(DEVICE_FAILURE)      # no encoder fitted
        if n in ("O1", "O2", "O3", "O4") and self.io[int(n[1])][0] != 16:
            raise ModbusError(DEVICE_FAILURE)      # point not configured as GP output
        if n in ("MA", "MR") and self.moving():
            raise ModbusError(DEVICE_FAILURE)
        if n == "MR":
            if not INT32_MIN <= self.params["P"] + value <= INT32_MAX:
                raise ModbusError(DEVICE_FAILURE)
        if n == "SL" and value != 0 and self.mode == "move":
            raise ModbusError(DEVICE_FAILURE)
        if n in ("P", "MS") and self.moving():
            raise ModbusError(DEVICE_FAILURE)
        if n in ("DC", "IC"):
            r = "R%d" % value
            cur = pending.get(r, self.params[r])
            nv = cur - 1 if n == "DC" else cur + 1
            if nv < INT32_MIN or nv > INT32_MAX:
                raise ModbusError(DEVICE_FAILURE)
            pending[r] = nv

    def apply_write(self, it, value):
        n = it.name
        if n == "MA":
            self.start_move(value)
        elif n == "MR":
            self.start_move(self.params["P"] + value)
        elif n == "SL":
            self.start_slew(value)
        elif n == "DC":
            self.params["R%d" % value] -= 1
        elif n == "IC":
            self.params["R%d" % value] += 1
        elif n == "S":
            self.nvm = self.settings_snapshot()
        elif n in ("O1", "O2", "O3", "O4"):
            self.latch[int(n[1])] = value
        elif n in ("OL", "OT"):
            for k in (1, 2, 3, 4):
                if self.io[k][0] == 16:
                    self.latch[k] = (value >> (k - 1)) & 1
        elif n == "ER":
            self.params["ER"] = 0
            self.ef = 0
        elif n == "ST":
            self.params["ST"] = 0
        elif n == "P":
            self.params["P"] = value
            self.pos_f = float(value)
        else:
            self.params[n] = value

    # ---------------- state dump
    def dump(self):
        hr = {}
        for it in ITEMS:
            key = "0x%04X" % it.addr
            if it.access in ("rw", "ro"):
                hr[key] = {"name": it.name, "registers": it.nregs, "access": it.access,
                           "value": self.read_item(it)}
            elif it.access == "var":
                hr[key] = {"name": it.name, "registers": 2, "access": "user variable",
                           "value": None, "declared": False}
        return {
            "device": "MDrive Plus2 Motion Control, Ethernet, no encoder",
            "holding_registers": hr,
            "coils": {"0x%04X" % (COIL_BASE + k - 1): self.out_state(k) for k in (1, 2, 3, 4)},
            "output_latches": {"O%d" % k: self.latch[k] for k in (1, 2, 3, 4)},
            "discrete_inputs": {"0x%04X" % (INPUT_BASE + k - 1): self.in_state(k)
                                for k in (1, 2, 3, 4)},
            "manufacturer_settings": {
                **{"S%d" % k: self.fmt_mfg("S%d" % k) for k in (1, 2, 3, 4)},
                **{k: self.fmt_mfg(k) for k in ("S7", "S8", "CR", "S5", "S13", "TR")}},
            "program": {"running": False, "paused": False, "stored_programs": []},
            "nvm": self.nvm,
            "device_identification": {"0x%02X" % k: v.decode("ascii").rstrip("\0")
                                      for k, v in DEVICE_ID.items()},
            "diagnostic_counters": dict(self.counters),
        }

    def fmt_mfg(self, m):
        if m in ("S1", "S2", "S3", "S4"):
            v = self.io[int(m[1])]
        else:
            v = self.mfg[m]
        if isinstance(v, str):
            return v
        return ", ".join(str(x) for x in v)


# ---------------------------------------------------------------------------
def u16(b, i):
    return (b[i] << 8) | b[i + 1]


def check_register_range(start, qty):
    """Address check for FC03/FC16: returns list of (item, values-slot) spans or raises 02."""
    if qty > MAX_QTY:
        raise ModbusError(ILLEGAL_ADDRESS)
    spans = []
    a = start
    end = start + qty
    while a < end:
        ent = REG_INDEX.get(a)
        if ent is None:
            raise ModbusError(ILLEGAL_ADDRESS)
        it, off = ent
        if off != 0 or a + it.nregs > end:
            raise ModbusError(ILLEGAL_ADDRESS)   # splits a 32 bit item
        spans.append(it)
        a += it.nregs
    return spans


class Server:
    def __init__(self, drive, state_file):
        self.drive = drive
        self.state_file = state_file
        self.conns = set()

    # ---------------- PDU processing
    def process(self, pdu):
        """Returns response PDU bytes or None (silence)."""
        fc = pdu[0]
        if fc == 0 or fc >= 0x80:
            return None
        try:
            handler = {0x01: self.fc01, 0x02: self.fc02, 0x03: self.fc03, 0x05: self.fc05,
                       0x10: self.fc16, 0x2B: self.fc43, 0x41: self.fc65, 0x42: self.fc66}.get(fc)
            if handler is None:
                raise ModbusError(ILLEGAL_FUNCTION)
            self.drive.tick()
            return handler(pdu)
        except ModbusError as e:
            self.drive.counters["exceptions"] += 1
            return bytes([fc | 0x80, e.code])

    def read_bits(self, pdu, base, getter):
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        start, qty = u16(pdu, 1), u16(pdu, 3)
        if qty < 1 or qty > 2000:
            raise ModbusError(ILLEGAL_VALUE)
        if qty > MAX_QTY or start < base or start + qty > base + 4:
            raise ModbusError(ILLEGAL_ADDRESS)
        val = 0
        for i in range(qty):
            val |= getter(start - base + 1 + i) << i
        return bytes([pdu[0], 1, val])

    def fc01(self, pdu):
        return self.read_bits(pdu, COIL_BASE, self.drive.out_state)

    def fc02(self, pdu):
        return self.read_bits(pdu, INPUT_BASE, self.drive.in_state)

    def fc03(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        start, qty = u16(pdu, 1), u16(pdu, 3)
        if qty < 1 or qty > 125:
            raise ModbusError(ILLEGAL_VALUE)
        spans = check_register_range(start, qty)
        words = []
        for it in spans:
            words += to_regs(self.drive.read_item(it), it.nregs)
        # ER is cleared by reading it
        for it in spans:
            if it.name == "ER":
                self.drive.params["ER"] = 0
                self.drive.ef = 0
        out = bytearray([0x03, 2 * len(words)])
        for w in words:
            out += bytes([w >> 8, w & 0xFF])
        return bytes(out)

    def fc05(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        addr, val = u16(pdu, 1), u16(pdu, 3)
        if val not in (0x0000, 0xFF00):
            raise ModbusError(ILLEGAL_VALUE)
        if not COIL_BASE <= addr < COIL_BASE + 4:
            raise ModbusError(ILLEGAL_ADDRESS)
        it = REG_INDEX[addr][0]
        v = 1 if val == 0xFF00 else 0
        self.drive.check_write(it, v, {})
        self.drive.apply_write(it, v)
        return bytes(pdu)

    def fc16(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(ILLEGAL_VALUE)
        start, qty, bc = u16(pdu, 1), u16(pdu, 3), pdu[5]
        if qty < 1 or qty > 123 or bc != 2 * qty or len(pdu) != 6 + bc:
            raise ModbusError(ILLEGAL_VALUE)
        spans = check_register_range(start, qty)
        words = [u16(pdu, 6 + 2 * i) for i in range(qty)]
        values = []
        pending = {}
        i = 0
        for it in spans:
            v = from_regs(words[i:i + it.nregs], it.signed)
            i += it.nregs
            self.drive.check_write(it, v, pending)
            if it.access == "rw":
                pending[it.name] = v
            values.append((it, v))
        for it, v in values:
            self.drive.apply_write(it, v)
        return bytes(pdu[:5])

    def fc43(self, pdu):
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
            if oid not in DEVICE_ID:
                raise ModbusError(ILLEGAL_ADDRESS)
            ids = [oid]
        else:
            cat = [0, 1, 2] if code == 1 else [0, 1, 2, 3, 4, 5, 6]
            if oid not in cat:
                oid = 0
            ids = cat[cat.index(oid):]
        out = bytearray([0x2B, 0x0E, code, CONFORMITY, 0x00, 0x00, len(ids)])
        for k in ids:
            out += bytes([k, len(DEVICE_ID[k])]) + DEVICE_ID[k]
        return bytes(out)

    def fc65(self, pdu):
        if len(pdu) < 5:
            raise ModbusError(ILLEGAL_VALUE)
        m = MFG_BY_BYTES.get(bytes(pdu[1:5]))
        if m is None or m == "MU":
            raise ModbusError(ILLEGAL_ADDRESS)
        d = self.drive
        if m == "EX":
            if len(pdu) < 6 or not 1 <= pdu[5] <= 4 or len(pdu) != 6 + pdu[5]:
                raise ModbusError(ILLEGAL_VALUE)
            label = bytes(pdu[6:])
            if not re.fullmatch(rb"[A-Za-z0-9]{1,4}", label):
                raise ModbusError(ILLEGAL_VALUE)
            raise ModbusError(DEVICE_FAILURE)       # no stored program with that label/address
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        if m == "E":
            return bytes([0x41, 0])
        if m in ("PS", "RS"):
            raise ModbusError(DEVICE_FAILURE)       # no program running
        s = d.fmt_mfg(m).encode("ascii")
        return bytes([0x41, len(s)]) + s

    def fc66(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(ILLEGAL_VALUE)
        bc = pdu[5]
        if bc < 1 or bc > 28 or len(pdu) != 6 + bc:
            raise ModbusError(ILLEGAL_VALUE)
        mb = bytes(pdu[1:5])
        m = MFG_BY_BYTES.get(mb)
        if m is None or m == "MU":
            raise ModbusError(ILLEGAL_ADDRESS)
        if m in MFG_ACTIONS:
            raise ModbusError(DEVICE_FAILURE)
        data = bytes(pdu[6:])
        d = self.drive
        lens = {"S1": (6, 7), "S2": (6, 7), "S3": (6, 7), "S4": (6, 7), "S7": (4, 5), "S8": (4, 5),
                "S5": (4, 5), "S13": (4, 5), "CR": (2, 6), "TR": (2, 28)}[m]
        if not lens[0] <= bc <= lens[1] or data[:1] != b"=":
            raise ModbusError(ILLEGAL_VALUE)
        body = data[1:]
        if m == "CR":
            if not re.fullmatch(rb"[0-9]+(\.[0-9]+)?|\.[0-9]+", body):
                raise ModbusError(ILLEGAL_VALUE)
            v = float(body.decode())
            if v <= 0:
                raise ModbusError(DEVICE_FAILURE)
            d.mfg["CR"] = "%.3f" % v
            return bytes([0x42, 4]) + mb
        if m == "TR":
            if not re.fullmatch(rb"-?[0-9]+(,-?[0-9]+){0,2}", body):
                raise ModbusError(ILLEGAL_VALUE)
            vals = [int(x) for x in body.split(b",")]
            if any(not INT32_MIN <= x <= INT32_MAX for x in vals) or vals[1:2] and vals[1] < 0:
                raise ModbusError(DEVICE_FAILURE)
            d.mfg["TR"] = (vals + [0, 0])[:3]
            return bytes([0x42, 4]) + mb
        nfields = 3 if m in ("S1", "S2", "S3", "S4") else 2
        if not re.fullmatch(rb"[0-9]+" + rb"(,[0-9]+)" * (nfields - 1), body):
            raise ModbusError(ILLEGAL_VALUE)
        vals = [int(x) for x in body.split(b",")]
        if any(x not in (0, 1) for x in vals[1:]):
            raise ModbusError(DEVICE_FAILURE)
        t = vals[0]
        if m in ("S1", "S2", "S3", "S4"):
            if t not in IN_TYPES + OUT_TYPES:
                raise ModbusError(DEVICE_FAILURE)
            n = int(m[1])
            if t != 16:
                d.latch[n] = 0
            d.io[n] = vals
        elif m in ("S7", "S8"):
            if t not in CLOCK_TYPES:
                raise ModbusError(DEVICE_FAILURE)
            d.mfg[m] = vals
        elif m == "S5":
            if t not in (9, 10):
                raise ModbusError(DEVICE_FAILURE)
            d.mfg[m] = vals
        elif m == "S13":
            if t not in (60, 61):
                raise ModbusError(DEVICE_FAILURE)
            d.mfg[m] = vals
        return bytes([0x42, 4]) + mb

    # ---------------- TCP
    async def handle(self, reader, writer):
        if len(self.conns) >= MAX_CONNECTIONS:
            writer.close()
            return
        self.conns.add(writer)
        buf = bytearray()
        try:
            while True:
                data = await reader.read(4096)
                if not data:
                    break
                buf += data
                closing = False
                while len(buf) >= 7:
                    tid, proto, length = u16(buf, 0), u16(buf, 2), u16(buf, 4)
                    if proto != 0 or length < 2 or length > 254:
                        self.drive.counters["connections_closed_bad_frame"] += 1
                        closing = True
                        break
                    if len(buf) < 6 + length:
                        break
                    unit = buf[6]
                    pdu = bytes(buf[7:6 + length])
                    del buf[:6 + length]
                    self.drive.counters["requests"] += 1
                    if unit not in ANSWERED_UNITS:
                        self.drive.counters["ignored_unit"] += 1
                        continue
                    try:
                        resp = self.process(pdu)
                    except Exception as e:     # never let one frame kill the server
                        print("internal error: %r" % (e,), file=sys.stderr)
                        resp = bytes([pdu[0] | 0x80, DEVICE_FAILURE])
                    if resp is None:
                        self.drive.counters["discarded"] += 1
                        continue
                    self.drive.counters["responses"] += 1
                    writer.write(bytes([tid >> 8, tid & 0xFF, 0, 0, (len(resp) + 1) >> 8,
                                        (len(resp) + 1) & 0xFF, unit]) + resp)
                await writer.drain()
                if closing:
                    break
        except (ConnectionError, OSError, asyncio.IncompleteReadError):
            pass
        except asyncio.CancelledError:
            pass
        finally:
            self.conns.discard(writer)
            try:
                writer.close()
            except Exception:
                pass

    def save_state(self):
        if not self.state_file:
            return
        self.drive.tick()
        tmp = self.state_file + ".tmp"
        try:
            with open(tmp, "w") as f:
                json.dump(self.drive.dump(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except OSError as e:
            print("state write failed: %s" % e, file=sys.stderr)


async def ticker(drive):
    while True:
        drive.tick()
        await asyncio.sleep(Drive.TICK)


async def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", default="127.0.0.1:0")
    ap.add_argument("--state", default=None)
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(":")
    drive = Drive()
    srv = Server(drive, args.state)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, srv.save_state)
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    server = await asyncio.start_server(srv.handle, host, int(port))
    t = asyncio.create_task(ticker(drive))
    p = server.sockets[0].getsockname()[1]
    print("listening tcp %s:%d" % (host, p), flush=True)
    await stop.wait()
    srv.save_state()
    t.cancel()
    server.close()
    for w in list(srv.conns):
        try:
            w.close()
        except Exception:
            pass


if __name__ == "__main__":
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
