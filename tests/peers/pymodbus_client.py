#!/usr/bin/env python3
"""A pymodbus (3.x) client for the interop tests: one connection, a list of operations, one output line each.

    pymodbus_client.py tcp HOST PORT UNIT OP...
    pymodbus_client.py rtutcp HOST PORT UNIT OP...     RTU frames inside TCP (pymodbus' RTU framer on a socket)
    pymodbus_client.py rtu DEVICE BAUD PARITY(N|E|O) STOP UNIT OP...

OP is one argument, fields separated by ':' (values decimal or 0x hex), the same as libmodbus_client.c:
    rh:ADDR:N  ri:ADDR:N  wr:ADDR:V  wh:ADDR:V,V...  rc:ADDR:N  wc:ADDR:B  wm:ADDR:B,B...
A Modbus exception prints "exception N" and the run goes on; any other error prints "error: ..." and exits 1.
"""

import sys

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ExceptionResponse


def num(s):
    return int(s, 0)


def values(s):
    return [num(v) for v in s.split(",") if v]


def run_op(client, unit, op):
    kind, addr, rest = op.split(":", 2)
    addr = num(addr)
    calls = {
        "rh": lambda: client.read_holding_registers(addr, count=num(rest), device_id=unit),
        "ri": lambda: client.read_input_registers(addr, count=num(rest), device_id=unit),
        "rc": lambda: client.read_coils(addr, count=num(rest), device_id=unit),
        "wr": lambda: client.write_register(addr, num(rest), device_id=unit),
        "wh": lambda: client.write_registers(addr, values(rest), device_id=unit),
        "wc": lambda: client.write_coil(addr, bool(num(rest)), device_id=unit),
        "wm": lambda: client.write_coils(addr, [bool(v) for v in values(rest)], device_id=unit),
    }
    if kind not in calls:
        print(f"error: unknown op {op}")
        return False
    rr = calls[kind]()
    if isinstance(rr, ExceptionResponse):
        print(f"exception {rr.exception_code}")
        return True
    if rr.isError():
        print(f"error: {op}: {rr}")
        return False
    if kind in ("rh", "ri"):
        print(" ".join(str(v) for v in rr.registers))
    elif kind == "rc":
        # pymodbus pads bits to a whole byte: keep the ones asked for.
        print(" ".join(str(int(b)) for b in rr.bits[: num(rest)]))
    else:
        print("ok")
    return True


def main(argv):
    if len(argv) >= 5 and argv[1] == "tcp":
        client = ModbusTcpClient(argv[2], port=num(argv[3]), timeout=2, retries=0)
        unit, first = num(argv[4]), 5
    elif len(argv) >= 5 and argv[1] == "rtutcp":
        client = ModbusTcpClient(
            argv[2], port=num(argv[3]), framer=FramerType.RTU, timeout=2, retries=0
        )
        unit, first = num(argv[4]), 5
    elif len(argv) >= 7 and argv[1] == "rtu":
        client = ModbusSerialClient(
            argv[2],
            baudrate=num(argv[3]),
            parity=argv[4][0].upper(),
            stopbits=num(argv[5]),
            bytesize=8,
            timeout=2,
            retries=0,
        )
        unit, first = num(argv[6]), 7
    else:
        print(__doc__, file=sys.stderr)
        return 2
    if not client.connect():
        print("error: connect failed")
        return 1
    try:
        for op in argv[first:]:
            if not run_op(client, unit, op):
                return 1
    except ModbusException as e:
        print(f"error: {e}")
        return 1
    finally:
        sys.stdout.flush()
        client.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
