"""Recordings: the MCAP format (Foxglove schemas), writer and reader, image-folder conversion, and
the replay source's pacing and stepping. No Zenoh here (see test_record_replay.py)."""
from __future__ import annotations

import json
import shutil
import subprocess
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import cli, read_mcap

from common import codec
from common.errors import SourceError
from common.messages import (
    CameraModel,
    CameraMount,
    DisparityMap,
    FreeSpace,
    GroundEstimate,
    GroundTruth,
    Obstacle,
    ObstacleList,
    ReplayControl,
    ServiceStats,
    StereoFrame,
    TruthObstacle,
)
from cores import recording as R
from cores.recording_reader import RecordingReader, decode_image
from services.capture.mcap_source import McapSource
from services.capture.sources import SourceContext

# (mcap is a dependency of the package itself, so only jsonschema may be missing)
jsonschema = pytest.importorskip("jsonschema", reason="schema checks need jsonschema (the `test` extra)")

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
if not REAL.is_dir():
    REAL = Path("/work/shared/data/real")
KARLSRUHE = REAL / "karlsruhe-0023"
CAMERA = CameraModel(width=64, height=48, focal_px=60.0, cx=32.0, cy=24.0, baseline_m=0.1, Q=[0.0] * 16)


def pair_images(k: int, colour: bool = False) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(k)
    shape = (48, 64, 3) if colour else (48, 64)
    return rng.integers(0, 256, shape, np.uint8), rng.integers(0, 256, shape, np.uint8)


def frame(k: int, rectified: bool = False, stamp0: int = 10**18) -> StereoFrame:
    left, right = pair_images(k)
    return StereoFrame(robot_id="r", seq=k, stamp_ns=stamp0 + k * 50_000_000, left=codec.image_from_array(left),
                       right=codec.image_from_array(right), camera=CAMERA if rectified else None)


def obstacles(k: int, stamp0: int = 10**18) -> ObstacleList:
    return ObstacleList(robot_id="r", seq=k, stamp_ns=stamp0 + k * 50_000_000, publish_ns=stamp0 + k * 50_000_000 + 9,
                        stale=False, obstacles=[Obstacle(id=3, position_m=(0.1, 0.2, 2.0), size_m=(0.4, 0.5, 0.3),
                                                         distance_m=1.9, bbox_px=(5, 6, 30, 40), area_px=500,
                                                         disparity_px=3.0, confidence=0.9,
                                                         position_base_m=(2.0, -0.1, 0.3))],
                        ground=GroundEstimate(height_m=1.0, pitch_deg=15, roll_deg=1, source="fitted"),
                        mount=CameraMount(height_m=1.0, pitch_deg=15, roll_deg=1, source="ground"))


def truth(k: int, stamp0: int = 10**18) -> GroundTruth:
    return GroundTruth(robot_id="r", seq=k, stamp_ns=stamp0 + k * 50_000_000, scenario="two-boxes", obstacles=[
        TruthObstacle(name="box", kind="box", center_m=(0, 0, 2), size_m=(0.4, 0.5, 0.3),
                      visible_centroid_m=(0, 0, 1.9), nearest_m=1.85, visible_px=500, bbox_px=(4, 5, 31, 41))])


def write_recording(path: Path, n: int = 5, image_format: str = "png", chunk_size: int = 4 << 20,
                    calibration: str | None = "rectified: true\nimage_size: [64, 48]\nfocal_px: 60\n"
                                              "principal_point: [32, 24]\nbaseline_m: 0.1\n",
                    close: bool = True) -> R.RecordingWriter:
    w = R.RecordingWriter(path, chunk_size=chunk_size)
    conv = R.Converter(R.RecordOptions(image_format=image_format, raw=True))
    if calibration:
        for r in conv.calibration(calibration, "test", 10**18 - 1):
            w.write(r.topic, r.doc, r.log_time_ns)
    for k in range(n):
        for r in conv.frame(frame(k)) + conv.truth(truth(k)):
            w.write(r.topic, r.doc, r.log_time_ns, r.sequence)
    if close:
        w.close()
    return w


# --- format ------------------------------------------------------------------------------------------

