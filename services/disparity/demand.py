"""A robot's side of a fleet pool's grants (fleet.py), for the dispatcher: it says it wants while
it holds a frame and no grant (again every 0.1 s: a worker forgets a want after 0.5 s, and a worker
that joins learns of it so), asks a little ahead while frames come faster than grants, holds a
grant that comes between frames about one frame interval, and gives back the grants it cannot use.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from common import codec
from common.messages import PoolDemand
from services.disparity.state import DispatchState


class KeyPut:
    """session.put on one key, shaped like a publisher."""

    def __init__(self, session: Any, key: str, qos_: dict[str, Any]):
        self.session, self.key, self.qos = session, key, qos_

    def put(self, payload: bytes) -> None:
        self.session.put(self.key, payload, **self.qos)


class GrantDemand:
    """count(key, n): the dispatcher's counters. pub (set when a pool is used) carries the demands;
    inbox (set by the dispatcher's run) is the frames' inbox, whose arrivals pace the asking."""

    def __init__(self, robot_id: str, state: DispatchState, count: Callable[[str, float], None]):
        self.rid, self.state, self._count = robot_id, state, count
        self.pub: KeyPut | None = None
        self.inbox: Any = None
        self.want_since: float | None = None  # wanting without a grant since
        self._want_at = 0.0  # last demand sent
        self._seq = 0
        self._refused: list[str] = []  # grants add_grant refused, to give back
        self._lock = threading.Lock()
        self._frame_interval_s = 1.0  # between the frames that arrive (input_rate)
        self._rx = (time.monotonic(), 0)
        self._wanted_at = -1e9  # last want with a frame in hand

    def refused(self, grant: str) -> None:
        """A grant add_grant refused: given back by the main loop (no put from a Zenoh callback)."""
        with self._lock:
            self._refused.append(grant)

    def send(self, want: bool, decline: Sequence[str] = ()) -> None:
        """Tell every worker of the pool that we hold a frame and no grant (want), and give back
        grants we cannot use (decline)."""
        if self.pub is None:
            return
        self._seq += 1
        for i in range(0, max(1, len(decline)), 32):
            msg = PoolDemand(robot_id=self.rid, seq=self._seq, stamp_ns=time.time_ns(), want=want,
                             decline=list(decline[i:i + 32]))
            self.pub.put(codec.encode(msg))
        if want:
            self._want_at = time.monotonic()
            self._count("pool_wants", 1)
        if decline:
            self._count("pool_declined", len(decline))

    def want(self, now: float, ahead: bool = False) -> None:
        """While we hold a frame and no grant: ask, again every 0.1 s. ahead: no frame yet, one is
        due (see backlogged); a grant that comes first is held for it (hold_s)."""
        if not ahead:
            self._wanted_at = now
        if self.want_since is None and not ahead:
            self.want_since = now
            self.send(want=True)
        elif now - self._want_at >= 0.1:
            self.send(want=True)

    def backlogged(self, now: float) -> bool:
        """Frames come faster than grants: we wanted with a frame in hand lately, and the next
        frame is due within the time a grant is held."""
        return now - self._wanted_at < 0.3 and self._frame_interval_s <= 0.5

    def give_back_refused(self) -> None:
        if self._refused:
            with self._lock:
                refused, self._refused = self._refused, []
            self.send(want=False, decline=refused)

    def decline_unused(self, held_s: float = 0.0) -> None:
        grants = [g for _, g in self.state.take_grants(held_s)]
        with self._lock:
            grants += self._refused
            self._refused = []
        if grants:
            self.send(want=False, decline=grants)

    def hold_s(self) -> float:
        """How long a grant that came while we hold no frame is kept for the next one: about one
        frame interval, and never past the moment its worker would start it (the worker computes
        another robot's item meanwhile, so the hold costs it nothing and saves a round of decline
        and re-grant; see DispatchState.take_grants)."""
        return min(0.5, 1.2 * self._frame_interval_s)

    def input_rate(self, now: float) -> None:
        """The interval between frames arriving (the inbox counts them all, taken or not)."""
        if self.inbox is None:
            return
        n, dt = self.inbox.received, now - self._rx[0]
        if dt >= 0.5:
            arrived = n - self._rx[1]
            interval = min(1.0, dt / arrived) if arrived else 1.0
            self._frame_interval_s = 0.5 * self._frame_interval_s + 0.5 * interval
            self._rx = (now, n)
