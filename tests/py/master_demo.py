#!/usr/bin/env python3
"""Runs `mbgate demo --master` with its console on a real terminal (a pty): sets an
input of the master, runs the read command the banner prints (as printed, through a
shell) until the slave's outputs show it, sets an input of the slave and waits for the
master's console to show its outputs follow; then Ctrl-C. Prints a JSON object: the
banner, what the printed command printed, and the exit code.

    master_demo.py MBGATE
"""

import json
import os
import signal
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(__file__))
from console import on_terminal, read_until  # noqa: E402


def main() -> int:
    mbgate = sys.argv[1]
    proc, console = on_terminal(
        [mbgate, "demo", "--master", "--poll-ms", "100", "--listen", "127.0.0.1:0"],
        cwd=os.path.dirname(mbgate),
    )
    banner = read_until(console, b"sim> ").decode()
    os.write(console, b"input 0 on\n")
    read_until(console, b"inputs 00000001")
    command = next(l for l in banner.splitlines() if " read --tcp " in l).strip()
    shown = ""
    end = time.monotonic() + 5
    while time.monotonic() < end:
        run = subprocess.run(command, shell=True, capture_output=True, text=True,
                             cwd=os.path.dirname(mbgate))
        shown = run.stdout + run.stderr
        if run.returncode == 0 and "0x0001" in shown:
            break
        time.sleep(0.1)
    os.write(console, b"slave input 3 on\n")
    followed = read_until(console, b"outputs 00001000 (the slave's inputs)").decode()
    proc.send_signal(signal.SIGINT)
    code = proc.wait(timeout=10)
    print(json.dumps({"banner": banner, "command": command, "shown": shown,
                      "followed": "outputs 00001000" in followed, "exit": code}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
