"""A hostile or broken disparity worker, or a forging peer, as its own process, for
tests/test_map_attacks.py (issue 25). Prints one JSON line per event on stdout ("ready", "attack"
when its first bad answer or forgery goes out, "answered" counts); runs until stdin closes.

Worker modes (it declares a worker token, takes work items from its own key like an honest worker
and answers the first --honest items honestly, to be trusted first):
  nan, inf      float32 maps full of NaN / +inf        uint8      all-zero uint8 maps
  invalid       int16 maps with every pixel invalid    small      320x240 maps for 640x480 frames
  huge          a map 100x larger than the frame's     future     honest maps stamped now + 0.2 s
  liar          receipts claiming success, no maps     silent     nothing at all
  erase         honest maps with what stands erased: each row's measured pixels at its far end (10th
                percentile), a plausible map of an empty floor that passes every check of size and range
Peer modes (no worker identity; --rate maps per second):
  forge-disparity  all-invalid maps stamped now + 0.2 s on `disparity` (unsigned, or with a made-up tag)
  forge-result     the same on an honest worker's result key (--victim), with a made-up nonce
"""
from __future__ import annotations

import argparse
import json
import os
import queue
import sys
import threading
import time

import numpy as np
import zenoh

from common import codec
from common.inbox import _META
from common.keys import topic
from common.messages import CameraModel, DisparityMap, StereoFrame, WorkDone
from common.zenoh_session import ZenohOptions, open_session
from cores import camera
from cores.matching.config import MatcherConfig
from services.disparity.computer import FrameComputer
from services.disparity.envelope import parse_attachment, receipt_attachment
from services.disparity.results import result_header

WORKER_MODES = ("nan", "inf", "uint8", "invalid", "small", "huge", "future", "liar", "silent", "erase")
AHEAD_NS = 200_000_000  # the takeover: now + 0.2 s, inside the 0.25 s a gate allows


def emit(kind: str, **kw) -> None:
    kw.update(k=kind, t=time.time())
    sys.stdout.write(json.dumps(kw) + "\n")
    sys.stdout.flush()


def bad_answer(mode: str, honest: DisparityMap) -> DisparityMap:
    h, w = honest.image.height, honest.image.width
    if mode in ("nan", "inf"):
        a = np.full((h, w), np.nan if mode == "nan" else np.inf, np.float32)
        return honest.model_copy(update={"image": codec.image_from_array(a)})
    if mode == "uint8":
        return honest.model_copy(update={"image": codec.image_from_array(np.zeros((h, w), np.uint8))})
    if mode == "invalid":
        a = np.full((h, w), honest.invalid_value, np.int16)
        return honest.model_copy(update={"image": codec.image_from_array(a)})
    if mode == "small":
        import cv2

        a = cv2.resize(codec.array_from_image(honest.image), (320, 240), interpolation=cv2.INTER_NEAREST)
        return honest.model_copy(update={"image": codec.image_from_array(a)})
    if mode == "huge":
        img = honest.image.model_copy(update={"data": honest.image.data * 100})
        return honest.model_copy(update={"image": img})
    if mode == "future":
        return honest.model_copy(update={"stamp_ns": time.time_ns() + AHEAD_NS})
    if mode == "erase":
        return honest.model_copy(update={"image": codec.image_from_array(erased(codec.array_from_image(honest.image)))})
    raise ValueError(mode)


def erased(d: np.ndarray) -> np.ndarray:
    """`erase`'s map: in each row, every measured pixel at the row's far end (its 10th percentile):
    what stands is gone, the floor and the wall stay about where they were. Float px (NaN: not
    measured) or fixed point (<= 0: not measured)."""
    out = d.copy()
    for y in range(d.shape[0]):
        ok = d[y] > 0  # NaN compares false
        if ok.any():
            out[y, ok] = np.percentile(d[y, ok], 10).astype(d.dtype)
    return out


