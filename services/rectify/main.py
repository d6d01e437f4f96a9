"""rectify: frames_raw -> frames_rect (with the rectified camera model).

A new calibration is taken at run time, without a restart and without a torn frame: the
calibration file changed on disk (checked once a second), or one published on the `calibration`
key (a CalibrationUpdate with the YAML text). Anyone who can put on the robot's Zenoh network could
publish one, so the key is trusted only where it must be. Calibrations signed with the robot's
calibration key (common/signing.py: capture --source ros2 from CameraInfo, --source mcap from a
recording; `up` makes a key per run) are the robot's own and always taken. Unsigned ones
(`calibration_updates`):
  auto (default)  only while rectify has no calibration of its own (rectify.calibration unset);
  on              always (only where untrusted peers cannot publish it, e.g. behind the TLS
                  gateway, whose ACL lets no offboard user put it);
  off             never (signed ones neither).
Every run-time calibration (key or file) whose baseline or focal length differs from the one in
use by more than `calibration_max_change` is refused (a restart takes it): half the baseline would
silently halve every distance. The exceptions: the first calibration for a real source that rectify
had none for (its frames were refused until then), and the first signed one. One that does not load or fits another image
size is refused too; the old one stays in use.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Literal

import cv2
from pydantic import Field

from common import codec
from common.errors import CalibrationError
from common.keys import topic
from common.messages import CalibrationUpdate, StereoFrame
from common.node import Node
from common.settings import ServiceSettings
from common.signing import calibration_key, signed
from cores.calibration.rectify import CalibrationHolder

log = logging.getLogger("ballbot")

SUBSCRIBES = ["frames_raw", "calibration"]
PUBLISHES = ["frames_rect"]


class RectifySettings(ServiceSettings):
    section = "rectify"
    calibration: str | None = Field(None, description="calibration YAML or built-in profile; required for camera, "
                                    "video and image sources (unset: the thesis rig 'lifecam-studio', which the "
                                    "synthetic scene renders, for the synthetic source only)")
    alpha: float = Field(0.0, ge=0.0, le=1.0, description="0: crop to valid pixels, 1: keep all source pixels")
    watch_s: float = Field(1.0, ge=0.0, le=3600.0, description="check the calibration file for changes this often (0: never)")
    calibration_updates: Literal["auto", "on", "off"] = Field(
        "auto", description="accept calibrations published on the calibration key: auto: only while no "
                            "calibration is set (the source provides it); on: always (only where untrusted peers "
                            "cannot publish it); off: never")
    calibration_max_change: float = Field(0.05, ge=0.0, le=10.0, description="refuse a run-time calibration whose "
                                          "baseline or focal length differs from the one in use by more than this "
                                          "fraction (0: no limit); a restart takes any calibration")


def reloader(node: Node, holder: CalibrationHolder, updates: "queue.Queue[tuple[CalibrationUpdate, bool]]",
             watch_s: float, configured: bool = True) -> None:
    """Off the frame loop: applies calibration messages (with whether they are signed) and watches
    the calibration file."""
    state = {"signed_taken": False}
    next_poll = time.monotonic() + watch_s
    while node.running:
        timeout = max(0.0, next_poll - time.monotonic()) if watch_s > 0 else 0.5
        try:
            upd = updates.get(timeout=timeout)
        except queue.Empty:
            upd = None
        if upd is not None:
            upd, is_signed = upd
            # The first one replaces a rig that was only assumed (a real source's frames are refused
            # until then; a replay or a ROS camera sends its calibration before its first frame), and
            # the first signed one (the robot's own source: a ROS camera's CameraInfo, a recording)
            # replaces a configured one: no jump check against those. Once synthetic frames flow,
            # their rig is the right one.
            first_for_real_source = (not configured and holder.generation == 0
                                     and holder.stream_source != "synthetic")
            first_signed = is_signed and not state["signed_taken"]
            origin = f"the calibration key ({upd.source or 'message'}{', signed' if is_signed else ''})"
            if holder.offer_yaml(upd.yaml, origin, check_change=not (first_for_real_source or first_signed)):
                state["signed_taken"] = state["signed_taken"] or is_signed
        if watch_s > 0 and time.monotonic() >= next_poll:
            holder.poll_file()
            next_poll = time.monotonic() + watch_s
        node.extra["calibration_generation"] = float(holder.generation)
        node.extra["calibration_refused"] = float(holder.refused)


# The rig the synthetic scene renders; assumed only for frames from that source.
SYNTHETIC_RIG = "lifecam-studio"


def check_assumed_calibration(source: str, holder: CalibrationHolder, configured: bool) -> None:
    """A real source (cameras, video, images, ...) with no calibration configured or received must
    not be rectified with the thesis rig's calibration: raise, naming what to set."""
    if configured or holder.generation > 0 or source == "synthetic":
        return
    raise CalibrationError(f"frames from a '{source or 'unknown'}' source need this rig's calibration: set "
                           f"rectify.calibration (--calibration FILE, BALLBOT_RECTIFY_CALIBRATION or the config "
                           f"file) or publish one on the calibration key; the built-in '{SYNTHETIC_RIG}' profile "
                           f"is assumed only for the synthetic scene")


