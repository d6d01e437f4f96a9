"""The live Foxglove server (`run foxglove`, `up --foxglove`) against a real client speaking the
Foxglove WebSocket protocol as its spec describes it (github.com/foxglove/ws-protocol): the
serverInfo and advertise messages, subscribe, and binary message data (opcode 1, subscription id,
log time, payload) decoded with the schema the server advertised, by Google's protobuf runtime.
Origins: a web page of another site is refused, a named one served."""
from __future__ import annotations

import asyncio
import base64
import json
import struct
import time

import cv2
import numpy as np
import pytest
from helpers import Collector, Up, free_port, wait_port

from common.keys import topic
from common.messages import ServiceStats
from services.foxglove.main import origin_allowed

aiohttp = pytest.importorskip("aiohttp")


def test_origins_without_a_header_or_named_are_served_others_refused():
    assert origin_allowed(None, []) and origin_allowed("", [])  # the desktop app, scripts
    assert not origin_allowed("https://evil.example", [])
    assert not origin_allowed("https://app.foxglove.dev", [])
    assert origin_allowed("https://app.foxglove.dev", ["https://app.foxglove.dev/"])
    assert not origin_allowed("https://app.foxglove.dev.evil.example", ["https://app.foxglove.dev"])
    assert origin_allowed("http://anything", ["*"])


