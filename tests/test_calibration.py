"""Calibration: chessboard views rendered through a known rig, OpenCV's sample chessboard pairs,
import/export round trips, and the built-in thesis profile."""
from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ballbot_vision.cli import main
from common.errors import CalibrationError
from cores import camera
from cores.calibration import calibrate as C
from cores.calibration import formats as F
from cores.calibration.report import format_report

PATTERN, SQUARE = (9, 6), 0.03
SIZE = (640, 480)
TRUE_LEFT = camera.Intrinsics(600.0, 602.0, 322.0, 238.0, 0.0, (-0.12, 0.08, 0.001, -0.0008, 0.0))
TRUE_RIGHT = camera.Intrinsics(605.0, 604.0, 316.0, 244.0, 0.0, (-0.10, 0.06, -0.0005, 0.0009, 0.0))
TRUE_R = cv2.Rodrigues(np.array([0.005, -0.01, 0.003]))[0]
TRUE_T = np.array([-0.1, 0.001, 0.002])


# --- rendering chessboard views through a known rig ----------------------------------------------

def _rays(cam: camera.Intrinsics, ss: int = 3, step: int = 4) -> np.ndarray:
    """Normalized undistorted coordinates (H*ss, W*ss, 2) of ss x ss samples inside each pixel:
    exact inverse distortion on a 4 px grid, bilinear in between (the distortion is smooth)."""
    w, h = SIZE
    gx = np.arange(-step, w + 2 * step, step, dtype=np.float64)
    gy = np.arange(-step, h + 2 * step, step, dtype=np.float64)
    X, Y = np.meshgrid(gx, gy)
    pts = np.stack([X.ravel(), Y.ravel()], -1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    und = cv2.undistortPoints(pts, cam.K, cam.D, None, None, None, crit).reshape(len(gy), len(gx), 2)
    o = (np.arange(ss) - (ss - 1) / 2) / ss
    fx = ((np.arange(w)[:, None] + o).ravel() + step) / step
    fy = ((np.arange(h)[:, None] + o).ravel() + step) / step
    ix, iy = np.floor(fx).astype(int), np.floor(fy).astype(int)
    ax, ay = (fx - ix)[None, :, None], (fy - iy)[:, None, None]
    a, b = und[iy][:, ix], und[iy][:, ix + 1]
    c, d = und[iy + 1][:, ix], und[iy + 1][:, ix + 1]
    return ((1 - ay) * ((1 - ax) * a + ax * b) + ay * ((1 - ax) * c + ax * d)).astype(np.float32)


def _texture(px: int = 100) -> np.ndarray:
    """The board seen from the front: grey background, white margin, (cols+1) x (rows+1) squares;
    texture pixel centres at k + 0.5, board coordinate (in squares) s at (s + 2.5) * px."""
    cols, rows = PATTERN
    t = np.full(((rows + 5) * px, (cols + 5) * px), 110, np.uint8)

    def at(s: float) -> int:
        return int(round((s + 2.5) * px))

    t[at(-2):at(rows + 1), at(-2):at(cols + 1)] = 220
    for i in range(-1, cols):
        for j in range(-1, rows):
            if (i + j) % 2 == 0:
                t[at(j):at(j + 1), at(i):at(i + 1)] = 30
    return t


def _render(rays: np.ndarray, Rb: np.ndarray, tb: np.ndarray, tex: np.ndarray, rng, px: int = 100) -> np.ndarray:
    """Ray-cast the board plane (pose Rb, tb in this camera) at every sample, box-filter to pixels."""
    H = np.column_stack([Rb[:, 0], Rb[:, 1], tb])  # board (x, y, 1) -> camera ray
    A = np.array([[px / SQUARE, 0, 2.5 * px - 0.5], [0, px / SQUARE, 2.5 * px - 0.5], [0, 0, 1]])
    m = cv2.perspectiveTransform(rays.reshape(-1, 1, 2), A @ np.linalg.inv(H)).reshape(rays.shape)
    img = cv2.remap(tex.astype(np.float32), m[..., 0], m[..., 1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=110)
    img = cv2.resize(img, SIZE, interpolation=cv2.INTER_AREA) + rng.normal(0, 1.0, (SIZE[1], SIZE[0]))
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def synthetic_views(tmp_path_factory) -> Path:
    """15 board poses (0.5-0.85 m, tilted up to ~30 deg) seen by the known rig, with distortion."""
    out = tmp_path_factory.mktemp("views")
    rng = np.random.default_rng(1)
    rl, rr = _rays(TRUE_LEFT), _rays(TRUE_RIGHT)
    tex = _texture()
    centre = np.array([(PATTERN[0] - 1) * SQUARE / 2, (PATTERN[1] - 1) * SQUARE / 2, 0.0])
    for i in range(15):
        Rb = cv2.Rodrigues(np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)]))[0]
        c = np.array([0.05 + rng.uniform(-0.08, 0.08), rng.uniform(-0.06, 0.06), rng.uniform(0.5, 0.85)])
        tb = c - Rb @ centre
        cv2.imwrite(str(out / f"left{i:02d}.png"), _render(rl, Rb, tb, tex, rng))
        cv2.imwrite(str(out / f"right{i:02d}.png"), _render(rr, TRUE_R @ Rb, TRUE_R @ tb + TRUE_T, tex, rng))
    return out


