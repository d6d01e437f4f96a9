"""The messages that travel over Zenoh. Pydantic models, msgpack on the wire (see codec.py).

Every message carries `schema_version`, `robot_id`, `seq` (the capture sequence number) and
`stamp_ns` (capture time, ns since the Unix epoch). `stages` maps a service name to the time (ns)
that service published its output for this `seq`, so latency can be split per stage.

Frame convention: "camera" is the rectified left camera, OpenCV optical axes (x right, y down,
z forward), metres. "base" is the robot base frame of ROS REP 103 (x forward, y left, z up).
"""
from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

# 2: ground estimate, track confirmation, truncation and base-frame velocities in ObstacleList;
#    FreeSpace; Odometry; an optional confidence image beside a disparity map.
# 3: ObstacleList.degraded and valid_fraction (can this list be trusted); GroundEstimate.confidence and the
#    configured mount beside the fitted ground (prior_*).
# 4: ObstacleList.range_m (the distances a list looked at: what "looked and saw nothing" covers).
# 5: StereoFrame.checks and DisparityMap.checks (rectify's live checks of the pair: rows, frozen cameras).
# 6: FrameChecks.blocked (a camera's view partly blocked).
# 7: ObstacleList.bearing_deg (the bearings a list looked at: left of the search's band is not among them).
# 8: RowAlignment.reversed_share (swapped cameras: the lists say cameras-swapped); FrameChecks.near (what
#    stands nearer than the vision range: the lists say nearer-than-range).
# 9: FrameChecks.clipped (where both cameras are washed out: the lists say washed-out).
# 10: CameraModel.view_left / view_right (the part of the rectified picture each camera saw, alpha > 0).
# 11: DisparityMap.gate_px (the matcher's vision range gate: what lies farther is not in the map; a gate
#     nearer than the segmenter's range makes the lists say far-unmeasured); FrameChecks.noise_grey (the
#     pictures' sensor noise: dusk's gain makes the lists say noisy).
# 12: DisparityMap.flat (sgbm's windows too plain to decide their match: no floor seen there for the free space).
SCHEMA_VERSION = 12

MAX_OUTLINE_POINTS = 4096
MAX_MIN_DISPARITY = 256  # |min_disparity| of a disparity search, px
MAX_NUM_DISPARITIES = 512  # disparities a search spans, px (a multiple of 16)
Pixel = Annotated[float, Field(ge=-65536.0, le=65536.0)]  # an image coordinate, px (fits fillPoly's fixed point)
Vec3 = tuple[float, float, float]
Metres = Annotated[float, Field(allow_inf_nan=False, ge=0.0, le=1000.0)]
Degrees90 = Annotated[float, Field(allow_inf_nan=False, ge=-90.0, le=90.0)]
# A robot's own motion: finite and physical, so one forged message cannot turn every track into NaN
Speed = Annotated[float, Field(allow_inf_nan=False, ge=-100.0, le=100.0)]  # m/s
TurnRate = Annotated[float, Field(allow_inf_nan=False, ge=-50.0, le=50.0)]  # rad/s


class Message(BaseModel):
    model_config = ConfigDict(extra="forbid")

    schema_version: int = SCHEMA_VERSION
    robot_id: str = Field(min_length=1, max_length=64)
    seq: int = Field(ge=0, description="capture sequence number, shared by everything derived from one pair")
    stamp_ns: int = Field(ge=0, description="capture time of the pair, ns since the Unix epoch")
    stages: dict[str, int] = Field(default_factory=dict, description="service -> publish time (ns) for this seq")


class Image(BaseModel):
    """One image. For encoding 'raw', `data` is the row-major pixel buffer (height, width[, channels])."""

    model_config = ConfigDict(extra="forbid")

    width: int = Field(gt=0, le=16384)
    height: int = Field(gt=0, le=16384)
    channels: Literal[1, 3] = 1
    dtype: Literal["uint8", "uint16", "int16", "float32"] = "uint8"
    encoding: Literal["raw", "png", "jpeg"] = "raw"
    data: bytes


