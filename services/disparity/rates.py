"""Byte counters per link for a service's stats (the dispatcher's and the workers')."""
from __future__ import annotations

import threading
import time

from common.node import Node


class Rates:
    """Byte counters per link: totals go into node.extra as '<name>_bytes' (name starts with in_ or
    out_, so `status` sums them with the node's own counters) and per-second rates as
    'rate_<name>_Bps', refreshed at most once a second by tick()."""

    def __init__(self, node: Node):
        self.node = node
        self._bytes: dict[str, int] = {}
        self._last: dict[str, int] = {}
        self._t = time.monotonic()
        self._lock = threading.Lock()

    def add(self, name: str, n: int) -> None:
        with self._lock:
            self._bytes[name] = self._bytes.get(name, 0) + n

    def forget(self, name: str) -> None:
        with self._lock:
            self._bytes.pop(name, None)
            self._last.pop(name, None)
        self.node.extra.pop(f"rate_{name}_Bps", None)
        self.node.extra.pop(f"{name}_bytes", None)

    def tick(self) -> None:
        now = time.monotonic()
        dt = now - self._t
        if dt < 1.0:
            return
        self._t = now
        with self._lock:
            for name, total in self._bytes.items():
                self.node.extra[f"rate_{name}_Bps"] = (total - self._last.get(name, 0)) / dt
                self.node.extra[f"{name}_bytes"] = float(total)
                self._last[name] = total


