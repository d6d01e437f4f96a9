"""segmenter: disparity -> obstacles (PUBLIC: ballbot/obstacles/<robot_id>) and free space
(PUBLIC: ballbot/freespace/<robot_id>); the robot's odometry, when published, makes velocities
ground-referenced. The work is cores/segmentation/builder.py's ObstacleBuilder."""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Generic, TypeVar

import cv2

from common.keys import topic
from common.messages import ObstacleList, Odometry
from common.node import Node
from common.signing import KEY_ENV, calibration_key
from cores.segmentation.builder import ObstacleBuilder
from cores.segmentation.settings import SegmenterSettings

log = logging.getLogger("ballbot")

SUBSCRIBES = ["disparity", "odometry"]
PUBLISHES = ["obstacles", "freespace"]
# One OpenCV thread, as in rectify: the segmenter's OpenCV calls (a median blur, morphology, labelling
# at 320x240) are too small to gain from a second thread, whose wake-ups cost CPU: at 640x480, 7.4 ms
# of CPU a frame with one thread against 8.8 with two, the same wall time (bench segmenter --profile).
OPENCV_THREADS = 1

__all__ = ["SegmenterSettings", "run"]


T = TypeVar("T")


@dataclass
class _Latest(Generic[T]):
    """The newest message of a kind and when it came (monotonic s)."""

    msg: T | None
    at: float


# What `status` says of a degraded list, most telling reason first: what happened and what to do.
# A reason not here is listed as it is.
REASON_STATUS: dict[str, str] = {
    "cameras-swapped": "rectify finds most matched features farther left in the left image than in the right: the "
                       "left and right cameras are swapped (cables, or the devices' order); exchange camera_left and "
                       "camera_right (or the inputs) in capture's settings",
    "map-contradicted": "the disparity map puts farther what rectify's own coarse look at the same pair sees "
                        "nearer, over {contradicted} of the picture: it is not of this view (a worker that erased "
                        "what stands, or answered with an old map; a matcher gone wrong); stop until the maps "
                        "agree again",
    "nearer-than-range": "{near_share} of the picture stands nearer than the vision range's {min_range} m (at about "
                         "{near_m}, by rectify's coarse wide search): the list does not cover it, and it blocks the "
                         "view of the range; stop or back off",
    "floor-out-of-view": "the floor within the vision range is below the camera's view; nothing low there can be "
                         "seen (lengthen the range, or pitch the camera down)",
    "input-frozen": "the disparity maps have not changed for over {stale_after_s:g} s: the camera repeats one "
                    "picture with fresh stamps (a hung driver?)",
    "camera-frozen": "the {cameras} camera's picture has not changed for over rectify's frozen_after_s while "
                     "its stamps go on: its driver repeats one buffer (unplug and replug it, or restart capture)",
    "view-blocked": "part of the {blocked} camera's view is flat or blurred where the other camera sees texture "
                    "(a finger, a sticker, glare, grease on the lens?): what stands there is measured little or not "
                    "at all; clean or clear the lens",
    "washed-out": "{washed} of the floor within the vision range is clipped white in both cameras, at infinity: "
                  "the sun or a lamp low ahead, glare over both lenses; what stands there is not seen (shade "
                  "the lenses with a hood, lower the exposure, or turn away from the light)",
    "little-measured": "the disparity map measured {measured} of the picture: too dark, fog, a plain wall "
                       "filling the view, or a matcher's texture threshold too high; what was not measured is not "
                       "in the list (light the scene, raise the cameras' exposure or gain, or try method sgbm)",
    "noisy": "the pictures' sensor noise is {noise} grey levels (low light brought up by the cameras' gain): "
             "the matcher rejects more and more of what is there, and what it missed is not in the list (light "
             "the scene, or a longer exposure if the robot moves slowly)",
    "rows-misaligned": "rectify finds the pair's rows {offset} apart: the calibration no longer fits the rig (a "
                       "knocked camera, a loose lens?); check it (`ballbot-vision calibration check`) and calibrate "
                       "again",
    "mount-disagrees": "the configured mount's floor is off the floor in the disparity (fit_floor false); measure "
                       "the mount again (`ballbot-vision mount estimate`), or set fit_floor true",
    "standing-not-listed": "something standing in the vision range is in no obstacle: seed drops what touches the "
                           "image border, is under its area opening or beyond its Otsu threshold (method layers "
                           "keeps them); or rectify's coarse look sees it where the disparity map measured nothing "
                           "(a worker that emptied what stands?)",
}


def _noise(builder: ObstacleBuilder) -> str:
    checks = builder.checks
    return f"{checks.noise_grey:.1f}" if checks is not None and checks.noise_grey is not None else "high"


