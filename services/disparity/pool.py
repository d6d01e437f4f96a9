"""The disparity worker pool: a dispatcher on the robot and any number of workers on any host.

One mechanism, push with checked answers:

    rectify --frames_rect--> dispatcher --work/<w>--> worker w
                                 ^    |                   |
                                 |    +--disparity-->  segmenter   (signed with the robot's key)
                                 +--work_result/<w>-------+   (w's map, answering one item)

* A worker declares a liveliness token `workers/<instance>` once it listens on its own
  `work/<instance>` key (queryables and subscribers do not load-balance, so each has its own key).
  The dispatcher follows the tokens: a killed process's token vanishes in milliseconds, a frozen
  or cut-off host's after the Zenoh lease (2 s by default, see zenoh_session.py).
* The dispatcher holds only the newest rectified frame (newest-wins inbox). When a worker has a free
  slot (fewer than max_in_flight items unanswered) it takes the newest frame, drops it if it is
  older than max_age_ms, and puts it on that one worker's key with a random nonce in the
  attachment: each frame goes to exactly one worker, is never retried, and a slow worker simply
  gets fewer frames.
* The worker publishes its DisparityMap only on its own `work_result/<instance>` key, the nonce
  echoed in a small header (results.py). The dispatcher takes it only as the answer to an item
  outstanding at that worker, checks it against the frame (size, format, range, pixels) cheapest
  first, and republishes it on `disparity` with the frame's stamp, stages and camera, signed
  (common/signed_payload.py): nothing a worker sends moves the segmenter's ordering reference or
  freshness clock. Results may arrive out of order; the segmenter never publishes an older seq
  after a newer one. A worker that drops an item says so with a receipt (work_done, nonce in the
  attachment).
* An item without an answer in time is freed (counted as a timeout), so a lost work item or a
  frozen worker costs its in-flight frames and nothing stalls. "In time" adapts to each worker's
  measured send-to-answer times (3x their 90th percentile, at least result_timeout_s), so a slow
  machine or a loaded robot is not taken for a dead one. Answers from unknown workers, without the
  item's nonce, or twice for one frame are logged, counted and dropped, and cost the worker the
  key names nothing (anyone may put on its key).
* A token alone is not a worker: a new one is on probation (one probe frame at a time) until its
  first accepted map. One that takes work and returns nothing (timeouts, failed receipts) is
  quarantined: no work but a single probe after a backoff (1 s, doubling to 30 s), until it
  answers again. One that answers wrongly (a map that does not fit its item, a receipt claiming a
  map it never sent) is quarantined at once.
* While no worker is trusted (or every trusted one is paused after a missed answer) the
  dispatcher computes in-process with the onboard fallback matcher (full or half resolution), or, with fallback none, says "no worker reachable" in its status while
  the segmenter's heartbeat marks the obstacle stream stale. The fallback is also what makes
  `ballbot-vision up` a single process per stage: no extra hop when everything runs on one host.

* With `--pool NAME` the dispatcher also uses a fleet pool's workers (fleet.py), named
  `<instance>@<pool>` here: the same trust, checks and fallback, but a pool worker gets a frame
  only against one of its grants (DispatchState.add_grant), which the dispatcher asks for while it
  holds a frame (PoolDemand) and gives back when it has none.

DispatchState is the pure bookkeeping (no Zenoh, unit-tested); Dispatcher and run_worker are the
Zenoh shells.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

import msgpack
import numpy as np

from common import codec
from common.errors import BallbotError, DecodeError
from common.keys import POOL_ROOT, topic
from common.messages import DisparityMap, PoolDemand, PoolGrant, StereoFrame, WorkDone
from common.node import Node, qos
from common.signing import calibration_key
from cores.matching.disparity import RecentValid
from cores.matching.matchers import SCALE, MatcherConfig
from cores.matching.stage import MatchStage
from services.disparity.results import MIN_MEASURED, Ticket, measure, parse_header, result_header, vet_header, vet_map

log = logging.getLogger("ballbot.pool")


# --- computing one frame (shared by workers and the onboard fallback) ----------------------------

class FrameComputer:
    """StereoFrame -> DisparityMap with one matcher. result_encoding 'raw': int16, invalid
    (min_disparity-1)*16; 'png': lossless uint16 for narrow links, invalid 0 (a disparity of exactly
    0, a point at infinity, is then invalid too; needs min_disparity >= 0). A method with a confidence
    (dense) sends it along, uint8, in the same encoding. num_disparities auto is resolved per camera
    model; `saturated` / `range_warning` tell about the last frame's search range (see report)."""

    def __init__(self, config: MatcherConfig, scale: float = 1.0, result_encoding: str = "raw", label: str = ""):
        if result_encoding not in ("raw", "png"):
            raise BallbotError(f"result_encoding: raw or png, got {result_encoding!r}")
        if result_encoding == "png" and config.min_disparity < 0:
            raise BallbotError("result_encoding png needs min_disparity >= 0")
        self.config = config
        self.scale = scale
        self.stage = MatchStage(config, scale)  # the matcher and gate the in-process pipeline runs too
        self.result_encoding = result_encoding
        self.method = config.method + ("" if scale == 1.0 else f"@{scale:g}") + (label and f"/{label}")
        self.saturated = 0.0
        self.range_warning = ""

    def compute(self, msg: StereoFrame, worker: str) -> DisparityMap:
        if msg.camera is None:
            raise DecodeError("StereoFrame.camera: missing; disparity needs a rectified pair")
        if (msg.left.width, msg.left.height) != (msg.camera.width, msg.camera.height):
            raise DecodeError(f"left image is {msg.left.width}x{msg.left.height}, its camera model "
                              f"{msg.camera.width}x{msg.camera.height}")
        left = codec.array_from_image(msg.left, "left")
        right = codec.array_from_image(msg.right, "right")
        out = self.stage.compute(left, right, msg.camera.focal_px, msg.camera.baseline_m)
        result = out.match
        self.saturated, self.range_warning = result.saturated, result.range_warning
        disp = result.disparity
        if self.result_encoding == "png":
            invalid = 0.0
            disp = np.where(disp > 0, disp, 0).astype(np.uint16)
            image = codec.image_from_array(disp, "png")
        else:
            invalid = float(out.invalid_value)
            image = codec.image_from_array(disp)
        confidence = None
        if result.confidence is not None:
            confidence = codec.image_from_array(result.confidence, self.result_encoding)
        # the range its values span (consumers treat anything outside it as invalid)
        return DisparityMap(robot_id=msg.robot_id, seq=msg.seq, stamp_ns=msg.stamp_ns, stages=msg.stages,
                            image=image, scale=SCALE, invalid_value=invalid, min_disparity=out.min_disparity,
                            num_disparities=out.num_disparities, camera=msg.camera, method=self.method,
                            worker=worker, confidence=confidence)

    def report(self, node: Node) -> None:
        """The last frame's search-range saturation into node's stats, and a (rate-limited) warning
        when a large share of the matched pixels sits at the top of the range."""
        node.extra["range_saturated_pct"] = round(self.saturated * 100.0, 2)
        if self.range_warning:
            node.warn("range", self.range_warning)


