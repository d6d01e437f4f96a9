"""Blank faces: a plain wall, door or cabinet in front of the robot, with nothing inside it to match.

Block matching measures a surface only where its image has texture. A painted cabinet 2 m ahead
leaves no disparity inside its outline; its sides, against what is behind, give a few pixels or
none. Without this step the list was empty or held a sliver, unflagged, with every matcher (dense
fills the blank from its farther surroundings). What does show is the floor: seen up to the face's
foot and not beyond.

Along each image column (a ray on the ground) the floor is seen out to a farthest point, Z_f. The
column holds a blank face standing at Z_f when
  - Z_f is short of the vision range (0.95 of it) and of near_field_m,
  - nothing measured stands in the column within BEHIND_M beyond Z_f (then that is what stops the
    floor: a car's dark underside below its body, a person's shadowed feet), and
  - the image above the floor's last row is unmeasured (UNMEASURED of it) all the way up past the
    horizon, to 0.1 m above the camera's height at Z_f. Unmeasured floor cannot reach that high:
    however far it went, it would stay below the horizon. Something stands at Z_f, as tall as the
    camera or taller.
Runs of such columns at least MIN_WIDTH_M wide at their median Z_f become standing pixels at the
floor's disparity at Z_f, up to robot_height_m above the floor: the obstacle is grouped, filtered
and tracked as any other, and its confidence (the share of its pixels the matcher measured) says
how little of it was seen.

A face lower than the camera is not found (its top cannot be told from unmeasured floor beyond);
nor one whose foot is not seen (nearer than the image's bottom edge). Farther than
near_field_m a road fading into the distance under a blank sky looks the same as a face:
on the street recording (karlsruhe, bm, 40 frames) 11 such stretches at 10-17 m, none nearer; on
the room recording and every synthetic scene, none.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cores import camera
from cores.segmentation.mount import FloorPlane

BEHIND_M = 1.0  # something standing measured this close beyond the floor's end explains it
UNMEASURED = 0.8  # share of the stretch above the floor's end that must be unmeasured
ABOVE_HORIZON_M = 0.1  # the stretch reaches this far above the camera's height at Z_f
MIN_WIDTH_M = 0.3  # narrower: a gap between two things, a pole's dark side, not a face to list


@dataclass
class BlankFaces:
    """Pixels taken for blank faces on the working grid, and their disparity (the floor's at each
    face's foot)."""

    mask: np.ndarray  # (h, w) bool
    disparity: np.ndarray  # (h, w) float32, valid where mask


def find(dm: np.ndarray, df: np.ndarray, seen_floor: np.ndarray, standing: np.ndarray, floor: FloorPlane,
         model: camera.RectifiedModel, step: int, range_m: float, within_m: float,
         robot_height_m: float) -> BlankFaces | None:
    """dm: working disparity (0 = unmeasured, not range-gated); df: the floor's disparity on the
    working grid; seen_floor / standing: the floor and standing pixels in range (bool, working grid).
    -> the blank faces' pixels, or None."""
    h, w = dm.shape
    if floor.b <= 0 or within_m <= 0:
        return None
    fB = model.focal_px * model.baseline_m
    limit = min(0.95 * range_m, within_m)
    has_floor = seen_floor.any(0)
    top_floor = np.argmax(seen_floor, axis=0)  # the topmost (farthest) floor row seen in each column
    cols = np.arange(w)
    d_end = np.where(has_floor, df[top_floor, cols], 0.0).astype(np.float64)
    with np.errstate(divide="ignore"):
        z_end = np.where(d_end > 0, fB / np.maximum(d_end, 1e-9), np.inf)
        d_stand = np.maximum.reduce(dm, axis=0, where=standing, initial=0)
        z_stand = np.where(d_stand > 0, fB / np.maximum(d_stand, 1e-9), np.inf)
    cand = has_floor & (z_end < limit) & (z_stand > z_end + BEHIND_M)
    if not cand.any():
        return None
    # the horizon's working row in each column (the floor's disparity 0) and 0.1 m above the camera there
    u = cols.astype(np.float64) * step
    v_h = (-floor.c - floor.a * u) / floor.b / step
    top = np.floor(v_h - ABOVE_HORIZON_M * model.focal_px / (z_end * step)).astype(np.int64)
    cand &= (top >= 0) & (top < top_floor)
    if not cand.any():
        return None
    c = np.flatnonzero(cand)
    # unmeasured pixels above each row of the candidate columns (a running count: one pass)
    unmeasured = np.concatenate([np.zeros((1, c.size), np.int32), np.cumsum(dm[:, c] <= 0, axis=0, dtype=np.int32)])
    k = np.arange(c.size)
    n = top_floor[c] - top[c]
    blank = (unmeasured[top_floor[c], k] - unmeasured[top[c], k]) >= UNMEASURED * n
    faces = np.zeros(w, bool)
    faces[c[blank]] = True
    faces = _wide_runs(faces, z_end, MIN_WIDTH_M * model.focal_px / step)
    if not faces.any():
        return None
    # each face column from its foot up to robot_height_m above the floor there (what the robot can hit)
    f = np.flatnonzero(faces)
    v1 = top_floor[f]
    v0 = v1 - np.ceil(robot_height_m * model.focal_px / (z_end[f] * step)).astype(np.int64)
    rows = np.arange(h)[:, None]
    in_face = (rows >= v0) & (rows < v1) & (dm[:, f] <= 0)
    if not in_face.any():
        return None
    mask = np.zeros((h, w), bool)
    disparity = np.zeros((h, w), np.float32)
    mask[:, f] = in_face
    disparity[:, f] = np.where(in_face, d_end[f].astype(np.float32), np.float32(0))
    return BlankFaces(mask, disparity)


def _wide_runs(a: np.ndarray, z: np.ndarray, fw: float) -> np.ndarray:
    """a (bool, 1-D: columns) with its runs of True narrower than fw / Z (working columns, at the
    run's median depth z) cleared."""
    out = np.zeros_like(a)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], a.astype(np.int8), [0]])))
    for s, e in zip(edges[::2], edges[1::2]):
        if e - s >= fw / float(np.median(z[s:e])):
            out[s:e] = True
    return out
