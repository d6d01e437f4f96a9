"""Drops: floor that falls away in front of the robot (a curb down, stairs down, a platform's edge).

Beyond such an edge the camera sees the lower floor, below the ground plane. Nothing there stands
up, so no obstacle was made of it; and points down to 0.42 m below the plane counted as floor seen,
so the free-space grid called the far side of a curb drivable. A ballbot rolling off a curb falls.

A pixel of the vision range within near_field_m is a drop when its point lies lower than the ground
by more than min_drop_m, plus the stereo noise there (ground_noise_px of disparity) and what the
ground's tilt can be off at that distance. Drop pixels are not floor seen. Groups of them (touching
on the working grid, MIN_WIDTH_M across or more) are listed as obstacles placed where the robot
would roll off: each pixel's ray where it crosses the ground plane, so the obstacle lies on the
floor over the hole, from its near edge. Their confidence is 1: the lower floor was measured.

Farther than near_field_m, a real road's camber, its gutters and the ground fit's own error put
road below the plane by as much (karlsruhe: hundreds of pixels 0.15 m below at 13-20 m a frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cores import camera
from cores.segmentation import stats
from cores.segmentation.mount import FloorPlane
from cores.segmentation.settings import SegmenterSettings

MIN_WIDTH_M = 0.2  # across: narrower is a crack or a drain, or noise


def mask(dk: np.ndarray, df: np.ndarray, above: np.ndarray, floor: FloorPlane, cfg: SegmenterSettings,
         fB: float, doubt: np.ndarray | float) -> np.ndarray | None:
    """dk: working disparity gated to the vision range (0: none); df: the ground's disparity there;
    above: height above the ground (m); doubt: what the ground's tilt can be off by at each pixel (m).
    -> bool mask of drop pixels within near_field_m, or None."""
    if cfg.near_field_m <= 0:
        return None
    near_d = np.float32(fB / cfg.near_field_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        noise = np.float32(floor.height_m * cfg.ground_noise_px) / dk
        out = (dk >= near_d) & (above < -(np.float32(cfg.min_drop_m) + noise + doubt))
    return out if out.any() else None


@dataclass
class Hole:
    """One group of drop pixels: its points on the ground plane over the hole (camera frame, m),
    their 2nd / 98th percentiles, its working-grid box (x0, y0, x1, y1), pixels and median disparity."""

    pts: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    box: tuple[int, int, int, int]
    area: int
    disparity_px: float


def groups(drop: np.ndarray, df: np.ndarray, dk: np.ndarray, model: camera.RectifiedModel,
           cfg: SegmenterSettings, step: int) -> list[Hole]:
    """The groups of drop pixels (touching, min_pixels or more, MIN_WIDTH_M across or more)."""
    n, lab, st, _ = cv2.connectedComponentsWithStats(cv2.morphologyEx(drop.view(np.uint8), cv2.MORPH_CLOSE,
                                                                      np.ones((3, 3), np.uint8)), connectivity=8)
    out: list[Hole] = []
    f, cx, cy = model.focal_px, model.cx, model.cy
    for k in range(1, n):
        if st[k, cv2.CC_STAT_AREA] < cfg.min_pixels:
            continue
        x0, y0 = int(st[k, cv2.CC_STAT_LEFT]), int(st[k, cv2.CC_STAT_TOP])
        x1, y1 = x0 + int(st[k, cv2.CC_STAT_WIDTH]), y0 + int(st[k, cv2.CC_STAT_HEIGHT])
        ys, xs = np.nonzero((lab[y0:y1, x0:x1] == k) & drop[y0:y1, x0:x1])
        if ys.size < cfg.min_pixels:
            continue
        ys, xs = ys + y0, xs + x0
        d_ground = df[ys, xs].astype(np.float64)  # where each pixel's ray crosses the ground plane
        ok = d_ground > 0
        if not ok.any():
            continue
        ys, xs, d_ground = ys[ok], xs[ok], d_ground[ok]
        z = model.baseline_m * f / d_ground
        u, v = xs.astype(np.float64) * step, ys.astype(np.float64) * step
        pts = np.stack([(u - cx) * z / f, (v - cy) * z / f, z], 1)
        lo, hi = stats.percentile(pts, [2, 98])
        if hi[0] - lo[0] < MIN_WIDTH_M:
            continue
        out.append(Hole(pts, lo, hi, (x0, y0, x1, y1), int(ys.size), float(np.median(dk[ys, xs]))))
    return out
