"""The ROS 2 bridge and capture --source ros2 as users run them, over real Zenoh, checked with
clients that are not ours: raw Zenoh sessions that parse keys, tokens and attachments as
rmw_zenoh's sources describe them, a rosbags typestore built here from .msg text, and
zenoh-ros2-sdk (an independent Python ROS-2-over-Zenoh implementation: its own type hashes,
key assembly and graph discovery) subscribing to the bridge and publishing camera topics."""
from __future__ import annotations

import os
import subprocess
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros2 extra (rosbags) is not installed")

from helpers import REPO, Collector, cli, free_port, wait_port

from common import codec
from common.keys import topic
from common.messages import FreeSpace, ObstacleList, ServiceStats
from common.zenoh_session import ZenohOptions, open_session

pytestmark = pytest.mark.system

# ROS 2 message definitions (Jazzy), written out here so the decoder and zenoh-ros2-sdk's hashes
# do not come from the code under test.
MSG = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n",
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": "std_msgs/Header header\nObjectHypothesisWithPose[] results\n"
                                   "BoundingBox3D bbox\nstring id\n",
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nDetection3D[] detections\n",
    "sensor_msgs/msg/Image": "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
                             "uint8 is_bigendian\nuint32 step\nuint8[] data\n",
    "sensor_msgs/msg/RegionOfInterest": "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\n"
                                        "bool do_rectify\n",
    "sensor_msgs/msg/CameraInfo": "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
                                  "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
                                  "uint32 binning_y\nRegionOfInterest roi\n",
}


