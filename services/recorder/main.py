"""record: the pipeline's messages -> an MCAP file that Foxglove opens (`ballbot-vision record OUT.mcap`).

Zenoh's callbacks only append the payload to a queue (bounded in bytes: past `queue_mb` a message
is dropped and counted, never the robot slowed); `threads` encoder threads decode, compress and
hand the messages to the writer. Ctrl-C, SIGTERM and SIGHUP stop the subscriptions, drain the
queue and close the file with its index, so a stopped recording is a complete file.
"""
from __future__ import annotations

import logging
import queue
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field

from common.codec import MIN_JPEG_QUALITY
from common.keys import topic
from common.messages import (
    CalibrationUpdate,
    DisparityMap,
    FreeSpace,
    GroundTruth,
    ObstacleList,
    ServiceStats,
    StereoFrame,
)
from common.node import Node
from common.settings import ServiceSettings
from cores.recording import Converter, Recorded, RecordingWriter, RecordOptions

log = logging.getLogger("ballbot.record")

SUBSCRIBES = ["frames_raw", "frames_rect", "disparity", "obstacles", "freespace", "truth", "stats", "calibration"]
PUBLISHES: list[str] = []


class RecordSettings(ServiceSettings):
    section = "record"
    image_format: Literal["jpeg", "png", "keep"] = Field(
        "jpeg", description="frames in the file: jpeg (small, fast), png (lossless, ~10x the CPU), keep (as "
                            "they travel: compressed payloads pass through, raw ones become jpeg)")
    # 90: at 75 (the default before; the bytes above it go to the sensor noise, and two-boxes' obstacles
    # agreed within 1 cm) low-faces' plain crate left a list replayed and the free space reached under it
    # (common/codec.py MIN_JPEG_QUALITY: 85 the least)
    jpeg_quality: int = Field(90, ge=MIN_JPEG_QUALITY, le=100, description="jpeg quality of frames and the "
                              "disparity picture")
    raw: bool = Field(False, description="record the raw pairs too (to rectify them again later, e.g. with another "
                      "calibration); replay needs only the rectified ones")
    rectified: bool = Field(True, description="record the rectified pairs (what the pipeline matched; what replay "
                            "publishes, with the rectified camera)")
    disparity: bool = Field(True, description="record the disparity as a colour picture")
    stats: bool = Field(True, description="record every service's stats")
    calibration: str | None = Field(None, description="calibration YAML or profile stored for replay (default: "
                                    "the rectify section's calibration of --config; unset: what the calibration "
                                    "key carries, and lifecam-studio for the synthetic scene, as rectify does)")
    compression: Literal["zstd", "lz4", "none"] = Field("zstd", description="MCAP chunk compression")
    threads: int = Field(2, ge=1, le=16, description="encoder threads")
    queue_mb: int = Field(1024, ge=16, le=65536, description="memory for messages waiting to be written; "
                          "beyond it messages are dropped and counted")
    duration_s: float = Field(0.0, ge=0, description="stop after this many seconds (0: until Ctrl-C)")
    pairs: int = Field(0, ge=0, description="stop after this many pairs (rectified, or raw with --raw true; 0: until "
                                            "Ctrl-C)")


@dataclass
class RecordResult:
    path: str
    seconds: float = 0.0
    counts: dict[str, int] = field(default_factory=dict)  # topic -> messages written
    received: dict[str, int] = field(default_factory=dict)  # key kind -> payloads received
    dropped_queue_full: int = 0
    decode_errors: int = 0
    pair_kind: str = "rectified"  # the pairs a replay publishes: rectified, or raw when recorded
    pair_seqs: list[int] = field(default_factory=list)
    bytes: int = 0

    @property
    def missing_pairs(self) -> int:
        """Pairs of the recorded kind that never reached the file: gaps in the capture seq (raw: lost
        by the recorder; rectified: also those the pipeline itself skipped under load; a restart of
        capture, which starts seq at 0 again, opens a new run)."""
        missing, last = 0, None
        for s in sorted(set(self.pair_seqs)):
            if last is not None and s > last + 1:
                missing += s - last - 1
            last = s
        return missing

    def summary(self) -> str:
        parts = ", ".join(f"{t} {n}" for t, n in sorted(self.counts.items()))
        return (f"wrote {self.path}: {parts or 'nothing'}; {self.bytes / 1e6:.1f} MB in {self.seconds:.1f} s; "
                f"dropped {self.dropped_queue_full} (queue full), "
                f"{self.missing_pairs} {self.pair_kind} pair(s) missing (seq gaps), {self.decode_errors} undecodable")


