"""Rectify: refusing malformed calibrations, swapping a calibration at run time, offline command."""
from __future__ import annotations

import os
import threading

import cv2
import numpy as np
import pytest
import yaml

from ballbot_vision.cli import main
from common.errors import BallbotError, CalibrationError
from cores import camera
from cores.calibration.rectify import CalibrationHolder, Rectifier


def _doc() -> dict:
    return camera.calibration_to_dict(camera.load_calibration("lifecam-studio"))


def _write(path, doc) -> str:
    path.write_text(yaml.safe_dump(doc))
    return str(path)


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d["left"].pop("K"), "'K'"),
    (lambda d: d.pop("T"), "'T'"),
    (lambda d: d.pop("image_size"), "'image_size'"),
    (lambda d: d.__setitem__("R", [1, 0, 0, 0, 2, 0, 0, 0, 1]), "R: not a rotation"),
    (lambda d: d["right"].__setitem__("distortion", [0.1, 0.2]), "'distortion'"),
    (lambda d: d["left"].__setitem__("image_size", [320, 240]), "'image_size'"),
    # T in mm read as metres: everything 1000 times farther, past every vision range, lists empty
    (lambda d: d.__setitem__("T", [t * 1000 for t in d["T"]]), "a baseline of 99.4.* m .*in millimetres"),
])
def test_malformed_calibration_is_refused(tmp_path, mutate, field):
    d = _doc()
    mutate(d)
    with pytest.raises(CalibrationError, match=field):
        camera.load_calibration(_write(tmp_path / "bad.yaml", d))


def test_wrong_image_size_names_both_sizes():
    r = Rectifier(camera.load_calibration("lifecam-studio"))
    with pytest.raises(BallbotError, match="320x240.*640x480"):
        r.rectify(np.zeros((240, 320), np.uint8), np.zeros((240, 320), np.uint8))


def test_skew_is_honoured_by_the_maps():
    rig = camera.load_calibration("lifecam-studio")
    skewed = camera.RawRig(rig.image_size, camera.Intrinsics(rig.left.fx, rig.left.fy, rig.left.cx, rig.left.cy, 3.0,
                                                             rig.left.dist), rig.right, rig.R, rig.T)
    for maps in ("float", "fixed"):
        a, b = Rectifier(rig, maps=maps), Rectifier(skewed, maps=maps)
        (la, la2), (lb, lb2) = a._maps[0], b._maps[0]
        if maps == "fixed":
            la, lb = cv2.convertMaps(la, la2, cv2.CV_32FC1)[0], cv2.convertMaps(lb, lb2, cv2.CV_32FC1)[0]
        # the source column of the skewed camera moves by s (v - cy) / fy: zero near cy, ~2 px at the top
        d = lb.astype(float) - la.astype(float)
        assert abs(np.median(d[240])) <= 1 and np.median(d[0]) <= -1, maps


def _rigs_with_a_raw_pair():
    from bench.rectify import EUROC, rigs

    found = rigs()
    assert found[0][0].startswith("synthetic")
    if not (EUROC / "cam0_sensor.yaml").exists():
        pytest.skip(f"real EuRoC recording not present ({EUROC}): checked on the synthetic rig only")
    return found


def test_float_maps_resample_exactly_and_fixed_ones_round():
    """The float remap tables (the default) give the exact bilinear resampling of their source
    positions, to the rounding of an 8-bit image, on the synthetic rig and on EuRoC's strongly
    distorted raw pair; fixed-point tables are 1/32 px off and differ by up to a few grey levels."""
    from bench.rectify import accuracy

    for name, cal, left, right in _rigs_with_a_raw_pair():
        acc = accuracy(cal, left, right)
        assert acc["float"]["max_grey_error"] <= 0.51, (name, acc)  # float32 weights: rounding and a hair
        assert acc["float"]["max_position_error_px"] == 0.0, (name, acc)
        assert 0 < acc["fixed"]["max_position_error_px"] <= 1 / 32, (name, acc)
        assert acc["fixed"]["share_above_1_grey"] < 0.01, (name, acc)


