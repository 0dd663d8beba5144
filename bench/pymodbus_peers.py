#!/usr/bin/env python3
"""The pymodbus (3.x) benchmark peers of bench/run.sh.

    pymodbus_peers.py server PORT               Modbus/TCP server on 127.0.0.1 (PORT 0: any free port),
                                                100 holding registers at 0-99, any unit id
    pymodbus_peers.py client HOST PORT SECS     FC 03 reads of 2 registers at 0, unit 1, one at a time

The server prints `listening tcp 127.0.0.1:PORT` once it serves and stops on SIGTERM/SIGINT. The client
makes 200 warm-up requests, then reads for SECS seconds and prints the line the other peers print:
    RESULT requests=N seconds=S rps=R p50_us=P p99_us=Q
"""

import asyncio
import logging
import os
import sys
import time

WARMUP = 200


def report(lat, secs):
    lat.sort()
    n = len(lat)
    p50 = lat[(n - 1) * 50 // 100] / 1e3 if n else 0.0
    p99 = lat[(n - 1) * 99 // 100] / 1e3 if n else 0.0
    rps = n / secs if secs > 0 else 0.0
    print(f"RESULT requests={n} seconds={secs:.3f} rps={rps:.0f} p50_us={p50:.1f} p99_us={p99:.1f}", flush=True)


def client(host, port, secs):
    from pymodbus.client import ModbusTcpClient

    c = ModbusTcpClient(host, port=port, timeout=2, retries=0)
    if not c.connect():
        print("error: connect failed", file=sys.stderr)
        return 1

    def read():
        rr = c.read_holding_registers(0, count=2, device_id=1)
        if rr.isError() or len(rr.registers) != 2:
            raise RuntimeError(f"bad answer: {rr}")

    for _ in range(WARMUP):
        read()
    lat = []
    clock = time.perf_counter_ns
    start = t = clock()
    end = start + int(secs * 1e9)
    while t < end:
        read()
        t2 = clock()
        lat.append(t2 - t)
        t = t2
    report(lat, (t - start) / 1e9)
    c.close()
    return 0


async def server(port):
    from pymodbus import FramerType
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    # The generic profile's tables (the simulator's --profile generic): 100 of each at 0-99, 0 at start.
    coils = [SimData(0, values=[False] * 100, datatype=DataType.BITS)]
    discrete = [SimData(0, values=[False] * 100, datatype=DataType.BITS, readonly=True)]
    holding = [SimData(0, count=100, values=0, datatype=DataType.REGISTERS)]
    inputs = [SimData(0, count=100, values=0, datatype=DataType.REGISTERS, readonly=True)]
    # device id 0: pymodbus answers every unit id, as the simulator and the libmodbus server do on TCP.
    dev = SimDevice(id=0, simdata=(coils, discrete, holding, inputs))
    srv = ModbusTcpServer(dev, framer=FramerType.SOCKET, address=("127.0.0.1", port))
    # The serving loop of the interop tests' pymodbus peer (tests/peers/pymodbus_server.py).
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "peers"))
    from pymodbus_server import serve_until_signalled, tcp_listening

    return await serve_until_signalled(srv, tcp_listening)


def main(argv):
    logging.getLogger("pymodbus").setLevel(logging.ERROR)
    if len(argv) == 3 and argv[1] == "server":
        return asyncio.run(server(int(argv[2])))
    if len(argv) == 5 and argv[1] == "client":
        return client(argv[2], int(argv[3]), float(argv[4]))
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv))
