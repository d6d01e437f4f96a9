"""The one in-process composition (cores/pipeline.py) gives what the services compute: the same pair
through the disparity service's FrameComputer and the segmenter's message decoding gives the same
disparity and the same obstacle list as Pipeline.process (which the offline commands, the evaluations
and the benchmarks run)."""
from __future__ import annotations

import numpy as np
import pytest

from common import codec
from common.messages import DisparityMap, StereoFrame
from cores import camera
from cores.matching.config import MatcherConfig
from cores.pipeline import Pipeline
from cores.segmentation.builder import ObstacleBuilder
from cores.segmentation.settings import SegmenterSettings
from services.capture.sources import SyntheticSource
from services.disparity.computer import FrameComputer


@pytest.fixture(scope="module")
def pairs():
    src = SyntheticSource("two-boxes", "lifecam-studio", 30.0)
    return [src.read() for _ in range(3)]


@pytest.mark.parametrize("method", ["bm", "sgbm"])
def test_the_pipeline_computes_what_the_services_compute(pairs, method):
    cal = camera.load_calibration("lifecam-studio")
    matcher, segmenter = MatcherConfig(method=method), SegmenterSettings()
    pipe = Pipeline(cal, matcher, segmenter)
    computer, builder = FrameComputer(matcher), ObstacleBuilder(segmenter)
    for k, pair in enumerate(pairs):
        t_s = k / 30.0
        frame = pipe.process(pair.left, pair.right, t_s=t_s, seq=k)
        # the services' path: rectify's frame, the disparity service's map over the wire, the segmenter's decoding
        msg = StereoFrame(robot_id="r", seq=k, stamp_ns=int(round(t_s * 1e9)), camera=pipe.rectifier.model_message,
                          left=codec.image_from_array(frame.left), right=codec.image_from_array(frame.right))
        wire = codec.decode(codec.encode(computer.compute(msg, "w")), DisparityMap)
        served = builder.process_message(wire, t_s=t_s)
        np.testing.assert_array_equal(np.isnan(served_disparity(builder, wire)), np.isnan(frame.disparity))
        assert np.nanmax(np.abs(served_disparity(builder, wire) - frame.disparity)) == 0
        a, b = frame.result.obstacles, served.obstacles
        assert len(a.obstacles) == len(b.obstacles) == 2, a.model_dump_json()
        for x, y in zip(a.obstacles, b.obstacles):
            assert x.position_m == y.position_m and x.bbox_px == y.bbox_px and x.id == y.id
        assert a.ground == b.ground and a.degraded == b.degraded and a.valid_fraction == b.valid_fraction
        # sgbm's plain windows (no floor seen there) cross the wire bit for bit, and both free spaces heed them
        flat = builder.decode(wire)[3]
        if method == "sgbm":
            np.testing.assert_array_equal(flat, frame.stage.match.flat)
        else:
            assert flat is None and frame.stage.match.flat is None
        assert served.freespace is not None and served.freespace.cells == frame.result.freespace.cells


def served_disparity(builder: ObstacleBuilder, wire: DisparityMap) -> np.ndarray:
    return builder.decode(wire)[0]


def test_fork_shares_the_matcher_and_keeps_its_own_tracks(pairs):
    pipe = Pipeline(camera.load_calibration("lifecam-studio"))
    other = pipe.fork(SegmenterSettings(method="seed"))
    assert other.matching is pipe.matching and other.builder is not pipe.builder
    stage = pipe.match(*pipe.rectify(pairs[0].left, pairs[0].right))
    assert other.segment(stage, t_s=0.0).obstacles.method == "seed"
    assert pipe.segment(stage, t_s=0.0).obstacles.method == "layers"


def test_a_matcher_gated_nearer_than_the_range_says_so_on_every_list(pairs):
    """The thesis's vision range gate on the disparity stage (max_range_m 2 m) under the segmenter's
    4.5 m range: the box at 2.3 m and the floor beyond 2 m are in no map, and the lists had said
    nothing of it (an empty list there read as a clear way to 4.5 m). Now the map carries its gate
    (DisparityMap.gate_px) and every list, the pipeline's and the services', says far-unmeasured. A
    gate at the range's own end (the thesis's 3 m with a 3 m range) is no news."""
    cal = camera.load_calibration("lifecam-studio")
    for gate_m, range_m, said in ((2.0, None, True), (3.0, 3.0, False)):
        matcher, segmenter = MatcherConfig(method="bm", max_range_m=gate_m), SegmenterSettings(max_range_m=range_m)
        pipe = Pipeline(cal, matcher, segmenter)
        computer, builder = FrameComputer(matcher), ObstacleBuilder(segmenter)
        for k, pair in enumerate(pairs[:2]):
            frame = pipe.process(pair.left, pair.right, t_s=k / 30.0, seq=k)
            msg = StereoFrame(robot_id="r", seq=k, stamp_ns=k, camera=pipe.rectifier.model_message,
                              left=codec.image_from_array(frame.left), right=codec.image_from_array(frame.right))
            wire = codec.decode(codec.encode(computer.compute(msg, "w")), DisparityMap)
            fB = pipe.model.focal_px * pipe.model.baseline_m
            assert wire.gate_px == pytest.approx(fB / gate_m)
            served = builder.process_message(wire, t_s=k / 30.0).obstacles
            for lst in (frame.result.obstacles, served):
                assert ("far-unmeasured" in lst.degraded) == said, (gate_m, lst.degraded)
                assert lst.range_m == pytest.approx((1.0, gate_m if said else range_m)), lst.range_m
        if said:
            assert f"nothing farther than {gate_m:.2f} m is measured" in builder.reach.message
            assert "max_range_m" in builder.reach.message and builder.reach.far_unmeasured
            assert [round(o.distance_m, 1) for o in served.obstacles if o.distance_m > gate_m] == []
