"""`ballbot-vision bench fleet`: several robots sharing one pool of disparity workers
(services/disparity/fleet.py), per robot against its fair share.

What runs: a router; per robot its disparity dispatcher (`run disparity --pool fleet`, no onboard
fallback, so every map is the pool's) fed rectified synthetic 640x480 pairs by this bench (one feeder
thread per robot: four full capture/rectify/segmenter pipelines do not fit a 2-core machine beside the
workers, and the pool is what is measured); sgbm pool workers with one OpenCV thread each, each in
its own network namespace joined to the router's by a veth pair (`ip netns`, as root; otherwise on
loopback, and the report says why). The maps are counted per robot on `ballbot/<robot>/disparity`,
where each robot's dispatcher republishes what it checked. The processes and the feeders are
bench/fleet_harness.py; this module measures with them and reports.

Phases, each measured on its own:
  equal   every robot offers twice its share (at least 8 pairs/s): maps/s per robot against total/N and ceiling/N
  alone   the last robot alone, offering half its share: its single-robot latency
  flood   robot 0 offers 4x (its dispatcher may hold 8 items per worker) and frames without grants
          are put on the workers' keys in its name; the middle robots offer twice their share, the
          last robot half of it (within its share): it must get all it offers at no more than
          1.5 x its single-robot latency, and the flood no more than the middle robots' share
  kill    a worker is SIGKILLed: per robot, the time until its rate is back at the new share
  add     a worker joins: the time until it computes its first map, and the shares after

The workers' ceiling is the in-process one-thread sgbm rate on the same pairs, measured in this run
before and after the pool phases, times min(workers, cores). On a machine whose cores also run the
robots' dispatchers, the router and the feeders, the workers cannot reach it whatever the pool does;
so each phase also reports each worker's time on items (its `pool_busy_s` over its own clock): the
share of the phase the pool kept it fed. What a worker idled, the pool lost; what a busy worker did
not turn into maps at the in-process rate, the machine's other processes took.

    ballbot-vision bench fleet            # or: python -m bench.fleet --robots 4 --workers 2
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
import uuid

import numpy as np

from bench.fleet_harness import Fleet, Map, fleet_frames
from bench.measure import percentiles
from common.errors import BallbotError

TARGET_SHARE = 0.9  # every robot >= 0.9 x its fair share; total >= 0.9 x the workers' ceiling
TARGET_RECOVER_S = 1.0  # after a kill: every robot back at its new share within 1 s; a new worker used within 1 s
TARGET_LATENCY_X = 1.5  # a robot's latency within 1.5 x the single-robot figure




def worker_ceiling(method: str, frames: list, seconds: float = 3.0) -> dict:
    """The pool worker's own compute (FrameComputer, the worker's settings, one OpenCV thread) on
    the fleet's frames, in this process: frames/s as frames / wall time."""
    import cv2

    from services.disparity.computer import FrameComputer
    from services.disparity.main import DisparitySettings

    computer = FrameComputer(DisparitySettings(method=method, threads=1), 1.0, "raw")
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        computer.compute(frames[0], "bench")  # the first call allocates
        n, t0, cpu0 = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < seconds or n < 3:
            computer.compute(frames[n % len(frames)], "bench")
            n += 1
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    finally:
        cv2.setNumThreads(before)
    return {"fps": n / wall, "ms": wall * 1e3 / n, "cpu_ms": cpu * 1e3 / n}



def summary(maps: list[Map], robots: list[str], seconds: float) -> dict:
    per = {}
    for r in robots:
        mine = [m for m in maps if m.robot == r]
        per[r] = {"maps": len(mine), "hz": len(mine) / seconds, "latency_ms": percentiles([m.latency_ms for m in mine]),
                  "workers": sorted({m.worker for m in mine})}
    return {"seconds": seconds, "total_hz": len(maps) / seconds, "robots": per}


def cpu_of(fleet: Fleet) -> dict[str, float]:
    from bench.measure import cpu_seconds

    out = {name: cpu_seconds(p.pid) for name, p in fleet.procs.items() if p.poll() is None}
    out["bench"] = time.process_time()  # the feeder
    return out


