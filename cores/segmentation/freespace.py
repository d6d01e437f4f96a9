"""What the robot may drive on: a 2D occupancy grid on the ground, robot base frame.

    floor points + obstacle points (camera frame) + the camera mount  ->  FreeSpace cells

A cell is free (0) where the camera saw floor in it, occupied (100) where an obstacle's points
stand in it (obstacles win), unknown (-1) where nothing was seen: behind obstacles, outside the
field of view, beyond the vision range, below the camera's near edge. The grid covers x from the
base origin to the vision range ahead and y as far to each side as the field of view reaches there,
laid out as ROS nav_msgs/OccupancyGrid (see common/messages.py FreeSpace).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cores import camera
from cores.segmentation.mount import FloorPlane, Mount
from cores.segmentation.settings import SegmenterSettings

UNKNOWN, FREE, OCCUPIED = -1, 0, 100  # cell values (nav_msgs/OccupancyGrid's)
MAX_CELLS = 4096  # per side (FreeSpace's bound); a coarser cell is used rather than a larger grid
MAX_FLOOR_SAMPLES = 1_000_000  # points of drivable floor per frame, at most
# where the floor seen ends is known to half a pixel of disparity (the tracker's centroid noise, measured
# on a real street): the free space stops that much short of it
END_NOISE_PX = 0.5
# A gap narrower than this between two things standing in the image is no way through (no robot fits)
# and may be no gap at all: read with dense's 11 px window, the low-faces cabinet's plain front stood in
# runs of columns with 7 columns (6 cm) of nothing standing between them, where the window had carried
# the floor up its foot, seen up to 20 cm behind the face: the cells behind it were free
NARROW_GAP_M = 0.15


@dataclass
class Grid:
    resolution_m: float
    width: int  # cells along base x
    height: int  # cells along base y
    origin_m: tuple[float, float]
    cells: np.ndarray  # (height, width) int8


def layout(model: camera.RectifiedModel, mount: Mount, range_m: float, resolution_m: float
           ) -> tuple[float, int, int, tuple[float, float]]:
    """(resolution, width, height, origin) of the grid that covers what the camera can see."""
    half_fov = np.arctan2(max(model.cx, model.width - model.cx), model.focal_px)
    half_y = min(range_m, range_m * float(np.tan(half_fov))) + abs(mount.y_m)
    x0 = min(0.0, mount.x_m)
    x_len = range_m + max(0.0, mount.x_m) - x0
    res = max(resolution_m, x_len / MAX_CELLS, 2 * half_y / MAX_CELLS)
    width = max(1, int(np.ceil(x_len / res)))
    height = max(1, int(np.ceil(2 * half_y / res)))
    return res, width, height, (x0, -height * res / 2)


def occupancy(floor_points: np.ndarray, obstacle_points: list[np.ndarray], mount: Mount,
              model: camera.RectifiedModel, range_m: float, resolution_m: float) -> Grid:
    """floor_points: (k, 3) camera-frame points seen on the floor; obstacle_points: per obstacle,
    its (n, 3) camera-frame points. -> the grid."""
    res, width, height, origin = layout(model, mount, range_m, resolution_m)
    cells = np.full(height * width, UNKNOWN, np.int8)

    def index(points_camera: np.ndarray) -> np.ndarray:
        if not len(points_camera):
            return np.zeros(0, np.int64)
        p = mount.to_base(points_camera)
        col = np.floor((p[:, 0] - origin[0]) / res).astype(np.int64)
        row = np.floor((p[:, 1] - origin[1]) / res).astype(np.int64)
        ok = (col >= 0) & (col < width) & (row >= 0) & (row < height)
        row *= width
        row += col
        return row.take(np.flatnonzero(ok))  # one selection of the flat index, by index (faster than a mask)

    cells[index(floor_points)] = FREE
    for points in obstacle_points:  # each apart: no copy of them all
        cells[index(points)] = OCCUPIED
    return Grid(res, width, height, origin, cells.reshape(height, width))


def drivable(floor: FloorPlane, df: np.ndarray, seen_floor: np.ndarray, standing: np.ndarray, dk: np.ndarray,
              model: camera.RectifiedModel, cfg: SegmenterSettings, step: int, gaps: Gaps | None = None) -> np.ndarray:
    """Points of the floor plane the robot may drive on, camera frame: along each image column (a
    ray on the ground), the floor from the image's bottom edge out to the farthest floor point seen
    in that column (each at the nearer of its measured depth and the plane's along its ray), but not
    beyond anything standing in it (any pixel above the floor margin, obstacle or not) or, for a thing
    3 columns wide or more, within the median filter's reach beside it or in a gap too narrow to pass
    between two (spread_sides), nor where
    anything standing is nearer on its vertical, which leaves the column when the camera rolls or
    pitches (_open_above), nor beyond the vision range. Block matching sees little of a smooth road,
    so the floor between seen points counts as seen; within near_field_m only where the rows between
    are too few to hide anything min_height_m tall (floor_gaps; gaps: computed already, or None): a
    longer unmeasured stretch, the bottom edge's included, is not known. Farther, every stretch
    counts, as the robot will see it again nearer: block matching leaves most of a smooth road
    unmeasured (karlsruhe, bm: half the columns from the image's bottom edge at 4 m to the first
    road point seen). A plain crate left no pixel, and the floor seen beyond it made it free space."""
    fB = model.focal_px * model.baseline_m

    def depth(d: np.ndarray) -> np.ndarray:  # float32 f B / d (inf where d <= 0): the same of a column's
        with np.errstate(divide="ignore"):  # extreme disparity as the extreme of the column's depths
            return np.where(d > 0, fB / np.maximum(d, 1e-6), np.inf)
    # the farthest floor seen (0: none), the nearest thing standing (all standing pixels have a disparity).
    # A floor pixel vouches for the floor out to the nearer of where it was measured and where the plane
    # puts its ray: a face's lowest rows, within floor_margin_m of the floor, pass for floor, and the plane
    # carries their rays on past the face (by Z h / (H - h): 8 cm at 3 m for a 3 cm row from a 1 m high
    # camera): the free space reached under the low-faces cabinet with downsample 1 or 4, or a 1280x720 rig.
    # And only to within its noise: half a pixel of disparity nearer (on a 640x360 rig with an 85 deg field of
    # view, 10 cm at 3 m, the floor seen beside the low-faces cabinet's side was free 5-8 cm inside it)
    far = depth(np.minimum.reduce(np.maximum(df, dk), axis=0, where=seen_floor, initial=np.inf)
                + np.float32(END_NOISE_PX))
    # The nearest thing standing stops its column and the columns beside it within the median filter's
    # reach: where a thing's side ends in the image is known to no better (dense's and bm's windows carry
    # the floor's depth a column or two into a side), and the floor seen in a column just past a side
    # lies behind the thing's face (sway-pivot, dense: the crate's first standing column was 2 right of
    # its side; the floor seen there, 1.5 cm inside the crate's back corner, made free a cell three
    # quarters of which lies in it). And the columns of a gap too narrow to pass (NARROW_GAP_M).
    near_standing = depth(spread_sides(np.maximum.reduce(dk, axis=0, where=standing, initial=0),
                                       cfg.median_px // 2, NARROW_GAP_M / (model.baseline_m * step)))
    limit = np.minimum(np.minimum(far, near_standing), cfg.range_for(model))
    near = depth(df[-1])  # the floor at the image's bottom edge
    cols = np.nonzero(np.isfinite(near) & (limit > near))[0]
    if not cols.size:
        return np.zeros((0, 3))
    # march along each column's ray on the floor in steps of half a free-space cell (coarser when a
    # wide image and a long range would make more than MAX_FLOOR_SAMPLES points)
    longest = float((limit[cols] - near[cols]).max())
    spacing = max(0.5 * cfg.freespace_resolution_m, longest * cols.size / MAX_FLOOR_SAMPLES)
    n = int(np.ceil(longest / spacing)) + 1
    z = near[cols][:, None] + spacing * np.arange(n)[None, :]
    z = np.where(z <= limit[cols][:, None], z, np.nan).ravel()
    u = np.repeat(cols.astype(np.float64) * step, n)
    ok = np.flatnonzero(np.isfinite(z))  # by index: faster than two masks
    z, u = z.take(ok), u.take(ok)
    f = model.focal_px
    # the floor's pixel row at depth z in column u: a u + b v + c = f B / z
    d = fB / z
    v = (d - floor.a * u - floor.c) / floor.b
    h = df.shape[0]
    vw = np.clip(np.floor(v / step).astype(np.int64), 0, h - 1)
    uw = u / step
    gaps = gaps or floor_gaps(seen_floor, df, model.baseline_m, cfg.min_height_m, step)
    unknown = gaps.mask & (df > np.float32(fB / max(cfg.near_field_m, 1e-3)))  # such stretches in the near field
    keep = ~unknown.ravel()[vw * df.shape[1] + uw.astype(np.int64)]
    keep &= _open_above(uw, v / step, d, standing, dk, vertical_point(floor, model, step))
    z, u, v = z[keep], u[keep], v[keep]
    return np.stack([(u - model.cx) * z / f, (v - model.cy) * z / f, z], 1)


def spread_sides(stand_d: np.ndarray, reach: int, narrow: float = 0.0) -> np.ndarray:
    """Per column the disparity of the nearest thing standing in it (0: none) -> the same with each
    thing's sides carried `reach` columns out, and a gap between two things narrower than `narrow`
    times the farther one's disparity (columns per px; NARROW_GAP_M / (B step): the gap's width in
    metres at that depth) closed at the nearer one's disparity (what a window carried into a plain
    face can be the floor behind it, farther than the face's both sides). Only things' (3 columns wide
    or more): a speck of the matcher's noise on a road stops its own column alone."""
    row = stand_d[None, :]
    things = cv2.erode(row, np.ones((1, 3), np.uint8))
    out = stand_d
    if narrow > 0:
        at = np.flatnonzero(cv2.dilate(things, np.ones((1, 3), np.uint8))[0] > 0)  # the things' columns
        if at.size > 1:
            gap = np.diff(at) - 1
            dl, dr = stand_d[at[:-1]], stand_d[at[1:]]
            close = np.flatnonzero((gap > 0) & (gap <= narrow * np.minimum(dl, dr)))
            if close.size:
                out = stand_d.copy()
                for k in close:
                    seg = out[at[k] + 1:at[k + 1]]
                    np.maximum(seg, max(dl[k], dr[k]), out=seg)
    if reach <= 0:
        return out
    sides = cv2.dilate(things, np.ones((1, 2 * reach + 3), np.uint8))
    return np.maximum(out[None, :], sides)[0]


