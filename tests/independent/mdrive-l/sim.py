#!/usr/bin/env python3
"""MDrive 23 Plus2 Motion Control (Ethernet, MODBUS/TCP) simulator.

Usage: python3 sim.py --listen 127.0.0.1:0 [--state FILE]
Standard library only.  See DECISIONS.md for every interpretation of the manual.
"""
import argparse
import json
import os
import signal
import socket
import struct
import sys
import threading
import time

MAX_CONNECTIONS = 4          # incl. the built-in HMI
IDLE_TIMEOUT = 120.0         # seconds without a complete request
SERVICE_TIME = 0.002         # controller time per request (global, one at a time)
TICK = 0.01                  # motion integration step
HMI_UNIT = 1
HMI_PERIOD = 0.05            # 20 requests per second

STEPS_PER_REV = {1: 200, 2: 400, 4: 800, 5: 1000, 8: 1600, 10: 2000, 16: 3200, 25: 5000,
                 32: 6400, 50: 10000, 64: 12800, 100: 20000, 125: 25000, 128: 25600,
                 200: 40000, 250: 50000, 256: 51200, 180: 36000, 108: 21600, 127: 25400}

DEVICE_ID = [b"SEM USA", b"MDI1PRD23A7-EQ", b"4.0.0.0", b"www.imshome.com",
             b"MDrive Ethernet", b"ENP23A7-004711", b"ASI 4.0.0.2"]


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


def rng(lo, hi):
    return lambda v, st: lo <= v <= hi


# Register map: (address, mnemonic, number of registers, access, signed, validator, default)
# access: rw, ro, wo, rc (read clears)
U32 = (0, 0xFFFFFFFF)
ITEMS = [
    (0x0000, "A", 2, "rw", False, rng(91, 1525878997), 1000000),
    (0x0005, "C1", 2, "rw", True, None, 0),
    (0x0007, "C2", 2, "rw", True, None, 0),
    (0x0009, "CE", 1, "rw", False, rng(0, 1), 1),
    (0x000B, "CM", 1, "rw", False, rng(0, 1), 0),
    (0x000F, "D1", 1, "rw", False, rng(0, 255), 0),
    (0x0010, "D2", 1, "rw", False, rng(0, 255), 0),
    (0x0011, "D3", 1, "rw", False, rng(0, 255), 0),
    (0x0012, "D4", 1, "rw", False, rng(0, 255), 0),
    (0x0013, "D5", 1, "rw", False, rng(0, 255), 0),
    (0x0018, "D", 2, "rw", False, rng(91, 1525878997), 1000000),
    (0x001A, "DB", 1, "rw", False, rng(0, 65000), 10),
    (0x001B, "DC", 1, "wo", False, rng(1, 12), None),
    (0x001C, "DE", 1, "rw", False, rng(0, 1), 1),
    (0x001E, "EE", 1, "rw", False, rng(0, 1), 0),
    (0x001F, "EF", 1, "ro", False, None, 0),
    (0x0021, "ER", 1, "rc", False, rng(0, 0), 0),
    (0x0029, "HC", 1, "rw", False, rng(0, 100), 5),
    (0x002B, "HM", 1, "rw", False, rng(1, 4), 1),
    (0x002C, "HT", 1, "rw", False, lambda v, st: v == 0 or 2 <= v <= 65535, 500),
    (0x002D, "I1", 1, "ro", False, None, None),
    (0x002E, "I2", 1, "ro", False, None, None),
    (0x002F, "I3", 1, "ro", False, None, None),
    (0x0030, "I4", 1, "ro", False, None, None),
    (0x0031, "I5", 1, "ro", False, None, None),
    (0x0032, "I6", 1, "ro", False, None, None),
    (0x0037, "IC", 1, "wo", False, rng(1, 12), None),
    (0x003A, "IL", 1, "ro", False, None, None),
    (0x003B, "IN", 1, "ro", False, None, None),
    (0x003F, "JE", 1, "rw", False, rng(0, 1), 0),
    (0x0042, "LM", 1, "rw", False, rng(1, 6), 1),
    (0x0043, "MA", 2, "wo", True, None, None),
    (0x0045, "MP", 1, "ro", False, None, None),
    (0x0046, "MR", 2, "wo", True, None, None),
    (0x0048, "MS", 1, "rw", False, lambda v, st: v in STEPS_PER_REV, 256),
    (0x0049, "MT", 1, "rw", False, rng(0, 65000), 0),
    (0x004A, "MV", 1, "ro", False, None, None),
    (0x004B, "O1", 1, "rw", False, rng(0, 1), None),
    (0x004C, "O2", 1, "rw", False, rng(0, 1), None),
    (0x004D, "O3", 1, "rw", False, rng(0, 1), None),
    (0x004E, "O4", 1, "rw", False, rng(0, 1), None),
    (0x0055, "OL", 1, "rw", False, rng(0, 15), None),
    (0x0056, "OT", 1, "rw", False, rng(0, 15), None),
    (0x0057, "P", 2, "rw", True, None, 0),
    (0x0059, "PC", 2, "ro", True, None, 0),
    (0x005C, "PM", 1, "rw", False, rng(0, 1), 0),
    (0x005F, "R1", 2, "rw", True, None, 0),
    (0x0061, "R2", 2, "rw", True, None, 0),
    (0x0063, "R3", 2, "rw", True, None, 0),
    (0x0065, "R4", 2, "rw", True, None, 0),
    (0x0067, "RC", 1, "rw", False, rng(1, 100), 25),
    (0x0076, "S", 1, "wo", False, None, None),
    (0x0077, "SF", 1, "rw", False, rng(0, 65000), 15),
    (0x0078, "SL", 2, "wo", True, rng(-5000000, 5000000), None),
    (0x007A, "SM", 1, "rw", False, rng(0, 1), 0),
    (0x007B, "ST", 1, "ro", False, None, 0),
    (0x007D, "TE", 1, "rw", False, lambda v, st: v in (0, 16), 0),
    (0x0085, "V", 2, "ro", True, None, None),
    (0x0088, "VC", 1, "ro", False, None, None),
    (0x0089, "VI", 2, "rw", False, rng(1, 4999999), 1000),
    (0x008B, "VM", 2, "rw", False, rng(2, 5000000), 768000),
]
for _i in range(8):
    ITEMS.append((0x00A8 + 2 * _i, "V%d" % (_i + 1), 2, "rw", True, None, 0))

