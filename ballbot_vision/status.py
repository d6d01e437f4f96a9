"""`ballbot-vision status`: every live service instance, from its stats and liveliness token."""
from __future__ import annotations

import json
import threading
import time

from .common import codec
from .common.errors import DecodeError
from .common.keys import topic
from .common.messages import ServiceStats
from .common.zenoh_session import ZenohOptions, open_session


def _fmt_bytes(b: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if b < 1000:
            return f"{b:.0f}{unit}"
        b /= 1000
    return f"{b:.0f}TB"


def status(opts: ZenohOptions, robot: str, wait_s: float, as_json: bool) -> int:
    latest: dict[str, ServiceStats] = {}
    seen_at: dict[str, float] = {}
    lock = threading.Lock()

    def on_stats(sample) -> None:
        try:
            s = codec.decode(sample.payload.to_bytes(), ServiceStats)
        except DecodeError:
            return
        with lock:
            latest[f"{s.robot_id}/{s.service}/{s.instance}"] = s
            seen_at[f"{s.robot_id}/{s.service}/{s.instance}"] = time.monotonic()

    alive_prefix = topic("alive").pattern(robot)
    with open_session(opts) as session:
        session.declare_subscriber(topic("stats").pattern(robot), on_stats)
        time.sleep(wait_s)  # stats arrive once a second: listen for a couple of periods
        alive = set()
        for reply in session.liveliness().get(alive_prefix, timeout=2.0):
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")  # ballbot/<robot>/alive/<service>/<instance>
                alive.add(f"{parts[1]}/{parts[3]}/{parts[4]}")
    now = time.monotonic()
    with lock:
        names = sorted(set(latest) | alive)
        rows = []
        warnings = []
        for name in names:
            s = latest.get(name)
            if s is None:
                warnings.append(f"{name}: alive but not reporting stats")
                continue
            if name not in alive:
                warnings.append(f"{name}: stopped (liveliness token gone)")
            elif now - seen_at[name] > 2.5:
                warnings.append(f"{name}: stopped reporting {now - seen_at[name]:.1f} s ago")
            rows.append(s)
    if as_json:
        print(json.dumps({"instances": [r.model_dump() for r in rows], "warnings": warnings}))
    else:
        print(f"{'service':10} {'instance':28} {'rate':>7} {'proc':>8} {'age':>8} {'drops':>6} {'dec.err':>7} "
              f"{'errors':>6} {'in':>8} {'out':>8}  status")
        for s in rows:
            inb = sum(v for k, v in s.extra.items() if k.startswith("in_"))
            outb = sum(v for k, v in s.extra.items() if k.startswith("out_"))
            print(f"{s.service:10} {s.instance[:28]:28} {s.rate_hz:5.1f}Hz {s.proc_ms_p50:6.1f}ms "
                  f"{s.age_ms_p50:6.1f}ms {s.drops:6d} {s.decode_errors:7d} {s.errors:6d} {_fmt_bytes(inb):>8} "
                  f"{_fmt_bytes(outb):>8}  {s.status}")
        for w in warnings:
            print(f"WARNING: {w}")
        if not names:
            print("no service instance found (is the pipeline up, and --connect right?)")
    return 0 if names else 1
