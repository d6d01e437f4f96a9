"""`dense`: a disparity and a confidence for every pixel, for offboard workers.

1. Semi-global matching (OpenCV's StereoSGBM, 3-way by default, the recommended penalties
   P1 = 8 w^2, P2 = 32 w^2 on grey images) with its own checks: left-right consistency
   (disp12_max_diff), uniqueness, speckles, and a texture floor (a window without horizontal
   gradient holds nothing to match, whatever SGBM says). The pair is padded on the left by the search range
   first, so the band x < max disparity that OpenCV leaves invalid is matched wherever its partner
   is in view (matches whose partner would lie in the padding are discarded).
2. Edge-aware filling: the fast global smoother (Min et al., "Fast global image smoothing based on
   weighted least squares", TIP 2014; the filter behind OpenCV-contrib's DisparityWLSFilter) spreads
   the measured disparities along the left image, weighted by validity, so fills stop at intensity
   edges: filled = FGS(c * d) / FGS(c). Each pass is one tridiagonal solve per row or column
   (LAPACK via scipy), at half resolution: holes are filled from far away, and measured pixels keep
   their own sub-pixel value. Regions walled in by strong edges without any measurement inside take
   the background (farther) neighbour's value along their row (background_fill).
3. Confidence (uint8): measured pixels 128..255 by how well they agree with the measured pixels
   around them (local_agreement) and their texture; filled pixels 1..127 by the share of measured support reaching
   them; 0 (and an invalid disparity) only where no measurement reaches at all.
"""
from __future__ import annotations

import cv2
import numpy as np
from scipy.linalg import solveh_banded

from common.errors import BallbotError
from cores.matching.config import SCALE, MatcherConfig
from cores.matching.disparity import MEASURED_CONFIDENCE, raw_at_least
from cores.matching.opencv import Match, compute_padded, create_sgbm, gray, reaches_padding, saturated_share, texture

FILL_SCALE = 0.5  # the smoother runs at this fraction of the image size
# One row+column pass of the smoother (lambda_1 = lambda / 2 in Min et al.'s schedule): on the
# Middlebury pairs as good as their three (bad-2 8.8 vs 9.0 %, 8.2 vs 8.3 %) at half the time.
FILL_ITERATIONS = 1
FLAT = 0.5  # mean |horizontal gradient| (grey levels / px) below which a window holds nothing to match
TEXTURE = 1.0  # ... at which a match keeps ~63 % of its confidence above 128 (a faint texture)
AGREE_WINDOW = 5  # px: the neighbourhood a measured pixel's confidence is judged in
AGREE_PX = 1.0  # a disparity spread (std) of this much around a measured pixel: confidence ~ 128 + 127/e


def edge_weights(guide: np.ndarray, sigma_color: float) -> tuple[np.ndarray, np.ndarray]:
    """guide: (H, W) or (H, W, C) image, 0..255. -> (H, W-1) weights between horizontal neighbours
    and (H-1, W) between vertical ones: exp(-|I_p - I_q| / sigma_color), colour distance in L2."""
    g = guide.astype(np.float32)
    if g.ndim == 2:
        g = g[..., None]
    dx = np.sqrt(((g[:, 1:] - g[:, :-1]) ** 2).sum(-1))
    dy = np.sqrt(((g[1:] - g[:-1]) ** 2).sum(-1))
    return np.exp(-dx / sigma_color), np.exp(-dy / sigma_color)


def _smooth_rows(f: np.ndarray, w: np.ndarray, lam: float) -> np.ndarray:
    """Solves (I + lam * L_w) u = f along every row at once. f: (H, W, K); w: (H, W-1) weights
    between x and x+1. The rows are chained into one symmetric tridiagonal system whose coupling
    between one row's end and the next row's start is zero."""
    h, wd, k = f.shape
    a = lam * w.astype(np.float64)
    diag = np.ones((h, wd))
    diag[:, 1:] += a
    diag[:, :-1] += a
    upper = np.zeros((h, wd))
    upper[:, 1:] = -a  # banded upper form: ab[0, j] = A[j - 1, j]
    ab = np.stack([upper.ravel(), diag.ravel()])
    u = solveh_banded(ab, f.reshape(h * wd, k), overwrite_ab=True, check_finite=False)
    return u.reshape(h, wd, k)


