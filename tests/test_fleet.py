"""A fleet pool (services/disparity/fleet.py): the worker's fair scheduler and the dispatcher's
grants without a network, then real processes: robots fed rectified frames sharing pool workers."""
from __future__ import annotations

import pytest

from common.errors import ConfigError
from services.disparity.fleet import FairScheduler, attachment_grant, parse_weights
from services.disparity.pool import DispatchState, make_attachment


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def run_worker(sched: FairScheduler, clock: FakeClock, wants, items: int, cost: float = 0.1,
               unsolicited: str | None = None) -> tuple[dict[str, int], dict[str, list[int]]]:
    """Drives one worker for `items` computed items. wants(robot, i) -> does robot want at step i.
    -> (items served per robot, per robot: how many other items were computed between its grant
    and the start of its item, i.e. what its frame waited behind)."""
    served: dict[str, int] = {}
    waits: dict[str, list[int]] = {}
    granted_at: dict[str, int] = {}
    started = 0
    robots = set(sched.weights) | {"a", "b", "c", "d"}

    def grant_all() -> None:
        while (g := sched.next_grant()) is not None:
            robot, grant = g
            granted_at[grant] = started
            assert sched.arrived(robot, grant, b"frame", None) == "ok"

    for i in range(items):
        for r in sorted(robots):
            if wants(r, i):
                sched.demand(r, True)
        if unsolicited:
            assert sched.arrived(unsolicited, "00" * 16, b"flood", None) == "unsolicited"
        grant_all()
        item = sched.take(0)
        if item is None:
            clock.t += cost
            continue
        grant_all()  # the next frame travels while this one is computed
        waits.setdefault(item.robot, []).append(started - granted_at.pop(item.grant))
        started += 1
        clock.t += cost
        sched.finished(item, cost)
        served[item.robot] = served.get(item.robot, 0) + 1
    return served, waits


def test_equal_robots_get_equal_shares_and_wait_behind_one_item_at_most():
    clock = FakeClock()
    sched = FairScheduler(clock=clock)
    served, waits = run_worker(sched, clock, lambda r, i: True, 400)
    assert sorted(served) == ["a", "b", "c", "d"]
    assert max(served.values()) - min(served.values()) <= 1, served
    # one item waits beside the one computed (a few more while there is no history to tell shares)
    assert all(sum(w[40:]) / len(w[40:]) <= 1.0 and max(w[40:]) <= 1 for w in waits.values()), waits


def test_weights_divide_the_worker():
    clock = FakeClock()
    sched = FairScheduler({"a": 2, "b": 1, "c": 1}, clock=clock)
    served, _ = run_worker(sched, clock, lambda r, i: r in "abc", 400)
    assert abs(served["a"] - 200) <= 2 and abs(served["b"] - 100) <= 2 and abs(served["c"] - 100) <= 2, served


def test_a_flooding_robot_gets_its_share_and_a_light_robot_is_served_at_once():
    """a floods (wants all the time and puts frames without a grant); d wants one frame in eight
    (well within its quarter): d is granted as soon as it asks, beyond the waiting slot, and its
    frame starts right after the item being computed."""
    clock = FakeClock()
    sched = FairScheduler(clock=clock)
    served, waits = run_worker(sched, clock, lambda r, i: r != "d" or i % 8 == 0, 800, unsolicited="a")
    assert served["d"] == 100, served
    others = [served[r] for r in "abc"]
    assert max(others) - min(others) <= 1, served  # the flood took no more than b or c
    assert max(waits["d"]) <= 1 and sum(waits["d"]) <= 5, waits["d"]
    assert sched.counters["priority"] >= 90
    assert sched.counters["unsolicited"] == 800


def test_a_robot_back_from_idle_banks_no_credit():
    clock = FakeClock()
    sched = FairScheduler(clock=clock)
    # a is idle for the first 300 items, then everybody wants
    served, _ = run_worker(sched, clock, lambda r, i: r != "a" or i >= 300, 400)
    # in the last 100 items a gets its quarter (25), not the 75 it "missed"
    assert served["a"] <= 27, served


def test_grants_expire_and_declined_grants_cost_nothing():
    clock = FakeClock()
    sched = FairScheduler(grant_ttl_s=1.0, clock=clock)
    sched.demand("a", True)
    robot, g = sched.next_grant()
    assert robot == "a" and sched.next_grant() is None  # one slot waiting
    clock.t += 1.5
    assert sched.expire() == [("a", g)]
    assert sched.arrived("a", g, b"late", None) == "unsolicited"
    sched.demand("a", True)
    sched.demand("b", True)
    first, g1 = sched.next_grant()
    sched.demand(first, False, [g1])  # given back: the slot is free again, the robot keeps its place
    second, g2 = sched.next_grant()
    assert second != first
    assert sched.arrived(second, g2, b"f", None) == "ok"
    assert sched.arrived(second, g2, b"again", None) == "unsolicited"  # a grant is good for one frame


