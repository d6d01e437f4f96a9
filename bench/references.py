"""The references every `bench` run measures in the same run, on the same frames: OpenCV's matcher
alone (the service's settings, 2 threads and 1) and the in-process per-frame compute (the one
pipeline, cores/pipeline.py, no messaging). The pipeline's figures are ratios of these."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from cores.calibration.rectify import Rectifier

# --- the frames and the references ---------------------------------------------------------------

@dataclass
class Frames:
    """The pairs capture loops (same scenario, rig, seed and noise as `run capture --preload N`),
    raw and rectified. raw/rectified: lists of ((H, W) uint8 left, right)."""

    raw: list[tuple[np.ndarray, np.ndarray]]
    rectified: list[tuple[np.ndarray, np.ndarray]]
    rectifier: Rectifier


def bench_frames(preload: int) -> Frames:
    from cores import camera
    from cores.calibration.rectify import Rectifier
    from services.capture.sources import SyntheticSource

    src = SyntheticSource("two-boxes", "lifecam-studio", 30.0, preload=preload)
    rect = Rectifier(camera.load_calibration("lifecam-studio"))
    raw = [(p.left, p.right) for p in (src.read() for _ in range(preload))]
    return Frames(raw, [rect.rectify(l, r) for l, r in raw], rect)


def opencv_matcher(method: str, model=None):
    """OpenCV's matcher object alone, with the settings the disparity service uses by default for
    this camera (num_disparities auto resolved), built where the service's is (cores/matching/opencv.py)."""
    from cores import camera
    from cores.calibration.rectify import Rectifier
    from cores.matching.matchers import MatcherConfig
    from cores.matching.opencv import create_opencv_matcher

    model = model or Rectifier(camera.load_calibration("lifecam-studio")).model
    return create_opencv_matcher(MatcherConfig(method=method).resolved(model.focal_px, model.baseline_m, model.width))


def matcher_alone(pairs: list, method: str, threads: int, seconds: float, model=None) -> dict:
    """OpenCV's matcher on the rectified pairs, back to back, with `threads` OpenCV threads.
    fps = frames / wall time (spikes count, as they do for the pipeline)."""
    import cv2

    m = opencv_matcher(method, model)
    before = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    try:
        m.compute(*pairs[0])  # first call allocates buffers
        times: list[float] = []
        cpu0 = time.process_time()
        t_start = time.perf_counter()
        while time.perf_counter() - t_start < seconds or len(times) < 5:
            l, r = pairs[len(times) % len(pairs)]
            t0 = time.perf_counter()
            m.compute(l, r)
            times.append(time.perf_counter() - t0)
        wall = time.perf_counter() - t_start
        cpu = time.process_time() - cpu0
    finally:
        cv2.setNumThreads(before)
    return {"threads": threads, "frames": len(times), "fps": len(times) / wall,
            "ms_p50": float(np.median(times)) * 1e3, "cpu_ms": cpu * 1e3 / len(times)}


def in_process_compute(frames: Frames, method: str, seconds: float) -> dict:
    """The pipeline's cores serially in this process, no messaging (cores/pipeline.py, with the
    services' default settings but the method): rectify with the checks on its frame path, disparity
    (OpenCV's default threads), segmenter and tracking. -> per-stage median ms and their sum, the
    per-frame compute."""
    from cores.matching.matchers import MatcherConfig
    from cores.pipeline import Pipeline

    pipe = Pipeline(frames.rectifier.calibration, MatcherConfig(method=method))
    stages = ("rectify", "disparity", "segmenter")
    times: dict[str, list[float]] = {s: [] for s in stages}
    cpu = dict.fromkeys(stages, 0.0)
    for i in range(3):  # first calls import and allocate (the tracker's scipy): not per-frame compute
        pipe.process(*frames.raw[i % len(frames.raw)], t_s=-1.0 + i / 30.0, seq=i, stamp_ns=0)
    t_end = time.perf_counter() + seconds
    n = 0
    while time.perf_counter() < t_end or n < 5:
        left, right = frames.raw[n % len(frames.raw)]
        m = pipe.front(left, right, t_s=n / 30.0, stamp_ns=0)
        t0, c0 = time.perf_counter(), time.process_time()
        pipe.segment(m.stage, t_s=n / 30.0, seq=n, stamp_ns=0, image=m.left, checks=m.checks)
        for s, ms, cpu_ms in (("rectify", m.rectify_ms, m.rectify_cpu_ms), ("disparity", m.match_ms, m.match_cpu_ms),
                              ("segmenter", (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3)):
            times[s].append(ms)
            cpu[s] += cpu_ms
        n += 1
    per_stage = {k: float(np.median(v)) for k, v in times.items()}
    total = sum(per_stage.values())
    # CPU time of all this process's threads (OpenCV's included), per frame: what each stage's
    # process needs at least; the pipeline's processes spend the rest on messaging.
    return {"frames": n, "stage_ms_p50": per_stage, "total_ms_p50": total, "fps": 1000.0 / total,
            "stage_cpu_ms": {k: v / n for k, v in cpu.items()}}


def references(frames: Frames, method: str, seconds: float = 2.0) -> dict:
    model = frames.rectifier.model
    return {"matcher_2_threads": matcher_alone(frames.rectified, method, 2, seconds, model),
            "matcher_1_thread": matcher_alone(frames.rectified, method, 1, seconds, model),
            "compute": in_process_compute(frames, method, seconds)}


def mean_references(a: dict, b: dict) -> dict:
    """Before and after the pipeline run -> their mean (fps and ms averaged), both kept."""
    out = {}
    for k in ("matcher_2_threads", "matcher_1_thread"):
        out[k] = dict(a[k], fps=(a[k]["fps"] + b[k]["fps"]) / 2, ms_p50=(a[k]["ms_p50"] + b[k]["ms_p50"]) / 2,
                      cpu_ms=(a[k]["cpu_ms"] + b[k]["cpu_ms"]) / 2,
                      before_fps=a[k]["fps"], after_fps=b[k]["fps"])
    ca, cb = a["compute"], b["compute"]
    total = (ca["total_ms_p50"] + cb["total_ms_p50"]) / 2
    out["compute"] = {"stage_ms_p50": {s: (ca["stage_ms_p50"][s] + cb["stage_ms_p50"][s]) / 2
                                       for s in ca["stage_ms_p50"]},
                      "stage_cpu_ms": {s: (ca["stage_cpu_ms"][s] + cb["stage_cpu_ms"][s]) / 2
                                       for s in ca["stage_cpu_ms"]},
                      "total_ms_p50": total, "fps": 1000.0 / total,
                      "before_ms": ca["total_ms_p50"], "after_ms": cb["total_ms_p50"]}
    return out
