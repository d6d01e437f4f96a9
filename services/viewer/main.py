"""viewer: a live web page of what the robot sees (`ballbot-vision run viewer`, `up --viewer`).

One port (default 127.0.0.1:8080) serves the page and one WebSocket per client. A viewer can
never slow the robot:
- Zenoh callbacks only keep payloads (newest few, by capture stamp); nothing is decoded there;
- the image streams are subscribed to only while a page is open (no watcher, no traffic);
- one composer thread builds at most `max_fps` updates a second (decode, JPEG, JSON), only when
  something new arrived and someone is watching;
- each client gets the newest update once it has drawn the previous one (it acks every frame);
  a slow client skips frames, it never queues them, and never holds anything up.
From a laptop: `ballbot-vision run viewer --mode client --connect tcp/ROBOT:7447`.

aiohttp serves both HTTP and WebSocket from one asyncio loop in one dependency (see pyproject's
`viewer` extra).
"""
from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
from pathlib import Path

from pydantic import Field

from common import codec
from common.errors import BallbotError
from common.keys import topic
from common.messages import FreeSpace, ObstacleList, ReplayControl, ServiceStats
from common.node import Node
from common.settings import ServiceSettings
from common.web import start_site
from services.viewer.core import Composer, ViewInputs

log = logging.getLogger("ballbot.viewer")

SUBSCRIBES = ["frames_rect", "disparity", "obstacles", "freespace", "truth", "stats"]
PUBLISHES = ["replay_control"]
STATIC = Path(__file__).resolve().parent / "static"


class ViewerSettings(ServiceSettings):
    section = "viewer"
    host: str = Field("127.0.0.1", description="address to bind (0.0.0.0: every interface; beyond loopback "
                                                "every page needs the token)")
    port: int = Field(8080, ge=0, le=65535, description="HTTP and WebSocket port (0: any free port)")
    max_fps: float = Field(15.0, gt=0, le=60, description="page updates per second at most")
    jpeg_quality: int = Field(80, ge=10, le=100, description="JPEG quality of the pictures sent")
    controls: bool = Field(True, description="let pages play/pause/step a replay (capture --source mcap)")
    idle_unsubscribe_s: float = Field(5.0, ge=0, le=3600, description="drop the image subscriptions this long "
                                      "after the last page closed")
    token: str = Field("", description="secret every page must carry (/?token=...); required when bound beyond "
                                       "loopback: empty then makes a random one at start and prints the URL with it")
    allowed_origins: list[str] = Field([], description="INSECURE beyond the default: other origins (scheme://host"
                                       "[:port]) whose pages may open the WebSocket; [\"*\"]: any. Default: only "
                                       "the viewer's own page")
    allowed_hosts: list[str] = Field([], description="names (besides IP addresses, localhost and this machine's "
                                     "name) under which the viewer is reached, e.g. a DNS name of the robot; any "
                                     "other Host header is refused (DNS rebinding)")