def measure(fleet: Fleet, rates: dict[str, float], warmup: float, seconds: float) -> dict:
    fleet.rates.update(rates)
    time.sleep(warmup)  # a benchmark's fixed warm-up, not a test synchronisation
    cpu0, t0 = cpu_of(fleet), time.monotonic()
    time.sleep(seconds)
    t1, cpu1 = time.monotonic(), cpu_of(fleet)
    out = summary(fleet.between(t0, t1), list(rates), t1 - t0)
    maps = max(1, sum(v["maps"] for v in out["robots"].values()))
    cpu = {k: (cpu1[k] - cpu0.get(k, 0.0)) * 1e3 / maps for k in cpu1}
    out["cpu_ms_per_map"] = {"workers": sum(v for k, v in cpu.items() if k.startswith("worker")),
                             "dispatchers": sum(v for k, v in cpu.items() if k.startswith("dispatch")),
                             "router": cpu.get("router", 0.0), "feeder": cpu.get("bench", 0.0)}
    with fleet.lock:
        proc = [v for t, v in fleet.proc_ms if t0 <= t <= t1 + 1.0]
        busy = {w: [(up, b) for t, up, b in samples if t0 <= t <= t1] for w, samples in fleet.busy.items()}
    out["worker_proc_ms_p50"] = float(np.median(proc)) if proc else float("nan")
    # per worker, the share of the window (its own clock, between its first and last stats in it) it
    # had an item: what it idled, the pool did not feed it; what a busy worker does not turn into
    # maps at the in-process rate, the machine's other processes took
    out["workers_busy"] = {w: (v[-1][1] - v[0][1]) / (v[-1][0] - v[0][0]) for w, v in busy.items()
                           if len(v) >= 2 and v[-1][0] - v[0][0] >= 0.5 * seconds}
    return out


def back_at_share(maps: list[Map], robot: str, t_event: float, share_hz: float, until: float,
                  window: float = 2.0, step: float = 0.05, settled_from: float | None = None) -> float | None:
    """Seconds from t_event until robot's maps/s over the next `window` s reach 0.9 x its new share
    (the first such moment, on a grid of `step`); None if never before `until`. The new share is
    share_hz, or the robot's own rate from settled_from on if that is lower: how long the event
    cost it, apart from how evenly the rest of the run happens to divide (reported separately)."""
    ts = np.array(sorted(m.t for m in maps if m.robot == robot and m.t >= t_event))
    if settled_from is not None and until > settled_from:
        share_hz = min(share_hz, np.count_nonzero(ts >= settled_from) / (until - settled_from))
    t = t_event
    while t + window <= until:
        n = np.count_nonzero((ts >= t) & (ts < t + window))
        if n / window >= TARGET_SHARE * share_hz:
            return t - t_event
        t += step
    return None


