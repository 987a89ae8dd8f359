"""Serving a pymodbus server for a test: READY on stdout once it listens, then until
SIGTERM or SIGINT, then a clean shutdown. Shared by the test servers in this folder."""

import asyncio
import signal


async def until_signalled(server):
    """Serves `server` in the background until SIGTERM or SIGINT; returns 0."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await server.serve_forever(background=True)
    print("READY", flush=True)
    await stop.wait()
    await server.shutdown()
    return 0
