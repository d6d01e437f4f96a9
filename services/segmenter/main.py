"""segmenter: disparity -> obstacles (PUBLIC: ballbot/obstacles/<robot_id>)."""
from __future__ import annotations

import threading
import time
from typing import Literal

import numpy as np
from pydantic import Field

from ...common import camera, codec
from ...common.errors import DecodeError
from ...common.messages import DisparityMap, Obstacle, ObstacleList
from ...common.node import Node
from ...common.settings import ServiceSettings
from ..disparity.matchers import to_float
from .seed import Detection, SeedConfig, segment
from .tracking import Tracker

SUBSCRIBES = ["disparity"]
PUBLISHES = ["obstacles"]


class SegmenterSettings(ServiceSettings):
    section = "segmenter"
    method: Literal["seed"] = Field("seed", description="seed: the thesis's Otsu pipeline")
    max_range_m: float = Field(3.0, gt=0, le=100, description="vision range; farther pixels are ignored")
    median_ksize: Literal[3, 5] = Field(5, description="median filter size, px")
    min_area_fraction: float = Field(0.03, ge=0, le=1, description="area opening: smallest region, fraction of image")
    close_radius_px: int = Field(3, ge=0, le=50, description="morphological closing radius, px")
    clear_border: bool = Field(True, description="drop regions touching the image border (the thesis)")
    mount_height_m: float | None = Field(1.0, gt=0, le=10, description="camera height above the floor (null: unknown, no floor removal)")
    mount_pitch_deg: float = Field(15.0, ge=-90, le=90, description="camera pitch, positive looking down")
    floor_margin_m: float = Field(0.08, ge=0, le=1, description="points this close to the floor are floor")
    track_gate_m: float = Field(0.6, gt=0, description="max distance between a track and its next detection")
    track_timeout_s: float = Field(1.0, gt=0, description="a track unseen this long is dropped")
    stale_after_s: float = Field(0.5, gt=0, description="input older than this (or none for this long) is stale")

    def seed_config(self) -> SeedConfig:
        return SeedConfig(max_range_m=self.max_range_m, median_ksize=self.median_ksize,
                          min_area_fraction=self.min_area_fraction, close_radius_px=self.close_radius_px,
                          clear_border=self.clear_border, mount_height_m=self.mount_height_m,
                          mount_pitch_deg=self.mount_pitch_deg, floor_margin_m=self.floor_margin_m)


def camera_to_base(p: np.ndarray, height_m: float, pitch_deg: float) -> tuple[float, float, float]:
    """Camera frame (x right, y down, z forward) -> base frame (x forward, y left, z up), base origin
    on the floor below the camera."""
    c, s = np.cos(np.deg2rad(pitch_deg)), np.sin(np.deg2rad(pitch_deg))
    x, y, z = (float(v) for v in p)
    return (z * c - y * s, -x, height_m - (y * c + z * s))


def model_from_message(msg: DisparityMap) -> camera.RectifiedModel:
    c = msg.camera
    return camera.RectifiedModel(c.width, c.height, c.focal_px, c.cx, c.cy, c.baseline_m)


class ObstacleBuilder:
    """Detections + tracking -> the public ObstacleList (pure: no Zenoh)."""

    def __init__(self, settings: SegmenterSettings):
        self.settings = settings
        self.tracker = Tracker(settings.track_gate_m, settings.track_timeout_s)

    def detect(self, msg: DisparityMap) -> list[Detection]:
        if (msg.image.width, msg.image.height) != (msg.camera.width, msg.camera.height):
            raise DecodeError(f"disparity image is {msg.image.width}x{msg.image.height}, its camera model "
                              f"{msg.camera.width}x{msg.camera.height}")
        raw = codec.array_from_image(msg.image, "disparity")
        disparity = to_float(raw, msg.scale, msg.invalid_value)
        return segment(disparity, model_from_message(msg), self.settings.seed_config())

    def build(self, msg: DisparityMap, detections: list[Detection], stale: bool) -> ObstacleList:
        s = self.settings
        tracks = self.tracker.update([d.position_m for d in detections], msg.stamp_ns / 1e9)
        obstacles = []
        for det, tr in zip(detections, tracks):
            base = (camera_to_base(det.position_m, s.mount_height_m, s.mount_pitch_deg)
                    if s.mount_height_m is not None else None)
            obstacles.append(Obstacle(
                id=tr.id, position_m=tuple(float(v) for v in det.position_m),
                size_m=tuple(float(v) for v in det.size_m), distance_m=det.distance_m,
                velocity_mps=tuple(float(v) for v in tr.velocity), bbox_px=det.bbox_px, area_px=det.area_px,
                disparity_px=det.disparity_px, confidence=min(1.0, det.confidence), position_base_m=base))
        obstacles.sort(key=lambda o: o.distance_m)
        return ObstacleList(robot_id=msg.robot_id, seq=msg.seq, stamp_ns=msg.stamp_ns, stages=dict(msg.stages),
                            publish_ns=time.time_ns(), stale=stale, method=s.method, obstacles=obstacles)


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
    last_seq = -1
    for msg in node.receive(inbox):
        with node.processing(msg):
            if msg.seq <= last_seq:
                node.extra["out_of_order"] = node.extra.get("out_of_order", 0) + 1
                continue
            detections = builder.detect(msg)
            stale = (time.time_ns() - msg.stamp_ns) / 1e9 > settings.stale_after_s
            result = builder.build(msg, detections, stale)
            with lock:
                out.put(result)
                last["list"], last["time"] = result, time.monotonic()
                last_seq = msg.seq
            node.status = "stale: input too old" if stale else "ok"
