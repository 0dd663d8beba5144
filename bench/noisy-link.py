#!/usr/bin/env python3
"""An imperfect link in front of a drive on loopback: a noisy RS-485 line, or a Modbus/TCP link with bad moments.

    noisy-link.py UPSTREAM_HOST:PORT --mode rtu|tcp [--rate R] [--seed N] [--outage-ms MS] [--lose-first N]
                  [--lose-after-unanswered N] [--lifetime S]

Listens on 127.0.0.1, port 0, prints `listening tcp 127.0.0.1:PORT`, and relays each connection to UPSTREAM
(a loopback address). Deterministic from --seed (default 1). Every event is one line on stderr.

--mode rtu (UPSTREAM serves RTU over TCP): each chunk that passes, in either direction (on loopback a chunk
is one frame, or one piece of a frame a client sends in pieces), is damaged with probability R/1000
(default 20): one bit flipped, one byte lost, a stray 0x00 or 0xFF before it (a transmitter switching on),
or cut short. A damaged request reaches the drive damaged (a conforming slave stays silent); a damaged
answer reaches the client damaged (the drive did execute the request). With --lose-first N the first N
request chunks (client to drive, counted over all connections) are lost on the line whatever the rate: the
drive never hears them. With --lose-after-unanswered N the first N request chunks that come at least 200 ms
after a request chunk the drive did not answer are lost (what follows a silence first: a liveness probe), and
so are N in a row.

--mode tcp (UPSTREAM serves Modbus/TCP): each request chunk from the client is, with probability R/1000
(default 10), the moment of a link event: `lost` (the request is dropped and the connection reset),
`answer-lost` (the request reaches the drive, its answer is dropped and the connection reset), or `outage`
(the request is dropped, the connection stays silent for --outage-ms, default 800, then is reset; connects
during the outage are accepted and reset at once). The drive's state is never touched by the link.

Ends by itself after --lifetime seconds (default 900). Standard library only.
"""

import argparse
import asyncio
import ipaddress
import random
import socket
import struct
import sys
import time

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("upstream")
ap.add_argument("--mode", choices=["rtu", "tcp"], required=True)
ap.add_argument("--rate", type=float, default=None, help="events per 1000 chunks (rtu: 20, tcp: 10)")
ap.add_argument("--seed", type=int, default=1)
ap.add_argument("--outage-ms", type=float, default=800.0)
ap.add_argument("--lose-first", type=int, default=0, help="rtu: the first N request chunks are lost")
ap.add_argument(
    "--lose-after-unanswered",
    type=int,
    default=0,
    help="rtu: the first N request chunks that come 200 ms or more after an unanswered one are lost",
)
ap.add_argument("--lifetime", type=float, default=900.0, help="seconds")
args = ap.parse_args()
up_host, up_port = args.upstream.rsplit(":", 1)
if not ipaddress.ip_address(up_host).is_loopback:
    sys.exit(f"noisy-link.py: {up_host} is not a loopback address")
rate = (args.rate if args.rate is not None else (20.0 if args.mode == "rtu" else 10.0)) / 1000.0
rng = random.Random(args.seed)
outage_until = 0.0
started = time.monotonic()
events = 0
lose_left = args.lose_first
lose_after_left = args.lose_after_unanswered
# The time of the last request chunk the drive has not answered yet (None: answered, or none yet).
unanswered_since = None


def say(what):
    print(f"noisy-link: {time.monotonic() - started:8.3f} s {what}", file=sys.stderr, flush=True)


def damage(data, direction):
    """One kind of line noise applied to `data` (bytes); the damaged bytes and what was done."""
    kind = rng.choice(["flip", "lose", "stray", "cut"] if len(data) > 1 else ["flip", "stray"])
    b = bytearray(data)
    if kind == "flip":
        i = rng.randrange(len(b))
        bit = rng.randrange(8)
        b[i] ^= 1 << bit
        told = f"bit {bit} of byte {i} flipped"
    elif kind == "lose":
        i = rng.randrange(len(b))
        del b[i]
        told = f"byte {i} lost"
    elif kind == "stray":
        v = rng.choice([0x00, 0xFF])
        b.insert(0, v)
        told = f"a stray 0x{v:02X} before it"
    else:
        n = rng.randrange(1, len(b))
        del b[n:]
        told = f"cut after {n} of {len(data)} bytes"
    say(f"{direction}: {data.hex()} -> {bytes(b).hex()} ({told})")
    return bytes(b)


