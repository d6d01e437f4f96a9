"""The thin Zenoh shell every service shares: inputs that keep only the newest message, publishers
from the key table, a liveliness token, stats once a second, and a clean stop on SIGINT/SIGTERM.

A service's main() reads like this (its cores know nothing of Zenoh):

    with Node("segmenter", opts, robot_id) as node:
        inbox = node.latest("disparity")          # newest wins; overwritten inputs count as drops
        out = node.publisher("obstacles")
        for msg in node.receive(inbox):           # decoded, validated; bad payloads logged+counted
            with node.processing(msg):            # times it; errors are logged, counted, dropped
                out.put(core(msg), msg)
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import statistics
import struct
import threading
import time
import uuid
from collections import deque
from contextlib import contextmanager
from typing import Any, Callable, Iterator, TypeVar

from . import codec
from .errors import BallbotError, DecodeError
from .keys import Topic, topic
from .messages import Message, ServiceStats
from .zenoh_session import ZenohOptions, open_session

log = logging.getLogger("ballbot")
M = TypeVar("M", bound=Message)


# Publishers attach the capture stamp of what they publish, so an inbox can order payloads
# without decoding them.
_STAMP = struct.Struct(">Q")


def stamp_of(attachment: Any) -> int | None:
    try:
        raw = attachment.to_bytes() if attachment is not None else None
        return _STAMP.unpack(raw)[0] if raw is not None and len(raw) == _STAMP.size else None
    except Exception:  # a foreign publisher's attachment: no ordering information
        return None


class Inbox:
    """A slot that holds only the newest payload (a ring channel of one). Zenoh's callback thread
    only swaps a reference here, so a slow service never backs up the network.

    "Newest" is by capture stamp when the publisher attached one: results that arrive out of order
    (several disparity workers) never replace a newer waiting payload, and nothing older than what
    was already taken gets through. Ordering by capture time rather than seq survives a capture
    restart, which starts seq again at 0."""

    def __init__(self, topic: Topic):
        self.topic = topic
        self._cond = threading.Condition()
        self._payload: bytes | None = None
        self._stamp: int | None = None
        self._taken_stamp = -1
        self.received = 0
        self.overwritten = 0
        self.late = 0
        self.bytes = 0

    def offer(self, payload: bytes, stamp_ns: int | None = None) -> None:
        with self._cond:
            self.received += 1
            self.bytes += len(payload)
            if stamp_ns is not None and (stamp_ns <= self._taken_stamp
                                         or (self._stamp is not None and stamp_ns < self._stamp)):
                self.late += 1
                return
            if self._payload is not None:
                self.overwritten += 1
            self._payload = payload
            self._stamp = stamp_ns
            self._cond.notify()

    def take(self, timeout: float) -> bytes | None:
        with self._cond:
            if self._payload is None:
                self._cond.wait(timeout)
            p, self._payload = self._payload, None
            if p is not None and self._stamp is not None:
                self._taken_stamp = self._stamp
            self._stamp = None
            return p


class _Window:
    """Values of the last stats period."""

    def __init__(self) -> None:
        self.values: deque[float] = deque(maxlen=10000)

    def add(self, v: float) -> None:
        self.values.append(v)

    def median_and_clear(self) -> float:
        if not self.values:
            return 0.0
        m = float(statistics.median(self.values))
        self.values.clear()
        return m


class Publisher:
    def __init__(self, node: "Node", topic: Topic, key: str):
        import zenoh

        self.node, self.topic, self.key = node, topic, key
        # Images: newest wins, so a congested link drops frames instead of delaying every later one.
        cc = zenoh.CongestionControl.DROP if topic.image_stream else zenoh.CongestionControl.BLOCK
        self._pub = node.session.declare_publisher(key, congestion_control=cc,
                                                   priority=zenoh.Priority.DATA if topic.image_stream
                                                   else zenoh.Priority.DATA_HIGH)
        self.bytes = 0

    def put(self, msg: Message, count: bool = True) -> None:
        """Publish; stamps this service's publish time into msg.stages and, if count, records the
        output in the service's rate and age (side outputs such as ground truth pass count=False)."""
        now = time.time_ns()
        msg.stages[self.node.service] = now
        payload = codec.encode(msg)
        self._pub.put(payload, attachment=_STAMP.pack(msg.stamp_ns))
        self.bytes += len(payload)
        if count:
            self.node._published(now - msg.stamp_ns)