def fast_global_smoother(f: np.ndarray, guide: np.ndarray, lam: float, sigma_color: float,
                         iterations: int = 3) -> np.ndarray:
    """f: (H, W, K) float channels smoothed together; guide: (H, W[, C]) uint8, the same size.
    Alternating row and column passes with the decreasing lambda schedule of Min et al."""
    wx, wy = edge_weights(guide, sigma_color)
    u = f.astype(np.float64)
    for t in range(iterations):
        lam_t = 1.5 * 4.0 ** (iterations - t - 1) / (4.0 ** iterations - 1) * lam
        u = _smooth_rows(u, wx, lam_t)
        u = _smooth_rows(u.transpose(1, 0, 2).copy(), np.ascontiguousarray(wy.T), lam_t).transpose(1, 0, 2)
    return u


def background_fill(d: np.ndarray) -> np.ndarray:
    """(H, W) float32 with NaN holes -> holes take the smaller (farther) of the nearest values left
    and right on their row (KITTI's background interpolation), then of those above and below where
    a whole row is empty. NaN stays only if d has no value at all."""
    out = d.copy()
    for a in (out, out.T):  # rows, then columns (a view: writes go to out)
        known = np.isfinite(a)
        idx = np.arange(a.shape[1])[None, :]
        left = np.maximum.accumulate(np.where(known, idx, -1), axis=1)
        right = np.minimum.accumulate(np.where(known, idx, a.shape[1])[:, ::-1], axis=1)[:, ::-1]
        rows = np.arange(a.shape[0])[:, None]
        vl = np.where(left >= 0, a[rows, np.clip(left, 0, None)], np.nan)
        vr = np.where(right < a.shape[1], a[rows, np.clip(right, None, a.shape[1] - 1)], np.nan)
        a[~known] = np.fmin(vl, vr)[~known]
    return out


def local_agreement(d: np.ndarray, c: np.ndarray) -> np.ndarray:
    """How much a measured pixel agrees with the measured pixels around it (AGREE_WINDOW px square),
    0..1: the share of them that are measured, times exp(-their disparity spread / AGREE_PX). Low at
    depth edges (where matching fattens the foreground) and for isolated matches; a slanted but smooth
    surface keeps a high value. d: (H, W) float32 px; c: (H, W) float32 1 = measured, 0 = not."""
    k = (AGREE_WINDOW, AGREE_WINDOW)
    dc = np.where(c > 0, d, 0).astype(np.float32)
    n = cv2.boxFilter(c, -1, k)
    m1 = cv2.boxFilter(dc, -1, k)
    m2 = cv2.boxFilter(dc * dc, -1, k)
    mean = m1 / np.maximum(n, 1e-6)
    spread = np.sqrt(np.maximum(m2 / np.maximum(n, 1e-6) - mean * mean, 0))
    return n * np.exp(spread * np.float32(-1.0 / AGREE_PX))


