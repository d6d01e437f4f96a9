"""`ballbot-vision bench transport`: what moving one 640x480 pair between two processes costs, and
what each copy on the way costs.

1. Copies, in this process: every step a frame takes from a numpy array in one service to a numpy
   array in the next (image_from_array, codec.encode, the copy out of Zenoh, msgpack, pydantic,
   array_from_image), CPU per pair.
2. One hop: a publisher and a subscriber process (through a router, as `up` runs them) pass
   rectified-pair-sized StereoFrame payloads at a camera-like rate; CPU per message on each side
   (all threads, Zenoh's included), with Zenoh's shared memory on (the default) and off (what a
   peer on another host costs at both ends, minus the wire).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np

from bench.measure import free_port

KEY = "bench/transport/frames"


def _frame_payload() -> tuple[bytes, np.ndarray, np.ndarray]:
    from common import codec
    from common.messages import StereoFrame
    from cores import camera
    from cores.calibration.rectify import camera_model_message

    rng = np.random.default_rng(1)
    left = rng.integers(0, 256, (480, 640), np.uint8)
    right = rng.integers(0, 256, (480, 640), np.uint8)
    model = camera_model_message(camera.rectify_rig(camera.load_raw_rig("lifecam-studio"), 0.0).model)
    msg = StereoFrame(robot_id="bench", seq=1, stamp_ns=time.time_ns(), left=codec.image_from_array(left),
                      right=codec.image_from_array(right), camera=model, source="synthetic")
    return codec.encode(msg), left, right


def copies(rounds: int = 5, n: int = 200) -> dict[str, float]:
    """CPU us per pair of each step of the frame path, median over rounds."""
    import msgpack

    from common import codec
    from common.messages import StereoFrame

    payload, left, right = _frame_payload()
    msg = codec.decode(payload, StereoFrame)
    doc = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    zb = None
    try:
        import zenoh

        zb = zenoh.ZBytes(payload)
    except ImportError:
        pass
    steps = {
        "image_from_array x2 (ndarray -> bytes)": lambda: (codec.image_from_array(left), codec.image_from_array(right)),
        "codec.encode (msgpack, image bytes copied in)": lambda: codec.encode(msg),
        "ZBytes.to_bytes (the copy out of Zenoh)": (lambda: zb.to_bytes()) if zb is not None else None,
        "msgpack.unpackb (image bytes copied out)": lambda: msgpack.unpackb(payload, raw=False, strict_map_key=False),
        "pydantic model_validate (no copy)": lambda: StereoFrame.model_validate(doc),
        "array_from_image x2 (a view, no copy)": lambda: (codec.array_from_image(msg.left),
                                                          codec.array_from_image(msg.right)),
        "memcpy of a pair (numpy copy, for scale)": lambda: (left.copy(), right.copy()),
    }
    out: dict[str, list[float]] = {k: [] for k, f in steps.items() if f is not None}
    for _ in range(rounds):
        for k, f in steps.items():
            if f is None:
                continue
            f()
            c0 = time.process_time()
            for _ in range(n):
                f()
            out[k].append((time.process_time() - c0) * 1e6 / n)
    return {k: float(np.median(v)) for k, v in out.items()}


def _session(endpoint: str, shm: bool, router: bool = False):
    from common.zenoh_session import ZenohOptions, open_session

    if router:
        return open_session(ZenohOptions(mode="router", connect=[], listen=[endpoint], shared_memory=shm))
    return open_session(ZenohOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"], shared_memory=shm))


def _role(args: argparse.Namespace) -> int:
    """One side of a hop, in its own process; prints one JSON line."""
    import zenoh

    shm = args.shm != "off"
    if args.role == "router":
        with _session(args.endpoint, shm, router=True):
            threading.Event().wait()
        return 0
    with _session(args.endpoint, shm) as s:
        if args.role == "sub":
            from common.inbox import Inbox
            from common.keys import topic

            inbox = Inbox(topic("frames_rect"), max_bytes=64 << 20)
            done = threading.Event()

            def on_sample(sample) -> None:
                inbox.offer_sample(sample)
                if inbox.received >= args.count + args.warmup:
                    done.set()

            s.declare_subscriber(KEY, on_sample)
            print(json.dumps({"ready": True}), flush=True)
            while inbox.received < args.warmup and not done.is_set():
                time.sleep(0.01)
            c0, n0 = time.process_time(), inbox.received
            done.wait(120)
            n = max(1, inbox.received - n0)
            print(json.dumps({"cpu_us": (time.process_time() - c0) * 1e6 / n, "received": inbox.received,
                              "shm": inbox.shm}), flush=True)
            return 0
        payload, _, _ = _frame_payload()
        pub = s.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        provider = None
        if args.shm == "explicit":
            import zenoh.shm as zshm

            provider = zshm.ShmProvider.default_backend(32 << 20)
            policy = zshm.BlockOn(zshm.GarbageCollect())
        time.sleep(1.0)  # discovery: the subscriber's interest reaches this peer
        period = 1.0 / args.rate
        c0 = time.process_time()  # (taken again when the warm-up ends)
        for i in range(args.count + args.warmup + 5):
            if i == args.warmup:
                c0 = time.process_time()
            if provider is not None:
                buf = provider.alloc(len(payload), policy)
                buf[:] = payload
                pub.put(zenoh.ZBytes(buf))
            else:
                pub.put(payload)
            time.sleep(period)
        print(json.dumps({"cpu_us": (time.process_time() - c0) * 1e6 / (args.count + 5)}), flush=True)
        time.sleep(0.5)
    return 0


def hop(shm: bool, rate: float = 60.0, count: int = 300, warmup: int = 30) -> dict:
    """CPU us per message of a publisher and a subscriber process, through a router."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    base = [sys.executable, "-m", "bench.transport", "--endpoint", endpoint, "--shm", "on" if shm else "off",
            "--rate", str(rate), "--count", str(count), "--warmup", str(warmup)]
    env = dict(os.environ, BALLBOT_LOG="WARNING")
    router = subprocess.Popen(base + ["--role", "router"], env=env, stdout=subprocess.DEVNULL)
    try:
        from common.supervisor import wait_for_tcp

        wait_for_tcp(endpoint, 15.0, threading.Event())
        sub = subprocess.Popen(base + ["--role", "sub"], env=env, stdout=subprocess.PIPE, text=True)
        assert sub.stdout is not None  # (stdout=PIPE)
        sub.stdout.readline()  # ready
        pub = subprocess.run(base + ["--role", "pub"], env=env, capture_output=True, text=True, timeout=300)
        got = json.loads(sub.communicate(timeout=120)[0].strip().splitlines()[-1])
        sent = json.loads(pub.stdout.strip().splitlines()[-1])
    finally:
        router.terminate()
        router.wait(10)
    return {"shm": shm, "publisher_cpu_us": sent["cpu_us"], "subscriber_cpu_us": got["cpu_us"],
            "received": got["received"], "via_shared_memory": got["shm"] / max(1, got["received"])}


