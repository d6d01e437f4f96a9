"""segmenter: disparity -> obstacles (PUBLIC: ballbot/obstacles/<robot_id>)."""
from __future__ import annotations

import threading
import time

import numpy as np

from ...common import camera, codec
from ...common.errors import DecodeError
from ...common.messages import DisparityMap, Obstacle, ObstacleList
from ...common.node import Node
from ...common.disparity import to_float
from . import layers, seed
from .mount import Mount
from .seed import Detection
from .settings import METHODS, SegmenterSettings  # noqa: F401  (SegmenterSettings: cli's service table)
from .tracking import Tracker

SUBSCRIBES = ["disparity"]
PUBLISHES = ["obstacles"]


def camera_to_base(p: np.ndarray, height_m: float, pitch_deg: float) -> tuple[float, float, float]:
    """Camera frame (x right, y down, z forward) -> base frame (x forward, y left, z up), base origin
    on the floor below the camera (a mount with only height and pitch; see mount.Mount)."""
    return tuple(float(v) for v in Mount(height_m, pitch_deg).to_base(p))  # type: ignore[return-value]


def model_from_message(msg: DisparityMap) -> camera.RectifiedModel:
    c = msg.camera
    return camera.RectifiedModel(c.width, c.height, c.focal_px, c.cx, c.cy, c.baseline_m)


class Segmenter:
    """One method with its settings: disparity -> detections (camera frame). Bad input (NaNs, no
    valid pixels, empty) gives no detections; a map whose size differs from the model raises."""

    def __init__(self, settings: SegmenterSettings):
        self.settings = settings
        self.method = settings.method

    def detect(self, disparity: np.ndarray, model: camera.RectifiedModel,
               image: np.ndarray | None = None) -> list[Detection]:
        """disparity: (H, W) float px, NaN = invalid, matching `model`."""
        if disparity.size == 0:
            return []
        if self.method == "seed":
            return seed.segment(disparity, model, self.settings)
        return layers.segment(disparity, model, self.settings, image=image)


class ObstacleBuilder:
    """Detections + tracking -> the public ObstacleList (pure: no Zenoh)."""

    def __init__(self, settings: SegmenterSettings):
        self.settings = settings
        self.segmenter = Segmenter(settings)
        self.mount = settings.mount()
        self.tracker = Tracker(settings.track_gate_m, settings.track_timeout_s)

    def detect(self, msg: DisparityMap) -> list[Detection]:
        if (msg.image.width, msg.image.height) != (msg.camera.width, msg.camera.height):
            raise DecodeError(f"disparity image is {msg.image.width}x{msg.image.height}, its camera model "
                              f"{msg.camera.width}x{msg.camera.height}")
        raw = codec.array_from_image(msg.image, "disparity")
        disparity = to_float(raw, msg.scale, msg.invalid_value)
        return self.segmenter.detect(disparity, model_from_message(msg))

    def obstacles(self, detections: list[Detection], t_s: float) -> list[Obstacle]:
        """Track the detections seen at time t_s (s) -> obstacles, nearest first."""
        tracks = self.tracker.update([d.position_m for d in detections], t_s)
        out = []
        for det, tr in zip(detections, tracks):
            base = (tuple(float(v) for v in self.mount.to_base(det.position_m)) if self.mount is not None else None)
            out.append(Obstacle(
                id=tr.id, position_m=tuple(float(v) for v in det.position_m),
                size_m=tuple(float(v) for v in det.size_m), distance_m=max(0.0, float(det.distance_m)),
                velocity_mps=tuple(float(v) for v in tr.velocity), bbox_px=det.bbox_px, area_px=det.area_px,
                disparity_px=float(det.disparity_px), confidence=float(min(1.0, max(0.0, det.confidence))),
                position_base_m=base))
        out.sort(key=lambda o: o.distance_m)
        return out

    def build(self, msg: DisparityMap, detections: list[Detection], stale: bool,
              t_s: float | None = None) -> ObstacleList:
        """t_s: the frame's time for tracking, s, on a clock that never goes backwards (the service
        passes Node.frame_time_s: monotonic); offline, the capture stamp."""
        obstacles = self.obstacles(detections, msg.stamp_ns / 1e9 if t_s is None else t_s)
        return ObstacleList(robot_id=msg.robot_id, seq=msg.seq, stamp_ns=msg.stamp_ns, stages=dict(msg.stages),
                            publish_ns=time.time_ns(), stale=stale, method=self.settings.method, obstacles=obstacles)


def run(node: Node, settings: SegmenterSettings) -> None:
    builder = ObstacleBuilder(settings)
    inbox = node.latest("disparity")
    out = node.publisher("obstacles")
    lock = threading.Lock()
    last: dict[str, ObstacleList | float] = {"list": None, "time": time.monotonic()}

    def heartbeat() -> None:
        # With no input the last list goes out again, flagged stale, so subscribers can tell a quiet
        # scene from a dead pipeline.
        while not node.stop_event.wait(settings.stale_after_s):
            with lock:
                prev = last["list"]
                quiet = time.monotonic() - last["time"] > settings.stale_after_s
                if quiet:
                    node.status = "stale: no disparity input"
                    if prev is not None:
                        prev.stale = True
                        prev.publish_ns = time.time_ns()
                        out.put(prev, count=False)

    threading.Thread(target=heartbeat, name="stale-heartbeat", daemon=True).start()
    # The inbox hands on only plausible stamps, newest first (common/node.py: FreshnessGate); ages
    # and the tracker's time base are on the monotonic clock, so a wall-clock step moves neither.
    for msg in node.receive(inbox):
        with node.processing(msg):
            detections = builder.detect(msg)
            stale = node.age_s(msg) > settings.stale_after_s
            result = builder.build(msg, detections, stale, t_s=node.frame_time_s(msg))
            with lock:
                out.put(result)
                last["list"], last["time"] = result, time.monotonic()
            node.status = "stale: input too old" if stale else "ok"
