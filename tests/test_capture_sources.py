"""Capture sources without hardware: image folders and videos the tests write, the camera source
through the cv2.VideoCapture interface on generated videos and fakes (unplug/replug, skew), the
errors a user meets, and one real `run capture --source images` process over Zenoh."""
from __future__ import annotations

import subprocess
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.errors import SourceError
from services.capture import cameras
from services.capture.main import open_source
from services.capture.settings import CaptureSettings
from services.capture.sources import SourceContext

W, H = 160, 120  # small frames keep the tests fast; the benchmark measures 640x480


def pattern(i: int, side: int, w: int = W, h: int = H) -> np.ndarray:
    """A frame whose index and side can be read back after lossy compression: a flat level
    (20 + 8 i + 100 side) with a textured border."""
    img = np.full((h, w, 3), 20 + 8 * i + 100 * side, np.uint8)
    img[:8] = np.random.default_rng(i).integers(0, 255, (8, w, 3), np.uint8)
    return img


def level(img: np.ndarray) -> float:
    return float(img[20:, :].mean())


def index_of(img: np.ndarray, side: int) -> int:
    return round((level(img) - 20 - 100 * side) / 8)


def write_video(path: Path, frames: list[np.ndarray], fps: float = 30.0) -> Path:
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened(), "this OpenCV build cannot write MJPG .avi"
    for f in frames:
        vw.write(f)
    vw.release()
    return path


@pytest.fixture
def image_dirs(tmp_path):
    left, right = tmp_path / "left", tmp_path / "right"
    left.mkdir(), right.mkdir()
    for i in range(11):  # names that sort wrongly as text: f2 < f10 only in natural order
        cv2.imwrite(str(left / f"f{i}.png"), pattern(i, 0)[:, :, 0])
        cv2.imwrite(str(right / f"f{i}.png"), pattern(i, 1)[:, :, 0])
    return left, right


