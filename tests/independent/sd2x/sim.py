#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier -- Modbus RTU slave simulator.

Transport: raw Modbus RTU frames (address, PDU, CRC-16, no MBAP) carried on a
TCP byte stream, as a transparent serial-to-Ethernet gateway would.  Frame
delimiting: see DECISIONS.md (function-code length rules + t3.5 silence).

Standard library only.  python3 sim.py --listen 127.0.0.1:0 [--state FILE]
"""
import argparse
import asyncio
import json
import math
import os
import signal
import socket
import struct
import sys
import time

# ---------------------------------------------------------------------------
# CRC-16 (Modbus), table driven
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
    return len(frame) >= 4 and crc16(frame[:-2]) == (frame[-2] | (frame[-1] << 8))


def add_crc(body):
    c = crc16(body)
    return bytes(body) + bytes((c & 0xFF, c >> 8))


# ---------------------------------------------------------------------------
# Constants from the manual
# ---------------------------------------------------------------------------
BAUD_RATES = (9600, 14400, 19200, 28800, 38400, 57600, 115200)   # manual 2.2.1
MAX_REGS = 48                       # n = 1..48 (30h) for FC03/04/16/23
TXPDO_BASE = 2000                   # input registers, actual values
RXPDO_BASE = 3000                   # holding registers, set points

# Modbus exception codes
ILLEGAL_FUNCTION = 0x01
ILLEGAL_DATA_ADDRESS = 0x02
ILLEGAL_DATA_VALUE = 0x03
SLAVE_DEVICE_FAILURE = 0x04

# SDO error codes (manual 3.8)
SDO_CMD_UNKNOWN = 0xFFFF0003
SDO_UNSUPPORTED_ACCESS = 0xFFFF0008
SDO_READ_WO = 0xFFFF0009
SDO_WRITE_RO = 0xFFFF000A
SDO_NO_OBJECT = 0xFFFF000B
SDO_LEN_TOO_LONG = 0xFFFF0012
SDO_LEN_TOO_SHORT = 0xFFFF0013
SDO_NO_SUBINDEX = 0xFFFF0014

# DS402 states
NOT_READY = "NOT_READY_TO_SWITCH_ON"
SOD = "SWITCH_ON_DISABLED"
RTSO = "READY_TO_SWITCH_ON"
SO = "SWITCHED_ON"
OE = "OPERATION_ENABLED"
QSA = "QUICK_STOP_ACTIVE"
FRA = "FAULT_REACTION_ACTIVE"
FAULT = "FAULT"

# Status word patterns (bit 4 voltage enabled = DC link present, bit 5 quick
# stop = 1 when no quick stop is active).  Fault = 0x0038 as in example 3.
STATUS_BITS = {
    NOT_READY: 0x0010,
    SOD: 0x0070,
    RTSO: 0x0031,
    SO: 0x0033,
    OE: 0x0037,
    QSA: 0x0017,
    FRA: 0x003F,
    FAULT: 0x0038,
}

ERR_WATCHDOG = 0x8130    # CiA 301/402 "life guard / heartbeat error" (603Fh)

# Object dictionary of the documented objects (drivemaster2 indices).
#   index: (name, type, access)
OBJECTS = {
    2: ("Hardware ID", "U32", "ro"),
    5: ("Hardware Version", "U32", "ro"),
    16: ("Software ID", "U32", "ro"),
    17: ("Software Version", "U32", "ro"),
    33: ("DC Voltage", "I16", "ro"),
    41: ("Temperature Power Stage", "I16", "ro"),
    63: ("Temperature Motor", "I16", "ro"),
    67: ("Status Word", "U16", "ro"),
    68: ("Control Word", "U16", "rw"),
    70: ("Error Code", "U16", "ro"),
    120: ("Max Speed", "I16", "ro"),
    168: ("Actual Speed", "I16", "ro"),
    171: ("Max Iq Current", "I16", "ro"),
    177: ("Speed Scaling", "I32", "ro"),
    182: ("Current Scaling", "I32", "ro"),
    209: ("Target Torque Limit", "I16", "rw"),
    210: ("Target Velocity", "I16", "rw"),
    390: ("Actual Output Power", "I16", "ro"),
    431: ("Actual Apparent Current", "I16", "ro"),
    434: ("Output Voltage", "I16", "ro"),
}
TYPE_SIZE = {"U16": 2, "I16": 2, "U32": 4, "I32": 4}

# Default TxPDO (input registers): register -> object index (32-bit objects
# occupy two registers, high word first).
TXPDO_MAP = [
    (2000, 67), (2001, 168), (2002, 209), (2003, 431), (2004, 390),
    (2005, 70), (2006, 41), (2007, 63), (2008, 434), (2009, 33),
    (2010, 2), (2012, 5), (2014, 16), (2016, 17), (2018, 171),
    (2019, 120), (2020, 177), (2022, 182),
]
# Default RxPDO (holding registers): register -> object index (None = watchdog)
RXPDO_MAP = [(3000, 68), (3001, 210), (3002, 209), (3003, None)]


def _build_reg_map(pdo):
    m = {}
    for reg, idx in pdo:
        if idx is None:
            m[reg] = (None, 0)
            continue
        size = TYPE_SIZE[OBJECTS[idx][1]]
        for w in range(size // 2):
            m[reg + w] = (idx, w)
    return m


TX_REGS = _build_reg_map(TXPDO_MAP)     # 2000..2023
RX_REGS = _build_reg_map(RXPDO_MAP)     # 3000..3003


def to_unsigned(value, typ):
    bits = TYPE_SIZE[typ] * 8
    return value & ((1 << bits) - 1)


def from_unsigned(raw, typ):
    bits = TYPE_SIZE[typ] * 8
    raw &= (1 << bits) - 1
    if typ[0] == "I" and raw & (1 << (bits - 1)):
        raw -= 1 << bits
    return raw


# ---------------------------------------------------------------------------
# One drive axis (a double-axis SD2 has two of these, each at its own address)
# ---------------------------------------------------------------------------
class Axis:
    # plausible drive data
    SPEED_SCALING = 60_000_000     # 0.001 rpm -> 60000 rpm = 1000 Hz
    MAX_SPEED_NORM = 0x3FFF        # 0x3FFF = Speed Scaling  -> 1000.0 Hz
    MAX_SPEED_01HZ = 10000         # the same in 0.1 Hz
    MAX_IQ = 200                   # 20.0 A
    CURRENT_SCALING = 20_000       # 0.001 A -> 20.000 A
    DC_VOLTAGE = 5600              # 560.0 V
    T_AMBIENT_STAGE = 250          # 25.0 degC
    T_AMBIENT_MOTOR = 230          # 23.0 degC
    COAST_RATE = 300.0             # 0.1 Hz/s when the power stage is off
    QUICKSTOP_RATE = 5000.0        # 0.1 Hz/s quick stop ramp

    def __init__(self, name, address):
        self.name = name
        self.address = address
        self.state = NOT_READY
        self.control_word = 0
        self.target_velocity = 0        # obj 210, 0.1 Hz
        self.torque_limit = 0           # obj 209, 0.1 A
        self.watchdog = 0               # reg 3003, ms
        self.wd_deadline = None
        self.error_code = 0
        self.speed = 0.0                # actual speed, 0.1 Hz (float internally)
        self.current = 0
        self.voltage = 0
        self.power = 0
        self.last_t = time.monotonic()
        self.hw_id = 0x00000201 if name == "A" else 0x00000202
        self.hw_version = 0x00020010    # 2.16
        self.sw_id = 0x00000410
        self.sw_version = 0x00040012    # 4.18
        # boot: Not ready to switch on -> Switch on disabled (automatic)
        self.state = SOD

    # -- derived values ----------------------------------------------------
    def effective_target(self):
        if self.state != OE or (self.control_word & 0x0100):   # bit 8 halt
            return 0.0
        t = self.target_velocity
        return float(max(-self.MAX_SPEED_01HZ, min(self.MAX_SPEED_01HZ, t)))

    def effective_limit(self):
        return min(abs(self.torque_limit), self.MAX_IQ)

    def status_word(self):
        sw = STATUS_BITS[self.state]
        if self.state == OE:
            tgt = self.effective_target()
            if int(round(self.speed)) == int(tgt):
                sw |= 0x0400            # bit 10 target reached
            if abs(self.target_velocity) > self.MAX_SPEED_01HZ:
                sw |= 0x0800            # bit 11 internal limit active
        return sw

    def object_value(self, idx):
        self.update()
        return {
            2: self.hw_id, 5: self.hw_version, 16: self.sw_id,
            17: self.sw_version, 33: self.DC_VOLTAGE,
            41: self.T_AMBIENT_STAGE, 63: self.T_AMBIENT_MOTOR,
            67: self.status_word(), 68: self.control_word,
            70: self.error_code, 120: self.MAX_SPEED_NORM,
            168: int(round(self.speed)), 171: self.MAX_IQ,
            177: self.SPEED_SCALING, 182: self.CURRENT_SCALING,
            209: self.torque_limit, 210: self.target_velocity,
            390: self.power, 431: self.current, 434: self.voltage,
        }[idx]

    def read_register(self, reg):
        if reg in TX_REGS:
            idx, w = TX_REGS[reg]
        else:
            idx, w = RX_REGS[reg]
            if idx is None:
                return self.watchdog
        typ = OBJECTS[idx][1]
        raw = to_unsigned(self.object_value(idx), typ)
        if TYPE_SIZE[typ] == 4:
            return (raw >> 16) & 0xFFFF if w == 0 else raw & 0xFFFF
        return raw

    # -- writes ------------------------------------------------------------
    def write_registers(self, start, values):
        """values already validated to lie in 3000..3003."""
        self.update()
        cw = None
        for i, v in enumerate(values):
            reg = start + i
            idx, _ = RX_REGS[reg]
            if idx is None:
                self.set_watchdog(v)
            elif idx == 68:
                cw = v
            else:
                self.write_object(idx, from_unsigned(v, OBJECTS[idx][1]))
        if cw is not None:
            self.write_control_word(cw)

    def set_watchdog(self, v):
        self.watchdog = v
        self.wd_deadline = (time.monotonic() + v / 1000.0) if v else None

    def write_object(self, idx, value):
        if idx == 68:
            self.write_control_word(value)
        elif idx == 209:
            self.torque_limit = value
        elif idx == 210:
            self.target_velocity = value

    def write_control_word(self, cw):
        prev = self.control_word
        self.control_word = cw
        st = self.state
        if st == FAULT:
            if (cw & 0x80) and not (prev & 0x80):      # fault reset, rising edge
                self.state = SOD
                self.error_code = 0
                if self.watchdog:
                    self.wd_deadline = time.monotonic() + self.watchdog / 1000.0
            return
        if st in (FRA, NOT_READY):
            return
        if cw & 0x80:            # fault reset bit outside fault: no command
            return
        shutdown = (cw & 0x87) == 0x06
        switch_on = (cw & 0x8F) == 0x07
        enable = (cw & 0x8F) == 0x0F
        disable_voltage = (cw & 0x82) == 0x00
        quick_stop = (cw & 0x86) == 0x02
        if st == SOD:
            if shutdown:
                self.state = RTSO
        elif st == RTSO:
            if switch_on:
                self.state = SO
            elif enable:
                self.state = OE          # transitions 3 + 4 (manual example 1)
            elif disable_voltage or quick_stop:
                self.state = SOD
        elif st == SO:
            if enable:
                self.state = OE
            elif shutdown:
                self.state = RTSO
            elif disable_voltage or quick_stop:
                self.state = SOD
        elif st == OE:
            if switch_on:                # "disable operation"
                self.state = SO
            elif shutdown:
                self.state = RTSO
            elif disable_voltage:
                self.state = SOD
            elif quick_stop:
                self.state = QSA
        elif st == QSA:
            if disable_voltage:
                self.state = SOD

    # -- time based behaviour ----------------------------------------------
    def update(self):
        now = time.monotonic()
        dt = now - self.last_t
        if dt < 0:
            dt = 0
        self.last_t = now
        # watchdog
        if self.wd_deadline is not None and now > self.wd_deadline and \
                self.state not in (FAULT,):
            self.state = FAULT
            self.error_code = ERR_WATCHDOG
            self.wd_deadline = None
        # motion
        dt = min(dt, 1.0)
        if self.state == OE:
            tgt = self.effective_target()
            lim = self.effective_limit()
            rate = lim * 20.0            # 10 A -> 200 Hz/s
            if rate <= 0:
                rate = 0.0
                self._coast(dt)
            else:
                self._approach(tgt, rate * dt)
            accelerating = rate > 0 and abs(tgt - self.speed) > 0.5
            load = 5 + abs(self.speed) * 50 / self.MAX_SPEED_01HZ   # 0.1 A
            cur = lim if accelerating else min(load, lim if lim else load)
            self.current = int(round(cur))
            self.voltage = int(round(abs(self.speed) * 4000 / self.MAX_SPEED_01HZ))
            self.power = int(round(math.sqrt(3) * (self.voltage / 10.0) *
                                   (self.current / 10.0) * 0.85 / 100.0))
        else:
            if self.state == QSA:
                self._approach(0.0, self.QUICKSTOP_RATE * dt)
                if abs(self.speed) < 0.5:
                    self.speed = 0.0
                    self.state = SOD          # quick stop option 2
            else:
                self._coast(dt)
            self.current = 5 if self.state == QSA and self.speed else 0
            self.voltage = 0
            self.power = 0

    def _approach(self, tgt, step):
        if self.speed < tgt:
            self.speed = min(tgt, self.speed + step)
        elif self.speed > tgt:
            self.speed = max(tgt, self.speed - step)

    def _coast(self, dt):
        self._approach(0.0, self.COAST_RATE * dt)

    # -- state dump ----------------------------------------------------------
    def dump(self):
        self.update()
        inputs = {str(r): self.read_register(r) for r in sorted(TX_REGS)}
        holding = {str(r): self.read_register(r) for r in sorted(RX_REGS)}
        objs = {}
        for idx, (name, typ, acc) in sorted(OBJECTS.items()):
            objs["%d/0" % idx] = {"index": idx, "subindex": 0, "name": name,
                                  "type": typ, "access": acc,
                                  "value": self.object_value(idx)}
        return {
            "slave_address": self.address,
            "ds402_state": self.state,
            "input_registers": inputs,
            "holding_registers": holding,
            "objects": objs,
            "watchdog": {"timeout_ms": self.watchdog,
                         "armed": self.wd_deadline is not None},
        }


# ---------------------------------------------------------------------------
# The drive (one RS-485 port, one or two axes)
# ---------------------------------------------------------------------------
class Drive:
    def __init__(self, args, addresses):
        self.args = args
        self.axes = {}
        for name, addr in zip("AB", addresses):
            self.axes[addr] = Axis(name, addr)
        self.counters = dict.fromkeys(
            ("bus_message", "bus_comm_error", "bus_exception",
             "slave_message", "slave_no_response"), 0)

    def inc(self, name):
        self.counters[name] = (self.counters[name] + 1) & 0xFFFF

    def tick(self):
        for ax in self.axes.values():
            ax.update()

    # -- frame level -----------------------------------------------------------
    def bad_frame(self):
        """A frame with a CRC error (or too short to carry one): silent."""
        self.inc("bus_message")
        self.inc("bus_comm_error")

    def handle_frame(self, frame):
        """frame: CRC-valid RTU frame.  Returns response bytes or None."""
        self.inc("bus_message")
        addr = frame[0]
        pdu = bytes(frame[1:-2])
        if addr == 0:                               # broadcast
            self.inc("slave_message")
            self.inc("slave_no_response")
            fc = pdu[0]
            if fc in (0x06, 0x10):                  # execute writes, no reply
                for ax in self.axes.values():
                    self.process(ax, pdu)
            return None
        ax = self.axes.get(addr)
        if ax is None:                              # other slave on the bus
            return None
        self.inc("slave_message")
        resp = self.process(ax, pdu)
        if resp is None:
            self.inc("slave_no_response")
            return None
        if resp[0] & 0x80:
            self.inc("bus_exception")
        return add_crc(bytes((addr,)) + resp)

    # -- PDU level ---------------------------------------------------------------
    def process(self, ax, pdu):
        fc = pdu[0]
        try:
            if fc in (0x03, 0x04):
                return self.fc_read(ax, pdu)
            if fc == 0x06:
                return self.fc06(ax, pdu)
            if fc == 0x08:
                return self.fc08(ax, pdu)
            if fc == 0x10:
                return self.fc16(ax, pdu)
            if fc == 0x17:
                return self.fc23(ax, pdu)
            if fc == 0x2B:
                return self.fc43(ax, pdu)
            return exc(fc, ILLEGAL_FUNCTION)
        except Exception as e:                      # never die on a frame
            sys.stderr.write("internal error on %s: %r\n" % (pdu.hex(), e))
            return exc(fc, SLAVE_DEVICE_FAILURE)

    @staticmethod
    def regs_valid(start, count, writing):
        regs = range(start, start + count)
        if writing:
            return all(r in RX_REGS for r in regs)
        return all(r in RX_REGS for r in regs) or all(r in TX_REGS for r in regs)

    def fc_read(self, ax, pdu):
        fc = pdu[0]
        if len(pdu) != 5:
            return exc(fc, ILLEGAL_DATA_VALUE)
        start, count = struct.unpack(">HH", pdu[1:5])
        if not 1 <= count <= MAX_REGS:
            return exc(fc, ILLEGAL_DATA_VALUE)
        if not self.regs_valid(start, count, False):
            return exc(fc, ILLEGAL_DATA_ADDRESS)
        ax.update()
        vals = [ax.read_register(start + i) for i in range(count)]
        return bytes((fc, 2 * count)) + struct.pack(">%dH" % count, *vals)

    def fc06(self, ax, pdu):
        if len(pdu) != 5:
            return exc(0x06, ILLEGAL_DATA_VALUE)
        reg, val = struct.unpack(">HH", pdu[1:5])
        if not self.regs_valid(reg, 1, True):
            return exc(0x06, ILLEGAL_DATA_ADDRESS)
        ax.write_registers(reg, [val])
        return pdu

    def fc16(self, ax, pdu):
        if len(pdu) < 6:
            return exc(0x10, ILLEGAL_DATA_VALUE)
        start, count, bc = struct.unpack(">HHB", pdu[1:6])
        if not 1 <= count <= MAX_REGS or bc != 2 * count or len(pdu) != 6 + bc:
            return exc(0x10, ILLEGAL_DATA_VALUE)
        if not self.regs_valid(start, count, True):
            return exc(0x10, ILLEGAL_DATA_ADDRESS)
        vals = struct.unpack(">%dH" % count, pdu[6:6 + bc])
        ax.write_registers(start, vals)
        return pdu[:5]

    def fc23(self, ax, pdu):
        if len(pdu) < 10:
            return exc(0x17, ILLEGAL_DATA_VALUE)
        rstart, rcount, wstart, wcount, bc = struct.unpack(">HHHHB", pdu[1:10])
        if not 1 <= rcount <= MAX_REGS or not 1 <= wcount <= MAX_REGS or \
                bc != 2 * wcount or len(pdu) != 10 + bc:
            return exc(0x17, ILLEGAL_DATA_VALUE)
        if not self.regs_valid(wstart, wcount, True) or \
                not self.regs_valid(rstart, rcount, False):
            return exc(0x17, ILLEGAL_DATA_ADDRESS)
        vals = struct.unpack(">%dH" % wcount, pdu[10:10 + bc])
        ax.write_registers(wstart, vals)             # write before read
        out = [ax.read_register(rstart + i) for i in range(rcount)]
        return bytes((0x17, 2 * rcount)) + struct.pack(">%dH" % rcount, *out)

    def fc08(self, ax, pdu):
        if len(pdu) != 5:
            return exc(0x08, ILLEGAL_DATA_VALUE)
        sub, data = struct.unpack(">HH", pdu[1:5])
        c = self.counters
        if sub == 0x00:
            return pdu
        if sub not in (0x0A, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F):
            return exc(0x08, ILLEGAL_FUNCTION)
        if data != 0:
            return exc(0x08, ILLEGAL_DATA_VALUE)
        if sub == 0x0A:
            for k in c:
                c[k] = 0
            return pdu
        key = {0x0B: "bus_message", 0x0C: "bus_comm_error",
               0x0D: "bus_exception", 0x0E: "slave_message",
               0x0F: "slave_no_response"}[sub]
        return struct.pack(">BHH", 0x08, sub, c[key])

    # FC 43 / MEI 0x0D CANopen general reference
    @staticmethod
    def parse_fc43(pdu):
        """Return (fields, layout) or None.  Layout 'A' = table layout with
        the reserved byte, 'B' = layout of the manual's example (no reserved
        byte)."""
        if len(pdu) < 3:
            return None
        write = bool(pdu[2] & 0x80)
        # layout A: fc mei ctrl res node idx(2) sub off(2) cnt(2) data
        if len(pdu) >= 12:
            n = (pdu[10] << 8) | pdu[11]
            if len(pdu) == 12 + (n if write else 0):
                return dict(ctrl=pdu[2], node=pdu[4],
                            index=(pdu[5] << 8) | pdu[6], sub=pdu[7],
                            offset=(pdu[8] << 8) | pdu[9], count=n,
                            data=pdu[12:], hdr_len=12), "A"
        # layout B: fc mei ctrl node idx(2) sub off(2) cnt(2) data
        if len(pdu) >= 11:
            n = (pdu[9] << 8) | pdu[10]
            if len(pdu) == 11 + (n if write else 0):
                return dict(ctrl=pdu[2], node=pdu[3],
                            index=(pdu[4] << 8) | pdu[5], sub=pdu[6],
                            offset=(pdu[7] << 8) | pdu[8], count=n,
                            data=pdu[11:], hdr_len=11), "B"
        return None

    def fc43(self, ax, pdu):
        if len(pdu) < 2:
            return exc(0x2B, ILLEGAL_DATA_VALUE)
        if pdu[1] != 0x0D:
            return exc(0x2B, ILLEGAL_FUNCTION)      # only MEI 0x0D supported
        parsed = self.parse_fc43(pdu)
        if parsed is None:
            return exc(0x2B, ILLEGAL_DATA_VALUE)
        f, _layout = parsed
        if f["count"] > 4:
            return exc(0x2B, ILLEGAL_DATA_VALUE)
        if f["node"] != ax.address:
            return exc(0x2B, ILLEGAL_DATA_ADDRESS)
        hdr = pdu[:f["hdr_len"] - 2]                 # up to the byte count
        ctrl = f["ctrl"]
        if ctrl & 0x7F:
            return sdo_err(SDO_CMD_UNKNOWN)
        if f["offset"] != 0:
            return sdo_err(SDO_UNSUPPORTED_ACCESS)
        idx = f["index"]
        if idx >= 0x2000 or idx not in OBJECTS:
            return sdo_err(SDO_NO_OBJECT)
        if f["sub"] != 0:
            return sdo_err(SDO_NO_SUBINDEX)
        _name, typ, acc = OBJECTS[idx]
        size = TYPE_SIZE[typ]
        n = f["count"]
        if ctrl & 0x80:                              # write
            if acc == "ro":
                return sdo_err(SDO_WRITE_RO)
            if n > size:
                return sdo_err(SDO_LEN_TOO_LONG)
            if n < size:
                return sdo_err(SDO_LEN_TOO_SHORT)
            raw = int.from_bytes(f["data"], "little")
            ax.update()
            ax.write_object(idx, from_unsigned(raw, typ))
            return pdu                               # echo
        # read
        if acc == "wo":
            return sdo_err(SDO_READ_WO)
        if n > size:
            return sdo_err(SDO_LEN_TOO_LONG)
        if 0 < n < size:
            return sdo_err(SDO_LEN_TOO_SHORT)
        raw = to_unsigned(ax.object_value(idx), typ)
        return hdr + struct.pack(">H", size) + raw.to_bytes(size, "little")

    # -- state file -------------------------------------------------------------
    def dump(self):
        return {
            "device": "SIEB & MEYER SD2x (simulated)",
            "settings": {
                "baud": self.args.baud, "parity": self.args.parity,
                "address_mode": self.args.address_mode,
                "id_switch": self.args.id_switch,
                "programmable_address": self.args.prog_address,
                "axes": self.args.axes,
                "slave_addresses": sorted(self.axes),
            },
            "axes": {str(a): ax.dump() for a, ax in sorted(self.axes.items())},
            "diagnostic_counters": dict(self.counters),
        }


def exc(fc, code):
    return bytes(((fc | 0x80) & 0xFF, code))


def sdo_err(code):
    return bytes((0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + struct.pack("<I", code)


# ---------------------------------------------------------------------------
# RTU-over-TCP framing
# ---------------------------------------------------------------------------
def expected_lengths(buf):
    """Length rules for requests.  Returns a list of candidate total frame
    lengths (address..CRC), [] if the function code has no length rule, or
    None if more bytes are needed to tell."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (0x03, 0x04, 0x06, 0x08):
        return [8]
    if fc == 0x10:
        return None if len(buf) < 7 else [9 + buf[6]]
    if fc == 0x17:
        return None if len(buf) < 11 else [13 + buf[10]]
    if fc == 0x2B:
        if len(buf) < 4:
            return None
        if buf[2] != 0x0D:
            return []
        write = bool(buf[3] & 0x80)
        if len(buf) < 13:
            return None
        na = (buf[11] << 8) | buf[12]
        nb = (buf[10] << 8) | buf[11]
        return sorted({15 + (na if write else 0), 14 + (nb if write else 0)})
    return []


