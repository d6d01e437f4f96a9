"""`ballbot-vision bench fleet`: several robots sharing one pool of disparity workers
(services/disparity/fleet.py), per robot against its fair share.

What runs: a router; per robot its disparity dispatcher (`run disparity --pool fleet`, no onboard
fallback, so every map is the pool's) fed rectified synthetic 640x480 pairs by this bench (one feeder
thread per robot: four full capture/rectify/segmenter pipelines do not fit a 2-core machine beside the
workers, and the pool is what is measured); sgbm pool workers with one OpenCV thread each, each in
its own network namespace joined to the router's by a veth pair (`ip netns`, as root; otherwise on
loopback, and the report says why). The maps are counted per robot on `ballbot/<robot>/disparity`,
where each robot's dispatcher republishes what it checked.

Phases, each measured on its own:
  equal   every robot offers twice its share (at least 8 pairs/s): maps/s per robot against total/N and ceiling/N
  alone   the last robot alone, offering half its share: its single-robot latency
  flood   robot 0 offers 4x (its dispatcher may hold 8 items per worker) and frames without grants
          are put on the workers' keys in its name; the middle robots offer twice their share, the
          last robot half of it (within its share): it must get all it offers at no more than
          1.5 x its single-robot latency, and the flood no more than the middle robots' share
  kill    a worker is SIGKILLed: per robot, the time until its rate is back at the new share
  add     a worker joins: the time until it computes its first map, and the shares after

The workers' ceiling is the in-process one-thread sgbm rate on the same pairs, measured in this run
before and after the pool phases, times min(workers, cores).

    ballbot-vision bench fleet            # or: python -m bench.fleet --robots 4 --workers 2
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import msgpack
import numpy as np

from bench.measure import free_port, percentiles
from common.errors import BallbotError

if TYPE_CHECKING:
    import zenoh

PY = sys.executable
POOL = "fleet"
TARGET_SHARE = 0.9  # every robot >= 0.9 x its fair share; total >= 0.9 x the workers' ceiling
TARGET_RECOVER_S = 1.0  # after a kill: every robot back at its new share within 1 s; a new worker used within 1 s
TARGET_LATENCY_X = 1.5  # a robot's latency within 1.5 x the single-robot figure


def netns_unavailable() -> str | None:
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "needs root (ip netns)"
    if not shutil.which("ip"):
        return "needs the `ip` tool (iproute2)"
    probe = f"bbprobe{uuid.uuid4().hex[:6]}"
    r = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if r.returncode != 0:
        return f"cannot create a network namespace here: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


@dataclass
class Map:
    robot: str
    seq: int
    worker: str
    t: float  # monotonic arrival
    latency_ms: float
    method: str = ""


@dataclass
class Fleet:
    """The processes of one fleet run; everything started is stopped (by pid) and every namespace
    deleted on exit, even on failure. Maps arrive in `maps`, pool worker tokens in `tokens`."""

    robots: list[str]
    method: str = "sgbm"
    netns: bool = True
    greedy: dict[str, int] = field(default_factory=dict)  # robot -> its dispatcher's max_in_flight
    fallback: dict[str, str] = field(default_factory=dict)  # robot -> its onboard fallback (default none)
    weights: str = ""
    logdir: str | None = None
    max_age_ms: float = 2000.0

    def __post_init__(self) -> None:
        self.procs: dict[str, subprocess.Popen] = {}
        self.namespaces: list[str] = []
        self.maps: list[Map] = []
        self.tokens: list[tuple[float, str, bool]] = []  # (t, worker, up)
        self.stats: dict[str, dict] = {}
        self.proc_ms: list[tuple[float, float]] = []  # (t, a pool worker's compute time per map, median of 1 s)
        self.lock = threading.Lock()
        self.tag = uuid.uuid4().hex[:5]
        self.rates: dict[str, float] = {r: 0.0 for r in self.robots}
        self.stop = threading.Event()
        self._session: zenoh.Session | None = None
        self.netns_reason = netns_unavailable() if self.netns else "not asked for (--no-netns)"
        self.use_netns = self.netns_reason is None
        self._octet = 16 + int(self.tag, 16) % 100

    # -- processes --------------------------------------------------------------------------------
    def _start(self, name: str, argv: list[str], prefix: list[str] | None = None) -> subprocess.Popen:
        env = dict(os.environ, BALLBOT_LOG=os.environ.get("BALLBOT_LOG", "WARNING"), PYTHONUNBUFFERED="1",
                   PYTHONFAULTHANDLER="1")  # a process that must be looked into: SIGABRT prints its threads
        env.setdefault("BALLBOT_CALIBRATION_KEY", os.urandom(32).hex())
        err = open(os.path.join(self.logdir, f"{name}.log"), "w") if self.logdir else subprocess.DEVNULL
        p = subprocess.Popen((prefix or []) + [PY, "-m", "ballbot_vision.cli", "run", *argv], env=env,
                             stdout=subprocess.DEVNULL, stderr=err)
        self.procs[name] = p
        return p

    def _sh(self, *args: str) -> None:
        subprocess.run(list(args), check=True, capture_output=True)

    def _namespace(self, i: int) -> tuple[list[str], str]:
        """A fresh namespace joined to ours by a veth pair -> (command prefix, the router's address
        seen from it)."""
        ns = f"bbfl{self.tag}{i}"
        here, there = f"bbh{self.tag}{i}", f"bbt{self.tag}{i}"
        a, b = f"10.{self._octet}.{i}.1", f"10.{self._octet}.{i}.2"
        self._sh("ip", "netns", "add", ns)
        self.namespaces.append(ns)
        self._sh("ip", "-n", ns, "link", "set", "lo", "up")
        self._sh("ip", "link", "add", here, "type", "veth", "peer", "name", there, "netns", ns)
        self._sh("ip", "addr", "add", f"{a}/30", "dev", here)
        self._sh("ip", "link", "set", here, "up")
        self._sh("ip", "-n", ns, "addr", "add", f"{b}/30", "dev", there)
        self._sh("ip", "-n", ns, "link", "set", there, "up")
        return ["ip", "netns", "exec", ns], a

    def __enter__(self) -> Fleet:
        from common.zenoh_session import ZenohOptions, open_session

        self.port = free_port()
        listen = f"tcp/0.0.0.0:{self.port}" if self.use_netns else f"tcp/127.0.0.1:{self.port}"
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        try:
            self._start("router", ["router", "--listen", listen])
            self._wait_port()
            for r in self.robots:
                self._start(f"dispatch-{r}", ["disparity", "--connect", self.endpoint, "--robot-id", r, "--pool", POOL,
                                              "--fallback", self.fallback.get(r, "none"),
                                              "--max-age-ms", f"{self.max_age_ms:g}",
                                              "--method", self.method,
                                              "--max-in-flight", str(self.greedy.get(r, 2))])
            self._session = open_session(ZenohOptions(mode="peer", connect=[self.endpoint], listen=[]))
            self._subscribe()
            self.frames = _frames()
            for r in self.robots:
                threading.Thread(target=self._feed, args=(r,), daemon=True, name=f"feed-{r}").start()
        except BaseException:
            self.__exit__()
            raise
        return self

    def _wait_port(self, timeout: float = 30.0) -> None:
        import socket

        deadline = time.monotonic() + timeout
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), 0.5).close()
                return
            except OSError:
                if time.monotonic() > deadline or self.procs["router"].poll() is not None:
                    raise RuntimeError(f"the router did not listen on port {self.port}") from None
                time.sleep(0.1)  # polling a TCP port for the router to come up (no event to wait on)

    def add_worker(self, name: str, *extra: str) -> None:
        i = sum(1 for n in self.procs if n.startswith("worker"))
        prefix, address = self._namespace(i) if self.use_netns else ([], "127.0.0.1")
        mode = ["--mode", "client"] if self.use_netns else []
        self._start(f"worker-{name}", ["disparity", "--role", "worker", "--pool", POOL, "--instance", name, *mode,
                                       "--connect", f"tcp/{address}:{self.port}", "--threads", "1",
                                       "--method", self.method, *(["--pool-weights", self.weights] if self.weights
                                                                  else []), *extra], prefix)

    def kill_worker(self, name: str) -> float:
        p = self.procs[f"worker-{name}"]
        t = time.monotonic()
        p.send_signal(signal.SIGKILL)
        p.wait()
        return t

    @property
    def session(self) -> zenoh.Session:
        """The bench's own Zenoh session, open inside `with fleet:` only."""
        if self._session is None:
            raise BallbotError("fleet bench: no Zenoh session outside `with fleet:`")
        return self._session

    def __exit__(self, *exc) -> None:
        self.stop.set()
        if self._session is not None:
            try:
                self._session.close()
            except Exception:
                pass
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 10
        for p in self.procs.values():
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for ns in self.namespaces:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self.namespaces.clear()

    # -- traffic ----------------------------------------------------------------------------------
    def _feed(self, robot: str) -> None:
        """Rectified pairs on the robot's frames_rect at self.rates[robot] per second."""
        import zenoh

        from common import codec
        from common.keys import topic
        from common.messages import StereoFrame

        pub = self.session.declare_publisher(topic("frames_rect").key(robot),
                                             congestion_control=zenoh.CongestionControl.DROP)
        frames = [StereoFrame(**{**f.model_dump(), "robot_id": robot}) for f in self.frames]
        seq, t_next = 0, time.monotonic()
        while not self.stop.is_set():
            rate = self.rates[robot]
            if rate <= 0:
                self.stop.wait(0.05)
                t_next = time.monotonic()
                continue
            f = frames[seq % len(frames)]
            f.seq, f.stamp_ns, f.stages = seq, time.time_ns(), {}
            pub.put(codec.encode(f))
            seq += 1
            t_next = max(t_next + 1.0 / rate, time.monotonic() - 0.5)
            self.stop.wait(max(0.0, t_next - time.monotonic()))

    def flood_unsolicited(self, robot: str, workers: list[str], rate: float, seconds: float) -> int:
        """Frames put straight on the pool workers' keys in robot's name, without grants."""
        from common import codec
        from common.keys import topic

        payload = codec.encode(self.frames[0].model_copy(update={"robot_id": robot}))
        n, t_end = 0, time.monotonic() + seconds
        while time.monotonic() < t_end and not self.stop.is_set():
            for w in workers:
                self.session.put(topic("pool_work").key(robot, pool=POOL, instance=w), payload)
                n += 1
            self.stop.wait(1.0 / rate)
        return n

    def _subscribe(self) -> None:
        import zenoh

        from common import codec
        from common.keys import topic
        from common.messages import ServiceStats

        def on_disp(sample) -> None:
            m = msgpack.unpackb(sample.payload.to_bytes())  # a few fields only: keep the bench light
            t = time.monotonic()
            with self.lock:
                self.maps.append(Map(m["robot_id"], m["seq"], m["worker"], t, (time.time_ns() - m["stamp_ns"]) / 1e6,
                                     m.get("method", "")))

        def on_token(sample) -> None:
            with self.lock:
                self.tokens.append((time.monotonic(), str(sample.key_expr).rsplit("/", 1)[-1],
                                    sample.kind == zenoh.SampleKind.PUT))

        def on_stats(sample) -> None:
            try:
                s = codec.decode(sample.payload.to_bytes(), ServiceStats)
            except Exception:
                return
            with self.lock:
                self.stats[f"{s.robot_id}/{s.role}/{s.instance}"] = {"extra": s.extra, "status": s.status,
                                                                    "t": time.monotonic()}
                if s.role == "pool-worker" and s.rate_hz > 0:
                    self.proc_ms.append((time.monotonic(), s.proc_ms_p50))

        self._subs = [self.session.declare_subscriber(topic("disparity").pattern("*"), on_disp),
                      self.session.declare_subscriber(topic("pool_stats").pattern(pool=POOL), on_stats),
                      self.session.declare_subscriber(topic("stats").pattern("*"), on_stats),
                      self.session.liveliness().declare_subscriber(topic("pool_worker").pattern(pool=POOL), on_token,
                                                                   history=True)]

    # -- reading ----------------------------------------------------------------------------------
    def wait(self, pred, timeout: float, what: str) -> float:
        deadline = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > deadline:
                raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}"
                                   + (f"; service logs in {self.logdir}" if self.logdir else ""))
            dead = [n for n, p in self.procs.items() if p.poll() is not None and not n.startswith("worker")]
            if dead:
                raise RuntimeError(f"{', '.join(dead)} exited" + (f"; logs in {self.logdir}" if self.logdir else ""))
            time.sleep(0.05)  # polling shared lists filled by Zenoh callbacks
        return time.monotonic()

    def between(self, t0: float, t1: float) -> list[Map]:
        with self.lock:
            return [m for m in self.maps if t0 <= m.t < t1]

    def token_time(self, worker: str, up: bool, after: float = 0.0) -> float | None:
        with self.lock:
            return next((t for t, w, u in self.tokens if w == worker and u == up and t >= after), None)


