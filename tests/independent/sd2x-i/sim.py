#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier -- Modbus RTU slave simulator.

Clean-room implementation from "Drive Amplifier SD2x - Modbus RTU Connection"
and the public MODBUS specifications. Standard library only.

Transport: RTU ADUs (address, PDU, CRC-16) over a TCP byte stream
("RTU over TCP"), optionally also a real serial line / pty with t3.5 framing.
See DECISIONS.md for all interpretation choices.
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

_CRC_TABLE = []
for _i in range(256):
    _c = _i
    for _ in range(8):
        _c = (_c >> 1) ^ 0xA001 if _c & 1 else _c >> 1
    _CRC_TABLE.append(_c)


def crc16(data):
    c = 0xFFFF
    for b in data:
        c = (c >> 8) ^ _CRC_TABLE[(c ^ b) & 0xFF]
    return c


def with_crc(body):
    c = crc16(body)
    return bytes(body) + bytes((c & 0xFF, c >> 8))


def crc_ok(frame):
    return len(frame) >= 4 and crc16(frame[:-2]) == (frame[-2] | (frame[-1] << 8))


def s16(v):
    v &= 0xFFFF
    return v - 0x10000 if v & 0x8000 else v


# ------------------------------------------------------------ constants --

TX_BASE, TX_LEN = 2000, 24      # 2000..2023 TxPDO (actual values)
RX_BASE, RX_LEN = 3000, 4       # 3000..3003 RxPDO (setpoints)
MAX_REGS = 48                   # manual: n = 1 to 48 (30h)

# DS402 states
SOD, RTSO, SO, OE, QSA, FAULT = ("SWITCH_ON_DISABLED", "READY_TO_SWITCH_ON", "SWITCHED_ON",
                                 "OPERATION_ENABLED", "QUICK_STOP_ACTIVE", "FAULT")
STATE_BITS = {SOD: 0x0040, RTSO: 0x0021, SO: 0x0023, OE: 0x0027, QSA: 0x0007, FAULT: 0x0008}
SW_VOLTAGE_ENABLED = 0x0010
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
SW_INTERNAL_LIMIT = 0x0800

ERR_WATCHDOG = 0x8130           # DS402/301 "life guard / heartbeat error"

# fixed device data (read only)
HW_ID = 0x00000214
HW_VERSION = 0x00010002         # 1.2
SW_ID = 0x00000A21
SW_VERSION = 0x00040010         # 4.16
MAX_IQ = 200                    # 20.0 A  (object 171)
MAX_SPEED = 10000               # 1000.0 Hz (object 120)
SPEED_SCALING = 98298000        # 0.001 rpm: 0x3FFF == 1638.3 Hz == 16383 x 0.1 Hz
CURRENT_SCALING = 1638300       # 0.001 A:   0x3FFF == 1638.3 A  == 16383 x 0.1 A
DC_VOLTAGE = 5650               # 565.0 V
TEMP_POWER_STAGE = 170          # 17.0 degC (manual example 6.2)
TEMP_MOTOR = 200                # 20.0 degC

ACCEL = 5000.0                  # 0.1 Hz per second (500 Hz/s)
QS_DECEL = 10000.0              # quick stop ramp 1000 Hz/s
COAST_DECEL = 1000.0            # free run-down 100 Hz/s

# SDO (extended) error codes
SDO_NO_OBJECT = 0xFFFF000B
SDO_READ_ONLY = 0xFFFF000A
SDO_SUBINDEX = 0xFFFF0014
SDO_LEN_LONG = 0xFFFF0012
SDO_LEN_SHORT = 0xFFFF0013
SDO_TOO_HIGH = 0xFFFF0016
SDO_TOO_LOW = 0xFFFF0017


