"""Disparity cores: OpenCV block matching (SAD, the thesis's method), semi-global matching, and
`dense` (dense.py: semi-global + edge-aware fill, a confidence for every pixel), with an optional
left-right check, subpixel output, a vision-range gate and a search-range saturation measure. No
Zenoh here: the service (services/disparity: computer.py), the offline `disparity` command and the benchmarks
share this.

Output convention everywhere: int16 fixed point, disparity_px = value / 16 (OpenCV's 4 fractional
bits), and INVALID (= (min_disparity - 1) * 16) where no match was accepted
(common.disparity.to_float turns it into float px with NaN where invalid). Confidence, where a
method gives one: uint8, 0 = no measurement, 255 = certain.

The settings are config.MatcherConfig (the disparity service's settings extend it); the cores take
either directly, with num_disparities resolved to px (config.resolved for `auto`).
"""
from __future__ import annotations

import cv2
import numpy as np

from common.errors import BallbotError
from cores.matching.config import (  # noqa: F401
    DEFAULT_BLOCK,
    SATURATION_WARN,
    SCALE,
    TOP_BAND_PX,
    MatcherConfig,
    auto_num_disparities,
    gate_for_range,
)
from cores.matching.disparity import raw_at_least
from cores.matching.opencv import (  # noqa: F401
    Match,
    compute_padded,
    create_opencv_matcher,
    create_sgbm,
    gray,
    reaches_padding,
    saturated_share,
    texture,
)

# texture (opencv.texture, over the window and its gradient's reach) from which a window decides its
# own match in semi-global matching; below it its disparity is carried in from around it (Match.flat).
# On the low-faces scene (sgbm, 12 frames) the floor carried into a plain crate's face made free space
# under it in 8 of 24 sightings as seen floor; taken for floor only above 1.25: 3; 1.5 and up: none.
SGBM_DECIDES = 2.0


def _check_pair(left: np.ndarray, right: np.ndarray) -> None:
    if left.shape != right.shape:
        raise BallbotError(f"left {left.shape} and right {right.shape} images differ in size")


