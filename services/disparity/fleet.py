"""A fleet pool: disparity workers shared by any robot, each robot served its weighted share.

    robot A's dispatcher --demand/A (want)-------------> every worker of pool P
                         <--grant/A/<w> (one frame)----- worker w (fair queueing over the robots)
                         --work/<w>/A (frame+grant)-----> w
                         <--result/A/<w> (map+nonce)----- w   (checked, republished on ballbot/A/disparity)

Keys (common/keys.py, `ballbot/pool/<pool>/...`) carry the robot id where a router's access control
can pin it: a robot sends only `work/*/<its id>` and `demand/<its id>`, reads only `grant/<its id>/*`,
`result/<its id>/*` and `done/<its id>/*` (deploy/zenoh/pool-acl.py writes the rules).

Why grants and not pushed work: with pushed work, four robots keeping two items each at a worker
means an item waits behind up to seven others, so every robot's latency grows with the fleet and a
robot that sends more gets more. Here the worker decides. A robot's dispatcher only says it wants
(it holds a frame and no grant); the worker grants one frame at a time, by start-time fair queueing
(SFQ: each robot's virtual time advances by its measured compute cost over its weight; the robot
with the smallest start tag is granted next; a robot returning from idle starts at the current
virtual time, so it banks no credit). The grant goes out when the worker starts computing an item,
so the granted frame (the robot's newest, sent only now) travels while the worker computes and waits
at most one item: a robot's latency stays about one item of wait plus its own compute, whatever the
fleet size, and a robot that wants more than its share gets only its share while others want theirs.
A frame without a valid grant is dropped unread (counted: `unsolicited`); a grant not used within
its ttl is reissued to the next robot; a dispatcher that holds no frame when a grant arrives gives
it back at once (`decline`), so a robot with little to do costs the others nothing.

The dispatcher side (trust, checks, republishing, fallback) is dispatcher.py's Dispatcher and results.py,
unchanged in what they check: a pool worker is one more worker there, named `<instance>@<pool>`,
that gets work only against its grants.

FairScheduler (scheduler.py) is the pure bookkeeping (no Zenoh, unit-tested); run_pool_worker here
is the Zenoh shell.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any

from common import codec
from common.errors import DecodeError
from common.keys import topic
from common.messages import PoolDemand, PoolGrant, StereoFrame, WorkDone
from common.node import Node, qos
from services.disparity.scheduler import FairScheduler, Item

log = logging.getLogger("ballbot.fleet")

# --- grant in a work item's attachment ----------------------------------------------------------------

def attachment_grant(raw: bytes | None) -> str:
    """The grant id a work item's attachment carries ("" for none or garbage)."""
    import msgpack

    try:
        doc = msgpack.unpackb(raw) if raw is not None and len(raw) <= 1024 else None
        g = doc.get("grant") if isinstance(doc, dict) else None
        return g if isinstance(g, str) and len(g) <= 64 else ""
    except Exception:
        return ""


# --- the pool worker (any host) ----------------------------------------------------------------------

def _chunk(key: str, index: int) -> str:
    return str(key).split("/")[index]