def worker_ceiling(method: str, frames: list, seconds: float = 3.0) -> dict:
    """The pool worker's own compute (FrameComputer, the worker's settings, one OpenCV thread) on
    the fleet's frames, in this process: frames/s as frames / wall time."""
    import cv2

    from services.disparity.computer import FrameComputer
    from services.disparity.main import DisparitySettings

    computer = FrameComputer(DisparitySettings(method=method, threads=1), 1.0, "raw")
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        computer.compute(frames[0], "bench")  # the first call allocates
        n, t0, cpu0 = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < seconds or n < 3:
            computer.compute(frames[n % len(frames)], "bench")
            n += 1
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    finally:
        cv2.setNumThreads(before)
    return {"fps": n / wall, "ms": wall * 1e3 / n, "cpu_ms": cpu * 1e3 / n}


def _frames() -> list:
    from bench.scaling import rectified_pairs, rectified_payloads

    return rectified_payloads("bench", rectified_pairs(4))


def summary(maps: list[Map], robots: list[str], seconds: float) -> dict:
    per = {}
    for r in robots:
        mine = [m for m in maps if m.robot == r]
        per[r] = {"maps": len(mine), "hz": len(mine) / seconds, "latency_ms": percentiles([m.latency_ms for m in mine]),
                  "workers": sorted({m.worker for m in mine})}
    return {"seconds": seconds, "total_hz": len(maps) / seconds, "robots": per}


