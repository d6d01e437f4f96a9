"""The thin Zenoh shell every service shares: inputs that keep only the newest message (inbox.py),
publishers from the key table, a liveliness token, stats once a second, and a clean stop on
SIGINT/SIGTERM.

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
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, TypeVar

from pydantic import BaseModel

from common import codec, signed_payload
from common.errors import BallbotError, DecodeError
from common.inbox import _META, REJECTIONS, Clock, FreshnessGate, FreshnessLimits, Inbox, Meta, clock_from_env, stamp_of
from common.keys import WORKER_SEGMENT, Topic, topic, topics_of
from common.memory import release_memory_eagerly, trim_memory
from common.messages import Message, ServiceStats
from common.settings import MountSettings
from common.zenoh_session import ZenohOptions, open_session

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("ballbot")
M = TypeVar("M", bound=BaseModel)  # a Message, or ServiceStats: both carry robot_id


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


def qos(t: Topic) -> dict[str, Any]:
    """Congestion control, priority and express for a topic's publisher.

    Every stream is DROP: a subscriber that cannot keep up (a stuck peer, a slow Wi-Fi client) loses
    messages on its own link instead of blocking the put, and so the producer and every other
    subscriber (with BLOCK, one peer whose callback takes 1 s stalled the obstacle stream for
    everyone). Each priority has its own transmission queue, so small messages never wait behind
    image fragments: the public streams go first (REAL_TIME, express: no batching delay), then
    receipts that free worker slots, then images, then stats."""
    import zenoh

    P = zenoh.Priority
    if t.public:
        prio, express = P.REAL_TIME, True
    elif t.name == "work_done":
        prio, express = P.INTERACTIVE_HIGH, True
    elif t.name == "stats":
        prio, express = P.DATA_LOW, False
    elif t.image_stream:
        prio, express = P.DATA, False
    else:
        prio, express = P.DATA_HIGH, False
    return {"congestion_control": zenoh.CongestionControl.DROP, "priority": prio, "express": express}


class Publisher:
    def __init__(self, node: Node, topic: Topic, key: str, sign_key: bytes | None = None):
        self.node, self.topic, self.key = node, topic, key
        self.sign_key = sign_key  # set: every payload is signed (common/signed_payload.py)
        self._pub = node.session.declare_publisher(key, **qos(topic))
        self.source = int.from_bytes(os.urandom(8), "big") or 1  # this publisher's id in every attachment
        self.seq = 0
        self.bytes = 0
        self.put_s_max = 0.0  # longest put() of the stats period: time the service waited on the network
        self._lock = threading.Lock()

    def put(self, msg: Message, count: bool = True) -> None:
        """Publish; stamps this service's publish time into msg.stages and, if count, records the
        output in the service's rate and age (side outputs such as ground truth pass count=False)."""
        msg.stages[self.node.service] = self.node.clock.wall_ns()
        payload = codec.encode(msg)
        with self._lock:  # a heartbeat thread and the main loop may share a publisher
            self.seq += 1
            attachment = _META.pack(msg.stamp_ns, self.source, self.seq)
            if self.sign_key is not None:
                attachment = signed_payload.seal(self.sign_key, self.key, attachment, payload)
            t0 = time.perf_counter()
            self._pub.put(payload, attachment=attachment)
            self.put_s_max = max(self.put_s_max, time.perf_counter() - t0)
        self.bytes += len(payload)
        if count:
            self.node._published(self.node.age_ns(msg))


