"""The pipeline `bench pipeline` measures, live: router, rectify, disparity (+ workers) and
segmenter as processes the way `up` runs them, capture restarted per offered rate, and what one
probe at a rate measured (lists received, pairs dropped, latency, CPU, sustainable or not)."""
from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from bench.measure import cpu_seconds, free_port, percentiles

if TYPE_CHECKING:
    from common.supervisor import Supervisor

STAGES = ["capture", "rectify", "disparity", "segmenter"]

# What "sustainable" means for an offered rate (the search keeps the highest rate that is):
MAX_DROPPED = 0.03  # at most this fraction of captured pairs never becomes an obstacle list (seq gaps)
MAX_P95_X_COMPUTE = 4.0  # capture-to-obstacle p95 within this multiple of the in-process compute


# --- one probe's numbers (pure) --------------------------------------------------------------------

@dataclass
class Received:
    recv_ns: int
    seq: int
    stamp_ns: int
    publish_ns: int
    stale: bool
    stages: dict[str, int] = field(default_factory=dict)


def seq_gaps(seqs: list[int]) -> tuple[int, int, int]:
    """Delivered seqs (any order, repeats allowed) -> (captured, dropped, duplicates): captured is
    the span first..last, dropped the seqs in that span never delivered."""
    if not seqs:
        return 0, 0, 0
    unique = set(seqs)
    captured = max(unique) - min(unique) + 1
    return captured, captured - len(unique), len(seqs) - len(unique)


def summarize(lists: list[Received], seconds: float, compute_ms: float) -> dict:
    """Obstacle lists received in a window of `seconds` -> fps, latency, drops, and whether the
    offered rate was sustainable (no stale list, few drops, bounded latency)."""
    fresh = [m for m in lists if not m.stale]
    captured, dropped, dups = seq_gaps([m.seq for m in fresh])
    lat = percentiles([(m.publish_ns - m.stamp_ns) / 1e6 for m in fresh])
    stage_lat = {}
    prev = "capture"
    for s in STAGES[1:]:
        stage_lat[s] = percentiles([(m.stages[s] - m.stages[prev]) / 1e6 for m in fresh
                                    if s in m.stages and prev in m.stages])
        prev = s
    # A stale list is a pair that came out too late; the segmenter's heartbeat also repeats the last
    # list, flagged stale, whenever no input came for stale_after_s (every pair at rates under 2/s):
    # those repeat a seq already delivered and say nothing about keeping up.
    fresh_seqs = {m.seq for m in fresh}
    stale = len({m.seq for m in lists if m.stale and m.seq not in fresh_seqs})
    dropped_fraction = dropped / captured if captured else 1.0
    why = []
    if not fresh:
        why.append("no obstacle list")
    if stale:
        why.append(f"{stale} pair(s) delivered stale")
    if dropped_fraction > MAX_DROPPED:
        why.append(f"{dropped_fraction:.0%} of pairs dropped")
    if fresh and lat["p95"] > MAX_P95_X_COMPUTE * compute_ms:
        why.append(f"p95 {lat['p95']:.0f} ms > {MAX_P95_X_COMPUTE:g} x compute")
    return {"seconds": seconds, "obstacle_lists": len(fresh), "fps": len(fresh) / seconds if seconds else 0.0,
            "captured_hz": captured / seconds if seconds else 0.0, "stale_lists": stale,
            "seq_gaps": {"captured": captured, "dropped": dropped, "dropped_fraction": dropped_fraction,
                         "duplicates": dups},
            "latency_ms": lat, "stage_latency_ms": stage_lat, "sustainable": not why, "why_not": why}


# --- the pipeline under test ----------------------------------------------------------------------

