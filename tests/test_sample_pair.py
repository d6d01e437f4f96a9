"""`sample-pair` gives the user data for README's offline examples: a raw pair (or sequence) of the
synthetic world, its calibration and ground truth, on which the offline commands find the truth."""
from __future__ import annotations

import json

import numpy as np

from ballbot_vision.cli import main
from cores import camera


def test_sample_pair_runs_the_offline_commands_as_readme_shows(tmp_path, capsys):
    out = tmp_path / "sample"
    assert main(["sample-pair", str(out)]) == 0
    assert {p.name for p in out.iterdir()} == {"left.png", "right.png", "calibration.yaml", "truth.json"}
    assert camera.load_calibration(out / "calibration.yaml").name == "lifecam-studio"
    truth = json.loads((out / "truth.json").read_text())
    capsys.readouterr()
    cal = str(out / "calibration.yaml")
    assert main(["obstacles", str(out / "left.png"), str(out / "right.png"), "--calibration", cal, "--json"]) == 0
    found = json.loads(capsys.readouterr().out)["obstacles"]
    assert len(found) == len(truth["obstacles"]) == 2
    for t in truth["obstacles"]:
        nearest = min(np.linalg.norm(np.subtract(o["position_m"], t["visible_centroid_m"])) for o in found)
        assert nearest < 0.05 * np.linalg.norm(t["visible_centroid_m"]), (t, found)
    assert main(["disparity", str(out / "left.png"), str(out / "right.png"), "--calibration", cal,
                 "-o", str(out / "d.npy")]) == 0
    assert np.isfinite(np.load(out / "d.npy")).mean() > 0.5


def test_sample_sequence_is_numbered_for_natural_order(tmp_path, capsys):
    out = tmp_path / "seq"
    assert main(["sample-pair", str(out), "--frames", "3", "--scenario", "person-walking"]) == 0
    assert sorted(p.name for p in (out / "left").iterdir()) == ["left0000.png", "left0001.png", "left0002.png"]
    assert [t["seq"] for t in json.loads((out / "truth.json").read_text())] == [0, 1, 2]
    assert main(["sample-pair", str(out), "--frames", "0"]) == 2
    assert "--frames 0: must be at least 1" in capsys.readouterr().err
