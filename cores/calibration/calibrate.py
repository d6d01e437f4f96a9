"""Stereo calibration from chessboard pairs: corner detection, per-camera and stereo calibration,
outlier views and uncertainties (the report on them: report.py).

No CLI and no Zenoh here: `ballbot-vision calibrate` (ballbot_vision/calibration_commands.py) and the
tests drive this module.

Conventions (those of cores/camera.py): pixel centres at integer coordinates; K = [[fx, s, cx],
[0, fy, cy], [0, 0, 1]] with s the skew in pixels (Bouguet's alpha_c = s / fx); distortion
(k1, k2, p1, p2, k3); ``X_right = R @ X_left + T``, T in the unit of --square-size (metres).

The standard deviations come from OpenCV's calibrateCameraExtended (skew fixed) or from the
Jacobian of our own refinement (skew free), scaled by the residual variance.
"""
from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from common.errors import CalibrationError
from common.files import IMAGE_EXTENSIONS, list_images, natural_sorted, pair_images, read_image
from cores import camera

Progress = Callable[[str], None]


def _quiet(_: str) -> None:
    pass


# --- finding the image pairs ---------------------------------------------------------------------

def parse_pattern(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6): inner corners per row, per column."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX*]\s*(\d+)\s*", str(text))
    if not m or int(m.group(1)) < 2 or int(m.group(2)) < 2:
        raise CalibrationError(f"--pattern {text!r}: expected inner corners as COLSxROWS, e.g. 9x6")
    return int(m.group(1)), int(m.group(2))


def find_pairs(left: str | None = None, right: str | None = None, pairs_dir: str | None = None
               ) -> list[tuple[Path, Path]]:
    """--left GLOB --right GLOB, or --pairs DIR (files with 'left' / 'right' in their names, or
    subfolders left/ and right/)."""
    if pairs_dir is not None:
        d = Path(pairs_dir)
        if not d.is_dir():
            raise CalibrationError(f"--pairs {pairs_dir}: " + ("is a file, not a folder" if d.exists() else
                                                               "no such file or folder"))
        if (d / "left").is_dir() and (d / "right").is_dir():
            return pair_images(list_images(str(d / "left"), "--pairs"), list_images(str(d / "right"), "--pairs"))
        imgs = natural_sorted([f for f in d.iterdir() if f.suffix.lower() in IMAGE_EXTENSIONS])
        ls = [f for f in imgs if re.search(r"left|links", f.name, re.I)]
        rs = [f for f in imgs if re.search(r"right|rechts", f.name, re.I)]
        if not ls or not rs:
            raise CalibrationError(f"--pairs {pairs_dir!r}: no image names containing 'left' and 'right' "
                                   f"(found {len(imgs)} images), and no left/ and right/ subfolders")
        return pair_images(ls, rs)
    if left is None or right is None:
        raise CalibrationError("give --left and --right (globs or folders), or --pairs DIR, "
                               "or --live (views from a running capture)")
    return pair_images(list_images(left, "--left"), list_images(right, "--right"))


# --- corners -------------------------------------------------------------------------------------

def read_gray(path: Path) -> np.ndarray:
    img = read_image(path)
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img


