"""Issue 11's probes against the real processes (`ballbot-vision up`, real Zenoh): a future-stamped
garbage frame, a replayed map stamped an hour ahead, a ghost worker token, a peer whose callback
takes 1 s, a burst of hostile payloads with the services' RSS measured before and after, a wall
clock stepped back and forward (simulated through the services' injectable clock), and the thesis
rate on two busy cores with a CPU hog.

Each probe checks what it must not cost (the obstacle stream goes on, fresh) and that the service
counted what it refused. Measurements are printed (pytest -s shows them)."""
from __future__ import annotations

import os
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import pytest
import zenoh
from helpers import Up

from common import codec
from common.keys import topic
from common.messages import SCHEMA_VERSION, DisparityMap, ObstacleList, ServiceStats

pytestmark = pytest.mark.system


class Stream:
    """Obstacle lists with their arrival time (monotonic), and the latest stats per instance."""

    def __init__(self) -> None:
        self.lists: list[tuple[float, ObstacleList]] = []
        self.stats: dict[str, ServiceStats] = {}
        self.cond = threading.Condition()

    def on_obstacles(self, sample) -> None:
        msg = codec.decode(sample.payload.to_bytes(), ObstacleList)
        with self.cond:
            self.lists.append((time.monotonic(), msg))
            self.cond.notify_all()

    def on_stats(self, sample) -> None:
        st = codec.decode(sample.payload.to_bytes(), ServiceStats)
        with self.cond:
            self.stats[st.role or st.service] = st
            self.cond.notify_all()

    def wait(self, pred, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                r = pred()
                if r:
                    return r
                left = deadline - time.monotonic()
                if left <= 0:
                    last = self.lists[-1][1] if self.lists else None
                    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}; last list: "
                                f"{last and (last.seq, last.stale)}; stats: "
                                f"{ {k: (s.health, s.status) for k, s in self.stats.items()} }")
                self.cond.wait(min(left, 0.5))

    def fresh(self, after: float = 0.0, before: float = float("inf")) -> list[tuple[float, ObstacleList]]:
        with self.cond:
            return [(t, m) for t, m in self.lists if after <= t <= before and not m.stale]

    def new(self, after: float = 0.0, before: float = float("inf")) -> list[tuple[float, ObstacleList]]:
        """Lists of a frame not published before: the stream's progress. (The heartbeat's stale
        repeats of the last list are not; a list marked stale because the machine is too loaded
        to keep its age under 0.5 s is.)"""
        seen: set[int] = set()
        out = []
        with self.cond:
            for t, m in self.lists:
                if m.seq not in seen and after <= t <= before:
                    out.append((t, m))
                seen.add(m.seq)
        return out

    def wait_fresh(self, n: int, after: float, timeout: float, what: str = "") -> None:
        self.wait(lambda: len(self.fresh(after)) >= n, timeout, what or f"{n} fresh obstacle lists")

    def wait_new(self, n: int, after: float, timeout: float, what: str = "") -> None:
        self.wait(lambda: len(self.new(after)) >= n, timeout, what or f"{n} new obstacle lists")

    def hold(self, seconds: float) -> None:
        """Let the pipeline run for a measured window (the window itself is the measurement)."""
        end = time.monotonic() + seconds
        with self.cond:
            while time.monotonic() < end:
                self.cond.wait(end - time.monotonic())

    def extra(self, who: str, key: str) -> float:
        with self.cond:
            st = self.stats.get(who)
            return st.extra.get(key, 0.0) if st else 0.0


def max_gap(times: list[float], start: float, end: float) -> float:
    ts = [start] + [t for t in times if start <= t <= end] + [end]
    return max(b - a for a, b in zip(ts, ts[1:]))


class Pipeline:
    def __init__(self, robot_id: str, extra_env: dict | None = None):
        self.up = Up(robot_id, extra_env)
        self.rid = robot_id
        self.stream = Stream()
        self.session = self.up.session().__enter__()
        self.subs = [self.session.declare_subscriber(topic("obstacles").key(robot_id), self.stream.on_obstacles),
                     self.session.declare_subscriber(topic("stats").pattern(robot_id), self.stream.on_stats)]

    def close(self) -> None:
        self.session.__exit__(None, None, None)
        self.up.stop()

    def key(self, name: str, **fields: str) -> str:
        return topic(name).key(self.rid, **fields)


