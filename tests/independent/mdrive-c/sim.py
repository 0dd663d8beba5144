#!/usr/bin/env python3
"""MDrive Plus2 Motion Control with Ethernet -- MODBUS/TCP server simulator.

Written from the IMS / Schneider Electric Motion USA "MODBUS/TCP Fieldbus
Manual" (R040611) and the public MODBUS specifications only.
Standard library only.  See DECISIONS.md for every interpretation made.

    python3 sim.py --listen 127.0.0.1:0 [--state FILE]
"""
import argparse
import asyncio
import json
import math
import os
import signal
import struct
import sys
import time
from decimal import Decimal, InvalidOperation

# ---------------------------------------------------------------------------
# Modbus exception codes (the manual lists 01..04 only, section 4 "Exception codes")
ILLEGAL_FUNCTION = 0x01
ILLEGAL_DATA_ADDRESS = 0x02
ILLEGAL_DATA_VALUE = 0x03
SLAVE_DEVICE_FAILURE = 0x04

ACCEPTED_UNIT_IDS = (0x00, 0xFF)      # DECISIONS.md D-03
MAX_CONNECTIONS = 8                    # DECISIONS.md D-05
FRAME_COMPLETION_TIMEOUT = 5.0         # seconds, DECISIONS.md D-04
MAX_MBAP_LENGTH = 254                  # unit id + 253 byte PDU

# MCode error codes placed in ER (0x0021) when the motion processor refuses
# an otherwise valid command (DECISIONS.md D-40).
MCODE_ERR_UNKNOWN_LABEL = 30
MCODE_ERR_PROGRAM_NOT_RUNNING = 40
MCODE_ERR_SAVE_WHILE_MOVING = 73
MCODE_ERR_MOVE_WHILE_MOVING = 85

# Microstep resolution table (register 0x0048): MS value -> steps / revolution
MS_TABLE = {1: 200, 2: 400, 4: 800, 5: 1000, 8: 1600, 10: 2000, 16: 3200,
            25: 5000, 32: 6400, 50: 10000, 64: 12800, 100: 20000, 125: 25000,
            128: 25600, 200: 40000, 250: 50000, 256: 51200, 180: 36000,
            108: 21600, 127: 25400}
ENCODER_COUNTS_PER_REV = 2048          # 512 line quadrature encoder, D-33

# Digital I/O address windows
INPUT_BASE = 0x002D                    # I1..I4, FC02 / FC03
OUTPUT_BASE = 0x004B                   # O1..O4, FC01 / FC05 / FC03 / FC16

# S1..S4 "A" parameter (I/O type) -- Plus2 subset (Hybrid-only 21/24/25 removed)
IO_INPUT_FUNCS = {0, 1, 2, 3, 5, 7, 8, 11}
IO_OUTPUT_FUNCS = {16, 17, 18, 20, 23}
CLOCK_IO_FUNCS = {33, 34, 35, 49, 50, 51}
ANALOG_MODES = {9, 10}
CAPTURE_TRIP_MODES = {60, 61}
TRIP_ON_RELATIVE_POSITION = 16

# Targets accepted by DC (0x001B) / IC (0x0037): start address of the variable
USER_VAR_ADDRS = {0x005F: 'R1', 0x0061: 'R2', 0x0063: 'R3', 0x0065: 'R4',
                  0x00A8: 'V1', 0x00AA: 'V2', 0x00AC: 'V3', 0x00AE: 'V4',
                  0x00B0: 'V5', 0x00B2: 'V6', 0x00B4: 'V7', 0x00B6: 'V8'}

DEVICE_ID_OBJECTS = {
    0x00: b"SEM USA",
    0x01: b"MDI1PRD23A7-EQ",
    0x02: b"4.0.0.0",
    0x03: b"www.imshome.com",
    0x04: b"MDrive Ethernet",
    0x05: b"0410000123",
    0x06: b"ASI 4.0.0.0",
}
CONFORMITY_LEVEL = 0x82               # regular identification, stream + individual


class MBException(Exception):
    def __init__(self, code, mcode_error=None):
        super().__init__(code)
        self.code = code
        self.mcode_error = mcode_error


def wrap32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


def sgn(x):
    return (x > 0) - (x < 0)


# ---------------------------------------------------------------------------
# Register map (Plus2 variant; Hybrid section 5.1 deliberately absent)

class Param:
    """One documented item of the holding register map."""

    def __init__(self, addr, nregs, name, access, lo=None, hi=None,
                 allowed=None, default=None, signed=False, lock=False,
                 desc=""):
        self.addr = addr
        self.n = nregs
        self.name = name
        self.access = access          # 'rw', 'ro', 'wo', 'clr' (rw, only 0 writable)
        self.lo = lo
        self.hi = hi
        self.allowed = allowed
        self.default = default
        self.signed = signed
        self.lock = lock              # may not be written while the axis moves
        self.desc = desc

    def check_value(self, v):
        if self.allowed is not None and v not in self.allowed:
            return False
        if self.lo is not None and v < self.lo:
            return False
        if self.hi is not None and v > self.hi:
            return False
        return True


