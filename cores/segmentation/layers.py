"""The default segmenter: things that stand up from the ground, one obstacle per object.

disparity (H, W) float32 px, NaN = invalid  ->  LayersFrame (detections camera frame, metres; the
floor plane and ground estimate used; the floor the robot may drive on, for free space)

Unlike the thesis's single Otsu threshold (seed.py), the floor is found in the data every frame,
only what stands on it counts, and objects are grouped where they stand.

 1. work on every `downsample`-th pixel (2: 320x240 for a 640x480 map), NaN -> 0; pixels whose
    matcher confidence is below min_confidence are invalid
 2. median filter (median_px: 5x5, 3x3 at downsample 4, about 10 px of the map; removes
    block-matching speckle, keeps depth steps sharp)
 3. range gate: min_range_m <= Z <= max_range_m
 4. the ground: a plane d = a u + b v + c in disparity space, fitted this frame (ground.py: the
    last frames' estimate, the configured mount or RANSAC as the first guess; checked, smoothed,
    published as height / pitch / roll)
 5. height band: a pixel stands when it is more than floor_margin_m (plus what the floor's tilt can
    be off at its distance, and ground_noise_px of disparity) above the floor and at most
    robot_height_m above it; markings, shadows, mats are floor, canopy and ceilings are above the
    robot
 5a. drops (drops.py): floor lower than the ground by min_drop_m (beyond the noise) within
    near_field_m is the far side of a curb or stairs down: not floor seen, and an obstacle
 5b. blank faces (blank.py): where the floor seen along a column ends short of the range with
    nothing measured standing there, and the image above is unmeasured up past the horizon, a
    plain face (a wall, a door, a cabinet: nothing inside to match) stands at the floor's end:
    its pixels stand, upright over that foot; a lower one, where what was measured above the floor's stop
    (the matcher's doubted pixels too) is mostly at the stop's depth, up to a top edge
 6. a standing pixel with a 4-neighbour nearer by more than step_px + step_rel * d sits on a depth
    step, where block matching blends two depths into a phantom: it is not grouped
 7. grouping on the column-disparity grid (u-disparity): a cell (column, disparity bin) is
    occupied when its standing pixels cover min_cell_height_m; touching cells are one object.
    In metres this is a polar grid on the ground as fine as the matcher can see: a car, a wall
    seen obliquely, a person stay whole; a person in front of a wall stays apart. A group whose
    disparities form two peaks with an empty valley between them, bridged only by the narrow
    ramp the matcher draws across an occlusion, is two things one behind the other: split
 8. objects whose top (the 95th percentile of their heights above the floor: on a small thing
    the 98th is its two or three highest pixels, the matcher's noise) is below min_height_m (plus
    what the floor's fit can be off at their distance: _floor_doubt, from how much the fitted tilt
    moves from frame to frame) are dropped; those smaller than min_size_m / min_area_m2 after 10
 9. per object, its 3D points; where a column ends within floor_margin_m (+4 cm) of the floor the
    object stands on it and the strip the band cut off is filled back in along the floor normal
10. objects whose 3D extents come within merge_gap_m are one (a chair's back leg seen between its
    front legs; along the view merge_gap_depth_m: a fence seen obliquely); a small object mostly
    inside a larger one's box is part of it (depths meet) or seen through it (wholly behind and
    framed by it: a car's windows) and dropped; a sliver cut by a side of the view joins the piece of
    its thing beside it within merge_gap_depth_m (regions.join_cut)
11. per object: centroid (mean of the points), extent (2nd-98th percentile), nearest distance
    (2nd percentile of range), bbox, area, median disparity, confidence (mean matcher confidence,
    else the fraction of its pixels with a valid raw disparity)
12. the drivable floor: along each column, from the image's bottom edge to the farthest floor
    point seen, stopped by anything standing (nearer than min_range_m too, in no list as it is),
    within near_field_m not across an unmeasured
    stretch that could hide something min_height_m tall (freespace.py: drivable, and the grid)
13. optional boundary refinement (edge_refine): each box side snapped to the strongest intensity
    edge of the left image within a few pixels (the thesis's hybrid idea)
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.messages import GroundEstimate
from cores import camera
from cores.segmentation import blank, depth_split, drops, freespace, regions, stats
from cores.segmentation.cells import LOW_M, group_cells, occupied
from cores.segmentation.ground import GroundEstimator, grid
from cores.segmentation.mount import FloorPlane, Mount
from cores.segmentation.seed import Detection
from cores.segmentation.settings import FAR_DISPARITY_PX, SegmenterSettings


def _fill_to_floor(mask: np.ndarray, d_box: np.ndarray, x0: int, y0: int, floor: FloorPlane, cfg: SegmenterSettings,
                   model: camera.RectifiedModel, step: int, doubt_deg: float = 0.0) -> np.ndarray | None:
    """The strip of an object that floor removal cut off: where a column of the region ends less
    than floor_margin_m (+4 cm) above the floor, the object is taken to stand on it, and points
    are added straight down (along the floor normal: a vertical face) to the floor, one per
    working-grid row they cover. d_box: the working disparity over mask's box (read where mask is
    set). -> (k, 3) camera-frame points, or None."""
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
    reach = cfg.floor_margin_m + 0.04 + _tilt_doubt(P[:, 2], floor.height_m, doubt_deg)  # as far as the band reaches
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


_SQUARE = np.ones((3, 3), np.uint8)
_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


@dataclass
class LayersFrame:
    """Everything one frame's segmentation found, for the obstacle list and the free-space grid."""

    detections: list[Detection]
    points: list[np.ndarray]  # per detection, its (n, 3) camera-frame points, m
    floor: FloorPlane | None  # the disparity-space floor plane used (None: no floor removed)
    ground: GroundEstimate | None  # what the ground estimator said (None: floor removal off)
    floor_points: np.ndarray  # (k, 3) camera-frame points of the floor the robot may drive on (see _drivable)
    # something standing in the vision range, of min_area_m2 frontal area, is in no detection (seed: it
    # touches the image border, is under the area opening or beyond the Otsu threshold): not a full view
    unlisted: bool = False


