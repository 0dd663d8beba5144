#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier -- Modbus RTU slave simulator.

Written from "Drive Amplifier SD2x - Modbus RTU Connection" and the public
Modbus specifications (Application Protocol V1.1b3, Serial Line V1.02) plus
CiA 402 conventions.  Standard library only.

Transports (one process, one of):
  --listen 127.0.0.1:PORT   RTU frames (address + PDU + CRC) on a TCP stream
  --serial PATH             RTU on a serial device (termios, raw)

See README.md and DECISIONS.md.
"""

import argparse
import json
import math
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


def add_crc(frame):
    c = crc16(frame)
    return bytes(frame) + bytes((c & 0xFF, c >> 8))


def crc_ok(frame):
    if len(frame) < 4:
        return False
    c = crc16(frame[:-2])
    return frame[-2] == (c & 0xFF) and frame[-1] == (c >> 8)


# ---------------------------------------------------------------------------
# Modbus constants
# ---------------------------------------------------------------------------

EXC_ILLEGAL_FUNCTION = 0x01
EXC_ILLEGAL_ADDRESS = 0x02
EXC_ILLEGAL_VALUE = 0x03
EXC_DEVICE_FAILURE = 0x04

MAX_REGS = 48            # manual: n = 1 to 48 (30h) for FC 03/04/16/23
MAX_RTU_FRAME = 256      # Serial Line spec: RTU ADU max 256 bytes

TXPDO_BASE = 2000
TXPDO_WORDS = 24         # 2000 .. 2023
RXPDO_BASE = 3000
RXPDO_WORDS = 4          # 3000 .. 3003

# SDO error codes (manual chapter 3.8)
SDO_CMD_INVALID = 0xFFFF0003
SDO_UNSUPPORTED_ACCESS = 0xFFFF0008
SDO_WRITE_ONLY = 0xFFFF0009
SDO_READ_ONLY = 0xFFFF000A
SDO_NO_OBJECT = 0xFFFF000B
SDO_LEN_MISMATCH = 0xFFFF0011
SDO_LEN_TOO_LONG = 0xFFFF0012
SDO_LEN_TOO_SHORT = 0xFFFF0013
SDO_NO_SUBINDEX = 0xFFFF0014
SDO_GENERAL = 0xFFFF0019


class ModbusException(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


class SdoAbort(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# ---------------------------------------------------------------------------
# Drive model
# ---------------------------------------------------------------------------

# DS402 states
NOT_READY = "NOT_READY_TO_SWITCH_ON"
SO_DISABLED = "SWITCH_ON_DISABLED"
READY = "READY_TO_SWITCH_ON"
SWITCHED_ON = "SWITCHED_ON"
OP_ENABLED = "OPERATION_ENABLED"
QUICK_STOP = "QUICK_STOP_ACTIVE"
FAULT_REACTION = "FAULT_REACTION_ACTIVE"
FAULT = "FAULT"

# DS402 error code for "Heartbeat/Watchdog" (CiA 301 EMCY 8130h, life guard
# / heartbeat error); object 70 maps DS402 0x603F.
ERR_WATCHDOG = 0x8130

# Simulated plant (units of the objects: 0.1 Hz, 0.1 A, 0.1 V, 0.1 kW)
ACCEL = 2000.0           # 0.1 Hz / s   (200 Hz/s) normal ramp
QS_DECEL = 10000.0       # 0.1 Hz / s   (1000 Hz/s) quick stop / fault reaction
COAST_DECEL = 500.0      # 0.1 Hz / s   (50 Hz/s) power stage off: free run-down

SPEED_SCALING = 60000000     # object 177, 0.001 rpm -> 60 000 rpm = 1000 Hz
MAX_SPEED = 0x3FFF           # object 120, 0x3FFF = speed scaling
CURRENT_SCALING = 60000      # object 182, 0.001 A -> 60 A
MAX_IQ = 300                 # object 171, 0.1 A -> 30.0 A
HW_ID = 0x00002100           # object 2
HW_VERSION = 0x00020010      # object 5 (2.16, manual example)
SW_ID = 0x00007310           # object 16
SW_VERSION = 0x00040012      # object 17 (4.18)
DC_VOLTAGE = 5650            # object 33, 565.0 V
TEMP_STAGE = 170             # object 41, 17.0 degC (manual example 6.2)
TEMP_MOTOR = 215             # object 63, 21.5 degC


def _to_signed(v, bits):
    v &= (1 << bits) - 1
    if v & (1 << (bits - 1)):
        v -= 1 << bits
    return v


class ObjDef:
    __slots__ = ("index", "name", "dtype", "access")

    def __init__(self, index, name, dtype, access):
        self.index = index
        self.name = name
        self.dtype = dtype      # 'u16', 'i16', 'u32', 'i32'
        self.access = access    # 'rw' or 'ro'

    @property
    def size(self):
        return 2 if self.dtype.endswith("16") else 4

    @property
    def signed(self):
        return self.dtype.startswith("i")


OBJECTS = {o.index: o for o in (
    ObjDef(2, "Hardware ID", "u32", "ro"),
    ObjDef(5, "Hardware Version", "u32", "ro"),
    ObjDef(16, "Software ID", "u32", "ro"),
    ObjDef(17, "Software Version", "u32", "ro"),
    ObjDef(33, "DC Voltage", "i16", "ro"),
    ObjDef(41, "Temperature Power Stage", "i16", "ro"),
    ObjDef(63, "Temperature Motor", "i16", "ro"),
    ObjDef(67, "Status Word", "u16", "ro"),
    ObjDef(68, "Control Word", "u16", "rw"),
    ObjDef(70, "Error Code", "u16", "ro"),
    ObjDef(120, "Max Speed", "i16", "ro"),
    ObjDef(168, "Actual Speed", "i16", "ro"),
    ObjDef(171, "Max Iq Current", "i16", "ro"),
    ObjDef(177, "Speed Scaling", "i32", "ro"),
    ObjDef(182, "Current Scaling", "i32", "ro"),
    ObjDef(209, "Target Torque Limit", "i16", "rw"),
    ObjDef(210, "Target Velocity", "i16", "rw"),
    ObjDef(390, "Actual Output Power", "i16", "ro"),
    ObjDef(431, "Actual Apparent Current", "i16", "ro"),
    ObjDef(434, "Output Voltage", "i16", "ro"),
)}

# Default TxPDO mapping (manual 4.2): register -> (object index, words)
TXPDO_MAP = [
    (2000, 67, 1), (2001, 168, 1), (2002, 209, 1), (2003, 431, 1),
    (2004, 390, 1), (2005, 70, 1), (2006, 41, 1), (2007, 63, 1),
    (2008, 434, 1), (2009, 33, 1), (2010, 2, 2), (2012, 5, 2),
    (2014, 16, 2), (2016, 17, 2), (2018, 171, 1), (2019, 120, 1),
    (2020, 177, 2), (2022, 182, 2),
]
TXPDO_NAMES = {
    2000: "Status Word", 2001: "Actual Speed", 2002: "Torque Limit Iq",
    2003: "Act Apparent Current", 2004: "Act Output Power", 2005: "Error Code",
    2006: "Temp Power Stage", 2007: "Temp Motor", 2008: "Output Voltage",
    2009: "DC Voltage", 2010: "Hardware ID", 2012: "Hardware Version",
    2014: "Software ID", 2016: "Software Version", 2018: "Max Iq Current",
    2019: "Max Speed", 2020: "Speed Scaling", 2022: "Current Scaling",
}
# Default RxPDO mapping (manual 4.1): register -> object index (None = watchdog)
RXPDO_MAP = {3000: 68, 3001: 210, 3002: 209, 3003: None}
RXPDO_NAMES = {3000: "Control Word", 3001: "Target Speed",
               3002: "Torque Limit Iq", 3003: "Watchdog"}


class Drive:
    def __init__(self):
        self.lock = threading.RLock()
        # writable objects
        self.controlword = 0
        self.target_velocity = 0      # signed, 0.1 Hz
        self.torque_limit = 0         # signed, 0.1 A
        self.watchdog_ms = 0
        # watchdog supervision
        self.wd_armed = False
        self.wd_deadline = 0.0
        self.wd_tripped = False
        # DS402
        self.state = NOT_READY
        self.error_code = 0
        self.speed = 0.0              # 0.1 Hz, float internally
        self.ramping = False
        self.last_tick = time.monotonic()
        # Boot: NOT READY TO SWITCH ON -> (transition 1, automatic)
        # SWITCH ON DISABLED once the self test has passed.
        self.state = SO_DISABLED

    # ----- derived values ------------------------------------------------
    def _power_on(self):
        return self.state in (OP_ENABLED, QUICK_STOP, FAULT_REACTION)

    def _current_limit(self):
        return min(abs(self.torque_limit), MAX_IQ)

    def _max_speed_units(self):
        # MAX_SPEED / 0x3FFF * SPEED_SCALING [0.001 rpm] -> 0.1 Hz
        rpm = MAX_SPEED / 0x3FFF * SPEED_SCALING / 1000.0
        return int(round(rpm / 60.0 * 10.0))

    def _effective_target(self):
        if self.state != OP_ENABLED or (self.controlword & 0x0100):
            return 0
        ms = self._max_speed_units()
        return max(-ms, min(ms, self.target_velocity))

    def actual_speed(self):
        return int(round(self.speed))

    def apparent_current(self):
        if not self._power_on():
            return 0
        lim = self._current_limit()
        if lim == 0:
            return 0
        nominal = 15 + abs(self.speed) / 100.0 + (50 if self.ramping else 0)
        return int(round(min(lim, nominal)))

    def output_voltage(self):
        if not self._power_on():
            return 0
        return int(round(abs(self.speed) * 0.4))

    def output_power(self):
        u = self.output_voltage() / 10.0
        i = self.apparent_current() / 10.0
        kw = math.sqrt(3) * u * i * 0.85 / 1000.0
        return int(round(kw * 10))

    def statusword(self):
        s = self.state
        sw = 0
        if s == NOT_READY:
            sw = 0x0000
        elif s == SO_DISABLED:
            sw = 0x0040
        elif s == READY:
            sw = 0x0001
        elif s == SWITCHED_ON:
            sw = 0x0003
        elif s == OP_ENABLED:
            sw = 0x0007
        elif s == QUICK_STOP:
            sw = 0x0007
        elif s == FAULT_REACTION:
            sw = 0x000F
        elif s == FAULT:
            sw = 0x0008
        if s != NOT_READY:
            sw |= 0x0010                   # bit 4 voltage enabled (DC link)
        if s not in (QUICK_STOP, NOT_READY):
            sw |= 0x0020                   # bit 5 quick stop (1 = not active)
        sw |= 0x0200                       # bit 9 remote (Modbus is control channel)
        eff = self._effective_target()
        if s == OP_ENABLED and self.actual_speed() == eff:
            sw |= 0x0400                   # bit 10 target reached
        if s == QUICK_STOP and self.actual_speed() == 0:
            sw |= 0x0400
        if s == OP_ENABLED and (abs(self.target_velocity) > self._max_speed_units()
                                or (self._current_limit() == 0 and eff != 0)):
            sw |= 0x0800                   # bit 11 internal limit active
        if self.actual_speed() == 0:
            sw |= 0x1000                   # bit 12 (pv mode) speed = 0
        return sw

    # ----- time evolution ------------------------------------------------
    def tick(self):
        with self.lock:
            now = time.monotonic()
            dt = now - self.last_tick
            if dt < 0:
                dt = 0
            if dt > 1.0:
                dt = 1.0
            self.last_tick = now
            # watchdog supervision
            if self.wd_armed and now >= self.wd_deadline:
                self.wd_armed = False
                self.wd_tripped = True
                self._fault(ERR_WATCHDOG)
            # motion
            s = self.state
            if s == OP_ENABLED:
                target = self._effective_target()
                rate = ACCEL if self._current_limit() > 0 else 0.0
                if rate == 0.0:
                    target, rate = 0.0, COAST_DECEL
            elif s in (QUICK_STOP, FAULT_REACTION):
                target = 0.0
                rate = QS_DECEL if self._current_limit() > 0 else COAST_DECEL
            else:
                target, rate = 0.0, COAST_DECEL
            diff = target - self.speed
            step = rate * dt
            if abs(diff) <= step:
                self.speed = float(target)
                self.ramping = False
            else:
                self.speed += step if diff > 0 else -step
                self.ramping = True
            # automatic transitions
            if self.state == QUICK_STOP and self.actual_speed() == 0:
                self.state = SO_DISABLED          # transition 12 (QS option 2)
            if self.state == FAULT_REACTION and self.actual_speed() == 0:
                self.state = FAULT                # transition 14
            self._evaluate_command()

    def _fault(self, code):
        if self.state in (FAULT, FAULT_REACTION):
            return
        self.error_code = code
        self.state = FAULT_REACTION if self.actual_speed() != 0 else FAULT

    def _evaluate_command(self):
        """Level-triggered DS402 device control (CiA 402 command table)."""
        s = self.state
        cw = self.controlword
        if s in (FAULT, FAULT_REACTION, NOT_READY):
            return
        if cw & 0x0080:
            return          # all commands require bit 7 = 0
        if not cw & 0x0002:
            cmd = "disable_voltage"
        elif not cw & 0x0004:
            cmd = "quick_stop"
        elif not cw & 0x0001:
            cmd = "shutdown"
        elif not cw & 0x0008:
            cmd = "switch_on"
        else:
            cmd = "enable_operation"
        if s == SO_DISABLED:
            if cmd == "shutdown":
                self.state = READY                      # 2
        elif s == READY:
            if cmd in ("disable_voltage", "quick_stop"):
                self.state = SO_DISABLED                # 7
            elif cmd == "switch_on":
                self.state = SWITCHED_ON                # 3
            elif cmd == "enable_operation":
                self.state = OP_ENABLED                 # 3 + 4
        elif s == SWITCHED_ON:
            if cmd == "shutdown":
                self.state = READY                      # 6
            elif cmd in ("disable_voltage", "quick_stop"):
                self.state = SO_DISABLED                # 10
            elif cmd == "enable_operation":
                self.state = OP_ENABLED                 # 4
        elif s == OP_ENABLED:
            if cmd == "switch_on":
                self.state = SWITCHED_ON                # 5
            elif cmd == "shutdown":
                self.state = READY                      # 8
            elif cmd == "disable_voltage":
                self.state = SO_DISABLED                # 9
            elif cmd == "quick_stop":
                self.state = QUICK_STOP                 # 11
        elif s == QUICK_STOP:
            if cmd == "disable_voltage":
                self.state = SO_DISABLED                # 12

    def write_controlword(self, value):
        with self.lock:
            old = self.controlword
            self.controlword = value & 0xFFFF
            if self.state == FAULT and (value & 0x0080) and not (old & 0x0080):
                # transition 15: fault reset on rising edge of bit 7
                self.error_code = 0
                self.wd_tripped = False
                self.state = SO_DISABLED
            self._evaluate_command()

    def write_watchdog(self, value):
        with self.lock:
            self.watchdog_ms = value & 0xFFFF
            if self.watchdog_ms:
                self.wd_armed = True
                self.wd_deadline = time.monotonic() + self.watchdog_ms / 1000.0
            else:
                self.wd_armed = False

    # ----- object access -------------------------------------------------
    def get_object(self, index):
        if index == 2:
            return HW_ID
        if index == 5:
            return HW_VERSION
        if index == 16:
            return SW_ID
        if index == 17:
            return SW_VERSION
        if index == 33:
            return DC_VOLTAGE
        if index == 41:
            return TEMP_STAGE
        if index == 63:
            return TEMP_MOTOR
        if index == 67:
            return self.statusword()
        if index == 68:
            return self.controlword
        if index == 70:
            return self.error_code
        if index == 120:
            return MAX_SPEED
        if index == 168:
            return self.actual_speed()
        if index == 171:
            return MAX_IQ
        if index == 177:
            return SPEED_SCALING
        if index == 182:
            return CURRENT_SCALING
        if index == 209:
            return self.torque_limit
        if index == 210:
            return self.target_velocity
        if index == 390:
            return self.output_power()
        if index == 431:
            return self.apparent_current()
        if index == 434:
            return self.output_voltage()
        raise KeyError(index)

    def set_object(self, index, raw):
        """raw: unsigned bit pattern of the object's width."""
        if index == 68:
            self.write_controlword(raw)
        elif index == 209:
            self.torque_limit = _to_signed(raw, 16)
        elif index == 210:
            self.target_velocity = _to_signed(raw, 16)
        else:
            raise KeyError(index)

    # ----- process image --------------------------------------------------
    def txpdo_words(self):
        words = [0] * TXPDO_WORDS
        for reg, idx, n in TXPDO_MAP:
            v = self.get_object(idx)
            if n == 1:
                words[reg - TXPDO_BASE] = v & 0xFFFF
            else:
                v &= 0xFFFFFFFF
                words[reg - TXPDO_BASE] = v >> 16          # high word first
                words[reg - TXPDO_BASE + 1] = v & 0xFFFF
        return words

    def rxpdo_words(self):
        return [self.controlword & 0xFFFF, self.target_velocity & 0xFFFF,
                self.torque_limit & 0xFFFF, self.watchdog_ms & 0xFFFF]

    def read_registers(self, start, count):
        """Returns list of words or raises ModbusException(02)."""
        end = start + count
        if TXPDO_BASE <= start and end <= TXPDO_BASE + TXPDO_WORDS:
            return self.txpdo_words()[start - TXPDO_BASE:end - TXPDO_BASE]
        if RXPDO_BASE <= start and end <= RXPDO_BASE + RXPDO_WORDS:
            return self.rxpdo_words()[start - RXPDO_BASE:end - RXPDO_BASE]
        raise ModbusException(EXC_ILLEGAL_ADDRESS)

    @staticmethod
    def check_write_range(start, count):
        if not (RXPDO_BASE <= start and start + count <= RXPDO_BASE + RXPDO_WORDS):
            raise ModbusException(EXC_ILLEGAL_ADDRESS)

    def write_registers(self, start, values):
        """Caller has validated the range. Applies setpoints first and the
        control word last so that a PDO carrying an enable command together
        with its setpoints acts on the new setpoints."""
        cw = None
        for i, v in enumerate(values):
            reg = start + i
            if reg == 3000:
                cw = v
            elif reg == 3001:
                self.target_velocity = _to_signed(v, 16)
            elif reg == 3002:
                self.torque_limit = _to_signed(v, 16)
            elif reg == 3003:
                self.write_watchdog(v)
        if cw is not None:
            self.write_controlword(cw)

    # ----- state dump -----------------------------------------------------
    def snapshot(self):
        with self.lock:
            tx = self.txpdo_words()
            rx = self.rxpdo_words()
            objs = {}
            for idx in sorted(OBJECTS):
                o = OBJECTS[idx]
                objs["%d.0" % idx] = {
                    "index": idx, "subindex": 0, "name": o.name,
                    "type": o.dtype, "access": o.access,
                    "value": self.get_object(idx),
                }
            return {
                "input_registers": {str(TXPDO_BASE + i): w for i, w in enumerate(tx)},
                "holding_registers": {str(RXPDO_BASE + i): w for i, w in enumerate(rx)},
                "txpdo": {str(r): {"name": TXPDO_NAMES[r], "object": idx,
                                   "words": n} for r, idx, n in TXPDO_MAP},
                "rxpdo": {str(r): {"name": RXPDO_NAMES[r], "object": RXPDO_MAP[r]}
                          for r in sorted(RXPDO_MAP)},
                "objects": objs,
                "ds402": {
                    "state": self.state,
                    "controlword": self.controlword,
                    "statusword": self.statusword(),
                    "error_code": self.error_code,
                    "actual_speed": self.actual_speed(),
                    "target_velocity": self.target_velocity,
                    "torque_limit": self.torque_limit,
                },
                "watchdog": {
                    "timeout_ms": self.watchdog_ms,
                    "armed": self.wd_armed,
                    "tripped": self.wd_tripped,
                },
            }


