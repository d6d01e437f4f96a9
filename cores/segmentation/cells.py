"""Objects on the column-disparity grid (u-disparity) of the standing points: which occupied cells
are one object.

Occupied cells that touch (one cell of slack) are one object, with one exception: where only low
things join them. A kerb, a snow bank or a low wall runs along a street and touches every parked car,
hedge and post beside it; joined through it, a street side is one obstacle 20 m long (on Karlsruhe
with sgbm, whose dense maps measure the whole kerb). Things that join above knee height (a table's top
on its legs, a car's body over its wheels, a person's arms) are one object. So within a touching group
the cells with something standing above LOW_M are the cores; a group with two or more separate cores
is cut between them: each low cell goes to the nearest core. A low thing that touches no more than
one core stays with it, and one that touches none is an object of its own (a kerb is an obstacle).
"""
from __future__ import annotations

import cv2
import numpy as np

LOW_M = 0.5  # a cell with nothing standing above this height over the floor joins no two objects
# tall cells a core needs: fewer, and a few noisy cells of a snow bank or a kerb become cores that cut
# pieces of it loose as obstacles of their own (sgbm at 20 m on Karlsruhe: 6.8 % flat with 3 cells, 3.3 % with 12)
MIN_CORE_CELLS = 12
_SQUARE = np.ones((3, 3), np.uint8)


def occupied(bins: np.ndarray, cols: np.ndarray, height: np.ndarray, shape: tuple[int, int],
             min_height_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The column-disparity grid of standing pixels: bins, cols their cell's row (disparity bin) and
    column from 0, height the metres of height each pixel covers; shape (bins, columns). -> (each
    pixel's flat cell index, cells (uint8, 1 = occupied: its pixels cover min_height_m of height))."""
    cell = bins * shape[1] + cols
    occ = np.bincount(cell, weights=height, minlength=shape[0] * shape[1]).reshape(shape)
    return cell, (occ >= min_height_m).astype(np.uint8)


def group_cells(cells: np.ndarray, tall: np.ndarray | None) -> tuple[np.ndarray, dict[int, int]]:
    """cells: (bins, columns) uint8, 1 = occupied; tall: the occupied cells with something standing
    above LOW_M (None: heights unknown, every cell counts as tall). -> (int32 labels per cell, 0 =
    none, labels need not be consecutive; {label: the touching group it was cut from} for the
    labels of cut groups: the pieces of one cut touch, and must not be joined again by how close
    they come)."""
    _, cc = cv2.connectedComponents(cv2.dilate(cells, _SQUARE), connectivity=8)
    if tall is None or not tall.any():
        return cc, {}
    n_core, core = cv2.connectedComponents(cv2.dilate(tall, _SQUARE), connectivity=8)
    if n_core <= 2:
        return cc, {}  # at most one core anywhere: nothing to cut
    # a core is a thing standing up, not a cell or two of noise above LOW_M
    small = np.bincount(core[tall > 0], minlength=n_core) < MIN_CORE_CELLS
    small[0] = False
    core[small[core]] = 0
    if not core.any():
        return cc, {}
    # groups (of the touching cells) holding two or more cores: which (group, core) pairs occur, by
    # counting them (np.unique over the pairs sorts every core cell: most of this function's time)
    on = core > 0
    n_cc = int(cc.max()) + 1
    seen = np.bincount(cc[on].astype(np.int64) * n_core + core[on], minlength=n_cc * n_core) > 0
    split = np.flatnonzero(seen.reshape(n_cc, n_core).sum(1) > 1)
    if split.size == 0:
        return cc, {}
    # each cell's nearest core cell (Euclidean on the grid): labelled by the zero pixels of src in raster order
    src = (core == 0).astype(np.uint8)
    _, nearest = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL)
    core_of_zero = core.ravel()[np.flatnonzero(src.ravel() == 0)]
    near_core = core_of_zero[nearest - 1]
    # a cell of a split group takes its nearest core's label (shifted past the group labels)
    is_split = np.zeros(n_cc, bool)
    is_split[split] = True
    in_split = is_split[cc] & (cells > 0)
    labels = np.where(in_split, near_core + n_cc, cc).astype(np.int32)
    # {piece: its group}; a piece whose cells lie in two groups keeps the last one in raster order
    k, g = labels[in_split][::-1], cc[in_split][::-1]
    first = np.unique(k, return_index=True)[1]
    return labels, dict(zip(k[first].tolist(), g[first].tolist()))
