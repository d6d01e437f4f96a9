"""`ballbot-vision bench [PART]`: the arguments and which benchmark runs (bench/pipeline.py for the
pipeline, one module each for the other parts)."""
from __future__ import annotations

import argparse
import json

from bench.pipeline import STEADY_RATE_HZ

PARTS = ["pipeline", "sources", "renderer", "segmenter", "scaling", "accuracy", "record", "rectify", "transport",
         "trust", "fleet"]


def add_bench_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("part", nargs="?", default="pipeline", choices=PARTS,
                   help="pipeline: the four services over Zenoh (default); sources: file capture sources; "
                        "renderer: the synthetic world; segmenter: time per method; scaling: disparity "
                        "workers 1-3 (sgbm); accuracy: bad-2px on a Middlebury pair; record: `record` at 30 "
                        "fps, drops and CPU (bench/record.py); rectify: CPU and accuracy of float vs "
                        "fixed-point remap tables; transport: the copies of the frame path and one hop between "
                        "processes with Zenoh's shared memory on and off; "
                        "trust: what checking and signing a worker's "
                        "map costs (bench/trust.py); fleet: 4 robots sharing 2 sgbm pool workers, per robot "
                        "against its fair share, a worker killed and one added (bench/fleet.py)")
    p.add_argument("--seconds", type=float, default=10.0, help="measured duration at the chosen rate")
    p.add_argument("--probe-seconds", type=float, default=3.0, help="measured duration of each search probe")
    p.add_argument("--warmup", type=float, default=1.5, help="seconds discarded after capture starts delivering")
    p.add_argument("--rate", type=float, default=0.0,
                   help="offer this many pairs/s and skip the search for the highest sustainable rate")
    p.add_argument("--probes", type=int, default=4, help="search probes after the saturating one")
    p.add_argument("--steady-rate", type=float, default=STEADY_RATE_HZ, metavar="HZ",
                   help="also measure at this offered rate (a camera's; its latency has a target of its own); "
                        "0: skip")
    p.add_argument("--repeat", type=int, default=1,
                   help="measure this many times (same processes) and report medians and spread")
    p.add_argument("--method", default=None, choices=["bm", "sgbm"],
                   help="disparity method (default: bm; scaling: sgbm)")
    p.add_argument("--reference-seconds", type=float, default=2.0,
                   help="duration of each reference measurement (matcher 2 threads, 1 thread, compute)")
    p.add_argument("--preload", type=int, default=16, help="pre-rendered pairs looped by capture")
    p.add_argument("--workers", type=int, default=0, help="disparity worker processes (one OpenCV thread each) "
                   "behind the dispatcher; 0: the dispatcher's onboard matcher (the single-host default)")
    p.add_argument("--nice", type=int, default=0, metavar="N",
                   help="run the pipeline's processes and this process (the references) at this priority, e.g. "
                        "-10 on a busy machine (needs root): both sides alike, so the ratios stay fair")
    p.add_argument("--profile", action="store_true",
                   help="segmenter: where the service's time per frame goes, step by step, at 640x480 (cProfile)")
    p.add_argument("--json", action="store_true", help="one JSON document on stdout")


def bench_part(part: str, args: argparse.Namespace) -> int:
    flags = ["--json"] if args.json else []
    if part == "sources":
        from bench.sources import main
        return main(flags)
    if part == "scaling":
        from bench.scaling import main
        if args.method:
            flags += ["--method", args.method]
        if args.workers:
            flags += ["--workers", *[str(n) for n in range(1, args.workers + 1)]]
        if args.repeat > 1:
            flags += ["--repeat", str(args.repeat)]
        if args.nice:
            flags += ["--nice", str(args.nice)]
        return main(flags)
    if part == "accuracy":
        from bench.accuracy import main
        return main(flags)
    if part == "record":
        from bench.record import main
        return main(flags)
    if part == "rectify":
        from bench.rectify import main
        return main(flags)
    if part == "transport":
        from bench.transport import main
        return main(flags + (["--repeat", str(args.repeat)] if args.repeat > 1 else []))
    if part == "segmenter" and getattr(args, "profile", False):
        from bench.segmenter_profile import main
        return main(flags)
    if part == "trust":
        from bench.trust import main
        return main(flags + ["--seconds", f"{args.seconds:g}"])
    if part == "fleet":
        from bench.fleet import main
        if args.method:
            flags += ["--method", args.method]
        if args.workers:
            flags += ["--workers", str(args.workers)]
        return main(flags + ["--seconds", f"{args.seconds:g}"])
    if part == "segmenter":
        from bench.segmenter import bench_segmenter, format_bench
        r = bench_segmenter()
    else:
        from bench.renderer import bench_renderer, format_renderer
        r = bench_renderer()
    print(json.dumps(r, indent=2) if args.json else (format_bench(r) if part == "segmenter" else format_renderer(r)))
    return 0


def bench_main(args: argparse.Namespace) -> int:
    if args.part != "pipeline":
        return bench_part(args.part, args)
    from bench.pipeline import bench_pipeline

    return bench_pipeline(args)
