#!/usr/bin/env python3
"""MDrive Hybrid (Ethernet, MODBUS/TCP) drive simulator.

Written from the IMS/SEM "MODBUS/TCP Fieldbus Manual" rev. R040611 and the public
MODBUS specifications only.  See DECISIONS.md for every place where the manual can be
read two ways and the reading this firmware implements.

Standard library only.  Usage:
    python3 sim.py --listen 127.0.0.1:0 [--state FILE]
"""
import argparse
import asyncio
import json
import os
import signal
import sys
import time

# ---------------------------------------------------------------------------
# Exceptions
ILLEGAL_FUNCTION = 0x01
ILLEGAL_ADDRESS = 0x02
ILLEGAL_VALUE = 0x03
DEVICE_FAILURE = 0x04


class MbExc(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# ---------------------------------------------------------------------------
# Register map (MDrive Hybrid).  width = number of 16-bit registers.
# access: 'rw', 'ro', 'wo' (write-only command)
class Item:
    def __init__(self, addr, mn, width=1, access='rw', lo=0, hi=255,
                 default=0, signed=False, kind='value'):
        self.addr = addr
        self.mn = mn
        self.width = width
        self.access = access
        self.lo = lo
        self.hi = hi
        self.default = default
        self.signed = signed
        self.kind = kind


S32_MIN, S32_MAX = -2147483648, 2147483647

ITEMS = [
    Item(0x0000, 'A', 2, 'rw', 91, 1525878997, 1000000),
    Item(0x0005, 'C1', 2, 'rw', S32_MIN, S32_MAX, 0, True),
    Item(0x0007, 'C2', 2, 'rw', S32_MIN, S32_MAX, 0, True),
    Item(0x0009, 'CE', 1, 'rw', 0, 1, 1),
    # 0x000B CM: MDrivePlus only -> absent on the Hybrid
    Item(0x000F, 'D1', 1, 'rw', 0, 255, 0),
    Item(0x0010, 'D2', 1, 'rw', 0, 255, 0),
    Item(0x0011, 'D3', 1, 'rw', 0, 255, 0),
    Item(0x0012, 'D4', 1, 'rw', 0, 255, 0),
    Item(0x0013, 'D5', 1, 'rw', 0, 255, 0),
    Item(0x0018, 'D', 2, 'rw', 91, 1525878997, 1000000),
    # 0x001A DB: MDrivePlus only -> absent
    Item(0x001B, 'DC', 1, 'wo', 0, 0xFFFF, None, kind='cmd'),
    Item(0x001C, 'DE', 1, 'rw', 0, 1, 1),
    Item(0x001E, 'EE', 1, 'rw', 0, 1, 0),
    Item(0x001F, 'EF', 1, 'ro', 0, 1, 0),
    Item(0x0021, 'ER', 1, 'rw', 0, 0, 0),          # only 0 may be written
    Item(0x0029, 'HC', 1, 'rw', 0, 100, 5),
    Item(0x002B, 'HM', 1, 'rw', 1, 4, 0),          # blank default -> 0 (unset)
    Item(0x002C, 'HT', 1, 'rw', 0, 65535, 500),    # 0 or 2..65535
    Item(0x002D, 'I1', 1, 'ro', 0, 1, 0, kind='input'),
    Item(0x002E, 'I2', 1, 'ro', 0, 1, 0, kind='input'),
    Item(0x002F, 'I3', 1, 'ro', 0, 1, 0, kind='input'),
    Item(0x0030, 'I4', 1, 'ro', 0, 1, 0, kind='input'),
    Item(0x0031, 'I5', 1, 'ro', 0, 1023, 0),
    # 0x0032 I6: MDrivePlus only -> absent
    Item(0x0037, 'IC', 1, 'wo', 0, 0xFFFF, None, kind='cmd'),
    Item(0x003A, 'IL', 1, 'ro', 0, 0x15, 0, kind='calc'),
    Item(0x003B, 'IN', 1, 'ro', 0, 0x15, 0, kind='calc'),
    Item(0x003F, 'JE', 1, 'rw', 0, 1, 0),
    Item(0x0042, 'LM', 1, 'rw', 1, 6, 1),
    Item(0x0043, 'MA', 2, 'wo', S32_MIN, S32_MAX, None, True, kind='cmd'),
    Item(0x0045, 'MP', 1, 'ro', 0, 1, 0),
    Item(0x0046, 'MR', 2, 'wo', S32_MIN, S32_MAX, None, True, kind='cmd'),
    Item(0x0048, 'MS', 1, 'rw', 0, 255, 0),        # 1 byte; 256 is stored as 0
    Item(0x0049, 'MT', 1, 'rw', 0, 65000, 0),
    Item(0x004A, 'MV', 1, 'ro', 0, 1, 0),
    Item(0x004B, 'O1', 1, 'rw', 0, 1, 0, kind='output'),
    Item(0x004C, 'O2', 1, 'rw', 0, 1, 0, kind='output'),
    Item(0x004D, 'O3', 1, 'rw', 0, 1, 0, kind='output'),
    Item(0x004E, 'O4', 1, 'rw', 0, 1, 0, kind='output'),
    Item(0x0055, 'OL', 1, 'rw', 0, 15, 0, kind='calc'),
    Item(0x0056, 'OT', 1, 'rw', 0, 15, 0, kind='calc'),
    Item(0x0057, 'P', 2, 'rw', S32_MIN, S32_MAX, 0, True),
    Item(0x0059, 'PC', 2, 'ro', S32_MIN, S32_MAX, 0, True),
    # 0x005C PM: MDrivePlus only -> absent
    Item(0x005F, 'R1', 2, 'rw', S32_MIN, S32_MAX, 0, True),
    Item(0x0061, 'R2', 2, 'rw', S32_MIN, S32_MAX, 0, True),
    Item(0x0063, 'R3', 2, 'rw', S32_MIN, S32_MAX, 0, True),
    Item(0x0065, 'R4', 2, 'rw', S32_MIN, S32_MAX, 0, True),
    Item(0x0067, 'RC', 1, 'rw', 1, 100, 25),
    Item(0x0076, 'S', 1, 'wo', 0, 255, None, kind='cmd'),
    # 0x0077 SF: MDrivePlus only -> absent
    Item(0x0078, 'SL', 2, 'wo', -5000000, 5000000, None, True, kind='cmd'),
    # 0x007A SM, 0x007B ST: MDrivePlus only -> absent
    Item(0x007D, 'TE', 1, 'rw', 0, 43, 0),
    Item(0x0085, 'V', 2, 'ro', S32_MIN, S32_MAX, 0, True, kind='calc'),
    Item(0x0088, 'VC', 1, 'ro', 0, 1, 0),
    Item(0x0089, 'VI', 2, 'rw', 1, 4999999, 1000),
    Item(0x008B, 'VM', 2, 'rw', 2, 5000000, 768000),
    # 5.1 Hybrid specific registers
    Item(0x008E, 'AS', 1, 'rw', 0, 3, 2),
    Item(0x008F, 'AF', 1, 'ro', 0, 255, 0, kind='calc'),
    Item(0x0090, 'CA', 1, 'rw', 0, 1, 1),
    Item(0x0091, 'CB', 1, 'rw', 0, 3, 1),
    Item(0x0092, 'CC', 1, 'rw', 1, 100, 100),
    Item(0x0093, 'CF', 1, 'wo', 0, 255, None, kind='cmd'),
    Item(0x0094, 'CT', 1, 'rw', 2, 65535, 200),
    Item(0x0095, 'LD', 2, 'rw', 0, S32_MAX, 102400),
    Item(0x0097, 'LG', 2, 'rw', 0, S32_MAX, 102400),
    Item(0x0099, 'LL', 2, 'ro', -S32_MAX, S32_MAX, 0, True),
    Item(0x009B, 'LR', 1, 'ro', 0, 1, 0),
    Item(0x009C, 'LT', 1, 'rw', 2, 65535, 2000),   # 2 bytes; 0x009D unused
    Item(0x009E, 'MF', 2, 'rw', 306, 5000000, 768000),
    Item(0x00A0, 'MU', 1, 'rw', 0, 2, 0),
    Item(0x00A1, 'SC', 1, 'wo', 0, 255, None, kind='cmd'),
    Item(0x00A2, 'SS', 1, 'rw', 0, 255, 0),
    Item(0x00A5, 'TD', 1, 'rw', 0, 1, 1),
    Item(0x00A6, 'TQ', 1, 'rw', 1, 100, 25),
    Item(0x00A7, 'TS', 1, 'rw', 0, 255, 0),
]
# 5.2 User variables V1..V8: exist only once declared (VA) by a running MCode program.
USER_VARS = {0x00A8 + 2 * i: 'V%d' % (i + 1) for i in range(8)}

BY_ADDR = {}      # register address -> (item, offset within item)
BY_MN = {}
for _it in ITEMS:
    BY_MN[_it.mn] = _it
    for _o in range(_it.width):
        BY_ADDR[_it.addr + _o] = (_it, _o)

MS_VALUES = {1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256,
             180, 108, 127}
IO_INPUT_TYPES = {0, 1, 2, 3, 5, 7, 8, 11}
IO_OUTPUT_TYPES = {16, 17, 18, 20, 21, 23, 24, 25}

COIL_BASE = 0x004B
INPUT_BASE = 0x002D

# Device identification (MEI 0x0E).  Field widths are the manual's fixed widths.
DEVICE_ID = {
    0x00: b'SEM',                                 # 3 bytes
    0x01: b'MDO1M23A7-EQ',                         # "MDrive P/N", length as needed
    0x02: b'4.0.0.0'.ljust(8, b' '),              # 8 bytes
    0x03: b'www.imshome.com'.ljust(32, b' '),     # 32 bytes
    0x04: b'MDrive Eth',                          # 10 bytes
    0x05: b'110400123',                           # "Serial number", length as needed
    0x06: b'ASI 4.0.0.0'.ljust(12, b' '),         # 12 bytes
}


def to_u16_words(value, width, signed):
    if width == 1:
        return [value & 0xFFFF]
    v = value & 0xFFFFFFFF
    return [(v >> 16) & 0xFFFF, v & 0xFFFF]      # high word first


def from_words(words, signed):
    if len(words) == 1:
        v = words[0]
        return v
    v = (words[0] << 16) | words[1]
    if signed and v & 0x80000000:
        v -= 0x100000000
    return v


def bcd(n):
    return ((n // 10) << 4) | (n % 10)


# ---------------------------------------------------------------------------
class Drive:
    TICK = 0.005

    def __init__(self):
        self.regs = {it.mn: it.default for it in ITEMS if it.kind == 'value'}
        self.regs['MS'] = 256                    # stored value; wire shows 256 & 0xFF
        self.out_latch = [0, 0, 0, 0]
        self.inputs = [0, 0, 0, 0]               # nothing wired: inactive
        self.io_cfg = [[0, 0, 0] for _ in range(4)]   # S1..S4 = 0,0,0 (GP in, act lo, sink)
        self.clk_cfg = {'S7': [33, 0], 'S8': [33, 0]}
        self.s5 = [9, 0]
        self.s13 = [60, 0]
        self.cr = '1.000'
        self.tr = [0, 0, 0]
        self.mu_param = 0
        self.program = 'none'                    # no MCode program is resident
        self.trip_ref = 0
        # motion
        self.pos = 0.0
        self.vel = 0.0
        self.target = None           # absolute target for MA/MR
        self.slew = None             # signed slew velocity for SL
        self.counters = {'requests': 0, 'responses': 0, 'exceptions': 0,
                         'discarded_frames': 0, 'connections': 0}

    # -------------------------------------------------------------- motion
    def moving(self):
        return self.target is not None or self.slew is not None or abs(self.vel) > 0

    def tick(self, dt):
        r = self.regs
        if self.target is None and self.slew is None and self.vel == 0:
            r['MV'] = 0
            r['MP'] = 0
            r['VC'] = 0
            return
        acc, dec = float(r['A']), float(r['D'])
        vi = float(r['VI'])
        old_v = self.vel
        if self.slew is not None:
            tv = float(self.slew)
            if tv == 0 and abs(self.vel) <= vi:
                self.vel = 0.0
                self.slew = None
            else:
                if self.vel == 0 and tv != 0:
                    self.vel = vi if tv > 0 else -vi
                    if abs(tv) < vi:
                        self.vel = tv
                dv = tv - self.vel
                rate = acc if abs(tv) > abs(self.vel) and tv * self.vel >= 0 else dec
                step = rate * dt
                if abs(dv) <= step:
                    self.vel = tv
                else:
                    self.vel += step if dv > 0 else -step
                if tv == 0 and abs(self.vel) <= vi:
                    self.vel = 0.0
                    self.slew = None
            self._advance(self.vel * dt)
        elif self.target is not None:
            dist = self.target - self.pos
            if abs(dist) < 0.5:
                self.pos = float(self.target)
                self.vel = 0.0
                self.target = None
            else:
                d = 1.0 if dist > 0 else -1.0
                sp = abs(self.vel)
                if sp == 0:
                    sp = vi
                stop_dist = (sp * sp - vi * vi) / (2 * dec) if sp > vi else 0.0
                if abs(dist) <= stop_dist + sp * dt:
                    sp = max(vi, sp - dec * dt)
                else:
                    sp = min(float(r['VM']), sp + acc * dt)
                mv = sp * dt
                if mv >= abs(dist):
                    self._advance(dist)
                    self.pos = float(self.target)
                    self.vel = 0.0
                    self.target = None
                else:
                    self.vel = d * sp
                    self._advance(d * mv)
        else:
            self.vel = 0.0
        r['VC'] = 1 if (self.vel != old_v and self.moving()) else 0
        r['MV'] = 1 if self.moving() else 0
        r['MP'] = 1 if self.target is not None else 0

    def _advance(self, delta):
        old = int(round(self.pos))
        self.pos += delta
        if self.pos > S32_MAX:
            self.pos -= 2 ** 32
        elif self.pos < S32_MIN:
            self.pos += 2 ** 32
        new = int(round(self.pos))
        steps = new - old
        r = self.regs
        r['P'] = new
        r['C1'] = wrap32(r['C1'] + steps)
        if r['EE']:
            r['C2'] = wrap32(r['C2'] + steps)
        if (r['TE'] & 16) and self.tr[0] != 0 and abs(new - self.trip_ref) >= abs(self.tr[0]):
            r['TE'] &= ~16          # trip fired; must be re-enabled via 0x007D

    # -------------------------------------------------------------- I/O
    def point_state(self, i):
        """Logic state (1 = ON/active) of I/O point i (0..3)."""
        t = self.io_cfg[i][0]
        if t in IO_INPUT_TYPES:
            return self.inputs[i]
        r = self.regs
        if t == 16:
            return self.out_latch[i]
        if t == 17:
            return r['MV']
        if t == 18:
            return r['EF']
        if t == 20:
            return r['VC']
        if t == 21:
            return r['LR']
        if t == 23:
            return r['MP']
        if t == 24:
            return 1 if self.hybrid_active() else 0
        return 0    # 25 make-up active: no make-up in progress

    def coil_state(self, i):
        return self.point_state(i) if self.io_cfg[i][0] in IO_OUTPUT_TYPES else 0

    def input_state(self, i):
        return self.point_state(i)

    def input_mask(self):
        return sum(self.input_state(i) << i for i in range(4))

    def output_mask(self):
        return sum(self.coil_state(i) << i for i in range(4))

    def hybrid_active(self):
        return self.regs['AS'] != 0 and self.regs['DE'] == 1

    def af(self):
        v = 128                               # calibration complete
        if self.hybrid_active():
            v |= 16
        if self.regs['LL'] == 0:
            v |= 64
        if self.regs['LR']:
            v |= 8
        return v

    # -------------------------------------------------------------- register reads
    def read_regs(self, start, qty):
        out = []
        a = start
        end = start + qty
        while a < end:
            if a in USER_VARS or a - 1 in USER_VARS:
                raise MbExc(ILLEGAL_ADDRESS)
            ent = BY_ADDR.get(a)
            if ent is None:
                raise MbExc(ILLEGAL_ADDRESS)
            it, off = ent
            if off != 0:
                raise MbExc(ILLEGAL_ADDRESS)       # starts inside a 32-bit item
            if it.access == 'wo':
                raise MbExc(ILLEGAL_ADDRESS)
            if a + it.width > end:
                raise MbExc(ILLEGAL_VALUE)         # quantity splits a 32-bit item
            a += it.width
        # all checks passed: build values (reads of ER clear it afterwards)
        a = start
        clear_er = False
        while a < end:
            it, _ = BY_ADDR[a]
            out.extend(to_u16_words(self.item_value(it), it.width, it.signed))
            if it.mn == 'ER':
                clear_er = True
            a += it.width
        if clear_er:
            self.regs['ER'] = 0
            self.regs['EF'] = 0
        return out

    def item_value(self, it):
        mn = it.mn
        r = self.regs
        if it.kind == 'input':
            return self.input_state(int(mn[1]) - 1)
        if it.kind == 'output':
            return self.coil_state(int(mn[1]) - 1)
        if mn in ('IL', 'IN'):
            return bcd(self.input_mask())
        if mn in ('OL', 'OT'):
            return self.output_mask()
        if mn == 'V':
            if r['AS'] == 3:
                return 0
            return int(round(self.vel))
        if mn == 'AF':
            return self.af()
        if mn == 'MS':
            return r['MS'] & 0xFF
        return r[mn]

    # -------------------------------------------------------------- register writes
    def write_regs(self, start, words):
        end = start + len(words)
        plan = []
        a = start
        while a < end:
            if a in USER_VARS or a - 1 in USER_VARS:
                raise MbExc(ILLEGAL_ADDRESS)
            ent = BY_ADDR.get(a)
            if ent is None:
                raise MbExc(ILLEGAL_ADDRESS)
            it, off = ent
            if off != 0 or it.access == 'ro':
                raise MbExc(ILLEGAL_ADDRESS)
            if a + it.width > end:
                raise MbExc(ILLEGAL_VALUE)
            i = a - start
            val = from_words(words[i:i + it.width], it.signed)
            plan.append((it, val))
            a += it.width
        # validate every value before applying any (the write is all or nothing)
        pending = {}
        for it, val in plan:
            self.check_value(it, val, pending)
            pending[it.mn] = val
        for it, val in plan:
            self.precheck_exec(it, val)
        for it, val in plan:
            self.apply(it, val)

    def check_value(self, it, val, pending):
        mn = it.mn
        r = dict(self.regs)
        r.update(pending)
        if mn == 'MS':
            if val == 0:
                return                      # 0 is the 1-byte image of 256
            if val not in MS_VALUES or val > 255:
                raise MbExc(ILLEGAL_VALUE)
            return
        if mn == 'HT':
            if val == 1 or val + r['MT'] > 65535:
                raise MbExc(ILLEGAL_VALUE)
            return
        if mn == 'MT':
            if not 0 <= val <= 65000 or val + r['HT'] > 65535:
                raise MbExc(ILLEGAL_VALUE)
            return
        if mn == 'VI':
            if not 1 <= val <= r['VM'] - 1:
                raise MbExc(ILLEGAL_VALUE)
            return
        if mn == 'VM':
            if not r['VI'] + 1 <= val <= 5000000:
                raise MbExc(ILLEGAL_VALUE)
            return
        if mn in ('IC', 'DC'):
            tgt = BY_ADDR.get(val)
            if tgt is None or tgt[1] != 0 or tgt[0].mn not in INCDEC_TARGETS:
                raise MbExc(ILLEGAL_VALUE)
            cur = r[tgt[0].mn]
            nv = cur + (1 if mn == 'IC' else -1)
            if not S32_MIN <= nv <= S32_MAX:
                raise MbExc(ILLEGAL_VALUE)
            return
        if mn in ('O1', 'O2', 'O3', 'O4'):
            if val not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            if self.io_cfg[int(mn[1]) - 1][0] != 16:
                raise MbExc(ILLEGAL_ADDRESS)    # point is not a general purpose output
            return
        if mn in ('OL', 'OT'):
            if not 0 <= val <= 15:
                raise MbExc(ILLEGAL_VALUE)
            for i in range(4):
                if (val >> i) & 1 and self.io_cfg[i][0] != 16:
                    raise MbExc(ILLEGAL_VALUE)
            return
        if not it.lo <= val <= it.hi:
            raise MbExc(ILLEGAL_VALUE)

    def precheck_exec(self, it, val):
        mn = it.mn
        if mn in ('MA', 'MR'):
            if self.regs['DE'] == 0 or self.moving():
                raise MbExc(DEVICE_FAILURE)
            if mn == 'MR' and not S32_MIN <= int(round(self.pos)) + val <= S32_MAX:
                raise MbExc(DEVICE_FAILURE)     # would leave the position counter range
        elif mn == 'SL':
            if self.regs['DE'] == 0 or self.target is not None:
                raise MbExc(DEVICE_FAILURE)
        elif mn == 'P':
            if self.moving():
                raise MbExc(DEVICE_FAILURE)

    def apply(self, it, val):
        mn = it.mn
        r = self.regs
        if mn == 'MA':
            self.target = val
            self.slew = None
        elif mn == 'MR':
            self.target = int(round(self.pos)) + val
        elif mn == 'SL':
            self.slew = val
            if val == 0 and self.vel == 0:
                self.slew = None
        elif mn == 'P':
            r['P'] = val
            self.pos = float(val)
        elif mn in ('IC', 'DC'):
            t = BY_ADDR[val][0].mn
            r[t] = r[t] + (1 if mn == 'IC' else -1)
            if t == 'P':
                self.pos = float(r['P'])
        elif mn == 'S':
            pass                                # working memory -> NVM: nothing visible
        elif mn in ('CF',):
            r['LR'] = 0
        elif mn == 'SC':
            pass                                # timed calibration (CT in microseconds)
        elif mn in ('O1', 'O2', 'O3', 'O4'):
            self.out_latch[int(mn[1]) - 1] = val
        elif mn in ('OL', 'OT'):
            for i in range(4):
                if self.io_cfg[i][0] == 16:
                    self.out_latch[i] = (val >> i) & 1
        elif mn == 'MS':
            r['MS'] = 256 if val == 0 else val
        elif mn == 'ER':
            r['ER'] = 0
            r['EF'] = 0
        elif mn == 'TE':
            r['TE'] = val
            self.trip_ref = r['P']
        elif mn == 'DE':
            r['DE'] = val
            if val == 0:
                self.target = None
                self.slew = None
                self.vel = 0.0
                r['MV'] = r['MP'] = r['VC'] = 0
        else:
            r[mn] = val

    # -------------------------------------------------------------- vendor functions
    def vendor_read(self, mn, extra):
        if mn == 'EX':
            label = extra
            if not (1 <= len(label) <= 4) or not all(0x21 <= c <= 0x7E for c in label):
                raise MbExc(ILLEGAL_VALUE)
            raise MbExc(DEVICE_FAILURE)         # no resident program to execute
        if extra:
            raise MbExc(ILLEGAL_VALUE)
        if mn == 'E':
            self.program = 'none'
            return ''
        if mn == 'PS':
            if self.program != 'running':
                raise MbExc(DEVICE_FAILURE)
            self.program = 'paused'
            return ''
        if mn == 'RS':
            if self.program != 'paused':
                raise MbExc(DEVICE_FAILURE)
            self.program = 'running'
            return ''
        vals = self.vendor_values(mn)
        return ', '.join(vals)

    def vendor_values(self, mn):
        if mn in ('S1', 'S2', 'S3', 'S4'):
            return [str(x) for x in self.io_cfg[int(mn[1]) - 1]]
        if mn in ('S7', 'S8'):
            return [str(x) for x in self.clk_cfg[mn]]
        if mn == 'S5':
            return [str(x) for x in self.s5]
        if mn == 'S13':
            return [str(x) for x in self.s13]
        if mn == 'CR':
            return [self.cr]
        if mn == 'TR':
            return [str(x) for x in self.tr]
        if mn == 'MU':
            return [str(self.regs['MU']), str(self.mu_param)]
        raise MbExc(ILLEGAL_ADDRESS)

    def vendor_write(self, mn, data):
        if mn not in VENDOR_WRITABLE:
            raise MbExc(ILLEGAL_ADDRESS)
        lo, hi = VENDOR_WRITABLE[mn]
        if not lo <= len(data) <= hi:
            raise MbExc(ILLEGAL_VALUE)
        try:
            s = data.decode('ascii')
        except UnicodeDecodeError:
            raise MbExc(ILLEGAL_VALUE)
        if not s.startswith('='):
            raise MbExc(ILLEGAL_VALUE)
        body = s[1:]
        if mn == 'CR':
            t = body.strip()
            try:
                if not t or t.startswith(('+', '-')) or not all(c.isdigit() or c == '.' for c in t):
                    raise ValueError
                f = float(t)
            except ValueError:
                raise MbExc(ILLEGAL_VALUE)
            if f <= 0 or f > 99.999:
                raise MbExc(ILLEGAL_VALUE)
            self.cr = '%.3f' % f
            return
        parts = [p.strip() for p in body.split(',')]
        nums = []
        for p in parts:
            if not p or not (p.lstrip('-').isdigit()) or (p.startswith('-') and mn != 'TR'):
                raise MbExc(ILLEGAL_VALUE)
            nums.append(int(p))
        if mn in ('S1', 'S2', 'S3', 'S4'):
            if len(nums) != 3:
                raise MbExc(ILLEGAL_VALUE)
            a, b, c = nums
            if a not in IO_INPUT_TYPES | IO_OUTPUT_TYPES or b not in (0, 1) or c not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            i = int(mn[1]) - 1
            if a != 16:
                self.out_latch[i] = 0
            self.io_cfg[i] = [a, b, c]
        elif mn in ('S7', 'S8'):
            if len(nums) != 2 or nums[0] not in (33, 34, 35, 49, 50, 51) or nums[1] not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            self.clk_cfg[mn] = nums
        elif mn == 'S5':
            if len(nums) != 2 or nums[0] not in (9, 10) or nums[1] not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            self.s5 = nums
        elif mn == 'S13':
            if len(nums) != 2 or nums[0] not in (60, 61) or nums[1] not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            self.s13 = nums
        elif mn == 'MU':
            if len(nums) != 2 or nums[0] not in (0, 1, 2) or nums[1] not in (0, 1):
                raise MbExc(ILLEGAL_VALUE)
            self.regs['MU'] = nums[0]
            self.mu_param = nums[1]
            if nums[1] == 1:
                self.regs['LL'] = 0            # clear lead/lag
        elif mn == 'TR':
            if not 1 <= len(nums) <= 3 or any(not S32_MIN <= n <= S32_MAX for n in nums):
                raise MbExc(ILLEGAL_VALUE)
            for k, n in enumerate(nums):
                self.tr[k] = n

    # -------------------------------------------------------------- state dump
    def snapshot(self):
        regs = {}
        for it in ITEMS:
            if it.access == 'wo':
                continue
            regs['0x%04X' % it.addr] = {'mnemonic': it.mn, 'value': self.item_value(it)}
        for a, n in USER_VARS.items():
            regs['0x%04X' % a] = {'mnemonic': n, 'value': None, 'declared': False}
        return {
            'device': 'MDrive Hybrid (MODBUS/TCP)',
            'holding_registers': regs,
            'coils': {'0x%04X' % (COIL_BASE + i): self.coil_state(i) for i in range(4)},
            'output_latches': {'O%d' % (i + 1): self.out_latch[i] for i in range(4)},
            'discrete_inputs': {'0x%04X' % (INPUT_BASE + i): self.input_state(i) for i in range(4)},
            'vendor_parameters': {
                'S1': self.io_cfg[0], 'S2': self.io_cfg[1], 'S3': self.io_cfg[2],
                'S4': self.io_cfg[3], 'S5': self.s5, 'S7': self.clk_cfg['S7'],
                'S8': self.clk_cfg['S8'], 'S13': self.s13, 'CR': self.cr,
                'TR': self.tr, 'MU': [self.regs['MU'], self.mu_param],
            },
            'program_state': self.program,
            'device_identification': {'0x%02X' % k: v.decode() for k, v in DEVICE_ID.items()},
            'diagnostic_counters': dict(self.counters),
        }


INCDEC_TARGETS = {'R1', 'R2', 'R3', 'R4', 'C1', 'C2', 'P'}
VENDOR_READABLE = {'S1', 'S2', 'S3', 'S4', 'S5', 'S7', 'S8', 'S13', 'CR', 'TR', 'MU',
                   'E', 'EX', 'PS', 'RS'}
# mnemonic -> (min, max) parameter data length in bytes (manual section 4.3.1)
VENDOR_WRITABLE = {'S1': (6, 7), 'S2': (6, 7), 'S3': (6, 7), 'S4': (6, 7),
                   'S7': (4, 5), 'S8': (4, 5), 'S5': (4, 5), 'S13': (4, 5),
                   'CR': (2, 6), 'TR': (2, 11), 'MU': (4, 4)}


def wrap32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


def decode_mnemonic(b):
    """4 bytes, ASCII of the mnemonic in reverse order, padded with spaces at the front."""
    s = bytes(reversed(b))
    try:
        t = s.decode('ascii')
    except UnicodeDecodeError:
        return None
    core = t.rstrip(' ')
    if not core or ' ' in core or not all(c.isalnum() for c in core):
        return None
    return core


# ---------------------------------------------------------------------------
# PDU processing
def exc(fc, code):
    return bytes([(fc | 0x80) & 0xFF, code])


def handle_pdu(drive, pdu):
    fc = pdu[0]
    try:
        if fc == 0x01:
            return fc_read_bits(drive, pdu, COIL_BASE, drive.coil_state)
        if fc == 0x02:
            return fc_read_bits(drive, pdu, INPUT_BASE, drive.input_state)
        if fc == 0x03:
            return fc03(drive, pdu)
        if fc == 0x05:
            return fc05(drive, pdu)
        if fc == 0x10:
            return fc16(drive, pdu)
        if fc == 0x2B:
            return fc43(drive, pdu)
        if fc == 0x41:
            return fc41(drive, pdu)
        if fc == 0x42:
            return fc42(drive, pdu)
        raise MbExc(ILLEGAL_FUNCTION)
    except MbExc as e:
        drive.counters['exceptions'] += 1
        return exc(fc, e.code)
    except Exception:
        drive.counters['exceptions'] += 1
        return exc(fc, DEVICE_FAILURE)


def fc_read_bits(drive, pdu, base, getter):
    if len(pdu) != 5:
        raise MbExc(ILLEGAL_VALUE)
    start = int.from_bytes(pdu[1:3], 'big')
    qty = int.from_bytes(pdu[3:5], 'big')
    if not 1 <= qty <= 4:
        raise MbExc(ILLEGAL_VALUE)
    if start < base or start + qty > base + 4:
        raise MbExc(ILLEGAL_ADDRESS)
    v = 0
    for k in range(qty):
        v |= getter(start - base + k) << k
    return bytes([pdu[0], 1, v])


def fc03(drive, pdu):
    if len(pdu) != 5:
        raise MbExc(ILLEGAL_VALUE)
    start = int.from_bytes(pdu[1:3], 'big')
    qty = int.from_bytes(pdu[3:5], 'big')
    if not 1 <= qty <= 4:
        raise MbExc(ILLEGAL_VALUE)
    if start + qty > 0x10000:
        raise MbExc(ILLEGAL_ADDRESS)
    words = drive.read_regs(start, qty)
    body = b''.join(w.to_bytes(2, 'big') for w in words)
    return bytes([0x03, len(body)]) + body


def fc05(drive, pdu):
    if len(pdu) != 5:
        raise MbExc(ILLEGAL_VALUE)
    addr = int.from_bytes(pdu[1:3], 'big')
    val = int.from_bytes(pdu[3:5], 'big')
    if val not in (0x0000, 0xFF00):
        raise MbExc(ILLEGAL_VALUE)
    if not COIL_BASE <= addr < COIL_BASE + 4:
        raise MbExc(ILLEGAL_ADDRESS)
    i = addr - COIL_BASE
    if drive.io_cfg[i][0] != 16:
        raise MbExc(ILLEGAL_ADDRESS)
    drive.out_latch[i] = 1 if val == 0xFF00 else 0
    return bytes(pdu)


def fc16(drive, pdu):
    if len(pdu) < 6:
        raise MbExc(ILLEGAL_VALUE)
    start = int.from_bytes(pdu[1:3], 'big')
    qty = int.from_bytes(pdu[3:5], 'big')
    bc = pdu[5]
    if not 1 <= qty <= 2 or bc != 2 * qty or len(pdu) != 6 + bc:
        raise MbExc(ILLEGAL_VALUE)
    if start + qty > 0x10000:
        raise MbExc(ILLEGAL_ADDRESS)
    words = [int.from_bytes(pdu[6 + 2 * k:8 + 2 * k], 'big') for k in range(qty)]
    drive.write_regs(start, words)
    return bytes(pdu[0:5])


def fc43(drive, pdu):
    if len(pdu) < 2:
        raise MbExc(ILLEGAL_VALUE)
    if pdu[1] != 0x0E:
        raise MbExc(ILLEGAL_FUNCTION)
    if len(pdu) != 4:
        raise MbExc(ILLEGAL_VALUE)
    code, obj = pdu[2], pdu[3]
    if code not in (1, 2, 3, 4):
        raise MbExc(ILLEGAL_VALUE)
    if code == 4:
        if obj not in DEVICE_ID:
            raise MbExc(ILLEGAL_ADDRESS)
        ids = [obj]
    else:
        rng = (0, 2) if code == 1 else (0, 6)   # no extended objects exist
        if not rng[0] <= obj <= rng[1]:
            obj = rng[0]
        ids = list(range(obj, rng[1] + 1))
    body = b''
    for i in ids:
        v = DEVICE_ID[i]
        body += bytes([i, len(v)]) + v
    return bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)]) + body


