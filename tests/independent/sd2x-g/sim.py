#!/usr/bin/env python3
"""SIEB & MEYER SD2x drive amplifier - Modbus RTU slave simulator.

Serves raw RTU frames (address, PDU, CRC) either on a TCP stream ("RTU over
TCP", --listen) or on a serial line / pty (--serial).  Standard library only.
See DECISIONS.md for every interpretation made.
"""
import argparse
import asyncio
import json
import os
import signal
import sys
import time

# ----------------------------------------------------------------- CRC ----

def _crc_table():
    tab = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0xA001 if c & 1 else c >> 1
        tab.append(c)
    return tab


_CRC_TAB = _crc_table()


def crc16(data):
    c = 0xFFFF
    for b in data:
        c = (c >> 8) ^ _CRC_TAB[(c ^ b) & 0xFF]
    return c


def add_crc(frame):
    c = crc16(frame)
    return bytes(frame) + bytes((c & 0xFF, c >> 8))


def crc_ok(frame):
    if len(frame) < 4:
        return False
    c = crc16(frame[:-2])
    return frame[-2] == (c & 0xFF) and frame[-1] == (c >> 8)


# --------------------------------------------------------------- drive ----

MAX_QTY = 48                    # manual lines 295, 433, 484, 488
TX_BASE, TX_END = 2000, 2023    # TxPDO (input registers), inclusive
RX_BASE, RX_END = 3000, 3003    # RxPDO (holding registers), inclusive
TX_32_LOW = (2010, 2012, 2014, 2016, 2020, 2022)   # first word of 32-bit values

SPEED_LIMIT = 10000             # 1000.0 Hz = Max Speed (0x3FFF = speed scaling)
RAMP = 2000.0                   # 0.1 Hz per second (200 Hz/s)
QS_RAMP = 5000.0                # quick stop ramp
WATCHDOG_ERROR = 0x8130         # CiA 301 life guard / heartbeat error

# DS402 states
SOD, RTSO, SON, OE, QSA, FAULT = ('switch_on_disabled', 'ready_to_switch_on',
                                  'switched_on', 'operation_enabled',
                                  'quick_stop_active', 'fault')
STATE_BITS = {SOD: 0x0040, RTSO: 0x0021, SON: 0x0023, OE: 0x0027,
              QSA: 0x0007, FAULT: 0x0008}

# SDO abort codes (manual 3.8)
SDO_CMD = 0xFFFF0003
SDO_UNSUPPORTED = 0xFFFF0008
SDO_READ_ONLY = 0xFFFF000A
SDO_NO_OBJECT = 0xFFFF000B
SDO_TOO_LONG = 0xFFFF0012
SDO_TOO_SHORT = 0xFFFF0013
SDO_NO_SUBINDEX = 0xFFFF0014


