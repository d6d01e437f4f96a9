"""A fleet pool (services/disparity/fleet.py): the worker's fair scheduler and the dispatcher's
grants without a network, then real processes: robots fed rectified frames sharing pool workers."""
from __future__ import annotations

import pytest

from common.errors import ConfigError
from services.disparity.envelope import make_attachment
from services.disparity.fleet import attachment_grant
from services.disparity.scheduler import FairScheduler, parse_weights
from services.disparity.state import DispatchState


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


def test_the_worker_counts_its_time_on_items_and_not_its_idle_time():
    """busy_s (reported as pool_busy_s): what `bench fleet` weighs the pool's feeding by."""
    clock = FakeClock()
    sched = FairScheduler(clock=clock)
    start = clock.t
    served, _ = run_worker(sched, clock, lambda r, i: True, 200)
    assert sched.busy_s == pytest.approx(clock.t - start) and sum(served.values()) == 200  # fed all along
    clock = FakeClock()
    sched = FairScheduler(clock=clock)
    start = clock.t
    served, _ = run_worker(sched, clock, lambda r, i: r == "a" and i % 4 == 0, 200)  # a quarter of the steps
    assert sched.busy_s == pytest.approx(0.1 * sum(served.values()))
    assert 0.2 < sched.busy_s / (clock.t - start) < 0.3


def test_the_worker_says_how_busy_it_was_lately():
    """busy_share, over the last 5 s (`status` shows it per pool worker): the item being computed
    counts; idle seconds pull it down; no figure before a second of history."""
    clock = FakeClock()
    sched = FairScheduler(clock=clock)
    assert sched.busy_share() is None
    sched.demand("a", True)
    robot, grant = sched.next_grant()
    assert sched.arrived(robot, grant, b"frame", None) == "ok"
    item = sched.take(0)
    assert item is not None
    clock.t += 2.0
    assert sched.busy_share() == pytest.approx(1.0)  # computing all along
    sched.finished(item, 2.0)
    clock.t += 2.0
    assert sched.busy_share() == pytest.approx(0.5)  # then idle as long
    for _ in range(30):  # idle on: the window forgets the busy seconds
        clock.t += 0.25
        share = sched.busy_share()
    assert share == pytest.approx(0.0)


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


# --- the pool router's access control (deploy/pool-acl.py), real router, users over tcp ------------------

