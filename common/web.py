"""The one way a service serves HTTP (the viewer, the Foxglove bridge): an aiohttp app on a TCP
site, with the port it really listens on and a clear error when it cannot listen."""
from __future__ import annotations

from typing import TYPE_CHECKING

from common.errors import BallbotError

if TYPE_CHECKING:
    from aiohttp import web


async def start_site(app: web.Application, host: str, port: int, what: str, hint: str) -> tuple[web.AppRunner, int]:
    """Serve app on host:port -> (its runner, for runner.cleanup(); the port it listens on: with
    port 0, the one the OS chose). A port that cannot be listened on is a BallbotError naming the
    service (what), the address and the OS's reason, then the hint."""
    from aiohttp import web

    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    try:
        await web.TCPSite(runner, host, port).start()
    except OSError as e:
        await runner.cleanup()
        raise BallbotError(f"{what}: cannot listen on {host}:{port}: {e.strerror or e} ({hint})") from None
    addresses = runner.addresses  # (the one site's sockets)
    return runner, addresses[0][1] if addresses else port