class FoxgloveClient:
    """A minimal Foxglove WebSocket client, written from the protocol spec."""

    def __init__(self, ws):
        self.ws = ws
        self.server_info: dict | None = None
        self.channels: dict[str, dict] = {}  # topic -> advertised channel
        self.subscriptions: dict[int, dict] = {}  # subscription id -> channel
        self._classes: dict[int, object] = {}

    async def handshake(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while self.server_info is None or not self.channels:
            msg = await self.ws.receive(timeout=max(0.1, deadline - time.monotonic()))
            assert msg.type == aiohttp.WSMsgType.TEXT, msg
            self._control(json.loads(msg.data))

    def _control(self, doc: dict) -> None:
        if doc["op"] == "serverInfo":
            self.server_info = doc
        elif doc["op"] == "advertise":
            for ch in doc["channels"]:
                self.channels[ch["topic"]] = ch

    async def subscribe(self, topics: list[str]) -> None:
        subs = []
        for i, t in enumerate(topics, start=1):
            self.subscriptions[i] = self.channels[t]
            subs.append({"id": i, "channelId": self.channels[t]["id"]})
        await self.ws.send_str(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def decode(self, channel: dict, payload: bytes):
        if channel["encoding"] == "json":
            return json.loads(payload)
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf"
        if channel["id"] not in self._classes:
            pool = descriptor_pool.DescriptorPool()
            for fd in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file:
                pool.Add(fd)
            self._classes[channel["id"]] = message_factory.GetMessageClass(
                pool.FindMessageTypeByName(channel["schemaName"]))
        return self._classes[channel["id"]].FromString(payload)

    async def messages(self, timeout: float):
        """(topic, log time ns, decoded message) as they come, until `timeout` s have passed."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg = await self.ws.receive(timeout=left)
            except TimeoutError:
                return
            if msg.type == aiohttp.WSMsgType.TEXT:
                self._control(json.loads(msg.data))
                continue
            assert msg.type == aiohttp.WSMsgType.BINARY, msg
            data = msg.data
            assert data[0] == 0x01, f"opcode {data[0]}"  # message data
            sub_id, log_time = struct.unpack_from("<IQ", data, 1)
            channel = self.subscriptions[sub_id]
            yield channel["topic"], log_time, self.decode(channel, data[13:])


async def _watch(port: int, topics: list[str], want, timeout: float) -> tuple[FoxgloveClient, dict[str, list]]:
    got: dict[str, list] = {t: [] for t in topics}
    async with aiohttp.ClientSession() as session:
        async with session.ws_connect(f"ws://127.0.0.1:{port}/", protocols=("foxglove.sdk.v1",),
                                      max_msg_size=64 << 20) as ws:
            client = FoxgloveClient(ws)
            await client.handshake(60)
            await client.subscribe(topics)
            async for name, log_time, msg in client.messages(timeout):
                got[name].append((log_time, msg))
                if want(got):
                    break
    return client, got


async def _refused(port: int, origin: str) -> int:
    async with aiohttp.ClientSession() as session:
        try:
            async with session.ws_connect(f"ws://127.0.0.1:{port}/", protocols=("foxglove.sdk.v1",),
                                          headers={"Origin": origin}):
                return 101
        except aiohttp.WSServerHandshakeError as e:
            return e.status


@pytest.mark.system
def test_image_annotations_say_when_a_list_cannot_vouch_for_its_view():
    from common.messages import Obstacle, ObstacleList
    from cores import foxglove as F

    def texts(msg: ObstacleList) -> list[str]:  # read back as a Foxglove client would, by the schema sent
        a = F.obstacle_annotations(msg)
        schema = a.get_schema()
        return [t.text for t in F.ProtobufDecoder().decode(schema.name, schema.data, a.encode()).texts]

    o = Obstacle(id=3, position_m=(0.1, 0.2, 2.0), size_m=(0.5, 0.6, 0.3), distance_m=1.9, bbox_px=(10, 20, 30, 40),
                 area_px=10, disparity_px=30.0, confidence=0.9)
    lst = ObstacleList(robot_id="r", seq=1, stamp_ns=5, publish_ns=5, stale=False, obstacles=[o])
    assert texts(lst) == ["#3 1.90 m"]
    assert texts(lst.model_copy(update={"obstacles": [], "degraded": ["near-unmeasured"]})) == \
        ["NOT A FULL VIEW: near-unmeasured"]
    assert texts(lst.model_copy(update={"stale": True})) == ["#3 1.90 m", "STALE"]


def test_a_foxglove_client_subscribes_and_decodes_the_live_pipeline():
    port = free_port()
    up = Up(robot_id="fox", extra_args=["--foxglove"],
            extra_env={"BALLBOT_FOXGLOVE_PORT": str(port), "BALLBOT_FOXGLOVE_IDLE_UNSUBSCRIBE_S": "0.5",
                       "BALLBOT_FOXGLOVE_ALLOWED_ORIGINS": '["https://app.foxglove.dev"]'})
    try:
        wait_port(port, up.proc, 120)
        stats = Collector(ServiceStats)
        with up.session() as s:
            s.declare_subscriber(topic("stats").key("fox", service="foxglove", instance="*"), stats)
            # nobody watches: the image streams are not subscribed to
            assert stats.wait_for(lambda items: len(items) >= 2, 120), "no stats from the foxglove service"
            assert stats.items[-1].extra.get("image_streams") == 0.0

            topics = ["/frames/rectified/left", "/frames/rectified/camera_info", "/disparity/color",
                      "/obstacles/scene", "/obstacles/boxes", "/freespace/grid", "/tf", "/ground", "/obstacles"]
            # (watched until the service's stats, once a second, have shown its image subscriptions too:
            # a fast client may otherwise be gone before the next stats)
            client, got = asyncio.run(_watch(port, topics, lambda g: all(len(v) >= 2 for v in g.values()) and any(
                st.extra.get("image_streams", 0) >= 2 for st in stats.items), 180))
            assert client.server_info["name"] == "ballbot-vision fox"
            for t in topics[:-1]:  # the SDK's own schemas, protobuf
                ch = client.channels[t]
                assert ch["schemaEncoding"] == "protobuf" and ch["schemaName"].startswith("foxglove."), ch
            assert client.channels["/obstacles"]["schemaName"] == "ballbot.ObstacleList"
            missing = [t for t, v in got.items() if len(v) < 2]
            assert not missing, f"no messages on {missing} within 180 s"

            _, image = got["/frames/rectified/left"][-1]
            assert image.format == "jpeg" and image.frame_id == "camera"
            picture = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_UNCHANGED)
            assert picture.shape[:2] == (480, 640) and picture.std() > 10  # the textured scene, not a blank
            disparity = cv2.imdecode(np.frombuffer(got["/disparity/color"][-1][1].data, np.uint8), cv2.IMREAD_COLOR)
            assert disparity.shape == (480, 640, 3)
            info = got["/frames/rectified/camera_info"][-1][1]
            assert (info.width, info.height) == (640, 480) and info.K[0] > 100
            # the synthetic scene's two boxes, 1.5-3 m ahead, as 3D boxes in the camera frame
            scenes = [m for _, m in got["/obstacles/scene"] if len(m.entities) >= 1]
            assert scenes, "no obstacle in any scene update"
            cube = scenes[-1].entities[0].cubes[0]
            assert scenes[-1].entities[0].frame_id == "camera" and 1.0 < cube.pose.position.z < 4.0
            lists = [doc for _, doc in got["/obstacles"]]
            assert all(doc["robot_id"] == "fox" for doc in lists)
            grid = got["/freespace/grid"][-1][1]
            assert grid.frame_id == "base"
            assert len(grid.data) == grid.column_count * (len(grid.data) // grid.column_count)
            tf = got["/tf"][-1][1]
            assert (tf.parent_frame_id, tf.child_frame_id) == ("base", "camera") and 0.3 < tf.translation.z < 3.0
            ground = got["/ground"][-1][1]
            assert ground.entities[0].frame_id == "base" and "ground" in ground.entities[0].texts[0].text
            # each message is logged at its capture time: the image and the scene of one frame line up
            image_times = {t for t, _ in got["/frames/rectified/left"]}
            assert all(t > 1.6e18 for t in image_times)

            # a malformed obstacle list while a client watches: logged, counted, dropped; the lists go on
            import threading

            stop = threading.Event()

            def garbage() -> None:
                pub = s.declare_publisher(topic("obstacles").key("fox"))
                while not stop.wait(0.005):
                    pub.put(b"\x00not msgpack\xff")

            t = threading.Thread(target=garbage, daemon=True)
            t.start()
            try:
                _, more = asyncio.run(_watch(port, ["/obstacles"], lambda g: len(g["/obstacles"]) >= 5, 120))
            finally:
                stop.set()
                t.join(10)
            assert len(more["/obstacles"]) >= 5
            assert stats.wait_for(lambda items: items[-1].decode_errors >= 1, 30), \
                [(st.decode_errors, st.status) for st in stats.items[-3:]]

            # watched: subscribed; the client gone: unsubscribed again (idle 0.5 s)
            n = len(stats.items)
            assert stats.wait_for(lambda items: len(items) > n and items[-1].extra.get("image_streams") == 0.0, 60), \
                [s.extra.get("image_streams") for s in stats.items[-5:]]
            assert any(s.extra.get("image_streams", 0) >= 2 for s in stats.items), "never subscribed to the images"

        # a web page of another site is refused before the SDK's server sees it; a named one is served
        assert asyncio.run(_refused(port, "https://evil.example")) == 403
        assert asyncio.run(_refused(port, "https://app.foxglove.dev")) == 101
    finally:
        up.stop()
    assert "refused a WebSocket from origin 'https://evil.example'" in up.log_path.read_text()
