#!/usr/bin/env python3
"""MDrive Plus2 / MDrive Hybrid Motion Control -- Modbus/TCP drive simulator.

Built on modbus-tk 1.1.5 (LGPL): TcpQuery (MBAP framing), Server/Databank/Slave
(dispatch, exception responses via ModbusError), ModbusBlock (register/coil/input
storage) and the library's standard FC01/02/03/05/16 handlers.  The vendor parts
(register map checks, FC43/14, FC65/FC66, motion) are added on top.
See DECISIONS.md for every place where the manual or the library was overridden.

Usage: python3 sim.py --listen 127.0.0.1:0 [--state FILE]
"""
import argparse
import json
import logging
import math
import os
import re
import select
import signal
import socket
import struct
import sys
import threading
import time

from modbus_tk import defines, LOGGER
from modbus_tk import modbus
from modbus_tk import modbus_tcp
from modbus_tk.exceptions import ModbusError

LOGGER.setLevel(logging.CRITICAL)
LOGGER.addHandler(logging.NullHandler())
LOGGER.propagate = False

ILLEGAL_FUNCTION = defines.ILLEGAL_FUNCTION
ILLEGAL_ADDRESS = defines.ILLEGAL_DATA_ADDRESS
ILLEGAL_VALUE = defines.ILLEGAL_DATA_VALUE
DEVICE_FAILURE = defines.SLAVE_DEVICE_FAILURE

I32_MIN, I32_MAX = -2 ** 31, 2 ** 31 - 1

# ----------------------------------------------------------------------------
# Register map (manual section 5).  (mcode, address, nregs, access, signed, lo, hi, default)
# access: rw read/write, ro read-only, wo write-only command (reads back 0)
# ----------------------------------------------------------------------------
MS_VALUES = (1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127)

