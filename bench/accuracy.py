"""Disparity accuracy on real pairs with ground truth, every method beside OpenCV's own settings.

Pairs (every real pair with ground truth that ships in a package here):
  motorcycle  Middlebury 2014 "Motorcycle", quarter size 741x500, from scikit-image
              (skimage.data.stereo_motorcycle; pip install scikit-image, or this project's `test` extra)
  aloe        Middlebury 2006 "Aloe" from OpenCV's samples (Debian: apt-get install opencv-doc), at half
              size 641x555 as OpenCV's own stereo_match.py runs it (pyrDown); ground truth halved
Each pair is searched over the same range by every method (0..63 px and 0..111 px: both cover the
ground truth; OpenCV's python sample uses 16..111 on aloe).

Metrics, over the pixels with ground truth: bad-1 / bad-2 / bad-4 = share with |d - gt| > 1, 2, 4 px,
INVALID COUNTED AS BAD (what a segmenter actually gets); EPE = mean |d - gt| with invalid pixels
filled by KITTI's background interpolation (the nearer-to-infinity neighbour on the row), so a
method cannot lower its EPE by leaving pixels out; invalid = share without a disparity.

OpenCV baselines, honest ones (documented or recommended settings, never P1 = P2 = 0 alone):
  opencv-bm-9         StereoBM with samples/cpp/stereo_match.cpp's settings (block 9, uniqueness 15,
                      speckle 100/32, prefilter cap 31, texture 10, disp12MaxDiff 1)
  opencv-bm-15        the same with block 15, the block size of our bm
  opencv-sgbm-default StereoSGBM_create(0, range): OpenCV's defaults (P1 = P2 = 0, block 3), reference
  opencv-sgbm-sample  stereo_match.cpp's SGBM on the colour pair: block 3, P1 = 8*cn*w^2, P2 = 32*cn*w^2
                      (OpenCV's recommended penalties), prefilter cap 63, uniqueness 10, speckle 100/32,
                      disp12MaxDiff 1, 5 paths
  opencv-sgbm-hh      the same, full 8 paths (MODE_HH)
  opencv-sgbm-3way    the same, MODE_SGBM_3WAY
  opencv-sgbm-5       the sample's settings with block 5 (recommended penalties for w = 5)
Ours: bm, bm+lr, sgbm, sgbm+lr (the service's defaults), dense (matching on grey, colour guides the
fill). The target of dense: at least 25 % fewer bad-2 pixels than the best OpenCV row on each pair.

Timing: every method on one 640x480 pair (the synthetic world rendered for the thesis rig, 64
disparities), median of several runs with OpenCV's default threads (one worker), and as a ratio to
opencv-sgbm-sample measured in the same run.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

OPENCV_DOC_DATA = Path("/usr/share/doc/opencv-doc/examples/data")
THRESHOLDS = (1.0, 2.0, 4.0)
OPENCV_METHODS = ["opencv-bm-9", "opencv-bm-15", "opencv-sgbm-default", "opencv-sgbm-sample",
                  "opencv-sgbm-hh", "opencv-sgbm-3way", "opencv-sgbm-5"]
OUR_METHODS = ["bm", "bm+lr", "sgbm", "sgbm+lr", "dense"]
REFERENCE = "opencv-sgbm-sample"


@dataclass
class Pair:
    name: str
    source: str
    left: np.ndarray  # (H, W, 3) BGR uint8, rectified
    right: np.ndarray
    gt: np.ndarray  # (H, W) float32 px, NaN = unknown
    num_disparities: int


class MissingPair(Exception):
    """A pair's package is not installed: the message says how to install it."""


