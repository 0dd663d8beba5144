#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier -- Modbus RTU slave simulator.

Written from the manual "Drive Amplifier SD2x - Modbus RTU Connection" and the
public Modbus specifications only.  See DECISIONS.md for every place where the
manual can be read two ways and which reading this firmware implements.

Modes:
  python3 sim.py --listen 127.0.0.1:0 [--state FILE]      RTU frames over TCP
  python3 sim.py --serial /dev/pts/N [--baud 19200] [--parity none|even|odd]
"""
import argparse
import asyncio
import json
import os
import signal
import struct
import sys
import time

# ---------------------------------------------------------------- CRC ----


def crc16(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            if crc & 1:
                crc = (crc >> 1) ^ 0xA001
            else:
                crc >>= 1
    return crc


def add_crc(body: bytes) -> bytes:
    c = crc16(body)
    return body + bytes((c & 0xFF, c >> 8))


def crc_ok(frame: bytes) -> bool:
    if len(frame) < 4:
        return False
    c = crc16(frame[:-2])
    return frame[-2] == (c & 0xFF) and frame[-1] == (c >> 8)


# ------------------------------------------------------ constants -------

MAX_REGS = 48                 # manual 3.1/3.4/3.5: n = 1 to 48 (30h)

TX_BASE = 2000                # TxPDO (input registers) 2000..2023
TX_END = 2023
RX_BASE = 3000                # RxPDO (holding registers) 3000..3003
RX_END = 3003

# 32-bit TxPDO values: first register (high word) -> name
TX32 = {2010: 'hw_id', 2012: 'hw_version', 2014: 'sw_id', 2016: 'sw_version',
        2020: 'speed_scaling', 2022: 'current_scaling'}

# SDO abort codes (manual 3.8)
SDO_CMD_UNKNOWN = 0xFFFF0003
SDO_UNSUPPORTED = 0xFFFF0008
SDO_READ_WO = 0xFFFF0009
SDO_WRITE_RO = 0xFFFF000A
SDO_NO_OBJECT = 0xFFFF000B
SDO_LEN_TOO_LONG = 0xFFFF0012
SDO_LEN_TOO_SHORT = 0xFFFF0013
SDO_NO_SUBINDEX = 0xFFFF0014

# Object dictionary (drivemaster2 indices, manual chapter 5):
#  index: (name, size_bytes, signed, access, attribute)
OBJECTS = {
    68:  ('control_word', 2, False, 'rw', 'control_word'),
    210: ('target_velocity', 2, True, 'rw', 'target_speed'),
    209: ('target_torque_limit', 2, True, 'rw', 'torque_limit'),
    67:  ('status_word', 2, False, 'ro', 'status_word'),
    168: ('actual_speed', 2, True, 'ro', 'actual_speed'),
    431: ('actual_apparent_current', 2, True, 'ro', 'apparent_current'),
    390: ('actual_output_power', 2, True, 'ro', 'output_power'),
    70:  ('error_code', 2, False, 'ro', 'error_code'),
    41:  ('temperature_power_stage', 2, True, 'ro', 'temp_power_stage'),
    63:  ('temperature_motor', 2, True, 'ro', 'temp_motor'),
    434: ('output_voltage', 2, True, 'ro', 'output_voltage'),
    33:  ('dc_voltage', 2, True, 'ro', 'dc_voltage'),
    2:   ('hardware_id', 4, False, 'ro', 'hw_id'),
    5:   ('hardware_version', 4, False, 'ro', 'hw_version'),
    16:  ('software_id', 4, False, 'ro', 'sw_id'),
    17:  ('software_version', 4, False, 'ro', 'sw_version'),
    171: ('max_iq_current', 2, True, 'ro', 'max_iq'),
    120: ('max_speed', 2, True, 'ro', 'max_speed'),
    177: ('speed_scaling', 4, True, 'ro', 'speed_scaling'),
    182: ('current_scaling', 4, True, 'ro', 'current_scaling'),
}

# DS402 states and their status word patterns (bits 0..6)
NRTSO, SOD, RTSO, SO, OE, QSA, FRA, FAULT = (
    'not_ready_to_switch_on', 'switch_on_disabled', 'ready_to_switch_on',
    'switched_on', 'operation_enabled', 'quick_stop_active',
    'fault_reaction_active', 'fault')
STATE_BITS = {NRTSO: 0x0000, SOD: 0x0040, RTSO: 0x0031, SO: 0x0033,
              OE: 0x0037, QSA: 0x0017, FRA: 0x001F, FAULT: 0x0018}

ERR_WATCHDOG = 0x8130      # CiA 301/402 "life guard / heartbeat error" (0x603F)

COAST_DECEL = 2000.0       # 0.1 Hz per second, speed decay when not driven
QS_DECEL = 5000.0          # quick stop ramp, 0.1 Hz per second
ACCEL_PER_CURRENT = 10.0   # (0.1 Hz/s) per (0.1 A) of effective Iq limit


def u16(v):
    return v & 0xFFFF


def s16(v):
    v &= 0xFFFF
    return v - 0x10000 if v & 0x8000 else v


# ------------------------------------------------------------ axis -------

class Axis:
    """One drive axis (one Modbus slave address)."""

    def __init__(self, name, slave):
        self.name = name
        self.slave = slave
        # RxPDO / writable objects (manual defaults: 0)
        self.control_word = 0
        self.target_speed = 0       # 0.1 Hz, int16
        self.torque_limit = 0       # 0.1 A, int16
        self.watchdog = 0           # ms, 0 = off
        # drive state
        self.state = NRTSO          # status word default value 0 (line 887)
        self.error_code = 0
        self.speed = 0.0            # actual speed, 0.1 Hz (float internally)
        self.accelerating = False
        # rating / identification (read-only)
        self.max_iq = 200           # 20.0 A
        self.speed_scaling = 60000000   # 60000.000 rpm  (= 1000 Hz)
        self.max_speed = 0x3FFF         # normalised: 0x3FFF = speed scaling
        self.current_scaling = 400      # 40.0 A (unit 0.1 A, see DECISIONS)
        self.hw_id = 0x00002021
        self.hw_version = 0x00020010    # 2.16 (manual example)
        self.sw_id = 0x00002100
        self.sw_version = 0x00020010    # 2.16 (manual example)
        self.temp_power_stage = 170     # 17.0 degC (manual example 2)
        self.temp_motor = 0             # no motor sensor: default value 0
        self.dc_voltage = 5600          # 560.0 V DC link
        # timers (not device state)
        self._wd_last = time.monotonic()
        self._prev_cw = 0
        self._qs_done_state = SOD

    # ---- derived values ------------------------------------------------
    @property
    def max_speed_01hz(self):
        # 0x3FFF corresponds to Speed Scaling (0.001 rpm); 1 Hz = 60 rpm
        hz01 = self.speed_scaling / 1000.0 / 60.0 * 10.0
        return hz01 * self.max_speed / 0x3FFF

    @property
    def eff_torque_limit(self):
        lim = self.torque_limit
        return max(-self.max_iq, min(self.max_iq, lim))

    @property
    def status_word(self):
        sw = STATE_BITS[self.state]
        if self.state == OE:
            tgt = self.clamped_target()
            if abs(self.speed - tgt) < 0.5:
                sw |= 0x0400        # bit 10 target reached
        return sw

    def clamped_target(self):
        m = self.max_speed_01hz
        return max(-m, min(m, float(self.target_speed)))

    @property
    def actual_speed(self):
        return int(round(self.speed))

    @property
    def apparent_current(self):
        if abs(self.speed) < 0.5 and not self.accelerating:
            return 0
        if self.accelerating:
            return abs(self.eff_torque_limit)
        # magnetising / friction current proportional to speed
        return min(self.max_iq, int(round(10 + abs(self.speed) / 100.0)))

    @property
    def output_voltage(self):
        # 0.1 V: 400 V at 1000 Hz
        return int(round(abs(self.speed) * 0.4))

    @property
    def output_power(self):
        # 0.1 kW = U * I * sqrt(3) (U in 0.1 V, I in 0.1 A)
        p = (self.output_voltage / 10.0) * (self.apparent_current / 10.0) * 1.732 * 0.9
        return int(round(p / 100.0))

    # ---- PDO registers -------------------------------------------------
    def read_reg(self, addr):
        if RX_BASE <= addr <= RX_END:
            return u16((self.control_word, self.target_speed,
                        self.torque_limit, self.watchdog)[addr - RX_BASE])
        if addr in TX32:
            return (getattr(self, TX32[addr]) >> 16) & 0xFFFF
        if addr - 1 in TX32:
            return getattr(self, TX32[addr - 1]) & 0xFFFF
        v = {2000: self.status_word, 2001: self.actual_speed,
             2002: self.eff_torque_limit, 2003: self.apparent_current,
             2004: self.output_power, 2005: self.error_code,
             2006: self.temp_power_stage, 2007: self.temp_motor,
             2008: self.output_voltage, 2009: self.dc_voltage,
             2018: self.max_iq, 2019: self.max_speed}[addr]
        return u16(v)

    def write_reg(self, addr, value):
        if addr == 3000:
            self.set_control_word(value)
        elif addr == 3001:
            self.target_speed = s16(value)
        elif addr == 3002:
            self.torque_limit = s16(value)
        elif addr == 3003:
            self.watchdog = value
            self._wd_last = time.monotonic()   # "rewritten" -> retrigger

    # ---- DS402 device control -------------------------------------------
    def set_control_word(self, cw):
        cw &= 0xFFFF
        prev = self._prev_cw
        self.control_word = cw
        self._prev_cw = cw
        st = self.state
        if st in (FAULT, FRA):
            if (cw & 0x80) and not (prev & 0x80) and st == FAULT:
                self.error_code = 0
                self.state = SOD
                self._wd_last = time.monotonic()
            return
        if cw & 0x80:
            return                    # fault reset bit without a fault: no-op
        c = cw & 0x0F
        disable_voltage = not (c & 0x02)
        quick_stop = (c & 0x06) == 0x02
        shutdown = (c & 0x07) == 0x06
        switch_on = (c & 0x0F) == 0x07
        enable_op = (c & 0x0F) == 0x0F
        if quick_stop:
            if st == OE:
                self.state = QSA
            elif st in (RTSO, SO, NRTSO):
                self.state = SOD
            return
        if disable_voltage:
            if st in (NRTSO, RTSO, SO, OE, QSA):
                self.state = SOD
            return
        if shutdown:
            if st in (NRTSO, SOD, SO, OE):
                self.state = RTSO
            return
        if switch_on:
            if st in (RTSO, OE):
                self.state = SO
            return
        if enable_op:
            if st in (RTSO, SO, QSA):
                self.state = OE
            return

    def raise_fault(self, code):
        if self.state in (FAULT, FRA):
            return
        self.error_code = code
        self.state = FRA
        self.accelerating = False

    # ---- periodic update --------------------------------------------------
    def tick(self, now, dt):
        if self.watchdog and self.state not in (FAULT, FRA):
            if (now - self._wd_last) * 1000.0 > self.watchdog:
                self.raise_fault(ERR_WATCHDOG)
        self.accelerating = False
        if self.state == OE:
            tgt = self.clamped_target()
            acc = ACCEL_PER_CURRENT * abs(self.eff_torque_limit) * dt
            diff = tgt - self.speed
            if abs(diff) <= acc:
                if acc > 0 and abs(diff) > 0.01:
                    self.accelerating = True
                self.speed = tgt if acc > 0 else self.speed
            else:
                self.accelerating = True
                self.speed += acc if diff > 0 else -acc
        else:
            dec = (QS_DECEL if self.state == QSA else COAST_DECEL) * dt
            if abs(self.speed) <= dec:
                self.speed = 0.0
            else:
                self.speed -= dec if self.speed > 0 else -dec
            if self.state == QSA and self.speed == 0.0:
                self.state = SOD
            if self.state == FRA and self.speed == 0.0:
                self.state = FAULT

    # ---- object dictionary ------------------------------------------------
    def obj_get(self, idx):
        return getattr(self, OBJECTS[idx][4])

    def obj_set(self, idx, raw):
        attr = OBJECTS[idx][4]
        if attr == 'control_word':
            self.set_control_word(raw)
        elif attr == 'target_speed':
            self.target_speed = s16(raw)
        elif attr == 'torque_limit':
            self.torque_limit = s16(raw)

    def dump(self):
        regs = {}
        for a in list(range(TX_BASE, TX_END + 1)) + list(range(RX_BASE, RX_END + 1)):
            regs[str(a)] = self.read_reg(a)
        objs = {}
        for idx, (name, size, signed, acc, attr) in sorted(OBJECTS.items()):
            v = self.obj_get(idx)
            objs['%d.0' % idx] = {'name': name, 'value': v, 'access': acc}
        return {
            'slave_address': self.slave,
            'holding_and_input_registers': regs,
            'rxpdo': {'control_word': self.control_word,
                      'target_speed_0.1Hz': self.target_speed,
                      'torque_limit_0.1A': self.torque_limit,
                      'watchdog_ms': self.watchdog},
            'objects': objs,
            'ds402_state': self.state,
        }


# ---------------------------------------------------------- device --------

class ModbusError(Exception):
    def __init__(self, code):
        self.code = code


class SdoError(Exception):
    def __init__(self, code):
        self.code = code


class Device:
    def __init__(self, addresses, config):
        # addresses: list of (slave, axis_name)
        self.axes = {}
        for slave, name in addresses:
            self.axes[slave] = Axis(name, slave)
        self.config = config
        self.counters = dict(bus_message_count=0, bus_communication_error_count=0,
                             bus_exception_error_count=0, slave_message_count=0,
                             slave_no_response_count=0)

    def tick(self, now, dt):
        for ax in self.axes.values():
            ax.tick(now, dt)

    # ---- frame entry point ------------------------------------------------
    def handle_frame(self, frame: bytes):
        """Return response bytes or None."""
        c = self.counters
        c['bus_message_count'] = (c['bus_message_count'] + 1) & 0xFFFF
        if not crc_ok(frame):
            c['bus_communication_error_count'] = (c['bus_communication_error_count'] + 1) & 0xFFFF
            return None
        slave = frame[0]
        pdu = frame[1:-2]
        if slave == 0:
            try:
                self.broadcast(pdu)
            except Exception:
                pass
            c['slave_no_response_count'] = (c['slave_no_response_count'] + 1) & 0xFFFF
            return None
        ax = self.axes.get(slave)
        if ax is None:
            return None
        clear = False
        try:
            rpdu, clear = self.dispatch(ax, pdu)
        except ModbusError as e:
            rpdu = bytes((pdu[0] | 0x80, e.code))
        except SdoError as e:
            rpdu = bytes((0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + struct.pack('>I', e.code)
        except Exception:
            rpdu = bytes(((pdu[0] | 0x80) & 0xFF, 0x04))
        if rpdu[0] & 0x80:
            c['bus_exception_error_count'] = (c['bus_exception_error_count'] + 1) & 0xFFFF
        c['slave_message_count'] = (c['slave_message_count'] + 1) & 0xFFFF
        if clear:
            for k in c:
                c[k] = 0
        return add_crc(bytes((slave,)) + rpdu)

    def broadcast(self, pdu):
        if len(pdu) < 1:
            return
        fc = pdu[0]
        if fc in (0x06, 0x10):
            for ax in self.axes.values():
                try:
                    self.dispatch(ax, pdu)
                except (ModbusError, SdoError):
                    pass

    def dispatch(self, ax, pdu):
        fc = pdu[0]
        if fc in (0x03, 0x04):
            return self.fc_read(ax, pdu), False
        if fc == 0x06:
            return self.fc_write_single(ax, pdu), False
        if fc == 0x08:
            return self.fc_diag(ax, pdu)
        if fc == 0x10:
            return self.fc_write_multiple(ax, pdu), False
        if fc == 0x17:
            return self.fc_read_write(ax, pdu), False
        if fc == 0x2B:
            return self.fc_mei(ax, pdu), False
        raise ModbusError(0x01)

    # ---- register address checks ------------------------------------------
    @staticmethod
    def check_read_range(start, count):
        end = start + count - 1
        if end > 0xFFFF:
            raise ModbusError(0x02)
        if TX_BASE <= start and end <= TX_END:
            # a 32-bit value is only accessible as a whole (line 785)
            if start - 1 in TX32 or end in TX32:
                raise ModbusError(0x02)
            return
        if RX_BASE <= start and end <= RX_END:
            return
        raise ModbusError(0x02)

    @staticmethod
    def check_write_range(start, count):
        end = start + count - 1
        if RX_BASE <= start and end <= RX_END:
            return
        raise ModbusError(0x02)

    # ---- FC 03 / 04 -----------------------------------------------------------
    def fc_read(self, ax, pdu):
        if len(pdu) != 5:
            raise ModbusError(0x03)
        start, count = struct.unpack('>HH', pdu[1:5])
        if not 1 <= count <= MAX_REGS:
            raise ModbusError(0x03)
        self.check_read_range(start, count)
        vals = [ax.read_reg(a) for a in range(start, start + count)]
        return bytes((pdu[0], 2 * count)) + struct.pack('>%dH' % count, *vals)

    # ---- FC 06 ------------------------------------------------------------
    def fc_write_single(self, ax, pdu):
        if len(pdu) != 5:
            raise ModbusError(0x03)
        addr, value = struct.unpack('>HH', pdu[1:5])
        self.check_write_range(addr, 1)
        ax.write_reg(addr, value)
        return bytes(pdu)

    # ---- FC 16 ------------------------------------------------------------
    def fc_write_multiple(self, ax, pdu):
        if len(pdu) < 6:
            raise ModbusError(0x03)
        start, count = struct.unpack('>HH', pdu[1:5])
        bc = pdu[5]
        if not 1 <= count <= MAX_REGS or bc != 2 * count or len(pdu) != 6 + bc:
            raise ModbusError(0x03)
        self.check_write_range(start, count)
        vals = struct.unpack('>%dH' % count, pdu[6:6 + bc])
        for i, v in enumerate(vals):
            ax.write_reg(start + i, v)
        return bytes(pdu[:5])

    # ---- FC 23 ------------------------------------------------------------
    def fc_read_write(self, ax, pdu):
        if len(pdu) < 10:
            raise ModbusError(0x03)
        rstart, rcount, wstart, wcount = struct.unpack('>HHHH', pdu[1:9])
        bc = pdu[9]
        if (not 1 <= rcount <= MAX_REGS or not 1 <= wcount <= MAX_REGS
                or bc != 2 * wcount or len(pdu) != 10 + bc):
            raise ModbusError(0x03)
        self.check_read_range(rstart, rcount)
        self.check_write_range(wstart, wcount)
        vals = struct.unpack('>%dH' % wcount, pdu[10:10 + bc])
        for i, v in enumerate(vals):              # write before read (spec)
            ax.write_reg(wstart + i, v)
        rv = [ax.read_reg(a) for a in range(rstart, rstart + rcount)]
        return bytes((0x17, 2 * rcount)) + struct.pack('>%dH' % rcount, *rv)

    # ---- FC 08 ------------------------------------------------------------
    DIAG = {11: 'bus_message_count', 12: 'bus_communication_error_count',
            13: 'bus_exception_error_count', 14: 'slave_message_count',
            15: 'slave_no_response_count'}

    def fc_diag(self, ax, pdu):
        if len(pdu) < 3:
            raise ModbusError(0x03)
        sub = struct.unpack('>H', pdu[1:3])[0]
        if sub not in (0, 10, 11, 12, 13, 14, 15):
            raise ModbusError(0x01)
        # fixed telegram size: exactly one data word (manual 3.3, line 368)
        if len(pdu) != 5:
            raise ModbusError(0x03)
        data = pdu[3:5]
        if sub == 0:
            return bytes(pdu), False
        if sub == 10:
            return bytes(pdu), True
        val = self.counters[self.DIAG[sub]]
        if sub == 14:
            val = (val + 1) & 0xFFFF     # this response is a message sent, too
        return bytes(pdu[:3]) + struct.pack('>H', val), False

    # ---- FC 43 / MEI 0x0D ---------------------------------------------------
    def fc_mei(self, ax, pdu):
        # layout as printed (and CRC-verified) in example 2, lines 1299-1317:
        # 2B 0D ctrl node idxH idxL sub offH offL cntH cntL [data]
        if len(pdu) < 2:
            raise ModbusError(0x03)
        if pdu[1] != 0x0D:
            raise ModbusError(0x01)
        if len(pdu) < 11:
            raise ModbusError(0x03)
        ctrl, node = pdu[2], pdu[3]
        idx = struct.unpack('>H', pdu[4:6])[0]
        sub = pdu[6]
        cnt = struct.unpack('>H', pdu[9:11])[0]
        write = bool(ctrl & 0x80)
        if cnt > 4:
            raise ModbusError(0x03)
        if write:
            if len(pdu) != 11 + cnt:
                raise ModbusError(0x03)
        elif len(pdu) != 11:
            raise ModbusError(0x03)
        if node != ax.slave:
            raise ModbusError(0x03)
        # object access
        if idx >= 0x2000:
            raise SdoError(SDO_UNSUPPORTED)    # DS301/DS402 area: not supported
        if idx not in OBJECTS:
            raise SdoError(SDO_NO_OBJECT)
        name, size, signed, access, attr = OBJECTS[idx]
        if sub != 0:
            raise SdoError(SDO_NO_SUBINDEX)
        hdr = bytes((0x2B, 0x0D, ctrl & 0x80, node)) + pdu[4:7] + b'\x00\x00'
        if write:
            if access == 'ro':
                raise SdoError(SDO_WRITE_RO)
            if cnt < size:
                raise SdoError(SDO_LEN_TOO_SHORT)
            if cnt > size:
                raise SdoError(SDO_LEN_TOO_LONG)
            data = bytes(pdu[11:11 + cnt])
            raw = int.from_bytes(data, 'big')
            ax.obj_set(idx, raw)
            return hdr + struct.pack('>H', cnt) + data
        if cnt != 0 and cnt < size:
            raise SdoError(SDO_LEN_TOO_SHORT)
        if cnt > size:
            raise SdoError(SDO_LEN_TOO_LONG)
        v = ax.obj_get(idx) & ((1 << (8 * size)) - 1)
        return hdr + struct.pack('>H', size) + v.to_bytes(size, 'big')

    # ---- state dump --------------------------------------------------------
    def dump(self):
        return {
            'device': 'SIEB & MEYER SD2x (simulated)',
            'configuration': self.config,
            'axes': {str(s): ax.dump() for s, ax in sorted(self.axes.items())},
            'diagnostic_counters': dict(self.counters),
        }


# ------------------------------------------------------- framing ---------

def expected_len(buf: bytes):
    """Length of a complete request frame starting at buf[0], or None."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (0x03, 0x04, 0x06, 0x08):
        return 8
    if fc == 0x10:
        return 9 + buf[6] if len(buf) >= 7 else None
    if fc == 0x17:
        return 13 + buf[10] if len(buf) >= 11 else None
    if fc == 0x2B:
        if len(buf) < 12:
            return None
        if buf[2] == 0x0D and (buf[3] & 0x80):
            return 14 + ((buf[10] << 8) | buf[11])
        return 14
    return None


