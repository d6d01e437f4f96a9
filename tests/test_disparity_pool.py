"""The disparity worker pool: bookkeeping without a network, then real processes over Zenoh
(three workers, one killed by PID mid-stream), then the same across two network namespaces."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid

import pytest

from bench.fleet_harness import netns_unavailable  # the one check whether this machine can make test hosts
from bench.measure import free_port
from common.errors import DecodeError
from common.supervisor import stop_processes
from services.disparity.envelope import make_attachment, parse_attachment
from services.disparity.state import DispatchState

# --- DispatchState: pure bookkeeping ----------------------------------------------------------------

class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_each_frame_goes_to_one_free_worker_and_slots_are_bounded():
    st = DispatchState(max_in_flight=1, result_timeout_s=1.0, clock=FakeClock())
    assert st.claim(1) is None  # nobody alive
    st.add_worker("a")
    st.add_worker("b")
    first, second = st.claim(1), st.claim(2)
    assert {first, second} == {"a", "b"}
    assert st.claim(3) is None  # both busy: at most max_in_flight each
    assert st.done(first, 1) == "ok"
    assert st.claim(4) == first


def test_receipts_unknown_duplicate_late_are_counted_and_never_free_a_slot():
    clock = FakeClock()
    st = DispatchState(max_in_flight=2, result_timeout_s=1.0, clock=clock)
    st.add_worker("a")
    assert st.claim(9) == "a" and st.claim(10) is None  # on probation: one probe at a time
    assert st.done("a", 9) == "ok"                        # proven: two slots from now on
    assert st.claim(10) == "a" and st.claim(11) == "a"
    assert st.done("a", 10) == "ok"
    assert st.done("a", 10) == "duplicate"          # a worker that answers twice
    assert st.done("a", 99) == "unknown_frame"      # never sent
    assert st.done("ghost", 11) == "unknown_worker"
    clock.t += 1.5
    assert st.expire() == [("a", 11)]               # overdue: slot freed, worker paused
    assert not st.has_free()
    assert st.done("a", 11) == "late"               # it answers after all: back in rotation
    assert st.has_free()
    c = st.counters
    assert (c["completed"], c["duplicate"], c["unknown_frame"], c["unknown_worker"], c["timeouts"], c["late"]) \
        == (2, 1, 1, 1, 1, 1)


def test_a_removed_worker_costs_only_its_in_flight_frames():
    st = DispatchState(max_in_flight=1, clock=FakeClock())
    for w in "abc":
        st.add_worker(w)
    owners = {st.claim(s): s for s in (1, 2, 3)}
    assert st.remove_worker("b") == 1
    assert st.counters["lost_in_flight"] == 1
    assert st.done("b", owners["b"]) == "unknown_worker"
    assert st.done("a", owners["a"]) == "ok"
    assert st.claim(4) == "a"


def test_a_token_alone_is_not_a_worker_a_ghost_is_quarantined_and_probed_with_backoff():
    clock = FakeClock()
    st = DispatchState(max_in_flight=2, result_timeout_s=1.0, clock=clock)
    st.add_worker("ghost")
    assert st.trusted() == 0 and st.alive() == 1  # the fallback keeps computing
    assert st.claim(1) == "ghost"                  # one probe frame
    assert st.claim(2) is None
    clock.t += 1.1
    assert st.expire() == [("ghost", 1)]
    assert st.workers["ghost"].trust == "quarantined" and st.counters["quarantined"] == 1
    assert st.claim(3) is None                     # no work during the backoff
    backoffs = []
    for seq in range(4, 9):                        # each unanswered probe doubles the wait
        t0 = clock.t
        while st.claim(seq) is None:
            clock.t += 0.25
        backoffs.append(clock.t - t0)
        clock.t += 1.1
        st.expire()
    assert backoffs[0] < backoffs[1] < backoffs[2], backoffs
    assert st.trusted() == 0


def test_a_quarantined_worker_that_answers_a_probe_is_trusted_again():
    clock = FakeClock()
    st = DispatchState(max_in_flight=1, result_timeout_s=1.0, clock=clock, strikes_to_quarantine=2)
    st.add_worker("w")
    assert st.claim(1) == "w" and st.done("w", 1) == "ok" and st.trusted() == 1
    for seq in (2, 3):                             # takes work, returns nothing
        while st.claim(seq) is None:
            clock.t += 0.1
        clock.t += 1.1
        st.expire()
    assert st.trusted() == 0 and st.workers["w"].trust == "quarantined"
    while st.claim(4) is None:
        clock.t += 0.1
    assert st.done("w", 4) == "ok" and st.trusted() == 1


def test_a_receipt_or_grant_naming_another_worker_is_counted_and_dropped():
    """One worker must not answer for another: what comes on b's key must name b."""
    from common import codec
    from common.messages import PoolGrant, WorkDone
    from common.node import Node
    from common.zenoh_session import ZenohOptions
    from services.disparity.answers import decode_from_worker

    node = Node("disparity", ZenohOptions(), "r", install_signal_handlers=False)
    done = codec.encode(WorkDone(robot_id="r", seq=3, stamp_ns=1, worker="host-b", ok=False, reason="too_old"))
    assert decode_from_worker(node, done, WorkDone, "receipt", "b", "host-b").seq == 3
    assert decode_from_worker(node, done, WorkDone, "receipt", "a", "host-a") is None
    assert node.extra["receipts_misnamed"] == 1 and node.decode_errors == 0
    grant = codec.encode(PoolGrant(robot_id="r", seq=1, stamp_ns=1, worker="host-b", grant="ab" * 8, ttl_ms=500))
    assert decode_from_worker(node, grant, PoolGrant, "grant", "a", "host-a") is None
    assert decode_from_worker(node, done[:-3], WorkDone, "receipt", "b", "host-b") is None  # truncated
    assert node.extra["grants_misnamed"] == 1 and node.decode_errors == 1


