#!/usr/bin/env python3
"""The host's side of scripts/pi-check's USB checks (docs/raspberry-pi.md "When the
adapter is pulled out"): the devices on the far end of the guest's USB serial adapter
(QEMU's usb-serial, an FTDI FT232 the guest's ftdi_sio drives), the masters that poll
the gateway in the guest through its network, and the hand that pulls the adapter out
and puts it back (QMP device_del and device_add), as the guest's scripts/usb-check
asks over a control port.

    usb-ring.py --qmp SOCK --ctl SOCK --line SOCK --modbus PORT --metrics PORT
                --python VENV_PYTHON --tests DIR --work DIR --results FILE

The adapter's line (the chardev `usbline`, a unix socket QEMU listens on: --line) is
connected while the adapter is in and routed, a whole RTU request at a time, to the
device serving its unit: pymodbus' RTU server (tests/py/serial_device.py, unit 1) or a
raw RTU device (tests/py/lone_device.py, unit 17), each on a socat pty pair, at 19200
8N1; a request to any other unit reaches nobody (silence, as on a bus). Their replies
go back on the line while the adapter is in; one made while it is out goes nowhere, as
on a bus whose adapter was pulled. The masters are tests/py/value_masters.py
(pymodbus' and pipelining ones, every reply checked by value).

The guest asks, one line each way on the control port:
  PLUG PORT        device_add on xhci port PORT, then the line connected (which
                   attaches it); "OK"
  UNPLUG           the line closed (which detaches it), then device_del; "OK"
  MASTERS          starts the masters (once); "OK"
  WINDOW NAME      the masters' answers since the last WINDOW (or since they started);
                   also writes a result line NAME-masters: every answer a right value
                   or 0x0A/0x0B within the masters' timeout, no connection closed
  SKIP             the next window starts now (the one before is not judged)
  CYCLES NAME N    N outages at random instants, each once the gateway serves again
                   (a master's right answer) and 1 to 4 s more, the adapter away 0.2 to 10 s each,
                   some while a request is on the wire (unplugged as it arrives) or a
                   reply half sent, every fourth plugged back on the other port; the
                   adapter is in when it ends; "DONE" and the figures
  METRICS          the gateway's mbgate_line_outages_total and
                   mbgate_line_outage_seconds_total, read from its /metrics
  END              stops everything; "OK"
Result lines (PASS, FAIL, FIGURE) the host judges go to --results.

Why the line is closed before device_del: QEMU 7.2 (bookworm's) dies of a SIGSEGV when
bytes reach usb-serial's chardev in the main loop's turn that runs device_del. The
chardev's read handler sizes its read before that turn's callbacks run, while the
adapter is still attached, and hands the bytes to the adapter after device_del has
taken it off the bus (usb_serial_read, usb_wakeup: its bus is NULL). With a pty line
and a reply on its way it came at the first pull. A closed socket line detaches the
adapter first (usb-serial's CHR_EVENT_CLOSED) and takes the chardev's read watch away,
so nothing reaches the adapter afterwards; device_del waits until QOM says
`attached` is false. scripts/usb-unplug-race plays the race both ways in seconds.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
import socket
import statistics
import termios
import time
import tty
import urllib.request

CRC_TABLE = []
for _i in range(256):
    _c = _i
    for _ in range(8):
        _c = (_c >> 1) ^ 0xA001 if _c & 1 else _c >> 1
    CRC_TABLE.append(_c)


def crc16(data: bytes) -> int:
    c = 0xFFFF
    for b in data:
        c = (c >> 8) ^ CRC_TABLE[(c ^ b) & 0xFF]
    return c


def request_length(buf: bytes) -> int | None:
    """The length of the RTU request at the start of `buf`, by its function code."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (1, 2, 3, 4, 5, 6):
        return 8
    if fc in (15, 16):
        return 9 + buf[6] if len(buf) >= 7 else None
    return 0  # unknown: dropped a byte at a time


def reply_length(buf: bytes) -> int | None:
    if len(buf) < 3:
        return None
    fc = buf[1]
    if fc & 0x80:
        return 5
    if fc in (1, 2, 3, 4):
        return 5 + buf[2]
    if fc in (5, 6, 15, 16):
        return 8
    return 0


def raw_pty(path: str) -> int:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    attrs = termios.tcgetattr(fd)
    attrs[2] &= ~termios.CRTSCTS
    termios.tcsetattr(fd, termios.TCSANOW, attrs)
    return fd