def reencode_frame(msg: StereoFrame, encoding: str, jpeg_quality: int = 90) -> StereoFrame:
    """The same pair with its images in `encoding` (raw, png lossless, jpeg lossy)."""
    if msg.left.encoding == encoding and msg.right.encoding == encoding:
        return msg
    left = codec.array_from_image(msg.left, "left")
    right = codec.array_from_image(msg.right, "right")
    return msg.model_copy(update={"left": codec.image_from_array(left, encoding, jpeg_quality),
                                  "right": codec.image_from_array(right, encoding, jpeg_quality)})


# --- rates for stats ------------------------------------------------------------------------------

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


# --- dispatcher bookkeeping (pure) ----------------------------------------------------------------

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
                keep = deque()
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


# --- work item envelope ---------------------------------------------------------------------------

def make_attachment(age_ms: float, max_age_ms: float, nonce: bytes = b"", grant: str = "") -> bytes:
    """Sent beside the (unchanged) StereoFrame payload: its age when sent and the max age, so a
    worker on another host can tell its age without synchronised clocks, and the item's random
    nonce, which the worker's answer must carry back (results.py); to a pool worker, also the grant
    it was sent against (fleet.py)."""
    doc = {"age_ms": float(age_ms), "max_age_ms": float(max_age_ms), "nonce": nonce}
    if grant:
        doc["grant"] = grant
    return msgpack.packb(doc, use_bin_type=True)


def parse_attachment(raw: bytes | None) -> tuple[float, float, bytes]:
    """-> (age_ms when sent, max_age_ms, nonce); (0, inf, b"") without one. Garbage raises DecodeError."""
    if raw is None:
        return 0.0, float("inf"), b""
    try:
        doc = msgpack.unpackb(raw)
        nonce = doc.get("nonce", b"")
        if not isinstance(nonce, bytes) or len(nonce) > 64:
            raise ValueError(f"nonce: {len(nonce) if isinstance(nonce, bytes) else type(nonce).__name__}")
        return float(doc["age_ms"]), float(doc["max_age_ms"]), nonce
    except Exception as e:
        raise DecodeError(f"work item attachment: {type(e).__name__}: {e}") from None


def receipt_attachment(nonce: bytes) -> bytes:
    """A receipt's attachment: the nonce of the item it is about (no nonce, no effect)."""
    return msgpack.packb({"nonce": nonce}, use_bin_type=True)


def receipt_nonce(raw: bytes | None) -> bytes:
    try:
        doc = msgpack.unpackb(raw) if raw is not None and len(raw) <= 256 else None
        nonce = doc.get("nonce") if isinstance(doc, dict) else None
        return nonce if isinstance(nonce, bytes) else b""
    except Exception:
        return b""