class Hub:
    """The newest packed update and who is waiting for it (thread-safe publish, asyncio wait)."""

    def __init__(self) -> None:
        self.version = 0
        self.latest: bytes | None = None
        self.clients = 0
        self.sent = 0
        self.skipped = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._changed: asyncio.Condition | None = None

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._changed = asyncio.Condition()

    def publish(self, message: bytes) -> None:
        """Any thread."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        loop.call_soon_threadsafe(self._set, message)

    def _set(self, message: bytes) -> None:
        self.version += 1
        self.latest = message
        asyncio.ensure_future(self._notify())

    def _condition(self) -> asyncio.Condition:
        if self._changed is None:
            raise BallbotError("viewer: the hub is used before bind() gave it the event loop")
        return self._changed

    async def _notify(self) -> None:
        changed = self._condition()
        async with changed:
            changed.notify_all()

    async def newer_than(self, version: int) -> tuple[int, bytes]:
        changed = self._condition()
        async with changed:
            await changed.wait_for(lambda: self.version > version and self.latest is not None)
            latest = self.latest
            assert latest is not None  # what wait_for waited for
            return self.version, latest


class Viewer:
    """The Zenoh side: inputs, lazy image subscriptions, the composer thread."""

    IMAGE_KINDS = ("frames_rect", "disparity", "truth")

    def __init__(self, node: Node, settings: ViewerSettings, hub: Hub):
        self.node, self.settings, self.hub = node, settings, hub
        self.inputs = ViewInputs()
        self.composer = Composer(node.robot_id, settings.jpeg_quality)
        self._lock = threading.Lock()
        self._new = threading.Event()
        self._image_subs: list = []
        self._last_client = time.monotonic()
        self._control = None
        self.composed = 0

    # Zenoh callback threads: keep the payload, nothing else
    def _keep(self, ring_name: str):
        ring = getattr(self.inputs, ring_name)

        def on_sample(sample) -> None:
            stamp = self.node.stamp_or_drop(sample, ring_name)
            if stamp is None:
                return
            with self._lock:
                ring.append((stamp, sample.payload.to_bytes()))
            if ring_name == "frames" and self.inputs.obstacles is None:
                self._new.set()  # no segmenter: frames alone drive the page
        return on_sample

    def _on_obstacles(self, sample) -> None:
        msg = self.node.decode_or_drop(sample.payload.to_bytes(), ObstacleList, "obstacle list")
        if msg is None:
            return
        with self._lock:
            old = self.inputs.obstacles
            if old is None or msg.stamp_ns >= old.stamp_ns or msg.stamp_ns < old.stamp_ns - 60e9:
                self.inputs.obstacles = msg  # (a capture restart starts a new timeline)
        self._new.set()

    def _on_freespace(self, sample) -> None:
        msg = self.node.decode_or_drop(sample.payload.to_bytes(), FreeSpace, "free space")
        if msg is not None:
            with self._lock:
                self.inputs.freespace = msg

    def _on_stats(self, sample) -> None:
        st = self.node.decode_or_drop(sample.payload.to_bytes(), ServiceStats, "stats", "stats")
        if st is not None:
            with self._lock:
                self.inputs.add_stats(st)

    def subscribe_small(self) -> None:
        rid = self.node.robot_id
        self.node.subscribe(topic("obstacles").key(rid), self._on_obstacles)
        self.node.subscribe(topic("freespace").key(rid), self._on_freespace)
        self.node.subscribe(topic("stats").pattern(rid), self._on_stats)
        if self.settings.controls:
            self._control = self.node.declare_publisher(topic("replay_control").key(rid))

    def _manage_image_subscriptions(self) -> None:
        now = time.monotonic()
        if self.hub.clients > 0:
            self._last_client = now
            if not self._image_subs:
                rid = self.node.robot_id
                sub = self.node.subscribe
                self._image_subs = [sub(topic("frames_rect").key(rid), self._keep("frames"), keep=False),
                                    sub(topic("disparity").key(rid), self._keep("disparities"), keep=False),
                                    sub(topic("truth").key(rid), self._keep("truths"), keep=False)]
                log.info("viewer: a page is open; subscribed to the image streams")
        elif self._image_subs and now - self._last_client > self.settings.idle_unsubscribe_s:
            for sub in self._image_subs:
                sub.undeclare()
            self._image_subs = []
            with self._lock:
                self.inputs.frames.clear()
                self.inputs.disparities.clear()
                self.inputs.truths.clear()
            log.info("viewer: no page open; image streams unsubscribed")

    def compose_loop(self) -> None:
        period = 1.0 / self.settings.max_fps
        next_t = time.monotonic()
        while self.node.running:
            self._manage_image_subscriptions()
            if self.hub.clients == 0:
                self.node.stop_event.wait(0.2)
                continue
            # new obstacles or frames, or at least a refresh of the stats twice a second
            self._new.wait(0.5)
            self._new.clear()
            delay = next_t - time.monotonic()
            if delay > 0:
                self.node.stop_event.wait(delay)
            next_t = max(next_t + period, time.monotonic())
            with self._lock:  # a consistent snapshot; the rings are small
                snapshot = ViewInputs(frames=self.inputs.frames.copy(), disparities=self.inputs.disparities.copy(),
                                      truths=self.inputs.truths.copy(), obstacles=self.inputs.obstacles,
                                      freespace=self.inputs.freespace, stats=dict(self.inputs.stats))
                Composer.drop_old_stats(self.inputs, time.monotonic())
            with self.node.processing():
                extra = {"viewer": {"clients": self.hub.clients, "sent": self.hub.sent, "skipped": self.hub.skipped,
                                    "controls": self.settings.controls, "max_fps": self.settings.max_fps}}
                message = self.composer.compose(snapshot, extra)
                self.hub.publish(message)
                self.composed += 1
                self.node.extra.update({"clients": float(self.hub.clients), "composed": float(self.composed),
                                        "sent": float(self.hub.sent), "skipped": float(self.hub.skipped)})

    def replay(self, action: str, frames: int = 1, speed: float | None = None) -> str | None:
        """A page's replay command -> ReplayControl; returns an error text or None."""
        if self._control is None:
            return "replay controls are off (viewer --controls false)"
        try:
            msg = ReplayControl(robot_id=self.node.robot_id, seq=0, stamp_ns=time.time_ns(), action=action,
                                frames=frames, speed=speed)
        except Exception as e:
            return f"bad replay command: {e}"
        if not self._control.matching_status.matching:
            return "no replay is running (capture --source mcap) for robot " + repr(self.node.robot_id)
        self._control.put(codec.encode(msg))
        return None


