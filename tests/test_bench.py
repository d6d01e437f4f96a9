"""The benchmarks' bookkeeping on made-up inputs (seq gaps, the sustainable verdict, the rate search,
the ratios and targets, references measured with the pipeline idle, the scaling runs scored against
the ceilings around them, the accuracy baselines' settings) and short real runs of `bench --json`
and `bench-segmenter` (numbers not judged here: speed targets live in the benchmarks, not in tests)."""
from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import pytest
from helpers import REPO, cli

from bench import live_pipeline, pipeline, references
from bench.live_pipeline import MAX_DROPPED, Received, seq_gaps, summarize
from bench.pipeline import search_rate

KARLSRUHE = Path("/work/shared/data/real/karlsruhe-0023")


def lists(seqs, stale=(), latency_ms=10.0, period_ms=20.0):
    t0 = 1_000_000_000_000
    out = []
    for s in seqs:
        stamp = t0 + int(s * period_ms * 1e6)
        pub = stamp + int(latency_ms * 1e6)
        out.append(Received(pub + 1000, s, stamp, pub, s in stale,
                            {"capture": stamp + 1, "rectify": stamp + 2, "disparity": stamp + 3, "segmenter": pub}))
    return out


def test_seq_gaps_counts_the_missing_seqs_between_first_and_last():
    assert seq_gaps([]) == (0, 0, 0)
    assert seq_gaps([5, 6, 7]) == (3, 0, 0)
    assert seq_gaps([5, 7, 10]) == (6, 3, 0)
    assert seq_gaps([7, 5, 5, 6]) == (3, 0, 1)  # order does not matter; a repeat is a duplicate


def test_summarize_steady_stream_is_sustainable():
    r = summarize(lists(range(100), latency_ms=12.0), 2.0, compute_ms=10.0)
    assert r["sustainable"], r["why_not"]
    assert r["fps"] == 50.0 and r["stale_lists"] == 0
    assert r["seq_gaps"]["dropped"] == 0
    assert r["latency_ms"]["p50"] == pytest.approx(12.0)
    assert r["stage_latency_ms"]["segmenter"]["p50"] == pytest.approx(12.0 - 3e-6, abs=1e-3)


def test_summarize_names_each_reason_a_rate_is_not_sustainable():
    dropped = summarize(lists(range(0, 100, 2)), 2.0, compute_ms=10.0)  # every other pair lost
    assert not dropped["sustainable"]
    assert dropped["seq_gaps"]["dropped_fraction"] > MAX_DROPPED
    assert any("dropped" in w for w in dropped["why_not"])

    stale = summarize(lists(range(50), stale={10}), 1.0, compute_ms=10.0)
    assert not stale["sustainable"] and any("stale" in w for w in stale["why_not"])
    assert stale["obstacle_lists"] == 49  # a stale list is not a delivered one

    # The segmenter's heartbeat repeats the last list, stale, when input pauses (any rate under 2/s):
    # not a pair delivered late.
    beat = lists(range(5), period_ms=1000.0)
    beat += [Received(m.recv_ns + 600_000_000, m.seq, m.stamp_ns, m.publish_ns + 600_000_000, True, m.stages)
             for m in beat]
    slow_rate = summarize(beat, 5.0, compute_ms=10.0)
    assert slow_rate["sustainable"], slow_rate["why_not"]
    assert slow_rate["stale_lists"] == 0 and slow_rate["obstacle_lists"] == 5

    slow = summarize(lists(range(50), latency_ms=100.0), 1.0, compute_ms=10.0)
    assert not slow["sustainable"] and any("p95" in w for w in slow["why_not"])

    nothing = summarize([], 1.0, compute_ms=10.0)
    assert not nothing["sustainable"] and nothing["fps"] == 0.0


def model_probe(capacity_hz: float, calls: list):
    """A pipeline that delivers min(rate, capacity) and drops the rest."""

    def probe(rate: float) -> dict:
        calls.append(rate)
        fps = min(rate, capacity_hz)
        dropped = max(0.0, 1.0 - capacity_hz / rate)
        return {"fps": fps, "sustainable": dropped <= MAX_DROPPED, "why_not": []}

    return probe


