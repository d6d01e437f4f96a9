"""disparity: frames_rect -> disparity, by a pool of workers on any host (see pool.py).

`run disparity` (role dispatch, on the robot) follows the workers' liveliness tokens and hands each
rectified frame to exactly one free worker; with no worker alive it computes onboard (fallback) or
reports "no worker reachable". `run disparity --role worker` (anywhere) computes frames from its own
work key and publishes DisparityMap on `disparity`.
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from ...common.node import Node
from .config import MatcherConfig

SUBSCRIBES = ["frames_rect", "work_done", "worker", "work"]  # dispatch: frames_rect, work_done, worker; worker: work
PUBLISHES = ["disparity", "work", "work_done", "worker"]


class DisparitySettings(MatcherConfig):
    """The service's settings: the matching settings (MatcherConfig, consumed by the cores as they
    are) plus where this process sits in the worker pool."""

    role: Literal["dispatch", "worker"] = Field("dispatch", description="dispatch: robot side, hands frames to "
                                                "workers; worker: computes frames from its own work key")
    # pool (dispatch side)
    max_in_flight: int = Field(2, ge=1, le=16, description="frames in flight per worker (2: the next frame "
                               "waits at the worker while it computes, so it never idles while frames travel)")
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


def node_options(settings: DisparitySettings) -> dict:
    """A worker reports on the workers' own stats and alive keys (keys.py: worker_stats): it may run
    offboard, where it must not be able to speak for the dispatcher."""
    return {"worker_keys": settings.role == "worker"}


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
