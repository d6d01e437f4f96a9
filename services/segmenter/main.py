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
from ...common.disparity import to_float
from . import layers, seed
from .mount import Mount
from .seed import Detection
from .tracking import Tracker

SUBSCRIBES = ["disparity"]
PUBLISHES = ["obstacles"]

METHODS = ("layers", "seed")
DEFAULT_RANGE_M = {"seed": 3.0, "layers": 4.5}


class SegmenterSettings(ServiceSettings):
    section = "segmenter"
    method: Literal["layers", "seed"] = Field(
        "layers", description="layers: depth-aware regions, floor plane, border objects kept; "
                              "seed: the thesis's Otsu pipeline")
    max_range_m: float | None = Field(None, gt=0, le=100, description="vision range; farther pixels are ignored "
                                      "(null: the method's own, seed 3 m as in the thesis, layers 4.5 m)")
    median_ksize: Literal[1, 3, 5] = Field(5, description="median filter size, px")
    floor_removal: bool = Field(True, description="remove the floor (false reproduces the thesis with seed)")
    floor_margin_m: float = Field(0.08, ge=0, le=1, description="points this close to the floor are floor")
    mount_height_m: float | None = Field(1.0, gt=0, le=10, description="camera height above the floor "
                                         "(null: unknown mount: no base frame; layers fits the floor without a prior)")
    mount_pitch_deg: float = Field(15.0, ge=-90, le=90, description="camera pitch, positive looking down")
    mount_yaw_deg: float = Field(0.0, ge=-180, le=180, description="camera yaw on the robot, positive to the left")
    mount_roll_deg: float = Field(0.0, ge=-90, le=90, description="camera roll, positive right side down")
    mount_x_m: float = Field(0.0, ge=-10, le=10, description="camera position ahead of the base origin")
    mount_y_m: float = Field(0.0, ge=-10, le=10, description="camera position left of the base origin")
    # seed
    min_area_fraction: float = Field(0.03, ge=0, le=1, description="seed: area opening, fraction of the image")
    close_radius_px: int = Field(3, ge=0, le=50, description="seed: morphological closing radius, px")
    clear_border: bool = Field(True, description="seed: drop regions touching the image border (the thesis)")
    # layers
    fit_floor: bool = Field(True, description="layers: fit the floor plane to the disparity (mount as prior/fallback)")
    step_px: float = Field(0.6, ge=0, le=50, description="layers: neighbours differing by more than "
                           "step_px + step_rel * d belong to different objects")
    step_rel: float = Field(0.03, ge=0, le=1, description="layers: relative part of the similarity tolerance")
    min_size_m: float = Field(0.08, ge=0, le=10, description="layers: smallest obstacle extent, m")
    min_area_m2: float = Field(0.006, ge=0, le=100, description="layers: smallest frontal area, m^2")
    downsample: Literal[1, 2, 4] = Field(2, description="layers: work on every n-th pixel")
    edge_refine: bool = Field(False, description="layers: snap boxes to intensity edges (needs the image; off in the service)")
    # tracking
    track_gate_m: float = Field(0.6, gt=0, description="max distance between a track and its next detection")
    track_timeout_s: float = Field(1.0, gt=0, description="a track unseen this long is dropped")
    stale_after_s: float = Field(0.5, gt=0, description="input older than this (or none for this long) is stale")

    @property
    def range_m(self) -> float:
        return self.max_range_m if self.max_range_m is not None else DEFAULT_RANGE_M[self.method]

    def mount(self) -> Mount | None:
        if self.mount_height_m is None:
            return None
        return Mount(self.mount_height_m, self.mount_pitch_deg, self.mount_yaw_deg, self.mount_roll_deg,
                     self.mount_x_m, self.mount_y_m)

    def seed_config(self) -> seed.SeedConfig:
        floor = self.floor_removal and self.mount_height_m is not None
        return seed.SeedConfig(max_range_m=self.range_m, median_ksize=max(3, self.median_ksize),
                               min_area_fraction=self.min_area_fraction, close_radius_px=self.close_radius_px,
                               clear_border=self.clear_border, mount_height_m=self.mount_height_m if floor else None,
                               mount_pitch_deg=self.mount_pitch_deg, floor_margin_m=self.floor_margin_m)

    def layers_config(self) -> layers.LayersConfig:
        return layers.LayersConfig(max_range_m=self.range_m, downsample=self.downsample, median_ksize=self.median_ksize,
                                   step_px=self.step_px, step_rel=self.step_rel, min_size_m=self.min_size_m,
                                   min_area_m2=self.min_area_m2, floor_removal=self.floor_removal,
                                   fit_floor=self.fit_floor, floor_margin_m=self.floor_margin_m,
                                   mount=self.mount(), edge_refine=self.edge_refine)


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
        self._seed = settings.seed_config()
        self._layers = settings.layers_config()

    def detect(self, disparity: np.ndarray, model: camera.RectifiedModel,
               image: np.ndarray | None = None) -> list[Detection]:
        """disparity: (H, W) float px, NaN = invalid, matching `model`."""
        if disparity.size == 0:
            return []
        if self.method == "seed":
            return seed.segment(disparity, model, self._seed)
        return layers.segment(disparity, model, self._layers, image=image)


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