def fc41(drive, pdu):
    if len(pdu) < 5:
        raise MbExc(ILLEGAL_VALUE)
    mn = decode_mnemonic(pdu[1:5])
    if mn is None or mn not in VENDOR_READABLE:
        raise MbExc(ILLEGAL_ADDRESS)
    extra = bytes(pdu[5:])
    text = drive.vendor_read(mn, extra).encode('ascii')
    n = len(text)
    data = text + (b'\x00' if n % 2 else b'')
    return bytes([0x41]) + n.to_bytes(2, 'big') + data


def fc42(drive, pdu):
    if len(pdu) < 6:
        raise MbExc(ILLEGAL_VALUE)
    bc = pdu[5]
    if not 1 <= bc <= 28 or len(pdu) != 6 + bc:
        raise MbExc(ILLEGAL_VALUE)
    mn = decode_mnemonic(pdu[1:5])
    if mn is None or mn not in VENDOR_WRITABLE:
        raise MbExc(ILLEGAL_ADDRESS)
    drive.vendor_write(mn, bytes(pdu[6:6 + bc]))
    return bytes([0x42, 0x04]) + bytes(pdu[1:5])


# ---------------------------------------------------------------------------
# Server
class Server:
    def __init__(self, drive, state_file):
        self.drive = drive
        self.state_file = state_file
        self.stop = None
        self.writers = set()

    def dump_state(self):
        if not self.state_file:
            return
        try:
            tmp = self.state_file + '.tmp'
            with open(tmp, 'w') as f:
                json.dump(self.drive.snapshot(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except OSError as e:
            print('state dump failed: %s' % e, file=sys.stderr)

    async def motion_loop(self):
        last = time.monotonic()
        while True:
            await asyncio.sleep(Drive.TICK)
            now = time.monotonic()
            dt = min(now - last, 0.1)
            last = now
            try:
                self.drive.tick(dt)
            except Exception as e:       # never let motion kill the server
                print('motion error: %r' % e, file=sys.stderr)

    async def client(self, reader, writer):
        d = self.drive
        d.counters['connections'] += 1
        self.writers.add(writer)
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid, pid, ln, uid = hdr[0:2], int.from_bytes(hdr[2:4], 'big'), \
                    int.from_bytes(hdr[4:6], 'big'), hdr[6]
                if ln < 1 or ln > 254:
                    d.counters['discarded_frames'] += 1
                    break                       # framing cannot be trusted any more
                body = await reader.readexactly(ln - 1)
                if pid != 0 or ln < 2:
                    d.counters['discarded_frames'] += 1
                    continue
                d.counters['requests'] += 1
                rsp = handle_pdu(d, body)
                d.counters['responses'] += 1
                writer.write(tid + b'\x00\x00' + (len(rsp) + 1).to_bytes(2, 'big')
                             + bytes([uid]) + rsp)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError,
                asyncio.CancelledError):
            pass
        finally:
            self.writers.discard(writer)
            try:
                writer.close()
            except Exception:
                pass

    async def run(self, host, port):
        loop = asyncio.get_running_loop()
        self.stop = asyncio.Event()
        for s in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(s, self.stop.set)
        loop.add_signal_handler(signal.SIGUSR1, self.dump_state)
        srv = await asyncio.start_server(self.client, host, port, reuse_address=True)
        mt = asyncio.create_task(self.motion_loop())
        p = srv.sockets[0].getsockname()[1]
        sys.stdout.write('listening tcp %s:%d\n' % (host, p))
        sys.stdout.flush()
        await self.stop.wait()
        mt.cancel()
        srv.close()
        for w in list(self.writers):
            try:
                w.close()
            except Exception:
                pass
        self.dump_state()


def main():
    ap = argparse.ArgumentParser(description='MDrive Hybrid MODBUS/TCP simulator')
    ap.add_argument('--listen', default='127.0.0.1:502')
    ap.add_argument('--state', default=None)
    a = ap.parse_args()
    host, _, port = a.listen.rpartition(':')
    if host not in ('127.0.0.1', 'localhost', '::1', '[::1]'):
        print('refusing to bind a non-loopback address', file=sys.stderr)
        sys.exit(2)
    host = host.strip('[]')
    asyncio.run(Server(Drive(), a.state).run(host, int(port)))
    os._exit(0)


if __name__ == '__main__':
    main()
