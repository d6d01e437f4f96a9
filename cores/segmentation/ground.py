"""The ground under the camera, every frame, from the disparity itself.

A flat floor or road is a plane d = a u + b v + c in disparity space. Each frame it is fitted to the
(median-filtered, range-gated) working-resolution disparity: least squares on the pixels in a band
around a first guess, the band narrowed over passes. The first guess is, in order: the smoothed
estimate of the last frames (a swaying robot's ground moves a little from frame to frame), the
configured camera mount, or, with neither, RANSAC on the lower half of the image. A fit is used
when it is plausible (the plane lies below the camera, within max_pitch/max_roll, at a height
between 5 cm and 20 m) and close to the guess (max_tilt_deg, 30 % height); otherwise the smoothed
estimate stands in ("tracked"), then the mount ("prior"). A fit that disagrees with the smoothed
estimate for `reinit_frames` frames in a row restarts it (the robot drove onto another floor).

The smoothed estimate exists for the fallback and the next guess; each frame removes the floor it
fitted itself, so a pitch change of a few degrees from one frame to the next is followed at once.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cores import camera
from common.messages import GroundEstimate
from cores.segmentation.mount import FloorPlane, Mount
from cores.segmentation.settings import MountSettings, SegmenterSettings

MIN_HEIGHT_M, MAX_HEIGHT_M = 0.05, 20.0
MAX_PITCH_DEG, MAX_ROLL_DEG = 75.0, 40.0
RANSAC_MAX_ROLL_DEG = 12.0  # a first guess without a prior: a camera rolled more is implausible


def grid(h: int, w: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution pixel coordinates of a working grid's samples (u: (1, w), v: (h, 1))."""
    return (np.arange(w, dtype=np.float32)[None, :] * step, np.arange(h, dtype=np.float32)[:, None] * step)


def pitch_roll(n_down: np.ndarray) -> tuple[float, float]:
    """(pitch, roll) in degrees of a camera whose floor normal (unit, camera frame, pointing at the
    floor) is n_down; the inverse of mount.Mount.down_camera: n = (sin r cos p, cos r cos p, sin p)."""
    n = np.asarray(n_down, float)
    return float(np.degrees(np.arcsin(np.clip(n[2], -1, 1)))), float(np.degrees(np.arctan2(n[0], n[1])))


def plane_from_mount(mount: Mount, model: camera.RectifiedModel) -> FloorPlane:
    return FloorPlane.from_normal(mount.down_camera, mount.height_m, model.focal_px, model.cx, model.cy,
                                  model.baseline_m)


def frame_mount(ground: GroundEstimate | None, settings: MountSettings) -> Mount | None:
    """Where the camera sat on the robot for one frame: the height, pitch and roll of the frame's
    ground estimate with the configured yaw and offsets (which the ground cannot tell); without an
    estimate, the configured mount (None: unknown). The segmenter's base frame, the pictures' and
    the ROS 2 bridge's /tf_static all come from here."""
    if ground is not None and ground.source != "none":
        return Mount(ground.height_m, ground.pitch_deg, settings.mount_yaw_deg, ground.roll_deg, settings.mount_x_m,
                     settings.mount_y_m)
    return settings.mount()


def ransac_plane(u: np.ndarray, v: np.ndarray, d: np.ndarray, rng: np.random.Generator,
                 n_hyp: int = 96) -> np.ndarray | None:
    """Floor candidate without a guess: the plane d = a u + b v + c with most points within 1 px
    (5 %), among planes that rise downwards and are rolled at most RANSAC_MAX_ROLL_DEG."""
    if d.size < 50:
        return None
    idx = rng.integers(0, d.size, size=(n_hyp, 3))
    A = np.stack([u[idx], v[idx], np.ones((n_hyp, 3), np.float32)], -1)
    ok = np.abs(np.linalg.det(A)) > 1e-3
    if not ok.any():
        return None
    planes = np.linalg.solve(A[ok], d[idx][ok][..., None])[..., 0]  # (k, 3)
    # rising downwards (b > 0), and not rolled more than a robot's camera plausibly is: the normal's
    # x / y components are a : b, so the roll is atan2(a, b)
    planes = planes[(planes[:, 1] > 1e-3) & (np.abs(planes[:, 0]) <= np.tan(np.radians(RANSAC_MAX_ROLL_DEG)) * planes[:, 1])]
    if not len(planes):
        return None
    res = np.abs(planes[:, 0:1] * u[None] + planes[:, 1:2] * v[None] + planes[:, 2:3] - d[None])
    score = (res < np.maximum(1.0, 0.05 * d[None])).sum(1)
    return planes[int(score.argmax())]