def list_status(msg: ObstacleList, builder: ObstacleBuilder, settings: SegmenterSettings, stale: bool) -> str:
    """The segmenter's status for its last list: ok, or why that list cannot be trusted."""
    reach = builder.reach
    if stale:
        return "stale: input too old"
    if reach.unreachable:
        return f"range-unreachable: {reach.message}"
    if reach.near_unmeasured or reach.far_unmeasured:
        said = [r for r, on in (("near-unmeasured", reach.near_unmeasured), ("far-unmeasured", reach.far_unmeasured))
                if on]
        return f"{', '.join(said)}: {reach.message}"
    for reason, text in REASON_STATUS.items():
        if reason in msg.degraded:
            rows = builder.checks.rows if builder.checks is not None else None
            offset = f"{rows.offset_px:.2f} px" if rows is not None else "too far"
            cameras = " and ".join(builder.checks.frozen) if builder.checks is not None else "a"
            blocked = " and ".join(builder.checks.blocked) if builder.checks is not None else "a"
            near = builder.near
            near_m = f"{near.distance_m:.2f} m" if near is not None and near.distance_m is not None else "?"
            near_share = f"{near.share:.0%}" if near is not None else "part"
            return f"{reason}: " + text.format(stale_after_s=settings.stale_after_s, offset=offset, cameras=cameras,
                                               blocked=blocked, near_m=near_m, near_share=near_share,
                                               measured=f"{msg.valid_fraction:.1%}",
                                               washed=f"{builder.washed_out:.1%}",
                                               noise=_noise(builder),
                                               min_range=f"{settings.min_range_m:g}",
                                               contradicted=f"{builder.contradicted:.1%}")
    if msg.degraded:  # no-ground, ground-uncertain, valid-collapse, ...
        return f"degraded lists: {', '.join(msg.degraded)}"
    return "ok"


def run(node: Node, settings: SegmenterSettings) -> None:
    cv2.setNumThreads(OPENCV_THREADS)
    builder = ObstacleBuilder(settings, node.mount)
    # Only the robot's dispatcher signs maps (with the key the robot's services share): anyone else's
    # are refused before their stamp reaches the freshness gate, so they cannot become the ordering
    # reference nor feed the list. Without a key (a bare `run segmenter`) any peer's map is taken.
    sign_key = calibration_key()
    unsigned_note = "" if sign_key else f" (disparity maps unauthenticated: no {KEY_ENV})"
    if sign_key is None:
        log.warning("segmenter: no %s: disparity maps are taken from anyone on the network, signed or not; "
                    "`up` and the compose files set one for the robot's services", KEY_ENV)
    inbox = node.latest("disparity", sign_key=sign_key)
    out = node.publisher("obstacles")
    free_out = node.publisher("freespace")
    lock = threading.Lock()
    last = _Latest[ObstacleList](None, time.monotonic())  # the last list published, for the heartbeat
    odometry = _Latest[Odometry](None, 0.0)
    odometry_cap = topic("odometry").max_bytes
    if node.mount.height_m is None and settings.method == "layers":
        log.info("segmenter: no camera mount configured: the ground is estimated from the disparity every frame "
                 "(published with each list; `ballbot-vision mount estimate` measures a mount for the config)")

    def on_odometry(sample) -> None:  # Zenoh's thread: size cap, decode, keep the newest
        payload = sample.payload.to_bytes()
        if odometry_cap and len(payload) > odometry_cap:
            node.decode_errors += 1
            node.warn("odometry", f"dropped an odometry message of {len(payload)} bytes (cap {odometry_cap})")
            return
        msg = node.decode_or_drop(payload, Odometry, "odometry message", "odometry")
        if msg is not None:
            odometry.msg, odometry.at = msg, time.monotonic()

    node.subscribe(topic("odometry").key(node.robot_id), on_odometry)

    def fresh_odometry() -> Odometry | None:
        msg = odometry.msg
        return msg if msg is not None and time.monotonic() - odometry.at <= settings.odometry_timeout_s else None

    def heartbeat() -> None:
        # With no input the last list goes out again, flagged stale, so subscribers can tell a quiet
        # scene from a dead pipeline.
        while not node.stop_event.wait(settings.stale_after_s):
            with lock:
                prev = last.msg
                quiet = time.monotonic() - last.at > settings.stale_after_s
                if quiet:
                    node.status = "stale: no disparity input" + unsigned_note
                    if prev is not None:
                        prev.stale = True
                        prev.publish_ns = time.time_ns()
                        out.put(prev, count=False)

    threading.Thread(target=heartbeat, name="stale-heartbeat", daemon=True).start()
    # The inbox hands on only plausible stamps, newest first (common/node.py: FreshnessGate); ages
    # and the tracker's time base are on the monotonic clock, so a wall-clock step moves neither.
    for msg in node.receive(inbox):
        with node.processing(msg):
            stale = node.age_s(msg) > settings.stale_after_s
            result = builder.process_message(msg, stale=stale, t_s=node.frame_time_s(msg), odometry=fresh_odometry())
            with lock:
                out.put(result.obstacles)
                last.msg, last.at = result.obstacles, time.monotonic()
            if result.freespace is not None:
                free_out.put(result.freespace, count=False)
            g = result.obstacles.ground
            node.extra["ground_height_m"] = g.height_m if g is not None else 0.0
            node.status = list_status(result.obstacles, builder, settings, stale) + unsigned_note
