"""What every benchmark measures with: free ports, percentiles, a process's CPU time."""
from __future__ import annotations

import os
import socket

import numpy as np


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
