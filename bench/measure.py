"""What every benchmark measures with: free ports, percentiles, a process's CPU time."""
from __future__ import annotations

import os
import socket
import threading

import numpy as np

_HANDED_OUT: set[int] = set()
_HANDED_OUT_LOCK = threading.Lock()


def free_port() -> int:
    """A loopback TCP port free now, and never one this process handed out before. The kernel may
    give a port it just released to the very next bind(0): two ports picked back to back (a
    service's and the router's) were then one, and the service met its own router on it."""
    with _HANDED_OUT_LOCK:
        while True:
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                port = s.getsockname()[1]
            if port not in _HANDED_OUT:
                _HANDED_OUT.add(port)
                return port


def percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {"p50": float("nan"), "p95": float("nan"), "p99": float("nan")}
    a = np.asarray(values)
    return {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)), "p99": float(np.percentile(a, 99))}


def cpu_seconds(pid: int, kernel_only: bool = False) -> float:
    """CPU time (user + system, or system alone) of a process so far, all its threads, in s, from
    /proc; 0 when gone. System time is mostly page faults and syscalls: copies into fresh memory."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        ticks = int(fields[12]) if kernel_only else int(fields[11]) + int(fields[12])
        return ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0