class Drive:
    def __init__(self, address, baud, parity):
        self.address = address
        self.baud = baud
        self.parity = parity
        # RxPDO (holding registers) - manual defaults 0
        self.control_word = 0
        self.target_speed = 0      # int16, 0.1 Hz
        self.torque_limit = 0      # int16, 0.1 A
        self.watchdog = 0          # uint16, ms
        # drive internals
        self.state = SOD
        self.error_code = 0
        self.speed = 0.0           # 0.1 Hz
        self.wd_deadline = None
        self.last = time.monotonic()
        # constants / measurements (DECISIONS S1)
        self.dc_voltage = 5650
        self.temp_stage = 250
        self.temp_motor = 230
        self.hw_id = 0x00000230
        self.hw_version = 0x00020010
        self.sw_id = 0x00005332
        self.sw_version = 0x00040012
        self.max_iq = 200
        self.max_speed = 0x3FFF
        self.speed_scaling = 60000000
        self.current_scaling = 20000
        self.counters = {'bus_message_count': 0,
                         'bus_communication_error_count': 0,
                         'bus_exception_error_count': 0,
                         'slave_message_count': 0,
                         'slave_no_response_count': 0}
        # object dictionary: index -> (name, size, signed, getter, setter)
        s = self
        self.objects = {
            2: ('Hardware ID', 4, False, lambda: s.hw_id, None),
            5: ('Hardware Version', 4, False, lambda: s.hw_version, None),
            16: ('Software ID', 4, False, lambda: s.sw_id, None),
            17: ('Software Version', 4, False, lambda: s.sw_version, None),
            33: ('DC Voltage', 2, True, lambda: s.dc_voltage, None),
            41: ('Temperature Power Stage', 2, True, lambda: s.temp_stage, None),
            63: ('Temperature Motor', 2, True, lambda: s.temp_motor, None),
            67: ('Status Word', 2, False, lambda: s.status_word(), None),
            68: ('Control Word', 2, False, lambda: s.control_word,
                 lambda v: s.write_control(v)),
            70: ('Error Code', 2, False, lambda: s.error_code, None),
            120: ('Max Speed', 2, True, lambda: s.max_speed, None),
            168: ('Actual Speed', 2, True, lambda: s.actual_speed(), None),
            171: ('Max Iq Current', 2, True, lambda: s.max_iq, None),
            177: ('Speed Scaling', 4, True, lambda: s.speed_scaling, None),
            182: ('Current Scaling', 4, True, lambda: s.current_scaling, None),
            209: ('Target Torque Limit', 2, True, lambda: s.torque_limit,
                  lambda v: setattr(s, 'torque_limit', v)),
            210: ('Target Velocity', 2, True, lambda: s.target_speed,
                  lambda v: setattr(s, 'target_speed', v)),
            390: ('Actual Output Power', 2, True, lambda: s.output_power(), None),
            431: ('Actual Apparent Current', 2, True, lambda: s.apparent_current(), None),
            434: ('Output Voltage', 2, True, lambda: s.output_voltage(), None),
        }

    # ------------------------------------------------------ simulation --
    def eff_target(self):
        if self.state != OE or (self.control_word & 0x0100):
            return 0
        return max(-SPEED_LIMIT, min(SPEED_LIMIT, self.target_speed))

    def update(self):
        now = time.monotonic()
        dt = now - self.last
        self.last = now
        if self.wd_deadline is not None and now >= self.wd_deadline:
            self.wd_deadline = None
            if self.state != FAULT:
                self.state = FAULT
                self.error_code = WATCHDOG_ERROR
        tgt = self.eff_target()
        rate = QS_RAMP if self.state == QSA else RAMP
        step = rate * max(dt, 0.0)
        if self.speed < tgt:
            self.speed = min(tgt, self.speed + step)
        elif self.speed > tgt:
            self.speed = max(tgt, self.speed - step)
        if self.state == QSA and self.speed == 0:
            self.state = SOD

    def actual_speed(self):
        return int(round(self.speed))

    def output_voltage(self):
        return int(round(abs(self.speed) / SPEED_LIMIT * 4000))

    def apparent_current(self):
        if self.speed == 0 and self.state != OE:
            return 0
        return int(round(15 + abs(self.speed) / SPEED_LIMIT * 60))

    def output_power(self):
        v = self.output_voltage() / 10.0
        i = self.apparent_current() / 10.0
        return int(round(1.732 * v * i * 0.8 / 100.0))   # 0.1 kW

    def status_word(self):
        sw = STATE_BITS[self.state] | 0x0010 | 0x0200   # voltage enabled, remote
        tgt = self.eff_target()
        if abs(self.speed - tgt) < 0.5:
            sw |= 0x0400                                 # target reached
        if self.state == OE and abs(self.target_speed) > SPEED_LIMIT:
            sw |= 0x0800                                 # internal limit active
        if self.actual_speed() == 0:
            sw |= 0x1000                                 # pv: speed = 0
        return sw

    def write_control(self, cw):
        prev = self.control_word
        self.control_word = cw
        st = self.state
        if st == FAULT:
            if (cw & 0x80) and not (prev & 0x80):
                self.state = SOD
                self.error_code = 0
            return
        if (cw & 0x80) and not (prev & 0x80):
            pass                     # fault reset outside fault: no effect
        low = cw & 0x0F
        if not (cw & 0x02):                      # disable voltage
            self.state = SOD
        elif not (cw & 0x04):                    # quick stop
            if st == OE:
                self.state = QSA
            elif st in (RTSO, SON):
                self.state = SOD
        elif st == QSA:
            if low == 0x0F:
                self.state = OE
        elif (low & 0x07) == 0x06:               # shutdown
            if st in (SOD, SON, OE):
                self.state = RTSO
        elif low == 0x07:                        # switch on / disable operation
            if st in (RTSO, OE):
                self.state = SON
        elif low == 0x0F:                        # switch on + enable operation
            if st in (RTSO, SON):
                self.state = OE

    # ------------------------------------------------------- registers --
    def input_registers(self):
        r = {}

        def u16(a, v):
            r[a] = v & 0xFFFF

        def u32(a, v):
            v &= 0xFFFFFFFF
            r[a] = v >> 16
            r[a + 1] = v & 0xFFFF
        u16(2000, self.status_word())
        u16(2001, self.actual_speed())
        u16(2002, self.torque_limit)
        u16(2003, self.apparent_current())
        u16(2004, self.output_power())
        u16(2005, self.error_code)
        u16(2006, self.temp_stage)
        u16(2007, self.temp_motor)
        u16(2008, self.output_voltage())
        u16(2009, self.dc_voltage)
        u32(2010, self.hw_id)
        u32(2012, self.hw_version)
        u32(2014, self.sw_id)
        u32(2016, self.sw_version)
        u16(2018, self.max_iq)
        u16(2019, self.max_speed)
        u32(2020, self.speed_scaling)
        u32(2022, self.current_scaling)
        return r

    def holding_registers(self):
        return {3000: self.control_word, 3001: self.target_speed & 0xFFFF,
                3002: self.torque_limit & 0xFFFF, 3003: self.watchdog}

    def read_ok(self, start, qty):
        end = start + qty - 1
        if end > 0xFFFF:
            return False
        if not ((TX_BASE <= start and end <= TX_END) or
                (RX_BASE <= start and end <= RX_END)):
            return False
        if (start - 1) in TX_32_LOW or end in TX_32_LOW:
            return False                         # DECISIONS U3
        return True

    @staticmethod
    def write_ok(start, qty):
        return RX_BASE <= start and start + qty - 1 <= RX_END

    def read_regs(self, start, qty):
        regs = self.input_registers()
        regs.update(self.holding_registers())
        return [regs[a] for a in range(start, start + qty)]

    def write_regs(self, start, values):
        cw = None
        for i, v in enumerate(values):
            a = start + i
            if a == 3000:
                cw = v
            elif a == 3001:
                self.target_speed = v - 0x10000 if v & 0x8000 else v
            elif a == 3002:
                self.torque_limit = v - 0x10000 if v & 0x8000 else v
            elif a == 3003:
                self.watchdog = v
                self.wd_deadline = (time.monotonic() + v / 1000.0) if v else None
        if cw is not None:
            self.write_control(cw)

    # ------------------------------------------------------------ state --
    def dump(self):
        self.update()
        objs = {}
        for idx, (name, size, signed, get, setter) in sorted(self.objects.items()):
            v = get()
            objs['%d/0' % idx] = {'name': name, 'value': v, 'size': size,
                                  'access': 'rw' if setter else 'ro'}
        return {
            'device': 'SIEB & MEYER SD2x (simulated)',
            'config': {'slave_address': self.address, 'baud': self.baud,
                       'parity': self.parity, 'address_mode': 'switch+1',
                       'id_switch': max(0, (self.address - 1) // 2),
                       'programmable_address': 1},
            'holding_registers': {str(a): v for a, v in self.holding_registers().items()},
            'input_registers': {str(a): v for a, v in self.input_registers().items()},
            'objects': objs,
            'drive': {'ds402_state': self.state, 'error_code': self.error_code,
                      'actual_speed_0.1Hz': self.actual_speed(),
                      'watchdog_armed': self.wd_deadline is not None},
            'diagnostic_counters': dict(self.counters),
        }

    # ------------------------------------------------------- protocol ---
    def handle_frame(self, frame):
        """frame: one delimited RTU frame. Returns response ADU or None."""
        self.update()
        if not crc_ok(frame):
            self.counters['bus_communication_error_count'] += 1
            return None
        self.counters['bus_message_count'] += 1
        addr = frame[0]
        if addr != self.address and addr != 0:
            return None
        bc = addr == 0
        self.counters['slave_message_count'] += 1
        try:
            resp = self.process(bytes(frame[1:-2]), bc)
        except Exception:                        # never die on one frame
            resp = None if bc else bytes((frame[1] | 0x80, 0x04))
        if bc or resp is None:
            self.counters['slave_no_response_count'] += 1
            return None
        if resp[0] & 0x80:
            self.counters['bus_exception_error_count'] += 1
        return add_crc(bytes((addr,)) + resp)

    def process(self, pdu, bc):
        fc = pdu[0]

        def exc(code):
            return bytes((fc | 0x80, code))

        if fc in (3, 4):
            if len(pdu) < 5:
                return None
            if len(pdu) > 5:
                return exc(3)
            start = int.from_bytes(pdu[1:3], 'big')
            qty = int.from_bytes(pdu[3:5], 'big')
            if not 1 <= qty <= MAX_QTY:
                return exc(3)
            if not self.read_ok(start, qty):
                return exc(2)
            if bc:
                return None
            vals = self.read_regs(start, qty)
            return bytes((fc, 2 * qty)) + b''.join(v.to_bytes(2, 'big') for v in vals)

        if fc == 6:
            if len(pdu) < 5:
                return None
            if len(pdu) > 5:
                return exc(3)
            a = int.from_bytes(pdu[1:3], 'big')
            v = int.from_bytes(pdu[3:5], 'big')
            if not self.write_ok(a, 1):
                return exc(2)
            self.write_regs(a, [v])
            return bytes(pdu)

        if fc == 16:
            if len(pdu) < 6:
                return None
            start = int.from_bytes(pdu[1:3], 'big')
            qty = int.from_bytes(pdu[3:5], 'big')
            n = pdu[5]
            if len(pdu) != 6 + n or not 1 <= qty <= MAX_QTY or n != 2 * qty:
                return exc(3)
            if not self.write_ok(start, qty):
                return exc(2)
            vals = [int.from_bytes(pdu[6 + 2 * i:8 + 2 * i], 'big') for i in range(qty)]
            self.write_regs(start, vals)
            return bytes(pdu[:5])

        if fc == 23:
            if len(pdu) < 10:
                return None
            rs = int.from_bytes(pdu[1:3], 'big')
            rq = int.from_bytes(pdu[3:5], 'big')
            ws = int.from_bytes(pdu[5:7], 'big')
            wq = int.from_bytes(pdu[7:9], 'big')
            n = pdu[9]
            if (len(pdu) != 10 + n or not 1 <= rq <= MAX_QTY or
                    not 1 <= wq <= MAX_QTY or n != 2 * wq):
                return exc(3)
            if not self.write_ok(ws, wq) or not self.read_ok(rs, rq):
                return exc(2)
            vals = [int.from_bytes(pdu[10 + 2 * i:12 + 2 * i], 'big') for i in range(wq)]
            self.write_regs(ws, vals)
            if bc:
                return None
            out = self.read_regs(rs, rq)
            return bytes((fc, 2 * rq)) + b''.join(v.to_bytes(2, 'big') for v in out)

        if fc == 8:
            if len(pdu) < 5:
                return None
            sub = int.from_bytes(pdu[1:3], 'big')
            if sub not in (0, 10, 11, 12, 13, 14, 15):
                return exc(1)
            if len(pdu) > 5:
                return exc(3)
            data = int.from_bytes(pdu[3:5], 'big')
            if sub == 0:
                return None if bc else bytes(pdu)
            if data != 0:
                return exc(3)
            if sub == 10:
                for k in self.counters:
                    self.counters[k] = 0
                return None if bc else bytes(pdu)
            if bc:
                return None
            key = {11: 'bus_message_count', 12: 'bus_communication_error_count',
                   13: 'bus_exception_error_count', 14: 'slave_message_count',
                   15: 'slave_no_response_count'}[sub]
            return bytes(pdu[:3]) + (self.counters[key] & 0xFFFF).to_bytes(2, 'big')

        if fc == 43:
            return self.fc43(pdu, bc)

        return exc(1)

    def fc43(self, pdu, bc):
        if len(pdu) < 2:
            return None
        if pdu[1] != 0x0D:
            return bytes((0xAB, 0x01))
        table = len(pdu) >= 5 and pdu[3] == 0x00     # DECISIONS M9
        hdr = 12 if table else 11
        if len(pdu) < hdr:
            return None
        ctrl = pdu[2]
        p = 4 if table else 3
        node = pdu[p]
        index = int.from_bytes(pdu[p + 1:p + 3], 'big')
        sub = pdu[p + 3]
        offset = int.from_bytes(pdu[p + 4:p + 6], 'big')
        n = int.from_bytes(pdu[p + 6:p + 8], 'big')
        data = pdu[hdr:]
        write = bool(ctrl & 0x80)
        if n > 4:
            return bytes((0xAB, 0x03))
        if (write and len(data) != n) or (not write and data):
            return bytes((0xAB, 0x03))
        if node != self.address:
            return None if bc else bytes((0xAB, 0x02))
        if bc and not write:
            return None
        header = bytes(pdu[:p + 6])

        def sdo(code):
            return bytes((0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE)) + code.to_bytes(4, 'little')

        def answer(value, size):
            return header + size.to_bytes(2, 'big') + (value & ((1 << (8 * size)) - 1)).to_bytes(size, 'little')

        if ctrl & 0x7F:
            return sdo(SDO_CMD)
        obj = self.objects.get(index)
        if obj is None:
            return sdo(SDO_NO_OBJECT)
        name, size, signed, get, setter = obj
        if sub != 0:
            return sdo(SDO_NO_SUBINDEX)
        if offset != 0:
            return sdo(SDO_UNSUPPORTED)
        if not write:
            if n not in (0, size):
                return sdo(SDO_TOO_LONG if n > size else SDO_TOO_SHORT)
            return answer(get(), size)
        if setter is None:
            return sdo(SDO_READ_ONLY)
        if n != size:
            return sdo(SDO_TOO_LONG if n > size else SDO_TOO_SHORT)
        v = int.from_bytes(data, 'little', signed=signed)
        setter(v)
        if bc:
            return None
        return answer(get(), size)


# -------------------------------------------------------------- framing ---

def expected_len(buf):
    """Total RTU frame length implied by the header, or None (unknown/need more)."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (3, 4, 6, 8):
        return 8
    if fc == 16:
        return 9 + buf[6] if len(buf) >= 7 else None
    if fc == 23:
        return 13 + buf[10] if len(buf) >= 11 else None
    if fc == 43:
        if len(buf) < 5 or buf[2] != 0x0D:
            return None
        table = buf[4] == 0
        hdr = 12 if table else 11
        if not buf[3] & 0x80:
            return 1 + hdr + 2
        if len(buf) < 1 + hdr:
            return None
        cpos = 1 + hdr - 2
        return 1 + hdr + int.from_bytes(buf[cpos:cpos + 2], 'big') + 2
    return None


class Framer:
    MAX_ADU = 256

    def __init__(self, drive, send, silence, overflow):
        self.drive = drive
        self.send = send
        self.silence = silence
        self.overflow = overflow
        self.buf = bytearray()
        self.timer = None
        self.loop = asyncio.get_running_loop()

    def feed(self, data):
        self.buf += data
        if self.timer:
            self.timer.cancel()
            self.timer = None
        while len(self.buf) >= 4:
            L = expected_len(self.buf)
            if L is None or L > len(self.buf) or not crc_ok(self.buf[:L]):
                break
            frame = bytes(self.buf[:L])
            del self.buf[:L]
            self._handle(frame)
        if len(self.buf) > self.MAX_ADU:
            self.drive.counters['bus_communication_error_count'] += 1
            self.buf.clear()
            self.overflow()
            return
        if self.buf:
            self.timer = self.loop.call_later(self.silence, self._flush)

    def _flush(self):
        self.timer = None
        frame = bytes(self.buf)
        self.buf.clear()
        if frame:
            self._handle(frame)

    def _handle(self, frame):
        resp = self.drive.handle_frame(frame)
        if resp:
            self.send(resp)

    def close(self):
        if self.timer:
            self.timer.cancel()
            self.timer = None


# ------------------------------------------------------------ transports --

async def serve_tcp(drive, host, port):
    async def client(reader, writer):
        closed = []

        def overflow():
            closed.append(True)            # DECISIONS U15
            writer.close()

        fr = Framer(drive, writer.write, 0.025, overflow)
        try:
            while not closed:
                data = await reader.read(1024)
                if not data:
                    break
                fr.feed(data)
                if not closed:
                    await writer.drain()
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            fr.close()
            try:
                writer.close()
            except Exception:
                pass

    server = await asyncio.start_server(client, host, port)
    return server


BAUDS = {9600: 'B9600', 14400: None, 19200: 'B19200', 28800: None,
         38400: 'B38400', 57600: 'B57600', 115200: 'B115200'}


def open_serial(dev, baud, parity):
    import termios
    import tty
    fd = os.open(dev, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    attrs = termios.tcgetattr(fd)
    cflag = attrs[2]
    cflag &= ~(termios.PARENB | termios.PARODD | termios.CSTOPB | termios.CSIZE)
    cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
    if parity == 'even':
        cflag |= termios.PARENB
    elif parity == 'odd':
        cflag |= termios.PARENB | termios.PARODD
    attrs[2] = cflag
    const = BAUDS.get(baud)
    if const and hasattr(termios, const):
        attrs[4] = attrs[5] = getattr(termios, const)
    attrs[6][termios.VMIN] = 0
    attrs[6][termios.VTIME] = 0
    try:
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
    except termios.error:
        pass
    return fd


def serve_serial(drive, dev, baud, parity):
    loop = asyncio.get_running_loop()
    fd = open_serial(dev, baud, parity)
    t35 = 1.75e-3 if baud > 19200 else 3.5 * 11 / baud
    silence = max(t35, 0.004)     # floor against scheduler jitter (DECISIONS S8)

    def send(data):
        try:
            os.write(fd, data)
        except OSError:
            pass

    fr = Framer(drive, send, silence, lambda: None)

    def readable():
        try:
            data = os.read(fd, 512)
        except BlockingIOError:
            return
        except OSError:
            loop.remove_reader(fd)
            loop.call_later(0.5, lambda: loop.add_reader(fd, readable))
            return
        if data:
            fr.feed(data)

    loop.add_reader(fd, readable)
    return fd


# ------------------------------------------------------------------ main --

def write_state(drive, path):
    if not path:
        return
    tmp = path + '.tmp'
    try:
        with open(tmp, 'w') as f:
            json.dump(drive.dump(), f, indent=1, sort_keys=True)
        os.replace(tmp, path)
    except OSError as e:
        print('state write failed: %s' % e, file=sys.stderr)


async def main_async(args):
    loop = asyncio.get_running_loop()
    drive = Drive(args.address, args.baud, args.parity)
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, lambda: write_state(drive, args.state))
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)

    server = None
    if args.listen:
        host, _, port = args.listen.rpartition(':')
        server = await serve_tcp(drive, host, int(port))
        p = server.sockets[0].getsockname()[1]
        print('listening tcp %s:%d' % (host, p), flush=True)
    if args.serial:
        serve_serial(drive, args.serial, args.baud, args.parity)
        print('listening serial %s' % args.serial, flush=True)

    async def ticker():
        while True:
            await asyncio.sleep(0.01)
            drive.update()
    tick = asyncio.create_task(ticker())
    await stop.wait()
    tick.cancel()
    write_state(drive, args.state)
    if server:
        server.close()


def main():
    ap = argparse.ArgumentParser(description='SIEB & MEYER SD2x Modbus RTU simulator')
    ap.add_argument('--listen', help='HOST:PORT for RTU over TCP (loopback)')
    ap.add_argument('--serial', help='serial device / pty')
    ap.add_argument('--baud', type=int, default=19200, choices=sorted(BAUDS))
    ap.add_argument('--parity', default='none', choices=('none', 'even', 'odd'))
    ap.add_argument('--address', type=int, default=1)
    ap.add_argument('--state', help='JSON state file')
    args = ap.parse_args()
    if not args.listen and not args.serial:
        ap.error('need --listen or --serial')
    if not 1 <= args.address <= 254:
        ap.error('--address must be 1..254')
    try:
        asyncio.run(main_async(args))
    except KeyboardInterrupt:
        pass
    os._exit(0)


if __name__ == '__main__':
    main()
