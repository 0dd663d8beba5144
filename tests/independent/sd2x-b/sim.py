#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier -- Modbus RTU slave simulator.

Written from the vendor manual "Drive Amplifier SD2x - Modbus RTU Connection"
and the public Modbus specifications only.  See DECISIONS.md for every place
where the manual is ambiguous or wrong and what this implementation does.

Transports (both may be given at once; they share one drive):
  --listen 127.0.0.1:PORT   raw RTU frames (address + PDU + CRC) on TCP streams
  --serial PATH             RTU on a serial device / pty (frames delimited by t3.5)

Standard library only.
"""

import argparse
import json
import os
import select
import signal
import socket
import sys
import termios
import threading
import time

# ---------------------------------------------------------------------------
# CRC
# ---------------------------------------------------------------------------

_CRC_TABLE = []
for _i in range(256):
    _c = _i
    for _ in range(8):
        _c = (_c >> 1) ^ 0xA001 if _c & 1 else _c >> 1
    _CRC_TABLE.append(_c)


def crc16(data):
    crc = 0xFFFF
    for b in data:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ b) & 0xFF]
    return crc


def crc_ok(frame):
    if len(frame) < 4:
        return False
    c = crc16(frame[:-2])
    return frame[-2] == (c & 0xFF) and frame[-1] == (c >> 8)


def add_crc(body):
    c = crc16(body)
    return bytes(body) + bytes((c & 0xFF, c >> 8))


# ---------------------------------------------------------------------------
# Exceptions
# ---------------------------------------------------------------------------

ILLEGAL_FUNCTION = 0x01
ILLEGAL_DATA_ADDRESS = 0x02
ILLEGAL_DATA_VALUE = 0x03
SLAVE_DEVICE_FAILURE = 0x04


class ModbusException(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


class SdoError(Exception):
    def __init__(self, code):
        super().__init__(hex(code))
        self.code = code


SDO_UNSUPPORTED_ACCESS = 0xFFFF0008
SDO_READ_WRITE_ONLY = 0xFFFF0009
SDO_WRITE_READ_ONLY = 0xFFFF000A
SDO_NO_OBJECT = 0xFFFF000B
SDO_LEN_WRONG = 0xFFFF0011
SDO_LEN_TOO_LONG = 0xFFFF0012
SDO_LEN_TOO_SHORT = 0xFFFF0013
SDO_NO_SUBINDEX = 0xFFFF0014

# ---------------------------------------------------------------------------
# Drive model
# ---------------------------------------------------------------------------

# DS402 states
NOT_READY = "NOT_READY_TO_SWITCH_ON"
SOD = "SWITCH_ON_DISABLED"
RTSO = "READY_TO_SWITCH_ON"
SO = "SWITCHED_ON"
OE = "OPERATION_ENABLED"
QSA = "QUICK_STOP_ACTIVE"
FRA = "FAULT_REACTION_ACTIVE"
FAULT = "FAULT"

_STATE_BITS = {
    NOT_READY: 0x0000,
    SOD: 0x0040,
    RTSO: 0x0021,
    SO: 0x0023,
    OE: 0x0027,
    QSA: 0x0007,
    FRA: 0x002F,
    FAULT: 0x0028,
}

ERR_WATCHDOG = 0x8130  # "Heartbeat/Watchdog" (CiA 301 life guard / heartbeat error)

# Ramps, in 0.1 Hz per second
ACCEL_FULL_CURRENT = 3000.0   # 300 Hz/s when the torque limit equals Max Iq
QUICKSTOP_DECEL = 4000.0      # 400 Hz/s quick stop / fault reaction ramp
COAST_DECEL = 500.0           # 50 Hz/s friction when the power stage is off


def s16(v):
    v &= 0xFFFF
    return v - 0x10000 if v & 0x8000 else v


def s32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


class Drive:
    """One SD2x axis: DS402 device control, velocity mode, watchdog."""

    # Constant / identification values
    HARDWARE_ID = 0x00002B21
    HARDWARE_VERSION = 0x00020010   # 2.16
    SOFTWARE_ID = 0x00000F3C
    SOFTWARE_VERSION = 0x00040012   # 4.18
    MAX_IQ = 250                    # 25.0 A
    MAX_SPEED = 13107               # 0x3FFF = speed scaling  -> ~800 Hz
    SPEED_SCALING = 60000000        # 60000.000 rpm (= 1000 Hz)
    CURRENT_SCALING = 40000         # 40.000 A
    TEMP_POWER_STAGE = 170          # 17.0 degC
    TEMP_MOTOR = 215                # 21.5 degC
    DC_VOLTAGE = 5650               # 565.0 V

    def __init__(self):
        self.lock = threading.RLock()
        self.state = SOD
        self.control_word = 0
        self.target_velocity = 0      # int16, 0.1 Hz
        self.torque_limit = 0         # int16, 0.1 A
        self.watchdog = 0             # uint16, ms
        self.watchdog_deadline = None
        self.error_code = 0
        self.speed = 0.0              # actual speed, 0.1 Hz (float internally)
        self.accelerating = False
        self.limit_active = False
        self.last_update = time.monotonic()

    # ------------------------------------------------------------- helpers
    def max_speed_01hz(self):
        # Max Speed is given so that 0x3FFF == Speed Scaling (0.001 rpm).
        rpm_x1000 = self.MAX_SPEED * self.SPEED_SCALING / 0x3FFF
        return int(round(rpm_x1000 / 1000.0 / 60.0 * 10.0))

    def power_stage_on(self):
        return self.state in (OE, QSA, FRA)

    # --------------------------------------------------------- simulation
    def update(self, now=None):
        with self.lock:
            if now is None:
                now = time.monotonic()
            dt = now - self.last_update
            if dt < 0:
                dt = 0.0
            self.last_update = now

            # watchdog
            if self.watchdog_deadline is not None and now >= self.watchdog_deadline:
                self.watchdog_deadline = None   # disarmed until 3003 is rewritten
                self.raise_fault(ERR_WATCHDOG)

            # level-triggered evaluation of the control word
            self._apply_command(self.control_word, edge=False)

            # speed ramp
            self.limit_active = False
            if self.state == OE:
                lim = min(abs(self.torque_limit), self.MAX_IQ)
                if self.control_word & 0x0100:        # halt
                    target = 0.0
                else:
                    vmax = self.max_speed_01hz()
                    target = float(max(-vmax, min(vmax, self.target_velocity)))
                    if target != self.target_velocity:
                        self.limit_active = True
                if lim == 0:
                    target, rate = 0.0, COAST_DECEL
                else:
                    rate = ACCEL_FULL_CURRENT * lim / self.MAX_IQ
            elif self.state in (QSA, FRA):
                target, rate = 0.0, QUICKSTOP_DECEL
            else:
                target, rate = 0.0, COAST_DECEL
            step = rate * dt
            diff = target - self.speed
            if abs(diff) <= step:
                self.speed = target
                self.accelerating = False
            else:
                self.speed += step if diff > 0 else -step
                self.accelerating = True

            if self.state == QSA and self.speed == 0.0:
                self.state = SOD          # quick stop option code 2
            if self.state == FRA and self.speed == 0.0:
                self.state = FAULT

    def raise_fault(self, code):
        with self.lock:
            if self.state in (FAULT, FRA):
                return
            self.error_code = code
            if self.power_stage_on() and self.speed != 0.0:
                self.state = FRA
            else:
                self.state = FAULT

    # ----------------------------------------------------- DS402 commands
    def _apply_command(self, cw, edge):
        st = self.state
        if st == FAULT:
            if edge:
                self.error_code = 0
                self.state = SOD          # transition 15
            return
        if st in (FRA, NOT_READY):
            return
        b0 = cw & 1
        b1 = (cw >> 1) & 1
        b2 = (cw >> 2) & 1
        b3 = (cw >> 3) & 1
        if cw & 0x80:
            # fault reset bit set: DS402 gives it priority; no other command
            return
        disable_voltage = b1 == 0
        quick_stop = b1 == 1 and b2 == 0
        shutdown = b2 == 1 and b1 == 1 and b0 == 0
        switch_on = b3 == 0 and b2 == 1 and b1 == 1 and b0 == 1
        enable_op = b3 == 1 and b2 == 1 and b1 == 1 and b0 == 1
        if st == SOD:
            if shutdown:
                self.state = RTSO                      # 2
        elif st == RTSO:
            if disable_voltage or quick_stop:
                self.state = SOD                       # 7
            elif switch_on:
                self.state = SO                        # 3
            elif enable_op:
                self.state = OE                        # 3 + 4
        elif st == SO:
            if disable_voltage or quick_stop:
                self.state = SOD                       # 10
            elif shutdown:
                self.state = RTSO                      # 6
            elif enable_op:
                self.state = OE                        # 4
        elif st == OE:
            if disable_voltage:
                self.state = SOD                       # 9
            elif quick_stop:
                self.state = QSA                       # 11
            elif shutdown:
                self.state = RTSO                      # 8
            elif switch_on:
                self.state = SO                        # 5
        elif st == QSA:
            if disable_voltage:
                self.state = SOD                       # 12

    def write_control_word(self, value):
        with self.lock:
            self.update()
            old = self.control_word
            self.control_word = value & 0xFFFF
            edge = bool(value & 0x80) and not (old & 0x80)
            self._apply_command(self.control_word, edge)

    def write_watchdog(self, value):
        with self.lock:
            self.watchdog = value & 0xFFFF
            if self.watchdog == 0:
                self.watchdog_deadline = None
            else:
                self.watchdog_deadline = time.monotonic() + self.watchdog / 1000.0

    # ----------------------------------------------------- actual values
    def status_word(self):
        sw = _STATE_BITS[self.state]
        sw |= 0x0010            # voltage enabled (DC link present)
        sw |= 0x0200            # remote: control channel is Modbus
        if self.state == OE:
            if self.control_word & 0x0100:
                reached = self.speed == 0.0
            else:
                vmax = self.max_speed_01hz()
                tgt = max(-vmax, min(vmax, self.target_velocity))
                reached = abs(self.speed - tgt) < 0.5
        else:
            reached = self.speed == 0.0
        if reached:
            sw |= 0x0400
        if self.limit_active:
            sw |= 0x0800
        return sw

    def actual_speed(self):
        return int(round(self.speed))

    def apparent_current(self):
        if not self.power_stage_on():
            return 0
        lim = min(abs(self.torque_limit), self.MAX_IQ)
        if self.accelerating and self.state == OE:
            return max(lim, 10)
        if self.accelerating:
            return self.MAX_IQ // 2
        return int(round(10 + abs(self.speed) / 100.0))     # 1 A magnetising + load

    def output_voltage(self):
        if not self.power_stage_on():
            return 0
        return int(round(abs(self.speed) * 0.4))

    def output_power(self):
        v = self.output_voltage() / 10.0
        i = self.apparent_current() / 10.0
        p_kw = 1.732 * v * i * 0.8 / 1000.0
        return int(round(p_kw * 10.0))



# index -> (name, type, access, getter, setter)
OBJECTS = {
    2: ("Hardware ID", "U32", "ro", lambda d: d.HARDWARE_ID, None),
    5: ("Hardware Version", "U32", "ro", lambda d: d.HARDWARE_VERSION, None),
    16: ("Software ID", "U32", "ro", lambda d: d.SOFTWARE_ID, None),
    17: ("Software Version", "U32", "ro", lambda d: d.SOFTWARE_VERSION, None),
    33: ("DC Voltage", "I16", "ro", lambda d: d.DC_VOLTAGE, None),
    41: ("Temperature Power Stage", "I16", "ro", lambda d: d.TEMP_POWER_STAGE, None),
    63: ("Temperature Motor", "I16", "ro", lambda d: d.TEMP_MOTOR, None),
    67: ("Status Word", "U16", "ro", lambda d: d.status_word(), None),
    68: ("Control Word", "U16", "rw", lambda d: d.control_word,
         lambda d, v: d.write_control_word(v)),
    70: ("Error Code", "U16", "ro", lambda d: d.error_code, None),
    120: ("Max Speed", "I16", "ro", lambda d: d.MAX_SPEED, None),
    168: ("Actual Speed", "I16", "ro", lambda d: d.actual_speed(), None),
    171: ("Max Iq Current", "I16", "ro", lambda d: d.MAX_IQ, None),
    177: ("Speed Scaling", "I32", "ro", lambda d: d.SPEED_SCALING, None),
    182: ("Current Scaling", "I32", "ro", lambda d: d.CURRENT_SCALING, None),
    209: ("Target Torque Limit", "I16", "rw", lambda d: d.torque_limit,
          lambda d, v: setattr(d, "torque_limit", s16(v))),
    210: ("Target Velocity", "I16", "rw", lambda d: d.target_velocity,
          lambda d, v: setattr(d, "target_velocity", s16(v))),
    390: ("Actual Output Power", "I16", "ro", lambda d: d.output_power(), None),
    431: ("Actual Apparent Current", "I16", "ro", lambda d: d.apparent_current(), None),
    434: ("Output Voltage", "I16", "ro", lambda d: d.output_voltage(), None),
}

_TYPE_SIZE = {"U16": 2, "I16": 2, "U32": 4, "I32": 4}

# Modbus register map: address -> (object index or "watchdog", word: 0 = only/high, 1 = low)
TXPDO_BASE = 2000
RXPDO_BASE = 3000
TXPDO = [  # (first register, object index)
    (2000, 67), (2001, 168), (2002, 209), (2003, 431), (2004, 390), (2005, 70),
    (2006, 41), (2007, 63), (2008, 434), (2009, 33), (2010, 2), (2012, 5),
    (2014, 16), (2016, 17), (2018, 171), (2019, 120), (2020, 177), (2022, 182),
]
RXPDO = [(3000, 68), (3001, 210), (3002, 209), (3003, "watchdog")]

REGISTER_MAP = {}
for _addr, _obj in TXPDO:
    _size = _TYPE_SIZE[OBJECTS[_obj][1]]
    REGISTER_MAP[_addr] = (_obj, 0, _size, False)
    if _size == 4:
        REGISTER_MAP[_addr + 1] = (_obj, 1, _size, False)
for _addr, _obj in RXPDO:
    REGISTER_MAP[_addr] = (_obj, 0, 2, True)


def obj_raw(drive, index):
    name, typ, acc, getter, setter = OBJECTS[index]
    v = getter(drive)
    return v & (0xFFFF if _TYPE_SIZE[typ] == 2 else 0xFFFFFFFF)


def reg_read(drive, addr):
    obj, word, size, _w = REGISTER_MAP[addr]
    if obj == "watchdog":
        return drive.watchdog
    raw = obj_raw(drive, obj)
    if size == 2:
        return raw
    return (raw >> 16) & 0xFFFF if word == 0 else raw & 0xFFFF


def reg_write(drive, addr, value):
    obj = REGISTER_MAP[addr][0]
    if obj == "watchdog":
        drive.write_watchdog(value)
    else:
        OBJECTS[obj][4](drive, value)


# ---------------------------------------------------------------------------
# Modbus slave (protocol layer, shared by all transports)
# ---------------------------------------------------------------------------

MAX_REGS = 48
COUNTER_NAMES = ("bus_message_count", "bus_communication_error_count",
                 "bus_exception_error_count", "slave_message_count",
                 "slave_no_response_count")


class Slave:
    def __init__(self, drive, address, serial_cfg=None):
        self.drive = drive
        self.address = address
        self.serial_cfg = serial_cfg
        self.lock = drive.lock
        self.counters = dict.fromkeys(COUNTER_NAMES, 0)

    def _inc(self, name):
        self.counters[name] = (self.counters[name] + 1) & 0xFFFF

    # ------------------------------------------------------------ framing
    def handle_frame(self, frame):
        """Process one complete RTU frame. Returns the response frame or None."""
        with self.lock:
            if len(frame) < 4 or not crc_ok(frame):
                self._inc("bus_communication_error_count")
                return None
            self._inc("bus_message_count")
            addr = frame[0]
            if addr != 0 and addr != self.address:
                return None
            broadcast = addr == 0
            self._inc("slave_message_count")
            if broadcast:
                self._inc("slave_no_response_count")
            pdu = bytes(frame[1:-2])
            self.drive.update()
            try:
                resp = self.dispatch(pdu, broadcast)
            except ModbusException as e:
                resp = bytes((pdu[0] | 0x80, e.code))
            except Exception:  # never let a request kill the server
                resp = bytes((pdu[0] | 0x80, SLAVE_DEVICE_FAILURE))
            if broadcast or resp is None:
                return None
            if resp[0] & 0x80:
                self._inc("bus_exception_error_count")
            return add_crc(bytes((self.address,)) + resp)

    # ----------------------------------------------------------- dispatch
    def dispatch(self, pdu, broadcast):
        fc = pdu[0]
        handler = {
            0x03: self.fc_read, 0x04: self.fc_read, 0x06: self.fc06,
            0x08: self.fc08, 0x10: self.fc16, 0x17: self.fc23, 0x2B: self.fc43,
        }.get(fc)
        if handler is None:
            if broadcast:
                return None
            raise ModbusException(ILLEGAL_FUNCTION)
        return handler(pdu, broadcast)

    @staticmethod
    def _check_range(addr, qty, write):
        for a in range(addr, addr + qty):
            ent = REGISTER_MAP.get(a)
            if ent is None or (write and not ent[3]):
                raise ModbusException(ILLEGAL_DATA_ADDRESS)

    def fc_read(self, pdu, broadcast):
        if broadcast:
            return None
        if len(pdu) != 5:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        addr = (pdu[1] << 8) | pdu[2]
        qty = (pdu[3] << 8) | pdu[4]
        if not 1 <= qty <= MAX_REGS:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        self._check_range(addr, qty, write=False)
        out = bytearray((pdu[0], qty * 2))
        for a in range(addr, addr + qty):
            v = reg_read(self.drive, a)
            out += bytes((v >> 8, v & 0xFF))
        return bytes(out)

    def fc06(self, pdu, broadcast):
        if len(pdu) != 5:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        addr = (pdu[1] << 8) | pdu[2]
        value = (pdu[3] << 8) | pdu[4]
        self._check_range(addr, 1, write=True)
        reg_write(self.drive, addr, value)
        return pdu

    def fc16(self, pdu, broadcast):
        if len(pdu) < 6:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        addr = (pdu[1] << 8) | pdu[2]
        qty = (pdu[3] << 8) | pdu[4]
        bc = pdu[5]
        if not 1 <= qty <= MAX_REGS or bc != 2 * qty or len(pdu) != 6 + bc:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        self._check_range(addr, qty, write=True)
        for i in range(qty):
            reg_write(self.drive, addr + i, (pdu[6 + 2 * i] << 8) | pdu[7 + 2 * i])
        return pdu[:5]

    def fc23(self, pdu, broadcast):
        if broadcast:
            return None
        if len(pdu) < 10:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        raddr = (pdu[1] << 8) | pdu[2]
        rqty = (pdu[3] << 8) | pdu[4]
        waddr = (pdu[5] << 8) | pdu[6]
        wqty = (pdu[7] << 8) | pdu[8]
        bc = pdu[9]
        if (not 1 <= rqty <= MAX_REGS or not 1 <= wqty <= MAX_REGS
                or bc != 2 * wqty or len(pdu) != 10 + bc):
            raise ModbusException(ILLEGAL_DATA_VALUE)
        self._check_range(waddr, wqty, write=True)
        self._check_range(raddr, rqty, write=False)
        for i in range(wqty):
            reg_write(self.drive, waddr + i, (pdu[10 + 2 * i] << 8) | pdu[11 + 2 * i])
        self.drive.update()
        out = bytearray((pdu[0], rqty * 2))
        for a in range(raddr, raddr + rqty):
            v = reg_read(self.drive, a)
            out += bytes((v >> 8, v & 0xFF))
        return bytes(out)

    def fc08(self, pdu, broadcast):
        if len(pdu) != 5:
            if broadcast:
                return None
            raise ModbusException(ILLEGAL_DATA_VALUE)
        sub = (pdu[1] << 8) | pdu[2]
        if sub == 0x0000:
            return None if broadcast else pdu
        if sub == 0x000A:
            for k in self.counters:
                self.counters[k] = 0
            return pdu
        if broadcast:
            return None
        names = {0x0B: "bus_message_count", 0x0C: "bus_communication_error_count",
                 0x0D: "bus_exception_error_count", 0x0E: "slave_message_count",
                 0x0F: "slave_no_response_count"}
        if sub not in names:
            raise ModbusException(ILLEGAL_FUNCTION)
        v = self.counters[names[sub]]
        return bytes((0x08, pdu[1], pdu[2], v >> 8, v & 0xFF))

    # -------------------------------------------- FC 43 / MEI 0x0D (CANopen)
    def fc43(self, pdu, broadcast):
        if len(pdu) < 2:
            if broadcast:
                return None
            raise ModbusException(ILLEGAL_DATA_VALUE)
        if pdu[1] != 0x0D:
            if broadcast:
                return None
            raise ModbusException(ILLEGAL_FUNCTION)
        # 2B 0D ctrl reserved node idxH idxL sub offH offL cntH cntL [data]
        if len(pdu) < 12:
            if broadcast:
                return None
            raise ModbusException(ILLEGAL_DATA_VALUE)
        ctrl, reserved, node = pdu[2], pdu[3], pdu[4]
        index = (pdu[5] << 8) | pdu[6]
        sub = pdu[7]
        offset = (pdu[8] << 8) | pdu[9]
        count = (pdu[10] << 8) | pdu[11]
        write = bool(ctrl & 0x80)
        if broadcast and not write:
            return None
        if (ctrl & 0x7F) or reserved != 0 or count > 4:
            if broadcast:
                return None
            raise ModbusException(ILLEGAL_DATA_VALUE)
        expected = 12 + (count if write else 0)
        if len(pdu) != expected:
            if broadcast:
                return None
            raise ModbusException(ILLEGAL_DATA_VALUE)
        if node != self.address:
            if broadcast:
                return None
            raise ModbusException(ILLEGAL_DATA_ADDRESS)
        header = bytes(pdu[:10])
        try:
            ent = OBJECTS.get(index)
            if ent is None:
                raise SdoError(SDO_NO_OBJECT)
            name, typ, acc, getter, setter = ent
            size = _TYPE_SIZE[typ]
            if sub != 0:
                raise SdoError(SDO_NO_SUBINDEX)
            if offset != 0:
                raise SdoError(SDO_UNSUPPORTED_ACCESS)
            if write:
                if acc == "ro":
                    raise SdoError(SDO_WRITE_READ_ONLY)
                if count > size:
                    raise SdoError(SDO_LEN_TOO_LONG)
                if count < size:
                    raise SdoError(SDO_LEN_TOO_SHORT)
                value = int.from_bytes(pdu[12:12 + count], "little")
                setter(self.drive, value)
                if broadcast:
                    return None
                return bytes(pdu)
            if acc == "wo":
                raise SdoError(SDO_READ_WRITE_ONLY)
            n = count if count else size
            if n > size:
                raise SdoError(SDO_LEN_TOO_LONG)
            if n < size:
                raise SdoError(SDO_LEN_TOO_SHORT)
            raw = obj_raw(self.drive, index)
            return header + bytes((n >> 8, n & 0xFF)) + raw.to_bytes(size, "little")
        except SdoError as e:
            if broadcast:
                return None
            return bytes((0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + e.code.to_bytes(4, "little")

    # ----------------------------------------------------------- state
    def snapshot(self):
        d = self.drive
        with self.lock:
            d.update()
            regs = {}
            for a in sorted(REGISTER_MAP):
                obj, word, size, writable = REGISTER_MAP[a]
                regs[str(a)] = {
                    "value": reg_read(d, a),
                    "access": "rw" if writable else "ro",
                    "object": obj if obj == "watchdog" else "%d" % obj,
                }
            objs = {}
            for idx in sorted(OBJECTS):
                name, typ, acc, getter, setter = OBJECTS[idx]
                objs["%d:0" % idx] = {
                    "name": name, "type": typ, "access": acc,
                    "value": getter(d),
                }
            return {
                "device": "SIEB & MEYER SD2x (simulated)",
                "settings": {
                    "slave_address": self.address,
                    "serial": self.serial_cfg,
                },
                "registers": regs,
                "objects": objs,
                "drive": {
                    "ds402_state": d.state,
                    "watchdog_ms": d.watchdog,
                    "watchdog_armed": d.watchdog_deadline is not None,
                    "error_code": d.error_code,
                    "actual_speed_0_1Hz": d.actual_speed(),
                },
                "diagnostic_counters": dict(self.counters),
            }


# ---------------------------------------------------------------------------
# Frame length prediction for stream transports
# ---------------------------------------------------------------------------

def predict_length(buf):
    """Length of the RTU frame starting at buf[0], 0 if more bytes are needed
    to know it, None if it cannot be predicted (unknown function code)."""
    if len(buf) < 2:
        return 0
    fc = buf[1]
    if fc in (0x03, 0x04, 0x06, 0x08):
        return 8
    if fc == 0x10:
        return 0 if len(buf) < 7 else 9 + buf[6]
    if fc == 0x17:
        return 0 if len(buf) < 11 else 13 + buf[10]
    if fc == 0x2B:
        if len(buf) < 3:
            return 0
        if buf[2] != 0x0D:
            return None
        if len(buf) < 13:
            return 0
        n = (buf[11] << 8) | buf[12]
        return 15 + (n if buf[3] & 0x80 and n <= 4 else 0)
    return None


# ---------------------------------------------------------------------------
# TCP transport (raw RTU frames on a stream)
# ---------------------------------------------------------------------------

TCP_SILENCE = 0.05      # seconds of stream silence that end an unfinished frame
MAX_BUF = 512


def serve_tcp_conn(slave, sock, stop):
    buf = bytearray()
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except OSError:
        pass
    try:
        while not stop.is_set():
            # fast path: complete frames of predictable length with a good CRC
            while buf:
                n = predict_length(buf)
                if not n or n > len(buf):
                    break
                if not crc_ok(buf[:n]):
                    break
                resp = slave.handle_frame(bytes(buf[:n]))
                del buf[:n]
                if resp:
                    sock.sendall(resp)
            timeout = TCP_SILENCE if buf else 0.5
            r, _, _ = select.select([sock], [], [], timeout)
            if not r:
                if buf:
                    # silence: whatever is buffered is one (bad or odd) frame
                    frame = bytes(buf)
                    buf.clear()
                    resp = slave.handle_frame(frame)
                    if resp:
                        sock.sendall(resp)
                continue
            data = sock.recv(4096)
            if not data:
                break
            buf += data
            if len(buf) > MAX_BUF:
                # not Modbus: drop it (counts as a communication error)
                buf.clear()
                with slave.lock:
                    slave._inc("bus_communication_error_count")
    except (OSError, ValueError):
        pass
    finally:
        try:
            sock.close()
        except OSError:
            pass


def tcp_acceptor(slave, lsock, stop):
    while not stop.is_set():
        try:
            r, _, _ = select.select([lsock], [], [], 0.5)
            if not r:
                continue
            conn, _ = lsock.accept()
        except OSError:
            if stop.is_set():
                return
            time.sleep(0.05)
            continue
        t = threading.Thread(target=serve_tcp_conn, args=(slave, conn, stop), daemon=True)
        t.start()


# ---------------------------------------------------------------------------
# Serial transport (RTU, frames delimited by t3.5)
# ---------------------------------------------------------------------------

BAUD_RATES = (9600, 14400, 19200, 28800, 38400, 57600, 115200)


def t35_seconds(baud, parity):
    if baud > 19200:
        return 0.00175
    bits = 11 if parity != "none" else 10   # start + 8 data + parity + 1 stop
    return 3.5 * bits / baud


def open_serial(path, baud, parity):
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    attrs = termios.tcgetattr(fd)
    iflag, oflag, cflag, lflag, ispeed, ospeed, cc = attrs
    iflag &= ~(termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP |
               termios.INLCR | termios.IGNCR | termios.ICRNL | termios.IXON |
               termios.IXOFF | termios.INPCK)
    oflag &= ~termios.OPOST
    lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG |
               termios.IEXTEN)
    cflag &= ~(termios.CSIZE | termios.PARENB | termios.PARODD | termios.CSTOPB)
    cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
    if parity in ("even", "odd"):
        cflag |= termios.PARENB
        iflag |= termios.INPCK
        if parity == "odd":
            cflag |= termios.PARODD
    speed = getattr(termios, "B%d" % baud, None)
    if speed is not None:
        ispeed = ospeed = speed
    cc = list(cc)
    cc[termios.VMIN] = 0
    cc[termios.VTIME] = 0
    try:
        termios.tcsetattr(fd, termios.TCSANOW,
                          [iflag, oflag, cflag, lflag, ispeed, ospeed, cc])
    except termios.error:
        pass
    return fd


def write_all(fd, data, stop):
    view = memoryview(data)
    deadline = time.monotonic() + 2.0
    while view and not stop.is_set() and time.monotonic() < deadline:
        try:
            n = os.write(fd, view)
            view = view[n:]
        except BlockingIOError:
            select.select([], [fd], [], 0.05)
        except OSError:
            return


def serial_loop(slave, fd, t35, stop):
    buf = bytearray()
    overflow = False
    last = 0.0
    while not stop.is_set():
        if buf or overflow:
            timeout = max(0.0, last + t35 - time.monotonic())
        else:
            timeout = 0.5
        try:
            r, _, _ = select.select([fd], [], [], timeout)
        except (OSError, ValueError):
            time.sleep(0.1)
            continue
        if r:
            try:
                data = os.read(fd, 512)
            except BlockingIOError:
                continue
            except OSError:
                # peer side of the pty not open (EIO): wait and retry
                time.sleep(0.05)
                continue
            if not data:
                time.sleep(0.01)
                continue
            last = time.monotonic()
            if not overflow:
                buf += data
                if len(buf) > 256:        # longer than any RTU ADU
                    overflow = True
                    buf.clear()
            continue
        # silence >= t3.5: end of frame
        if time.monotonic() - last < t35:
            continue
        if overflow:
            overflow = False
            with slave.lock:
                slave._inc("bus_communication_error_count")
            continue
        if buf:
            frame = bytes(buf)
            buf.clear()
            resp = slave.handle_frame(frame)
            if resp:
                write_all(fd, resp, stop)


# ---------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------

def ticker(drive, stop):
    while not stop.wait(0.005):
        try:
            drive.update()
        except Exception:
            pass


def write_state(slave, path):
    if not path:
        return
    try:
        data = json.dumps(slave.snapshot(), indent=1, sort_keys=True)
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            f.write(data)
            f.write("\n")
        os.replace(tmp, path)
    except Exception as e:  # pragma: no cover
        print("state dump failed: %s" % e, file=sys.stderr, flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description="SIEB & MEYER SD2x Modbus RTU simulator")
    ap.add_argument("--listen", help="HOST:PORT (loopback) for RTU frames over TCP")
    ap.add_argument("--serial", help="serial device path")
    ap.add_argument("--baud", type=int, default=19200)
    ap.add_argument("--parity", choices=("even", "odd", "none"), default="none")
    ap.add_argument("--address", type=int, default=1)
    ap.add_argument("--state", help="JSON state file")
    args = ap.parse_args(argv)

    if not args.listen and not args.serial:
        ap.error("give --listen and/or --serial")
    if not 1 <= args.address <= 254:
        ap.error("--address must be 1..254")
    if args.baud not in BAUD_RATES:
        ap.error("--baud must be one of %s" % ", ".join(map(str, BAUD_RATES)))

    drive = Drive()
    serial_cfg = None
    if args.serial:
        serial_cfg = {"path": args.serial, "baud": args.baud, "parity": args.parity,
                      "stop_bits": 1}
    slave = Slave(drive, args.address, serial_cfg)
    stop = threading.Event()

    lsock = None
    if args.listen:
        host, _, port = args.listen.rpartition(":")
        host = host.strip("[]")
        if host not in ("127.0.0.1", "localhost", "::1") and not host.startswith("127."):
            ap.error("--listen must be a loopback address")
        fam = socket.AF_INET6 if ":" in host else socket.AF_INET
        lsock = socket.socket(fam, socket.SOCK_STREAM)
        lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        lsock.bind((host, int(port)))
        lsock.listen(16)

    fd = None
    if args.serial:
        fd = open_serial(args.serial, args.baud, args.parity)

    def on_term(signum, frame):
        stop.set()

    def on_usr1(signum, frame):
        write_state(slave, args.state)

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    signal.signal(signal.SIGUSR1, on_usr1)

    threading.Thread(target=ticker, args=(drive, stop), daemon=True).start()
    if lsock is not None:
        threading.Thread(target=tcp_acceptor, args=(slave, lsock, stop), daemon=True).start()
        print("listening tcp %s:%d" % (args.listen.rpartition(":")[0],
                                       lsock.getsockname()[1]), flush=True)
    if fd is not None:
        t35 = t35_seconds(args.baud, args.parity)
        threading.Thread(target=serial_loop, args=(slave, fd, t35, stop), daemon=True).start()
        print("listening serial %s" % args.serial, flush=True)

    while not stop.is_set():
        stop.wait(0.2)

    write_state(slave, args.state)
    try:
        if lsock is not None:
            lsock.close()
        if fd is not None:
            os.close(fd)
    except OSError:
        pass
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
