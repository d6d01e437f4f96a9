"""Acceptance of the segmenter on the real pipeline: every shipped synthetic scenario rendered,
rectified, block-matched and segmented, scored against ground truth (evaluation/synthetic.py).
The thesis's method (`seed`) passes its one-object scene and shows its known failures; `layers`
(the default) passes them all."""
from __future__ import annotations

import json

import numpy as np
import pytest

from evaluation import synthetic as E
from sim import list_builtin_scenarios

SCENARIOS = ["two-boxes", "toolbox", "chair", "touching", "border", "person-walking"]


@pytest.fixture(scope="module")
def data():
    assert set(SCENARIOS) <= set(list_builtin_scenarios())
    out = {}
    for name in SCENARIOS:
        # the walking person: 2.6 s at 10 fps covers a turn at the near end of the path
        frames, fps = (26, 10.0) if name == "person-walking" else (2, 15.0)
        out[name] = E.render_scenario(name, frames=frames, fps=fps)
    return out


@pytest.fixture(scope="module")
def result(data):
    return E.evaluate(SCENARIOS, E.DEFAULT_METHODS, data=data)


def test_the_measurable_surface_is_what_both_cameras_see():
    """The truth a detection is scored on is the surface the matcher can measure; it counted what
    the left camera sees, so the strip of a crate beside a nearer person that the right camera
    does not see (the sway scene's crate, 9 px wide behind the walking person) was a miss no
    matcher could avoid. On a rectified row, a background at 10 px of disparity is hidden from
    the right camera over the 20 px left of a person at 30 px (within a pixel); a background at
    infinity over 30 px; the person itself and the rest are seen."""
    d = np.full((2, 100), 10.0)
    d[1] = 0.0  # the background at infinity
    d[:, 50:71] = 30.0
    seen = E.visible_in_right(d)
    assert np.flatnonzero(~seen[0]).tolist() == list(range(32, 50))
    assert np.flatnonzero(~seen[1]).tolist() == list(range(22, 50))
    assert seen[:, 50:].all()


def test_layers_meets_the_acceptance_targets(result):
    s = result["overall"]["layers"]
    assert s.recall >= 0.95, E.format_table(result)
    assert s.precision >= 0.95, E.format_table(result)
    assert s.depth_err_med_pct <= 3.0, E.format_table(result)
    assert s.pos_err_med_pct <= 3.0, E.format_table(result)
    assert s.floor_fp == 0 and s.wall_fp == 0
    assert s.free_under == 0, E.format_table(result)  # no free cell in what stands
    for name in SCENARIOS:
        sc = result["scenarios"][name]["layers"]
        assert sc.recall >= 0.95 and sc.precision >= 0.95, (name, E.format_table(result))
        assert sc.floor_fp == 0, name


def test_layers_tracks_the_walking_person_without_an_id_switch(result):
    s = result["scenarios"]["person-walking"]["layers"]
    person = s.per_truth["person"]
    assert person["matched"] == person["seen"] > 20
    assert len(person["ids"]) == 1 and s.id_switches == 0
    # 0.8 m/s; the error is dominated by the instant turn at the end of the path
    assert s.vel_err_mps < 0.3


def test_layers_positions_against_the_truth(result):
    # the strip that floor removal cuts off objects standing on the floor is filled back in
    for name in ("two-boxes", "touching", "toolbox", "chair", "person-walking"):
        s = result["scenarios"][name]["layers"]
        assert s.pos_err_p95_pct <= 2.0, (name, s.pos_err_p95_pct)
        det = [v for v in s.per_truth.values()]
        assert all(d["matched"] == d["seen"] for d in det)


def test_seed_reproduces_the_thesis_on_its_one_object_scene(result):
    s = result["scenarios"]["toolbox"]["seed"]
    assert s.recall == 1.0 and s.precision == 1.0
    assert s.depth_err_med_pct <= 3.0


def test_seed_known_failures_are_shown(result):
    sc = result["scenarios"]
    # floor in range: without floor removal the floor becomes (or swallows) the obstacle
    assert sc["two-boxes"]["seed"].floor_fp > 0
    assert sc["two-boxes"]["seed"].recall < 0.5
    # touching objects at different depths merge into one region (even with the floor removed)
    assert sc["touching"]["seed+floor"].recall <= 0.5
    assert sc["touching"]["seed+floor"].detections < sc["touching"]["seed+floor"].truths
    # objects touching the image border are removed
    assert sc["border"]["seed+floor"].matched == 0
    # the default beats it overall
    assert result["overall"]["layers"].recall > result["overall"]["seed"].recall
    assert result["overall"]["layers"].recall > result["overall"]["seed+floor"].recall


def test_report_formats(result):
    table = E.format_table(result)
    for name in SCENARIOS + ["overall"]:
        assert name in table
    doc = E.result_to_json(result)
    text = json.dumps(doc)  # NaN-free
    assert "NaN" not in text
    assert doc["overall"]["layers"]["recall"] >= 0.95
    assert set(doc["scenarios"]) == set(SCENARIOS)


def test_mount_recovered_from_the_world_matches_the_scene(result):
    data = E.render_scenario("toolbox", frames=1)
    m = data.mount
    assert abs(m.height_m - data.scene.camera_height_m) < 1e-6
    assert abs(m.pitch_deg - data.scene.camera_pitch_deg) < 1.0  # rectification turns the camera slightly
    # the truth centre, taken to the base frame by the mount, is where the scene put the object
    t = data.frames[0].truth[0]
    base = m.to_base(np.asarray(t.center_m))
    box = data.scene.boxes[0]
    assert np.allclose(base[:2], box.center[:2], atol=1e-6)


def test_a_wrong_mount_is_a_prior_for_both_methods(data):
    """A ballbot leans while it balances: the segmenter's idea of the mount is off by degrees. Both
    methods remove the floor the ground estimator finds, the mount only its prior: seed's lists with
    the wrong mount are its lists with the right one (before, seed removed the floor by the mount and
    turned it into obstacles)."""
    r = E.evaluate(SCENARIOS, ["seed+floor", "layers"], data=data,
                   mount_error={"pitch_deg": -4.0, "roll_deg": 3.0, "height_m": 0.1})
    right = E.evaluate(SCENARIOS, ["seed+floor"], data=data)["overall"]["seed+floor"]
    layers, seed_floor = r["overall"]["layers"], r["overall"]["seed+floor"]
    assert layers.recall >= 0.95 and layers.precision >= 0.95 and layers.floor_fp == 0, E.format_table(r)
    assert seed_floor.floor_fp == 0, E.format_table(r)
    assert (seed_floor.matched, seed_floor.detections) == (right.matched, right.detections), E.format_table(r)


def test_a_miss_is_said(result):
    """A list that leaves out what stands in view says so (degraded): the thesis's border clearing drops
    the box at the border, and seed's lists there say standing-not-listed. What is left unsaid is a merge,
    two objects in one obstacle (touching, for seed). The default method misses nothing here, and flags
    nothing: on these scenes every list can be trusted."""
    sc = result["scenarios"]
    s = sc["border"]["seed+floor"]
    assert s.matched < s.truths and s.silent_misses == 0 and s.flagged_frames == s.frames, s.to_dict()
    silent = {name: by["seed+floor"].silent_misses for name, by in sc.items() if by["seed+floor"].silent_misses}
    assert set(silent) <= {"touching"}, silent
    layers = result["overall"]["layers"]
    assert layers.silent_misses == 0 and layers.flagged_frames == 0, layers.to_dict()


