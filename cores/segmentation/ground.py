"""The ground under the camera, every frame, from the disparity itself, from whatever start.

A flat floor or road is a plane d = a u + b v + c in disparity space. Each frame several candidate
planes are fitted to the (median-filtered, range-gated) working-resolution disparity and the one
the data support best is taken; nothing that came before decides it, so a wrong configured mount
or a lost track costs at most a frame:
- candidates: RANSAC planes (random triples, half of them from nearby rows, where a sparse road
  seen by block matching still gives three points of one surface), the dominant lines of the
  v-disparity histogram (a floor is a line d = s (v - v_horizon) there, however little of it is
  matched), the smoothed estimate of the last frames and the configured mount. Each is refined by
  least squares on the pixels in a band around it, the band narrowed over passes.
- geometry: a candidate must be a floor under the camera: it rises towards the image bottom,
  the camera is 5 cm - 20 m above it, pitched at most MAX_PITCH_DEG and rolled at most
  MAX_ROLL_DEG (a wall, a facade or a ceiling is none of these).
- score: the share of the valid pixels on the plane, minus BELOW_WEIGHT times the share seen
  THROUGH it (farther than the plane along their ray: under the floor). The floor is the lowest
  large plane: a pavement, a car roof, a snow bank or a sloped patch of one object has the road's
  pixels under it and loses; the road has nothing under it.
- time: a candidate that agrees with the smoothed estimate of the last frames gets a small bonus
  (the scene rarely jumps), the configured mount none: a mount is a prior, never a cage. When the
  fitted ground and the configured mount disagree, the data win; this is logged once and both are
  published (GroundEstimate.prior_*).
- prediction: the "tracked" candidate is the last fitted frame's ground carried on at its rate of
  turn (a balancing robot leans by several degrees a frame). With little floor in view (the robot
  close to a table) a fit that is not this expected ground and is trusted less than it (a plane on
  the furniture and the strip of floor at its foot) does not replace it: the expected ground stands in.
Without an acceptable candidate the expected ground stands in for up to `ground_reinit_frames`
frames ("tracked", its confidence halving each frame), then the configured mount ("prior"), then nothing
("none"). GroundEstimate.confidence says how far each frame's ground can be trusted.

With fit_floor false the configured mount is the floor, as the user chose; the ground is still fitted
to check it by, and a mount whose floor lies more than MOUNT_TOLERANCE_M off a trusted fit within the
vision range says so (prior_agrees false, low confidence: the list is degraded "mount-disagrees").
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from common.messages import GroundEstimate
from common.settings import MountSettings
from cores import camera
from cores.segmentation import stats
from cores.segmentation.ground_planes import (
    MAX_HEIGHT_M,
    MAX_ROLL_DEG,
    MIN_HEIGHT_M,
    Pixels,
    in_band,
    ransac_planes,
    similar_disparities,
    vdisparity_planes,
)
from cores.segmentation.mount import FloorPlane, Mount
from cores.segmentation.settings import SegmenterSettings

log = logging.getLogger("ballbot")

MAX_PITCH_DEG = 60.0  # a floor seen more steeply is not one (a wall seen from a camera pitched up)
UNDER_M = 0.25  # a pixel this far below a plane (and BELOW_PX) is seen through it: the plane is no floor
NEAR_PX = 10.0
BELOW_PX = 2.5  # and this much disparity: block matching errs by a pixel or two on a far road
BELOW_WEIGHT = 1.0  # score = support - BELOW_WEIGHT * share of pixels under the plane
MIN_SUPPORT = 0.04  # a floor carries at least this share of the valid pixels ...
MIN_INLIERS = 100  # ... and this many pixels
# A fitted floor this large (pixels of the map: 500 samples of a 640x480 map at downsample 2) is trusted
# for its size; counted in samples, the same road at downsample 4 came to a quarter of it, and the
# street's lists said ground-uncertain in 30 frames of 40
MIN_FLOOR_PX = 8000.0
TRACK_BONUS = 0.05  # score bonus of a candidate agreeing with the last frames
# A real road is not a plane: a plane rolled across it fits its drained sides and a plaza beside it a
# little better than the road itself. Roll away from the last frames' (level without any) costs score.
ROLL_COST = 0.02  # per degree beyond ROLL_FREE_DEG
ROLL_FREE_DEG = 2.0
TRUSTED = 0.3  # below this confidence a list says "ground-uncertain"
MOUNT_CONFIDENCE = 0.5  # of the configured mount where the user chose it over fitting (fit_floor false, seed)
# ... as long as its floor lies within this of the ground the data show (90th percentile over the floor
# in the vision range): more, and things standing that much above the real floor fall under the mount's
# floor margin (or the road a mount puts too low stands up as obstacles)
MOUNT_TOLERANCE_M = 0.1
TILT_RATE = 0.2  # weight of a new fit in the running tilt doubt
MAX_TILT_DOUBT_DEG = 1.0
SEARCH_EVERY = 4  # frames: a full search at least this often (in between, the last frames' ground refined)
# A camera on a balancing robot leans by several degrees a frame, smoothly: its ground is predicted
# from the last two frames' at their rate of turn, which carries on into the frames without a fit,
# slowing by RATE_DECAY a frame (a lean swings back: carried at most twice as far as it went in the
# last frame), and never faster than ground_step_deg a frame.
RATE_DECAY = 0.5
# ... when it turned by more than this a frame: less is within the scatter of fits on a real road
# (MAX_TILT_DOUBT_DEG), a car's camera hardly turns, and its ground is the last frames', smoothed
TURN_MIN_DEG = 1.0
# The floor a fit stands on spans at least this ratio of distances (its 95th to 5th percentile of
# disparity), or its pitch and height trade off against each other along the strip it is seen on.
MIN_FLOOR_SPAN = 1.5


def grid(h: int, w: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution pixel coordinates of a working grid's samples (u: (1, w), v: (h, 1))."""
    return (np.arange(w, dtype=np.float32)[None, :] * step, np.arange(h, dtype=np.float32)[:, None] * step)


