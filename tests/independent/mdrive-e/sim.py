#!/usr/bin/env python3
"""MDrive 23 Hybrid Motion Control (Ethernet) -- MODBUS/TCP drive simulator.

Built on pymodbus 3.16.1: its asyncio TCP server/transport, MBAP framer,
PDU classes (encode/decode/responses), SimDevice/SimData datastore with an
action callback, and ExceptionResponse.  On top of that: the MDrive register
map and its checks, the manufacturer function codes 0x41/0x42, and a simple
motion model.  See DECISIONS.md for every place where we deviate from the
library or interpret the manual.

Usage: python3 sim.py --listen 127.0.0.1:0 [--state FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import re
import signal
import struct
import sys
import time
import traceback
from collections import deque

from pymodbus.constants import ExcCodes
from pymodbus.framer.socket import FramerSocket
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadDiscreteInputsRequest,
    WriteSingleCoilRequest,
)
from pymodbus.pdu.mei_message import ReadDeviceInformationResponse
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    WriteMultipleRegistersRequest,
)
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.simulator.simutils import SimUtils

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

PRODUCT = "MDrive 23 Hybrid Motion Control, Ethernet (MODBUS/TCP)"

# --------------------------------------------------------------------------
# Register map (manual section 5, lines 1022-1165).  Hybrid variant:
# MDrivePlus-only registers (footnote 1) are not present -> reserved.
# (address, words, mnemonic, access, check, default)
#   access: rw / ro / wo
#   check: (lo, hi) inclusive range, a set, or None (special / no check)
# --------------------------------------------------------------------------
I32 = (-(2**31), 2**31 - 1)
MS_VALUES = {1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250,
             256, 180, 108, 127}
REGMAP = [
    (0x0000, 2, "A", "rw", (91, 1525878997), 1000000),
    (0x0005, 2, "C1", "rw", I32, 0),
    (0x0007, 2, "C2", "rw", I32, 0),
    (0x0009, 1, "CE", "rw", (0, 1), 1),
    (0x000F, 1, "D1", "rw", (0, 255), 0),
    (0x0010, 1, "D2", "rw", (0, 255), 0),
    (0x0011, 1, "D3", "rw", (0, 255), 0),
    (0x0012, 1, "D4", "rw", (0, 255), 0),
    (0x0013, 1, "D5", "rw", (0, 255), 0),
    (0x0018, 2, "D", "rw", (91, 1525878997), 1000000),
    (0x001B, 1, "DC", "wo", None, 0),
    (0x001C, 1, "DE", "rw", (0, 1), 1),
    (0x001E, 1, "EE", "rw", (0, 1), 0),
    (0x001F, 1, "EF", "ro", None, 0),
    (0x0021, 1, "ER", "rw", (0, 0), 0),
    (0x0029, 1, "HC", "rw", (0, 100), 5),
    (0x002B, 1, "HM", "rw", (1, 4), 1),
    (0x002C, 1, "HT", "rw", None, 500),
    (0x002D, 1, "I1", "ro", None, 0),
    (0x002E, 1, "I2", "ro", None, 0),
    (0x002F, 1, "I3", "ro", None, 0),
    (0x0030, 1, "I4", "ro", None, 0),
    (0x0031, 1, "I5", "ro", None, 0),
    (0x0037, 1, "IC", "wo", None, 0),
    (0x003A, 1, "IL", "ro", None, 0),
    (0x003B, 1, "IN", "ro", None, 0),
    (0x003F, 1, "JE", "rw", (0, 1), 0),
    (0x0042, 1, "LM", "rw", (1, 6), 1),
    (0x0043, 2, "MA", "wo", I32, 0),
    (0x0045, 1, "MP", "ro", None, 0),
    (0x0046, 2, "MR", "wo", I32, 0),
    (0x0048, 1, "MS", "rw", MS_VALUES, 256),
    (0x0049, 1, "MT", "rw", (0, 65000), 0),
    (0x004A, 1, "MV", "ro", None, 0),
    (0x004B, 1, "O1", "rw", (0, 1), 0),
    (0x004C, 1, "O2", "rw", (0, 1), 0),
    (0x004D, 1, "O3", "rw", (0, 1), 0),
    (0x004E, 1, "O4", "rw", (0, 1), 0),
    (0x0055, 1, "OL", "rw", (0, 15), 0),
    (0x0056, 1, "OT", "rw", (0, 15), 0),
    (0x0057, 2, "P", "rw", I32, 0),
    (0x0059, 2, "PC", "ro", None, 0),
    (0x005F, 2, "R1", "rw", I32, 0),
    (0x0061, 2, "R2", "rw", I32, 0),
    (0x0063, 2, "R3", "rw", I32, 0),
    (0x0065, 2, "R4", "rw", I32, 0),
    (0x0067, 1, "RC", "rw", (1, 100), 25),
    (0x0076, 1, "S", "wo", None, 0),
    (0x0078, 2, "SL", "wo", (-5000000, 5000000), 0),
    (0x007D, 1, "TE", "rw", {0, 16}, 0),
    (0x0085, 2, "V", "ro", None, 0),
    (0x0088, 1, "VC", "ro", None, 0),
    (0x0089, 2, "VI", "rw", None, 1000),
    (0x008B, 2, "VM", "rw", None, 768000),
    # 5.1 Hybrid specific registers
    (0x008E, 1, "AS", "rw", (0, 3), 2),
    (0x008F, 1, "AF", "ro", None, 0),
    (0x0090, 1, "CA", "rw", (0, 1), 1),
    (0x0091, 1, "CB", "rw", (0, 3), 1),
    (0x0092, 1, "CC", "rw", (1, 100), 100),
    (0x0093, 1, "CF", "wo", None, 0),
    (0x0094, 1, "CT", "rw", (2, 65535), 200),
    (0x0095, 2, "LD", "rw", (0, 2147483647), 102400),
    (0x0097, 2, "LG", "rw", (0, 2147483647), 102400),
    (0x0099, 2, "LL", "ro", None, 0),
    (0x009B, 1, "LR", "ro", None, 0),
    (0x009C, 2, "LT", "rw", (2, 65535), 2000),
    (0x009E, 2, "MF", "rw", (306, 5000000), 768000),
    (0x00A0, 1, "MU", "rw", (0, 2), 0),
    (0x00A1, 1, "SC", "wo", None, 0),
    (0x00A2, 1, "SS", "rw", (0, 255), 0),
    (0x00A5, 1, "TD", "rw", (0, 1), 1),
    (0x00A6, 1, "TQ", "rw", (1, 100), 25),
    (0x00A7, 1, "TS", "rw", (0, 255), 0),
    # 5.2 User variable registers
    (0x00A8, 2, "V1", "rw", I32, 0),
    (0x00AA, 2, "V2", "rw", I32, 0),
    (0x00AC, 2, "V3", "rw", I32, 0),
    (0x00AE, 2, "V4", "rw", I32, 0),
    (0x00B0, 2, "V5", "rw", I32, 0),
    (0x00B2, 2, "V6", "rw", I32, 0),
    (0x00B4, 2, "V7", "rw", I32, 0),
    (0x00B6, 2, "V8", "rw", I32, 0),
]
BY_ADDR = {r[0]: r for r in REGMAP}
BY_NAME = {r[2]: r for r in REGMAP}
# every word address -> (item start address, word index inside item)
WORD_OWNER = {}
for _r in REGMAP:
    for _i in range(_r[1]):
        WORD_OWNER[_r[0] + _i] = (_r[0], _i)

# Variables that IC / DC (0x0037 / 0x001B) may address: value written is the
# start address of the 32-bit variable.
INCDEC_TARGETS = {BY_NAME[n][0] for n in
                  ("C1", "C2", "P", "R1", "R2", "R3", "R4",
                   "V1", "V2", "V3", "V4", "V5", "V6", "V7", "V8")}

INPUT_ADDRS = range(0x002D, 0x0031)   # discrete inputs I1..I4 (FC 02)
OUTPUT_ADDRS = range(0x004B, 0x004F)  # coils O1..O4 (FC 01 / 05)
MAX_QTY = 4                           # manual 4.2.x: quantity 1 to 4

IO_INPUT_TYPES = {0, 1, 2, 3, 5, 7, 8, 11}
IO_OUTPUT_TYPES = {16, 17, 18, 20, 21, 23, 24, 25}
GP_OUTPUT = 16


def to_s32(v: int) -> int:
    v &= 0xFFFFFFFF
    return v - (1 << 32) if v & 0x80000000 else v


def wrap32(v: int) -> int:
    return to_s32(int(v))


# --------------------------------------------------------------------------
# Drive model
# --------------------------------------------------------------------------
class Drive:
    """The MDrive state and behaviour (independent of Modbus encoding)."""

    def __init__(self) -> None:
        self.p = {r[2]: r[5] for r in REGMAP if r[3] != "wo"}
        self.out_latch = [0, 0, 0, 0]
        # manufacturer-specific settings (section 4.3.1)
        self.io = [[0, 0, 0] for _ in range(4)]   # S1..S4: type, active, sink/src
        self.clk = {"S7": [33, 0], "S8": [33, 0]}
        self.cr = 1000                             # clock ratio in 1/1000
        self.s5 = [9, 0]
        self.s13 = [60, 0]
        self.tr = 0                                # trip relative distance
        self.mu_param = 0                          # MU B parameter (last)
        self.program = {"state": "idle", "label": None}
        # motion
        self.pos = 0.0
        self.vel = 0.0
        self.mode = None          # None / "move" / "slew"
        self.target = 0
        self.slew_v = 0.0
        self.changing = False
        self.cal_until = 0.0
        self.trip_ref = 0
        self.c2_frac = 0.0
        self.counters = {"requests": 0, "responses": 0, "exceptions": 0,
                         "discarded_frames": 0, "connections": 0}

    # ---------------- derived values ----------------
    def moving(self) -> bool:
        return self.mode is not None

    def output_state(self, i: int) -> int:
        t = self.io[i][0]
        if t == GP_OUTPUT:
            return self.out_latch[i]
        if t == 17:
            return int(self.moving())
        if t == 18:
            return int(self.p["EF"])
        if t == 20:
            return int(self.changing)
        if t == 21:
            return int(self.p["LR"])
        if t == 23:
            return int(self.mode == "move")
        if t == 24:
            return int(self.p["AS"] != 0)
        if t == 25:
            return 0
        return 0

    def input_state(self, i: int) -> int:
        # No hardware is connected: an input point reads inactive; a point
        # configured as an output reads back its output level.
        if self.io[i][0] in IO_OUTPUT_TYPES:
            return self.output_state(i)
        return 0

    def refresh(self) -> None:
        """Bring status variables up to date."""
        now = time.monotonic()
        p = self.p
        p["P"] = wrap32(round(self.pos))
        p["V"] = 0 if p["AS"] == 3 else wrap32(round(self.vel))
        p["MV"] = int(self.moving())
        p["MP"] = int(self.mode == "move")
        p["VC"] = int(self.changing)
        for i in range(4):
            p["I%d" % (i + 1)] = self.input_state(i)
        bcd = sum(self.input_state(i) << i for i in range(4))
        p["IL"] = bcd
        p["IN"] = bcd
        outs = sum(self.output_state(i) << i for i in range(4))
        for i in range(4):
            p["O%d" % (i + 1)] = self.output_state(i)
        p["OL"] = outs
        p["OT"] = outs
        af = 0
        if p["LR"]:
            af |= 8
        if p["AS"] != 0:
            af |= 16
        if p["LL"] == 0:
            af |= 64
        if now >= self.cal_until:
            af |= 128
        p["AF"] = af

    def start_calibration(self) -> None:
        self.cal_until = time.monotonic() + self.p["CT"] / 1000.0

    # ---------------- motion ----------------
    def tick(self, dt: float) -> None:
        p = self.p
        if self.mode is None:
            self.changing = False
            return
        vi, vm = float(p["VI"]), float(p["VM"])
        acc, dec = float(p["A"]), float(p["D"])
        old = self.pos
        if self.mode == "move":
            rem = self.target - self.pos
            direction = 1.0 if rem > 0 else -1.0
            speed = max(abs(self.vel), vi)
            stop_dist = max(0.0, (speed * speed - vi * vi) / (2.0 * dec))
            if abs(rem) <= stop_dist + speed * dt:
                nspeed = max(vi, speed - dec * dt)
            else:
                nspeed = min(vm, speed + acc * dt)
            self.changing = nspeed != speed
            step = nspeed * dt
            if abs(rem) <= step or rem == 0:
                self.pos = float(self.target)
                self.vel = 0.0
                self.mode = None
                self.changing = False
            else:
                self.pos += direction * step
                self.vel = direction * nspeed
        else:  # slew
            tv = self.slew_v
            v = self.vel
            if v == 0.0 and tv != 0.0:
                v = vi if tv > 0 else -vi
            if tv == 0.0 or (v != 0 and (tv > 0) != (v > 0)):
                # decelerate towards zero (stop or reversal)
                sp = abs(v) - dec * dt
                if sp <= vi:
                    if tv == 0.0:
                        self.vel = 0.0
                        self.mode = None
                        self.changing = False
                        self._after_motion(old)
                        return
                    v = vi if tv > 0 else -vi
                else:
                    v = sp if v > 0 else -sp
                self.changing = True
            else:
                sp, tsp = abs(v), abs(tv)
                if sp < tsp:
                    sp = min(tsp, sp + acc * dt)
                elif sp > tsp:
                    sp = max(tsp, sp - dec * dt)
                self.changing = sp != abs(self.vel)
                v = sp if tv > 0 else -sp
            self.vel = v
            self.pos += v * dt
        self._after_motion(old)

    def _after_motion(self, old: float) -> None:
        p = self.p
        delta = round(self.pos) - round(old)
        if delta:
            p["C1"] = wrap32(p["C1"] + delta)
            if p["EE"]:
                # internal encoder: 2048 counts per revolution
                self.c2_frac += delta * 2048.0 / (200.0 * p["MS"])
                whole = int(self.c2_frac)
                self.c2_frac -= whole
                p["C2"] = wrap32(p["C2"] + whole)
        # trip on relative position (TE bit 16, distance set by TR)
        if p["TE"] & 16 and self.tr:
            if abs(round(self.pos) - self.trip_ref) >= abs(self.tr):
                p["TE"] &= ~16

    def stop_now(self) -> None:
        self.mode = None
        self.vel = 0.0
        self.changing = False

    # ---------------- commands ----------------
    def can_move(self) -> bool:
        return bool(self.p["DE"]) and not self.p["LR"]

    def cmd_move(self, target: int) -> ExcCodes | None:
        if not self.can_move() or self.mode is not None:
            return ExcCodes.DEVICE_FAILURE
        if target == round(self.pos):
            return None
        self.target = target
        self.vel = 0.0
        self.mode = "move"
        return None

    def cmd_slew(self, v: int) -> ExcCodes | None:
        if self.mode == "move":
            return ExcCodes.DEVICE_FAILURE
        if v != 0 and not self.can_move():
            return ExcCodes.DEVICE_FAILURE
        if self.mode is None and v == 0:
            return None
        self.slew_v = float(v)
        self.mode = "slew"
        return None


DRIVE = Drive()


# --------------------------------------------------------------------------
# Holding-register checks and the pymodbus SimDevice action callback
# --------------------------------------------------------------------------
def _items_in(address: int, count: int):
    """Return ([(item, first_word, nwords)], error) for the word range."""
    out = []
    a = address
    end = address + count
    while a < end:
        own = WORD_OWNER.get(a)
        if own is None:
            return None, ExcCodes.ILLEGAL_ADDRESS
        start, idx = own
        item = BY_ADDR[start]
        n = min(item[1] - idx, end - a)
        out.append((item, idx, n))
        a += n
    return out, None


def _check_value(name: str, check, value: int, new: dict) -> bool:
    if name == "HT":
        if not (value == 0 or 2 <= value <= 65535):
            return False
        return value + new.get("MT", DRIVE.p["MT"]) <= 65535
    if name == "MT":
        if not 0 <= value <= 65000:
            return False
        return new.get("HT", DRIVE.p["HT"]) + value <= 65535
    if name == "VI":
        return 1 <= value < new.get("VM", DRIVE.p["VM"])
    if name == "VM":
        return new.get("VI", DRIVE.p["VI"]) < value <= 5000000
    if name in ("DC", "IC"):
        return value in INCDEC_TARGETS
    if name in ("S", "CF", "SC"):
        return True
    if check is None:
        return True
    if isinstance(check, set):
        return value in check
    return check[0] <= value <= check[1]


def holding_write(address: int, values: list[int]) -> ExcCodes | None:
    """Validate and apply an FC16 write (atomic: all or nothing)."""
    items, err = _items_in(address, len(values))
    if err:
        return err
    decoded = []
    pos = 0
    for item, idx, n in items:
        start, words, name, access, check, _ = item
        if idx != 0 or n != words:
            return ExcCodes.ILLEGAL_ADDRESS      # partial 32-bit write
        if access == "ro":
            return ExcCodes.ILLEGAL_ADDRESS
        raw = values[pos:pos + n]
        pos += n
        val = raw[0] if words == 1 else to_s32((raw[0] << 16) | raw[1])
        decoded.append((name, check, val))
    new = {name: val for name, _c, val in decoded}
    for name, check, val in decoded:
        if not _check_value(name, check, val, new):
            return ExcCodes.ILLEGAL_VALUE
    # state-dependent checks before anything is applied
    for name, _c, val in decoded:
        if name in ("O1", "O2", "O3", "O4"):
            i = int(name[1]) - 1
            if DRIVE.io[i][0] != GP_OUTPUT:
                return ExcCodes.DEVICE_FAILURE
        if name in ("OL", "OT"):
            for i in range(4):
                if (val >> i) & 1 and DRIVE.io[i][0] != GP_OUTPUT:
                    return ExcCodes.DEVICE_FAILURE
        if name in ("MA", "MR") and (not DRIVE.can_move() or DRIVE.moving()):
            return ExcCodes.DEVICE_FAILURE
        if name == "SL" and (DRIVE.mode == "move" or (val and not DRIVE.can_move())):
            return ExcCodes.DEVICE_FAILURE
    for name, _c, val in decoded:
        apply_item(name, val)
    return None


def apply_item(name: str, val: int) -> None:
    d = DRIVE
    p = d.p
    if name == "MA":
        d.cmd_move(val)
    elif name == "MR":
        d.cmd_move(round(d.pos) + val)
    elif name == "SL":
        d.cmd_slew(val)
    elif name in ("IC", "DC"):
        tname = BY_ADDR[val][2]
        if tname == "P":
            d.pos += 1 if name == "IC" else -1
            p["P"] = wrap32(round(d.pos))
        else:
            p[tname] = wrap32(p[tname] + (1 if name == "IC" else -1))
    elif name == "S":
        pass  # working memory saved to NVM; nothing observable over Modbus
    elif name == "CF":
        p["LR"] = 0
        d.start_calibration()
    elif name == "SC":
        d.start_calibration()
    elif name == "P":
        shift = val - round(d.pos)
        d.pos = float(val)
        if d.mode == "move":
            d.target += shift
        d.trip_ref += shift
        p["P"] = val
    elif name in ("O1", "O2", "O3", "O4"):
        d.out_latch[int(name[1]) - 1] = val
    elif name in ("OL", "OT"):
        for i in range(4):
            if d.io[i][0] == GP_OUTPUT:
                d.out_latch[i] = (val >> i) & 1
    elif name == "ER":
        p["ER"] = 0
        p["EF"] = 0
    elif name == "DE":
        if val == 0 and d.moving():
            d.stop_now()
        if val == 1 and p["DE"] == 0:
            d.start_calibration()   # bridge re-enabled -> calibration
        p["DE"] = val
    elif name == "MS":
        if val != p["MS"]:
            d.start_calibration()
        p["MS"] = val
    elif name == "AS":
        if val != 0 and p["AS"] == 0:
            d.start_calibration()
        p["AS"] = val
    elif name == "TE":
        p["TE"] = val
        d.trip_ref = round(d.pos)
    elif name == "MU":
        p["MU"] = val
    else:
        p[name] = val


def holding_read(address: int, count: int) -> list[int] | ExcCodes:
    items, err = _items_in(address, count)
    if err:
        return err
    DRIVE.refresh()
    words = []
    for item, idx, n in items:
        start, nw, name, access, _c, _d = item
        if access == "wo":
            return ExcCodes.ILLEGAL_ADDRESS
        v = DRIVE.p[name]
        full = [v & 0xFFFF] if nw == 1 else [(v >> 16) & 0xFFFF, v & 0xFFFF]
        words.extend(full[idx:idx + n])
    if any(BY_ADDR[it[0][0]][2] == "ER" for it in items):
        # ER: "must be read or set to 0 to clear" (reading clears it)
        DRIVE.p["ER"] = 0
        DRIVE.p["EF"] = 0
    return words


async def drive_action(func_code, start_address, address, count, registers, values):
    """pymodbus SimDevice action: the library has already checked that the
    addresses exist (not reserved) and that writes do not target read-only
    registers; we add the MDrive semantics and keep its image in sync."""
    if func_code in (1, 2, 5):
        bits = SimUtils.registersToBits(registers)
        writing = func_code == 5 and values is not None
        if writing:
            i = address - OUTPUT_ADDRS.start
            if DRIVE.io[i][0] != GP_OUTPUT:
                return ExcCodes.DEVICE_FAILURE
            DRIVE.out_latch[i] = int(bool(values[0]))
        DRIVE.refresh()
        base = start_address * 16
        rng = OUTPUT_ADDRS if func_code in (1, 5) else INPUT_ADDRS
        for a in rng:
            i = a - rng.start
            st = DRIVE.output_state(i) if func_code in (1, 5) else DRIVE.input_state(i)
            bits[a - base] = bool(st)
        registers[0:] = SimUtils.bitsToRegisters(bits)
        if writing:
            values[0] = bits[address - base]
        return None
    if func_code == 3:
        res = holding_read(address, count)
        if isinstance(res, ExcCodes):
            return res
        registers[address - start_address:address - start_address + count] = res
        return None
    if func_code == 16:
        res = holding_write(address, list(values))
        if res:
            return res
        # the library copies `values` into its image afterwards; keep the
        # image equal to the drive state for readable items
        DRIVE.refresh()
        for k in range(len(values)):
            start, idx = WORD_OWNER[address + k]
            it = BY_ADDR[start]
            if it[3] != "wo":
                v = DRIVE.p[it[2]]
                full = [v & 0xFFFF] if it[1] == 1 else [(v >> 16) & 0xFFFF, v & 0xFFFF]
                values[k] = full[idx]
        return None
    return ExcCodes.ILLEGAL_FUNCTION


def build_simdevice() -> SimDevice:
    hr = []
    for start, words, name, access, _c, _d in REGMAP:
        hr.append(SimData(start, values=0,
                          datatype=DataType.UINT16 if words == 1 else DataType.INT32,
                          readonly=(access == "ro")))
    coils = [SimData(OUTPUT_ADDRS.start, count=len(OUTPUT_ADDRS), values=False,
                     datatype=DataType.BITS)]
    dis = [SimData(INPUT_ADDRS.start, count=len(INPUT_ADDRS), values=False,
                   datatype=DataType.BITS)]
    ir = [SimData(0, values=0, datatype=DataType.UINT16)]  # FC04 not supported
    return SimDevice(id=0, simdata=(coils, dis, hr, ir), action=drive_action)


# --------------------------------------------------------------------------
# PDU classes (standard function codes with the MDrive's checks)
# --------------------------------------------------------------------------
class _SafeDecode:
    """Never raise from decode(): remember a malformed PDU instead, so the
    drive answers exception 03 rather than pymodbus' generic error."""

    malformed = False

    def _fixed(self, data: bytes, n: int) -> bool:
        if len(data) != n:
            self.malformed = True
            return False
        return True


