#!/usr/bin/env python3
"""MDrive 23 Hybrid Motion Control (Ethernet) -- MODBUS/TCP server simulator.

Written from the "MODBUS/TCP Fieldbus Manual, MDrive Motion Control Products"
(R040611) and the public Modbus specifications.  Standard library only.
See DECISIONS.md for every place where the manual was silent or wrong.
"""
import argparse
import asyncio
import json
import os
import signal
import struct
import sys
import time

# ---------------------------------------------------------------------------
# "Microcontroller" characteristics (see DECISIONS.md, section M)
# ---------------------------------------------------------------------------
MAX_CONNECTIONS = 4        # socket pool of the Ethernet controller
RX_BUFFER = 64             # bytes: one ADU (MBAP + PDU) receive buffer
PROC_DELAY = 0.003         # s: main-loop turnaround before each answer
NVM_SAVE_TIME = 0.400      # s: EEPROM write time after a Save (0x0076)
TICK = 0.005               # s: motion profile tick

INT32_MIN, INT32_MAX = -2 ** 31, 2 ** 31 - 1
MS_VALUES = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200,
             250, 256, 180, 108, 127)

# Exception codes
ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3
DEVICE_FAILURE = 4
DEVICE_BUSY = 6


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# ---------------------------------------------------------------------------
# Register map (Section 5 / 5.1 / 5.2).  Variant: MDrive Hybrid.
#   (address, words, mnemonic, access, lo, hi, default, signed)
#   access: rw = read/write, ro = read only, cmd = command (write; reads 0)
# ---------------------------------------------------------------------------
S32 = (INT32_MIN, INT32_MAX)
REGISTERS = [
    (0x0000, 2, 'A', 'rw', 91, 1525878997, 1000000, False),
    (0x0005, 2, 'C1', 'rw', *S32, 0, True),
    (0x0007, 2, 'C2', 'rw', *S32, 0, True),
    (0x0009, 1, 'CE', 'rw', 0, 1, 1, False),
    (0x000F, 1, 'D1', 'rw', 0, 255, 0, False),
    (0x0010, 1, 'D2', 'rw', 0, 255, 0, False),
    (0x0011, 1, 'D3', 'rw', 0, 255, 0, False),
    (0x0012, 1, 'D4', 'rw', 0, 255, 0, False),
    (0x0013, 1, 'D5', 'rw', 0, 255, 0, False),
    (0x0018, 2, 'D', 'rw', 91, 1525878997, 1000000, False),
    (0x001B, 1, 'DC', 'cmd', 1, 4, 0, False),
    (0x001C, 1, 'DE', 'rw', 0, 1, 1, False),
    (0x001E, 1, 'EE', 'rw', 0, 1, 0, False),
    (0x001F, 1, 'EF', 'ro', 0, 1, 0, False),
    (0x0021, 1, 'ER', 'rw', 0, 0, 0, False),
    (0x0029, 1, 'HC', 'rw', 0, 100, 5, False),
    (0x002B, 1, 'HM', 'rw', 1, 4, 1, False),
    (0x002C, 1, 'HT', 'rw', 0, 65535, 500, False),
    (0x002D, 1, 'I1', 'ro', 0, 1, 0, False),
    (0x002E, 1, 'I2', 'ro', 0, 1, 0, False),
    (0x002F, 1, 'I3', 'ro', 0, 1, 0, False),
    (0x0030, 1, 'I4', 'ro', 0, 1, 0, False),
    (0x0031, 1, 'I5', 'ro', 0, 1023, 0, False),
    (0x0037, 1, 'IC', 'cmd', 1, 4, 0, False),
    (0x003A, 1, 'IL', 'ro', 0, 15, 0, False),
    (0x003B, 1, 'IN', 'ro', 0, 15, 0, False),
    (0x003F, 1, 'JE', 'rw', 0, 1, 0, False),
    (0x0042, 1, 'LM', 'rw', 1, 6, 1, False),
    (0x0043, 2, 'MA', 'cmd', *S32, 0, True),
    (0x0045, 1, 'MP', 'ro', 0, 1, 0, False),
    (0x0046, 2, 'MR', 'cmd', *S32, 0, True),
    (0x0048, 1, 'MS', 'rw', 1, 256, 256, False),
    (0x0049, 1, 'MT', 'rw', 0, 65000, 0, False),
    (0x004A, 1, 'MV', 'ro', 0, 1, 0, False),
    (0x004B, 1, 'O1', 'rw', 0, 1, 0, False),
    (0x004C, 1, 'O2', 'rw', 0, 1, 0, False),
    (0x004D, 1, 'O3', 'rw', 0, 1, 0, False),
    (0x004E, 1, 'O4', 'rw', 0, 1, 0, False),
    (0x0055, 1, 'OL', 'rw', 0, 15, 0, False),
    (0x0056, 1, 'OT', 'rw', 0, 15, 0, False),
    (0x0057, 2, 'P', 'rw', *S32, 0, True),
    (0x0059, 2, 'PC', 'ro', *S32, 0, True),
    (0x005F, 2, 'R1', 'rw', *S32, 0, True),
    (0x0061, 2, 'R2', 'rw', *S32, 0, True),
    (0x0063, 2, 'R3', 'rw', *S32, 0, True),
    (0x0065, 2, 'R4', 'rw', *S32, 0, True),
    (0x0067, 1, 'RC', 'rw', 1, 100, 25, False),
    (0x0076, 1, 'S', 'cmd', 0, 65535, 0, False),
    (0x0078, 2, 'SL', 'cmd', -5000000, 5000000, 0, True),
    (0x007D, 1, 'TE', 'rw', 0, 16, 0, False),
    (0x0085, 2, 'V', 'ro', *S32, 0, True),
    (0x0088, 1, 'VC', 'ro', 0, 1, 0, False),
    (0x0089, 2, 'VI', 'rw', 1, 4999999, 1000, False),
    (0x008B, 2, 'VM', 'rw', 2, 5000000, 768000, False),
    # 5.1 Hybrid specific registers
    (0x008E, 1, 'AS', 'rw', 0, 3, 2, False),
    (0x008F, 1, 'AF', 'ro', 0, 255, 0, False),
    (0x0090, 1, 'CA', 'rw', 0, 1, 1, False),
    (0x0091, 1, 'CB', 'rw', 0, 3, 1, False),
    (0x0092, 1, 'CC', 'rw', 1, 100, 100, False),
    (0x0093, 1, 'CF', 'cmd', 0, 65535, 0, False),
    (0x0094, 1, 'CT', 'rw', 2, 65535, 200, False),
    (0x0095, 2, 'LD', 'rw', 0, INT32_MAX, 102400, False),
    (0x0097, 2, 'LG', 'rw', 0, INT32_MAX, 102400, False),
    (0x0099, 2, 'LL', 'ro', *S32, 0, True),
    (0x009B, 1, 'LR', 'ro', 0, 1, 0, False),
    (0x009C, 2, 'LT', 'rw', 2, 65535, 2000, False),
    (0x009E, 2, 'MF', 'rw', 306, 5000000, 768000, False),
    (0x00A0, 1, 'MU', 'rw', 0, 2, 0, False),
    (0x00A1, 1, 'SC', 'cmd', 0, 65535, 0, False),
    (0x00A2, 1, 'SS', 'rw', 0, 255, 0, False),
    (0x00A5, 1, 'TD', 'rw', 0, 1, 1, False),
    (0x00A6, 1, 'TQ', 'rw', 1, 100, 25, False),
    (0x00A7, 1, 'TS', 'rw', 0, 255, 0, False),
]
# 5.2 User variable registers V1..V8
for _i in range(8):
    REGISTERS.append((0x00A8 + 2 * _i, 2, 'V%d' % (_i + 1), 'rw', *S32, 0, True))

