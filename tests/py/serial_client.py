#!/usr/bin/env python3
"""Talk MBAP directly to device.py over a serial port (checks device.py itself).

    serial_client.py --port PATH [--unit 1] [--address 0] [--count 3] [--baud 19200] [--timeout 1]
    serial_client.py --port PATH --raw HEX [--raw HEX ...] [--timeout 1]

Default mode: pymodbus' serial client reads holding registers with MBAP framing and
prints one JSON line: {"unit": 1, "address": 0, "registers": [...]} (exit 0),
{"unit": 1, ..., "exception": 2} (exit 3) or {"unit": 1, ..., "timeout": true} (exit 4).

pymodbus' serial clients refuse FramerType.SOCKET, so the client is built with RTU and
its transaction manager then gets a socket framer (``client.ctx.framer``).

--raw mode: write each HEX frame as is (spaces allowed; all of one --raw in one write),
collect what comes back within --timeout, print one JSON line per --raw with
{"sent": hex, "received": hex}. For framing cross-checks and back-to-back tests.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
import time

import serial

from pymodbus.client import AsyncModbusSerialClient
from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerSocket, FramerType
from pymodbus.pdu import DecodePDU


async def read_registers(args: argparse.Namespace) -> int:
    client = AsyncModbusSerialClient(
        args.port,
        framer=FramerType.RTU,
        baudrate=args.baud,
        timeout=args.timeout,
        retries=0,
        reconnect_delay=0,
    )
    client.ctx.framer = FramerSocket(DecodePDU(False))
    result = {"unit": args.unit, "address": args.address, "count": args.count}
    if not await client.connect():
        print(f"serial_client: cannot open {args.port}", file=sys.stderr)
        return 2
    try:
        rr = await client.read_holding_registers(args.address, count=args.count, device_id=args.unit)
    except ModbusException as exc:  # no reply within --timeout
        result["timeout"] = True
        print(f"serial_client: {exc}", file=sys.stderr)
        code = 4
    else:
        if rr.isError():
            result["exception"] = rr.exception_code
            code = 3
        else:
            result["registers"] = list(rr.registers)
            code = 0
    finally:
        client.close()
    print(json.dumps(result), flush=True)
    return code


def raw(args: argparse.Namespace) -> int:
    with serial.Serial(args.port, baudrate=args.baud, timeout=0, exclusive=True) as ser:
        ser.reset_input_buffer()
        for hx in args.raw:
            frame = bytes.fromhex(hx)
            ser.write(frame)
            got = b""
            deadline = time.monotonic() + args.timeout
            while time.monotonic() < deadline:
                got += ser.read(4096)
                time.sleep(0.005)
            print(json.dumps({"sent": frame.hex(" "), "received": got.hex(" ")}), flush=True)
    return 0


def main() -> int:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--port", required=True)
    p.add_argument("--unit", type=int, default=1)
    p.add_argument("--address", type=int, default=0)
    p.add_argument("--count", type=int, default=3)
    p.add_argument("--baud", type=int, default=19200)
    p.add_argument("--timeout", type=float, default=1.0, help="seconds to wait for a reply")
    p.add_argument("--raw", action="append", metavar="HEX", help="send these bytes instead")
    args = p.parse_args()
    if args.raw:
        return raw(args)
    return asyncio.run(read_registers(args))


if __name__ == "__main__":
    sys.exit(main())
