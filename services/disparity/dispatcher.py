"""The disparity dispatcher: on the robot, it hands each rectified frame to one of any number of
workers on any host (worker.py) or computes it onboard, and publishes only maps it checked.

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
  dispatcher computes in-process with the onboard fallback matcher (full or half resolution), or,
  with fallback none, says "no worker reachable" in its status while the segmenter's heartbeat
  marks the obstacle stream stale. The fallback is also what makes `ballbot-vision up` a single
  process per stage: no extra hop when everything runs on one host.

* With `--pool NAME` the dispatcher also uses a fleet pool's workers (fleet.py), named
  `<instance>@<pool>` here: the same trust, checks and fallback, but a pool worker gets a frame
  only against one of its grants (DispatchState.add_grant), which the dispatcher asks for while it
  holds a frame (PoolDemand) and gives back when it has none.

The pieces: state.py (DispatchState, the pure bookkeeping, unit-tested without Zenoh), envelope.py
(what travels beside an item), results.py (the checks of an answer), answers.py (where the answers
come in, are checked and republished), computer.py (one frame, for workers and the fallback),
demand.py (asking a pool for grants), this file (the sending side of the dispatcher's Zenoh
shell), worker.py (the worker's).
"""
from __future__ import annotations

import logging
import time
from typing import Any

from common import codec
from common.errors import BallbotError, DecodeError
from common.keys import POOL_ROOT, topic
from common.messages import PoolGrant, StereoFrame
from common.node import Node, qos
from common.signing import calibration_key
from services.disparity.answers import Answers, decode_from_worker
from services.disparity.computer import FrameComputer, reencode_frame
from services.disparity.demand import GrantDemand, KeyPut
from services.disparity.envelope import (
    make_attachment,
)
from services.disparity.rates import Rates
from services.disparity.results import (
    Ticket,
    measure,
)
from services.disparity.state import DispatchState

log = logging.getLogger("ballbot.pool")


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
        self.demand = GrantDemand(node.robot_id, state, node.count)  # asking the pool for grants
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
        self.answers = Answers(node, state, self.rates, self._name)  # what comes back: checked, then published

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
            self.answers.forget(name)
            self.rates.forget(f"out_work_{name}")
            log.warning("worker %s left (%d alive, %d trusted); %d in-flight frame(s) lost", name, self.state.alive(),
                        self.state.trusted(), lost)

    def _on_grant(self, sample) -> None:
        """A pool worker lets us send it one frame; kept for the main loop (or given back at once
        when it is none of ours or holds enough)."""
        name, instance = self._name(sample.key_expr)
        if len(sample.payload) > topic("pool_grant").max_bytes:
            self.node.count("grants_oversized")
            return
        msg = decode_from_worker(self.node, sample.payload.to_bytes(), PoolGrant, "grant", name, instance)
        if msg is None:
            return
        self.pool_load[name] = (msg.robots, msg.share, msg.queued)
        # a little under the worker's ttl: a frame sent at the last moment must still find its grant
        if not self.state.add_grant(name, msg.grant, 0.8 * msg.ttl_ms / 1e3, msg.wait_ms / 1e3):
            self.demand.refused(msg.grant)

    def _take(self, inbox: Any, timeout: float) -> tuple[StereoFrame, bytes] | None:
        return self.node.take(inbox, timeout)

    def start(self) -> None:
        s = self.node.session
        self._subs.append(self.node.subscribe(topic("work_done").pattern(self.rid), self.answers.on_done))
        self._subs.append(self.node.subscribe(topic("work_result").pattern(self.rid), self.answers.on_result))
        self._subs.append(self.node.watch_tokens(topic("worker").pattern(self.rid), self._on_token))
        self.node.uses("publishes", self._work.pattern(self.rid))  # put per item (_send)
        if self.pool:
            p = self.pool
            self._subs.append(self.node.subscribe(topic("pool_done").pattern(self.rid, pool=p), self.answers.on_done))
            self._subs.append(self.node.subscribe(topic("pool_result").pattern(self.rid, pool=p),
                                                  self.answers.on_result))
            self._subs.append(self.node.subscribe(topic("pool_grant").pattern(self.rid, pool=p), self._on_grant))
            self._subs.append(self.node.watch_tokens(topic("pool_worker").pattern(pool=p), self._on_token))
            key = topic("pool_demand").key(self.rid, pool=p)
            # a put per demand, not a declared publisher: no publisher state that could go stale while
            # workers come and go (in one bench run a robot's demands stopped reaching the workers
            # after a worker was replaced; the cause is not established)
            self.demand.pub = KeyPut(s, key, qos(topic("pool_demand")))
            self.node.uses("publishes", key)
            self.node.uses("publishes", topic("pool_work").pattern(self.rid, pool=p))
        self.answers.start()

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

    def _housekeeping(self) -> None:
        self.demand.input_rate(time.monotonic())
        self.demand.give_back_refused()
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
            methods = sorted({m for w, m in list(self.answers.methods.items())
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
            self.node.count("too_old")
            return True
        return False

    def _compute_onboard(self, fallback: FrameComputer, msg: StereoFrame) -> None:
        node = self.node
        with node.processing(msg):
            m = fallback.compute(msg, node.instance)
            raw = codec.array_from_image(m.image, "disparity")
            conf = codec.array_from_image(m.confidence, "disparity confidence") if m.confidence is not None else None
            vf = measure(raw, m.invalid_value, m.scale, m.min_disparity, m.num_disparities, conf).valid_fraction
            self.answers.publish(m, vf, time.monotonic())
            fallback.report(node)
            node.count("fallback_frames")

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
        inbox = self.demand.inbox = node.latest("frames_rect")
        self.answers.out = node.publisher("disparity", sign_key=self.sign_key)
        if self.sign_key is None:
            log.warning("dispatcher: no BALLBOT_CALIBRATION_KEY: the disparity maps are published unsigned, so the "
                        "segmenter cannot tell them from anyone else's (`up` and the compose files set one)")
        self.start()
        pending: tuple[StereoFrame, bytes] | None = None
        next_house = 0.0
        while node.running:
            now = time.monotonic()
            if now >= next_house:
                self._housekeeping()
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
                    self.demand.want(time.monotonic())  # a pool worker on probation probes only with a grant
                    if self.fallback is None and self.state.wait_free(0.1):
                        name, nonce = self._claim(msg)
                if name is not None:
                    self.demand.want_since = None
                    self._dispatch(name, msg, payload, nonce)
                elif self.fallback is not None:
                    self._compute_onboard(self.fallback, msg)
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
                    if self.demand.backlogged(now):
                        self.demand.want(now, ahead=True)
                    else:
                        self.demand.want_since = None
                    continue
                self.demand.want(now)
                since = self.demand.want_since  # (set by want)
                if self.fallback is not None and since is not None and now - since > self.pool_patience_s:
                    # the pool is there but grants us nothing (a full fleet): the robot is not left blind
                    self.node.count("pool_starved")
                    self._compute_onboard(self.fallback, pending[0])
                    pending, self.demand.want_since = None, None
                    continue
                self.state.wait_free(0.05)  # a grant wakes it
                continue
            if not self.state.wait_free(0.1):
                continue
            got = self._take(inbox, 0.0 if pending or self.pool else 0.1)
            if got is not None:
                if pending is not None:
                    node.count("replaced_pending")
                pending = got
            if pending is None:
                if self.pool:
                    # nothing to send: a grant held about a frame interval is given back (the pool
                    # worker then grants another robot)
                    self.demand.decline_unused(self.demand.hold_s())
                    self.demand.want_since = None
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
            self.demand.want_since = None
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


