"""What a new user meets in the first hour, each fed as they would meet it: `watch` with nothing
running says so and how to check, while it keeps waiting; an image narrower than the search range
is one line for every method, offline and in the service; the test command shows why tests skip;
recordings land in one git-ignored folder. (A misspelled config section: test_settings.py; a
replay naming its calibration: test_recording.py and test_record_replay.py.)"""
from __future__ import annotations

import subprocess
import sys
import threading
import time

import cv2
import numpy as np
import pytest
from helpers import REPO, Collector, cli, free_port, wait_port

from common import codec
from common.keys import topic
from common.messages import CameraModel, ServiceStats, StereoFrame


def _router(port: int) -> subprocess.Popen:
    proc = subprocess.Popen(cli("run", "router", "--listen", f"tcp/127.0.0.1:{port}"), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, cwd=REPO)
    wait_port(port, proc, 60)
    return proc


def _stop(*procs: subprocess.Popen) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_watch_with_nothing_running_says_so_and_how_to_check_while_it_keeps_waiting():
    port = free_port()
    router = _router(port)  # a router, no pipeline: what `watch` meets when `up` is not running
    endpoint = f"tcp/127.0.0.1:{port}"
    watch = subprocess.Popen(cli("watch", "--connect", endpoint), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, cwd=REPO)
    lines: list[str] = []
    hinted = threading.Event()

    def read() -> None:
        for line in watch.stderr:
            lines.append(line)
            if "nothing published" in line:
                hinted.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        assert hinted.wait(90), "".join(lines)
        hint = next(line for line in lines if "nothing published" in line)
        assert "ballbot/obstacles/**" in hint and "still waiting" in hint
        assert f"`ballbot-vision status --connect {endpoint}`" in hint
        assert watch.poll() is None  # it keeps waiting: a pipeline started later is still watched
    finally:
        _stop(watch, router)


NARROW = ["--num-disparities", "64"]


@pytest.fixture(scope="module")
def narrow_pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("narrow")
    rng = np.random.default_rng(1)
    img = rng.integers(0, 255, (60, 50), np.uint8)
    cv2.imwrite(str(d / "l.png"), img)
    cv2.imwrite(str(d / "r.png"), np.roll(img, -3, axis=1))
    (d / "cal.yaml").write_text("rectified: true\nimage_size: [50, 60]\nfocal_px: 40\nprincipal_point: [25, 30]\n"
                                "baseline_m: 0.1\n")
    return d


@pytest.mark.parametrize("command", ["disparity", "obstacles"])
@pytest.mark.parametrize("method", ["bm", "sgbm", "dense"])
def test_an_image_narrower_than_the_search_range_is_one_line_for_every_method(narrow_pair, command, method):
    d = narrow_pair
    flag = "--method" if command == "disparity" else "--disparity-method"
    extra = ["-o", str(d / f"{method}.png")] if command == "disparity" else []
    ndisp = NARROW if command == "disparity" else ["--disparity-num-disparities", "64"]
    r = subprocess.run(cli(command, str(d / "l.png"), str(d / "r.png"), "--calibration", str(d / "cal.yaml"),
                           flag, method, *ndisp, *extra), capture_output=True, text=True, timeout=180)
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in r.stderr, r.stderr
    assert err[0].startswith("ballbot-vision: error: ") and "the image is 50 px wide, too narrow for the search " \
        f"range: {method} searches disparities 0..63 px" in err[0], err[0]
    assert "--num-disparities to at most" in err[0]


@pytest.mark.system
def test_the_disparity_service_logs_and_counts_a_narrow_frame_and_goes_on(tmp_path):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = _router(port)
    log_path = tmp_path / "disparity.log"
    with open(log_path, "w") as log:
        service = subprocess.Popen(cli("run", "disparity", "--connect", endpoint, "--robot-id", "narrow",
                                       "--num-disparities", "64"), stdout=log, stderr=subprocess.STDOUT, cwd=REPO)
    try:
        from common.inbox import _META
        from common.zenoh_session import ZenohOptions, open_session

        stats = Collector(ServiceStats)
        with open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"])) as s:
            s.declare_subscriber(topic("stats").key("narrow", service="disparity", instance="*"), stats)
            assert stats.wait_for(lambda items: len(items) >= 1, 120), log_path.read_text()
            pub = s.declare_publisher(topic("frames_rect").key("narrow"))
            cam = CameraModel(width=50, height=60, focal_px=40.0, cx=25.0, cy=30.0, baseline_m=0.1, Q=[0.0] * 16)
            rng = np.random.default_rng(2)
            for seq in range(1, 40):
                img = rng.integers(0, 255, (60, 50), np.uint8)
                stamp = time.time_ns()
                msg = StereoFrame(robot_id="narrow", seq=seq, stamp_ns=stamp, left=codec.image_from_array(img),
                                  right=codec.image_from_array(img), camera=cam)
                pub.put(codec.encode(msg), attachment=_META.pack(stamp, 7, seq))
                if stats.wait_for(lambda items: any(st.errors >= 3 for st in items), 0.2):
                    break
            assert stats.wait_for(lambda items: any(st.errors >= 3 for st in items), 60), \
                [(st.errors, st.status) for st in stats.items[-3:]] + [log_path.read_text()[-2000:]]
        assert service.poll() is None, "the service died on a narrow frame"
    finally:
        _stop(service, router)
    text = log_path.read_text()
    assert "too narrow for the search range" in text and "Traceback" not in text, text[-3000:]


def test_the_test_command_shows_why_tests_were_skipped(tmp_path):
    (tmp_path / "test_skips.py").write_text("import pytest\n\n\ndef test_x():\n    pytest.skip('no camera attached')\n")
    r = subprocess.run([sys.executable, "-m", "pytest", "-c", str(REPO / "pyproject.toml"), "--rootdir", str(REPO),
                        "-p", "no:cacheprovider", str(tmp_path / "test_skips.py")],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    assert "SKIPPED [1]" in r.stdout and "no camera attached" in r.stdout, r.stdout


def test_recordings_land_in_one_folder_that_git_ignores(tmp_path):
    from ballbot_vision.mcap_commands import default_recording_path

    p = default_recording_path("r7", now=time.mktime((2026, 12, 1, 18, 5, 9, 0, 0, -1)))
    assert str(p) == "recordings/r7-20261201-180509.mcap"
    for path in (str(p), "session.mcap", "deep/down/x.mcap"):
        r = subprocess.run(["git", "check-ignore", "-q", path], cwd=REPO)
        assert r.returncode == 0, f"{path} is not git-ignored"
    r = subprocess.run(cli("record", "--help"), capture_output=True, text=True, timeout=60)
    assert "recordings/<robot id>-<date>-<time>.mcap" in " ".join(r.stdout.split())
