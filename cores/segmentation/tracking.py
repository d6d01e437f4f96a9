"""Track ids and velocities across frames.

Each track is a constant-velocity Kalman filter in 3D (the robot base frame when the ground is
known, else the camera frame; metres; the axes are independent, so the filter is three 2-state
filters sharing one covariance shape). Association is one-to-one (Hungarian). In the camera frame
its cost is the distance between a track's prediction and a detection; in the base frame it is
the gap between their footprints on the ground (0 when they overlap) plus a tenth of the centroid
distance, and the centroids may differ by no more than the gate plus half the larger footprint
(seen with more or less of it, an object's centroid moves by up to half its extent: a railing
whose visible part slides along, a car entering the view). The gate is gate_m plus twice the
stereo noise at that distance (half a pixel of disparity, from the rig's f B) plus how far the
track may have moved while unseen (max_speed_mps * time unseen). A track unseen for longer than timeout_s and in at
least min_missed frames is dropped, so a short occlusion keeps its id and a long one does not,
while a segmenter starved of CPU (frames 1 s apart on a loaded robot) does not drop tracks it
simply had no frame to see them in. t_s must not go backwards (the service passes a monotonic
time base).

Velocities are the filter's: a new track starts at zero velocity with the variance of the speeds
obstacles have (most of what a robot sees stands still; two noisy centroids a frame apart are
not a speed), and sightings pull it by the Kalman gain. A sighting cut by the side of the view or
the vision range does not move its track's velocity by its centroid (which slides with the view);
cut on one side only, the other side's edge measures the motion (a person walking into the
image). Nor does a sighting whose footprint changed shape (more or less of the object segmented):
the position restarts from it, the velocity stays.

A track is confirmed once it has been seen in confirm_m of the last confirm_n frames, and stays
confirmed while it lives: one-frame flukes never reach a planner as trusted. When the frame the
positions are given in moves (the robot drove and turned: odometry), `move` carries every track
into the new frame first, so a parked car keeps its id and a zero velocity over the ground.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Track:
    id: int
    position: np.ndarray  # (3,) m, filtered
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) m/s
    last_seen_s: float = 0.0
    hits: int = 1
    missed: int = 0  # frames since it was last seen
    seen_bits: int = 1  # bit k: seen k frames ago
    confirmed: bool = False
    # pos var, pos-vel cov, vel var (per axis)
    P: np.ndarray = field(default_factory=lambda: np.array([0.05, 0.05, 1.0]))
    box: np.ndarray | None = None  # (2, 2): lo, hi of the footprint on the ground (x, y), when known
    last_whole: bool = True  # the last sighting was not cut by the edge of the view (see _correct)
    moving: bool = False  # the velocity has been measured (two sightings that measure motion)
    edges: np.ndarray | None = None  # (2, 3) left and right edge points of the last sighting

    def predicted(self, t_s: float) -> np.ndarray:
        return self.position + self.velocity * max(0.0, t_s - self.last_seen_s)

    def predicted_box(self, t_s: float) -> np.ndarray | None:
        if self.box is None:
            return None
        return self.box + (self.velocity[:2] * max(0.0, t_s - self.last_seen_s))[None, :]


class Tracker:
    """update(positions, t) -> one Track per position, in order (new tracks get new ids)."""

    def __init__(self, gate_m: float = 0.6, timeout_s: float = 1.0, velocity_smoothing: float = 0.5,
                 accel_mps2: float = 2.0, max_speed_mps: float = 2.5, min_missed: int = 3, confirm_m: int = 3,
                 confirm_n: int = 5):
        self.gate_m = gate_m
        self.confirm_m, self.confirm_n = confirm_m, max(confirm_n, confirm_m)
        self.timeout_s = timeout_s
        self.min_missed = min_missed
        # velocity_smoothing is kept for compatibility; the Kalman gain replaces it
        self.accel = accel_mps2
        self.max_speed = max_speed_mps
        self.tracks: list[Track] = []
        self._next_id = 1

    def move(self, R: np.ndarray, t: np.ndarray) -> None:
        """The frame moved: a point p of the old frame is R p + t in the new one."""
        for tr in self.tracks:
            tr.position = R @ tr.position + t
            tr.velocity = R @ tr.velocity
            if tr.edges is not None:
                tr.edges = tr.edges @ R.T + t
            if tr.box is not None:
                (x0, y0), (x1, y1) = tr.box
                corners = np.array([[x0, y0, 0], [x1, y0, 0], [x0, y1, 0], [x1, y1, 0]]) @ R.T + t
                tr.box = np.array([corners[:, :2].min(0), corners[:, :2].max(0)])

    def clear(self) -> None:
        self.tracks = []

    depth_scale: float | None = None  # f * B of the rig (px m), when known
    # True when positions are in the base frame (z up): tracks are associated by where they stand on
    # the ground, so a detection that grows or shrinks in height (a car merging with the tree behind
    # it in one frame) still finds its track
    ground_plane: bool = False

    def measurement_var(self, p: np.ndarray) -> float:
        """Centroid noise (m^2) of a detection at p: stereo depth noise grows with the square of the
        distance over f B (half a pixel of centroid disparity noise: measured on a real street); without
        the rig, a generic indoor one. The distance is |p|: the same in the camera and the base frame, near enough."""
        z2 = float(p @ p)
        k = 0.5 / self.depth_scale if self.depth_scale else 0.005
        return (0.01 + k * z2) ** 2

    def _correct(self, tr: Track, p: np.ndarray, t_s: float,
                 cut: tuple[bool, bool, bool] = (False, False, False), edges: np.ndarray | None = None,
                 reshaped: bool = False) -> None:
        """Update a track with a sighting at p. cut: (left, right, far): the sighting is cut by the
        left or right edge of what the camera measures, or by the vision range; its centroid then
        slides with the view (a car entering the image, a railing along the road). If one side is
        cut, the other side's edge (edges: (2, 3) left and right edge points) still moves with the
        object and measures its motion; cut otherwise, the position follows and the velocity keeps
        what earlier sightings gave it."""
        dt = t_s - tr.last_seen_s
        whole = not any(cut)
        meas = p
        usable = whole
        if not whole and not cut[2] and cut[0] != cut[1] and edges is not None and tr.edges is not None:
            k = 1 if cut[0] else 0  # cut on the left: the right edge moves with the object
            meas = tr.position + (edges[k] - tr.edges[k])
            usable = True
        r = self.measurement_var(p)
        if not usable:
            x = tr.position + tr.velocity * max(0.0, dt)
            pp = tr.P[0] + (self.accel ** 2) * max(0.0, dt) ** 4 / 4
            kp = pp / (pp + r)
            tr.position = x + kp * (p - x)
            tr.P = np.array([(1 - kp) * pp, tr.P[1], tr.P[2]])
        elif (whole and not tr.last_whole) or reshaped:
            # whole again after cut sightings, or seen with another shape (more or less of it
            # segmented): the centroid moved because of what is seen, not because the object
            # moved; the position restarts from it, the velocity stays
            tr.position = p.copy()
            tr.P = np.array([r, 0.0, tr.P[2]])
        else:
            pp, pv, vv = tr.P
            if dt > 0:
                q = self.accel ** 2
                pp, pv, vv = (pp + 2 * dt * pv + dt * dt * vv + q * dt ** 4 / 4, pv + dt * vv + q * dt ** 3 / 2,
                              vv + q * dt * dt)
            x = tr.position + tr.velocity * dt
            s = pp + r
            kp, kv = pp / s, pv / s
            innov = meas - x
            tr.position = x + kp * innov
            tr.velocity = tr.velocity + kv * innov
            tr.P = np.array([(1 - kp) * pp, (1 - kp) * pv, vv - kv * pv])
            tr.moving = tr.moving or dt > 1e-6
        tr.last_seen_s = t_s
        tr.hits += 1
        tr.last_whole = whole
        tr.edges = None if edges is None else np.asarray(edges, float).copy()

    def update(self, positions: list[np.ndarray], t_s: float, boxes: list[np.ndarray] | None = None,
               cuts: list[tuple[bool, bool, bool]] | None = None,
               edges: list[np.ndarray | None] | None = None) -> list[Track]:
        """positions: 3D points (camera or base frame, m) seen at time t_s (s) -> one track per
        position. boxes (ground_plane only): per position, its footprint (2, 2) lo, hi in x, y:
        tracks are then associated by the gap between footprints (0 when they overlap) plus a tenth
        of the centroid distance, so a long wall or railing whose visible part slides along as the
        robot drives keeps its id. cuts and edges:
        per position, where the edge of the view cuts it and its left/right edge points (_correct)."""
        self.tracks = [tr for tr in self.tracks
                       if t_s - tr.last_seen_s <= self.timeout_s or tr.missed < self.min_missed]
        pos = [np.asarray(p, dtype=float) for p in positions]
        assigned: dict[int, Track] = {}
        if self.tracks and pos:
            from scipy.optimize import linear_sum_assignment

            pred = np.array([tr.predicted(t_s) for tr in self.tracks])
            P = np.array(pos)
            dims = slice(0, 2) if self.ground_plane else slice(0, 3)
            D = np.linalg.norm(pred[:, None, dims] - P[None, :, dims], axis=2)
            unseen = np.array([t_s - tr.last_seen_s for tr in self.tracks])
            sigma = np.sqrt([self.measurement_var(p) for p in pred])
            gate = self.gate_m + 2 * sigma + self.max_speed * np.maximum(0.0, unseen - 0.1)
            slack = np.zeros_like(D)  # how far a centroid may move because of what of the object is seen
            if self.ground_plane and boxes is not None:
                tb = [tr.predicted_box(t_s) for tr in self.tracks]
                have = np.array([b is not None for b in tb])
                if have.any():
                    T = np.array([b if b is not None else np.zeros((2, 2)) for b in tb])  # (nt, 2, 2)
                    B = np.asarray(boxes, float)  # (nd, 2, 2)
                    gap = np.maximum(0.0, np.maximum(T[:, None, 0] - B[None, :, 1], B[None, :, 0] - T[:, None, 1]))
                    # the centroids too may differ by no more than the gate and half the larger
                    # footprint: seen with more or less of it (a fence whose stretches come and go,
                    # a car entering the view) an object's centroid moves by up to half its extent
                    ext_t = np.ptp(T, axis=1).max(1)
                    ext_d = np.ptp(B, axis=1).max(1)
                    slack = np.where(have[:, None], 0.5 * np.maximum(ext_t[:, None], ext_d[None, :]), 0.0)
                    far = D > slack + gate[:, None]
                    D = np.where(have[:, None], np.linalg.norm(gap, axis=2) + 0.1 * D, D)
                    D = np.where(far, 1e6, D)
            cost = np.where(D <= gate[:, None], D, 1e6)
            for ti, pi in zip(*linear_sum_assignment(cost)):
                if cost[ti, pi] < 1e6:
                    assigned[int(pi)] = self.tracks[int(ti)]
        out = []
        for pi, p in enumerate(pos):
            tr = assigned.get(pi)
            if tr is None:
                cut = cuts[pi] if cuts is not None else (False, False, False)
                # most of what a robot sees stands still: the velocity starts at zero, as uncertain
                # as the speeds obstacles have, and sightings pull it by the Kalman gain (two noisy
                # centroids 0.1 s apart are not a speed)
                tr = Track(self._next_id, p.copy(), last_seen_s=t_s, last_whole=not any(cut),
                           edges=None if edges is None or edges[pi] is None else np.asarray(edges[pi], float),
                           P=np.array([self.measurement_var(p), 0.0, (0.5 * self.max_speed) ** 2]))
                self._next_id += 1
                self.tracks.append(tr)
            else:
                reshaped = False
                if boxes is not None and tr.box is not None:
                    e_old, e_new = np.ptp(tr.box, axis=0), np.ptp(np.asarray(boxes[pi], float), axis=0)
                    reshaped = bool(np.max(np.abs(e_new - e_old)) > 0.2 + 0.25 * max(e_old.max(), e_new.max()))
                self._correct(tr, p, t_s, cuts[pi] if cuts is not None else (False, False, False),
                              edges[pi] if edges is not None else None, reshaped)
            if boxes is not None:
                tr.box = np.asarray(boxes[pi], float)
            tr.missed = -1  # seen in this frame (0 after the count below)
            out.append(tr)
        window = (1 << self.confirm_n) - 1
        for tr in self.tracks:
            tr.missed += 1
            if tr.missed == 0 and tr.hits > 1:
                tr.seen_bits = ((tr.seen_bits << 1) | 1) & window
            elif tr.missed > 0:
                tr.seen_bits = (tr.seen_bits << 1) & window
            tr.confirmed = tr.confirmed or bin(tr.seen_bits).count("1") >= self.confirm_m
        return out
