"""The dense method: every pixel a disparity and a confidence. Its pieces (fill, smoother,
confidence), its accuracy on the synthetic world's exact ground truth and on real Middlebury pairs,
the automatic search range and the saturation warning, the offline command, and a real dense worker
beside an onboard bm dispatcher over Zenoh."""
from __future__ import annotations

import time
import uuid

import numpy as np
import pytest
from pydantic import ValidationError

import sim as S
from common import codec
from common.errors import BallbotError
from common.messages import DisparityMap, ServiceStats, StereoFrame
from cores import camera
from cores.calibration.rectify import Rectifier, camera_model_message
from cores.matching import dense
from cores.matching.config import auto_num_disparities
from cores.matching.disparity import to_float
from cores.matching.matchers import MatcherConfig, make_matcher
from services.disparity.computer import FrameComputer


@pytest.fixture(scope="module")
def scene():
    rig = camera.load_calibration("lifecam-studio")
    rect = camera.rectify_rig(rig, 0.0)
    world = S.SyntheticWorld(S.Scene.default(), rig, rect, seed=0)
    left, right = Rectifier(rig).rectify(*world.render(0.0))
    return left, right, world.true_disparity(0.0), rect.model


def frame(left, right, model, seq=1) -> StereoFrame:
    return StereoFrame(robot_id="t", seq=seq, stamp_ns=1, left=codec.image_from_array(left),
                       right=codec.image_from_array(right), camera=camera_model_message(model))


def bad_rate(d, gt, px):
    has = np.isfinite(gt)
    ok = np.isfinite(d) & has & (np.abs(np.nan_to_num(d) - np.nan_to_num(gt)) <= px)
    return 1 - ok.sum() / has.sum()


# --- pieces -----------------------------------------------------------------------------------------

def test_fill_stops_at_an_intensity_edge():
    """Holes on either side of an edge take the value of their own side, not an average."""
    guide = np.full((60, 80), 40, np.uint8)
    guide[:, 40:] = 200
    d = np.where(np.arange(80)[None, :] < 40, 10.0, 30.0).astype(np.float32).repeat(60, 0)
    valid = np.zeros(d.shape, bool)
    valid[:, 5:10] = valid[:, 70:75] = True  # measurements far from the edge only
    out, conf = dense.fill_and_confidence(np.where(valid, d, 0).astype(np.float32), valid, guide, 8000.0, 1.5)
    assert np.abs(out[:, :38] - 10).max() < 0.5 and np.abs(out[:, 42:] - 30).max() < 0.5
    assert (conf[valid] >= 128).all() and (conf[~valid] < 128).all() and (conf > 0).all()


def test_background_fill_takes_the_farther_neighbour_and_empty_rows_from_columns():
    d = np.array([[5, np.nan, np.nan, 9], [np.nan] * 4, [7, np.nan, 3, np.nan]], np.float32)
    out = dense.background_fill(d)
    assert out[0].tolist() == [5, 5, 5, 9]
    assert out[2].tolist() == [7, 3, 3, 3]
    assert np.isfinite(out[1]).all()  # the empty row: from above and below
    assert np.isnan(dense.background_fill(np.full((3, 3), np.nan, np.float32))).all()


def test_smoother_keeps_a_constant_and_smooths_noise_within_regions():
    rng = np.random.default_rng(0)
    guide = np.full((40, 50), 100, np.uint8)
    f = np.dstack([np.full((40, 50), 7.0), np.ones((40, 50))])
    assert np.allclose(dense.fast_global_smoother(f, guide, 500.0, 1.5), f, atol=1e-6)
    noisy = 7.0 + rng.normal(0, 1, (40, 50, 1))
    assert dense.fast_global_smoother(noisy, guide, 500.0, 1.5).std() < 0.2 * noisy.std()