@pytest.fixture(scope="module")
def pipeline():
    p = Pipeline("probe")
    try:
        p.stream.wait_new(10, 0.0, 180, "the pipeline to start")
        yield p
    finally:
        p.close()


def test_future_stamped_garbage_costs_only_itself(pipeline):
    """The issue's probe: 12 bytes of garbage on frames/raw whose stamp attachment says 2^64-1
    stopped rectify for good. Now it is refused before decoding and counted."""
    s, st = pipeline.session, pipeline.stream
    t0 = time.monotonic()
    s.put(pipeline.key("frames_raw"), b"\x00garbage\xff\x00", attachment=struct.pack(">Q", 2**64 - 1))
    s.put(pipeline.key("frames_raw"), b"\x01garbage\xff\x01", attachment=struct.pack(">QQQ", 2**64 - 1, 99, 1))
    st.wait_new(15, t0, 90, "new lists after the forged stamp")
    st.wait(lambda: st.extra("rectify", "in_frames_raw_future") >= 2, 30, "rectify to count 2 future stamps")
    assert st.stats["rectify"].health == "ok"


def test_a_map_replayed_an_hour_ahead_is_refused(pipeline):
    """A real DisparityMap, replayed with its stamp 1 h ahead, with and without a matching
    attachment: refused, never published as an obstacle list, and the real maps keep flowing.
    `up`'s segmenter takes only maps its dispatcher signed, so both are refused before the
    freshness gate (unsigned); the gate's own refusal of such a stamp is in test_freshness.py."""
    s, st = pipeline.session, pipeline.stream
    maps: list[DisparityMap] = []
    got = threading.Event()

    def on_map(sample) -> None:
        if not maps:
            maps.append(codec.decode(sample.payload.to_bytes(), DisparityMap))
            got.set()

    sub = s.declare_subscriber(pipeline.key("disparity"), on_map)
    assert got.wait(60), "no disparity map to replay"
    sub.undeclare()
    forged = maps[0].model_copy(update={"stamp_ns": maps[0].stamp_ns + 3600 * 10**9})
    payload = codec.encode(forged)
    def refused() -> float:
        return sum(st.extra("segmenter", f"in_disparity_{k}") for k in ("unsigned", "forged", "future"))

    before = refused()
    t0 = time.monotonic()
    s.put(pipeline.key("disparity"), payload, attachment=struct.pack(">QQQ", forged.stamp_ns, 77, 1))
    st.wait(lambda: refused() >= before + 1, 30, "the segmenter to refuse it")
    s.put(pipeline.key("disparity"), payload)
    st.wait(lambda: refused() >= before + 2, 30, "the segmenter to refuse the unattached replay")
    assert st.extra("segmenter", "in_disparity_future") == 0, "an unsigned stamp reached the freshness gate"
    st.wait_new(15, t0, 90, "new lists after the replayed map")
    assert not [m for _, m in st.lists if m.stamp_ns == forged.stamp_ns], "the replayed map became a list"


@pytest.mark.slow
def test_a_ghost_worker_token_is_quarantined_and_the_onboard_fallback_carries_on(pipeline):
    """A liveliness token on workers/ghost with nobody doing work cut fresh lists from ~30 Hz to
    2 per 10 s. Now the ghost gets one probe frame, is quarantined, and the rate holds."""
    s, st = pipeline.session, pipeline.stream
    t0 = time.monotonic()
    st.hold(6.0)
    before = len(st.new(t0)) / (time.monotonic() - t0)
    token = s.liveliness().declare_token(pipeline.key("worker", instance="ghost"))
    try:
        st.wait(lambda: "quarantined: ghost" in st.stats.get("dispatcher", ServiceStats.model_construct(
            status="")).status, 30, "the dispatcher to quarantine the ghost")
        t1 = time.monotonic()
        st.hold(10.0)
        after = len(st.new(t1)) / (time.monotonic() - t1)
        print(f"obstacle lists: {before:.1f}/s before the ghost token, {after:.1f}/s with it")
        assert after >= 0.5 * before, f"a ghost token cut the list rate from {before:.1f} to {after:.1f}/s"
        assert "quarantined: ghost" in st.stats["dispatcher"].status
        assert st.extra("dispatcher", "pool_probes") >= 1
    finally:
        token.undeclare()


