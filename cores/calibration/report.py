"""The calibration report in the style of Bouguet's toolbox (and the thesis): each camera's
intrinsics and the extrinsics with their uncertainties, the views used and rejected, and what the
rig gives after rectification (baseline, focal length, the disparity range of a depth range).

Uncertainties are reported as 3 standard deviations, like Bouguet's Camera Calibration Toolbox.
"""
from __future__ import annotations

import math

import cv2

from common.errors import CalibrationError
from cores import camera
from cores.calibration.calibrate import CameraResult, StereoResult

SIGMAS = 3.0  # uncertainties are printed as +/- 3 sigma (Bouguet's convention)


def disparity_range(model: camera.RectifiedModel, near_m: float, far_m: float) -> tuple[float, float, int]:
    """Disparities (px) of the far and near depth, and numDisparities (a multiple of 16) covering
    [0, near]."""
    if not (0 < near_m < far_m):
        raise CalibrationError(f"--depth-range {near_m} {far_m}: expected 0 < near < far (metres)")
    d_far = model.disparity_for_depth(far_m)
    d_near = model.disparity_for_depth(near_m)
    return d_far, d_near, int(16 * math.ceil(d_near / 16.0))


def _pm(v: float, s: float, fmt: str = "{:.5f}") -> str:
    return fmt.format(v) + (" (fixed)" if s == 0 else f" ± {fmt.format(SIGMAS * s)}")


def format_camera(title: str, c: CameraResult) -> list[str]:
    K, D, s = c.K, c.D, c.std
    alpha = K[0, 1] / K[0, 0]
    alpha_sd = s[4] / K[0, 0]
    angle = 90.0 - math.degrees(math.atan(alpha))
    kc = "[ " + "  ".join(f"{d:.5f}" for d in D) + " ]"
    kc_sd = "[ " + "  ".join("fixed" if e == 0 else f"{SIGMAS * e:.5f}" for e in s[5:]) + " ]"
    return [
        f"{title}:",
        f"  Focal Length:     fc = [ {K[0, 0]:.5f}  {K[1, 1]:.5f} ] ± [ {SIGMAS * s[0]:.5f}  {SIGMAS * s[1]:.5f} ]",
        f"  Principal point:  cc = [ {K[0, 2]:.5f}  {K[1, 2]:.5f} ] ± [ {SIGMAS * s[2]:.5f}  {SIGMAS * s[3]:.5f} ]",
        f"  Skew:        alpha_c = {_pm(alpha, s[4] and alpha_sd)}  => angle of pixel axes = {angle:.5f} degrees",
        f"  Distortion:       kc = {kc} ± {kc_sd}",
        f"  Pixel error:     RMS = {c.rms:.5f} px over {len(c.per_view)} views",
    ]


def format_report(r: StereoResult, depth_range: tuple[float, float] | None = (0.5, 3.0), alpha: float = 0.0
                  ) -> str:
    om = cv2.Rodrigues(r.R)[0].ravel()
    lines = [f"Calibration of {len(r.views)} view pairs ({r.total_pairs} given, {len(r.without_board)} without "
             f"a board, {len(r.rejected)} rejected), pattern {r.pattern[0]}x{r.pattern[1]} inner corners, "
             f"square {r.square_size * 1000:.2f} mm, image {r.image_size[0]}x{r.image_size[1]}",
             f"Uncertainties are ± {SIGMAS:g} standard deviations (as in Bouguet's toolbox).", ""]
    lines += format_camera("Left camera", r.left) + [""] + format_camera("Right camera", r.right) + [""]
    T_mm = r.T * 1000.0
    lines += [
        "Extrinsic parameters (position of right camera wrt left camera):",
        f"  Rotation vector:     om = [ {om[0]:.5f}  {om[1]:.5f}  {om[2]:.5f} ] ± "
        f"[ {SIGMAS * r.om_std[0]:.5f}  {SIGMAS * r.om_std[1]:.5f}  {SIGMAS * r.om_std[2]:.5f} ]",
        f"  Translation vector:   T = [ {T_mm[0]:.5f}  {T_mm[1]:.5f}  {T_mm[2]:.5f} ] mm ± "
        f"[ {SIGMAS * r.T_std[0] * 1000:.5f}  {SIGMAS * r.T_std[1] * 1000:.5f}  {SIGMAS * r.T_std[2] * 1000:.5f} ]",
        "  Rotation matrix:      R = " + " / ".join("[ " + "  ".join(f"{x:+.6f}" for x in row) + " ]" for row in r.R),
        f"  Stereo RMS reprojection error: {r.rms:.5f} px",
        "",
        "Per-view RMS reprojection error (px): single-camera left / right, stereo left / right:",
    ]
    for i, v in enumerate(r.views):
        lines.append(f"  {v.name:40s} {r.left.per_view[i]:.4f} / {r.right.per_view[i]:.4f}   "
                     f"{r.per_view[i, 0]:.4f} / {r.per_view[i, 1]:.4f}")
    if r.rejected:
        lines.append("Rejected views (outliers; calibrated again without them):")
        for v, why in r.rejected:
            lines.append(f"  {v.left_path}  {v.right_path}: {why}")
    if r.without_board:
        lines.append("Pairs without a detected board (skipped): "
                     + ", ".join(v.name for v in r.without_board))
    if r.rig is not None:
        m = camera.rectify_rig(r.rig, alpha).model
        lines += ["", f"Rectified: f = {m.focal_px:.3f} px, baseline = {m.baseline_m * 1000:.3f} mm, "
                      f"principal point = [ {m.cx:.3f}  {m.cy:.3f} ] (alpha {alpha:g})"]
        if depth_range:
            d_far, d_near, nd = disparity_range(m, *depth_range)
            lines.append(f"Depth {depth_range[0]:g}..{depth_range[1]:g} m -> disparity {d_far:.1f}..{d_near:.1f} px "
                         f"(numDisparities >= {nd})")
    return "\n".join(lines)
