"""`calibrate --live`: chessboard views collected from the raw frames of a running capture (the
Zenoh loop; which views to keep is cores/calibration/views.py's, the calibration the calibrate
command's)."""
from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from common.errors import CalibrationError


def collect_live(args: argparse.Namespace, pattern: tuple[int, int],
                 say: Callable[[str], None]) -> list[tuple[Path, Path]]:
    """Collect chessboard views from the raw frames of a running capture until --views are accepted,
    the stream stalls, or Ctrl-C; save each accepted pair as PNG; return the saved pairs. The
    choice of views is cores/calibration/views.py's; this is only the Zenoh loop around it."""
    import tempfile
    import time

    import cv2

    from ballbot_vision.cli import robot_id, zenoh_options
    from common import codec
    from common.errors import DecodeError
    from common.inbox import Inbox, stamp_of
    from common.keys import topic
    from common.messages import StereoFrame
    from common.zenoh_session import open_session
    from cores.calibration import calibrate as C
    from cores.calibration.views import Coverage

    if args.views < 1:
        raise CalibrationError(f"--views {args.views}: must be at least 1")
    if args.timeout <= 0:
        raise CalibrationError(f"--timeout {args.timeout}: must be positive (seconds)")
    if args.save_dir:
        save_dir = Path(args.save_dir)
        save_dir.mkdir(parents=True, exist_ok=True)
    else:
        save_dir = Path(tempfile.mkdtemp(prefix="ballbot-calib-"))
    rid = robot_id(args)
    t = topic("frames_raw")
    key = t.key(rid)
    say(f"calibrate --live: collecting {args.views} views of a {pattern[0]}x{pattern[1]} board from {key}; "
         f"accepted pairs are saved in {save_dir}; Ctrl-C stops and calibrates with what was collected")
    inbox = Inbox(t)  # newest wins: frames that arrive while a pair is being searched are skipped
    pairs: list[tuple[Path, Path]] = []
    cov: Coverage | None = None
    size: tuple[int, int] | None = None
    frames = 0
    fast = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    with open_session(zenoh_options(args)) as session:
        sub = session.declare_subscriber(key, lambda s: inbox.offer(s.payload.to_bytes(), stamp_of(s.attachment)))
        last = time.monotonic()
        try:
            while len(pairs) < args.views:
                payload = inbox.take(0.2)
                if payload is None:
                    if time.monotonic() - last < args.timeout:
                        continue
                    if frames == 0:
                        raise CalibrationError(f"no frames on {key} within {args.timeout:g} s: is capture running "
                                               f"and --connect right?")
                    say(f"no frames on {key} for {args.timeout:g} s: the stream stopped; "
                         f"stopping with {len(pairs)} views")
                    break
                last = time.monotonic()
                try:
                    msg = codec.decode(payload, StereoFrame)
                    left = codec.array_from_image(msg.left, "left")
                    right = codec.array_from_image(msg.right, "right")
                except DecodeError as e:
                    say(f"skipping an undecodable frame: {e}")
                    continue
                frames += 1
                if left.shape != right.shape:
                    raise CalibrationError(f"frame {msg.seq}: left is {left.shape[1]}x{left.shape[0]} but right is "
                                           f"{right.shape[1]}x{right.shape[0]}")
                s = (left.shape[1], left.shape[0])
                if size is None:
                    size = s
                    cov = Coverage(pattern, size)
                elif s != size:
                    raise CalibrationError(f"frame {msg.seq}: image size changed from {size[0]}x{size[1]} "
                                           f"to {s[0]}x{s[1]}")
                gl = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY) if left.ndim == 3 else left
                gr = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY) if right.ndim == 3 else right
                if gl.dtype != "uint8":
                    gl = cv2.convertScaleAbs(gl, alpha=255.0 / max(float(gl.max()), 1.0))
                    gr = cv2.convertScaleAbs(gr, alpha=255.0 / max(float(gr.max()), 1.0))
                # a cheap look first: most live frames of someone walking around hold no full board
                if not cv2.findChessboardCorners(gl, pattern, flags=fast)[0]:
                    continue
                cl = C.detect_corners(gl, pattern)
                cr = C.detect_corners(gr, pattern) if cl is not None else None
                if cl is None or cr is None:
                    continue
                if cov is None:  # (set with the first frame's size above)
                    continue
                ok, why = cov.consider(cl, C._same_order(cl, cr))
                if not ok:
                    continue
                n = len(pairs) + 1
                lp, rp = save_dir / f"left{n:02d}.png", save_dir / f"right{n:02d}.png"
                for path, img in ((lp, left), (rp, right)):
                    if not cv2.imwrite(str(path), img):
                        raise CalibrationError(f"{path}: cannot write the image (--save-dir {save_dir})")
                pairs.append((lp, rp))
                say(f"view {n}/{args.views} accepted (frame {msg.seq}, {why}); {cov.summary()}")
        except KeyboardInterrupt:
            say(f"\nstopped: {len(pairs)} views collected")
        finally:
            try:
                sub.undeclare()
            except Exception:  # the session is closing anyway
                pass
    say(f"collected {len(pairs)} views from {frames} frames; saved in {save_dir}")
    if len(pairs) < args.min_views:
        raise CalibrationError(f"only {len(pairs)} views with the board in both images were collected; at least "
                               f"--min-views {args.min_views} are needed (the pairs are saved in {save_dir})")
    return pairs
