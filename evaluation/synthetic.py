"""Score segmentation methods against the synthetic world's ground truth, through the real cores:

    render (synthetic.SyntheticWorld) -> Rectifier -> StereoMatcher -> Segmenter -> Tracker

Each scenario is rendered once (a few frames for a static scene, a sequence for a moving one), its
disparity computed once, and every method runs on the same maps with its own tracker.

Matching: per frame, detections and true obstacles are paired one-to-one (Hungarian) by 3D distance
between the detection's centroid and the centroid of the truth's measurable surface: the surface
points seen by the left image's pixels (as `visible_centroid_m`) restricted to the columns where
block matching has a right-image counterpart (x >= min_disparity + num_disparities + block/2 - 1;
for dense, which pads the pair and matches that band too, x >= d + block/2, d the pixel's true
disparity; this differs from `visible_centroid_m` only for objects cut by the left border) and lower than the
segmenter's robot_height_m above the floor (what stands higher is in no list: SLICE_M), within a gate of
max(gate_m, gate_rel * distance). A true obstacle counts (is expected to be detected) when at least
`min_visible_px` (400) pixels of its measurable surface are visible and it is within `eval_range_m`.
A true obstacle that is only glimpsed (1 .. min_visible_px - 1 measurable pixels, e.g. the last sliver
of a person walking behind a box) is neither expected nor held against the method: a detection of it
is matched after the counted truths and then left out of the detections (not a false positive); one
that is not visible at all (occluded, out of view) expects nothing. Unmatched detections are
classified by what the rendered pixels inside their box are: `floor`, `wall`, or `object` (a piece of
a true obstacle: a split).

A scenario whose camera moves (a driving, swaying robot: `camera_motion` in the scenario) gives the
segmenter the robot's true motion as odometry each frame and the upright mount as its configured
mount (the sway is for the ground estimate to find).

Reported per scenario and method: recall, precision, 3D position error (median, 95th percentile; m
and % of distance), depth error (% , truths 0.5-4 m), errors against the object's box centre and
against `visible_centroid_m`,
floor false positives, id switches (a counted true obstacle matched to a different track id than in
its previous counted, matched frame: across an occlusion, only if the id after reappearance differs
from the id before), mean velocity error (tracks at least `vel_warmup` frames old), and the
mean segmentation time per frame. In the robot base frame (REP 103, on the floor, not tilted by
the sway; the segmenter's from its ground estimate): the error of each matched detection's
`position_base_m` against the truth's measurable centroid taken to the true base frame (median,
95th percentile), and its steadiness: per obstacle standing still in the world and matched in at
least 3 frames, how far each frame's error vector strays from that obstacle's median error vector
(the wobble a swaying camera puts on what stands still; 95th percentile and maximum over all such
sightings). The ground: the share of frames whose ground was fitted in that frame, and the 95th
percentile and maximum of the error of its pitch, roll (deg) and height (m) against the camera's
true mount in that frame.

Free space (the list's FreeSpace grid, base frame): `free under` counts the true obstacles in range
whose ground outline (each part that reaches between STANDS_FROM_M and STANDS_TO_M above the floor,
hidden parts included) has a free cell more than half of which lies FREE_TOLERANCE_M or more inside
it: the grid saying the way is clear where something stands (_free_under). The same ground truth as
the rest, in the true base frame, so a ground estimate's error shows there too.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

import sim as S
from common import codec
from common.files import output_folder, write_image
from common.messages import FrameChecks, GroundEstimate, Odometry
from common.settings import MountSettings
from cores import camera
from cores.matching.matchers import MatcherConfig
from cores.pipeline import Pipeline
from cores.segmentation.builder import ObstacleBuilder
from cores.segmentation.ground import plane_from_mount
from cores.segmentation.mount import Mount
from cores.segmentation.settings import SegmenterSettings

# eval method name -> settings overrides. `seed` is the thesis as written (no floor removal);
# `seed+floor` adds the floor removal from the camera mount; `layers` is the default.
METHODS: dict[str, dict] = {
    "seed": {"method": "seed", "floor_removal": False},
    "seed+floor": {"method": "seed", "floor_removal": True},
    "layers": {"method": "layers"},
}
DEFAULT_METHODS = ["seed", "seed+floor", "layers"]


@dataclass
class EvalFrame:
    t_s: float
    left: np.ndarray  # (H, W) uint8, rectified left image
    disparity: np.ndarray  # (H, W) float32 px, NaN invalid
    truth: list  # synthetic.ObstacleTruth, rectified left frame
    kind: np.ndarray  # (H, W) int8: -3 nothing, -2 wall, -1 floor, >= 0 obstacle index
    measurable: list  # per truth: (centroid (3,) m, pixels) of its surface the matcher can see
    nearest: list = field(default_factory=list)  # per truth: nearest distance (m) of that surface, NaN if none
    T_base_rect: np.ndarray = field(default_factory=lambda: np.eye(4))  # the camera's true pose on the robot
    odometry: tuple[np.ndarray, np.ndarray] | None = None  # (linear, angular) base frame; a moving camera only
    # what else the disparity stage hands the segmenter with the map, as the disparity message carries it
    # (StageResult.handed: the matcher's confidence and flat windows, the search, the vision range gate):
    # taken whole, so what the stage adds reaches the eval as it reaches the segmenter service
    stage_handed: dict = field(default_factory=dict)
    checks: FrameChecks | None = None  # rectify's checks of the pair (the noise, the near field, ...)
    # per truth: the ground outlines ((4, 2) base-frame (x, y), m) of its parts between STANDS_FROM_M and
    # STANDS_TO_M above the floor (SyntheticWorld.footprints): where it stands, which free space must never call free
    stands: list = field(default_factory=list)
    # per truth: that surface in height slices above the floor (SLICE_M): (sums of its points (SLICES, 3),
    # pixels (SLICES,)), the last slice holding all above
    slices: list = field(default_factory=list)

    def measurable_below(self, height_m: float) -> list:
        """measurable, of each truth's surface lower than height_m above the floor: what a robot that
        tall lists of it."""
        k = min(SLICES, int(round(height_m / SLICE_M)))
        if not self.slices or k >= SLICES:
            return self.measurable
        out = []
        for sums, counts in self.slices:
            n = int(counts[:k].sum())
            out.append((sums[:k].sum(0) / n if n else np.full(3, np.nan), n))
        return out

    def handed(self) -> dict:
        """What the services hand the segmenter with the map, as ObstacleBuilder.process takes it."""
        return {**self.stage_handed, "checks": self.checks}

    @property
    def confidence(self) -> np.ndarray | None:
        """The matcher's confidence, (H, W) uint8 (None: it gives none)."""
        return self.stage_handed.get("confidence")

    @property
    def search(self) -> tuple[int, int] | None:
        """(min_disparity, num_disparities) the map's values span."""
        return self.stage_handed.get("search")

    @property
    def gate_px(self) -> float:
        """The matcher's vision range gate (DisparityMap.gate_px; 0: none)."""
        return float(self.stage_handed.get("gate_px", 0.0))

    @property
    def flat(self) -> np.ndarray | None:
        """The matcher's Match.flat (windows too plain to decide their match), if it says."""
        return self.stage_handed.get("flat")

    @property
    def mount(self) -> Mount:
        """The camera's true mount at this frame (height, pitch, roll of the swaying camera)."""
        return mount_from_T(self.T_base_rect)


