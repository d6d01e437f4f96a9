"""Record the running pipeline, stop the recorder the ways a user does (Ctrl-C, SIGTERM, kill -9),
read the file back with the mcap reader, then replay it through `up` (capture --source mcap) and
check the obstacles against the recorded truth; step a replay frame by frame; replay a real
recording."""
from __future__ import annotations

import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap", reason="recordings need the `mcap` package (the `record` extra)")

from helpers import REPO, Collector, Up, cli, read_mcap

from common.keys import topic
from common.messages import GroundTruth, ObstacleList, ServiceStats, StereoFrame
from cores import recording as R
from cores.recording_reader import RecordingReader

pytestmark = pytest.mark.system

REAL = Path("/work/shared/data/real")
KARLSRUHE = REAL / "karlsruhe-0023"


def start_recorder(up: Up, out: Path, *args: str) -> subprocess.Popen:
    """`record` once the pipeline runs (fresh obstacle lists), as a user would start it."""
    lists = Collector(ObstacleList)
    with up.session() as s:
        s.declare_subscriber(topic("obstacles").key(up.robot_id), lists)
        assert lists.wait_for(lambda items: sum(not m.stale for m in items) >= 3, 120), "the pipeline did not start"
    log = open(str(out) + ".log", "w")
    return subprocess.Popen(cli("record", str(out), "--connect", up.endpoint, "--robot-id", up.robot_id, *args),
                            stdout=log, stderr=subprocess.STDOUT, cwd=REPO)


def wait_recorded(up: Up, pairs: int, timeout: float = 120) -> None:
    """Until the recorder's own stats say it wrote `pairs` pairs (rectified, or raw with --raw true)."""
    stats = Collector(ServiceStats)
    with up.session() as s:
        s.declare_subscriber(topic("stats").key(up.robot_id, service="record", instance="*"), stats)
        ok = stats.wait_for(lambda items: any(st.extra.get("pairs_written", 0) >= pairs for st in items), timeout)
    assert ok, f"the recorder did not write {pairs} pairs within {timeout} s"


def read_back(path: Path) -> dict[str, list]:
    """Every message by topic, decoded by the schemas in the file (as the Foxglove app does); the file
    must have its summary, and every channel the schema of the layout."""
    channels, _, decoded = read_mcap(path)
    for t, (name, _, _) in channels.items():
        assert name == R.TOPIC_SCHEMAS[t], t
    out: dict[str, list] = {}
    for t, msg in decoded:
        out.setdefault(t, []).append(msg)
    return out


