#!/usr/bin/env python3
"""Preset a running independent LMD (lmd/sim.py) the way a configured drive is: output 2 set up as a function
output (OS=2,17,0: 'Moving', active low) and output 1 on. Loopback only.

    python3 tests/independent/lmd/sim.py --listen 127.0.0.1:0 --state /tmp/lmd.json &   # prints its address
    python3 tests/independent/lmd/preset_output_function.py 127.0.0.1:PORT
    modbus-harness run --target tcp://127.0.0.1:PORT --profile lmd

Reproduces the open item "LMD outputs set up as function outputs" of tests/independent/README.md (4 FAIL,
the drive's state as found).
"""
import socket
import sys

host, port = sys.argv[1].rsplit(':', 1)
if not host.startswith('127.') and host not in ('localhost', '::1'):
    sys.exit('loopback only')
s = socket.create_connection((host, int(port)), timeout=2)
tid = 1


def mnemonic(m):
    return bytes(reversed(m.ljust(4).encode()))


def send(pdu):
    global tid
    adu = tid.to_bytes(2, 'big') + b'\0\0' + (len(pdu) + 1).to_bytes(2, 'big') + b'\x01' + pdu
    tid += 1
    s.sendall(adu)
    answer = s.recv(300)[7:]
    print(pdu.hex(' '), '->', answer.hex(' '))
    return answer


params = b'=2,17,0'
assert send(b'\x42' + mnemonic('OS') + bytes([len(params)]) + params)[0] == 0x42
assert send(b'\x05\x00\x00\xff\x00')[0] == 0x05  # output 1 on
send(b'\x41' + mnemonic('OS'))  # read back: the setups of all lines
