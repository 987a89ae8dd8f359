#!/usr/bin/env python3
"""A pymodbus ModbusSerialServer as a device on a serial line: the given unit ids,
framing, baud rate, parity and stop bits; silent for any other unit id
(ignore_missing_devices), as a device on a bus is. stock_server.py's data for each
unit, and a device identification (FC 43/14: vendor "pymodbus-test", product code
"SCAN-<unit>").

    serial_device.py --port PATH --framer rtu|ascii --baud 9600 --parity N|E|O
                     [--stopbits 1|2] --units 3,17 [--echo]
                     [--delay SECONDS] [--late-even SECONDS] [--size 20]
                     [--silence SECONDS]

--echo: the line echoes what the device sends (pymodbus' handle_local_echo discards it).
--delay: every answer waits this long after its request is in (a device's turnaround:
3.5 character times is what Modbus over Serial Line V1.02 §2.5.1.1 lets it keep).
--size: how many of each table's addresses the device has.
--late-even: a read or write of an even register (its first) waits this long instead,
as a device that now and then answers after the master has given up.
The waits are the event loop's (asyncio.sleep): at least that long, longer when the
machine is busy; a request that comes meanwhile is read and answered in its turn.

A scan sends such a device requests at wrong baud rates and parities, which it hears
as garbage. pymodbus 3.16.1 keeps garbage in its receive buffer and may never find a
frame after it; a device on a bus starts afresh after a silence (Modbus over Serial
Line V1.02 §2.5.1.1), so here the buffer is emptied when bytes come after a silence
of 10 character times, and at least 50 ms (longer than 3.5 characters, and than
Python's own pauses, or the virtual line's, on a loaded machine inside a frame);
--silence sets it, for a test that sends no garbage and long frames at a low baud
rate, where a busy machine pauses inside a frame for longer.

Prints READY on stdout once serving, then serves until SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time

from pymodbus import FramerType, ModbusDeviceIdentification
from pymodbus.datastore import ModbusServerContext
from pymodbus.server import ModbusSerialServer
from pymodbus.transport.transport import ModbusProtocol
import serving
from stock_server import context

SILENCE = [0.050]
_received = ModbusProtocol.datagram_received


def _afresh_after_silence(self, data, addr):
    now = time.monotonic()
    if now - getattr(self, "_last_byte", 0.0) > SILENCE[0]:
        self.recv_buffer = b""
    self._last_byte = now  # pylint: disable=protected-access
    _received(self, data, addr)


ModbusProtocol.datagram_received = _afresh_after_silence


class Paced:
    """The server's datastore, each read and write first waiting its delay (the event
    loop runs on, as a device's processing does not stop the bus)."""

    def __init__(self, core, delay: float, late_even: float | None):
        self.core = core
        self.delay = delay
        self.late_even = late_even

    async def pace(self, address: int) -> None:
        wait = self.delay
        if self.late_even is not None and address % 2 == 0:
            wait = self.late_even
        if wait > 0:
            await asyncio.sleep(wait)

    async def async_getValues(self, device_id, func_code, address, count=1):
        await self.pace(address)
        return await self.core.async_getValues(device_id, func_code, address, count)

    async def async_setValues(self, device_id, func_code, address, values):
        await self.pace(address)
        return await self.core.async_setValues(device_id, func_code, address, values)

    def __getattr__(self, name):
        return getattr(self.core, name)


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", required=True)
    ap.add_argument("--framer", choices=["rtu", "ascii"], default="rtu")
    ap.add_argument("--baud", type=int, default=19200)
    ap.add_argument("--parity", choices=["N", "E", "O"], default="N")
    ap.add_argument("--stopbits", type=int, default=1)
    ap.add_argument("--units", default="1")
    ap.add_argument("--echo", action="store_true", help="the line echoes: discard our own replies")
    ap.add_argument("--size", type=int, default=20)
    ap.add_argument("--silence", type=float, default=None)
    ap.add_argument("--delay", type=float, default=0.0)
    ap.add_argument("--late-even", type=float, default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.CRITICAL, stream=sys.stderr)
    units = [int(u) for u in args.units.split(",")]
    SILENCE[0] = args.silence if args.silence is not None else max(0.050, 10 * 11 / args.baud)
    devices = {u: context(args.size, u)._devices[u] for u in units}  # pylint: disable=protected-access
    identity = ModbusDeviceIdentification(
        info_name={"VendorName": "pymodbus-test", "ProductCode": "SCAN", "MajorMinorRevision": "3.16"}
    )

    def unit_of(frame: bytes) -> int:
        if args.framer == "ascii":
            return int(frame[1:3], 16) if len(frame) >= 3 else -1
        return frame[0] if frame else -1

    def silent_for_others(sending: bool, data: bytes) -> bytes:
        # pymodbus 3.16.1 answers an unknown unit with exception 04 even with
        # ignore_missing_devices (its simulator core looks the unit up itself): the
        # reply to any unit but ours is not sent, as a device on a bus stays silent.
        if sending and unit_of(data) not in units:
            return b""
        return data

    server = ModbusSerialServer(
        ModbusServerContext(devices=devices, single=False),
        framer={"rtu": FramerType.RTU, "ascii": FramerType.ASCII}[args.framer],
        identity=identity,
        port=args.port,
        baudrate=args.baud,
        parity=args.parity,
        stopbits=args.stopbits,
        ignore_missing_devices=True,
        handle_local_echo=args.echo,
        trace_packet=silent_for_others,
    )
    if args.delay > 0 or args.late_even is not None:
        server.context = Paced(server.context, args.delay, args.late_even)
    return await serving.until_signalled(server)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
