"""`ballbot-vision status`: every live service instance, from its stats and liveliness token, read at
a glance: one verdict line for the pipeline, then one row per instance with its health, rates (per
second, over the last stats period) and latency. `--json` gives the same for scripts.

Trust: a robot service's stats count only from its own key (`stats/<service>/<instance>`, which the
gateway lets no offboard user write) and only when the message names that same service and instance.
Offboard disparity workers report on their own key (`stats/worker/<instance>`, the only stats key the
worker role may write): their rows are shown as self-reported and never move the verdict (the
dispatcher's own stats say what the robot got from its workers).

Exit status: 0 healthy, 3 something degraded, failed or gone, 1 nothing found."""
from __future__ import annotations

import json
import threading
import time

from common import codec
from common.errors import DecodeError
from common.keys import WORKER_SEGMENT, topic
from common.messages import ServiceStats
from common.zenoh_session import LiveTokens, ZenohOptions, open_session

ORDER = {"router": 0, "capture": 1, "rectify": 2, "disparity": 3, "segmenter": 4}


def _fmt_rate(bps: float) -> str:
    for unit in ("B/s", "kB/s", "MB/s", "GB/s"):
        if bps < 1000:
            return f"{bps:.0f}{unit}"
        bps /= 1000
    return f"{bps:.0f}TB/s"


def stats_source(key: str, s: ServiceStats) -> tuple[str, bool] | None:
    """Where a stats message may be believed: -> (row key 'robot/service/instance' from the KEY it came
    on, trusted), or None for one whose message names another robot, service or instance than its
    key (a forgery, or a misconfigured sender). Workers' keys are never trusted."""
    parts = key.split("/")  # ballbot/<robot>/stats/<service>/<instance>
    if len(parts) != 5 or parts[2] != "stats":
        return None
    rid, service, instance = parts[1], parts[3], parts[4]
    if service == WORKER_SEGMENT:
        ok = s.robot_id == rid and s.instance == instance
        return (f"{rid}/{service}/{instance}", False) if ok else None
    if (s.robot_id, s.service, s.instance) != (rid, service, instance):
        return None
    return f"{rid}/{service}/{instance}", True


def as_worker(s: ServiceStats) -> ServiceStats:
    """A worker speaks for itself only: whatever service its message claims, it is a disparity worker."""
    return s.model_copy(update={"service": "disparity", "role": "worker"})


def name_of(s: ServiceStats) -> str:
    """What a person calls it: the disparity service is a dispatcher or a worker."""
    return s.role if s.service == "disparity" and s.role else s.service


def link_rates(s: ServiceStats) -> tuple[float, float]:
    """Bytes per second in and out, summed over the instance's links."""
    inb = sum(v for k, v in s.extra.items() if k.startswith("rate_in_") and k.endswith("_Bps"))
    outb = sum(v for k, v in s.extra.items() if k.startswith("rate_out_") and k.endswith("_Bps"))
    return inb, outb


def per_second(first: ServiceStats | None, last: ServiceStats, field: str) -> float | None:
    if first is None or last.uptime_s <= first.uptime_s:
        return None
    return (getattr(last, field) - getattr(first, field)) / (last.uptime_s - first.uptime_s)


def verdict(rows: list[dict], warnings: list[str]) -> tuple[str, str]:
    """-> (ok | degraded | failed, one line a person reads first). Only trusted rows count."""
    rows = [r for r in rows if r.get("trusted", True)]
    bad = [r for r in rows if r["health"] in ("degraded", "failed")]
    seg = [r for r in rows if r["service"] == "segmenter"]
    if any(r["health"] == "failed" for r in bad):
        level = "failed"
    elif bad or warnings:
        level = "degraded"
    else:
        level = "ok"
    parts = []
    if seg:
        s = seg[0]
        if not s["status"].startswith("ok"):  # stale, or its lists say they cannot vouch for their view
            level = "degraded" if level == "ok" else level
            parts.append(f"obstacles {s['status']}")
        else:
            parts.append(f"obstacles at {s['rate_hz']:.1f} Hz, {s['age_ms_p50']:.0f} ms after capture")
    else:
        parts.append("no segmenter: no obstacles")
        level = "degraded" if level == "ok" else level
    parts += [f"{r['name']} {r['status']}" for r in bad]
    parts += warnings
    return level, "; ".join(parts)


