"""A worker's answer to one work item, and how the dispatcher vets it before the robot sees it.

A disparity worker may run on any host, so its output is the least trusted input of the robot. It
publishes each map only on its own key (`work_result/<instance>`), with a small header in the
attachment (ResultHeader: the item's nonce, seq and stamp, and what the map says it is). The
dispatcher takes a map only as the answer to a work item it gave that worker and that is still
outstanding, and republishes it on `disparity` with the frame's own stamp, stages and camera, signed
(common/signed_payload.py): nothing a worker sends moves the segmenter's ordering reference or its
freshness clock. The checks, cheapest first:

1. before the payload is copied out of Zenoh (Answers.on_result, answers.py): its length against the bound
   for the frame's size; the header (a few hundred bytes) names the nonce, seq and stamp of an item
   outstanding at the worker the key names, the frame's width and height, an encoding the pool uses
   (raw int16 or png uint16) with the pool's fixed-point scale, that encoding's invalid value and a
   search range a matcher can have (vet_header);
2. then the message, decoded, must say what the header said and carry the frame's camera model, and
   its pixels are looked at (vet_map): values outside the stated range are invalid pixels, and a map
   with more than 1 % of them is refused; its valid fraction is measured, and a map that measured
   nothing while the robot's recent maps did, or under half of what the worker's own maps of the
   last 2 s did, is refused (Answers._collapsed, with common/disparity.py's RecentValid).

A refused map costs the worker its place (quarantine, DispatchState.reject), never the robot its
output: the onboard fallback or the other workers take the next frames.
"""
from __future__ import annotations

import hmac
import os
from dataclasses import dataclass, field

import msgpack
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from common import codec
from common.errors import DecodeError
from common.messages import MAX_MIN_DISPARITY, MAX_NUM_DISPARITIES, CameraModel, DisparityMap, FrameChecks, StereoFrame
from cores.calibration.check import SWAPPED_SHARE
from cores.calibration.near import CONTRADICTED_SHARE, contradicted, map_cells
from cores.matching.config import SCALE
from cores.matching.disparity import MEASURED_CONFIDENCE, raw_at_least, raw_at_most, searched_range

NONCE_BYTES = 16
HEADER_MAX_BYTES = 1024
# (encoding, dtype) of the maps a worker sends (FrameComputer): raw int16 or lossless png uint16
POOL_FORMATS = {("raw", "int16"), ("png", "uint16")}
# Share of a map's pixels that may lie outside its stated search range before the map is refused:
# an honest matcher gives none; a few from a rounding bug cost those pixels, not the map.
MAX_OUT_OF_RANGE = 0.01
# A map measuring less of the image than this measured nothing (as the segmenter's no-valid-disparity)
MIN_MEASURED = 0.01


@dataclass(frozen=True)
class Ticket:
    """What the dispatcher remembers of a work item it sent: the answer must match it, and the map
    it republishes carries the frame's own stamp, stages, camera and checks, not the worker's say-so."""

    robot_id: str
    seq: int
    stamp_ns: int
    width: int
    height: int
    camera: CameraModel
    stages: dict[str, int] = field(default_factory=dict)
    checks: FrameChecks | None = None
    nonce: bytes = field(default_factory=lambda: os.urandom(NONCE_BYTES))

    @classmethod
    def for_frame(cls, msg: StereoFrame) -> Ticket:
        if msg.camera is None:
            raise DecodeError("StereoFrame.camera: missing; a work item needs a rectified pair")
        return cls(msg.robot_id, msg.seq, msg.stamp_ns, msg.camera.width, msg.camera.height, msg.camera,
                   dict(msg.stages), msg.checks)


class ResultHeader(BaseModel):
    """The attachment of a worker's map: which item it answers and what the map says it is, small
    enough to check before the payload is copied or decoded."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)

    nonce: bytes = Field(min_length=NONCE_BYTES, max_length=NONCE_BYTES)
    seq: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    width: int = Field(gt=0, le=16384)
    height: int = Field(gt=0, le=16384)
    encoding: str = Field(max_length=8)
    dtype: str = Field(max_length=8)
    scale: float
    invalid_value: float
    min_disparity: int
    num_disparities: int
    confidence: bool
    flat: bool = False


def result_header(m: DisparityMap, nonce: bytes) -> bytes:
    """The worker's side: the header for map m answering the item with this nonce."""
    return msgpack.packb({"nonce": nonce, "seq": m.seq, "stamp_ns": m.stamp_ns, "width": m.image.width,
                          "height": m.image.height, "encoding": m.image.encoding, "dtype": m.image.dtype,
                          "scale": float(m.scale), "invalid_value": float(m.invalid_value),
                          "min_disparity": m.min_disparity, "num_disparities": m.num_disparities,
                          "confidence": m.confidence is not None, "flat": m.flat is not None}, use_bin_type=True)


