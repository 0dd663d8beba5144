#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier - Modbus RTU slave simulator (clean-room, team j).

Usage:
  python3 sim.py --listen 127.0.0.1:0 [--state FILE] [--baud B] [--parity none|even|odd]
  python3 sim.py --serial /dev/pts/N [--baud B] [--parity none|even|odd] [--state FILE]
Standard library only.  See DECISIONS.md.
"""
import argparse
import asyncio
import json
import os
import random
import select
import signal
import struct
import sys
import termios
import time
import tty

SLAVE_ADDR = 1          # ID switch 0, "Address selector switch + 1", single axis
MAX_QTY = 48

# ---------------------------------------------------------------- CRC
_CRC_TAB = []
for _i in range(256):
    _c = _i
    for _ in range(8):
        _c = (_c >> 1) ^ 0xA001 if _c & 1 else _c >> 1
    _CRC_TAB.append(_c)


def crc16(data):
    c = 0xFFFF
    for b in data:
        c = (c >> 8) ^ _CRC_TAB[(c ^ b) & 0xFF]
    return c


def crc_ok(frame):
    return len(frame) >= 4 and crc16(frame[:-2]) == (frame[-2] | (frame[-1] << 8))


def add_crc(body):
    c = crc16(body)
    return bytes(body) + bytes((c & 0xFF, c >> 8))


# ---------------------------------------------------------------- device
# DS402 states
SOD, RTSO, SO, OE, QSA, FAULT = 'switch_on_disabled', 'ready_to_switch_on', 'switched_on', \
    'operation_enabled', 'quick_stop_active', 'fault'
STATUS_BITS = {SOD: 0x0050, RTSO: 0x0031, SO: 0x0033, OE: 0x0037, QSA: 0x0017, FAULT: 0x0038}

RAMP = 2000.0          # 0.1 Hz per s  (200 Hz/s)
QS_RAMP = 10000.0      # quick stop ramp 1000 Hz/s
SPEED_MAX = 10000      # 1000.0 Hz (Max Speed 0x3FFF = Speed Scaling)
ERR_WATCHDOG = 0x8130

# objects: index -> (name, type, access)   type: 'u16','i16','u32','i32'
OBJECTS = {
    2: ('Hardware ID', 'u32', 'ro'),
    5: ('Hardware Version', 'u32', 'ro'),
    16: ('Software ID', 'u32', 'ro'),
    17: ('Software Version', 'u32', 'ro'),
    33: ('DC Voltage', 'i16', 'ro'),
    41: ('Temperature Power Stage', 'i16', 'ro'),
    63: ('Temperature Motor', 'i16', 'ro'),
    67: ('Status Word', 'u16', 'ro'),
    68: ('Control Word', 'u16', 'rw'),
    70: ('Error Code', 'u16', 'ro'),
    120: ('Max Speed', 'i16', 'ro'),
    168: ('Actual Speed', 'i16', 'ro'),
    171: ('Max Iq Current', 'i16', 'ro'),
    177: ('Speed Scaling', 'i32', 'ro'),
    182: ('Current Scaling', 'i32', 'ro'),
    209: ('Target Torque Limit', 'i16', 'rw'),
    210: ('Target Velocity', 'i16', 'rw'),
    390: ('Actual Output Power', 'i16', 'ro'),
    431: ('Actual Apparent Current', 'i16', 'ro'),
    434: ('Output Voltage', 'i16', 'ro'),
}
IDENT_OBJECTS = (2, 5, 16, 17)
TYPE_SIZE = {'u16': 2, 'i16': 2, 'u32': 4, 'i32': 4}

# TxPDO register map: first register -> (object index, width in registers)
TXPDO = [(2000, 67, 1), (2001, 168, 1), (2002, 209, 1), (2003, 431, 1), (2004, 390, 1),
         (2005, 70, 1), (2006, 41, 1), (2007, 63, 1), (2008, 434, 1), (2009, 33, 1),
         (2010, 2, 2), (2012, 5, 2), (2014, 16, 2), (2016, 17, 2), (2018, 171, 1),
         (2019, 120, 1), (2020, 177, 2), (2022, 182, 2)]
TX_FIRST, TX_LAST = 2000, 2023
RX_FIRST, RX_LAST = 3000, 3003
RX_NAMES = {3000: 'Control Word', 3001: 'Target Speed', 3002: 'Torque Limit Iq', 3003: 'Watchdog'}


class ModbusExc(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


class SdoErr(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


class Drive:
    def __init__(self, baud, parity):
        self.baud = baud
        self.parity = parity
        # RxPDO / RW objects
        self.control_word = 0
        self.target_velocity = 0
        self.torque_limit = 0
        self.watchdog = 0
        # constants
        self.hw_id = 0x00002A31
        self.hw_version = 0x00010003
        self.sw_id = 0x00005D21
        self.sw_version = 0x00040012
        self.dc_voltage = 3250
        self.temp_ps = 170
        self.temp_motor = 235
        self.max_iq = 200
        self.max_speed = 0x3FFF
        self.speed_scaling = 60000000
        self.current_scaling = 20000
        # dynamic
        self.state = SOD
        self.error_code = 0
        self.speed = 0.0
        self.ramping = False
        self.t_last = time.monotonic()
        self.wd_deadline = None
        self.counters = {'bus_message_count': 0, 'bus_communication_error_count': 0,
                         'bus_exception_error_count': 0, 'slave_message_count': 0,
                         'slave_no_response_count': 0}

    # ---- counters
    def cnt(self, name):
        self.counters[name] = (self.counters[name] + 1) & 0xFFFF

    # ---- simulation
    def _integrate(self, dt):
        if dt <= 0:
            return
        if self.state == OE:
            tgt = max(-SPEED_MAX, min(SPEED_MAX, self.target_velocity))
            rate = RAMP
        elif self.state == QSA:
            tgt, rate = 0, QS_RAMP
        else:
            tgt, rate = 0, RAMP
        diff = tgt - self.speed
        step = rate * dt
        if abs(diff) <= step:
            self.speed = float(tgt)
            self.ramping = False
        else:
            self.speed += step if diff > 0 else -step
            self.ramping = True
        if self.state == QSA and self.speed == 0:
            self.state = SOD

    def update(self, now=None):
        if now is None:
            now = time.monotonic()
        if self.wd_deadline is not None and self.wd_deadline <= now:
            self._integrate(self.wd_deadline - self.t_last)
            self.t_last = max(self.t_last, self.wd_deadline)
            self.wd_deadline = None
            self.state = FAULT
            self.error_code = ERR_WATCHDOG
        self._integrate(now - self.t_last)
        self.t_last = max(self.t_last, now)

    def is_ramping(self):
        self.update()
        return self.ramping

    # ---- derived values
    def speed_i(self):
        return int(round(self.speed))

    def status_word(self):
        sw = STATUS_BITS[self.state]
        if self.state == OE and not self.ramping and \
                self.speed_i() == max(-SPEED_MAX, min(SPEED_MAX, self.target_velocity)):
            sw |= 0x0400
        if self.state == QSA and self.speed_i() == 0:
            sw |= 0x0400
        return sw

    def turning(self):
        return self.speed_i() != 0 and self.state in (OE, QSA)

    def app_current(self):
        if not self.turning():
            return 0
        return 20 + (40 if self.ramping else 0)

    def out_voltage(self):
        return int(abs(self.speed_i()) * 4 // 10) if self.turning() else 0

    def out_power(self):
        return int(abs(self.speed_i()) * 5 // 1000) if self.turning() else 0

    def obj_get(self, idx):
        self.update()
        v = {2: self.hw_id, 5: self.hw_version, 16: self.sw_id, 17: self.sw_version,
             33: self.dc_voltage, 41: self.temp_ps, 63: self.temp_motor,
             67: self.status_word(), 68: self.control_word, 70: self.error_code,
             120: self.max_speed, 168: self.speed_i(), 171: self.max_iq,
             177: self.speed_scaling, 182: self.current_scaling, 209: self.torque_limit,
             210: self.target_velocity, 390: self.out_power(), 431: self.app_current(),
             434: self.out_voltage()}[idx]
        return v

    # ---- DS402 command handling
    def write_control_word(self, cw):
        self.update()
        old = self.control_word
        self.control_word = cw
        st = self.state
        if st == FAULT:
            if (cw & 0x80) and not (old & 0x80):
                self.state = SOD
                self.error_code = 0
            return
        if cw & 0x80:
            return          # fault reset bit set outside fault: no command (DS402 priority)
        if not (cw & 0x02):                      # disable voltage
            if st in (RTSO, SO, OE, QSA):
                self.state = SOD
            return
        if not (cw & 0x04):                      # quick stop
            if st in (RTSO, SO):
                self.state = SOD
            elif st == OE:
                self.state = QSA
                if self.speed_i() == 0:
                    self.state = SOD
            return
        low = cw & 0x0F
        if (cw & 0x07) == 0x06:                  # shutdown (bit0 = 0)
            if st in (SOD, SO, OE):
                self.state = RTSO
        elif low == 0x07:                        # switch on / disable operation
            if st == RTSO or st == OE:
                self.state = SO
        elif low == 0x0F:                        # switch on + enable operation
            if st in (RTSO, SO, QSA):
                self.state = OE

    def command_changes_state(self, cw):
        """Read-only prediction for the timing model (does not change state)."""
        self.update()
        saved = (self.state, self.control_word, self.error_code)
        self.write_control_word(cw)
        changed = self.state != saved[0]
        self.state, self.control_word, self.error_code = saved
        return changed

    # ---- registers
    def read_reg(self, addr):
        if TX_FIRST <= addr <= TX_LAST:
            for first, idx, width in TXPDO:
                if first <= addr < first + width:
                    v = self.obj_get(idx) & (0xFFFFFFFF if width == 2 else 0xFFFF)
                    if width == 2:
                        return (v >> 16) & 0xFFFF if addr == first else v & 0xFFFF
                    return v
        self.update()
        return {3000: self.control_word, 3001: self.target_velocity & 0xFFFF,
                3002: self.torque_limit & 0xFFFF, 3003: self.watchdog}[addr]

    def write_reg(self, addr, value):
        if addr == 3000:
            self.write_control_word(value)
        elif addr == 3001:
            self.update()
            self.target_velocity = value - 0x10000 if value & 0x8000 else value
        elif addr == 3002:
            self.torque_limit = value - 0x10000 if value & 0x8000 else value
        elif addr == 3003:
            self.update()
            self.watchdog = value
            self.wd_deadline = time.monotonic() + value / 1000.0 if value else None

    @staticmethod
    def check_read_range(start, qty):
        end = start + qty - 1
        if not ((TX_FIRST <= start and end <= TX_LAST) or (RX_FIRST <= start and end <= RX_LAST)):
            raise ModbusExc(2)

    @staticmethod
    def check_write_range(start, qty):
        end = start + qty - 1
        if not (RX_FIRST <= start and end <= RX_LAST):
            raise ModbusExc(2)

    # ---- state dump
    def dump(self):
        self.update()
        inp = {str(a): self.read_reg(a) for a in range(TX_FIRST, TX_LAST + 1)}
        hold = {str(a): self.read_reg(a) for a in range(RX_FIRST, RX_LAST + 1)}
        objs = {}
        for idx, (name, typ, acc) in sorted(OBJECTS.items()):
            objs['%d:0' % idx] = {'index_hex': '0x%04X' % idx, 'subindex': 0, 'name': name,
                                 'type': typ, 'access': acc, 'value': self.obj_get(idx)}
        return {
            'device': 'SIEB & MEYER SD2x (single axis) - Modbus RTU',
            'settings': {'slave_address': SLAVE_ADDR, 'slave_address_mode': 'Address selector switch + 1',
                         'id_switch': 0, 'programmable_address': 1, 'baud': self.baud,
                         'parity': self.parity, 'stop_bits': 1, 'node_id': SLAVE_ADDR},
            'input_registers': inp,
            'holding_registers': hold,
            'register_names': {**{str(a): OBJECTS[i][0] for a, i, w in TXPDO}, **{str(a): n for a, n in RX_NAMES.items()}},
            'objects': objs,
            'drive': {'ds402_state': self.state, 'status_word': self.status_word(),
                      'error_code': self.error_code, 'actual_speed_0_1Hz': self.speed_i(),
                      'watchdog_ms': self.watchdog, 'watchdog_armed': self.wd_deadline is not None},
            'diagnostic_counters': dict(self.counters),
        }


# ---------------------------------------------------------------- protocol
def exc(addr, fc, code):
    return add_crc(bytes((addr, (fc | 0x80) & 0xFF, code)))


class Protocol:
    def __init__(self, drive):
        self.d = drive

    # -- classification for timing (pure)
    def service_time(self, frame, short43=False):
        fc = frame[1] if len(frame) > 1 else 0
        r = random.uniform
        if fc in (3, 4):
            t = r(0.0010, 0.0030)
        elif fc in (6, 16, 23):
            t = r(0.0015, 0.0035)
            cw = self._cw_in(frame)
            if cw is not None and self.d.command_changes_state(cw):
                t += r(0.008, 0.015)
        elif fc == 8:
            t = r(0.0005, 0.0015)
        elif fc == 0x2B:
            info = self._fc43_peek(frame, short43)
            if info is None:
                t = r(0.001, 0.003)
            elif info[0]:   # write
                t = r(0.020, 0.040)
            elif info[1] in IDENT_OBJECTS:
                t = r(0.025, 0.045)
            else:
                t = r(0.006, 0.012)
        else:
            t = r(0.0005, 0.0015)
        if self.d.is_ramping():
            t += r(0.002, 0.006)                # own behaviour B
        return t

    def _cw_in(self, f):
        try:
            if f[1] == 6 and len(f) == 8 and struct.unpack('>H', f[2:4])[0] == 3000:
                return struct.unpack('>H', f[4:6])[0]
            if f[1] == 16 and len(f) >= 11:
                start, qty = struct.unpack('>HH', f[2:6])
                if start <= 3000 < start + qty and len(f) >= 9 + 2 * qty:
                    o = 7 + 2 * (3000 - start)
                    return struct.unpack('>H', f[o:o + 2])[0]
            if f[1] == 23 and len(f) >= 15:
                start, qty = struct.unpack('>HH', f[6:10])
                if start <= 3000 < start + qty and len(f) >= 13 + 2 * qty:
                    o = 11 + 2 * (3000 - start)
                    return struct.unpack('>H', f[o:o + 2])[0]
        except (struct.error, IndexError):
            pass
        return None

    def _fc43_peek(self, f, short43):
        o = 4 if short43 else 5
        if len(f) >= o + 3 and f[2] == 0x0D:
            return (bool(f[3] & 0x80), struct.unpack('>H', f[o + 1:o + 3])[0])
        return None

    # -- main entry: returns response bytes or None (no answer)
    def handle(self, frame, short43=False):
        d = self.d
        addr, fc = frame[0], frame[1]
        d.cnt('bus_message_count')
        if addr != SLAVE_ADDR and addr != 0:
            return None
        d.cnt('slave_message_count')
        bcast = addr == 0
        if bcast:
            if fc in (6, 16):
                try:
                    self._dispatch(frame, short43)
                except (ModbusExc, SdoErr):
                    pass
            d.cnt('slave_no_response_count')
            return None
        try:
            pdu = self._dispatch(frame, short43)
        except ModbusExc as e:
            d.cnt('bus_exception_error_count')
            return exc(addr, fc, e.code)
        except SdoErr as e:
            d.cnt('bus_exception_error_count')
            return add_crc(bytes((addr, 0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + struct.pack('<I', e.code))
        except Exception:
            d.cnt('bus_exception_error_count')
            return exc(addr, fc, 4)
        return add_crc(bytes((addr,)) + pdu)

    def _dispatch(self, f, short43):
        fc = f[1]
        d = self.d
        n = len(f)
        if fc in (3, 4):
            if n != 8:
                raise ModbusExc(3)
            start, qty = struct.unpack('>HH', f[2:6])
            if qty < 1 or qty > MAX_QTY:
                raise ModbusExc(3)
            d.check_read_range(start, qty)
            vals = [d.read_reg(a) for a in range(start, start + qty)]
            return bytes((fc, 2 * qty)) + struct.pack('>%dH' % qty, *vals)
        if fc == 6:
            if n != 8:
                raise ModbusExc(3)
            a, v = struct.unpack('>HH', f[2:6])
            d.check_write_range(a, 1)
            d.write_reg(a, v)
            return f[1:6]
        if fc == 16:
            if n < 9:
                raise ModbusExc(3)
            start, qty = struct.unpack('>HH', f[2:6])
            bc = f[6]
            if bc != 2 * qty or n != 9 + bc:
                raise ModbusExc(3)
            if qty < 1 or qty > MAX_QTY:
                raise ModbusExc(3)
            d.check_write_range(start, qty)
            vals = struct.unpack('>%dH' % qty, f[7:7 + bc])
            for i, v in enumerate(vals):
                d.write_reg(start + i, v)
            return f[1:6]
        if fc == 23:
            if n < 13:
                raise ModbusExc(3)
            rs, rq, ws, wq = struct.unpack('>HHHH', f[2:10])
            bc = f[10]
            if bc != 2 * wq or n != 13 + bc:
                raise ModbusExc(3)
            if rq < 1 or rq > MAX_QTY or wq < 1 or wq > MAX_QTY:
                raise ModbusExc(3)
            d.check_write_range(ws, wq)
            d.check_read_range(rs, rq)
            vals = struct.unpack('>%dH' % wq, f[11:11 + bc])
            for i, v in enumerate(vals):
                d.write_reg(ws + i, v)
            rv = [d.read_reg(a) for a in range(rs, rs + rq)]
            return bytes((23, 2 * rq)) + struct.pack('>%dH' % rq, *rv)
        if fc == 8:
            if n != 8:
                raise ModbusExc(3)
            sub, data = struct.unpack('>HH', f[2:6])
            c = d.counters
            if sub == 0:
                return f[1:6]
            if sub not in (10, 11, 12, 13, 14, 15):
                raise ModbusExc(1)
            if data != 0:
                raise ModbusExc(3)
            if sub == 10:
                for k in c:
                    c[k] = 0
                val = 0
            else:
                val = c[{11: 'bus_message_count', 12: 'bus_communication_error_count',
                         13: 'bus_exception_error_count', 14: 'slave_message_count',
                         15: 'slave_no_response_count'}[sub]]
            return struct.pack('>BHH', 8, sub, val)
        if fc == 0x2B:
            return self._fc43(f, short43)
        raise ModbusExc(1)

    def _fc43(self, f, short43):
        n = len(f)
        if n < 5:
            raise ModbusExc(3)
        if f[2] != 0x0D:
            raise ModbusExc(1)
        hdr = 12 if short43 else 13            # bytes before data (incl. address)
        if n < hdr + 2:
            raise ModbusExc(3)
        ctrl = f[3]
        o = 4 if short43 else 5
        node = f[o]
        idx = struct.unpack('>H', f[o + 1:o + 3])[0]
        sub = f[o + 3]
        off, cnt = struct.unpack('>HH', f[o + 4:o + 8])
        data = f[hdr:n - 2]
        write = bool(ctrl & 0x80)
        if ctrl & 0x7F:
            raise ModbusExc(3)
        if cnt > 4:
            raise ModbusExc(3)
        if (write and len(data) != cnt) or (not write and len(data) != 0):
            raise ModbusExc(3)
        if node != SLAVE_ADDR:
            raise ModbusExc(3)
        if off != 0:
            raise SdoErr(0xFFFF0008)
        if idx not in OBJECTS:
            raise SdoErr(0xFFFF000B)
        if sub != 0:
            raise SdoErr(0xFFFF0014)
        name, typ, acc = OBJECTS[idx]
        size = TYPE_SIZE[typ]
        head = bytes((0x2B, 0x0D, ctrl)) + (b'' if short43 else b'\x00') + bytes((node,)) + \
            struct.pack('>HBH', idx, sub, off)
        if write:
            if acc == 'ro':
                raise SdoErr(0xFFFF000A)
            if cnt > size:
                raise SdoErr(0xFFFF0012)
            if cnt < size:
                raise SdoErr(0xFFFF0013)
            v = struct.unpack('<H', data)[0]
            if idx == 68:
                self.d.write_reg(3000, v)
            elif idx == 210:
                self.d.write_reg(3001, v)
            elif idx == 209:
                self.d.write_reg(3002, v)
            return head + struct.pack('>H', cnt) + bytes(data)
        if cnt and cnt > size:
            raise SdoErr(0xFFFF0012)
        if cnt and cnt < size:
            raise SdoErr(0xFFFF0013)
        v = self.d.obj_get(idx)
        raw = struct.pack('<I', v & 0xFFFFFFFF) if size == 4 else struct.pack('<H', v & 0xFFFF)
        return head + struct.pack('>H', size) + raw


# ---------------------------------------------------------------- framer
def candidate_lengths(buf):
    """Return list of (length, short43) candidates, or None if more bytes needed to know."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (3, 4, 6, 8):
        return [(8, False)]
    if fc == 16:
        if len(buf) < 7:
            return None
        return [(9 + buf[6], False)]
    if fc == 23:
        if len(buf) < 11:
            return None
        return [(13 + buf[10], False)]
    if fc == 0x2B:
        if len(buf) < 4:
            return None
        if buf[2] != 0x0D:
            return []
        write = buf[3] & 0x80
        c = []
        if len(buf) >= 12:
            cnt_s = (buf[10] << 8) | buf[11]
            if not write:
                c.append((14, True))
            elif cnt_s <= 250:
                c.append((14 + cnt_s, True))
        if len(buf) >= 13:
            cnt_l = (buf[11] << 8) | buf[12]
            if not write:
                c.insert(0, (15, False))
            elif cnt_l <= 250:
                c.insert(0, (15 + cnt_l, False))
        else:
            return None if not c else c + [(None, False)]
        return c
    return []