def reset(writer):
    sock = writer.get_extra_info("socket")
    if sock is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        except OSError:
            pass
    writer.close()


async def relay_rtu(src, dst, direction):
    try:
        while True:
            data = await src.read(4096)
            if not data:
                break
            global lose_left, lose_after_left, unanswered_since
            if direction == "answer":
                unanswered_since = None
            if direction == "request" and lose_left > 0:
                lose_left -= 1
                say(f"{direction}: {data.hex()} lost (--lose-first)")
                continue
            if direction == "request":
                now = time.monotonic()
                after_silence = unanswered_since is not None and now - unanswered_since >= 0.2
                if unanswered_since is None or after_silence:
                    unanswered_since = now
                if after_silence and lose_after_left > 0:
                    lose_after_left -= 1
                    say(f"{direction}: {data.hex()} lost (--lose-after-unanswered)")
                    continue
            if rng.random() < rate:
                global events
                events += 1
                data = damage(data, direction)
            dst.write(data)
            await dst.drain()
    except (ConnectionError, OSError):
        pass
    try:
        if dst.can_write_eof():
            dst.write_eof()
    except (ConnectionError, OSError):
        pass


async def handle(client_r, client_w):
    global outage_until, events
    peer = client_w.get_extra_info("peername")
    if time.monotonic() < outage_until:
        say(f"connect from {peer} during an outage: reset")
        reset(client_w)
        return
    try:
        server_r, server_w = await asyncio.open_connection(up_host, int(up_port))
    except OSError as e:
        say(f"cannot connect to {args.upstream}: {e}")
        reset(client_w)
        return
    for w in (client_w, server_w):
        s = w.get_extra_info("socket")
        if s is not None:
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    if args.mode == "rtu":
        await asyncio.gather(
            relay_rtu(client_r, server_w, "request"), relay_rtu(server_r, client_w, "answer")
        )
        for w in (client_w, server_w):
            w.close()
        return
    # Modbus/TCP: answers are relayed as they come; a request may be the moment of a link event.
    drop_answers = asyncio.Event()

    async def answers():
        try:
            while True:
                data = await server_r.read(4096)
                if not data or drop_answers.is_set():
                    break
                client_w.write(data)
                await client_w.drain()
        except (ConnectionError, OSError):
            pass

    task = asyncio.create_task(answers())
    try:
        while True:
            data = await client_r.read(4096)
            if not data:
                break
            if rng.random() < rate:
                events += 1
                kind = rng.choice(["lost", "answer-lost", "outage"])
                if kind == "answer-lost":
                    drop_answers.set()
                    server_w.write(data)
                    await server_w.drain()
                    await asyncio.sleep(0.05)
                    say(f"{peer}: request {data.hex()} reached the drive, its answer lost; connection reset")
                elif kind == "lost":
                    say(f"{peer}: request {data.hex()} lost; connection reset")
                else:
                    outage_until = time.monotonic() + args.outage_ms / 1000.0
                    say(f"{peer}: request {data.hex()} lost; outage of {args.outage_ms:.0f} ms, then reset")
                    drop_answers.set()
                    await asyncio.sleep(args.outage_ms / 1000.0)
                reset(client_w)
                break
            server_w.write(data)
            await server_w.drain()
    except (ConnectionError, OSError):
        pass
    drop_answers.set()
    server_w.close()
    task.cancel()
    try:
        client_w.close()
    except (ConnectionError, OSError):
        pass


async def main():
    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    print(f"listening tcp 127.0.0.1:{port}", flush=True)
    async with server:
        try:
            await asyncio.wait_for(server.serve_forever(), args.lifetime)
        except asyncio.TimeoutError:
            pass
    say(f"{events} events")


if __name__ == "__main__":
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