_FULL_GRIDS: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}


def _full_grid(h: int, w: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """grid's u and v as (h, w) arrays, made once per shape and step (read only: shared by every frame)."""
    g = _FULL_GRIDS.get((h, w, step))
    if g is None:
        if len(_FULL_GRIDS) >= 8:  # a few models at most in one process
            _FULL_GRIDS.clear()
        uu, vv = grid(h, w, step)
        g = np.broadcast_to(uu, (h, w)).copy(), np.broadcast_to(vv, (h, w)).copy()
        for a in g:
            a.flags.writeable = False
        _FULL_GRIDS[(h, w, step)] = g
    return g


def _within_1(x: float) -> float:
    """np.clip(x, -1, 1) of one number (NaN stays NaN), without numpy's dispatch on a scalar."""
    return -1.0 if x < -1.0 else 1.0 if x > 1.0 else x


def pitch_roll(n_down: np.ndarray) -> tuple[float, float]:
    """(pitch, roll) in degrees of a camera whose floor normal (unit, camera frame, pointing at the
    floor) is n_down; the inverse of mount.Mount.down_camera: n = (sin r cos p, cos r cos p, sin p)."""
    n = np.asarray(n_down, float)
    return float(np.degrees(np.arcsin(_within_1(n[2])))), float(np.degrees(np.arctan2(n[0], n[1])))


def plane_from_mount(mount: Mount, model: camera.RectifiedModel) -> FloorPlane:
    return FloorPlane.from_normal(mount.down_camera, mount.height_m, model.focal_px, model.cx, model.cy,
                                  model.baseline_m)


UPRIGHT_TAU_S = 5.0  # time constant of the upright mount's average: a lean at 0.5 Hz ripples it by 1/16 of itself
UPRIGHT_OFF_DEG = 3.0  # an upright this far from the configured mount's pitch or roll is said, once


class Upright:
    """Where a balancing robot's camera sits when the robot stands upright, from the data. It leans
    all the time, but about upright: the ground's height, pitch and roll averaged over time (an
    exponential average with time constant UPRIGHT_TAU_S, of the frames with a fitted ground) are
    the upright mount's. The average starts at the configured mount (none configured: at the first
    fitted ground) and moves to the data's, so a mount guessed a few degrees off stops placing the
    camera by a wrong lean: 8 deg about a ball 0.15 m up put a camera 0.9 m high 10 cm off over the
    floor, and the free space under what stood there."""

    def __init__(self, configured: Mount | None, tau_s: float = UPRIGHT_TAU_S):
        self.configured, self.tau_s = configured, tau_s
        self.value = None if configured is None else \
            np.array([configured.height_m, configured.pitch_deg, configured.roll_deg], float)
        self._t: float | None = None  # the last fitted frame's time
        self._span_s = 0.0  # the time the data have been averaged over
        self._logged = False

    def update(self, ground: GroundEstimate | None, t_s: float) -> None:
        """One frame's ground estimate at t_s (s, a clock that never goes backwards)."""
        if ground is None or ground.source != "fitted":
            return
        x = np.array([ground.height_m, ground.pitch_deg, ground.roll_deg], float)
        if self.value is None:
            self.value = x
        elif self._t is not None:
            dt = max(0.0, t_s - self._t)
            self.value = self.value + (1.0 - math.exp(-dt / self.tau_s)) * (x - self.value)
            self._span_s += dt
        self._t = t_s
        c = self.configured
        if c is not None and not self._logged and self._span_s >= self.tau_s and \
                max(abs(self.value[1] - c.pitch_deg), abs(self.value[2] - c.roll_deg)) > UPRIGHT_OFF_DEG:
            self._logged = True
            log.warning("segmenter: the robot leans about pitch %+.1f deg, roll %+.1f deg on average, the configured "
                        "mount says %+.1f, %+.1f: the camera is placed by its lean from the average (measure the "
                        "mount, e.g. `ballbot-vision mount estimate --write`)", self.value[1], self.value[2],
                        c.pitch_deg, c.roll_deg)

    def mount(self, configured: MountSettings) -> Mount | None:
        """The upright mount: the average's height, pitch and roll, the configured yaw and offsets
        (None before any estimate)."""
        if self.value is None:
            return None
        h, p, r = (float(v) for v in self.value)
        return Mount(h, p, configured.yaw_deg, r, configured.x_m, configured.y_m)


def frame_mount(ground: GroundEstimate | None, configured: MountSettings,
                upright: Mount | None = None) -> tuple[Mount | None, str]:
    """Where the camera sat on the robot for one frame, and whence: the height, pitch and roll of the
    frame's ground estimate with the configured yaw and offsets (which the ground cannot tell; with a
    pivot_height_m, the offsets the lean about it carries the camera to, the lean measured from
    `upright`, the robot's upright mount: Upright's, else the configured one): "ground"; without an
    estimate, the configured mount: "configured" (None: unknown). The segmenter's base frame comes
    from here and travels with its list (ObstacleList.mount)."""
    if ground is not None and ground.source != "none":
        upright, pivot = upright or Mount.of(configured), configured.pivot_height_m
        if upright is not None and pivot is not None:  # a lean about the pivot moves the camera too
            return upright.leaned(ground.height_m, ground.pitch_deg, ground.roll_deg, pivot), "ground"
        return Mount(ground.height_m, ground.pitch_deg, configured.yaw_deg, ground.roll_deg, configured.x_m,
                     configured.y_m), "ground"
    return Mount.of(configured), "configured"


@dataclass
class Fit:
    plane: FloorPlane
    normal: np.ndarray  # (3,) unit, camera frame, pointing at the floor
    inlier_fraction: float
    below_fraction: float = 0.0  # share of the valid pixels seen through the plane (under the floor)
    score: float = 0.0
    origin: str = ""  # the candidate it came from: ransac, v-disparity, tracked, prior
    floor_px: float = 0.0  # the floor seen on it: its inliers, each standing for spacing^2 pixels of the map

    @property
    def pitch_roll(self) -> tuple[float, float]:
        return pitch_roll(self.normal)


def _refine(p: np.ndarray, px: Pixels, tols: tuple[float, ...] = (0.15, 0.08, 0.04)) -> np.ndarray | None:
    for tol in tols:
        inl = px.band(px.disparity(p), tol)
        if np.count_nonzero(inl) < MIN_INLIERS:
            return None
        p = px.fit(inl)
    return p


def _polish(p: np.ndarray, px: Pixels, iterations: int = 2) -> np.ndarray:
    """The chosen plane settled on its surface: iteratively reweighted least squares with Cauchy
    weights on the residual relative to 3 % of the plane's disparity (0.3 px at least), so that
    starts a little apart on one road end on one plane, frame after frame (band fits stop wherever
    their last band left them, and a base frame that jitters by a few tenths of a degree moves far
    obstacles by decimetres)."""
    for _ in range(iterations):
        pred = px.disparity(p)
        sigma = np.multiply(np.float32(0.03), pred)
        np.maximum(np.float32(0.3), sigma, out=sigma)
        r = np.subtract(px.d, pred)
        r /= sigma
        m = np.abs(r) < 3
        m &= pred > 0
        i = np.flatnonzero(m)
        if i.size < MIN_INLIERS:
            break
        rm = r.take(i)
        p = px.fit(i, 1.0 / (1.0 + rm * rm))
    return p


def _judge(p: np.ndarray, px: Pixels, model: camera.RectifiedModel, origin: str) -> Fit | None:
    """A refined plane -> its Fit (support, pixels under it, score), or None when it is no floor
    under the camera (module doc: geometry)."""
    plane = FloorPlane(float(p[0]), float(p[1]), float(p[2]), 1.0, True, 0)
    n, height = plane.normal_height(model.focal_px, model.cx, model.cy, model.baseline_m)
    pitch, roll = pitch_roll(n)
    if not (MIN_HEIGHT_M <= height <= MAX_HEIGHT_M and n[1] > 0 and abs(pitch) <= MAX_PITCH_DEG
            and abs(roll) <= MAX_ROLL_DEG):
        return None
    pred = px.disparity(p)
    inl = px.band(pred, 0.04)
    k = int(np.count_nonzero(inl))
    if k < MIN_INLIERS:
        return None
    # seen through the plane: farther along the ray than the floor by more than a kerb and matching
    # noise (a real road is not quite a plane: it drains to its sides)
    # (only where the plane's disparity is NEAR_PX or more: farther, matching noise is the plane's height)
    beyond = np.subtract(pred, np.float32(BELOW_PX))
    np.minimum(beyond, pred * np.float32(height / (height + UNDER_M)), out=beyond)
    below = px.d < beyond
    below &= pred >= NEAR_PX
    n_px = px.d.size
    support, under = k / n_px, float(np.count_nonzero(below)) / n_px
    # the floor is under the robot, on both sides of its heading: a surface seen only to one side (a
    # plaza draining away beside the road, a pavement) is worth less than one that spans the view
    left = int(np.count_nonzero(inl & px.left(model.cx)))
    balance = min(left, k - left) / max(1, max(left, k - left))
    return Fit(FloorPlane(plane.a, plane.b, plane.c, height, True, k), n, support, under,
               support * (0.5 + 0.5 * balance) - BELOW_WEIGHT * under, origin, k * px.spacing ** 2)


def _pixels(dm: np.ndarray, step: int) -> Pixels:
    s = 2  # every other working pixel is plenty for three parameters
    sub = dm[::s, ::s]
    h, w = sub.shape
    uu, vv = _full_grid(h, w, step * s)
    i = np.flatnonzero(sub > 0)  # (by index: faster than three masks)
    return Pixels(uu.take(i), vv.take(i), sub.take(i), spacing=step * s)


def fit_candidates(dm: np.ndarray, model: camera.RectifiedModel, step: int, guesses: dict[str, FloorPlane],
                   rng: np.random.Generator) -> list[Fit]:
    """Every acceptable floor candidate of a working-resolution disparity map dm (0 = invalid), best
    score first: from the guesses (name -> plane), RANSAC and the v-disparity histogram."""
    return _candidates(_pixels(dm, step), model, guesses, rng)


def _candidates(px: Pixels, model: camera.RectifiedModel, guesses: dict[str, FloorPlane], rng: np.random.Generator,
                search: bool = True) -> list[Fit]:
    """fit_candidates on the pixels px; search False: from the guesses alone."""
    u, v, d = px.u, px.v, px.d
    if d.size < MIN_INLIERS:
        return []
    starts: list[tuple[str, np.ndarray]] = [(name, np.array([g.a, g.b, g.c])) for name, g in guesses.items()]
    if search:
        starts += [("ransac", p) for p in ransac_planes(u, v, d, rng)]
        starts += [("v-disparity", p) for p in vdisparity_planes(u, v, d, model, rng)]
    fits: list[Fit] = []
    refined: list[np.ndarray] = []  # the refined planes' disparities on the pixels telling planes apart
    uc, vc = u[::max(1, u.size // 256)], v[::max(1, v.size // 256)]
    for origin, p0 in starts:
        if refined:
            dp = p0[0] * uc + p0[1] * vc + p0[2]
            if any(similar_disparities(dp, q) for q in refined):
                continue  # it would refine to a plane already judged
        p = _refine(p0, px)
        if p is None:
            continue
        dp = p[0] * uc + p[1] * vc + p[2]
        if any(similar_disparities(dp, q) for q in refined):
            continue
        refined.append(dp)
        fit = _judge(p, px, model, origin)
        if fit is not None:
            fits.append(fit)
    fits.sort(key=lambda f: -f.score)
    return fits


def fit_plane(dm: np.ndarray, model: camera.RectifiedModel, step: int, guess: FloorPlane | None,
              rng: np.random.Generator) -> Fit | None:
    """The best floor candidate of dm (see fit_candidates), with `guess` as one more start."""
    fits = fit_candidates(dm, model, step, {} if guess is None else {"guess": guess}, rng)
    return fits[0] if fits else None


def _close(n: np.ndarray, h: float, n0: np.ndarray, h0: float, tilt_deg: float, rel_h: float = 0.3) -> bool:
    tilt = np.degrees(np.arccos(_within_1(float(n @ n0))))
    return bool(tilt <= tilt_deg and abs(h - h0) <= rel_h * h0)


def floor_span(fit: Fit, px: Pixels) -> float:
    """How many times farther the far end of the fit's floor is than its near end (95th and 5th
    percentile of its pixels' disparity; every 4th pixel tells them)."""
    d = px.d[::4]
    d = d[in_band(d, fit.plane.disparity(px.u[::4], px.v[::4]), 0.04)]
    if d.size == 0:
        return 1.0
    lo, hi = stats.percentile(d, [5, 95])
    return float(hi) / max(float(lo), 1e-6)


def fit_confidence(fit: Fit, consistent: bool) -> float:
    """How far one frame's fitted ground can be trusted, 0..1: its support (a third of the valid
    pixels on it is plenty), the pixels seen through it (15 % make it worthless), its size in pixels
    and whether it agrees with the last frames."""
    support = min(1.0, fit.inlier_fraction / 0.3)
    under = max(0.0, 1.0 - fit.below_fraction / 0.15)
    size = min(1.0, fit.floor_px / MIN_FLOOR_PX)
    return float(support * under * size * (1.0 if consistent else 0.7))


class GroundEstimator:
    """update(dm) -> (the floor plane for this frame or None, the GroundEstimate to publish)."""

    def __init__(self, cfg: SegmenterSettings, prior: Mount | None = None):
        """prior: the configured mount (a first guess among the candidates, never a cage)."""
        self.cfg = cfg
        self.prior = prior
        self.smooth_n: np.ndarray | None = None  # smoothed normal and height of the last frames
        self.smooth_h = 0.0
        self.confidence = 0.0  # of the smoothed estimate
        self.missed = 0  # frames in a row without an acceptable fit
        self.since_search = 0  # frames since every candidate last competed
        self.tilt_var = 0.0  # running mean square (deg^2) of each fit's tilt from the last frames' ground
        self.last_n: np.ndarray | None = None  # the last fitted frame's ground (normal, height) ...
        self.last_h = 0.0
        self.rate_n = np.zeros(3)  # ... and its change a frame (from the frame before it; 0 without one)
        self.rate_h = 0.0
        self.prior_disagreement_logged = False
        self.mount_disagreed = False  # fit_floor false: the last check of the mount found it off
        self.rng = np.random.default_rng(0)

    @property
    def tilt_doubt_deg(self) -> float:
        """How far this frame's fitted tilt may be off: the rms of the fits' tilts from the last
        frames' ground (a fit on a real road moves by a few tenths of a degree; an exact plane by
        hardly any), at most MAX_TILT_DOUBT_DEG. The segmenter widens its floor band by it at a distance."""
        if not self.cfg.fit_floor:
            return 0.0  # the floor is the configured mount's, which does not wobble
        return float(min(MAX_TILT_DOUBT_DEG, np.sqrt(self.tilt_var)))

    def predicted(self) -> tuple[np.ndarray, float] | None:
        """The ground expected in this frame: the last fitted frame's, carried on at its rate of turn
        (and of rise) for the frames since (module constants: RATE_DECAY, TURN_MIN_DEG); None
        without a fit."""
        if self.last_n is None:
            return None
        if self.smooth_n is not None and float(np.degrees(np.linalg.norm(self.rate_n))) <= TURN_MIN_DEG:
            return self.smooth_n, self.smooth_h  # no turn to speak of: the last frames' ground, smoothed
        k = sum(RATE_DECAY ** i for i in range(self.missed + 1))
        n = self.last_n + k * self.rate_n
        return n / np.linalg.norm(n), max(MIN_HEIGHT_M, self.last_h + k * self.rate_h)

    def _remember(self, n: np.ndarray, h: float, follows: bool) -> None:
        """A frame's fitted ground (normal, height); follows: it is the ground of the frame right after
        the last fitted one, and agrees with it (else the rate of turn is not known: 0)."""
        if follows and self.last_n is not None:
            step = float(np.degrees(np.arccos(_within_1(n @ self.last_n))))
            scale = min(1.0, self.cfg.ground_step_deg / step) if step > 0 else 1.0
            self.rate_n, self.rate_h = scale * (n - self.last_n), scale * (h - self.last_h)
        else:
            self.rate_n, self.rate_h = np.zeros(3), 0.0
        self.last_n, self.last_h = n.copy(), float(h)

    def _plane(self, n: np.ndarray, h: float, model: camera.RectifiedModel) -> FloorPlane:
        return FloorPlane.from_normal(n, h, model.focal_px, model.cx, model.cy, model.baseline_m)

    def _estimate(self, n: np.ndarray, h: float, source: str, inliers: float = 0.0, confidence: float = 0.0,
                  agrees: bool | None = None) -> GroundEstimate:
        pitch, roll = pitch_roll(n)
        p = self.prior
        return GroundEstimate(height_m=float(h), pitch_deg=pitch, roll_deg=roll, source=source,
                              inlier_fraction=float(min(1.0, max(0.0, inliers))),
                              confidence=float(min(1.0, max(0.0, confidence))),
                              prior_height_m=None if p is None else p.height_m,
                              prior_pitch_deg=None if p is None else p.pitch_deg,
                              prior_roll_deg=None if p is None else p.roll_deg, prior_agrees=agrees)

    def _none(self) -> GroundEstimate:
        return self._estimate(np.array([0.0, 1.0, 0.0]), 0.0, "none")

    def update(self, dm: np.ndarray, model: camera.RectifiedModel,
               step: int) -> tuple[FloorPlane | None, GroundEstimate]:
        """dm: the working-resolution disparity where the floor is looked for (0 = invalid): the
        vision range, or out to where the rig still measures when that is farther (layers.py)."""
        prior = self.prior
        if self.cfg.fit_floor:
            return self._fit(_pixels(dm, step), model)
        if prior is None:
            return None, self._none()
        # The user chose the configured mount over fitting: it is the floor, as configured. The ground
        # is still fitted, only to check the mount by: a mount a few degrees off hides what stands low
        # (or turns the road into obstacles) at a distance, and a list must not look trustworthy then.
        px = _pixels(dm, step)
        self._fit(px, model)
        plane = plane_from_mount(prior, model)
        off = self._mount_offset(plane, px, model)
        # once off, back only well within the tolerance: a mount right at its edge does not flicker
        agrees = None if off is None else off <= MOUNT_TOLERANCE_M * (0.75 if self.mount_disagreed else 1.0)
        if agrees is not None:
            self.mount_disagreed = not agrees
        if agrees is False and not self.prior_disagreement_logged and self.smooth_n is not None:
            self.prior_disagreement_logged = True
            pitch, roll = pitch_roll(self.smooth_n)
            log.warning("segmenter: the configured mount (camera %.2f m high, pitch %+.1f deg, roll %+.1f deg) puts "
                        "the floor %.2f m off the floor in the disparity (camera %.2f m above it, pitch %+.1f deg, "
                        "roll %+.1f deg) within the vision range; fit_floor is false, so the mount is used and "
                        "every such list says mount-disagrees (measure the mount again, e.g. `ballbot-vision mount "
                        "estimate --write`, or set fit_floor true)",
                        prior.height_m, prior.pitch_deg, prior.roll_deg, off, self.smooth_h, pitch, roll)
        return plane, self._estimate(prior.down_camera, prior.height_m, "prior",
                                     confidence=MOUNT_CONFIDENCE if agrees is not False else 0.1, agrees=agrees)

    def _mount_offset(self, plane: FloorPlane, px: Pixels, model: camera.RectifiedModel) -> float | None:
        """How far the configured mount's floor `plane` lies from the trusted ground of the last
        frames, m: the 90th percentile, over this frame's pixels on that ground within the vision
        range, of the height of the ground there above (or below) the mount's floor. None when there
        is no trusted ground to tell (the mount then stands unchecked)."""
        if self.smooth_n is None or self.missed > 0 or self.confidence < TRUSTED:
            return None
        fitted = self._plane(self.smooth_n, self.smooth_h, model)
        d_fit = fitted.disparity(px.u, px.v)
        on = px.band(d_fit, 0.04)
        on &= d_fit >= np.float32(model.focal_px * model.baseline_m / self.cfg.range_for(model))
        i = np.flatnonzero(on)
        if i.size < MIN_INLIERS:
            return None
        d_mount = plane.disparity(px.u.take(i), px.v.take(i))
        above = plane.height_m * (1.0 - d_mount / d_fit.take(i))
        return float(stats.percentile(np.abs(above), 90))

    def _fit(self, px: Pixels, model: camera.RectifiedModel) -> tuple[FloorPlane | None, GroundEstimate]:
        """This frame's ground fitted to the pixels px (module doc)."""
        cfg = self.cfg
        prior = self.prior
        guesses = {}
        expected = self.predicted() if self.smooth_n is not None else None
        if expected is not None:
            guesses["tracked"] = self._plane(*expected, model)
        ref_roll = pitch_roll(self.smooth_n)[1] if self.smooth_n is not None else 0.0

        def agrees(f: Fit) -> bool:
            return self.smooth_n is not None and _close(f.normal, f.plane.height_m, self.smooth_n, self.smooth_h,
                                                        cfg.ground_step_deg, 0.15)

        def closeness(f: Fit) -> float:
            """1 for the ground expected from the last frames, falling to 0 at ground_step_deg or 15 %
            of the height away."""
            if expected is None:
                return 0.0
            tilt = float(np.degrees(np.arccos(_within_1(f.normal @ expected[0]))))
            dh = abs(f.plane.height_m - expected[1]) / max(expected[1], 1e-3)
            return max(0.0, 1.0 - tilt / max(cfg.ground_step_deg, 1e-3)) * max(0.0, 1.0 - dh / 0.15)

        def rank(f: Fit) -> float:
            roll = abs(f.pitch_roll[1] - ref_roll)
            return f.score - ROLL_COST * max(0.0, roll - ROLL_FREE_DEG) + TRACK_BONUS * closeness(f)

        def choose(px: Pixels, quick: bool) -> tuple[Fit | None, bool | None]:
            """The frame's ground among the candidates on px (and whether it agrees with the last
            frames'); quick: from the expected ground alone, if that stays a trusted floor."""
            fits: list[Fit] = []
            if quick:
                fits = _candidates(px, model, guesses, self.rng, search=False)
                if not (fits and closeness(fits[0]) > 0 and fits[0].inlier_fraction >= MIN_SUPPORT
                        and fit_confidence(fits[0], True) >= TRUSTED):
                    fits = []
            if not fits:
                self.since_search = 0
                if self.prior is not None:
                    guesses["prior"] = plane_from_mount(self.prior, model)
                fits = _candidates(px, model, guesses, self.rng)
            fits.sort(key=lambda f: -rank(f))
            consistent = agrees(fits[0]) if fits and self.smooth_n is not None else None
            fit = fits[0] if fits and fits[0].inlier_fraction >= MIN_SUPPORT else None
            if fit is not None:
                polished = _judge(_polish(np.array([fit.plane.a, fit.plane.b, fit.plane.c]), px), px, model,
                                  fit.origin)
                if polished is not None:
                    fit = polished
            if fit is not None and expected is not None and self.missed < self.cfg.ground_reinit_frames:
                # little floor in view (the robot close to a table): a fit that is not the ground the last
                # frames expect (a plane on the furniture, on a strip of floor and the furniture's foot)
                # does not replace that ground while that is trusted more (its trust halving with each
                # frame it stands in: a fit that is right wins within a frame or two)
                if closeness(fit) <= 0 and fit_confidence(fit, False) < self.confidence * 0.5 ** (self.missed + 1):
                    fit = None
            return fit, consistent

        # Between full searches the last frames' ground, refined on this frame, is enough while it
        # stays a trusted floor close to them; every SEARCH_EVERY frames (and whenever it is not)
        # every candidate competes, so a wrong lock lasts a few frames at most.
        self.since_search += 1
        fit, consistent = choose(px, bool(guesses) and self.since_search < SEARCH_EVERY)
        span = floor_span(fit, px) if fit is not None else 0.0
        if fit is not None:
            self._remember(fit.normal, fit.plane.height_m, self.missed == 0 and consistent is True)
            self.missed = 0
            if consistent:
                tilt = float(np.degrees(np.arccos(_within_1(fit.normal @ self.smooth_n))))
                self.tilt_var = (1 - TILT_RATE) * self.tilt_var + TILT_RATE * tilt * tilt
            a = cfg.ground_smoothing
            if self.smooth_n is None or not consistent:
                self.smooth_n, self.smooth_h = fit.normal.copy(), fit.plane.height_m  # the world changed
            else:
                n = (1 - a) * self.smooth_n + a * fit.normal
                self.smooth_n = n / np.linalg.norm(n)
                self.smooth_h = (1 - a) * self.smooth_h + a * fit.plane.height_m
            # a floor seen over too short a stretch (and nothing beyond it) may be tilted far off: trusted
            # less the shorter it is
            conf = fit_confidence(fit, consistent is not False) * min(1.0, (span - 1.0) / (MIN_FLOOR_SPAN - 1.0))
            self.confidence = conf
            agrees_prior = None
            if prior is not None and cfg.fit_floor:
                agrees_prior = _close(fit.normal, fit.plane.height_m, prior.down_camera, prior.height_m,
                                      cfg.max_tilt_deg)
                if not agrees_prior and not self.prior_disagreement_logged and conf >= TRUSTED:
                    self.prior_disagreement_logged = True
                    pitch, roll = fit.pitch_roll
                    log.warning("segmenter: the ground in the disparity (camera %.2f m above it, pitch %+.1f deg, "
                                "roll %+.1f deg) disagrees with the configured mount (%.2f m, %+.1f deg, %+.1f deg): "
                                "using the data; both are published with each list (GroundEstimate.prior_*)",
                                fit.plane.height_m, pitch, roll, prior.height_m, prior.pitch_deg, prior.roll_deg)
            return fit.plane, self._estimate(fit.normal, fit.plane.height_m, "fitted", fit.inlier_fraction, conf,
                                             agrees_prior)
        self.missed += 1
        if expected is not None and self.missed <= cfg.ground_reinit_frames:
            conf = self.confidence * 0.5 ** self.missed  # a robot that sways moves its ground every frame
            return self._plane(*expected, model), self._estimate(*expected, "tracked", confidence=conf)
        self.smooth_n = self.last_n = None
        if prior is not None:
            return plane_from_mount(prior, model), self._estimate(prior.down_camera, prior.height_m, "prior",
                                                                  confidence=0.1)
        return None, self._none()
