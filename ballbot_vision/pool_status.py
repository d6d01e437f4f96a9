"""The fleet pools in `ballbot-vision status`: per pool its workers (from their stats on
`ballbot/pool/<pool>/stats/<instance>`, never taken for a robot's services; each with its share of
the last 5 s on items: near 100 % the pool is saturated, and a robot gets only its share) and each robot's weight,
share of the pool, maps/s and queue, summed over the workers (services/disparity/fleet.py)."""
from __future__ import annotations

import threading
import time
from typing import Any

from common import codec
from common.errors import DecodeError
from common.keys import topic
from common.messages import ServiceStats
from common.zenoh_session import LiveTokens


class PoolWatch:
    """Collects pool workers' stats and liveliness while `status` listens."""

    def __init__(self, session: Any):
        self.latest: dict[tuple[str, str], ServiceStats] = {}
        self.seen_at: dict[tuple[str, str], float] = {}
        self.lock = threading.Lock()
        self._sub = session.declare_subscriber(topic("pool_stats").pattern(), self._on_stats)
        self._tokens = LiveTokens(session, topic("pool_alive").pattern())

    def _on_stats(self, sample) -> None:
        parts = str(sample.key_expr).split("/")  # ballbot/pool/<pool>/stats/<instance>
        try:
            s = codec.decode(sample.payload.to_bytes(), ServiceStats)
        except DecodeError:
            return
        if len(parts) != 5 or s.instance != parts[4]:
            return
        with self.lock:
            self.latest[(parts[2], parts[4])] = s
            self.seen_at[(parts[2], parts[4])] = time.monotonic()

    def collect(self, robot: str = "*") -> list[dict]:
        """-> one dict per pool: workers, robots (weight, share, maps/s, queue), warnings."""
        alive: set[tuple[str, str]] = set()
        for token in self._tokens.keys():
            parts = token.split("/")  # ballbot/pool/<pool>/alive/<instance>
            if len(parts) == 5:
                alive.add((parts[2], parts[4]))
        now = time.monotonic()
        pools: dict[str, dict] = {}
        with self.lock:
            for (pool, instance) in sorted(set(self.latest) | alive):
                p = pools.setdefault(pool, {"pool": pool, "workers": [], "robots": {}, "warnings": []})
                s = self.latest.get((pool, instance))
                if s is None:
                    p["warnings"].append(f"{instance}: alive but not reporting stats")
                    continue
                if (pool, instance) not in alive:
                    p["warnings"].append(f"{instance}: stopped (liveliness token gone)")
                    continue
                if now - self.seen_at[(pool, instance)] > 2.5:
                    silent_s = now - self.seen_at[(pool, instance)]
                    p["warnings"].append(f"{instance}: stopped reporting {silent_s:.1f} s ago")
                p["workers"].append({"instance": instance, "host": s.host, "rate_hz": s.rate_hz,
                                     "proc_ms_p50": s.proc_ms_p50, "busy": s.extra.get("pool_busy_share"),
                                     "health": s.health, "status": s.status})
                for key, v in s.extra.items():
                    if not key.startswith("robot."):
                        continue
                    rid, _, what = key[len("robot."):].rpartition(".")
                    if robot not in ("*", rid):
                        continue
                    r = p["robots"].setdefault(rid, {"robot": rid, "weight": v if what == "weight" else 1.0,
                                                     "share": 0.0, "hz": 0.0, "queue": 0.0, "unsolicited": 0.0})
                    if what == "weight":
                        r["weight"] = v
                    elif what in ("share", "hz", "queue", "unsolicited"):
                        r[what] += v
        for p in pools.values():
            n = max(1, len(p["workers"]))
            for r in p["robots"].values():
                r["share"] /= n  # of the pool: the mean of its share at each worker
            p["robots"] = sorted(p["robots"].values(), key=lambda r: r["robot"])
        return list(pools.values())


def format_pools(pools: list[dict]) -> list[str]:
    lines = []
    for p in pools:
        lines.append(f"pool {p['pool']}: {len(p['workers'])} worker(s)")
        for w in p["workers"]:
            mark = {"ok": " ", "starting": " ", "degraded": "!", "failed": "X"}.get(w["health"], "?")
            busy = "    -" if w["busy"] is None else f"{w['busy']:5.0%}"
            lines.append(f"  {mark} worker {w['instance'][:24]:24} {w['host'][:16]:16} {w['rate_hz']:5.1f}Hz "
                         f"{w['proc_ms_p50']:6.1f}ms {busy} busy  {w['status']}")
        if p["robots"]:
            lines.append(f"    {'robot':20} {'weight':>6} {'share':>6} {'maps/s':>7} {'queue':>5} {'unsolicited':>11}")
        for r in p["robots"]:
            lines.append(f"    {r['robot'][:20]:20} {r['weight']:6g} {r['share']:6.0%} {r['hz']:7.1f} "
                         f"{r['queue']:5.0f} {r['unsolicited']:11.0f}")
        lines += [f"  WARNING: {w}" for w in p["warnings"]]
    return lines