@dataclass
class ScenarioData:
    name: str
    scene: S.Scene
    model: camera.RectifiedModel
    mount: Mount
    frames: list[EvalFrame]
    render_s: float = 0.0


def mount_from_world(world: S.SyntheticWorld) -> Mount:
    """The exact mount of the rectified left camera on the robot standing upright (the world = base
    frame of a camera that does not move): what a configured mount would say."""
    return mount_from_T(world.T_base_rect_upright())


def mount_from_T(T: np.ndarray) -> Mount:
    """A 4x4 rectified-camera -> base transform as a Mount: position and the yaw/pitch/roll that
    Mount composes (Rz Ry Rx times the optical-to-body axes)."""
    body = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    R = T[:3, :3] @ body.T  # = Rz(yaw) Ry(pitch) Rx(roll)
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    yaw = math.atan2(R[1, 0], R[0, 0])
    roll = math.atan2(R[2, 1], R[2, 2])
    return Mount(float(T[2, 3]), math.degrees(pitch), math.degrees(yaw), math.degrees(roll),
                 float(T[0, 3]), float(T[1, 3]))


# a part reaching into these heights above the floor (m) stands in the way of a robot 2 m tall (the
# segmenter's robot_height_m); a thing lower than 0.1 m is within the floor's noise
STANDS_FROM_M, STANDS_TO_M = 0.1, 2.0
# a truth's measurable surface is kept in slices of this height above the floor, so that it is scored
# on its part a robot of the segmenter's robot_height_m lists (a 0.5 m robot lists a person's legs:
# scored on the whole person, 37 of 45 walking-person sightings were "missed", 0.4 m off)
SLICE_M, SLICES = 0.05, 80
FREE_TOLERANCE_M = 0.05  # half the default 0.1 m cell; see _free_under


