#!/usr/bin/env python3
# One Modbus/TCP master polling FC 03 × 1 of unit 1 back to back, each reply checked
# (its transaction id and function code): the master of the measuring scripts
# (scripts/syscalls, scripts/cpu-ab).
# Usage: python3 scripts/poll.py [--udp | --listen] [--addr A] PORT N [PID]
#   --udp: the master sends each request as a datagram to a Modbus/UDP listener
#   (`transport = "udp"`) and reads its reply datagram.
#   --listen: the master is dialed (a `[[dial]]` of the gateway): it listens on PORT
#   and polls over the connection the gateway makes.
#   --addr A: reads holding register A (default 0).
#   PID: after 1000 warm-up transactions, poll N more on the same connection and print
#   PID's CPU time a transaction in µs (/proc/PID/task/*/schedstat, every thread),
#   then its user and kernel time a transaction in µs (/proc/PID/stat utime and
#   stime, in clock ticks: exact over many transactions only).
import os
import socket
import struct
import sys
import time


def cpu_ns(pid):
    return sum(
        int(open(f"/proc/{pid}/task/{t}/schedstat").read().split()[0])
        for t in os.listdir(f"/proc/{pid}/task")
    )


def times(pid):
    """PID's user and kernel time (utime, stime) in clock ticks."""
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return int(fields[11]), int(fields[12])


def main():
    args = sys.argv[1:]
    udp = listen = False
    addr = 0
    while args and args[0].startswith("--"):
        if args[0] == "--udp":
            udp = True
        elif args[0] == "--listen":
            listen = True
        elif args[0] == "--addr":
            addr = int(args[1])
            args = args[1:]
        args = args[1:]
    port, n = int(args[0]), int(args[1])
    pid = int(args[2]) if len(args) > 2 else None
    if udp:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.connect(("127.0.0.1", port))
        s.settimeout(10)
    if listen:
        server = socket.socket()
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(("127.0.0.1", port))
        server.listen(1)
        server.settimeout(60)
        s, _ = server.accept()
    for _ in range(0 if udp or listen else 100):
        try:
            s = socket.create_connection(("127.0.0.1", port))
            break
        except OSError:
            time.sleep(0.05)
    else:
        if not (udp or listen):
            raise SystemExit(f"nothing listens on {port}")
    if not udp:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def rd(k):
        b = b""
        while len(b) < k:
            c = s.recv(k - len(b))
            if not c:
                raise SystemExit("closed")
            b += c
        return b

    def ask(tid):
        """One datagram out, one back (retried while the listener is not up yet)."""
        req = struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, addr, 1)
        for _ in range(100):
            try:
                s.send(req)
                return s.recv(300)
            except (ConnectionRefusedError, socket.timeout):
                time.sleep(0.05)
        raise SystemExit(f"no reply on UDP port {port}")

    def run(k):
        for i in range(k):
            tid = i & 0xFFFF
            if udp:
                d = ask(tid)
                assert struct.unpack(">H", d[:2])[0] == tid and d[7] == 3, d
                continue
            s.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, addr, 1))
            h = rd(7)
            body = rd(struct.unpack(">H", h[4:6])[0] - 1)
            assert struct.unpack(">H", h[:2])[0] == tid and body[0] == 3, (h, body)

    if pid is None:
        run(n)
        return
    run(1000)
    c0, t0 = cpu_ns(pid), times(pid)
    run(n)
    c1, t1 = cpu_ns(pid), times(pid)
    tick_us = 1e6 / os.sysconf("SC_CLK_TCK")
    user, kernel = ((b - a) * tick_us / n for a, b in zip(t0, t1))
    print(f"{(c1 - c0) / n / 1000:.1f} {user:.2f} {kernel:.2f}")


main()