def build_map():
    P = Param
    S32 = dict(lo=-2147483648, hi=2147483647, signed=True)
    items = [
        P(0x0000, 2, 'A', 'rw', 91, 1525878997, default=1000000, desc='Acceleration'),
        P(0x0005, 2, 'C1', 'rw', default=0, lock=True, desc='Counter 1', **S32),
        P(0x0007, 2, 'C2', 'rw', default=0, lock=True, desc='Counter 2', **S32),
        P(0x0009, 1, 'CE', 'rw', 0, 1, default=1, desc='Software reset enable'),
        P(0x000B, 1, 'CM', 'rw', 0, 1, default=0, lock=True, desc='Clock mode enable'),
        P(0x000F, 1, 'D1', 'rw', 0, 255, default=0, desc='Input 1 debounce'),
        P(0x0010, 1, 'D2', 'rw', 0, 255, default=0, desc='Input 2 debounce'),
        P(0x0011, 1, 'D3', 'rw', 0, 255, default=0, desc='Input 3 debounce'),
        P(0x0012, 1, 'D4', 'rw', 0, 255, default=0, desc='Input 4 debounce'),
        P(0x0013, 1, 'D5', 'rw', 0, 255, default=0, desc='Analog input filter'),
        P(0x0018, 2, 'D', 'rw', 91, 1525878997, default=1000000, desc='Deceleration'),
        P(0x001A, 1, 'DB', 'rw', 0, 65000, default=10, desc='Encoder deadband'),
        P(0x001B, 1, 'DC', 'wo', allowed=set(USER_VAR_ADDRS), desc='Decrement variable'),
        P(0x001C, 1, 'DE', 'rw', 0, 1, default=1, desc='Drive enable'),
        P(0x001E, 1, 'EE', 'rw', 0, 1, default=0, lock=True, desc='Encoder enable'),
        P(0x001F, 1, 'EF', 'ro', desc='Error flag'),
        P(0x0021, 1, 'ER', 'clr', 0, 0, desc='Error (last error code)'),
        P(0x0029, 1, 'HC', 'rw', 0, 100, default=5, desc='Holding current'),
        P(0x002B, 1, 'HM', 'rw', 1, 4, default=1, desc='Homing mode'),
        P(0x002C, 1, 'HT', 'rw', 0, 65535, default=500, desc='Hold current delay time'),
        P(0x002D, 1, 'I1', 'ro', desc='Read input 1'),
        P(0x002E, 1, 'I2', 'ro', desc='Read input 2'),
        P(0x002F, 1, 'I3', 'ro', desc='Read input 3'),
        P(0x0030, 1, 'I4', 'ro', desc='Read input 4'),
        P(0x0031, 1, 'I5', 'ro', desc='Read analog input'),
        P(0x0032, 1, 'I6', 'ro', desc='Read index mark'),
        P(0x0037, 1, 'IC', 'wo', allowed=set(USER_VAR_ADDRS), desc='Increment variable'),
        P(0x003A, 1, 'IL', 'ro', desc='Read inputs 1-4 as BCD'),
        P(0x003B, 1, 'IN', 'ro', desc='Read all inputs as BCD'),
        P(0x003F, 1, 'JE', 'rw', 0, 1, default=0, desc='Jog enable'),
        P(0x0042, 1, 'LM', 'rw', 1, 6, default=1, desc='Limit stop mode'),
        P(0x0043, 2, 'MA', 'wo', desc='Move to absolute position', **S32),
        P(0x0045, 1, 'MP', 'ro', desc='Moving to position'),
        P(0x0046, 2, 'MR', 'wo', desc='Move to relative position', **S32),
        P(0x0048, 1, 'MS', 'rw', allowed=set(MS_TABLE), default=256, lock=True,
          desc='Microstep resolution'),
        P(0x0049, 1, 'MT', 'rw', 0, 65000, default=0, desc='Motor settling delay time'),
        P(0x004A, 1, 'MV', 'ro', desc='Moving'),
        P(0x004B, 1, 'O1', 'rw', 0, 1, desc='Write output 1'),
        P(0x004C, 1, 'O2', 'rw', 0, 1, desc='Write output 2'),
        P(0x004D, 1, 'O3', 'rw', 0, 1, desc='Write output 3'),
        P(0x004E, 1, 'O4', 'rw', 0, 1, desc='Write output 4'),
        P(0x0055, 1, 'OL', 'rw', 0, 15, desc='Set outputs 1-4 as a group (OL)'),
        P(0x0056, 1, 'OT', 'rw', 0, 15, desc='Set outputs 1-4 as a group (OT)'),
        P(0x0057, 2, 'P', 'rw', default=0, lock=True, desc='Position counter', **S32),
        P(0x0059, 2, 'PC', 'ro', desc='Position capture at trip', **S32),
        P(0x005C, 1, 'PM', 'rw', 0, 1, default=0, desc='Position maintenance'),
        P(0x005F, 2, 'R1', 'rw', default=0, desc='User register 1', **S32),
        P(0x0061, 2, 'R2', 'rw', default=0, desc='User register 2', **S32),
        P(0x0063, 2, 'R3', 'rw', default=0, desc='User register 3', **S32),
        P(0x0065, 2, 'R4', 'rw', default=0, desc='User register 4', **S32),
        P(0x0067, 1, 'RC', 'rw', 1, 100, default=25, desc='Run current'),
        P(0x0076, 1, 'S', 'wo', 1, 1, desc='Save to NVM'),
        P(0x0077, 1, 'SF', 'rw', 0, 65000, default=15, desc='Stall factor'),
        P(0x0078, 2, 'SL', 'wo', -5000000, 5000000, signed=True, desc='Slew axis'),
        P(0x007A, 1, 'SM', 'rw', 0, 1, default=0, desc='Stall mode'),
        P(0x007B, 1, 'ST', 'clr', 0, 0, desc='Stall flag'),
        P(0x007D, 1, 'TE', 'rw', allowed={0, TRIP_ON_RELATIVE_POSITION}, default=0,
          desc='Trip enable'),
        P(0x0085, 2, 'V', 'ro', signed=True, desc='Read axis velocity'),
        P(0x0088, 1, 'VC', 'ro', desc='Velocity is changing'),
        P(0x0089, 2, 'VI', 'rw', 1, 4999999, default=1000, desc='Initial velocity'),
        P(0x008B, 2, 'VM', 'rw', 2, 5000000, default=768000, desc='Maximum velocity'),
    ]
    for i in range(8):
        items.append(P(0x00A8 + 2 * i, 2, 'V%d' % (i + 1), 'rw', default=0,
                       desc='User variable %d' % (i + 1), **S32))
    by_name = {p.name: p for p in items}
    by_addr = {}
    for p in items:
        for k in range(p.n):
            by_addr[p.addr + k] = p
    return items, by_name, by_addr


