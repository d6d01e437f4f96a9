"""The thesis's segmentation (chapter 4), step by step, plus an optional floor removal (the ground
found in the map, as for layers) so that a textured floor in range does not swallow the objects
standing on it.

disparity (H, W) float32 px, NaN = invalid  ->  list of Detection (camera frame, metres)

 1. vision-range gate: pixels with d < f*B / max_range_m are removed (3 m -> d >= ~20 px)
 2. floor removal (if floor_removal): pixels whose 3D point lies within floor_margin_m of the floor plane
    are removed; the plane is the ground estimator's (ground.py, as for layers: fitted to the map every frame,
    the configured mount its prior; with fit_floor false, the mount)
 3. 2-D median filter
 4. normalise to grey (0..255)
 5. Otsu threshold
 6. area opening: regions smaller than min_area_fraction of the image are removed
 7. close, fill holes, clear border
 8. connected regions; per region: centroid (x, y), mode of the disparity, Z = B f / d,
    X = x Z / f, Y = y Z / f with x, y measured from the principal point
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cores import camera
from cores.segmentation.mount import FloorPlane
from cores.segmentation.settings import SegmenterSettings

MODE_BIN_PX = 0.25  # histogram bin of the region's disparity mode


@dataclass
class Detection:
    position_m: np.ndarray  # (3,) camera frame
    size_m: np.ndarray  # (3,)
    distance_m: float
    bbox_px: tuple[int, int, int, int]  # x0, y0, x1, y1 inclusive-exclusive
    area_px: int
    disparity_px: float
    confidence: float
    # cut by the edge of what the camera measures: (left, right, far): the image's sides or the matcher's
    # blind left band, the vision range; its centroid describes the visible part only
    cut: tuple[bool, bool, bool] = (False, False, False)
    edges: np.ndarray | None = None  # (2, 3) camera-frame points of its left and right edge

    @property
    def truncated(self) -> bool:
        return any(self.cut)


def floor_mask(disparity: np.ndarray, floor: FloorPlane, margin_m: float) -> np.ndarray:
    """True where the pixel's 3D point is within margin_m of (or below) the floor plane.

    A pixel's point lies h (1 - d_floor / d) above the floor (FloorPlane), so the test
    height < margin is, for d > 0, d (h - margin) < h d_floor: linear in the map."""
    h, w = disparity.shape
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    d_floor = floor.disparity(u, v)  # float32: numpy keeps a Python float's product with float32 in float32
    with np.errstate(invalid="ignore"):
        return disparity * np.float32(floor.height_m - margin_m) < np.float32(floor.height_m) * d_floor


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """Background not reachable from the image border becomes foreground (MATLAB's imfill 'holes').
    A flood fill from a padded border is several times faster than scipy's binary_fill_holes."""
    h, w = mask.shape
    padded = np.zeros((h + 2, w + 2), np.uint8)
    padded[1:-1, 1:-1] = mask
    cv2.floodFill(padded, None, (0, 0), 2)
    return (padded[1:-1, 1:-1] != 2).astype(np.uint8)


def _mode(values: np.ndarray, bin_px: float) -> float:
    """Mode of the disparities, refined as the median of the values in the modal bin."""
    lo = values.min()
    idx = ((values - lo) / bin_px).astype(np.int64)
    b = np.bincount(idx).argmax()
    return float(np.median(values[idx == b]))


def segment(disparity: np.ndarray, model: camera.RectifiedModel,
            cfg: SegmenterSettings | None = None, floor: FloorPlane | None = None) -> list[Detection]:
    """The detections of segment_frame (the thesis's steps; see there)."""
    return segment_frame(disparity, model, cfg, floor)[0]


def segment_frame(disparity: np.ndarray, model: camera.RectifiedModel, cfg: SegmenterSettings | None = None,
                  floor: FloorPlane | None = None) -> tuple[list[Detection], bool]:
    """disparity: (H, W) float32 px, NaN = invalid, rectified left camera `model` -> detections,
    camera frame. Reads range_m, median_px (at least 3), floor_removal, floor_margin_m,
    min_area_fraction, close_radius_px and clear_border; the floor plane is removed (None: no floor
    removed, as in the thesis; ObstacleBuilder passes the ground estimator's, as for layers).
    -> (detections, unlisted): unlisted when, with a floor removed, what stands in the vision range
    leaves a region outside every detection whose frontal area is that of the smallest obstacle the
    default method reports (min_area_m2): the thesis drops what touches the image border, what lies on
    the far side of its Otsu threshold and what is smaller than its area opening (3 % of the image:
    at 10 m a parked car covers less of a street camera's), so such a list is not a full view of the range."""
    cfg = cfg or SegmenterSettings(method="seed")
    if disparity.shape != (model.height, model.width):
        raise ValueError(f"disparity is {disparity.shape[1]}x{disparity.shape[0]}, camera model is "
                         f"{model.width}x{model.height}")
    h, w = disparity.shape
    d_min = model.disparity_for_depth(cfg.range_m)
    d = np.asarray(disparity, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(d) & (d >= d_min)
    if cfg.floor_removal and floor is not None:
        keep &= ~floor_mask(d, floor, cfg.floor_margin_m)
    if not keep.any():
        return [], False
    gated = np.where(keep, d, 0.0).astype(np.float32)
    filtered = cv2.medianBlur(gated, max(3, cfg.median_px))
    top = float(filtered.max())
    if top <= 0:
        return [], False
    grey = np.clip(filtered * (255.0 / top), 0, 255).astype(np.uint8)
    _, binary = cv2.threshold(grey, 0, 1, cv2.THRESH_BINARY | cv2.THRESH_OTSU)

    min_area = cfg.min_area_fraction * h * w
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    big = np.zeros(n, bool)
    big[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area
    mask = big[labels].astype(np.uint8)

    r = cfg.close_radius_px
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    mask = fill_holes(mask)

    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    fB = model.focal_px * model.baseline_m
    out: list[Detection] = []
    listed = np.zeros(n, bool)
    for i in range(1, n):
        x0, y0, bw, bh, area = (int(v) for v in stats[i])
        if cfg.clear_border and (x0 == 0 or y0 == 0 or x0 + bw >= w or y0 + bh >= h):
            continue
        region = labels[y0:y0 + bh, x0:x0 + bw] == i
        dv = d[y0:y0 + bh, x0:x0 + bw][region]
        valid = dv[np.isfinite(dv) & (dv >= d_min)]
        if valid.size == 0:
            continue
        disp = _mode(valid, MODE_BIN_PX)
        z = fB / disp
        cx_px, cy_px = centroids[i]
        x = (cx_px - model.cx) * z / model.focal_px
        y = (cy_px - model.cy) * z / model.focal_px
        # depth spread and nearest point from pixels near the mode (robust to mismatches)
        near = valid[np.abs(valid - disp) <= max(2.0, 0.15 * disp)]
        zs = fB / near
        size = np.array([bw * z / model.focal_px, bh * z / model.focal_px,
                         float(np.percentile(zs, 95) - np.percentile(zs, 5))])
        distance = float(np.percentile(zs, 2)) if zs.size else z
        out.append(Detection(
            position_m=np.array([x, y, z]), size_m=size, distance_m=distance,
            bbox_px=(x0, y0, x0 + bw, y0 + bh), area_px=area, disparity_px=disp,
            confidence=float(valid.size / max(area, 1))))
        listed[i] = True
    unlisted = False
    if floor is not None:
        rest = (filtered > 0) & ~listed[labels]
        n_rest, rest_labels = cv2.connectedComponents(rest.view(np.uint8), connectivity=8)
        if n_rest > 1:  # each region's frontal area: a pixel at disparity d covers (B / d)^2 m^2
            frontal = np.bincount(rest_labels[rest], weights=(model.baseline_m / filtered[rest]) ** 2,
                                  minlength=n_rest)
            unlisted = bool(frontal[1:].max() >= cfg.min_area_m2)
    return out, unlisted
