#!/usr/bin/env python3
"""A multi-drop RS-485 line on loopback: several RTU-over-TCP drives (drops) on one line, one master.

    line.py DROP_HOST:PORT [DROP_HOST:PORT ...] [--hear-replies on|off] [--gap MS] [--lifetime S]

A drive on a machine shares its RS-485 line with other devices: every byte the master sends reaches every
device, and a device's reply is on the line for every other device to hear (MODBUS over Serial Line V1.02,
sections 2.1 and 3.3: one master, up to 247 slaves, a two-wire bus). This joins one RTU-over-TCP connection
to each drop (say `simulate --rtu-over-tcp 127.0.0.1:0 --unit N`, one per address) into such a line, and
serves the master over RTU over TCP on 127.0.0.1 (port 0; prints `listening tcp 127.0.0.1:PORT`): what the
master sends is copied to every drop as it comes, what a drop sends goes to the master and, with
`--hear-replies on` (the default, as on a real line), to every other drop. The master's bytes go on the line
--gap MS (default 2, 3.5 characters at 19200 baud) after the line's last byte at the earliest, as a serial
device server keeps the silence that separates frames (spec 2.5.1.1): without it a drop would hear another's
reply and the next request as one frame. Two drops answering at once both
reach the master, their bytes interleaved as they come (a collision, garbage to the master). A new master
connection replaces the one before; the drops' connections stay. A stats line goes to stderr when it ends: bytes
from the master, bytes from each drop. Ends by itself after --lifetime seconds (default 900). Standard
library only; loopback only.
"""
import argparse
import asyncio
import signal
import sys

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("drops", nargs="+")
ap.add_argument("--hear-replies", choices=["on", "off"], default="on")
ap.add_argument("--gap", type=float, default=2.0, help="milliseconds")
ap.add_argument("--lifetime", type=float, default=900.0, help="seconds")
args = ap.parse_args()
for d in args.drops:
    host = d.rsplit(":", 1)[0]
    if host not in ("127.0.0.1", "localhost", "::1") and not host.startswith("127."):
        sys.exit("line: every drop must be on loopback")

stats = {"master": 0}
drops = []  # (reader, writer, name)
master = {"w": None}
line = {"last": 0.0}


async def pump_drop(i, r, name):
    while True:
        d = await r.read(4096)
        if not d:
            print(f"line: drop {name} closed its connection", file=sys.stderr)
            return
        stats[name] = stats.get(name, 0) + len(d)
        line["last"] = asyncio.get_running_loop().time()
        w = master["w"]
        if w is not None and not w.is_closing():
            w.write(d)
        if args.hear_replies == "on":
            for j, (_, dw, _) in enumerate(drops):
                if j != i:
                    dw.write(d)


async def on_master(r, w):
    old = master["w"]
    if old is not None and not old.is_closing():
        # One master on a line: a new connection replaces the old one (as a device server does).
        old.close()
    master["w"] = w
    try:
        while True:
            d = await r.read(4096)
            if not d:
                break
            stats["master"] += len(d)
            loop = asyncio.get_running_loop()
            wait = line["last"] + args.gap / 1000 - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)
            line["last"] = loop.time()
            for _, dw, _ in drops:
                dw.write(d)
    except ConnectionError:
        pass
    finally:
        if master["w"] is w:
            master["w"] = None
        w.close()


async def main():
    for d in args.drops:
        host, port = d.rsplit(":", 1)
        r, w = await asyncio.open_connection(host, int(port))
        drops.append((r, w, d))
    for i, (r, _, name) in enumerate(drops):
        asyncio.ensure_future(pump_drop(i, r, name))
    server = await asyncio.start_server(on_master, "127.0.0.1", 0)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for s in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(s, stop.set)
    port = server.sockets[0].getsockname()[1]
    print(f"listening tcp 127.0.0.1:{port}", flush=True)
    try:
        await asyncio.wait_for(stop.wait(), args.lifetime)
    except asyncio.TimeoutError:
        pass
    print("line: stats " + " ".join(f"{k}={v}" for k, v in stats.items()), file=sys.stderr, flush=True)


asyncio.run(main())
