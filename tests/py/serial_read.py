#!/usr/bin/env python3
"""pymodbus' ModbusSerialClient reads one holding register once: prints
"REPLY <value>" or "NO REPLY" (nothing valid within --timeout seconds).

    serial_read.py --port PATH --framer rtu|ascii --baud 9600 --parity N|E|O --unit 1
"""

from __future__ import annotations

import argparse
import logging
import sys

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", required=True)
    ap.add_argument("--framer", choices=["rtu", "ascii"], default="rtu")
    ap.add_argument("--baud", type=int, default=19200)
    ap.add_argument("--parity", choices=["N", "E", "O"], default="N")
    ap.add_argument("--unit", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=1.0)
    args = ap.parse_args()
    logging.basicConfig(level=logging.CRITICAL, stream=sys.stderr)
    client = ModbusSerialClient(
        args.port,
        framer={"rtu": FramerType.RTU, "ascii": FramerType.ASCII}[args.framer],
        baudrate=args.baud,
        parity=args.parity,
        timeout=args.timeout,
        retries=0,
    )
    if not client.connect():
        print("NO PORT", flush=True)
        return 1
    try:
        rr = client.read_holding_registers(0, count=1, device_id=args.unit)
        if rr.isError():
            print(f"EXCEPTION {rr}", flush=True)
        else:
            print(f"REPLY {rr.registers[0]}", flush=True)
    except Exception as exc:  # pylint: disable=broad-except
        print(f"NO REPLY {type(exc).__name__}", flush=True)
    finally:
        client.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
