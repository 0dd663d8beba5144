#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier - Modbus RTU slave simulator (clean-room).

Transports:
  python3 sim.py --listen 127.0.0.1:0 [--state FILE] [--baud B] [--parity none|even|odd]
      RTU frames (address, PDU, CRC) over TCP, as behind a serial device server.
  python3 sim.py --serial /dev/pts/N [--baud B] [--parity none|even|odd] [--state FILE]
      RTU on a serial line (termios, raw).

Standard library only.  See DECISIONS.md for every choice made.
"""
import argparse
import json
import os
import select
import signal
import socket
import sys
import threading
import time

# ---------------------------------------------------------------- CRC
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


def add_crc(frame):
    c = crc16(frame)
    return bytes(frame) + bytes((c & 0xFF, c >> 8))


def crc_ok(frame):
    if len(frame) < 4:
        return False
    c = crc16(frame[:-2])
    return frame[-2] == (c & 0xFF) and frame[-1] == (c >> 8)


# ---------------------------------------------------------------- constants
# Factory setting: ID switch 0, "Address selector switch + 1", programmable
# address 0 -> slave address 1 (manual 2.2.2 table, examples 6.1-6.3).
ID_SWITCH = 0
PROGRAMMABLE_ADDRESS = 0
ADDRESS_MODE = "address_selector_switch_plus_1"
SLAVE_ADDRESS = ID_SWITCH * 2 + 1

MAX_REGS = 48          # n = 1..48 (0x30) for FC03/04/16/23

# CiA 402 states
S_NOT_READY = "not_ready_to_switch_on"
S_SOD = "switch_on_disabled"
S_RTSO = "ready_to_switch_on"
S_SO = "switched_on"
S_OE = "operation_enabled"
S_QS = "quick_stop_active"
S_FRA = "fault_reaction_active"
S_FAULT = "fault"

STATE_BITS = {            # bits 0,1,2,3,5,6 per CiA 402
    S_NOT_READY: 0x0000,
    S_SOD: 0x0040 | 0x0020,
    S_RTSO: 0x0021,
    S_SO: 0x0023,
    S_OE: 0x0027,
    S_QS: 0x0007,
    S_FRA: 0x002F,
    S_FAULT: 0x0028,
}

ERR_NONE = 0x0000
ERR_WATCHDOG = 0x8130   # CiA 301 emergency code: life guard / heartbeat error
ERROR_TEXT = {ERR_NONE: "no error", ERR_WATCHDOG: "Heartbeat/Watchdog"}

# Identification / rating constants of this unit
HW_ID = 0x00000215
HW_VERSION = 0x00020010      # 2.16 (manual example value)
SW_ID = 0x00000D21
SW_VERSION = 0x00040011      # 4.17
MAX_IQ = 200                 # 20.0 A (0.1 A)
MAX_SPEED = 10000            # 1000.0 Hz (0.1 Hz)
SPEED_SCALING = 60000000     # 60000.000 rpm = 1000 Hz (0.001 rpm)
CURRENT_SCALING = 20000      # 20.000 A (0.001 A)
DC_BUS = 5650                # 565.0 V: mains connected on the bench
T_STAGE = 170                # 17.0 degC (manual example 6.2)
T_MOTOR = 0                  # no motor temperature sensor connected

RAMP = 2000.0                # 0.1 Hz per second (200 Hz/s)
QS_RAMP = 10000.0            # quick stop / fault reaction ramp

SDO_CMD_INVALID = 0xFFFF0003
SDO_UNSUPPORTED = 0xFFFF0008
SDO_WRITE_RO = 0xFFFF000A
SDO_NO_OBJECT = 0xFFFF000B
SDO_LEN_WRONG = 0xFFFF0011
SDO_LEN_HIGH = 0xFFFF0012
SDO_LEN_LOW = 0xFFFF0013
SDO_NO_SUBINDEX = 0xFFFF0014


def s16(v):
    v &= 0xFFFF
    return v - 0x10000 if v & 0x8000 else v


class ModbusExc(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


class SdoError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


# ---------------------------------------------------------------- device
class Drive:
    def __init__(self, baud, parity):
        self.lock = threading.RLock()
        self.baud = baud
        self.parity = parity
        # RxPDO (holding registers 3000..3003), power-on defaults 0
        self.control_word = 0
        self.target_velocity = 0       # int16, 0.1 Hz
        self.torque_limit = 0          # int16, 0.1 A
        self.watchdog = 0              # uint16, ms
        self.wd_last = time.monotonic()
        # Bench state: fault latched before shipment (watchdog tripped when the
        # last controller was unplugged).  See DECISIONS.md.
        self.state = S_FAULT
        self.error_code = ERR_WATCHDOG
        self.fault_latched = True
        self.speed = 0.0               # actual speed, 0.1 Hz
        self.last_tick = time.monotonic()
        self.counters = dict(bus_message=0, bus_comm_error=0, bus_exception_error=0,
                             slave_message=0, slave_no_response=0)

    # ---------------- dynamics
    def tick(self):
        with self.lock:
            now = time.monotonic()
            dt = now - self.last_tick
            self.last_tick = now
            if dt < 0:
                dt = 0
            # watchdog monitoring (active whenever register != 0)
            if self.watchdog and (now - self.wd_last) * 1000.0 > self.watchdog:
                if self.state not in (S_FAULT, S_FRA):
                    self._fault(ERR_WATCHDOG)
            # speed
            if self.state == S_OE:
                tgt = max(-MAX_SPEED, min(MAX_SPEED, self.target_velocity))
                if self.torque_limit == 0:
                    tgt = self.speed  # no torque available: cannot accelerate
                rate = RAMP
            else:
                tgt = 0.0
                rate = QS_RAMP if self.state in (S_QS, S_FRA) else RAMP
            step = rate * dt
            if self.speed < tgt:
                self.speed = min(tgt, self.speed + step)
            elif self.speed > tgt:
                self.speed = max(tgt, self.speed - step)
            if self.state == S_QS and self.speed == 0:
                self.state = S_SOD
            if self.state == S_FRA and self.speed == 0:
                self.state = S_FAULT

    def _fault(self, code):
        self.error_code = code
        self.fault_latched = True
        self.state = S_FRA if self.speed != 0 else S_FAULT

    def _watchdog_expired(self):
        return bool(self.watchdog) and (time.monotonic() - self.wd_last) * 1000.0 > self.watchdog

    # ---------------- control word (CiA 402 device control)
    def write_control_word(self, new):
        old = self.control_word
        self.control_word = new & 0xFFFF
        st = self.state
        if st in (S_FAULT, S_FRA):
            if st == S_FAULT and (new & 0x80) and not (old & 0x80):
                # fault reset (rising edge bit 7): clears a latched fault whose
                # cause is gone; the watchdog fault re-trips if still expired.
                if self._watchdog_expired():
                    return
                self.fault_latched = False
                self.error_code = ERR_NONE
                self.state = S_SOD
            return  # every other command is taken but not acted on
        if new & 0x80:
            return  # bit 7 set outside fault: no state change
        cmd = new & 0x0F
        if (new & 0x02) == 0:                       # disable voltage
            self.state = S_SOD
        elif (new & 0x06) == 0x02:                  # quick stop
            if st == S_OE:
                self.state = S_QS
            elif st in (S_RTSO, S_SO):
                self.state = S_SOD
        elif (new & 0x07) == 0x06:                  # shutdown
            if st in (S_SOD, S_SO, S_OE):
                self.state = S_RTSO
        elif cmd == 0x07:                           # switch on / disable operation
            if st in (S_RTSO, S_OE):
                self.state = S_SO
        elif cmd == 0x0F:                           # enable operation
            if st in (S_SO, S_RTSO):                # 3+4 allowed (manual ex. 6.1)
                self.state = S_OE
            elif st == S_QS:
                pass

    # ---------------- status
    def status_word(self):
        sw = STATE_BITS[self.state] | 0x0010        # bit 4: voltage enabled (DC bus present)
        sw |= 0x6000                                # bits 13,14: manufacturer-specific, always 1
        if int(self.speed) == 0:
            sw |= 0x1000                            # bit 12: speed = 0
        if self.state == S_OE and self.torque_limit != 0 and \
                int(self.speed) == max(-MAX_SPEED, min(MAX_SPEED, self.target_velocity)):
            sw |= 0x0400                            # bit 10: target reached
        return sw

    def actual_values(self):
        spd = int(self.speed)
        running = self.state in (S_OE, S_QS, S_FRA)
        if running:
            cur = 15 + (20 if int(self.speed) != max(-MAX_SPEED, min(MAX_SPEED, self.target_velocity)) else 0)
            cur = min(cur, abs(self.torque_limit), MAX_IQ) if self.torque_limit else 0
            outv = abs(spd) * 4 // 10
            power = abs(spd) * cur // 5000
        else:
            cur = outv = power = 0
        return spd, cur, power, outv

    # ---------------- register image
    def tx_registers(self):
        self.tick()
        spd, cur, power, outv = self.actual_values()
        regs = [
            self.status_word(), spd & 0xFFFF, self.torque_limit & 0xFFFF, cur & 0xFFFF,
            power & 0xFFFF, self.error_code, T_STAGE & 0xFFFF, T_MOTOR & 0xFFFF,
            outv & 0xFFFF, DC_BUS & 0xFFFF,
        ]
        for v in (HW_ID, HW_VERSION, SW_ID, SW_VERSION):
            regs += [(v >> 16) & 0xFFFF, v & 0xFFFF]
        regs += [MAX_IQ & 0xFFFF, MAX_SPEED & 0xFFFF]
        for v in (SPEED_SCALING, CURRENT_SCALING):
            v &= 0xFFFFFFFF
            regs += [(v >> 16) & 0xFFFF, v & 0xFFFF]
        return regs  # 2000..2023

    def rx_registers(self):
        return [self.control_word, self.target_velocity & 0xFFFF,
                self.torque_limit & 0xFFFF, self.watchdog]

    def read_registers(self, start, count):
        end = start + count
        if 2000 <= start and end <= 2024:
            return self.tx_registers()[start - 2000:end - 2000]
        if 3000 <= start and end <= 3004:
            self.tick()
            return self.rx_registers()[start - 3000:end - 3000]
        raise ModbusExc(2)

    @staticmethod
    def check_writable(start, count):
        if not (3000 <= start and start + count <= 3004):
            raise ModbusExc(2)

    def write_registers(self, start, values):
        self.tick()
        for i, v in enumerate(values):
            self._write_reg(start + i, v)

    def _write_reg(self, addr, v):
        if addr == 3000:
            self.write_control_word(v)
        elif addr == 3001:
            self.target_velocity = s16(v)
        elif addr == 3002:
            self.torque_limit = s16(v)
        elif addr == 3003:
            self.watchdog = v & 0xFFFF
            self.wd_last = time.monotonic()

    # ---------------- object dictionary (FC43)
    # index: (name, size, signed, access, getter, setter)
    def objects(self):
        tx = None

        def txv(i):
            nonlocal tx
            if tx is None:
                tx = self.tx_registers()
            return tx[i]

        def tx32(i):
            return (txv(i) << 16) | txv(i + 1)
        return {
            2: ("Hardware ID", 4, False, "ro", lambda: tx32(10), None),
            5: ("Hardware Version", 4, False, "ro", lambda: tx32(12), None),
            16: ("Software ID", 4, False, "ro", lambda: tx32(14), None),
            17: ("Software Version", 4, False, "ro", lambda: tx32(16), None),
            33: ("DC Voltage", 2, True, "ro", lambda: txv(9), None),
            41: ("Temperature Power Stage", 2, True, "ro", lambda: txv(6), None),
            63: ("Temperature Motor", 2, True, "ro", lambda: txv(7), None),
            67: ("Status Word", 2, False, "ro", lambda: txv(0), None),
            68: ("Control Word", 2, False, "rw", lambda: self.control_word,
                 lambda v: self._write_reg(3000, v)),
            70: ("Error Code", 2, False, "ro", lambda: txv(5), None),
            120: ("Max Speed", 2, True, "ro", lambda: txv(19), None),
            168: ("Actual Speed", 2, True, "ro", lambda: txv(1), None),
            171: ("Max Iq Current", 2, True, "ro", lambda: txv(18), None),
            177: ("Speed Scaling", 4, True, "ro", lambda: tx32(20), None),
            182: ("Current Scaling", 4, True, "ro", lambda: tx32(22), None),
            209: ("Target Torque Limit", 2, True, "rw", lambda: self.torque_limit & 0xFFFF,
                  lambda v: self._write_reg(3002, v)),
            210: ("Target Velocity", 2, True, "rw", lambda: self.target_velocity & 0xFFFF,
                  lambda v: self._write_reg(3001, v)),
            390: ("Actual Output Power", 2, True, "ro", lambda: txv(4), None),
            431: ("Actual Apparent Current", 2, True, "ro", lambda: txv(3), None),
            434: ("Output Voltage", 2, True, "ro", lambda: txv(8), None),
        }

    # ---------------- dump
    def dump(self):
        with self.lock:
            self.tick()
            tx = self.tx_registers()
            rx = self.rx_registers()
            hr = {str(2000 + i): v for i, v in enumerate(tx)}
            hr.update({str(3000 + i): v for i, v in enumerate(rx)})
            objs = {}
            for idx, (name, size, signed, acc, get, _s) in sorted(self.objects().items()):
                v = get()
                if signed:
                    v = v - (1 << (8 * size)) if v & (1 << (8 * size - 1)) else v
                objs[str(idx)] = {"name": name, "subindex": {"0": v}, "access": acc.upper(),
                                  "size_bytes": size}
            sw = tx[0]
            return {
                "device": "SIEB & MEYER SD2x (single-axis) Modbus RTU simulator",
                "bus_settings": {"slave_address": SLAVE_ADDRESS, "address_mode": ADDRESS_MODE,
                                 "id_switch": ID_SWITCH,
                                 "programmable_address": PROGRAMMABLE_ADDRESS,
                                 "baud": self.baud, "parity": self.parity, "stop_bits": 1,
                                 "node_id": SLAVE_ADDRESS},
                "registers": hr,
                "input_registers_txpdo": {str(2000 + i): v for i, v in enumerate(tx)},
                "holding_registers_rxpdo": {str(3000 + i): v for i, v in enumerate(rx)},
                "objects": objs,
                "drive_status": {
                    "cia402_state": self.state,
                    "status_word": sw,
                    "status_bits": {
                        "ready_to_switch_on": bool(sw & 1), "switched_on": bool(sw & 2),
                        "operation_enabled": bool(sw & 4), "fault": bool(sw & 8),
                        "voltage_enabled": bool(sw & 0x10), "quick_stop": bool(sw & 0x20),
                        "switch_on_disabled": bool(sw & 0x40), "warning": bool(sw & 0x80),
                        "remote": bool(sw & 0x200), "target_reached": bool(sw & 0x400),
                        "speed_zero": bool(sw & 0x1000)},
                    "fault_latched": self.fault_latched,
                    "error_code": self.error_code,
                    "error_text": ERROR_TEXT.get(self.error_code, "unknown"),
                    "warnings": [],
                    "watchdog_monitoring_active": bool(self.watchdog),
                    "watchdog_expired": self._watchdog_expired(),
                    "dc_bus_present": True,
                    "power_stage_enabled": self.state in (S_OE, S_QS, S_FRA),
                },
                "diagnostic_counters": dict(self.counters),
            }


# ---------------------------------------------------------------- protocol
class Protocol:
    def __init__(self, drive):
        self.d = drive

    @staticmethod
    def expected_lengths(buf):
        """Candidate complete-frame lengths (incl. CRC) for the buffered request,
        or None if not determinable yet / unknown function."""
        if len(buf) < 2:
            return None
        fc = buf[1]
        if fc in (3, 4, 6, 8):
            return [8]
        if fc == 16:
            if len(buf) < 7:
                return None
            return [9 + buf[6]]
        if fc == 23:
            if len(buf) < 11:
                return None
            return [13 + buf[10]]
        if fc == 43:
            if len(buf) < 4 or buf[2] != 0x0D:
                return None
            wr = buf[3] & 0x80
            out = []
            # documented layout (with reserved byte): count at [12:14]
            if len(buf) >= 14:
                n = (buf[12] << 8) | buf[13]
                out.append(15 + (n if wr else 0))
            # example-6.2 layout (no reserved byte): count at [11:13]
            if len(buf) >= 13:
                n = (buf[11] << 8) | buf[12]
                out.append(14 + (n if wr else 0))
            return out or None
        return None

    def handle_frame(self, frame):
        """frame: full RTU ADU with good CRC. Returns response ADU or None."""
        d = self.d
        with d.lock:
            d.counters["bus_message"] = (d.counters["bus_message"] + 1) & 0xFFFF
            addr = frame[0]
            if addr != SLAVE_ADDRESS and addr != 0:
                return None
            d.counters["slave_message"] = (d.counters["slave_message"] + 1) & 0xFFFF
            pdu = bytes(frame[1:-2])
            broadcast = addr == 0
            fc = pdu[0]
            try:
                if broadcast:
                    if fc in (6, 16):
                        self.dispatch(pdu)
                    d.counters["slave_no_response"] = (d.counters["slave_no_response"] + 1) & 0xFFFF
                    return None
                resp = self.dispatch(pdu)
            except ModbusExc as e:
                d.counters["bus_exception_error"] = (d.counters["bus_exception_error"] + 1) & 0xFFFF
                resp = bytes((fc | 0x80, e.code))
            except SdoError as e:
                d.counters["bus_exception_error"] = (d.counters["bus_exception_error"] + 1) & 0xFFFF
                resp = bytes((0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + e.code.to_bytes(4, "little")
            except Exception:  # never crash on a frame
                d.counters["bus_exception_error"] = (d.counters["bus_exception_error"] + 1) & 0xFFFF
                resp = bytes(((fc | 0x80) & 0xFF, 4))
            if resp is None:
                return None
            return add_crc(bytes((SLAVE_ADDRESS,)) + resp)

    def dispatch(self, pdu):
        fc = pdu[0]
        d = self.d
        if fc in (3, 4):
            if len(pdu) != 5:
                raise ModbusExc(3)
            start = (pdu[1] << 8) | pdu[2]
            cnt = (pdu[3] << 8) | pdu[4]
            if not 1 <= cnt <= MAX_REGS:
                raise ModbusExc(3)
            regs = d.read_registers(start, cnt)
            return bytes((fc, 2 * cnt)) + b"".join(r.to_bytes(2, "big") for r in regs)
        if fc == 6:
            if len(pdu) != 5:
                raise ModbusExc(3)
            a = (pdu[1] << 8) | pdu[2]
            v = (pdu[3] << 8) | pdu[4]
            d.check_writable(a, 1)
            d.write_registers(a, [v])
            return pdu
        if fc == 16:
            if len(pdu) < 6:
                raise ModbusExc(3)
            a = (pdu[1] << 8) | pdu[2]
            cnt = (pdu[3] << 8) | pdu[4]
            bc = pdu[5]
            if not 1 <= cnt <= MAX_REGS or bc != 2 * cnt or len(pdu) != 6 + bc:
                raise ModbusExc(3)
            d.check_writable(a, cnt)
            vals = [(pdu[6 + 2 * i] << 8) | pdu[7 + 2 * i] for i in range(cnt)]
            d.write_registers(a, vals)
            return pdu[:5]
        if fc == 23:
            if len(pdu) < 10:
                raise ModbusExc(3)
            ra = (pdu[1] << 8) | pdu[2]
            rc = (pdu[3] << 8) | pdu[4]
            wa = (pdu[5] << 8) | pdu[6]
            wc = (pdu[7] << 8) | pdu[8]
            bc = pdu[9]
            if not 1 <= rc <= MAX_REGS or not 1 <= wc <= MAX_REGS or bc != 2 * wc \
                    or len(pdu) != 10 + bc:
                raise ModbusExc(3)
            d.check_writable(wa, wc)
            d.read_registers(ra, rc)  # address check before anything is written
            vals = [(pdu[10 + 2 * i] << 8) | pdu[11 + 2 * i] for i in range(wc)]
            d.write_registers(wa, vals)
            regs = d.read_registers(ra, rc)
            return bytes((23, 2 * rc)) + b"".join(r.to_bytes(2, "big") for r in regs)
        if fc == 8:
            return self.diag(pdu)
        if fc == 43:
            return self.mei(pdu)
        raise ModbusExc(1)

    def diag(self, pdu):
        c = self.d.counters
        if len(pdu) < 3:
            raise ModbusExc(3)
        sub = (pdu[1] << 8) | pdu[2]
        if sub == 0:
            return pdu  # return query data (any length)
        if sub not in (10, 11, 12, 13, 14, 15):
            raise ModbusExc(1)
        if len(pdu) != 5:
            raise ModbusExc(3)
        if sub == 10:
            for k in c:
                c[k] = 0
            return pdu
        key = {11: "bus_message", 12: "bus_comm_error", 13: "bus_exception_error",
               14: "slave_message", 15: "slave_no_response"}[sub]
        return pdu[:3] + (c[key] & 0xFFFF).to_bytes(2, "big")

    def mei(self, pdu):
        if len(pdu) < 2:
            raise ModbusExc(3)
        if pdu[1] != 0x0D:
            raise ModbusExc(1)
        ctrl = pdu[2] if len(pdu) > 2 else 0
        write = bool(ctrl & 0x80)

        def try_layout(reserved):
            h = 11 if reserved else 10  # bytes up to and incl. byte count
            if len(pdu) < h + 1:
                return None
            n = (pdu[h - 1] << 8) | pdu[h]
            if len(pdu) != h + 1 + (n if write else 0):
                return None
            return h
        h = try_layout(True)
        reserved = True
        if h is None:
            h = try_layout(False)
            reserved = False
        if h is None:
            raise ModbusExc(3)
        p = 3
        if reserved:
            if pdu[3] != 0:
                raise ModbusExc(3)
            p = 4
        node = pdu[p]
        idx = (pdu[p + 1] << 8) | pdu[p + 2]
        sub = pdu[p + 3]
        off = (pdu[p + 4] << 8) | pdu[p + 5]
        n = (pdu[p + 6] << 8) | pdu[p + 7]
        data = pdu[p + 8:]
        if n > 4:
            raise ModbusExc(3)
        if node != SLAVE_ADDRESS:
            raise ModbusExc(2)
        header = pdu[:p + 6]  # fc .. address offset
        if ctrl & 0x7F:
            raise SdoError(SDO_CMD_INVALID)
        objs = self.d.objects()
        if idx not in objs:
            raise SdoError(SDO_NO_OBJECT)
        name, size, signed, acc, get, setter = objs[idx]
        if sub != 0:
            raise SdoError(SDO_NO_SUBINDEX)
        if off != 0:
            raise SdoError(SDO_UNSUPPORTED)
        if not write:
            if n == 0:
                n = size
            if n > size:
                raise SdoError(SDO_LEN_HIGH)
            if n < size:
                raise SdoError(SDO_LEN_LOW)
            v = get() & ((1 << (8 * size)) - 1)
            return header + n.to_bytes(2, "big") + v.to_bytes(size, "little")
        if acc == "ro":
            raise SdoError(SDO_WRITE_RO)
        if n == 0:
            raise SdoError(SDO_LEN_WRONG)
        if n > size:
            raise SdoError(SDO_LEN_HIGH)
        if n < size:
            raise SdoError(SDO_LEN_LOW)
        self.d.tick()
        setter(int.from_bytes(data, "little"))
        return header + n.to_bytes(2, "big")


# ---------------------------------------------------------------- framer
class Framer:
    """Collects bytes; a request ends when its length (from the function code)
    is reached and the CRC matches, or at an inter-frame silence."""

    def __init__(self, proto, silence):
        self.proto = proto
        self.silence = silence
        self.buf = bytearray()
        self.last_rx = 0.0

    def feed(self, data):
        out = []
        if self.buf and self._complete_frame(data):
            # leftover bytes that never formed a frame, followed by a chunk
            # that is a whole valid frame on its own: resynchronise
            self._bad()
        self.buf += data
        self.last_rx = time.monotonic()
        if len(self.buf) > 512:           # no RTU frame is longer than 256 bytes
            self._bad()
            return out
        while self.buf:
            lens = Protocol.expected_lengths(self.buf)
            if not lens:
                break
            hit = None
            for L in lens:
                if len(self.buf) >= L and crc_ok(self.buf[:L]):
                    hit = L
                    break
            if hit is None:
                break
            frame = bytes(self.buf[:hit])
            del self.buf[:hit]
            r = self.proto.handle_frame(frame)
            if r:
                out.append(r)
        return out

    @staticmethod
    def _complete_frame(data):
        lens = Protocol.expected_lengths(data)
        return bool(lens) and any(len(data) >= L and crc_ok(data[:L]) for L in lens)

    def timeout(self):
        """Seconds until the pending silence expires, or None."""
        if not self.buf:
            return None
        return max(0.0, self.last_rx + self.silence - time.monotonic())

    def on_silence(self):
        out = []
        if self.buf:
            frame = bytes(self.buf)
            self.buf.clear()
            if len(frame) >= 4 and crc_ok(frame):
                r = self.proto.handle_frame(frame)
                if r:
                    out.append(r)
            else:
                self._count_bad(frame)
                # garbage glued to a valid request (TCP coalescing): answer a
                # complete valid frame found at the end of the buffer
                for i in range(1, len(frame) - 3):
                    tail = frame[i:]
                    lens = Protocol.expected_lengths(tail)
                    if lens and len(tail) in lens and crc_ok(tail):
                        r = self.proto.handle_frame(tail)
                        if r:
                            out.append(r)
                        break
        return out

    def _bad(self):
        self._count_bad(bytes(self.buf))
        self.buf.clear()

    def _count_bad(self, frame):
        d = self.proto.d
        with d.lock:
            d.counters["bus_comm_error"] = (d.counters["bus_comm_error"] + 1) & 0xFFFF


# ---------------------------------------------------------------- transports
def char_time(baud, parity):
    bits = 1 + 8 + (0 if parity == "none" else 1) + 1
    return bits / float(baud)


def t35(baud, parity):
    if baud > 19200:
        return 0.00175
    return 3.5 * char_time(baud, parity)


def serve_conn(sock, proto, silence, stop):
    fr = Framer(proto, silence)
    sock.setblocking(False)
    try:
        while not stop.is_set():
            to = fr.timeout()
            wait = 0.5 if to is None else to
            r, _, _ = select.select([sock], [], [], wait)
            if r:
                try:
                    data = sock.recv(4096)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:
                    break
                if not data:
                    break
                resps = fr.feed(data)
            else:
                resps = fr.on_silence() if fr.buf else []
            for resp in resps:
                try:
                    sock.setblocking(True)
                    sock.settimeout(2.0)
                    sock.sendall(resp)
                except OSError:
                    return
                finally:
                    try:
                        sock.setblocking(False)
                    except OSError:
                        pass
    finally:
        try:
            sock.close()
        except OSError:
            pass


def tcp_server(host, port, proto, silence, stop):
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind((host, port))
    srv.listen(16)
    return srv


def accept_loop(srv, proto, silence, stop):
    while not stop.is_set():
        try:
            r, _, _ = select.select([srv], [], [], 0.5)
            if not r:
                continue
            c, _ = srv.accept()
            c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError:
            continue
        threading.Thread(target=serve_conn, args=(c, proto, silence, stop), daemon=True).start()


def open_serial(path, baud, parity):
    import termios
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    attrs = termios.tcgetattr(fd)
    iflag, oflag, cflag, lflag, ispeed, ospeed, cc = attrs
    iflag = 0 if parity == "none" else termios.INPCK
    oflag = 0
    lflag = 0
    cflag = termios.CS8 | termios.CREAD | termios.CLOCAL
    if parity != "none":
        cflag |= termios.PARENB
        if parity == "odd":
            cflag |= termios.PARODD
    speed = getattr(termios, "B%d" % baud, None)
    if speed is None:
        speed = termios.B19200  # 14400/28800 have no POSIX constant
    cc = list(cc)
    cc[termios.VMIN] = 0
    cc[termios.VTIME] = 0
    termios.tcsetattr(fd, termios.TCSANOW, [iflag, oflag, cflag, lflag, speed, speed, cc])
    return fd


def serial_loop(fd, proto, silence, stop):
    fr = Framer(proto, silence)
    while not stop.is_set():
        to = fr.timeout()
        wait = 0.5 if to is None else to
        try:
            r, _, _ = select.select([fd], [], [], wait)
        except (OSError, ValueError):
            time.sleep(0.1)
            continue
        resps = []
        if r:
            try:
                data = os.read(fd, 4096)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                time.sleep(0.05)  # peer closed (pty): keep the line open
                continue
            if not data:
                time.sleep(0.01)
                continue
            # bytes are collected until silence on a serial line; length-
            # based completion is also applied (see DECISIONS.md)
            resps = fr.feed(data)
        else:
            resps = fr.on_silence() if fr.buf else []
        for resp in resps:
            try:
                view = resp
                t_end = time.monotonic() + 2.0
                while view and time.monotonic() < t_end:
                    try:
                        n = os.write(fd, view)
                        view = view[n:]
                    except BlockingIOError:
                        select.select([], [fd], [], 0.05)
            except OSError:
                pass


def ticker(drive, stop):
    while not stop.wait(0.02):
        try:
            drive.tick()
        except Exception:
            pass


def write_state(drive, path):
    if not path:
        return
    try:
        data = drive.dump()
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(data, f, indent=1, sort_keys=True)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except Exception as e:  # never die from a dump
        sys.stderr.write("state dump failed: %s\n" % e)


def main():
    ap = argparse.ArgumentParser(description="SIEB & MEYER SD2x Modbus RTU simulator")
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--listen", help="HOST:PORT (RTU frames over TCP)")
    g.add_argument("--serial", help="serial device path")
    ap.add_argument("--state", help="JSON state dump file")
    ap.add_argument("--baud", type=int, default=19200,
                    choices=[9600, 14400, 19200, 28800, 38400, 57600, 115200])
    ap.add_argument("--parity", choices=["none", "even", "odd"], default="none")
    a = ap.parse_args()

    drive = Drive(a.baud, a.parity)
    proto = Protocol(drive)
    stop = threading.Event()
    flags = {"dump": False, "exit": False}

    def on_usr1(_s, _f):
        flags["dump"] = True

    def on_term(_s, _f):
        flags["exit"] = True
        stop.set()

    signal.signal(signal.SIGUSR1, on_usr1)
    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)

    threading.Thread(target=ticker, args=(drive, stop), daemon=True).start()
    if a.listen:
        host, _, port = a.listen.rpartition(":")
        silence = max(t35(a.baud, a.parity), 0.050)
        srv = tcp_server(host, int(port), proto, silence, stop)
        threading.Thread(target=accept_loop, args=(srv, proto, silence, stop), daemon=True).start()
        print("listening tcp %s:%d" % (host, srv.getsockname()[1]), flush=True)
    else:
        fd = open_serial(a.serial, a.baud, a.parity)
        silence = max(t35(a.baud, a.parity), 0.004)
        threading.Thread(target=serial_loop, args=(fd, proto, silence, stop), daemon=True).start()
        print("listening serial %s" % a.serial, flush=True)

    while not flags["exit"]:
        stop.wait(0.1)
        if flags["dump"]:
            flags["dump"] = False
            write_state(drive, a.state)
    write_state(drive, a.state)
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
