"""No silent calibration on a real rig: the rectify service, started without a calibration, rectifies
the synthetic scene with the thesis rig it renders, refuses frames from any other source with an
error naming the setting, and takes them once a calibration arrives on its key. Real processes,
real Zenoh."""
from __future__ import annotations

import os
import signal
import subprocess
import time

import numpy as np
import pytest

from common import codec
from common.errors import CalibrationError
from common.keys import topic
from common.messages import CalibrationUpdate, ServiceStats, StereoFrame
from common.zenoh_session import ZenohOptions, open_session
from cores.calibration.rectify import CalibrationHolder
from services.rectify.main import RectifySettings, check_assumed_calibration

from helpers import REPO, Collector, cli, free_port, wait_port

RID = "rectdef"


def test_the_default_calibration_is_unset_and_only_the_synthetic_source_may_assume_one():
    assert RectifySettings().calibration is None
    holder = CalibrationHolder("lifecam-studio")
    check_assumed_calibration("synthetic", holder, configured=False)
    check_assumed_calibration("images", holder, configured=True)
    for source in ("cameras", "video", "images", "sbs", ""):
        with pytest.raises(CalibrationError, match="rectify.calibration.*lifecam-studio.*synthetic"):
            check_assumed_calibration(source, holder, configured=False)
    # the first calibration received replaces an assumed rig: the service takes it without the jump check
    assert holder.offer_yaml("rectified: true\nimage_size: [640, 480]\nfocal_px: 500\nprincipal_point: [320, 240]\n"
                             "baseline_m: 0.1\n", "test", check_change=False)
    check_assumed_calibration("images", holder, configured=False)  # received one: fine


def _frame(seq: int, source: str) -> StereoFrame:
    img = np.random.default_rng(seq).integers(0, 255, (480, 640), dtype=np.uint8)
    return StereoFrame(robot_id=RID, seq=seq, stamp_ns=time.time_ns(), left=codec.image_from_array(img),
                       right=codec.image_from_array(img), source=source)


@pytest.mark.system
def test_rectify_service_refuses_real_frames_without_a_calibration_and_says_so():
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for k in ("BALLBOT_RECTIFY_CALIBRATION", "BALLBOT_CONFIG", "BALLBOT_ZENOH_CONFIG"):
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
            # a calibration on the key: the real frames flow
            cal = s.declare_publisher(topic("calibration").key(RID))
            cal.put(codec.encode(CalibrationUpdate(
                robot_id=RID, seq=0, stamp_ns=time.time_ns(), source="test",
                yaml="rectified: true\nimage_size: [640, 480]\nfocal_px: 500\nprincipal_point: [320, 240]\n"
                     "baseline_m: 0.1\n")))
            assert sent_until("images", lambda items: any(f.source == "images" for f in items))
            assert len(rect.items) > n_synthetic
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
