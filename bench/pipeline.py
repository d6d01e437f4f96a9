"""`ballbot-vision bench`: the four services as separate processes over Zenoh, on a preloaded loop
of synthetic pairs (the renderer is not measured), beside the in-process compute ceiling of the
same stages (one process, no Zenoh, no encoding)."""
from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import threading
import time

import numpy as np

STAGES = ["capture", "rectify", "disparity", "segmenter"]


PARTS = ["pipeline", "sources", "renderer", "segmenter", "scaling", "accuracy"]


def add_bench_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("part", nargs="?", default="pipeline", choices=PARTS,
                   help="pipeline: the four services over Zenoh (default); sources: file capture sources; "
                        "renderer: the synthetic world; segmenter: time per method; scaling: disparity "
                        "workers 1-3 (sgbm); accuracy: bad-2px on a Middlebury pair")
    p.add_argument("--seconds", type=float, default=10.0, help="measured duration of the pipeline run")
    p.add_argument("--warmup", type=float, default=3.0, help="seconds discarded before measuring")
    p.add_argument("--rate", type=float, default=60.0, help="capture rate offered to the pipeline, pairs/s")
    p.add_argument("--method", default="bm", choices=["bm", "sgbm"], help="disparity method")
    p.add_argument("--preload", type=int, default=16, help="pre-rendered pairs looped by capture")
    p.add_argument("--workers", type=int, default=0, help="disparity worker processes (one OpenCV thread each) "
                   "behind the dispatcher; 0: the dispatcher's onboard matcher (the single-host default)")
    p.add_argument("--json", action="store_true", help="one JSON document on stdout")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {"p50": float("nan"), "p95": float("nan"), "p99": float("nan")}
    a = np.asarray(values)
    return {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)), "p99": float(np.percentile(a, 99))}


def compute_ceiling(method: str, preload: int, seconds: float = 3.0) -> dict:
    """The same cores, serially, in this process: what the hardware allows with no messaging."""
    from ..services.capture.sources import SyntheticSource
    from ..common.disparity import to_float
    from ..services.disparity.matchers import MatcherConfig, StereoMatcher
    from ..services.rectify.core import Rectifier
    from ..services.segmenter.main import Segmenter, SegmenterSettings
    from ..common import camera

    src = SyntheticSource("two-boxes", "lifecam-studio", 30.0, preload=max(1, min(preload, 8)))
    rect = Rectifier(camera.load_calibration("lifecam-studio"))
    cfg = MatcherConfig(method=method)
    matcher = StereoMatcher(cfg)
    segmenter = Segmenter(SegmenterSettings())  # the service's default method
    times = {"rectify": [], "disparity": [], "segmenter": []}
    t_end = time.perf_counter() + seconds
    n = 0
    while time.perf_counter() < t_end or n < 5:
        pair = src.read()
        t0 = time.perf_counter()
        l, r = rect.rectify(pair.left, pair.right)
        t1 = time.perf_counter()
        d = matcher.compute(l, r)
        t2 = time.perf_counter()
        segmenter.detect(to_float(d, 16.0, cfg.invalid_value), rect.model)
        t3 = time.perf_counter()
        times["rectify"].append((t1 - t0) * 1e3)
        times["disparity"].append((t2 - t1) * 1e3)
        times["segmenter"].append((t3 - t2) * 1e3)
        n += 1
    per_stage = {k: float(np.median(v)) for k, v in times.items()}
    total = sum(per_stage.values())
    return {"frames": n, "stage_ms_p50": per_stage, "total_ms_p50": total, "fps": 1000.0 / total}


