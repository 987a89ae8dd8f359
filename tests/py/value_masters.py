#!/usr/bin/env python3
"""Masters that poll a gateway for as long as they run and check every reply by value,
as SCADA masters do while a USB adapter is pulled out and put back: pymodbus'
ModbusTcpClient (one request at a time), and raw asyncio masters that pipeline (several
requests on one connection before the first reply, MBAP by hand).

    value_masters.py --port N [--host 127.0.0.1] [--pymodbus 2] [--pipelined 2]
                     [--depth 4] [--unit 1] [--lone 17] [--every 0.02]
                     [--timeout 5] --out FILE

The device is stock_server.py's data (serial_device.py serves it, unit --unit):
holding register i = 1000 + i, input register i = 2000 + i. Reads are of registers
nobody writes, so their values hold whatever happens to the device; writes (FC 06, FC
16) go to holding registers 100 to 159, each master's its own, and are checked by their
echo. With --lone, reads of unit LONE too (lone_device.py: register i = 1000 + i, a
device silent for other ids). Every reply must be the right value, or exception 0x0A
or 0x0B; anything else is "wrong". A request with no answer within --timeout is
"lost"; a connection the gateway closed is "closed" (a pymodbus master then connects
again, a pipelined one too).

Each answer that is not a right value, and the first right one after any that was
not (with --all, every answer), goes to FILE (an answer that comes after its request was counted lost is "late") as a JSON line {"t": sent, "at": answered (time.monotonic(),
CLOCK_MONOTONIC), "m": master, "kind": "x0a"|"x0b"|"wrong"|"lost"|"closed"|"ok"};
at the end (SIGTERM or SIGINT: no new request, those on their way awaited up to 2 s) a last line {"summary": {...counts by kind, "max_s":
the longest answer}}. Prints READY once every master has connected.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import random
import signal
import struct
import sys
import threading
import time

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusIOException

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


class Record:
    """The answers of every master, written as they come."""

    def __init__(self, path: str):
        self.f = open(path, "w", encoding="ascii")  # noqa: SIM115 - closed in close()
        self.lock = threading.Lock()
        self.counts: dict[str, int] = {}
        self.max_s = 0.0
        self.bad_before: set[str] = set()
        self.all = False

    def add(self, master: str, kind: str, sent: float, at: float) -> None:
        with self.lock:
            self.counts[kind] = self.counts.get(kind, 0) + 1
            self.max_s = max(self.max_s, at - sent)
            if kind != "ok" or master in self.bad_before or self.all:
                self.f.write(json.dumps({"t": round(sent, 6), "at": round(at, 6), "m": master, "kind": kind}) + "\n")
                self.f.flush()
            if kind == "ok":
                self.bad_before.discard(master)
            else:
                self.bad_before.add(master)

    def close(self) -> None:
        with self.lock:
            self.f.write(json.dumps({"summary": dict(self.counts, max_s=round(self.max_s, 3))}) + "\n")
            self.f.close()


def pymodbus_master(a, n: int, rec: Record, stop: threading.Event, ready: threading.Barrier) -> None:
    name = f"pymodbus-{n}"
    rnd = random.Random(n)
    client = ModbusTcpClient(a.host, port=a.port, timeout=a.timeout, retries=0)
    client.connect()
    ready.wait()
    k = 0
    while not stop.is_set():
        k += 1
        sent = time.monotonic()
        try:
            if k % 3 == 0:
                addr, value = 100 + n * 4 + k % 4, rnd.randrange(65536)
                r = client.write_register(addr, value, device_id=a.unit)
                good = not r.isError() and r.address == addr and r.registers == [value]
            elif k % 3 == 1:
                addr = rnd.randrange(1, 90)
                r = client.read_holding_registers(addr, count=2, device_id=a.unit)
                good = not r.isError() and r.registers == [1000 + addr, 1001 + addr]
            else:
                addr = rnd.randrange(0, 90)
                r = client.read_input_registers(addr, count=1, device_id=a.unit)
                good = not r.isError() and r.registers == [2000 + addr]
            at = time.monotonic()
            if r.isError():
                code = getattr(r, "exception_code", None)
                kind = {10: "x0a", 11: "x0b"}.get(code, "wrong")
            else:
                kind = "ok" if good else "wrong"
        except (ConnectionException, ModbusIOException, OSError) as e:
            at = time.monotonic()
            kind = "lost" if at - sent >= a.timeout * 0.9 and "closed" not in str(e).lower() else "closed"
            client.close()
            client.connect()
        rec.add(name, kind, sent, at)
        time.sleep(a.every)
    client.close()


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


async def pipelined_master(a, n: int, rec: Record, stop: asyncio.Event, ready: list) -> None:
    name = f"pipelined-{n}"
    rnd = random.Random(1000 + n)
    first = True
    while not stop.is_set():
        try:
            reader, writer = await asyncio.open_connection(a.host, a.port)
        except OSError:
            await asyncio.sleep(0.5)
            continue
        if first:
            ready.append(n)
            first = False
        await pipelined_connection(a, name, rnd, rec, stop, reader, writer)
        # Closed by the gateway (counted): connect again, as a master does.
        await asyncio.sleep(0.5)


async def pipelined_connection(a, name, rnd, rec, stop, reader, writer) -> None:
    n = int(name.rsplit("-", 1)[1])
    tid = 0
    waiting: dict[int, tuple[float, bytes]] = {}
    room = asyncio.Semaphore(a.depth)

    async def send() -> None:
        nonlocal tid
        while not stop.is_set():
            await room.acquire()
            if stop.is_set():
                return
            tid = tid % 65535 + 1
            pick = rnd.randrange(4)
            if pick == 0:
                addr, value = 120 + n * 8 + rnd.randrange(8), rnd.randrange(65536)
                unit, pdu = a.unit, struct.pack(">BHH", 6, addr, value)
                want = pdu
            elif pick == 1:
                addr, values = 140 + n * 8, [rnd.randrange(65536) for _ in range(3)]
                unit = a.unit
                pdu = struct.pack(">BHHB", 16, addr, 3, 6) + struct.pack(">3H", *values)
                want = struct.pack(">BHH", 16, addr, 3)
            elif pick == 2 or not a.lone:
                addr = rnd.randrange(1, 90)
                unit, pdu = a.unit, struct.pack(">BHH", 3, addr, 2)
                want = struct.pack(">BB2H", 3, 4, 1000 + addr, 1001 + addr)
            else:
                addr = rnd.randrange(0, 90)
                unit, pdu = a.lone, struct.pack(">BHH", 3, addr, 1)
                want = struct.pack(">BBH", 3, 2, 1000 + addr)
            waiting[tid] = (time.monotonic(), struct.pack(">B", unit) + want)
            writer.write(mbap(tid, unit, pdu))
            await writer.drain()
            await asyncio.sleep(a.every / a.depth)

    async def receive() -> None:
        while True:
            head = await reader.readexactly(7)
            t, _, length, unit = struct.unpack(">HHHB", head)
            pdu = await reader.readexactly(length - 1)
            at = time.monotonic()
            if t not in waiting:
                # The answer to a request already counted lost: late, not wrong.
                rec.add(name, "late", at, at)
                continue
            sent, want = waiting.pop(t)
            got = struct.pack(">B", unit) + pdu
            if got == want:
                kind = "ok"
            elif len(pdu) == 2 and pdu[0] & 0x80 and unit == want[0] and pdu[0] & 0x7F == want[1]:
                kind = {10: "x0a", 11: "x0b"}.get(pdu[1], "wrong")
            else:
                kind = "wrong"
            rec.add(name, kind, sent, at)
            room.release()

    sender = asyncio.ensure_future(send())
    receiver = asyncio.ensure_future(receive())
    while not stop.is_set():
        if receiver.done():
            # The gateway closed it.
            now = time.monotonic()
            rec.add(name, "closed", now, now)
            break
        now = time.monotonic()
        for t, (sent, _) in list(waiting.items()):
            if now - sent > a.timeout:
                waiting.pop(t)
                rec.add(name, "lost", sent, now)
                room.release()
        await asyncio.sleep(0.05)
    sender.cancel()
    # Stopped: what is on its way is awaited up to 2 s (the caller's grace before a
    # kill is 3 s); a request sent just before the stop is not lost for being cut off.
    end = time.monotonic() + min(a.timeout, 2.0)
    while waiting and not receiver.done() and time.monotonic() < end:
        await asyncio.sleep(0.01)
    receiver.cancel()
    writer.close()
    for sent, _ in waiting.values():
        # Never answered before the connection went.
        rec.add(name, "lost", sent, time.monotonic())


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--pymodbus", type=int, default=2)
    ap.add_argument("--pipelined", type=int, default=2)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--unit", type=int, default=1)
    ap.add_argument("--lone", type=int, default=0)
    ap.add_argument("--every", type=float, default=0.02)
    ap.add_argument("--timeout", type=float, default=5.0)
    ap.add_argument("--out", required=True)
    ap.add_argument("--all", action="store_true", help="every answer to FILE, right ones too")
    a = ap.parse_args()
    rec = Record(a.out)
    rec.all = a.all
    stop_threads = threading.Event()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    barrier = threading.Barrier(a.pymodbus + 1)
    threads = [
        threading.Thread(target=pymodbus_master, args=(a, n, rec, stop_threads, barrier), daemon=True)
        for n in range(a.pymodbus)
    ]
    for t in threads:
        t.start()
    ready: list = []
    tasks = [asyncio.ensure_future(pipelined_master(a, n, rec, stop, ready)) for n in range(a.pipelined)]
    await loop.run_in_executor(None, barrier.wait)
    while len(ready) < a.pipelined:
        await asyncio.sleep(0.01)
    print("READY", flush=True)
    await stop.wait()
    stop_threads.set()
    await asyncio.gather(*tasks, return_exceptions=True)
    for t in threads:
        t.join(1.0)
    rec.close()
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