def cpu_of(fleet: Fleet) -> dict[str, float]:
    from bench.measure import cpu_seconds

    out = {name: cpu_seconds(p.pid) for name, p in fleet.procs.items() if p.poll() is None}
    out["bench"] = time.process_time()  # the feeder
    return out


def measure(fleet: Fleet, rates: dict[str, float], warmup: float, seconds: float) -> dict:
    fleet.rates.update(rates)
    time.sleep(warmup)  # a benchmark's fixed warm-up, not a test synchronisation
    cpu0, t0 = cpu_of(fleet), time.monotonic()
    time.sleep(seconds)
    t1, cpu1 = time.monotonic(), cpu_of(fleet)
    out = summary(fleet.between(t0, t1), list(rates), t1 - t0)
    maps = max(1, sum(v["maps"] for v in out["robots"].values()))
    cpu = {k: (cpu1[k] - cpu0.get(k, 0.0)) * 1e3 / maps for k in cpu1}
    out["cpu_ms_per_map"] = {"workers": sum(v for k, v in cpu.items() if k.startswith("worker")),
                             "dispatchers": sum(v for k, v in cpu.items() if k.startswith("dispatch")),
                             "router": cpu.get("router", 0.0), "feeder": cpu.get("bench", 0.0)}
    with fleet.lock:
        proc = [v for t, v in fleet.proc_ms if t0 <= t <= t1 + 1.0]
    out["worker_proc_ms_p50"] = float(np.median(proc)) if proc else float("nan")
    return out


