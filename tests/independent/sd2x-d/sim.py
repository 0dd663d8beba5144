#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier - Modbus RTU slave simulator.

Written from the vendor manual "Drive Amplifier SD2x - Modbus RTU Connection"
and the public Modbus specifications only.  Behaves like a small
microcontroller firmware: one main loop, a fixed 256-byte receive buffer per
channel, a few ms of processing time per request, a single-channel object
dictionary (SDO) server whose write jobs take some time.

Transports
  --listen 127.0.0.1:PORT   RTU frames (addr + PDU + CRC16, no MBAP) on TCP
  --serial PATH             RTU on a serial line / pty, t3.5 silence framing

Standard library only (Python 3.11).
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

# ---------------------------------------------------------------------------
# Firmware constants (see DECISIONS.md)
# ---------------------------------------------------------------------------
RX_BUF_SIZE = 256            # fixed receive buffer (max RTU ADU)
MAX_TCP_CONNECTIONS = 4      # socket pool of the lightweight TCP/IP stack
PROCESSING_DELAY = 0.003     # main-loop turnaround before each answer
TCP_FRAME_GAP = 0.050        # idle time that ends a frame on the TCP stream
SDO_WRITE_TIME = 0.020       # object dictionary write job duration
TICK = 0.010                 # control loop period of the simulation
MAX_REGS = 48                # manual: n = 1 .. 48 (30h)

# Process images (manual chapter 4)
TXPDO_BASE = 2000
TXPDO_LEN = 24               # 2000 .. 2023
RXPDO_BASE = 3000
RXPDO_LEN = 4                # 3000 .. 3003

# SDO error codes (manual chapter 3.8)
SDO_CMD_UNKNOWN = 0xFFFF0003
SDO_UNSUPPORTED_ACCESS = 0xFFFF0008
SDO_WRITE_ONLY = 0xFFFF0009
SDO_READ_ONLY = 0xFFFF000A
SDO_NO_OBJECT = 0xFFFF000B
SDO_LEN_TOO_LONG = 0xFFFF0012
SDO_LEN_TOO_SHORT = 0xFFFF0013
SDO_NO_SUBINDEX = 0xFFFF0014
SDO_DEVICE_STATE = 0xFFFF001C

# Modbus exception codes
ILLEGAL_FUNCTION = 0x01
ILLEGAL_DATA_ADDRESS = 0x02
ILLEGAL_DATA_VALUE = 0x03
SLAVE_DEVICE_FAILURE = 0x04

# DS402 control word / state machine
ST_NOT_READY = "NOT_READY_TO_SWITCH_ON"
ST_SOD = "SWITCH_ON_DISABLED"
ST_RTSO = "READY_TO_SWITCH_ON"
ST_SO = "SWITCHED_ON"
ST_OE = "OPERATION_ENABLED"
ST_QSA = "QUICK_STOP_ACTIVE"
ST_FRA = "FAULT_REACTION_ACTIVE"
ST_FAULT = "FAULT"

STATE_BITS = {
    ST_NOT_READY: 0x0000,
    ST_SOD: 0x0040,
    ST_RTSO: 0x0021 | 0x0010,
    ST_SO: 0x0023 | 0x0010,
    ST_OE: 0x0027 | 0x0010,
    ST_QSA: 0x0007 | 0x0010,
    ST_FRA: 0x000F,
    ST_FAULT: 0x0008,
}
SW_VOLTAGE_ENABLED = 0x0010
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400

ERR_WATCHDOG = 0x8130        # "Heartbeat/Watchdog" (CiA 301 heartbeat/life guard error)


def crc16(data):
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            if crc & 1:
                crc = (crc >> 1) ^ 0xA001
            else:
                crc >>= 1
    return crc


def add_crc(frame):
    c = crc16(frame)
    return bytes(frame) + bytes((c & 0xFF, c >> 8))


def crc_ok(frame):
    if len(frame) < 4:
        return False
    c = crc16(frame[:-2])
    return frame[-2] == (c & 0xFF) and frame[-1] == (c >> 8)


def s16(v):
    v &= 0xFFFF
    return v - 0x10000 if v & 0x8000 else v


def s32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


