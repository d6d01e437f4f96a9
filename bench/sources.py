"""Frames per second of each file-backed capture source at 640x480: how fast `capture` can read,
decode and split pairs when nothing paces it (pace=max). Encoding for the wire and Zenoh are not
included (`ballbot-vision bench` measures the pipeline).

    python -m bench.sources [--frames 150] [--size 640x480] [--json]

The content is the synthetic world's textured scene (what block matching needs, and harder for
JPEG/PNG than flat test patterns), rendered once and written by this benchmark to a temporary
folder as: PNG and JPEG image folders, two MJPG .avi files, one side-by-side MJPG .avi, and the
`cameras` source driven through cv2.VideoCapture on the two .avi files (decode cost of two MJPG
cameras, without the USB).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def _scene_pairs(n: int, width: int, height: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """n distinct BGR pairs of the synthetic scene (resized if another size is asked for)."""
    from services.capture.sources import SyntheticSource

    src = SyntheticSource("two-boxes", "lifecam-studio", 30.0)
    out = []
    for _ in range(n):
        p = src.read()
        pair = []
        for img in (p.left, p.right):
            if img.shape[:2] != (height, width):
                img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
            pair.append(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img)
        out.append((pair[0], pair[1]))
    return out


def write_files(root: Path, frames: int, width: int = 640, height: int = 480, distinct: int = 12) -> dict:
    """The benchmark's inputs under root: {name: settings for CaptureSettings}."""
    pairs = _scene_pairs(min(distinct, frames), width, height)
    for d in ("png/left", "png/right", "jpg/left", "jpg/right"):
        (root / d).mkdir(parents=True, exist_ok=True)
    fourcc = cv2.VideoWriter.fourcc(*"MJPG")
    writers = {"left": cv2.VideoWriter(str(root / "left.avi"), fourcc, 30.0, (width, height)),
               "right": cv2.VideoWriter(str(root / "right.avi"), fourcc, 30.0, (width, height)),
               "sbs": cv2.VideoWriter(str(root / "sbs.avi"), fourcc, 30.0, (2 * width, height))}
    for i in range(frames):
        left, right = pairs[i % len(pairs)]
        for side, img in (("left", left), ("right", right)):
            cv2.imwrite(str(root / f"png/{side}/{i:06d}.png"), img[:, :, 0])  # grey, as rectified datasets
            cv2.imwrite(str(root / f"jpg/{side}/{i:06d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        writers["left"].write(left)
        writers["right"].write(right)
        writers["sbs"].write(np.hstack([left, right]))
    for w in writers.values():
        w.release()
    return {
        "images-png": dict(source="images", images_left=str(root / "png/left"), images_right=str(root / "png/right")),
        "images-jpeg": dict(source="images", images_left=str(root / "jpg/left"), images_right=str(root / "jpg/right")),
        "video": dict(source="video", video_left=str(root / "left.avi"), video_right=str(root / "right.avi")),
        "video-sbs": dict(source="video", video_left=str(root / "sbs.avi")),
        "cameras-on-video": dict(source="cameras", camera_left=str(root / "left.avi"),
                                 camera_right=str(root / "right.avi")),
    }


def measure(settings: dict, frames: int) -> dict:
    """Open the source as `capture` would (pace=max) and read every pair; pairs/s and ms/pair."""
    from services.capture.main import open_source
    from services.capture.settings import CaptureSettings
    from services.capture.sources import SourceContext

    s = CaptureSettings(pace="max", **settings)
    opener = (lambda spec: cv2.VideoCapture(str(spec))) if s.source == "cameras" else None
    t0 = time.perf_counter()
    src = open_source(s, SourceContext(), opener)
    t_open = time.perf_counter() - t0
    n, shape = 0, None
    t0 = time.perf_counter()
    try:
        while n < frames:
            pair = src.read()
            if pair is None:
                break
            shape = pair.left.shape
            n += 1
    finally:
        src.close()
    dt = time.perf_counter() - t0
    return {"pairs": n, "seconds": dt, "fps": n / dt if dt else 0.0, "ms_per_pair": 1e3 * dt / max(n, 1),
            "open_s": t_open, "image": "x".join(map(str, (shape[1], shape[0]) + shape[2:])) if shape else ""}


def bench_sources(frames: int = 150, width: int = 640, height: int = 480, only: list[str] | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="ballbot-bench-sources-") as tmp:
        cases = write_files(Path(tmp), frames, width, height)
        results = {name: measure(cfg, frames) for name, cfg in cases.items() if not only or name in only}
    return {"width": width, "height": height, "frames": frames, "opencv": cv2.__version__,
            "threads": cv2.getNumThreads(), "sources": results}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.sources", description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=150, help="pairs per source")
    p.add_argument("--size", default="640x480", help="WIDTHxHEIGHT of one camera image")
    p.add_argument("--only", action="append", default=None, help="one source case (repeatable)")
    p.add_argument("--json", action="store_true", help="one JSON document on stdout")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)  # "the driver refused ..." is expected on files
    width, height = (int(v) for v in args.size.lower().split("x"))
    r = bench_sources(args.frames, width, height, args.only)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(f"capture sources, {width}x{height} per camera, {args.frames} pairs, as fast as possible "
          f"(OpenCV {r['opencv']}, {r['threads']} threads)")
    print(f"{'source':18} {'pairs/s':>8} {'ms/pair':>8}  image")
    for name, m in r["sources"].items():
        print(f"{name:18} {m['fps']:8.1f} {m['ms_per_pair']:8.2f}  {m['image']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
