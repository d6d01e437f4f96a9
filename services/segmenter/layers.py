"""The default segmenter: depth-aware region growing on the disparity map, with the floor removed.

disparity (H, W) float32 px, NaN = invalid  ->  list of Detection (camera frame, metres)

Unlike the thesis's single Otsu threshold (seed.py), objects that touch in the image but sit at
different depths stay apart, objects cut by the image border are kept, and the floor is a fitted
plane rather than "whatever is far".

 1. work on every `downsample`-th pixel (2: 320x240 for a 640x480 map), NaN -> 0
 2. 5x5 median filter (removes block-matching speckle, keeps depth steps sharp)
 3. range gate: min_range_m <= Z <= max_range_m
 4. floor: a plane d = a u + b v + c in disparity space (a flat floor is a plane there),
    fitted by least squares to the pixels in a band around the plane the camera mount predicts,
    the band narrowed over three passes (without a mount: RANSAC on the lower half first);
    checked against the mount (normal within max_tilt_deg, height within 30 %), the mount's plane
    as the fallback; pixels less than floor_margin_m above it are floor
 5. region growing with a similarity tolerance: 4-neighbours belong together when their
    disparities differ by at most step_px + step_rel * d. Implemented as one connected-components
    pass after removing every pixel with a 4-neighbour nearer by more than the tolerance (one
    3x3 dilation), so no region can leak across a depth step
 6. regions smaller than min_size_m (largest extent) or min_area_m2 (frontal area) are dropped
 7. per region, its pixels' 3D points (outliers beyond the tolerance of the median disparity
    dropped); where a column ends within floor_margin_m (+4 cm) of the floor, the object stands on
    it and the strip that floor removal cut off is filled back in along the floor normal
 8. regions whose 3D extents come within merge_gap_m of each other on every axis are one object
    (a chair's back leg, seen between its front legs, is apart from the seat in the image)
 9. per object: centroid (mean of the points, like the surface points a camera sees), extent
    (2nd-98th percentile), nearest distance (2nd percentile of range), bbox, area, median
    disparity, confidence = fraction of the region's pixels with a valid raw disparity
10. optional boundary refinement (edge_refine): each box side is snapped to the strongest
    intensity edge of the left image within a few pixels (the thesis's hybrid idea)
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ...common import camera
from .mount import FloorPlane, Mount
from .seed import Detection
from .settings import SegmenterSettings


def _coords(h: int, w: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution pixel coordinates of the working grid's samples (u: (1, w), v: (h, 1))."""
    return (np.arange(w, dtype=np.float32)[None, :] * step, np.arange(h, dtype=np.float32)[:, None] * step)


def _plane_from_mount(mount: Mount, model: camera.RectifiedModel) -> FloorPlane:
    return FloorPlane.from_normal(mount.down_camera, mount.height_m, model.focal_px, model.cx, model.cy,
                                  model.baseline_m)


def _ransac_plane(u: np.ndarray, v: np.ndarray, d: np.ndarray, rng: np.random.Generator,
                  n_hyp: int = 64) -> np.ndarray | None:
    """Floor candidate without a mount: the plane d = a u + b v + c with most points within 1 px,
    among planes that rise downwards (b > 0: nearer towards the bottom of the image)."""
    if d.size < 50:
        return None
    idx = rng.integers(0, d.size, size=(n_hyp, 3))
    A = np.stack([u[idx], v[idx], np.ones((n_hyp, 3), np.float32)], -1)
    ok = np.abs(np.linalg.det(A)) > 1e-3
    if not ok.any():
        return None
    planes = np.linalg.solve(A[ok], d[idx][ok][..., None])[..., 0]  # (k, 3)
    planes = planes[planes[:, 1] > 1e-3]
    if not len(planes):
        return None
    res = np.abs(planes[:, 0:1] * u[None] + planes[:, 1:2] * v[None] + planes[:, 2:3] - d[None])
    score = (res < 1.0).sum(1)
    return planes[int(score.argmax())]


def _lstsq_plane(u: np.ndarray, v: np.ndarray, d: np.ndarray) -> np.ndarray:
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