class MDReadCoils(_SafeDecode, ReadCoilsRequest):
    RANGE = OUTPUT_ADDRS

    def decode(self, data: bytes) -> None:
        if self._fixed(data, 4):
            self.address, self.count = struct.unpack(">HH", data)

    async def datastore_update(self, context, device_id):
        if self.malformed or not 1 <= self.count <= MAX_QTY:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        if self.address not in self.RANGE or self.address + self.count - 1 not in self.RANGE:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_ADDRESS)
        return await super().datastore_update(context, device_id)


class MDReadInputs(MDReadCoils):
    function_code = 2
    RANGE = INPUT_ADDRS

    async def datastore_update(self, context, device_id):
        # ReadCoilsRequest.datastore_update selects the response class by
        # function code, so the library path works unchanged for FC 02.
        return await MDReadCoils.datastore_update(self, context, device_id)


class MDWriteCoil(_SafeDecode, WriteSingleCoilRequest):
    raw_value = 0

    def decode(self, data: bytes) -> None:
        if self._fixed(data, 4):
            self.address, self.raw_value = struct.unpack(">HH", data)
            self.bits = [self.raw_value == 0xFF00]

    async def datastore_update(self, context, device_id):
        if self.malformed or self.raw_value not in (0x0000, 0xFF00):
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        if self.address not in OUTPUT_ADDRS:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_ADDRESS)
        return await super().datastore_update(context, device_id)