REG_BY_NAME = {r[2]: r for r in REGISTERS}
# word address -> (register tuple, word index within it)
WORD_MAP = {}
for _r in REGISTERS:
    for _k in range(_r[1]):
        WORD_MAP[_r[0] + _k] = (_r, _k)

COIL_BASE = 0x004B      # FC01 / FC05: outputs 1-4
INPUT_BASE = 0x002D     # FC02: inputs 1-4

# Manufacturer specific I/O function codes (4.3.1)
IO_INPUT_FUNCS = {0, 1, 2, 3, 5, 7, 8, 11}
IO_OUTPUT_FUNCS = {16, 17, 18, 20, 21, 23, 24, 25}   # 24/25: Hybrid only (we are Hybrid)
CLK_FUNCS = {33, 34, 35, 49, 50, 51}

DEVICE_ID = [
    b'SEM USA',             # 0x00 VendorName
    b'MAI1FRZ23A7-EQ',      # 0x01 ProductCode ("MDrive P/N")
    b'4.0.0.0',             # 0x02 MajorMinorRevision
    b'www.imshome.com',     # 0x03 VendorUrl
    b'MDrive Ethernet',     # 0x04 ProductName
    b'H2311040001',         # 0x05 ("Serial number" per manual)
    b'ASI 4.0.0.0',         # 0x06 ("ASI 4.x.x.x" per manual)
]


def u16(v):
    return v & 0xFFFF


def wrap32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