BY_ADDR = {}
for _it in ITEMS:
    BY_ADDR[_it[0]] = _it
# register -> (item start) for every covered register
REG_OWNER = {}
for _it in ITEMS:
    for _k in range(_it[2]):
        REG_OWNER[_it[0] + _k] = _it[0]

# Parameters saved in NVM by S (and restored at power on)
STORED = [it[1] for it in ITEMS if it[3] == "rw" and it[6] is not None
          and it[1] not in ("C1", "C2", "P")]
STORED_EXTRA = ["R1", "R2", "R3", "R4"]

INPUT_FUNCS = {0, 1, 2, 3, 5, 7, 8, 11}
OUTPUT_FUNCS = {16, 17, 18, 20, 21, 23}     # 24, 25 are Hybrid-only
HYBRID_OUTPUT_FUNCS = {24, 25}


def to_s32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


class Drive:
    """The drive state; every access under self.lock."""

    def __init__(self):
        self.lock = threading.RLock()
        self.params = {}
        for it in ITEMS:
            if it[3] in ("rw", "rc", "ro") and it[6] is not None:
                self.params[it[1]] = it[6]
        # I/O points 1..4: [type, active, sink]; output latches (logic state)
        self.io = {n: [0, 0, 0] for n in (1, 2, 3, 4)}
        self.outputs = {n: 0 for n in (1, 2, 3, 4)}
        self.mfg = {"S7": [33, 0], "S8": [33, 0], "CR": 1.0, "S5": [9, 0], "S13": [60, 0],
                    "TR": [0, 0, 0]}
        self.program = {"stored": False, "running": False, "paused": False}
        # motion
        self.pos = 0.0
        self.vel = 0.0
        self.mode = None           # None, 'pos', 'slew'
        self.target = 0.0
        self.slew_v = 0.0
        self.vchanging = False
        self.trip_ref = 0
        self.nvm = None
        self.nvm = self.nvm_image()
        self.counters = {"requests": 0, "responses": 0, "exception_responses": 0,
                         "dropped_frames": 0, "connections_accepted": 0,
                         "connections_refused": 0, "connections_closed_framing": 0,
                         "connections_closed_idle": 0}

    # ---- helpers --------------------------------------------------------
    def get_param(self, name):
        return self.params[name]

    def nvm_image(self):
        img = {k: self.params[k] for k in STORED}
        for k in STORED_EXTRA:
            img[k] = self.params[k]
        img["io"] = {str(n): list(v) for n, v in self.io.items()}
        img["mfg"] = json.loads(json.dumps(self.mfg))
        return img

    def is_gp_output(self, n):
        return self.io[n][0] == 16

    def point_state(self, n):
        """Logic state of I/O point n (what I1-I4 / FC 02 read)."""
        t = self.io[n][0]
        if t in OUTPUT_FUNCS:
            return self.output_logic(n)
        return 0                   # nothing wired to the inputs

    def output_logic(self, n):
        t = self.io[n][0]
        if t == 16:
            return self.outputs[n]
        if t == 17:
            return 1 if self.mode else 0
        if t == 18:
            return self.params["EF"]
        if t == 20:
            return 1 if self.vchanging else 0
        if t == 23:
            return 1 if self.mode == "pos" else 0
        return 0                   # 21 locked rotor: never

    def coil_state(self, n):
        return self.output_logic(n) if self.io[n][0] in OUTPUT_FUNCS else 0

    def out_group(self):
        return sum(self.coil_state(n) << (n - 1) for n in (1, 2, 3, 4))

    def in_group(self):
        return sum(self.point_state(n) << (n - 1) for n in (1, 2, 3, 4))

    # ---- item read / write ---------------------------------------------
    def read_item(self, it):
        name = it[1]
        if name in ("I1", "I2", "I3", "I4"):
            return self.point_state(int(name[1]))
        if name == "I5":
            return 0
        if name == "I6":
            return 0
        if name in ("IL", "IN"):
            return self.in_group()
        if name == "MP":
            return 1 if self.mode == "pos" else 0
        if name == "MV":
            return 1 if self.mode else 0
        if name == "VC":
            return 1 if self.vchanging else 0
        if name == "V":
            return int(round(self.vel))
        if name == "P":
            return int(round(self.pos))
        if name in ("O1", "O2", "O3", "O4"):
            return self.coil_state(int(name[1]))
        if name in ("OL", "OT"):
            return self.out_group()
        if name == "ER":
            v = self.params["ER"]
            self.params["ER"] = 0
            self.params["EF"] = 0
            return v
        return self.params[name]

    def check_write(self, it, v):
        """Validate; raise ModbusError.  v already decoded (signed if item is signed)."""
        addr, name, n, acc, sgn, val, dflt = it
        if acc == "ro":
            raise ModbusError(2)
        if not sgn and n == 2 and v < 0:
            raise ModbusError(3)
        if val is not None and not val(v, self):
            raise ModbusError(3)
        # execution checks (04)
        if name in ("O1", "O2", "O3", "O4"):
            if not self.is_gp_output(int(name[1])):
                raise ModbusError(4)
        if name in ("MA", "MR"):
            if self.params["DE"] == 0 or self.mode is not None:
                raise ModbusError(4)
        if name == "SL":
            if self.params["DE"] == 0 or self.mode == "pos":
                raise ModbusError(4)
        if name in ("P", "MS") and self.mode is not None:
            raise ModbusError(4)

    def apply_write(self, it, v):
        name = it[1]
        if name in ("O1", "O2", "O3", "O4"):
            self.outputs[int(name[1])] = v
        elif name in ("OL", "OT"):
            for n in (1, 2, 3, 4):
                if self.is_gp_output(n):
                    self.outputs[n] = (v >> (n - 1)) & 1
        elif name == "ER":
            self.params["ER"] = 0
            self.params["EF"] = 0
        elif name in ("DC", "IC"):
            var = "R%d" % v if v <= 4 else "V%d" % (v - 4)
            d = 1 if name == "IC" else -1
            self.params[var] = to_s32(self.params[var] + d)
        elif name == "MA":
            self.target = float(v)
            self.mode = "pos"
        elif name == "MR":
            self.target = self.pos + v
            self.mode = "pos"
        elif name == "SL":
            self.slew_v = float(v)
            if v != 0 or self.mode == "slew":
                self.mode = "slew"
        elif name == "S":
            self.nvm = self.nvm_image()
        elif name == "P":
            self.pos = float(v)
            self.params["P"] = v
        elif name == "DE":
            self.params["DE"] = v
            if v == 0:
                self.mode = None
                self.vel = 0.0
                self.vchanging = False
        elif name == "TE":
            self.params["TE"] = v
            self.trip_ref = int(round(self.pos))
        else:
            self.params[name] = v

    # ---- motion ---------------------------------------------------------
    def tick(self, dt):
        if self.mode is None:
            self.vel = 0.0
            self.vchanging = False
            return
        A = float(self.params["A"])
        D = float(self.params["D"])
        VI = float(self.params["VI"])
        VM = float(self.params["VM"])
        old_pos = self.pos
        old_speed = abs(self.vel)
        if self.mode == "pos":
            d = self.target - self.pos
            if abs(d) < 0.5:
                self.pos = self.target
                self._stop()
            else:
                sgn = 1.0 if d > 0 else -1.0
                speed = abs(self.vel)
                stopdist = max(0.0, speed * speed - VI * VI) / (2.0 * D)
                if stopdist >= abs(d):
                    speed = max(VI, speed - D * dt)
                elif speed < VM:
                    speed = min(VM, max(VI, speed + A * dt))
                elif speed > VM:
                    speed = max(VM, speed - D * dt)
                step = speed * dt
                if step >= abs(d):
                    self.pos = self.target
                    self._stop()
                else:
                    self.pos += sgn * step
                    self.vel = sgn * speed
                    self.vchanging = abs(speed - old_speed) > 1e-9
        else:
            tv = self.slew_v
            v = self.vel
            if v == 0.0:
                if tv == 0.0:
                    self._stop()
                    return
                v = (1.0 if tv > 0 else -1.0) * min(VI, abs(tv))
            elif tv == 0.0 or (tv > 0) != (v > 0):
                s = abs(v) - D * dt
                if s <= VI:
                    v = 0.0
                    if tv == 0.0:
                        self.pos += 0.0
                        self._stop()
                        self._update_counts(old_pos)
                        return
                else:
                    v = (1.0 if v > 0 else -1.0) * s
            else:
                s = abs(v)
                if s < abs(tv):
                    s = min(abs(tv), s + A * dt)
                elif s > abs(tv):
                    s = max(abs(tv), s - D * dt)
                v = (1.0 if v > 0 else -1.0) * s
            self.vel = v
            self.vchanging = abs(abs(v) - old_speed) > 1e-9
            self.pos += v * dt
        self._update_counts(old_pos)

    def _stop(self):
        self.mode = None
        self.vel = 0.0
        self.vchanging = False

    def _update_counts(self, old_pos):
        pos = min(max(self.pos, -2147483648.0), 2147483647.0)
        self.pos = pos
        delta = int(round(pos)) - int(round(old_pos))
        self.params["P"] = int(round(pos))
        self.params["C1"] = to_s32(self.params["C1"] + delta)
        if self.params["EE"]:
            spr = STEPS_PER_REV.get(self.params["MS"], 51200)
            self._c2_frac = getattr(self, "_c2_frac", 0.0) + delta * 2048.0 / spr
            whole = int(self._c2_frac)
            self._c2_frac -= whole
            self.params["C2"] = to_s32(self.params["C2"] + whole)
        te = self.params["TE"]
        trd = abs(self.mfg["TR"][0])
        if te & 16 and trd and abs(self.params["P"] - self.trip_ref) >= trd:
            self.params["TE"] = 0  # position trip fired; re-enable via TE

    # ---- dump -----------------------------------------------------------
    def dump(self):
        regs = {}
        for it in ITEMS:
            addr, name, n, acc = it[:4]
            if acc == "wo":
                continue
            if acc == "rc":
                v = self.params[name]       # do not clear while dumping
            else:
                v = self.read_item(it)
            regs["0x%04X" % addr] = {"mnemonic": name, "registers": n, "access": acc, "value": v}
        return {
            "device": "MDrive 23 Plus2 Motion Control, Ethernet (MODBUS/TCP)",
            "device_identification": {str(i): s.decode() for i, s in enumerate(DEVICE_ID)},
            "registers": regs,
            "io": {str(n): {"S%d" % n: list(self.io[n]), "output_latch": self.outputs[n]}
                   for n in (1, 2, 3, 4)},
            "mfg": {"S7": list(self.mfg["S7"]), "S8": list(self.mfg["S8"]),
                    "CR": "%.3f" % self.mfg["CR"], "S5": list(self.mfg["S5"]),
                    "S13": list(self.mfg["S13"]), "TR": list(self.mfg["TR"])},
            "motion": {"mode": self.mode, "moving": bool(self.mode)},
            "program": dict(self.program),
            "nvm": self.nvm,
            "diagnostic_counters": dict(self.counters),
            "live": {},
        }