def run(args: argparse.Namespace, say) -> dict:
    robots = [f"r{i}{uuid.uuid4().hex[:3]}" for i in range(args.robots)]
    cores = os.cpu_count() or 1
    frames = fleet_frames()
    say("in-process one-thread ceiling (the worker's own compute) ...")
    ceilings = [worker_ceiling(args.method, frames)]
    workers = [f"w{i}" for i in range(args.workers)]
    report: dict = {"method": args.method, "image": "640x480", "cores": cores, "robots": robots, "workers": workers,
                    "load_avg_1min_start": os.getloadavg()[0]}
    greedy = robots[0]
    with Fleet(robots, args.method, not args.no_netns, {greedy: 8}, logdir=args.logdir) as fleet:
        report["netns"] = fleet.use_netns
        report["netns_reason"] = fleet.netns_reason
        where = "their own network namespaces" if fleet.use_netns else f"this namespace: {fleet.netns_reason}"
        say(f"workers in {where}")
        for w in workers:
            fleet.add_worker(w)
        one = ceilings[0]["fps"]
        ceiling_now = min(len(workers), cores) * one
        # each robot wants twice its share (at least 8/s: the load of a shared machine can fall later)
        offer = max(8.0, 2.0 * ceiling_now / len(robots))
        report["offered"] = {}
        fleet.rates.update({r: offer for r in robots})
        fleet.wait(lambda: {m.robot for m in fleet.between(0, 1e18)} >= set(robots)
                   and {m.worker.split("@")[0] for m in fleet.between(0, 1e18)} >= set(workers), 180,
                   "every robot to get maps from every worker")
        say(f"equal: {len(robots)} robots, each offered {offer:.1f}/s ...")
        report["offered_hz"] = offer
        report["offered"]["equal"] = {r: offer for r in robots}
        report["equal"] = measure(fleet, report["offered"]["equal"], 3.0, args.seconds)
        say(f"alone, saturating: {robots[1]} offers {2 * ceiling_now:.1f}/s, the others nothing ...")
        report["alone_full"] = measure(fleet, {**{r: 0.0 for r in robots}, robots[1]: 2 * ceiling_now}, 3.0,
                                       args.seconds)
        report["alone_full"]["robots"] = {robots[1]: report["alone_full"]["robots"][robots[1]]}
        light = robots[-1]
        light_hz = 0.5 * report["equal"]["total_hz"] / len(robots)  # within its share
        report["light_hz"] = light_hz
        say(f"alone: {light} offers {light_hz:.2f}/s, the others nothing ...")
        quiet = {r: 0.0 for r in robots}
        report["alone"] = measure(fleet, {**quiet, light: light_hz}, 3.0, args.seconds)
        report["alone"]["robots"] = {light: report["alone"]["robots"][light]}
        say(f"flood: {greedy} offers {4 * offer:.1f}/s and puts frames without grants; {light} {light_hz:.2f}/s ...")
        flood = threading.Thread(target=fleet.flood_unsolicited, args=(greedy, workers, 2.0, args.seconds + 3.0),
                                 daemon=True)
        flood.start()
        report["offered"]["flood"] = {**{r: offer for r in robots}, greedy: 4 * offer, light: light_hz}
        report["flood"] = measure(fleet, report["offered"]["flood"], 3.0, args.seconds)
        flood.join()
        fleet.rates.update({r: offer for r in robots})
        say(f"kill: SIGKILL {workers[0]} ...")
        time.sleep(3.0)
        t_before = time.monotonic()
        t_kill = fleet.kill_worker(workers[0])
        time.sleep(args.seconds)
        t_end = time.monotonic()
        maps = fleet.between(t_before - 3.0, t_end)
        after = [m for m in maps if m.t >= t_kill + 2.0]
        new_share = len(after) / max(1e-3, t_end - t_kill - 2.0) / len(robots)
        gone = fleet.token_time(workers[0], False, t_kill)
        report["kill"] = {"token_gone_s": None if gone is None else gone - t_kill, "new_share_hz": new_share,
                          "new_share_from_ceiling_hz": min(len(workers) - 1, cores) * one / len(robots),
                          "after": summary(after, robots, t_end - t_kill - 2.0),
                          "back_at_share_s": {r: back_at_share(maps, r, t_kill, new_share, t_end,
                                                               settled_from=t_kill + 2.0) for r in robots},
                          "longest_gap_s": {r: _gap([m.t for m in maps if m.robot == r], t_kill, t_end)
                                            for r in robots}}
        say(f"add: a new worker {workers[0]}b ...")
        t_start = time.monotonic()
        fleet.add_worker(workers[0] + "b")
        t_up = fleet.wait(lambda: fleet.token_time(workers[0] + "b", True, t_start) is not None, 120,
                          "the new worker's token")
        t_token = fleet.token_time(workers[0] + "b", True, t_start)
        if t_token is None:  # (the wait above saw it)
            raise BallbotError(f"fleet bench: the token of {workers[0]}b came and went")
        fleet.wait(lambda: any(m.worker.startswith(workers[0] + "b@") for m in fleet.between(t_token, 1e18)), 60,
                   "the new worker's first map")
        first = min(m.t for m in fleet.between(t_token, 1e18) if m.worker.startswith(workers[0] + "b@"))
        time.sleep(args.seconds)
        t_end = time.monotonic()
        maps = fleet.between(t_token, t_end)
        settled = [m for m in maps if m.t >= t_token + 2.0]
        share2 = len(settled) / max(1e-3, t_end - t_token - 2.0) / len(robots)
        report["add"] = {"process_to_token_s": t_up - t_start, "token_to_first_map_s": first - t_token,
                         "share_hz": share2, "after": summary(settled, robots, t_end - t_token - 2.0),
                         "back_at_share_s": {r: back_at_share(maps, r, t_token, share2, t_end,
                                                              settled_from=t_token + 2.0) for r in robots}}
        starved = [r for r in robots if report["add"]["after"]["robots"][r]["maps"] == 0]
        if starved:  # a robot that got nothing: how its dispatcher stood, and its threads in its log
            report["starved"] = {r: {k: v for k, v in fleet.stats.items() if k.startswith(r + "/")} for r in starved}
            for r in starved:
                fleet.procs[f"dispatch-{r}"].send_signal(signal.SIGABRT)
            time.sleep(1.0)
        with fleet.lock:
            report["pool_stats"] = {k: v for k, v in fleet.stats.items() if "/pool-worker/" in k}
            report["dispatcher_stats"] = {k: {x: v["extra"].get(x, 0) for x in (
                "results_unmatched", "pool_grants", "pool_declined", "pool_wants", "results_rejected")}
                for k, v in fleet.stats.items() if "/dispatcher/" in k}
    say("in-process one-thread ceiling again ...")
    ceilings.append(worker_ceiling(args.method, frames))
    one = float(np.mean([c["fps"] for c in ceilings]))
    report["ceiling_one_thread_fps"] = [c["fps"] for c in ceilings]
    report["workers_ceiling_hz"] = min(len(workers), cores) * one
    cpu = report["equal"]["cpu_ms_per_map"]
    work, rest = cpu["workers"], cpu["dispatchers"] + cpu["router"] + cpu["feeder"]
    # what the measured CPU per map allows on this many cores with nothing else running
    report["projected_quiet_hz"] = (min(min(len(workers), cores) * 1e3 / work, cores * 1e3 / (work + rest))
                                    if work > 0 else 0.0)
    # On a pool host of its own only the workers and the router run there (dispatchers and capture are
    # on the robots): the pool's maps/s over the ideal of its workers (each as fast as the matcher
    # in-process), from CPU time per map, which a shared machine's load does not change much.
    inproc_cpu = float(np.mean([c["cpu_ms"] for c in ceilings]))
    n_w = min(len(workers), cores)
    host = min(n_w * 1e3 / work, cores * 1e3 / (work + cpu["router"])) if work > 0 else 0.0
    report["pool_host_projection"] = {"inprocess_cpu_ms": inproc_cpu, "worker_cpu_ms": work / 1.0,
                                      "router_cpu_ms": cpu["router"], "maps_per_s": host,
                                      "ideal_maps_per_s": n_w * 1e3 / inproc_cpu,
                                      "x_ideal": host / (n_w * 1e3 / inproc_cpu)}
    report["load_avg_1min_end"] = os.getloadavg()[0]
    report["targets"] = targets(report)
    return report


