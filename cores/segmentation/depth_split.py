"""The depth-layer split of the default segmenter (layers.py): a group of the column-disparity grid
whose disparities form two peaks with a valley between them that holds only the ramp block matching
draws across an occlusion is two things one behind the other (split_layers has the rules).
"""
from __future__ import annotations

import cv2
import numpy as np

from cores import camera
from cores.segmentation.cells import LOW_M, group_cells, occupied
from cores.segmentation.settings import SegmenterSettings

_LAYER_BIN_PX = 1.0 / 16.0  # disparity histogram bins of the layer split: the matchers' sub-pixel step
_LAYER_SMOOTH_BINS = 1.0  # Gaussian smoothing of that histogram, bins (sub-pixel matching noise)
_LAYER_BAND = 0.35  # the valley band: bins below this share of the smaller peak's density
_LAYER_MAX_SPLITS = 3  # each side of a split is split again, this many levels deep at most
_LAYER_ON_TOP_M = 0.25  # a valley at most this far above the farther side's top rests on it
_LAYER_RAMP_FLANKED = 0.6  # a ramp: at least this share of its pixels between the two sides in their row


def ground_disparity(ys: np.ndarray, xs: np.ndarray, dv: np.ndarray, normal: np.ndarray, model: camera.RectifiedModel,
                     step: int) -> np.ndarray:
    """The disparity each working-grid pixel (ys, xs, disparity dv) would have at its distance along
    the ground: fB over its point's reach along the ground in the camera's forward direction (the
    optical axis with the floor's unit normal `normal`, camera frame, taken out). The optical axis of
    a pitched camera runs down through an upright thing: 20 deg down, a person 1.7 m tall spans 0.58
    m of it, as much as a person behind another, and two people 0.55 m apart 4.3 m away from 1.2 m up
    showed one hump of the histogram, its valley too shallow (people-queue). Along the ground an
    upright thing is one depth at any pitch; with the camera level the two are the same."""
    n = np.asarray(normal, np.float64)
    fwd = np.array([0.0, 0.0, 1.0]) - n[2] * n
    fwd /= max(float(np.linalg.norm(fwd)), 1e-9)
    k = np.float32(1.0 / model.focal_px)
    scale = ((xs * step - np.float32(model.cx)) * k * np.float32(fwd[0])
             + (ys * step - np.float32(model.cy)) * k * np.float32(fwd[1]) + np.float32(fwd[2]))
    return (dv / np.maximum(scale, np.float32(1e-3))).astype(np.float32)