@pytest.fixture(scope="module")
def synthetic_result(synthetic_views) -> C.StereoResult:
    return C.calibrate_stereo(C.find_pairs(pairs_dir=str(synthetic_views)), PATTERN, SQUARE)


def test_synthetic_rig_is_recovered(synthetic_result):
    r = synthetic_result
    assert len(r.views) >= 12 and not r.without_board
    for got, true in ((r.left.K, TRUE_LEFT), (r.right.K, TRUE_RIGHT)):
        assert got[0, 0] == pytest.approx(true.fx, rel=0.005)
        assert got[1, 1] == pytest.approx(true.fy, rel=0.005)
        assert abs(got[0, 2] - true.cx) < 3 and abs(got[1, 2] - true.cy) < 3
    assert np.linalg.norm(r.T) == pytest.approx(np.linalg.norm(TRUE_T), rel=0.005)
    assert np.linalg.norm(cv2.Rodrigues(r.R.T @ TRUE_R)[0]) < 0.004  # rad (0.23 deg; correlated with cx)
    assert r.left.rms < 0.3 and r.right.rms < 0.3 and r.rms < 0.3
    assert np.all(r.left.std[[0, 1, 2, 3, 5, 6, 7, 8]] > 0) and r.left.std[4] == 0 and r.left.std[9] == 0
    rect = camera.rectify_rig(r.rig).model
    assert rect.baseline_m == pytest.approx(np.linalg.norm(TRUE_T), rel=0.005)
    report = format_report(r, (0.5, 3.0))
    for text in ("Focal Length", "Principal point", "Skew", "Distortion", "Rotation vector", "Translation vector",
                 "Stereo RMS", "± 3 standard deviations", "Rectified: f =", "disparity"):
        assert text in report


