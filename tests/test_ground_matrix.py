"""The ground from any start, on the real recordings in ../shared/data/real (issue 20, item 6):
{karlsruhe street, euroc room} x {bm, sgbm, dense} x {range 5, 10, 20, 30, 40 m} x {no mount, pitch +-8 deg
off, height +-30 % off, and item 1's limits: roll 15 deg off, pitch 15 deg and height 50 % off at
once}. In every cell, from the 5th frame on, the segmenter's ground agrees with an independent
estimate within 0.1 m and 2 deg, at most 5 % of the obstacles are flat on the road, and in the room
no obstacle box reaches down onto the floor with the tape strips and the mat.

The independent estimate is real_eval's RoadProfile: a robust line in the v-disparity histogram of
the lower half of the image, no plane fit, no roll, no temporal state, no prior.
- The ground is compared with the profile of the cell's own map gated where the segmenter looks
  for the floor: its vision range, or out to where the rig measures (16 px of disparity: 23 m on
  the street) when that is farther. The ground must agree with the data the segmenter was given (a
  real road is not a plane: the road within 10 m and out to 30 m differ by a few centimetres and a
  degree). The difference to the profile of the sgbm map (the road itself) is printed beside it.
- Flatness is judged against the profile of the semi-global (sgbm) map of the same pair, ungated,
  as eval --real does: on block matching's own map the far road comes out a degree or more too
  steep, which at 25 m misplaces it by half a metre and would call kerbs and bollards flat. The room's
  camera looks ~22 deg down, so its floor fills the lower half and the same line is the floor (its
  figures agree with the fit of `mount estimate`: see test_real_eval). The mount offsets are taken
  from the recording's own road profile (median over the frames), the true mount as far as the data
  tell.

Each method's maps are computed once per recording (the matcher's search follows the calibration:
num_disparities auto; the vision range only gates the segmenter), and shared by the 35 cells.
Set BALLBOT_MATRIX_REPORT=FILE to write every cell's figures as JSON."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
from test_real_eval import EUROC, KARLSRUHE

from cores.segmentation.settings import FAR_DISPARITY_PX
from evaluation import real as R
from evaluation import recordings, road_profile

pytestmark = pytest.mark.slow

FRAMES = 10  # per cell; the ground must agree from frame index SETTLE on
SETTLE = 4
METHODS = ("bm", "sgbm", "dense")
REFERENCE = "sgbm"  # the matcher whose map judges flatness (see the module doc)
RANGES = (5.0, 10.0, 20.0, 30.0, 40.0)
# the matrix of item 6, then item 1's limits: a prior off by 15 deg of roll, and by 15 deg of pitch
# and 50 % of height at once
MOUNTS = ("none", "pitch+8", "pitch-8", "height+30%", "height-30%", "roll+15", "pitch-15,h+50%")
FLOOR_ROW = 320  # room: rows below this are the floor with the tape strips and the mat (test_real_eval)


def _maps(root, method: str, **matcher):
    """(recording, model, the matcher settings resolved, [(disparity px float with NaN, confidence or
    None)]) of the first FRAMES pairs, rectified and matched as the pipeline does (matcher: more
    MatcherConfig settings)."""
    from common.files import read_image
    from cores.matching.config import MatcherConfig
    from cores.pipeline import Pipeline

    rec = recordings.open_recording(root)
    pipe = Pipeline(rec.calibration, MatcherConfig(method=method, num_disparities="auto", **matcher))
    out, cfg = [], None
    for lp, rp in rec.pairs[:FRAMES]:
        stage = pipe.match(*pipe.rectify(read_image(lp), read_image(rp)))
        out.append((stage.disparity_px(), stage.match.confidence))
        cfg = stage.config
    return rec, pipe.model, cfg, out


def _mount(kind: str, height: float, pitch: float) -> dict:
    return {"none": {}, "pitch+8": {"height_m": height, "pitch_deg": pitch + 8},
            "pitch-8": {"height_m": height, "pitch_deg": pitch - 8},
            "height+30%": {"height_m": height * 1.3, "pitch_deg": pitch},
            "height-30%": {"height_m": height * 0.7, "pitch_deg": pitch},
            "roll+15": {"height_m": height, "pitch_deg": pitch, "roll_deg": 15.0},
            "pitch-15,h+50%": {"height_m": height * 1.5, "pitch_deg": pitch - 15}}[kind]


def _cells(name: str, root, room: bool) -> list[dict]:
    from common.settings import MountSettings
    from cores.segmentation.builder import ObstacleBuilder
    from cores.segmentation.settings import SegmenterSettings

    rows = []
    computed = {method: _maps(root, method) for method in METHODS}
    # the road of each frame from the semi-global map of the pair: what flatness is judged by
    _, model, _, ref_maps = computed[REFERENCE]
    fB = model.focal_px * model.baseline_m
    full = [road_profile.fit_road_profile(d, model) for d, _ in ref_maps]  # judges flatness, as eval --real does
    assert all(r is not None for r in full), f"{name}: no road profile in some frame"
    h0 = float(np.median([r.height_m for r in full]))
    p0 = float(np.median([r.pitch_deg for r in full]))
    for method in METHODS:
        rec, model, mcfg, maps = computed[method]
        for rng in RANGES:
            # the segmenter fits the ground out to where the rig measures, however short the range
            gate = fB / max(rng, fB / FAR_DISPARITY_PX)
            gated = [road_profile.fit_road_profile(np.where(d >= gate, d, np.nan), model) for d, _ in maps]
            truth = [road_profile.fit_road_profile(np.where(d >= gate, d, np.nan), model) for d, _ in ref_maps]
            for kind in MOUNTS:
                settings = SegmenterSettings(max_range_m=rng)
                builder = ObstacleBuilder(settings, MountSettings(**_mount(kind, h0, p0)))
                dh, dp, flat, judged, on_floor, sources = [], [], 0, 0, [], []
                dh_ref, dp_ref = [], []  # against the sgbm map's road: shown, not judged
                for k, (d, conf) in enumerate(maps):
                    t = rec.stamps_s[k]
                    lst = builder.process(d, model, t_s=t, seq=k, stamp_ns=int(t * 1e9), confidence=conf,
                                          search=(mcfg.min_disparity, mcfg.num_disparities)).obstacles
                    g, ref = lst.ground, gated[k]
                    sources.append(g.source)
                    if k >= SETTLE:
                        dh.append(g.height_m - ref.height_m if ref is not None else float("nan"))
                        dp.append(g.pitch_deg - ref.pitch_deg if ref is not None else float("nan"))
                        if truth[k] is not None:
                            dh_ref.append(g.height_m - truth[k].height_m)
                            dp_ref.append(g.pitch_deg - truth[k].pitch_deg)
                    for o in lst.obstacles:
                        h95 = road_profile.obstacle_height_p95(d, o.bbox_px, o.disparity_px, full[k])
                        if h95 is not None:
                            judged += 1
                            flat += h95 < R.FLAT_HEIGHT_M
                        if room and o.bbox_px[3] >= FLOOR_ROW:
                            on_floor.append((k, o.bbox_px))
                worst_h = float(np.max(np.abs(dh)))
                worst_p = float(np.max(np.abs(dp)))
                flat_fraction = flat / judged if judged else 0.0
                ok = worst_h <= 0.1 and worst_p <= 2.0 and flat_fraction <= 0.05 and not on_floor
                rows.append({"recording": name, "method": method, "range_m": rng, "mount": kind,
                             "num_disparities": mcfg.num_disparities, "height_err_m": worst_h,
                             "pitch_err_deg": worst_p, "height_err_vs_sgbm_m": float(np.max(np.abs(dh_ref))),
                             "pitch_err_vs_sgbm_deg": float(np.max(np.abs(dp_ref))), "flat": flat, "judged": judged,
                             "flat_fraction": flat_fraction, "boxes_on_floor": on_floor[:3],
                             "sources": sorted(set(sources)), "ok": ok})
    return rows


def _check(rows: list[dict]) -> None:
    lines = [f"{r['recording']:9} {r['method']:5} {r['range_m']:4.0f} m {r['mount']:14} "
             f"dh {r['height_err_m']:.3f} m dp {r['pitch_err_deg']:.2f} deg "
             f"(vs sgbm's road {r['height_err_vs_sgbm_m']:.3f} m {r['pitch_err_vs_sgbm_deg']:.2f} deg) "
             f"flat {r['flat']}/{r['judged']} ({r['flat_fraction']:.1%})"
             f"{' boxes on the floor ' + str(r['boxes_on_floor']) if r['boxes_on_floor'] else ''}"
             f" {'ok' if r['ok'] else 'FAIL'}" for r in rows]
    print("\n" + "\n".join(lines))
    out = os.environ.get("BALLBOT_MATRIX_REPORT")
    if out:
        with open(out, "a") as fh:
            fh.write(json.dumps(rows) + "\n")
    bad = [line for line, r in zip(lines, rows) if not r["ok"]]
    assert not bad, f"{len(bad)} of {len(rows)} cells fail:\n" + "\n".join(bad)


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(),
                    reason=f"real recording {KARLSRUHE} absent (see DESIGN.md: ../shared/data/real)")
def test_ground_matrix_on_the_street():
    _check(_cells("karlsruhe", KARLSRUHE, room=False))


@pytest.mark.skipif(not (EUROC / "cam0_sensor.yaml").exists(),
                    reason=f"real recording {EUROC} absent (see DESIGN.md: ../shared/data/real)")
def test_ground_matrix_in_the_room():
    _check(_cells("euroc", EUROC, room=True))


# Matcher settings nobody tuned, each with the shortest range at which its ground had gone wrong
# while the lists trusted it (the ground was fitted on the floor inside the vision range)
UNTUNED = (("bm", {"block_size": 31}, 10.0), ("bm", {"block_size": 21}, 10.0), ("bm", {"block_size": 9}, 7.0),
           ("dense", {}, 7.0))


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(),
                    reason=f"real recording {KARLSRUHE} absent (see DESIGN.md: ../shared/data/real)")
def test_untuned_matchers_at_a_short_range_give_the_road_or_say_they_cannot():
    """Inside 7-10 m on the street, block matching with a block other than the default sees a snow
    bank and the parking stripes but little of the smooth road, and dense a short strip: the ground
    fitted on the floor inside the range was 0.2-0.8 m and 2-7 deg off the road (bm with 31 px
    blocks at 10 m: up to 2.4 m and 13 deg against the road's 1.6 m and 5.5 deg), trusted. The ground is
    now fitted out to where the rig measures whatever the range: it is the one the same maps give
    with the range out to there, and on every list from the 5th frame it is within 0.15 m and 2 deg
    of the semi-global map's road profile or the list says ground-uncertain."""
    from cores.segmentation.builder import ObstacleBuilder
    from cores.segmentation.settings import SegmenterSettings

    rec, model, _, ref = _maps(KARLSRUHE, REFERENCE)
    road = [road_profile.fit_road_profile(d, model) for d, _ in ref]
    far = model.focal_px * model.baseline_m / FAR_DISPARITY_PX
    bad = []
    for method, matcher, rng in UNTUNED:
        rec, model, mcfg, maps = _maps(KARLSRUHE, method, **matcher)
        short = ObstacleBuilder(SegmenterSettings(max_range_m=rng))
        full = ObstacleBuilder(SegmenterSettings(max_range_m=far))
        for k, (d, conf) in enumerate(maps):
            kw = dict(t_s=rec.stamps_s[k], seq=k, stamp_ns=k, confidence=conf,
                      search=(mcfg.min_disparity, mcfg.num_disparities))
            lst, wide = short.process(d, model, **kw).obstacles, full.process(d, model, **kw).obstacles
            g = lst.ground
            assert (g.height_m, g.pitch_deg, g.roll_deg) == (wide.ground.height_m, wide.ground.pitch_deg,
                                                             wide.ground.roll_deg), (method, matcher, rng, k)
            off = (g.height_m - road[k].height_m, g.pitch_deg - road[k].pitch_deg)
            if k >= SETTLE and (abs(off[0]) > 0.15 or abs(off[1]) > 2.0) and "ground-uncertain" not in lst.degraded:
                bad.append((method, matcher, rng, k, round(off[0], 2), round(off[1], 1), lst.degraded))
    assert not bad, bad