def test_failed_receipts_quarantine_a_worker_that_fails_every_frame():
    st = DispatchState(max_in_flight=1, clock=FakeClock(), strikes_to_quarantine=3)
    st.add_worker("w")
    assert st.claim(1) == "w" and st.done("w", 1) == "ok"
    for seq in (2, 3, 4):
        assert st.claim(seq) == "w" and st.done("w", seq, ok=False) == "failed"
    assert st.workers["w"].trust == "quarantined" and st.trusted() == 0


def test_receipt_timeouts_adapt_to_a_slow_worker():
    """A worker that needs 2.5 s per frame on a loaded machine: its late receipts teach the
    dispatcher to wait longer instead of quarantining it."""
    clock = FakeClock()
    st = DispatchState(max_in_flight=1, result_timeout_s=1.0, clock=clock)
    st.add_worker("slow")
    assert st.claim(1) == "slow"
    clock.t += 2.5
    assert st.expire() == [("slow", 1)]
    assert st.done("slow", 1) == "late"           # it did answer, 2.5 s after the send
    assert st.timeout_for(st.workers["slow"]) >= 2.5 * 3 - 1e-9
    timeouts = st.counters["timeouts"]
    for seq in range(2, 12):
        while st.claim(seq) is None:
            clock.t += 0.1
        clock.t += 2.5
        assert st.expire() == []
        assert st.done("slow", seq) == "ok"
    assert st.counters["timeouts"] == timeouts and st.trusted() == 1


def test_frames_to_workers_png_is_lossless_jpeg_is_smaller():
    import numpy as np

    from common import codec
    from common.messages import CameraModel, StereoFrame
    from services.disparity.computer import reencode_frame

    rng = np.random.default_rng(0)
    img = cv2_blur(rng.integers(0, 255, (120, 160), dtype=np.uint8))
    cam = CameraModel(width=160, height=120, focal_px=100, cx=80, cy=60, baseline_m=0.1, Q=[0.0] * 16)
    f = StereoFrame(robot_id="r", seq=1, stamp_ns=1, left=codec.image_from_array(img),
                    right=codec.image_from_array(img), camera=cam)
    png, jpeg = reencode_frame(f, "png"), reencode_frame(f, "jpeg", 80)
    assert png.left.encoding == "png" and np.array_equal(codec.array_from_image(png.left), img)
    assert len(jpeg.left.data) < len(png.left.data) < len(f.left.data)
    assert np.abs(codec.array_from_image(jpeg.right).astype(int) - img).mean() < 4
    assert reencode_frame(f, "raw") is f and (png.seq, png.camera) == (f.seq, f.camera)


def cv2_blur(a):
    import cv2

    return cv2.GaussianBlur(a, (5, 5), 1.5)