DECIDING = ("floor_margin_m", "ground_noise_px", "min_height_m", "min_size_m", "min_area_m2", "min_cell_height_m")


def test_the_settings_that_decide_an_obstacle_at_the_ends_of_their_ranges_still_list_what_stands(data):
    """Each setting that decides what is an obstacle, at the upper end its settings allow, and all of them
    at once, misses nothing here: past those ends the lists thinned with no word (min_cell_height_m 0.2
    lost the walking person in 13 of 26 frames, min_height_m 0.5 and floor_margin_m 0.3 the thesis's
    toolbox and freed the floor under it; group_bin_px 0.1, the lower end before, the walking person in 14
    frames). Read from the settings, so a bound widened fails here."""
    from test_settings_bounds import _ends

    from cores.segmentation.settings import SegmenterSettings

    bounds: dict[str, list] = {}
    for name, value in _ends(SegmenterSettings):
        bounds.setdefault(name, []).append(value)
    ends = {name: max(bounds[name]) for name in DECIDING}
    # and the lower ends that matter: the floor's own noise standing, standing points grouped too finely
    others = [{"floor_margin_m": min(bounds["floor_margin_m"])}] + [{"group_bin_px": v} for v in bounds["group_bin_px"]]
    for overrides in [{name: value} for name, value in ends.items()] + [ends] + others:
        r = E.evaluate(SCENARIOS, ["layers"], data=data, overrides=overrides)
        s = r["overall"]["layers"]
        missed = {n: by["layers"].silent_misses for n, by in r["scenarios"].items() if by["layers"].silent_misses}
        assert not missed and s.free_under == 0, (overrides, missed, s.free_under)


def test_a_low_robot_is_scored_on_what_it_lists_of_a_person_their_legs(data):
    """A robot 0.5 m tall lists a person's legs (what stands higher is not in its way); scored against the
    whole person's centroid, 0.4 m higher, the eval called 37 of the walking person's 45 sightings missed
    and the legs false positives. Each truth is scored on its surface below the robot's height."""
    for robot in (2.0, 0.5):
        s = E.evaluate(["person-walking"], ["layers"], data=data, overrides={"robot_height_m": robot})
        s = s["overall"]["layers"]
        assert s.recall == 1.0 and s.precision == 1.0 and s.pos_err_p95_m < 0.15, (robot, s.to_dict())
    fr = data["person-walking"].frames[0]
    (whole, n), (legs, n_legs) = fr.measurable[0], fr.measurable_below(0.5)[0]
    assert 0 < n_legs < 0.5 * n and legs[1] > whole[1] + 0.3, (whole, legs)  # image y points down


@pytest.mark.parametrize("method", ["bm", "sgbm", "dense"])
def test_each_matcher_at_its_smallest_window_lists_the_plain_low_faces(method):
    """The smallest window each matcher takes (MIN_BLOCK) still lists the plain crate and cabinet, with
    no free space under them: bm at 5 px (allowed before, and by OpenCV) missed both in every frame
    with no degraded reason. Read from the settings, so a bound lowered fails here."""
    from cores.matching.config import MIN_BLOCK, MatcherConfig

    data = E.render_scenario("low-faces", matcher=MatcherConfig(method=method, block_size=MIN_BLOCK[method]))
    s = E.score_method(data, "layers")
    assert s.silent_misses == 0 and s.free_under == 0, s.to_dict()


def test_the_eval_segments_what_the_disparity_stage_hands_on():
    """The eval's segmenter gets the map's search with the map, as the service does from the disparity
    message: a 32 px search on this rig measures nothing nearer than 2.1 m, the toolbox stands nearer,
    and every list says near-unmeasured (the eval had dropped the search: 0 of its lists were flagged,
    and its 86 misses of 208 over the shipped scenes all looked like clear ways)."""
    from cores.matching.matchers import MatcherConfig

    data = {"toolbox": E.render_scenario("toolbox", frames=2, matcher=MatcherConfig(num_disparities=32))}
    assert data["toolbox"].frames[0].search == (0, 32)
    s = E.evaluate(["toolbox"], ["layers"], data=data)["overall"]["layers"]
    assert s.matched < s.truths and s.flagged_frames == s.frames and s.silent_misses == 0, s.to_dict()


def test_the_eval_segments_with_the_gate_and_rectify_s_checks_the_services_hand_on():
    """The rest of what the services hand the segmenter with a map: the disparity stage's vision range
    gate (DisparityMap.gate_px) and rectify's checks of the pair (FrameChecks). The eval had dropped
    both: a matcher gated at 1 m, nothing beyond measured, gave lists that said nothing; and a list
    could never say what rectify finds (a noisy pair, what stands nearer than the range)."""
    import dataclasses

    from common.messages import FrameChecks
    from cores.matching.matchers import MatcherConfig

    data = E.render_scenario("toolbox", frames=2, matcher=MatcherConfig(max_range_m=1.0))
    fB = data.model.focal_px * data.model.baseline_m
    assert data.frames[0].gate_px == pytest.approx(fB / 1.0)
    s = E.evaluate(["toolbox"], ["layers"], data={"toolbox": data})["overall"]["layers"]
    assert s.flagged_frames == s.frames and s.silent_misses == 0, s.to_dict()
    # rectify's checks measured each pair (the renderer's sensor noise: a daylight camera's)...
    data = E.render_scenario("toolbox", frames=2)
    checks = [f.checks for f in data.frames]
    assert all(c is not None and 0.5 < c.noise_grey < 3.0 and c.near is not None for c in checks), checks
    assert E.evaluate(["toolbox"], ["layers"], data={"toolbox": data})["overall"]["layers"].flagged_frames == 0
    # ... and what they say reaches the lists the eval scores
    data.frames[:] = [dataclasses.replace(f, checks=FrameChecks(noise_grey=9.0)) for f in data.frames]
    s = E.evaluate(["toolbox"], ["layers"], data={"toolbox": data})["overall"]["layers"]
    assert s.flagged_frames == s.frames, s.to_dict()


# --- people close to a low camera (10 m range) ------------------------------------------------------

PEOPLE = ["people-side", "people-side-far", "people-queue", "people-queue-far", "people-border"]


@pytest.fixture(scope="module")
def people():
    data = {name: E.render_scenario(name, frames=2) for name in PEOPLE}
    return E.evaluate(PEOPLE, ["layers"], data=data)["scenarios"]


def test_people_side_by_side_are_one_obstacle_each_from_2_5_to_9_5_m(people):
    """Pairs 0.15-0.3 m apart at 2.5, 5, 7 and 9.5 m: each person is one obstacle where they stand."""
    for name in ("people-side", "people-side-far"):
        s = people[name]["layers"]
        assert s.recall == 1.0 and s.precision == 1.0, (name, s.to_dict())
        assert s.pos_err_p95_pct <= 2.5, (name, s.pos_err_p95_pct)


