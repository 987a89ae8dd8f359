#!/usr/bin/env python3
"""Masters of mbgate's Modbus over UDP listener (tests/e2e/dial.rs), each reply checked by
value against stock_server.py's device (unit 1) behind the gateway.

    udp_master.py --port PORT [--malformed N] [--flood N]

Without --flood: N malformed datagrams first (none is one MBAP request), then
pymodbus' ModbusUdpClient (prints "sync ok") and AsyncModbusUdpClient ("async ok").
With --flood N: one raw socket sends N read requests without waiting for replies,
in 40 bursts; after each burst a polite ModbusUdpClient on its own socket asks once
and checks the reply ("polite ok 40"); then the flood's replies are counted
("flood replies M"). Exits 1 with "FAIL ..." on any wrong or missing reply.
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import struct
import sys
import time

from pymodbus.client import AsyncModbusUdpClient, ModbusUdpClient

HOST = "127.0.0.1"


def fail(what: str) -> None:
    print(f"FAIL {what}", flush=True)
    sys.exit(1)


def check_sync(port: int, label: str, rounds: int = 1) -> None:
    client = ModbusUdpClient(HOST, port=port, timeout=10, retries=0)
    if not client.connect():
        fail(f"{label}: no socket")
    for i in range(rounds):
        address = 1 + i % 50
        r = client.read_holding_registers(address, count=2, device_id=1)
        if r.isError() or list(r.registers) != [1000 + address, 1001 + address]:
            fail(f"{label}: holding {address}: {r}")
    client.close()


def sync_checks(port: int) -> None:
    client = ModbusUdpClient(HOST, port=port, timeout=10, retries=0)
    client.connect()
    r = client.read_input_registers(3, count=3, device_id=1)
    if r.isError() or list(r.registers) != [2003, 2004, 2005]:
        fail(f"sync input registers: {r}")
    r = client.write_register(120, 4242, device_id=1)
    if r.isError():
        fail(f"sync write: {r}")
    r = client.read_holding_registers(120, count=1, device_id=1)
    if r.isError() or list(r.registers) != [4242]:
        fail(f"sync read back: {r}")
    r = client.read_coils(0, count=6, device_id=1)
    if r.isError() or list(r.bits[:6]) != [i % 3 == 0 for i in range(6)]:
        fail(f"sync coils: {r}")
    client.close()
    check_sync(port, "sync", 5)
    print("sync ok", flush=True)


async def async_checks(port: int) -> None:
    client = AsyncModbusUdpClient(HOST, port=port, timeout=10, retries=0)
    await client.connect()
    for address in (2, 30, 77):
        r = await client.read_holding_registers(address, count=4, device_id=1)
        want = [1000 + address + i for i in range(4)]
        if r.isError() or list(r.registers) != want:
            fail(f"async holding {address}: {r}")
    r = await client.write_registers(130, [5, 6, 7], device_id=1)
    if r.isError():
        fail(f"async write: {r}")
    r = await client.read_holding_registers(130, count=3, device_id=1)
    if r.isError() or list(r.registers) != [5, 6, 7]:
        fail(f"async read back: {r}")
    client.close()
    print("async ok", flush=True)


def request(tid: int) -> bytes:
    """Read holding register 1, unit 1, as an MBAP datagram."""
    return struct.pack(">HHHBBHH", tid & 0xFFFF, 0, 6, 1, 3, 1, 1)


def malformed(port: int, n: int) -> None:
    good = request(1)
    bad = [
        b"hello",
        good[:7],
        good[:2] + b"\x00\x01" + good[4:],
        good + good,
        good[:4] + b"\x00\x09" + good[6:],
    ]
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for i in range(n):
        s.sendto(bad[i % len(bad)], (HOST, port))
    s.close()


def flood(port: int, n: int) -> None:
    flooder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    flooder.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    polite = ModbusUdpClient(HOST, port=port, timeout=10, retries=0)
    polite.connect()
    bursts = 40
    sent = 0
    for b in range(bursts):
        for _ in range(n // bursts):
            flooder.sendto(request(sent), (HOST, port))
            sent += 1
        address = 1 + b
        r = polite.read_holding_registers(address, count=1, device_id=1)
        if r.isError() or list(r.registers) != [1000 + address]:
            fail(f"polite {b}: {r}")
    polite.close()
    print(f"polite ok {bursts}", flush=True)
    flooder.settimeout(2.0)
    replies = 0
    try:
        while True:
            d = flooder.recv(512)
            if len(d) != 11 or d[7:9] != b"\x03\x02" or d[9:11] != b"\x03\xe9":
                fail(f"flood reply {d.hex()}")
            replies += 1
    except socket.timeout:
        pass
    flooder.close()
    print(f"flood replies {replies}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--malformed", type=int, default=0)
    ap.add_argument("--flood", type=int, default=0)
    args = ap.parse_args()
    if args.flood:
        flood(args.port, args.flood)
        return 0
    malformed(args.port, args.malformed)
    # The malformed ones go first on the gateway's one receive loop.
    time.sleep(0.1)
    sync_checks(args.port)
    asyncio.run(async_checks(args.port))
    return 0


if __name__ == "__main__":
    sys.exit(main())