def run(node: Node, settings: RectifySettings) -> None:
    configured = settings.calibration is not None
    holder = CalibrationHolder(settings.calibration or SYNTHETIC_RIG, settings.alpha, settings.calibration_max_change)
    accept_key = settings.calibration_updates == "on" or (settings.calibration_updates == "auto" and not configured)
    # the size cap of frames_raw follows from the calibrated image size (two colour images, any dtype);
    # without a calibration of its own the source's may be any size: the key table's cap stands
    w, h = holder.current().size
    frame_cap = 2 * w * h * 3 * 4 + (1 << 20) if configured else None
    if not configured:
        log.info("rectify: no calibration set: '%s' is assumed for the synthetic scene only; frames from any "
                 "other source are refused until one is set", SYNTHETIC_RIG)
    updates: queue.Queue[tuple[CalibrationUpdate, bool]] = queue.Queue(maxsize=8)

    key = calibration_key()
    last_signed = {"stamp_ns": -1}

    def refuse(why: str) -> None:
        holder.refused += 1
        node.extra["calibration_refused"] = float(holder.refused)
        node.warn("calibration", f"refused a calibration published on the calibration key: {why}")

    def on_calibration(sample) -> None:  # Zenoh's thread: decode, vet and hand over, nothing heavy
        msg = node.decode_or_drop(sample.payload.to_bytes(), CalibrationUpdate, "calibration message", "calibration")
        if msg is None:
            return
        is_signed = settings.calibration_updates != "off" and signed(msg, key)
        if is_signed:
            if msg.stamp_ns <= last_signed["stamp_ns"]:
                return refuse("a replay of an older signed one")
            last_signed["stamp_ns"] = msg.stamp_ns
        elif not accept_key:
            return refuse(f"unsigned, rectify has a calibration of its own and calibration_updates is "
                          f"{settings.calibration_updates} (on: accept unsigned ones)"
                          if settings.calibration_updates != "off" else "calibration_updates is off")
        try:
            updates.put_nowait((msg, is_signed))
        except queue.Full:
            node.warn("calibration", "calibration messages arrive faster than they can be applied; dropped one")

    node.subscribe(topic("calibration").key(node.robot_id), on_calibration)
    threading.Thread(target=reloader, args=(node, holder, updates, settings.watch_s, configured), name="calibration",
                     daemon=True).start()
    # One OpenCV thread: a pair's remap is ~1.2 ms of CPU, and a second thread's wake-ups and spinning
    # cost more CPU (1.45 ms per pair, mostly in the kernel, at 20 pairs/s in the pipeline) than the
    # ~0.6 ms of latency it saves; rectify's process spent 3.6 ms per pair with two threads, 2.65 with one.
    cv2.setNumThreads(1)
    inbox = node.latest("frames_raw", max_bytes=frame_cap)
    out = node.publisher("frames_rect")
    for msg in node.receive(inbox):
        holder.stream_source = msg.source
        with node.processing(msg):
            try:
                check_assumed_calibration(msg.source, holder, configured)
            except CalibrationError:
                node.status = f"error: no calibration for the '{msg.source}' source (set rectify.calibration)"
                raise
            if node.status.startswith("error: no calibration"):
                node.status = "ok"
            rectifier = holder.current()  # one calibration for the whole pair
            holder.note_frame(msg.left.width, msg.left.height)
            left = codec.array_from_image(msg.left, "left")
            right = codec.array_from_image(msg.right, "right")
            rl, rr = rectifier.rectify(left, right)
            out.put(StereoFrame(robot_id=msg.robot_id, seq=msg.seq, stamp_ns=msg.stamp_ns, stages=msg.stages,
                                left=codec.image_from_array(rl), right=codec.image_from_array(rr),
                                camera=rectifier.model_message, source=msg.source))
