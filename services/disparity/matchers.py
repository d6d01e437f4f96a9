"""Disparity cores: OpenCV block matching (SAD, the thesis's method) and semi-global matching, with
an optional left-right consistency check, subpixel output and a vision-range gate. No Zenoh here:
the service (main.py, pool.py), the offline `disparity` command and the benchmarks share this.

Output convention everywhere: int16 fixed point, disparity_px = value / 16 (OpenCV's 4 fractional
bits), and INVALID (= (min_disparity - 1) * 16) where no match was accepted. `to_float` masks
invalid pixels as NaN explicitly rather than hiding them behind an epsilon.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import cv2
import numpy as np

from ...common.errors import BallbotError

SCALE = 16.0

# Per-method default matching window (block_size = 0 picks these): the thesis's 15 px SAD window for
# bm; 5 px for sgbm, whose smoothness terms do the aggregation (better than OpenCV's 3 on Middlebury).
DEFAULT_BLOCK = {"bm": 15, "sgbm": 5}
_SGBM_MODES = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "hh": cv2.STEREO_SGBM_MODE_HH,
               "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY, "hh4": cv2.STEREO_SGBM_MODE_HH4}


@dataclass(frozen=True)
class MatcherConfig:
    """Matching settings. Disparities in px, window sizes in px.

    num_disparities: search range (multiple of 16); min_disparity: first disparity searched.
    block_size: odd window (0: DEFAULT_BLOCK of the method). uniqueness_ratio: % margin the best
    cost must win by. texture_threshold: bm only, windows with less texture are invalid.
    speckle_window / speckle_range: regions smaller than the window (px) whose disparity varies by
    at most range (px) are removed (window 0: off). prefilter: bm 'xsobel' or 'normalized';
    prefilter_cap clips the prefiltered image. p1 / p2: sgbm smoothness penalties (0: 8 and 32 x
    channels x block^2). disp12_max_diff: sgbm's internal check (-1: off). sgbm_mode: sgbm, hh, 3way,
    hh4. lr_check: compute the right image's disparity too and invalidate pixels whose two
    disparities differ by more than lr_max_diff px. subpixel: keep OpenCV's 1/16 px; False rounds to
    whole px. min_valid_disparity: the range gate, px (see gate_for_range); smaller values are invalid.
    """

    method: Literal["bm", "sgbm"] = "bm"
    num_disparities: int = 64
    min_disparity: int = 0
    block_size: int = 0
    uniqueness_ratio: int = 10
    texture_threshold: int = 10
    speckle_window: int = 100
    speckle_range: int = 2
    prefilter: Literal["xsobel", "normalized"] = "xsobel"
    prefilter_size: int = 9
    prefilter_cap: int = 31
    p1: int = 0
    p2: int = 0
    disp12_max_diff: int = 1
    sgbm_mode: Literal["sgbm", "hh", "3way", "hh4"] = "sgbm"
    lr_check: bool = False
    lr_max_diff: float = 1.0
    subpixel: bool = True
    min_valid_disparity: float = 0.0

    def __post_init__(self) -> None:
        if self.method not in DEFAULT_BLOCK:
            raise BallbotError(f"method: unknown matcher {self.method!r} (bm, sgbm)")
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise BallbotError(f"num_disparities: must be a positive multiple of 16, got {self.num_disparities}")
        b = self.block
        if b < 1 or b % 2 == 0:
            raise BallbotError(f"block_size: must be odd, got {self.block_size}")
        if self.method == "bm" and not 5 <= b <= 255:
            raise BallbotError(f"block_size: block matching needs 5..255, got {b}")
        if self.method == "bm" and (self.prefilter_size % 2 == 0 or not 5 <= self.prefilter_size <= 255):
            raise BallbotError(f"prefilter_size: must be odd in 5..255, got {self.prefilter_size}")
        if not 1 <= self.prefilter_cap <= 63:
            raise BallbotError(f"prefilter_cap: must be in 1..63, got {self.prefilter_cap}")
        if self.p2 and self.p1 and self.p2 <= self.p1:
            raise BallbotError(f"p2 ({self.p2}) must be greater than p1 ({self.p1})")
        if self.lr_max_diff < 0:
            raise BallbotError(f"lr_max_diff: must be >= 0, got {self.lr_max_diff}")

    @property
    def block(self) -> int:
        return self.block_size or DEFAULT_BLOCK[self.method]

    @property
    def invalid_value(self) -> int:
        return (self.min_disparity - 1) * int(SCALE)


def gate_for_range(max_range_m: float | None, focal_px: float, baseline_m: float) -> float:
    """Smallest disparity (px) inside the vision range: d = f * B / Z. None or <= 0: no gate."""
    if not max_range_m or max_range_m <= 0:
        return 0.0
    return focal_px * baseline_m / max_range_m


def _gray(image: np.ndarray) -> np.ndarray:
    if image.dtype != np.uint8:
        raise BallbotError(f"matching needs 8-bit images, got {image.dtype}")
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image


def _create(c: MatcherConfig, min_disparity: int):
    b = c.block
    if c.method == "bm":
        m = cv2.StereoBM_create(numDisparities=c.num_disparities, blockSize=b)
        m.setMinDisparity(min_disparity)
        m.setUniquenessRatio(c.uniqueness_ratio)
        m.setTextureThreshold(c.texture_threshold)
        m.setSpeckleWindowSize(c.speckle_window)
        m.setSpeckleRange(c.speckle_range)
        m.setPreFilterType(cv2.StereoBM_PREFILTER_XSOBEL if c.prefilter == "xsobel"
                           else cv2.StereoBM_PREFILTER_NORMALIZED_RESPONSE)
        m.setPreFilterSize(c.prefilter_size)
        m.setPreFilterCap(c.prefilter_cap)
        m.setDisp12MaxDiff(-1)
        return m
    area = b * b
    return cv2.StereoSGBM_create(minDisparity=min_disparity, numDisparities=c.num_disparities, blockSize=b,
                                 P1=c.p1 or 8 * area, P2=c.p2 or 32 * area, disp12MaxDiff=c.disp12_max_diff,
                                 preFilterCap=c.prefilter_cap, uniquenessRatio=c.uniqueness_ratio,
                                 speckleWindowSize=c.speckle_window, speckleRange=c.speckle_range,
                                 mode=_SGBM_MODES[c.sgbm_mode])


class StereoMatcher:
    """Computes disparity of the left image. Images: (H, W) uint8 or (H, W, 3) BGR, rectified
    (epipolar lines are rows), the same size."""

    def __init__(self, config: MatcherConfig):
        self.config = c = config
        self._m = _create(c, c.min_disparity)
        # The right view's disparity: the same matcher on mirrored images (right becomes "left").
        # Its search starts at -(min + num - 1) mirrored, i.e. the same disparities seen from the right.
        self._mr = _create(c, c.min_disparity) if c.lr_check else None

    def compute(self, left: np.ndarray, right: np.ndarray, min_valid_disparity: float | None = None) -> np.ndarray:
        """-> (H, W) int16, disparity * 16; invalid pixels hold config.invalid_value.
        min_valid_disparity (px) overrides the config's range gate for this pair."""
        if left.shape != right.shape:
            raise BallbotError(f"left {left.shape} and right {right.shape} images differ in size")
        c = self.config
        gl, gr = _gray(left), _gray(right)
        d = self._m.compute(gl, gr)
        invalid = d < c.min_disparity * SCALE  # OpenCV marks failures below min_disparity*16
        if self._mr is not None:
            invalid |= ~self._consistent(d, gl, gr)
        gate = c.min_valid_disparity if min_valid_disparity is None else min_valid_disparity
        if gate > 0:
            invalid |= d < gate * SCALE
        if not c.subpixel:
            d = ((d.astype(np.int32) + 8) // 16 * 16).astype(np.int16)
        d[invalid] = c.invalid_value
        return d

    def _consistent(self, d: np.ndarray, gl: np.ndarray, gr: np.ndarray) -> np.ndarray:
        """True where the left disparity at x agrees with the right disparity at x - d."""
        c = self.config
        dr = self._mr.compute(np.ascontiguousarray(gr[:, ::-1]), np.ascontiguousarray(gl[:, ::-1]))[:, ::-1]
        h, w = d.shape
        xs = np.arange(w, dtype=np.int32)[None, :]
        xr = xs - ((d.astype(np.int32) + 8) >> 4)  # round(d) in px
        inside = (xr >= 0) & (d >= 0)
        xr = np.clip(xr, 0, w - 1)
        dr_at = np.take_along_axis(dr, xr, axis=1)
        ok = inside & (dr_at >= c.min_disparity * SCALE)
        ok &= np.abs(d.astype(np.int32) - dr_at.astype(np.int32)) <= c.lr_max_diff * SCALE
        return ok


def to_float(raw: np.ndarray, scale: float, invalid_value: float) -> np.ndarray:
    """Fixed-point disparity -> float32 px with NaN where invalid."""
    d = raw.astype(np.float32) / np.float32(scale)
    d[raw == invalid_value] = np.nan
    return d


def half_resolution(config: MatcherConfig) -> MatcherConfig:
    """The same settings for images of half the width and height (the cheap onboard fallback)."""
    nd = max(16, -(-config.num_disparities // 2 // 16) * 16)
    block = config.block // 2 | 1
    if config.method == "bm":
        block = max(5, block)
    return replace(config, num_disparities=nd, min_disparity=config.min_disparity // 2, block_size=block,
                   speckle_window=config.speckle_window // 4, min_valid_disparity=config.min_valid_disparity / 2)


class HalfResolutionMatcher:
    """Matches at half width and height, then returns a full-size map in full-resolution pixels
    (values doubled, nearest-neighbour upsampled), so consumers see the same contract."""

    def __init__(self, config: MatcherConfig):
        self.config = config
        self._inner = StereoMatcher(half_resolution(config))

    def compute(self, left: np.ndarray, right: np.ndarray, min_valid_disparity: float | None = None) -> np.ndarray:
        if left.shape != right.shape:
            raise BallbotError(f"left {left.shape} and right {right.shape} images differ in size")
        h, w = left.shape[:2]
        small = [cv2.resize(_gray(x), (w // 2, h // 2), interpolation=cv2.INTER_AREA) for x in (left, right)]
        gate = None if min_valid_disparity is None else min_valid_disparity / 2
        d = self._inner.compute(small[0], small[1], gate)
        invalid = d == self._inner.config.invalid_value
        out = (d.astype(np.int32) * 2).clip(-32768, 32767).astype(np.int16)
        out[invalid] = self.config.invalid_value
        return cv2.resize(out, (w, h), interpolation=cv2.INTER_NEAREST)


def make_matcher(config: MatcherConfig, scale: float = 1.0):
    """scale 1: full resolution; 0.5: HalfResolutionMatcher."""
    if scale == 1.0:
        return StereoMatcher(config)
    if scale == 0.5:
        return HalfResolutionMatcher(config)
    raise BallbotError(f"scale: 1.0 or 0.5, got {scale}")