def parse_header(raw: bytes | None) -> ResultHeader:
    """The attachment of a result -> its header; DecodeError saying what is wrong."""
    if raw is None:
        raise DecodeError("work result: no header attachment (a map must name the item it answers)")
    if len(raw) > HEADER_MAX_BYTES:
        raise DecodeError(f"work result: header of {len(raw)} bytes (at most {HEADER_MAX_BYTES})")
    try:
        doc = msgpack.unpackb(raw, raw=False)
    except Exception as e:
        raise DecodeError(f"work result header: not msgpack ({type(e).__name__}: {e})") from None
    if not isinstance(doc, dict):
        raise DecodeError(f"work result header: expected a map, got {type(doc).__name__}")
    try:
        return ResultHeader.model_validate(doc)
    except ValidationError as e:
        first = e.errors()[0]
        raise DecodeError(f"work result header.{'.'.join(str(p) for p in first['loc'])}: {first['msg']}") from None


def max_payload_bytes(width: int, height: int, confidence: bool, flat: bool = False) -> int:
    """Largest honest payload for a map of this size: 2 bytes a pixel (a png of noise is a little
    larger than its pixels: 1 % slack), plus a uint8 confidence and a uint8 flat mask of the same
    size if there are, plus the message's small fields."""
    px = width * height
    n = 2 * px + 2 * px // 100 + 4096
    n += (int(confidence) + int(flat)) * (px + px // 100 + 4096)
    return n + (64 << 10)


def vet_header(h: ResultHeader, t: Ticket, payload_len: int) -> str:
    """-> "" when the header fits the item, else why not (the map is then refused undecoded)."""
    if not hmac.compare_digest(h.nonce, t.nonce):
        return "its nonce is not the one sent with the item"
    if (h.seq, h.stamp_ns) != (t.seq, t.stamp_ns):
        return f"it answers seq {h.seq} stamp {h.stamp_ns}, the item was seq {t.seq} stamp {t.stamp_ns}"
    if (h.width, h.height) != (t.width, t.height):
        return f"it is {h.width}x{h.height}, the frame {t.width}x{t.height}"
    if (h.encoding, h.dtype) not in POOL_FORMATS:
        return f"it is {h.encoding} {h.dtype}; the pool sends raw int16 or png uint16"
    if h.scale != SCALE:
        return f"fixed-point scale {h.scale:g}, the pool's is {SCALE:g}"
    if not (abs(h.min_disparity) <= MAX_MIN_DISPARITY and 16 <= h.num_disparities <= MAX_NUM_DISPARITIES
            and h.num_disparities % 16 == 0):  # as DisparityMap allows
        return f"search range min {h.min_disparity} num {h.num_disparities} is no matcher's"
    invalid = 0.0 if h.encoding == "png" else float((h.min_disparity - 1) * int(SCALE))
    if h.invalid_value != invalid or (h.encoding == "png" and h.min_disparity < 0):
        return f"invalid value {h.invalid_value:g} for {h.encoding} from min_disparity {h.min_disparity}"
    limit = max_payload_bytes(t.width, t.height, h.confidence, h.flat)
    if payload_len > limit:
        return f"{payload_len} bytes for a {t.width}x{t.height} map (at most {limit})"
    return ""


@dataclass
class MapCheck:
    valid_fraction: float  # share of the pixels measured (> 0 px; not a dense fill) in the stated range
    out_of_range: float  # share of the pixels neither invalid nor in the stated range


def measure(raw: np.ndarray, invalid_value: float, scale: float, min_disparity: int,
            num_disparities: int, confidence: np.ndarray | None = None) -> MapCheck:
    """Valid and out-of-range shares of a fixed-point map (int16/uint16). With the map's confidence,
    only what the matcher measured (MEASURED_CONFIDENCE or more) counts as valid: dense fills every
    pixel its measurements reach, so its maps would never measure less, dark or blind, and a
    worker whose matcher stopped measuring would never be told from one that sees."""
    lo, hi = searched_range(min_disparity, num_disparities)
    # integer bounds: the map's integers are compared as they are, not cast to float64 (raw_at_least)
    valid = raw != int(invalid_value) if float(invalid_value).is_integer() else np.ones(raw.shape, bool)
    inside = (raw >= raw_at_least(lo * scale)) & (raw <= raw_at_most(hi * scale))
    n = max(1, raw.size)
    measured_px = valid & inside & (raw > 0)
    if confidence is not None and confidence.shape == raw.shape:
        measured_px &= confidence >= MEASURED_CONFIDENCE
    measured = np.count_nonzero(measured_px)
    outside = np.count_nonzero(valid & ~inside)
    return MapCheck(measured / n, outside / n)


def matcher_of(method: str) -> str:
    """The matcher a map's method names: a half-resolution or labelled worker says `sgbm@0.5`,
    `dense/x` (computer.FrameComputer.method); what each matcher must send beside its map
    does not change with the resolution or the label."""
    return method.split("@")[0].split("/")[0]


def vet_map(m: DisparityMap, h: ResultHeader, t: Ticket) -> tuple[str, MapCheck | None]:
    """The decoded message against its header and the item, then its pixels. -> ("", check) or
    (why it is refused, None)."""
    img = m.image
    if (m.robot_id, m.seq, m.stamp_ns) != (t.robot_id, t.seq, t.stamp_ns):
        return f"the map is for {m.robot_id} seq {m.seq} stamp {m.stamp_ns}, not the item's", None
    said = (h.width, h.height, 1, h.encoding, h.dtype, h.scale, h.invalid_value, h.min_disparity,
            h.num_disparities, h.confidence, h.flat)
    has = (img.width, img.height, img.channels, img.encoding, img.dtype, m.scale, m.invalid_value,
           m.min_disparity, m.num_disparities, m.confidence is not None, m.flat is not None)
    if said != has:
        return f"the map is not what its header said (header {said}, map {has})", None
    if m.camera != t.camera:
        return "the map carries another camera model than the frame's", None
    matcher = matcher_of(m.method)
    if matcher == "dense" and m.confidence is None:
        # dense fills every pixel its measurements reach: without the confidence that tells them apart the
        # segmenter would take the fill for measurement, and a dark or blank view for a full one
        return "it says dense and carries no confidence (its fill cannot be told from what it measured)", None
    if matcher == "sgbm" and m.flat is None:
        # the disparities sgbm carries into a plain face from the floor beside it would pass for floor
        # seen, and the free space would reach under the face
        return ("it says sgbm and carries no flat mask (what it carried into plain windows would pass for "
                "measured)"), None
    try:
        raw = codec.array_from_image(img, "disparity")
        # the confidence travels as the map does, the flat mask as one bit a pixel (it is decoded only to
        # see that it decodes)
        conf = codec.side_images(m, {"confidence": img.encoding, "flat mask": "png"}).get("confidence")
    except DecodeError as e:
        return str(e), None
    check = measure(raw, m.invalid_value, m.scale, m.min_disparity, m.num_disparities, conf)
    if check.out_of_range > MAX_OUT_OF_RANGE:
        return (f"{check.out_of_range:.1%} of its pixels lie outside its search range "
                f"[{m.min_disparity}, {m.min_disparity + m.num_disparities}] px"), None
    # against the robot's own coarse look at the pair (rectify's near field): a worker that erased what
    # stands, or answers with an old map, passes every check above. Not for a pair whose cameras rectify
    # finds swapped or its rows apart: both looks are then off, through no fault of the worker's (the
    # lists say cameras-swapped, rows-misaligned), and a quarantine would only move its load onboard
    near = t.checks.near if t.checks is not None else None
    rows = t.checks.rows if t.checks is not None else None
    if near is not None and not (rows is not None and (rows.reversed_share > SWAPPED_SHARE
                                                       or rows.offset_px > rows.tolerance_px)):
        band = m.min_disparity + m.num_disparities
        share = contradicted(map_cells(raw, near, m.scale, max(0.0, m.invalid_value)), band - 1, band)
        if share >= CONTRADICTED_SHARE:
            return (f"it puts {share:.1%} of the picture farther than rectify's coarse look at the same pair sees "
                    f"it (a map not of this pair, or with what stands erased)"), None
    return "", check
