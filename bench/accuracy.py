"""Disparity accuracy on real pairs with ground truth: bad-2px rate (|d - gt| > 2 px, invalid
counts as bad, over pixels with ground truth) of each method beside OpenCV's defaults.

Pairs: Middlebury 2014 "Motorcycle" as shipped by scikit-image (`skimage.data.stereo_motorcycle`,
quarter size, 741x500, ground truth in px with inf = unknown). Optional: scikit-image is only in
the `test` extra. The matching runs on grey images, as in the service.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

BAD_PX = 2.0


def motorcycle():
    """-> (left, right) uint8 grey, ground truth float32 px (NaN = unknown), or None without skimage."""
    try:
        from skimage import data
    except ImportError:
        return None
    import cv2

    left, right, gt = data.stereo_motorcycle()
    gt = np.where(np.isfinite(gt), gt, np.nan).astype(np.float32)
    return (cv2.cvtColor(left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(right, cv2.COLOR_RGB2GRAY), gt)


def bad_rate(disparity_px: np.ndarray, gt: np.ndarray, threshold: float = BAD_PX) -> dict[str, float]:
    """disparity_px: float32 px, NaN invalid. -> bad (invalid counts as bad), invalid and bad among
    valid, as fractions of the pixels with ground truth."""
    has = np.isfinite(gt)
    valid = np.isfinite(disparity_px) & has
    err = np.abs(np.where(valid, disparity_px, 0) - np.where(has, gt, 0))
    wrong = valid & (err > threshold)
    n = max(1, int(has.sum()))
    return {"bad": float((wrong.sum() + (has & ~valid).sum()) / n), "invalid": float((has & ~valid).sum() / n),
            "bad_of_valid": float(wrong.sum() / max(1, valid.sum()))}


def methods(num_disparities: int):
    """name -> compute(left, right) -> float px with NaN invalid."""
    import cv2

    from ..common.disparity import to_float
    from ..services.disparity.matchers import MatcherConfig, StereoMatcher

    def opencv(make):
        def run(l, r):
            raw = make().compute(l, r)
            d = raw.astype(np.float32) / 16.0
            d[raw < 0] = np.nan  # OpenCV marks failures with (minDisparity - 1) * 16
            return d
        return run

    def ours(**kw):
        cfg = MatcherConfig(num_disparities=num_disparities, **kw)
        m = StereoMatcher(cfg)
        return lambda l, r: to_float(m.compute(l, r), 16.0, cfg.invalid_value)

    return {
        "opencv-default-bm": opencv(lambda: cv2.StereoBM_create(numDisparities=num_disparities)),
        "opencv-default-sgbm": opencv(lambda: cv2.StereoSGBM_create(numDisparities=num_disparities)),
        "bm": ours(method="bm"),
        "bm+lr": ours(method="bm", lr_check=True),
        "sgbm": ours(method="sgbm"),
        "sgbm+lr": ours(method="sgbm", lr_check=True),
    }


def accuracy_table(num_disparities: int = 64) -> dict:
    pair = motorcycle()
    if pair is None:
        return {"error": "scikit-image is not installed (pip install scikit-image, or the 'test' extra)"}
    left, right, gt = pair
    rows = {}
    for name, run in methods(num_disparities).items():
        t0 = time.perf_counter()
        d = run(left, right)
        ms = (time.perf_counter() - t0) * 1e3
        rows[name] = {**bad_rate(d, gt), "ms": ms}
    return {"pair": "middlebury-2014 motorcycle (scikit-image, 741x500)", "num_disparities": num_disparities,
            "threshold_px": BAD_PX, "methods": rows}


def print_table(t: dict, out=sys.stdout) -> None:
    if "error" in t:
        print(f"accuracy: {t['error']}", file=out)
        return
    print(f"accuracy on {t['pair']}, {t['num_disparities']} disparities; bad = |d - gt| > "
          f"{t['threshold_px']:g} px or invalid, over pixels with ground truth", file=out)
    print(f"{'method':22} {'bad-2px':>8} {'invalid':>8} {'bad/valid':>9} {'ms':>7}", file=out)
    for name, r in t["methods"].items():
        print(f"{name:22} {r['bad'] * 100:7.1f}% {r['invalid'] * 100:7.1f}% {r['bad_of_valid'] * 100:8.1f}% "
              f"{r['ms']:7.1f}", file=out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--num-disparities", type=int, default=64)
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    t = accuracy_table(a.num_disparities)
    print(json.dumps(t, indent=2)) if a.json else print_table(t)
    return 0


if __name__ == "__main__":
    sys.exit(main())
