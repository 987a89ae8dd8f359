#!/usr/bin/env python3
"""Simulated "serial Modbus/TCP" device (CIE-M10 style) for the mbgate end-to-end tests.

Speaks whole MBAP frames (no CRC) on a serial port or pty:

    device.py --port PATH [--units 1] [--size 200] [--baud 19200]
              [--delay-ms 0] [--gap-ms 100] [--trace]

Prints exactly ``READY`` on stdout once the port is open and being served, and nothing
else on stdout; diagnostics go to stderr. Exits 0 on SIGTERM/SIGINT.

Why not pymodbus' ``ModbusSerialServer(framer=FramerType.SOCKET)``: in pymodbus 3.16.1 it
(a) answers an unknown unit id with exception 04 (SimCore raises KeyError, so even
``ignore_missing_devices=True`` does not silence it), (b) handles only the first frame of
a read chunk (a second, back-to-back request stays in the buffer unanswered until more
bytes arrive), (c) pads bit tables to a multiple of 16, so coils size..size+7 read
without exception 02, (d) answers a count of 0 with "80 01" instead of "83 03". So the
MBAP framing and the datastore are done here, and pymodbus does the PDUs: it decodes
each request (``DecodePDU``), executes it (``datastore_update``) and encodes the reply.

Data, per served unit, ``size`` entries in each table, addresses 0..size-1 (PDU
addresses, 0-based, no offset), anything beyond -> exception 02:
  holding register 0 = 0x00FF, holding register i = 1000 + i (i >= 1)
  input register i   = 2000 + i
  coil i             = ON when i % 3 == 0
  discrete input i   = ON when i % 2 == 0
Requests for unit ids not in ``--units`` get no reply at all.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import struct
import sys
import time

import serial

from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerSocket
from pymodbus.pdu import DecodePDU, ExceptionResponse

MBAP_HEADER = 6  # tid(2) pid(2) length(2); the length counts unit id + PDU
MIN_LENGTH = 2
MAX_LENGTH = 254


def log(msg: str) -> None:
    print(f"device: {msg}", file=sys.stderr, flush=True)


class UnitStore:
    """The four tables of one unit."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.tables: dict[str, list] = {
            "c": [i % 3 == 0 for i in range(size)],
            "d": [i % 2 == 0 for i in range(size)],
            "h": [0x00FF] + [(1000 + i) & 0xFFFF for i in range(1, size)],
            "i": [(2000 + i) & 0xFFFF for i in range(size)],
        }


class Context:
    """What pymodbus' ``datastore_update`` calls (the ModbusServerContext interface)."""

    TABLE_OF_FC = {1: "c", 5: "c", 15: "c", 2: "d", 4: "i", 3: "h", 6: "h", 16: "h", 22: "h", 23: "h"}
    BIT_TABLES = ("c", "d")

    def __init__(self, units: list[int], size: int) -> None:
        self.units = {u: UnitStore(size) for u in units}

    def device_ids(self) -> list[int]:
        return list(self.units)

    def _locate(self, device_id: int, func_code: int, address: int, count: int):
        table = self.TABLE_OF_FC.get(func_code)
        if table is None:
            return None, ExcCodes.ILLEGAL_FUNCTION
        store = self.units[device_id]
        if address < 0 or count < 1 or address + count > store.size:
            return None, ExcCodes.ILLEGAL_ADDRESS
        return store.tables[table], table

    async def async_getValues(self, device_id: int, func_code: int, address: int, count: int = 1):
        values, table = self._locate(device_id, func_code, address, count)
        if values is None:
            return table  # an ExcCodes
        return list(values[address : address + count])

    async def async_setValues(self, device_id: int, func_code: int, address: int, values):
        values = list(values) if isinstance(values, (list, tuple)) else [values]
        dest, table = self._locate(device_id, func_code, address, len(values))
        if dest is None:
            return table
        if table in self.BIT_TABLES:
            dest[address : address + len(values)] = [bool(v) for v in values]
        else:
            dest[address : address + len(values)] = [int(v) & 0xFFFF for v in values]
        return None