def split_layers(ys: np.ndarray, xs: np.ndarray, dv: np.ndarray, lab: np.ndarray, cfg: SegmenterSettings,
                  model: camera.RectifiedModel, step: int, heights: np.ndarray | None = None,
                  normal: np.ndarray | None = None) -> tuple[np.ndarray, dict[int, int]]:
    """Split grouped objects that are two things one behind the other: (new labels for the grouped
    pixels, sorted by label as _group gives them, 0 = dropped; {label: the group it was split
    from} for every label of a split group, whose layers later steps do not join again by depth).

    The column-disparity grid joins cells up to a few pixels of disparity apart (one object's
    surfaces at slightly different depths; a wall seen obliquely), which far away is metres: a
    person 0.3 m behind another, a person behind a table, are one cell group. They show as two
    peaks of the group's disparity histogram (area-weighted: m^2 of surface per bin) with a valley
    between them that holds only the ramp block matching draws across the occlusion's contour, a
    band a few pixels wide. A valley splits the group when
    - its density is at most layer_valley_ratio of the smaller peak's;
    - each side holds layer_min_area_m2 of surface and a tenth of the other side's (specks of
      phantom depth beside a car or a facade stay with it), or the valley is empty over
      layer_gap_m of depth and each side holds min_area_m2 (a table's back leg, grouped with the
      person beside it, is no speck of theirs);
    - the peaks stand layer_gap_m apart in depth (a torso before the legs is one person);
    - the valley's pixels are a thin band, at most layer_bridge_px wide along most image rows
      they are in (the median row): a table top or a chair seat also fills the valley between
      front and back legs, but across the object's whole width in all its rows, and keeps it
      whole; a rail reaching back in a few rows beside a ramp along a person's whole side does not;
    - the far side is within layer_split_range_m (a far street's facades and shelters would fall
      apart into panels).
    The valley's pixels (the ramp: phantom depths) are dropped; each side may be split again, and
    each layer is then cut into the things it holds apart on the grid (apart).

    normal (the floor's unit normal, camera frame; None without a floor): a group the optical axis
    finds no valley in is looked at along the ground too (ground_disparity), where an upright thing
    is one depth at any pitch, and split there across a valley that is a ramp in its rows (flanked),
    not a surface reaching back."""
    family: dict[int, int] = {}
    if cfg.layer_valley_ratio <= 0 or lab.size == 0:
        return lab, family
    out = lab.copy()
    next_label = int(lab.max()) + 1
    fB = model.focal_px * model.baseline_m
    bridge = cfg.layer_bridge_px / step
    k = np.arange(-4, 5, dtype=np.float64)
    kernel = np.exp(-0.5 * (k / _LAYER_SMOOTH_BINS) ** 2)
    kernel /= kernel.sum()
    bounds = np.flatnonzero(np.diff(lab)) + 1
    starts, ends = np.concatenate([[0], bounds]), np.concatenate([bounds, [lab.size]])
    d_lo, d_hi = np.minimum.reduceat(dv, starts), np.maximum.reduceat(dv, starts)
    # a group spanning less depth than layer_gap_m, or all beyond layer_split_range_m, has nothing to split
    deep = (fB / np.maximum(d_lo, 1e-6) - fB / np.maximum(d_hi, 1e-6) >= cfg.layer_gap_m) & \
        (fB / np.maximum(d_hi, 1e-6) <= cfg.layer_split_range_m) & (ends - starts >= 2 * cfg.min_pixels)

    def split_group(a: int, b: int, dh: np.ndarray, ramp_guard: bool) -> bool:
        """Split the group of grouped pixels a:b by the histogram of dh (dv, or its disparity along the
        ground); ramp_guard: a valley must also look like a ramp in its rows (flanked). -> whether it split."""
        nonlocal next_label
        split = False
        todo = [(np.arange(a, b), 0)]
        while todo:
            idx, level = todo.pop()
            if level >= _LAYER_MAX_SPLITS or idx.size < 2 * cfg.min_pixels:
                continue
            d = dh[idx].astype(np.float64)
            bins = np.floor(d / _LAYER_BIN_PX).astype(np.int64)
            b0 = int(bins.min())
            rel = bins - b0
            # m^2 of surface a working pixel covers at its depth
            area = (step * model.baseline_m / dv[idx].astype(np.float64)) ** 2
            raw = np.bincount(rel, weights=area)
            hist = np.convolve(np.pad(raw, kernel.size // 2), kernel, mode="valid")
            if hist.size < 3:
                continue
            mass_left = np.cumsum(hist)
            mass_right = mass_left[-1] - mass_left + hist
            least = np.maximum(cfg.layer_min_area_m2, 0.1 * np.maximum(mass_left, mass_right))
            ok = (mass_left >= least) & (mass_right >= least)
            # a stretch of depth with no pixel at all, layer_gap_m long, is no ramp nor a hand held
            # out: what lies beyond it is a thing of its own however small (a table's back leg seen
            # past a person's side), as long as it is an obstacle's size
            # and seen with _LAYER_EMPTY_MIN_PIXELS on each side: a small thing far away is a
            # handful of pixels, split off one frame and not the next
            gap = empty_runs(raw == 0, b0, fB) >= cfg.layer_gap_m
            n_left = np.cumsum(np.bincount(rel, minlength=hist.size))
            n_right = n_left[-1] - n_left + np.bincount(rel, minlength=hist.size)
            ok |= gap & (mass_left >= cfg.min_area_m2) & (mass_right >= cfg.min_area_m2) & \
                (np.minimum(n_left, n_right) >= _LAYER_EMPTY_MIN_PIXELS)
            ok[0] = ok[-1] = False
            if not ok.any():
                continue
            lower = np.minimum(np.maximum.accumulate(hist), np.maximum.accumulate(hist[::-1])[::-1])
            ratio = np.where(ok, hist / np.maximum(lower, 1e-12), np.inf)
            i = int(np.argmin(ratio))
            if ratio[i] > cfg.layer_valley_ratio:
                continue
            band = hist <= _LAYER_BAND * lower[i]
            lo = hi = i
            while lo > 0 and band[lo - 1]:
                lo -= 1
            while hi < hist.size - 1 and band[hi + 1]:
                hi += 1
            z_far = fB / ((b0 + int(np.argmax(hist[:lo])) + 0.5) * _LAYER_BIN_PX)
            z_near = fB / ((b0 + hi + 1 + int(np.argmax(hist[hi + 1:])) + 0.5) * _LAYER_BIN_PX)
            if z_far > cfg.layer_split_range_m or z_far - z_near < cfg.layer_gap_m:
                continue
            in_band = (rel >= lo) & (rel <= hi)
            # how wide the valley's pixels are along the image rows they are in: a ramp along an
            # occlusion's contour is a few pixels wide whatever the contour's shape. The median row,
            # not the mean: a surface reaching across the valley in a few rows (a table's rail seen
            # end-on, beside a person walking behind it) must not outweigh the contour's many rows
            # (an empty valley bridges nothing: two things with clear space between them in depth)
            rows = np.unique(ys[idx[in_band]], return_counts=True)[1]
            if rows.size and np.median(rows) > bridge:
                continue
            far, near = idx[rel < lo], idx[rel > hi]
            # the ramp across an occlusion runs down the nearer thing's side where the farther one is
            # seen beside it: at heights up to the farther one's top. A valley mostly just above that
            # top (within _LAYER_ON_TOP_M) is a surface resting on the farther side (a table's top and
            # side apron seen end-on, on its back leg): one object
            if heights is not None and rests_on(ys, xs, heights, idx[in_band], far):
                continue
            # a ramp lies between the two sides in its own row: the nearer side within a ramp's width
            # on one hand, the farther on the other; a table's rail reaching back is flanked by neither,
            # mostly (the floor, its top or the wall beside it). An empty valley has no pixels to ask
            if ramp_guard and ratio[i] > 0 and flanked(ys, xs, idx[in_band], near, far, bridge) < _LAYER_RAMP_FLANKED:
                continue
            # the ramp runs along the nearer side's contour, so within its rows and a ramp's width
            # (layer_bridge_px) above or below them. What of the valley lies farther up or down is a
            # surface at those depths: the sway's table, before a person walking behind it, lost its
            # back legs below the top as the ramp, and its box ended at the top
            band = idx[in_band]
            yb, yn = ys[band], ys[near]
            ramp = (yb >= yn.min() - bridge) & (yb <= yn.max() + bridge)
            if not ramp.all():
                d_split = 0.5 * fB * (1.0 / z_far + 1.0 / z_near)
                kept = band[~ramp]
                to_near = dh[kept] >= d_split
                far, near = np.concatenate([far, kept[~to_near]]), np.concatenate([near, kept[to_near]])
                band = band[ramp]
            out[band] = 0
            out[far] = next_label
            family[next_label] = family[int(lab[a])] = int(lab[a])
            next_label += 1
            split = True
            todo += [(far, level + 1), (near, level + 1)]
        return split

    # along the optical axis first, as ever; where that finds no valley and the ground is known, along
    # the ground, where an upright thing is one depth at any pitch (ground_disparity), but only across a
    # valley that looks like a ramp: along the ground a table's side rails, seen end-on, fill the valley
    # between its legs as thinly as a ramp does. A group as shallow as one thing along the ground (one
    # person seen from above) has nothing to split there
    along: np.ndarray | None = None  # per grouped pixel, filled for the groups that need it
    for a, b in zip(starts[deep].tolist(), ends[deep].tolist()):
        if split_group(a, b, dv, False) or normal is None:
            continue
        if along is None:
            along = np.zeros_like(dv)
        g = along[a:b] = ground_disparity(ys[a:b], xs[a:b], dv[a:b], normal, model, step)
        if fB / max(float(g.min()), 1e-6) - fB / max(float(g.max()), 1e-6) >= cfg.layer_gap_m:
            split_group(a, b, along, True)
    if family:
        apart(ys, xs, dv, out, family, cfg, model, step, next_label, heights)
    return out, family


def apart(ys: np.ndarray, xs: np.ndarray, dv: np.ndarray, out: np.ndarray, family: dict[int, int],
          cfg: SegmenterSettings, model: camera.RectifiedModel, step: int, next_label: int,
          heights: np.ndarray | None = None) -> None:
    """Each layer of a split group, in place in `out` (labels) and `family`, as the things it holds
    apart: its occupied cells of the column-disparity grid grouped again as _group groups them
    (cells that touch, one cell of slack), each group holding layer_min_area_m2 of surface and
    standing up past LOW_M (heights: above the floor; a kerb's or a snow bank's stretch stays where
    it was, as cells.py keeps low things with what they touch) a label of its own in the same family
    (the rest stays with the largest). Before the split the farther
    layer joined the nearer things across itself: two people side by side 7 m from a low camera, the
    wall at 12 m seen between them one disparity bin farther, were one group and, the wall split
    off, one obstacle (people-side-far with a 20 m range: 3 of 12 people in no list, nothing said).
    New labels from next_label."""
    height = np.float32(step * model.baseline_m) / dv  # metres one working pixel covers at its depth
    for label in list(family):
        idx = np.flatnonzero(out == label)
        if idx.size < 2:
            continue
        bins = (dv[idx] / np.float32(cfg.group_bin_px)).astype(np.int32)
        x = xs[idx].astype(np.int32)
        b0, x0 = int(bins.min()), int(x.min())
        shape = (int(bins.max()) - b0 + 1, int(x.max()) - x0 + 1)
        h = height[idx]
        cell, cells = occupied(bins - b0, x - x0, h, shape, cfg.min_cell_height_m)
        cc = group_cells(cells, None)[0]  # _group's touching cells, no low-bridge cut here
        if int(cc.max()) < 2:
            continue
        comp = (cc * cells).ravel()[cell]
        area = np.bincount(comp, weights=h * h)
        area[0] = 0.0
        largest = int(np.argmax(area))
        # (area > 0: a component number bincount counts that holds no pixel, and the unoccupied 0, are not
        # things; at layer_min_area_m2 0 they were, and the street's frames raised IndexError)
        for c in np.flatnonzero((area >= cfg.layer_min_area_m2) & (area > 0)).tolist():
            if c != largest and (heights is None or float(np.percentile(heights[idx[comp == c]], 95)) >= LOW_M):
                out[idx[comp == c]] = next_label
                family[next_label] = family[label]
                next_label += 1


def flanked(ys: np.ndarray, xs: np.ndarray, band: np.ndarray, near: np.ndarray, far: np.ndarray,
            reach: float) -> float:
    """The share of a valley's pixels (indices `band`) with a pixel of the nearer side and one of the
    farther side (indices `near`, `far`) both within `reach` working pixels in their own row: most
    of an occlusion's ramp (people-queue from 1.2 m / 20 deg, bm: 0.77), little of a surface reaching
    back (the sway's table's side rails seen end-on: 0.04-0.52)."""
    if band.size == 0:
        return 0.0
    pts = np.concatenate([band, near, far])
    y0, x0 = int(ys[pts].min()), int(xs[pts].min())
    shape = (int(ys[pts].max()) - y0 + 1, int(xs[pts].max()) - x0 + 1)
    kernel = np.ones((1, 2 * int(reach) + 1), np.uint8)
    beside = np.ones(band.size, np.uint8)
    for side in (near, far):
        m = np.zeros(shape, np.uint8)
        m[ys[side] - y0, xs[side] - x0] = 1
        beside &= cv2.dilate(m, kernel)[ys[band] - y0, xs[band] - x0]
    return float(np.count_nonzero(beside)) / band.size


def rests_on(ys: np.ndarray, xs: np.ndarray, heights: np.ndarray, band: np.ndarray, far: np.ndarray) -> bool:
    """Whether most of a valley's pixels (indices `band`) lie right on top of the farther side: in
    an image column where the farther side is seen, above its topmost pixel there, and at most
    _LAYER_ON_TOP_M higher than its top in that column (a table's side rail seen end-on, on its
    back leg). The ramp across an occlusion runs down beside the farther thing, at its heights."""
    if band.size == 0 or far.size == 0:
        return False
    cols = int(max(xs[band].max(), xs[far].max())) + 1
    top_row = np.full(cols, np.iinfo(np.int64).max)
    np.minimum.at(top_row, xs[far], ys[far].astype(np.int64))
    top_h = np.full(cols, -np.inf)
    np.maximum.at(top_h, xs[far], heights[far])
    xb = xs[band]
    hb = heights[band]
    on = (ys[band] < top_row[xb]) & (hb > top_h[xb]) & (hb <= top_h[xb] + _LAYER_ON_TOP_M)
    return bool(np.mean(on) > 0.5)


_LAYER_EMPTY_PX = 2.0  # an empty valley spans at least this much disparity: far beyond matching noise
_LAYER_EMPTY_MIN_PIXELS = 100  # working pixels on each side of an empty valley split


def empty_runs(empty: np.ndarray, b0: int, fB: float) -> np.ndarray:
    """Per histogram bin (of _LAYER_BIN_PX, the first at bin b0): the depth (m) spanned by the run
    of empty bins it lies in (0 for a bin that is not empty, or in a run narrower than
    _LAYER_EMPTY_PX of disparity: far away, a few empty bins are the matcher's noise)."""
    out = np.zeros(empty.size)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], empty.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):
        if (b - a) * _LAYER_BIN_PX < _LAYER_EMPTY_PX:
            continue
        d_lo, d_hi = (b0 + a) * _LAYER_BIN_PX, (b0 + b) * _LAYER_BIN_PX
        out[a:b] = fB / max(d_lo, 1e-6) - fB / d_hi
    return out
