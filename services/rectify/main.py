"""rectify: frames_raw -> frames_rect (with the rectified camera model).

A new calibration is taken at run time, without a restart and without a torn frame: published on
the `calibration` key (a CalibrationUpdate with the YAML text), or the calibration file changed on
disk (checked once a second). A bad one is logged and refused; the old one stays in use.
"""
from __future__ import annotations

import logging
import queue
import threading
import time

from pydantic import Field

from ...common import codec
from ...common.errors import CalibrationError
from ...common.keys import topic
from ...common.messages import CalibrationUpdate, StereoFrame
from ...common.node import Node
from ...common.settings import ServiceSettings
from .core import CalibrationHolder

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
    holder = CalibrationHolder(settings.calibration or SYNTHETIC_RIG, settings.alpha)
    if not configured:
        log.info("rectify: no calibration set: '%s' is assumed for the synthetic scene only; frames from any "
                 "other source are refused until one is set", SYNTHETIC_RIG)
    updates: queue.Queue[CalibrationUpdate] = queue.Queue(maxsize=8)

    def on_calibration(sample) -> None:  # Zenoh's thread: decode and hand over, nothing heavy
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
    inbox = node.latest("frames_raw")
    out = node.publisher("frames_rect")
    for msg in node.receive(inbox):
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