def fit_floor(d: np.ndarray, model: camera.RectifiedModel, cfg: SegmenterSettings, step: int) -> FloorPlane | None:
    """The floor plane in disparity space from a (median-filtered) working-resolution disparity map
    d (0 = invalid); the mount's plane when the fit fails or disagrees with it; None when there is
    neither a mount nor a plausible fit."""
    mount = cfg.mount()
    prior = _plane_from_mount(mount, model) if mount is not None else None
    if not cfg.fit_floor:
        return prior
    h, w = d.shape
    s = 2  # fit on every other working pixel
    sub = d[::s, ::s]
    uu, vv = _coords(*sub.shape, step * s)
    uu = np.broadcast_to(uu, sub.shape)
    vv = np.broadcast_to(vv, sub.shape)
    valid = sub > 0
    u, v, dv = uu[valid], vv[valid], sub[valid]
    if dv.size < 50:
        return prior
    if prior is not None:
        p = np.array([prior.a, prior.b, prior.c])
        tols = (0.25, 0.12, 0.06)
    else:
        low = v > model.cy
        p = _ransac_plane(u[low], v[low], dv[low], np.random.default_rng(0))
        if p is None:
            return None
        tols = (0.12, 0.06)
    inl = np.zeros(0, bool)
    for tol in tols:
        pred = p[0] * u + p[1] * v + p[2]
        inl = (pred > 0) & (np.abs(dv - pred) <= np.maximum(0.6, tol * pred))
        if inl.sum() < 200:
            return prior
        p = _lstsq_plane(u[inl], v[inl], dv[inl])
    fitted = FloorPlane(float(p[0]), float(p[1]), float(p[2]), 1.0, True, int(inl.sum()))
    n, height = fitted.normal_height(model.focal_px, model.cx, model.cy, model.baseline_m)
    fitted = FloorPlane(fitted.a, fitted.b, fitted.c, height, True, fitted.inliers)
    if prior is not None:
        n0, h0 = prior.normal_height(model.focal_px, model.cx, model.cy, model.baseline_m)
        tilt = np.degrees(np.arccos(np.clip(float(n @ n0), -1, 1)))
        if tilt > cfg.max_tilt_deg or abs(height - h0) > 0.3 * h0:
            return prior
    elif n[1] <= 0.2:  # the floor must be below the camera
        return None
    return fitted


@dataclass
class _Region:
    pts: np.ndarray  # (n, 3) camera-frame points (m) of the region's inlier pixels
    lo: np.ndarray  # (3,) 2nd percentile of the points
    hi: np.ndarray  # (3,) 98th percentile
    bbox: tuple[int, int, int, int]  # working-resolution x0, y0, x1, y1 (exclusive)
    area: int  # working-resolution pixels
    valid: int  # of which with a valid raw disparity
    disparities: np.ndarray  # (n,) px
    filled: int = 0  # points added by _fill_to_floor (included in pts)


def _fill_to_floor(mask: np.ndarray, d_box: np.ndarray, x0: int, y0: int, floor: FloorPlane, cfg: SegmenterSettings,
                   model: camera.RectifiedModel, step: int) -> np.ndarray | None:
    """The strip of an object that floor removal cut off: where a column of the region ends less
    than floor_margin_m (+4 cm) above the floor, the object is taken to stand on it, and points
    are added straight down (along the floor normal: a vertical face) to the floor, one per
    working-grid row they cover. -> (k, 3) camera-frame points, or None."""
    has = mask.any(0)
    if not has.any():
        return None
    f, cx, cy, B = model.focal_px, model.cx, model.cy, model.baseline_m
    n_down, _ = floor.normal_height(f, cx, cy, B)
    bh = mask.shape[0]
    cols = np.nonzero(has)[0]
    rows = (bh - 1 - np.argmax(mask[::-1], axis=0))[cols]
    db = d_box[rows, cols].astype(np.float64)
    ok = db > 0
    if not ok.any():
        return None
    cols, rows, db = cols[ok], rows[ok], db[ok]
    u = (cols + x0).astype(np.float64) * step
    v = (rows + y0).astype(np.float64) * step
    z = f * B / db
    P = np.stack([(u - cx) * z / f, (v - cy) * z / f, z], 1)
    height = floor.height_m - P @ n_down  # above the floor
    reach = cfg.floor_margin_m + 0.04
    on_floor = (height > -0.02) & (height <= reach)
    if not on_floor.any():
        return None
    P, v, height = P[on_floor], v[on_floor], np.maximum(height[on_floor], 0.0)
    F = P + height[:, None] * n_down  # the foot of each column on the floor
    v_foot = np.minimum(F[:, 1] * f / F[:, 2] + cy, model.height - 1)
    n = np.maximum(np.floor((v_foot - v) / step), 0).astype(np.int64)
    total = int(n.sum())
    if total == 0:
        return None
    idx = np.repeat(np.arange(len(n)), n)
    k = np.arange(total) - np.repeat(np.cumsum(n) - n, n) + 1
    t = (k / n[idx]) * height[idx]
    return P[idx] + t[:, None] * n_down


