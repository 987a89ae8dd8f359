#!/usr/bin/env python3
"""A pymodbus ModbusSerialClient (RTU) polling as a plant's master does: FC 03 of
unit A and FC 04 of unit B in turn, every --every seconds, until SIGTERM or SIGINT.

    rtu_poller.py --port PATH --baud 9600 --units 5,9 [--every 0.1]

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
    ap.add_argument("--every", type=float, default=0.1)
    args = ap.parse_args()
    logging.basicConfig(level=logging.CRITICAL, stream=sys.stderr)
    a, b = (int(u) for u in args.units.split(","))
    running = [True]

    def stop(*_):
        running[0] = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    client = ModbusSerialClient(args.port, framer=FramerType.RTU, baudrate=args.baud, timeout=1, retries=0)
    if not client.connect():
        return 1
    print("READY", flush=True)
    while running[0]:
        try:
            client.read_holding_registers(0, count=2, device_id=a)
            time.sleep(args.every)
            client.read_input_registers(1, count=1, device_id=b)
        except Exception:  # pylint: disable=broad-except
            pass
        time.sleep(args.every)
    client.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
