#!/usr/bin/python3
"""Lexium MDrive Ethernet (LMD, closed loop / hMTechnology) Modbus/TCP device simulator.

Written from the LMD MODBUS/TCP Fieldbus manual (LMD-MODBUS-REV-D) and the public Modbus
specifications only.  See DECISIONS.md for the interpretation of the manual.
Python 3.11 standard library only.
"""
import argparse
import json
import math
import os
import random
import re
import signal
import socket
import struct
import sys
import threading
import time

# ---------------------------------------------------------------------------------------------
# Register map (section 5).  width = number of 16-bit registers (2 => 32-bit value, low word first)
# access: RW, RO, WO ; kind: 'u' unsigned, 's' signed
# ---------------------------------------------------------------------------------------------
MS_ALLOWED = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)
I32 = (-2147483648, 2147483647)

# addr: (mcode, width, access, signed, lo, hi, factory_default)
REGS = {
    0x0000: ('A', 2, 'RW', True, 91, 1525878997, 1000000),
    0x0004: ('BY', 1, 'RO', False, 0, 1, 0),
    0x0005: ('C1', 2, 'RW', True, I32[0], I32[1], 0),
    0x0007: ('C2', 2, 'RW', True, I32[0], I32[1], 0),
    0x0009: ('CE', 1, 'RW', False, 0, 1, 1),
    0x000E: ('CW', 1, 'RW', False, 0, 255, 10),
    0x000F: ('D1', 1, 'RW', False, 0, 255, 0),
    0x0010: ('D2', 1, 'RW', False, 0, 255, 0),
    0x0011: ('D3', 1, 'RW', False, 0, 255, 0),
    0x0012: ('D4', 1, 'RW', False, 0, 255, 0),
    0x0013: ('D5', 1, 'RW', False, 0, 255, 0),
    0x0018: ('D', 2, 'RW', True, 91, 1525878997, 1000000),
    0x001A: ('DB', 1, 'RW', False, 0, 65000, 10),
    0x001B: ('DC', 1, 'WO', False, 0, 65535, None),
    0x001C: ('DE', 1, 'RW', False, 0, 1, 1),
    0x001E: ('EE', 1, 'RW', False, 0, 1, 0),
    0x001F: ('EF', 1, 'RO', False, 0, 1, 0),
    0x0021: ('ER', 1, 'RW', False, 0, 0, 0),
    0x0024: ('FC', 1, 'RW', False, 0, 9, 0),
    0x0029: ('HC', 1, 'RW', False, 0, 100, 5),
    0x002A: ('HI', 1, 'WO', False, 1, 4, None),
    0x002B: ('HM', 1, 'WO', False, 1, 4, None),
    0x002C: ('HT', 1, 'RW', False, 0, 65535, 500),
    0x002D: ('I1', 1, 'RO', False, 0, 1, None),
    0x002E: ('I2', 1, 'RO', False, 0, 1, None),
    0x002F: ('I3', 1, 'RO', False, 0, 1, None),
    0x0030: ('I4', 1, 'RO', False, 0, 1, None),
    0x0031: ('I5', 1, 'RO', False, 0, 1023, None),
    0x0032: ('I6', 1, 'RO', False, 0, 1, None),
    0x0037: ('IC', 1, 'WO', False, 0, 65535, None),
    0x003B: ('IN', 1, 'RO', False, 0, 15, None),
    0x003C: ('IP', 1, 'WO', False, 0, 65535, None),
    0x003F: ('JE', 1, 'RW', False, 0, 1, 0),
    0x0042: ('LM', 1, 'RW', False, 1, 6, 1),
    0x0043: ('MA', 2, 'WO', True, I32[0], I32[1], None),
    0x0045: ('MP', 1, 'RO', False, 0, 1, 0),
    0x0046: ('MR', 2, 'WO', True, I32[0], I32[1], None),
    0x0048: ('MS', 1, 'RW', False, 1, 256, 256),
    0x0049: ('MT', 1, 'RW', False, 0, 65000, 0),
    0x004A: ('MV', 1, 'RO', False, 0, 1, 0),
    0x004B: ('O1', 1, 'RW', False, 0, 1, None),
    0x004C: ('O2', 1, 'RW', False, 0, 1, None),
    0x004D: ('O3', 1, 'RW', False, 0, 1, None),
    0x004E: ('OF', 1, 'RO', False, 0, 1, 0),
    0x0056: ('OT', 1, 'RW', False, 0, 15, None),
    0x0057: ('P', 2, 'RW', True, I32[0], I32[1], 0),
    0x0059: ('PC', 2, 'RO', True, I32[0], I32[1], 0),
    0x005C: ('PM', 1, 'RW', False, 0, 1, 0),
    0x005F: ('R1', 2, 'RW', True, I32[0], I32[1], 0),
    0x0061: ('R2', 2, 'RW', True, I32[0], I32[1], 0),
    0x0063: ('R3', 2, 'RW', True, I32[0], I32[1], 0),
    0x0065: ('R4', 2, 'RW', True, I32[0], I32[1], 0),
    0x0067: ('RC', 1, 'RW', False, 1, 100, 25),
    0x0076: ('S', 1, 'WO', False, 0, 65535, None),
    0x0077: ('SF', 1, 'RW', False, 0, 65000, 15),
    0x0078: ('SL', 2, 'WO', True, -5000000, 5000000, None),
    0x007A: ('SM', 1, 'RW', False, 0, 1, 0),
    0x007B: ('ST', 1, 'RO', False, 0, 1, 0),
    0x007D: ('TE', 1, 'RW', False, 0, 63, 0),
    0x0085: ('V', 2, 'RO', True, I32[0], I32[1], 0),
    0x0088: ('VC', 1, 'RO', False, 0, 1, 0),
    0x0089: ('VI', 2, 'RW', True, 1, 2559999, 1000),
    0x008B: ('VM', 2, 'RW', True, 2, 2560000, 768000),
    0x008D: ('WT', 1, 'RW', False, 0, 84, 80),
    0x008E: ('AS', 1, 'RW', False, 0, 3, 2),
    0x008F: ('AF', 1, 'RO', False, 0, 255, None),
    0x0091: ('CB', 1, 'RW', False, 0, 3, 1),
    0x0093: ('CF', 1, 'WO', False, 0, 65535, None),
    0x0095: ('LD', 2, 'RW', True, 0, 2147483647, 102400),
    0x0097: ('LG', 2, 'RW', True, 0, 2147483647, 102400),
    0x0099: ('LL', 2, 'RO', True, -2147483647, 2147483647, None),
    0x009B: ('LR', 1, 'RO', False, 0, 1, 0),
    0x009C: ('LT', 2, 'RW', True, 2, 65535, 2000),
    0x009E: ('MF', 2, 'RW', True, 306, 2560000, 768000),
    0x00A0: ('MU', 1, 'RW', False, 0, 2, 0),
    0x00A1: ('SC', 1, 'WO', False, 0, 65535, None),
    0x00A3: ('TS', 2, 'RW', True, 0, 255, 0),
    0x00A5: ('TD', 1, 'RW', False, 0, 1, 1),
    0x00A6: ('TQ', 1, 'RW', False, 1, 100, 25),
    0x00A7: ('VF', 1, 'RW', False, 0, 1000, 0),
}
for _i in range(8):
    REGS[0x00A8 + 2 * _i] = ('V%d' % (_i + 1), 2, 'RW', True, I32[0], I32[1], 0)
