#!/usr/bin/env python3
"""A Modbus/TCP-to-RTU gateway on loopback, in front of an RTU-over-TCP drive.

    gateway.py UPSTREAM_HOST:PORT [--timeout MS] [--on-timeout exception|silence] [--units FIRST-LAST]
               [--broadcast silence|exception] [--turnaround MS] [--lifetime S]

A user reaches an RTU drive (the SD2x) over Modbus/TCP through such a gateway: it takes MBAP requests on
127.0.0.1 (port 0; prints `listening tcp 127.0.0.1:PORT`), sends each as an RTU frame (unit id as the slave
address, CRC added) on one upstream RTU-over-TCP connection, one request at a time, and answers with the
drive's reply in an MBAP frame. Where the drive stays silent it does what gateways do (MODBUS Application
Protocol V1.1b3, section 7):
  --on-timeout exception  (default) answers exception 0B, Gateway Target Device Failed to Respond, after
                          --timeout MS (default 100) without a reply;
  --on-timeout silence    answers nothing, as a gateway that leaves the timeout to its client.
A unit id outside --units (default 1-247, the serial line's unicast addresses) has no path: exception 0A,
Gateway Path Unavailable, at once. Unit id 0 is a broadcast: sent, then --turnaround MS (default 20) of
quiet, and no answer (--broadcast exception: 0B after it, as some gateways do). A request with a protocol id
other than 0 is discarded (MBAP checks, TCP guide 4.4.2.2); an MBAP length below 2 or above 254 closes the
connection (no RTU frame can carry it). Pipelined requests are served in order. A stats line goes to stderr
when it ends: requests, replies relayed, 0A, 0B, broadcasts, discarded. Ends by itself after --lifetime
seconds (default 900). Standard library only; loopback only.
"""
import argparse
import asyncio
import signal
import struct
import sys

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("upstream")
ap.add_argument("--timeout", type=float, default=200.0, help="milliseconds")
ap.add_argument("--on-timeout", choices=["exception", "silence"], default="exception")
ap.add_argument("--units", default="1-247")
ap.add_argument("--broadcast", choices=["silence", "exception"], default="silence")
ap.add_argument("--turnaround", type=float, default=20.0, help="milliseconds")
ap.add_argument("--lifetime", type=float, default=900.0, help="seconds")
args = ap.parse_args()
up_host, up_port = args.upstream.rsplit(":", 1)
if up_host not in ("127.0.0.1", "localhost", "::1") and not up_host.startswith("127."):
    sys.exit("gateway: the upstream must be on loopback")
first, _, last = args.units.partition("-")
routed = range(int(first), int(last or first) + 1)

stats = dict(requests=0, relayed=0, path_unavailable=0, no_response=0, broadcasts=0, discarded=0)


def crc16(data):
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return struct.pack("<H", crc)


class Line:
    """The RTU side: one connection to the drive, one transaction at a time."""

    def __init__(self):
        self.lock = asyncio.Lock()
        self.r = self.w = None

    async def open(self):
        if self.w is None or self.w.is_closing():
            self.r, self.w = await asyncio.open_connection(up_host, int(up_port))

    async def transact(self, unit, pdu, answer):
        """Send one frame; the drive's reply PDU, or None (nothing, or nothing valid, in time)."""
        async with self.lock:
            await self.open()
            # A reply that came after its request's timeout is not this request's.
            while True:
                try:
                    stale = await asyncio.wait_for(self.r.read(4096), 0.0005)
                except asyncio.TimeoutError:
                    break
                if not stale:
                    self.w = None
                    await self.open()
                    break
            self.w.write(bytes([unit]) + pdu + crc16(bytes([unit]) + pdu))
            await self.w.drain()
            if not answer:
                await asyncio.sleep(args.turnaround / 1000)
                return None
            loop = asyncio.get_running_loop()
            deadline = loop.time() + args.timeout / 1000
            buf = b""
            while True:
                left = deadline - loop.time() if not buf else 0.005
                if left <= 0:
                    break
                try:
                    d = await asyncio.wait_for(self.r.read(4096), left)
                except asyncio.TimeoutError:
                    break
                if not d:
                    self.w = None
                    break
                buf += d
            if len(buf) < 4 or buf[0] != unit or crc16(buf[:-2]) != buf[-2:]:
                return None
            return buf[1:-2]


line = Line()


async def client(r, w):
    try:
        while True:
            head = await r.readexactly(7)
            tid, pid, length, unit = struct.unpack(">HHHB", head)
            if length < 2 or length > 254:
                break
            pdu = await r.readexactly(length - 1)
            stats["requests"] += 1
            if pid != 0:
                stats["discarded"] += 1
                continue
            fc = pdu[0]
            reply = None
            if unit == 0:
                stats["broadcasts"] += 1
                await line.transact(0, pdu, answer=False)
                if args.broadcast == "exception":
                    reply = bytes([fc | 0x80, 0x0B])
            elif unit not in routed:
                stats["path_unavailable"] += 1
                reply = bytes([fc | 0x80, 0x0A])
            else:
                reply = await line.transact(unit, pdu, answer=True)
                if reply is not None:
                    stats["relayed"] += 1
                elif args.on_timeout == "exception":
                    stats["no_response"] += 1
                    reply = bytes([fc | 0x80, 0x0B])
            if reply is not None:
                w.write(struct.pack(">HHHB", tid, 0, len(reply) + 1, unit) + reply)
                await w.drain()
    except (asyncio.IncompleteReadError, ConnectionError):
        pass
    finally:
        w.close()


async def main():
    server = await asyncio.start_server(client, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    print(f"listening tcp 127.0.0.1:{port}", flush=True)
    done = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        asyncio.get_running_loop().add_signal_handler(sig, done.set)
    try:
        await asyncio.wait_for(done.wait(), args.lifetime)
    except asyncio.TimeoutError:
        pass
    finally:
        print("stats " + " ".join(f"{k}={v}" for k, v in stats.items()), file=sys.stderr, flush=True)


asyncio.run(main())
