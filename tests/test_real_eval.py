"""eval --real, mount estimate and their parts: the independent road profile, INS odometry, the
config merge on synthetic input; then a few frames of the real recordings in
../shared/data/real (skipped with the reason when that folder is absent)."""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ballbot_vision.cli import main
from common.errors import BallbotError, ConfigError
from common.messages import GroundEstimate
from common.settings import MountSettings, load_settings
from cores import camera
from cores.segmentation import draw as D
from cores.segmentation.mount import Mount
from cores.segmentation.mount_estimate import estimate_from_grounds, merge_into_config
from cores.segmentation.settings import SegmenterSettings
from evaluation import real as R
from evaluation import recordings, road_profile


def _real_data() -> Path:
    """../shared/data/real beside the repository (a worktree sits one level deeper), or BALLBOT_REAL_DATA."""
    if os.environ.get("BALLBOT_REAL_DATA"):
        return Path(os.environ["BALLBOT_REAL_DATA"])
    repo = Path(__file__).resolve().parents[1]
    return next((p / "shared" / "data" / "real" for p in (repo.parent, repo.parent.parent)
                 if (p / "shared" / "data" / "real").is_dir()), repo.parent / "shared" / "data" / "real")


REAL = _real_data()
KARLSRUHE = REAL / "karlsruhe-0023"
EUROC = REAL / "euroc-v1-01"
needs_karlsruhe = pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(),
                                     reason=f"real recording {KARLSRUHE} absent (see DESIGN.md: ../shared/data/real)")
needs_euroc = pytest.mark.skipif(not (EUROC / "cam0_sensor.yaml").exists(),
                                 reason=f"real recording {EUROC} absent (see DESIGN.md: ../shared/data/real)")

MODEL = camera.RectifiedModel(640, 360, 500.0, 320.0, 180.0, 0.5)


