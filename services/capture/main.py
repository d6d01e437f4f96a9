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
from typing import Annotated, Any, Literal

import cv2
from pydantic import BeforeValidator, Field

from ...common import codec
from ...common.errors import SourceError
from ...common.messages import GroundTruth, StereoFrame, TruthObstacle
from ...common.node import Node
from ...common.settings import ServiceSettings
from .sources import CapturedPair, SourceContext, SyntheticSource

SUBSCRIBES: list[str] = []
PUBLISHES = ["frames_raw", "truth"]


def _device(v: Any) -> Any:
    """A camera given as text: all digits is an index, in decimal ("010" is 10), else a path."""
    if isinstance(v, str) and v.strip().isdigit():
        return int(v.strip(), 10)
    return v


# A V4L2 device: an index (0 -> /dev/video0), a path (/dev/video0, /dev/v4l/by-id/...) or a file.
Device = Annotated[int | str, BeforeValidator(_device)]


class CaptureSettings(ServiceSettings):
    """capture's settings: the one model that `run capture` (flags, environment, config section) and
    every source's core read (CameraSource takes it as it is); defaults live here only."""

    section = "capture"
    source: Literal["synthetic", "cameras", "sbs", "video", "images", "ros2", "mcap"] = Field(
        "synthetic", description="where pairs come from: synthetic, cameras, sbs, video, images, ros2, "
                                 "mcap (a recording)")
    # --- every source
    rate_hz: float = Field(30.0, gt=0, le=1000, description="pairs per second (synthetic, images; video with "
                                                            "--pace rate or when the file states no rate)")
    pace: Literal["auto", "rate", "max"] = Field(
        "auto", description="file sources: auto (video: the file's fps; images: rate-hz; mcap: as recorded, "
                            "times mcap-speed), rate (rate-hz), "
                            "max (as fast as they decode); cameras are always paced by the devices")
    loop: bool = Field(False, description="video, images: start again at the end instead of ending the stream")
    grayscale: bool = Field(False, description="cameras, sbs, video, images: publish 8-bit grey instead of BGR")
    encoding: Literal["raw", "png", "jpeg"] = Field("raw", description="image encoding on the wire")
    jpeg_quality: int = Field(90, ge=1, le=100, description="jpeg quality")
    # --- synthetic
    scenario: str = Field("two-boxes", description="synthetic: built-in scenario name or YAML file")
    calibration: str = Field("lifecam-studio", description="synthetic: the rig rendered for (YAML or profile)")
    seed: int = Field(0, description="synthetic: random seed (textures, noise)")
    noise_sigma: float = Field(1.5, ge=0, le=50, description="synthetic: sensor noise, grey levels")
    preload: int = Field(0, ge=0, le=10000, description="synthetic: render this many pairs first, then loop them")
    # --- cameras / sbs (V4L2 devices)
    camera_left: Device = Field(0, description="cameras: left device, index or path (/dev/video0, /dev/v4l/by-id/...)")
    camera_right: Device = Field(2, description="cameras: right device, index or path (a UVC camera has two "
                                                "nodes, capture and metadata: two cameras are often 0 and 2)")
    camera_width: int = Field(640, ge=0, le=16384, description="cameras, sbs: frame width per device (sbs: the "
                                                               "double-width frame); 0 keeps the driver's")
    camera_height: int = Field(480, ge=0, le=16384, description="cameras, sbs: frame height; 0 keeps the driver's")
    camera_fps: float = Field(30.0, ge=0, le=1000,
                              description="cameras, sbs: requested frame rate; 0 keeps the driver's")
    camera_fourcc: Literal["MJPG", "YUYV", "default"] = Field(
        "MJPG", description="cameras, sbs: pixel format (MJPG lets two cameras share one USB 2 bus); "
                            "default keeps the driver's")
    camera_exposure: float | None = Field(None, description="cameras, sbs: manual exposure in driver units "
                                                            "(uvcvideo: 100 us); unset: automatic")
    camera_buffers: int = Field(2, ge=0, le=32,
                                description="cameras, sbs: driver buffers (few: low latency); 0 keeps the driver's")
    camera_max_skew_ms: float = Field(20.0, gt=0, description="cameras: drop pairs whose left/right capture times "
                                                              "differ by more than this")
    camera_skew_clock: Literal["driver", "grab"] = Field(
        "driver", description="cameras: skew from V4L2 buffer timestamps (driver, when given) or grab() return times")
    camera_retry_s: float = Field(0.5, gt=0, le=60, description="cameras, sbs: first reconnect delay after a "
                                                                "camera is lost; doubles up to camera-retry-max-s")
    camera_retry_max_s: float = Field(8.0, gt=0, le=600, description="cameras, sbs: longest reconnect delay")
    camera_timeout_s: float = Field(2.0, gt=0, le=60, description="cameras, sbs: a device silent this long is lost")
    # --- sbs
    sbs_device: Device = Field(0, description="sbs: device (index or path) or video file with side-by-side frames")
    # --- video
    video_left: str = Field("", description="video: left video file, or a side-by-side video when video-right is empty")
    video_right: str = Field("", description="video: right video file")
    # --- images
    images_left: str = Field("", description="images: left folder or glob pattern (paired with right by sorted name)")
    images_right: str = Field("", description="images: right folder or glob pattern")
    # --- ros2 (a ROS 2 camera driver on rmw_zenoh, same Zenoh network)
    ros2_left: str = Field("", description="ros2: left image topic (sensor_msgs/Image, or .../compressed)")
    ros2_right: str = Field("", description="ros2: right image topic")
    ros2_left_info: str = Field("", description="ros2: left CameraInfo topic (empty: camera_info beside the image)")
    ros2_right_info: str = Field("", description="ros2: right CameraInfo topic (empty: camera_info beside the image)")
    ros2_domain_id: int = Field(0, ge=0, le=232, description="ros2: ROS_DOMAIN_ID")
    ros2_distro: Literal["humble", "jazzy"] = Field("jazzy", description="ros2: the driver's ROS distro (graph tokens)")
    ros2_namespace: str = Field("/", description="ros2: namespace of this subscriber node (relative topics too)")
    ros2_node_name: str = Field("ballbot_vision_capture", description="ros2: node name in the ROS graph")
    ros2_max_skew_ms: float = Field(5.0, ge=0, le=1000, description="ros2: left/right header stamps differ by "
                                                                    "at most this to pair")
    ros2_calibration: Literal["camera_info", "none"] = Field(
        "camera_info", description="ros2: camera_info: send rectify the calibration the CameraInfo pair gives; "
                                   "none: rectify keeps its own --calibration")
    ros2_rectified: bool = Field(False, description="ros2: the topics carry rectified images (image_rect): "
                                                    "only the projection matrices count")
    # --- mcap (replay a recording; see mcap_source.py)
    mcap: str = Field("", description="mcap: the recording to replay (ballbot-vision record, mcap from-images)")
    mcap_speed: float = Field(1.0, gt=0, le=1000, description="mcap: playback speed with --pace auto (2: twice as fast)")
    mcap_step: bool = Field(False, description="mcap: start paused; one pair per `ballbot-vision replay step`")



