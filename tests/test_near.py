"""What stands nearer than the vision range: rectify's coarse wide search (cores/calibration/near.py)
and the segmenter's reading of it (cores/segmentation/near.py). A person who steps up to the camera
is beyond the matcher's search; before this check the lists covered their range, empty, and said
nothing."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from common.messages import NearField
from common.settings import MountSettings
from cores import camera
from cores.calibration.near import NearCheck
from cores.calibration.rectify import Rectifier
from cores.matching.config import MatcherConfig
from cores.pipeline import Pipeline
from cores.segmentation.settings import SegmenterSettings

APPROACH = """
name: approach
description: a person-sized textured box walks up to the camera and stops 0.3 m from it
camera_height_m: 1.0
camera_pitch_deg: 15.0
wall_distance_m: 5.0
noise_sigma: 1.5
objects:
  - name: person
    kind: box
    size: [0.6, 1.8, 0.3]
    texture_seed: 5
    path:
      waypoints: [[3.0, 0.0], [0.45, 0.0]]
      speed_mps: 0.6
      loop: false
"""
RATE_HZ = 5.0


def face_m(k: int) -> float:
    """The box's face, m ahead of the camera, at pair k (its centre walks from 3 m to 0.45 m)."""
    return max(0.45, 3.0 - 0.6 * k / RATE_HZ) - 0.15


@pytest.fixture(scope="module")
def approach(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scene") / "approach.yaml"
    path.write_text(APPROACH)
    return path


def frames(scene: Path | str, n: int, rate_hz: float = RATE_HZ):
    from services.capture.sources import SyntheticSource

    src = SyntheticSource(str(scene), "lifecam-studio", rate_hz)
    return [src.read() for _ in range(n)]


def test_the_coarse_search_measures_a_face_from_3_m_to_0_3_m(approach):
    rect = Rectifier(camera.load_calibration("lifecam-studio"), 0.0)
    model, check = rect.model, NearCheck()
    for k, pair in enumerate(frames(approach, 30)):
        if k % 4:
            continue
        near = check.field(*rect.rectify(pair.left, pair.right))
        assert near is not None and (near.width, near.height) == (160, 120)
        d = np.frombuffer(near.data, np.uint8).reshape(120, 160) / 4 * model.width / near.width
        centre = d[55:65, 75:85]  # the box, whatever its distance
        at = model.baseline_m * model.focal_px / np.median(centre)
        assert abs(at - face_m(k)) < 0.05 * face_m(k) + 0.02, (k, at, face_m(k))


@pytest.fixture(scope="module")
def approach_left(tmp_path_factory) -> Path:
    """The same walk 0.35 m left of the axis: at 0.3 m the box fills the picture's left third."""
    path = tmp_path_factory.mktemp("scene") / "approach-left.yaml"
    path.write_text(APPROACH.replace("[[3.0, 0.0], [0.45, 0.0]]", "[[3.0, 0.35], [0.45, 0.35]]"))
    return path


@pytest.mark.parametrize("fit_floor", [False, True])
@pytest.mark.parametrize("method, side", [("bm", "ahead"), ("sgbm", "ahead"), ("dense", "ahead"), ("bm", "left")])
def test_a_list_says_nearer_than_range_while_someone_stands_nearer_than_its_range(approach, approach_left, method,
                                                                                  side, fit_floor):
    """The mount configured (1 m, 15 deg: the scene's); fit_floor false is where nothing else was said:
    bm listed nothing, sgbm and dense obstacles at the search's limit or at the wall. On the left the
    box is in the columns block matching leaves unmatched (the coarse search matches them from the
    right image)."""
    pipe = Pipeline(camera.load_calibration("lifecam-studio"), MatcherConfig(method=method),
                    SegmenterSettings(fit_floor=fit_floor), mount=MountSettings(height_m=1.0, pitch_deg=15.0))
    said = []
    for k, pair in enumerate(frames(approach if side == "ahead" else approach_left, 36)):
        lst = pipe.process(pair.left, pair.right, t_s=k / RATE_HZ, seq=k).result.obstacles
        said.append((face_m(k), "nearer-than-range" in lst.degraded))
    assert all(flag for face, flag in said if face < 0.95), said
    assert not any(flag for face, flag in said if face > 1.1), said


@pytest.mark.parametrize("scene", ["sway", "people-queue", "chair"])
def test_the_floor_below_a_pitched_low_camera_is_not_nearer_than_the_range(scene):
    """The sway's camera, 0.5-1.2 m up and pitching +-10 deg, sees floor nearer than 1 m at the
    picture's bottom: floor, not a blocked view (the evaluation's 3 s at 15 Hz; 6 s on, the sway's robot
    has driven to within a metre of the table and the walking person, and then the lists say so)."""
    pipe = Pipeline(camera.load_calibration("lifecam-studio"), MatcherConfig(), SegmenterSettings())
    for k, pair in enumerate(frames(scene, 45, 15.0)):
        lst = pipe.process(pair.left, pair.right, t_s=k / 15.0, seq=k).result.obstacles
        assert "nearer-than-range" not in lst.degraded, (k, pipe.builder.near)


def test_a_near_field_that_does_not_add_up_is_refused():
    ok = {"width": 4, "height": 2, "image_width": 16, "image_height": 8, "data": bytes(8)}
    NearField.model_validate(ok)
    for bad in ({"data": bytes(7)}, {"width": 32}, {"width": 0}, {"image_height": 1}):
        with pytest.raises(ValidationError):
            NearField.model_validate({**ok, **bad})