def _truth_maps(world: S.SyntheticWorld, t: float, x_valid: int,
                band_margin: int | None = None
                ) -> tuple[np.ndarray, dict[int, tuple[np.ndarray, int, float, tuple[np.ndarray, np.ndarray]]]]:
    """(kind map (H, W) int8: -3 nothing, -2 wall, -1 floor, >= 0 obstacle index;
    {obstacle index: (centroid (3,) m, pixels, nearest distance m, slices)} of the obstacle's surface that
    the matcher can measure: visible in the left image at columns >= x_valid, where block matching
    has a right-image counterpart; with band_margin (a matcher that matches the left band too,
    dense), at columns x >= d + band_margin instead, d its true disparity: where its partner's
    window is in the right image); and seen by the right camera too (visible_in_right: the sliver
    of a crate beside a nearer person that only the left camera sees is no measurable surface)."""
    ids = world.obstacle_ids(t).astype(np.int8)
    depth = world.true_depth(t)
    m = world.rect.model
    h, w = depth.shape
    u = (np.arange(w) - m.cx) / m.focal_px
    v = (np.arange(h) - m.cy) / m.focal_px
    pts = np.stack([np.broadcast_to(u[None, :], (h, w)), np.broadcast_to(v[:, None], (h, w)), np.ones((h, w))], -1)
    pts = pts * depth[..., None]
    T = world.T_world_rect_at(t)
    z_world = pts @ T[2, :3] + T[2, 3]
    kind = np.where(ids >= 0, ids, np.where(np.isfinite(depth), np.where(z_world < 0.02, -1, -2), -3)).astype(np.int8)
    seen = {}
    if band_margin is None:
        cols = np.arange(w)[None, :] >= x_valid
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            cols = np.arange(w)[None, :] >= m.focal_px * m.baseline_m / depth + band_margin
    with np.errstate(divide="ignore", invalid="ignore"):
        cols = cols & visible_in_right(m.focal_px * m.baseline_m / depth)
    for i in range(len(world.scene.boxes)):
        mask = (ids == i) & cols
        n = int(mask.sum())
        p = pts[mask]
        nearest = float(np.sqrt((p * p).sum(1).min())) if n else float("nan")
        sl = np.clip((z_world[mask] / SLICE_M).astype(np.int64), 0, SLICES - 1)
        sums = np.stack([np.bincount(sl, weights=p[:, j], minlength=SLICES) for j in range(3)], -1)
        seen[i] = (p.mean(0) if n else np.full(3, np.nan), n, nearest, (sums, np.bincount(sl, minlength=SLICES)))
    return kind, seen


def visible_in_right(d: np.ndarray, tol_px: float = 1.0) -> np.ndarray:
    """(H, W) bool: which pixels of the left image, at true disparity d (px, 0 at infinity), the right
    camera sees too. On a rectified row a point at column x appears at x - d in the right image;
    it is hidden there when a point to its right in the left image appears at or left of it in the
    right one (that point is nearer: its ray crosses this one's): x - d > min over x' > x of
    x' - d', by more than tol_px."""
    r = np.arange(d.shape[1], dtype=np.float64)[None, :] - np.nan_to_num(d, nan=0.0, posinf=0.0)
    # the smallest right-image column of everything to the right, per row (a suffix minimum)
    right_min = np.minimum.accumulate(r[:, ::-1], axis=1)[:, ::-1]
    after = np.concatenate([right_min[:, 1:], np.full((d.shape[0], 1), np.inf)], axis=1)
    return r <= after + tol_px


def default_sequence(scene: S.Scene) -> tuple[int, float]:
    """(frames, fps): 3 frames of a static scene (sensor noise differs), 3 s at 15 fps of a moving one
    (objects or the camera)."""
    return (3, 15.0) if scene.is_static() else (45, 15.0)


def render_scenario(name: str | S.Scene, frames: int | None = None, fps: float | None = None, seed: int = 0,
                    calibration: str = "lifecam-studio", matcher: MatcherConfig | None = None,
                    match_scale: float = 1.0, wire: tuple[str, int] | None = None) -> ScenarioData:
    """Render `frames` pairs at `fps` (scene time) of a built-in scenario (by name) or a Scene,
    rectify and match them (match_scale 0.5: at half resolution, as the onboard `fallback: half`).
    wire: (encoding, jpeg quality): each pair as capture sends it so (common/codec), decoded."""
    t0 = time.perf_counter()
    scene = name if isinstance(name, S.Scene) else S.Scene.builtin(name)
    rig = camera.load_raw_rig(calibration)  # the world renders through the lenses
    pipe = Pipeline(rig, matcher or MatcherConfig(), match_scale=match_scale)  # rectify and match as the services do
    assert pipe.rectifier.rectification is not None  # a raw rig is rectified
    world = S.SyntheticWorld(scene, rig, pipe.rectifier.rectification, seed=seed)
    n_def, fps_def = default_sequence(scene)
    frames = frames or n_def
    fps = fps or fps_def
    out = []
    built = pipe.matching.matcher(pipe.model.focal_px, pipe.model.baseline_m, pipe.model.width)
    c = built.config
    x_valid = c.min_disparity + c.fixed_num_disparities + c.block // 2 - 1
    band = c.block // 2 if getattr(built, "pad", 0) else None  # dense pads the pair: its band is matched
    static = _truth_maps(world, 0.0, x_valid, band) if scene.is_static() else None
    for k in range(frames):
        t = k / fps
        left, right = world.render(t)
        if wire is not None:
            left, right = (codec.array_from_image(codec.image_from_array(a, *wire)) for a in (left, right))
        m = pipe.front(left, right, t_s=t)  # rectify, with its checks, and match: as the services do
        stage = m.stage
        kind, seen = static if static is not None else _truth_maps(world, t, x_valid, band)
        n = len(scene.boxes)
        out.append(EvalFrame(t, m.left, stage.disparity_px(), world.truth(t), kind, [seen[i][:2] for i in range(n)],
                             [seen[i][2] for i in range(n)], world.T_base_rect(t),
                             world.odometry(t) if scene.camera_moves() else None, stage.handed(), m.checks,
                             stands=world.footprints(t, STANDS_FROM_M, STANDS_TO_M),
                             slices=[seen[i][3] for i in range(n)]))
    return ScenarioData(scene.name, scene, pipe.model, mount_from_world(world), out, time.perf_counter() - t0)