def lstsq_plane(u: np.ndarray, v: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Least-squares (a, b, c) of d = a u + b v + c, by the 3x3 normal equations (centred)."""
    u = u.astype(np.float64)
    v = v.astype(np.float64)
    d = d.astype(np.float64)
    mu, mv, md = u.mean(), v.mean(), d.mean()
    u -= mu
    v -= mv
    d -= md
    A = np.array([[u @ u, u @ v], [u @ v, v @ v]])
    a, b = np.linalg.solve(A + 1e-9 * np.eye(2), np.array([u @ d, v @ d]))
    return np.array([a, b, md - a * mu - b * mv])


@dataclass
class Fit:
    plane: FloorPlane
    normal: np.ndarray  # (3,) unit, camera frame, pointing at the floor
    inlier_fraction: float


def fit_plane(dm: np.ndarray, model: camera.RectifiedModel, step: int, guess: FloorPlane | None,
              rng: np.random.Generator) -> Fit | None:
    """The floor plane fitted to a working-resolution disparity map dm (0 = invalid), starting from
    `guess` (None: RANSAC on the lower half). None when no plausible plane is found."""
    s = 2  # every other working pixel is plenty for three parameters
    sub = dm[::s, ::s]
    uu, vv = grid(*sub.shape, step * s)
    valid = sub > 0
    u = np.broadcast_to(uu, sub.shape)[valid]
    v = np.broadcast_to(vv, sub.shape)[valid]
    dv = sub[valid]
    if dv.size < 100:
        return None
    if guess is not None:
        p = np.array([guess.a, guess.b, guess.c])
        tols = (0.25, 0.12, 0.06)
    else:
        low = v > model.cy
        p = ransac_plane(u[low], v[low], dv[low], rng)
        if p is None:
            return None
        tols = (0.05, 0.04, 0.04)
    inl = np.zeros(0, bool)
    for tol in tols:
        pred = p[0] * u + p[1] * v + p[2]
        inl = (pred > 0) & (np.abs(dv - pred) <= np.maximum(0.6, tol * pred))
        if inl.sum() < 100:
            return None
        p = lstsq_plane(u[inl], v[inl], dv[inl])
    plane = FloorPlane(float(p[0]), float(p[1]), float(p[2]), 1.0, True, int(inl.sum()))
    n, height = plane.normal_height(model.focal_px, model.cx, model.cy, model.baseline_m)
    pitch, roll = pitch_roll(n)
    max_roll = MAX_ROLL_DEG if guess is not None else RANSAC_MAX_ROLL_DEG + 3.0
    if not (MIN_HEIGHT_M <= height <= MAX_HEIGHT_M and n[1] > 0 and abs(pitch) <= MAX_PITCH_DEG
            and abs(roll) <= max_roll):
        return None
    return Fit(FloorPlane(plane.a, plane.b, plane.c, height, True, plane.inliers), n, float(inl.sum()) / dv.size)


def _close(n: np.ndarray, h: float, n0: np.ndarray, h0: float, tilt_deg: float) -> bool:
    tilt = np.degrees(np.arccos(np.clip(float(n @ n0), -1, 1)))
    return bool(tilt <= tilt_deg and abs(h - h0) <= 0.3 * h0)


class GroundEstimator:
    """update(dm) -> (the floor plane for this frame or None, the GroundEstimate to publish)."""

    def __init__(self, cfg: SegmenterSettings):
        self.cfg = cfg
        self.prior = cfg.mount()
        self.smooth_n: np.ndarray | None = None  # smoothed normal and height of the last frames
        self.smooth_h = 0.0
        self.disagree = 0
        self.rng = np.random.default_rng(0)

    def _plane(self, n: np.ndarray, h: float, model: camera.RectifiedModel) -> FloorPlane:
        return FloorPlane.from_normal(n, h, model.focal_px, model.cx, model.cy, model.baseline_m)

    def _estimate(self, n: np.ndarray, h: float, source: str, inliers: float = 0.0) -> GroundEstimate:
        pitch, roll = pitch_roll(n)
        return GroundEstimate(height_m=float(h), pitch_deg=pitch, roll_deg=roll, source=source,
                              inlier_fraction=float(min(1.0, max(0.0, inliers))))

    def update(self, dm: np.ndarray, model: camera.RectifiedModel, step: int) -> tuple[FloorPlane | None, GroundEstimate]:
        cfg = self.cfg
        prior_n = prior_h = None
        if self.prior is not None:
            prior_n, prior_h = self.prior.down_camera, self.prior.height_m
        if not cfg.fit_floor:
            if self.prior is None:
                return None, GroundEstimate(height_m=0.0, pitch_deg=0.0, roll_deg=0.0, source="none")
            return plane_from_mount(self.prior, model), self._estimate(prior_n, prior_h, "prior")
        if self.smooth_n is not None:
            guess = self._plane(self.smooth_n, self.smooth_h, model)
        elif self.prior is not None:
            guess = plane_from_mount(self.prior, model)
        else:
            guess = None
        fit = fit_plane(dm, model, step, guess, self.rng)
        if fit is None and self.smooth_n is not None and self.disagree + 1 >= cfg.ground_reinit_frames:
            fit = fit_plane(dm, model, step, None, self.rng)  # lost it: look again without the guess
        ok = fit is not None
        if ok and prior_n is not None:
            ok = _close(fit.normal, fit.plane.height_m, prior_n, prior_h, cfg.max_tilt_deg)
        if ok and self.smooth_n is not None and not _close(fit.normal, fit.plane.height_m, self.smooth_n,
                                                           self.smooth_h, cfg.ground_step_deg):
            ok = self.disagree + 1 >= cfg.ground_reinit_frames
            if ok:
                self.smooth_n = None  # the world changed: restart from this fit
        if ok:
            self.disagree = 0
            a = cfg.ground_smoothing
            if self.smooth_n is None:
                self.smooth_n, self.smooth_h = fit.normal.copy(), fit.plane.height_m
            else:
                n = (1 - a) * self.smooth_n + a * fit.normal
                self.smooth_n = n / np.linalg.norm(n)
                self.smooth_h = (1 - a) * self.smooth_h + a * fit.plane.height_m
            return fit.plane, self._estimate(fit.normal, fit.plane.height_m, "fitted", fit.inlier_fraction)
        self.disagree += 1
        if self.smooth_n is not None:
            return self._plane(self.smooth_n, self.smooth_h, model), self._estimate(self.smooth_n, self.smooth_h,
                                                                                    "tracked")
        if self.prior is not None:
            return plane_from_mount(self.prior, model), self._estimate(prior_n, prior_h, "prior")
        return None, GroundEstimate(height_m=0.0, pitch_deg=0.0, roll_deg=0.0, source="none")