def test_the_left_band_is_matched_where_the_partner_is_in_view():
    """OpenCV leaves x < max disparity invalid; dense matches there, but never against its padding:
    a pixel whose partner is out of view is filled (confidence < 128), not measured."""
    import cv2

    rng = np.random.default_rng(1)
    left = cv2.GaussianBlur(rng.integers(0, 256, (120, 200), dtype=np.uint8), (3, 3), 0)
    right = np.zeros_like(left)
    right[:, :-20] = left[:, 20:]  # disparity 20 everywhere
    right[:, -20:] = left[:, -20:]
    m = make_matcher(MatcherConfig(method="dense", num_disparities=64)).match(left, right)
    d = m.disparity / 16.0
    assert (m.confidence[:, :20] < 128).all()  # partner at x - 20 < 0: no measurement there
    assert (m.confidence[5:-5, 24:64] >= 128).mean() > 0.95  # in OpenCV's empty band, yet measured
    assert np.abs(d[5:-5, 24:180] - 20).max() <= 0.5
    assert np.abs(d[5:-5, :20] - 20).max() <= 0.5  # filled from the measured neighbours


def test_nothing_matched_means_no_disparity_and_zero_confidence():
    blank = np.full((120, 160), 128, np.uint8)
    m = make_matcher(MatcherConfig(method="dense", num_disparities=32)).match(blank, blank)
    assert (m.confidence == 0).all() and (m.disparity == -16).all()


# --- accuracy ------------------------------------------------------------------------------------------

def test_dense_gives_every_pixel_a_value_and_beats_sgbm_on_the_synthetic_world(scene):
    left, right, gt, _ = scene
    cfg = MatcherConfig(method="dense", num_disparities=64)
    m = make_matcher(cfg).match(left, right)
    d = to_float(m.disparity, 16, cfg.invalid_value)
    assert np.isfinite(d).all() and m.confidence.dtype == np.uint8 and m.confidence.shape == d.shape
    sgbm = to_float(make_matcher(MatcherConfig(method="sgbm", num_disparities=64)).compute(left, right), 16, -16)
    for px in (1.0, 2.0):
        assert bad_rate(d, gt, px) < 0.7 * bad_rate(sgbm, gt, px), px
    # confidence means something: the confident half is more often right than the rest
    has = np.isfinite(gt)
    err = np.abs(d - np.nan_to_num(gt))
    high = has & (m.confidence >= 200)
    low = has & (m.confidence < 128)
    assert high.mean() > 0.5
    assert (err[high] > 1).mean() < 0.5 * (err[low] > 1).mean()


def test_dense_beats_every_opencv_setting_by_a_quarter_on_each_real_pair():
    """The issue's target, on every real pair with ground truth this machine has (bench accuracy)."""
    from bench import accuracy

    pairs = accuracy.available_pairs()
    if not pairs:
        pytest.skip("no real pair with ground truth: pip install scikit-image, apt-get install opencv-doc")
    for pair in pairs:
        rows = accuracy.evaluate_pair(pair, methods=["dense", *accuracy.OPENCV_METHODS], repeats=1)
        best = min(rows[n]["bad2"] for n in accuracy.OPENCV_METHODS)
        assert rows["dense"]["bad2"] <= 0.75 * best, (pair.name, rows)
        assert rows["dense"]["invalid"] == 0.0


# --- search range ----------------------------------------------------------------------------------

