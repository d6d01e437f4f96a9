"""The viewer's core: the latest pipeline messages -> what one page update carries. Pure: no Zenoh,
no web server.

One update is one binary WebSocket message (see `pack`): a 4-byte big-endian length, the JSON
document of the frame, then the images it names in `blobs` (JPEG/PNG bytes, in that order). The
JSON and the images belong to the same capture seq wherever the viewer still holds that frame
(`matched` says so), so the boxes drawn are the boxes of the picture shown.

Pictures: `left` is the rectified left image (JPEG), `disparity` the disparity in colour (JPEG,
near = warm, no measurement = black), `freespace` the occupancy grid as seen from above (PNG,
RGBA: forward up, left to the left; free green, occupied red, unknown transparent).
"""
from __future__ import annotations

import json
import struct
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from common import codec
from common.messages import DisparityMap, FreeSpace, GroundTruth, ObstacleList, ServiceStats, StereoFrame
from cores.recording import colorize_disparity

STAGES = ("capture", "rectify", "disparity", "segmenter")
RING = 48  # recent frames, disparity maps and truths kept to pair with a later obstacle list
STATS_MAX_AGE_S = 3.5  # stats are published once a second; older ones belong to a stopped instance


@dataclass
class Blob:
    name: str
    mime: str
    data: bytes


def pack(doc: dict, blobs: list[Blob]) -> bytes:
    """One WebSocket message: u32 JSON length, JSON (with `blobs`: name, type, size), the blobs."""
    doc = dict(doc, blobs=[{"name": b.name, "type": b.mime, "size": len(b.data)} for b in blobs])
    head = json.dumps(doc, separators=(",", ":")).encode()
    return b"".join([struct.pack(">I", len(head)), head] + [b.data for b in blobs])


def unpack(message: bytes) -> tuple[dict, dict[str, bytes]]:
    """Inverse of pack (tests and Python clients)."""
    (n,) = struct.unpack(">I", message[:4])
    doc = json.loads(message[4:4 + n])
    out, pos = {}, 4 + n
    for b in doc["blobs"]:
        out[b["name"]] = message[pos:pos + b["size"]]
        pos += b["size"]
    if pos != len(message):
        raise ValueError(f"message of {len(message)} bytes, blobs end at {pos}")
    return doc, out