def test_attachment_round_trip_and_garbage():
    nonce = os.urandom(16)
    assert parse_attachment(make_attachment(12.5, 500, nonce)) == (12.5, 500.0, nonce)
    assert parse_attachment(None) == (0.0, float("inf"), b"")
    with pytest.raises(DecodeError):
        parse_attachment(b"\xc1garbage")
    with pytest.raises(DecodeError, match="nonce"):
        parse_attachment(make_attachment(1, 2, b"x" * 1000))


# --- real processes ------------------------------------------------------------------------------

PY = sys.executable

COLLECTOR = r"""
import json, sys, time, threading, zenoh
from common import codec
from common.keys import topic
from common.messages import DisparityMap, ObstacleList, ServiceStats
from common.zenoh_session import ZenohOptions, open_session
rid, endpoint = sys.argv[1], sys.argv[2]
lock = threading.Lock()
def emit(**kw):
    kw["t"] = time.time()
    with lock:
        sys.stdout.write(json.dumps(kw) + "\n"); sys.stdout.flush()
def on_disp(s):
    m = codec.decode(s.payload.to_bytes(), DisparityMap)
    emit(k="D", seq=m.seq, worker=m.worker, method=m.method)
def on_obs(s):
    m = codec.decode(s.payload.to_bytes(), ObstacleList)
    emit(k="O", seq=m.seq, stale=m.stale)
def on_tok(s):
    emit(k="L", up=s.kind == zenoh.SampleKind.PUT, name=str(s.key_expr).rsplit("/", 1)[-1])
def on_stats(s):
    m = codec.decode(s.payload.to_bytes(), ServiceStats)
    if m.service == "disparity":
        emit(k="S", instance=m.instance, status=m.status, extra=m.extra, decode_errors=m.decode_errors)
with open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=[])) as s:
    subs = [s.declare_subscriber(topic("disparity").key(rid), on_disp),
            s.declare_subscriber(topic("obstacles").key(rid), on_obs),
            s.declare_subscriber(topic("stats").pattern(rid), on_stats),
            s.liveliness().declare_subscriber(topic("worker").pattern(rid), on_tok, history=True)]
    emit(k="ready")
    sys.stdin.read()  # until the test closes stdin
"""

INJECT = r"""
import sys, time, msgpack
from common import codec
from common.keys import topic
from common.messages import WorkDone
from common.zenoh_session import ZenohOptions, open_session
rid, endpoint, worker = sys.argv[1], sys.argv[2], sys.argv[3]
with open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=[])) as s:
    time.sleep(0.5)  # let the declarations propagate (a helper process, not the test)
    s.put(topic("work").key(rid, instance=worker), b"\x00garbage work item")
    s.put(topic("work").key(rid, instance=worker), b"\x81\xa1a\x01", attachment=b"not msgpack\xc1")
    s.put(topic("work_done").key(rid, instance=worker), b"garbage receipt")
    for seq in (10**9, 10**9):  # a receipt for a frame never sent, twice
        s.put(topic("work_done").key(rid, instance=worker),
              codec.encode(WorkDone(robot_id=rid, seq=seq, stamp_ns=0, worker=worker, ok=True)))
    s.put(topic("work_done").key(rid, instance="ghost"),
          codec.encode(WorkDone(robot_id=rid, seq=1, stamp_ns=0, worker="ghost", ok=True)))
    time.sleep(0.5)
"""


class Procs:
    """Processes this test started; all stopped (by pid) on exit, even on failure."""

    logdir: str | None = None  # set per test: each service's stderr goes to <logdir>/<name>.log

    def __init__(self, prefix: list[str] | None = None):
        self.prefix = prefix or []
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, argv: list[str], **kw) -> subprocess.Popen:
        env = dict(os.environ, BALLBOT_LOG="WARNING", PYTHONUNBUFFERED="1")
        p = subprocess.Popen(self.prefix + argv, env=env, **kw)
        self.procs[name] = p
        return p

    def service(self, name: str, *args: str) -> subprocess.Popen:
        err = open(os.path.join(Procs.logdir, f"{name}.log"), "w") if Procs.logdir else subprocess.DEVNULL
        return self.start(name, [PY, "-m", "ballbot_vision.cli", "run", *args], stdout=subprocess.DEVNULL, stderr=err)

    def stop_all(self) -> None:
        stop_processes(self.procs, 5.0)