def detect_corners(gray: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """Inner chessboard corners, (N, 1, 2) float32 in pixels, refined to sub-pixel; None if the
    whole board is not found. Classic detector + cornerSubPix (the sector-based detector is left
    out: it also reports a smaller board inside a larger one, which hides a wrong --pattern)."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if found:
        # The window must stay inside one square: a fraction of the smallest corner spacing.
        c = corners.reshape(pattern[1], pattern[0], 2)
        spacing = min(np.linalg.norm(np.diff(c, axis=1), axis=2).min(),
                      np.linalg.norm(np.diff(c, axis=0), axis=2).min())
        win = int(max(2, min(11, spacing * 0.4)))
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
        return cv2.cornerSubPix(gray, corners, (win, win), (-1, -1), crit)
    return None


def board_points(pattern: tuple[int, int], square_size: float) -> np.ndarray:
    """Object points (N, 1, 3) float32, row by row as findChessboardCorners orders the corners."""
    cols, rows = pattern
    g = np.zeros((rows * cols, 1, 3), np.float32)
    g[:, 0, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_size
    return g


def _same_order(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The detector may number a board from either end; make the right view's order match the
    left's (first-to-last corner directions agree)."""
    dl = left[-1, 0] - left[0, 0]
    dr = right[-1, 0] - right[0, 0]
    return right[::-1].copy() if float(np.dot(dl, dr)) < 0 else right


@dataclass
class ViewPair:
    left_path: Path
    right_path: Path
    left: np.ndarray | None  # corners (N, 1, 2) or None
    right: np.ndarray | None

    @property
    def found(self) -> bool:
        return self.left is not None and self.right is not None

    @property
    def name(self) -> str:
        return f"{self.left_path.name}+{self.right_path.name}"

    def corners(self) -> tuple[np.ndarray, np.ndarray]:
        """(left, right) corners of a view found in both images."""
        if self.left is None or self.right is None:
            raise CalibrationError(f"{self.name}: the board is not found in both images")
        return self.left, self.right


def detect_pairs(pairs: Sequence[tuple[Path, Path]], pattern: tuple[int, int], progress: Progress = _quiet
                 ) -> tuple[list[ViewPair], tuple[int, int]]:
    """Detect the board in every pair; checks all images have one size. Returns views, (w, h)."""
    views: list[ViewPair] = []
    sizes: dict[tuple[int, int], list[Path]] = {}
    for i, (lp, rp) in enumerate(pairs):
        gl, gr = read_gray(lp), read_gray(rp)
        for p, g in ((lp, gl), (rp, gr)):
            sizes.setdefault((g.shape[1], g.shape[0]), []).append(p)
        cl = detect_corners(gl, pattern)
        cr = detect_corners(gr, pattern)
        if cl is not None and cr is not None:
            cr = _same_order(cl, cr)
        views.append(ViewPair(lp, rp, cl, cr))
        progress(f"[{i + 1:2d}/{len(pairs)}] {lp.name}: {'found' if cl is not None else 'NOT FOUND'}   "
                 f"{rp.name}: {'found' if cr is not None else 'NOT FOUND'}")
    if len(sizes) > 1:
        parts = [f"{w}x{h}: {', '.join(str(p) for p in ps[:4])}{' ...' if len(ps) > 4 else ''}"
                 for (w, h), ps in sorted(sizes.items(), key=lambda kv: -len(kv[1]))]
        raise CalibrationError("images of different sizes:\n  " + "\n  ".join(parts))
    return views, next(iter(sizes))


# --- one camera ----------------------------------------------------------------------------------

@dataclass
class CameraResult:
    """One calibrated camera. std: 1-sigma of (fx, fy, cx, cy, skew, k1, k2, p1, p2, k3); 0 = fixed."""

    K: np.ndarray
    D: np.ndarray  # 5
    std: np.ndarray  # 10
    rms: float
    per_view: np.ndarray  # RMS per view, px
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]

    @property
    def intrinsics(self) -> camera.Intrinsics:
        return camera.Intrinsics.from_matrix(self.K, self.D)


def _mono_flags(k3: bool) -> int:
    return 0 if k3 else cv2.CALIB_FIX_K3


def _rodrigues_batch(r: np.ndarray) -> np.ndarray:
    """(M, 3) rotation vectors -> (M, 3, 3) matrices."""
    th = np.linalg.norm(r, axis=1)
    small = th < 1e-12
    k = r / np.where(small, 1.0, th)[:, None]
    Kx = np.zeros((len(r), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2] = -k[:, 2], k[:, 1]
    Kx[:, 1, 0], Kx[:, 1, 2] = k[:, 2], -k[:, 0]
    Kx[:, 2, 0], Kx[:, 2, 1] = -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3)[None] + s * Kx + (1 - c) * (Kx @ Kx)


