"""Does a change to the segmenter keep its output? Record the disparity maps an evaluation feeds the
segmenter once, replay them through the code as it is now, compare the outputs exactly.

    python -m bench.segmenter_replay capture DIR/syn synthetic              (what `eval` runs)
    python -m bench.segmenter_replay capture DIR/sway synthetic sway        (`eval sway`)
    python -m bench.segmenter_replay capture DIR/kit real ../shared/data/real/karlsruhe-0023  (`eval --real`)
    python -m bench.segmenter_replay replay DIR/kit DIR/kit.before     (on the old code)
    python -m bench.segmenter_replay replay DIR/kit DIR/kit.after      (on the new code)
    python -m bench.segmenter_replay compare DIR/kit.before DIR/kit.after

capture runs the evaluation (the layers method; a recording with `eval --real`'s defaults: range
30 m, num_disparities auto) and pickles every ObstacleBuilder's settings, mount and process()
inputs (the map, the model, the call's keywords but the image) to NAME.pkl; replay feeds each
recorded stream to a fresh builder and pickles, per frame, the obstacle list (without its publish
time), the ground, the mount, the degraded flags, the free-space grid and the floor plane; compare
says which frames differ and how (exit 1 if any). Floats are compared by repr: to the last bit.
The files are large (the maps: ~150 MB for all synthetic scenarios) and are pickles: replay only
files you made.
"""
from __future__ import annotations

import pickle
import sys
import time
from pathlib import Path

import numpy as np


def capture(name: str, kind: str, args: list[str]) -> int:
    from cores.segmentation import builder as B

    streams: list[dict] = []
    init, process = B.ObstacleBuilder.__init__, B.ObstacleBuilder.process

    def recording_init(self, settings, mount=None):  # type: ignore[no-untyped-def]
        init(self, settings, mount)
        self._replay_stream = {"settings": settings.model_dump(),
                               "mount": None if mount is None else mount.model_dump(), "calls": []}
        streams.append(self._replay_stream)

    def recording_process(self, disparity, model, **kw):  # type: ignore[no-untyped-def]
        self._replay_stream["calls"].append((disparity.copy(), model, {k: v for k, v in kw.items() if k != "image"}))
        return process(self, disparity, model, **kw)

    B.ObstacleBuilder.__init__ = recording_init  # type: ignore[method-assign]
    B.ObstacleBuilder.process = recording_process  # type: ignore[method-assign]
    try:
        _evaluate(kind, args)
    finally:
        B.ObstacleBuilder.__init__, B.ObstacleBuilder.process = init, process  # type: ignore[method-assign]
    kept = [s for s in streams if s["calls"] and s["settings"]["method"] == "layers"]
    with open(f"{name}.pkl", "wb") as f:
        pickle.dump(kept, f)
    print(f"{name}.pkl: {len(kept)} stream(s), {sum(len(s['calls']) for s in kept)} frame(s)")
    return 0


def _evaluate(kind: str, args: list[str]) -> None:
    if kind == "synthetic":
        from evaluation.synthetic import evaluate

        evaluate(args or None, ["layers"])
    elif kind == "real" and len(args) == 1:
        from cores.matching.config import MatcherConfig
        from cores.segmentation.settings import SegmenterSettings
        from evaluation import real, recordings

        real.evaluate_recording(recordings.open_recording(args[0]),
                                SegmenterSettings(max_range_m=real.REAL_MAX_RANGE_M),
                                MatcherConfig(num_disparities="auto"))
    else:
        raise SystemExit(f"capture: synthetic [SCENARIO ...] or real DIR, not {kind} {' '.join(args)}")


def _output(res) -> tuple:  # type: ignore[no-untyped-def]
    o = res.obstacles
    free = None if res.freespace is None else (res.freespace.cells, res.freespace.width, res.freespace.height,
                                               res.freespace.origin_m, res.freespace.resolution_m)
    floor = None if res.floor is None else (res.floor.a, res.floor.b, res.floor.c, res.floor.height_m)
    return repr(o.obstacles), repr(o.ground), repr(o.mount), list(o.degraded), o.valid_fraction, free, floor


def replay(name: str, out: str) -> int:
    from common.settings import MountSettings
    from cores.segmentation.builder import ObstacleBuilder
    from cores.segmentation.settings import SegmenterSettings

    with open(f"{name}.pkl", "rb") as f:
        streams = pickle.load(f)
    outputs, ms = [], []
    for s in streams:
        b = ObstacleBuilder(SegmenterSettings(**s["settings"]),
                            None if s["mount"] is None else MountSettings(**s["mount"]))
        for disparity, model, kw in s["calls"]:
            t0 = time.perf_counter()
            res = b.process(disparity, model, **kw)
            ms.append((time.perf_counter() - t0) * 1e3)
            outputs.append(_output(res))
    with open(f"{out}.pkl", "wb") as f:
        pickle.dump(outputs, f)
    print(f"{out}.pkl: {len(outputs)} frame(s), process() median {np.median(ms):.2f} ms")
    return 0


def compare(a: str, b: str) -> int:
    with open(f"{a}.pkl", "rb") as f:
        A = pickle.load(f)
    with open(f"{b}.pkl", "rb") as f:
        B = pickle.load(f)
    if len(A) != len(B):
        print(f"{a} has {len(A)} frames, {b} {len(B)}")
        return 1
    fields = ("obstacles", "ground", "mount", "degraded", "valid_fraction", "free space", "floor")
    bad = [i for i, (x, y) in enumerate(zip(A, B)) if x != y]
    print(f"{Path(a).name} vs {Path(b).name}: {len(A)} frames, {len(bad)} differ{':' if bad else ''} {bad[:20]}")
    for i in bad[:3]:
        diff = [name for name, x, y in zip(fields, A[i], B[i]) if x != y]
        print(f"  frame {i}: {', '.join(diff)}")
    return 1 if bad else 0


def main(argv: list[str]) -> int:
    if len(argv) >= 3 and argv[0] == "capture":
        return capture(argv[1], argv[2], argv[3:])
    if len(argv) == 3 and argv[0] in ("replay", "compare"):
        return (replay if argv[0] == "replay" else compare)(argv[1], argv[2])
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