class MDReadHolding(_SafeDecode, ReadHoldingRegistersRequest):
    def decode(self, data: bytes) -> None:
        if self._fixed(data, 4):
            self.address, self.count = struct.unpack(">HH", data)

    async def datastore_update(self, context, device_id):
        if self.malformed or not 1 <= self.count <= MAX_QTY:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        if self.address + self.count > 0x10000:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_ADDRESS)
        return await super().datastore_update(context, device_id)


class MDWriteMultiple(_SafeDecode, WriteMultipleRegistersRequest):
    def decode(self, data: bytes) -> None:
        if len(data) < 5:
            self.malformed = True
            return
        super().decode(data)

    async def datastore_update(self, context, device_id):
        if self.malformed or not 1 <= self.count <= MAX_QTY:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        if self.byte_count != self.count * 2 or self._payload_byte_count != self.byte_count:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        if self.address + self.count > 0x10000:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_ADDRESS)
        return await super().datastore_update(context, device_id)


# --------------------------------------------------------------------------
# FC 43 / MEI 14 Read Device Identification
# --------------------------------------------------------------------------
DEVICE_ID = {
    0x00: "SEM USA",
    0x01: "MDM1FSD23A4-EQ",
    0x02: "4.0.0.0",
    0x03: "www.imshome.com",
    0x04: "MDrive Ethernet",
    0x05: "SIM0000001",
    0x06: "ASI 4.0.0.0",
}
CONFORMITY = 0x82   # regular identification, stream + individual access


