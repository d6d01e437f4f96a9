"""Live sources: `cameras` (two USB/V4L2 cameras) and `sbs` (one device whose frames hold left and
right side by side). No Zenoh here.

Both go through the `cv2.VideoCapture` interface (isOpened, grab, retrieve, get, set, release), and
the function that opens a device is injectable, so everything here, including unplug and replug,
runs in tests on video files and fakes.

Timing: every device is grab()bed before any is retrieve()d (grab only dequeues a buffer; decoding
happens in retrieve), so the two frames are as close in time as unsynchronised cameras allow. The
skew of a pair is the difference of the two frames' capture times: the V4L2 buffer timestamps
(`camera_skew_clock="driver"`, kernel monotonic clock) when the driver gives them, else the instants the two
grab() calls returned (`"grab"`, a lower bound). Pairs whose skew exceeds `camera_max_skew_ms` are dropped
and counted. Stats extra: skew_ms_p50, skew_ms_max (last 120 pairs), dropped_skew, lost, reconnects.

A device that stops delivering (unplugged, driver error) is reported in the status ("camera
/dev/video1 lost, retrying in 2.0 s"); all devices are closed and reopened with exponential backoff
until they deliver again, then the stream resumes by itself with the same settings. Waiting happens
on the context's stop event, so a stop request ends it at once.
"""
from __future__ import annotations

import glob
import logging
import os
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2

from common.errors import SourceError
from services.capture.sources import CapturedPair, RollingStats, SourceContext, natural_key, split_sbs

if TYPE_CHECKING:
    from services.capture.settings import CaptureSettings

log = logging.getLogger("ballbot.capture")

DEV_DIR = "/dev"
SYS_DIR = "/sys/class/video4linux"

Capture = Any  # anything with the cv2.VideoCapture interface
Opener = Callable[[Any], Capture]


# --- devices -------------------------------------------------------------------------------------

def device_path(spec: Any) -> str:
    """0 or "0" -> "/dev/video0"; a path stays a path."""
    s = str(spec).strip()
    return f"{DEV_DIR}/video{s}" if s.isdigit() else s


def video_devices() -> list[str]:
    """The video device nodes present, with the driver's name for each when known:
    ["/dev/video0 (Microsoft LifeCam Studio)", ...]."""
    out = []
    for dev in sorted(glob.glob(f"{DEV_DIR}/video*"), key=natural_key):
        try:
            label = (Path(SYS_DIR) / Path(dev).name / "name").read_text().strip()
        except OSError:
            label = ""
        out.append(f"{dev} ({label})" if label else dev)
    return out


def devices_hint() -> str:
    devs = video_devices()
    if not devs:
        return (f"no video devices present ({DEV_DIR}/video* matches nothing: is the camera plugged in, "
                f"and in a container, is the device passed in with --device?)")
    return ("video devices present: " + ", ".join(devs)
            + " (a USB camera often shows two nodes; the first of the two captures)")


def open_v4l2(spec: Any) -> cv2.VideoCapture:
    """The default opener: a camera by index (0), path (/dev/video0) or stable link
    (/dev/v4l/by-id/...). Raises SourceError naming the device and listing those present."""
    path = device_path(spec)
    if "://" not in path:  # a device path, not a stream URL
        if not os.path.exists(path):
            raise SourceError(f"camera {path}: no such device; {devices_hint()}")
        if not os.access(path, os.R_OK | os.W_OK):
            raise SourceError(f"camera {path}: permission denied (add the user to the 'video' group)")
    m = re.fullmatch(r"/dev/video(\d+)", os.path.realpath(path))
    if m:  # by index: what every OpenCV V4L2 build supports
        cap = cv2.VideoCapture(int(m.group(1)), cv2.CAP_V4L2 if sys.platform.startswith("linux") else cv2.CAP_ANY)
    else:
        cap = cv2.VideoCapture(path)
    if not cap.isOpened():
        cap.release()
        raise SourceError(f"camera {path}: cannot be opened (busy in another process, or not a capture "
                          f"node); {devices_hint()}")
    return cap


def _fourcc_text(v: float) -> str:
    i = int(v)
    s = "".join(chr((i >> 8 * k) & 0xFF) for k in range(4))
    return s if s.isprintable() and s.strip() else "?"


