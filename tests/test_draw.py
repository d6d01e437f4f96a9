"""draw.py: one frame drawn over the rectified left image, checked pixel by pixel on synthetic input."""
from __future__ import annotations

import numpy as np
import pytest

from common.messages import FreeSpace, GroundEstimate, Obstacle, ObstacleList
from common.settings import MountSettings
from cores import camera
from cores.segmentation import draw as D
from cores.segmentation.ground import frame_mount
from cores.segmentation.mount import Mount

MODEL = camera.RectifiedModel(320, 240, 200.0, 160.0, 120.0, 0.1)
GREY = 100


def _obstacle(id_: int, bbox, confirmed: bool, distance: float = 2.0) -> Obstacle:
    return Obstacle(id=id_, position_m=(0.0, 0.0, distance), size_m=(0.3, 0.3, 0.3), distance_m=distance,
                    bbox_px=bbox, area_px=100, disparity_px=10.0, confidence=1.0, confirmed=confirmed)


def _list(obstacles, ground=None) -> ObstacleList:
    """A list as the segmenter makes it: with a ground, the mount it puts the camera at (frame_mount)."""
    mount, source = frame_mount(ground, MountSettings())
    return ObstacleList(robot_id="t", seq=7, stamp_ns=0, publish_ns=0, stale=False, obstacles=obstacles, ground=ground,
                        mount=None if mount is None else mount.message(source))


def _is(px, colour) -> bool:
    return tuple(int(c) for c in px) == tuple(colour)


def test_boxes_are_drawn_where_the_bbox_says_confirmed_solid_unconfirmed_dashed():
    img = np.full((240, 320), GREY, np.uint8)
    confirmed = _obstacle(3, (20, 60, 80, 120), True)
    tentative = _obstacle(9, (150, 80, 250, 200), False, 4.0)
    out = D.draw_frame(img, _list([confirmed, tentative]), MODEL)
    assert out.shape == (240, 320, 3) and out.dtype == np.uint8
    assert img.max() == GREY  # the input is not drawn on
    # confirmed: every pixel of all four sides, thick
    assert all(_is(out[60, x], D.CONFIRMED) for x in range(20, 80))
    assert all(_is(out[119, x], D.CONFIRMED) for x in range(20, 80))
    assert all(_is(out[y, 20], D.CONFIRMED) and _is(out[y, 79], D.CONFIRMED) for y in range(60, 120))
    assert _is(out[61, 50], D.CONFIRMED)  # 2 px thick
    assert _is(out[90, 50], (GREY,) * 3) and _is(out[90, 85], (GREY,) * 3)  # inside and outside untouched
    # unconfirmed: its own colour, dashed (drawn and gaps along each side), thin
    left = [_is(out[y, 150], D.UNCONFIRMED) for y in range(80, 200)]
    top = [_is(out[80, x], D.UNCONFIRMED) for x in range(150, 250)]
    for side in (left, top):
        assert 0.3 < np.mean(side) < 0.7
    assert _is(out[84, 150], D.UNCONFIRMED) and _is(out[80, 154], D.UNCONFIRMED)
    assert _is(out[150, 152], (GREY,) * 3)
    assert not np.all(out[80:200, 150:250] == D.CONFIRMED, axis=-1).any()
    # the labels: text in each box's colour (anti-aliased: near it) just above it
    def near(a, colour):
        return (np.abs(a.astype(int) - colour).max(axis=-1) < 90).sum()

    assert near(out[40:59, 20:90], D.CONFIRMED) > 20 and near(out[40:59, 20:90], D.UNCONFIRMED) == 0
    assert near(out[60:79, 150:250], D.UNCONFIRMED) > 20 and near(out[60:79, 150:250], D.CONFIRMED) == 0