@dataclass
class Score:
    scenario: str
    method: str
    frames: int = 0
    truths: int = 0
    detections: int = 0
    matched: int = 0
    recall: float = float("nan")
    precision: float = float("nan")
    pos_err_med_m: float = float("nan")
    pos_err_p95_m: float = float("nan")
    pos_err_med_pct: float = float("nan")
    pos_err_p95_pct: float = float("nan")
    depth_err_med_pct: float = float("nan")  # truths with 0.5 <= z <= 4 m
    center_err_med_m: float = float("nan")
    visible_err_med_m: float = float("nan")  # against visible_centroid_m, measurable or not
    floor_fp: int = 0
    wall_fp: int = 0
    split_fp: int = 0
    id_switches: int = 0
    # truths missed in a list that named no reason it could not be trusted (degraded empty), at the distances
    # it says it looked at (range_m): the misses a planner takes for a clear way; a miss in a flagged list, or
    # beyond the list's range, was at least said
    silent_misses: int = 0
    flagged_frames: int = 0  # lists with a reason in degraded
    # truths in range whose ground outline (EvalFrame.stands) holds a cell the list's free space calls free,
    # past the tolerance (_free_under): the way said clear where something stands
    free_under: int = 0
    vel_err_mps: float = float("nan")
    seg_ms: float = float("nan")
    base_err_med_m: float = float("nan")  # base frame, against the truth's measurable centroid
    base_err_p95_m: float = float("nan")
    base_wobble_p95_m: float = float("nan")  # static obstacles: spread of the base-frame error over frames
    base_wobble_max_m: float = float("nan")
    ground_fitted: float = float("nan")  # share of frames with a ground fitted in that frame
    ground_pitch_err_p95_deg: float = float("nan")
    ground_pitch_err_max_deg: float = float("nan")
    ground_roll_err_p95_deg: float = float("nan")
    ground_roll_err_max_deg: float = float("nan")
    ground_height_err_p95_m: float = float("nan")
    ground_height_err_max_m: float = float("nan")
    near_err_med_m: float = float("nan")  # distance_m against the nearest measurable point of the truth
    near_err_p95_m: float = float("nan")
    border_truths: int = 0  # matched truths cut by the image's left or right side
    border_flagged: int = 0  # of which the detection says truncated
    border_edge_err_px: float = float("nan")  # median error of the box side away from the border, px
    # name -> {"seen", "matched", "ids", "hidden", "gaps"[, "wobble_p95_m"]}
    per_truth: dict = field(default_factory=dict)
    ground: list = field(default_factory=list)  # per frame: {"frame", "source", "true": (h, p, r), "est": (h, p, r)}
    _pos: list = field(default_factory=list, repr=False)
    _pct: list = field(default_factory=list, repr=False)
    _depth: list = field(default_factory=list, repr=False)
    _center: list = field(default_factory=list, repr=False)
    _visible: list = field(default_factory=list, repr=False)
    _vel: list = field(default_factory=list, repr=False)
    _ms: list = field(default_factory=list, repr=False)
    _base: list = field(default_factory=list, repr=False)
    _wobble: list = field(default_factory=list, repr=False)
    _base_vec: dict = field(default_factory=dict, repr=False)  # static truth name -> [error vector (3,)]
    _near: list = field(default_factory=list, repr=False)
    _edge: list = field(default_factory=list, repr=False)

    def finish(self) -> Score:
        self.recall = self.matched / self.truths if self.truths else float("nan")
        self.precision = (self.matched / self.detections if self.detections
                          else (1.0 if self.truths == 0 else float("nan")))
        med = lambda a: float(np.median(a)) if len(a) else float("nan")  # noqa: E731
        p95 = lambda a: float(np.percentile(a, 95)) if len(a) else float("nan")  # noqa: E731
        self.pos_err_med_m, self.pos_err_p95_m = med(self._pos), p95(self._pos)
        self.pos_err_med_pct, self.pos_err_p95_pct = med(self._pct), p95(self._pct)
        self.depth_err_med_pct = med(self._depth)
        self.center_err_med_m = med(self._center)
        self.visible_err_med_m = med(self._visible)
        self.vel_err_mps = float(np.mean(self._vel)) if self._vel else float("nan")
        self.seg_ms = float(np.mean(self._ms)) if self._ms else float("nan")
        for name, vecs in self._base_vec.items():
            if len(vecs) >= 3:
                e = np.asarray(vecs)
                wobble = np.linalg.norm(e - np.median(e, axis=0), axis=1)
                self._wobble.extend(wobble.tolist())
                if name in self.per_truth:
                    self.per_truth[name]["wobble_p95_m"] = float(np.percentile(wobble, 95))
        self._base_vec = {}
        self.base_err_med_m, self.base_err_p95_m = med(self._base), p95(self._base)
        self.near_err_med_m, self.near_err_p95_m = med(self._near), p95(self._near)
        self.border_edge_err_px = med(self._edge)
        self.base_wobble_p95_m = p95(self._wobble)
        self.base_wobble_max_m = float(np.max(self._wobble)) if self._wobble else float("nan")
        judged = [g for g in self.ground if g["source"] != "none"]
        if self.ground:
            self.ground_fitted = sum(g["source"] == "fitted" for g in self.ground) / len(self.ground)
        if judged:
            err = np.abs(np.array([np.subtract(g["est"], g["true"]) for g in judged]))  # (n, 3): h, p, r
            (self.ground_height_err_p95_m, self.ground_pitch_err_p95_deg,
             self.ground_roll_err_p95_deg) = (float(x) for x in np.percentile(err, 95, axis=0))
            (self.ground_height_err_max_m, self.ground_pitch_err_max_deg,
             self.ground_roll_err_max_deg) = (float(x) for x in err.max(0))
        return self

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if not k.startswith("_") and k != "ground"}

    @classmethod
    def pooled(cls, scores: Iterable[Score], scenario: str = "overall") -> Score:
        scores = list(scores)
        out = cls(scenario, scores[0].method if scores else "")
        for s in scores:
            for k in ("frames", "truths", "detections", "matched", "floor_fp", "wall_fp", "split_fp", "id_switches",
                      "border_truths", "border_flagged", "silent_misses", "flagged_frames", "free_under"):
                setattr(out, k, getattr(out, k) + getattr(s, k))
            for k in ("_pos", "_pct", "_depth", "_center", "_visible", "_vel", "_ms", "_base", "_wobble", "ground",
                      "_near", "_edge"):
                getattr(out, k).extend(getattr(s, k))
        return out.finish()