class MDReadDeviceId(_SafeDecode, ModbusPDU):
    function_code = 0x2B
    mei_type = 0
    read_code = 0
    object_id = 0

    def decode(self, data: bytes) -> None:
        if len(data) < 1:
            self.malformed = True
            self.mei_type = 0x0E     # no MEI type at all: malformed (03)
            return
        self.mei_type = data[0]
        if len(data) != 3:
            self.malformed = True
            return
        self.read_code, self.object_id = data[1], data[2]

    async def datastore_update(self, context, device_id):
        _ = context
        if self.mei_type != 0x0E:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_FUNCTION)
        if self.malformed or not 1 <= self.read_code <= 4:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        if self.read_code == 4:
            if self.object_id not in DEVICE_ID:
                return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_ADDRESS)
            ids = [self.object_id]
        else:
            last = 0x02 if self.read_code == 1 else 0x06
            first = self.object_id if self.object_id <= last else 0
            ids = list(range(first, last + 1))
        resp = ReadDeviceInformationResponse(
            read_code=self.read_code,
            information={i: DEVICE_ID[i].encode() for i in ids},
            dev_id=device_id, transaction_id=self.transaction_id)
        resp.conformity = CONFORMITY
        return resp


# --------------------------------------------------------------------------
# FC 65 / 66 manufacturer specific (section 4.3)
# --------------------------------------------------------------------------
def _mnem_bytes(m: str) -> bytes:
    return m.ljust(4).encode()[::-1]