class _Progress:
    """Input, output and failure counts of the last few stats periods: the service's health is
    about progress, not about being alive. A stage whose input arrives but that published nothing
    for stall_s is degraded (failed after fail_s); one whose every input fails is failed."""

    def __init__(self, stall_s: float, fail_s: float):
        self.stall_s, self.fail_s = stall_s, fail_s
        self.history: deque[tuple[float, int, int, int, int]] = deque()  # (t, inputs, published, ok, failed)
        self.quiet_since: float | None = None  # input arriving but nothing published, since

    def update(self, t: float, inputs: int, published: int, ok: int, failed: int) -> tuple[str, str]:
        self.history.append((t, inputs, published, ok, failed))
        while len(self.history) > 2 and t - self.history[1][0] >= self.stall_s:
            self.history.popleft()
        t0, i0, p0, ok0, f0 = self.history[0]
        span = t - t0
        d_in, d_pub, d_ok, d_fail = inputs - i0, published - p0, ok - ok0, failed - f0
        if span < self.stall_s or d_in == 0 or d_pub > 0:
            self.quiet_since = None
            return "ok", ""
        if d_fail > 0 and d_ok == 0:
            return "failed", f"every input fails ({d_fail} failed in the last {span:.0f} s)"
        if self.quiet_since is None:
            self.quiet_since = t0
        quiet = t - self.quiet_since
        return ("failed" if quiet >= self.fail_s else "degraded",
                f"input arrives ({d_in} in the last {span:.0f} s) but nothing published for {quiet:.0f} s")