# ---------------------------------------------------------------------------
# Drive model
# ---------------------------------------------------------------------------
class Drive:
    # identification (fixed by firmware / hardware)
    HARDWARE_ID = 0x00000210          # SD2x single axis device type code
    HARDWARE_VERSION = 0x00020010     # 2.16 (manual example coding)
    SOFTWARE_ID = 0x00005344          # "SD"
    SOFTWARE_VERSION = 0x00040017     # 4.23
    MAX_IQ = 200                      # 20.0 A (0.1 A)
    SPEED_SCALING = 60_000_000        # 60000.000 rpm = 1000 Hz (0.001 rpm)
    MAX_SPEED = 0x3FFF                # 0x3FFF = speed scaling -> 1000 Hz
    CURRENT_SCALING = 20_000          # 20.000 A (0.001 A)
    DC_VOLTAGE = 5650                 # 565.0 V
    TEMP_POWER_STAGE = 170            # 17.0 degC (manual example 6.2)
    TEMP_MOTOR = 165                  # 16.5 degC
    ACCEL = 1000.0                    # 0.1 Hz per second (=100 Hz/s)
    QUICK_STOP_DECEL = 4000.0         # 0.1 Hz per second
    COAST_DECEL = 500.0               # 0.1 Hz per second (no torque)

    def __init__(self):
        # RxPDO / writable objects
        self.control_word = 0          # obj 68, reg 3000
        self.target_velocity = 0       # obj 210, reg 3001 (signed)
        self.torque_limit = 0          # obj 209, reg 3002 (signed)
        self.watchdog = 0              # reg 3003 (no object index)
        # internal state
        self.state = ST_SOD            # boot: not ready -> switch on disabled
        self.error_code = 0
        self.speed = 0.0               # 0.1 Hz, float for ramping
        self.accelerating = False
        self._last_tick = time.monotonic()
        self._wd_last = time.monotonic()
        self._prev_fault_reset = False

    # ---- derived actual values ------------------------------------------
    def max_speed_01hz(self):
        # max speed in "0x3FFF = speed scaling" units -> 0.1 Hz
        hz = self.MAX_SPEED / 0x3FFF * (self.SPEED_SCALING / 1000.0) / 60.0
        return int(round(hz * 10))

    def actual_speed(self):
        return max(-32768, min(32767, int(round(self.speed))))

    def apparent_current(self):
        if self.state not in (ST_OE, ST_QSA):
            return 0
        lim = min(abs(self.torque_limit), self.MAX_IQ)
        i = 12 + abs(self.speed) * 0.004
        if self.accelerating:
            i += lim * 0.6
        return int(min(i, max(lim, 12)))

    def output_voltage(self):
        if self.state not in (ST_OE, ST_QSA):
            return 0
        return int(round(abs(self.speed) / self.max_speed_01hz() * 4000))

    def output_power(self):
        # 0.1 kW; sqrt(3) * U * I * cos(phi)
        u = self.output_voltage() / 10.0
        i = self.apparent_current() / 10.0
        return int(round(math.sqrt(3) * u * i * 0.85 / 100.0))

    def status_word(self):
        sw = STATE_BITS[self.state] | SW_REMOTE
        if self.state == ST_OE:
            halt = bool(self.control_word & 0x0100)
            tgt = 0 if halt else self._clamped_target()
            if abs(self.speed - tgt) < 0.5:
                sw |= SW_TARGET_REACHED
        return sw

    def _clamped_target(self):
        m = self.max_speed_01hz()
        return max(-m, min(m, self.target_velocity))

    # ---- control ---------------------------------------------------------
    def watchdog_written(self, now):
        self._wd_last = now

    def _fault(self, code):
        self.error_code = code
        self.state = ST_FAULT

    def _state_machine(self):
        cw = self.control_word
        fr = bool(cw & 0x0080)
        fr_edge = fr and not self._prev_fault_reset
        self._prev_fault_reset = fr
        st = self.state
        if st in (ST_FAULT, ST_FRA):
            if st == ST_FAULT and fr_edge:
                self.error_code = 0
                self.state = ST_SOD
                self._wd_last = time.monotonic()
            return
        if fr:      # bit 7 set overrides the other commands (DS402)
            return
        ev = cw & 0x02
        qs = cw & 0x04          # quick stop is active low
        so = cw & 0x01
        eo = cw & 0x08
        if not ev:                                    # disable voltage
            if st in (ST_RTSO, ST_SO, ST_OE, ST_QSA):
                self.state = ST_SOD
            return
        if not qs:                                    # quick stop
            if st in (ST_RTSO, ST_SO):
                self.state = ST_SOD
            elif st == ST_OE:
                self.state = ST_QSA
            return
        if st == ST_QSA:
            return  # stays until standstill, then -> switch on disabled
        if not so:                                    # shutdown (x110)
            if st in (ST_SOD, ST_SO, ST_OE):
                self.state = ST_RTSO
            return
        # switch on (0111) / enable operation (1111)
        if st == ST_RTSO:
            self.state = ST_OE if eo else ST_SO
        elif st == ST_SO and eo:
            self.state = ST_OE
        elif st == ST_OE and not eo:
            self.state = ST_SO

    def tick(self, now=None):
        if now is None:
            now = time.monotonic()
        dt = max(0.0, min(now - self._last_tick, 1.0))
        self._last_tick = now
        # watchdog: register must be rewritten within its timeout (ms)
        if self.watchdog and self.state != ST_FAULT:
            if (now - self._wd_last) * 1000.0 > self.watchdog:
                self._fault(ERR_WATCHDOG)
        self._state_machine()
        # motion
        self.accelerating = False
        if self.state == ST_OE:
            halt = bool(self.control_word & 0x0100)
            tgt = 0 if halt else self._clamped_target()
            rate = self.ACCEL if self.torque_limit != 0 else 0.0
            diff = tgt - self.speed
            step = rate * dt
            if abs(diff) <= step:
                self.speed = float(tgt)
            elif step > 0:
                self.speed += step if diff > 0 else -step
                self.accelerating = abs(self.speed) > 0 and (diff > 0) == (self.speed > 0)
        elif self.state == ST_QSA:
            step = self.QUICK_STOP_DECEL * dt
            if abs(self.speed) <= step:
                self.speed = 0.0
                self.state = ST_SOD
            else:
                self.speed -= step if self.speed > 0 else -step
        else:
            step = self.COAST_DECEL * dt
            if abs(self.speed) <= step:
                self.speed = 0.0
            else:
                self.speed -= step if self.speed > 0 else -step

    # ---- process image -----------------------------------------------------
    def txpdo_words(self):
        w = [
            self.status_word(),
            self.actual_speed() & 0xFFFF,
            self.torque_limit & 0xFFFF,
            self.apparent_current() & 0xFFFF,
            self.output_power() & 0xFFFF,
            self.error_code & 0xFFFF,
            self.TEMP_POWER_STAGE & 0xFFFF,
            self.TEMP_MOTOR & 0xFFFF,
            self.output_voltage() & 0xFFFF,
            self.DC_VOLTAGE & 0xFFFF,
        ]
        for v in (self.HARDWARE_ID, self.HARDWARE_VERSION,
                  self.SOFTWARE_ID, self.SOFTWARE_VERSION):
            w += [(v >> 16) & 0xFFFF, v & 0xFFFF]
        w += [self.MAX_IQ & 0xFFFF, self.MAX_SPEED & 0xFFFF]
        for v in (self.SPEED_SCALING, self.CURRENT_SCALING):
            v &= 0xFFFFFFFF
            w += [(v >> 16) & 0xFFFF, v & 0xFFFF]
        assert len(w) == TXPDO_LEN
        return w

    def rxpdo_words(self):
        return [self.control_word & 0xFFFF, self.target_velocity & 0xFFFF,
                self.torque_limit & 0xFFFF, self.watchdog & 0xFFFF]

    def write_rxpdo(self, reg, value, now):
        idx = reg - RXPDO_BASE
        if idx == 0:
            self.control_word = value & 0xFFFF
        elif idx == 1:
            self.target_velocity = s16(value)
        elif idx == 2:
            self.torque_limit = s16(value)
        elif idx == 3:
            self.watchdog = value & 0xFFFF
            self.watchdog_written(now)