def _gap(ts: list[float], t0: float, t1: float) -> float:
    ts = [t0] + sorted(t for t in ts if t0 <= t <= t1) + [t1]
    return max(b - a for a, b in zip(ts, ts[1:]))


def max_min_fair(total: float, demands: dict[str, float]) -> dict[str, float]:
    """What each robot is entitled to of `total` maps/s when robot i asks for demands[i]: max-min
    fairness (water filling): a robot asking less than an equal split gets what it asks, the
    others split the rest equally. A robot that is sent all it asks for loses nothing to a flood."""
    left, out = total, {}
    pending = sorted(demands.items(), key=lambda kv: kv[1])
    while pending:
        even = left / len(pending)
        robot, want = pending[0]
        if want <= even:
            out[robot] = want
            left -= want
            pending.pop(0)
        else:
            for robot, _ in pending:
                out[robot] = even
            break
    return out


def entitled(phase: dict, offered: dict[str, float]) -> dict[str, float]:
    return max_min_fair(phase["total_hz"], {r: offered[r] for r in phase["robots"]})


def targets(r: dict) -> list[tuple[str, float, str, float, bool]]:
    n = len(r["robots"])
    eq = r["equal"]
    ph = r["pool_host_projection"]
    fed = min(eq["workers_busy"].values()) if eq.get("workers_busy") else float("nan")
    out = [("total / workers' ceiling", eq["total_hz"] / r["workers_ceiling_hz"], ">=", TARGET_SHARE,
            eq["total_hz"] / r["workers_ceiling_hz"] >= TARGET_SHARE),
           ("  equal: the least busy worker's share of the time on items (the pool kept it fed)", fed, ">=",
            TARGET_SHARE, fed >= TARGET_SHARE),
           ("  a pool host of its own, from CPU per map: x ideal", ph["x_ideal"], ">=", TARGET_SHARE,
            ph["x_ideal"] >= TARGET_SHARE)]
    worst = min(v["hz"] for v in eq["robots"].values())
    ent = entitled(eq, r["offered"]["equal"])
    x = min(eq["robots"][k]["hz"] / ent[k] for k in ent)
    out.append(("equal: worst robot / its max-min fair share", x, ">=", TARGET_SHARE, x >= TARGET_SHARE))
    ceil_share = r["workers_ceiling_hz"] / n
    out.append(("equal: worst robot / ceiling share (ceiling/N)", worst / ceil_share, ">=", TARGET_SHARE,
                worst / ceil_share >= TARGET_SHARE))
    fl = r["flood"]
    greedy, light = r["robots"][0], r["robots"][-1]
    got = fl["robots"][light]["hz"] / r["light_hz"]
    out.append(("flood: light robot's maps/s / what it offered", got, ">=", TARGET_SHARE, got >= TARGET_SHARE))
    alone = r["alone"]["robots"][light]["latency_ms"]["p50"]
    lat = fl["robots"][light]["latency_ms"]["p50"] / alone
    out.append(("flood: light robot's latency p50 / alone", lat, "<=", TARGET_LATENCY_X, lat <= TARGET_LATENCY_X))
    # the same in units of the workers' compute time per map in each phase: on a shared 2-core machine
    # a map takes longer while both workers compute than while one does
    norm = (fl["robots"][light]["latency_ms"]["p50"] / fl["worker_proc_ms_p50"]) / \
        (alone / r["alone"]["worker_proc_ms_p50"])
    out.append(("  same, each over its phase's compute time per map", norm, "<=", TARGET_LATENCY_X,
                norm <= TARGET_LATENCY_X))
    # max-min fair: a robot asking less than an equal split gets what it asks, the others split the rest
    ent = entitled(fl, r["offered"]["flood"])
    g = fl["robots"][greedy]["hz"] / ent[greedy]
    out.append(("flood: flooding robot / its max-min fair share", g, "<=", 1.1, g <= 1.1))
    others = min(fl["robots"][k]["hz"] / ent[k] for k in ent if k != greedy)
    out.append(("flood: worst other robot / its max-min fair share", others, ">=", TARGET_SHARE,
                others >= TARGET_SHARE))
    backs = [v for v in r["kill"]["back_at_share_s"].values()]
    worst_back = max((b if b is not None else float("inf")) for b in backs)
    out.append(("kill: slowest robot back at its new share (s)", worst_back, "<=", TARGET_RECOVER_S,
                worst_back <= TARGET_RECOVER_S))
    used = r["add"]["token_to_first_map_s"]
    out.append(("add: new worker's token to its first map (s)", used, "<=", TARGET_RECOVER_S,
                used <= TARGET_RECOVER_S))
    return out


