#!/usr/bin/env python3
"""pymodbus' own ModbusTcpServer as the Modbus/TCP slave a master line reaches.

    tcp_slave.py --port N [--unit 1] [--base 0] [--size 100]

One unit (--unit). Data (PDU
addresses, 0-based): holding register i = base + i except 0..=15 which start at 0
(the CIE-M10 port registers: inputs at 0, outputs at 8), input register i = base + 500
+ i, coil i ON when (i + base) % 3 == 0, discrete input i ON when (i + base) % 2 == 0.
Prints READY on stdout once serving; SIGTERM stops it.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys

from pymodbus.datastore import (
    ModbusDeviceContext,
    ModbusSequentialDataBlock,
    ModbusServerContext,
)
from pymodbus.server import ModbusTcpServer
import serving


def context(unit: int, base: int, size: int) -> ModbusServerContext:
    hr = [0] * 16 + [base + i for i in range(16, size)]
    device = ModbusDeviceContext(
        co=ModbusSequentialDataBlock(1, [(i + base) % 3 == 0 for i in range(size)]),
        di=ModbusSequentialDataBlock(1, [(i + base) % 2 == 0 for i in range(size)]),
        hr=ModbusSequentialDataBlock(1, hr),
        ir=ModbusSequentialDataBlock(1, [base + 500 + i for i in range(size)]),
    )
    return ModbusServerContext(devices={unit: device}, single=False)


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--unit", type=int, default=1)
    ap.add_argument("--base", type=int, default=0)
    ap.add_argument("--size", type=int, default=100)
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)
    server = ModbusTcpServer(
        context(args.unit, args.base, args.size), address=("127.0.0.1", args.port)
    )
    return await serving.until_signalled(server)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
