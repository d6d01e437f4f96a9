"""Track ids and velocities across frames.

Each track is a constant-velocity Kalman filter in 3D (camera frame, metres; the three axes are
independent, so the filter is three 2-state filters sharing one covariance shape). Association is
one-to-one (Hungarian) on the distance between a track's prediction and a detection, gated at
gate_m plus how far the track may have drifted while unseen (max_speed_mps * time unseen). A track
unseen for longer than timeout_s and in at least min_missed frames is dropped, so a short
occlusion keeps its id and a long one does not, while a segmenter starved of CPU (frames 1 s
apart on a loaded robot) does not drop tracks it simply had no frame to see them in. Velocities
are the filter's, zero until a track has been seen twice. t_s must not go backwards (the service
passes a monotonic time base).

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
    P: np.ndarray = field(default_factory=lambda: np.diag([0.05, 0.05, 1.0]))  # pos var, cov, vel var (per axis)
    box: np.ndarray | None = None  # (2, 2): lo, hi of the footprint on the ground (x, y), when known

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
        distance over f B (a quarter pixel of centroid disparity noise); without the rig, a generic
        indoor one. The distance is |p|: the same in the camera and the base frame, near enough."""
        z2 = float(p @ p)
        k = 0.25 / self.depth_scale if self.depth_scale else 0.005
        return (0.01 + k * z2) ** 2

    def _correct(self, tr: Track, p: np.ndarray, t_s: float) -> None:
        dt = t_s - tr.last_seen_s
        if tr.hits == 1:
            # second sighting: velocity from the two positions, with its uncertainty
            if dt > 1e-6:
                tr.velocity = (p - tr.position) / dt
                r = self.measurement_var(p)
                tr.P = np.array([r, r / dt, 2 * r / dt ** 2 + self.accel ** 2 * dt])
            tr.position = p.copy()
        else:
            pp, pv, vv = tr.P
            if dt > 0:
                q = self.accel ** 2
                pp, pv, vv = (pp + 2 * dt * pv + dt * dt * vv + q * dt ** 4 / 4, pv + dt * vv + q * dt ** 3 / 2,
                              vv + q * dt * dt)
            x = tr.position + tr.velocity * dt
            r = self.measurement_var(p)
            s = pp + r
            kp, kv = pp / s, pv / s
            innov = p - x
            tr.position = x + kp * innov
            tr.velocity = tr.velocity + kv * innov
            tr.P = np.array([(1 - kp) * pp, (1 - kp) * pv, vv - kv * pv])
        tr.last_seen_s = t_s
        tr.hits += 1

    def update(self, positions: list[np.ndarray], t_s: float, boxes: list[np.ndarray] | None = None,
               widen_m: float = 0.0) -> list[Track]:
        """positions: 3D points (camera or base frame, m) seen at time t_s (s) -> one track per
        position. boxes (ground_plane only): per position, its footprint (2, 2) lo, hi in x, y:
        tracks are then associated by the gap between footprints (0 when they overlap) plus a tenth
        of the centroid distance, so a long wall or railing whose visible part slides along as the
        robot drives keeps its id. widen_m: added to the gate (the caller's allowance for how much
        more of the scene changes between frames when the robot itself moves fast)."""
        self.tracks = [tr for tr in self.tracks if t_s - tr.last_seen_s <= self.timeout_s or tr.missed < self.min_missed]
        pos = [np.asarray(p, dtype=float) for p in positions]
        assigned: dict[int, Track] = {}
        if self.tracks and pos:
            from scipy.optimize import linear_sum_assignment

            pred = np.array([tr.predicted(t_s) for tr in self.tracks])
            P = np.array(pos)
            dims = slice(0, 2) if self.ground_plane else slice(0, 3)
            D = np.linalg.norm(pred[:, None, dims] - P[None, :, dims], axis=2)
            if self.ground_plane and boxes is not None:
                tb = [tr.predicted_box(t_s) for tr in self.tracks]
                have = np.array([b is not None for b in tb])
                if have.any():
                    T = np.array([b if b is not None else np.zeros((2, 2)) for b in tb])  # (nt, 2, 2)
                    B = np.asarray(boxes, float)  # (nd, 2, 2)
                    gap = np.maximum(0.0, np.maximum(T[:, None, 0] - B[None, :, 1], B[None, :, 0] - T[:, None, 1]))
                    D = np.where(have[:, None], np.linalg.norm(gap, axis=2) + 0.1 * D, D)
            unseen = np.array([t_s - tr.last_seen_s for tr in self.tracks])
            sigma = np.sqrt([self.measurement_var(p) for p in pred])
            gate = self.gate_m + widen_m + 2 * sigma + self.max_speed * np.maximum(0.0, unseen - 0.1)
            cost = np.where(D <= gate[:, None], D, 1e6)
            for ti, pi in zip(*linear_sum_assignment(cost)):
                if cost[ti, pi] < 1e6:
                    assigned[int(pi)] = self.tracks[int(ti)]
        out = []
        for pi, p in enumerate(pos):
            tr = assigned.get(pi)
            if tr is None:
                tr = Track(self._next_id, p.copy(), last_seen_s=t_s)
                self._next_id += 1
                self.tracks.append(tr)
            else:
                self._correct(tr, p, t_s)
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