def _match(obstacles, centroids: list[np.ndarray], gate_m: float, gate_rel: float) -> list[tuple[int, int]]:
    from scipy.optimize import linear_sum_assignment

    if not obstacles or not centroids:
        return []
    P = np.array([o.position_m for o in obstacles])
    C = np.array(centroids)
    D = np.linalg.norm(P[:, None] - C[None], axis=2)
    gate = np.maximum(gate_m, gate_rel * np.linalg.norm(C, axis=1))[None, :]
    cost = np.where(D <= gate, D, 1e6)
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c)) for r, c in zip(rows, cols) if cost[r, c] < 1e6]


class _TrueGround:
    """Stands in for the segmenter's ground estimator when eval is asked for the true ground
    (--true-ground): each frame's floor comes from the camera's true mount in that frame, so the
    figures show what segmentation and tracking do when the ground is right, apart from how well
    the ground is found."""

    tilt_doubt_deg = 0.0  # the true floor is exact: no band for a fit's wobble

    def __init__(self) -> None:
        self.mount: Mount | None = None

    def update(self, dm: np.ndarray, model: camera.RectifiedModel, step: int, wider=None):
        m = self.mount
        if m is None:
            raise RuntimeError("_TrueGround.update before the frame's true mount was set")
        return plane_from_mount(m, model), GroundEstimate(height_m=m.height_m, pitch_deg=m.pitch_deg,
                                                          roll_deg=m.roll_deg, source="fitted", inlier_fraction=1.0,
                                                          confidence=1.0)


