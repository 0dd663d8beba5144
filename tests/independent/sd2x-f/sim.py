#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier - Modbus RTU slave simulator.

Bench unit taken from a customer's machine, spindle motor attached.
Transport: RTU frames over a TCP stream (--listen) or over a serial line (--serial).
Python 3.11 standard library only.  See DECISIONS.md / README.md.
"""
import argparse
import json
import math
import os
import random
import select
import signal
import socket
import struct
import sys
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
    c = 0xFFFF
    for b in data:
        c = (c >> 8) ^ _CRC_TABLE[(c ^ b) & 0xFF]
    return c


def crc_ok(frame):
    if len(frame) < 4:
        return False
    c = crc16(frame[:-2])
    return frame[-2] == (c & 0xFF) and frame[-1] == (c >> 8)


def add_crc(frame):
    c = crc16(frame)
    return bytes(frame) + bytes((c & 0xFF, c >> 8))


# ---------------------------------------------------------------------------
# Constants
# ---------------------------------------------------------------------------
TX_BASE = 2000          # TxPDO (actual values), 24 registers 2000..2023
TX_END = 2023
RX_BASE = 3000          # RxPDO (set points), 4 registers 3000..3003
RX_END = 3003
MAX_QTY = 48            # manual: n = 1 to 48 (30h)

SDO_NOT_EXIST = 0xFFFF000B
SDO_WRITE_RO = 0xFFFF000A
SDO_SUBINDEX = 0xFFFF0014
SDO_TOO_LONG = 0xFFFF0012
SDO_TOO_SHORT = 0xFFFF0013

ERR_WATCHDOG = 0x8130   # CiA 301 "life guard / heartbeat error" (object 70 = 0x603F)

# DS402 states
NRTSO, SOD, RTSO, SO, OE, QSA, FRA, FAULT = (
    "not_ready_to_switch_on", "switch_on_disabled", "ready_to_switch_on",
    "switched_on", "operation_enabled", "quick_stop_active",
    "fault_reaction_active", "fault")

# --- commissioned customer configuration (see DECISIONS.md) ---------------
HW_ID = 0x00000253          # object 2   (SD2S single-axis power unit code)
HW_VERSION = 0x00020010     # object 5   (2.16)
SW_ID = 0x00003A02          # object 16  (spindle firmware "0x3A02")
SW_VERSION = 0x00040021     # object 17  (4.33)
SPEED_SCALING = 42000000    # object 177, 0.001 rpm  -> 42000 rpm (= 700 Hz, 1 pole pair)
MAX_SPEED_RPM = 36000       # motor nameplate max speed (customer parameter)
MAX_SPEED_OBJ = round(0x3FFF * MAX_SPEED_RPM * 1000 / SPEED_SCALING)  # object 120 (14043)
MAX_SPEED_01HZ = MAX_SPEED_RPM // 6   # 600.0 Hz in 0.1 Hz = 6000 (used for clamping)
CURRENT_SCALING = 32000     # object 182, 0.001 A -> 32.000 A drive peak current
MAX_IQ = 180                # object 171, 0.1 A -> 18.0 A (customer current limitation)
ACCEL_01HZ_S = 1500.0       # customer acceleration ramp 150 Hz/s
DECEL_01HZ_S = 1000.0       # customer deceleration ramp 100 Hz/s
QSTOP_01HZ_S = 3000.0       # customer quick stop ramp 300 Hz/s
COAST_01HZ_S = 60.0         # free run-down of the spindle with power stage off (6 Hz/s)

INIT_CONTROL_WORD = 0
INIT_TARGET_VELOCITY = 4000     # 400.0 Hz, stored set point of the customer parameter set
INIT_TORQUE_LIMIT = 150         # 15.0 A
INIT_WATCHDOG = 0               # watchdog off at power-up


def s16(v):
    v &= 0xFFFF
    return v - 0x10000 if v & 0x8000 else v


def u16(v):
    return v & 0xFFFF


def s32(v):
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


class SdoError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# ---------------------------------------------------------------------------
# Device
# ---------------------------------------------------------------------------
class Drive:
    def __init__(self, address):
        self.address = address
        self.lock = threading.RLock()
        # RxPDO / RW objects
        self.control_word = INIT_CONTROL_WORD
        self.target_velocity = INIT_TARGET_VELOCITY   # signed, 0.1 Hz (object 210)
        self.torque_limit = INIT_TORQUE_LIMIT         # signed, 0.1 A (object 209)
        self.watchdog = INIT_WATCHDOG                 # ms
        self.wd_deadline = None
        # drive state
        self.state = SOD
        self.error_code = 0
        self.prev_cw_bit7 = 0
        # physics
        self.speed = 0.0            # actual speed, 0.1 Hz (float)
        self.speed_reported = 0
        self.t0 = time.monotonic()
        self.t_last = self.t0
        self.rng = random.Random()
        self.temp_ps = 293.0        # 0.1 degC (29.3 degC) - float model
        self.temp_motor = 262.0     # 26.2 degC
        self.dc_base = 5652.0       # 565.2 V
        self.i_filtered = 0.0
        self.accel_now = 0.0
        self.live = {}
        self.limit_active = False
        self.counters = dict(bus_message=0, bus_comm_error=0, bus_exception_error=0,
                             slave_message=0, slave_no_response=0)
        self._update_live(0.0)

    # ---------------- diagnostics counters ----------------
    def _inc(self, name):
        self.counters[name] = (self.counters[name] + 1) & 0xFFFF

    # ---------------- DS402 ----------------
    def status_word(self):
        st = self.state
        if st == NRTSO:
            sw = 0x0000
        elif st == SOD:
            sw = 0x0040
        elif st == RTSO:
            sw = 0x0021
        elif st == SO:
            sw = 0x0023
        elif st == OE:
            sw = 0x0027
        elif st == QSA:
            sw = 0x0007
        elif st == FRA:
            sw = 0x000F
        else:
            sw = 0x0008
        if st in (SOD,):
            sw |= 0x0020        # quick stop not active
        # bit 4 voltage enabled: DC link is charged (hardware)
        if self.live.get("dc", 0) > 3000:
            sw |= 0x0010
        sw |= 0x0200            # bit 9 remote: control channel = Modbus
        if st == OE:
            tgt = self._effective_target()
            if abs(self.speed - tgt) <= 10.0:
                sw |= 0x0400    # bit 10 target reached (1 Hz window)
            if self.limit_active:
                sw |= 0x0800    # bit 11 internal limit active
        return sw

    def _effective_target(self):
        t = self.target_velocity
        return float(max(-MAX_SPEED_01HZ, min(MAX_SPEED_01HZ, t)))

    def apply_control_word(self):
        cw = self.control_word
        bit7 = (cw >> 7) & 1
        rising = bit7 and not self.prev_cw_bit7
        self.prev_cw_bit7 = bit7
        st = self.state
        if st == FAULT:
            if rising:
                self.state = SOD
                self.error_code = 0
            return
        if st in (FRA, NRTSO):
            return
        if bit7:
            return  # fault reset bit has priority over other commands (no fault present)
        low = cw & 0x0F
        if not (cw & 0x02):                       # disable voltage
            self.state = SOD
        elif not (cw & 0x04):                     # quick stop
            if st == OE:
                self.state = QSA
            elif st in (RTSO, SO):
                self.state = SOD
        elif (cw & 0x07) == 0x06:                 # shutdown
            if st in (SOD, SO, OE):
                self.state = RTSO
        elif low == 0x07:                         # switch on / disable operation
            if st in (RTSO, OE):
                self.state = SO
        elif low == 0x0F:                         # enable operation
            if st in (RTSO, SO):
                self.state = OE
            elif st == QSA:
                self.state = OE

    def raise_fault(self, code):
        if self.state != FAULT:
            self.state = FAULT
            self.error_code = code

    # ---------------- physics ----------------
    def tick(self):
        with self.lock:
            now = time.monotonic()
            dt = max(0.0, min(0.5, now - self.t_last))
            self.t_last = now
            # watchdog
            if self.wd_deadline is not None and now >= self.wd_deadline:
                self.wd_deadline = None
                self.raise_fault(ERR_WATCHDOG)
            # motion
            st = self.state
            v = self.speed
            self.limit_active = False
            if st == OE:
                tgt = self.target_velocity
                if abs(tgt) > MAX_SPEED_01HZ:
                    self.limit_active = True
                tgt = self._effective_target()
                rate = ACCEL_01HZ_S if abs(tgt) > abs(v) and (tgt * v >= 0) else DECEL_01HZ_S
            elif st == SO:
                tgt, rate = 0.0, DECEL_01HZ_S
            elif st == QSA:
                tgt, rate = 0.0, QSTOP_01HZ_S
            else:
                tgt, rate = 0.0, COAST_01HZ_S
            step = rate * dt
            old = v
            if v < tgt:
                v = min(tgt, v + step)
            elif v > tgt:
                v = max(tgt, v - step)
            self.speed = v
            self.accel_now = (v - old) / dt if dt > 0 else 0.0
            if st == QSA and abs(v) < 0.5:
                self.speed = 0.0
                self.state = SOD
            self._update_live(dt)

    def _update_live(self, dt):
        r = self.rng
        now = time.monotonic() - self.t0
        st = self.state
        powered = st in (OE, SO, QSA)
        f_hz = abs(self.speed) / 10.0
        # apparent current (0.1 A)
        if powered:
            i_target = 21.0 + f_hz * 0.018 + abs(self.accel_now) * 0.05
            i_target = min(i_target, float(MAX_IQ))
        else:
            i_target = 0.0
        self.i_filtered += (i_target - self.i_filtered) * min(1.0, dt * 8.0 if dt else 1.0)
        cur = self.i_filtered + (r.uniform(-1.5, 1.5) if powered else 0.0)
        cur = int(round(max(0.0, cur)))
        if not powered:
            cur = r.choice((0, 0, 0, 1))          # offset noise of the current measurement
        # output voltage (0.1 V), V/f characteristic 380 V @ 600 Hz with boost
        if powered:
            uo = 80.0 + f_hz * 6.2 + r.uniform(-4, 4)
            uo = min(uo, 3900.0)
        else:
            uo = 0.0
        # output power (0.1 kW)
        if powered:
            p_kw = (0.05 + f_hz * 0.0009 + abs(self.accel_now) * f_hz * 0.000004)
            pw = int(round(p_kw * 10 + r.choice((-1, 0, 0, 0, 1)) * (1 if f_hz > 50 else 0)))
            pw = max(0, pw)
        else:
            pw = 0
        # temperatures (0.1 degC) - slow first order toward a load dependent value
        amb = 240.0
        ps_target = 293.0 + 6.0 * math.sin(now / 900.0) + cur * 0.9
        mot_target = 262.0 + 3.0 * math.sin(now / 1300.0 + 1.0) + f_hz * 0.05 + cur * 0.4
        k = min(1.0, dt / 60.0) if dt else 0.0
        self.temp_ps += (ps_target - self.temp_ps) * k
        self.temp_motor += (mot_target - self.temp_motor) * k * 0.5
        self.temp_ps = max(amb, min(900.0, self.temp_ps))
        self.temp_motor = max(amb, min(1300.0, self.temp_motor))
        tps = int(round(self.temp_ps + r.choice((-1, 0, 0, 1))))
        tmo = int(round(self.temp_motor + r.choice((-1, 0, 0, 0, 1))))
        # DC link voltage (0.1 V): mains ripple/drift + load sag
        dc = self.dc_base + 18.0 * math.sin(now / 240.0) - cur * 0.4 + r.uniform(-4, 4)
        dc = int(round(max(5300.0, min(6100.0, dc))))
        # actual speed (0.1 Hz) with measurement jitter
        if abs(self.speed) < 0.5 and not powered:
            sp = r.choice((0, 0, 0, 1, -1))
        else:
            sp = int(round(self.speed + r.choice((-2, -1, 0, 0, 0, 1, 2))))
        sp = max(-32768, min(32767, sp))
        self.speed_reported = sp
        self.live = {"speed": sp, "current": cur, "power": pw, "tps": tps,
                     "tmotor": tmo, "uout": int(round(uo)), "dc": dc}

    # ---------------- register image ----------------
    def tx_register(self, addr):
        lv = self.live
        r = addr - TX_BASE
        def hi(v):
            return (v >> 16) & 0xFFFF
        def lo(v):
            return v & 0xFFFF
        table = {
            0: self.status_word(),
            1: u16(lv["speed"]),
            2: u16(self.torque_limit),
            3: u16(lv["current"]),
            4: u16(lv["power"]),
            5: u16(self.error_code),
            6: u16(lv["tps"]),
            7: u16(lv["tmotor"]),
            8: u16(lv["uout"]),
            9: u16(lv["dc"]),
            10: hi(HW_ID), 11: lo(HW_ID),
            12: hi(HW_VERSION), 13: lo(HW_VERSION),
            14: hi(SW_ID), 15: lo(SW_ID),
            16: hi(SW_VERSION), 17: lo(SW_VERSION),
            18: u16(MAX_IQ),
            19: u16(MAX_SPEED_OBJ),
            20: hi(SPEED_SCALING & 0xFFFFFFFF), 21: lo(SPEED_SCALING),
            22: hi(CURRENT_SCALING & 0xFFFFFFFF), 23: lo(CURRENT_SCALING),
        }
        return table[r]

    def rx_register(self, addr):
        r = addr - RX_BASE
        return (u16(self.control_word), u16(self.target_velocity),
                u16(self.torque_limit), u16(self.watchdog))[r]

    def read_register(self, addr):
        if TX_BASE <= addr <= TX_END:
            return self.tx_register(addr)
        return self.rx_register(addr)

    @staticmethod
    def readable(start, qty):
        end = start + qty - 1
        return (TX_BASE <= start and end <= TX_END) or (RX_BASE <= start and end <= RX_END)

    @staticmethod
    def writable(start, qty):
        end = start + qty - 1
        return RX_BASE <= start and end <= RX_END

    def write_registers(self, start, values):
        cw_written = False
        for i, v in enumerate(values):
            a = start + i
            if a == 3000:
                self.control_word = v
                cw_written = True
            elif a == 3001:
                self.target_velocity = s16(v)
            elif a == 3002:
                self.torque_limit = s16(v)
            elif a == 3003:
                self.watchdog = v
                self.wd_deadline = (time.monotonic() + v / 1000.0) if v else None
        if cw_written:
            self.apply_control_word()

    # ---------------- object dictionary ----------------
    # index -> (name, type, access, getter, setter)
    def _objects(self):
        lv = self.live
        return {
            2: ("Hardware ID", "U32", "RO", lambda: HW_ID, None),
            5: ("Hardware Version", "U32", "RO", lambda: HW_VERSION, None),
            16: ("Software ID", "U32", "RO", lambda: SW_ID, None),
            17: ("Software Version", "U32", "RO", lambda: SW_VERSION, None),
            33: ("DC Voltage", "I16", "RO", lambda: lv["dc"], None),
            41: ("Temperature Power Stage", "I16", "RO", lambda: lv["tps"], None),
            63: ("Temperature Motor", "I16", "RO", lambda: lv["tmotor"], None),
            67: ("Status Word", "U16", "RO", self.status_word, None),
            68: ("Control Word", "U16", "RW", lambda: self.control_word, self._set_cw),
            70: ("Error Code", "U16", "RO", lambda: self.error_code, None),
            120: ("Max Speed", "I16", "RO", lambda: MAX_SPEED_OBJ, None),
            168: ("Actual Speed", "I16", "RO", lambda: lv["speed"], None),
            171: ("Max Iq Current", "I16", "RO", lambda: MAX_IQ, None),
            177: ("Speed Scaling", "I32", "RO", lambda: SPEED_SCALING, None),
            182: ("Current Scaling", "I32", "RO", lambda: CURRENT_SCALING, None),
            209: ("Target Torque Limit", "I16", "RW", lambda: self.torque_limit, self._set_tl),
            210: ("Target Velocity", "I16", "RW", lambda: self.target_velocity, self._set_tv),
            390: ("Actual Output Power", "I16", "RO", lambda: lv["power"], None),
            431: ("Actual Apparent Current", "I16", "RO", lambda: lv["current"], None),
            434: ("Output Voltage", "I16", "RO", lambda: lv["uout"], None),
        }

    LIVE_OBJECTS = (33, 41, 63, 168, 390, 431, 434)

    def _set_cw(self, v):
        self.control_word = v & 0xFFFF
        self.apply_control_word()

    def _set_tl(self, v):
        self.torque_limit = s16(v)

    def _set_tv(self, v):
        self.target_velocity = s16(v)

    @staticmethod
    def _size(t):
        return 4 if t.endswith("32") else 2

    def sdo_read(self, index, sub, n):
        objs = self._objects()
        if index not in objs:
            raise SdoError(SDO_NOT_EXIST)
        name, t, acc, get, _ = objs[index]
        if sub != 0:
            raise SdoError(SDO_SUBINDEX)
        size = self._size(t)
        if n != 0 and n < size:
            raise SdoError(SDO_TOO_SHORT)
        if n > size:
            raise SdoError(SDO_TOO_LONG)
        v = get()
        if size == 2:
            return struct.pack("<H", v & 0xFFFF)
        return struct.pack("<I", v & 0xFFFFFFFF)

    def sdo_write(self, index, sub, data):
        objs = self._objects()
        if index not in objs:
            raise SdoError(SDO_NOT_EXIST)
        name, t, acc, get, setter = objs[index]
        if sub != 0:
            raise SdoError(SDO_SUBINDEX)
        if acc == "RO":
            raise SdoError(SDO_WRITE_RO)
        size = self._size(t)
        if len(data) < size:
            raise SdoError(SDO_TOO_SHORT)
        if len(data) > size:
            raise SdoError(SDO_TOO_LONG)
        setter(struct.unpack("<H", data)[0])

    # ---------------- state dump ----------------
    def snapshot(self):
        with self.lock:
            live_regs = {2001, 2003, 2004, 2006, 2007, 2008, 2009}
            hr = {str(a): self.rx_register(a) for a in range(RX_BASE, RX_END + 1)}
            ir = {str(a): self.tx_register(a) for a in range(TX_BASE, TX_END + 1)
                  if a not in live_regs}
            objs = {}
            live = {}
            for idx, (name, t, acc, get, _) in sorted(self._objects().items()):
                v = get()
                if t == "I16":
                    v = s16(v)
                elif t == "I32":
                    v = s32(v)
                key = "%d:0" % idx
                if idx in self.LIVE_OBJECTS:
                    live[key] = v
                else:
                    objs[key] = {"name": name, "type": t, "access": acc, "value": v}
            for a in sorted(live_regs):
                live[str(a)] = self.tx_register(a)
            return {
                "device": "SIEB & MEYER SD2x (bench unit, simulated)",
                "slave_address": self.address,
                "holding_registers": hr,
                "input_registers": ir,
                "objects": objs,
                "drive": {"ds402_state": self.state, "error_code": self.error_code,
                          "watchdog_ms": self.watchdog},
                "live": live,
                "diagnostic_counters": dict(self.counters),
            }

    # ---------------- Modbus PDU processing ----------------
    def handle_frame(self, frame):
        """frame: full RTU ADU with valid CRC. Returns response ADU or None."""
        with self.lock:
            self._inc("bus_message")
            addr = frame[0]
            if addr != self.address and addr != 0:
                return None
            self._inc("slave_message")
            pdu = bytes(frame[1:-2])
            broadcast = addr == 0
            try:
                resp = self.handle_pdu(pdu, broadcast)
            except ModbusError as e:
                resp = bytes((pdu[0] | 0x80, e.code))
            except Exception:                      # never die on one frame
                resp = bytes(((pdu[0] if pdu else 0) | 0x80, 0x04))
            if broadcast or resp is None:
                self._inc("slave_no_response")
                return None
            if resp[0] & 0x80:
                self._inc("bus_exception_error")
            return add_crc(bytes((self.address,)) + resp)

    def handle_pdu(self, pdu, broadcast):
        fc = pdu[0]
        if fc in (0x03, 0x04):
            if broadcast:
                return None
            if len(pdu) != 5:
                raise ModbusError(3)
            start, qty = struct.unpack(">HH", pdu[1:5])
            if not 1 <= qty <= MAX_QTY:
                raise ModbusError(3)
            if not self.readable(start, qty):
                raise ModbusError(2)
            vals = [self.read_register(a) for a in range(start, start + qty)]
            return bytes((fc, 2 * qty)) + struct.pack(">%dH" % qty, *vals)
        if fc == 0x06:
            if len(pdu) != 5:
                raise ModbusError(3)
            a, v = struct.unpack(">HH", pdu[1:5])
            if not self.writable(a, 1):
                raise ModbusError(2)
            self.write_registers(a, [v])
            return pdu
        if fc == 0x10:
            if len(pdu) < 6:
                raise ModbusError(3)
            start, qty = struct.unpack(">HH", pdu[1:5])
            bc = pdu[5]
            if not 1 <= qty <= MAX_QTY or bc != 2 * qty or len(pdu) != 6 + bc:
                raise ModbusError(3)
            if not self.writable(start, qty):
                raise ModbusError(2)
            vals = list(struct.unpack(">%dH" % qty, pdu[6:6 + bc]))
            self.write_registers(start, vals)
            return pdu[:5]
        if fc == 0x17:
            if broadcast:
                return None
            if len(pdu) < 10:
                raise ModbusError(3)
            rs, rq, ws, wq = struct.unpack(">HHHH", pdu[1:9])
            bc = pdu[9]
            if (not 1 <= rq <= MAX_QTY or not 1 <= wq <= MAX_QTY or bc != 2 * wq
                    or len(pdu) != 10 + bc):
                raise ModbusError(3)
            if not self.readable(rs, rq) or not self.writable(ws, wq):
                raise ModbusError(2)
            vals = list(struct.unpack(">%dH" % wq, pdu[10:10 + bc]))
            self.write_registers(ws, vals)
            out = [self.read_register(a) for a in range(rs, rs + rq)]
            return bytes((fc, 2 * rq)) + struct.pack(">%dH" % rq, *out)
        if fc == 0x08:
            if broadcast:
                return None
            if len(pdu) != 5:
                raise ModbusError(3)
            sub, data = struct.unpack(">HH", pdu[1:5])
            if sub == 0x00:
                return pdu
            if sub not in (0x0A, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F):
                raise ModbusError(1)
            if data != 0:
                raise ModbusError(3)
            c = self.counters
            if sub == 0x0A:
                for k in c:
                    c[k] = 0
                val = 0
            else:
                val = {0x0B: c["bus_message"], 0x0C: c["bus_comm_error"],
                       0x0D: c["bus_exception_error"], 0x0E: c["slave_message"],
                       0x0F: c["slave_no_response"]}[sub]
            return struct.pack(">BHH", 0x08, sub, val)
        if fc == 0x2B:
            if broadcast:
                return None
            return self.handle_mei(pdu)
        raise ModbusError(1)

    def handle_mei(self, pdu):
        if len(pdu) < 2:
            raise ModbusError(3)
        if pdu[1] != 0x0D:
            raise ModbusError(1)
        layout = mei_layout(pdu)
        if layout is None:
            raise ModbusError(3)
        has_rsv = layout
        p = 4 if has_rsv else 3          # offset of Node-ID
        ctrl = pdu[2]
        if ctrl & 0x7F:
            raise ModbusError(3)
        if has_rsv and pdu[3] != 0:
            raise ModbusError(3)
        node = pdu[p]
        index = (pdu[p + 1] << 8) | pdu[p + 2]
        sub = pdu[p + 3]
        offset = (pdu[p + 4] << 8) | pdu[p + 5]
        n = (pdu[p + 6] << 8) | pdu[p + 7]
        data = pdu[p + 8:]
        if node != (self.address & 0xFF):
            raise ModbusError(2)
        if offset != 0 or n > 4:
            raise ModbusError(3)
        header = pdu[:p + 6]
        try:
            if ctrl & 0x80:
                self.sdo_write(index, sub, data)
                return pdu
            out = self.sdo_read(index, sub, n)
            return header + struct.pack(">H", len(out)) + out
        except SdoError as e:
            return bytes((0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + struct.pack("<I", e.code)


def mei_layout(pdu):
    """Decide FC43/MEI 0x0D layout from the PDU length.
    True = with reserved byte (manual table), False = without (manual example 6.2),
    None = length fits neither."""
    if len(pdu) < 3:
        return None
    write = bool(pdu[2] & 0x80)
    # with reserved: fc mei ctrl rsv node idx(2) sub off(2) cnt(2) = 12 bytes
    if len(pdu) >= 12:
        n = (pdu[10] << 8) | pdu[11]
        if len(pdu) == 12 + (n if write else 0):
            return True
    if len(pdu) >= 11:
        n = (pdu[9] << 8) | pdu[10]
        if len(pdu) == 11 + (n if write else 0):
            return False
    return None


# ---------------------------------------------------------------------------
# Stream framing (RTU over TCP)
# ---------------------------------------------------------------------------
def candidate_lengths(buf):
    """Possible ADU lengths for the frame at the start of buf.
    None = need more bytes to decide, [] = unknown function (length unknown)."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (0x03, 0x04, 0x06, 0x08):
        return [8]
    if fc == 0x10:
        return [9 + buf[6]] if len(buf) >= 7 else None
    if fc == 0x17:
        return [13 + buf[10]] if len(buf) >= 11 else None
    if fc == 0x2B:
        if len(buf) < 4:
            return None
        if not buf[3] & 0x80:
            return [15, 14]          # with / without reserved byte
        c = []
        if len(buf) >= 13:
            c.append(15 + ((buf[11] << 8) | buf[12]))
        if len(buf) >= 12:
            c.append(14 + ((buf[10] << 8) | buf[11]))
        return c if len(c) == 2 else None
    return []


