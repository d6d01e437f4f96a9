"""The near field: a coarse block matching of the rectified pair over a wide search, so that what
stands nearer than the matcher's own search reaches (a person stepping up to the camera, a door
the robot turned into) is seen at all.

Why: the matcher searches the disparities of the vision range only. Something nearer has a
disparity beyond the search: bm and sgbm measure nothing or garbage there, dense fills it with the
background's. The list then covers its range, empty or with a few wrong obstacles, while its view
of that range is blocked (a textured box 0.3 m from the camera: 0 obstacles, `degraded` empty with
a configured mount and fit_floor false; with sgbm, obstacles at the search's 1.05 m limit). At a
quarter of the resolution half the picture's width of disparity, matched from each image, costs
about 1.3 ms of one core a 640x480 pair and measures the near face to within 5 % (0.3-2.9 m). The segmenter
decides what of it stands above its floor (cores/segmentation/near.py). It is also the robot's own
look at the pair that every disparity map is held against (`contradicted`: the dispatcher refuses a
worker's map that puts farther what it sees nearer, the segmenter says map-contradicted of a list
made of one). No Zenoh here.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.messages import NearField
from cores import camera

COARSE_MIN_WIDTH = 160  # coarse pixels across: the scale is the largest that keeps 160 x 120 or more
COARSE_MIN_HEIGHT = 120
MAX_COARSE_DISPARITIES = 64  # coarse px: a 640 px wide pair at scale 4 searches 256 px, 0.26 m for lifecam-studio
BLOCK = 9


def near_scale(width: int, height: int) -> int:
    return max(1, min(width // COARSE_MIN_WIDTH, height // COARSE_MIN_HEIGHT))


class NearCheck:
    """Per pair: the coarse disparity map (NearField). One StereoBM, kept for the stream."""

    def __init__(self) -> None:
        self._bm: cv2.StereoBM | None = None
        self._size: tuple[int, int, int] | None = None  # coarse width, height, disparities

    def field(self, left: np.ndarray, right: np.ndarray, view: camera.RectifiedModel | None = None
              ) -> NearField | None:
        """A rectified pair (H, W[, 3]) uint8 -> its NearField; None for a pair too small to search.
        view: the rectified camera, whose outlines say what each camera saw (None: all of it)."""
        gl = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY) if left.ndim == 3 else left
        gr = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY) if right.ndim == 3 else right
        h, w = gl.shape[:2]
        s = near_scale(w, h)
        cw, ch = w // s, h // s
        nd = min(MAX_COARSE_DISPARITIES, cw // 2) // 16 * 16
        if nd < 16 or ch < BLOCK:
            return None
        if self._bm is None or self._size != (cw, ch, nd):
            bm = cv2.StereoBM.create(nd, BLOCK)
            bm.setTextureThreshold(5)
            bm.setUniquenessRatio(10)
            bm.setSpeckleWindowSize(16)  # lone mismatches are not a near face
            bm.setSpeckleRange(2)
            self._bm, self._size = bm, (cw, ch, nd)
        sl, sr = (_shrink(g, s, cw, ch) for g in (gl, gr))
        d = self._bm.compute(sl, sr).astype(np.int32)  # 1/16 coarse px; left of column nd: nothing
        # BM leaves the picture's left nd columns (40 % of it) unmatched, where something near and a
        # little left of ahead stands. Matched from the right image (both flipped), a right pixel
        # x_r with disparity dr is the left one's x_r + dr: put those into the left band.
        c0 = cw - 2 * nd  # flipped, the right image's first nd columns and the nd the search needs beside them
        fl, fr = (np.ascontiguousarray(cv2.flip(g, 1)[:, c0:]) for g in (sr, sl))
        dr = self._bm.compute(fl, fr)[:, ::-1][:, :nd].astype(np.int32)
        rows, xr = np.nonzero(dr > 0)
        xl = xr + ((dr[rows, xr] + 8) >> 4)
        band = xl < nd
        rows, xl, dband = rows[band], xl[band], dr[rows[band], xr[band]]
        d[rows, xl] = np.maximum(d[rows, xl], dband)
        masks = None if view is None or (view.width, view.height) != (w, h) else \
            camera.view_masks(view, BLOCK // 2 + 2, scale=s)
        if masks is not None:  # the seam of what a camera saw draws phantom near faces (camera.RectifiedModel)
            d[~camera.seen_by_both(d, 16, *masks)] = 0
        # quarter coarse px (BM's 1/16, rounded); <= 0: nothing; the search's last quarter clips to 255
        q = np.clip((d + 2) >> 2, 0, 255).astype(np.uint8)
        return NearField(width=cw, height=ch, image_width=w, image_height=h, data=q.tobytes())


def _shrink(gray: np.ndarray, s: int, cw: int, ch: int) -> np.ndarray:
    """The mean of each s x s block. Halving with INTER_AREA takes OpenCV's fast path: two halvings
    cost 0.02 ms a 640x480 picture against 0.13-0.2 for one quartering."""
    if s == 4 and gray.shape[1] >= 2 * 2 * cw and gray.shape[0] >= 2 * 2 * ch:
        half = cv2.resize(gray[:4 * ch, :4 * cw], (2 * cw, 2 * ch), interpolation=cv2.INTER_AREA)
        return cv2.resize(half, (cw, ch), interpolation=cv2.INTER_AREA)
    return cv2.resize(gray[:s * ch, :s * cw], (cw, ch), interpolation=cv2.INTER_AREA)


# The map against the near field. A disparity map that puts farther, over a patch of the picture
# this share of it or larger, what the coarse look at the same pair sees nearer contradicts the
# robot's own view: a worker that erased what stands (its map a floor where boxes stand), one that
# answers with an old map under a new stamp, a matcher gone wrong. The lists would be fresh, checked
# and empty. Measured, the largest such patch of honest maps (bm, sgbm, dense; bm and sgbm matching
# their band; 64-256 px searches; 11 and 31 px blocks; full and half resolution): the 15 scenes and the
# sway at most 0.17 % (noise on the blank faces, both maps), the street 0.21 % (a facade's windows the
# coarse look aliases), the room 0.12 %; maps whose near boxes and people were replaced by the floor
# behind them 1.1-9 % where those stand within 3 m (two-boxes 6.3 %, people-border 1.2 %; farther, or
# small, they slip under it: the coarse look does not resolve them), each row's far end (map_attacker's
# erase) 5-13 %; the street answered with the map of half a second before: 68-74 % of its pairs over it.
CONTRADICTED_SHARE = 0.005
CONTRADICTED_REL = 0.15  # nearer by more than this share of the coarse disparity (and two map pixels)


@dataclass(frozen=True)
class MapCells:
    """A disparity map read on its near field's grid (map_cells)."""

    coarse: np.ndarray  # (ch, cw) float32: what the near field sees in each cell, map px (0: nothing)
    nearest: np.ndarray  # (ch, cw) float32: the nearest the map measured in each cell, px (0: nothing)
    sx: float  # map px per cell, across and down
    sy: float