MAX_BUF = 1024


class Framer:
    def __init__(self, gap):
        self.buf = bytearray()
        self.gap = gap
        self.last_rx = 0.0

    def feed(self, data, t):
        self.buf += data
        self.last_rx = t

    def pending(self):
        return len(self.buf) > 0

    def poll(self, now):
        """Return list of events: ('frame', bytes, short43) or ('error',)."""
        out = []
        silent = (now - self.last_rx) >= self.gap
        if len(self.buf) > MAX_BUF:          # runaway garbage: flush like an RX overrun
            out.append(('error',))
            self.buf = bytearray()
        while self.buf:
            buf = self.buf
            cands = candidate_lengths(buf)
            if cands is None:
                if silent:
                    if len(buf) >= 4 and crc_ok(bytes(buf)):
                        out.append(('frame', bytes(buf), False))
                        self.buf = bytearray()
                        break
                    self._garbage(out)
                    continue
                break
            matched = False
            need_more = False
            for L, short in cands:
                if L is None:
                    need_more = True
                    continue
                if len(buf) >= L:
                    if crc_ok(bytes(buf[:L])):
                        out.append(('frame', bytes(buf[:L]), short))
                        del self.buf[:L]
                        matched = True
                        break
                else:
                    need_more = True
            if matched:
                continue
            if not cands:   # unknown function code: shortest prefix with valid CRC
                for k in range(4, len(buf) + 1):
                    if crc_ok(bytes(buf[:k])):
                        out.append(('frame', bytes(buf[:k]), False))
                        del self.buf[:k]
                        matched = True
                        break
                if matched:
                    continue
            if not silent:
                if need_more or not cands:
                    break
                break
            # silence: whole buffer as one frame?
            if len(buf) >= 4 and crc_ok(bytes(buf)):
                out.append(('frame', bytes(buf), False))
                self.buf = bytearray()
                break
            self._garbage(out)
        return out

    def _garbage(self, out):
        """CRC/framing error: resync at the next position that starts a valid frame."""
        buf = self.buf
        for s in range(1, len(buf) - 3):
            cands = candidate_lengths(buf[s:])
            if not cands:
                continue
            for L, short in cands:
                if L is not None and len(buf) - s >= L and crc_ok(bytes(buf[s:s + L])):
                    out.append(('error',))
                    del self.buf[:s]
                    return
        out.append(('error',))
        self.buf = bytearray()