def project(obj: np.ndarray, rvecs: np.ndarray, tvecs: np.ndarray, intr: np.ndarray) -> np.ndarray:
    """Pinhole + (k1, k2, p1, p2, k3) + skew, like cv2.projectPoints but honouring K[0, 1].

    obj: (N, 3) board points; rvecs, tvecs: (M, 3); intr: fx, fy, cx, cy, s, k1, k2, p1, p2, k3.
    Returns (M, N, 2) pixels."""
    fx, fy, cx, cy, s, k1, k2, p1, p2, k3 = intr
    X = np.einsum("mij,nj->mni", _rodrigues_batch(rvecs), obj) + tvecs[:, None, :]
    x, y = X[..., 0] / X[..., 2], X[..., 1] / X[..., 2]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=-1)


def _refine_with_skew(obj: np.ndarray, img: list[np.ndarray], start: CameraResult, k3: bool) -> CameraResult:
    """Bundle adjustment of one camera with the skew free (OpenCV's calibrateCamera keeps it 0)."""
    from scipy.optimize import least_squares

    M, N = len(img), obj.shape[0]
    obs = np.stack([p.reshape(-1, 2) for p in img]).astype(np.float64)
    free = [0, 1, 2, 3, 4, 5, 6, 7, 8] + ([9] if k3 else [])
    intr0 = np.array([start.K[0, 0], start.K[1, 1], start.K[0, 2], start.K[1, 2], start.K[0, 1], *start.D])
    x0 = np.concatenate([intr0[free], np.concatenate(start.rvecs).ravel(), np.concatenate(start.tvecs).ravel()])
    nf = len(free)

    def unpack(x: np.ndarray):
        intr = intr0.copy()
        intr[free] = x[:nf]
        r = x[nf:nf + 3 * M].reshape(M, 3)
        t = x[nf + 3 * M:].reshape(M, 3)
        return intr, r, t

    def residuals(x: np.ndarray) -> np.ndarray:
        intr, r, t = unpack(x)
        return (project(obj, r, t, intr) - obs).ravel()

    # Levenberg-Marquardt from OpenCV's skew-free solution: a few iterations of a small problem.
    sol = least_squares(residuals, x0, method="lm", x_scale="jac", xtol=1e-10, ftol=1e-10, max_nfev=200 * x0.size)
    intr, r, t = unpack(sol.x)
    res = sol.fun.reshape(M, N, 2)
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else sol.jac
    dof = max(res.size - x0.size, 1)
    sigma2 = float(np.sum(res ** 2)) / dof
    try:
        cov = np.linalg.pinv(J.T @ J) * sigma2
    except np.linalg.LinAlgError:
        cov = np.full((x0.size, x0.size), np.nan)
    std = np.zeros(10)
    std[free] = np.sqrt(np.maximum(np.diag(cov)[:nf], 0))
    K = np.array([[intr[0], intr[4], intr[2]], [0, intr[1], intr[3]], [0, 0, 1.0]])
    return CameraResult(K, intr[5:].copy(), std, float(np.sqrt(np.mean(np.sum(res ** 2, axis=2)))),
                        np.sqrt(np.mean(np.sum(res ** 2, axis=2), axis=1)),
                        [v.reshape(3, 1) for v in r], [v.reshape(3, 1) for v in t])