def test_people_side_by_side_stay_apart_once_their_tracks_are_confirmed():
    """From the fourth frame on, a confirmed track takes in the detections inside its footprint
    (a fence's pieces): padded by the stereo noise 9.5 m away (0.35 m) across the line of sight too,
    one person's footprint took in the one 0.3 m beside them, and 3 of 6 sightings of her were in no
    list with nothing said. The noise is in the range: the pad lies along the line of sight."""
    data = E.render_scenario("people-side-far", frames=6)
    s = E.score_method(data, "layers")
    assert s.matched == s.truths == 24 and s.silent_misses == 0 and s.id_switches == 0, s.to_dict()


def test_people_one_behind_another_are_separate_obstacles(people):
    """0.3 m between the back of one and the front of the other: at 2 m and 4.5 m, and at 7 m where
    it is under half a pixel of disparity for this rig's 10 cm baseline."""
    s = people["people-queue"]["layers"]
    assert s.recall == 1.0 and s.precision == 1.0, s.to_dict()
    far = people["people-queue-far"]["layers"]
    for name in ("front-c", "behind-c"):
        assert far.per_truth[name]["matched"] == far.per_truth[name]["seen"] == 2, far.per_truth
    assert far.precision == 1.0


def test_people_side_by_side_stay_apart_with_the_wall_behind_them_in_range():
    """The far pairs with a 20 m range (the scene's is 10 m): the wall at 12 m, seen between the two
    of a pair one disparity bin farther, joins them on the column-disparity grid; the depth split
    takes the wall off, and each layer is cut again into the things it holds apart. Before, each
    pair was one obstacle matched to one of them: 3 of 12 people in no list, nothing said."""
    data = E.render_scenario("people-side-far", frames=2)
    s = E.score_method(data, "layers", {"max_range_m": 20.0}, eval_range_m=10.0)
    assert s.matched == s.truths == 8 and s.silent_misses == 0, s.to_dict()


@pytest.mark.xfail(strict=True, reason="9 m from the lifecam rig (f B = 64 px m) 0.55 m of depth is 0.43 px of "
                   "disparity, within block matching's noise on a person (their disparities spread over ~0.5 px): "
                   "the two are one obstacle")
def test_people_one_behind_another_9_m_away_are_separate(people):
    far = people["people-queue-far"]["layers"]
    assert all(far.per_truth[n]["matched"] == far.per_truth[n]["seen"] for n in ("front-d", "behind-d"))


def test_people_cut_by_the_image_border_are_obstacles_flagged_truncated_with_their_near_edge_right(people):
    s = people["people-border"]["layers"]
    assert s.recall == 1.0 and s.precision == 1.0, s.to_dict()
    assert s.border_truths == 4 and s.border_flagged == 4  # two people cut, two frames
    assert s.near_err_p95_m <= 0.05, s.near_err_p95_m  # the nearest point, against the truth's measurable one
    assert s.border_edge_err_px <= 8, s.border_edge_err_px  # the box side away from the border


# --- a swaying ballbot ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def sway():
    # 20 frames at 15 fps: the camera pitches from 11 to 17 and back to 1.5 deg, rolls from +6 to -9 deg
    return E.render_scenario("sway", frames=20, fps=15.0)


SPLITTING = ("min_cell_height_m", "group_bin_px", "merge_gap_m", "merge_gap_depth_m", "layer_valley_ratio",
             "layer_min_area_m2", "layer_gap_m", "layer_bridge_px", "layer_split_range_m")


def test_grouping_and_splitting_at_each_end_of_their_ranges_keep_the_sway_s_people_and_furniture_apart(sway):
    """Where people walk among furniture, the settings that group standing points, merge regions and
    split them by depth each at either end of its range miss at most 2 more things than the defaults:
    at the old ends (min_cell_height_m 0, group_bin_px 4, merge gaps 0.5 m, a depth split that never
    splits) people stood merged with the chair or the table in 14-203 of `eval sway`'s 223 sightings, no
    degraded reason said. Read from the settings, so a bound widened fails here."""
    from test_settings_bounds import _ends

    from cores.segmentation.settings import SegmenterSettings
    base = E.evaluate(["sway"], ["layers"], data={"sway": sway})["overall"]["layers"].silent_misses
    for name, value in _ends(SegmenterSettings):
        if name in SPLITTING:
            s = E.evaluate(["sway"], ["layers"], data={"sway": sway}, overrides={name: value})["overall"]["layers"]
            assert s.silent_misses <= base + 2 and s.free_under == 0, (name, value, base, s.to_dict())


def test_sway_with_the_true_ground_holds_what_stands_still_within_5_cm(sway):
    """Given each frame's true ground, the base frame (REP 103, not tilted by the sway) holds the
    chair, the standing person and the crate steady within 5 cm while the robot drives and sways;
    the table, which the walking person passes behind, is seen with more or less of it. (Seen
    almost edge-on from 0.9 m, the table's top barely shows: its back leg is at times seen apart from
    its front, 3 cm deep at the back edge of the table's tracked footprint, and joins it there: it
    was an obstacle of its own in 2 frames, precision 98 %, while a footprint under 5 cm deep
    counted only partly inside the table's.)"""
    s = E.score_method(sway, "layers", true_ground=True)
    assert s.ground_fitted == 1.0 and s.ground_pitch_err_max_deg < 1e-6
    for name in ("chair", "standing", "crate"):
        assert s.per_truth[name]["wobble_p95_m"] <= 0.05, (name, s.per_truth[name])
    assert s.base_err_med_m <= 0.05, s.to_dict()
    assert s.recall >= 0.85 and s.precision == 1.0 and s.split_fp == 0, s.to_dict()


def test_sway_the_ground_is_found_every_frame(sway):
    """The camera pitches and rolls by up to 8 deg from one frame to the next: the ground is fitted
    afresh in every frame, within a degree (cores/segmentation/ground.py)."""
    s = E.score_method(sway, "layers")
    assert s.ground_fitted == 1.0 and s.ground_pitch_err_max_deg <= 1.0 and s.ground_roll_err_max_deg <= 1.0, \
        [g for g in s.ground if g["source"] != "fitted"]


def test_sway_a_table_s_back_leg_is_not_cut_from_it_nor_the_person_behind_joined_to_it(sway):
    """With the ground estimate: the table's side rail, seen end-on on its back leg, keeps the leg
    with the table (the layer split once cut it off: a false positive beside the table in most
    frames, precision 91 %), and the person walking behind the table stays apart from it."""
    s = E.score_method(sway, "layers")
    assert s.recall >= 0.99 and s.precision == 1.0, s.to_dict()


def test_sway_about_the_ball_the_configured_pivot_places_the_camera():
    """The same sway as a lean of the robot about its ball (sway-pivot: 0.15 m high) carries the
    camera over the floor by up to 13 cm, which the ground cannot show. Told the pivot
    (mount.pivot_height_m), the segmenter places the camera by the lean the ground shows: with each
    frame's true ground, what stands still stays within 5 cm (median error; without the pivot
    10 cm, the chair and the crate wobbling by 10-13 cm)."""
    data = E.render_scenario("sway-pivot", frames=12, fps=15.0)
    s = E.score_method(data, "layers", true_ground=True)
    assert s.base_err_med_m <= 0.05, s.to_dict()
    for name in ("chair", "crate"):
        assert s.per_truth[name]["wobble_p95_m"] <= 0.05, (name, s.per_truth[name])