def test_a_calibration_with_half_the_baseline_published_on_the_key_is_refused(pipeline):
    """The local calibration key accepted any well-formed rig from anyone: half the baseline halved
    every distance, silently. Now a jump like that is refused and the distances stay."""
    import yaml

    from common.messages import CalibrationUpdate
    from cores import camera

    st = pipeline.stream
    t0 = time.monotonic()
    st.wait_new(5, t0, 60)
    generation0, refused0 = st.extra("rectify", "calibration_generation"), st.extra("rectify", "calibration_refused")
    before = [o.distance_m for _, m in st.new(t0)[-3:] for o in m.obstacles]
    doc = camera.calibration_to_dict(camera.load_calibration("lifecam-studio"))
    doc["T"] = [t / 2 for t in doc["T"]]
    pipeline.session.put(pipeline.key("calibration"), codec.encode(CalibrationUpdate(
        robot_id=pipeline.rid, seq=0, stamp_ns=time.time_ns(), yaml=yaml.safe_dump(doc), source="an attacker")))
    st.wait(lambda: st.extra("rectify", "calibration_refused") >= refused0 + 1, 30, "rectify to refuse the calibration")
    t1 = time.monotonic()
    st.wait_new(10, t1, 60)
    after = [o.distance_m for _, m in st.new(t1)[-3:] for o in m.obstacles]
    assert st.extra("rectify", "calibration_generation") == generation0
    assert after and abs(sum(after) / len(after) - sum(before) / len(before)) < 0.1 * sum(before) / len(before)


# --- calibration is configuration (issue 25) ---------------------------------------------------------

def nearest_m(st: Stream, after: float) -> float:
    """Median over the new lists since `after` of the nearest obstacle's distance: the robot's truth."""
    import statistics

    d = [min(o.distance_m for o in m.obstacles) for _, m in st.new(after) if m.obstacles and not m.stale]
    assert d, "no fresh list with an obstacle"
    return statistics.median(d)


def publish_calibrations(pipeline: Pipeline, docs: list[dict], key: bytes | None, what: str) -> list[str]:
    """Publish each calibration (signed with key, if any) and wait until rectify took or refused it.
    -> 'taken' / 'refused' per calibration, from rectify's own counts."""
    import yaml

    from common.messages import CalibrationUpdate
    from common.signing import sign

    st = pipeline.stream
    out = []
    for i, doc in enumerate(docs):
        g0, r0 = st.extra("rectify", "calibration_generation"), st.extra("rectify", "calibration_refused")
        msg = CalibrationUpdate(robot_id=pipeline.rid, seq=i, stamp_ns=time.time_ns(), yaml=yaml.safe_dump(doc),
                                source=what)
        pipeline.session.put(pipeline.key("calibration"), codec.encode(sign(msg, key) if key else msg))
        st.wait(lambda g0=g0, r0=r0: st.extra("rectify", "calibration_generation")
                + st.extra("rectify", "calibration_refused") > g0 + r0, 30, f"rectify to take or refuse {what} {i + 1}")
        out.append("taken" if st.extra("rectify", "calibration_generation") > g0 else "refused")
    return out


def drift_steps(n: int = 18, factor: float = 0.96) -> list[dict]:
    """The issue's attack: n calibrations of the thesis rig, each baseline 4 % shorter than the last
    (each step passes a 5 % step check; together they end at 48 %)."""
    from cores import camera

    doc = camera.calibration_to_dict(camera.load_calibration("lifecam-studio"))
    out = []
    for _ in range(n):
        doc = dict(doc, T=[t * factor for t in doc["T"]])
        out.append(doc)
    return out


def run_drift(pipeline: Pipeline, key: bytes | None, label: str) -> tuple[list[str], float, float]:
    """-> (outcomes, baseline after / before from rectify's stats, nearest obstacle after / before)."""
    st = pipeline.stream
    t0 = time.monotonic()
    st.wait_new(10, t0, 90, "lists before the attack")
    b0, d0 = st.extra("rectify", "calibration_baseline_mm"), nearest_m(st, t0)
    t_attack = time.monotonic()
    outcomes = publish_calibrations(pipeline, drift_steps(), key, label)
    took_s = time.monotonic() - t_attack
    t1 = time.monotonic()
    st.wait_new(10, t1, 90, "lists after the attack")
    b1, d1 = st.extra("rectify", "calibration_baseline_mm"), nearest_m(st, t1)
    print(f"{label}: 18 x -4 % baseline in {took_s:.0f} s: {outcomes.count('taken')} taken, "
          f"{outcomes.count('refused')} refused; rectify's baseline {b0:.2f} -> {b1:.2f} mm; nearest obstacle "
          f"{d0:.2f} -> {d1:.2f} m")
    return outcomes, b1 / b0, d1 / d0


