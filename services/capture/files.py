"""File sources: `images` (two folders or glob patterns of left/right images, paired by sorted
name) and `video` (two video files, or one side-by-side video). No Zenoh here.

End of stream: when the files are exhausted and `loop` is off, read() returns None and `ended`
is set; the capture service then reports status "end of stream" and stays up, idle, until it is
stopped (exit status 0), so `ballbot-vision up` never restarts it into a loop and the other
services see the stream end (their inputs go stale) rather than a crash.
"""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import cv2
import numpy as np

from common import files
from common.errors import FileError, SourceError
from services.capture.sources import CapturedPair, SourceContext, split_sbs

log = logging.getLogger("ballbot.capture")


# --- images ----------------------------------------------------------------------------------------

def list_images(spec: str, side: str, label: str = "") -> list[Path]:
    """A folder (every image file in it) or a glob pattern ('left/*.png', 'data/**/im0.png') ->
    files in natural sort order (img2 before img10). Errors name `label` (default: the capture
    setting, --images-left)."""
    try:
        return files.list_images(spec, label or f"images: --images-{side}")
    except FileError as e:
        raise SourceError(str(e)) from None


def read_image(path: Path) -> np.ndarray:
    """One image file -> (H, W) uint8 grey or (H, W, 3) uint8 BGR (alpha dropped, 16 bit scaled);
    a missing, truncated, corrupt or impossibly sized file is a SourceError naming it."""
    try:
        return files.read_image(path, "image")
    except FileError as e:
        raise SourceError(str(e)) from None


class ImageSource:
    """Left/right image files paired by sorted name, at `rate_hz` (or as fast as possible).

    At open: both lists must have the same count, must not share files, and the first pair must
    read and agree in size, else SourceError (the CLI exits 2). Later, an unreadable file or a pair
    whose size differs raises SourceError naming the file(s); the service drops that pair and goes on.
    """

    name = "images"

    def __init__(self, left: str, right: str, rate_hz: float = 30.0, loop: bool = False,
                 max_rate: bool = False, ctx: SourceContext | None = None, labels: tuple[str, str] = ("", "")):
        """labels: how errors name the two arguments (default: capture's --images-left/right)."""
        self.ctx = ctx or SourceContext()
        self.left_files = list_images(left, "left", labels[0])
        self.right_files = list_images(right, "right", labels[1])
        nl, nr = len(self.left_files), len(self.right_files)
        if nl != nr:
            n = min(nl, nr)
            extra = (self.left_files if nl > nr else self.right_files)[n]
            raise SourceError(f"images: {nl} left images ({left}) but {nr} right images ({right}); "
                              f"the first without a partner is {extra}")
        shared = sorted(set(map(os.path.realpath, self.left_files)) & set(map(os.path.realpath, self.right_files)))
        if shared:
            raise SourceError(f"images: {len(shared)} file(s) are both left and right images, e.g. {shared[0]}; "
                              f"give two folders or two patterns that select different files")
        self.loop = loop
        self.period_s = 0.0 if max_rate else 1.0 / rate_hz
        self.ended = False
        self.index = 0
        self.size: tuple[int, ...] | None = None
        first = self._read(0)  # fail at start, not after the pipeline is up
        self.size = first.left.shape
        self._pending: CapturedPair | None = first
        self.ctx.extra.update({"pairs_total": float(nl)})

    def __len__(self) -> int:
        return len(self.left_files)

    def _read(self, i: int) -> CapturedPair:
        lf, rf = self.left_files[i], self.right_files[i]
        left, right = read_image(lf), read_image(rf)
        if left.shape != right.shape:
            raise SourceError(f"images: {lf} is {_shape(left)} but its partner {rf} is {_shape(right)}")
        if self.size is not None and left.shape != self.size:
            raise SourceError(f"images: {lf} and {rf} are {_shape(left)}, the earlier pairs {_shape_t(self.size)}")
        return CapturedPair(left, right, t_s=i * self.period_s, stamp_ns=time.time_ns(),
                            extra={"index": float(i)})

    def read(self) -> CapturedPair | None:
        if self._pending is not None:
            pair, self._pending = self._pending, None
            self.index = 1
            return pair
        if self.index >= len(self.left_files):
            if not self.loop:
                self.ended = True
                return None
            self.index = 0
        i = self.index
        self.index += 1  # advance first: a bad file is skipped, not retried forever
        return self._read(i)

    def close(self) -> None:
        pass


def _shape(a: np.ndarray) -> str:
    return _shape_t(a.shape)


