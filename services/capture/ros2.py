"""capture --source ros2: stereo pairs from a ROS 2 camera driver over rmw_zenoh, no ROS install.

Subscribes to the left and right image topics (sensor_msgs/Image, or sensor_msgs/CompressedImage
as image_transport's `.../compressed` topics carry) and their sensor_msgs/CameraInfo, on the
rmw_zenoh data keys with the type hash as a wildcard (a Humble or a Jazzy driver alike), and
declares itself in the ROS graph (node + subscriptions), so `ros2 topic info` lists it and lazy
drivers start publishing. Left and right are paired by header stamp: a pair is two images whose
stamps differ by at most `ros2_max_skew_ms`; an image without a partner in time is dropped and
counted. With `ros2_calibration camera_info` the stereo calibration is derived from the two
CameraInfo messages and sent to rectify (on its calibration key) whenever it changes.

StampPairer is the pure core; Ros2Source the Zenoh side.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.errors import BallbotError, SourceError
from cores import camera
from services.capture.sources import CapturedPair, SourceContext

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
CALIBRATION_REPEAT_S = 10.0  # a rectify started later still gets the CameraInfo calibration


@dataclass
class Stamped:
    stamp_ns: int
    value: Any


class StampPairer:
    """Pairs left and right items by stamp. offer() returns the newest pair that the new item
    completes (None if none yet); items older than a returned pair are discarded and counted in
    `unpaired`, as are items that fall out of the `keep` most recent of their side."""

    def __init__(self, max_skew_ns: int, keep: int = 8):
        self.max_skew_ns = int(max_skew_ns)
        self.sides: dict[str, deque[Stamped]] = {"left": deque(), "right": deque()}
        self.keep = keep
        self.unpaired = 0
        self.last_pair_ns = -1

    def offer(self, side: str, stamp_ns: int, value: Any) -> tuple[Stamped, Stamped] | None:
        if stamp_ns <= self.last_pair_ns:  # older than a pair already made: late or replayed
            self.unpaired += 1
            return None
        mine, other = self.sides[side], self.sides["right" if side == "left" else "left"]
        best = min(other, key=lambda s: abs(s.stamp_ns - stamp_ns), default=None)
        if best is not None and abs(best.stamp_ns - stamp_ns) <= self.max_skew_ns:
            item = Stamped(stamp_ns, value)
            pair_stamp = max(stamp_ns, best.stamp_ns)
            # everything up to the pair on both sides is used or too old now
            dropped = sum(1 for s in other if s.stamp_ns <= pair_stamp and s is not best)
            dropped += sum(1 for s in mine if s.stamp_ns <= pair_stamp)
            self.unpaired += dropped
            for q in (mine, other):
                while q and q[0].stamp_ns <= pair_stamp:
                    q.popleft()
                kept = [s for s in q if s.stamp_ns > pair_stamp]
                q.clear()
                q.extend(kept)
            self.last_pair_ns = pair_stamp
            return (item, best) if side == "left" else (best, item)
        mine.append(Stamped(stamp_ns, value))
        if len(mine) > 1 and mine[-1].stamp_ns < mine[-2].stamp_ns:
            mine_sorted = sorted(mine, key=lambda s: s.stamp_ns)
            mine.clear()
            mine.extend(mine_sorted)
        while len(mine) > self.keep:
            mine.popleft()
            self.unpaired += 1
        return None


def camera_info_topic(image_topic: str) -> str:
    """image_transport's convention: the CameraInfo beside an image topic ('/stereo/left/image_raw'
    or '/stereo/left/image_raw/compressed' -> '/stereo/left/camera_info')."""
    parts = image_topic.rstrip("/").split("/")
    if len(parts) > 1 and parts[-1] in ("compressed", "compressedDepth", "theora"):
        parts = parts[:-1]
    return "/".join(parts[:-1] + ["camera_info"]) if len(parts) > 1 else "camera_info"


class Ros2Source:
    name = "ros2"
    period_s = 0.0  # the driver paces the stream
    ended = False

    def __init__(self, settings: Any, ctx: SourceContext):
        from common.ros2 import rmw
        from common.ros2.graph import RosNode
        from common.ros2.msgs import types_for
        from cores import ros2_convert as convert

        node = getattr(ctx, "node", None)
        if node is None or getattr(node, "session", None) is None:
            raise SourceError("ros2: this source needs a running capture service (a Zenoh session)")
        s = settings
        if not s.ros2_left or not s.ros2_right:
            raise SourceError("ros2: set both image topics (--ros2-left and --ros2-right)")
        self._convert = convert
        self.ctx, self.settings = ctx, s
        self.types = types_for(s.ros2_distro)
        self.pairer = StampPairer(int(s.ros2_max_skew_ms * 1e6))
        self._cond = threading.Condition()
        self._ready: tuple[Stamped, Stamped] | None = None
        self._infos: dict[str, Any] = {}
        self._calibration_sent = ""
        self._calibration_at = -1e9
        self._infos_used: tuple[int, int] | None = None
        self.received = {"left": 0, "right": 0}
        self.errors = 0
        try:
            self.graph = RosNode(node.session, self.types, s.ros2_domain_id, s.ros2_namespace, s.ros2_node_name)
            qos = rmw.Qos(reliability="best_effort", depth=5)  # image_transport's sensor-data profile
            typename = COMPRESSED if s.ros2_left.rstrip("/").endswith("/compressed") else IMAGE
            for side, topic in (("left", s.ros2_left), ("right", s.ros2_right)):
                self.graph.subscription(topic, typename, qos, self._on_image(side), any_type=True)
                info_topic = s.ros2_left_info if side == "left" else s.ros2_right_info
                self.graph.subscription(info_topic or camera_info_topic(topic), CAMERA_INFO, rmw.Qos(depth=5),
                                        self._on_info(side))
        except (rmw.RosNameError, ValueError) as e:
            raise SourceError(f"ros2: {e}") from None
        self._calibration = node.publisher("calibration") if s.ros2_calibration == "camera_info" else None
        ctx.status("waiting for ROS 2 images on " + ", ".join(e.topic for e in self.graph.entities[::2]))

    # -- Zenoh's thread ---------------------------------------------------------------------------
    def _where(self, key: str) -> str:
        return f"ros2 topic key {key}"

    def _count_error(self, text: str) -> None:
        self.errors += 1
        self.ctx.extra["ros2_errors"] = float(self.errors)
        warn = getattr(getattr(self.ctx, "node", None), "warn", None)
        if warn is not None:
            warn("ros2", text)

    def _on_image(self, side: str):
        from common.ros2 import rmw

        def on_sample(key: str, payload: bytes, attachment: bytes | None) -> None:
            typename = rmw.ros_type_from_dds(key.split("/")[-2])
            if typename not in (IMAGE, COMPRESSED):
                self._count_error(f"{self._where(key)}: {typename or 'unknown type'} is no image; ignored")
                return
            try:
                msg = self.types.deserialize(payload, typename)
            except Exception as e:  # a truncated or foreign payload costs only itself
                self._count_error(f"{self._where(key)}: CDR does not decode as {typename}: {type(e).__name__}: {e}")
                return
            self.received[side] += 1
            stamp = self._convert.stamp_ns(msg.header.stamp)
            with self._cond:
                pair = self.pairer.offer(side, stamp, (typename, msg, key))
                self.ctx.extra["ros2_unpaired"] = float(self.pairer.unpaired)
                if pair is not None:
                    self._ready = pair
                    self._cond.notify_all()
        return on_sample

    def _on_info(self, side: str):
        def on_sample(key: str, payload: bytes, attachment: bytes | None) -> None:
            try:
                msg = self.types.deserialize(payload, CAMERA_INFO)
            except Exception as e:
                self._count_error(f"{self._where(key)}: CDR does not decode as CameraInfo: {type(e).__name__}: {e}")
                return
            with self._cond:
                self._infos[side] = msg
        return on_sample

    # -- the capture loop's thread ----------------------------------------------------------------
    def _array(self, typename: str, msg: Any, key: str) -> np.ndarray:
        if typename == COMPRESSED:
            return self._convert.array_from_compressed(msg, self._where(key))
        return self._convert.array_from_ros_image(msg, self._where(key))

    def _send_calibration(self) -> None:
        import yaml

        from common.messages import CalibrationUpdate
        from common.signing import sign

        with self._cond:
            left, right = self._infos.get("left"), self._infos.get("right")
        if self._calibration is None or left is None or right is None:
            return
        # the same CameraInfo objects as last time: nothing to derive, unless it is time to repeat
        # it for a rectify that (re)started since
        fresh = (id(left), id(right)) != self._infos_used
        if not fresh and time.monotonic() - self._calibration_at < CALIBRATION_REPEAT_S:
            return
        self._infos_used = (id(left), id(right))
        try:
            cal = self._convert.calibration_from_camera_infos(left, right, self.settings.ros2_rectified,
                                                              "ros2 CameraInfo")
        except BallbotError as e:
            self._count_error(f"calibration from CameraInfo refused: {e}")
            return
        text = yaml.safe_dump(camera.calibration_to_dict(cal), sort_keys=False)
        if text == self._calibration_sent and time.monotonic() - self._calibration_at < CALIBRATION_REPEAT_S:
            return
        node = self.ctx.node
        self._calibration.put(sign(CalibrationUpdate(robot_id=node.robot_id, seq=0, stamp_ns=time.time_ns(), yaml=text,
                                                     source="capture --source ros2 (CameraInfo)")), count=False)
        self._calibration_sent = text
        self._calibration_at = time.monotonic()

    def read(self) -> CapturedPair | None:
        while not self.ctx.stop.is_set():
            with self._cond:
                if self._ready is None:
                    self._cond.wait(0.2)
                pair, self._ready = self._ready, None
            if pair is None:
                continue
            (lt, lmsg, lkey), (rt, rmsg, rkey) = pair[0].value, pair[1].value
            try:
                left, right = self._array(lt, lmsg, lkey), self._array(rt, rmsg, rkey)
            except BallbotError as e:
                raise SourceError(str(e)) from None
            if left.shape[:2] != right.shape[:2]:
                raise SourceError(f"ros2: left image {left.shape[1]}x{left.shape[0]} and right "
                                  f"{right.shape[1]}x{right.shape[0]} differ in size")
            self._send_calibration()
            self.ctx.status("ok")
            skew = abs(pair[0].stamp_ns - pair[1].stamp_ns) / 1e6
            return CapturedPair(left, right, pair[0].stamp_ns / 1e9, extra={"skew_ms": skew}, stamp_ns=pair[0].stamp_ns)
        return None

    def close(self) -> None:
        try:
            self.graph.close()
        except Exception:
            pass