def _merge_close(regions: list[_Region], gap_m: float) -> list[_Region]:
    """Merge regions whose 3D extents come within gap_m of each other along every axis: the parts
    of one object that the image shows apart (a chair's back leg seen between its front legs)."""
    if len(regions) < 2 or gap_m <= 0:
        return regions
    parent = list(range(len(regions)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    lo = np.array([r.lo for r in regions])
    hi = np.array([r.hi for r in regions])
    gap = np.maximum(lo[:, None, :] - hi[None, :, :], lo[None, :, :] - hi[:, None, :])  # (n, n, 3)
    close = np.all(gap <= gap_m, axis=2)
    for i, j in zip(*np.nonzero(np.triu(close, 1))):
        parent[root(int(i))] = root(int(j))
    groups: dict[int, list[_Region]] = {}
    for i, r in enumerate(regions):
        groups.setdefault(root(i), []).append(r)
    out = []
    for g in groups.values():
        if len(g) == 1:
            out.append(g[0])
            continue
        pts = np.concatenate([r.pts for r in g])
        lo, hi = np.percentile(pts[::max(1, len(pts) // _STAT_SAMPLES)], [2, 98], axis=0)
        out.append(_Region(pts, lo, hi,
                           (min(r.bbox[0] for r in g), min(r.bbox[1] for r in g),
                            max(r.bbox[2] for r in g), max(r.bbox[3] for r in g)),
                           sum(r.area for r in g), sum(r.valid for r in g),
                           np.concatenate([r.disparities for r in g]), sum(r.filled for r in g)))
    return out


_STAT_SAMPLES = 1500  # percentiles of a region are taken on at most ~2x this many of its points
_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
_GRIDS: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}


def segment(disparity: np.ndarray, model: camera.RectifiedModel, cfg: SegmenterSettings | None = None,
            image: np.ndarray | None = None, floor_out: list | None = None) -> list[Detection]:
    """disparity: (H, W) float32 px, NaN = invalid, rectified left camera `model`.
    image: the rectified left image (H, W) uint8, only for edge_refine. floor_out: if a list, the
    floor plane used (or None) is appended to it. -> detections, camera frame."""
    cfg = cfg or SegmenterSettings()
    if disparity.shape != (model.height, model.width):
        raise ValueError(f"disparity is {disparity.shape[1]}x{disparity.shape[0]}, camera model is "
                         f"{model.width}x{model.height}")
    step = max(1, int(cfg.downsample))
    d0 = np.nan_to_num(np.asarray(disparity, dtype=np.float32)[::step, ::step], nan=0.0, posinf=0.0, neginf=0.0)
    h, w = d0.shape
    np.maximum(d0, 0, out=d0)
    dm = cv2.medianBlur(d0, cfg.median_ksize) if cfg.median_ksize > 1 else d0
    fB = model.focal_px * model.baseline_m
    keep = cv2.inRange(dm, fB / cfg.range_m, fB / cfg.min_range_m)  # uint8 0/255
    floor = None
    if cfg.floor_removal and keep.any():
        floor = fit_floor(np.where(keep > 0, dm, np.float32(0)), model, cfg, step)
        if floor is not None:
            key = (h, w, step)
            if key not in _GRIDS:
                _GRIDS[key] = _coords(h, w, step)
            u, v = _GRIDS[key]
            k = 1.0 / max(1e-3, 1.0 - cfg.floor_margin_m / floor.height_m)
            df = (np.float32(floor.a) * u) + (np.float32(floor.b) * v + np.float32(floor.c))
            thr = np.maximum(df * np.float32(k), df + np.float32(0.5))
            keep[dm <= thr] = 0
    if floor_out is not None:
        floor_out.append(floor)
    if not keep.any():
        return []

    # Region growing with a similarity tolerance, as one connected-components pass: a pixel whose
    # 4-neighbour is nearer by more than the tolerance is cut, so no region crosses a depth step.
    dk = np.where(keep > 0, dm, np.float32(0))
    nearest_nb = cv2.dilate(dk, _CROSS)
    keep[nearest_nb > dk * np.float32(1.0 + cfg.step_rel) + np.float32(cfg.step_px)] = 0
    n, labels, stats, _ = cv2.connectedComponentsWithStats(keep, connectivity=4)
    f = model.focal_px
    regions: list[_Region] = []
    for i in range(1, n):
        x0, y0, bw, bh, area = (int(x) for x in stats[i])
        if area < cfg.min_pixels:
            continue
        lab = labels[y0:y0 + bh, x0:x0 + bw]
        ys, xs = np.nonzero(lab == i)
        dv = dk[y0:y0 + bh, x0:x0 + bw][ys, xs]
        med = float(np.median(dv))
        px_m = fB / med / f * step  # metres per working pixel at the region's depth
        if max(bw, bh) * px_m < cfg.min_size_m and area * px_m * px_m < cfg.min_area_m2:
            continue
        if area * px_m * px_m < 0.25 * cfg.min_area_m2:
            continue
        good = np.abs(dv - med) <= 3 * (cfg.step_px + cfg.step_rel * med) + 0.1 * med
        dg = dv[good].astype(np.float64)
        zs = fB / dg
        pts = np.stack([((xs[good] + x0) * step - model.cx) * zs / f, ((ys[good] + y0) * step - model.cy) * zs / f,
                        zs], 1)
        valid = int(np.count_nonzero(d0[y0:y0 + bh, x0:x0 + bw][ys, xs]))
        y1 = y0 + bh
        filled = 0
        if floor is not None and cfg.fill_to_floor:
            extra = _fill_to_floor(lab == i, dk[y0:y0 + bh, x0:x0 + bw], x0, y0, floor, cfg, model, step)
            if extra is not None:
                pts = np.concatenate([pts, extra])
                filled = len(extra)
                y1 = max(y1, min(h, int(np.ceil((float(np.max(extra[:, 1] / extra[:, 2])) * f + model.cy) / step)) + 1))
        lo, hi = np.percentile(pts[::max(1, len(pts) // _STAT_SAMPLES)], [2, 98], axis=0)
        regions.append(_Region(pts, lo, hi, (x0, y0, x0 + bw, y1), area, valid, dg, filled))
    regions = _merge_close(regions, cfg.merge_gap_m)
    out: list[Detection] = []
    for r in regions:
        size = r.hi - r.lo
        if max(size[0], size[1]) < cfg.min_size_m or r.area * (float(np.mean(r.pts[:, 2])) / f * step) ** 2 < cfg.min_area_m2:
            continue
        sub = r.pts[::max(1, len(r.pts) // _STAT_SAMPLES)]
        rng = np.sqrt((sub * sub).sum(1))
        x0, y0, x1, y1 = r.bbox
        out.append(Detection(position_m=r.pts.mean(0), size_m=np.maximum(size, 0.0),
                             distance_m=float(np.percentile(rng, 2)),
                             bbox_px=(x0 * step, y0 * step, min(model.width, x1 * step), min(model.height, y1 * step)),
                             area_px=int((r.area + r.filled) * step * step),
                             disparity_px=float(np.median(r.disparities)),
                             confidence=r.valid / max(1, r.area)))
    if cfg.edge_refine and image is not None and out:
        out = [_refine_box(det, image) for det in out]
    return out


def _refine_box(det: Detection, image: np.ndarray, reach: int = 4) -> Detection:
    """Snap each side of the box to the strongest intensity edge within `reach` px (the thesis's
    hybrid of disparity regions and intensity edges)."""
    img = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    H, W = img.shape
    x0, y0, x1, y1 = det.bbox_px
    gx = np.abs(cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3))
    gy = np.abs(cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3))

    def snap(pos: int, limit: int, profile) -> int:
        lo, hi = max(0, pos - reach), min(limit, pos + reach + 1)
        if hi <= lo:
            return pos
        return lo + int(np.argmax([profile(p) for p in range(lo, hi)]))

    ya, yb = max(0, y0), max(y0 + 1, min(H, y1))
    xa, xb = max(0, x0), max(x0 + 1, min(W, x1))
    nx0 = snap(x0, W - 1, lambda p: gx[ya:yb, p].mean())
    nx1 = snap(x1 - 1, W - 1, lambda p: gx[ya:yb, p].mean()) + 1
    ny0 = snap(y0, H - 1, lambda p: gy[p, xa:xb].mean())
    ny1 = snap(y1 - 1, H - 1, lambda p: gy[p, xa:xb].mean()) + 1
    if nx1 <= nx0 or ny1 <= ny0:
        return det
    det.bbox_px = (nx0, ny0, nx1, ny1)
    return det
