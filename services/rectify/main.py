"""rectify: frames_raw -> frames_rect (with the rectified camera model).

A new calibration is taken at run time, without a restart and without a torn frame: the
calibration file changed on disk (checked once a second), or one published on the `calibration`
key (a CalibrationUpdate with the YAML text). The calibration is configuration, not a message
anyone on the robot's network may send:
- on the key, only calibrations signed with the robot's calibration key are taken
  (common/signing.py: capture signs a ROS camera's CameraInfo and a recording's calibration;
  `calibration publish` / `calibrate --publish` sign with the key of the local user; `up` makes a
  key per run, a deployment shares one). Unsigned ones are refused, counted and logged, whatever
  `calibration_updates` says, unless `insecure_unsigned_calibrations` is set (a network nobody
  else can reach); `calibration_updates: off` refuses every one.
- drift is bounded against the calibration rectify STARTED with (CalibrationHolder.reference),
  not step by step: a run-time calibration (key or file) whose baseline or focal length differs
  from it by more than `calibration_max_change` is refused, however small each step was; a
  restart takes any calibration.
- a real source's first calibration comes from the configuration or a signed update, and must fit
  the frames' size. Without rectify.calibration the thesis rig is assumed for synthetic frames only;
  once it rectified one, it is what rectify started with, so a forged "camera" frame cannot turn
  the next update into a first one.
A refused one leaves the one in use in place.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from common import codec
from common.errors import CalibrationError
from common.keys import topic
from common.messages import CalibrationUpdate, StereoFrame
from common.node import Node
from common.settings import ServiceSettings
from common.signing import KEY_ENV, calibration_key, signed
from cores.calibration.check import SWAPPED_SHARE, PairChecks, RowMonitor
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
    watch_s: float = Field(1.0, ge=0.0, le=3600.0,
                           description="check the calibration file for changes this often (0: never)")
    calibration_updates: Literal["auto", "on", "off"] = Field(
        "auto", description="calibrations published on the calibration key: auto, on: take those signed with "
                            "the robot's calibration key (BALLBOT_CALIBRATION_KEY), within calibration_max_change "
                            "of the one rectify started with; off: take none. Unsigned ones are refused either way "
                            "(see insecure_unsigned_calibrations)")
    insecure_unsigned_calibrations: bool = Field(
        False, description="INSECURE: also take UNSIGNED calibrations from the calibration key, from anyone who "
                           "can publish on the robot's network (still within calibration_max_change); only where "
                           "nobody else can reach that network")
    calibration_max_change: float = Field(0.05, ge=0.0, le=10.0, description="refuse a run-time calibration whose "
                                          "baseline or focal length differs from the one rectify started with by "
                                          "more than this fraction (0: no limit); a restart takes any calibration")
    row_check_s: float = Field(1.0, ge=0.0, le=3600.0, description="check one rectified pair this often that "
                               "matched features lie on the same rows (10-14 ms of one core, off the frame path; 0: "
                               "never); every frame carries the last result, and lists say rows-misaligned")
    max_row_offset_px: float = Field(0.5, gt=0.0, le=100.0, description="median vertical offset of matched "
                                     "features above which the rows are misaligned (a well calibrated rig: 0.05-0.2 "
                                     "px; a camera knocked 1 px: 1.0)")
    frozen_after_s: float = Field(0.5, gt=0.0, le=10.0, description="a camera whose picture has not changed, "
                                  "bit for bit, for this long while its stamps go on is frozen (a hung driver "
                                  "repeating its last buffer; a live camera's noise never repeats): every list says "
                                  "camera-frozen (a view partly blocked, flat where the other camera sees texture, "
                                  "is said at once: view-blocked; at most 10 s: at an hour, a hung camera's lists "
                                  "looked fresh for an hour)")
    near_check: bool = Field(True, description="match each rectified pair coarsely (a quarter of the resolution, from "
                             "each image) "
                             "over half the picture's width of disparity, so that what stands nearer than the vision "
                             "range is seen: lists say nearer-than-range (about 1.6 ms of one core a 640x480 pair; "
                             "false for a rig that sees part of the robot over min_height_m up)")
    source: Literal["synthetic", "cameras", "sbs", "video", "images", "ros2", "mcap"] | None = Field(
        None, description="the capture source this rectify serves, when the deployment knows it (the compose files "
                          "set it from CAPTURE_SOURCE): cameras, sbs, video and images need rectify.calibration and "
                          "rectify refuses to start without it; ros2 and mcap send theirs, signed; null: unknown "
                          "(frames of a real source are refused until a calibration is set or signed)")


def reloader(node: Node, holder: CalibrationHolder, updates: queue.Queue[tuple[CalibrationUpdate, bool]],
             watch_s: float) -> None:
    """Off the frame loop: applies vetted calibration messages (with whether they are signed) and
    watches the calibration file."""
    next_poll = time.monotonic() + watch_s
    while node.running:
        timeout = max(0.0, next_poll - time.monotonic()) if watch_s > 0 else 0.5
        try:
            item = updates.get(timeout=timeout)
        except queue.Empty:
            item = None
        if item is not None:
            upd, is_signed = item
            origin = f"the calibration key ({upd.source or 'message'}, {'signed' if is_signed else 'UNSIGNED'})"
            holder.offer_yaml(upd.yaml, origin)
        if watch_s > 0 and time.monotonic() >= next_poll:
            holder.poll_file()
            next_poll = time.monotonic() + watch_s
        publish_calibration_stats(node, holder)


def publish_calibration_stats(node: Node, holder: CalibrationHolder) -> None:
    """What status (and an attack test) can read: swaps, refusals, and the rig in use."""
    m = holder.current().model
    node.extra["calibration_generation"] = float(holder.generation)
    node.extra["calibration_refused"] = float(holder.refused)
    node.extra["calibration_baseline_mm"] = m.baseline_m * 1000.0
    node.extra["calibration_focal_px"] = m.focal_px


# The rig the synthetic scene renders; assumed only for frames from that source.
SYNTHETIC_RIG = "lifecam-studio"


def check_assumed_calibration(source: str, holder: CalibrationHolder, configured: bool) -> None:
    """A real source (cameras, video, images, ...) with no calibration configured or received must
    not be rectified with the thesis rig's calibration: raise, naming what to set."""
    if configured or holder.generation > 0 or source == "synthetic":
        return
    raise CalibrationError(f"frames from a '{source or 'unknown'}' source need this rig's calibration: set "
                           f"rectify.calibration (--calibration FILE, BALLBOT_RECTIFY_CALIBRATION or the config "
                           f"file) or publish one signed with the robot's key (ballbot-vision calibration publish); "
                           f"the built-in '{SYNTHETIC_RIG}' profile is assumed only for the synthetic scene")


