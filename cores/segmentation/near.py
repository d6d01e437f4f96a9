"""What of rectify's near field (common/messages.py: NearField) stands nearer than the vision range:
the floor the camera looks down at is nearer than the range's near end too, and is no reason to
doubt a list. No Zenoh here."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.messages import NearField
from cores import camera
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