MAP_END = 0x00B7

# address -> (base, offset)
ADDR = {}
for _b, _d in REGS.items():
    for _o in range(_d[1]):
        ADDR[_b + _o] = (_b, _o)
NAME2ADDR = {d[0]: a for a, d in REGS.items()}

# Parameters held in working memory (copied by S, reset by IP)
PARAM_NAMES = [d[0] for a, d in sorted(REGS.items()) if d[2] == 'RW' and d[6] is not None
               and d[0] not in ('C1', 'C2', 'P', 'ER')]

IN_FUNCS = (0, 1, 2, 3, 5, 7, 8, 11, 12)
OUT_FUNCS = (16, 17, 18, 20, 21, 23, 24, 25, 28, 29)

FACTORY_IO = {1: [0, 0, 0], 2: [0, 0, 0], 3: [0, 0, 0], 4: [0, 0, 0]}
FACTORY_ANALOG = [9, 0]
FACTORY_MFG = {'AO': 0, 'RD': 0, 'AJ': 1, 'AT': 0, 'BE': 0, 'BL': 0, 'BM': 0, 'DJ': 1, 'DT': 0,
               'FS': 0, 'FL': 0, 'LS': [[0, 0, 0], [1, 0, 0]], 'MUB': 0, 'TR': [0, 0, 0]}

# ---------------- commissioned (customer) configuration ----------------
CUSTOMER_PARAMS = {
    'A': 256000, 'D': 384000, 'VI': 2000, 'VM': 128000, 'MS': 128,
    'RC': 60, 'HC': 10, 'HT': 750, 'MT': 50,
    'D1': 5, 'D4': 10, 'D5': 8, 'DB': 20, 'EE': 1, 'LM': 2, 'SF': 30, 'WT': 75,
    'CB': 2, 'LD': 51200, 'LG': 51200, 'LT': 1500, 'MF': 256000,
    'TS': 10, 'TQ': 40, 'VF': 100,
    'R1': 2500, 'R2': -1200, 'R4': 48213, 'V1': 100, 'V2': 3200,
}
CUSTOMER_IO = {1: [1, 0, 0],     # I/O 1: input, Homing, active low, sinking
               2: [16, 1, 0],    # I/O 2: output, general purpose, active high
               3: [17, 1, 0],    # I/O 3: output, Moving, active high
               4: [0, 1, 0]}     # I/O 4: input, general purpose, active high
CUSTOMER_ANALOG = [9, 1]         # voltage mode, 0-10 V
CUSTOMER_MFG = {'AO': 32841, 'RD': 1, 'AJ': 64, 'AT': 1, 'BE': 0, 'BL': 0, 'BM': 0, 'DJ': 64,
                'DT': 1, 'FS': 250, 'FL': 0,
                'LS': [[0, -256000, 1], [1, 5120000, 1]], 'MUB': 0, 'TR': [0, 0, 0]}
PROGRAM_LABELS = {'SU': 1, 'G1': 24, 'K1': 87, 'K2': 112}   # customer MCode program

# electrical level of the input pins on the bench (True = high)
BENCH_PIN_HIGH = {1: True, 2: False, 3: False, 4: True}

DEVICE_ID = {
    0: b'IMS USA',
    1: b'LMDCE572',
    2: b'4.0.0.2',
    3: b'https://novantaims.com/',
    4: b'LMD Ethernet',
    5: b'0416C1127',
    6: b'LMDCM 6.012, Hw: 2.0',
}


