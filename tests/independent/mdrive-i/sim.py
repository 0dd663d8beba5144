#!/usr/bin/env python3
"""MDrive Hybrid (Ethernet, Modbus/TCP) simulator -- clean-room, standard library only.

Written from the IMS / Schneider Electric Motion USA "MODBUS/TCP Fieldbus Manual",
rev. R040611, and the public MODBUS specifications.  See DECISIONS.md.
"""
import argparse
import asyncio
import json
import os
import signal
import struct
import sys
import time

# ---------------------------------------------------------------- exceptions
ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3
DEVICE_FAILURE = 4


class MbErr(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


I32_MIN, I32_MAX = -2147483648, 2147483647
MS_TABLE = {1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127}
ENCODER_COUNTS_PER_REV = 4096          # decision D-ENC
FULL_STEPS_PER_REV = 200

# ---------------------------------------------------------------- register map
# kind: rw (parameter), ro (status), wo (command), plus (MDrivePlus only -> absent on Hybrid),
#       var (user variable V1..V8, only valid inside a running MCode program)
# (addr, name, words, kind, lo, hi, default, signed)
REGS = [
    (0x0000, 'A', 2, 'rw', 91, 1525878997, 1000000, False),
    (0x0005, 'C1', 2, 'rw', I32_MIN, I32_MAX, 0, True),
    (0x0007, 'C2', 2, 'rw', I32_MIN, I32_MAX, 0, True),
    (0x0009, 'CE', 1, 'rw', 0, 1, 1, False),
    (0x000B, 'CM', 1, 'plus', 0, 1, 0, False),
    (0x000F, 'D1', 1, 'rw', 0, 255, 0, False),
    (0x0010, 'D2', 1, 'rw', 0, 255, 0, False),
    (0x0011, 'D3', 1, 'rw', 0, 255, 0, False),
    (0x0012, 'D4', 1, 'rw', 0, 255, 0, False),
    (0x0013, 'D5', 1, 'rw', 0, 255, 0, False),
    (0x0018, 'D', 2, 'rw', 91, 1525878997, 1000000, False),
    (0x001A, 'DB', 1, 'plus', 0, 65000, 10, False),
    (0x001B, 'DC', 1, 'wo', 0, 0xFFFF, None, False),
    (0x001C, 'DE', 1, 'rw', 0, 1, 1, False),
    (0x001E, 'EE', 1, 'rw', 0, 1, 0, False),
    (0x001F, 'EF', 1, 'ro', 0, 1, 0, False),
    (0x0021, 'ER', 1, 'rw', 0, 0, 0, False),
    (0x0029, 'HC', 1, 'rw', 0, 100, 5, False),
    (0x002B, 'HM', 1, 'rw', 1, 4, 1, False),
    (0x002C, 'HT', 1, 'rw', 0, 65535, 500, False),
    (0x002D, 'I1', 1, 'ro', 0, 1, 0, False),
    (0x002E, 'I2', 1, 'ro', 0, 1, 0, False),
    (0x002F, 'I3', 1, 'ro', 0, 1, 0, False),
    (0x0030, 'I4', 1, 'ro', 0, 1, 0, False),
    (0x0031, 'I5', 1, 'ro', 0, 1023, 0, False),
    (0x0032, 'I6', 1, 'plus', 0, 1, 0, False),
    (0x0037, 'IC', 1, 'wo', 0, 0xFFFF, None, False),
    (0x003A, 'IL', 1, 'ro', 0, 15, 0, False),
    (0x003B, 'IN', 1, 'ro', 0, 15, 0, False),
    (0x003F, 'JE', 1, 'rw', 0, 1, 0, False),
    (0x0042, 'LM', 1, 'rw', 1, 6, 1, False),
    (0x0043, 'MA', 2, 'wo', I32_MIN, I32_MAX, None, True),
    (0x0045, 'MP', 1, 'ro', 0, 1, 0, False),
    (0x0046, 'MR', 2, 'wo', I32_MIN, I32_MAX, None, True),
    (0x0048, 'MS', 1, 'rw', 1, 256, 256, False),
    (0x0049, 'MT', 1, 'rw', 0, 65000, 0, False),
    (0x004A, 'MV', 1, 'ro', 0, 1, 0, False),
    (0x004B, 'O1', 1, 'rw', 0, 1, 0, False),
    (0x004C, 'O2', 1, 'rw', 0, 1, 0, False),
    (0x004D, 'O3', 1, 'rw', 0, 1, 0, False),
    (0x004E, 'O4', 1, 'rw', 0, 1, 0, False),
    (0x0055, 'OL', 1, 'rw', 0, 15, 0, False),
    (0x0056, 'OT', 1, 'rw', 0, 15, 0, False),
    (0x0057, 'P', 2, 'rw', I32_MIN, I32_MAX, 0, True),
    (0x0059, 'PC', 2, 'ro', I32_MIN, I32_MAX, 0, True),
    (0x005C, 'PM', 1, 'plus', 0, 1, 0, False),
    (0x005F, 'R1', 2, 'rw', I32_MIN, I32_MAX, 0, True),
    (0x0061, 'R2', 2, 'rw', I32_MIN, I32_MAX, 0, True),
    (0x0063, 'R3', 2, 'rw', I32_MIN, I32_MAX, 0, True),
    (0x0065, 'R4', 2, 'rw', I32_MIN, I32_MAX, 0, True),
    (0x0067, 'RC', 1, 'rw', 1, 100, 25, False),
    (0x0076, 'S', 1, 'wo', 0, 0xFFFF, None, False),
    (0x0077, 'SF', 1, 'plus', 0, 65000, 15, False),
    (0x0078, 'SL', 2, 'wo', -5000000, 5000000, None, True),
    (0x007A, 'SM', 1, 'plus', 0, 1, 0, False),
    (0x007B, 'ST', 1, 'plus', 0, 1, 0, False),
    (0x007D, 'TE', 1, 'rw', 0, 43, 0, False),
    (0x0085, 'V', 2, 'ro', I32_MIN, I32_MAX, 0, True),
    (0x0088, 'VC', 1, 'ro', 0, 1, 0, False),
    (0x0089, 'VI', 2, 'rw', 1, 4999999, 1000, False),
    (0x008B, 'VM', 2, 'rw', 2, 5000000, 768000, False),
    (0x008E, 'AS', 1, 'rw', 0, 3, 2, False),
    (0x008F, 'AF', 1, 'ro', 0, 255, 0, False),
    (0x0090, 'CA', 1, 'rw', 0, 1, 1, False),
    (0x0091, 'CB', 1, 'rw', 0, 3, 1, False),
    (0x0092, 'CC', 1, 'rw', 1, 100, 100, False),
    (0x0093, 'CF', 1, 'wo', 0, 0xFFFF, None, False),
    (0x0094, 'CT', 1, 'rw', 2, 65535, 200, False),
    (0x0095, 'LD', 2, 'rw', 0, I32_MAX, 102400, False),
    (0x0097, 'LG', 2, 'rw', 0, I32_MAX, 102400, False),
    (0x0099, 'LL', 2, 'ro', -I32_MAX, I32_MAX, 0, True),
    (0x009B, 'LR', 1, 'ro', 0, 1, 0, False),
    (0x009C, 'LT', 2, 'rw', 2, 65535, 2000, False),
    (0x009E, 'MF', 2, 'rw', 306, 5000000, 768000, False),
    (0x00A0, 'MU', 1, 'rw', 0, 2, 0, False),
    (0x00A1, 'SC', 1, 'wo', 0, 0xFFFF, None, False),
    (0x00A2, 'SS', 1, 'rw', 0, 255, 0, False),
    (0x00A5, 'TD', 1, 'rw', 0, 1, 1, False),
    (0x00A6, 'TQ', 1, 'rw', 1, 100, 25, False),
    (0x00A7, 'TS', 1, 'rw', 0, 255, 0, False),
] + [(0x00A8 + 2 * i, 'V%d' % (i + 1), 2, 'var', I32_MIN, I32_MAX, 0, True) for i in range(8)]


class Item:
    __slots__ = ('addr', 'name', 'words', 'kind', 'lo', 'hi', 'default', 'signed')

    def __init__(self, t):
        (self.addr, self.name, self.words, self.kind, self.lo, self.hi,
         self.default, self.signed) = t


ITEMS = [Item(t) for t in REGS]
BY_NAME = {it.name: it for it in ITEMS}
ADDR_MAP = {}          # register address -> (item, word index)
for _it in ITEMS:
    for _w in range(_it.words):
        ADDR_MAP[_it.addr + _w] = (_it, _w)

COIL_BASE, INPUT_BASE, NPOINTS = 0x004B, 0x002D, 4
PARAM_NAMES = [it.name for it in ITEMS if it.kind == 'rw']

# manufacturer functions: mnemonic -> (min len, max len) of the parameter string
IN_FUNCS = {0, 1, 2, 3, 5, 7, 8, 11}
OUT_FUNCS = {16, 17, 18, 20, 21, 23, 24, 25}
MFG_CONFIG = {'S1': (6, 7), 'S2': (6, 7), 'S3': (6, 7), 'S4': (6, 7),
              'S7': (4, 5), 'S8': (4, 5), 'CR': (2, 6), 'S5': (4, 5),
              'S13': (4, 5), 'TR': (2, 11), 'MU': (4, 4)}
MFG_PROGRAM = {'E', 'EX', 'PS', 'RS'}


def to_words(value, words, signed):
    if words == 1:
        return [value & 0xFFFF]
    v = value & 0xFFFFFFFF
    return [(v >> 16) & 0xFFFF, v & 0xFFFF]


def from_words(ws, signed):
    if len(ws) == 1:
        v = ws[0]
        if signed and v >= 0x8000:
            v -= 0x10000
        return v
    v = (ws[0] << 16) | ws[1]
    if signed and v >= 0x80000000:
        v -= 0x100000000
    return v


def wrap32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v >= 0x80000000 else v


class Drive:
    def __init__(self):
        self.p = {it.name: it.default for it in ITEMS if it.kind == 'rw'}
        self.latch = [0, 0, 0, 0]               # general purpose output latches O1..O4
        self.io = [[0, 0, 0] for _ in range(4)]  # S1..S4: type, active, sink/source
        self.mfg = {'S7': [33, 0], 'S8': [33, 0], 'CR': 1000, 'S5': [9, 0],
                    'S13': [60, 0], 'TR': [0, 0, 0], 'MU_B': 0}
        self.er = 0
        self.pc = 0
        self.ll = 0
        self.lr = 0
        # motion
        self.pos = 0.0
        self.c1f = 0.0
        self.c2f = 0.0
        self.vel = 0.0          # signed steps/s
        self.mode = None        # None, 'move', 'slew'
        self.target = 0
        self.slew = 0
        self.vchg = 0
        self.cal_until = 0.0    # calibration finished (power-on calibration assumed done)
        self.trip_origin = 0
        self.last = time.monotonic()
        self.nvm = None
        self.nvm = self.snapshot_settings()
        self.counters = {'requests': 0, 'responses': 0, 'exceptions': 0,
                         'discarded_frames': 0, 'connections': 0}

    # ------------------------------------------------------------ helpers
    def snapshot_settings(self):
        return {'registers': dict(self.p), 'outputs': list(self.latch),
                'io': [list(x) for x in self.io],
                'mfg': json.loads(json.dumps(self.mfg))}

    def calibrating(self):
        return time.monotonic() < self.cal_until

    def start_calibration(self):
        self.cal_until = time.monotonic() + self.p['CT'] / 1000.0

    def moving(self):
        return self.mode is not None

    def steps_per_rev(self):
        return FULL_STEPS_PER_REV * self.p['MS']

    def hybrid_active(self):
        return 1 if (self.p['AS'] != 0 and self.p['DE'] == 1) else 0

    def af(self):
        v = 0
        if self.lr:
            v |= 8
        if self.hybrid_active():
            v |= 16
        if self.ll == 0:
            v |= 64
        if not self.calibrating():
            v |= 128
        return v

    def out_level(self, n):
        t = self.io[n][0]
        if t not in OUT_FUNCS:
            return 0
        if t == 16:
            return self.latch[n]
        if t == 17:
            return 1 if self.moving() else 0
        if t == 18:
            return 1 if self.er else 0
        if t == 20:
            return self.vchg
        if t == 21:
            return self.lr
        if t == 23:
            return 1 if self.mode == 'move' else 0
        if t == 24:
            return self.hybrid_active()
        if t == 25:
            return 1 if (self.p['MU'] != 0 and self.ll != 0) else 0
        return 0

    def in_level(self, n):
        # nothing is wired to the simulated inputs: an input point reads inactive;
        # a point configured as an output reads back the level it drives.
        if self.io[n][0] in OUT_FUNCS:
            return self.out_level(n)
        return 0

    # ------------------------------------------------------------ motion
    def tick(self):
        now = time.monotonic()
        dt = now - self.last
        self.last = now
        if dt <= 0 or self.mode is None:
            self.vchg = 0
            return
        dt = min(dt, 0.1)
        VI, VM, A, D = self.p['VI'], self.p['VM'], self.p['A'], self.p['D']
        old = self.pos
        if self.mode == 'move':
            rem = self.target - self.pos
            d = 1 if rem >= 0 else -1
            rem = abs(rem)
            sp = abs(self.vel)
            if sp < VI:
                sp = VI
            stop = (sp * sp - VI * VI) / (2.0 * D) if sp > VI else 0.0
            if rem <= stop + sp * dt:
                nsp = max(VI, sp - D * dt)
            else:
                nsp = min(VM, sp + A * dt)
            self.vchg = 1 if nsp != sp else 0
            sp = nsp
            stepd = sp * dt
            if stepd >= rem:
                self.pos = float(self.target)
                self.vel = 0.0
                self.mode = None
                self.vchg = 0
            else:
                self.pos += d * stepd
                self.vel = d * sp
        else:  # slew
            tgt = float(self.slew)
            v = self.vel
            if v == 0.0 and tgt != 0.0:
                v = min(VI, abs(tgt)) * (1 if tgt > 0 else -1)
            if tgt == 0.0 or (v > 0) != (tgt > 0):
                # decelerate towards zero
                sp = abs(v) - D * dt
                if sp <= VI:
                    if tgt == 0.0:
                        v = 0.0
                    else:
                        v = min(VI, abs(tgt)) * (1 if tgt > 0 else -1)
                else:
                    v = sp * (1 if v > 0 else -1)
            else:
                sp = abs(v)
                if sp < abs(tgt):
                    sp = min(abs(tgt), sp + A * dt)
                elif sp > abs(tgt):
                    sp = max(abs(tgt), sp - D * dt)
                v = sp * (1 if tgt > 0 else -1)
            self.vchg = 1 if v != self.vel else 0
            self.pos += (self.vel + v) / 2.0 * dt
            self.vel = v
            if v == 0.0 and tgt == 0.0:
                self.mode = None
                self.vchg = 0
            self.pos = max(float(I32_MIN), min(float(I32_MAX), self.pos))
        delta = self.pos - old
        self.c1f += delta
        self.c2f += delta * ENCODER_COUNTS_PER_REV / self.steps_per_rev()
        self.check_trip()

    def check_trip(self):
        if self.p['TE'] & 16 and self.mfg['TR'][0] != 0:
            if abs(self.get_p() - self.trip_origin) >= abs(self.mfg['TR'][0]):
                self.p['TE'] &= ~16     # a trip fires once; re-enable through 0x007D

    def get_p(self):
        return int(round(self.pos))

    def stop_now(self):
        self.mode = None
        self.vel = 0.0
        self.vchg = 0
        self.pos = float(self.get_p())

    # ------------------------------------------------------------ item read
    def read_item(self, it):
        n = it.name
        if it.kind == 'wo':
            return 0
        if n == 'C1':
            return wrap32(int(round(self.c1f)))
        if n == 'C2':
            return wrap32(int(round(self.c2f)))
        if n == 'P':
            return self.get_p()
        if n == 'ER':
            return self.er
        if n == 'EF':
            return 1 if self.er else 0
        if n in ('I1', 'I2', 'I3', 'I4'):
            return self.in_level(int(n[1]) - 1)
        if n == 'I5':
            return 0
        if n in ('IL', 'IN'):
            return sum(self.in_level(i) << i for i in range(4))
        if n == 'MP':
            return 1 if self.mode == 'move' else 0
        if n == 'MV':
            return 1 if self.moving() else 0
        if n in ('O1', 'O2', 'O3', 'O4'):
            return self.out_level(int(n[1]) - 1)
        if n in ('OL', 'OT'):
            return sum(self.out_level(i) << i for i in range(4))
        if n == 'PC':
            return self.pc
        if n == 'V':
            return 0 if self.p['AS'] == 3 else int(round(self.vel))
        if n == 'VC':
            return self.vchg
        if n == 'AF':
            return self.af()
        if n == 'LL':
            return self.ll
        if n == 'LR':
            return self.lr
        return self.p[n]

    # ------------------------------------------------------------ Modbus reads
    def read_regs(self, start, qty):
        out = []
        touched_er = False
        for a in range(start, start + qty):
            ent = ADDR_MAP.get(a)
            if ent is None or ent[0].kind == 'plus':
                raise MbErr(ILLEGAL_ADDRESS)
            if ent[0].kind == 'var':
                raise MbErr(DEVICE_FAILURE)
        for a in range(start, start + qty):
            it, w = ADDR_MAP[a]
            v = self.read_item(it)
            if it.name == 'ER':
                touched_er = True
            out.append(to_words(v, it.words, it.signed)[w])
        if touched_er:
            self.er = 0          # "must be read or set to 0 to clear"
        return out

    # ------------------------------------------------------------ Modbus writes
    def write_regs(self, start, words):
        qty = len(words)
        items = []   # (item, value)
        a = start
        end = start + qty
        while a < end:
            ent = ADDR_MAP.get(a)
            if ent is None:
                raise MbErr(ILLEGAL_ADDRESS)
            it, w = ent
            if it.kind in ('plus', 'ro'):
                raise MbErr(ILLEGAL_ADDRESS)
            if w != 0 or a + it.words > end:
                raise MbErr(ILLEGAL_ADDRESS)     # must write a whole 32-bit item
            items.append((it, from_words(words[a - start:a - start + it.words], it.signed)))
            a += it.words
        if any(it.kind == 'var' for it, _ in items):
            raise MbErr(DEVICE_FAILURE)
        new = dict(self.p)
        for it, v in items:
            if it.kind == 'rw':
                new[it.name] = v
        # ---- value checks (03)
        for it, v in items:
            self.check_value(it, v, new)
        # ---- state checks (04)
        for it, v in items:
            self.check_state(it, v, new)
        # ---- apply
        for it, v in items:
            self.apply(it, v)

    def check_value(self, it, v, new):
        n = it.name
        if not (it.lo <= v <= it.hi):
            raise MbErr(ILLEGAL_VALUE)
        if n == 'MS' and v not in MS_TABLE:
            raise MbErr(ILLEGAL_VALUE)
        if n == 'HT' and v == 1:
            raise MbErr(ILLEGAL_VALUE)
        if n in ('HT', 'MT') and new['HT'] + new['MT'] > 65535:
            raise MbErr(ILLEGAL_VALUE)
        if n in ('VI', 'VM') and not (new['VI'] <= new['VM'] - 1):
            raise MbErr(ILLEGAL_VALUE)
        if n == 'TE' and v not in (0, 16):
            raise MbErr(ILLEGAL_VALUE)
        if n == 'MR':
            if not (I32_MIN <= self.get_p() + v <= I32_MAX):
                raise MbErr(ILLEGAL_VALUE)
        if n in ('DC', 'IC'):
            if v not in (0x0005, 0x0007, 0x0057, 0x005F, 0x0061, 0x0063, 0x0065) and \
                    not (0x00A8 <= v <= 0x00B6 and v % 2 == 0):
                raise MbErr(ILLEGAL_VALUE)

    def motion_ready(self):
        return self.p['DE'] == 1 and not self.calibrating() and not self.lr

    def check_state(self, it, v, new):
        n = it.name
        if n in ('MS', 'AS', 'P') and self.moving():
            if not (n == 'MS' and v == self.p['MS']) and not (n == 'AS' and v == self.p['AS']):
                raise MbErr(DEVICE_FAILURE)
        if n == 'CB' and new['AS'] == 3 and v != 0:
            raise MbErr(DEVICE_FAILURE)
        if n in ('O1', 'O2', 'O3', 'O4'):
            i = int(n[1]) - 1
            if self.io[i][0] != 16:
                raise MbErr(DEVICE_FAILURE)
        if n in ('OL', 'OT'):
            for i in range(4):
                if (v >> i) & 1 and self.io[i][0] != 16:
                    raise MbErr(DEVICE_FAILURE)
        if n in ('MA', 'MR'):
            if self.moving() or not self.motion_ready():
                raise MbErr(DEVICE_FAILURE)
        if n == 'SL':
            if self.mode == 'move':
                raise MbErr(DEVICE_FAILURE)
            if v != 0 and not self.motion_ready():
                raise MbErr(DEVICE_FAILURE)
        if n == 'SC' and self.moving():
            raise MbErr(DEVICE_FAILURE)
        if n in ('DC', 'IC'):
            if v >= 0x00A8:
                raise MbErr(DEVICE_FAILURE)      # V1..V8 not declared (no program)
            if v == 0x0057 and self.moving():
                raise MbErr(DEVICE_FAILURE)

    def apply(self, it, v):
        n = it.name
        if it.kind == 'rw':
            old = self.p[n]
        if n == 'C1':
            self.c1f = float(v)
        elif n == 'C2':
            self.c2f = float(v)
        elif n == 'P':
            self.pos = float(v)
            self.trip_origin = v
        elif n == 'ER':
            self.er = 0
        elif n in ('O1', 'O2', 'O3', 'O4'):
            self.latch[int(n[1]) - 1] = v
        elif n in ('OL', 'OT'):
            for i in range(4):
                if self.io[i][0] == 16:
                    self.latch[i] = (v >> i) & 1
        elif n == 'MA':
            self.mode, self.target, self.vel = 'move', v, 0.0
        elif n == 'MR':
            self.mode, self.target, self.vel = 'move', self.get_p() + v, 0.0
        elif n == 'SL':
            if v == 0 and self.mode is None:
                pass
            else:
                self.slew = v
                self.mode = 'slew'
        elif n == 'S':
            self.nvm = self.snapshot_settings()
        elif n == 'CF':
            self.lr = 0
            self.start_calibration()
        elif n == 'SC':
            self.start_calibration()
        elif n in ('DC', 'IC'):
            d = -1 if n == 'DC' else 1
            if v == 0x0005:
                self.c1f = float(wrap32(int(round(self.c1f)) + d))
            elif v == 0x0007:
                self.c2f = float(wrap32(int(round(self.c2f)) + d))
            elif v == 0x0057:
                self.pos = float(wrap32(self.get_p() + d))
            else:
                rn = 'R%d' % ((v - 0x005F) // 2 + 1)
                self.p[rn] = wrap32(self.p[rn] + d)
        if it.kind != 'rw' or n in ('ER', 'O1', 'O2', 'O3', 'O4', 'OL', 'OT', 'C1', 'C2', 'P'):
            return
        self.p[n] = v
        if n == 'TE' and v & 16:
            self.trip_origin = self.get_p()
        if n == 'AS':
            if v == 3:
                self.p['CB'] = 0        # torque mode: control bounds preset for torque
            if old == 0 and v != 0 and self.p['DE'] == 1:
                self.start_calibration()
        elif n == 'DE':
            if v == 0:
                self.stop_now()
            elif old == 0 and self.p['AS'] != 0:
                self.start_calibration()
        elif n == 'MS':
            if v != old and self.p['AS'] != 0:
                self.start_calibration()

    # ------------------------------------------------------------ manufacturer functions
    def mfg_read(self, mn):
        if mn in ('S1', 'S2', 'S3', 'S4'):
            a, b, c = self.io[int(mn[1]) - 1]
            return '%d, %d, %d' % (a, b, c)
        if mn in ('S7', 'S8', 'S5', 'S13'):
            return '%d, %d' % tuple(self.mfg[mn])
        if mn == 'CR':
            return '%d.%03d' % divmod(self.mfg['CR'], 1000)
        if mn == 'TR':
            return '%d, %d, %d' % tuple(self.mfg['TR'])
        if mn == 'MU':
            return '%d, %d' % (self.p['MU'], self.mfg['MU_B'])
        raise MbErr(ILLEGAL_ADDRESS)

    @staticmethod
    def parse_fields(s, nmin, nmax):
        if not s.startswith('='):
            raise MbErr(ILLEGAL_VALUE)
        parts = s[1:].split(',')
        if not (nmin <= len(parts) <= nmax):
            raise MbErr(ILLEGAL_VALUE)
        out = []
        for p in parts:
            p = p.strip()
            q = p[1:] if p[:1] in '+-' else p
            if not q.isdigit() or not q.isascii():
                raise MbErr(ILLEGAL_VALUE)
            out.append(int(p))
        return out

    def mfg_write(self, mn, data):
        lo, hi = MFG_CONFIG[mn]
        if not (lo <= len(data) <= hi):
            raise MbErr(ILLEGAL_VALUE)
        try:
            s = data.decode('ascii')
        except UnicodeDecodeError:
            raise MbErr(ILLEGAL_VALUE)
        if mn in ('S1', 'S2', 'S3', 'S4'):
            a, b, c = self.parse_fields(s, 3, 3)
            if a not in IN_FUNCS | OUT_FUNCS or b not in (0, 1) or c not in (0, 1):
                raise MbErr(ILLEGAL_VALUE)
            i = int(mn[1]) - 1
            if [a, b, c] != self.io[i]:
                if (a in OUT_FUNCS) != (self.io[i][0] in OUT_FUNCS) or a != 16:
                    self.latch[i] = 0
                self.io[i] = [a, b, c]
        elif mn in ('S7', 'S8'):
            a, b = self.parse_fields(s, 2, 2)
            if a not in (33, 34, 35, 49, 50, 51) or b not in (0, 1):
                raise MbErr(ILLEGAL_VALUE)
            self.mfg[mn] = [a, b]
        elif mn == 'S5':
            a, b = self.parse_fields(s, 2, 2)
            if a not in (9, 10) or b not in (0, 1):
                raise MbErr(ILLEGAL_VALUE)
            self.mfg[mn] = [a, b]
        elif mn == 'S13':
            a, b = self.parse_fields(s, 2, 2)
            if a not in (60, 61) or b not in (0, 1):
                raise MbErr(ILLEGAL_VALUE)
            self.mfg[mn] = [a, b]
        elif mn == 'CR':
            if not s.startswith('='):
                raise MbErr(ILLEGAL_VALUE)
            t = s[1:]
            ip, _, fp = t.partition('.')
            if not ip.isdigit() or (fp and not fp.isdigit()) or (_ and not fp) or \
                    not t.isascii():
                raise MbErr(ILLEGAL_VALUE)
            # held at 0.001 resolution: extra decimals are rounded
            fpv = int(round(float('0.' + fp) * 1000)) if fp else 0
            val = int(ip) * 1000 + fpv
            if val <= 0:
                raise MbErr(ILLEGAL_VALUE)
            self.mfg['CR'] = val
        elif mn == 'TR':
            f = self.parse_fields(s, 1, 3)
            if not (I32_MIN <= f[0] <= I32_MAX) or any(x < 0 or x > 65535 for x in f[1:]):
                raise MbErr(ILLEGAL_VALUE)
            self.mfg['TR'] = (f + [0, 0])[:3]
        elif mn == 'MU':
            a, b = self.parse_fields(s, 2, 2)
            if a not in (0, 1, 2) or b not in (0, 1):
                raise MbErr(ILLEGAL_VALUE)
            self.p['MU'] = a
            self.mfg['MU_B'] = b
            if b == 1:
                self.ll = 0          # clear lead/lag

    def program_cmd(self, mn, data):
        if mn == 'EX':
            s = data.decode('ascii', 'replace')
            if s.startswith('='):
                s = s[1:]
            if not (1 <= len(s) <= 3) or not s.isalnum():
                raise MbErr(ILLEGAL_VALUE)
            raise MbErr(DEVICE_FAILURE)        # no MCode program stored in a fresh drive
        if data:
            raise MbErr(ILLEGAL_VALUE)
        # E / PS / RS: no program is running -> accepted, nothing to do

    # ------------------------------------------------------------ state dump
    def dump(self):
        self.tick()
        regs = {}
        for it in ITEMS:
            if it.kind in ('wo', 'plus', 'var'):
                continue
            if it.name == 'ER':
                v = self.er
            else:
                v = self.read_item(it)
            regs['0x%04X' % it.addr] = {'name': it.name, 'words': it.words, 'value': v}
        return {
            'device': 'MDrive Hybrid Ethernet (Modbus/TCP)',
            'holding_registers': regs,
            'coils': {'0x%04X' % (COIL_BASE + i): self.out_level(i) for i in range(4)},
            'discrete_inputs': {'0x%04X' % (INPUT_BASE + i): self.in_level(i) for i in range(4)},
            'output_latches': list(self.latch),
            'manufacturer': {
                'S1': self.mfg_read('S1'), 'S2': self.mfg_read('S2'),
                'S3': self.mfg_read('S3'), 'S4': self.mfg_read('S4'),
                'S7': self.mfg_read('S7'), 'S8': self.mfg_read('S8'),
                'CR': self.mfg_read('CR'), 'S5': self.mfg_read('S5'),
                'S13': self.mfg_read('S13'), 'TR': self.mfg_read('TR'),
                'MU': self.mfg_read('MU')},
            'user_variables_V1_V8': 'not declared (no MCode program)',
            'program': {'stored': False, 'running': False},
            'nvm': self.nvm,
            'diagnostic_counters': dict(self.counters),
        }


# ---------------------------------------------------------------- device identification
DEV_ID = {
    0: b'SEM USA',
    1: b'MAI3PRD23A7-EQ',
    2: b'4.0.0.0',
    3: b'www.imshome.com',
    4: b'MDrive Ethernet',
    5: b'269100001',
    6: b'ASI 4.0.0.2',
}


def fc43(pdu):
    if len(pdu) < 2:
        raise MbErr(ILLEGAL_VALUE)
    if pdu[1] != 0x0E:
        raise MbErr(ILLEGAL_FUNCTION)
    if len(pdu) != 4:
        raise MbErr(ILLEGAL_VALUE)
    code, obj = pdu[2], pdu[3]
    if code not in (1, 2, 3, 4):
        raise MbErr(ILLEGAL_VALUE)
    if code == 4:
        if obj not in DEV_ID:
            raise MbErr(ILLEGAL_ADDRESS)
        v = DEV_ID[obj]
        return bytes([0x2B, 0x0E, 4, 0x82, 0x00, 0x00, 1, obj, len(v)]) + v
    last = 2 if code == 1 else 6
    if obj > last:
        obj = 0
    body = b''
    n = 0
    nxt = 0
    more = 0
    for o in range(obj, last + 1):
        v = DEV_ID[o]
        if len(body) + 2 + len(v) > 253 - 7:
            more, nxt = 0xFF, o
            break
        body += bytes([o, len(v)]) + v
        n += 1
    return bytes([0x2B, 0x0E, code, 0x82, more, nxt, n]) + body


# ---------------------------------------------------------------- PDU dispatcher
def handle_pdu(dev, pdu):
    fc = pdu[0]
    dev.tick()
    if fc in (0x01, 0x02):
        if len(pdu) != 5:
            raise MbErr(ILLEGAL_VALUE)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not (1 <= qty <= 2000):
            raise MbErr(ILLEGAL_VALUE)
        base = COIL_BASE if fc == 1 else INPUT_BASE
        if start < base or start + qty > base + NPOINTS:
            raise MbErr(ILLEGAL_ADDRESS)
        bits = 0
        for k in range(qty):
            i = start - base + k
            lv = dev.out_level(i) if fc == 1 else dev.in_level(i)
            bits |= lv << k
        return bytes([fc, 1, bits])
    if fc == 0x05:
        if len(pdu) != 5:
            raise MbErr(ILLEGAL_VALUE)
        addr, val = struct.unpack('>HH', pdu[1:5])
        if val not in (0x0000, 0xFF00):
            raise MbErr(ILLEGAL_VALUE)
        if not (COIL_BASE <= addr < COIL_BASE + NPOINTS):
            raise MbErr(ILLEGAL_ADDRESS)
        i = addr - COIL_BASE
        if dev.io[i][0] != 16:
            raise MbErr(DEVICE_FAILURE)
        dev.latch[i] = 1 if val else 0
        return bytes(pdu)
    if fc == 0x03:
        if len(pdu) != 5:
            raise MbErr(ILLEGAL_VALUE)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not (1 <= qty <= 125):
            raise MbErr(ILLEGAL_VALUE)
        if start + qty > 0x10000:
            raise MbErr(ILLEGAL_ADDRESS)
        ws = dev.read_regs(start, qty)
        return bytes([3, 2 * qty]) + struct.pack('>%dH' % qty, *ws)
    if fc == 0x10:
        if len(pdu) < 6:
            raise MbErr(ILLEGAL_VALUE)
        start, qty, bc = struct.unpack('>HHB', pdu[1:6])
        if not (1 <= qty <= 123) or bc != 2 * qty or len(pdu) != 6 + bc:
            raise MbErr(ILLEGAL_VALUE)
        if start + qty > 0x10000:
            raise MbErr(ILLEGAL_ADDRESS)
        ws = list(struct.unpack('>%dH' % qty, pdu[6:6 + bc]))
        dev.write_regs(start, ws)
        return bytes(pdu[0:5])
    if fc == 0x2B:
        return fc43(pdu)
    if fc in (0x41, 0x42):
        if len(pdu) < 5:
            raise MbErr(ILLEGAL_VALUE)
        raw = pdu[1:5]
        try:
            txt = bytes(raw[::-1]).decode('ascii')
        except UnicodeDecodeError:
            raise MbErr(ILLEGAL_ADDRESS)
        mn = txt.rstrip(' ')
        if txt != mn.ljust(4) or mn not in MFG_CONFIG and mn not in MFG_PROGRAM:
            raise MbErr(ILLEGAL_ADDRESS)
        if fc == 0x41:
            if mn in MFG_PROGRAM:
                data = b''
                if len(pdu) > 5:
                    bc = pdu[5]
                    if len(pdu) != 6 + bc or bc > 28:
                        raise MbErr(ILLEGAL_VALUE)
                    data = bytes(pdu[6:])
                dev.program_cmd(mn, data)
                return bytes([0x41, 0])
            if len(pdu) != 5:
                raise MbErr(ILLEGAL_VALUE)
            s = dev.mfg_read(mn).encode('ascii')
            return bytes([0x41, len(s)]) + s
        # 0x42
        if len(pdu) < 6:
            raise MbErr(ILLEGAL_VALUE)
        bc = pdu[5]
        if bc > 28 or len(pdu) != 6 + bc:
            raise MbErr(ILLEGAL_VALUE)
        data = bytes(pdu[6:])
        if mn in MFG_PROGRAM:
            dev.program_cmd(mn, data)
        else:
            if bc == 0:
                raise MbErr(ILLEGAL_VALUE)
            dev.mfg_write(mn, data)
        return bytes([0x42, bc]) + bytes(raw)
    raise MbErr(ILLEGAL_FUNCTION)


# ---------------------------------------------------------------- TCP server
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
        except Exception as e:   # never die because of the dump
            print('state dump failed: %s' % e, file=sys.stderr)

    async def client(self, reader, writer):
        dev = self.dev
        dev.counters['connections'] += 1
        buf = b''
        try:
            while True:
                data = await reader.read(4096)
                if not data:
                    break
                buf += data
                while len(buf) >= 7:
                    tid, proto, length, unit = struct.unpack('>HHHB', buf[:7])
                    if length < 2 or length > 254:
                        # cannot resynchronise a byte stream: drop the connection
                        dev.counters['discarded_frames'] += 1
                        writer.close()
                        return
                    if len(buf) < 6 + length:
                        break
                    pdu = buf[7:6 + length]
                    buf = buf[6 + length:]
                    if proto != 0:
                        dev.counters['discarded_frames'] += 1
                        continue
                    dev.counters['requests'] += 1
                    try:
                        resp = handle_pdu(dev, pdu)
                    except MbErr as e:
                        dev.counters['exceptions'] += 1
                        resp = bytes([(pdu[0] | 0x80) & 0xFF, e.code])
                    except Exception as e:   # defensive: report a device failure
                        print('internal error: %r' % e, file=sys.stderr)
                        dev.counters['exceptions'] += 1
                        resp = bytes([(pdu[0] | 0x80) & 0xFF, DEVICE_FAILURE])
                    dev.counters['responses'] += 1
                    writer.write(struct.pack('>HHHB', tid, 0, len(resp) + 1, unit) + resp)
                await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError, OSError,
                asyncio.CancelledError):
            pass
        finally:
            try:
                writer.close()
            except Exception:
                pass

    async def ticker(self):
        while True:
            await asyncio.sleep(0.01)
            try:
                self.dev.tick()
            except Exception as e:
                print('tick error: %r' % e, file=sys.stderr)

    async def main(self, host, port):
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        loop.add_signal_handler(signal.SIGTERM, stop.set)
        loop.add_signal_handler(signal.SIGINT, stop.set)
        loop.add_signal_handler(signal.SIGUSR1, self.save_state)
        srv = await asyncio.start_server(self.client, host, port, reuse_address=True)
        p = srv.sockets[0].getsockname()[1]
        sys.stdout.write('listening tcp %s:%d\n' % (host, p))
        sys.stdout.flush()
        t = asyncio.ensure_future(self.ticker())
        await stop.wait()
        srv.close()
        self.save_state()
        sys.stdout.flush()
        os._exit(0)


def main():
    ap = argparse.ArgumentParser(description='MDrive Hybrid Modbus/TCP simulator')
    ap.add_argument('--listen', required=True, help='127.0.0.1:PORT')
    ap.add_argument('--state', default=None)
    a = ap.parse_args()
    host, _, port = a.listen.rpartition(':')
    if host not in ('127.0.0.1', 'localhost', '::1', '[::1]'):
        ap.error('only loopback addresses are allowed')
    host = host.strip('[]')
    if host == 'localhost':
        host = '127.0.0.1'
    asyncio.run(Server(a.state).main(host, int(port)))
    os._exit(0)


if __name__ == '__main__':
    main()
