#!/usr/bin/env python3
"""A drive with few connection slots, in front of a Modbus/TCP (or RTU over TCP) server on loopback.

    one-slot-proxy.py UPSTREAM_HOST:PORT [--policy refuse|reset|queue|replace] [--slots N]
                      [--notice MS] [--lifetime S]

Listens on 127.0.0.1, port 0; prints `listening tcp 127.0.0.1:PORT`, then a stats line on stderr every second (connections
accepted, refused, queued, replaced, most held at once). At most N connections (default 1) are relayed to
UPSTREAM at a time; one that arrives while they are all held is
  refuse   accepted and closed at once (FIN), as a firmware with its slots taken does;
  reset    the same with a reset (RST; FreeModbus's lwIP port aborts it so);
  queue    left unserved until a slot is free (a listen backlog);
  replace  served, and the oldest connection closed.
A client's close is noticed --notice MS late (default 0: a firmware that polls its sockets every few
milliseconds); then the drive closes its side and frees the slot at once. Where the server closes first,
the slot is freed at once. With --idle MS, a connection on which the client sent nothing for MS is closed
by the drive (an idle timeout, as many drives have). Ends by itself after --lifetime seconds (default 900). Standard library only.
"""
import argparse
import asyncio
import socket
import struct
import sys

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("upstream")
ap.add_argument("--policy", choices=["refuse", "reset", "queue", "replace"], default="refuse")
ap.add_argument("--slots", type=int, default=1)
ap.add_argument("--notice", type=float, default=0.0, help="milliseconds")
ap.add_argument("--lifetime", type=float, default=900.0, help="seconds")
ap.add_argument("--idle", type=float, default=0.0, help="milliseconds; 0: never")
args = ap.parse_args()
up_host, up_port = args.upstream.rsplit(":", 1)
if up_host not in ("127.0.0.1", "localhost", "::1") and not up_host.startswith("127."):
    sys.exit("one-slot-proxy: the upstream must be on loopback")

active = []
stats = dict(accepted=0, refused=0, queued=0, replaced=0, held_at_once=0, idle_closed=0)
slot = None  # asyncio.Condition, made in main()


async def pipe(r, w, idle=0.0):
    try:
        while True:
            if idle:
                try:
                    d = await asyncio.wait_for(r.read(65536), idle / 1000)
                except asyncio.TimeoutError:
                    stats["idle_closed"] += 1
                    return "idle"
            else:
                d = await r.read(65536)
            if not d:
                break
            w.write(d)
            await w.drain()
    except Exception:
        pass


async def handle(cr, cw):
    stats["accepted"] += 1
    if len(active) >= args.slots:
        if args.policy in ("refuse", "reset"):
            stats["refused"] += 1
            if args.policy == "reset":
                cw.get_extra_info("socket").setsockopt(
                    socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            cw.close()
            return
        if args.policy == "queue":
            stats["queued"] += 1
            async with slot:
                await slot.wait_for(lambda: len(active) < args.slots)
        else:
            stats["replaced"] += 1
            for w in active.pop(0):
                w.close()
    try:
        ur, uw = await asyncio.open_connection(up_host, int(up_port))
    except OSError:
        cw.close()
        return
    me = (cw, uw)
    active.append(me)
    stats["held_at_once"] = max(stats["held_at_once"], len(active))
    try:
        up = asyncio.ensure_future(pipe(cr, uw, args.idle))
        down = asyncio.ensure_future(pipe(ur, cw))
        done, _ = await asyncio.wait([up, down], return_when=asyncio.FIRST_COMPLETED)
        if up in done and args.notice and up.result() != "idle":
            await asyncio.sleep(args.notice / 1000)
        # The slot is freed before the drive's FIN goes out, as a firmware closing its socket does.
        if me in active:
            active.remove(me)
        for w in me:
            w.close()
        up.cancel()
        down.cancel()
    finally:
        if me in active:
            active.remove(me)
        async with slot:
            slot.notify_all()


async def report():
    while True:
        await asyncio.sleep(1)
        print("stats", stats, flush=True, file=sys.stderr)


async def main():
    global slot
    slot = asyncio.Condition()
    srv = await asyncio.start_server(handle, "127.0.0.1", 0)
    print("listening tcp 127.0.0.1:%d" % srv.sockets[0].getsockname()[1], flush=True)
    asyncio.get_running_loop().create_task(report())
    async with srv:
        try:
            await asyncio.wait_for(srv.serve_forever(), args.lifetime)
        except asyncio.TimeoutError:
            pass
    print("stats", stats, flush=True, file=sys.stderr)


asyncio.run(main())