class ModbusExc(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


def to_s32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


class Drive:
    def __init__(self):
        self.lock = threading.RLock()
        self.t0 = time.monotonic()
        self.rng = random.Random(0x1D6F)
        self.params = {}
        for a, d in REGS.items():
            if d[0] in PARAM_NAMES:
                self.params[d[0]] = d[6]
        self.params.update(CUSTOMER_PARAMS)
        self.io = {k: list(v) for k, v in CUSTOMER_IO.items()}
        self.analog = list(CUSTOMER_ANALOG)
        self.mfg = json.loads(json.dumps(CUSTOMER_MFG))
        self.out_latch = {1: 0, 2: 0, 3: 0}
        self.labels = dict(PROGRAM_LABELS)
        self.nvm = self._snapshot_config()
        # dynamic state
        self.P = 0.0            # position counter (steps), float accumulator
        self.C1 = 0.0
        self.enc = 0.0          # encoder base (C2 without noise)
        self.phys_off = 5000.0  # physical position = P + phys_off (home flag edge at phys 0)
        self.v = 0.0            # profile velocity, steps/s (signed)
        self.mode = None        # None, 'pos', 'slew', 'home'
        self.target = 0
        self.slew_v = 0.0
        self.home_zero = False
        self.vchanging = 0
        self.ER = 0
        self.EF = 0
        self.PC = 0
        self.LR = 0
        self.lag_clear = 0.0
        self.calib_until = 0.0
        self.prog = None        # dict(label, remaining, paused)
        self.upgrade_until = None
        self.upgrade_pending = False
        self.heat = 0.0
        self.last_tick = time.monotonic()

    # ---------------- helpers ----------------
    def _snapshot_config(self):
        return json.loads(json.dumps({'params': self.params, 'io': self.io, 'analog': self.analog,
                                      'mfg': self.mfg, 'labels': self.labels}))

    def now(self):
        return time.monotonic() - self.t0

    def moving(self):
        return self.mode is not None

    def calibrating(self):
        return time.monotonic() < self.calib_until

    def is_output(self, n):
        return n in self.io and self.io[n][0] >= 16

    def output_state(self, n):
        """logic state of I/O point n configured as output"""
        f = self.io[n][0]
        if f == 16:
            return self.out_latch.get(n, 0)
        if f == 17:
            return 1 if self.moving() else 0
        if f == 18:
            return self.EF
        if f == 20:
            return self.vchanging
        if f == 21:
            return self.LR
        if f == 23:
            return 1 if self.mode == 'pos' else 0
        if f == 24:
            return 1 if self.hmt_active() else 0
        if f == 29:
            return 1 if (self.attention_bits() & self.mfg['AO']) else 0
        return 0

    def input_state(self, n):
        if self.is_output(n):
            return self.output_state(n)
        f, act = self.io[n][0], self.io[n][1]
        if f == 1:   # homing input: the bench home flag is wired to this point
            return 1 if (self.P + self.phys_off) <= 0.5 else 0
        else:
            high = BENCH_PIN_HIGH[n]
        return 1 if (high if act == 1 else not high) else 0

    def hmt_active(self):
        return self.params['AS'] != 0 and self.params['DE'] == 1 and not self.LR

    def attention_bits(self):
        b = 0
        if self.EF:
            b |= 1
        if self.LR:
            b |= 2
        if self.hmt_active():
            b |= 16
        if self.calibrating():
            b |= 32
        if self.params['DE'] == 0:
            b |= 2048
        if self.moving():
            b |= 16384
        return b

    # ---------------- live measured values ----------------
    def live_ll(self):
        noise = self.rng.randint(-3, 3)
        lag = 0.0
        if self.moving() and self.params['AS'] != 0:
            lag = self.v * 0.0004
        return int(round(lag)) + noise

    def live_c2(self):
        return to_s32(int(round(self.enc)) + self.rng.randint(-2, 2))

    def live_af(self):
        af = 0
        if self.hmt_active():
            af |= 16
        if self.LR:
            af |= 8
        ll = self.live_ll()
        if abs(ll) <= self.params['DB'] and not self.moving():
            af |= 64
        if not self.calibrating():
            af |= 128
        return af

    def live_i5(self):
        t = self.now()
        base = 4.0 + 1.5 * math.sin(t / 41.0)
        return max(0, min(1023, int(round(base + self.rng.gauss(0, 1.0)))))

    def live_i6(self):
        spr = 200 * self.params['MS'] if self.params['MS'] not in (180, 108, 127) else 36000
        ph = (self.P + self.phys_off) % spr
        return 1 if ph < 4 or ph > spr - 4 else 0

    def live_it(self):
        t = self.now()
        bridge = 36.0 + 5.0 * (1 - math.exp(-t / 900.0)) + 0.6 * math.sin(t / 113.0) + self.heat
        mcu = 33.0 + 3.0 * (1 - math.exp(-t / 600.0)) + 0.3 * math.sin(t / 71.0)
        bridge += self.rng.choice((-1, 0, 0, 0, 1)) * 0.6
        mcu += self.rng.choice((-1, 0, 0, 0, 1)) * 0.6
        return '%d,%d' % (int(round(bridge)), int(round(mcu)))

    def live_vt(self):
        t = self.now()
        aux = 24.0 + 0.3 * math.sin(t / 57.0) + self.rng.uniform(-0.55, 0.55)
        vp = 48.0 + 0.4 * math.sin(t / 89.0) + self.rng.uniform(-0.6, 0.6) - (0.7 if self.moving() else 0)
        return '%d,%d' % (int(round(aux)), int(round(vp)))

    def live_av(self):
        if not self.hmt_active():
            return 0
        n = self.rng.randint(-4, 4)
        return int(round(self.v)) + n

    # ---------------- motion ----------------
    def tick(self):
        with self.lock:
            now = time.monotonic()
            dt = min(0.1, now - self.last_tick)
            self.last_tick = now
            if self.upgrade_until is not None and now >= self.upgrade_until:
                self._reboot()
            if self.prog is not None and not self.prog['paused']:
                self.prog['remaining'] -= dt
                if self.prog['remaining'] <= 0:
                    self.prog = None
            if self.heat > 0 and not self.moving():
                self.heat = max(0.0, self.heat - dt * 0.002)
            if self.mode is None:
                self.v = 0.0
                self.vchanging = 0
                return
            if self.params['DE'] == 0:
                self._stop_now()
                return
            self.heat = min(6.0, self.heat + dt * 0.004 * self.params['RC'] / 100.0)
            A = float(self.params['A'])
            D = float(self.params['D'])
            VM = float(self.params['VM'])
            VI = float(self.params['VI'])
            old_v = self.v
            if self.mode in ('pos', 'home'):
                rem = self.target - self.P
                direction = 1.0 if rem > 0 else -1.0
                if abs(rem) < 0.5:
                    self._finish_pos()
                    return
                speed = abs(self.v)
                vmax = VM if self.mode == 'pos' else (VM if abs(rem) > 2000 else max(VI, 1.0))
                stop_dist = (speed * speed - VI * VI) / (2 * D) if speed > VI else 0.0
                if self.v * direction < 0:
                    speed = max(0.0, speed - D * dt)
                elif abs(rem) <= stop_dist + speed * dt:
                    speed = max(VI, speed - D * dt)
                elif speed < vmax:
                    speed = min(vmax, max(speed, VI) + A * dt)
                else:
                    speed = max(vmax, speed - D * dt)
                step = speed * dt
                if step >= abs(rem):
                    self._advance(rem)
                    self._finish_pos()
                    return
                self.v = direction * speed
                self._advance(direction * step)
            elif self.mode == 'slew':
                tv = self.slew_v
                if tv > self.v:
                    rate = A if self.v >= 0 else D
                    self.v = min(tv, self.v + rate * dt)
                elif tv < self.v:
                    rate = A if self.v <= 0 else D
                    self.v = max(tv, self.v - rate * dt)
                if tv == 0 and abs(self.v) <= VI:
                    self.v = 0.0
                    self.mode = None
                    self.vchanging = 0
                    return
                nxt = self.v * dt
                lim = self._limit_block(self.P + nxt, nxt)
                if lim is not None:
                    self._advance(lim - self.P)
                    self._stop_now()
                    return
                self._advance(nxt)
            self.vchanging = 1 if abs(self.v - old_v) > 1e-9 else 0

    def _advance(self, d):
        self.P += d
        if self.P > I32[1] or self.P < I32[0]:
            self.P = float(to_s32(int(self.P)))
        self.C1 += d
        if self.C1 > I32[1] or self.C1 < I32[0]:
            self.C1 = float(to_s32(int(self.C1)))
        self.enc += d

    def _finish_pos(self):
        self.P = float(self.target)
        if self.mode == 'home' and self.home_zero:
            self.phys_off += self.P
            self.P = 0.0
        self._stop_now()

    def _stop_now(self):
        self.mode = None
        self.v = 0.0
        self.vchanging = 0

    def _soft_limits(self):
        lo = hi = None
        for d, pos, en in self.mfg['LS']:
            if en:
                if d == 0:
                    lo = pos
                else:
                    hi = pos
        return lo, hi

    def _limit_block(self, newp, delta):
        lo, hi = self._soft_limits()
        if hi is not None and delta > 0 and newp > hi:
            return float(hi)
        if lo is not None and delta < 0 and newp < lo:
            return float(lo)
        return None

    def _hw_limit_active(self, direction):
        for n in (1, 2, 3, 4):
            f = self.io[n][0]
            if (f == 2 and direction > 0) or (f == 3 and direction < 0):
                if self.input_state(n):
                    return True
        return False

    def _check_motion_allowed(self, direction=0):
        if self.params['DE'] == 0 or self.LR or self.calibrating():
            raise ModbusExc(4)
        if direction and self._hw_limit_active(direction):
            raise ModbusExc(4)

    def start_move(self, target):
        target = to_s32(int(target))
        if self.mode is not None:
            raise ModbusExc(4)
        direction = 1 if target > self.P else (-1 if target < self.P else 0)
        self._check_motion_allowed(direction)
        lo, hi = self._soft_limits()
        if (hi is not None and target > hi) or (lo is not None and target < lo):
            raise ModbusExc(4)
        if direction == 0:
            return
        self.target = target
        self.mode = 'pos'
        self.v = 0.0

    def start_slew(self, vel):
        if self.mode in ('pos', 'home'):
            raise ModbusExc(4)
        if vel == 0:
            if self.mode == 'slew':
                self.slew_v = 0.0
            return
        self._check_motion_allowed(1 if vel > 0 else -1)
        self.slew_v = float(vel)
        self.mode = 'slew'

    def start_home(self, index=False, offset=0):
        if self.mode is not None:
            raise ModbusExc(4)
        self._check_motion_allowed()
        if not index:
            if not any(self.io[n][0] == 1 for n in (1, 2, 3, 4)):
                raise ModbusExc(4)      # no input configured as home switch
            tgt = -self.phys_off        # position where the home flag edge is
        else:
            spr = 200 * self.params['MS']
            ph = (self.P + self.phys_off) % spr
            tgt = self.P - ph + offset
        self.target = int(round(tgt))
        self.home_zero = True
        self.mode = 'home'

    def stop_all(self):
        if self.mode is not None:
            if self.mode == 'slew':
                self.slew_v = 0.0
            else:
                # decelerate: convert into a slew to zero from current velocity
                self.mode = 'slew'
                self.slew_v = 0.0
        self.prog = None

    def _reboot(self):
        self.upgrade_until = None
        cfg = json.loads(json.dumps(self.nvm))
        self.params = cfg['params']
        self.io = {int(k): v for k, v in cfg['io'].items()}
        self.analog = cfg['analog']
        self.mfg = cfg['mfg']
        self.labels = cfg['labels']
        self.phys_off += self.P
        self.P = 0.0
        self.C1 = 0.0
        self.enc = 0.0
        self._stop_now()
        self.ER = 0
        self.EF = 0
        self.PC = 0
        self.LR = 0
        self.prog = None
        self.out_latch = {1: 0, 2: 0, 3: 0}
        self.calib_until = time.monotonic() + 1.0

    # ---------------- register access ----------------
    def reg_value(self, base):
        """current value of the parameter at base address (integer)"""
        name = REGS[base][0]
        if name in self.params:
            return self.params[name]
        if name == 'BY':
            return 1 if self.prog is not None else 0
        if name == 'C1':
            return to_s32(int(round(self.C1)))
        if name == 'C2':
            return self.live_c2()
        if name == 'EF':
            return self.EF
        if name == 'ER':
            return self.ER
        if name in ('I1', 'I2', 'I3', 'I4'):
            return self.input_state(int(name[1]))
        if name == 'I5':
            return self.live_i5()
        if name == 'I6':
            return self.live_i6()
        if name == 'IN':
            return sum(self.input_state(n) << (n - 1) for n in (1, 2, 3, 4))
        if name == 'MP':
            return 1 if self.mode == 'pos' else 0
        if name == 'MV':
            return 1 if self.moving() else 0
        if name in ('O1', 'O2', 'O3'):
            return self.input_state(int(name[1]))
        if name == 'OF':
            return 0
        if name == 'OT':
            return sum((self.output_state(n) if self.is_output(n) else 0) << (n - 1) for n in (1, 2, 3))
        if name == 'P':
            return to_s32(int(round(self.P)))
        if name == 'PC':
            return self.PC
        if name == 'ST':
            return 0
        if name == 'V':
            if self.params['AS'] == 3:
                return 0
            return int(round(self.v))
        if name == 'VC':
            return self.vchanging
        if name == 'AF':
            return self.live_af()
        if name == 'LL':
            return self.live_ll()
        if name == 'LR':
            return self.LR
        raise ModbusExc(4)

    def read_regs(self, start, qty):
        words = []
        seen = set()
        for a in range(start, start + qty):
            if a not in ADDR:
                raise ModbusExc(2)
            base, off = ADDR[a]
            d = REGS[base]
            if d[2] == 'WO':
                raise ModbusExc(2)
            if d[1] == 2 and (base < start or base + 1 > start + qty - 1):
                raise ModbusExc(2)      # a 32-bit value must be read as a whole
        vals = {}
        for a in range(start, start + qty):
            base, off = ADDR[a]
            if base not in vals:
                vals[base] = self.reg_value(base)
            v = vals[base] & 0xFFFFFFFF
            words.append((v >> (16 * off)) & 0xFFFF)
        # side effect: reading ER clears the error (manual: "must be read or set to 0 to clear")
        for base in vals:
            if REGS[base][0] == 'ER' and self.ER:
                self.ER = 0
                self.EF = 0
        return words

    def write_regs(self, start, words):
        qty = len(words)
        items = []
        for a in range(start, start + qty):
            if a not in ADDR:
                raise ModbusExc(2)
            base, off = ADDR[a]
            d = REGS[base]
            if d[2] == 'RO':
                raise ModbusExc(2)
            if d[1] == 2 and (base < start or base + 1 > start + qty - 1):
                raise ModbusExc(2)
            if off == 0:
                if d[1] == 2:
                    raw = words[a - start] | (words[a - start + 1] << 16)
                    val = to_s32(raw) if d[3] else raw
                else:
                    val = words[a - start]
                items.append((base, val))
        # range validation of every item before any is applied
        newp = dict(self.params)
        for base, val in items:
            name, w, acc, sg, lo, hi, dflt = REGS[base]
            if not (lo <= val <= hi):
                raise ModbusExc(3)
            if name == 'MS' and val not in MS_ALLOWED:
                raise ModbusExc(3)
            if name == 'HT' and val == 1:
                raise ModbusExc(3)
            if name in newp:
                newp[name] = val
        if newp['VI'] >= newp['VM']:
            raise ModbusExc(3)
        if newp['HT'] + newp['MT'] > 65535:
            raise ModbusExc(3)
        for base, val in items:
            self._apply(REGS[base][0], val, newp)

    def _apply(self, name, val, newp):
        if name in self.params:
            if name == 'MU':
                pass
            self.params[name] = val
            return
        if name == 'C1':
            self.C1 = float(val)
        elif name == 'C2':
            self.enc = float(val)
        elif name == 'P':
            if self.mode is not None:
                raise ModbusExc(4)
            self.phys_off += self.P - val
            self.P = float(val)
        elif name == 'ER':
            self.ER = 0
            self.EF = 0
        elif name in ('O1', 'O2', 'O3'):
            n = int(name[1])
            if not self.is_output(n) or self.io[n][0] != 16:
                raise ModbusExc(4)
            self.out_latch[n] = val
        elif name == 'OT':
            for n in (1, 2, 3):
                if self.is_output(n) and self.io[n][0] == 16:
                    self.out_latch[n] = (val >> (n - 1)) & 1
        elif name in ('DC', 'IC'):
            self._incdec(val, -1 if name == 'DC' else 1)
        elif name == 'IP':
            if self.moving() or self.prog is not None:
                raise ModbusExc(4)
            self.factory_reset()
        elif name == 'S':
            if self.moving():
                raise ModbusExc(4)
            self.nvm = self._snapshot_config()
        elif name == 'MA':
            self.start_move(val)
        elif name == 'MR':
            self.start_move(int(round(self.P)) + val)
        elif name == 'SL':
            self.start_slew(val)
        elif name == 'HM':
            self.start_home(False)
        elif name == 'HI':
            self.start_home(True)
        elif name == 'CF':
            if self.moving():
                raise ModbusExc(4)
            self.LR = 0
            self.calib_until = time.monotonic() + 1.5
        elif name == 'SC':
            if self.moving() or self.params['DE'] == 0:
                raise ModbusExc(4)
            self.calib_until = time.monotonic() + 3.0

    def _incdec(self, addr, delta):
        allowed = {NAME2ADDR[n] for n in ('C1', 'C2', 'P', 'R1', 'R2', 'R3', 'R4',
                                           'V1', 'V2', 'V3', 'V4', 'V5', 'V6', 'V7', 'V8')}
        if addr not in allowed:
            raise ModbusExc(3)
        name = REGS[addr][0]
        if name == 'C1':
            self.C1 = float(to_s32(int(round(self.C1)) + delta))
        elif name == 'C2':
            self.enc = float(to_s32(int(round(self.enc)) + delta))
        elif name == 'P':
            if self.mode is not None:
                raise ModbusExc(4)
            self.P = float(to_s32(int(round(self.P)) + delta))
            self.phys_off -= delta
        else:
            self.params[name] = to_s32(self.params[name] + delta)

    def factory_reset(self):
        for a, d in REGS.items():
            if d[0] in PARAM_NAMES:
                self.params[d[0]] = d[6]
        self.io = {k: list(v) for k, v in FACTORY_IO.items()}
        self.analog = list(FACTORY_ANALOG)
        self.mfg = json.loads(json.dumps(FACTORY_MFG))
        self.out_latch = {1: 0, 2: 0, 3: 0}

    # ---------------- coils / inputs ----------------
    def read_coils(self, start, qty):
        return [self.output_state(n) if self.is_output(n) else 0 for n in range(start + 1, start + qty + 1)]

    def write_coil(self, addr, val):
        n = addr + 1
        if n == 4:
            raise ModbusExc(2)
        if not self.is_output(n) or self.io[n][0] != 16:
            raise ModbusExc(4)
        self.out_latch[n] = val

    # ---------------- manufacturer specific (FC 65/66) ----------------
    MFG_RW = ('AO', 'IS', 'MU', 'OS', 'RD', 'AJ', 'AT', 'BE', 'BL', 'BM', 'DJ', 'DT', 'FS', 'FL', 'LS',
              'TR', 'S1', 'S2', 'S3', 'S4', 'S5')
    MFG_RO = ('IT', 'AV', 'VT')
    MFG_WO = ('\x1b', 'CP', 'EX', 'PS', 'RS', 'HF', 'UG', 'E')

    def mfg_read(self, mn):
        if mn in self.MFG_WO:
            raise ModbusExc(2)
        if mn not in self.MFG_RW and mn not in self.MFG_RO:
            raise ModbusExc(2)
        m = self.mfg
        if mn == 'IT':
            return self.live_it()
        if mn == 'VT':
            return self.live_vt()
        if mn == 'AV':
            return str(self.live_av())
        if mn in ('AO', 'RD', 'AJ', 'AT', 'BE', 'BL', 'BM', 'DJ', 'DT', 'FS', 'FL'):
            return str(m[mn])
        if mn == 'MU':
            return '%d,%d' % (self.params['MU'], m['MUB'])
        if mn == 'LS':
            return ' '.join('%d,%d,%d' % tuple(x) for x in m['LS'])
        if mn == 'TR':
            return '%d, %d, %d' % tuple(m['TR'])
        if mn == 'IS':
            parts = ['%d,%d,%d' % (n, self.io[n][0], self.io[n][1]) for n in (1, 2, 3, 4)
                     if not self.is_output(n)]
            parts.append('5,%d,%d' % tuple(self.analog))
            return ' '.join(parts)
        if mn == 'OS':
            return ' '.join('%d,%d,%d' % (n, self.io[n][0], self.io[n][1]) for n in (1, 2, 3)
                            if self.is_output(n))
        if mn in ('S1', 'S2', 'S3', 'S4'):
            return '%d,%d,%d' % tuple(self.io[int(mn[1])])
        if mn == 'S5':
            return '%d,%d' % tuple(self.analog)
        raise ModbusExc(2)

    @staticmethod
    def _ints(s, n_min, n_max):
        if not s.startswith('='):
            raise ModbusExc(3)
        parts = s[1:].split(',')
        if not (n_min <= len(parts) <= n_max):
            raise ModbusExc(3)
        out = []
        for p in parts:
            p = p.strip()
            if not re.fullmatch(r'[+-]?\d{1,10}', p):
                raise ModbusExc(3)
            out.append(int(p))
        return out

    def mfg_write(self, mn, data):
        if mn in self.MFG_RO:
            raise ModbusExc(2)
        if mn not in self.MFG_RW and mn not in self.MFG_WO:
            raise ModbusExc(2)
        try:
            s = data.decode('ascii')
        except UnicodeDecodeError:
            raise ModbusExc(3)
        m = self.mfg
        one = lambda lo, hi: self._one(s, lo, hi)
        if mn in ('\x1b', 'CP', 'PS', 'RS', 'E'):
            if s.strip() not in ('',):
                raise ModbusExc(3)
            if mn == '\x1b':
                self.stop_all()
            elif mn == 'CP':
                if self.prog is not None:
                    raise ModbusExc(4)
                self.labels = {}
            elif mn == 'PS':
                if self.prog is None:
                    raise ModbusExc(4)
                self.prog['paused'] = True
            elif mn == 'RS':
                if self.prog is None:
                    raise ModbusExc(4)
                self.prog['paused'] = False
            elif mn == 'E':
                self.prog = None
            return
        if mn == 'EX':
            lab = s.strip().lstrip('=').strip().upper()
            if not lab:
                raise ModbusExc(3)
            if lab.isdigit():
                if int(lab) not in self.labels.values():
                    raise ModbusExc(3)
                lab = [k for k, v in self.labels.items() if v == int(lab)][0]
            elif lab not in self.labels:
                raise ModbusExc(3)
            if self.prog is not None:
                raise ModbusExc(4)
            self.prog = {'label': lab, 'remaining': 4.0, 'paused': False}
            return
        if mn == 'UG':
            code = s.strip().lstrip('=').strip()
            if code != '2956102':
                raise ModbusExc(3)
            if self.moving():
                raise ModbusExc(4)
            self.prog = None
            self.upgrade_pending = True
            return
        if mn == 'HF':
            mode = one(1, 4)
            self.start_home(True, m['FS'])
            return
        if mn == 'AO':
            m['AO'] = one(0, 65535)
        elif mn in ('RD', 'BE', 'BM', 'FL', 'AT', 'DT'):
            v = one(0, 1)
            if mn == 'RD' and self.moving():
                raise ModbusExc(4)
            m[mn] = v
        elif mn in ('AJ', 'DJ'):
            m[mn] = one(1, 999)
        elif mn == 'BL':
            m[mn] = one(0, 2147483647)
        elif mn == 'FS':
            m[mn] = one(-9999, 99999)
        elif mn == 'MU':
            a, b = self._ints(s, 2, 2)
            if not (0 <= a <= 2 and 0 <= b <= 1):
                raise ModbusExc(3)
            self.params['MU'] = a
            m['MUB'] = b
        elif mn == 'LS':
            d, pos, en = self._ints(s, 3, 3)
            if d not in (0, 1) or en not in (0, 1) or not (I32[0] <= pos <= I32[1]):
                raise ModbusExc(3)
            m['LS'][d] = [d, pos, en]
        elif mn == 'TR':
            vals = self._ints(s, 1, 3)
            for v in vals:
                if not (I32[0] <= v <= I32[1]):
                    raise ModbusExc(3)
            m['TR'] = (vals + [0, 0, 0])[:3]
        elif mn == 'IS':
            a, b, c = self._ints(s, 3, 3)
            if a == 5:
                if b not in (9, 10) or c not in (0, 1):
                    raise ModbusExc(3)
                self.analog = [b, c]
                return
            if a not in (1, 2, 3, 4) or b not in IN_FUNCS or c not in (0, 1):
                raise ModbusExc(3)
            if b == 12 and a != 1:
                raise ModbusExc(3)
            self._set_io(a, [b, c, self.io[a][2]])
        elif mn == 'OS':
            a, b, c = self._ints(s, 3, 3)
            if a not in (1, 2, 3) or b not in OUT_FUNCS or c not in (0, 1):
                raise ModbusExc(3)
            if b == 28 and a != 3:
                raise ModbusExc(3)
            self._set_io(a, [b, c, self.io[a][2]])
        elif mn in ('S1', 'S2', 'S3', 'S4'):
            n = int(mn[1])
            vals = self._ints(s, 2, 3)
            b, c = vals[0], vals[1]
            d = vals[2] if len(vals) == 3 else self.io[n][2]
            ok_in = b in IN_FUNCS and (b != 12 or n == 1)
            ok_out = n != 4 and b in OUT_FUNCS and (b != 28 or n == 3)
            if not (ok_in or ok_out) or c not in (0, 1) or d not in (0, 1):
                raise ModbusExc(3)
            self._set_io(n, [b, c, d])
        elif mn == 'S5':
            b, c = self._ints(s, 2, 2)
            if b not in (9, 10) or c not in (0, 1):
                raise ModbusExc(3)
            self.analog = [b, c]

    def _one(self, s, lo, hi):
        v = self._ints(s, 1, 1)[0]
        if not (lo <= v <= hi):
            raise ModbusExc(3)
        return v

    def _set_io(self, n, cfg):
        if self.moving():
            raise ModbusExc(4)
        was_out = self.is_output(n)
        self.io[n] = cfg
        if n in self.out_latch and (not was_out or cfg[0] != 16):
            self.out_latch[n] = 0

    # ---------------- state dump ----------------
    def dump(self):
        with self.lock:
            regs = {}
            live_names = ('C2', 'I5', 'I6', 'AF', 'LL')
            live = {}
            for base in sorted(REGS):
                d = REGS[base]
                if d[2] == 'WO':
                    continue
                key = '0x%04X' % base
                val = self.reg_value(base)
                if d[0] in live_names:
                    live[key] = {'mcode': d[0], 'value': val}
                else:
                    regs[key] = {'mcode': d[0], 'value': val}
            coils = {str(a): v for a, v in enumerate(self.read_coils(0, 4))}
            dis = {str(n - 1): self.input_state(n) for n in (1, 2, 3, 4)}
            mfg = {}
            for mn in self.MFG_RW:
                mfg[mn] = self.mfg_read(mn)
            live['IT'] = self.live_it()
            live['VT'] = self.live_vt()
            live['AV'] = str(self.live_av())
            return {
                'device': 'Lexium MDrive Ethernet LMDCE572 (hMTechnology), Modbus/TCP',
                'holding_registers': regs,
                'coils': coils,
                'discrete_inputs': dis,
                'manufacturer_functions': mfg,
                'io_setup': {str(k): v for k, v in self.io.items()},
                'analog_input_setup': self.analog,
                'program': {'labels': self.labels,
                            'running': None if self.prog is None else self.prog['label'],
                            'paused': bool(self.prog and self.prog['paused'])},
                'upgrade_mode': self.upgrade_until is not None,
                'nvm': self.nvm,
                'device_identification': {'0x%02X' % k: v.decode() for k, v in DEVICE_ID.items()},
                'diagnostic_counters': {},
                'live': live,
            }


# ---------------------------------------------------------------------------------------------
# Modbus PDU handling
# ---------------------------------------------------------------------------------------------
def exc(fc, code):
    return bytes([(fc | 0x80) & 0xFF, code])


def handle_pdu(drv, pdu):
    fc = pdu[0]
    try:
        with drv.lock:
            if drv.upgrade_until is not None and fc in (0x01, 0x02, 0x03, 0x05, 0x10, 0x2B, 0x41, 0x42):
                raise ModbusExc(6)
            r = _dispatch(drv, fc, pdu)
            if getattr(drv, 'upgrade_pending', False):
                drv.upgrade_pending = False
                drv.upgrade_until = time.monotonic() + 20.0
            return r
    except ModbusExc as e:
        return exc(fc, e.code)
    except Exception:
        return exc(fc, 4)


def _dispatch(drv, fc, pdu):
    n = len(pdu)
    if fc in (0x01, 0x02):
        if n != 5:
            raise ModbusExc(3)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not 1 <= qty <= 4:
            raise ModbusExc(3)
        if fc == 0x02 and 0x002D <= start <= 0x0030:
            start -= 0x002D          # register-address alias used in the manual's example
        if start + qty > 4:
            raise ModbusExc(2)
        if fc == 0x01:
            bits = drv.read_coils(start, qty)
        else:
            bits = [drv.input_state(k) for k in range(start + 1, start + qty + 1)]
        b = 0
        for i, v in enumerate(bits):
            b |= (v & 1) << i
        return bytes([fc, 1, b])
    if fc == 0x05:
        if n != 5:
            raise ModbusExc(3)
        addr, val = struct.unpack('>HH', pdu[1:5])
        if val not in (0x0000, 0xFF00):
            raise ModbusExc(3)
        if addr > 3:
            raise ModbusExc(2)
        drv.write_coil(addr, 1 if val == 0xFF00 else 0)
        return bytes(pdu)
    if fc == 0x03:
        if n != 5:
            raise ModbusExc(3)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not 1 <= qty <= 2:
            raise ModbusExc(3)
        if start + qty - 1 > MAP_END:
            raise ModbusExc(2)
        words = drv.read_regs(start, qty)
        return bytes([0x03, 2 * qty]) + b''.join(struct.pack('>H', w) for w in words)
    if fc == 0x10:
        if n < 6:
            raise ModbusExc(3)
        start, qty, bc = struct.unpack('>HHB', pdu[1:6])
        if not 1 <= qty <= 2 or bc != 2 * qty or n != 6 + bc:
            raise ModbusExc(3)
        if start + qty - 1 > MAP_END:
            raise ModbusExc(2)
        words = list(struct.unpack('>%dH' % qty, pdu[6:6 + bc]))
        drv.write_regs(start, words)
        return struct.pack('>BHH', 0x10, start, qty)
    if fc == 0x2B:
        if n < 2:
            raise ModbusExc(3)
        if pdu[1] != 0x0E:
            raise ModbusExc(1)
        if n != 4:
            raise ModbusExc(3)
        code, oid = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise ModbusExc(3)
        if code == 4:
            if oid not in DEVICE_ID:
                raise ModbusExc(2)
            ids = [oid]
        else:
            last = 2 if code == 1 else 6
            if oid > last:
                oid = 0
            ids = list(range(oid, last + 1))
        body = b''.join(bytes([i, len(DEVICE_ID[i])]) + DEVICE_ID[i] for i in ids)
        return bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)]) + body
    if fc in (0x41, 0x42):
        if n < 5:
            raise ModbusExc(3)
        raw = bytes(pdu[1:5])
        mn = bytes(reversed(raw)).decode('latin-1').strip(' \x00').upper()
        if fc == 0x41:
            if n != 5:
                raise ModbusExc(3)
            s = drv.mfg_read(mn).encode('ascii')
            return bytes([0x41, len(s)]) + s
        if n < 6:
            raise ModbusExc(3)
        bc = pdu[5]
        if bc > 28 or n != 6 + bc:
            raise ModbusExc(3)
        drv.mfg_write(mn, bytes(pdu[6:]))
        return bytes([0x42, 4]) + raw
    raise ModbusExc(1)