def _shape_t(s: tuple[int, ...]) -> str:
    return f"{s[1]}x{s[0]} " + ("grey" if len(s) == 2 else "BGR")


# --- video -----------------------------------------------------------------------------------------

def open_video(path: str) -> cv2.VideoCapture:
    p = Path(os.path.expanduser(path))
    if not path:
        raise SourceError("video: no file given (--video-left)")
    if not p.exists():
        raise SourceError(f"video {path}: no such file")
    if not p.is_file():
        raise SourceError(f"video {path}: not a regular file")
    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        raise SourceError(f"video {path}: OpenCV cannot open it (not a video, or a codec this build lacks)")
    return cap


class VideoSource:
    """Two video files played side by side in step, or one side-by-side (double-width) file split
    in two. Paced at the file's frame rate (`pace="file"`), at `rate_hz` ("rate") or as fast as
    frames decode ("max"). At the end: start again if `loop`, else end of stream. If one file is
    shorter, the stream ends (or loops) with it."""

    name = "video"

    def __init__(self, left: str, right: str = "", pace: str = "file", rate_hz: float = 30.0,
                 loop: bool = False, ctx: SourceContext | None = None, name: str = "video"):
        self.name = name
        self.ctx = ctx or SourceContext()
        self.paths = [left] + ([right] if right else [])
        self.sbs = not right
        self.loop = loop
        self.ended = False
        self.frames = 0  # pairs read since the (re)start
        self.caps: list[cv2.VideoCapture] = []
        self._open()
        fps = [c.get(cv2.CAP_PROP_FPS) for c in self.caps]
        counts = [int(c.get(cv2.CAP_PROP_FRAME_COUNT)) for c in self.caps]
        self.fps = fps[0] if 0 < fps[0] <= 1000 else 0.0
        if len(fps) == 2 and abs(fps[0] - fps[1]) > 0.01 * max(fps):
            log.warning("video: %s is %.3f fps but %s is %.3f fps; playing them frame by frame together",
                        left, fps[0], right, fps[1])
        if len(counts) == 2 and counts[0] > 0 and counts[1] > 0 and counts[0] != counts[1]:
            log.warning("video: %s has %d frames, %s has %d; the stream ends with the shorter",
                        left, counts[0], right, counts[1])
        if pace == "max":
            self.period_s = 0.0
        elif pace == "file" and self.fps:
            self.period_s = 1.0 / self.fps
        else:
            self.period_s = 1.0 / rate_hz
        first = self._grab()  # decodable, same size: checked before anything is published
        if first is None:
            raise SourceError(f"video {self.paths[0]}: holds no frame OpenCV can decode")
        self.size = first.left.shape
        self._pending: CapturedPair | None = first

    def _open(self) -> None:
        self.close()
        self.caps = [open_video(p) for p in self.paths]
        self.frames = 0

    def _grab(self) -> CapturedPair | None:
        """Next pair, or None when a file ends (naming it in the log)."""
        for cap, path in zip(self.caps, self.paths):
            if not cap.grab():
                log.info("video %s ended after %d frames", path, self.frames)
                return None
        stamp = time.time_ns()
        pos_s = self.caps[0].get(cv2.CAP_PROP_POS_MSEC) / 1e3
        imgs = []
        for cap, path in zip(self.caps, self.paths):
            ok, img = cap.retrieve()
            if not ok or img is None:
                raise SourceError(f"video {path}: frame {self.frames} does not decode")
            imgs.append(img)
        if self.sbs:
            left, right = split_sbs(imgs[0], f"video {self.paths[0]}")
        else:
            left, right = imgs
            if left.shape != right.shape:
                raise SourceError(f"video: {self.paths[0]} is {_shape(left)} but {self.paths[1]} is {_shape(right)}")
        if getattr(self, "size", None) is not None and left.shape != self.size:
            raise SourceError(f"video {self.paths[0]}: frame {self.frames} is {_shape(left)}, "
                              f"earlier frames {_shape_t(self.size)}")
        self.frames += 1
        return CapturedPair(left, right, t_s=pos_s, stamp_ns=stamp, extra={"frame": float(self.frames - 1)})

    def read(self) -> CapturedPair | None:
        if self._pending is not None:
            pending, self._pending = self._pending, None
            return pending
        if self.ended:
            return None
        pair = self._grab()
        if pair is None and self.loop and self.frames:
            self._open()
            self.ctx.extra["loops"] = self.ctx.extra.get("loops", 0.0) + 1
            pair = self._grab()
        if pair is None:
            self.ended = True
        return pair

    def close(self) -> None:
        for c in self.caps:
            c.release()
        self.caps = []
