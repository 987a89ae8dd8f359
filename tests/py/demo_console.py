#!/usr/bin/env python3
"""Runs `mbgate demo` with its console on a real terminal (a pty), stops it with SIGINT
as Ctrl-C would, and prints what the terminal showed after the last `sim> ` prompt,
then "exit N".

    demo_console.py MBGATE
"""

import os
import signal
import sys

sys.path.insert(0, os.path.dirname(__file__))
from console import on_terminal, read_until  # noqa: E402


def main() -> int:
    mbgate = sys.argv[1]
    proc, console = on_terminal([mbgate, "demo", "--listen", "127.0.0.1:0"])
    read_until(console, b"sim> ")
    proc.send_signal(signal.SIGINT)
    rest = read_until(console, b"stopped: ", timeout=10)
    rest += read_until(console, b"\n", timeout=5)
    code = proc.wait(timeout=10)
    print(repr(rest.decode()), flush=True)
    print(f"exit {code}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
