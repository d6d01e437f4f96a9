"""The one table of Zenoh keys. No service spells a key string itself: it asks this table.

Public: `ballbot/obstacles/<robot_id>` and `ballbot/freespace/<robot_id>`. Everything else lives
under `ballbot/<robot_id>/`, except a fleet pool's keys (`ballbot/pool/<pool>/...`, shared by the
robots that use the pool): in those, the robot id sits where a router's access control can pin it (a
robot sends only `work/*/<its id>`, reads only `result/<its id>/*`), see docs/fleet.md.
"""
from __future__ import annotations

from dataclasses import dataclass

from pydantic import BaseModel

from common.messages import (
    CalibrationUpdate,
    DisparityMap,
    FreeSpace,
    GroundTruth,
    ObstacleList,
    Odometry,
    PoolDemand,
    PoolGrant,
    ReplayControl,
    ServiceStats,
    StereoFrame,
    WorkDone,
)


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

    def pattern(self, robot_id: str = "*", **fields: str) -> str:
        """Key expression matching every instance of this topic (wildcards for unknown fields)."""
        out = self.template.replace("{robot_id}", robot_id)
        for name, value in fields.items():
            out = out.replace("{" + name + "}", value)
        while "{" in out:
            i, j = out.index("{"), out.index("}")
            out = out[:i] + "*" + out[j + 1:]
        return out


TOPICS: dict[str, Topic] = {t.name: t for t in [
    Topic("frames_raw", "ballbot/{robot_id}/frames/raw", StereoFrame, "capture", 30.0, ("rectify", "recorder"),
          "raw stereo pair, left and right share seq and stamp", image_stream=True, max_bytes=80 << 20),
    Topic("truth", "ballbot/{robot_id}/truth", GroundTruth, "capture", 30.0,
          ("viewer", "foxglove", "recorder", "tests"),
          "ground truth of the synthetic scene for the pair with the same seq", max_bytes=4 << 20),
    Topic("frames_rect", "ballbot/{robot_id}/frames/rectified", StereoFrame, "rectify", 30.0,
          ("disparity", "viewer", "foxglove", "recorder", "ros2"),
          "rectified pair with its camera model", image_stream=True, max_bytes=80 << 20),
    Topic("disparity", "ballbot/{robot_id}/disparity", DisparityMap, "disparity", 30.0,
          ("segmenter", "viewer", "foxglove", "recorder", "ros2"),
          "disparity map of the rectified left image, fixed point; only the robot's dispatcher publishes "
          "here, signed with the robot's key", image_stream=True, max_bytes=40 << 20),
    Topic("worker", "ballbot/{robot_id}/workers/{instance}", None, "disparity", 0.0, ("disparity",),
          "liveliness token of a disparity worker ready for work on its own work key"),
    Topic("work", "ballbot/{robot_id}/work/{instance}", StereoFrame, "disparity", 30.0, ("disparity",),
          "rectified pair for one worker (dispatcher -> worker; raw, png or jpeg)", image_stream=True,
          max_bytes=80 << 20),
    Topic("work_result", "ballbot/{robot_id}/work_result/{instance}", DisparityMap, "disparity", 30.0,
          ("disparity",), "a worker's map for one work item, on the worker's own key (worker -> dispatcher, "
          "which checks it against the item and republishes it on disparity)", image_stream=True,
          max_bytes=40 << 20),
    Topic("work_done", "ballbot/{robot_id}/work_done/{instance}", WorkDone, "disparity", 30.0, ("disparity",),
          "a worker's receipt for a work item it dropped (worker -> dispatcher)", max_bytes=64 << 10),
    # A fleet pool (services/disparity/fleet.py): workers shared by any robot, granted work fairly.
    Topic("pool_worker", "ballbot/pool/{pool}/workers/{instance}", None, "disparity", 0.0, ("disparity",),
          "liveliness token of a pool worker (`run disparity --role worker --pool NAME`) ready for grants"),
    Topic("pool_demand", "ballbot/pool/{pool}/demand/{robot_id}", PoolDemand, "disparity", 20.0, ("disparity",),
          "a robot's dispatcher: it has a frame and no grant (want), or gives grants back (dispatcher -> every "
          "pool worker)", max_bytes=16 << 10),
    Topic("pool_grant", "ballbot/pool/{pool}/grant/{robot_id}/{instance}", PoolGrant, "disparity", 30.0,
          ("disparity",), "a pool worker lets one robot send it one frame (worker -> that robot's dispatcher), "
          "issued by weighted fair queueing over the robots that want", max_bytes=16 << 10),
    Topic("pool_work", "ballbot/pool/{pool}/work/{instance}/{robot_id}", StereoFrame, "disparity", 30.0,
          ("disparity",), "rectified pair for one pool worker, sent against a grant (dispatcher -> worker)",
          image_stream=True, max_bytes=80 << 20),
    Topic("pool_result", "ballbot/pool/{pool}/result/{robot_id}/{instance}", DisparityMap, "disparity", 30.0,
          ("disparity",), "a pool worker's map for one item, to the robot that sent it only (worker -> that "
          "robot's dispatcher, which checks it and republishes it on disparity)", image_stream=True,
          max_bytes=40 << 20),
    Topic("pool_done", "ballbot/pool/{pool}/done/{robot_id}/{instance}", WorkDone, "disparity", 30.0,
          ("disparity",), "a pool worker's receipt for an item it dropped (worker -> that robot's dispatcher)",
          max_bytes=64 << 10),
    Topic("pool_stats", "ballbot/pool/{pool}/stats/{instance}", ServiceStats, "disparity", 1.0, ("status",),
          "a pool worker's stats, with each robot's weight, share, queue and maps/s", max_bytes=256 << 10),
    Topic("pool_alive", "ballbot/pool/{pool}/alive/{instance}", None, "disparity", 0.0, ("status",),
          "liveliness token of a running pool worker process"),
    Topic("obstacles", "ballbot/obstacles/{robot_id}", ObstacleList, "segmenter", 30.0, ("anyone",),
          "PUBLIC: obstacle list with 3D positions in metres", public=True, max_bytes=4 << 20),
    Topic("freespace", "ballbot/freespace/{robot_id}", FreeSpace, "segmenter", 30.0, ("anyone",),
          "PUBLIC: occupancy grid of the ground around the robot, base frame", public=True, max_bytes=17 << 20),
    Topic("odometry", "ballbot/{robot_id}/odometry", Odometry, "robot", 0.0, ("segmenter",),
          "the robot's own velocity over the ground (optional input: ground-referenced obstacle velocities)",
          max_bytes=64 << 10),
    Topic("stats", "ballbot/{robot_id}/stats/{service}/{instance}", ServiceStats, "every service", 1.0,
          ("status", "viewer", "recorder", "capture"), "per-instance rate, latency, drops and errors, once a second "
          "(capture's replay follows rectify's)", max_bytes=256 << 10),
    Topic("alive", "ballbot/{robot_id}/alive/{service}/{instance}", None, "every service", 0.0,
          ("status", "capture"), "liveliness token of a running instance"),
    # An offboard worker's own keys, apart from the robot services' (service segment WORKER_SEGMENT,
    # which no service is named): the gateway's worker role may write these and no other stats or
    # alive key, so a worker can never pose as the dispatcher or any robot service, and `status` /
    # `healthcheck` show what comes from here as self-reported.
    Topic("worker_stats", "ballbot/{robot_id}/stats/worker/{instance}", ServiceStats, "disparity (worker)", 1.0,
          ("status",), "a disparity worker's own stats, once a second (self-reported: never a robot service's)",
          max_bytes=256 << 10),
    Topic("worker_alive", "ballbot/{robot_id}/alive/worker/{instance}", None, "disparity (worker)", 0.0,
          ("status",), "liveliness token of a running disparity worker"),
    Topic("calibration", "ballbot/{robot_id}/calibration", CalibrationUpdate, "calibrate, capture", 0.0,
          ("rectify", "recorder"),
          "a new calibration (YAML text) for rectify, applied between frames without a restart", max_bytes=2 << 20),
    Topic("replay_control", "ballbot/{robot_id}/replay/control", ReplayControl, "viewer, replay", 0.0, ("capture",),
          "play / pause / step a replayed recording (capture --source mcap)", max_bytes=64 << 10),
]}

