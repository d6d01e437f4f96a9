"""The recording format: which MCAP topics hold what, a writer, a converter from pipeline messages
to recorded messages, and a reader that gives stereo pairs back. Pure: no Zenoh.

Layout 2 (metadata `ballbot.layout` = "2"): the foxglove.* channels are Foxglove's own protobuf
schemas and messages, made by Foxglove's SDK (cores/foxglove.py), so images are their JPEG or PNG
bytes as they are; the ballbot.* channels are JSON with the JSON Schema of our pydantic models.
Layout 1 (before: every channel JSON, images base64 inside it, no `layout` entry) is still read.

Topics (schema; log time = the pair's capture stamp, so a frame, its disparity and its boxes line
up in Foxglove; MCAP `sequence` = the capture seq):

| topic | schema | what |
|---|---|---|
| /frames/rectified/left, .../right | foxglove.CompressedImage | the rectified pairs: what the pipeline matched, what replay publishes |
| /frames/rectified/camera_info | foxglove.CameraCalibration | the rectified left camera (Foxglove projects 3D boxes with it) |
| /frames/rectified/calibration | ballbot.Calibration | the rectified rig as a `rectified: true` calibration (replay hands it to rectify, which passes the pairs through) |
| /frames/raw/left, /frames/raw/right | foxglove.CompressedImage | the pairs as captured, only when asked (`record --raw true`; `mcap from-images` writes these) |
| /disparity/color | foxglove.CompressedImage | disparity in colour (near = warm, no measurement = black) |
| /obstacles | ballbot.ObstacleList (JSON Schema) | the public obstacle list, as published |
| /obstacles/boxes | foxglove.ImageAnnotations | each obstacle's box, id and distance on the rectified left image |
| /obstacles/scene | foxglove.SceneUpdate | 3D boxes, camera frame |
| /freespace, /freespace/grid | ballbot.FreeSpace, foxglove.Grid | the occupancy grid (base frame) |
| /tf | foxglove.FrameTransform | base -> camera from the segmenter's ground estimate |
| /truth, /truth/boxes | ballbot.GroundTruth, foxglove.ImageAnnotations | the synthetic scene's truth |
| /stats | ballbot.ServiceStats | every service's stats, once a second each |
| /calibration | ballbot.Calibration | the calibration YAML the raw pairs need (replay of raw pairs hands it to rectify) |
"""
from __future__ import annotations

import itertools
import json
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Iterator

import cv2
import numpy as np

from common import codec
from common.errors import BallbotError, path_error
from common.messages import (CameraModel, DisparityMap, FreeSpace, GroundTruth, Image, ObstacleList, ServiceStats,
                                StereoFrame, TruthObstacle)