PARAMS, PARAM_BY_NAME, PARAM_BY_ADDR = build_map()

# Settings copied to non-volatile memory by the Save command (0x0076)
NVM_REGISTER_SETTINGS = ['A', 'CE', 'CM', 'D1', 'D2', 'D3', 'D4', 'D5', 'D', 'DB',
                         'DE', 'EE', 'HC', 'HM', 'HT', 'JE', 'LM', 'MS', 'MT', 'PM',
                         'R1', 'R2', 'R3', 'R4', 'RC', 'SF', 'SM', 'VI', 'VM']
STORED_SETTINGS = NVM_REGISTER_SETTINGS + ['TE'] + ['V%d' % i for i in range(1, 9)]


# ---------------------------------------------------------------------------
# Motion profile: piecewise constant-acceleration velocity segments

class Motion:
    def __init__(self, t0, kind, segs, target=None, distance=None):
        self.t0 = t0
        self.kind = kind              # 'abs' (MA/MR) or 'slew' (SL)
        self.segs = [s for s in segs if s[0] > 0]   # (duration, v0, accel)
        self.target = target          # absolute target (abs moves)
        self.distance = distance      # exact signed distance (abs moves)
        total = 0.0
        for d, _, _ in self.segs:
            total += d
        self.duration = total
        self.end = t0 + total

    def eval(self, t):
        """Return (distance, velocity, accelerating, finished) at time t."""
        e = max(0.0, t - self.t0)
        dist = 0.0
        for dur, v0, a in self.segs:
            if e < dur:
                return dist + v0 * e + 0.5 * a * e * e, v0 + a * e, a != 0, False
            dist += v0 * dur + 0.5 * a * dur * dur
            e -= dur
        return dist, 0.0, False, True


def profile_abs(distance, vi, vm, acc, dec):
    """Trapezoidal (or triangular) point-to-point profile starting/ending at VI."""
    d = abs(distance)
    s = sgn(distance)
    if d == 0:
        return []
    vi = float(min(vi, vm))
    da = (vm * vm - vi * vi) / (2.0 * acc)
    dd = (vm * vm - vi * vi) / (2.0 * dec)
    if da + dd <= d:
        vp = float(vm)
        cruise = (d - da - dd) / vp
    else:
        vp = math.sqrt(vi * vi + 2.0 * d * acc * dec / (acc + dec))
        cruise = 0.0
    return [((vp - vi) / acc, s * vi, s * acc),
            (cruise, s * vp, 0.0),
            ((vp - vi) / dec, s * vp, -s * dec)]


def profile_slew(v, vt, vi, acc, dec):
    """Velocity-mode profile from current velocity v to target vt."""
    inf = math.inf
    segs = []
    if v == 0:
        if vt == 0:
            return segs
        s = sgn(vt)
        vs = min(vi, abs(vt))
        segs.append(((abs(vt) - vs) / acc, s * vs, s * acc))
        segs.append((inf, vt, 0.0))
        return segs
    s = sgn(v)
    if vt == 0 or sgn(vt) != s:
        if abs(v) > vi:
            segs.append(((abs(v) - vi) / dec, v, -s * dec))
        if vt == 0:
            return segs
        return segs + profile_slew(0, vt, vi, acc, dec)
    if abs(vt) > abs(v):
        segs.append(((abs(vt) - abs(v)) / acc, v, s * acc))
    elif abs(vt) < abs(v):
        segs.append(((abs(v) - abs(vt)) / dec, v, -s * dec))
    segs.append((inf, vt, 0.0))
    return segs