class Qmp:
    def __init__(self, path: str):
        self.path = path

    async def open(self) -> None:
        self.r, self.w = await asyncio.open_unix_connection(self.path)
        await self.r.readline()  # greeting
        await self.call("qmp_capabilities")

    async def call(self, cmd: str, **args) -> dict:
        self.w.write(json.dumps({"execute": cmd, "arguments": args}).encode() + b"\n")
        await self.w.drain()
        while True:
            msg = json.loads(await self.r.readline())
            if "return" in msg or "error" in msg:
                if "error" in msg:
                    raise RuntimeError(f"QMP {cmd}: {msg['error']}")
                return msg


class Ring:
    def __init__(self, a):
        self.a = a
        self.port = 1
        self.plugged = False
        self.procs: list[asyncio.subprocess.Process] = []
        self.devices: dict[int, int] = {}
        self.line = -1
        self.arm: str | None = None  # "request" or "reply": pull at the next one
        self.armed = asyncio.Event()
        self.masters = None
        self.events_seen = 0
        self.results = open(a.results, "a", encoding="utf-8")  # noqa: SIM115
        self.passed = self.failed = 0

    def result(self, kind: str, name: str, text: str) -> None:
        if kind == "PASS":
            self.passed += 1
        elif kind == "FAIL":
            self.failed += 1
        self.results.write(f"{kind} {name}: {text}\n")
        self.results.flush()

    async def start_devices(self) -> None:
        for unit, script, extra in (
            (1, "serial_device.py", ["--framer", "rtu", "--parity", "N", "--units", "1", "--size", "300"]),
            (17, "lone_device.py", ["--framer", "rtu", "--unit", "17"]),
        ):
            near, far = f"{self.a.work}/dev{unit}-line", f"{self.a.work}/dev{unit}"
            socat = await asyncio.create_subprocess_exec(
                "socat", f"pty,raw,echo=0,link={near}", f"pty,raw,echo=0,link={far}"
            )
            self.procs.append(socat)
            for _ in range(100):
                if os.path.exists(near) and os.path.exists(far):
                    break
                await asyncio.sleep(0.05)
            dev = await asyncio.create_subprocess_exec(
                self.a.python, f"{self.a.tests}/{script}", "--port", far, "--baud", "19200", *extra,
                stdout=asyncio.subprocess.PIPE,
            )
            self.procs.append(dev)
            line = await asyncio.wait_for(dev.stdout.readline(), 30)
            assert line.strip() == b"READY", f"{script}: {line!r}"
            self.devices[unit] = raw_pty(near)
        loop = asyncio.get_running_loop()
        for unit, fd in self.devices.items():
            loop.add_reader(fd, self.from_device, unit)
        self.line_buf = b""
        self.dev_buf = {u: b"" for u in self.devices}

    def connect_line(self) -> None:
        """The adapter's line connected: QEMU's usb-serial attaches as it sees it."""
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.connect(self.a.line)
        sock.setblocking(False)
        self.line_sock = sock
        self.line = sock.fileno()
        self.line_buf = b""
        asyncio.get_running_loop().add_reader(self.line, self.from_line)

    def close_line(self) -> None:
        """The adapter's line closed: QEMU's usb-serial detaches as it sees it; what was
        on its way is lost, as with an adapter pulled out."""
        if self.line < 0:
            return
        asyncio.get_running_loop().remove_reader(self.line)
        self.line_sock.close()
        self.line = -1

    def to_line(self, data: bytes) -> None:
        if self.line < 0:
            return  # the adapter is out: to nowhere
        try:
            self.line_sock.send(data)
        except (BlockingIOError, OSError):
            pass

    def from_line(self) -> None:
        try:
            got = os.read(self.line, 4096)
        except (BlockingIOError, OSError):
            return
        if not got:
            self.close_line()
            return
        self.line_buf += got
        while True:
            n = request_length(self.line_buf)
            if n is None or len(self.line_buf) < max(n, 1):
                return
            frame = self.line_buf[:n] if n else b""
            if n == 0 or crc16(frame[:-2]) != int.from_bytes(frame[-2:], "little"):
                self.line_buf = self.line_buf[1:]
                continue
            self.line_buf = self.line_buf[n:]
            if self.arm == "request":
                # On the wire, never to reach the device: pulled as it arrives.
                self.arm = None
                self.armed.set()
                continue
            fd = self.devices.get(frame[0])
            if fd is not None:
                os.write(fd, frame)

    def from_device(self, unit: int) -> None:
        try:
            self.dev_buf[unit] += os.read(self.devices[unit], 4096)
        except (BlockingIOError, OSError):
            return
        buf = self.dev_buf[unit]
        n = reply_length(buf)
        if n is None or len(buf) < max(n, 1):
            return
        frame, self.dev_buf[unit] = (buf[:n], buf[n:]) if n else (buf, b"")
        if self.arm == "reply" and len(frame) > 2 and self.line >= 0:
            # Half a reply on the wire, then the adapter is gone.
            self.to_line(frame[: len(frame) // 2])
            self.arm = None
            self.armed.set()
            return
        self.to_line(frame)

    async def attached(self) -> bool:
        r = await self.qmp.call("qom-get", path="/machine/peripheral/adapter", property="attached")
        return bool(r["return"])

    async def until_attached(self, want: bool) -> None:
        for _ in range(500):
            if await self.attached() == want:
                return
            await asyncio.sleep(0.01)
        raise RuntimeError(f"usb-serial never {'attached' if want else 'detached'} (5 s)")

    async def plug(self, port: int) -> None:
        # Added without its line (not always-plugged), then attached as the line
        # connects. The chardev of the adapter just removed is let go a moment after
        # (the device is finalized later): "Device 'usbline' is in use" until then.
        for attempt in range(100):
            try:
                await self.qmp.call(
                    "device_add", driver="usb-serial", id="adapter", chardev="usbline",
                    bus="xhci.0", port=str(port), serial="A50285BI",
                )
                break
            except RuntimeError as e:
                if "in use" not in str(e) or attempt == 99:
                    raise
                await asyncio.sleep(0.02)
        self.connect_line()
        await self.until_attached(True)
        self.port, self.plugged = port, True

    async def unplug(self) -> None:
        # The line first (the module notes): detached, nothing more reaches it.
        self.close_line()
        await self.until_attached(False)
        await self.qmp.call("device_del", id="adapter")
        # The chardev is free again once the device is gone.
        for _ in range(200):
            found = await self.qmp.call("qom-list", path="/machine/peripheral")
            if not any(p["name"] == "adapter" for p in found["return"]):
                break
            await asyncio.sleep(0.01)
        self.plugged = False

    async def start_masters(self) -> None:
        self.masters_out = f"{self.a.work}/masters.jsonl"
        self.masters = await asyncio.create_subprocess_exec(
            self.a.python, f"{self.a.tests}/value_masters.py", "--port", str(self.a.modbus),
            "--pymodbus", "2", "--pipelined", "2", "--depth", "2", "--lone", "17",
            "--every", "0.2", "--timeout", str(self.a.timeout), "--out", self.masters_out, "--all",
            stdout=asyncio.subprocess.PIPE,
        )
        line = await asyncio.wait_for(self.masters.stdout.readline(), 60)
        assert line.strip() == b"READY", f"value_masters.py: {line!r}"
        self.window_from = time.monotonic()
        self.outages: list[tuple[float, float]] = []

    def events(self, since: float, until: float) -> list[dict]:
        """The masters' answers from `since` to `until` (their file read as it grows)."""
        if not hasattr(self, "_ev"):
            self._ev, self._pos = [], 0
        with open(self.masters_out, encoding="ascii") as f:
            f.seek(self._pos)
            while True:
                line = f.readline()
                if not line.endswith("\n"):
                    break
                self._pos += len(line)
                e = json.loads(line)
                if "summary" not in e and e["kind"] != "late":
                    self._ev.append(e)
        return [e for e in self._ev if since <= e["at"] < until]

    def window(self, name: str) -> str:
        now = time.monotonic()
        ev = self.events(self.window_from, now)
        kinds = {k: sum(1 for e in ev if e["kind"] == k) for k in ("x0a", "x0b", "wrong", "lost", "closed")}
        slow = [e for e in ev if e["at"] - e["t"] > self.a.timeout]
        summary = f"{kinds['x0a']} answered 0x0A, {kinds['x0b']} 0x0B, {kinds['wrong']} wrong, {kinds['lost']} unanswered within {self.a.timeout} s, {kinds['closed']} connections closed"
        if kinds["wrong"] or kinds["lost"] or kinds["closed"] or slow:
            self.result("FAIL", f"{name}-masters", summary + (f"; first: {ev[0]}" if ev else ""))
        else:
            self.result("PASS", f"{name}-masters", "4 masters (2 pymodbus, 2 pipelining 2 deep), units 1 and 17, reads and writes: " + summary)
        self.window_from = now
        return summary

    async def cycles(self, name: str, n: int) -> str:
        rnd = random.Random(f"{name}-{n}")
        lost_per_outage = []
        away = []
        ports = []
        for i in range(1, n + 1):
            # Served for 1 to 4 s from the first right answer after the plug: under
            # emulation the guest's udev may take seconds to make the node and link,
            # and an unplug before the gateway had the port again is no outage of its.
            await self.served_since(time.monotonic() if i == 1 else back, 120)
            await asyncio.sleep(rnd.uniform(1.0, 4.0))
            how = {3: "request", 1: "reply"}.get(i % 4)
            if how:
                self.arm = how
                self.armed.clear()
                try:
                    await asyncio.wait_for(self.armed.wait(), 10)
                    if how == "reply":
                        # The half reply let into the adapter first: the line's close
                        # drops what QEMU has not read of it yet.
                        await asyncio.sleep(0.02)
                except asyncio.TimeoutError:
                    self.arm = None
            pulled = time.monotonic()
            await self.unplug()
            gone = math.exp(rnd.uniform(math.log(0.2), math.log(10.0)))
            await asyncio.sleep(gone)
            port = 2 if i % 4 == 2 else 1
            await self.plug(port)
            back = time.monotonic()
            away.append(back - pulled)
            ports.append(port)
            self.outages.append((pulled, back))
        await self.served_since(back, 120)
        await asyncio.sleep(1.0)
        # Answers lost to each outage: the exceptions from its pull until the next pull.
        ends = [p for p, _ in self.outages[-n:]][1:] + [time.monotonic()]
        for (pulled, _), end in zip(self.outages[-n:], ends):
            ev = self.events(pulled - 0.05, end)
            lost_per_outage.append(sum(1 for e in ev if e["kind"] in ("x0a", "x0b")))
        figure = (
            f"{n} outages ({sum(1 for p in ports if p == 2)} plugged back on port 2), away "
            f"{min(away):.2f} to {max(away):.2f} s; answers lost per outage (0x0A or 0x0B) "
            f"min {min(lost_per_outage)}, median {statistics.median(lost_per_outage):g}, max {max(lost_per_outage)}"
        )
        self.result("FIGURE", f"{name}-lost-per-outage", figure)
        return f"away_total={sum(away):.3f} " + figure

    async def served_since(self, since: float, within: float) -> None:
        """Waits until a master got a right answer sent after `since`."""
        end = time.monotonic() + within
        while time.monotonic() < end:
            if any(e["kind"] == "ok" and e["t"] >= since for e in self.events(since, time.monotonic() + 1)):
                return
            await asyncio.sleep(0.1)

    def metrics(self) -> str:
        body = urllib.request.urlopen(f"http://127.0.0.1:{self.a.metrics}/metrics", timeout=10).read().decode()
        want = {}
        for line in body.splitlines():
            for key in ("mbgate_line_outages_total", "mbgate_line_outage_seconds_total", "mbgate_line_opens_total"):
                if line.startswith(key + "{") or line.startswith(key + " "):
                    want[key] = float(line.rsplit(" ", 1)[1])
        return " ".join(f"{k}={v:g}" for k, v in sorted(want.items()))

    async def serve(self) -> None:
        self.qmp = Qmp(self.a.qmp)
        await self.qmp.open()
        await self.start_devices()
        for _ in range(6000):
            try:
                r, w = await asyncio.open_unix_connection(self.a.ctl)
                break
            except OSError:
                await asyncio.sleep(0.1)
        buf = b""
        while True:
            line = await r.readline()
            if not line:
                break
            words = line.decode().split()
            if not words:
                continue
            cmd = words[0]
            try:
                if cmd == "PLUG":
                    await self.plug(int(words[1]))
                    reply = "OK"
                elif cmd == "UNPLUG":
                    await self.unplug()
                    reply = "OK"
                elif cmd == "MASTERS":
                    if self.masters is None:
                        await self.start_masters()
                    reply = "OK"
                elif cmd == "WINDOW":
                    reply = "OK " + self.window(words[1])
                elif cmd == "SKIP":
                    # A window not judged (the service restarted: its connections
                    # closed, as a restart does).
                    self.window_from = time.monotonic()
                    reply = "OK"
                elif cmd == "CYCLES":
                    reply = "DONE " + await self.cycles(words[1], int(words[2]))
                elif cmd == "METRICS":
                    reply = "OK " + self.metrics()
                elif cmd == "END":
                    w.write(b"OK\n")
                    await w.drain()
                    break
                else:
                    reply = f"ERROR unknown {cmd}"
            except Exception as e:  # noqa: BLE001 - told to the guest, which fails the check
                reply = f"ERROR {type(e).__name__}: {e}"
            w.write(reply.encode() + b"\n")
            await w.drain()
        del buf
        if self.masters is not None:
            self.masters.terminate()
            await self.masters.wait()
        for p in self.procs:
            p.terminate()
        self.results.close()


def main() -> int:
    ap = argparse.ArgumentParser()
    for key in ("qmp", "ctl", "line", "python", "tests", "work", "results"):
        ap.add_argument(f"--{key}", required=True)
    ap.add_argument("--modbus", type=int, required=True)
    ap.add_argument("--metrics", type=int, required=True)
    # A SCADA master's timeout; the gateway's own is 3 s, with a resend (each answer
    # is a value, 0x0A or 0x0B well within this on a line that works).
    ap.add_argument("--timeout", type=float, default=20.0)
    a = ap.parse_args()
    asyncio.run(Ring(a).serve())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