def build_objects(drive):
    """Object dictionary: index -> (name, type, access, getter, setter)."""
    d = drive

    def setter(attr, conv):
        def f(v):
            setattr(d, attr, conv(v))
        return f

    return {
        2: ("Hardware ID", "U32", "RO", lambda: d.HARDWARE_ID, None),
        5: ("Hardware Version", "U32", "RO", lambda: d.HARDWARE_VERSION, None),
        16: ("Software ID", "U32", "RO", lambda: d.SOFTWARE_ID, None),
        17: ("Software Version", "U32", "RO", lambda: d.SOFTWARE_VERSION, None),
        33: ("DC Voltage", "I16", "RO", lambda: d.DC_VOLTAGE, None),
        41: ("Temperature Power Stage", "I16", "RO", lambda: d.TEMP_POWER_STAGE, None),
        63: ("Temperature Motor", "I16", "RO", lambda: d.TEMP_MOTOR, None),
        67: ("Status Word", "U16", "RO", d.status_word, None),
        68: ("Control Word", "U16", "RW", lambda: d.control_word,
             setter("control_word", lambda v: v & 0xFFFF)),
        70: ("Error Code", "U16", "RO", lambda: d.error_code, None),
        120: ("Max Speed", "I16", "RO", lambda: d.MAX_SPEED, None),
        168: ("Actual Speed", "I16", "RO", d.actual_speed, None),
        171: ("Max Iq Current", "I16", "RO", lambda: d.MAX_IQ, None),
        177: ("Speed Scaling", "I32", "RO", lambda: d.SPEED_SCALING, None),
        182: ("Current Scaling", "I32", "RO", lambda: d.CURRENT_SCALING, None),
        209: ("Target Torque Limit", "I16", "RW", lambda: d.torque_limit,
              setter("torque_limit", s16)),
        210: ("Target Velocity", "I16", "RW", lambda: d.target_velocity,
              setter("target_velocity", s16)),
        390: ("Actual Output Power", "I16", "RO", d.output_power, None),
        431: ("Actual Apparent Current", "I16", "RO", d.apparent_current, None),
        434: ("Output Voltage", "I16", "RO", d.output_voltage, None),
    }


