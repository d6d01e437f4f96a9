"""Fixed-point disparity maps as they travel (DisparityMap): shared by producers and consumers.

A map is (H, W) integers with disparity_px = value / scale, and one explicit `invalid_value` for
pixels without a measurement. Consumers turn it into float px with NaN where invalid, so invalid
pixels are masked explicitly rather than hidden behind an epsilon.

A map also states the range its matcher searched (min_disparity, num_disparities). A value outside
it, and a NaN or an infinity, is no measurement a matcher made: it is an invalid pixel, never a
depth (a buggy or hostile producer must not turn "unmeasured" into "far away" or "right here").
"""
from __future__ import annotations

import functools
import math
import statistics

import cv2
import numpy as np


def searched_range(min_disparity: float, num_disparities: float) -> tuple[float, float]:
    """(lowest, highest) disparity in px a matcher searching this range can give, subpixel included."""
    return float(min_disparity), float(min_disparity + num_disparities)


# A matcher's confidence (uint8, where it gives one): 0 = no measurement, 255 = certain; from this
# value on, the pixel was measured; below it, filled in from measured ones around it (dense's fill)
MEASURED_CONFIDENCE = 128
_BEYOND = 2**31  # past every value of a map's integer type: the bound an infinite one stands for


def raw_at_least(x: float) -> int:
    """The smallest integer >= x: `raw >= x` as `raw >= raw_at_least(x)` (and `raw < x` as
    `raw < raw_at_least(x)`) on an integer map compares in the map's own type; a float scalar
    casts every pixel to float64 first (0.12 ms against 0.02 at 640x480). An infinite x (a range
    gate of a vanishing range) selects as it would: all or nothing."""
    return math.ceil(x) if math.isfinite(x) else _infinite(x)


def raw_at_most(x: float) -> int:
    """The largest integer <= x: `raw <= x` as `raw <= raw_at_most(x)` on an integer map."""
    return math.floor(x) if math.isfinite(x) else _infinite(x)


def _infinite(x: float) -> int:
    if math.isnan(x):
        raise ValueError("a NaN bound selects no pixel either way: no integer stands for it")
    return _BEYOND if x > 0 else -_BEYOND


def to_float(raw: np.ndarray, scale: float, invalid_value: float,
             valid_range: tuple[float, float] | None = None) -> np.ndarray:
    """(H, W) fixed-point disparity -> (H, W) float32 px, NaN where raw == invalid_value, where
    it is not finite and, with valid_range (lo, hi) px, where it lies outside [lo, hi]."""
    d = raw.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        np.divide(d, np.float32(scale), out=d)  # a scale too small for float32 gives inf: masked
        # integers scaled by a finite divisor stay finite when the largest of their type does:
        # the full-image isfinite pass is then known to find nothing
        finite = raw.dtype.kind in "iu" and bool(np.isfinite(_largest_float32(raw.dtype) / np.float32(scale)))
    interval = None
    if finite and valid_range is not None and raw.ndim == 2 and raw.size and raw.flags.c_contiguous:
        interval = _valid_interval(raw.dtype, float(scale), (float(valid_range[0]), float(valid_range[1])))
    if interval is not None:
        # the valid raw values are one interval (d grows monotonically with raw): two integer
        # bounds on the raw map replace the float comparisons (~0.4 ms at 640x480)
        lo, hi = interval
        ok = cv2.inRange(raw, lo, hi) if lo <= hi else np.zeros(raw.shape, np.uint8)
        if lo <= invalid_value <= hi and float(invalid_value).is_integer():
            ok[raw == invalid_value] = 0
        np.copyto(d, np.float32(np.nan), where=ok == 0)
        return d
    bad = raw == invalid_value
    if not finite:
        bad |= ~np.isfinite(d)
    if valid_range is not None:
        with np.errstate(invalid="ignore"):
            bad |= d < valid_range[0]
            bad |= d > valid_range[1]
    np.copyto(d, np.float32(np.nan), where=bad)
    return d