def _attachment_bytes(sample) -> bytes | None:
    try:
        return sample.attachment.to_bytes() if sample.attachment is not None else None
    except Exception:
        return None


# --- the dispatcher (robot side) --------------------------------------------------------------------

class _KeyPut:
    """session.put on one key, shaped like a publisher."""

    def __init__(self, session: Any, key: str, qos_: dict[str, Any]):
        self.session, self.key, self.qos = session, key, qos_

    def put(self, payload: bytes) -> None:
        self.session.put(self.key, payload, **self.qos)


class Dispatcher:
    """frames_rect -> one worker's work key, following the workers' liveliness tokens; each
    worker's map from its result key, checked against the item (results.py), -> `disparity`,
    signed with the robot's key (the segmenter refuses anything else)."""

    def __init__(self, node: Node, state: DispatchState, max_age_ms: float, transport: str = "raw",
                 jpeg_quality: int = 90, fallback: FrameComputer | None = None, sign_key: bytes | None = None,
                 pool: str = "", pool_patience_s: float = 1.0):
        if transport not in ("raw", "png", "jpeg"):
            raise BallbotError(f"transport: raw, png or jpeg, got {transport!r}")
        # a fleet pool (fleet.py): its workers are named <instance>@<pool> here and work against grants
        self.pool, self.pool_patience_s = pool, pool_patience_s
        self._want_at = 0.0  # last demand sent
        self._want_since: float | None = None  # wanting without a grant since
        self._demand_seq = 0
        self._demand_pub: Any = None
        self._refused_grants: list[str] = []  # grants add_grant refused, to give back
        self._frame_interval_s = 1.0  # between the frames that arrive (_input_rate)
        self._rx = (time.monotonic(), 0)
        self._inbox: Any = None
        self._wanted_at = -1e9  # last want with a frame in hand
        self.pool_load: dict[str, tuple[int, float, int]] = {}  # pool worker -> (robots, our share, queued)
        self.node, self.state = node, state
        self.max_age_ms = max_age_ms
        self.transport, self.jpeg_quality = transport, jpeg_quality
        self.fallback = fallback
        self.sign_key = sign_key
        self.rates = Rates(node)
        self.rid = node.robot_id
        self._work = topic("work")
        self._subs: list[Any] = []
        self.methods: dict[str, str] = {}  # worker -> the method its last map was made with
        # Maps that passed the cheap checks, waiting for the full ones: at most one per item in
        # flight (DispatchState.answer lets only the first answer to an item through).
        self._results: queue.Queue = queue.Queue()
        self.recent = RecentValid()  # valid fractions of the maps published lately (any source)
        self.recent_by_worker: dict[str, RecentValid] = {}  # ... and of each worker's own
        self._recent_lock = threading.Lock()
        self.out: Any = None

    def _count(self, key: str, n: float = 1) -> None:
        self.node.extra[key] = self.node.extra.get(key, 0) + n

    def _name(self, key_expr: Any) -> tuple[str, str]:
        """-> (the worker's name here, its instance) from a key it answers on: a robot's own worker
        is its instance; a pool worker <instance>@<pool> (the pool's keys end with the instance)."""
        key = str(key_expr)
        instance = key.rsplit("/", 1)[-1]
        if self.pool and key.startswith(POOL_ROOT):
            return f"{instance}@{self.pool}", instance
        return instance, instance

    def _instance(self, name: str) -> tuple[str, bool]:
        """-> (instance, is a pool worker) of a worker's name here."""
        if self.pool and name.endswith("@" + self.pool):
            return name[: -len(self.pool) - 1], True
        return name, False

    # callbacks (Zenoh threads: bookkeeping and small checks only)
    def _on_token(self, sample) -> None:
        import zenoh

        name, _ = self._name(sample.key_expr)
        if sample.kind == zenoh.SampleKind.PUT:
            if self.state.add_worker(name, pooled=name != _):
                log.info("worker %s joined (%d alive); on probation until its first good map", name,
                         self.state.alive())
        else:
            lost = self.state.remove_worker(name)
            self.methods.pop(name, None)
            with self._recent_lock:
                self.recent_by_worker.pop(name, None)
            self.rates.forget(f"out_work_{name}")
            log.warning("worker %s left (%d alive, %d trusted); %d in-flight frame(s) lost", name, self.state.alive(),
                        self.state.trusted(), lost)

    def _on_done(self, sample) -> None:
        """A receipt: a worker says it dropped an item (too old, undecodable, failed). Taken only
        with the item's nonce; one claiming success is a lie (the map is the answer)."""
        payload = sample.payload.to_bytes()
        self.rates.add("in_work_done", len(payload))
        name, instance = self._name(sample.key_expr)
        msg = self.node.decode_or_drop(payload, WorkDone, "receipt", "receipt")
        if msg is None:
            return
        if msg.worker != instance:
            self._count("receipts_misnamed")
            self.node.warn("receipt-misnamed", f"dropped a receipt on {name}'s key naming worker {msg.worker}")
            return
        kind, ticket = self.state.answer(name, msg.seq, receipt_nonce(_attachment_bytes(sample)))
        if kind not in ("outstanding", "late"):
            self.node.warn(f"receipt-{kind}", f"dropped receipt from {name} for seq {msg.seq}: {kind}")
            return
        if msg.ok:
            self._refuse(name, msg.seq, "a receipt claiming a map that never came on its result key "
                                        "(a worker of an older version publishes maps elsewhere)")
            return
        if self.state.done(name, msg.seq, False) == "failed":
            self.node.warn("receipt-failed", f"worker {name} dropped seq {msg.seq}: {msg.reason}")

    def _on_result(self, sample) -> None:
        """A worker's map: everything that can be checked without copying or decoding the payload
        is checked here; what passes waits for the results thread."""
        name, _ = self._name(sample.key_expr)
        n = len(sample.payload)
        self.rates.add("in_work_result", n)
        try:
            header = parse_header(_attachment_bytes(sample))
        except DecodeError as e:
            # anyone can put on a worker's key: costs the named worker nothing
            self._count("results_unmatched")
            self.node.warn("result-header", f"dropped a map on {name}'s result key: {e}")
            return
        kind, ticket = self.state.answer(name, header.seq, header.nonce)
        if ticket is None:
            self._count("results_unmatched")
            self.node.warn(f"result-{kind}", f"dropped a map on {name}'s result key for seq {header.seq}: {kind} "
                                             f"(no item in flight there with its nonce)")
            return
        why = vet_header(header, ticket, n)
        if why:
            self._refuse(name, header.seq, why)
            return
        if kind == "late":
            self.state.done(name, header.seq, True)
            self.node.warn("result-late", f"worker {name}: map for seq {header.seq} came after its timeout; "
                                          f"not published")
            return
        self._results.put((name, header, ticket, sample.payload.to_bytes()))

    def _refuse(self, name: str, seq: int, why: str) -> None:
        self.state.reject(name, seq, why)
        self._count("results_rejected")
        self.node.warn("result-rejected", f"refused worker {name}'s answer for seq {seq}: {why}; worker quarantined")

    # the results thread: full checks, then republish
    def _results_loop(self) -> None:
        while self.node.running:
            try:
                name, header, ticket, payload = self._results.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                checked = self._check(name, header, ticket, payload)
            except Exception:  # never leave an item half-settled, never die on a worker's map
                self.node.errors += 1
                checked = None
                self._refuse(name, header.seq, "its map could not be checked (see the dispatcher's log)")
                if self.node._should_log("result-exception"):
                    log.exception("dispatcher: checking worker %s's map for seq %s failed", name, header.seq)
            if checked is not None:
                with self.node.processing(checked[0]):
                    self._settle(name, ticket, *checked)

    def _check(self, name: str, header: Any, ticket: Any, payload: bytes) -> tuple[DisparityMap, float] | None:
        """-> (the map, its valid fraction) when it may reach the robot; else None, the worker refused."""
        try:
            m = codec.decode(payload, DisparityMap)
        except DecodeError as e:
            self._refuse(name, ticket.seq, str(e))
            return None
        why, check = vet_map(m, header, ticket)
        if not why:
            why = self._collapsed(name, check.valid_fraction)
        if why:
            self._refuse(name, ticket.seq, why)
            return None
        return m, check.valid_fraction

    def _collapsed(self, name: str, vf: float) -> str:
        """Why a worker's map that measured far less than expected is refused ("" if it is not):
        nothing measured while the robot's maps of the last 2 s (any source) measured plenty, or
        under half of what that worker's own maps of the last 2 s measured. A scene that really
        goes blank shows in the fallback's maps too, and the worker's next probe is judged on them;
        a worker whose method simply measures less than another's is judged on its own."""
        now = time.monotonic()
        with self._recent_lock:
            robot = self.recent.median(now)
            own = self.recent_by_worker.get(name)
            own_median = own.median(now) if own is not None else None
        last = f"of the last {self.recent.window_s:g} s"
        if robot is not None and vf < MIN_MEASURED and robot >= 10 * MIN_MEASURED:
            return f"it measured {vf:.1%} of the image, the robot's maps {last} {robot:.1%}"
        if own_median is not None and vf < self.recent.factor * own_median:
            return f"it measured {vf:.1%} of the image, its own maps {last} {own_median:.1%}"
        return ""

    def _settle(self, name: str, ticket: Any, m: DisparityMap, valid_fraction: float) -> None:
        if self.state.done(name, ticket.seq, True) != "ok":
            self._count("results_late")  # timed out while being checked
            return
        # The frame's own stamp, stages and camera: nothing the worker says moves the robot's clock.
        out = m.model_copy(update={"robot_id": ticket.robot_id, "seq": ticket.seq, "stamp_ns": ticket.stamp_ns,
                                   "stages": dict(ticket.stages), "camera": ticket.camera, "worker": name,
                                   "method": m.method[:64]})
        self._publish(out, valid_fraction, time.monotonic())
        with self._recent_lock:
            self.recent_by_worker.setdefault(name, RecentValid()).add(valid_fraction, time.monotonic())
        key = f"maps_{out.method}"
        if key not in self.node.extra and sum(k.startswith("maps_") for k in list(self.node.extra)) >= 16:
            key = "maps_other"  # a worker naming every map differently must not grow the stats without bound
        self.node.extra[key] = self.node.extra.get(key, 0) + 1
        self.methods[name] = out.method

    def _publish(self, m: DisparityMap, valid_fraction: float, now: float) -> None:
        self.out.put(m)
        with self._recent_lock:
            self.recent.add(valid_fraction, now)

    def _on_grant(self, sample) -> None:
        """A pool worker lets us send it one frame; kept for the main loop (or given back at once
        when it is none of ours or holds enough)."""
        name, instance = self._name(sample.key_expr)
        if len(sample.payload) > topic("pool_grant").max_bytes:
            self._count("grants_oversized")
            return
        msg = self.node.decode_or_drop(sample.payload.to_bytes(), PoolGrant, "grant", "grant")
        if msg is None:
            return
        if msg.worker != instance:
            self._count("grants_misnamed")
            self.node.warn("grant-misnamed", f"dropped a grant on {instance}'s key naming worker {msg.worker}")
            return
        self.pool_load[name] = (msg.robots, msg.share, msg.queued)
        # a little under the worker's ttl: a frame sent at the last moment must still find its grant
        if not self.state.add_grant(name, msg.grant, 0.8 * msg.ttl_ms / 1e3, msg.wait_ms / 1e3):
            with self._recent_lock:  # given back by the main loop: no put from a Zenoh callback
                self._refused_grants.append(msg.grant)

    def _demand(self, want: bool, decline: list[str] = ()) -> None:
        """Tell every worker of the pool that we hold a frame and no grant (want), and give back
        grants we cannot use (decline)."""
        if self._demand_pub is None:
            return
        self._demand_seq += 1
        for i in range(0, max(1, len(decline)), 32):
            msg = PoolDemand(robot_id=self.rid, seq=self._demand_seq, stamp_ns=time.time_ns(), want=want,
                             decline=list(decline[i:i + 32]))
            self._demand_pub.put(codec.encode(msg))
        if want:
            self._want_at = time.monotonic()
            self._count("pool_wants")
        if decline:
            self._count("pool_declined", len(decline))

    def _want(self, now: float, ahead: bool = False) -> None:
        """While we hold a frame and no grant: ask, again every 0.1 s (a worker forgets a want after
        0.5 s, and a worker that joins learns of it so). ahead: no frame yet, one is due (see
        _backlogged); a grant that comes first is held for it (_hold_s)."""
        if not ahead:
            self._wanted_at = now
        if self._want_since is None and not ahead:
            self._want_since = now
            self._demand(want=True)
        elif now - self._want_at >= 0.1:
            self._demand(want=True)

    def _backlogged(self, now: float) -> bool:
        """Frames come faster than grants: we wanted with a frame in hand lately, and the next
        frame is due within the time a grant is held."""
        return now - self._wanted_at < 0.3 and self._frame_interval_s <= 0.5

    def _decline_unused(self, held_s: float = 0.0) -> None:
        grants = [g for _, g in self.state.take_grants(held_s)]
        with self._recent_lock:
            grants += self._refused_grants
            self._refused_grants = []
        if grants:
            self._demand(want=False, decline=grants)

    def _hold_s(self) -> float:
        """How long a grant that came while we hold no frame is kept for the next one: about one
        frame interval, and never past the moment its worker would start it (the worker computes
        another robot's item meanwhile, so the hold costs it nothing and saves a round of decline
        and re-grant; see DispatchState.take_grants)."""
        return min(0.5, 1.2 * self._frame_interval_s)

    def _take(self, inbox: Any, timeout: float) -> tuple[StereoFrame, bytes] | None:
        return self.node.take(inbox, timeout)

    def _input_rate(self, now: float) -> None:
        """The interval between frames arriving (the inbox counts them all, taken or not)."""
        if self._inbox is None:
            return
        n, dt = self._inbox.received, now - self._rx[0]
        if dt >= 0.5:
            arrived = n - self._rx[1]
            interval = min(1.0, dt / arrived) if arrived else 1.0
            self._frame_interval_s = 0.5 * self._frame_interval_s + 0.5 * interval
            self._rx = (now, n)

    def start(self) -> None:
        s = self.node.session
        self._subs.append(self.node.subscribe(topic("work_done").pattern(self.rid), self._on_done))
        self._subs.append(self.node.subscribe(topic("work_result").pattern(self.rid), self._on_result))
        self._subs.append(s.liveliness().declare_subscriber(topic("worker").pattern(self.rid), self._on_token,
                                                           history=True))
        if self.pool:
            p = self.pool
            self._subs.append(self.node.subscribe(topic("pool_done").pattern(self.rid, pool=p), self._on_done))
            self._subs.append(self.node.subscribe(topic("pool_result").pattern(self.rid, pool=p), self._on_result))
            self._subs.append(self.node.subscribe(topic("pool_grant").pattern(self.rid, pool=p), self._on_grant))
            self._subs.append(s.liveliness().declare_subscriber(topic("pool_worker").pattern(pool=p), self._on_token,
                                                               history=True))
            key = topic("pool_demand").key(self.rid, pool=p)
            # a put per demand, not a declared publisher: no publisher state that could go stale while
            # workers come and go (in one bench run a robot's demands stopped reaching the workers
            # after a worker was replaced; the cause is not established)
            self._demand_pub = _KeyPut(s, key, qos(topic("pool_demand")))
            self.node.uses("publishes", key)
            self.node.uses("publishes", topic("pool_work").pattern(self.rid, pool=p))
        threading.Thread(target=self._results_loop, name="results", daemon=True).start()

    def _send(self, name: str, msg: StereoFrame, payload: bytes, nonce: bytes) -> None:
        import zenoh

        if self.transport != "raw" or msg.left.encoding != "raw":
            payload = codec.encode(reencode_frame(msg, self.transport, self.jpeg_quality))
        age_ms = self.node.age_s(msg) * 1e3
        instance, pooled = self._instance(name)
        key = (topic("pool_work").key(self.rid, pool=self.pool, instance=instance) if pooled
               else self._work.key(self.rid, instance=name))
        grant = self.state.grant_of(name, msg.seq) if pooled else ""
        self.node.session.put(key, payload, congestion_control=zenoh.CongestionControl.DROP,
                              priority=zenoh.Priority.DATA,
                              attachment=make_attachment(age_ms, self.max_age_ms, nonce, grant))
        self.rates.add(f"out_work_{name}", len(payload))

    def _housekeeping(self, out) -> None:
        self._input_rate(time.monotonic())
        if self._refused_grants:
            with self._recent_lock:
                refused, self._refused_grants = self._refused_grants, []
            self._demand(want=False, decline=refused)
        for name, seq in self.state.expire():
            self.node.warn("timeout", f"worker {name}: no map for seq {seq} in time; slot freed")
        alive, trusted = self.state.alive(), self.state.trusted()
        snap = self.state.snapshot()
        self.node.extra.update({f"pool_{k}": float(v) for k, v in snap["counters"].items()})
        self.node.extra["workers_alive"] = float(alive)
        self.node.extra["workers_trusted"] = float(trusted)
        self.node.extra["in_flight"] = float(sum(w["in_flight"] for w in snap["workers"].values()))
        doubtful = {n: w for n, w in snap["workers"].items() if w["trust"] != "trusted"}
        quarantined = [f"{n} ({w['why']})" for n, w in doubtful.items() if w["trust"] == "quarantined"]
        probation = [n for n, w in doubtful.items() if w["trust"] == "probation"]
        self.node.extra["workers_quarantined"] = float(len(quarantined))
        if self.pool:
            pooled = {n: w for n, w in snap["workers"].items() if w["pooled"]}
            self.node.extra["pool_workers"] = float(len(pooled))
            self.node.extra["pool_workers_trusted"] = float(sum(w["trust"] == "trusted" for w in pooled.values()))
            for n in [k for k in self.pool_load if k not in pooled]:
                self.pool_load.pop(n, None)
            # our share of each pool worker, as it said in its last grant
            self.node.extra["pool_share"] = float(sum(share for _, share, _ in list(self.pool_load.values())))
        notes = ([f"quarantined: {', '.join(quarantined)}"] if quarantined else []) + \
                ([f"on probation: {', '.join(probation)}"] if probation else [])
        note = f"; {'; '.join(notes)}" if notes else ""
        if trusted:
            methods = sorted({m for w, m in list(self.methods.items())
                              if w in snap["workers"] and snap["workers"][w]["trust"] == "trusted"})
            in_pool = int(self.node.extra.get("pool_workers_trusted", 0))
            self.node.status = (f"ok: {trusted} worker{'s' if trusted > 1 else ''}"
                                + (f" ({', '.join(methods)})" if methods else "")
                                + (f", {in_pool} of them in pool {self.pool}" if in_pool else "") + note)
        elif self.fallback is not None:
            # One host with no offboard worker is the normal single-machine setup, not a fault.
            what = f"computing onboard ({self.fallback.method}){note}"
            self.node.status = f"ok: {what}" if not alive else f"fallback: {what}"
        else:
            self.node.status = f"no worker reachable{note}"
        self.rates.tick()

    def _too_old(self, msg: StereoFrame) -> bool:
        if self.node.age_s(msg) * 1e3 > self.max_age_ms:
            self.node.extra["too_old"] = self.node.extra.get("too_old", 0) + 1
            return True
        return False

    def _compute_onboard(self, msg: StereoFrame) -> None:
        node = self.node
        with node.processing(msg):
            m = self.fallback.compute(msg, node.instance)
            raw = codec.array_from_image(m.image, "disparity")
            vf = measure(raw, m.invalid_value, m.scale, m.min_disparity, m.num_disparities).valid_fraction
            self._publish(m, vf, time.monotonic())
            self.fallback.report(node)
            node.extra["fallback_frames"] = node.extra.get("fallback_frames", 0) + 1

    def _claim(self, msg: StereoFrame) -> tuple[str | None, bytes]:
        """-> (worker the frame goes to, or None; the item's nonce)."""
        try:
            ticket = Ticket.for_frame(msg)
        except DecodeError as e:
            self.node.decode_errors += 1
            self.node.warn("decode", f"dropped frame seq {msg.seq}: {e}")
            return None, b""
        return self.state.claim(msg.seq, ticket), ticket.nonce

    def run(self) -> None:
        node = self.node
        inbox = self._inbox = node.latest("frames_rect")
        self.out = node.publisher("disparity", sign_key=self.sign_key)
        if self.sign_key is None:
            log.warning("dispatcher: no BALLBOT_CALIBRATION_KEY: the disparity maps are published unsigned, so the "
                        "segmenter cannot tell them from anyone else's (`up` and the compose files set one)")
        self.start()
        pending: tuple[StereoFrame, bytes] | None = None
        next_house = 0.0
        while node.running:
            now = time.monotonic()
            if now >= next_house:
                self._housekeeping(self.out)
                next_house = now + 0.1
            if self.state.available() == 0:
                # No proven worker (or every one paused after a missed answer): the onboard fallback
                # computes, except for a frame that goes to a worker due for a probe (a new one, or
                # one back from quarantine).
                pending = None
                if self.fallback is None and not self.state.probe_due() and not self.state.pooled():
                    inbox.take(0.1)  # drain: overwritten frames count as drops; nothing to do
                    continue
                got = self._take(inbox, 0.1)
                if got is None or self._too_old(got[0]):
                    continue
                msg, payload = got
                name, nonce = self._claim(msg)
                if name is None and self.state.pooled():
                    self._want(time.monotonic())  # a pool worker on probation probes only with a grant
                    if self.fallback is None and self.state.wait_free(0.1):
                        name, nonce = self._claim(msg)
                if name is not None:
                    self._want_since = None
                    self._dispatch(name, msg, payload, nonce)
                elif self.fallback is not None:
                    self._compute_onboard(msg)
                continue
            if self.pool and not self.state.has_free():
                # Pool workers give work only against grants: hold a frame and ask for one (the
                # newest is taken, and decoded, only when a grant comes). While frames come faster
                # than grants, ask a little ahead, so a turn is not skipped for want of a frame
                # at that instant.
                if pending is None:
                    pending = self._take(inbox, 0.05)
                if pending is not None and self._too_old(pending[0]):
                    pending = None
                    continue
                now = time.monotonic()
                if pending is None:
                    if self._backlogged(now):
                        self._want(now, ahead=True)
                    else:
                        self._want_since = None
                    continue
                self._want(now)
                if self.fallback is not None and now - self._want_since > self.pool_patience_s:
                    # the pool is there but grants us nothing (a full fleet): the robot is not left blind
                    self._count("pool_starved")
                    self._compute_onboard(pending[0])
                    pending, self._want_since = None, None
                    continue
                self.state.wait_free(0.05)  # a grant wakes it
                continue
            if not self.state.wait_free(0.1):
                continue
            got = self._take(inbox, 0.0 if pending or self.pool else 0.1)
            if got is not None:
                if pending is not None:
                    node.extra["replaced_pending"] = node.extra.get("replaced_pending", 0) + 1
                pending = got
            if pending is None:
                if self.pool:
                    # nothing to send: a grant held about a frame interval is given back (the pool
                    # worker then grants another robot)
                    self._decline_unused(self._hold_s())
                    self._want_since = None
                    if not self.state.has_free():
                        continue
                    got = self._take(inbox, 0.01 if self.state.holds_grants() else 0.1)
                    if got is None:
                        continue
                    pending = got
                else:
                    continue
            msg, payload = pending
            if self._too_old(msg):
                pending = None
                continue
            name, nonce = self._claim(msg)
            if name is None:
                if not nonce:
                    pending = None  # not a frame a worker can answer
                continue  # the free worker vanished meanwhile; keep the frame for the next one
            pending = None
            self._want_since = None
            self._dispatch(name, msg, payload, nonce)

    def _dispatch(self, name: str, msg: StereoFrame, payload: bytes, nonce: bytes) -> None:
        with self.node.processing(msg):
            try:
                self._send(name, msg, payload, nonce)
            except BaseException:
                self.state.unclaim(name, msg.seq)
                raise