TYPE_SIZE = {"U16": 2, "I16": 2, "U32": 4, "I32": 4}


class SdoError(Exception):
    def __init__(self, code):
        super().__init__(hex(code))
        self.code = code


class ModbusException(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# ---------------------------------------------------------------------------
# Modbus slave (PDU level) - one instance shared by all channels = main loop
# ---------------------------------------------------------------------------
class Slave:
    def __init__(self, address, settings):
        self.address = address
        self.settings = settings
        self.drive = Drive()
        self.objects = build_objects(self.drive)
        self.counters = dict(bus_message=0, bus_comm_error=0, bus_exception=0,
                             slave_message=0, slave_no_response=0)
        self.lock = asyncio.Lock()       # main loop handles one request at a time
        self.sdo_busy_until = 0.0        # single-channel SDO server

    # ---- framing helpers ---------------------------------------------------
    @staticmethod
    def expected_lengths(buf):
        """Candidate RTU frame lengths for the bytes at the start of buf.

        Returns None when more header bytes are needed, [] when the function
        code is unknown (frame then ends at the idle gap)."""
        if len(buf) < 2:
            return None
        fc = buf[1]
        if fc in (1, 2, 3, 4, 5, 6):
            return [8]
        if fc == 8:
            return [8]
        if fc in (7, 11, 12, 17):
            return [4]
        if fc in (15, 16):
            if len(buf) < 7:
                return None
            return [9 + buf[6]]
        if fc == 22:
            return [10]
        if fc == 23:
            if len(buf) < 11:
                return None
            return [13 + buf[10]]
        if fc == 24:
            return [6]
        if fc in (20, 21):
            if len(buf) < 3:
                return None
            return [5 + buf[2]]
        if fc == 43:
            if len(buf) < 4:
                return None
            if buf[2] == 0x0E:
                return [7]
            if buf[2] != 0x0D:
                return []
            write = bool(buf[3] & 0x80)
            c = []
            # CiA 309-2 layout with reserved byte (manual table, p. 13)
            if len(buf) >= 13:
                n = (buf[11] << 8) | buf[12]
                c.append(15 + n if write else 15)
            # layout of manual example 6.2 (no reserved byte)
            if len(buf) >= 12:
                n = (buf[10] << 8) | buf[11]
                c.append(14 + n if write else 14)
            return sorted(set(c)) if c else None
        return []

    # ---- ADU handling --------------------------------------------------------
    async def handle_adu(self, adu):
        """adu has a valid CRC. Returns response ADU bytes or None."""
        async with self.lock:
            now = time.monotonic()
            self.drive.tick(now)
            self.counters["bus_message"] += 1
            addr = adu[0]
            pdu = adu[1:-2]
            if addr != self.address and addr != 0:
                return None
            self.counters["slave_message"] += 1
            if addr == 0:
                # broadcast: only the write services are executed, never answered
                if pdu and pdu[0] in (6, 16):
                    try:
                        self.process_pdu(pdu, now)
                    except (ModbusException, SdoError):
                        pass
                self.counters["slave_no_response"] += 1
                return None
            await asyncio.sleep(PROCESSING_DELAY)
            try:
                rpdu = self.process_pdu(pdu, now)
            except ModbusException as e:
                self.counters["bus_exception"] += 1
                rpdu = bytes(((pdu[0] | 0x80) & 0xFF, e.code))
            except SdoError as e:
                self.counters["bus_exception"] += 1
                rpdu = (bytes((0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE))
                        + struct.pack("<I", e.code))
            except Exception:            # never let one frame kill the loop
                self.counters["bus_exception"] += 1
                rpdu = bytes(((pdu[0] | 0x80) & 0xFF, SLAVE_DEVICE_FAILURE))
            if rpdu is None:
                return None
            delay = 0.0
            if isinstance(rpdu, tuple):      # deferred SDO write job
                delay, rpdu = rpdu
        if delay:
            # the SDO job runs in the background; the main loop keeps serving
            # other channels, this answer is sent when the job is done
            await asyncio.sleep(delay)
        return add_crc(bytes((self.address,)) + rpdu)

    def process_pdu(self, pdu, now):
        fc = pdu[0]
        if fc in (3, 4):
            return self.fc_read(pdu)
        if fc == 6:
            return self.fc_write_single(pdu, now)
        if fc == 8:
            return self.fc_diag(pdu)
        if fc == 16:
            return self.fc_write_multiple(pdu, now)
        if fc == 23:
            return self.fc_read_write(pdu, now)
        if fc == 43:
            return self.fc_mei(pdu, now)
        raise ModbusException(ILLEGAL_FUNCTION)

    # ---- register access -----------------------------------------------------
    def read_regs(self, start, count):
        if TXPDO_BASE <= start and start + count <= TXPDO_BASE + TXPDO_LEN:
            w = self.drive.txpdo_words()
            return w[start - TXPDO_BASE:start - TXPDO_BASE + count]
        if RXPDO_BASE <= start and start + count <= RXPDO_BASE + RXPDO_LEN:
            w = self.drive.rxpdo_words()
            return w[start - RXPDO_BASE:start - RXPDO_BASE + count]
        raise ModbusException(ILLEGAL_DATA_ADDRESS)

    @staticmethod
    def check_write_range(start, count):
        if not (RXPDO_BASE <= start and start + count <= RXPDO_BASE + RXPDO_LEN):
            raise ModbusException(ILLEGAL_DATA_ADDRESS)

    def write_regs(self, start, values, now):
        for i, v in enumerate(values):
            self.drive.write_rxpdo(start + i, v, now)
        self.drive.tick(now)

    def fc_read(self, pdu):
        if len(pdu) != 5:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        start, count = struct.unpack(">HH", pdu[1:5])
        if not 1 <= count <= MAX_REGS:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        words = self.read_regs(start, count)
        return bytes((pdu[0], 2 * count)) + struct.pack(">%dH" % count, *words)

    def fc_write_single(self, pdu, now):
        if len(pdu) != 5:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        reg, value = struct.unpack(">HH", pdu[1:5])
        self.check_write_range(reg, 1)
        self.write_regs(reg, [value], now)
        return bytes(pdu)

    def fc_write_multiple(self, pdu, now):
        if len(pdu) < 6:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        start, count = struct.unpack(">HH", pdu[1:5])
        bc = pdu[5]
        if not 1 <= count <= MAX_REGS or bc != 2 * count or len(pdu) != 6 + bc:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        self.check_write_range(start, count)
        values = struct.unpack(">%dH" % count, pdu[6:6 + bc])
        self.write_regs(start, values, now)
        return bytes(pdu[:5])

    def fc_read_write(self, pdu, now):
        if len(pdu) < 10:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        rstart, rcount, wstart, wcount = struct.unpack(">HHHH", pdu[1:9])
        bc = pdu[9]
        if (not 1 <= rcount <= MAX_REGS or not 1 <= wcount <= MAX_REGS
                or bc != 2 * wcount or len(pdu) != 10 + bc):
            raise ModbusException(ILLEGAL_DATA_VALUE)
        self.check_write_range(wstart, wcount)
        self.read_regs(rstart, rcount)           # validate before writing
        values = struct.unpack(">%dH" % wcount, pdu[10:10 + bc])
        self.write_regs(wstart, values, now)     # write first, then read
        words = self.read_regs(rstart, rcount)
        return bytes((23, 2 * rcount)) + struct.pack(">%dH" % rcount, *words)

    # ---- FC 08 -----------------------------------------------------------------
    def fc_diag(self, pdu):
        if len(pdu) < 3:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        sub = (pdu[1] << 8) | pdu[2]
        data = pdu[3:]
        c = self.counters
        if sub == 0x00:
            if len(data) != 2:
                raise ModbusException(ILLEGAL_DATA_VALUE)
            return bytes(pdu)
        table = {0x0B: "bus_message", 0x0C: "bus_comm_error",
                 0x0D: "bus_exception", 0x0E: "slave_message",
                 0x0F: "slave_no_response"}
        if sub != 0x0A and sub not in table:
            raise ModbusException(ILLEGAL_FUNCTION)
        if len(data) != 2 or data != b"\x00\x00":
            raise ModbusException(ILLEGAL_DATA_VALUE)
        if sub == 0x0A:
            for k in c:
                c[k] = 0
            return bytes(pdu)
        return bytes(pdu[:3]) + struct.pack(">H", c[table[sub]] & 0xFFFF)

    # ---- FC 43 / MEI 0x0D: CANopen object access ------------------------------
    def fc_mei(self, pdu, now):
        if len(pdu) < 2:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        if pdu[1] != 0x0D:
            raise ModbusException(ILLEGAL_FUNCTION)
        req = self._parse_mei(pdu)
        if req is None:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        hdr, ctrl, node, index, sub, offset, count, data = req
        if node != self.address:
            raise ModbusException(ILLEGAL_DATA_VALUE)
        if now < self.sdo_busy_until:
            raise SdoError(SDO_DEVICE_STATE)
        if ctrl & 0x7F:
            raise SdoError(SDO_CMD_UNKNOWN)
        write = bool(ctrl & 0x80)
        obj = self.objects.get(index)
        if obj is None:
            raise SdoError(SDO_NO_OBJECT)
        name, typ, access, getter, setter_ = obj
        if sub != 0:
            raise SdoError(SDO_NO_SUBINDEX)
        if offset != 0:
            raise SdoError(SDO_UNSUPPORTED_ACCESS)
        size = TYPE_SIZE[typ]
        if not write:
            if count == 0:
                count = size           # 0 = "whole object"
            if count > size:
                raise SdoError(SDO_LEN_TOO_LONG)
            if count < size:
                raise SdoError(SDO_LEN_TOO_SHORT)
            self.drive.tick(now)
            val = getter() & (0xFFFFFFFF if size == 4 else 0xFFFF)
            payload = val.to_bytes(size, "little")
            return hdr + struct.pack(">H", size) + payload
        if access == "RO":
            raise SdoError(SDO_READ_ONLY)
        if count > size:
            raise SdoError(SDO_LEN_TOO_LONG)
        if count < size:
            raise SdoError(SDO_LEN_TOO_SHORT)
        value = int.from_bytes(data, "little")
        setter_(value)
        self.drive.tick(now)
        self.sdo_busy_until = now + SDO_WRITE_TIME
        # the answer is sent when the object dictionary job has finished
        return (SDO_WRITE_TIME, hdr + struct.pack(">H", count) + bytes(data))

    @staticmethod
    def _parse_mei(pdu):
        """Accept the table layout (with reserved byte) and the layout of
        example 6.2 (without).  Returns header bytes to echo and fields."""
        ctrl = pdu[2] if len(pdu) > 2 else 0
        write = bool(ctrl & 0x80)
        for with_res in (True, False):
            h = 12 if with_res else 11        # PDU bytes up to byte count
            if len(pdu) < h:
                continue
            count = (pdu[h - 2] << 8) | pdu[h - 1]
            if count > 4:
                continue
            if write:
                if len(pdu) != h + count:
                    continue
                data = pdu[h:]
            else:
                if len(pdu) != h:
                    continue
                data = b""
            p = 4 if with_res else 3
            node = pdu[p]
            index = (pdu[p + 1] << 8) | pdu[p + 2]
            sub = pdu[p + 3]
            offset = (pdu[p + 4] << 8) | pdu[p + 5]
            hdr = bytes(pdu[:h - 2])
            return hdr, ctrl, node, index, sub, offset, count, data
        return None

    # ---- state dump ------------------------------------------------------------
    def snapshot(self):
        d = self.drive
        d.tick()
        tx = d.txpdo_words()
        rx = d.rxpdo_words()
        objs = {}
        for idx in sorted(self.objects):
            name, typ, access, getter, _ = self.objects[idx]
            objs["%d:0" % idx] = {"name": name, "type": typ, "access": access,
                                  "value": getter()}
        return {
            "device": "SIEB & MEYER SD2x (simulated), Modbus RTU",
            "settings": dict(self.settings, slave_address=self.address),
            "drive_state": d.state,
            "input_registers": {str(TXPDO_BASE + i): v for i, v in enumerate(tx)},
            "holding_registers": {str(RXPDO_BASE + i): v for i, v in enumerate(rx)},
            "objects": objs,
            "diagnostic_counters": dict(self.counters),
        }


# ---------------------------------------------------------------------------
# RTU framer (one per channel: fixed buffer, idle-gap + length framing)
# ---------------------------------------------------------------------------
class Framer:
    def __init__(self, slave, gap, write):
        self.slave = slave
        self.gap = gap
        self.write = write
        self.buf = bytearray()
        self.discarding = False

    async def feed(self, data):
        if self.discarding:
            return
        self.buf += data
        while True:
            cands = self.slave.expected_lengths(self.buf)
            if not cands:
                break
            done = False
            for n in cands:
                if len(self.buf) >= n and crc_ok(self.buf[:n]):
                    frame = bytes(self.buf[:n])
                    del self.buf[:n]
                    await self._deliver(frame)
                    done = True
                    break
            if not done:
                break
        if len(self.buf) > RX_BUF_SIZE:
            # receive buffer overrun: drop everything until the line is idle
            self.slave.counters["bus_comm_error"] += 1
            self.buf.clear()
            self.discarding = True

    async def idle(self):
        if self.discarding:
            self.discarding = False
            self.buf.clear()
            return
        if not self.buf:
            return
        frame = bytes(self.buf)
        self.buf.clear()
        if crc_ok(frame):
            await self._deliver(frame)
        else:
            self.slave.counters["bus_comm_error"] += 1

    async def _deliver(self, frame):
        try:
            resp = await self.slave.handle_adu(frame)
        except Exception:
            resp = None
        if resp:
            try:
                await self.write(resp)
            except Exception:
                pass

    @property
    def pending(self):
        return bool(self.buf) or self.discarding


# ---------------------------------------------------------------------------
# Transports
# ---------------------------------------------------------------------------
class TcpServer:
    def __init__(self, slave):
        self.slave = slave
        self.conns = set()

    async def client(self, reader, writer):
        if len(self.conns) >= MAX_TCP_CONNECTIONS:
            # no free socket in the stack's pool: close immediately
            try:
                writer.close()
            except Exception:
                pass
            return
        task = asyncio.current_task()
        self.conns.add(task)

        async def write(b):
            writer.write(b)
            await writer.drain()

        fr = Framer(self.slave, TCP_FRAME_GAP, write)
        try:
            while True:
                try:
                    if fr.pending:
                        data = await asyncio.wait_for(reader.read(512), self.slave_gap())
                    else:
                        data = await reader.read(512)
                except (asyncio.TimeoutError, TimeoutError):
                    await fr.idle()
                    continue
                if not data:
                    break
                await fr.feed(data)
        except (ConnectionError, OSError, asyncio.IncompleteReadError):
            pass
        except asyncio.CancelledError:
            pass
        finally:
            self.conns.discard(task)
            try:
                writer.close()
            except Exception:
                pass

    @staticmethod
    def slave_gap():
        return TCP_FRAME_GAP


def t35(baud):
    if baud > 19200:
        return 0.00175
    return 3.5 * 11.0 / baud


async def serve_serial(slave, path, baud, parity, stop):
    import termios
    import tty
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        attrs = termios.tcgetattr(fd)
        tty.setraw(fd)
        attrs = termios.tcgetattr(fd)
        speed = getattr(termios, "B%d" % baud, None)
        cflag = attrs[2]
        cflag &= ~(termios.PARENB | termios.PARODD | termios.CSTOPB | termios.CSIZE)
        cflag |= termios.CS8 | termios.CLOCAL | termios.CREAD
        if parity == "even":
            cflag |= termios.PARENB
        elif parity == "odd":
            cflag |= termios.PARENB | termios.PARODD
        attrs[2] = cflag
        if speed is not None:
            attrs[4] = attrs[5] = speed
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
    except Exception:
        pass   # a pty may not accept all settings
    loop = asyncio.get_running_loop()
    q = asyncio.Queue()

    def readable():
        try:
            data = os.read(fd, 512)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if data:
            q.put_nowait(data)

    loop.add_reader(fd, readable)

    async def write(b):
        try:
            os.write(fd, b)
        except OSError:
            pass

    gap = max(t35(baud), 0.003)
    fr = Framer(slave, gap, write)
    try:
        while not stop.is_set():
            try:
                data = await asyncio.wait_for(q.get(), gap if fr.pending else 0.5)
            except (asyncio.TimeoutError, TimeoutError):
                if fr.pending:
                    await fr.idle()
                continue
            await fr.feed(data)
    finally:
        loop.remove_reader(fd)
        os.close(fd)


def write_state(slave, path):
    if not path:
        return
    try:
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(slave.snapshot(), f, indent=2, sort_keys=True)
            f.write("\n")
        os.replace(tmp, path)
    except Exception as e:
        print("state dump failed: %s" % e, file=sys.stderr, flush=True)


async def ticker(slave, stop):
    while not stop.is_set():
        await asyncio.sleep(TICK)
        if not slave.lock.locked():
            slave.drive.tick()


async def main_async(args):
    settings = {"transport": "serial" if args.serial else "tcp",
                "baud": args.baud, "parity": args.parity}
    slave = Slave(args.address, settings)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    loop.add_signal_handler(signal.SIGUSR1, lambda: write_state(slave, args.state))
    tick_task = asyncio.create_task(ticker(slave, stop))
    server = None
    serial_task = None
    if args.serial:
        serial_task = asyncio.create_task(
            serve_serial(slave, args.serial, args.baud, args.parity, stop))
        await asyncio.sleep(0)
        print("listening serial %s" % args.serial, flush=True)
    else:
        host, _, port = args.listen.rpartition(":")
        tcp = TcpServer(slave)
        server = await asyncio.start_server(tcp.client, host, int(port))
        p = server.sockets[0].getsockname()[1]
        print("listening tcp %s:%d" % (host, p), flush=True)
    await stop.wait()
    if server:
        server.close()
        for t in list(tcp.conns):
            t.cancel()
    if serial_task:
        serial_task.cancel()
        try:
            await serial_task
        except BaseException:
            pass
    tick_task.cancel()
    write_state(slave, args.state)


def main():
    ap = argparse.ArgumentParser(description="SIEB & MEYER SD2x Modbus RTU simulator")
    ap.add_argument("--listen", help="HOST:PORT for RTU over TCP (use 127.0.0.1:0)")
    ap.add_argument("--serial", help="serial device / pty path")
    ap.add_argument("--baud", type=int, default=19200,
                    choices=[9600, 14400, 19200, 28800, 38400, 57600, 115200])
    ap.add_argument("--parity", default="none", choices=["even", "odd", "none"])
    ap.add_argument("--address", type=int, default=1,
                    help="slave address 1..254 (default 1: ID switch 0, "
                         "mode 'address selector switch + 1', single axis)")
    ap.add_argument("--state", help="JSON state file (SIGUSR1 and exit)")
    args = ap.parse_args()
    if not args.listen and not args.serial:
        args.listen = "127.0.0.1:0"
    if not 1 <= args.address <= 254:
        ap.error("--address must be 1..254")
    if args.listen:
        host = args.listen.rpartition(":")[0]
        if host != "127.0.0.1":
            ap.error("only the loopback address 127.0.0.1 is allowed")
    try:
        asyncio.run(main_async(args))
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
