"""The disparity worker pool: a dispatcher on the robot and any number of workers on any host.

One mechanism, push with receipts:

    rectify --frames_rect--> dispatcher --work/<w>--> worker w --disparity--> segmenter
                                 ^                        |
                                 +------work_done/<w>-----+   (small receipt: frees w's slot)

* A worker declares a liveliness token `workers/<instance>` once it listens on its own
  `work/<instance>` key (queryables and subscribers do not load-balance, so each has its own key).
  The dispatcher follows the tokens: a killed process's token vanishes in milliseconds, a frozen
  or cut-off host's after the Zenoh lease (2 s by default, see zenoh_session.py).
* The dispatcher holds only the newest rectified frame (newest-wins inbox). When a worker has a free
  slot (fewer than max_in_flight items without a receipt) it takes the newest frame, drops it if it
  is older than max_age_ms, and puts it on that one worker's key: each frame goes to exactly one
  worker, is never retried, and a slow worker simply gets fewer frames.
* The worker publishes the DisparityMap straight on `disparity` (no relay hop) and then its receipt.
  Results may arrive out of order; the segmenter never publishes an older seq after a newer one.
* A slot without a receipt in time is freed (counted as a timeout), so a lost work item or a frozen
  worker costs its in-flight frames and nothing stalls. "In time" adapts to each worker's measured
  send-to-receipt times (3x their 90th percentile, at least result_timeout_s), so a slow machine
  or a loaded robot is not taken for a dead one. Receipts from unknown workers, for frames not in
  flight, or twice for one frame are logged, counted and dropped.
* A token alone is not a worker: a new one is on probation (one probe frame at a time) until its
  first good receipt. One that takes work and returns nothing good (timeouts, failed receipts) is
  quarantined: no work but a single probe after a backoff (1 s, doubling to 30 s), until it
  answers again.
* While no worker is trusted the dispatcher computes in-process with the onboard fallback matcher
  (full or half resolution), or, with fallback none, says "no worker reachable" in its status while
  the segmenter's heartbeat marks the obstacle stream stale. The fallback is also what makes
  `ballbot-vision up` a single process per stage: no extra hop when everything runs on one host.

DispatchState is the pure bookkeeping (no Zenoh, unit-tested); Dispatcher and run_worker are the
Zenoh shells.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

import msgpack
import numpy as np

from common import codec
from common.errors import BallbotError, DecodeError
from common.keys import topic
from common.messages import DisparityMap, StereoFrame, WorkDone
from common.node import Node
from cores.matching.matchers import SCALE, MatcherConfig, gate_for_range, make_matcher

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
        self._matchers: dict[tuple, Any] = {}
        if config.num_disparities != "auto":  # bad settings fail now, not on the first frame
            self._matchers[()] = make_matcher(config, scale)
        self.result_encoding = result_encoding
        self.method = config.method + ("" if scale == 1.0 else f"@{scale:g}") + (label and f"/{label}")
        self.saturated = 0.0
        self.range_warning = ""

    def _matcher(self, cam) -> Any:
        if () in self._matchers:
            return self._matchers[()]
        key = (cam.focal_px, cam.baseline_m, cam.width)
        if key not in self._matchers:
            if len(self._matchers) >= 4:  # calibrations come and go; keep a few, never grow without bound
                self._matchers.clear()
            self._matchers[key] = make_matcher(self.config.resolved(*key), self.scale)
        return self._matchers[key]

    def compute(self, msg: StereoFrame, worker: str) -> DisparityMap:
        if msg.camera is None:
            raise DecodeError("StereoFrame.camera: missing; disparity needs a rectified pair")
        if (msg.left.width, msg.left.height) != (msg.camera.width, msg.camera.height):
            raise DecodeError(f"left image is {msg.left.width}x{msg.left.height}, its camera model "
                              f"{msg.camera.width}x{msg.camera.height}")
        left = codec.array_from_image(msg.left, "left")
        right = codec.array_from_image(msg.right, "right")
        matcher = self._matcher(msg.camera)
        gate = gate_for_range(self.config.max_range_m, msg.camera.focal_px, msg.camera.baseline_m)
        result = matcher.match(left, right, gate)
        self.saturated, self.range_warning = result.saturated, result.range_warning
        c = matcher.config
        disp = result.disparity
        if self.result_encoding == "png":
            invalid = 0.0
            disp = np.where(disp > 0, disp, 0).astype(np.uint16)
            image = codec.image_from_array(disp, "png")
        else:
            invalid = float(c.invalid_value)
            image = codec.image_from_array(disp)
        confidence = None
        if result.confidence is not None:
            confidence = codec.image_from_array(result.confidence, self.result_encoding)
        return DisparityMap(robot_id=msg.robot_id, seq=msg.seq, stamp_ns=msg.stamp_ns, stages=msg.stages,
                            image=image, scale=SCALE, invalid_value=invalid, min_disparity=c.min_disparity,
                            num_disparities=c.num_disparities, camera=msg.camera, method=self.method,
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
    assigned: int = 0
    completed: int = 0
    failed: int = 0
    timeouts: int = 0
    last_assigned: float = 0.0
    paused_until: float = 0.0  # after a timeout: no new work for a while unless it answers
    recent: deque = field(default_factory=lambda: deque(maxlen=512))  # (seq, outcome) finished lately
    # trust: a liveliness token alone is not a worker
    trust: str = "probation"  # probation (not proven yet) | trusted | quarantined
    strikes: int = 0  # consecutive work items without a good receipt
    next_probe: float = 0.0  # probation/quarantine: when it may get its next (single) probe frame
    probe_backoff_s: float = 1.0
    why: str = ""  # why it is quarantined
    rtt: deque = field(default_factory=lambda: deque(maxlen=32))  # s from send to receipt, recent items


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
            "unknown_frame", "duplicate", "late", "workers_joined", "workers_left", "quarantined", "probes")}

    # membership
    def add_worker(self, name: str) -> bool:
        with self.cond:
            if name in self.workers:
                return False
            self.workers[name] = WorkerSlot(name, next_probe=self.clock())
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

    def timeout_for(self, w: WorkerSlot) -> float:
        if not w.rtt:
            return self.result_timeout_s
        p90 = float(np.percentile(np.fromiter(w.rtt, float), 90))
        return min(self.max_result_timeout_s, max(self.result_timeout_s, self.timeout_factor * p90))

    # assignment
    def _due_probe(self, now: float) -> list[WorkerSlot]:
        return [w for w in self.workers.values() if w.trust != "trusted" and not w.in_flight and w.next_probe <= now]

    def _free(self, now: float) -> list[WorkerSlot]:
        probes = self._due_probe(now)
        if probes:  # a probe first: a new worker is tried on the next frame, whoever else is free
            return probes
        return [w for w in self.workers.values()
                if w.trust == "trusted" and len(w.in_flight) < self.max_in_flight and w.paused_until <= now]

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

    def claim(self, seq: int) -> str | None:
        """Assign frame `seq` to a worker due for a probe, else to the free trusted worker with the
        fewest items in flight (then the one idle longest). -> its name, or None if none is free."""
        with self.cond:
            now = self.clock()
            free = self._free(now)
            if not free:
                return None
            w = min(free, key=lambda s: (len(s.in_flight), s.last_assigned))
            if w.trust != "trusted":
                self.counters["probes"] += 1
            w.in_flight[seq] = now
            w.assigned += 1
            w.last_assigned = now
            self.counters["dispatched"] += 1
            return w.name

    def unclaim(self, name: str, seq: int) -> None:
        """The send failed: the frame never left."""
        with self.cond:
            w = self.workers.get(name)
            if w is not None and w.in_flight.pop(seq, None) is not None:
                w.assigned -= 1
                self.counters["dispatched"] -= 1
                self.cond.notify_all()

    # trust
    def _good(self, w: WorkerSlot) -> None:
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
        if w.trust != "quarantined":
            self.counters["quarantined"] += 1
            log.warning("worker %s quarantined: %s; the onboard fallback covers for it until it answers a probe",
                        w.name, why)
        else:
            w.probe_backoff_s = min(w.probe_backoff_s * 2, self.max_probe_backoff_s)
        w.trust, w.why = "quarantined", why
        w.next_probe = now + w.probe_backoff_s

    # receipts
    def done(self, name: str, seq: int, ok: bool = True) -> str:
        """A receipt. -> 'ok' | 'failed' (the worker dropped it) | 'unknown_worker' |
        'duplicate' | 'late' (after its timeout) | 'unknown_frame'. Only ok/failed free a slot."""
        with self.cond:
            now = self.clock()
            w = self.workers.get(name)
            if w is None:
                self.counters["unknown_worker"] += 1
                return "unknown_worker"
            sent = w.in_flight.pop(seq, None)
            if sent is None:
                prior = next(((s, o) for s, o in reversed(w.recent) if s == seq), None)
                if prior is not None and prior[1][0] == "timeout":
                    kind = "late"
                    w.rtt.append(now - prior[1][1])  # its real time: the timeout adapts to it
                    if ok:
                        self._good(w)  # it answers again: back in the rotation
                    self.cond.notify_all()
                    w.recent.append((seq, ("late", now)))
                else:
                    kind = "duplicate" if prior is not None else "unknown_frame"
                self.counters[kind] += 1
                return kind
            outcome = "ok" if ok else "failed"
            w.recent.append((seq, (outcome, sent)))
            w.rtt.append(now - sent)
            if ok:
                w.completed += 1
                self.counters["completed"] += 1
                self._good(w)
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
                    if now - sent > timeout:
                        del w.in_flight[seq]
                        w.recent.append((seq, ("timeout", sent)))
                        w.timeouts += 1
                        self.counters["timeouts"] += 1
                        self._strike(w, now, f"no receipt within {timeout:.1f} s "
                                             f"({w.strikes + 1} item(s) in a row)")
                        out.append((w.name, seq))
            if out:
                self.cond.notify_all()
        return out

    def snapshot(self) -> dict[str, Any]:
        with self.cond:
            return {"counters": dict(self.counters),
                    "workers": {n: {"in_flight": len(w.in_flight), "assigned": w.assigned,
                                    "completed": w.completed, "failed": w.failed, "timeouts": w.timeouts,
                                    "trust": w.trust, "why": w.why, "timeout_s": self.timeout_for(w)}
                                for n, w in self.workers.items()}}


# --- work item envelope ---------------------------------------------------------------------------

def make_attachment(age_ms: float, max_age_ms: float) -> bytes:
    """Sent beside the (unchanged) StereoFrame payload: its age when sent and the max age, so a
    worker on another host can tell its age without synchronised clocks."""
    return msgpack.packb({"age_ms": float(age_ms), "max_age_ms": float(max_age_ms)})


def parse_attachment(raw: bytes | None) -> tuple[float, float]:
    """-> (age_ms when sent, max_age_ms); (0, inf) without one. Garbage raises DecodeError."""
    if raw is None:
        return 0.0, float("inf")
    try:
        doc = msgpack.unpackb(raw)
        return float(doc["age_ms"]), float(doc["max_age_ms"])
    except Exception as e:
        raise DecodeError(f"work item attachment: {type(e).__name__}: {e}") from None


# --- the dispatcher (robot side) --------------------------------------------------------------------

class Dispatcher:
    """frames_rect -> one worker's work key, following the workers' liveliness tokens."""

    def __init__(self, node: Node, state: DispatchState, max_age_ms: float, transport: str = "raw",
                 jpeg_quality: int = 90, fallback: FrameComputer | None = None):
        if transport not in ("raw", "png", "jpeg"):
            raise BallbotError(f"transport: raw, png or jpeg, got {transport!r}")
        self.node, self.state = node, state
        self.max_age_ms = max_age_ms
        self.transport, self.jpeg_quality = transport, jpeg_quality
        self.fallback = fallback
        self.rates = Rates(node)
        self.rid = node.robot_id
        self._work = topic("work")
        self._subs: list[Any] = []
        self.methods: dict[str, str] = {}  # worker -> the method its last map was made with

    # callbacks (Zenoh threads: bookkeeping only)
    def _on_token(self, sample) -> None:
        import zenoh

        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if sample.kind == zenoh.SampleKind.PUT:
            if self.state.add_worker(name):
                log.info("worker %s joined (%d alive); on probation until its first good receipt", name,
                         self.state.alive())
        else:
            lost = self.state.remove_worker(name)
            self.methods.pop(name, None)
            self.rates.forget(f"out_work_{name}")
            log.warning("worker %s left (%d alive, %d trusted); %d in-flight frame(s) lost", name, self.state.alive(),
                        self.state.trusted(), lost)

    def _on_done(self, sample) -> None:
        payload = sample.payload.to_bytes()
        self.rates.add("in_work_done", len(payload))
        msg = self.node.decode_or_drop(payload, WorkDone, "receipt", "receipt")
        if msg is None:
            return
        verdict = self.state.done(msg.worker, msg.seq, msg.ok)
        if verdict == "ok" and msg.method:  # which matcher produced each map, per method
            key = f"maps_{msg.method}"
            self.node.extra[key] = self.node.extra.get(key, 0) + 1
            self.methods[msg.worker] = msg.method
        if verdict not in ("ok", "failed"):
            self.node.warn(f"receipt-{verdict}", f"dropped receipt from {msg.worker} for seq {msg.seq}: {verdict}")
        elif verdict == "failed":
            self.node.warn("receipt-failed", f"worker {msg.worker} dropped seq {msg.seq}: {msg.reason}")

    def start(self) -> None:
        s = self.node.session
        self._subs.append(self.node.subscribe(topic("work_done").pattern(self.rid), self._on_done))
        self._subs.append(s.liveliness().declare_subscriber(topic("worker").pattern(self.rid), self._on_token,
                                                           history=True))

    def _send(self, name: str, msg: StereoFrame, payload: bytes) -> None:
        import zenoh

        if self.transport != "raw" or msg.left.encoding != "raw":
            payload = codec.encode(reencode_frame(msg, self.transport, self.jpeg_quality))
        age_ms = self.node.age_s(msg) * 1e3
        self.node.session.put(self._work.key(self.rid, instance=name), payload,
                              congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA,
                              attachment=make_attachment(age_ms, self.max_age_ms))
        self.rates.add(f"out_work_{name}", len(payload))

    def _housekeeping(self, out) -> None:
        for name, seq in self.state.expire():
            self.node.warn("timeout", f"worker {name}: no receipt for seq {seq} in time; slot freed")
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
        notes = ([f"quarantined: {', '.join(quarantined)}"] if quarantined else []) + \
                ([f"on probation: {', '.join(probation)}"] if probation else [])
        note = f"; {'; '.join(notes)}" if notes else ""
        if trusted:
            methods = sorted({m for w, m in list(self.methods.items())
                              if w in snap["workers"] and snap["workers"][w]["trust"] == "trusted"})
            self.node.status = (f"ok: {trusted} worker{'s' if trusted > 1 else ''}"
                                + (f" ({', '.join(methods)})" if methods else "") + note)
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

    def run(self) -> None:
        node = self.node
        inbox = node.latest("frames_rect")
        out = node.publisher("disparity")
        self.start()
        pending: tuple[StereoFrame, bytes] | None = None
        next_house = 0.0
        while node.running:
            now = time.monotonic()
            if now >= next_house:
                self._housekeeping(out)
                next_house = now + 0.1
            if self.state.trusted() == 0:
                # No proven worker: the onboard fallback computes, except for a frame that goes to a
                # worker due for a probe (a new one, or one back from quarantine).
                pending = None
                if self.fallback is None and not self.state.probe_due():
                    inbox.take(0.1)  # drain: overwritten frames count as drops; nothing to do
                    continue
                got = node.take(inbox, 0.1)
                if got is None or self._too_old(got[0]):
                    continue
                msg, payload = got
                name = self.state.claim(msg.seq)
                if name is not None:
                    self._dispatch(name, msg, payload)
                elif self.fallback is not None:
                    with node.processing(msg):
                        out.put(self.fallback.compute(msg, node.instance))
                        self.fallback.report(node)
                        self.node.extra["fallback_frames"] = self.node.extra.get("fallback_frames", 0) + 1
                continue
            if not self.state.wait_free(0.1):
                continue
            got = node.take(inbox, 0.0 if pending else 0.1)
            if got is not None:
                if pending is not None:
                    node.extra["replaced_pending"] = node.extra.get("replaced_pending", 0) + 1
                pending = got
            if pending is None:
                continue
            msg, payload = pending
            if self._too_old(msg):
                pending = None
                continue
            name = self.state.claim(msg.seq)
            if name is None:
                continue  # the free worker vanished meanwhile; keep the frame for the next one
            pending = None
            self._dispatch(name, msg, payload)

    def _dispatch(self, name: str, msg: StereoFrame, payload: bytes) -> None:
        with self.node.processing(msg):
            try:
                self._send(name, msg, payload)
            except BaseException:
                self.state.unclaim(name, msg.seq)
                raise
            self.node._published(self.node.age_ns(msg))


def run_dispatcher(node: Node, settings: Any) -> None:
    fallback = None
    if settings.fallback != "none":
        scale = 0.5 if settings.fallback == "half" else 1.0
        fallback = FrameComputer(settings, scale, "raw", label="onboard")
    state = DispatchState(settings.max_in_flight, settings.result_timeout_s)
    Dispatcher(node, state, settings.max_age_ms, settings.transport, settings.jpeg_quality, fallback).run()


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
    queue = WorkQueue()
    rates = Rates(node)

    def on_work(sample) -> None:
        att = sample.attachment
        node.count_input()
        if len(sample.payload) > topic("work").max_bytes:
            node.extra["in_work_oversized"] = node.extra.get("in_work_oversized", 0) + 1
            return
        payload = sample.payload.to_bytes()
        rates.add("in_work", len(payload))
        queue.offer(payload, att.to_bytes() if att is not None else None)

    node.subscribe(topic("work").key(rid, instance=me), on_work)
    out = node.publisher("disparity")
    receipts = node.publisher("work_done", instance=me)
    # Announce only once the work key is subscribed: the dispatcher sends as soon as it sees this.
    token = node.session.liveliness().declare_token(topic("worker").key(rid, instance=me))
    node.status = f"ok: {computer.method}, waiting for work"
    log.info("disparity worker %s ready on %s", me, topic("work").key(rid, instance=me))

    def receipt(msg: Any, ok: bool, reason: str = "", proc_ms: float = 0.0) -> None:
        receipts.put(WorkDone(robot_id=rid, seq=msg.seq, stamp_ns=msg.stamp_ns, worker=me, ok=ok,
                              reason=reason, proc_ms=proc_ms, method=computer.method if ok else ""), count=False)

    try:
        while node.running:
            rates.tick()
            node.extra["queue_overflowed"] = float(queue.overflowed)
            item = queue.take(0.2)
            if item is None:
                continue
            payload, attachment, received = item
            try:
                msg = node.decode(payload, StereoFrame)
                age_ms, max_age_ms = parse_attachment(attachment)
            except DecodeError as e:
                node.decode_errors += 1
                node.warn("decode", f"dropped work item: {e}")
                continue
            age_now = age_ms + (time.monotonic() - received) * 1e3
            if age_now > max_age_ms:
                node.extra["too_old"] = node.extra.get("too_old", 0) + 1
                receipt(msg, False, f"too old: {age_now:.0f} ms > {max_age_ms:.0f} ms")
                continue
            ok = False
            with node.processing(msg):
                result = computer.compute(msg, me)
                out.put(result)
                rates.add("out_disparity", len(result.image.data))
                computer.report(node)
                ok = True
                node.status = f"ok: {computer.method}"
            receipt(msg, ok, "" if ok else "failed (see worker log)", (time.monotonic() - received) * 1e3)
    finally:
        try:
            token.undeclare()
        except Exception:
            pass
