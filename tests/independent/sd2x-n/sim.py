#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier -- Modbus RTU slave simulator.

Built on uModbus 1.0.4 (RTUServer, route map, standard function classes,
exception classes, CRC).  Added on top: FC 08, FC 23, FC 43 / MEI 0x0D,
the SD2x PDO register map, the object dictionary, a CiA 402 state machine,
the watchdog and the FC 08 counters.  See DECISIONS.md.

  sim.py --serial DEVICE [--baud 19200] [--parity even] [--state FILE]
  sim.py --listen 127.0.0.1:0 [--state FILE]        (RTU framing over TCP)
"""
import argparse
import json
import logging
import os
import select
import signal
import socket
import struct
import sys
import threading
import time

from umodbus import log as umodbus_log
from umodbus.functions import (ModbusFunction, ReadHoldingRegisters,
                               ReadInputRegisters, WriteSingleRegister,
                               WriteMultipleRegisters)
from umodbus.exceptions import (ModbusError, IllegalFunctionError,
                                IllegalDataAddressError, IllegalDataValueError)
from umodbus.server.serial import get_server
from umodbus.server.serial.rtu import RTUServer, get_char_size
from umodbus.client.serial.redundancy_check import get_crc
from umodbus.utils import pack_exception_pdu

log = logging.getLogger('sd2x')

MAX_REGS = 48                      # manual: n = 1 to 48 (30h) for 03/04/16/23
TXPDO = range(2000, 2024)          # input registers (actual values)
RXPDO = range(3000, 3004)          # holding registers (setpoints)

# CiA 402 states
NOT_READY = 'not_ready_to_switch_on'
SOD = 'switch_on_disabled'
RTSO = 'ready_to_switch_on'
SO = 'switched_on'
OE = 'operation_enabled'
QSA = 'quick_stop_active'
FAULT = 'fault'

STATUS_BITS = {NOT_READY: 0x0000, SOD: 0x0040, RTSO: 0x0021, SO: 0x0023,
               OE: 0x0027, QSA: 0x0007, FAULT: 0x0008}

ERR_WATCHDOG = 0x8130              # CiA 301 "life guard / heartbeat error"

# SDO (extended) error codes, manual 3.8
SDO_CMD_UNKNOWN = 0xFFFF0003
SDO_UNSUPPORTED_ACCESS = 0xFFFF0008
SDO_READ_ONLY = 0xFFFF000A
SDO_NO_OBJECT = 0xFFFF000B
SDO_LEN_TOO_LONG = 0xFFFF0012
SDO_LEN_TOO_SHORT = 0xFFFF0013
SDO_NO_SUBINDEX = 0xFFFF0014

# object dictionary (manual chapter 5): index -> (attr, type, access, name)
OBJECTS = {
    2: ('hw_id', 'u32', 'ro', 'Hardware ID'),
    5: ('hw_version', 'u32', 'ro', 'Hardware Version'),
    16: ('sw_id', 'u32', 'ro', 'Software ID'),
    17: ('sw_version', 'u32', 'ro', 'Software Version'),
    33: ('dc_voltage', 'i16', 'ro', 'DC Voltage'),
    41: ('temp_power_stage', 'i16', 'ro', 'Temperature Power Stage'),
    63: ('temp_motor', 'i16', 'ro', 'Temperature Motor'),
    67: ('status_word', 'u16', 'ro', 'Status Word'),
    68: ('control_word', 'u16', 'rw', 'Control Word'),
    70: ('error_code', 'u16', 'ro', 'Error Code'),
    120: ('max_speed', 'i16', 'ro', 'Max Speed'),
    168: ('actual_speed', 'i16', 'ro', 'Actual Speed'),
    171: ('max_iq', 'i16', 'ro', 'Max Iq Current'),
    177: ('speed_scaling', 'i32', 'ro', 'Speed Scaling'),
    182: ('current_scaling', 'i32', 'ro', 'Current Scaling'),
    209: ('torque_limit', 'i16', 'rw', 'Target Torque Limit'),
    210: ('target_velocity', 'i16', 'rw', 'Target Velocity'),
    390: ('output_power', 'i16', 'ro', 'Actual Output Power'),
    431: ('apparent_current', 'i16', 'ro', 'Actual Apparent Current'),
    434: ('output_voltage', 'i16', 'ro', 'Output Voltage'),
}
TYPE_FMT = {'u16': '<H', 'i16': '<h', 'u32': '<I', 'i32': '<i'}

# TxPDO layout: first register address -> (attr, words)
TXPDO_MAP = {
    2000: ('status_word', 1), 2001: ('actual_speed', 1),
    2002: ('torque_limit_eff', 1), 2003: ('apparent_current', 1),
    2004: ('output_power', 1), 2005: ('error_code', 1),
    2006: ('temp_power_stage', 1), 2007: ('temp_motor', 1),
    2008: ('output_voltage', 1), 2009: ('dc_voltage', 1),
    2010: ('hw_id', 2), 2012: ('hw_version', 2), 2014: ('sw_id', 2),
    2016: ('sw_version', 2), 2018: ('max_iq', 1), 2019: ('max_speed', 1),
    2020: ('speed_scaling', 2), 2022: ('current_scaling', 2),
}
RXPDO_MAP = {3000: 'control_word', 3001: 'target_velocity',
             3002: 'torque_limit', 3003: 'watchdog'}


def s16(v):
    v &= 0xFFFF
    return v - 0x10000 if v & 0x8000 else v


def clamp(v, lo, hi):
    return lo if v < lo else hi if v > hi else v


class Drive(object):
    """Device model: PDO registers, objects, CiA 402 state, simulated motor."""

    ACCEL = 1000.0       # 0.1 Hz per second  (100 Hz/s)
    COAST = 500.0        # deceleration with the power stage off
    QS_DECEL = 3000.0    # quick stop ramp

    def __init__(self, unit):
        self.lock = threading.RLock()
        self.unit = unit
        # RxPDO / writable objects
        self.control_word = 0
        self.target_velocity = 0
        self.torque_limit = 0
        self.watchdog = 0
        # constants of this (simulated) device
        self.hw_id = 0x00002120
        self.hw_version = 0x00020010          # 2.16
        self.sw_id = 0x0000D204
        self.sw_version = 0x00040017          # 4.23
        self.dc_voltage = 5650                # 565.0 V
        self.temp_power_stage = 170           # 17.0 degC (manual example 6.2)
        self.temp_motor = 235                 # 23.5 degC
        self.max_iq = 200                     # 20.0 A
        self.max_speed = 0x3FFF               # = speed scaling
        self.speed_scaling = 98298000         # 0.001 rpm -> 98298 rpm = 1638.3 Hz
        self.current_scaling = 32000          # 0.001 A -> 32 A peak
        # dynamic
        self.state = SOD
        self.error_code = 0
        self.speed = 0.0
        self.accelerating = 0
        self.limit_active = False
        now = time.monotonic()
        self._last = now
        self._wd_last = now
        self.counters = {'bus_message_count': 0,
                         'bus_communication_error_count': 0,
                         'bus_exception_error_count': 0,
                         'slave_message_count': 0,
                         'slave_no_response_count': 0}

    # ---- counters ------------------------------------------------------
    def count(self, name):
        with self.lock:
            self.counters[name] = (self.counters[name] + 1) & 0xFFFF

    def clear_counters(self):
        for k in self.counters:
            self.counters[k] = 0

    # ---- simulation ----------------------------------------------------
    def power_stage_on(self):
        return self.state in (SO, OE, QSA)

    def _fault(self, code):
        self.state = FAULT
        self.error_code = code

    def update(self):
        now = time.monotonic()
        dt = now - self._last
        if dt < 0:
            dt = 0
        self._last = now
        # watchdog (manual lines 870, 1228)
        if self.watchdog and self.state != FAULT:
            if (now - self._wd_last) * 1000.0 > self.watchdog:
                self._fault(ERR_WATCHDOG)
        # speed profile
        vmax = float(self.max_speed)
        self.limit_active = False
        if self.state == OE:
            tgt = float(s16(self.target_velocity))
            if self.control_word & 0x0100:          # halt
                tgt = 0.0
            if abs(tgt) > vmax:
                tgt = clamp(tgt, -vmax, vmax)
                self.limit_active = True
            rate = self.ACCEL if self.torque_limit != 0 else 0.0
            if rate == 0.0:                            # no torque allowed
                tgt, rate = 0.0, self.COAST
        elif self.state == QSA:
            tgt, rate = 0.0, self.QS_DECEL
        else:
            tgt, rate = 0.0, self.COAST
        step = rate * dt
        old = self.speed
        if abs(tgt - self.speed) <= step:
            self.speed = tgt
        else:
            self.speed += step if tgt > self.speed else -step
        self.accelerating = (abs(self.speed) > abs(old) + 1e-9)
        if self.state == QSA and self.speed == 0.0:
            self.state = SOD                         # quick stop option: -> SOD

    # derived actual values
    @property
    def actual_speed(self):
        return int(round(self.speed))

    @property
    def torque_limit_eff(self):
        return clamp(s16(self.torque_limit), -self.max_iq, self.max_iq)

    @property
    def apparent_current(self):
        if not self.power_stage_on():
            return 0
        cur = 15 + abs(self.speed) / 200.0           # magnetising + load
        if self.accelerating:
            cur += abs(self.torque_limit_eff) * 0.6
        return int(round(min(cur, self.max_iq)))

    @property
    def output_voltage(self):
        if not self.power_stage_on():
            return 0
        return int(round(abs(self.speed) * 0.25))    # 0.25 V/Hz (V/f)

    @property
    def output_power(self):
        # 0.1 kW; P = sqrt(3) * U * I * cos(phi)
        u = self.output_voltage / 10.0
        i = self.apparent_current / 10.0
        p = 1.732 * u * i * 0.85 / 100.0
        return int(round(p))

    @property
    def status_word(self):
        sw = STATUS_BITS[self.state]
        sw |= 0x0010                                 # voltage enabled (DC link)
        sw |= 0x0200                                 # remote (control channel Modbus)
        if self.state == OE:
            tgt = 0 if self.control_word & 0x0100 else clamp(
                s16(self.target_velocity), -self.max_speed, self.max_speed)
            if self.torque_limit == 0:
                tgt = 0
            if abs(self.speed - tgt) < 0.5:
                sw |= 0x0400                         # target reached
        if self.limit_active:
            sw |= 0x0800                             # internal limit active
        return sw

    # ---- CiA 402 control word -----------------------------------------
    def apply_control_word(self, cw):
        old = self.control_word
        self.control_word = cw & 0xFFFF
        st = self.state
        if st == FAULT:
            if (cw & 0x80) and not (old & 0x80):      # fault reset (rising edge)
                self.error_code = 0
                self.state = SOD
                self._wd_last = time.monotonic()
            return
        if cw & 0x80:
            return
        if (cw & 0x02) == 0:                          # disable voltage
            self.state = SOD
        elif (cw & 0x06) == 0x02:                     # quick stop
            if st == OE:
                self.state = QSA
            elif st in (RTSO, SO):
                self.state = SOD
        elif (cw & 0x07) == 0x06:                     # shutdown
            if st in (SOD, SO, OE):
                self.state = RTSO
        elif (cw & 0x0F) == 0x07:                     # switch on / disable op.
            if st in (RTSO, OE):
                self.state = SO
        elif (cw & 0x0F) == 0x0F:                     # (switch on +) enable op.
            if st in (RTSO, SO, QSA):
                self.state = OE

    # ---- register access ----------------------------------------------
    def read_register(self, addr):
        if addr in RXPDO_MAP:
            return getattr(self, RXPDO_MAP[addr]) & 0xFFFF
        base = addr if addr in TXPDO_MAP else addr - 1
        attr, words = TXPDO_MAP[base]
        v = getattr(self, attr)
        if words == 1:
            return v & 0xFFFF
        v &= 0xFFFFFFFF
        return (v >> 16) if addr == base else (v & 0xFFFF)   # high word first

    def write_register(self, addr, value):
        value &= 0xFFFF
        if addr == 3000:
            self.apply_control_word(value)
        elif addr == 3001:
            self.target_velocity = value
        elif addr == 3002:
            self.torque_limit = value
        elif addr == 3003:
            self.watchdog = value
            self._wd_last = time.monotonic()

    # ---- object access (FC 43) ----------------------------------------
    def read_object(self, index):
        attr, typ, _, _ = OBJECTS[index]
        v = getattr(self, attr)
        if typ == 'i16':
            v = s16(v)
        elif typ == 'u16':
            v &= 0xFFFF
        elif typ == 'u32':
            v &= 0xFFFFFFFF
        return struct.pack(TYPE_FMT[typ], v)

    def write_object(self, index, data):
        attr, typ, _, _ = OBJECTS[index]
        v = struct.unpack(TYPE_FMT[typ], data)[0]
        if index == 68:
            self.apply_control_word(v)
        else:
            setattr(self, attr, v & 0xFFFF)

    # ---- state dump ----------------------------------------------------
    def snapshot(self, settings):
        with self.lock:
            self.update()
            objs = {}
            for idx in sorted(OBJECTS):
                attr, typ, acc, name = OBJECTS[idx]
                raw = self.read_object(idx)
                objs['%d:0' % idx] = {
                    'index_hex': '0x%04X' % idx, 'subindex': 0, 'name': name,
                    'type': typ, 'access': acc,
                    'value': struct.unpack(TYPE_FMT[typ], raw)[0]}
            return {
                'device': 'SIEB & MEYER SD2x (simulated)',
                'settings': settings,
                'holding_registers': {str(a): self.read_register(a)
                                      for a in RXPDO},
                'input_registers': {str(a): self.read_register(a)
                                    for a in TXPDO},
                'objects': objs,
                'drive': {'cia402_state': self.state,
                          'control_word': self.control_word,
                          'target_velocity_0p1Hz': s16(self.target_velocity),
                          'torque_limit_0p1A': s16(self.torque_limit),
                          'watchdog_ms': self.watchdog,
                          'error_code': self.error_code,
                          'actual_speed_0p1Hz': self.actual_speed},
                'diagnostic_counters': dict(self.counters),
            }


DRIVE = None   # the single device of this process (set in main)


# ---------------------------------------------------------------------------
# Function classes: library classes tightened to the manual, plus FC 08/23/43
# ---------------------------------------------------------------------------
def _check_read_request(pdu):
    if len(pdu) != 5:
        raise IllegalDataValueError()
    _, start, qty = struct.unpack('>BHH', pdu)
    if not 1 <= qty <= MAX_REGS:
        raise IllegalDataValueError()
    if start + qty > 0x10000:
        raise IllegalDataAddressError()
    return start, qty


class SD2ReadHoldingRegisters(ReadHoldingRegisters):
    @classmethod
    def create_from_request_pdu(cls, pdu):
        start, qty = _check_read_request(pdu)
        inst = cls()
        inst.starting_address = start
        inst.quantity = qty
        return inst


class SD2ReadInputRegisters(ReadInputRegisters):
    @classmethod
    def create_from_request_pdu(cls, pdu):
        start, qty = _check_read_request(pdu)
        inst = cls()
        inst.starting_address = start
        inst.quantity = qty
        return inst


class SD2WriteSingleRegister(WriteSingleRegister):
    @classmethod
    def create_from_request_pdu(cls, pdu):
        if len(pdu) != 5:
            raise IllegalDataValueError()
        return super(SD2WriteSingleRegister, cls).create_from_request_pdu(pdu)


def _precheck_addresses(route_map, slave_id, fc, start, qty):
    for a in range(start, start + qty):
        if route_map.match(slave_id, fc, a) is None:
            raise IllegalDataAddressError()


class SD2WriteMultipleRegisters(WriteMultipleRegisters):
    @classmethod
    def create_from_request_pdu(cls, pdu):
        if len(pdu) < 6:
            raise IllegalDataValueError()
        _, start, qty, bc = struct.unpack('>BHHB', pdu[:6])
        if not 1 <= qty <= MAX_REGS or bc != 2 * qty or len(pdu) != 6 + bc:
            raise IllegalDataValueError()
        if start + qty > 0x10000:
            raise IllegalDataAddressError()
        inst = cls()
        inst.starting_address = start
        inst.values = list(struct.unpack('>' + 'H' * qty, pdu[6:]))
        return inst

    def execute(self, slave_id, route_map):
        # all-or-nothing: validate every address before writing any
        _precheck_addresses(route_map, slave_id, self.function_code,
                            self.starting_address, len(self.values))
        return super(SD2WriteMultipleRegisters, self).execute(slave_id,
                                                              route_map)


class ReadWriteMultipleRegisters(ModbusFunction):
    """FC 23 (0x17): write first, then read (Modbus spec 6.17)."""
    function_code = 23

    @classmethod
    def create_from_request_pdu(cls, pdu):
        if len(pdu) < 10:
            raise IllegalDataValueError()
        _, rs, rq, ws, wq, bc = struct.unpack('>BHHHHB', pdu[:10])
        if not (1 <= rq <= MAX_REGS and 1 <= wq <= MAX_REGS) \
                or bc != 2 * wq or len(pdu) != 10 + bc:
            raise IllegalDataValueError()
        if rs + rq > 0x10000 or ws + wq > 0x10000:
            raise IllegalDataAddressError()
        inst = cls()
        inst.read_start, inst.read_qty = rs, rq
        inst.write_start = ws
        inst.values = list(struct.unpack('>' + 'H' * wq, pdu[10:]))
        return inst

    def execute(self, slave_id, route_map):
        # the write half is routed like FC 16, the read half like FC 03
        _precheck_addresses(route_map, slave_id, 16, self.write_start,
                            len(self.values))
        _precheck_addresses(route_map, slave_id, 3, self.read_start,
                            self.read_qty)
        for i, v in enumerate(self.values):
            a = self.write_start + i
            route_map.match(slave_id, 16, a)(slave_id=slave_id, address=a,
                                             value=v, function_code=23)
        return [route_map.match(slave_id, 3, a)(slave_id=slave_id, address=a,
                                                function_code=23)
                for a in range(self.read_start, self.read_start + self.read_qty)]

    def create_response_pdu(self, data):
        return struct.pack('>BB' + 'H' * len(data), self.function_code,
                           2 * len(data), *data)


class Diagnostics(ModbusFunction):
    """FC 08 with the sub-functions of manual 3.3."""
    function_code = 8
    SUBS = {0x00: None, 0x0A: None,
            0x0B: 'bus_message_count', 0x0C: 'bus_communication_error_count',
            0x0D: 'bus_exception_error_count', 0x0E: 'slave_message_count',
            0x0F: 'slave_no_response_count'}

    @classmethod
    def create_from_request_pdu(cls, pdu):
        if len(pdu) != 5:           # manual: the telegram always has the same size
            raise IllegalDataValueError()
        _, sub, data = struct.unpack('>BHH', pdu)
        if sub not in cls.SUBS:
            raise IllegalFunctionError()
        inst = cls()
        inst.sub, inst.data = sub, data
        return inst

    def execute(self, slave_id, route_map):
        if self.sub == 0x00:
            return self.data
        if self.sub == 0x0A:
            DRIVE.clear_counters()
            return self.data
        return DRIVE.counters[self.SUBS[self.sub]]

    def create_response_pdu(self, value):
        return struct.pack('>BHH', self.function_code, self.sub, value)


class SDOError(Exception):
    def __init__(self, code):
        Exception.__init__(self, '%08X' % code)
        self.code = code


class EncapsulatedInterfaceTransport(ModbusFunction):
    """FC 43 / MEI 0x0D (CANopen general reference), manual 3.6."""
    function_code = 43

    @classmethod
    def create_from_request_pdu(cls, pdu):
        if len(pdu) < 2:
            raise IllegalDataValueError()
        if pdu[1] != 0x0D:
            raise IllegalFunctionError()       # only MEI type 0x0D exists
        inst = cls()
        # layout of the table (with reserved byte): 12-byte header
        if len(pdu) >= 12:
            cnt = struct.unpack('>H', pdu[10:12])[0]
            if len(pdu) == 12 + (cnt if pdu[2] & 0x80 else 0):
                inst.short = False
                inst.ctrl, inst.reserved, inst.node = pdu[2], pdu[3], pdu[4]
                inst.index, inst.sub, inst.offset, inst.count = \
                    struct.unpack('>HBHH', pdu[5:12])
                inst.data = bytes(pdu[12:])
                return inst._check()
        # layout of example 6.2 (no reserved byte): 11-byte header
        if len(pdu) >= 11:
            cnt = struct.unpack('>H', pdu[9:11])[0]
            if len(pdu) == 11 + (cnt if pdu[2] & 0x80 else 0):
                inst.short = True
                inst.ctrl, inst.reserved, inst.node = pdu[2], 0, pdu[3]
                inst.index, inst.sub, inst.offset, inst.count = \
                    struct.unpack('>HBHH', pdu[4:11])
                inst.data = bytes(pdu[11:])
                return inst._check()
        raise IllegalDataValueError()

    def _check(self):
        if self.count > 4:
            raise IllegalDataValueError()
        return self

    def _header(self, count):
        if self.short:
            return struct.pack('>BBBBHBHH', 43, 0x0D, self.ctrl, self.node,
                               self.index, self.sub, self.offset, count)
        return struct.pack('>BBBBBHBHH', 43, 0x0D, self.ctrl, 0, self.node,
                           self.index, self.sub, self.offset, count)

    def execute(self, slave_id, route_map):
        if self.node != DRIVE.unit:
            raise IllegalDataAddressError()
        try:
            if self.ctrl not in (0x00, 0x80):
                raise SDOError(SDO_CMD_UNKNOWN)
            if self.index not in OBJECTS:
                raise SDOError(SDO_NO_OBJECT)
            if self.sub != 0:
                raise SDOError(SDO_NO_SUBINDEX)
            if self.offset != 0:
                raise SDOError(SDO_UNSUPPORTED_ACCESS)
            typ, acc = OBJECTS[self.index][1], OBJECTS[self.index][2]
            size = struct.calcsize(TYPE_FMT[typ])
            if self.ctrl == 0x00:
                if self.count not in (0, size):
                    raise SDOError(SDO_LEN_TOO_LONG if self.count > size
                                   else SDO_LEN_TOO_SHORT)
                data = DRIVE.read_object(self.index)
                return self._header(size) + data
            if acc != 'rw':
                raise SDOError(SDO_READ_ONLY)
            if self.count != size:
                raise SDOError(SDO_LEN_TOO_LONG if self.count > size
                               else SDO_LEN_TOO_SHORT)
            DRIVE.write_object(self.index, self.data)
            return self._header(self.count) + self.data
        except SDOError as e:
            # extended exception: AB FF 0006 0D CE <SDO code, little-endian>
            return struct.pack('>BBHBB', 0xAB, 0xFF, 6, 0x0D, 0xCE) + \
                struct.pack('<I', e.code)

    def create_response_pdu(self, pdu):
        return pdu


FUNCTIONS = {3: SD2ReadHoldingRegisters, 4: SD2ReadInputRegisters,
             6: SD2WriteSingleRegister, 8: Diagnostics,
             16: SD2WriteMultipleRegisters, 23: ReadWriteMultipleRegisters,
             43: EncapsulatedInterfaceTransport}


# ---------------------------------------------------------------------------
# Server: uModbus RTUServer with unit filtering, counters, broadcast handling
# ---------------------------------------------------------------------------
class PortClosed(Exception):
    pass


class SD2RTUServer(RTUServer):
    MIN_GAP = 0.005     # floor for t3.5 on a pty / USB adapter (OS jitter)

    def serve_forever(self, poll_interval=0.5):
        self.serial_port.timeout = poll_interval
        while not self._shutdown_request:
            try:
                self.serve_once()
            except ValueError:          # library idiom: nothing received
                pass
            except (PortClosed, ConnectionError):
                return
            except Exception as e:      # never let one frame kill the server
                log.warning('serial/socket error: %r', e)
                time.sleep(0.1)

    def serve_once(self):
        adu = self.read_frame()
        if len(adu) == 0:
            raise ValueError
        self.handle_frame(bytes(adu))

    def read_frame(self):
        """The library reads serial_port.read(256) and relies on
        inter_byte_timeout; on POSIX pyserial that only sets VTIME, and
        read() then waits for the whole timeout (0.5 s) or 256 bytes, gluing
        frames together.  Here: first byte with the poll timeout, then
        collect until the line has been silent for t3.5."""
        port = self.serial_port
        if isinstance(port, SocketPort):
            return port.read(256)
        first = port.read(1)
        if not first:
            return b''
        buf = bytearray(first)
        gap = max(3.5 * get_char_size(port.baudrate), self.MIN_GAP)
        fd = port.fileno()
        while len(buf) < 256:
            r, _, _ = select.select([fd], [], [], gap)
            if not r:
                break
            n = port.in_waiting
            if n <= 0:
                break
            buf += port.read(min(n, 256 - len(buf)))
        return bytes(buf)

    def handle_frame(self, adu):
        drive = DRIVE
        drive.count('bus_message_count')
        if len(adu) < 4 or get_crc(adu[:-2]) != adu[-2:]:
            drive.count('bus_communication_error_count')
            log.debug('dropped frame %s', adu.hex())
            return
        unit, fc = adu[0], adu[1]
        if unit != drive.unit and unit != 0:
            return                                  # not for us: silence
        drive.count('slave_message_count')
        if unit == 0:
            # broadcast: only the write services are executed, never answered
            if fc in (6, 16):
                self.process(adu)
            drive.count('slave_no_response_count')
            return
        if fc & 0x80:
            # 0x80..0xFF are exception codes, not requests: no answer
            drive.count('slave_no_response_count')
            return
        response = self.process(adu)
        if response[1] & 0x80:
            drive.count('bus_exception_error_count')
        self.respond(response)

    def execute_route(self, meta_data, request_pdu):
        fc = request_pdu[0]
        try:
            cls = FUNCTIONS.get(fc)
            if cls is None:
                raise IllegalFunctionError()
            function = cls.create_from_request_pdu(request_pdu)
            with DRIVE.lock:
                DRIVE.update()
                results = function.execute(meta_data['unit_id'],
                                           self.route_map)
                DRIVE.update()
            if results is None:
                return function.create_response_pdu()
            return function.create_response_pdu(results)
        except ModbusError as e:
            return pack_exception_pdu(fc, e.error_code)
        except (struct.error, IndexError) as e:
            return pack_exception_pdu(fc, IllegalDataValueError.error_code)
        except Exception:
            log.exception('could not handle request')
            return pack_exception_pdu(fc, 4)


def install_routes(server, drive):
    unit = drive.unit

    @server.route(slave_ids=[unit], function_codes=[3, 4],
                  addresses=list(TXPDO) + list(RXPDO))
    def read_register(slave_id, function_code, address):
        return drive.read_register(address)

    @server.route(slave_ids=[unit, 0], function_codes=[6, 16],
                  addresses=list(RXPDO))
    def write_register(slave_id, function_code, address, value):
        drive.write_register(address, value)


def make_server(port, drive):
    server = get_server(SD2RTUServer, port)
    install_routes(server, drive)
    return server


class SocketPort(object):
    """Looks like a pyserial port to the RTU server: RTU frames over TCP
    (transparent serial device server).  A frame ends when the bytes so far
    carry a valid CRC, or after a silent gap of MIN_GAP (TCP has no t3.5)."""
    MIN_GAP = 0.05

    def __init__(self, sock, baudrate):
        self.sock = sock
        self.baudrate = baudrate
        self.timeout = 0.5
        self._ibt = self.MIN_GAP

    @property
    def inter_byte_timeout(self):
        return self._ibt

    @inter_byte_timeout.setter
    def inter_byte_timeout(self, v):
        self._ibt = max(v, self.MIN_GAP)

    def read(self, size):
        r, _, _ = select.select([self.sock], [], [], self.timeout)
        if not r:
            return b''
        data = self.sock.recv(size)
        if not data:
            raise PortClosed()
        buf = bytearray(data)
        while len(buf) < size:
            if len(buf) >= 4 and get_crc(bytes(buf[:-2])) == bytes(buf[-2:]):
                break
            r, _, _ = select.select([self.sock], [], [], self._ibt)
            if not r:
                break
            d = self.sock.recv(size - len(buf))
            if not d:
                break
            buf += d
        return bytes(buf)

    def write(self, data):
        self.sock.sendall(data)


# ---------------------------------------------------------------------------
def write_state(path, settings):
    if not path:
        return
    snap = DRIVE.snapshot(settings)
    tmp = path + '.tmp'
    with open(tmp, 'w') as f:
        json.dump(snap, f, indent=1, sort_keys=True)
    os.replace(tmp, path)


def open_serial(device, baud, parity):
    """Open the port with the configured parity.  Linux pseudo-terminals do
    not emulate parity and some kernels refuse PARENB on a pty with EINVAL;
    then the port is opened without parity bits (a pty carries bytes, not
    bits, so nothing changes on the wire)."""
    import serial
    import termios
    last = None
    for par in ([parity, 'N'] if parity != 'N' else ['N']):
        port = None
        try:
            port = serial.Serial(port=device, baudrate=baud, bytesize=8,
                                 parity=par, stopbits=1, timeout=0.5)
            srv = make_server(port, DRIVE)
            if par != parity:
                log.warning('%s refuses parity %s (pseudo-terminal?); '
                            'running without parity bits', device, parity)
            return srv
        except (termios.error, serial.SerialException, OSError,
                ValueError) as e:
            last = e
            if port is not None:
                try:
                    port.close()
                except Exception:
                    pass
    raise SystemExit('cannot open %s: %s' % (device, last))


def ticker(stop):
    while not stop.wait(0.02):
        with DRIVE.lock:
            DRIVE.update()


def main():
    global DRIVE
    ap = argparse.ArgumentParser(description='SIEB & MEYER SD2x Modbus RTU simulator')
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument('--serial', metavar='DEVICE')
    g.add_argument('--listen', metavar='127.0.0.1:PORT')
    ap.add_argument('--baud', type=int, default=19200,
                    choices=[9600, 14400, 19200, 28800, 38400, 57600, 115200])
    ap.add_argument('--parity', default='even',
                    choices=['none', 'even', 'odd', 'N', 'E', 'O'])
    ap.add_argument('--address', type=int, default=1,
                    help='slave address 1..254 (default 1 = ID switch 0, single axis)')
    ap.add_argument('--state', metavar='FILE')
    args = ap.parse_args()
    if not 1 <= args.address <= 254:
        ap.error('--address must be 1..254')
    parity = {'none': 'N', 'even': 'E', 'odd': 'O'}.get(args.parity, args.parity)

    logging.basicConfig(level=logging.DEBUG if os.environ.get('SD2X_DEBUG') else logging.WARNING, stream=sys.stderr,
                        format='%(asctime)s %(name)s %(levelname)s %(message)s')
    umodbus_log.setLevel(logging.CRITICAL)

    DRIVE = Drive(args.address)
    settings = {'slave_address': args.address, 'baud': args.baud,
                'parity': parity, 'stop_bits': 1,
                'transport': 'serial' if args.serial else 'rtu-over-tcp'}

    stop = threading.Event()

    def on_term(signum, frame):
        stop.set()

    def on_usr1(signum, frame):
        try:
            write_state(args.state, settings)
        except Exception as e:
            log.warning('state dump failed: %r', e)

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    signal.signal(signal.SIGUSR1, on_usr1)

    threading.Thread(target=ticker, args=(stop,), daemon=True).start()

    servers = []
    if args.serial:
        srv = open_serial(args.serial, args.baud, parity)
        servers.append(srv)
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        print('listening serial %s' % args.serial, flush=True)
    else:
        host, _, p = args.listen.rpartition(':')
        lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        lsock.bind((host, int(p)))
        lsock.listen(16)
        lsock.settimeout(0.5)

        def conn_thread(conn):
            try:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                srv = make_server(SocketPort(conn, args.baud), DRIVE)
                servers.append(srv)
                srv.serve_forever()
            except Exception as e:
                log.warning('connection error: %r', e)
            finally:
                try:
                    conn.close()
                except OSError:
                    pass

        def accept_loop():
            while not stop.is_set():
                try:
                    conn, _ = lsock.accept()
                except socket.timeout:
                    continue
                except OSError:
                    if stop.is_set():
                        return
                    time.sleep(0.05)
                    continue
                conn.setblocking(True)
                threading.Thread(target=conn_thread, args=(conn,),
                                 daemon=True).start()

        threading.Thread(target=accept_loop, daemon=True).start()
        print('listening tcp %s:%d' % lsock.getsockname()[:2], flush=True)

    while not stop.is_set():
        stop.wait(0.2)
    for s in list(servers):
        s.shutdown()
    try:
        write_state(args.state, settings)
    except Exception as e:
        log.warning('state dump failed: %r', e)
    sys.stdout.flush()
    os._exit(0)


if __name__ == '__main__':
    main()
