"""The synthetic world's surfaces: one tiling procedural texture, prefiltered into a pyramid, sampled
with anisotropic filtering along each pixel's footprint, and a simple Lambert shading (what gives
the block matcher something to match at every distance)."""
from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

# --- texture ---------------------------------------------------------------------------------------

TEX_SIZE = 1024  # texels per side; the texture tiles (wraps) in both directions
TEXELS_PER_M = 200.0  # 5 mm texels at scale 1: features of 1-3 cm, i.e. several pixels at 1-5 m
_N_LEVELS = 5  # prefiltered copies, level l blurred over ~2**l texels (a full-resolution mip chain)
_MAX_TAPS = 8  # anisotropic filtering: samples along a footprint's long axis
LIGHT_DIR = np.array([-0.5, 0.4, 1.0]) / np.linalg.norm([-0.5, 0.4, 1.0])  # world, towards the light
AMBIENT = 0.45  # shade = texture * (ambient + (1 - ambient) * max(0, n . light))


def _periodic_blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur with wrap-around borders (via FFT), so the texture tiles without seams."""
    if sigma <= 0:
        return a.astype(np.float32)
    fy = np.fft.fftfreq(a.shape[0]).astype(np.float32)
    fx = np.fft.rfftfreq(a.shape[1]).astype(np.float32)
    g = np.exp(np.float32(-2.0 * (math.pi * sigma) ** 2) * (fy[:, None] ** 2 + fx[None, :] ** 2))
    return np.fft.irfft2(np.fft.rfft2(a.astype(np.float32)) * g, s=a.shape).astype(np.float32)


@functools.lru_cache(maxsize=4)
def texture_pyramid(seed: int = 0) -> tuple[np.ndarray, ...]:
    """The shared surface texture and its prefiltered copies.

    Level 0 is a TEX_SIZE x TEX_SIZE multi-octave noise, high contrast (mean 128, std ~55, clipped
    to 0..255 and quantised to uint8 values); level l is level 0 blurred over ~2**l texels, same size.
    Returns float32 arrays (grey levels). Deterministic for `seed`.
    """
    rng = np.random.default_rng([seed, 0x7E47])
    acc = np.zeros((TEX_SIZE, TEX_SIZE), np.float64)
    # fine octaves dominate so block matching finds texture at every distance; coarse ones vary
    # the local mean so surfaces do not look like uniform grey noise
    for sigma, amp in ((1.0, 1.3), (2.0, 1.0), (4.0, 0.7), (10.0, 0.4), (32.0, 0.3)):
        o = _periodic_blur(rng.standard_normal((TEX_SIZE, TEX_SIZE)), sigma)
        acc += amp * (o - o.mean()) / o.std()
    acc = (acc - acc.mean()) / acc.std()
    base = np.clip(np.round(128.0 + 55.0 * acc), 0, 255).astype(np.uint8).astype(np.float32)
    levels = [base] + [_periodic_blur(base, 0.45 * 2.0 ** lv) for lv in range(1, _N_LEVELS)]
    for lv in levels:
        lv.setflags(write=False)
    return tuple(levels)


def _remap_1d(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Bilinear samples of `img` at n points (cv2.remap limits maps to < 32767 rows/cols)."""
    n = mx.size
    cols = 1024
    rows = -(-n // cols)
    mx2 = np.zeros(rows * cols, np.float32)
    my2 = np.zeros(rows * cols, np.float32)
    mx2[:n], my2[:n] = mx, my
    map_x, map_y = mx2.reshape(rows, cols), my2.reshape(rows, cols)
    return cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP).ravel()[:n]