def calibrate_camera(obj: np.ndarray, img: list[np.ndarray], size: tuple[int, int], fix_skew: bool = True,
                     k3: bool = False) -> CameraResult:
    """obj: (N, 1, 3) board points, img: per view (N, 1, 2) corners -> one calibrated camera."""
    objs = [obj] * len(img)
    # (OpenCV's stubs take no None for the camera matrix and distortion; OpenCV itself does: no guess)
    rms, K, D, rv, tv, std_i, _, per_view = cv2.calibrateCameraExtended(  # type: ignore[call-overload]
        objs, img, size, None, None, flags=_mono_flags(k3),
        criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    D5 = np.zeros(5)
    D5[:min(5, D.size)] = D.ravel()[:5]
    s = np.asarray(std_i, dtype=np.float64).ravel()
    std = np.zeros(10)
    std[:4] = s[:4]
    std[5:10] = s[4:9]
    res = CameraResult(K, D5, std, float(rms), np.asarray(per_view).ravel(), list(rv), list(tv))
    if not fix_skew:
        res = _refine_with_skew(obj.reshape(-1, 3).astype(np.float64), img, res, k3)
    return res


def deskew_points(pts: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Image points of a camera with skew -> those of the same camera with K[0, 1] = 0, so that
    OpenCV functions (which ignore the skew) see exact observations: u' = u - s (v - cy) / fy."""
    s = K[0, 1]
    if s == 0:
        return pts
    out = pts.astype(np.float64).copy()
    out[..., 0] -= s * (out[..., 1] - K[1, 2]) / K[1, 1]
    return out.astype(pts.dtype)


def _no_skew(K: np.ndarray) -> np.ndarray:
    K = K.copy()
    K[0, 1] = 0.0
    return K


# --- the pair ------------------------------------------------------------------------------------

@dataclass
class StereoResult:
    image_size: tuple[int, int]
    pattern: tuple[int, int]
    square_size: float
    left: CameraResult
    right: CameraResult
    R: np.ndarray
    T: np.ndarray
    rms: float
    per_view: np.ndarray  # (views, 2): RMS of the left and right image in the stereo fit
    views: list[ViewPair]  # the views used, in order
    rejected: list[tuple[ViewPair, str]] = field(default_factory=list)
    without_board: list[ViewPair] = field(default_factory=list)
    total_pairs: int = 0
    rig: camera.RawRig = field(kw_only=True)  # the calibrated rig (always: the rest is how it was found)
    om_std: np.ndarray = field(default_factory=lambda: np.zeros(3))
    T_std: np.ndarray = field(default_factory=lambda: np.zeros(3))


OUTLIER_FLOOR_PX = 0.2


def outlier_threshold(errors: np.ndarray, max_view_rms: float) -> float:
    """A view is an outlier above min(max_view_rms, max(median + 3 MAD, 2 median, 0.2 px)), MAD
    scaled to a standard deviation (x 1.4826). The floors keep views of uniformly tiny error
    (synthetic boards, a good rig) from being thrown out for being merely above average."""
    med = float(np.median(errors))
    mad = 1.4826 * float(np.median(np.abs(errors - med)))
    return min(max_view_rms, max(med + 3 * mad, 2 * med, OUTLIER_FLOOR_PX))


def _stereo_extrinsics_std(obj: np.ndarray, pl: list[np.ndarray], pr: list[np.ndarray], Kl, Dl, Kr, Dr,
                           R: np.ndarray, T: np.ndarray, rvecs: list, tvecs: list) -> tuple[np.ndarray, np.ndarray]:
    """1-sigma of (om, T) with the intrinsics fixed: Jacobian of the stereo reprojection residuals
    over (om, T, the board pose per view) at the solution, scaled by the residual variance."""
    M = len(pl)
    obj = obj.reshape(-1, 3).astype(np.float64)
    il = np.array([Kl[0, 0], Kl[1, 1], Kl[0, 2], Kl[1, 2], 0.0, *Dl])
    ir = np.array([Kr[0, 0], Kr[1, 1], Kr[0, 2], Kr[1, 2], 0.0, *Dr])
    obs_l = np.stack([p.reshape(-1, 2) for p in pl]).astype(np.float64)
    obs_r = np.stack([p.reshape(-1, 2) for p in pr]).astype(np.float64)
    om = cv2.Rodrigues(R)[0].ravel()
    x0 = np.concatenate([om, T.ravel(), np.concatenate([np.ravel(v) for v in rvecs]),
                         np.concatenate([np.ravel(v) for v in tvecs])])

    def residuals(x: np.ndarray) -> np.ndarray:
        Rs = _rodrigues_batch(x[None, :3])[0]
        r = x[6:6 + 3 * M].reshape(M, 3)
        t = x[6 + 3 * M:].reshape(M, 3)
        Rl = _rodrigues_batch(r)
        rr = np.stack([cv2.Rodrigues(Rs @ Rm)[0].ravel() for Rm in Rl])
        tr = t @ Rs.T + x[3:6]
        return np.concatenate([(project(obj, r, t, il) - obs_l).ravel(), (project(obj, rr, tr, ir) - obs_r).ravel()])

    f0 = residuals(x0)
    J = np.empty((f0.size, x0.size))
    for j in range(x0.size):
        h = 1e-7 * max(1.0, abs(x0[j]))
        xp, xm = x0.copy(), x0.copy()
        xp[j] += h
        xm[j] -= h
        J[:, j] = (residuals(xp) - residuals(xm)) / (2 * h)
    sigma2 = float(f0 @ f0) / max(f0.size - x0.size, 1)
    cov = np.linalg.pinv(J.T @ J) * sigma2
    sd = np.sqrt(np.maximum(np.diag(cov)[:6], 0))
    return sd[:3], sd[3:6]


def calibrate_stereo(pairs: Sequence[tuple[Path, Path]], pattern: tuple[int, int], square_size: float,
                     fix_skew: bool = True, k3: bool = False, refine_intrinsics: bool = False,
                     min_views: int = 6, max_view_rms: float = 1.0, reject_outliers: bool = True,
                     progress: Progress = _quiet, name: str = "") -> StereoResult:
    """Chessboard pairs -> calibrated rig. Views where either camera misses the board are skipped;
    views whose reprojection error is an outlier (see outlier_threshold) are rejected and the rig
    recalibrated without them."""
    if square_size <= 0:
        raise CalibrationError(f"--square-size {square_size}: must be positive (metres)")
    views_all, size = detect_pairs(pairs, pattern, progress)
    found = [v for v in views_all if v.found]
    missing = [v for v in views_all if not v.found]
    if len(found) < min_views:
        lines = []
        for v in missing:
            sides = [p.name for p, c in ((v.left_path, v.left), (v.right_path, v.right)) if c is None]
            lines.append(f"{v.name}: no {pattern[0]}x{pattern[1]} board in {', '.join(sides)}")
        raise CalibrationError(
            f"the board was found in both images of {len(found)} of {len(views_all)} pairs; at least "
            f"{min_views} are needed (is --pattern {pattern[0]}x{pattern[1]} the count of INNER corners?)"
            + ("\n  " + "\n  ".join(lines) if lines else ""))
    obj = board_points(pattern, square_size)

    views = list(found)
    rejected: list[tuple[ViewPair, str]] = []
    for _round in range(3):
        progress(f"calibrating the left and right cameras on {len(views)} views ...")
        cl = calibrate_camera(obj, [v.corners()[0] for v in views], size, fix_skew, k3)
        cr = calibrate_camera(obj, [v.corners()[1] for v in views], size, fix_skew, k3)
        if not reject_outliers:
            break
        out = []
        for side, res in (("left", cl), ("right", cr)):
            thr = outlier_threshold(res.per_view, max_view_rms)
            for v, e in zip(views, res.per_view):
                if e > thr:
                    out.append((v, f"{side} RMS {e:.3f} px > {thr:.3f} px"))
        if not out:
            break
        bad = {id(v) for v, _ in out}
        if len(views) - len(bad) < min_views:
            progress(f"not rejecting {len(bad)} outlier view(s): fewer than {min_views} would remain")
            break
        for v, why in out:
            progress(f"rejecting {v.name}: {why}")
        rejected.extend(out)
        views = [v for v in views if id(v) not in bad]

    flags = cv2.CALIB_FIX_INTRINSIC
    if refine_intrinsics:
        flags = cv2.CALIB_USE_INTRINSIC_GUESS | _mono_flags(k3)
    Kl, Kr = _no_skew(cl.K), _no_skew(cr.K)
    for _round in range(5):
        progress(f"calibrating the pair on {len(views)} views ...")
        pl = [deskew_points(v.corners()[0], cl.K) for v in views]
        pr = [deskew_points(v.corners()[1], cr.K) for v in views]
        # (OpenCV's stubs take no None for R and T; OpenCV itself does: outputs only)
        (rms, Kl2, Dl2, Kr2, Dr2, R, T, _E, _F, rvecs, tvecs,
         per_view) = cv2.stereoCalibrateExtended(  # type: ignore[call-overload]
            [obj] * len(views), pl, pr, Kl.copy(), cl.D.reshape(1, 5).copy(), Kr.copy(), cr.D.reshape(1, 5).copy(),
            size, None, None, flags=flags, criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12))
        per_view = np.asarray(per_view).reshape(-1, 2)
        if not reject_outliers:
            break
        # A pair can be fine for each camera alone and still wrong as a pair (images from
        # different moments, a swapped file): the stereo per-view errors catch that.
        # One wrong pair drags R, T and so every view's error up: first drop the views that stand
        # out from the others, refit, and only then apply the absolute limit.
        err = per_view.max(axis=1)
        thr = outlier_threshold(err, float("inf"))
        if not np.any(err > thr):
            thr = min(thr, max_view_rms)
        stereo_bad = [(v, f"stereo RMS {e:.3f} px > {thr:.3f} px") for v, e in zip(views, err) if e > thr]
        if not stereo_bad:
            break
        if len(views) - len(stereo_bad) < min_views:
            progress(f"not rejecting {len(stereo_bad)} stereo outlier view(s): fewer than {min_views} would remain")
            break
        for v, why in stereo_bad:
            progress(f"rejecting {v.name}: {why}")
        rejected.extend(stereo_bad)
        ids = {id(v) for v, _ in stereo_bad}
        keep = [i for i, v in enumerate(views) if id(v) not in ids]
        views = [views[i] for i in keep]
        for c in (cl, cr):  # keep the per-camera per-view errors aligned with `views`
            c.per_view = c.per_view[keep]
            c.rvecs = [c.rvecs[i] for i in keep]
            c.tvecs = [c.tvecs[i] for i in keep]
    if refine_intrinsics:
        Kl2[0, 1], Kr2[0, 1] = cl.K[0, 1], cr.K[0, 1]
        cl.K, cl.D = Kl2, np.asarray(Dl2).ravel()[:5]
        cr.K, cr.D = Kr2, np.asarray(Dr2).ravel()[:5]
    T = np.asarray(T, dtype=np.float64).ravel()
    try:
        om_std, T_std = _stereo_extrinsics_std(obj, pl, pr, _no_skew(cl.K), cl.D, _no_skew(cr.K), cr.D, R, T,
                                               rvecs, tvecs)
    except Exception:  # uncertainties are a report nicety; never fail a calibration on them
        om_std, T_std = np.full(3, np.nan), np.full(3, np.nan)
    try:
        rig = camera.RawRig(size, cl.intrinsics, cr.intrinsics, R, T, name)
    except CalibrationError as e:
        raise CalibrationError(f"the stereo calibration is not usable: {e}") from None
    return StereoResult(size, pattern, square_size, cl, cr, R, T, float(rms), per_view,
                        views, rejected, missing, len(views_all), om_std, T_std, rig=rig)
