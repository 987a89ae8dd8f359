#!/usr/bin/env python3
"""Drives `mbgate sim`'s console on a real terminal (a pty) and a raw master on the line.

    console.py MBGATE DEVICE_PTY MASTER_PTY

Prints a transcript: "> command", the console's answer, "line: <hex>" for what the
master read on the line, "log: <line>" for the packet log, and "exit N" at the end.
"""

import os
import pty
import select
import subprocess
import sys
import tempfile
import time


def read_until(fd, marker: bytes, timeout=5.0) -> bytes:
    buf = b""
    end = time.monotonic() + timeout
    while marker not in buf:
        left = end - time.monotonic()
        if left <= 0:
            raise SystemExit(f"timed out waiting for {marker!r}; got {buf!r}")
        r, _, _ = select.select([fd], [], [], left)
        if r:
            try:
                chunk = os.read(fd, 4096)
            except OSError:  # EIO: the process closed the terminal
                break
            if not chunk:
                break
            buf += chunk
    return buf


def on_terminal(args, stderr=subprocess.DEVNULL, cwd=None):
    """Starts `args` with a pty as its terminal (stdin and stdout); returns the
    process and our side of the pty."""
    console, terminal = pty.openpty()
    proc = subprocess.Popen(
        args, stdin=terminal, stdout=terminal, stderr=stderr, close_fds=True, cwd=cwd,
    )
    os.close(terminal)
    return proc, console


def main() -> int:
    mbgate, device, master = sys.argv[1:4]
    log = tempfile.NamedTemporaryFile(prefix="mbgate-sim-", suffix=".log")
    proc, console = on_terminal(
        [mbgate, "sim", "--serial", device, "--log-level", "info"], stderr=log,
    )
    read_until(console, b"sim> ")
    end = time.monotonic() + 5
    while b"simulating" not in open(log.name, "rb").read():
        if time.monotonic() > end:
            raise SystemExit("the simulator never opened its port")
        time.sleep(0.01)

    def command(line: str, prefix: str = "") -> None:
        print(f"> {line}", flush=True)
        os.write(console, line.encode() + b"\n")
        out = read_until(console, b"sim> " if line != "quit" else b"bye")
        text = out.decode().replace("\r", "")
        for l in text.split("\n"):
            if l.startswith(line) or l in ("sim> ", ""):
                continue  # the terminal's echo of the command, the prompt
            print(f"{prefix}{l}", flush=True)

    command("inputs 0xA5")
    line = os.open(master, os.O_RDWR | os.O_NOCTTY)
    os.write(line, bytes.fromhex("000100000006010300000001"))
    got = b""
    end = time.monotonic() + 5
    while len(got) < 11 and time.monotonic() < end:
        r, _, _ = select.select([line], [], [], 0.1)
        if r:
            got += os.read(line, 64)
    print("line: " + " ".join(f"{b:02X}" for b in got), flush=True)
    command("list")
    command("input 0 off")
    print("> log", flush=True)
    os.write(console, b"log\n")
    text = read_until(console, b"sim> ").decode().replace("\r", "")
    for l in text.split("\n"):
        if l and not l.startswith("log") and l != "sim> ":
            print(f"log: {l}", flush=True)
    command("add 2")
    command("bogus")
    command("clear-log")
    command("quit")
    print(f"exit {proc.wait(timeout=5)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
