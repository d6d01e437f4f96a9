"""Computing one frame, shared by the workers and the onboard fallback: a rectified StereoFrame ->
its DisparityMap through the matching stage every composition runs (cores/matching/stage.py)."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from common import codec
from common.errors import BallbotError, DecodeError
from common.messages import DisparityMap, StereoFrame
from common.node import Node
from cores import camera
from cores.matching.matchers import SCALE, MatcherConfig
from cores.matching.stage import MatchStage
from services.disparity.rates import Rates
from services.disparity.results import result_header


class FrameComputer:
    """StereoFrame -> DisparityMap with one matcher. result_encoding 'raw': int16, invalid
    (min_disparity-1)*16; 'png': lossless uint16 for narrow links, invalid 0 (a disparity of exactly
    0, a point at infinity, is then invalid too; needs min_disparity >= 0). A method with a confidence
    (dense) sends it along, uint8, in the same encoding; one that says which windows were too plain to
    decide their match (sgbm) sends that mask as a one-bit png. num_disparities auto is resolved per camera
    model; `saturated` / `range_warning` tell about the last frame's search range (see report)."""

    def __init__(self, config: MatcherConfig, scale: float = 1.0, result_encoding: str = "raw", label: str = ""):
        if result_encoding not in ("raw", "png"):
            raise BallbotError(f"result_encoding: raw or png, got {result_encoding!r}")
        if result_encoding == "png" and config.min_disparity < 0:
            raise BallbotError("result_encoding png needs min_disparity >= 0")
        self.config = config
        self.scale = scale
        self.stage = MatchStage(config, scale)  # the matcher and gate the in-process pipeline runs too
        self.result_encoding = result_encoding
        self.method = config.method + ("" if scale == 1.0 else f"@{scale:g}") + (label and f"/{label}")
        self.saturated = 0.0
        self.range_warning = ""
        self.exposure_gain = 1.0  # the last pair's right-image gain (cores/matching/exposure.py; 1: untouched)

    def compute(self, msg: StereoFrame, worker: str) -> DisparityMap:
        if msg.camera is None:
            raise DecodeError("StereoFrame.camera: missing; disparity needs a rectified pair")
        if (msg.left.width, msg.left.height) != (msg.camera.width, msg.camera.height):
            raise DecodeError(f"left image is {msg.left.width}x{msg.left.height}, its camera model "
                              f"{msg.camera.width}x{msg.camera.height}")
        left = codec.array_from_image(msg.left, "left")
        right = codec.array_from_image(msg.right, "right")
        out = self.stage.compute(left, right, msg.camera.focal_px, msg.camera.baseline_m, camera.model_of(msg.camera))
        result = out.match
        self.saturated, self.range_warning = result.saturated, result.range_warning
        self.exposure_gain = out.exposure.gain
        disp = result.disparity
        if self.result_encoding == "png":
            invalid = 0.0
            disp = np.where(disp > 0, disp, 0).astype(np.uint16)
            image = codec.image_from_array(disp, "png")
        else:
            invalid = float(out.invalid_value)
            image = codec.image_from_array(disp)
        confidence = flat = None
        if result.confidence is not None:
            confidence = codec.image_from_array(result.confidence, self.result_encoding)
        if result.flat is not None:  # a mask: one bit a pixel in any encoding (raw would add half the map's bytes)
            flat = codec.image_from_array(result.flat.view(np.uint8) * np.uint8(255), "png", bilevel=True)
        # the range its values span (consumers treat anything outside it as invalid)
        return DisparityMap(robot_id=msg.robot_id, seq=msg.seq, stamp_ns=msg.stamp_ns, stages=msg.stages,
                            image=image, scale=SCALE, invalid_value=invalid, min_disparity=out.min_disparity,
                            num_disparities=out.num_disparities, gate_px=out.gate_px, camera=msg.camera,
                            method=self.method, worker=worker, confidence=confidence, flat=flat, checks=msg.checks)

    def answer(self, node: Node, msg: StereoFrame, worker: str, nonce: bytes, put: Callable[..., Any],
               rates: Rates) -> bool:
        """A worker's answer to one work item: its map, put with the header that names the item
        (its nonce) so the dispatcher takes it as that item's answer; timed and counted as the
        node's processing. False when computing failed (logged and counted by node.processing):
        the caller sends a receipt saying so, so the dispatcher frees the item at once."""
        with node.processing(msg):
            result = self.compute(msg, worker)
            result.stages[node.service] = node.clock.wall_ns()
            data = codec.encode(result)
            put(data, attachment=result_header(result, nonce))
            node._published(node.age_ns(msg))
            rates.add("out_work_result", len(data))
            self.report(node)
            return True
        return False

    def report(self, node: Node) -> None:
        """The last frame's search-range saturation and right-image gain into node's stats, and a
        (rate-limited) warning when a large share of the matched pixels sits at the top of the range."""
        node.extra["range_saturated_pct"] = round(self.saturated * 100.0, 2)
        node.extra["exposure_gain"] = round(self.exposure_gain, 3)
        if self.range_warning:
            node.warn("range", self.range_warning)


def reencode_frame(msg: StereoFrame, encoding: str, jpeg_quality: int = 90) -> StereoFrame:
    """The same pair with its images in `encoding` (raw, png lossless, jpeg lossy)."""
    if msg.left.encoding == encoding and msg.right.encoding == encoding:
        return msg
    left = codec.array_from_image(msg.left, "left")
    right = codec.array_from_image(msg.right, "right")
    return msg.model_copy(update={"left": codec.image_from_array(left, encoding, jpeg_quality),
                                  "right": codec.image_from_array(right, encoding, jpeg_quality)})


