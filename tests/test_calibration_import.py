"""`calibration import` of Kalibr camchain and EuRoC sensor.yaml files (the format most robotics rigs
ship), checked on synthetic rigs with known poses and on the real EuRoC V1_01 pair (rows line up
after rectification); and every bad calibration file is refused in one line, nothing written."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ballbot_vision.cli import main
from common.errors import CalibrationError, FileError
from cores import camera
from cores.calibration import formats as F

EUROC = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "euroc-v1-01"
if not EUROC.is_dir():
    EUROC = Path("/work/shared/data/real/euroc-v1-01")


def _pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rot(rx: float, ry: float, rz: float) -> np.ndarray:
    return cv2.Rodrigues(np.array([rx, ry, rz], float))[0]


RIG = camera.load_calibration("lifecam-studio")
T_RL = _pose(RIG.R, RIG.T)  # X_right = T_RL X_left


def _cam(c: camera.Intrinsics, extra: dict) -> dict:
    return {"camera_model": "pinhole", "intrinsics": [c.fx, c.fy, c.cx, c.cy], "distortion_model": "radtan",
            "distortion_coeffs": list(c.dist[:4]), "resolution": [640, 480], "rostopic": "/cam/image_raw", **extra}


def _same(a: camera.RawRig, b: camera.RawRig) -> None:
    assert a.image_size == b.image_size
    for x, y in ((a.left, b.left), (a.right, b.right)):
        np.testing.assert_allclose(x.K, y.K, atol=1e-9)
        np.testing.assert_allclose(x.D[:4], y.D[:4], atol=1e-12)
    np.testing.assert_allclose(a.R, b.R, atol=1e-9)
    np.testing.assert_allclose(a.T, b.T, atol=1e-12)


def _lists(T: np.ndarray) -> list:
    return [[float(x) for x in row] for row in T]


def test_kalibr_camchain_gives_the_rig(tmp_path, capsys):
    """Kalibr: T_cn_cnm1 maps cam0's points into cam1's: OpenCV's R, T as they are."""
    doc = {"cam0": _cam(RIG.left, {"T_cam_imu": _lists(np.eye(4))}),
           "cam1": _cam(RIG.right, {"T_cn_cnm1": _lists(T_RL)})}
    f = tmp_path / "camchain-imucam.yaml"
    f.write_text(yaml.safe_dump(doc, sort_keys=False))
    out = tmp_path / "rig.yaml"
    assert main(["calibration", "import", str(f), "-o", str(out)]) == 0
    _same(camera.load_calibration(out), RIG)
    assert f"wrote {out}" in capsys.readouterr().out


def test_kalibr_chain_of_three_and_imu_only_poses(tmp_path):
    """A third camera is reached through the chain; --cameras picks any two; a chain with only
    T_cam_imu per camera gives the same rig."""
    T_10 = T_RL
    T_21 = _pose(_rot(0.01, -0.02, 0.005), [-0.05, 0.001, 0.002])
    T_20 = T_21 @ T_10
    chain = {"cam0": _cam(RIG.left, {}), "cam1": _cam(RIG.right, {"T_cn_cnm1": _lists(T_10)}),
             "cam2": _cam(RIG.right, {"T_cn_cnm1": _lists(T_21)})}
    f = tmp_path / "camchain.yaml"
    f.write_text(yaml.safe_dump(chain))
    rig = F.import_files([str(f)], cameras=("cam0", "cam2"))
    np.testing.assert_allclose(rig.R, T_20[:3, :3], atol=1e-12)
    np.testing.assert_allclose(rig.T, T_20[:3, 3], atol=1e-12)
    rig12 = F.import_files([str(f)], cameras=("cam1", "cam2"))
    np.testing.assert_allclose(rig12.T, T_21[:3, 3], atol=1e-12)
    with pytest.raises(CalibrationError, match="no camera 'cam5' .*cam0, cam1, cam2"):
        F.import_files([str(f)], cameras=("cam0", "cam5"))

    T_c0_imu = _pose(_rot(0.3, -1.2, 0.1), [0.07, -0.02, 0.01])
    imu = {"cam0": _cam(RIG.left, {"T_cam_imu": _lists(T_c0_imu)}),
           "cam1": _cam(RIG.right, {"T_cam_imu": _lists(T_RL @ T_c0_imu)})}
    g = tmp_path / "imu.yaml"
    g.write_text(yaml.safe_dump(imu))
    _same(F.import_files([str(g)]), RIG)