# -- web ------------------------------------------------------------------------------------------

LOOPBACK_NAMES = ("localhost",)


def is_loopback(host: str) -> bool:
    import ipaddress

    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def split_host(value: str) -> tuple[str, int | None]:
    """'name:8080' / '[::1]:8080' / 'name' -> (lowercase name, port or None); ('', None) if malformed."""
    value = value.strip().lower()
    if value.startswith("["):
        name, _, rest = value[1:].partition("]")
        port = rest[1:] if rest.startswith(":") else ""
        if rest and not rest.startswith(":"):
            return "", None
    else:
        name, _, port = value.partition(":")
    if port and not port.isdigit():
        return "", None
    return name.rstrip("."), int(port) if port else None


class Gate:
    """Who may talk to the viewer. A browser lets any web page open a WebSocket to any address, and
    DNS rebinding lets a page on the attacker's name reach 127.0.0.1 as if same-origin; so:
    - every request's Host must be an IP address, localhost, this machine's name or an allowed
      host (a rebinding page always arrives with the attacker's name);
    - a WebSocket from a browser must come from the viewer's own page (Origin = Host) or an
      allowed origin; non-browser clients send no Origin;
    - with a token (required beyond loopback) the page and the WebSocket must carry it."""

    def __init__(self, settings: ViewerSettings, node: Node):
        import secrets
        import socket

        self.settings, self.node = settings, node
        self.hosts = {h.lower().rstrip(".") for h in settings.allowed_hosts}
        me = socket.gethostname().lower()
        self.hosts |= {me, me + ".local", *LOOPBACK_NAMES}
        self.origins = {o.rstrip("/").lower() for o in settings.allowed_origins}
        self.token = settings.token or ("" if is_loopback(settings.host) else secrets.token_urlsafe(18))
        for k in ("refused_host", "refused_origin", "refused_token"):
            node.extra[k] = 0.0

    def refuse(self, kind: str, why: str):
        from aiohttp import web

        self.node.count(f"refused_{kind}")
        self.node.warn(f"refused-{kind}", f"refused a request: {why}")
        return web.Response(status=403 if kind != "token" else 401, text=f"ballbot-vision viewer: {why}\n")

    def host_ok(self, host: str | None) -> bool:
        import ipaddress

        name, _ = split_host(host or "")
        if not name:
            return False
        try:
            ipaddress.ip_address(name)
            return True  # an address cannot be rebound to another machine
        except ValueError:
            return name in self.hosts

    def origin_ok(self, origin: str | None, host: str) -> bool:
        if origin is None:
            return True  # not a browser: nothing to forge on a user's behalf
        o = origin.rstrip("/").lower()
        if "*" in self.origins or o in self.origins:
            return True
        scheme, sep, rest = o.partition("://")
        if not sep or scheme not in ("http", "https"):
            return False  # "null" (sandboxed frames, files) and anything odd
        default = 443 if scheme == "https" else 80
        oname, oport = split_host(rest)
        hname, hport = split_host(host)
        return bool(oname) and oname == hname and (oport or default) == (hport or default)

    def token_ok(self, request) -> bool:
        import hmac

        if not self.token:
            return True
        given = request.query.get("token", "")
        return hmac.compare_digest(given.encode(), self.token.encode())

    def middleware(self):
        from aiohttp import web

        @web.middleware
        async def check(request, handler):
            host = request.headers.get("Host")
            if not self.host_ok(host):
                return self.refuse("host", f"Host {host!r} is not a name this viewer answers to (allowed_hosts)")
            if request.path in ("/", "/ws") and not self.token_ok(request):
                return self.refuse("token", "a token is required: open the URL the viewer printed at start "
                                            "(/?token=...)")
            if request.path == "/ws" and not self.origin_ok(request.headers.get("Origin"), host or ""):
                return self.refuse("origin", f"a WebSocket from the page of {request.headers.get('Origin')!r}, "
                                             f"not this viewer's (allowed_origins)")
            return await handler(request)

        return check