class CameraModel(BaseModel):
    """The rectified camera: Z = focal_px * baseline_m / d; X = (u - cx) Z / f; Y = (v - cy) Z / f."""

    # every number finite: one NaN principal point would turn each obstacle, and then each track, into NaN
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    width: int = Field(gt=0)
    height: int = Field(gt=0)
    focal_px: float = Field(gt=0)
    cx: float
    cy: float
    baseline_m: float = Field(gt=0)
    Q: list[float] = Field(min_length=16, max_length=16, description="4x4 disparity-to-depth matrix, row-major")
    view_left: list[tuple[Pixel, Pixel]] | None = Field(
        None, min_length=3, max_length=MAX_OUTLINE_POINTS, description="outline (polygon, px) of the part of the "
        "rectified left picture the left camera saw (None: all of it). rectify's alpha above 0 keeps more of the "
        "view and leaves the rest black; the matcher measures nothing within its window of the black")
    view_right: list[tuple[Pixel, Pixel]] | None = Field(
        None, min_length=3, max_length=MAX_OUTLINE_POINTS, description="the same for the right picture")


class RowAlignment(BaseModel):
    """rectify's last live check that its pairs are rectified: matched features of one pair lie on
    the same row in both images (cores/calibration/check.py: RowMonitor). Over `tolerance_px` the
    calibration no longer fits the rig (a knocked camera, a loose lens, another rig's calibration):
    the matcher measures less and wrongly, and each list says `rows-misaligned`."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    offset_px: float = Field(ge=0, le=1000, description="median vertical offset |dy| of the matched features, px")
    p95_px: float = Field(ge=0, le=1000, description="its 95th percentile, px")
    matches: int = Field(ge=0, description="features measured")
    tolerance_px: float = Field(gt=0, le=1000, description="rectify's max_row_offset_px: more is misaligned")
    checked_ns: int = Field(ge=0, description="capture stamp of the pair checked")
    reversed_share: float = Field(0.0, ge=0, le=1, description="of the matched features over 1 px off zero "
                                  "disparity, the share at negative disparity (left of their place in the right "
                                  "image): about 0 for a rectified pair, about 1 with the cameras swapped; over "
                                  "0.5 each list says cameras-swapped (0: fewer than 10 such features)")


class NearField(BaseModel):
    """rectify's coarse disparity map of the pair over a wide search (cores/calibration/near.py):
    what stands nearer than the matcher's search reaches shows here, so a list can say its view of
    the range was blocked (`nearer-than-range`) instead of saying nothing."""

    model_config = ConfigDict(extra="forbid")

    width: int = Field(gt=0, le=1024, description="coarse pixels across")
    height: int = Field(gt=0, le=1024, description="coarse pixels down")
    image_width: int = Field(gt=0, le=16384, description="the rectified pair's width it was made from, px")
    image_height: int = Field(gt=0, le=16384, description="the rectified pair's height, px")
    data: bytes = Field(description="width*height uint8, row-major: disparity in quarter coarse px (0: not "
                       "measured)")

    @model_validator(mode="after")
    def _sized(self) -> NearField:
        if len(self.data) != self.width * self.height:
            raise ValueError(f"data: {len(self.data)} bytes for {self.width}x{self.height}")
        if self.width > self.image_width or self.height > self.image_height:
            raise ValueError("the coarse map is larger than the pair it was made from")
        return self


class ClippedTiles(BaseModel):
    """rectify's coarse grid over the rectified pair: per tile, the share of its pixels clipped white
    in both cameras at the same place, in patches whose outline is the same in both pictures, so at
    infinity (the sun or a lamp low ahead, glare over both lenses, the sky; not a white thing near
    enough to sit apart in the two). Nothing is measured there; the segmenter tells where on its
    floor the pair is blind (`washed-out`)."""

    model_config = ConfigDict(extra="forbid")

    width: int = Field(gt=0, le=256, description="tiles across")
    height: int = Field(gt=0, le=256, description="tiles down")
    data: bytes = Field(description="width*height uint8, row-major: the tile's share clipped in both "
                        "cameras, 0-255 for 0-1")

    @model_validator(mode="after")
    def _sized(self) -> ClippedTiles:
        if len(self.data) != self.width * self.height:
            raise ValueError(f"data: {len(self.data)} bytes for {self.width}x{self.height}")
        return self


class FrameChecks(BaseModel):
    """What rectify checked of a pair beyond its stamps, carried by the pair and its disparity map to
    the segmenter, whose list says what failed."""

    model_config = ConfigDict(extra="forbid")

    rows: RowAlignment | None = Field(None, description="the last live check of the rows (None: not checked yet)")
    frozen: list[Literal["left", "right"]] = Field(
        default_factory=list, max_length=2, description="cameras whose picture has not changed, bit for bit, for "
        "over rectify's frozen_after_s while stamps went on (a hung driver repeating its last buffer): each list "
        "says camera-frozen. One frozen camera of two leaves the maps changing, so input-frozen cannot tell")
    blocked: list[Literal["left", "right"]] = Field(
        default_factory=list, max_length=2, description="cameras with a part of their view blocked (a finger, a "
        "sticker, glare, grease: flat or blurred where the other camera sees texture), from the first pair "
        "rectify sees it in: each list says view-blocked; little or nothing standing there is measured")
    near: NearField | None = Field(None, description="the pair's coarse wide disparity map (None: not checked): "
                                   "what stands nearer than the vision range shows here; each list says "
                                   "nearer-than-range")
    clipped: ClippedTiles | None = Field(None, description="where both cameras are clipped white (None: not "
                                         "checked): over WASHED_OUT of the floor in range, each list says "
                                         "washed-out")
    noise_grey: float | None = Field(None, ge=0.0, le=255.0, allow_inf_nan=False,
                                     description="the noisier camera's sensor noise, grey levels (None: not "
                                     "checked): over NOISY_GREY (low light, a high gain), each list says noisy")


class StereoFrame(Message):
    """One stereo pair. Raw from capture (camera=None) or rectified by rectify (camera set)."""

    left: Image
    right: Image
    camera: CameraModel | None = None
    source: str = ""
    checks: FrameChecks | None = Field(None, description="rectify's live checks (None: a raw pair)")


class DisparityMap(Message):
    """Disparity of the rectified left image. pixel value / scale = disparity in px;
    pixels equal to invalid_value carry no measurement. depth_m = focal_px * baseline_m / disparity."""

    image: Image
    scale: float = Field(gt=0, description="fixed-point scale: disparity_px = value / scale")
    invalid_value: float = Field(description="raw pixel value marking 'no disparity'")
    # the search of any matcher of ours (MatcherConfig; a half-resolution one's doubled): a map saying
    # more was made by none, and where a list looked (range_m, bearing_deg) is read off these two
    min_disparity: int = Field(ge=-MAX_MIN_DISPARITY, le=MAX_MIN_DISPARITY, description="smallest disparity "
                               "searched, px")
    num_disparities: int = Field(ge=16, le=MAX_NUM_DISPARITIES, multiple_of=16, description="disparities searched "
                                 "from min_disparity, px")
    gate_px: float = Field(0.0, ge=0.0, le=4096.0, allow_inf_nan=False,
                           description="the matcher's vision range gate, px: smaller disparities (what lies farther "
                           "than its max_range_m) were dropped, measured or not (0: no gate)")
    camera: CameraModel
    method: str
    worker: str = ""
    confidence: Image | None = Field(None, description="per-pixel confidence of the disparity, uint8, same size: "
                                     "0 = no measurement, 255 = certain (None: the method gives none)")
    flat: Image | None = Field(None, description="uint8 png, same size: 255 where the matching window held too little "
                               "texture to decide its own match (semi-global matching carries the disparities around "
                               "it in: no evidence of floor there), 0 elsewhere (None: the method says nothing of it)")
    checks: FrameChecks | None = Field(None, description="the frame's StereoFrame.checks: rectify's live checks")


class WorkDone(Message):
    """A disparity worker's receipt for a work item (seq) it dropped: it frees the worker's slot at
    the dispatcher. A computed item is answered by its map on the worker's `work_result` key; the
    dispatcher takes either only with the item's nonce in the attachment."""

    worker: str = Field(min_length=1, description="instance name of the worker")
    ok: bool = Field(description="false: the item was dropped (too old, undecodable, failed)")
    reason: str = ""
    proc_ms: float = Field(0.0, ge=0, description="time from receipt to published map, ms")
    method: str = Field("", description="the matcher that produced the map (its DisparityMap.method); "
                        "empty for a dropped item")


