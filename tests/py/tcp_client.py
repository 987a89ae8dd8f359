#!/usr/bin/env python3
"""An ordinary Modbus/TCP user (pymodbus AsyncModbusTcpClient) against mbgate + stock_server.py.

    tcp_client.py --host 127.0.0.1 --port N [--unit 1 [--unit 2 ...]] [--timeout 3]

Expects the device behind the gateway to be tests/py/stock_server.py with its defaults
(size 200, fresh state). Runs every step below, prints one JSON object on stdout
({"ok": bool, "steps": [{"step", "ok", "got", "expected"|"error"}, ...]}) and exits 0
only if every expectation held; otherwise exits 1 and names each failing step on
stderr. Each request: 3 s timeout, no retries. With several --unit, each unit's steps
run at once on a connection of its own (a device behind each; steps named UNIT/step).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException


def expected_coils(start: int, count: int) -> list[bool]:
    return [i % 3 == 0 for i in range(start, start + count)]


def expected_inputs(start: int, count: int) -> list[bool]:
    return [i % 2 == 0 for i in range(start, start + count)]


class Runner:
    def __init__(self, client: AsyncModbusTcpClient, unit: int) -> None:
        self.client = client
        self.unit = unit
        self.steps: list[dict] = []

    def record(self, step: str, ok: bool, got, expected=None, error: str | None = None) -> None:
        entry = {"step": step, "ok": ok, "got": got}
        if error is not None:
            entry["error"] = error
        else:
            entry["expected"] = expected
        self.steps.append(entry)

    async def call(self, step: str, make):
        """Send one request (``make()`` builds it); a transport error or an exception
        response fails the step. pymodbus raises "not connected" from the call itself,
        not from the awaitable, hence the lambda."""
        try:
            rr = await make()
        except ModbusException as exc:
            self.record(step, False, None, error=f"{type(exc).__name__}: {exc}")
            return None
        if rr.isError():
            self.record(step, False, {"exception_code": rr.exception_code}, error="exception response")
            return None
        return rr

    async def expect_registers(self, step: str, make, expected: list[int]) -> None:
        if (rr := await self.call(step, make)) is not None:
            got = list(rr.registers)
            self.record(step, got == expected, got, expected)

    async def expect_bits(self, step: str, make, expected: list[bool]) -> None:
        if (rr := await self.call(step, make)) is not None:
            got = list(rr.bits)[: len(expected)]  # pymodbus pads to whole bytes
            self.record(step, got == expected, got, expected)

    async def run(self) -> None:
        c, u = self.client, self.unit

        await self.expect_registers(
            "read_holding_0_4",
            lambda: c.read_holding_registers(0, count=5, device_id=u),
            [255, 1001, 1002, 1003, 1004],
        )

        if (rr := await self.call("write_register_8", lambda: c.write_register(8, 0x0011, device_id=u))) is not None:
            got = {"address": rr.address, "value": rr.registers[0]}
            want = {"address": 8, "value": 0x0011}
            self.record("write_register_8", got == want, got, want)
        await self.expect_registers(
            "read_back_register_8", lambda: c.read_holding_registers(8, count=1, device_id=u), [0x0011]
        )

        if (rr := await self.call("write_registers_20_22", lambda: c.write_registers(20, [7, 8, 9], device_id=u))) is not None:
            got = {"address": rr.address, "count": rr.count}
            want = {"address": 20, "count": 3}
            self.record("write_registers_20_22", got == want, got, want)
        await self.expect_registers(
            "read_back_registers_20_22", lambda: c.read_holding_registers(20, count=3, device_id=u), [7, 8, 9]
        )

        await self.expect_registers(
            "read_input_registers_0_2",
            lambda: c.read_input_registers(0, count=3, device_id=u),
            [2000, 2001, 2002],
        )

        await self.expect_bits("read_coils_0_9", lambda: c.read_coils(0, count=10, device_id=u), expected_coils(0, 10))
        await self.expect_bits(
            "read_discrete_inputs_0_9",
            lambda: c.read_discrete_inputs(0, count=10, device_id=u),
            expected_inputs(0, 10),
        )

        if (rr := await self.call("write_coil_5_on", lambda: c.write_coil(5, True, device_id=u))) is not None:
            got = {"address": rr.address, "value": bool(rr.bits[0])}
            want = {"address": 5, "value": True}
            self.record("write_coil_5_on", got == want, got, want)
        await self.expect_bits("read_back_coil_5", lambda: c.read_coils(5, count=1, device_id=u), [True])

        new_bits = [True, True, False]  # initial 10..12 is [False, False, True]
        if (rr := await self.call("write_coils_10_12", lambda: c.write_coils(10, new_bits, device_id=u))) is not None:
            got = {"address": rr.address, "count": rr.count}
            want = {"address": 10, "count": 3}
            self.record("write_coils_10_12", got == want, got, want)
        want_coils = expected_coils(4, 10)
        want_coils[5 - 4] = True
        want_coils[10 - 4 : 13 - 4] = new_bits
        await self.expect_bits("read_back_coils_4_13", lambda: c.read_coils(4, count=10, device_id=u), want_coils)

        # FC 23: the write (40..41) happens before the read (39..42).
        await self.expect_registers(
            "readwrite_registers_fc23",
            lambda: c.readwrite_registers(
                read_address=39, read_count=4, write_address=40, values=[0x1234, 0x5678], device_id=u
            ),
            [1039, 0x1234, 0x5678, 1042],
        )

        step = "read_holding_10000_exception_02"
        try:
            rr = await c.read_holding_registers(10000, count=1, device_id=u)
        except ModbusException as exc:
            self.record(step, False, None, error=f"{type(exc).__name__}: {exc}")
        else:
            got = {"function_code": rr.function_code, "exception_code": getattr(rr, "exception_code", None)}
            want = {"function_code": 0x83, "exception_code": 2}
            self.record(step, rr.isError() and got == want, got, want)

        # Put back what was written, so the script can run again on the same device.
        for step, make in (
            ("restore_register_8", lambda: c.write_register(8, 1008, device_id=u)),
            ("restore_registers_20_22", lambda: c.write_registers(20, [1020, 1021, 1022], device_id=u)),
            ("restore_registers_40_41", lambda: c.write_registers(40, [1040, 1041], device_id=u)),
            ("restore_coil_5", lambda: c.write_coil(5, False, device_id=u)),
            ("restore_coils_10_12", lambda: c.write_coils(10, expected_coils(10, 3), device_id=u)),
        ):
            if await self.call(step, make) is not None:
                self.record(step, True, "written", "written")


async def one_unit(args: argparse.Namespace, unit: int) -> list[dict]:
    client = AsyncModbusTcpClient(
        args.host,
        port=args.port,
        timeout=args.timeout,
        retries=0,
        reconnect_delay=0,
    )
    if not await client.connect():
        return [{"step": "connect", "ok": False, "got": None, "error": f"cannot connect to {args.host}:{args.port}"}]
    runner = Runner(client, unit)
    try:
        await runner.run()
    finally:
        client.close()
    return runner.steps


async def amain(args: argparse.Namespace) -> int:
    units = args.unit or [1]
    results = await asyncio.gather(*(one_unit(args, u) for u in units))
    steps = []
    for unit, unit_steps in zip(units, results):
        for s in unit_steps:
            if len(units) > 1:
                s["step"] = f"{unit}/{s['step']}"
            steps.append(s)
    ok = all(s["ok"] for s in steps)
    print(json.dumps({"ok": ok, "steps": steps}), flush=True)
    for s in steps:
        if not s["ok"]:
            detail = s.get("error") or f"got {s['got']!r}, expected {s['expected']!r}"
            print(f"tcp_client: FAIL {s['step']}: {detail}", file=sys.stderr)
    return 0 if ok else 1


def main() -> int:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--unit", type=int, action="append", help="unit id (repeat for several; default 1)")
    p.add_argument("--timeout", type=float, default=3.0, help="seconds per request (default 3)")
    return asyncio.run(amain(p.parse_args()))


if __name__ == "__main__":
    sys.exit(main())
