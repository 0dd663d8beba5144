#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet, closed-loop model (LMDCE) - Modbus/TCP server simulator.

Written from the LMD MODBUS/TCP Fieldbus manual (LMD-MODBUS-REV-D) and the public
Modbus specifications only.  Standard library only.  See DECISIONS.md.

Usage: python3 sim.py --listen 127.0.0.1:0 [--state FILE]
"""
import argparse
import asyncio
import json
import os
import signal
import sys
import time

# ---------------------------------------------------------------------------
# Microcontroller / stack limits (see DECISIONS.md, section "MCU behaviour")
MAX_CONNECTIONS = 4          # socket slots in the lightweight TCP/IP stack
RX_BUFFER = 260              # max MODBUS/TCP ADU (7 byte MBAP + 253 PDU)
PROCESS_DELAY = 0.003        # main-loop turnaround before each answer (s)
PARTIAL_FRAME_TIMEOUT = 2.0  # incomplete ADU discarded after this (s)
NVM_SAVE_TIME = 0.25         # 'S' (save to NVM) duration (s)
CP_ERASE_TIME = 0.40         # 'CP' (clear program flash) duration (s)
UPGRADE_TIME = 3.0           # 'UG' upgrade mode waits this long for an image (s)
SC_TIME = 0.5                # configuration test (SC) duration (s)
HOME_TIME = 0.6              # homing sequence duration (s)
PROGRAM_TIME = 1.0           # simulated MCode program run time (EX) (s)

# Exception codes
ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3
DEVICE_FAILURE = 4
DEVICE_BUSY = 6


class MbExc(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


def s32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


# ---------------------------------------------------------------------------
# Register map (section 5).  kind: 'rw' stored parameter, 'ro' status,
# 'wo' write-only command.  nregs = number of 16-bit Modbus registers.
# (addr, mnemonic, nregs, kind, lo, hi, default, signed)
MS_VALUES = {1: 200, 2: 400, 4: 800, 5: 1000, 8: 1600, 10: 2000, 16: 3200,
             25: 5000, 32: 6400, 50: 10000, 64: 12800, 100: 20000, 125: 25000,
             128: 25600, 200: 40000, 250: 50000, 256: 51200, 180: 36000,
             108: 21600, 127: 25400}

REGMAP = [
    (0x0000, 'A', 2, 'rw', 91, 1525878997, 1000000, False),
    (0x0004, 'BY', 1, 'ro', 0, 1, 0, False),
    (0x0005, 'C1', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x0007, 'C2', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x0009, 'CE', 1, 'rw', 0, 1, 1, False),
    (0x000E, 'CW', 1, 'rw', 0, 255, 10, False),
    (0x000F, 'D1', 1, 'rw', 0, 255, 0, False),
    (0x0010, 'D2', 1, 'rw', 0, 255, 0, False),
    (0x0011, 'D3', 1, 'rw', 0, 255, 0, False),
    (0x0012, 'D4', 1, 'rw', 0, 255, 0, False),
    (0x0013, 'D5', 1, 'rw', 0, 255, 0, False),
    (0x0018, 'D', 2, 'rw', 91, 1525878997, 1000000, False),
    (0x001A, 'DB', 1, 'rw', 0, 65000, 10, False),
    (0x001B, 'DC', 1, 'wo', 0, 65535, None, False),
    (0x001C, 'DE', 1, 'rw', 0, 1, 1, False),
    (0x001E, 'EE', 1, 'rw', 0, 1, 0, False),
    (0x001F, 'EF', 1, 'ro', 0, 1, 0, False),
    (0x0021, 'ER', 1, 'rw', 0, 0, 0, False),       # only 0 may be written (clear)
    (0x0024, 'FC', 1, 'rw', 0, 9, 0, False),
    (0x0029, 'HC', 1, 'rw', 0, 100, 5, False),
    (0x002A, 'HI', 1, 'wo', 1, 4, None, False),
    (0x002B, 'HM', 1, 'wo', 1, 4, None, False),
    (0x002C, 'HT', 1, 'rw', 0, 65535, 500, False),
    (0x002D, 'I1', 1, 'ro', 0, 1, 0, False),
    (0x002E, 'I2', 1, 'ro', 0, 1, 0, False),
    (0x002F, 'I3', 1, 'ro', 0, 1, 0, False),
    (0x0030, 'I4', 1, 'ro', 0, 1, 0, False),
    (0x0031, 'I5', 1, 'ro', 0, 1023, 0, False),
    (0x0032, 'I6', 1, 'ro', 0, 1, 0, False),
    (0x0037, 'IC', 1, 'wo', 0, 65535, None, False),
    (0x003B, 'IN', 1, 'ro', 0, 15, 0, False),
    (0x003C, 'IP', 1, 'wo', 0, 65535, None, False),
    (0x003F, 'JE', 1, 'rw', 0, 1, 0, False),
    (0x0042, 'LM', 1, 'rw', 1, 6, 1, False),
    (0x0043, 'MA', 2, 'wo', -2147483648, 2147483647, None, True),
    (0x0045, 'MP', 1, 'ro', 0, 1, 0, False),
    (0x0046, 'MR', 2, 'wo', -2147483648, 2147483647, None, True),
    (0x0048, 'MS', 1, 'rw', 1, 256, 256, False),
    (0x0049, 'MT', 1, 'rw', 0, 65000, 0, False),
    (0x004A, 'MV', 1, 'ro', 0, 1, 0, False),
    (0x004B, 'O1', 1, 'rw', 0, 1, 0, False),
    (0x004C, 'O2', 1, 'rw', 0, 1, 0, False),
    (0x004D, 'O3', 1, 'rw', 0, 1, 0, False),
    (0x004E, 'OF', 1, 'ro', 0, 1, 0, False),
    (0x0056, 'OT', 1, 'rw', 0, 15, 0, False),
    (0x0057, 'P', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x0059, 'PC', 2, 'ro', -2147483648, 2147483647, 0, True),
    (0x005C, 'PM', 1, 'rw', 0, 1, 0, False),
    (0x005F, 'R1', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x0061, 'R2', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x0063, 'R3', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x0065, 'R4', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x0067, 'RC', 1, 'rw', 1, 100, 25, False),
    (0x0076, 'S', 1, 'wo', 0, 65535, None, False),
    (0x0077, 'SF', 1, 'rw', 0, 65000, 15, False),
    (0x0078, 'SL', 2, 'wo', -5000000, 5000000, None, True),
    (0x007A, 'SM', 1, 'rw', 0, 1, 0, False),
    (0x007B, 'ST', 1, 'rw', 0, 0, 0, False),       # only 0 may be written (clear)
    (0x007D, 'TE', 1, 'rw', 0, 43, 0, False),
    (0x0085, 'V', 2, 'ro', -2147483648, 2147483647, 0, True),
    (0x0088, 'VC', 1, 'ro', 0, 1, 0, False),
    (0x0089, 'VI', 2, 'rw', 1, 2559999, 1000, False),
    (0x008B, 'VM', 2, 'rw', 2, 2560000, 768000, False),
    (0x008D, 'WT', 1, 'rw', 0, 84, 80, False),
    # 5.1 hMTechnology (closed loop only)
    (0x008E, 'AS', 1, 'rw', 0, 3, 2, False),
    (0x008F, 'AF', 1, 'ro', 0, 255, 0, False),
    (0x0091, 'CB', 1, 'rw', 0, 3, 1, False),
    (0x0093, 'CF', 1, 'wo', 0, 65535, None, False),
    (0x0095, 'LD', 2, 'rw', 0, 2147483647, 102400, False),
    (0x0097, 'LG', 2, 'rw', 0, 2147483647, 102400, False),
    (0x0099, 'LL', 2, 'ro', -2147483647, 2147483647, 0, True),
    (0x009B, 'LR', 1, 'ro', 0, 1, 0, False),
    (0x009C, 'LT', 2, 'rw', 2, 65535, 2000, False),
    (0x009E, 'MF', 2, 'rw', 306, 2560000, 768000, False),
    (0x00A0, 'MU', 1, 'rw', 0, 2, 0, False),
    (0x00A1, 'SC', 1, 'wo', 0, 65535, None, False),
    (0x00A3, 'TS', 2, 'rw', 0, 255, 0, False),
    (0x00A5, 'TD', 1, 'rw', 0, 1, 1, False),
    (0x00A6, 'TQ', 1, 'rw', 1, 100, 25, False),
    (0x00A7, 'VF', 1, 'rw', 0, 1000, 0, False),
    # 5.2 user variables
    (0x00A8, 'V1', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x00AA, 'V2', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x00AC, 'V3', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x00AE, 'V4', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x00B0, 'V5', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x00B2, 'V6', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x00B4, 'V7', 2, 'rw', -2147483648, 2147483647, 0, True),
    (0x00B6, 'V8', 2, 'rw', -2147483648, 2147483647, 0, True),
]


class Reg:
    __slots__ = ('addr', 'mn', 'n', 'kind', 'lo', 'hi', 'default', 'signed')

    def __init__(self, t):
        (self.addr, self.mn, self.n, self.kind, self.lo, self.hi,
         self.default, self.signed) = t


REGS = [Reg(t) for t in REGMAP]
REG_AT = {r.addr: r for r in REGS}              # first register -> parameter
REG_BY_MN = {r.mn: r for r in REGS}
COVERED = {}
for _r in REGS:
    for _i in range(_r.n):
        COVERED[_r.addr + _i] = _r
# Settings restored by IP (initialize parameters) and saved by S
SETTINGS = [r.mn for r in REGS if r.kind == 'rw' and r.mn not in
            ('C1', 'C2', 'P', 'ER', 'ST', 'O1', 'O2', 'O3', 'OT',
             'R1', 'R2', 'R3', 'R4', 'V1', 'V2', 'V3', 'V4', 'V5', 'V6', 'V7', 'V8')]
NVM_ITEMS = SETTINGS + ['R1', 'R2', 'R3', 'R4']

# Manufacturer-specific (FC 65/66) defaults; see section 4.3 / 4.4
IS_TYPES = {0, 1, 2, 3, 5, 7, 8, 11, 12}
OS_TYPES = {16, 17, 18, 20, 21, 23, 24, 25, 28, 29}

MFG_DEFAULTS = {
    'AO': 0, 'EL': 1000, 'RD': 0, 'AJ': 128, 'AT': 0, 'BE': 0, 'BL': 0, 'BM': 0,
    'DJ': 128, 'DT': 0, 'FS': 0, 'FL': 0,
    'IS': {1: [0, 0, 0], 2: [0, 0, 0], 3: [0, 0, 0], 4: [0, 0, 0], 5: [9, 0]},
    'OS': {1: [16, 0], 2: [16, 0], 3: [16, 0], 4: [16, 0]},
    'MU_B': 0,
    'LS': {0: [0, 0], 1: [0, 0]},     # limit 0 = minus, 1 = plus : [position, enabled]
    'TR': [0, 0, 0],
}
# name -> (access, kind)
MFG = {
    'ESC': 'W', 'AO': 'RW', 'CP': 'W', 'EL': 'RW', 'EX': 'W', 'IS': 'RW', 'IT': 'R',
    'MU': 'RW', 'OS': 'RW', 'PS': 'W', 'RS': 'W', 'E': 'W',
    'RD': 'RW', 'AJ': 'RW', 'AT': 'RW', 'BE': 'RW', 'BL': 'RW', 'BM': 'RW', 'DJ': 'RW',
    'DT': 'RW', 'FS': 'RW', 'HF': 'W', 'AV': 'R', 'FL': 'RW', 'LS': 'RW', 'UG': 'W',
    'VT': 'R', 'TR': 'RW', 'S1': 'RW', 'S2': 'RW', 'S3': 'RW', 'S4': 'RW',
}
# scalar mfg settings: (lo, hi)
MFG_SCALAR = {'AO': (0, 65535), 'EL': (1, 65535), 'RD': (0, 1), 'AJ': (0, 999),
              'AT': (0, 1), 'BE': (0, 1), 'BL': (0, 2147483647), 'BM': (0, 1),
              'DJ': (0, 999), 'DT': (0, 1), 'FS': (-9999, 99999), 'FL': (0, 1)}


def mnemonic_key(b4):
    """Decode the 4 mnemonic bytes (Hi word, Lo word; characters reversed).
    Returns (name, line) or (None, None)."""
    hi0, hi1, lo0, lo1 = b4
    if hi0 != 0x20:
        return None, None
    line = None
    if hi1 != 0x20:
        if 0x31 <= hi1 <= 0x35:
            line = hi1 - 0x30
        else:
            return None, None
    if (lo0, lo1) == (0x1B, 0x20):
        name = 'ESC'
    elif lo0 == 0x20 and lo1 == 0x45:
        name = 'E'
    elif 0x41 <= lo1 <= 0x5A and (0x41 <= lo0 <= 0x5A or 0x31 <= lo0 <= 0x34):
        name = chr(lo1) + chr(lo0)
    else:
        return None, None
    if name not in MFG:
        return None, None
    if line is not None and name not in ('IS', 'OS', 'TR'):
        return None, None
    return name, line


def parse_ints(s, count_min, count_max):
    s = s.strip()
    if s.startswith('='):
        s = s[1:]
    parts = [p.strip() for p in s.split(',')]
    if not (count_min <= len(parts) <= count_max):
        raise MbExc(ILLEGAL_VALUE)
    out = []
    for p in parts:
        if not p:
            raise MbExc(ILLEGAL_VALUE)
        body = p[1:] if p[0] in '+-' else p
        if not body.isdigit() or len(body) > 10:
            raise MbExc(ILLEGAL_VALUE)
        out.append(int(p))
    return out


# ---------------------------------------------------------------------------
class Drive:
    def __init__(self):
        self.v = {r.mn: r.default for r in REGS if r.default is not None}
        self.nvm = {k: self.v[k] for k in NVM_ITEMS}
        self.coils = [0, 0, 0, 0]
        self.mfg = json.loads(json.dumps(MFG_DEFAULTS))
        self.mfg['IS'] = {int(k): v for k, v in self.mfg['IS'].items()}
        self.mfg['OS'] = {int(k): v for k, v in self.mfg['OS'].items()}
        self.mfg['LS'] = {int(k): v for k, v in self.mfg['LS'].items()}
        self.nvm_mfg = json.loads(json.dumps(self.mfg))
        self.counters = {'requests': 0, 'responses': 0, 'exceptions': 0,
                         'framing_errors': 0, 'connections_accepted': 0,
                         'connections_refused': 0, 'nvm_writes': 0}
        # motion state
        self.pos = 0.0
        self.vel = 0.0
        self.mode = 'idle'        # idle | move | slew | home
        self.t_last = time.monotonic()
        self.move = None
        self.slew_target = 0.0
        self.home_end = 0.0
        self.velocity_changing = False
        # busy windows
        self.busy_until = 0.0          # NVM / flash write: writes refused
        self.upgrade_until = 0.0       # upgrade mode: everything refused
        self.sc_until = 0.0
        # program
        self.prog_state = 'stopped'    # stopped | running | paused
        self.prog_remaining = 0.0
        self.prog_t = 0.0

    # ----------------------------------------------------------- motion
    def steps_to_counts(self, dsteps):
        spr = MS_VALUES.get(self.v['MS'], 51200)
        return dsteps * 4 * self.mfg['EL'] / spr

    def _advance_pos(self, newpos):
        old_i = int(round(self.pos))
        new_i = int(round(newpos))
        d = new_i - old_i
        if d:
            self.v['P'] = s32(self.v['P'] + d)
            self.v['C1'] = s32(self.v['C1'] + d)
            self._c2acc = getattr(self, '_c2acc', 0.0) + self.steps_to_counts(d)
            ci = int(self._c2acc)
            self._c2acc -= ci
            self.v['C2'] = s32(self.v['C2'] + ci)
        self.pos = newpos

    def update(self):
        now = time.monotonic()
        dt = now - self.t_last
        self.t_last = now
        if self.prog_state == 'running':
            self.prog_remaining -= dt
            if self.prog_remaining <= 0:
                self.prog_state = 'stopped'
        if self.mode == 'move':
            m = self.move
            t = now - m['t0']
            if t >= m['T']:
                self._advance_pos(m['p0'] + m['dir'] * m['d'])
                self.vel = 0.0
                self.mode = 'idle'
                self.velocity_changing = False
            else:
                s, v, chg = self._profile(m, t)
                self._advance_pos(m['p0'] + m['dir'] * s)
                self.vel = m['dir'] * v
                self.velocity_changing = chg
        elif self.mode == 'slew':
            self._slew_step(dt)
        elif self.mode == 'home':
            if now >= self.home_end:
                self.mode = 'idle'
                self.vel = 0.0
                self.pos = 0.0
                self.v['P'] = 0
                self.velocity_changing = False

    def _profile(self, m, t):
        ta, tc, td, vi, vp, a, dd = m['ta'], m['tc'], m['td'], m['vi'], m['vp'], m['a'], m['dd']
        if t < ta:
            return vi * t + 0.5 * a * t * t, vi + a * t, True
        sa = vi * ta + 0.5 * a * ta * ta
        if t < ta + tc:
            return sa + vp * (t - ta), vp, False
        tt = t - ta - tc
        return sa + vp * tc + vp * tt - 0.5 * dd * tt * tt, vp - dd * tt, True

    def start_move(self, target):
        d = abs(target - int(round(self.pos)))
        direction = 1 if target >= int(round(self.pos)) else -1
        self.pos = float(int(round(self.pos)))
        if d == 0:
            return
        vi = float(self.v['VI'])
        vm = float(self.v['VM'])
        a = float(self.v['A'])
        dd = float(self.v['D'])
        da = (vm * vm - vi * vi) / (2 * a)
        ddc = (vm * vm - vi * vi) / (2 * dd)
        if da + ddc <= d:
            vp = vm
            ta = (vm - vi) / a
            td = (vm - vi) / dd
            tc = (d - da - ddc) / vm
        else:
            vp = (vi * vi + 2 * d * a * dd / (a + dd)) ** 0.5
            ta = (vp - vi) / a
            td = (vp - vi) / dd
            tc = 0.0
        self.move = {'t0': time.monotonic(), 'p0': self.pos, 'd': d, 'dir': direction,
                     'ta': ta, 'tc': tc, 'td': td, 'vi': vi, 'vp': vp, 'a': a, 'dd': dd,
                     'T': ta + tc + td}
        self.mode = 'move'
        self.vel = direction * vi

    def _slew_step(self, dt):
        vt = self.slew_target
        v = self.vel
        if v == vt:
            self._advance_pos(self.pos + v * dt)
            self.velocity_changing = False
            return
        rate = float(self.v['A']) if (abs(vt) > abs(v) and v * vt >= 0) else float(self.v['D'])
        sgn = 1.0 if vt > v else -1.0
        tr = abs(vt - v) / rate
        if dt < tr:
            self._advance_pos(self.pos + v * dt + 0.5 * sgn * rate * dt * dt)
            self.vel = v + sgn * rate * dt
            self.velocity_changing = True
        else:
            self._advance_pos(self.pos + v * tr + 0.5 * sgn * rate * tr * tr + vt * (dt - tr))
            self.vel = vt
            self.velocity_changing = False
            if vt == 0:
                self.mode = 'idle'
                self.pos = float(int(round(self.pos)))

    def start_slew(self, vel):
        if self.mode != 'slew':
            self.mode = 'slew'
            self.pos = float(int(round(self.pos)))
            if vel != 0:
                vi = float(self.v['VI'])
                self.vel = vi if vel > 0 else -vi
                if abs(vel) < vi:
                    self.vel = float(vel)
            else:
                self.vel = 0.0
        self.slew_target = float(vel)
        if vel == 0 and self.vel == 0:
            self.mode = 'idle'

    def stop(self, hard=False):
        if self.mode == 'idle':
            return
        if hard:
            self.mode = 'idle'
            self.vel = 0.0
            self.velocity_changing = False
            self.pos = float(int(round(self.pos)))
            return
        if self.mode == 'home':
            self.mode = 'idle'
            self.vel = 0.0
            return
        self.mode = 'slew'
        self.slew_target = 0.0

    def moving(self):
        return self.mode != 'idle'

    # ----------------------------------------------------------- registers
    def read_value(self, r):
        mn = r.mn
        if mn == 'BY':
            return 1 if self.prog_state != 'stopped' else 0
        if mn == 'EF':
            return 1 if self.v['ER'] else 0
        if mn == 'ER':
            val = self.v['ER']
            self.v['ER'] = 0            # reading the error clears it (manual 0x0021)
            return val
        if mn in ('I1', 'I2', 'I3', 'I4', 'I5', 'I6', 'IN', 'OF', 'LR', 'PC', 'LL'):
            return 0
        if mn == 'MV':
            return 1 if self.moving() else 0
        if mn == 'MP':
            return 1 if self.mode == 'move' else 0
        if mn == 'V':
            return int(round(self.vel))
        if mn == 'VC':
            return 1 if (self.moving() and self.velocity_changing) else 0
        if mn in ('O1', 'O2', 'O3'):
            return self.coils[int(mn[1]) - 1]
        if mn == 'OT':
            return sum(b << i for i, b in enumerate(self.coils))
        if mn == 'AF':
            af = 128                                   # calibration complete
            if self.v['AS'] != 0:
                af |= 16                               # hMT active
                if not self.moving():
                    af |= 64                           # at zero
            return af
        return self.v[mn]

    def check_write(self, r, val, pending):
        """Validate a write; pending = dict of values written in the same request."""
        mn = r.mn
        if r.kind == 'ro':
            raise MbExc(ILLEGAL_ADDRESS)
        if not (r.lo <= val <= r.hi):
            raise MbExc(ILLEGAL_VALUE)
        get = lambda k: pending.get(k, self.v.get(k))
        if mn == 'MS' and val not in MS_VALUES:
            raise MbExc(ILLEGAL_VALUE)
        if mn == 'HT' and val == 1:
            raise MbExc(ILLEGAL_VALUE)
        if mn in ('HT', 'MT') and get('HT') + get('MT') > 65535:
            raise MbExc(ILLEGAL_VALUE)
        if mn in ('VI', 'VM') and not get('VI') < get('VM'):
            raise MbExc(ILLEGAL_VALUE)
        if mn in ('DC', 'IC'):
            t = REG_AT.get(val)
            if t is None or t.mn not in ('R1', 'R2', 'R3', 'R4', 'V1', 'V2', 'V3', 'V4',
                                         'V5', 'V6', 'V7', 'V8'):
                raise MbExc(ILLEGAL_VALUE)
            nv = self.v[t.mn] + (1 if mn == 'IC' else -1)
            if not (t.lo <= nv <= t.hi):
                raise MbExc(ILLEGAL_VALUE)
        # state-dependent refusals
        if mn in ('MA', 'MR', 'HI', 'HM', 'SL'):
            if not self.v['DE'] and not (mn == 'SL' and val == 0):
                raise MbExc(DEVICE_FAILURE)         # drive (bridge) disabled
            if mn != 'SL' and self.moving():
                raise MbExc(DEVICE_BUSY)
            if mn == 'SL' and self.mode in ('move', 'home'):
                raise MbExc(DEVICE_BUSY)
            if time.monotonic() < self.sc_until:
                raise MbExc(DEVICE_BUSY)
        if mn in ('P', 'IP', 'SC', 'MS') and self.moving():
            raise MbExc(DEVICE_BUSY)

    def apply_write(self, r, val):
        mn = r.mn
        if r.kind == 'rw':
            if mn in ('O1', 'O2', 'O3'):
                self.coils[int(mn[1]) - 1] = val
            elif mn == 'OT':
                self.coils = [(val >> i) & 1 for i in range(4)]
            elif mn == 'P':
                self.v['P'] = val
                self.pos = 0.0
            elif mn == 'DE':
                self.v['DE'] = val
                if not val:
                    self.stop(hard=True)
            else:
                self.v[mn] = val
            return
        # write-only commands
        if mn == 'MA':
            self.start_move_abs(val)
        elif mn == 'MR':
            self.start_move_abs(self.v['P'] + val)
        elif mn == 'SL':
            self.start_slew(val)
        elif mn in ('HI', 'HM'):
            self.start_home()
        elif mn in ('DC', 'IC'):
            t = REG_AT[val]
            self.v[t.mn] += (1 if mn == 'IC' else -1)
        elif mn == 'IP':
            for k in SETTINGS:
                self.v[k] = REG_BY_MN[k].default
            self.mfg = json.loads(json.dumps(MFG_DEFAULTS))
            for k in ('IS', 'OS', 'LS'):
                self.mfg[k] = {int(a): b for a, b in self.mfg[k].items()}
        elif mn == 'S':
            self.nvm = {k: self.v[k] for k in NVM_ITEMS}
            self.nvm_mfg = json.loads(json.dumps(self.mfg))
            self.counters['nvm_writes'] += 1
            self.busy_until = time.monotonic() + NVM_SAVE_TIME
        elif mn == 'CF':
            pass                                  # no locked rotor in the simulation
        elif mn == 'SC':
            self.sc_until = time.monotonic() + SC_TIME

    def start_move_abs(self, target):
        # P holds the reference; keep the float integrator aligned with P
        self.pos = 0.0
        self.start_move(target - self.v['P'])

    def start_home(self):
        self.mode = 'home'
        self.vel = float(self.v['VI'])
        self.velocity_changing = False
        self.home_end = time.monotonic() + HOME_TIME

    # ----------------------------------------------------------- mfg specific
    def mfg_read(self, name, line):
        m = self.mfg
        if name in MFG_SCALAR:
            return str(m[name])
        if name == 'IT':
            return '38,41'
        if name == 'VT':
            return '24,48'
        if name == 'AV':
            return str(int(round(self.vel)))
        if name == 'MU':
            return '%d, %d' % (self.v['MU'], m['MU_B'])
        if name == 'IS':
            lines = [line] if line else [1, 2, 3, 4, 5]
            if line and line not in m['IS']:
                raise MbExc(ILLEGAL_ADDRESS)
            return '; '.join('%d, %d, %d' % (n, m['IS'][n][0], m['IS'][n][1]) for n in lines)
        if name == 'OS':
            lines = [line] if line else [1, 2, 3, 4]
            if line and line not in m['OS']:
                raise MbExc(ILLEGAL_ADDRESS)
            return '; '.join('%d, %d, %d' % (n, m['OS'][n][0], m['OS'][n][1]) for n in lines)
        if name in ('S1', 'S2', 'S3', 'S4'):
            c = m['IS'][int(name[1])]
            return '%d, %d, %d' % (c[0], c[1], c[2])
        if name == 'LS':
            return '; '.join('%d, %d, %d' % (k, m['LS'][k][0], m['LS'][k][1]) for k in (0, 1))
        if name == 'TR':
            return '%d, %d, %d' % tuple(m['TR'])
        raise MbExc(ILLEGAL_ADDRESS)

    def mfg_write(self, name, line, data):
        m = self.mfg
        try:
            s = data.decode('ascii')
        except UnicodeDecodeError:
            raise MbExc(ILLEGAL_VALUE)
        now = time.monotonic()
        if name in ('ESC', 'CP', 'PS', 'RS', 'E'):
            if s.strip():
                raise MbExc(ILLEGAL_VALUE)
            if name == 'ESC':
                self.prog_state = 'stopped'
                self.stop()
            elif name == 'E':
                self.prog_state = 'stopped'
            elif name == 'PS':
                if self.prog_state == 'running':
                    self.prog_state = 'paused'
            elif name == 'RS':
                if self.prog_state == 'paused':
                    self.prog_state = 'running'
            elif name == 'CP':
                if self.prog_state != 'stopped':
                    raise MbExc(DEVICE_BUSY)
                self.busy_until = now + CP_ERASE_TIME
            return
        if name == 'EX':
            lab = s.strip().lstrip('=').strip()
            if not (1 <= len(lab) <= 3 and lab.isalnum()):
                raise MbExc(ILLEGAL_VALUE)
            if self.prog_state != 'stopped':
                raise MbExc(DEVICE_BUSY)
            self.prog_state = 'running'
            self.prog_remaining = PROGRAM_TIME
            return
        if name == 'UG':
            if s.strip().lstrip('=').strip() != '2956102':
                raise MbExc(ILLEGAL_VALUE)
            if self.moving() or self.prog_state != 'stopped':
                raise MbExc(DEVICE_BUSY)
            self.upgrade_until = now + UPGRADE_TIME
            return
        if name == 'HF':
            (d,) = parse_ints(s, 1, 1)
            if d not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            if not self.v['DE']:
                raise MbExc(DEVICE_FAILURE)
            if self.moving():
                raise MbExc(DEVICE_BUSY)
            self.start_home()
            return
        if name in MFG_SCALAR:
            (x,) = parse_ints(s, 1, 1)
            lo, hi = MFG_SCALAR[name]
            if not lo <= x <= hi:
                raise MbExc(ILLEGAL_VALUE)
            m[name] = x
            return
        if name == 'MU':
            a, b = parse_ints(s, 2, 2)
            if a not in (0, 1, 2) or b not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            self.v['MU'] = a
            m['MU_B'] = b
            return
        if name == 'IS':
            vals = parse_ints(s, 3, 3)
            n = vals[0]
            if line is not None and n != line:
                raise MbExc(ILLEGAL_VALUE)
            if n == 5:
                if vals[1] not in (9, 10) or vals[2] not in (0, 1):
                    raise MbExc(ILLEGAL_VALUE)
                m['IS'][5] = [vals[1], vals[2]]
                return
            if n not in (1, 2, 3, 4) or vals[1] not in IS_TYPES or vals[2] not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            m['IS'][n][0] = vals[1]
            m['IS'][n][1] = vals[2]
            return
        if name in ('S1', 'S2', 'S3', 'S4'):
            vals = parse_ints(s, 2, 3)
            if vals[0] not in IS_TYPES or vals[1] not in (0, 1) or \
                    (len(vals) == 3 and vals[2] not in (0, 1)):
                raise MbExc(ILLEGAL_VALUE)
            c = m['IS'][int(name[1])]
            c[0], c[1] = vals[0], vals[1]
            if len(vals) == 3:
                c[2] = vals[2]
            return
        if name == 'OS':
            n, t, a = parse_ints(s, 3, 3)
            if line is not None and n != line:
                raise MbExc(ILLEGAL_VALUE)
            if n not in (1, 2, 3, 4) or t not in OS_TYPES or a not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            if t == 28 and n != 3:
                raise MbExc(ILLEGAL_VALUE)
            m['OS'][n] = [t, a]
            return
        if name == 'LS':
            k, pos, en = parse_ints(s, 3, 3)
            if k not in (0, 1) or en not in (0, 1) or not -2147483648 <= pos <= 2147483647:
                raise MbExc(ILLEGAL_VALUE)
            m['LS'][k] = [pos, en]
            return
        if name == 'TR':
            pos, out, st = parse_ints(s, 3, 3)
            if not -2147483648 <= pos <= 2147483647 or out not in (0, 3) or st not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            m['TR'] = [pos, out, st]
            return
        raise MbExc(ILLEGAL_ADDRESS)

    # ----------------------------------------------------------- dump
    def snapshot(self):
        self.update()
        regs = {}
        for r in REGS:
            if r.kind == 'wo':
                continue
            if r.mn == 'ER':
                val = self.v['ER']          # do not clear on dump
            else:
                val = self.read_value(r)
            regs['0x%04X' % r.addr] = {'mcode': r.mn, 'registers': r.n,
                                       'access': r.kind.upper(), 'value': val}
        m = self.mfg
        mfg = {k: m[k] for k in MFG_SCALAR}
        mfg['MU'] = [self.v['MU'], m['MU_B']]
        mfg['IS'] = {str(k): v for k, v in m['IS'].items()}
        mfg['OS'] = {str(k): v for k, v in m['OS'].items()}
        mfg['LS'] = {str(k): v for k, v in m['LS'].items()}
        mfg['TR'] = m['TR']
        mfg['IT'] = '38,41'
        mfg['VT'] = '24,48'
        mfg['AV'] = int(round(self.vel))
        return {
            'device': 'LMD Ethernet closed loop (LMDCE) - Modbus/TCP',
            'holding_registers': regs,
            'coils': {str(i): b for i, b in enumerate(self.coils)},
            'discrete_inputs': {str(i): 0 for i in range(4)},
            'manufacturer_specific': mfg,
            'program': self.prog_state,
            'nvm': {'registers': dict(self.nvm), 'manufacturer_specific': json.loads(
                json.dumps({k: (v if not isinstance(v, dict) else {str(a): b for a, b in v.items()})
                            for k, v in self.nvm_mfg.items()}))},
            'device_identification': {str(k): v.decode() for k, v in DEVICE_ID.items()},
            'diagnostic_counters': dict(self.counters),
        }


DEVICE_ID = {
    0: b'IMS USA',
    1: b'LMDCE571',
    2: b'4.0.0.0',
    3: b'https://novantaims.com/',
    4: b'LMD Ethernet',
    5: b'2013071800042',
    6: b'LMDCM 6.012, Hw: 1.0',
}


# ---------------------------------------------------------------------------
class Server:
    def __init__(self, state_file):
        self.drive = Drive()
        self.state_file = state_file
        self.lock = asyncio.Lock()      # one main loop: one request at a time
        self.conns = {}                 # writer -> last activity

    # --------------------------------------------------------- PDU processing
    def process(self, pdu):
        d = self.drive
        d.update()
        fc = pdu[0]
        now = time.monotonic()
        if now < d.upgrade_until:
            raise MbExc(DEVICE_BUSY)
        if fc == 0x01 or fc == 0x02:
            if len(pdu) != 5:
                raise MbExc(ILLEGAL_VALUE)
            start = int.from_bytes(pdu[1:3], 'big')
            qty = int.from_bytes(pdu[3:5], 'big')
            if not 1 <= qty <= 2000:
                raise MbExc(ILLEGAL_VALUE)
            if start + qty > 4:
                raise MbExc(ILLEGAL_ADDRESS)
            bits = d.coils if fc == 1 else [0, 0, 0, 0]
            val = 0
            for i in range(qty):
                val |= bits[start + i] << i
            return bytes([fc, 1, val])
        if fc == 0x05:
            if len(pdu) != 5:
                raise MbExc(ILLEGAL_VALUE)
            addr = int.from_bytes(pdu[1:3], 'big')
            val = int.from_bytes(pdu[3:5], 'big')
            if val not in (0x0000, 0xFF00):
                raise MbExc(ILLEGAL_VALUE)
            if addr > 3:
                raise MbExc(ILLEGAL_ADDRESS)
            if now < d.busy_until:
                raise MbExc(DEVICE_BUSY)
            d.coils[addr] = 1 if val else 0
            return bytes(pdu)
        if fc == 0x03:
            if len(pdu) != 5:
                raise MbExc(ILLEGAL_VALUE)
            start = int.from_bytes(pdu[1:3], 'big')
            qty = int.from_bytes(pdu[3:5], 'big')
            if not 1 <= qty <= 2:
                raise MbExc(ILLEGAL_VALUE)
            params = self.span(start, qty)
            for r in params:
                if r.kind == 'wo':
                    raise MbExc(ILLEGAL_ADDRESS)
            out = bytearray([3, qty * 2])
            for r in params:
                v = d.read_value(r) & 0xFFFFFFFF
                if r.n == 2:
                    out += (v & 0xFFFF).to_bytes(2, 'big') + (v >> 16).to_bytes(2, 'big')
                else:
                    out += (v & 0xFFFF).to_bytes(2, 'big')
            return bytes(out)
        if fc == 0x10:
            if len(pdu) < 6:
                raise MbExc(ILLEGAL_VALUE)
            start = int.from_bytes(pdu[1:3], 'big')
            qty = int.from_bytes(pdu[3:5], 'big')
            bc = pdu[5]
            if not 1 <= qty <= 2 or bc != 2 * qty or len(pdu) != 6 + bc:
                raise MbExc(ILLEGAL_VALUE)
            params = self.span(start, qty)
            words = [int.from_bytes(pdu[6 + 2 * i:8 + 2 * i], 'big') for i in range(qty)]
            vals = []
            i = 0
            for r in params:
                if r.n == 2:
                    raw = words[i] | (words[i + 1] << 16)
                    v = s32(raw) if r.signed else raw
                else:
                    v = words[i]
                i += r.n
                vals.append((r, v))
            for r, v in vals:
                if r.kind == 'ro':
                    raise MbExc(ILLEGAL_ADDRESS)
            if now < d.busy_until:
                raise MbExc(DEVICE_BUSY)
            pending = {}
            for r, v in vals:
                pending[r.mn] = v
            for r, v in vals:
                d.check_write(r, v, pending)
            for r, v in vals:
                d.apply_write(r, v)
            return bytes(pdu[0:5])
        if fc == 0x2B:
            return self.devid(pdu)
        if fc == 0x41:
            if len(pdu) != 5:
                raise MbExc(ILLEGAL_VALUE)
            name, line = mnemonic_key(pdu[1:5])
            if name is None or 'R' not in MFG[name]:
                raise MbExc(ILLEGAL_ADDRESS)
            if line is not None and name == 'TR' and line != 3:
                raise MbExc(ILLEGAL_ADDRESS)
            txt = d.mfg_read(name, line).encode('ascii')
            return bytes([0x41, len(txt)]) + txt
        if fc == 0x42:
            if len(pdu) < 6:
                raise MbExc(ILLEGAL_VALUE)
            bc = pdu[5]
            if bc > 28 or len(pdu) != 6 + bc:
                raise MbExc(ILLEGAL_VALUE)
            name, line = mnemonic_key(pdu[1:5])
            if name is None or 'W' not in MFG[name]:
                raise MbExc(ILLEGAL_ADDRESS)
            if line is not None and name == 'TR' and line != 3:
                raise MbExc(ILLEGAL_ADDRESS)
            if now < d.busy_until:
                raise MbExc(DEVICE_BUSY)
            d.mfg_write(name, line, bytes(pdu[6:]))
            return bytes([0x42, bc]) + bytes(pdu[1:5])
        raise MbExc(ILLEGAL_FUNCTION)

    def span(self, start, qty):
        """The request must cover whole parameters only (no reserved words,
        no half of a 32-bit parameter)."""
        params = []
        a = start
        end = start + qty
        while a < end:
            r = REG_AT.get(a)
            if r is None or a + r.n > end:
                raise MbExc(ILLEGAL_ADDRESS)
            params.append(r)
            a += r.n
        return params

    def devid(self, pdu):
        if len(pdu) < 2:
            raise MbExc(ILLEGAL_VALUE)
        if pdu[1] != 0x0E:
            raise MbExc(ILLEGAL_FUNCTION)
        if len(pdu) != 4:
            raise MbExc(ILLEGAL_VALUE)
        code, oid = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise MbExc(ILLEGAL_VALUE)
        if code == 4:
            if oid not in DEVICE_ID:
                raise MbExc(ILLEGAL_ADDRESS)
            ids = [oid]
        else:
            last = 2 if code == 1 else 6
            if oid > last:
                oid = 0
            ids = list(range(oid, last + 1))
        out = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)])
        for i in ids:
            out += bytes([i, len(DEVICE_ID[i])]) + DEVICE_ID[i]
        return bytes(out)

    # --------------------------------------------------------- TCP
    async def handle(self, reader, writer):
        d = self.drive
        if len(self.conns) >= MAX_CONNECTIONS:
            # stack out of sockets: recycle the longest-idle one if idle >= 10 s
            oldest = min(self.conns.items(), key=lambda kv: kv[1])
            if time.monotonic() - oldest[1] >= 10.0:
                try:
                    oldest[0].close()
                except Exception:
                    pass
                self.conns.pop(oldest[0], None)
            else:
                d.counters['connections_refused'] += 1
                writer.close()
                return
        d.counters['connections_accepted'] += 1
        self.conns[writer] = time.monotonic()
        try:
            while True:
                try:
                    hdr = await reader.readexactly(7)
                except (asyncio.IncompleteReadError, ConnectionError):
                    break
                except asyncio.CancelledError:
                    break
                self.conns[writer] = time.monotonic()
                tid = hdr[0:2]
                pid = int.from_bytes(hdr[2:4], 'big')
                length = int.from_bytes(hdr[4:6], 'big')
                uid = hdr[6]
                if pid != 0 or length < 2 or length > RX_BUFFER - 6:
                    # not MODBUS or longer than the receive buffer: framing is
                    # lost, the stack drops the connection
                    d.counters['framing_errors'] += 1
                    break
                try:
                    pdu = await asyncio.wait_for(reader.readexactly(length - 1),
                                                 PARTIAL_FRAME_TIMEOUT)
                except asyncio.TimeoutError:
                    d.counters['framing_errors'] += 1
                    break
                except (asyncio.IncompleteReadError, ConnectionError, asyncio.CancelledError):
                    break
                self.conns[writer] = time.monotonic()
                async with self.lock:
                    d.counters['requests'] += 1
                    await asyncio.sleep(PROCESS_DELAY)
                    try:
                        resp = self.process(pdu)
                    except MbExc as e:
                        d.counters['exceptions'] += 1
                        resp = bytes([(pdu[0] | 0x80) & 0xFF, e.code])
                    except Exception:
                        d.counters['exceptions'] += 1
                        resp = bytes([(pdu[0] | 0x80) & 0xFF, DEVICE_FAILURE])
                    d.counters['responses'] += 1
                adu = tid + b'\x00\x00' + (len(resp) + 1).to_bytes(2, 'big') + bytes([uid]) + resp
                try:
                    writer.write(adu)
                    await writer.drain()
                except (ConnectionError, OSError):
                    break
        finally:
            self.conns.pop(writer, None)
            try:
                writer.close()
            except Exception:
                pass

    def dump(self):
        if not self.state_file:
            return
        try:
            data = self.drive.snapshot()
            tmp = self.state_file + '.tmp'
            with open(tmp, 'w') as f:
                json.dump(data, f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except Exception as e:  # never die because of the dump
            print('state dump failed: %s' % e, file=sys.stderr)


async def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--listen', default='127.0.0.1:502')
    ap.add_argument('--state', default=None)
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(':')
    srv = Server(args.state)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, srv.dump)
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    server = await asyncio.start_server(srv.handle, host, int(port), backlog=8)
    p = server.sockets[0].getsockname()[1]
    print('listening tcp %s:%d' % (host, p), flush=True)
    await stop.wait()
    server.close()
    for w in list(srv.conns):
        try:
            w.close()
        except Exception:
            pass
    srv.dump()


if __name__ == '__main__':
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
