#!/usr/bin/env python3
# The master of scripts/cold-path: one transaction (FC 03 × 1 of unit 1, the reply
# checked) through each path in turn after an idle gap, ROUNDS rounds, the order of the
# paths turned each round; then back to back through the two relays in turns. Prints
# each relay's CPU a transaction (/proc/PID/task/*/schedstat, every thread, ns) and
# each path's round trip.
# Usage: python3 scripts/cold.py ROUNDS GAP_MS BACK_TO_BACK DIRECT_PTY NAME=PORT:PID...
#   DIRECT_PTY: a pty whose other side is a simulated device, written and read here
#   directly (no process between: the floor of a round trip).
#   NAME=PORT:PID: a relay listening on PORT (socat, mbgate), its process PID.
import os
import socket
import statistics
import struct
import sys
import termios
import time
import tty


def cpu_ns(pid):
    total = 0
    for t in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{t}/schedstat") as f:
                total += int(f.read().split()[0])
        except FileNotFoundError:
            pass  # a thread that ended meanwhile
    return total


def request(tid):
    return struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, 0, 1)


class Relay:
    def __init__(self, name, port, pid):
        self.name, self.pid = name, pid
        for _ in range(200):
            try:
                self.s = socket.create_connection(("127.0.0.1", port))
                break
            except OSError:
                time.sleep(0.05)
        else:
            raise SystemExit(f"cold.py: nothing listens on {port} ({name})")
        self.s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def rd(self, k):
        b = b""
        while len(b) < k:
            c = self.s.recv(k - len(b))
            if not c:
                raise SystemExit(f"cold.py: {self.name} closed the connection")
            b += c
        return b

    def ask(self, tid):
        self.s.sendall(request(tid))
        h = self.rd(7)
        body = self.rd(struct.unpack(">H", h[4:6])[0] - 1)
        assert struct.unpack(">H", h[:2])[0] == tid and body[0] == 3, (self.name, h, body)


class Direct:
    """The master on the pty itself: a request written, its reply read."""

    name = "direct"
    pid = None

    def __init__(self, path):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        termios.tcflush(self.fd, termios.TCIOFLUSH)

    def ask(self, tid):
        os.write(self.fd, request(tid))
        b = b""
        while len(b) < 7 or len(b) < 6 + struct.unpack(">H", b[4:6])[0]:
            b += os.read(self.fd, 260)
        assert struct.unpack(">H", b[:2])[0] == tid and b[7] == 3, ("direct", b)


def pct(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))]


def main():
    rounds, gap, b2b = int(sys.argv[1]), float(sys.argv[2]) / 1000, int(sys.argv[3])
    paths = [Direct(sys.argv[4])]
    for arg in sys.argv[5:]:
        name, rest = arg.split("=", 1)
        port, pid = rest.split(":")
        paths.append(Relay(name, int(port), int(pid)))
    relays = [p for p in paths if p.pid]
    # Warm-up: every path answers, the relays' first-use costs are paid.
    for p in paths:
        for i in range(50):
            p.ask(i)
    rtt = {p.name: [] for p in paths}
    before = {p.name: cpu_ns(p.pid) for p in relays}
    tid = 0
    for r in range(rounds):
        k = r % len(paths)
        for p in paths[k:] + paths[:k]:
            time.sleep(gap)
            tid = (tid + 1) & 0xFFFF
            t0 = time.perf_counter_ns()
            p.ask(tid)
            rtt[p.name].append(time.perf_counter_ns() - t0)
    cold = {p.name: (cpu_ns(p.pid) - before[p.name]) / rounds / 1000 for p in relays}
    # Back to back: blocks of b2b / 4 transactions, the relays in turns.
    warm = {p.name: 0 for p in relays}
    block = max(1, b2b // 4)
    for _ in range(4):
        for p in relays:
            c0 = cpu_ns(p.pid)
            for i in range(block):
                p.ask(i & 0xFFFF)
            warm[p.name] += cpu_ns(p.pid) - c0
    n = block * 4
    ref = relays[0].name
    print(f"cold path: {rounds} rounds, one transaction a path each after {gap * 1000:g} ms idle, paths in turn")
    for p in paths:
        xs = [x / 1000 for x in rtt[p.name]]
        line = f"  {p.name:8} round trip p50 {statistics.median(xs):7.1f} µs, p90 {pct(xs, 0.9):7.1f} µs"
        if p.pid:
            line += f"; CPU {cold[p.name]:6.2f} µs a transaction ({cold[p.name] / cold[ref]:.2f} × {ref})"
        print(line)
    print(f"back to back: {n} transactions a relay, in 4 turns")
    for p in relays:
        us = warm[p.name] / n / 1000
        print(f"  {p.name:8} CPU {us:6.2f} µs a transaction ({warm[p.name] / warm[ref]:.2f} × {ref})")


main()
