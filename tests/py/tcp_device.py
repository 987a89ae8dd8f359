#!/usr/bin/env python3
"""pymodbus' own ModbusTcpServer: a Modbus/TCP device on the network, for the tests of
a line on TCP (README "A device on the network").

    tcp_device.py --port N [--unit 1] [--size 200]

Listens on 127.0.0.1:N. One unit (id --unit); the data of stock_server.py: holding
register 0 = 0x00FF, holding register i = 1000 + i, input register i = 2000 + i.
Prints READY on stdout once serving; SIGTERM stops it (and closes its connections).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys

from pymodbus.server import ModbusTcpServer
import serving
from stock_server import context


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--unit", type=int, default=1)
    ap.add_argument("--size", type=int, default=200)
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)
    # A unit it does not have is answered exception 04 (the tests ask for one on
    # purpose): no traceback for it.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

    server = ModbusTcpServer(context(args.size, args.unit), address=("127.0.0.1", args.port))
    return await serving.until_signalled(server)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
