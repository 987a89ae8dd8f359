#!/usr/bin/env python3
"""pymodbus' ModbusTcpServer as a gateway with devices at the given unit ids: any
other unit gets exception 0x0B (gateway target device failed to respond), as a
gateway answers for a unit nothing answers at. stock_server.py's data for each unit.

    tcp_units.py --port N --units 3,17

Listens on 127.0.0.1:N. Prints READY on stdout once serving; SIGTERM stops it.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys

from pymodbus import FramerType
from pymodbus.datastore import ModbusServerContext
from pymodbus.server import ModbusTcpServer
import serving
from stock_server import context


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--units", default="1")
    args = ap.parse_args()
    logging.basicConfig(level=logging.CRITICAL, stream=sys.stderr)
    units = [int(u) for u in args.units.split(",")]
    devices = {u: context(20, u)._devices[u] for u in units}  # pylint: disable=protected-access

    def gateway_exception(sending: bool, data: bytes) -> bytes:
        # pymodbus 3.16.1 answers an unknown unit with exception 04; a gateway says
        # 0x0B. MBAP: 7 header bytes (the unit last), then the PDU.
        if sending and len(data) >= 9 and data[6] not in units and data[7] & 0x80:
            return data[:8] + b"\x0b"
        return data

    server = ModbusTcpServer(
        ModbusServerContext(devices=devices, single=False),
        framer=FramerType.SOCKET,
        address=("127.0.0.1", args.port),
        trace_packet=gateway_exception,
    )
    return await serving.until_signalled(server)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
