"""The processes of the pipeline (which services, in which order and priority) and the supervisor
that runs them for `ballbot-vision up` and the benchmarks: every service as its own OS process,
restarted if it dies (with a backoff that starts again from 0.5 s once a child has run healthily for
a while), all stopped on Ctrl-C or SIGTERM (SIGTERM to all at once, a generous grace for a loaded
machine, SIGKILL only after it), and none left behind if the supervisor itself is killed."""
from __future__ import annotations

import ctypes
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

log = logging.getLogger("ballbot.up")

# A service folder's name is its process name, its compose service name and its `producer` entry.
SERVICES = {
    "capture": ("services.capture.main", "CaptureSettings"),
    "rectify": ("services.rectify.main", "RectifySettings"),
    "disparity": ("services.disparity.main", "DisparitySettings"),
    "segmenter": ("services.segmenter.main", "SegmenterSettings"),
    "ros2": ("services.ros2.main", "Ros2Settings"),
    "viewer": ("services.viewer.main", "ViewerSettings"),
    "foxglove": ("services.foxglove.main", "FoxgloveSettings"),
}
PIPELINE = ["capture", "rectify", "disparity", "segmenter"]


def stop_processes(procs: dict[str, subprocess.Popen], timeout_s: float) -> list[str]:
    """SIGTERM to every running one at once, then one shared deadline for all (a loaded machine
    stops them in parallel), then SIGKILL for the rest. -> the names that had to be killed."""
    live = {n: p for n, p in procs.items() if p.poll() is None}
    for p in live.values():
        try:
            p.send_signal(signal.SIGTERM)
        except ProcessLookupError:
            pass
    deadline = time.monotonic() + timeout_s
    killed = []
    for name, p in live.items():
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            killed.append(name)
            p.kill()
            p.wait()
    return killed


def stage_nice(name: str) -> int:
    """Scheduling priority of a pipeline stage relative to `up --nice`: each stage runs ahead of
    the ones before it (capture +3 ... segmenter +0). When the CPU is short, a pair already in
    the pipeline is finished before a new one is started: lower latency, and no CPU spent on pairs
    that a busy later stage would drop (on a loaded 2-core machine at overload: p50 latency -28 %,
    CPU per delivered list -13 %, `ballbot-vision bench`). With CPU to spare it changes nothing."""
    return len(PIPELINE) - 1 - PIPELINE.index(name) if name in PIPELINE else 0


PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    # Runs in the child before exec: the kernel sends SIGTERM to it when the supervisor dies.
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


def wait_for_tcp(endpoint: str, timeout_s: float, stop: threading.Event) -> bool:
    """True once something accepts TCP connections at a tcp/HOST:PORT endpoint."""
    if not endpoint.startswith("tcp/"):
        return True
    host, _, port = endpoint[4:].rpartition(":")
    host = host.strip("[]")
    if host in ("0.0.0.0", "::"):
        host = "127.0.0.1"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not stop.is_set():
        try:
            socket.create_connection((host, int(port)), timeout=0.5).close()
            return True
        except OSError:
            stop.wait(0.05)
    return False


@dataclass
class Child:
    name: str
    argv: list[str]
    proc: subprocess.Popen | None = None
    restarts: int = 0
    next_start: float = 0.0
    backoff_s: float = field(default=0.5)
    started_at: float = 0.0
    nice_offset: int = 0  # added to the supervisor's nice for this child (see cli.stage_nice)
    optional: bool = False  # not part of the pipeline (viewer, ros2): a missing dependency disables it alone
    disabled: str = ""  # why it is no longer started


INITIAL_BACKOFF_S = 0.5
MAX_BACKOFF_S = 10.0