GrantId = Annotated[str, Field(min_length=8, max_length=64, pattern=r"^[0-9a-f]+$")]


class PoolDemand(Message):
    """A robot's dispatcher to every worker of a fleet pool: `want` (it holds a frame and no grant;
    repeated while that lasts) and grants it gives back unused (`decline`). `seq` and `stamp_ns`
    are the sender's own counter and send time; the robot is the one in the key."""

    want: bool
    decline: list[GrantId] = Field(default_factory=list, max_length=32)


class PoolGrant(Message):
    """A pool worker lets one robot send it one frame: the frame must carry `grant` in its
    attachment, within `ttl_ms`. Issued by weighted fair queueing over the robots that want; the
    load figures are this worker's view when it granted. `seq` and `stamp_ns`: the worker's own
    counter and send time."""

    worker: str = Field(min_length=1, max_length=128)
    grant: GrantId
    ttl_ms: float = Field(gt=0, le=60000)
    robots: int = Field(0, ge=0, description="robots wanting or holding work at this worker")
    share: float = Field(0.0, ge=0, le=1, description="this robot's weight over theirs")
    queued: int = Field(0, ge=0, description="items waiting at the worker beside the one it computes")
    wait_ms: float = Field(0.0, ge=0, le=60000, description="how long a frame sent now would wait there before "
                           "it is started (a robot holding several grants sends to the soonest)")