def encode_jpeg(a: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    return buf.tobytes()


def freespace_picture(msg: FreeSpace) -> np.ndarray:
    """(W, H, 4) RGBA uint8 of the grid seen from above: screen rows run along -x (forward is up),
    screen columns along -y (left is left). The image's top-left corner is the base-frame point
    (origin_x + width*res, origin_y + height*res)."""
    cells = np.frombuffer(msg.cells, np.int8)
    if cells.size != msg.width * msg.height:
        raise ValueError(f"FreeSpace: {cells.size} cells for a {msg.width}x{msg.height} grid")
    grid = cells.reshape(msg.height, msg.width)
    rgba = np.zeros((msg.height, msg.width, 4), np.uint8)
    rgba[grid == 0] = (60, 200, 90, 110)
    occupied = grid >= 50
    rgba[occupied] = (235, 60, 50, 200)
    return np.ascontiguousarray(rgba.transpose(1, 0, 2)[::-1, ::-1])


def obstacle_doc(o) -> dict:
    return {"id": o.id, "bbox_px": list(o.bbox_px), "distance_m": round(o.distance_m, 3),
            "position_m": [round(v, 3) for v in o.position_m], "size_m": [round(v, 3) for v in o.size_m],
            "position_base_m": None if o.position_base_m is None else [round(v, 3) for v in o.position_base_m],
            "velocity_mps": [round(v, 3) for v in o.velocity_mps], "confidence": round(o.confidence, 3),
            "confirmed": o.confirmed}


def latency_doc(msg: ObstacleList) -> dict:
    """Milliseconds from capture to each stage's publish, and the time each stage took."""
    at = {s: (msg.stages[s] - msg.stamp_ns) / 1e6 for s in STAGES if s in msg.stages}
    steps, prev = {}, 0.0
    for s in STAGES:
        if s in at:
            steps[s] = round(at[s] - prev, 2)
            prev = at[s]
    return {"at_ms": {k: round(v, 2) for k, v in at.items()}, "step_ms": steps,
            "capture_to_obstacles_ms": round((msg.publish_ns - msg.stamp_ns) / 1e6, 2)}


@dataclass
class ViewInputs:
    """What the viewer holds: recent frames and disparity maps (payloads by capture stamp, decoded
    only when shown), the latest obstacle list, free space, truth and every instance's stats."""

    # (stamp_ns, payload): enough to still hold the picture of an obstacle list that comes ~1.5 s
    # (30 Hz) to ~5 s (10 Hz) after its capture, at most ~45 MB of 640x480 BGR pairs
    frames: deque = field(default_factory=lambda: deque(maxlen=RING))
    disparities: deque = field(default_factory=lambda: deque(maxlen=RING))
    truths: deque = field(default_factory=lambda: deque(maxlen=RING))
    obstacles: ObstacleList | None = None
    freespace: FreeSpace | None = None
    stats: dict[tuple[str, str], tuple[float, ServiceStats]] = field(default_factory=dict)

    def add_stats(self, st: ServiceStats, now: float | None = None) -> None:
        self.stats[(st.service, st.instance)] = (time.monotonic() if now is None else now, st)

    @staticmethod
    def pick(ring: deque, stamp_ns: int | None) -> tuple[Any, bool]:
        """The payload with this capture stamp (matched) or else the newest (not matched). Only
        stamped payloads count (the service keeps no other: an unstamped one cannot be ordered)."""
        items = [sp for sp in ring if sp[0] is not None]
        if not items:
            return None, False
        if stamp_ns is not None:
            for s, p in reversed(items):
                if s == stamp_ns:
                    return p, True
        return max(items, key=lambda sp: sp[0])[1], False


class Composer:
    """ViewInputs -> one packed page update. Decodes and encodes; keeps no Zenoh state."""

    def __init__(self, robot_id: str, jpeg_quality: int = 80):
        self.robot_id = robot_id
        self.jpeg_quality = jpeg_quality

    def compose(self, inputs: ViewInputs, extra: dict | None = None, now: float | None = None) -> bytes:
        now = time.monotonic() if now is None else now
        obstacles = inputs.obstacles
        stamp = obstacles.stamp_ns if obstacles is not None else None
        doc: dict[str, Any] = {"robot_id": self.robot_id, "sent_ns": 0}
        blobs: list[Blob] = []

        frame_payload, frame_matched = inputs.pick(inputs.frames, stamp)
        if frame_payload is not None:
            frame = codec.decode(frame_payload, StereoFrame)
            left = codec.array_from_image(frame.left, "left")
            if left.dtype != np.uint8:
                # (OpenCV's stubs refuse dst None; OpenCV takes it: a new array)
                left = cv2.normalize(left, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)  # type: ignore[call-overload]
            blobs.append(Blob("left", "image/jpeg", encode_jpeg(left, self.jpeg_quality)))
            doc["image"] = {"seq": frame.seq, "stamp_ns": frame.stamp_ns, "width": frame.left.width,
                            "height": frame.left.height, "matched": frame_matched}
            stamp = stamp if frame_matched else frame.stamp_ns
        disp_payload, disp_matched = inputs.pick(inputs.disparities, stamp)
        if disp_payload is not None:
            d = codec.decode(disp_payload, DisparityMap)
            blobs.append(Blob("disparity", "image/jpeg", encode_jpeg(colorize_disparity(d), self.jpeg_quality)))
            doc["disparity"] = {"seq": d.seq, "stamp_ns": d.stamp_ns, "method": d.method,
                                "num_disparities": d.num_disparities, "matched": disp_matched,
                                "focal_px": d.camera.focal_px, "baseline_m": d.camera.baseline_m}
        if obstacles is not None:
            doc["obstacles"] = {"seq": obstacles.seq, "stamp_ns": obstacles.stamp_ns,
                                "publish_ns": obstacles.publish_ns, "stale": obstacles.stale,
                                "degraded": list(obstacles.degraded), "method": obstacles.method,
                                "range_m": None if obstacles.range_m is None else list(obstacles.range_m),
                                "bearing_deg": None if obstacles.bearing_deg is None else list(obstacles.bearing_deg),
                                "list": [obstacle_doc(o) for o in obstacles.obstacles],
                                "latency": latency_doc(obstacles),
                                "ground": None if obstacles.ground is None else obstacles.ground.model_dump()}
        truth_payload, truth_matched = inputs.pick(inputs.truths, stamp)
        if truth_payload is not None and truth_matched:
            truth = codec.decode(truth_payload, GroundTruth)
            doc["truth"] = [{"name": t.name, "bbox_px": list(t.bbox_px), "nearest_m": round(t.nearest_m, 3),
                             "center_m": [round(v, 3) for v in t.center_m]}
                            for t in truth.obstacles if t.bbox_px is not None]
        if inputs.freespace is not None:
            fs = inputs.freespace
            picture = freespace_picture(fs)
            ok, png = cv2.imencode(".png", cv2.cvtColor(picture, cv2.COLOR_RGBA2BGRA))
            blobs.append(Blob("freespace", "image/png", png.tobytes()))
            doc["freespace"] = {"seq": fs.seq, "resolution_m": fs.resolution_m, "width": fs.width,
                                "height": fs.height, "origin_m": list(fs.origin_m),
                                # the picture's top-left corner in the base frame
                                "top_left_m": [fs.origin_m[0] + fs.width * fs.resolution_m,
                                               fs.origin_m[1] + fs.height * fs.resolution_m]}
        doc["services"] = self.services(inputs, now)
        if extra:
            doc.update(extra)
        return pack(doc, blobs)

    @staticmethod
    def services(inputs: ViewInputs, now: float) -> list[dict]:
        out = []
        for (service, instance), (t, st) in sorted(inputs.stats.items()):
            if now - t > STATS_MAX_AGE_S:
                continue
            row = {"service": service, "instance": instance, "rate_hz": round(st.rate_hz, 2),
                   "proc_ms": round(st.proc_ms_p50, 2), "age_ms": round(st.age_ms_p50, 2), "drops": st.drops,
                   "errors": st.errors + st.decode_errors, "status": st.status}
            if "replay_total" in st.extra:
                row["replay"] = {"index": int(st.extra.get("replay_index", 0)),
                                 "total": int(st.extra["replay_total"]),
                                 "paused": bool(st.extra.get("replay_paused", 0)),
                                 "speed": st.extra.get("replay_speed", 1.0)}
            out.append(row)
        return out

    @staticmethod
    def drop_old_stats(inputs: ViewInputs, now: float) -> None:
        for k in [k for k, (t, _) in inputs.stats.items() if now - t > 10 * STATS_MAX_AGE_S]:
            del inputs.stats[k]