MNEMONICS = {_mnem_bytes(m): m for m in
             ("S1", "S2", "S3", "S4", "S7", "S8", "CR", "S5", "S13", "TR",
              "E", "EX", "PS", "RS", "MU")}
PROGRAM_CMDS = ("E", "EX", "PS", "RS")
MAX_PARAM = 28
PARAM_MAXLEN = {"S1": 7, "S2": 7, "S3": 7, "S4": 7, "S7": 5, "S8": 5,
                "CR": 6, "S5": 5, "S13": 5, "TR": 11, "MU": 4, "EX": 4}
_INT = r"(0|[1-9][0-9]*)"


def mfg_read(m: str) -> str:
    d = DRIVE
    if m in ("S1", "S2", "S3", "S4"):
        return "%d, %d, %d" % tuple(d.io[int(m[1]) - 1])
    if m in ("S7", "S8"):
        return "%d, %d" % tuple(d.clk[m])
    if m == "CR":
        return "%d.%03d" % divmod(d.cr, 1000)
    if m == "S5":
        return "%d, %d" % tuple(d.s5)
    if m == "S13":
        return "%d, %d" % tuple(d.s13)
    if m == "TR":
        return "%d, 0, 0" % d.tr
    if m == "MU":
        return "%d, %d" % (d.p["MU"], d.mu_param)
    return ""