def test_unsigned_calibration_drift_is_refused_step_by_step_in_the_default_up(pipeline):
    """The issue: 18 unsigned updates of -4 % each moved the nearest obstacle from 1.77 to 0.85 m in
    the default `up`. Unsigned, every one is refused now, and counted as such."""
    u0 = pipeline.stream.extra("rectify", "calibration_unsigned_refused")
    outcomes, baseline, nearest = run_drift(pipeline, None, "unsigned drift")
    assert outcomes == ["refused"] * 18
    assert pipeline.stream.extra("rectify", "calibration_unsigned_refused") - u0 == 18
    assert baseline == 1.0 and 0.93 < nearest < 1.07


def forge_camera_frame(pipeline: Pipeline, like: bytes) -> None:
    """One raw frame marked as a camera source (an attacker's), until rectify has looked at one: it
    counts it as an error (no calibration for a camera source) or, once it took a run-time
    calibration, rectifies it (then it is on frames/rectified with the forged stamp)."""
    from common.inbox import stamp_of
    from common.messages import StereoFrame

    st = pipeline.stream
    frame = codec.decode(like, StereoFrame)
    e0 = st.stats["rectify"].errors
    stamps: set[int] = set()
    rectified = threading.Event()

    def on_rect(sample) -> None:
        if stamp_of(sample.attachment) in stamps:
            rectified.set()

    sub = pipeline.session.declare_subscriber(pipeline.key("frames_rect"), on_rect)
    try:
        deadline = time.monotonic() + 60
        n = 0
        while st.stats["rectify"].errors == e0 and not rectified.is_set() and time.monotonic() < deadline:
            # stamped 0.1 s ahead (within what rectify accepts), so the real frames that follow do
            # not displace it from rectify's newest-wins slot before rectify looks at it
            n += 1
            stamp = time.time_ns() + 100_000_000
            stamps.add(stamp)
            pipeline.session.put(pipeline.key("frames_raw"), codec.encode(frame.model_copy(
                update={"stamp_ns": stamp, "seq": frame.seq + 10**6, "source": "cameras"})),
                attachment=struct.pack(">QQQ", stamp, 4343, n))
            st.hold(0.5)
    finally:
        sub.undeclare()
    assert st.stats["rectify"].errors > e0 or rectified.is_set(), "rectify never saw the forged camera frame"


def raw_frame(pipeline: Pipeline) -> bytes:
    got: list[bytes] = []
    ev = threading.Event()

    def keep(sample) -> None:
        if not got:
            got.append(sample.payload.to_bytes())
            ev.set()

    sub = pipeline.session.declare_subscriber(pipeline.key("frames_raw"), keep)
    assert ev.wait(60), "no raw frame"
    sub.undeclare()
    return got[0]


def half_baseline() -> dict:
    from cores import camera

    doc = camera.calibration_to_dict(camera.load_calibration("lifecam-studio"))
    return dict(doc, T=[t / 2 for t in doc["T"]])


def test_a_forged_camera_frame_does_not_make_the_next_calibration_the_first(pipeline):
    """The issue: one forged raw frame marked as a camera source, then a half-baseline calibration,
    was taken at once as "the first calibration" of a real source. Now: unsigned, refused; signed
    with the robot's key, still refused (the thesis rig rectified the synthetic frames, so it is what
    rectify started with, and half of it is a 50 % jump)."""
    from common.signing import calibration_key

    st = pipeline.stream
    like = raw_frame(pipeline)
    t0 = time.monotonic()
    st.wait_new(10, t0, 90)
    b0, d0 = st.extra("rectify", "calibration_baseline_mm"), nearest_m(st, t0)
    outcomes = []
    for key in (None, calibration_key(pipeline.rid)):
        forge_camera_frame(pipeline, like)
        outcomes += publish_calibrations(pipeline, [half_baseline()], key, "half baseline after a camera frame")
    t1 = time.monotonic()
    st.wait_new(10, t1, 90)
    b1, d1 = st.extra("rectify", "calibration_baseline_mm"), nearest_m(st, t1)
    print(f"forged camera frame + half baseline (unsigned, signed): {outcomes}; rectify's baseline {b0:.2f} -> "
          f"{b1:.2f} mm; nearest obstacle {d0:.2f} -> {d1:.2f} m")
    assert outcomes == ["refused", "refused"]
    assert b1 == b0 and 0.93 < d1 / d0 < 1.07


