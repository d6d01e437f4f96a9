"""How much of the floor within the vision range rectify found clipped white in both cameras, at
infinity (common/messages.py: ClippedTiles): the sun low ahead, a lamp, glare over both lenses.
Nothing is measured there and what stands there is in no list, while the rest of the view looks
normal: the map measures plenty elsewhere (no little-measured), and both cameras see the same white
(no view-blocked). The sky is clipped white at infinity too, but it lies above the floor's horizon;
the floor within the range is where a robot's path goes and where a list's silence would be read as
a clear way. No Zenoh here."""
from __future__ import annotations

import numpy as np

from common.messages import ClippedTiles
from cores import camera
from cores.segmentation.mount import FloorPlane

# Of the floor's tiles within the range, the share clipped at infinity in both cameras over which a
# list cannot vouch for its view. Measured: 0.000 on every frame of both recordings, the synthetic
# scenes and the sway; a glare disc over the street's horizon, of radius 0.1/0.15/0.5 of the
# picture's height: 0.007/0.016/0.18 (docs/architecture.md, washed-out).
WASHED_OUT = 0.005


def washed_out_share(clipped: ClippedTiles, model: camera.RectifiedModel, floor: FloorPlane,
                     min_range_m: float, range_m: float) -> float:
    """The share of the floor between min_range_m and range_m, as the picture shows it, that is
    clipped white at infinity in both cameras (0 when no floor in the range is in view). The tiles
    are put in the model's pixels (a map downsampled by the disparity stage has a model of its own
    size)."""
    share = np.frombuffer(clipped.data, np.uint8).reshape(clipped.height, clipped.width).astype(np.float32) / 255
    sx, sy = model.width / clipped.width, model.height / clipped.height
    u = (np.arange(clipped.width) + 0.5) * sx - 0.5
    v = (np.arange(clipped.height) + 0.5) * sy - 0.5
    d_floor = floor.disparity(u[None, :], v[:, None])
    bf = model.focal_px * abs(model.baseline_m)
    in_range = (d_floor >= bf / range_m) & (d_floor <= bf / max(min_range_m, 1e-3))
    if not in_range.any():
        return 0.0
    return float(share[in_range].mean())
