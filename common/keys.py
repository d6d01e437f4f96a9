"""The one table of Zenoh keys. No service spells a key string itself: it asks this table.

Public: `ballbot/obstacles/<robot_id>` and `ballbot/freespace/<robot_id>`. Everything else lives under `ballbot/<robot_id>/`.
"""
from __future__ import annotations

from dataclasses import dataclass

from pydantic import BaseModel

from .messages import (CalibrationUpdate, DisparityMap, FreeSpace, GroundTruth, ObstacleList, Odometry, ReplayControl,
                       ServiceStats, StereoFrame, WorkDone)


@dataclass(frozen=True)
class Topic:
    name: str
    template: str
    model: type[BaseModel] | None  # None: a liveliness token, no payload
    producer: str
    rate_hz: float  # expected rate; 0 = event-driven
    consumers: tuple[str, ...]
    description: str
    image_stream: bool = False  # large payloads: newest wins, DROP under congestion
    public: bool = False  # a contract with users: ballbot/<what>/<robot_id>, outside the internal tree
    # Largest payload accepted on this key, checked before anything is copied or decoded (a
    # subscriber may tighten it, e.g. rectify from its calibrated image size). Images: a 4096x3000
    # colour stereo pair; small messages: far above any honest one.
    max_bytes: int = 1 << 20

    def key(self, robot_id: str, **fields: str) -> str:
        return self.template.format(robot_id=robot_id, **fields)

    def pattern(self, robot_id: str = "*") -> str:
        """Key expression matching every instance of this topic (wildcards for unknown fields)."""
        out = self.template.replace("{robot_id}", robot_id)
        while "{" in out:
            i, j = out.index("{"), out.index("}")
            out = out[:i] + "*" + out[j + 1:]
        return out


TOPICS: dict[str, Topic] = {t.name: t for t in [
    Topic("frames_raw", "ballbot/{robot_id}/frames/raw", StereoFrame, "capture", 30.0, ("rectify",),
          "raw stereo pair, left and right share seq and stamp", image_stream=True, max_bytes=80 << 20),
    Topic("truth", "ballbot/{robot_id}/truth", GroundTruth, "capture", 30.0, ("eval", "tests"),
          "ground truth of the synthetic scene for the pair with the same seq", max_bytes=4 << 20),
    Topic("frames_rect", "ballbot/{robot_id}/frames/rectified", StereoFrame, "rectify", 30.0, ("disparity",),
          "rectified pair with its camera model", image_stream=True, max_bytes=80 << 20),
    Topic("disparity", "ballbot/{robot_id}/disparity", DisparityMap, "disparity", 30.0, ("segmenter",),
          "disparity map of the rectified left image, fixed point", image_stream=True, max_bytes=40 << 20),
    Topic("worker", "ballbot/{robot_id}/workers/{instance}", None, "disparity", 0.0, ("disparity",),
          "liveliness token of a disparity worker ready for work on its own work key"),
    Topic("work", "ballbot/{robot_id}/work/{instance}", StereoFrame, "disparity", 30.0, ("disparity",),
          "rectified pair for one worker (dispatcher -> worker; raw, png or jpeg)", image_stream=True,
          max_bytes=80 << 20),
    Topic("work_done", "ballbot/{robot_id}/work_done/{instance}", WorkDone, "disparity", 30.0, ("disparity",),
          "a worker's receipt for one work item (worker -> dispatcher)", max_bytes=64 << 10),
    Topic("obstacles", "ballbot/obstacles/{robot_id}", ObstacleList, "segmenter", 30.0, ("anyone",),
          "PUBLIC: obstacle list with 3D positions in metres", public=True, max_bytes=4 << 20),
    Topic("freespace", "ballbot/freespace/{robot_id}", FreeSpace, "segmenter", 30.0, ("anyone",),
          "PUBLIC: occupancy grid of the ground around the robot, base frame", public=True, max_bytes=17 << 20),
    Topic("odometry", "ballbot/{robot_id}/odometry", Odometry, "robot", 0.0, ("segmenter",),
          "the robot's own velocity over the ground (optional input: ground-referenced obstacle velocities)",
          max_bytes=64 << 10),
    Topic("stats", "ballbot/{robot_id}/stats/{service}/{instance}", ServiceStats, "every service", 1.0,
          ("status",), "per-instance rate, latency, drops and errors, once a second", max_bytes=256 << 10),
    Topic("alive", "ballbot/{robot_id}/alive/{service}/{instance}", None, "every service", 0.0,
          ("status",), "liveliness token of a running instance"),
    # An offboard worker's own keys, apart from the robot services' (service segment WORKER_SEGMENT,
    # which no service is named): the gateway's worker role may write these and no other stats or
    # alive key, so a worker can never pose as the dispatcher or any robot service, and `status` /
    # `healthcheck` show what comes from here as self-reported.
    Topic("worker_stats", "ballbot/{robot_id}/stats/worker/{instance}", ServiceStats, "disparity (worker)", 1.0,
          ("status",), "a disparity worker's own stats, once a second (self-reported: never a robot service's)",
          max_bytes=256 << 10),
    Topic("worker_alive", "ballbot/{robot_id}/alive/worker/{instance}", None, "disparity (worker)", 0.0,
          ("status",), "liveliness token of a running disparity worker"),
    Topic("calibration", "ballbot/{robot_id}/calibration", CalibrationUpdate, "calibrate, capture", 0.0, ("rectify",),
          "a new calibration (YAML text) for rectify, applied between frames without a restart", max_bytes=2 << 20),
    Topic("replay_control", "ballbot/{robot_id}/replay/control", ReplayControl, "viewer, replay", 0.0, ("capture",),
          "play / pause / step a replayed recording (capture --source mcap)", max_bytes=64 << 10),
]}

# The service segment of the workers' stats and alive keys; no service may be named so.
WORKER_SEGMENT = "worker"

OBSTACLES_ALL = "ballbot/obstacles/**"
FREESPACE_ALL = "ballbot/freespace/**"


def topic(name: str) -> Topic:
    return TOPICS[name]