# ---------------------------------------------------------------------------------------------
# TCP server
# ---------------------------------------------------------------------------------------------
MAX_CONN = 16
_conn_count = [0]
_conn_lock = threading.Lock()


def recv_exact(sock, n):
    buf = b''
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return buf


def serve_conn(drv, sock):
    try:
        sock.settimeout(None)
        while True:
            hdr = recv_exact(sock, 7)
            if hdr is None:
                return
            tid, pid, length, uid = struct.unpack('>HHHB', hdr)
            if length < 2 or length > 254:
                return              # cannot re-synchronise the stream: close (Implementation Guide)
            body = recv_exact(sock, length - 1)
            if body is None:
                return
            if pid != 0:
                continue            # not a Modbus frame: silently discarded
            resp = handle_pdu(drv, body)
            sock.sendall(struct.pack('>HHHB', tid, 0, len(resp) + 1, uid) + resp)
    except OSError:
        pass
    finally:
        try:
            sock.close()
        except OSError:
            pass
        with _conn_lock:
            _conn_count[0] -= 1


def motion_loop(drv):
    while True:
        time.sleep(0.01)
        try:
            drv.tick()
        except Exception:
            pass


def write_state(drv, path):
    if not path:
        return
    try:
        data = drv.dump()
        tmp = path + '.tmp'
        with open(tmp, 'w') as f:
            json.dump(data, f, indent=1, sort_keys=True)
        os.replace(tmp, path)
    except Exception as e:
        sys.stderr.write('state dump failed: %r\n' % (e,))


