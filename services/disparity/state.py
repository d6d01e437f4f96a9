"""The dispatcher's bookkeeping, pure (no Zenoh, unit-tested): which worker is alive and trusted,
what each has in flight, the verdict on every answer, the pool grants (see dispatcher.py)."""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.errors import BallbotError

log = logging.getLogger("ballbot.pool")


@dataclass
class WorkerSlot:
    name: str
    in_flight: dict[int, float] = field(default_factory=dict)  # seq -> monotonic send time
    tickets: dict[int, Any] = field(default_factory=dict)  # seq -> results.Ticket of the item in flight
    answering: set[int] = field(default_factory=set)  # in-flight seqs whose map is being checked
    assigned: int = 0
    completed: int = 0
    failed: int = 0
    timeouts: int = 0
    last_assigned: float = 0.0
    paused_until: float = 0.0  # after a timeout: no new work for a while unless it answers
    recent: deque = field(default_factory=lambda: deque(maxlen=512))  # (seq, (outcome, t, ticket)) finished lately
    # trust: a liveliness token alone is not a worker
    trust: str = "probation"  # probation (not proven yet) | trusted | quarantined
    strikes: int = 0  # consecutive work items without a good receipt
    next_probe: float = 0.0  # probation/quarantine: when it may get its next (single) probe frame
    probe_backoff_s: float = 1.0
    why: str = ""  # why it is quarantined
    quarantined_at: float = -1.0  # only an item sent after this (a probe) can bring it back
    rtt: deque = field(default_factory=lambda: deque(maxlen=32))  # s from send to receipt, recent items
    # a fleet pool's worker (fleet.py): work only against its grants, each good for one frame
    pooled: bool = False
    grants: deque = field(default_factory=deque)  # grant ids not used yet
    item_grant: dict[int, str] = field(default_factory=dict)  # seq -> the grant it was sent with
    last_grant: float = 0.0


