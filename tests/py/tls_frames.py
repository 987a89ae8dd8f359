#!/usr/bin/env python3
"""Raw frames over Modbus/TCP Security, through Python's ssl (OpenSSL): connects to
mbgate's TLS listener with a client certificate, writes each frame given (hex, one
argument each) with a pause after it, then prints every byte that came back within
a second of the last, as one hex line per read, and `end`.

    tls_frames.py --port N --ca CA.pem --cert C.pem --key C.key HEX...
"""

from __future__ import annotations

import argparse
import socket
import ssl
import sys
import time


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--ca", required=True)
    ap.add_argument("--cert", required=True)
    ap.add_argument("--key", required=True)
    ap.add_argument("frames", nargs="+")
    args = ap.parse_args()
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.load_verify_locations(args.ca)
    ctx.load_cert_chain(args.cert, args.key)
    raw = socket.create_connection(("127.0.0.1", args.port), timeout=10)
    s = ctx.wrap_socket(raw, server_hostname="localhost")
    for f in args.frames:
        s.sendall(bytes.fromhex(f))
        time.sleep(0.1)
    s.settimeout(1.0)
    try:
        while True:
            d = s.recv(1000)
            if not d:
                print("closed", flush=True)
                break
            print(d.hex(), flush=True)
    except (socket.timeout, TimeoutError):
        pass
    print("end", flush=True)
    s.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
