#!/usr/bin/env python3
"""The SCADA server a dialing mbgate connects to (tests/e2e/dial.rs): it listens, accepts
mbgate's connections one after another, and in each plays one round; requests are
built and replies decoded by pymodbus' own socket (MBAP) framer, and every reply is
checked by value against stock_server.py's device (unit 1) behind the gateway.

    dial_server.py --listen HOST:PORT --identity TEXT [--heartbeat HEX] [--framer rtu]
                   [--tls CERT:KEY:CA [--wrong CERT:KEY]] --round ROUND [--round ...]

--tls: every connection is TLS, the server presenting CERT and requiring a client
certificate chained to CA (Modbus/TCP Security with mbgate as the client).

Rounds, each one accepted connection:
  close    accept and close at once
  garbage  accept, send bytes that are no Modbus request (taken for the identity's
           answer), then more, and wait for mbgate to close
  halfway  accept, read the identity, send a request, close before the reply
  serve    read the identity, send requests and check every reply, then hold the
           connection 1.5 s and close
  echo     read the identity and echo it back, wait for a heartbeat and echo it,
           then as serve (the echoes must not be taken for requests)
  ack      read the identity and answer it "ACK\\r\\n", check; twice: wait for a
           heartbeat, answer it "HB-ACK\\r\\n", check (the answers are no requests)
  refused  (TLS) present --wrong's certificate: mbgate must refuse it
  readonly read the identity, check the reads; a write must be answered 0x01
  deaf     read the identity, send 400 reads of 125 registers and read no reply;
           print "deaf sent", wait for a line on stdin, then read until mbgate
           closes (it must have given up on the unread replies)
  keep     read the identity, check, print "kept", wait for a line on stdin, then
           check again on the same connection (it outlived whatever happened between)

--restarts N: instead of rounds, the server restarts N times: each time it listens
anew, takes mbgate's connection, reads the identity, checks two reads, holds the
connection --hold seconds and closes it and its listening socket (with --busy: sends
reads and checks their replies throughout the --hold seconds, then one more read, and
closes before its reply). Before the first
restart and after the last it serves a connection that waits for a line on stdin
(prints "held"), so the test can look at the gateway then. Prints "restarts ok N
replies M" (M: the replies checked in the restarts).

Prints READY once listening, a line per round ("serve ok 12"), and exits 0 when
every round passed; any failure prints "FAIL ..." and exits 1.
"""

from __future__ import annotations

import argparse
import socket
import ssl
import sys
import time

from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.bit_message import ReadCoilsRequest, ReadDiscreteInputsRequest
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
    WriteMultipleRegistersRequest,
    WriteSingleRegisterRequest,
)

TIMEOUT = 20.0


def fail(what: str) -> None:
    print(f"FAIL {what}", flush=True)
    sys.exit(1)


def read_exact(conn: socket.socket, n: int) -> bytes:
    got = b""
    while len(got) < n:
        chunk = conn.recv(n - len(got))
        if not chunk:
            fail(f"connection closed after {got!r}, expected {n} bytes")
        got += chunk
    return got


