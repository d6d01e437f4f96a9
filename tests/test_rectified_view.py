"""What part of the rectified picture each camera saw (rectify's alpha above 0): the matcher measures
nothing within its reach of the black beyond it, so its seam is no wall of phantom depths.

On the room (EuRoC, a wide lens) with alpha 1, a quarter of each rectified picture is black. Before,
bm boxed the seam along both sides as obstacles 1.7-1.9 m away (2 of 3 obstacles a frame, flat on the
floor), sgbm 81 % of its obstacles, and rectify's near check said nearer-than-range on 15 of 16 lists.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from common import codec
from common.messages import CameraModel, StereoFrame
from cores import camera
from cores.calibration.rectify import Rectifier, camera_model_message
from cores.matching.config import MatcherConfig
from cores.matching.stage import window_reach
from cores.pipeline import Pipeline
from cores.segmentation.settings import SegmenterSettings
from services.disparity.computer import FrameComputer

EUROC = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "euroc-v1-01"
needs_euroc = pytest.mark.skipif(not (EUROC / "cam0").exists(), reason="../shared/data/real/euroc-v1-01 absent")


def seen_by_maps(rectifier: Rectifier, k: int) -> np.ndarray:
    mx, my = rectifier._maps[k]
    w, h = rectifier.size
    return (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)


def test_the_outline_is_what_the_camera_saw_and_alpha_0_has_none():
    rig = camera.PROFILES["lifecam-studio"]()
    assert Rectifier(rig, 0.0).model.view_left is None and Rectifier(rig, 0.0).model.view_right is None
    wide = Rectifier(rig, 1.0)
    masks = camera.view_masks(wide.model, 0)
    assert masks is not None
    for k, mask in enumerate(masks):
        truth = seen_by_maps(wide, k)
        assert 0.03 < 1.0 - truth.mean() < 0.1  # alpha 1 leaves a few % of this rig's picture black
        # the polygon follows the maps' outline within its tolerance: they differ only along it
        differ = mask != truth
        near_outline = cv2.dilate((truth != cv2.erode(truth.astype(np.uint8), np.ones((3, 3), np.uint8))
                                   ).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        assert not (differ & ~near_outline).any()
    # an already-rectified calibration passes pictures as they are: all of them seen
    assert Rectifier(camera.RectifiedRig(camera.RectifiedModel(640, 480, 500.0, 320.0, 240.0, 0.1))).model.view_left \
        is None


def test_the_outline_travels_with_the_camera_model_and_a_broken_one_is_refused():
    model = Rectifier(camera.PROFILES["lifecam-studio"](), 1.0).model
    msg = camera_model_message(model)
    back = codec.decode(codec.encode(StereoFrame(robot_id="r", seq=0, stamp_ns=0, left=codec.image_from_array(
        np.zeros((4, 4), np.uint8)), right=codec.image_from_array(np.zeros((4, 4), np.uint8)), camera=msg)),
        StereoFrame)
    assert back.camera is not None and camera.model_of(back.camera) == model
    with pytest.raises(ValueError, match="view_left"):
        CameraModel(**{**msg.model_dump(), "view_left": [(0.0, 0.0), (1.0, 1.0)]})
    with pytest.raises(ValueError, match="view_right"):
        CameraModel(**{**msg.model_dump(), "view_right": [(0.0, 0.0), (float("nan"), 1.0), (2.0, 0.0)]})
    with pytest.raises(ValueError, match="view_right"):  # would overflow the rasteriser's fixed point
        CameraModel(**{**msg.model_dump(), "view_right": [(0.0, 0.0), (1e9, 1.0), (2.0, 0.0)]})


@needs_euroc
@pytest.mark.parametrize("method", ["bm", "sgbm", "dense"])
def test_the_room_with_alpha_1_has_no_phantom_seam_and_nothing_said_nearer(method):
    from evaluation.recordings import open_recording

    rec = open_recording(EUROC)
    pairs = [(cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE), cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE))
             for lp, rp in rec.pairs[:16:4]]
    cfg = MatcherConfig(method=method)
    wide = Pipeline(rec.calibration, cfg, SegmenterSettings(), alpha=1.0)
    assert wide.model.view_left is not None
    reach = window_reach(wide.matching.matcher(wide.model.focal_px, wide.model.baseline_m, wide.model.width).config)
    seen = camera.view_masks(wide.model, reach)
    band = camera.view_masks(wide.model, reach + 20)
    assert seen is not None and band is not None
    cropped = Pipeline(rec.calibration, cfg, SegmenterSettings(), alpha=0.0)
    for k, (left, right) in enumerate(pairs):
        f = wide.process(left, right, t_s=0.05 * k, seq=k)
        measured = np.isfinite(f.disparity)
        assert not (measured & ~seen[0]).any()  # nothing within the matcher's reach of the black
        ol = f.result.obstacles
        assert "nearer-than-range" not in ol.degraded and not ol.degraded, ol.degraded
        near_seam = [o for o in ol.obstacles if o.distance_m < 2.0
                     and not band[0][o.bbox_px[1]:o.bbox_px[3] + 1, o.bbox_px[0]:o.bbox_px[2] + 1].all()]
        if method != "sgbm":  # sgbm also boxes a glossy mat at the picture's bottom, which alpha 0 crops away
            assert not near_seam, [(o.distance_m, o.bbox_px) for o in near_seam]
        g, g0 = ol.ground, cropped.process(left, right, t_s=0.05 * k, seq=k).result.obstacles.ground
        assert g is not None and g0 is not None
        assert abs(g.height_m - g0.height_m) < 0.03 and abs(g.pitch_deg - g0.pitch_deg) < 1.0


@needs_euroc
def test_a_disparity_worker_drops_the_seam_as_the_pipeline_does():
    """The disparity service reads the outline from the pair's camera model: its map is the
    in-process pipeline's, to the bit."""
    from evaluation.recordings import open_recording

    rec = open_recording(EUROC)
    left, right = (cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in rec.pairs[0])
    pipe = Pipeline(rec.calibration, MatcherConfig(), SegmenterSettings(), alpha=1.0)
    rl, rr = pipe.rectify(left, right)
    frame = StereoFrame(robot_id="r", seq=0, stamp_ns=1, left=codec.image_from_array(rl),
                        right=codec.image_from_array(rr), camera=pipe.rectifier.model_message)
    frame = codec.decode(codec.encode(frame), StereoFrame)  # as it arrives over the network
    got = FrameComputer(MatcherConfig()).compute(frame, "w")
    want = pipe.match(rl, rr).match.disparity
    assert np.array_equal(codec.array_from_image(got.image, "map"), want)
    # and without the outline (an old rectify) the seam is matched: the test sees a difference
    blind = frame.model_copy(update={"camera": frame.camera.model_copy(update={"view_left": None,  # type: ignore
                                                                                "view_right": None})})
    assert not np.array_equal(codec.array_from_image(FrameComputer(MatcherConfig()).compute(blind, "w").image, "m"),
                              want)


def test_a_recording_of_pairs_rectified_with_alpha_1_keeps_the_outline_for_replay(tmp_path):
    """Replay hands rectify the rectified calibration the recording carries (`rectified: true`): with
    the outline in it, the replayed pairs' seam is left alone as it was live."""
    from cores.recording import rectified_calibration_yaml

    model = Rectifier(camera.PROFILES["lifecam-studio"](), 1.0).model
    path = tmp_path / "rectified.yaml"
    path.write_text(rectified_calibration_yaml(camera_model_message(model)))
    again = camera.load_calibration(str(path))
    assert isinstance(again, camera.RectifiedRig) and again.model == model
    assert Rectifier(again).model == model  # passed through, outline and all
    path.write_text(path.read_text().replace("view_left:", "view_left: [[0, 0], [1, 1]]\nold_left:"))
    with pytest.raises(camera.CalibrationError, match="view_left"):
        camera.load_calibration(str(path))
