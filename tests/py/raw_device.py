#!/usr/bin/env python3
"""A raw RTU device on a serial port, written with nothing but os and termios (no
pymodbus, nothing of mbgate's): it answers as a misbehaving or stalling device does,
to attack the gateway's rule that a reply answers its request or nothing.

    raw_device.py --port PATH --unit 1 MODE [options]

Modes:
  fixed HEX        answers every request it reads with the PDU HEX (unit and CRC
                   added), whatever was asked: `fixed 0302002A` is an FC 03 reply of
                   one register 0x002A, `fixed 8602` an FC 06 exception.
  registers        an honest device: FC 03 and 04 reads give each register its
                   address plus 1000, FC 06 and 16 writes are echoed as the
                   specification asks; silent for other unit ids, as a bus device is.
    --stall-after N --stall-for S [--drain S]
                   (with registers) after answering N requests, stops reading for S
                   seconds (a hung firmware, an adapter that stops draining); then
                   reads everything that waited and answers every request in it, in
                   order: its backlog, at once, or with --drain one answer every S
                   seconds (the first S seconds after the stall). Requests that came
                   meanwhile are answered after it, in order, as usual.
    --slow-every N --slow S --fast S
                   (with registers) answers each request after `fast` seconds, but
                   every Nth (counting from 1) after `slow` seconds.
    --extra-every N --extra before|after --extra-gap S [--extra-from M]
                   (with registers) every Nth answer (counting from 1; from the Mth
                   on) comes with an extra frame: a CRC-valid reply of the right shape
                   for the address before the one asked (FC 03/04: the registers from
                   address - 1; a write: its echo at address - 1), written `gap`
                   seconds before (`before`) or after (`after`) the real one. A device
                   that sends one frame too many: the gateway must never hand either
                   frame to the wrong request.

Requests are told apart by their function code's length (FC 01-06: 8 bytes; FC
0F/10: 9 + byte count), so a backlog read in one go splits into its requests.
Prints READY on stdout once the port is open, and serves until SIGTERM.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import sys
import termios
import time
import tty


def crc16(data: bytes) -> bytes:
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes([crc & 0xFF, crc >> 8])


def request_length(buf: bytes) -> int | None:
    """The length of the RTU request at the start of `buf`, if known yet."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (0x0F, 0x10):
        return 9 + buf[6] if len(buf) >= 7 else None
    return 8


def split(buf: bytes) -> tuple[list[bytes], bytes]:
    """Whole requests with a good CRC off the front of `buf`, and the rest; bytes that
    make no request are dropped one at a time."""
    frames = []
    while True:
        n = request_length(buf)
        if n is None or len(buf) < n:
            return frames, buf
        frame = buf[:n]
        if crc16(frame[:-2]) == frame[-2:]:
            frames.append(frame)
            buf = buf[n:]
        else:
            buf = buf[1:]


def answer(args, frame: bytes, shift: int = 0) -> bytes | None:
    """The reply to `frame`, or None for a unit this device is not; `shift` answers as
    if the request's address were that much lower (the extra frame)."""
    unit, pdu = frame[0], frame[1:-2]
    if unit != args.unit:
        return None
    if args.mode == "fixed":
        out = bytes.fromhex(args.hex)
    else:
        fc = pdu[0]
        addr = (int.from_bytes(pdu[1:3], "big") - shift) & 0xFFFF
        pdu = pdu[:1] + addr.to_bytes(2, "big") + pdu[3:]
        if fc in (3, 4):
            count = int.from_bytes(pdu[3:5], "big")
            regs = b"".join(((addr + i + 1000) & 0xFFFF).to_bytes(2, "big") for i in range(count))
            out = bytes([fc, len(regs)]) + regs
        elif fc == 6:
            out = pdu
        elif fc == 16:
            out = pdu[:5]
        else:
            out = bytes([fc | 0x80, 1])
    body = bytes([unit]) + out
    return body + crc16(body)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", required=True)
    ap.add_argument("--unit", type=int, default=1)
    ap.add_argument("mode", choices=["fixed", "registers"])
    ap.add_argument("hex", nargs="?", default="")
    ap.add_argument("--stall-after", type=int, default=0)
    ap.add_argument("--stall-for", type=float, default=0.0)
    ap.add_argument("--slow-every", type=int, default=0)
    ap.add_argument("--slow", type=float, default=0.0)
    ap.add_argument("--fast", type=float, default=0.0)
    ap.add_argument("--drain", type=float, default=0.0)
    ap.add_argument("--extra-every", type=int, default=0)
    ap.add_argument("--extra", choices=["before", "after"], default="before")
    ap.add_argument("--extra-gap", type=float, default=0.0)
    ap.add_argument("--extra-from", type=int, default=0)
    args = ap.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    fd = os.open(args.port, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    attrs = termios.tcgetattr(fd)
    attrs[3] &= ~termios.ECHO
    termios.tcsetattr(fd, termios.TCSANOW, attrs)
    print("READY", flush=True)
    buf, answered, stalled, draining = b"", 0, False, False
    while True:
        ready, _, _ = select.select([fd], [], [], 0.002 if buf else 1.0)
        if ready:
            buf += os.read(fd, 4096)
        elif buf:
            # A silence: what is left is no request (RTU ends a frame at silence).
            buf = b""
        frames, buf = split(buf)
        # The requests read right after the stall are its backlog.
        backlog, draining = draining and bool(frames), draining and not frames
        for frame in frames:
            reply = answer(args, frame)
            if reply is None:
                continue
            answered += 1
            if backlog and args.drain:
                time.sleep(args.drain)
            elif args.slow_every and answered % args.slow_every == 0:
                time.sleep(args.slow)
            elif args.fast:
                time.sleep(args.fast)
            extra = (
                args.extra_every
                and answered % args.extra_every == 0
                and answered >= args.extra_from
            )
            if extra and args.extra == "before":
                os.write(fd, answer(args, frame, shift=1))
                time.sleep(args.extra_gap)
            os.write(fd, reply)
            if extra and args.extra == "after":
                time.sleep(args.extra_gap)
                os.write(fd, answer(args, frame, shift=1))
            if args.stall_after and answered == args.stall_after and not stalled:
                stalled, draining = True, True
                # Reads nothing meanwhile: what the gateway writes waits for it.
                time.sleep(args.stall_for)


if __name__ == "__main__":
    sys.exit(main())
