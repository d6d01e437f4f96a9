"""ros2: the pipeline's output as ROS 2 topics on rmw_zenoh (Nav2, rviz, rosbag on the same router).

Subscribes to obstacles (public), free space (public), the rectified frames and the disparity maps,
and publishes, as the ROS node `<namespace>/<node_name>` of ROS domain `domain_id`:

  <ns>/obstacles/detections   vision_msgs/Detection3DArray   camera_frame, per obstacle list
  <ns>/obstacles/markers      visualization_msgs/MarkerArray camera_frame, per obstacle list
  <ns>/obstacles/points       sensor_msgs/PointCloud2        camera_frame, the obstacles' 3D points
  <ns>/camera/left/image_rect sensor_msgs/Image              camera_frame, rectified left image
  <ns>/camera/left/camera_info sensor_msgs/CameraInfo        its rectified pinhole model
  <ns>/freespace              nav_msgs/OccupancyGrid         base_frame, when free space is published
  /tf_static                  tf2_msgs/TFMessage             base_frame -> camera_frame, transient local
  /diagnostics                diagnostic_msgs/DiagnosticArray per obstacle list: how far it can be trusted

The camera->base transform is the mount each obstacle list carries (ObstacleList.mount: where the
segmenter placed the camera for that list, from its fitted ground and the configured yaw and
offsets), else the configured one (the `mount:` section); it is re-published when it moves by more
than tf_update_m / tf_update_deg. Obstacle lists flagged stale are not republished unless
publish_stale (ROS messages have no stale flag); even then the segmenter's heartbeat repeats of its
last list (same capture stamp, sent while its input has stopped) never are: the node inbox refuses a
stamp it has already handed on, and a ROS consumer tells a stopped stream from the header stamps'
age. A Detection3DArray cannot say whether its list may be trusted: every list, stale ones too, is
also a DiagnosticArray on /diagnostics (OK; WARN naming the `degraded` reasons: an empty array is no
clear way; STALE), stamped like the detections, and the OccupancyGrid of such a list has no free cell.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from common.keys import topic
from common.messages import DisparityMap, ObstacleList
from common.node import Node
from common.settings import MountSettings, ServiceSettings
from cores.segmentation.mount import Mount

SUBSCRIBES = ["obstacles", "freespace", "frames_rect", "disparity"]
PUBLISHES: list[str] = []  # ROS 2 topics on rmw_zenoh keys, listed in the docstring

TOPICS = {
    "detections": ("obstacles/detections", "vision_msgs/msg/Detection3DArray"),
    "markers": ("obstacles/markers", "visualization_msgs/msg/MarkerArray"),
    "points": ("obstacles/points", "sensor_msgs/msg/PointCloud2"),
    "image": ("camera/left/image_rect", "sensor_msgs/msg/Image"),
    "camera_info": ("camera/left/camera_info", "sensor_msgs/msg/CameraInfo"),
    "freespace": ("freespace", "nav_msgs/msg/OccupancyGrid"),
    "tf_static": ("/tf_static", "tf2_msgs/msg/TFMessage"),
    "diagnostics": ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
}


class Ros2Settings(ServiceSettings):
    section = "ros2"
    distro: Literal["humble", "jazzy"] = Field("jazzy", description="ROS 2 distro of the other side (humble: "
                                               "TypeHashNotSupported in keys, 24-byte GIDs; jazzy: RIHS01 hashes)")
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID")
    namespace: str = Field("/", description="ROS namespace of the node and its relative topics, e.g. /ballbot")
    node_name: str = Field("ballbot_vision", description="ROS node name")
    camera_frame: str = Field("stereo_camera_optical_frame", min_length=1,
                              description="frame_id of camera-frame data (rectified left camera, optical axes)")
    base_frame: str = Field("base_link", min_length=1, description="frame_id of the robot base (REP 103)")
    reliability: Literal["reliable", "best_effort"] = Field("reliable", description="QoS reliability of the topics")
    depth: int = Field(10, ge=1, le=1000, description="QoS history depth (keep last)")
    publish_image: bool = Field(True, description="publish the rectified left image and its CameraInfo")
    image_max_rate_hz: float = Field(10.0, ge=0, le=1000, description="at most this many images per second (0: all)")
    publish_points: bool = Field(True, description="publish the obstacles' 3D points (needs the disparity maps)")
    points_margin_m: float = Field(0.05, ge=0, le=2, description="points: widen each obstacle's 3D box by this")
    points_max: int = Field(5000, ge=1, le=1_000_000, description="points: at most this many per cloud")
    publish_stale: bool = Field(False, description="also republish obstacle lists computed from late "
                                               "input (flagged stale); heartbeat repeats of the last list never are")
    marker_lifetime_s: float = Field(0.5, ge=0, le=60,
                                     description="markers vanish after this unless renewed (0: never)")
    tf_static: bool = Field(True, description="publish base_frame -> camera_frame on /tf_static")
    tf_update_m: float = Field(0.02, ge=0, le=1, description="re-publish /tf_static when the camera moved this much")
    tf_update_deg: float = Field(1.0, ge=0, le=90, description="... or turned this much")

    @field_validator("namespace", "node_name")
    @classmethod
    def _ros_name(cls, v: str, info) -> str:
        from common.ros2.rmw import RosNameError, check_namespace, check_node_name

        try:
            return check_namespace(v) if info.field_name == "namespace" else check_node_name(v)
        except RosNameError as e:
            raise ValueError(str(e)) from None


def mount_from(msg: ObstacleList | None, configured: MountSettings) -> Mount | None:
    """The camera mount: the one the obstacle list carries (the segmenter's, for that list), else the
    configured one. None: not known yet."""
    return Mount.of(msg.mount if msg is not None and msg.mount is not None else configured)


def mount_moved(a: Mount | None, b: Mount, s: Ros2Settings) -> bool:
    if a is None:
        return True
    dist = float(np.linalg.norm(a.origin_base - b.origin_base))
    cos = (np.trace(a.R_base_camera.T @ b.R_base_camera) - 1) / 2
    angle = float(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return dist > s.tf_update_m or angle > s.tf_update_deg


class DisparityCache:
    """The last few disparity payloads by capture stamp (decoded only when an obstacle list of the
    same stamp asks for its points)."""

    def __init__(self, keep: int = 6):
        self._items: deque[tuple[int, bytes]] = deque(maxlen=keep)
        self._lock = threading.Lock()

    def offer(self, stamp_ns: int | None, payload: bytes) -> None:
        if stamp_ns is not None:
            with self._lock:
                self._items.append((stamp_ns, payload))

    def take(self, stamp_ns: int) -> bytes | None:
        with self._lock:
            for s, p in self._items:
                if s == stamp_ns:
                    return p
        return None


def preflight(settings: Ros2Settings) -> None:
    """Before the service is up (cli.cmd_run): the ros2 extra is installed."""
    from common.errors import require

    require(("rosbags", "xxhash"), "ros2", "the ROS 2 bridge")


def run(node: Node, settings: Ros2Settings) -> None:
    from common.ros2 import rmw
    from common.ros2.graph import RosNode
    from common.ros2.msgs import types_for
    from cores import ros2_convert as convert

    try:
        types = types_for(settings.distro)
    except ImportError as e:
        from common.errors import MissingDependency

        raise MissingDependency(f"ros2: {e.name} is not installed; install the extra: "
                                f"pip install 'ballbot-vision[ros2]'") from None
    s = settings
    qos = rmw.Qos(reliability=s.reliability, depth=s.depth)
    graph = RosNode(node.session, types, s.domain_id, s.namespace, s.node_name)
    pubs = {}
    for name, (tname, typename) in TOPICS.items():
        if name in ("image", "camera_info") and not s.publish_image or name == "points" and not s.publish_points \
                or name == "tf_static" and not s.tf_static:
            continue
        q = rmw.Qos(reliability="reliable", durability="transient_local", depth=1) if name == "tf_static" else qos
        pubs[name] = graph.publisher(tname, typename, q)
    node.extra["ros2_publishers"] = float(len(pubs))
    state: dict[str, Mount | None] = {"mount": None}  # the mount last sent on /tf_static
    status_name = f"{graph.namespace.rstrip('/')}/{graph.name}: obstacles"  # the node's fully qualified name
    lock = threading.Lock()

    def publish_tf(msg: ObstacleList | None, stamp: int) -> None:
        mount = mount_from(msg, node.mount)
        with lock:
            if "tf_static" in pubs and mount is not None and mount_moved(state["mount"], mount, s):
                pubs["tf_static"].publish(convert.tf_static(types, mount, stamp, s.base_frame, s.camera_frame))
                state["mount"] = mount

    def obstacles_loop() -> None:
        cache = DisparityCache()
        if "points" in pubs:
            node.subscribe(topic("disparity").key(node.robot_id),
                           lambda smp: cache.offer(_stamp(smp), smp.payload.to_bytes()))
        inbox = node.latest("obstacles")
        for msg in node.receive(inbox):
            with node.processing(msg):
                # said first, stale or not: an empty Detection3DArray cannot tell "saw nothing" from "could not look"
                pubs["diagnostics"].publish(convert.trust(types, msg, status_name))
                if msg.stale and not s.publish_stale:
                    node.count("ros2_stale_skipped")
                    continue
                pubs["detections"].publish(convert.detections(types, msg, s.camera_frame))
                pubs["markers"].publish(convert.markers(types, msg, s.camera_frame, s.marker_lifetime_s))
                publish_tf(msg, msg.stamp_ns)
                if "points" in pubs:
                    raw = cache.take(msg.stamp_ns)
                    if raw is not None:
                        disp = node.decode(raw, DisparityMap)
                        pts, ids = convert.obstacle_points(disp, msg, s.points_margin_m, s.points_max)
                        pubs["points"].publish(convert.point_cloud(types, pts, ids, msg.stamp_ns, s.camera_frame))
                    else:
                        node.count("ros2_points_missing")
                node._published(time.time_ns() - msg.stamp_ns)

    def image_loop() -> None:
        inbox = node.latest("frames_rect")
        period = 1.0 / s.image_max_rate_hz if s.image_max_rate_hz > 0 else 0.0
        last = -1e9
        for msg in node.receive(inbox):
            if time.monotonic() - last < period:
                continue
            with node.processing(msg):
                img, info = convert.image(types, msg, s.camera_frame)
                pubs["image"].publish(img)
                pubs["camera_info"].publish(info)
                last = time.monotonic()

    def freespace_loop() -> None:
        inbox = node.latest("freespace")
        for msg in node.receive(inbox):
            with node.processing(msg):
                pubs["freespace"].publish(convert.occupancy_grid(types, msg, s.base_frame))

    publish_tf(None, time.time_ns())
    loops = [obstacles_loop, freespace_loop] + ([image_loop] if "image" in pubs else [])
    threads = [threading.Thread(target=f, name=f.__name__, daemon=True) for f in loops]
    for t in threads:
        t.start()
    keys = ", ".join(p.topic for p in pubs.values())
    node.status = "ok"
    import logging

    logging.getLogger("ballbot").info("ros2: node %s%s (domain %d, %s) publishes %s", s.namespace.rstrip("/") + "/",
                                      s.node_name, s.domain_id, s.distro, keys)
    try:
        while not node.stop_event.wait(1.0):
            for name, p in pubs.items():
                node.extra[f"ros2_{name}_published"] = float(p.published)
    finally:
        node.stop_event.set()
        for t in threads:
            t.join(timeout=2.0)
        graph.close()


def _stamp(sample) -> int | None:
    from common.inbox import stamp_of

    return stamp_of(sample.attachment)
