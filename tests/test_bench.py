"""The pipeline benchmark: its bookkeeping (seq gaps, the sustainable verdict, the rate search) on
made-up inputs, and one short real run of `ballbot-vision bench --json` (numbers not judged here:
speed targets live in the benchmark, not in tests)."""
from __future__ import annotations

import json
import subprocess

import pytest

from ballbot_vision.bench.pipeline import (MAX_DROPPED, Received, search_rate, seq_gaps, summarize)
from helpers import REPO, cli


def lists(seqs, stale=(), latency_ms=10.0, period_ms=20.0):
    t0 = 1_000_000_000_000
    out = []
    for i, s in enumerate(seqs):
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


def test_bench_json_runs_the_four_processes_and_the_references():
    out = subprocess.run(cli("bench", "--json", "--rate", "8", "--seconds", "3", "--warmup", "2",
                             "--reference-seconds", "0.3", "--preload", "2"),
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
    assert r["targets"] == {"fps_x_matcher_2_threads": 0.8, "latency_p50_x_compute": 1.5}