def test_eval_ground_figures_agree_with_the_estimator_on_a_still_camera(data):
    """The eval's true mount and the estimator's ground use one convention: on the still scenes
    the fitted ground is within a few tenths of a degree and a centimetre."""
    r = E.evaluate(["two-boxes", "chair"], ["layers"], data=data)["overall"]["layers"]
    assert r.ground_fitted == 1.0
    assert r.ground_pitch_err_max_deg < 0.5 and r.ground_roll_err_max_deg < 0.8 and r.ground_height_err_max_m < 0.02


@pytest.fixture(scope="module")
def low_faces():
    """method -> the low-faces scene's score with that matcher (rendered once per method)."""
    from cores.matching.config import MatcherConfig

    rendered: dict = {}
    scores: dict = {}

    def score(method: str, range_m: float | None = None) -> E.Score:
        """range_m: the vision range the segmenter runs with (and the truths count within); None: the scene's."""
        if method not in rendered:
            rendered[method] = E.render_scenario("low-faces", matcher=MatcherConfig(method=method))
        if (method, range_m) not in scores:
            scores[method, range_m] = E.score_method(rendered[method], "layers",
                                                     None if range_m is None else {"max_range_m": range_m},
                                                     eval_range_m=range_m)
        return scores[method, range_m]
    return score


@pytest.mark.parametrize("method", ["bm", "sgbm", "dense"])
def test_a_plain_cabinet_lower_than_the_camera_is_an_obstacle_with_every_matcher(method, low_faces):
    """The low-faces scene's plain cabinet, 0.85 m high 3 m ahead: the floor beyond it shows above
    it. dense doubted every pixel of it and the list was empty in every frame, silently; now its
    doubted top edge and face make it an obstacle with every matcher."""
    s = low_faces(method)
    t = s.per_truth["cabinet"]
    assert t["matched"] == t["seen"] == 3, (method, t)
    assert s.floor_fp == 0 and s.wall_fp == 0


@pytest.mark.parametrize("method", ["bm", "sgbm", "dense"])
def test_a_plain_crate_is_an_obstacle_with_a_vision_range_short_of_the_floor_beyond_it(method, low_faces):
    """With a 2-3 m range the floor that shows again above the crate's top (out to 3.1 m) lies beyond
    the range: dense left the crate in no list in every frame, nothing said, until the floor measured
    beyond the range counted as floor seen where plain faces are looked for."""
    for range_m in (2.0, 2.5):
        s = low_faces(method, range_m)
        t = s.per_truth["crate"]
        assert t["matched"] == t["seen"] == 3 and s.silent_misses == 0, (method, range_m, t)
        assert s.free_under == 0 and s.floor_fp == 0


@pytest.mark.xfail(strict=True, reason="with a 20 cm baseline bm measures the plain cabinet's side 2-4 px wide "
                   "(its half-occluded band is twice the thesis rig's), which the 5 px median filter on the working "
                   "grid removes; and the floor's disparities carried up the face by bm's window end 12 rows above "
                   "its foot, 7 px of disparity off the face's (CAP_PX is 3), so no side at the stop's depth is "
                   "found even in the raw map: both boxes in no list in any frame (the free space leaves them "
                   "unknown but for a cell at an edge)")
def test_plain_low_faces_are_obstacles_on_a_rig_with_twice_the_baseline(tmp_path):
    from cores import camera

    base = camera.load_raw_rig("lifecam-studio")
    wide = camera.RawRig(image_size=base.image_size, left=base.left, right=base.right, R=base.R, T=base.T * 2.0,
                         name="wide")
    camera.save_calibration(wide, tmp_path / "wide.yaml")
    data = E.render_scenario("low-faces", frames=3, calibration=str(tmp_path / "wide.yaml"))
    s = E.score_method(data, "layers")
    assert s.matched == s.truths and s.silent_misses == 0 and s.free_under == 0, s.to_dict()


@pytest.mark.parametrize("scene", ["low-faces", "blank-faces"])
def test_the_half_resolution_fallback_leaves_no_free_space_under_a_plain_face(scene):
    """The dispatcher's onboard `fallback: half` matches at half resolution. Its speckle filter was
    scaled with the area (25 px): the blobs bm makes of a plain face's noise stayed, passed for floor
    seen far away, and the free space reached under the low-faces crate and cabinet (7 of 16
    sightings in 8 frames; the crate in no list in one); blank-faces' panel was missed once."""
    from cores.matching.config import MatcherConfig

    data = E.render_scenario(scene, frames=8, matcher=MatcherConfig(method="bm"), match_scale=0.5)
    s = E.score_method(data, "layers")
    assert s.free_under == 0 and s.silent_misses == 0 and s.matched == s.truths, s.to_dict()


def test_a_face_s_lowest_rows_passing_for_floor_take_the_free_space_no_further_than_the_face():
    """A face's rows within floor_margin_m of the floor pass for floor. Taken where the floor plane
    puts their rays, they vouched for floor behind the face: with the segmenter working on every
    pixel (downsample 1) or every 4th, the free space reached under the low-faces cabinet in its 5th
    frame (8 cm inside it; the same on a 1280x720 rig). A floor pixel now counts out to the nearer of
    where it was measured and where the plane puts it."""
    from cores.matching.config import MatcherConfig

    data = E.render_scenario("low-faces", frames=6, matcher=MatcherConfig(method="bm"))
    for downsample in (1, 4):
        s = E.score_method(data, "layers", {"downsample": downsample})
        assert s.free_under == 0, (downsample, s.to_dict())


@pytest.mark.parametrize("method", ["bm", "dense"])
def test_plain_low_faces_are_obstacles_when_the_segmenter_works_on_every_4th_pixel(method):
    """At downsample 4 a 5 px median filter spans 20 px of the map: it wiped out the narrow side block
    matching measures of the low-faces cabinet (bm) or crate (dense), the face's only evidence, and
    each was in no list in any frame, unflagged. The default filter there is 3 px (12 px of the map,
    as 5 at downsample 2 spans 10)."""
    from cores.matching.config import MatcherConfig

    data = E.render_scenario("low-faces", matcher=MatcherConfig(method=method))
    s = E.score_method(data, "layers", {"downsample": 4})
    assert s.matched == s.truths and s.silent_misses == 0 and s.free_under == 0, (method, s.to_dict())


@pytest.mark.parametrize("scene", ["chair", "people-queue"])
def test_what_stands_nearer_than_the_vision_range_stops_the_free_space(scene):
    """min_range_m 2: the chair's front and the nearest person stand nearer, in no list (the range
    leaves them out); the floor seen beyond them made free the cells under the chair's seat and the
    person (free under 3 and 2 with bm). What stands there stops the free space as anything standing."""
    from cores.matching.config import MatcherConfig

    data = E.render_scenario(scene, matcher=MatcherConfig(method="bm"))
    s = E.score_method(data, "layers", {"min_range_m": 2.0})
    assert s.free_under == 0, s.to_dict()