class Device:
    def __init__(self, args: argparse.Namespace, units: list[int]) -> None:
        self.args = args
        self.units = set(units)
        self.context = Context(units, args.size)
        self.decoder = DecodePDU(True)
        self.known_fcs = set(self.decoder.list_function_codes())
        self.framer = FramerSocket(self.decoder)
        self.buf = bytearray()
        self.last_rx = time.monotonic()
        self.frames: asyncio.Queue[bytes] = asyncio.Queue()
        self.dropped = 0
        self.ser: serial.Serial | None = None
        self.loop = asyncio.get_running_loop()
        self.stop = asyncio.Event()
        self.gap_timer: asyncio.TimerHandle | None = None
        self.failed = False

    # ---------------------------------------------------------------- serial side
    def open(self) -> None:
        self.ser = serial.Serial(
            self.args.port,
            baudrate=self.args.baud,
            bytesize=8,
            parity="N",
            stopbits=1,
            timeout=0,
            write_timeout=2,
            exclusive=True,
        )
        self.loop.add_reader(self.ser.fileno(), self.on_readable)

    def close(self) -> None:
        if self.ser is not None:
            try:
                self.loop.remove_reader(self.ser.fileno())
            except Exception:  # noqa: BLE001
                pass
            self.ser.close()
            self.ser = None

    def on_readable(self) -> None:
        try:
            data = self.ser.read(max(self.ser.in_waiting, 1))
        except (serial.SerialException, OSError) as exc:
            log(f"serial read failed: {exc}; stopping")
            self.failed = True
            self.stop.set()
            self.loop.remove_reader(self.ser.fileno())
            return
        if not data:
            return
        if self.args.trace:
            log(f"rx chunk {data.hex(' ')}")
        self.buf += data
        self.last_rx = time.monotonic()
        self.extract()
        if self.gap_timer is not None:
            self.gap_timer.cancel()
            self.gap_timer = None
        if self.buf:
            self.gap_timer = self.loop.call_later(self.args.gap_ms / 1000, self.on_gap)

    def drop(self, n: int, why: str) -> None:
        if self.args.trace:
            log(f"drop {bytes(self.buf[:n]).hex(' ')} ({why})")
        del self.buf[:n]
        self.dropped += n

    def extract(self) -> None:
        """Cut every complete, plausible MBAP frame off the front of the buffer."""
        while len(self.buf) >= MBAP_HEADER:
            pid = int.from_bytes(self.buf[2:4], "big")
            length = int.from_bytes(self.buf[4:6], "big")
            if pid != 0 or not MIN_LENGTH <= length <= MAX_LENGTH:
                self.drop(1, "implausible header")
                continue
            total = MBAP_HEADER + length
            if len(self.buf) < total:
                return
            frame = bytes(self.buf[:total])
            del self.buf[:total]
            self.frames.put_nowait(frame)

    def on_gap(self) -> None:
        """A partial frame got no new byte for --gap-ms: drop a byte at a time and rescan."""
        self.gap_timer = None
        while self.buf:
            self.drop(1, "stalled partial frame")
            self.extract()

    def write(self, data: bytes) -> None:
        try:
            self.ser.write(data)
        except serial.SerialTimeoutException:
            log(f"write timed out, reply lost: {data.hex(' ')}")
        except (serial.SerialException, OSError) as exc:
            log(f"serial write failed: {exc}; stopping")
            self.failed = True
            self.stop.set()

    # ------------------------------------------------------------------ requests
    async def worker(self) -> None:
        """Answer frames one at a time, in arrival order."""
        while True:
            frame = await self.frames.get()
            reply = await self.handle(frame)
            if reply is not None:
                if self.args.trace:
                    log(f"tx {reply.hex(' ')}")
                self.write(reply)

    async def handle(self, frame: bytes) -> bytes | None:
        tid, _pid, _length, unit = struct.unpack(">HHHB", frame[:7])
        pdu = frame[7:]
        if self.args.trace:
            log(f"rx frame {frame.hex(' ')}")
        if unit not in self.units:
            if self.args.trace:
                log(f"unit {unit} not served: no reply")
            return None
        if self.args.delay_ms:
            await asyncio.sleep(self.args.delay_ms / 1000)
        fc = pdu[0]
        response = None
        if fc & 0x80 or fc not in self.known_fcs:
            response = ExceptionResponse(fc & 0x7F, ExcCodes.ILLEGAL_FUNCTION)
        elif fc == 5 and (len(pdu) < 5 or pdu[3:5] not in (b"\xff\x00", b"\x00\x00")):
            # pymodbus takes any non-zero value as ON; the spec says FF00/0000 only.
            response = ExceptionResponse(fc, ExcCodes.ILLEGAL_VALUE)
        else:
            request = self.decoder.decode(pdu)
            if request is None:  # bad quantity or truncated data
                response = ExceptionResponse(fc, ExcCodes.ILLEGAL_VALUE)
            else:
                request.dev_id = unit
                request.transaction_id = tid
                try:
                    response = await request.datastore_update(self.context, unit)
                except Exception as exc:  # noqa: BLE001
                    log(f"request failed: {exc!r}")
                    response = ExceptionResponse(fc, ExcCodes.DEVICE_FAILURE)
        response.transaction_id = tid
        response.dev_id = unit
        return self.framer.buildFrame(response)


def parse_args(argv: list[str] | None = None) -> tuple[argparse.Namespace, list[int]]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--port", required=True, help="serial port or pty path")
    p.add_argument("--units", default="1", help="comma list of served unit ids (default 1)")
    p.add_argument("--size", type=int, default=200, help="entries per table (default 200)")
    p.add_argument("--baud", type=int, default=19200)
    p.add_argument("--delay-ms", type=int, default=0, help="answer this late (default 0)")
    p.add_argument("--gap-ms", type=int, default=100, help="discard a stalled partial frame after this (default 100)")
    p.add_argument("--trace", action="store_true", help="log every frame as hex on stderr")
    args = p.parse_args(argv)
    try:
        units = sorted({int(u, 0) for u in args.units.split(",") if u.strip()})
    except ValueError:
        p.error(f"--units: not a comma list of integers: {args.units!r}")
    if not units or any(not 0 <= u <= 255 for u in units):
        p.error("--units: ids must be 0..255")
    if not 1 <= args.size <= 65536:
        p.error("--size must be 1..65536")
    return args, units


async def amain(args: argparse.Namespace, units: list[int]) -> int:
    dev = Device(args, units)
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, dev.stop.set)
    try:
        dev.open()
    except (serial.SerialException, OSError) as exc:
        log(f"cannot open {args.port}: {exc}")
        return 1
    worker = asyncio.create_task(dev.worker())
    log(f"serving units {units} on {args.port} ({args.baud} baud), size {args.size}")
    sys.stdout.write("READY\n")
    sys.stdout.flush()
    await dev.stop.wait()
    worker.cancel()
    dev.close()
    log(f"stopped (dropped {dev.dropped} bytes)")
    return 1 if dev.failed else 0


def main() -> int:
    logging.getLogger("pymodbus").setLevel(logging.ERROR)
    args, units = parse_args()
    return asyncio.run(amain(args, units))


if __name__ == "__main__":
    sys.exit(main())