def score_method(data: ScenarioData, method: str, overrides: dict | None = None, min_visible_px: int = 400,
                 eval_range_m: float | None = None, gate_m: float = 0.3, gate_rel: float = 0.15,
                 vel_warmup: int = 4, mount_error: dict | None = None, true_ground: bool = False,
                 draw_dir: Path | None = None) -> Score:
    """mount_error: added to the true mount the segmenter is told, e.g. {"pitch_deg": 5,
    "height_m": 0.1} (a balancing robot leans; the floor fit should absorb it). eval_range_m: truths
    nearer than this count (None: the scenario's range_m, which the segmenter then runs with too,
    else 4.5 m). true_ground: the floor each frame is the true one (see _TrueGround). draw_dir: one
    picture per frame there, <scenario>-<method>-<frame>.png: the segmenter's output (draw.draw_frame)
    and the truths it was scored on (draw.draw_truths: matched or missed)."""
    if eval_range_m is None:
        eval_range_m = data.scene.range_m or 4.5
    m = data.mount
    off = {"height_m": 0.0, "pitch_deg": 0.0, "roll_deg": 0.0, **(mount_error or {})}
    cfg = dict(METHODS[method])
    motion = data.scene.camera_motion
    mount = MountSettings(height_m=m.height_m + off["height_m"], pitch_deg=m.pitch_deg + off["pitch_deg"],
                          yaw_deg=m.yaw_deg, roll_deg=m.roll_deg + off["roll_deg"], x_m=m.x_m, y_m=m.y_m,
                          pivot_height_m=None if motion is None else motion.pivot_height_m)
    if data.scene.range_m:
        cfg["max_range_m"] = data.scene.range_m
    cfg.update(overrides or {})
    settings = SegmenterSettings(**cfg)
    builder = ObstacleBuilder(settings, mount)
    oracle = _TrueGround() if true_ground else None
    if oracle is not None:
        builder.ground = oracle  # type: ignore[assignment]
    w = data.model.width
    sc = Score(data.name, method, frames=len(data.frames))
    first_seen: dict[int, int] = {}
    last_id: dict[str, int] = {}
    for k, fr in enumerate(data.frames):
        if oracle is not None:
            oracle.mount = fr.mount
        odo = None
        if fr.odometry is not None:
            odo = Odometry(robot_id="eval", seq=k, stamp_ns=int(fr.t_s * 1e9), linear_mps=_vec3(fr.odometry[0]),
                           angular_radps=_vec3(fr.odometry[1]), source="synthetic")
        t0 = time.perf_counter()
        res = builder.process(fr.disparity, data.model, t_s=fr.t_s, seq=k, stamp_ns=int(fr.t_s * 1e9), image=fr.left,
                              odometry=odo, **fr.handed())
        sc._ms.append((time.perf_counter() - t0) * 1e3)
        obs = res.obstacles.obstacles
        g = res.obstacles.ground
        if g is not None:
            true = fr.mount
            sc.ground.append({"frame": k, "source": g.source, "true": (true.height_m, true.pitch_deg, true.roll_deg),
                              "est": (g.height_m, g.pitch_deg, g.roll_deg)})
        for o in obs:
            first_seen.setdefault(o.id, k)
        measurable = fr.measurable_below(settings.robot_height_m)
        in_range = [i for i, (c, n) in enumerate(measurable) if n > 0 and 0 < c[2] <= eval_range_m]
        keep = [i for i in in_range if measurable[i][1] >= min_visible_px]
        glimpsed = [i for i in in_range if measurable[i][1] < min_visible_px]
        truths = [fr.truth[i] for i in keep]
        centroids = [measurable[i][0] for i in keep]
        pairs = _match(obs, centroids, gate_m, gate_rel)
        # detections of a barely visible truth: neither a hit nor a false positive
        rest = [oi for oi in range(len(obs)) if oi not in {p[0] for p in pairs}]
        ignored = {rest[r] for r, _ in _match([obs[oi] for oi in rest], [measurable[i][0] for i in glimpsed],
                                              gate_m, gate_rel)}
        sc.truths += len(truths)
        sc.detections += len(obs) - len(ignored)
        sc.matched += len(pairs)
        if res.obstacles.degraded:
            sc.flagged_frames += 1
        else:  # only what lies at the distances the list says it looked at (a method's range may end nearer)
            lo, hi = res.obstacles.range_m or (0.0, math.inf)
            found = {ti for _, ti in pairs}
            sc.silent_misses += sum(1 for ti, c in enumerate(centroids) if ti not in found and lo <= c[2] <= hi)
        sc.free_under += _free_under(res.freespace, [fr.stands[i] for i in in_range] if fr.stands else [])
        for i, t in enumerate(fr.truth):
            rec = sc.per_truth.setdefault(t.name, {"seen": 0, "matched": 0, "ids": [], "hidden": 0, "gaps": 0})
            if i in keep:
                rec["seen"] += 1
                if rec.get("_gone"):
                    rec["gaps"] += 1  # counted again after frames without: a reappearance
                rec["_gone"] = False
            else:
                rec["hidden"] += 1  # occluded, out of view or range, or only glimpsed
                rec["_gone"] = rec["seen"] > 0
        matched_obs = set(ignored)
        for oi, ti in pairs:
            o, t = obs[oi], truths[ti]
            matched_obs.add(oi)
            p = np.array(o.position_m)
            c = centroids[ti]
            err = float(np.linalg.norm(p - c))
            sc._visible.append(float(np.linalg.norm(p - np.asarray(t.visible_centroid_m, float))))
            dist = float(np.linalg.norm(c))
            sc._pos.append(err)
            sc._pct.append(100.0 * err / dist)
            if 0.5 <= c[2] <= 4.0:
                sc._depth.append(100.0 * abs(p[2] - c[2]) / c[2])
            sc._center.append(float(np.linalg.norm(p - np.asarray(t.center_m, float))))
            if o.position_base_m is not None:
                e = np.array(o.position_base_m) - (fr.T_base_rect[:3, :3] @ c + fr.T_base_rect[:3, 3])
                sc._base.append(float(np.linalg.norm(e)))
                if t.static:
                    sc._base_vec.setdefault(t.name, []).append(e)
            ti_scene = keep[ti]
            near = fr.nearest[ti_scene] if fr.nearest else float("nan")
            if np.isfinite(near):
                sc._near.append(abs(float(o.distance_m) - near))
            if t.bbox_px is not None and (t.bbox_px[0] == 0 or t.bbox_px[2] == w - 1):
                sc.border_truths += 1
                sc.border_flagged += int(o.truncated)
                # the side of the box away from the border is where the object really ends
                sc._edge.append(abs(o.bbox_px[2] - (t.bbox_px[2] + 1)) if t.bbox_px[0] == 0
                                else abs(o.bbox_px[0] - t.bbox_px[0]))
            rec = sc.per_truth[t.name]
            rec["matched"] += 1
            if t.name in last_id and last_id[t.name] != o.id:
                sc.id_switches += 1
            last_id[t.name] = o.id
            if not rec["ids"] or rec["ids"][-1] != o.id:
                rec["ids"].append(o.id)
            if k - first_seen[o.id] >= vel_warmup:
                sc._vel.append(float(np.linalg.norm(np.array(o.velocity_mps) - np.asarray(t.velocity_mps, float))))
        if draw_dir is not None:
            found = {ti for _, ti in pairs}
            _draw(draw_dir / f"{data.name}-{method}-{k:03d}.png", fr, res, data.model,
                  [(t.name, t.bbox_px, ti in found) for ti, t in enumerate(truths) if t.bbox_px is not None])
        for oi, o in enumerate(obs):
            if oi in matched_obs:
                continue
            x0, y0, x1, y1 = o.bbox_px
            kinds = fr.kind[y0:y1, x0:x1]
            counts = {"floor": int((kinds == -1).sum()), "wall": int((kinds == -2).sum()),
                      "object": int((kinds >= 0).sum())}
            what = max(counts, key=lambda k: counts[k])
            if what == "floor":
                sc.floor_fp += 1
            elif what == "wall":
                sc.wall_fp += 1
            else:
                sc.split_fp += 1
    for rec in sc.per_truth.values():
        rec.pop("_gone", None)
    return sc.finish()