def test_caption_band_and_colour_input():
    img = np.zeros((240, 320, 3), np.uint8)
    img[..., 2] = 200  # red
    ground = GroundEstimate(height_m=1.0, pitch_deg=20.0, roll_deg=0.0, source="fitted", inlier_fraction=0.5)
    lst = _list([_obstacle(1, (100, 100, 140, 140), True)], ground)
    out = D.draw_frame(img, lst, MODEL)
    band = out[: D.CAPTION_PX]
    assert (band == 255).all(axis=-1).sum() > 50  # white text
    assert band[..., 2].max() <= 255 and np.median(band[..., 2]) < 100  # darkened
    text = D.caption(lst)
    for part in ("seq 7", "1 obstacle", "h 1.00 m", "pitch +20.0", "fitted"):
        assert part in text, (part, text)
    assert "STALE" not in text and "NOT A FULL VIEW" not in text
    flagged = D.caption(lst.model_copy(update={"stale": True, "degraded": ["standing-not-listed"]}))
    assert flagged.endswith("  STALE  NOT A FULL VIEW: standing-not-listed"), flagged
    assert _is(out[200, 10], (0, 0, 200))  # elsewhere the colour image as it was


def _project(mount: Mount, p_base) -> tuple[int, int]:
    """A base-frame point -> its pixel (independent of draw.py: the inverse of Mount.to_base)."""
    p = mount.R_base_camera.T @ (np.asarray(p_base, float) - mount.origin_base)
    return int(round(MODEL.focal_px * p[0] / p[2] + MODEL.cx)), int(round(MODEL.focal_px * p[1] / p[2] + MODEL.cy))


def test_free_space_cells_project_onto_the_ground_green_free_red_occupied():
    ground = GroundEstimate(height_m=1.0, pitch_deg=20.0, roll_deg=3.0, source="fitted")
    mount, _ = frame_mount(ground, MountSettings())
    res, n = 0.5, 20
    cells = np.full((n, n), -1, np.int8)  # row: y from -5 m, col: x from 0 m
    cells[:, 2:8] = 0  # x 1..4 m free
    cells[9:11, 6] = 100  # x 3..3.5 m, y -0.5..0.5 m occupied
    fs = FreeSpace(robot_id="t", seq=7, stamp_ns=0, publish_ns=0, resolution_m=res, width=n, height=n,
                   origin_m=(0.0, -5.0), cells=cells.tobytes())
    img = np.full((240, 320), GREY, np.uint8)
    out = D.draw_frame(img, _list([], ground), MODEL, fs)
    assert np.array_equal(out, D.draw_frame(img, _list([], ground), MODEL, fs, mount))
    free_px = _project(mount, (1.75, 0.25, 0.0))
    occ_px = _project(mount, (3.25, -0.25, 0.0))
    unknown_px = _project(mount, (0.9, 0.0, 0.0))  # ahead of the free cells
    for u, v in (free_px, occ_px, unknown_px):
        assert 0 <= u < 320 and D.CAPTION_PX < v < 240
    b, g, r = (int(c) for c in out[free_px[1], free_px[0]])
    assert g > GREY + 20 and b < GREY and r < GREY
    b, g, r = (int(c) for c in out[occ_px[1], occ_px[0]])
    assert r > GREY + 40 and g < GREY and b < GREY
    assert _is(out[unknown_px[1], unknown_px[0]], (GREY,) * 3)
    assert _is(out[30, 160], (GREY,) * 3)  # above the horizon: nothing
    # the same grid with the mount yawed 90 deg left sees none of it (the cells lie to its right)
    turned = D.draw_frame(img, _list([], ground), MODEL, fs,
                          frame_mount(ground, MountSettings(yaw_deg=90.0, x_m=-6.0))[0])
    assert np.all(turned[D.CAPTION_PX:] == GREY)
    # no ground estimate: no grid
    plain = D.draw_frame(img, _list([]), MODEL, fs)
    assert np.all(plain[D.CAPTION_PX:] == GREY)


def test_bad_images_are_refused():
    with pytest.raises(ValueError, match="320x240"):
        D.draw_frame(np.zeros((100, 100), np.uint8), _list([]), MODEL)
    with pytest.raises(ValueError, match="8-bit"):
        D.draw_frame(np.zeros((240, 320), np.float32), _list([]), MODEL)


