#!/usr/bin/env python3
"""A pymodbus Modbus RTU master on a serial port (pymodbus' ModbusSerialClient with the
RTU framer) that runs the steps it is given and reports what came back.

    rtu_master.py --port PATH [--baud 19200] [--timeout 2] [--timed] STEPS_JSON

STEPS_JSON and the printed results are as in master.py (the Modbus/TCP master);
--timed adds the seconds each step took to its result.
"""

import argparse
import logging
import sys

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient

from master import run_steps


def main() -> int:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    p = argparse.ArgumentParser()
    p.add_argument("--port", required=True)
    p.add_argument("--baud", type=int, default=19200)
    p.add_argument("--timeout", type=float, default=2.0)
    p.add_argument("--timed", action="store_true")
    p.add_argument("steps")
    a = p.parse_args()
    client = ModbusSerialClient(
        a.port, framer=FramerType.RTU, baudrate=a.baud, timeout=a.timeout, retries=0
    )
    return run_steps(client, a.steps, a.timed)


if __name__ == "__main__":
    sys.exit(main())