class DispatchState:
    """Which worker is alive and trusted, what each has in flight, and the verdict on every receipt.
    Thread-safe; `cond` is notified on every change that can free a slot.

    Trust: a worker whose token appears is on probation: it gets one probe frame at a time, and
    its first good receipt makes it trusted. A worker that takes work and returns nothing good
    (timeouts, failed receipts: `strikes_to_quarantine` in a row, or one while on probation) is
    quarantined: no work but a single probe after a backoff (1 s doubling to max_probe_backoff_s);
    a good receipt brings it back. Only trusted workers count as alive for the onboard fallback, so
    a ghost token, a hung or a broken worker cannot starve the pool.

    Receipt timeouts adapt to each worker's measured send-to-receipt times (timeout_factor x their
    90th percentile, at least result_timeout_s, at most max_result_timeout_s), so a slow machine
    or a loaded robot is not mistaken for a dead worker.
    """

    def __init__(self, max_in_flight: int = 1, result_timeout_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic, strikes_to_quarantine: int = 3,
                 max_probe_backoff_s: float = 30.0, timeout_factor: float = 3.0, max_result_timeout_s: float = 30.0):
        if max_in_flight < 1:
            raise BallbotError(f"max_in_flight: must be >= 1, got {max_in_flight}")
        self.max_in_flight = max_in_flight
        self.result_timeout_s = result_timeout_s
        self.clock = clock
        self.strikes_to_quarantine = strikes_to_quarantine
        self.max_probe_backoff_s = max_probe_backoff_s
        self.timeout_factor = timeout_factor
        self.max_result_timeout_s = max(max_result_timeout_s, result_timeout_s)
        self.cond = threading.Condition()
        self.workers: dict[str, WorkerSlot] = {}
        self.counters: dict[str, int] = {k: 0 for k in (
            "dispatched", "completed", "failed", "timeouts", "lost_in_flight", "unknown_worker",
            "unknown_frame", "duplicate", "late", "workers_joined", "workers_left", "quarantined", "probes",
            "rejected", "grants")}

    # membership
    def add_worker(self, name: str, pooled: bool = False) -> bool:
        with self.cond:
            if name in self.workers:
                return False
            self.workers[name] = WorkerSlot(name, next_probe=self.clock(), pooled=pooled)
            self.counters["workers_joined"] += 1
            self.cond.notify_all()
            return True

    def remove_worker(self, name: str) -> int:
        """-> number of frames lost with it (its in-flight items)."""
        with self.cond:
            w = self.workers.pop(name, None)
            if w is None:
                return 0
            self.counters["workers_left"] += 1
            self.counters["lost_in_flight"] += len(w.in_flight)
            self.cond.notify_all()
            return len(w.in_flight)

    def alive(self) -> int:
        """Workers with a liveliness token (trusted or not)."""
        with self.cond:
            return len(self.workers)

    def trusted(self) -> int:
        """Workers that proved themselves and are not quarantined: only these replace the fallback."""
        with self.cond:
            return sum(1 for w in self.workers.values() if w.trust == "trusted")

    def available(self) -> int:
        """Trusted workers not paused after a missed answer: while there is none, the onboard
        fallback computes (a worker that went quiet costs the robot its timeout, not its strikes)."""
        with self.cond:
            now = self.clock()
            return sum(1 for w in self.workers.values() if w.trust == "trusted" and w.paused_until <= now)

    def timeout_for(self, w: WorkerSlot) -> float:
        if not w.rtt:
            return self.result_timeout_s
        p90 = float(np.percentile(np.fromiter(w.rtt, float), 90))
        return min(self.max_result_timeout_s, max(self.result_timeout_s, self.timeout_factor * p90))

    # assignment
    def _due_probe(self, now: float) -> list[WorkerSlot]:
        return [w for w in self.workers.values() if w.trust != "trusted" and not w.in_flight and w.next_probe <= now
                and self._granted(w, now)]

    def _granted(self, w: WorkerSlot, now: float) -> bool:
        """A robot's own worker needs nothing; a pool worker a live grant."""
        if not w.pooled:
            return True
        self._prune_grants(w, now)
        return bool(w.grants)

    def _free(self, now: float) -> list[WorkerSlot]:
        probes = self._due_probe(now)
        if probes:  # a probe first: a new worker is tried on the next frame, whoever else is free
            return probes
        return [w for w in self.workers.values()
                if w.trust == "trusted" and self._held(w) < self.max_in_flight and w.paused_until <= now
                and self._granted(w, now)]

    @staticmethod
    def _held(w: WorkerSlot) -> int:
        """Items a worker holds: in flight; for a pool worker not those whose map is being checked
        (it granted the next frame when it finished them)."""
        return len(w.in_flight) - (len(w.answering) if w.pooled else 0)

    def has_free(self) -> bool:
        with self.cond:
            return bool(self._free(self.clock()))

    def probe_due(self) -> bool:
        with self.cond:
            return bool(self._due_probe(self.clock()))

    def wait_free(self, timeout: float) -> bool:
        with self.cond:
            if self._free(self.clock()):
                return True
            self.cond.wait(timeout)
            return bool(self._free(self.clock()))

    def claim(self, seq: int, ticket: Any = None) -> str | None:
        """Assign frame `seq` to a worker due for a probe, else to the free trusted worker with the
        fewest items in flight (then the one idle longest). -> its name, or None if none is free.
        ticket (results.Ticket): what its answer must match (ticket_for())."""
        with self.cond:
            now = self.clock()
            free = self._free(now)
            if not free:
                return None
            # the soonest start: a pool worker's grant says when it would start our frame
            w = min(free, key=lambda s: (s.grants[0][3] if s.pooled and s.grants else now, len(s.in_flight),
                                         s.last_assigned))
            if w.trust != "trusted":
                self.counters["probes"] += 1
            if w.pooled:
                w.item_grant[seq] = w.grants.popleft()[0]
            w.in_flight[seq] = now
            w.tickets[seq] = ticket
            w.assigned += 1
            w.last_assigned = now
            self.counters["dispatched"] += 1
            return w.name

    def grant_of(self, name: str, seq: int) -> str:
        """The grant a pool worker's item `seq` was claimed with ("" for a robot's own worker)."""
        with self.cond:
            w = self.workers.get(name)
            return w.item_grant.pop(seq, "") if w is not None else ""

    # fleet pool grants (fleet.py)
    def add_grant(self, name: str, grant: str, ttl_s: float = 1.0, wait_s: float = 0.0) -> bool:
        """A pool worker lets us send it one frame (within ttl_s). -> False, to give it back, when
        it is no pool worker of ours, may get no work now (quarantined and no probe due, paused
        after a missed answer) or already holds max_in_flight items and grants."""
        with self.cond:
            now = self.clock()
            w = self.workers.get(name)
            if w is None or not w.pooled:
                self.counters["unknown_worker"] += 1
                return False
            self._prune_grants(w, now)
            if w.trust == "trusted":
                usable = w.paused_until <= now and self._held(w) + len(w.grants) < self.max_in_flight
            else:
                usable = not w.in_flight and not w.grants and w.next_probe <= now
            if not usable:
                return False
            w.grants.append((grant, now + ttl_s, now, now + wait_s))
            w.last_grant = now
            self.counters["grants"] += 1
            self.cond.notify_all()
            return True

    def take_grants(self, held_s: float = 0.0) -> list[tuple[str, str]]:
        """Grants not used yet, held longer than held_s or up to when their worker would start the
        frame (from then on it would idle for us), removed: -> [(worker, grant)] to give back."""
        with self.cond:
            now = self.clock()
            out = []
            for w in self.workers.values():
                self._prune_grants(w, now)
                keep: deque = deque()  # (the type of w.grants)
                for held in w.grants:
                    if now - held[2] >= held_s or now >= held[3]:
                        out.append((w.name, held[0]))
                    else:
                        keep.append(held)
                w.grants = keep
            return out

    def holds_grants(self) -> bool:
        with self.cond:
            return any(w.grants for w in self.workers.values())

    @staticmethod
    def _prune_grants(w: WorkerSlot, now: float) -> None:
        """Grants past their ttl are void at the worker too: never send against one."""
        while w.grants and w.grants[0][1] <= now:
            w.grants.popleft()

    def pooled(self) -> int:
        """Pool workers present (any trust): whether wanting work from the pool makes sense."""
        with self.cond:
            return sum(1 for w in self.workers.values() if w.pooled)

    def unclaim(self, name: str, seq: int) -> None:
        """The send failed: the frame never left."""
        with self.cond:
            w = self.workers.get(name)
            if w is not None and w.in_flight.pop(seq, None) is not None:
                w.tickets.pop(seq, None)
                w.assigned -= 1
                self.counters["dispatched"] -= 1
                self.cond.notify_all()

    # trust
    def _good(self, w: WorkerSlot, sent: float) -> None:
        if w.trust == "quarantined" and sent <= w.quarantined_at:
            return  # an item it had before its quarantine: only an answered probe brings it back
        w.strikes = 0
        w.paused_until = 0.0
        if w.trust != "trusted":
            log.info("worker %s %s", w.name, "proved itself: trusted" if w.trust == "probation"
                     else "answers again: back from quarantine")
            w.trust, w.why, w.probe_backoff_s = "trusted", "", 1.0

    def _strike(self, w: WorkerSlot, now: float, why: str, pause: bool = True) -> None:
        w.strikes += 1
        if w.trust == "trusted" and w.strikes < self.strikes_to_quarantine:
            if pause:  # silent: no new work for a while unless it answers
                w.paused_until = now + self.timeout_for(w)
            return
        self._quarantine(w, now, why)

    def _quarantine(self, w: WorkerSlot, now: float, why: str) -> None:
        if w.trust != "quarantined":
            self.counters["quarantined"] += 1
            log.warning("worker %s quarantined: %s; the onboard fallback or the other workers cover for it "
                        "until it answers a probe", w.name, why)
        else:
            w.probe_backoff_s = min(w.probe_backoff_s * 2, self.max_probe_backoff_s)
        w.trust, w.why = "quarantined", why
        w.quarantined_at = now
        w.next_probe = now + w.probe_backoff_s

    # receipts
    def done(self, name: str, seq: int, ok: bool = True) -> str:
        """An answer: ok (its map was accepted) or not (the worker says it dropped the item). ->
        'ok' | 'failed' | 'unknown_worker' | 'duplicate' | 'late' (after its timeout) |
        'unknown_frame'. Only ok/failed free a slot. A late answer teaches the worker's timeout
        and lifts its pause, but is no map for the robot and no way out of quarantine."""
        with self.cond:
            now = self.clock()
            w = self.workers.get(name)
            if w is None:
                self.counters["unknown_worker"] += 1
                return "unknown_worker"
            sent = w.in_flight.pop(seq, None)
            w.tickets.pop(seq, None)
            w.answering.discard(seq)
            if sent is None:
                prior = self._prior(w, seq)
                if prior is not None and prior[0] == "timeout":
                    kind = "late"
                    w.rtt.append(now - prior[1])  # its real time: the timeout adapts to it
                    if ok and w.trust == "trusted":
                        w.paused_until = 0.0  # it is alive after all: back in the rotation
                    self.cond.notify_all()
                    w.recent.append((seq, ("late", now, None)))
                else:
                    kind = "duplicate" if prior is not None else "unknown_frame"
                self.counters[kind] += 1
                return kind
            outcome = "ok" if ok else "failed"
            w.recent.append((seq, (outcome, sent, None)))
            w.rtt.append(now - sent)
            if ok:
                w.completed += 1
                self.counters["completed"] += 1
                self._good(w, sent)
            else:
                w.failed += 1
                self.counters["failed"] += 1
                self._strike(w, now, f"{w.strikes + 1} failed receipt(s) in a row", pause=False)
            self.cond.notify_all()
            return outcome

    def expire(self) -> list[tuple[str, int]]:
        """Free slots whose receipt is overdue (each worker's own adaptive timeout); a strike for
        the worker. -> [(worker, seq)]."""
        out = []
        with self.cond:
            now = self.clock()
            for w in self.workers.values():
                timeout = self.timeout_for(w)
                for seq, sent in list(w.in_flight.items()):
                    if now - sent > timeout and seq not in w.answering:
                        del w.in_flight[seq]
                        w.recent.append((seq, ("timeout", sent, w.tickets.pop(seq, None))))
                        w.timeouts += 1
                        self.counters["timeouts"] += 1
                        self._strike(w, now, f"no receipt within {timeout:.1f} s "
                                             f"({w.strikes + 1} item(s) in a row)")
                        out.append((w.name, seq))
            if out:
                self.cond.notify_all()
        return out

    @staticmethod
    def _prior(w: WorkerSlot, seq: int) -> tuple | None:
        """(outcome, time, ticket) of a recently finished item of w, or None."""
        return next((o for s, o in reversed(w.recent) if s == seq), None)

    def answer(self, name: str, seq: int, nonce: bytes) -> tuple[str, Any]:
        """A map (or a receipt) from worker `name` for item `seq`, carrying `nonce`. -> ('outstanding',
        ticket) for the first answer to an item in flight at that worker whose nonce matches (its map
        is then checked; done() or reject() settle it); ('late', ticket) for one that timed out lately;
        else (why it is dropped, None): 'unknown_worker', 'unknown_frame' (never sent to it, or the
        nonce does not match: someone else's forgery, which costs the named worker nothing) or
        'duplicate'. Nothing here moves the worker's trust."""
        import hmac

        with self.cond:
            w = self.workers.get(name)
            if w is None:
                self.counters["unknown_worker"] += 1
                return "unknown_worker", None
            t = w.tickets.get(seq) if seq in w.in_flight else None
            kind = "outstanding"
            if t is None:
                prior = self._prior(w, seq)
                t = prior[2] if prior is not None and prior[0] == "timeout" else None
                kind = "late"
                if t is None and prior is not None:
                    self.counters["duplicate"] += 1
                    return "duplicate", None
            if t is None or not hmac.compare_digest(t.nonce, nonce):
                self.counters["unknown_frame"] += 1
                return "unknown_frame", None
            if kind == "outstanding":
                if seq in w.answering:
                    self.counters["duplicate"] += 1
                    return "duplicate", None
                w.answering.add(seq)
            return kind, t

    def reject(self, name: str, seq: int, why: str) -> None:
        """A wrong answer to an item of this worker (a map that does not fit the item, a receipt
        claiming a map it never sent): the item is settled and the worker quarantined at once. An
        honest worker never sends one, so there is no second chance as for a lost item."""
        with self.cond:
            w = self.workers.get(name)
            if w is None:
                return
            now = self.clock()
            sent = w.in_flight.pop(seq, None)
            w.tickets.pop(seq, None)
            w.answering.discard(seq)
            if sent is not None:
                w.recent.append((seq, ("rejected", sent, None)))
            w.failed += 1
            w.strikes += 1
            self.counters["rejected"] += 1
            self._quarantine(w, now, why)
            self.cond.notify_all()

    def snapshot(self) -> dict[str, Any]:
        with self.cond:
            return {"counters": dict(self.counters),
                    "workers": {n: {"in_flight": len(w.in_flight), "assigned": w.assigned,
                                    "completed": w.completed, "failed": w.failed, "timeouts": w.timeouts,
                                    "trust": w.trust, "why": w.why, "timeout_s": self.timeout_for(w),
                                    "pooled": w.pooled}
                                for n, w in self.workers.items()}}