def test_a_speck_of_false_floor_on_a_plain_face_frees_nothing():
    """Block matching without its speckle filter (speckle_window 0) matches bits of the plain crate's
    face at random; one bit, 3 working pixels in a row at the floor's disparity of its row, passed for
    floor seen 22 rows above the image's bottom edge, a stretch too short to hide anything: the free
    space ran from the edge to it, under the crate. A floor pixel with fewer than 3 of its 8 neighbours
    floor is no floor seen."""
    from cores.matching.config import MatcherConfig

    data = E.render_scenario("low-faces", matcher=MatcherConfig(method="bm", speckle_window=0))
    s = E.score_method(data, "layers")
    assert s.free_under == 0 and s.matched == s.truths, s.to_dict()


def test_the_free_space_stops_short_of_the_floor_s_end_by_its_noise(tmp_path):
    """On a 640x360 rig with an 85 deg field of view (f 350 px, 12 cm: half a pixel is 10 cm at 3 m)
    the floor seen beside the low-faces cabinet's plain side ended 5-8 cm inside it, and the free space
    reached that far in from the 3rd frame on. The free space now stops half a pixel of disparity
    short of where the floor seen ends."""
    from cores import camera

    intr = camera.Intrinsics(350.0, 350.0, 319.5, 179.5, 0.0, (0.0, 0.0, 0.0, 0.0, 0.0))
    rig = camera.RawRig(image_size=(640, 360), left=intr, right=intr, R=np.eye(3), T=np.array([-0.12, 0.0, 0.0]),
                        name="wide-view")
    camera.save_calibration(rig, tmp_path / "wide-view.yaml")
    data = E.render_scenario("low-faces", frames=4, calibration=str(tmp_path / "wide-view.yaml"))
    assert E.score_method(data, "layers").free_under == 0


def test_the_floor_seen_just_past_a_thing_s_side_frees_nothing_behind_it():
    """sway-pivot with dense, frame 16: the crate's first standing column lay 2 working columns right
    of its side (dense's window carries the floor's depth into it), and the floor seen in the column
    beside it reached 1.5 cm inside the crate's back corner, which freed a 10 cm cell three quarters
    of which lies in the crate. A thing standing now stops the columns beside it, within the median
    filter's reach."""
    from cores.matching.config import MatcherConfig

    data = E.render_scenario("sway-pivot", frames=17, matcher=MatcherConfig(method="dense"))
    s = E.score_method(data, "layers")
    assert s.free_under == 0 and s.silent_misses == 0, s.to_dict()


def test_a_plain_crate_half_in_the_blind_band_is_an_obstacle():
    """bm searching 128 px is blind in the image's left 128 columns: of the low-faces crate, cut by the
    image's left side, it saw 58 working columns (0.27 m) right of the band, a run of plain face
    columns narrower than a face (blank.MIN_WIDTH_M), and the crate was in no list in frame 2,
    unflagged. A face run that ends at the side of the view is as wide as it is there or wider."""
    from cores.matching.config import MatcherConfig

    data = E.render_scenario("low-faces", matcher=MatcherConfig(method="bm", num_disparities=128))
    s = E.score_method(data, "layers")
    assert s.matched == s.truths and s.silent_misses == 0 and s.free_under == 0, s.to_dict()


@pytest.mark.parametrize("method", ["bm", "dense"])
def test_a_plain_crate_below_the_image_is_an_obstacle_whatever_the_smallest_height(method):
    """Rule 3 (blank._below_image) tied how far the crate's measured side may end short of the image's
    bottom edge and of its top edge to min_height_m, and measured the side's height from the edge: at
    min_height_m 0.1 dense's side ended 0.14 m short of the edge, at 0.3 bm's (0.35 m crate) was 0.3 m
    tall from it less half a row, and the crate was in no list in 1-2 of 3 frames, unflagged. Where a
    matcher loses a side is no obstacle's height (blank.SIDE_SHORT_M); a height is from the foot."""
    from cores.matching.config import MatcherConfig

    data = E.render_scenario("low-faces", matcher=MatcherConfig(method=method))
    for min_height in (0.1, 0.2):
        s = E.score_method(data, "layers", {"min_height_m": min_height})
        assert s.matched == s.truths and s.silent_misses == 0 and s.free_under == 0, (min_height, s.to_dict())


def test_a_plain_face_seen_in_pieces_frees_nothing_behind_it():
    """dense with an 11 px window reads the low-faces cabinet's plain front in runs of columns with
    7 working columns (6 cm) of nothing standing between them, where the window carried the floor up
    the face's foot: seen up to 20 cm behind the face, it freed a cell 5-15 cm inside the cabinet in
    frame 0. A gap too narrow to pass between two things stops the free space at the nearer one."""
    from cores.matching.config import MatcherConfig

    data = E.render_scenario("low-faces", frames=1, matcher=MatcherConfig(method="dense", block_size=11))
    s = E.score_method(data, "layers")
    assert s.free_under == 0 and s.matched == s.truths, s.to_dict()


@pytest.mark.parametrize("method", ["bm", "sgbm", "dense"])
def test_the_free_space_never_reaches_under_a_plain_crate_or_cabinet(method, low_faces):
    """sgbm carries the floor's disparities beside a plain face into it, row by row: taken for floor
    seen, they made free space under the crate in 8 of 24 sightings (12 frames). Its windows too
    plain to decide their match (Match.flat) are no floor seen."""
    assert low_faces(method).free_under == 0, method


def test_a_person_behind_another_seen_from_a_tall_camera_looking_down_is_an_obstacle_of_their_own():
    """people-queue from 1.2 m at 20 deg down: the person 0.5 m behind the nearer one at 2 m, side by
    side with them in the image (their heads cut by its top), were two regions whose boxes came
    within 7 cm in depth (each reached into the other's depths by the ramp between them), the
    nearest points 0.4 m apart: merge_close joined them by their boxes, one obstacle, the person
    behind in no list (bm, sgbm, dense: 7-8 of 16 people missed in 4 frames). Two regions each as
    wide as a person that meet side by side in the image are now joined only where their points
    touch. Without "side by side in the image" a facade seen obliquely on the street, its pieces
    apart in the image, fell into 6 obstacles (bm 30 m: long tracks 68.8 -> 64.2 %). (The pair at
    4.3 and 4.9 m is one cell group whose depth valley is just too shallow to split: still one.)"""
    import dataclasses

    import sim as S

    scene = dataclasses.replace(S.Scene.builtin("people-queue"), camera_height_m=1.2, camera_pitch_deg=20.0)
    s = E.score_method(E.render_scenario(scene, frames=2), "layers")
    for name in ("front-a", "behind-a"):
        assert s.per_truth[name]["matched"] == s.per_truth[name]["seen"] == 2, (name, s.per_truth)
    assert s.precision == 1.0, s.to_dict()