@pytest.mark.parametrize("capacity", [12.0, 47.0, 95.0])
def test_search_finds_the_highest_sustainable_rate_within_a_few_probes(capacity):
    calls: list[float] = []
    rate, probes = search_rate(model_probe(capacity, calls), 130.0, probes=4)
    assert len(calls) <= 5 and len(probes) == len(calls)
    assert calls[0] == 130.0  # saturating first
    assert capacity * 0.9 <= rate <= capacity / (1 - MAX_DROPPED) + 1e-9
    assert all(p["offered_hz"] == c for p, c in zip(probes, calls))


def test_search_when_even_the_start_rate_holds_stops_at_once():
    calls: list[float] = []
    rate, probes = search_rate(model_probe(500.0, calls), 130.0, probes=4)
    assert rate == 130.0 and calls == [130.0]


def test_search_when_nothing_holds_reports_the_lowest_rate_tried():
    def never(rate: float) -> dict:
        return {"fps": rate * 0.5, "sustainable": False, "why_not": ["stale"]}

    rate, probes = search_rate(never, 100.0, probes=3)
    assert rate == min(p["offered_hz"] for p in probes)


@pytest.mark.slow
def test_bench_json_runs_the_four_processes_and_the_references():
    out = subprocess.run(cli("bench", "--json", "--rate", "8", "--seconds", "3", "--warmup", "2",
                             "--reference-seconds", "0.3", "--preload", "2", "--steady-rate", "5"),
                         capture_output=True, text=True, timeout=300, cwd=REPO)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout)
    run = r["runs"][0]
    # Obstacle lists came out of the four processes (on a machine this busy they may be stale).
    assert run["pipeline"]["obstacle_lists"] + run["pipeline"]["stale_lists"] > 0, run["pipeline"]
    assert run["pipeline"]["offered_hz"] == 8
    assert set(run["pipeline"]["cpu_ms_per_list"]) >= {"router", "capture", "rectify", "disparity", "segmenter"}
    ref = run["references"]
    assert ref["matcher_2_threads"]["threads"] == 2 and ref["matcher_1_thread"]["threads"] == 1
    assert ref["compute"]["total_ms_p50"] > 0
    assert run["ratios"]["fps_x_matcher_2_threads"] == pytest.approx(
        run["pipeline"]["fps"] / ref["matcher_2_threads"]["fps"])
    if run["pipeline"]["obstacle_lists"]:
        assert run["ratios"]["latency_p50_x_compute"] > 0
    # the second measured run, at the steady (camera's) rate, with its own latency ratio
    assert run["steady"]["offered_hz"] == 5
    if run["steady"]["obstacle_lists"]:
        assert run["ratios"]["latency_p50_x_compute_steady"] == pytest.approx(
            run["steady"]["latency_ms"]["p50"] / ref["compute"]["total_ms_p50"])
    by_process = run["ratios"]["cpu_x_matcher_1_thread_by_process"]
    assert set(by_process) == set(run["pipeline"]["cpu_ms_per_list"]) - {"bench"}
    assert r["targets"] == {"fps_x_matcher_2_threads": 0.8, "cpu_x_matcher_1_thread": 1.5,
                            "latency_p50_x_compute": 1.5, "latency_p50_x_compute_steady": 1.2}


# --- ratios, targets and the references ------------------------------------------------------------

def made_up_references(m2_fps=100.0, m1_fps=60.0, compute_ms=20.0) -> dict:
    return {"matcher_2_threads": {"threads": 2, "fps": m2_fps, "ms_p50": 1000.0 / m2_fps, "cpu_ms": 18.0},
            "matcher_1_thread": {"threads": 1, "fps": m1_fps, "ms_p50": 1000.0 / m1_fps, "cpu_ms": 15.0},
            "compute": {"stage_ms_p50": {"rectify": 2.0, "disparity": compute_ms - 5.0, "segmenter": 3.0},
                        "stage_cpu_ms": {"rectify": 2.0, "disparity": compute_ms - 5.0, "segmenter": 3.0},
                        "total_ms_p50": compute_ms, "fps": 1000.0 / compute_ms}}


