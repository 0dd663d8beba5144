#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet - Modbus/TCP drive simulator.

Built on uModbus 1.0.4 (MPL 2.0): its socketserver based TCP request handler,
MBAP (un)packing, the PDU classes of FC 01/02/03/05/16, its route map and its
exception classes.  On top of it: the LMD register map (section 5 of the
LMD Modbus/TCP manual), the vendor function codes 65/66 (0x41/0x42), Read
Device Identification (43/14) and a small motion / program model.

See DECISIONS.md for every place where the manual or the library was not
followed literally.
"""
import argparse
import json
import os
import re
import signal
import socketserver
import struct
import sys
import threading
import time

from umodbus import log
from umodbus.server.tcp import RequestHandler, get_server
from umodbus.functions import (ModbusFunction, ReadCoils, ReadDiscreteInputs,
                               ReadHoldingRegisters, WriteSingleCoil,
                               WriteMultipleRegisters)
from umodbus.exceptions import (ModbusError, IllegalFunctionError,
                                IllegalDataAddressError, IllegalDataValueError,
                                ServerDeviceFailureError)
from umodbus.utils import pack_mbap, unpack_mbap, recv_exactly

INT32_MIN, INT32_MAX = -2147483648, 2147483647

# --------------------------------------------------------------------------
# Register map (manual section 5, 5.1, 5.2)
#   addr: (mcode, words, access, signed, lo, hi, default)
#   access: 'rw', 'ro' (status), 'wo' (command)
#   lo/hi = None -> full range of the data type; 'set' given via MS_VALUES
# --------------------------------------------------------------------------
MS_VALUES = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250,
             256, 180, 108, 127)

REGS = {
    0x0000: ('A', 2, 'rw', False, 91, 1525878997, 1000000),
    0x0004: ('BY', 1, 'ro', False, 0, 1, 0),
    0x0005: ('C1', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x0007: ('C2', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x0009: ('CE', 1, 'rw', False, 0, 1, 1),
    0x000E: ('CW', 1, 'rw', False, 0, 255, 10),
    0x000F: ('D1', 1, 'rw', False, 0, 255, 0),
    0x0010: ('D2', 1, 'rw', False, 0, 255, 0),
    0x0011: ('D3', 1, 'rw', False, 0, 255, 0),
    0x0012: ('D4', 1, 'rw', False, 0, 255, 0),
    0x0013: ('D5', 1, 'rw', False, 0, 255, 0),
    0x0018: ('D', 2, 'rw', False, 91, 1525878997, 1000000),
    0x001A: ('DB', 1, 'rw', False, 0, 65000, 10),
    0x001B: ('DC', 1, 'wo', False, 1, 4, None),
    0x001C: ('DE', 1, 'rw', False, 0, 1, 1),
    0x001E: ('EE', 1, 'rw', False, 0, 1, 0),
    0x001F: ('EF', 1, 'ro', False, 0, 1, 0),
    0x0021: ('ER', 1, 'rw', False, 0, 0, 0),      # only 0 (clear) writable
    0x0024: ('FC', 1, 'rw', False, 0, 9, 0),
    0x0029: ('HC', 1, 'rw', False, 0, 100, 5),
    0x002A: ('HI', 1, 'wo', False, 1, 4, None),
    0x002B: ('HM', 1, 'wo', False, 1, 4, None),
    0x002C: ('HT', 1, 'rw', False, 0, 65535, 500),
    0x002D: ('I1', 1, 'ro', False, 0, 1, 0),
    0x002E: ('I2', 1, 'ro', False, 0, 1, 0),
    0x002F: ('I3', 1, 'ro', False, 0, 1, 0),
    0x0030: ('I4', 1, 'ro', False, 0, 1, 0),
    0x0031: ('I5', 1, 'ro', False, 0, 1023, 0),
    0x0032: ('I6', 1, 'ro', False, 0, 1, 0),
    0x0037: ('IC', 1, 'wo', False, 1, 4, None),
    0x003B: ('IN', 1, 'ro', False, 0, 15, 0),
    0x003C: ('IP', 1, 'wo', False, 0, 65535, None),
    0x003F: ('JE', 1, 'rw', False, 0, 1, 0),
    0x0042: ('LM', 1, 'rw', False, 1, 6, 1),
    0x0043: ('MA', 2, 'wo', True, INT32_MIN, INT32_MAX, None),
    0x0045: ('MP', 1, 'ro', False, 0, 1, 0),
    0x0046: ('MR', 2, 'wo', True, INT32_MIN, INT32_MAX, None),
    0x0048: ('MS', 1, 'rw', False, 1, 256, 256),
    0x0049: ('MT', 1, 'rw', False, 0, 65000, 0),
    0x004A: ('MV', 1, 'ro', False, 0, 1, 0),
    0x004B: ('O1', 1, 'rw', False, 0, 1, 0),
    0x004C: ('O2', 1, 'rw', False, 0, 1, 0),
    0x004D: ('O3', 1, 'rw', False, 0, 1, 0),
    0x004E: ('OF', 1, 'ro', False, 0, 1, 0),
    0x0056: ('OT', 1, 'rw', False, 0, 15, 0),
    0x0057: ('P', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x0059: ('PC', 2, 'ro', True, INT32_MIN, INT32_MAX, 0),
    0x005C: ('PM', 1, 'rw', False, 0, 1, 0),
    0x005F: ('R1', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x0061: ('R2', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x0063: ('R3', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x0065: ('R4', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x0067: ('RC', 1, 'rw', False, 1, 100, 25),
    0x0076: ('S', 1, 'wo', False, 0, 65535, None),
    0x0077: ('SF', 1, 'rw', False, 0, 65000, 15),
    0x0078: ('SL', 2, 'wo', True, -5000000, 5000000, None),
    0x007A: ('SM', 1, 'rw', False, 0, 1, 0),
    0x007B: ('ST', 1, 'rw', False, 0, 0, 0),      # only 0 (clear) writable
    0x007D: ('TE', 1, 'rw', False, 0, 43, 0),
    0x0085: ('V', 2, 'ro', True, INT32_MIN, INT32_MAX, 0),
    0x0088: ('VC', 1, 'ro', False, 0, 1, 0),
    0x0089: ('VI', 2, 'rw', False, 1, 2559999, 1000),
    0x008B: ('VM', 2, 'rw', False, 2, 2560000, 768000),
    0x008D: ('WT', 1, 'rw', False, 0, 84, 80),
    # 5.1 hMTechnology (closed loop)
    0x008E: ('AS', 1, 'rw', False, 0, 3, 2),
    0x008F: ('AF', 1, 'ro', False, 0, 255, 0),
    0x0091: ('CB', 1, 'rw', False, 0, 3, 1),
    0x0093: ('CF', 1, 'wo', False, 0, 65535, None),
    0x0095: ('LD', 2, 'rw', False, 0, INT32_MAX, 102400),
    0x0097: ('LG', 2, 'rw', False, 0, INT32_MAX, 102400),
    0x0099: ('LL', 2, 'ro', True, -INT32_MAX, INT32_MAX, 0),
    0x009B: ('LR', 1, 'ro', False, 0, 1, 0),
    0x009C: ('LT', 2, 'rw', False, 2, 65535, 2000),
    0x009E: ('MF', 2, 'rw', False, 306, 2560000, 768000),
    0x00A0: ('MU', 1, 'rw', False, 0, 2, 0),
    0x00A1: ('SC', 1, 'wo', False, 0, 65535, None),
    0x00A3: ('TS', 2, 'rw', False, 0, 255, 0),
    0x00A5: ('TD', 1, 'rw', False, 0, 1, 1),
    0x00A6: ('TQ', 1, 'rw', False, 1, 100, 25),
    0x00A7: ('VF', 1, 'rw', False, 0, 1000, 0),
    # 5.2 user variables
    0x00A8: ('V1', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x00AA: ('V2', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x00AC: ('V3', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x00AE: ('V4', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x00B0: ('V5', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x00B2: ('V6', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x00B4: ('V7', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
    0x00B6: ('V8', 2, 'rw', True, INT32_MIN, INT32_MAX, 0),
}
BY_NAME = {v[0]: a for a, v in REGS.items()}
# word address -> (variable start address, word index 0=low word, 1=high)
WORD_MAP = {}
for _a, _v in REGS.items():
    for _i in range(_v[1]):
        WORD_MAP[_a + _i] = (_a, _i)

# Settings that are restored by IP and stored by S (parameters, not status,
# not position/counters/user data).
PARAMS = [v[0] for v in REGS.values()
          if v[2] == 'rw' and v[0] not in
          ('C1', 'C2', 'P', 'ER', 'ST', 'O1', 'O2', 'O3', 'OT',
           'R1', 'R2', 'R3', 'R4', 'V1', 'V2', 'V3', 'V4', 'V5', 'V6', 'V7',
           'V8')]

# Input functions (4.4.6), output functions (4.4.9)
IN_TYPES = {0, 1, 2, 3, 5, 7, 8, 11, 12}
OUT_TYPES = {16, 17, 18, 20, 21, 23, 24, 25, 28, 29}
UPGRADE_CODE = '2956102'

DEVICE_ID = {
    0: b'IMS USA',
    1: b'LMDCE572',
    2: b'4.0.0.0',
    3: b'https://novantaims.com/',
    4: b'LMD Ethernet',
    5: b'LMD190412001',
    6: b'LMDCM 6.012, Hw: 1.0',
}

MAX_MOVE_TIME = 5.0          # s, cap of a simulated point-to-point move
HOMING_TIME = 0.6            # s
PROGRAM_TIME = 1.0           # s a started program stays busy


def _to_words(value, words):
    """Value -> list of 16 bit words, low word first (manual 4.2.4/4.2.5)."""
    if words == 1:
        return [value & 0xFFFF]
    v = value & 0xFFFFFFFF
    return [v & 0xFFFF, (v >> 16) & 0xFFFF]


def _from_words(ws, signed):
    if len(ws) == 1:
        v = ws[0]
        return v - 0x10000 if signed and v & 0x8000 else v
    v = ws[0] | (ws[1] << 16)
    if signed and v & 0x80000000:
        v -= 0x100000000
    return v


class Device:
    """LMD state: parameters, I/O, motion and program model."""

    def __init__(self):
        self.lock = threading.RLock()
        self.vals = {}
        for a, (n, w, acc, s, lo, hi, d) in REGS.items():
            if d is not None:
                self.vals[n] = d
        self.latch = [0, 0, 0, 0]          # output latches (coils 0..3)
        self.inputs = [0, 0, 0, 0]          # electrical input level (no wiring)
        self.analog = 0
        # I/O point configuration: point -> [dir, type, active, sink]
        self.io = {p: ['in', 0, 0, 0] for p in (1, 2, 3, 4)}
        self.analog_cfg = [9, 0]            # S5 / IS line 5: mode, range
        self.mfg = {'AO': 0, 'EL': 1000, 'MU_B': 0, 'RD': 0, 'AJ': 128,
                    'AT': 0, 'BE': 0, 'BL': 0, 'BM': 0, 'DJ': 128, 'DT': 0,
                    'FS': 0, 'FL': 0, 'LS': [0, 0, 0], 'TR': [0, 0, 0]}
        self.program_present = True
        self.prog_state = 'idle'            # idle / running / paused
        self.prog_end = 0.0
        self.prog_left = 0.0
        self.upgrade_armed = False
        self.capture = 0
        # motion
        self.mot = None                     # dict describing current motion
        self.frozen = False                 # consistent snapshot of a block
        self.nvm = self._param_snapshot()
        self.counters = {'requests': 0, 'exceptions': 0,
                         'bad_frames_dropped': 0, 'connections': 0}

    # ---------------- helpers -------------------------------------------
    def _param_snapshot(self):
        snap = {n: self.vals[n] for n in PARAMS}
        snap['_mfg'] = json.loads(json.dumps(self.mfg))
        snap['_io'] = json.loads(json.dumps(self.io))
        snap['_analog'] = list(self.analog_cfg)
        return snap

    def _restore_params(self, snap):
        for n in PARAMS:
            self.vals[n] = snap[n]
        self.mfg = json.loads(json.dumps(snap['_mfg']))
        self.io = {int(k): v for k, v in
                   json.loads(json.dumps(snap['_io'])).items()}
        self.analog_cfg = list(snap['_analog'])

    # ---------------- motion model --------------------------------------
    def update(self):
        """Advance simulated motion/program to 'now'."""
        if self.frozen:
            return
        now = time.monotonic()
        if self.prog_state == 'running' and now >= self.prog_end:
            self.prog_state = 'idle'
        m = self.mot
        if m is None:
            return
        if m['kind'] == 'slew':
            steps = int(m['vel'] * (now - m['t0']))
            if steps:
                self._set_pos(self.vals['P'] + steps)
                m['t0'] += steps / m['vel']
            return
        frac = (now - m['t0']) / m['dur'] if m['dur'] > 0 else 1.0
        if frac >= 1.0:
            self._set_pos(m['target'])
            if m['kind'] == 'home':
                self.vals['P'] = 0
            self.mot = None
        else:
            self._set_pos(m['p0'] + int((m['target'] - m['p0']) * frac))

    def _set_pos(self, pos):
        pos = max(INT32_MIN, min(INT32_MAX, pos))
        d = pos - self.vals['P']
        self.vals['P'] = pos
        for c in ('C1', 'C2'):
            v = self.vals[c] + d
            v = (v + 2 ** 31) % 2 ** 32 - 2 ** 31
            self.vals[c] = v

    def moving(self):
        return self.mot is not None

    def velocity(self):
        m = self.mot
        if m is None:
            return 0
        if m['kind'] == 'slew':
            return int(m['vel'])
        sign = 1 if m['target'] >= m['p0'] else -1
        return sign * int(m['speed'])

    def _need_enabled(self):
        if not self.vals['DE']:
            raise ServerDeviceFailureError()

    def start_move(self, target):
        self._need_enabled()
        self.update()
        target = max(INT32_MIN, min(INT32_MAX, target))
        dist = abs(target - self.vals['P'])
        vm = self.vals['VM']
        a = self.vals['A']
        dur = dist / vm + vm / a if dist else 0.0
        dur = min(MAX_MOVE_TIME, max(0.05 if dist else 0.0, dur))
        speed = min(vm, int(dist / dur)) if dur else 0
        self.mot = {'kind': 'move', 't0': time.monotonic(),
                    'p0': self.vals['P'], 'target': target, 'dur': dur,
                    'speed': speed}

    def start_slew(self, vel):
        self.update()
        if vel == 0:
            self.mot = None
            return
        self._need_enabled()
        self.mot = {'kind': 'slew', 't0': time.monotonic(),
                    'p0': self.vals['P'], 'vel': vel}

    def start_home(self):
        self._need_enabled()
        self.update()
        self.mot = {'kind': 'home', 't0': time.monotonic(),
                    'p0': self.vals['P'], 'target': self.vals['P'],
                    'dur': HOMING_TIME, 'speed': self.vals['VI']}

    def stop_all(self):
        self.update()
        self.mot = None
        self.prog_state = 'idle'

    # ---------------- derived status ------------------------------------
    def input_level(self, point):
        """Logic state of I/O point 1..4 (I1..I4, FC 02)."""
        cfg = self.io[point]
        if cfg[0] == 'out':
            return self.latch[point - 1]
        return self.inputs[point - 1]

    def af(self):
        if self.vals['AS'] == 0:
            return 64 if not self.moving() else 0
        v = 16 | 128
        if not self.moving():
            v |= 64
        return v

    def status(self, name):
        self.update()
        if name == 'BY':
            return 1 if self.prog_state in ('running', 'paused') else 0
        if name in ('I1', 'I2', 'I3', 'I4'):
            return self.input_level(int(name[1]))
        if name == 'I5':
            return self.analog
        if name == 'I6':
            return 0
        if name == 'IN':
            return sum(self.input_level(p) << (p - 1) for p in (1, 2, 3, 4))
        if name == 'MV':
            return 1 if self.moving() else 0
        if name == 'MP':
            return 1 if (self.mot and self.mot['kind'] == 'move') else 0
        if name == 'V':
            return self.velocity()
        if name == 'VC':
            return 0
        if name == 'AF':
            return self.af()
        if name in ('O1', 'O2', 'O3'):
            return self.latch[int(name[1]) - 1]
        if name == 'OT':
            return sum(b << i for i, b in enumerate(self.latch))
        if name == 'PC':
            return self.capture
        if name in ('EF', 'OF', 'LR'):
            return 0
        if name == 'LL':
            return 0
        return self.vals[name]

    # ---------------- register access -----------------------------------
    def check_read(self, start, qty):
        """Validate an FC 03 request (addresses and 32 bit alignment)."""
        for addr in range(start, start + qty):
            if addr not in WORD_MAP:
                raise IllegalDataAddressError()
            base, _ = WORD_MAP[addr]
            if REGS[base][2] == 'wo':
                raise IllegalDataAddressError()
        self._check_whole(start, qty)

    def _check_whole(self, start, qty):
        end = start + qty
        for addr in range(start, end):
            base, _ = WORD_MAP[addr]
            w = REGS[base][1]
            if base < start or base + w > end:
                raise IllegalDataAddressError()   # split 32-bit variable

    def read_word(self, addr):
        base, idx = WORD_MAP[addr]
        n, w, acc, signed = REGS[base][:4]
        if acc == 'rw' and n not in ('O1', 'O2', 'O3', 'OT', 'P', 'C1', 'C2'):
            v = self.vals[n]
        else:
            v = self.status(n)
        return _to_words(v, w)[idx]

    def write_block(self, start, words):
        qty = len(words)
        for addr in range(start, start + qty):
            if addr not in WORD_MAP:
                raise IllegalDataAddressError()
            base, _ = WORD_MAP[addr]
            if REGS[base][2] == 'ro':
                raise IllegalDataAddressError()
        self._check_whole(start, qty)
        # decode and range check everything before touching state
        todo = []
        a = start
        while a < start + qty:
            n, w, acc, signed, lo, hi, _d = REGS[a]
            v = _from_words(words[a - start:a - start + w], signed)
            if n == 'MS':
                if v not in MS_VALUES:
                    raise IllegalDataValueError()
            elif not lo <= v <= hi:
                raise IllegalDataValueError()
            todo.append((n, v))
            a += w
        # cross checks against the values after this request
        new = dict(self.vals)
        new.update({n: v for n, v in todo if REGS[BY_NAME[n]][2] == 'rw'})
        if new['HT'] == 1:
            raise IllegalDataValueError()           # 0 or 2..65535
        if new['HT'] + new['MT'] > 65535:
            raise IllegalDataValueError()
        if not new['VI'] < new['VM']:
            raise IllegalDataValueError()
        for n, v in todo:
            if n in ('MA', 'MR', 'SL', 'HI', 'HM') and not self.vals['DE'] \
                    and not (n == 'SL' and v == 0):
                raise ServerDeviceFailureError()
        for n, v in todo:
            self._apply(n, v)

    def _apply(self, n, v):
        if n in ('O1', 'O2', 'O3'):
            self.latch[int(n[1]) - 1] = v
        elif n == 'OT':
            self.latch = [(v >> i) & 1 for i in range(4)]
        elif n == 'P':
            self.update()
            if self.mot is not None and self.mot['kind'] != 'slew':
                off = v - self.vals['P']
                self.mot['p0'] += off
                self.mot['target'] += off
            self.vals['P'] = v
        elif n == 'MA':
            self.start_move(v)
        elif n == 'MR':
            self.update()
            self.start_move(self.vals['P'] + v)
        elif n == 'SL':
            self.start_slew(v)
        elif n in ('HI', 'HM'):
            self.start_home()
        elif n in ('DC', 'IC'):
            r = 'R%d' % v
            nv = self.vals[r] + (1 if n == 'IC' else -1)
            self.vals[r] = (nv + 2 ** 31) % 2 ** 32 - 2 ** 31
        elif n == 'IP':
            self.stop_all()
            self._restore_params(self.nvm)
        elif n == 'S':
            self.nvm = self._param_snapshot()
        elif n in ('CF', 'SC'):
            pass                                     # no locked rotor to clear
        elif n == 'ER':
            self.vals['ER'] = 0
        elif n == 'ST':
            self.vals['ST'] = 0
        elif n == 'DE':
            self.vals['DE'] = v
            if not v:
                self.update()
                self.mot = None
        elif n == 'MU':
            self.vals['MU'] = v
        else:
            self.vals[n] = v

    # ---------------- manufacturer specific (65/66) ---------------------
    def mfg_read(self, mn):
        self.update()
        m = self.mfg
        if mn == 'AO':
            return str(m['AO'])
        if mn == 'EL':
            return str(m['EL'])
        if mn == 'IS':
            parts = ['%d, %d, %d' % (p, self.io[p][1], self.io[p][2])
                     for p in (1, 2, 3, 4) if self.io[p][0] == 'in']
            parts.append('5, %d, %d' % tuple(self.analog_cfg))
            return '; '.join(parts)
        if mn == 'OS':
            parts = ['%d, %d, %d' % (p, self.io[p][1], self.io[p][2])
                     for p in (1, 2, 3) if self.io[p][0] == 'out']
            return '; '.join(parts)
        if mn in ('S1', 'S2', 'S3', 'S4'):
            c = self.io[int(mn[1])]
            return '%d, %d, %d' % (c[1], c[2], c[3])
        if mn == 'S5':
            return '%d, %d' % tuple(self.analog_cfg)
        if mn == 'IT':
            return '38,41'
        if mn == 'VT':
            return '24,48'
        if mn == 'MU':
            return '%d, %d' % (self.vals['MU'], m['MU_B'])
        if mn in ('RD', 'AJ', 'AT', 'BE', 'BL', 'BM', 'DJ', 'DT', 'FS', 'FL'):
            return str(m[mn])
        if mn == 'AV':
            return str(self.velocity())
        if mn in ('LS', 'TR'):
            return '%d, %d, %d' % tuple(m[mn])
        raise IllegalDataAddressError()

    def mfg_write(self, mn, text):
        m = self.mfg
        nozero = ('\x1b', 'CP', 'PS', 'RS', 'E')
        if mn in nozero:
            if text.strip() not in ('', '='):
                raise IllegalDataValueError()
            if mn == '\x1b':
                self.stop_all()
            elif mn == 'CP':
                self.update()
                self.prog_state = 'idle'
                self.program_present = False
            elif mn == 'PS':
                self.update()
                if self.prog_state == 'running':
                    self.prog_left = max(0.0, self.prog_end - time.monotonic())
                    self.prog_state = 'paused'
            elif mn == 'RS':
                self.update()
                if self.prog_state == 'paused':
                    self.prog_end = time.monotonic() + self.prog_left
                    self.prog_state = 'running'
            elif mn == 'E':
                self.update()
                self.prog_state = 'idle'
            return
        body = text.strip()
        if body.startswith('='):
            body = body[1:].strip()
        if body == '':
            raise IllegalDataValueError()

        def ints(n_expected):
            parts = [p.strip() for p in body.split(',')]
            if len(parts) != n_expected:
                raise IllegalDataValueError()
            out = []
            for p in parts:
                if not re.fullmatch(r'[+-]?\d{1,11}', p):
                    raise IllegalDataValueError()
                out.append(int(p))
            return out

        def rng(v, lo, hi):
            if not lo <= v <= hi:
                raise IllegalDataValueError()
            return v

        if mn == 'EX':
            if not re.fullmatch(r'[A-Za-z0-9]{1,3}', body):
                raise IllegalDataValueError()
            if not self.program_present:
                raise ServerDeviceFailureError()
            self.update()
            self.prog_state = 'running'
            self.prog_end = time.monotonic() + PROGRAM_TIME
            return
        if mn == 'UG':
            if body != UPGRADE_CODE:
                raise IllegalDataValueError()
            self.upgrade_armed = True
            return
        if mn == 'HF':
            (v,) = ints(1)
            rng(v, 1, 4)
            self.start_home()
            return
        if mn == 'AO':
            (v,) = ints(1)
            m['AO'] = rng(v, 0, 65535)
        elif mn == 'EL':
            (v,) = ints(1)
            m['EL'] = rng(v, 1, 65535)
        elif mn == 'IS':
            line, a, b = ints(3)
            if line == 5:
                rng(a, 9, 10)
                rng(b, 0, 1)
                self.analog_cfg = [a, b]
            else:
                rng(line, 1, 4)
                if a not in IN_TYPES:
                    raise IllegalDataValueError()
                rng(b, 0, 1)
                if a == 12 and line != 1:
                    raise IllegalDataValueError()
                c = self.io[line]
                self.io[line] = ['in', a, b, c[3]]
        elif mn == 'OS':
            line, a, b = ints(3)
            rng(line, 1, 3)
            if a not in OUT_TYPES:
                raise IllegalDataValueError()
            if a == 28 and line != 3:
                raise IllegalDataValueError()
            rng(b, 0, 1)
            c = self.io[line]
            self.io[line] = ['out', a, b, c[3]]
        elif mn in ('S1', 'S2', 'S3', 'S4'):
            p = int(mn[1])
            parts = body.split(',')
            vals = ints(len(parts)) if len(parts) in (2, 3) else ints(3)
            t, act = vals[0], vals[1]
            sink = vals[2] if len(vals) == 3 else self.io[p][3]
            rng(act, 0, 1)
            rng(sink, 0, 1)
            if t in IN_TYPES:
                if t == 12 and p != 1:
                    raise IllegalDataValueError()
                self.io[p] = ['in', t, act, sink]
            elif t in OUT_TYPES and p != 4:
                if t == 28 and p != 3:
                    raise IllegalDataValueError()
                self.io[p] = ['out', t, act, sink]
            else:
                raise IllegalDataValueError()
        elif mn == 'S5':
            a, b = ints(2)
            self.analog_cfg = [rng(a, 9, 10), rng(b, 0, 1)]
        elif mn == 'MU':
            a, b = ints(2)
            self.vals['MU'] = rng(a, 0, 2)
            m['MU_B'] = rng(b, 0, 1)
        elif mn in ('RD', 'AT', 'BE', 'BM', 'DT', 'FL'):
            (v,) = ints(1)
            m[mn] = rng(v, 0, 1)
        elif mn in ('AJ', 'DJ'):
            (v,) = ints(1)
            m[mn] = rng(v, 1, 999)
        elif mn == 'BL':
            (v,) = ints(1)
            m['BL'] = rng(v, 0, INT32_MAX)
        elif mn == 'FS':
            (v,) = ints(1)
            m['FS'] = rng(v, -65535, 65535)
        elif mn == 'LS':
            d, pos, en = ints(3)
            m['LS'] = [rng(d, 0, 1), rng(pos, INT32_MIN, INT32_MAX),
                       rng(en, 0, 1)]
        elif mn == 'TR':
            a, b, c = ints(3)
            m['TR'] = [rng(a, INT32_MIN, INT32_MAX),
                       rng(b, INT32_MIN, INT32_MAX), rng(c, 0, 1)]
        else:
            raise IllegalDataAddressError()

    # ---------------- state dump ----------------------------------------
    def dump(self):
        with self.lock:
            self.update()
            self.frozen = True
            try:
                return self._dump()
            finally:
                self.frozen = False

    def _dump(self):
        if True:
            regs = {}
            for a in sorted(REGS):
                n, w, acc = REGS[a][:3]
                if acc == 'wo':
                    continue
                v = self.read_value(n)
                regs['0x%04X' % a] = {'mcode': n, 'words': w, 'value': v,
                                      'access': acc}
            return {
                'device': 'Lexium MDrive LMD Ethernet (Modbus/TCP)',
                'holding_registers': regs,
                'coils': {str(i): self.latch[i] for i in range(4)},
                'discrete_inputs': {str(i): self.input_level(i + 1)
                                    for i in range(4)},
                'manufacturer_specific': {
                    'AO': self.mfg['AO'], 'EL': self.mfg['EL'],
                    'IS_S1_S4': {str(p): {'direction': c[0], 'type': c[1],
                                          'active': c[2], 'sink': c[3]}
                                 for p, c in self.io.items()},
                    'IS5_analog': {'mode': self.analog_cfg[0],
                                   'range': self.analog_cfg[1]},
                    'MU': [self.vals['MU'], self.mfg['MU_B']],
                    'RD': self.mfg['RD'], 'AJ': self.mfg['AJ'],
                    'AT': self.mfg['AT'], 'BE': self.mfg['BE'],
                    'BL': self.mfg['BL'], 'BM': self.mfg['BM'],
                    'DJ': self.mfg['DJ'], 'DT': self.mfg['DT'],
                    'FS': self.mfg['FS'], 'FL': self.mfg['FL'],
                    'LS': list(self.mfg['LS']), 'TR': list(self.mfg['TR']),
                    'IT': self.mfg_read('IT'), 'VT': self.mfg_read('VT'),
                    'AV': self.velocity(),
                },
                'program': {'present': self.program_present,
                            'state': self.prog_state,
                            'upgrade_mode_requested': self.upgrade_armed},
                'nvm_saved': self.nvm,
                'diagnostic_counters': dict(self.counters),
            }

    def read_value(self, n):
        w = REGS[BY_NAME[n]][1]
        signed = REGS[BY_NAME[n]][3]
        words = [self.read_word(BY_NAME[n] + i) for i in range(w)]
        return _from_words(words, signed)


DEV = Device()


# --------------------------------------------------------------------------
# Function classes: library PDU parsing, LMD specific execution
# --------------------------------------------------------------------------
class LmdReadCoils(ReadCoils):
    # library: qty 1..2000 -> 03, unrouted address -> 02 (kept)
    pass


class LmdReadDiscreteInputs(ReadDiscreteInputs):
    pass


class LmdWriteSingleCoil(WriteSingleCoil):
    @classmethod
    def create_from_request_pdu(cls, pdu):
        # library accepts 0x0001 as ON; the manual (4.2.3) says only
        # 0x0000/0xFF00 are legal -> 03 for anything else.
        _, address, value = struct.unpack('>BHH', pdu)
        if value not in (0x0000, 0xFF00):
            raise IllegalDataValueError()
        return super().create_from_request_pdu(pdu)


class LmdReadHoldingRegisters(ReadHoldingRegisters):
    @classmethod
    def create_from_request_pdu(cls, pdu):
        inst = super().create_from_request_pdu(pdu)   # 1..125 check -> 03
        if inst.quantity > 2:                          # manual 4.2.4: 1 to 2
            raise IllegalDataValueError()
        return inst

    def execute(self, slave_id, route_map):
        with DEV.lock:
            if self.starting_address + self.quantity > 0x10000:
                raise IllegalDataAddressError()
            DEV.check_read(self.starting_address, self.quantity)
            DEV.update()
            DEV.frozen = True
            try:
                return super().execute(slave_id, route_map)
            finally:
                DEV.frozen = False


class LmdWriteMultipleRegisters(WriteMultipleRegisters):
    @classmethod
    def create_from_request_pdu(cls, pdu):
        if len(pdu) < 6:
            raise IllegalDataValueError()
        _, start, qty, bc = struct.unpack('>BHHB', pdu[:6])
        if not 1 <= qty <= 0x7B or bc != qty * 2 or len(pdu) != 6 + bc:
            raise IllegalDataValueError()
        if qty > 2:                                    # manual 4.2.5
            raise IllegalDataValueError()
        return super().create_from_request_pdu(pdu)

    def execute(self, slave_id, route_map):
        with DEV.lock:
            if self.starting_address + len(self.values) > 0x10000:
                raise IllegalDataAddressError()
            DEV.write_block(self.starting_address, list(self.values))


class DeviceIdentification(ModbusFunction):
    function_code = 0x2B

    @classmethod
    def create_from_request_pdu(cls, pdu):
        if len(pdu) < 2:
            raise IllegalDataValueError()
        inst = cls()
        inst.mei = pdu[1]
        if inst.mei != 0x0E:
            raise IllegalFunctionError()
        if len(pdu) != 4:
            raise IllegalDataValueError()
        inst.code, inst.obj = pdu[2], pdu[3]
        if inst.code not in (1, 2, 3, 4):
            raise IllegalDataValueError()
        return inst

    def execute(self, slave_id, route_map):
        if self.code == 4:
            if self.obj not in DEVICE_ID:
                raise IllegalDataAddressError()
            return [self.obj]
        last = 2 if self.code == 1 else 6
        first = self.obj if self.obj <= last else 0
        return list(range(first, last + 1))

    def create_response_pdu(self, ids):
        out = bytes([0x2B, 0x0E, self.code, 0x82, 0x00, 0x00, len(ids)])
        for i in ids:
            v = DEVICE_ID[i]
            out += bytes([i, len(v)]) + v
        return out


def _mnemonic(b4):
    """4 request bytes, ASCII sent in reverse order (4.4.2)."""
    s = bytes(reversed(b4)).replace(b'\x00', b' ').decode('latin-1')
    return s.strip(' ')


READ_MN = {'AO', 'EL', 'IS', 'IT', 'MU', 'OS', 'RD', 'AJ', 'AT', 'BE', 'BL',
           'BM', 'DJ', 'DT', 'FS', 'AV', 'FL', 'LS', 'VT', 'S1', 'S2', 'S3',
           'S4', 'S5', 'TR'}
WRITE_MN = {'\x1b', 'AO', 'CP', 'EL', 'EX', 'IS', 'MU', 'OS', 'PS', 'RS',
            'RD', 'AJ', 'AT', 'BE', 'BL', 'BM', 'DJ', 'DT', 'FS', 'HF', 'FL',
            'LS', 'UG', 'E', 'S1', 'S2', 'S3', 'S4', 'S5', 'TR'}


class ReadMfgSpecific(ModbusFunction):
    function_code = 0x41

    @classmethod
    def create_from_request_pdu(cls, pdu):
        if len(pdu) != 5:
            raise IllegalDataValueError()
        inst = cls()
        inst.raw = bytes(pdu[1:5])
        inst.mn = _mnemonic(inst.raw)
        return inst

    def execute(self, slave_id, route_map):
        if self.mn not in READ_MN:
            raise IllegalDataAddressError()
        with DEV.lock:
            return DEV.mfg_read(self.mn).encode('ascii')

    def create_response_pdu(self, text):
        return bytes([0x41, len(text)]) + text


class WriteMfgSpecific(ModbusFunction):
    function_code = 0x42

    @classmethod
    def create_from_request_pdu(cls, pdu):
        if len(pdu) < 6:
            raise IllegalDataValueError()
        bc = pdu[5]
        if bc > 28 or len(pdu) != 6 + bc:
            raise IllegalDataValueError()
        inst = cls()
        inst.raw = bytes(pdu[1:5])
        inst.mn = _mnemonic(inst.raw)
        data = bytes(pdu[6:])
        if any(c < 0x20 or c > 0x7E for c in data):
            raise IllegalDataValueError()
        inst.text = data.decode('ascii')
        return inst

    def execute(self, slave_id, route_map):
        if self.mn not in WRITE_MN:
            raise IllegalDataAddressError()
        with DEV.lock:
            DEV.mfg_write(self.mn, self.text)

    def create_response_pdu(self):
        return bytes([0x42, 0x04]) + self.raw


FUNCTIONS = {
    0x01: LmdReadCoils,
    0x02: LmdReadDiscreteInputs,
    0x03: LmdReadHoldingRegisters,
    0x05: LmdWriteSingleCoil,
    0x10: LmdWriteMultipleRegisters,
    0x2B: DeviceIdentification,
    0x41: ReadMfgSpecific,
    0x42: WriteMfgSpecific,
}
READ_FUNCTIONS = (ReadCoils, ReadDiscreteInputs, ReadHoldingRegisters,
                  DeviceIdentification, ReadMfgSpecific)


# --------------------------------------------------------------------------
# Routes (library route map) for bit and register access
# --------------------------------------------------------------------------
def install_routes(server):
    @server.route(function_codes=[1], addresses=list(range(4)))
    def read_coil(slave_id, function_code, address):
        with DEV.lock:
            return DEV.latch[address]

    @server.route(function_codes=[5], addresses=list(range(4)))
    def write_coil(slave_id, function_code, address, value):
        with DEV.lock:
            DEV.latch[address] = 1 if value else 0

    @server.route(function_codes=[2], addresses=list(range(4)))
    def read_input(slave_id, function_code, address):
        with DEV.lock:
            return DEV.input_level(address + 1)

    @server.route(function_codes=[3], addresses=sorted(WORD_MAP))
    def read_register(slave_id, function_code, address):
        return DEV.read_word(address)            # caller holds DEV.lock


# --------------------------------------------------------------------------
# Request handler
# --------------------------------------------------------------------------
class LmdRequestHandler(RequestHandler):
    def setup(self):
        self.request.settimeout(None)
        with DEV.lock:
            DEV.counters['connections'] += 1

    def handle(self):
        recv = self.request.recv
        try:
            while True:
                try:
                    mbap = recv_exactly(recv, 7)
                except ValueError:
                    return
                tid, pid, length, uid = unpack_mbap(mbap)
                if length == 1:
                    # header only, no PDU: nothing to answer, stream in sync
                    with DEV.lock:
                        DEV.counters['bad_frames_dropped'] += 1
                    continue
                if length < 1 or length > 254:
                    # Not a Modbus/TCP stream we can stay in sync with.
                    with DEV.lock:
                        DEV.counters['bad_frames_dropped'] += 1
                    return
                try:
                    pdu = recv_exactly(recv, length - 1)
                except ValueError:
                    return
                if pid != 0:
                    with DEV.lock:
                        DEV.counters['bad_frames_dropped'] += 1
                    continue
                meta = {'transaction_id': tid, 'protocol_id': pid,
                        'length': length, 'unit_id': uid}
                resp = self.execute_route(meta, pdu)
                self.respond(self.create_response_adu(meta, resp))
        except (OSError, ConnectionError):
            return

    def execute_route(self, meta_data, request_pdu):
        fc = request_pdu[0]
        with DEV.lock:
            DEV.counters['requests'] += 1
        try:
            cls = FUNCTIONS.get(fc)
            if cls is None:
                raise IllegalFunctionError()
            try:
                function = cls.create_from_request_pdu(request_pdu)
            except (struct.error, ValueError, IndexError):
                raise IllegalDataValueError()
            results = function.execute(meta_data['unit_id'],
                                       self.server.route_map)
            if isinstance(function, READ_FUNCTIONS):
                return function.create_response_pdu(results)
            return function.create_response_pdu()
        except ModbusError as e:
            code = e.error_code
        except Exception:
            log.exception('Could not handle request')
            code = ServerDeviceFailureError.error_code
        with DEV.lock:
            DEV.counters['exceptions'] += 1
        return bytes([(fc | 0x80) & 0xFF, code])

    def respond(self, response_adu):
        self.request.sendall(response_adu)


class Server(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = 16


# --------------------------------------------------------------------------
def write_state(path):
    if not path:
        return
    data = DEV.dump()
    tmp = path + '.tmp'
    with open(tmp, 'w') as f:
        json.dump(data, f, indent=1, sort_keys=True)
    os.replace(tmp, path)


def main():
    ap = argparse.ArgumentParser(description='LMD Ethernet Modbus/TCP sim')
    ap.add_argument('--listen', required=True, help='127.0.0.1:PORT')
    ap.add_argument('--state', default=None)
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(':')
    if host not in ('127.0.0.1', 'localhost'):
        sys.exit('only 127.0.0.1 is allowed')
    server = get_server(Server, ('127.0.0.1', int(port)), LmdRequestHandler)
    install_routes(server)

    stop = threading.Event()
    dump_req = threading.Event()

    def on_term(signum, frame):
        stop.set()

    def on_usr1(signum, frame):
        dump_req.set()

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    signal.signal(signal.SIGUSR1, on_usr1)

    t = threading.Thread(target=server.serve_forever,
                         kwargs={'poll_interval': 0.2}, daemon=True)
    t.start()
    print('listening tcp 127.0.0.1:%d' % server.server_address[1], flush=True)

    while not stop.is_set():
        stop.wait(0.1)
        if dump_req.is_set():
            dump_req.clear()
            try:
                write_state(args.state)
            except Exception as e:
                print('state dump failed: %s' % e, file=sys.stderr)
    try:
        write_state(args.state)
    finally:
        try:
            server.server_close()
        except Exception:
            pass
        sys.stdout.flush()
        os._exit(0)


if __name__ == '__main__':
    main()
