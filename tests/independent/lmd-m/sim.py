#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet, closed-loop model, Modbus/TCP server simulator.

Written from LMD-MODBUS-REV-D and the public Modbus specifications only.
Standard library only. Single thread, selectors based.
See DECISIONS.md for every interpretation of the manual and for the link model.
"""
import argparse
import errno
import json
import os
import random
import selectors
import signal
import socket
import struct
import sys
import time

# ---------------------------------------------------------------------------
# Register map (section 5).  width = number of 16-bit registers.
# kind: 'rw' parameter, 'ro' status, 'cmd' write-only command (reads 0),
#       'clr' readable flag that may only be written with 0 (clears it)
# ---------------------------------------------------------------------------
MS_VALUES = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250,
             256, 180, 108, 127)


class P:
    def __init__(self, addr, mn, width, kind, lo=None, hi=None, default=0,
                 signed=False, allowed=None, cfg=True):
        self.addr, self.mn, self.width, self.kind = addr, mn, width, kind
        self.lo, self.hi, self.default, self.signed = lo, hi, default, signed
        self.allowed = allowed
        self.cfg = cfg          # reset by IP / saved by S


S32_MIN, S32_MAX = -2147483648, 2147483647

PARAMS = [
    P(0x0000, 'A', 2, 'rw', 91, 1525878997, 1000000),
    P(0x0004, 'BY', 1, 'ro'),
    P(0x0005, 'C1', 2, 'rw', S32_MIN, S32_MAX, 0, signed=True, cfg=False),
    P(0x0007, 'C2', 2, 'rw', S32_MIN, S32_MAX, 0, signed=True, cfg=False),
    P(0x0009, 'CE', 1, 'rw', 0, 1, 1),
    P(0x000E, 'CW', 1, 'rw', 0, 255, 10),
    P(0x000F, 'D1', 1, 'rw', 0, 255, 0),
    P(0x0010, 'D2', 1, 'rw', 0, 255, 0),
    P(0x0011, 'D3', 1, 'rw', 0, 255, 0),
    P(0x0012, 'D4', 1, 'rw', 0, 255, 0),
    P(0x0013, 'D5', 1, 'rw', 0, 255, 0),
    P(0x0018, 'D', 2, 'rw', 91, 1525878997, 1000000),
    P(0x001A, 'DB', 1, 'rw', 0, 65000, 10),
    P(0x001B, 'DC', 1, 'cmd', 1, 4),
    P(0x001C, 'DE', 1, 'rw', 0, 1, 1),
    P(0x001E, 'EE', 1, 'rw', 0, 1, 0),
    P(0x001F, 'EF', 1, 'ro'),
    P(0x0021, 'ER', 1, 'clr', 0, 0, 0),
    P(0x0024, 'FC', 1, 'rw', 0, 9, 0),
    P(0x0029, 'HC', 1, 'rw', 0, 100, 5),
    P(0x002A, 'HI', 1, 'cmd', 1, 4),
    P(0x002B, 'HM', 1, 'cmd', 1, 4),
    P(0x002C, 'HT', 1, 'rw', 0, 65535, 500),
    P(0x002D, 'I1', 1, 'ro'),
    P(0x002E, 'I2', 1, 'ro'),
    P(0x002F, 'I3', 1, 'ro'),
    P(0x0030, 'I4', 1, 'ro'),
    P(0x0031, 'I5', 1, 'ro'),
    P(0x0032, 'I6', 1, 'ro'),
    P(0x0037, 'IC', 1, 'cmd', 1, 4),
    P(0x003B, 'IN', 1, 'ro'),
    P(0x003C, 'IP', 1, 'cmd', 1, 1),
    P(0x003F, 'JE', 1, 'rw', 0, 1, 0),
    P(0x0042, 'LM', 1, 'rw', 1, 6, 1),
    P(0x0043, 'MA', 2, 'cmd', S32_MIN, S32_MAX, signed=True),
    P(0x0045, 'MP', 1, 'ro'),
    P(0x0046, 'MR', 2, 'cmd', S32_MIN, S32_MAX, signed=True),
    P(0x0048, 'MS', 1, 'rw', default=256, allowed=MS_VALUES),
    P(0x0049, 'MT', 1, 'rw', 0, 65000, 0),
    P(0x004A, 'MV', 1, 'ro'),
    P(0x004B, 'O1', 1, 'rw', 0, 1, 0, cfg=False),
    P(0x004C, 'O2', 1, 'rw', 0, 1, 0, cfg=False),
    P(0x004D, 'O3', 1, 'rw', 0, 1, 0, cfg=False),
    P(0x004E, 'OF', 1, 'ro'),
    P(0x0056, 'OT', 1, 'rw', 0, 15, 0, cfg=False),
    P(0x0057, 'P', 2, 'rw', S32_MIN, S32_MAX, 0, signed=True, cfg=False),
    P(0x0059, 'PC', 2, 'ro', signed=True),
    P(0x005C, 'PM', 1, 'rw', 0, 1, 0),
    P(0x005F, 'R1', 2, 'rw', S32_MIN, S32_MAX, 0, signed=True, cfg=False),
    P(0x0061, 'R2', 2, 'rw', S32_MIN, S32_MAX, 0, signed=True, cfg=False),
    P(0x0063, 'R3', 2, 'rw', S32_MIN, S32_MAX, 0, signed=True, cfg=False),
    P(0x0065, 'R4', 2, 'rw', S32_MIN, S32_MAX, 0, signed=True, cfg=False),
    P(0x0067, 'RC', 1, 'rw', 1, 100, 25),
    P(0x0076, 'S', 1, 'cmd', 1, 1),
    P(0x0077, 'SF', 1, 'rw', 0, 65000, 15),
    P(0x0078, 'SL', 2, 'cmd', -5000000, 5000000, signed=True),
    P(0x007A, 'SM', 1, 'rw', 0, 1, 0),
    P(0x007B, 'ST', 1, 'clr', 0, 0, 0),
    P(0x007D, 'TE', 1, 'rw', 0, 43, 0),
    P(0x0085, 'V', 2, 'ro', signed=True),
    P(0x0088, 'VC', 1, 'ro'),
    P(0x0089, 'VI', 2, 'rw', 1, 2559999, 1000),
    P(0x008B, 'VM', 2, 'rw', 2, 2560000, 768000),
    P(0x008D, 'WT', 1, 'rw', 0, 84, 80),
    # 5.1 hMTechnology
    P(0x008E, 'AS', 1, 'rw', 0, 3, 2),
    P(0x008F, 'AF', 1, 'ro'),
    P(0x0091, 'CB', 1, 'rw', 0, 3, 1),
    P(0x0093, 'CF', 1, 'cmd', 1, 1),
    P(0x0095, 'LD', 2, 'rw', 0, S32_MAX, 102400),
    P(0x0097, 'LG', 2, 'rw', 0, S32_MAX, 102400),
    P(0x0099, 'LL', 2, 'ro', signed=True),
    P(0x009B, 'LR', 1, 'ro'),
    P(0x009C, 'LT', 2, 'rw', 2, 65535, 2000),
    P(0x009E, 'MF', 2, 'rw', 306, 2560000, 768000),
    P(0x00A0, 'MU', 1, 'rw', 0, 2, 0),
    P(0x00A1, 'SC', 1, 'cmd', 1, 1),
    P(0x00A3, 'TS', 2, 'rw', 0, 255, 0),
    P(0x00A5, 'TD', 1, 'rw', 0, 1, 1),
    P(0x00A6, 'TQ', 1, 'rw', 1, 100, 25),
    P(0x00A7, 'VF', 1, 'rw', 0, 1000, 0),
]
for _i in range(8):  # 5.2 user variables
    PARAMS.append(P(0x00A8 + 2 * _i, 'V%d' % (_i + 1), 2, 'rw', S32_MIN, S32_MAX,
                    0, signed=True, cfg=False))

REG = {}      # register address -> (param, word index 0=low word)
BY_MN = {}
for _p in PARAMS:
    BY_MN[_p.mn] = _p
    for _k in range(_p.width):
        REG[_p.addr + _k] = (_p, _k)

# ---------------------------------------------------------------------------
# Vendor (FC 0x41/0x42) mnemonics
# ---------------------------------------------------------------------------
IN_TYPES = (0, 1, 2, 3, 5, 7, 8, 11, 12)
OUT_TYPES = (16, 17, 18, 20, 21, 23, 24, 25, 28, 29)
VENDOR_RW = {'AO', 'EL', 'IS', 'MU', 'OS', 'RD', 'AJ', 'AT', 'BE', 'BL', 'BM',
             'DJ', 'DT', 'FS', 'FL', 'LS', 'TR', 'S1', 'S2', 'S3', 'S4', 'S5'}
VENDOR_RO = {'IT', 'VT', 'AV'}
VENDOR_WO = {'\x1b', 'CP', 'EX', 'PS', 'RS', 'E', 'HF', 'UG'}


def default_vendor():
    return {
        'AO': 0, 'EL': 1000,
        'inputs': {str(n): [0, 0, 0] for n in range(1, 5)},   # type, active, sink/source
        'analog': [9, 0],                                      # mode, range
        'outputs': {str(n): [16, 1] for n in range(1, 4)},     # type, active
        'RD': 0, 'AJ': 128, 'AT': 0, 'BE': 0, 'BL': 0, 'BM': 0,
        'DJ': 128, 'DT': 0, 'FS': 0, 'FL': 0,
        'LS': {'0': [0, 0], '1': [0, 0]},                      # dir -> position, enable
        'TR': [0, 0, 0],
    }


class VErr(Exception):
    def __init__(self, code):
        self.code = code


def s16(v):
    return v - 0x10000 if v & 0x8000 else v


def to_s32(lo_word, hi_word):
    v = (hi_word << 16) | lo_word
    return v - (1 << 32) if v & 0x80000000 else v


# ---------------------------------------------------------------------------
# The drive
# ---------------------------------------------------------------------------
class Drive:
    def __init__(self):
        self.v = {p.mn: p.default for p in PARAMS if p.kind in ('rw', 'clr')}
        self.vendor = default_vendor()
        self.nvm = None   # saved image (S); None = factory
        self.pos = 0.0                # commanded position, steps (float)
        self.vel = 0.0                # signed velocity steps/s
        self.mode = None              # None | 'pos' | 'slew' | 'stop' | 'home'
        self.target = 0.0
        self.slew_v = 0.0
        self.home_until = 0.0
        self.vc = 0
        self.c2_acc = 0.0
        self.last = time.monotonic()
        self.t0 = self.last
        self.er = 0
        self.pc = 0

    # ---- motion ---------------------------------------------------------
    def tick(self):
        now = time.monotonic()
        dt = now - self.last
        self.last = now
        if self.mode is None or dt <= 0:
            self.vc = 0
            return
        steps = min(int(dt / 0.001) + 1, 20000)
        h = dt / steps
        for _ in range(steps):
            self._step(h, now)
            if self.mode is None:
                break

    def _move_pos(self, dp):
        if dp == 0:
            return
        old = self.pos
        self.pos += dp
        d_int = int(round(self.pos)) - int(round(old))
        if d_int:
            self.v['P'] = self._wrap(self.v['P'] + d_int)
            self.v['C1'] = self._wrap(self.v['C1'] + d_int)
            self.c2_acc += d_int * 2048.0 / (200.0 * self.v['MS'])
            c = int(self.c2_acc)
            if c:
                self.c2_acc -= c
                self.v['C2'] = self._wrap(self.v['C2'] + c)

    @staticmethod
    def _wrap(x):
        return ((x + 2 ** 31) % 2 ** 32) - 2 ** 31

    def _step(self, h, now):
        acc, dec = float(self.v['A']), float(self.v['D'])
        vm = float(self.v['VM'])
        vi = float(self.v['VI'])
        v = self.vel
        if self.mode == 'pos':
            rem = self.target - self.pos
            if abs(rem) < 0.5 and abs(v) <= vi + 1:
                self._move_pos(rem)
                self.vel = 0.0
                self.mode = None
                self.vc = 0
                return
            sgn = 1.0 if rem > 0 else -1.0
            if v * sgn < 0:          # moving wrong way: brake
                nv = v + sgn * dec * h
                self.vc = 1
            else:
                sp = abs(v)
                stop_d = (sp * sp - vi * vi) / (2 * dec) if sp > vi else 0.0
                if abs(rem) <= stop_d + sp * h:
                    sp = max(vi, sp - dec * h)
                    self.vc = 1
                elif sp < vm:
                    sp = max(vi, min(vm, sp + acc * h))
                    self.vc = 1
                else:
                    sp = vm
                    self.vc = 0
                nv = sgn * sp
            dp = nv * h
            if abs(dp) >= abs(rem) and dp * rem > 0:
                dp = rem
            self.vel = nv
            self._move_pos(dp)
        elif self.mode in ('slew', 'stop'):
            tv = self.slew_v if self.mode == 'slew' else 0.0
            if v == tv:
                self.vc = 0
            else:
                self.vc = 1
                if v == 0.0 and tv != 0.0:
                    v = min(vi, abs(tv)) * (1 if tv > 0 else -1)
                rate = acc if abs(tv) > abs(v) and v * tv >= 0 else dec
                if tv > v:
                    v = min(tv, v + rate * h)
                else:
                    v = max(tv, v - rate * h)
                if tv == 0.0 and abs(v) < vi:
                    v = 0.0
            self.vel = v
            self._move_pos(v * h)
            if self.mode == 'stop' and self.vel == 0.0:
                self.mode = None
                self.vc = 0
        elif self.mode == 'home':
            # simulated search: creep toward the home switch, then zero
            if now >= self.home_until:
                self.vel = 0.0
                self.mode = None
                self.vc = 0
                self.v['P'] = 0
                self.pos = 0.0
            else:
                self.vel = -min(vm, 20000.0)
                self._move_pos(self.vel * h)

    def moving(self):
        return self.mode is not None

    # ---- I/O model ------------------------------------------------------
    def inputs(self):
        return [0, 0, 0, 0]   # nothing wired to the inputs

    def output_state(self, n):
        typ, act = self.vendor['outputs'][str(n)]
        if typ == 16:
            return self.v['O%d' % n]
        if typ == 17:
            return 1 if self.moving() else 0
        if typ == 18:
            return 1 if self.er else 0
        if typ == 20:
            return self.vc
        if typ == 23:
            return 1 if self.mode == 'pos' else 0
        if typ == 24:
            return 1 if self.v['AS'] != 0 else 0
        return 0

    def af(self):
        a = 128
        if self.v['AS'] != 0:
            a |= 16
        a |= 64  # lead/lag at zero (no load simulated)
        return a

    # ---- register read --------------------------------------------------
    def pvalue(self, p):
        mn = p.mn
        if p.kind == 'cmd':
            return 0
        if mn in self.v:
            if mn == 'ER':
                return self.er
            if mn == 'OT':
                return sum(self.output_state(n) << (n - 1) for n in (1, 2, 3))
            if mn in ('O1', 'O2', 'O3'):
                return self.output_state(int(mn[1]))
            return self.v[mn]
        ins = self.inputs()
        if mn == 'BY':
            return 0
        if mn == 'EF':
            return 1 if self.er else 0
        if mn in ('I1', 'I2', 'I3', 'I4'):
            return ins[int(mn[1]) - 1]
        if mn == 'I5':
            return 0
        if mn == 'I6':
            return 0
        if mn == 'IN':
            return sum(b << i for i, b in enumerate(ins))
        if mn == 'MP':
            return 1 if self.mode == 'pos' else 0
        if mn == 'MV':
            return 1 if self.moving() else 0
        if mn == 'OF':
            return 0
        if mn == 'PC':
            return self.pc
        if mn == 'V':
            return 0 if self.v['AS'] == 3 else int(round(self.vel))
        if mn == 'VC':
            return self.vc if self.moving() else 0
        if mn == 'AF':
            return self.af()
        if mn == 'LL':
            return 0
        if mn == 'LR':
            return 0
        return 0

    def read_word(self, addr):
        p, k = REG[addr]
        val = self.pvalue(p)
        if p.width == 1:
            return val & 0xFFFF
        val &= 0xFFFFFFFF
        return val & 0xFFFF if k == 0 else (val >> 16) & 0xFFFF

    # ---- register write -------------------------------------------------
    def check_write(self, p, val):
        """Return exception code or 0."""
        if p.kind == 'ro':
            return 2
        if p.allowed is not None:
            if val not in p.allowed:
                return 3
        elif not (p.lo <= val <= p.hi):
            return 3
        mn = p.mn
        if mn == 'HT' and val == 1:
            return 3
        if mn == 'HT' and val + self.v['MT'] > 65535:
            return 3
        if mn == 'MT' and val + self.v['HT'] > 65535:
            return 3
        if mn == 'VI' and val >= self.v['VM']:
            return 3
        if mn == 'VM' and val <= self.v['VI']:
            return 3
        if mn in ('MA', 'MR', 'SL', 'HI', 'HM') and self.v['DE'] == 0:
            return 4
        if mn in ('O1', 'O2', 'O3') and self.vendor['outputs'][mn[1]][0] != 16:
            return 4
        if mn == 'OT':
            for n in (1, 2, 3):
                if self.vendor['outputs'][str(n)][0] != 16 and \
                        ((val >> (n - 1)) & 1) != self.output_state(n):
                    return 4
        return 0

    def apply_write(self, p, val):
        mn = p.mn
        now = time.monotonic()
        if p.kind in ('rw',):
            if mn == 'OT':
                for n in (1, 2, 3):
                    if self.vendor['outputs'][str(n)][0] == 16:
                        self.v['O%d' % n] = (val >> (n - 1)) & 1
                return
            if mn == 'P':
                self.v['P'] = val
                if self.mode == 'pos':
                    self.target += val - self.pos
                self.pos = float(val)
                return
            self.v[mn] = val
            return
        if p.kind == 'clr':
            if mn == 'ER':
                self.er = 0
            self.v[mn] = 0
            return
        # commands
        if mn in ('DC', 'IC'):
            r = 'R%d' % val
            self.v[r] = self._wrap(self.v[r] + (1 if mn == 'IC' else -1))
        elif mn == 'IP':
            self.init_params()
        elif mn == 'S':
            self.nvm = self.snapshot_cfg()
        elif mn == 'MA':
            self.pos = float(self.v['P'])
            self.target = float(val)
            self.mode = 'pos'
        elif mn == 'MR':
            self.pos = float(self.v['P'])
            self.target = self.pos + val
            self.mode = 'pos'
        elif mn == 'SL':
            if val == 0:
                if self.moving():
                    self.mode = 'stop'
            else:
                self.slew_v = float(val)
                self.mode = 'slew'
        elif mn in ('HI', 'HM'):
            self.mode = 'home'
            self.home_until = now + 0.8
        elif mn in ('CF', 'SC'):
            pass   # no locked rotor; calibration completes at once

    def snapshot_cfg(self):
        cfg = {p.mn: self.v[p.mn] for p in PARAMS if p.cfg and p.kind == 'rw'}
        return {'registers': cfg, 'vendor': json.loads(json.dumps(self.vendor))}

    def init_params(self):
        for p in PARAMS:
            if p.cfg and p.kind == 'rw':
                self.v[p.mn] = p.default
        out_vals = {n: self.v['O%d' % n] for n in (1, 2, 3)}
        self.vendor = default_vendor()
        for n in (1, 2, 3):
            self.v['O%d' % n] = out_vals[n]

    def stop(self):
        if self.moving():
            self.mode = 'stop' if self.mode != 'home' else None
            if self.mode is None:
                self.vel = 0.0

    # ---- vendor functions ----------------------------------------------
    def live(self):
        t = time.monotonic() - self.t0
        # slow, bounded drift: warms up over minutes
        bridge = 34 + min(8, t / 90.0) + (1 if self.moving() else 0)
        cpu = 37 + min(4, t / 180.0)
        return {'IT': [int(bridge), int(cpu)], 'VT': [24, 48]}

    def vendor_read(self, mn):
        vd = self.vendor
        if mn in VENDOR_WO:
            raise VErr(2)
        if mn == 'IT':
            a, b = self.live()['IT']
            return '%d,%d' % (a, b)
        if mn == 'VT':
            a, b = self.live()['VT']
            return '%d,%d' % (a, b)
        if mn == 'AV':
            return '%d' % (int(round(self.vel)) if self.v['AS'] != 0 else 0)
        if mn == 'MU':
            return '%d, 0' % self.v['MU']
        if mn == 'IS':
            g = ['%d, %d, %d' % (n, vd['inputs'][str(n)][0], vd['inputs'][str(n)][1])
                 for n in range(1, 5)]
            g.append('5, %d, %d' % tuple(vd['analog']))
            return '; '.join(g)
        if mn == 'OS':
            return '; '.join('%d, %d, %d' % (n, *vd['outputs'][str(n)]) for n in (1, 2, 3))
        if mn in ('S1', 'S2', 'S3', 'S4'):
            return ', '.join(str(x) for x in vd['inputs'][mn[1]])
        if mn == 'S5':
            return '%d, %d' % tuple(vd['analog'])
        if mn == 'LS':
            return '; '.join('%s, %d, %d' % (d, *vd['LS'][d]) for d in ('0', '1'))
        if mn == 'TR':
            return ', '.join(str(x) for x in vd['TR'])
        if mn in vd:
            return str(vd[mn])
        raise VErr(2)

    @staticmethod
    def _ints(s, n_min, n_max):
        s = s.strip()
        if not s.startswith('='):
            raise VErr(3)
        parts = s[1:].split(',')
        if not (n_min <= len(parts) <= n_max):
            raise VErr(3)
        out = []
        for x in parts:
            x = x.strip()
            if not x or not (x.lstrip('+-').isdigit()) or len(x) > 11:
                raise VErr(3)
            out.append(int(x))
        return out

    def vendor_write(self, mn, data):
        """Validate fully, then apply. Raise VErr on refusal."""
        if mn in VENDOR_RO:
            raise VErr(2)
        try:
            s = data.decode('ascii')
        except UnicodeDecodeError:
            raise VErr(3)
        vd = self.vendor
        if mn in ('\x1b', 'CP', 'PS', 'RS', 'E'):
            if s.strip():
                raise VErr(3)
            if mn == '\x1b':
                self.stop()
            return
        if mn == 'EX':
            lab = s.strip()
            if not lab or len(lab) > 3 or not lab.isalnum():
                raise VErr(3)
            raise VErr(4)           # no MCode program stored in the drive
        if mn == 'UG':
            if s.strip() != '2956102':
                raise VErr(3)
            raise VErr(4)           # upgrade only through LSS on MCode/TCP
        if mn == 'HF':
            (a,) = self._ints(s, 1, 1)
            if not 1 <= a <= 4:
                raise VErr(3)
            if self.v['DE'] == 0:
                raise VErr(4)
            self.mode = 'home'
            self.home_until = time.monotonic() + 0.8
            return
        single = {'AO': (0, 65535), 'EL': (1, 65535), 'RD': (0, 1), 'AJ': (1, 999),
                  'AT': (0, 1), 'BE': (0, 1), 'BL': (0, 2147483647), 'BM': (0, 1),
                  'DJ': (1, 999), 'DT': (0, 1), 'FS': (0, 99999), 'FL': (0, 1)}
        if mn in single:
            (a,) = self._ints(s, 1, 1)
            lo, hi = single[mn]
            if not lo <= a <= hi:
                raise VErr(3)
            vd[mn] = a
            return
        if mn == 'MU':
            a, b = self._ints(s, 2, 2)
            if not (0 <= a <= 2 and 0 <= b <= 1):
                raise VErr(3)
            self.v['MU'] = a
            return
        if mn == 'IS':
            vals = self._ints(s, 3, 3)
            line = vals[0]
            if 1 <= line <= 4:
                t, act = vals[1], vals[2]
                if t not in IN_TYPES or act not in (0, 1) or (t == 12 and line != 1):
                    raise VErr(3)
                vd['inputs'][str(line)][0] = t
                vd['inputs'][str(line)][1] = act
                return
            if line == 5:
                m, r = vals[1], vals[2]
                if m not in (9, 10) or r not in (0, 1):
                    raise VErr(3)
                vd['analog'] = [m, r]
                return
            raise VErr(3)
        if mn in ('S1', 'S2', 'S3', 'S4'):
            vals = self._ints(s, 2, 3)
            line = int(mn[1])
            t, act = vals[0], vals[1]
            ss = vals[2] if len(vals) == 3 else vd['inputs'][mn[1]][2]
            if t not in IN_TYPES or act not in (0, 1) or ss not in (0, 1) or \
                    (t == 12 and line != 1):
                raise VErr(3)
            vd['inputs'][mn[1]] = [t, act, ss]
            return
        if mn == 'S5':
            m, r = self._ints(s, 2, 2)
            if m not in (9, 10) or r not in (0, 1):
                raise VErr(3)
            vd['analog'] = [m, r]
            return
        if mn == 'OS':
            line, t, act = self._ints(s, 3, 3)
            if not 1 <= line <= 3 or t not in OUT_TYPES or act not in (0, 1) or \
                    (t == 28 and line != 3):
                raise VErr(3)
            vd['outputs'][str(line)] = [t, act]
            return
        if mn == 'LS':
            d, pos, en = self._ints(s, 3, 3)
            if d not in (0, 1) or en not in (0, 1) or not S32_MIN <= pos <= S32_MAX:
                raise VErr(3)
            vd['LS'][str(d)] = [pos, en]
            return
        if mn == 'TR':
            vals = self._ints(s, 1, 3)
            if not S32_MIN <= vals[0] <= S32_MAX:
                raise VErr(3)
            if len(vals) > 1 and not 0 <= vals[1] <= 65535:
                raise VErr(3)
            if len(vals) > 2 and not 0 <= vals[2] <= 3:
                raise VErr(3)
            vd['TR'] = (vals + vd['TR'][len(vals):])[:3]
            return
        raise VErr(2)

    # ---- state dump -----------------------------------------------------
    def dump(self):
        self.tick()
        regs = {}
        params = {}
        for p in PARAMS:
            for k in range(p.width):
                regs['0x%04X' % (p.addr + k)] = self.read_word(p.addr + k)
            if p.kind != 'cmd':
                params[p.mn] = self.pvalue(p)
        coils = {str(n - 1): self.output_state(n) for n in (1, 2, 3)}
        dis = {str(i): b for i, b in enumerate(self.inputs())}
        vend = {mn: self.vendor_read(mn) for mn in sorted(VENDOR_RW)}
        return {
            'device': 'Lexium MDrive Ethernet closed loop (LMDCE572), Modbus/TCP',
            'holding_registers': regs,
            'parameters': params,
            'coils': coils,
            'discrete_inputs': dis,
            'vendor_settings': vend,
            'nvm_saved': self.nvm,
            'motion': {'moving': self.moving(), 'mode': self.mode},
            'diagnostic_counters': {},
            'live': self.live(),
        }


# ---------------------------------------------------------------------------
# Device identification (FC 43 / MEI 14)
# ---------------------------------------------------------------------------
DEV_ID = {
    0: b'IMS USA',
    1: b'LMDCE572',
    2: b'4.0.0.0',
    3: b'https://novantaims.com/',
    4: b'LMD Ethernet',
    5: b'LMD0213A4471',
    6: b'LMDCM 6.004, Hw: 1.0',
}


def fc43(pdu):
    if len(pdu) != 4:
        return exc(0x2B, 3)
    mei, code, oid = pdu[1], pdu[2], pdu[3]
    if mei != 0x0E:
        return exc(0x2B, 1)
    if code not in (1, 2, 3, 4):
        return exc(0x2B, 3)
    if code == 4:
        if oid not in DEV_ID:
            return exc(0x2B, 2)
        ids = [oid]
    else:
        rng = {1: range(0, 3), 2: range(0, 7), 3: range(0, 7)}[code]
        if oid not in rng:
            oid = rng.start
        ids = [i for i in rng if i >= oid]
    body = b''
    for i in ids:
        body += bytes([i, len(DEV_ID[i])]) + DEV_ID[i]
    return bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)]) + body


def exc(fc, code):
    return bytes([(fc | 0x80) & 0xFF, code])


# ---------------------------------------------------------------------------
# PDU dispatcher
# ---------------------------------------------------------------------------
def parse_mnemonic(b4):
    chars = bytes(reversed(b4))
    try:
        s = chars.decode('ascii')
    except UnicodeDecodeError:
        return None
    s = s.replace('\x00', ' ').strip(' ')
    return s if s else None


def handle_pdu(drv, pdu):
    drv.tick()
    fc = pdu[0]
    if fc == 0x01:   # read coils
        if len(pdu) != 5:
            return exc(fc, 3)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not 1 <= qty <= 4:
            return exc(fc, 3)
        if start + qty > 3:
            return exc(fc, 2)
        bits = sum(drv.output_state(start + i + 1) << i for i in range(qty))
        return bytes([fc, 1, bits])
    if fc == 0x02:   # read discrete inputs
        if len(pdu) != 5:
            return exc(fc, 3)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not 1 <= qty <= 4:
            return exc(fc, 3)
        if start + qty > 4:
            return exc(fc, 2)
        ins = drv.inputs()
        bits = sum(ins[start + i] << i for i in range(qty))
        return bytes([fc, 1, bits])
    if fc == 0x05:   # write single coil
        if len(pdu) != 5:
            return exc(fc, 3)
        addr, val = struct.unpack('>HH', pdu[1:5])
        if val not in (0x0000, 0xFF00):
            return exc(fc, 3)
        if addr > 2:
            return exc(fc, 2)
        p = BY_MN['O%d' % (addr + 1)]
        v = 1 if val else 0
        e = drv.check_write(p, v)
        if e:
            return exc(fc, e)
        drv.apply_write(p, v)
        return bytes(pdu)
    if fc == 0x03:   # read holding registers
        if len(pdu) != 5:
            return exc(fc, 3)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not 1 <= qty <= 2:
            return exc(fc, 3)
        for a in range(start, start + qty):
            if a not in REG:
                return exc(fc, 2)
        words = []
        for a in range(start, start + qty):
            p, k = REG[a]
            if p.mn == 'ER' and p.kind == 'clr':
                words.append(drv.read_word(a))
                drv.er = 0          # reading ER clears it (manual 0x0021)
            else:
                words.append(drv.read_word(a))
        return bytes([fc, 2 * qty]) + b''.join(struct.pack('>H', w) for w in words)
    if fc == 0x10:   # write multiple registers
        if len(pdu) < 6:
            return exc(fc, 3)
        start, qty, bc = struct.unpack('>HHB', pdu[1:6])
        if not 1 <= qty <= 2 or bc != 2 * qty or len(pdu) != 6 + bc:
            return exc(fc, 3)
        words = struct.unpack('>%dH' % qty, pdu[6:6 + bc])
        # decompose into whole parameters
        plan = []
        a = start
        i = 0
        while i < qty:
            if a not in REG:
                return exc(fc, 2)
            p, k = REG[a]
            if k != 0:
                return exc(fc, 2)
            if i + p.width > qty:
                return exc(fc, 3)
            if p.width == 1:
                val = s16(words[i]) if p.signed else words[i]
            else:
                val = to_s32(words[i], words[i + 1])
            plan.append((p, val))
            a += p.width
            i += p.width
        for p, val in plan:
            e = drv.check_write(p, val)
            if e:
                return exc(fc, e)
        for p, val in plan:
            drv.apply_write(p, val)
        return bytes([fc]) + struct.pack('>HH', start, qty)
    if fc == 0x2B:
        return fc43(pdu)
    if fc == 0x41:
        if len(pdu) != 5:
            return exc(fc, 3)
        mn = parse_mnemonic(pdu[1:5])
        if mn is None or mn not in (VENDOR_RW | VENDOR_RO | VENDOR_WO):
            return exc(fc, 2)
        try:
            s = drv.vendor_read(mn).encode('ascii')
        except VErr as e:
            return exc(fc, e.code)
        return bytes([fc, len(s)]) + s
    if fc == 0x42:
        if len(pdu) < 6:
            return exc(fc, 3)
        bc = pdu[5]
        if bc > 28 or len(pdu) != 6 + bc:
            return exc(fc, 3)
        mn = parse_mnemonic(pdu[1:5])
        if mn is None or mn not in (VENDOR_RW | VENDOR_RO | VENDOR_WO):
            return exc(fc, 2)
        try:
            drv.vendor_write(mn, bytes(pdu[6:6 + bc]))
        except VErr as e:
            return exc(fc, e.code)
        return bytes([fc, bc]) + bytes(pdu[1:5])
    return exc(fc, 1)


# ---------------------------------------------------------------------------
# Link model and TCP server
# ---------------------------------------------------------------------------
STACK_TIMEOUT = 1.0          # s, the stack gives up on a silent connection
OUTAGE_MIN, OUTAGE_MAX = 0.3, 2.0
REFUSE_MIN, REFUSE_MAX = 0.3, 0.8
W_OUTAGE, W_BUFRESET, W_LOSTANSWER = 0.2, 0.3, 0.5
MAX_CONN = 8
MAX_ADU_LEN = 254            # MBAP length field upper bound (unit id + PDU 253)


class Conn:
    def __init__(self, cid, sock, peer):
        self.cid, self.sock, self.peer = cid, sock, peer
        self.rbuf = bytearray()
        self.wbuf = bytearray()
        self.dead_until = None       # silent; RST at this time


class Server:
    def __init__(self, host, port, drv, state_file, seed, rate):
        self.host, self.drv, self.state_file = host, drv, state_file
        self.rng = random.Random(seed)
        self.rate = rate
        self.sel = selectors.DefaultSelector()
        self.conns = {}
        self.next_cid = 1
        self.t0 = time.monotonic()
        self.outage_until = None
        self.reset_all_at = None
        self.reopen_at = None
        self.lsock = None
        self.port = port
        self.req_no = 0
        self.flag_dump = False
        self.flag_exit = False
        self._open_listener()

    def _open_listener(self):
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((self.host, self.port))
        s.listen(16)
        s.setblocking(False)
        self.port = s.getsockname()[1]
        self.lsock = s
        self.sel.register(s, selectors.EVENT_READ, None)

    def _close_listener(self):
        if self.lsock is not None:
            try:
                self.sel.unregister(self.lsock)
            except (KeyError, ValueError):
                pass
            self.lsock.close()
            self.lsock = None

    def log(self, what, conn=None, extra=''):
        t = time.monotonic() - self.t0
        wall = time.strftime('%H:%M:%S', time.localtime()) + '.%03d' % (int(time.time() * 1000) % 1000)
        c = ('conn=%d(%s:%d)' % (conn.cid, conn.peer[0], conn.peer[1])) if conn else 'conn=all'
        sys.stderr.write('link-event t=%.3fs wall=%s %s event=%s %s\n' % (t, wall, c, what, extra))
        sys.stderr.flush()

    def rst_close(self, c):
        try:
            self.sel.unregister(c.sock)
        except (KeyError, ValueError):
            pass
        try:
            c.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack('ii', 1, 0))
        except OSError:
            pass
        try:
            c.sock.close()
        except OSError:
            pass
        self.conns.pop(c.cid, None)

    def plain_close(self, c):
        try:
            self.sel.unregister(c.sock)
        except (KeyError, ValueError):
            pass
        try:
            c.sock.close()
        except OSError:
            pass
        self.conns.pop(c.cid, None)

    def accept(self):
        for _ in range(16):
            try:
                s, peer = self.lsock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if len(self.conns) >= MAX_CONN:
                try:
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack('ii', 1, 0))
                except OSError:
                    pass
                s.close()
                continue
            s.setblocking(False)
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            c = Conn(self.next_cid, s, peer)
            self.next_cid += 1
            self.conns[c.cid] = c
            self.sel.register(s, selectors.EVENT_READ, c)

    def link_down(self):
        return self.outage_until is not None

    def on_readable(self, c):
        try:
            data = c.sock.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self.plain_close(c)
            return
        if not data:
            self.plain_close(c)
            return
        if self.link_down() or c.dead_until is not None:
            return      # lost on the wire / connection already dead
        c.rbuf += data
        if len(c.rbuf) > 65536:
            self.plain_close(c)
            return
        self.process(c)

    def process(self, c):
        for _ in range(64):
            if c.cid not in self.conns or c.dead_until is not None or self.link_down():
                return
            if len(c.rbuf) < 7:
                return
            tid, proto, length = struct.unpack('>HHH', c.rbuf[:6])
            if length < 2 or length > MAX_ADU_LEN:
                self.plain_close(c)       # not Modbus/TCP: stream unusable
                return
            if len(c.rbuf) < 6 + length:
                return
            frame = bytes(c.rbuf[:6 + length])
            del c.rbuf[:6 + length]
            if proto != 0:
                continue                  # not Modbus protocol: discard silently
            unit = frame[6]
            pdu = frame[7:]
            self.req_no += 1
            ev = self.draw_event()
            if ev == 'outage':
                dur = self.rng.uniform(OUTAGE_MIN, OUTAGE_MAX)
                ref = self.rng.uniform(REFUSE_MIN, REFUSE_MAX)
                now = time.monotonic()
                self.outage_until = now + dur
                self.refuse_for = ref
                self.reset_all_at = now + max(STACK_TIMEOUT, dur)
                self.outage_conns = list(self.conns.keys())
                if self.lsock is not None:
                    try:
                        self.sel.unregister(self.lsock)   # SYNs go unanswered
                    except (KeyError, ValueError):
                        pass
                self.log('link-outage', None,
                         'trigger_conn=%d req#=%d fc=0x%02X executed=no duration=%.2fs '
                         'connections=%s reset_at=+%.2fs refuse_after=%.2fs'
                         % (c.cid, self.req_no, pdu[0], dur,
                            ','.join(str(x) for x in self.outage_conns) or '-',
                            max(STACK_TIMEOUT, dur), ref))
                return
            if ev == 'bufreset':
                self.log('buffer-reset', c, 'req#=%d fc=0x%02X executed=no rst=now' % (self.req_no, pdu[0]))
                self.rst_close(c)
                return
            resp = handle_pdu(self.drv, pdu)
            if ev == 'lostanswer':
                c.dead_until = time.monotonic() + STACK_TIMEOUT
                self.log('answer-lost', c, 'req#=%d fc=0x%02X executed=yes silent, rst in %.2fs'
                         % (self.req_no, pdu[0], STACK_TIMEOUT))
                return
            out = struct.pack('>HHHB', tid, 0, len(resp) + 1, unit) + resp
            self.send(c, out)

    def draw_event(self):
        if self.rate <= 0:
            return None
        if self.rng.random() >= self.rate / 1000.0:
            return None
        r = self.rng.random()
        if r < W_OUTAGE:
            return 'outage'
        if r < W_OUTAGE + W_BUFRESET:
            return 'bufreset'
        return 'lostanswer'

    def send(self, c, data):
        c.wbuf += data
        self.flush(c)

    def flush(self, c):
        while c.wbuf:
            try:
                n = c.sock.send(c.wbuf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self.plain_close(c)
                return
            del c.wbuf[:n]
        if c.cid in self.conns:
            ev = selectors.EVENT_READ | (selectors.EVENT_WRITE if c.wbuf else 0)
            try:
                self.sel.modify(c.sock, ev, c)
            except (KeyError, ValueError):
                pass
        if len(c.wbuf) > 1 << 20:
            self.plain_close(c)

    def timers(self):
        now = time.monotonic()
        for c in list(self.conns.values()):
            if c.dead_until is not None and now >= c.dead_until:
                self.rst_close(c)
        if self.outage_until is not None:
            if self.reset_all_at is not None and now >= self.reset_all_at:
                for cid in self.outage_conns:
                    if cid in self.conns:
                        self.rst_close(self.conns[cid])
                self.reset_all_at = None
            if now >= self.outage_until and self.reopen_at is None:
                # link back: the stack restarts its listener; refuses meanwhile
                self._close_listener()
                self.reopen_at = now + self.refuse_for
            if self.reopen_at is not None and now >= self.reopen_at and self.reset_all_at is None:
                try:
                    self._open_listener()
                except OSError:
                    self.reopen_at = now + 0.05
                    return
                self.outage_until = None
                self.reopen_at = None

    def write_state(self):
        if not self.state_file:
            return
        try:
            tmp = self.state_file + '.tmp'
            with open(tmp, 'w') as f:
                json.dump(self.drv.dump(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except OSError as e:
            sys.stderr.write('state dump failed: %s\n' % e)

    def run(self):
        while not self.flag_exit:
            try:
                events = self.sel.select(timeout=0.02)
            except InterruptedError:
                events = []
            for key, mask in events:
                if self.flag_exit:
                    break
                if key.data is None:
                    if self.lsock is not None and key.fileobj is self.lsock:
                        if not self.link_down():
                            self.accept()
                        # during an outage, SYNs sit unanswered in the backlog
                    continue
                c = key.data
                if c.cid not in self.conns:
                    continue
                if mask & selectors.EVENT_WRITE:
                    self.flush(c)
                if c.cid in self.conns and mask & selectors.EVENT_READ:
                    self.on_readable(c)
            self.timers()
            self.drv.tick()
            if self.flag_dump:
                self.flag_dump = False
                self.write_state()
        self.write_state()


def main():
    ap = argparse.ArgumentParser(description='LMD Ethernet (closed loop) Modbus/TCP simulator')
    ap.add_argument('--listen', default='127.0.0.1:502')
    ap.add_argument('--state', default=None)
    ap.add_argument('--seed', type=int, default=4913)
    ap.add_argument('--glitch-rate', type=float, default=5.0)
    a = ap.parse_args()
    host, _, port = a.listen.rpartition(':')
    host = host or '127.0.0.1'
    srv = Server(host, int(port), Drive(), a.state, a.seed, max(0.0, a.glitch_rate))

    def on_usr1(signum, frame):
        srv.flag_dump = True

    def on_term(signum, frame):
        srv.flag_exit = True

    signal.signal(signal.SIGUSR1, on_usr1)
    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    sys.stdout.write('listening tcp %s:%d\n' % (host, srv.port))
    sys.stdout.flush()
    srv.run()


if __name__ == '__main__':
    main()