SYNTHETIC_RIG, SYNTHETIC_RIG_SOURCE = "lifecam-studio", "synthetic"  # what rectify assumes, for which source

MODELS: dict[str, type[BaseModel]] = {"frames_raw": StereoFrame, "frames_rect": StereoFrame, "disparity": DisparityMap,
          "obstacles": ObstacleList, "freespace": FreeSpace, "truth": GroundTruth, "stats": ServiceStats,
          "calibration": CalibrationUpdate}


def calibration_text(spec: str) -> str:
    """A calibration file's text, or a built-in profile written out as YAML."""
    import yaml

    from cores import camera

    cal = camera.load_calibration(spec)  # raises a CalibrationError naming the file
    if spec in camera.PROFILES:
        return yaml.safe_dump(camera.calibration_to_dict(cal), sort_keys=False)
    return Path(spec).read_text()


class Recorder:
    """The Zenoh side of a recording: subscriptions, the byte-bounded queue, encoder threads."""

    def __init__(self, node: Node, settings: RecordSettings, writer: RecordingWriter):
        self.node, self.settings, self.writer = node, settings, writer
        self.converter = Converter(RecordOptions(image_format=settings.image_format, jpeg_quality=settings.jpeg_quality,
                                                 raw=settings.raw, rectified=settings.rectified,
                                                 disparity=settings.disparity))
        self.queue: queue.Queue[tuple[str, bytes] | None] = queue.Queue()
        self.queued_bytes = 0
        self.max_bytes = settings.queue_mb << 20
        self.accepting = True
        self._lock = threading.Lock()
        self.result = RecordResult(str(writer.path))
        self.pairs_written = threading.Event()
        # the pairs a replay will publish: the raw ones where recorded, else the rectified ones
        self.pair_kind = "frames_raw" if settings.raw else "frames_rect"
        self.result.pair_kind = "raw" if settings.raw else "rectified"
        self._threads: list[threading.Thread] = []
        self.has_calibration = False  # set once a calibration is in the file

    def offer(self, kind: str, payload: bytes) -> None:
        """Zenoh's callback thread: count, bound, enqueue; nothing else."""
        with self._lock:
            if not self.accepting:
                return
            self.result.received[kind] = self.result.received.get(kind, 0) + 1
            if self.queued_bytes + len(payload) > self.max_bytes:
                self.result.dropped_queue_full += 1
                return
            self.queued_bytes += len(payload)
        self.queue.put((kind, payload))

    def subscribe(self) -> None:
        s = self.settings
        kinds = ["frames_raw", "frames_rect", "disparity", "obstacles", "freespace", "truth", "calibration"]
        kinds += ["stats"] if s.stats else []
        skip = {"frames_raw": not s.raw, "frames_rect": not s.rectified, "disparity": not s.disparity}
        for kind in kinds:
            if skip.get(kind):
                continue
            t = topic(kind)
            key = t.pattern(self.node.robot_id) if kind == "stats" else t.key(self.node.robot_id)
            def on_sample(sample: Any, k: str = kind) -> None:  # (k: this iteration's kind)
                self.offer(k, sample.payload.to_bytes())

            self.node.subscribe(key, on_sample)

    def start(self) -> None:
        for i in range(self.settings.threads):
            t = threading.Thread(target=self._work, name=f"record-{i}", daemon=True)
            t.start()
            self._threads.append(t)

    def _convert(self, kind: str, msg: Any) -> list[Recorded]:
        c = self.converter
        if kind in ("frames_raw", "frames_rect"):
            return c.frame(msg)
        if kind == "calibration":
            return c.calibration(msg.yaml, msg.source or "calibration key", msg.stamp_ns)
        convert: dict[str, Callable[[Any], list[Recorded]]] = {
            "disparity": c.disparity, "obstacles": c.obstacles, "freespace": c.freespace, "truth": c.truth,
            "stats": c.stats}
        return convert[kind](msg)

    def _work(self) -> None:
        while True:
            item = self.queue.get()
            if item is None:
                return
            kind, payload = item
            try:
                msg = self.node.decode_or_drop(payload, MODELS[kind], f"{kind} message")
                if msg is None:
                    continue
                with self.node.processing(msg):
                    if kind == "calibration":
                        self.has_calibration = True
                    elif kind == "frames_raw" and not self.has_calibration and isinstance(msg, StereoFrame):
                        self._assume_calibration(msg)
                    for r in self._convert(kind, msg):
                        self.writer.write(r.topic, r.doc, r.log_time_ns, r.sequence)
                    if kind == self.pair_kind and isinstance(msg, StereoFrame):
                        with self._lock:
                            self.result.pair_seqs.append(msg.seq)
                            n = len(self.result.pair_seqs)
                        self.node.extra["pairs_written"] = float(n)
                        if self.settings.pairs and n >= self.settings.pairs:
                            self.pairs_written.set()
            finally:
                with self._lock:
                    self.queued_bytes -= len(payload)
                self.node.extra["queue_mb"] = self.queued_bytes / 1e6
                self.node.extra["dropped_queue_full"] = float(self.result.dropped_queue_full)

    def _assume_calibration(self, msg: StereoFrame) -> None:
        """No calibration configured or received: rectify assumes the thesis rig for the synthetic
        scene only, and so does the recording (just before that pair); other sources are recorded
        without one (replay then needs rectify.calibration)."""
        with self._lock:
            if self.has_calibration:
                return
            self.has_calibration = True
        if msg.source == SYNTHETIC_RIG_SOURCE:
            text = calibration_text(SYNTHETIC_RIG)
            source = f"{SYNTHETIC_RIG} (assumed for the synthetic scene)"
            for r in Converter.calibration(text, source, msg.stamp_ns - 1):
                self.writer.write(r.topic, r.doc, r.log_time_ns)
        else:
            log.warning("record: no calibration configured (--calibration, rectify.calibration) or published; "
                        "replaying these %s pairs will need rectify.calibration", msg.source or "unknown")

    def drain(self, timeout_s: float = 30.0) -> None:
        """Stop accepting, let the encoder threads finish what is queued, then stop them."""
        with self._lock:
            self.accepting = False
        for _ in self._threads:
            self.queue.put(None)
        deadline = time.monotonic() + timeout_s
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        if any(t.is_alive() for t in self._threads):
            log.warning("record: %d message(s) still queued after %.0f s; closing without them",
                        self.queue.qsize(), timeout_s)