# ---------------------------------------------------------------- timing helpers
TICK = 0.001
DEADLINE = 0.450


def char_time(baud, parity):
    return (11 if parity != 'none' else 10) / float(baud)


def t35(baud, parity):
    return 0.00175 if baud > 19200 else 3.5 * char_time(baud, parity)


class Timing:
    def __init__(self, baud, parity):
        self.ct = char_time(baud, parity)
        self.t35 = t35(baud, parity)
        self.epoch = time.monotonic()

    def ready_time(self, t_end, t_start_service, service, nbytes_resp, first_penalty=0.0):
        ready = max(t_end + self.t35, t_start_service + service + first_penalty)
        # own behaviour A: 1 ms control-loop tick
        k = (ready - self.epoch) / TICK
        ready = self.epoch + TICK * int(k + 0.999999)
        latest = t_end + DEADLINE - nbytes_resp * self.ct - 0.05
        ready = min(ready, max(latest, t_end + self.t35))
        return ready


def expected_resp_len(frame):
    fc = frame[1] if len(frame) > 1 else 0
    if fc in (3, 4) and len(frame) >= 6:
        return 5 + 2 * min(MAX_QTY, (frame[4] << 8) | frame[5])
    if fc == 23 and len(frame) >= 6:
        return 5 + 2 * min(MAX_QTY, (frame[4] << 8) | frame[5])
    if fc == 0x2B:
        return 22
    return 8


