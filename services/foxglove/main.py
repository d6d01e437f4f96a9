"""foxglove: a live Foxglove WebSocket server (`ballbot-vision run foxglove`, `up --foxglove`).

Open ws://127.0.0.1:8765 in Foxglove (desktop or web app: Open connection, Foxglove WebSocket) and
see what the robot sees: the rectified left image with each obstacle's box, the disparity in
colour, the obstacles as 3D boxes, the free-space grid, the ground and the transform base ->
camera, with the messages and schemas of Foxglove's own SDK (the server is the SDK's too).

It can never slow the robot:
- Zenoh callbacks only keep the newest payload of each stream (an older one not yet converted is
  overwritten and counted as skipped); only the small streams (obstacles, free space) are decoded
  there, as the viewer does, so that a flood of malformed lists cannot take the slot of the good
  ones: it costs its own messages, the lists go on; the images are decoded by the converter, and
  an image payload without its stamp attachment (every publisher of ours stamps) is dropped;
- the image streams are subscribed to only while a Foxglove client subscribes to their channels;
- one converter thread turns at most `max_fps` sets of messages a second into Foxglove messages,
  only for channels some client subscribed to;
- the SDK's server keeps at most `backlog` messages per client and drops the oldest: a slow client
  skips frames, it never holds anything up.

Origins: the server binds to 127.0.0.1 by default and refuses WebSocket requests that a web page
of another site makes (a browser sends its Origin header): any page you visit could otherwise
watch the robot's camera. Clients that send no Origin (the desktop app, scripts) are served; web
origins only when named in `allowed_origins` (e.g. https://app.foxglove.dev for the web app). The
SDK's server has no such check, so it listens on a loopback port of its own that only this front
door (aiohttp, the viewer's dependency) connects to.
"""
from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pydantic import Field

from common.errors import BallbotError
from common.keys import topic
from common.messages import DisparityMap, FreeSpace, GroundTruth, Message, ObstacleList, StereoFrame
from common.node import Node
from common.settings import ServiceSettings
from common.web import start_site

log = logging.getLogger("ballbot.foxglove")

SUBSCRIBES = ["frames_rect", "disparity", "obstacles", "freespace", "truth"]
PUBLISHES: list[str] = []
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")


class FoxgloveSettings(ServiceSettings):
    section = "foxglove"
    host: str = Field("127.0.0.1", description="address to bind (0.0.0.0: every interface; the server has no "
                                                "login, so only on networks you trust)")
    port: int = Field(8765, ge=0, le=65535, description="WebSocket port (0: any free port)")
    allowed_origins: list[str] = Field(default_factory=list, description="web origins whose pages may connect "
                                       "(JSON list, e.g. [\"https://app.foxglove.dev\"] for Foxglove's web app; "
                                       "\"*\": any); clients that send no Origin (the desktop app, scripts) are "
                                       "always served")
    max_fps: float = Field(15.0, gt=0, le=60, description="image and scene updates per second at most")
    jpeg_quality: int = Field(80, ge=10, le=100, description="JPEG quality of the images sent")
    backlog: int = Field(64, ge=4, le=4096, description="messages kept per client; beyond it the oldest are dropped")
    idle_unsubscribe_s: float = Field(5.0, ge=0, le=3600, description="drop the image subscriptions this long "
                                      "after the last client stopped watching them")


def origin_allowed(origin: str | None, allowed: list[str]) -> bool:
    """A request without an Origin header is not a web page's; one with it only if named (or '*')."""
    if not origin:
        return True
    return "*" in allowed or origin.rstrip("/") in {a.rstrip("/") for a in allowed}


# -- channels and conversion ------------------------------------------------------------------------

RECT_LEFT, CAMERA_INFO, DISPARITY_COLOR = "/frames/rectified/left", "/frames/rectified/camera_info", "/disparity/color"
OBSTACLES, OBSTACLE_BOXES, OBSTACLE_SCENE = "/obstacles", "/obstacles/boxes", "/obstacles/scene"
FREESPACE_GRID, GROUND, TF, TRUTH_BOXES = "/freespace/grid", "/ground", "/tf", "/truth/boxes"
# which Zenoh stream feeds which channels (an image stream is subscribed to only while one of its
# channels has a subscriber)
FEEDS = {"frames_rect": (RECT_LEFT, CAMERA_INFO), "disparity": (DISPARITY_COLOR,), "truth": (TRUTH_BOXES,),
         "obstacles": (OBSTACLES, OBSTACLE_BOXES, OBSTACLE_SCENE, GROUND, TF), "freespace": (FREESPACE_GRID,)}
