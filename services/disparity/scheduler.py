"""A fleet pool's fair scheduler, the pure bookkeeping of one pool worker (no Zenoh, unit-tested):
which robot is granted the next frame, by start-time fair queueing over the robots' weights, the
grants out and the items queued, expiry and the per-robot report. The protocol and the reasons
for it are in fleet.py (the worker's Zenoh shell)."""
from __future__ import annotations

import os
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from common.errors import BallbotError

GRANT_BYTES = 16
RATE_WINDOW_S = 5.0  # served maps/s per robot: over this window
BUSY_WINDOW_S = 5.0  # the worker's share of time on items (`status`): over this window


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
        # seconds spent on items, taken to finished: over a span of the clock, the share of it the worker
        # had work (what the pool did not feed it, it idled: `bench fleet` weighs that, not the machine's load)
        self.busy_s = 0.0
        self._busy_marks: deque[tuple[float, float]] = deque()  # (clock, busy_s then)
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
            if self.busy_since is not None:
                self.busy_s += max(0.0, now - self.busy_since)
            self.busy_since = None
            if compute_s is None:
                f.counts["stale"] += 1
                return
            f.cost_s = compute_s if not f.cost_s else 0.8 * f.cost_s + 0.2 * compute_s
            self.cost_s = compute_s if not self.cost_s else 0.9 * self.cost_s + 0.1 * compute_s
            f.served.append(now)
            f.counts["served"] += 1

    def busy_share(self, window_s: float = BUSY_WINDOW_S) -> float | None:
        """The share of the last window_s (of the clock) spent on items, the item being computed
        included; None until a second of history. Called periodically (the worker's report)."""
        now = self.clock()
        with self.cond:
            busy = self.busy_s + (now - self.busy_since if self.busy_since is not None else 0.0)
            marks = self._busy_marks
            marks.append((now, busy))
            while len(marks) > 2 and now - marks[1][0] >= window_s:
                marks.popleft()
            t0, b0 = marks[0]
            return None if now - t0 < 1.0 else min(1.0, max(0.0, (busy - b0) / (now - t0)))

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
