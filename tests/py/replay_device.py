#!/usr/bin/env python3
"""A pymodbus RTU server with several units, the device tests/e2e/replay.rs records through
the gateway and then replays (mbgate sim --replay).

    replay_device.py --port PATH [--baud 19200] [--delay-ms MS] [--framer rtu|ascii|socket]

Units (PDU addresses, 0-based; any address past a table is exception 02, pymodbus'
own answer; a unit id not listed gets no answer):
  1: coils 0-15 (ON when i % 3 == 0), holding registers 0-19 (100 + i), input
     registers 0-9 (200 + i);
  2: coils 0-7 (ON when i % 2 == 0), holding registers 0-9 (3000 + 7 i), input
     registers 0-19 (4000 + i);
  3: input register 0 a counter: tenths of a second since the server started, as
     read; input register 1 and holding registers 0-3 zero.
--framer: RTU (the default), ASCII, or MBAP on the serial line (socket).
--delay-ms: units 1 and 2 take this long over each request, as a device's own
processing does (a PLC's scan, a meter's), on top of pymodbus' own time.
Prints READY on stdout once serving, then serves until SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time

from pymodbus import FramerType
from pymodbus.datastore import (
    ModbusDeviceContext,
    ModbusSequentialDataBlock,
    ModbusServerContext,
)
from pymodbus.server import ModbusSerialServer
import serving

STARTED = time.monotonic()
DELAY_S = 0.0


async def counter(function_code, start_address, address, count, registers, values):
    """Unit 3's input register 0 counts tenths of a second whenever it is read."""
    if function_code == 4 and values is None:
        at = 0 - start_address
        if 0 <= at < len(registers):
            registers[at] = int((time.monotonic() - STARTED) * 10) & 0xFFFF
    return None


async def slow(function_code, start_address, address, count, registers, values):
    """Units 1 and 2's processing time (--delay-ms)."""
    if DELAY_S:
        await asyncio.sleep(DELAY_S)
    return None


def block(values):
    # ModbusSequentialDataBlock(1, ...) puts PDU address 0 at values[0].
    return ModbusSequentialDataBlock(1, values)


def context() -> ModbusServerContext:
    one = ModbusDeviceContext(
        co=block([i % 3 == 0 for i in range(16)]),
        di=block([False] * 8),
        hr=block([100 + i for i in range(20)]),
        ir=block([200 + i for i in range(10)]),
    )
    two = ModbusDeviceContext(
        co=block([i % 2 == 0 for i in range(8)]),
        di=block([True] * 8),
        hr=block([3000 + 7 * i for i in range(10)]),
        ir=block([4000 + i for i in range(20)]),
    )
    three = ModbusDeviceContext(
        co=block([False] * 8),
        di=block([False] * 8),
        hr=block([0] * 4),
        ir=block([0, 0]),
    )
    one.simdevice.action = slow
    two.simdevice.action = slow
    three.simdevice.action = counter
    return ModbusServerContext(devices={1: one, 2: two, 3: three}, single=False)


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", required=True)
    ap.add_argument("--baud", type=int, default=19200)
    ap.add_argument("--delay-ms", type=float, default=0.0)
    ap.add_argument("--framer", choices=["rtu", "ascii", "socket"], default="rtu")
    args = ap.parse_args()
    global DELAY_S
    DELAY_S = args.delay_ms / 1000
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    server = ModbusSerialServer(
        context(),
        framer={"rtu": FramerType.RTU, "ascii": FramerType.ASCII, "socket": FramerType.SOCKET}[args.framer],
        port=args.port,
        baudrate=args.baud,
    )
    return await serving.until_signalled(server)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