def test_every_recorded_message_decodes_by_the_schema_in_the_file(tmp_path):
    conv = R.Converter(R.RecordOptions(raw=True))
    disparity = DisparityMap(robot_id="r", seq=1, stamp_ns=10**18, scale=16.0, invalid_value=-16, min_disparity=0,
                             num_disparities=64, camera=CAMERA, method="bm",
                             image=codec.image_from_array(np.full((48, 64), 320, np.int16)))
    cells = np.full(20 * 10, -1, np.int8)
    cells[:50] = 0
    cells[60:70] = 100
    free = FreeSpace(robot_id="r", seq=1, stamp_ns=10**18, publish_ns=10**18, resolution_m=0.1, width=20, height=10,
                     origin_m=(0.0, -0.5), cells=cells.tobytes())
    stats = ServiceStats(robot_id="r", service="capture", instance="i", host="h", pid=1, stamp_ns=10**18, uptime_s=1,
                         rate_hz=30, proc_ms_p50=1, age_ms_p50=1, processed=1, published=1, drops=0, decode_errors=0,
                         errors=0)
    records = (conv.frame(frame(1)) + conv.frame(frame(1, rectified=True)) + conv.disparity(disparity)
               + conv.obstacles(obstacles(1)) + conv.freespace(free) + conv.truth(truth(1)) + conv.stats(stats)
               + conv.calibration("rectified: true", "x"))
    assert {r.topic for r in records} == set(R.TOPIC_SCHEMAS)
    path = tmp_path / "all.mcap"
    w = R.RecordingWriter(path)
    for r in records:
        w.write(r.topic, r.doc, r.log_time_ns, r.sequence)
    w.close()
    channels, counts, decoded = read_mcap(path)
    for topic, name in R.TOPIC_SCHEMAS.items():
        encoding = ("protobuf", "protobuf") if name.startswith("foxglove.") else ("jsonschema", "json")
        assert channels[topic] == (name, *encoding), topic
        assert counts[topic] == sum(r.topic == topic for r in records), topic
    got = dict(decoded)
    boxes = got[R.OBSTACLE_BOXES]
    pts = boxes.points[0].points
    assert (pts[0].x, pts[0].y, pts[2].x, pts[2].y) == (5, 6, 30, 40)
    assert boxes.texts[0].text == "#3 1.90 m" and boxes.timestamp.seconds == 10**9
    cube = got[R.OBSTACLE_SCENE].entities[0].cubes[0]
    assert (cube.pose.position.x, cube.pose.position.y, cube.pose.position.z) == pytest.approx((0.1, 0.2, 2.0))
    assert (cube.size.x, cube.size.y, cube.size.z) == pytest.approx((0.4, 0.5, 0.3))
    tf = got[R.TF]
    assert tf.translation.z == pytest.approx(1.0) and (tf.parent_frame_id, tf.child_frame_id) == ("base", "camera")
    # the camera's optical axis (z) points forward and pitched 15 deg down in the base frame
    from scipy.spatial.transform import Rotation
    q = tf.rotation
    axis = Rotation.from_quat([q.x, q.y, q.z, q.w]).apply([0, 0, 1])
    assert axis[0] > 0.9 and axis[2] == pytest.approx(-np.sin(np.deg2rad(15)), abs=0.02)
    grid = got[R.FREESPACE_GRID]
    assert grid.column_count == 20 and grid.data == cells.tobytes() and grid.fields[0].name == "occupancy"
    info = got[R.CAMERA_INFO]
    assert (info.width, info.height, info.K[0], info.P[2]) == (64, 48, 60.0, 32.0)
    colour = got[R.DISPARITY_COLOR]
    assert colour.format == "jpeg" and colour.data[:2] == b"\xff\xd8"  # the JPEG's own bytes, not base64
    picture = decode_image(colour.data, colour.format, "disparity")
    assert picture.shape == (48, 64, 3) and picture.mean() > 20  # 20 px of 64: a colour, not black
    raw = got[R.RAW_LEFT]
    assert raw.frame_id == "camera_raw" and raw.data[:2] == b"\xff\xd8"
    assert decode_image(raw.data, raw.format, "raw").shape == (48, 64)
    assert got[R.OBSTACLES]["obstacles"][0]["id"] == 3