def record(node: Node, settings: RecordSettings, path: str | Path, calibration_spec: str | None,
           started: threading.Event | None = None) -> RecordResult:
    """Record until stopped (node.stop_event: Ctrl-C, SIGTERM, SIGHUP), `duration_s` or `pairs`."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGHUP, lambda *_: node.stop_event.set())
    # before the file exists: a bad calibration costs nothing
    text = calibration_text(calibration_spec) if calibration_spec else None
    writer = RecordingWriter(path, compression=settings.compression,
                             metadata={"robot_id": node.robot_id, "calibration": calibration_spec or "",
                                       "image_format": settings.image_format})
    t0 = time.monotonic()
    rec = Recorder(node, settings, writer)
    try:
        if text is not None and calibration_spec:
            for r in Converter.calibration(text, calibration_spec):
                writer.write(r.topic, r.doc, r.log_time_ns)
            rec.has_calibration = True
        rec.start()
        rec.subscribe()
        node.status = "recording"
        if started is not None:
            started.set()
        deadline = t0 + settings.duration_s if settings.duration_s else None
        while node.running and not rec.pairs_written.is_set():
            if deadline is not None and time.monotonic() >= deadline:
                break
            node.stop_event.wait(0.1)
        node.status = "closing"
        rec.drain()
    finally:
        writer.close()
    res = rec.result
    res.seconds = time.monotonic() - t0
    res.counts = dict(writer.counts)
    res.bytes = writer.path.stat().st_size
    res.decode_errors = node.decode_errors
    return res
