#!/usr/bin/env python3
"""A pymodbus Modbus/TCP master that runs the steps it is given and reports what came back.

    master.py --port N [--host 127.0.0.1] [--timeout 3] [--framer socket|rtu] STEPS_JSON

--framer rtu: RTU over TCP (RTU frames with their CRC on the socket, no MBAP header).

STEPS_JSON is a list of [method, args, kwargs] for pymodbus' ModbusTcpClient, e.g.
[["read_holding_registers", [0], {"count": 2, "device_id": 1}]]. Prints one JSON list,
one entry per step: {"exception": code} for an exception response, {"registers": [...]},
{"bits": [...]} (as pymodbus returns them, padded to whole bytes), {"address": a,
"count": n} or {"address": a, "value": v} for writes, {"error": "..."} for no answer,
{"sent": true} for a request sent with no_response_expected.
The test that runs it holds the expectations.
"""

import argparse
import json
import logging
import sys
import time

from pymodbus import FramerType
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException


def outcome(rr):
    if rr is None:  # no_response_expected=True: sent, nothing awaited
        return {"sent": True}
    if rr.isError():
        return {"exception": rr.exception_code}
    out = {}
    if getattr(rr, "registers", None):
        out["registers"] = list(rr.registers)
    if getattr(rr, "bits", None):
        out["bits"] = [bool(b) for b in rr.bits]
    for key in ("address", "count"):
        if hasattr(rr, key) and rr.function_code in (5, 6, 15, 16):
            out[key] = getattr(rr, key)
    return out


def run_steps(client, steps_json: str, timed: bool = False) -> int:
    """Connects `client`, runs the steps, prints the results as one JSON list; the
    exit code (1: no connection). `timed`: each result also has the seconds its step
    took ("seconds")."""
    if not client.connect():
        print(json.dumps([{"error": "connect failed"}]))
        return 1
    results = []
    for method, args, kwargs in json.loads(steps_json):
        start = time.monotonic()
        try:
            result = outcome(getattr(client, method)(*args, **kwargs))
        except ModbusException as exc:
            result = {"error": f"{type(exc).__name__}: {exc}"}
        if timed:
            result["seconds"] = time.monotonic() - start
        results.append(result)
    client.close()
    print(json.dumps(results))
    return 0


def main() -> int:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    p = argparse.ArgumentParser()
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--timeout", type=float, default=3.0)
    p.add_argument("--framer", choices=["socket", "rtu"], default="socket")
    p.add_argument("steps")
    a = p.parse_args()
    framer = {"socket": FramerType.SOCKET, "rtu": FramerType.RTU}[a.framer]
    client = ModbusTcpClient(a.host, port=a.port, timeout=a.timeout, retries=0, framer=framer)
    return run_steps(client, a.steps)


if __name__ == "__main__":
    sys.exit(main())