class LivePipeline:
    """Router, rectify, disparity (+ workers) and segmenter as processes, capture restarted per
    offered rate, and a subscriber collecting every obstacle list (msgpack only: the bench stays light)."""

    def __init__(self, method: str, preload: int, workers: int = 0, robot_id: str = "bench", nice: int = 0):
        self.method, self.preload, self.workers, self.rid, self.nice = method, preload, workers, robot_id, nice
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.received: list[Received] = []
        self._lock = threading.Lock()
        self._first = threading.Event()
        self._want_stamp = 0
        self._capture: Supervisor | None = None  # capture alone, restarted per offered rate
        self.processed: dict[str, list[tuple[int, int]]] = {}  # service -> [(stats stamp ns, frames processed)]

    def _env(self) -> dict[str, str]:
        return dict(os.environ, BALLBOT_LOG="WARNING")

    def __enter__(self) -> LivePipeline:
        from common.keys import topic
        from common.supervisor import Supervisor, stage_nice
        from common.zenoh_session import ZenohOptions, open_session

        c = ["--connect", self.endpoint, "--robot-id", self.rid]
        self.sup = sup = Supervisor(env=self._env(), nice=self.nice)  # as `up` runs them
        sup.add("router", ["run", "router", "--listen", self.endpoint, "--robot-id", self.rid])
        sup.add("rectify", ["run", "rectify", *c], nice_offset=stage_nice("rectify"))
        sup.add("disparity", ["run", "disparity", *c, "--method", self.method]
                + (["--fallback", "none"] if self.workers else []), nice_offset=stage_nice("disparity"))
        sup.add("segmenter", ["run", "segmenter", *c], nice_offset=stage_nice("segmenter"))
        for i in range(self.workers):
            sup.add(f"worker{i}", ["run", "disparity", *c, "--role", "worker", "--instance", f"bench-worker{i}",
                                   "--threads", "1", "--method", self.method], nice_offset=stage_nice("disparity"))
        sup.start_all(self.endpoint)
        self.session = open_session(ZenohOptions(mode="peer", connect=[self.endpoint], listen=["tcp/127.0.0.1:0"]))
        self.session.declare_subscriber(topic("obstacles").key(self.rid), self._on_obstacles)
        self.session.declare_subscriber(topic("stats").pattern(self.rid), self._on_stats)
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.session.close()
        finally:
            self.stop_capture()
            self.sup.stop_all()

    def _on_obstacles(self, sample) -> None:
        import msgpack

        t = time.time_ns()
        try:
            m = msgpack.unpackb(sample.payload.to_bytes())
            r = Received(t, int(m["seq"]), int(m["stamp_ns"]), int(m["publish_ns"]), bool(m["stale"]),
                         dict(m.get("stages") or {}))
        except Exception:  # not the bench's business to judge a malformed list; it is not counted
            return
        with self._lock:
            self.received.append(r)
        if r.stamp_ns >= self._want_stamp and not r.stale:
            self._first.set()

    def _on_stats(self, sample) -> None:
        import msgpack

        try:
            m = msgpack.unpackb(sample.payload.to_bytes())
            service, stamp, processed = str(m["service"]), int(m["stamp_ns"]), int(m["processed"])
        except Exception:  # not the bench's business
            return
        with self._lock:
            seen = self.processed.setdefault(service, [])
            if seen and processed < seen[-1][1]:  # restarted (capture is, per offered rate): counts from 0 again
                seen.clear()
            seen.append((stamp, processed))
            del seen[:-64]

    def processed_between(self, t0_ns: int, t1_ns: int) -> dict[str, float]:
        """Frames each service processed between two wall times, interpolated between its stats
        (sent once a second); services without stats on both sides are left out."""
        out = {}
        with self._lock:
            for service, seen in self.processed.items():
                if len(seen) < 2 or seen[0][0] > t0_ns or seen[-1][0] < t1_ns:
                    continue
                t, n = np.array([a for a, _ in seen], float), np.array([b for _, b in seen], float)
                out[service] = float(np.interp(t1_ns, t, n) - np.interp(t0_ns, t, n))
        return out

    def processes(self) -> dict[str, int]:
        sups = [self.sup] + ([self._capture] if self._capture is not None else [])
        return {c.name: c.proc.pid for s in sups for c in s.children if c.proc is not None}

    def cpu(self) -> dict[str, float]:
        """CPU s of every process so far; 'sys:<name>' the kernel's part of it."""
        out = {}
        for name, pid in self.processes().items():
            out[name] = cpu_seconds(pid)
            out[f"sys:{name}"] = cpu_seconds(pid, kernel_only=True)
        out["bench"] = time.process_time()
        return out

    @property
    def capturing(self) -> bool:
        return self._capture is not None

    def stop_capture(self) -> None:
        """Stop offering pairs: the pipeline idles (its processes stay up), so a reference measured
        now has the cores to itself, as the pipeline had them while it was measured."""
        if self._capture is not None:
            self._capture.stop_all()
            self._capture = None

    def offer(self, rate: float, timeout_s: float = 90.0) -> None:
        """(Re)start capture at `rate` pairs/s; returns once its pairs come out as obstacle lists."""
        from common.supervisor import Supervisor, stage_nice

        self.stop_capture()
        self._want_stamp = time.time_ns()
        self._first.clear()
        self._capture = Supervisor(env=self._env(), nice=self.nice)
        self._capture.add("capture", ["run", "capture", "--connect", self.endpoint, "--robot-id", self.rid,
                                      "--preload", str(self.preload), "--rate-hz", f"{rate:.3f}"],
                          nice_offset=stage_nice("capture"))
        self._capture.start_all()
        if not self._first.wait(timeout_s):
            raise RuntimeError(f"no obstacle list within {timeout_s:g} s of starting capture at {rate:.1f}/s "
                               "(run `ballbot-vision up` to see which service fails)")

    def measure(self, rate: float, warmup_s: float, seconds: float, compute_ms: float) -> dict:
        self.offer(rate)
        time.sleep(warmup_s)  # a benchmark's warm-up, not a synchronisation
        cpu0, t0 = self.cpu(), time.time_ns()
        time.sleep(seconds)
        t1, cpu1 = time.time_ns(), self.cpu()
        time.sleep(1.1)  # the stats of the window's last second (each service sends them once a second)
        with self._lock:
            window = [m for m in self.received if t0 <= m.recv_ns < t1 and m.stamp_ns >= self._want_stamp]
        r = summarize(window, (t1 - t0) / 1e9, compute_ms)
        n = max(1, r["obstacle_lists"])
        per = {k: (cpu1[k] - cpu0.get(k, 0.0)) * 1e3 / n for k in cpu1}
        r["cpu_ms_per_list"] = {k: v for k, v in per.items() if not k.startswith("sys:")}
        r["kernel_cpu_ms_per_list"] = {k[4:]: v for k, v in per.items() if k.startswith("sys:")}
        # Per frame each stage processed: unlike per list, not inflated by pairs a later stage
        # dropped, so it still tells a stage's own cost when a busy machine makes a rate unsustainable.
        frames = self.processed_between(t0, t1)
        r["cpu_ms_per_frame_processed"] = {k: (cpu1[k] - cpu0.get(k, 0.0)) * 1e3 / n for k, n in frames.items()
                                           if k in cpu1 and n >= 1}
        r["offered_hz"] = rate
        self.stop_capture()
        return r
