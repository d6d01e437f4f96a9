"""capture's settings: every source's, in one model (see CaptureSettings)."""
from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field

from common.codec import MIN_JPEG_QUALITY
from common.settings import ServiceSettings


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
    jpeg_quality: int = Field(90, ge=MIN_JPEG_QUALITY, le=100, description="jpeg quality (from 85: common/codec.py)")
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
    mcap_speed: float = Field(1.0, gt=0, le=1000,
                              description="mcap: playback speed with --pace auto (2: twice as fast)")
    mcap_step: bool = Field(False, description="mcap: start paused; one pair per `ballbot-vision replay step`")
