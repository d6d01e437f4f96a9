"""What arrives at a service: newest-wins inboxes, the freshness gate every stamped payload passes
before it may wait there, and the clock ages are measured on (the Node hands them out; no Zenoh here
beyond reading a sample's payload and attachment).

Ordering and freshness rules are FreshnessGate's; the attachment every Publisher puts beside a
payload is Meta (common/node.py writes it).
"""
from __future__ import annotations

import os
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from common import signed_payload
from common.keys import Topic

# --- what travels beside every payload ------------------------------------------------------------

@dataclass(frozen=True)
class Meta:
    """The attachment every Publisher puts beside a payload, so an inbox can order and vet payloads
    without decoding them: the capture stamp of what is published (ns since the epoch, the
    capture host's clock), the publisher's random 64-bit id (new on every start) and its own
    sequence number (1, 2, ... per publisher: gaps are losses)."""

    stamp_ns: int
    source: int = 0  # 0: unknown (an 8-byte legacy attachment: the stamp only)
    seq: int = 0


_META = struct.Struct(">QQQ")
_STAMP = struct.Struct(">Q")


def meta_of(attachment: Any) -> Meta | None:
    """The Meta of a sample's attachment; None for none or a foreign one (then only the message's
    own stamp, after decoding, is checked)."""
    try:
        raw = attachment.to_bytes() if attachment is not None else None
    except Exception:  # a foreign publisher's attachment: no ordering information
        return None
    if raw is None:
        return None
    if len(raw) in (_META.size, _META.size + signed_payload.TAG_BYTES):  # signed: the tag follows
        return Meta(*_META.unpack(raw[:_META.size]))
    if len(raw) == _STAMP.size:
        return Meta(_STAMP.unpack(raw)[0])
    return None


def _in_shared_memory(payload: Any) -> bool:
    try:
        return payload.as_shm() is not None
    except Exception:  # a build without shared memory, or an API that changed: not known to be
        return False


def stamp_of(attachment: Any) -> int | None:
    m = meta_of(attachment)
    return None if m is None else m.stamp_ns


class Clock:
    """Wall and monotonic time in ns. One object so tests can inject a stepping wall clock; the
    monotonic clock is what every age and every time base uses, so a wall-clock step (NTP on a
    robot without an RTC) moves no age and no velocity."""

    def wall_ns(self) -> int:
        return time.time_ns()

    def mono_ns(self) -> int:
        return time.monotonic_ns()


SYSTEM_CLOCK = Clock()


class OffsetFileClock(Clock):
    """Fault injection: the wall clock plus the offset (seconds, may be negative) written in a file,
    re-read every 50 ms. With BALLBOT_FAULT_CLOCK_OFFSET_FILE set, every service of a test run
    sees one simulated NTP step when the test writes the file, without touching the machine's
    clock; the monotonic clock is untouched, as with a real step."""

    def __init__(self, path: str):
        self.path = path
        self._offset_ns = 0
        self._read_at = -1.0
        self._lock = threading.Lock()

    def wall_ns(self) -> int:
        now = time.monotonic()
        with self._lock:
            if now - self._read_at >= 0.05:
                self._read_at = now
                try:
                    with open(self.path) as f:
                        self._offset_ns = int(float(f.read().strip() or 0) * 1e9)
                except (OSError, ValueError):
                    pass  # keep the last offset
            return time.time_ns() + self._offset_ns


def clock_from_env() -> Clock:
    path = os.environ.get("BALLBOT_FAULT_CLOCK_OFFSET_FILE")
    return OffsetFileClock(path) if path else SYSTEM_CLOCK