def run_worker(s, a) -> None:
    computer = FrameComputer(MatcherConfig(method="bm"), 1.0)
    items: queue.Queue = queue.Queue(maxsize=4)

    def on_work(sample) -> None:
        att = sample.attachment
        try:
            items.put_nowait((sample.payload.to_bytes(), att.to_bytes() if att is not None else None))
        except queue.Full:
            pass

    s.declare_subscriber(topic("work").key(a.rid, instance=a.name), on_work)
    # BLOCK: a 61 MB map is delivered whole, not dropped on a full queue (an attacker may choose)
    results = s.declare_publisher(topic("work_result").key(a.rid, instance=a.name),
                                  congestion_control=zenoh.CongestionControl.BLOCK)
    receipts = s.declare_publisher(topic("work_done").key(a.rid, instance=a.name))
    token = s.liveliness().declare_token(topic("worker").key(a.rid, instance=a.name))
    emit("ready")
    n = bad = 0
    while not stop.is_set():
        try:
            payload, att = items.get(timeout=0.2)
        except queue.Empty:
            continue
        msg = codec.decode(payload, StereoFrame)
        _, _, nonce = parse_attachment(att)
        n += 1
        if n <= a.honest:
            m = computer.compute(msg, a.name)
            results.put(codec.encode(m), attachment=result_header(m, nonce))
            emit("answered", seq=msg.seq, honest=True)
            continue
        if bad == 0:
            emit("attack", seq=msg.seq)
        bad += 1
        if a.mode == "silent":
            continue
        if a.mode == "liar":
            receipts.put(codec.encode(WorkDone(robot_id=a.rid, seq=msg.seq, stamp_ns=msg.stamp_ns, worker=a.name,
                                               ok=True, method="bm", proc_ms=5.0)),
                         attachment=receipt_attachment(nonce))
            continue
        m = bad_answer(a.mode, computer.compute(msg, a.name))
        header = result_header(m, nonce)
        if a.mode == "huge":  # the header says what the frame is; the payload is 100 times that
            header = result_header(m.model_copy(update={"image": m.image.model_copy(
                update={"data": m.image.data[:len(m.image.data) // 100]})}), nonce)
        results.put(codec.encode(m), attachment=header)
        emit("answered", seq=msg.seq, honest=False)
    token.undeclare()


def forged_map(rid: str, seq: int) -> DisparityMap:
    """An all-invalid map for the robot's camera, stamped 0.2 s ahead (no subscription needed: a
    worker credential reads no map)."""
    from cores.calibration.rectify import Rectifier

    m = Rectifier(camera.load_calibration("lifecam-studio")).model
    cam = CameraModel(width=m.width, height=m.height, focal_px=m.focal_px, cx=m.cx, cy=m.cy, baseline_m=m.baseline_m,
                      Q=[0.0] * 16)
    a = np.full((m.height, m.width), -16, np.int16)
    return DisparityMap(robot_id=rid, seq=seq, stamp_ns=time.time_ns() + AHEAD_NS, image=codec.image_from_array(a),
                        scale=16.0, invalid_value=-16.0, min_disparity=0, num_disparities=64, camera=cam,
                        method="bm", worker=a_name)


def run_forger(s, a) -> None:
    template = forged_map(a.rid, 10**6)
    if a.mode == "forge-disparity":
        key = topic("disparity").key(a.rid)
    else:
        key = topic("work_result").key(a.rid, instance=a.victim)
    pub = s.declare_publisher(key)
    emit("ready")
    source = int.from_bytes(os.urandom(8), "big")
    i = 0
    while not stop.is_set():
        i += 1
        m = template.model_copy(update={"seq": template.seq + i, "stamp_ns": time.time_ns() + AHEAD_NS})
        payload = codec.encode(m)
        meta = _META.pack(m.stamp_ns, source, i)
        if a.mode == "forge-disparity":
            attachment = meta if i % 2 else meta + os.urandom(32)  # unsigned, or a made-up signature
        else:
            attachment = result_header(m.model_copy(update={"seq": i}), os.urandom(16))
        pub.put(payload, attachment=attachment)
        if i == 1:
            emit("attack")
        stop.wait(1.0 / a.rate)
    emit("answered", count=i, honest=False)


stop = threading.Event()
a_name = "attacker"

if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--rid", required=True)
    p.add_argument("--connect", required=True)
    p.add_argument("--mode", required=True, choices=WORKER_MODES + ("forge-disparity", "forge-result"))
    p.add_argument("--name", default="attacker")
    p.add_argument("--honest", type=int, default=10)
    p.add_argument("--victim", default="")
    p.add_argument("--rate", type=float, default=5.0)
    p.add_argument("--zenoh-config", default=None)
    p.add_argument("--client", action="store_true")
    a = p.parse_args()
    a_name = a.name
    o = ZenohOptions(mode="client" if a.client else "peer", connect=[a.connect],
                     listen=[] if a.client else ["tcp/127.0.0.1:0"], config_file=a.zenoh_config)
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    with open_session(o) as session:
        (run_worker if a.mode in WORKER_MODES else run_forger)(session, a)