# ---------------------------------------------------------------- state file
def write_state(path, drive):
    if not path:
        return
    try:
        data = json.dumps(drive.dump(), indent=1, sort_keys=True)
        tmp = path + '.tmp'
        with open(tmp, 'w') as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except Exception as e:   # never crash on a dump
        print('state dump failed: %s' % e, file=sys.stderr, flush=True)


# ---------------------------------------------------------------- TCP transport
MAX_CONN = 4
IDLE_TIMEOUT = 120.0
TCP_GAP = 0.200
PACK_TIMER = 0.004
RX_CHUNK = 512
QUEUE_FRAMES = 8


class TcpServer:
    def __init__(self, drive, proto, timing):
        self.drive = drive
        self.proto = proto
        self.timing = timing
        self.conns = set()

    async def client(self, reader, writer):
        if len(self.conns) >= MAX_CONN:
            writer.close()
            return
        me = object()
        self.conns.add(me)
        q = asyncio.Queue(maxsize=QUEUE_FRAMES)
        framer = Framer(TCP_GAP)
        worker = asyncio.ensure_future(self.worker(q, writer))
        try:
            last_any = time.monotonic()
            while True:
                timeout = TCP_GAP + 0.002 if framer.pending() else \
                    max(0.01, IDLE_TIMEOUT - (time.monotonic() - last_any))
                try:
                    data = await asyncio.wait_for(reader.read(RX_CHUNK), timeout)
                except asyncio.TimeoutError:
                    data = None
                now = time.monotonic()
                if data == b'':
                    break
                if data:
                    last_any = now
                    framer.feed(data, now)
                elif not framer.pending() and now - last_any >= IDLE_TIMEOUT:
                    break
                for ev in framer.poll(time.monotonic()):
                    if ev[0] == 'error':
                        self.drive.cnt('bus_communication_error_count')
                    else:
                        while q.full() and not worker.done():
                            await asyncio.sleep(0.002)     # zero window: stop reading
                        if worker.done():
                            break
                        q.put_nowait((ev[1], ev[2], now))
                if worker.done():
                    break
        except (ConnectionError, OSError):
            pass
        finally:
            self.conns.discard(me)
            try:
                q.put_nowait(None)
            except asyncio.QueueFull:
                worker.cancel()
            try:
                await asyncio.wait_for(worker, 2.0)
            except (asyncio.TimeoutError, asyncio.CancelledError, Exception):
                worker.cancel()
            try:
                writer.close()
            except Exception:
                pass

    async def worker(self, q, writer):
        first = True
        line_free = 0.0
        tm = self.timing
        try:
            while True:
                item = await q.get()
                if item is None:
                    return
                frame, short43, t_end = item
                now = time.monotonic()
                svc = self.proto.service_time(frame, short43)
                pen = random.uniform(0.015, 0.025) if first else 0.0   # own behaviour C
                first = False
                ready = tm.ready_time(t_end, max(now, line_free), svc, expected_resp_len(frame), pen)
                dt = ready - time.monotonic()
                if dt > 0:
                    await asyncio.sleep(dt)
                resp = self.proto.handle(frame, short43)
                if resp is None:
                    continue
                await self.send_paced(writer, resp)
                line_free = time.monotonic()
        except (ConnectionError, OSError, asyncio.CancelledError):
            return

    async def send_paced(self, writer, resp):
        """Bytes go on the 'line' at baud pace; the device server packs them on a 5 ms timer."""
        ct = self.timing.ct
        t0 = time.monotonic()
        sent = 0
        n = len(resp)
        while sent < n:
            nxt = t0 + PACK_TIMER * (int((time.monotonic() - t0) / PACK_TIMER) + 1)
            await asyncio.sleep(max(0.0, nxt - time.monotonic()))
            done = min(n, int((time.monotonic() - t0) / ct))
            if done > sent:
                writer.write(resp[sent:done])
                await writer.drain()
                sent = done