class Supervisor:
    """stop_timeout_s: how long children get to stop after SIGTERM before SIGKILL. A child closes
    its Zenoh session and exits; on an idle machine that takes well under a second, on a loaded
    2-core machine several (a 1.5 s grace killed children mid-close there).
    healthy_after_s: a child that ran this long before it died restarts after the initial backoff
    again, so a crash every half hour is not punished like a crash loop."""

    def __init__(self, stop_timeout_s: float = 10.0, env: dict[str, str] | None = None,
                 healthy_after_s: float = 30.0, nice: int = 0):
        self.env = env
        self.nice = nice
        self.children: list[Child] = []
        self.stop = threading.Event()
        self.stop_timeout_s = stop_timeout_s
        self.healthy_after_s = healthy_after_s

    def add(self, name: str, argv: list[str], nice_offset: int = 0, optional: bool = False) -> None:
        self.children.append(Child(name, argv, nice_offset=nice_offset, optional=optional))

    def _start(self, c: Child) -> None:
        nice = self.nice + c.nice_offset
        c.proc = subprocess.Popen([sys.executable, "-m", "ballbot_vision.cli", *c.argv],
                                  preexec_fn=lambda: self._child_setup(nice), env=self.env)
        c.started_at = time.monotonic()
        log.info("started %s (pid %d)", c.name, c.proc.pid)

    def _child_setup(self, nice: int) -> None:
        """In the child before exec: die with the supervisor; run at the requested priority."""
        die_with_parent()
        if nice:
            try:
                os.setpriority(os.PRIO_PROCESS, 0, max(-20, min(19, nice)))
            except OSError:  # a negative nice needs root or CAP_SYS_NICE: run at the default
                pass

    def start_all(self, wait_for_endpoint: str | None = None) -> None:
        """Start the first child (the router), wait until it accepts connections, then the rest."""
        first, rest = self.children[0], self.children[1:]
        self._start(first)
        if wait_for_endpoint and not wait_for_tcp(wait_for_endpoint, 15.0, self.stop):
            if not self.stop.is_set():
                log.error("%s is not accepting connections on %s after 15 s", first.name, wait_for_endpoint)
        for c in rest:
            if not self.stop.is_set():
                self._start(c)

    def run(self, wait_for_endpoint: str | None = None) -> int:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: self.stop.set())
        try:
            self.start_all(wait_for_endpoint)
            while not self.stop.wait(0.1):
                failed = self._restart_dead()
                if failed:
                    proc = self._child(failed).proc
                    status = proc.returncode if proc is not None else None
                    log.error("%s refused to start (exit status %s: %s, see above); stopping everything", failed,
                              status, "a missing dependency" if status == 3 else "a usage or configuration error")
                    return 2
        finally:
            self.stop_all()
        return 0

    def _restart_dead(self) -> str | None:
        """Restart crashed children with backoff; returns the name of one that exited with status 2
        (bad settings or input: restarting cannot help), or with status 3 (a missing dependency) if
        the pipeline needs it. An optional child that exits with status 3 is disabled: never
        restarted, the others keep running."""
        now = time.monotonic()
        for c in self.children:
            if c.disabled:
                continue
            if c.proc is not None and c.proc.poll() == 3:
                if not c.optional:
                    return c.name
                c.disabled = "a dependency is missing"
                c.proc = None
                log.error("%s is disabled: it needs a dependency that is not installed (its message above says "
                          "what to install); the other services keep running", c.name)
                continue
            if c.proc is not None and c.proc.poll() == 2:
                return c.name
            if c.proc is not None and c.proc.poll() is not None:
                ran = now - c.started_at
                if ran >= self.healthy_after_s:
                    c.backoff_s = INITIAL_BACKOFF_S  # it ran fine for a while: not a crash loop
                log.warning("%s exited with status %s after %.0f s; restarting in %.1f s", c.name, c.proc.returncode,
                            ran, c.backoff_s)
                c.proc = None
                c.next_start = now + c.backoff_s
                c.backoff_s = min(c.backoff_s * 2, MAX_BACKOFF_S)
                c.restarts += 1
            elif c.proc is None and now >= c.next_start:
                self._start(c)
        return None

    def _child(self, name: str) -> Child:
        return next(c for c in self.children if c.name == name)

    def stop_all(self) -> None:
        live = {c.name: c.proc for c in self.children if c.proc is not None and c.proc.poll() is None}
        t0 = time.monotonic()
        for name in stop_processes(live, self.stop_timeout_s):
            log.warning("%s (pid %d) did not stop within %.0f s of SIGTERM; killing it", name, live[name].pid,
                        self.stop_timeout_s)
        if live:
            log.info("all stopped in %.2f s", time.monotonic() - t0)
