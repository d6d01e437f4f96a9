"""OpenCV's matchers built from the settings (the one place their parameters are set) and the pieces
every method shares: a pair's Match, grey conversion, the search-range saturation measure."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.errors import BallbotError
from cores.matching.config import SATURATION_WARN, SCALE, TOP_BAND_PX, MatcherConfig
from cores.matching.disparity import raw_at_least

_SGBM_MODES = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "hh": cv2.STEREO_SGBM_MODE_HH,
               "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY, "hh4": cv2.STEREO_SGBM_MODE_HH4}


@dataclass
class Match:
    """One pair's result. disparity: (H, W) int16, px * 16, config.invalid_value where invalid;
    confidence: (H, W) uint8 (0 = no measurement, 255 = certain) or None if the method gives none;
    saturated: share of the measured pixels within TOP_BAND_PX of the largest disparity searched
    (above SATURATION_WARN: nearer things exist than the range covers); flat: (H, W) bool, the
    pixels whose window holds too little texture to have decided their own match (sgbm, which
    carries disparities into them from around them; None: the method says nothing of it)."""

    disparity: np.ndarray
    confidence: np.ndarray | None
    saturated: float
    flat: np.ndarray | None = None

    @property
    def range_warning(self) -> str:
        if self.saturated <= SATURATION_WARN:
            return ""
        return (f"{self.saturated:.1%} of the matched pixels sit at the top of the disparity search range: "
                "something is nearer than the range reaches; raise num_disparities (or num_disparities auto "
                "with a smaller min_range_m)")


def saturated_share(raw: np.ndarray, valid: np.ndarray, max_disparity: float) -> float:
    """Share of `valid` pixels of raw (int16 px * 16) within TOP_BAND_PX of max_disparity (px)."""
    n = int(np.count_nonzero(valid))
    if not n:
        return 0.0
    return float(np.count_nonzero(valid & (raw >= raw_at_least((max_disparity - TOP_BAND_PX) * SCALE))) / n)


def gray(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) BGR uint8 -> (H, W) uint8."""
    if image.dtype != np.uint8:
        raise BallbotError(f"matching needs 8-bit images, got {image.dtype}")
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image


def texture(gray_image: np.ndarray, window: int) -> np.ndarray:
    """(H, W) uint8 -> (H, W) float32: the horizontal gradient (3x3 Sobel / 4: twice the grey levels a
    pixel of a ramp) averaged over a window x window square. Matching lives on horizontal gradients;
    where there are none, any disparity fits equally well."""
    gx = np.abs(cv2.Sobel(gray_image, cv2.CV_32F, 1, 0, ksize=3)) * np.float32(0.25)
    return cv2.boxFilter(gx, -1, (window, window))


def compute_padded(matcher, gray_left: np.ndarray, gray_right: np.ndarray, pad: int) -> np.ndarray:
    """matcher.compute on the pair padded on the left by `pad` replicated columns, cropped back to
    the pair: OpenCV leaves x < min + num disparities unmatched; padded by that much, the band is
    matched too (dense always; bm and sgbm with match_band). Drop what reached into the padding
    with reaches_padding."""
    if not pad:
        return matcher.compute(gray_left, gray_right)
    return matcher.compute(cv2.copyMakeBorder(gray_left, 0, 0, pad, 0, cv2.BORDER_REPLICATE),
                           cv2.copyMakeBorder(gray_right, 0, 0, pad, 0, cv2.BORDER_REPLICATE))[:, pad:]


def reaches_padding(raw: np.ndarray, block: int, pad: int) -> np.ndarray:
    """(H, min(W, pad + block // 2)) bool: the left columns' matches (raw, px * 16) whose partner's
    window reaches into the padding of compute_padded (d > x - block // 2): they compared against
    nothing real. Right of those columns no disparity searched reaches it."""
    w = min(raw.shape[1], pad + block // 2)
    return raw[:, :w].astype(np.int32) > (np.arange(w, dtype=np.int32) - block // 2) * int(SCALE)


def create_sgbm(c: MatcherConfig):
    """OpenCV's StereoSGBM with these settings (penalties default to the recommended 8 and 32 x block^2)."""
    b = c.block
    area = b * b
    return cv2.StereoSGBM.create(minDisparity=c.min_disparity, numDisparities=c.fixed_num_disparities, blockSize=b,
                                 P1=c.p1 or 8 * area, P2=c.p2 or 32 * area, disp12MaxDiff=c.disp12_max_diff,
                                 preFilterCap=c.prefilter_cap, uniquenessRatio=c.uniqueness_ratio,
                                 speckleWindowSize=c.speckle_window, speckleRange=c.speckle_range,
                                 mode=_SGBM_MODES[c.mode])


def create_opencv_matcher(c: MatcherConfig):
    """OpenCV's StereoBM or StereoSGBM with these settings: the one place their parameters are set."""
    if c.method != "bm":
        return create_sgbm(c)
    m = cv2.StereoBM.create(numDisparities=c.fixed_num_disparities, blockSize=c.block)
    m.setMinDisparity(c.min_disparity)
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
