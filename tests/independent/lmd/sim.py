#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet - Modbus/TCP server simulator.

Written from the "MODBUS/TCP Fieldbus manual" (LMD-MODBUS-REV-D) and the
public Modbus specifications only.  Standard library only.

    python3 sim.py --listen 127.0.0.1:0 [--state FILE]

See DECISIONS.md for every place where the manual was ambiguous or wrong.
"""
import argparse
import asyncio
import json
import math
import os
import re
import signal
import struct
import sys
import time

INT32_MIN = -2147483648
INT32_MAX = 2147483647

# Modbus exception codes
ILLEGAL_FUNCTION = 0x01
ILLEGAL_ADDRESS = 0x02
ILLEGAL_VALUE = 0x03
DEVICE_FAILURE = 0x04


class MbError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# ---------------------------------------------------------------------------
# Register map (manual section 5, 5.1, 5.2)
# ---------------------------------------------------------------------------
# access: 'RW' read/write, 'RO' read only, 'WO' write only (commands)
# kind:   'par'  persistent parameter (saved by S / reset by IP)
#         'var'  volatile variable
#         'sta'  computed status (read only)
#         'cmd'  command (write only, no stored value)
#         'out'  output point (O1..O3, OT)

class Item:
    def __init__(self, name, addr, nregs, access, kind, lo=None, hi=None,
                 default=0, allowed=None, allow16=False, desc=''):
        self.name = name
        self.addr = addr
        self.nregs = nregs
        self.access = access
        self.kind = kind
        self.lo = lo
        self.hi = hi
        self.default = default
        self.allowed = allowed
        self.allow16 = allow16
        self.desc = desc


MS_ALLOWED = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250,
              256, 180, 108, 127)

ITEMS = [
    Item('A', 0x0000, 2, 'RW', 'par', 91, 1525878997, 1000000, desc='Acceleration'),
    Item('BY', 0x0004, 1, 'RO', 'sta', desc='Busy (program executing)'),
    Item('C1', 0x0005, 2, 'RW', 'var', INT32_MIN, INT32_MAX, 0, desc='Counter 1'),
    Item('C2', 0x0007, 2, 'RW', 'var', INT32_MIN, INT32_MAX, 0, desc='Counter 2 (encoder)'),
    Item('CE', 0x0009, 1, 'RW', 'par', 0, 1, 1, desc='Software reset enable'),
    Item('CW', 0x000E, 1, 'RW', 'par', 0, 255, 10, desc='Clock width'),
    Item('D1', 0x000F, 1, 'RW', 'par', 0, 255, 0, desc='Input 1 debounce'),
    Item('D2', 0x0010, 1, 'RW', 'par', 0, 255, 0, desc='Input 2 debounce'),
    Item('D3', 0x0011, 1, 'RW', 'par', 0, 255, 0, desc='Input 3 debounce'),
    Item('D4', 0x0012, 1, 'RW', 'par', 0, 255, 0, desc='Input 4 debounce'),
    Item('D5', 0x0013, 1, 'RW', 'par', 0, 255, 0, desc='Analog input filter'),
    Item('D', 0x0018, 2, 'RW', 'par', 91, 1525878997, 1000000, desc='Deceleration'),
    Item('DB', 0x001A, 1, 'RW', 'par', 0, 65000, 10, desc='Encoder deadband'),
    Item('DC', 0x001B, 1, 'WO', 'cmd', desc='Decrement variable'),
    Item('DE', 0x001C, 1, 'RW', 'par', 0, 1, 1, desc='Drive enable'),
    Item('EE', 0x001E, 1, 'RW', 'par', 0, 1, 0, desc='Encoder enable'),
    Item('EF', 0x001F, 1, 'RO', 'sta', desc='Error flag'),
    Item('ER', 0x0021, 1, 'RW', 'var', 0, 0, 0, desc='Error code (read or write 0 clears)'),
    Item('FC', 0x0024, 1, 'RW', 'par', 0, 9, 0, desc='Filter capture'),
    Item('HC', 0x0029, 1, 'RW', 'par', 0, 100, 5, desc='Holding current'),
    Item('HI', 0x002A, 1, 'WO', 'cmd', 1, 4, desc='Home to index mark'),
    Item('HM', 0x002B, 1, 'WO', 'cmd', 1, 4, desc='Homing'),
    Item('HT', 0x002C, 1, 'RW', 'par', 0, 65535, 500, desc='Hold current delay time'),
    Item('I1', 0x002D, 1, 'RO', 'sta', desc='Read input 1'),
    Item('I2', 0x002E, 1, 'RO', 'sta', desc='Read input 2'),
    Item('I3', 0x002F, 1, 'RO', 'sta', desc='Read input 3'),
    Item('I4', 0x0030, 1, 'RO', 'sta', desc='Read input 4'),
    Item('I5', 0x0031, 1, 'RO', 'sta', desc='Read analog input'),
    Item('I6', 0x0032, 1, 'RO', 'sta', desc='Read index mark'),
    Item('IC', 0x0037, 1, 'WO', 'cmd', desc='Increment variable'),
    Item('IN', 0x003B, 1, 'RO', 'sta', desc='Read all inputs'),
    Item('IP', 0x003C, 1, 'WO', 'cmd', desc='Initialize parameters'),
    Item('JE', 0x003F, 1, 'RW', 'par', 0, 1, 0, desc='Jog enable'),
    Item('LM', 0x0042, 1, 'RW', 'par', 1, 6, 1, desc='Limit stop mode'),
    Item('MA', 0x0043, 2, 'WO', 'cmd', INT32_MIN, INT32_MAX, desc='Move absolute'),
    Item('MP', 0x0045, 1, 'RO', 'sta', desc='Moving to position'),
    Item('MR', 0x0046, 2, 'WO', 'cmd', INT32_MIN, INT32_MAX, desc='Move relative'),
    Item('MS', 0x0048, 1, 'RW', 'par', None, None, 256, allowed=MS_ALLOWED, desc='Microstep resolution'),
    Item('MT', 0x0049, 1, 'RW', 'par', 0, 65000, 0, desc='Motor settling delay'),
    Item('MV', 0x004A, 1, 'RO', 'sta', desc='Moving'),
    Item('O1', 0x004B, 1, 'RW', 'out', 0, 1, desc='Output 1'),
    Item('O2', 0x004C, 1, 'RW', 'out', 0, 1, desc='Output 2'),
    Item('O3', 0x004D, 1, 'RW', 'out', 0, 1, desc='Output 3'),
    Item('OF', 0x004E, 1, 'RO', 'sta', desc='Output fault'),
    Item('OT', 0x0056, 1, 'RW', 'out', 0, 15, desc='Outputs 1-4 as group'),
    Item('P', 0x0057, 2, 'RW', 'var', INT32_MIN, INT32_MAX, 0, desc='Position counter'),
    Item('PC', 0x0059, 2, 'RO', 'sta', desc='Position capture at trip'),
    Item('PM', 0x005C, 1, 'RW', 'par', 0, 1, 0, desc='Position maintenance'),
    Item('R1', 0x005F, 2, 'RW', 'par', INT32_MIN, INT32_MAX, 0, desc='User register 1'),
    Item('R2', 0x0061, 2, 'RW', 'par', INT32_MIN, INT32_MAX, 0, desc='User register 2'),
    Item('R3', 0x0063, 2, 'RW', 'par', INT32_MIN, INT32_MAX, 0, desc='User register 3'),
    Item('R4', 0x0065, 2, 'RW', 'par', INT32_MIN, INT32_MAX, 0, desc='User register 4'),
    Item('RC', 0x0067, 1, 'RW', 'par', 1, 100, 25, desc='Run current'),
    Item('S', 0x0076, 1, 'WO', 'cmd', desc='Save to NVM'),
    Item('SF', 0x0077, 1, 'RW', 'par', 0, 65000, 15, desc='Stall factor'),
    Item('SL', 0x0078, 2, 'WO', 'cmd', -5000000, 5000000, desc='Slew axis'),
    Item('SM', 0x007A, 1, 'RW', 'par', 0, 1, 0, desc='Stall mode'),
    Item('ST', 0x007B, 1, 'RW', 'var', 0, 1, 0, desc='Stall flag'),
    Item('TE', 0x007D, 1, 'RW', 'par', 0, 63, 0, desc='Trip enable'),
    Item('V', 0x0085, 2, 'RO', 'sta', desc='Axis velocity'),
    Item('VC', 0x0088, 1, 'RO', 'sta', desc='Velocity changing'),
    Item('VI', 0x0089, 2, 'RW', 'par', 1, 2560000 - 1, 1000, desc='Initial velocity'),
    Item('VM', 0x008B, 2, 'RW', 'par', 2, 2560000, 768000, desc='Maximum velocity'),
    Item('WT', 0x008D, 1, 'RW', 'par', 0, 84, 80, desc='Warning temperature'),
    # 5.1 hMTechnology (closed loop)
    Item('AS', 0x008E, 1, 'RW', 'par', 0, 3, 2, desc='hMT mode'),
    Item('AF', 0x008F, 1, 'RO', 'sta', desc='hMT status'),
    Item('CB', 0x0091, 1, 'RW', 'par', 0, 3, 1, desc='Control bounds'),
    Item('CF', 0x0093, 1, 'WO', 'cmd', desc='Clear locked rotor'),
    Item('LD', 0x0095, 2, 'RW', 'par', 0, INT32_MAX, 102400, desc='Lead limit'),
    Item('LG', 0x0097, 2, 'RW', 'par', 0, INT32_MAX, 102400, desc='Lag limit'),
    Item('LL', 0x0099, 2, 'RO', 'sta', desc='Position lead/lag'),
    Item('LR', 0x009B, 1, 'RO', 'sta', desc='Locked rotor'),
    Item('LT', 0x009C, 2, 'RW', 'par', 2, 65535, 2000, allow16=True, desc='Locked rotor timeout'),
    Item('MF', 0x009E, 2, 'RW', 'par', 306, 2560000, 768000, desc='Make up frequency'),
    Item('MU', 0x00A0, 1, 'RW', 'par', 0, 2, 0, desc='Make up mode'),
    Item('SC', 0x00A1, 1, 'WO', 'cmd', desc='Start configuration test'),
    Item('TS', 0x00A3, 2, 'RW', 'par', 0, 255, 0, allow16=True, desc='Torque speed'),
    Item('TD', 0x00A5, 1, 'RW', 'par', 0, 1, 1, desc='Torque direction'),
    Item('TQ', 0x00A6, 1, 'RW', 'par', 1, 100, 25, desc='Torque percent'),
    Item('VF', 0x00A7, 1, 'RW', 'par', 0, 1000, 0, desc='hMT velocity filter'),
]
# 5.2 user variables V1..V8
for _i in range(8):
    ITEMS.append(Item('V%d' % (_i + 1), 0x00A8 + 2 * _i, 2, 'RW', 'var',
                      INT32_MIN, INT32_MAX, 0, desc='User variable %d' % (_i + 1)))

BY_NAME = {it.name: it for it in ITEMS}
REG_OWNER = {}          # register address -> (Item, word index 0=low word)
for _it in ITEMS:
    for _k in range(_it.nregs):
        assert _it.addr + _k not in REG_OWNER
        REG_OWNER[_it.addr + _k] = (_it, _k)
MAX_REG_ADDR = 0x00B7

# Variables that DC / IC may act on (value written = target register address)
IC_DC_TARGETS = ('C1', 'C2', 'P', 'R1', 'R2', 'R3', 'R4') + tuple('V%d' % i for i in range(1, 9))

# ---------------------------------------------------------------------------
# Manufacturer specific settings (FC 65 / 66)
# ---------------------------------------------------------------------------
INPUT_TYPES = (0, 1, 2, 3, 5, 7, 8, 11, 12)
OUTPUT_TYPES = (16, 17, 18, 20, 21, 23, 24, 25, 28, 29)   # 26/27 reserved

MFG_DEFAULTS = {
    'AO': 0,
    'EL': 1000,
    'IN_SETUP': {'1': [0, 0, 0], '2': [0, 0, 0], '3': [0, 0, 0], '4': [0, 0, 0]},
    'ANALOG_SETUP': [9, 0],
    'OUT_SETUP': {'1': [16, 1], '2': [16, 1], '3': [16, 1]},
    'MU_B': 0,
    'RD': 0, 'AJ': 128, 'AT': 0, 'BE': 0, 'BL': 0, 'BM': 0, 'DJ': 128, 'DT': 0,
    'FS': 0, 'FL': 0,
    'LS': {'0': [0, 0], '1': [0, 0]},
    'TR': [0, 0, 0],
}

SIMPLE_MFG = {   # mnemonic -> (lo, hi)
    'AO': (0, 65535),
    'EL': (1, 65535),
    'RD': (0, 1),
    'AJ': (1, 999),
    'AT': (0, 1),
    'BE': (0, 1),
    'BL': (0, INT32_MAX),
    'BM': (0, 1),
    'DJ': (1, 999),
    'DT': (0, 1),
    'FS': (INT32_MIN, INT32_MAX),
    'FL': (0, 1),
}

DEVICE_ID = [
    b'IMS USA',                     # 0 VendorName
    b'LMDCE572',                    # 1 ProductCode  (LMDxExxx)
    b'4.0.0.0',                     # 2 MajorMinorRevision
    b'https://novantaims.com/',     # 3 VendorUrl
    b'LMD Ethernet',                # 4 ProductName
    b'SN0000000001',                # 5 ModelName (manual: serial number)
    b'LMDCM 6.004, Hw: 1.0',        # 6 UserApplicationName
]

BRIDGE_TEMP = 52      # deg C (manual IT example "52,37")
CPU_TEMP = 37
AUX_VOLT = 22         # manual VT example "22,37"
SUPPLY_VOLT = 37

UPGRADE_KEY = '2956102'

NUM_RE = re.compile(r'^[+-]?\d{1,11}$')


def to_u16_words(value, nregs):
    if nregs == 1:
        return [value & 0xFFFF]
    u = value & 0xFFFFFFFF
    return [u & 0xFFFF, (u >> 16) & 0xFFFF]     # low word first (manual 4.2.4/4.2.5)


def from_words(words):
    if len(words) == 1:
        return words[0]
    u = words[0] | (words[1] << 16)
    return u - 0x100000000 if u & 0x80000000 else u


# ---------------------------------------------------------------------------
# Motion model
# ---------------------------------------------------------------------------
class Profile:
    """Piecewise constant-acceleration profile.  phases: (dur, p0, v0, a)."""

    def __init__(self, t0, phases, kind, final_pos=None):
        self.t0 = t0
        self.phases = phases
        self.kind = kind            # 'move', 'slew', 'home'
        self.final_pos = final_pos  # exact target for moves

    def eval(self, t):
        dt = max(0.0, t - self.t0)
        for dur, p0, v0, a in self.phases:
            if dt < dur:
                return p0 + v0 * dt + 0.5 * a * dt * dt, v0 + a * dt, (a != 0), False
            dt -= dur
        if self.final_pos is not None:
            return float(self.final_pos), 0.0, False, True
        dur, p0, v0, a = self.phases[-1]
        return p0 + v0 * dur + 0.5 * a * dur * dur, 0.0, False, True


def ramp_phases(p, v_from, v_to, acc, dec):
    """Phases bringing velocity from v_from to v_to (signed)."""
    phases = []
    if v_from != 0 and v_to != 0 and (v_from > 0) != (v_to > 0):
        dur = abs(v_from) / dec
        a = -math.copysign(dec, v_from)
        phases.append((dur, p, v_from, a))
        p = p + v_from * dur + 0.5 * a * dur * dur
        v_from = 0.0
    if v_to == v_from:
        return phases, p
    if abs(v_to) > abs(v_from):
        rate = acc
    else:
        rate = dec
    dur = abs(v_to - v_from) / rate
    a = math.copysign(rate, v_to - v_from)
    phases.append((dur, p, v_from, a))
    p = p + v_from * dur + 0.5 * a * dur * dur
    return phases, p


def move_phases(p_start, target, vi, vm, acc, dec):
    dist = abs(target - p_start)
    s = 1.0 if target >= p_start else -1.0
    v0 = float(min(vi, vm))
    vp = math.sqrt(v0 * v0 + dist * 2.0 * acc * dec / (acc + dec))
    vp = min(float(vm), vp)
    if vp < v0:
        vp = v0
    ta = (vp - v0) / acc
    da = (vp * vp - v0 * v0) / (2 * acc)
    td = (vp - v0) / dec
    dd = (vp * vp - v0 * v0) / (2 * dec)
    dc = max(0.0, dist - da - dd)
    tc = dc / vp if vp > 0 else 0.0
    p1 = p_start + s * da
    p2 = p1 + s * dc
    return [(ta, float(p_start), s * v0, s * acc),
            (tc, p1, s * vp, 0.0),
            (td, p2, s * vp, -s * dec)]


# ---------------------------------------------------------------------------
# Device
# ---------------------------------------------------------------------------
class Device:
    def __init__(self):
        self.factory = {it.name: it.default for it in ITEMS if it.kind == 'par'}
        self.values = {}
        for it in ITEMS:
            if it.kind in ('par', 'var'):
                self.values[it.name] = it.default
        self.mfg = json.loads(json.dumps(MFG_DEFAULTS))
        self.nvm = {'registers': dict(self.factory), 'mfg': json.loads(json.dumps(MFG_DEFAULTS))}
        self.out_bits = [0, 0, 0, 0]        # commanded state of outputs 1..4
        self.inputs = [0, 0, 0, 0]          # physical inputs 1..4 (nothing wired)
        self.analog = 0
        self.index_mark = 0
        self.pc = 0                         # position capture
        self.lead_lag = 0
        self.locked_rotor = 0
        self.output_fault = 0
        self.busy = 0
        self.program_paused = 0
        self.profile = None
        self.last_p_int = 0
        self.c2_frac = 0.0

    # ---- motion bookkeeping ------------------------------------------------
    def update(self):
        if self.profile is None:
            return
        pos, vel, changing, done = self.profile.eval(time.monotonic())
        p_int = int(round(pos))
        p_int = max(INT32_MIN, min(INT32_MAX, p_int))
        self._apply_position(p_int)
        if done:
            self.profile = None

    def _apply_position(self, p_int):
        delta = p_int - self.values['P']
        if delta:
            self.values['P'] = p_int
            c1 = self.values['C1'] + delta
            self.values['C1'] = ((c1 - INT32_MIN) % (1 << 32)) + INT32_MIN
            # encoder: 2048 lines x4 = 8192 counts/rev, 200 full steps/rev
            self.c2_frac += delta * 8192.0 / (200.0 * self.values['MS'])
            whole = int(self.c2_frac)
            self.c2_frac -= whole
            c2 = self.values['C2'] + whole
            self.values['C2'] = ((c2 - INT32_MIN) % (1 << 32)) + INT32_MIN

    def motion_state(self):
        """(moving, velocity(int), velocity_changing, moving_to_position)"""
        self.update()
        if self.profile is None:
            return 0, 0, 0, 0
        pos, vel, changing, done = self.profile.eval(time.monotonic())
        if done:
            return 0, 0, 0, 0
        return 1, int(round(vel)), 1 if changing else 0, 1 if self.profile.kind in ('move', 'home') else 0

    def current_velocity(self):
        if self.profile is None:
            return 0.0
        pos, vel, changing, done = self.profile.eval(time.monotonic())
        return 0.0 if done else vel

    def stop_now(self):
        self.update()
        self.profile = None

    def check_can_move(self):
        if self.values['DE'] == 0:
            raise MbError(DEVICE_FAILURE)
        if self.locked_rotor:
            raise MbError(DEVICE_FAILURE)

    def start_move(self, target, kind='move'):
        self.update()
        self.check_can_move()
        if self.profile is not None:
            raise MbError(DEVICE_FAILURE)      # motion in progress
        start = self.values['P']
        if target == start:
            return
        ph = move_phases(start, target, self.values['VI'], self.values['VM'],
                         self.values['A'], self.values['D'])
        self.profile = Profile(time.monotonic(), ph, kind, final_pos=target)

    def start_slew(self, vel):
        self.update()
        if vel != 0:
            self.check_can_move()
        if self.profile is not None and self.profile.kind != 'slew':
            raise MbError(DEVICE_FAILURE)
        now = time.monotonic()
        if self.profile is None:
            if vel == 0:
                return
            p = float(self.values['P'])
            v_from = math.copysign(min(float(self.values['VI']), abs(vel)), vel)
        else:
            p, v_from, _, _ = self.profile.eval(now)
        phases, p_end = ramp_phases(p, v_from, float(vel), float(self.values['A']),
                                    float(self.values['D']))
        if vel != 0:
            phases.append((float('inf'), p_end, float(vel), 0.0))
            self.profile = Profile(now, phases, 'slew')
        else:
            if not phases:
                self.profile = None
                return
            self.profile = Profile(now, phases, 'slew', final_pos=int(round(p_end)))

    # ---- I/O ---------------------------------------------------------------
    def output_type(self, line):            # line 1..4
        if line == 4:
            return 16, 1
        t, act = self.mfg['OUT_SETUP'][str(line)]
        return t, act

    def output_logic(self, line):
        t, _ = self.output_type(line)
        moving, vel, vc, mp = self.motion_state()
        if t == 16:
            return self.out_bits[line - 1]
        if t == 17:
            return moving
        if t == 18:
            return self.error_flag()
        if t == 20:
            return vc
        if t == 21:
            return self.locked_rotor
        if t == 23:
            return mp
        if t == 24:
            return 1 if self.values['AS'] != 0 else 0
        if t == 29:
            return 1 if (self.attention_bits() & self.mfg['AO']) else 0
        return 0     # 25 make-up active, 28 trip: never active in the simulation

    def write_output(self, line, bit):
        t, _ = self.output_type(line)
        if t != 16:
            raise MbError(DEVICE_FAILURE)    # point not configured as general purpose output
        self.out_bits[line - 1] = bit

    def input_logic(self, line):
        return self.inputs[line - 1]

    def error_flag(self):
        return 1 if self.values['ER'] != 0 else 0

    def hmt_status(self):
        af = 64 | 128        # at zero, calibration complete
        if self.values['AS'] != 0:
            af |= 16
        if self.locked_rotor:
            af |= 8
        return af

    def attention_bits(self):
        moving, vel, vc, mp = self.motion_state()
        bits = 0
        if self.error_flag():
            bits |= 1
        if self.locked_rotor:
            bits |= 2
        if self.values['AS'] != 0:
            bits |= 16
        if BRIDGE_TEMP >= 85:
            bits |= 64
        if not moving:
            bits |= 512      # current reduction (holding current) active when stopped
        if self.values['DE'] == 0:
            bits |= 2048
        if BRIDGE_TEMP >= self.values['WT']:
            bits |= 4096
        if moving:
            bits |= 16384
        if self.values['ST']:
            bits |= 32768
        return bits

    # ---- register read / write -----------------------------------------------
    def read_item(self, it):
        n = it.name
        if it.kind in ('par', 'var'):
            v = self.values[n]
            if n == 'P':
                self.update()
                v = self.values['P']
            elif n in ('C1', 'C2'):
                self.update()
                v = self.values[n]
            return v
        if n == 'BY':
            return self.busy
        if n == 'EF':
            return self.error_flag()
        if n in ('I1', 'I2', 'I3', 'I4'):
            return self.input_logic(int(n[1]))
        if n == 'I5':
            return self.analog
        if n == 'I6':
            return self.index_mark
        if n == 'IN':
            return sum(self.input_logic(i) << (i - 1) for i in range(1, 5))
        if n == 'MP':
            return self.motion_state()[3]
        if n == 'MV':
            return self.motion_state()[0]
        if n == 'VC':
            return self.motion_state()[2]
        if n == 'V':
            return self.motion_state()[1]
        if n in ('O1', 'O2', 'O3'):
            return self.output_logic(int(n[1]))
        if n == 'OT':
            return sum(self.output_logic(i) << (i - 1) for i in range(1, 5))
        if n == 'OF':
            return self.output_fault
        if n == 'PC':
            return self.pc
        if n == 'AF':
            return self.hmt_status()
        if n == 'LL':
            return self.lead_lag
        if n == 'LR':
            return self.locked_rotor
        return 0

    def read_registers(self, start, qty):
        words = []
        after = []
        for a in range(start, start + qty):
            own = REG_OWNER.get(a)
            if own is None or own[0].access == 'WO':
                raise MbError(ILLEGAL_ADDRESS)
        cache = {}
        for a in range(start, start + qty):
            it, k = REG_OWNER[a]
            if it.name not in cache:
                cache[it.name] = to_u16_words(self.read_item(it), it.nregs)
                if it.name == 'ER':
                    after.append('ER')
            words.append(cache[it.name][k])
        for n in after:        # ER: "must be read or set to 0 to clear"
            self.values['ER'] = 0
        return words

    def check_value(self, it, v):
        if it.allowed is not None:
            if v not in it.allowed:
                raise MbError(ILLEGAL_VALUE)
            return
        if it.lo is not None and (v < it.lo or v > it.hi):
            raise MbError(ILLEGAL_VALUE)

    def write_registers(self, start, words):
        qty = len(words)
        # split into whole items
        plan = []
        a = start
        while a < start + qty:
            own = REG_OWNER.get(a)
            if own is None:
                raise MbError(ILLEGAL_ADDRESS)
            it, k = own
            if k != 0 or it.access == 'RO':
                raise MbError(ILLEGAL_ADDRESS)
            remaining = start + qty - a
            if it.nregs == 2 and remaining < 2:
                if not it.allow16:
                    raise MbError(ILLEGAL_ADDRESS)
                plan.append((it, words[a - start]))
                a += 1
                continue
            plan.append((it, from_words(words[a - start:a - start + it.nregs])))
            a += it.nregs
        # validate all first (all-or-nothing)
        for it, v in plan:
            self.check_value(it, v)
            self.validate_special(it, v, plan)
        for it, v in plan:
            self.apply_write(it, v)

    def validate_special(self, it, v, plan):
        n = it.name
        pending = {p.name: pv for p, pv in plan}
        if n == 'HT':
            if v == 1:
                raise MbError(ILLEGAL_VALUE)             # 0 or 2..65535
            mt = pending.get('MT', self.values['MT'])
            if v + mt > 65535:
                raise MbError(ILLEGAL_VALUE)
        elif n == 'MT':
            ht = pending.get('HT', self.values['HT'])
            if v + ht > 65535:
                raise MbError(ILLEGAL_VALUE)
        elif n == 'VI':
            if v >= self.values['VM']:
                raise MbError(ILLEGAL_VALUE)
        elif n == 'VM':
            if v <= self.values['VI']:
                raise MbError(ILLEGAL_VALUE)
        elif n == 'DC' or n == 'IC':
            own = REG_OWNER.get(v)
            if own is None or own[1] != 0 or own[0].name not in IC_DC_TARGETS:
                raise MbError(ILLEGAL_VALUE)
        elif n == 'MS':
            self.update()
            if self.profile is not None:
                raise MbError(DEVICE_FAILURE)

    def apply_write(self, it, v):
        n = it.name
        if it.kind in ('par', 'var'):
            if n == 'P':
                self.update()
                if self.profile is not None:
                    raise MbError(DEVICE_FAILURE)
                self.values['P'] = v
                return
            if n in ('C1', 'C2'):
                self.update()
                if n == 'C2':
                    self.c2_frac = 0.0
            if n == 'DE' and v == 0:
                self.stop_now()
            self.values[n] = v
            return
        if n in ('O1', 'O2', 'O3'):
            self.write_output(int(n[1]), v)
            return
        if n == 'OT':
            for line in range(1, 5):
                if self.output_type(line)[0] == 16:
                    self.out_bits[line - 1] = (v >> (line - 1)) & 1
            return
        # commands
        if n == 'MA':
            self.start_move(v)
        elif n == 'MR':
            self.update()
            target = self.values['P'] + v
            if target < INT32_MIN or target > INT32_MAX:
                raise MbError(ILLEGAL_VALUE)
            self.start_move(target)
        elif n == 'SL':
            self.start_slew(v)
        elif n in ('HM', 'HI'):
            self.start_move(0, kind='home')
        elif n in ('DC', 'IC'):
            tgt = REG_OWNER[v][0]
            if tgt.name == 'P':
                self.update()
                if self.profile is not None:
                    raise MbError(DEVICE_FAILURE)
            nv = self.values[tgt.name] + (1 if n == 'IC' else -1)
            if nv < INT32_MIN or nv > INT32_MAX:
                raise MbError(DEVICE_FAILURE)
            self.values[tgt.name] = nv
        elif n == 'IP':
            self.initialize_parameters()
        elif n == 'S':
            self.save()
        elif n == 'CF':
            self.locked_rotor = 0
        elif n == 'SC':
            pass            # configuration test: calibration completes instantly

    def initialize_parameters(self):
        self.stop_now()
        for k, v in self.factory.items():
            self.values[k] = v
        self.mfg = json.loads(json.dumps(MFG_DEFAULTS))

    def save(self):
        self.nvm = {'registers': {k: self.values[k] for k in self.factory},
                    'mfg': json.loads(json.dumps(self.mfg))}

    # ---- coils / discrete inputs ------------------------------------------
    def read_coils(self, start, qty):
        return [self.output_logic(i + 1) for i in range(start, start + qty)]

    def read_inputs(self, start, qty):
        return [self.input_logic(i + 1) for i in range(start, start + qty)]

    # ---- manufacturer specific ---------------------------------------------
    def mfg_read(self, mn):
        m = self.mfg
        if mn in SIMPLE_MFG:
            return str(m[mn])
        if mn == 'IT':
            return '%d,%d' % (BRIDGE_TEMP, CPU_TEMP)
        if mn == 'VT':
            return '%d,%d' % (AUX_VOLT, SUPPLY_VOLT)
        if mn == 'AV':
            if self.values['AS'] == 0:
                return '0'
            self.update()
            return str(int(round(self.current_velocity())))
        if mn == 'MU':
            return '%d, %d' % (self.values['MU'], m['MU_B'])
        if mn == 'TR':
            return ', '.join(str(x) for x in m['TR'])
        if mn == 'LS':
            return ', '.join('%s, %d, %d' % (d, m['LS'][d][0], m['LS'][d][1]) for d in ('0', '1'))
        line = self.io_line(mn)
        if line is not None:
            kind, n = line
            if kind == 'I':
                if n == 5:
                    return ', '.join(str(x) for x in m['ANALOG_SETUP'])
                return ', '.join(str(x) for x in m['IN_SETUP'][str(n)])
            return ', '.join(str(x) for x in m['OUT_SETUP'][str(n)])
        if mn == 'IS':
            parts = ['%d,%d,%d' % (i, m['IN_SETUP'][str(i)][0], m['IN_SETUP'][str(i)][1])
                     for i in range(1, 5)]
            parts.append('5,%d,%d' % tuple(m['ANALOG_SETUP']))
            return ';'.join(parts)
        if mn == 'OS':
            return ';'.join('%d,%d,%d' % (i, m['OUT_SETUP'][str(i)][0], m['OUT_SETUP'][str(i)][1])
                            for i in range(1, 4))
        raise MbError(ILLEGAL_ADDRESS)

    @staticmethod
    def io_line(mn):
        """S1..S5 / IS1..IS5 -> ('I', n); OS1..OS3 -> ('O', n)."""
        mt = re.fullmatch(r'(?:S|IS)([1-5])', mn)
        if mt:
            return 'I', int(mt.group(1))
        mt = re.fullmatch(r'OS([1-3])', mn)
        if mt:
            return 'O', int(mt.group(1))
        return None

    @staticmethod
    def parse_params(data, n_min, n_max):
        """'=a,b,c' -> [ints].  The leading '=' is mandatory for settings."""
        if not data.startswith('='):
            raise MbError(ILLEGAL_VALUE)
        body = data[1:].strip()
        parts = [p.strip() for p in body.split(',')]
        if len(parts) < n_min or len(parts) > n_max:
            raise MbError(ILLEGAL_VALUE)
        out = []
        for p in parts:
            if not NUM_RE.match(p):
                raise MbError(ILLEGAL_VALUE)
            out.append(int(p))
        return out

    @staticmethod
    def in_range(v, lo, hi):
        if v < lo or v > hi:
            raise MbError(ILLEGAL_VALUE)

    def check_input_setup(self, n, vals):
        if n == 5:
            if len(vals) != 2 or vals[0] not in (9, 10) or vals[1] not in (0, 1):
                raise MbError(ILLEGAL_VALUE)
            return vals
        if vals[0] not in INPUT_TYPES:
            raise MbError(ILLEGAL_VALUE)
        for x in vals[1:]:
            self.in_range(x, 0, 1)
        return vals

    def check_output_setup(self, n, vals):
        t, act = vals
        if t not in OUTPUT_TYPES or (t == 28 and n != 3):
            raise MbError(ILLEGAL_VALUE)
        self.in_range(act, 0, 1)
        return vals

    def mfg_write(self, mn, data):
        m = self.mfg
        no_param = ('\x1b', 'CP', 'PS', 'RS', 'E')
        if mn in no_param:
            if data:
                raise MbError(ILLEGAL_VALUE)
            if mn == '\x1b':
                self.stop_now()
                self.busy = 0
                self.program_paused = 0
            elif mn == 'CP':
                pass              # program space is already empty
            elif mn == 'PS':
                if self.busy:
                    self.program_paused = 1
            elif mn == 'RS':
                self.program_paused = 0
            elif mn == 'E':
                self.busy = 0
                self.program_paused = 0
            return
        if mn in ('IT', 'VT', 'AV'):
            raise MbError(ILLEGAL_ADDRESS)            # read only
        if mn == 'EX':
            arg = data[1:].strip() if data[:1] in (' ', '=') else None
            if not arg or not (re.fullmatch(r'[A-Za-z][A-Za-z0-9]', arg) or re.fullmatch(r'\d{1,4}', arg)):
                raise MbError(ILLEGAL_VALUE)
            raise MbError(DEVICE_FAILURE)   # no MCode program in memory: label/address unknown
        if mn == 'UG':
            arg = data[1:].strip() if data[:1] in (' ', '=') else None
            if arg != UPGRADE_KEY:
                raise MbError(ILLEGAL_VALUE)
            raise MbError(DEVICE_FAILURE)   # firmware upgrade not possible in the simulator
        if mn == 'HF':
            if data[:1] not in (' ', '='):
                raise MbError(ILLEGAL_VALUE)
            arg = data[1:].strip()
            if not re.fullmatch(r'[1-4]', arg):
                raise MbError(ILLEGAL_VALUE)
            self.start_move(0, kind='home')
            return
        if mn in SIMPLE_MFG:
            (v,) = self.parse_params(data, 1, 1)
            self.in_range(v, *SIMPLE_MFG[mn])
            m[mn] = v
            return
        if mn == 'MU':
            vals = self.parse_params(data, 1, 2)
            self.in_range(vals[0], 0, 2)
            if len(vals) == 2:
                self.in_range(vals[1], 0, 1)
            self.values['MU'] = vals[0]
            if len(vals) == 2:
                m['MU_B'] = vals[1]
                if vals[1] == 1:
                    self.lead_lag = 0
            return
        if mn == 'TR':
            vals = self.parse_params(data, 3, 3)
            for x in vals:
                self.in_range(x, INT32_MIN, INT32_MAX)
            m['TR'] = vals
            return
        if mn == 'LS':
            d, pos, en = self.parse_params(data, 3, 3)
            self.in_range(d, 0, 1)
            self.in_range(pos, INT32_MIN, INT32_MAX)
            self.in_range(en, 0, 1)
            m['LS'][str(d)] = [pos, en]
            return
        line = self.io_line(mn)
        if line is not None:
            kind, n = line
            if kind == 'I':
                if n == 5:
                    vals = self.parse_params(data, 2, 2)
                    m['ANALOG_SETUP'] = self.check_input_setup(5, vals)
                else:
                    vals = self.parse_params(data, 2, 3)
                    self.check_input_setup(n, vals)
                    cur = m['IN_SETUP'][str(n)]
                    m['IN_SETUP'][str(n)] = vals + cur[len(vals):]
            else:
                vals = self.parse_params(data, 2, 2)
                m['OUT_SETUP'][str(n)] = self.check_output_setup(n, vals)
            return
        if mn == 'IS':
            vals = self.parse_params(data, 3, 3)
            n = vals[0]
            if n == 5:
                m['ANALOG_SETUP'] = self.check_input_setup(5, vals[1:])
            elif 1 <= n <= 4:
                self.check_input_setup(n, vals[1:])
                m['IN_SETUP'][str(n)] = vals[1:] + m['IN_SETUP'][str(n)][2:]
            else:
                raise MbError(ILLEGAL_VALUE)
            return
        if mn == 'OS':
            vals = self.parse_params(data, 3, 3)
            n = vals[0]
            if not 1 <= n <= 3:
                raise MbError(ILLEGAL_VALUE)
            m['OUT_SETUP'][str(n)] = self.check_output_setup(n, vals[1:])
            return
        raise MbError(ILLEGAL_ADDRESS)

    # ---- state dump ----------------------------------------------------------
    def state(self):
        self.update()
        regs = {}
        for it in ITEMS:
            entry = {'name': it.name, 'access': it.access, 'registers': it.nregs}
            if it.access == 'WO':
                entry['value'] = None
            else:
                if it.name == 'ER':
                    v = self.values['ER']        # do not clear on dump
                else:
                    v = self.read_item(it)
                entry['value'] = v
                entry['words'] = to_u16_words(v, it.nregs)
            regs['0x%04X' % it.addr] = entry
        return {
            'device': 'Lexium MDrive Ethernet (LMD) - Modbus/TCP simulator',
            'holding_registers': regs,
            'coils': {str(i): self.output_logic(i + 1) for i in range(4)},
            'coils_commanded': {str(i): self.out_bits[i] for i in range(4)},
            'discrete_inputs': {str(i): self.input_logic(i + 1) for i in range(4)},
            'manufacturer_specific': self.mfg,
            'nvm': self.nvm,
            'internal': {
                'moving': self.profile is not None,
                'motion_kind': self.profile.kind if self.profile else None,
                'locked_rotor': self.locked_rotor,
                'lead_lag': self.lead_lag,
                'program_busy': self.busy,
                'program_paused': self.program_paused,
                'position_capture': self.pc,
            },
            'device_identification': {str(i): v.decode() for i, v in enumerate(DEVICE_ID)},
        }


# ---------------------------------------------------------------------------
# PDU processing
# ---------------------------------------------------------------------------
def decode_mnemonic(b4):
    """ASCII of the mnemonic is sent in reverse order, padded with 0x20."""
    s = bytes(reversed(b4))
    try:
        txt = s.decode('ascii')
    except UnicodeDecodeError:
        return None
    return txt.strip(' ')


MFG_READABLE = set(SIMPLE_MFG) | {'IT', 'VT', 'AV', 'MU', 'TR', 'LS', 'IS', 'OS'}


def process_pdu(dev, pdu):
    fc = pdu[0]
    try:
        if fc == 0x01 or fc == 0x02:
            if len(pdu) != 5:
                raise MbError(ILLEGAL_VALUE)
            start, qty = struct.unpack('>HH', pdu[1:5])
            if not 1 <= qty <= 4:
                raise MbError(ILLEGAL_VALUE)
            if start + qty > 4:
                raise MbError(ILLEGAL_ADDRESS)
            bits = dev.read_coils(start, qty) if fc == 1 else dev.read_inputs(start, qty)
            val = sum(b << i for i, b in enumerate(bits))
            return bytes([fc, 1, val])
        if fc == 0x05:
            if len(pdu) != 5:
                raise MbError(ILLEGAL_VALUE)
            addr, value = struct.unpack('>HH', pdu[1:5])
            if value not in (0x0000, 0xFF00):
                raise MbError(ILLEGAL_VALUE)
            if addr > 3:
                raise MbError(ILLEGAL_ADDRESS)
            dev.write_output(addr + 1, 1 if value else 0)
            return bytes(pdu)
        if fc == 0x03:
            if len(pdu) != 5:
                raise MbError(ILLEGAL_VALUE)
            start, qty = struct.unpack('>HH', pdu[1:5])
            if not 1 <= qty <= 2:
                raise MbError(ILLEGAL_VALUE)
            if start + qty - 1 > MAX_REG_ADDR:
                raise MbError(ILLEGAL_ADDRESS)
            words = dev.read_registers(start, qty)
            return bytes([0x03, 2 * qty]) + b''.join(struct.pack('>H', w) for w in words)
        if fc == 0x10:
            if len(pdu) < 6:
                raise MbError(ILLEGAL_VALUE)
            start, qty, bc = struct.unpack('>HHB', pdu[1:6])
            if not 1 <= qty <= 2 or bc != 2 * qty or len(pdu) != 6 + bc:
                raise MbError(ILLEGAL_VALUE)
            if start + qty - 1 > MAX_REG_ADDR:
                raise MbError(ILLEGAL_ADDRESS)
            words = [struct.unpack('>H', pdu[6 + 2 * i:8 + 2 * i])[0] for i in range(qty)]
            dev.write_registers(start, words)
            return struct.pack('>BHH', 0x10, start, qty)
        if fc == 0x2B:
            if len(pdu) < 2:
                raise MbError(ILLEGAL_VALUE)
            if pdu[1] != 0x0E:
                raise MbError(ILLEGAL_FUNCTION)
            if len(pdu) != 4:
                raise MbError(ILLEGAL_VALUE)
            code, obj = pdu[2], pdu[3]
            if code not in (1, 2, 3, 4):
                raise MbError(ILLEGAL_VALUE)
            if code == 4:
                if obj >= len(DEVICE_ID):
                    raise MbError(ILLEGAL_ADDRESS)
                ids = [obj]
            else:
                lo, hi = (0, 2) if code == 1 else (0, len(DEVICE_ID) - 1)
                if obj < lo or obj > hi:
                    obj = lo
                ids = list(range(obj, hi + 1))
            body = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)])
            for i in ids:
                v = DEVICE_ID[i]
                body += bytes([i, len(v)]) + v
            return bytes(body)
        if fc == 0x41:
            if len(pdu) != 5:
                raise MbError(ILLEGAL_VALUE)
            mn = decode_mnemonic(pdu[1:5])
            if mn is None:
                raise MbError(ILLEGAL_ADDRESS)
            if not (mn in MFG_READABLE or dev.io_line(mn) is not None):
                raise MbError(ILLEGAL_ADDRESS)
            txt = dev.mfg_read(mn).encode('ascii')
            return bytes([0x41, len(txt)]) + txt
        if fc == 0x42:
            if len(pdu) < 6:
                raise MbError(ILLEGAL_VALUE)
            bc = pdu[5]
            if bc > 28 or len(pdu) != 6 + bc:
                raise MbError(ILLEGAL_VALUE)
            mn = decode_mnemonic(pdu[1:5])
            if mn is None:
                raise MbError(ILLEGAL_ADDRESS)
            try:
                data = pdu[6:].decode('ascii')
            except UnicodeDecodeError:
                raise MbError(ILLEGAL_VALUE)
            dev.mfg_write(mn, data)
            return bytes([0x42, 0x04]) + bytes(pdu[1:5])
        raise MbError(ILLEGAL_FUNCTION)
    except MbError as e:
        return bytes([(fc | 0x80) & 0xFF, e.code])
    except Exception:      # never let one frame take the server down
        return bytes([(fc | 0x80) & 0xFF, DEVICE_FAILURE])


# ---------------------------------------------------------------------------
# Modbus/TCP server
# ---------------------------------------------------------------------------
class Server:
    def __init__(self, state_file):
        self.dev = Device()
        self.state_file = state_file
        self.writers = set()

    def dump_state(self):
        if not self.state_file:
            return
        try:
            data = json.dumps(self.dev.state(), indent=1, sort_keys=True)
            tmp = self.state_file + '.tmp'
            with open(tmp, 'w') as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.state_file)
        except Exception as e:      # pragma: no cover
            print('state dump failed: %s' % e, file=sys.stderr, flush=True)

    async def handle(self, reader, writer):
        self.writers.add(writer)
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid, pid, length, uid = struct.unpack('>HHHB', hdr)
                if length < 2 or length > 254:
                    break          # framing cannot be trusted: drop the connection
                pdu = await reader.readexactly(length - 1)
                if pid != 0:
                    continue       # not Modbus: silently discard (TCP impl. guide)
                resp = process_pdu(self.dev, pdu)
                writer.write(struct.pack('>HHHB', tid, 0, len(resp) + 1, uid) + resp)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            pass
        finally:
            self.writers.discard(writer)
            try:
                writer.close()
            except Exception:
                pass


async def amain(host, port, state_file):
    srv = Server(state_file)
    server = await asyncio.start_server(srv.handle, host, port, reuse_address=True)
    sock = server.sockets[0]
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, srv.dump_state)
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    # (modbus-harness: the handlers before the line, so that a SIGUSR1 right after it finds them.)
    print('listening tcp %s:%d' % (host, sock.getsockname()[1]), flush=True)
    await stop.wait()
    srv.dump_state()
    server.close()
    for w in list(srv.writers):
        try:
            w.close()
        except Exception:
            pass
    try:
        await asyncio.wait_for(server.wait_closed(), 1.0)
    except Exception:
        pass


def main():
    ap = argparse.ArgumentParser(description='Lexium MDrive Ethernet Modbus/TCP simulator')
    ap.add_argument('--listen', default='127.0.0.1:502')
    ap.add_argument('--state', default=None)
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(':')
    asyncio.run(amain(host or '127.0.0.1', int(port), args.state))


if __name__ == '__main__':
    main()
