"""What checking a worker's map costs the robot (issue 25): a worker's map reaches the segmenter
only through the dispatcher, which checks it against the work item, republishes it with the
frame's stamp and signs it; the segmenter checks the signature.

    ballbot-vision bench trust            # or: python -m bench.trust [--seconds 10] [--json]

1. In-process, per 640x480 map of the synthetic scene (raw int16, and png uint16 from a worker with
   result_encoding png), the median of many repetitions of each step the robot adds: the header
   check (before the payload is copied), the message decode, the map check (pixels decoded and
   measured), the republished message's encoding, its HMAC-SHA256, and the segmenter's check of it.
2. Live: router, capture (15 Hz), rectify, the dispatcher (no fallback) and one bm worker as
   processes; a subscriber on the worker's result key and on `disparity` times the hop per seq
   (arrival of the republished map minus arrival of the worker's), and /proc gives the dispatcher's
   CPU per map (everything it does: frames out, maps in, checks, republishing).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import threading
import time
from typing import Any


def _median_ms(fn, n: int) -> float:
    fn()
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def in_process(n: int = 200) -> dict:
    from bench.scaling import rectified_frames
    from common import codec, signed_payload
    from common.inbox import _META
    from common.keys import topic
    from common.messages import DisparityMap
    from cores.matching.config import MatcherConfig
    from services.disparity.computer import FrameComputer
    from services.disparity.results import Ticket, parse_header, result_header, vet_header, vet_map

    # as rectify publishes it, with its checks: the map is checked against the frame's near field
    frame = rectified_frames(1)[0].model_copy(update={"seq": 1, "stamp_ns": time.time_ns()})
    ticket = Ticket.for_frame(frame)
    key = os.urandom(32)
    key_expr = topic("disparity").key("bench")
    def steps_for(enc: str) -> dict:
        result = FrameComputer(MatcherConfig(method="bm"), 1.0, enc).compute(frame, "w")
        payload = codec.encode(result)
        raw_header = result_header(result, ticket.nonce)
        header = parse_header(raw_header)
        msg = codec.decode(payload, DisparityMap)
        republished = codec.encode(msg.model_copy(update={"worker": "w", "stages": dict(ticket.stages)}))
        meta = _META.pack(msg.stamp_ns, 1, 1)
        attachment = signed_payload.seal(key, key_expr, meta, republished)
        steps = {
            "header_check": _median_ms(lambda: vet_header(parse_header(raw_header), ticket, len(payload)), n),
            "decode": _median_ms(lambda: codec.decode(payload, DisparityMap), n),
            "map_check": _median_ms(lambda: vet_map(msg, header, ticket), n),
            "republish_encode": _median_ms(lambda: codec.encode(msg.model_copy(
                update={"worker": "w", "stages": dict(ticket.stages)})), n),
            "hmac_sign": _median_ms(lambda: signed_payload.seal(key, key_expr, meta, republished), n),
            "segmenter_hmac_check": _median_ms(lambda: signed_payload.check(key, key_expr, attachment, republished,
                                                                            _META.size), n),
        }
        steps["dispatcher_total"] = sum(v for k, v in steps.items() if k != "segmenter_hmac_check")
        return {"payload_bytes": len(payload), "ms": {k: round(v, 3) for k, v in steps.items()}}

    return {enc: steps_for(enc) for enc in ("raw", "png")}


def live(seconds: float = 10.0, rate: float = 15.0) -> dict:
    from bench.measure import cpu_seconds, free_port, percentiles
    from common.keys import topic
    from common.supervisor import Supervisor
    from common.zenoh_session import ZenohOptions, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rid = f"trust{os.getpid()}"
    c = ["--connect", endpoint, "--robot-id", rid]
    env = dict(os.environ, BALLBOT_CALIBRATION_KEY=os.urandom(32).hex())
    sup = Supervisor(env=env)
    sup.add("router", ["run", "router", "--listen", endpoint, "--robot-id", rid])
    sup.add("capture", ["run", "capture", *c, "--preload", "8", "--rate-hz", f"{rate:g}"])
    sup.add("rectify", ["run", "rectify", *c])
    sup.add("dispatch", ["run", "disparity", *c, "--fallback", "none"])
    sup.add("worker", ["run", "disparity", *c, "--role", "worker", "--instance", "w0"])
    arrived: dict[str, dict[int, int]] = {"result": {}, "disparity": {}}
    lock = threading.Lock()
    measuring = threading.Event()

    def on(kind: str):
        import msgpack

        def cb(sample) -> None:
            t = time.monotonic_ns()
            if measuring.is_set():
                seq = msgpack.unpackb(sample.payload.to_bytes())["seq"]
                with lock:
                    arrived[kind][seq] = t
        return cb

    try:
        sup.start_all(endpoint)
        with open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"])) as session:
            session.declare_subscriber(topic("work_result").pattern(rid), on("result"))
            session.declare_subscriber(topic("disparity").key(rid), on("disparity"))
            time.sleep(8.0)  # a benchmark's fixed warm-up (start-up, the worker's probation), not a synchronisation
            pid = next(ch.proc.pid for ch in sup.children if ch.name == "dispatch" and ch.proc is not None)
            cpu0 = cpu_seconds(pid)
            measuring.set()
            time.sleep(seconds)
            measuring.clear()
            cpu1 = cpu_seconds(pid)
    finally:
        sup.stop_all()
    hops = [(arrived["disparity"][s] - t) / 1e6 for s, t in arrived["result"].items() if s in arrived["disparity"]]
    maps = len(arrived["disparity"])
    return {"seconds": seconds, "offered_hz": rate, "worker_maps": len(arrived["result"]), "republished": maps,
            "hop_ms": percentiles(hops), "dispatcher_cpu_ms_per_map": (cpu1 - cpu0) * 1e3 / max(1, maps),
            "load_avg_1min": os.getloadavg()[0]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="ballbot-vision bench trust", description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--repeat", type=int, default=200, help="repetitions per in-process step")
    p.add_argument("--no-live", action="store_true", help="only the in-process steps")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    report: dict[str, Any] = {"in_process": in_process(a.repeat), "cores": os.cpu_count()}
    if not a.no_live:
        report["live"] = live(a.seconds)
    if a.json:
        print(json.dumps(report, indent=2))
        return 0
    for enc, r in report["in_process"].items():
        print(f"{enc} map ({r['payload_bytes'] / 1e3:.0f} kB), ms per map: "
              + ", ".join(f"{k} {v:.3f}" for k, v in r["ms"].items()))
    if "live" in report:
        lv = report["live"]
        h = lv["hop_ms"]
        print(f"live at {lv['offered_hz']:g} Hz, {lv['seconds']:g} s: {lv['worker_maps']} worker maps, "
              f"{lv['republished']} republished; hop (worker's map -> republished map) p50 {h['p50']:.2f} ms, "
              f"p95 {h['p95']:.2f} ms; "
              f"dispatcher CPU {lv['dispatcher_cpu_ms_per_map']:.2f} ms per map (all it does); load avg "
              f"{lv['load_avg_1min']:.1f} on {report['cores']} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
