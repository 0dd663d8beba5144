#!/usr/bin/env python3
"""A serial line that gives back what the master sends: a two-wire RS-485 adapter's local echo, on a pty.

    echo-line.py --link PATH UPSTREAM [--echo on|off] [--corrupt-at N,...] [--drop-at N,...]
                 [--echo-delay MS] [--lifetime S]

Many USB-to-RS-485 adapters in two-wire mode keep their receiver on while they transmit, so every byte the
master sends comes back to it, ahead of the slave's answer. This script is such an adapter for tests: it
makes a pseudo-terminal, links PATH to it (the master, e.g. modbus-harness with
`--target "rtu://PATH?echo=on"`, opens PATH), and relays what the master writes to UPSTREAM, where the
drive is: a serial device or pty path (`/dev/pts/N`, one end of a socat pty pair that
`modbus-harness simulate --serial` serves), or HOST:PORT of an RTU-over-TCP drive on loopback. Every chunk
the master writes is first written back to it (the echo), then relayed; what UPSTREAM sends goes to the
master. So the master reads its request, then the answer, as on the real line.

  --echo off           relays without echo (the plain line, for comparison);
  --corrupt-at N,...   flips the low bit of the first byte of the echo of the Nth chunk the master writes
                       (counted from 1): a collision on the bus;
  --drop-at N,...      leaves out the echo of the Nth chunk (an adapter that does not echo reliably);
  --echo-delay MS      gives the echo back MS milliseconds late (an adapter's latency timer).

Prints `serial PATH` once the link exists, a stats line on stderr at the end (chunks, echoed, corrupted,
dropped, bytes up, bytes down), and ends by itself after --lifetime seconds (default 900) or on SIGTERM.
Standard library only; loopback only.
"""
import argparse
import os
import selectors
import signal
import socket
import sys
import termios
import time
import tty

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("upstream")
ap.add_argument("--link", required=True)
ap.add_argument("--echo", choices=["on", "off"], default="on")
ap.add_argument("--corrupt-at", default="")
ap.add_argument("--drop-at", default="")
ap.add_argument("--echo-delay", type=float, default=0.0, help="milliseconds")
ap.add_argument("--lifetime", type=float, default=900.0, help="seconds")
args = ap.parse_args()
corrupt_at = {int(n) for n in args.corrupt_at.split(",") if n}
drop_at = {int(n) for n in args.drop_at.split(",") if n}

stats = dict(chunks=0, echoed=0, corrupted=0, dropped=0, up=0, down=0)


def raw(fd):
    tty.setraw(fd)
    attrs = termios.tcgetattr(fd)
    attrs[3] &= ~(termios.ECHO | termios.ICANON)
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


def open_upstream(spec):
    """The drive's side: a serial device (raw) or an RTU-over-TCP connection on loopback."""
    if spec.startswith("/"):
        fd = os.open(spec, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        raw(fd)
        return fd, (lambda b: os.write(fd, b)), (lambda: os.read(fd, 4096))
    host, _, port = spec.rpartition(":")
    if host not in ("127.0.0.1", "localhost", "::1", "[::1]") and not host.startswith("127."):
        sys.exit("echo-line: the upstream must be on loopback")
    s = socket.create_connection((host.strip("[]"), int(port)), timeout=5)
    s.setblocking(False)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s, s.sendall, (lambda: s.recv(4096))


def write_all(fd, data):
    while data:
        try:
            n = os.write(fd, data)
            data = data[n:]
        except BlockingIOError:
            time.sleep(0.0005)


master, slave = os.openpty()
# The slave stays open here too: the line neither hangs up nor echoes by its own discipline while the
# master (the harness) has it closed between runs.
raw(slave)
os.set_blocking(master, False)
if os.path.lexists(args.link):
    os.unlink(args.link)
os.symlink(os.ttyname(slave), args.link)

up, up_write, up_read = open_upstream(args.upstream)

stop = False


def on_term(*_):
    global stop
    stop = True


signal.signal(signal.SIGTERM, on_term)
signal.signal(signal.SIGINT, on_term)
print(f"serial {args.link}", flush=True)

sel = selectors.DefaultSelector()
sel.register(master, selectors.EVENT_READ, "master")
sel.register(up, selectors.EVENT_READ, "upstream")
end = time.monotonic() + args.lifetime
try:
    while not stop and time.monotonic() < end:
        for key, _ in sel.select(timeout=0.2):
            if key.data == "master":
                try:
                    chunk = os.read(master, 4096)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:
                    # EIO: no process has the slave open but this one; nothing to read.
                    time.sleep(0.01)
                    continue
                if not chunk:
                    continue
                stats["chunks"] += 1
                if args.echo == "on":
                    if stats["chunks"] in drop_at:
                        stats["dropped"] += 1
                    else:
                        echo = bytearray(chunk)
                        if stats["chunks"] in corrupt_at:
                            echo[0] ^= 0x01
                            stats["corrupted"] += 1
                        if args.echo_delay:
                            time.sleep(args.echo_delay / 1000)
                        write_all(master, bytes(echo))
                        stats["echoed"] += 1
                up_write(chunk)
                stats["up"] += len(chunk)
            else:
                try:
                    data = up_read()
                except (BlockingIOError, InterruptedError):
                    continue
                if not data:
                    stop = True
                    break
                write_all(master, data)
                stats["down"] += len(data)
finally:
    print("echo-line: " + ", ".join(f"{k} {v}" for k, v in stats.items()), file=sys.stderr, flush=True)
    try:
        os.unlink(args.link)
    except OSError:
        pass