@dataclass
class FreshnessLimits:
    """max_future_s: a stamp this far ahead of our clock (plus the learned offset) is refused: no
    honest sender is ahead of the capture that stamped it. max_past_s: one this far behind is
    refused (a replay, or garbage). resync_s: after this long without accepting anything while
    stamped input keeps being refused, the gate adopts the time base of the input that arrives
    most (a clock step on the capture host, a source on another time base)."""

    max_future_s: float = 0.25
    max_past_s: float = 10.0
    resync_s: float = 1.0

    @classmethod
    def from_env(cls) -> FreshnessLimits:
        def f(name: str, default: float) -> float:
            v = os.environ.get(name)
            return float(v) if v else default
        return cls(f("BALLBOT_MAX_FUTURE_S", cls.max_future_s), f("BALLBOT_MAX_PAST_S", cls.max_past_s),
                   f("BALLBOT_RESYNC_S", cls.resync_s))


REJECTIONS = ("future", "old", "late")


class FreshnessGate:
    """Decides, before decoding, whether a stamped payload is plausible and newer than what was
    already handed on. Pure bookkeeping (no Zenoh); not thread-safe on its own (Inbox locks it).

    - A stamp more than max_future_s ahead of this host's wall clock (corrected by the learned
      offset) is refused as "future", more than max_past_s behind as "old": one forged stamp
      (2^64-1, an hour ahead) can no longer become the reference that every later frame is
      compared with.
    - Order: nothing at or before the stamp last handed on passes ("late"), so results of several
      workers never go backwards. That reference is committed only once the payload decoded and
      its own stamp matched the attachment (commit()), so garbage with a plausible stamp costs
      nothing but itself.
    - Our own wall clock stepping back leaves the reference in the future: it is dropped at once
      (counted as a clock step), so a local NTP step costs the frames in flight and no more.
    - A per-publisher sequence number: gaps count as lost (a replay is refused as late).
    - Resynchronisation: if nothing was accepted for resync_s while stamped payloads kept being
      refused, the gate adopts the time base of the publisher that sent the most of them (the
      offset between its stamps and our clock) and forgets the reference: a capture host whose
      clock stepped, or a source on another time base, costs at most resync_s.
    """

    MAX_SOURCES = 64

    def __init__(self, clock: Clock = SYSTEM_CLOCK, limits: FreshnessLimits | None = None):
        self.clock = clock
        self.limits = limits or FreshnessLimits()
        self.offset_ns = 0  # the senders' capture clock minus our wall clock, learned on resync
        self.reference: int | None = None  # stamp of the last payload handed on
        self.counts: dict[str, int] = {k: 0 for k in (*REJECTIONS, "lost", "resyncs", "clock_steps")}
        self._last_accept_mono = clock.mono_ns()
        self._refused_by_source: dict[int, int] = {}
        self._refused_since_accept = 0
        self._seq: dict[int, int] = {}  # source -> last seq seen

    def _skew_ns(self, stamp_ns: int) -> int:
        """How far the stamp is ahead (+) or behind (-) our clock, in the senders' time base."""
        return stamp_ns - self.offset_ns - self.clock.wall_ns()

    def check(self, meta: Meta, waiting: int | None = None) -> str:
        """-> "ok" or the reason it is refused (one of REJECTIONS). waiting: the stamp of the
        payload already waiting in the inbox, which an older one must not displace."""
        lim = self.limits
        future_ns, past_ns = int(lim.max_future_s * 1e9), int(lim.max_past_s * 1e9)
        if self.reference is not None and self._skew_ns(self.reference) > future_ns:
            self.reference = None  # our clock stepped back under the reference: forget it
            self.counts["clock_steps"] += 1
        now_mono = self.clock.mono_ns()
        verdict = "ok"
        skew = self._skew_ns(meta.stamp_ns)
        if skew > future_ns:
            verdict = "future"
        elif skew < -past_ns:
            verdict = "old"
        elif (self.reference is not None and meta.stamp_ns <= self.reference) or \
                (waiting is not None and meta.stamp_ns < waiting):
            verdict = "late"  # also a replay of anything already handed on
        if verdict == "ok" and meta.source:
            # Losses on the way, per publisher. Only accepted payloads move this, and an implausible
            # jump counts nothing, so a forged sequence number cannot poison a real publisher's.
            last = self._seq.get(meta.source)
            if last is not None and last < meta.seq <= last + 1000:
                self.counts["lost"] += meta.seq - last - 1
            self._seq[meta.source] = meta.seq
            if len(self._seq) > self.MAX_SOURCES:  # forged ids cannot grow this without bound
                self._seq.pop(next(iter(self._seq)))
        if verdict == "ok":
            self._accepted(now_mono)
            return verdict
        if self._should_resync(meta, now_mono):
            if abs(skew) > future_ns:  # a clearly different time base: adopt it (ages stay right)
                self.offset_ns += skew
            self.reference = None
            self.counts["resyncs"] += 1
            self._accepted(now_mono)
            return "ok"
        self.counts[verdict] += 1
        return verdict

    def _accepted(self, now_mono: int) -> None:
        self._last_accept_mono = now_mono
        self._refused_since_accept = 0
        self._refused_by_source.clear()

    def _should_resync(self, meta: Meta, now_mono: int) -> bool:
        self._refused_since_accept += 1
        n = self._refused_by_source.get(meta.source, 0) + 1
        self._refused_by_source[meta.source] = n
        if len(self._refused_by_source) > self.MAX_SOURCES:
            self._refused_by_source.pop(next(iter(self._refused_by_source)))
        quiet = now_mono - self._last_accept_mono >= self.limits.resync_s * 1e9
        return quiet and self._refused_since_accept >= 3 and n == max(self._refused_by_source.values())

    def commit(self, stamp_ns: int) -> bool:
        """The payload with this stamp decoded: it becomes the new reference and may be handed on
        (True), unless a newer one was committed meanwhile (False: counted late). check() saw the
        reference before the newer payload, taken ahead of it, had finished decoding; without this
        second look a worker's older map would follow the newer one out, and the lists would go
        backwards."""
        if self.reference is not None and stamp_ns <= self.reference:
            self.counts["late"] += 1
            return False
        self.reference = stamp_ns
        self._accepted(self.clock.mono_ns())
        return True

    def age_ns(self, stamp_ns: int, wall_ns: int) -> int:
        """Age of a capture stamp at wall time wall_ns (ours), in the learned time base; >= 0."""
        return max(0, wall_ns + self.offset_ns - stamp_ns)