def map_cells(disparity: np.ndarray, near: NearField, scale: float = 1.0, invalid: float = 0.0) -> MapCells | None:
    """`disparity` ((H, W) at any resolution of the pair's: px float with NaN, or a matcher's fixed
    point (int16, uint16) of `scale` per px; NaN, or at most `invalid` (0, or a fixed-point map's
    invalid value, below every valid one): not measured) beside its near field, cell by cell. None
    for a map smaller than the field. ~0.25 ms at 640x480."""
    h, w = disparity.shape
    if near.width < 2 or near.height < 2 or h < near.height or w < near.width:
        return None
    sx, sy = w / near.width, h / near.height
    dc = np.frombuffer(near.data, np.uint8).reshape(near.height, near.width).astype(np.float32) * np.float32(sx / 4)
    # the nearest the map measured in each coarse cell (a block max, sampled at the cells' centres)
    if disparity.dtype.kind == "f":
        f = np.array(disparity, np.float32)  # a copy: NaN (not measured) becomes 0, by OpenCV (np.where: 1 ms)
        cv2.patchNaNs(f, 0.0)
    else:
        f = disparity  # OpenCV dilates int16 and uint16 as they are
    kx, ky = max(1, int(np.ceil(sx))), max(1, int(np.ceil(sy)))
    cell = cv2.dilate(f, cv2.getStructuringElement(cv2.MORPH_RECT, (kx, ky)))
    if sx.is_integer() and sy.is_integer():  # a view, no gather
        fmax = cell[int(sy) // 2::int(sy), int(sx) // 2::int(sx)]
    else:
        ix = np.minimum(((np.arange(near.width) + 0.5) * sx).astype(np.intp), w - 1)
        iy = np.minimum(((np.arange(near.height) + 0.5) * sy).astype(np.intp), h - 1)
        fmax = cell[np.ix_(iy, ix)]
    nearest = np.where(fmax > invalid, fmax.astype(np.float32) / np.float32(scale), np.float32(0))
    return MapCells(dc, nearest, sx, sy)


REACH = BLOCK // 2 + 1  # cells: how far a coarse block spreads a near face over what is beside it


def beside_band(cells: MapCells, band_px: float) -> int:
    """The first cell column judged: right of the matcher's blind band (x < band_px: nothing measured,
    bm and sgbm) and the coarse window's reach beside it (the map measures there what is behind a thing
    standing in the band, whose edge the coarse block spreads)."""
    return int(np.ceil(band_px / cells.sx)) + REACH + 1


def largest(mask: np.ndarray) -> float:
    """The largest 8-connected patch of a cell mask, as a share of the cells."""
    if not mask.any():
        return 0.0
    n, _, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    return float(stats[1:, cv2.CC_STAT_AREA].max()) / mask.size


def contradicted(cells: MapCells | None, search_max: float, band_px: float) -> float:
    """The largest patch of the picture (a share of it) where the map measured something, and all
    it measured within the coarse window's reach lies farther than the near field sees there. Not
    judged: where the map measured nothing (not measuring is no claim; the valid share,
    near-unmeasured and standing-not-listed speak of it), what the coarse look sees nearer than the
    map's search reaches (search_max, px: nearer-than-range is its word), the blind band and beside
    it (beside_band)."""
    if cells is None:
        return 0.0
    dc, fmax = cells.coarse, cells.nearest
    reach = cv2.dilate(fmax, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * REACH + 1, 2 * REACH + 1)))
    tol = np.maximum(np.float32(2 * cells.sx), np.float32(CONTRADICTED_REL) * dc)
    contra = (dc > 0) & (dc <= search_max) & (fmax > 0) & (dc > reach + tol)
    contra[:, :beside_band(cells, band_px)] = False
    return largest(contra)