def run_dispatcher(node: Node, settings: Any) -> None:
    fallback = None
    if settings.fallback != "none":
        scale = 0.5 if settings.fallback == "half" else 1.0
        fallback = FrameComputer(settings, scale, "raw", label="onboard")
    state = DispatchState(settings.max_in_flight, settings.result_timeout_s)
    Dispatcher(node, state, settings.max_age_ms, settings.transport, settings.jpeg_quality, fallback,
               calibration_key(), settings.pool, settings.pool_patience_s).run()


# --- the worker (any host) ------------------------------------------------------------------------

class WorkQueue:
    """Work items in arrival order, at most `capacity` of them and `max_bytes` in all (the oldest
    are dropped beyond that: the dispatcher bounds what is in flight, so this only guards against a
    misbehaving sender, whose items could otherwise hold 8 x 80 MB)."""

    def __init__(self, capacity: int = 8, max_bytes: int = 128 << 20):
        self._items: deque[tuple[bytes, bytes | None, float]] = deque()
        self.capacity, self.max_bytes = capacity, max_bytes
        self._held = 0
        self._cond = threading.Condition()
        self.received = self.overflowed = self.bytes = 0

    def offer(self, payload: bytes, attachment: bytes | None) -> None:
        with self._cond:
            self._items.append((payload, attachment, time.monotonic()))
            self._held += len(payload)
            while len(self._items) > 1 and (len(self._items) > self.capacity or self._held > self.max_bytes):
                self._held -= len(self._items.popleft()[0])
                self.overflowed += 1
            self.received += 1
            self.bytes += len(payload)
            self._cond.notify()

    def take(self, timeout: float) -> tuple[bytes, bytes | None, float] | None:
        with self._cond:
            if not self._items:
                self._cond.wait(timeout)
            if not self._items:
                return None
            item = self._items.popleft()
            self._held -= len(item[0])
            return item


