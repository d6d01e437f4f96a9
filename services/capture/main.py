"""capture: a stereo source -> frames_raw (+ truth for the synthetic world).

Sources (`--source`): synthetic (default), cameras, sbs, video, images, ros2, mcap (a recording); see
sources.py, cameras.py, files.py, ros2.py and mcap_source.py. Problems found at start (a missing
camera, an unreadable first image, left/right count or size mismatch) raise SourceError: `run
capture` prints it and exits 2. A pair that cannot be read later is logged, counted in `errors` and
skipped. When a file source ends (without --loop) the service reports status "end of stream" and
stays up, idle, until stopped (exit 0), so the supervisor never restarts it in a loop. A lost
camera is reported in the status and reconnected with backoff while the other services keep running.
"""
from __future__ import annotations

import os
import time

import cv2

from common import codec
from common.errors import SourceError
from common.messages import GroundTruth, StereoFrame, TruthObstacle
from common.node import Node
from services.capture.settings import CaptureSettings
from services.capture.sources import CapturedPair, SourceContext, SyntheticSource

# replay (--source mcap) follows rectify's stats and tokens and takes replay commands
SUBSCRIBES = ["replay_control", "stats", "alive"]
PUBLISHES = ["frames_raw", "truth", "calibration"]  # calibration: a replay's or a ROS camera's, signed


def preflight(s: CaptureSettings) -> None:
    """Before the service is up (cli.cmd_run): the optional dependency of the chosen source."""
    from common.errors import require

    if s.source == "mcap":
        require(("mcap",), "record", "capture --source mcap")
    elif s.source == "ros2":
        require(("rosbags", "xxhash"), "ros2", "capture --source ros2")


def open_source(s: CaptureSettings, ctx: SourceContext | None = None, opener=None):
    """The source the settings name. `opener` replaces cv2.VideoCapture for cameras/sbs (tests)."""
    ctx = ctx or SourceContext()
    if s.source == "ros2":
        from services.capture.ros2 import Ros2Source

        return Ros2Source(s, ctx)
    if s.source == "synthetic":
        src = SyntheticSource(s.scenario, s.calibration, s.rate_hz, s.seed, s.noise_sigma, s.preload)
        if s.pace == "max":
            src.period_s = 0.0
        return src
    if s.source == "images":
        from services.capture.files import ImageSource

        return ImageSource(s.images_left, s.images_right, s.rate_hz, s.loop, max_rate=s.pace == "max", ctx=ctx)
    if s.source == "mcap":
        from services.capture.mcap_source import McapSource

        return McapSource(s.mcap, s.mcap_speed, s.pace, s.rate_hz, s.loop, s.mcap_step, ctx)
    if s.source == "video":
        from services.capture.files import VideoSource

        return VideoSource(s.video_left, s.video_right, {"auto": "file"}.get(s.pace, s.pace), s.rate_hz, s.loop, ctx)
    from services.capture.cameras import CameraSource, device_path

    if s.source == "sbs":
        path = device_path(s.sbs_device)
        if opener is None and os.path.isfile(path):  # a side-by-side video file, not a device
            from services.capture.files import VideoSource

            return VideoSource(path, "", {"auto": "file"}.get(s.pace, s.pace), s.rate_hz, s.loop, ctx, name="sbs")
        return CameraSource([s.sbs_device], s, ctx, opener, sbs=True)
    return CameraSource([s.camera_left, s.camera_right], s, ctx, opener)


def truth_message(robot_id: str, seq: int, stamp_ns: int, scenario: str, truth: list) -> GroundTruth:
    def v3(a) -> tuple[float, float, float]:
        return tuple(float(x) for x in a)  # type: ignore[return-value]

    return GroundTruth(robot_id=robot_id, seq=seq, stamp_ns=stamp_ns, scenario=scenario, obstacles=[
        TruthObstacle(name=o.name, kind=o.kind, center_m=v3(o.center_m), size_m=v3(o.size_m),
                      visible_centroid_m=v3(o.visible_centroid_m), nearest_m=float(o.nearest_m),
                      visible_px=int(o.visible_px),
                      bbox_px=None if o.bbox_px is None else tuple(int(x) for x in o.bbox_px),
                      velocity_mps=v3(o.velocity_mps)) for o in truth])


def _grey(a):
    return cv2.cvtColor(a, cv2.COLOR_BGR2GRAY) if a.ndim == 3 else a


def run(node: Node, settings: CaptureSettings, source=None) -> None:
    """Publish one StereoFrame per pair until stopped. `source` replaces the one the settings name."""

    def set_status(text: str) -> None:
        node.status = text

    ctx = SourceContext(stop=node.stop_event, status=set_status, extra=node.extra, node=node)
    source = source or open_source(settings, ctx)
    if source.name == "mcap":
        from services.capture.mcap_source import connect_replay

        connect_replay(node, source)
    frames = node.publisher("frames_raw")
    truth = node.publisher("truth")
    grey = settings.grayscale and source.name != "synthetic"
    seq = 0
    next_t = time.monotonic()
    try:
        while node.running:
            period = source.period_s
            try:
                pair: CapturedPair | None = source.read()
            except SourceError as e:  # one unreadable pair: name the file, count it, go on
                node.errors += 1
                node.warn("source", f"skipped a pair: {e}")
                pair = None
            else:
                if pair is None:
                    if source.ended:
                        node.status = "end of stream"
                        node.warn("end", f"{source.name}: end of stream; idle until stopped")
                        node.stop_event.wait()
                    break
            if pair is not None:
                with node.processing():
                    stamp = pair.stamp_ns or node.clock.wall_ns()
                    left, right = (_grey(pair.left), _grey(pair.right)) if grey else (pair.left, pair.right)
                    msg = StereoFrame(robot_id=node.robot_id, seq=seq, stamp_ns=stamp,
                                      left=codec.image_from_array(left, settings.encoding, settings.jpeg_quality),
                                      right=codec.image_from_array(right, settings.encoding, settings.jpeg_quality),
                                      source=source.name)
                    frames.put(msg)
                    if pair.truth is not None:
                        truth.put(truth_message(node.robot_id, seq, stamp, getattr(source, "scenario", ""),
                                                pair.truth), count=False)
                    seq += 1
            if period <= 0:  # the source paces itself (cameras) or as fast as possible
                continue
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:  # fell behind (slow renderer): do not burst to catch up
                next_t = time.monotonic()
            elif delay > 0:
                node.stop_event.wait(delay)
    finally:
        source.close()