def _free_under(fs, stands: list[list[np.ndarray]]) -> int:
    """How many of these truths (each its parts' ground outlines, EvalFrame.stands) the free space
    grid `fs` (FreeSpace or None) calls free: a free cell more than half of which lies FREE_TOLERANCE_M
    or more inside one of its parts. A cell the outline only crosses holds floor beside it too, and
    floor seen right at a face's foot falls a few centimetres either side of it (stereo noise, the
    ground's fit; 3.7 cm past the low-faces cabinet's plain side): which way such a cell goes is the
    grid's resolution, not a way said clear through the thing."""
    if fs is None:
        return 0
    grid = np.frombuffer(fs.cells, np.int8).reshape(fs.height, fs.width)
    res, origin = fs.resolution_m, np.asarray(fs.origin_m, float)
    sub = (np.arange(4) + 0.5) / 4  # 4 x 4 samples of a cell
    n = 0
    for rects in stands:
        for rect in rects:  # corners in order: two sides from corner 0 along the part's axes
            centre = rect.mean(0)
            axes = np.stack([rect[1] - rect[0], rect[3] - rect[0]])
            length = np.linalg.norm(axes, axis=1)
            half = length / 2 - FREE_TOLERANCE_M  # the part shrunk by the tolerance on every side
            if np.any(half <= 0):
                continue
            c0, r0 = np.maximum(np.floor((rect.min(0) - origin) / res).astype(int), 0)
            c1, r1 = np.minimum(np.floor((rect.max(0) - origin) / res).astype(int), (fs.width - 1, fs.height - 1))
            if c0 > c1 or r0 > r1:
                continue
            rows, cols = np.nonzero(grid[r0:r1 + 1, c0:c1 + 1] == 0)
            if not rows.size:
                continue
            # sample points of every free cell in the part's box, (cells, 16, 2)
            x = origin[0] + (cols[:, None, None] + c0 + sub[None, :, None]) * res
            y = origin[1] + (rows[:, None, None] + r0 + sub[None, None, :]) * res
            pts = np.stack(np.broadcast_arrays(x, y), -1).reshape(rows.size, 16, 2)
            along = np.abs((pts - centre) @ (axes / length[:, None]).T)  # (cells, 16, 2) from the centre
            if np.any(np.all(along <= half, axis=-1).mean(1) > 0.5):
                n += 1
                break
    return n


def _draw(path: Path, fr, res, model: camera.RectifiedModel, truths: list) -> None:
    from cores.segmentation.draw import draw_frame, draw_truths

    write_image(path, draw_truths(draw_frame(fr.left, res.obstacles, model, res.freespace), truths), "--draw")


def default_scenarios() -> list[str]:
    """The shipped scenarios `eval` runs when given none: all but those marked default_eval: false
    (too slow to render for every run; they run by name)."""
    return [n for n in S.list_builtin_scenarios() if S.Scene.builtin(n).default_eval]


def _vec3(v) -> tuple[float, float, float]:
    return tuple(float(x) for x in v)  # type: ignore[return-value]


