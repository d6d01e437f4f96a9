"""The regions the default segmenter (layers.py) finds, and how they become objects: regions whose 3D
extents come close are one (the parts of one object the image shows apart: a chair's back leg seen
between its front legs, the stretches of a fence), except the depth layers and the low-bridge
pieces a group was cut into, and things whose extents come close but whose points do not
(merge_close); a small region mostly inside a larger one's box is part of it, seen through it, or
in front of it (absorb_contained).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import cdist

from cores import camera
from cores.segmentation import stats

APART_WIDTH_M = 0.25  # as wide as a person across the view (merge_close)
STAT_SAMPLES = 1500  # percentiles of a region are taken on at most ~2x this many of its points


@dataclass
class Region:
    pts: np.ndarray  # (n, 3) camera-frame points (m) of the region's inlier pixels
    lo: np.ndarray  # (3,) 2nd percentile of the points
    hi: np.ndarray  # (3,) 98th percentile
    bbox: tuple[int, int, int, int]  # working-resolution x0, y0, x1, y1 (exclusive)
    area: int  # working-resolution pixels
    valid: float  # of which with a valid raw disparity (with a confidence map: its sum / 255)
    disparities: np.ndarray  # (n,) px
    filled: int = 0  # points added by layers._fill_to_floor (included in pts)
    groups: frozenset = frozenset()  # the split groups (split_layers) it holds a depth layer of
    cuts: frozenset = frozenset()  # the touching groups cut at a low bridge (cells.py) it holds a piece of


def merge_close(regions: list[Region], gap_m: float, depth_gap_m: float = 0.0) -> list[Region]:
    """Merge regions whose 3D extents come within gap_m of each other across the view (x, y) and
    within max(gap_m, depth_gap_m) along it (z): the parts of one object that the image shows
    apart (a chair's back leg seen between its front legs; a fence or a wall along the road seen
    obliquely, whose texture-poor stretches the matcher leaves out). Where the extents say little of
    how close the things come, their points must touch: two depth layers of one split group, boxes
    sharing image columns (one in front of the other), and two things each as wide as a person
    side by side in the image (abut: only depth parts them)."""
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
    close = np.all(gap <= np.array([gap_m, gap_m, max(gap_m, depth_gap_m)]), axis=2)
    wide = (hi - lo)[:, 0] >= APART_WIDTH_M
    held = [set(r.groups) for r in regions]  # per root: the split groups it holds a layer of
    cut = [set(r.cuts) for r in regions]  # per root: the cut groups it holds a piece of
    for i, j in zip(*np.nonzero(np.triu(close, 1))):
        a, b = root(int(i)), root(int(j))
        # two depth layers of one group (a person behind another) are not joined again by the gap
        # along the view that joins a fence's stretches, only where they touch: their points, not
        # just their boxes (a person walking past a table's back corner)
        if a == b or cut[a] & cut[b]:
            continue  # two pieces of a group cut between two things (cells.py) touch by construction
        layers = bool(held[a] & held[b])
        # boxes that share image columns are apart along the view only: one stands in front of the
        # other, and how close the boxes come says little of how close the things do (a table's
        # top reaches back over the floor where a person walks behind it). The slack along the view
        # is for one surface receding from the camera (a fence, a wall seen obliquely), whose
        # stretches lie side by side in the image: these two are joined only where their points touch
        in_front = share_columns(regions[i], regions[j])
        if (layers or in_front) and gap[i, j, 2] > gap_m:
            continue
        # two things each as wide as a person that meet side by side in the image, where only the depth
        # parts them, are joined only where their points touch too, within the slack along the view: a
        # person and one 0.5 m behind seen from 1.2 m at 20 deg down came within 7 cm by their boxes
        # (each reaching into the other's depths by the ramp between them), 0.4 m apart by their points,
        # and the one behind was in no list. Pieces apart in the image (a facade seen obliquely, its
        # stretches left out between them) still join by their boxes
        if layers or in_front:
            within = gap_m
        elif wide[i] and wide[j] and abut(regions[i], regions[j]):
            within = max(gap_m, depth_gap_m)
        else:
            within = None
        if within is not None and not touch(regions[i], regions[j], within):  # one point search a pair
            continue
        parent[a] = b
        held[b] |= held[a]
        cut[b] |= cut[a]
    groups: dict[int, list[Region]] = {}
    for i, r in enumerate(regions):
        groups.setdefault(root(i), []).append(r)
    out = []
    for g in groups.values():
        if len(g) == 1:
            out.append(g[0])
            continue
        out.append(union(g))
    return out


def join_cut(regions: list[Region], cut: list[bool], gap_m: float) -> list[Region]:
    """Join regions that a side of the view cuts (cut: per region, on the same side), share image
    columns there, and whose 3D extents come within gap_m of each other, where one of them is a sliver
    (narrower across the view than APART_WIDTH_M): the pieces of one thing, of which the view shows a
    sliver. Beside the edge of what the matcher sees the sliver is a column or two of the working grid,
    and the median filter takes its thinner stretches:
    people-border's person cut by the left side, with bm matching its band, was its arm (1.22 m away)
    and a 2-4 px sliver of its leg (1.35 m) whose upper rows had gone, 0.19 m apart up the view, two
    obstacles in every frame. Wider pieces come apart for what they are (the street's railing and the
    people in front of it, cut by sgbm's blind band, were joined into things 20 m long)."""
    idx = [i for i, c in enumerate(cut) if c]
    if len(idx) < 2:
        return regions
    parent = {i: i for i in idx}

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for a, i in enumerate(idx):
        for j in idx[a + 1:]:
            p, q = regions[i], regions[j]
            gap = np.maximum(p.lo - q.hi, q.lo - p.hi)
            sliver = min(p.hi[0] - p.lo[0], q.hi[0] - q.lo[0]) < APART_WIDTH_M
            if sliver and share_columns(p, q) and (gap <= gap_m).all() and root(i) != root(j):
                parent[root(i)] = root(j)
    groups: dict[int, list[Region]] = {}
    for i in idx:
        groups.setdefault(root(i), []).append(regions[i])
    if len(groups) == len(idx):
        return regions
    return [r for i, r in enumerate(regions) if not cut[i]] + [g[0] if len(g) == 1 else union(g)
                                                               for g in groups.values()]


def overlap(p: Region, q: Region) -> tuple[int, int]:
    """How far p's and q's image boxes overlap: (columns, rows), negative where they lie apart."""
    return (min(p.bbox[2], q.bbox[2]) - max(p.bbox[0], q.bbox[0]),
            min(p.bbox[3], q.bbox[3]) - max(p.bbox[1], q.bbox[1]))


def abut(p: Region, q: Region) -> bool:
    """Whether p's and q's image boxes meet side by side: their columns overlap or touch, and their rows overlap."""
    cols, rows = overlap(p, q)
    return cols >= 0 and rows > 0


def share_columns(p: Region, q: Region, share: float = 0.25) -> bool:
    """Whether p's and q's image boxes overlap in columns by at least `share` of the narrower one's width."""
    cols = overlap(p, q)[0]
    return cols >= share * min(p.bbox[2] - p.bbox[0], q.bbox[2] - q.bbox[0])


def touch(p: Region, q: Region, gap_m: float, samples: int = 400) -> bool:
    """Whether some point of p comes within gap_m of some point of q (on up to `samples` of each)."""
    a = p.pts[::max(1, len(p.pts) // samples)]
    b = q.pts[::max(1, len(q.pts) // samples)]
    # scipy's distances in C: 1.1 ms for 400 x 400 points, against 14 ms for numpy's (400, 400, 3) temporaries
    return bool((cdist(a, b, "sqeuclidean") <= gap_m * gap_m).any())


def absorb_contained(regions: list[Region], gap_m: float, model: camera.RectifiedModel, step: int,
                      inside: float = 0.8) -> list[Region]:
    """A region whose image box lies mostly (inside) within a larger region's box is, compared
    with the larger one's depth in the same image columns: part of it (the depths meet: merged),
    seen through it (farther: a car's windows, a shelter's glass; dropped, the nearer object is
    what stands in the way), or in front of it (kept: a chessboard on its stand before a wall)."""
    if len(regions) < 2:
        return regions
    order = sorted(range(len(regions)), key=lambda i: -regions[i].area)
    alive = [True] * len(regions)
    for ci in order:
        if not alive[ci]:
            continue
        c = regions[ci]
        for ri in order:
            r = regions[ri]
            if ri == ci or not alive[ri] or r.area >= c.area:
                continue
            ix, iy = (max(0, k) for k in overlap(r, c))
            own = (r.bbox[2] - r.bbox[0]) * (r.bbox[3] - r.bbox[1])
            if ix * iy < inside * own:
                continue
            u = c.pts[:, 0] / c.pts[:, 2] * model.focal_px + model.cx  # full-resolution columns
            there = (u >= r.bbox[0] * step) & (u < r.bbox[2] * step)
            if not there.any():
                continue
            zc = stats.percentile(c.pts[there, 2], [10, 90])
            zr = float(stats.median(r.pts[:, 2]))
            tol = gap_m + 0.02 * zr
            hidden_top = capped(c, r, model, step)
            if r.groups & c.groups and not hidden_top:
                continue  # two depth layers of one group: one stands behind the other, both are there
            if zr > zc[1] + tol:
                # behind it and seen under it (its top hidden by it: a table's back leg under the top,
                # beside or between the front legs) or seen through it (framed by it: a car's windows)
                # it is dropped: the nearer object stands in the way. Unless it is whole in a gap: it
                # stands on the floor seen there and its own top is seen (a box between a person's
                # legs); what is seen through a car's windows ends at their lower edge
                if hidden_top or (encloses(c, r, model, step) and not r.filled):
                    alive[ri] = False
            elif zr >= zc[0] - tol:
                alive[ri] = False
                c = regions[ci] = union([c, r])
    return [r for r, a in zip(regions, alive) if a]


def encloses(c: Region, r: Region, model: camera.RectifiedModel, step: int) -> bool:
    """Whether c's points surround r's box in the image: on both sides of it within its rows, or
    above and below it within its columns. What is seen through an object (a car's windows, a
    gap between a person's legs) is framed by it; a person standing behind a chair, seen above and
    beside its back, is not, though the chair's box (its back reaching up, its legs out) holds
    theirs."""
    u = c.pts[:, 0] / c.pts[:, 2] * model.focal_px + model.cx
    v = c.pts[:, 1] / c.pts[:, 2] * model.focal_px + model.cy
    x0, y0, x1, y1 = (k * step for k in r.bbox)
    rows, cols = (v >= y0) & (v < y1), (u >= x0) & (u < x1)
    return bool(((rows & (u < x0)).any() and (rows & (u >= x1)).any())
                or ((cols & (v < y0)).any() and (cols & (v >= y1)).any()))


def capped(c: Region, r: Region, model: camera.RectifiedModel, step: int, rows: int = 10) -> bool:
    """Whether c's points lie right above r's box (within `rows` working rows of its top) across
    most of its columns: r's top is hidden by c, r may reach on up behind it. (A few of c's points
    there are the ragged edge of the frame beside r, not a cap over it.) Ten rows, not three: a
    table's top seen from above has depth, and its back leg's top hides up to ~20 px below the
    top's lower edge in the image (sway, frame 25)."""
    u = c.pts[:, 0] / c.pts[:, 2] * model.focal_px + model.cx
    v = c.pts[:, 1] / c.pts[:, 2] * model.focal_px + model.cy
    x0, y0, x1, _ = r.bbox
    over = (u >= x0 * step) & (u < x1 * step) & (v >= (y0 - rows) * step) & (v < (y0 + 1) * step)
    cols = np.unique((u[over] / step).astype(np.int64))
    return cols.size >= 0.5 * (x1 - x0)


def union(g: list[Region]) -> Region:
    pts = np.concatenate([r.pts for r in g])
    lo, hi = stats.percentile(pts[::max(1, len(pts) // STAT_SAMPLES)], [2, 98])
    return Region(pts, lo, hi, (min(r.bbox[0] for r in g), min(r.bbox[1] for r in g), max(r.bbox[2] for r in g),
                                 max(r.bbox[3] for r in g)), sum(r.area for r in g), sum(r.valid for r in g),
                   np.concatenate([r.disparities for r in g]), sum(r.filled for r in g),
                   frozenset().union(*(r.groups for r in g)), frozenset().union(*(r.cuts for r in g)))
