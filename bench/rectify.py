"""`ballbot-vision bench rectify`: what one rectified pair costs with float and with fixed-point
remap tables, and how far each is from the exact bilinear resampling of the same maps.

Rigs: the synthetic scene's (lifecam-studio, 640x480) and, when the real EuRoC recording is
there (../shared/data/real/euroc-v1-01, raw 752x480 with strong distortion), its first pair with
the calibration imported from its sensor files. CPU is this process's CPU time per pair (all
threads), with one OpenCV thread and with OpenCV's default; float and fixed are interleaved in
rounds so a load change on a shared machine moves both alike.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from common.errors import CalibrationError, FileError
from cores.calibration.rectify import Rectifier
from cores.camera import Calibration

EUROC = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "euroc-v1-01"
if not EUROC.is_dir():
    EUROC = Path("/work/shared/data/real/euroc-v1-01")


def rigs() -> list[tuple[str, Calibration, np.ndarray, np.ndarray]]:
    """-> [(name, calibration, raw left, raw right)]"""
    from cores import camera
    from services.capture.sources import SyntheticSource

    out: list[tuple[str, Calibration, np.ndarray, np.ndarray]] = []
    pair = SyntheticSource("two-boxes", "lifecam-studio", 30.0, preload=1).read()
    out.append(("synthetic lifecam-studio 640x480", camera.load_calibration("lifecam-studio"), pair.left, pair.right))
    if (EUROC / "cam0_sensor.yaml").exists():
        from cores.calibration import formats

        rig = formats.import_files([str(EUROC / "cam0_sensor.yaml"), str(EUROC / "cam1_sensor.yaml")])
        first = sorted((EUROC / "cam0").iterdir())[0].name
        left = cv2.imread(str(EUROC / "cam0" / first), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(EUROC / "cam1" / first), cv2.IMREAD_GRAYSCALE)
        if left is None or right is None:
            raise FileError(f"{EUROC}: cannot read the pair {first}")
        out.append((f"EuRoC V1_01 raw {left.shape[1]}x{left.shape[0]}", rig, left, right))
    return out


def exact(image: np.ndarray, mx: np.ndarray, my: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear resampling of `image` at float64 positions (mx, my) -> (values, mask of positions
    at least 1 px inside the image, where no border rule is involved)."""
    from scipy import ndimage

    ref = ndimage.map_coordinates(image.astype(np.float64), [my.astype(np.float64), mx.astype(np.float64)],
                                  order=1, mode="nearest")
    h, w = image.shape[:2]
    inside = (mx >= 1) & (my >= 1) & (mx <= w - 2) & (my <= h - 2)
    return ref, inside


def _maps_of(r: Rectifier) -> tuple:
    if r._maps is None:  # an already rectified calibration: nothing is resampled
        raise CalibrationError("bench rectify: this needs a raw rig, not a rectified calibration")
    return r._maps


def accuracy(cal, left: np.ndarray, right: np.ndarray) -> dict:
    """Per map type: grey-level error against the exact resampling at the float maps' positions
    (max, share above 1 grey level) and the largest source-position error of its maps, px."""
    exact_maps = _maps_of(Rectifier(cal, maps="float"))
    out = {}
    for kind in ("float", "fixed"):
        r = Rectifier(cal, maps=kind)
        rl, rr = r.rectify(left, right)
        err, above, pos = 0.0, 0, 0.0
        n = 0
        for (mx, my), (a, b), img, got in zip(exact_maps, _maps_of(r), (left, right), (rl, rr)):
            ref, inside = exact(img, mx, my)
            d = np.abs(got.astype(np.float64) - ref)[inside]
            err, above, n = max(err, float(d.max())), above + int((d > 1.0).sum()), n + d.size
            fx, fy = (a, b) if kind == "float" else cv2.convertMaps(a, b, cv2.CV_32FC1)
            pos = max(pos, float(np.abs(fx - mx).max()), float(np.abs(fy - my).max()))
        out[kind] = {"max_grey_error": err, "share_above_1_grey": above / n, "max_position_error_px": pos}
    return out


def cpu_per_pair(cal, left: np.ndarray, right: np.ndarray, threads: int, rounds: int = 5, n: int = 40) -> dict:
    """CPU ms per rectified pair (process time, every thread), median over interleaved rounds."""
    rect = {k: Rectifier(cal, maps=k) for k in ("float", "fixed")}
    before = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    times: dict[str, list[float]] = {k: [] for k in rect}
    try:
        for _ in range(rounds):
            for k, r in rect.items():
                r.rectify(left, right)
                c0 = time.process_time()
                for _ in range(n):
                    r.rectify(left, right)
                times[k].append((time.process_time() - c0) * 1e3 / n)
    finally:
        cv2.setNumThreads(before)
    return {k: float(np.median(v)) for k, v in times.items()}


def bench_rectify() -> dict:
    default_threads = cv2.getNumThreads()
    out: dict[str, Any] = {"load_avg_1min": os.getloadavg()[0], "opencv": cv2.__version__, "rigs": []}
    for name, cal, left, right in rigs():
        out["rigs"].append({"rig": name, "accuracy": accuracy(cal, left, right),
                            "cpu_ms_1_thread": cpu_per_pair(cal, left, right, 1),
                            f"cpu_ms_{default_threads}_threads": cpu_per_pair(cal, left, right, default_threads)})
    out["load_avg_1min_end"] = os.getloadavg()[0]
    return out


def format_rectify(r: dict) -> str:
    lines = [f"rectification, one pair, OpenCV {r['opencv']} (load avg {r['load_avg_1min']:.1f} -> "
             f"{r['load_avg_1min_end']:.1f}):"]
    for g in r["rigs"]:
        lines.append(f"  {g['rig']}:")
        for kind in ("float", "fixed"):
            a = g["accuracy"][kind]
            cpu = ", ".join(f"{k[len('cpu_ms_'):].replace('_', ' ')} {v[kind]:.2f} ms" for k, v in g.items()
                            if k.startswith("cpu_ms_"))
            lines.append(f"    {kind:5} maps: CPU per pair {cpu}; "
                         f"vs exact bilinear: max {a['max_grey_error']:.2f} grey, "
                         f"{a['share_above_1_grey']:.3%} of pixels > 1 grey, source positions within "
                         f"{a['max_position_error_px']:.4f} px")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="ballbot-vision bench rectify")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    r = bench_rectify()
    print(json.dumps(r, indent=2) if args.json else format_rectify(r))
    return 0