@pytest.mark.parametrize("method", ["bm", "sgbm", "dense"])
def test_a_chair_is_one_obstacle_with_every_matcher(method):
    """The chair seen from 2 m: its front leg stands apart in the image from the seat's body, and
    the seat's corner between them is a region under the smallest obstacle's size. Dropped before
    regions were joined, it left the leg 13 cm from the rest (merge_gap_m: 12 cm): with dense the
    leg was an obstacle of its own in every frame (precision 50 %). Small pieces now join the
    regions they touch; what stays small alone is still dropped."""
    from cores.matching.config import MatcherConfig

    data = {"chair": E.render_scenario("chair", matcher=MatcherConfig(method=method))}
    s = E.evaluate(["chair"], ["layers"], data=data)["scenarios"]["chair"]["layers"]
    assert s.recall == 1.0 and s.precision == 1.0 and s.split_fp == 0, (method, s.to_dict())


@pytest.mark.parametrize("method", ["bm", "sgbm", "dense"])
def test_plain_faces_nothing_can_be_matched_in_are_obstacles_with_every_matcher(method):
    """A painted cabinet and a white panel, taller than the camera: block matching measures at most
    their outlines. Each is an obstacle in every frame, with every matcher (dense's own fill takes
    them for the wall behind: its confidence says the fill is a guess); none is a silent miss. Each
    is one obstacle that holds still: sgbm carries the floor and the wall around them into them, and
    had split them into 15 obstacles for 9 (6 pieces) wobbling 22 cm, until what it carried in
    (its flat mask) counted as unmeasured where plain faces are looked for."""
    from cores.matching.config import MatcherConfig

    data = {"blank-faces": E.render_scenario("blank-faces", matcher=MatcherConfig(method=method))}
    s = E.evaluate(["blank-faces"], ["layers"], data=data)["scenarios"]["blank-faces"]["layers"]
    for name in ("cabinet", "panel"):
        t = s.per_truth[name]
        assert t["matched"] == t["seen"] == 3, (method, name, t)
    assert s.silent_misses == 0 and s.floor_fp == 0 and s.wall_fp == 0
    assert s.split_fp == 0 and s.base_wobble_p95_m < 0.05, (method, s.split_fp, s.base_wobble_p95_m)
    # where they stand: upright over their foot (the camera looks 15 deg down; at the foot's disparity all
    # the way up they leaned back, 16-18 cm off)
    assert s.pos_err_med_m < 0.08, (method, s.pos_err_med_m)


@pytest.mark.parametrize("height_m,pitch_deg", [(0.5, 5.0), (0.7, 8.0)])
def test_the_scenes_seen_from_a_ballbot_height_camera(height_m, pitch_deg):
    """The scenes were made for their own mounts (most 1 m high, 15 deg down). Seen from a camera as
    low as a ballbot's (0.5-0.7 m, 5-8 deg down: the plain cabinet is taller than the camera, the floor
    between two people's legs shows under their torsos), with bm: every obstacle in every frame, none
    missed silently, no free cell under anything."""
    import dataclasses

    from sim import scene as S

    for name in ("two-boxes", "occlusion", "touching", "toolbox", "people-side", "person-walking",
                 "blank-faces", "low-faces"):
        scene = dataclasses.replace(S.Scene.builtin(name), camera_height_m=height_m, camera_pitch_deg=pitch_deg)
        s = E.score_method(E.render_scenario(scene, frames=4), "layers")
        assert s.matched == s.truths and s.silent_misses == 0 and s.free_under == 0, (name, s.to_dict())


@pytest.mark.parametrize("method", ["bm", "dense"])
def test_a_plain_cabinet_cut_by_the_top_of_the_view_is_placed_by_its_whole_face(method):
    """From 1.2 m up, 20 deg down, the blank-faces cabinet (1.4 m, plain) is cut by the image's top. bm
    finds it by its outline (blank._outlined): it measures the side's vertical edge, whose disparity
    grows by 8 px up the column (the camera pitches). Held to the stop's disparity the edge ended a
    third of the way up, the face with it, and the cabinet was listed 0.33 m below its centre, outside
    the match: in no list (scored) in 3 of 3 frames. dense finds it by its top edges (rule 2), its
    doubted matches up the face, held to the stop's disparity too: in pieces, in no list (scored) in 3
    of 3 frames. Both are now held to an upright face through the stop as well."""
    import dataclasses

    from cores.matching.config import MatcherConfig
    from sim import scene as S

    scene = dataclasses.replace(S.Scene.builtin("blank-faces"), camera_height_m=1.2, camera_pitch_deg=20.0)
    s = E.score_method(E.render_scenario(scene, matcher=MatcherConfig(method=method)), "layers")
    t = s.per_truth["cabinet"]
    assert t["matched"] == t["seen"] == 3 and s.free_under == 0, (t, s.to_dict())


def test_a_plain_crate_seen_from_a_ballbot_height_camera_is_an_obstacle_with_dense():
    """From a camera 0.5 m high the low-faces crate (0.35 m) is seen nearly edge-on. dense's doubted
    matches on its plain face stray 8-9 px off its depth in most columns (streaks along its paths),
    and some pass for top edges (rule 2): those columns were left out of the run of floor stops the
    outline's side (_outlined) is looked for beside, which broke the run into pieces, each narrower
    than a face, and the crate was in no list in 3 of 4 frames, unflagged. The run now spans every
    stop column at one depth; the columns rule 2 took keep their own face."""
    import dataclasses

    from cores.matching.config import MatcherConfig
    from sim import scene as S

    scene = dataclasses.replace(S.Scene.builtin("low-faces"), camera_height_m=0.5, camera_pitch_deg=5.0)
    s = E.score_method(E.render_scenario(scene, frames=4, matcher=MatcherConfig(method="dense")), "layers")
    t = s.per_truth["crate"]
    assert t["matched"] == t["seen"] == 4 and s.silent_misses == 0 and s.free_under == 0, (t, s.to_dict())


def test_a_box_cut_by_the_blind_band_from_a_ballbot_height_camera_is_listed_truncated():
    """From 0.5 m up, 12 deg down, bm (64 px) sees 4 cm of the border scene's box right of its blind
    band: a region too small in area for an obstacle's face, dropped, and the box 2.2 m away was in no
    list of 3, the list saying it looked there. A region cut by a side of the view shows only part of
    its face; as tall as an obstacle, it is listed, truncated."""
    import dataclasses

    from sim import scene as S

    scene = dataclasses.replace(S.Scene.builtin("border"), camera_height_m=0.5, camera_pitch_deg=12.0)
    s = E.score_method(E.render_scenario(scene), "layers")
    assert s.per_truth["box"]["matched"] == s.per_truth["box"]["seen"] == 3, s.to_dict()
    assert s.border_flagged == s.border_truths == 3 and s.silent_misses == 0 and s.detections == 3, s.to_dict()


def test_two_people_one_behind_the_other_seen_from_a_pitched_camera_are_two_obstacles():
    """people-queue from 0.5 m up, 12 deg down, bm: the far pair (0.55 m apart, 4.4 and 4.9 m away) was
    one obstacle in every frame, the person behind in no list and nothing said: along the optical
    axis of a pitched camera each upright person spans a range of depths, and the two ranges met.
    The depth split looks along the ground too (depth_split.ground_disparity)."""
    import dataclasses

    from sim import scene as S

    scene = dataclasses.replace(S.Scene.builtin("people-queue"), camera_height_m=0.5, camera_pitch_deg=12.0)
    s = E.score_method(E.render_scenario(scene), "layers")
    assert s.matched == s.truths == 12 and s.silent_misses == 0 and s.free_under == 0, s.to_dict()