def back_at_share(maps: list[Map], robot: str, t_event: float, share_hz: float, until: float,
                  window: float = 2.0, step: float = 0.05, settled_from: float | None = None) -> float | None:
    """Seconds from t_event until robot's maps/s over the next `window` s reach 0.9 x its new share
    (the first such moment, on a grid of `step`); None if never before `until`. The new share is
    share_hz, or the robot's own rate from settled_from on if that is lower: how long the event
    cost it, apart from how evenly the rest of the run happens to divide (reported separately)."""
    ts = np.array(sorted(m.t for m in maps if m.robot == robot and m.t >= t_event))
    if settled_from is not None and until > settled_from:
        share_hz = min(share_hz, np.count_nonzero(ts >= settled_from) / (until - settled_from))
    t = t_event
    while t + window <= until:
        n = np.count_nonzero((ts >= t) & (ts < t + window))
        if n / window >= TARGET_SHARE * share_hz:
            return t - t_event
        t += step
    return None


def run(args: argparse.Namespace, say) -> dict:
    robots = [f"r{i}{uuid.uuid4().hex[:3]}" for i in range(args.robots)]
    cores = os.cpu_count() or 1
    frames = _frames()
    say("in-process one-thread ceiling (the worker's own compute) ...")
    ceilings = [worker_ceiling(args.method, frames)]
    workers = [f"w{i}" for i in range(args.workers)]
    report: dict = {"method": args.method, "image": "640x480", "cores": cores, "robots": robots, "workers": workers,
                    "load_avg_1min_start": os.getloadavg()[0]}
    greedy = robots[0]
    with Fleet(robots, args.method, not args.no_netns, {greedy: 8}, logdir=args.logdir) as fleet:
        report["netns"] = fleet.use_netns
        report["netns_reason"] = fleet.netns_reason
        where = "their own network namespaces" if fleet.use_netns else f"this namespace: {fleet.netns_reason}"
        say(f"workers in {where}")
        for w in workers:
            fleet.add_worker(w)
        one = ceilings[0]["fps"]
        ceiling_now = min(len(workers), cores) * one
        # each robot wants twice its share (at least 8/s: the load of a shared machine can fall later)
        offer = max(8.0, 2.0 * ceiling_now / len(robots))
        report["offered"] = {}
        fleet.rates.update({r: offer for r in robots})
        fleet.wait(lambda: {m.robot for m in fleet.between(0, 1e18)} >= set(robots)
                   and {m.worker.split("@")[0] for m in fleet.between(0, 1e18)} >= set(workers), 180,
                   "every robot to get maps from every worker")
        say(f"equal: {len(robots)} robots, each offered {offer:.1f}/s ...")
        report["offered_hz"] = offer
        report["offered"]["equal"] = {r: offer for r in robots}
        report["equal"] = measure(fleet, report["offered"]["equal"], 3.0, args.seconds)
        say(f"alone, saturating: {robots[1]} offers {2 * ceiling_now:.1f}/s, the others nothing ...")
        report["alone_full"] = measure(fleet, {**{r: 0.0 for r in robots}, robots[1]: 2 * ceiling_now}, 3.0,
                                       args.seconds)
        report["alone_full"]["robots"] = {robots[1]: report["alone_full"]["robots"][robots[1]]}
        light = robots[-1]
        light_hz = 0.5 * report["equal"]["total_hz"] / len(robots)  # within its share
        report["light_hz"] = light_hz
        say(f"alone: {light} offers {light_hz:.2f}/s, the others nothing ...")
        quiet = {r: 0.0 for r in robots}
        report["alone"] = measure(fleet, {**quiet, light: light_hz}, 3.0, args.seconds)
        report["alone"]["robots"] = {light: report["alone"]["robots"][light]}
        say(f"flood: {greedy} offers {4 * offer:.1f}/s and puts frames without grants; {light} {light_hz:.2f}/s ...")
        flood = threading.Thread(target=fleet.flood_unsolicited, args=(greedy, workers, 2.0, args.seconds + 3.0),
                                 daemon=True)
        flood.start()
        report["offered"]["flood"] = {**{r: offer for r in robots}, greedy: 4 * offer, light: light_hz}
        report["flood"] = measure(fleet, report["offered"]["flood"], 3.0, args.seconds)
        flood.join()
        fleet.rates.update({r: offer for r in robots})
        say(f"kill: SIGKILL {workers[0]} ...")
        time.sleep(3.0)
        t_before = time.monotonic()
        t_kill = fleet.kill_worker(workers[0])
        time.sleep(args.seconds)
        t_end = time.monotonic()
        maps = fleet.between(t_before - 3.0, t_end)
        after = [m for m in maps if m.t >= t_kill + 2.0]
        new_share = len(after) / max(1e-3, t_end - t_kill - 2.0) / len(robots)
        gone = fleet.token_time(workers[0], False, t_kill)
        report["kill"] = {"token_gone_s": None if gone is None else gone - t_kill, "new_share_hz": new_share,
                          "new_share_from_ceiling_hz": min(len(workers) - 1, cores) * one / len(robots),
                          "after": summary(after, robots, t_end - t_kill - 2.0),
                          "back_at_share_s": {r: back_at_share(maps, r, t_kill, new_share, t_end,
                                                               settled_from=t_kill + 2.0) for r in robots},
                          "longest_gap_s": {r: _gap([m.t for m in maps if m.robot == r], t_kill, t_end)
                                            for r in robots}}
        say(f"add: a new worker {workers[0]}b ...")
        t_start = time.monotonic()
        fleet.add_worker(workers[0] + "b")
        t_up = fleet.wait(lambda: fleet.token_time(workers[0] + "b", True, t_start) is not None, 120,
                          "the new worker's token")
        t_token = fleet.token_time(workers[0] + "b", True, t_start)
        if t_token is None:  # (the wait above saw it)
            raise BallbotError(f"fleet bench: the token of {workers[0]}b came and went")
        fleet.wait(lambda: any(m.worker.startswith(workers[0] + "b@") for m in fleet.between(t_token, 1e18)), 60,
                   "the new worker's first map")
        first = min(m.t for m in fleet.between(t_token, 1e18) if m.worker.startswith(workers[0] + "b@"))
        time.sleep(args.seconds)
        t_end = time.monotonic()
        maps = fleet.between(t_token, t_end)
        settled = [m for m in maps if m.t >= t_token + 2.0]
        share2 = len(settled) / max(1e-3, t_end - t_token - 2.0) / len(robots)
        report["add"] = {"process_to_token_s": t_up - t_start, "token_to_first_map_s": first - t_token,
                         "share_hz": share2, "after": summary(settled, robots, t_end - t_token - 2.0),
                         "back_at_share_s": {r: back_at_share(maps, r, t_token, share2, t_end,
                                                              settled_from=t_token + 2.0) for r in robots}}
        starved = [r for r in robots if report["add"]["after"]["robots"][r]["maps"] == 0]
        if starved:  # a robot that got nothing: how its dispatcher stood, and its threads in its log
            report["starved"] = {r: {k: v for k, v in fleet.stats.items() if k.startswith(r + "/")} for r in starved}
            for r in starved:
                fleet.procs[f"dispatch-{r}"].send_signal(signal.SIGABRT)
            time.sleep(1.0)
        with fleet.lock:
            report["pool_stats"] = {k: v for k, v in fleet.stats.items() if "/pool-worker/" in k}
            report["dispatcher_stats"] = {k: {x: v["extra"].get(x, 0) for x in (
                "results_unmatched", "pool_grants", "pool_declined", "pool_wants", "results_rejected")}
                for k, v in fleet.stats.items() if "/dispatcher/" in k}
    say("in-process one-thread ceiling again ...")
    ceilings.append(worker_ceiling(args.method, frames))
    one = float(np.mean([c["fps"] for c in ceilings]))
    report["ceiling_one_thread_fps"] = [c["fps"] for c in ceilings]
    report["workers_ceiling_hz"] = min(len(workers), cores) * one
    cpu = report["equal"]["cpu_ms_per_map"]
    work, rest = cpu["workers"], cpu["dispatchers"] + cpu["router"] + cpu["feeder"]
    # what the measured CPU per map allows on this many cores with nothing else running
    report["projected_quiet_hz"] = (min(min(len(workers), cores) * 1e3 / work, cores * 1e3 / (work + rest))
                                    if work > 0 else 0.0)
    # On a pool host of its own only the workers and the router run there (dispatchers and capture are
    # on the robots): the pool's maps/s over the ideal of its workers (each as fast as the matcher
    # in-process), from CPU time per map, which a shared machine's load does not change much.
    inproc_cpu = float(np.mean([c["cpu_ms"] for c in ceilings]))
    n_w = min(len(workers), cores)
    host = min(n_w * 1e3 / work, cores * 1e3 / (work + cpu["router"])) if work > 0 else 0.0
    report["pool_host_projection"] = {"inprocess_cpu_ms": inproc_cpu, "worker_cpu_ms": work / 1.0,
                                      "router_cpu_ms": cpu["router"], "maps_per_s": host,
                                      "ideal_maps_per_s": n_w * 1e3 / inproc_cpu,
                                      "x_ideal": host / (n_w * 1e3 / inproc_cpu)}
    report["load_avg_1min_end"] = os.getloadavg()[0]
    report["targets"] = targets(report)
    return report


