"""capture: a stereo source -> frames_raw (+ truth for the synthetic world)."""
from __future__ import annotations

import time
from typing import Literal

from pydantic import Field

from ...common import codec
from ...common.messages import GroundTruth, StereoFrame, TruthObstacle
from ...common.node import Node
from ...common.settings import ServiceSettings
from .sources import CapturedPair, SyntheticSource

SUBSCRIBES: list[str] = []
PUBLISHES = ["frames_raw", "truth"]


class CaptureSettings(ServiceSettings):
    section = "capture"
    source: Literal["synthetic"] = Field("synthetic", description="where pairs come from")
    scenario: str = Field("two-boxes", description="synthetic: built-in scenario name or YAML file")
    calibration: str = Field("lifecam-studio", description="synthetic: the rig rendered for (YAML or profile)")
    rate_hz: float = Field(30.0, gt=0, le=1000, description="pairs per second")
    seed: int = Field(0, description="synthetic: random seed (textures, noise)")
    noise_sigma: float = Field(1.5, ge=0, le=50, description="synthetic: sensor noise, grey levels")
    preload: int = Field(0, ge=0, le=10000, description="synthetic: render this many pairs first, then loop them")
    encoding: Literal["raw", "png", "jpeg"] = Field("raw", description="image encoding on the wire")
    jpeg_quality: int = Field(90, ge=1, le=100, description="jpeg quality")


def open_source(s: CaptureSettings):
    return SyntheticSource(s.scenario, s.calibration, s.rate_hz, s.seed, s.noise_sigma, s.preload)


def truth_message(robot_id: str, seq: int, stamp_ns: int, scenario: str, truth: list) -> GroundTruth:
    def v3(a) -> tuple[float, float, float]:
        return tuple(float(x) for x in a)  # type: ignore[return-value]

    return GroundTruth(robot_id=robot_id, seq=seq, stamp_ns=stamp_ns, scenario=scenario, obstacles=[
        TruthObstacle(name=o.name, kind=o.kind, center_m=v3(o.center_m), size_m=v3(o.size_m),
                      visible_centroid_m=v3(o.visible_centroid_m), nearest_m=float(o.nearest_m),
                      visible_px=int(o.visible_px), bbox_px=tuple(int(x) for x in o.bbox_px),
                      velocity_mps=v3(o.velocity_mps)) for o in truth])


def run(node: Node, settings: CaptureSettings) -> None:
    source = open_source(settings)
    frames = node.publisher("frames_raw")
    truth = node.publisher("truth")
    period = 1.0 / settings.rate_hz
    seq = 0
    next_t = time.monotonic()
    try:
        while node.running:
            pair: CapturedPair | None = source.read()
            if pair is None:
                node.status = "end of stream"
                node.stop_event.wait()
                break
            with node.processing():
                stamp = time.time_ns()
                msg = StereoFrame(robot_id=node.robot_id, seq=seq, stamp_ns=stamp,
                                  left=codec.image_from_array(pair.left, settings.encoding, settings.jpeg_quality),
                                  right=codec.image_from_array(pair.right, settings.encoding, settings.jpeg_quality),
                                  source=source.name)
                frames.put(msg)
                if pair.truth is not None:
                    truth.put(truth_message(node.robot_id, seq, stamp, getattr(source, "scenario", ""), pair.truth),
                              count=False)
                seq += 1
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:  # fell behind (slow renderer): do not burst to catch up
                next_t = time.monotonic()
            elif delay > 0:
                node.stop_event.wait(delay)
    finally:
        source.close()