@pytest.mark.parametrize("stop", [pytest.param(signal.SIGINT, marks=pytest.mark.slow), signal.SIGTERM])
def test_a_stopped_recording_is_a_complete_file_that_replays_like_the_live_pipeline(tmp_path, stop):
    out = tmp_path / "session.mcap"
    up = Up(robot_id="rec")
    raw = stop == signal.SIGTERM  # one run records the raw pairs too
    try:
        rec = start_recorder(up, out, *(["--raw", "true"] if raw else []))
        wait_recorded(up, 30)
        rec.send_signal(stop)  # Ctrl-C is SIGINT
        assert rec.wait(60) == 0, Path(str(out) + ".log").read_text()
    finally:
        up.stop()
    log = Path(str(out) + ".log").read_text()
    assert "wrote " in log and "dropped 0 (queue full)" in log, log
    msgs = read_back(out)
    assert len(msgs[R.RECT_LEFT]) >= 30 and len(msgs[R.RECT_LEFT]) == len(msgs[R.RECT_RIGHT])
    for t in (R.DISPARITY_COLOR, R.OBSTACLES, R.OBSTACLE_BOXES, R.OBSTACLE_SCENE, R.TRUTH, R.STATS,
              R.CAMERA_INFO, R.RECT_CALIBRATION):
        assert msgs.get(t), f"nothing on {t}"
    image = msgs[R.RECT_LEFT][0]
    assert image.format == "jpeg" and image.data[:2] == b"\xff\xd8"  # the JPEG itself, no base64
    lists = [ObstacleList.model_validate(d) for d in msgs[R.OBSTACLES]]
    assert any(len(m.obstacles) == 2 and not m.stale for m in lists)
    assert "rectified: true" in msgs[R.RECT_CALIBRATION][0]["yaml"]
    if raw:
        assert len(msgs[R.RAW_LEFT]) >= 30 and len(msgs[R.RAW_LEFT]) == len(msgs[R.RAW_RIGHT])
        assert "lifecam" in msgs[R.CALIBRATION][0]["source"] and "T:" in msgs[R.CALIBRATION][0]["yaml"]
        return
    assert R.RAW_LEFT not in msgs
    # --- replay the recording through the unchanged pipeline; its truth goes out with each pair
    up = Up(robot_id="replay", extra_env={"BALLBOT_CAPTURE_SOURCE": "mcap", "BALLBOT_CAPTURE_MCAP": str(out),
                                          "BALLBOT_CAPTURE_LOOP": "true"})
    try:
        truths, lists, frames = Collector(GroundTruth), Collector(ObstacleList), Collector(StereoFrame)
        with up.session() as s:
            s.declare_subscriber(topic("truth").key(up.robot_id), truths)
            s.declare_subscriber(topic("obstacles").key(up.robot_id), lists)
            s.declare_subscriber(topic("frames_raw").key(up.robot_id), frames)
            # five fresh lists whose pair's truth has arrived too (truth and lists travel on their own
            # keys, and on a loaded machine either may be a little behind the other)
            def judged(items) -> list:
                truth_seqs = {t.seq for t in list(truths.items)}
                return [m for m in items if not m.stale and m.seq in truth_seqs]
            assert lists.wait_for(lambda items: sum(m.obstacles != [] for m in judged(items)) >= 5, 120), \
                up.log_path.read_text()[-3000:]
            assert frames.items[0].source == "mcap"
            by_seq = {t.seq: t for t in truths.items}
            checked = 0
            for m in judged(lists.items)[-5:]:
                truth = by_seq[m.seq]
                assert len(m.obstacles) == len(truth.obstacles)
                for t in truth.obstacles:
                    best = min(np.linalg.norm(np.subtract(o.position_m, t.visible_centroid_m)) for o in m.obstacles)
                    assert best <= 0.05 * np.linalg.norm(t.visible_centroid_m), (t.name, best)
                checked += 1
            assert checked >= 3
    finally:
        up.stop()
    log = up.log_path.read_text()
    # the replay names the calibration it runs with (it used to be '?')
    assert "mcap: replaying" in log and "rectified pairs, calibration 'rectified camera'" in log, log[-3000:]
    assert "calibration 'rectified camera' from the calibration key (recording" in log


