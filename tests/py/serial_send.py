#!/usr/bin/env python3
"""Writes bytes on a serial port at a baud rate with pyserial, waits until they have
left, and exits: garbage put on a line before a test (what a device heard earlier).

    serial_send.py --port PATH --baud 9600 --hex 3A30415A5A
"""

from __future__ import annotations

import argparse
import sys
import time

import serial


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", required=True)
    ap.add_argument("--baud", type=int, default=9600)
    ap.add_argument("--hex", required=True)
    args = ap.parse_args()
    data = bytes.fromhex(args.hex)
    with serial.Serial(args.port, args.baud, timeout=0) as port:
        port.write(data)
        port.flush()
        # A pty's flush does not wait for the far side: the bytes' time on the wire,
        # and a margin, before the port closes.
        time.sleep(len(data) * 11 / args.baud + 0.3)
    return 0


if __name__ == "__main__":
    sys.exit(main())