class Master:
    """Requests over one accepted connection, pymodbus framing them."""

    # The framing of every connection: socket (MBAP) or, with --framer rtu, RTU over TCP.
    FRAMER = FramerSocket

    def __init__(self, conn: socket.socket) -> None:
        self.conn = conn
        self.framer = self.FRAMER(DecodePDU(is_server=False))
        self.tid = 0
        self.buf = b""

    def ask(self, request):
        self.tid += 1
        request.transaction_id = self.tid
        request.dev_id = 1
        self.conn.sendall(self.framer.buildFrame(request))
        while True:
            used, pdu = self.framer.handleFrame(self.buf, 0, 0)
            if pdu is not None:
                self.buf = self.buf[used:]
                if self.FRAMER is FramerSocket and pdu.transaction_id != self.tid:
                    fail(f"reply id {pdu.transaction_id}, asked {self.tid}")
                if pdu.isError():
                    fail(f"exception reply {pdu} to {request}")
                return pdu
            chunk = self.conn.recv(512)
            if not chunk:
                fail(f"closed while waiting for the reply to {request}")
            self.buf += chunk

    def refused_write(self) -> None:
        """A write the access rules deny: exception 0x01, never reaching the line."""
        self.tid += 1
        request = WriteSingleRegisterRequest(address=100, registers=[1], dev_id=1, transaction_id=self.tid)
        self.conn.sendall(self.framer.buildFrame(request))
        while True:
            used, pdu = self.framer.handleFrame(self.buf, 0, 0)
            if pdu is not None:
                self.buf = self.buf[used:]
                if not pdu.isError() or pdu.exception_code != 1:
                    fail(f"a denied write answered {pdu}")
                return
            chunk = self.conn.recv(512)
            if not chunk:
                fail("closed while waiting for the denied write's reply")
            self.buf += chunk

    def reads(self) -> int:
        for address in (1, 5, 40):
            r = self.ask(ReadHoldingRegistersRequest(address=address, count=3))
            want = [1000 + address + i for i in range(3)]
            if list(r.registers) != want:
                fail(f"holding {address}: {list(r.registers)} != {want}")
        return 3

    def checks(self) -> int:
        """Reads and writes, each reply checked by value; how many were asked."""
        n = 0
        for address in (1, 5, 40):
            r = self.ask(ReadHoldingRegistersRequest(address=address, count=3))
            want = [1000 + address + i for i in range(3)]
            if list(r.registers) != want:
                fail(f"holding {address}: {list(r.registers)} != {want}")
            n += 1
        r = self.ask(ReadInputRegistersRequest(address=7, count=4))
        if list(r.registers) != [2007, 2008, 2009, 2010]:
            fail(f"input registers {list(r.registers)}")
        r = self.ask(ReadCoilsRequest(address=0, count=9))
        if list(r.bits[:9]) != [i % 3 == 0 for i in range(9)]:
            fail(f"coils {list(r.bits)}")
        r = self.ask(ReadDiscreteInputsRequest(address=1, count=6))
        if list(r.bits[:6]) != [(1 + i) % 2 == 0 for i in range(6)]:
            fail(f"discrete inputs {list(r.bits)}")
        n += 3
        value = 4000 + self.tid
        self.ask(WriteSingleRegisterRequest(address=100, registers=[value]))
        r = self.ask(ReadHoldingRegistersRequest(address=100, count=1))
        if list(r.registers) != [value]:
            fail(f"written {value}, read back {list(r.registers)}")
        self.ask(WriteMultipleRegistersRequest(address=110, registers=[7, 8, 9]))
        r = self.ask(ReadHoldingRegistersRequest(address=110, count=3))
        if list(r.registers) != [7, 8, 9]:
            fail(f"written 7 8 9, read back {list(r.registers)}")
        return n + 4


def take(server: socket.socket, identity: bytes) -> Master:
    try:
        conn, _ = server.accept()
    except socket.timeout:
        fail(f"mbgate did not dial in {TIMEOUT} s")
    conn.settimeout(TIMEOUT)
    got = read_exact(conn, len(identity))
    if got != identity:
        fail(f"identity {got!r}, expected {identity!r}")
    return Master(conn)


