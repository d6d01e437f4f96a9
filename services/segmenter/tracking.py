"""Track ids and velocities across frames: greedy nearest-neighbour association in 3D with a
gate, a constant-velocity prediction, and a timeout so short occlusions keep their id."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Track:
    id: int
    position: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    last_seen_s: float = 0.0
    hits: int = 1


class Tracker:
    def __init__(self, gate_m: float = 0.6, timeout_s: float = 1.0, velocity_smoothing: float = 0.5):
        self.gate_m = gate_m
        self.timeout_s = timeout_s
        self.alpha = velocity_smoothing
        self.tracks: list[Track] = []
        self._next_id = 1

    def update(self, positions: list[np.ndarray], t_s: float) -> list[Track]:
        """positions: 3D points (camera frame, m) seen at time t_s -> one track per position, in order."""
        self.tracks = [tr for tr in self.tracks if t_s - tr.last_seen_s <= self.timeout_s]
        pairs = []
        for ti, tr in enumerate(self.tracks):
            predicted = tr.position + tr.velocity * (t_s - tr.last_seen_s)
            for pi, p in enumerate(positions):
                dist = float(np.linalg.norm(predicted - p))
                if dist <= self.gate_m:
                    pairs.append((dist, ti, pi))
        pairs.sort()
        assigned: dict[int, Track] = {}
        used: set[int] = set()
        for _, ti, pi in pairs:
            if ti in used or pi in assigned:
                continue
            tr = self.tracks[ti]
            dt = t_s - tr.last_seen_s
            if dt > 1e-6:
                v = (positions[pi] - tr.position) / dt
                tr.velocity = v if tr.hits == 1 else self.alpha * v + (1 - self.alpha) * tr.velocity
            tr.position = np.asarray(positions[pi], dtype=float)
            tr.last_seen_s = t_s
            tr.hits += 1
            used.add(ti)
            assigned[pi] = tr
        out = []
        for pi, p in enumerate(positions):
            tr = assigned.get(pi)
            if tr is None:
                tr = Track(self._next_id, np.asarray(p, dtype=float), last_seen_s=t_s)
                self._next_id += 1
                self.tracks.append(tr)
            out.append(tr)
        return out