# ---------------------------------------------------------------------------
# Modbus slave (protocol engine, transport independent)
# ---------------------------------------------------------------------------

class Counters:
    NAMES = ("bus_message_count", "bus_communication_error_count",
             "bus_exception_error_count", "slave_message_count",
             "slave_no_response_count")

    def __init__(self):
        self.clear()

    def clear(self):
        for n in self.NAMES:
            setattr(self, n, 0)

    def inc(self, name):
        setattr(self, name, (getattr(self, name) + 1) & 0xFFFF)

    def as_dict(self):
        return {n: getattr(self, n) for n in self.NAMES}


class Slave:
    def __init__(self, drive, address, settings):
        self.drive = drive
        self.address = address
        self.settings = settings
        self.counters = Counters()
        self.lock = drive.lock

    # ----- frame level ----------------------------------------------------
    def handle_frame(self, frame):
        """One delimited RTU frame (address..CRC).  Returns the response
        frame (bytes) or None.  Never raises."""
        with self.lock:
            try:
                return self._handle_frame(frame)
            except Exception:       # pragma: no cover - last resort
                return None

    def bad_frame(self):
        """A frame that failed CRC / was too short / overran the buffer."""
        with self.lock:
            self.counters.inc("bus_communication_error_count")

    def _handle_frame(self, frame):
        if len(frame) > MAX_RTU_FRAME or not crc_ok(frame):
            self.counters.inc("bus_communication_error_count")
            return None
        self.counters.inc("bus_message_count")
        addr = frame[0]
        if addr != 0 and addr != self.address:
            return None
        self.counters.inc("slave_message_count")
        pdu = bytes(frame[1:-2])
        self.drive.tick()
        if addr == 0:
            self.counters.inc("slave_no_response_count")
            try:
                self._broadcast(pdu)
            except (ModbusException, SdoAbort):
                pass
            return None
        fc = pdu[0]
        if fc & 0x80:
            # not a request (exception function codes are reserved for
            # responses): no reply, as if not for us
            self.counters.inc("slave_no_response_count")
            return None
        try:
            resp = self._dispatch(pdu)
        except ModbusException as e:
            resp = bytes((fc | 0x80, e.code))
        except SdoAbort as e:
            resp = bytes((0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + \
                e.code.to_bytes(4, "little")
        except Exception:
            resp = bytes((fc | 0x80, EXC_DEVICE_FAILURE))
        if resp[0] & 0x80:
            self.counters.inc("bus_exception_error_count")
        return add_crc(bytes((self.address,)) + resp)

    # ----- broadcast --------------------------------------------------------
    def _broadcast(self, pdu):
        fc = pdu[0]
        if fc == 0x06:
            self._fc06(pdu)
        elif fc == 0x10:
            self._fc16(pdu)
        elif fc == 0x17:
            self._fc23(pdu, broadcast=True)
        elif fc == 0x08 and pdu[1:] == b"\x00\x0A\x00\x00":
            self.counters.clear()
        # everything else: not executed on broadcast

    # ----- PDU level --------------------------------------------------------
    def _dispatch(self, pdu):
        fc = pdu[0]
        if fc in (0x03, 0x04):
            return self._fc03(pdu)
        if fc == 0x06:
            return self._fc06(pdu)
        if fc == 0x08:
            return self._fc08(pdu)
        if fc == 0x10:
            return self._fc16(pdu)
        if fc == 0x17:
            return self._fc23(pdu)
        if fc == 0x2B:
            return self._fc43(pdu)
        raise ModbusException(EXC_ILLEGAL_FUNCTION)

    def _fc03(self, pdu):
        if len(pdu) != 5:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        start = int.from_bytes(pdu[1:3], "big")
        count = int.from_bytes(pdu[3:5], "big")
        if not 1 <= count <= MAX_REGS:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        words = self.drive.read_registers(start, count)
        out = bytearray((pdu[0], 2 * count))
        for w in words:
            out += w.to_bytes(2, "big")
        return bytes(out)

    def _fc06(self, pdu):
        if len(pdu) != 5:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        addr = int.from_bytes(pdu[1:3], "big")
        value = int.from_bytes(pdu[3:5], "big")
        self.drive.check_write_range(addr, 1)
        self.drive.write_registers(addr, [value])
        return bytes(pdu)

    def _fc16(self, pdu):
        if len(pdu) < 6:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        start = int.from_bytes(pdu[1:3], "big")
        count = int.from_bytes(pdu[3:5], "big")
        bc = pdu[5]
        if not 1 <= count <= MAX_REGS or bc != 2 * count or len(pdu) != 6 + bc:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        self.drive.check_write_range(start, count)
        values = [int.from_bytes(pdu[6 + 2 * i:8 + 2 * i], "big") for i in range(count)]
        self.drive.write_registers(start, values)
        return bytes(pdu[:5])

    def _fc23(self, pdu, broadcast=False):
        if len(pdu) < 10:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        rstart = int.from_bytes(pdu[1:3], "big")
        rcount = int.from_bytes(pdu[3:5], "big")
        wstart = int.from_bytes(pdu[5:7], "big")
        wcount = int.from_bytes(pdu[7:9], "big")
        bc = pdu[9]
        if (not 1 <= rcount <= MAX_REGS or not 1 <= wcount <= MAX_REGS
                or bc != 2 * wcount or len(pdu) != 10 + bc):
            raise ModbusException(EXC_ILLEGAL_VALUE)
        self.drive.check_write_range(wstart, wcount)
        # validate the read range before anything is written
        self.drive.read_registers(rstart, rcount)
        values = [int.from_bytes(pdu[10 + 2 * i:12 + 2 * i], "big") for i in range(wcount)]
        self.drive.write_registers(wstart, values)
        if broadcast:
            return b""
        words = self.drive.read_registers(rstart, rcount)   # write before read
        out = bytearray((0x17, 2 * rcount))
        for w in words:
            out += w.to_bytes(2, "big")
        return bytes(out)

    def _fc08(self, pdu):
        if len(pdu) < 3:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        sub = int.from_bytes(pdu[1:3], "big")
        data = pdu[3:]
        if sub == 0x0000:
            if len(data) < 2:
                raise ModbusException(EXC_ILLEGAL_VALUE)
            return bytes(pdu)               # Return Query Data: echo
        if sub not in (0x0A, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F):
            raise ModbusException(EXC_ILLEGAL_FUNCTION)
        if data != b"\x00\x00":
            raise ModbusException(EXC_ILLEGAL_VALUE)
        c = self.counters
        if sub == 0x0A:
            c.clear()
            return bytes(pdu)
        value = {
            0x0B: c.bus_message_count,
            0x0C: c.bus_communication_error_count,
            0x0D: c.bus_exception_error_count,
            0x0E: c.slave_message_count,
            0x0F: c.slave_no_response_count,
        }[sub]
        return bytes(pdu[:3]) + value.to_bytes(2, "big")

    # FC 43 / MEI 0x0D -- CANopen object access
    def _fc43(self, pdu):
        if len(pdu) < 2:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        if pdu[1] != 0x0D:
            raise ModbusException(EXC_ILLEGAL_FUNCTION)   # only MEI 0x0D
        if len(pdu) < 4:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        ctrl = pdu[2]
        if pdu[3] == 0x00:
            # table layout (CiA 309-2): ctrl, reserved, node, index...
            hdr = 12
            node = pdu[4] if len(pdu) > 4 else None
            o = 5
        else:
            # layout of the manual's example 6.2 (no reserved byte)
            hdr = 11
            node = pdu[3]
            o = 4
        if len(pdu) < hdr:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        index = int.from_bytes(pdu[o:o + 2], "big")
        sub = pdu[o + 2]
        offset = int.from_bytes(pdu[o + 3:o + 5], "big")
        n = int.from_bytes(pdu[o + 5:o + 7], "big")
        data = pdu[hdr:]
        write = bool(ctrl & 0x80)
        if n > 4:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        if len(data) != (n if write else 0):
            raise ModbusException(EXC_ILLEGAL_VALUE)
        if node == 0 or node > 0x7F:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        if node != self.address:
            raise ModbusException(EXC_ILLEGAL_ADDRESS)
        if offset != 0:
            raise ModbusException(EXC_ILLEGAL_VALUE)
        if ctrl & 0x7F:
            raise SdoAbort(SDO_CMD_INVALID)
        obj = OBJECTS.get(index)
        if obj is None:
            raise SdoAbort(SDO_NO_OBJECT)
        if sub != 0:
            raise SdoAbort(SDO_NO_SUBINDEX)
        head = bytes(pdu[:hdr - 2])
        if write:
            if obj.access != "rw":
                raise SdoAbort(SDO_READ_ONLY)
            if n > obj.size:
                raise SdoAbort(SDO_LEN_TOO_LONG)
            if n < obj.size:
                raise SdoAbort(SDO_LEN_TOO_SHORT)
            raw = int.from_bytes(data, "little")
            self.drive.set_object(index, raw)
            return head + n.to_bytes(2, "big") + bytes(data)
        # read
        if n != 0 and n > obj.size:
            raise SdoAbort(SDO_LEN_TOO_LONG)
        if n != 0 and n < obj.size:
            raise SdoAbort(SDO_LEN_TOO_SHORT)
        size = obj.size
        v = self.drive.get_object(index) & ((1 << (8 * size)) - 1)
        return head + size.to_bytes(2, "big") + v.to_bytes(size, "little")

    # ----- state -----------------------------------------------------------
    def state(self):
        with self.lock:
            self.drive.tick()
            st = {"device": "SIEB & MEYER SD2x (simulated)",
                  "settings": dict(self.settings, slave_address=self.address,
                                   node_id=self.address)}
            st.update(self.drive.snapshot())
            st["diagnostic_counters"] = self.counters.as_dict()
            return st


# ---------------------------------------------------------------------------
# Frame delimiting
# ---------------------------------------------------------------------------

def expected_length(buf):
    """Length of the RTU request frame starting at buf[0], derived from the
    function code (used on the TCP stream, where no line timing exists).
    Returns an int, 0 when more bytes are needed to tell, or None when the
    length cannot be derived (unknown function code)."""
    if len(buf) < 2:
        return 0
    fc = buf[1]
    if fc in (0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x08):
        return 8
    if fc in (0x07, 0x0B, 0x0C, 0x11):
        return 4
    if fc in (0x0F, 0x10):
        return 9 + buf[6] if len(buf) > 6 else 0
    if fc in (0x14, 0x15):
        return 5 + buf[2] if len(buf) > 2 else 0
    if fc == 0x16:
        return 10
    if fc == 0x17:
        return 13 + buf[10] if len(buf) > 10 else 0
    if fc == 0x18:
        return 6
    if fc == 0x2B:
        if len(buf) < 3:
            return 0
        if buf[2] == 0x0E:
            return 7
        if buf[2] == 0x0D:
            if len(buf) < 5:
                return 0
            std = buf[4] == 0
            cpos = 11 if std else 10
            if len(buf) < cpos + 2:
                return 0
            n = int.from_bytes(buf[cpos:cpos + 2], "big")
            base = cpos + 2 + 2
            return base + (n if buf[3] & 0x80 else 0)
        return None
    return None


class TcpFramer:
    """RTU over a TCP byte stream: frames are cut by their function-code
    derived length and CRC; whatever cannot be cut that way is treated as
    one frame once the stream has been silent for `gap` seconds."""

    def __init__(self, slave, gap):
        self.slave = slave
        self.gap = gap
        self.buf = bytearray()

    def feed(self, data):
        out = []
        self.buf += data
        while self.buf:
            n = expected_length(self.buf)
            if not n or len(self.buf) < n:
                break
            if crc_ok(self.buf[:n]):
                frame = bytes(self.buf[:n])
                del self.buf[:n]
                r = self.slave.handle_frame(frame)
                if r:
                    out.append(r)
                continue
            break
        if len(self.buf) > MAX_RTU_FRAME:
            self.slave.bad_frame()
            self.buf.clear()
        return out

    def silence(self):
        if not self.buf:
            return None
        frame = bytes(self.buf)
        self.buf.clear()
        if len(frame) < 4:
            self.slave.bad_frame()
            return None
        return self.slave.handle_frame(frame)


_QUICKACK = getattr(socket, "TCP_QUICKACK", None)


def serve_tcp_conn(conn, slave, gap, stop):
    framer = TcpFramer(slave, gap)
    try:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if _QUICKACK is not None:
            conn.setsockopt(socket.IPPROTO_TCP, _QUICKACK, 1)
        while not stop.is_set():
            conn.settimeout(gap if framer.buf else 0.5)
            try:
                data = conn.recv(4096)
            except socket.timeout:
                if framer.buf:
                    r = framer.silence()
                    if r:
                        conn.sendall(r)
                continue
            if not data:
                break
            if _QUICKACK is not None:
                try:    # ACK at once so a Nagle-delayed rest of a frame follows
                    conn.setsockopt(socket.IPPROTO_TCP, _QUICKACK, 1)
                except OSError:
                    pass
            for r in framer.feed(data):
                conn.sendall(r)
    except OSError:
        pass
    finally:
        try:
            conn.close()
        except OSError:
            pass


MAX_CONNECTIONS = 64


def tcp_server(sock, slave, gap, stop):
    active = []
    while not stop.is_set():
        try:
            conn, _ = sock.accept()
        except socket.timeout:
            continue
        except OSError:
            if stop.is_set():
                break
            time.sleep(0.05)
            continue
        active = [t for t in active if t.is_alive()]
        if len(active) >= MAX_CONNECTIONS:
            conn.close()
            continue
        t = threading.Thread(target=serve_tcp_conn, args=(conn, slave, gap, stop),
                             daemon=True)
        t.start()
        active.append(t)


BAUD_CONSTS = {
    9600: "B9600", 19200: "B19200", 38400: "B38400",
    57600: "B57600", 115200: "B115200",
}


def open_serial(path, baud, parity):
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        attrs = termios.tcgetattr(fd)
        iflag, oflag, cflag, lflag, ispeed, ospeed, cc = attrs
        iflag &= ~(termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP |
                   termios.INLCR | termios.IGNCR | termios.ICRNL | termios.IXON |
                   termios.IXOFF | termios.IXANY | termios.INPCK)
        oflag &= ~termios.OPOST
        lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG |
                   termios.IEXTEN)
        cflag &= ~(termios.CSIZE | termios.PARENB | termios.PARODD | termios.CSTOPB)
        cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
        if parity == "even":
            cflag |= termios.PARENB
            iflag |= termios.INPCK
        elif parity == "odd":
            cflag |= termios.PARENB | termios.PARODD
            iflag |= termios.INPCK
        name = BAUD_CONSTS.get(baud)
        if name and hasattr(termios, name):
            ispeed = ospeed = getattr(termios, name)
        cc = list(cc)
        cc[termios.VMIN] = 0
        cc[termios.VTIME] = 0
        termios.tcsetattr(fd, termios.TCSANOW,
                          [iflag, oflag, cflag, lflag, ispeed, ospeed, cc])
    except termios.error:
        pass        # not a tty (or a pty that refuses): keep going raw
    return fd


def serial_write(fd, data, stop):
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


def serial_server(fd, slave, gap, stop):
    """Classic RTU slave: a frame is everything received between two
    silences of at least t3.5."""
    buf = bytearray()
    overrun = False
    while not stop.is_set():
        timeout = gap if buf or overrun else 0.5
        try:
            r, _, _ = select.select([fd], [], [], timeout)
        except (OSError, ValueError):
            time.sleep(0.05)
            continue
        if r:
            try:
                data = os.read(fd, 4096)
            except BlockingIOError:
                continue
            except OSError:
                # e.g. EIO when the other side of a pty is not open
                time.sleep(0.05)
                continue
            if not data:
                time.sleep(0.01)
                continue
            if not overrun:
                buf += data
                if len(buf) > MAX_RTU_FRAME:
                    overrun = True
                    buf.clear()
            continue
        # silence >= t3.5: end of frame
        if overrun:
            overrun = False
            slave.bad_frame()
            continue
        if buf:
            frame = bytes(buf)
            buf.clear()
            if len(frame) < 4:
                slave.bad_frame()
                continue
            resp = slave.handle_frame(frame)
            if resp:
                serial_write(fd, resp, stop)


# ---------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------

def write_state(path, slave):
    if not path:
        return
    try:
        st = slave.state()
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(st, f, indent=1, sort_keys=True)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except Exception as e:          # never die because of the dump
        print("state dump failed: %s" % e, file=sys.stderr, flush=True)


def ticker(drive, stop):
    while not stop.wait(0.01):
        try:
            drive.tick()
        except Exception:
            pass


def main():
    ap = argparse.ArgumentParser(description="SIEB & MEYER SD2x Modbus RTU simulator")
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--listen", help="HOST:PORT, RTU frames over TCP (loopback only)")
    g.add_argument("--serial", help="serial device path (e.g. one end of a socat pty pair)")
    ap.add_argument("--baud", type=int, default=19200)
    ap.add_argument("--parity", choices=("even", "odd", "none"), default="none")
    ap.add_argument("--address", type=int, default=1,
                    help="slave address 1..254 (default 1: ID switch 0, single axis)")
    ap.add_argument("--state", help="JSON state dump file (SIGUSR1 and on exit)")
    ap.add_argument("--gap-ms", type=float, default=None,
                    help="frame-end silence; default t3.5 (serial, min 3 ms) / 50 ms (tcp)")
    args = ap.parse_args()

    if not 1 <= args.address <= 254:
        ap.error("--address must be 1..254 (programmable address 0..253 + 1)")
    if args.baud not in (9600, 14400, 19200, 28800, 38400, 57600, 115200):
        print("warning: %d baud is not a rate the SD2x offers" % args.baud,
              file=sys.stderr, flush=True)

    drive = Drive()
    settings = {"baud": args.baud, "parity": args.parity,
                "stop_bits": 1, "protocol": "Modbus RTU",
                "transport": "tcp" if args.listen else "serial"}
    slave = Slave(drive, args.address, settings)
    stop = threading.Event()

    def on_usr1(signum, frame):
        write_state(args.state, slave)

    def on_term(signum, frame):
        stop.set()

    signal.signal(signal.SIGUSR1, on_usr1)
    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)

    threading.Thread(target=ticker, args=(drive, stop), daemon=True).start()

    if args.listen:
        host, _, port = args.listen.rpartition(":")
        host = host.strip("[]") or "127.0.0.1"
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, int(port)))
        sock.listen(16)
        sock.settimeout(0.5)
        gap = (args.gap_ms / 1000.0) if args.gap_ms else 0.050
        threading.Thread(target=tcp_server, args=(sock, slave, gap, stop),
                         daemon=True).start()
        print("listening tcp %s:%d" % sock.getsockname()[:2], flush=True)
    else:
        bits = 11 if args.parity != "none" else 10   # 1 start, 8 data, [parity], 1 stop
        t35 = 3.5 * bits / args.baud if args.baud <= 19200 else 0.00175
        gap = (args.gap_ms / 1000.0) if args.gap_ms else max(t35, 0.003)
        fd = open_serial(args.serial, args.baud, args.parity)
        threading.Thread(target=serial_server, args=(fd, slave, gap, stop),
                         daemon=True).start()
        print("listening serial %s" % args.serial, flush=True)

    while not stop.is_set():
        stop.wait(0.05)     # signal handlers run between waits
    write_state(args.state, slave)
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
