"""The disparity worker (any host): work items from its own key -> maps on its own result key
(the dispatcher checks and republishes them, see dispatcher.py)."""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Any

from common import codec
from common.errors import DecodeError
from common.keys import topic
from common.messages import StereoFrame, WorkDone
from common.node import Node, qos
from services.disparity.computer import FrameComputer
from services.disparity.envelope import parse_attachment, receipt_attachment
from services.disparity.rates import Rates

log = logging.getLogger("ballbot.pool")


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
            node.count("in_work_oversized")
            return
        payload = sample.payload.to_bytes()
        rates.add("in_work", len(payload))
        queue_.offer(payload, att.to_bytes() if att is not None else None)

    node.subscribe(topic("work").key(rid, instance=me), on_work)
    # Maps go only to this worker's own result key: the dispatcher checks each against the item it
    # sent and republishes it on `disparity`; receipts only for items dropped.
    results = node.declare_publisher(topic("work_result").key(rid, instance=me), **qos(topic("work_result")))
    receipts = node.declare_publisher(topic("work_done").key(rid, instance=me), **qos(topic("work_done")))
    # Announce only once the work key is subscribed: the dispatcher sends as soon as it sees this.
    token = node.declare_token(topic("worker").key(rid, instance=me))
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
                node.count("too_old")
                dropped(msg, nonce, f"too old: {age_now:.0f} ms > {max_age_ms:.0f} ms")
                continue
            if computer.answer(node, msg, me, nonce, results.put, rates):
                node.status = f"ok: {computer.method}"
            else:
                dropped(msg, nonce, "failed (see worker log)", (time.monotonic() - received) * 1e3)
    finally:
        try:
            token.undeclare()
        except Exception:
            pass