def test_euroc_sensor_pair_gives_the_rig(tmp_path):
    """EuRoC: T_BS is each camera's pose in the body frame; T_cam1_cam0 = inv(T_BS_cam1) T_BS_cam0.
    Files start with OpenCV's `%YAML:1.0` line, as EuRoC's do."""
    T_B0 = _pose(_rot(-0.02, 0.03, 1.56), [-0.02, -0.06, 0.01])
    T_B1 = T_B0 @ np.linalg.inv(T_RL)  # so that inv(T_B1) T_B0 = T_RL
    for name, c, T in (("cam0", RIG.left, T_B0), ("cam1", RIG.right, T_B1)):
        doc = {"sensor_type": "camera", "comment": name,
               "T_BS": {"cols": 4, "rows": 4, "data": [float(x) for x in T.ravel()]},
               "rate_hz": 20, "resolution": [640, 480], "camera_model": "pinhole",
               "intrinsics": [c.fx, c.fy, c.cx, c.cy], "distortion_model": "radial-tangential",
               "distortion_coefficients": list(c.dist[:4])}
        (tmp_path / name).mkdir()
        (tmp_path / name / "sensor.yaml").write_text("%YAML:1.0\n" + yaml.safe_dump(doc, sort_keys=False))
    out = tmp_path / "rig.yaml"
    assert main(["calibration", "import", str(tmp_path / "cam0/sensor.yaml"), str(tmp_path / "cam1/sensor.yaml"),
                 "-o", str(out)]) == 0
    _same(camera.load_calibration(out), RIG)


@pytest.mark.skipif(not EUROC.is_dir(), reason=f"real EuRoC recording not present ({EUROC})")
def test_real_euroc_pair_rectifies_with_rows_aligned(tmp_path, capsys):
    out = tmp_path / "euroc.yaml"
    assert main(["calibration", "import", str(EUROC / "cam0_sensor.yaml"), str(EUROC / "cam1_sensor.yaml"),
                 "-o", str(out)]) == 0
    rig = camera.load_calibration(out)
    assert rig.image_size == (752, 480)
    # the published EuRoC stereo extrinsics: 11.0 cm baseline, right camera along -x of T
    np.testing.assert_allclose(rig.T, [-0.110074, 0.000399, -0.000854], atol=2e-6)
    capsys.readouterr()
    assert main(["calibration", "check", str(EUROC / "cam0"), str(EUROC / "cam1"), "--calibration", str(out)]) == 0
    text = capsys.readouterr().out
    overall = float(text.split("median of the median |dy| ")[1].split(" px")[0])
    assert overall < 0.3, text
    # without rectification the same pairs are ~13 px apart: the check can tell
    raw = tmp_path / "raw.yaml"
    raw.write_text("rectified: true\nimage_size: [752, 480]\nfocal_px: 458\nprincipal_point: [367, 248]\n"
                   "baseline_m: 0.11\n")
    first = sorted((EUROC / "cam0").iterdir())[0].name
    assert main(["calibration", "check", str(EUROC / "cam0" / first), str(EUROC / "cam1" / first),
                 "--calibration", str(raw)]) == 0
    assert float(capsys.readouterr().out.split("|dy| median ")[1].split(" px")[0]) > 5


def _camchain(tmp_path, **changes) -> Path:
    cam0 = _cam(RIG.left, {})
    cam1 = _cam(RIG.right, {"T_cn_cnm1": _lists(T_RL)})
    for k, v in changes.items():
        which, field = k.split("__")
        (cam0 if which == "cam0" else cam1)[field] = v
    f = tmp_path / "camchain.yaml"
    f.write_text(yaml.safe_dump({"cam0": cam0, "cam1": cam1}))
    return f