from cores import foxglove

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
    model = {"ballbot.ObstacleList": ObstacleList, "ballbot.FreeSpace": FreeSpace,
             "ballbot.GroundTruth": GroundTruth, "ballbot.ServiceStats": ServiceStats}[name]
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
    jpeg_quality: int = 75
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
        if rectified and self._camera_info_due(msg.camera, msg.stamp_ns):
            out.append(Recorded(CAMERA_INFO, foxglove.camera_calibration(msg.stamp_ns, msg.camera),
                                msg.stamp_ns, msg.seq))
            # log time just before the pair's, so that a reader has it when the pair comes
            out.append(Recorded(RECT_CALIBRATION, {"yaml": rectified_calibration_yaml(msg.camera),
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
    """The rectified rig a frame was rectified for, as a calibration file (`rectified: true`)."""
    import yaml as pyyaml

    return pyyaml.safe_dump({"name": "rectified camera", "rectified": True, "image_size": [cam.width, cam.height],
                             "focal_px": float(cam.focal_px), "principal_point": [float(cam.cx), float(cam.cy)],
                             "baseline_m": float(cam.baseline_m)}, sort_keys=False)


# -- reading -------------------------------------------------------------------------------------

@dataclass
class RecordedPair:
    """One stereo pair read back. left/right: (H, W) grey or (H, W, 3) BGR uint8."""

    seq: int
    stamp_ns: int
    left: np.ndarray
    right: np.ndarray
    truth: list[TruthObstacle] | None = None
    scenario: str = ""
    calibration_yaml: str | None = None  # the latest calibration for these pairs recorded at or before this pair
    calibration_source: str = ""  # where that calibration came from, as recorded (a file, a profile, ...)


@dataclass
class RecordingInfo:
    path: str
    channels: dict[str, int] = field(default_factory=dict)  # topic -> message count
    start_ns: int = 0
    end_ns: int = 0
    complete: bool = True  # False: no summary (the writer was killed); counts come from a scan
    metadata: dict[str, str] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return max(0, self.end_ns - self.start_ns) / 1e9

    def pairs(self, kind: str = "raw") -> int:
        left, right = (RAW_LEFT, RAW_RIGHT) if kind == "raw" else (RECT_LEFT, RECT_RIGHT)
        return min(self.channels.get(left, 0), self.channels.get(right, 0))


def image_payload(topic: str, message_encoding: str, schema_name: str, schema_data: bytes, data: bytes,
                  decoder: "foxglove.ProtobufDecoder", where: str) -> tuple[bytes, str]:
    """A recorded foxglove.CompressedImage -> (its image bytes, format). Layout 2: protobuf, by the
    schema the file carries; layout 1: JSON with the bytes in base64."""
    if message_encoding == "protobuf":
        try:
            msg = decoder.decode(schema_name, schema_data, data)
            return bytes(msg.data), str(msg.format)
        except Exception as e:  # protobuf's DecodeError, a schema that is not a FileDescriptorSet, ...
            raise RecordingError(f"{where}: not a {schema_name} protobuf message ({type(e).__name__})") from None
    import base64

    try:
        doc = json.loads(data)
        return base64.b64decode(doc["data"]), str(doc.get("format", "?"))
    except (KeyError, TypeError, ValueError) as e:
        raise RecordingError(f"{where}: no base64 image data ({type(e).__name__})") from None


def decode_image(data: bytes, fmt: str, where: str, strict: bool = True) -> np.ndarray:
    """Recorded image bytes -> array. strict: a JPEG or PNG that libjpeg or libpng reports damaged
    is refused (their warnings on stderr are captured for it, see common/files.py); else only an
    image that does not decode at all is."""
    from common.errors import FileError
    from common.files import imdecode_checked

    if strict:  # a damaged JPEG or PNG is refused, not decoded grey with libjpeg's warning on stderr
        try:
            a = imdecode_checked(data, where, cv2.IMREAD_UNCHANGED)
        except FileError as e:
            raise RecordingError(str(e)) from None
    else:
        a = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
        if a is None:
            raise RecordingError(f"{where}: {fmt} image of {len(data)} bytes does not decode")
    if a.ndim == 3 and a.shape[2] == 4:
        a = cv2.cvtColor(a, cv2.COLOR_BGRA2BGR)
    return a


def named_calibration(yaml_text: str, name: str) -> str:
    """A calibration's YAML with `name` set where it has none, so that whoever loads it (rectify,
    in its log and status) can say which calibration it is."""
    import yaml as pyyaml

    from common.files import parse_yaml

    try:
        doc = parse_yaml(yaml_text, "calibration")
    except Exception:
        return yaml_text  # whoever loads it says what is wrong with it
    if not isinstance(doc, dict) or doc.get("name") or not name:
        return yaml_text
    return pyyaml.safe_dump({"name": name, **doc}, sort_keys=False)


class RecordingReader:
    """Reads a recording back. Opening checks it is an MCAP file; a file whose writer was killed
    (no summary) is read up to its last complete chunk, with `truncated` set and a warning.
    strict_images: see decode_image (off where other threads log meanwhile: capturing stderr
    around a decode would swallow their lines)."""

    def __init__(self, path: str | Path, strict_images: bool = True):
        self.path = Path(path)
        self.strict_images = strict_images
        try:
            with open(self.path, "rb") as f:
                magic = f.read(8)
        except OSError as e:
            raise RecordingError(f"recording {path}: {path_error(e)}") from None
        if magic != b"\x89MCAP0\r\n":
            raise RecordingError(f"{path}: not an MCAP file (it starts with {magic[:8]!r})")
        self.truncated = False
        self._info: RecordingInfo | None = None

    def _messages(self, topics: list[str] | None = None) -> Iterator[tuple[str, Any, Any, Any]]:
        """(topic, mcap message, channel, schema) in log-time order where the file has an index,
        else file order."""
        from mcap.reader import make_reader

        with open(self.path, "rb") as f:
            reader = make_reader(f)
            try:
                indexed = reader.get_summary() is not None
            except Exception:  # a truncated file has no readable footer
                indexed = False
            if not indexed:
                from mcap.reader import NonSeekingReader

                f.seek(0)
                reader = NonSeekingReader(f, validate_crcs=False)
            n = 0
            try:
                for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=indexed):
                    n += 1
                    yield channel.topic, message, channel, schema
            except Exception as e:  # the mcap reader raises several types at a cut-off end
                if indexed:
                    raise RecordingError(f"{self.path}: damaged after {n} messages: {e}") from None
            if not indexed and not self.truncated:
                self.truncated = True
                log.warning("%s: no index (the recorder was killed?); read %d messages up to the last "
                            "complete chunk", self.path, n)

    def info(self) -> RecordingInfo:
        if self._info is not None:
            return self._info
        from mcap.reader import make_reader

        info = RecordingInfo(str(self.path))
        summary = None
        with open(self.path, "rb") as f:
            try:
                reader = make_reader(f)
                summary = reader.get_summary()
                for m in reader.iter_metadata():
                    info.metadata.update(m.metadata)
            except Exception:
                summary = None
        if summary is not None and summary.statistics is not None:
            st = summary.statistics
            info.channels = {summary.channels[cid].topic: n for cid, n in st.channel_message_counts.items()}
            info.start_ns, info.end_ns = st.message_start_time, st.message_end_time
        else:
            info.complete = False
            times = []
            for topic, m, _, _ in self._messages():
                info.channels[topic] = info.channels.get(topic, 0) + 1
                times.append(m.log_time)
            if times:
                info.start_ns, info.end_ns = min(times), max(times)
        layout = info.metadata.get("layout", "1")
        if not layout.isdigit() or int(layout) > LAYOUT:
            raise RecordingError(f"{self.path}: recording layout {layout}, newer than this version of ballbot-vision "
                                 f"reads (layouts 1 to {LAYOUT}); update ballbot-vision to read it")
        self._info = info
        return info

    def pairs(self, kind: str = "auto") -> Iterator[RecordedPair]:
        """Stereo pairs in capture order: the raw pairs ("raw"), the rectified ones ("rectified"),
        or raw when the recording has them, else rectified ("auto"). A pair missing a half is
        skipped (counted in `unpaired`), as is one with a damaged image (logged, counted in
        `damaged`): a replay goes on past it."""
        info = self.info()
        if kind == "auto":
            kind = "raw" if info.pairs("raw") else "rectified"
        left_t, right_t = (RAW_LEFT, RAW_RIGHT) if kind == "raw" else (RECT_LEFT, RECT_RIGHT)
        if not info.pairs(kind):
            have = ", ".join(sorted(info.channels)) or "no messages"
            hint = (" (`record` keeps them with --raw true)" if kind == "raw" and info.pairs("rectified") else "")
            raise RecordingError(f"{self.path}: no {kind} stereo pairs ({left_t} and {right_t}){hint}; it holds {have}")
        self.kind = kind
        self.unpaired = 0
        self.damaged = 0
        halves: dict[int, dict[str, Any]] = {}
        truths: dict[int, GroundTruth] = {}
        calibration: str | None = None
        calibration_source = ""
        decoder = foxglove.ProtobufDecoder()
        pending: tuple[int, int, dict] | None = None  # a complete pair waits for its truth (same log time)

        def finish(seq: int, t: int, half: dict) -> RecordedPair | None:
            where = f"{self.path}: pair seq {seq}"
            truth = truths.pop(seq, None)
            for old in [s for s in truths if s < seq]:
                del truths[old]
            try:
                left = decode_image(*half[left_t][0], f"{where} left", self.strict_images)
                right = decode_image(*half[right_t][0], f"{where} right", self.strict_images)
            except RecordingError as e:
                self.damaged += 1
                log.warning("%s; pair skipped", e)
                return None
            return RecordedPair(seq=seq, stamp_ns=t, left=left, right=right,
                                truth=None if truth is None else truth.obstacles,
                                scenario="" if truth is None else truth.scenario,
                                calibration_yaml=calibration, calibration_source=calibration_source)

        calibration_topic = CALIBRATION if kind == "raw" else RECT_CALIBRATION
        for topic, m, channel, schema in self._messages([left_t, right_t, TRUTH, calibration_topic]):
            if pending is not None and m.log_time > pending[1]:
                if (pair := finish(*pending)) is not None:
                    yield pair
                pending = None
            if topic in (calibration_topic, TRUTH):
                try:
                    doc = json.loads(m.data)
                except ValueError:
                    log.warning("%s: a %s message is not JSON; skipped", self.path, topic)
                    continue
            if topic == calibration_topic:
                calibration = doc.get("yaml") if isinstance(doc, dict) else None
                calibration_source = str(doc.get("source") or "") if isinstance(doc, dict) else ""
                continue
            if topic == TRUTH:
                try:
                    truths[m.sequence] = GroundTruth.model_validate(doc)
                except Exception:
                    log.warning("%s: a %s message does not validate; skipped", self.path, topic)
                continue
            try:
                image = image_payload(topic, channel.message_encoding, schema.name if schema else "",
                                      schema.data if schema else b"", m.data, decoder,
                                      f"{self.path}: {topic} seq {m.sequence}")
            except RecordingError as e:
                self.damaged += 1
                log.warning("%s; skipped", e)
                continue
            half = halves.setdefault(m.sequence, {})
            half[topic] = (image, m.log_time)
            if len(half) < 2:
                continue
            del halves[m.sequence]
            for old in [s for s in halves if s < m.sequence - 64]:  # a half whose partner never came
                del halves[old]
                self.unpaired += 1
            if pending is not None and (pair := finish(*pending)) is not None:
                yield pair
            pending = (m.sequence, half[left_t][1], half)
        if pending is not None and (pair := finish(*pending)) is not None:
            yield pair
        self.unpaired += len(halves)



def offline_pairs(path: str | Path, calibration: str | None = None):
    """A recording for the offline commands (`obstacles rec.mcap`): (pairs, calibration), where
    pairs yields (left label, right label, left, right, t_s) in capture order, t_s from the
    recording's stamps, and calibration is `calibration` (a file or profile) or else the
    recording's own, as a Calibration."""
    from cores import camera
    from common.files import parse_yaml

    reader = RecordingReader(path)
    pairs = reader.pairs("auto")  # raw pairs where recorded (they need a calibration), else the rectified ones
    first = next(pairs, None)
    if first is None:
        raise RecordingError(f"{path}: no stereo pair could be read")
    where = f"{path}: {CALIBRATION if reader.kind == 'raw' else RECT_CALIBRATION}"
    if calibration and reader.kind == "rectified":
        raise RecordingError(f"{path}: holds rectified pairs, recorded with their rectified camera: they need no "
                             f"--calibration")
    if calibration:
        cal = camera.load_calibration(calibration)
    elif first.calibration_yaml:
        cal = camera.calibration_from_dict(parse_yaml(first.calibration_yaml, where), where=where)
    else:
        raise RecordingError(f"{path}: the recording holds no calibration; give one with --calibration")

    def labelled():
        for p in itertools.chain([first], pairs):
            yield (f"{path}#{p.seq}:left", f"{path}#{p.seq}:right", p.left, p.right,
                   (p.stamp_ns - first.stamp_ns) / 1e9)
    return labelled(), cal
