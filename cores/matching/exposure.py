"""Exposure: the right image brought to the left one's grey levels before matching.

Two cameras with their own auto exposure (two USB cameras, the usual low-cost rig) see one scene at
different brightness. Block matching's x-Sobel prefilter drops an offset but not a gain, and
semi-global matching's costs see both: on the street (karlsruhe) with the right image 1.6 times
brighter (+10 grey levels) sgbm measured a third of the image where it had measured two thirds, a
confirmed phantom stood 4.7 m ahead in the middle of the road, and no list said anything (the share
measured was low from the start, so nothing had collapsed). The two views hold nearly the same
scene, so their grey-level distributions agree but for the cameras' response: the right image's
quartiles are mapped onto the left's by a gain and an offset. A pair whose quartiles agree within
TOLERANCE grey levels passes untouched, so a rig with matched exposure computes what it always did.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cores.matching.opencv import gray

QUANTILES = (0.25, 0.5, 0.75)
# grey levels the mapping must move a quartile by to be applied: the two views' different content moves
# them up to 13 on a rig with matched exposure (karlsruhe, 40 pairs); EuRoC's darker right camera, 25
TOLERANCE = 16.0
# gains outside this are no exposure difference (a covered or blinded lens): left alone, for rectify's
# view-blocked (texture under a quarter of the other camera's) and the valid-share checks to see. Two
# stops (a quarter) are an auto exposure's: the range had ended at 0.4 and 2.5, and the street with the
# right camera at a quarter of its light was matched unequalized: sgbm listed half as many again, kept
# 71 % of what it lists in daylight within 15 m, and 11 of 14 lists said nothing (equalized: 90 %)
GAIN_RANGE = (0.2, 5.0)
MIN_SPREAD = 4.0  # grey levels between the quartiles: less is a blank image, nothing to map from


@dataclass(frozen=True)
class Exposure:
    """The map applied to the right image: right' = gain * right + offset (1, 0: untouched)."""

    gain: float = 1.0
    offset: float = 0.0

    @property
    def applied(self) -> bool:
        return (self.gain, self.offset) != (1.0, 0.0)


def quartiles(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 -> its QUANTILES, grey levels (from the histogram: one pass, no sort)."""
    hist = cv2.calcHist([image], [0], None, [256], [0, 256]).ravel()
    cdf = np.cumsum(hist) / max(float(hist.sum()), 1.0)
    return np.searchsorted(cdf, QUANTILES).astype(np.float64)


def estimate(left: np.ndarray, right: np.ndarray) -> Exposure:
    """The gain and offset that bring right's quartiles onto left's; Exposure() where they agree
    within TOLERANCE or cannot be told (a blank image, a gain outside GAIN_RANGE)."""
    ql, qr = quartiles(gray(left)), quartiles(gray(right))
    spread = qr[2] - qr[0]
    if spread < MIN_SPREAD or ql[2] - ql[0] < MIN_SPREAD:
        return Exposure()
    gain = float((ql[2] - ql[0]) / spread)
    offset = float(ql[1] - gain * qr[1])
    if not GAIN_RANGE[0] <= gain <= GAIN_RANGE[1] or np.abs(gain * qr + offset - qr).max() <= TOLERANCE:
        return Exposure()
    return Exposure(gain, offset)


def equalize(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, Exposure]:
    """(right mapped onto left's grey levels, or right itself; the map used)."""
    e = estimate(left, right)
    if not e.applied:
        return right, e
    return cv2.convertScaleAbs(right, alpha=e.gain, beta=e.offset), e