IMAGE_KINDS = ("frames_rect", "disparity", "truth")
MODELS: dict[str, type[Message]] = {"frames_rect": StereoFrame, "disparity": DisparityMap, "truth": GroundTruth,
                                    "obstacles": ObstacleList, "freespace": FreeSpace}


def make_channels(context) -> dict[str, Any]:
    """One SDK channel per topic, typed (the SDK's schemas); the obstacle list as JSON with its JSON Schema."""
    import foxglove
    from foxglove import channels as fc

    obstacle_schema = ObstacleList.model_json_schema()
    obstacle_schema["title"] = "ballbot.ObstacleList"
    return {RECT_LEFT: fc.CompressedImageChannel(RECT_LEFT, context=context),
            CAMERA_INFO: fc.CameraCalibrationChannel(CAMERA_INFO, context=context),
            DISPARITY_COLOR: fc.CompressedImageChannel(DISPARITY_COLOR, context=context),
            OBSTACLES: foxglove.Channel(OBSTACLES, schema=obstacle_schema, context=context),
            OBSTACLE_BOXES: fc.ImageAnnotationsChannel(OBSTACLE_BOXES, context=context),
            OBSTACLE_SCENE: fc.SceneUpdateChannel(OBSTACLE_SCENE, context=context),
            GROUND: fc.SceneUpdateChannel(GROUND, context=context),
            TF: fc.FrameTransformChannel(TF, context=context),
            FREESPACE_GRID: fc.GridChannel(FREESPACE_GRID, context=context),
            TRUTH_BOXES: fc.ImageAnnotationsChannel(TRUTH_BOXES, context=context)}


def convert(kind: str, msg, jpeg_quality: int, wanted: Callable[[str], bool]) -> list[tuple[str, Any, int]]:
    """One pipeline message -> [(topic, SDK message or JSON text, log time ns)] for the channels
    someone watches (`wanted`); the picture work (JPEG) only for those."""
    from cores import foxglove as F
    from cores.recording import colorize_disparity, compress_image, encode_array

    out: list[tuple[str, Any, int]] = []
    t = msg.stamp_ns
    if kind == "frames_rect":
        if wanted(RECT_LEFT):
            data, fmt = compress_image(msg.left, "jpeg", jpeg_quality)
            out.append((RECT_LEFT, F.compressed_image(t, "camera", data, fmt), t))
        if wanted(CAMERA_INFO) and msg.camera is not None:
            out.append((CAMERA_INFO, F.camera_calibration(t, msg.camera), t))
    elif kind == "disparity":
        if wanted(DISPARITY_COLOR):
            data = encode_array(colorize_disparity(msg), "jpeg", jpeg_quality)
            out.append((DISPARITY_COLOR, F.compressed_image(t, "camera", data, "jpeg"), t))
    elif kind == "truth":
        if wanted(TRUTH_BOXES):
            out.append((TRUTH_BOXES, F.truth_annotations(msg), t))
    elif kind == "obstacles":
        t = msg.publish_ns if msg.stale else msg.stamp_ns
        if wanted(OBSTACLES):
            out.append((OBSTACLES, msg.model_dump_json(), t))
        if not msg.stale:
            if wanted(OBSTACLE_BOXES):
                out.append((OBSTACLE_BOXES, F.obstacle_annotations(msg), t))
            if wanted(OBSTACLE_SCENE):
                out.append((OBSTACLE_SCENE, F.obstacle_scene(msg), t))
        if wanted(GROUND):
            out.append((GROUND, F.ground_scene(msg), t))
        if wanted(TF) and msg.mount is not None:  # the camera where the segmenter placed it for this list
            out.append((TF, F.base_to_camera(msg.stamp_ns, msg.mount), t))
    elif kind == "freespace":
        if wanted(FREESPACE_GRID):
            out.append((FREESPACE_GRID, F.freespace_grid(msg), t))
    return out


