"""Fixed-point disparity maps as they travel (DisparityMap): shared by producers and consumers.

A map is (H, W) integers with disparity_px = value / scale, and one explicit `invalid_value` for
pixels without a measurement. Consumers turn it into float px with NaN where invalid, so invalid
pixels are masked explicitly rather than hidden behind an epsilon.
"""
from __future__ import annotations

import numpy as np


def to_float(raw: np.ndarray, scale: float, invalid_value: float) -> np.ndarray:
    """(H, W) fixed-point disparity -> (H, W) float32 px, NaN where raw == invalid_value."""
    d = raw.astype(np.float32) / np.float32(scale)
    d[raw == invalid_value] = np.nan
    return d