class Collector:
    """Reads the collector subprocess's JSON lines into a list; wait_for(pred) polls with a deadline."""

    def __init__(self, procs: Procs, rid: str, endpoint: str):
        self.events: list[dict] = []
        self.cond = threading.Condition()
        self.p = procs.start("collector", [PY, "-c", COLLECTOR, rid, endpoint], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.p.stdout:
            with self.cond:
                self.events.append(json.loads(line))
                self.cond.notify_all()

    def wait_for(self, pred, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                r = pred(self.events)
                if r:
                    return r
                left = deadline - time.monotonic()
                if left <= 0 or self.p.poll() is not None:
                    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}; "
                                f"last events: {self.events[-5:]}; service logs in {Procs.logdir}")
                self.cond.wait(min(left, 0.5))

    def of(self, kind: str) -> list[dict]:
        with self.cond:
            return [e for e in self.events if e["k"] == kind]


def alive_workers(events: list[dict]) -> set[str]:
    alive: set[str] = set()
    for e in events:
        if e["k"] == "L":
            (alive.add if e["up"] else alive.discard)(e["name"])
    return alive


def start_robot(procs: Procs, rid: str, endpoint: str, listen: str, rate: float = 15.0,
                fallback: str = "none", transport: str = "raw") -> None:
    common = ["--robot-id", rid]
    procs.service("router", "router", "--listen", listen, *common)
    host, port = listen[4:].rsplit(":", 1)
    deadline = time.monotonic() + 20
    host = endpoint[4:].rsplit(":", 1)[0]
    probe = procs.prefix + [PY, "-c", f"import socket; socket.create_connection(('{host}', {port}), 1).close()"]
    while subprocess.run(probe, stderr=subprocess.DEVNULL).returncode != 0:
        assert time.monotonic() < deadline, "router did not start listening"
        time.sleep(0.1)  # polling a TCP port for the router to come up (no event to wait on)
    c = ["--connect", endpoint, *common]
    procs.service("capture", "capture", *c, "--rate-hz", str(rate), "--preload", "6")
    procs.service("rectify", "rectify", *c)
    procs.service("dispatch", "disparity", *c, "--fallback", fallback, "--max-age-ms", "1000",
                  "--transport", transport)
    procs.service("segmenter", "segmenter", *c)


def check_kill_continuity(col: Collector, procs: Procs, workers: list[str]) -> dict:
    """Waits for every worker to produce, kills one by PID, checks the stream goes on."""
    col.wait_for(lambda ev: alive_workers(ev) >= set(workers), 90, f"worker tokens {workers}")
    col.wait_for(lambda ev: {e["worker"] for e in ev if e["k"] == "D"} >= set(workers), 90,
                 "disparity maps from every worker")
    col.wait_for(lambda ev: sum(1 for e in ev if e["k"] == "O" and not e["stale"]) >= 15, 60,
                 "a steady obstacle stream (the segmenter warms up on its first frames)")
    victim = workers[0]
    t_kill = time.time()
    procs.procs[victim].send_signal(signal.SIGKILL)
    procs.procs[victim].wait()
    col.wait_for(lambda ev: victim not in alive_workers(ev), 5, f"{victim}'s token to vanish")
    t_gone = time.time()
    print(f"killed worker's token gone after {(t_gone - t_kill) * 1e3:.0f} ms")
    survivors = set(workers[1:])
    col.wait_for(lambda ev: {e["worker"] for e in ev if e["k"] == "D" and e["t"] > t_kill + 2} >= survivors
                 and any(e["k"] == "O" and not e["stale"] and e["t"] > t_kill + 3 for e in ev), 60,
                 "the survivors to carry the stream for 3 s after the kill")
    d = [e for e in col.of("D")]
    o = [e for e in col.of("O") if not e["stale"]]
    window = lambda es: [e["t"] for e in es if t_kill - 0.5 <= e["t"] <= t_kill + 3]  # noqa: E731
    for name, es in (("disparity", d), ("obstacles", o)):
        ts = [t_kill] + window(es)
        gap = max(b - a for a, b in zip(ts, ts[1:]))
        print(f"{name}: longest gap around the kill {gap * 1e3:.0f} ms")
        assert gap < 1.0, f"{name} stream stopped for {gap:.2f} s around the kill"
    seqs = [e["seq"] for e in d]
    assert len(seqs) == len(set(seqs)), "a seq was published twice on disparity"
    oseq = [e["seq"] for e in o]
    assert all(b > a for a, b in zip(oseq, oseq[1:])), "the obstacle stream went backwards"
    assert not [e for e in d if e["worker"] == victim and e["t"] > t_gone + 0.5]
    return {"t_kill": t_kill, "token_gone_s": t_gone - t_kill}


