#!/usr/bin/env python3
"""A raw pyserial Modbus device, independent of pymodbus and of mbgate: one unit id,
RTU or ASCII, answering FC 03 and FC 04 reads for that id only and silent for every
other id, as a device on a bus is (pymodbus answers every id).

    lone_device.py --port PATH --baud 9600 --framer rtu|ascii --unit 17
                   [--delay SECONDS] [--fixed HEX]

Its receiver is a real device's: RTU, a frame is what came between two silences of
more than 3.5 character times (Modbus over Serial Line V1.02 §2.5.1.1; at least 30 ms
here, below), checked by its CRC; ASCII, a frame runs from ':' to LF, a ':' starting afresh (§2.5.2.1), checked by
its LRC. Register N holds N + 1000 (so a reply says which address was read).
Other functions to its id get exception 01.

--delay: each reply waits this long after its request (a slow device).
--fixed: every request, of any id or function, is answered with these bytes as they
are (a device that always sends one frame).

Prints READY once the port is open, then serves until SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time

import serial
from raw_device import crc16


def lrc(data: bytes) -> int:
    return (-sum(data)) & 0xFF


def answer(unit: int, pdu: bytes, mine: int) -> bytes | None:
    """The reply PDU to `pdu` for `unit`, or None (silent)."""
    if unit != mine or not pdu:
        return None
    fc = pdu[0]
    if fc in (3, 4) and len(pdu) == 5:
        address = int.from_bytes(pdu[1:3], "big")
        count = int.from_bytes(pdu[3:5], "big")
        if not 1 <= count <= 125:
            return bytes([fc | 0x80, 3])
        data = b"".join(((address + i + 1000) & 0xFFFF).to_bytes(2, "big") for i in range(count))
        return bytes([fc, len(data)]) + data
    return bytes([(fc | 0x80) & 0xFF, 1])


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", required=True)
    ap.add_argument("--baud", type=int, default=9600)
    ap.add_argument("--framer", choices=["rtu", "ascii"], default="rtu")
    ap.add_argument("--unit", type=int, required=True)
    ap.add_argument("--delay", type=float, default=0.0)
    ap.add_argument("--fixed", default=None)
    args = ap.parse_args()
    fixed = bytes.fromhex(args.fixed) if args.fixed else None
    running = [True]

    def stop(*_):
        running[0] = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    port = serial.Serial(args.port, args.baud, timeout=0)
    # The silence that ends a frame: 3.5 characters on a real line; here at least
    # 30 ms, since a virtual line on a loaded machine, and Python's own reads, pause
    # up to about 9 ms inside a frame (measured at 9600 baud behind `mbgate wire`
    # with 5 builds beside it). A scan leaves 50 ms and more between its requests.
    char = 11 / args.baud
    gap = max(3.5 * char, 0.030)
    print("READY", flush=True)
    buf = b""
    last = time.monotonic()

    def reply(unit: int, pdu: bytes) -> None:
        if fixed is not None:
            out = fixed
        else:
            rep = answer(unit, pdu, args.unit)
            if rep is None:
                return
            if args.framer == "rtu":
                frame = bytes([unit]) + rep
                out = frame + crc16(frame)
            else:
                frame = bytes([unit]) + rep
                out = b":" + (frame + bytes([lrc(frame)])).hex().upper().encode() + b"\r\n"
        if args.delay > 0:
            time.sleep(args.delay)
        port.write(out)

    while running[0]:
        chunk = port.read(512)
        now = time.monotonic()
        if not chunk:
            time.sleep(0.0005)
            continue
        if args.framer == "rtu":
            if now - last > gap:
                buf = b""
            last = now
            buf += chunk
            if len(buf) >= 4 and crc16(buf[:-2]) == buf[-2:]:
                frame, buf = buf, b""
                reply(frame[0], frame[1:-2])
        else:
            for b in chunk:
                c = bytes([b])
                if c == b":":
                    buf = c
                elif buf:
                    buf += c
                    if c == b"\n":
                        line, buf = buf, b""
                        try:
                            raw = bytes.fromhex(line[1:-2].decode())
                        except ValueError:
                            continue
                        if len(raw) >= 3 and lrc(raw[:-1]) == raw[-1]:
                            reply(raw[0], raw[1:-1])
                    elif len(buf) > 520:
                        buf = b""
    return 0


if __name__ == "__main__":
    sys.exit(main())