# The service segment of the workers' stats and alive keys; no service may be named so.
WORKER_SEGMENT = "worker"

OBSTACLES_ALL = "ballbot/obstacles/**"
POOL_ROOT = "ballbot/pool/"  # every fleet pool's keys start so (the pool_* topics above)
FREESPACE_ALL = "ballbot/freespace/**"


def topic(name: str) -> Topic:
    return TOPICS[name]


def markdown_table() -> str:
    """The key table as Markdown (docs/keys.md is this text; a test holds it to the table)."""
    rows = ["| key | message | producer | consumers | rate | what |", "|---|---|---|---|---|---|"]
    for t in TOPICS.values():
        model = t.model.__name__ if t.model else "liveliness token"
        rate = f"{t.rate_hz:g} Hz" if t.rate_hz else "event"
        key = t.template.replace("{", "<").replace("}", ">")
        rows.append(f"| `{key}` | {model} | {t.producer} | {', '.join(t.consumers)} | {rate} | "
                    f"{t.description} |")
    return "\n".join(rows) + "\n"


def _chunks_meet(a: list[str], b: list[str]) -> bool:
    """Do two key expressions (chunks split on '/'; '*' one chunk, '**' any number) share a key?"""
    if not a or not b:
        return (not a or a == ["**"]) and (not b or b == ["**"])
    if a[0] == "**":
        return _chunks_meet(a[1:], b) or _chunks_meet(a, b[1:])
    if b[0] == "**":
        return _chunks_meet(a, b[1:]) or _chunks_meet(a[1:], b)
    return (a[0] == b[0] or "*" in (a[0], b[0])) and _chunks_meet(a[1:], b[1:])


def topics_of(key_expr: str) -> list[str]:
    """The names of the table's topics a key expression is meant for: of those it reaches (any
    robot), the ones whose literal chunks it names most (`ballbot/obstacles/**` would also reach
    `ballbot/*/frames/raw` for a robot called "obstacles": it means the obstacle lists)."""
    chunks = key_expr.split("/")
    literal = {c for c in chunks if "*" not in c}
    scored = [(len(literal & {c for c in t.pattern("*").split("/") if c != "*"}), t.name) for t in TOPICS.values()
              if _chunks_meet(chunks, t.pattern("*").split("/"))]
    best = max((n for n, _ in scored), default=0)
    return [name for n, name in scored if n == best]
