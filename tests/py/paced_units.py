#!/usr/bin/env python3
"""pymodbus' ModbusSerialServer (RTU) answering several unit ids, each after its own
delay: a bus of a fast device beside a slow one, for the per-unit and learned timeouts
of tests/e2e/units.rs.

    paced_units.py --port PATH --delays FILE [--baud 4000000]

FILE holds one `unit=seconds` a line (`1=0.02`, `2=0.3`) and is read again before each
request, so the test can change a unit's pace, or kill it (`1=dead`: the unit does not
answer at all, as a device switched off; pymodbus' ignore_missing_devices). Each unit
serves stock_server.py's data, its holding register i (i > 0) being 1000 × unit + i, so a
reply taken for another unit's, or another address's, shows in its value. Prints READY on stdout once serving.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys

from pymodbus import FramerType
from pymodbus.datastore import ModbusServerContext
from pymodbus.exceptions import NoSuchIdException
from pymodbus.server import ModbusSerialServer
import serving
from stock_server import device


def delays(path: str) -> dict[int, float | None]:
    """The file: unit -> seconds, None for a dead unit."""
    out: dict[int, float | None] = {}
    with open(path, encoding="utf-8") as f:
        for line in f:
            if "=" in line:
                unit, value = line.strip().split("=", 1)
                out[int(unit)] = None if value == "dead" else float(value)
    return out


class Paced:
    """The server's datastore, each request to a unit first waiting for that unit's
    delay (the event loop runs on, as a device's processing does not stop the bus);
    a dead unit raises NoSuchIdException, which the server drops without an answer."""

    def __init__(self, core, path: str):
        self.core = core
        self.path = path
        # The unit whose answer is being sent: pymodbus 3.16.1's request handler
        # labels a reply with the unit of the last request it received, which is
        # another's when a request came while this one was still waiting for its
        # delay (after the gateway timed it out); a device on a bus answers with its
        # own id, so `own_id` puts it back as the reply goes out.
        self.answering = None

    async def pace(self, device_id: int) -> None:
        delay = delays(self.path).get(device_id, 0.0)
        if delay is None:
            raise NoSuchIdException(f"unit {device_id} is dead")
        await asyncio.sleep(delay)

    async def async_getValues(self, device_id, *args, **kwargs):
        await self.pace(device_id)
        values = await self.core.async_getValues(device_id, *args, **kwargs)
        self.answering = device_id
        return values

    async def async_setValues(self, device_id, *args, **kwargs):
        await self.pace(device_id)
        result = await self.core.async_setValues(device_id, *args, **kwargs)
        self.answering = device_id
        return result

    def own_id(self, sending: bool, pdu):
        """trace_pdu: a reply goes out with the id of the unit that made it (nothing
        is awaited between the datastore's answer and the send)."""
        if sending and self.answering is not None:
            pdu.dev_id = self.answering
            self.answering = None
        return pdu

    def __getattr__(self, name):
        return getattr(self.core, name)


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", required=True)
    ap.add_argument("--delays", required=True)
    ap.add_argument("--baud", type=int, default=4_000_000)
    ap.add_argument("--size", type=int, default=200)
    args = ap.parse_args()
    logging.basicConfig(level=logging.CRITICAL, stream=sys.stderr)
    units = sorted(delays(args.delays))
    devices = {u: device(args.size, 1000 * u) for u in units}
    hooks: list = []
    server = ModbusSerialServer(
        ModbusServerContext(devices=devices, single=False),
        framer=FramerType.RTU,
        port=args.port,
        baudrate=args.baud,
        ignore_missing_devices=True,
        trace_pdu=lambda sending, pdu: hooks[0](sending, pdu),
    )
    server.context = Paced(server.context, args.delays)
    hooks.append(server.context.own_id)
    return await serving.until_signalled(server)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
