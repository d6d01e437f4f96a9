"""The pipeline in one process: rectify -> match -> segment, with the services' settings and gates.

This is the one composition of the cores. The services run the same three steps in three
processes (services/rectify: Rectifier; services/disparity: MatchStage; services/segmenter:
ObstacleBuilder); the offline commands (`rectify`, `disparity`, `obstacles`), the evaluations
(`eval`, `eval --real`) and every benchmark's in-process reference run them here, so what is
evaluated and benchmarked is what runs:

    pipe = Pipeline(calibration, MatcherConfig(), SegmenterSettings())
    frame = pipe.process(left, right, t_s=0.0, seq=0)   # raw pair -> rectified, disparity, obstacles
    frame.result.obstacles                              # the ObstacleList the segmenter would publish

Stateful like the segmenter: the ground estimate and the tracks carry over from pair to pair, so
feed one stream in order (a new Pipeline, or `fork()`, for another stream).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from common.messages import FrameChecks, Odometry
from common.settings import MountSettings
from cores import camera
from cores.calibration.check import PairChecks
from cores.calibration.rectify import Rectifier
from cores.matching.config import MatcherConfig
from cores.matching.stage import MatchStage, StageResult
from cores.segmentation.builder import FrameResult, ObstacleBuilder
from cores.segmentation.settings import SegmenterSettings


@dataclass
class MatchedPair:
    """One pair through rectify and the disparity stage, as their services hand it on: the rectified
    pair, the stage's result, rectify's checks of the pair (FrameChecks, which the map carries to the
    segmenter), and the time each step took."""

    left: np.ndarray
    right: np.ndarray
    stage: StageResult
    checks: FrameChecks
    rectify_ms: float  # wall time; rectify's checks on its frame path included
    match_ms: float
    rectify_cpu_ms: float = 0.0  # this process's CPU time (all its threads), the same two steps
    match_cpu_ms: float = 0.0


@dataclass
class PipelineFrame:
    """One pair through the pipeline: the rectified pair, the disparity stage's result, the float
    disparity the segmenter saw (px, NaN invalid), its FrameResult, and the time each step took."""

    seq: int
    left: np.ndarray
    right: np.ndarray
    stage: StageResult
    disparity: np.ndarray
    result: FrameResult
    rectify_ms: float
    match_ms: float
    segment_ms: float


class Pipeline:
    """calibration: a raw rig (rectified here) or an already-rectified model (pairs pass as they
    are); matcher: the disparity settings; segmenter: the segmenter's settings; alpha: rectify's;
    mount: the camera on the robot (the `mount:` section every service reads); rows: rectify's live
    row check (row_check_s, max_row_offset_px; run in line here, on stream time); frozen_after_s:
    rectify's, for a camera whose picture stopped changing; near_check: rectify's coarse wide search
    for what stands nearer than the vision range; match_scale: the matcher's resolution (0.5: the
    dispatcher's onboard `fallback: half`)."""

    def __init__(self, calibration: camera.Calibration, matcher: MatcherConfig | None = None,
                 segmenter: SegmenterSettings | None = None, alpha: float = 0.0, mount: MountSettings | None = None,
                 rows: tuple[float, float] = (1.0, 0.5), frozen_after_s: float = 0.5, near_check: bool = True,
                 match_scale: float = 1.0):
        self.rectifier = Rectifier(calibration, alpha)
        self.checks = PairChecks(*rows, frozen_after_s, near_check)
        self.model: camera.RectifiedModel = self.rectifier.model
        self.matching = MatchStage(matcher or MatcherConfig(), match_scale)
        self.segmenter_settings = segmenter or SegmenterSettings()
        self.mount = mount or MountSettings()
        self.builder = ObstacleBuilder(self.segmenter_settings, self.mount)

    def fork(self, segmenter: SegmenterSettings | None = None, mount: MountSettings | None = None) -> Pipeline:
        """Another stream through the same rectification and matcher (shared: they keep no state
        between pairs), with a segmenter of its own (fresh ground and tracks)."""
        other = object.__new__(Pipeline)
        other.rectifier, other.model, other.matching = self.rectifier, self.model, self.matching
        other.checks = self.checks.fresh()
        other.segmenter_settings = segmenter or self.segmenter_settings
        other.mount = mount or self.mount
        other.builder = ObstacleBuilder(other.segmenter_settings, other.mount)
        return other

    def rectify(self, left: np.ndarray, right: np.ndarray, names: tuple[str, str] = ("left", "right")
                ) -> tuple[np.ndarray, np.ndarray]:
        """A raw pair of this calibration's size -> the rectified pair (sizes checked, named)."""
        self.rectifier.check_size(left, names[0])
        self.rectifier.check_size(right, names[1])
        return self.rectifier.rectify(left, right)

    def match(self, left: np.ndarray, right: np.ndarray) -> StageResult:
        """A rectified pair -> the disparity stage's result, as the disparity service computes it."""
        return self.matching.compute(left, right, self.model.focal_px, self.model.baseline_m, self.model)

    def segment(self, stage: StageResult | np.ndarray, *, t_s: float, seq: int = 0, stamp_ns: int | None = None,
                odometry: Odometry | None = None, image: np.ndarray | None = None,
                confidence: np.ndarray | None = None, checks: FrameChecks | None = None) -> FrameResult:
        """A disparity (the stage's result, or a float px map with NaN invalid) -> the segmenter's
        FrameResult. t_s: the pair's time (s, never going backwards); checks: rectify's of the pair."""
        if isinstance(stage, StageResult):
            disparity, handed = stage.disparity_px(), stage.handed()
        else:
            disparity, handed = stage, {"confidence": confidence}
        return self.builder.process(disparity, self.model, t_s=t_s, seq=seq,
                                    stamp_ns=int(round(t_s * 1e9)) if stamp_ns is None else stamp_ns,
                                    odometry=odometry, image=image, checks=checks, **handed)

    def front(self, left: np.ndarray, right: np.ndarray, *, t_s: float, stamp_ns: int | None = None,
              names: tuple[str, str] = ("left", "right"), rectified: bool = False) -> MatchedPair:
        """One pair, raw (rectified=False) or already rectified, through rectify (with its checks) and
        the disparity stage: what the segmenter is handed. Stateful (rectify's checks watch the
        stream's time): one stream in order."""
        stamp = int(round(t_s * 1e9)) if stamp_ns is None else stamp_ns

        def rows(lf: np.ndarray, rt: np.ndarray) -> None:
            # on stream time, in line: the service runs it in a thread of the same process (its wall time
            # is off the frame path there, its CPU is not: timed here as rectify's, once a row_check_s)
            self.checks.rows.observe(lf, rt, t_s, stamp)

        t0, c0 = time.perf_counter(), time.process_time()
        left, right, checks = self.checks.frame(
            left, right, t_s, (lambda lf, rt: (lf, rt)) if rectified else (lambda lf, rt: self.rectify(lf, rt, names)),
            self.model, rows)
        t1, c1 = time.perf_counter(), time.process_time()
        stage = self.match(left, right)
        t2, c2 = time.perf_counter(), time.process_time()
        return MatchedPair(left, right, stage, checks, (t1 - t0) * 1e3, (t2 - t1) * 1e3, (c1 - c0) * 1e3,
                           (c2 - c1) * 1e3)

    def process(self, left: np.ndarray, right: np.ndarray, *, t_s: float, seq: int = 0, stamp_ns: int | None = None,
                odometry: Odometry | None = None, names: tuple[str, str] = ("left", "right"),
                rectified: bool = False) -> PipelineFrame:
        """One pair, raw (rectified=False) or already rectified, through the three steps."""
        stamp_ns = int(round(t_s * 1e9)) if stamp_ns is None else stamp_ns
        m = self.front(left, right, t_s=t_s, stamp_ns=stamp_ns, names=names, rectified=rectified)
        t2 = time.perf_counter()
        disparity = m.stage.disparity_px()
        result = self.builder.process(disparity, self.model, t_s=t_s, seq=seq, stamp_ns=stamp_ns, odometry=odometry,
                                      image=m.left, checks=m.checks, **m.stage.handed())
        t3 = time.perf_counter()
        return PipelineFrame(seq, m.left, m.right, m.stage, disparity, result, m.rectify_ms, m.match_ms,
                             (t3 - t2) * 1e3)