@pytest.fixture(scope="module")
def videos(tmp_path_factory):
    d = tmp_path_factory.mktemp("videos")
    n = 12
    return {
        "left": write_video(d / "left.avi", [pattern(i, 0) for i in range(n)]),
        "right": write_video(d / "right.avi", [pattern(i, 1) for i in range(n)]),
        "sbs": write_video(d / "sbs.avi", [np.hstack([pattern(i, 0), pattern(i, 1)]) for i in range(n)]),
        "small": write_video(d / "small.avi", [pattern(i, 1, W // 2, H // 2) for i in range(n)]),
        "n": n,
    }


def source(ctx=None, opener=None, **kw):
    return open_source(CaptureSettings(**kw), ctx or SourceContext(), opener)


def drain(src, limit: int = 1000) -> list:
    out = []
    while len(out) < limit and (p := src.read()) is not None:
        out.append(p)
    return out


# --- images --------------------------------------------------------------------------------------

def test_images_paired_by_natural_sort_then_end_of_stream(image_dirs):
    left, right = image_dirs
    src = source(source="images", images_left=str(left), images_right=str(right / "*.png"), rate_hz=50)
    assert src.period_s == pytest.approx(0.02)
    pairs = drain(src)
    assert len(pairs) == 11 and src.ended and src.read() is None
    for i, p in enumerate(pairs):
        assert p.left.shape == (H, W) and p.left.dtype == np.uint8
        assert level(p.left) == pytest.approx(20 + 8 * i) and level(p.right) == pytest.approx(120 + 8 * i)


def test_images_loop_and_max_rate(image_dirs):
    left, right = image_dirs
    src = source(source="images", images_left=str(left), images_right=str(right), loop=True, pace="max")
    assert src.period_s == 0
    pairs = drain(src, 25)
    assert len(pairs) == 25 and not src.ended
    assert [index_of(p.left, 0) for p in pairs[10:13]] == [10, 0, 1]


def test_images_count_mismatch_names_the_unpaired_file(image_dirs):
    left, right = image_dirs
    (right / "f10.png").unlink()
    with pytest.raises(SourceError, match=r"11 left images .* 10 right images .*f10\.png"):
        source(source="images", images_left=str(left), images_right=str(right))


def test_images_missing_folder_and_same_files(image_dirs, tmp_path):
    left, _ = image_dirs
    with pytest.raises(SourceError, match="no such file or folder"):
        source(source="images", images_left=str(tmp_path / "nope"), images_right=str(left))
    with pytest.raises(SourceError, match="no file matches"):
        source(source="images", images_left=str(left / "*.jpg"), images_right=str(left))
    with pytest.raises(SourceError, match="both left and right"):
        source(source="images", images_left=str(left), images_right=str(left / "*.png"))


def test_images_size_mismatch_names_both_files(image_dirs):
    left, right = image_dirs
    cv2.imwrite(str(right / "f0.png"), np.zeros((H, W + 2), np.uint8))
    with pytest.raises(SourceError,
                       match=rf"left/f0\.png is {W}x{H} grey but its partner .*right/f0\.png is {W + 2}x{H} grey"):
        source(source="images", images_left=str(left), images_right=str(right))


def test_images_unreadable_file_mid_stream_is_named_and_skipped(image_dirs):
    left, right = image_dirs
    (right / "f3.png").write_bytes(b"not a png")
    cv2.imwrite(str(left / "f5.png"), np.zeros((H // 2, W), np.uint8))
    cv2.imwrite(str(right / "f5.png"), np.zeros((H // 2, W), np.uint8))
    cv2.imwrite(str(left / "f7.png"), np.zeros((H, W + 4), np.uint8))
    src = source(source="images", images_left=str(left), images_right=str(right))
    got, errors = [], []
    while not src.ended:
        try:
            p = src.read()
        except SourceError as e:
            errors.append(str(e))
            continue
        if p is not None:
            got.append(index_of(p.left, 0))
    assert got == [0, 1, 2, 4, 6, 8, 9, 10]
    assert "right/f3.png: not an image file OpenCV can decode" in errors[0]
    assert "left/f5.png and" in errors[1] and f"are {W}x{H // 2} grey, the earlier pairs {W}x{H} grey" in errors[1]
    assert f"left/f7.png is {W + 4}x{H} grey but its partner" in errors[2]


# --- video ---------------------------------------------------------------------------------------

def test_video_two_files_in_step_at_file_rate_then_end(videos):
    src = source(source="video", video_left=str(videos["left"]), video_right=str(videos["right"]))
    assert src.period_s == pytest.approx(1 / 30)
    pairs = drain(src)
    assert len(pairs) == videos["n"] and src.ended
    assert [index_of(p.left, 0) for p in pairs] == list(range(videos["n"]))
    assert [index_of(p.right, 1) for p in pairs] == list(range(videos["n"]))
    assert pairs[3].t_s == pytest.approx(0.1)


def test_video_side_by_side_split_loop_and_rates(videos):
    src = source(source="video", video_left=str(videos["sbs"]), loop=True, pace="max")
    assert src.period_s == 0
    pairs = drain(src, videos["n"] + 3)
    assert not src.ended and src.ctx.extra["loops"] == 1
    assert pairs[0].left.shape == (H, W, 3) and pairs[0].right.shape == (H, W, 3)
    assert [index_of(p.left, 0) for p in pairs[-4:]] == [videos["n"] - 1, 0, 1, 2]
    assert [index_of(p.right, 1) for p in pairs[-4:]] == [videos["n"] - 1, 0, 1, 2]
    assert source(source="video", video_left=str(videos["sbs"]), pace="rate", rate_hz=5).period_s == 0.2


def test_video_errors_name_the_file(videos, tmp_path):
    with pytest.raises(SourceError, match=rf"{videos['left']} is {W}x{H} BGR but .*small.avi is {W // 2}x{H // 2} BGR"):
        source(source="video", video_left=str(videos["left"]), video_right=str(videos["small"]))
    with pytest.raises(SourceError, match="nope.avi: no such file"):
        source(source="video", video_left=str(tmp_path / "nope.avi"), video_right=str(videos["right"]))
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"\0" * 1000)
    with pytest.raises(SourceError, match="junk.avi"):
        source(source="video", video_left=str(junk))


# --- cameras through the VideoCapture interface ----------------------------------------------------

FAST = dict(camera_retry_s=0.01, camera_retry_max_s=0.04)


def test_cameras_on_video_files_grab_both_then_retrieve(videos):
    calls = []

    class Spy:
        def __init__(self, spec):
            self.cap, self.spec = cv2.VideoCapture(str(spec)), Path(spec).stem

        def __getattr__(self, name):
            attr = getattr(self.cap, name)
            if name in ("grab", "retrieve"):
                return lambda *a: (calls.append((name, self.spec)), attr(*a))[1]
            return attr

    ctx = SourceContext()
    src = source(ctx, Spy, source="cameras", camera_left=str(videos["left"]), camera_right=str(videos["right"]),
                 camera_skew_clock="driver", **FAST)
    assert src.name == "cameras" and src.period_s == 0
    pairs = [src.read() for _ in range(5)]
    assert [index_of(p.left, 0) for p in pairs] == [0, 1, 2, 3, 4]
    assert [index_of(p.right, 1) for p in pairs] == [0, 1, 2, 3, 4]
    assert calls[:4] == [("grab", "left"), ("grab", "right"), ("retrieve", "left"), ("retrieve", "right")]
    # file positions are no kernel timestamps: the grab clock is used; both grabs are microseconds apart
    assert all(0 <= p.extra["skew_ms"] < 20 for p in pairs)
    assert set(ctx.extra) >= {"skew_ms_p50", "skew_ms_max", "dropped_skew", "lost", "reconnects"}
    assert ctx.extra["skew_ms_p50"] < 20 and ctx.extra["dropped_skew"] == 0
    src.close()


def test_sbs_device_is_split(videos):
    src = source(None, lambda spec: cv2.VideoCapture(str(spec)), source="sbs", sbs_device=str(videos["sbs"]))
    p = src.read()
    assert src.name == "sbs" and p.left.shape == (H, W, 3)
    assert index_of(p.left, 0) == 0 and index_of(p.right, 1) == 0
    src.close()
    # without an opener, a file is played as a side-by-side video
    assert source(source="sbs", sbs_device=str(videos["sbs"])).name == "sbs"


class FakeCamera:
    """The cv2.VideoCapture interface over generated frames. `world` decides whether the device
    is plugged in; driver timestamps (CAP_PROP_POS_MSEC, kernel monotonic ms) carry `offset_ms`."""

    def __init__(self, spec, world):
        self.spec, self.world = spec, world
        self.side = 0 if spec == "L" else 1
        self.opened = world.plugged[spec]
        self.k = -1
        self.ts = 0.0

    def isOpened(self):
        return self.opened

    def grab(self):
        if not (self.opened and self.world.plugged[self.spec]):
            return False
        self.world.grabs[self.spec] += 1
        if self.world.on_grab:
            self.world.on_grab(self)
        self.k += 1
        self.ts = time.monotonic_ns() / 1e6 + self.world.offset_ms.get(self.spec, 0.0)
        return True

    def retrieve(self):
        return True, pattern(self.k % 12, self.side)

    def get(self, prop):
        known = {cv2.CAP_PROP_POS_MSEC: self.ts, cv2.CAP_PROP_FRAME_WIDTH: W, cv2.CAP_PROP_FRAME_HEIGHT: H}
        return known.get(prop, 0.0)

    def set(self, prop, value):
        return True

    def release(self):
        self.opened = False


class World:
    def __init__(self):
        self.plugged = {"L": True, "R": True}
        self.grabs = {"L": 0, "R": 0}
        self.opens = 0
        self.offset_ms: dict[str, float] = {}
        self.on_grab = None

    def open(self, spec):
        self.opens += 1
        return FakeCamera(spec, self)


def test_camera_unplugged_mid_run_is_reported_retried_with_backoff_and_resumes():
    world, statuses = World(), []
    ctx = SourceContext(status=statuses.append)
    src = source(ctx, world.open, source="cameras", camera_left="L", camera_right="R", **FAST)
    assert src.read() is not None and src.read() is not None

    unplugged_opens = []

    def unplug_then_replug(cam):  # the right camera vanishes; comes back after 4 failed reopens
        if cam.spec == "R" and world.grabs["R"] == 4:
            world.plugged["R"] = False
            unplugged_opens.append(world.opens)

    world.on_grab = unplug_then_replug
    original_open = world.open

    def opener(spec):
        if not world.plugged["R"] and world.opens - unplugged_opens[0] >= 8:
            world.plugged["R"] = True  # replugged
        return original_open(spec)

    src.opener = opener
    pairs = [src.read() for _ in range(6)]
    assert all(p is not None for p in pairs)
    assert statuses[:3] == ["camera R lost, retrying in 0.01 s", "camera R lost, retrying in 0.02 s",
                            "camera R lost, retrying in 0.04 s"]  # doubling up to camera_retry_max_s
    assert set(statuses[3:-1]) == {"camera R lost, retrying in 0.04 s"} and statuses[-1] == "ok"
    assert ctx.extra["reconnects"] == 1 and ctx.extra["lost"] == 0
    assert src._backoff == src.settings.camera_retry_s  # reset after recovery
    assert world.plugged["R"]


def test_camera_backoff_doubles_and_stop_ends_the_wait():
    world, statuses = World(), []
    ctx = SourceContext(status=statuses.append)
    src = source(ctx, world.open, source="cameras", camera_left="L", camera_right="R",
                 camera_retry_s=0.1, camera_retry_max_s=0.4)
    world.plugged["L"] = False
    waits = []
    real_wait = ctx.stop.wait

    def wait(timeout=None):  # record the backoff; do not really wait; stop after five retries
        waits.append(timeout)
        if len(waits) == 5:
            ctx.stop.set()
        return real_wait(0)

    ctx.stop.wait = wait
    src._pending = None
    assert src.read() is None  # stopped while reconnecting
    assert waits == [0.1, 0.2, 0.4, 0.4, 0.4]
    assert statuses[:3] == ["camera L lost, retrying in 0.1 s", "camera L lost, retrying in 0.2 s",
                            "camera L lost, retrying in 0.4 s"]


def test_camera_pairs_with_too_much_skew_are_dropped_and_counted():
    world, statuses = World(), []
    ctx = SourceContext(status=statuses.append)
    src = source(ctx, world.open, source="cameras", camera_left="L", camera_right="R", camera_max_skew_ms=10)
    assert src.read().extra["skew_ms"] < 10
    world.offset_ms["R"] = 25.0  # right frames 25 ms later by the driver clock
    done = threading.Event()

    def fix_after_twelve(cam):
        if cam.spec == "R" and world.grabs["R"] >= 14:
            world.offset_ms["R"] = 3.0
            done.set()

    world.on_grab = fix_after_twelve
    p = src.read()
    assert done.is_set() and 2 <= p.extra["skew_ms"] < 10
    assert ctx.extra["dropped_skew"] == 12
    assert ctx.extra["skew_ms_max"] >= 25
    assert statuses == ["dropping pairs: left/right skew 25.0 ms > 10 ms", "ok"]


def test_camera_size_mismatch_is_an_error(videos):
    with pytest.raises(SourceError, match=rf"left.avi delivers {W}x{H} but .*small.avi {W // 2}x{H // 2}"):
        source(None, lambda spec: cv2.VideoCapture(str(spec)), source="cameras",
               camera_left=str(videos["left"]), camera_right=str(videos["small"]))


def test_missing_camera_names_it_and_lists_the_devices_present(tmp_path, monkeypatch):
    dev, sys_dir = tmp_path / "dev", tmp_path / "sys"
    dev.mkdir()
    for n in (0, 1, 10):
        (dev / f"video{n}").touch()
        (sys_dir / f"video{n}").mkdir(parents=True)
        (sys_dir / f"video{n}" / "name").write_text(f"Cam {n}\n")
    monkeypatch.setattr(cameras, "DEV_DIR", str(dev))
    monkeypatch.setattr(cameras, "SYS_DIR", str(sys_dir))
    with pytest.raises(SourceError) as e:
        source(source="cameras", camera_left=7, camera_right=0)
    msg = str(e.value)
    assert f"camera {dev}/video7: no such device" in msg
    assert f"video devices present: {dev}/video0 (Cam 0), {dev}/video1 (Cam 1), {dev}/video10 (Cam 10)" in msg
    monkeypatch.setattr(cameras, "DEV_DIR", str(tmp_path / "empty"))
    with pytest.raises(SourceError, match="no video devices present"):
        source(source="sbs", sbs_device=3)


def test_cli_missing_camera_exits_2_with_the_message():
    from helpers import cli, free_port

    r = subprocess.run(cli("run", "capture", "--source", "cameras", "--camera-left", "/dev/video97",
                           "--connect", f"tcp/127.0.0.1:{free_port()}"), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert "camera /dev/video97: no such device;" in r.stderr and "video devices" in r.stderr
    assert "Traceback" not in r.stderr


def test_run_loop_skips_bad_pairs_converts_to_grey_and_idles_at_end(image_dirs):
    """main.run on a real Node object without a Zenoh session (publishers replaced)."""
    from common.node import Node
    from common.zenoh_session import ZenohOptions
    from services.capture.main import run

    left, right = image_dirs
    (left / "f4.png").write_bytes(b"")
    for i in range(11):  # colour files; the service publishes grey
        cv2.imwrite(str(right / f"f{i}.png"), pattern(i, 1))
        if i != 4:
            cv2.imwrite(str(left / f"f{i}.png"), pattern(i, 0))
    ended = threading.Event()

    class TestNode(Node):
        @property
        def status(self):
            return self._status

        @status.setter
        def status(self, v):
            self._status = v
            if v == "end of stream":
                ended.set()

    node = TestNode("capture", ZenohOptions(), "unit", install_signal_handlers=False)
    sent = {"frames_raw": [], "truth": []}

    class Pub:
        def __init__(self, name):
            self.name = name

        def put(self, msg, count=True):
            sent[self.name].append(msg)

    node.publisher = Pub
    settings = CaptureSettings(source="images", images_left=str(left), images_right=str(right), pace="max",
                               grayscale=True, encoding="jpeg", jpeg_quality=95)
    t = threading.Thread(target=run, args=(node, settings))
    t.start()
    try:
        assert ended.wait(30)
    finally:
        node.stop_event.set()
        t.join(10)
    assert not t.is_alive()
    frames = sent["frames_raw"]
    assert [f.seq for f in frames] == list(range(10)) and node.errors == 1 and not sent["truth"]
    from common import codec

    for f, i in zip(frames, [0, 1, 2, 3, 5, 6, 7, 8, 9, 10]):
        assert f.left.channels == 1 and f.left.encoding == "jpeg" and f.source == "images"
        a = codec.array_from_image(f.left)
        assert abs(level(a) - (20 + 8 * i)) < 2
    assert len({f.stamp_ns for f in frames}) == 10


def test_bench_sources_measures_every_file_source():
    from bench.sources import bench_sources

    r = bench_sources(frames=4, width=W, height=H)
    assert set(r["sources"]) == {"images-png", "images-jpeg", "video", "video-sbs", "cameras-on-video"}
    assert all(m["pairs"] == 4 and m["fps"] > 0 for m in r["sources"].values()), r


# --- the real process over Zenoh -----------------------------------------------------------------

@pytest.mark.system
def test_run_capture_images_publishes_pairs_over_zenoh_then_idles_at_end_of_stream(image_dirs):
    """Two real capture processes on one router: a looping one whose pairs are checked against
    the files, and one that reaches the end of its 11 pairs and must stay up, idle, then exit 0."""
    from helpers import Collector, cli, free_port

    from common import codec
    from common.keys import topic
    from common.messages import ServiceStats, StereoFrame
    from common.zenoh_session import ZenohOptions, open_session

    left, right = image_dirs
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs: dict[str, subprocess.Popen] = {}

    def capture(rid: str, *more: str) -> subprocess.Popen:
        return subprocess.Popen(cli("run", "capture", "--connect", endpoint, "--robot-id", rid, "--source", "images",
                                    "--images-left", str(left), "--images-right", str(right / "*.png"), *more),
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    procs["router"] = subprocess.Popen(cli("run", "router", "--listen", endpoint),
                                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        frames, stats = Collector(StereoFrame), Collector(ServiceStats)
        opts = ZenohOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"])
        with open_session(opts) as s:
            s.declare_subscriber(topic("frames_raw").key("looping"), frames)
            s.declare_subscriber(topic("stats").pattern("ending"), stats)
            procs["looping"] = capture("looping", "--loop", "true", "--rate-hz", "30", "--encoding", "png")
            procs["ending"] = capture("ending", "--rate-hz", "50")
            # a subscriber may miss the first pairs while routes form; a loop gives it every file
            assert frames.wait_for(lambda xs: len({m.seq % 11 for m in xs}) == 11, 60), \
                procs["looping"].stderr.read() if procs["looping"].poll() is not None else len(frames.items)
            for m in frames.items:
                assert m.source == "images" and m.left.encoding == "png" and (m.left.width, m.left.height) == (W, H)
                a, b = codec.array_from_image(m.left), codec.array_from_image(m.right)
                assert a.shape == (H, W) and index_of(a, 0) == m.seq % 11 and index_of(b, 1) == m.seq % 11
            seqs = [m.seq for m in frames.items]
            assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs), "one message per pair, in order"
            assert stats.wait_for(lambda xs: any(x.status == "end of stream" for x in xs), 60), \
                procs["ending"].stderr.read() if procs["ending"].poll() is not None else stats.items
            done = next(x for x in stats.items if x.status == "end of stream")
            assert done.published == 11 and done.errors == 0
        for name in ("looping", "ending"):
            assert procs[name].poll() is None, f"{name} capture must stay up"
            procs[name].terminate()
            assert procs[name].wait(10) == 0, procs[name].stderr.read()
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()


def test_a_looped_synthetic_preload_never_repeats_a_picture_bit_for_bit():
    """`--preload N` loops N rendered pairs. A stage that, under load, sees only every N-th pair (the
    bench offering 40-100 pairs/s) saw one picture again and again, and rectify's frozen-camera check
    said camera-frozen on a live source. Each lap is stamped into the pictures: no two pairs are equal,
    and the check, fed every 4th pair of a 4-pair loop for 2 s, never says frozen."""
    from cores.calibration.check import PairChecks
    from services.capture.sources import SyntheticSource

    src = SyntheticSource("two-boxes", "lifecam-studio", 30.0, preload=4)
    pairs = [src.read() for _ in range(48)]
    assert not any(np.array_equal(pairs[0].left, pairs[k].left) for k in range(4, 48, 4))
    assert np.count_nonzero(pairs[0].left != pairs[4].left) <= 4  # four bytes of the top-left corner
    checks = PairChecks(frozen_after_s=0.5)
    said = [checks.pictures(p.left, p.right, t_s=k / 6.0)[0] for k, p in enumerate(pairs[::4])]
    assert not any(said), said
