"""Glare in both cameras: "washed-out".

A saturated disc over the street's horizon in both pictures (the sun low ahead) hid what stood in it,
while the rest of the view was measured as usual: no valid-collapse, no little-measured, and both
cameras alike, so no view-blocked. Before this reason the lists said nothing."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from common.messages import ClippedTiles, FrameChecks
from common.settings import MountSettings
from cores import camera
from cores.calibration.check import clipped_tiles
from cores.matching.config import MatcherConfig
from cores.pipeline import Pipeline
from cores.segmentation.builder import ObstacleBuilder
from cores.segmentation.mount import FloorPlane, Mount
from cores.segmentation.settings import SegmenterSettings
from cores.segmentation.washout import WASHED_OUT, washed_out_share

KARLSRUHE = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "karlsruhe-0023"
MODEL = camera.RectifiedModel(640, 480, 500.0, 320.0, 240.0, 0.12)


def glare(image: np.ndarray, cx: float, cy: float, radius: float) -> np.ndarray:
    """A saturated disc (centre and radius in px) with a halo, added over the picture: the light of a
    sun at infinity, at the same place in both cameras."""
    h, w = image.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(xx - cx, yy - cy)
    veil = np.where(r <= radius, 1.0, np.exp(-np.maximum(r - radius, 0) / (0.3 * radius)))
    out = image.astype(np.float32) + (255 - image.astype(np.float32)) * veil
    return np.clip(out, 0, 255).astype(np.uint8)


def textured(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(20, 200, (480, 640)).astype(np.uint8)


def floor_of(settings: MountSettings) -> FloorPlane:
    mount = Mount.of(settings)
    assert mount is not None
    return FloorPlane.from_normal(mount.down_camera, mount.height_m, MODEL.focal_px, MODEL.cx, MODEL.cy,
                                  MODEL.baseline_m)


def tiles(c: ClippedTiles) -> np.ndarray:
    return np.frombuffer(c.data, np.uint8).reshape(c.height, c.width) / 255


def test_white_at_the_same_place_in_both_pictures_is_marked_a_near_white_thing_is_not():
    left, right = textured(1), textured(2)
    sun = tiles(clipped_tiles(glare(left, 320, 300, 60), glare(right, 320, 300, 60)))
    assert sun.sum() > 20 and sun[15, 16] == 1.0  # the disc's tiles, around (320, 300) px
    assert sun[:, :8].sum() == 0 and sun[:5].sum() == 0  # nothing away from it
    # a white board 100 px wide, 40 px apart in the two pictures (1.5 m away with this rig)
    lw, rw = left.copy(), right.copy()
    lw[250:400, 300:400] = 255
    rw[250:400, 260:360] = 255
    assert tiles(clipped_tiles(lw, rw)).sum() == 0
    # the same board far off, 2 px apart: at infinity as near as the pictures can tell
    rw = right.copy()
    rw[250:400, 298:398] = 255
    assert tiles(clipped_tiles(lw, rw)).sum() > 10
    # one camera only: BlockedView's, not this
    assert tiles(clipped_tiles(glare(left, 320, 300, 60), right)).sum() == 0


def test_only_the_floor_within_the_range_counts():
    floor = floor_of(MountSettings(height_m=1.0, pitch_deg=10.0))
    grid = np.zeros((24, 32), np.uint8)
    sky = grid.copy()
    sky[:6] = 255  # the top quarter: above the horizon (row 152 with a 10 deg pitch)
    share = washed_out_share(ClippedTiles(width=32, height=24, data=sky.tobytes()), MODEL, floor, 1.0, 10.0)
    assert share == 0.0
    ahead = grid.copy()
    ahead[12:18, 12:20] = 255  # the floor 2.5-4 m ahead
    share = washed_out_share(ClippedTiles(width=32, height=24, data=ahead.tobytes()), MODEL, floor, 1.0, 10.0)
    assert 0.05 < share < 0.5
    # the same tiles, with a vision range that ends before them: not its floor
    assert washed_out_share(ClippedTiles(width=32, height=24, data=ahead.tobytes()), MODEL, floor, 1.0, 2.0) == 0.0


def test_a_list_whose_floor_is_washed_out_says_so():
    mount = MountSettings(height_m=1.0, pitch_deg=10.0)
    b = ObstacleBuilder(SegmenterSettings(fit_floor=False), mount)
    floor = floor_of(mount)
    vv, uu = np.mgrid[0:480, 0:640].astype(np.float32)
    d = floor.disparity(uu, vv).astype(np.float32)
    d[d < 2] = np.nan  # the floor, measured to 30 m
    ahead = np.zeros((24, 32), np.uint8)
    ahead[12:18, 12:20] = 255
    clean = b.process(d.copy(), MODEL, t_s=0.0, seq=0, stamp_ns=0,
                      checks=FrameChecks(clipped=ClippedTiles(width=32, height=24, data=bytes(768))))
    assert "washed-out" not in clean.obstacles.degraded and b.washed_out == 0.0
    glared = b.process(d.copy(), MODEL, t_s=0.1, seq=1, stamp_ns=1,
                       checks=FrameChecks(clipped=ClippedTiles(width=32, height=24, data=ahead.tobytes())))
    assert "washed-out" in glared.obstacles.degraded and b.washed_out > WASHED_OUT
    assert not glared.obstacles.obstacles  # nothing stands: only the flag keeps this from a clear way
    unchecked = b.process(d.copy(), MODEL, t_s=0.2, seq=2, stamp_ns=2)
    assert "washed-out" not in unchecked.obstacles.degraded
    # a floor the list cannot vouch for (the mount taped 12 deg off, fit_floor false) does not say where
    # the floor lies in the picture: its "floor" may be the sky, whose white is no glare
    taped = ObstacleBuilder(SegmenterSettings(fit_floor=False), MountSettings(height_m=1.0, pitch_deg=22.0))
    out = taped.process(d.copy(), MODEL, t_s=0.0, seq=0, stamp_ns=0,
                        checks=FrameChecks(clipped=ClippedTiles(width=32, height=24, data=ahead.tobytes())))
    assert "mount-disagrees" in out.obstacles.degraded and "washed-out" not in out.obstacles.degraded


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
def test_the_street_with_the_sun_low_ahead_says_washed_out():
    """The street's pairs with a saturated disc over the horizon (radius 0.15 of the picture's
    height) in both cameras: obstacles in it go missing and, before, no list said anything. Every
    list of the street as it was recorded measures no washed-out floor at all."""
    from evaluation.recordings import open_recording

    rec = open_recording(KARLSRUHE)
    pairs = [(cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE), cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE))
             for lp, rp in rec.pairs[:40:5]]
    pipe = Pipeline(rec.calibration, MatcherConfig(), SegmenterSettings())
    day = [pipe.process(lf, rt, t_s=0.1 * k, seq=k) for k, (lf, rt) in enumerate(pairs)]
    assert not any("washed-out" in f.result.obstacles.degraded for f in day)
    assert all(f.result.obstacles.obstacles for f in day)
    h, w = pairs[0][0].shape
    pipe = pipe.fork()
    sun = [pipe.process(glare(lf, 0.5 * w, 0.42 * h, 0.15 * h), glare(rt, 0.5 * w, 0.42 * h, 0.15 * h),
                        t_s=0.1 * k, seq=k) for k, (lf, rt) in enumerate(pairs)]
    said = ["washed-out" in f.result.obstacles.degraded for f in sun]
    assert sum(said) >= len(sun) - 1, said
