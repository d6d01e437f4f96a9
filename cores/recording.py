"""The recording format: which MCAP topics hold what, a writer and a converter from pipeline
messages to recorded messages (the reader that gives stereo pairs back is recording_reader.py).
Pure: no Zenoh.

Layout 2 (metadata `ballbot.layout` = "2"): the foxglove.* channels are Foxglove's own protobuf
schemas and messages, made by Foxglove's SDK (cores/foxglove.py), so images are their JPEG or PNG
bytes as they are; the ballbot.* channels are JSON with the JSON Schema of our pydantic models.
Layout 1 (before: every channel JSON, images base64 inside it, no `layout` entry) is still read.

Topics (schema; log time = the pair's capture stamp, so a frame, its disparity and its boxes line
up in Foxglove; MCAP `sequence` = the capture seq):

| topic | schema | what |
|---|---|---|
| /frames/rectified/left, .../right | foxglove.CompressedImage | the rectified pairs: what the pipeline matched (1) |
| /frames/rectified/camera_info | foxglove.CameraCalibration | the rectified left camera (for Foxglove's 3D boxes) |
| /frames/rectified/calibration | ballbot.Calibration | the rectified rig as a `rectified: true` calibration (2) |
| /frames/raw/left, /frames/raw/right | foxglove.CompressedImage | the pairs as captured, only when asked (3) |
| /disparity/color | foxglove.CompressedImage | disparity in colour (near = warm, no measurement = black) |
| /obstacles | ballbot.ObstacleList (JSON Schema) | the public obstacle list, as published |
| /obstacles/boxes | foxglove.ImageAnnotations | each obstacle's box, id and distance on the rectified left image |
| /obstacles/scene | foxglove.SceneUpdate | 3D boxes, camera frame |
| /freespace, /freespace/grid | ballbot.FreeSpace, foxglove.Grid | the occupancy grid (base frame) |
| /tf | foxglove.FrameTransform | base -> camera from the segmenter's ground estimate |
| /truth, /truth/boxes | ballbot.GroundTruth, foxglove.ImageAnnotations | the synthetic scene's truth |
| /stats | ballbot.ServiceStats | every service's stats, once a second each |
| /calibration | ballbot.Calibration | the calibration YAML the raw pairs need (4) |

(1) what replay publishes. (2) replay hands it to rectify, which passes the pairs through.
(3) `record --raw true`; `mcap from-images` writes these. (4) replay of raw pairs hands it to rectify.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np
from pydantic import BaseModel

from common import codec
from common.errors import BallbotError, path_error
from common.messages import (
    CameraModel,
    DisparityMap,
    FreeSpace,
    GroundTruth,
    Image,
    ObstacleList,
    ServiceStats,
    StereoFrame,
)
from cores import camera, foxglove

log = logging.getLogger("ballbot.recording")

# What this writer writes and the newest this reader reads (metadata "ballbot", key "layout").
LAYOUT = 2

RAW_LEFT, RAW_RIGHT = "/frames/raw/left", "/frames/raw/right"
RECT_LEFT, RECT_RIGHT = "/frames/rectified/left", "/frames/rectified/right"
CAMERA_INFO = "/frames/rectified/camera_info"
RECT_CALIBRATION = "/frames/rectified/calibration"
DISPARITY_COLOR = "/disparity/color"
OBSTACLES, OBSTACLE_BOXES, OBSTACLE_SCENE = "/obstacles", "/obstacles/boxes", "/obstacles/scene"
FREESPACE, FREESPACE_GRID = "/freespace", "/freespace/grid"
TF = "/tf"
TRUTH, TRUTH_BOXES = "/truth", "/truth/boxes"
STATS = "/stats"
CALIBRATION = "/calibration"

_CALIBRATION_SCHEMA = {"title": "ballbot.Calibration", "type": "object",
                       "description": "a calibration file's text (see README: calibration files)",
                       "properties": {"yaml": {"type": "string"}, "source": {"type": "string"}},
                       "required": ["yaml"]}

# topic -> schema name
TOPIC_SCHEMAS: dict[str, str] = {
    RAW_LEFT: "foxglove.CompressedImage", RAW_RIGHT: "foxglove.CompressedImage",
    RECT_LEFT: "foxglove.CompressedImage", RECT_RIGHT: "foxglove.CompressedImage",
    CAMERA_INFO: "foxglove.CameraCalibration", RECT_CALIBRATION: "ballbot.Calibration",
    DISPARITY_COLOR: "foxglove.CompressedImage",
    OBSTACLES: "ballbot.ObstacleList", OBSTACLE_BOXES: "foxglove.ImageAnnotations",
    OBSTACLE_SCENE: "foxglove.SceneUpdate", FREESPACE: "ballbot.FreeSpace", FREESPACE_GRID: "foxglove.Grid",
    TF: "foxglove.FrameTransform", TRUTH: "ballbot.GroundTruth", TRUTH_BOXES: "foxglove.ImageAnnotations",
    STATS: "ballbot.ServiceStats", CALIBRATION: "ballbot.Calibration",
}


def schema_document(name: str) -> dict:
    """The JSON Schema of one of our own (ballbot.*) channels."""
    if name == "ballbot.Calibration":
        return _CALIBRATION_SCHEMA
    models: dict[str, type[BaseModel]] = {"ballbot.ObstacleList": ObstacleList, "ballbot.FreeSpace": FreeSpace,
                                          "ballbot.GroundTruth": GroundTruth, "ballbot.ServiceStats": ServiceStats}
    model = models[name]
    doc = model.model_json_schema()
    doc["title"] = name
    return doc


class RecordingError(BallbotError):
    """A recording that cannot be written or read; the message names the file and the problem."""


# -- writing -------------------------------------------------------------------------------------

class RecordingWriter:
    """An MCAP file being written. `write()` may be called from any thread. Chunks go to disk as
    they fill, so a process killed outright leaves every finished chunk readable; close() (on
    Ctrl-C/SIGTERM too) writes the index and summary that make the file complete."""

    def __init__(self, path: str | Path, compression: str = "zstd", chunk_size: int = 4 << 20,
                 metadata: dict[str, str] | None = None):
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        try:
            self._file: IO[bytes] = open(self.path, "wb")
        except OSError as e:
            raise RecordingError(f"{path}: cannot write the recording ({path_error(e)})") from None
        kinds = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in kinds:
            raise RecordingError(f"compression {compression!r}: expected one of {', '.join(kinds)}")
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=kinds[compression])
        self._writer.start(profile="", library="ballbot-vision")
        self._lock = threading.Lock()
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self.bytes = 0
        self.closed = False
        self._writer.add_metadata("ballbot", {"layout": str(LAYOUT),
                                              **{k: str(v) for k, v in (metadata or {}).items()}})

    def _channel(self, topic: str) -> int:
        if topic not in self._channels:
            name = TOPIC_SCHEMAS[topic]
            sdk_type = foxglove.TYPES.get(name)
            if name not in self._schemas:
                if sdk_type is not None:  # the SDK's own schema: protobuf, a FileDescriptorSet
                    schema = sdk_type.get_schema()
                    self._schemas[name] = self._writer.register_schema(name=schema.name, encoding=schema.encoding,
                                                                       data=bytes(schema.data))
                else:
                    self._schemas[name] = self._writer.register_schema(
                        name=name, encoding="jsonschema", data=json.dumps(schema_document(name)).encode())
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="protobuf" if sdk_type is not None else "json",
                schema_id=self._schemas[name])
        return self._channels[topic]

    def write(self, topic: str, doc: Any, log_time_ns: int, sequence: int = 0,
              publish_time_ns: int | None = None) -> None:
        """doc: an SDK message (foxglove.* topics), or a JSON text or mapping (ballbot.* topics)."""
        if isinstance(doc, str):
            data = doc.encode()
        elif isinstance(doc, dict):
            data = json.dumps(doc, separators=(",", ":")).encode()
        else:
            data = doc.encode()
        with self._lock:
            if self.closed:
                return
            self._writer.add_message(self._channel(topic), log_time=int(log_time_ns), data=data,
                                     publish_time=int(publish_time_ns if publish_time_ns is not None else log_time_ns),
                                     sequence=int(sequence) & 0xFFFFFFFF)
            self.counts[topic] = self.counts.get(topic, 0) + 1
            self.bytes += len(data)

    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self.closed = True
            try:
                self._writer.finish()
            finally:
                self._file.close()


# -- converting pipeline messages ----------------------------------------------------------------

def compress_image(img: Image, fmt: str, jpeg_quality: int = 90) -> tuple[bytes, str]:
    """An Image payload -> (jpeg or png bytes, format). A payload already in `fmt` (or any
    compressed payload when fmt is 'keep') passes through untouched."""
    if img.encoding != "raw" and fmt in (img.encoding, "keep"):
        return img.data, img.encoding
    a = codec.array_from_image(img)
    if a.dtype != np.uint8:
        raise RecordingError(f"cannot record a {img.dtype} image as {fmt}")
    fmt = "jpeg" if fmt == "keep" else fmt
    return encode_array(a, fmt, jpeg_quality), fmt


def encode_array(a: np.ndarray, fmt: str, jpeg_quality: int = 90) -> bytes:
    """(H, W) grey or (H, W, 3) BGR uint8 -> jpeg or png bytes. JPEGs get optimised Huffman tables:
    the same pixels in 4-5 % fewer bytes, for about 1 ms more per 640x480 image."""
    if fmt == "jpeg":
        ok, buf = cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality), cv2.IMWRITE_JPEG_OPTIMIZE, 1])
    elif fmt == "png":
        ok, buf = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    else:
        raise RecordingError(f"image format {fmt!r}: expected jpeg or png")
    return buf.tobytes()


def _disparity_colours() -> np.ndarray:
    """(256, 1, 3) uint8 BGR: black, then TURBO over 1..255."""
    table = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(256, 1), cv2.COLORMAP_TURBO)
    table[0] = 0
    return table


_DISPARITY_COLOURS = _disparity_colours()


def colorize_disparity(msg: DisparityMap) -> np.ndarray:
    """A disparity message -> (H, W, 3) uint8 BGR: TURBO over the searched range (near = warm),
    pixels without a measurement black."""
    raw = codec.array_from_image(msg.image, "disparity")
    # OpenCV passes on one channel instead of float numpy arithmetic: valid disparities -> 1..255,
    # no measurement -> 0, which the colour table maps to black
    alpha = 254.0 / (max(msg.num_disparities, 1) * msg.scale)
    scaled = cv2.convertScaleAbs(raw, alpha=alpha, beta=1.0 - msg.min_disparity * msg.scale * alpha)
    scaled[raw == msg.invalid_value] = 0
    out = cv2.applyColorMap(scaled, _DISPARITY_COLOURS)
    return out


@dataclass
class Recorded:
    """One message ready for the writer."""

    topic: str
    doc: Any  # an SDK message (foxglove.*), or JSON text or a mapping (ballbot.*)
    log_time_ns: int
    sequence: int = 0


@dataclass
class RecordOptions:
    image_format: str = "jpeg"  # jpeg, png or keep (as on the wire; raw payloads become jpeg)
    jpeg_quality: int = 90  # RecordSettings: from common.codec.MIN_JPEG_QUALITY
    raw: bool = False  # the rectified pairs are what the pipeline matched; raw ones only when asked
    rectified: bool = True
    disparity: bool = True


class Converter:
    """Pipeline messages -> recorded messages (pure; one instance per recording, called from
    several threads: it keeps only small state under a lock)."""

    CAMERA_INFO_EVERY_NS = 1_000_000_000

    def __init__(self, options: RecordOptions | None = None):
        self.options = options or RecordOptions()
        self._lock = threading.Lock()
        self._camera_info_ns: dict[str, int] = {}

    def _image(self, img: Image) -> tuple[bytes, str]:
        return compress_image(img, self.options.image_format, self.options.jpeg_quality)

    def _camera_info_due(self, cam: CameraModel, stamp_ns: int) -> bool:
        key = cam.model_dump_json()
        with self._lock:
            last = self._camera_info_ns.get(key)
            if last is not None and 0 <= stamp_ns - last < self.CAMERA_INFO_EVERY_NS:
                return False
            self._camera_info_ns = {key: stamp_ns}
            return True

    def frame(self, msg: StereoFrame) -> list[Recorded]:
        rectified = msg.camera is not None
        if not (self.options.rectified if rectified else self.options.raw):
            return []
        lt, rt = (RECT_LEFT, RECT_RIGHT) if rectified else (RAW_LEFT, RAW_RIGHT)
        frame_id = "camera" if rectified else "camera_raw"
        out = []
        for topic, img in ((lt, msg.left), (rt, msg.right)):
            data, fmt = self._image(img)
            out.append(Recorded(topic, foxglove.compressed_image(msg.stamp_ns, frame_id, data, fmt),
                                msg.stamp_ns, msg.seq))
        cam = msg.camera  # (None: raw pairs)
        if cam is not None and self._camera_info_due(cam, msg.stamp_ns):
            out.append(Recorded(CAMERA_INFO, foxglove.camera_calibration(msg.stamp_ns, cam),
                                msg.stamp_ns, msg.seq))
            # log time just before the pair's, so that a reader has it when the pair comes
            out.append(Recorded(RECT_CALIBRATION, {"yaml": rectified_calibration_yaml(cam),
                                                   "source": "the rectified camera"}, msg.stamp_ns - 1, msg.seq))
        return out

    def disparity(self, msg: DisparityMap) -> list[Recorded]:
        if not self.options.disparity:
            return []
        data = encode_array(colorize_disparity(msg), "jpeg", self.options.jpeg_quality)
        return [Recorded(DISPARITY_COLOR, foxglove.compressed_image(msg.stamp_ns, "camera", data, "jpeg"),
                         msg.stamp_ns, msg.seq)]

    def obstacles(self, msg: ObstacleList) -> list[Recorded]:
        # A stale re-publication carries an old capture stamp: log it when it was published.
        t = msg.publish_ns if msg.stale else msg.stamp_ns
        out = [Recorded(OBSTACLES, msg.model_dump_json(), t, msg.seq)]
        if not msg.stale:
            out += [Recorded(OBSTACLE_BOXES, foxglove.obstacle_annotations(msg), t, msg.seq),
                    Recorded(OBSTACLE_SCENE, foxglove.obstacle_scene(msg), t, msg.seq)]
        if msg.mount is not None:  # the camera where the segmenter placed it for this list
            out.append(Recorded(TF, foxglove.base_to_camera(msg.stamp_ns, msg.mount), t, msg.seq))
        return out

    def freespace(self, msg: FreeSpace) -> list[Recorded]:
        return [Recorded(FREESPACE, msg.model_dump_json(), msg.stamp_ns, msg.seq),
                Recorded(FREESPACE_GRID, foxglove.freespace_grid(msg), msg.stamp_ns, msg.seq)]

    def truth(self, msg: GroundTruth) -> list[Recorded]:
        return [Recorded(TRUTH, msg.model_dump_json(), msg.stamp_ns, msg.seq),
                Recorded(TRUTH_BOXES, foxglove.truth_annotations(msg), msg.stamp_ns, msg.seq)]

    def stats(self, msg: ServiceStats) -> list[Recorded]:
        return [Recorded(STATS, msg.model_dump_json(), msg.stamp_ns)]

    @staticmethod
    def calibration(yaml_text: str, source: str, stamp_ns: int | None = None) -> list[Recorded]:
        t = time.time_ns() if stamp_ns is None else stamp_ns
        return [Recorded(CALIBRATION, {"yaml": yaml_text, "source": source}, t)]


def rectified_calibration_yaml(cam: CameraModel) -> str:
    """The rectified rig a frame was rectified for, as a calibration file (`rectified: true`), with
    what each camera saw of pairs rectified with alpha > 0: replayed, the matcher still leaves the
    black alone."""
    import yaml as pyyaml

    rig = camera.RectifiedRig(camera.model_of(cam), "rectified camera")
    return pyyaml.safe_dump(camera.calibration_to_dict(rig), sort_keys=False)


# -- reading -------------------------------------------------------------------------------------