def make_app(viewer: Viewer, hub: Hub, gate: Gate | None = None):
    from aiohttp import WSMsgType, web

    async def index(_request):
        return web.FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    async def health(_request):
        return web.json_response({"ok": True, "clients": hub.clients, "version": hub.version})

    async def websocket(request):
        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=64 * 1024)
        await ws.prepare(request)
        hub.clients += 1
        acked = asyncio.Event()
        acked.set()

        async def sender() -> None:
            version = 0
            while not ws.closed:
                # latest-frame-only: wait until the page has drawn the last update (or 3 s), then
                # send the newest; whatever came in between is skipped for this client
                try:
                    await asyncio.wait_for(acked.wait(), 3.0)
                except TimeoutError:
                    pass
                new_version, message = await hub.newer_than(version)
                hub.skipped += max(0, new_version - version - 1) if version else 0
                version = new_version
                acked.clear()
                try:
                    await ws.send_bytes(message)
                except (ConnectionError, RuntimeError):  # the page went away mid-send
                    return
                hub.sent += 1

        task = asyncio.ensure_future(sender())
        try:
            async for msg in ws:
                if msg.type != WSMsgType.TEXT:
                    continue
                try:
                    cmd = json.loads(msg.data)
                except ValueError:
                    continue
                if not isinstance(cmd, dict):
                    continue
                if cmd.get("ack"):
                    acked.set()
                elif "replay" in cmd:
                    frames = cmd.get("frames", 1)
                    speed = cmd.get("speed")
                    error = viewer.replay(str(cmd["replay"]), frames if isinstance(frames, int) else 1,
                                          speed if isinstance(speed, (int, float)) else None)
                    if error:
                        await ws.send_str(json.dumps({"error": error}))
        finally:
            task.cancel()
            hub.clients -= 1
        return ws

    app = web.Application(middlewares=[gate.middleware()] if gate is not None else [])
    app.router.add_get("/", index)
    app.router.add_get("/healthz", health)
    async def no_favicon(_request: web.Request) -> web.Response:
        return web.Response(status=204)

    app.router.add_get("/favicon.ico", no_favicon)
    app.router.add_get("/ws", websocket)
    app.router.add_static("/static/", STATIC)
    return app


async def serve(node: Node, settings: ViewerSettings, viewer: Viewer, hub: Hub,
                started: threading.Event | None = None) -> None:
    hub.bind(asyncio.get_running_loop())
    gate = Gate(settings, node)
    runner, port = await start_site(make_app(viewer, hub, gate), settings.host, settings.port, "viewer",
                                    "another viewer? choose one with --port")
    node.extra["port"] = float(port)
    url = f"http://{'127.0.0.1' if settings.host in ('0.0.0.0', '::', '') else settings.host}:{port}/"
    url += f"?token={gate.token}" if gate.token else ""
    print(f"viewer: open {url}", flush=True)
    if gate.token and not settings.token:
        print("viewer: listening beyond loopback: every page needs this token (set your own with "
              "BALLBOT_VIEWER_TOKEN / --token)", flush=True)
    log.info("viewer listening on %s:%d", settings.host, port)
    if started is not None:
        started.set()
    try:
        await asyncio.get_running_loop().run_in_executor(None, node.stop_event.wait)
    finally:
        await runner.cleanup()


def preflight(settings: ViewerSettings) -> None:
    """Before the service is up (cli.cmd_run): the viewer's optional dependency is installed. `up
    --viewer` then disables the viewer alone (exit status 3) and keeps the pipeline running."""
    from common.errors import require

    require(("aiohttp",), "viewer", "the viewer")


def run(node: Node, settings: ViewerSettings) -> None:
    preflight(settings)
    hub = Hub()
    viewer = Viewer(node, settings, hub)
    viewer.subscribe_small()
    threading.Thread(target=viewer.compose_loop, name="compose", daemon=True).start()
    asyncio.run(serve(node, settings, viewer, hub))
