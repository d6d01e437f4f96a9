"""Disparity cores: OpenCV block matching (SAD, the thesis's method) and semi-global matching.

Output convention everywhere: int16 fixed point, disparity_px = value / 16 (OpenCV's), and
INVALID (= (min_disparity - 1) * 16) where no match was accepted. `to_float` masks invalid
pixels as NaN explicitly rather than hiding them behind an epsilon.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from ...common.errors import BallbotError

SCALE = 16.0


@dataclass(frozen=True)
class MatcherConfig:
    method: Literal["bm", "sgbm"] = "bm"
    num_disparities: int = 64
    min_disparity: int = 0
    block_size: int = 15
    uniqueness_ratio: int = 10
    texture_threshold: int = 10
    speckle_window: int = 100
    speckle_range: int = 2
    prefilter_cap: int = 31
    p1: int = 0  # sgbm; 0 = 8 * block_size^2
    p2: int = 0  # sgbm; 0 = 32 * block_size^2

    def __post_init__(self) -> None:
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise BallbotError(f"num_disparities: must be a positive multiple of 16, got {self.num_disparities}")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise BallbotError(f"block_size: must be odd, got {self.block_size}")
        if self.method == "bm" and not 5 <= self.block_size <= 255:
            raise BallbotError(f"block_size: block matching needs 5..255, got {self.block_size}")

    @property
    def invalid_value(self) -> int:
        return (self.min_disparity - 1) * int(SCALE)


def _gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        raise BallbotError(f"matching needs 8-bit images, got {image.dtype}")
    return image


class StereoMatcher:
    """Computes disparity of the left image. Images: (H, W) uint8 or (H, W, 3) BGR, rectified."""

    def __init__(self, config: MatcherConfig):
        self.config = c = config
        if c.method == "bm":
            m = cv2.StereoBM_create(numDisparities=c.num_disparities, blockSize=c.block_size)
            m.setMinDisparity(c.min_disparity)
            m.setUniquenessRatio(c.uniqueness_ratio)
            m.setTextureThreshold(c.texture_threshold)
            m.setSpeckleWindowSize(c.speckle_window)
            m.setSpeckleRange(c.speckle_range)
            m.setPreFilterCap(c.prefilter_cap)
        elif c.method == "sgbm":
            area = c.block_size * c.block_size
            m = cv2.StereoSGBM_create(minDisparity=c.min_disparity, numDisparities=c.num_disparities,
                                      blockSize=c.block_size, P1=c.p1 or 8 * area, P2=c.p2 or 32 * area,
                                      disp12MaxDiff=1, preFilterCap=c.prefilter_cap,
                                      uniquenessRatio=c.uniqueness_ratio, speckleWindowSize=c.speckle_window,
                                      speckleRange=c.speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM)
        else:
            raise BallbotError(f"method: unknown matcher {c.method!r} (bm, sgbm)")
        self._m = m

    def compute(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """-> (H, W) int16, disparity * 16; invalid pixels hold config.invalid_value."""
        if left.shape != right.shape:
            raise BallbotError(f"left {left.shape} and right {right.shape} images differ in size")
        d = self._m.compute(_gray(left), _gray(right))
        # OpenCV marks failures with values below min_disparity*16; make them one explicit value.
        d[d < self.config.min_disparity * SCALE] = self.config.invalid_value
        return d


def to_float(raw: np.ndarray, scale: float, invalid_value: float) -> np.ndarray:
    """Fixed-point disparity -> float32 px with NaN where invalid."""
    d = raw.astype(np.float32) / np.float32(scale)
    d[raw == invalid_value] = np.nan
    return d