@pytest.mark.slow
def test_signed_calibration_drift_is_bounded_by_the_calibration_rectify_started_with(pipeline):
    """The same 18 steps signed with the robot's own key (what a compromised or buggy holder of it
    would send): the first step (-4 %) is within 5 % of the calibration rectify started with and is
    taken; the second (-7.8 % in all) and every later one are refused."""
    from common.signing import calibration_key

    key = calibration_key(pipeline.rid)  # `up`'s per-run key file: the local user's
    assert key, "the test plays the local key holder: `up` keeps its key where the CLI finds it"
    outcomes, baseline, nearest = run_drift(pipeline, key, "signed drift")
    assert outcomes == ["taken"] + ["refused"] * 17
    assert baseline == pytest.approx(0.96, abs=1e-3)
    assert nearest > 0.9  # the attack aimed at 0.48


@pytest.mark.slow
def test_insecure_unsigned_calibrations_are_still_bounded_and_never_a_first_one(tmp_path):
    """With the explicit opt-in (rectify.insecure_unsigned_calibrations), unsigned updates get in, but
    only as far as a signed one would: drift bounded against the start, no forged "first" one."""
    p = Pipeline("insecure", {"BALLBOT_RECTIFY_INSECURE_UNSIGNED_CALIBRATIONS": "true"})
    try:
        p.stream.wait_new(10, 0.0, 180, "the pipeline to start")
        forge_camera_frame(p, raw_frame(p))
        race = publish_calibrations(p, [half_baseline()], None, "half baseline after a camera frame, insecure opt-in")
        print(f"forged camera frame + unsigned half baseline, insecure opt-in: {race}")
        assert race == ["refused"]
        outcomes, baseline, nearest = run_drift(p, None, "unsigned drift, insecure opt-in")
        assert outcomes == ["taken"] + ["refused"] * 17 and baseline == pytest.approx(0.96, abs=1e-3)
        assert nearest > 0.9
    finally:
        p.close()


SLOW_PEER = r"""
import sys, time
from common.keys import topic
from common.zenoh_session import ZenohOptions, open_session
rid, endpoint = sys.argv[1], sys.argv[2]
def slow(sample):
    time.sleep(1.0)  # a stuck consumer: one second per sample
with open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"])) as s:
    subs = [s.declare_subscriber(topic("frames_rect").key(rid), slow),
            s.declare_subscriber(topic("obstacles").key(rid), slow)]
    print("ready", flush=True)
    sys.stdin.read()
"""