def run_worker(node: Node, settings: Any) -> None:
    computer = FrameComputer(settings, 1.0, settings.result_encoding)
    rid, me = node.robot_id, node.instance
    queue_ = WorkQueue()
    rates = Rates(node)

    def on_work(sample) -> None:
        att = sample.attachment
        node.count_input()
        if len(sample.payload) > topic("work").max_bytes:
            node.extra["in_work_oversized"] = node.extra.get("in_work_oversized", 0) + 1
            return
        payload = sample.payload.to_bytes()
        rates.add("in_work", len(payload))
        queue_.offer(payload, att.to_bytes() if att is not None else None)

    node.subscribe(topic("work").key(rid, instance=me), on_work)
    # Maps go only to this worker's own result key: the dispatcher checks each against the item it
    # sent and republishes it on `disparity`; receipts only for items dropped.
    results = node.session.declare_publisher(topic("work_result").key(rid, instance=me), **qos(topic("work_result")))
    receipts = node.session.declare_publisher(topic("work_done").key(rid, instance=me), **qos(topic("work_done")))
    # Announce only once the work key is subscribed: the dispatcher sends as soon as it sees this.
    token = node.session.liveliness().declare_token(topic("worker").key(rid, instance=me))
    node.status = f"ok: {computer.method}, waiting for work"
    log.info("disparity worker %s ready on %s", me, topic("work").key(rid, instance=me))

    def dropped(msg: Any, nonce: bytes, reason: str, proc_ms: float = 0.0) -> None:
        receipts.put(codec.encode(WorkDone(robot_id=rid, seq=msg.seq, stamp_ns=msg.stamp_ns, worker=me, ok=False,
                                           reason=reason, proc_ms=proc_ms)),
                     attachment=receipt_attachment(nonce))

    try:
        while node.running:
            rates.tick()
            node.extra["queue_overflowed"] = float(queue_.overflowed)
            item = queue_.take(0.2)
            if item is None:
                continue
            payload, attachment, received = item
            try:
                msg = node.decode(payload, StereoFrame)
                age_ms, max_age_ms, nonce = parse_attachment(attachment)
            except DecodeError as e:
                node.decode_errors += 1
                node.warn("decode", f"dropped work item: {e}")
                continue
            age_now = age_ms + (time.monotonic() - received) * 1e3
            if age_now > max_age_ms:
                node.extra["too_old"] = node.extra.get("too_old", 0) + 1
                dropped(msg, nonce, f"too old: {age_now:.0f} ms > {max_age_ms:.0f} ms")
                continue
            ok = False
            with node.processing(msg):
                result = computer.compute(msg, me)
                result.stages[node.service] = node.clock.wall_ns()
                data = codec.encode(result)
                results.put(data, attachment=result_header(result, nonce))
                node._published(node.age_ns(msg))
                rates.add("out_work_result", len(data))
                computer.report(node)
                ok = True
                node.status = f"ok: {computer.method}"
            if not ok:
                dropped(msg, nonce, "failed (see worker log)", (time.monotonic() - received) * 1e3)
    finally:
        try:
            token.undeclare()
        except Exception:
            pass
