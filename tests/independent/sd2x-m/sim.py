#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier -- Modbus RTU slave simulator (clean-room).

Transports: RTU over a raw TCP connection (--listen) or a serial device / pty (--serial).
A noisy RS-485 line is simulated deterministically from --seed (see DECISIONS.md).
Standard library only.
"""
import argparse
import asyncio
import json
import math
import os
import random
import signal
import sys
import termios
import time
import tty

# ----------------------------------------------------------------------------- CRC

def crc16(data):
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def add_crc(pdu_with_addr):
    c = crc16(pdu_with_addr)
    return bytes(pdu_with_addr) + bytes((c & 0xFF, c >> 8))


def crc_ok(frame):
    return len(frame) >= 4 and crc16(frame[:-2]) == (frame[-2] | (frame[-1] << 8))

# ----------------------------------------------------------------------------- drive model

SLAVE_ADDRESS = 1          # ID switch 0, mode "Address selector switch + 1" -> 0*2+1
MAX_REGS = 48              # manual: n = 1 to 48 (30h)

# DS402 states
SOD, RTSO, SO, OE, QSA, FRA, FAULT = ("SWITCH_ON_DISABLED", "READY_TO_SWITCH_ON", "SWITCHED_ON",
                                      "OPERATION_ENABLED", "QUICK_STOP_ACTIVE", "FAULT_REACTION_ACTIVE", "FAULT")
SW_BITS = {SOD: 0x0040, RTSO: 0x0021, SO: 0x0023, OE: 0x0027, QSA: 0x0007, FRA: 0x000F, FAULT: 0x0008}
SW_VOLTAGE_ENABLED = 0x0010
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400

ERR_WATCHDOG = 0x8130      # CiA 301 "life guard / heartbeat error" (object 70 mirrors 0x603F)

# identification / limits (factory values of our unit)
HW_ID = 0x00000214
HW_VERSION = 0x00010002        # 1.2
SW_ID = 0x00002A31
SW_VERSION = 0x00040010        # 4.16
MAX_IQ = 250                   # 25.0 A
SPEED_SCALING = 60000000       # 0.001 rpm -> 60000 rpm
CURRENT_SCALING = 32000        # 0.001 A -> 32 A
MAX_SPEED_RAW = 0x3FFF         # = Speed Scaling
MAX_SPEED_01HZ = 10000         # 60000 rpm / 60 = 1000.0 Hz (one pole pair)
ACCEL = 1000.0                 # 0.1 Hz per s  (100 Hz/s)
QS_DECEL = 5000.0              # quick stop ramp, 500 Hz/s
COAST_DECEL = 1500.0           # power stage off: motor coasts down, ~150 Hz/s


def s16(v):
    v &= 0xFFFF
    return v - 0x10000 if v & 0x8000 else v


class Drive:
    def __init__(self):
        self.t0 = time.monotonic()
        self.last = self.t0
        # RxPDO / writable objects
        self.control_word = 0
        self.target_velocity = 0      # obj 210, int16, 0.1 Hz
        self.torque_limit = 0         # obj 209, int16, 0.1 A
        self.watchdog = 0             # reg 3003, ms
        self.wd_deadline = None
        # internal
        self.state = SOD
        self.error_code = 0
        self.speed = 0.0              # 0.1 Hz
        self.accelerating = False
        self.counters = dict(bus_message=0, bus_comm_error=0, bus_exception_error=0,
                             slave_message=0, slave_no_response=0)

    # ---- time-dependent behaviour
    def update(self, now=None):
        now = time.monotonic() if now is None else now
        total = now - self.last
        self.last = now
        if self.wd_deadline is not None and now >= self.wd_deadline:
            self.wd_deadline = None
            if self.state != FAULT:
                self._fault(ERR_WATCHDOG)
        steps = max(1, min(200, int(total / 0.01) + 1))
        dt = max(0.0, total) / steps
        for _ in range(steps):
            self._step(dt)

    def _fault(self, code):
        self.error_code = code
        self.state = FAULT
        print(f"drive: fault 0x{code:04X} (watchdog expired)", file=sys.stderr, flush=True)

    def _effective_target(self):
        if self.state != OE or (self.control_word & 0x0100):
            return 0.0
        t = max(-MAX_SPEED_01HZ, min(MAX_SPEED_01HZ, self.target_velocity))
        if self.torque_limit <= 0:
            return 0.0   # current limit 0: the motor cannot produce torque, it stays at rest
        return float(t)

    def _step(self, dt):
        if dt <= 0:
            self.accelerating = False
            return
        if self.state == QSA:
            dec = QS_DECEL
            tgt = 0.0
        elif self.state == OE:
            tgt = self._effective_target()
            dec = ACCEL
        else:
            tgt = 0.0
            dec = COAST_DECEL
        diff = tgt - self.speed
        stepv = dec * dt
        self.accelerating = abs(diff) > 0.5 and self.state == OE and abs(tgt) > abs(self.speed)
        if abs(diff) <= stepv:
            self.speed = tgt
        else:
            self.speed += stepv if diff > 0 else -stepv
        if self.state == QSA and self.speed == 0.0:
            self.state = SOD

    # ---- control word / DS402 state machine
    def write_control_word(self, cw):
        old = self.control_word
        self.control_word = cw & 0xFFFF
        st = self.state
        if st == FAULT:
            if (cw & 0x80) and not (old & 0x80):
                self.state = SOD
                self.error_code = 0
            return
        if cw & 0x80:
            return  # fault reset bit outside fault: no transition
        if (cw & 0x02) == 0:                       # disable voltage
            self.state = SOD
        elif (cw & 0x06) == 0x02:                  # quick stop
            self.state = QSA if st == OE else SOD
        elif (cw & 0x0F) == 0x06 or (cw & 0x07) == 0x06:   # shutdown
            if st in (SOD, SO, OE, RTSO):
                self.state = RTSO
        elif (cw & 0x0F) == 0x07:                  # switch on / disable operation
            if st in (RTSO, OE, SO):
                self.state = SO
        elif (cw & 0x0F) == 0x0F:                  # enable operation
            if st in (SO, RTSO, OE):
                self.state = OE
            elif st == QSA:
                pass

    def write_watchdog(self, v):
        self.watchdog = v & 0xFFFF
        self.wd_deadline = (time.monotonic() + self.watchdog / 1000.0) if self.watchdog else None

    # ---- derived actual values
    def status_word(self):
        sw = SW_BITS[self.state] | SW_VOLTAGE_ENABLED | SW_REMOTE
        if self.state == OE and abs(self._effective_target() - self.speed) < 0.5:
            sw |= SW_TARGET_REACHED
        return sw

    def actual_speed(self):
        return int(round(self.speed))

    def torque_limit_eff(self):
        return max(0, min(self.torque_limit, MAX_IQ))

    def apparent_current(self):
        if self.state not in (OE, QSA):
            return 0
        f = abs(self.speed)
        cur = 18 + f * 0.002                         # magnetising + friction, 0.1 A
        if self.accelerating:
            cur = max(cur, self.torque_limit_eff() * 0.9)
        if self.state == QSA and f > 0:
            cur = max(cur, MAX_IQ * 0.6)
        return int(round(min(cur, MAX_IQ)))

    def output_voltage(self):
        if self.state not in (OE, QSA):
            return 0
        return int(round(abs(self.speed) * 0.4))    # V/f 0.4 V per Hz, 0.1 V units

    def output_power(self):
        # kW*10 = V*I*sqrt3 / 1000 *10 (V,I in 0.1 units)
        p = self.output_voltage() / 10.0 * self.apparent_current() / 10.0 * 1.732 * 0.3 / 1000.0
        return int(round(p * 10))

    def t_rel(self):
        return time.monotonic() - self.t0

    def temp_power_stage(self):
        run = min(60, abs(self.speed) / 200.0)
        return int(round(170 + run + 2 * math.sin(self.t_rel() / 47.0)))

    def temp_motor(self):
        return int(round(215 + 1.5 * math.sin(self.t_rel() / 83.0 + 1.0)))

    def dc_voltage(self):
        return int(round(5650 + 4 * math.sin(self.t_rel() / 13.0)))

    # ---- object dictionary: index -> (name, type, access, getter, setter)
    def objects(self):
        return {
            2: ("Hardware ID", "U32", "RO", lambda: HW_ID),
            5: ("Hardware Version", "U32", "RO", lambda: HW_VERSION),
            16: ("Software ID", "U32", "RO", lambda: SW_ID),
            17: ("Software Version", "U32", "RO", lambda: SW_VERSION),
            33: ("DC Voltage", "I16", "RO", self.dc_voltage),
            41: ("Temperature Power Stage", "I16", "RO", self.temp_power_stage),
            63: ("Temperature Motor", "I16", "RO", self.temp_motor),
            67: ("Status Word", "U16", "RO", self.status_word),
            68: ("Control Word", "U16", "RW", lambda: self.control_word),
            70: ("Error Code", "U16", "RO", lambda: self.error_code),
            120: ("Max Speed", "I16", "RO", lambda: MAX_SPEED_RAW),
            168: ("Actual Speed", "I16", "RO", self.actual_speed),
            171: ("Max Iq Current", "I16", "RO", lambda: MAX_IQ),
            177: ("Speed Scaling", "I32", "RO", lambda: SPEED_SCALING),
            182: ("Current Scaling", "I32", "RO", lambda: CURRENT_SCALING),
            209: ("Target Torque Limit", "I16", "RW", lambda: self.torque_limit),
            210: ("Target Velocity", "I16", "RW", lambda: self.target_velocity),
            390: ("Actual Output Power", "I16", "RO", self.output_power),
            431: ("Actual Apparent Current", "I16", "RO", self.apparent_current),
            434: ("Output Voltage", "I16", "RO", self.output_voltage),
        }

    def write_object(self, index, raw):
        if index == 68:
            self.write_control_word(raw)
        elif index == 209:
            self.torque_limit = s16(raw)
        elif index == 210:
            self.target_velocity = s16(raw)

    # ---- Modbus register image
    def input_register_map(self):
        """2000.. TxPDO; returns dict addr -> 16-bit value."""
        r = {}
        def w16(a, v):
            r[a] = v & 0xFFFF
        def w32(a, v):
            v &= 0xFFFFFFFF
            r[a] = v >> 16
            r[a + 1] = v & 0xFFFF
        w16(2000, self.status_word())
        w16(2001, self.actual_speed())
        w16(2002, self.torque_limit_eff())
        w16(2003, self.apparent_current())
        w16(2004, self.output_power())
        w16(2005, self.error_code)
        w16(2006, self.temp_power_stage())
        w16(2007, self.temp_motor())
        w16(2008, self.output_voltage())
        w16(2009, self.dc_voltage())
        w32(2010, HW_ID)
        w32(2012, HW_VERSION)
        w32(2014, SW_ID)
        w32(2016, SW_VERSION)
        w16(2018, MAX_IQ)
        w16(2019, MAX_SPEED_RAW)
        w32(2020, SPEED_SCALING)
        w32(2022, CURRENT_SCALING)
        return r

    def holding_register_map(self):
        return {3000: self.control_word, 3001: self.target_velocity & 0xFFFF,
                3002: self.torque_limit & 0xFFFF, 3003: self.watchdog}

    def readable(self, addr):
        return 2000 <= addr <= 2023 or 3000 <= addr <= 3003

    def read_regs(self, start, n):
        im = self.input_register_map()
        hm = self.holding_register_map()
        out = []
        for a in range(start, start + n):
            out.append(im[a] if a in im else hm[a])
        return out

    def write_reg(self, addr, v):
        if addr == 3000:
            self.write_control_word(v)
        elif addr == 3001:
            self.target_velocity = s16(v)
        elif addr == 3002:
            self.torque_limit = s16(v)
        elif addr == 3003:
            self.write_watchdog(v)

    # ---- state dump
    LIVE_REGS = (2006, 2007, 2009)
    LIVE_OBJS = (33, 41, 63)

    def dump(self):
        self.update()
        im = self.input_register_map()
        objs = self.objects()
        def objval(i):
            v = objs[i][3]()
            return v
        return {
            "device": "SIEB & MEYER SD2x (single-axis), Modbus RTU",
            "settings": {"slave_address": SLAVE_ADDRESS, "address_mode": "Address selector switch + 1",
                         "id_switch": 0, "programmable_address": 0,
                         "baud": ARGS.baud, "parity": ARGS.parity},
            "drive_state": self.state,
            "holding_registers": {str(a): v for a, v in self.holding_register_map().items()},
            "input_registers": {str(a): v for a, v in im.items() if a not in self.LIVE_REGS},
            "objects": {f"{i}/0": {"name": o[0], "type": o[1], "access": o[2], "value": objval(i)}
                        for i, o in objs.items() if i not in self.LIVE_OBJS},
            "live": {
                "input_registers": {str(a): im[a] for a in self.LIVE_REGS},
                "objects": {f"{i}/0": {"name": objs[i][0], "value": objval(i)} for i in self.LIVE_OBJS},
            },
            "diagnostic_counters": dict(self.counters),
        }

# ----------------------------------------------------------------------------- Modbus processing

class ModbusSlave:
    def __init__(self, drive):
        self.d = drive

    @staticmethod
    def exc(fc, code):
        return bytes((SLAVE_ADDRESS, (fc | 0x80) & 0xFF, code))

    def handle_frame(self, frame, parity_error=False):
        """frame: bytes as the receiver got them (after t3.5 delimitation).
        Returns the response frame (with CRC) or None."""
        d = self.d
        c = d.counters
        d.update()
        if not frame:
            return None
        c["bus_message"] = (c["bus_message"] + 1) & 0xFFFF
        if parity_error or len(frame) < 4 or len(frame) > 256 or not crc_ok(frame):
            c["bus_comm_error"] = (c["bus_comm_error"] + 1) & 0xFFFF
            return None
        addr = frame[0]
        if addr not in (0, SLAVE_ADDRESS):
            return None
        c["slave_message"] = (c["slave_message"] + 1) & 0xFFFF
        pdu = frame[1:-2]
        fc = pdu[0]
        broadcast = addr == 0
        if broadcast:
            if fc in (0x06, 0x10):
                try:
                    self.process(pdu)
                except Exception:
                    pass
            c["slave_no_response"] = (c["slave_no_response"] + 1) & 0xFFFF
            return None
        if fc == 0 or fc >= 0x80:
            c["slave_no_response"] = (c["slave_no_response"] + 1) & 0xFFFF
            return None
        try:
            resp = self.process(pdu)
        except Exception as e:  # never crash: slave device failure
            print(f"drive: internal error {e!r}", file=sys.stderr, flush=True)
            resp = self.exc(fc, 0x04)
        if resp is None:
            c["slave_no_response"] = (c["slave_no_response"] + 1) & 0xFFFF
            return None
        if resp[1] & 0x80:
            c["bus_exception_error"] = (c["bus_exception_error"] + 1) & 0xFFFF
        return add_crc(resp)

    def process(self, pdu):
        fc = pdu[0]
        h = {0x03: self.fc_read, 0x04: self.fc_read, 0x06: self.fc06, 0x08: self.fc08,
             0x10: self.fc16, 0x17: self.fc23, 0x2B: self.fc43}.get(fc)
        if h is None:
            return self.exc(fc, 0x01)
        return h(pdu)

    def _range_ok(self, start, n, writable=False):
        for a in range(start, start + n):
            if writable:
                if not 3000 <= a <= 3003:
                    return False
            elif not self.d.readable(a):
                return False
        return True

    def fc_read(self, pdu):
        fc = pdu[0]
        if len(pdu) != 5:
            return self.exc(fc, 0x03)
        start = int.from_bytes(pdu[1:3], "big")
        n = int.from_bytes(pdu[3:5], "big")
        if not 1 <= n <= MAX_REGS:
            return self.exc(fc, 0x03)
        if start + n > 0x10000 or not self._range_ok(start, n):
            return self.exc(fc, 0x02)
        vals = self.d.read_regs(start, n)
        return bytes((SLAVE_ADDRESS, fc, 2 * n)) + b"".join(v.to_bytes(2, "big") for v in vals)

    def fc06(self, pdu):
        if len(pdu) != 5:
            return self.exc(0x06, 0x03)
        addr = int.from_bytes(pdu[1:3], "big")
        val = int.from_bytes(pdu[3:5], "big")
        if not 3000 <= addr <= 3003:
            return self.exc(0x06, 0x02)
        self.d.write_reg(addr, val)
        return bytes((SLAVE_ADDRESS,)) + bytes(pdu)

    def fc16(self, pdu):
        if len(pdu) < 6:
            return self.exc(0x10, 0x03)
        start = int.from_bytes(pdu[1:3], "big")
        n = int.from_bytes(pdu[3:5], "big")
        bc = pdu[5]
        if not 1 <= n <= MAX_REGS or bc != 2 * n or len(pdu) != 6 + bc:
            return self.exc(0x10, 0x03)
        if start + n > 0x10000 or not self._range_ok(start, n, writable=True):
            return self.exc(0x10, 0x02)
        for i in range(n):
            self.d.write_reg(start + i, int.from_bytes(pdu[6 + 2 * i:8 + 2 * i], "big"))
        return bytes((SLAVE_ADDRESS,)) + bytes(pdu[0:5])

    def fc23(self, pdu):
        if len(pdu) < 10:
            return self.exc(0x17, 0x03)
        rs = int.from_bytes(pdu[1:3], "big")
        rn = int.from_bytes(pdu[3:5], "big")
        ws = int.from_bytes(pdu[5:7], "big")
        wn = int.from_bytes(pdu[7:9], "big")
        bc = pdu[9]
        if not 1 <= rn <= MAX_REGS or not 1 <= wn <= MAX_REGS or bc != 2 * wn or len(pdu) != 10 + bc:
            return self.exc(0x17, 0x03)
        if rs + rn > 0x10000 or ws + wn > 0x10000 or not self._range_ok(rs, rn) \
                or not self._range_ok(ws, wn, writable=True):
            return self.exc(0x17, 0x02)
        for i in range(wn):  # write first, then read (MODBUS spec)
            self.d.write_reg(ws + i, int.from_bytes(pdu[10 + 2 * i:12 + 2 * i], "big"))
        vals = self.d.read_regs(rs, rn)
        return bytes((SLAVE_ADDRESS, 0x17, 2 * rn)) + b"".join(v.to_bytes(2, "big") for v in vals)

    def fc08(self, pdu):
        if len(pdu) != 5:
            return self.exc(0x08, 0x03)
        sub = int.from_bytes(pdu[1:3], "big")
        data = int.from_bytes(pdu[3:5], "big")
        c = self.d.counters
        keymap = {0x0B: "bus_message", 0x0C: "bus_comm_error", 0x0D: "bus_exception_error",
                  0x0E: "slave_message", 0x0F: "slave_no_response"}
        if sub == 0x00:
            return bytes((SLAVE_ADDRESS,)) + bytes(pdu)
        if sub != 0x0A and sub not in keymap:
            return self.exc(0x08, 0x01)
        if data != 0:
            return self.exc(0x08, 0x03)
        if sub == 0x0A:
            for k in c:
                c[k] = 0
            return bytes((SLAVE_ADDRESS,)) + bytes(pdu)
        return bytes((SLAVE_ADDRESS, 0x08)) + pdu[1:3] + c[keymap[sub]].to_bytes(2, "big")

    def sdo_err(self, code):
        return bytes((SLAVE_ADDRESS, 0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + code.to_bytes(4, "little")

    def fc43(self, pdu):
        # PDU: 2B MEI ctrl res node idxH idxL sub offH offL cntH cntL data...
        if len(pdu) < 2:
            return self.exc(0x2B, 0x03)
        if pdu[1] != 0x0D:
            return self.exc(0x2B, 0x01)
        if len(pdu) < 12:
            return self.exc(0x2B, 0x03)
        ctrl, res, node = pdu[2], pdu[3], pdu[4]
        index = int.from_bytes(pdu[5:7], "big")
        sub = pdu[7]
        off = int.from_bytes(pdu[8:10], "big")
        cnt = int.from_bytes(pdu[10:12], "big")
        data = pdu[12:]
        write = bool(ctrl & 0x80)
        if ctrl & 0x7F or res != 0 or off != 0 or cnt > 4:
            return self.exc(0x2B, 0x03)
        if write and len(data) != cnt:
            return self.exc(0x2B, 0x03)
        if not write and len(data) != 0:
            return self.exc(0x2B, 0x03)
        if node != SLAVE_ADDRESS:
            return self.exc(0x2B, 0x02)
        objs = self.d.objects()
        if index not in objs:
            return self.sdo_err(0xFFFF000B)
        name, typ, access, getter = objs[index]
        if sub != 0:
            return self.sdo_err(0xFFFF0014)
        size = 4 if typ.endswith("32") else 2
        if write and access == "RO":
            return self.sdo_err(0xFFFF000A)
        if cnt > size:
            return self.sdo_err(0xFFFF0012)
        if cnt < size:
            return self.sdo_err(0xFFFF0013)
        header = bytes((SLAVE_ADDRESS,)) + bytes(pdu[0:12])
        if write:
            self.d.write_object(index, int.from_bytes(data, "little"))
            return header + bytes(data)
        v = getter() & (0xFFFFFFFF if size == 4 else 0xFFFF)
        return header + v.to_bytes(size, "little")

# ----------------------------------------------------------------------------- noisy line

class Noise:
    KINDS = (("bit-flip", 45), ("stray-byte", 20), ("byte-lost", 15), ("cut-short", 20))

    def __init__(self, seed, rate):
        self.rng = random.Random(seed)
        self.p = max(0.0, rate) / 1000.0
        self.frames = 0
        self.t0 = time.monotonic()

    def apply(self, frame, direction, conn):
        """Returns (bytes_on_line, parity_error_flag)."""
        self.frames += 1
        if self.p <= 0 or not frame or self.rng.random() >= self.p:
            return frame, False
        r = self.rng.random() * 100
        acc = 0
        kind = "bit-flip"
        for k, w in self.KINDS:
            acc += w
            if r < acc:
                kind = k
                break
        b = bytearray(frame)
        parity_err = False
        if kind == "bit-flip":
            nbits = 1 if self.rng.random() < 0.7 else 2
            i = self.rng.randrange(len(b))
            bits = self.rng.sample(range(8), nbits)
            old = b[i]
            for bit in bits:
                b[i] ^= 1 << bit
            detail = f"byte {i} bits {sorted(bits)} 0x{old:02X}->0x{b[i]:02X}"
            parity_err = ARGS.parity != "none" and nbits % 2 == 1
            if parity_err:
                detail += " (parity error)"
        elif kind == "stray-byte":
            sb = 0x00 if self.rng.random() < 0.5 else 0xFF
            b.insert(0, sb)
            detail = f"stray 0x{sb:02X} before frame"
        elif kind == "byte-lost":
            i = self.rng.randrange(len(b))
            detail = f"byte {i} (0x{b[i]:02X}) lost"
            del b[i]
        else:
            keep = self.rng.randrange(1, len(b)) if len(b) > 1 else 0
            detail = f"cut after {keep} of {len(b)} bytes"
            del b[keep:]
        print(f"noise t={time.monotonic() - self.t0:.3f}s frame#{self.frames} dir={direction} "
              f"conn={conn} kind={kind}: {detail} [{frame.hex(' ')}] -> [{bytes(b).hex(' ')}]",
              file=sys.stderr, flush=True)
        return bytes(b), parity_err

# ----------------------------------------------------------------------------- framing

def expected_len(buf):
    """Length of a request frame by its function code, or None if unknown/not yet known."""
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
        if len(buf) >= 4 and buf[3] & 0x80:
            return 15 + int.from_bytes(buf[12:14], "big") if len(buf) >= 14 else None
        return 15
    return None


class Line:
    """One RTU line segment (a TCP connection or the serial device)."""

    def __init__(self, name, send, slave, noise, loop):
        self.name = name
        self.send = send
        self.slave = slave
        self.noise = noise
        self.loop = loop
        self.buf = bytearray()
        self.timer = None
        self.frames = asyncio.Queue(maxsize=64)
        self.closed = False
        self.worker = loop.create_task(self.work())

    def feed(self, data):
        self.buf += data
        if self.timer:
            self.timer.cancel()
            self.timer = None
        # fast path: a complete frame by length whose CRC checks ends here
        for _ in range(64):
            L = expected_len(self.buf)
            if L is None or len(self.buf) < L or not crc_ok(bytes(self.buf[:L])):
                break
            self._emit(bytes(self.buf[:L]))
            del self.buf[:L]
        if len(self.buf) > 1024:          # runaway garbage: keep only the tail
            del self.buf[:-300]
        if self.buf:
            self.timer = self.loop.call_later(T35, self._silence)

    def _silence(self):
        self.timer = None
        if self.buf:
            self._emit(bytes(self.buf))
            self.buf.clear()

    def _emit(self, frame):
        try:
            self.frames.put_nowait(frame)
        except asyncio.QueueFull:
            pass  # receiver overrun: frame lost

    async def work(self):
        while not self.closed:
            frame = await self.frames.get()
            line_bytes, perr = self.noise.apply(frame, "to-drive", self.name)
            resp = self.slave.handle_frame(line_bytes, perr)
            if resp is None:
                continue
            await asyncio.sleep(T35 + len(resp) * CHAR_T)   # turnaround + transmission time
            out, _ = self.noise.apply(resp, "from-drive", self.name)
            if out and not self.closed:
                try:
                    self.send(out)
                except Exception:
                    pass

    def close(self):
        self.closed = True
        if self.timer:
            self.timer.cancel()
        self.worker.cancel()

# ----------------------------------------------------------------------------- transports

async def serve_tcp(host, port, slave, noise, ready):
    n = [0]

    async def client(reader, writer):
        n[0] += 1
        peer = writer.get_extra_info("peername")
        name = f"tcp#{n[0]}({peer[0]}:{peer[1]})" if peer else f"tcp#{n[0]}"
        line = Line(name, writer.write, slave, noise, asyncio.get_running_loop())
        try:
            while True:
                data = await reader.read(512)
                if not data:
                    break
                line.feed(data)
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            line.close()
            try:
                writer.close()
            except Exception:
                pass

    server = await asyncio.start_server(client, host, port, reuse_address=True)
    p = server.sockets[0].getsockname()[1]
    ready(f"listening tcp {host}:{p}")
    return server


BAUD_CONST = {9600: "B9600", 19200: "B19200", 38400: "B38400", 57600: "B57600", 115200: "B115200"}


def open_serial(path):
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    attrs = termios.tcgetattr(fd)
    cflag = attrs[2]
    cflag &= ~(termios.PARENB | termios.PARODD | termios.CSTOPB | termios.CSIZE)
    cflag |= termios.CS8 | termios.CLOCAL | termios.CREAD
    if ARGS.parity == "even":
        cflag |= termios.PARENB
    elif ARGS.parity == "odd":
        cflag |= termios.PARENB | termios.PARODD
    attrs[2] = cflag
    attrs[6][termios.VMIN] = 0
    attrs[6][termios.VTIME] = 0
    bc = BAUD_CONST.get(ARGS.baud)
    if bc and hasattr(termios, bc):
        attrs[4] = attrs[5] = getattr(termios, bc)
    try:
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
    except termios.error:
        pass
    return fd


async def serve_serial(path, slave, noise, ready):
    loop = asyncio.get_running_loop()
    state = {"fd": None}

    def send(data):
        fd = state["fd"]
        if fd is None:
            return
        view = memoryview(data)
        for _ in range(100):
            try:
                k = os.write(fd, view)
            except BlockingIOError:
                k = 0
            view = view[k:]
            if not view:
                break
            time.sleep(0.001)

    line = Line("serial", send, slave, noise, loop)

    def on_read():
        fd = state["fd"]
        try:
            data = os.read(fd, 512)
        except BlockingIOError:
            return
        except OSError as e:
            data = b""
            print(f"serial: read error {e}", file=sys.stderr, flush=True)
        if not data:
            loop.remove_reader(fd)
            try:
                os.close(fd)
            except OSError:
                pass
            state["fd"] = None
            loop.call_later(1.0, reopen)
            return
        line.feed(data)

    def reopen():
        try:
            state["fd"] = open_serial(path)
            loop.add_reader(state["fd"], on_read)
        except OSError:
            loop.call_later(1.0, reopen)

    state["fd"] = open_serial(path)
    loop.add_reader(state["fd"], on_read)
    ready(f"listening serial {path}")

# ----------------------------------------------------------------------------- main

def write_state(drive):
    if not ARGS.state:
        return
    try:
        tmp = ARGS.state + ".tmp"
        with open(tmp, "w") as f:
            json.dump(drive.dump(), f, indent=1, sort_keys=True)
        os.replace(tmp, ARGS.state)
    except Exception as e:
        print(f"state: cannot write {e!r}", file=sys.stderr, flush=True)


async def main():
    loop = asyncio.get_running_loop()
    drive = Drive()
    slave = ModbusSlave(drive)
    noise = Noise(ARGS.seed, ARGS.noise_rate)
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    loop.add_signal_handler(signal.SIGUSR1, lambda: write_state(drive))

    def ready(msg):
        print(msg, flush=True)

    server = None
    if ARGS.listen:
        host, _, port = ARGS.listen.rpartition(":")
        server = await serve_tcp(host, int(port), slave, noise, ready)
    else:
        await serve_serial(ARGS.serial, slave, noise, ready)

    async def ticker():
        while True:
            drive.update()
            await asyncio.sleep(0.02)
    tk = loop.create_task(ticker())
    await stop.wait()
    tk.cancel()
    if server:
        server.close()
    write_state(drive)


def parse():
    ap = argparse.ArgumentParser(description="SIEB & MEYER SD2x Modbus RTU drive simulator")
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--listen", help="HOST:PORT, RTU frames over raw TCP")
    g.add_argument("--serial", help="serial device / pty path")
    ap.add_argument("--baud", type=int, default=19200,
                    choices=[9600, 14400, 19200, 28800, 38400, 57600, 115200])
    ap.add_argument("--parity", default="none", choices=["none", "even", "odd"])
    ap.add_argument("--state")
    ap.add_argument("--seed", type=int, default=2013)
    ap.add_argument("--noise-rate", type=float, default=5.0,
                    help="mean damaged frames per 1000 frames on the line (both directions)")
    return ap.parse_args()


ARGS = parse()
BITS_PER_CHAR = 10 if ARGS.parity == "none" else 11   # manual: 1 stop bit in every parity mode
CHAR_T = BITS_PER_CHAR / ARGS.baud
T35 = 0.00175 if ARGS.baud > 19200 else 3.5 * CHAR_T

if __name__ == "__main__":
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