def _ints(s: str, n: int):
    m = re.fullmatch("=" + ",".join([_INT] * n), s)
    return [int(x) for x in m.groups()] if m else None


def mfg_write(m: str, text: str) -> ExcCodes | None:
    d = DRIVE
    if m in PARAM_MAXLEN and len(text) > PARAM_MAXLEN[m]:
        return ExcCodes.ILLEGAL_VALUE
    if m in ("S1", "S2", "S3", "S4"):
        v = _ints(text, 3)
        if not v or v[0] not in IO_INPUT_TYPES | IO_OUTPUT_TYPES or v[1] > 1 or v[2] > 1:
            return ExcCodes.ILLEGAL_VALUE
        i = int(m[1]) - 1
        if v[0] != GP_OUTPUT:
            d.out_latch[i] = 0
        d.io[i] = v
        return None
    if m in ("S7", "S8"):
        v = _ints(text, 2)
        if not v or v[0] not in (33, 34, 35, 49, 50, 51) or v[1] > 1:
            return ExcCodes.ILLEGAL_VALUE
        d.clk[m] = v
        return None
    if m == "CR":
        mm = re.fullmatch(r"=([0-9]+)(?:\.([0-9]{1,3}))?", text)
        if not mm:
            return ExcCodes.ILLEGAL_VALUE
        val = int(mm.group(1)) * 1000 + int((mm.group(2) or "0").ljust(3, "0"))
        if not 1 <= val <= 2000000:
            return ExcCodes.ILLEGAL_VALUE
        d.cr = val
        return None
    if m == "S5":
        v = _ints(text, 2)
        if not v or v[0] not in (9, 10) or v[1] > 1:
            return ExcCodes.ILLEGAL_VALUE
        d.s5 = v
        return None
    if m == "S13":
        v = _ints(text, 2)
        if not v or v[0] not in (60, 61) or v[1] > 1:
            return ExcCodes.ILLEGAL_VALUE
        d.s13 = v
        return None
    if m == "TR":
        mm = re.fullmatch(r"=(-?" + _INT + ")", text)
        if not mm:
            return ExcCodes.ILLEGAL_VALUE
        val = int(mm.group(1))
        if not I32[0] <= val <= I32[1]:
            return ExcCodes.ILLEGAL_VALUE
        d.tr = val
        d.trip_ref = round(d.pos)
        return None
    if m == "MU":
        v = _ints(text, 2)
        if not v or v[0] > 2 or v[1] > 1:
            return ExcCodes.ILLEGAL_VALUE
        d.p["MU"] = v[0]
        d.mu_param = v[1]
        if v[1] == 1:
            d.p["LL"] = 0    # clear lead/lag
        return None
    if m == "EX":
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9]|[0-9]{1,4}", text):
            return ExcCodes.ILLEGAL_VALUE
        d.program = {"state": "running", "label": text}
        return None
    return mfg_command(m)