class StereoMatcher:
    """bm or sgbm: disparity of the left image. Images: (H, W) uint8 or (H, W, 3) BGR, rectified
    (epipolar lines are rows), the same size."""

    def __init__(self, config: MatcherConfig):
        if config.method == "dense":
            raise BallbotError("StereoMatcher is bm or sgbm; make_matcher builds dense")
        self.config = c = config
        self._m = create_opencv_matcher(c)
        # The right view's disparity: the same matcher on mirrored images (right becomes "left").
        # Its search starts at -(min + num - 1) mirrored, i.e. the same disparities seen from the right.
        self._mr = create_opencv_matcher(c) if c.lr_check else None
        # match_band: the band OpenCV leaves unmatched (x < min + num) is matched on the pair padded
        # on the left, as dense does. A band pixel whose partner lies left of the right image's edge
        # (nearer than x px of disparity) still finds some best window: bm's own left-right check
        # drops most of those (the synthetic scenes' band: 2.1 % of its matches off by more than a
        # pixel without it, 1.1 % with it, the rest of the image 0.9 %); sgbm has its own already.
        self.pad = max(0, c.min_disparity + c.fixed_num_disparities) if c.match_band else 0
        if self.pad and c.method == "bm":
            self._m.setDisp12MaxDiff(c.disp12_max_diff)

    def compute(self, left: np.ndarray, right: np.ndarray, min_valid_disparity: float = 0.0) -> np.ndarray:
        """-> (H, W) int16, disparity * 16; invalid pixels hold config.invalid_value.
        min_valid_disparity: the range gate for this pair, px (gate_for_range(config.max_range_m, f, B)
        for its camera); smaller disparities are invalid. 0: no gate."""
        return self.match(left, right, min_valid_disparity).disparity

    def match(self, left: np.ndarray, right: np.ndarray, min_valid_disparity: float = 0.0) -> Match:
        _check_pair(left, right)
        c = self.config
        c.check_width(left.shape[1])
        gl, gr = gray(left), gray(right)
        d = compute_padded(self._m, gl, gr, self.pad)
        invalid = d < raw_at_least(c.min_disparity * SCALE)  # OpenCV marks failures below min_disparity*16
        if self.pad:
            outside = reaches_padding(d, c.block, self.pad)
            invalid[:, :outside.shape[1]] |= outside
        if self._mr is not None:
            invalid |= ~self._consistent(self._mr, d, gl, gr)
        saturated = saturated_share(d, ~invalid, c.max_disparity)
        if min_valid_disparity > 0:
            invalid |= d < raw_at_least(min_valid_disparity * SCALE)
        if not c.subpixel:
            d = ((d.astype(np.int32) + 8) // 16 * 16).astype(np.int16)
        d[invalid] = c.invalid_value
        # semi-global matching answers in a window with nothing to match too: it carries the
        # disparities around it in (a plain face takes the floor's beside it, row by row)
        flat = texture(gl, c.block + 2) < SGBM_DECIDES if c.method == "sgbm" else None
        return Match(d, None, saturated, flat)

    def _consistent(self, mr: cv2.StereoMatcher, d: np.ndarray, gl: np.ndarray, gr: np.ndarray) -> np.ndarray:
        """True where the left disparity at x agrees with the right disparity at x - d (mr: the
        matcher for the right image, as the left one mirrored)."""
        c = self.config
        # Mirrored, OpenCV's unmatched band (x < min + num) is the right image's right edge: left
        # unmatched, it failed every left pixel there (x >= W - num + d), a band as wide as the search
        # along the right side that the lists said they had looked at (the street: the right 320 px of
        # 1344 blind, and what stood there standing-not-listed in every list). Matched padded, as
        # match_band matches the left band; what reached into the padding compared against nothing.
        pad = max(0, c.min_disparity + c.fixed_num_disparities)
        dr = compute_padded(mr, np.ascontiguousarray(gr[:, ::-1]), np.ascontiguousarray(gl[:, ::-1]), pad)
        blind = reaches_padding(dr, c.block, pad)
        dr[:, :blind.shape[1]][blind] = (c.min_disparity - 1) * SCALE
        dr = dr[:, ::-1]
        h, w = d.shape
        xs = np.arange(w, dtype=np.int32)[None, :]
        xr = xs - ((d.astype(np.int32) + 8) >> 4)  # round(d) in px
        inside = (xr >= 0) & (d >= 0)
        xr = np.clip(xr, 0, w - 1)
        dr_at = np.take_along_axis(dr, xr, axis=1)
        ok = inside & (dr_at >= c.min_disparity * SCALE)
        ok &= np.abs(d.astype(np.int32) - dr_at.astype(np.int32)) <= c.lr_max_diff * SCALE
        return ok


def half_resolution(config: MatcherConfig) -> MatcherConfig:
    """The same settings for images of half the width and height (the cheap onboard fallback)."""
    nd = max(16, -(-config.fixed_num_disparities // 2 // 16) * 16)
    block = config.block // 2 | 1
    if config.method == "bm":
        block = max(5, block)
    # the speckle filter keeps its size in pixels: scaled with the area (a quarter), it left the blobs
    # bm makes of a plain face's noise at half resolution (20-40 of them), taken for floor seen far
    # away, and the free space reached under the low-faces crate and cabinet (7 of 16 sightings)
    return config.model_copy(update=dict(num_disparities=nd, min_disparity=config.min_disparity // 2,
                                         block_size=block))


class HalfResolutionMatcher:
    """Matches at half width and height, then returns a full-size map in full-resolution pixels
    (values doubled, nearest-neighbour upsampled), so consumers see the same contract."""

    def __init__(self, config: MatcherConfig):
        self.config = config
        self._inner = make_matcher(half_resolution(config))

    @property
    def output_range(self) -> tuple[int, int]:
        """(min_disparity, num_disparities) its values span, full-resolution px: the half-size search
        doubled, which can reach beyond the full-size settings' range (80 px searched as 48 -> 96)."""
        c = self._inner.config
        return 2 * c.min_disparity, 2 * c.fixed_num_disparities

    def compute(self, left: np.ndarray, right: np.ndarray, min_valid_disparity: float = 0.0) -> np.ndarray:
        return self.match(left, right, min_valid_disparity).disparity

    def match(self, left: np.ndarray, right: np.ndarray, min_valid_disparity: float = 0.0) -> Match:
        _check_pair(left, right)
        h, w = left.shape[:2]
        small = [cv2.resize(x, (w // 2, h // 2), interpolation=cv2.INTER_AREA) for x in (left, right)]
        m = self._inner.match(small[0], small[1], min_valid_disparity / 2)
        invalid = m.disparity == self._inner.config.invalid_value
        out = (m.disparity.astype(np.int32) * 2).clip(-32768, 32767).astype(np.int16)
        out[invalid] = self.config.invalid_value
        up = lambda a: cv2.resize(a, (w, h), interpolation=cv2.INTER_NEAREST)  # noqa: E731
        return Match(up(out), None if m.confidence is None else up(m.confidence), m.saturated,
                     None if m.flat is None else up(m.flat.view(np.uint8)).view(bool))


def make_matcher(config: MatcherConfig, scale: float = 1.0):
    """The matcher for these settings (num_disparities resolved). scale 1: full resolution;
    0.5: HalfResolutionMatcher. Every matcher has compute() -> int16 map and match() -> Match."""
    if scale == 0.5:
        return HalfResolutionMatcher(config)
    if scale != 1.0:
        raise BallbotError(f"scale: 1.0 or 0.5, got {scale}")
    if config.method == "dense":
        from cores.matching.dense import DenseMatcher

        return DenseMatcher(config)
    return StereoMatcher(config)
