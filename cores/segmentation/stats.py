"""np.percentile (method "linear") and np.median of NaN-free 1-D arrays, and of (n, k) arrays along
axis 0, with the same values to the last bit at a fraction of the cost.

The segmenter takes a dozen order statistics of a few thousand points per object and frame; numpy's
own functions spend most of their time in argument handling around one np.partition. These do the
partition and numpy's interpolation (_lerp: a + (b - a) t, or b - (b - a)(1 - t) for t >= 0.5) in
the same dtypes: a list of percentiles interpolates in float64, one Python number (weak, NEP 50)
in the array's own dtype. tests/test_segmenter_stats.py holds them to numpy's results.
"""
from __future__ import annotations

import math

import numpy as np


def percentile(a: np.ndarray, q: float | list[float]):
    """np.percentile(a, q, axis=0) for a NaN-free a of at least one row (q: a Python number or a list)."""
    n = a.shape[0]
    weak = type(q) in (int, float)  # numpy's rule (a numpy scalar is no Python number)
    qs: list[float] = [q] if isinstance(q, (int, float)) else q
    at = []  # per percentile: (the index below, above, and numpy's gamma) as numpy computes them
    for x in qs:
        virtual = (n - 1) * (x / 100)  # the float64 operations of numpy's
        if virtual >= n - 1:
            at.append((n - 1, n - 1, virtual + 1))  # numpy's gamma against the index -1: lerp gives hi
        else:
            k = math.floor(virtual)
            at.append((k, k + 1, virtual - k))
    kth = sorted({i for lo_hi in at for i in lo_hi[:2]})
    # the columns of an (n, k) array partitioned as rows of its contiguous transpose: the same order
    # statistics, several times faster than along a strided axis 0
    part = np.partition(a, kth) if a.ndim == 1 else np.partition(np.ascontiguousarray(a.T), kth, axis=1).T
    out = []
    for k0, k1, gamma in at:
        lo, hi = part[k0], part[k1]
        t = gamma if weak else np.float64(gamma)  # one Python number interpolates in a's dtype
        diff = hi - lo
        out.append(hi - diff * (1 - t) if gamma >= 0.5 else lo + diff * t)
    return out[0] if weak else np.array(out)


def median(a: np.ndarray):
    """np.median of a NaN-free 1-D array (the mean of the middle two, in the array's dtype)."""
    n = a.size
    h = n // 2
    if n % 2:
        return np.partition(a, h)[h] / 1
    part = np.partition(a, (h - 1, h))
    return (part[h - 1] + part[h]) / 2


def mean0(a: np.ndarray) -> np.ndarray:
    """a.mean(0) of an (n, k) float64 array: numpy sums down axis 0 row by row, and so does einsum,
    several times faster for a few columns (tests/test_segmenter_stats.py holds the two equal)."""
    return np.einsum("ij->j", a) / a.shape[0]
