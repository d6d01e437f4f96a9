"""The live rectification check: a pair whose rows no longer align (a knocked camera, another rig's
calibration) is measured off the frame path and said by every list (`rows-misaligned`)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from common.messages import DisparityMap, FrameChecks, RowAlignment, StereoFrame
from cores import camera
from cores.calibration.check import BlockedView, RowMonitor
from cores.calibration.rectify import Rectifier
from cores.pipeline import Pipeline
from cores.segmentation.builder import ObstacleBuilder
from cores.segmentation.settings import SegmenterSettings

KARLSRUHE = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "karlsruhe-0023"


def knocked(right: np.ndarray, dy_px: float) -> np.ndarray:
    """The right image moved dy_px down, sub-pixel: a camera knocked on its mount."""
    h, w = right.shape[:2]
    return cv2.warpAffine(right, np.float32([[1, 0, 0], [0, 1, dy_px]]), (w, h), flags=cv2.INTER_LINEAR)


@pytest.fixture(scope="module")
def rectified_pairs() -> list[tuple[np.ndarray, np.ndarray]]:
    from services.capture.sources import SyntheticSource

    src = SyntheticSource("person-walking", "lifecam-studio", 15.0)
    rect = Rectifier(camera.load_calibration("lifecam-studio"), 0.0)
    return [rect.rectify(*(lambda p: (p.left, p.right))(src.read())) for _ in range(3)]


@pytest.mark.parametrize("dy, lo, hi", [(0.0, 0.0, 0.2), (1.0, 0.85, 1.15), (4.0, 3.8, 4.2)])
def test_the_monitor_measures_how_far_the_rows_are_apart(rectified_pairs, dy, lo, hi):
    m = RowMonitor()
    for k, (left, right) in enumerate(rectified_pairs):
        rows = m.check(left, knocked(right, dy), float(k), k)
        assert rows is not None and lo <= rows.offset_px <= hi and rows.matches >= 50, rows
        assert rows.checked_ns == k and rows.tolerance_px == 0.5


def test_a_turned_camera_is_misaligned_too(rectified_pairs):
    left, right = rectified_pairs[0]
    h, w = right.shape[:2]
    turned = cv2.warpAffine(right, cv2.getRotationMatrix2D((w / 2, h / 2), 0.3, 1.0), (w, h))
    rows = RowMonitor().check(left, turned, 0.0, 0)
    assert rows is not None and rows.offset_px > 0.5 and rows.p95_px > 1.0, rows


def test_checks_are_spaced_on_stream_time_and_a_new_calibration_starts_afresh(rectified_pairs):
    left, right = rectified_pairs[0]
    m = RowMonitor(interval_s=1.0)
    assert m.take(10.0) == 0 and m.take(10.5) is None and m.take(11.0) == 0
    bad = m.check(left, knocked(right, 2.0), 11.0, 1, epoch=0)
    assert bad is not None and bad.offset_px > 1.5
    # a textureless pair (a bare wall) measures nothing: what was measured stays
    flat = np.full_like(left, 128)
    assert m.check(flat, flat, 12.0, 2) is bad and m.failed == 1
    # a new calibration: the last result was another rectification's; the next pair is due at once,
    # and a check taken before the change does not count
    m.reset()
    assert m.latest is None and m.due(12.1)
    assert m.check(left, right, 12.1, 3, epoch=0) is None
    good = m.observe(left, right, 12.2, 4)
    assert good is not None and good.offset_px < 0.2 and m.observe(left, right, 12.3, 5) is good


def test_every_list_after_a_misaligned_check_says_so(rectified_pairs):
    """The builder decides from what the map carried: over the tolerance rectify measured with."""
    model = Rectifier(camera.load_calibration("lifecam-studio"), 0.0).model
    b = ObstacleBuilder(SegmenterSettings())
    disparity = np.full((model.height, model.width), np.nan, np.float32)
    disparity[200:, :] = 30.0
    said = []
    for k, offset in enumerate([None, 0.1, 0.49, 0.51, 3.0]):
        rows = None if offset is None else RowAlignment(offset_px=offset, p95_px=offset, matches=80,
                                                        tolerance_px=0.5, checked_ns=0)
        said.append("rows-misaligned" in b.process(disparity, model, t_s=k / 10, seq=k, stamp_ns=k,
                                                   checks=FrameChecks(rows=rows)).obstacles.degraded)
    assert said == [False, False, False, True, True]


def test_a_row_check_is_finite_and_bounded_on_the_wire():
    from pydantic import ValidationError

    for bad in ({"offset_px": float("nan")}, {"offset_px": -1.0}, {"tolerance_px": 0.0}, {"matches": -1}):
        doc = {"offset_px": 0.1, "p95_px": 0.2, "matches": 80, "tolerance_px": 0.5, "checked_ns": 0, **bad}
        with pytest.raises(ValidationError):
            RowAlignment.model_validate(doc)
    assert "checks" in StereoFrame.model_fields and "checks" in DisparityMap.model_fields


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
@pytest.mark.parametrize("dy, flagged", [(0.0, False), (1.0, True)])
def test_the_offline_pipeline_checks_the_street_rows_as_rectify_does(dy, flagged):
    """The street recording as it is (0.1 px) and with the right camera knocked 1 px: the lists of the
    one composition every offline command and eval runs say it from the first pair on."""
    from common.files import read_image
    from cores.matching.config import MatcherConfig
    from evaluation.recordings import open_recording

    rec = open_recording(KARLSRUHE)
    pipe = Pipeline(rec.calibration, MatcherConfig(num_disparities="auto"), SegmenterSettings())
    said = []
    for k in range(12):
        left, right = read_image(rec.pairs[k][0]), read_image(rec.pairs[k][1])
        f = pipe.process(left, knocked(right, dy), t_s=rec.stamps_s[k], seq=k)
        said.append("rows-misaligned" in f.result.obstacles.degraded)
    assert said == [flagged] * 12
    assert pipe.checks.rows.checks == 2  # ~10 Hz: one check a second of the recording


# --- swapped cameras ---------------------------------------------------------------------------------

def test_the_monitor_finds_swapped_cameras_from_where_features_lie(rectified_pairs):
    """Exchanged cables: what is near lies farther left in the "left" image than in the "right" one.
    The rows still align (a rectified pair swapped is still rectified), so only the sign tells."""
    left, right = rectified_pairs[0]
    good = RowMonitor().check(left, right, 0.0, 0)
    swapped = RowMonitor().check(right, left, 0.0, 0)
    assert good is not None and good.reversed_share < 0.1, good
    assert swapped is not None and swapped.reversed_share > 0.9 and swapped.offset_px < 0.5, swapped


def test_a_scene_all_at_infinity_says_nothing_of_a_swap():
    from cores.calibration.check import reversed_share

    rng = np.random.default_rng(0)
    assert reversed_share(rng.normal(0.0, 0.4, 200)) == 0.0  # nothing over 1 px off zero: no evidence
    assert reversed_share(np.array([-5.0] * 9 + [0.0] * 100)) == 0.0  # 9: too few to say
    assert reversed_share(np.array([-5.0] * 9 + [3.0])) == 0.9


@pytest.mark.parametrize("share, said", [(0.0, False), (0.5, False), (0.51, True), (1.0, True)])
def test_a_list_says_cameras_swapped_over_half_reversed(share, said):
    model = Rectifier(camera.load_calibration("lifecam-studio"), 0.0).model
    disparity = np.full((model.height, model.width), np.nan, np.float32)
    disparity[200:, :] = 30.0
    rows = RowAlignment(offset_px=0.1, p95_px=0.2, matches=80, tolerance_px=0.5, checked_ns=0, reversed_share=share)
    out = ObstacleBuilder(SegmenterSettings()).process(disparity, model, t_s=0.0, seq=0, stamp_ns=0,
                                                       checks=FrameChecks(rows=rows)).obstacles
    assert ("cameras-swapped" in out.degraded) == said


def test_a_frozen_camera_says_camera_frozen_and_nothing_of_the_rows():
    """A row check that compared a live picture with a frozen one (before the freeze was declared)
    compared two moments: it said cameras-swapped, first in `status` (the street through `up` with
    its right camera hung). The list says camera-frozen only; live again, the rows count."""
    model = Rectifier(camera.load_calibration("lifecam-studio"), 0.0).model
    disparity = np.full((model.height, model.width), np.nan, np.float32)
    disparity[200:, :] = 30.0
    rows = RowAlignment(offset_px=0.9, p95_px=2.0, matches=80, tolerance_px=0.5, checked_ns=0, reversed_share=0.8)
    b = ObstacleBuilder(SegmenterSettings())
    out = b.process(disparity, model, t_s=0.0, seq=0, stamp_ns=0, checks=FrameChecks(rows=rows, frozen=["right"]))
    assert "camera-frozen" in out.obstacles.degraded
    assert not {"cameras-swapped", "rows-misaligned"} & set(out.obstacles.degraded)
    out = b.process(disparity, model, t_s=0.1, seq=1, stamp_ns=1, checks=FrameChecks(rows=rows))
    assert {"cameras-swapped", "rows-misaligned"} <= set(out.obstacles.degraded)


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
def test_the_street_with_its_cameras_swapped_is_flagged_and_claims_no_free_floor():
    """The street with left and right exchanged and the rig's mount configured as a prior only
    (fit_floor false): before the check these lists carried the mirror scene's 3-9 obstacles, none of
    them a car, free floor, and no reason at all. Now every list says cameras-swapped and no cell is
    free; the pairs the right way round say nothing of it."""
    from common.files import read_image
    from common.settings import MountSettings
    from cores.matching.config import MatcherConfig
    from cores.segmentation.freespace import FREE
    from evaluation.recordings import open_recording

    rec = open_recording(KARLSRUHE)
    mount = MountSettings(height_m=1.64, pitch_deg=6.0)
    settings = SegmenterSettings(fit_floor=False)
    for swap in (True, False):
        pipe = Pipeline(rec.calibration, MatcherConfig(num_disparities="auto"), settings, mount=mount)
        for k in range(0, 40, 8):
            left, right = read_image(rec.pairs[k][0]), read_image(rec.pairs[k][1])
            f = pipe.process(*((right, left) if swap else (left, right)), t_s=rec.stamps_s[k], seq=k)
            assert ("cameras-swapped" in f.result.obstacles.degraded) == swap, (k, f.result.obstacles.degraded)
            if swap:
                cells = np.frombuffer(f.result.freespace.cells, np.int8)
                assert not np.any(cells == FREE), k


# --- a frozen camera ---------------------------------------------------------------------------------

@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
def test_one_camera_repeating_its_picture_is_said_by_every_list_after_frozen_after_s():
    """The street with the right camera's driver hung after the first pair (it repeats that picture
    while the left goes on): the maps still change with the left image, so input-frozen cannot tell,
    and wherever anything moved they are wrong. From 0.5 s on every list says camera-frozen, naming
    the right camera; the left one live, nothing said of it."""
    from common.files import read_image
    from cores.matching.config import MatcherConfig
    from evaluation.recordings import open_recording

    rec = open_recording(KARLSRUHE)
    pipe = Pipeline(rec.calibration, MatcherConfig(num_disparities="auto"), SegmenterSettings())
    stuck_right = read_image(rec.pairs[0][1])
    said = []
    for k in range(12):
        f = pipe.process(read_image(rec.pairs[k][0]), stuck_right, t_s=rec.stamps_s[k], seq=k)
        said.append((rec.stamps_s[k], "camera-frozen" in f.result.obstacles.degraded,
                     "input-frozen" in f.result.obstacles.degraded))
    assert all(flag == (t > 0.5 + 1e-6) for t, flag, _ in said), said
    assert not any(whole for _, _, whole in said)  # the maps changed all along
    assert pipe.builder.checks.frozen == ["right"]


# --- a blocked view ----------------------------------------------------------------------------------

def finger(image: np.ndarray) -> np.ndarray:
    """A dark disc over the lower right of the picture, a sixth of it: a finger on the lens."""
    out = image.copy()
    h, w = out.shape[:2]
    cv2.circle(out, (w * 3 // 4, h * 2 // 3), h // 2, 20, -1)
    return out


def test_a_finger_on_one_lens_blocks_that_camera_from_the_first_pair_and_the_scene_does_not(rectified_pairs):
    """The synthetic scene, then the same with a finger over the right lens: the right camera is
    blocked from the first pair on (it had waited frozen_after_s, 0.5 s, of lists that missed what
    the finger hid and said nothing), the left never. The scene alone, a lens covered on both
    cameras (nothing to compare with) and the picture once the finger is gone clear it, at the next
    look (every 0.1 s)."""
    left, right = rectified_pairs[0]
    view = BlockedView()
    times = np.arange(0, 1.5, 1 / 15)
    assert all(view.blocked(left, finger(right), t) == ["right"] for t in times)
    assert view.blocked(left, right, 1.6) == []  # the finger gone: at once
    clean = BlockedView()
    assert all(clean.blocked(left, right, t) == [] for t in times)
    both = BlockedView()
    assert all(both.blocked(finger(left), finger(right), t) == [] for t in times)
    assert BlockedView().blocked(finger(left), right, 0.0) == ["left"]


def smudge(image: np.ndarray, sigma: float = 4.0) -> np.ndarray:
    """A blur of sigma px over the middle of the picture, a quarter of it: grease on the lens."""
    out = image.copy()
    h, w = out.shape[:2]
    box = (slice(h // 5, h * 5 // 6), slice(w * 5 // 16, w * 3 // 4))
    out[box] = cv2.GaussianBlur(image, (0, 0), sigma)[box]
    return out


@pytest.mark.parametrize("sigma", [3.0, 4.0])
def test_a_smudge_on_one_lens_blocks_that_camera_and_a_dimmer_camera_does_not(rectified_pairs, sigma):
    """A blurred patch keeps the coarse texture the finger check looks at, yet the matcher loses what
    is behind it (two-boxes, bm, sigma 4: the box 2.3 m away gone from the list, unflagged). Its
    fine detail, against the other camera's, tells it. A camera at 0.4 of the other's brightness has
    less detail everywhere, which is no smudge."""
    left, right = rectified_pairs[0]
    times = np.arange(0, 1.0, 1 / 15)
    view = BlockedView()
    said = [view.blocked(left, smudge(right, sigma), t) for t in times]
    assert all(s == ["right"] for s in said), said
    view = BlockedView()
    assert all(view.blocked(smudge(left, sigma), right, t) == ["left"] for t in times)
    dim = (right * 0.4).astype(np.uint8)
    view = BlockedView()
    assert all(view.blocked(left, dim, t) == [] for t in times)


@pytest.mark.parametrize("recording, cameras", [("karlsruhe-0023", ("left", "right")),
                                               ("euroc-v1-01", ("cam0", "cam1"))])
def test_neither_recording_has_a_blocked_view_in_any_pair(recording, cameras):
    """What one camera sees and the other does not (a window saturated in one, the near edge of the
    other's view) stays under BlockedView.SHARE of the tiles in every pair of both recordings:
    karlsruhe at most 4.7 %, euroc 6.2 %."""
    folder = KARLSRUHE.parent / recording
    if not folder.exists():
        pytest.skip(f"{folder} absent")
    lefts, rights = (sorted((folder / c).glob("*.png")) for c in cameras)
    assert len(lefts) == len(rights) >= 16
    grey = cv2.IMREAD_GRAYSCALE
    worst = max(max(BlockedView.shares(cv2.imread(str(a), grey), cv2.imread(str(b), grey)))
                for a, b in zip(lefts, rights))
    assert worst < BlockedView.SHARE - 0.03, worst


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
def test_a_finger_on_the_right_lens_is_said_by_every_list_on_the_street():
    """The street (karlsruhe) with a dark disc over a sixth of the right picture: the white car 17 m
    ahead went from the lists, which said nothing. Now every list says view-blocked, from the first
    pair, and the unblocked street none."""
    from common.files import read_image
    from cores.matching.config import MatcherConfig
    from evaluation.recordings import open_recording

    rec = open_recording(KARLSRUHE)
    for blocked in (False, True):
        pipe = Pipeline(rec.calibration, MatcherConfig(num_disparities="auto"), SegmenterSettings())
        said = []
        for k in range(12):
            right = read_image(rec.pairs[k][1])
            f = pipe.process(read_image(rec.pairs[k][0]), finger(right) if blocked else right,
                             t_s=rec.stamps_s[k], seq=k)
            said.append((rec.stamps_s[k], "view-blocked" in f.result.obstacles.degraded))
        assert all(flag == blocked for t, flag in said), (blocked, said)
    assert pipe.builder.checks.blocked == ["right"]