MAX_BUF = 300          # an RTU frame is at most 256 bytes


class RtuConnection(asyncio.Protocol):
    def __init__(self, server):
        self.server = server
        self.drive = server.drive
        self.buf = bytearray()
        self.garbled = False        # current frame can only end at silence
        self.overrun = False
        self.timer = None
        self.transport = None

    def connection_made(self, transport):
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:
                pass
        self.server.conns.add(self)

    def connection_lost(self, exc_):
        self.server.conns.discard(self)
        if self.timer:
            self.timer.cancel()
            self.timer = None

    def data_received(self, data):
        try:
            self.buf += data
            incomplete = self.parse()
            if len(self.buf) > MAX_BUF:             # not a frame any more
                self.overrun = True
                self.garbled = True
                incomplete = False
                del self.buf[:]
            if self.timer:
                self.timer.cancel()
                self.timer = None
            if self.buf or self.overrun:
                # t3.5 ends a frame as on the line; a frame that the length
                # rules say is still incomplete gets the (longer) TCP
                # reassembly allowance instead (see DECISIONS.md, framing).
                delay = self.server.reassembly if incomplete else self.server.t35
                self.timer = asyncio.get_running_loop().call_later(
                    delay, self.silence)
        except Exception as e:                      # pragma: no cover
            sys.stderr.write("framing error: %r\n" % (e,))
            del self.buf[:]

    def parse(self):
        """Cut complete frames off the buffer.  Returns True when the
        buffer holds the beginning of a frame that is not complete yet."""
        while not self.garbled:
            if len(self.buf) < 4:
                return bool(self.buf)
            cands = expected_lengths(self.buf)
            if cands is None:
                return True
            if not cands:
                self.garbled = True        # no length rule: wait for silence
                return False
            done = False
            for L in cands:
                if len(self.buf) >= L and crc_ok(self.buf[:L]):
                    frame = bytes(self.buf[:L])
                    del self.buf[:L]
                    self.dispatch(frame)
                    done = True
                    break
            if done:
                continue
            if all(len(self.buf) >= L for L in cands):
                self.garbled = True        # CRC error / bad length: silence ends it
                return False
            return True
        return False

    def silence(self):
        """t3.5 without a byte: whatever is buffered is one frame."""
        self.timer = None
        try:
            frame = bytes(self.buf)
            del self.buf[:]
            overrun, self.overrun, self.garbled = self.overrun, False, False
            if overrun:
                self.drive.bad_frame()
                return
            if not frame:
                return
            if crc_ok(frame):
                self.dispatch(frame)
            else:
                self.drive.bad_frame()
        except Exception as e:                      # pragma: no cover
            sys.stderr.write("silence handler error: %r\n" % (e,))

    def dispatch(self, frame):
        resp = self.drive.handle_frame(frame)
        if resp and self.transport and not self.transport.is_closing():
            self.transport.write(resp)


