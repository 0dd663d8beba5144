#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet, open loop -- Modbus/TCP server simulator.

Written from the LMD MODBUS/TCP Fieldbus manual (LMD-MODBUS-REV-D) and the
public Modbus specifications only.  Standard library only.
See DECISIONS.md for every interpretation made.
"""
import argparse
import asyncio
import json
import os
import signal
import struct
import sys
import time

# ---------------------------------------------------------------------------
# constants / identification
# ---------------------------------------------------------------------------
ACCEPTED_UNITS = (0x00, 0xFF)      # TCP guide 4.4.1.3: 0xFF recommended, 0 also accepted
MAX_CONNECTIONS = 4
MAX_REG_QTY = 2                    # manual l.898-902 / 965-969: 1 to 2 registers
MAX_BIT_QTY = 4                    # manual l.733 / 798: 1 to 4 points
MFG_WRITE_MAX = 28                 # manual l.1174

DEVICE_ID = {
    0x00: b"IMS USA",
    0x01: b"LMDOE421",
    0x02: b"4.0.0.0",
    0x03: b"https://novantaims.com/",
    0x04: b"LMD Ethernet",
    0x05: b"LMD0000471",
    0x06: b"LMDCM 6.010, Hw: 1.0",
}

MS_VALUES = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)

INPUT_TYPES = (0, 1, 2, 3, 5, 7, 8, 11, 12)
OUTPUT_TYPES_OPEN = (16, 17, 18, 20, 23, 28, 29)       # 21/24/25 closed loop, 26/27 reserved

I32_MIN, I32_MAX = -2147483648, 2147483647

# ---------------------------------------------------------------------------
# register map
# kinds: 'rw' read/write setting, 'ro' read-only status, 'cmd' write-only command
# (reads back 0), 'cl' closed-loop only -> not present on this open-loop product
# ---------------------------------------------------------------------------


class Item:
    def __init__(self, addr, n, name, kind, lo=None, hi=None, default=0, signed=False,
                 allowed=None, param=False):
        self.addr, self.n, self.name, self.kind = addr, n, name, kind
        self.lo, self.hi, self.default, self.signed = lo, hi, default, signed
        self.allowed, self.param = allowed, param


ITEMS = [
    Item(0x0000, 2, "A", "rw", 91, 1525878997, 1000000, param=True),
    Item(0x0004, 1, "BY", "ro"),
    Item(0x0005, 2, "C1", "rw", I32_MIN, I32_MAX, 0, signed=True),
    Item(0x0007, 2, "C2", "cl"),
    Item(0x0009, 1, "CE", "rw", 0, 1, 1, param=True),
    Item(0x000E, 1, "CW", "rw", 0, 255, 10, param=True),
    Item(0x000F, 1, "D1", "rw", 0, 255, 0, param=True),
    Item(0x0010, 1, "D2", "rw", 0, 255, 0, param=True),
    Item(0x0011, 1, "D3", "rw", 0, 255, 0, param=True),
    Item(0x0012, 1, "D4", "rw", 0, 255, 0, param=True),
    Item(0x0013, 1, "D5", "rw", 0, 255, 0, param=True),
    Item(0x0018, 2, "D", "rw", 91, 1525878997, 1000000, param=True),
    Item(0x001A, 1, "DB", "cl"),
    Item(0x001B, 1, "DC", "cmd"),
    Item(0x001C, 1, "DE", "rw", 0, 1, 1, param=True),
    Item(0x001E, 1, "EE", "cl"),
    Item(0x001F, 1, "EF", "ro"),
    Item(0x0021, 1, "ER", "rw", 0, 0, 0),
    Item(0x0024, 1, "FC", "rw", 0, 9, 0, param=True),
    Item(0x0029, 1, "HC", "rw", 0, 100, 5, param=True),
    Item(0x002A, 1, "HI", "cl"),
    Item(0x002B, 1, "HM", "cmd", 1, 4),
    Item(0x002C, 1, "HT", "rw", 0, 65535, 500, param=True),
    Item(0x002D, 1, "I1", "ro"),
    Item(0x002E, 1, "I2", "ro"),
    Item(0x002F, 1, "I3", "ro"),
    Item(0x0030, 1, "I4", "ro"),
    Item(0x0031, 1, "I5", "ro"),
    Item(0x0032, 1, "I6", "cl"),
    Item(0x0037, 1, "IC", "cmd"),
    Item(0x003B, 1, "IN", "ro"),
    Item(0x003C, 1, "IP", "cmd"),
    Item(0x003F, 1, "JE", "rw", 0, 1, 0, param=True),
    Item(0x0042, 1, "LM", "rw", 1, 6, 1, param=True),
    Item(0x0043, 2, "MA", "cmd", I32_MIN, I32_MAX, signed=True),
    Item(0x0045, 1, "MP", "ro"),
    Item(0x0046, 2, "MR", "cmd", I32_MIN, I32_MAX, signed=True),
    Item(0x0048, 1, "MS", "rw", None, None, 256, allowed=MS_VALUES, param=True),
    Item(0x0049, 1, "MT", "rw", 0, 65000, 0, param=True),
    Item(0x004A, 1, "MV", "ro"),
    Item(0x004B, 1, "O1", "rw", 0, 1, 0),
    Item(0x004C, 1, "O2", "rw", 0, 1, 0),
    Item(0x004D, 1, "O3", "rw", 0, 1, 0),
    Item(0x004E, 1, "OF", "ro"),
    Item(0x0056, 1, "OT", "rw", 0, 15, 0),
    Item(0x0057, 2, "P", "rw", I32_MIN, I32_MAX, 0, signed=True),
    Item(0x0059, 2, "PC", "ro", signed=True),
    Item(0x005C, 1, "PM", "cl"),
    Item(0x005F, 2, "R1", "rw", I32_MIN, I32_MAX, 0, signed=True),
    Item(0x0061, 2, "R2", "rw", I32_MIN, I32_MAX, 0, signed=True),
    Item(0x0063, 2, "R3", "rw", I32_MIN, I32_MAX, 0, signed=True),
    Item(0x0065, 2, "R4", "rw", I32_MIN, I32_MAX, 0, signed=True),
    Item(0x0067, 1, "RC", "rw", 1, 100, 25, param=True),
    Item(0x0076, 1, "S", "cmd"),
    Item(0x0077, 1, "SF", "cl"),
    Item(0x0078, 2, "SL", "cmd", -5000000, 5000000, signed=True),
    Item(0x007A, 1, "SM", "cl"),
    Item(0x007B, 1, "ST", "cl"),
    Item(0x007D, 1, "TE", "rw", None, None, 0, allowed=(0, 16), param=True),
    Item(0x0085, 2, "V", "ro", signed=True),
    Item(0x0088, 1, "VC", "ro"),
    Item(0x0089, 2, "VI", "rw", 1, 2559999, 1000, param=True),
    Item(0x008B, 2, "VM", "rw", 2, 2560000, 768000, param=True),
    Item(0x008D, 1, "WT", "rw", 0, 84, 80, param=True),
    # 5.1 hMTechnology specific registers: closed loop only
    Item(0x008E, 1, "AS", "cl"),
    Item(0x008F, 1, "AF", "cl"),
    Item(0x0091, 1, "CB", "cl"),
    Item(0x0093, 1, "CF", "cl"),
    Item(0x0095, 2, "LD", "cl"),
    Item(0x0097, 2, "LG", "cl"),
    Item(0x0099, 2, "LL", "cl"),
    Item(0x009B, 1, "LR", "cl"),
    Item(0x009C, 2, "LT", "cl"),
    Item(0x009E, 2, "MF", "cl"),
    Item(0x00A0, 1, "MU", "cl"),
    Item(0x00A1, 1, "SC", "cl"),
    Item(0x00A3, 2, "TS", "cl"),
    Item(0x00A5, 1, "TD", "cl"),
    Item(0x00A6, 1, "TQ", "cl"),
    Item(0x00A7, 1, "VF", "cl"),
]
for _i in range(8):
    ITEMS.append(Item(0x00A8 + 2 * _i, 2, "V%d" % (_i + 1), "rw", I32_MIN, I32_MAX, 0, signed=True))

# register address -> (item, offset)
REGMAP = {}
for _it in ITEMS:
    for _k in range(_it.n):
        REGMAP[_it.addr + _k] = (_it, _k)
ITEM_BY_NAME = {it.name: it for it in ITEMS}

# manufacturer-specific mnemonics: name -> access ('r','w','rw'), or 'na'
MFG = {
    "\x1b": "w", "AO": "rw", "CP": "w", "EX": "w", "IS": "rw", "IT": "r", "OS": "rw",
    "PS": "w", "RS": "w", "E": "w", "RD": "rw", "AJ": "rw", "AT": "rw", "BE": "rw",
    "BL": "rw", "BM": "rw", "DJ": "rw", "DT": "rw", "FL": "rw", "LS": "rw", "UG": "w",
    "VT": "r", "TR": "rw", "S1": "rw", "S2": "rw", "S3": "rw", "S4": "rw",
    # not applicable to an open-loop integrated LMD
    "EL": "na", "MU": "na", "FS": "na", "HF": "na", "AV": "na",
}
SIMPLE_MFG = {  # name -> (lo, hi, default)
    "AO": (0, 65535, 0), "RD": (0, 1, 0), "AJ": (1, 999, 128), "AT": (0, 1, 0),
    "BE": (0, 1, 0), "BL": (0, 2147483647, 0), "BM": (0, 1, 0), "DJ": (1, 999, 128),
    "DT": (0, 1, 0), "FL": (0, 1, 0),
}
UG_KEY = "2956102"


class ModbusExc(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


def to_i32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


# ---------------------------------------------------------------------------
# device model
# ---------------------------------------------------------------------------
class Drive:
    def __init__(self):
        self.counters = {"bus_messages": 0, "exception_responses": 0, "dropped_frames": 0,
                         "closed_connections_bad_mbap": 0, "other_unit_frames": 0}
        self.factory_params()
        self.regs = {}
        for it in ITEMS:
            if it.kind == "rw":
                self.regs[it.name] = it.default
        self.pos = 0.0          # motor position, steps
        self.vel = 0.0          # signed steps/s
        self.c1 = 0.0
        self.mode = None        # None, 'move', 'slew', 'home', 'stop'
        self.target = 0
        self.slew_v = 0
        self.home_phase = 0
        self.home_t = 0.0
        self.vc = 0
        self.latch = [0, 0, 0, 0]   # output latches 1-4
        self.pc = 0
        self.nvm = self.param_snapshot()

    # parameters restored by IP (manual l.2172) and saved by S (l.2384)
    def factory_params(self):
        self.mfg = {k: v[2] for k, v in SIMPLE_MFG.items()}
        self.inputs = {n: {"type": 0, "active": 0, "sink": 0} for n in (1, 2, 3, 4)}
        self.analog = {"mode": 9, "range": 0}
        self.outputs = {n: {"type": 16, "active": 1} for n in (1, 2, 3)}
        self.softlim = {0: {"pos": 0, "enable": 0}, 1: {"pos": 0, "enable": 0}}
        self.trip = {"pos": 0, "output": 0, "state": 0}

    def param_snapshot(self):
        d = {it.name: (self.regs[it.name] if hasattr(self, "regs") and it.name in self.regs else it.default)
             for it in ITEMS if it.param}
        d["mfg"] = dict(self.mfg)
        d["inputs"] = json.loads(json.dumps(self.inputs))
        d["analog"] = dict(self.analog)
        d["outputs"] = json.loads(json.dumps(self.outputs))
        d["softlim"] = json.loads(json.dumps(self.softlim))
        d["trip"] = dict(self.trip)
        return d

    def initialize_parameters(self):
        for it in ITEMS:
            if it.param:
                self.regs[it.name] = it.default
        self.factory_params()

    # ------------------------------------------------------------ status
    @property
    def moving(self):
        return 1 if self.mode is not None else 0

    def output_state(self, n):
        if n == 4:
            return self.latch[3]
        cfg = self.outputs[n]
        t = cfg["type"]
        if t == 16:
            return self.latch[n - 1]
        if t == 17:
            act = self.moving
        elif t == 18:
            act = 0
        elif t == 20:
            act = self.vc
        elif t == 23:
            act = 1 if self.mode == "move" else 0
        else:
            act = 0
        return act

    def read_item(self, it):
        nm = it.name
        if it.kind == "cmd":
            return 0
        if nm in ("I1", "I2", "I3", "I4", "I5", "IN", "EF", "OF", "BY"):
            return 0
        if nm == "P":
            return to_i32(int(round(self.pos)))
        if nm == "C1":
            return to_i32(int(round(self.c1)))
        if nm == "MV":
            return self.moving
        if nm == "MP":
            return 1 if self.mode == "move" else 0
        if nm == "VC":
            return self.vc
        if nm == "V":
            return int(self.vel)
        if nm == "PC":
            return self.pc
        if nm in ("O1", "O2", "O3"):
            return self.output_state(int(nm[1]))
        if nm == "OT":
            return sum(self.output_state(k) << (k - 1) for k in (1, 2, 3, 4))
        return self.regs[nm]

    # ------------------------------------------------------------ motion
    def start_motion(self, kind, value):
        if self.regs["DE"] == 0:
            raise ModbusExc(4)
        if kind == "slew":
            if self.mode in ("move", "home"):
                raise ModbusExc(4)
            if value == 0:
                if self.mode == "slew":
                    self.slew_v = 0
                return
            self.mode = "slew"
            self.slew_v = value
            return
        if self.mode is not None:
            raise ModbusExc(4)
        if kind == "MA":
            tgt = value
        elif kind == "MR":
            tgt = int(round(self.pos)) + value
        else:  # home
            self.mode = "home"
            self.home_phase = 0
            self.home_t = 0.0
            hm = value
            self.home_dir = -1 if hm in (1, 2) else 1
            self.creep_dir = 1 if hm in (1, 4) else -1
            return
        if tgt == int(round(self.pos)):
            return
        self.mode = "move"
        self.target = tgt

    def stop(self):
        if self.mode is not None:
            self.mode = "stop"

    def tick(self, dt):
        if self.mode is None:
            self.vc = 0
            return
        A = self.regs["A"]
        D = self.regs["D"]
        VI = self.regs["VI"]
        VM = self.regs["VM"]
        old = self.pos
        speed = abs(self.vel)
        if self.mode == "move":
            rem = self.target - self.pos
            d = 1 if rem > 0 else -1
            stopd = speed * speed / (2.0 * D)
            if abs(rem) <= stopd + speed * dt:
                nspeed = max(speed - D * dt, float(VI))
            else:
                nspeed = min(max(speed, float(VI)) + A * dt, float(VM))
            self.vc = 1 if nspeed != speed else 0
            step = nspeed * dt
            if step >= abs(rem):
                self.pos = float(self.target)
                self.vel = 0.0
                self.mode = None
                self.vc = 0
            else:
                self.pos += d * step
                self.vel = d * nspeed
        elif self.mode in ("slew", "stop"):
            sv = float(self.slew_v) if self.mode == "slew" else 0.0
            if self.vel == 0.0 and sv != 0.0:
                self.vel = VI if sv > 0 else -VI
                if abs(sv) < VI:
                    self.vel = sv
            dv = sv - self.vel
            accel = abs(sv) > abs(self.vel) and (sv * self.vel) >= 0
            rate = (A if accel else D) * dt
            if abs(dv) <= rate:
                self.vel = sv
                self.vc = 0
            else:
                self.vel += rate if dv > 0 else -rate
                self.vc = 1
            if sv == 0.0 and abs(self.vel) <= VI:
                self.vel = 0.0
            self.pos += self.vel * dt
            if self.vel == 0.0 and sv == 0.0:
                self.mode = None
                self.vc = 0
        elif self.mode == "home":
            self.home_t += dt
            if self.home_phase == 0:        # slew towards switch at VM
                self.vel = self.home_dir * min(float(VM), max(speed, float(VI)) + A * dt)
                self.vc = 1 if abs(self.vel) < VM else 0
                if self.home_t >= 0.4:
                    self.home_phase, self.home_t = 1, 0.0
            elif self.home_phase == 1:      # decelerate
                s = max(0.0, speed - D * dt)
                self.vel = self.home_dir * s
                self.vc = 1
                if s <= VI:
                    self.home_phase, self.home_t = 2, 0.0
            else:                           # creep off switch at VI
                self.vel = self.creep_dir * float(VI)
                self.vc = 0
                if self.home_t >= 0.1:
                    self.pos = 0.0
                    self.vel = 0.0
                    self.mode = None
                    return
            self.pos += self.vel * dt
        # software limits (LS), hard stop at the limit position
        for dr, sgn in ((1, 1), (0, -1)):
            lim = self.softlim[dr]
            if lim["enable"] and self.mode is not None and self.mode != "home":
                if (sgn > 0 and self.pos > lim["pos"] and self.vel > 0) or \
                   (sgn < 0 and self.pos < lim["pos"] and self.vel < 0):
                    self.pos = float(lim["pos"])
                    self.vel = 0.0
                    self.mode = None
                    self.vc = 0
        self.c1 += self.pos - old
        if self.pos > I32_MAX or self.pos < I32_MIN:
            self.pos = float(to_i32(int(self.pos)))

    # ------------------------------------------------------------ dump
    def dump(self):
        hr = {}
        for it in ITEMS:
            if it.kind == "cl":
                continue
            hr["0x%04X" % it.addr] = {"name": it.name, "value": self.read_item(it)}
        return {
            "device": "Lexium MDrive LMD Ethernet (open loop), Modbus/TCP",
            "holding_registers": hr,
            "coils": {"0x%04X" % i: self.output_state(i + 1) for i in range(4)},
            "output_latches": list(self.latch),
            "discrete_inputs": {"0x%04X" % i: 0 for i in range(4)},
            "manufacturer_functions": {
                **{k: v for k, v in self.mfg.items()},
                "IS": {str(k): v for k, v in self.inputs.items()},
                "IS5_analog": dict(self.analog),
                "OS": {str(k): v for k, v in self.outputs.items()},
                "LS": {str(k): v for k, v in self.softlim.items()},
                "TR": dict(self.trip),
                "IT": "31,35", "VT": "24,48",
            },
            "motion": {"moving": self.moving, "mode": self.mode, "velocity": int(self.vel)},
            "program": {"stored": False, "running": False},
            "nvm": self.nvm,
            "device_identification": {"0x%02X" % k: v.decode() for k, v in DEVICE_ID.items()},
            "diagnostic_counters": dict(self.counters),
        }


# ---------------------------------------------------------------------------
# PDU handling
# ---------------------------------------------------------------------------
def u16(b, o):
    return (b[o] << 8) | b[o + 1]


class Server:
    def __init__(self, state_file):
        self.d = Drive()
        self.state_file = state_file
        self.conns = set()

    # ---------------------------------------------------------------- FC 01/02
    def fc_read_bits(self, fc, pdu):
        if len(pdu) < 5:
            raise ModbusExc(3)
        start, qty = u16(pdu, 1), u16(pdu, 3)
        if qty < 1 or qty > 2000:
            raise ModbusExc(3)
        if fc == 2 and 0x002D <= start <= 0x0030:
            start -= 0x002D          # alias: manual example l.761-763 uses 0x002D
        if start + qty > MAX_BIT_QTY:
            raise ModbusExc(2)
        if fc == 1:
            bits = [self.d.output_state(start + k + 1) for k in range(qty)]
        else:
            bits = [0] * qty
        val = 0
        for k, b in enumerate(bits):
            val |= b << k
        return bytes([fc, 1, val])

    # ---------------------------------------------------------------- FC 05
    def fc_write_coil(self, pdu):
        if len(pdu) < 5:
            raise ModbusExc(3)
        addr, val = u16(pdu, 1), u16(pdu, 3)
        if val not in (0x0000, 0xFF00):
            raise ModbusExc(3)
        if addr >= MAX_BIT_QTY:
            raise ModbusExc(2)
        self.d.latch[addr] = 1 if val else 0
        return bytes(pdu[:5])

    # ---------------------------------------------------------------- register helpers
    def resolve(self, start, qty):
        """Return list of whole items covering [start, start+qty)."""
        items = []
        a = start
        end = start + qty
        while a < end:
            ent = REGMAP.get(a)
            if ent is None:
                raise ModbusExc(2)
            it, off = ent
            if off != 0 or it.addr + it.n > end or it.kind == "cl":
                raise ModbusExc(2)
            items.append(it)
            a += it.n
        return items

    # ---------------------------------------------------------------- FC 03
    def fc_read_regs(self, pdu):
        if len(pdu) < 5:
            raise ModbusExc(3)
        start, qty = u16(pdu, 1), u16(pdu, 3)
        if qty < 1 or qty > 125:
            raise ModbusExc(3)
        if qty > MAX_REG_QTY:
            raise ModbusExc(2)
        items = self.resolve(start, qty)
        out = bytearray()
        for it in items:
            v = self.d.read_item(it)
            if it.n == 2:
                v &= 0xFFFFFFFF
                out += struct.pack(">HH", v & 0xFFFF, v >> 16)   # low word first
            else:
                out += struct.pack(">H", v & 0xFFFF)
            if it.name == "ER":
                self.d.regs["ER"] = 0   # l.2083-2085: reading ER clears it
        return bytes([3, len(out)]) + bytes(out)

    # ---------------------------------------------------------------- FC 16
    def fc_write_regs(self, pdu):
        if len(pdu) < 6:
            raise ModbusExc(3)
        start, qty, bc = u16(pdu, 1), u16(pdu, 3), pdu[5]
        if qty < 1 or qty > 123 or bc != 2 * qty or len(pdu) < 6 + bc:
            raise ModbusExc(3)
        if qty > MAX_REG_QTY:
            raise ModbusExc(2)
        items = self.resolve(start, qty)
        data = pdu[6:6 + bc]
        vals = []
        o = 0
        for it in items:
            if it.n == 2:
                lo, hi = u16(data, o), u16(data, o + 2)
                raw = (hi << 16) | lo
                v = to_i32(raw) if it.signed else raw
            else:
                raw = u16(data, o)
                v = raw
                if it.signed or it.name == "DB":
                    v = raw - 0x10000 if raw & 0x8000 else raw
            o += 2 * it.n
            vals.append((it, v))
        for it, v in vals:
            if it.kind == "ro":
                raise ModbusExc(3)
        for it, v in vals:
            self.check_value(it, v, vals)
        for it, v in vals:
            self.apply(it, v)
        return bytes(pdu[:5])

    def check_value(self, it, v, vals):
        d = self.d
        nm = it.name
        if it.allowed is not None:
            if v not in it.allowed:
                raise ModbusExc(3)
        elif it.lo is not None and not (it.lo <= v <= it.hi):
            raise ModbusExc(3)
        pending = {i.name: x for i, x in vals}
        if nm == "HT":
            if v == 1 or v + pending.get("MT", d.regs["MT"]) > 65535:
                raise ModbusExc(3)
        if nm == "MT":
            if v + pending.get("HT", d.regs["HT"]) > 65535:
                raise ModbusExc(3)
        if nm == "VI" and v >= pending.get("VM", d.regs["VM"]):
            raise ModbusExc(3)
        if nm == "VM" and v <= pending.get("VI", d.regs["VI"]):
            raise ModbusExc(3)
        if nm in ("DC", "IC"):
            tgt = REGMAP.get(v)
            if tgt is None or tgt[1] != 0 or tgt[0].name not in \
                    ("C1", "P", "R1", "R2", "R3", "R4") + tuple("V%d" % k for k in range(1, 9)):
                raise ModbusExc(3)
            if tgt[0].name == "P" and d.mode is not None:
                raise ModbusExc(4)
        if nm == "P" and d.mode is not None:
            raise ModbusExc(4)
        if nm in ("MA", "MR", "HM", "SL"):
            if d.regs["DE"] == 0:
                raise ModbusExc(4)
            if nm in ("MA", "MR", "HM") and d.mode is not None:
                raise ModbusExc(4)
            if nm == "SL" and d.mode in ("move", "home"):
                raise ModbusExc(4)

    def apply(self, it, v):
        d = self.d
        nm = it.name
        if nm == "MA":
            d.start_motion("MA", v)
        elif nm == "MR":
            d.start_motion("MR", v)
        elif nm == "SL":
            d.start_motion("slew", v)
        elif nm == "HM":
            d.start_motion("home", v)
        elif nm in ("DC", "IC"):
            tgt = REGMAP[v][0]
            delta = -1 if nm == "DC" else 1
            if tgt.name == "P":
                d.pos = float(to_i32(int(round(d.pos)) + delta))
            elif tgt.name == "C1":
                d.c1 = float(to_i32(int(round(d.c1)) + delta))
            else:
                d.regs[tgt.name] = to_i32(d.regs[tgt.name] + delta)
        elif nm == "IP":
            d.initialize_parameters()
        elif nm == "S":
            d.nvm = d.param_snapshot()
        elif nm == "P":
            d.pos = float(v)
        elif nm == "C1":
            d.c1 = float(v)
        elif nm in ("O1", "O2", "O3"):
            d.latch[int(nm[1]) - 1] = v
        elif nm == "OT":
            for k in range(4):
                d.latch[k] = (v >> k) & 1
        elif nm == "DE":
            d.regs["DE"] = v
            if v == 0:
                d.mode = None
                d.vel = 0.0
                d.vc = 0
        else:
            d.regs[nm] = v

    # ---------------------------------------------------------------- FC 43/14
    def fc_devid(self, pdu):
        if len(pdu) < 2:
            raise ModbusExc(3)
        if pdu[1] != 0x0E:
            raise ModbusExc(1)
        if len(pdu) < 4:
            raise ModbusExc(3)
        code, oid = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise ModbusExc(3)
        if code == 4:
            if oid not in DEVICE_ID:
                raise ModbusExc(2)
            objs = [oid]
        else:
            last = 0x02 if code == 1 else 0x06
            if oid > last:
                oid = 0
            objs = list(range(oid, last + 1))
        body = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(objs)])
        for o in objs:
            body += bytes([o, len(DEVICE_ID[o])]) + DEVICE_ID[o]
        return bytes(body)

    # ---------------------------------------------------------------- FC 65/66
    @staticmethod
    def decode_mnemonic(b4):
        s = bytes(reversed(b4)).replace(b"\x00", b"").replace(b" ", b"")
        try:
            s = s.decode("ascii")
        except UnicodeDecodeError:
            return None, None
        point = None
        if len(s) >= 2 and s[-1].isdigit() and s[:-1] in ("IS", "OS", "LS", "TR"):
            point = int(s[-1])
            s = s[:-1]
        return s, point

    @staticmethod
    def fmt(vals):
        return ", ".join(str(v) for v in vals)

    def mfg_read(self, name, point):
        d = self.d
        if name in SIMPLE_MFG:
            return str(d.mfg[name])
        if name == "IT":
            return "31,35"
        if name == "VT":
            return "24,48"
        if name in ("S1", "S2", "S3", "S4"):
            c = d.inputs[int(name[1])]
            return self.fmt((c["type"], c["active"], c["sink"]))
        if name == "IS":
            def one(n):
                if n == 5:
                    return (5, d.analog["mode"], d.analog["range"])
                return (n, d.inputs[n]["type"], d.inputs[n]["active"])
            if point is None:
                return self.fmt(sum((one(n) for n in (1, 2, 3, 4, 5)), ()))
            if point not in (1, 2, 3, 4, 5):
                raise ModbusExc(2)
            return self.fmt(one(point))
        if name == "OS":
            def one(n):
                return (n, d.outputs[n]["type"], d.outputs[n]["active"])
            if point is None:
                return self.fmt(sum((one(n) for n in (1, 2, 3)), ()))
            if point not in (1, 2, 3):
                raise ModbusExc(2)
            return self.fmt(one(point))
        if name == "LS":
            def one(n):
                return (n, d.softlim[n]["pos"], d.softlim[n]["enable"])
            if point is None:
                return self.fmt(one(0) + one(1))
            if point not in (0, 1):
                raise ModbusExc(2)
            return self.fmt(one(point))
        if name == "TR":
            if point not in (None, 3):
                raise ModbusExc(2)
            t = d.trip
            return self.fmt((t["pos"], t["output"], t["state"]))
        raise ModbusExc(1)

    @staticmethod
    def parse_ints(data, count):
        try:
            s = data.decode("ascii")
        except UnicodeDecodeError:
            raise ModbusExc(3)
        if not s.startswith("="):
            raise ModbusExc(3)
        parts = s[1:].split(",")
        if len(parts) != count:
            raise ModbusExc(3)
        out = []
        for p in parts:
            p = p.strip()
            body = p[1:] if p[:1] in "+-" else p
            if not body.isdigit() or not body.isascii():
                raise ModbusExc(3)
            out.append(int(p))
        return out

    def mfg_write(self, name, point, data):
        d = self.d
        if name in ("\x1b", "CP", "PS", "RS", "E"):
            if data:
                raise ModbusExc(3)
            if name == "\x1b":
                d.stop()
            return
        if point is not None and name != "TR":
            raise ModbusExc(2)
        if name == "EX":
            lbl = data.decode("ascii", "replace").strip()
            if not lbl or len(data) > 4:
                raise ModbusExc(3)
            raise ModbusExc(3)      # no program stored (factory fresh), label unknown
        if name == "UG":
            key = data.decode("ascii", "replace").strip()
            if key != UG_KEY:
                raise ModbusExc(3)
            raise ModbusExc(4)      # upgrade only through the LSS Ethernet interface
        if name in SIMPLE_MFG:
            lo, hi, _ = SIMPLE_MFG[name]
            (v,) = self.parse_ints(data, 1)
            if not lo <= v <= hi:
                raise ModbusExc(3)
            d.mfg[name] = v
            return
        if name in ("S1", "S2", "S3", "S4"):
            t, a, s = self.parse_ints(data, 3)
            if t not in INPUT_TYPES or a not in (0, 1) or s not in (0, 1):
                raise ModbusExc(3)
            d.inputs[int(name[1])] = {"type": t, "active": a, "sink": s}
            return
        if name == "IS":
            ln, t, a = self.parse_ints(data, 3)
            if ln in (1, 2, 3, 4):
                if t not in INPUT_TYPES or a not in (0, 1):
                    raise ModbusExc(3)
                d.inputs[ln]["type"] = t
                d.inputs[ln]["active"] = a
            elif ln == 5:
                if t not in (9, 10) or a not in (0, 1):
                    raise ModbusExc(3)
                d.analog = {"mode": t, "range": a}
            else:
                raise ModbusExc(3)
            return
        if name == "OS":
            ln, t, a = self.parse_ints(data, 3)
            if ln not in (1, 2, 3) or t not in OUTPUT_TYPES_OPEN or a not in (0, 1):
                raise ModbusExc(3)
            if t == 28 and ln != 3:
                raise ModbusExc(3)
            d.outputs[ln] = {"type": t, "active": a}
            return
        if name == "LS":
            dr, p, en = self.parse_ints(data, 3)
            if dr not in (0, 1) or not I32_MIN <= p <= I32_MAX or en not in (0, 1):
                raise ModbusExc(3)
            d.softlim[dr] = {"pos": p, "enable": en}
            return
        if name == "TR":
            if point not in (None, 3):
                raise ModbusExc(2)
            p, o, st = self.parse_ints(data, 3)
            if not I32_MIN <= p <= I32_MAX or o not in (0, 1, 2, 3) or st not in (0, 1):
                raise ModbusExc(3)
            d.trip = {"pos": p, "output": o, "state": st}
            return
        raise ModbusExc(1)

    def fc_mfg(self, fc, pdu):
        if len(pdu) < 5 or (fc == 0x42 and len(pdu) < 6):
            raise ModbusExc(3)
        name, point = self.decode_mnemonic(pdu[1:5])
        if fc == 0x42:
            bc = pdu[5]
            if bc > MFG_WRITE_MAX or len(pdu) < 6 + bc:
                raise ModbusExc(3)
        acc = MFG.get(name)
        if acc is None or acc == "na":
            raise ModbusExc(1)
        if fc == 0x41:
            if "r" not in acc:
                raise ModbusExc(1)
            s = self.mfg_read(name, point).encode("ascii")
            out = bytes([0x41, len(s)]) + s
            if len(s) % 2:
                out += b"\x00"      # l.1129: n = N or N+1 (pad to even)
            return out
        if "w" not in acc:
            raise ModbusExc(1)
        data = bytes(pdu[6:6 + bc])
        self.mfg_write(name, point, data)
        return bytes([0x42, bc]) + bytes(pdu[1:5])

    # ---------------------------------------------------------------- dispatcher
    def handle_pdu(self, pdu):
        fc = pdu[0]
        try:
            if fc in (1, 2):
                return self.fc_read_bits(fc, pdu)
            if fc == 5:
                return self.fc_write_coil(pdu)
            if fc == 3:
                return self.fc_read_regs(pdu)
            if fc == 0x10:
                return self.fc_write_regs(pdu)
            if fc == 0x2B:
                return self.fc_devid(pdu)
            if fc in (0x41, 0x42):
                return self.fc_mfg(fc, pdu)
            raise ModbusExc(1)
        except ModbusExc as e:
            self.d.counters["exception_responses"] += 1
            return bytes([fc | 0x80, e.code])
        except Exception:
            self.d.counters["exception_responses"] += 1
            return bytes([fc | 0x80, 4])

    # ---------------------------------------------------------------- TCP
    async def client(self, reader, writer):
        if len(self.conns) >= MAX_CONNECTIONS:
            writer.close()
            return
        self.conns.add(writer)
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid, pid, ln, uid = struct.unpack(">HHHB", hdr)
                if pid != 0 or ln < 2 or ln > 254:
                    self.d.counters["closed_connections_bad_mbap"] += 1
                    break
                pdu = await reader.readexactly(ln - 1)
                fc = pdu[0]
                if uid not in ACCEPTED_UNITS:
                    self.d.counters["other_unit_frames"] += 1
                    continue
                if fc == 0 or fc >= 0x80:
                    self.d.counters["dropped_frames"] += 1
                    continue
                self.d.counters["bus_messages"] += 1
                resp = self.handle_pdu(pdu)
                writer.write(struct.pack(">HHHB", tid, 0, len(resp) + 1, uid) + resp)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            self.conns.discard(writer)
            try:
                writer.close()
            except Exception:
                pass

    def write_state(self):
        if not self.state_file:
            return
        try:
            tmp = self.state_file + ".tmp"
            with open(tmp, "w") as f:
                json.dump(self.d.dump(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except Exception as e:
            print("state write failed: %s" % e, file=sys.stderr)

    async def motion_loop(self):
        last = time.monotonic()
        while True:
            await asyncio.sleep(0.01 if self.d.mode is not None else 0.05)
            now = time.monotonic()
            dt = min(now - last, 0.1)
            last = now
            try:
                self.d.tick(dt)
            except Exception:
                self.d.mode = None
                self.d.vel = 0.0


async def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", default="127.0.0.1:0")
    ap.add_argument("--state", default=None)
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(":")
    srv = Server(args.state)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, srv.write_state)
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    server = await asyncio.start_server(srv.client, host, int(port))
    mt = asyncio.create_task(srv.motion_loop())
    p = server.sockets[0].getsockname()[1]
    print("listening tcp %s:%d" % (host, p), flush=True)
    await stop.wait()
    server.close()
    mt.cancel()
    for w in list(srv.conns):
        try:
            w.close()
        except Exception:
            pass
    srv.write_state()


if __name__ == "__main__":
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