def _gap(ts: list[float], t0: float, t1: float) -> float:
    ts = [t0] + sorted(t for t in ts if t0 <= t <= t1) + [t1]
    return max(b - a for a, b in zip(ts, ts[1:]))


def max_min_fair(total: float, demands: dict[str, float]) -> dict[str, float]:
    """What each robot is entitled to of `total` maps/s when robot i asks for demands[i]: max-min
    fairness (water filling): a robot asking less than an equal split gets what it asks, the
    others split the rest equally. A robot that is sent all it asks for loses nothing to a flood."""
    left, out = total, {}
    pending = sorted(demands.items(), key=lambda kv: kv[1])
    while pending:
        even = left / len(pending)
        robot, want = pending[0]
        if want <= even:
            out[robot] = want
            left -= want
            pending.pop(0)
        else:
            for robot, _ in pending:
                out[robot] = even
            break
    return out


def entitled(phase: dict, offered: dict[str, float]) -> dict[str, float]:
    return max_min_fair(phase["total_hz"], {r: offered[r] for r in phase["robots"]})


def targets(r: dict) -> list[tuple[str, float, str, float, bool]]:
    n = len(r["robots"])
    eq = r["equal"]
    ph = r["pool_host_projection"]
    out = [("total / workers' ceiling", eq["total_hz"] / r["workers_ceiling_hz"], ">=", TARGET_SHARE,
            eq["total_hz"] / r["workers_ceiling_hz"] >= TARGET_SHARE),
           ("  a pool host of its own, from CPU per map: x ideal", ph["x_ideal"], ">=", TARGET_SHARE,
            ph["x_ideal"] >= TARGET_SHARE)]
    worst = min(v["hz"] for v in eq["robots"].values())
    ent = entitled(eq, r["offered"]["equal"])
    x = min(eq["robots"][k]["hz"] / ent[k] for k in ent)
    out.append(("equal: worst robot / its max-min fair share", x, ">=", TARGET_SHARE, x >= TARGET_SHARE))
    ceil_share = r["workers_ceiling_hz"] / n
    out.append(("equal: worst robot / ceiling share (ceiling/N)", worst / ceil_share, ">=", TARGET_SHARE,
                worst / ceil_share >= TARGET_SHARE))
    fl = r["flood"]
    greedy, light = r["robots"][0], r["robots"][-1]
    got = fl["robots"][light]["hz"] / r["light_hz"]
    out.append(("flood: light robot's maps/s / what it offered", got, ">=", TARGET_SHARE, got >= TARGET_SHARE))
    alone = r["alone"]["robots"][light]["latency_ms"]["p50"]
    lat = fl["robots"][light]["latency_ms"]["p50"] / alone
    out.append(("flood: light robot's latency p50 / alone", lat, "<=", TARGET_LATENCY_X, lat <= TARGET_LATENCY_X))
    # the same in units of the workers' compute time per map in each phase: on a shared 2-core machine
    # a map takes longer while both workers compute than while one does
    norm = (fl["robots"][light]["latency_ms"]["p50"] / fl["worker_proc_ms_p50"]) / \
        (alone / r["alone"]["worker_proc_ms_p50"])
    out.append(("  same, each over its phase's compute time per map", norm, "<=", TARGET_LATENCY_X,
                norm <= TARGET_LATENCY_X))
    # max-min fair: a robot asking less than an equal split gets what it asks, the others split the rest
    ent = entitled(fl, r["offered"]["flood"])
    g = fl["robots"][greedy]["hz"] / ent[greedy]
    out.append(("flood: flooding robot / its max-min fair share", g, "<=", 1.1, g <= 1.1))
    others = min(fl["robots"][k]["hz"] / ent[k] for k in ent if k != greedy)
    out.append(("flood: worst other robot / its max-min fair share", others, ">=", TARGET_SHARE,
                others >= TARGET_SHARE))
    backs = [v for v in r["kill"]["back_at_share_s"].values()]
    worst_back = max((b if b is not None else float("inf")) for b in backs)
    out.append(("kill: slowest robot back at its new share (s)", worst_back, "<=", TARGET_RECOVER_S,
                worst_back <= TARGET_RECOVER_S))
    used = r["add"]["token_to_first_map_s"]
    out.append(("add: new worker's token to its first map (s)", used, "<=", TARGET_RECOVER_S,
                used <= TARGET_RECOVER_S))
    return out


