"""The judge of `eval --real`: a model of the road independent of the segmenter's ground fit (a
line in v-disparity per frame), and the height of an obstacle's pixels above it. An obstacle with
nothing higher than FLAT_HEIGHT_M above this road is flat: a segmenter that boxes the road cannot
hide it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cores import camera


@dataclass(frozen=True)
class RoadProfile:
    """The road in v-disparity: d = slope * (v - horizon_v) on the rectified left image (a flat road
    without roll seen by a camera pitched by theta: slope = B cos(theta) / h, horizon_v = cy - f tan(theta)).
    Independent of the segmenter's ground fit: a robust line in the lower image's d-vs-v histogram."""

    slope: float  # px of disparity per image row
    horizon_v: float  # row, px
    support: float  # share of the lower image's valid pixels on the line
    focal_px: float
    cy: float
    baseline_m: float

    @property
    def pitch_deg(self) -> float:
        return math.degrees(math.atan2(self.cy - self.horizon_v, self.focal_px))

    @property
    def height_m(self) -> float:
        return self.baseline_m * math.cos(math.radians(self.pitch_deg)) / self.slope

    def road_row(self, d: np.ndarray) -> np.ndarray:
        return self.horizon_v + np.asarray(d) / self.slope

    def height_above(self, v: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Height (m) above the road of pixels at rows v with disparities d (> 0)."""
        d = np.asarray(d, np.float64)
        return math.cos(math.radians(self.pitch_deg)) * (self.road_row(d) - v) * self.baseline_m / d


def fit_road_profile(disparity: np.ndarray, model: camera.RectifiedModel, min_height_m: float = 0.1,
                     max_height_m: float = 10.0, hypotheses: int = 300, seed: int = 0) -> RoadProfile | None:
    """disparity: (H, W) float px, NaN invalid. The v-disparity histogram of the lower half of the
    image (1 px disparity bins), then RANSAC over lines through two of its occupied cells (drawn by
    count) whose slope puts the camera min_height_m..max_height_m above the road, scored by the pixel
    count within 1 px + 3 % of the line; refined by count-weighted least squares on the inliers.
    None: too few valid pixels or no line with 5 % support."""
    h, w = disparity.shape
    v0 = h // 2
    d = disparity[v0:]
    ok = np.isfinite(d) & (d > 0.5)
    if np.count_nonzero(ok) < 200:
        return None
    rows = np.broadcast_to(np.arange(v0, h)[:, None], d.shape)[ok]
    bins = np.round(d[ok]).astype(np.int64)
    nd = int(bins.max()) + 1
    hist = np.bincount((rows - v0) * nd + bins, minlength=(h - v0) * nd).reshape(h - v0, nd).astype(np.float64)
    hist[:, 0] = 0
    vv, dd = np.nonzero(hist)
    cnt = hist[vv, dd]
    vv = vv + v0
    total = float(cnt.sum())
    B = model.baseline_m
    lo, hi = B / max_height_m, B / min_height_m
    rng = np.random.default_rng(seed)
    p = cnt / total
    i = rng.choice(len(cnt), size=hypotheses, p=p)
    j = rng.choice(len(cnt), size=hypotheses, p=p)
    dv = (vv[j] - vv[i]).astype(np.float64)
    good = np.abs(dv) >= 2
    slope = np.where(good, (dd[j] - dd[i]) / np.where(good, dv, 1.0), 0.0)
    good &= (slope >= lo) & (slope <= hi)
    if not good.any():
        return None
    slope = slope[good]
    hv = vv[i][good] - dd[i][good] / slope  # the horizon row of each candidate line

    def inliers(s: float, v_h: float) -> np.ndarray:
        pred = s * (vv - v_h)
        return (pred > 0) & (np.abs(dd - pred) <= 1.0 + 0.03 * pred)

    scores = [cnt[inliers(s, v_h)].sum() for s, v_h in zip(slope, hv)]
    k = int(np.argmax(scores))
    s, v_h = float(slope[k]), float(hv[k])
    for _ in range(3):
        m = inliers(s, v_h)
        if m.sum() < 3:
            return None
        wts, x, y = cnt[m], vv[m].astype(np.float64), dd[m].astype(np.float64)
        xm, ym = np.average(x, weights=wts), np.average(y, weights=wts)
        var = np.average((x - xm) ** 2, weights=wts)
        if var <= 0:
            return None
        s_new = float(np.average((x - xm) * (y - ym), weights=wts) / var)
        if not lo <= s_new <= hi:
            break
        s, v_h = s_new, float(xm - ym / s_new)
    support = float(cnt[inliers(s, v_h)].sum() / total)
    if support < 0.05:
        return None
    return RoadProfile(s, v_h, support, model.focal_px, model.cy, B)


def obstacle_height_p95(disparity: np.ndarray, bbox: tuple[int, int, int, int], disparity_px: float,
                        road: RoadProfile, rel_tol: float = 0.1, min_pixels: int = 10) -> float | None:
    """95th percentile height (m) above the road of the obstacle's pixels: those in its box whose
    disparity is within max(1 px, rel_tol * d) of its own. None with fewer than min_pixels."""
    h, w = disparity.shape
    x0, y0, x1, y1 = bbox
    x0, x1 = max(0, x0), min(w, x1)
    y0, y1 = max(0, y0), min(h, y1)
    if x1 <= x0 or y1 <= y0:
        return None
    box = disparity[y0:y1, x0:x1]
    tol = max(1.0, rel_tol * disparity_px)
    m = np.isfinite(box) & (box > 0.5) & (np.abs(box - disparity_px) <= tol)
    if np.count_nonzero(m) < min_pixels:
        return None
    v = np.broadcast_to(np.arange(y0, y1)[:, None], box.shape)[m]
    return float(np.percentile(road.height_above(v, box[m]), 95))
