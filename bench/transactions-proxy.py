#!/usr/bin/env python3
"""A Modbus/TCP server with a few transactions, in front of a Modbus/TCP server on loopback.

    transactions-proxy.py UPSTREAM_HOST:PORT --transactions N [--lifetime S]

Listens on 127.0.0.1, port 0, prints `listening tcp 127.0.0.1:PORT`, and relays each connection to UPSTREAM
(a loopback address). Of the requests that arrive together (in one read from the socket), the first N go to
UPSTREAM and are answered by it; each one after them is answered by this server with exception 06, Server
Busy, as the TCP implementation guide has a server do when it has no transaction left (4.4.2.2; its
NumberMaxOfServerTransaction "may have a value from 1 to 16", 4.4.2.1). The answers go back in the order of
the requests. A request is cut by its MBAP length. Ends by itself after --lifetime seconds (default 900).
Standard library only.
"""

import argparse
import asyncio
import ipaddress
import struct
import sys

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("upstream")
ap.add_argument("--transactions", type=int, required=True)
ap.add_argument("--lifetime", type=float, default=900.0, help="seconds")
args = ap.parse_args()
up_host, up_port = args.upstream.rsplit(":", 1)
if not ipaddress.ip_address(up_host).is_loopback:
    sys.exit(f"transactions-proxy.py: {up_host} is not a loopback address")
if not 1 <= args.transactions <= 16:
    sys.exit("transactions-proxy.py: --transactions is 1 to 16 (TCP guide 4.4.2.1)")


def adus(buf):
    """Whole ADUs at the front of `buf` (by MBAP length) and the bytes left."""
    out = []
    while len(buf) >= 7:
        n = 6 + struct.unpack(">H", buf[4:6])[0]
        if len(buf) < n:
            break
        out.append(bytes(buf[:n]))
        buf = buf[n:]
    return out, buf


async def read_adu(reader):
    head = await reader.readexactly(6)
    n = struct.unpack(">H", head[4:6])[0]
    return head + await reader.readexactly(n)


async def handle(client_r, client_w):
    try:
        server_r, server_w = await asyncio.open_connection(up_host, int(up_port))
    except OSError:
        client_w.close()
        return
    buf = b""
    try:
        while True:
            data = await client_r.read(4096)
            if not data:
                break
            whole, buf = adus(buf + data)
            served, refused = whole[: args.transactions], whole[args.transactions :]
            for adu in served:
                server_w.write(adu)
            await server_w.drain()
            for _ in served:
                client_w.write(await asyncio.wait_for(read_adu(server_r), 5))
            for adu in refused:
                tid, unit, fc = adu[0:2], adu[6], adu[7] if len(adu) > 7 else 0
                client_w.write(tid + b"\x00\x00\x00\x03" + bytes([unit, (fc | 0x80) & 0xFF, 0x06]))
            await client_w.drain()
    except (ConnectionError, OSError, asyncio.IncompleteReadError, asyncio.TimeoutError):
        pass
    server_w.close()
    client_w.close()


async def main():
    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    print(f"listening tcp 127.0.0.1:{port}", flush=True)
    async with server:
        await asyncio.sleep(args.lifetime)


asyncio.run(main())
