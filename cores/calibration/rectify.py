"""Rectification core: maps computed once from a calibration, then two remaps per pair.

No Zenoh here; the service (main.py) and the offline `rectify` command share this.
`CalibrationHolder` swaps in a new calibration at run time without a torn frame.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import threading
from pathlib import Path

import cv2
import numpy as np

from common.errors import BallbotError, CalibrationError
from common.messages import CameraModel
from cores import camera


def camera_model_message(m: camera.RectifiedModel) -> CameraModel:
    return CameraModel(width=m.width, height=m.height, focal_px=m.focal_px, cx=m.cx, cy=m.cy,
                       baseline_m=m.baseline_m, Q=[float(x) for x in m.Q.ravel()],
                       view_left=None if m.view_left is None else list(m.view_left),
                       view_right=None if m.view_right is None else list(m.view_right))


def _map(cam: camera.Intrinsics, R: np.ndarray, P: np.ndarray, size: tuple[int, int],
         map_type: int = cv2.CV_32FC1) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables for one camera, float (CV_32FC1, the default) or fixed point (CV_16SC2).

    Float maps: OpenCV 5's remap has a vectorised bilinear path for them that takes half the CPU of
    the fixed-point one (640x480 pair: 1.2 ms vs 2.3 ms on one core, `ballbot-vision bench rectify`),
    and they are exact where fixed point rounds every source position to 1/32 px. They take 2.4 MB
    per camera at 640x480 instead of 0.9 MB.

    OpenCV ignores K[0, 1]; with a skew s the source column is shifted by s (v - cy) / fy, v being
    the source row of the skew-free camera."""
    if cam.skew == 0:
        return cv2.initUndistortRectifyMap(cam.K, cam.D, R, P, size, map_type)
    K = cam.K.copy()
    K[0, 1] = 0.0
    mx, my = cv2.initUndistortRectifyMap(K, cam.D, R, P, size, cv2.CV_32FC1)
    mx = mx + np.float32(cam.skew / cam.fy) * (my - np.float32(cam.cy))
    return (mx, my) if map_type == cv2.CV_32FC1 else cv2.convertMaps(mx, my, map_type)


MAP_TYPES = {"float": cv2.CV_32FC1, "fixed": cv2.CV_16SC2}
UNSEEN_SHARE = 0.001  # less of the picture than this unseen (alpha 0: a few corner pixels) is no outline
OUTLINE_TOLERANCE_PX = 1.0  # well within the matcher's margin (window_reach)


def seen_outline(mx: np.ndarray, my: np.ndarray, size: tuple[int, int]) -> tuple[tuple[float, float], ...] | None:
    """The outline (polygon, px, within OUTLINE_TOLERANCE_PX) of the rectified pixels whose source
    lies inside the camera's picture (all of the bilinear remap's four source pixels), by its float
    maps; None when (nearly) all do."""
    w, h = size
    seen = ((mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)).astype(np.uint8)
    if 1.0 - seen.mean() < UNSEEN_SHARE:
        return None
    contours, _ = cv2.findContours(seen, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0))  # the camera saw none of it
    c = cv2.approxPolyDP(max(contours, key=cv2.contourArea), OUTLINE_TOLERANCE_PX, True)
    return tuple((float(x), float(y)) for x, y in c.reshape(-1, 2))


