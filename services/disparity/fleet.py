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

FairScheduler is the pure bookkeeping (no Zenoh, unit-tested); run_pool_worker is the Zenoh shell.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from common import codec
from common.errors import BallbotError, DecodeError
from common.keys import topic
from common.messages import PoolDemand, PoolGrant, StereoFrame, WorkDone
from common.node import Node, qos

log = logging.getLogger("ballbot.fleet")

GRANT_BYTES = 16
RATE_WINDOW_S = 5.0  # served maps/s per robot: over this window


def parse_weights(value: Any) -> dict[str, float]:
    """`robotA=2,robotB=1` (a flag or environment variable) or a mapping (YAML) -> {robot: weight}."""
    if value is None or value == "":
        return {}
    if isinstance(value, dict):
        items = list(value.items())
    elif isinstance(value, str):
        items = []
        for part in value.split(","):
            part = part.strip()
            if not part:
                continue
            if "=" not in part:
                raise ValueError(f"pool weights: {part!r} is not robot=weight (e.g. robotA=2,robotB=1)")
            k, v = part.split("=", 1)
            items.append((k.strip(), v.strip()))
    else:
        raise ValueError(f"pool weights: expected robot=weight pairs or a mapping, got {type(value).__name__}")
    out: dict[str, float] = {}
    for k, v in items:
        try:
            w = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"pool weights: {k}={v!r}: the weight is not a number") from None
        if not k or "/" in k or "*" in k:
            raise ValueError(f"pool weights: {k!r} is not a robot id")
        if not 0 < w <= 1000:
            raise ValueError(f"pool weights: {k}={w:g}: a weight is > 0 and <= 1000")
        out[k] = w
    return out


@dataclass
class Item:
    payload: Any  # bytes, or a Zenoh payload not copied yet
    attachment: bytes | None
    received: float  # monotonic
    robot: str
    grant: str = ""  # "" for an item pushed on the worker's own robot's key
    tag: float = 0.0  # SFQ start tag
    priority: bool = False  # granted beyond the waiting slots to a robot within its share: first among equal tags


@dataclass
class Flow:
    """One robot at this worker."""

    robot: str
    weight: float
    finish: float = 0.0  # virtual finish tag of its last granted (or pushed) item
    want_until: float = 0.0  # monotonic; wanting until then (a demand refreshes it)
    grants: dict[str, tuple[float, float, bool]] = field(default_factory=dict)  # grant -> (issued, start tag, priority)
    queued: deque = field(default_factory=deque)  # Items received, not started
    computing: int = 0
    cost_s: float = 0.0  # EMA of its compute time; 0: not measured yet
    served: deque = field(default_factory=deque)  # monotonic times of finished maps (RATE_WINDOW_S)
    counts: dict[str, int] = field(default_factory=lambda: {k: 0 for k in (
        "granted", "received", "served", "declined", "expired", "unsolicited", "stale", "superseded")})
    last_active: float = 0.0
    last_granted: float = 0.0


