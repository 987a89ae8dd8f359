#!/usr/bin/env python3
"""A pymodbus Modbus/TCP master that polls until it is stopped, as a SCADA does: reads
holding register 0 (count 1) of one unit every EVERY seconds, and opens a new
connection whenever the gateway is gone (refused, closed, no answer).

    poller.py --port N [--host 127.0.0.1] --unit 1 [--every 0.2] [--timeout 2]

Prints READY once started, then polls until SIGTERM or SIGINT. It prints nothing
else: the test that runs it watches what the gateway and Prometheus say.
"""

import argparse
import logging
import signal
import sys
import time

from pymodbus.client import ModbusTcpClient

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--unit", type=int, default=1)
    ap.add_argument("--every", type=float, default=0.2)
    ap.add_argument("--timeout", type=float, default=2.0)
    a = ap.parse_args()
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    print("READY", flush=True)
    client = None
    while not stop:
        try:
            if client is None:
                client = ModbusTcpClient(a.host, port=a.port, timeout=a.timeout, retries=0)
                if not client.connect():
                    raise ConnectionError("not connected")
            # An exception reply (0x0A, 0x0B) is an answer: the connection stays.
            client.read_holding_registers(0, count=1, device_id=a.unit)
        except Exception:  # noqa: BLE001 - any failure: a new connection next time
            if client is not None:
                client.close()
            client = None
        time.sleep(a.every)
    if client is not None:
        client.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