class Drive:
    def __init__(self):
        self.val = {r[2]: r[6] for r in REGISTERS}
        # manufacturer-specific settings (4.3.1)
        self.io = {n: [0, 0, 0] for n in (1, 2, 3, 4)}   # GP input, active lo, sinking
        self.clk = {7: [33, 0], 8: [33, 0]}
        self.cr_milli = 1000                              # clock ratio 1.000
        self.s5 = [9, 0]
        self.s13 = [60, 0]
        self.tr = [0, 0, 0]
        self.mu_b = 0
        self.latch = {n: 0 for n in (1, 2, 3, 4)}
        self.program = {'state': 'stopped', 'label': None}
        # motion
        self.pos = 0.0
        self.vel = 0.0
        self.mode = 'idle'          # idle | move | slew
        self.target = 0
        self.slew_v = 0.0
        self.vchanging = 0
        self.trip_ref = 0
        now = time.monotonic()
        self.last = now
        self.cal_until = now        # power-on calibration already complete
        self.busy_until = 0.0       # NVM write in progress until
        self.lock = asyncio.Lock()
        self.counters = {'bus_messages': 0, 'exception_responses': 0,
                         'non_modbus_frames_dropped': 0, 'oversize_frames': 0,
                         'connections_refused': 0, 'framing_errors': 0}
        self.nvm = self._nvm_image()

    # ------------------------------------------------------------------ state
    def _nvm_image(self):
        img = {('0x%04X' % r[0]): self.val[r[2]] for r in REGISTERS
               if r[3] == 'rw' and r[2] not in ('C1', 'C2', 'P', 'ER', 'O1', 'O2', 'O3',
                                                   'O4', 'OL', 'OT')}
        img.update(self._mfg_strings())
        return img

    def _mfg_strings(self):
        d = {}
        for n in (1, 2, 3, 4):
            d['S%d' % n] = '%d, %d, %d' % tuple(self.io[n])
        for n in (7, 8):
            d['S%d' % n] = '%d, %d' % tuple(self.clk[n])
        d['CR'] = '%d.%03d' % divmod(self.cr_milli, 1000)
        d['S5'] = '%d, %d' % tuple(self.s5)
        d['S13'] = '%d, %d' % tuple(self.s13)
        d['TR'] = '%d, %d, %d' % tuple(self.tr)
        d['MU'] = '%d, %d' % (self.val['MU'], self.mu_b)
        return d

    def calibrating(self, now):
        return now < self.cal_until

    def start_calibration(self, now):
        if self.val['AS'] != 0:
            self.cal_until = now + self.val['CT'] / 1000.0

    def pin(self, n):
        """Logic state of I/O point n (1..4)."""
        f = self.io[n][0]
        if f < 16:
            return 0            # no field wiring: inputs are inactive
        return {16: self.latch[n], 17: int(self.mode != 'idle'),
                18: self.val['EF'], 20: self.vchanging, 21: 0,
                23: int(self.mode == 'move'),
                24: int(self.val['AS'] != 0 and self.val['DE'] == 1),
                25: 0}.get(f, 0)

    def out_bits(self):
        return sum(self.pin(n) << (n - 1) for n in (1, 2, 3, 4))

    def af(self, now):
        v = 0
        if self.val['AS'] != 0 and self.val['DE'] == 1:
            v |= 16
        v |= 64                          # lead/lag is zero (ideal rotor)
        if not self.calibrating(now):
            v |= 128
        return v

    def reg_value(self, name, now, side_effects=False):
        if name == 'P':
            return wrap32(round(self.pos))
        if name in ('I1', 'I2', 'I3', 'I4'):
            return self.pin(int(name[1]))
        if name in ('O1', 'O2', 'O3', 'O4'):
            return self.pin(int(name[1]))
        if name in ('IL', 'IN', 'OL', 'OT'):
            return self.out_bits()
        if name == 'MV':
            return int(self.mode != 'idle')
        if name == 'MP':
            return int(self.mode == 'move')
        if name == 'V':
            return int(round(self.vel))
        if name == 'VC':
            return self.vchanging
        if name == 'AF':
            return self.af(now)
        if name in ('LL', 'LR', 'I5', 'PC'):
            return self.val[name]
        if name == 'ER' and side_effects:
            v = self.val['ER']
            self.val['ER'] = 0          # "must be read or set to 0 to clear"
            self.val['EF'] = 0
            return v
        if REG_BY_NAME[name][3] == 'cmd':
            return 0
        return self.val[name]

    # ----------------------------------------------------------------- motion
    def update(self, now):
        dt = now - self.last
        self.last = now
        if dt <= 0:
            return
        if dt > 5.0:
            dt = 5.0
        steps = 0
        while dt > 1e-9 and steps < 2000:
            h = min(TICK, dt)
            self._step(h)
            dt -= h
            steps += 1

    def _advance(self, delta):
        old = wrap32(round(self.pos))
        self.pos += delta
        if self.pos > INT32_MAX + 0.5:
            self.pos -= 2 ** 32
        elif self.pos < INT32_MIN - 0.5:
            self.pos += 2 ** 32
        new = wrap32(round(self.pos))
        d = wrap32(new - old)
        if d:
            self.val['C1'] = wrap32(self.val['C1'] + d)
            self.val['C2'] = wrap32(self.val['C2'] + d)
            if self.val['TE'] & 16 and self.tr[0] != 0:
                if abs(wrap32(new - self.trip_ref)) >= abs(self.tr[0]):
                    self.val['TE'] &= ~16       # trip fired; re-enable via 0x007D

    def _stop(self):
        self.mode = 'idle'
        self.vel = 0.0
        self.vchanging = 0

    def _step(self, h):
        if self.mode == 'idle':
            self.vchanging = 0
            return
        A = float(self.val['A'])
        D = float(self.val['D'])
        vi = float(self.val['VI'])
        vm = float(self.val['VM'])
        if self.mode == 'move':
            d = self.target - self.pos
            if abs(d) < 0.5:
                self.pos = float(self.target)
                self._stop()
                return
            s = 1.0 if d > 0 else -1.0
            dist = abs(d)
            v = abs(self.vel)
            if v < vi:
                v = vi
            stop_dist = (v * v - vi * vi) / (2.0 * D) if v > vi else 0.0
            if dist <= stop_dist + v * h:
                nv = max(vi, v - D * h)
            elif v > vm:
                nv = max(vm, v - D * h)
            else:
                nv = min(vm, v + A * h)
            self.vchanging = int(abs(nv - abs(self.vel)) > 1e-6)
            step = nv * h
            if step >= dist:
                self._advance(self.target - self.pos)
                self.pos = float(self.target)
                self._stop()
            else:
                self._advance(s * step)
                self.vel = s * nv
        elif self.mode == 'slew':
            vt = self.slew_v
            v = self.vel
            if v == 0.0:
                if vt == 0.0:
                    self._stop()
                    return
                v = (1.0 if vt > 0 else -1.0) * min(vi, abs(vt))
            same = (v > 0) == (vt > 0) and vt != 0.0
            if same and abs(vt) >= abs(v):
                nv = min(abs(vt), abs(v) + A * h)
                nv = nv if v > 0 else -nv
            elif same:
                nv = max(abs(vt), abs(v) - D * h)
                nv = nv if v > 0 else -nv
            else:
                mag = abs(v) - D * h
                if mag <= min(vi, abs(v)):
                    if vt == 0.0:
                        self._stop()
                        return
                    nv = (1.0 if vt > 0 else -1.0) * min(vi, abs(vt))
                else:
                    nv = mag if v > 0 else -mag
            self.vchanging = int(abs(nv - self.vel) > 1e-6)
            self.vel = nv
            self._advance(nv * h)

    def check_motion_allowed(self, now):
        if self.val['DE'] != 1:
            raise ModbusError(DEVICE_FAILURE)
        if self.calibrating(now):
            raise ModbusError(DEVICE_BUSY)

    # --------------------------------------------------------------- PDU entry
    def process(self, pdu, now):
        """Return a response PDU (bytes) or raise ModbusError."""
        fc = pdu[0]
        if fc not in (0x01, 0x02, 0x03, 0x05, 0x10, 0x2B, 0x41, 0x42):
            raise ModbusError(ILLEGAL_FUNCTION)
        if fc == 0x2B:
            return self.fc43(pdu)
        self.update(now)
        if now < self.busy_until:
            raise ModbusError(DEVICE_BUSY)
        if fc in (0x01, 0x02):
            return self.fc_bits(pdu)
        if fc == 0x03:
            return self.fc03(pdu, now)
        if fc == 0x05:
            return self.fc05(pdu)
        if fc == 0x10:
            return self.fc16(pdu, now)
        if fc == 0x41:
            return self.fc41(pdu, now)
        return self.fc42(pdu, now)

    # FC 01 / 02
    def fc_bits(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        fc = pdu[0]
        start, qty = struct.unpack('>HH', pdu[1:5])
        if qty < 1 or qty > 2000:
            raise ModbusError(ILLEGAL_VALUE)
        base = COIL_BASE if fc == 0x01 else INPUT_BASE
        if start < base or start + qty > base + 4:
            raise ModbusError(ILLEGAL_ADDRESS)
        bits = 0
        for i in range(qty):
            bits |= self.pin(start - base + 1 + i) << i
        nbytes = (qty + 7) // 8
        return bytes([fc, nbytes]) + bits.to_bytes(nbytes, 'little')

    # FC 03
    def fc03(self, pdu, now):
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if qty < 1 or qty > 4:
            raise ModbusError(ILLEGAL_VALUE)
        if start + qty > 0x10000:
            raise ModbusError(ILLEGAL_ADDRESS)
        for a in range(start, start + qty):
            if a not in WORD_MAP:
                raise ModbusError(ILLEGAL_ADDRESS)
        out = bytearray([0x03, 2 * qty])
        cache = {}
        for a in range(start, start + qty):
            r, k = WORD_MAP[a]
            if r[2] not in cache:
                cache[r[2]] = self.reg_value(r[2], now, side_effects=True)
            v = cache[r[2]]
            if r[1] == 2:
                w = (v >> 16) & 0xFFFF if k == 0 else v & 0xFFFF
            else:
                w = u16(v)
            out += struct.pack('>H', w)
        return bytes(out)

    # FC 05
    def fc05(self, pdu):
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        addr, value = struct.unpack('>HH', pdu[1:5])
        if value not in (0x0000, 0xFF00):
            raise ModbusError(ILLEGAL_VALUE)
        if not COIL_BASE <= addr < COIL_BASE + 4:
            raise ModbusError(ILLEGAL_ADDRESS)
        n = addr - COIL_BASE + 1
        if self.io[n][0] != 16:
            raise ModbusError(DEVICE_FAILURE)   # point is not a general purpose output
        self.latch[n] = 1 if value == 0xFF00 else 0
        return bytes(pdu)

    # FC 16
    def fc16(self, pdu, now):
        if len(pdu) < 6:
            raise ModbusError(ILLEGAL_VALUE)
        start, qty, bc = struct.unpack('>HHB', pdu[1:6])
        if qty < 1 or qty > 4 or bc != 2 * qty or len(pdu) != 6 + bc:
            raise ModbusError(ILLEGAL_VALUE)
        if start + qty > 0x10000:
            raise ModbusError(ILLEGAL_ADDRESS)
        words = struct.unpack('>%dH' % qty, pdu[6:6 + bc])
        # address / access check: whole parameters, writable only
        regs = []
        a = start
        i = 0
        while a < start + qty:
            if a not in WORD_MAP:
                raise ModbusError(ILLEGAL_ADDRESS)
            r, k = WORD_MAP[a]
            if k != 0 or a + r[1] > start + qty:
                raise ModbusError(ILLEGAL_ADDRESS)   # partial 32-bit parameter
            if r[3] == 'ro':
                raise ModbusError(ILLEGAL_ADDRESS)
            if r[1] == 2:
                raw = (words[i] << 16) | words[i + 1]
                v = wrap32(raw) if r[7] else raw
            else:
                v = words[i]
            regs.append((r, v))
            a += r[1]
            i += r[1]
        self.write_params(regs, now)
        return bytes([0x10]) + struct.pack('>HH', start, qty)

    def write_params(self, regs, now):
        new = {r[2]: v for r, v in regs}
        # --- value validation (all before any is applied) ---
        for r, v in regs:
            name, lo, hi = r[2], r[4], r[5]
            if not lo <= v <= hi:
                raise ModbusError(ILLEGAL_VALUE)
            if name == 'MS' and v not in MS_VALUES:
                raise ModbusError(ILLEGAL_VALUE)
            if name == 'HT' and v == 1:
                raise ModbusError(ILLEGAL_VALUE)
            if name == 'TE' and v not in (0, 16):
                raise ModbusError(ILLEGAL_VALUE)
        vi = new.get('VI', self.val['VI'])
        vm = new.get('VM', self.val['VM'])
        if ('VI' in new or 'VM' in new) and not vi < vm:
            raise ModbusError(ILLEGAL_VALUE)
        ht = new.get('HT', self.val['HT'])
        mt = new.get('MT', self.val['MT'])
        if ('HT' in new or 'MT' in new) and ht + mt > 65535:
            raise ModbusError(ILLEGAL_VALUE)
        for name in ('DC', 'IC'):
            if name in new:
                rn = 'R%d' % new[name]
                res = self.val[rn] + (1 if name == 'IC' else -1)
                if not INT32_MIN <= res <= INT32_MAX:
                    raise ModbusError(ILLEGAL_VALUE)
        if 'MR' in new:
            t = wrap32(round(self.pos)) + new['MR']
            if not INT32_MIN <= t <= INT32_MAX:
                raise ModbusError(ILLEGAL_VALUE)
        # --- state checks for commands ---
        if 'MA' in new or 'MR' in new:
            self.check_motion_allowed(now)
            if self.mode != 'idle':
                raise ModbusError(DEVICE_BUSY)
        if 'SL' in new and new['SL'] != 0:
            self.check_motion_allowed(now)
        if 'P' in new and self.mode != 'idle':
            raise ModbusError(DEVICE_BUSY)
        for n in (1, 2, 3, 4):
            if ('O%d' % n) in new and self.io[n][0] != 16:
                raise ModbusError(DEVICE_FAILURE)   # point is not a GP output
        # --- apply, in address order ---
        for r, v in regs:
            self.apply(r[2], v, now)

    def apply(self, name, v, now):
        if name in ('O1', 'O2', 'O3', 'O4'):
            self.latch[int(name[1])] = v
            return
        if name in ('OL', 'OT'):
            for n in (1, 2, 3, 4):
                if self.io[n][0] == 16:
                    self.latch[n] = (v >> (n - 1)) & 1
            return
        if name == 'P':
            self.pos = float(v)
            return
        if name == 'MA':
            self.target = v
            self.mode = 'move'
            return
        if name == 'MR':
            self.target = wrap32(round(self.pos)) + v
            self.mode = 'move'
            return
        if name == 'SL':
            if self.mode == 'idle' and v == 0:
                return
            self.slew_v = float(v)
            self.mode = 'slew'
            return
        if name in ('DC', 'IC'):
            rn = 'R%d' % v
            self.val[rn] += (1 if name == 'IC' else -1)
            return
        if name == 'S':
            self.nvm = self._nvm_image()
            self.busy_until = now + NVM_SAVE_TIME
            return
        if name in ('SC', 'CF'):
            # CF: clear locked rotor (LR), re-enable bridge, timed calibration
            if name == 'CF':
                self.val['LR'] = 0
            self.start_calibration(now)
            return
        old = self.val.get(name)
        self.val[name] = v
        if name == 'DE':
            if v == 0:
                self._stop()
            elif old == 0:
                self.start_calibration(now)
        elif name == 'AS':
            if old == 0 and v != 0:
                self.start_calibration(now)
        elif name == 'MS':
            if v != old:
                self.start_calibration(now)
        elif name == 'TE':
            if v & 16:
                self.trip_ref = wrap32(round(self.pos))
        elif name == 'ER':
            self.val['EF'] = 0

    # FC 43 / 14
    def fc43(self, pdu):
        if len(pdu) < 2:
            raise ModbusError(ILLEGAL_VALUE)
        if pdu[1] != 0x0E:
            raise ModbusError(ILLEGAL_FUNCTION)
        if len(pdu) != 4:
            raise ModbusError(ILLEGAL_VALUE)
        code, oid = pdu[2], pdu[3]
        if code not in (1, 2, 3, 4):
            raise ModbusError(ILLEGAL_VALUE)
        if code == 4:
            if oid >= len(DEVICE_ID):
                raise ModbusError(ILLEGAL_ADDRESS)
            ids = [oid]
        else:
            last = 2 if code == 1 else len(DEVICE_ID) - 1
            if oid > last:
                oid = 0
            ids = list(range(oid, last + 1))
        out = bytearray([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)])
        for i in ids:
            out += bytes([i, len(DEVICE_ID[i])]) + DEVICE_ID[i]
        return bytes(out)

    # ------------------------------------------------- manufacturer specific
    MNEMONICS = ('S1', 'S2', 'S3', 'S4', 'S7', 'S8', 'CR', 'S5', 'S13', 'TR',
                 'E', 'EX', 'PS', 'RS', 'MU')

    @staticmethod
    def mnemonic(b4):
        try:
            s = bytes(reversed(b4)).decode('ascii')
        except UnicodeDecodeError:
            raise ModbusError(ILLEGAL_ADDRESS)
        s = s.rstrip(' ')
        if s not in Drive.MNEMONICS:
            raise ModbusError(ILLEGAL_ADDRESS)
        return s

    def fc41(self, pdu, now):
        if len(pdu) < 5:
            raise ModbusError(ILLEGAL_VALUE)
        m = self.mnemonic(pdu[1:5])
        if m == 'EX':
            # EX carries a label: accept the FC66 layout (count + label)
            if len(pdu) < 6 or len(pdu) != 6 + pdu[5]:
                raise ModbusError(ILLEGAL_VALUE)
            self.run_program(m, pdu[6:], now)
            return bytes([0x41, 0x00])
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE)
        if m in ('E', 'PS', 'RS'):
            self.run_program(m, b'', now)
            return bytes([0x41, 0x00])
        s = self._mfg_strings()[m].encode('ascii')
        return bytes([0x41, len(s)]) + s

    def fc42(self, pdu, now):
        if len(pdu) < 6:
            raise ModbusError(ILLEGAL_VALUE)
        n = pdu[5]
        if len(pdu) != 6 + n or n > 28:
            raise ModbusError(ILLEGAL_VALUE)
        m = self.mnemonic(pdu[1:5])
        data = pdu[6:]
        if m in ('E', 'EX', 'PS', 'RS'):
            self.run_program(m, data, now)
        else:
            self.set_mfg(m, data, now)
        return bytes([0x42, n]) + bytes(pdu[1:5])

    def run_program(self, m, data, now):
        if m == 'EX':
            try:
                label = data.decode('ascii')
            except UnicodeDecodeError:
                raise ModbusError(ILLEGAL_VALUE)
            if not 1 <= len(label) <= 4 or not label.isalnum():
                raise ModbusError(ILLEGAL_VALUE)
            if self.val['DE'] != 1:
                raise ModbusError(DEVICE_FAILURE)
            self.program = {'state': 'running', 'label': label.upper()}
            return
        if data:
            raise ModbusError(ILLEGAL_VALUE)
        st = self.program['state']
        if m == 'E':
            self.program = {'state': 'stopped', 'label': None}
        elif m == 'PS' and st == 'running':
            self.program['state'] = 'paused'
        elif m == 'RS' and st == 'paused':
            self.program['state'] = 'running'

    @staticmethod
    def _ints(data, count_min, count_max):
        try:
            s = data.decode('ascii')
        except UnicodeDecodeError:
            raise ModbusError(ILLEGAL_VALUE)
        if not s.startswith('='):
            raise ModbusError(ILLEGAL_VALUE)
        toks = s[1:].split(',')
        if not count_min <= len(toks) <= count_max:
            raise ModbusError(ILLEGAL_VALUE)
        out = []
        for t in toks:
            t = t.strip(' ')
            body = t[1:] if t[:1] in '+-' else t
            if not body or not body.isdigit() or len(body) > 10:
                raise ModbusError(ILLEGAL_VALUE)
            out.append(int(t))
        return out

    def set_mfg(self, m, data, now):
        if m in ('S1', 'S2', 'S3', 'S4'):
            a, b, c = self._ints(data, 3, 3)
            if a not in IO_INPUT_FUNCS | IO_OUTPUT_FUNCS or b not in (0, 1) or c not in (0, 1):
                raise ModbusError(ILLEGAL_VALUE)
            n = int(m[1])
            self.io[n] = [a, b, c]
            if a != 16:
                self.latch[n] = 0
        elif m in ('S7', 'S8'):
            a, b = self._ints(data, 2, 2)
            if a not in CLK_FUNCS or b not in (0, 1):
                raise ModbusError(ILLEGAL_VALUE)
            self.clk[int(m[1])] = [a, b]
        elif m == 'S5':
            a, b = self._ints(data, 2, 2)
            if a not in (9, 10) or b not in (0, 1):
                raise ModbusError(ILLEGAL_VALUE)
            self.s5 = [a, b]
        elif m == 'S13':
            a, b = self._ints(data, 2, 2)
            if a not in (60, 61) or b not in (0, 1):
                raise ModbusError(ILLEGAL_VALUE)
            self.s13 = [a, b]
        elif m == 'TR':
            vals = self._ints(data, 1, 3)
            if any(not INT32_MIN <= v <= INT32_MAX for v in vals):
                raise ModbusError(ILLEGAL_VALUE)
            if any(v < 0 for v in vals[1:]):
                raise ModbusError(ILLEGAL_VALUE)
            self.tr = (vals + self.tr[len(vals):])[:3]
        elif m == 'MU':
            a, b = self._ints(data, 2, 2)
            if a not in (0, 1, 2) or b not in (0, 1):
                raise ModbusError(ILLEGAL_VALUE)
            self.val['MU'] = a
            self.mu_b = b
            if b == 1:
                self.val['LL'] = 0
        elif m == 'CR':
            try:
                s = data.decode('ascii')
            except UnicodeDecodeError:
                raise ModbusError(ILLEGAL_VALUE)
            if not s.startswith('='):
                raise ModbusError(ILLEGAL_VALUE)
            t = s[1:].strip(' ')
            ip, _, fp = t.partition('.')
            if (not ip and not fp) or (ip and not ip.isdigit()) or (fp and not fp.isdigit()) \
                    or len(fp) > 3 or len(ip) > 5:
                raise ModbusError(ILLEGAL_VALUE)
            milli = int(ip or '0') * 1000 + int((fp + '000')[:3])
            if not 1 <= milli <= 99999999:
                raise ModbusError(ILLEGAL_VALUE)
            self.cr_milli = milli
        else:
            raise ModbusError(ILLEGAL_ADDRESS)

    # ---------------------------------------------------------------- dump
    def snapshot(self):
        now = time.monotonic()
        self.update(now)
        regs = {}
        for r in REGISTERS:
            regs['0x%04X' % r[0]] = {'mnemonic': r[2], 'words': r[1], 'access': r[3],
                                     'value': self.reg_value(r[2], now)}
        return {
            'device': 'MDrive 23 Hybrid Motion Control, Ethernet (MODBUS/TCP)',
            'holding_registers': regs,
            'coils': {'0x%04X' % (COIL_BASE + i): self.pin(i + 1) for i in range(4)},
            'discrete_inputs': {'0x%04X' % (INPUT_BASE + i): self.pin(i + 1) for i in range(4)},
            'output_latches': {'O%d' % n: self.latch[n] for n in (1, 2, 3, 4)},
            'manufacturer_specific': self._mfg_strings(),
            'program': dict(self.program),
            'nvm': dict(self.nvm),
            'diagnostic_counters': dict(self.counters),
        }