# ---------------------------------------------------------------------------
class Drive:
    def __init__(self):
        self.reg = {p.name: p.default for p in PARAMS if p.name in STORED_SETTINGS}
        self.er = 0
        self.stall = 0
        self.pc = 0
        self.out_latch = [0, 0, 0, 0]           # general purpose output latches
        self.mfg = {
            'S1': (0, 0, 0), 'S2': (0, 0, 0), 'S3': (0, 0, 0), 'S4': (0, 0, 0),
            'S7': (33, 0), 'S8': (33, 0),
            'S5': (9, 0),
            'S13': (60, 0),
            'CR': Decimal('1.000'),
            'TR': 0,
        }
        # motion / counters (base values valid while self.motion is None)
        self.p_base = 0
        self.c1_base = 0
        self.c2_base = 0
        self.c2_frac = 0.0
        self.motion = None
        self.trip_ref = 0
        self.trip_events = 0
        self.program = {'state': 'idle', 'label': None}
        self.nvm = self._nvm_image()
        self.nvm_saves = 0
        self.counters = {
            'connections_accepted': 0, 'connections_refused': 0,
            'frames_received': 0, 'responses_sent': 0,
            'frames_dropped_protocol_id': 0, 'frames_dropped_unit_id': 0,
            'connections_closed_bad_length': 0, 'connections_closed_timeout': 0,
            'exceptions': {'01': 0, '02': 0, '03': 0, '04': 0},
        }

    # ----------------------------------------------------------- motion core
    def _steps_per_rev(self):
        return MS_TABLE[self.reg['MS']]

    def _motion_delta(self, now):
        """Integer step delta since base, velocity, accelerating flag."""
        m = self.motion
        if m is None:
            return 0, 0.0, False
        dist, vel, accel, finished = m.eval(now)
        if m.kind == 'abs':
            if finished:
                return m.distance, 0.0, False
            d = int(dist)
            if abs(d) > abs(m.distance):
                d = m.distance
            return d, vel, accel
        return int(dist), vel, accel

    def _commit(self, delta):
        self.p_base = wrap32(self.p_base + delta)
        self.c1_base = wrap32(self.c1_base + delta)
        enc = self.c2_frac + delta * ENCODER_COUNTS_PER_REV / self._steps_per_rev()
        whole = math.floor(enc)
        self.c2_base = wrap32(self.c2_base + whole)
        self.c2_frac = enc - whole

    def update(self, now=None):
        if now is None:
            now = time.monotonic()
        m = self.motion
        if m is not None and now >= m.end:
            if m.kind == 'abs':
                delta = m.distance
            else:
                delta = int(round(m.eval(m.end)[0]))
            self._check_trip(self._pos_from_delta(delta))
            self._commit(delta)
            self.motion = None
        self._check_trip(self.position(now))

    def _pos_from_delta(self, delta):
        return wrap32(self.p_base + delta)

    def position(self, now):
        delta, _, _ = self._motion_delta(now)
        return self._pos_from_delta(delta)

    def _check_trip(self, pos):
        if self.reg['TE'] & TRIP_ON_RELATIVE_POSITION and self.mfg['TR'] != 0:
            if abs(wrap32(pos - self.trip_ref)) >= abs(self.mfg['TR']):
                # trip fires once; TE must be written again to re-arm (manual 4.3.1)
                self.reg['TE'] &= ~TRIP_ON_RELATIVE_POSITION
                self.trip_events += 1

    def _rebase(self, now):
        """Freeze the running motion at 'now' into the base counters."""
        delta, vel, _ = self._motion_delta(now)
        self._commit(delta)
        self.motion = None
        return vel

    def stop_immediately(self, now):
        if self.motion is not None:
            self._rebase(now)

    def start_abs(self, now, target, dist):
        if dist == 0:
            return
        segs = profile_abs(dist, self.reg['VI'], self.reg['VM'], self.reg['A'], self.reg['D'])
        self.motion = Motion(now, 'abs', segs, target=target, distance=dist)

    def start_slew(self, now, vt):
        v = 0.0
        if self.motion is not None:
            v = self._rebase(now)
        segs = profile_slew(v, float(vt), float(self.reg['VI']),
                            float(self.reg['A']), float(self.reg['D']))
        if segs:
            self.motion = Motion(now, 'slew', segs)

    # ----------------------------------------------------------- I/O helpers
    def io_kind(self, point):
        """'in' or 'out' for I/O point 1..4."""
        return 'out' if self.mfg['S%d' % point][0] in IO_OUTPUT_FUNCS else 'in'

    def output_state(self, point, now):
        func = self.mfg['S%d' % point][0]
        if func == 16:
            return self.out_latch[point - 1]
        delta, vel, accel = self._motion_delta(now)
        moving = self.motion is not None
        if func == 17:
            return int(moving)
        if func == 18:
            return int(self.er != 0)
        if func == 20:
            return int(moving and accel)
        if func == 23:
            return int(moving and self.motion.kind == 'abs')
        return 0

    def input_state(self, point):
        # Nothing is wired to the simulated drive: every input is inactive.
        return 0

    def output_group(self, now):
        v = 0
        for i in range(1, 5):
            if self.io_kind(i) == 'out' and self.output_state(i, now):
                v |= 1 << (i - 1)
        return v

    def input_group(self):
        v = 0
        for i in range(1, 5):
            if self.io_kind(i) == 'in' and self.input_state(i):
                v |= 1 << (i - 1)
        return v

    # ----------------------------------------------------------- register values
    def read_value(self, p, now):
        n = p.name
        if n in self.reg:
            return self.reg[n]
        delta, vel, accel = self._motion_delta(now)
        moving = self.motion is not None
        if n == 'P':
            return self._pos_from_delta(delta)
        if n == 'C1':
            return wrap32(self.c1_base + delta)
        if n == 'C2':
            enc = self.c2_frac + delta * ENCODER_COUNTS_PER_REV / self._steps_per_rev()
            return wrap32(self.c2_base + math.floor(enc))
        if n == 'EF':
            return int(self.er != 0)
        if n == 'ER':
            return self.er
        if n == 'ST':
            return self.stall
        if n == 'PC':
            return self.pc
        if n in ('I1', 'I2', 'I3', 'I4'):
            return self.input_state(int(n[1]))
        if n == 'I5':
            return 0
        if n == 'I6':
            return 0
        if n in ('IL', 'IN'):
            return self.input_group()
        if n == 'MP':
            return int(moving and self.motion.kind == 'abs')
        if n == 'MV':
            return int(moving)
        if n == 'VC':
            return int(moving and accel)
        if n == 'V':
            return int(round(vel))
        if n in ('O1', 'O2', 'O3', 'O4'):
            return self.output_state(int(n[1]), now)
        if n in ('OL', 'OT'):
            return self.output_group(now)
        raise MBException(ILLEGAL_DATA_ADDRESS)

    def readable(self, p):
        if p.access == 'wo':
            return False
        if p.name in ('I1', 'I2', 'I3', 'I4'):
            return self.io_kind(int(p.name[1])) == 'in'
        if p.name in ('O1', 'O2', 'O3', 'O4'):
            return self.io_kind(int(p.name[1])) == 'out'
        return True

    # ----------------------------------------------------------- PDU dispatch
    def process(self, pdu):
        fc = pdu[0]
        now = time.monotonic()
        try:
            self.update(now)
            handler = {
                0x01: self.fc_read_coils,
                0x02: self.fc_read_discrete_inputs,
                0x03: self.fc_read_holding,
                0x05: self.fc_write_single_coil,
                0x10: self.fc_write_multiple,
                0x2B: self.fc_encapsulated,
                0x41: self.fc_mfg_read,
                0x42: self.fc_mfg_write,
            }.get(fc)
            if handler is None:
                raise MBException(ILLEGAL_FUNCTION)
            return handler(pdu, now)
        except MBException as e:
            if e.mcode_error is not None:
                self.er = e.mcode_error
            code = e.code
        except Exception:                     # never let one frame kill the server
            code = SLAVE_DEVICE_FAILURE
        self.counters['exceptions']['%02d' % code] += 1
        return bytes([(fc | 0x80) & 0xFF, code])

    # FC 01 / FC 02 ---------------------------------------------------------
    def _bit_window_request(self, pdu):
        if len(pdu) != 5:
            raise MBException(ILLEGAL_DATA_VALUE)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not 1 <= qty <= 4:
            raise MBException(ILLEGAL_DATA_VALUE)
        return start, qty

    def fc_read_coils(self, pdu, now):
        start, qty = self._bit_window_request(pdu)
        if start < OUTPUT_BASE or start + qty > OUTPUT_BASE + 4:
            raise MBException(ILLEGAL_DATA_ADDRESS)
        bits = 0
        for k in range(qty):
            point = start - OUTPUT_BASE + k + 1
            if self.io_kind(point) != 'out':
                raise MBException(ILLEGAL_DATA_ADDRESS)
            if self.output_state(point, now):
                bits |= 1 << k
        return bytes([0x01, 1, bits])

    def fc_read_discrete_inputs(self, pdu, now):
        start, qty = self._bit_window_request(pdu)
        if start < INPUT_BASE or start + qty > INPUT_BASE + 4:
            raise MBException(ILLEGAL_DATA_ADDRESS)
        bits = 0
        for k in range(qty):
            point = start - INPUT_BASE + k + 1
            if self.io_kind(point) != 'in':
                raise MBException(ILLEGAL_DATA_ADDRESS)
            if self.input_state(point):
                bits |= 1 << k
        return bytes([0x02, 1, bits])

    # FC 05 ---------------------------------------------------------------
    def fc_write_single_coil(self, pdu, now):
        if len(pdu) != 5:
            raise MBException(ILLEGAL_DATA_VALUE)
        addr, value = struct.unpack('>HH', pdu[1:5])
        if value not in (0x0000, 0xFF00):
            raise MBException(ILLEGAL_DATA_VALUE)
        if not OUTPUT_BASE <= addr < OUTPUT_BASE + 4:
            raise MBException(ILLEGAL_DATA_ADDRESS)
        point = addr - OUTPUT_BASE + 1
        if self.mfg['S%d' % point][0] != 16:
            raise MBException(ILLEGAL_DATA_ADDRESS)
        self.out_latch[point - 1] = 1 if value == 0xFF00 else 0
        return bytes(pdu[:5])

    # FC 03 ---------------------------------------------------------------
    def _resolve(self, start, qty, for_write):
        """Map [start, start+qty) onto whole parameters or raise 02."""
        if start + qty > 0x10000:
            raise MBException(ILLEGAL_DATA_ADDRESS)
        out = []
        a = start
        end = start + qty
        while a < end:
            p = PARAM_BY_ADDR.get(a)
            if p is None or p.addr != a or a + p.n > end:
                raise MBException(ILLEGAL_DATA_ADDRESS)
            if for_write:
                if p.access == 'ro':
                    raise MBException(ILLEGAL_DATA_ADDRESS)
                if p.name in ('O1', 'O2', 'O3', 'O4') and \
                        self.mfg['S' + p.name[1]][0] != 16:
                    raise MBException(ILLEGAL_DATA_ADDRESS)
            else:
                if not self.readable(p):
                    raise MBException(ILLEGAL_DATA_ADDRESS)
            out.append(p)
            a += p.n
        return out

    def fc_read_holding(self, pdu, now):
        if len(pdu) != 5:
            raise MBException(ILLEGAL_DATA_VALUE)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if not 1 <= qty <= 4:
            raise MBException(ILLEGAL_DATA_VALUE)
        params = self._resolve(start, qty, for_write=False)
        data = b''
        for p in params:
            v = self.read_value(p, now)
            if p.n == 2:
                data += struct.pack('>I', v & 0xFFFFFFFF)
            else:
                data += struct.pack('>H', v & 0xFFFF)
        for p in params:
            if p.name == 'ER':            # "must be read or set to 0 to clear"
                self.er = 0
        return bytes([0x03, len(data)]) + data

    # FC 16 ---------------------------------------------------------------
    def fc_write_multiple(self, pdu, now):
        if len(pdu) < 6:
            raise MBException(ILLEGAL_DATA_VALUE)
        start, qty, bc = struct.unpack('>HHB', pdu[1:6])
        if not 1 <= qty <= 4 or bc != 2 * qty or len(pdu) != 6 + bc:
            raise MBException(ILLEGAL_DATA_VALUE)
        params = self._resolve(start, qty, for_write=True)
        # decode
        values = []
        off = 6
        for p in params:
            if p.n == 2:
                raw = struct.unpack('>I', pdu[off:off + 4])[0]
                v = wrap32(raw) if p.signed else raw
            else:
                raw = struct.unpack('>H', pdu[off:off + 2])[0]
                v = raw
            off += 2 * p.n
            values.append((p, v))
        # range / value checks (03)
        new = {}
        for p, v in values:
            if not p.check_value(v):
                raise MBException(ILLEGAL_DATA_VALUE)
            new[p.name] = v
        vi = new.get('VI', self.reg['VI'])
        vm = new.get('VM', self.reg['VM'])
        if not vi < vm:
            raise MBException(ILLEGAL_DATA_VALUE)
        ht = new.get('HT', self.reg['HT'])
        mt = new.get('MT', self.reg['MT'])
        if ht == 1 or ht + mt > 65535:
            raise MBException(ILLEGAL_DATA_VALUE)
        for name in ('OL', 'OT'):
            if name in new:
                for i in range(4):
                    if new[name] >> i & 1 and self.mfg['S%d' % (i + 1)][0] != 16:
                        raise MBException(ILLEGAL_DATA_VALUE)
        # state interlocks (04)
        moving = self.motion is not None
        abs_moving = moving and self.motion.kind == 'abs'
        de = new.get('DE', self.reg['DE'])
        for p, v in values:
            if p.lock and moving:
                raise MBException(SLAVE_DEVICE_FAILURE)
            if p.name in ('MA', 'MR'):
                if de != 1:
                    raise MBException(SLAVE_DEVICE_FAILURE)
                if moving:
                    raise MBException(SLAVE_DEVICE_FAILURE, MCODE_ERR_MOVE_WHILE_MOVING)
            if p.name == 'SL':
                if abs_moving:
                    raise MBException(SLAVE_DEVICE_FAILURE, MCODE_ERR_MOVE_WHILE_MOVING)
                if v != 0 and de != 1:
                    raise MBException(SLAVE_DEVICE_FAILURE)
            if p.name == 'S' and moving:
                raise MBException(SLAVE_DEVICE_FAILURE, MCODE_ERR_SAVE_WHILE_MOVING)
        # apply settings first, commands afterwards
        commands = []
        for p, v in values:
            if p.access == 'wo':
                commands.append((p, v))
            else:
                self._apply_setting(p, v, now)
        for p, v in commands:
            self._apply_command(p, v, now)
        return bytes([0x10]) + struct.pack('>HH', start, qty)

    def _apply_setting(self, p, v, now):
        n = p.name
        if n == 'P':
            self.p_base = v
        elif n == 'C1':
            self.c1_base = v
        elif n == 'C2':
            self.c2_base = v
            self.c2_frac = 0.0
        elif n == 'ER':
            self.er = 0
        elif n == 'ST':
            self.stall = 0
        elif n in ('O1', 'O2', 'O3', 'O4'):
            self.out_latch[int(n[1]) - 1] = v
        elif n in ('OL', 'OT'):
            for i in range(4):
                if self.mfg['S%d' % (i + 1)][0] == 16:
                    self.out_latch[i] = v >> i & 1
        elif n == 'DE':
            self.reg['DE'] = v
            if v == 0:
                self.stop_immediately(now)     # bridge off: axis stops at once
        elif n == 'TE':
            self.reg['TE'] = v
            if v & TRIP_ON_RELATIVE_POSITION:
                self.trip_ref = self.position(now)
        elif n in self.reg:
            self.reg[n] = v

    def _apply_command(self, p, v, now):
        n = p.name
        if n == 'MA':
            self.start_abs(now, v, v - self.p_base)
        elif n == 'MR':
            self.start_abs(now, wrap32(self.p_base + v), v)
        elif n == 'SL':
            if self.motion is None and v == 0:
                return
            self.start_slew(now, v)
        elif n == 'S':
            self.nvm = self._nvm_image()
            self.nvm_saves += 1
        elif n in ('DC', 'IC'):
            name = USER_VAR_ADDRS[v]
            self.reg[name] = wrap32(self.reg[name] + (1 if n == 'IC' else -1))

    def _nvm_image(self):
        img = {k: self.reg[k] for k in NVM_REGISTER_SETTINGS}
        img.update(self.mfg_strings())
        return img

    # FC 43 / 14 ----------------------------------------------------------
    def fc_encapsulated(self, pdu, now):
        if len(pdu) < 2:
            raise MBException(ILLEGAL_DATA_VALUE)
        if pdu[1] != 0x0E:
            raise MBException(ILLEGAL_FUNCTION)
        if len(pdu) != 4:
            raise MBException(ILLEGAL_DATA_VALUE)
        code, obj = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise MBException(ILLEGAL_DATA_VALUE)
        if code == 4:
            if obj not in DEVICE_ID_OBJECTS:
                raise MBException(ILLEGAL_DATA_ADDRESS)
            ids = [obj]
        else:
            last = 0x02 if code == 1 else 0x06
            if obj > last:
                obj = 0
            ids = list(range(obj, last + 1))
        body = b''
        for i in ids:
            val = DEVICE_ID_OBJECTS[i]
            body += bytes([i, len(val)]) + val
        return bytes([0x2B, 0x0E, code, CONFORMITY_LEVEL, 0x00, 0x00, len(ids)]) + body

    # FC 65 / FC 66 -------------------------------------------------------
    @staticmethod
    def _mnemonic(b4):
        s = bytes(reversed(b4))
        stripped = s.rstrip(b' ')
        if not stripped or b' ' in stripped:
            return None
        try:
            return stripped.decode('ascii')
        except UnicodeDecodeError:
            return None

    SETTING_MNEMONICS = ('S1', 'S2', 'S3', 'S4', 'S7', 'S8', 'CR', 'S5', 'S13', 'TR')
    ACTION_MNEMONICS = ('E', 'EX', 'PS', 'RS')
    PARAM_LENGTHS = {'S1': (6, 7), 'S2': (6, 7), 'S3': (6, 7), 'S4': (6, 7),
                     'S7': (4, 5), 'S8': (4, 5), 'CR': (2, 6), 'S5': (4, 5),
                     'S13': (4, 5), 'TR': (2, 11), 'EX': (1, 4),
                     'E': (0, 0), 'PS': (0, 0), 'RS': (0, 0)}

    def mfg_string(self, m):
        v = self.mfg[m]
        if m == 'CR':
            return self._fmt_cr(v)
        if m == 'TR':
            return str(v)
        return ', '.join(str(x) for x in v)

    def mfg_strings(self):
        return {m: self.mfg_string(m) for m in self.SETTING_MNEMONICS}

    @staticmethod
    def _fmt_cr(d):
        if d.as_tuple().exponent > -3:
            d = d.quantize(Decimal('0.001'))
        return format(d, 'f')

    def fc_mfg_read(self, pdu, now):
        if len(pdu) < 5:
            raise MBException(ILLEGAL_DATA_VALUE)
        m = self._mnemonic(pdu[1:5])
        if m not in self.SETTING_MNEMONICS and m not in self.ACTION_MNEMONICS:
            raise MBException(ILLEGAL_DATA_ADDRESS)
        if len(pdu) == 5:
            params = b''
        else:
            if pdu[5] != len(pdu) - 6:
                raise MBException(ILLEGAL_DATA_VALUE)
            params = bytes(pdu[6:])
        if m in self.SETTING_MNEMONICS:
            if len(pdu) != 5:
                raise MBException(ILLEGAL_DATA_VALUE)
            s = self.mfg_string(m).encode('ascii')
            return bytes([0x41, len(s)]) + s
        self._run_action(m, params)
        return bytes([0x41, 0x00])

    def fc_mfg_write(self, pdu, now):
        if len(pdu) < 6:
            raise MBException(ILLEGAL_DATA_VALUE)
        bc = pdu[5]
        if bc != len(pdu) - 6 or bc > 28:
            raise MBException(ILLEGAL_DATA_VALUE)
        m = self._mnemonic(pdu[1:5])
        if m not in self.SETTING_MNEMONICS and m not in self.ACTION_MNEMONICS:
            raise MBException(ILLEGAL_DATA_ADDRESS)
        params = bytes(pdu[6:])
        if m in self.ACTION_MNEMONICS:
            self._run_action(m, params)
        else:
            lo, hi = self.PARAM_LENGTHS[m]
            if not lo <= len(params) <= hi:
                raise MBException(ILLEGAL_DATA_VALUE)
            self.mfg[m] = self._parse_setting(m, params)
            if m in ('S1', 'S2', 'S3', 'S4') and self.mfg[m][0] != 16:
                self.out_latch[int(m[1]) - 1] = 0   # no longer a GP output
        return bytes([0x42, 0x04]) + bytes(pdu[1:5])

    @staticmethod
    def _int_field(s, allow_sign=False):
        neg = False
        if allow_sign and s[:1] in ('-', '+'):
            neg = s[0] == '-'
            s = s[1:]
        if not s or not s.isdigit() or not s.isascii():
            raise MBException(ILLEGAL_DATA_VALUE)
        v = int(s)
        return -v if neg else v

    def _parse_setting(self, m, params):
        try:
            text = params.decode('ascii')
        except UnicodeDecodeError:
            raise MBException(ILLEGAL_DATA_VALUE)
        if not text.startswith('='):
            raise MBException(ILLEGAL_DATA_VALUE)
        body = text[1:]
        if m == 'CR':
            if not body or any(c not in '0123456789.' for c in body) or body.count('.') > 1 \
                    or body == '.':
                raise MBException(ILLEGAL_DATA_VALUE)
            try:
                d = Decimal(body)
            except InvalidOperation:
                raise MBException(ILLEGAL_DATA_VALUE)
            if not Decimal('0.001') <= d <= Decimal('1000'):
                raise MBException(ILLEGAL_DATA_VALUE)
            return d
        if m == 'TR':
            v = self._int_field(body, allow_sign=True)
            if not -2147483648 <= v <= 2147483647:
                raise MBException(ILLEGAL_DATA_VALUE)
            return v
        fields = [self._int_field(f) for f in body.split(',')]
        if m in ('S1', 'S2', 'S3', 'S4'):
            if len(fields) != 3:
                raise MBException(ILLEGAL_DATA_VALUE)
            a, b, c = fields
            if a not in IO_INPUT_FUNCS | IO_OUTPUT_FUNCS or b not in (0, 1) or c not in (0, 1):
                raise MBException(ILLEGAL_DATA_VALUE)
            return (a, b, c)
        if len(fields) != 2:
            raise MBException(ILLEGAL_DATA_VALUE)
        a, b = fields
        allowed = {'S7': CLOCK_IO_FUNCS, 'S8': CLOCK_IO_FUNCS,
                   'S5': ANALOG_MODES, 'S13': CAPTURE_TRIP_MODES}[m]
        if a not in allowed or b not in (0, 1):
            raise MBException(ILLEGAL_DATA_VALUE)
        return (a, b)

    def _run_action(self, m, params):
        lo, hi = self.PARAM_LENGTHS[m]
        if not lo <= len(params) <= hi:
            raise MBException(ILLEGAL_DATA_VALUE)
        if m == 'E':
            self.program = {'state': 'idle', 'label': None}
            return
        if m == 'EX':
            try:
                lab = params.decode('ascii')
            except UnicodeDecodeError:
                raise MBException(ILLEGAL_DATA_VALUE)
            is_label = len(lab) == 2 and 'A' <= lab[0] <= 'Z' and \
                (lab[1].isdigit() or 'A' <= lab[1] <= 'Z')
            is_addr = lab.isdigit() and lab.isascii() and int(lab) >= 1
            if not (is_label or is_addr):
                raise MBException(ILLEGAL_DATA_VALUE)
            # Program memory is empty: programs can only be downloaded over
            # MCode/TCP (port 503), which this unit does not offer.
            raise MBException(SLAVE_DEVICE_FAILURE, MCODE_ERR_UNKNOWN_LABEL)
        if m == 'PS':
            if self.program['state'] != 'running':
                raise MBException(SLAVE_DEVICE_FAILURE, MCODE_ERR_PROGRAM_NOT_RUNNING)
            self.program['state'] = 'paused'
            return
        if m == 'RS':
            if self.program['state'] != 'paused':
                raise MBException(SLAVE_DEVICE_FAILURE, MCODE_ERR_PROGRAM_NOT_RUNNING)
            self.program['state'] = 'running'
            return

    # ----------------------------------------------------------- state dump
    def snapshot(self):
        now = time.monotonic()
        self.update(now)
        regs = {}
        for p in PARAMS:
            key = '0x%04X' % p.addr
            entry = {'name': p.name, 'registers': p.n, 'access': p.access,
                     'signed': p.signed}
            if p.access == 'wo':
                entry['value'] = None
            else:
                entry['value'] = self.read_value(p, now)
            regs[key] = entry
        coils = {}
        inputs = {}
        for i in range(1, 5):
            coils['0x%04X' % (OUTPUT_BASE + i - 1)] = {
                'point': i, 'configured_as_output': self.io_kind(i) == 'out',
                'latch': self.out_latch[i - 1], 'state': self.output_state(i, now)}
            inputs['0x%04X' % (INPUT_BASE + i - 1)] = {
                'point': i, 'configured_as_input': self.io_kind(i) == 'in',
                'state': self.input_state(i)}
        delta, vel, accel = self._motion_delta(now)
        motion = {
            'moving': self.motion is not None,
            'kind': self.motion.kind if self.motion else None,
            'target': self.motion.target if self.motion else None,
            'position': self._pos_from_delta(delta),
            'velocity': int(round(vel)),
            'trip_reference_position': self.trip_ref,
        }
        counters = dict(self.counters)
        counters['trip_events'] = self.trip_events
        counters['nvm_save_count'] = self.nvm_saves
        return {
            'device': 'MDrive Plus2 Motion Control Ethernet (MODBUS/TCP)',
            'unit_ids': list(ACCEPTED_UNIT_IDS),
            'holding_registers': regs,
            'coils': coils,
            'discrete_inputs': inputs,
            'manufacturer_parameters': self.mfg_strings(),
            'nvm': self.nvm,
            'program': dict(self.program),
            'motion': motion,
            'device_identification': {('0x%02X' % k): v.decode() for k, v in
                                       DEVICE_ID_OBJECTS.items()},
            'diagnostic_counters': counters,
        }


