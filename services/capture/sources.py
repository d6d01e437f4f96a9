"""Capture sources: each yields stereo pairs (left, right as numpy images) plus, for the synthetic
world, the ground truth of that pair. No Zenoh here.

The source interface (what `main.run` relies on):

    name: str                 "synthetic", "cameras", "sbs", "video" or "images" (StereoFrame.source)
    period_s: float           seconds between pairs the loop should keep; 0 = the source paces itself
                              (a camera blocks until its next frame) or "as fast as possible"
    ended: bool               True once a file source has nothing more to give (see read)
    read() -> CapturedPair | None
                              the next pair. None means: the stream ended (`ended` is set), or the
                              loop is stopping (the context's stop event is set). A pair that cannot
                              be read (an unreadable image file, ...) raises SourceError naming the
                              file; the loop logs and counts it and goes on with the next pair.
    close()

Sources that wait (a camera being reconnected) or report (skew, drops) do it through a
`SourceContext`: they wait on its stop event, never in a bare sleep, report their state through
`status(text)` (main wires it to the service's status string) and keep numbers in `extra`
(main copies them into the service's stats).
"""
from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from common.errors import SourceError
from common.files import natural_key  # noqa: F401  (the sources' sort order; re-exported)
from cores import camera


@dataclass
class CapturedPair:
    left: np.ndarray  # (H, W) uint8 or (H, W, 3) BGR, raw (distorted) camera image
    right: np.ndarray
    t_s: float  # scene time of the pair (synthetic), stream position (files) or capture time (cameras), s
    truth: list[Any] | None = None  # synthetic.ObstacleTruth, rectified left camera frame
    extra: dict[str, float] = field(default_factory=dict)  # e.g. skew_ms of a camera pair
    stamp_ns: int | None = None  # capture time (ns since the Unix epoch) if the source knows it


@dataclass
class SourceContext:
    """What a source may use of its surroundings (the Node in the service, plain objects in tests)."""

    stop: threading.Event = field(default_factory=threading.Event)
    status: Callable[[str], None] = lambda text: None
    extra: dict[str, float] = field(default_factory=dict)
    node: Any = None  # the service's Node (its Zenoh session), for sources that talk Zenoh (ros2)


class RollingStats:
    """Median and maximum of the last `n` values (skew of the last pairs, for stats)."""

    def __init__(self, n: int = 120):
        self.values: deque[float] = deque(maxlen=n)

    def add(self, v: float) -> None:
        self.values.append(v)

    def p50(self) -> float:
        return float(np.median(np.fromiter(self.values, float))) if self.values else 0.0

    def max(self) -> float:
        return max(self.values) if self.values else 0.0


def split_sbs(frame: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """A side-by-side frame (H, 2W[, 3]) -> left half, right half, each contiguous (H, W[, 3])."""
    w = frame.shape[1]
    if w % 2:
        raise SourceError(f"{where}: side-by-side frame is {w} px wide, an odd width cannot be split in two")
    h = w // 2
    return np.ascontiguousarray(frame[:, :h]), np.ascontiguousarray(frame[:, h:])


def _stamped(image: np.ndarray, lap: int) -> np.ndarray:
    """A copy of the picture with `lap` in its first four bytes (row 0: the top-left pixels)."""
    out = image.copy()
    out.reshape(-1)[:4] = np.frombuffer((lap & 0xFFFFFFFF).to_bytes(4, "little"), np.uint8)
    return out


class SyntheticSource:
    """The built-in world rendered for a calibrated rig. Scene time advances 1/rate_hz per pair,
    so a run is deterministic whatever the machine's speed. preload > 0 renders that many pairs up
    front and loops them (benchmarks measure the pipeline, not the renderer)."""

    name = "synthetic"
    ended = False

    def __init__(self, scenario: str, calibration: str, rate_hz: float, seed: int = 0,
                 noise_sigma: float = 1.5, preload: int = 0, alpha: float = 0.0):
        from sim import Scene, SyntheticWorld

        rig = camera.load_calibration(calibration)
        if not isinstance(rig, camera.RawRig):
            raise camera.CalibrationError(f"{calibration}: the synthetic world needs a raw rig (K, D, R, T)")
        self.rig = rig
        self.rect = camera.rectify_rig(rig, alpha)
        self.scene = Scene.builtin(scenario) if hasattr(Scene, "builtin") else Scene.default()
        self.scenario = scenario
        self.world = SyntheticWorld(self.scene, rig, self.rect, seed=seed, noise_sigma=noise_sigma)
        self.dt = 1.0 / rate_hz
        self.period_s = self.dt
        self.k = 0
        self._loop: list[CapturedPair] = []
        for _ in range(preload):
            self._loop.append(self._render())

    def _render(self) -> CapturedPair:
        t = self.k * self.dt
        self.k += 1
        left, right = self.world.render(t)
        return CapturedPair(left, right, t, self.world.truth(t))

    def read(self) -> CapturedPair:  # (a synthetic scene never ends)
        if self._loop:
            n = len(self._loop)
            pair, lap = self._loop[self.k % n], self.k // n
            self.k += 1
            if lap:
                # the same buffer again: the lap is stamped into its first pixels so that no two pairs are
                # equal, as a live camera's noise makes them. rectify's frozen-camera check compares bytes:
                # a stage that saw only every 8th or 16th pair of a 16-pair loop (dropping the rest under
                # load, as `bench` offers it) saw one picture repeat and said camera-frozen
                pair = replace(pair, left=_stamped(pair.left, lap), right=_stamped(pair.right, lap))
            return pair
        return self._render()

    def close(self) -> None:
        pass
