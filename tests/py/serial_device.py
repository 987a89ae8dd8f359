#!/usr/bin/env python3
"""A pymodbus ModbusSerialServer as a device on a serial line: the given unit ids,
framing, baud rate, parity and stop bits; silent for any other unit id
(ignore_missing_devices), as a device on a bus is. stock_server.py's data for each
unit, and a device identification (FC 43/14: vendor "pymodbus-test", product code
"SCAN-<unit>").

    serial_device.py --port PATH --framer rtu|ascii --baud 9600 --parity N|E|O
                     [--stopbits 1|2] --units 3,17 [--echo]

--echo: the line echoes what the device sends (pymodbus' handle_local_echo discards it).

A scan sends such a device requests at wrong baud rates and parities, which it hears
as garbage. pymodbus 3.16.1 keeps garbage in its receive buffer and may never find a
frame after it; a device on a bus starts afresh after a silence (Modbus over Serial
Line V1.02 §2.5.1.1), so here the buffer is emptied when bytes come after a silence
of 10 character times, and at least 50 ms (longer than 3.5 characters, and than
Python's own pauses, or the virtual line's, on a loaded machine inside a frame).

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


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", required=True)
    ap.add_argument("--framer", choices=["rtu", "ascii"], default="rtu")
    ap.add_argument("--baud", type=int, default=19200)
    ap.add_argument("--parity", choices=["N", "E", "O"], default="N")
    ap.add_argument("--stopbits", type=int, default=1)
    ap.add_argument("--units", default="1")
    ap.add_argument("--echo", action="store_true", help="the line echoes: discard our own replies")
    args = ap.parse_args()
    logging.basicConfig(level=logging.CRITICAL, stream=sys.stderr)
    units = [int(u) for u in args.units.split(",")]
    SILENCE[0] = max(0.050, 10 * 11 / args.baud)
    devices = {u: context(20, u)._devices[u] for u in units}  # pylint: disable=protected-access
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
    return await serving.until_signalled(server)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
