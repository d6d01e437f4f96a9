"""Capture sources: each yields stereo pairs (left, right as numpy images) plus, for the synthetic
world, the ground truth of that pair. No Zenoh here."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...common import camera


@dataclass
class CapturedPair:
    left: np.ndarray  # (H, W) uint8 or (H, W, 3) BGR, raw (distorted) camera image
    right: np.ndarray
    t_s: float  # scene time of the pair (synthetic) or capture time (cameras), seconds
    truth: list[Any] | None = None  # synthetic.ObstacleTruth, rectified left camera frame
    extra: dict[str, float] = field(default_factory=dict)


class SyntheticSource:
    """The built-in world rendered for a calibrated rig. Scene time advances 1/rate_hz per pair,
    so a run is deterministic whatever the machine's speed. preload > 0 renders that many pairs up
    front and loops them (benchmarks measure the pipeline, not the renderer)."""

    name = "synthetic"

    def __init__(self, scenario: str, calibration: str, rate_hz: float, seed: int = 0,
                 noise_sigma: float = 1.5, preload: int = 0, alpha: float = 0.0):
        from .synthetic import Scene, SyntheticWorld

        rig = camera.load_calibration(calibration)
        if not isinstance(rig, camera.RawRig):
            raise camera.CalibrationError(f"{calibration}: the synthetic world needs a raw rig (K, D, R, T)")
        self.rig = rig
        self.rect = camera.rectify_rig(rig, alpha)
        self.scene = Scene.builtin(scenario) if hasattr(Scene, "builtin") else Scene.default()
        self.scenario = scenario
        self.world = SyntheticWorld(self.scene, rig, self.rect, seed=seed, noise_sigma=noise_sigma)
        self.dt = 1.0 / rate_hz
        self.k = 0
        self._loop: list[CapturedPair] = []
        for _ in range(preload):
            self._loop.append(self._render())

    def _render(self) -> CapturedPair:
        t = self.k * self.dt
        self.k += 1
        left, right = self.world.render(t)
        return CapturedPair(left, right, t, self.world.truth(t))

    def read(self) -> CapturedPair | None:
        if self._loop:
            pair = self._loop[self.k % len(self._loop)]
            self.k += 1
            return pair
        return self._render()

    def close(self) -> None:
        pass
