"""Disparity cores: OpenCV block matching (SAD, the thesis's method) and semi-global matching, with
an optional left-right consistency check, subpixel output and a vision-range gate. No Zenoh here:
the service (main.py, pool.py), the offline `disparity` command and the benchmarks share this.

Output convention everywhere: int16 fixed point, disparity_px = value / 16 (OpenCV's 4 fractional
bits), and INVALID (= (min_disparity - 1) * 16) where no match was accepted
(common.disparity.to_float turns it into float px with NaN where invalid).

The settings are config.MatcherConfig (the disparity service's settings extend it); the cores take
either directly.
"""
from __future__ import annotations

import cv2
import numpy as np

from ...common.errors import BallbotError
from .config import DEFAULT_BLOCK, SCALE, MatcherConfig, gate_for_range  # noqa: F401 (the cores' API)

_SGBM_MODES = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "hh": cv2.STEREO_SGBM_MODE_HH,
               "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY, "hh4": cv2.STEREO_SGBM_MODE_HH4}


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

    def compute(self, left: np.ndarray, right: np.ndarray, min_valid_disparity: float = 0.0) -> np.ndarray:
        """-> (H, W) int16, disparity * 16; invalid pixels hold config.invalid_value.
        min_valid_disparity: the range gate for this pair, px (gate_for_range(config.max_range_m, f, B)
        for its camera); smaller disparities are invalid. 0: no gate."""
        if left.shape != right.shape:
            raise BallbotError(f"left {left.shape} and right {right.shape} images differ in size")
        c = self.config
        gl, gr = _gray(left), _gray(right)
        d = self._m.compute(gl, gr)
        invalid = d < c.min_disparity * SCALE  # OpenCV marks failures below min_disparity*16
        if self._mr is not None:
            invalid |= ~self._consistent(d, gl, gr)
        if min_valid_disparity > 0:
            invalid |= d < min_valid_disparity * SCALE
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


def half_resolution(config: MatcherConfig) -> MatcherConfig:
    """The same settings for images of half the width and height (the cheap onboard fallback)."""
    nd = max(16, -(-config.num_disparities // 2 // 16) * 16)
    block = config.block // 2 | 1
    if config.method == "bm":
        block = max(5, block)
    return config.model_copy(update=dict(num_disparities=nd, min_disparity=config.min_disparity // 2,
                                         block_size=block, speckle_window=config.speckle_window // 4))


class HalfResolutionMatcher:
    """Matches at half width and height, then returns a full-size map in full-resolution pixels
    (values doubled, nearest-neighbour upsampled), so consumers see the same contract."""

    def __init__(self, config: MatcherConfig):
        self.config = config
        self._inner = StereoMatcher(half_resolution(config))

    def compute(self, left: np.ndarray, right: np.ndarray, min_valid_disparity: float = 0.0) -> np.ndarray:
        if left.shape != right.shape:
            raise BallbotError(f"left {left.shape} and right {right.shape} images differ in size")
        h, w = left.shape[:2]
        small = [cv2.resize(_gray(x), (w // 2, h // 2), interpolation=cv2.INTER_AREA) for x in (left, right)]
        d = self._inner.compute(small[0], small[1], min_valid_disparity / 2)
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
