#!/usr/bin/env python3
"""Several pymodbus ModbusSerialServers in one process, each stock_server.py's device
(its data, unit 1) on its own serial port or pty, in its own framing, at its own
baud rate: the third-party devices of tests/e2e/third_party.rs, started once for all.

    serial_servers.py --serve FRAMER:PATH:BAUD [--serve ...] [--size 200]

FRAMER is socket (MBAP on the serial line), rtu or ascii. On a pty nothing paces
pymodbus: each answers as soon as the request is in, whatever BAUD says (its FC 05
and 06 replies are byte for byte the request). Prints READY on stdout once all serve,
then serves until SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys

from pymodbus import FramerType
from pymodbus.server import ModbusSerialServer
from stock_server import context

FRAMERS = {"socket": FramerType.SOCKET, "rtu": FramerType.RTU, "ascii": FramerType.ASCII}


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--serve", action="append", required=True, help="FRAMER:PATH:BAUD")
    ap.add_argument("--size", type=int, default=200)
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)
    servers = []
    for spec in args.serve:
        framer, path, baud = spec.split(":")
        servers.append(
            ModbusSerialServer(context(args.size), framer=FRAMERS[framer], port=path, baudrate=int(baud))
        )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    for server in servers:
        await server.serve_forever(background=True)
    print("READY", flush=True)
    await stop.wait()
    for server in servers:
        await server.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