def mfg_command(m: str) -> ExcCodes | None:
    d = DRIVE
    st = d.program["state"]
    if m == "E":
        d.program = {"state": "idle", "label": None}
    elif m == "PS":
        if st == "running":
            d.program["state"] = "paused"
    elif m == "RS":
        if st == "paused":
            d.program["state"] = "running"
    return None


class MDMfgRead(_SafeDecode, ModbusPDU):
    function_code = 0x41
    mnem = b""
    text = b""

    def decode(self, data: bytes) -> None:
        if self._fixed(data, 4):
            self.mnem = bytes(data)

    def encode(self) -> bytes:
        return bytes([len(self.text)]) + self.text

    async def datastore_update(self, context, device_id):
        if self.malformed:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        m = MNEMONICS.get(self.mnem)
        if m is None:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_ADDRESS)
        if m == "EX":   # needs a label; FC 65 has no parameter field
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        DRIVE.refresh()
        if m in PROGRAM_CMDS:
            mfg_command(m)
            txt = ""
        else:
            txt = mfg_read(m)
        resp = MDMfgRead(dev_id=device_id, transaction_id=self.transaction_id)
        resp.text = txt.encode()
        return resp


class MDMfgWrite(_SafeDecode, ModbusPDU):
    function_code = 0x42
    mnem = b""
    params = b""
    written = 0

    def decode(self, data: bytes) -> None:
        if len(data) < 5 or data[4] != len(data) - 5 or data[4] > MAX_PARAM:
            self.malformed = True
            return
        self.mnem = bytes(data[:4])
        self.params = bytes(data[5:])

    def encode(self) -> bytes:
        return bytes([self.written]) + self.mnem

    async def datastore_update(self, context, device_id):
        if self.malformed:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        m = MNEMONICS.get(self.mnem)
        if m is None:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_ADDRESS)
        try:
            text = self.params.decode("ascii")
        except UnicodeDecodeError:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        if m in ("E", "PS", "RS"):
            if text:
                return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        elif not text:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        if err := mfg_write(m, text):
            return ExceptionResponse(self.function_code, err)
        resp = MDMfgWrite(dev_id=device_id, transaction_id=self.transaction_id)
        resp.written = len(self.params)
        resp.mnem = self.mnem
        return resp


CUSTOM_PDUS = [MDReadCoils, MDReadInputs, MDWriteCoil, MDReadHolding,
               MDWriteMultiple, MDReadDeviceId, MDMfgRead, MDMfgWrite]
SUPPORTED_FC = {c.function_code for c in CUSTOM_PDUS}


# --------------------------------------------------------------------------
# Transport / framing fixes on top of pymodbus
# --------------------------------------------------------------------------
class FramingError(Exception):
    """MBAP length field impossible: the stream cannot be resynchronised."""


class MDFramer(FramerSocket):
    """FramerSocket with MBAP validation (see DECISIONS.md, L1-L3)."""

    MIN_SIZE = 7

    def decode(self, data: bytes) -> tuple[int, int, int, bytes]:
        if len(data) >= 6:
            length = struct.unpack(">H", data[4:6])[0]
            if length < 1 or length > 254:
                raise FramingError(length)
        if len(data) < 7:
            return 0, 0, 0, self.EMPTY
        tid, pid, length, uid = struct.unpack(">HHHB", data[:7])
        total = 6 + length
        if len(data) < total:
            return 0, 0, 0, self.EMPTY
        if pid != 0:
            return total, uid, tid, self.EMPTY   # not Modbus: discard silently
        return total, uid, tid, data[7:total]