def preflight(s: CaptureSettings) -> None:
    """Before the service is up (cli.cmd_run): the optional dependency of the chosen source."""
    from ...common.errors import require

    if s.source == "mcap":
        require(("mcap",), "record", "capture --source mcap")
    elif s.source == "ros2":
        require(("rosbags", "xxhash"), "ros2", "capture --source ros2")


def open_source(s: CaptureSettings, ctx: SourceContext | None = None, opener=None):
    """The source the settings name. `opener` replaces cv2.VideoCapture for cameras/sbs (tests)."""
    ctx = ctx or SourceContext()
    if s.source == "ros2":
        from .ros2 import Ros2Source

        return Ros2Source(s, ctx)
    if s.source == "synthetic":
        src = SyntheticSource(s.scenario, s.calibration, s.rate_hz, s.seed, s.noise_sigma, s.preload)
        if s.pace == "max":
            src.period_s = 0.0
        return src
    if s.source == "images":
        from .files import ImageSource

        return ImageSource(s.images_left, s.images_right, s.rate_hz, s.loop, max_rate=s.pace == "max", ctx=ctx)
    if s.source == "mcap":
        from .mcap_source import McapSource

        return McapSource(s.mcap, s.mcap_speed, s.pace, s.rate_hz, s.loop, s.mcap_step, ctx)
    if s.source == "video":
        from .files import VideoSource

        return VideoSource(s.video_left, s.video_right, {"auto": "file"}.get(s.pace, s.pace), s.rate_hz, s.loop, ctx)
    from .cameras import CameraSource, device_path

    if s.source == "sbs":
        path = device_path(s.sbs_device)
        if opener is None and os.path.isfile(path):  # a side-by-side video file, not a device
            from .files import VideoSource

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
        from .mcap_source import connect_replay

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
