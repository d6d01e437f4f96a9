"""disparity: frames_rect -> disparity, by a pool of workers on any host (see dispatcher.py).

`run disparity` (role dispatch, on the robot) follows the workers' liveliness tokens and hands each
rectified frame to exactly one free worker; with no worker alive it computes onboard (fallback) or
reports "no worker reachable". `run disparity --role worker` (anywhere) computes frames from its own
work key and publishes DisparityMap on `disparity`.

A fleet pool (fleet.py): `run disparity --role worker --pool NAME` serves any robot whose dispatcher
runs with `--pool NAME`, each robot its weighted share (`--pool-weights robotA=2,robotB=1`); with
`--serve-robot` it also serves its own robot's work key.
"""
from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BeforeValidator, Field

from common.codec import MIN_JPEG_QUALITY
from common.node import Node
from cores.matching.config import MatcherConfig

# dispatch: frames_rect, work_result, work_done, worker (+ pool_result, pool_done, pool_grant, pool_worker);
# worker: work (+ pool_demand, pool_work)
SUBSCRIBES = ["frames_rect", "work_result", "work_done", "worker", "work", "pool_worker", "pool_demand", "pool_grant",
              "pool_work", "pool_result", "pool_done"]
PUBLISHES = ["disparity", "work", "work_result", "work_done", "worker", "pool_worker", "pool_demand", "pool_grant",
             "pool_work", "pool_result", "pool_done", "pool_stats", "pool_alive"]


def _weights(value):
    from services.disparity.scheduler import parse_weights

    return parse_weights(value)


class DisparitySettings(MatcherConfig):
    """The service's settings: the matching settings (MatcherConfig, consumed by the cores as they
    are) plus where this process sits in the worker pool."""

    role: Literal["dispatch", "worker"] = Field("dispatch", description="dispatch: robot side, hands frames to "
                                                "workers; worker: computes frames from its own work key")
    # pool (dispatch side)
    max_in_flight: int = Field(2, ge=1, le=16, description="frames in flight per worker (2: the next frame "
                               "waits at the worker while it computes, so it never idles while frames travel)")
    max_age_ms: float = Field(500.0, gt=0, le=10000, description="a frame older than this is never started (at "
                              "most 10 s: the segmenter's stale_after_s can be no longer)")
    result_timeout_s: float = Field(1.0, gt=0, description="a worker slot without receipt is freed "
                                    "after this at the least; longer for a worker measured to need longer")
    transport: Literal["raw", "png", "jpeg"] = Field("raw", description="image encoding of frames sent to workers")
    jpeg_quality: int = Field(90, ge=MIN_JPEG_QUALITY, le=100, description="for transport jpeg (from 85: "
                              "common/codec.py)")
    fallback: Literal["none", "full", "half"] = Field("full", description="onboard matcher used only while no "
                                                     "worker is alive (half: half resolution; "
                                                     "none: report \"no worker reachable\")")
    # fleet pool (both sides)
    pool: str = Field("", pattern=r"^([A-Za-z0-9_.-]{1,64})?$", description="a fleet pool's name: a worker serves "
                      "any robot of it (its stats go to the pool's keys); a dispatcher also sends work to its workers "
                      "(empty: no pool)")
    serve_robot: bool = Field(False, description="worker with --pool: also serve its own robot's work key")
    pool_weights: Annotated[dict[str, float], BeforeValidator(_weights)] = Field(
        default_factory=dict, description="worker with --pool: each robot's weight, robotA=2,robotB=1 (others 1)")
    pool_queue: int = Field(1, ge=1, le=8, description="worker with --pool: items waiting beside the one computed "
                            "(1: a frame is ready when the current one ends, and none waits behind more than one)")
    pool_grant_ttl_s: float = Field(1.0, gt=0, le=30, description="worker with --pool: a grant not used in this "
                                    "time goes to the next robot")
    pool_patience_s: float = Field(1.0, gt=0, description="dispatcher with --pool: wanting this long without a grant "
                                   "(a full pool), the onboard fallback computes the frame")
    # worker side
    result_encoding: Literal["raw", "png"] = Field("raw", description="disparity map encoding (png: lossless, "
                                                   "for narrow links; invalid 0)")


def node_options(settings: DisparitySettings) -> dict:
    """A pool worker's stats and liveliness go to its pool's keys, so no robot's `status` takes it
    for one of its own services; any other worker reports on the workers' own stats and alive keys
    (keys.py: worker_stats): it may run offboard, where it must not be able to speak for the dispatcher."""
    if settings.role == "worker" and settings.pool:
        return {"pool": settings.pool}
    return {"worker_keys": settings.role == "worker"}


def run(node: Node, settings: DisparitySettings) -> None:
    import cv2

    from services.disparity.dispatcher import run_dispatcher
    from services.disparity.worker import run_worker

    if settings.threads:
        cv2.setNumThreads(settings.threads)
    if settings.role == "worker" and settings.pool:
        from services.disparity.fleet import run_pool_worker

        node.role = "pool-worker"
        run_pool_worker(node, settings)
    elif settings.role == "worker":
        node.role = "worker"
        run_worker(node, settings)
    else:
        node.role = "dispatcher"
        run_dispatcher(node, settings)
