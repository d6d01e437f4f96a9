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


def test_what_sgbm_carried_into_plain_windows_is_not_a_measurement():
    """sgbm gives a disparity in a window with nothing to match too, carried in from around it; it says
    which (flat). Those pixels count neither in the list's valid_fraction nor in an obstacle's
    confidence (a plain cabinet's and panel's in blank-faces: 0.87 and 0.84, all carried in; now 0.11
    and 0.08), though the obstacle stands as before."""
    d = box_map(300, 0)
    flat = np.zeros(d.shape, bool)
    flat[:, 320:] = True  # the box's right half: plain
    assert measured_share(d, None, flat=flat) == pytest.approx(measured_share(d, None) / 2, rel=0.02)
    b = ObstacleBuilder(SegmenterSettings(fit_floor=False), MountSettings(height_m=1.0, pitch_deg=5.0))
    plain = b.process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0, flat=flat).obstacles
    seen = ObstacleBuilder(SegmenterSettings(fit_floor=False), MountSettings(height_m=1.0, pitch_deg=5.0)).process(
        d, MODEL, t_s=0.0, seq=0, stamp_ns=0).obstacles
    assert len(plain.obstacles) == len(seen.obstacles) == 1
    assert plain.obstacles[0].bbox_px == seen.obstacles[0].bbox_px and plain.obstacles[0].position_m == \
        seen.obstacles[0].position_m
    assert seen.obstacles[0].confidence > 0.9 and plain.obstacles[0].confidence == pytest.approx(
        seen.obstacles[0].confidence / 2, abs=0.05)
    assert plain.valid_fraction == pytest.approx(seen.valid_fraction / 2, rel=0.02)
    # a mask over the whole picture (a worker's sgbm saw nothing it could match, or says so): no list
    # vouches for the view
    b = ObstacleBuilder(SegmenterSettings(fit_floor=False), MountSettings(height_m=1.0, pitch_deg=5.0))
    every = np.ones(d.shape, bool)
    blind = [b.process(d, MODEL, t_s=i / 10, seq=i, stamp_ns=i, flat=every).obstacles for i in range(6)]
    assert all({"little-measured", "no-valid-disparity"} & set(o.degraded) for o in blind), \
        [(o.valid_fraction, o.degraded) for o in blind]


def test_the_pictures_noise_is_measured_through_texture_and_edges():
    """picture_noise: the street's own pictures, full of edges and texture, read as the 1-2 grey levels
    of a camera in daylight; the same with a sensor noise added read as that noise, within 15 %."""
    from cores.calibration.check import picture_noise

    if not (KARLSRUHE / "calibration.yaml").exists():
        pytest.skip("../shared/data/real/karlsruhe-0023 absent")
    image = cv2.imread(str(sorted((KARLSRUHE / "left").glob("*.png"))[10]), cv2.IMREAD_GRAYSCALE)
    assert picture_noise(image) < 2.5
    rng = np.random.default_rng(1)
    for sigma in (4.0, 8.0, 12.0):
        noisy = np.clip(image + rng.normal(0, sigma, image.shape), 0, 255).astype(np.uint8)
        assert picture_noise(noisy) == pytest.approx(sigma, rel=0.15), sigma
    # a 16-bit camera's picture reads in 8-bit grey levels too (int16 arithmetic on it had wrapped round)
    assert picture_noise(noisy.astype(np.uint16) * 257) == picture_noise(noisy)
    assert picture_noise(np.full((2, 2), 7, np.uint8)) == 0.0  # too small to tell: no noise claimed


def test_a_list_says_noisy_when_rectify_measured_the_pictures_noisy():
    from common.messages import FrameChecks
    from cores.segmentation.builder import NOISY_GREY

    d = box_map(160, 0)
    for noise, said in ((None, False), (1.5, False), (NOISY_GREY - 0.1, False), (NOISY_GREY + 0.1, True)):
        lst = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0,
                                                           checks=FrameChecks(noise_grey=noise)).obstacles
        assert ("noisy" in lst.degraded) == said, (noise, lst.degraded)


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
def test_the_street_at_a_fifth_of_its_light_says_noisy_on_every_list():
    """Dusk before little-measured: at 20 % of its light bm measured 15 % of the picture and listed
    about 60 % of what it listed within 15 m in daylight, and half its lists said nothing. Now every
    list says noisy (rectify's picture_noise: 7.7 grey levels); in daylight none does."""
    from evaluation.recordings import open_recording

    rec = open_recording(KARLSRUHE)
    pairs = [(cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE), cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE))
             for lp, rp in rec.pairs[:40:5]]
    pipe = Pipeline(rec.calibration, MatcherConfig(method="bm"), SegmenterSettings(max_range_m=30.0))
    day = [pipe.process(lf, rt, t_s=0.1 * k, seq=k).result.obstacles for k, (lf, rt) in enumerate(pairs)]
    assert not any("noisy" in o.degraded for o in day)
    rng = np.random.default_rng(0)
    pipe = pipe.fork()
    dim = [pipe.process(dusk(lf, 0.2, rng), dusk(rt, 0.2, rng), t_s=0.1 * k, seq=k).result.obstacles
           for k, (lf, rt) in enumerate(pairs)]
    def near(lists) -> int:
        return sum(sum(o.distance_m <= 15 for o in lst.obstacles) for lst in lists)
    assert near(dim) < 0.85 * near(day)  # the dusk costs what stands near
    assert all("noisy" in o.degraded for o in dim), [(len(o.obstacles), o.degraded) for o in dim]


EUROC = KARLSRUHE.parent / "euroc-v1-01"


@pytest.mark.skipif(not (EUROC / "cam0_sensor.yaml").exists(), reason="../shared/data/real/euroc-v1-01 absent")
def test_a_raw_rig_at_dusk_says_noisy_the_remap_does_not_hide_the_noise():
    """The EuRoC room is a raw rig: rectifying interpolates, which smooths the noise (at 20 % of the
    light 7.4 grey levels in the cameras' pictures, 2.2 in the rectified ones). Judged on the rectified
    pair no list said noisy while bm listed 5 obstacles a frame where daylight has 1; the noise is
    measured on the cameras' own pictures."""
    from evaluation.recordings import open_recording

    rec = open_recording(EUROC)
    pairs = [(cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE), cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE))
             for lp, rp in rec.pairs[:8:2]]
    pipe = Pipeline(rec.calibration, MatcherConfig(method="bm"), SegmenterSettings(max_range_m=5.0))
    day = [pipe.process(lf, rt, t_s=0.05 * k, seq=k).result.obstacles for k, (lf, rt) in enumerate(pairs)]
    assert not any(o.degraded for o in day), [o.degraded for o in day]
    rng = np.random.default_rng(0)
    pipe = pipe.fork()
    dim = [pipe.process(dusk(lf, 0.2, rng), dusk(rt, 0.2, rng), t_s=0.05 * k, seq=k).result.obstacles
           for k, (lf, rt) in enumerate(pairs)]
    assert all("noisy" in o.degraded for o in dim), [(len(o.obstacles), o.degraded) for o in dim]