def format_report(r: dict) -> str:
    lines = [f"{len(r['robots'])} robots, {len(r['workers'])} {r['method']} pool workers (1 OpenCV thread each), "
             f"{r['image']}, {r['cores']} cores; workers "
             + ("each in its own network namespace" if r["netns"] else f"on loopback ({r['netns_reason']})"),
             "in-process 1-thread ceiling (before / after): "
             + " / ".join(f"{v:.2f}" for v in r["ceiling_one_thread_fps"])
             + f" fps -> workers' ceiling {r['workers_ceiling_hz']:.2f} maps/s; "
             f"load avg {r['load_avg_1min_start']:.1f} at start, {r['load_avg_1min_end']:.1f} at end",
             f"the equal phase's CPU per map allows {r['projected_quiet_hz']:.2f} maps/s on {r['cores']} "
             f"otherwise idle cores; a pool host of its own "
             f"(workers {r['pool_host_projection']['worker_cpu_ms']:.1f} + router "
             f"{r['pool_host_projection']['router_cpu_ms']:.1f} ms CPU per map, the matcher in-process "
             f"{r['pool_host_projection']['inprocess_cpu_ms']:.1f} ms): {r['pool_host_projection']['maps_per_s']:.1f} "
             f"maps/s = {r['pool_host_projection']['x_ideal']:.2f} x its workers' ideal",
             f"each robot offered {r['offered_hz']:.1f} pairs/s (flood: robot 0 x4, max_in_flight 8, plus "
             f"unsolicited frames; the last robot {r['light_hz']:.2f}/s, half its share)"]

    def block(name: str, s: dict) -> None:
        n = len(s["robots"])
        lines.append(f"{name}: total {s['total_hz']:.2f} maps/s over {s['seconds']:.1f} s"
                     + (f", fair share {s['total_hz'] / n:.2f}" if n > 1 else "")
                     + (f"; a worker's compute p50 {s['worker_proc_ms_p50']:.0f} ms per map"
                        if "worker_proc_ms_p50" in s else ""))
        if "cpu_ms_per_map" in s:
            lines.append("    CPU per map: " + ", ".join(f"{k} {v:.1f} ms" for k, v in s["cpu_ms_per_map"].items()))
        if s.get("workers_busy"):
            busy = sorted(s["workers_busy"].items())
            lines.append("    time on items: " + ", ".join(f"{w} {v:.0%}" for w, v in busy))
        for robot, v in s["robots"].items():
            lat = v["latency_ms"]
            lines.append(f"    {robot}: {v['hz']:5.2f} maps/s"
                         + (f" = {v['hz'] / (s['total_hz'] / n):.2f} x share" if n > 1 and s["total_hz"] else "")
                         + f", latency p50 {lat['p50']:.0f} ms p95 {lat['p95']:.0f} ms, from {', '.join(v['workers'])}")

    block("equal", r["equal"])
    block("alone, saturating", r["alone_full"])
    block("alone", r["alone"])
    block("flood", r["flood"])
    k = r["kill"]
    lines.append(f"kill: token gone after {k['token_gone_s'] * 1e3:.0f} ms; new share {k['new_share_hz']:.2f} maps/s "
                 f"(ceiling/N {k['new_share_from_ceiling_hz']:.2f})" if k["token_gone_s"] is not None else "kill: ?")
    for robot in r["robots"]:
        b = k["back_at_share_s"][robot]
        lines.append(f"    {robot}: back at 0.9 x new share after "
                     + (f"{b:.2f} s" if b is not None else "never")
                     + f", longest gap {k['longest_gap_s'][robot]:.2f} s")
    block("  after the kill", k["after"])
    a = r["add"]
    lines.append(f"add: process start to token {a['process_to_token_s']:.1f} s; token to its first map "
                 f"{a['token_to_first_map_s'] * 1e3:.0f} ms; share after {a['share_hz']:.2f} maps/s")
    for robot in r["robots"]:
        b = a["back_at_share_s"][robot]
        lines.append(f"    {robot}: at 0.9 x the new share after " + (f"{b:.2f} s" if b is not None else "never"))
    block("  after the add", a["after"])
    for robot, st in r.get("starved", {}).items():
        lines.append(f"STARVED after the add: {robot}: " + "; ".join(f"{k}: {v['status']}" for k, v in st.items()))
    lines.append("targets:")
    for label, value, op, target, ok in r["targets"]:
        lines.append(f"  {label:52} {value:6.2f}   target {op} {target:.2f}   {'met' if ok else 'MISSED'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, default=4)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--method", default="sgbm", choices=["bm", "sgbm"])
    p.add_argument("--seconds", type=float, default=15.0, help="measured seconds per phase")
    p.add_argument("--no-netns", action="store_true", help="workers on loopback, not in network namespaces")
    p.add_argument("--logdir", default=None, help="each process's log here")
    p.add_argument("--json", action="store_true")
    p.add_argument("--save", default=None, metavar="FILE", help="also write the JSON report here")
    a = p.parse_args(argv)
    if a.robots < 2 or a.workers < 1:
        p.error("--robots >= 2 and --workers >= 1")
    say = (lambda text: None) if a.json else (lambda text: print(text, file=sys.stderr, flush=True))
    # SIGTERM unwinds like Ctrl-C, so the fleet's processes are stopped and its namespaces deleted
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    r = run(a, say)
    if a.save:
        with open(a.save, "w") as f:
            json.dump(r, f, indent=2, default=str)
    print(json.dumps(r, indent=2, default=str) if a.json else format_report(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
