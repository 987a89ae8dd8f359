#!/usr/bin/env python3
"""pymodbus' own ModbusSerialServer with the socket (MBAP) framer: the stock device the
issue names for the byte-exact CIE-M10 examples and the ordinary-client test; with
--framer rtu or ascii, the stock RTU or ASCII device.

    stock_server.py --port PATH [--size 200] [--baud 19200] [--framer socket|rtu|ascii]
                    [--broadcast]

--broadcast: unit 0 is a broadcast (pymodbus' broadcast_enable): writes act on every
unit, and nothing is answered.

One unit (id 1; pymodbus answers other ids with exception 04). Data (PDU addresses, 0-based):
holding register 0 = 0x00FF (the CIE-M10 inputs 0..7 ON), holding register i = 1000 + i,
input register i = 2000 + i, coil i ON when i % 3 == 0, discrete input i ON when
i % 2 == 0. Prints READY on stdout once serving. It handles one request at a time and
does not resynchronise after garbage (pymodbus 3.16.1 behaviour), so the gateway must feed it
one frame at a time, which it does with max_in_flight = 1.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys

from pymodbus import FramerType
from pymodbus.datastore import (
    ModbusDeviceContext,
    ModbusSequentialDataBlock,
    ModbusServerContext,
)
from pymodbus.server import ModbusSerialServer
import serving


def context(size: int, unit: int = 1) -> ModbusServerContext:
    """The data above, as unit `unit` (tcp_device.py serves it too)."""
    return ModbusServerContext(devices={unit: device(size)}, single=False)


def device(size: int, base: int = 1000) -> ModbusDeviceContext:
    """One device with the data above, holding register i (i > 0) base + i
    (paced_units.py serves several, each its own base)."""
    # ModbusSequentialDataBlock(1, ...) puts PDU address 0 at values[0].
    return ModbusDeviceContext(
        co=ModbusSequentialDataBlock(1, [i % 3 == 0 for i in range(size)]),
        di=ModbusSequentialDataBlock(1, [i % 2 == 0 for i in range(size)]),
        hr=ModbusSequentialDataBlock(1, [0x00FF] + [base + i for i in range(1, size)]),
        ir=ModbusSequentialDataBlock(1, [2000 + i for i in range(size)]),
    )


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", required=True)
    ap.add_argument("--size", type=int, default=200)
    ap.add_argument("--baud", type=int, default=19200)
    ap.add_argument("--framer", choices=["socket", "rtu", "ascii"], default="socket")
    ap.add_argument("--broadcast", action="store_true")
    args = ap.parse_args()
    framer = {"socket": FramerType.SOCKET, "rtu": FramerType.RTU, "ascii": FramerType.ASCII}[args.framer]
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)

    server = ModbusSerialServer(
        context(args.size),
        framer=framer,
        port=args.port,
        baudrate=args.baud,
        broadcast_enable=args.broadcast,
    )
    return await serving.until_signalled(server)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
