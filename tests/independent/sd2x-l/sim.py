#!/usr/bin/env python3
"""Simulated RS-485 Modbus RTU line: SIEB & MEYER SD2x drive (addr 1), I/O module (addr 2), SD2x (addr 3).

Transports: RTU over TCP (raw RTU frames in a TCP stream) and/or a serial device / pty.
Standard library only. See DECISIONS.md.
"""
import argparse
import json
import math
import os
import queue
import select
import signal
import socket
import struct
import sys
import threading
import time

BAUDS = (9600, 14400, 19200, 28800, 38400, 57600, 115200)
LOCK = threading.RLock()


def crc16(data):
    c = 0xFFFF
    for x in data:
        c ^= x
        for _ in range(8):
            c = (c >> 1) ^ 0xA001 if c & 1 else c >> 1
    return c


def add_crc(frame):
    c = crc16(frame)
    return frame + bytes((c & 0xFF, c >> 8))


def crc_ok(frame):
    return len(frame) >= 4 and crc16(frame[:-2]) == (frame[-2] | (frame[-1] << 8))


def s16(v):
    v &= 0xFFFF
    return v - 0x10000 if v & 0x8000 else v


def u16(v):
    return v & 0xFFFF


def expected_len(buf):
    """Length of a request ADU whose size follows from the function code, or None."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (1, 2, 3, 4, 5, 6, 8):
        return 8
    if fc in (7, 11, 12, 17):
        return 4
    if fc in (15, 16):
        return 9 + buf[6] if len(buf) >= 7 else None
    if fc == 22:
        return 10
    if fc == 23:
        return 13 + buf[10] if len(buf) >= 11 else None
    if fc == 24:
        return 6
    if fc == 43:
        if len(buf) < 3:
            return None
        if buf[2] == 0x0E:
            return 7
        if buf[2] == 0x0D:
            # table form: addr fc mei ctrl rsv node idx idx sub off off cnt cnt data crc
            if len(buf) < 13:
                return None
            ctrl = buf[3]
            n = (buf[11] << 8) | buf[12]
            return 15 + (n if ctrl & 0x80 else 0)
    return None


class Counters:
    def __init__(self):
        self.clear()

    def clear(self):
        self.bus_message = 0
        self.bus_comm_error = 0
        self.exception_error = 0
        self.slave_message = 0
        self.slave_no_response = 0

    def inc(self, name):
        setattr(self, name, (getattr(self, name) + 1) & 0xFFFF)

    def dump(self):
        return {"bus_message_count": self.bus_message, "bus_communication_error_count": self.bus_comm_error,
                "bus_exception_error_count": self.exception_error, "slave_message_count": self.slave_message,
                "slave_no_response_count": self.slave_no_response}


class ModbusExc(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


class Device:
    kind = "device"
    turnaround = 0.002
    broadcast_fcs = ()

    def __init__(self, address):
        self.address = address
        self.counters = Counters()

    def update(self, now):
        pass

    def diag(self, pdu, subs_zero_any_len):
        if len(pdu) < 5:
            raise ModbusExc(3)
        sub = (pdu[1] << 8) | pdu[2]
        data = pdu[3:]
        if sub == 0:
            if subs_zero_any_len:
                if len(data) % 2 or len(data) > 250:
                    raise ModbusExc(3)
            elif len(data) != 2:
                raise ModbusExc(3)
            return bytes(pdu)
        if sub not in (10, 11, 12, 13, 14, 15):
            raise ModbusExc(1)
        if len(data) != 2 or data != b"\x00\x00":
            raise ModbusExc(3)
        c = self.counters
        if sub == 10:
            c.clear()
            val = 0
        else:
            val = {11: c.bus_message, 12: c.bus_comm_error, 13: c.exception_error,
                   14: c.slave_message, 15: c.slave_no_response}[sub]
        return bytes(pdu[:3]) + struct.pack(">H", val)

    def handle(self, pdu, broadcast):
        """Returns response PDU or None."""
        self.counters.inc("slave_message")
        now = time.monotonic()
        self.update(now)
        if broadcast:
            self.counters.inc("slave_no_response")
            if pdu[0] in self.broadcast_fcs:
                try:
                    self.process(pdu, now)
                except ModbusExc:
                    pass
                except Exception:
                    pass
            return None
        try:
            return self.process(pdu, now)
        except ModbusExc as e:
            self.counters.inc("exception_error")
            return bytes(((pdu[0] | 0x80) & 0xFF, e.code))
        except Exception:
            self.counters.inc("exception_error")
            return bytes(((pdu[0] | 0x80) & 0xFF, 4))


# ----------------------------------------------------------------------------------------------------------------
# SD2x drive
ST_SOD, ST_RTSO, ST_SO, ST_OE, ST_QSA, ST_FRA, ST_FAULT = range(7)
ST_NAMES = {ST_SOD: "Switch on disabled", ST_RTSO: "Ready to switch on", ST_SO: "Switched on",
            ST_OE: "Operation enabled", ST_QSA: "Quick stop active", ST_FRA: "Fault reaction active",
            ST_FAULT: "Fault"}
ST_BITS = {ST_SOD: 0x0040, ST_RTSO: 0x0021, ST_SO: 0x0023, ST_OE: 0x0027, ST_QSA: 0x0007, ST_FRA: 0x000F,
           ST_FAULT: 0x0008}
WATCHDOG_ERROR = 0x8130

ACCEL = 2000.0      # 0.1 Hz / s  (200 Hz/s)
QS_DECEL = 10000.0  # 0.1 Hz / s
COAST = 500.0       # 0.1 Hz / s


class SD2x(Device):
    kind = "SIEB & MEYER SD2x (single-axis)"
    turnaround = 0.002
    broadcast_fcs = (6, 16)

    HW_ID = 0x00005D21
    HW_VER = 0x00020010
    SW_ID = 0x00005D40
    SW_VER = 0x0004001E
    MAX_IQ = 200
    MAX_SPEED = 10000
    SPEED_SCALING = 98298000
    CURRENT_SCALING = 20000

    def __init__(self, id_switch, temps):
        super().__init__(id_switch * 2 + 1)
        self.id_switch = id_switch
        self.cw = 0
        self.target = 0
        self.torque = 0
        self.wd = 0
        self.wd_deadline = None
        self.state = ST_SOD
        self.error = 0
        self.speed = 0.0
        self.current = 0.0
        self.t_ps_base, self.t_mot_base, self.dc_base = temps
        self.t_ps = float(self.t_ps_base)
        self.t_mot = float(self.t_mot_base)
        self.t_last = time.monotonic()
        self.phase = id_switch * 17.0
        self.accelerating = False

    # ---- simulation
    def eff_limit(self):
        return max(0, min(self.torque, self.MAX_IQ))

    def commanded(self):
        if self.state == ST_OE and not (self.cw & 0x0100):
            return float(max(-self.MAX_SPEED, min(self.MAX_SPEED, self.target)))
        return 0.0

    def _advance(self, dt):
        cmd = self.commanded()
        lim = self.eff_limit()
        powered = self.state in (ST_OE, ST_QSA, ST_FRA)
        if not powered or lim <= 0:
            rate = COAST
            cmd = 0.0
        elif self.state == ST_OE:
            rate = ACCEL * min(1.0, lim / 50.0)
        else:
            rate = QS_DECEL * min(1.0, lim / 50.0)
            cmd = 0.0
        diff = cmd - self.speed
        step = rate * dt
        self.accelerating = powered and lim > 0 and abs(diff) > 0.5
        if abs(diff) <= step:
            self.speed = cmd
        else:
            self.speed += step if diff > 0 else -step
        if powered:
            i = 8 + abs(self.speed) * 0.0012 + (20 if self.accelerating else 0)
            self.current = min(float(lim), i) if lim > 0 else 0.0
        else:
            self.current = 0.0
        # thermal (tau 60 s power stage, 300 s motor)
        tgt_ps = self.t_ps_base + self.current * 1.0
        tgt_m = self.t_mot_base + self.current * 1.5
        self.t_ps += (tgt_ps - self.t_ps) * min(1.0, dt / 60.0)
        self.t_mot += (tgt_m - self.t_mot) * min(1.0, dt / 300.0)
        if self.state == ST_FRA and abs(self.speed) < 0.5:
            self.state = ST_FAULT
        if self.state == ST_QSA and lim <= 0 and abs(self.speed) < 0.5:
            pass

    def update(self, now):
        while True:
            dt = now - self.t_last
            if dt <= 0:
                return
            if self.wd_deadline is not None and self.wd_deadline <= now:
                dl = self.wd_deadline
                step = max(0.0, dl - self.t_last)
                self._step(step)
                self.t_last = dl
                self.wd_deadline = None
                self.fault(WATCHDOG_ERROR)
                continue
            self._step(dt)
            self.t_last = now
            return

    def _step(self, dt):
        while dt > 0:
            d = min(dt, 0.05)
            self._advance(d)
            dt -= d

    def fault(self, code):
        if self.state in (ST_FAULT, ST_FRA):
            return
        self.error = code
        if self.state in (ST_OE, ST_QSA) and abs(self.speed) >= 0.5:
            self.state = ST_FRA
        else:
            self.state = ST_FAULT

    def write_cw(self, v):
        old = self.cw
        self.cw = v
        st = self.state
        if v & 0x80:
            if not (old & 0x80) and st == ST_FAULT:
                self.state = ST_SOD
                self.error = 0
            return
        if st in (ST_FAULT, ST_FRA):
            return
        low = v & 0x0F
        if not (v & 0x02):                      # disable voltage
            self.state = ST_SOD
        elif not (v & 0x04):                    # quick stop
            if st == ST_OE:
                self.state = ST_QSA
            elif st in (ST_RTSO, ST_SO):
                self.state = ST_SOD
        elif low & 0x07 == 0x06:                # shutdown
            if st in (ST_SOD, ST_SO, ST_OE):
                self.state = ST_RTSO
        elif low == 0x07:                       # switch on / disable operation
            if st in (ST_RTSO, ST_OE):
                self.state = ST_SO
        elif low == 0x0F:                       # enable operation
            if st in (ST_RTSO, ST_SO, ST_QSA):
                self.state = ST_OE

    def status_word(self):
        sw = ST_BITS[self.state] | 0x0010 | 0x0200
        if self.state in (ST_OE, ST_QSA) and abs(self.speed - self.commanded()) < 0.5:
            sw |= 0x0400
        return sw

    def out_voltage(self):
        if self.state in (ST_OE, ST_QSA, ST_FRA):
            return int(round(max(50.0, abs(self.speed) * 0.4)))
        return 0

    def power(self):
        u = self.out_voltage() / 10.0
        i = self.current / 10.0
        return int(round(1.732 * u * i * 0.8 / 1000.0 * 10))

    def drift(self, period, amp):
        return amp * math.sin(2 * math.pi * (time.monotonic() / period) + self.phase)

    def temp_ps(self):
        return int(round(self.t_ps + self.drift(97.0, 2.0)))

    def temp_motor(self):
        return int(round(self.t_mot + self.drift(151.0, 1.0)))

    def dc_voltage(self):
        return int(round(self.dc_base + self.drift(43.0, 4.0)))

    # ---- register image
    def read_reg(self, a):
        if 3000 <= a <= 3003:
            return (self.cw, u16(self.target), u16(self.torque), self.wd)[a - 3000]
        if 2000 <= a <= 2023:
            i = a - 2000
            r32 = {10: self.HW_ID, 12: self.HW_VER, 14: self.SW_ID, 16: self.SW_VER,
                   20: self.SPEED_SCALING, 22: self.CURRENT_SCALING}
            if i in r32:
                return (r32[i] >> 16) & 0xFFFF
            if i - 1 in r32:
                return r32[i - 1] & 0xFFFF
            v = {0: self.status_word(), 1: int(round(self.speed)), 2: self.eff_limit(),
                 3: int(round(self.current)), 4: self.power(), 5: self.error, 6: self.temp_ps(),
                 7: self.temp_motor(), 8: self.out_voltage(), 9: self.dc_voltage(), 18: self.MAX_IQ,
                 19: self.MAX_SPEED}[i]
            return u16(v)
        raise ModbusExc(2)

    def write_reg(self, a, v, now):
        if a == 3000:
            self.write_cw(v)
        elif a == 3001:
            self.target = s16(v)
        elif a == 3002:
            self.torque = s16(v)
        elif a == 3003:
            self.wd = v
            self.wd_deadline = now + v / 1000.0 if v else None

    @staticmethod
    def writable(a):
        return 3000 <= a <= 3003

    @staticmethod
    def readable(a):
        return 2000 <= a <= 2023 or 3000 <= a <= 3003

    # ---- object dictionary (FC 43)
    def objects(self):
        # index: (size, signed, rw, getter)
        return {
            2: (4, False, False, lambda: self.HW_ID),
            5: (4, False, False, lambda: self.HW_VER),
            16: (4, False, False, lambda: self.SW_ID),
            17: (4, False, False, lambda: self.SW_VER),
            33: (2, True, False, self.dc_voltage),
            41: (2, True, False, self.temp_ps),
            63: (2, True, False, self.temp_motor),
            67: (2, False, False, self.status_word),
            68: (2, False, True, lambda: self.cw),
            70: (2, False, False, lambda: self.error),
            120: (2, True, False, lambda: self.MAX_SPEED),
            168: (2, True, False, lambda: int(round(self.speed))),
            171: (2, True, False, lambda: self.MAX_IQ),
            177: (4, True, False, lambda: self.SPEED_SCALING),
            182: (4, True, False, lambda: self.CURRENT_SCALING),
            209: (2, True, True, lambda: self.torque),
            210: (2, True, True, lambda: self.target),
            390: (2, True, False, self.power),
            431: (2, True, False, lambda: int(round(self.current))),
            434: (2, True, False, self.out_voltage),
        }

    def obj_write(self, idx, value, now):
        if idx == 68:
            self.write_cw(value & 0xFFFF)
        elif idx == 209:
            self.torque = s16(value)
        elif idx == 210:
            self.target = s16(value)

    # ---- function codes
    def process(self, pdu, now):
        fc = pdu[0]
        n = len(pdu)
        if fc in (3, 4):
            if n != 5:
                raise ModbusExc(3)
            a, q = struct.unpack(">HH", pdu[1:5])
            if not 1 <= q <= 48:
                raise ModbusExc(3)
            if not all(self.readable(x) for x in range(a, a + q)):
                raise ModbusExc(2)
            vals = [self.read_reg(x) for x in range(a, a + q)]
            return bytes((fc, 2 * q)) + struct.pack(">%dH" % q, *vals)
        if fc == 6:
            if n != 5:
                raise ModbusExc(3)
            a, v = struct.unpack(">HH", pdu[1:5])
            if not self.writable(a):
                raise ModbusExc(2)
            self.write_reg(a, v, now)
            return bytes(pdu)
        if fc == 16:
            if n < 6:
                raise ModbusExc(3)
            a, q = struct.unpack(">HH", pdu[1:5])
            bc = pdu[5]
            if not 1 <= q <= 48 or bc != 2 * q or n != 6 + bc:
                raise ModbusExc(3)
            if not all(self.writable(x) for x in range(a, a + q)):
                raise ModbusExc(2)
            vals = struct.unpack(">%dH" % q, pdu[6:6 + bc])
            for i, v in enumerate(vals):
                self.write_reg(a + i, v, now)
            return bytes(pdu[:5])
        if fc == 23:
            if n < 10:
                raise ModbusExc(3)
            ra, rq, wa, wq = struct.unpack(">HHHH", pdu[1:9])
            bc = pdu[9]
            if not 1 <= rq <= 48 or not 1 <= wq <= 48 or bc != 2 * wq or n != 10 + bc:
                raise ModbusExc(3)
            if not all(self.readable(x) for x in range(ra, ra + rq)):
                raise ModbusExc(2)
            if not all(self.writable(x) for x in range(wa, wa + wq)):
                raise ModbusExc(2)
            vals = struct.unpack(">%dH" % wq, pdu[10:10 + bc])
            for i, v in enumerate(vals):
                self.write_reg(wa + i, v, now)
            out = [self.read_reg(x) for x in range(ra, ra + rq)]
            return bytes((23, 2 * rq)) + struct.pack(">%dH" % rq, *out)
        if fc == 8:
            return self.diag(pdu, False)
        if fc == 43:
            return self.fc43(pdu, now)
        raise ModbusExc(1)

    def fc43(self, pdu, now):
        n = len(pdu)
        if n < 2:
            raise ModbusExc(3)
        if pdu[1] != 0x0D:
            raise ModbusExc(1)
        # Decide the form: table form (with reserved byte) first, else Example 2's short form.
        form = None
        for rsv in (True, False):
            hl = 12 if rsv else 11
            if n < hl:
                continue
            ctrl = pdu[2]
            cnt = (pdu[hl - 2] << 8) | pdu[hl - 1]
            need = hl + (cnt if ctrl & 0x80 else 0)
            if n == need:
                form = rsv
                break
        if form is None:
            raise ModbusExc(3)
        hl = 12 if form else 11
        ctrl = pdu[2]
        p = 3
        if form:
            if ctrl not in (0x00, 0x80):
                raise ModbusExc(3)
            if pdu[3] != 0:
                raise ModbusExc(3)
            p = 4
        elif ctrl not in (0x00, 0x80):
            raise ModbusExc(3)
        node = pdu[p]
        idx = (pdu[p + 1] << 8) | pdu[p + 2]
        sub = pdu[p + 3]
        off = (pdu[p + 4] << 8) | pdu[p + 5]
        cnt = (pdu[p + 6] << 8) | pdu[p + 7]
        data = bytes(pdu[hl:])
        if node != self.address:
            raise ModbusExc(2)
        if off != 0 or cnt > 4:
            raise ModbusExc(3)
        header = bytes(pdu[:hl])
        objs = self.objects()
        if idx >= 0x2000 or idx not in objs:
            return self.sdo_err(0xFFFF000B)
        size, signed, rw, getter = objs[idx]
        if sub != 0:
            return self.sdo_err(0xFFFF0014)
        if cnt > size:
            return self.sdo_err(0xFFFF0012)
        if cnt < size:
            return self.sdo_err(0xFFFF0013)
        if ctrl & 0x80:
            if not rw:
                return self.sdo_err(0xFFFF000A)
            value = int.from_bytes(data, "little", signed=False)
            self.obj_write(idx, value, now)
            return bytes(pdu)
        v = getter() & ((1 << (8 * size)) - 1)
        return header + v.to_bytes(size, "little")

    def sdo_err(self, code):
        self.counters.inc("exception_error")
        return bytes((0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + code.to_bytes(4, "little")

    # ---- dump
    def dump(self):
        regs_in = {}
        for a in range(2000, 2024):
            if a in (2006, 2007, 2009):
                continue
            regs_in[str(a)] = self.read_reg(a)
        objs = {}
        for idx, (size, signed, rw, g) in self.objects().items():
            if idx in (33, 41, 63):
                continue
            v = g()
            objs[str(idx)] = {"subindex_0": v, "access": "rw" if rw else "ro"}
        return {
            "kind": self.kind,
            "config": {"id_switch": self.id_switch, "slave_address_mode": "Address selector switch + 1",
                       "programmable_address": 0, "axes": 1, "slave_address": self.address,
                       "node_id": self.address},
            "holding_registers": {str(a): self.read_reg(a) for a in range(3000, 3004)},
            "input_registers": regs_in,
            "objects": objs,
            "drive_state": ST_NAMES[self.state],
            "watchdog_armed": self.wd_deadline is not None,
            "diagnostic_counters": self.counters.dump(),
        }

    def live(self):
        return {"input_registers": {"2006": self.temp_ps(), "2007": self.temp_motor(), "2009": self.dc_voltage()},
                "objects": {"41": self.temp_ps(), "63": self.temp_motor(), "33": self.dc_voltage()}}


# ----------------------------------------------------------------------------------------------------------------
class IOModule(Device):
    kind = "SMIO-8/8 I/O module (8 DI, 8 DO, 2 AI)"
    turnaround = 0.001
    broadcast_fcs = (5, 6, 15, 16)

    def __init__(self, address):
        super().__init__(address)
        self.coils = [0] * 8
        self.di = [1, 1, 0, 0, 0, 0, 0, 0]
        self.di_filter = 3
        self.ai_filter = 4

    def ai1(self):
        return int(round(4980 + 6 * math.sin(time.monotonic() * 2 * math.pi / 37.0)))

    def temp(self):
        return int(round(310 + 2 * math.sin(time.monotonic() * 2 * math.pi / 113.0)))

    def input_regs(self):
        return [self.ai1(), 0, u16(self.temp()), 0x0001]

    def holding(self):
        return [sum(b << i for i, b in enumerate(self.coils)), self.di_filter, self.ai_filter]

    def process(self, pdu, now):
        fc = pdu[0]
        n = len(pdu)
        if fc in (1, 2, 3, 4):
            if n != 5:
                raise ModbusExc(3)
            a, q = struct.unpack(">HH", pdu[1:5])
            if fc in (1, 2):
                if not 1 <= q <= 2000:
                    raise ModbusExc(3)
                if a + q > 8:
                    raise ModbusExc(2)
                bits = (self.coils if fc == 1 else self.di)[a:a + q]
                out = bytearray((q + 7) // 8)
                for i, b in enumerate(bits):
                    if b:
                        out[i // 8] |= 1 << (i % 8)
                return bytes((fc, len(out))) + bytes(out)
            if not 1 <= q <= 125:
                raise ModbusExc(3)
            regs = self.holding() if fc == 3 else self.input_regs()
            if a + q > len(regs):
                raise ModbusExc(2)
            return bytes((fc, 2 * q)) + struct.pack(">%dH" % q, *regs[a:a + q])
        if fc == 5:
            if n != 5:
                raise ModbusExc(3)
            a, v = struct.unpack(">HH", pdu[1:5])
            if v not in (0x0000, 0xFF00):
                raise ModbusExc(3)
            if a >= 8:
                raise ModbusExc(2)
            self.coils[a] = 1 if v else 0
            return bytes(pdu)
        if fc == 6:
            if n != 5:
                raise ModbusExc(3)
            a, v = struct.unpack(">HH", pdu[1:5])
            if a >= 3:
                raise ModbusExc(2)
            self.check_hr(a, v)
            self.write_hr(a, v)
            return bytes(pdu)
        if fc == 15:
            if n < 6:
                raise ModbusExc(3)
            a, q = struct.unpack(">HH", pdu[1:5])
            bc = pdu[5]
            if not 1 <= q <= 1968 or bc != (q + 7) // 8 or n != 6 + bc:
                raise ModbusExc(3)
            if a + q > 8:
                raise ModbusExc(2)
            for i in range(q):
                self.coils[a + i] = (pdu[6 + i // 8] >> (i % 8)) & 1
            return bytes(pdu[:5])
        if fc == 16:
            if n < 6:
                raise ModbusExc(3)
            a, q = struct.unpack(">HH", pdu[1:5])
            bc = pdu[5]
            if not 1 <= q <= 123 or bc != 2 * q or n != 6 + bc:
                raise ModbusExc(3)
            if a + q > 3:
                raise ModbusExc(2)
            vals = struct.unpack(">%dH" % q, pdu[6:6 + bc])
            for i, v in enumerate(vals):
                self.check_hr(a + i, v)
            for i, v in enumerate(vals):
                self.write_hr(a + i, v)
            return bytes(pdu[:5])
        if fc == 8:
            return self.diag(pdu, True)
        raise ModbusExc(1)

    @staticmethod
    def check_hr(a, v):
        lim = (0xFF, 100, 15)[a]
        if v > lim:
            raise ModbusExc(3)

    def write_hr(self, a, v):
        if a == 0:
            self.coils = [(v >> i) & 1 for i in range(8)]
        elif a == 1:
            self.di_filter = v
        else:
            self.ai_filter = v

    def dump(self):
        return {
            "kind": self.kind,
            "config": {"slave_address": self.address},
            "coils": {str(i): b for i, b in enumerate(self.coils)},
            "discrete_inputs": {str(i): b for i, b in enumerate(self.di)},
            "holding_registers": {str(i): v for i, v in enumerate(self.holding())},
            "input_registers": {"1": 0, "3": 0x0001},
            "diagnostic_counters": self.counters.dump(),
        }

    def live(self):
        return {"input_registers": {"0": self.ai1(), "2": self.temp()}}


# ----------------------------------------------------------------------------------------------------------------
class Line:
    def __init__(self, baud, parity):
        self.baud = baud
        self.parity = parity
        bits = 10 + (1 if parity != "none" else 0)
        self.char_time = bits / baud
        self.gap = max(3.5 * self.char_time, 0.005)
        self.devices = {1: SD2x(0, (285, 262, 5650)), 2: IOModule(2), 3: SD2x(1, (301, 255, 5640))}
        self.q = queue.Queue()

    def submit(self, frame, reply):
        self.q.put((frame, reply))

    def run(self):
        while True:
            frame, reply = self.q.get()
            try:
                resp, delay = self.dispatch(frame)
            except Exception as e:  # never die
                sys.stderr.write("line error: %r\n" % (e,))
                resp, delay = None, 0
            if resp is not None:
                time.sleep(delay)
                try:
                    reply(resp)
                except Exception:
                    pass

    def dispatch(self, frame):
        with LOCK:
            devs = list(self.devices.values())
            if len(frame) < 4 or len(frame) > 256 or not crc_ok(frame):
                for d in devs:
                    d.counters.inc("bus_comm_error")
                return None, 0
            for d in devs:
                d.counters.inc("bus_message")
            addr = frame[0]
            pdu = bytes(frame[1:-2])
            if addr == 0:
                for d in devs:
                    d.handle(pdu, True)
                return None, 0
            answers = []
            for d in devs:
                if d.address == addr:
                    r = d.handle(pdu, False)
                    if r is not None:
                        answers.append((add_crc(bytes((addr,)) + r), d.turnaround))
            if not answers:
                return None, 0
            if len(answers) == 1:
                resp, ta = answers[0]
                return resp, ta + len(resp) * self.char_time
            # collision: dominant-low line -> bitwise AND, as long as the longest answer
            L = max(len(a) for a, _ in answers)
            out = bytearray(b"\xff" * L)
            for a, _ in answers:
                for i in range(L):
                    out[i] &= a[i] if i < len(a) else 0xFF
            if crc_ok(bytes(out)):
                out[-1] ^= 0x55
            ta = min(t for _, t in answers)
            return bytes(out), ta + L * self.char_time

    def ticker(self):
        while True:
            time.sleep(0.02)
            with LOCK:
                now = time.monotonic()
                for d in self.devices.values():
                    d.update(now)

    def dump(self):
        with LOCK:
            now = time.monotonic()
            for d in self.devices.values():
                d.update(now)
            return {
                "line": {"baud": self.baud, "parity": self.parity, "data_bits": 8, "stop_bits": 1,
                         "addresses": sorted(self.devices)},
                "devices": {str(a): d.dump() for a, d in sorted(self.devices.items())},
                "live": {str(a): d.live() for a, d in sorted(self.devices.items())},
            }


class Framer:
    """Collects bytes; emits frames by known length (with valid CRC) or on silence."""

    def __init__(self, line, reply):
        self.line = line
        self.reply = reply
        self.buf = bytearray()

    def feed(self, data):
        self.buf += data
        while self.buf:
            L = expected_len(self.buf)
            if L is not None and len(self.buf) >= L and crc_ok(bytes(self.buf[:L])):
                self.line.submit(bytes(self.buf[:L]), self.reply)
                del self.buf[:L]
                continue
            break
        if len(self.buf) > 512:
            self.silence()

    def silence(self):
        if self.buf:
            self.line.submit(bytes(self.buf), self.reply)
            self.buf = bytearray()


def tcp_client(line, conn):
    wlock = threading.Lock()
    alive = [True]

    def reply(data):
        if not alive[0]:
            return
        with wlock:
            conn.sendall(data)

    fr = Framer(line, reply)
    conn.settimeout(line.gap)
    try:
        while True:
            try:
                data = conn.recv(4096)
            except socket.timeout:
                fr.silence()
                continue
            if not data:
                break
            fr.feed(data)
    except OSError:
        pass
    finally:
        alive[0] = False
        try:
            conn.close()
        except OSError:
            pass


def tcp_server(line, srv):
    while True:
        try:
            conn, _ = srv.accept()
        except OSError:
            time.sleep(0.05)
            continue
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        threading.Thread(target=tcp_client, args=(line, conn), daemon=True).start()


def open_serial(path, baud, parity):
    import termios
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    attrs = termios.tcgetattr(fd)
    iflag, oflag, cflag, lflag, ispeed, ospeed, cc = attrs
    iflag &= ~(termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP | termios.INLCR |
               termios.IGNCR | termios.ICRNL | termios.IXON | termios.IXOFF | termios.IXANY | termios.INPCK)
    oflag &= ~termios.OPOST
    lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
    cflag &= ~(termios.CSIZE | termios.PARENB | termios.PARODD | termios.CSTOPB)
    cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
    if parity != "none":
        cflag |= termios.PARENB
        iflag |= termios.INPCK
        if parity == "odd":
            cflag |= termios.PARODD
    cc = list(cc)
    cc[termios.VMIN] = 0
    cc[termios.VTIME] = 0
    sp = getattr(termios, "B%d" % baud, None)
    if sp is not None:
        ispeed = ospeed = sp
    else:
        sys.stderr.write("note: %d baud has no termios constant; port speed left unchanged\n" % baud)
    termios.tcsetattr(fd, termios.TCSANOW, [iflag, oflag, cflag, lflag, ispeed, ospeed, cc])
    return fd


def serial_loop(line, fd):
    wlock = threading.Lock()

    def reply(data):
        with wlock:
            view = memoryview(data)
            while view:
                try:
                    k = os.write(fd, view)
                    view = view[k:]
                except BlockingIOError:
                    select.select([], [fd], [], 0.05)

    fr = Framer(line, reply)
    while True:
        try:
            r, _, _ = select.select([fd], [], [], line.gap)
        except (OSError, ValueError):
            time.sleep(0.05)
            continue
        if not r:
            fr.silence()
            continue
        try:
            data = os.read(fd, 4096)
        except BlockingIOError:
            continue
        except OSError:
            # peer (e.g. socat) went away for a moment; keep trying
            time.sleep(0.05)
            continue
        if not data:
            time.sleep(0.01)
            continue
        fr.feed(data)


def main():
    ap = argparse.ArgumentParser(description="SD2x Modbus RTU multi-drop line simulator")
    ap.add_argument("--listen", help="HOST:PORT for RTU over TCP")
    ap.add_argument("--serial", help="serial device or pty path")
    ap.add_argument("--state", help="JSON state dump file")
    ap.add_argument("--baud", type=int, default=19200)
    ap.add_argument("--parity", choices=("none", "even", "odd"), default="none")
    args = ap.parse_args()
    if args.baud not in BAUDS:
        ap.error("baud must be one of %s" % (BAUDS,))
    if not args.listen and not args.serial:
        ap.error("need --listen or --serial")

    line = Line(args.baud, args.parity)
    stop = threading.Event()

    def write_state():
        if not args.state:
            return
        try:
            data = json.dumps(line.dump(), indent=1, sort_keys=True)
            tmp = args.state + ".tmp"
            with open(tmp, "w") as f:
                f.write(data)
            os.replace(tmp, args.state)
        except Exception as e:
            sys.stderr.write("state dump failed: %r\n" % (e,))

    dump_req = threading.Event()
    signal.signal(signal.SIGTERM, lambda s, f: stop.set())
    signal.signal(signal.SIGINT, lambda s, f: stop.set())
    signal.signal(signal.SIGUSR1, lambda s, f: dump_req.set())

    threading.Thread(target=line.run, daemon=True).start()
    threading.Thread(target=line.ticker, daemon=True).start()

    if args.listen:
        host, _, port = args.listen.rpartition(":")
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind((host, int(port)))
        srv.listen(16)
        threading.Thread(target=tcp_server, args=(line, srv), daemon=True).start()
        print("listening tcp %s:%d" % (host, srv.getsockname()[1]), flush=True)
    if args.serial:
        fd = open_serial(args.serial, args.baud, args.parity)
        threading.Thread(target=serial_loop, args=(line, fd), daemon=True).start()
        print("listening serial %s" % args.serial, flush=True)

    while not stop.is_set():
        stop.wait(0.1)
        if dump_req.is_set():
            dump_req.clear()
            write_state()
    write_state()
    os._exit(0)


if __name__ == "__main__":
    main()
