"""rectify: frames_raw -> frames_rect (with the rectified camera model).

A new calibration is taken at run time, without a restart and without a torn frame: the
calibration file changed on disk (checked once a second), or, only with `calibration_updates: on`,
published on the `calibration` key (a CalibrationUpdate with the YAML text). Anyone who can put on
the robot's Zenoh network could otherwise rescale every distance, so that key is off by default
(turn it on where only trusted peers can publish it: the secured deployment's gateway lets no
offboard user put it). Either way a calibration whose baseline or focal length differs from the one
in use by more than `calibration_max_change` is refused (a restart takes it), as is one that does
not load or fits another image size; the old one stays in use.
"""
from __future__ import annotations

import queue
import threading
import time
from typing import Literal

from pydantic import Field

from ...common import codec
from ...common.keys import topic
from ...common.messages import CalibrationUpdate, StereoFrame
from ...common.node import Node
from ...common.settings import ServiceSettings
from .core import CalibrationHolder

SUBSCRIBES = ["frames_raw", "calibration"]
PUBLISHES = ["frames_rect"]


class RectifySettings(ServiceSettings):
    section = "rectify"
    calibration: str = Field("lifecam-studio", description="calibration YAML or built-in profile")
    alpha: float = Field(0.0, ge=0.0, le=1.0, description="0: crop to valid pixels, 1: keep all source pixels")
    watch_s: float = Field(1.0, ge=0.0, le=3600.0, description="check the calibration file for changes this often (0: never)")
    calibration_updates: Literal["off", "on"] = Field(
        "off", description="accept calibrations published on the calibration key (on: only where untrusted "
                           "peers cannot publish it, e.g. behind the TLS gateway)")
    calibration_max_change: float = Field(0.05, ge=0.0, le=10.0, description="refuse a run-time calibration whose "
                                          "baseline or focal length differs from the one in use by more than this "
                                          "fraction (0: no limit); a restart takes any calibration")


def reloader(node: Node, holder: CalibrationHolder, updates: "queue.Queue[CalibrationUpdate]", watch_s: float) -> None:
    """Off the frame loop: applies calibration messages and watches the calibration file."""
    next_poll = time.monotonic() + watch_s
    while node.running:
        timeout = max(0.0, next_poll - time.monotonic()) if watch_s > 0 else 0.5
        try:
            upd = updates.get(timeout=timeout)
        except queue.Empty:
            upd = None
        if upd is not None:
            holder.offer_yaml(upd.yaml, f"the calibration key ({upd.source or 'message'})")
        if watch_s > 0 and time.monotonic() >= next_poll:
            holder.poll_file()
            next_poll = time.monotonic() + watch_s
        node.extra["calibration_generation"] = float(holder.generation)
        node.extra["calibration_refused"] = float(holder.refused)


def run(node: Node, settings: RectifySettings) -> None:
    holder = CalibrationHolder(settings.calibration, settings.alpha, settings.calibration_max_change)
    # the size cap of frames_raw follows from the calibrated image size (two colour images, any dtype)
    w, h = holder.current().size
    frame_cap = 2 * w * h * 3 * 4 + (1 << 20)
    updates: queue.Queue[CalibrationUpdate] = queue.Queue(maxsize=8)

    def on_calibration(sample) -> None:  # Zenoh's thread: decode and hand over, nothing heavy
        if settings.calibration_updates != "on":
            holder.refused += 1
            node.extra["calibration_refused"] = float(holder.refused)
            node.warn("calibration", "refused a calibration published on the calibration key: calibration updates "
                                     "over Zenoh are off (rectify setting calibration_updates)")
            return
        msg = node.decode_or_drop(sample.payload.to_bytes(), CalibrationUpdate, "calibration message", "calibration")
        if msg is None:
            return
        try:
            updates.put_nowait(msg)
        except queue.Full:
            node.warn("calibration", "calibration messages arrive faster than they can be applied; dropped one")

    node.subscribe(topic("calibration").key(node.robot_id), on_calibration)
    threading.Thread(target=reloader, args=(node, holder, updates, settings.watch_s), name="calibration",
                     daemon=True).start()
    inbox = node.latest("frames_raw", max_bytes=frame_cap)
    out = node.publisher("frames_rect")
    for msg in node.receive(inbox):
        with node.processing(msg):
            rectifier = holder.current()  # one calibration for the whole pair
            holder.note_frame(msg.left.width, msg.left.height)
            left = codec.array_from_image(msg.left, "left")
            right = codec.array_from_image(msg.right, "right")
            rl, rr = rectifier.rectify(left, right)
            out.put(StereoFrame(robot_id=msg.robot_id, seq=msg.seq, stamp_ns=msg.stamp_ns, stages=msg.stages,
                                left=codec.image_from_array(rl), right=codec.image_from_array(rr),
                                camera=rectifier.model_message, source=msg.source))
