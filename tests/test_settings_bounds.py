"""Every matcher and segmenter setting at each end of its allowed range runs: a value the settings
take must never crash a service (OpenCV's 3-way SGBM once died of SIGFPE at uniqueness_ratio 100,
the segmenter divided by zero at min_range_m 0). Each case runs in a child process, so a native
crash fails its case instead of the whole run."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from annotated_types import Ge, Gt, Le, Lt

ROOT = Path(__file__).resolve().parent.parent


def _ends(model) -> list[tuple[str, object]]:
    out = []
    for name, f in model.model_fields.items():
        floating = "float" in str(f.annotation)
        for m in f.metadata:
            if isinstance(m, Ge):
                out.append((name, m.ge))
            elif isinstance(m, Gt):
                out.append((name, m.gt + (1e-3 if floating else 1)))
            elif isinstance(m, Le):
                out.append((name, m.le))
            elif isinstance(m, Lt):
                out.append((name, m.lt - (1e-3 if floating else 1)))
    return out


RUN = """
import sys, traceback
from annotated_types import Ge, Gt, Le, Lt
from pydantic import ValidationError
from cores import camera
from cores.matching.config import MatcherConfig
from cores.pipeline import Pipeline
from cores.segmentation.settings import SegmenterSettings
from services.capture.sources import SyntheticSource
from test_settings_bounds import _ends
part, method = sys.argv[1], sys.argv[2]
src = SyntheticSource("person-walking", "lifecam-studio", 15.0)
pairs = [src.read() for _ in range(2)]
cal = camera.load_calibration("lifecam-studio")
reference = Pipeline(cal, MatcherConfig())
stages = [reference.match(*reference.rectify(p.left, p.right)) for p in pairs]
for name, value in _ends(MatcherConfig if part == "matcher" else SegmenterSettings):
    print("try", name, repr(value), flush=True)
    try:
        if part == "matcher":
            pipe = Pipeline(cal, MatcherConfig(method=method, **{name: value}))
        else:
            pipe = reference.fork(SegmenterSettings(method=method, **{name: value}))
    except ValidationError:
        continue  # refused with a message naming the setting: not a crash
    try:
        for k, (pair, stage) in enumerate(zip(pairs, stages)):
            if part == "matcher":
                pipe.process(pair.left, pair.right, t_s=k / 15, seq=k)
            else:
                pipe.segment(stage, t_s=k / 15, seq=k)
    except Exception:
        print("error", name, repr(value), traceback.format_exc(limit=3).replace(chr(10), " | "), flush=True)
print("done", flush=True)
"""


@pytest.mark.slow
@pytest.mark.parametrize("part, method", [("matcher", "bm"), ("matcher", "sgbm"), ("matcher", "dense"),
                                          ("segmenter", "layers"), ("segmenter", "seed")])
def test_every_setting_at_the_ends_of_its_range_runs(part, method):
    out = subprocess.run([sys.executable, "-c", RUN, part, method], cwd=ROOT, capture_output=True, text=True,
                         timeout=900, env={**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{ROOT / 'tests'}"})
    lines = out.stdout.strip().splitlines()
    tried = [ln for ln in lines if ln.startswith("try ")]
    assert out.returncode == 0 and lines and lines[-1] == "done", \
        f"{part} {method}: exit {out.returncode} (signal {-out.returncode if out.returncode < 0 else 'none'}) at " \
        f"{tried[-1] if tried else 'the start'}\n{out.stderr[-2000:]}"
    assert len(tried) >= 20 and not [ln for ln in lines if ln.startswith("error ")], \
        [ln for ln in lines if ln.startswith("error ")]