@pytest.mark.slow
def test_a_killed_recorder_leaves_a_readable_file(tmp_path):
    out = tmp_path / "killed.mcap"
    up = Up(robot_id="kill")
    try:
        rec = start_recorder(up, out)
        wait_recorded(up, 40)
        rec.send_signal(signal.SIGKILL)
        rec.wait(30)
    finally:
        up.stop()
    reader = RecordingReader(out)
    pairs = list(reader.pairs())
    assert reader.truncated and len(pairs) >= 10, len(pairs)  # up to the last chunk that reached the disk
    r = subprocess.run(cli("mcap", "info", str(out)), capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "NO INDEX" in r.stdout


@pytest.mark.slow
def test_a_replay_steps_frame_by_frame(tmp_path):
    out = tmp_path / "three.mcap"
    left, right = tmp_path / "L", tmp_path / "R"
    left.mkdir()
    right.mkdir()
    import cv2

    from services.capture.sources import SyntheticSource

    src = SyntheticSource("two-boxes", "lifecam-studio", 30.0)
    for i in range(3):
        p = src.read()
        cv2.imwrite(str(left / f"{i}.png"), p.left)
        cv2.imwrite(str(right / f"{i}.png"), p.right)
    r = subprocess.run(cli("mcap", "from-images", str(left), str(right), "-o", str(out), "--calibration",
                           "lifecam-studio"), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    up = Up(robot_id="step", extra_env={"BALLBOT_CAPTURE_SOURCE": "mcap", "BALLBOT_CAPTURE_MCAP": str(out),
                                        "BALLBOT_CAPTURE_MCAP_STEP": "true", "BALLBOT_CAPTURE_LOOP": "true"})
    try:
        frames, stats = Collector(StereoFrame), Collector(ServiceStats)
        with up.session() as s:
            s.declare_subscriber(topic("frames_raw").key(up.robot_id), frames)
            s.declare_subscriber(topic("stats").key(up.robot_id, service="capture", instance="*"), stats)
            assert stats.wait_for(lambda items: any("paused 0/3" in st.status for st in items), 120)
            assert not frames.wait_for(lambda items: len(items) > 0, 2.0), "a paused replay published a pair"

            def step(n: int) -> None:
                r = subprocess.run(cli("replay", "step", "--frames", str(n), "--connect", up.endpoint, "--robot-id",
                                       up.robot_id), capture_output=True, text=True, timeout=60)
                assert r.returncode == 0, r.stderr

            step(2)
            assert frames.wait_for(lambda items: len(items) == 2, 60)
            assert not frames.wait_for(lambda items: len(items) > 2, 2.0), "stepped past the 2 pairs asked for"
            step(2)  # the third pair, then the first again (looping)
            assert frames.wait_for(lambda items: len(items) == 4, 60)
            assert not frames.wait_for(lambda items: len(items) > 4, 2.0)
            r = subprocess.run(cli("replay", "step", "--frames", "0", "--connect", up.endpoint),
                               capture_output=True, text=True, timeout=60)
            assert r.returncode == 2 and "replay --frames" in r.stderr
    finally:
        up.stop()


@pytest.mark.skipif(not KARLSRUHE.is_dir(), reason=f"real recordings not found at {REAL} (see HELPERS.md)")
def test_the_karlsruhe_recording_replayed_through_up_gives_obstacle_lists(tmp_path):
    out = tmp_path / "karlsruhe.mcap"
    r = subprocess.run(cli("mcap", "from-images", str(KARLSRUHE / "left"), str(KARLSRUHE / "right"), "-o", str(out),
                           "--fps", "10", "--calibration", str(KARLSRUHE / "calibration.yaml")),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    config = tmp_path / "karlsruhe.yaml"
    # A car's camera: 128 disparities reach 5.7 m at f*B = 368 px m; the range gate at 25 m.
    config.write_text(f"capture: {{source: mcap, mcap: {out}, loop: true}}\n"
                      "disparity: {num_disparities: 128}\n"
                      "segmenter: {max_range_m: 25}\n"
                      "mount: {height_m: 1.65, pitch_deg: 0}\n")
    up = Up(robot_id="karlsruhe", extra_args=["--config", str(config)])
    try:
        lists = Collector(ObstacleList)
        with up.session() as s:
            s.declare_subscriber(topic("obstacles").key(up.robot_id), lists)
            # three lists computed from three recorded pairs (on a busy machine they may come late and
            # be flagged stale: the flag is about the robot's latency, not about the replay)
            assert lists.wait_for(lambda items: len({m.seq for m in items}) >= 3, 240), \
                up.log_path.read_text()[-3000:]
    finally:
        up.stop()
    log = up.log_path.read_text()
    assert "from the calibration key (recording" in log  # rectify took the recording's calibration
    assert any(m.obstacles for m in lists.items)
    for m in lists.items:
        for o in m.obstacles:
            x0, y0, x1, y1 = o.bbox_px
            assert 0 <= x0 < x1 <= 1344 and 0 <= y0 < y1 <= 372  # boxes in the recorded 1344x372 image