def fill_and_confidence(disparity: np.ndarray, valid: np.ndarray, guide: np.ndarray, lam: float,
                        sigma_color: float, texture_map: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """disparity: (H, W) float32 px (anything where not valid); valid: (H, W) bool; guide: the left
    image; texture_map: texture() of it (None: no texture term).
    -> (filled disparity float32 px, NaN only without any measurement; confidence uint8).
    The smoother runs at FILL_SCALE; pixels it cannot reach (walled in by strong edges) take
    background_fill's value there, with confidence 1."""
    h, w = disparity.shape
    c = valid.astype(np.float32)
    f = np.dstack([np.where(valid, disparity, 0).astype(np.float32), c])
    hs, ws = max(1, round(h * FILL_SCALE)), max(1, round(w * FILL_SCALE))
    small = cv2.resize(f, (ws, hs), interpolation=cv2.INTER_AREA)  # channel 0 is now mean(c * d)
    small_guide = cv2.resize(guide, (ws, hs), interpolation=cv2.INTER_AREA)
    u = fast_global_smoother(small, small_guide, lam * FILL_SCALE ** 2, sigma_color, FILL_ITERATIONS)
    support = np.clip(u[..., 1], 0.0, 1.0).astype(np.float32)
    smoothed: np.ndarray = np.where(support > 1e-6, u[..., 0] / np.maximum(u[..., 1], 1e-12), np.nan).astype(np.float32)
    if np.isnan(smoothed).any():
        smoothed = background_fill(smoothed)
    if np.isnan(smoothed).all():
        return np.full((h, w), np.nan, np.float32), np.zeros((h, w), np.uint8)
    smoothed = cv2.resize(smoothed, (w, h), interpolation=cv2.INTER_LINEAR)
    support = cv2.resize(support, (w, h), interpolation=cv2.INTER_LINEAR)
    out = np.where(valid, disparity, smoothed)
    trust = local_agreement(out, c)
    if texture_map is not None:
        trust *= 1 - np.exp(texture_map * np.float32(-1.0 / TEXTURE))
    top = 255 - MEASURED_CONFIDENCE
    conf = np.where(valid, MEASURED_CONFIDENCE + top * trust, 1 + (MEASURED_CONFIDENCE - 2) * support)
    return out, (conf + 0.5).astype(np.uint8)


class DenseMatcher:
    """Left image's disparity and confidence for every pixel (see the module docstring).
    Images: (H, W) uint8 or (H, W, 3) BGR (colour guides the fill better), rectified, the same size."""

    def __init__(self, config: MatcherConfig):
        if config.method != "dense":
            raise BallbotError(f"DenseMatcher needs method dense, got {config.method}")
        self.config = config
        self.pad = max(0, config.min_disparity + config.fixed_num_disparities)
        self._m = create_sgbm(config)

    def compute(self, left: np.ndarray, right: np.ndarray, min_valid_disparity: float = 0.0) -> np.ndarray:
        """-> (H, W) int16, disparity * 16 (see match)."""
        return self.match(left, right, min_valid_disparity).disparity

    def measure(self, gray_left: np.ndarray, gray_right: np.ndarray) -> np.ndarray:
        """Semi-global matching on the left-padded pair -> (H, W) int16, px * 16; values below
        min_disparity * 16 are OpenCV's 'no match'."""
        return compute_padded(self._m, gray_left, gray_right, self.pad)

    def match(self, left: np.ndarray, right: np.ndarray, min_valid_disparity: float = 0.0) -> Match:
        """-> Match: every pixel reached by a measurement has a disparity (int16, px * 16) and a
        confidence > 0; invalid (config.invalid_value, confidence 0) only where none reaches or
        below the range gate min_valid_disparity (px)."""
        if left.shape != right.shape:
            raise BallbotError(f"left {left.shape} and right {right.shape} images differ in size")
        c = self.config
        c.check_width(left.shape[1])
        gl = gray(left)
        raw = self.measure(gl, gray(right))
        tex = texture(gl, c.block + 2)
        valid = (raw >= raw_at_least(c.min_disparity * SCALE)) & (tex >= FLAT)  # no texture: SGBM's answer is a guess
        # In the left band a match must keep its partner's window in view (beyond, it compared
        # against the padding).
        outside = reaches_padding(raw, c.block, self.pad)
        valid[:, :outside.shape[1]] &= ~outside
        saturated = saturated_share(raw, valid, c.max_disparity)
        filled, confidence = fill_and_confidence(raw.astype(np.float32) / np.float32(SCALE), valid, left,
                                                 c.fill_lambda, c.fill_sigma_color, tex)
        reached = np.isfinite(filled)
        d = np.clip(np.nan_to_num(filled), c.min_disparity, c.max_disparity)
        if not c.subpixel:
            d = np.round(d)
        out = np.round(d * SCALE).astype(np.int16)
        invalid = ~reached
        if min_valid_disparity > 0:
            invalid |= out < raw_at_least(min_valid_disparity * SCALE)
        out[invalid] = c.invalid_value
        confidence[invalid] = 0
        return Match(out, confidence, saturated)