class ModbusExc(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


class SdoError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# ---------------------------------------------------------------- drive --

class Drive:
    def __init__(self, address=1):
        self.address = address
        self.baud = 19200
        self.parity = "none"
        # RxPDO register image (raw, as written by the master)
        self.control_word = 0
        self.target_speed_raw = 0
        self.torque_limit_raw = 0
        self.watchdog_ms = 0
        # drive state
        self.state = SOD
        self.error_code = 0
        self.speed = 0.0          # actual speed, 0.1 Hz
        self.current = 0
        self.power = 0
        self.out_voltage = 0
        self.accelerating = False
        self.wd_armed = False
        self.wd_deadline = 0.0
        self.last_t = time.monotonic()
        self.counters = dict(bus_message=0, bus_comm_error=0, bus_exception_error=0,
                             slave_message=0, slave_no_response=0)
        self.objects = self._object_table()

    # ---- effective (tied) values ------------------------------------
    def eff_torque_limit(self):
        """Object 209 / TxPDO 2002: limited by the drive peak current."""
        return max(0, min(s16(self.torque_limit_raw), MAX_IQ))

    def eff_target(self):
        """Object 210: target velocity limited to +-Max Speed (object 120)."""
        return max(-MAX_SPEED, min(s16(self.target_speed_raw), MAX_SPEED))

    def energized(self):
        return self.state in (OE, QSA)

    def status_word(self):
        sw = STATE_BITS[self.state] | SW_VOLTAGE_ENABLED | SW_REMOTE
        if self.state == OE:
            goal = 0 if self.control_word & 0x0100 else self.eff_target()
            if int(round(self.speed)) == goal:
                sw |= SW_TARGET_REACHED
            if (s16(self.target_speed_raw) != self.eff_target()
                    or s16(self.torque_limit_raw) > MAX_IQ):
                sw |= SW_INTERNAL_LIMIT
        return sw

    # ---- time evolution ----------------------------------------------
    def update(self, now=None):
        if now is None:
            now = time.monotonic()
        dt = now - self.last_t
        if dt < 0:
            dt = 0
        self.last_t = now
        if self.wd_armed and now >= self.wd_deadline:
            self.wd_armed = False
            self.trip(ERR_WATCHDOG)
        dt = min(dt, 1.0)
        v = self.speed
        self.accelerating = False
        if self.state == OE:
            if self.eff_torque_limit() == 0:
                goal, rate = 0.0, COAST_DECEL     # no torque available: runs down
            else:
                goal = 0.0 if self.control_word & 0x0100 else float(self.eff_target())
                rate = ACCEL
                self.accelerating = abs(goal) > abs(v) and v != goal
        elif self.state == QSA:
            goal, rate = 0.0, QS_DECEL
        else:
            goal, rate = 0.0, COAST_DECEL
        step = rate * dt
        if abs(goal - v) <= step:
            v = goal
        else:
            v += step if goal > v else -step
        self.speed = v
        if self.state == QSA and v == 0.0:
            self.state = SOD                  # quick stop option code 2
        spd = abs(int(round(v)))
        if self.energized():
            cur = 20 + spd // 50 + (30 if self.accelerating else 0)
            cur = min(cur, self.eff_torque_limit())
            self.current = cur
            self.out_voltage = (spd * 2) // 5
            self.power = (spd * cur) // 20000
        else:
            self.current = self.power = self.out_voltage = 0

    def trip(self, code):
        self.error_code = code
        self.state = FAULT

    # ---- DS402 control word -----------------------------------------
    def next_state(self, state, old_cw, cw):
        if cw & 0x80:
            if state == FAULT and not old_cw & 0x80:
                return SOD
            return state                       # fault reset has priority
        if state == FAULT:
            return state
        if not cw & 0x02:                      # disable voltage
            return SOD
        if not cw & 0x04:                      # quick stop
            if state == OE:
                return QSA
            if state in (RTSO, SO):
                return SOD
            return state
        low = cw & 0x0F
        if low in (0x06, 0x0E):                # shutdown xxxx x110
            if state in (SOD, SO, OE):
                return RTSO
            return state
        if low == 0x07:                        # switch on / disable operation
            if state == RTSO:
                return SO
            if state == OE:
                return SO
            return state
        if low == 0x0F:                        # switch on + enable operation
            if state in (RTSO, SO, QSA):
                return OE
            return state
        return state

    def write_control_word(self, cw):
        self.update()
        old = self.control_word
        self.control_word = cw & 0xFFFF
        new_state = self.next_state(self.state, old, self.control_word)
        if self.state == FAULT and new_state == SOD:
            self.error_code = 0
        self.state = new_state
        self.update()

    def write_watchdog(self, val):
        self.update()
        self.watchdog_ms = val & 0xFFFF
        if self.watchdog_ms:
            self.wd_armed = True
            self.wd_deadline = time.monotonic() + self.watchdog_ms / 1000.0
        else:
            self.wd_armed = False

    # ---- register map -----------------------------------------------
    def read_reg(self, addr):
        if RX_BASE <= addr < RX_BASE + RX_LEN:
            return (self.control_word, self.target_speed_raw & 0xFFFF,
                    self.torque_limit_raw & 0xFFFF, self.watchdog_ms)[addr - RX_BASE]
        o = addr - TX_BASE
        spd = int(round(self.speed))
        u32 = {10: HW_ID, 12: HW_VERSION, 14: SW_ID, 16: SW_VERSION,
               20: SPEED_SCALING, 22: CURRENT_SCALING}
        if o in u32:
            return (u32[o] >> 16) & 0xFFFF
        if o - 1 in u32:
            return u32[o - 1] & 0xFFFF
        vals = {0: self.status_word(), 1: spd, 2: self.eff_torque_limit(), 3: self.current,
                4: self.power, 5: self.error_code, 6: TEMP_POWER_STAGE, 7: TEMP_MOTOR,
                8: self.out_voltage, 9: DC_VOLTAGE, 18: MAX_IQ, 19: MAX_SPEED}
        return vals[o] & 0xFFFF

    @staticmethod
    def readable(addr, qty):
        end = addr + qty
        return ((TX_BASE <= addr and end <= TX_BASE + TX_LEN)
                or (RX_BASE <= addr and end <= RX_BASE + RX_LEN))

    @staticmethod
    def writable(addr, qty):
        return RX_BASE <= addr and addr + qty <= RX_BASE + RX_LEN

    def check_write(self, addr, values):
        """Validate a PDO write against the state ties before anything is applied."""
        state = self.state
        for i, v in enumerate(values):
            a = addr + i
            if a == RX_BASE:
                state = self.next_state(state, self.control_word, v)
            elif a == RX_BASE + 3 and v == 0 and state in (OE, QSA):
                # not in the manual: watchdog cannot be switched off while energized
                raise ModbusExc(3)

    def write_regs(self, addr, values):
        self.update()
        self.check_write(addr, values)
        for i, v in enumerate(values):
            a = addr + i
            if a == RX_BASE:
                self.write_control_word(v)
            elif a == RX_BASE + 1:
                self.target_speed_raw = s16(v)
            elif a == RX_BASE + 2:
                self.torque_limit_raw = s16(v)
            elif a == RX_BASE + 3:
                self.write_watchdog(v)
        self.update()

    # ---- object dictionary (FC 43 / MEI 0x0D) -----------------------
    def _object_table(self):
        # index: (name, size, signed, access, getter, setter)
        ro = "RO"
        return {
            2: ("Hardware ID", 4, False, ro, lambda: HW_ID, None),
            5: ("Hardware Version", 4, False, ro, lambda: HW_VERSION, None),
            16: ("Software ID", 4, False, ro, lambda: SW_ID, None),
            17: ("Software Version", 4, False, ro, lambda: SW_VERSION, None),
            33: ("DC Voltage", 2, True, ro, lambda: DC_VOLTAGE, None),
            41: ("Temperature Power Stage", 2, True, ro, lambda: TEMP_POWER_STAGE, None),
            63: ("Temperature Motor", 2, True, ro, lambda: TEMP_MOTOR, None),
            67: ("Status Word", 2, False, ro, self.status_word, None),
            68: ("Control Word", 2, False, "RW", lambda: self.control_word, self._set_cw),
            70: ("Error Code", 2, False, ro, lambda: self.error_code, None),
            120: ("Max Speed", 2, True, ro, lambda: MAX_SPEED, None),
            168: ("Actual Speed", 2, True, ro, lambda: int(round(self.speed)), None),
            171: ("Max Iq Current", 2, True, ro, lambda: MAX_IQ, None),
            177: ("Speed Scaling", 4, True, ro, lambda: SPEED_SCALING, None),
            182: ("Current Scaling", 4, True, ro, lambda: CURRENT_SCALING, None),
            209: ("Target Torque Limit", 2, True, "RW", self.eff_torque_limit, self._set_tl),
            210: ("Target Velocity", 2, True, "RW", self.eff_target, self._set_tv),
            390: ("Actual Output Power", 2, True, ro, lambda: self.power, None),
            431: ("Actual Apparent Current", 2, True, ro, lambda: self.current, None),
            434: ("Output Voltage", 2, True, ro, lambda: self.out_voltage, None),
        }

    def _set_cw(self, v):
        self.write_control_word(v & 0xFFFF)

    def _set_tl(self, v):
        if v > MAX_IQ:
            raise SdoError(SDO_TOO_HIGH)
        if v < 0:
            raise SdoError(SDO_TOO_LOW)
        self.torque_limit_raw = v

    def _set_tv(self, v):
        if v > MAX_SPEED:
            raise SdoError(SDO_TOO_HIGH)
        if v < -MAX_SPEED:
            raise SdoError(SDO_TOO_LOW)
        self.target_speed_raw = v

    def obj_read(self, index, sub, count):
        ent = self.objects.get(index)
        if ent is None:
            raise SdoError(SDO_NO_OBJECT)
        if sub != 0:
            raise SdoError(SDO_SUBINDEX)
        name, size, signed, acc, get, _ = ent
        if count == 0:
            count = size
        if count > size:
            raise SdoError(SDO_LEN_LONG)
        if count < size:
            raise SdoError(SDO_LEN_SHORT)
        self.update()
        v = get() & ((1 << (8 * size)) - 1)
        return v.to_bytes(size, "little")

    def obj_write(self, index, sub, data):
        ent = self.objects.get(index)
        if ent is None:
            raise SdoError(SDO_NO_OBJECT)
        if sub != 0:
            raise SdoError(SDO_SUBINDEX)
        name, size, signed, acc, get, setter = ent
        if acc == "RO":
            raise SdoError(SDO_READ_ONLY)
        if len(data) > size:
            raise SdoError(SDO_LEN_LONG)
        if len(data) < size:
            raise SdoError(SDO_LEN_SHORT)
        v = int.from_bytes(data, "little", signed=signed)
        self.update()
        setter(v)
        self.update()

    # ---- state dump -----------------------------------------------------
    def snapshot(self):
        self.update()
        objs = {}
        for idx, ent in sorted(self.objects.items()):
            v = ent[4]() & ((1 << (8 * ent[1])) - 1)
            if ent[2] and v >> (8 * ent[1] - 1):
                v -= 1 << (8 * ent[1])
            objs["%d/0" % idx] = v
        return {
            "device": "SIEB & MEYER SD2x (simulated), single axis",
            "settings": {"slave_address": self.address, "baud": self.baud,
                         "parity": self.parity, "node_id": self.address},
            "holding_registers": {str(a): self.read_reg(a) for a in range(RX_BASE, RX_BASE + RX_LEN)},
            "input_registers": {str(a): self.read_reg(a) for a in range(TX_BASE, TX_BASE + TX_LEN)},
            "objects": objs,
            "drive": {"ds402_state": self.state, "error_code": self.error_code,
                      "watchdog_armed": self.wd_armed},
            "diagnostic_counters": dict(self.counters),
        }


# ------------------------------------------------------ Modbus protocol --

FIXED_LEN = {0x01: 8, 0x02: 8, 0x03: 8, 0x04: 8, 0x05: 8, 0x06: 8, 0x08: 8,
             0x07: 4, 0x0B: 4, 0x0C: 4, 0x11: 4, 0x16: 10, 0x18: 6}


class Server:
    def __init__(self, drive):
        self.d = drive

    def count_comm_error(self):
        c = self.d.counters
        c["bus_comm_error"] = (c["bus_comm_error"] + 1) & 0xFFFF

    # ---- ADU level ---------------------------------------------------
    def handle_adu(self, adu):
        """adu: full frame incl. CRC. Returns response bytes or None."""
        d = self.d
        c = d.counters
        if not crc_ok(adu):
            c["bus_comm_error"] = (c["bus_comm_error"] + 1) & 0xFFFF
            return None
        c["bus_message"] = (c["bus_message"] + 1) & 0xFFFF
        addr = adu[0]
        if addr != 0 and addr != d.address:
            return None
        c["slave_message"] = (c["slave_message"] + 1) & 0xFFFF
        pdu = bytes(adu[1:-2])
        d.update()
        try:
            resp = self.handle_pdu(pdu, broadcast=(addr == 0))
        except ModbusExc as e:
            resp = bytes((pdu[0] | 0x80, e.code))
        except Exception:                       # never die on one frame
            resp = bytes(((pdu[0] if pdu else 0) | 0x80, 4))
        if addr == 0:
            c["slave_no_response"] = (c["slave_no_response"] + 1) & 0xFFFF
            return None
        if resp is None:
            return None
        if resp[0] & 0x80:
            c["bus_exception_error"] = (c["bus_exception_error"] + 1) & 0xFFFF
        return with_crc(bytes((addr,)) + resp)

    # ---- PDU level ---------------------------------------------------
    def handle_pdu(self, pdu, broadcast=False):
        fc = pdu[0]
        if fc in (0x03, 0x04):
            if broadcast:
                return None
            return self.fc_read(pdu)
        if fc == 0x06:
            return self.fc06(pdu)
        if fc == 0x08:
            if broadcast:
                return None
            return self.fc08(pdu)
        if fc == 0x10:
            return self.fc16(pdu)
        if fc == 0x17:
            if broadcast:
                return None
            return self.fc23(pdu)
        if fc == 0x2B:
            if broadcast:
                return None
            return self.fc43(pdu)
        raise ModbusExc(1)

    def fc_read(self, pdu):
        if len(pdu) != 5:
            raise ModbusExc(3)
        addr, qty = struct.unpack(">HH", pdu[1:5])
        if not 1 <= qty <= MAX_REGS:
            raise ModbusExc(3)
        if not self.d.readable(addr, qty):
            raise ModbusExc(2)
        vals = [self.d.read_reg(addr + i) for i in range(qty)]
        return bytes((pdu[0], 2 * qty)) + struct.pack(">%dH" % qty, *vals)

    def fc06(self, pdu):
        if len(pdu) != 5:
            raise ModbusExc(3)
        addr, val = struct.unpack(">HH", pdu[1:5])
        if not self.d.writable(addr, 1):
            raise ModbusExc(2)
        self.d.write_regs(addr, [val])
        return pdu

    def fc08(self, pdu):
        if len(pdu) != 5:
            raise ModbusExc(3)
        sub, data = struct.unpack(">HH", pdu[1:5])
        c = self.d.counters
        if sub == 0x00:
            return pdu
        keys = {0x0B: "bus_message", 0x0C: "bus_comm_error", 0x0D: "bus_exception_error",
                0x0E: "slave_message", 0x0F: "slave_no_response"}
        if sub == 0x0A:
            if data != 0:
                raise ModbusExc(3)
            for k in c:
                c[k] = 0
            return pdu
        if sub in keys:
            if data != 0:
                raise ModbusExc(3)
            return pdu[:3] + struct.pack(">H", c[keys[sub]] & 0xFFFF)
        raise ModbusExc(1)

    def fc16(self, pdu):
        if len(pdu) < 6:
            raise ModbusExc(3)
        addr, qty, bc = struct.unpack(">HHB", pdu[1:6])
        if not 1 <= qty <= MAX_REGS or bc != 2 * qty or len(pdu) != 6 + bc:
            raise ModbusExc(3)
        if not self.d.writable(addr, qty):
            raise ModbusExc(2)
        vals = list(struct.unpack(">%dH" % qty, pdu[6:6 + bc]))
        self.d.write_regs(addr, vals)
        return pdu[:5]

    def fc23(self, pdu):
        if len(pdu) < 10:
            raise ModbusExc(3)
        ra, rq, wa, wq, bc = struct.unpack(">HHHHB", pdu[1:10])
        if (not 1 <= rq <= MAX_REGS or not 1 <= wq <= MAX_REGS or bc != 2 * wq
                or len(pdu) != 10 + bc):
            raise ModbusExc(3)
        if not self.d.writable(wa, wq) or not self.d.readable(ra, rq):
            raise ModbusExc(2)
        vals = list(struct.unpack(">%dH" % wq, pdu[10:10 + bc]))
        self.d.write_regs(wa, vals)            # write first, then read (spec)
        out = [self.d.read_reg(ra + i) for i in range(rq)]
        return bytes((0x17, 2 * rq)) + struct.pack(">%dH" % rq, *out)

    @staticmethod
    def fc43_layout(pdu):
        """Return (has_reserved, header_len) or None. header_len counts from FC."""
        # layout R (table, manual l.542-552): FC MEI CTRL RES NODE IDX(2) SUB OFF(2) CNT(2)
        # layout N (example 6.2, l.1299-1317): FC MEI CTRL NODE IDX(2) SUB OFF(2) CNT(2)
        cands = []
        for res, hl in ((True, 12), (False, 11)):
            if len(pdu) < hl:
                continue
            ctrl = pdu[2]
            cnt = (pdu[hl - 2] << 8) | pdu[hl - 1]
            n = cnt if ctrl & 0x80 else 0
            if len(pdu) == hl + n:
                cands.append((res, hl))
        return cands[0] if cands else None

    def fc43(self, pdu):
        if len(pdu) < 2:
            raise ModbusExc(3)
        if pdu[1] != 0x0D:
            raise ModbusExc(1)
        lay = self.fc43_layout(pdu)
        if lay is None:
            raise ModbusExc(3)
        res, hl = lay
        ctrl = pdu[2]
        p = 3
        if res:
            if pdu[3] != 0:
                raise ModbusExc(3)
            p = 4
        node = pdu[p]
        index = (pdu[p + 1] << 8) | pdu[p + 2]
        sub = pdu[p + 3]
        off = (pdu[p + 4] << 8) | pdu[p + 5]
        cnt = (pdu[p + 6] << 8) | pdu[p + 7]
        data = pdu[hl:]
        if ctrl & 0x7F or off != 0 or cnt > 4 or not 1 <= node <= 0x7F:
            raise ModbusExc(3)
        if node != self.d.address:
            raise ModbusExc(2)
        head = bytes(pdu[:hl - 2])
        try:
            if ctrl & 0x80:
                self.d.obj_write(index, sub, bytes(data))
                return bytes(pdu)
            val = self.d.obj_read(index, sub, cnt)
            return head + struct.pack(">H", len(val)) + val
        except SdoError as e:
            return bytes((0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + struct.pack("<I", e.code)


# ----------------------------------------------------------- framing ---

GAP = 0.05      # seconds of silence that ends a frame on the TCP stream


class StreamFramer:
    """Cuts RTU frames out of a TCP byte stream.

    - FCs with a length fixed by the function code (or by a byte count field)
      are cut by that length;
    - FC 43/MEI 0x0D: both documented layouts are tried, the CRC decides;
    - anything else: the shortest prefix (>= 4 bytes) whose CRC matches, else
      everything up to a gap of GAP seconds is one (bad) frame.
    - after a CRC error everything up to the next gap is discarded.
    """

    def __init__(self, server):
        self.srv = server
        self.buf = bytearray()
        self.discarding = False

    def feed(self, data):
        """Returns a list of responses."""
        out = []
        if self.discarding:
            return out                          # still inside a corrupted burst
        self.buf += data
        while self.buf:
            res = self._cut()
            if res is None:
                break                           # need more bytes
            n = res
            if n < 0:                           # unrecoverable: drop until gap
                self.srv.count_comm_error()
                self.buf.clear()
                self.discarding = True
                break
            frame = bytes(self.buf[:n])
            del self.buf[:n]
            r = self.srv.handle_adu(frame)
            if r:
                out.append(r)
        return out

    def gap(self):
        """Called after GAP seconds of silence."""
        if self.buf:
            # an incomplete frame: counts as a communication error
            self.srv.count_comm_error()
            self.buf.clear()
        self.discarding = False

    def _known_len(self, b):
        fc = b[1]
        if fc in FIXED_LEN:
            return FIXED_LEN[fc]
        if fc in (0x0F, 0x10):
            return None if len(b) < 7 else 9 + b[6]
        if fc == 0x17:
            return None if len(b) < 11 else 13 + b[10]
        if fc in (0x14, 0x15):
            return None if len(b) < 3 else 5 + b[2]
        return "unknown"

    def _cut(self):
        b = self.buf
        if len(b) < 2:
            return None
        fc = b[1]
        if fc == 0x2B:
            return self._cut43()
        n = self._known_len(b)
        if n is None:
            return None
        if n == "unknown":
            return self._crc_scan()
        if len(b) < n:
            return None
        if crc_ok(b[:n]):
            return n
        return -1

    def _cut43(self):
        b = self.buf
        if len(b) < 3:
            return None
        if b[2] != 0x0D:
            if b[2] == 0x0E:
                n = 7
                if len(b) < n:
                    return None
                return n if crc_ok(b[:n]) else -1
            return self._crc_scan()
        if len(b) < 4:
            return None
        write = b[3] & 0x80
        waiting = False
        for hl in (12, 13):                     # N layout first, then R (incl. address)
            if len(b) < hl:
                waiting = True
                continue
            cnt = (b[hl - 2] << 8) | b[hl - 1]
            n = hl + (cnt if write else 0) + 2
            if cnt > 250:
                continue
            if len(b) < n:
                waiting = True
                continue
            if crc_ok(b[:n]):
                return n
        return None if waiting else -1

    def _crc_scan(self):
        b = self.buf
        for n in range(4, min(len(b), 256) + 1):
            if crc_ok(b[:n]):
                return n
        if len(b) >= 256:
            return -1
        return None


class TcpConn(asyncio.Protocol):
    def __init__(self, server):
        self.framer = StreamFramer(server)
        self.timer = None
        self.transport = None

    def connection_made(self, transport):
        self.transport = transport

    def data_received(self, data):
        loop = asyncio.get_running_loop()
        if self.timer:
            self.timer.cancel()
        try:
            for r in self.framer.feed(data):
                self.transport.write(r)
        except Exception:
            self.framer.buf.clear()
        self.timer = loop.call_later(GAP, self.framer.gap)

    def connection_lost(self, exc):
        if self.timer:
            self.timer.cancel()


class SerialPort:
    """RTU over a real serial line / pty with t3.5 frame delimiting."""

    def __init__(self, server, dev, baud, parity):
        import termios
        import tty
        self.srv = server
        self.fd = os.open(dev, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            tty.setraw(self.fd)
            attrs = termios.tcgetattr(self.fd)
            speed = getattr(termios, "B%d" % baud, termios.B19200)
            attrs[4] = attrs[5] = speed
            cflag = attrs[2] & ~(termios.PARENB | termios.PARODD | termios.CSTOPB | termios.CSIZE)
            cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
            if parity == "even":
                cflag |= termios.PARENB
            elif parity == "odd":
                cflag |= termios.PARENB | termios.PARODD
            attrs[2] = cflag
            termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
        except Exception:
            pass
        bits = 11
        self.t35 = 0.00175 if baud > 19200 else 3.5 * bits / baud
        self.buf = bytearray()
        self.timer = None
        loop = asyncio.get_running_loop()
        loop.add_reader(self.fd, self._readable)

    def _readable(self):
        try:
            data = os.read(self.fd, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            return
        self.buf += data
        if self.timer:
            self.timer.cancel()
        self.timer = asyncio.get_running_loop().call_later(max(self.t35, 0.002), self._frame_end)

    def _frame_end(self):
        frame = bytes(self.buf)
        self.buf.clear()
        if len(frame) > 256 or len(frame) < 4:
            self.srv.count_comm_error()
            return
        try:
            r = self.srv.handle_adu(frame)
        except Exception:
            r = None
        if r:
            try:
                os.write(self.fd, r)
            except OSError:
                pass


# --------------------------------------------------------------- main ---

def dump_state(drive, path):
    if not path:
        return
    tmp = path + ".tmp"
    try:
        with open(tmp, "w") as f:
            json.dump(drive.snapshot(), f, indent=1, sort_keys=True)
        os.replace(tmp, path)
    except OSError as e:
        print("state dump failed: %s" % e, file=sys.stderr)


async def ticker(drive):
    while True:
        await asyncio.sleep(0.01)
        try:
            drive.update()
        except Exception:
            pass


async def amain(args):
    drive = Drive(address=args.address)
    drive.baud = args.baud
    drive.parity = args.parity
    srv = Server(drive)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()

    def on_term():
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, on_term)
    loop.add_signal_handler(signal.SIGUSR1, lambda: dump_state(drive, args.state))
    tick = asyncio.ensure_future(ticker(drive))
    servers = []
    if args.listen:
        host, _, port = args.listen.rpartition(":")
        s = await loop.create_server(lambda: TcpConn(srv), host or "127.0.0.1", int(port))
        servers.append(s)
        p = s.sockets[0].getsockname()[1]
        print("listening tcp %s:%d" % (host, p), flush=True)
    if args.serial:
        SerialPort(srv, args.serial, args.baud, args.parity)
        print("listening serial %s" % args.serial, flush=True)
    await stop.wait()
    tick.cancel()
    for s in servers:
        s.close()
    dump_state(drive, args.state)


def main():
    ap = argparse.ArgumentParser(description="SIEB & MEYER SD2x Modbus RTU simulator")
    ap.add_argument("--listen", help="HOST:PORT for RTU over TCP (e.g. 127.0.0.1:0)")
    ap.add_argument("--state", help="JSON state dump file (SIGUSR1 and exit)")
    ap.add_argument("--serial", help="serial device / pty for RTU with t3.5 framing")
    ap.add_argument("--baud", type=int, default=19200,
                    choices=[9600, 14400, 19200, 28800, 38400, 57600, 115200])
    ap.add_argument("--parity", default="none", choices=["none", "even", "odd"])
    ap.add_argument("--address", type=int, default=1,
                    help="slave address (1..254; default 1 = ID switch 0, single axis)")
    args = ap.parse_args()
    if not args.listen and not args.serial:
        ap.error("need --listen and/or --serial")
    if not 1 <= args.address <= 254:
        ap.error("address must be 1..254")
    try:
        asyncio.run(amain(args))
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