def test_default_rectifier_uses_the_float_maps():
    cal = camera.load_calibration("lifecam-studio")
    default, fixed = Rectifier(cal), Rectifier(cal, maps="fixed")
    assert default._maps[0][0].dtype == np.float32 and fixed._maps[0][0].dtype == np.int16
    left, right = _pair()
    a, b = default.rectify(left, right), fixed.rectify(left, right)
    for x, y in zip(a, b):  # the same geometry: the two agree but for the fixed point's rounding
        assert x.dtype == y.dtype == np.uint8
        assert np.percentile(np.abs(x.astype(int) - y.astype(int)), 99.9) <= 1
    with pytest.raises(BallbotError, match="maps: one of float, fixed"):
        Rectifier(cal, maps="half")


def _pair(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 255, (480, 640), dtype=np.uint8), (5, 5), 0)
    return img, np.roll(img, -20, axis=1)


def test_hot_reload_by_message_and_by_file(tmp_path):
    path = tmp_path / "cal.yaml"
    d = _doc()
    _write(path, d)
    h = CalibrationHolder(str(path), max_change=0)  # any baseline: this test is about the mechanics
    first = h.current()
    h.note_frame(640, 480)

    d2 = _doc()
    d2["T"] = [-0.12, 0.0, 0.0]
    assert h.offer_yaml(yaml.safe_dump(d2), "test") is True
    assert h.current() is not first and h.current().model.baseline_m == pytest.approx(0.12)
    second = h.current()

    # refused, old one stays: bad YAML, a missing field, a non-rotation, another image size
    assert h.offer_yaml("{not: [yaml", "test") is False
    bad = _doc()
    bad.pop("R")
    assert h.offer_yaml(yaml.safe_dump(bad), "test") is False and "'R'" in h.last_error
    bad = _doc()
    bad["R"] = [1, 0, 0, 0, 1, 0, 0, 0, -1]
    assert h.offer_yaml(yaml.safe_dump(bad), "test") is False and "rotation" in h.last_error
    bad = _doc()
    bad["image_size"] = [1280, 720]
    assert h.offer_yaml(yaml.safe_dump(bad), "test") is False and "image_size" in h.last_error
    assert h.current() is second and h.refused == 4

    # the file changes on disk: picked up by the poll, unchanged file is not reloaded
    assert h.poll_file() is None
    d3 = _doc()
    d3["T"] = [-0.08, 0.0, 0.0]
    _write(path, d3)
    st = os.stat(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 2_000_000_000))
    assert h.poll_file() is True and h.current().model.baseline_m == pytest.approx(0.08)
    assert h.poll_file() is None
    path.write_text("left: {}\n")  # a broken save: refused, 0.08 stays
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 4_000_000_000))
    assert h.poll_file() is False and h.current().model.baseline_m == pytest.approx(0.08)


def test_a_run_time_calibration_that_rescales_every_distance_is_refused():
    """Half the baseline halves every distance: a jump like that is refused at run time (by
    message or file), a small recalibration of the same rig is taken."""
    h = CalibrationHolder("lifecam-studio")  # default max_change 5 %
    h.note_frame(640, 480)
    before = h.current()
    half = _doc()
    half["T"] = [t / 2 for t in half["T"]]
    assert h.offer_yaml(yaml.safe_dump(half), "the calibration key") is False
    assert "baseline" in h.last_error and "50.0%" in h.last_error and "restart" in h.last_error
    focal = _doc()
    for cam in ("left", "right"):
        focal[cam]["K"] = [v * 1.2 if i in (0, 4) else v for i, v in enumerate(focal[cam]["K"])]
    assert h.offer_yaml(yaml.safe_dump(focal), "the calibration key") is False and "focal length" in h.last_error
    assert h.current() is before
    tweak = _doc()
    tweak["T"] = [t * 1.01 for t in tweak["T"]]
    assert h.offer_yaml(yaml.safe_dump(tweak), "the calibration key") is True
    assert h.current().model.baseline_m == pytest.approx(before.model.baseline_m * 1.01, rel=1e-3)