# ------------------------------------------------------------------------
# Modbus PDU handling
# ------------------------------------------------------------------------
def mnemonic_of(b4):
    try:
        s = b4[::-1].decode("ascii")
    except UnicodeDecodeError:
        return None
    return s.rstrip(" ")


READ_MFG = {"S1", "S2", "S3", "S4", "S7", "S8", "CR", "S5", "S13", "TR", "E", "EX", "PS", "RS"}
WRITE_MFG = {"S1", "S2", "S3", "S4", "S7", "S8", "CR", "S5", "S13", "TR"}


def parse_fields(data):
    try:
        s = data.decode("ascii")
    except UnicodeDecodeError:
        raise ModbusError(3)
    s = s.replace(" ", "")
    if not s.startswith("="):
        raise ModbusError(3)
    parts = s[1:].split(",")
    if any(p == "" for p in parts):
        raise ModbusError(3)
    return parts


def parse_int(p):
    if not p or not (p.isdigit() or (p[0] in "+-" and p[1:].isdigit())):
        raise ModbusError(3)
    return int(p)


class Processor:
    def __init__(self, drive):
        self.d = drive

    def handle(self, pdu):
        """Return response PDU (bytes).  Called with the drive lock held."""
        fc = pdu[0]
        try:
            if fc == 0x01:
                return self.fc_bits(pdu, coils=True)
            if fc == 0x02:
                return self.fc_bits(pdu, coils=False)
            if fc == 0x03:
                return self.fc03(pdu)
            if fc == 0x05:
                return self.fc05(pdu)
            if fc == 0x10:
                return self.fc16(pdu)
            if fc == 0x2B:
                return self.fc43(pdu)
            if fc == 0x41:
                return self.fc65(pdu)
            if fc == 0x42:
                return self.fc66(pdu)
            raise ModbusError(1)
        except ModbusError as e:
            self.d.counters["exception_responses"] += 1
            return bytes([(fc | 0x80) & 0xFF, e.code])
        except Exception:
            self.d.counters["exception_responses"] += 1
            return bytes([(fc | 0x80) & 0xFF, 4])

    # FC 01 / 02
    def fc_bits(self, pdu, coils):
        if len(pdu) != 5:
            raise ModbusError(3)
        start, qty = struct.unpack(">HH", pdu[1:5])
        if qty < 1 or qty > 4:
            raise ModbusError(3)
        base = 0x004B if coils else 0x002D
        if start < base or start + qty > base + 4:
            raise ModbusError(2)
        val = 0
        for i in range(qty):
            n = start - base + i + 1
            bit = self.d.coil_state(n) if coils else self.d.point_state(n)
            val |= bit << i
        return bytes([pdu[0], 1, val])

    def _items_for(self, start, qty):
        items = []
        a = start
        end = start + qty
        while a < end:
            if a not in BY_ADDR:
                raise ModbusError(2)
            it = BY_ADDR[a]
            if a + it[2] > end:
                raise ModbusError(2)
            items.append(it)
            a += it[2]
        return items

    def fc03(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(3)
        start, qty = struct.unpack(">HH", pdu[1:5])
        if qty < 1 or qty > 4:
            raise ModbusError(3)
        items = self._items_for(start, qty)
        for it in items:
            if it[3] == "wo":
                raise ModbusError(2)
        out = b""
        for it in items:
            v = self.d.read_item(it)
            if it[2] == 2:
                out += struct.pack(">I", v & 0xFFFFFFFF)
            else:
                out += struct.pack(">H", v & 0xFFFF)
        return bytes([0x03, len(out)]) + out

    def fc05(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(3)
        addr, value = struct.unpack(">HH", pdu[1:5])
        if value not in (0x0000, 0xFF00):
            raise ModbusError(3)
        if not 0x004B <= addr <= 0x004E:
            raise ModbusError(2)
        n = addr - 0x004B + 1
        if not self.d.is_gp_output(n):
            raise ModbusError(4)
        self.d.outputs[n] = 1 if value == 0xFF00 else 0
        return bytes(pdu)

    def fc16(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(3)
        start, qty, bc = struct.unpack(">HHB", pdu[1:6])
        if qty < 1 or qty > 4 or bc != 2 * qty or len(pdu) != 6 + bc:
            raise ModbusError(3)
        items = self._items_for(start, qty)
        data = pdu[6:]
        vals = []
        off = 0
        for it in items:
            if it[2] == 2:
                raw = struct.unpack(">I", data[off:off + 4])[0]
                v = to_s32(raw) if it[4] else raw
            else:
                raw = struct.unpack(">H", data[off:off + 2])[0]
                v = raw
            off += 2 * it[2]
            vals.append(v)
        # validate everything first (ro -> 02 before values)
        for it in items:
            if it[3] == "ro":
                raise ModbusError(2)
        for it, v in zip(items, vals):
            self.d.check_write(it, v)
        # cross-item constraints inside one request (VI/VM, HT/MT)
        names = {it[1]: v for it, v in zip(items, vals)}
        if "VI" in names or "VM" in names:
            vi = names.get("VI", self.d.params["VI"])
            vm = names.get("VM", self.d.params["VM"])
            if not 1 <= vi < vm <= 5000000:
                raise ModbusError(3)
        if "HT" in names or "MT" in names:
            ht = names.get("HT", self.d.params["HT"])
            mt = names.get("MT", self.d.params["MT"])
            if ht + mt > 65535:
                raise ModbusError(3)
        for it, v in zip(items, vals):
            self.d.apply_write(it, v)
        return pdu[0:5]

    def fc43(self, pdu):
        if len(pdu) < 2:
            raise ModbusError(3)
        if pdu[1] != 0x0E:
            raise ModbusError(1)
        if len(pdu) != 4:
            raise ModbusError(3)
        code, obj = pdu[2], pdu[3]
        if code < 1 or code > 4:
            raise ModbusError(3)
        if code == 4:
            if obj > 6:
                raise ModbusError(2)
            objs = [obj]
        else:
            last = 2 if code == 1 else 6
            if obj > last:
                obj = 0
            objs = list(range(obj, last + 1))
        body = b""
        for o in objs:
            s = DEVICE_ID[o]
            body += bytes([o, len(s)]) + s
        return bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(objs)]) + body

    def fc65(self, pdu):
        if len(pdu) < 5:
            raise ModbusError(3)
        m = mnemonic_of(pdu[1:5])
        if m == "EX":
            # FC, mnemonic, byte count, label
            if len(pdu) < 6 or pdu[5] < 1 or pdu[5] > 4 or len(pdu) != 6 + pdu[5]:
                raise ModbusError(3)
            label = pdu[6:]
            if not all(0x30 <= c <= 0x39 or 0x41 <= c <= 0x5A or 0x61 <= c <= 0x7A for c in label):
                raise ModbusError(3)
            # no MCode program is stored in this drive -> label/address does not exist
            raise ModbusError(3)
        if len(pdu) != 5:
            raise ModbusError(3)
        if m not in READ_MFG:
            raise ModbusError(2)
        d = self.d
        if m in ("E", "PS", "RS"):
            if m == "E":
                d.program["running"] = False
                d.program["paused"] = False
            elif m == "PS" and d.program["running"]:
                d.program["paused"] = True
            elif m == "RS" and d.program["running"]:
                d.program["paused"] = False
            return bytes([0x41, 0])
        if m in ("S1", "S2", "S3", "S4"):
            vals = d.io[int(m[1])]
        elif m == "CR":
            txt = ("%.3f" % d.mfg["CR"]).encode()
            return bytes([0x41, len(txt)]) + txt
        else:
            vals = d.mfg[m]
        txt = ", ".join(str(v) for v in vals).encode()
        return bytes([0x41, len(txt)]) + txt

    def fc66(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(3)
        bc = pdu[5]
        if bc < 1 or bc > 28 or len(pdu) != 6 + bc:
            raise ModbusError(3)
        m = mnemonic_of(pdu[1:5])
        if m not in WRITE_MFG:
            raise ModbusError(2)
        parts = parse_fields(pdu[6:])
        d = self.d
        if m in ("S1", "S2", "S3", "S4"):
            if len(parts) != 3:
                raise ModbusError(3)
            a, b, c = (parse_int(p) for p in parts)
            if a not in INPUT_FUNCS and a not in OUTPUT_FUNCS:
                raise ModbusError(3)
            if b not in (0, 1) or c not in (0, 1):
                raise ModbusError(3)
            n = int(m[1])
            was_gp = d.io[n][0] == 16
            d.io[n] = [a, b, c]
            if a != 16 or not was_gp:
                d.outputs[n] = 0
        elif m in ("S7", "S8"):
            if len(parts) != 2:
                raise ModbusError(3)
            a, b = (parse_int(p) for p in parts)
            if a not in (33, 34, 35, 49, 50, 51) or b not in (0, 1):
                raise ModbusError(3)
            d.mfg[m] = [a, b]
        elif m == "S5":
            if len(parts) != 2:
                raise ModbusError(3)
            a, b = (parse_int(p) for p in parts)
            if a not in (9, 10) or b not in (0, 1):
                raise ModbusError(3)
            d.mfg[m] = [a, b]
        elif m == "S13":
            if len(parts) != 2:
                raise ModbusError(3)
            a, b = (parse_int(p) for p in parts)
            if a not in (60, 61) or b not in (0, 1):
                raise ModbusError(3)
            d.mfg[m] = [a, b]
        elif m == "CR":
            if len(parts) != 1:
                raise ModbusError(3)
            p = parts[0]
            ip, _, fp = p.partition(".")
            if not ip.isdigit() or (fp and not fp.isdigit()) or len(fp) > 3 or (p.endswith(".")):
                raise ModbusError(3)
            v = float(p)
            if not 0.001 <= v <= 2000.0:
                raise ModbusError(3)
            d.mfg["CR"] = round(v, 3)
        elif m == "TR":
            if not 1 <= len(parts) <= 3:
                raise ModbusError(3)
            vals = [parse_int(p) for p in parts]
            if not -2147483648 <= vals[0] <= 2147483647:
                raise ModbusError(3)
            for v in vals[1:]:
                if not 0 <= v <= 65535:
                    raise ModbusError(3)
            while len(vals) < 3:
                vals.append(0)
            d.mfg["TR"] = vals
        return bytes([0x42, bc]) + pdu[1:5]


# ------------------------------------------------------------------------
# TCP server
# ------------------------------------------------------------------------
class Server:
    def __init__(self, host, port, state_file):
        self.drive = Drive()
        self.proc = Processor(self.drive)
        self.service_lock = threading.Lock()     # one request at a time, all connections
        self.state_file = state_file
        self.stop = threading.Event()
        self.slots = 0
        self.slot_lock = threading.Lock()
        self.conns = set()
        self.lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.lsock.bind((host, port))
        self.lsock.listen(16)
        self.host = host
        self.port = self.lsock.getsockname()[1]

    # -- connections --
    def accept_loop(self):
        while not self.stop.is_set():
            try:
                c, _ = self.lsock.accept()
            except OSError:
                if self.stop.is_set():
                    return
                time.sleep(0.05)
                continue
            with self.slot_lock:
                full = self.slots >= MAX_CONNECTIONS
                if not full:
                    self.slots += 1
                    self.conns.add(c)
            with self.drive.lock:
                self.drive.counters["connections_refused" if full else "connections_accepted"] += 1
            if full:
                try:
                    c.close()
                except OSError:
                    pass
                continue
            threading.Thread(target=self.conn_loop, args=(c,), daemon=True).start()

    def conn_loop(self, c):
        buf = b""
        try:
            c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            c.settimeout(IDLE_TIMEOUT)
            while not self.stop.is_set():
                try:
                    data = c.recv(4096)
                except socket.timeout:
                    with self.drive.lock:
                        self.drive.counters["connections_closed_idle"] += 1
                    return
                if not data:
                    return
                buf += data
                while len(buf) >= 7:
                    tid, pid, length = struct.unpack(">HHH", buf[:6])
                    if length < 2 or length > 254:
                        with self.drive.lock:
                            self.drive.counters["connections_closed_framing"] += 1
                        return
                    if len(buf) < 6 + length:
                        break
                    frame = buf[:6 + length]
                    buf = buf[6 + length:]
                    unit = frame[6]
                    pdu = frame[7:]
                    if pid != 0:
                        with self.drive.lock:
                            self.drive.counters["dropped_frames"] += 1
                        continue
                    with self.service_lock:
                        time.sleep(SERVICE_TIME)
                        with self.drive.lock:
                            self.drive.counters["requests"] += 1
                            resp = self.proc.handle(pdu)
                            self.drive.counters["responses"] += 1
                    adu = struct.pack(">HHHB", tid, 0, len(resp) + 1, unit) + resp
                    c.sendall(adu)
        except OSError:
            pass
        finally:
            with self.slot_lock:
                self.slots -= 1
                self.conns.discard(c)
            try:
                c.close()
            except OSError:
                pass

    # -- motion --
    def motion_loop(self):
        last = time.monotonic()
        while not self.stop.is_set():
            time.sleep(TICK)
            now = time.monotonic()
            dt = min(now - last, 0.1)
            last = now
            with self.drive.lock:
                self.drive.tick(dt)

    # -- the machine's HMI: a real client on our own port --
    def hmi_loop(self):
        polls = [
            (0x03, 0x0057, 2), (0x03, 0x0085, 2), (0x03, 0x004A, 1), (0x03, 0x0045, 1),
            (0x03, 0x001F, 1), (0x03, 0x007B, 1), (0x02, 0x002D, 4), (0x01, 0x004B, 4),
            (0x03, 0x0031, 1), (0x03, 0x0088, 1),
        ]
        tid = 0
        while not self.stop.is_set():
            s = None
            try:
                s = socket.create_connection(("127.0.0.1", self.port), timeout=2.0)
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                s.settimeout(1.0)
                i = 0
                nxt = time.monotonic()
                while not self.stop.is_set():
                    fc, addr, qty = polls[i % len(polls)]
                    i += 1
                    tid = (tid + 1) & 0xFFFF
                    pdu = struct.pack(">BHH", fc, addr, qty)
                    s.sendall(struct.pack(">HHHB", tid, 0, len(pdu) + 1, HMI_UNIT) + pdu)
                    resp = b""
                    need = 7
                    while len(resp) < need:
                        chunk = s.recv(260)
                        if not chunk:
                            raise ConnectionError("closed")
                        resp += chunk
                        if len(resp) >= 6:
                            need = 6 + struct.unpack(">H", resp[4:6])[0]
                    nxt += HMI_PERIOD
                    delay = nxt - time.monotonic()
                    if delay > 0:
                        self.stop.wait(delay)
                    else:
                        nxt = time.monotonic()
            except (OSError, ConnectionError, struct.error):
                pass
            finally:
                if s is not None:
                    try:
                        s.close()
                    except OSError:
                        pass
            self.stop.wait(1.0)

    # -- state --
    def write_state(self):
        if not self.state_file:
            return
        with self.drive.lock:
            data = self.drive.dump()
        tmp = self.state_file + ".tmp"
        try:
            with open(tmp, "w") as f:
                json.dump(data, f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except OSError as e:
            sys.stderr.write("state dump failed: %s\n" % e)


def main():
    ap = argparse.ArgumentParser(description="MDrive Plus2 Ethernet MODBUS/TCP simulator")
    ap.add_argument("--listen", required=True, help="127.0.0.1:PORT")
    ap.add_argument("--state", default=None)
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(":")
    srv = Server(host, int(port), args.state)

    flags = {"dump": False, "exit": False}

    def on_usr1(signum, frame):
        flags["dump"] = True

    def on_term(signum, frame):
        flags["exit"] = True

    signal.signal(signal.SIGUSR1, on_usr1)
    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)

    threading.Thread(target=srv.accept_loop, daemon=True).start()
    threading.Thread(target=srv.motion_loop, daemon=True).start()
    print("listening tcp %s:%d" % (host, srv.port), flush=True)
    threading.Thread(target=srv.hmi_loop, daemon=True).start()

    while not flags["exit"]:
        time.sleep(0.05)
        if flags["dump"]:
            flags["dump"] = False
            srv.write_state()
    srv.stop.set()
    srv.write_state()
    try:
        srv.lsock.close()
    except OSError:
        pass
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