class Node:
    def __init__(self, service: str, options: ZenohOptions, robot_id: str, instance: str | None = None,
                 install_signal_handlers: bool = True, clock: Clock | None = None,
                 limits: FreshnessLimits | None = None, pool: str | None = None, worker_keys: bool = False,
                 mount: MountSettings | None = None):
        """pool: a fleet pool's worker: its stats and token live under the pool's keys. worker_keys:
        publish stats and liveliness on the workers' own keys (worker_stats, worker_alive), the only
        ones the gateway lets an offboard worker write."""
        if service == WORKER_SEGMENT:
            raise ValueError(f"no service may be named '{WORKER_SEGMENT}': its stats key is the workers' own")
        self.service = service
        self.mount = mount or MountSettings()  # the camera on the robot (the `mount:` section)
        self.pool = pool
        self.worker_keys = worker_keys
        self.robot_id = robot_id
        self.instance = instance or f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:4]}"
        self.options = options
        self.clock = clock or clock_from_env()
        self.limits = limits or FreshnessLimits.from_env()
        self.stop_event = threading.Event()
        self.status = "starting"
        self.role = ""  # shown by `status`: e.g. disparity's dispatcher or worker
        self.health = "starting"
        self.extra: dict[str, float] = {}
        self._lock = threading.Lock()
        self._proc = _Window()
        self._age = _Window()
        self._published_in_window = 0
        self.processed = self.published = self.decode_errors = self.errors = 0
        self.inputs = 0  # inputs that arrive outside an inbox (count_input())
        self._inboxes: list[Inbox] = []
        self._subscribes: set[str] = set()  # topic names, see uses()
        self._publishes: set[str] = {"stats", "alive"}
        self._publishers: list[Publisher] = []
        self._subscribers: list[Any] = []
        self._started = time.monotonic()
        self._last_log: dict[str, float] = {}
        self._install_signals = install_signal_handlers
        # capture stamp -> the capture moment on our monotonic clock (ns), for what was received lately
        self._capture_mono: dict[int, int] = {}
        self._time_base_ns = 0  # last frame time handed out: frame times never go backwards
        self._progress = _Progress(float(os.environ.get("BALLBOT_STALL_S", 3.0)),
                                   float(os.environ.get("BALLBOT_FAIL_S", 10.0)))
        self._bytes_last: dict[str, float] = {}
        self._session: zenoh.Session | None = None

    # -- lifecycle ------------------------------------------------------------------------------
    @property
    def session(self) -> zenoh.Session:
        """The Zenoh session, open inside `with node:` only."""
        if self._session is None:
            raise BallbotError(f"{self.service}: no Zenoh session outside `with node:`")
        return self._session

    def __enter__(self) -> Node:
        if self._install_signals and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda *_: self.stop_event.set())
        release_memory_eagerly()
        self._session = open_session(self.options)
        if self.pool:
            alive_key = topic("pool_alive").key(self.robot_id, pool=self.pool, instance=self.instance)
            stats_key = topic("pool_stats").key(self.robot_id, pool=self.pool, instance=self.instance)
            self._publishes = {"pool_stats", "pool_alive"}
        elif self.worker_keys:
            alive_key = topic("worker_alive").key(self.robot_id, instance=self.instance)
            stats_key = topic("worker_stats").key(self.robot_id, instance=self.instance)
            self._publishes = {"worker_stats", "worker_alive"}
        else:
            alive_key = topic("alive").key(self.robot_id, service=self.service, instance=self.instance)
            stats_key = topic("stats").key(self.robot_id, service=self.service, instance=self.instance)
        self._token = self.session.liveliness().declare_token(alive_key)
        self._stats_pub = self.session.declare_publisher(stats_key, **qos(topic("stats")))
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
    def latest(self, name: str, key: str | None = None, max_bytes: int | None = None,
               sign_key: bytes | None = None) -> Inbox:
        """A newest-wins inbox on a topic, with a freshness gate and a size cap (the topic's
        max_bytes unless a tighter one is known, e.g. from the calibrated image size). With
        sign_key, only payloads signed with it pass (common/signed_payload.py), checked before
        their stamp reaches the gate."""
        t = topic(name)
        key = key or t.key(self.robot_id)
        inbox = Inbox(t, FreshnessGate(self.clock, self.limits), max_bytes, self.clock)
        self.uses("subscribes", key)
        if sign_key is not None:
            inbox.sign_key, inbox.sign_key_expr = sign_key, key

        def refused(verdict: str, meta: Meta) -> None:
            if verdict in inbox.unauthenticated:
                self.warn(f"refused-{verdict}", f"dropped input on {name}: "
                          + ("not signed with this robot's key" if verdict == "unsigned"
                             else "its signature does not match (another key, or changed on the way)")
                          + f" (counted in in_{name}_{verdict})")
            else:
                self.warn(f"refused-{verdict}", f"dropped input on {name}: capture stamp {meta.stamp_ns} is "
                                                f"{'in the future' if verdict == 'future' else 'too old'} for this "
                                                f"clock (counted in in_{name}_{verdict})")

        inbox.on_refused = refused
        sub = self.session.declare_subscriber(key, inbox.offer_sample)
        self._subscribers.append(sub)
        self._inboxes.append(inbox)
        return inbox

    def subscribe(self, key: str, callback: Callable[[Any], None], keep: bool = True) -> Any:
        """A subscriber on a key of the table (recorded in the stats). keep: held until the node
        closes; False for one the caller undeclares itself (a stream subscribed only while watched)."""
        self.uses("subscribes", key)
        sub = self.session.declare_subscriber(key, callback)
        if keep:
            self._subscribers.append(sub)
        return sub

    def watch_tokens(self, key: str, callback: Callable[[Any], None]) -> Any:
        """A liveliness subscriber (with the tokens alive already: history) on a key of the table."""
        self.uses("subscribes", key)
        sub = self.session.liveliness().declare_subscriber(key, callback, history=True)
        self._subscribers.append(sub)
        return sub

    def declare_token(self, key: str) -> Any:
        """A liveliness token on a key of the table (recorded in the stats)."""
        self.uses("publishes", key)
        return self.session.liveliness().declare_token(key)

    def declare_publisher(self, key: str, **qos_: Any) -> Any:
        """A raw Zenoh publisher on a key of the table (recorded in the stats), for payloads that are
        not one of our messages with its stamp (Publisher is for those)."""
        self.uses("publishes", key)
        return self.session.declare_publisher(key, **qos_)

    def uses(self, how: str, key_expr: str) -> None:
        """Record that this instance subscribes to or publishes on a key expression: its stats
        carry the key table's topics it really uses (tests hold them against the table)."""
        found = topics_of(key_expr)
        if not found:
            raise ValueError(f"{self.service}: {key_expr} is not a key of common/keys.py's table")
        with self._lock:
            getattr(self, "_" + how).update(found)

    def count_input(self) -> None:
        """An input that arrived outside an inbox (health: input arrives, is anything published?)."""
        with self._lock:
            self.inputs += 1

    def take(self, inbox: Inbox, timeout: float) -> tuple[Any, bytes] | None:
        """The newest waiting input, decoded and vetted -> (message, payload), or None (nothing
        within timeout, or it was dropped: undecodable, another robot's, or its stamp refused)."""
        d = inbox.take_delivery(timeout)
        if d is None:
            return None
        model = inbox.topic.model
        if model is None or not issubclass(model, Message):
            raise BallbotError(f"take: {inbox.topic.name} carries no stamped message")
        msg = self.decode_or_drop(d.payload, model, f"input on {inbox.topic.name}")
        if msg is None:
            return None
        if d.meta is not None and d.meta.stamp_ns != msg.stamp_ns:
            self.decode_errors += 1
            self.warn("decode", f"dropped input on {inbox.topic.name}: attachment stamp {d.meta.stamp_ns} "
                                f"!= message stamp {msg.stamp_ns}")
            return None
        if d.meta is None:
            verdict = inbox.vet(msg.stamp_ns)
            if verdict != "ok":
                self.warn(f"refused-{verdict}", f"refused input on {inbox.topic.name}: stamp {verdict}")
                return None
        if not inbox.commit(msg.stamp_ns):
            return None  # a newer payload was handed on while this one decoded
        age = inbox.gate.age_ns(msg.stamp_ns, d.wall_ns) if inbox.gate is not None else 0
        with self._lock:
            self._capture_mono[msg.stamp_ns] = d.mono_ns - age
            while len(self._capture_mono) > 256:
                self._capture_mono.pop(next(iter(self._capture_mono)))
        return msg, d.payload

    def receive(self, inbox: Inbox, poll_s: float = 0.2) -> Iterator[Any]:
        """Yield decoded, vetted messages until stopped. A payload that does not decode is logged,
        counted and dropped; so is one for another robot, and one whose stamp is refused."""
        while self.running:
            got = self.take(inbox, poll_s)
            if got is not None:
                yield got[0]

    # -- time -----------------------------------------------------------------------------------
    def age_ns(self, msg: Message) -> int:
        """Age of a received message (or of one derived from it: same stamp) on our monotonic
        clock: the wall clock is read once, at arrival. For a stamp we never received (capture's
        own frames) the wall clock says."""
        with self._lock:
            t = self._capture_mono.get(msg.stamp_ns)
        if t is None:
            return max(0, self.clock.wall_ns() - msg.stamp_ns)
        return max(0, self.clock.mono_ns() - t)

    def age_s(self, msg: Message) -> float:
        return self.age_ns(msg) / 1e9

    def frame_time_s(self, msg: Message) -> float:
        """The capture moment of a received message on our monotonic clock, in s, never earlier
        than the one handed out before: the time base for velocities, immune to wall-clock steps."""
        with self._lock:
            t = self._capture_mono.get(msg.stamp_ns)
            if t is None:
                t = self.clock.mono_ns() - max(0, self.clock.wall_ns() - msg.stamp_ns)
            t = max(t, self._time_base_ns)
            self._time_base_ns = t
        return t / 1e9

    def decode(self, payload: bytes, model: type[M]) -> M:
        """Decode a message that must be this robot's; raises DecodeError otherwise."""
        msg = codec.decode(payload, model)
        robot = getattr(msg, "robot_id", None)
        if robot != self.robot_id:
            raise DecodeError(f"{model.__name__}: robot_id {robot!r} on {self.robot_id!r}'s key")
        return msg

    def decode_or_drop(self, payload: bytes, model: type[M], what: str, kind: str = "decode") -> M | None:
        """decode(), or None after counting the decode error and logging (rate-limited) what was dropped."""
        try:
            return self.decode(payload, model)
        except DecodeError as e:
            self.decode_errors += 1
            self.warn(kind, f"dropped {what}: {e}")
            return None

    def stamp_or_drop(self, sample: Any, stream: str) -> int | None:
        """The capture stamp of a sample's attachment, or None after counting (in_<stream>_unstamped)
        and logging (rate-limited) that it came without one: every publisher of ours stamps, and in
        a newest-wins slot an unstamped payload could only push the good ones out."""
        stamp = stamp_of(sample.attachment)
        if stamp is None:
            self.count(f"in_{stream}_unstamped")
            self.warn("unstamped", f"dropped a payload on {stream} without its stamp attachment")
        return stamp

    @contextmanager
    def processing(self, msg: BaseModel | None = None) -> Iterator[None]:
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
    def publisher(self, name: str, sign_key: bytes | None = None, **fields: str) -> Publisher:
        t = topic(name)
        p = Publisher(self, t, t.key(self.robot_id, **fields), sign_key)
        with self._lock:
            self._publishes.add(name)
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
            extra = dict(self.extra)  # count() adds keys from the callback threads
        inputs = self.inputs
        refused: dict[str, int] = {}
        for inbox in self._inboxes:
            # repeats of what was already handed on (a heartbeat's stale copy) are not new input,
            # nor is anyone's payload without the robot's signature
            inputs += (inbox.received - inbox.refusals().get("late", 0) - sum(inbox.unauthenticated.values())
                       - inbox.unstamped)
            name = inbox.topic.name
            self._rate(extra, f"in_{name}", inbox.bytes, window)
            extra[f"in_{name}_oversized"] = float(inbox.oversized)
            extra[f"in_{name}_unstamped"] = float(inbox.unstamped)
            extra[f"in_{name}_shm"] = float(inbox.shm)
            for k, v in inbox.refusals().items():
                extra[f"in_{name}_{k}"] = float(v)
                refused[k] = refused.get(k, 0) + v
        for p in self._publishers:
            self._rate(extra, f"out_{p.topic.name}", p.bytes, window)
            extra[f"out_{p.topic.name}_put_ms_max"], p.put_s_max = p.put_s_max * 1e3, 0.0
        health, why = self._progress.update(now, inputs, self.published, self.processed,
                                            self.errors + self.decode_errors)
        if why and sum(refused.get(k, 0) for k in REJECTIONS):
            why += " (refused so far: " + ", ".join(f"{refused[k]} {k}" for k in REJECTIONS if refused.get(k)) + ")"
        self.health = health
        status = self.status if health == "ok" else f"{health}: {why}"
        return ServiceStats(
            robot_id=self.robot_id, service=self.service, role=self.role, instance=self.instance,
            host=socket.gethostname(),
            pid=os.getpid(), stamp_ns=self.clock.wall_ns(), uptime_s=now - self._started,
            rate_hz=published / window, proc_ms_p50=self._proc.median_and_clear(),
            age_ms_p50=self._age.median_and_clear(), processed=self.processed, published=self.published,
            drops=sum(i.overwritten + i.late + i.oversized + i.unstamped for i in self._inboxes),
            decode_errors=self.decode_errors, errors=self.errors, status=status, health=health, extra=extra,
            subscribes=sorted(self._subscribes), publishes=sorted(self._publishes))

    def count(self, key: str, n: float = 1.0) -> None:
        """Add n to the counter `key` in extra (shown by `status`). Callbacks run on several Zenoh
        threads: the lock keeps a read-modify-write from losing counts."""
        with self._lock:
            self.extra[key] = self.extra.get(key, 0.0) + n

    def _rate(self, extra: dict[str, float], name: str, total: float, window: float) -> None:
        """Byte total and per-second rate of one link: '<name>_bytes', 'rate_<name>_Bps'."""
        extra[f"{name}_bytes"] = float(total)
        extra[f"rate_{name}_Bps"] = (total - self._bytes_last.get(name, 0.0)) / window
        self._bytes_last[name] = float(total)

    def _stats_loop(self) -> None:
        while not self.stop_event.wait(1.0):
            try:
                self._stats_pub.put(codec.encode(self.stats()))
                trim_memory()
            except Exception:  # a closing session; the loop ends with the stop event
                if self.running and self._should_log("stats"):
                    log.exception("stats publish failed")


def setup_logging(level: str = "INFO") -> None:
    logging.basicConfig(level=os.environ.get("BALLBOT_LOG", level),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