def configure(cap: Capture, s: CaptureSettings, name: str) -> None:
    """Request format, size, rate, buffers and exposure (the camera_* settings, in the order V4L2
    wants); log what the driver refused or changed. Nothing here is fatal: a camera that cannot do
    30 fps still works."""
    refused = []
    fourcc = "" if s.camera_fourcc == "default" else s.camera_fourcc

    def ask(prop: int, value: float, what: str) -> None:
        try:
            ok = cap.set(prop, value)
        except cv2.error:
            ok = False
        if not ok:
            refused.append(what)

    if fourcc:
        ask(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*fourcc), f"fourcc {fourcc}")
    if s.camera_width and s.camera_height:
        ask(cv2.CAP_PROP_FRAME_WIDTH, s.camera_width, f"width {s.camera_width}")
        ask(cv2.CAP_PROP_FRAME_HEIGHT, s.camera_height, f"height {s.camera_height}")
    if s.camera_fps:
        ask(cv2.CAP_PROP_FPS, s.camera_fps, f"{s.camera_fps:g} fps")
    if s.camera_buffers:
        ask(cv2.CAP_PROP_BUFFERSIZE, s.camera_buffers, f"{s.camera_buffers} buffers")
    if s.camera_exposure is not None:
        ask(cv2.CAP_PROP_AUTO_EXPOSURE, 1, "manual exposure")  # V4L2_EXPOSURE_MANUAL
        ask(cv2.CAP_PROP_EXPOSURE, s.camera_exposure, f"exposure {s.camera_exposure:g}")
    w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    fps, got_fourcc = cap.get(cv2.CAP_PROP_FPS), _fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
    if refused:
        log.warning("camera %s: the driver refused %s", name, ", ".join(refused))
    if s.camera_width and s.camera_height and (w, h) != (s.camera_width, s.camera_height):
        log.warning("camera %s delivers %dx%d, not the requested %dx%d", name, w, h, s.camera_width, s.camera_height)
    log.info("camera %s: %dx%d %s %.1f fps", name, w, h, got_fourcc, fps)


# --- the source ----------------------------------------------------------------------------------

def _secs(s: float) -> str:
    return f"{s:.1f}" if s >= 0.1 else f"{s:.2f}"


class _Device:
    def __init__(self, spec: Any):
        self.spec = spec
        self.name = device_path(spec)
        self.cap: Capture | None = None

    def release(self) -> None:
        if self.cap is not None:
            try:
                self.cap.release()
            except Exception:  # a vanished device may fail to close; it is gone either way
                pass
            self.cap = None


class _Lost(Exception):
    def __init__(self, dev: _Device, why: str):
        super().__init__(why)
        self.dev = dev


