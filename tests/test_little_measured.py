"""A map that measured too little of the picture to vouch for what it did not list: "little-measured".

The dark comes on too slowly for valid-collapse: before this reason, the street at 4 % of its light,
with the mount configured and fit_floor false, gave empty lists with nothing said."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from common.settings import MountSettings
from cores import camera
from cores.matching.config import MatcherConfig
from cores.pipeline import Pipeline
from cores.segmentation.builder import LITTLE_MEASURED, ObstacleBuilder, measured_share
from cores.segmentation.settings import SegmenterSettings

KARLSRUHE = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "karlsruhe-0023"
MODEL = camera.RectifiedModel(640, 480, 665.0, 320.0, 240.0, 0.1)


def box_map(measured_rows: int, seed: int) -> np.ndarray:
    """A 640x480 map: a box 1.8 m ahead over the middle columns, measured on `measured_rows` rows of
    it; the rest unmeasured (NaN), as a dark picture leaves it."""
    rng = np.random.default_rng(seed)
    d = np.full((480, 640), np.nan, np.float32)
    rows = slice(240 - measured_rows // 2, 240 + measured_rows // 2)
    d[rows, 200:440] = MODEL.focal_px * MODEL.baseline_m / 1.8 + rng.normal(0, 0.05, (rows.stop - rows.start, 240))
    return d


def lists(maps: list[np.ndarray], confidence: list[np.ndarray | None] | None = None):
    b = ObstacleBuilder(SegmenterSettings(fit_floor=False), MountSettings(height_m=1.0, pitch_deg=5.0))
    confidence = confidence or [None] * len(maps)
    return [b.process(m, MODEL, t_s=i / 10, seq=i, stamp_ns=i, confidence=c).obstacles
            for i, (m, c) in enumerate(zip(maps, confidence))]


def test_a_map_measuring_under_a_tenth_of_the_picture_says_so_on_every_list():
    # 120 of 480 rows of 240 of 640 columns: 9.4 % of the picture, steadily (no collapse to see)
    thin = lists([box_map(120, i) for i in range(12)])
    assert all("little-measured" in o.degraded for o in thin)
    assert all("valid-collapse" not in o.degraded for o in thin[5:])  # steady: only the new reason tells
    assert all(0.09 < o.valid_fraction < LITTLE_MEASURED for o in thin)
    # 160 rows: 12.5 %, enough
    assert not any("little-measured" in o.degraded for o in lists([box_map(160, i) for i in range(12)]))


def test_a_dense_matchers_fill_is_not_a_measurement():
    """dense fills every pixel its measurements reach (confidence below 128); only what it measured
    and the segmenter uses (min_confidence, 200, and over) counts."""
    d = np.full((480, 640), MODEL.focal_px * MODEL.baseline_m / 3.0, np.float32)  # a map valid everywhere
    filled = np.full(d.shape, 60, np.uint8)
    filled[200:240, :] = 200  # 8.3 % measured
    assert measured_share(d, filled) == pytest.approx(40 / 480)
    assert measured_share(d, None) == 1.0
    doubted = filled.copy()
    doubted[240:300, :] = 150  # measured, below the segmenter's min_confidence: not used, not counted
    assert measured_share(d, doubted, 200) == pytest.approx(40 / 480)
    assert measured_share(d, doubted, 0) == pytest.approx(100 / 480)
    o = lists([d] * 6, [filled] * 6)[-1]
    assert "little-measured" in o.degraded and o.valid_fraction == pytest.approx(40 / 480)
    measured = np.full(d.shape, 200, np.uint8)
    assert "little-measured" not in lists([d] * 6, [measured] * 6)[-1].degraded


def dusk(image: np.ndarray, light: float, rng: np.random.Generator) -> np.ndarray:
    """The picture at `light` of its light, brought back up by the camera's gain with the sensor's
    noise (1.5 grey levels before the gain)."""
    dark = image.astype(np.float32) * light + rng.normal(0, 1.5, image.shape)
    return np.clip(np.round(dark / light), 0, 255).astype(np.uint8)


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
@pytest.mark.parametrize("method", ["bm", "dense"])
def test_the_street_at_dusk_never_gives_an_unflagged_empty_list(method):
    """The street's pairs at 4 % of their light (bm listed 0-3 of the 18 things it lists in daylight,
    dense 0-5 of 21), the mount configured and fit_floor false, so no ground fit fails to tell: every
    list says why it cannot vouch for the view. In daylight no list says little-measured."""
    from evaluation.recordings import open_recording

    rec = open_recording(KARLSRUHE)
    pairs = [(cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE), cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE))
             for lp, rp in rec.pairs[:40:5]]
    mount = MountSettings(height_m=1.64, pitch_deg=6.0)
    pipe = Pipeline(rec.calibration, MatcherConfig(method=method), SegmenterSettings(fit_floor=False), mount=mount)
    day = [pipe.process(lf, rt, t_s=0.1 * k, seq=k).result.obstacles for k, (lf, rt) in enumerate(pairs)]
    assert not any("little-measured" in o.degraded for o in day) and all(o.obstacles for o in day)
    rng = np.random.default_rng(0)
    pipe = pipe.fork()
    night = [pipe.process(dusk(lf, 0.04, rng), dusk(rt, 0.04, rng), t_s=0.1 * k, seq=k).result.obstacles
             for k, (lf, rt) in enumerate(pairs)]
    assert sum(len(o.obstacles) for o in night) < 0.5 * sum(len(o.obstacles) for o in day)  # the dark costs
    assert all({"little-measured", "no-valid-disparity"} & set(o.degraded) for o in night), \
        [(len(o.obstacles), o.valid_fraction, o.degraded) for o in night]