def test_auto_range_from_the_calibration(scene):
    """auto: the multiple of 16 nearest to the disparity of min_range_m (it reaches about that far),
    capped at 512 and at a quarter of the image width (bm measures nothing in the left band)."""
    left, right, _, model = scene
    assert auto_num_disparities(600.0, 0.1, 0.5) == 128  # d = 120 px at 0.5 m: 0..120 is 121 values
    assert auto_num_disparities(600.0, 0.1, 1.0) == 64  # 60 px
    assert auto_num_disparities(640.0, 0.1, 1.0) == 64  # 64 px: reaches 1.02 m (80 px would widen the band)
    assert auto_num_disparities(720.0, 0.1, 1.0) == 80  # 72 px: 73 values are nearer 80 than 64
    assert auto_num_disparities(600.0, 0.1, 1.0, min_disparity=8) == 48  # 8..60 (53 values)
    assert auto_num_disparities(600.0, 0.1, 0.01) == 512
    assert auto_num_disparities(600.0, 0.1, 0.01, width=320) == 80  # a quarter of the width: bm's blind band
    assert auto_num_disparities(645.24, 0.5707, 0.5, width=1344) == 336  # Karlsruhe: 1.1 m, not 0.5 m
    with pytest.raises(BallbotError, match="focal length and baseline"):
        _ = MatcherConfig(num_disparities="auto").fixed_num_disparities
    with pytest.raises(ValidationError):
        MatcherConfig(num_disparities="far")
    cfg = MatcherConfig(method="bm", num_disparities="auto", min_range_m=0.5)
    near = model.focal_px * model.baseline_m / 0.5  # 132 px for the thesis rig at 0.5 m
    assert cfg.resolved(model.focal_px, model.baseline_m).num_disparities == 128 == round(near / 16) * 16
    out = FrameComputer(cfg).compute(frame(left, right, model), "w")
    assert out.num_disparities == 128 and out.method == "bm"
    # the default: about 1 m on the thesis rig, as its 64 px reached
    assert MatcherConfig().resolved(model.focal_px, model.baseline_m, model.width).num_disparities == 64


def test_a_too_small_range_is_reported(scene):
    left, right, _, model = scene
    small = make_matcher(MatcherConfig(method="sgbm", num_disparities=16)).match(left, right)
    enough = make_matcher(MatcherConfig(method="sgbm", num_disparities=96)).match(left, right)
    assert small.saturated > 0.01 and "top of the disparity search range" in small.range_warning
    assert enough.saturated < 0.005 and enough.range_warning == ""


# --- the worker's message ---------------------------------------------------------------------------

@pytest.mark.parametrize("encoding", ["raw", "png"])
def test_dense_maps_carry_their_confidence(scene, encoding):
    left, right, _, model = scene
    cfg = MatcherConfig(method="dense", num_disparities=64)
    msg = FrameComputer(cfg, result_encoding=encoding).compute(frame(left, right, model), "w")
    assert msg.method == "dense" and msg.confidence is not None
    assert msg.confidence.encoding == encoding
    conf = codec.array_from_image(msg.confidence, "confidence")
    direct = make_matcher(cfg).match(left, right)
    assert np.array_equal(conf, direct.confidence)  # lossless either way
    bm = FrameComputer(MatcherConfig(method="bm")).compute(frame(left, right, model), "w")
    assert bm.confidence is None  # bm measures none; no bytes wasted on the wire


def test_bad_inputs_are_refused(scene):
    left, right, _, _ = scene
    m = make_matcher(MatcherConfig(method="dense", num_disparities=64))
    with pytest.raises(BallbotError, match="differ in size"):
        m.match(left, right[:-2])
    with pytest.raises(BallbotError, match="8-bit"):
        m.match(left.astype(np.float32), right.astype(np.float32))
    with pytest.raises(ValidationError, match="odd"):
        MatcherConfig(method="dense", block_size=4)


# --- the offline command ----------------------------------------------------------------------------

