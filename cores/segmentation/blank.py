"""Blank faces: a plain wall, door or cabinet in front of the robot, with nothing inside it to match.

Block matching measures a surface only where its image has texture. A painted cabinet 2 m ahead
leaves no disparity inside its outline; its sides, against what is behind, give a few pixels or
none. Without this step the list was empty or held a sliver, unflagged, with every matcher (dense
fills the blank from its farther surroundings). What does show is the floor: seen up to the face's
foot and not beyond.

Along each image column (a ray on the ground) the floor is seen out to a farthest point, Z_f. The
column holds a blank face standing at Z_f when
  - Z_f is short of the vision range (0.95 of it) and of near_field_m,
  - nothing measured stands in the column at Z_f or within BEHIND_M beyond it (then that is what
    stops the floor: a car's dark underside below its body, a person's shadowed feet; what stands
    nearer, with floor seen beyond it, does not), and
  - the image above the floor's last row is unmeasured (UNMEASURED of it) all the way up past the
    horizon, to 0.1 m above the camera's height at Z_f. Unmeasured floor cannot reach that high:
    however far it went, it would stay below the horizon. Something stands at Z_f, as tall as the
    camera or taller.
Runs of such columns at least MIN_WIDTH_M wide at their median Z_f become standing pixels of an
upright face over the floor at Z_f (_upright: for a camera that pitches or rolls, not one disparity
up the column), up to robot_height_m above the floor: the obstacle is grouped, filtered and tracked
as any other, and its confidence (the share of its pixels the matcher measured) says how little of
it was seen.

A face lower than the camera (a plain box, a bench, a stair riser) leaves the floor beyond it in
view above its top, so the stretch above its foot is not unmeasured up past the horizon. Along each
column, where the floor seen stops for as many rows as a face min_height_m tall standing there would
cover, the stop may be such a face's foot (each of the column's lowest three such stops: a patch of
floor the matcher missed, a dark rug, lies below the foot of a face behind it as a stop of its own,
and looked for at the lowest alone, a plain box 3 m away behind a rug was in no list, unflagged).
What tells it from a plain patch of floor is what was
measured above the stop: mostly (FACE_SHARE) within CAP_PX of the stop's disparity (or of an upright
face's through it: a pitched camera sees a face's top edge nearer than its foot), up to a top edge
at that depth, nearer it than the floor's at its row and min_height_m or more above the floor. A
plain patch of floor ends in floor farther away, or too close above its near edge to be that tall.
Such a column holds a face from the stop up to that edge, whatever stands farther. What was
measured includes what the matcher doubted (confidence MEASURED or more, below the segmenter's
min_confidence): dense gives every depth edge a low confidence, and so set aside the very pixels
that show the face; on the low-faces scene it missed the plain cabinet in 2 of 3 frames, silently.
Block matching measures no such top edge where the face stands against texture (a cabinet before a
wall: the edge takes the wall's depth) but measures its side; _outlined takes a run of stops at one
depth beside such a measured side for one face. A face whose foot is below the image (nearer than
the floor at its bottom edge) leaves no stop: _below_image takes a plain stretch from the bottom edge
up to the floor seen again, beside a side measured down to that edge, for one face. A face of which
nothing at its depth was measured is not found. Farther than
near_field_m a road fading into the distance under a blank sky looks the same as a face:
on the street recording (karlsruhe, bm, 40 frames) 11 such stretches at 10-17 m, none nearer; on
the room recording and every synthetic scene, none.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cores import camera
from cores.matching.disparity import MEASURED_CONFIDENCE
from cores.segmentation import freespace, stats
from cores.segmentation.mount import FloorPlane

BEHIND_M = 1.0  # something standing measured this close beyond the floor's end explains it
UNMEASURED = 0.8  # share of the stretch above the floor's end that must be unmeasured
ABOVE_HORIZON_M = 0.1  # the stretch reaches this far above the camera's height at Z_f
MIN_WIDTH_M = 0.3  # narrower: a gap between two things, a pole's dark side, not a face to list
# a low face's pixels are this close to the disparity at its foot, px: a doubted match's noise (dense on
# the plain faces of the low-faces scene: 1.3-1.6 px half the interquartile range), whatever the depth
CAP_PX = 3.0
GAP_COLS = 2  # working columns
# where a near thing's edge lands in the right image, the floor this close to it (full-resolution px) is
# as good as hidden: the matcher's window there straddles the thing's edge
SHADOW_TOL_PX = 4.0
# rule 3's measured side may end this far short of the image's bottom edge and of the face's top edge (or
# min_height_m, if more): where the matcher loses a side has nothing to do with how low an obstacle may be
# (dense ended the low-faces crate's side 29 rows, 0.14 m, short of the bottom edge, bm 0.1-0.2 m short of
# its top edge; with min_height_m 0.1 the crate was in no list in 1 (bm) or 2 (dense) of 3 frames, unflagged)
SIDE_SHORT_M = 0.2
FACE_SHARE = 0.6  # share of what was measured between a low face's foot and its top edge that is at its depth
# confidence from which a pixel the segmenter sets aside still counts as measured (a top edge): dense
# gives MEASURED_CONFIDENCE..255 to what SGBM measured and less to what its fill spread
MEASURED = MEASURED_CONFIDENCE


@dataclass
class BlankFaces:
    """Pixels taken for blank faces on the working grid, and their disparity (from the floor's at each
    face's foot: upright over it for rule 1's, that disparity up the column for the others')."""

    mask: np.ndarray  # (h, w) bool
    disparity: np.ndarray  # (h, w) float32, valid where mask


def find(dm: np.ndarray, df: np.ndarray, seen_floor: np.ndarray, standing: np.ndarray, floor: FloorPlane,
         model: camera.RectifiedModel, step: int, range_m: float, within_m: float,
         robot_height_m: float, min_height_m: float = 0.2, doubtful: np.ndarray | None = None,
         gaps: freespace.Gaps | None = None, bottom_start: np.ndarray | None = None) -> BlankFaces | None:
    """dm: working disparity (0 = unmeasured, not range-gated); df: the floor's disparity on the
    working grid; seen_floor / standing: the floor and standing pixels in range (bool, working grid);
    doubtful: the disparity of pixels measured but set aside for their low confidence (0 elsewhere);
    gaps: freespace.floor_gaps of seen_floor (None: computed here); bottom_start: per column, where the
    stretch without floor from the bottom edge starts (-1: none) counting the floor seen beyond the
    vision range too (None: gaps'), rule 3's: how far up a plain stretch from the bottom edge goes
    (the crate 1.6 m ahead on low-faces hides the floor out to 3.1 m).
    -> the blank faces' pixels, or None."""
    h, w = dm.shape
    if floor.b <= 0 or within_m <= 0:
        return None
    fB = model.focal_px * model.baseline_m
    normal, _ = floor.normal_height(model.focal_px, model.cx, model.cy, model.baseline_m)  # for _upright
    limit = min(0.95 * range_m, within_m)
    has_floor = seen_floor.any(0)
    top_floor = np.argmax(seen_floor, axis=0)  # the topmost (farthest) floor row seen in each column
    cols = np.arange(w)
    d_end = np.where(has_floor, df[top_floor, cols], 0.0).astype(np.float64)
    with np.errstate(divide="ignore"):
        z_end = np.where(d_end > 0, fB / np.maximum(d_end, 1e-9), np.inf)
    near = has_floor & (z_end < limit)
    faces = np.zeros(w, bool)
    face_top = np.zeros(w, np.int64)  # per face column, the row its face ends at (the top edge, or robot height)
    shift = np.zeros(w)  # per face column, its disparity less the floor's at its foot (a measured side's)
    # 1. taller than the camera: unmeasured from the floor's end up past the horizon
    cand = near & ~_explained(near, d_end, z_end, dm, standing, fB)
    # the horizon's working row in each column (the floor's disparity 0) and 0.1 m above the camera there
    u = cols.astype(np.float64) * step
    v_h = (-floor.c - floor.a * u) / floor.b / step
    top = np.floor(v_h - ABOVE_HORIZON_M * model.focal_px / (z_end * step)).astype(np.int64)
    cand &= (top >= 0) & (top < top_floor)
    # 2. lower than the camera (looked for after 1's columns are known): where the floor seen stops,
    # for as many rows as a face min_height_m tall would hide (or to the image's top), within the limit
    gaps = gaps or freespace.floor_gaps(seen_floor, df, model.baseline_m, min_height_m, step)
    # the lowest stretches of each column, lowest first: a patch of floor the matcher missed below a plain
    # face's foot (a rug, a shadow; any small one with a low min_height_m) must not hide the face
    lows = gaps.ends
    d_lows = np.where(lows >= 0, df[np.maximum(lows, 0), cols[None, :]], 0.0)
    stops_k = (lows >= 0) & (d_lows > fB / limit)
    stops = stops_k.any(0)
    bottom_start = gaps.bottom_start if bottom_start is None else bottom_start
    bottom = (bottom_start >= 0) & (df[h - 1] > fB / limit)  # 3's columns
    # unmeasured pixels above each row of the columns the rules look at (a running count: one pass)
    need = np.flatnonzero(cand | stops | bottom)
    at = np.full(w, -1)
    at[need] = np.arange(need.size)
    unmeasured = np.concatenate([np.zeros((1, need.size), np.int32),
                                 np.cumsum(dm[:, need] <= 0, axis=0, dtype=np.int32)])
    if cand.any():
        c = np.flatnonzero(cand)
        n = top_floor[c] - top[c]
        blank = (unmeasured[top_floor[c], at[c]] - unmeasured[top[c], at[c]]) >= UNMEASURED * n
        faces[c[blank]] = True
    tall_face = faces.copy()
    foot = np.where(faces, top_floor, -1)  # per face column, the floor row at its foot
    rows = np.arange(h)[:, None]
    for low, d_low, stop in zip(lows, d_lows, stops_k):
        _low_face(np.flatnonzero(stop & ~faces), low, d_low, dm, df, standing, doubtful, unmeasured, at, rows,
                  robot_height_m, min_height_m, normal, model, step, faces, foot, face_top, shift)
    # 3. a face whose foot is below the image: nearer than the floor at the image's bottom edge
    _below_image(np.flatnonzero(bottom & ~faces), bottom_start, df, dm, standing, unmeasured, at,
                 min_height_m, model, step, faces, foot, face_top, shift)
    if not faces.any():
        return None
    d_face = np.where(faces, df[np.clip(foot, 0, h - 1), cols] + shift, 0.0).astype(np.float64)
    with np.errstate(divide="ignore"):
        z_face = np.where(d_face > 0, fB / np.maximum(d_face, 1e-9), np.inf)
    # each face column from its foot up to its top edge, or robot_height_m above the floor there (what
    # the robot can hit)
    with np.errstate(invalid="ignore", over="ignore"):
        reach = np.ceil(robot_height_m * model.focal_px / (np.where(faces, z_face, 1.0) * step)).astype(np.int64)
    v0_all = np.maximum(foot - reach, face_top)
    measured = np.flatnonzero(dm.any(0))  # the matcher's blind left band: no column of it measured
    band = np.maximum(d_face / step, measured[0] if measured.size else 0)
    f = np.flatnonzero(faces)
    cut = (f <= band[f] + GAP_COLS + 2).any()  # a run _wide_runs may keep for the edge of the view
    hidden = _hidden(faces, v0_all, foot, dm, df, step) if cut else None
    faces = _wide_runs(faces, z_face, MIN_WIDTH_M * model.focal_px / step, band, hidden)
    if not faces.any():
        return None
    f = np.flatnonzero(faces)
    v1 = foot[f]
    v0 = v0_all[f]
    # a face of rule 1 stands upright to above the camera; what rules 2 and 3 find reaches up to a top edge
    # measured at its foot's depth (the top of a box seen from above is in it: that depth all the way up)
    d_col = np.where(tall_face[f][None, :], _upright(d_face[f], f, np.clip(v1, 0, h - 1), rows, normal, model, step),
                     d_face[f][None, :])
    in_face = (rows >= v0) & (rows < v1) & (dm[:, f] <= 0) & (d_col > 0)
    if not in_face.any():
        return None
    mask = np.zeros((h, w), bool)
    disparity = np.zeros((h, w), np.float32)
    mask[:, f] = in_face
    disparity[:, f] = np.where(in_face, d_col.astype(np.float32), np.float32(0))
    return BlankFaces(mask, disparity)


def _upright(d_foot: np.ndarray, cols: np.ndarray, foot: np.ndarray, rows: np.ndarray, normal: np.ndarray,
             model: camera.RectifiedModel, step: int) -> np.ndarray:
    """The disparity over working rows `rows` ((h, 1)) of each face column `cols` whose foot, at working
    row `foot`, has disparity d_foot: the face stands upright on the floor, a vertical plane through
    its foot turned to the camera. A camera that pitches or rolls sees such a face's pixels at
    disparities that change along the column (pitched 20 deg down, the top of a cabinet 2 m away is
    0.4 m nearer along the optical axis than its foot); the foot's disparity all the way up leaned the
    face back, and the blank-faces cabinet and panel (the camera 15 deg down) were placed 16-18 cm too
    far, a face 2.01 m ahead had its nearest point at 2.19 m. An upright camera gets the foot's
    disparity in every row. normal: the floor's (FloorPlane.normal_height: unit, camera frame, towards
    the floor). (h, k) float64; <= 0 where the plane is not in front of the camera."""
    f = model.focal_px
    n0, n1, n2 = (float(x) for x in normal)
    rx, ry = (cols * step - model.cx) / f, (foot * step - model.cy) / f  # rays to the feet: (rx, ry, 1)
    nr = n0 * rx + n1 * ry + n2
    # the face's normal m: the ray's part along the floor (its length cancels)
    m1 = ry - n1 * nr
    rm = rx * (rx - n0 * nr) + ry * m1 + (1.0 - n2 * nr)
    # a pixel of the column, dv rows from the foot, has the foot's ray plus (0, dv step / f, 0): by the
    # plane (r . m) Z = const, its disparity is the foot's times (r . m) over the foot's (r . m)
    slope = np.divide(step * m1, f * rm, out=np.zeros(rm.shape), where=rm > 0)
    return d_foot[None, :] * (1.0 + (rows - foot[None, :]) * slope[None, :])


def _low_face(c: np.ndarray, low: np.ndarray, d_low: np.ndarray, dm: np.ndarray, df: np.ndarray,
              standing: np.ndarray, doubtful: np.ndarray | None, unmeasured: np.ndarray, at: np.ndarray,
              rows: np.ndarray, robot_height_m: float, min_height_m: float, normal: np.ndarray,
              model: camera.RectifiedModel, step: int,
              faces: np.ndarray, foot: np.ndarray, face_top: np.ndarray, shift: np.ndarray) -> None:
    """Rule 2 (faces, foot, face_top, shift updated in place) at one stretch of each column c: low, the
    floor row just below it (d_low: the floor's disparity there). Above the stop, what was measured at
    all (doubted or not) is mostly at the stop's depth, up to a top edge min_height_m or more above the
    floor; else, by its outline (_outlined). At the face's depth: between the stop's disparity and an
    upright face's through it (_upright), within CAP_PX: a pitched camera sees a face's top edge nearer
    than its foot (dense's doubted matches up the blank-faces cabinet from 1.2 m up, 20 deg down), a
    box's top farther."""
    h = dm.shape[0]
    fB = model.focal_px * model.baseline_m
    if c.size:
        # the stretch a face min_height_m tall would cover must be unmeasured: else the matcher saw what
        # stands there (a textured thing, listed already), and the column costs no more
        v1 = low[c]
        first = np.maximum(v1 - np.ceil(min_height_m * d_low[c] / (model.baseline_m * step)).astype(np.int64), 0)
        c = c[unmeasured[v1, at[c]] - unmeasured[first, at[c]] >= UNMEASURED * (v1 - first)]
    if not c.size:
        return
    sub = dm[:, c]
    d = sub if doubtful is None else np.where(sub > 0, sub, doubtful[:, c])
    v1 = low[c]
    d0 = d_low[c].astype(np.float32)
    z0 = fB / d0
    reach = np.ceil(robot_height_m * model.focal_px / (z0 * step)).astype(np.int64)
    window = (rows < v1) & (rows >= v1 - reach)
    evidence = window & (d > 0)
    # at the face's depth, within the noise of a doubted match (near the foot the floor's too)
    d_up = _upright(d0, c, v1, rows, normal, model, step).astype(np.float32)
    off = np.abs(d - np.clip(d, np.minimum(d0, d_up), np.maximum(d0, d_up)))
    at_end = evidence & (off <= np.float32(CAP_PX))
    # counts from the foot upwards: rows at and below r, down to the foot
    n_ev = np.cumsum(evidence[::-1], axis=0, dtype=np.int32)[::-1]
    n_at = np.cumsum(at_end[::-1], axis=0, dtype=np.int32)[::-1]
    n_unm = unmeasured[v1, at[c]][None, :] - unmeasured[:h, at[c]]  # in [r, v1): the window's, for r in it
    span = v1[None, :] - rows  # rows from r to the foot
    tall = span * step * z0[None, :] / model.focal_px >= max(min_height_m, 1e-6)
    # a top edge: at the face's depth and nearer it than the floor's at its row, so no floor
    top_ok = (at_end & (off < np.abs(d - df[:, c])) & tall & (n_at >= FACE_SHARE * n_ev)
              & (n_unm >= UNMEASURED * span))
    found = top_ok.any(0)
    faces[c[found]] = True
    foot[c[found]] = v1[found]
    face_top[c[found]] = np.argmax(top_ok, axis=0)[found]  # the highest such top edge
    _outlined(c, low, d_low, dm, standing, unmeasured, at, min_height_m, normal, model, step,
              faces, foot, face_top, shift)


def _explained(near: np.ndarray, d_end: np.ndarray, z_end: np.ndarray, dm: np.ndarray, standing: np.ndarray,
               fB: float) -> np.ndarray:
    """Per column: whether something measured stands where it stops the floor seen, at the floor's end
    (within CAP_PX nearer) or up to BEHIND_M beyond it. What stands nearer, with floor seen beyond it,
    does not: a table top, or what a semi-global matcher makes of a plain wall's sensor noise (sgbm
    measured 1-3 % of a plain wall across the view 2 m ahead, blobs at 1.2-2.9 m, and the wall was in
    no list, unflagged, in 5 frames of 6)."""
    out = np.zeros(near.shape, bool)
    c = np.flatnonzero(near)
    if c.size:
        d = dm[:, c]
        at_end = (d >= (fB / (z_end[c] + BEHIND_M))[None, :]) & (d <= (d_end[c] + CAP_PX)[None, :])
        out[c] = (at_end & standing[:, c]).any(0)
    return out


def _outlined(c: np.ndarray, low: np.ndarray, d_low: np.ndarray, dm: np.ndarray, standing: np.ndarray,
              unmeasured: np.ndarray, at: np.ndarray, min_height_m: float, normal: np.ndarray,
              model: camera.RectifiedModel, step: int, faces: np.ndarray, foot: np.ndarray, face_top: np.ndarray,
              shift: np.ndarray) -> None:
    """Rule 2's third way (faces, foot, face_top, shift updated in place): c, the stop columns that passed
    its prefilter (the stretch above the stop unmeasured); those that showed a top edge (faces already)
    keep their face but still make up the runs below (dense's doubted matches straying up a plain crate
    seen from 0.5 m passed for top edges in scattered columns, and left out they broke the run into
    pieces each narrower than a face: the crate in no list in 3 of 4 frames, unflagged). Block matching
    measures no top edge of a plain cabinet against a textured wall behind: the edge's pixels take the
    wall's depth. It measures the outline's side (the face's edge against what is beside it), a
    sliver standing at the face's depth; the list held that sliver alone, 0.1 m wide, its centre
    0.48 m from the 0.9 m wide cabinet's. A run of stops at one depth (each column within CAP_PX of
    the next), with such a sliver beside one of its ends (within GAP_COLS + 2 columns, within CAP_PX of
    an upright face through the end's stop, reaching down to within min_height_m of that stop,
    min_height_m tall or more) is one face, as tall as the sliver, where the stretch up to that height
    is unmeasured (UNMEASURED of it). Upright: a camera that pitches sees a vertical edge's disparity
    change up the column (by 8 px up the blank-faces cabinet's 1.2 m from 1.2 m up, 20 deg down, where
    the stop's disparity alone kept the face to its lowest third, 0.33 m below the cabinet's centre).
    A plain patch of floor (a shadow beside a pole) fails that: the floor beyond it is measured
    within the pole's height. The face takes the side's depth: the floor seen reaches a little way up
    a face (what is within the floor margin counts as floor), so its last row lies beyond the foot (on
    low-faces, bm: 7.5 cm beyond the cabinet's 2.75 m); the run keeps the stops' slope along it."""
    if not c.size:
        return
    h, w = dm.shape
    near = GAP_COLS + 2
    rows = np.arange(h)
    # runs of stop columns: adjacent (GAP_COLS apart at most) and at one depth
    split = np.flatnonzero((np.diff(c) > GAP_COLS + 1) | (np.abs(np.diff(d_low[c])) > CAP_PX)) + 1
    runs = np.split(c, split)
    # the columns beside each run's ends with anything standing in them, and their end: the upright
    # face through each end's stop, for all of them at once
    has = np.any(standing, axis=0)
    beside = [(i, col, end) for i, run in enumerate(runs)
              for end, side in ((run[0], range(run[0] - 1, max(run[0] - 1 - near, -1), -1)),
                                (run[-1], range(run[-1] + 1, min(run[-1] + 1 + near, w))))
              for col in side if has[col]]
    if not beside:
        return
    where, cols, ends = (np.array(x) for x in zip(*beside))
    d_up = _upright(d_low[ends], cols, low[ends], rows[:, None], normal, model, step)
    tops_of: list[list[int]] = [[] for _ in runs]
    offsets_of: list[list[float]] = [[] for _ in runs]
    for k, (i, col, end) in enumerate(zip(where, cols, ends)):
        d0, v1 = d_low[end], low[end]
        at_depth = standing[:, col] & (np.abs(dm[:, col] - d_up[:, k]) <= CAP_PX)
        if not at_depth.any():
            continue
        r = rows[at_depth]
        # it reaches down to the stop's row, but for the floor margin (what is that low counts
        # as floor): within min_height_m of it; else it stands elsewhere, higher up
        if (v1 - r[-1]) * step * model.baseline_m / d0 > max(min_height_m, 1e-6):
            continue
        if (v1 - r[0]) * step * model.baseline_m / d0 >= max(min_height_m, 1e-6):
            tops_of[i].append(v1 - int(r[0]))  # the sliver's height above the stop, rows
            offsets_of[i].append(float(stats.median(dm[at_depth, col])) - d0)
    for run, tops, offsets in zip(runs, tops_of, offsets_of):
        if not tops:
            continue
        rise = max(tops)
        v1 = low[run]
        v0 = np.maximum(v1 - rise, 0)
        plain = (unmeasured[v1, at[run]] - unmeasured[v0, at[run]]) >= UNMEASURED * (v1 - v0)
        ok = run[plain & ~faces[run]]
        faces[ok] = True
        foot[ok] = low[ok]
        face_top[ok] = np.maximum(low[ok] - rise, 0)
        shift[ok] = offsets[int(np.argmax(tops))]


def _below_image(c: np.ndarray, start: np.ndarray, df: np.ndarray, dm: np.ndarray, standing: np.ndarray,
                 unmeasured: np.ndarray, at: np.ndarray, min_height_m: float, model: camera.RectifiedModel,
                 step: int, faces: np.ndarray, foot: np.ndarray, face_top: np.ndarray, shift: np.ndarray) -> None:
    """Rule 3 (faces, foot, face_top, shift updated in place): c, the columns whose floor seen stops
    for a stretch that reaches the image's bottom edge (start: its first row). A plain crate 0.35 m high
    whose near face stands just short of the image's bottom edge (low-faces: the floor there at 1.65 m,
    the crate at 1.4-1.8 m) leaves such a stretch: its faces and top unmeasured, the floor seen again
    just above its far top edge. Neither rule above sees it (no floor at its foot), and the list held
    its measured side alone (bm) or nothing (dense), unflagged. A smooth road at the bottom edge leaves
    the same stretch (karlsruhe, bm: most columns), so the stretch alone says nothing. What tells a
    face is a measured sliver beside one end of a run of such columns (within GAP_COLS + 2 columns)
    standing nearer than the floor at the bottom edge (so its foot is below the image too), reaching
    down to within SIDE_SHORT_M (or min_height_m, if more) of the edge, its top min_height_m or more
    above its foot (the floor's row at its disparity, below the image: seen from the edge, the 0.35 m
    crate's side was under 0.3 m tall), with the floor seen again within as much above its top (what
    stands there hides the floor up to its top edge; the side measured may fall short of it: 26 rows
    in one low-faces frame) and the run's columns unmeasured (UNMEASURED) from there down. The face
    reaches up to where the floor is seen again, at the sliver's median disparity. A pole beside a
    plain stretch of road fails: the road beyond is measured within the pole's height."""
    h, w = dm.shape
    c = c[(unmeasured[h, at[c]] - unmeasured[start[c], at[c]]) >= UNMEASURED * (h - start[c])]  # the plain ones
    if not c.size:
        return
    near = GAP_COLS + 2
    per_m = 1.0 / (model.baseline_m * step)  # rows a metre of height covers, per px of disparity
    for run in np.split(c, np.flatnonzero(np.diff(c) > GAP_COLS + 1) + 1):
        # the tallest sliver: (its top row, its median disparity, its nearest part's: the 95th percentile)
        best: tuple[int, float, float] | None = None
        for side in (range(run[0] - 1, max(run[0] - 1 - near, -1), -1), range(run[-1] + 1, min(run[-1] + 1 + near, w))):
            for col in side:
                nearer = standing[:, col] & (dm[:, col] > df[h - 1, col])
                if not nearer.any():
                    continue
                r = np.flatnonzero(nearer)
                ds = dm[nearer, col]
                d = float(stats.median(ds))
                tall = min_height_m * d * per_m
                short = max(min_height_m, SIDE_SHORT_M) * d * per_m
                # its foot, below the image: the floor's row at disparity d, down the floor's slope in the column
                slope = float(df[h - 1, col] - df[h - 2, col])
                v_foot = h - 1 + (d - float(df[h - 1, col])) / slope if slope > 0 else h
                if h - r[-1] > short or v_foot - r[0] < max(tall, 1):  # stands higher up, or too low
                    continue
                if best is None or r[0] < best[0]:
                    best = (int(r[0]), d, float(stats.percentile(ds, 95)))
        if best is None:
            continue
        top, d, d_near = best
        # left of x = d nothing at disparity d has a partner in the right image: unmeasured there says
        # nothing of plainness, out to the disparity of the face's nearest part (dense, karlsruhe: that
        # band beside a railing 3.9-4.3 m away, ending at its median 85-95 px, passed for a face in 12 of 40 frames)
        run = run[run * step >= d_near + step]
        if not run.size:
            continue
        v0 = np.minimum(start[run], top)  # up to where the floor is seen again
        plain = (unmeasured[h, at[run]] - unmeasured[v0, at[run]]) >= UNMEASURED * (h - v0)
        plain &= start[run] >= top - max(min_height_m, SIDE_SHORT_M) * d * per_m
        ok = run[plain]
        faces[ok] = True
        foot[ok] = h
        face_top[ok] = v0[plain]
        shift[ok] = d - df[h - 1, ok]


def _hidden(faces: np.ndarray, v0: np.ndarray, v1: np.ndarray, dm: np.ndarray, df: np.ndarray,
            step: int) -> np.ndarray:
    """Per face column: whether the floor beyond its foot (rows v0 to v1, where the floor lies in front
    of the camera) would be hidden from the right camera, in most of those rows (UNMEASURED of them), by
    something measured nearer to its right. Left of every near thing lies such a shadow, as wide as the
    two disparities differ: the floor seen ends there and nothing beyond is measured, whatever stands
    there or not, so that is no sign of a plain face. Runs of face columns in it are a shadow, not a face
    cut by the edge of the view (_wide_runs)."""
    out = np.zeros(faces.shape, bool)
    f = np.flatnonzero(faces)
    if not f.size:
        return out
    h, w = dm.shape
    r0, r1 = int(max(v0[f].min(), 0)), int(min(v1[f].max(), h))
    if r1 <= r0:
        return out
    sub = dm[r0:r1]
    # where each measured pixel lands in the right image (full-resolution columns); then, per column, the
    # leftmost of those among the columns to its right
    x_right = np.where(sub > 0, np.arange(w, dtype=np.float32) * step - sub, np.inf)
    right_min = np.minimum.accumulate(x_right[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([right_min[:, 1:], np.full((r1 - r0, 1), np.inf, np.float32)], axis=1)
    d_floor = df[r0:r1][:, f]
    x_floor = f[None, :] * step - d_floor  # where the floor's pixel would land in the right image
    rows = np.arange(r0, r1)[:, None]
    stretch = (rows >= v0[f][None, :]) & (rows < v1[f][None, :]) & (d_floor > 0)
    covered = stretch & (right_min[:, f] <= x_floor + SHADOW_TOL_PX)
    n = stretch.sum(0)
    out[f] = (n > 0) & (covered.sum(0) >= UNMEASURED * n)
    return out


def _wide_runs(a: np.ndarray, z: np.ndarray, fw: float, band: np.ndarray,
               hidden: np.ndarray | None = None) -> np.ndarray:
    """a (bool, 1-D: columns) with its runs of True narrower than fw / Z (working columns, at the
    run's median depth z) cleared. Runs apart by GAP_COLS columns or fewer are measured as one (a
    column or two the rules missed on a noisy face); the gap itself stays False. A run that ends
    within GAP_COLS + 2 columns of the left edge of what the matcher sees at its disparity (band: per
    column, working columns: the matcher's blind band, or x = d, left of which nothing at d has a
    partner in the right image) is as wide as it is there or wider, and is kept (GAP_COLS + 1 columns
    or more): bm searching 128 px saw 58 columns (0.27 m) of the low-faces crate right of its blind
    band, and the crate was in no list, unflagged. Not at the image's right side: there the road
    fading under a bright sky at 5-10 m made narrow runs, flat on the road (karlsruhe: 28 cells of the
    ground matrix over 5 % flat). Nor a run that lies mostly in a near thing's shadow (hidden: per
    column, _hidden): two-boxes from 0.5 m up, 12 deg down, with bm matching its left band
    (match_band), had the 16 px between the image's left edge at box-a's depth and box-a as a plain
    face 2.3 m away in every list."""
    out = np.zeros_like(a)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], a.astype(np.int8), [0]])))
    starts, ends = list(edges[::2]), list(edges[1::2])
    i = 0
    while i < len(starts):
        j = i
        while j + 1 < len(starts) and starts[j + 1] - ends[j] <= GAP_COLS:
            j += 1
        s, e = starts[i], ends[j]
        cut = s <= band[s] + GAP_COLS + 2
        if cut and hidden is not None and hidden[s:e][a[s:e]].mean() >= 0.5:
            cut = False  # a near thing's shadow beside the edge of the view, not a face that edge cuts
        if e - s >= (GAP_COLS + 1 if cut else fw / float(stats.median(z[s:e][a[s:e]]))):
            out[s:e] = a[s:e]
        i = j + 1
    return out