@dataclass
class Delivery:
    """One payload taken from an inbox, with what was known when it arrived."""

    payload: bytes
    meta: Meta | None
    wall_ns: int  # our wall clock at arrival
    mono_ns: int  # our monotonic clock at arrival


class Inbox:
    """A slot that holds only the newest payload (a ring channel of one). Zenoh's callback thread
    only swaps a reference here, so a slow service never backs up the network.

    With a FreshnessGate (every Node inbox has one) a stamped payload is vetted before it may wait
    here: see FreshnessGate for what is refused. Without one (a tool's plain inbox) "newest" is by
    capture stamp alone. A payload larger than max_bytes is dropped before it is copied out of
    Zenoh (counted as oversized).

    The one copy: a payload from a peer on this host sits in Zenoh's shared memory (see
    zenoh_session.py; counted in `shm`), but zenoh-python 1.10 lends no buffer over it, so
    to_bytes() copies it out (about 0.05 ms for a 640x480 pair); from there the images are numpy
    views of these bytes (codec.array_from_image), not copied again."""

    def __init__(self, topic: Topic, gate: FreshnessGate | None = None, max_bytes: int | None = None,
                 clock: Clock = SYSTEM_CLOCK):
        self.topic = topic
        self.gate = gate
        self.clock = clock
        self.max_bytes = max_bytes if max_bytes is not None else topic.max_bytes
        self._cond = threading.Condition()
        self._waiting: Delivery | None = None
        self._taken_stamp = -1  # without a gate
        self.on_refused: Callable[[str, Meta], None] | None = None  # (verdict, meta): the node logs it
        self.sign_key: bytes | None = None  # set: only payloads signed with it for their key pass
        self.sign_key_expr = ""  # the key, for a sample that does not name its own
        self.unauthenticated = {"unsigned": 0, "forged": 0}
        self.received = 0
        self.overwritten = 0
        self.late = 0  # every refusal (future, old, late; without a gate: late only)
        self.oversized = 0
        self.unstamped = 0  # without an attachment, dropped because a stamped payload waited
        self.bytes = 0
        self.shm = 0  # payloads that came through shared memory (a peer on this host)

    def offer_sample(self, sample: Any) -> None:
        """The Zenoh callback: size cap first (nothing copied), then the signature (with a sign_key:
        before the stamp may touch the freshness gate), then offer()."""
        n = len(sample.payload)
        if n > self.max_bytes:
            with self._cond:
                self.received += 1
                self.oversized += 1
                self.bytes += n
            return
        payload = sample.payload.to_bytes()
        if self.sign_key is not None:
            try:
                att = sample.attachment.to_bytes() if sample.attachment is not None else None
            except Exception:  # a foreign attachment: unsigned
                att = None
            # the key it came on (a wildcard subscription still checks each sample's own key)
            key_expr = str(sample.key_expr) if getattr(sample, "key_expr", None) is not None else self.sign_key_expr
            verdict = signed_payload.check(self.sign_key, key_expr, att, payload, _META.size)
            if verdict != "ok":
                with self._cond:
                    self.received += 1
                    self.bytes += n
                    self.late += 1
                    self.unauthenticated[verdict] += 1
                if self.on_refused is not None:
                    self.on_refused(verdict, meta_of(sample.attachment) or Meta(0))
                return
        if _in_shared_memory(sample.payload):
            self.shm += 1
        self.offer(payload, meta_of(sample.attachment))

    def offer(self, payload: bytes, meta: Meta | int | None = None) -> None:
        if isinstance(meta, int):
            meta = Meta(meta)
        with self._cond:
            self.received += 1
            self.bytes += len(payload)
            waiting = self._waiting.meta.stamp_ns if self._waiting is not None and self._waiting.meta else None
            if meta is not None:
                if self.gate is not None:
                    verdict = self.gate.check(meta, waiting)
                    if verdict != "ok":
                        self.late += 1
                        if self.on_refused is not None and verdict != "late":
                            self.on_refused(verdict, meta)
                        return
                elif meta.stamp_ns <= self._taken_stamp or (waiting is not None and meta.stamp_ns < waiting):
                    self.late += 1
                    return
            elif waiting is not None:
                # Without an attachment nothing can be vetted before decoding, so such a payload never
                # takes the place of a stamped one that waits: a flood of garbage costs itself, not
                # every good payload it would otherwise overwrite.
                self.unstamped += 1
                return
            if self._waiting is not None:
                self.overwritten += 1
            self._waiting = Delivery(payload, meta, self.clock.wall_ns(), self.clock.mono_ns())
            self._cond.notify()

    def take_delivery(self, timeout: float) -> Delivery | None:
        with self._cond:
            if self._waiting is None and timeout > 0:
                self._cond.wait(timeout)
            d, self._waiting = self._waiting, None
            if d is not None and d.meta is not None and self.gate is None:
                self._taken_stamp = d.meta.stamp_ns
            return d

    def take(self, timeout: float) -> bytes | None:
        d = self.take_delivery(timeout)
        return None if d is None else d.payload

    def vet(self, stamp_ns: int) -> str:
        """For a payload that came without an attachment: check its decoded stamp. -> 'ok' | reason."""
        if self.gate is None:
            return "ok"
        with self._cond:
            verdict = self.gate.check(Meta(stamp_ns))
            if verdict != "ok":
                self.late += 1
            return verdict

    def commit(self, stamp_ns: int) -> bool:
        """-> may the decoded payload with this stamp be handed on (FreshnessGate.commit)?"""
        if self.gate is None:
            return True
        with self._cond:
            ok = self.gate.commit(stamp_ns)
            if not ok:
                self.late += 1
            return ok

    def refusals(self) -> dict[str, int]:
        out = dict(self.gate.counts) if self.gate is not None else {"late": self.late}
        if self.sign_key is not None:
            out.update(self.unauthenticated)
        return out