class Server:
    def __init__(self, drive, t35, reassembly):
        self.drive = drive
        self.t35 = t35
        self.reassembly = max(t35, reassembly)
        self.conns = set()


# ---------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------
def compute_addresses(args, parser):
    if args.address is not None:
        a = args.address
        addrs = [a] if args.axes == 1 else [a, a + 1]
    elif args.address_mode == "switch":
        a = args.id_switch * 2 + 1
        addrs = [a] if args.axes == 1 else [a, a + 1]
    elif args.address_mode == "switch+prog":
        a = args.id_switch * 2 + args.prog_address + 1
        addrs = [a] if args.axes == 1 else [a, a + 1]
    else:                                            # prog
        addrs = [args.prog_address + 1]
    for a in addrs:
        if not 1 <= a <= 254:
            parser.error("resulting slave address %d outside 1..254" % a)
    return addrs


def write_state(drive, path):
    if not path:
        return
    try:
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(drive.dump(), f, indent=1, sort_keys=True)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except Exception as e:
        sys.stderr.write("state write failed: %r\n" % (e,))


async def main_async(args, addresses):
    drive = Drive(args, addresses)
    if args.t35_ms is not None:
        t35 = args.t35_ms / 1000.0
    elif args.baud > 19200:
        t35 = 0.00175
    else:
        bits = 10 if args.parity == "none" else 11
        t35 = 3.5 * bits / args.baud
    server = Server(drive, t35, args.reassembly_ms / 1000.0)
    host, _, port = args.listen.rpartition(":")
    host = host.strip("[]")
    loop = asyncio.get_running_loop()
    srv = await loop.create_server(lambda: RtuConnection(server), host,
                                   int(port), reuse_address=True)
    port = srv.sockets[0].getsockname()[1]
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    if hasattr(signal, "SIGUSR1"):
        loop.add_signal_handler(signal.SIGUSR1,
                                lambda: write_state(drive, args.state))
    # (modbus-harness: the handlers before the line, so that a SIGUSR1 right after it finds them.)
    sys.stdout.write("listening tcp %s:%d\n" % (host, port))
    sys.stdout.flush()

    async def ticker():
        while True:
            await asyncio.sleep(0.01)
            try:
                drive.tick()
            except Exception as e:                  # pragma: no cover
                sys.stderr.write("tick error: %r\n" % (e,))

    tick_task = asyncio.create_task(ticker())
    await stop.wait()
    tick_task.cancel()
    srv.close()
    for c in list(server.conns):
        if c.transport:
            c.transport.abort()
    write_state(drive, args.state)


