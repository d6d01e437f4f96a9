"""The cores chained in one process (no Zenoh) on the synthetic scene, against ground truth."""
from __future__ import annotations

import numpy as np
import pytest

from common.errors import BallbotError
from cores import camera
from cores.calibration.rectify import Rectifier
from cores.matching.disparity import to_float
from cores.matching.matchers import MatcherConfig, StereoMatcher
from cores.segmentation.ground import plane_from_mount
from cores.segmentation.mount import Mount
from cores.segmentation.seed import segment
from cores.segmentation.settings import SegmenterSettings
from services.capture.sources import SyntheticSource


@pytest.fixture(scope="module")
def chain():
    src = SyntheticSource("two-boxes", "lifecam-studio", 30.0)
    pair = src.read()
    rect = Rectifier(camera.load_calibration("lifecam-studio"))
    left, right = rect.rectify(pair.left, pair.right)
    cfg = MatcherConfig(num_disparities=64)
    disparity = to_float(StereoMatcher(cfg).compute(left, right), 16.0, cfg.invalid_value)
    return pair, rect, left, right, disparity


def test_rectified_rows_are_epipolar_lines(chain):
    import cv2
    _, _, left, right, _ = chain
    orb = cv2.ORB.create(2000)
    kl, dl = orb.detectAndCompute(left, None)
    kr, dr = orb.detectAndCompute(right, None)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
    dy = np.array([abs(kl[m.queryIdx].pt[1] - kr[m.trainIdx].pt[1]) for m in matches])
    dx = np.array([kl[m.queryIdx].pt[0] - kr[m.trainIdx].pt[0] for m in matches])
    good = (dx > 0) & (dx < 80)
    assert good.sum() > 100
    assert np.median(dy[good]) < 0.5


def test_block_matching_agrees_with_true_depth(chain):
    pair, rect, _, _, disparity = chain
    from sim import Scene, SyntheticWorld
    rig = camera.load_calibration("lifecam-studio")
    world = SyntheticWorld(Scene.default(), rig, rect.rectification, seed=0)
    truth = world.true_disparity(0.0)
    both = np.isfinite(truth) & np.isfinite(disparity) & (truth > 20)
    assert both.mean() > 0.2
    bad = np.abs(disparity[both] - truth[both]) > 1.0
    assert bad.mean() < 0.05


def test_seed_segmentation_finds_both_boxes_within_5_percent(chain):
    pair, rect, _, _, disparity = chain
    floor = plane_from_mount(Mount(1.0, 15.0), rect.model)
    dets = segment(disparity, rect.model, SegmenterSettings(method="seed"), floor)
    assert len(dets) == len(pair.truth) == 2
    for t in pair.truth:
        c = np.asarray(t.visible_centroid_m)
        d = min(dets, key=lambda x: np.linalg.norm(x.position_m - c))
        assert np.linalg.norm(d.position_m - c) <= 0.05 * np.linalg.norm(c)
        assert d.distance_m <= d.position_m[2] + 0.05
        assert 0.5 < d.confidence <= 1.0


def test_without_floor_removal_the_floor_swallows_the_boxes(chain):
    """The thesis's pipeline alone: the textured floor in range joins both boxes into one region.
    This is why the camera mount is a setting."""
    pair, rect, _, _, disparity = chain
    dets = segment(disparity, rect.model, SegmenterSettings(method="seed"), floor=None)
    assert len(dets) < len(pair.truth)


def test_empty_and_all_invalid_disparity_give_no_obstacles(chain):
    _, rect, _, _, _ = chain
    m = rect.model
    assert segment(np.full((m.height, m.width), np.nan, np.float32), m) == []
    assert segment(np.zeros((m.height, m.width), np.float32), m) == []
    with pytest.raises(ValueError, match="camera model"):
        segment(np.zeros((10, 10), np.float32), m)


def test_rectifier_refuses_images_of_another_size():
    rect = Rectifier(camera.load_calibration("lifecam-studio"))
    small = np.zeros((240, 320), np.uint8)
    with pytest.raises(BallbotError, match="left: image is 320x240.*640x480"):
        rect.rectify(small, small)
