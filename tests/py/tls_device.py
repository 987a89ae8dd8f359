#!/usr/bin/env python3
"""pymodbus' own ModbusTlsServer: a Modbus/TCP Security device on the network that
requires a client certificate, for the tests of mbgate as a TLS client of a device
(docs/security.md "A device behind TLS").

    tls_device.py --port N --cert C.pem --key C.key --ca CA.pem [--unit 1]

Listens on 127.0.0.1:N with TLS 1.2 or later; a client must present a certificate that
chains to CA.pem. The data of stock_server.py (holding register i = 1000 + i, register
0 = 0x00FF). Prints READY once serving; SIGTERM stops it.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import ssl
import sys

from pymodbus.server import ModbusTlsServer
import serving
from stock_server import context


async def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--cert", required=True)
    ap.add_argument("--key", required=True)
    ap.add_argument("--ca", required=True)
    ap.add_argument("--unit", type=int, default=1)
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.load_cert_chain(args.cert, args.key)
    ctx.load_verify_locations(args.ca)
    ctx.verify_mode = ssl.CERT_REQUIRED
    server = ModbusTlsServer(context(200, args.unit), address=("127.0.0.1", args.port), sslctx=ctx)
    return await serving.until_signalled(server)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