@pytest.fixture(autouse=True)
def _service_logs(tmp_path):
    Procs.logdir = str(tmp_path)
    yield
    Procs.logdir = None


@pytest.mark.slow
@pytest.mark.system
def test_three_worker_processes_survive_a_kill_and_garbage():
    rid = f"pool{uuid.uuid4().hex[:6]}"
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    procs = Procs()
    workers = [f"w{i}-{rid}" for i in range(3)]
    try:
        start_robot(procs, rid, endpoint, endpoint)
        col = Collector(procs, rid, endpoint)
        for w in workers:
            procs.service(w, "disparity", "--role", "worker", "--instance", w, "--connect", endpoint,
                          "--robot-id", rid, "--threads", "1")
        check_kill_continuity(col, procs, workers)
        # bytes per second on each link, in the stats of both ends
        col.wait_for(lambda ev: any(e["k"] == "S" and any(k.startswith("rate_out_work_") and v > 1e5
                                                          for k, v in e["extra"].items()) for e in ev), 15,
                     "the dispatcher's per-worker link rate in its stats")
        col.wait_for(lambda ev: any(e["k"] == "S" and e["extra"].get("rate_in_work_Bps", 0) > 1e5 for e in ev), 15,
                     "a worker's incoming link rate in its stats")
        # garbage work items and receipts: logged, counted, dropped; nothing stalls
        t_inject = time.time()
        inj = procs.start("inject", [PY, "-c", INJECT, rid, endpoint, workers[1]])
        assert inj.wait(60) == 0
        col.wait_for(lambda ev: any(e["k"] == "S" and e["extra"].get("pool_unknown_frame", 0) >= 1
                                    and e["extra"].get("pool_duplicate", 0)
                                    + e["extra"].get("pool_unknown_frame", 0) >= 2
                                    and e["extra"].get("pool_unknown_worker", 0) >= 1 and e["decode_errors"] >= 1
                                    for e in ev), 30, "the dispatcher to count bad receipts")
        col.wait_for(lambda ev: any(e["k"] == "S" and e["instance"] == workers[1] and e["decode_errors"] >= 2
                                    for e in ev), 30, "the worker to count bad work items")
        col.wait_for(lambda ev: sum(1 for e in ev if e["k"] == "D" and e["worker"] == workers[1]
                                    and e["t"] > t_inject + 1) >= 3, 30, "the garbage-fed worker to keep working")
        # a frozen host (SIGSTOP): dropped after the 2 s lease, not Zenoh's default 10 s
        frozen = procs.procs[workers[1]]
        t_stop = time.time()
        frozen.send_signal(signal.SIGSTOP)
        col.wait_for(lambda ev: workers[1] not in alive_workers(ev), 15, "the frozen worker's token to expire")
        detected = time.time() - t_stop
        print(f"frozen worker noticed after {detected:.2f} s")
        assert detected < 2.0 + 1.5, f"a frozen worker was noticed only after {detected:.1f} s (lease 2 s)"
        col.wait_for(lambda ev: sum(1 for e in ev if e["k"] == "D" and e["worker"] == workers[2]
                                    and e["t"] > t_stop + detected) >= 3, 30, "the last worker to carry on")
        # nobody left: the dispatcher says so and the obstacle stream marks itself stale
        frozen.kill()
        procs.procs[workers[2]].kill()
        t_none = time.time()
        col.wait_for(lambda ev: any(e["k"] == "S" and e["status"] == "no worker reachable" and e["t"] > t_none
                                    for e in ev), 15, "status 'no worker reachable'")
        col.wait_for(lambda ev: any(e["k"] == "O" and e["stale"] and e["t"] > t_none for e in ev), 15,
                     "a stale obstacle list")
    finally:
        procs.stop_all()


# --- two hosts: network namespaces joined by a veth pair --------------------------------------------