class StreamFramer:
    MAX_BUF = 1024

    def __init__(self, drive):
        self.drive = drive
        self.buf = bytearray()

    def _delimited(self, frame, out):
        if crc_ok(frame):
            r = self.drive.handle_frame(bytes(frame))
            if r:
                out.append(r)
        else:
            with self.drive.lock:
                self.drive._inc("bus_comm_error")

    def feed(self, data):
        out = []
        self.buf += data
        if len(self.buf) > self.MAX_BUF:
            self.buf.clear()
            with self.drive.lock:
                self.drive._inc("bus_comm_error")
            return out
        while self.buf:
            b = self.buf
            c = candidate_lengths(b)
            if c is None:
                break
            done = False
            for L in c:
                if len(b) >= L and crc_ok(b[:L]):
                    r = self.drive.handle_frame(bytes(b[:L]))
                    if r:
                        out.append(r)
                    del b[:L]
                    done = True
                    break
            if done:
                continue
            if c and len(b) >= max(c):
                if crc_ok(b):
                    self._delimited(b, out)
                    b.clear()
                else:
                    # corrupted frame: drop the length its header announced
                    with self.drive.lock:
                        self.drive._inc("bus_comm_error")
                    del b[:min(c)]
                continue
            # incomplete, or unknown function: a chunk ending with a valid CRC is a frame
            if len(b) >= 4 and crc_ok(b):
                self._delimited(b, out)
                b.clear()
            break
        return out

    def idle(self):
        """Silence on the stream: whatever is buffered is one (possibly broken) frame."""
        out = []
        if self.buf:
            self._delimited(self.buf, out)
            self.buf.clear()
        return out


