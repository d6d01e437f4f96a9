"""The occlusion and right-border scenarios through the real pipeline (render -> rectify -> block
matching -> segmenter -> tracker), scored by evaluation/synthetic.py: a person hidden behind a
nearer box for ~0.5 s keeps its track id, the hidden frames are not held against the method, and the
thesis's method (`seed`) shows its failure on an object cut by the right image border."""
from __future__ import annotations

import numpy as np
import pytest

import sim as S
from cores import camera
from cores.calibration.rectify import Rectifier
from evaluation import synthetic as E

NEW = ["occlusion", "border-right"]


@pytest.fixture(scope="module")
def data():
    # 0 .. 2.13 s at 15 fps: the person walks in, is hidden from ~0.87 s to ~1.33 s, walks out
    return {"occlusion": E.render_scenario("occlusion", frames=33, fps=15.0),
            "border-right": E.render_scenario("border-right", frames=2)}


@pytest.fixture(scope="module")
def result(data):
    return E.evaluate(NEW, E.DEFAULT_METHODS, data=data)


def test_the_person_is_hidden_for_a_short_time_behind_the_nearer_box():
    scene = S.Scene.builtin("occlusion")
    rig = camera.load_calibration("lifecam-studio")
    world = S.SyntheticWorld(scene, rig, Rectifier(rig).rectification)
    times = np.arange(0.0, 2.2, 1 / 30)
    truth = [world.truth(t) for t in times]
    box, person = truth[0]
    assert box.center_m[2] < person.center_m[2] - 1.0  # the box is nearer
    px = np.array([tr[1].visible_px for tr in truth])
    hidden = times[px == 0]
    assert hidden.size and np.all(np.diff(hidden) < 1.5 / 30)  # one contiguous gap
    assert 0.3 <= hidden[-1] - hidden[0] + 1 / 30 <= 0.6, hidden
    assert px[times < hidden[0] - 0.3].min() > 10000 and px[times > hidden[-1] + 0.3].min() > 10000


def test_layers_keeps_the_persons_id_through_the_occlusion(result):
    s = result["scenarios"]["occlusion"]["layers"]
    person = s.per_truth["person"]
    assert person["hidden"] >= 6 and person["gaps"] == 1  # gone for a while, then back
    assert len(person["ids"]) == 1 and s.id_switches == 0, person
    assert person["matched"] >= person["seen"] - 1 > 20


def test_layers_recall_and_precision_on_the_new_scenarios(result):
    for name in NEW:
        s = result["scenarios"][name]["layers"]
        assert s.recall >= 0.95 and s.precision >= 0.95, (name, E.format_table(result))
        assert s.floor_fp == 0 and s.wall_fp == 0, name
        assert s.depth_err_med_pct <= 3.0, name
    # hidden frames expect nothing: only frames with >= 400 measurable pixels are counted
    occ = result["scenarios"]["occlusion"]["layers"]
    assert occ.truths == 2 * occ.frames - occ.per_truth["person"]["hidden"]


def test_an_id_lost_in_the_gap_is_one_id_switch(data):
    """A tracker that forgets the person while hidden: the id after reappearance differs -> 1 switch."""
    s = E.score_method(data["occlusion"], "layers", {"track_timeout_s": 0.2})
    person = s.per_truth["person"]
    assert s.id_switches == 1 and len(person["ids"]) == 2, person
    assert s.recall >= 0.95 and s.precision >= 0.95  # detection is unaffected


def test_glimpsed_obstacles_are_neither_required_nor_false_positives(data):
    # with a high bar the partly hidden person is only "glimpsed" in many frames: its detections
    # there must not count against precision
    s = E.score_method(data["occlusion"], "layers", min_visible_px=15000)
    assert s.per_truth["person"]["hidden"] > 10
    assert s.precision == 1.0 and s.split_fp == 0 and s.recall >= 0.95


def test_seed_fails_on_the_right_border_object(result):
    sc = result["scenarios"]["border-right"]
    # the thesis's method, floor in range: the floor swallows the box
    assert sc["seed"].matched == 0 and sc["seed"].floor_fp > 0
    assert sc["layers"].recall == 1.0


@pytest.mark.xfail(strict=True, reason="seed's clear-border step tests the image edge, but block matching "
                   "leaves the last block/2 columns invalid, so a region cut by the right border ends at "
                   "x = W - 7 and is kept (the thesis's imclearborder would remove it)")
def test_seed_clear_border_removes_the_right_border_object(result):
    assert result["scenarios"]["border-right"]["seed+floor"].matched == 0


def test_eval_runs_every_shipped_scenario_by_default():
    """All but those too slow to render for every run (the swaying camera: every frame ray-cast
    anew), which run by name."""
    names = S.list_builtin_scenarios()
    assert set(NEW) <= set(names)
    slow = [n for n in names if not S.Scene.builtin(n).default_eval]
    assert slow == ["sway", "sway-pivot"]
    r = E.evaluate(None, ["layers"], frames=1)
    assert list(r["scenarios"]) == [n for n in names if n not in slow]