def test_obstacles_command_draws_one_picture_per_pair_and_prints_ground_and_free_space(tmp_path, capsys):
    import json
    import re

    import cv2

    from ballbot_vision.cli import main
    from common.messages import ObstacleList
    from sim import Scene, SyntheticWorld

    rig = camera.load_calibration("lifecam-studio")
    world = SyntheticWorld(Scene.builtin("touching"), rig, camera.rectify_rig(rig), seed=0)
    (tmp_path / "L").mkdir()
    (tmp_path / "R").mkdir()
    for k in range(2):
        left, right = world.render(k / 15)
        cv2.imwrite(str(tmp_path / "L" / f"left{k}.png"), left)
        cv2.imwrite(str(tmp_path / "R" / f"right{k}.png"), right)
    out = tmp_path / "pictures"
    assert main(["obstacles", str(tmp_path / "L"), str(tmp_path / "R"), "--calibration", "lifecam-studio",
                 "--draw", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.count("  ground: ") == 2 and text.count("  free space: ") == 2
    # each list says where it looked, as `watch` does (an empty one says nothing of elsewhere), and each
    # obstacle how far its track goes
    heads = [line for line in text.splitlines() if "obstacle(s)" in line]
    assert len(heads) == 2 and all(re.search(r"2 obstacle\(s\) at [\d.]+-[\d.]+ m, [+-]\d+\.\.[+-]\d+ deg$", h)
                                   for h in heads), heads
    first, second = text.split(heads[1])
    assert first.count(" 1 frame, unconfirmed") == 2 and second.count(" 2 frames") == 2, text
    pictures = sorted(p.name for p in out.glob("*.png"))
    assert pictures == ["left0.png", "left1.png"]
    pic = cv2.imread(str(out / "left1.png"))
    assert pic.shape == (480, 640, 3)
    assert (np.all(pic == D.CONFIRMED, axis=-1) | np.all(pic == D.UNCONFIRMED, axis=-1)).sum() > 100
    # --json stays one ObstacleList per pair
    assert main(["obstacles", str(tmp_path / "L"), str(tmp_path / "R"), "--calibration", "lifecam-studio",
                 "--json"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2
    for line in lines:
        doc = json.loads(line)
        doc.pop("left"), doc.pop("right")
        assert len(ObstacleList.model_validate(doc).obstacles) == 2


def test_truths_matched_dashed_cyan_missed_solid_orange():
    pic = np.full((240, 320, 3), GREY, np.uint8)
    D.draw_truths(pic, [("a", (20, 40, 60, 100), True), ("b", (150, 50, 200, 120), False)])
    assert _is(pic[40, 20], D.TRUTH) and _is(pic[70, 20], D.TRUTH)       # corner, and on the left side
    assert not _is(pic[40, 24], D.TRUTH)                                  # a dash's gap: matched is dashed
    assert all(_is(pic[50, x], D.MISSED) for x in range(150, 201))        # missed: a solid top side
    assert all(_is(pic[y, 200], D.MISSED) for y in range(50, 121))
    assert _is(pic[70, 40], (GREY,) * 3) and _is(pic[80, 175], (GREY,) * 3)  # insides untouched


def test_eval_draw_writes_each_scenario_frame_with_its_truths(tmp_path, capsys):
    import cv2

    from ballbot_vision.cli import main

    out = tmp_path / "pictures"
    assert main(["eval", "touching", "--method", "layers", "--frames", "2", "--draw", str(out), "--json"]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in out.glob("*.png")) == ["touching-layers-000.png", "touching-layers-001.png"]
    pic = cv2.imread(str(out / "touching-layers-001.png"))
    assert pic.shape == (480, 640, 3)
    obstacles = (np.all(pic == D.CONFIRMED, axis=-1) | np.all(pic == D.UNCONFIRMED, axis=-1)).sum()
    assert obstacles > 100 and np.all(pic == D.TRUTH, axis=-1).sum() > 100  # both boxes found: drawn, with truths
    assert np.all(pic == D.MISSED, axis=-1).sum() == 0
    blocked = tmp_path / "file"
    blocked.write_text("")
    # a folder that cannot be made: a clear error naming it, before any rendering
    assert main(["eval", "touching", "--method", "layers", "--frames", "1", "--draw", str(blocked / "sub")]) != 0
    err = capsys.readouterr().err
    assert f"--draw {blocked / 'sub'}" in err and "Traceback" not in err