class Rectifier:
    """Undistort and rectify stereo pairs so that epipolar lines are image rows.

    For a raw rig the maps come from cv2.stereoRectify + initUndistortRectifyMap (float maps by
    default, see _map; maps="fixed" for fixed-point ones); an already-rectified rig passes images
    through after a size check.
    """

    def __init__(self, calibration: camera.Calibration, alpha: float = 0.0,
                 interpolation: int = cv2.INTER_LINEAR, maps: str = "float"):
        if maps not in MAP_TYPES:
            raise BallbotError(f"maps: one of {', '.join(MAP_TYPES)}, got {maps!r}")
        self.calibration = calibration
        self.size = calibration.image_size
        self.interpolation = interpolation
        if isinstance(calibration, camera.RectifiedRig):
            self.rectification = None
            self.model = calibration.model
            self._maps = None
        else:
            r = camera.rectify_rig(calibration, alpha)
            self.rectification = r
            floats = (_map(calibration.left, r.R1, r.P1, self.size), _map(calibration.right, r.R2, r.P2, self.size))
            self.model = dataclasses.replace(r.model, view_left=seen_outline(*floats[0], self.size),
                                             view_right=seen_outline(*floats[1], self.size))
            self._maps = floats if maps == "float" else \
                tuple(cv2.convertMaps(mx, my, MAP_TYPES[maps]) for mx, my in floats)  # type: ignore[assignment]
        self.model_message = camera_model_message(self.model)

    def check_size(self, image: np.ndarray, name: str) -> None:
        h, w = image.shape[:2]
        if (w, h) != tuple(self.size):
            named = f" '{self.calibration.name}'" if self.calibration.name else ""
            raise BallbotError(f"{name}: image is {w}x{h}, the calibration{named} is for {self.size[0]}x{self.size[1]}")

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """left, right: (H, W) or (H, W, 3) images of the calibrated size -> rectified, same dtype."""
        self.check_size(left, "left")
        self.check_size(right, "right")
        if self._maps is None:
            return left, right
        (l1, l2), (r1, r2) = self._maps
        return (cv2.remap(left, l1, l2, self.interpolation, borderMode=cv2.BORDER_CONSTANT),
                cv2.remap(right, r1, r2, self.interpolation, borderMode=cv2.BORDER_CONSTANT))


log = logging.getLogger("ballbot.rectify")


def implausible_change(old: camera.RectifiedModel, new: camera.RectifiedModel, max_change: float,
                       old_name: str = "the one in use") -> str:
    """Why swapping `old` for `new` at run time is implausible, or "" if it is not. Every distance
    is f*B/d: a baseline or focal length that changes by more than max_change (a fraction) between
    two calibrations of the same rig is a different rig or a mistake, and would silently rescale
    every obstacle (half the baseline halves every distance). 0 disables the check."""
    if max_change <= 0:
        return ""
    for what, a, b, unit, k in (("baseline", old.baseline_m, new.baseline_m, "mm", 1000.0),
                                ("focal length", old.focal_px, new.focal_px, "px", 1.0)):
        if abs(b - a) > max_change * abs(a):
            return (f"its {what} {b * k:.2f} {unit} differs from {old_name} ({a * k:.2f} {unit}) by "
                    f"{abs(b - a) / abs(a):.1%}, more than {max_change:.0%}")
    return ""


