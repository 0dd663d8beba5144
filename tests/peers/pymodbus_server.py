#!/usr/bin/env python3
"""A pymodbus (3.x) server shaped like the harness's generic profile (corpus/profiles/generic.toml), as a
third-party target for `modbus-harness run --profile generic`.

    pymodbus_server.py tcp [HOST] [PORT]                 Modbus/TCP; PORT 0 (default): any free port
    pymodbus_server.py rtu DEVICE [BAUD] [PARITY] [STOP] RTU on a serial line or pty (default 19200 N 1)

Prints one line once it serves, `listening tcp HOST:PORT` or `listening serial DEVICE`, and stops cleanly on
SIGTERM or SIGINT (exit 0).

The data model is the generic profile's, configured through pymodbus' own SimDevice API, not patched:
100 coils, 100 discrete inputs, 100 holding registers and 100 input registers at 0-99; coils, discrete inputs
and holding registers 0 at start, input register n holds n; the identification objects of the profile.
Modbus/TCP answers any unit id (device id 0 is pymodbus' "every id"); RTU answers slave address 1 and takes
address 0 as a broadcast (other addresses: pymodbus' ignore_missing_devices). pymodbus stores bits 16 to a
register, so it would serve coils and discrete inputs 100-111 as well, and its `action` hook is told the count
of 16-bit words, not of bits: a thin wrapper around the server's datastore answers exception 02 for a bit
access that reaches 100 or beyond, as the profile's map says. Nothing else is changed: framing, validation,
exceptions and every other answer are pymodbus' own.
"""

import asyncio
import logging
import signal
import sys

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.pdu.device import ModbusDeviceIdentification
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

#: Map size of the generic profile: every table holds addresses 0..SIZE-1.
SIZE = 100


#: Function codes that address the bit tables (coils, discrete inputs).
BIT_FUNCTIONS = (1, 2, 5, 15)


class BoundedBits:
    """The server's datastore, with the bit tables ending at SIZE as the profile's do (pymodbus pads them
    to a multiple of 16 bits). Register tables are exact already; everything else is passed through."""

    def __init__(self, inner):
        self.inner = inner

    def device_ids(self):
        return self.inner.device_ids()

    async def async_getValues(self, device_id, func_code, address, count=1):
        if func_code in BIT_FUNCTIONS and address + count > SIZE:
            return ExcCodes.ILLEGAL_ADDRESS
        return await self.inner.async_getValues(device_id, func_code, address, count)

    async def async_setValues(self, device_id, func_code, address, values):
        if func_code in BIT_FUNCTIONS and address + len(values) > SIZE:
            return ExcCodes.ILLEGAL_ADDRESS
        return await self.inner.async_setValues(device_id, func_code, address, values)


def device(dev_id):
    """The generic profile's data model as a pymodbus device answering `dev_id` (0: any id)."""
    coils = [SimData(0, values=[False] * SIZE, datatype=DataType.BITS)]
    discrete = [SimData(0, values=[False] * SIZE, datatype=DataType.BITS, readonly=True)]
    holding = [SimData(0, count=SIZE, values=0, datatype=DataType.REGISTERS)]
    inputs = [SimData(0, values=list(range(SIZE)), datatype=DataType.REGISTERS, readonly=True)]
    return SimDevice(id=dev_id, simdata=(coils, discrete, holding, inputs))


def identity():
    """The generic profile's identification objects (FC 2B/0E)."""
    ident = ModbusDeviceIdentification(
        info_name={
            "VendorName": "modbus-harness",
            "ProductCode": "GENERIC",
            "MajorMinorRevision": "1.0",
            "ProductName": "Generic Modbus server",
            "ModelName": "simulator",
        }
    )
    return ident


def tcp_listening(server):
    """The line a Modbus/TCP server prints once it serves: `listening tcp HOST:PORT`."""
    host, port = server.transport.sockets[0].getsockname()[:2]
    return f"listening tcp {host}:{port}"


async def serve_until_signalled(server, listening):
    """Serve with `server` (a pymodbus server) until SIGTERM or SIGINT, then shut it down (returns 0).
    `listening(server)` is the line printed once it serves. bench/pymodbus_peers.py's server uses it too."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await server.serve_forever(background=True)
    print(listening(server), flush=True)
    await stop.wait()
    await server.shutdown()
    return 0


def usage():
    print(__doc__, file=sys.stderr)
    return 2


async def serve(argv):
    if len(argv) >= 2 and argv[1] == "tcp":
        host = argv[2] if len(argv) > 2 else "127.0.0.1"
        port = int(argv[3]) if len(argv) > 3 else 0
        server = ModbusTcpServer(
            device(0),
            framer=FramerType.SOCKET,
            identity=identity(),
            address=(host, port),
        )
    elif len(argv) >= 3 and argv[1] == "rtu":
        server = ModbusSerialServer(
            device(1),
            framer=FramerType.RTU,
            identity=identity(),
            port=argv[2],
            baudrate=int(argv[3]) if len(argv) > 3 else 19200,
            parity=(argv[4] if len(argv) > 4 else "N")[0].upper(),
            stopbits=int(argv[5]) if len(argv) > 5 else 1,
            bytesize=8,
            broadcast_enable=True,
            ignore_missing_devices=True,
        )
    else:
        return usage()

    server.context = BoundedBits(server.context)
    if argv[1] == "tcp":
        return await serve_until_signalled(server, tcp_listening)
    return await serve_until_signalled(server, lambda _: f"listening serial {argv[2]}")


def main(argv):
    # pymodbus warns on stderr about its v4 API; keep real errors only.
    logging.getLogger("pymodbus").setLevel(logging.ERROR)
    try:
        return asyncio.run(serve(argv))
    except (OSError, RuntimeError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