@functools.lru_cache(maxsize=16)
def _valid_interval(dtype: np.dtype, scale: float, valid_range: tuple[float, float]) -> tuple[int, int] | None:
    """(lo, hi) inclusive: the raw values of this 8/16-bit integer type whose disparity (computed as
    to_float does) lies in valid_range; None when they are no single interval or the type is wider."""
    if dtype.kind not in "iu" or dtype.itemsize > 2:
        return None
    info = np.iinfo(dtype)
    vals = np.arange(int(info.min), int(info.max) + 1).astype(dtype)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        d = vals.astype(np.float32) / np.float32(scale)
        inside = np.flatnonzero(np.isfinite(d) & (d >= valid_range[0]) & (d <= valid_range[1]))
    if not inside.size:
        return 1, 0  # none valid
    if inside[-1] - inside[0] + 1 != inside.size:
        return None
    return int(vals[inside[0]]), int(vals[inside[-1]])


def _largest_float32(dtype: np.dtype) -> np.float32:
    info = np.iinfo(dtype)
    return np.float32(max(-int(info.min), int(info.max)))


class RecentValid:
    """The valid fraction of the maps of the last `window_s` seconds, to tell a map that measured
    far less than the ones before it ("collapsed": below `factor` x their median) from a scene that
    simply offers less. Judged only once `min_frames` maps are known (warm-up); a lasting change
    becomes the new normal once it fills half the window. Times in s on any clock that does not go
    backwards (older entries are dropped by it)."""

    def __init__(self, window_s: float = 2.0, factor: float = 0.5, min_frames: int = 5):
        from collections import deque

        self.window_s, self.factor, self.min_frames = window_s, factor, min_frames
        self._recent: deque[tuple[float, float]] = deque()

    def median(self, now_s: float) -> float | None:
        """Median valid fraction of the window ending at now_s; None during the warm-up."""
        while self._recent and self._recent[0][0] < now_s - self.window_s:
            self._recent.popleft()
        if len(self._recent) < self.min_frames:
            return None
        return float(statistics.median(v for _, v in self._recent))  # np.median's array costs ~0.2 ms here

    def collapsed(self, valid_fraction: float, now_s: float) -> bool:
        m = self.median(now_s)
        return m is not None and valid_fraction < self.factor * m

    def add(self, valid_fraction: float, now_s: float) -> None:
        if self._recent and now_s < self._recent[-1][0]:
            self._recent.clear()  # a clock that went back (a replayed sequence starting over)
        self._recent.append((now_s, valid_fraction))


class FrozenInput:
    """Whether the maps have stopped changing. A camera whose driver hangs (a USB glitch, a driver
    republishing its last buffer) goes on delivering its last picture with fresh stamps, and every
    map of it is the same, bit for bit, while a live camera's noise never gives two equal maps.
    frozen(map, now_s) is True once the map has equalled one of the last `keep` distinct maps (a
    driver may cycle through a few buffers) for longer than `after_s`. Maps are compared on every
    `row_step`-th row: noise tells them apart there as well as anywhere, at an eighth of the cost.
    Times in s on any clock that does not go backwards."""

    def __init__(self, after_s: float, keep: int = 3, row_step: int = 8):
        from collections import deque

        self.after_s, self.row_step = after_s, row_step
        self._recent: deque[bytes] = deque(maxlen=keep)
        self._changed_s: float | None = None  # when the map last differed from every recent one

    def frozen(self, disparity: np.ndarray, now_s: float) -> bool:
        # the bytes, shape and type included: one picture gives the same bits, NaNs too, and comparing
        # bytes stops at the first that differs (a live map's first row)
        a = np.ascontiguousarray(disparity[::self.row_step])
        sample = f"{a.shape}{a.dtype}".encode() + a.tobytes()
        same = any(s == sample for s in self._recent)
        if not same or self._changed_s is None or now_s < self._changed_s:
            self._changed_s = now_s
            self._recent.append(sample)
            return False
        return now_s - self._changed_s > self.after_s