@dataclass(frozen=True)
class SurfaceTexture:
    """How one surface samples the shared texture: texels = scale * rot @ uv_m + offset."""

    scale: float
    cos: float
    sin: float
    off_u: float
    off_v: float

    @property
    def params(self) -> np.ndarray:
        """(5,) float32: scale, cos, sin, off_u, off_v, as `sample_texture` takes them."""
        return np.array([self.scale, self.cos, self.sin, self.off_u, self.off_v], np.float32)

    @classmethod
    def blank(cls) -> SurfaceTexture:
        """One texel everywhere: an even grey (the mean of the texture's blurriest level there)."""
        return cls(0.0, 1.0, 0.0, 0.0, 0.0)

    @classmethod
    def from_seed(cls, *seed: int) -> SurfaceTexture:
        rng = np.random.default_rng([*seed, 0x5EED])
        a = rng.uniform(0, 2 * math.pi)
        return cls(TEXELS_PER_M * float(rng.uniform(0.8, 1.25)), math.cos(a), math.sin(a),
                   float(rng.uniform(0, TEX_SIZE)), float(rng.uniform(0, TEX_SIZE)))


def sample_texture(levels: Sequence[np.ndarray], u: np.ndarray, v: np.ndarray, minor_m: np.ndarray,
            major_m: np.ndarray, au: np.ndarray, av: np.ndarray, tex: np.ndarray) -> np.ndarray:
    """Filtered texture lookup: surface coordinates (m) -> grey level, float32 (n,).

    Each pixel's footprint on the surface is an ellipse, `minor_m` across and `major_m` along the
    unit surface direction (au, av) (the slant direction). The prefilter level follows the minor
    axis and up to _MAX_TAPS samples are averaged along the major axis (anisotropic filtering): a
    grazing floor would otherwise alias, and aliasing differs between the two cameras.
    tex: (n, 5) per-pixel surface parameters (scale, cos, sin, off_u, off_v).
    """
    n_taps = np.clip(np.ceil(major_m / np.maximum(minor_m, 1e-9) - 0.25), 1, _MAX_TAPS).astype(np.int32)
    # sorted by tap count, the pixels needing a k-th tap are a prefix: slices instead of gathers
    order = np.argsort(-n_taps, kind="stable")
    n_taps = n_taps[order]
    u, v, au, av, major_m = (np.asarray(a, np.float32)[order] for a in (u, v, au, av, major_m))
    tex = tex[order]
    scale, cs, sn, ou, ov = (tex[:, k] for k in range(5))
    lev = np.clip(np.log2(np.maximum(minor_m[order] * scale, 1e-6)), 0.0, _N_LEVELS - 1.0)
    counts = np.bincount(n_taps, minlength=_MAX_TAPS + 1)
    acc = np.zeros(u.shape, np.float32)
    for k in range(_MAX_TAPS):
        c = int(counts[k + 1:].sum())
        if c == 0:
            break
        off = ((k + 0.5) / n_taps[:c] - 0.5) * major_m[:c]
        uk, vk = u[:c] + off * au[:c], v[:c] + off * av[:c]
        tu = np.mod(scale[:c] * (cs[:c] * uk - sn[:c] * vk) + ou[:c], TEX_SIZE)
        tv = np.mod(scale[:c] * (sn[:c] * uk + cs[:c] * vk) + ov[:c], TEX_SIZE)
        acc[:c] += _trilinear(levels, tu, tv, lev[:c])
    out = np.empty_like(acc)
    out[order] = acc / n_taps
    return out


def _trilinear(levels: Sequence[np.ndarray], tu: np.ndarray, tv: np.ndarray, lev: np.ndarray) -> np.ndarray:
    """Bilinear samples at texel coordinates (tu, tv), blended between prefilter levels `lev`."""
    i0 = np.minimum(lev.astype(np.int32), _N_LEVELS - 2)
    w1 = (lev - i0).astype(np.float32)
    out = np.zeros(tu.shape, np.float32)
    for lv in range(_N_LEVELS):
        lo, hi = i0 == lv, (i0 + 1 == lv) & (w1 > 0)  # most pixels need one level only
        m = lo | hi
        if not m.any():
            continue
        out[m] += np.where(lo[m], 1.0 - w1[m], w1[m]) * _remap_1d(levels[lv], tu[m], tv[m])
    return out
