"""The disparity stage as the disparity service runs it, for one rectified pair: the matcher of the
settings (num_disparities `auto` resolved for the camera), the vision-range gate, and the range its
values span. The service (services/disparity: onboard fallback and workers) and the in-process
pipeline (cores/pipeline.py: offline commands, evaluations, benchmarks) both compute through
MatchStage, so what is evaluated is what runs.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cores import camera
from cores.matching import exposure
from cores.matching.config import SCALE, MatcherConfig, gate_for_range
from cores.matching.disparity import searched_range, to_float
from cores.matching.exposure import Exposure
from cores.matching.matchers import make_matcher
from cores.matching.opencv import Match


@dataclass
class StageResult:
    """One pair's disparity. match.disparity: (H, W) int16, px * SCALE, `invalid_value` where no
    match; (min_disparity, num_disparities): the range the values span (what a DisparityMap
    states); gate_px: the vision range gate (config.max_range_m) that dropped the smaller ones (0:
    none); config: the settings it was computed with (num_disparities resolved)."""

    match: Match
    config: MatcherConfig
    min_disparity: int
    num_disparities: int
    gate_px: float = 0.0
    exposure: Exposure = Exposure()  # what the right image's grey levels were mapped by

    @property
    def invalid_value(self) -> int:
        return self.config.invalid_value

    def handed(self) -> dict[str, Any]:
        """What the disparity message carries to the segmenter beside the map (DisparityMap's
        confidence, flat, search and gate_px), as ObstacleBuilder.process takes it."""
        return {"confidence": self.match.confidence, "flat": self.match.flat,
                "search": (self.min_disparity, self.num_disparities), "gate_px": self.gate_px}

    def disparity_px(self) -> np.ndarray:
        """(H, W) float32 px, NaN where invalid or outside the stated range: what a consumer of the
        DisparityMap gets (cores/segmentation/builder.py decodes it the same way)."""
        return to_float(self.match.disparity, SCALE, self.invalid_value,
                        searched_range(self.min_disparity, self.num_disparities))


class MatchStage:
    """Rectified pairs of any camera -> StageResult. scale 1: full resolution; 0.5: the
    half-resolution matcher (the onboard fallback's `half`). Matchers are built once per camera
    (focal length, baseline, width), a few kept: calibrations come and go."""

    def __init__(self, config: MatcherConfig, scale: float = 1.0):
        self.config = config
        self.scale = scale
        self._matchers: dict[tuple, Any] = {}
        if config.num_disparities != "auto":  # bad settings fail now, not on the first frame
            self._matchers[()] = make_matcher(config, scale)

    def matcher(self, focal_px: float, baseline_m: float, width: int) -> Any:
        if () in self._matchers:
            return self._matchers[()]
        key = (focal_px, baseline_m, width)
        if key not in self._matchers:
            if len(self._matchers) >= 4:
                self._matchers.clear()
            self._matchers[key] = make_matcher(self.config.resolved(*key), self.scale)
        return self._matchers[key]

    def compute(self, left: np.ndarray, right: np.ndarray, focal_px: float, baseline_m: float,
                view: camera.RectifiedModel | None = None) -> StageResult:
        """left, right: (H, W) or (H, W, 3) uint8, rectified, of a camera with this focal length (px)
        and baseline (m). view: the rectified camera, whose outlines (view_left, view_right) say
        what part of each picture its camera saw (None: all of it)."""
        matcher = self.matcher(focal_px, baseline_m, left.shape[1])
        right, exp = exposure.equalize(left, right)  # two auto exposures: the right one brought to the left's
        gate = gate_for_range(self.config.max_range_m, focal_px, baseline_m)
        result = matcher.match(left, right, gate)
        c = matcher.config
        if view is not None and view.width == left.shape[1] and view.height == left.shape[0]:
            masks = camera.view_masks(view, window_reach(c, self.scale))
            if masks is not None:
                result = drop_unseen(result, *masks, c.invalid_value)
        lo, num = getattr(matcher, "output_range", (c.min_disparity, c.fixed_num_disparities))
        return StageResult(result, c, int(lo), int(num), float(gate), exp)


# Semi-global matching (sgbm, dense) carries a pixel's cost along its paths past its window: on the room
# (EuRoC) with alpha 1, sgbm's phantom obstacles along the seam of the black went only at 6 px more.
SEMI_GLOBAL_REACH_PX = 6


def window_reach(config: MatcherConfig, scale: float = 1.0) -> int:
    """How far (px of the full picture) from a pixel the matcher's cost looks: half its window, the
    pre-filter's (bm's normalized one; x-Sobel's 1 px), a pixel of interpolation, and for
    semi-global matching SEMI_GLOBAL_REACH_PX."""
    pre = config.prefilter_size // 2 if config.method == "bm" and config.prefilter == "normalized" else 1
    paths = 0 if config.method == "bm" else SEMI_GLOBAL_REACH_PX
    return int(np.ceil((config.block // 2 + pre + 1 + paths) / scale))


def drop_unseen(match: Match, seen_left: np.ndarray, seen_right: np.ndarray, invalid: int) -> Match:
    """The match without the disparities whose window, in the left picture or at its partner in the
    right one (x - d), reaches what its camera did not see (the masks: camera.view_masks). Along
    that seam the two pictures end in black at places the scene's depth has nothing to do with, and
    the matcher finds a wall of phantom depths there; farther in, a window sees only black and
    matches nothing."""
    d = match.disparity
    drop = (d != invalid) & ~camera.seen_by_both(d, SCALE, seen_left, seen_right)
    if not drop.any():
        return match
    conf = match.confidence
    return Match(np.where(drop, np.int16(invalid), d), None if conf is None else np.where(drop, np.uint8(0), conf),
                 match.saturated, match.flat)