def test_ratios_put_the_pipeline_over_the_references_of_the_same_run():
    pipe = summarize(lists(range(160), latency_ms=30.0, period_ms=12.5), 2.0, compute_ms=20.0)
    pipe["cpu_ms_per_list"] = {"capture": 1.0, "rectify": 3.0, "disparity": 16.0, "segmenter": 5.0, "bench": 9.0}
    x = pipeline.ratios(made_up_references(), pipe)
    assert x["fps_x_matcher_2_threads"] == pytest.approx(80.0 / 100.0)
    assert x["fps_x_matcher_1_thread"] == pytest.approx(80.0 / 60.0)
    assert x["latency_p50_x_compute"] == pytest.approx(30.0 / 20.0)
    assert x["latency_p95_x_compute"] == pytest.approx(pipe["latency_ms"]["p95"] / 20.0)
    assert x["latency_p99_x_compute"] == pytest.approx(pipe["latency_ms"]["p99"] / 20.0)
    assert x["cpu_x_matcher_1_thread"] == pytest.approx(25.0 / 15.0)  # the bench's own subscriber left out
    assert x["cpu_x_matcher_1_thread_by_process"] == pytest.approx(
        {"capture": 1 / 15, "rectify": 3 / 15, "disparity": 16 / 15, "segmenter": 5 / 15})
    verdicts = {label: ok for label, _, _, _, ok in pipeline.targets({"ratios": x})}
    assert verdicts == {"delivered fps / OpenCV matcher alone (2 threads)": True,
                        "CPU per list / the matcher's own CPU (1 thread)": False,  # 1.67 > 1.5
                        "latency p50 / in-process per-frame compute": True}  # no steady run: no verdict on it
    x["fps_x_matcher_2_threads"], x["latency_p50_x_compute"] = 0.79, 1.51
    assert not any(ok for *_, ok in pipeline.targets({"ratios": x}))
    # at a camera's rate: 30 Hz offered, all delivered, p50 22 ms over a 20 ms compute
    steady = summarize(lists(range(60), latency_ms=22.0, period_ms=33.3), 2.0, compute_ms=20.0)
    steady["cpu_ms_per_list"] = {"capture": 1.0, "rectify": 2.0, "disparity": 15.0, "segmenter": 4.0}
    steady["offered_hz"] = 30.0
    x = pipeline.ratios(made_up_references(), pipe, steady)
    assert x["latency_p50_x_compute_steady"] == pytest.approx(22.0 / 20.0)
    assert x["cpu_x_matcher_1_thread_steady"] == pytest.approx(22.0 / 15.0)
    verdicts = {label: ok for label, _, _, _, ok in pipeline.targets({"ratios": x})}
    assert verdicts["latency p50 at a camera's rate / in-process compute"] is True
    assert "a camera's rate" in pipeline.format_run(
        {"references": made_up_references() | {
            "matcher_2_threads": made_up_references()["matcher_2_threads"] | {"before_fps": 100.0, "after_fps": 100.0},
            "matcher_1_thread": made_up_references()["matcher_1_thread"] | {"before_fps": 60.0, "after_fps": 60.0}},
         "search": [], "pipeline": pipe | {"offered_hz": 80.0, "kernel_cpu_ms_per_list": {}}, "steady": steady,
         "ratios": x, "load_avg_1min": 1.0}, {"frames": 2, "method": "bm", "processes": "fake"})


def test_ratios_without_any_pipeline_cpu_are_not_a_number_rather_than_a_crash():
    pipe = summarize([], 1.0, compute_ms=20.0)
    pipe["cpu_ms_per_list"] = {"bench": 0.1}
    x = pipeline.ratios(made_up_references(), pipe)
    assert x["fps_x_matcher_2_threads"] == 0.0
    assert x["cpu_x_matcher_1_thread"] != x["cpu_x_matcher_1_thread"]  # NaN


