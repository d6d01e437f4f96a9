"""Disparity worker pool scaling: disparity maps per second with 1..N worker processes (one OpenCV
thread each) behind the dispatcher, beside the single-process compute ceiling.

Measured stage: capture (preloaded synthetic pairs) -> rectify -> dispatcher -> N workers ->
`disparity`, counted by a subscriber; the segmenter is not run, so the workers have the CPU the
pipeline leaves them. The offered rate is 1.25x what min(N, cores) single-thread workers can do
(from the in-process single-thread time), so capture and rectify do not burn CPU on frames that
would be dropped anyway.

    python -m ballbot_vision.bench.scaling --method sgbm --workers 1 2 3
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time

import numpy as np


def ceiling(method: str, threads: int, seconds: float = 3.0) -> dict:
    """In-process disparity only, on rectified synthetic pairs: frames/s with `threads` OpenCV threads
    (0: OpenCV's default, one per core)."""
    import cv2

    from ..common import camera
    from ..services.capture.sources import SyntheticSource
    from ..services.disparity.main import DisparitySettings
    from ..services.disparity.matchers import StereoMatcher
    from ..services.rectify.core import Rectifier

    src = SyntheticSource("two-boxes", "lifecam-studio", 30.0, preload=2)
    rect = Rectifier(camera.load_calibration("lifecam-studio"))
    pairs = [rect.rectify(p.left, p.right) for p in (src.read(), src.read())]
    m = StereoMatcher(DisparitySettings(method=method).matcher_config())
    before = cv2.getNumThreads()
    cv2.setNumThreads(threads if threads else -1)
    try:
        times = []
        t_end = time.perf_counter() + seconds
        while time.perf_counter() < t_end or len(times) < 3:
            l, r = pairs[len(times) % 2]
            t0 = time.perf_counter()
            m.compute(l, r)
            times.append(time.perf_counter() - t0)
    finally:
        cv2.setNumThreads(before)
    ms = float(np.median(times)) * 1e3
    return {"threads": threads or cv2.getNumThreads(), "ms_p50": ms, "fps": 1000.0 / ms}


def pool_run(method: str, workers: int, rate: float, warmup_s: float, seconds: float) -> dict:
    from ..common import codec
    from ..common.keys import topic
    from ..common.messages import DisparityMap, ServiceStats
    from ..common.zenoh_session import ZenohOptions, open_session
    from ..supervisor import Supervisor
    from .pipeline import free_port, percentiles

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rid = f"scale{os.getpid()}"
    common = ["--robot-id", rid]
    sup = Supervisor()
    sup.add("router", ["run", "router", "--listen", endpoint] + common)
    c = ["--connect", endpoint] + common
    sup.add("capture", ["run", "capture", *c, "--preload", "8", "--rate-hz", f"{rate:.2f}"])
    sup.add("rectify", ["run", "rectify", *c])
    sup.add("dispatch", ["run", "disparity", *c, "--method", method, "--fallback", "none"])
    for i in range(workers):
        sup.add(f"worker{i}", ["run", "disparity", *c, "--role", "worker", "--instance", f"w{i}", "--threads", "1",
                               "--method", method])
    got: list[tuple[int, str, float]] = []
    link: dict[str, float] = {}
    lock = threading.Lock()
    measuring = threading.Event()

    def on_disp(sample) -> None:
        if measuring.is_set():
            m = codec.decode(sample.payload.to_bytes(), DisparityMap)
            with lock:
                got.append((m.seq, m.worker, (time.time_ns() - m.stamp_ns) / 1e6))

    def on_stats(sample) -> None:
        s = codec.decode(sample.payload.to_bytes(), ServiceStats)
        if measuring.is_set():
            for k, v in s.extra.items():
                if k.endswith("_Bps"):
                    link[f"{s.instance}:{k}"] = v

    try:
        sup.start_all(endpoint)
        with open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"])) as session:
            session.declare_subscriber(topic("disparity").key(rid), on_disp)
            session.declare_subscriber(topic("stats").pattern(rid), on_stats)
            time.sleep(warmup_s)  # a benchmark's fixed warm-up, not a test synchronisation
            measuring.set()
            t0 = time.monotonic()
            time.sleep(seconds)
            measuring.clear()
            elapsed = time.monotonic() - t0
    finally:
        sup.stop_all()
    per_worker: dict[str, int] = {}
    for _, w, _ in got:
        per_worker[w] = per_worker.get(w, 0) + 1
    seqs = [s for s, _, _ in got]
    return {"workers": workers, "offered_hz": rate, "seconds": elapsed, "maps": len(got),
            "fps": len(got) / elapsed, "per_worker": per_worker, "latency_ms": percentiles([a for *_, a in got]),
            "duplicates": len(seqs) - len(set(seqs)), "link_Bps": link}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--method", default="sgbm", choices=["bm", "sgbm"])
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2, 3])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--warmup", type=float, default=5.0)
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    cores = os.cpu_count() or 1
    one, ceil = ceiling(a.method, 1), ceiling(a.method, 0)
    runs = []
    for n in a.workers:
        rate = min(120.0, 1.25 * min(n, cores) * one["fps"])
        if not a.json:
            print(f"{n} worker(s), offering {rate:.1f} pairs/s ...", file=sys.stderr, flush=True)
        runs.append(pool_run(a.method, n, rate, a.warmup, a.seconds))
    base = runs[0]["fps"] if runs and runs[0]["workers"] == 1 else None
    report = {"method": a.method, "image": "640x480", "cores": cores, "ceiling_one_thread": one,
              "ceiling_all_threads": ceil, "runs": runs}
    if a.json:
        print(json.dumps(report, indent=2))
        return 0
    print(f"{a.method}, 640x480, 64 disparities, {cores} cores")
    print(f"in-process ceiling: 1 thread {one['fps']:.1f} fps ({one['ms_p50']:.1f} ms), "
          f"{ceil['threads']} threads {ceil['fps']:.1f} fps ({ceil['ms_p50']:.1f} ms)")
    for r in runs:
        speedup = f"{r['fps'] / base:.2f}x" if base else "-"
        print(f"{r['workers']} worker(s): {r['fps']:6.1f} maps/s ({speedup} of 1 worker), offered {r['offered_hz']:.1f}/s, "
              f"latency p50 {r['latency_ms']['p50']:.0f} ms, per worker {r['per_worker']}, duplicates {r['duplicates']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