@pytest.mark.slow
def test_a_peer_that_takes_1_s_per_sample_does_not_stall_the_obstacle_stream(pipeline):
    """With BLOCK, one such peer made 6-12 s gaps in the obstacle stream for everyone; issue 25 still
    measured 0.44-1.1 s gaps with it. Its cost to the robot: the publishers of 1.8 MB frames wait on
    its link (Zenoh's fragment deadline) and, under load, healthy subscribers lost frames. Measured
    here in alternating windows without and with the peer (the machine's load is shared by both):
    the longest gap between new lists, the rate, rectify's longest put and the frames the
    dispatcher lost."""
    import statistics

    st = pipeline.stream

    def window(seconds: float) -> dict:
        lost0 = st.extra("dispatcher", "in_frames_rect_lost")
        t0 = time.monotonic()
        puts = []
        end = t0 + seconds
        while time.monotonic() < end:
            st.hold(min(1.0, end - time.monotonic()))
            puts.append(st.extra("rectify", "out_frames_rect_put_ms_max"))
        t1 = time.monotonic()
        times = [t for t, _ in st.new(t0, t1)]
        gaps = sorted(b - a for a, b in zip([t0] + times, times + [t1]))
        return {"gap": gaps[-1], "p95": gaps[int(0.95 * (len(gaps) - 1))], "rate": len(times) / (t1 - t0),
                "put_ms": max(puts), "lost": st.extra("dispatcher", "in_frames_rect_lost") - lost0}

    base, slow = [], []
    for _ in range(2):
        base.append(window(8.0))
        peer = subprocess.Popen([sys.executable, "-c", SLOW_PEER, pipeline.rid, pipeline.up.endpoint],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            assert peer.stdout.readline().strip() == "ready"
            slow.append(window(12.0))
        finally:
            peer.stdin.close()
            peer.terminate()
            peer.wait(30)
    base.append(window(8.0))
    for name, ws in (("without the slow peer", base), ("with the slow peer", slow)):
        print(f"{name:22}: longest gap {max(w['gap'] for w in ws):.2f} s (p95 "
              f"{statistics.median(w['p95'] for w in ws):.2f} s), {statistics.mean(w['rate'] for w in ws):.1f} new "
              f"lists/s, rectify's longest put {max(w['put_ms'] for w in ws):.0f} ms, frames the dispatcher lost "
              f"{sum(w['lost'] for w in ws):.0f} in {len(ws)} windows")
    gap_base, gap_slow = max(w["gap"] for w in base), max(w["gap"] for w in slow)
    print(f"the slow peer's cost: {gap_slow - gap_base:+.2f} s on the longest gap")
    # generous on purpose: the machine's load moves both by more than the peer does
    assert gap_slow < max(1.0, gap_base + 0.5), f"the slow peer stalled the obstacle stream for {gap_slow:.2f} s"
    assert statistics.mean(w["rate"] for w in slow) > 0.6 * statistics.mean(w["rate"] for w in base)


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for pid {pid}")


def fuzz(session, rid: str, keys: list[str], rounds: int) -> int:
    """Hostile payloads on each key: random bytes, msgpack maps with huge byte strings where the
    images go (valid msgpack, invalid messages), and payloads far over the per-key caps. -> bytes sent."""
    rng = os.urandom
    noise = [rng(n) for n in (1 << 10, 1 << 20, 4 << 20)]
    big = rng(7 << 20)
    over = b"\x00" * (90 << 20)  # over every image cap (80 MB), under Zenoh's reassembly cap
    now = time.time_ns()
    img = {"width": 640, "height": 480, "channels": 1, "dtype": "uint8", "encoding": "raw", "data": big}
    doc = msgpack.packb({"schema_version": SCHEMA_VERSION, "robot_id": rid, "seq": 1, "stamp_ns": now,
                         "left": img, "right": img, "image": img, "scale": 16.0}, use_bin_type=True)
    sent = 0
    block = zenoh.CongestionControl.BLOCK
    for r in range(rounds):
        for key in keys:
            for p in noise + [doc] + ([over] if r % 10 == 0 else []):
                session.put(key, p, congestion_control=block,
                            attachment=struct.pack(">QQQ", time.time_ns(), 4242, r * 100 + len(p) % 97 + 1))
                sent += len(p)
    return sent


@pytest.mark.slow
def test_memory_stays_bounded_under_a_burst_of_hostile_payloads(pipeline):
    st, up = pipeline.stream, pipeline.up
    pids = up.child_pids()
    watched = ("router", "rectify", "disparity", "segmenter")
    t0 = time.monotonic()
    st.wait_new(10, t0, 60)
    before = {n: rss_mb(pids[n]) for n in watched}
    keys = [pipeline.key("frames_raw"), pipeline.key("frames_rect"), pipeline.key("disparity")]
    t_fuzz = time.monotonic()
    sent = fuzz(pipeline.session, pipeline.rid, keys, rounds=20)
    took = time.monotonic() - t_fuzz
    t1 = time.monotonic()
    st.wait_new(20, t1, 120, "new lists after the fuzz burst")
    st.hold(3.0)  # trimmed once a second by the services' stats thread
    after = {n: rss_mb(pids[n]) for n in watched}
    print(f"fuzz: {sent / 1e9:.2f} GB in {took:.0f} s; RSS MB before -> after: "
          + ", ".join(f"{n} {before[n]:.0f} -> {after[n]:.0f}" for n in watched))
    for n in watched:
        assert after[n] - before[n] < 80, f"{n} grew by {after[n] - before[n]:.0f} MB under fuzzing"
    assert st.extra("rectify", "in_frames_raw_oversized") >= 1 and st.extra("segmenter", "in_disparity_oversized") >= 1
    assert all(st.stats[n].health == "ok" for n in ("rectify", "dispatcher", "segmenter")), \
        {n: st.stats[n].status for n in ("rectify", "dispatcher", "segmenter")}


# --- the wall clock steps (NTP on a robot without an RTC) ---------------------------------------------

@pytest.mark.slow
def test_a_wall_clock_step_costs_no_more_than_the_frames_in_flight(tmp_path):
    """Every service reads its wall clock through one injectable clock; the fault file moves it for
    all of them at once, as an NTP step moves a robot's clock. Back 10 s froze rectify for 10 s and
    the tracker then saw 33 ms where 10 s had passed. Now: no gap, sane velocities, same ids."""
    offset = tmp_path / "clock-offset"
    offset.write_text("0")
    p = Pipeline("clock", {"BALLBOT_FAULT_CLOCK_OFFSET_FILE": str(offset)})
    st = p.stream
    try:
        st.wait_new(30, 0.0, 180, "the pipeline to start")
        for step in (-10, +10):
            t_ref = time.monotonic()
            st.hold(4.0)  # the reference: gaps this machine makes without a step
            base_gap = max_gap([t for t, _ in st.new(t_ref)], t_ref, time.monotonic())
            offset.write_text(str(float(offset.read_text()) + step))
            t_step = time.monotonic()
            st.wait_new(30, t_step + 2.0, 60, f"new lists after a {step:+d} s step")
            fresh = st.new(t_step - 2.0)
            gap = max_gap([t for t, _ in fresh], t_step - 1.0, t_step + 3.0)
            speeds = [max(abs(v) for v in o.velocity_mps) for _, m in fresh for o in m.obstacles if o.track_frames > 2]
            ids = {tuple(sorted(o.id for o in m.obstacles)) for t, m in fresh}
            print(f"clock step {step:+d} s: longest gap {gap:.2f} s ({base_gap:.2f} s before it), fastest static "
                  f"obstacle {max(speeds, default=0):.2f} m/s, id sets {ids}")
            assert gap < max(2.0, 2 * base_gap), f"a {step:+d} s clock step stopped the obstacle stream for {gap:.1f} s"
            assert max(speeds, default=0.0) < 0.5, "velocities of a static scene went wild across the step"
            assert len(ids) == 1, f"track ids changed across the step: {ids}"
        assert st.extra("rectify", "in_frames_raw_clock_steps") >= 1
    finally:
        p.close()


# --- the thesis rate on two busy cores ------------------------------------------------------------------

@pytest.mark.slow
def test_thesis_rate_on_two_cores_with_a_cpu_hog_no_stale_lists_no_id_changes(tmp_path):
    """15 fps (the thesis rate), the services started with `up --nice -10` (perception ahead of other
    work, as on a robot), then one busy loop per core competing for the CPUs: the lists stay as
    fresh as without the hog (on a quiet machine: none stale) and the two boxes keep their ids.
    The same run without the hogs is the reference: if other work already on the machine (seven
    engineers' test suites here) makes lists stale without any hog, the premise of this test
    does not hold and it skips, saying so."""
    cfg = tmp_path / "15fps.yaml"
    cfg.write_text("capture: {rate_hz: 15}\n")
    p = Pipeline("hog", {"BALLBOT_CONFIG": str(cfg), "BALLBOT_NICE": "-10"})
    hogs: list[subprocess.Popen] = []
    st = p.stream
    window_s = 30.0

    def measure(t0: float) -> tuple[list, float]:
        st.hold(window_s)
        lists = [m for t, m in list(st.lists) if t >= t0]
        return lists, len(lists) / (time.monotonic() - t0)

    try:
        st.wait_new(30, 0.0, 180, "the pipeline to start")
        quiet, quiet_rate = measure(time.monotonic())
        stale_quiet = sum(m.stale for m in quiet) / max(1, len(quiet))
        if stale_quiet > 0.01:
            pytest.skip(f"the machine is oversubscribed before the test adds its hogs: {stale_quiet:.0%} of the "
                        f"lists are stale without them ({quiet_rate:.1f} lists/s, load average "
                        f"{os.getloadavg()[0]:.0f} on {os.cpu_count()} cores); this test measures a known load")
        hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(os.cpu_count() or 2)]
        t0 = time.monotonic()
        st.wait_new(1, t0, 30)
        loaded, rate = measure(time.monotonic())
        stale = sum(m.stale for m in loaded) / max(1, len(loaded))
        ids = {tuple(sorted(o.id for o in m.obstacles)) for m in quiet + loaded}
        print(f"15 fps: {quiet_rate:.1f} lists/s, {stale_quiet:.1%} stale without the hogs; with {len(hogs)} CPU "
              f"hogs {rate:.1f} lists/s, {stale:.1%} stale; id sets {ids}")
        assert stale <= stale_quiet + 0.02, f"{stale:.1%} stale lists with a CPU hog ({stale_quiet:.1%} without)"
        assert len(ids) == 1, f"track ids changed on a static scene: {ids}"
        assert rate >= 0.5 * quiet_rate
    finally:
        for h in hogs:
            h.kill()
            h.wait()
        p.close()