class MDConnection(ServerRequestHandler):
    """Per-connection handler: frames are queued and answered in order."""

    def __init__(self, owner, *args):
        super().__init__(owner, *args)
        self.max_buffer_size = 1 << 20   # we consume every complete frame
        self.pending: deque = deque()
        self.worker: asyncio.Task | None = None
        DRIVE.counters["connections"] += 1

    def send(self, data: bytes, addr: tuple | None = None) -> None:
        # ModbusProtocol.send() clears recv_buffer, which loses pipelined
        # requests on a stream socket; write directly instead.
        if self.transport:
            self.transport.write(data)

    def callback_data(self, data: bytes, addr: tuple | None = None) -> int:
        used = 0
        while used < len(data):
            try:
                n, uid, tid, pdu = self.framer.decode(data[used:])
            except FramingError:
                DRIVE.counters["discarded_frames"] += 1
                self.pending.clear()
                self.close()
                return len(data)
            if not n:
                break
            used += n
            if not pdu:
                DRIVE.counters["discarded_frames"] += 1
                continue
            self.pending.append((uid, tid, pdu))
        if self.pending and (self.worker is None or self.worker.done()):
            self.worker = asyncio.ensure_future(self.work())
        return used

    def callback_disconnected(self, exc: Exception | None) -> None:
        super().callback_disconnected(exc)
        self.pending.clear()
        if self.worker and not self.worker.done():
            self.worker.cancel()

    async def work(self) -> None:
        while self.pending:
            uid, tid, pdu_bytes = self.pending.popleft()
            resp = await self.process(uid, tid, pdu_bytes)
            if resp is None or not self.transport:
                continue
            resp.transaction_id = tid
            resp.dev_id = uid
            if isinstance(resp, ExceptionResponse):
                DRIVE.counters["exceptions"] += 1
            DRIVE.counters["responses"] += 1
            self.pdu_send(resp)

    async def process(self, uid: int, tid: int, pdu_bytes: bytes):
        DRIVE.counters["requests"] += 1
        fc = pdu_bytes[0]
        if fc not in SUPPORTED_FC:
            return ExceptionResponse(fc & 0x7F if fc & 0x80 else fc,
                                     ExcCodes.ILLEGAL_FUNCTION)
        pdu = self.framer.decoder.decode(pdu_bytes)
        if pdu is None:
            return ExceptionResponse(fc, ExcCodes.ILLEGAL_VALUE)
        pdu.dev_id, pdu.transaction_id = uid, tid
        try:
            return await pdu.datastore_update(self.server.context, uid)
        except Exception:  # pylint: disable=broad-except
            traceback.print_exc(file=sys.stderr)
            return ExceptionResponse(fc, ExcCodes.DEVICE_FAILURE)


class MDServer(ModbusTcpServer):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.framer = MDFramer
        # only the function codes of manual table 4.1 are known
        table = self.decoder.pdu_table
        for fc in list(table):
            if fc not in SUPPORTED_FC:
                del table[fc]

    def callback_new_connection(self):
        return MDConnection(self, self.trace_packet, self.trace_pdu,
                            self.trace_connect)


# --------------------------------------------------------------------------
# State dump
# --------------------------------------------------------------------------
def state_dict() -> dict:
    d = DRIVE
    d.refresh()
    regs = {}
    items = {}
    for start, words, name, access, _c, _dflt in REGMAP:
        if access == "wo":
            continue
        v = d.p[name]
        items[name] = {"address": "0x%04X" % start, "value": v, "access": access}
        full = [v & 0xFFFF] if words == 1 else [(v >> 16) & 0xFFFF, v & 0xFFFF]
        for k, w in enumerate(full):
            regs["0x%04X" % (start + k)] = w
    return {
        "product": PRODUCT,
        "holding_registers": regs,
        "parameters": items,
        "coils": {"0x%04X" % a: d.output_state(a - OUTPUT_ADDRS.start)
                  for a in OUTPUT_ADDRS},
        "output_latches": {"0x%04X" % a: d.out_latch[a - OUTPUT_ADDRS.start]
                           for a in OUTPUT_ADDRS},
        "discrete_inputs": {"0x%04X" % a: d.input_state(a - INPUT_ADDRS.start)
                            for a in INPUT_ADDRS},
        "manufacturer_specific": {m: mfg_read(m) for m in
                                  ("S1", "S2", "S3", "S4", "S7", "S8", "CR",
                                   "S5", "S13", "TR", "MU")},
        "program": dict(d.program),
        "device_identification": {"0x%02X" % k: v for k, v in DEVICE_ID.items()},
        "diagnostic_counters": dict(d.counters),
    }


def write_state(path: str | None) -> None:
    if not path:
        return
    try:
        tmp = path + ".tmp"
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(state_dict(), fh, indent=1, sort_keys=True)
        os.replace(tmp, path)
    except OSError as exc:
        print("state dump failed: %s" % exc, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------
async def motion_loop() -> None:
    last = time.monotonic()
    while True:
        await asyncio.sleep(0.01)
        now = time.monotonic()
        dt = min(now - last, 0.1)
        last = now
        try:
            DRIVE.tick(dt)
        except Exception:  # pylint: disable=broad-except
            DRIVE.stop_now()


async def main() -> None:
    ap = argparse.ArgumentParser(description=PRODUCT)
    ap.add_argument("--listen", default="127.0.0.1:502")
    ap.add_argument("--state", default=None)
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(":")
    host = host or "127.0.0.1"
    server = MDServer(build_simdevice(), address=(host, int(port)),
                      custom_pdu=CUSTOM_PDUS)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGUSR1, write_state, args.state)
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    await server.serve_forever(background=True)
    sock = server.transport.sockets[0]
    print("listening tcp %s:%d" % sock.getsockname()[:2], flush=True)
    mover = asyncio.ensure_future(motion_loop())
    await stop.wait()
    write_state(args.state)
    mover.cancel()
    try:
        await asyncio.wait_for(server.shutdown(), 2.0)
    except Exception:  # pylint: disable=broad-except
        pass


if __name__ == "__main__":
    asyncio.run(main())