def restarts(server: socket.socket, at, identity: bytes, n: int, hold: float, busy: bool) -> int:
    """The server killed and started again n times (see the module's doc)."""
    replies = 0
    for i in range(n + 2):
        if i > 0:
            server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            server.bind(at)
            server.listen(1)
            server.settimeout(TIMEOUT)
        master = take(server, identity)
        if i == 0 or i == n + 1:
            master.checks()
            print("held", flush=True)
            sys.stdin.readline()
        elif busy:
            # Under load to the end: reads checked for `hold` seconds, then one more
            # sent and the server gone before its reply.
            until = time.monotonic() + hold
            while time.monotonic() < until:
                replies += master.reads()
            master.conn.sendall(master.framer.buildFrame(ReadHoldingRegistersRequest(address=1, count=1, dev_id=1, transaction_id=0)))
        else:
            replies += master.reads()
            time.sleep(hold)
        master.conn.close()
        server.close()
    print(f"restarts ok {n} replies {replies}", flush=True)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", required=True)
    ap.add_argument("--identity", required=True)
    ap.add_argument("--heartbeat", default="")
    ap.add_argument("--round", action="append", default=[])
    ap.add_argument("--restarts", type=int, default=0)
    ap.add_argument("--hold", type=float, default=0.3)
    ap.add_argument("--busy", action="store_true")
    ap.add_argument("--rcvbuf", type=int, default=0)
    ap.add_argument("--framer", choices=["socket", "rtu"], default="socket")
    ap.add_argument("--tls", default="")
    ap.add_argument("--wrong", default="")
    args = ap.parse_args()
    if args.framer == "rtu":
        Master.FRAMER = FramerRTU
    contexts = {}
    if args.tls:
        cert, key, ca = args.tls.split(":")
        for which, (c, k) in (("right", (cert, key)), ("wrong", tuple(args.wrong.split(":")) if args.wrong else (cert, key))):
            ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            ctx.load_cert_chain(c, k)
            ctx.verify_mode = ssl.CERT_REQUIRED
            ctx.load_verify_locations(ca)
            contexts[which] = ctx
    host, port = args.listen.rsplit(":", 1)
    identity = args.identity.encode()
    heartbeat = bytes.fromhex(args.heartbeat)
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if args.rcvbuf:
        # Inherited by the connections accepted: unread replies fill it soon.
        server.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, args.rcvbuf)
    server.bind((host, int(port)))
    server.listen(1)
    server.settimeout(TIMEOUT)
    print("READY", flush=True)
    if args.restarts:
        return restarts(server, (host, int(port)), identity, args.restarts, args.hold, args.busy)
    for name in args.round:
        try:
            conn, _ = server.accept()
        except socket.timeout:
            fail(f"{name}: mbgate did not dial in {TIMEOUT} s")
        conn.settimeout(TIMEOUT)
        if contexts:
            ctx = contexts["wrong" if name == "refused" else "right"]
            try:
                conn = ctx.wrap_socket(conn, server_side=True)
                if name == "refused":
                    # TLS 1.3: the client's verdict comes after the server's handshake.
                    if conn.recv(512):
                        fail("refused: mbgate sent bytes over a certificate it must refuse")
            except (ssl.SSLError, OSError) as e:
                if name != "refused":
                    fail(f"{name}: TLS handshake: {e}")
            if name == "refused":
                conn.close()
                print("refused ok", flush=True)
                continue
        if name == "close":
            conn.close()
            print("close ok", flush=True)
            continue
        if name == "garbage":
            # The first bytes may be the identity's answer (dropped, the connection
            # kept: docs/dialing.md); the second break the protocol.
            conn.sendall(b"hello, this is not Modbus\r\n")
            time.sleep(0.3)
            conn.sendall(b"hello again\r\n")
            # mbgate closes at once: the read ends.
            while conn.recv(512):
                pass
            conn.close()
            print("garbage ok", flush=True)
            continue
        got = read_exact(conn, len(identity))
        if got != identity:
            fail(f"{name}: identity {got!r}, expected {identity!r}")
        master = Master(conn)
        if name == "halfway":
            conn.sendall(master.framer.buildFrame(ReadHoldingRegistersRequest(address=1, count=1, dev_id=1, transaction_id=9)))
            conn.close()
            print("halfway ok", flush=True)
            continue
        if name == "echo":
            conn.sendall(identity)
            beat = read_exact(conn, len(heartbeat))
            if beat != heartbeat:
                fail(f"heartbeat {beat!r}, expected {heartbeat!r}")
            conn.sendall(heartbeat)
        elif name == "ack":
            # Answers of the server's own to the identity and to two heartbeats, each
            # on its own (a request on an answer's heels would be lost with it).
            conn.sendall(b"ACK\r\n")
            time.sleep(0.3)
            n = master.checks()
            for _ in range(2):
                beat = read_exact(conn, len(heartbeat))
                if beat != heartbeat:
                    fail(f"heartbeat {beat!r}, expected {heartbeat!r}")
                conn.sendall(b"HB-ACK\r\n")
                time.sleep(0.3)
                n += master.checks()
            time.sleep(0.3)
            conn.close()
            print(f"ack ok {n}", flush=True)
            continue
        elif name == "readonly":
            n = master.reads()
            master.refused_write()
            n += master.reads()
            time.sleep(1.5)
            conn.close()
            print(f"readonly ok {n}", flush=True)
            continue
        elif name == "deaf":
            for i in range(400):
                conn.sendall(master.framer.buildFrame(ReadHoldingRegistersRequest(address=0, count=125, dev_id=1, transaction_id=i + 1)))
            print("deaf sent", flush=True)
            sys.stdin.readline()
            try:
                while conn.recv(65536):
                    pass
            except ConnectionResetError:
                pass
            except socket.timeout:
                fail("deaf: mbgate kept the connection")
            conn.close()
            print("deaf ok", flush=True)
            continue
        elif name == "keep":
            n = master.checks()
            print(f"kept {n}", flush=True)
            sys.stdin.readline()
            n += master.checks()
            conn.close()
            print(f"keep ok {n}", flush=True)
            continue
        elif name != "serve":
            fail(f"unknown round {name}")
        n = master.checks()
        time.sleep(1.5)
        conn.close()
        print(f"{name} ok {n}", flush=True)
    print("DONE", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