def test_home_robot_items_share_the_worker_with_the_pool():
    clock = FakeClock()
    sched = FairScheduler(clock=clock)
    served = {"home": 0, "a": 0}
    for _ in range(200):
        if len([f for f in sched.flows.values() if f.robot == "home" and f.queued]) == 0:
            sched.push("home", b"h", None)
            sched.push("home", b"h", None)
        sched.demand("a", True)
        while (g := sched.next_grant()) is not None:
            sched.arrived(g[0], g[1], b"f", None)
        item = sched.take(0)
        clock.t += 0.1
        sched.finished(item, 0.1)
        served[item.robot] += 1
    assert abs(served["home"] - served["a"]) <= 4, served


def test_pool_weights_text_and_errors():
    assert parse_weights("robotA=2, robotB=1") == {"robotA": 2.0, "robotB": 1.0}
    assert parse_weights({"x": 3}) == {"x": 3.0}
    for bad, what in (("robotA", "robot=weight"), ("a=two", "not a number"), ("a=0", "> 0"), ("a/b=1", "robot id")):
        with pytest.raises(ValueError, match=what):
            parse_weights(bad)


def test_pool_weights_flag_error_names_the_flag(monkeypatch):
    from common.settings import load_settings
    from services.disparity.main import DisparitySettings

    monkeypatch.setenv("BALLBOT_DISPARITY_POOL_WEIGHTS", "a=1,b=x")
    with pytest.raises(ConfigError, match="BALLBOT_DISPARITY_POOL_WEIGHTS.*not a number"):
        load_settings(DisparitySettings)
    monkeypatch.setenv("BALLBOT_DISPARITY_POOL_WEIGHTS", "a=1,b=3")
    assert load_settings(DisparitySettings).pool_weights == {"a": 1.0, "b": 3.0}


# --- the dispatcher's side: a pool worker gets work only against its grants ------------------------------

def test_a_pool_worker_gets_work_only_against_a_live_grant():
    clock = FakeClock()
    st = DispatchState(max_in_flight=2, result_timeout_s=1.0, clock=clock)
    st.add_worker("w@lab", pooled=True)
    assert st.claim(1) is None  # on probation, but no grant: no probe
    assert st.add_grant("w@lab", "aa" * 16, ttl_s=0.5)
    assert not st.add_grant("w@lab", "bb" * 16)  # probation: one probe at a time
    assert st.claim(1) == "w@lab" and st.grant_of("w@lab", 1) == "aa" * 16
    assert st.done("w@lab", 1) == "ok" and st.trusted() == 1
    assert st.claim(2) is None  # trusted, yet nothing without a grant
    assert st.add_grant("w@lab", "cc" * 16, ttl_s=0.5) and st.add_grant("w@lab", "dd" * 16, ttl_s=0.5)
    assert not st.add_grant("w@lab", "ee" * 16)  # at most max_in_flight items and grants
    clock.t += 0.6
    assert st.claim(2) is None  # expired: never send against a grant the worker has withdrawn
    assert st.add_grant("w@lab", "ff" * 16, ttl_s=0.5)
    assert st.take_grants() == [("w@lab", "ff" * 16)] and st.claim(3) is None
    assert not st.add_grant("ghost@lab", "11" * 16) and st.counters["unknown_worker"] == 1


def test_a_quarantined_pool_worker_gets_a_probe_only_when_due_and_granted():
    clock = FakeClock()
    st = DispatchState(max_in_flight=1, result_timeout_s=1.0, clock=clock)
    st.add_worker("w@lab", pooled=True)
    assert st.add_grant("w@lab", "aa" * 16) and st.claim(1) == "w@lab"
    clock.t += 1.1
    st.expire()
    assert st.workers["w@lab"].trust == "quarantined"
    assert not st.add_grant("w@lab", "bb" * 16)  # backoff: its grant is given back
    clock.t += 1.1
    assert st.add_grant("w@lab", "cc" * 16) and st.claim(2) == "w@lab"  # the probe
    assert st.done("w@lab", 2) == "ok" and st.trusted() == 1


def test_the_grant_travels_in_the_work_items_attachment():
    att = make_attachment(3.0, 500.0, b"n" * 16, "ab" * 16)
    assert attachment_grant(att) == "ab" * 16
    assert attachment_grant(make_attachment(3.0, 500.0, b"n" * 16)) == ""
    assert attachment_grant(b"\xc1junk") == "" and attachment_grant(None) == ""