def _working_disparity(disparity: np.ndarray, cfg: SegmenterSettings, confidence: np.ndarray | None,
                       step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(raw, median-filtered, doubtful) working-resolution disparity, 0 = invalid; pixels whose
    confidence is below min_confidence are invalid. doubtful: the disparity of the pixels set aside
    that the matcher measured nonetheless (confidence from blank.MEASURED up), 0 elsewhere; None when
    nothing was set aside."""
    d0 = np.ascontiguousarray(np.asarray(disparity, dtype=np.float32)[::step, ::step])
    if d0.base is disparity or d0 is disparity:
        d0 = d0.copy()  # (step 1) the caller's map stays as it is
    cv2.patchNaNs(d0, 0)  # NaN, negative and infinite -> 0, in place (OpenCV: several times numpy's speed)
    cv2.threshold(d0, 0, 0, cv2.THRESH_TOZERO, dst=d0)
    cv2.threshold(d0, float(np.finfo(np.float32).max), 0, cv2.THRESH_TOZERO_INV, dst=d0)
    doubtful = None
    if confidence is not None and cfg.min_confidence > 0:
        c0 = np.asarray(confidence)[::step, ::step]
        low = c0 < cfg.min_confidence
        if cfg.min_confidence > blank.MEASURED:
            doubtful = np.where(low & (c0 >= blank.MEASURED), d0, np.float32(0))
        d0[low] = 0
    dm = cv2.medianBlur(d0, cfg.median_px) if cfg.median_px > 1 else d0
    return d0, dm, doubtful


def _left_margin(d0: np.ndarray, step: int, left_edge: int, search: tuple[int, int] | None) -> float:
    """How far right of x = d (px) the matcher measures its first pixel at disparity d, on a map that
    matches the band left of its search (dense; bm and sgbm with match_band): half its window, since a
    match whose partner's window reaches past the right image's left edge is dropped (bm's 15 px
    blocks: 7). The map shows it: in each row the leftmost measured pixel lies that far right of its
    x = d or farther (farther where the scene there is plain); the least over the rows, less the
    column of the working grid that side_cut's reach allows already (dense's 1-2 px stay within it). 0
    where the search is unknown or the map measures nothing left of its band (its cut is its first
    column)."""
    if search is None or left_edge * step >= search[0] + search[1]:
        return 0.0
    rows = np.flatnonzero(d0.any(1))
    if not rows.size:
        return 0.0
    first = np.argmax(d0[rows] > 0, axis=1)
    return max(0.0, float(np.min(first * step - d0[rows, first])) - step)


def _nearest_disparity(fB: float, cfg: SegmenterSettings) -> float:
    """The disparity of min_range_m (px); min_range_m 0 keeps everything near (no division by zero)."""
    return fB / cfg.min_range_m if cfg.min_range_m > 0 else float(np.finfo(np.float32).max)


def _masked(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """np.where(mask, a, 0) of a 2-D map and a uint8 mask, by OpenCV (several times faster)."""
    out = np.zeros_like(a)
    cv2.copyTo(a, mask, out)
    return out


def _fit_ground(dm: np.ndarray, dk: np.ndarray | None, model: camera.RectifiedModel, cfg: SegmenterSettings,
                ground: GroundEstimator, step: int) -> tuple[FloorPlane | None, GroundEstimate]:
    """This frame's floor from the working disparity dm (dk: dm gated to the vision range, if at hand).
    The ground is the world's, not the range's: it is fitted on the floor out to where the rig still
    measures (FAR_DISPARITY_PX), however short the vision range. Inside a short range the floor is
    seen over too short a stretch to tell pitch from height (a car's camera with a 5 m range sees
    the road from 4.3 to 5 m: a plane pivoting on that strip fits as well 1 m higher and 20 deg
    steeper); inside 10 m, block matching with a larger block than the default sees a snow bank and
    the parking stripes but little of the smooth road, and the ground was 0.2-0.8 m and 2-7 deg
    off the road, trusted."""
    fB = model.focal_px * model.baseline_m
    range_m = cfg.range_for(model)
    ground_range = max(range_m, fB / FAR_DISPARITY_PX)
    if dk is not None and ground_range <= range_m:
        dg = dk
    else:
        dg = _masked(dm, cv2.inRange(dm, fB / ground_range, _nearest_disparity(fB, cfg)))
    return ground.update(dg, model, step)


def estimate_ground(disparity: np.ndarray, model: camera.RectifiedModel, cfg: SegmenterSettings,
                    ground: GroundEstimator, confidence: np.ndarray | None = None
                    ) -> tuple[FloorPlane | None, GroundEstimate]:
    """The floor plane and ground estimate of one full-resolution map, as segment_frame finds them
    (for the seed method, which removes the floor by it)."""
    step = max(1, int(cfg.downsample))
    _, dm, _ = _working_disparity(disparity, cfg, confidence, step)
    return _fit_ground(dm, None, model, cfg, ground, step)


def _label_order(lab: np.ndarray) -> np.ndarray:
    """np.argsort(lab, kind="stable") of labels >= 0: as 16-bit keys where they fit (numpy sorts
    those by radix: ~5x faster than its merge sort of 32-bit ones; the same order)."""
    return np.argsort(lab.astype(np.uint16) if lab.size and int(lab.max()) < 1 << 16 else lab, kind="stable")


def _group(dm: np.ndarray, stand: np.ndarray, cfg: SegmenterSettings, model: camera.RectifiedModel,
           step: int, extras: tuple[np.ndarray, ...] = (), above: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[np.ndarray], dict[int, int]]:
    """Group standing pixels into objects on the column-disparity grid (u-disparity): a cell
    (column, disparity bin) is occupied when its standing pixels cover min_cell_height_m of height;
    occupied cells that touch (one cell of slack) are one object. In metres this is a polar grid
    on the ground whose depth resolution follows the matcher's (fine near, coarse far), so a car's
    parts and a wall seen obliquely stay whole while a person in front of a wall stays apart.
    -> (ys, xs, d, label, [each of extras (maps like dm) there, then `above` (the height above the
    floor) there if given], cells.group_cells' cut groups) of the grouped pixels, sorted by label
    (labels from 1)."""
    yx = cv2.findNonZero(stand.view(np.uint8))  # np.nonzero's pixels in its order, faster (int32)
    xs, ys = (np.zeros(0, np.int32),) * 2 if yx is None else yx.reshape(-1, 2).T
    w = dm.shape[1]
    flat = ys * w + xs  # the maps' values there by index (several times faster than by a mask)
    dv = dm.ravel().take(flat)
    bins = (dv / np.float32(cfg.group_bin_px)).astype(np.int32)
    nb = int(bins.max()) + 2 if bins.size else 1
    height = np.float32(step * model.baseline_m) / dv  # metres of height one working pixel covers
    cell, cells = occupied(bins, xs, height, (nb, w), cfg.min_cell_height_m)
    tall, hv = None, None
    if above is not None:  # only low things between two objects do not join them (cells.py)
        hv = above.ravel().take(flat)
        high = np.bincount(cell, weights=height * (hv > LOW_M), minlength=nb * w)
        tall = ((high.reshape(nb, w) >= cfg.min_cell_height_m) & (cells > 0)).astype(np.uint8)
    cc, cut_from = group_cells(cells, tall)
    lab = (cc * cells).ravel()[cell]
    order = _label_order(lab)[np.count_nonzero(lab == 0):]  # label 0 (ungrouped) sorts first
    gathered = [e.ravel().take(flat.take(order)) for e in extras] + ([] if hv is None else [hv.take(order)])
    return ys[order], xs[order], dv[order], lab[order], gathered, cut_from


def segment_frame(disparity: np.ndarray, model: camera.RectifiedModel, cfg: SegmenterSettings | None = None,
                  ground: GroundEstimator | None = None, confidence: np.ndarray | None = None,
                  image: np.ndarray | None = None, flat: np.ndarray | None = None,
                  search: tuple[int, int] | None = None) -> LayersFrame:
    """disparity: (H, W) float32 px, NaN = invalid, rectified left camera `model`. ground: the
    estimator that carries the ground from frame to frame (None: a fresh one, this frame alone).
    confidence: (H, W) uint8 from the matcher, if it gives one. image: the rectified left image,
    only for edge_refine. flat: (H, W) bool, the pixels whose window was too plain to decide their
    match (Match.flat: sgbm carries into a plain face the floor's disparities beside it, row by row,
    and the free space reached under a plain crate): no floor is seen there, they count as unmeasured
    where blank faces are looked for, and otherwise stand as before. search: the map's (min_disparity,
    num_disparities), for where its left band ends (_left_margin; None: unknown)."""
    cfg = cfg or SegmenterSettings()
    if disparity.shape != (model.height, model.width):
        raise ValueError(f"disparity is {disparity.shape[1]}x{disparity.shape[0]}, camera model is "
                         f"{model.width}x{model.height}")
    if confidence is not None and confidence.shape != disparity.shape:
        raise ValueError(f"confidence is {confidence.shape[1]}x{confidence.shape[0]}, disparity "
                         f"{disparity.shape[1]}x{disparity.shape[0]}")
    if flat is not None and flat.shape != disparity.shape:
        raise ValueError(f"flat is {flat.shape[1]}x{flat.shape[0]}, disparity "
                         f"{disparity.shape[1]}x{disparity.shape[0]}")
    step = max(1, int(cfg.downsample))
    d0, dm, doubtful = _working_disparity(disparity, cfg, confidence, step)
    fw = None if flat is None else flat[::step, ::step]  # on the working grid
    h, w = dm.shape
    f, B = model.focal_px, model.baseline_m
    fB = f * B
    range_m = cfg.range_for(model)
    keep8 = cv2.inRange(dm, fB / range_m, _nearest_disparity(fB, cfg))
    keep = keep8 > 0
    dk = _masked(dm, keep8)
    floor, estimate = None, None
    doubt_deg = 0.0
    if cfg.floor_removal:
        ground = ground or GroundEstimator(cfg)
        floor, estimate = _fit_ground(dm, dk, model, cfg, ground, step)
        if floor is not None and ground.tilt_doubt_deg >= MIN_DOUBT_DEG:
            doubt_deg = ground.tilt_doubt_deg
    floor_points = np.zeros((0, 3))
    if floor is not None:
        u, v = grid(h, w, step)
        df = np.float32(floor.a) * u + (np.float32(floor.b) * v + np.float32(floor.c))
        # the margin grows with distance by what the floor's tilt can be off there (_tilt_doubt)
        doubt: np.ndarray | float = 0.0  # a floor that holds still: one margin everywhere (no per-pixel work)
        if doubt_deg >= MIN_DOUBT_DEG:
            with np.errstate(divide="ignore"):
                doubt = _tilt_doubt(np.float32(fB) / df, floor.height_m, doubt_deg)
            margin = np.float32(cfg.floor_margin_m) + doubt
            k = 1.0 / np.maximum(np.float32(1e-3), 1.0 - margin / np.float32(floor.height_m))
        else:
            k = np.float32(1.0 / max(1e-3, 1.0 - cfg.floor_margin_m / floor.height_m))
        floor_top = np.maximum(df * k, df + np.float32(cfg.ground_noise_px))  # the floor's largest disparity
        under_m = -4 * cfg.floor_margin_m - 0.1  # how far below the floor a pixel of it may seem to lie
        on_floor = dk <= floor_top
        with np.errstate(divide="ignore", invalid="ignore"):
            above = np.float32(floor.height_m) * (1 - df / dk)  # height above the floor, m
        stand = keep & ~on_floor & (above <= cfg.robot_height_m)
        seen_floor = keep & on_floor & (above > under_m)
        if fw is not None:  # what the matcher carried into a plain window is no floor seen (Match.flat)
            seen_floor &= ~fw
        drop = drops.mask(dk, df, above, floor, cfg, fB, doubt)
        if drop is not None:
            seen_floor &= ~drop  # the floor beyond a curb down is no floor to drive on
        # a floor pixel with fewer than 3 of its 8 neighbours floor is no floor seen: a speck of a plain
        # face the matcher matched at random at the floor's disparity of its row (bm without its speckle
        # filter on the low-faces crate) vouched for the floor from the image's bottom edge to it
        n = cv2.boxFilter(seen_floor.view(np.uint8), cv2.CV_8U, (3, 3), normalize=False)
        seen_floor &= n >= 4
        gaps = freespace.floor_gaps(seen_floor, df, model.baseline_m, cfg.min_height_m, step)
        # The floor measured beyond the vision range is no free space, but it is floor seen: where it
        # shows again above a plain face, the face is low. Without it a vision range shorter than where
        # the floor shows again (low-faces, dense, range 3 m or less: the crate's top hides the floor out
        # to 3.1 m) left the plain crate in no list, nothing said.
        # Only the columns whose floor seen in range leaves a stretch from the bottom edge are read (rule
        # 3 of blank.find): a whole grid's floor_gaps again cost ~0.5 ms a frame.
        bottom_start = gaps.bottom_start
        c = np.flatnonzero(bottom_start >= 0)
        if c.size:
            dmc, dfc = dm[:, c], df[:, c]
            with np.errstate(divide="ignore", invalid="ignore"):  # seen_floor's tests, out of range
                beyond = ((dmc > 0) & (dmc < np.float32(fB / range_m)) & (dmc <= floor_top[:, c])
                          & (np.float32(floor.height_m) * (1 - dfc / dmc) > under_m))
            if fw is not None:
                beyond &= ~fw[:, c]
            if beyond.any():
                bottom_start = bottom_start.copy()
                bottom_start[c] = freespace.floor_gaps(seen_floor[:, c] | beyond, dfc, model.baseline_m,
                                                       cfg.min_height_m, step).bottom_start
        # a plain face is looked for where nothing was measured: what sgbm carried into it is not (flat),
        # and a face found takes those pixels at its own depth
        faces = blank.find(dm if fw is None else np.where(fw, np.float32(0), dm), df, seen_floor,
                           stand if fw is None else stand & ~fw, floor, model, step, range_m, cfg.near_field_m,
                           cfg.robot_height_m, cfg.min_height_m, doubtful, gaps, bottom_start)
        not_floor = keep & ~on_floor
        if faces is not None:  # a plain face the matcher could not measure stands at the floor's end
            dm = np.where(faces.mask, faces.disparity, dm)
            dk = np.where(faces.mask, faces.disparity, dk)
            with np.errstate(divide="ignore", invalid="ignore"):
                above = np.where(faces.mask, np.float32(floor.height_m) * (1 - df / faces.disparity), above)
            stand |= faces.mask
            not_floor |= faces.mask  # a face stops the free space as anything standing does
        # What stands nearer than min_range_m is in no list (the range leaves it out) but it is there: it
        # stops the free space as anything standing does. Left out of it, the floor seen beyond a chair
        # whose front stood nearer made free the cells under its seat (min_range_m 2: chair, people-queue)
        dk_free = dk
        near_stand = (dm > np.float32(_nearest_disparity(fB, cfg))) & (dm > floor_top)
        if near_stand.any():
            not_floor = not_floor | near_stand
            dk_free = np.where(near_stand, dm, dk)
        floor_points = freespace.drivable(floor, df, seen_floor, not_floor, dk_free, model, cfg, step, gaps)
    else:
        above, drop = None, None
        stand = keep
    measured = np.flatnonzero(d0.any(0))  # columns the matcher measured (not its blind left band)
    left_edge, right_edge = (int(measured[0]), int(measured[-1])) if measured.size else (0, w - 1)
    # px an object's side may lie right of where it is cut: the median filter's reach and a column, and
    # never under two columns (the matcher's own first columns beside no data are doubtful)
    edge_reach = max(2, cfg.median_px // 2 + 1) * step
    lead = _left_margin(d0, step, left_edge, search)

    def side_cut(box: tuple[int, int, int, int], disparity_px: float) -> tuple[bool, bool]:
        """(left, right): is a working-grid box cut by a side of what the matcher measures? Left of
        x = d its points have no partner in the right image, whatever the matcher: dense's band is
        as wide as the disparity there (no fixed band; low-faces: the crate cut by the image's side
        ended at 20 px, unflagged). The median filter eats its reach into an edge beside no data,
        and the grid rounds by a column (people-border, dense: a person's lower piece began 4.6 px
        right of x = d). Nor right of x = d plus the matcher's margin there (_left_margin: bm matching
        its band from x = d + 7; people-border's person cut by the left side, its arm 62 px from the
        image's edge at 54 px of disparity, went unflagged, as did 14 of 26 things cut there in the
        15 scenes)."""
        x0, x1 = box[0], box[2]
        return x0 <= left_edge + 1 or x0 * step <= disparity_px + lead + edge_reach, x1 - 1 >= right_edge - 1

    def detection(pts: np.ndarray, lo: np.ndarray, hi: np.ndarray, box: tuple[int, int, int, int], area: int,
                  disparity_px: float, confidence: float) -> Detection:
        """An obstacle of its camera-frame points, its 2nd/98th percentiles and its working-grid box."""
        sub = pts[::max(1, len(pts) // regions.STAT_SAMPLES)]
        rng = np.sqrt((sub * sub).sum(1))
        x0, y0, x1, y1 = box
        return Detection(position_m=stats.mean0(pts), size_m=np.maximum(hi - lo, 0.0),
                         distance_m=float(stats.percentile(rng, 2)),
                         bbox_px=(x0 * step, y0 * step, min(model.width, x1 * step), min(model.height, y1 * step)),
                         area_px=int(area * step * step), disparity_px=disparity_px, confidence=confidence,
                         # cut at the sides or by the range: its footprint is partial (a cut at the
                         # top or bottom changes its height, not where it stands)
                         cut=(*side_cut(box, disparity_px), bool(hi[2] >= 0.97 * range_m)),
                         edges=_edges(sub, model))

    dropped: tuple[list[Detection], list[np.ndarray]] = ([], [])
    if drop is not None:  # measured lower floor, over which the robot would roll off: confidence 1
        holes = drops.groups(drop, df, dk, model, cfg, step)
        dropped = ([detection(g.pts, g.lo, g.hi, g.box, g.area, g.disparity_px, 1.0) for g in holes],
                   [g.pts for g in holes])
    # A pixel with a 4-neighbour nearer by more than the similarity tolerance sits on a depth step,
    # where block matching blends the two depths into a phantom between them: it is not grouped.
    ds = _masked(dm, stand.view(np.uint8))
    stand &= ~(cv2.dilate(ds, _CROSS) > ds * np.float32(1.0 + cfg.step_rel) + np.float32(cfg.step_px))
    if not stand.any():
        return LayersFrame(*dropped, floor, estimate, floor_points)

    ys, xs, dv, lab, ex, cut_from = _group(dm, stand, cfg, model, step, (d0,), above)
    dv0, hv = ex[0], ex[1] if above is not None else np.zeros(ys.size, np.float32)  # raw, height above the floor
    normal = None if floor is None else floor.normal_height(f, model.cx, model.cy, B)[0]
    lab, family = depth_split.split_layers(ys, xs, dv, lab, cfg, model, step, None if above is None else hv, normal)
    if family:  # labels changed (else they are _group's, sorted, from 1)
        order = _label_order(lab)[np.count_nonzero(lab == 0):]  # 0: dropped, sorts first
        ys, xs, dv, lab, hv, dv0 = ys[order], xs[order], dv[order], lab[order], hv[order], dv0[order]
    bounds = np.flatnonzero(np.diff(lab)) + 1
    found: list[regions.Region] = []
    for gy, gx, gd, gh, g0, gl in zip(np.split(ys, bounds), np.split(xs, bounds), np.split(dv, bounds),
                                      np.split(hv, bounds), np.split(dv0, bounds),
                                      lab[np.concatenate([[0], bounds]).astype(np.int64)] if lab.size else []):
        area = gy.size
        if area < cfg.min_pixels:
            continue
        x0, y0, x1, y1 = int(gx.min()), int(gy.min()), int(gx.max()) + 1, int(gy.max()) + 1
        med = float(stats.median(gd))
        px_m = B / med * step  # metres per working pixel at the region's depth
        # a piece under the smallest obstacle's size still joins the regions it comes close to (10),
        # and only what stays that small alone is dropped (after 10): the chair's seat corner between
        # its body and a front leg, dropped here, left the leg 13 cm from the rest and an obstacle
        # of its own (dense: in every frame)
        if area * px_m * px_m < 0.25 * cfg.min_area_m2:
            continue
        if floor is not None and above is not None and float(stats.percentile(gh, 95)) < \
                cfg.min_height_m + _floor_doubt(floor, med, fB, doubt_deg):
            continue  # nothing of it stands up: a marking, a shadow, a mat
        pts = _points(gy, gx, gd, model, step)
        if confidence is not None:
            valid: float = float(confidence[gy * step, gx * step].astype(np.float32).sum() / 255.0)
        else:  # what the matcher decided itself: not what it carried into a plain window (flat)
            valid = int(np.count_nonzero(g0 if fw is None else g0 * ~fw[gy, gx]))
        filled = 0
        if floor is not None and cfg.fill_to_floor:
            mask = np.zeros((y1 - y0, x1 - x0), bool)
            mask.ravel()[(gy - y0) * (x1 - x0) + (gx - x0)] = True  # by flat index: no 2-D scatter
            extra = _fill_to_floor(mask, dm[y0:y1, x0:x1], x0, y0, floor, cfg,
                                   model, step, doubt_deg)
            if extra is not None:
                pts = np.concatenate([pts, extra])
                filled = len(extra)
                y1 = max(y1, min(h, int(np.ceil((float(np.max(extra[:, 1] / extra[:, 2])) * f + model.cy) / step)) + 1))
        lo, hi = stats.percentile(pts[::max(1, len(pts) // regions.STAT_SAMPLES)], [2, 98])
        groups = frozenset({family[int(gl)]}) if int(gl) in family else frozenset()
        origin = family.get(int(gl), int(gl))  # its label before the depth split
        cuts = frozenset({cut_from[origin]}) if origin in cut_from else frozenset()
        found.append(regions.Region(pts, lo, hi, (x0, y0, x1, y1), area, valid, gd.astype(np.float64), filled,
                                    groups, cuts))
    found = regions.absorb_contained(regions.merge_close(found, cfg.merge_gap_m, cfg.merge_gap_depth_m),
                                     cfg.merge_gap_m, model, step)
    found = regions.join_cut(found, [side_cut(r.bbox, float(stats.median(r.disparities)))[0] for r in found],
                             cfg.merge_gap_depth_m)
    out: list[Detection] = []
    points: list[np.ndarray] = []
    for r in found:
        if floor is None and cfg.floor_removal and _floor_like(r.pts):
            continue  # no ground to tell it by: a patch of floor is still no obstacle (the list says no-ground)
        size = r.hi - r.lo
        px_m = float(np.mean(r.pts[:, 2])) / f * step
        d_med = float(stats.median(r.disparities))
        # a region cut by a side of the view shows only part of its face: its area says nothing of
        # the thing's (a box cut by bm's blind band, 4 cm of it in view from 0.5 m up, was in no
        # list and the list said nothing). A sliver as tall as an obstacle is listed, truncated; a
        # speck (a person's hand beside the band, the rest of the arm in it) is not
        sliver = size[1] >= cfg.min_height_m and any(side_cut(r.bbox, d_med))
        if max(size[0], size[1]) < cfg.min_size_m or (r.area * px_m * px_m < cfg.min_area_m2 and not sliver):
            continue
        out.append(detection(r.pts, r.lo, r.hi, r.bbox, r.area + r.filled, d_med,
                             float(min(1.0, r.valid / max(1, r.area)))))
        points.append(r.pts)
    if cfg.edge_refine and image is not None and out:
        out = [_refine_box(det, image) for det in out]
    return LayersFrame(out + dropped[0], points + dropped[1], floor, estimate, floor_points)


def merge_detections(dets: list[Detection], points: list[np.ndarray], model: camera.RectifiedModel
                     ) -> tuple[Detection, np.ndarray]:
    """Several detections of one object as one: the statistics of segment_frame over the union of
    their camera-frame points (n_i, 3) m. -> (the detection, its points)."""
    pts = np.concatenate(points)
    sub = pts[::max(1, len(pts) // regions.STAT_SAMPLES)]
    lo, hi = stats.percentile(sub, [2, 98])
    area = sum(d.area_px for d in dets)
    return Detection(position_m=stats.mean0(pts), size_m=np.maximum(hi - lo, 0.0),
                     distance_m=min(float(d.distance_m) for d in dets),
                     bbox_px=(min(d.bbox_px[0] for d in dets), min(d.bbox_px[1] for d in dets),
                              max(d.bbox_px[2] for d in dets), max(d.bbox_px[3] for d in dets)),
                     area_px=area, disparity_px=float(np.median([d.disparity_px for d in dets])),
                     confidence=float(sum(d.confidence * d.area_px for d in dets) / max(1, area)),
                     cut=tuple(any(d.cut[k] for d in dets) for k in range(3)),  # type: ignore[arg-type]
                     edges=_edges(sub, model)), pts


PIVOT_HEIGHTS = 2.0
MIN_DOUBT_DEG = 0.02  # below this the floor band widens by less than a centimetre within 20 m


def _tilt_doubt(z, height_m: float, doubt_deg: float):
    """Height (m) by which a floor whose tilt is doubt_deg off misses at depth z: nothing within
    PIVOT_HEIGHTS camera heights (the floor seen more than ~27 deg below the horizon, densely: where
    the fit rests), growing beyond (a real road is no plane: its grade changes over tens of metres)."""
    return np.maximum(z - np.float32(PIVOT_HEIGHTS * height_m), 0) * np.float32(np.tan(np.radians(doubt_deg)))


def _floor_doubt(floor: FloorPlane, d: float, fB: float, doubt_deg: float) -> float:
    """How far the fitted floor can be off, in height, at the depth of disparity d: its tilt's doubt
    and half a pixel of disparity. A top lower than min_height_m plus this cannot be told from the floor."""
    return float(_tilt_doubt(fB / max(d, 1e-3), floor.height_m, doubt_deg)) + floor.height_m * 0.5 / max(d, 1e-3)


def _floor_like(pts: np.ndarray, max_tilt_deg: float = 45.0) -> bool:
    """A region whose points lie on one plane (within 5 cm + 1 % of their depth) facing the camera's
    y axis (within max_tilt_deg): a patch of floor or road, told apart without a ground estimate."""
    sub = pts[::max(1, len(pts) // regions.STAT_SAMPLES)]
    if len(sub) < 10:
        return False
    c = sub - sub.mean(0)
    w, V = np.linalg.eigh(c.T @ c / len(c))
    thin = np.sqrt(max(float(w[0]), 0.0)) < 0.05 + 0.01 * float(np.median(sub[:, 2]))
    return bool(thin and abs(V[1, 0]) > np.cos(np.radians(max_tilt_deg)))


def _edges(points: np.ndarray, model: camera.RectifiedModel) -> np.ndarray:
    """(2, 3): the mean of an object's points in its leftmost and its rightmost 5 % of image columns."""
    u = points[:, 0] / points[:, 2]
    lo, hi = stats.percentile(u, [5, 95])
    return np.stack([stats.mean0(points[u <= lo]), stats.mean0(points[u >= hi])])


def _points(ys: np.ndarray, xs: np.ndarray, d: np.ndarray, model: camera.RectifiedModel, step: int) -> np.ndarray:
    """Camera-frame points (n, 3), m, of working-grid pixels (ys, xs) with disparities d."""
    z = model.focal_px * model.baseline_m / d.astype(np.float64)
    return np.stack([(xs * step - model.cx) * z / model.focal_px, (ys * step - model.cy) * z / model.focal_px, z], 1)


def segment(disparity: np.ndarray, model: camera.RectifiedModel, cfg: SegmenterSettings | None = None,
            image: np.ndarray | None = None, floor_out: list | None = None, mount: Mount | None = None
            ) -> list[Detection]:
    """One frame on its own (a fresh ground estimate, with `mount` as its prior): detections, camera
    frame. floor_out: if a list, the floor plane used (or None) is appended to it."""
    cfg = cfg or SegmenterSettings()
    frame = segment_frame(disparity, model, cfg, ground=GroundEstimator(cfg, mount), image=image)
    if floor_out is not None:
        floor_out.append(frame.floor)
    return frame.detections


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