def evaluate(scenarios: list[str] | None = None, methods: list[str] | None = None, frames: int | None = None,
             fps: float | None = None, seed: int = 0, matcher: MatcherConfig | None = None,
             overrides: dict | None = None, data: dict[str, ScenarioData] | None = None,
             mount_error: dict | None = None, true_ground: bool = False, draw_dir: str | Path | None = None) -> dict:
    """-> {"scenarios": {name: {method: Score}}, "overall": {method: Score}, "render_s": {name: s}}.
    `data` may hold already-rendered scenarios (reused, e.g. by tests). draw_dir: pictures of every
    frame (score_method), the folder made if missing."""
    scenarios = scenarios or default_scenarios()
    methods = methods or DEFAULT_METHODS
    for m in methods:
        if m not in METHODS:
            raise ValueError(f"unknown method {m!r} (known: {', '.join(METHODS)})")
    out = None if draw_dir is None else output_folder(draw_dir, "--draw")
    result: dict = {"scenarios": {}, "overall": {}, "render_s": {}}
    # every scenario and method has a segmenter of its own, and each says its warnings (a search that
    # cannot reach the range): once each is enough
    once, log = _Once(), logging.getLogger("ballbot")
    log.addFilter(once)
    try:
        for name in scenarios:
            d = (data or {}).get(name) or render_scenario(name, frames, fps, seed, matcher=matcher)
            if data is not None:
                data[name] = d
            result["render_s"][name] = d.render_s
            result["scenarios"][name] = {m: score_method(d, m, overrides, mount_error=mount_error,
                                                         true_ground=true_ground, draw_dir=out)
                                         for m in methods}
    finally:
        log.removeFilter(once)
    for m in methods:
        result["overall"][m] = Score.pooled([result["scenarios"][n][m] for n in scenarios])
    return result


class _Once(logging.Filter):
    """Lets each message through once."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if msg in self.seen:
            return False
        self.seen.add(msg)
        return True


COLUMNS = [("recall", "recall", "{:.0%}"), ("precision", "prec", "{:.0%}"), ("pos_err_med_m", "err med m", "{:.3f}"),
           ("pos_err_p95_m", "err p95 m", "{:.3f}"), ("pos_err_med_pct", "err med %", "{:.1f}"),
           ("pos_err_p95_pct", "err p95 %", "{:.1f}"), ("depth_err_med_pct", "depth med %", "{:.1f}"),
           ("center_err_med_m", "vs centre m", "{:.3f}"), ("visible_err_med_m", "vs visib. m", "{:.3f}"),
           ("floor_fp", "floor FP", "{}"), ("wall_fp", "wall FP", "{}"),
           ("split_fp", "split FP", "{}"), ("id_switches", "id sw", "{}"), ("silent_misses", "silent miss", "{}"),
           ("flagged_frames", "flagged", "{}"), ("free_under", "free under", "{}"),
           ("vel_err_mps", "vel err m/s", "{:.2f}"), ("seg_ms", "seg ms", "{:.1f}")]


# the base frame and the ground (the second table)
BASE_COLUMNS = [("base_err_med_m", "base err m", "{:.3f}"), ("base_err_p95_m", "b. err p95", "{:.3f}"),
                ("base_wobble_p95_m", "wobble p95", "{:.3f}"), ("base_wobble_max_m", "wobble max", "{:.3f}"),
                ("ground_fitted", "ground fit", "{:.0%}"), ("ground_pitch_err_p95_deg", "pitch p95", "{:.2f}"),
                ("ground_pitch_err_max_deg", "pitch max", "{:.2f}"), ("ground_roll_err_p95_deg", "roll p95", "{:.2f}"),
                ("ground_roll_err_max_deg", "roll max", "{:.2f}"), ("ground_height_err_p95_m", "height p95", "{:.3f}"),
                ("ground_height_err_max_m", "height max", "{:.3f}"), ("near_err_med_m", "near err m", "{:.3f}"),
                ("near_err_p95_m", "n. err p95", "{:.3f}"), ("border", "border flag", "{}"),
                ("border_edge_err_px", "edge err px", "{:.0f}")]


def format_table(result: dict) -> str:
    rows = [(n, s) for n, by in result["scenarios"].items() for s in by.values()]
    rows += [("overall", s) for s in result["overall"].values()]
    lines: list[str] = []
    for columns, counts in ((COLUMNS, True), (BASE_COLUMNS, False)):
        head = (f"{'scenario':15} {'method':11} " + (f"{'truth':>5} {'det':>5} " if counts else "")
                + " ".join(f"{c[1]:>11}" for c in columns))
        if lines:
            lines += ["", "robot base frame (errors against the truth; wobble: static obstacles' error spread over "
                          "frames), the ground (errors against the true mount of each frame; deg, m), the nearest "
                          "distance, and truths cut by the image side (flagged truncated / all; inner box side)"]
        lines += [head, "-" * len(head)]
        prev = None
        for name, s in rows:
            if prev is not None and name != prev:
                lines.append("")
            prev = name
            cells = []
            for key, _, fmt in columns:
                v = f"{s.border_flagged}/{s.border_truths}" if key == "border" else getattr(s, key)
                cells.append(f"{('-' if isinstance(v, float) and math.isnan(v) else fmt.format(v)):>11}")
            lines.append(f"{name:15} {s.method:11} " + (f"{s.truths:>5} {s.detections:>5} " if counts else "")
                         + " ".join(cells))
    return "\n".join(lines)


def result_to_json(result: dict) -> dict:
    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list):
            return [clean(v) for v in x]
        return x

    return clean({
        "scenarios": {n: {m: s.to_dict() for m, s in by.items()} for n, by in result["scenarios"].items()},
        "overall": {m: s.to_dict() for m, s in result["overall"].items()},
    })