@pytest.mark.slow
@pytest.mark.system
def test_workers_in_another_network_namespace_survive_a_kill():
    why = netns_unavailable()
    if why:
        pytest.skip(why)
    tag = uuid.uuid4().hex[:5]
    robot, off = f"bbrobot{tag}", f"bboff{tag}"
    veth_r, veth_o = f"bbr{tag}", f"bbo{tag}"
    octet = 16 + int(tag, 16) % 200  # a private /30 on our own veth pair only
    ip_r, ip_o = f"10.231.{octet}.1", f"10.231.{octet}.2"

    def sh(*args: str) -> None:
        subprocess.run(list(args), check=True, capture_output=True)

    created: list[str] = []
    procs_r, procs_o = Procs(["ip", "netns", "exec", robot]), Procs(["ip", "netns", "exec", off])
    try:
        for ns in (robot, off):
            sh("ip", "netns", "add", ns)
            created.append(ns)
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        sh("ip", "link", "add", veth_r, "netns", robot, "type", "veth", "peer", "name", veth_o, "netns", off)
        sh("ip", "-n", robot, "addr", "add", f"{ip_r}/30", "dev", veth_r)
        sh("ip", "-n", off, "addr", "add", f"{ip_o}/30", "dev", veth_o)
        sh("ip", "-n", robot, "link", "set", veth_r, "up")
        sh("ip", "-n", off, "link", "set", veth_o, "up")
        rid = f"ns{tag}"
        port = 7447
        endpoint = f"tcp/{ip_r}:{port}"
        start_robot(procs_r, rid, f"tcp/127.0.0.1:{port}", f"tcp/0.0.0.0:{port}", fallback="half",
                    transport="png")  # a narrow link: lossless png both ways
        col = Collector(procs_r, rid, f"tcp/127.0.0.1:{port}")
        workers = [f"w{i}-{rid}" for i in range(3)]
        for w in workers:  # offboard: clients of the robot's router, across the veth link
            procs_o.service(w, "disparity", "--role", "worker", "--instance", w, "--mode", "client",
                            "--connect", endpoint, "--robot-id", rid, "--threads", "1", "--result-encoding", "png")
        procs_r.procs.update(procs_o.procs)  # so check_kill_continuity can find the victim
        check_kill_continuity(col, procs_r, workers)
        # cut the link: the offboard workers are dropped after the lease and the robot's half-resolution
        # onboard fallback takes over, so the robot is not blind
        t_cut = time.time()
        sh("ip", "-n", robot, "link", "set", veth_r, "down")
        col.wait_for(lambda ev: not alive_workers(ev), 15, "the cut-off workers' tokens to expire")
        detected = time.time() - t_cut
        print(f"cut-off host noticed after {detected:.2f} s")
        assert detected < 2.0 + 1.5, f"a cut-off host was noticed only after {detected:.1f} s (lease 2 s)"
        col.wait_for(lambda ev: sum(1 for e in ev if e["k"] == "D" and "onboard" in e["method"]
                                    and e["t"] > t_cut) >= 3, 20, "the onboard fallback to take over")
        o = [e["seq"] for e in col.of("O") if not e["stale"]]
        assert all(b > a for a, b in zip(o, o[1:])), "the obstacle stream went backwards"
        t_all = min(e["t"] for e in col.of("D") if "onboard" not in e["method"])
        onboard_while_workers = [e for e in col.of("D") if "onboard" in e["method"] and t_all + 0.5 < e["t"] < t_cut]
        assert not onboard_while_workers, "the onboard fallback ran while offboard workers were alive"
    finally:
        procs_r.stop_all()
        procs_o.stop_all()
        for ns in created:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def test_a_workers_queue_is_bounded_in_items_and_bytes():
    from services.disparity.worker import WorkQueue

    q = WorkQueue(capacity=3, max_bytes=10 << 20)
    for i in range(5):
        q.offer(bytes([i]) * 100, None)
    assert [q.take(0)[0][0] for _ in range(3)] == [2, 3, 4] and q.overflowed == 2
    for i in range(4):
        q.offer(bytes([i]) * (4 << 20), None)  # a misbehaving sender's large items
    assert q.overflowed == 4 and q.take(0)[0][0] == 2 and q.take(0)[0][0] == 3 and q.take(0) is None