def vertical_point(floor: FloorPlane, model: camera.RectifiedModel, step: int) -> np.ndarray:
    """Where every vertical line meets in the working grid's image: the image of the floor's normal,
    homogeneous (x, y, w). w = 0 (a point at infinity) for a camera that does not pitch: verticals
    are parallel, image columns unless it rolls; a camera pitched down sees them converge below the
    image (3.9 deg at the side of a 640 px image pitched 8 deg down), one that rolls sees them lean."""
    n, _ = floor.normal_height(model.focal_px, model.cx, model.cy, model.baseline_m)
    f = model.focal_px
    return np.array([(f * n[0] + model.cx * n[2]) / step, (f * n[1] + model.cy * n[2]) / step, n[2]])


def _open_above(uw: np.ndarray, vw: np.ndarray, d: np.ndarray, standing: np.ndarray, dk: np.ndarray,
                vertical: np.ndarray) -> np.ndarray:
    """For floor samples at working-grid (uw, vw) with disparity d: False where something standing
    is nearer on the sample's vertical in the image (vertical: vertical_point).

    drivable stops each column's floor at the nearest thing standing in the column: the column is
    the vertical through the floor only for a camera that neither rolls nor pitches. Rolled (a
    ballbot leans by 10 degrees), the vertical above the floor beside a table runs through the table
    top in the next columns, and the floor under its edge was free (the sway: up to 11 cm under the
    top); pitched 12 degrees down, the same beside a table at the image's side. The standing
    disparities are resampled along the verticals, one per column (the one through that column at
    the middle row), and a sample is open when nothing standing on its vertical is nearer: the
    column rule, along the vertical."""
    h, w = dk.shape
    mid = 0.5 * h
    vx, vy, vz = (float(x) for x in vertical)
    den = vy - mid * vz
    if abs(den) < 1e-9 * max(1.0, abs(vx)):  # verticals lie along the rows: a camera looking straight down
        return np.ones(uw.shape, bool)

    def crossing(u: np.ndarray, v: np.ndarray) -> np.ndarray:  # the middle row's column of the vertical through (u, v)
        t = (v - mid) / den
        with np.errstate(divide="ignore", invalid="ignore"):
            return (u - t * vx) / (1.0 - t * vz)
    # one resampled column per vertical that crosses the image: those through its sides lean out of
    # the middle row's span (converging below the image, they spread above it)
    ends = crossing(np.array([0.0, w - 1.0, 0.0, w - 1.0]), np.array([0.0, 0.0, h - 1.0, h - 1.0]))
    first = int(np.floor(max(-w, np.nanmin(ends)))) if np.isfinite(ends).any() else 0
    last = int(np.ceil(min(2 * w, np.nanmax(ends)))) if np.isfinite(ends).any() else w - 1
    c = np.arange(min(first, 0), max(last, w - 1) + 1, dtype=np.float64)
    slope = (vx - c * vz) / den  # du/dv of the vertical through (c, mid)
    if np.abs(slope).max() * h < 0.5:  # no vertical drifts half a working column over the image: columns
        return np.ones(uw.shape, bool)
    # float32 maps and OpenCV's column max: a sixth of the time of float64 maps and numpy's
    rows = np.arange(h, dtype=np.float32)[:, None] - np.float32(mid)
    map_x = c.astype(np.float32)[None, :] + rows * slope.astype(np.float32)[None, :]
    map_y = np.repeat(np.arange(h, dtype=np.float32)[:, None], c.size, axis=1)
    on_vertical = cv2.remap(dk * standing, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                            borderValue=0.0)
    nearest = cv2.reduce(on_vertical, 0, cv2.REDUCE_MAX).ravel()
    col = np.rint(crossing(uw, vw)) - c[0]
    inside = np.isfinite(col) & (col >= 0) & (col < c.size)
    return ~(inside & (nearest.take(np.clip(np.nan_to_num(col), 0, c.size - 1).astype(np.int64)) > d))


