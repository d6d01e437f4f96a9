"""Where the ground's candidate planes come from (ground.py judges them): a floor or road is a plane
d = a u + b v + c in disparity space. RANSAC over random triples of the working-resolution pixels
(half of them from nearby rows), and the dominant lines of the v-disparity histogram (a floor is a
line d = s (v - v_horizon) there, however little of it is matched); least-squares planes and the
pixels in a band about a plane (Pixels).
"""
from __future__ import annotations

import numpy as np

from cores import camera

MIN_HEIGHT_M, MAX_HEIGHT_M = 0.05, 20.0  # the camera above a floor candidate
# A balancing robot leans by about 10 degrees, a car's camera hardly rolls: a plane rolled more is a
# slope beside the way (a snow bank, an embankment), not the floor under the robot.
MAX_ROLL_DEG = 15.0
RANSAC_HYPOTHESES = 96
SCORE_SAMPLES = 2000  # RANSAC hypotheses are scored on this many pixels; the refinement uses all


def lstsq_plane(u: np.ndarray, v: np.ndarray, d: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Least-squares (a, b, c) of d = a u + b v + c (weights w), by the 3x3 normal equations (centred)."""
    return lstsq(u.astype(np.float64), v.astype(np.float64), d.astype(np.float64),
                  None if w is None else w.astype(np.float64))


def lstsq(u: np.ndarray, v: np.ndarray, d: np.ndarray, w: np.ndarray | None) -> np.ndarray:
    """lstsq_plane on float64 arrays of the caller's own (centred in place)."""
    if w is None:  # unit weights: their products are the values themselves, their sum the count
        ones = np.ones_like(d)
        sw = float(d.size)
        mu, mv, md = (ones @ u) / sw, (ones @ v) / sw, (ones @ d) / sw
    else:
        sw = w.sum()
        mu, mv, md = (w @ u) / sw, (w @ v) / sw, (w @ d) / sw
    u -= mu
    v -= mv
    d -= md
    wu, wv = (u, v) if w is None else (w * u, w * v)
    p, q, r = wu @ u + 1e-9, wu @ v, wv @ v + 1e-9  # the 2x2 normal equations, solved by hand
    x, y = wu @ d, wv @ d
    det = p * r - q * q
    if abs(det) < 1e-12:
        det = 1e-12
    a, b = (r * x - q * y) / det, (p * y - q * x) / det
    return np.array([a, b, md - a * mu - b * mv])


def in_band(d: np.ndarray, pred: np.ndarray, rel: float) -> np.ndarray:
    """Where the disparities d lie within max(0.6, rel pred) of a plane's disparities pred, in front
    of the camera (pred > 0)."""
    tol = np.multiply(np.float32(rel), pred)
    np.maximum(np.float32(0.6), tol, out=tol)
    off = np.subtract(d, pred)
    np.abs(off, out=off)
    inl = off <= tol
    inl &= pred > 0
    return inl


class Pixels:
    """A frame's valid working pixels: float32 u, v, d, where the bands are drawn, and float64
    copies for the least squares, made once a frame instead of at every fit."""

    def __init__(self, u: np.ndarray, v: np.ndarray, d: np.ndarray, spacing: float):
        self.u, self.v, self.d = u, v, d
        self.spacing = spacing  # px of the map between two samples (a 640x480 map at downsample 2: 4)
        self.u64, self.v64, self.d64 = u.astype(np.float64), v.astype(np.float64), d.astype(np.float64)
        self._left: tuple[float, np.ndarray] | None = None

    def disparity(self, p: np.ndarray) -> np.ndarray:
        """The plane's float32 disparity at the pixels: (a u + b v) + c, in place."""
        pred = np.float32(p[0]) * self.u
        pred += np.float32(p[1]) * self.v
        pred += np.float32(p[2])
        return pred

    def band(self, pred: np.ndarray, rel: float) -> np.ndarray:
        """The pixels within max(0.6, rel pred) of the plane's disparity pred, in front of the camera."""
        return in_band(self.d, pred, rel)

    def fit(self, m: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """lstsq_plane on the pixels of mask m, or of indices m (weights w: one per pixel of m)."""
        i = np.flatnonzero(m) if m.dtype == bool else m  # by index: several times faster than 3 masks
        w64 = None if w is None else w.astype(np.float64)
        return lstsq(self.u64.take(i), self.v64.take(i), self.d64.take(i), w64)

    def left(self, cx: float) -> np.ndarray:
        """The pixels left of column cx."""
        if self._left is None or self._left[0] != cx:
            self._left = (cx, self.u < cx)
        return self._left[1]


def ransac_planes(u: np.ndarray, v: np.ndarray, d: np.ndarray, rng: np.random.Generator,
                  n_hyp: int = RANSAC_HYPOTHESES, keep: int = 3) -> list[np.ndarray]:
    """Floor candidates without a guess: planes through random triples of pixels (half of them
    drawn from nearby rows: pixels are in raster order), kept when they rise downwards (b > 0) and
    are rolled at most MAX_ROLL_DEG; the `keep` best by the pixels within 1 px (5 %) of them, each
    unlike the ones before it."""
    n = d.size
    if n < 50:
        return []
    i = rng.integers(0, n, size=n_hyp)
    near = n_hyp // 2
    span = max(3, n // 8)
    j = np.empty(n_hyp, np.int64)
    k = np.empty(n_hyp, np.int64)
    j[:near] = np.clip(i[:near] + rng.integers(-span, span + 1, near), 0, n - 1)
    k[:near] = np.clip(i[:near] + rng.integers(-span, span + 1, near), 0, n - 1)
    j[near:], k[near:] = rng.integers(0, n, size=(2, n_hyp - near))
    idx = np.stack([i, j, k], 1)
    # each triple's plane by Cramer's rule, written out (np.linalg on stacks of 3x3 costs milliseconds)
    uu, vv, dd = u[idx].astype(np.float64), v[idx].astype(np.float64), d[idx].astype(np.float64)

    def det3(c0: np.ndarray, c1: np.ndarray, c2: np.ndarray) -> np.ndarray:  # columns of the 3x3 systems
        return (c0[:, 0] * (c1[:, 1] * c2[:, 2] - c1[:, 2] * c2[:, 1])
                - c0[:, 1] * (c1[:, 0] * c2[:, 2] - c1[:, 2] * c2[:, 0])
                + c0[:, 2] * (c1[:, 0] * c2[:, 1] - c1[:, 1] * c2[:, 0]))
    one = np.ones_like(uu)
    det = det3(uu, vv, one)
    ok = np.abs(det) > 1e-3
    if not ok.any():
        return []
    planes = np.stack([det3(dd, vv, one), det3(uu, dd, one), det3(uu, vv, dd)], 1)
    planes = (planes / np.where(ok, det, 1.0)[:, None])[ok]
    planes = planes[(planes[:, 1] > 1e-4) & (np.abs(planes[:, 0]) <= np.tan(np.radians(MAX_ROLL_DEG)) * planes[:, 1])]
    if not len(planes):
        return []
    s = rng.choice(n, size=min(n, SCORE_SAMPLES), replace=False)
    us, vs, ds = u[s], v[s], d[s]
    score = support_counts(planes, us.astype(np.float64), vs.astype(np.float64), ds.astype(np.float64))
    out: list[np.ndarray] = []
    kept: list[np.ndarray] = []  # their disparities on the pixels telling planes apart
    uc, vc = us[:256], vs[:256]  # enough to tell two planes apart
    best = np.argsort(-score)[:24]  # the best few: most hypotheses are one floor drawn again
    preds = planes[best, 0:1] * uc + planes[best, 1:2] * vc + planes[best, 2:3]
    for q, dp in zip(best, preds):
        if score[q] < 10 or len(out) >= keep:
            break
        if all(not similar_disparities(dp, dq) for dq in kept):
            out.append(planes[q])
            kept.append(dp)
    return out


def support_counts(planes: np.ndarray, u: np.ndarray, v: np.ndarray, d: np.ndarray, block: int = 32) -> np.ndarray:
    """Per plane, the pixels (float64 u, v, d) within 1 px (5 %) of it in front of the camera. In
    blocks of planes into buffers reused: a (planes, pixels) array at once, and float32 pixels
    broadcast against float64 planes, cost several times more (the same values either way)."""
    score = np.empty(len(planes), np.int64)
    shape = (min(block, len(planes)), d.size)
    pred, tol = np.empty(shape), np.empty(shape)
    front, near = np.empty(shape, bool), np.empty(shape, bool)
    for i in range(0, len(planes), block):
        pl = planes[i:i + block]
        k = len(pl)
        pr, t, f, m = pred[:k], tol[:k], front[:k], near[:k]
        np.multiply(pl[:, 0:1], u, out=pr)
        np.multiply(pl[:, 1:2], v, out=t)
        pr += t
        pr += pl[:, 2:3]
        np.greater(pr, 0, out=f)
        np.multiply(0.05, pr, out=t)
        np.maximum(1.0, t, out=t)
        pr -= d
        np.abs(pr, out=pr)
        np.less(pr, t, out=m)
        f &= m
        score[i:i + k] = np.count_nonzero(f, axis=1)
    return score


def similar_planes(p: np.ndarray, q: np.ndarray, u: np.ndarray, v: np.ndarray) -> bool:
    """Two planes predicting within 5 % of each other on the pixels where either is in view."""
    return similar_disparities(p[0] * u + p[1] * v + p[2], q[0] * u + q[1] * v + q[2])


def similar_disparities(dp: np.ndarray, dq: np.ndarray) -> bool:
    """similar_planes on the two planes' disparities (float64) at the same pixels."""
    m = (dp > 0) | (dq > 0)
    if not m.any():
        return True
    r = np.abs(dp[m] - dq[m]) / np.maximum(np.abs(dq[m]), 1.0)
    return bool(r.sum() / r.size < 0.05)  # np.mean's sum and division, without its dispatch


def vdisparity_planes(u: np.ndarray, v: np.ndarray, d: np.ndarray, model: camera.RectifiedModel,
                      rng: np.random.Generator, keep: int = 2, hypotheses: int = 96) -> list[np.ndarray]:
    """Floor candidates from the v-disparity histogram of the middle half of the columns (a floor
    is a line d = s (v - v_horizon) there, a standing object a vertical one; a rolled floor blurs
    the line the less, the narrower the columns): RANSAC over lines through two occupied cells drawn
    by count, scored by the count within 1 px + 3 %. -> planes (a = 0, b = s, c = -s v_horizon)."""
    w = model.width
    mid = (u > 0.25 * w) & (u < 0.75 * w) & (d > 0.5)
    if np.count_nonzero(mid) < 50:
        return []
    i = np.flatnonzero(mid)
    vv, dd = v.take(i), np.round(d.take(i)).astype(np.int64)
    nd = int(dd.max()) + 1
    rows = vv.astype(np.int64)
    cells, cnt = np.unique(rows * nd + dd, return_counts=True)
    cv, cd = (cells // nd).astype(np.float64), (cells % nd).astype(np.float64)
    cnt = cnt.astype(np.float64)
    p = cnt / cnt.sum()
    i = rng.choice(len(cnt), size=hypotheses, p=p)
    j = rng.choice(len(cnt), size=hypotheses, p=p)
    dv = cv[j] - cv[i]
    good = np.abs(dv) >= 2
    slope = np.where(good, (cd[j] - cd[i]) / np.where(good, dv, 1.0), 0.0)
    B = model.baseline_m
    good &= (slope >= B / MAX_HEIGHT_M) & (slope <= B / MIN_HEIGHT_M)
    if not good.any():
        return []
    slope = slope[good]
    hv = cv[i][good] - cd[i][good] / slope
    pred = np.subtract(cv, hv[:, None])  # the same operations as slope (cv - hv) etc., in place
    pred *= slope[:, None]
    tol = np.multiply(0.03, pred)
    tol += 1.0
    off = np.subtract(cd, pred)
    np.abs(off, out=off)
    on = off <= tol
    on &= pred > 0
    score = on @ cnt  # whole counts: their sum is exact in any order
    order = np.argsort(-score)
    slope, hv = slope[order], hv[order]
    # best first, each unlike the ones before it: the first line still unlike all kept, found by
    # one mask over all lines per kept one (most lines are the one floor's, drawn again)
    unlike = np.ones(len(order), bool)
    out: list[np.ndarray] = []
    while len(out) < keep:
        rest = np.flatnonzero(unlike)
        if not rest.size:
            break
        q = rest[0]
        plane = np.array([0.0, slope[q], -slope[q] * hv[q]])
        out.append(plane)
        unlike[:q + 1] = False
        unlike &= (np.abs(slope - plane[1]) > 0.05 * plane[1]) | (np.abs(hv + plane[2] / plane[1]) > 5)
    return out