def run_pool_worker(node: Node, settings: Any) -> None:
    """A worker of pool settings.pool (and, with serve_robot, of its own robot's work key too)."""

    from services.disparity.computer import FrameComputer
    from services.disparity.envelope import parse_attachment, receipt_attachment
    from services.disparity.rates import Rates

    pool, me, home = settings.pool, node.instance, node.robot_id
    computer = FrameComputer(settings, 1.0, settings.result_encoding)
    sched = FairScheduler(settings.pool_weights, waiting=settings.pool_queue, grant_ttl_s=settings.pool_grant_ttl_s)
    rates = Rates(node)
    publishers: dict[tuple[str, str], Any] = {}  # (topic, robot) -> publisher; bounded like the flows
    seq = [0]
    lock = threading.Lock()

    def publisher(name: str, robot: str) -> Any:
        with lock:
            p = publishers.get((name, robot))
            if p is None:
                if len(publishers) >= 4 * sched.max_robots:
                    for k in list(publishers)[: len(publishers) // 2]:
                        publishers.pop(k).undeclare()
                if robot == home and name in ("work_result", "work_done"):
                    key = topic(name).key(home, instance=me)
                else:
                    key = topic(name).key(robot, pool=pool, instance=me)
                p = publishers[(name, robot)] = node.declare_publisher(key, **qos(topic(name)))
            return p

    def send_grants() -> None:
        while True:
            g = sched.next_grant()
            if g is None:
                return
            robot, grant = g
            robots, share = sched.share_of(robot)
            with lock:
                seq[0] += 1
                n = seq[0]
            msg = PoolGrant(robot_id=robot, seq=n, stamp_ns=time.time_ns(), worker=me, grant=grant,
                            ttl_ms=sched.grant_ttl_s * 1e3, robots=robots, share=min(1.0, share),
                            queued=sched.queued(), wait_ms=min(60000.0, sched.grant_wait_s(robot, grant) * 1e3))
            publisher("pool_grant", robot).put(codec.encode(msg))

    def on_demand(sample) -> None:
        robot = _chunk(sample.key_expr, -1)
        if len(sample.payload) > topic("pool_demand").max_bytes:
            node.count("demand_oversized")
            return
        try:
            d = codec.decode(sample.payload.to_bytes(), PoolDemand)
        except DecodeError as e:
            node.decode_errors += 1
            node.warn("demand", f"dropped a demand on {robot}'s key: {e}")
            return
        if d.robot_id != robot:
            node.decode_errors += 1
            node.warn("demand-robot", f"dropped a demand naming robot {d.robot_id!r} on {robot!r}'s key")
            return
        sched.demand(robot, d.want, d.decline)
        send_grants()

    def on_work(sample) -> None:
        node.count_input()
        n = len(sample.payload)
        robot = _chunk(sample.key_expr, -1)
        if n > topic("pool_work").max_bytes:
            node.count("in_work_oversized")
            return
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        grant = attachment_grant(att)
        verdict = sched.arrived(robot, grant, sample.payload, att)  # copied out of Zenoh only once taken
        rates.add("in_work", n)
        if verdict != "ok":
            node.warn("unsolicited", f"dropped a frame from {robot} without a grant of this worker "
                                     f"(counted in pool_unsolicited)")

    def on_home_work(sample) -> None:
        node.count_input()
        n = len(sample.payload)
        if n > topic("work").max_bytes:
            node.count("in_work_oversized")
            return
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        rates.add("in_work", n)
        dropped = sched.push(home, sample.payload.to_bytes(), att)
        if dropped is not None:
            receipt(dropped, None, "superseded: more items than the dispatcher may have in flight")

    def receipt(item: Item, msg: StereoFrame | None, reason: str, proc_ms: float = 0.0) -> None:
        try:
            _, _, nonce = parse_attachment(item.attachment)
        except DecodeError:
            return
        name = "work_done" if not item.grant else "pool_done"
        done = WorkDone(robot_id=item.robot, seq=msg.seq if msg else 0, stamp_ns=msg.stamp_ns if msg else 0,
                        worker=me, ok=False, reason=reason[:200], proc_ms=proc_ms)
        publisher(name, item.robot).put(codec.encode(done), attachment=receipt_attachment(nonce))

    subs = [node.subscribe(topic("pool_demand").pattern(pool=pool), on_demand),
            node.subscribe(topic("pool_work").pattern(pool=pool, instance=me), on_work)]
    if settings.serve_robot:
        subs.append(node.subscribe(topic("work").key(home, instance=me), on_home_work))
    for name in ("pool_grant", "pool_result", "pool_done") + (("work_result", "work_done") if settings.serve_robot
                                                              else ()):
        node.uses("publishes", topic(name).pattern(pool=pool))
    tokens = [node.declare_token(topic("pool_worker").key("", pool=pool, instance=me))]
    if settings.serve_robot:
        tokens.append(node.declare_token(topic("worker").key(home, instance=me)))
    node.status = f"ok: {computer.method} in pool {pool}, waiting for work"
    log.info("pool worker %s ready in pool %s%s", me, pool, f" and for robot {home}" if settings.serve_robot else "")

    next_house = 0.0
    try:
        while node.running:
            now = time.monotonic()
            if now >= next_house:
                next_house = now + 0.25
                sched.expire()
                _report(node, sched, rates, f"{computer.method} in pool {pool}")
                send_grants()
            item = sched.take(0.1)
            if item is None:
                continue
            send_grants()  # the next robot's frame travels while this one is computed
            t0 = time.perf_counter()
            msg = None
            try:
                payload = item.payload if isinstance(item.payload, bytes) else item.payload.to_bytes()
                msg = codec.decode(payload, StereoFrame)
                if msg.robot_id != item.robot:
                    raise DecodeError(f"StereoFrame: robot_id {msg.robot_id!r} on {item.robot!r}'s key")
                age_ms, max_age_ms, nonce = parse_attachment(item.attachment)
            except DecodeError as e:
                node.decode_errors += 1
                node.warn("decode", f"dropped work item from {item.robot}: {e}")
                sched.finished(item, None)
                continue
            age_now = age_ms + (time.monotonic() - item.received) * 1e3
            if age_now > max_age_ms:
                node.count("too_old")
                receipt(item, msg, f"too old: {age_now:.0f} ms > {max_age_ms:.0f} ms")
                sched.finished(item, None)
                continue
            name = "pool_result" if item.grant else "work_result"
            # the publisher is looked up inside answer's processing: a failure there costs this item only
            # (the lambda runs before the loop moves on, so its loop variables are this item's)
            ok = computer.answer(node, msg, me, nonce,
                                 lambda data, **kw: publisher(name, item.robot).put(data, **kw), rates)  # noqa: B023
            sched.finished(item, time.perf_counter() - t0 if ok else None)
            if not ok:
                receipt(item, msg, "failed (see worker log)", (time.perf_counter() - t0) * 1e3)
    finally:
        for t in tokens:
            try:
                t.undeclare()
            except Exception:
                pass
        del subs


def _report(node: Node, sched: FairScheduler, rates: Any, what: str) -> None:
    """Per-robot figures into the stats (`status` shows them per pool): robot.<id>.<what>."""
    rates.tick()
    report = sched.report()
    for k in [k for k in node.extra if k.startswith("robot.")]:
        if k.split(".")[1] not in report:
            del node.extra[k]
    for robot, figures in report.items():
        for k in ("weight", "share", "queue", "hz", "wanting", "served", "unsolicited", "expired", "declined"):
            node.extra[f"robot.{robot}.{k}"] = float(figures[k])
    node.extra.update({f"pool_{k}": float(v) for k, v in sched.counters.items()})
    node.extra["pool_busy_s"] = round(sched.busy_s, 4)  # the worker's seconds on items since it started
    share = sched.busy_share()
    if share is not None:  # of the last few seconds, on items: near 1, the pool is saturated
        node.extra["pool_busy_share"] = round(share, 3)
    busy = [r for r, f in report.items() if f["share"] > 0]
    node.status = f"ok: {what}, " + (f"serving {len(busy)} robot(s)" if busy else "waiting for work")
