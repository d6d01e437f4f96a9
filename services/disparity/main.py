"""disparity: frames_rect -> disparity, by a pool of workers on any host (see pool.py).

`run disparity` (role dispatch, on the robot) follows the workers' liveliness tokens and hands each
rectified frame to exactly one free worker; with no worker alive it computes onboard (fallback) or
reports "no worker reachable". `run disparity --role worker` (anywhere) computes frames from its own
work key and publishes DisparityMap on `disparity`.
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from ...common.errors import BallbotError
from ...common.node import Node
from ...common.settings import ServiceSettings
from .matchers import MatcherConfig

SUBSCRIBES = ["frames_rect", "work_done", "worker", "work"]  # dispatch: frames_rect, work_done, worker; worker: work
PUBLISHES = ["disparity", "work", "work_done", "worker"]


class DisparitySettings(ServiceSettings):
    section = "disparity"
    role: Literal["dispatch", "worker"] = Field("dispatch", description="dispatch: robot side, hands frames to "
                                                "workers; worker: computes frames from its own work key")
    method: Literal["bm", "sgbm"] = Field("bm", description="bm: block matching, SAD (the thesis); sgbm: semi-global")
    num_disparities: int = Field(64, ge=16, le=512, multiple_of=16, description="disparity search range, px")
    min_disparity: int = Field(0, ge=-256, le=256, description="smallest disparity searched, px")
    block_size: int = Field(0, ge=0, le=255, description="matching window, odd, px (0: bm 15, sgbm 5)")
    uniqueness_ratio: int = Field(10, ge=0, le=100, description="reject matches not this percent better than the next")
    texture_threshold: int = Field(10, ge=0, description="bm: reject windows with less texture")
    speckle_window: int = Field(100, ge=0, description="max size of speckles removed, px (0: off)")
    speckle_range: int = Field(2, ge=0, description="max disparity variation within a speckle")
    prefilter: Literal["xsobel", "normalized"] = Field("xsobel", description="bm pre-filter")
    prefilter_size: int = Field(9, ge=5, le=255, description="bm normalized pre-filter window, odd, px")
    prefilter_cap: int = Field(31, ge=1, le=63, description="pre-filter clipping")
    p1: int = Field(0, ge=0, description="sgbm smoothness penalty for +-1 px changes (0: 8*block^2)")
    p2: int = Field(0, ge=0, description="sgbm penalty for larger changes (0: 32*block^2)")
    sgbm_mode: Literal["sgbm", "hh", "3way", "hh4"] = Field("sgbm", description="sgbm variant (hh: 8 paths)")
    lr_check: bool = Field(False, description="left-right consistency check (doubles matching time)")
    lr_max_diff: float = Field(1.0, ge=0, description="max left/right disagreement, px")
    subpixel: bool = Field(True, description="1/16 px output; false rounds to whole px")
    max_range_m: float = Field(0.0, ge=0, description="vision range gate, m (disparity >= f*B/range; 0: off)")
    threads: int = Field(0, ge=0, le=64, description="OpenCV threads for matching (0: one per core)")
    # pool (dispatch side)
    max_in_flight: int = Field(1, ge=1, le=16, description="frames in flight per worker")
    max_age_ms: float = Field(500.0, gt=0, description="a frame older than this is never started")
    result_timeout_s: float = Field(1.0, gt=0, description="a worker slot without receipt is freed "
                                    "after this at the least; longer for a worker measured to need longer")
    transport: Literal["raw", "png", "jpeg"] = Field("raw", description="image encoding of frames sent to workers")
    jpeg_quality: int = Field(90, ge=1, le=100, description="for transport jpeg")
    fallback: Literal["none", "full", "half"] = Field("full", description="onboard matcher used only while no "
                                                     "worker is alive (half: half resolution; none: report \"no worker reachable\")")
    # worker side
    result_encoding: Literal["raw", "png"] = Field("raw", description="disparity map encoding (png: lossless, "
                                                   "for narrow links; invalid 0)")

    @model_validator(mode="after")
    def _check(self) -> "DisparitySettings":
        try:
            self.matcher_config()
        except BallbotError as e:  # bad combinations (even block size, ...) read like any bad setting
            raise ValueError(str(e)) from None
        return self

    def matcher_config(self) -> MatcherConfig:
        return MatcherConfig(method=self.method, num_disparities=self.num_disparities,
                             min_disparity=self.min_disparity, block_size=self.block_size,
                             uniqueness_ratio=self.uniqueness_ratio, texture_threshold=self.texture_threshold,
                             speckle_window=self.speckle_window, speckle_range=self.speckle_range,
                             prefilter=self.prefilter, prefilter_size=self.prefilter_size,
                             prefilter_cap=self.prefilter_cap, p1=self.p1, p2=self.p2, sgbm_mode=self.sgbm_mode,
                             lr_check=self.lr_check, lr_max_diff=self.lr_max_diff, subpixel=self.subpixel)


def run(node: Node, settings: DisparitySettings) -> None:
    import cv2

    from .pool import run_dispatcher, run_worker

    if settings.threads:
        cv2.setNumThreads(settings.threads)
    if settings.role == "worker":
        node.role = "worker"
        run_worker(node, settings)
    else:
        node.role = "dispatcher"
        run_dispatcher(node, settings)