@pytest.mark.system
def test_pool_router_keeps_robots_and_workers_apart(tmp_path):
    """Robot A reads only its own grants and maps and cannot send work or demands in B's name; a
    worker sees only the frames sent to it and cannot answer as another worker. The router is
    started from the generated config (--plain: user/password over tcp; TLS is make-certs.sh's)."""
    import json
    import subprocess
    import sys
    import threading
    import time

    from helpers import REPO, free_port, wait_port

    from common.keys import topic
    from common.zenoh_session import ZenohOptions, open_session

    port = free_port()
    users = {"robot-A": "pa", "robot-B": "pb", "worker-w0": "p0", "worker-w1": "p1"}
    (tmp_path / "users.txt").write_text("".join(f"{u}:{p}\n" for u, p in users.items()))
    out = subprocess.run([sys.executable, str(REPO / "deploy/pool-acl.py"), "--pool", "lab", "--robot", "A",
                          "--robot", "B", "--worker", "w0", "--worker", "w1", "--plain", "--listen",
                          f"tcp/127.0.0.1:{port}", "--certs-path", str(tmp_path)],
                         check=True, capture_output=True, text=True)
    (tmp_path / "pool.json5").write_text(out.stdout)
    bad = subprocess.run([sys.executable, str(REPO / "deploy/pool-acl.py"), "--pool", "lab", "--robot", "a/b",
                          "--worker", "w"], capture_output=True, text=True)
    assert bad.returncode != 0 and "--robot 'a/b'" in bad.stderr
    log = open(tmp_path / "router.log", "w")
    router = subprocess.Popen([sys.executable, "-m", "ballbot_vision.cli", "run", "router", "--zenoh-config",
                               str(tmp_path / "pool.json5")], stdout=log, stderr=subprocess.STDOUT)

    def session(user: str):
        conf = tmp_path / f"{user}.json5"
        conf.write_text(json.dumps({"transport": {"auth": {"usrpwd": {"user": user, "password": users[user]}}}}))
        return open_session(ZenohOptions(mode="client", connect=[f"tcp/127.0.0.1:{port}"], listen=[],
                                         config_file=str(conf)))

    got: dict[str, list[str]] = {}
    cond = threading.Condition()

    def record(who: str):
        def cb(sample) -> None:
            with cond:
                got.setdefault(who, []).append(str(sample.key_expr))
                got.setdefault(who + ":payload", []).append(sample.payload.to_bytes())
                cond.notify_all()
        return cb

    def wait(pred, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with cond:
            while not pred():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                cond.wait(min(left, 0.5))
            return True

    P = "ballbot/pool/lab"
    try:
        wait_port(port, router)
        with session("robot-A") as a, session("robot-B") as b, session("worker-w0") as w0, \
                session("worker-w1") as w1:
            subs = [a.declare_subscriber(topic("pool_result").pattern("A", pool="lab"), record("A-own")),
                    a.declare_subscriber(f"{P}/result/B/*", record("A-spy")),
                    a.declare_subscriber(f"{P}/**", record("A-all")),
                    b.declare_subscriber(f"{P}/result/B/*", record("B-own")),
                    w0.declare_subscriber(topic("pool_work").pattern(pool="lab", instance="w0"), record("w0-own")),
                    w1.declare_subscriber(f"{P}/work/w0/*", record("w1-spy")),
                    w1.declare_subscriber(f"{P}/work/w1/*", record("w1-own"))]
            # a marker that must arrive proves the links and declarations are up before the denials count
            deadline = time.monotonic() + 30
            while not wait(lambda: "B-own" in got and "w0-own" in got, 0.5):
                assert time.monotonic() < deadline, f"nothing allowed arrived; router log in {tmp_path}"
                w0.put(f"{P}/result/B/w0", b"marker")
                a.put(f"{P}/work/w0/A", b"marker")
            a.put(f"{P}/work/w1/B", b"A sends in B's name")     # denied: not A's key
            a.put(f"{P}/demand/B", b"A asks in B's name")       # denied
            w0.put(f"{P}/result/A/w1", b"w0 answers as w1")     # denied: not w0's key
            w0.put(f"{P}/result/A/w0", b"w0's map for A")       # allowed, to A only
            w1.put(f"{P}/result/B/w1", b"w1's map for B")       # allowed, to B only
            b.put(f"{P}/work/w1/B", b"B's frame for w1")        # allowed, to w1 only
            assert wait(lambda: len(got.get("A-own", [])) >= 1 and len(got.get("w1-own", [])) >= 1
                        and len(got.get("B-own", [])) >= 2, 20), got
            time.sleep(1.0)  # bounded wait for what must NOT arrive (stated; all else waits on events)
            with cond:
                assert got.get("A-own") == [f"{P}/result/A/w0"], got
                assert "A-spy" not in got, got                      # A never sees B's maps
                # nothing of B's through the router (A's own puts come back to its own subscriber locally)
                assert not [k for k in got.get("A-all", []) if "/B/" in k or k.endswith("/w1")], got
                assert "w1-spy" not in got, got                     # w1 never sees w0's frames
                assert got.get("w1-own:payload") == [b"B's frame for w1"], got  # nor A's frame in B's name
            del subs
    finally:
        router.send_signal(15)
        try:
            router.wait(10)
        except subprocess.TimeoutExpired:
            router.kill()


# --- real processes: robots fed rectified frames, pool workers in their own network namespaces ---------

@pytest.mark.system
@pytest.mark.slow
def test_a_fleet_shares_a_pool_fairly_and_survives_a_kill_and_a_join(tmp_path):
    """Three robots (their dispatchers fed rectified frames by bench/fleet.py's feeder) share two
    sgbm pool workers, each in its own network namespace where `ip netns` works: every robot gets
    its share, a flooding robot no more, each map reaches only the robot that asked, a killed
    worker costs nobody the stream, a new worker is used, `status` shows the pool, and a robot
    whose pool vanishes computes onboard. Bounds are generous: the machine is shared."""
    import json
    import subprocess
    import sys
    import threading
    import time

    from bench.fleet_harness import Fleet

    robots = ["fa", "fb", "fc"]
    with Fleet(robots, greedy={"fa": 8}, fallback={"fc": "half"}, logdir=str(tmp_path)) as fleet:
        print("workers in", "network namespaces" if fleet.use_netns else f"this namespace ({fleet.netns_reason})")
        fleet.add_worker("w0")
        fleet.add_worker("w1")
        fleet.rates.update({r: 6.0 for r in robots})
        fleet.wait(lambda: {(m.robot, m.worker) for m in fleet.between(0, 1e18)}
                   >= {(r, f"{w}@fleet") for r in robots for w in ("w0", "w1")}, 240,
                   "every robot to get maps from both pool workers")

        def window(seconds: float) -> dict[str, float]:
            t0 = time.monotonic()
            time.sleep(seconds)  # a measuring window (what is measured arrives by events)
            ms = fleet.between(t0, time.monotonic())
            return {r: sum(1 for m in ms if m.robot == r) / seconds for r in robots}

        equal = window(8.0)
        total = sum(equal.values())
        print("equal maps/s", equal)
        assert total > 0 and all(v >= 0.5 * total / 3 for v in equal.values()), equal
        # fa floods: 4x the frames, 8 items in flight allowed, and frames without grants in its name
        fleet.rates["fa"] = 24.0
        flood = threading.Thread(target=fleet.flood_unsolicited, args=("fa", ["w0", "w1"], 2.0, 8.0), daemon=True)
        flood.start()
        flooded = window(8.0)
        flood.join()
        fleet.rates["fa"] = 6.0
        print("flood maps/s", flooded)
        others = (flooded["fb"] + flooded["fc"]) / 2
        # Max-min fairness: each of the others gets what it asks (6/s) or an equal share of what the pool
        # delivered, whichever is less; the flooder gets more than they do only out of capacity they leave
        # unused (a faster machine serves all 6/s of theirs and fa's surplus too). Against what the pool
        # delivered in this window, not before: on a shared machine its capacity moves with the load.
        entitled = min(6.0, sum(flooded.values()) / 3)
        assert min(flooded["fb"], flooded["fc"]) >= 0.8 * entitled, (equal, flooded)
        others_fully_served = min(flooded["fb"], flooded["fc"]) >= 0.9 * 6.0
        assert others_fully_served or flooded["fa"] <= 1.6 * others, (equal, flooded)
        fleet.wait(lambda: any(v["extra"].get("robot.fa.unsolicited", 0) > 0 for k, v in fleet.stats.items()
                               if "/pool-worker/" in k), 20, "a pool worker to count fa's unsolicited frames")
        # each worker says how long it has been on items (bench fleet weighs the pool's feeding by it):
        # some time, after the work above, and never more than it has been up
        with fleet.lock:
            busy = {w: v for w, v in fleet.busy.items() if len(v) >= 2}
        assert busy and all(0.0 < v[-1][2] <= v[-1][1] for v in busy.values()), busy
        # each map went back only to the robot that asked: no dispatcher saw a result it had not asked for
        fleet.wait(lambda: len([k for k in fleet.stats if "/dispatcher/" in k]) == 3, 20, "every dispatcher's stats")
        for k, v in fleet.stats.items():
            if "/dispatcher/" in k:
                assert v["extra"].get("results_unmatched", 0) == 0 and v["extra"].get("results_rejected", 0) == 0, \
                    (k, v["extra"])
        # `status` shows the pool: its workers and each robot's share
        out = subprocess.run([sys.executable, "-m", "ballbot_vision.cli", "status", "--json", "--connect",
                              fleet.endpoint, "--mode", "peer", "--wait", "3"], capture_output=True, text=True,
                             timeout=120)
        pools = {p["pool"]: p for p in json.loads(out.stdout)["pools"]}
        assert {w["instance"] for w in pools["fleet"]["workers"]} == {"w0", "w1"}, pools
        assert all(w["busy"] is not None and 0.0 <= w["busy"] <= 1.0 for w in pools["fleet"]["workers"]), pools
        shares = {r["robot"]: r for r in pools["fleet"]["robots"]}
        assert set(robots) <= set(shares) and all(0 < shares[r]["share"] <= 1 for r in robots), shares
        # a killed worker: every robot carries on with the survivor
        t_kill = fleet.kill_worker("w0")
        fleet.wait(lambda: {m.robot for m in fleet.between(t_kill + 0.5, 1e18) if m.worker == "w1@fleet"}
                   >= set(robots), 30, "every robot's maps from the surviving worker")
        time.sleep(3.0)  # the window the gaps are measured over
        for r in robots:
            ts = [t_kill] + sorted(m.t for m in fleet.between(t_kill, t_kill + 3.0) if m.robot == r)
            gap = max(b - a for a, b in zip(ts, ts[1:]))
            assert gap < 3.0, f"{r}: no map for {gap:.1f} s after the kill"
        # a new worker is used by every robot
        t_add = time.monotonic()
        fleet.add_worker("w2")
        fleet.wait(lambda: {m.robot for m in fleet.between(t_add, 1e18) if m.worker == "w2@fleet"} >= set(robots),
                   120, "every robot's maps from the new worker")
        token = fleet.token_time("w2", True, t_add)
        first = min(m.t for m in fleet.between(t_add, 1e18) if m.worker == "w2@fleet")
        print(f"new worker: first map {first - token:.2f} s after its token")
        assert first - token < 10.0
        # the pool vanishes: fc computes onboard (half resolution), the others say no worker reachable
        for w in ("w1", "w2"):
            fleet.kill_worker(w)
        t_gone = time.monotonic()
        fleet.wait(lambda: any(m.robot == "fc" and "onboard" in m.method for m in fleet.between(t_gone, 1e18)), 30,
                   "fc's onboard fallback")


@pytest.mark.system
@pytest.mark.slow
def test_a_fleet_bench_stopped_by_sigterm_leaves_no_process_or_namespace_behind():
    """`bench fleet` started from a shell script and stopped by `kill` (SIGTERM), mid-run: its
    router, dispatchers and pool workers stop with it and the network namespaces it made are
    deleted (a stopped bench once left a router listening and two namespaces behind)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from helpers import pid_alive

    def namespaces() -> set[str]:
        r = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True)
        return {line.split()[0] for line in r.stdout.splitlines() if line.startswith("bbfl")} if r.returncode == 0 \
            else set()

    def children(pid: int) -> set[int]:
        found: set[int] = set()
        todo = [pid]
        while todo:
            p = todo.pop()
            try:
                kids = {int(c) for t in os.listdir(f"/proc/{p}/task")
                        for c in open(f"/proc/{p}/task/{t}/children").read().split()}
            except OSError:
                continue
            todo += list(kids - found)
            found |= kids
        return found

    before = namespaces()
    argv = [sys.executable, "-m", "bench.fleet", "--robots", "2", "--workers", "1", "--seconds", "30"]
    bench = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        # the equal phase starts once every robot has maps from the worker: everything is running
        for line in bench.stderr:
            if line.startswith("equal:"):
                break
        else:
            pytest.fail(f"bench fleet ended before its first phase (exit {bench.wait()})")
        started = children(bench.pid)
        made = namespaces() - before
        assert len(started) >= 4, started  # router, 2 dispatchers, a worker (and `ip netns exec` where used)
        bench.send_signal(signal.SIGTERM)
        assert bench.wait(60) == 143
    finally:
        if bench.poll() is None:
            bench.kill()
            bench.wait()
    deadline = time.monotonic() + 30
    while any(pid_alive(p) for p in started) and time.monotonic() < deadline:
        time.sleep(0.1)  # children exit on their own SIGTERM; polled, no event to wait on
    assert not [p for p in started if pid_alive(p)], "processes outlived the bench"
    assert not (made & namespaces()), f"namespaces left behind: {made & namespaces()}"