@dataclass
class Slots:
    """The newest undelivered payload (or, for a small stream, decoded message) of each stream
    (newest wins)."""

    payloads: dict[str, Any] = field(default_factory=dict)
    skipped: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)
    new: threading.Event = field(default_factory=threading.Event)

    def put(self, kind: str, payload: Any) -> None:
        with self.lock:
            if kind in self.payloads:
                self.skipped += 1
            self.payloads[kind] = payload
        self.new.set()

    def take_all(self) -> dict[str, Any]:
        with self.lock:
            taken, self.payloads = self.payloads, {}
            self.new.clear()
        return taken


class Bridge:
    """The Zenoh side: small streams always, image streams while watched, one converter thread."""

    def __init__(self, node: Node, settings: FoxgloveSettings, channels: dict[str, Any]):
        self.node, self.settings, self.channels = node, settings, channels
        self.slots = Slots()
        self._image_subs: dict[str, Any] = {}
        self._last_watched: dict[str, float] = {}
        self.sent = 0
        self.clients = 0

    def watched(self, topic_name: str) -> bool:
        return self.channels[topic_name].has_sinks()

    def _keep(self, kind: str):
        def on_sample(sample) -> None:  # Zenoh's thread: keep the bytes, nothing else
            if self.node.stamp_or_drop(sample, kind) is None:
                return
            self.slots.put(kind, sample.payload.to_bytes())
        return on_sample

    def _keep_decoded(self, kind: str):
        def on_sample(sample) -> None:  # Zenoh's thread: a small message, decoded; a malformed one dropped here
            msg = self.node.decode_or_drop(sample.payload.to_bytes(), MODELS[kind], f"{kind} message")
            if msg is not None:
                self.slots.put(kind, msg)
        return on_sample

    def subscribe_small(self) -> None:
        rid = self.node.robot_id
        for kind in ("obstacles", "freespace"):
            self.node.subscribe(topic(kind).key(rid), self._keep_decoded(kind))

    def manage_image_subscriptions(self) -> None:
        now = time.monotonic()
        for kind in IMAGE_KINDS:
            if any(self.watched(t) for t in FEEDS[kind]):
                self._last_watched[kind] = now
                if kind not in self._image_subs:
                    self._image_subs[kind] = self.node.subscribe(topic(kind).key(self.node.robot_id),
                                                                 self._keep(kind), keep=False)
                    log.info("foxglove: a client watches %s; subscribed to %s", ", ".join(FEEDS[kind]), kind)
            elif (kind in self._image_subs
                  and now - self._last_watched.get(kind, 0.0) >= self.settings.idle_unsubscribe_s):
                self._image_subs.pop(kind).undeclare()
                log.info("foxglove: nobody watches %s any more; %s unsubscribed", ", ".join(FEEDS[kind]), kind)
        self.node.extra["image_streams"] = float(len(self._image_subs))

    def convert_loop(self) -> None:
        period = 1.0 / self.settings.max_fps
        next_t = time.monotonic()
        while self.node.running:
            self.manage_image_subscriptions()
            if not self.slots.new.wait(0.2):
                continue
            delay = next_t - time.monotonic()
            if delay > 0:  # at most max_fps rounds; what arrives meanwhile overwrites its slot
                self.node.stop_event.wait(delay)
            next_t = max(next_t + period, time.monotonic())
            for kind, item in self.slots.take_all().items():
                if not any(self.watched(t) for t in FEEDS[kind]):
                    continue  # nobody watches its channels: not even decoded
                msg = item if isinstance(item, Message) else self.node.decode_or_drop(item, MODELS[kind],
                                                                                       f"{kind} message")
                if msg is None:
                    continue
                with self.node.processing(msg):
                    for name, message, log_time in convert(kind, msg, self.settings.jpeg_quality, self.watched):
                        self.channels[name].log(message, log_time=int(log_time))
                        self.sent += 1
            self.node.extra.update({"sent": float(self.sent), "skipped": float(self.slots.skipped),
                                    "clients": float(self.clients)})


