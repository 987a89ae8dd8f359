#!/usr/bin/env python3
"""A pymodbus ModbusSerialClient polling as a plant's master does: a read of unit A
and a read of unit B in turn (FC 03 of A and FC 04 of B unless --functions says
otherwise), every --every seconds, until SIGTERM or SIGINT. With --retries a request
that gets no reply in --timeout is sent again, byte for byte, as pymodbus does.

    rtu_poller.py --port PATH --baud 9600 --units 5,9 [--every 0.1]
                  [--framer rtu|ascii] [--functions 3,4] [--timeout 1] [--retries 0]

Prints READY once the port is open.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import time

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", required=True)
    ap.add_argument("--baud", type=int, default=9600)
    ap.add_argument("--units", default="5,9")
    ap.add_argument("--functions", default="3,4")
    ap.add_argument("--every", type=float, default=0.1)
    ap.add_argument("--framer", choices=["rtu", "ascii"], default="rtu")
    ap.add_argument("--timeout", type=float, default=1.0)
    ap.add_argument("--retries", type=int, default=0)
    args = ap.parse_args()
    logging.basicConfig(level=logging.CRITICAL, stream=sys.stderr)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    units = [int(u) for u in args.units.split(",")]
    functions = [int(f) for f in args.functions.split(",")]
    running = [True]

    def stop(*_):
        running[0] = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    client = ModbusSerialClient(
        args.port,
        framer={"rtu": FramerType.RTU, "ascii": FramerType.ASCII}[args.framer],
        baudrate=args.baud,
        timeout=args.timeout,
        retries=args.retries,
    )
    if not client.connect():
        return 1
    print("READY", flush=True)
    read = {3: client.read_holding_registers, 4: client.read_input_registers}
    while running[0]:
        for unit, function in zip(units, functions):
            if not running[0]:
                break
            try:
                if function in read:
                    read[function](0 if function == 3 else 1, count=2 if function == 3 else 1, device_id=unit)
                elif function == 6:
                    client.write_register(1, 7, device_id=unit)
            except Exception:  # pylint: disable=broad-except
                pass
            time.sleep(args.every)
    client.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