def main():
    p = argparse.ArgumentParser(description="SIEB & MEYER SD2x Modbus RTU "
                                "slave simulator (RTU frames over TCP)")
    p.add_argument("--listen", required=True, help="HOST:PORT, e.g. 127.0.0.1:0")
    p.add_argument("--state", help="JSON state file (SIGUSR1 and exit)")
    p.add_argument("--baud", type=int, default=19200,
                   help="baud rate for t3.5 timing: %s" % (BAUD_RATES,))
    p.add_argument("--parity", choices=("none", "even", "odd"), default="none")
    p.add_argument("--address", type=int, default=None,
                   help="slave address (overrides the address-mode rules); "
                        "default: ID switch 0 + 1 = 1")
    p.add_argument("--address-mode", choices=("switch", "switch+prog", "prog"),
                   default="switch")
    p.add_argument("--id-switch", type=lambda s: int(s, 16), default=0,
                   help="ID switch position 0..F")
    p.add_argument("--prog-address", type=int, default=1,
                   help="programmable address 0..253")
    p.add_argument("--axes", type=int, choices=(1, 2), default=1,
                   help="1 = single-axis device, 2 = double-axis device")
    p.add_argument("--t35-ms", type=float, default=None,
                   help="override the inter-frame silence (ms)")
    p.add_argument("--reassembly-ms", type=float, default=100.0,
                   help="how long an incomplete frame (by the length rules) "
                        "waits for the rest of its bytes (TCP segmentation)")
    args = p.parse_args()
    if args.baud not in BAUD_RATES:
        p.error("baud must be one of %s" % (BAUD_RATES,))
    if not 0 <= args.id_switch <= 15:
        p.error("--id-switch must be 0..F")
    if not 0 <= args.prog_address <= 253:
        p.error("--prog-address must be 0..253")
    addresses = compute_addresses(args, p)
    try:
        asyncio.run(main_async(args, addresses))
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
