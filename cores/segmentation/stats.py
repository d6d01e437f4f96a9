"""np.percentile (method "linear") and np.median of NaN-free 1-D arrays, and of (n, k) arrays along
axis 0, with the same values to the last bit at a fraction of the cost.

The segmenter takes a dozen order statistics of a few thousand points per object and frame; numpy's
own functions spend most of their time in argument handling around one np.partition. These do the
partition and numpy's interpolation (_lerp: a + (b - a) t, or b - (b - a)(1 - t) for t >= 0.5) in
the same dtypes: a list of percentiles interpolates in float64, one Python number (weak, NEP 50)
in the array's own dtype. tests/test_segmenter_stats.py holds them to numpy's results.
"""
from __future__ import annotations

import numpy as np


def percentile(a: np.ndarray, q: float | list[float]):
    """np.percentile(a, q, axis=0) for a NaN-free a of at least one row (q: one number or a list)."""
    n = a.shape[0]
    weak = type(q) in (int, float)
    qs = np.true_divide(q, 100, out=...)
    virtual = (n - 1) * qs  # float64, as numpy's
    prev = np.floor(virtual)
    top = virtual >= n - 1
    prev_i = np.where(top, n - 1, prev).astype(np.intp)
    next_i = np.where(top, n - 1, prev + 1).astype(np.intp)
    part = np.partition(a, np.unique(np.concatenate((prev_i.ravel(), next_i.ravel()))), axis=0)
    lo, hi = part[prev_i], part[next_i]
    # numpy's gamma: against the index -1 where the position is the last one (its lerp then gives hi)
    t = virtual - np.where(top, -1.0, prev)
    if weak:
        t = float(t)
    elif a.ndim > 1:
        t = t.reshape(t.shape + (1,) * (a.ndim - 1))
    diff = hi - lo
    out = lo + diff * t
    return np.where(np.asarray(t) >= 0.5, hi - diff * (1 - t), out)[()] if not weak else \
        (hi - diff * (1 - t) if t >= 0.5 else out)


def median(a: np.ndarray):
    """np.median of a NaN-free 1-D array (the mean of the middle two, in the array's dtype)."""
    n = a.size
    h = n // 2
    if n % 2:
        return np.partition(a, h)[h] / 1
    part = np.partition(a, (h - 1, h))
    return (part[h - 1] + part[h]) / 2
