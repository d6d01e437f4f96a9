"""No silent calibration on a real rig: the rectify service, started without a calibration, rectifies
the synthetic scene with the thesis rig it renders, refuses frames from any other source with an
error naming the setting, and takes them once a calibration arrives on its key. Real processes,
real Zenoh."""
from __future__ import annotations

import os
import subprocess
import time

import numpy as np
import pytest
from helpers import REPO, Collector, cli, free_port, wait_port

from common import codec
from common.errors import CalibrationError
from common.keys import topic
from common.messages import CalibrationUpdate, ServiceStats, StereoFrame
from common.signing import sign
from common.supervisor import stop_processes
from common.zenoh_session import ZenohOptions, open_session
from cores.calibration.rectify import CalibrationHolder
from services.rectify.main import RectifySettings, check_assumed_calibration

RID = "rectdef"
KEY = b"test-robot-key"


def test_the_default_calibration_is_unset_and_only_the_synthetic_source_may_assume_one():
    assert RectifySettings().calibration is None
    holder = CalibrationHolder("lifecam-studio")
    check_assumed_calibration("synthetic", holder, configured=False)
    check_assumed_calibration("images", holder, configured=True)
    for source in ("cameras", "video", "images", "sbs", ""):
        with pytest.raises(CalibrationError, match="rectify.calibration.*lifecam-studio.*synthetic"):
            check_assumed_calibration(source, holder, configured=False)
    # the first calibration received replaces an assumed rig that rectified nothing yet: no jump check
    holder = CalibrationHolder("lifecam-studio", started=False)
    assert holder.offer_yaml("rectified: true\nimage_size: [640, 480]\nfocal_px: 500\nprincipal_point: [320, 240]\n"
                             "baseline_m: 0.1\n", "test")
    check_assumed_calibration("images", holder, configured=False)  # received one: fine


def _frame(seq: int, source: str) -> StereoFrame:
    img = np.random.default_rng(seq).integers(0, 255, (480, 640), dtype=np.uint8)
    return StereoFrame(robot_id=RID, seq=seq, stamp_ns=time.time_ns(), left=codec.image_from_array(img),
                       right=codec.image_from_array(img), source=source)