async def run_tcp(host, port, drive, state_path, timing):
    proto = Protocol(drive)
    srv = TcpServer(drive, proto, timing)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    loop.add_signal_handler(signal.SIGUSR1, lambda: write_state(state_path, drive))
    server = await asyncio.start_server(srv.client, host, port, backlog=8)
    p = server.sockets[0].getsockname()[1]
    print('listening tcp %s:%d' % (host, p), flush=True)
    await stop.wait()
    server.close()
    write_state(state_path, drive)


# ---------------------------------------------------------------- serial transport
class SerialServer:
    def __init__(self, dev, drive, timing, baud, parity, state_path):
        self.dev = dev
        self.drive = drive
        self.proto = Protocol(drive)
        self.timing = timing
        self.stop = False
        self.dump_req = False
        self.state_path = state_path
        self.fd = os.open(dev, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            tty.setraw(self.fd)
            attrs = termios.tcgetattr(self.fd)
            speed = getattr(termios, 'B%d' % baud, None)
            if speed is not None:
                attrs[4] = attrs[5] = speed
            cflag = attrs[2] & ~(termios.PARENB | termios.PARODD | termios.CSTOPB | termios.CSIZE)
            cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
            if parity == 'even':
                cflag |= termios.PARENB
            elif parity == 'odd':
                cflag |= termios.PARENB | termios.PARODD
            attrs[2] = cflag
            termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
        except (termios.error, OSError):
            pass
        self.gap = max(timing.t35, 0.002)

    def _write_byte(self, b):
        while True:
            try:
                os.write(self.fd, b)
                return
            except BlockingIOError:
                select.select([], [self.fd], [], 0.01)
            except OSError:
                return

    def send_paced(self, resp):
        ct = self.timing.ct
        last = None
        for i in range(len(resp)):
            if last is not None:
                target = last + ct
                while True:
                    rem = target - time.perf_counter()
                    if rem <= 0:
                        break
                    if rem > 0.002:
                        time.sleep(rem - 0.0015)
            last = time.perf_counter()
            self._write_byte(resp[i:i + 1])

    def run(self):
        framer = Framer(self.gap)
        tm = self.timing
        pending = []
        line_free = 0.0
        while not self.stop:
            if self.dump_req:
                self.dump_req = False
                write_state(self.state_path, self.drive)
            try:
                r, _, _ = select.select([self.fd], [], [], 0.001)
            except (OSError, ValueError):
                r = []
            now = time.monotonic()
            if r:
                try:
                    data = os.read(self.fd, 4096)
                except BlockingIOError:
                    data = b''
                except OSError:
                    data = b''
                    time.sleep(0.01)   # peer side closed; keep waiting
                if data:
                    framer.feed(data, now)
            for ev in framer.poll(time.monotonic()):
                if ev[0] == 'error':
                    self.drive.cnt('bus_communication_error_count')
                else:
                    pending.append((ev[1], ev[2], framer.last_rx))
            while pending and not self.stop:
                frame, short43, t_end = pending.pop(0)
                svc = self.proto.service_time(frame, short43)
                ready = tm.ready_time(t_end, max(time.monotonic(), line_free), svc,
                                      expected_resp_len(frame))
                while True:
                    rem = ready - time.monotonic()
                    if rem <= 0:
                        break
                    time.sleep(min(rem, 0.005))
                resp = self.proto.handle(frame, short43)
                if resp is not None:
                    self.send_paced(resp)
                    line_free = time.monotonic()
        try:
            os.close(self.fd)
        except OSError:
            pass


def run_serial(dev, drive, timing, baud, parity, state_path):
    srv = SerialServer(dev, drive, timing, baud, parity, state_path)

    def on_stop(signum, frame):
        srv.stop = True

    def on_usr1(signum, frame):
        srv.dump_req = True

    signal.signal(signal.SIGTERM, on_stop)
    signal.signal(signal.SIGINT, on_stop)
    signal.signal(signal.SIGUSR1, on_usr1)
    print('listening serial %s' % dev, flush=True)
    srv.run()
    write_state(state_path, drive)


# ---------------------------------------------------------------- main
def main():
    ap = argparse.ArgumentParser(description='SIEB & MEYER SD2x Modbus RTU simulator')
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument('--listen', help='HOST:PORT (RTU frames over TCP)')
    g.add_argument('--serial', help='serial device (e.g. /dev/pts/N)')
    ap.add_argument('--baud', type=int, default=19200,
                    choices=[9600, 14400, 19200, 28800, 38400, 57600, 115200])
    ap.add_argument('--parity', default='none', choices=['none', 'even', 'odd'])
    ap.add_argument('--state', default=None)
    a = ap.parse_args()
    drive = Drive(a.baud, a.parity)
    timing = Timing(a.baud, a.parity)
    if a.listen:
        host, _, port = a.listen.rpartition(':')
        asyncio.run(run_tcp(host or '127.0.0.1', int(port), drive, a.state, timing))
    else:
        run_serial(a.serial, drive, timing, a.baud, a.parity, a.state)


if __name__ == '__main__':
    main()