def test_calibrate_command(synthetic_views, tmp_path, capsys):
    out = tmp_path / "calib.yaml"
    rc = main(["calibrate", "--left", str(synthetic_views / "left*.png"),
               "--right", str(synthetic_views / "right*.png"),
               "--pattern", "9x6", "--square-size", str(SQUARE), "--depth-range", "0.5", "3", "-o", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    assert "left00.png: found" in text and "Stereo RMS reprojection error" in text
    assert "rectification check:" in text
    rig = camera.load_calibration(out)
    assert isinstance(rig, camera.RawRig) and rig.image_size == SIZE
    assert rig.left.fx == pytest.approx(TRUE_LEFT.fx, rel=0.005)
    assert np.linalg.norm(rig.T) == pytest.approx(0.1, rel=0.005)
    med = float(text.split("|dy| median ")[1].split(" px")[0])
    assert med < 0.5


def test_free_skew_and_k3(synthetic_views):
    pairs = C.find_pairs(pairs_dir=str(synthetic_views))[:10]
    r = C.calibrate_stereo(pairs, PATTERN, SQUARE, fix_skew=False, k3=True)
    for got, true in ((r.left.K, TRUE_LEFT), (r.right.K, TRUE_RIGHT)):
        assert abs(got[0, 1] / got[0, 0]) < 0.002  # the true skew is 0
        assert got[0, 0] == pytest.approx(true.fx, rel=0.005)
    assert r.left.std[4] > 0 and r.left.std[9] > 0  # skew and k3 were estimated
    assert r.rms < 0.3


def test_outlier_view_is_rejected(synthetic_views, tmp_path):
    for f in synthetic_views.iterdir():
        shutil.copy(f, tmp_path / f.name)
    # A corrupted view: the right image of one pair replaced by another pose's right image.
    shutil.copy(synthetic_views / "right03.png", tmp_path / "right07.png")
    r = C.calibrate_stereo(C.find_pairs(pairs_dir=str(tmp_path)), PATTERN, SQUARE)
    names = {v.right_path.name for v, _ in r.rejected}
    # Per camera the swapped image is still a valid view; the stereo per-view error catches it.
    assert names == {"right07.png"}
    assert r.rms < 0.3 and len(r.views) == 14
    assert "right07.png" in format_report(r)


def test_errors_are_clear(synthetic_views, tmp_path, capsys):
    rc = main(["calibrate", "--left", str(tmp_path / "nothing*.png"), "--right", str(synthetic_views),
               "--square-size", "0.03"])
    err = capsys.readouterr().err
    assert rc == 2 and "nothing*.png: no file matches the pattern" in err and "Traceback" not in err

    for f in ("left00.png", "right00.png", "left01.png", "right01.png", "left02.png", "right02.png"):
        shutil.copy(synthetic_views / f, tmp_path / f)
    rc = main(["calibrate", "--pairs", str(tmp_path), "--pattern", "7x5", "--square-size", "0.03",
               "-o", str(tmp_path / "x.yaml")])
    err = capsys.readouterr().err
    assert rc == 2 and "found in both images of 0 of 3 pairs" in err and "left00.png" in err
    rc = main(["calibrate", "--pairs", str(tmp_path), "--square-size", "0.03", "-o", str(tmp_path / "x.yaml")])
    err = capsys.readouterr().err
    assert rc == 2 and "found in both images of 3 of 3 pairs; at least 6 are needed" in err

    cv2.imwrite(str(tmp_path / "right01.png"), np.zeros((240, 320), np.uint8))
    rc = main(["calibrate", "--pairs", str(tmp_path), "--square-size", "0.03"])
    err = capsys.readouterr().err
    assert rc == 2 and "different sizes" in err and "right01.png" in err and "320x240" in err

    with pytest.raises(CalibrationError, match="pattern"):
        C.parse_pattern("9by6")


# --- OpenCV's sample chessboard pairs (Debian package opencv-doc) -------------------------------

SAMPLE_DIRS = ["/usr/share/doc/opencv-doc/examples/data", "/usr/share/opencv4/samples/data",
               "/usr/share/doc/opencv-doc/examples/cpp", "/usr/share/opencv/samples/data"]


@pytest.fixture(scope="module")
def opencv_sample_pairs(tmp_path_factory) -> Path:
    for d in map(Path, SAMPLE_DIRS):
        found = sorted(d.glob("left[0-9][0-9].jpg*")) if d.is_dir() else []
        if len(found) >= 10:
            out = tmp_path_factory.mktemp("opencv-samples")
            for f in sorted(d.glob("left[0-9][0-9].jpg*")) + sorted(d.glob("right[0-9][0-9].jpg*")):
                if f.suffix == ".gz":
                    with gzip.open(f) as src, open(out / f.stem, "wb") as dst:
                        shutil.copyfileobj(src, dst)
                else:
                    shutil.copy(f, out / f.name)
            return out
    pytest.skip("OpenCV's sample chessboard pairs left01..14.jpg are not installed "
                "(apt-get install opencv-doc: /usr/share/doc/opencv-doc/examples/data)")


def test_opencv_sample_pairs(opencv_sample_pairs, tmp_path, capsys):
    d = opencv_sample_pairs
    out = tmp_path / "cal.yaml"
    rc = main(["calibrate", "--left", str(d / "left*.jpg"), "--right", str(d / "right*.jpg"), "--pattern", "9x6",
               "--square-size", "0.025", "-o", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    rig = camera.load_calibration(out)
    assert 500 < rig.left.fx < 570 and 500 < rig.right.fx < 570
    assert 0.05 < np.linalg.norm(rig.T) < 0.12  # ~3.3 squares of 25 mm
    med = float(text.split("|dy| median ")[1].split(" px")[0])
    assert med < 0.5, text
    rc = main(["calibration", "check", str(d / "left03.jpg"), str(d / "right03.jpg"), "--calibration", str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and float(text.split("|dy| median ")[1].split(" px")[0]) < 0.5


# --- import / export / show ---------------------------------------------------------------------

def _assert_same_rig(a: camera.RawRig, b: camera.RawRig, tol: float = 1e-9) -> None:
    assert a.image_size == b.image_size
    for ca, cb in ((a.left, b.left), (a.right, b.right)):
        np.testing.assert_allclose(ca.K, cb.K, rtol=tol, atol=tol)
        np.testing.assert_allclose(ca.D, cb.D, rtol=tol, atol=tol)
    np.testing.assert_allclose(a.R, b.R, atol=tol)
    np.testing.assert_allclose(a.T, b.T, atol=tol)


def test_stereo_calib_import_round_trip(tmp_path, capsys):
    rig = camera.load_calibration("lifecam-studio")
    # As OpenCV's stereo_calib writes them, T in square units (here mm, so --units-m 0.001).
    fs = cv2.FileStorage(str(tmp_path / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", rig.left.K), fs.write("D1", rig.left.D.reshape(1, 5))
    fs.write("M2", rig.right.K), fs.write("D2", rig.right.D.reshape(1, 5))
    fs.release()
    fs = cv2.FileStorage(str(tmp_path / "extrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("R", rig.R), fs.write("T", (rig.T * 1000).reshape(3, 1))
    fs.write("R1", np.eye(3))  # rectification in the file is ignored (always derived)
    fs.release()
    out = tmp_path / "cal.yaml"
    rc = main(["calibration", "import", str(tmp_path / "intrinsics.yml"), str(tmp_path / "extrinsics.yml"),
               "--units-m", "0.001", "-o", str(out)])
    err = capsys.readouterr()
    assert rc == 2 and "--image-size" in err.err  # the sample writes no image size
    rc = main(["calibration", "import", str(tmp_path / "extrinsics.yml"), str(tmp_path / "intrinsics.yml"),
               "--units-m", "0.001", "--image-size", "640x480", "-o", str(out)])
    assert rc == 0
    _assert_same_rig(camera.load_calibration(out), rig)
    capsys.readouterr()
    assert main(["calibration", "show", str(out)]) == 0
    shown = capsys.readouterr().out
    assert "-99.44854  -0.53398  2.09170" in shown and "644.66377  643.44653" in shown


def test_ros_camera_info_round_trip(tmp_path):
    rig = camera.load_calibration("lifecam-studio")
    # Written as ROS's camera_calibration does: R1/R2/P1/P2 from stereoRectify, P2[0,3] = -fx' B.
    R1, R2, P1, P2, *_ = cv2.stereoRectify(rig.left.K, rig.left.D, rig.right.K, rig.right.D, rig.image_size,
                                           rig.R, rig.T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.3)
    for name, c, R, P in (("left", rig.left, R1, P1), ("right", rig.right, R2, P2)):
        doc = {"image_width": 640, "image_height": 480, "camera_name": name,
               "camera_matrix": {"rows": 3, "cols": 3, "data": c.K.ravel().tolist()},
               "distortion_model": "plumb_bob",
               "distortion_coefficients": {"rows": 1, "cols": 5, "data": list(c.dist)},
               "rectification_matrix": {"rows": 3, "cols": 3, "data": R.ravel().tolist()},
               "projection_matrix": {"rows": 3, "cols": 4, "data": P.ravel().tolist()}}
        (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump(doc))
    assert P2[0, 3] == pytest.approx(-P2[0, 0] * np.linalg.norm(rig.T), rel=1e-9)
    out = tmp_path / "cal.yaml"
    assert main(["calibration", "import", str(tmp_path / "right.yaml"), str(tmp_path / "left.yaml"),
                 "-o", str(out)]) == 0
    _assert_same_rig(camera.load_calibration(out), rig)
    # and back out through our writer, and in again
    F.write_ros_pair(camera.load_calibration(out), tmp_path / "l2_left.yaml", tmp_path / "l2_right.yaml")
    _assert_same_rig(F.import_files([str(tmp_path / "l2_left.yaml"), str(tmp_path / "l2_right.yaml")]), rig)
    F.write_stereo_calib(rig, tmp_path / "i.yml", tmp_path / "e.yml")
    _assert_same_rig(F.import_files([str(tmp_path / "i.yml"), str(tmp_path / "e.yml")]), rig)


def test_import_refuses_bad_files(tmp_path):
    (tmp_path / "left.yaml").write_text("camera_matrix: {data: [1,0,0,0,1,0,0,0,1]}\nprojection_matrix: {}\n")
    (tmp_path / "right.yaml").write_text("camera_matrix: {data: [1,0,0,0,1,0,0,0,1]}\nprojection_matrix: {}\n")
    with pytest.raises(CalibrationError, match="image_width"):
        F.import_files([str(tmp_path / "left.yaml"), str(tmp_path / "right.yaml")])
    fs = cv2.FileStorage(str(tmp_path / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", np.eye(3))
    fs.release()
    with pytest.raises(CalibrationError, match="D1"):
        F.import_files([str(tmp_path / "intrinsics.yml")], image_size=(640, 480))


def test_lifecam_profile_is_the_thesis_calibration(capsys):
    rig = camera.load_calibration("lifecam-studio")
    assert rig.image_size == (640, 480)
    assert (rig.left.fx, rig.left.fy, rig.left.cx, rig.left.cy) == (644.66377, 643.44653, 299.62051, 238.17653)
    assert rig.left.dist == (-0.01557, 0.06445, -0.00456, -0.00842, 0.0)
    assert (rig.right.fx, rig.right.fy, rig.right.cx, rig.right.cy) == (646.13434, 646.10041, 302.35729, 245.68957)
    assert rig.right.dist == (-0.02068, 0.09349, -0.00615, -0.00943, 0.0)
    assert rig.left.skew == 0 and rig.right.skew == 0
    np.testing.assert_allclose(cv2.Rodrigues(rig.R)[0].ravel(), [0.00026, 0.00426, -0.00106], atol=1e-12)
    np.testing.assert_allclose(rig.T * 1000, [-99.44854, -0.53398, 2.09170], atol=1e-9)
    assert main(["calibration", "show", "lifecam-studio"]) == 0
    text = capsys.readouterr().out
    for s in ("644.66377  643.44653", "299.62051  238.17653", "-0.01557  0.06445  -0.00456  -0.00842  0.00000",
              "646.13434  646.10041", "302.35729  245.68957", "-0.02068  0.09349  -0.00615  -0.00943  0.00000",
              "om = [ 0.00026  0.00426  -0.00106 ]", "T  = [ -99.44854  -0.53398  2.09170 ] mm",
              "baseline = 99.47197 mm", "rectified (alpha 0): f ="):
        assert s in text, s