@pytest.mark.system
def test_rectify_service_refuses_real_frames_without_a_calibration_and_says_so():
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, PYTHONUNBUFFERED="1", BALLBOT_CALIBRATION_KEY=KEY.decode())
    for k in ("BALLBOT_RECTIFY_CALIBRATION", "BALLBOT_CONFIG", "BALLBOT_ZENOH_CONFIG", "BALLBOT_CALIBRATION_KEY_FILE"):
        env.pop(k, None)
    procs = [subprocess.Popen(cli("run", "router", "--listen", endpoint, "--robot-id", RID), env=env, cwd=REPO,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        wait_port(port, procs[0])
        procs.append(subprocess.Popen(cli("run", "rectify", "--connect", endpoint, "--mode", "client",
                                          "--robot-id", RID), env=env, cwd=REPO,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        rect, stats = Collector(StereoFrame), Collector(ServiceStats)
        with open_session(ZenohOptions(mode="client", connect=[endpoint], listen=[])) as s:
            s.declare_subscriber(topic("frames_rect").key(RID), rect)
            s.declare_subscriber(topic("stats").pattern(RID), stats)
            assert stats.wait_for(lambda items: any(x.service == "rectify" for x in items), 60)
            raw = s.declare_publisher(topic("frames_raw").key(RID))
            seq = 0

            def send(source: str) -> None:
                nonlocal seq
                seq += 1
                raw.put(codec.encode(_frame(seq, source)))

            def sent_until(source, pred, timeout=60.0) -> bool:
                """Send frames of `source` (the service keeps only the newest) until pred(rectified)."""
                deadline = time.monotonic() + timeout
                while time.monotonic() < deadline:
                    send(source)
                    if rect.wait_for(pred, 0.5):
                        return True
                return False

            # the synthetic scene: rectified with the thesis rig it renders

            assert sent_until("synthetic", lambda items: len(items) >= 1)
            n_synthetic = len(rect.items)
            # a real source: refused, counted, and the status names the setting
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                send("images")
                if stats.wait_for(lambda items: any(x.service == "rectify" and x.errors > 0 and "calibration" in
                                                    x.status for x in items), 0.5):
                    break
            last = [x for x in stats.items if x.service == "rectify"][-1]
            assert last.errors > 0 and last.status.startswith("error: no calibration for the 'images' source")
            assert all(f.source == "synthetic" for f in rect.items), "a real frame was rectified with the thesis rig"
            # calibrations on the key. The thesis rig rectified synthetic frames: it is what rectify
            # started with. Unsigned: refused; signed but of another size, or another rig (f 500 px):
            # refused; signed, the same rig (its rectified model): taken, and the real frames flow
            cal = s.declare_publisher(topic("calibration").key(RID))
            m = CalibrationHolder("lifecam-studio").current().model

            def calibration(size: str, key: bytes | None, f: float = 500.0, b: float = 0.1) -> bytes:
                msg = CalibrationUpdate(robot_id=RID, seq=0, stamp_ns=time.time_ns(), source="test",
                                        yaml=f"rectified: true\nimage_size: {size}\nfocal_px: {f}\n"
                                             f"principal_point: [{m.cx}, {m.cy}]\nbaseline_m: {b}\n")
                return codec.encode(sign(msg, key) if key else msg)

            def refused(n: int):
                return lambda items: any(x.service == "rectify" and x.extra.get("calibration_refused", 0) >= n
                                         for x in items)

            cal.put(calibration("[640, 480]", None))
            assert stats.wait_for(refused(1), 60)
            assert stats.items[-1].extra.get("calibration_unsigned_refused", 0) >= 1
            send("images")  # the stream's size, 640x480, is what a calibration must fit
            cal.put(calibration("[320, 240]", KEY))
            assert stats.wait_for(refused(2), 60)
            cal.put(calibration("[640, 480]", KEY))
            assert stats.wait_for(refused(3), 60)
            assert not any(f.source == "images" for f in rect.items)
            cal.put(calibration("[640, 480]", KEY, m.focal_px, m.baseline_m))
            assert sent_until("images", lambda items: any(f.source == "images" for f in items))
            assert len(rect.items) > n_synthetic
    finally:
        stop_processes({str(k): p for k, p in enumerate(procs)}, 10.0)


@pytest.mark.system
def test_calibration_publish_signs_with_the_robots_key_and_reports_what_rectify_did(tmp_path):
    """The local CLI that holds the key is the way to change a running rectify's calibration: a small
    recalibration of the same rig is taken, half the baseline is refused (exit 1, saying so), and
    without a key nothing is sent (exit 2, naming where the key comes from)."""
    import yaml

    from cores import camera

    rid = "publish"
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, PYTHONUNBUFFERED="1", BALLBOT_CALIBRATION_KEY=KEY.decode(), XDG_RUNTIME_DIR=str(tmp_path))
    for k in ("BALLBOT_RECTIFY_CALIBRATION", "BALLBOT_CONFIG", "BALLBOT_ZENOH_CONFIG", "BALLBOT_CALIBRATION_KEY_FILE"):
        env.pop(k, None)
    key_file = tmp_path / "robot.key"
    key_file.write_text(KEY.decode() + "\n")
    doc = camera.calibration_to_dict(camera.load_calibration("lifecam-studio"))
    tweak, half = tmp_path / "tweak.yaml", tmp_path / "half.yaml"
    tweak.write_text(yaml.safe_dump(dict(doc, T=[t * 1.02 for t in doc["T"]])))
    half.write_text(yaml.safe_dump(dict(doc, T=[t / 2 for t in doc["T"]])))
    procs = [subprocess.Popen(cli("run", "router", "--listen", endpoint, "--robot-id", rid), env=env, cwd=REPO,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        wait_port(port, procs[0])
        procs.append(subprocess.Popen(cli("run", "rectify", "--connect", endpoint, "--robot-id", rid,
                                          "--calibration", "lifecam-studio"), env=env, cwd=REPO,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        cli_env = {k: v for k, v in env.items() if k != "BALLBOT_CALIBRATION_KEY"}  # the user's shell: a key file

        def publish(path, *extra) -> subprocess.CompletedProcess:
            return subprocess.run(cli("calibration", "publish", str(path), "--connect", endpoint, "--robot-id", rid,
                                      "--timeout", "60", *extra), env=cli_env, cwd=REPO, capture_output=True,
                                  text=True, timeout=180)

        no_key = publish(tweak)
        taken = publish(tweak, "--key-file", str(key_file))
        refused = publish(half, "--key-file", str(key_file))
    finally:
        stop_processes({str(k): p for k, p in enumerate(procs)}, 10.0)
    print(f"calibration publish: no key -> {no_key.returncode}; +2 % baseline -> {taken.returncode} "
          f"({taken.stdout.strip()}); half baseline -> {refused.returncode} ({refused.stdout.strip()[:90]})")
    assert no_key.returncode == 2 and "no calibration key" in no_key.stderr and "--key-file" in no_key.stderr
    assert taken.returncode == 0 and ": taken " in taken.stdout, taken.stdout + taken.stderr
    assert refused.returncode == 1 and ": refused " in refused.stdout, refused.stdout + refused.stderr


def test_a_deployment_that_names_a_real_source_must_configure_the_rig(capsys, monkeypatch):
    """The compose files pass CAPTURE_SOURCE to rectify (rectify.source): a real source with no
    rectify.calibration stops rectify before it is up, naming what to set; synthetic, ros2 and mcap
    (which send their own, signed) start as before."""
    from ballbot_vision.cli import main
    from services.rectify.main import preflight

    monkeypatch.delenv("BALLBOT_RECTIFY_CALIBRATION", raising=False)
    assert main(["run", "rectify", "--source", "cameras", "--connect", "tcp/127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert "rectify.source is 'cameras'" in err and "RECTIFY_CALIBRATION" in err and " up (robot" not in err
    for ok in ("synthetic", "ros2", "mcap", None):
        preflight(RectifySettings(source=ok))
    preflight(RectifySettings(source="images", calibration="lifecam-studio"))