@pytest.mark.parametrize("changes,message", [
    ({"cam0__intrinsics": [-458.0, 457.0, 367.0, 248.0]}, "positive focal lengths"),
    ({"cam1__intrinsics": [".nan", 457.0, 367.0, 248.0]}, "finite numbers|must hold numbers"),
    ({"cam0__distortion_model": "equidistant"}, "distortion_model 'equidistant' is not supported"),
    ({"cam1__camera_model": "omni"}, "camera_model 'omni' is not supported"),
    ({"cam1__resolution": [1280, 720]}, "resolutions differ"),
    ({"cam0__resolution": [200000, 200000], "cam1__resolution": [200000, 200000]}, "larger than this program"),
    ({"cam1__T_cn_cnm1": [[1, 0, 0, 0.1], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "not a rotation"),
    ({"cam1__T_cn_cnm1": [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0]]}, "must hold 16 finite numbers"),
    ({"cam0__distortion_coeffs": [0.1, 0.2]}, "must hold 4 numbers"),
])
def test_bad_kalibr_files_are_refused_and_nothing_is_written(tmp_path, capsys, changes, message):
    f = _camchain(tmp_path, **changes)
    out = tmp_path / "rig.yaml"
    assert main(["calibration", "import", str(f), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ballbot-vision: error: ") and len(err.strip().splitlines()) == 1, err
    assert str(f) in err
    import re
    assert re.search(message, err), err
    assert not out.exists()


@pytest.mark.parametrize("content,message", [
    (b"", "the file is empty"),
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00", "binary data, not a text file"),
    (bytes(range(256)) * 4, "binary data, not a text file"),
    (b"just some words\n", "not a calibration format this command knows"),
    (b"a: [unclosed\n", "not a calibration format this command knows"),
])
def test_empty_binary_or_text_files_to_import_are_one_line_errors(tmp_path, capsys, content, message):
    f = tmp_path / "intrinsics.yml"
    f.write_bytes(content)
    out = tmp_path / "rig.yaml"
    assert main(["calibration", "import", str(f), "--image-size", "640x480", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err and str(f) in err, err
    assert "Traceback" not in err and "SystemError" not in err
    assert not out.exists()


def test_import_writes_only_what_the_loader_accepts(tmp_path, capsys):
    """stereo_calib files with a NaN or negative focal length: refused like the loader refuses them."""
    for bad in (float("nan"), -640.0):
        K = RIG.left.K.copy()
        K[0, 0] = bad
        fs = cv2.FileStorage(str(tmp_path / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
        fs.write("M1", K), fs.write("D1", RIG.left.D.reshape(1, 5))
        fs.write("M2", RIG.right.K), fs.write("D2", RIG.right.D.reshape(1, 5))
        fs.release()
        fs = cv2.FileStorage(str(tmp_path / "extrinsics.yml"), cv2.FILE_STORAGE_WRITE)
        fs.write("R", RIG.R), fs.write("T", RIG.T.reshape(3, 1))
        fs.release()
        out = tmp_path / "rig.yaml"
        assert main(["calibration", "import", str(tmp_path / "intrinsics.yml"), str(tmp_path / "extrinsics.yml"),
                     "--image-size", "640x480", "-o", str(out)]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "field 'K'" in err, err
        assert not out.exists()
    with pytest.raises(CalibrationError, match="refusing to write"):
        bad = camera.RawRig((640, 480), camera.Intrinsics(-1.0, 1.0, 0, 0), RIG.right, RIG.R, RIG.T)
        camera.save_calibration(bad, tmp_path / "x.yaml")
    assert not (tmp_path / "x.yaml").exists()


@pytest.mark.parametrize("content,message", [
    (b"", "the file is empty"),
    (bytes(range(256)), "binary data, not a text file"),
    (b"rectified: true\nimage_size: [200000, 200000]\nfocal_px: 700\nprincipal_point: [1, 1]\nbaseline_m: 0.1\n",
     "larger than this program handles"),
    (b"rectified: true\nimage_size: [1, 1]\nfocal_px: 700\nprincipal_point: [1, 1]\nbaseline_m: 0.1\n",
     "too small"),
    (b"rectified: true\nimage_size: [640, 480]\nfocal_px: 700\nprincipal_point: [320, 240]\nbaseline_m: 120\n",
     "a baseline of 120 m (over 5 m): calibrations are in metres"),
    (b"%YAML:1.0\nM1: !!opencv-matrix\n   rows: 1\n   cols: 1\n   dt: d\n   data: [ 1. ]\n",
     "calibration import"),
    (b"cam0: {camera_model: pinhole, intrinsics: [1, 1, 1, 1]}\n", "a Kalibr camchain file"),
])
def test_calibration_loader_errors_are_one_line(tmp_path, capsys, content, message):
    f = tmp_path / "cal.yaml"
    f.write_bytes(content)
    assert main(["calibration", "show", str(f)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err and str(f) in err, err
    with pytest.raises((CalibrationError, FileError)):
        camera.load_calibration(f)