def pipeline_run(rate: float, method: str, preload: int, warmup_s: float, seconds: float,
                 extra_args: dict[str, list[str]] | None = None, workers: int = 0) -> dict:
    from ..common import codec
    from ..common.keys import topic
    from ..common.messages import ObstacleList
    from ..common.zenoh_session import ZenohOptions, open_session
    from ..supervisor import Supervisor

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rid = "bench"
    common = ["--robot-id", rid]
    sup = Supervisor(env=dict(os.environ, BALLBOT_LOG="WARNING"))
    sup.add("router", ["run", "router", "--listen", endpoint] + common)
    per_service = {
        "capture": ["--preload", str(preload), "--rate-hz", str(rate)],
        "disparity": ["--method", method] + (["--fallback", "none"] if workers else []),
    }
    for name, more in (extra_args or {}).items():
        per_service.setdefault(name, []).extend(more)
    for name in STAGES:
        sup.add(name, ["run", name, "--connect", endpoint] + common + per_service.get(name, []))
    for i in range(workers):
        sup.add(f"worker{i}", ["run", "disparity", "--role", "worker", "--instance", f"bench-worker{i}",
                               "--threads", "1", "--method", method, "--connect", endpoint] + common)
    received: list[tuple[float, ObstacleList]] = []
    lock = threading.Lock()
    measuring = threading.Event()

    def on_obstacles(sample) -> None:
        t = time.time_ns()
        if measuring.is_set():
            msg = codec.decode(sample.payload.to_bytes(), ObstacleList)
            with lock:
                received.append((t, msg))

    try:
        sup.start_all(endpoint)
        opts = ZenohOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"])
        with open_session(opts) as session:
            session.declare_subscriber(topic("obstacles").key(rid), on_obstacles)
            time.sleep(warmup_s)
            measuring.set()
            t0 = time.monotonic()
            time.sleep(seconds)
            measuring.clear()
            elapsed = time.monotonic() - t0
    finally:
        sup.stop_all()
    fresh = [(t, m) for t, m in received if not m.stale]
    e2e = [(m.publish_ns - m.stamp_ns) / 1e6 for _, m in fresh]
    delivered = [(t - m.stamp_ns) / 1e6 for t, m in fresh]
    stage_lat = {}
    prev = "capture"
    for s in STAGES[1:]:
        stage_lat[s] = percentiles([(m.stages[s] - m.stages[prev]) / 1e6 for _, m in fresh
                                    if s in m.stages and prev in m.stages])
        prev = s
    return {
        "offered_rate_hz": rate, "seconds": elapsed, "obstacle_lists": len(fresh),
        "fps": len(fresh) / elapsed if elapsed else 0.0,
        "latency_ms": percentiles(e2e), "delivered_latency_ms": percentiles(delivered),
        "stage_latency_ms": stage_lat,
        "seq_gaps": int(sum(1 for a, b in zip(fresh, fresh[1:]) if b[1].seq != a[1].seq + 1)),
    }


def bench_part(part: str, as_json: bool) -> int:
    flags = ["--json"] if as_json else []
    if part == "sources":
        from .sources import main
        return main(flags)
    if part == "scaling":
        from .scaling import main
        return main(flags)
    if part == "accuracy":
        from .accuracy import main
        return main(flags)
    if part == "segmenter":
        from .segmenter import bench_segmenter, format_bench
        r = bench_segmenter()
    else:
        from .renderer import bench_renderer, format_renderer
        r = bench_renderer()
    print(json.dumps(r, indent=2) if as_json else (format_bench(r) if part == "segmenter" else format_renderer(r)))
    return 0


def bench_main(args: argparse.Namespace) -> int:
    if args.part != "pipeline":
        return bench_part(args.part, args.json)
    if not args.json:
        print("measuring the in-process compute ceiling ...", file=sys.stderr, flush=True)
    ceiling = compute_ceiling(args.method, args.preload)
    if not args.json:
        print(f"running the pipeline over Zenoh for {args.seconds:g} s at {args.rate:g} pairs/s offered ...",
              file=sys.stderr, flush=True)
    pipe = pipeline_run(args.rate, args.method, args.preload, args.warmup, args.seconds,
                        workers=getattr(args, "workers", 0))
    report = {"image": "640x480", "method": args.method, "workers": getattr(args, "workers", 0), "num_disparities": 64, "ceiling": ceiling,
              "pipeline": pipe, "ratio_fps": pipe["fps"] / ceiling["fps"] if ceiling["fps"] else 0.0,
              "targets": {"fps": 60.0, "latency_p50_ms": 25.0}}
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    c, p = ceiling, pipe
    print(f"in-process ceiling ({args.method}, 640x480, 64 disparities): {c['fps']:.1f} fps, "
          + ", ".join(f"{k} {v:.2f} ms" for k, v in c["stage_ms_p50"].items()))
    print(f"pipeline over Zenoh, offered {p['offered_rate_hz']:g}/s: {p['fps']:.1f} fps "
          f"({report['ratio_fps']:.2f} of the ceiling), {p['obstacle_lists']} lists in {p['seconds']:.1f} s")
    lat = p["latency_ms"]
    print(f"capture -> obstacles published: p50 {lat['p50']:.1f} ms  p95 {lat['p95']:.1f} ms  p99 {lat['p99']:.1f} ms")
    for s, v in p["stage_latency_ms"].items():
        print(f"  {s:10} (since previous stage published): p50 {v['p50']:.2f}  p95 {v['p95']:.2f}  p99 {v['p99']:.2f} ms")
    print("targets: >= 60 fps, p50 <= 25 ms")
    return 0