def test_rectified_pairs_replay_with_their_rectified_camera_and_raw_ones_only_when_asked(tmp_path):
    """By default a recording holds the rectified pairs (what the pipeline matched) and the rectified
    camera as a `rectified: true` calibration: replay hands rectify that, and it passes the pairs
    through unchanged. The raw pairs are recorded with `raw`."""
    assert [r.topic for r in R.Converter().frame(frame(1))] == []
    assert [r.topic for r in R.Converter(R.RecordOptions(raw=True)).frame(frame(1))] == [R.RAW_LEFT, R.RAW_RIGHT]
    path = tmp_path / "rect.mcap"
    w = R.RecordingWriter(path)
    conv = R.Converter(R.RecordOptions(image_format="png"))
    for k in range(4):
        for r in conv.frame(frame(k)) + conv.frame(frame(k, rectified=True)) + conv.truth(truth(k)):
            w.write(r.topic, r.doc, r.log_time_ns, r.sequence)
    w.close()
    reader = RecordingReader(path)
    assert reader.info().pairs("raw") == 0 and reader.info().pairs("rectified") == 4
    got = list(reader.pairs())
    assert reader.kind == "rectified" and [p.seq for p in got] == [0, 1, 2, 3]
    from common.files import parse_yaml
    from cores import camera

    cal = camera.calibration_from_dict(parse_yaml(got[0].calibration_yaml, "rectified calibration"))
    assert isinstance(cal, camera.RectifiedRig) and cal.name == "rectified camera"
    assert (cal.model.width, cal.model.height, cal.model.focal_px, cal.model.baseline_m) == (64, 48, 60.0, 0.1)
    from cores.calibration.rectify import Rectifier

    for p in got:
        left, right = pair_images(p.seq)
        assert np.array_equal(p.left, left) and np.array_equal(p.right, right)
        rectified = Rectifier(cal).rectify(p.left, p.right)
        assert [np.array_equal(a, b) for a, b in zip(rectified, (left, right))] == [True, True]
    with pytest.raises(R.RecordingError, match=r"no raw stereo pairs .*\(`record` keeps them with --raw true\)"):
        list(reader.pairs("raw"))


def write_layout1(path: Path, n: int) -> None:
    """A recording as ballbot-vision wrote them before layout 2: every channel JSON, images base64."""
    import base64

    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="ballbot-vision")
        sid = w.register_schema(name="foxglove.CompressedImage", encoding="jsonschema",
                                data=json.dumps({"title": "foxglove.CompressedImage", "type": "object"}).encode())
        cal = w.register_schema(name="ballbot.Calibration", encoding="jsonschema", data=b"{}")
        ids = {t: w.register_channel(topic=t, message_encoding="json", schema_id=sid)
               for t in (R.RAW_LEFT, R.RAW_RIGHT)}
        c = w.register_channel(topic=R.CALIBRATION, message_encoding="json", schema_id=cal)
        w.add_message(c, log_time=1, publish_time=1,
                      data=json.dumps({"yaml": "rectified: true", "source": "x"}).encode())
        for k in range(n):
            for t, img in zip((R.RAW_LEFT, R.RAW_RIGHT), pair_images(k)):
                data = cv2.imencode(".png", img)[1].tobytes()
                doc = {"timestamp": {"sec": 1, "nsec": k}, "frame_id": "camera_raw",
                       "data": base64.b64encode(data).decode(), "format": "png"}
                w.add_message(ids[t], log_time=10 + k, publish_time=10 + k, sequence=k, data=json.dumps(doc).encode())
        w.add_metadata("ballbot", {"robot_id": "r"})
        w.finish()


def test_layout_1_recordings_are_still_read_and_a_newer_layout_is_refused_by_name(tmp_path):
    old = tmp_path / "old.mcap"
    write_layout1(old, 4)
    got = list(RecordingReader(old).pairs())
    assert [p.seq for p in got] == [0, 1, 2, 3] and got[0].calibration_yaml == "rectified: true"
    for p in got:
        assert np.array_equal(p.left, pair_images(p.seq)[0]) and np.array_equal(p.right, pair_images(p.seq)[1])
    new = tmp_path / "new.mcap"
    write_recording(new, n=2)
    assert RecordingReader(new).info().metadata["layout"] == "2"
    future = tmp_path / "future.mcap"
    w = R.RecordingWriter(future, metadata={"layout": "3"})
    w.close()
    with pytest.raises(R.RecordingError, match=r"future\.mcap: recording layout 3, newer than this version of "
                                               r"ballbot-vision reads \(layouts 1 to 2\)"):
        RecordingReader(future).info()
    with pytest.raises(SourceError, match="recording layout 3"):
        McapSource(str(future))