# Sources that send rectify their own calibration, signed (capture's ros2.py and mcap_source.py).
SELF_CALIBRATING = ("ros2", "mcap")


def preflight(settings: RectifySettings) -> None:
    """Before the service is up (cli.cmd_run calls it before the Node opens): a deployment that names
    a real source must configure its rig."""
    if settings.calibration is None and settings.source not in (None, "synthetic", *SELF_CALIBRATING):
        raise CalibrationError(f"rectify.source is '{settings.source}' and rectify.calibration is not set: a real "
                               f"rig's calibration is configuration (--calibration FILE, BALLBOT_RECTIFY_CALIBRATION, "
                               f"or RECTIFY_CALIBRATION in the compose files); the built-in '{SYNTHETIC_RIG}' profile "
                               f"fits the synthetic scene only")


class LiveRowCheck:
    """The RowMonitor off the frame path: the loop hands a due pair to a thread of its own (a pair
    arriving while one is checked is not queued), and reads `latest` for each frame it publishes."""

    def __init__(self, node: Node, monitor: RowMonitor):
        self.node, self.monitor = node, monitor
        self.slot: queue.Queue[tuple[np.ndarray, np.ndarray, float, int, int]] = queue.Queue(maxsize=1)
        self.warned = False
        self.warned_swapped = False
        node.extra["row_checks"] = 0.0
        threading.Thread(target=self._run, name="row-check", daemon=True).start()

    def offer(self, left: np.ndarray, right: np.ndarray, t_s: float, stamp_ns: int) -> None:
        epoch = self.monitor.take(t_s)
        if epoch is None:
            return
        try:
            self.slot.put_nowait((left, right, t_s, stamp_ns, epoch))
        except queue.Full:
            pass

    def _run(self) -> None:
        while self.node.running:
            try:
                left, right, t_s, stamp_ns, epoch = self.slot.get(timeout=0.5)
            except queue.Empty:
                continue
            try:
                rows = self.monitor.check(left, right, t_s, stamp_ns, epoch)
            except Exception as e:  # a pair OpenCV cannot take (an odd size, a type): this check only, logged
                self.monitor.failed += 1
                self.node.warn("rows", f"the row check failed on one pair: {type(e).__name__}: {e}")
                continue
            self.node.extra["row_checks"] = float(self.monitor.checks)
            self.node.extra["row_checks_failed"] = float(self.monitor.failed)
            if rows is None:
                continue
            self.node.extra["row_offset_px"] = round(rows.offset_px, 3)
            self.node.extra["reversed_share"] = round(rows.reversed_share, 3)
            swapped = rows.reversed_share > SWAPPED_SHARE
            if swapped and not self.warned_swapped:
                self.node.warn("swapped", f"cameras swapped: {rows.reversed_share:.0%} of the matched features off "
                               f"zero disparity lie farther left in the left image than in the right; exchange "
                               f"camera_left and camera_right (or the inputs) in capture's settings; every list "
                               f"says cameras-swapped")
            elif self.warned_swapped and not swapped:
                log.info("rectify: cameras the right way round again (%.0f%% reversed)", 100 * rows.reversed_share)
            self.warned_swapped = swapped
            bad = rows.offset_px > rows.tolerance_px
            if bad:
                self.node.warn("rows", f"rectified rows misaligned: matched features lie {rows.offset_px:.2f} px "
                               f"apart vertically (median of {rows.matches}; max_row_offset_px "
                               f"{rows.tolerance_px:g}): the calibration no longer fits the rig (a knocked camera? "
                               f"check with `ballbot-vision calibration check`, or calibrate again); every list "
                               f"says rows-misaligned")
            elif self.warned:
                log.info("rectify: rows aligned again (%.2f px)", rows.offset_px)
            self.warned = bad