# --- health is about progress ------------------------------------------------------------------------

@pytest.mark.slow
def test_health_and_healthcheck_report_a_stage_that_makes_no_progress(tmp_path):
    """A dispatcher with no worker and no fallback (input arrives, nothing is published) is degraded,
    and a rectify whose calibration fits no frame (every input fails) is failed; `healthcheck` fails
    for both, naming why, and passes for a healthy capture."""
    from helpers import cli, free_port, wait_port

    rid = "health"
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cal = tmp_path / "small.yaml"
    cal.write_text("rectified: true\nimage_size: [320, 240]\nfocal_px: 300\nprincipal_point: [160, 120]\n"
                   "baseline_m: 0.1\n")
    env = dict(os.environ, BALLBOT_LOG="WARNING")
    procs = []

    def start(*argv: str) -> None:
        procs.append(subprocess.Popen(cli("run", *argv, "--robot-id", rid), env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))

    try:
        start("router", "--listen", endpoint)
        wait_port(port, procs[0])
        start("capture", "--connect", endpoint, "--rate-hz", "10", "--preload", "4")
        start("rectify", "--connect", endpoint, "--calibration", str(cal))
        stats = Stream()
        from common.zenoh_session import ZenohOptions, open_session

        with open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"])) as s:
            s.declare_subscriber(topic("stats").pattern(rid), stats.on_stats)
            stats.wait(lambda: stats.stats.get("rectify") is not None and stats.stats["rectify"].health == "failed",
                       120, "rectify to report failed")
            assert "every input fails" in stats.stats["rectify"].status
            hc = subprocess.run(cli("healthcheck", "--service", "rectify", "--connect", endpoint, "--robot-id", rid,
                                    "--timeout", "30"), capture_output=True, text=True, timeout=120)
            assert hc.returncode == 1 and "every input fails" in hc.stderr, hc.stderr
            hc = subprocess.run(cli("healthcheck", "--service", "capture", "--connect", endpoint, "--robot-id", rid,
                                    "--timeout", "30"), capture_output=True, text=True, timeout=120)
            assert hc.returncode == 0, hc.stderr
            # the dispatcher: frames arrive (rectify publishes nothing, so feed it rectified frames directly)
            start("disparity", "--connect", endpoint, "--fallback", "none")
            frame = None
            raw = threading.Event()

            def keep(sample) -> None:
                nonlocal frame
                frame = sample.payload.to_bytes()
                raw.set()

            sub = s.declare_subscriber(topic("frames_raw").key(rid), keep)
            assert raw.wait(60)
            sub.undeclare()
            from common.messages import CameraModel, StereoFrame

            msg = codec.decode(frame, StereoFrame)
            msg.camera = CameraModel(width=msg.left.width, height=msg.left.height, focal_px=600, cx=320, cy=240,
                                     baseline_m=0.1, Q=[0.0] * 16)
            pub = s.declare_publisher(topic("frames_rect").key(rid))
            feeding = threading.Event()

            def feed() -> None:  # rectified frames at 10 Hz for as long as the check lasts
                while not feeding.wait(0.1):
                    msg.stamp_ns = time.time_ns()
                    msg.seq += 1
                    pub.put(codec.encode(msg))

            feeder = threading.Thread(target=feed, daemon=True)
            feeder.start()
            try:
                stats.wait(lambda: stats.stats.get("dispatcher") is not None
                           and stats.stats["dispatcher"].health != "ok", 120, "the dispatcher to report degraded")
                d = stats.stats["dispatcher"]
                assert d.health == "degraded" and "nothing published" in d.status, d.status
                hc = subprocess.run(cli("healthcheck", "--service", "disparity", "--connect", endpoint, "--robot-id",
                                        rid, "--timeout", "30"), capture_output=True, text=True, timeout=120)
                assert hc.returncode == 1 and "nothing published" in hc.stderr, hc.stderr
            finally:
                feeding.set()
                feeder.join(10)
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