def test_pairs_read_back_as_written(tmp_path):
    path = tmp_path / "r.mcap"
    write_recording(path, n=6)
    reader = RecordingReader(path)
    info = reader.info()
    assert info.complete and info.pairs("raw") == 6 and info.channels[R.CALIBRATION] == 1
    got = list(reader.pairs())
    assert [p.seq for p in got] == list(range(6))
    for p in got:
        left, right = pair_images(p.seq)
        assert np.array_equal(p.left, left) and np.array_equal(p.right, right)  # png: lossless
        assert p.truth[0].bbox_px == (4, 5, 31, 41) and p.scenario == "two-boxes"
        assert "baseline_m: 0.1" in p.calibration_yaml
    assert reader.unpaired == 0


def test_jpeg_recording_is_close_to_the_original(tmp_path):
    path = tmp_path / "j.mcap"
    w = R.RecordingWriter(path)
    conv = R.Converter(R.RecordOptions(image_format="jpeg", jpeg_quality=95, raw=True))
    img = cv2.GaussianBlur(pair_images(0)[0], (7, 7), 2)
    msg = StereoFrame(robot_id="r", seq=0, stamp_ns=1, left=codec.image_from_array(img),
                      right=codec.image_from_array(img))
    for r in conv.frame(msg):
        w.write(r.topic, r.doc, r.log_time_ns, r.sequence)
    w.close()
    (p,) = list(RecordingReader(path).pairs())
    assert np.abs(p.left.astype(int) - img).mean() < 2.0