class Server:
    def __init__(self, device, state_file):
        self.device = device
        self.state_file = state_file
        self.stop = asyncio.Event()

    def save_state(self):
        if not self.state_file:
            return
        try:
            tmp = self.state_file + '.tmp'
            with open(tmp, 'w') as f:
                json.dump(self.device.dump(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except Exception as e:      # never die because of the dump
            print('state dump failed: %s' % e, file=sys.stderr)

    async def ticker(self):
        last = time.monotonic()
        while not self.stop.is_set():
            await asyncio.sleep(0.01)
            now = time.monotonic()
            try:
                self.device.tick(now, now - last)
            except Exception as e:
                print('tick error: %s' % e, file=sys.stderr)
            last = now

    def process(self, frame):
        try:
            return self.device.handle_frame(bytes(frame))
        except Exception as e:
            print('frame error: %s' % e, file=sys.stderr)
            return None

    # ---- RTU over TCP --------------------------------------------------------
    async def tcp_client(self, reader, writer):
        gap = 0.03
        buf = bytearray()
        try:
            while True:
                try:
                    data = await asyncio.wait_for(reader.read(4096), timeout=gap if buf else None)
                except asyncio.TimeoutError:
                    # line silent: whatever is buffered is one frame
                    resp = self.process(buf)
                    buf.clear()
                    if resp:
                        writer.write(resp)
                        await writer.drain()
                    continue
                if not data:
                    break
                buf += data
                if len(buf) > 4096:
                    self.process(buf[:4096])
                    buf.clear()
                    continue
                # complete, CRC-valid frames can be served without waiting
                while True:
                    n = expected_len(buf)
                    if n is None or len(buf) < n or not crc_ok(bytes(buf[:n])):
                        break
                    frame = bytes(buf[:n])
                    del buf[:n]
                    resp = self.process(frame)
                    if resp:
                        writer.write(resp)
                        await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            try:
                writer.close()
            except Exception:
                pass

    async def run_tcp(self, host, port):
        srv = await asyncio.start_server(self.tcp_client, host, port)
        p = srv.sockets[0].getsockname()[1]
        print('listening tcp %s:%d' % (host, p), flush=True)
        async with srv:
            await self.stop.wait()

    # ---- serial RTU ---------------------------------------------------------
    async def run_serial(self, dev, baud, parity):
        import termios
        import tty
        fd = os.open(dev, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(fd)
        attrs = termios.tcgetattr(fd)
        speed = getattr(termios, 'B%d' % baud, None)
        if speed is not None:
            attrs[4] = attrs[5] = speed
        cflag = attrs[2]
        cflag &= ~(termios.PARENB | termios.PARODD | termios.CSTOPB | termios.CSIZE)
        cflag |= termios.CS8 | termios.CLOCAL | termios.CREAD
        if parity == 'even':
            cflag |= termios.PARENB
        elif parity == 'odd':
            cflag |= termios.PARENB | termios.PARODD
        attrs[2] = cflag          # 1 stop bit in every setting (manual 2.2.3)
        attrs[6][termios.VMIN] = 0
        attrs[6][termios.VTIME] = 0
        try:
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
        except termios.error:
            pass
        bits = 1 + 8 + (0 if parity == 'none' else 1) + 1
        t35 = 0.00175 if baud > 19200 else 3.5 * bits / baud
        loop = asyncio.get_running_loop()
        buf = bytearray()
        timer = [None]

        def flush_frame():
            timer[0] = None
            if not buf:
                return
            frame = bytes(buf)
            buf.clear()
            resp = self.process(frame)
            if resp:
                try:
                    os.write(fd, resp)
                except OSError:
                    pass

        def on_read():
            try:
                data = os.read(fd, 4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                data = b''
            if not data:
                return
            buf.extend(data)
            if len(buf) > 4096:
                del buf[:-256]
            if timer[0] is not None:
                timer[0].cancel()
            timer[0] = loop.call_later(t35, flush_frame)

        loop.add_reader(fd, on_read)
        print('listening serial %s' % dev, flush=True)
        try:
            await self.stop.wait()
        finally:
            loop.remove_reader(fd)
            os.close(fd)


def compute_addresses(mode, switch, prog, axes):
    """Slave address(es) per manual 2.2.2 (see DECISIONS.md D20/D21)."""
    if mode == 'switch':
        a = switch * 2 + 1
        return [(a, 'A'), (a + 1, 'B')] if axes == 2 else [(a, 'A')]
    if mode == 'switch+prog':
        a = switch + prog + 1           # text of line 226, not the example
        return [(a, 'A'), (a + 1, 'B')] if axes == 2 else [(a, 'A')]
    return [(prog + 1, 'A')]            # "regardless of ... double-axis" (line 259)


def main():
    ap = argparse.ArgumentParser(description='SD2x Modbus RTU simulator')
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument('--listen', help='HOST:PORT for RTU over TCP')
    g.add_argument('--serial', help='tty device')
    ap.add_argument('--baud', type=int, default=19200,
                    choices=[9600, 14400, 19200, 28800, 38400, 57600, 115200])
    ap.add_argument('--parity', default='none', choices=['none', 'even', 'odd'])
    ap.add_argument('--state', help='JSON state file')
    ap.add_argument('--axes', type=int, default=2, choices=[1, 2],
                    help='single- or double-axis device (default 2)')
    ap.add_argument('--id-switch', type=lambda s: int(s, 16), default=0,
                    help='ID switch position 0..F (default 0)')
    ap.add_argument('--address-mode', default='switch',
                    choices=['switch', 'switch+prog', 'prog'])
    ap.add_argument('--prog-address', type=int, default=0, help='0..253')
    args = ap.parse_args()
    if not 0 <= args.id_switch <= 15 or not 0 <= args.prog_address <= 253:
        ap.error('address setting out of range')
    addrs = compute_addresses(args.address_mode, args.id_switch,
                              args.prog_address, args.axes)
    addrs = [(a, n) for a, n in addrs if 1 <= a <= 254]
    if not addrs:
        ap.error('resulting slave address outside 1..254')
    config = {'baud_rate': args.baud, 'parity': args.parity, 'stop_bits': 1,
              'axes': args.axes, 'id_switch': args.id_switch,
              'slave_address_mode': args.address_mode,
              'programmable_address': args.prog_address,
              'slave_addresses': [a for a, _ in addrs]}
    dev = Device(addrs, config)

    async def amain():
        srv = Server(dev, args.state)
        loop = asyncio.get_running_loop()

        def on_exit():
            srv.save_state()
            try:
                sys.stdout.flush()
            finally:
                os._exit(0)

        loop.add_signal_handler(signal.SIGTERM, on_exit)
        loop.add_signal_handler(signal.SIGINT, on_exit)
        loop.add_signal_handler(signal.SIGUSR1, srv.save_state)
        tick = asyncio.create_task(srv.ticker())
        if args.listen:
            host, _, port = args.listen.rpartition(':')
            await srv.run_tcp(host or '127.0.0.1', int(port))
        else:
            await srv.run_serial(args.serial, args.baud, args.parity)
        tick.cancel()

    try:
        asyncio.run(amain())
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