def test_offline_dense_with_confidence_auto_range_and_warnings(tmp_path, capsys):
    import cv2

    from ballbot_vision.cli import main

    rig = camera.load_calibration("lifecam-studio")
    world = S.SyntheticWorld(S.Scene.default(), rig, camera.rectify_rig(rig, 0.0), seed=0)
    raw_l, raw_r = world.render(0.0)
    cv2.imwrite(str(tmp_path / "l.png"), raw_l)
    cv2.imwrite(str(tmp_path / "r.png"), raw_r)
    pair = [str(tmp_path / "l.png"), str(tmp_path / "r.png")]
    cal = ["--calibration", "lifecam-studio"]
    assert main(["disparity", *pair, *cal, "-o", str(tmp_path / "d.npy"), "--method", "dense",
                 "--num-disparities", "auto", "--confidence", str(tmp_path / "c.png")]) == 0
    out = capsys.readouterr()
    assert "searched 0..63 px" in out.out and "warning" not in out.err  # about 1 m (min_range_m), as the thesis
    d, c = np.load(tmp_path / "d.npy"), cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED)
    assert np.isfinite(d).all() and c.dtype == np.uint8 and c.shape == d.shape and c.max() > 200
    # a range too small for the scene: said on stderr
    assert main(["disparity", *pair, *cal, "-o", str(tmp_path / "s.npy"), "--method", "sgbm",
                 "--num-disparities", "16"]) == 0
    assert "top of the disparity search range" in capsys.readouterr().err
    # bad requests name what is wrong
    assert main(["disparity", *pair, "-o", str(tmp_path / "x.npy"), "--num-disparities", "auto"]) == 2
    assert "needs --calibration" in capsys.readouterr().err
    assert main(["disparity", *pair, *cal, "-o", str(tmp_path / "x.npy"), "--confidence", str(tmp_path / "c.png")]) == 2
    assert "gives no confidence" in capsys.readouterr().err
    assert main(["disparity", *pair, *cal, "-o", str(tmp_path / "x.npy"), "--method", "dense",
                 "--confidence", str(tmp_path / "c.jpg")]) == 2
    assert ".png" in capsys.readouterr().err


# --- a dense worker beside an onboard bm dispatcher ------------------------------------------------------

@pytest.mark.system
def test_robot_runs_bm_onboard_and_an_offboard_worker_runs_dense(tmp_path):
    from helpers import Collector
    from test_disparity_pool import Procs, free_port, start_robot

    from common.keys import topic
    from common.zenoh_session import ZenohOptions, open_session

    rid = f"dense{uuid.uuid4().hex[:6]}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    Procs.logdir = str(tmp_path)
    procs = Procs()
    maps, stats = Collector(DisparityMap), Collector(ServiceStats)
    try:
        start_robot(procs, rid, endpoint, endpoint, rate=5.0, fallback="full")  # the robot: bm onboard
        with open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=[])) as s:
            subs = [s.declare_subscriber(topic("disparity").key(rid), maps),  # noqa: F841 (kept alive)
                    s.declare_subscriber(topic("stats").pattern(rid), stats)]
            assert maps.wait_for(lambda ms: any(m.method == "bm/onboard" for m in ms), 90), \
                f"no onboard bm map; logs in {tmp_path}"
            procs.service("worker", "disparity", "--role", "worker", "--method", "dense", "--num-disparities",
                          "auto", "--min-range-m", "1.0", "--connect", endpoint, "--robot-id", rid)
            t_join = time.time_ns()
            assert maps.wait_for(lambda ms: any(m.method == "dense" for m in ms), 120), \
                f"no dense map from the worker; logs in {tmp_path}"
            d = next(m for m in maps.items if m.method == "dense")
            assert d.confidence is not None and d.num_disparities == 64 and d.stamp_ns > 0
            conf = codec.array_from_image(d.confidence, "confidence")
            assert conf.shape == (d.image.height, d.image.width) and conf.max() > 200
            assert not any(m.confidence is not None for m in maps.items if m.method == "bm/onboard")
            assert stats.wait_for(lambda st: any(x.extra.get("maps_dense", 0) >= 1 and "dense" in x.status
                                                 for x in st if x.service == "disparity"), 30), \
                [(x.instance, x.status, x.extra) for x in stats.items[-4:]]
            # the synthetic cameras share one exposure: the stage matched the pairs untouched
            assert stats.wait_for(lambda st: any("range_saturated_pct" in x.extra and x.status.startswith("ok: dense")
                                                 and x.extra.get("exposure_gain") == 1.0
                                                 for x in st if x.stamp_ns > t_join), 30)
    finally:
        procs.stop_all()
        Procs.logdir = None
