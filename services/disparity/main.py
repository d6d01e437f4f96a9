"""disparity: frames_rect -> disparity (int16 fixed point, f and baseline attached)."""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from ...common import codec
from ...common.errors import DecodeError
from ...common.messages import DisparityMap
from ...common.node import Node
from ...common.settings import ServiceSettings
from .matchers import SCALE, MatcherConfig, StereoMatcher

SUBSCRIBES = ["frames_rect"]
PUBLISHES = ["disparity"]


class DisparitySettings(ServiceSettings):
    section = "disparity"
    method: Literal["bm", "sgbm"] = Field("bm", description="bm: block matching, SAD (the thesis); sgbm: semi-global")
    num_disparities: int = Field(64, ge=16, le=512, multiple_of=16, description="disparity search range, px")
    min_disparity: int = Field(0, ge=-256, le=256, description="smallest disparity searched, px")
    block_size: int = Field(15, ge=1, le=255, description="matching window, odd, px")
    uniqueness_ratio: int = Field(10, ge=0, le=100, description="reject matches not this % better than the next")
    texture_threshold: int = Field(10, ge=0, description="bm: reject windows with less texture")
    speckle_window: int = Field(100, ge=0, description="max size of speckles removed, px (0: off)")
    speckle_range: int = Field(2, ge=0, description="max disparity variation within a speckle")
    threads: int = Field(0, ge=0, le=64, description="OpenCV threads for matching (0: one per core)")

    def matcher_config(self) -> MatcherConfig:
        return MatcherConfig(method=self.method, num_disparities=self.num_disparities,
                             min_disparity=self.min_disparity, block_size=self.block_size,
                             uniqueness_ratio=self.uniqueness_ratio, texture_threshold=self.texture_threshold,
                             speckle_window=self.speckle_window, speckle_range=self.speckle_range)


def run(node: Node, settings: DisparitySettings) -> None:
    import cv2

    if settings.threads:
        cv2.setNumThreads(settings.threads)
    cfg = settings.matcher_config()
    matcher = StereoMatcher(cfg)
    inbox = node.latest("frames_rect")
    out = node.publisher("disparity")
    for msg in node.receive(inbox):
        with node.processing(msg):
            if msg.camera is None:
                raise DecodeError("StereoFrame.camera: missing; disparity needs a rectified pair")
            left = codec.array_from_image(msg.left, "left")
            right = codec.array_from_image(msg.right, "right")
            if (msg.left.width, msg.left.height) != (msg.camera.width, msg.camera.height):
                raise DecodeError(f"left image is {msg.left.width}x{msg.left.height}, its camera model "
                                  f"{msg.camera.width}x{msg.camera.height}")
            disp = matcher.compute(left, right)
            out.put(DisparityMap(robot_id=msg.robot_id, seq=msg.seq, stamp_ns=msg.stamp_ns, stages=msg.stages,
                                 image=codec.image_from_array(disp), scale=SCALE,
                                 invalid_value=float(cfg.invalid_value), min_disparity=cfg.min_disparity,
                                 num_disparities=cfg.num_disparities, camera=msg.camera, method=cfg.method,
                                 worker=node.instance))