class Idle:
    """Stands in for the capture supervisor: no processes."""
    children: list = []

    def stop_all(self) -> None:
        pass


@pytest.mark.parametrize("rate", [0.0, 40.0])
def test_every_reference_is_measured_with_capture_stopped(monkeypatch, rate):
    """The last probe's pairs kept flowing while OpenCV's matcher was measured alone: the reference
    shared the cores with the pipeline and every ratio came out flattered."""
    live = live_pipeline.LivePipeline("bm", preload=2)
    live.sup = Idle()
    offered = []

    def offer(r: float, timeout_s: float = 90.0) -> None:
        offered.append(r)
        live._capture = Idle()

    monkeypatch.setattr(live, "offer", offer)
    seen = []

    def references(frames, method, seconds=2.0):
        seen.append(live.capturing)
        return made_up_references()

    monkeypatch.setattr(pipeline, "references", references)
    monkeypatch.setattr(pipeline.time, "sleep", lambda s: None)
    live.offer(10.0)  # the warm-up leaves capture running
    args = argparse.Namespace(rate=rate, warmup=0.0, probe_seconds=0.0, seconds=0.0, probes=2, reference_seconds=0.0,
                              steady_rate=30.0)
    r = pipeline.measure_once(live, frames=None, args=args, log=lambda text: None)
    assert seen and not any(seen), seen
    assert len(seen) == (3 if rate == 0 else 2)  # the search's first look, before and after the measured runs
    # the warm-up, the search's probes, the measured run, (searched rates only) the runs at lower
    # rates after it was not sustained (nothing is, here: no obstacle list ever comes), the steady run
    assert len(offered) == 1 + len(r["search"]) + 1 + len(r["rejected"]) + 1
    assert offered[-1] == 30.0 and r["steady"]["offered_hz"] == 30.0
    assert len(r["rejected"]) == (pipeline.MAX_BACKOFFS if rate == 0 else 0)
    assert not live.capturing


def test_a_searched_rate_the_measured_run_does_not_sustain_is_stepped_down(monkeypatch):
    """Probes are short; the measured run may show a few % more drops at the same rate."""
    monkeypatch.setattr(pipeline, "references", lambda frames, method, seconds=2.0: made_up_references())
    calls = []

    class Live:
        method = "bm"

        def stop_capture(self) -> None:
            pass

        def measure(self, rate, warmup_s, seconds, compute_ms) -> dict:
            calls.append((rate, seconds))
            drop_every = 4 if (rate > 50 or (seconds == 10.0 and rate > 45)) else 0  # the long run holds less
            seqs = [s for s in range(200) if not drop_every or s % drop_every]
            r = summarize(lists(seqs), 2.0, compute_ms)
            r["cpu_ms_per_list"], r["kernel_cpu_ms_per_list"] = {"disparity": 10.0}, {"disparity": 1.0}
            return dict(r, offered_hz=rate)

    args = argparse.Namespace(rate=0.0, warmup=0.0, probe_seconds=3.0, seconds=10.0, probes=6, reference_seconds=0.0)
    r = pipeline.measure_once(Live(), frames=None, args=args, log=lambda text: None)
    searched = max(p["offered_hz"] for p in r["search"] if p["sustainable"])
    assert 45 < searched <= 50
    assert [q["offered_hz"] for q in r["rejected"]] == [searched]
    assert r["pipeline"]["sustainable"] and r["pipeline"]["offered_hz"] == pytest.approx(searched * pipeline.BACKOFF)
    assert "not sustained" in pipeline.format_run(r, {"frames": 2, "method": "bm", "processes": "fake"})