def bench_transport(repeat: int = 3) -> dict:
    out: dict[str, Any] = {"load_avg_1min": os.getloadavg()[0], "copies_us": copies(), "hops": []}
    for _ in range(repeat):  # interleaved: a load change moves both alike
        out["hops"] += [hop(True), hop(False)]
    out["load_avg_1min_end"] = os.getloadavg()[0]
    return out


def format_transport(r: dict) -> str:
    lines = [f"the frame path, CPU per 640x480 pair "
             f"(load avg {r['load_avg_1min']:.1f} -> {r['load_avg_1min_end']:.1f}):"]
    lines += [f"  {k:48} {v:7.1f} us" for k, v in r["copies_us"].items()]
    lines.append("one hop between two processes (60 pairs/s, through a router), CPU per message, median of runs:")
    for shm in (True, False):
        runs = [h for h in r["hops"] if h["shm"] == shm]
        pub = float(np.median([h["publisher_cpu_us"] for h in runs]))
        sub = float(np.median([h["subscriber_cpu_us"] for h in runs]))
        via = float(np.median([h["via_shared_memory"] for h in runs]))
        lines.append(f"  shared memory {'on ' if shm else 'off'}: publisher {pub:6.0f} us, subscriber {sub:6.0f} us "
                     f"({via:.0%} of payloads arrived through shared memory)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="ballbot-vision bench transport")
    p.add_argument("--json", action="store_true")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--role", choices=["router", "pub", "sub"], help=argparse.SUPPRESS)
    p.add_argument("--endpoint", help=argparse.SUPPRESS)
    p.add_argument("--shm", choices=["on", "off", "explicit"], default="on", help=argparse.SUPPRESS)
    p.add_argument("--rate", type=float, default=60.0, help=argparse.SUPPRESS)
    p.add_argument("--count", type=int, default=300, help=argparse.SUPPRESS)
    p.add_argument("--warmup", type=int, default=30, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.role:
        return _role(args)
    r = bench_transport(max(1, args.repeat))
    print(json.dumps(r, indent=2) if args.json else format_transport(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