class Node:
    def __init__(self, service: str, options: ZenohOptions, robot_id: str, instance: str | None = None,
                 install_signal_handlers: bool = True):
        self.service = service
        self.robot_id = robot_id
        self.instance = instance or f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:4]}"
        self.options = options
        self.stop_event = threading.Event()
        self.status = "starting"
        self.extra: dict[str, float] = {}
        self._lock = threading.Lock()
        self._proc = _Window()
        self._age = _Window()
        self._published_in_window = 0
        self.processed = self.published = self.decode_errors = self.errors = 0
        self._inboxes: list[Inbox] = []
        self._publishers: list[Publisher] = []
        self._subscribers: list[Any] = []
        self._started = time.monotonic()
        self._last_log: dict[str, float] = {}
        self._install_signals = install_signal_handlers
        self.session = None

    # -- lifecycle ------------------------------------------------------------------------------
    def __enter__(self) -> "Node":
        if self._install_signals and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda *_: self.stop_event.set())
        self.session = open_session(self.options)
        self._token = self.session.liveliness().declare_token(
            topic("alive").key(self.robot_id, service=self.service, instance=self.instance))
        self._stats_pub = self.session.declare_publisher(
            topic("stats").key(self.robot_id, service=self.service, instance=self.instance))
        self._stats_thread = threading.Thread(target=self._stats_loop, name="stats", daemon=True)
        self._stats_thread.start()
        self.status = "ok"
        log.info("%s %s up (robot %s)", self.service, self.instance, self.robot_id)
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop_event.set()
        try:
            self.session.close()
        except Exception:  # closing a session twice or after a fatal error must not mask the cause
            pass

    @property
    def running(self) -> bool:
        return not self.stop_event.is_set()

    # -- inputs ---------------------------------------------------------------------------------
    def latest(self, name: str, key: str | None = None) -> Inbox:
        t = topic(name)
        inbox = Inbox(t)
        sub = self.session.declare_subscriber(key or t.key(self.robot_id),
                                              lambda s: inbox.offer(s.payload.to_bytes(), stamp_of(s.attachment)))
        self._subscribers.append(sub)
        self._inboxes.append(inbox)
        return inbox

    def subscribe(self, key: str, callback: Callable[[Any], None]) -> Any:
        sub = self.session.declare_subscriber(key, callback)
        self._subscribers.append(sub)
        return sub

    def receive(self, inbox: Inbox, poll_s: float = 0.2) -> Iterator[Any]:
        """Yield decoded messages until stopped. A payload that does not decode is logged, counted
        and dropped; so is one for another robot."""
        model = inbox.topic.model
        while self.running:
            payload = inbox.take(poll_s)
            if payload is None:
                continue
            msg = self.decode_or_drop(payload, model, f"input on {inbox.topic.name}")
            if msg is not None:
                yield msg

    def decode(self, payload: bytes, model: type[M]) -> M:
        """Decode a message that must be this robot's; raises DecodeError otherwise."""
        msg = codec.decode(payload, model)
        if msg.robot_id != self.robot_id:
            raise DecodeError(f"{model.__name__}: robot_id {msg.robot_id!r} on {self.robot_id!r}'s key")
        return msg

    def decode_or_drop(self, payload: bytes, model: type[M], what: str, kind: str = "decode") -> M | None:
        """decode(), or None after counting the decode error and logging (rate-limited) what was dropped."""
        try:
            return self.decode(payload, model)
        except DecodeError as e:
            self.decode_errors += 1
            self.warn(kind, f"dropped {what}: {e}")
            return None

    @contextmanager
    def processing(self, msg: Message | None = None) -> Iterator[None]:
        """Time one unit of work; a failure is logged, counted and dropped, never fatal."""
        t0 = time.perf_counter()
        try:
            yield
        except DecodeError as e:
            self.decode_errors += 1
            self.warn("decode", f"dropped seq {getattr(msg, 'seq', '?')}: {e}")
        except BallbotError as e:
            self.errors += 1
            self.warn("error", f"dropped seq {getattr(msg, 'seq', '?')}: {e}")
        except Exception:
            self.errors += 1
            if self._should_log("exception"):
                log.exception("%s: unexpected failure on seq %s (dropped)", self.service, getattr(msg, "seq", "?"))
        else:
            self.processed += 1
        finally:
            self._proc.add((time.perf_counter() - t0) * 1e3)

    # -- outputs --------------------------------------------------------------------------------
    def publisher(self, name: str, **fields: str) -> Publisher:
        t = topic(name)
        p = Publisher(self, t, t.key(self.robot_id, **fields))
        self._publishers.append(p)
        return p

    def _published(self, age_ns: int) -> None:
        with self._lock:
            self.published += 1
            self._published_in_window += 1
        self._age.add(age_ns / 1e6)

    # -- logging and stats ----------------------------------------------------------------------
    def _should_log(self, kind: str, every_s: float = 2.0) -> bool:
        now = time.monotonic()
        if now - self._last_log.get(kind, -1e9) >= every_s:
            self._last_log[kind] = now
            return True
        return False

    def warn(self, kind: str, text: str) -> None:
        """Rate-limited warning, so a flood of garbage cannot flood the log."""
        if self._should_log(kind):
            log.warning("%s: %s", self.service, text)

    def stats(self) -> ServiceStats:
        now = time.monotonic()
        window = max(now - getattr(self, "_window_start", self._started), 1e-3)
        self._window_start = now
        with self._lock:
            published, self._published_in_window = self._published_in_window, 0
        extra = dict(self.extra)
        for inbox in self._inboxes:
            extra[f"in_{inbox.topic.name}_bytes"] = float(inbox.bytes)
            extra[f"in_{inbox.topic.name}_late"] = float(inbox.late)
        for p in self._publishers:
            extra[f"out_{p.topic.name}_bytes"] = float(p.bytes)
        return ServiceStats(
            robot_id=self.robot_id, service=self.service, instance=self.instance, host=socket.gethostname(),
            pid=os.getpid(), stamp_ns=time.time_ns(), uptime_s=now - self._started,
            rate_hz=published / window, proc_ms_p50=self._proc.median_and_clear(),
            age_ms_p50=self._age.median_and_clear(), processed=self.processed, published=self.published,
            drops=sum(i.overwritten + i.late for i in self._inboxes), decode_errors=self.decode_errors,
            errors=self.errors, status=self.status, extra=extra)

    def _stats_loop(self) -> None:
        while not self.stop_event.wait(1.0):
            try:
                self._stats_pub.put(codec.encode(self.stats()))
            except Exception:  # a closing session; the loop ends with the stop event
                if self.running and self._should_log("stats"):
                    log.exception("stats publish failed")


def setup_logging(level: str = "INFO") -> None:
    logging.basicConfig(level=os.environ.get("BALLBOT_LOG", level),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