def test_the_matcher_reference_has_the_services_matcher_settings():
    from cores.matching.matchers import MatcherConfig

    c = MatcherConfig(method="bm")
    m = references.opencv_matcher("bm")
    # the service's search range for the synthetic rig: num_disparities auto, about 1 m (f*B = 66 px m)
    assert (m.getBlockSize(), m.getNumDisparities(), m.getMinDisparity()) == (c.block, 64, c.min_disparity)
    assert (m.getUniquenessRatio(), m.getTextureThreshold()) == (c.uniqueness_ratio, c.texture_threshold)
    s = MatcherConfig(method="sgbm")
    g = references.opencv_matcher("sgbm")
    assert (g.getBlockSize(), g.getP1(), g.getP2()) == (s.block, 8 * s.block ** 2, 32 * s.block ** 2)  # grey: cn 1


# --- scaling ----------------------------------------------------------------------------------------

def ceiling_of(fps: float) -> dict:
    return {"threads": 1, "fps": fps, "ms_p50": 1000.0 / fps, "cpu_ms": 1000.0 / fps}


def test_scaling_scores_each_run_against_the_ceilings_measured_around_it():
    from bench.scaling import TARGETS, score_runs

    runs = [{"workers": 1, "fps": 18.0}, {"workers": 2, "fps": 27.0}, {"workers": 3, "fps": 30.0}]
    # the machine got busier during the bench: the ceiling fell from 20 to 10 fps
    ceilings = [ceiling_of(20.0), ceiling_of(20.0), ceiling_of(10.0), ceiling_of(10.0)]
    by_n, targets = score_runs(runs, ceilings, cores=2)
    assert [r["x_one_thread_ceiling"] for r in runs] == pytest.approx([18 / 20, 27 / 15, 30 / 10])
    assert runs[1]["ceiling_one_thread"]["before_fps"] == 20.0 and runs[1]["ceiling_one_thread"]["after_fps"] == 10.0
    assert by_n[3]["median"] == pytest.approx(3.0)
    assert set(targets) == {1, 2}  # three workers have no target; two only where there are two cores
    assert targets[1] == {"x_one_thread_ceiling": pytest.approx(0.9), "target": TARGETS[1], "met": True}
    assert targets[2]["met"] and targets[2]["target"] == 1.8
    _, one_core = score_runs([dict(r) for r in runs], ceilings, cores=1)
    assert set(one_core) == {1}


def test_scaling_repeats_give_medians_and_a_short_ceiling_list_is_refused():
    from bench.scaling import score_runs

    runs = [{"workers": 1, "fps": f} for f in (16.0, 19.0, 10.0)]
    by_n, targets = score_runs(runs, [ceiling_of(20.0)] * 4, cores=2)
    assert by_n[1] == {"median": pytest.approx(0.8), "min": pytest.approx(0.5), "max": pytest.approx(0.95), "n": 3}
    assert not targets[1]["met"]
    with pytest.raises(ValueError, match="ceilings"):
        score_runs(runs, [ceiling_of(20.0)] * 3, cores=2)


# --- accuracy baselines -----------------------------------------------------------------------------

def test_accuracy_compares_with_opencvs_recommended_penalties_and_the_same_bm_block():
    from bench import accuracy
    from cores.matching.matchers import MatcherConfig

    base = accuracy.opencv_baselines(64)
    assert list(base) == accuracy.OPENCV_METHODS
    for name in ("opencv-sgbm-sample", "opencv-sgbm-hh", "opencv-sgbm-3way", "opencv-sgbm-5"):
        m, colour = base[name]
        w, cn = m.getBlockSize(), 3 if colour else 1
        assert colour and (m.getP1(), m.getP2()) == (8 * cn * w * w, 32 * cn * w * w), name
    assert base["opencv-sgbm-5"][0].getBlockSize() == MatcherConfig(method="sgbm").block
    bare, _ = base["opencv-sgbm-default"]
    assert (bare.getP1(), bare.getP2()) == (0, 0)  # kept as a reference row, never the only one
    bm, colour = base["opencv-bm-15"]
    assert bm.getBlockSize() == MatcherConfig(method="bm").block and not colour
    assert accuracy.REFERENCE in base


