#!/usr/bin/env python3
"""A TCP proxy on loopback that delays every chunk by a fixed one-way latency, in both directions.

    bench/delay-proxy.py --to HOST:PORT --delay-ms MS

Listens on 127.0.0.1 (any free port), prints `listening 127.0.0.1:PORT`, and relays each connection to
HOST:PORT (which must be a loopback address). Each chunk read is written to the other side MS ms after it
was read, in order; chunks read while earlier ones wait are delayed by MS too, not queued behind them, so
the proxy behaves like a wire with a fixed latency and enough bandwidth: requests in flight together
overlap their latency, as they would between a test bench and a drive on a network. The machine has no
netem (`tc qdisc ... netem` reports the qdisc kind unknown), hence a proxy.
"""

import argparse
import asyncio
import ipaddress
import sys
import time


async def pipe(reader, writer, delay):
    queue = asyncio.Queue()

    async def deliver():
        while True:
            due, data = await queue.get()
            if data is None:
                break
            wait = due - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            writer.write(data)
            await writer.drain()
        if writer.can_write_eof():
            writer.write_eof()

    task = asyncio.create_task(deliver())
    try:
        while True:
            data = await reader.read(65536)
            if not data:
                break
            queue.put_nowait((time.monotonic() + delay, data))
    except (ConnectionError, OSError):
        pass
    queue.put_nowait((0, None))
    try:
        await task
    except (ConnectionError, OSError):
        pass


async def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--to", required=True, help="HOST:PORT to relay to (loopback only)")
    ap.add_argument("--delay-ms", type=float, required=True, help="one-way delay in milliseconds")
    args = ap.parse_args()
    host, port = args.to.rsplit(":", 1)
    if not ipaddress.ip_address(host).is_loopback:
        sys.exit(f"delay-proxy.py: {host} is not a loopback address")
    delay = args.delay_ms / 1000.0

    async def handle(client_r, client_w):
        try:
            server_r, server_w = await asyncio.open_connection(host, int(port))
        except OSError as e:
            print(f"delay-proxy.py: cannot connect to {args.to}: {e}", file=sys.stderr)
            client_w.close()
            return
        for w in (client_w, server_w):
            sock = w.get_extra_info("socket")
            if sock is not None:
                import socket

                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        await asyncio.gather(pipe(client_r, server_w, delay), pipe(server_r, client_w, delay))
        for w in (client_w, server_w):
            w.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    print(f"listening {server.sockets[0].getsockname()[0]}:{server.sockets[0].getsockname()[1]}", flush=True)
    async with server:
        await server.serve_forever()


if __name__ == "__main__":
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