REGS = [
    ('A', 0x0000, 2, 'rw', False, 91, 1525878997, 1000000),
    ('C1', 0x0005, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('C2', 0x0007, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('CE', 0x0009, 1, 'rw', False, 0, 1, 1),
    ('CM', 0x000B, 1, 'rw', False, 0, 1, 0),
    ('D1', 0x000F, 1, 'rw', False, 0, 255, 0),
    ('D2', 0x0010, 1, 'rw', False, 0, 255, 0),
    ('D3', 0x0011, 1, 'rw', False, 0, 255, 0),
    ('D4', 0x0012, 1, 'rw', False, 0, 255, 0),
    ('D5', 0x0013, 1, 'rw', False, 0, 255, 0),
    ('D', 0x0018, 2, 'rw', False, 91, 1525878997, 1000000),
    ('DB', 0x001A, 1, 'rw', False, 0, 65000, 10),
    ('DC', 0x001B, 1, 'wo', False, 0, 0xFFFF, 0),
    ('DE', 0x001C, 1, 'rw', False, 0, 1, 1),
    ('EE', 0x001E, 1, 'rw', False, 0, 1, 0),
    ('EF', 0x001F, 1, 'ro', False, 0, 1, 0),
    ('ER', 0x0021, 1, 'rw', False, 0, 0, 0),
    ('HC', 0x0029, 1, 'rw', False, 0, 100, 5),
    ('HM', 0x002B, 1, 'rw', False, 1, 4, 1),
    ('HT', 0x002C, 1, 'rw', False, 0, 65535, 500),
    ('I1', 0x002D, 1, 'ro', False, 0, 1, 0),
    ('I2', 0x002E, 1, 'ro', False, 0, 1, 0),
    ('I3', 0x002F, 1, 'ro', False, 0, 1, 0),
    ('I4', 0x0030, 1, 'ro', False, 0, 1, 0),
    ('I5', 0x0031, 1, 'ro', False, 0, 1023, 0),
    ('I6', 0x0032, 1, 'ro', False, 0, 1, 0),
    ('IC', 0x0037, 1, 'wo', False, 0, 0xFFFF, 0),
    ('IL', 0x003A, 1, 'ro', False, 0, 15, 0),
    ('IN', 0x003B, 1, 'ro', False, 0, 15, 0),
    ('JE', 0x003F, 1, 'rw', False, 0, 1, 0),
    ('LM', 0x0042, 1, 'rw', False, 1, 6, 1),
    ('MA', 0x0043, 2, 'wo', True, I32_MIN, I32_MAX, 0),
    ('MP', 0x0045, 1, 'ro', False, 0, 1, 0),
    ('MR', 0x0046, 2, 'wo', True, I32_MIN, I32_MAX, 0),
    ('MS', 0x0048, 1, 'rw', False, 1, 256, 256),
    ('MT', 0x0049, 1, 'rw', False, 0, 65000, 0),
    ('MV', 0x004A, 1, 'ro', False, 0, 1, 0),
    ('O1', 0x004B, 1, 'rw', False, 0, 1, 0),
    ('O2', 0x004C, 1, 'rw', False, 0, 1, 0),
    ('O3', 0x004D, 1, 'rw', False, 0, 1, 0),
    ('O4', 0x004E, 1, 'rw', False, 0, 1, 0),
    ('OL', 0x0055, 1, 'rw', False, 0, 15, 0),
    ('OT', 0x0056, 1, 'rw', False, 0, 15, 0),
    ('P', 0x0057, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('PC', 0x0059, 2, 'ro', True, I32_MIN, I32_MAX, 0),
    ('PM', 0x005C, 1, 'rw', False, 0, 1, 0),
    ('R1', 0x005F, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('R2', 0x0061, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('R3', 0x0063, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('R4', 0x0065, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('RC', 0x0067, 1, 'rw', False, 1, 100, 25),
    ('S', 0x0076, 1, 'wo', False, 0, 0xFFFF, 0),
    ('SF', 0x0077, 1, 'rw', False, 0, 65000, 15),
    ('SL', 0x0078, 2, 'wo', True, -5000000, 5000000, 0),
    ('SM', 0x007A, 1, 'rw', False, 0, 1, 0),
    ('ST', 0x007B, 1, 'ro', False, 0, 1, 0),
    ('TE', 0x007D, 1, 'rw', False, 0, 16, 0),
    ('V', 0x0085, 2, 'ro', True, I32_MIN, I32_MAX, 0),
    ('VC', 0x0088, 1, 'ro', False, 0, 1, 0),
    ('VI', 0x0089, 2, 'rw', False, 1, 4999999, 1000),
    ('VM', 0x008B, 2, 'rw', False, 2, 5000000, 768000),
    # 5.1 Hybrid specific
    ('AS', 0x008E, 1, 'rw', False, 0, 3, 2),
    ('AF', 0x008F, 1, 'ro', False, 0, 255, 0),
    ('CA', 0x0090, 1, 'rw', False, 0, 1, 1),
    ('CB', 0x0091, 1, 'rw', False, 0, 3, 1),
    ('CC', 0x0092, 1, 'rw', False, 1, 100, 100),
    ('CF', 0x0093, 1, 'wo', False, 0, 0xFFFF, 0),
    ('CT', 0x0094, 1, 'rw', False, 2, 65535, 200),
    ('LD', 0x0095, 2, 'rw', False, 0, 2147483647, 102400),
    ('LG', 0x0097, 2, 'rw', False, 0, 2147483647, 102400),
    ('LL', 0x0099, 2, 'ro', True, -2147483647, 2147483647, 0),
    ('LR', 0x009B, 1, 'ro', False, 0, 1, 0),
    ('LT', 0x009C, 2, 'rw', False, 2, 65535, 2000),
    ('MF', 0x009E, 2, 'rw', False, 306, 5000000, 768000),
    ('MU', 0x00A0, 1, 'rw', False, 0, 2, 0),
    ('SC', 0x00A1, 1, 'wo', False, 0, 0xFFFF, 0),
    ('SS', 0x00A2, 1, 'rw', False, 0, 255, 0),
    ('TD', 0x00A5, 1, 'rw', False, 0, 1, 1),
    ('TQ', 0x00A6, 1, 'rw', False, 1, 100, 25),
    ('TS', 0x00A7, 1, 'rw', False, 0, 255, 0),
    # 5.2 User variables
    ('V1', 0x00A8, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('V2', 0x00AA, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('V3', 0x00AC, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('V4', 0x00AE, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('V5', 0x00B0, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('V6', 0x00B2, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('V7', 0x00B4, 2, 'rw', True, I32_MIN, I32_MAX, 0),
    ('V8', 0x00B6, 2, 'rw', True, I32_MIN, I32_MAX, 0),
]


class Reg(object):
    __slots__ = ('name', 'addr', 'n', 'access', 'signed', 'lo', 'hi', 'default')

    def __init__(self, *a):
        (self.name, self.addr, self.n, self.access, self.signed, self.lo, self.hi, self.default) = a


REG_LIST = [Reg(*r) for r in REGS]
BY_NAME = {r.name: r for r in REG_LIST}
BY_ADDR = {}  # every register address -> Reg
for _r in REG_LIST:
    for _i in range(_r.n):
        BY_ADDR[_r.addr + _i] = _r
REG_SPACE = 0x00B8  # 0x0000..0x00B7

# DC / IC operate on these signed 32-bit variables, selected by their register address
COUNTABLE = {BY_NAME[n].addr: n for n in ('C1', 'C2', 'P', 'R1', 'R2', 'R3', 'R4',
                                          'V1', 'V2', 'V3', 'V4', 'V5', 'V6', 'V7', 'V8')}

INPUT_ADDR = 0x002D   # discrete inputs 1-4 (FC02)
COIL_ADDR = 0x004B    # coils / outputs 1-4 (FC01 / FC05)

IO_INPUT_FUNCS = (0, 1, 2, 3, 5, 7, 8, 11)
IO_OUTPUT_FUNCS = (16, 17, 18, 20, 21, 23, 24, 25)

# FC65 / FC66 mnemonics: 4 request bytes (mnemonic ASCII reversed, space padded)
def _mnem(name):
    return name[::-1].rjust(4).encode('ascii')


MFG_RW = ('S1', 'S2', 'S3', 'S4', 'S7', 'S8', 'CR', 'S5', 'S13', 'TR', 'MU')
MFG_PROGRAM = ('E', 'EX', 'PS', 'RS')
MNEMONICS = {_mnem(n): n for n in MFG_RW + MFG_PROGRAM}

DEVICE_ID = [
    b'SEM USA',            # 0 VendorName
    b'MDI1PRL23B7-EQ',     # 1 ProductCode (MDrive part number)
    b'4.0.0.0',            # 2 MajorMinorRevision
    b'www.imshome.com',    # 3 VendorUrl
    b'MDrive Ethernet',    # 4 ProductName
    b'0000269051',         # 5 (manual: serial number)
    b'ASI 4.0.0.2',        # 6 (manual: "ASI 4.x.x.x")
]


def to_i32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


def _int_field(s, lo, hi):
    if not re.fullmatch(r'[+-]?\d{1,11}', s):
        raise ModbusError(ILLEGAL_VALUE)
    v = int(s)
    if v < lo or v > hi:
        raise ModbusError(ILLEGAL_VALUE)
    return v


# ----------------------------------------------------------------------------
# The drive
# ----------------------------------------------------------------------------
class MDriveSlave(modbus.Slave):
    """modbus_tk Slave restricted to the MDrive function codes, with the MDrive map."""

    def __init__(self, slave_id=1):
        super(MDriveSlave, self).__init__(slave_id, unsigned=True)
        self.add_block('regs', defines.HOLDING_REGISTERS, 0, REG_SPACE)
        self.add_block('coils', defines.COILS, COIL_ADDR, 4)
        self.add_block('inputs', defines.DISCRETE_INPUTS, INPUT_ADDR, 4)
        self._regs = self._get_block('regs')
        self._coils = self._get_block('coils')
        self._inputs = self._get_block('inputs')
        # only the function codes of manual table 4.1 (library default map replaced)
        self._fn_code_map = {
            defines.READ_COILS: self._fc01,
            defines.READ_DISCRETE_INPUTS: self._fc02,
            defines.READ_HOLDING_REGISTERS: self._fc03,
            defines.WRITE_SINGLE_COIL: self._fc05,
            defines.WRITE_MULTIPLE_REGISTERS: self._fc16,
            defines.DEVICE_INFO: self._fc43,
            0x41: self._fc65,
            0x42: self._fc66,
        }
        for r in REG_LIST:
            self._put(r, r.default if r.access != 'wo' else 0)
        self.outputs = [0, 0, 0, 0]           # latches of general purpose outputs
        self.io_cfg = {'S1': [0, 0, 0], 'S2': [0, 0, 0], 'S3': [0, 0, 0], 'S4': [0, 0, 0]}
        self.clk_cfg = {'S7': [33, 0], 'S8': [33, 0]}
        self.cr = 1.0
        self.s5 = [9, 0]
        self.s13 = [60, 0]
        self.tr = [0, 0, 0]
        self.mu_b = 0
        self.program = {'state': 'idle', 'label': ''}
        # motion
        self.mode = None          # None / 'move' / 'slew'
        self.posf = 0.0           # unbounded position (steps)
        self.target = 0
        self.slew_v = 0
        self.vel = 0.0
        self.vc = 0
        self.calibrated_at = 0.0   # monotonic time calibration completes
        self.nvm = self.settings()
        self.counters = {'requests': 0, 'exception_responses': 0, 'dropped_frames': 0,
                         'connections_accepted': 0, 'connections_refused': 0}

    # ---- raw register helpers (storage = library ModbusBlock) ----
    def _get(self, r):
        if r.n == 1:
            return self._regs[r.addr]
        v = (self._regs[r.addr] << 16) | self._regs[r.addr + 1]
        return to_i32(v) if r.signed else v

    def _put(self, r, v):
        if r.n == 1:
            self._regs[r.addr] = v & 0xFFFF
        else:
            v &= 0xFFFFFFFF
            self._regs[r.addr] = v >> 16
            self._regs[r.addr + 1] = v & 0xFFFF

    def get(self, name):
        return self._get(BY_NAME[name])

    def put(self, name, v):
        self._put(BY_NAME[name], v)

    def settings(self):
        """non volatile settings (what S saves)"""
        d = {r.name: self._get(r) for r in REG_LIST if r.access == 'rw'
             and r.name not in ('C1', 'C2', 'P', 'ER', 'O1', 'O2', 'O3', 'O4', 'OL', 'OT')}
        d.update(self.mfg_strings())
        return d

    # ---- I/O points ----
    def point_state(self, i):
        a = self.io_cfg['S%d' % (i + 1)][0]
        if a < 16:
            return 0          # simulated inputs are not wired: logic state 0
        if a == 16:
            return self.outputs[i]
        if a == 17:
            return 1 if self.mode else 0
        if a == 18:
            return self.get('EF')
        if a == 20:
            return self.vc
        if a == 21:
            return self.get('LR')
        if a == 23:
            return 1 if self.mode == 'move' else 0
        if a == 24:
            return 1 if self.get('AS') else 0
        return 0

    def coil_state(self, i):
        return self.point_state(i) if self.io_cfg['S%d' % (i + 1)][0] >= 16 else 0

    def is_gp_output(self, i):
        return self.io_cfg['S%d' % (i + 1)][0] == 16

    def calibrating(self):
        return time.monotonic() < self.calibrated_at

    def start_calibration(self):
        self.calibrated_at = time.monotonic() + self.get('CT') / 1000.0

    def refresh(self):
        """bring derived / live values into the library blocks"""
        bits = 0
        for i in range(4):
            s = self.point_state(i)
            self._inputs[i] = s
            self.put('I%d' % (i + 1), s)
            bits |= s << i
            c = self.coil_state(i)
            self._coils[i] = c
            self.put('O%d' % (i + 1), c)
        self.put('IL', bits)
        self.put('IN', bits)
        ob = sum(self.coil_state(i) << i for i in range(4))
        self.put('OL', ob)
        self.put('OT', ob)
        self.put('MV', 1 if self.mode else 0)
        self.put('MP', 1 if self.mode == 'move' else 0)
        self.put('VC', self.vc)
        self.put('V', 0 if self.get('AS') == 3 else int(self.vel))
        af = 0
        if self.get('AS'):
            af |= 16
            if self.get('LL') == 0:
                af |= 64
        if not self.calibrating():
            af |= 128
        af |= 8 if self.get('LR') else 0
        self.put('AF', af)

    # ---- PDU helpers ----
    @staticmethod
    def _need_len(pdu, n):
        if len(pdu) != n:
            raise ModbusError(ILLEGAL_VALUE)

    # FC01 / FC02: library handlers (quantity 0 or >2000 -> 03, outside block -> 02)
    def _fc01(self, pdu):
        self._need_len(pdu, 5)
        self.refresh()
        return self._read_coils(pdu)

    def _fc02(self, pdu):
        self._need_len(pdu, 5)
        self.refresh()
        return self._read_discrete_inputs(pdu)

    def _check_span(self, start, qty):
        if start + qty > REG_SPACE:
            raise ModbusError(ILLEGAL_ADDRESS)
        for a in range(start, start + qty):
            if a not in BY_ADDR:
                raise ModbusError(ILLEGAL_ADDRESS)

    def _fc03(self, pdu):
        self._need_len(pdu, 5)
        start, qty = struct.unpack('>HH', pdu[1:5])
        if qty < 1 or qty > 4:
            raise ModbusError(ILLEGAL_VALUE)
        self._check_span(start, qty)
        self.refresh()
        resp = self._read_registers(defines.HOLDING_REGISTERS, pdu)
        er = BY_NAME['ER'].addr
        if start <= er < start + qty:      # ER: "must be read or set to 0 to clear"
            self.put('ER', 0)
            self.put('EF', 0)
        return resp

    def _fc05(self, pdu):
        self._need_len(pdu, 5)
        addr, value = struct.unpack('>HH', pdu[1:5])
        if value not in (0x0000, 0xFF00):
            raise ModbusError(ILLEGAL_VALUE)
        if not COIL_ADDR <= addr < COIL_ADDR + 4:
            raise ModbusError(ILLEGAL_ADDRESS)
        i = addr - COIL_ADDR
        if not self.is_gp_output(i):
            raise ModbusError(DEVICE_FAILURE)
        resp = self._write_single_coil(pdu)
        self.outputs[i] = 1 if value else 0
        self.refresh()
        return resp

    def _fc16(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(ILLEGAL_VALUE)
        start, qty, bc = struct.unpack('>HHB', pdu[1:6])
        if len(pdu) != 6 + bc or qty < 1 or qty > 4 or bc != 2 * qty:
            raise ModbusError(ILLEGAL_VALUE)
        self._check_span(start, qty)
        words = struct.unpack('>%dH' % qty, pdu[6:])
        # collect whole parameters covered by the request
        writes = []
        a = start
        while a < start + qty:
            r = BY_ADDR[a]
            if r.addr != a or r.addr + r.n > start + qty:
                raise ModbusError(ILLEGAL_ADDRESS)   # partial multi-register parameter
            if r.access == 'ro':
                raise ModbusError(ILLEGAL_ADDRESS)
            off = a - start
            if r.n == 1:
                v = words[off]
            else:
                v = (words[off] << 16) | words[off + 1]
                if r.signed:
                    v = to_i32(v)
            writes.append((r, v))
            a += r.n
        new = {r.name: v for r, v in writes}
        self._validate(new)
        resp = self._write_multiple_registers(pdu)   # library stores the words
        self._apply(new)
        self.refresh()
        return resp

    def _validate(self, new):
        cur = lambda n: new[n] if n in new else self.get(n)
        for name, v in new.items():
            r = BY_NAME[name]
            if v < r.lo or v > r.hi:
                raise ModbusError(ILLEGAL_VALUE)
            if name == 'MS' and v not in MS_VALUES:
                raise ModbusError(ILLEGAL_VALUE)
            if name == 'HT' and v == 1:
                raise ModbusError(ILLEGAL_VALUE)
            if name == 'TE' and v not in (0, 16):
                raise ModbusError(ILLEGAL_VALUE)
            if name in ('DC', 'IC') and v not in COUNTABLE:
                raise ModbusError(ILLEGAL_VALUE)
        if cur('VI') >= cur('VM'):
            raise ModbusError(ILLEGAL_VALUE)
        if cur('HT') + cur('MT') > 65535:
            raise ModbusError(ILLEGAL_VALUE)
        # state dependent refusals
        for name, v in new.items():
            if name in ('P', 'MS') and self.mode:
                raise ModbusError(DEVICE_FAILURE)
            if name in ('DC', 'IC') and COUNTABLE[v] == 'P' and self.mode:
                raise ModbusError(DEVICE_FAILURE)
            if name[0] == 'O' and len(name) == 2 and name[1] in '1234':
                if not self.is_gp_output(int(name[1]) - 1):
                    raise ModbusError(DEVICE_FAILURE)
            if name in ('OL', 'OT'):
                for i in range(4):
                    if (v >> i) & 1 and not self.is_gp_output(i):
                        raise ModbusError(DEVICE_FAILURE)

    def _apply(self, new):
        old_as, old_de = self.get('AS'), self.get('DE')
        for name, v in new.items():
            r = BY_NAME[name]
            if r.access == 'wo':
                self._put(r, 0)
            if name in ('O1', 'O2', 'O3', 'O4'):
                self.outputs[int(name[1]) - 1] = v
            elif name in ('OL', 'OT'):
                for i in range(4):
                    if self.is_gp_output(i):
                        self.outputs[i] = (v >> i) & 1
            elif name == 'ER':
                self.put('EF', 0)
            elif name == 'P':
                self.posf = float(v)
            elif name in ('DC', 'IC'):
                tgt = COUNTABLE[v]
                nv = to_i32(self.get(tgt) + (1 if name == 'IC' else -1))
                self.put(tgt, nv)
                if tgt == 'P':
                    self.posf = float(nv)
            elif name == 'MA':
                self._start_move(v)
            elif name == 'MR':
                self._start_move(self.posf + v)
            elif name == 'SL':
                self.slew_v = v
                if v == 0 and self.mode != 'slew':
                    pass
                else:
                    self.mode = 'slew'
            elif name == 'S':
                self.nvm = self.settings()
            elif name == 'CF':
                self.put('LR', 0)
                self.start_calibration()
            elif name == 'SC':
                self.start_calibration()
            elif name == 'MS':
                if self.get('AS'):
                    self.start_calibration()
            elif name == 'MU':
                pass
        if 'AS' in new and old_as == 0 and new['AS'] != 0:
            self.start_calibration()
        if 'DE' in new and old_de == 0 and new['DE'] == 1 and self.get('AS'):
            self.start_calibration()

    def _start_move(self, target):
        self.target = int(round(target))
        if self.target == int(round(self.posf)) and not self.mode:
            return
        self.mode = 'move'

    # ---- FC43 / 14 ----
    def _fc43(self, pdu):
        if len(pdu) < 2:
            raise ModbusError(ILLEGAL_VALUE)
        if pdu[1] != 0x0E:
            raise ModbusError(ILLEGAL_FUNCTION)
        self._need_len(pdu, 4)
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
                oid = 0          # spec: unknown object id -> restart at 0
            ids = list(range(oid, last + 1))
        body = b''
        for i in ids:
            body += struct.pack('>BB', i, len(DEVICE_ID[i])) + DEVICE_ID[i]
        return struct.pack('>BBBBBB', 0x0E, code, 0x82, 0x00, 0x00, len(ids)) + body

    # ---- FC65 / FC66 ----
    def mfg_strings(self):
        j = lambda l: ', '.join(str(x) for x in l)
        d = {k: j(v) for k, v in self.io_cfg.items()}
        d.update({k: j(v) for k, v in self.clk_cfg.items()})
        d['CR'] = '%.3f' % self.cr
        d['S5'] = j(self.s5)
        d['S13'] = j(self.s13)
        d['TR'] = j(self.tr)
        d['MU'] = j([self.get('MU'), self.mu_b])
        return d

    def _mnemonic(self, pdu):
        name = MNEMONICS.get(bytes(pdu[1:5]))
        if name is None:
            raise ModbusError(ILLEGAL_ADDRESS)
        return name

    def _fc65(self, pdu):
        if len(pdu) < 5:
            raise ModbusError(ILLEGAL_VALUE)
        name = self._mnemonic(pdu)
        extra = bytes(pdu[5:])
        if name == 'EX':
            if not 1 <= len(extra) <= 4:
                raise ModbusError(ILLEGAL_VALUE)
            self._execute(extra)
            return struct.pack('>B', 0)
        if extra:
            raise ModbusError(ILLEGAL_VALUE)
        if name in MFG_PROGRAM:
            self._program(name)
            return struct.pack('>B', 0)
        s = self.mfg_strings()[name].encode('ascii')
        return struct.pack('>B', len(s)) + s

    def _fc66(self, pdu):
        if len(pdu) < 6:
            raise ModbusError(ILLEGAL_VALUE)
        bc = pdu[5]
        if len(pdu) != 6 + bc or bc < 1 or bc > 28:
            raise ModbusError(ILLEGAL_VALUE)
        name = self._mnemonic(pdu)
        data = bytes(pdu[6:])
        if name in ('E', 'PS', 'RS'):
            raise ModbusError(ILLEGAL_ADDRESS)   # read-only (FC65) commands
        if name == 'EX':
            self._execute(data[1:] if data[:1] == b'=' else data)
        else:
            self._set_mfg(name, data)
        return struct.pack('>B', 4) + bytes(pdu[1:5])

    def _parse_params(self, data, nmin, nmax, maxlen):
        if len(data) > maxlen:
            raise ModbusError(ILLEGAL_VALUE)
        try:
            s = data.decode('ascii')
        except UnicodeDecodeError:
            raise ModbusError(ILLEGAL_VALUE)
        if not s.startswith('='):
            raise ModbusError(ILLEGAL_VALUE)
        parts = [p.strip() for p in s[1:].split(',')]
        if not nmin <= len(parts) <= nmax:
            raise ModbusError(ILLEGAL_VALUE)
        return parts

    def _set_mfg(self, name, data):
        if name in ('S1', 'S2', 'S3', 'S4'):
            p = self._parse_params(data, 3, 3, 7)
            a = _int_field(p[0], 0, 25)
            if a not in IO_INPUT_FUNCS + IO_OUTPUT_FUNCS:
                raise ModbusError(ILLEGAL_VALUE)
            b, c = _int_field(p[1], 0, 1), _int_field(p[2], 0, 1)
            i = int(name[1]) - 1
            self.io_cfg[name] = [a, b, c]
            if a != 16:
                self.outputs[i] = 0
        elif name in ('S7', 'S8'):
            p = self._parse_params(data, 2, 2, 5)
            a = _int_field(p[0], 33, 51)
            if a not in (33, 34, 35, 49, 50, 51):
                raise ModbusError(ILLEGAL_VALUE)
            self.clk_cfg[name] = [a, _int_field(p[1], 0, 1)]
        elif name == 'CR':
            p = self._parse_params(data, 1, 1, 6)
            if not re.fullmatch(r'\d+(\.\d{1,3})?', p[0]):
                raise ModbusError(ILLEGAL_VALUE)
            v = float(p[0])
            if v <= 0:
                raise ModbusError(ILLEGAL_VALUE)
            self.cr = v
        elif name == 'S5':
            p = self._parse_params(data, 2, 2, 5)
            a = _int_field(p[0], 9, 10)
            self.s5 = [a, _int_field(p[1], 0, 1)]
        elif name == 'S13':
            p = self._parse_params(data, 2, 2, 5)
            self.s13 = [_int_field(p[0], 60, 61), _int_field(p[1], 0, 1)]
        elif name == 'TR':
            p = self._parse_params(data, 1, 3, 11)
            vals = [_int_field(p[0], I32_MIN, I32_MAX)]
            vals += [_int_field(x, 0, 255) for x in p[1:]]
            self.tr = vals + self.tr[len(vals):]
        elif name == 'MU':
            p = self._parse_params(data, 2, 2, 4)
            a, b = _int_field(p[0], 0, 2), _int_field(p[1], 0, 1)
            self.put('MU', a)
            self.mu_b = b
        self.refresh()

    def _execute(self, label):
        try:
            s = label.decode('ascii')
        except UnicodeDecodeError:
            raise ModbusError(ILLEGAL_VALUE)
        if not re.fullmatch(r'[A-Za-z][A-Za-z0-9]?|[0-9]{1,4}', s):
            raise ModbusError(ILLEGAL_VALUE)
        self.program = {'state': 'running', 'label': s}

    def _program(self, name):
        st = self.program['state']
        if name == 'E':
            self.program = {'state': 'idle', 'label': ''}
        elif name == 'PS':
            if st != 'running':
                raise ModbusError(DEVICE_FAILURE)
            self.program['state'] = 'paused'
        elif name == 'RS':
            if st != 'paused':
                raise ModbusError(DEVICE_FAILURE)
            self.program['state'] = 'running'

    # ---- motion (called from the motion thread under the data lock) ----
    def tick(self, dt):
        if not self.mode:
            self.vel, self.vc = 0.0, 0
            return
        acc, dec = float(self.get('A')), float(self.get('D'))
        vi, vm = float(self.get('VI')), float(self.get('VM'))
        old_int = int(round(self.posf))
        v = self.vel
        s = abs(v)
        if self.mode == 'move':
            rem = self.target - self.posf
            d = 1.0 if rem > 0 else -1.0
            if rem == 0:
                self._stop()
            elif v * d < 0:                       # moving the wrong way: brake first
                s = s - dec * dt
                if s <= vi:
                    s = vi
                    v = d * s
                else:
                    v = math.copysign(s, v)
            else:
                s = max(s, vi)
                brake = (s * s - vi * vi) / (2.0 * dec)
                if abs(rem) <= brake + s * dt:
                    s = max(vi, s - dec * dt)
                elif s < vm:
                    s = min(vm, s + acc * dt)
                elif s > vm:
                    s = max(vm, s - dec * dt)
                v = d * s
            if self.mode == 'move':
                step = v * dt
                if abs(step) >= abs(self.target - self.posf) and v * d > 0:
                    self.posf = float(self.target)
                    self._stop()
                else:
                    self.posf += step
        else:   # slew
            tv = float(self.slew_v)
            if tv == 0 or (v != 0 and v * tv < 0):
                s = s - dec * dt
                if s <= vi:
                    if tv == 0:
                        self._stop()
                        s = 0.0
                    else:
                        s = min(vi, abs(tv))
                        v = math.copysign(s, tv)
                if self.mode:
                    v = math.copysign(s, v if v != 0 else tv)
            else:
                ts = abs(tv)
                if s == 0:
                    s = min(vi, ts)
                if s < ts:
                    s = min(ts, s + acc * dt)
                elif s > ts:
                    s = max(ts, s - dec * dt)
                v = math.copysign(s, tv)
            if self.mode:
                self.posf += v * dt
        self.vc = 1 if self.mode and abs(abs(v) - abs(self.vel)) > 1e-9 else 0
        self.vel = v if self.mode else 0.0
        new_int = int(round(self.posf))
        delta = new_int - old_int
        if delta:
            self.put('P', to_i32(new_int))
            self.put('C1', to_i32(self.get('C1') + delta))
            if self.get('EE'):
                self.put('C2', to_i32(self.get('C2') + delta))
        # keep the float position inside the int32 window (the P counter wraps)
        if self.posf > I32_MAX or self.posf < I32_MIN:
            w = to_i32(int(round(self.posf)))
            shift = w - int(round(self.posf))
            self.posf += shift
            self.target += shift

    def _stop(self):
        self.mode = None
        self.vel = 0.0
        self.vc = 0
        self.slew_v = 0

    # ---- state dump ----
    def dump(self):
        self.refresh()
        regs = {}
        params = {}
        for r in REG_LIST:
            val = self._get(r)
            params[r.name] = {'address': '0x%04X' % r.addr, 'registers': r.n,
                              'access': r.access, 'value': val}
            for i in range(r.n):
                regs['0x%04X' % (r.addr + i)] = self._regs[r.addr + i]
        return {
            'device': 'MDrive Plus2 / Hybrid Motion Control (Modbus/TCP)',
            'holding_registers': regs,
            'parameters': params,
            'coils': {'0x%04X' % (COIL_ADDR + i): self._coils[i] for i in range(4)},
            'discrete_inputs': {'0x%04X' % (INPUT_ADDR + i): self._inputs[i] for i in range(4)},
            'output_latches': list(self.outputs),
            'manufacturer_functions': self.mfg_strings(),
            'program': dict(self.program),
            'motion': {'moving': 1 if self.mode else 0, 'mode': self.mode or 'idle'},
            'nvm': self.nvm,
            'device_identification': {str(i): v.decode() for i, v in enumerate(DEVICE_ID)},
            'diagnostic_counters': dict(self.counters),
        }


class MDriveDatabank(modbus.Databank):
    """One drive answering every unit id; always answers with a complete MBAP frame."""

    def __init__(self, slave):
        super(MDriveDatabank, self).__init__(error_on_missing_slave=False)
        self.slave = slave

    def handle_request(self, query, request):
        try:
            unit_id, pdu = query.parse_request(request)
        except Exception:
            self.slave.counters['dropped_frames'] += 1
            return b''
        if query._request_mbap.protocol_id != 0 or len(pdu) == 0:
            self.slave.counters['dropped_frames'] += 1
            return b''
        fc = pdu[0]
        self.slave.counters['requests'] += 1
        if fc & 0x80:
            resp = struct.pack('>BB', fc, ILLEGAL_FUNCTION)
        else:
            try:
                resp = self.slave.handle_request(pdu)     # library dispatch + ModbusError
            except Exception:
                resp = struct.pack('>BB', fc | 0x80, DEVICE_FAILURE)
        if resp and resp[0] & 0x80:
            self.slave.counters['exception_responses'] += 1
        return query.build_response(resp)


class MDriveTcpServer(modbus_tcp.TcpServer):
    """modbus_tk TcpServer; one reader thread per connection (see DECISIONS.md)."""

    MAX_CONN = 8
    FRAME_TIMEOUT = 2.0

    def __init__(self, address, port, slave):
        super(MDriveTcpServer, self).__init__(port=port, address=address,
                                              databank=MDriveDatabank(slave))
        self.slave = slave
        self._clients = set()
        self._clients_lock = threading.Lock()

    def bind(self):
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind(self._sa)
        self._sock.listen(16)
        self._sock.setblocking(False)
        return self._sock.getsockname()[1]

    def _do_init(self):
        pass

    def _do_run(self):
        try:
            r = select.select([self._sock], [], [], 0.2)[0]
        except (OSError, ValueError):
            time.sleep(0.2)
            return
        if not r:
            return
        try:
            client, _addr = self._sock.accept()
        except OSError:
            return
        with self._clients_lock:
            if len(self._clients) >= self.MAX_CONN:
                self.slave.counters['connections_refused'] += 1
                client.close()
                return
            self._clients.add(client)
        self.slave.counters['connections_accepted'] += 1
        client.setblocking(True)
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        threading.Thread(target=self._serve_client, args=(client,), daemon=True).start()

    def _serve_client(self, sock):
        buf = b''
        partial_since = None
        try:
            sock.settimeout(0.25)
            while self._go.is_set():
                # process every complete frame in the buffer
                while len(buf) >= 6:
                    length = self._get_request_length(buf[:6])   # library MBAP parse
                    if length == 0 or length > 254:
                        return                                    # cannot resync: close
                    if len(buf) < 6 + length:
                        break
                    frame, buf = buf[:6 + length], buf[6 + length:]
                    partial_since = None
                    try:
                        response = self._handle(frame)           # library Server._handle
                    except Exception:
                        response = b''
                    if response:
                        sock.sendall(response)
                partial_since = (partial_since or time.monotonic()) if buf else None
                if partial_since and time.monotonic() - partial_since > self.FRAME_TIMEOUT:
                    self.slave.counters['dropped_frames'] += 1
                    return                                        # incomplete frame: close
                try:
                    data = sock.recv(4096)
                except socket.timeout:
                    continue
                if not data:
                    return
                buf += data
        except Exception:
            pass
        finally:
            with self._clients_lock:
                self._clients.discard(sock)
            try:
                sock.close()
            except OSError:
                pass

    def _do_exit(self):
        with self._clients_lock:
            for c in list(self._clients):
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                try:
                    c.close()
                except OSError:
                    pass
            self._clients.clear()
        try:
            self._sock.close()
        except OSError:
            pass


def motion_loop(slave, stop):
    last = time.monotonic()
    while not stop.wait(0.01):
        now = time.monotonic()
        dt = min(now - last, 0.1)
        last = now
        with slave._data_lock:
            try:
                slave.tick(dt)
            except Exception:
                slave._stop()


def write_state(slave, path):
    if not path:
        return
    with slave._data_lock:
        data = slave.dump()
    tmp = path + '.tmp'
    with open(tmp, 'w') as f:
        json.dump(data, f, indent=1, sort_keys=True)
    os.replace(tmp, path)


def main():
    ap = argparse.ArgumentParser(description='MDrive Plus2/Hybrid Modbus/TCP simulator')
    ap.add_argument('--listen', required=True, help='HOST:PORT (use 127.0.0.1:0)')
    ap.add_argument('--state', help='JSON state dump file (SIGUSR1 and exit)')
    args = ap.parse_args()
    host, _, port = args.listen.rpartition(':')
    host = host or '127.0.0.1'

    slave = MDriveSlave()
    stop = threading.Event()
    dump_req = threading.Event()

    def on_term(signum, frame):
        stop.set()

    def on_usr1(signum, frame):
        dump_req.set()

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    signal.signal(signal.SIGUSR1, on_usr1)

    server = MDriveTcpServer(host, int(port), slave)
    real_port = server.bind()
    server.start()
    mt = threading.Thread(target=motion_loop, args=(slave, stop), daemon=True)
    mt.start()
    sys.stdout.write('listening tcp %s:%d\n' % (host, real_port))
    sys.stdout.flush()
    try:
        while not stop.is_set():
            stop.wait(0.1)
            if dump_req.is_set():
                dump_req.clear()
                try:
                    write_state(slave, args.state)
                except Exception as e:
                    sys.stderr.write('state dump failed: %s\n' % e)
    finally:
        stop.set()
        server.stop()
        try:
            write_state(slave, args.state)
        except Exception as e:
            sys.stderr.write('state dump failed: %s\n' % e)
    return 0


if __name__ == '__main__':
    sys.exit(main())
