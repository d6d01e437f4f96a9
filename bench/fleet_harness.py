"""The fleet bench's harness (bench/fleet.py measures with it): a router, per robot its disparity
dispatcher on the pool, pool workers each in its own network namespace when this machine allows
(`ip netns`, as root; otherwise on loopback, and netns_unavailable says why), one feeder thread per
robot putting rectified synthetic pairs, and what comes back: every robot's maps, the pool's
stats, the workers' liveliness tokens."""
from __future__ import annotations

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

from bench.measure import free_port
from common.errors import BallbotError
from common.supervisor import die_with_parent, stop_processes

if TYPE_CHECKING:
    import zenoh

PY = sys.executable
POOL = "fleet"


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
        self.busy: dict[str, list[tuple[float, float, float]]] = {}  # worker -> (received, uptime_s, pool_busy_s)
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
        # die_with_parent: a bench killed outright leaves no router or worker running (the
        # namespaces are deleted by __exit__, which main runs on SIGTERM as on Ctrl-C)
        p = subprocess.Popen((prefix or []) + [PY, "-m", "ballbot_vision.cli", "run", *argv], env=env,
                             stdout=subprocess.DEVNULL, stderr=err, preexec_fn=die_with_parent)
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
            self.frames = fleet_frames()
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
        stop_processes(self.procs, 10.0)
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
                if s.role == "pool-worker" and "pool_busy_s" in s.extra:
                    self.busy.setdefault(s.instance, []).append((time.monotonic(), s.uptime_s, s.extra["pool_busy_s"]))

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


def fleet_frames() -> list:
    """The rectified frames every feeder sends (with rectify's checks, as on a robot), and the workers'
    ceiling is measured on."""
    from bench.scaling import rectified_frames

    return rectified_frames(4)