class Obstacle(BaseModel):
    model_config = ConfigDict(extra="forbid")

    id: int = Field(ge=0, description="track id, stable across frames")
    position_m: Vec3 = Field(description="3D centroid, camera frame")
    size_m: Vec3 = Field(description="extent along x, y, z, camera frame")
    distance_m: float = Field(ge=0, description="distance to the nearest point of the obstacle")
    velocity_mps: Vec3 = (0.0, 0.0, 0.0)
    bbox_px: tuple[int, int, int, int] = Field(description="x0, y0, x1, y1 in the rectified left image")
    area_px: int = Field(ge=0)
    disparity_px: float = Field(description="robust (mode) disparity of the region")
    confidence: float = Field(ge=0, le=1, description="fraction of the region the matcher measured (a valid "
                              "disparity it decided itself: not a dense fill, not what sgbm carried into a plain "
                              "window)")
    position_base_m: Vec3 | None = Field(default=None, description="3D centroid in the robot base frame, if mounted")
    velocity_base_mps: Vec3 | None = Field(default=None, description="velocity in the robot base frame, if mounted "
                                           "(relative to what ObstacleList.velocity_reference says)")
    confirmed: bool = Field(True, description="the track was seen in enough recent frames to be trusted")
    track_frames: int = Field(1, ge=0, description="frames this track has been seen in")
    truncated: bool = Field(False, description="cut at the side by the edge of what the camera measures (the "
                            "image's side, the matcher's blind band) or by the vision range: position and size "
                            "describe the visible part; its velocity comes only from sightings that were not "
                            "cut (zero until one)")


class GroundEstimate(BaseModel):
    """The floor / road plane under the camera for this frame: where the camera is above it."""

    model_config = ConfigDict(extra="forbid")

    height_m: float = Field(description="camera height above the ground plane, m")
    pitch_deg: float = Field(description="camera pitch, positive looking down")
    roll_deg: float = Field(description="camera roll, positive right side down")
    source: Literal["fitted", "tracked", "prior", "none"] = Field(
        description="fitted: from this frame's disparity; tracked: fit rejected, the smoothed estimate of the "
                    "last frames; prior: the configured mount; none: unknown (no floor removed)")
    inlier_fraction: float = Field(0.0, ge=0, le=1, description="share of the valid pixels on the plane")
    confidence: float = Field(0.0, ge=0, le=1, description="how far the ground can be trusted for this frame: 0 = "
                              "not at all (no floor seen, a guess), 1 = a well-supported fit agreeing with the "
                              "recent frames")
    # The configured mount is a prior, never a cage: where the data disagree the fitted ground is used,
    # and what was configured stays visible beside it.
    prior_height_m: float | None = Field(None, description="the configured mount's camera height, m (None: no "
                                         "mount configured)")
    prior_pitch_deg: float | None = Field(None, description="the configured mount's pitch, deg")
    prior_roll_deg: float | None = Field(None, description="the configured mount's roll, deg")
    prior_agrees: bool | None = Field(None, description="the fitted ground agrees with the configured mount (within "
                                      "max_tilt_deg and 30 % of the height; with fit_floor false, where the mount "
                                      "is the floor: within 0.1 m over the floor in the vision range); None: no "
                                      "mount, or nothing fitted to check it by")


