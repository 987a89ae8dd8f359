#!/usr/bin/env python3
"""pymodbus' own ModbusUdpServer, serving stock_server.py's device as unit 1 (holding
register i = 1000 + i): the other end of the loops tests/e2e/udp_hostile.rs tries to start
between it and mbgate's UDP listener. pymodbus answers every datagram it can decode,
even an answer: a reply with `80 01`, an exception with exception 04.

    udp_server.py --port N

Prints READY once serving; then, for each line `count` on stdin, one line
`in DATAGRAMS BYTES out DATAGRAMS BYTES`: what it received and sent so far.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys

from pymodbus.server import ModbusUdpServer

import stock_server

counts = {True: [0, 0], False: [0, 0]}


def trace(sending: bool, data: bytes) -> bytes:
    counts[sending][0] += 1
    counts[sending][1] += len(data)
    return data


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    args = ap.parse_args()
    logging.disable(logging.CRITICAL)
    server = ModbusUdpServer(
        stock_server.context(200),
        address=("127.0.0.1", args.port),
        trace_packet=trace,
    )
    task = asyncio.create_task(server.serve_forever())
    await asyncio.sleep(0.2)
    print("READY", flush=True)
    loop = asyncio.get_running_loop()
    while True:
        line = await loop.run_in_executor(None, sys.stdin.readline)
        if not line:
            break
        if line.strip() == "count":
            (i, ib), (o, ob) = counts[False], counts[True]
            print(f"in {i} {ib} out {o} {ob}", flush=True)
    await server.shutdown()
    task.cancel()
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
