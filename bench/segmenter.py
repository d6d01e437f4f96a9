"""Segmentation time per frame for each method, beside the default disparity matcher's time on the
same kind of pair measured in the same run (the ratio is what holds on a busy machine):

* synthetic: the block-matching disparity of a synthetic scenario (640x480 for the default rig),
  with the scenario's exact camera mount;
* real (`--real DIR`, e.g. ../shared/data/real/karlsruhe-0023): DIR/left and DIR/right image
  folders and DIR/calibration.yaml; the first `--real-pairs` pairs are rectified and matched with
  the default matcher, then segmented out to `--real-max-range` (20 m: with 64 disparities nothing
  on Karlsruhe's 0.57 m baseline is nearer than ~6 m, beyond the robot's default range). The mount
  of a recording is unknown (none is configured: the segmenter fits the floor without a prior), as
  it is for a camera nobody measured.

`ballbot-vision bench-segmenter [--real DIR] [--json]`.
"""
from __future__ import annotations

import time
import typing
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np


def segmenter_methods() -> list[str]:
    """The methods the segmenter's settings accept."""
    from cores.segmentation.settings import SegmenterSettings

    return list(typing.get_args(SegmenterSettings.model_fields["method"].annotation))


def _timed(run: Callable[[int], object], repeat: int) -> dict:
    """run(k) once per k (a warm-up first) -> median, p95 and min ms."""
    run(0)
    times = []
    for k in range(repeat):
        t0 = time.perf_counter()
        run(k)
        times.append((time.perf_counter() - t0) * 1e3)
    t = np.array(times)
    return {"ms_median": float(np.median(t)), "ms_p95": float(np.percentile(t, 95)), "ms_min": float(t.min()),
            "runs": repeat}


def time_methods(inputs: list[tuple[np.ndarray, dict]], model, settings_for: Callable[[str], tuple],
                 matcher_ms: float, methods: list[str] | None, repeat: int) -> dict:
    """The segmenter's step of the pipeline as the service runs it (ObstacleBuilder.process: the
    ground carried from frame to frame, tracks, free space) on the maps in turn, each with what the
    service is handed with it (the DisparityMap's confidence, search, gate and rectify's checks: as
    ObstacleBuilder.process takes them), one stream per method (settings_for(method) ->
    (segmenter settings, mount settings)) -> per method the time, its ratio to the matcher's
    (x_matcher) and the obstacles on the first map."""
    from cores.segmentation.builder import ObstacleBuilder

    out = {}
    for method in methods or segmenter_methods():
        first = ObstacleBuilder(*settings_for(method)).process(inputs[0][0], model, t_s=0.0, seq=0, stamp_ns=0,
                                                                **inputs[0][1])
        builder = ObstacleBuilder(*settings_for(method))
        frame = iter(range(1 << 30))  # the stream's own frame count: its time never goes back

        # _timed calls step within this iteration only; the defaults bind this iteration's pair plainly
        def step(k: int, frame: Iterator[int] = frame, builder: ObstacleBuilder = builder) -> None:
            n = next(frame)
            disparity, handed = inputs[k % len(inputs)]
            builder.process(disparity, model, t_s=n / 15.0, seq=n, stamp_ns=0, **handed)
        r = _timed(step, repeat)
        r["x_matcher"] = r["ms_median"] / matcher_ms
        r["detections"] = len(first.obstacles.obstacles)
        out[method] = r
    return out


def _matcher_ms(stereo, pairs: list, repeat: int) -> float:
    return _timed(lambda k: stereo.compute(*pairs[k % len(pairs)]), max(3, min(repeat, 20)))["ms_median"]


def bench_synthetic(scenario: str, methods: list[str] | None, repeat: int, frames: int = 1) -> dict:
    from common.settings import MountSettings
    from cores import camera
    from cores.calibration.rectify import Rectifier
    from cores.matching.matchers import MatcherConfig
    from cores.matching.stage import MatchStage
    from cores.segmentation.settings import SegmenterSettings
    from evaluation.synthetic import render_scenario
    from services.capture.sources import SyntheticSource

    data = render_scenario(scenario, frames=frames)
    src = SyntheticSource(scenario, "lifecam-studio", 15.0)
    rect = Rectifier(camera.load_calibration("lifecam-studio"))
    cfg = MatcherConfig()
    pairs = [rect.rectify(p.left, p.right) for p in (src.read() for _ in range(2))]
    m = rect.model  # the disparity service's matcher for this rig (search range resolved)
    matcher_ms = _matcher_ms(MatchStage(cfg).matcher(m.focal_px, m.baseline_m, m.width), pairs, repeat)
    mount = data.mount
    return {"data": f"synthetic {scenario}", "image": f"{data.model.width}x{data.model.height}", "pairs": frames,
            "mount": f"exact ({mount.height_m:.2f} m, pitch {mount.pitch_deg:.1f} deg)",
            "matcher": {"method": cfg.method, "ms_median": matcher_ms},
            "methods": time_methods([(f.disparity, f.handed()) for f in data.frames], data.model,
                                    lambda method: (SegmenterSettings(method=method),
                                                    MountSettings(height_m=mount.height_m,
                                                                  pitch_deg=mount.pitch_deg)),
                                    matcher_ms, methods, repeat)}