class CameraSource:
    """Two cameras (left, right) or, with sbs=True, one device whose frames are split in halves.
    Paced by the devices (period_s = 0). Startup problems raise SourceError (the CLI exits 2);
    later losses are retried forever (see the module docstring)."""

    period_s = 0.0
    ended = False
    SKEW_STATUS_AFTER = 10  # consecutive dropped pairs before the status says so

    def __init__(self, devices: list[Any], settings: CaptureSettings | None = None, ctx: SourceContext | None = None,
                 opener: Opener | None = None, sbs: bool = False):
        if settings is None:
            from services.capture.settings import CaptureSettings

            settings = CaptureSettings(source="sbs" if sbs else "cameras")
        self.settings = settings
        # the backoff doubles from camera_retry_s up to camera_retry_max_s (never below the first delay)
        self._retry_max_s = max(self.settings.camera_retry_max_s, self.settings.camera_retry_s)
        self.ctx = ctx or SourceContext()
        self.sbs = sbs
        self.name = "sbs" if sbs else "cameras"
        if len(devices) != (1 if sbs else 2):
            raise SourceError(f"{self.name}: expected {1 if sbs else 2} device(s), got {len(devices)}")
        self.devs = [_Device(d) for d in devices]
        if not sbs and os.path.realpath(self.devs[0].name) == os.path.realpath(self.devs[1].name):
            raise SourceError(f"cameras: left and right are the same device {self.devs[0].name}")
        # OpenCV's V4L2 grab waits this long for a frame before failing (default 10 s); read once
        os.environ.setdefault("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT", str(max(1, round(self.settings.camera_timeout_s))))
        self.opener = opener or open_v4l2
        self.skew = RollingStats()
        self.dropped_skew = 0
        self._dropping = 0
        self.reconnects = 0
        self.lost = 0
        self._lost_dev: _Device | None = None
        self._backoff = self.settings.camera_retry_s
        self.ctx.extra.update(skew_ms_p50=0.0, skew_ms_max=0.0, dropped_skew=0.0, lost=0.0, reconnects=0.0)
        try:
            self._open_all()
            first = self._read_once()
        except _Lost as e:
            self.close()
            raise SourceError(f"camera {e.dev.name} opened but delivers no frames ({e}); {devices_hint()}") from None
        except BaseException:
            self.close()
            raise
        self.size = first.left.shape
        self._pending: CapturedPair | None = first

    # -- opening --------------------------------------------------------------------------------
    def _open_all(self) -> None:
        for d in self.devs:
            cap = self.opener(d.spec)
            if not cap.isOpened():
                raise SourceError(f"camera {d.name}: cannot be opened; {devices_hint()}")
            d.cap = cap
            configure(cap, self.settings, d.name)

    def _reconnect(self) -> bool:
        """Reopen every device, backing off, until a pair of frames arrives. False when stopped."""
        name = self._lost_dev.name if self._lost_dev else "?"
        t0 = time.monotonic()
        while not self.ctx.stop.wait(self._backoff):
            self.close()
            try:
                for d in self.devs:
                    name = d.name
                    cap = self.opener(d.spec)
                    if not cap.isOpened():
                        raise SourceError("cannot be opened")
                    d.cap = cap
                    configure(cap, self.settings, d.name)
                    if not cap.grab():  # opens but delivers nothing: not back yet
                        raise _Lost(d, "no frame")
            except Exception as e:
                self._backoff = min(self._backoff * 2, self._retry_max_s)
                self.ctx.status(f"camera {name} lost, retrying in {_secs(self._backoff)} s")
                log.debug("camera %s: reconnect failed: %s", name, e)
                continue
            self._lost_dev = None
            self._backoff = self.settings.camera_retry_s
            self.reconnects += 1
            self.ctx.extra.update(lost=0.0, reconnects=float(self.reconnects))
            self.ctx.status("ok")
            log.warning("%s: camera %s is back after %.1f s; capturing again", self.name, name, time.monotonic() - t0)
            return True
        return False

    def _lose(self, lost: _Lost) -> None:
        self.lost += 1
        self._lost_dev = lost.dev
        self._backoff = self.settings.camera_retry_s
        self.close()
        self.ctx.extra["lost"] = 1.0
        self.ctx.status(f"camera {lost.dev.name} lost, retrying in {_secs(self._backoff)} s")
        log.warning("%s: camera %s lost (%s); retrying with backoff", self.name, lost.dev.name, lost)

    # -- reading --------------------------------------------------------------------------------
    def _read_once(self) -> CapturedPair:
        grabbed = []
        caps = []
        for d in self.devs:
            if d.cap is None or not d.cap.grab():
                raise _Lost(d, "grab failed")
            grabbed.append(time.monotonic_ns())
            caps.append((d, d.cap))
        mono, wall = time.monotonic_ns(), time.time_ns()
        times = grabbed
        if self.settings.camera_skew_clock == "driver":
            drv = [cap.get(cv2.CAP_PROP_POS_MSEC) for _, cap in caps]
            # V4L2 buffer timestamps are kernel monotonic ms; anything else (a file position) is not
            if all(0 < t and abs(mono / 1e6 - t) < 5000 for t in drv):
                times = [int(t * 1e6) for t in drv]
        imgs = []
        for d, cap in caps:
            ok, img = cap.retrieve()
            if not ok or img is None:
                raise _Lost(d, "retrieve failed")
            imgs.append(img)
        if self.sbs:
            left, right = split_sbs(imgs[0], f"sbs {self.devs[0].name}")
        else:
            left, right = imgs
            if left.shape[:2] != right.shape[:2]:
                raise SourceError(f"cameras: {self.devs[0].name} delivers {left.shape[1]}x{left.shape[0]} but "
                                  f"{self.devs[1].name} {right.shape[1]}x{right.shape[0]}; set --camera-width/height")
        skew_ms = abs(times[-1] - times[0]) / 1e6
        return CapturedPair(left, right, t_s=times[0] / 1e9, stamp_ns=wall - (mono - times[0]),
                            extra={"skew_ms": skew_ms})

    def read(self) -> CapturedPair | None:
        while not self.ctx.stop.is_set():
            if self._lost_dev is not None and not self._reconnect():
                return None
            if self._pending is not None:
                pair, self._pending = self._pending, None
            else:
                try:
                    pair = self._read_once()
                except _Lost as e:
                    self._lose(e)
                    continue
            skew = pair.extra["skew_ms"]
            self.skew.add(skew)
            self.ctx.extra.update(skew_ms_p50=self.skew.p50(), skew_ms_max=self.skew.max())
            if not self.sbs and skew > self.settings.camera_max_skew_ms:
                self.dropped_skew += 1
                self._dropping += 1
                self.ctx.extra["dropped_skew"] = float(self.dropped_skew)
                if self._dropping == self.SKEW_STATUS_AFTER:
                    self.ctx.status(f"dropping pairs: left/right skew {skew:.1f} ms > "
                                    f"{self.settings.camera_max_skew_ms:g} ms")
                continue
            if self._dropping >= self.SKEW_STATUS_AFTER:
                self.ctx.status("ok")
            self._dropping = 0
            return pair
        return None

    def close(self) -> None:
        for d in self.devs:
            d.release()