def test_a_killed_writer_leaves_every_finished_chunk_readable(tmp_path):
    path = tmp_path / "killed.mcap"
    w = write_recording(path, n=20, chunk_size=2000, close=False)  # never finished: no index, no footer
    w._file.flush()
    cut = tmp_path / "cut.mcap"
    shutil.copy(path, cut)
    reader = RecordingReader(cut)
    pairs = list(reader.pairs())
    assert reader.truncated and not reader.info().complete
    assert 15 <= len(pairs) <= 20, len(pairs)
    assert [p.seq for p in pairs] == list(range(len(pairs)))
    w.close()
    # a complete file cut off in the middle reads up to the cut as well
    data = path.read_bytes()
    half = tmp_path / "half.mcap"
    half.write_bytes(data[: len(data) // 2])
    r2 = RecordingReader(half)
    n = len(list(r2.pairs()))
    assert r2.truncated and 3 <= n < 20


@pytest.mark.parametrize("content, error", [
    (None, r"recording .*missing\.mcap: no such file or folder"),
    (b"hello, not a recording", r"bad\.mcap: not an MCAP file"),
])
def test_unreadable_recordings_are_named(tmp_path, content, error):
    name = "missing.mcap" if content is None else "bad.mcap"
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(R.RecordingError, match=error):
        RecordingReader(path).info()
    with pytest.raises(SourceError, match="mcap: .*" + error):
        McapSource(str(path))


def test_a_replay_names_its_calibration(tmp_path, caplog):
    """A recorded calibration without a name is named after where it came from, so rectify's log
    says which calibration a replay runs with (it used to say '?')."""
    path = tmp_path / "r.mcap"
    write_recording(path, n=2)  # its calibration has no `name:`; recorded from "test"
    with caplog.at_level("INFO", logger="ballbot.capture"):
        src = McapSource(str(path))
    assert src.calibration_name == "test" and "name: test" in src.calibration_yaml
    assert "2 raw pairs, calibration 'test'" in caplog.text
    from common.files import parse_yaml
    from cores import camera

    assert camera.calibration_from_dict(parse_yaml(src.calibration_yaml, "x")).model.baseline_m == 0.1


def test_a_recording_without_pairs_says_what_it_holds(tmp_path):
    path = tmp_path / "stats-only.mcap"
    w = R.RecordingWriter(path)
    for r in R.Converter.calibration("rectified: true", "x"):
        w.write(r.topic, r.doc, r.log_time_ns)
    w.close()
    with pytest.raises(SourceError, match=r"stats-only\.mcap holds no stereo pairs \(topics: /calibration\)"):
        McapSource(str(path))
    with pytest.raises(R.RecordingError, match=r"no raw stereo pairs .* it holds /calibration"):
        list(RecordingReader(path).pairs("raw"))
    with pytest.raises(SourceError, match=r"no recording given \(--mcap FILE\)"):
        McapSource("")


# --- replay source -------------------------------------------------------------------------------------

def test_replay_keeps_the_recorded_timing_times_the_speed(tmp_path):
    path = tmp_path / "r.mcap"
    write_recording(path, n=9)  # 8 gaps of 50 ms = 0.4 s as recorded
    for speed, recorded_s in ((1.0, 0.4), (4.0, 0.1)):
        src = McapSource(str(path), speed=speed)
        t0 = time.monotonic()
        n = 0
        while src.read() is not None:
            n += 1
        took = time.monotonic() - t0
        assert n == 9 and src.ended
        assert took >= recorded_s * 0.95, (speed, took)  # never faster than asked
    src = McapSource(str(path), pace="max")
    assert sum(1 for _ in iter(src.read, None)) == 9


def test_replay_steps_frame_by_frame_and_loops(tmp_path):
    path = tmp_path / "r.mcap"
    write_recording(path, n=3)
    ctx = SourceContext()
    src = McapSource(str(path), step=True, loop=True, ctx=ctx)
    got: list = []
    done = threading.Event()

    def reader():
        while not ctx.stop.is_set():
            pair = src.read()
            if pair is None:
                break
            got.append(int(pair.extra["recorded_seq"]))
            if len(got) in (2, 5):
                done.set()

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    assert not done.wait(0.5) and got == []  # paused: nothing until a step
    src.control(ReplayControl(robot_id="r", seq=0, stamp_ns=0, action="step", frames=2))
    assert done.wait(10) and got == [0, 1]
    done.clear()
    src.control(ReplayControl(robot_id="r", seq=0, stamp_ns=0, action="step", frames=3))
    assert done.wait(10)
    assert got == [0, 1, 2, 0, 1]  # looped after the third pair
    assert ctx.extra["replay_paused"] == 1.0 and ctx.extra["replay_total"] == 3.0
    ctx.stop.set()
    src.close()
    t.join(5)
    assert not t.is_alive()


# --- image folders <-> MCAP ------------------------------------------------------------------------------

def make_folders(root: Path, n: int, colour: bool, names=lambda i: f"img{i}.png") -> tuple[Path, Path]:
    (root / "L").mkdir(parents=True)
    (root / "R").mkdir()
    for i in range(n):
        left, right = pair_images(i, colour)
        cv2.imwrite(str(root / "L" / names(i)), left)
        cv2.imwrite(str(root / "R" / names(i)), right)
    return root / "L", root / "R"


@pytest.mark.parametrize("colour", [False, True])
def test_image_folders_to_mcap_and_back_are_identical(tmp_path, colour):
    left, right = make_folders(tmp_path / "in", 12, colour)  # img2 before img10: natural order
    out = tmp_path / "rec.mcap"
    r = subprocess.run(cli("mcap", "from-images", str(left), str(right), "-o", str(out), "--fps", "10",
                           "--calibration", "lifecam-studio"), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    info = json.loads(subprocess.run(cli("mcap", "info", str(out), "--json"), capture_output=True, text=True,
                                     timeout=60).stdout)
    assert info["raw_pairs"] == 12 and info["duration_s"] == pytest.approx(1.1)
    back = tmp_path / "back"
    r = subprocess.run(cli("mcap", "to-images", str(out), "-o", str(back)), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    for i in range(12):
        a, b = pair_images(i, colour)
        assert np.array_equal(cv2.imread(str(back / "left" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED), a)
        assert np.array_equal(cv2.imread(str(back / "right" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED), b)
    assert "T:" in (back / "calibration.yaml").read_text()


def test_timestamp_names_give_the_recorded_times(tmp_path):
    t0 = 1403715275262142976
    left, right = make_folders(tmp_path / "in", 4, False, names=lambda i: f"{t0 + i * 50_000_000}.png")
    out = tmp_path / "rec.mcap"
    r = subprocess.run(cli("mcap", "from-images", str(left), str(right), "-o", str(out)), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    stamps = [p.stamp_ns for p in RecordingReader(out).pairs()]
    assert stamps == [t0 + i * 50_000_000 for i in range(4)]


def test_from_images_names_what_is_wrong(tmp_path):
    left, right = make_folders(tmp_path / "in", 3, False)
    (right / "img2.png").unlink()
    r = subprocess.run(cli("mcap", "from-images", str(left), str(right), "-o", str(tmp_path / "x.mcap")),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "3 left images" in r.stderr and "2 right images" in r.stderr and "img2.png" in r.stderr
    r = subprocess.run(cli("mcap", "from-images", str(left), str(right), "-o", str(tmp_path / "x.txt")),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "x.txt: a recording's name ends in .mcap" in r.stderr
    r = subprocess.run(cli("mcap", "info", str(left / "img0.png")), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "img0.png: not an MCAP file" in r.stderr


@pytest.mark.skipif(not KARLSRUHE.is_dir(), reason=f"real recordings not found at {REAL} (see HELPERS.md)")
def test_karlsruhe_folders_round_trip_with_their_calibration(tmp_path):
    out = tmp_path / "karlsruhe.mcap"
    r = subprocess.run(cli("mcap", "from-images", str(KARLSRUHE / "left"), str(KARLSRUHE / "right"), "-o", str(out),
                           "--fps", "10", "--calibration", str(KARLSRUHE / "calibration.yaml")),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    back = tmp_path / "back"
    r = subprocess.run(cli("mcap", "to-images", str(out), "-o", str(back)), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    originals = sorted((KARLSRUHE / "left").glob("*.png"))
    copies = sorted((back / "left").glob("*.png"))
    assert len(originals) == len(copies) == 40
    for a, b in zip(originals[::7], copies[::7]):
        assert np.array_equal(cv2.imread(str(a), cv2.IMREAD_UNCHANGED), cv2.imread(str(b), cv2.IMREAD_UNCHANGED))
    assert (back / "calibration.yaml").read_text() == (KARLSRUHE / "calibration.yaml").read_text()


def test_obstacles_reads_a_recording_like_the_image_folders_it_came_from(tmp_path):
    from services.capture.sources import SyntheticSource

    src = SyntheticSource("two-boxes", "lifecam-studio", 15.0)
    left_dir, right_dir = tmp_path / "L", tmp_path / "R"
    left_dir.mkdir()
    right_dir.mkdir()
    for i in range(3):
        p = src.read()
        cv2.imwrite(str(left_dir / f"{i}.png"), p.left)
        cv2.imwrite(str(right_dir / f"{i}.png"), p.right)
    rec = tmp_path / "rec.mcap"
    r = subprocess.run(cli("mcap", "from-images", str(left_dir), str(right_dir), "-o", str(rec), "--fps", "15",
                           "--calibration", "lifecam-studio"), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    from_files = subprocess.run(cli("obstacles", str(left_dir), str(right_dir), "--calibration", "lifecam-studio",
                                    "--json"), capture_output=True, text=True, timeout=300)
    from_mcap = subprocess.run(cli("obstacles", str(rec), "--json"), capture_output=True, text=True, timeout=300)
    assert from_files.returncode == 0 and from_mcap.returncode == 0, from_mcap.stderr
    a = [json.loads(line)["obstacles"] for line in from_files.stdout.splitlines()]
    b = [json.loads(line)["obstacles"] for line in from_mcap.stdout.splitlines()]
    assert len(a) == len(b) == 3 and len(b[0]) == 2
    assert [[o["position_m"] for o in lst] for lst in a] == [[o["position_m"] for o in lst] for lst in b]
    r = subprocess.run(cli("obstacles", str(left_dir)), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "need LEFT, RIGHT and --calibration" in r.stderr