REAL_MAX_RANGE_M = 20.0  # a street seen from a car: 64 disparities reach no nearer than ~6 m on Karlsruhe's rig


def bench_real(folder: str | Path, methods: list[str] | None, repeat: int, pairs: int = 1,
               max_range_m: float = REAL_MAX_RANGE_M) -> dict:
    """A recording's folder (left/, right/, calibration.yaml) -> the same report as bench_synthetic,
    segmented out to max_range_m (the robot's few metres would leave a car's view empty)."""
    from common.errors import FileError
    from common.files import list_images, pair_images, read_image
    from common.settings import MountSettings
    from cores import camera
    from cores.matching.matchers import MatcherConfig
    from cores.pipeline import Pipeline
    from cores.segmentation.settings import SegmenterSettings

    root = Path(folder).expanduser()
    cal_file = root / "calibration.yaml"
    if not cal_file.is_file():
        raise FileError(f"--real {folder}: no calibration.yaml in it (expected left/, right/ and calibration.yaml)")
    pipe = Pipeline(camera.load_calibration(cal_file), MatcherConfig())  # rectify and match as the services do
    files = pair_images(list_images(str(root / "left"), "--real DIR/left"),
                        list_images(str(root / "right"), "--real DIR/right"))[:max(1, pairs)]
    # rectified, checked and matched as the services do (each pair a moment later on the stream's clock)
    matched = [pipe.front(read_image(lp), read_image(rp), t_s=k / 10.0, names=(str(lp), str(rp)))
               for k, (lp, rp) in enumerate(files)]
    rectified = [(m.left, m.right) for m in matched]
    inputs = [(m.stage.disparity_px(), {**m.stage.handed(), "checks": m.checks}) for m in matched]
    model = pipe.model
    cfg = pipe.matching.config
    matcher_ms = _matcher_ms(pipe.matching.matcher(model.focal_px, model.baseline_m, model.width), rectified, repeat)
    return {"data": f"{root.name} ({', '.join(p.name for p in files[0])}{', ...' if len(files) > 1 else ''})",
            "folder": str(root), "image": f"{model.width}x{model.height}", "pairs": len(files),
            "mount": "unknown (none configured: the floor is fitted without a prior)", "max_range_m": max_range_m,
            "matcher": {"method": cfg.method, "ms_median": matcher_ms},
            "methods": time_methods(inputs, model,
                                    lambda method: (SegmenterSettings(method=method, max_range_m=max_range_m),
                                                    MountSettings()),
                                    matcher_ms, methods, repeat)}


def bench_segmenter(scenario: str = "two-boxes", methods: list[str] | None = None, repeat: int = 50,
                    frames: int = 1, real: str | Path | None = None, real_pairs: int = 1,
                    real_max_range_m: float = REAL_MAX_RANGE_M) -> dict:
    """-> {"sets": [synthetic, real (with --real)], "load_avg_1min"}; each set: data, image, pairs,
    mount, matcher {method, ms_median}, methods {name: {ms_median, ms_p95, ms_min, runs, x_matcher,
    detections}}."""
    import os

    sets = [bench_synthetic(scenario, methods, repeat, frames)]
    if real is not None:
        sets.append(bench_real(real, methods, repeat, real_pairs, real_max_range_m))
    return {"sets": sets, "load_avg_1min": os.getloadavg()[0]}


def format_bench(result: dict) -> str:
    lines = []
    for s in result["sets"]:
        reach = f", range {s['max_range_m']:g} m" if "max_range_m" in s else ""
        lines += [f"segmentation time per frame, {s['data']}, {s['image']}, {s['pairs']} pair(s){reach}, "
                  f"mount {s['mount']}; "
                  f"x = ratio to the default matcher ({s['matcher']['method']}, {s['matcher']['ms_median']:.2f} ms "
                  f"per pair) in this run:",
                  f"  {'method':8} {'median ms':>10} {'p95 ms':>8} {'min ms':>8} {'x matcher':>10} {'detections':>11}"]
        for name, r in s["methods"].items():
            lines.append(f"  {name:8} {r['ms_median']:10.2f} {r['ms_p95']:8.2f} {r['ms_min']:8.2f} "
                         f"{r['x_matcher']:10.2f} {r['detections']:11d}")
    lines.append(f"load average {result['load_avg_1min']:.1f}")
    return "\n".join(lines)