class CalibrationHolder:
    """The Rectifier in use, and how a new calibration replaces it at run time.

    A new calibration (a message, or the calibration file changed on disk) is loaded and its maps
    built on the caller's thread, away from the frame loop; only a finished Rectifier is published,
    by one reference assignment. The frame loop calls `current()` once per pair and uses that
    object for both images, so a pair is never rectified half with the old and half with the new
    calibration. A calibration that does not load, or whose image size differs from the stream's,
    is logged and refused; the old one stays in use.

    Drift is bounded against the calibration the robot started with (`reference`), never step by
    step: 18 updates of -4 % each pass a step check one by one and halve every distance in the end.
    The reference is the configured calibration (started=True), or else the assumed rig once it
    rectified a frame (`mark_used`), or else the first calibration taken at run time: until then
    there is nothing to drift from.
    """

    def __init__(self, spec: str, alpha: float = 0.0, max_change: float = 0.05, started: bool = True):
        self.alpha = alpha
        self.max_change = max_change
        self.spec = spec
        self._lock = threading.Lock()  # serialises offers (file watcher vs. messages), not frames
        self._rectifier = Rectifier(camera.load_calibration(spec), alpha)
        self.reference: camera.RectifiedModel | None = self._rectifier.model if started else None
        self.reference_name = (self._rectifier.calibration.name or spec) if started else ""
        self._path = Path(spec) if spec not in camera.PROFILES and Path(spec).exists() else None
        self._mtime = self._stat()
        self.stream_size: tuple[int, int] | None = None
        self.stream_source: str | None = None  # StereoFrame.source of the frames seen lately
        self.generation = 0
        self.refused = 0
        self.last_error = ""

    def current(self) -> Rectifier:
        return self._rectifier

    def note_frame(self, width: int, height: int) -> None:
        """The stream's image size, so a calibration for another size can be refused up front."""
        self.stream_size = (int(width), int(height))

    def mark_used(self) -> None:
        """A frame was rectified with the calibration in use: if the robot had no reference yet
        (an assumed rig), this one is what it started with."""
        if self.reference is None:
            with self._lock:
                if self.reference is None:
                    self.reference = self._rectifier.model
                    self.reference_name = self._rectifier.calibration.name or self.spec

    def _refuse(self, origin: str, why: str) -> bool:
        self.refused += 1
        self.last_error = f"{origin}: {why}"
        log.warning("rectify: new calibration from %s refused, keeping '%s': %s", origin,
                    self._rectifier.calibration.name or self.spec, why)
        return False

    def offer(self, cal: camera.Calibration, origin: str) -> bool:
        """Build a Rectifier for `cal` and swap it in; False (and logged) if refused."""
        with self._lock:
            if self.stream_size is not None and tuple(cal.image_size) != self.stream_size:
                return self._refuse(origin, f"field 'image_size' {cal.image_size[0]}x{cal.image_size[1]} differs "
                                            f"from the stream's {self.stream_size[0]}x{self.stream_size[1]}")
            try:
                new = Rectifier(cal, self.alpha)
            except BallbotError as e:
                return self._refuse(origin, str(e))
            except cv2.error as e:
                return self._refuse(origin, f"OpenCV cannot rectify with it: {str(e).strip().splitlines()[-1]}")
            first = self.reference is None
            if self.reference is not None:
                jump = implausible_change(self.reference, new.model, self.max_change,
                                          f"the calibration rectify started with ('{self.reference_name}')")
                if jump:
                    return self._refuse(origin, f"{jump}; a change this large is not applied at run time "
                                                f"(restart rectify with the new calibration if it is right)")
            self._rectifier = new  # the swap: one reference assignment, between two frames
            self.generation += 1
            if first:
                self.reference, self.reference_name = new.model, cal.name or origin
            m = new.model
            log.info("rectify: calibration '%s' from %s in use (f %.2f px, baseline %.2f mm)%s",
                     cal.name or "?", origin, m.focal_px, m.baseline_m * 1000,
                     "; the first one: later ones may differ from it by at most "
                     f"{self.max_change:.0%}" if first and self.max_change > 0 else "")
            return True

    def offer_yaml(self, text: str, origin: str) -> bool:
        from common.errors import FileError
        from common.files import parse_yaml

        try:  # hostile YAML (aliases that expand to millions of values) is refused before it is walked
            doc = parse_yaml(text, "calibration")
        except FileError as e:
            return self._refuse(origin, str(e))
        try:
            cal = camera.calibration_from_dict(doc, where=origin)
        except CalibrationError as e:
            return self._refuse(origin, str(e))
        return self.offer(cal, origin)

    def _stat(self) -> tuple[float, int] | None:
        if self._path is None:
            return None
        try:
            st = os.stat(self._path)
        except OSError:
            return None
        return (st.st_mtime_ns, st.st_size)

    def poll_file(self) -> bool | None:
        """Reload the calibration file if it changed since the last look (mtime or size).
        None: unchanged (or a profile); True: swapped; False: refused."""
        if self._path is None:
            return None
        st = self._stat()
        if st is None or st == self._mtime:
            return None
        self._mtime = st
        try:
            text = self._path.read_text()
        except OSError as e:
            return self._refuse(str(self._path), f"cannot read: {e}")
        return self.offer_yaml(text, str(self._path))