class FairScheduler:
    """Which robot this worker lets send the next frame, and which received item it computes next.
    Thread-safe (one lock; `cond` is notified when an item becomes ready).

    waiting: items a worker holds beside the one it computes (granted or received): 1 keeps a frame
    ready when the current one ends, and no robot's frame waits behind more than one other.
    Each robot holds at most one of them, so with more robots than slots nobody is skipped twice.
    """

    def __init__(self, weights: dict[str, float] | None = None, default_weight: float = 1.0, waiting: int = 1,
                 grant_ttl_s: float = 1.0, want_ttl_s: float = 0.5, max_robots: int = 64,
                 push_capacity: int = 4, clock: Callable[[], float] = time.monotonic):
        if waiting < 1:
            raise BallbotError(f"pool queue: at least 1 item waiting beside the one computed, got {waiting}")
        self.weights = dict(weights or {})
        self.default_weight = default_weight
        self.waiting = waiting
        self.grant_ttl_s, self.want_ttl_s = grant_ttl_s, want_ttl_s
        self.max_robots = max_robots
        self.push_capacity = push_capacity
        self.clock = clock
        self.cond = threading.Condition()
        self.flows: dict[str, Flow] = {}
        self.vtime = 0.0  # start tag of the item last started
        self.busy_since: float | None = None  # when the item being computed started
        self.cost_s = 0.0  # EMA over every robot: a new robot's first estimate
        self.counters = {k: 0 for k in ("granted", "declined", "expired", "unsolicited", "too_many_robots",
                                        "superseded", "priority")}

    # -- flows ------------------------------------------------------------------------------------
    def _flow(self, robot: str, now: float, create: bool = True) -> Flow | None:
        f = self.flows.get(robot)
        if f is None and create:
            if len(self.flows) >= self.max_robots and not self._forget_idle(now):
                self.counters["too_many_robots"] += 1
                return None
            f = self.flows[robot] = Flow(robot, self.weights.get(robot, self.default_weight), finish=self.vtime)
        if f is not None:
            f.last_active = now
        return f

    def _forget_idle(self, now: float) -> bool:
        idle = [f for f in self.flows.values() if not (f.grants or f.queued or f.computing)
                and f.want_until <= now]
        if not idle:
            return False
        del self.flows[min(idle, key=lambda f: f.last_active).robot]
        return True

    def _cost(self, f: Flow) -> float:
        """An item's cost in virtual time: 1, times how much dearer this robot's frames are than the
        worker's average (larger images take longer: the share is of the worker's time)."""
        if not f.cost_s or not self.cost_s:
            return 1.0
        return min(16.0, max(1 / 16, f.cost_s / self.cost_s))

    def _start_tag(self, f: Flow) -> float:
        return max(f.finish, self.vtime)

    def _advance(self, f: Flow) -> float:
        start = self._start_tag(f)
        f.finish = start + self._cost(f) / f.weight
        return start

    def _below_share(self, f: Flow, now: float) -> bool:
        """Did f get less than 0.8 x its weighted share of what this worker served lately?"""
        served = {g.robot: sum(1 for t in g.served if now - t <= RATE_WINDOW_S) for g in self.flows.values()}
        total = sum(served.values())
        if total < 2 * len(self.flows):
            return True  # too little history to tell: nobody is backlogged for long yet
        weights = sum(g.weight for g in self.flows.values() if self.active(g, now) or g is f)
        return served[f.robot] < 0.8 * total * f.weight / weights

    def _held(self) -> int:
        """Granted items not started (pushed ones of the worker's own robot are bounded by its
        dispatcher, and take turns with these in take())."""
        return sum(len(f.grants) + sum(1 for i in f.queued if i.grant) for f in self.flows.values())

    # -- the robots' side ---------------------------------------------------------------------------
    def demand(self, robot: str, want: bool, decline: Sequence[str] = ()) -> None:
        now = self.clock()
        with self.cond:
            f = self._flow(robot, now, create=want)
            if f is None:
                return
            for g in decline:
                issued = f.grants.pop(g, None)
                if issued is not None:
                    f.counts["declined"] += 1
                    self.counters["declined"] += 1
                    f.finish = min(f.finish, issued[1])  # a grant given back costs the robot no share
            f.want_until = now + self.want_ttl_s if want else 0.0

    def next_grant(self) -> tuple[str, str] | None:
        """-> (robot, grant id) for the robot to send its next frame, or None (no slot, or nobody
        wants). The robot's want is spent: it asks again if it still wants more.

        A robot within its share (it got less than 0.8 x its share of this worker's last 5 s: it
        wants less than its share, or was idle) may get one grant beyond the waiting slots: its frame then starts right
        after the item being computed, ahead of the backlogged robots' waiting item, so its latency
        stays about what it is alone; the backlogged robots lose nothing of their share (the
        waiting item is merely later)."""
        now = self.clock()
        with self.cond:
            wanting = [f for f in self.flows.values()
                       if f.want_until > now and not f.grants and not f.queued]
            if not wanting:
                return None
            held = self._held()
            priority = held >= self.waiting
            if priority:
                if held > self.waiting:
                    return None
                tags = [t for g in self.flows.values() for t in [s for _, s, _ in g.grants.values()]
                        + [i.tag for i in g.queued if i.grant]]
                wanting = [f for f in wanting if self._below_share(f, now)
                           and (not tags or self._start_tag(f) <= min(tags))]
                if not wanting:
                    return None
                self.counters["priority"] += 1
            f = min(wanting, key=lambda f: (self._start_tag(f), f.last_granted))
            start = self._advance(f)
            grant = os.urandom(GRANT_BYTES).hex()
            f.grants[grant] = (now, start, priority)
            f.want_until = 0.0
            f.last_granted = now
            f.counts["granted"] += 1
            self.counters["granted"] += 1
            return f.robot, grant

    def arrived(self, robot: str, grant: str, payload: bytes, attachment: bytes | None) -> str:
        """A frame from `robot` carrying `grant`. -> 'ok' (queued), 'expired' (its grant timed out
        lately: the sender gets a failed receipt) or 'unsolicited' (no such grant: dropped unread)."""
        now = self.clock()
        with self.cond:
            f = self.flows.get(robot)
            issued = f.grants.pop(grant, None) if f is not None and grant else None
            if f is None or issued is None:
                self.counters["unsolicited"] += 1
                if f is not None:
                    f.counts["unsolicited"] += 1
                return "unsolicited"
            f.counts["received"] += 1
            f.last_active = now
            f.queued.append(Item(payload, attachment, now, robot, grant, issued[1], issued[2]))
            self.cond.notify_all()
            return "ok"

    def push(self, robot: str, payload: bytes, attachment: bytes | None) -> Item | None:
        """An item pushed on the worker's own robot's key (no grant: that robot's dispatcher bounds
        what it has in flight). Tagged like a granted one, so its robot gets its share and no more.
        -> the item dropped to make room (the oldest, beyond push_capacity), if any."""
        now = self.clock()
        with self.cond:
            f = self._flow(robot, now)
            if f is None:
                return None
            f.counts["received"] += 1
            f.queued.append(Item(payload, attachment, now, robot, "", self._advance(f)))
            dropped = None
            if len(f.queued) > self.push_capacity:
                dropped = f.queued.popleft()
                f.counts["superseded"] += 1
                self.counters["superseded"] += 1
            self.cond.notify_all()
            return dropped

    # -- the worker's side ----------------------------------------------------------------------------
    def take(self, timeout: float) -> Item | None:
        """The received item with the smallest start tag (its robot's turn), or None within timeout."""
        with self.cond:
            if not any(f.queued for f in self.flows.values()):
                self.cond.wait(timeout)
            ready = [f for f in self.flows.values() if f.queued]
            if not ready:
                return None
            f = min(ready, key=lambda f: (f.queued[0].tag, not f.queued[0].priority))
            item = f.queued.popleft()
            f.computing += 1
            self.vtime = max(self.vtime, item.tag)
            self.busy_since = self.clock()
            return item

    def finished(self, item: Item, compute_s: float | None) -> None:
        """The item is done (compute_s: its compute time, None when it was dropped unmatched)."""
        now = self.clock()
        with self.cond:
            f = self.flows.get(item.robot)
            if f is None:
                return
            f.computing = max(0, f.computing - 1)
            self.busy_since = None
            if compute_s is None:
                f.counts["stale"] += 1
                return
            f.cost_s = compute_s if not f.cost_s else 0.8 * f.cost_s + 0.2 * compute_s
            self.cost_s = compute_s if not self.cost_s else 0.9 * self.cost_s + 0.1 * compute_s
            f.served.append(now)
            f.counts["served"] += 1

    def grant_wait_s(self, robot: str, grant: str) -> float:
        """How long the frame sent against this grant will wait here before it is started: the rest
        of the item being computed, and the granted items ahead of it (a robot that holds grants of
        several workers sends its frame to the one that starts it first)."""
        now = self.clock()
        with self.cond:
            f = self.flows.get(robot)
            if f is None or grant not in f.grants:
                return 0.0
            cost = self.cost_s or 0.0
            rest = max(0.0, self.busy_since + cost - now) if self.busy_since is not None else 0.0
            _, tag, priority = f.grants[grant]
            ahead = sum(1 for g in self.flows.values() for i in g.queued if i.grant and
                        (i.tag, not i.priority) < (tag, not priority))
            ahead += sum(1 for g in self.flows.values() for gid, (_, t, p) in g.grants.items()
                         if gid != grant and (t, not p) < (tag, not priority))
            return rest + ahead * cost

    def expire(self) -> list[tuple[str, str]]:
        """Grants not used within grant_ttl_s are withdrawn (the slot goes to the next robot), and
        long-idle robots forgotten. -> [(robot, grant)] withdrawn."""
        now = self.clock()
        out = []
        with self.cond:
            for f in list(self.flows.values()):
                for g, (t, start, _) in list(f.grants.items()):
                    if now - t > self.grant_ttl_s:
                        del f.grants[g]
                        f.counts["expired"] += 1
                        self.counters["expired"] += 1
                        f.finish = min(f.finish, start)
                        out.append((f.robot, g))
                while f.served and now - f.served[0] > RATE_WINDOW_S:
                    f.served.popleft()
                if not (f.grants or f.queued or f.computing or f.served) and now - f.last_active > 60.0:
                    del self.flows[f.robot]
        return out

    def active(self, f: Flow, now: float) -> bool:
        return bool(f.want_until > now or f.grants or f.queued or f.computing
                    or (f.served and now - f.served[-1] < 1.0))

    def report(self) -> dict[str, dict[str, float]]:
        """Per robot: weight, share (its weight over those of the robots active now), queue
        (granted or received, not started), maps/s served over the last RATE_WINDOW_S, counters."""
        now = self.clock()
        with self.cond:
            active = [f for f in self.flows.values() if self.active(f, now)]
            total = sum(f.weight for f in active) or 1.0
            out = {}
            for f in self.flows.values():
                span = min(RATE_WINDOW_S, max(1e-3, now - (f.served[0] if f.served else now)))
                n = len([t for t in f.served if now - t <= RATE_WINDOW_S])
                out[f.robot] = {"weight": f.weight, "share": f.weight / total if f in active else 0.0,
                                "queue": float(len(f.grants) + len(f.queued)), "computing": float(f.computing),
                                "hz": n / max(span, 1.0) if n else 0.0, "wanting": float(f.want_until > now),
                                **{k: float(v) for k, v in f.counts.items()}}
            return out

    def share_of(self, robot: str) -> tuple[int, float]:
        now = self.clock()
        with self.cond:
            active = [f for f in self.flows.values() if self.active(f, now)]
            total = sum(f.weight for f in active) or 1.0
            f = self.flows.get(robot)
            return len(active), (f.weight / total if f is not None else 0.0)

    def queued(self) -> int:
        with self.cond:
            return sum(len(f.queued) for f in self.flows.values())


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
    from services.disparity.results import result_header

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
            node.extra["demand_oversized"] = node.extra.get("demand_oversized", 0) + 1
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
            node.extra["in_work_oversized"] = node.extra.get("in_work_oversized", 0) + 1
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
            node.extra["in_work_oversized"] = node.extra.get("in_work_oversized", 0) + 1
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
                node.extra["too_old"] = node.extra.get("too_old", 0) + 1
                receipt(item, msg, f"too old: {age_now:.0f} ms > {max_age_ms:.0f} ms")
                sched.finished(item, None)
                continue
            ok = False
            with node.processing(msg):
                result = computer.compute(msg, me)
                result.stages[node.service] = node.clock.wall_ns()
                data = codec.encode(result)
                name = "pool_result" if item.grant else "work_result"
                publisher(name, item.robot).put(data, attachment=result_header(result, nonce))
                node._published(node.age_ns(msg))
                rates.add("out_work_result", len(data))
                computer.report(node)
                ok = True
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
    busy = [r for r, f in report.items() if f["share"] > 0]
    node.status = f"ok: {what}, " + (f"serving {len(busy)} robot(s)" if busy else "waiting for work")
