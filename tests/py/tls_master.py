#!/usr/bin/env python3
"""A Modbus/TCP Security master as users run one: pymodbus' AsyncModbusTlsClient with a
Python ssl.SSLContext (the CA that signed the gateway's certificate, and the master's
own certificate and key), for the TLS tests of mbgate (docs/security.md).

    tls_master.py --port N --ca CA.pem [--cert C.pem --key C.key] [--unit 1]

Reads commands on stdin, one a line, and answers each with one JSON line on stdout:

    connect               pymodbus connects: {"ok": bool}
    read ADDR COUNT       FC 03: {"ok": true, "registers": [...]} or {"ok": false,
                          "exception": CODE} or {"ok": false, "error": TEXT}
    write ADDR VALUE      FC 06, the same answers
    handshake             a raw ssl socket: the handshake, then one FC 03 request of
                          register 0; {"ok": bool, "error": TEXT, "protocol": "TLSv1.3",
                          "subject": the gateway certificate's CN}
    rtu-read              the same over an RTU-over-TCP listener: the RTU frame of an
                          FC 03 read of register 0 (unit 1, CRC); {"ok", "reply"}
    stall                 opens a plain TCP connection to the port that never sends a
                          byte (a master stuck before its handshake): {"ok": true}
    stalled               {"open": bool}: has the gateway not closed it yet?
    quit

Each request: 3 s timeout, no retries. Prints READY once it reads commands.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import socket
import ssl
import struct
import sys
import time

from pymodbus.client import AsyncModbusTlsClient
from pymodbus.exceptions import ModbusException


def context(args) -> ssl.SSLContext:
    ctx = ssl.create_default_context(cafile=args.ca)
    if args.cert:
        ctx.load_cert_chain(args.cert, args.key)
    return ctx


# FC 03, unit 1, register 0, count 1, with its CRC-16.
RTU_READ = bytes.fromhex("010300000001840a")


def handshake(args, rtu: bool = False) -> dict:
    """The TLS handshake alone with a raw socket, then one read of register 0: with TLS
    1.3 a refused client certificate shows only when the server's alert arrives, after
    the client's side of the handshake is done."""
    ctx = context(args)
    out: dict = {"ok": False}
    try:
        with socket.create_connection(("127.0.0.1", args.port), timeout=5) as raw:
            with ctx.wrap_socket(raw, server_hostname="localhost") as s:
                out["protocol"] = s.version()
                subject = dict(x[0] for x in s.getpeercert()["subject"])
                out["subject"] = subject.get("commonName")
                if rtu:
                    s.sendall(RTU_READ)
                else:
                    s.sendall(struct.pack(">HHHBBHH", 7, 0, 6, args.unit, 3, 0, 1))
                reply = b""
                want = 7 if rtu else 1
                while len(reply) < want:
                    got = s.recv(260)
                    if not got:
                        break
                    reply += got
                if not reply:
                    out["error"] = "closed by the gateway"
                else:
                    out["ok"] = True
                    out["reply"] = reply.hex()
    except (ssl.SSLError, OSError) as exc:
        out["error"] = f"{type(exc).__name__}: {exc}"
    return out


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--ca", required=True)
    ap.add_argument("--cert")
    ap.add_argument("--key")
    ap.add_argument("--unit", type=int, default=1)
    args = ap.parse_args()
    logging.basicConfig(level=logging.CRITICAL, stream=sys.stderr)
    client = AsyncModbusTlsClient(
        "127.0.0.1", port=args.port, sslctx=context(args), timeout=3, retries=0
    )
    stalled: socket.socket | None = None
    loop = asyncio.get_running_loop()
    print("READY", flush=True)
    while True:
        line = await loop.run_in_executor(None, sys.stdin.readline)
        words = line.split()
        if not words or words[0] == "quit":
            break
        cmd, rest = words[0], [int(w, 0) for w in words[1:]]
        started = time.monotonic()
        out: dict
        if cmd == "connect":
            out = {"ok": bool(await client.connect())}
        elif cmd in ("read", "write"):
            try:
                if cmd == "read":
                    rr = await client.read_holding_registers(rest[0], count=rest[1], device_id=args.unit)
                else:
                    rr = await client.write_register(rest[0], rest[1], device_id=args.unit)
                if rr.isError():
                    out = {"ok": False, "exception": rr.exception_code}
                else:
                    out = {"ok": True, "registers": list(getattr(rr, "registers", []) or [])}
            except ModbusException as exc:
                out = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        elif cmd == "handshake":
            out = await loop.run_in_executor(None, handshake, args)
        elif cmd == "rtu-read":
            out = await loop.run_in_executor(None, handshake, args, True)
        elif cmd == "stall":
            stalled = socket.create_connection(("127.0.0.1", args.port), timeout=5)
            stalled.setblocking(False)
            out = {"ok": True}
        elif cmd == "stalled":
            try:
                data = stalled.recv(1, socket.MSG_PEEK)
                out = {"open": False, "got": data.hex()}
            except BlockingIOError:
                out = {"open": True}
            except OSError as exc:
                out = {"open": False, "error": str(exc)}
        else:
            out = {"ok": False, "error": f"unknown command {cmd}"}
        out["ms"] = round(1000 * (time.monotonic() - started), 1)
        print(json.dumps(out), flush=True)
    client.close()
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