def _say_cameras(node: Node, check: str, cameras: list[Literal["left", "right"]],
                 said: list[Literal["left", "right"]], warning: str, cleared: str) -> list[Literal["left", "right"]]:
    """One of PairChecks' per-camera verdicts into the stats (`<check>_cameras`) and, when it changed
    since `said`, the log: a warning naming the cameras ({cameras} in `warning`), or `cleared`.
    -> what is now said."""
    node.extra[f"{check}_cameras"] = float(len(cameras))
    if cameras != said:
        if cameras:
            node.warn(check, warning.format(cameras=" and ".join(cameras)))
        else:
            log.info("rectify: %s", cleared)
    return cameras


def run(node: Node, settings: RectifySettings) -> None:
    preflight(settings)
    configured = settings.calibration is not None
    holder = CalibrationHolder(settings.calibration or SYNTHETIC_RIG, settings.alpha, settings.calibration_max_change,
                               started=configured)
    # the size cap of frames_raw follows from the calibrated image size (two colour images, any dtype);
    # without a calibration of its own the source's may be any size: the key table's cap stands
    w, h = holder.current().size
    frame_cap = 2 * w * h * 3 * 4 + (1 << 20) if configured else None
    if not configured:
        log.info("rectify: no calibration set: '%s' is assumed for the synthetic scene only; frames from any "
                 "other source are refused until one is set or a signed one arrives", SYNTHETIC_RIG)
    updates: queue.Queue[tuple[CalibrationUpdate, bool]] = queue.Queue(maxsize=8)

    key = calibration_key()
    take = settings.calibration_updates != "off"
    unsigned_ok = take and settings.insecure_unsigned_calibrations
    if not take:
        log.info("rectify: calibration_updates is off: calibrations on the calibration key are refused")
    elif unsigned_ok:
        log.warning("rectify: insecure_unsigned_calibrations is set: anyone who can publish on this robot's network "
                    "may change its calibration (within %.0f %% of the one it started with)",
                    settings.calibration_max_change * 100)
    elif key is None:
        log.warning("rectify: no calibration key (%s): calibrations on the calibration key cannot be verified and "
                    "are refused", KEY_ENV)
    last_signed = {"stamp_ns": -1}
    node.extra["calibration_unsigned_refused"] = 0.0
    publish_calibration_stats(node, holder)

    def refuse(why: str, unsigned: bool = False) -> None:
        holder.refused += 1
        node.extra["calibration_refused"] = float(holder.refused)
        if unsigned:
            node.count("calibration_unsigned_refused")
        node.warn("calibration", f"refused a calibration published on the calibration key: {why}")

    def on_calibration(sample) -> None:  # Zenoh's thread: decode, vet and hand over, nothing heavy
        msg = node.decode_or_drop(sample.payload.to_bytes(), CalibrationUpdate, "calibration message", "calibration")
        if msg is None:
            return
        if not take:
            return refuse("calibration_updates is off")
        is_signed = signed(msg, key)
        if is_signed:
            if msg.stamp_ns <= last_signed["stamp_ns"]:
                return refuse("a replay of an older signed one")
            last_signed["stamp_ns"] = msg.stamp_ns
        elif not unsigned_ok:
            why = ("its signature does not verify with this robot's calibration key" if msg.signature else
                   "it is not signed with this robot's calibration key")
            if key is None:
                why += f" (rectify has no key: {KEY_ENV} is not set)"
            return refuse(f"{why}; calibrations are configuration (rectify.calibration, or `ballbot-vision "
                          f"calibration publish` with the key)", unsigned=True)
        try:
            updates.put_nowait((msg, is_signed))
        except queue.Full:
            node.warn("calibration", "calibration messages arrive faster than they can be applied; dropped one")

    node.subscribe(topic("calibration").key(node.robot_id), on_calibration)
    threading.Thread(target=reloader, args=(node, holder, updates, settings.watch_s), name="calibration",
                     daemon=True).start()
    # One OpenCV thread: a pair's remap is ~1.2 ms of CPU, and a second thread's wake-ups and spinning
    # cost more CPU (1.45 ms per pair, mostly in the kernel, at 20 pairs/s in the pipeline) than the
    # ~0.6 ms of latency it saves; rectify's process spent 3.6 ms per pair with two threads, 2.65 with one.
    cv2.setNumThreads(1)
    inbox = node.latest("frames_raw", max_bytes=frame_cap)
    out = node.publisher("frames_rect")
    checks = PairChecks(settings.row_check_s, settings.max_row_offset_px, settings.frozen_after_s, settings.near_check)
    rows = LiveRowCheck(node, checks.rows)
    rows_generation = holder.generation
    said_frozen: list[Literal["left", "right"]] = []
    said_blocked: list[Literal["left", "right"]] = []
    for msg in node.receive(inbox):
        holder.stream_source = msg.source
        with node.processing(msg):
            # the size of what arrives, so the first calibration for a real source must fit it
            holder.note_frame(msg.left.width, msg.left.height)
            try:
                check_assumed_calibration(msg.source, holder, configured)
            except CalibrationError:
                node.status = f"error: no calibration for the '{msg.source}' source (set rectify.calibration)"
                raise
            if node.status.startswith("error: no calibration"):
                node.status = "ok"
            rectifier = holder.current()  # one calibration for the whole pair
            if holder.generation != rows_generation:
                rows.monitor.reset()  # a new calibration: its rows are checked on this pair
                rows_generation = holder.generation
            left = codec.array_from_image(msg.left, "left")
            right = codec.array_from_image(msg.right, "right")
            def offer(lf: np.ndarray, rt: np.ndarray, stamp_ns: int = msg.stamp_ns) -> None:
                rows.offer(lf, rt, time.monotonic(), stamp_ns)  # checked off the frame path
            rl, rr, pair_checks = checks.frame(left, right, time.monotonic(), rectifier.rectify, rectifier.model,
                                               offer)
            holder.mark_used()
            said_frozen = _say_cameras(
                node, "frozen", pair_checks.frozen, said_frozen,
                f"the {{cameras}} camera's picture has not changed for over {settings.frozen_after_s:g} s while its "
                f"stamps go on: its driver repeats one buffer; every list says camera-frozen",
                "both cameras' pictures change again")
            said_blocked = _say_cameras(
                node, "blocked", pair_checks.blocked, said_blocked,
                "part of the {cameras} camera's view is flat or blurred where the other camera sees texture (a "
                "finger, a sticker, glare, grease on the lens?): little or nothing there is measured; every list "
                "says view-blocked",
                "both cameras see the whole view again")
            out.put(StereoFrame(robot_id=msg.robot_id, seq=msg.seq, stamp_ns=msg.stamp_ns, stages=msg.stages,
                                left=codec.image_from_array(rl), right=codec.image_from_array(rr),
                                camera=rectifier.model_message, source=msg.source,
                                checks=pair_checks))