def test_drift_is_bounded_against_the_calibration_rectify_started_with_not_step_by_step():
    """18 updates of -4 % each pass a 5 % step check one by one and end at 48 % of the baseline;
    against the calibration rectify started with, the second one already goes too far."""
    h = CalibrationHolder("lifecam-studio")
    h.note_frame(640, 480)
    start = h.current().model.baseline_m
    doc, taken = _doc(), []
    for _ in range(18):
        doc["T"] = [t * 0.96 for t in doc["T"]]
        taken.append(h.offer_yaml(yaml.safe_dump(doc), "the calibration key"))
    assert taken == [True] + [False] * 17, taken
    assert "the calibration rectify started with" in h.last_error
    assert h.current().model.baseline_m == pytest.approx(start * 0.96, rel=1e-3)
    assert h.refused == 17


def test_an_assumed_rig_becomes_the_reference_once_it_rectified_a_frame():
    """Without a configured calibration nothing is drifted from until a frame was rectified with the
    assumed rig; from then on (a forged "camera" frame or not) a half-baseline one is a jump."""
    half = _doc()
    half["T"] = [t / 2 for t in half["T"]]
    fresh = CalibrationHolder("lifecam-studio", started=False)
    assert fresh.reference is None and fresh.offer_yaml(yaml.safe_dump(half), "the first one")  # a real rig's first
    used = CalibrationHolder("lifecam-studio", started=False)
    used.note_frame(640, 480)
    used.mark_used()
    assert used.offer_yaml(yaml.safe_dump(half), "after a frame") is False and "50.0%" in used.last_error
    wrong = CalibrationHolder("lifecam-studio", started=False)
    wrong.note_frame(320, 240)  # the first calibration must fit the frames
    assert wrong.offer_yaml(yaml.safe_dump(_doc()), "another size") is False and "320x240" in wrong.last_error


def test_swap_never_tears_a_frame():
    """The frame loop takes one Rectifier per pair; swaps from another thread land between pairs."""
    d_a, d_b = _doc(), _doc()
    d_b["T"] = [-0.12, 0.001, 0.0]
    text = {0: yaml.safe_dump(d_a), 1: yaml.safe_dump(d_b)}
    h = CalibrationHolder("lifecam-studio", max_change=0)
    left, right = _pair()
    expect = {}
    for k in (0, 1):
        r = Rectifier(camera.calibration_from_dict(yaml.safe_load(text[k])))
        expect[round(r.model.baseline_m, 4)] = r.rectify(left, right)
    stop = threading.Event()

    def flipper() -> None:
        k = 1
        while not stop.is_set():
            h.offer_yaml(text[k], "flipper")
            k = 1 - k

    t = threading.Thread(target=flipper)
    t.start()
    seen = set()
    try:
        for _ in range(40):
            r = h.current()
            rl, rr = r.rectify(left, right)
            el, er = expect[round(r.model.baseline_m, 4)]
            assert np.array_equal(rl, el) and np.array_equal(rr, er)
            seen.add(round(r.model.baseline_m, 4))
    finally:
        stop.set()
        t.join(10)
    assert h.generation > 0


def test_offline_rectify_command(tmp_path, capsys):
    left, right = _pair()
    (tmp_path / "in").mkdir()
    for i in range(2):
        cv2.imwrite(str(tmp_path / "in" / f"left{i}.png"), left)
        cv2.imwrite(str(tmp_path / "in" / f"right{i}.png"), right)
    out = tmp_path / "out"
    rc = main(["rectify", str(tmp_path / "in" / "left*.png"), str(tmp_path / "in" / "right*.png"),
               "--calibration", "lifecam-studio", "-o", str(out)])
    assert rc == 0
    files = sorted(p.name for p in out.iterdir())
    assert files == ["left0.png", "left1.png", "right0.png", "right1.png"]
    expect = Rectifier(camera.load_calibration("lifecam-studio")).rectify(left, right)
    assert np.array_equal(cv2.imread(str(out / "left1.png"), cv2.IMREAD_UNCHANGED), expect[0])
    rc = main(["rectify", str(tmp_path / "in" / "left0.png"), str(tmp_path / "in" / "right0.png"),
               "--calibration", str(tmp_path / "missing.yaml"), "-o", str(out)])
    assert rc == 2 and "missing.yaml" in capsys.readouterr().err