def format_report(r: dict) -> str:
    lines = [f"{len(r['robots'])} robots, {len(r['workers'])} {r['method']} pool workers (1 OpenCV thread each), "
             f"{r['image']}, {r['cores']} cores; workers "
             + ("each in its own network namespace" if r["netns"] else f"on loopback ({r['netns_reason']})"),
             "in-process 1-thread ceiling (before / after): "
             + " / ".join(f"{v:.2f}" for v in r["ceiling_one_thread_fps"])
             + f" fps -> workers' ceiling {r['workers_ceiling_hz']:.2f} maps/s; "
             f"load avg {r['load_avg_1min_start']:.1f} at start, {r['load_avg_1min_end']:.1f} at end",
             f"the equal phase's CPU per map allows {r['projected_quiet_hz']:.2f} maps/s on {r['cores']} "
             f"otherwise idle cores; a pool host of its own "
             f"(workers {r['pool_host_projection']['worker_cpu_ms']:.1f} + router "
             f"{r['pool_host_projection']['router_cpu_ms']:.1f} ms CPU per map, the matcher in-process "
             f"{r['pool_host_projection']['inprocess_cpu_ms']:.1f} ms): {r['pool_host_projection']['maps_per_s']:.1f} "
             f"maps/s = {r['pool_host_projection']['x_ideal']:.2f} x its workers' ideal",
             f"each robot offered {r['offered_hz']:.1f} pairs/s (flood: robot 0 x4, max_in_flight 8, plus "
             f"unsolicited frames; the last robot {r['light_hz']:.2f}/s, half its share)"]

    def block(name: str, s: dict) -> None:
        n = len(s["robots"])
        lines.append(f"{name}: total {s['total_hz']:.2f} maps/s over {s['seconds']:.1f} s"
                     + (f", fair share {s['total_hz'] / n:.2f}" if n > 1 else "")
                     + (f"; a worker's compute p50 {s['worker_proc_ms_p50']:.0f} ms per map"
                        if "worker_proc_ms_p50" in s else ""))
        if "cpu_ms_per_map" in s:
            lines.append("    CPU per map: " + ", ".join(f"{k} {v:.1f} ms" for k, v in s["cpu_ms_per_map"].items()))
        for robot, v in s["robots"].items():
            lat = v["latency_ms"]
            lines.append(f"    {robot}: {v['hz']:5.2f} maps/s"
                         + (f" = {v['hz'] / (s['total_hz'] / n):.2f} x share" if n > 1 and s["total_hz"] else "")
                         + f", latency p50 {lat['p50']:.0f} ms p95 {lat['p95']:.0f} ms, from {', '.join(v['workers'])}")

    block("equal", r["equal"])
    block("alone, saturating", r["alone_full"])
    block("alone", r["alone"])
    block("flood", r["flood"])
    k = r["kill"]
    lines.append(f"kill: token gone after {k['token_gone_s'] * 1e3:.0f} ms; new share {k['new_share_hz']:.2f} maps/s "
                 f"(ceiling/N {k['new_share_from_ceiling_hz']:.2f})" if k["token_gone_s"] is not None else "kill: ?")
    for robot in r["robots"]:
        b = k["back_at_share_s"][robot]
        lines.append(f"    {robot}: back at 0.9 x new share after "
                     + (f"{b:.2f} s" if b is not None else "never")
                     + f", longest gap {k['longest_gap_s'][robot]:.2f} s")
    block("  after the kill", k["after"])
    a = r["add"]
    lines.append(f"add: process start to token {a['process_to_token_s']:.1f} s; token to its first map "
                 f"{a['token_to_first_map_s'] * 1e3:.0f} ms; share after {a['share_hz']:.2f} maps/s")
    for robot in r["robots"]:
        b = a["back_at_share_s"][robot]
        lines.append(f"    {robot}: at 0.9 x the new share after " + (f"{b:.2f} s" if b is not None else "never"))
    block("  after the add", a["after"])
    for robot, st in r.get("starved", {}).items():
        lines.append(f"STARVED after the add: {robot}: " + "; ".join(f"{k}: {v['status']}" for k, v in st.items()))
    lines.append("targets:")
    for label, value, op, target, ok in r["targets"]:
        lines.append(f"  {label:52} {value:6.2f}   target {op} {target:.2f}   {'met' if ok else 'MISSED'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, default=4)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--method", default="sgbm", choices=["bm", "sgbm"])
    p.add_argument("--seconds", type=float, default=15.0, help="measured seconds per phase")
    p.add_argument("--no-netns", action="store_true", help="workers on loopback, not in network namespaces")
    p.add_argument("--logdir", default=None, help="each process's log here")
    p.add_argument("--json", action="store_true")
    p.add_argument("--save", default=None, metavar="FILE", help="also write the JSON report here")
    a = p.parse_args(argv)
    if a.robots < 2 or a.workers < 1:
        p.error("--robots >= 2 and --workers >= 1")
    say = (lambda text: None) if a.json else (lambda text: print(text, file=sys.stderr, flush=True))
    r = run(a, say)
    if a.save:
        with open(a.save, "w") as f:
            json.dump(r, f, indent=2, default=str)
    print(json.dumps(r, indent=2, default=str) if a.json else format_report(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