def motorcycle() -> Pair:
    try:
        from skimage import data
    except ImportError:
        raise MissingPair("motorcycle: scikit-image is not installed (pip install scikit-image, "
                          "or this project's 'test' extra)") from None
    import cv2

    left, right, gt = data.stereo_motorcycle()
    gt = np.where(np.isfinite(gt), gt, np.nan).astype(np.float32)
    return Pair("motorcycle", "Middlebury 2014 Motorcycle, quarter size (scikit-image)",
                cv2.cvtColor(left, cv2.COLOR_RGB2BGR), cv2.cvtColor(right, cv2.COLOR_RGB2BGR), gt, 64)


def aloe(data_dir: Path = OPENCV_DOC_DATA) -> Pair:
    import cv2

    files = [data_dir / n for n in ("aloeL.jpg", "aloeR.jpg", "aloeGT.png")]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise MissingPair(f"aloe: {', '.join(missing)} not found (Debian: apt-get install opencv-doc)")
    left, right = (cv2.imread(str(f), cv2.IMREAD_COLOR) for f in files[:2])
    gt_full = cv2.imread(str(files[2]), cv2.IMREAD_GRAYSCALE)
    if left is None or right is None or gt_full is None:
        raise MissingPair(f"aloe: cannot read the images in {data_dir}")
    # Middlebury 2006 ground truth: disparity in px at full size, 0 = unknown. Halved with the images.
    left, right = cv2.pyrDown(left), cv2.pyrDown(right)
    gt = gt_full[::2, ::2].astype(np.float32) / 2.0
    gt[gt_full[::2, ::2] == 0] = np.nan
    h, w = left.shape[:2]
    return Pair("aloe", "Middlebury 2006 Aloe, half size (opencv-doc)", left, right, gt[:h, :w], 112)


PAIRS = {"motorcycle": motorcycle, "aloe": aloe}


def available_pairs(names: list[str] | None = None) -> list[Pair]:
    """The pairs whose packages are installed (others are left out silently)."""
    out = []
    for n in names or PAIRS:
        try:
            out.append(PAIRS[n]())
        except MissingPair:
            pass
    return out


