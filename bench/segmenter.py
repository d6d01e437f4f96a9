"""Segmentation time per frame for each method, on the block-matching disparity of a synthetic
scenario (640x480 for the default rig). `ballbot-vision bench-segmenter [--json]`."""
from __future__ import annotations

import time

import numpy as np


def bench_segmenter(scenario: str = "two-boxes", methods: list[str] | None = None, repeat: int = 50,
                    frames: int = 1) -> dict:
    from ..services.segmenter.eval import render_scenario
    from ..services.segmenter.main import METHODS, Segmenter, SegmenterSettings

    data = render_scenario(scenario, frames=frames)
    m = data.mount
    out = {"scenario": scenario, "image": f"{data.model.width}x{data.model.height}", "methods": {}}
    for method in methods or list(METHODS):
        seg = Segmenter(SegmenterSettings(method=method, mount_height_m=m.height_m, mount_pitch_deg=m.pitch_deg))
        for fr in data.frames:  # warm-up
            seg.detect(fr.disparity, data.model)
        times = []
        for k in range(repeat):
            fr = data.frames[k % len(data.frames)]
            t0 = time.perf_counter()
            seg.detect(fr.disparity, data.model)
            times.append((time.perf_counter() - t0) * 1e3)
        t = np.array(times)
        out["methods"][method] = {"ms_median": float(np.median(t)), "ms_p95": float(np.percentile(t, 95)),
                                  "ms_min": float(t.min()), "runs": repeat}
    return out


def format_bench(result: dict) -> str:
    lines = [f"segmentation time per frame, {result['scenario']} ({result['image']}):",
             f"  {'method':8} {'median ms':>10} {'p95 ms':>8} {'min ms':>8}"]
    for name, r in result["methods"].items():
        lines.append(f"  {name:8} {r['ms_median']:10.2f} {r['ms_p95']:8.2f} {r['ms_min']:8.2f}")
    return "\n".join(lines)