def _road_scene(height_m: float, pitch_deg: float) -> tuple[np.ndarray, tuple[int, int, int, int], float]:
    """Disparity of a flat road seen from `height_m` at `pitch_deg`, with a 1.2 m tall wall standing
    on it 10 m ahead in the middle third of the image. -> (disparity, the wall's box, its disparity)."""
    m = Mount(height_m, pitch_deg)
    v, u = np.mgrid[0:MODEL.height, 0:MODEL.width].astype(np.float64)
    ray = np.stack([(u - MODEL.cx) / MODEL.focal_px, (v - MODEL.cy) / MODEL.focal_px, np.ones_like(u)], -1)
    down = ray @ m.down_camera  # > 0: the ray meets the road
    with np.errstate(divide="ignore", invalid="ignore"):
        z_road = np.where(down > 1e-6, height_m / down, np.inf)  # depth of the road along each ray
    d = np.where(np.isfinite(z_road), MODEL.focal_px * MODEL.baseline_m / z_road, np.nan)
    wall_z = 10.0
    # the wall stands 1.2 m high on the road at depth 10 m (base x ~ 10 m): rows between its foot and top
    p_foot = m.R_base_camera.T @ (np.array([wall_z, 0.0, 0.0]) - m.origin_base)
    p_top = m.R_base_camera.T @ (np.array([wall_z, 0.0, 1.2]) - m.origin_base)
    v_foot = MODEL.focal_px * p_foot[1] / p_foot[2] + MODEL.cy
    v_top = MODEL.focal_px * p_top[1] / p_top[2] + MODEL.cy
    cols = slice(MODEL.width // 3, 2 * MODEL.width // 3)
    rows = slice(int(math.ceil(v_top)), int(v_foot))
    wall_d = MODEL.focal_px * MODEL.baseline_m / p_foot[2]
    d[rows, cols] = wall_d
    d[d < 0.5] = np.nan
    return d.astype(np.float32), (cols.start, rows.start, cols.stop, rows.stop), wall_d


def test_road_profile_recovers_height_and_pitch_and_judges_heights():
    d, wall_box, wall_d = _road_scene(1.6, 6.0)
    road = road_profile.fit_road_profile(d, MODEL)
    assert road is not None
    assert road.height_m == pytest.approx(1.6, rel=0.02)
    assert road.pitch_deg == pytest.approx(6.0, abs=0.2)
    # the wall's pixels reach 1.2 m (95th percentile: ~1.14 m); a patch of road (a marking) is flat
    assert road_profile.obstacle_height_p95(d, wall_box, wall_d, road) == pytest.approx(1.14, abs=0.06)
    mark = (20, 300, 120, 330)
    assert abs(road_profile.obstacle_height_p95(d, mark, float(np.nanmedian(d[300:330, 20:120])), road)) < 0.05
    assert road_profile.fit_road_profile(np.full_like(d, np.nan), MODEL) is None


def test_odometry_from_poses_is_base_frame_velocity_and_yaw_rate(tmp_path):
    t = np.arange(20) * 0.1
    yaw = 0.5 + 0.1 * t  # turning left at 0.1 rad/s, heading ~29 deg from x (east)
    speed = 10.0
    x = np.cumsum(np.r_[0, speed * 0.1 * np.cos(yaw[:-1] + 0.005)])
    y = np.cumsum(np.r_[0, speed * 0.1 * np.sin(yaw[:-1] + 0.005)])
    poses = np.zeros((20, 10))
    poses[:, 0] = 1.6e18 + t * 1e9
    poses[:, 4], poses[:, 5], poses[:, 9] = x, y, yaw
    poses[:, 8] = 2.07  # the unusable pitch column is not read
    odo = recordings.odometry_from_poses(poses)
    for o in odo[1:-1]:
        assert o.linear_mps[0] == pytest.approx(speed, rel=0.01)
        assert abs(o.linear_mps[1]) < 0.2
        assert o.angular_radps == pytest.approx((0.0, 0.0, 0.1), abs=1e-6)
    f = tmp_path / "insdata.txt"
    np.savetxt(f, poses)
    assert np.allclose(recordings.read_insdata(f), poses)
    poses[:, 9] += math.pi / 2  # yaw no longer the direction of travel: another convention
    np.savetxt(f, poses)
    with pytest.raises(BallbotError, match="direction of travel"):
        recordings.read_insdata(f)


def test_figures_count_flat_obstacles_and_track_life():
    def frame(k, obs):
        return R.FrameRecord(k, f"{k}.png", [R.ObstacleRecord(i, dist, True, h, None if h is None else h < 0.25)
                                             for i, dist, h in obs], None, None, 10.0, 20.0, 0.0)
    # track 1 seen in all 6 frames (near), track 2 in 2 frames (near, flat), track 3 far in 6 frames
    frames = [frame(k, [(1, 8.0, 1.0), (3, 25.0, None)] + ([(2, 5.0, 0.05)] if k < 2 else [])) for k in range(6)]
    f = R.figures(frames)
    assert f["median_obstacles_per_frame"] == 2 and f["max_obstacles_per_frame"] == 3
    assert f["flat_judged"] == 8 and f["flat_fraction"] == pytest.approx(2 / 8)
    assert f["near_obstacles"] == 8 and f["near_long_track_fraction"] == pytest.approx(6 / 8)
    assert f["tracks"] == 3 and f["median_track_frames"] == 6
    # track 2 was there in the first frame: it may have lived longer before the run began, so its
    # sightings say nothing of the tracker and are left out of the censored figure
    assert f["near_censored"] == 2 and f["near_long_track_fraction_uncensored"] == pytest.approx(1.0)
    # a short track wholly inside the run counts against it
    frames[3].obstacles.append(R.ObstacleRecord(4, 6.0, False, 1.0, False))
    f = R.figures(frames)
    assert f["near_censored"] == 2 and f["near_long_track_fraction_uncensored"] == pytest.approx(6 / 7)
    # one that came into view cut by its edge (a post leaving the matcher's band), or left it so, was
    # seen briefly by the camera, not lost by the tracker: left out too; cut in its middle only, it counts
    frames[4].obstacles.append(R.ObstacleRecord(5, 6.0, False, 1.0, False, whole=False))
    frames[2].obstacles.append(R.ObstacleRecord(6, 7.0, False, 1.0, False))
    frames[3].obstacles.append(R.ObstacleRecord(6, 7.0, False, 1.0, False, whole=False))
    frames[4].obstacles.append(R.ObstacleRecord(6, 7.0, False, 1.0, False))
    f = R.figures(frames)
    assert f["near_censored"] == 3 and f["near_long_track_fraction_uncensored"] == pytest.approx(6 / 10)
    assert f["targets"]["flat_fraction"]["met"] is False and f["targets"]["median_obstacles_per_frame"]["met"] is True


def test_figures_count_a_track_lost_and_born_again_where_it_stood():
    """A thing tracked over the ground (odometry), lost for a frame and found again under a new id 0.4 m
    from where it was last seen: a restart, the tracker's loss. A new thing 3 m away, or one born where
    a track still lives (a neighbour), is not."""
    def o(i, xy, dist=8.0):
        return R.ObstacleRecord(i, dist, True, 1.0, False, world_xy=xy)

    frames = [R.FrameRecord(k, f"{k}.png", obs, None, None, 10.0, 20.0, 0.0) for k, obs in enumerate([
        [o(1, (10.0, 0.0)), o(2, (12.0, 3.0))],
        [o(1, (10.0, 0.1)), o(2, (12.0, 3.0))],
        [o(2, (12.0, 3.0))],
        [o(3, (10.4, 0.1)), o(2, (12.0, 3.0)), o(4, (13.0, 0.0)), o(5, (12.3, 3.0))],
    ])]
    f = R.figures(frames)
    assert f["near_births"] == 3 and f["track_restart_fraction"] == pytest.approx(1 / 3)


def test_merge_into_config_keeps_the_file_and_load_settings_reads_it(tmp_path):
    cfg = tmp_path / "robot.yaml"
    cfg.write_text("# my robot\nsegmenter:\n  method: layers  # the default\nmount:\n  height_m: 1.0  # taped\n\n"
                   "disparity:\n  method: sgbm\n")
    values = {"height_m": 0.944, "pitch_deg": 22.5, "roll_deg": -1.2}
    assert merge_into_config(cfg, values) is True
    text = cfg.read_text()
    assert "# my robot" in text and "# the default" in text and "height_m: 1.0" not in text
    m = load_settings(MountSettings, str(cfg))
    assert (m.height_m, m.pitch_deg, m.roll_deg) == (0.944, 22.5, -1.2)
    assert load_settings(SegmenterSettings, str(cfg)).method == "layers"
    from cores.matching.config import MatcherConfig
    assert load_settings(MatcherConfig, str(cfg)).method == "sgbm"
    flow = tmp_path / "flow.yaml"  # a flow-style section: rewritten from its content
    flow.write_text("segmenter: {method: seed}\nmount: {height_m: 1.0}\nviewer: {port: 8081}\n")
    assert merge_into_config(flow, values) is False
    assert load_settings(SegmenterSettings, str(flow)).method == "seed"
    assert load_settings(MountSettings, str(flow)).pitch_deg == 22.5
    new = tmp_path / "new.yaml"
    merge_into_config(new, values)
    assert load_settings(MountSettings, str(new)).roll_deg == -1.2
    before = cfg.read_text()
    with pytest.raises(ConfigError, match="not be valid"):
        merge_into_config(cfg, {"height_m": -1.0})
    assert cfg.read_text() == before


def test_no_fitted_ground_is_a_clear_error():
    prior = GroundEstimate(height_m=1.0, pitch_deg=15.0, roll_deg=0.0, source="prior")
    with pytest.raises(BallbotError, match=r"none of the 3 frame\(s\) gave a fitted ground plane \(got: prior 2, "
                                           r"no estimate 1\)"):
        estimate_from_grounds([prior, None, prior])
    fitted = [GroundEstimate(height_m=h, pitch_deg=5.0 + h, roll_deg=0.5, source="fitted") for h in (1.5, 1.6, 1.7)]
    e = estimate_from_grounds(fitted + [prior])
    assert (e.fitted, e.frames) == (3, 4)
    assert (e.height_m, e.pitch_deg, e.roll_deg) == pytest.approx((1.6, 6.6, 0.5))


# --- the real recordings -------------------------------------------------------------------------------

def _box_pixels(picture: np.ndarray) -> int:
    return int(np.all(picture == D.CONFIRMED, axis=-1).sum() + np.all(picture == D.UNCONFIRMED, axis=-1).sum())


@needs_karlsruhe
def test_karlsruhe_eval_real_gives_figures_and_pictures(tmp_path, capsys):
    out = tmp_path / "pictures"
    assert main(["eval", "--real", str(KARLSRUHE), "--frames", "3", "--draw", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    f = doc["figures"]
    assert f["frames"] == 3 and doc["odometry"] is True and doc["stamps"] == "insdata.txt"
    assert doc["settings"]["range_m"] == 30.0 and doc["settings"]["mount"]["height_m"] is None
    assert f["obstacles"] > 0 and f["median_obstacles_per_frame"] > 0
    assert f["flat_fraction"] is not None and 0 <= f["flat_fraction"] <= 1
    assert f["segment_ms"]["n"] == 3 and f["road_profile_frames"] == 3
    # the independent road model sees the car's camera ~1.65 m above the road, pitched a few degrees down
    assert 1.4 < f["road_height_m"]["median"] < 1.9 and 3 < f["road_pitch_deg"]["median"] < 10
    for name in ("median_obstacles_per_frame", "flat_fraction", "near_long_track_fraction"):
        assert name in f["targets"]
    pictures = sorted(out.glob("*.png"))
    assert [p.name for p in pictures] == ["I1_000000.png", "I1_000001.png", "I1_000002.png"]
    for p in pictures:
        pic = cv2.imread(str(p))
        assert pic.shape == (372, 1344, 3)
        assert _box_pixels(pic) > 100
    # the text report names the targets
    assert main(["eval", "--real", str(KARLSRUHE), "--frames", "1"]) == 0
    text = capsys.readouterr().out
    assert "obstacles per frame" in text and "target <= 25 (Karlsruhe)" in text and "max_range_m 30" in text


@needs_karlsruhe
def test_karlsruhe_insdata_odometry_is_the_car_driving_forward():
    rec = recordings.open_recording(KARLSRUHE)
    assert len(rec.odometry) == len(rec.pairs) == 40
    fwd = np.array([o.linear_mps[0] for o in rec.odometry])
    left = np.array([o.linear_mps[1] for o in rec.odometry])
    rate = np.array([o.angular_radps[2] for o in rec.odometry])
    assert 11.5 < np.median(fwd[:10]) < 13.0 and np.all(fwd > 8.5)  # ~12 m/s forward, braking to ~9
    assert np.all(np.abs(left) < 0.5) and np.all(np.abs(rate) < 0.1)
    assert 0.09 < np.median(np.diff(rec.stamps_s)) < 0.12  # ~10 Hz


@needs_euroc
def test_euroc_is_imported_rectified_and_evaluated(tmp_path, capsys):
    out = tmp_path / "pictures"
    assert main(["eval", "--real", str(EUROC), "--frames", "2", "--draw", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert "EuRoC, imported" in doc["calibration"] and doc["stamps"] == "image names (ns)"
    assert doc["odometry"] is False and doc["figures"]["frames"] == 2
    pictures = sorted(out.glob("*.png"))
    assert len(pictures) == 2 and cv2.imread(str(pictures[0])).shape == (480, 752, 3)
    rec = recordings.open_recording(EUROC)
    assert 0.04 < rec.stamps_s[1] < 0.06  # 20 Hz from the image names


@needs_euroc
def test_mount_estimate_writes_a_config_that_load_settings_reads(tmp_path, capsys):
    cfg = tmp_path / "drone.yaml"
    cfg.write_text("# the drone\ndisparity:\n  method: bm\n")
    assert main(["mount", "estimate", "--real", str(EUROC), "--frames", "3", "--write", str(cfg)]) == 0
    text = capsys.readouterr().out
    assert "height_m:" in text and "p10" in text and f"to {cfg}" in text
    s = load_settings(MountSettings, str(cfg))
    # the floor ~0.94 m below the camera looking ~22 deg down (the road profile agrees: see eval --real)
    assert 0.7 < s.height_m < 1.2 and 15 < s.pitch_deg < 30 and abs(s.roll_deg) < 5
    assert cfg.read_text().startswith("# the drone\ndisparity:\n  method: bm\n")


@needs_karlsruhe
def test_mount_estimate_without_a_fitted_ground_fails_clearly(tmp_path, capsys):
    # LEFT RIGHT --calibration form; the left images given as both sides: no depth, no ground
    left = str(KARLSRUHE / "left" / "I1_00000[01].png")
    rc = main(["mount", "estimate", left, left, "--calibration", str(KARLSRUHE / "calibration.yaml"),
               "--write", str(tmp_path / "x.yaml")])
    assert rc == 2
    assert "none of the 2 frame(s) gave a fitted ground plane" in capsys.readouterr().err
    assert not (tmp_path / "x.yaml").exists()
    # a vision range of 2 m sees no road (it starts ~4.3 m ahead of the car): the ground comes from
    # the road beyond it, as far as the rig measures
    rc = main(["mount", "estimate", left, str(KARLSRUHE / "right" / "I2_00000[01].png"), "--calibration",
               str(KARLSRUHE / "calibration.yaml"), "--max-range-m", "2", "--write", str(tmp_path / "x.yaml")])
    assert rc == 0, capsys.readouterr().err
    mount = yaml.safe_load((tmp_path / "x.yaml").read_text())["mount"]
    assert abs(mount["height_m"] - 1.64) < 0.08 and abs(mount["pitch_deg"] - 6.0) < 1.0, mount


# --- the acceptance figures on the real recordings (label-free) ---------------------------

@needs_karlsruhe
def test_karlsruhe_meets_the_real_scene_targets_with_the_default_segmenter():
    """The street drive, all 40 frames, default segmenter and matcher, the recording's odometry:
    median obstacles per frame <= 25, <= 5 % flat on the road (the independent road profile's
    judgement); of the confirmed obstacles within 20 m (what a planner trusts) >= 80 % in tracks
    seen in >= 5 frames, while tracks do not hop between objects (few jumps over the ground) and
    the parked street's obstacles come out nearly still over the ground; the ground is the road
    (its height and pitch agree with the independent profile). Of all near obstacles, confirmed
    or not, two in three live 5 frames (the issue's 80 % is not reached: see the README), with almost no
    track hopping more than 2 m over the ground."""
    from cores.matching.config import MatcherConfig
    from cores.segmentation.settings import SegmenterSettings

    rec = recordings.open_recording(KARLSRUHE)
    # the matcher's default search (auto: from the calibration and min_range_m; 128 px measures nothing
    # nearer than 2.9 m on this rig, and its lists say near-unmeasured, with no free space)
    report = R.evaluate_recording(rec, SegmenterSettings(max_range_m=30.0), MatcherConfig())
    f = report.figures
    assert f["degraded_frames"] == {}, f
    assert f["median_obstacles_per_frame"] <= 25, f
    assert f["flat_fraction"] <= 0.05, f
    assert f["near_confirmed_long_track_fraction"] >= 0.80, f
    assert f["near_long_track_fraction"] >= 0.60, f
    assert f["track_jump_fraction"] <= 0.05, f
    assert f["static_speed_mps"]["median"] <= 1.0, f
    assert f["ground_sources"] == {"fitted": 40}
    assert abs(f["ground_height_m"]["median"] - f["road_height_m"]["median"]) < 0.1
    assert abs(f["ground_pitch_deg"]["median"] - f["road_pitch_deg"]["median"]) < 1.0
    assert all(fr.freespace_free > 1000 for fr in report.frames)  # the road ahead is free


@needs_karlsruhe
def test_the_street_s_ground_is_trusted_when_the_segmenter_works_on_every_4th_pixel():
    """How much floor a fitted ground stands on is counted in pixels of the map, not in samples: at
    downsample 4 the same road is a quarter of the samples of downsample 2, and the street's lists said
    ground-uncertain in 30 frames of 40 (confidence 0.22) on a ground within 3 cm and 0.1 deg of the
    road profile's."""
    from cores.matching.config import MatcherConfig
    from cores.segmentation.settings import SegmenterSettings

    report = R.evaluate_recording(recordings.open_recording(KARLSRUHE), SegmenterSettings(max_range_m=30.0,
                                                                                          downsample=4),
                                  MatcherConfig(num_disparities="auto"), frames=20)
    f = report.figures
    assert f["degraded_frames"] == {} and f["ground_confidence"]["median"] >= 0.5, f
    assert f["flat_fraction"] <= 0.05, f
    assert abs(f["ground_height_m"]["median"] - f["road_height_m"]["median"]) < 0.1


@needs_karlsruhe
def test_the_street_with_the_left_right_check_is_seen_to_its_right_edge():
    """The check's mirrored match left the right image's right edge unmatched, and so failed every
    left pixel there: the right 320 px of 1344 were never measured while the lists' bearings said
    they were looked at, and the parked cars there were standing-not-listed in all 40 lists (7-13
    obstacles a frame instead of 17-18)."""
    from cores.matching.config import MatcherConfig
    from cores.segmentation.settings import SegmenterSettings

    rec = recordings.open_recording(KARLSRUHE)
    for pf in R.process_recording(rec, SegmenterSettings(), MatcherConfig(lr_check=True), frames=6):
        lst = pf.result.obstacles
        right = np.isfinite(pf.disparity[:, -300:]).mean()
        assert right > 0.25 and lst.bearing_deg is not None and lst.bearing_deg[1] > 45, (pf.seq, right)
        assert "standing-not-listed" not in lst.degraded and len(lst.obstacles) >= 12, (pf.seq, lst.degraded)


@needs_karlsruhe
def test_the_street_at_the_ends_of_the_layer_split_s_area_runs():
    """layer_min_area_m2 0 (allowed) raised IndexError in the depth split on the street's first frames:
    a component number that holds no pixel passed the area test."""
    from cores.matching.config import MatcherConfig
    from cores.segmentation.settings import SegmenterSettings

    rec = recordings.open_recording(KARLSRUHE)
    for area in (0.0, 0.06):
        for pf in R.process_recording(rec, SegmenterSettings(layer_min_area_m2=area), MatcherConfig(), frames=3):
            assert pf.result.obstacles.obstacles, (area, pf.seq)


@needs_euroc
def test_euroc_tape_and_mat_on_the_floor_are_free_the_mattresses_and_chessboard_are_obstacles():
    """The room: tape strips and a play mat lie on the floor (bottom half of the image), mattresses
    lean on the walls and a chessboard stands before the right one. Pixel places read off the
    pictures of the first frames (rectified left image, 752x480)."""
    from cores.matching.config import MatcherConfig
    from cores.segmentation.mount import Mount
    from cores.segmentation.settings import SegmenterSettings

    rec = recordings.open_recording(EUROC)
    settings = SegmenterSettings(max_range_m=30.0)
    for pf in R.process_recording(rec, settings, MatcherConfig(num_disparities=128), frames=3):
        lst = pf.result.obstacles
        assert lst.ground.source == "fitted" and 0.8 < lst.ground.height_m < 1.1
        boxes = [o.bbox_px for o in lst.obstacles]

        def covered(u, v, boxes=boxes):
            return any(x0 <= u < x1 and y0 <= v < y1 for x0, y0, x1, y1 in boxes)
        assert covered(690, 230), "the chessboard"
        assert covered(400, 180), "the mattress leaning on the back wall"
        for x0, y0, x1, y1 in boxes:
            assert y1 < 320, f"an obstacle box {x0, y0, x1, y1} reaches down onto the floor (tape, mat)"
        # the floor with the tape strips (left, middle) and the mat (right) is free space
        fs = pf.result.freespace
        cells = np.frombuffer(fs.cells, np.int8).reshape(fs.height, fs.width)
        mount = Mount.of(lst.mount)  # where the segmenter put the camera for this list
        for u, v in ((200, 420), (420, 400), (620, 400)):  # a tape strip, the middle tape, the mat
            ray = np.array([(u - pf.model.cx) / pf.model.focal_px, (v - pf.model.cy) / pf.model.focal_px, 1.0])
            n = mount.R_base_camera.T @ np.array([0.0, 0.0, -1.0])  # floor normal (down), camera frame
            p = ray * (mount.height_m / float(n @ ray))  # where the pixel's ray meets the floor
            x, y = mount.to_base(p)[:2]
            cell = cells[int((y - fs.origin_m[1]) / fs.resolution_m), int((x - fs.origin_m[0]) / fs.resolution_m)]
            assert cell == 0, f"pixel ({u}, {v}) on the floor is {cell}, not free"


@needs_karlsruhe
def test_obstacles_with_only_a_calibration_sees_the_street_and_an_unreachable_range_says_so(capsys):
    """issue 20: the defaults (layers, its range grown with the rig; the search following the
    calibration) give obstacles on the street, not silence; a range the search cannot reach is a
    warning at the start and a degraded reason on every list."""
    pairs = [str(KARLSRUHE / "left" / "I1_00000[01].png"), str(KARLSRUHE / "right" / "I2_00000[01].png")]
    cal = ["--calibration", str(KARLSRUHE / "calibration.yaml")]
    assert main(["obstacles", *pairs, *cal, "--json"]) == 0
    lists = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(lists) == 2
    for lst in lists:
        assert lst["obstacles"] and lst["degraded"] == [] and lst["ground"]["source"] == "fitted"
        assert abs(lst["ground"]["height_m"] - 1.6) < 0.15
    # the round-one defaults: 64 px (nothing nearer than 5.75 m) and a small robot's 4.5 m
    assert main(["obstacles", *pairs, *cal, "--json", "--disparity-num-disparities", "64", "--max-range-m", "4.5"]) == 0
    out = capsys.readouterr()
    assert "do not overlap" in out.err and "5.85 m" in out.err  # f*B / 63 px
    for lst in map(json.loads, out.out.splitlines()):
        assert "range-unreachable" in lst["degraded"]
    # the same 64 px with a 10 m range: measured from 5.85 m, the road nearer than that (in view from
    # 4.3 m) aliases to false depths, on which the ground was fitted 0.5 m and 5 deg off, unflagged
    assert main(["obstacles", *pairs, *cal, "--json", "--disparity-num-disparities", "64", "--max-range-m", "10"]) == 0
    out = capsys.readouterr()
    assert "nothing nearer than 5.85 m" in out.err and "near-unmeasured" in out.err
    for lst in map(json.loads, out.out.splitlines()):
        assert "near-unmeasured" in lst["degraded"] and "range-unreachable" not in lst["degraded"]
    # a min_disparity of 32 px, or the disparity stage's 10 m gate, under the street's 30 m: nothing farther than
    # 11.5 m (10 m) is measured; the lists had said nothing of it (issue 20: never silent emptiness)
    for flag, far in ((["--disparity-min-disparity", "32"], "11.51"), (["--disparity-max-range-m", "10"], "10.00")):
        assert main(["obstacles", *pairs, *cal, "--json", *flag]) == 0
        out = capsys.readouterr()
        assert f"nothing farther than {far} m is measured" in out.err and "far-unmeasured" in out.err, out.err
        for lst in map(json.loads, out.out.splitlines()):
            assert "far-unmeasured" in lst["degraded"] and "near-unmeasured" not in lst["degraded"], lst["degraded"]


# Values far past where a field stops having a bound: what a user may still type
_FAR = {"texture_threshold": 1000, "speckle_window": 100000, "speckle_range": 1000, "p1": 100000, "p2": 400000,
        "fill_lambda": 1e7, "fill_sigma_color": 1000.0, "min_range_m": 100.0, "max_range_m": 1000.0,
        "disp12_max_diff": 1000, "min_pixels": 100000}


@pytest.mark.slow
@needs_karlsruhe
@pytest.mark.parametrize("part", ["bm", "sgbm", "dense", "segmenter"])
def test_at_every_end_of_every_setting_no_street_list_is_empty_and_unsaid(part):
    """The round's rule on the street, setting by setting: each matcher setting of each method, and each
    segmenter setting, at each end of its range (and far past it where it has none), on the street's
    first 4 pairs: every list holds obstacles or says why it cannot be trusted. Before their bounds,
    min_pixels 100000 left 7 of 8 lists empty with nothing said, and min_height_m 5, min_area_m2 100,
    min_cell_height_m 5 and robot_height_m 0.001 every list."""
    from pydantic import ValidationError
    from test_settings_bounds import _ends

    from common.files import read_image
    from cores.matching.config import MatcherConfig
    from cores.pipeline import Pipeline
    from cores.segmentation.settings import SegmenterSettings

    rec = recordings.open_recording(KARLSRUHE)
    pairs = [tuple(read_image(p) for p in rec.pairs[k]) for k in range(4)]
    seg = SegmenterSettings(max_range_m=30.0)
    model = SegmenterSettings if part == "segmenter" else MatcherConfig
    runs = _ends(model) + [(n, v) for n, v in _FAR.items() if n in model.model_fields]
    reference = Pipeline(rec.calibration, MatcherConfig(), seg)
    fronts = [reference.front(left, right, t_s=rec.stamps_s[k]) for k, (left, right) in enumerate(pairs)]
    tried, unsaid = 0, []
    for name, value in runs:
        if name in ("threads",):
            continue
        try:
            if part == "segmenter":
                pipe = reference.fork(SegmenterSettings(**{"max_range_m": 30.0, name: value}))
            else:
                pipe = Pipeline(rec.calibration, MatcherConfig(method=part, **{name: value}), seg)
        except (ValidationError, BallbotError):
            continue  # refused, with a message naming it
        tried += 1
        for k, (left, right) in enumerate(pairs):
            if part == "segmenter":
                m = fronts[k]
                lst = pipe.segment(m.stage, t_s=rec.stamps_s[k], seq=k, image=m.left, checks=m.checks).obstacles
            else:
                lst = pipe.process(left, right, t_s=rec.stamps_s[k], seq=k).result.obstacles
            if not lst.obstacles and not lst.degraded:
                unsaid.append((name, value, k))
    assert tried >= 20 and not unsaid, unsaid


@pytest.mark.slow
@needs_karlsruhe
def test_the_street_keeps_its_near_things_and_their_ids_at_the_ends_of_the_size_floor_and_the_gate():
    """min_pixels is a floor for noise in pixels: far, small things are what it can lose. At its end
    (24) every confirmed obstacle within 10 m of the street's first 15 lists is still listed (at 50
    some went unsaid, at 100000 every list was empty). track_gate_m at its end (0.9 m) keeps ids on
    their things: at most 5 % of the tracks' steps over the ground jump more than 2 m (at 100 m: 26 %,
    and the lists joined into lumps with parked cars moving at 6 m/s)."""
    from test_settings_bounds import _ends

    from cores.matching.config import MatcherConfig
    from cores.segmentation.settings import SegmenterSettings

    top: dict[str, float] = {}  # the upper ends
    for name, value in _ends(SegmenterSettings):
        top[name] = max(value, top.get(name, value))
    rec = recordings.open_recording(KARLSRUHE)

    def near_confirmed(**over) -> int:
        report = R.evaluate_recording(rec, SegmenterSettings(max_range_m=30.0, **over),
                                      MatcherConfig(num_disparities="auto"), frames=15)
        return sum(o.confirmed and o.distance_m <= 10.0 for f in report.frames for o in f.obstacles)

    assert near_confirmed(min_pixels=top["min_pixels"]) >= near_confirmed() > 20
    f = R.evaluate_recording(rec, SegmenterSettings(max_range_m=30.0, track_gate_m=top["track_gate_m"]),
                             MatcherConfig(num_disparities="auto")).figures
    assert f["track_steps"] > 100 and f["track_jump_fraction"] <= 0.05, f