class CameraMount(BaseModel):
    """Where the rectified left camera sat on the robot base for one list (REP 103 base: x forward,
    y left, z up, origin on the floor; angles as in the `mount:` settings). The base-frame positions
    of the list, its free space and every picture or transform of it use exactly this."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    height_m: float = Field(gt=0, le=100)
    pitch_deg: float = Field(ge=-90, le=90, description="positive looking down")
    roll_deg: float = Field(ge=-180, le=180, description="positive right side down")
    yaw_deg: float = Field(0.0, ge=-180, le=180, description="positive turned left")
    x_m: float = Field(0.0, ge=-100, le=100)
    y_m: float = Field(0.0, ge=-100, le=100)
    source: Literal["ground", "configured"] = Field(
        description="ground: height, pitch and roll from this frame's ground estimate (yaw and offsets as "
                    "configured); configured: the `mount:` settings as they are (no ground this frame)")


class ObstacleList(Message):
    """What stands in the robot's way for one captured pair.

    The rule for planners: a list with `stale` false and `degraded` empty is trustworthy, and then
    an empty `obstacles` means "looked and saw nothing" at the distances in `range_m`. Anything else
    (stale, or any reason in `degraded`) means the view could not be checked as it should: slow down
    or stop, do not take an empty list as a clear way."""

    publish_ns: int = Field(ge=0)
    stale: bool = Field(description="true when the input stream stopped or fell behind")
    degraded: list[str] = Field(default_factory=list, max_length=32, description="short reasons this list cannot be "
                                "trusted as a full view (empty: trustworthy; e.g. 'input-frozen', "
                                "'no-valid-disparity', 'little-measured', 'valid-collapse', 'no-ground', "
                                "'ground-uncertain', 'range-unreachable', 'near-unmeasured', 'far-unmeasured', "
                                "'floor-out-of-view', 'standing-not-listed', "
                                "'mount-disagrees', 'rows-misaligned', 'cameras-swapped', 'camera-frozen', "
                                "'view-blocked', 'nearer-than-range', 'map-contradicted', 'washed-out', 'noisy')")
    valid_fraction: float = Field(0.0, ge=0, le=1, description="share of the image the disparity map measured "
                                  "(valid pixels within the vision range gate's search; with a confidence, only "
                                  "measured ones, not a dense matcher's fill) for this list")
    range_m: tuple[Metres, Metres] | None = Field(None, description="the distances this list looked at, m: "
                                                  "[nearest, farthest] of the vision range, or of the part of it "
                                                  "the disparity search measures where the list says near- or "
                                                  "far-unmeasured. What is nearer or farther is not in the list, "
                                                  "however clear it looks (None: not said)")
    bearing_deg: tuple[Degrees90, Degrees90] | None = Field(
        None, description="the bearings this list looked at, deg from the optical axis, positive to the right "
        "(camera x): [leftmost, rightmost] image column the disparity search measures at every distance of "
        "range_m. Left of it (x < min_disparity + num_disparities) the right camera does not see the near part "
        "of the range, and what stands there is not in the list, however clear it looks (None: not said)")
    frame_id: Literal["camera"] = "camera"
    method: str = ""
    obstacles: list[Obstacle] = Field(default_factory=list)
    ground: GroundEstimate | None = Field(None, description="the ground plane used for this list")
    mount: CameraMount | None = Field(None, description="the camera on the robot for this list (None: unknown, "
                                      "no base frame)")
    velocity_reference: Literal["camera", "ground"] = Field(
        "camera", description="camera: velocities relative to the moving camera; ground: over the ground "
                              "(the robot's own motion from odometry removed)")

    @field_validator("bearing_deg")
    @classmethod
    def _left_before_right(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and v[0] > v[1]:
            raise ValueError(f"leftmost bearing {v[0]:g} deg lies right of the rightmost, {v[1]:g} deg")
        return v

    def warnings(self) -> list[str]:
        """What a person watching must read before taking an empty list as a clear way (none when the
        list is trustworthy): STALE, and NOT A FULL VIEW with the degraded reasons."""
        return (["STALE"] if self.stale else []) + \
            ([f"NOT A FULL VIEW: {', '.join(self.degraded)}"] if self.degraded else [])


class FreeSpace(Message):
    """What the robot may drive on: a 2D occupancy grid on the ground plane in the robot base frame
    (REP 103: x forward, y left), laid out like ROS nav_msgs/OccupancyGrid. Cell (row, col) covers
    x in [origin_m[0] + col*res, +res), y in [origin_m[1] + row*res, +res); `cells[row*width + col]`
    is an int8: -1 unknown (not seen), 0 free (seen ground), 100 occupied (an obstacle stands there).
    The grid of a list that is stale or degraded (ObstacleList, same seq) has no free cell: it cannot
    vouch for a clear way."""

    model_config = ConfigDict(extra="forbid", ser_json_bytes="base64", val_json_bytes="base64")

    publish_ns: int = Field(ge=0)
    frame_id: Literal["base"] = "base"
    resolution_m: float = Field(gt=0, le=10, description="cell size, m")
    width: int = Field(gt=0, le=4096, description="cells along base x")
    height: int = Field(gt=0, le=4096, description="cells along base y")
    origin_m: tuple[float, float] = Field(description="base-frame (x, y) of the outer corner of cell (0, 0), m")
    cells: bytes = Field(description="width*height int8, row-major: -1 unknown, 0 free, 100 occupied")
    ground: GroundEstimate | None = None
    mount: CameraMount | None = None


class Odometry(Message):
    """The robot's own motion (wheel odometry, IMU, a recording's poses), base frame at `stamp_ns`.
    Optional input: with it, obstacle velocities are given over the ground."""

    linear_mps: tuple[Speed, Speed, Speed] = Field(description="base-frame linear velocity, m/s (|v| <= 100)")
    angular_radps: tuple[TurnRate, TurnRate, TurnRate] = Field((0.0, 0.0, 0.0), description="base-frame angular "
                                                                 "velocity, rad/s (|w| <= 50)")
    source: str = ""


class TruthObstacle(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str
    kind: str
    center_m: Vec3
    size_m: Vec3
    visible_centroid_m: Vec3
    nearest_m: float
    visible_px: int = Field(ge=0, description="pixels of the obstacle seen in the rectified left image")
    bbox_px: tuple[int, int, int, int] | None = Field(description="None when no pixel is visible")
    velocity_mps: Vec3 = (0.0, 0.0, 0.0)


class GroundTruth(Message):
    """What the synthetic scene knows about the pair with the same seq, in the camera frame."""

    scenario: str
    obstacles: list[TruthObstacle]


class ServiceStats(BaseModel):
    model_config = ConfigDict(extra="forbid")

    schema_version: int = SCHEMA_VERSION
    robot_id: str
    service: str
    role: str = Field("", description="what this instance does within its service (disparity: dispatcher or worker)")
    instance: str
    host: str
    pid: int
    stamp_ns: int
    uptime_s: float
    rate_hz: float = Field(description="outputs published per second, last window")
    proc_ms_p50: float = Field(description="processing time per input, median of last window")
    age_ms_p50: float = Field(description="capture-to-publish age of outputs, median of last window")
    processed: int
    published: int
    drops: int = Field(description="inputs overwritten by a newer one before they were processed")
    decode_errors: int
    errors: int
    status: str = "ok"
    health: Literal["starting", "ok", "degraded", "failed"] = Field(
        "ok", description="progress, not liveness: degraded/failed when input arrives but nothing is "
                          "published, or every input fails (the reason is in status)")
    extra: dict[str, float] = Field(default_factory=dict)
    subscribes: list[str] = Field(default_factory=list, max_length=64, description="the key table's topics this "
                                  "instance subscribes to (recorded by its Node, not declared by hand)")
    publishes: list[str] = Field(default_factory=list, max_length=64, description="the key table's topics this "
                                 "instance publishes on")


class CalibrationUpdate(Message):
    """A new calibration for the rectify service, applied between two frames without a restart.
    `yaml` is the text of a calibration file (see cores/camera.py); a calibration that does not
    load, or whose image size differs from the stream's, is refused and the old one stays."""

    yaml: str = Field(min_length=1, max_length=1_000_000, description="calibration file text (YAML)")
    source: str = Field("", description="where it came from (a path, `calibrate`, a user)")
    signature: str = Field("", max_length=128, description="hex HMAC-SHA256 of robot_id, stamp_ns, source and yaml "
                           "with the robot's calibration key (BALLBOT_CALIBRATION_KEY); empty: unsigned")


class ReplayControl(Message):
    """A command to the capture service while it replays a recording (`--source mcap`): play,
    pause, or step N pairs and pause again; `speed` (optional) changes the playback speed factor.
    `seq` and `stamp_ns` are the sender's own counter and send time."""

    action: Literal["play", "pause", "step"]
    frames: int = Field(1, ge=1, le=100000, description="step: how many pairs to publish before pausing again")
    speed: float | None = Field(None, gt=0, le=1000, description="new playback speed factor (1 = as recorded)")


PUBLIC_MODELS: dict[str, type[BaseModel]] = {
    "ObstacleList": ObstacleList,
    "FreeSpace": FreeSpace,
    "Odometry": Odometry,
    "StereoFrame": StereoFrame,
    "DisparityMap": DisparityMap,
    "GroundTruth": GroundTruth,
    "ServiceStats": ServiceStats,
    "CalibrationUpdate": CalibrationUpdate,
    "ReplayControl": ReplayControl,
}