def main():
    ap = argparse.ArgumentParser(description='Lexium MDrive Ethernet (hMT) Modbus/TCP simulator')
    ap.add_argument('--listen', default='127.0.0.1:502')
    ap.add_argument('--state', default=None)
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(':')
    host = host.strip('[]') or '127.0.0.1'
    drv = Drive()
    drv.upgrade_pending = False

    def on_usr1(signum, frame):
        threading.Thread(target=write_state, args=(drv, args.state), daemon=True).start()

    def on_term(signum, frame):
        write_state(drv, args.state)
        try:
            sys.stdout.flush()
        except Exception:
            pass
        os._exit(0)

    signal.signal(signal.SIGUSR1, on_usr1)
    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)

    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind((host, int(port)))
    srv.listen(16)
    threading.Thread(target=motion_loop, args=(drv,), daemon=True).start()
    print('listening tcp %s:%d' % (host, srv.getsockname()[1]), flush=True)
    while True:
        try:
            c, _ = srv.accept()
        except OSError:
            continue
        with _conn_lock:
            if _conn_count[0] >= MAX_CONN:
                c.close()
                continue
            _conn_count[0] += 1
        c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        threading.Thread(target=serve_conn, args=(drv, c), daemon=True).start()


if __name__ == '__main__':
    main()
