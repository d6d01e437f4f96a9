"""`calibrate --live`: the view selection and coverage logic (cores/calibration/views.py) on projected
board corners, and end to end: a router, a real capture looping rendered chessboard pairs, and
`ballbot-vision calibrate --live` collecting views from it and writing a calibration."""
from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import REPO, cli, free_port, wait_port
from test_calibration import PATTERN, SIZE, SQUARE, TRUE_LEFT, TRUE_R, TRUE_RIGHT, TRUE_T, _rays, _render, _texture

from cores import camera
from cores.calibration import calibrate as C
from cores.calibration import views as L

CENTRE = np.array([(PATTERN[0] - 1) * SQUARE / 2, (PATTERN[1] - 1) * SQUARE / 2, 0.0])
OBJ = C.board_points(PATTERN, SQUARE).reshape(-1, 3).astype(np.float64)


def pose(rot: tuple[float, float, float], centre: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Board pose in the left camera: rotation vector, and where the board's centre is (m)."""
    Rb = cv2.Rodrigues(np.array(rot, float))[0]
    return Rb, np.array(centre, float) - Rb @ CENTRE


def corners(Rb: np.ndarray, tb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Projected board corners (N, 1, 2) in the left and right camera of the known rig."""
    pl = cv2.projectPoints(OBJ, cv2.Rodrigues(Rb)[0], tb, TRUE_LEFT.K, TRUE_LEFT.D)[0]
    pr = cv2.projectPoints(OBJ, cv2.Rodrigues(TRUE_R @ Rb)[0], TRUE_R @ tb + TRUE_T, TRUE_RIGHT.K, TRUE_RIGHT.D)[0]
    return pl.astype(np.float32), pr.astype(np.float32)


def poses() -> list[tuple[np.ndarray, np.ndarray]]:
    """16 poses: a 3x3 grid of positions at 0.75 m with tilts of ~25 degrees each way, then 7
    nearer, more tilted ones. All keep the board inside both images."""
    tilts = [(0.45, 0), (-0.45, 0), (0, 0.45), (0, -0.45), (0.3, 0.3), (-0.3, 0.3), (0.3, -0.3), (-0.3, -0.3), (0, 0)]
    out = []
    for k, (gy, gx) in enumerate((y, x) for y in (-0.085, 0.0, 0.085) for x in (-0.11, 0.0, 0.11)):
        rx, ry = tilts[k]
        out.append(pose((rx, ry, 0.1 * (k % 3 - 1)), (0.05 + gx, gy, 0.75)))
    for j, (rx, ry) in enumerate([(0.5, 0.2), (-0.5, -0.2), (0.2, 0.5), (-0.2, -0.5), (0.0, 0.0), (0.4, -0.4),
                                  (-0.4, 0.4)]):
        out.append(pose((rx, ry, 0.15 * (j % 3 - 1)), (0.05 + 0.04 * (j % 3 - 1), 0.03 * (j % 2), 0.55 + 0.04 * j)))
    return out


# --- the pure logic ------------------------------------------------------------------------------

def test_tilt_is_measured_and_named_by_the_side_turned_away():
    flat = L.describe_board(corners(*pose((0, 0, 0), (0.05, 0, 0.7)))[0], PATTERN, SIZE)
    assert abs(flat.tilt_x) < 0.05 and abs(flat.tilt_y) < 0.05 and flat.tilts == set()
    # rotating the board about the camera's y axis by -0.45 rad moves its right side away
    right_away = L.describe_board(corners(*pose((0, -0.45, 0), (0.05, 0, 0.7)))[0], PATTERN, SIZE)
    assert right_away.tilts == {"right"} and right_away.tilt_x == pytest.approx(0.45, abs=0.12)
    left_away = L.describe_board(corners(*pose((0, 0.45, 0), (0.05, 0, 0.7)))[0], PATTERN, SIZE)
    assert left_away.tilts == {"left"} and left_away.tilt_x == pytest.approx(-0.45, abs=0.12)
    bottom_away = L.describe_board(corners(*pose((0.45, 0, 0), (0.05, 0, 0.7)))[0], PATTERN, SIZE)
    top_away = L.describe_board(corners(*pose((-0.45, 0, 0), (0.05, 0, 0.7)))[0], PATTERN, SIZE)
    assert bottom_away.tilts == {"down"} and top_away.tilts == {"up"}
    # the same tilt reads the same near and far (the measure is an angle, not a ratio)
    far = L.describe_board(corners(*pose((0, -0.45, 0), (0.05, 0, 1.2)))[0], PATTERN, SIZE)
    assert far.tilt_x == pytest.approx(right_away.tilt_x, abs=0.08)
    # the corner numbering of the detector (from either end) does not change the answer
    pl = corners(*pose((0, -0.45, 0), (0.05, 0, 0.7)))[0]
    assert L.describe_board(pl[::-1], PATTERN, SIZE).tilts == {"right"}


def test_cells_and_centre():
    top_left = L.describe_board(corners(*pose((0, 0, 0), (-0.13, -0.1, 0.75)))[0], PATTERN, SIZE)
    assert (0, 0) in top_left.cells and (2, 2) not in top_left.cells
    assert top_left.centre[0] < SIZE[0] / 2 and top_left.centre[1] < SIZE[1] / 2
    assert L.cell_names()[0][0] == "top-left" and L.cell_names()[1][1] == "centre" and L.cell_names()[2][1] == "bottom"


def test_coverage_accepts_different_views_and_reports_what_is_missing():
    cov = L.Coverage(PATTERN, SIZE)
    assert cov.missing_tilts() == ["left", "right", "up", "down"] and len(cov.missing_cells()) == 9
    a = corners(*pose((0, 0, 0), (0.05, 0, 0.75)))
    assert cov.consider(*a) == (True, "first")
    # the same view again, or one barely moved: refused
    assert cov.consider(*a)[0] is False
    assert cov.consider(*corners(*pose((0, 0, 0.02), (0.055, 0.003, 0.75))))[0] is False
    assert "top-left" in cov.summary() and "tilts: left, right, up, down" in cov.summary()
    # moved, nearer (bigger), tilted: each accepted, for its own reason
    assert cov.consider(*corners(*pose((0, 0, 0), (-0.08, -0.08, 0.75)))) == (True, "moved")
    assert cov.consider(*corners(*pose((0, 0, 0), (0.05, 0, 0.55)))) == (True, "size")
    assert cov.consider(*corners(*pose((0, -0.45, 0), (0.05, 0, 0.75)))) == (True, "tilt")
    assert cov.missing_tilts() == ["left", "up", "down"]
    assert "top-left" not in cov.missing_cells()
    text = cov.summary()
    assert text.startswith("missing: ") and "; tilts: left, up, down" in text and "bottom-right" in text


def test_coverage_of_a_full_set_of_views():
    cov = L.Coverage(PATTERN, SIZE)
    accepted = sum(cov.consider(*corners(*p))[0] for p in poses())
    assert accepted >= 13
    assert cov.missing_cells() == [] and cov.missing_tilts() == []
    assert cov.summary() == "missing: none; tilts: all seen"


def test_a_cell_counts_only_when_covered_in_both_images():
    cov = L.Coverage(PATTERN, SIZE)
    pl, pr = corners(*pose((0, 0, 0), (0.05, 0, 0.75)))
    far_right = pr.copy()
    x = far_right[..., 0]
    far_right[..., 0] = 440 + (x - x.min()) * 190 / (x.max() - x.min())  # right image: only the right column
    cov.consider(pl, far_right)
    assert "centre" in cov.missing_cells() and "right" not in cov.missing_cells()
    both = L.Coverage(PATTERN, SIZE)
    both.consider(pl, pr)
    assert "centre" not in both.missing_cells()


# --- end to end ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def live_views(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("live-views")
    (out / "left").mkdir()
    (out / "right").mkdir()
    rng = np.random.default_rng(3)
    rl, rr = _rays(TRUE_LEFT), _rays(TRUE_RIGHT)
    tex = _texture()
    for i, (Rb, tb) in enumerate(poses()):
        cv2.imwrite(str(out / "left" / f"{i:02d}.png"), _render(rl, Rb, tb, tex, rng))
        cv2.imwrite(str(out / "right" / f"{i:02d}.png"), _render(rr, TRUE_R @ Rb, TRUE_R @ tb + TRUE_T, tex, rng))
    return out


@pytest.fixture
def running_capture(live_views):
    """A router and a real capture looping the rendered pairs at 8 Hz: (endpoint, robot id)."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    rid = "calib-live"
    procs: dict[str, subprocess.Popen] = {}
    try:
        procs["router"] = subprocess.Popen(cli("run", "router", "--listen", endpoint), cwd=REPO,
                                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wait_port(port, procs["router"])
        procs["capture"] = subprocess.Popen(
            cli("run", "capture", "--connect", endpoint, "--robot-id", rid, "--source", "images",
                "--images-left", str(live_views / "left"), "--images-right", str(live_views / "right"),
                "--loop", "true", "--rate-hz", "8", "--encoding", "png"),
            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        yield endpoint, rid
        assert procs["capture"].poll() is None, procs["capture"].stderr.read()
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()


def _missing_count(line: str) -> int:
    cells = line.split("missing: ")[1].split(";")[0]
    tilts = line.split("; tilts: ")[1]
    return (0 if cells == "none" else len(cells.split(", "))) + (0 if tilts == "all seen" else len(tilts.split(", ")))


@pytest.mark.system
def test_calibrate_live_from_a_running_capture(running_capture, tmp_path):
    endpoint, rid = running_capture
    out = tmp_path / "live.yaml"
    saved = tmp_path / "saved"
    calib = subprocess.run(
        cli("calibrate", "--live", "--connect", endpoint, "--robot-id", rid, "--views", "12", "--timeout", "20",
            "--pattern", "9x6", "--square-size", str(SQUARE), "--save-dir", str(saved), "-o", str(out)),
        cwd=REPO, capture_output=True, text=True, timeout=120)
    text = calib.stdout
    assert calib.returncode == 0, text + calib.stderr
    # progress after each accepted view, with what is still missing: never more than before
    progress = [line for line in text.splitlines() if line.startswith("view ")]
    assert len(progress) == 12, text
    assert progress[0].startswith("view 1/12 accepted") and "missing: " in progress[0] and "; tilts: " in progress[0]
    counts = [_missing_count(line) for line in progress]
    assert counts == sorted(counts, reverse=True) and counts[0] > counts[-1], text
    assert f"saved in {saved}" in text
    assert len(list(saved.glob("left*.png"))) == 12 and len(list(saved.glob("right*.png"))) == 12
    # the same calibration core and report as for files
    assert "Stereo RMS reprojection error" in text and "rectification check:" in text and f"wrote {out}" in text
    rig = camera.load_calibration(out)
    assert isinstance(rig, camera.RawRig) and rig.image_size == SIZE
    for got, true in ((rig.left, TRUE_LEFT), (rig.right, TRUE_RIGHT)):
        assert got.fx == pytest.approx(true.fx, rel=0.01) and got.fy == pytest.approx(true.fy, rel=0.01)
    assert np.linalg.norm(rig.T) == pytest.approx(np.linalg.norm(TRUE_T), rel=0.01)

    # Ctrl-C before --views: calibrates with the views collected so far
    out2 = tmp_path / "interrupted.yaml"
    proc = subprocess.Popen(
        cli("calibrate", "--live", "--connect", endpoint, "--robot-id", rid, "--views", "100", "--timeout", "20",
            "--pattern", "9x6", "--square-size", str(SQUARE), "--save-dir", str(tmp_path / "saved2"), "-o", str(out2)),
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if line.startswith("view 7/100 accepted"):
                proc.send_signal(signal.SIGINT)
                break
        rest, err = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text2 = "".join(lines) + rest
    assert proc.returncode == 0, text2 + err
    # (a view accepted while the signal was on its way counts too)
    n = int(text2.split("stopped: ")[1].split(" views")[0])
    assert n in (7, 8) and f"calibrate: {n} image pairs" in text2, text2
    assert camera.load_calibration(out2).left.fx == pytest.approx(TRUE_LEFT.fx, rel=0.02)


@pytest.mark.system
def test_calibrate_live_without_frames_says_so(tmp_path):
    port = free_port()  # nothing runs there: no router, no capture
    t0 = time.monotonic()
    r = subprocess.run(cli("calibrate", "--live", "--connect", f"tcp/127.0.0.1:{port}", "--robot-id", "nobody",
                           "--timeout", "1.5", "--square-size", "0.03", "--save-dir", str(tmp_path / "s"),
                           "-o", str(tmp_path / "x.yaml")),
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "no frames on ballbot/nobody/frames/raw within 1.5 s: is capture running and --connect right?" in r.stderr
    assert time.monotonic() - t0 < 30
    assert not (tmp_path / "x.yaml").exists()
