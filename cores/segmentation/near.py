"""What of rectify's near field (common/messages.py: NearField) stands nearer than the vision range
(the floor the camera looks down at is nearer than the range's near end too, and is no reason to
doubt a list), and what it sees standing in the range that neither the map measured nor the list
holds. No Zenoh here."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.messages import NearField
from cores import camera
from cores.calibration.near import REACH, MapCells, beside_band, largest
from cores.segmentation.mount import FloorPlane

# Of the picture standing nearer than the range: the list's view of its range is blocked. Measured:
# at most 0.66 % on scenes with nothing that near (the sway's floor at its most pitched; the street
# 0, the room 0.1 %); a box 0.3 m ahead-left 1.9-2.3 % (its face is then in the left camera's view
# only: what the coarse search sees is its side).
NEAR_SHARE = 0.012


@dataclass(frozen=True)
class NearStanding:
    share: float  # of the picture: standing, and nearer than the range's near end
    distance_m: float | None  # the median distance of that part (None: nothing)

    @property
    def blocks(self) -> bool:
        return self.share >= NEAR_SHARE


def near_standing(near: NearField, model: camera.RectifiedModel, floor: FloorPlane | None, min_range_m: float,
                  min_height_m: float) -> NearStanding:
    """The share of the picture that stands (over min_height_m above the floor; without a floor,
    all of it) nearer than min_range_m, by the near field. The coarse map is put in the model's
    pixels (a map downsampled by the disparity stage has a model of its own size)."""
    d = np.frombuffer(near.data, np.uint8).reshape(near.height, near.width).astype(np.float32) / 4  # coarse px
    sx = model.width / near.width  # model px per coarse px, across (disparity is horizontal)
    sy = model.height / near.height
    d_model = d * sx
    bf = model.baseline_m * model.focal_px
    # one coarse pixel of margin: the coarse map's own step
    near_d = bf / max(min_range_m, 1e-3) + sx
    v, u = np.nonzero(d_model > near_d)
    if v.size == 0:
        return NearStanding(0.0, None)
    dn = d_model[v, u]
    if floor is not None:
        d_floor = floor.disparity((u + 0.5) * sx - 0.5, (v + 0.5) * sy - 0.5)
        standing = floor.height_m * (1.0 - d_floor / dn) > min_height_m  # the height above the floor
        dn = dn[standing]
    share = float(dn.size) / d.size
    return NearStanding(share, float(bf / np.median(dn)) if dn.size else None)


# Of the picture: what the near field sees standing in the vision range where the map measured nothing
# and no obstacle is. A worker that sets what stands to "not measured" (every other check passes: the
# share it measured drops by what the boxes covered) made two-boxes' lists empty, fresh, no reason;
# the segmenter's blank faces find a plain face by the floor's end, not a textured box whose map was
# emptied. Measured, the largest such patch: two-boxes so emptied 8.4 %, touching 3.5 %, people-queue
# 2.1-2.4 % (chair's and others' blank faces then cover most of it); honest maps (bm, sgbm, dense, bm
# and sgbm matching their band): the 15 scenes and the sway at their ranges, 3 m and 8 m at most 0.28 %
# (low-faces with bm at 3 m), the street at 5-40 m 0.16 % (a parked car's piece between two of its
# boxes, past their margin), the room 0; no honest list flagged.
UNLISTED_SHARE = 0.005


def unlisted_standing(cells: MapCells, floor: FloorPlane, boxes: list[tuple[int, int, int, int]], far_px: float,
                      search_max: float, band_px: float, min_height_m: float, robot_height_m: float) -> float:
    """The largest patch of the picture (a share of it) the near field sees standing (min_height_m to
    robot_height_m above the floor) within the vision range (far_px to search_max, px) where the map
    measured nothing within two cells and no obstacle's box (map px; grown by the coarse window's
    reach: a block spreads a thing's edge, and a listed thing's unmeasured piece lies beside its box)
    lies. Not judged: the blind band and beside it (beside_band)."""
    dc, fmax = cells.coarse, cells.nearest
    empty = cv2.dilate(fmax, cv2.getStructuringElement(cv2.MORPH_RECT, (5, 5))) <= 0
    m = empty & (dc >= far_px) & (dc <= search_max)
    m[:, :beside_band(cells, band_px)] = False
    if not m.any():
        return 0.0
    v, u = np.nonzero(m)
    d_floor = floor.disparity((u + 0.5) * cells.sx - 0.5, (v + 0.5) * cells.sy - 0.5)
    above = floor.height_m * (1.0 - d_floor / dc[v, u])  # dc >= far_px > 0
    low_or_high = (above <= min_height_m) | (above > robot_height_m)
    m[v[low_or_high], u[low_or_high]] = False
    g = REACH + 1
    for x0, y0, x1, y1 in boxes:
        m[max(0, int(y0 // cells.sy) - g):int(np.ceil(y1 / cells.sy)) + g,
          max(0, int(x0 // cells.sx) - g):int(np.ceil(x1 / cells.sx)) + g] = False
    return largest(m)
