"""`calibrate`, `calibration {import,show,check}` and `rectify`: the calibration and rectification
commands (registered through cli.py's COMMAND_MODULES hook). The work is done by
cores/calibration/ (calibrate, report, formats, check, rectify); this module only parses and prints
(calibrate --live's Zenoh loop: calibration_live.py)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from common.errors import BallbotError, CalibrationError


def _out(text: str = "") -> None:
    print(text, flush=True)


def _depth_range(v: list[float] | None) -> tuple[float, float] | None:
    if not v:
        return None
    near, far = v
    if not (0 < near < far):
        raise CalibrationError(f"--depth-range {near} {far}: expected 0 < NEAR < FAR (metres)")
    return near, far


def _pairs_from(left: str, right: str) -> list[tuple[Path, Path]]:
    from common.files import list_images, pair_images

    return pair_images(list_images(left, "LEFT"), list_images(right, "RIGHT"))


def _read(path: Path, rectifier=None):
    """One image file; with a rectifier, also checked against the calibrated size, naming the file."""
    from common.files import read_image

    img = read_image(path)
    if rectifier is not None:
        rectifier.check_size(img, str(path))
    return img


# --- calibrate ---------------------------------------------------------------------------------

def cmd_calibrate(args: argparse.Namespace) -> int:
    from cores import camera
    from cores.calibration import calibrate as C
    from cores.calibration.check import row_alignment
    from cores.calibration.rectify import Rectifier
    from cores.calibration.report import format_report

    pattern = C.parse_pattern(args.pattern)
    depth = _depth_range(args.depth_range)
    if args.square_size is None or args.square_size <= 0:
        raise CalibrationError("--square-size: give the chessboard's square size in metres (e.g. 0.025)")
    if args.live:
        if args.left or args.right or args.pairs:
            raise CalibrationError("--live collects views from a running capture: leave out --left/--right/--pairs")
        from ballbot_vision.calibration_live import collect_live

        pairs = collect_live(args, pattern, _out)
    else:
        pairs = C.find_pairs(args.left, args.right, args.pairs)
    _out(f"calibrate: {len(pairs)} image pairs, pattern {pattern[0]}x{pattern[1]} inner corners, "
         f"square {args.square_size * 1000:g} mm, skew {'fixed at 0' if args.fix_skew else 'free'}, "
         f"k3 {'free' if args.k3 else 'fixed at 0'}")
    result = C.calibrate_stereo(pairs, pattern, args.square_size, fix_skew=args.fix_skew, k3=args.k3,
                                refine_intrinsics=args.refine_intrinsics, min_views=args.min_views,
                                max_view_rms=args.max_view_rms, reject_outliers=not args.keep_outliers,
                                progress=_out, name=args.name or Path(args.output).stem)
    _out()
    _out(format_report(result, depth, args.alpha))
    camera.save_calibration(result.rig, args.output)
    _out()
    _out(f"wrote {args.output}")
    v = result.views[0]
    try:
        r = Rectifier(result.rig, args.alpha)
        rl, rr = r.rectify(_read(v.left_path, r), _read(v.right_path, r))
        _out(f"{v.name}: " + row_alignment(rl, rr).format())
    except BallbotError as e:
        _out(f"{v.name}: rectification check not possible: {e}")
    if args.publish:
        _out()
        return publish_calibration(args, args.output)
    return 0


# --- calibration publish -------------------------------------------------------------------------

def _publish_key(args: argparse.Namespace, rid: str) -> bytes:
    from common.signing import KEY_ENV, KEY_FILE_ENV, calibration_key, read_key_file, run_key_path

    if args.key_file:
        try:
            return read_key_file(args.key_file)
        except OSError as e:
            raise BallbotError(f"--key-file {args.key_file}: {e.strerror or e}") from None
        except ValueError as e:
            raise BallbotError(f"--key-file {e}") from None
    key = calibration_key(rid)
    if key is None:
        raise BallbotError(f"no calibration key to sign with: rectify takes only calibrations signed with the "
                           f"robot's key. Give it with --key-file FILE, {KEY_ENV} or {KEY_FILE_ENV} (a deployment's "
                           f"is in its .env); `ballbot-vision up` keeps its per-run key in {run_key_path(rid)}")
    return key


def publish_calibration(args: argparse.Namespace, path: str) -> int:
    """Sign a calibration with the robot's key and publish it on the calibration key; report whether
    rectify took it (its stats count calibrations taken and refused). Exit 0 taken, 1 not."""
    import threading
    import time

    import yaml

    from ballbot_vision.cli import robot_id, zenoh_options
    from common import codec
    from common.errors import DecodeError
    from common.keys import topic
    from common.messages import CalibrationUpdate, ServiceStats
    from common.signing import sign
    from common.zenoh_session import open_session
    from cores import camera

    rid = robot_id(args)
    cal = camera.load_calibration(path)  # a file rectify could not load is refused here, naming it
    key = _publish_key(args, rid)
    text = yaml.safe_dump(camera.calibration_to_dict(cal), sort_keys=False)
    counts: dict[str, tuple[float, float]] = {}  # rectify instance -> (taken, refused)
    changed = threading.Condition()

    def on_stats(sample) -> None:
        try:
            st = codec.decode(sample.payload.to_bytes(), ServiceStats)
        except DecodeError:
            return
        with changed:
            counts[st.instance] = (st.extra.get("calibration_generation", 0.0),
                                   st.extra.get("calibration_refused", 0.0))
            changed.notify_all()

    def wait(pred, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with changed:
            while not pred():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                changed.wait(min(left, 0.2))
            return True

    with open_session(zenoh_options(args)) as session:
        session.declare_subscriber(topic("stats").key(rid, service="rectify", instance="*"), on_stats)
        if not wait(lambda: bool(counts), args.timeout):
            raise BallbotError(f"no rectify of robot '{rid}' reports within {args.timeout:g} s (is the pipeline up, "
                               f"and --connect / --robot-id right?)")
        with changed:
            before = dict(counts)
        pub = session.declare_publisher(topic("calibration").key(rid))
        # (zenoh's stub says matching_status is a bool; it is a MatchingStatus)
        wait(lambda: pub.matching_status.matching, args.timeout)  # type: ignore[attr-defined]
        msg = sign(CalibrationUpdate(robot_id=rid, seq=0, stamp_ns=time.time_ns(), yaml=text,
                                     source=f"calibration publish {path}"), key)
        pub.put(codec.encode(msg))

        def outcome() -> dict[str, str]:
            out = {}
            for inst, (g, r) in counts.items():
                g0, r0 = before.get(inst, (g, r))
                if g > g0:
                    out[inst] = "taken"
                elif r > r0:
                    out[inst] = "refused"
            return out

        wait(lambda: len(outcome()) >= len(before), args.timeout)
        with changed:
            result = outcome()
    if not result:
        print(f"published {path} (signed) to robot '{rid}'; no rectify reported taking or refusing it within "
              f"{args.timeout:g} s", file=sys.stderr)
        return 1
    for inst, what in sorted(result.items()):
        _out(f"rectify {inst}: {what} {path}" + ("" if what == "taken" else " (its log says why: e.g. the baseline or "
                                                  "focal length moved more than calibration_max_change from the one "
                                                  "it started with, or another image size)"))
    return 0 if all(v == "taken" for v in result.values()) else 1


# --- calibration import / show / check ---------------------------------------------------------

def cmd_import(args: argparse.Namespace) -> int:
    from cores import camera
    from cores.calibration import formats as F

    size = F.parse_size(args.image_size) if args.image_size else None
    rig = F.import_files(args.files, args.units_m, size, args.name or Path(args.output).stem,
                         tuple(args.cameras) if args.cameras else None)
    camera.save_calibration(rig, args.output)
    _out(F.describe(rig))
    _out(f"wrote {args.output}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from cores import camera
    from cores.calibration import formats as F

    cal = camera.load_calibration(args.calibration)
    if not isinstance(cal, camera.RawRig):
        raise CalibrationError(f"{args.calibration}: an already-rectified calibration has no raw rig to export")
    a, b = args.files
    if args.format == "ros":
        F.write_ros_pair(cal, a, b, args.alpha)
    else:
        F.write_stereo_calib(cal, a, b, args.units_m, args.alpha)
    _out(f"wrote {a} and {b}")
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    from cores import camera
    from cores.calibration import formats as F

    _out(F.describe(camera.load_calibration(args.calibration), _depth_range(args.depth_range), args.alpha))
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    import numpy as np

    from cores import camera
    from cores.calibration.check import row_alignment
    from cores.calibration.rectify import Rectifier

    r = Rectifier(camera.load_calibration(args.calibration), args.alpha)
    medians = []
    for lp, rp in _pairs_from(args.left, args.right):
        rl, rr = r.rectify(_read(lp, r), _read(rp, r))
        try:
            c = row_alignment(rl, rr)
        except BallbotError as e:
            _out(f"{lp.name} {rp.name}: {e}")
            continue
        medians.append(c.median_dy)
        _out(f"{lp.name} {rp.name}: {c.format()}")
    if not medians:
        raise BallbotError("rectification check: no pair gave enough matches")
    if len(medians) > 1:
        _out(f"over {len(medians)} pairs: median of the median |dy| {float(np.median(medians)):.3f} px")
    return 0


# --- rectify (offline) -------------------------------------------------------------------------

def cmd_rectify(args: argparse.Namespace) -> int:
    from common.files import write_image
    from cores import camera
    from cores.calibration.rectify import Rectifier

    r = Rectifier(camera.load_calibration(args.calibration), args.alpha)
    pairs = _pairs_from(args.left, args.right)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    lstems = {p.stem for p, _ in pairs}
    rstems = {p.stem for _, p in pairs}
    split = bool(lstems & rstems)  # same names on both sides: left/ and right/ subfolders
    if split:
        (out / "left").mkdir(exist_ok=True)
        (out / "right").mkdir(exist_ok=True)
    for lp, rp in pairs:
        rl, rr = r.rectify(_read(lp, r), _read(rp, r))
        for src, img, side in ((lp, rl, "left"), (rp, rr, "right")):
            dst = (out / side / f"{src.stem}.png") if split else (out / f"{src.stem}.png")
            write_image(dst, img)
        _out(f"{lp} {rp} -> {out}")
    m = r.model
    _out(f"rectified {len(pairs)} pair(s): f = {m.focal_px:.3f} px, baseline = {m.baseline_m * 1000:.3f} mm, "
         f"cc = [{m.cx:.2f} {m.cy:.2f}], {m.width}x{m.height}")
    return 0


# --- parser ------------------------------------------------------------------------------------

def _publish_arguments(p: argparse.ArgumentParser, publish_help: str | None) -> None:
    g = p.add_argument_group("publishing to a running rectify (Zenoh options below)")
    if publish_help:
        g.add_argument("--publish", action="store_true", help=publish_help)
    g.add_argument("--key-file", default=None, metavar="FILE",
                   help="the robot's calibration key (default: BALLBOT_CALIBRATION_KEY, BALLBOT_CALIBRATION_KEY_FILE, "
                        "or the key file of `up`)")
    # calibrate --live already has a --timeout of its own (frames); publishing shares it
    if publish_help is None:
        g.add_argument("--timeout", type=float, default=10.0, metavar="S",
                       help="wait this long for rectify to report (default: 10)")

def register(sub: argparse._SubParsersAction, common) -> None:
    c = sub.add_parser("calibrate", help="chessboard image pairs -> calibration YAML, with an RMS report",
                       description="Detect a chessboard in left/right image pairs (files, or --live from a "
                                   "running capture), calibrate each camera and the pair, reject outlier views, "
                                   "and write the calibration YAML.")
    src = c.add_argument_group("images")
    src.add_argument("--left", help="left images: a glob ('dir/left*.jpg') or a folder")
    src.add_argument("--right", help="right images: a glob or a folder (paired by name, else by sorted order)")
    src.add_argument("--pairs", metavar="DIR", help="a folder with *left* and *right* images, or left/ and right/")
    live = c.add_argument_group("live (from a running capture's raw frames; Zenoh options below)")
    live.add_argument("--live", action="store_true",
                      help="collect views from the running capture instead of image files; prints which image "
                           "cells and tilts are still missing after each accepted view")
    live.add_argument("--views", type=int, default=20, help="--live: stop after this many views (default: 20)")
    live.add_argument("--save-dir", default=None, metavar="DIR",
                      help="--live: save accepted pairs here as PNG (default: a new temporary folder, printed)")
    live.add_argument("--timeout", type=float, default=10.0, metavar="S",
                      help="--live: give up when no frame arrives for S seconds (default: 10)")
    c.add_argument("--pattern", default="9x6", help="inner corners per row x per column (default: 9x6)")
    c.add_argument("--square-size", type=float, default=None, metavar="M", help="square size in metres (required)")
    skew = c.add_mutually_exclusive_group()
    skew.add_argument("--fix-skew", dest="fix_skew", action="store_true", default=True,
                      help="keep the skew at 0 (default)")
    skew.add_argument("--free-skew", dest="fix_skew", action="store_false", help="estimate the skew too")
    c.add_argument("--k3", action="store_true", help="estimate the third radial term k3 (default: fixed at 0)")
    c.add_argument("--refine-intrinsics", action="store_true",
                   help="let the stereo fit refine the intrinsics (default: fixed from the per-camera fits)")
    c.add_argument("--min-views", type=int, default=6, help="fewest usable pairs (default: 6)")
    c.add_argument("--max-view-rms", type=float, default=1.0, metavar="PX",
                   help="a view above this RMS is always rejected (default: 1.0)")
    c.add_argument("--keep-outliers", action="store_true", help="do not reject outlier views")
    c.add_argument("--depth-range", type=float, nargs=2, default=[0.5, 3.0], metavar=("NEAR", "FAR"),
                   help="report the disparity range for this depth range in metres (default: 0.5 3)")
    c.add_argument("--alpha", type=float, default=0.0, help="rectification crop: 0 valid pixels only, 1 all")
    c.add_argument("--name", default=None, help="calibration name (default: the output's stem)")
    c.add_argument("-o", "--output", default="calib.yaml", help="calibration YAML to write (default: calib.yaml)")
    _publish_arguments(c, "then sign the result with the robot's calibration key and publish it to the running "
                          "rectify (as `calibration publish`)")
    common(c)
    c.set_defaults(func=cmd_calibrate)

    cal = sub.add_parser("calibration", help="import, export, show or check a calibration")
    cs = cal.add_subparsers(dest="calibration_command", required=True, metavar="ACTION")
    i = cs.add_parser("import", help="another tool's calibration -> calibration YAML (Kalibr camchain, "
                                     "EuRoC sensor.yaml pair, ROS camera_info pair, OpenCV stereo_calib)",
                      description="Convert another tool's stereo calibration into this program's raw-rig YAML, "
                                  "checked as every command checks it on loading. Accepted: a Kalibr camchain.yaml "
                                  "(one file); EuRoC cam0/sensor.yaml + cam1/sensor.yaml (left first); ROS "
                                  "camera_info left.yaml + right.yaml; OpenCV stereo_calib intrinsics.yml + "
                                  "extrinsics.yml (with --image-size).")
    i.add_argument("files", nargs="+", metavar="FILE")
    i.add_argument("--cameras", nargs=2, metavar=("LEFT", "RIGHT"), default=None,
                   help="Kalibr camchain: the two cameras of the chain to use (default: cam0 cam1)")
    i.add_argument("-o", "--output", required=True, help="calibration YAML to write")
    i.add_argument("--units-m", type=float, default=1.0,
                   help="stereo_calib: metres per unit of T (the sample uses square-size units; default 1)")
    i.add_argument("--image-size", default=None, metavar="WxH", help="stereo_calib: image size (not in its files)")
    i.add_argument("--name", default=None)
    i.set_defaults(func=cmd_import)

    e = cs.add_parser("export", help="calibration -> ROS camera_info pair or OpenCV stereo_calib pair")
    e.add_argument("calibration", metavar="CAL", help="calibration YAML or built-in profile")
    e.add_argument("files", nargs=2, metavar="FILE", help="left.yaml right.yaml (ros) or intrinsics.yml "
                                                          "extrinsics.yml (opencv)")
    e.add_argument("--format", choices=["ros", "opencv"], default="ros")
    e.add_argument("--units-m", type=float, default=1.0, help="opencv: metres per unit of the written T")
    e.add_argument("--alpha", type=float, default=0.0)
    e.set_defaults(func=cmd_export)

    s = cs.add_parser("show", help="print a calibration (file or built-in profile, e.g. lifecam-studio)")
    s.add_argument("calibration", metavar="CAL")
    s.add_argument("--depth-range", type=float, nargs=2, default=[0.5, 3.0], metavar=("NEAR", "FAR"))
    s.add_argument("--alpha", type=float, default=0.0)
    s.set_defaults(func=cmd_show)

    pb = cs.add_parser("publish", help="sign a calibration with the robot's key and send it to the running rectify",
                       description="Rectify takes a calibration at run time only when it is signed with the robot's "
                                   "calibration key, and only within calibration_max_change of the one it started "
                                   "with (restart it for a larger change). The key: --key-file, "
                                   "BALLBOT_CALIBRATION_KEY, BALLBOT_CALIBRATION_KEY_FILE, or the per-run key file "
                                   "of `ballbot-vision up` for this robot id. Exit 0 once every rectify took it.")
    pb.add_argument("calibration", metavar="CAL", help="calibration YAML or built-in profile")
    _publish_arguments(pb, None)
    common(pb)
    pb.set_defaults(func=lambda a: publish_calibration(a, a.calibration))

    k = cs.add_parser("check", help="vertical offset of ORB matches after rectification (median, 95th pct.)")
    k.add_argument("left", metavar="LEFT", help="left image, glob or folder")
    k.add_argument("right", metavar="RIGHT", help="right image, glob or folder")
    k.add_argument("--calibration", required=True, metavar="CAL")
    k.add_argument("--alpha", type=float, default=0.0)
    k.set_defaults(func=cmd_check)

    r = sub.add_parser("rectify", help="offline: rectify image pairs with a calibration")
    r.add_argument("left", metavar="LEFT", help="left image, glob or folder")
    r.add_argument("right", metavar="RIGHT", help="right image, glob or folder")
    r.add_argument("--calibration", required=True, metavar="CAL")
    r.add_argument("--alpha", type=float, default=0.0)
    r.add_argument("-o", "--output", required=True, metavar="DIR")
    r.set_defaults(func=cmd_rectify)


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use: ballbot-vision calibrate | calibration | rectify")