# ---------------------------------------------------------------------------
class Server:
    def __init__(self, drive, state_file):
        self.drive = drive
        self.state_file = state_file
        self.active = 0
        self.stop_event = None

    def dump_state(self):
        if not self.state_file:
            return
        try:
            data = json.dumps(self.drive.snapshot(), indent=1, sort_keys=True)
            tmp = self.state_file + '.tmp'
            with open(tmp, 'w') as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.state_file)
        except Exception as e:              # a dump problem must not kill the drive
            print('state dump failed: %s' % e, file=sys.stderr, flush=True)

    async def handle(self, reader, writer):
        c = self.drive.counters
        if self.active >= MAX_CONNECTIONS:
            c['connections_refused'] += 1
            writer.close()
            return
        self.active += 1
        c['connections_accepted'] += 1
        try:
            while True:
                first = await reader.readexactly(1)
                try:
                    rest = await asyncio.wait_for(reader.readexactly(6),
                                                  FRAME_COMPLETION_TIMEOUT)
                except asyncio.TimeoutError:
                    c['connections_closed_timeout'] += 1
                    break
                tid, pid, length, uid = struct.unpack('>HHHB', first + rest)
                if length < 2 or length > MAX_MBAP_LENGTH:
                    # cannot resynchronise a byte stream with a bogus length
                    c['connections_closed_bad_length'] += 1
                    break
                try:
                    pdu = await asyncio.wait_for(reader.readexactly(length - 1),
                                                 FRAME_COMPLETION_TIMEOUT)
                except asyncio.TimeoutError:
                    c['connections_closed_timeout'] += 1
                    break
                c['frames_received'] += 1
                if pid != 0:
                    c['frames_dropped_protocol_id'] += 1
                    continue
                if uid not in ACCEPTED_UNIT_IDS:
                    c['frames_dropped_unit_id'] += 1
                    continue
                resp = self.drive.process(pdu)
                writer.write(struct.pack('>HHHB', tid, 0, len(resp) + 1, uid) + resp)
                c['responses_sent'] += 1
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError):
            pass
        finally:
            self.active -= 1
            try:
                writer.close()
            except Exception:
                pass

    async def run(self, host, port):
        loop = asyncio.get_running_loop()
        self.stop_event = asyncio.Event()
        loop.add_signal_handler(signal.SIGUSR1, self.dump_state)
        loop.add_signal_handler(signal.SIGTERM, self.stop_event.set)
        loop.add_signal_handler(signal.SIGINT, self.stop_event.set)
        server = await asyncio.start_server(self.handle, host, port, reuse_address=True)
        actual = server.sockets[0].getsockname()[1]
        print('listening tcp %s:%d' % (host, actual), flush=True)
        try:
            await self.stop_event.wait()
        finally:
            server.close()
            self.dump_state()


def parse_listen(s):
    host, _, port = s.rpartition(':')
    if host not in ('127.0.0.1', 'localhost', '::1', '[::1]'):
        raise SystemExit('refusing to bind to non-loopback address %r' % host)
    if host == 'localhost':
        host = '127.0.0.1'
    return host.strip('[]'), int(port)


def main():
    ap = argparse.ArgumentParser(description='MDrive Plus2 Ethernet MODBUS/TCP simulator')
    ap.add_argument('--listen', default='127.0.0.1:0')
    ap.add_argument('--state', default=None)
    args = ap.parse_args()
    host, port = parse_listen(args.listen)
    srv = Server(Drive(), args.state)
    asyncio.run(srv.run(host, port))


if __name__ == '__main__':
    main()
