#!/usr/bin/env python3
"""A bus of three ends: whatever one end's port receives is written to the other two,
as every station on an RS-485 pair hears every other. Each end is a serial port
(a pty's far side, a virtual line's end) opened with pyserial at --baud. Counts the
bytes each end has sent onto the bus in --counts (a line `END BYTES` each, rewritten
as they change), so a test can show an end sent nothing.

    bus3.py --ends A,B,C --baud 9600 --counts FILE

Prints READY once the ports are open, then runs until SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time

import serial


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--ends", required=True)
    ap.add_argument("--baud", type=int, default=9600)
    ap.add_argument("--counts", required=True)
    args = ap.parse_args()
    running = [True]

    def stop(*_):
        running[0] = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    ports = [serial.Serial(p, args.baud, timeout=0) for p in args.ends.split(",")]
    counts = [0] * len(ports)

    def save() -> None:
        with open(args.counts + ".new", "w", encoding="ascii") as f:
            for i, n in enumerate(counts):
                f.write(f"{i} {n}\n")
        import os

        os.replace(args.counts + ".new", args.counts)

    save()
    print("READY", flush=True)
    while running[0]:
        moved = False
        for i, p in enumerate(ports):
            data = p.read(4096)
            if data:
                moved = True
                counts[i] += len(data)
                for j, q in enumerate(ports):
                    if j != i:
                        q.write(data)
                save()
        if not moved:
            time.sleep(0.0005)
    return 0


if __name__ == "__main__":
    sys.exit(main())
