"""`ballbot-vision disparity LEFT RIGHT -o OUT`: the disparity core, offline, on two image files.

Output by extension: .npy float32 px with NaN where invalid; .pfm float32 px with inf where invalid
(Middlebury's convention); .png a colour picture for people (near = warm, invalid = black).
`--confidence C.png` also writes the per-pixel confidence (method dense: 0 = no measurement, 255 =
certain). A warning is printed when many matched pixels sit at the top of the search range (something
is nearer than it reaches); `--num-disparities auto` derives the range from the calibration.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from common.errors import BallbotError

FORMATS = (".npy", ".pfm", ".png")


def write_pfm(path: str, d: np.ndarray) -> None:
    """Grey PFM: little-endian float32, rows stored bottom to top; NaN becomes inf."""
    a = np.where(np.isfinite(d), d, np.inf).astype("<f4")
    with open(path, "wb") as f:
        f.write(f"Pf\n{a.shape[1]} {a.shape[0]}\n-1.0\n".encode("ascii"))
        f.write(np.ascontiguousarray(a[::-1]).tobytes())


def read_pfm(path: str) -> np.ndarray:
    """Inverse of write_pfm (inf stays inf)."""
    with open(path, "rb") as f:
        kind = f.readline().strip()
        w, h = (int(v) for v in f.readline().split())
        scale = float(f.readline())
        if kind != b"Pf":
            raise BallbotError(f"{path}: only grey PFM is supported")
        a = np.frombuffer(f.read(w * h * 4), dtype="<f4" if scale < 0 else ">f4").reshape(h, w)
    return a[::-1].astype(np.float32)


def colour(d: np.ndarray, max_disparity: float) -> np.ndarray:
    import cv2

    valid = np.isfinite(d)
    scaled = np.zeros(d.shape, np.uint8)
    scaled[valid] = np.clip(d[valid] * (255.0 / max(max_disparity, 1e-6)), 0, 255).astype(np.uint8)
    out = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
    out[~valid] = 0
    return out


def cmd_disparity(args: argparse.Namespace) -> int:
    import cv2

    from common.files import check_pair, read_image, write_image
    from common.settings import load_settings
    from cores import camera
    from cores.matching.matchers import MatcherConfig, gate_for_range
    from cores.matching.stage import MatchStage
    from cores.pipeline import Pipeline

    out = Path(args.output)
    if out.suffix.lower() not in FORMATS:
        raise BallbotError(f"-o {args.output}: the extension picks the format, one of {', '.join(FORMATS)}")
    cfg = load_settings(MatcherConfig, args.config, args)
    if cfg.threads:
        cv2.setNumThreads(cfg.threads)
    left, right = read_image(args.left, "LEFT"), read_image(args.right, "RIGHT")
    check_pair(left, right, f"LEFT {args.left}", f"RIGHT {args.right}")
    if args.confidence and Path(args.confidence).suffix.lower() != ".png":
        raise BallbotError(f"--confidence {args.confidence}: a .png file (8-bit confidence)")
    if args.calibration:  # rectified and matched as the pipeline does (cores/pipeline.py)
        pipe = Pipeline(camera.load_calibration(args.calibration), cfg)
        left, right = pipe.rectify(left, right, (args.left, args.right))
        t0 = time.perf_counter()
        stage = pipe.match(left, right)
    elif cfg.max_range_m:
        raise BallbotError("--max-range-m needs --calibration (focal length and baseline turn metres into px)")
    elif cfg.num_disparities == "auto":
        raise BallbotError("--num-disparities auto (the default) needs --calibration (focal length and baseline "
                           "give the disparity of the nearest range of interest); for a rectified pair without "
                           "one, set --num-disparities in px")
    else:  # an already-rectified pair and no camera: the same stage, no range gate
        t0 = time.perf_counter()
        stage = MatchStage(cfg).compute(left, right, 0.0, 0.0)
    ms = (time.perf_counter() - t0) * 1e3
    result, cfg = stage.match, stage.config
    d = stage.disparity_px()
    gate = gate_for_range(cfg.max_range_m, pipe.model.focal_px, pipe.model.baseline_m) if args.calibration else 0.0
    if args.confidence and result.confidence is None:
        raise BallbotError(f"--confidence: method {cfg.method} gives no confidence (method dense does)")
    out.parent.mkdir(parents=True, exist_ok=True)
    suffix = out.suffix.lower()
    if suffix == ".npy":
        np.save(out, d)
    elif suffix == ".pfm":
        write_pfm(str(out), d)
    else:
        write_image(out, colour(d, cfg.min_disparity + cfg.fixed_num_disparities))
    if args.confidence and result.confidence is not None:  # (None refused above)
        Path(args.confidence).parent.mkdir(parents=True, exist_ok=True)
        write_image(args.confidence, result.confidence)
    valid = np.isfinite(d)
    rng = f"{np.nanmin(d):.1f}..{np.nanmax(d):.1f} px" if valid.any() else "none"
    print(f"{out}: {d.shape[1]}x{d.shape[0]} {cfg.method}{' +LR' if cfg.lr_check else ''}, "
          f"{valid.mean() * 100:.1f}% valid, disparity {rng} (searched {cfg.min_disparity}..{cfg.max_disparity} px), "
          f"{ms:.1f} ms" + (f", range gate d >= {gate:.1f} px" if gate else ""))
    if result.range_warning:
        print(f"warning: {result.range_warning}", file=sys.stderr)
    return 0


def register(sub, common) -> None:
    from common.settings import add_settings_arguments
    from cores.matching.config import MatcherConfig

    p = sub.add_parser("disparity", help="disparity of one stereo pair of image files (offline, in-process)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("left")
    p.add_argument("right")
    p.add_argument("-o", "--output", required=True, help="OUT.npy, OUT.pfm or OUT.png")
    p.add_argument("--confidence", default=None, metavar="C.png",
                   help="also write the per-pixel confidence, 8-bit (method dense)")
    p.add_argument("--calibration", default=None, help="rectify first with this calibration (YAML or profile); "
                   "without it the pair must already be rectified")
    p.add_argument("--config", default=None, metavar="FILE", help="YAML file; its 'disparity' section applies")
    add_settings_arguments(p, MatcherConfig)  # matching settings only: no pool flags offline
    p.set_defaults(func=cmd_disparity)