@dataclass
class Gaps:
    """Stretches of a working grid's columns without floor seen, each ending (below) at a floor row
    seen or the image's bottom edge, with at least as many rows as a face min_height_m tall standing
    at that end would cover (min_height_m f / Z = min_height_m d / B pixels, and 2): an obstacle that
    tall may hide in one; a shorter stretch is the matcher missing smooth floor."""

    mask: np.ndarray  # (h, w) bool: rows inside such a stretch
    # (w,) int64: the first row of a column's stretch that reaches the image's bottom edge (-1: none), what
    # stands nearer than the floor there leaves: its foot is below the image
    bottom_start: np.ndarray
    # (ENDS, w) int64: the floor rows just below a column's ENDS lowest such stretches, lowest first (-1:
    # none)
    ends: np.ndarray


ENDS = 3  # Gaps.ends: the lowest stretches of a column a plain face's foot is looked for at (blank.py)


def floor_gaps(seen_floor: np.ndarray, df: np.ndarray, baseline_m: float, min_height_m: float, step: int) -> Gaps:
    """seen_floor: (h, w) bool; df: the floor's disparity there. -> Gaps (by runs: one pass each way)."""
    h, w = seen_floor.shape
    t = np.ones((w, h + 2), np.int8)  # columns as rows, with floor at the virtual rows -1 and h
    t[:, 1:-1] = seen_floor.T
    edge = np.diff(t, axis=1)  # -1 where a stretch without floor starts, +1 where it ends (exclusive)
    cols, starts = np.divmod(np.flatnonzero(edge < 0), h + 1)
    ends = np.flatnonzero(edge > 0) % (h + 1)  # runs alternate: the k-th end closes the k-th start
    near = df[np.minimum(ends, h - 1), cols]  # the image's bottom edge stands in for a floor row below
    long = (ends - starts) >= np.maximum(min_height_m * np.maximum(near, 0) / (baseline_m * step), 2)
    cols, starts, ends = cols[long], starts[long], ends[long]
    inside = np.zeros((w, h + 1), np.int8)
    inside[cols, starts] = 1  # no two runs share a start or an end: a floor row lies between them
    inside[cols, ends] = -1
    mask = np.cumsum(inside[:, :h], axis=1, dtype=np.int8).T > 0
    below = ends < h
    # per column the floor rows just below its ENDS lowest stretches, lowest first (runs come in column
    # order, top to bottom within one: a column's k-th from the bottom is k before its last)
    ends_below, cols_below = ends[below], cols[below]
    last = np.flatnonzero(np.r_[cols_below[1:] != cols_below[:-1], True]) if cols_below.size else cols_below
    lowest = np.full((ENDS, w), -1, np.int64)
    for k in range(ENDS):
        i = last - k
        ok = i >= 0
        i = i[ok]
        ok_col = cols_below[i] == cols_below[last[ok]]  # still the same column k runs up
        lowest[k, cols_below[i[ok_col]]] = ends_below[i[ok_col]]
    bottom_start = np.full(w, -1, np.int64)
    bottom_start[cols[~below]] = starts[~below]  # a column has one stretch at most that reaches row h
    return Gaps(mask, bottom_start, lowest)