# ---------------------------------------------------------------------------
# TCP server
# ---------------------------------------------------------------------------
class Server:
    def __init__(self, drive, state_file):
        self.drive = drive
        self.state_file = state_file
        self.conns = set()

    def dump(self):
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
        except Exception as e:  # never die because of the dump
            print('state dump failed: %s' % e, file=sys.stderr, flush=True)

    def handle_frame(self, body):
        """body = unit id + PDU.  Returns response PDU or None."""
        d = self.drive
        pdu = body[1:]
        if not pdu:
            d.counters['framing_errors'] += 1
            return None
        d.counters['bus_messages'] += 1
        fc = pdu[0]
        now = time.monotonic()
        try:
            if 7 + len(pdu) > RX_BUFFER:
                # frame larger than the receive buffer: only the head was kept
                d.counters['oversize_frames'] += 1
                if fc not in (0x01, 0x02, 0x03, 0x05, 0x10, 0x2B, 0x41, 0x42):
                    raise ModbusError(ILLEGAL_FUNCTION)
                raise ModbusError(ILLEGAL_VALUE)
            return d.process(pdu, now)
        except ModbusError as e:
            d.counters['exception_responses'] += 1
            return bytes([(fc | 0x80) & 0xFF, e.code])
        except Exception as e:  # firmware safety net
            print('internal error: %r' % e, file=sys.stderr, flush=True)
            d.counters['exception_responses'] += 1
            return bytes([(fc | 0x80) & 0xFF, DEVICE_FAILURE])

    async def client(self, reader, writer):
        if len(self.conns) >= MAX_CONNECTIONS:
            self.drive.counters['connections_refused'] += 1
            writer.close()
            return
        self.conns.add(writer)
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid, pid, length, uid = struct.unpack('>HHHB', hdr)
                if length < 2 or length > 254:
                    # MBAP length impossible: framing lost, drop the connection
                    self.drive.counters['framing_errors'] += 1
                    break
                rest = await reader.readexactly(length - 1)
                if pid != 0:
                    self.drive.counters['non_modbus_frames_dropped'] += 1
                    continue
                async with self.drive.lock:
                    await asyncio.sleep(PROC_DELAY)
                    resp = self.handle_frame(bytes([uid]) + rest)
                if resp is None:
                    continue
                writer.write(struct.pack('>HHHB', tid, 0, len(resp) + 1, uid) + resp)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            pass
        finally:
            self.conns.discard(writer)
            try:
                writer.close()
            except Exception:
                pass

    async def ticker(self):
        while True:
            await asyncio.sleep(TICK * 2)
            try:
                self.drive.update(time.monotonic())
            except Exception as e:
                print('tick error: %r' % e, file=sys.stderr, flush=True)


async def main():
    ap = argparse.ArgumentParser(description='MDrive Hybrid MODBUS/TCP simulator')
    ap.add_argument('--listen', default='127.0.0.1:502')
    ap.add_argument('--state', default=None)
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(':')
    drive = Drive()
    srv = Server(drive, args.state)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, srv.dump)
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    server = await asyncio.start_server(srv.client, host, int(port), backlog=8)
    p = server.sockets[0].getsockname()[1]
    print('listening tcp %s:%d' % (host, p), flush=True)
    tick = asyncio.create_task(srv.ticker())
    await stop.wait()
    srv.dump()
    tick.cancel()
    server.close()
    for w in list(srv.conns):
        try:
            w.close()
        except Exception:
            pass


if __name__ == '__main__':
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
