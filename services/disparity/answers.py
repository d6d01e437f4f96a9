"""The dispatcher's answer desk: what comes back from the workers (maps on their result keys,
receipts on their done keys) is taken only as the answer to an item outstanding at that worker,
checked (results.py: the cheap checks in the Zenoh callback, the full ones on this desk's own
thread) and only then republished on `disparity`, signed. A refused answer costs the worker its
trust (DispatchState.reject), never the robot its output. The sending side is dispatcher.py.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from common import codec
from common.errors import DecodeError
from common.messages import DisparityMap, PoolGrant, WorkDone
from common.node import Node
from cores.matching.disparity import RecentValid
from services.disparity.envelope import _attachment_bytes, receipt_nonce
from services.disparity.rates import Rates
from services.disparity.results import MIN_MEASURED, parse_header, vet_header, vet_map
from services.disparity.state import DispatchState

log = logging.getLogger("ballbot.pool")
M = TypeVar("M", WorkDone, PoolGrant)  # the messages a worker signs with its name


def decode_from_worker(node: Node, payload: bytes, model: type[M], what: str, name: str, instance: str) -> M | None:
    """A `what` (receipt, grant) that came on the key of worker `instance` (called `name` here), or
    None. One naming another worker is forged or misrouted: believing it would let one worker
    answer for another, so it is counted (`<what>s_misnamed`) and dropped like one that does not
    decode."""
    msg = node.decode_or_drop(payload, model, what, what)
    if msg is None:
        return None
    if msg.worker != instance:
        node.count(f"{what}s_misnamed")
        node.warn(f"{what}-misnamed", f"dropped a {what} on {name}'s key naming worker {msg.worker}")
        return None
    return msg


class Answers:
    """name_of(key_expr) -> (the worker's name here, its instance): how the dispatcher names the
    worker a key belongs to. out (set by the dispatcher's run) is the signed `disparity` publisher."""

    def __init__(self, node: Node, state: DispatchState, rates: Rates,
                 name_of: Callable[[Any], tuple[str, str]]):
        self.node, self.state, self.rates, self.name_of = node, state, rates, name_of
        self.out: Any = None
        self.methods: dict[str, str] = {}  # worker -> the method its last map was made with
        # Maps that passed the cheap checks, waiting for the full ones: at most one per item in
        # flight (DispatchState.answer lets only the first answer to an item through).
        self._results: queue.Queue = queue.Queue()
        self.recent = RecentValid()  # valid fractions of the maps published lately (any source)
        self.recent_by_worker: dict[str, RecentValid] = {}  # ... and of each worker's own
        self._recent_lock = threading.Lock()

    def start(self) -> None:
        threading.Thread(target=self.run, name="results", daemon=True).start()

    def forget(self, name: str) -> None:
        """A worker left: its history goes with it."""
        self.methods.pop(name, None)
        with self._recent_lock:
            self.recent_by_worker.pop(name, None)

    # callbacks (Zenoh threads: bookkeeping and small checks only)
    def on_done(self, sample) -> None:
        """A receipt: a worker says it dropped an item (too old, undecodable, failed). Taken only
        with the item's nonce; one claiming success is a lie (the map is the answer)."""
        payload = sample.payload.to_bytes()
        self.rates.add("in_work_done", len(payload))
        name, instance = self.name_of(sample.key_expr)
        msg = decode_from_worker(self.node, payload, WorkDone, "receipt", name, instance)
        if msg is None:
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

    def on_result(self, sample) -> None:
        """A worker's map: everything that can be checked without copying or decoding the payload
        is checked here; what passes waits for the results thread."""
        name, _ = self.name_of(sample.key_expr)
        n = len(sample.payload)
        self.rates.add("in_work_result", n)
        try:
            header = parse_header(_attachment_bytes(sample))
        except DecodeError as e:
            # anyone can put on a worker's key: costs the named worker nothing
            self.node.count("results_unmatched")
            self.node.warn("result-header", f"dropped a map on {name}'s result key: {e}")
            return
        kind, ticket = self.state.answer(name, header.seq, header.nonce)
        if ticket is None:
            self.node.count("results_unmatched")
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
        self.node.count("results_rejected")
        self.node.warn("result-rejected", f"refused worker {name}'s answer for seq {seq}: {why}; worker quarantined")

    # the results thread: full checks, then republish
    def run(self) -> None:
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
        why, check = vet_map(m, header, ticket)  # (check: None exactly when why says what is wrong)
        if check is not None and not why:
            why = self._collapsed(name, check.valid_fraction)
        if why or check is None:
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
            self.node.count("results_late")  # timed out while being checked
            return
        # The frame's own stamp, stages, camera and checks: nothing the worker says moves the robot's
        # clock or clears a misaligned rig or a frozen camera.
        out = m.model_copy(update={"robot_id": ticket.robot_id, "seq": ticket.seq, "stamp_ns": ticket.stamp_ns,
                                   "stages": dict(ticket.stages), "camera": ticket.camera, "checks": ticket.checks,
                                   "worker": name,
                                   "method": m.method[:64]})
        self.publish(out, valid_fraction, time.monotonic())
        with self._recent_lock:
            self.recent_by_worker.setdefault(name, RecentValid()).add(valid_fraction, time.monotonic())
        key = f"maps_{out.method}"
        if key not in self.node.extra and sum(k.startswith("maps_") for k in list(self.node.extra)) >= 16:
            key = "maps_other"  # a worker naming every map differently must not grow the stats without bound
        self.node.count(key)
        self.methods[name] = out.method

    def publish(self, m: DisparityMap, valid_fraction: float, now: float) -> None:
        self.out.put(m)
        with self._recent_lock:
            self.recent.add(valid_fraction, now)

