"""`ballbot-vision bench record`: can `record` keep up with 640x480 pairs at 30 fps?

This process publishes what a running pipeline publishes per pair (raw and rectified frames as
raw pixels, the disparity map, the obstacle list, the synthetic truth; pre-computed by the real
cores, so the pipeline's own compute does not compete), at the offered rate, to a Zenoh router;
`ballbot-vision record` runs as its own process and is stopped with SIGINT like a user's Ctrl-C.
Then the file is read back: pairs published vs. pairs in the file, seq gaps, queue drops, the
recorder's CPU per pair. The reference, measured in the same run: the recorder's own conversion
(decode, JPEG/PNG, JSON, MCAP) of the same messages in this process on one thread, in CPU time,
i.e. the pairs per second one whole core allows; `headroom` = that ceiling / the offered rate.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any


def _pipeline_messages(n: int):
    """n consecutive pairs as the pipeline publishes them: (raw, rectified, disparity, obstacles, truth)."""
    from common import codec
    from common.messages import StereoFrame
    from cores import camera
    from cores.calibration.rectify import Rectifier
    from cores.matching.config import MatcherConfig
    from cores.segmentation.builder import ObstacleBuilder
    from cores.segmentation.settings import SegmenterSettings
    from services.capture.main import truth_message
    from services.capture.sources import SyntheticSource
    from services.disparity.computer import FrameComputer

    src = SyntheticSource("person-walking", "lifecam-studio", 30.0)
    rect = Rectifier(camera.load_calibration("lifecam-studio"))
    computer = FrameComputer(MatcherConfig())  # the map as the disparity service publishes it
    builder = ObstacleBuilder(SegmenterSettings())
    out = []
    for k in range(n):
        pair = src.read()
        stamp = 10**18 + k * 33_333_333
        raw = StereoFrame(robot_id="bench", seq=k, stamp_ns=stamp, left=codec.image_from_array(pair.left),
                          right=codec.image_from_array(pair.right), source="synthetic")
        l, r = rect.rectify(pair.left, pair.right)
        rectified = StereoFrame(robot_id="bench", seq=k, stamp_ns=stamp, left=codec.image_from_array(l),
                                right=codec.image_from_array(r), camera=rect.model_message)
        d = computer.compute(rectified, "bench")
        obstacles = builder.process_message(d).obstacles
        truth = truth_message("bench", k, stamp, "person-walking", pair.truth or [])
        out.append((raw, rectified, d, obstacles, truth))
    return out


def conversion_ceiling(messages, image_format: str, seconds: float = 3.0) -> float:
    """Pairs per CPU-second of the recorder's conversion and writing, on one thread in this process."""
    from common import codec
    from common.messages import DisparityMap, GroundTruth, ObstacleList, StereoFrame
    from cores.recording import Converter, RecordingWriter, RecordOptions

    payloads = [tuple(codec.encode(m) for m in msgs) for msgs in messages]
    # raw and rectified pairs at quality 90: the heaviest recording, as this benchmark measured it before
    conv = Converter(RecordOptions(image_format=image_format, raw=True, jpeg_quality=90))
    with tempfile.TemporaryDirectory() as tmp:
        sink = RecordingWriter(Path(tmp) / "ceiling.mcap")
        # CPU time, not wall time: what one core allows, whatever else the machine runs
        n, t0 = 0, time.process_time()
        while time.process_time() - t0 < seconds or n < 5:
            raw, rect, d, obs, truth = payloads[n % len(payloads)]
            records = (conv.frame(codec.decode(raw, StereoFrame)) + conv.frame(codec.decode(rect, StereoFrame))
                       + conv.disparity(codec.decode(d, DisparityMap)) + conv.obstacles(codec.decode(obs, ObstacleList))
                       + conv.truth(codec.decode(truth, GroundTruth)))
            for r in records:
                sink.write(r.topic, r.doc, r.log_time_ns, r.sequence)
            n += 1
        took = time.process_time() - t0
        sink.close()
    return n / took


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def record_run(messages, rate: float, seconds: float, image_format: str, threads: int) -> dict:
    import zenoh

    from bench.measure import free_port
    from common import codec
    from common.inbox import _STAMP
    from common.keys import topic
    from common.messages import ServiceStats
    from common.zenoh_session import ZenohOptions, open_session

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cli = [sys.executable, "-m", "ballbot_vision.cli"]
    router = subprocess.Popen(cli + ["run", "router", "--listen", endpoint, "--robot-id", "bench"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    tmp = tempfile.TemporaryDirectory()
    out = Path(tmp.name) / "bench.mcap"
    log_path = Path(tmp.name) / "record.log"
    recorder = None
    from common.supervisor import wait_for_tcp
    try:
        if not wait_for_tcp(endpoint, 30.0, threading.Event()):
            raise RuntimeError(f"the Zenoh router did not listen on {endpoint}")
        with open_session(ZenohOptions(mode="peer", connect=[endpoint])) as session:
            ready = threading.Event()

            def on_stats(sample) -> None:
                try:
                    st = codec.decode(sample.payload.to_bytes(), ServiceStats)
                except Exception:
                    return
                if st.status == "recording":
                    ready.set()

            session.declare_subscriber(topic("stats").key("bench", service="record", instance="*"), on_stats)
            with open(log_path, "w") as log:
                recorder = subprocess.Popen(cli + ["record", str(out), "--connect", endpoint, "--robot-id", "bench",
                                                   "--image-format", image_format, "--threads", str(threads),
                                                   "--raw", "true", "--jpeg-quality", "90"],
                                            stdout=log, stderr=subprocess.STDOUT)
            if not ready.wait(60):
                raise RuntimeError(f"record did not start: {log_path.read_text()[-2000:]}")
            pubs = {name: session.declare_publisher(topic(name).key("bench"),
                                                    congestion_control=zenoh.CongestionControl.DROP
                                                    if topic(name).image_stream else zenoh.CongestionControl.BLOCK)
                    for name in ("frames_raw", "frames_rect", "disparity", "obstacles", "truth")}
            cpu0, t0 = _cpu_s(recorder.pid), time.monotonic()
            n, late = 0, 0
            period = 1.0 / rate
            while time.monotonic() - t0 < seconds:
                due = t0 + n * period
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)  # the offered rate's clock, not a wait for an event
                elif delay < -period:
                    late += 1
                raw, rect, d, obs, truth = messages[n % len(messages)]
                stamp = time.time_ns()
                for name, msg in zip(("frames_raw", "frames_rect", "disparity", "obstacles", "truth"),
                                     (raw, rect, d, obs, truth)):
                    msg = msg.model_copy(update={"seq": n, "stamp_ns": stamp})
                    pubs[name].put(codec.encode(msg), attachment=_STAMP.pack(stamp))
                n += 1
            sent_s = time.monotonic() - t0
            # the recorder writes as it receives: let the last pairs arrive, then Ctrl-C
            time.sleep(0.5)
            cpu = _cpu_s(recorder.pid) - cpu0
            recorder.send_signal(signal.SIGINT)
            recorder.wait(120)
        from cores.recording import RAW_LEFT
        from cores.recording_reader import RecordingReader

        info = RecordingReader(out).info()
        seqs = []
        from mcap.reader import make_reader

        with open(out, "rb") as f:
            for _, _ch, m in make_reader(f).iter_messages(topics=[RAW_LEFT]):
                seqs.append(m.sequence)
        written = len(set(seqs))
        log_text = log_path.read_text()
        return {"format": image_format, "offered_fps": rate, "seconds": round(sent_s, 2), "published_pairs": n,
                "publisher_late": late, "written_pairs": written, "missing_pairs": n - written,
                "file_complete": info.complete, "file_mb": round(out.stat().st_size / 1e6, 1),
                "mb_per_s": round(out.stat().st_size / 1e6 / sent_s, 1),
                "recorder_cpu_ms_per_pair": round(cpu * 1e3 / max(n, 1), 1),
                "recorder_cpu_cores": round(cpu / sent_s, 2),
                "recorder_summary": next((l for l in log_text.splitlines() if l.startswith("wrote ")), log_text[-500:])}
    finally:
        for p in (recorder, router):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
        tmp.cleanup()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="ballbot-vision bench record", description=__doc__.split("\n\n")[0])
    p.add_argument("--rate", type=float, default=30.0, help="pairs per second offered")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--format", action="append", default=None, choices=["jpeg", "png"],
                   help="image format(s) in the file (default: jpeg, then png)")
    p.add_argument("--threads", type=int, default=2, help="the recorder's encoder threads")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    messages = _pipeline_messages(16)
    result: dict[str, Any] = {"size": "640x480", "cores": os.cpu_count(), "runs": []}
    for fmt in args.format or ["jpeg", "png"]:
        ceiling = conversion_ceiling(messages, fmt)
        run = record_run(messages, args.rate, args.seconds, fmt, args.threads)
        run["ceiling_pairs_per_s_one_thread"] = round(ceiling, 1)
        run["headroom"] = round(ceiling / args.rate, 2)
        result["runs"].append(run)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"record: 640x480 pairs (raw + rectified frames, disparity, obstacles, truth) offered at {args.rate:g} fps "
          f"for {args.seconds:g} s; {os.cpu_count()} cores")
    print(f"{'format':7} {'published':>9} {'written':>8} {'missing':>8} {'MB/s':>6} {'CPU ms/pair':>12} "
          f"{'cores':>6} {'ceiling/s':>10} {'headroom':>9}")
    for r in result["runs"]:
        print(f"{r['format']:7} {r['published_pairs']:9d} {r['written_pairs']:8d} {r['missing_pairs']:8d} "
              f"{r['mb_per_s']:6.1f} {r['recorder_cpu_ms_per_pair']:12.1f} {r['recorder_cpu_cores']:6.2f} "
              f"{r['ceiling_pairs_per_s_one_thread']:10.1f} {r['headroom']:8.2f}x")
    print("ceiling: the same conversion on one thread of this process, pairs per CPU-second (one whole core); "
          "headroom = ceiling / offered rate")
    return 0


if __name__ == "__main__":
    sys.exit(main())