@pytest.mark.parametrize("method", ["bm", "sgbm"])
def test_with_match_band_a_person_in_the_blind_band_of_a_ballbot_height_camera_is_listed(method):
    """From 0.5 m up, 5 deg down, people-border's nearest person stands mostly in the band bm and sgbm
    leave unmatched (64 px): what is measured right of it is too small to list, and they were in no
    list of 3, the list saying it looked there. With match_band the band is matched where the partner
    is in view, and the person is in every list."""
    import dataclasses

    from cores.matching.config import MatcherConfig
    from sim import scene as S

    scene = dataclasses.replace(S.Scene.builtin("people-border"), camera_height_m=0.5, camera_pitch_deg=5.0)
    s = E.score_method(E.render_scenario(scene, matcher=MatcherConfig(method=method, match_band=True)), "layers")
    assert s.matched == s.truths == 9 and s.silent_misses == 0 and s.free_under == 0, s.to_dict()


def test_with_match_band_what_the_left_side_of_the_view_cuts_is_flagged_truncated():
    """bm matching its band measures its first pixel at disparity d at x = d + 7 (half its 15 px
    window: a match whose partner's window reaches past the right image's edge is dropped), beyond
    the reach side_cut allowed: people-border's person cut by the left side, its arm 62 px from the
    image's edge at 54 px of disparity, was listed unflagged in every frame, its footprint partial
    and nothing said (14 of 26 things cut there in the 15 scenes)."""
    from cores.matching.config import MatcherConfig

    s = E.score_method(E.render_scenario("people-border", matcher=MatcherConfig(method="bm", match_band=True)),
                       "layers")
    assert s.border_truths == 6 and s.border_flagged == 6, s.to_dict()


@pytest.mark.parametrize("band", [False, True])
def test_a_sliver_cut_by_the_side_of_the_view_joins_the_rest_of_its_person(band):
    """people-border, bm: the person cut by the left side shows a sliver of a leg beside the edge of
    what the matcher sees, a column or two of the working grid whose thinner stretches the median filter
    takes, so the leg's piece and the arm's came apart up the view (0.19 m) and were two obstacles in
    every frame: with the band matched at the scene's mount, without it from 1.2 m / 20 deg."""
    import dataclasses

    from cores.matching.config import MatcherConfig
    from sim import scene as S

    scene = S.Scene.builtin("people-border")
    if not band:
        scene = dataclasses.replace(scene, camera_height_m=1.2, camera_pitch_deg=20.0)
    s = E.score_method(E.render_scenario(scene, matcher=MatcherConfig(method="bm", match_band=band)), "layers")
    assert s.matched == s.truths and s.precision == 1.0 and s.border_flagged == s.border_truths, s.to_dict()


def test_the_shadow_beside_a_near_box_at_the_edge_of_the_view_is_no_face():
    """two-boxes from 0.5 m up, 12 deg down, bm matching its left band: left of box-a (1.7 m away,
    52 px from the image's left edge) the right camera sees neither the wall nor the floor beyond
    2.3 m, hidden behind the box, so the floor seen ends there with nothing measured above it; and
    left of that nothing at 2.3 m has a partner in the right image (x < d). The run of blank-face
    columns between was taken for a face the edge of the view cuts, kept however narrow: a plain face
    2.3 m away in every list (7 wall false positives in 3 frames)."""
    import dataclasses

    from cores.matching.config import MatcherConfig
    from sim import scene as S

    scene = dataclasses.replace(S.Scene.builtin("two-boxes"), camera_height_m=0.5, camera_pitch_deg=12.0)
    s = E.score_method(E.render_scenario(scene, matcher=MatcherConfig(method="bm", match_band=True)), "layers")
    assert s.matched == s.truths == 6 and s.wall_fp == s.floor_fp == s.split_fp == 0, s.to_dict()


PLAIN_WALL = """name: plain-wall
description: A plain wall across the whole view 2 m ahead.
camera_height_m: 1.0
camera_pitch_deg: 15.0
wall_distance_m: 6.0
noise_sigma: 1.5
objects:
  - {name: wall, kind: panel, size: [5.0, 2.5, 0.05], position: [2.0, 0.0], blank: true}
"""


@pytest.mark.parametrize("method", ["bm", "sgbm", "dense"])
def test_a_plain_wall_across_the_view_is_in_every_list(method, tmp_path):
    """Nothing to match in it but the sensor's noise: sgbm makes blobs of that noise at 1.2-2.9 m, and
    before the blank-face rule read only what stands where the floor stops, the wall was in 1 list of
    6, and the others said nothing."""
    from common.settings import MountSettings
    from cores.matching.config import MatcherConfig
    from cores.segmentation.builder import ObstacleBuilder
    from cores.segmentation.settings import SegmenterSettings

    scene = tmp_path / "plain-wall.yaml"
    scene.write_text(PLAIN_WALL)
    data = E.render_scenario(str(scene), frames=6, matcher=MatcherConfig(method=method))
    m = data.mount
    builder = ObstacleBuilder(SegmenterSettings(), MountSettings(height_m=m.height_m, pitch_deg=m.pitch_deg,
                                                                 roll_deg=m.roll_deg))
    for k, fr in enumerate(data.frames):
        o = builder.process(fr.disparity, data.model, t_s=fr.t_s, seq=k, stamp_ns=k, confidence=fr.confidence,
                            search=fr.search, flat=fr.flat).obstacles
        wall = [ob for ob in o.obstacles if 1.8 < ob.position_m[2] < 2.6]
        assert o.degraded == [] and sum(ob.bbox_px[2] - ob.bbox_px[0] for ob in wall) > 200, \
            (method, k, [(ob.position_m, ob.bbox_px) for ob in o.obstacles], o.degraded)


# --- free space under what stands -------------------------------------------------------------------

def _grid(cells: np.ndarray, res: float = 0.1, origin=(0.0, -1.0)):
    from common.messages import FreeSpace

    return FreeSpace(robot_id="t", seq=0, stamp_ns=0, publish_ns=0, resolution_m=res, width=cells.shape[1],
                     height=cells.shape[0], origin_m=origin, cells=cells.astype(np.int8).tobytes())


def test_footprints_are_each_part_s_outline_on_the_ground_in_the_base_frame():
    import sim as S
    from cores import camera
    from cores.pipeline import Pipeline

    rig = camera.load_raw_rig("lifecam-studio")
    world = S.SyntheticWorld(S.Scene.builtin("two-boxes"), rig, Pipeline(rig).rectifier.rectification, seed=0)
    polys = world.footprints(0.0, E.STANDS_FROM_M, E.STANDS_TO_M)
    for box, outline in zip(world.scene.boxes, polys):
        (p,) = outline
        w, _, d = box.size
        assert np.allclose(p.mean(0), box.center[:2], atol=1e-9)
        sides = sorted(np.linalg.norm(np.roll(p, -1, 0) - p, axis=1).round(9))
        assert np.allclose(sides, sorted([w, w, d, d]))
    # a part wholly above the band (over the robot) stands in nobody's way
    assert world.footprints(0.0, 5.0, 6.0) == [[], []]