def status(opts: ZenohOptions, robot: str, wait_s: float, as_json: bool) -> int:
    first: dict[str, ServiceStats] = {}
    latest: dict[str, ServiceStats] = {}
    seen_at: dict[str, float] = {}
    trusted: dict[str, bool] = {}
    forged: dict[str, str] = {}  # key it came on -> what it claimed
    lock = threading.Lock()

    def on_stats(sample) -> None:
        try:
            s = codec.decode(sample.payload.to_bytes(), ServiceStats)
        except DecodeError:
            return
        where = stats_source(str(sample.key_expr), s)
        with lock:
            if where is None:
                forged[str(sample.key_expr)] = f"{s.robot_id}/{s.service}/{s.instance}"
                return
            key, ok = where
            s = s if ok else as_worker(s)
            first.setdefault(key, s)
            latest[key] = s
            seen_at[key] = time.monotonic()
            trusted[key] = ok

    from ballbot_vision.pool_status import PoolWatch, format_pools

    alive_prefix = topic("alive").pattern(robot)
    with open_session(opts) as session:
        session.declare_subscriber(topic("stats").pattern(robot), on_stats)
        tokens = LiveTokens(session, alive_prefix)
        pool_watch = PoolWatch(session)  # fleet pools: their workers report under ballbot/pool/<pool>/
        time.sleep(wait_s)  # stats arrive once a second: listen for a couple of periods
        pools = pool_watch.collect(robot)
        alive = set()
        for token in tokens.keys():
            parts = token.split("/")  # ballbot/<robot>/alive/<service>/<instance>
            alive.add(f"{parts[1]}/{parts[3]}/{parts[4]}")
    now = time.monotonic()
    with lock:
        names = sorted(set(latest) | alive)
        rows: list[dict] = []
        warnings: list[str] = []
        notes: list[str] = []  # about workers' own keys: shown, never in the verdict
        for key in names:
            s = latest.get(key)
            said = notes if key.split("/")[1] == WORKER_SEGMENT else warnings
            if s is None:
                said.append(f"{key}: alive but not reporting stats")
                continue
            if key not in alive:
                said.append(f"{key}: stopped (liveliness token gone)")
            elif now - seen_at[key] > 2.5:
                said.append(f"{key}: stopped reporting {now - seen_at[key]:.1f} s ago")
            inb, outb = link_rates(s)
            f = first.get(key)
            f = f if f is not s else None
            rows.append({**s.model_dump(), "name": name_of(s), "trusted": trusted[key], "in_Bps": inb, "out_Bps": outb,
                         "drops_per_s": per_second(f, s, "drops"),
                         "errors_per_s": (None if f is None else
                                          ((s.errors + s.decode_errors) - (f.errors + f.decode_errors))
                                          / max(1e-3, s.uptime_s - f.uptime_s))})
        for key, claimed in sorted(forged.items()):
            warnings.append(f"ignored stats on {key} that claim to be {claimed}'s (the message does not match its key)")
    rows.sort(key=lambda r: (r["robot_id"], ORDER.get(r["service"], 9), r["role"] != "dispatcher", r["instance"]))
    level, line = verdict(rows, warnings)
    if as_json:
        print(json.dumps({"pipeline": {"health": level, "summary": line}, "instances": rows, "warnings": warnings,
                          "pools": pools, "notes": notes}))
    elif not names and not pools:
        print("no service instance found (is the pipeline up, and --connect right?)")
    elif not names:
        print("\n".join(format_pools(pools)))
    else:
        print(f"pipeline {level.upper()}: {line}")
        print(f"{'':2}{'name':10} {'instance':26} {'rate':>7} {'proc':>7} {'age':>7} {'drops':>7} {'errors':>7} "
              f"{'in':>9} {'out':>9}  status")
        for r in rows:
            mark = {"ok": " ", "starting": " ", "degraded": "!", "failed": "X"}[r["health"]]

            def ps(v: float | None) -> str:
                return "-" if v is None else f"{v:.1f}/s"

            print(f"{mark:2}{r['name']:10} {r['instance'][:26]:26} {r['rate_hz']:5.1f}Hz {r['proc_ms_p50']:5.1f}ms "
                  f"{r['age_ms_p50']:5.0f}ms {ps(r['drops_per_s']):>7} {ps(r['errors_per_s']):>7} "
                  f"{_fmt_rate(r['in_Bps']):>9} {_fmt_rate(r['out_Bps']):>9}  {r['status']}"
                  + ("" if r["trusted"] else "  (self-reported)"))
        if any(not r["trusted"] for r in rows):
            print("(self-reported: a worker's own stats, from a key the gateway's worker role may write; shown, "
                  "never counted in the verdict)")
        for w in warnings:
            print(f"WARNING: {w}")
        if pools:
            print("\n".join(format_pools(pools)))
        for n in notes:
            print(f"note (worker): {n}")
    if not names:
        return 0 if pools and not any(p["warnings"] for p in pools) else (3 if pools else 1)
    return 0 if level == "ok" else 3