def serve_tcp_conn(conn, drive, stop):
    framer = StreamFramer(drive)
    conn.settimeout(0.3)
    try:
        while not stop.is_set():
            try:
                data = conn.recv(4096)
            except socket.timeout:
                for r in framer.idle():
                    conn.sendall(r)
                continue
            except OSError:
                break
            if not data:
                break
            for r in framer.feed(data):
                conn.sendall(r)
    except Exception:
        pass
    finally:
        try:
            conn.close()
        except OSError:
            pass


def serve_tcp(lsock, drive, stop):
    while not stop.is_set():
        try:
            conn, _ = lsock.accept()
        except socket.timeout:
            continue
        except OSError:
            if stop.is_set():
                break
            time.sleep(0.05)
            continue
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        threading.Thread(target=serve_tcp_conn, args=(conn, drive, stop), daemon=True).start()


# ---------------------------------------------------------------------------
# Serial line
# ---------------------------------------------------------------------------
def open_serial(dev, baud, parity):
    import termios
    fd = os.open(dev, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    attrs = termios.tcgetattr(fd)
    iflag, oflag, cflag, lflag, ispeed, ospeed, cc = attrs
    iflag &= ~(termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP | termios.INLCR
               | termios.IGNCR | termios.ICRNL | termios.IXON | termios.IXOFF | termios.IXANY
               | termios.INPCK)
    oflag &= ~termios.OPOST
    lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
    cflag &= ~(termios.CSIZE | termios.PARENB | termios.PARODD | termios.CSTOPB)
    cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
    if parity in ("even", "odd"):
        cflag |= termios.PARENB
        iflag |= termios.INPCK
        if parity == "odd":
            cflag |= termios.PARODD
    if hasattr(termios, "CRTSCTS"):
        cflag &= ~termios.CRTSCTS
    speed = getattr(termios, "B%d" % baud, None)
    if speed is not None:
        ispeed = ospeed = speed
    cc = list(cc)
    cc[termios.VMIN] = 0
    cc[termios.VTIME] = 0
    try:
        termios.tcsetattr(fd, termios.TCSANOW, [iflag, oflag, cflag, lflag, ispeed, ospeed, cc])
    except termios.error:
        pass
    return fd


def serial_write(fd, data):
    view = memoryview(data)
    deadline = time.monotonic() + 2.0
    while view and time.monotonic() < deadline:
        try:
            n = os.write(fd, view)
            view = view[n:]
        except BlockingIOError:
            select.select([], [fd], [], 0.05)
        except OSError:
            return


def serve_serial(fd, drive, baud, stop):
    if baud > 19200:
        t35 = 0.00175
    else:
        t35 = 3.5 * 11.0 / baud
    buf = bytearray()
    while not stop.is_set():
        try:
            r, _, _ = select.select([fd], [], [], t35 if buf else 0.2)
        except (OSError, ValueError):
            time.sleep(0.05)
            continue
        if r:
            try:
                data = os.read(fd, 512)
            except BlockingIOError:
                continue
            except OSError:
                time.sleep(0.05)     # e.g. EIO while the other pty end is closed
                continue
            if data:
                buf += data
                if len(buf) > 2048:
                    del buf[:-512]
                continue
            time.sleep(0.01)
            continue
        if buf:
            frame = bytes(buf)
            buf.clear()
            if len(frame) > 256 or not crc_ok(frame):
                with drive.lock:
                    drive._inc("bus_comm_error")
                continue
            resp = drive.handle_frame(frame)
            if resp:
                serial_write(fd, resp)


# ---------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------
def write_state(drive, path):
    if not path:
        return
    try:
        snap = drive.snapshot()
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(snap, f, indent=1, sort_keys=True)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except Exception as e:
        print("state dump failed: %s" % e, file=sys.stderr, flush=True)


def main():
    ap = argparse.ArgumentParser(description="SIEB & MEYER SD2x Modbus RTU simulator")
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--listen", help="HOST:PORT for RTU-over-TCP")
    g.add_argument("--serial", help="serial device")
    ap.add_argument("--baud", type=int, default=19200)
    ap.add_argument("--parity", choices=("even", "odd", "none"), default="none")
    ap.add_argument("--address", type=int, default=1)
    ap.add_argument("--state")
    a = ap.parse_args()
    if not 1 <= a.address <= 247:
        ap.error("address must be 1..247")

    drive = Drive(a.address)
    stop = threading.Event()

    def physics():
        while not stop.is_set():
            try:
                drive.tick()
            except Exception:
                pass
            stop.wait(0.02)

    def on_usr1(signum, frame):
        write_state(drive, a.state)

    def on_term(signum, frame):
        stop.set()

    signal.signal(signal.SIGUSR1, on_usr1)
    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)

    threading.Thread(target=physics, daemon=True).start()

    if a.listen:
        host, _, port = a.listen.rpartition(":")
        lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        lsock.bind((host, int(port)))
        lsock.listen(16)
        lsock.settimeout(0.2)
        threading.Thread(target=serve_tcp, args=(lsock, drive, stop), daemon=True).start()
        print("listening tcp %s:%d" % (host, lsock.getsockname()[1]), flush=True)
    else:
        fd = open_serial(a.serial, a.baud, a.parity)
        threading.Thread(target=serve_serial, args=(fd, drive, a.baud, stop), daemon=True).start()
        print("listening serial %s" % a.serial, flush=True)

    while not stop.is_set():
        stop.wait(0.2)
    write_state(drive, a.state)
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
