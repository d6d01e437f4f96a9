"""Frames per second of the synthetic world (render of both raw images + ground truth) at 640x480,
one OpenCV thread, for a static and a moving scenario. `ballbot-vision bench renderer`."""
from __future__ import annotations

import time

import numpy as np


def bench_renderer(scenarios: tuple[str, ...] = ("two-boxes", "person-walking"), frames: int = 30) -> dict:
    import cv2

    from cores import camera
    from sim import Scene, SyntheticWorld

    cv2.setNumThreads(1)
    rig = camera.load_raw_rig("lifecam-studio")
    rect = camera.rectify_rig(rig)
    out = {}
    for name in scenarios:
        world = SyntheticWorld(Scene.builtin(name), rig, rect, seed=0)
        world.render(0.0)  # texture pyramids and ray tables are built once
        times = []
        for k in range(frames):
            t = (k + 1) / 30.0
            t0 = time.perf_counter()
            world.render(t)
            world.truth(t)
            times.append((time.perf_counter() - t0) * 1e3)
        ms = float(np.median(times))
        out[name] = {"static": world.is_static(), "ms_median": ms, "fps": 1000.0 / ms, "frames": frames}
    return out


def format_renderer(result: dict) -> str:
    lines = ["synthetic world, render both images + ground truth, 640x480, 1 thread:"]
    for name, r in result.items():
        lines.append(f"  {name:16} {'static' if r['static'] else 'moving':7} {r['ms_median']:7.2f} ms  "
                     f"{r['fps']:7.1f} fps")
    return "\n".join(lines)
