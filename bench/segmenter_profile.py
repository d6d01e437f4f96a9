"""`ballbot-vision bench segmenter --profile`: where the segmenter service's time per frame goes, step
by step, at 640x480: the service's own path (its OpenCV threads; decode the DisparityMap message, ObstacleBuilder with
the service's default settings, encode the obstacle list and the free-space grid) on the pipeline
bench's frames (the two-boxes scenario, the lifecam-studio rig, the default matcher), under cProfile.

Reported per frame: the wall time of the whole path without the profiler (the reference), then
the profiled cumulative CPU time of the functions of cores/segmentation (the steps) and of the
heaviest library calls (the hot spots). cProfile adds its own overhead to every Python call, so
per-step times are for telling where the time goes, not for adding up to the reference.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import time


def service_frames(n: int = 16) -> list[bytes]:
    """DisparityMap payloads as the segmenter receives them, from the pipeline bench's pairs."""
    from bench.scaling import rectified_frames
    from common import codec
    from cores.matching.matchers import MatcherConfig
    from services.disparity.computer import FrameComputer

    computer = FrameComputer(MatcherConfig())  # the map as the disparity service publishes it
    out = []
    for frame in rectified_frames(n):
        frame.stamp_ns = time.time_ns()
        out.append(codec.encode(computer.compute(frame, "bench")))
    return out


def _path(payloads: list[bytes]):
    from common import codec
    from common.messages import DisparityMap
    from cores.segmentation.builder import ObstacleBuilder
    from cores.segmentation.settings import SegmenterSettings

    builder = ObstacleBuilder(SegmenterSettings())
    state = {"k": 0}

    def one() -> None:
        k = state["k"]
        state["k"] += 1
        msg = codec.decode(payloads[k % len(payloads)], DisparityMap)
        result = builder.process_message(msg, stale=False, t_s=k / 30.0)
        codec.encode(result.obstacles)
        if result.freespace is not None:
            codec.encode(result.freespace)

    return one


def profile_segmenter(frames: int = 200, top: int = 25) -> dict:
    import cv2

    from services.segmenter.main import OPENCV_THREADS

    payloads = service_frames()
    before = cv2.getNumThreads()
    cv2.setNumThreads(OPENCV_THREADS)  # as the service runs
    try:
        return _profile(_path(payloads), frames, top)
    finally:
        cv2.setNumThreads(before)


def _profile(one, frames: int, top: int) -> dict:  # type: ignore[no-untyped-def]
    for _ in range(5):  # first calls import and allocate (scipy's tracker)
        one()
    c0, t0 = time.process_time(), time.perf_counter()
    for _ in range(frames):
        one()
    wall_ms, cpu_ms = (time.perf_counter() - t0) * 1e3 / frames, (time.process_time() - c0) * 1e3 / frames
    prof = cProfile.Profile(time.process_time)  # CPU time: on a shared machine, wall time is mostly waiting
    prof.enable()
    for _ in range(frames):
        one()
    prof.disable()
    st = pstats.Stats(prof)
    rows = []
    for (path, line, fn), (_cc, nc, tt, ct, _) in st.stats.items():  # type: ignore[attr-defined]
        rows.append({"function": fn, "where": _where(path, line), "calls_per_frame": nc / frames,
                     "cum_ms": ct * 1e3 / frames, "own_ms": tt * 1e3 / frames})
    profiled_ms = sum(r["own_ms"] for r in rows)
    steps = {parent: _callees(st, parent, where, frames)[:top] for parent, where in STEP_PARENTS.items()}
    hot = sorted(rows, key=lambda r: -r["own_ms"])[:top]
    return {"image": "640x480", "frames": frames, "wall_ms_per_frame": wall_ms, "cpu_ms_per_frame": cpu_ms,
            "profiled_ms_per_frame": profiled_ms, "steps": steps, "hot_spots": hot,
            "load_avg_1min": os.getloadavg()[0]}


# the functions whose direct callees are the steps: the service's frame, the builder, the layers
STEP_PARENTS = {"one": "bench/segmenter_profile.py", "process": "cores/segmentation/builder.py",
                "segment_frame": "cores/segmentation/layers.py"}


def _where(path: str, line: int) -> str:
    for marker in ("site-packages/", "/cores/", "/common/", "/bench/"):
        if marker in path:
            return (marker.strip("/") + "/" if marker != "site-packages/" else "") + path.split(marker)[-1] + f":{line}"
    return f"{path}:{line}"


def _callees(st: pstats.Stats, parent: str, where: str, frames: int) -> list[dict]:
    """The functions `parent` (by name, in a file whose path ends with `where`) calls, with the
    CPU they took from it, heaviest first."""
    parents = [f for f in st.stats if f[2] == parent and f[0].endswith(where)]  # type: ignore[attr-defined]
    out = []
    for func, (_, _, _, _, callers) in st.stats.items():  # type: ignore[attr-defined]
        for p in parents:
            if p in callers:
                nc, _, tt, ct = callers[p]
                out.append({"function": func[2], "where": _where(func[0], func[1]), "calls_per_frame": nc / frames,
                            "cum_ms": ct * 1e3 / frames, "own_ms": tt * 1e3 / frames})
    return sorted(out, key=lambda r: -r["cum_ms"])


def format_profile(r: dict) -> str:
    lines = [f"segmenter service path at {r['image']} (decode, ObstacleBuilder with the default settings, encode), "
             f"{r['frames']} frames: {r['wall_ms_per_frame']:.2f} ms wall, {r['cpu_ms_per_frame']:.2f} ms CPU per "
             f"frame without the profiler ({r['profiled_ms_per_frame']:.2f} ms under it); load avg "
             f"{r['load_avg_1min']:.1f}",
             f"  {'cum ms':>7} {'own ms':>7} {'calls':>7}  function (CPU per frame under the profiler)"]
    titles = {"one": "the service's frame: decode, build, encode", "process": "ObstacleBuilder.process",
              "segment_frame": "layers.segment_frame (the default method)"}
    for parent, rows in r["steps"].items():
        lines.append(f"steps of {titles.get(parent, parent)}:")
        for s in rows:
            if s["cum_ms"] >= 0.05:
                lines.append(f"  {s['cum_ms']:7.3f} {s['own_ms']:7.3f} {s['calls_per_frame']:7.1f}  {s['function']} "
                             f"({s['where']})")
    lines.append("hot spots (own CPU time, any function), ms per frame:")
    for s in r["hot_spots"]:
        lines.append(f"  {s['own_ms']:7.3f} {'':7} {s['calls_per_frame']:7.1f}  {s['function']} ({s['where']})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="ballbot-vision bench segmenter --profile")
    p.add_argument("--json", action="store_true")
    p.add_argument("--frames", type=int, default=200)
    args = p.parse_args(argv)
    r = profile_segmenter(args.frames)
    print(json.dumps(r, indent=2) if args.json else format_profile(r))
    return 0
