#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet - Modbus/TCP drive simulator (clean-room, manual LMD-MODBUS-REV-D).

Standard library only.  Usage:  python3 sim.py --listen 127.0.0.1:0 [--state FILE]
See DECISIONS.md for every reading of the manual taken here.
"""
import argparse
import asyncio
import copy
import json
import math
import os
import signal
import struct
import sys
import time

# ---------------------------------------------------------------------------
# Register map (section 5).  Addresses are the protocol addresses printed in hex.
# kind: 'rw' parameter, 'ro' status, 'cmd' action (write triggers, reads 0), 'uv' user variable V1-V8
# ---------------------------------------------------------------------------
I32_MIN, I32_MAX = -2147483648, 2147483647
MS_ALLOWED = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)


class Item:
    def __init__(self, addr, n, mn, kind, lo=None, hi=None, default=0, signed=False, allowed=None):
        self.addr, self.n, self.mn, self.kind = addr, n, mn, kind
        self.lo, self.hi, self.default, self.signed, self.allowed = lo, hi, default, signed, allowed


ITEMS = [
    Item(0x0000, 2, 'A', 'rw', 91, 1525878997, 1000000),
    Item(0x0004, 1, 'BY', 'ro'),
    Item(0x0005, 2, 'C1', 'rw', I32_MIN, I32_MAX, 0, True),
    Item(0x0007, 2, 'C2', 'rw', I32_MIN, I32_MAX, 0, True),
    Item(0x0009, 1, 'CE', 'rw', 0, 1, 1),
    Item(0x000E, 1, 'CW', 'rw', 0, 255, 10),
    Item(0x000F, 1, 'D1', 'rw', 0, 255, 0),
    Item(0x0010, 1, 'D2', 'rw', 0, 255, 0),
    Item(0x0011, 1, 'D3', 'rw', 0, 255, 0),
    Item(0x0012, 1, 'D4', 'rw', 0, 255, 0),
    Item(0x0013, 1, 'D5', 'rw', 0, 255, 0),
    Item(0x0018, 2, 'D', 'rw', 91, 1525878997, 1000000),
    Item(0x001A, 1, 'DB', 'rw', 0, 65000, 10),
    Item(0x001B, 1, 'DC', 'cmd'),
    Item(0x001C, 1, 'DE', 'rw', 0, 1, 1),
    Item(0x001E, 1, 'EE', 'rw', 0, 1, 0),
    Item(0x001F, 1, 'EF', 'ro'),
    Item(0x0021, 1, 'ER', 'rw', 0, 0, 0),
    Item(0x0024, 1, 'FC', 'rw', 0, 9, 0),
    Item(0x0029, 1, 'HC', 'rw', 0, 100, 5),
    Item(0x002A, 1, 'HI', 'cmd', 1, 4),
    Item(0x002B, 1, 'HM', 'rw', 1, 4, 1),
    Item(0x002C, 1, 'HT', 'rw', 0, 65535, 500),
    Item(0x002D, 1, 'I1', 'ro'),
    Item(0x002E, 1, 'I2', 'ro'),
    Item(0x002F, 1, 'I3', 'ro'),
    Item(0x0030, 1, 'I4', 'ro'),
    Item(0x0031, 1, 'I5', 'ro'),
    Item(0x0032, 1, 'I6', 'ro'),
    Item(0x0037, 1, 'IC', 'cmd'),
    Item(0x003B, 1, 'IN', 'ro'),
    Item(0x003C, 1, 'IP', 'cmd'),
    Item(0x003F, 1, 'JE', 'rw', 0, 1, 0),
    Item(0x0042, 1, 'LM', 'rw', 1, 6, 1),
    Item(0x0043, 2, 'MA', 'cmd', I32_MIN, I32_MAX, 0, True),
    Item(0x0045, 1, 'MP', 'ro'),
    Item(0x0046, 2, 'MR', 'cmd', I32_MIN, I32_MAX, 0, True),
    Item(0x0048, 1, 'MS', 'rw', default=256, allowed=MS_ALLOWED),
    Item(0x0049, 1, 'MT', 'rw', 0, 65000, 0),
    Item(0x004A, 1, 'MV', 'ro'),
    Item(0x004B, 1, 'O1', 'out', 0, 1),
    Item(0x004C, 1, 'O2', 'out', 0, 1),
    Item(0x004D, 1, 'O3', 'out', 0, 1),
    Item(0x004E, 1, 'OF', 'ro'),
    Item(0x0056, 1, 'OT', 'out', 0, 15),
    Item(0x0057, 2, 'P', 'rw', I32_MIN, I32_MAX, 0, True),
    Item(0x0059, 2, 'PC', 'ro', signed=True),
    Item(0x005C, 1, 'PM', 'rw', 0, 1, 0),
    Item(0x005F, 2, 'R1', 'rw', I32_MIN, I32_MAX, 0, True),
    Item(0x0061, 2, 'R2', 'rw', I32_MIN, I32_MAX, 0, True),
    Item(0x0063, 2, 'R3', 'rw', I32_MIN, I32_MAX, 0, True),
    Item(0x0065, 2, 'R4', 'rw', I32_MIN, I32_MAX, 0, True),
    Item(0x0067, 1, 'RC', 'rw', 1, 100, 25),
    Item(0x0076, 1, 'S', 'cmd'),
    Item(0x0077, 1, 'SF', 'rw', 0, 65000, 15),
    Item(0x0078, 2, 'SL', 'cmd', -5000000, 5000000, 0, True),
    Item(0x007A, 1, 'SM', 'rw', 0, 1, 0),
    Item(0x007B, 1, 'ST', 'ro'),
    Item(0x007D, 1, 'TE', 'rw', default=0, allowed=(0, 16)),
    Item(0x0085, 2, 'V', 'ro', signed=True),
    Item(0x0088, 1, 'VC', 'ro'),
    Item(0x0089, 2, 'VI', 'rw', 1, 2559999, 1000),
    Item(0x008B, 2, 'VM', 'rw', 2, 2560000, 768000),
    Item(0x008D, 1, 'WT', 'rw', 0, 84, 80),
    Item(0x008E, 1, 'AS', 'rw', 0, 3, 2),
    Item(0x008F, 1, 'AF', 'ro'),
    Item(0x0091, 1, 'CB', 'rw', 0, 3, 1),
    Item(0x0093, 1, 'CF', 'cmd'),
    Item(0x0095, 2, 'LD', 'rw', 0, 2147483647, 102400),
    Item(0x0097, 2, 'LG', 'rw', 0, 2147483647, 102400),
    Item(0x0099, 2, 'LL', 'ro', signed=True),
    Item(0x009B, 1, 'LR', 'ro'),
    Item(0x009C, 1, 'LT', 'rw', 2, 65535, 2000),
    Item(0x009E, 2, 'MF', 'rw', 306, 2560000, 768000),
    Item(0x00A0, 1, 'MU', 'rw', 0, 2, 0),
    Item(0x00A1, 1, 'SC', 'cmd'),
    Item(0x00A3, 1, 'TS', 'rw', 0, 255, 0),
    Item(0x00A5, 1, 'TD', 'rw', 0, 1, 1),
    Item(0x00A6, 1, 'TQ', 'rw', 1, 100, 25),
    Item(0x00A7, 1, 'VF', 'rw', 0, 1000, 0),
] + [Item(0x00A8 + 2 * i, 2, 'V%d' % (i + 1), 'uv', I32_MIN, I32_MAX, 0, True) for i in range(8)]

BY_ADDR = {it.addr: it for it in ITEMS}
BY_MN = {it.mn: it for it in ITEMS}
# which register (address) belongs to which item
REG_OWNER = {}
for _it in ITEMS:
    for _k in range(_it.n):
        REG_OWNER[_it.addr + _k] = _it

# parameters saved by S / restored by IP
PARAM_MN = [it.mn for it in ITEMS if it.kind == 'rw' and it.mn not in ('C1', 'C2', 'P', 'ER')] + ['R1', 'R2', 'R3', 'R4']
PARAM_MN = list(dict.fromkeys(PARAM_MN))

IN_TYPES = (0, 1, 2, 3, 5, 7, 8, 11, 12)
OUT_TYPES = (16, 17, 18, 20, 21, 23, 24, 25, 28, 29)   # 26/27 reserved

DEVICE_ID = {   # length column of section 4.1.1 is authoritative (see DECISIONS.md D1)
    0: b'IMS',
    1: b'LMDCE421',
    2: b'4.0.0.0\x00',
    3: b'https://novantaims.com/'.ljust(32, b'\x00'),
    4: b'LMD Ethern',
    5: b'0123456789',
    6: b'LMDCM 6.004\x00',
}

MFG_DEFAULTS = {
    'AO': 0, 'RD': 0, 'AJ': 1, 'AT': 0, 'BE': 0, 'BL': 0, 'BM': 0, 'DJ': 1, 'DT': 0,
    'FS': 0, 'FL': 0, 'LS': [0, 0, 0], 'MU_B': 0, 'TR': [0, 0, 0],
}


class Refuse(Exception):
    def __init__(self, code):
        self.code = code


class Drive:
    def __init__(self):
        self.p = {it.mn: it.default for it in ITEMS if it.kind in ('rw', 'uv')}
        self.mfg = copy.deepcopy(MFG_DEFAULTS)
        self.inputs = {i: [0, 0, 0] for i in range(1, 5)}   # line -> [type, active, sink/source]
        self.analog = [9, 0]                               # mode, range
        self.outputs = {i: [16, 0] for i in range(1, 4)}  # line -> [type, active]
        self.is_sel, self.os_sel = 1, 1
        self.latch = 0          # 4-bit output latch (coils 0..3)
        self.pc = 0
        self.ll = 0
        self.ef = 0
        self.nvm = self._snapshot_params()
        self.uv_declared = False   # V1..V8 exist only when declared by a running MCode program (none)
        self.motion = None
        self.counters = {'requests': 0, 'exceptions': 0, 'bad_frames': 0}

    # ---- NVM ----
    def _snapshot_params(self):
        return {'registers': {mn: self.p[mn] for mn in PARAM_MN},
                'mfg': copy.deepcopy(self.mfg),
                'inputs': copy.deepcopy(self.inputs), 'analog': list(self.analog),
                'outputs': copy.deepcopy(self.outputs)}

    def _restore_params(self, snap):
        for mn, v in snap['registers'].items():
            self.p[mn] = v
        self.mfg = copy.deepcopy(snap['mfg'])
        self.inputs = {int(k): list(v) for k, v in snap['inputs'].items()}
        self.analog = list(snap['analog'])
        self.outputs = {int(k): list(v) for k, v in snap['outputs'].items()}

    # ---- motion ----
    def tick(self):
        m = self.motion
        if not m:
            return
        now = time.monotonic()
        t = now - m['t0']
        if m['type'] == 'move':
            pos, vel, accel, done = self._profile(m, t)
        else:
            pos, vel, accel, done = self._slew(m, t)
        d = pos - m['last']
        m['last'] = pos
        self._advance(d)
        m['vel'] = vel
        m['accel'] = accel
        if done:
            if m.get('home'):
                self.p['P'] = 0
            self.motion = None

    def _advance(self, d):
        if d:
            self.p['P'] = wrap32(self.p['P'] + d)
            self.p['C1'] = wrap32(self.p['C1'] + d)
            if self.p['EE']:
                self.p['C2'] = wrap32(self.p['C2'] + d)

    @staticmethod
    def _profile(m, t):
        dist, sgn = m['dist'], m['sgn']
        v0, vp, a, dcl, ta, tc, td = m['v0'], m['vp'], m['a'], m['d'], m['ta'], m['tc'], m['td']
        total = ta + tc + td
        if t >= total:
            return sgn * dist, 0, False, True
        if t < ta:
            x = v0 * t + 0.5 * a * t * t
            v = v0 + a * t
            acc = True
        elif t < ta + tc:
            x = m['da'] + vp * (t - ta)
            v = vp
            acc = False
        else:
            u = t - ta - tc
            x = m['da'] + vp * tc + vp * u - 0.5 * dcl * u * u
            v = vp - dcl * u
            acc = True
        x = min(int(x), dist)
        return sgn * x, sgn * int(v), acc, False

    @staticmethod
    def _slew(m, t):
        v0, vt, a = m['v0'], m['vt'], m['a']
        tr = abs(vt - v0) / a
        s = 1 if vt >= v0 else -1
        if t < tr:
            x = v0 * t + 0.5 * s * a * t * t
            return m['x0'] + int(x), int(v0 + s * a * t), True, False
        x = v0 * tr + 0.5 * s * a * tr * tr + vt * (t - tr)
        return m['x0'] + int(x), int(vt), False, (vt == 0)

    def moving(self):
        self.tick()
        return self.motion is not None

    def start_move(self, dist, home=False):
        if not self.p['DE']:
            raise Refuse(4)
        if self.motion is not None:
            raise Refuse(4)
        sgn = 1 if dist >= 0 else -1
        dist = abs(dist)
        v0 = float(min(self.p['VI'], self.p['VM']))
        vm = float(self.p['VM'])
        a, d = float(self.p['A']), float(self.p['D'])
        da = (vm * vm - v0 * v0) / (2 * a)
        dd = (vm * vm - v0 * v0) / (2 * d)
        if da + dd > dist:
            vp = math.sqrt(v0 * v0 + dist / (1 / (2 * a) + 1 / (2 * d)))
            da = (vp * vp - v0 * v0) / (2 * a)
            dd = (vp * vp - v0 * v0) / (2 * d)
        else:
            vp = vm
        ta = (vp - v0) / a
        td = (vp - v0) / d
        tc = max(0.0, (dist - da - dd) / vp) if vp > 0 else 0.0
        self.motion = dict(type='move', t0=time.monotonic(), dist=dist, sgn=sgn, v0=v0, vp=vp, a=a, d=d,
                           ta=ta, tc=tc, td=td, da=da, last=0, vel=0, accel=True, home=home)
        if dist == 0:
            self.motion = None

    def slew(self, v):
        if v != 0 and not self.p['DE']:
            raise Refuse(4)
        self.tick()
        m = self.motion
        if m is not None and m['type'] == 'move':
            raise Refuse(4)
        if m is None and v == 0:
            return
        v0 = float(m['vel']) if m else 0.0
        a = float(self.p['A'] if abs(v) > abs(v0) else self.p['D'])
        self.motion = dict(type='slew', t0=time.monotonic(), x0=0, v0=v0, vt=float(v), a=a, last=0,
                           vel=v0, accel=True)

    def stop_now(self):
        self.tick()
        self.motion = None

    # ---- derived status ----
    def status(self, mn):
        self.tick()
        m = self.motion
        if mn == 'BY':
            return 0
        if mn == 'MV':
            return 1 if m else 0
        if mn == 'MP':
            return 1 if (m and m['type'] == 'move') else 0
        if mn == 'VC':
            return 1 if (m and m['accel']) else 0
        if mn == 'V':
            return int(m['vel']) if m else 0
        if mn == 'EF':
            return 1 if self.p['ER'] else 0
        if mn in ('I1', 'I2', 'I3', 'I4', 'I6', 'I5', 'IN', 'OF', 'ST', 'LR'):
            return 0
        if mn == 'PC':
            return self.pc
        if mn == 'LL':
            return self.ll
        if mn == 'AF':
            v = 128
            if self.p['AS']:
                v |= 16
            if not m:
                v |= 64
            return v
        raise KeyError(mn)

    def output_state(self, line):   # line 1..4 -> logic state
        if line == 4:
            return (self.latch >> 3) & 1
        typ = self.outputs[line][0]
        if typ == 16:
            return (self.latch >> (line - 1)) & 1
        m = self.moving()
        if typ == 17:
            return 1 if m else 0
        if typ == 18:
            return self.status('EF')
        if typ == 20:
            return self.status('VC')
        if typ == 23:
            return self.status('MP')
        if typ == 24:
            return 1 if self.p['AS'] else 0
        if typ == 29:
            return 1 if (self.mfg['AO'] & self.attention_bits()) else 0
        return 0

    def attention_bits(self):
        b = 0
        if self.status('EF'):
            b |= 1
        if self.p['AS']:
            b |= 16
        if not self.p['DE']:
            b |= 2048
        if self.motion:
            b |= 16384
        return b

    # ---- register access ----
    def read_item(self, it, side_effects=True):
        if it.kind == 'ro':
            v = self.status(it.mn)
        elif it.kind == 'cmd':
            v = 0
        elif it.kind == 'out':
            if it.mn == 'OT':
                v = sum(self.output_state(i) << (i - 1) for i in range(1, 5))
            else:
                v = self.output_state(int(it.mn[1]))
        else:
            if it.mn in ('P', 'C1', 'C2'):
                self.tick()
            v = self.p[it.mn]
            if it.mn == 'ER' and side_effects:
                self.p['ER'] = 0      # "must be read or set to 0 to clear"
        return v

    def write_item(self, it, v):
        """v: raw unsigned value from the wire (16 or 32 bit). Validation already done by validate()."""
        mn = it.mn
        if it.kind == 'cmd':
            return self._command(it, v)
        if it.kind == 'out':
            if mn == 'OT':
                for line in range(1, 5):
                    if line == 4 or self.outputs[line][0] == 16:
                        bit = 1 << (line - 1)
                        self.latch = (self.latch & ~bit) | (v & bit)
            else:
                self.set_coil(int(mn[1]) - 1, v)
            return
        if mn == 'P':
            self.tick()        # a running move continues from the new origin
        self.p[mn] = v

    def set_coil(self, idx, on):
        line = idx + 1
        if line <= 3 and self.outputs[line][0] != 16:
            raise Refuse(4)
        bit = 1 << idx
        self.latch = (self.latch | bit) if on else (self.latch & ~bit)

    def validate(self, it, v):
        """returns the typed value or raises Refuse(3)"""
        if it.kind == 'ro':
            raise Refuse(2)
        if it.kind == 'uv' and not self.uv_declared:
            raise Refuse(4)
        if it.signed:
            if it.n == 2 and v >= 0x80000000:
                v -= 0x100000000
        if it.mn in ('DC', 'IC'):
            tgt = REG_OWNER.get(v)
            if tgt is None or tgt.addr != v or tgt.mn not in ('C1', 'C2', 'P', 'R1', 'R2', 'R3', 'R4'):
                raise Refuse(3)
            return v
        if it.kind == 'cmd' and it.lo is None:
            return v
        if it.allowed is not None:
            if v not in it.allowed:
                raise Refuse(3)
            return v
        if it.lo is not None and not (it.lo <= v <= it.hi):
            raise Refuse(3)
        if it.n == 1 and it.hi is not None and it.hi <= 255 and v > 255:
            raise Refuse(3)
        mn = it.mn
        if mn == 'VI' and not v <= self.p['VM'] - 1:
            raise Refuse(3)
        if mn == 'VM' and not v >= self.p['VI'] + 1:
            raise Refuse(3)
        if mn == 'HT' and v == 1:
            raise Refuse(3)
        if mn == 'HT' and v + self.p['MT'] > 65535:
            raise Refuse(3)
        if mn == 'MT' and v + self.p['HT'] > 65535:
            raise Refuse(3)
        return v

    def _command(self, it, v):
        mn = it.mn
        if mn in ('DC', 'IC'):
            tgt = REG_OWNER[v]
            self.tick()
            self.p[tgt.mn] = wrap32(self.p[tgt.mn] + (1 if mn == 'IC' else -1))
        elif mn == 'IP':
            if self.moving():
                raise Refuse(4)
            self._restore_params(self.nvm)
        elif mn == 'S':
            if self.moving():
                raise Refuse(4)
            self.nvm = self._snapshot_params()
        elif mn == 'MA':
            self.tick()
            self.start_move(v - self.p['P'])
        elif mn == 'MR':
            self.start_move(v)
        elif mn == 'SL':
            self.slew(v)
        elif mn == 'HI':
            self.start_home(v)
        elif mn == 'CF':
            self.ll = 0
        elif mn == 'SC':
            if self.moving():
                raise Refuse(4)

    def start_home(self, mode):
        dist = 200 * self.p['MS'] // 4
        if mode in (1, 2):
            dist = -dist
        self.start_move(dist, home=True)

    # ---- state dump ----
    def dump(self):
        self.tick()
        regs = {}
        for it in ITEMS:
            if it.kind == 'uv':
                v = self.p[it.mn]
            else:
                v = self.read_item(it, side_effects=False)
            regs['0x%04X' % it.addr] = {'mnemonic': it.mn, 'registers': it.n, 'value': v}
        return {
            'device': 'Lexium MDrive Ethernet (LMD) Modbus/TCP simulator',
            'holding_registers': regs,
            'coils': {'0x%04X' % i: self.output_state(i + 1) for i in range(4)},
            'output_latch': self.latch,
            'discrete_inputs': {'0x%04X' % i: 0 for i in range(4)},
            'manufacturer_functions': {
                'AO': self.mfg['AO'], 'RD': self.mfg['RD'], 'AJ': self.mfg['AJ'], 'AT': self.mfg['AT'],
                'BE': self.mfg['BE'], 'BL': self.mfg['BL'], 'BM': self.mfg['BM'], 'DJ': self.mfg['DJ'],
                'DT': self.mfg['DT'], 'FS': self.mfg['FS'], 'FL': self.mfg['FL'], 'LS': self.mfg['LS'],
                'MU': [self.p['MU'], self.mfg['MU_B']], 'TR': self.mfg['TR'],
                'IS': {str(k): v for k, v in self.inputs.items()}, 'IS_analog': self.analog,
                'IS_selected_line': self.is_sel,
                'OS': {str(k): v for k, v in self.outputs.items()}, 'OS_selected_line': self.os_sel,
                'IT': '52,37', 'VT': '22,37', 'AV': self.av(),
            },
            'user_variables_declared': self.uv_declared,
            'nvm': self.nvm,
            'device_identification': {str(k): v.decode('latin-1') for k, v in DEVICE_ID.items()},
            'diagnostic_counters': dict(self.counters),
        }

    def av(self):
        return self.status('V') if self.p['AS'] else 0


def wrap32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


# ---------------------------------------------------------------------------
# Manufacturer specific functions 0x41 / 0x42
# ---------------------------------------------------------------------------
def parse_ints(s, n):
    parts = [x.strip() for x in s.split(',')]
    if len(parts) != n:
        raise Refuse(3)
    out = []
    for x in parts:
        if not x or not (x.lstrip('+-').isdigit()) or x.count('-') + x.count('+') > 1:
            raise Refuse(3)
        out.append(int(x))
    return out


SIMPLE = {   # mnemonic -> (lo, hi, max data length incl. '=')
    'AO': (0, 65535, 6), 'RD': (0, 1, 2), 'AJ': (1, 999, 4), 'AT': (0, 1, 2), 'BE': (0, 1, 2),
    'BL': (0, 2147483647, 11), 'BM': (0, 1, 2), 'DJ': (1, 999, 4), 'DT': (0, 1, 2),
    'FS': (-9999, 99999, 6), 'FL': (0, 1, 2),
}
WRITE_ONLY0 = ('\x1b', 'CP', 'PS', 'RS', 'E')          # no parameter data
READ_ONLY = ('IT', 'VT', 'AV')
ALIASES = {'TR3': 'TR'}
KNOWN = set(SIMPLE) | set(WRITE_ONLY0) | set(READ_ONLY) | {'IS', 'OS', 'MU', 'LS', 'TR', 'EX', 'HF', 'UG',
                                                           'S1', 'S2', 'S3', 'S4'}


def decode_mnemonic(b4):
    s = bytes(reversed(b4)).strip(b' \x00')
    try:
        name = s.decode('ascii')
    except UnicodeDecodeError:
        return None
    return ALIASES.get(name, name)


def mfg_read(dev, name):
    if name in WRITE_ONLY0 or name in ('EX', 'HF', 'UG'):
        raise Refuse(1)
    if name in SIMPLE:
        return '=%d' % dev.mfg[name]
    if name == 'IT':
        return '52,37'
    if name == 'VT':
        return '22,37'
    if name == 'AV':
        return '%d' % dev.av()
    if name == 'MU':
        return '=%d,%d' % (dev.p['MU'], dev.mfg['MU_B'])
    if name == 'LS':
        return '=%d,%d,%d' % tuple(dev.mfg['LS'])
    if name == 'TR':
        return '%d, %d, %d' % tuple(dev.mfg['TR'])
    if name == 'IS':
        if dev.is_sel == 5:
            return '=5,%d,%d' % tuple(dev.analog)
        t, a, _ = dev.inputs[dev.is_sel]
        return '=%d,%d,%d' % (dev.is_sel, t, a)
    if name == 'OS':
        t, a = dev.outputs[dev.os_sel]
        return '=%d,%d,%d' % (dev.os_sel, t, a)
    if name in ('S1', 'S2', 'S3', 'S4'):
        return '=%d,%d,%d' % tuple(dev.inputs[int(name[1])])
    raise Refuse(2)


def mfg_write(dev, name, data):
    try:
        s = data.decode('ascii')
    except UnicodeDecodeError:
        raise Refuse(3)
    if name in READ_ONLY:
        raise Refuse(1)
    if name in WRITE_ONLY0:
        if s != '':
            raise Refuse(3)
        if name == '\x1b':
            dev.stop_now()
        elif name == 'CP':
            if dev.moving():
                raise Refuse(4)
        return
    if name == 'EX':
        if not (s.startswith(' ') and 2 <= len(s) <= 4 and s[1:].isalnum()):
            raise Refuse(3)
        raise Refuse(4)              # program space is empty: no label/address to execute
    if name == 'UG':
        if s != ' 2956102':
            raise Refuse(3)
        if dev.moving():
            raise Refuse(4)
        return                       # acknowledged; upgrade (boot loader) mode is not simulated
    if not s.startswith('='):
        raise Refuse(3)
    body = s[1:]
    if name in SIMPLE:
        lo, hi, mx = SIMPLE[name]
        if len(s) > mx:
            raise Refuse(3)
        v = parse_ints(body, 1)[0]
        if not lo <= v <= hi:
            raise Refuse(3)
        dev.mfg[name] = v
        return
    if name == 'HF':
        if len(s) != 2:
            raise Refuse(3)
        v = parse_ints(body, 1)[0]
        if not 1 <= v <= 4:
            raise Refuse(3)
        dev.start_home(v)
        return
    if name == 'MU':
        a, b = parse_ints(body, 2)
        if not (0 <= a <= 2 and b in (0, 1)):
            raise Refuse(3)
        dev.p['MU'] = a
        dev.mfg['MU_B'] = b
        if b == 1:
            dev.ll = 0
        return
    if name == 'LS':
        if len(s) > 16:
            raise Refuse(3)
        a, pos, c = parse_ints(body, 3)
        if a not in (0, 1) or c not in (0, 1) or not I32_MIN <= pos <= I32_MAX:
            raise Refuse(3)
        dev.mfg['LS'] = [a, pos, c]
        return
    if name == 'TR':
        vals = parse_ints(body, 3)
        if any(not I32_MIN <= x <= I32_MAX for x in vals):
            raise Refuse(3)
        dev.mfg['TR'] = vals
        return
    if name == 'IS':
        if len(s) > 7:
            raise Refuse(3)
        line, typ, act = parse_ints(body, 3)
        if line == 5:
            if typ not in (9, 10) or act not in (0, 1):
                raise Refuse(3)
            dev.analog = [typ, act]
        elif 1 <= line <= 4:
            if typ not in IN_TYPES or act not in (0, 1) or (typ == 12 and line != 1):
                raise Refuse(3)
            dev.inputs[line][0] = typ
            dev.inputs[line][1] = act
        else:
            raise Refuse(3)
        dev.is_sel = line
        return
    if name == 'OS':
        if len(s) > 7:
            raise Refuse(3)
        line, typ, act = parse_ints(body, 3)
        if not 1 <= line <= 3 or typ not in OUT_TYPES or act not in (0, 1) or (typ == 28 and line != 3):
            raise Refuse(3)
        dev.outputs[line] = [typ, act]
        dev.os_sel = line
        return
    if name in ('S1', 'S2', 'S3', 'S4'):
        parts = body.split(',')
        if len(parts) == 2:
            typ, act = parse_ints(body, 2)
            snk = dev.inputs[int(name[1])][2]
        else:
            typ, act, snk = parse_ints(body, 3)
        line = int(name[1])
        if typ not in IN_TYPES or act not in (0, 1) or snk not in (0, 1) or (typ == 12 and line != 1):
            raise Refuse(3)
        dev.inputs[line] = [typ, act, snk]
        return
    raise Refuse(2)


# ---------------------------------------------------------------------------
# PDU handling
# ---------------------------------------------------------------------------
def handle_pdu(dev, pdu):
    fc = pdu[0]
    try:
        return fc, _handle(dev, fc, pdu)
    except Refuse as r:
        dev.counters['exceptions'] += 1
        return fc, bytes([(fc | 0x80) & 0xFF, r.code])


def _handle(dev, fc, pdu):
    n = len(pdu)
    if fc in (0x01, 0x02):
        if n != 5:
            raise Refuse(3)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not 1 <= qty <= 4:
            raise Refuse(3)
        if fc == 0x01:
            if start != 0x0000:            # table: starting address 0x0000 only
                raise Refuse(2)
            bits = [dev.output_state(i + 1) for i in range(qty)]
        else:
            if start > 3 or start + qty > 4:
                raise Refuse(2)
            bits = [0] * qty
        val = sum(b << i for i, b in enumerate(bits))
        return bytes([fc, 1, val])
    if fc == 0x05:
        if n != 5:
            raise Refuse(3)
        addr, val = struct.unpack('>HH', pdu[1:5])
        if val not in (0x0000, 0xFF00):
            raise Refuse(3)
        if addr > 3:
            raise Refuse(2)
        dev.set_coil(addr, val == 0xFF00)
        return bytes(pdu)
    if fc == 0x03:
        if n != 5:
            raise Refuse(3)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not 1 <= qty <= 2:
            raise Refuse(3)
        items = span_items(start, qty)
        for it in items:
            if it.kind == 'uv' and not dev.uv_declared:
                raise Refuse(4)
        out = b''
        for it in items:
            v = dev.read_item(it)
            out += encode(it, v)
        return bytes([3, len(out)]) + out
    if fc == 0x10:
        if n < 6:
            raise Refuse(3)
        start, qty, bc = struct.unpack('>HHB', pdu[1:6])
        if not 1 <= qty <= 2 or bc != 2 * qty or n != 6 + bc:
            raise Refuse(3)
        items = span_items(start, qty)
        data = pdu[6:]
        vals = []
        off = 0
        for it in items:
            raw = int.from_bytes(data[off:off + 2 * it.n], 'big')   # high word first (D3)
            off += 2 * it.n
            vals.append(dev.validate(it, raw))
        for it, v in zip(items, vals):
            dev.write_item(it, v)
        return bytes([0x10]) + struct.pack('>HH', start, qty)
    if fc == 0x2B:
        if n < 2:
            raise Refuse(3)
        if pdu[1] != 0x0E:
            raise Refuse(1)
        if n != 4:
            raise Refuse(3)
        code, oid = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise Refuse(3)
        if code == 4:
            if oid not in DEVICE_ID:
                raise Refuse(2)
            ids = [oid]
        else:
            last = 2 if code == 1 else 6
            if oid > last:
                oid = 0
            ids = list(range(oid, last + 1))
        body = b''
        for i in ids:
            body += bytes([i, len(DEVICE_ID[i])]) + DEVICE_ID[i]
        return bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)]) + body
    if fc == 0x41:
        if n != 5:
            raise Refuse(3)
        name = decode_mnemonic(pdu[1:5])
        if name not in KNOWN:
            raise Refuse(2)
        s = mfg_read(dev, name).encode('ascii')
        return bytes([0x41]) + struct.pack('>H', len(s)) + s      # 2-byte byte count (D10)
    if fc == 0x42:
        if n < 6:
            raise Refuse(3)
        bc = pdu[5]
        if bc > 28 or n != 6 + bc:
            raise Refuse(3)
        name = decode_mnemonic(pdu[1:5])
        if name not in KNOWN:
            raise Refuse(2)
        mfg_write(dev, name, bytes(pdu[6:]))
        return bytes([0x42, 0x04]) + bytes(pdu[1:5])               # "quantity of characters returned" (D11)
    raise Refuse(1)


def span_items(start, qty):
    items = []
    a = start
    end = start + qty
    while a < end:
        it = REG_OWNER.get(a)
        if it is None or it.addr != a or a + it.n > end:
            raise Refuse(2)
        items.append(it)
        a += it.n
    return items


def encode(it, v):
    if it.n == 2:
        return (v & 0xFFFFFFFF).to_bytes(4, 'big')     # high word at the lower address (D3)
    return (v & 0xFFFF).to_bytes(2, 'big')


# ---------------------------------------------------------------------------
# TCP server
# ---------------------------------------------------------------------------
class Server:
    def __init__(self, state_file):
        self.dev = Drive()
        self.state_file = state_file

    def save_state(self):
        if not self.state_file:
            return
        try:
            tmp = self.state_file + '.tmp'
            with open(tmp, 'w') as f:
                json.dump(self.dev.dump(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except Exception as e:  # never die because of the dump
            print('state dump failed: %s' % e, file=sys.stderr)

    async def client(self, reader, writer):
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid, pid, ln, uid = struct.unpack('>HHHB', hdr)
                if ln < 2 or ln > 254:
                    self.dev.counters['bad_frames'] += 1
                    break                       # cannot resynchronise the stream: drop the connection
                pdu = await reader.readexactly(ln - 1)
                if pid != 0:
                    self.dev.counters['bad_frames'] += 1
                    continue                    # not MODBUS: silently discarded
                self.dev.counters['requests'] += 1
                try:
                    fc, resp = handle_pdu(self.dev, pdu)
                except Exception as e:          # internal error -> slave device failure
                    print('internal error: %r' % e, file=sys.stderr)
                    resp = bytes([(pdu[0] | 0x80) & 0xFF, 4])
                writer.write(struct.pack('>HHHB', tid, 0, len(resp) + 1, uid) + resp)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            try:
                writer.close()
            except Exception:
                pass


async def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--listen', required=True)
    ap.add_argument('--state')
    args = ap.parse_args()
    host, port = args.listen.rsplit(':', 1)
    srv = Server(args.state)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, srv.save_state)
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    server = await asyncio.start_server(srv.client, host, int(port))
    p = server.sockets[0].getsockname()[1]
    print('listening tcp %s:%d' % (host, p), flush=True)
    await stop.wait()
    server.close()
    srv.save_state()


if __name__ == '__main__':
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
    os._exit(0)