def independent_typestore():
    """rosbags' Jazzy store plus the vision_msgs above: decodes what the bridge published."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name, text in MSG.items():
        if name.startswith("vision_msgs"):
            types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


class Sdk:
    """zenoh-ros2-sdk pointed at a router, with message definitions from a local folder (it
    would otherwise fetch them from git)."""

    def __init__(self, port: int, tmp: Path):
        pytest.importorskip("zenoh_ros2_sdk", reason="zenoh-ros2-sdk not installed")
        from zenoh_ros2_sdk import message_registry
        from zenoh_ros2_sdk.session import ZenohSession

        for name, text in MSG.items():
            p = tmp / "msgs" / (name + ".msg")
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(text)
        message_registry._registry = None
        message_registry.get_registry(str(tmp / "msgs"))
        if ZenohSession._instance is not None:
            ZenohSession._instance.close()
        self.port = port
        self.session = ZenohSession.get_instance("127.0.0.1", port)
        self.entities: list = []

    def close(self) -> None:
        for e in self.entities:
            e.close()
        self.session.close()


def start(args: list[str], log: Path, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen(cli(*args), stdout=open(log, "w"), stderr=subprocess.STDOUT, cwd=REPO,
                            env=dict(os.environ, **(env or {})))


def stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def wait_until(pred, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    ev = threading.Event()
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        ev.wait(0.2)


def parse_qos(text: str) -> dict:
    rel, dur, hist, *_ = text.split(":")
    kind, depth = hist.split(",")
    return {"reliability": int(rel or 1), "durability": int(dur or 2), "depth": int(depth or 42)}


EXPECTED = {
    "obstacles/detections": "vision_msgs/msg/Detection3DArray",
    "obstacles/markers": "visualization_msgs/msg/MarkerArray",
    "obstacles/points": "sensor_msgs/msg/PointCloud2",
    "camera/left/image_rect": "sensor_msgs/msg/Image",
    "camera/left/camera_info": "sensor_msgs/msg/CameraInfo",
    "freespace": "nav_msgs/msg/OccupancyGrid",
    "tf_static": "tf2_msgs/msg/TFMessage",
    "diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}


def test_bridge_topics_read_by_raw_zenoh_rosbags_and_zenoh_ros2_sdk(tmp_path):
    import xxhash
    import zenoh
    import zenoh.ext as zext

    store = independent_typestore()
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("mount: {height_m: 0.9, pitch_deg: 20}\n")  # the one section every service reads
    t0 = time.time_ns()
    up = start(["up", "--ros2", "--connect", ep, "--robot-id", "rb", "--config", str(cfg)], tmp_path / "up.log")
    samples: dict[str, list] = defaultdict(list)
    tokens: set[str] = set()
    lock = threading.Lock()
    try:
        wait_port(port, up)
        with open_session(ZenohOptions(mode="peer", connect=[ep])) as s:
            def on_data(smp) -> None:
                with lock:
                    if len(samples[str(smp.key_expr)]) < 40:
                        samples[str(smp.key_expr)].append((smp.payload.to_bytes(), smp.attachment.to_bytes()))

            s.declare_subscriber("0/**", on_data)
            s.liveliness().declare_subscriber("@ros2_lv/0/**", lambda smp: tokens.add(str(smp.key_expr)), history=True)
            lists = Collector(ObstacleList)
            s.declare_subscriber(topic("obstacles").key("rb"), lists)
            grids = Collector(FreeSpace)
            s.declare_subscriber(topic("freespace").key("rb"), grids)

            sdk = Sdk(port, tmp_path)
            from zenoh_ros2_sdk import ROS2Subscriber
            from zenoh_ros2_sdk.discovery import get_topic_info, get_topic_names_and_types

            got_sdk: list = []
            sdk.entities.append(ROS2Subscriber(topic="/obstacles/detections",
                                               msg_type="vision_msgs/msg/Detection3DArray",
                                               callback=got_sdk.append, router_port=port, domain_id=0))

            def enough() -> bool:
                with lock:
                    counts = {k.split("/sensor_msgs")[0].split("/vision_msgs")[0].split("/visualization_msgs")[0]:
                              len(v) for k, v in samples.items()}
                return len(got_sdk) >= 3 and all(any(c >= 4 for k, c in counts.items() if k == "0/" + t)
                                                 for t in ("obstacles/detections", "obstacles/markers",
                                                           "obstacles/points", "camera/left/image_rect"))
            wait_until(enough, 120, "the bridge's topics and three Detection3DArrays at zenoh-ros2-sdk")

            # free space: the segmenter's grid, republished as an OccupancyGrid
            wait_until(lambda: grids.items and any("/freespace/" in k for k in samples), 30, "an OccupancyGrid")

            # /tf_static is transient local: a subscriber that comes late still gets it (as tf2's
            # static listener does through rmw_zenoh's AdvancedSubscriber)
            late: list = []
            zext.declare_advanced_subscriber(s, "0/tf_static/*/*", lambda smp: late.append(smp.payload.to_bytes()),
                                             history=zext.HistoryConfig(detect_late_publishers=True))
            wait_until(lambda: late, 30, "/tf_static at a late transient-local subscriber")

            # the SDK's graph query gathers liveliness tokens for `timeout`; on a loaded machine one
            # query can come back before the publisher's token, and get_topic_info then returns None
            # (a topic it found no entity of), not an empty info: ask again until it is seen (deadline)
            graph: dict = {}

            def graph_seen() -> bool:
                graph["names"] = dict(get_topic_names_and_types(domain_id=0, router_port=port, timeout=2.0))
                graph["info"] = get_topic_info("/obstacles/detections", domain_id=0, router_port=port, timeout=2.0,
                                               verbose=True)
                info = graph["info"]
                return info is not None and info.publisher_count >= 1 and "/freespace" in graph["names"]
            wait_until(graph_seen, 60, "the bridge's publishers in the SDK's graph query")
            names, info = graph["names"], graph["info"]
            sdk.close()
    finally:
        stop(up)
    t1 = time.time_ns()

    # --- keys: <domain>/<topic>/<dds type>/<RIHS01 hash of that type> ---------------------------
    by_topic = {}
    for key, items in samples.items():
        parts = key.split("/")
        domain, dds, h, name = parts[0], parts[-2], parts[-1], "/".join(parts[1:-2])
        assert domain == "0" and name in EXPECTED, key
        ros_type = EXPECTED[name]
        pkg, _, typ = ros_type.split("/")
        assert dds == f"{pkg}::msg::dds_::{typ}_" and h == store.hash_rihs01(ros_type), key
        by_topic[name] = (key, items)
    assert set(by_topic) == set(EXPECTED)

    # --- tokens: one node, one MP per topic, fields as rmw_zenoh's liveliness_utils writes them --
    nodes = [t.split("/") for t in tokens if t.split("/")[5] == "NN" and t.endswith("/ballbot_vision")]
    assert len(nodes) == 1 and nodes[0][6:] == ["%", "%", "ballbot_vision"] and nodes[0][3] == nodes[0][4]
    zid, nid = nodes[0][2], nodes[0][3]
    pubs = {}
    for tk in tokens:
        f = tk.split("/")
        if f[5] != "MP" or f[2] != zid:
            continue
        assert len(f) == 13 and f[0] == "@ros2_lv" and f[1] == "0" and (f[2], f[3]) == (zid, nid), tk
        name = f[9].replace("%", "/").lstrip("/")
        key = by_topic[name][0]
        assert key.split("/")[-2:] == f[10:12], tk
        q = parse_qos(f[12])
        assert q["durability"] == (1 if name == "tf_static" else 2) and q["depth"] == (1 if name == "tf_static" else 10)
        pubs[name] = tk
    assert set(pubs) == set(EXPECTED) and len({tk.split("/")[4] for tk in pubs.values()}) == len(EXPECTED)

    # --- attachments: int64 seq, int64 source time, GID = XXH3-128 of the MP token; CDR payloads -
    lists_by_stamp = {m.stamp_ns: m for m in lists.items}
    grids_by_stamp = {m.stamp_ns: m for m in grids.items}
    grids_checked = 0
    trust_checked = 0
    tf_heights: list[float] = []
    checked = 0
    for name, (_key, items) in by_topic.items():
        seqs = []
        for payload, att in items:
            seq, ts, gid = zext.z_deserialize(tuple[zext.Int64, zext.Int64, list[zext.UInt8]], zenoh.ZBytes(att))
            assert bytes(gid) == xxhash.xxh3_128_intdigest(pubs[name].encode()).to_bytes(16, "little")
            assert t0 <= ts <= t1 and seq >= 1
            seqs.append(seq)
            assert payload[:4] == b"\x00\x01\x00\x00"
            msg = store.deserialize_cdr(payload, EXPECTED[name])
            # (a header only where the message has one: not TFMessage, not MarkerArray)
            stamp_ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec if hasattr(msg, "header") else None
            if name == "obstacles/detections" and stamp_ns in lists_by_stamp:
                ol = lists_by_stamp[stamp_ns]
                assert [d.id for d in msg.detections] == [str(o.id) for o in ol.obstacles]
                for d, o in zip(msg.detections, ol.obstacles):
                    c = d.bbox.center.position
                    assert np.allclose((c.x, c.y, c.z), o.position_m) and np.allclose(
                        (d.bbox.size.x, d.bbox.size.y, d.bbox.size.z), o.size_m)
                    assert msg.header.frame_id == "stereo_camera_optical_frame"
                checked += 1
            if name == "freespace":
                fs = grids_by_stamp.get(stamp_ns)
                if fs is not None:  # the grid the segmenter published with that capture stamp
                    assert np.array_equal(msg.data, np.frombuffer(fs.cells, np.int8))
                    assert msg.header.frame_id == "base_link"
                    assert (msg.info.width, msg.info.height) == (fs.width, fs.height)
                    assert msg.info.origin.position.x == pytest.approx(fs.origin_m[0])
                    assert (np.frombuffer(fs.cells, np.int8) == 0).any()  # the synthetic floor is seen free
                    grids_checked += 1
            if name == "diagnostics" and stamp_ns in lists_by_stamp:
                # the synthetic scene's lists are trusted: OK, and the list's own figures
                (st,) = msg.status
                kv = {x.key: x.value for x in st.values}
                ol = lists_by_stamp[stamp_ns]
                assert (st.level, st.name, st.hardware_id) == (0, "/ballbot_vision: obstacles", "rb"), st
                assert kv["seq"] == str(ol.seq) and kv["obstacles"] == str(len(ol.obstacles)) and kv["degraded"] == ""
                trust_checked += 1
            if name == "tf_static":
                tf = msg.transforms[0]
                assert (tf.header.frame_id, tf.child_frame_id) == ("base_link", "stereo_camera_optical_frame")
                # the configured mount (0.9 m) until a list carries the mount the segmenter used (its
                # fitted ground, which wins over the configured prior): the synthetic camera is 1.0 m
                # above its floor
                tf_heights.append(tf.transform.translation.z)
            if name == "obstacles/points" and msg.width:
                assert msg.point_step == 16 and len(msg.data) == 16 * msg.width
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), f"{name}: sequence numbers {seqs}"
    assert checked >= 2, "no Detection3DArray matched an obstacle list by stamp"
    assert grids_checked >= 1, "no OccupancyGrid matched a FreeSpace by stamp"
    assert trust_checked >= 2, "no DiagnosticArray matched an obstacle list by stamp"
    assert tf_heights and all(z == pytest.approx(0.9) or z == pytest.approx(1.0, abs=0.05) for z in tf_heights)
    assert tf_heights[-1] == pytest.approx(1.0, abs=0.05), tf_heights
    assert store.deserialize_cdr(late[0], "tf2_msgs/msg/TFMessage").transforms[0].child_frame_id

    # --- zenoh-ros2-sdk: computed the same hash (else it would not have received), decoded, listed
    assert all(m.__msgtype__ == "vision_msgs/msg/Detection3DArray" for m in got_sdk[:3])
    assert {"/obstacles/detections", "/obstacles/points", "/tf_static", "/freespace"} <= set(names)
    assert names["/obstacles/detections"] == ["vision_msgs/msg/Detection3DArray"]
    assert info.publisher_count == 1 and info.publishers[0].node_name == "ballbot_vision"


def test_capture_from_ros2_camera_topics_gives_obstacles(tmp_path):
    """A ROS 2 'camera driver' (zenoh-ros2-sdk publishers) sends the synthetic scene's raw pairs
    and the rig's CameraInfo; rectify has no calibration of its own (a real source's frames are
    refused until one arrives) and must take the CameraInfo's, which capture signs; obstacles must
    come out where the scene's truth puts them. (A configured rectify.calibration is what rectify
    starts with: a CameraInfo more than 5 % away from it is refused, see test_reliability.py.)"""
    from cores import camera
    from services.capture.sources import SyntheticSource

    src = SyntheticSource("two-boxes", "lifecam-studio", 10.0, seed=3, noise_sigma=1.5, preload=0)
    frames = [src.read() for _ in range(6)]
    truth = [o for o in frames[0].truth if o.visible_px > 2000]
    assert truth
    rig = camera.load_calibration("lifecam-studio")
    r = camera.rectify_rig(rig)

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("capture: {source: ros2, ros2_left: /stereo/left/image_raw, ros2_right: /stereo/right/image_raw}\n")
    up = start(["up", "--connect", ep, "--robot-id", "rc", "--config", str(cfg)], tmp_path / "up.log")
    stop_pub = threading.Event()
    try:
        wait_port(port, up)
        with open_session(ZenohOptions(mode="peer", connect=[ep])) as s:
            lists = Collector(ObstacleList)
            stats = Collector(ServiceStats)
            s.declare_subscriber(topic("obstacles").key("rc"), lists)
            s.declare_subscriber(topic("stats").pattern("rc"), stats)
            sdk = Sdk(port, tmp_path)
            from zenoh_ros2_sdk import ROS2Publisher
            from zenoh_ros2_sdk.discovery import get_topic_info

            pubs = {side: (ROS2Publisher(topic=f"/stereo/{side}/image_raw", msg_type="sensor_msgs/msg/Image",
                                         router_port=port, domain_id=0, node_name=f"cam_{side}"),
                           ROS2Publisher(topic=f"/stereo/{side}/camera_info", msg_type="sensor_msgs/msg/CameraInfo",
                                         router_port=port, domain_id=0, node_name=f"cam_{side}_info"))
                    for side in ("left", "right")}
            sdk.entities += [p for pair in pubs.values() for p in pair]
            types = sdk.session.store.types
            Header, Time, Roi = (types[n] for n in ("std_msgs/msg/Header", "builtin_interfaces/msg/Time",
                                                    "sensor_msgs/msg/RegionOfInterest"))
            infos = {"left": (rig.left, r.R1, r.P1), "right": (rig.right, r.R2, r.P2)}

            def driver() -> None:
                i = 0
                while not stop_pub.wait(0.1):
                    now = time.time_ns()
                    if i % 5 == 0:  # now and then a garbage sample on the image key: it must cost only itself
                        s.put(pubs["left"][0].keyexpr, b"\x00\x01\x00\x00garbage")
                    for side in ("left", "right"):
                        f = frames[i % len(frames)]
                        a = np.ascontiguousarray(getattr(f, side))
                        hdr = Header(stamp=Time(sec=now // 10**9, nanosec=now % 10**9), frame_id=f"{side}_optical")
                        img, info = pubs[side]
                        img.publish(header=hdr, height=a.shape[0], width=a.shape[1],
                                    encoding="bgr8" if a.ndim == 3 else "mono8", is_bigendian=0, step=a.strides[0],
                                    data=a.reshape(-1))
                        cam, R, P = infos[side]
                        info.publish(header=hdr, height=480, width=640, distortion_model="plumb_bob", d=cam.D.copy(),
                                     k=cam.K.ravel().copy(), r=R.ravel().copy(), p=P.ravel().copy(), binning_x=0,
                                     binning_y=0, roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
                    i += 1

            th = threading.Thread(target=driver, daemon=True)
            th.start()

            def matches(ol: ObstacleList) -> bool:
                return all(any(np.linalg.norm(np.subtract(o.position_m, t.visible_centroid_m)) < 0.3
                               for o in ol.obstacles) for t in truth)
            ok = lists.wait_for(lambda items: sum(matches(m) for m in items) >= 3, 150)
            seen: dict = {}

            def subscribed() -> bool:  # asked again until the capture's token is in (loaded machine)
                seen["graph"] = get_topic_info("/stereo/left/image_raw", domain_id=0, router_port=port, timeout=2.0,
                                               verbose=True)
                return seen["graph"] is not None and seen["graph"].subscriber_count >= 1
            wait_until(subscribed, 60, "the capture's subscription in the SDK's graph query")
            graph = seen["graph"]
            cap = stats.wait_for(lambda items: any(x.service == "capture" and x.extra.get("ros2_errors", 0) >= 1
                                                   for x in items), 20)
            stop_pub.set()
            th.join(5)
            sdk.close()
    finally:
        stop_pub.set()
        stop(up)
    log = (tmp_path / "up.log").read_text()
    last = lists.items[-1] if lists.items else None
    assert ok, (f"no obstacle lists matching the truth {[t.visible_centroid_m for t in truth]}; last: "
                f"{last and [o.position_m for o in last.obstacles]}\n{log[-3000:]}")
    assert graph is not None and graph.subscriber_count >= 1
    assert any(e.node_name == "ballbot_vision_capture" for e in graph.subscribers)
    assert cap, "capture did not count the garbage sample in its ros2_errors"
    assert up.returncode in (0, -15)


def test_humble_domain_namespace_and_stale_lists(tmp_path):
    """`run ros2 --distro humble` on domain 5 under /robot1, fed obstacle lists by hand: Humble's
    keys and tokens carry TypeHashNotSupported and 24-byte GIDs; stale lists and garbage are not
    republished."""
    import zenoh
    import zenoh.ext as zext

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    router = start(["run", "router", "--listen", ep, "--robot-id", "rh"], tmp_path / "router.log")
    bridge = None
    got: list = []
    tokens: set[str] = set()
    try:
        wait_port(port, router)
        bridge = start(["run", "ros2", "--connect", ep, "--robot-id", "rh", "--distro", "humble", "--domain-id", "5",
                        "--namespace", "/robot1", "--publish-image", "false", "--publish-points", "false"],
                       tmp_path / "ros2.log")
        with open_session(ZenohOptions(mode="peer", connect=[ep])) as s:
            s.declare_subscriber("5/robot1/obstacles/detections/**",
                                 lambda smp: got.append((str(smp.key_expr), smp.payload.to_bytes(),
                                                         smp.attachment.to_bytes())))
            said: list = []
            s.declare_subscriber("5/diagnostics/**", lambda smp: said.append((str(smp.key_expr),
                                                                             smp.payload.to_bytes())))
            s.liveliness().declare_subscriber("@ros2_lv/5/**", lambda smp: tokens.add(str(smp.key_expr)), history=True)
            wait_until(lambda: any("/MP/" in t for t in tokens), 60, "the bridge's publisher tokens")
            key = topic("obstacles").key("rh")
            # Garbage first, on its own: the inbox keeps only the newest payload, so garbage put just
            # before a real list may be overwritten unread. Until the bridge counts one.
            stats = Collector(ServiceStats)
            s.declare_subscriber(topic("stats").key("rh", service="ros2", instance="*"), stats)
            counted = lambda items: any(st.decode_errors > 0 for st in items)  # noqa: E731
            deadline = time.monotonic() + 60
            while not counted(list(stats.items)) and time.monotonic() < deadline:
                s.put(key, b"\xc1garbage")
                stats.wait_for(counted, 0.5)
            assert counted(list(stats.items)), "the bridge never counted a garbage sample"

            stale_stamps: set[int] = set()

            def put(stale: bool, seq: int) -> None:
                # every fresh list but the first says the near range was not measured
                ol = ObstacleList(robot_id="rh", seq=seq, stamp_ns=time.time_ns(), publish_ns=time.time_ns(),
                                  stale=stale, obstacles=[], degraded=[] if seq == 2 else ["near-unmeasured"])
                if stale:
                    stale_stamps.add(ol.stamp_ns)
                s.put(key, codec.encode(ol))

            for seq in range(1, 400, 2):  # stale and fresh lists alternate: only fresh ones may come out
                put(True, seq)
                threading.Event().wait(0.05)
                put(False, seq + 1)
                if len(got) >= 3:
                    break
                threading.Event().wait(0.05)
            wait_until(lambda: len(got) >= 3, 30, "Detection3DArrays on domain 5")
    finally:
        if bridge is not None:
            stop(bridge)
        stop(router)
    k, payload, att = got[0]
    assert k == "5/robot1/obstacles/detections/vision_msgs::msg::dds_::Detection3DArray_/TypeHashNotSupported"
    seq, ts, gid = zext.z_deserialize(tuple[zext.Int64, zext.Int64, list[zext.UInt8]], zenoh.ZBytes(att))
    assert len(gid) == 24 and bytes(gid[16:]) == bytes(8)
    msg = independent_typestore().deserialize_cdr(payload, "vision_msgs/msg/Detection3DArray")
    assert msg.detections == []
    mp = [t for t in tokens if "/MP/" in t and "%robot1%obstacles%detections" in t]
    assert len(mp) == 1 and mp[0].split("/")[7:9] == ["%robot1", "ballbot_vision"]
    assert mp[0].split("/")[11] == "TypeHashNotSupported"
    log = (tmp_path / "ros2.log").read_text()
    assert "dropped" in log  # the garbage, logged and counted; the service went on
    store = independent_typestore()
    stamps = {(lambda m: m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)(
        store.deserialize_cdr(p, "vision_msgs/msg/Detection3DArray")) for _, p, _ in got}
    assert stale_stamps and not stamps & stale_stamps, "a stale obstacle list was republished"
    # ... but each list, stale or degraded, is said for what it is on /diagnostics (absolute: not under /robot1)
    assert said and all(k == "5/diagnostics/diagnostic_msgs::msg::dds_::DiagnosticArray_/TypeHashNotSupported"
                        for k, _ in said), said[0][0]
    levels = {}
    for _, p in said:
        (st,) = store.deserialize_cdr(p, "diagnostic_msgs/msg/DiagnosticArray").status
        kv = {x.key: x.value for x in st.values}
        levels[int(kv["seq"])] = st.level
        assert st.name == "/robot1/ballbot_vision: obstacles" and st.hardware_id == "rh"
    assert {1, 3} <= set(levels.values()), levels  # (the inbox keeps the newest: not every list is said)
    assert all(level == 3 for seq, level in levels.items() if seq % 2)  # stale
    assert all(level == (0 if seq == 2 else 1) for seq, level in levels.items() if not seq % 2), levels