def test_free_under_counts_a_free_cell_inside_what_stands_and_not_one_its_outline_only_crosses():
    cells = np.full((20, 30), -1)  # 0.1 m cells from (0, -1): cell (row, col) is x 0.1 col, y -1 + 0.1 row
    box = [np.array([[1.0, -0.5], [1.5, -0.5], [1.5, -0.03], [1.0, -0.03]])]  # x 1.0-1.5, y -0.5 to -0.03
    assert E._free_under(_grid(cells), [box]) == 0  # nothing free
    inside = cells.copy()
    inside[7, 12] = 0  # x 1.2-1.3, y -0.3 to -0.2: wholly inside
    assert E._free_under(_grid(inside), [box]) == 1
    assert E._free_under(_grid(inside), [box, box]) == 2  # per truth
    assert E._free_under(_grid(inside), [[]]) == 0
    occupied = cells.copy()
    occupied[7, 12] = 100
    assert E._free_under(_grid(occupied), [box]) == 0
    assert E._free_under(None, [box]) == 0
    crossed = cells.copy()
    # y -0.1 to 0: 70 % of it under the box, but only 20 % deeper than the half cell (5 cm) within which floor
    # seen right at a face's foot may stray into it
    crossed[9, 12] = 0
    crossed[10, 12] = crossed[7, 15] = crossed[4, 9] = 0  # beside the box
    assert E._free_under(_grid(crossed), [box]) == 0


def test_a_rolled_camera_sees_no_free_floor_under_a_table_top_beside_the_column(monkeypatch):
    """A leaning ballbot's camera rolls: image columns are no longer verticals, and the floor under a
    table top's edge, whose vertical runs through the top in the next columns, was free (the sway,
    camera rolled 9 deg: up to 11 cm under the top)."""
    import sim as S
    from cores.segmentation import freespace

    legs = [{"name": f"leg-{k}", "offset": [x, y, 0.355], "size": [0.05, 0.71, 0.05]}
            for k, x, y in (("fl", -0.26, 0.36), ("fr", -0.26, -0.36), ("bl", 0.26, 0.36), ("br", 0.26, -0.36))]
    table = {"name": "table", "kind": "table", "position": [2.7, -0.75], "yaw_deg": 10, "texture_seed": 83,
             "parts": [{"name": "top", "offset": [0.0, 0.0, 0.73], "size": [0.8, 0.04, 0.6]},
                       {"name": "apron-f", "offset": [-0.27, 0.0, 0.65], "size": [0.72, 0.12, 0.03]},
                       {"name": "apron-l", "offset": [0.0, 0.37, 0.65], "size": [0.03, 0.12, 0.52]}, *legs]}
    scene = S.Scene.from_dict({
        "name": "rolled-table", "camera_height_m": 0.9, "camera_pitch_deg": 3.25, "wall_distance_m": 7.0,
        "noise_sigma": 1.5, "objects": [table],
        # the sway's frame 13: the robot 0.22 m on, turned 2.6 deg, the camera rolled 9.3 deg (held)
        "camera_motion": {"start": [0.22, 0.0, 2.6],
                          "roll_deg": [{"amplitude": 9.3, "frequency_hz": 0.001, "phase_deg": 270}]}})
    data = E.render_scenario(scene, frames=1)
    s = E.score_method(data, "layers")
    assert s.recall == 1.0 and s.free_under == 0, s.to_dict()
    # the columns alone, as before: the floor under the top's edge is free
    monkeypatch.setattr(freespace, "vertical_point", _columns)
    monkeypatch.setattr(freespace, "spread_sides", _unspread)
    assert E.score_method(data, "layers").free_under == 1


def _columns(floor, model, step):
    """vertical_point of a camera that neither rolls nor pitches: verticals are image columns."""
    return np.array([0.0, 1.0, 0.0])


def _unspread(stand_d, reach, narrow=0.0):
    """freespace.spread_sides before it: a thing standing stops its own columns only."""
    return stand_d


def test_a_pitched_camera_sees_no_free_floor_under_a_table_top_at_the_image_side(monkeypatch):
    """A camera pitched 12 deg down sees verticals converge below the image: at its side they lean
    by several degrees, and the floor under a table top's edge, whose vertical runs through the top
    in the next columns out, was free."""
    import sim as S
    from cores.segmentation import freespace

    legs = [{"name": f"leg-{k}", "offset": [x, y, 0.355], "size": [0.05, 0.71, 0.05]}
            for k, x, y in (("fl", -0.26, 0.36), ("fr", -0.26, -0.36), ("bl", 0.26, 0.36), ("br", 0.26, -0.36))]
    table = {"name": "table", "kind": "table", "position": [1.6, -1.0], "texture_seed": 83,
             "parts": [{"name": "top", "offset": [0.0, 0.0, 0.73], "size": [0.8, 0.04, 0.6]},
                       {"name": "apron-f", "offset": [-0.27, 0.0, 0.65], "size": [0.72, 0.12, 0.03]}, *legs]}
    scene = S.Scene.from_dict({"name": "pitched-table", "camera_height_m": 0.9, "camera_pitch_deg": 12.0,
                               "wall_distance_m": 7.0, "noise_sigma": 1.5, "objects": [table]})
    data = E.render_scenario(scene, frames=1)
    s = E.score_method(data, "layers")
    assert s.recall == 1.0 and s.free_under == 0, s.to_dict()
    monkeypatch.setattr(freespace, "vertical_point", _columns)  # the columns alone, as before
    monkeypatch.setattr(freespace, "spread_sides", _unspread)
    assert E.score_method(data, "layers").free_under == 1


def test_pairs_sent_as_jpeg_at_the_least_quality_allowed_list_what_stands(tmp_path):
    """Pairs through capture's codec as JPEG at MIN_JPEG_QUALITY list low-faces' plain crate and cabinet
    with no free space under them; at 80 and 75 (the recorder's default before) the crate left a list
    and the free space reached under it, unflagged: block artefacts are texture the matcher trusts.
    capture, the dispatcher's transport and the recorder refuse a lower quality by name."""
    from common.codec import MIN_JPEG_QUALITY
    from common.errors import ConfigError
    from common.settings import load_settings
    from services.capture.settings import CaptureSettings
    from services.disparity.main import DisparitySettings
    from services.recorder.main import RecordSettings

    for q, holds in ((MIN_JPEG_QUALITY, True), (80, False)):
        s = E.score_method(E.render_scenario("low-faces", wire=("jpeg", q)), "layers")
        assert (s.silent_misses == 0 and s.free_under == 0) == holds, (q, s.to_dict())
    for cls in (CaptureSettings, DisparitySettings, RecordSettings):
        cfg = tmp_path / f"{cls.section}.yaml"
        cfg.write_text(f"{cls.section}:\n  jpeg_quality: 80\n")
        with pytest.raises(ConfigError, match=f"{cls.section}.jpeg_quality: .*greater than or equal to 85"):
            load_settings(cls, str(cfg))