def scores(d: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """d: (H, W) float32 px, NaN = invalid; gt likewise (NaN = unknown). -> bad-1/2/4 (invalid is
    bad), EPE (invalid filled by background interpolation), invalid, as fractions / px."""
    from cores.matching.dense import background_fill

    has = np.isfinite(gt)
    n = max(1, int(has.sum()))
    valid = np.isfinite(d) & has
    err = np.abs(np.where(valid, d, 0) - np.where(has, gt, 0))
    out = {f"bad{t:g}": float(((valid & (err > t)) | (has & ~valid)).sum() / n) for t in THRESHOLDS}
    filled = background_fill(d.astype(np.float32)) if np.isfinite(d).any() else np.zeros_like(d)
    out["epe"] = float(np.abs(np.nan_to_num(filled) - np.where(has, gt, 0))[has].mean())
    out["invalid"] = float((has & ~valid).sum() / n)
    return out


def opencv_baselines(num_disparities: int) -> dict:
    """name -> (OpenCV matcher object, whether it matches the colour pair): the OpenCV rows, with
    the documented settings the module docstring lists."""
    import cv2

    def bm_sample(block):
        m = cv2.StereoBM.create(num_disparities, block)
        m.setPreFilterCap(31)
        m.setTextureThreshold(10)
        m.setUniquenessRatio(15)
        m.setSpeckleWindowSize(100)
        m.setSpeckleRange(32)
        m.setDisp12MaxDiff(1)
        return m, False

    def sgbm_sample(block, mode=cv2.STEREO_SGBM_MODE_SGBM, cn=3):
        # OpenCV's recommended penalties for cn channels and a block of w = block (stereo_match.cpp)
        return cv2.StereoSGBM.create(0, num_disparities, block, P1=8 * cn * block * block,
                                     P2=32 * cn * block * block, disp12MaxDiff=1, preFilterCap=63,
                                     uniquenessRatio=10, speckleWindowSize=100, speckleRange=32, mode=mode), cn == 3

    return {
        "opencv-bm-9": bm_sample(9),
        "opencv-bm-15": bm_sample(15),
        "opencv-sgbm-default": (cv2.StereoSGBM.create(0, num_disparities), True),
        "opencv-sgbm-sample": sgbm_sample(3),
        "opencv-sgbm-hh": sgbm_sample(3, cv2.STEREO_SGBM_MODE_HH),
        "opencv-sgbm-3way": sgbm_sample(3, cv2.STEREO_SGBM_MODE_SGBM_3WAY),
        "opencv-sgbm-5": sgbm_sample(5),
    }


def matchers(num_disparities: int) -> dict:
    """name -> run(left_bgr, right_bgr) -> float32 px, NaN invalid."""
    from cores.matching.matchers import MatcherConfig, gray
    from cores.matching.stage import MatchStage

    def opencv(m, colour: bool):
        invalid = (m.getMinDisparity() - 1) * 16

        def run(left, right):
            raw = m.compute(left, right) if colour else m.compute(gray(left), gray(right))
            d = raw.astype(np.float32) / 16.0
            d[raw <= invalid] = np.nan
            return d
        return run

    def ours(**kw):  # the disparity stage the services run (no camera here: no range gate)
        stage = MatchStage(MatcherConfig(num_disparities=num_disparities, **kw))
        return lambda left, right: stage.compute(left, right, 0.0, 0.0).disparity_px()

    runs = {name: opencv(m, colour) for name, (m, colour) in opencv_baselines(num_disparities).items()}
    return {
        **runs,
        "bm": ours(method="bm"),
        "bm+lr": ours(method="bm", lr_check=True),
        "sgbm": ours(method="sgbm"),
        "sgbm+lr": ours(method="sgbm", lr_check=True),
        "dense": ours(method="dense"),
    }


def _median_ms(run, left, right, repeats: int) -> tuple[np.ndarray, float, float]:
    """-> (last result, median wall ms, median process CPU ms: all threads' work, which a busy
    machine inflates less than the wall time)."""
    wall, cpu = [], []
    for _ in range(max(1, repeats)):
        t0, c0 = time.perf_counter(), time.process_time()
        d = run(left, right)
        wall.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return d, float(np.median(wall)), float(np.median(cpu))


def evaluate_pair(pair: Pair, methods: list[str] | None = None, repeats: int = 1) -> dict[str, dict]:
    runs = matchers(pair.num_disparities)
    rows = {}
    for name in methods or list(runs):
        d, ms, _ = _median_ms(runs[name], pair.left, pair.right, repeats)
        rows[name] = {**scores(d, pair.gt), "ms": ms}
    return rows


def timing_pair() -> tuple[np.ndarray, np.ndarray]:
    """One rectified 640x480 pair: the synthetic world for the thesis rig (no package needed)."""
    import sim as S
    from cores import camera
    from cores.calibration.rectify import Rectifier

    rig = camera.load_raw_rig("lifecam-studio")
    world = S.SyntheticWorld(S.Scene.default(), rig, camera.rectify_rig(rig, 0.0), seed=0)
    left, right = Rectifier(rig).rectify(*world.render(0.0))
    if left.ndim == 2:
        import cv2
        left, right = cv2.cvtColor(left, cv2.COLOR_GRAY2BGR), cv2.cvtColor(right, cv2.COLOR_GRAY2BGR)
    return left, right


def timings(repeats: int = 7, methods: list[str] | None = None) -> dict:
    left, right = timing_pair()
    runs = matchers(64)
    rows = {}
    for name in methods or list(runs):
        _, ms, cpu_ms = _median_ms(runs[name], left, right, repeats)
        rows[name] = {"ms": ms, "fps": 1e3 / ms, "cpu_ms": cpu_ms}
    ref = rows.get(REFERENCE)
    for r in rows.values():
        r["x_reference"] = r["ms"] / ref["ms"] if ref else float("nan")
        r["cpu_x_reference"] = r["cpu_ms"] / ref["cpu_ms"] if ref else float("nan")
    import os

    import cv2

    return {"size": f"{left.shape[1]}x{left.shape[0]}", "num_disparities": 64, "repeats": repeats,
            "reference": REFERENCE, "opencv_threads": cv2.getNumThreads(),
            "load_average_1min": os.getloadavg()[0], "methods": rows}


def accuracy_report(pair_names: list[str] | None = None, repeats: int = 1, timing_repeats: int = 7) -> dict:
    """-> {"pairs": {name: {source, size, num_disparities, methods, best_opencv, dense_vs_best}}, "timing",
    "missing": [messages]}."""
    report: dict = {"pairs": {}, "missing": []}
    pairs = []
    for n in pair_names or list(PAIRS):
        try:
            pairs.append(PAIRS[n]())
        except MissingPair as e:
            report["missing"].append(str(e))
    if report["missing"]:  # an incomplete comparison is no result: say what to install, run nothing
        return report
    for pair in pairs:
        n = pair.name
        rows = evaluate_pair(pair, repeats=repeats)
        best = min(OPENCV_METHODS, key=lambda m: rows[m]["bad2"])
        report["pairs"][n] = {"source": pair.source, "size": f"{pair.left.shape[1]}x{pair.left.shape[0]}",
                              "num_disparities": pair.num_disparities, "methods": rows, "best_opencv": best,
                              "dense_bad2_vs_best": rows["dense"]["bad2"] / max(rows[best]["bad2"], 1e-9) - 1}
    report["timing"] = timings(timing_repeats)
    return report


def print_report(r: dict, out=sys.stdout) -> None:
    for name, p in r["pairs"].items():
        print(f"{name}: {p['source']}, {p['size']}, disparities 0..{p['num_disparities'] - 1}; invalid counts "
              f"as bad; EPE with invalid background-filled", file=out)
        print(f"  {'method':20} {'bad-1':>7} {'bad-2':>7} {'bad-4':>7} {'EPE px':>7} {'invalid':>8} {'ms':>7}",
              file=out)
        for m, s in p["methods"].items():
            print(f"  {m:20} {s['bad1'] * 100:6.1f}% {s['bad2'] * 100:6.1f}% {s['bad4'] * 100:6.1f}% "
                  f"{s['epe']:7.2f} {s['invalid'] * 100:7.1f}% {s['ms']:7.1f}", file=out)
        print(f"  dense: {-p['dense_bad2_vs_best'] * 100:.0f} % fewer bad-2 pixels than the best OpenCV setting "
              f"({p['best_opencv']}; target >= 25 %)", file=out)
    t = r.get("timing")
    if not t:
        return
    print(f"time per {t['size']} pair, {t['num_disparities']} disparities, median of {t['repeats']}, "
          f"{t['opencv_threads']} OpenCV threads, load average {t['load_average_1min']:.1f}; x = ratio to "
          f"{t['reference']} in this run (wall; CPU = all threads' work, steadier on a busy machine):", file=out)
    print(f"  {'method':20} {'wall ms':>8} {'fps':>6} {'x':>5}  {'CPU ms':>7} {'x':>5}", file=out)
    for m, s in t["methods"].items():
        print(f"  {m:20} {s['ms']:8.1f} {s['fps']:6.1f} {s['x_reference']:5.2f}  {s['cpu_ms']:7.1f} "
              f"{s['cpu_x_reference']:5.2f}", file=out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pairs", nargs="+", choices=list(PAIRS), default=None, help="default: all")
    p.add_argument("--repeats", type=int, default=1, help="runs per method and pair (median time)")
    p.add_argument("--timing-repeats", type=int, default=7, help="runs per method on the 640x480 pair")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    r = accuracy_report(a.pairs, a.repeats, a.timing_repeats)
    if r["missing"]:
        print("bench accuracy: incomplete, a pair with ground truth is missing:\n  " + "\n  ".join(r["missing"]),
              file=sys.stderr)
        return 2
    print(json.dumps(r, indent=2)) if a.json else print_report(r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