# -- the front door: origin check, then the SDK's server -----------------------------------------------

async def serve(node: Node, settings: FoxgloveSettings, bridge: Bridge, sdk_port: int,
                started: threading.Event | None = None) -> None:
    import aiohttp
    from aiohttp import WSMsgType, web

    session = aiohttp.ClientSession()

    async def websocket(request: web.Request):
        origin = request.headers.get("Origin")
        if not origin_allowed(origin, settings.allowed_origins):
            node.count("refused_origins")
            node.warn("origin", f"refused a WebSocket from origin {origin!r} (allow it with --allowed-origins "
                                f"'[\"{origin}\"]' or the foxglove section's allowed_origins)")
            return web.Response(status=403, text=f"origin {origin} is not allowed (see allowed_origins)\n")
        offered = [p.strip() for p in request.headers.get("Sec-WebSocket-Protocol", "").split(",") if p.strip()]
        try:
            upstream = await session.ws_connect(f"ws://127.0.0.1:{sdk_port}/", protocols=tuple(offered or SUBPROTOCOLS),
                                                max_msg_size=0, autoping=True)
        except aiohttp.ClientError as e:
            return web.Response(status=502, text=f"the Foxglove server refused the connection: {e}\n")
        ws = web.WebSocketResponse(protocols=(upstream.protocol,) if upstream.protocol else (), heartbeat=10.0,
                                   max_msg_size=1 << 20)
        await ws.prepare(request)
        bridge.clients += 1
        node.extra["clients"] = float(bridge.clients)

        async def pump(src, dst) -> None:
            async for msg in src:
                if msg.type == WSMsgType.TEXT:
                    await dst.send_str(msg.data)
                elif msg.type == WSMsgType.BINARY:
                    await dst.send_bytes(msg.data)
                else:
                    break

        tasks = [asyncio.ensure_future(pump(upstream, ws)), asyncio.ensure_future(pump(ws, upstream))]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        except (ConnectionError, RuntimeError):  # a client gone mid-send
            pass
        finally:
            for t in tasks:
                t.cancel()
            await upstream.close()
            await ws.close()
            bridge.clients -= 1
            node.extra["clients"] = float(bridge.clients)
        return ws

    async def health(_request):
        return web.json_response({"ok": True, "clients": bridge.clients})

    app = web.Application()
    app.router.add_get("/", websocket)
    app.router.add_get("/healthz", health)
    try:
        runner, port = await start_site(app, settings.host, settings.port, "foxglove",
                                        "another Foxglove server? choose one with --port")
    except BallbotError:
        await session.close()
        raise
    node.extra["port"] = float(port)
    shown = "127.0.0.1" if settings.host in ("0.0.0.0", "") else settings.host
    print(f"foxglove: open ws://{shown}:{port} in Foxglove (Open connection > Foxglove WebSocket)", flush=True)
    log.info("foxglove listening on %s:%d", settings.host, port)
    node.status = "serving"
    if started is not None:
        started.set()
    try:
        await asyncio.get_running_loop().run_in_executor(None, node.stop_event.wait)
    finally:
        await runner.cleanup()
        await session.close()


def run(node: Node, settings: FoxgloveSettings) -> None:
    try:
        import aiohttp  # noqa: F401
        import foxglove
    except ImportError as e:
        raise BallbotError(f"the Foxglove server needs {e.name}: pip install -e . (it is a dependency)") from None
    # the SDK's own lines name its inner port, which is not the one to connect to
    logging.getLogger("foxglove").setLevel(logging.WARNING)
    context = foxglove.Context()
    channels = make_channels(context)
    # the SDK's server, on a loopback port only the front door uses
    server = foxglove.start_server(name=f"ballbot-vision {node.robot_id}", host="127.0.0.1", port=0, context=context,
                                   message_backlog_size=settings.backlog)
    try:
        bridge = Bridge(node, settings, channels)
        bridge.subscribe_small()
        threading.Thread(target=bridge.convert_loop, name="convert", daemon=True).start()
        asyncio.run(serve(node, settings, bridge, server.port))
    finally:
        server.stop()