# --- bench-segmenter --------------------------------------------------------------------------------

def test_bench_segmenter_times_every_method_beside_the_matcher():
    from bench.segmenter import bench_segmenter, format_bench, segmenter_methods

    r = bench_segmenter(repeat=2)
    (synthetic,) = r["sets"]
    assert synthetic["image"] == "640x480" and synthetic["matcher"]["method"] == "bm"
    assert set(synthetic["methods"]) == set(segmenter_methods()) >= {"layers"}
    for m in synthetic["methods"].values():
        assert m["runs"] == 2 and m["ms_min"] <= m["ms_median"] <= m["ms_p95"]
        assert m["x_matcher"] == pytest.approx(m["ms_median"] / synthetic["matcher"]["ms_median"])
    assert synthetic["methods"]["layers"]["detections"] >= 1  # two boxes: it segmented something
    assert "x matcher" in format_bench(r)


@pytest.mark.skipif(not KARLSRUHE.is_dir(), reason=f"real recordings not found at {KARLSRUHE.parent} (see HELPERS.md)")
def test_bench_segmenter_times_a_real_karlsruhe_pair():
    out = subprocess.run(cli("bench-segmenter", "--real", str(KARLSRUHE), "--repeat", "2", "--method", "layers",
                             "--json"), capture_output=True, text=True, timeout=300, cwd=REPO)
    assert out.returncode == 0, out.stderr[-3000:]
    synthetic, real = json.loads(out.stdout)["sets"]
    assert real["image"] == "1344x372" and real["pairs"] == 1 and real["max_range_m"] == 20.0
    assert list(real["methods"]) == ["layers"] and real["methods"]["layers"]["runs"] == 2
    assert real["methods"]["layers"]["detections"] > 0  # a street within 20 m: segmented, not an empty map
    assert real["matcher"]["ms_median"] > 0


def test_bench_segmenter_without_a_recording_says_what_is_missing(tmp_path):
    out = subprocess.run(cli("bench-segmenter", "--real", str(tmp_path), "--repeat", "1"),
                         capture_output=True, text=True, timeout=300, cwd=REPO)
    assert out.returncode != 0
    assert "calibration.yaml" in out.stderr and "Traceback" not in out.stderr


# --- the parts of issue 22: the segmenter's steps, the frame path's copies -----------------------------

def test_segmenter_profile_breaks_the_service_path_into_steps():
    from bench.segmenter_profile import format_profile, profile_segmenter

    r = profile_segmenter(frames=3)
    assert set(r["steps"]) == {"one", "process", "segment_frame"}
    assert r["steps"]["one"][0]["function"] == "process_message"  # the builder is the frame's heaviest step
    names = {s["function"] for s in r["steps"]["segment_frame"]}
    assert {"_group", "_fit_ground"} <= names, names  # grouping and the ground fit are among the layers' steps
    assert "steps of layers.segment_frame" in format_profile(r)


def test_transport_copies_names_every_step_of_the_frame_path():
    from bench.transport import copies

    r = copies(rounds=1, n=2)
    assert all(any(step in k for k in r) for step in ("to_bytes", "unpackb", "array_from_image"))
    assert all(v >= 0 for v in r.values())


def test_free_port_never_hands_out_a_port_twice_even_when_the_kernel_repeats_itself(monkeypatch):
    """The kernel gave a just-released port to the next bind(0): a test's foxglove port and its
    router's were one, and the service met the router there. free_port skips what it gave before."""
    import socket

    from bench import measure

    given = iter([41001, 41001, 41001, 41002])

    class Repeating:
        def __init__(self, *a):
            self.port = next(given)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def bind(self, addr):
            pass

        def getsockname(self):
            return ("127.0.0.1", self.port)

    monkeypatch.setattr(measure, "_HANDED_OUT", set())
    monkeypatch.setattr(socket, "socket", Repeating)
    assert [measure.free_port(), measure.free_port()] == [41001, 41002]
