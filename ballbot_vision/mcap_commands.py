"""`record`, `mcap info / from-images / to-images` and `replay play / pause / step`: recordings
(registered through cli.py's COMMAND_MODULES hook). The work is done by services/recorder/ and
services/capture/mcap_source.py; this module parses and prints."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from common.codec import MIN_JPEG_QUALITY
from common.errors import BallbotError


def _need_mcap() -> None:
    """Before anything starts (exit status 3, common/errors.py MissingDependency)."""
    from common.errors import require

    require(("mcap",), "record", "recordings")


# --- record ------------------------------------------------------------------------------------

RECORDINGS = "recordings"  # where `record` without a name writes (git-ignored, as is every *.mcap)


def default_recording_path(robot: str, now: float | None = None) -> Path:
    """recordings/<robot>-<local date and time>.mcap: one predictable folder, names that sort by time."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
    return Path(RECORDINGS) / f"{robot}-{stamp}.mcap"


def cmd_record(args: argparse.Namespace) -> int:
    from ballbot_vision.cli import config_file, robot_id, zenoh_options
    from common.node import Node
    from common.settings import load_settings
    from services.recorder.main import RecordSettings, record
    from services.rectify.main import RectifySettings

    _need_mcap()
    settings = load_settings(RecordSettings, config_file(args), args)
    calibration = settings.calibration or load_settings(RectifySettings, config_file(args)).calibration
    out = Path(args.output) if args.output else default_recording_path(robot_id(args))
    if out.suffix.lower() != ".mcap":
        raise BallbotError(f"{out}: a recording's name ends in .mcap")
    if not out.parent.exists():  # recordings/ the first time (a file in the way: the writer's one-line error)
        out.parent.mkdir(parents=True)
    with Node("record", zenoh_options(args), robot_id(args)) as node:
        print(f"recording to {out} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        result = record(node, settings, out, calibration)
    print(result.summary(), file=sys.stderr, flush=True)
    return 0


# --- mcap info / from-images / to-images -------------------------------------------------------

def cmd_info(args: argparse.Namespace) -> int:
    from cores.recording_reader import RecordingReader

    _need_mcap()
    info = RecordingReader(args.recording).info()
    if args.json:
        print(json.dumps({"path": info.path, "complete": info.complete, "duration_s": info.duration_s,
                          "start_ns": info.start_ns, "end_ns": info.end_ns, "raw_pairs": info.pairs("raw"),
                          "rectified_pairs": info.pairs("rectified"), "channels": info.channels,
                          "metadata": info.metadata}, indent=2))
        return 0
    print(f"{info.path}: {info.duration_s:.2f} s, {info.pairs('raw')} raw pairs, "
          f"{info.pairs('rectified')} rectified pairs{'' if info.complete else ' (NO INDEX: writer was killed)'}")
    for t, n in sorted(info.channels.items()):
        print(f"  {t:34} {n:7d}")
    return 0


def _stamps_from_names(files: list[Path]) -> list[int] | None:
    """Image names that are nanosecond timestamps (EuRoC: 1403715275262142976.png) -> stamps."""
    try:
        stamps = [int(f.stem) for f in files]
    except ValueError:
        return None
    ok = all(s > 10**17 for s in stamps) and all(b > a for a, b in zip(stamps, stamps[1:]))
    return stamps if ok else None


def cmd_from_images(args: argparse.Namespace) -> int:
    from common.errors import SourceError
    from cores import foxglove
    from cores.recording import RAW_LEFT, RAW_RIGHT, Converter, RecordingWriter, encode_array
    from services.capture.files import ImageSource
    from services.recorder.main import calibration_text

    _need_mcap()
    out = Path(args.output)
    if out.suffix.lower() != ".mcap":
        raise BallbotError(f"{out}: a recording's name ends in .mcap")
    src = ImageSource(args.left, args.right, max_rate=True, labels=("LEFT", "RIGHT"))  # names what is wrong
    if not out.parent.exists():  # e.g. recordings/, where `record` writes too
        out.parent.mkdir(parents=True)
    cal = calibration_text(args.calibration) if args.calibration else None
    stamps = None if args.fps else _stamps_from_names(src.left_files)
    fps = args.fps or 30.0
    if stamps is None:
        t0 = args.start_ns if args.start_ns is not None else 0
        stamps = [t0 + round(i * 1e9 / fps) for i in range(len(src))]
    writer = RecordingWriter(out, compression=args.compression,
                             metadata={"left": args.left, "right": args.right, "calibration": args.calibration or "",
                                       "from": "images"})
    n = 0
    try:
        if cal is not None:
            for r in Converter.calibration(cal, args.calibration, stamps[0]):
                writer.write(r.topic, r.doc, r.log_time_ns)
        while True:
            try:
                pair = src.read()
            except SourceError as e:  # a bad file later on: the pairs before it stay in a complete file
                raise BallbotError(f"{e}; {out} holds the {n} pair(s) before it") from None
            if pair is None:
                break
            i = int(pair.extra["index"])
            for topic, img in ((RAW_LEFT, pair.left), (RAW_RIGHT, pair.right)):
                data = encode_array(img, args.format, args.jpeg_quality)
                writer.write(topic, foxglove.compressed_image(stamps[i], "camera_raw", data, args.format), stamps[i], i)
            n += 1
    finally:
        writer.close()
    print(f"wrote {out}: {n} pairs ({args.format}), {(stamps[-1] - stamps[0]) / 1e9:.2f} s"
          f"{', calibration ' + args.calibration if cal else ', no calibration'}", file=sys.stderr)
    return 0


def cmd_to_images(args: argparse.Namespace) -> int:
    from common.files import write_image
    from cores.recording_reader import RecordingReader

    _need_mcap()
    reader = RecordingReader(args.recording)
    out = Path(args.output)
    left_dir, right_dir = out / "left", out / "right"
    left_dir.mkdir(parents=True, exist_ok=True)
    right_dir.mkdir(parents=True, exist_ok=True)
    n, calibration = 0, None
    for pair in reader.pairs(args.frames):
        name = f"{pair.stamp_ns}.{args.ext}" if args.names == "stamp" else f"{n:06d}.{args.ext}"
        for d, img in ((left_dir, pair.left), (right_dir, pair.right)):
            write_image(d / name, img)
        calibration = pair.calibration_yaml or calibration
        n += 1
    if calibration:
        (out / "calibration.yaml").write_text(calibration)
    print(f"wrote {n} {reader.kind} pairs to {left_dir} and {right_dir}"
          f"{' and calibration.yaml' if calibration else ''}"
          f"{' (the recording was cut off: read up to its last complete chunk)' if reader.truncated else ''}"
          f"{f'; {reader.damaged} pair(s) with a damaged image skipped' if getattr(reader, 'damaged', 0) else ''}",
          file=sys.stderr)
    return 0


# --- replay play / pause / step ----------------------------------------------------------------

def cmd_replay(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from ballbot_vision.cli import robot_id, zenoh_options
    from common import codec
    from common.keys import topic
    from common.messages import ReplayControl
    from common.zenoh_session import open_session

    try:
        msg = ReplayControl(robot_id=robot_id(args), seq=0, stamp_ns=time.time_ns(), action=args.action,
                            frames=args.frames, speed=args.speed)
    except ValidationError as e:
        err = e.errors()[0]
        raise BallbotError(f"replay --{err['loc'][0]}: {err['msg']}") from None
    key = topic("replay_control").key(robot_id(args))
    with open_session(zenoh_options(args)) as session:
        import threading

        import zenoh

        # A new peer learns of the subscribers a moment after it connects: wait for capture's.
        pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        matched = threading.Event()

        def on_matching(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                matched.set()

        listener = pub.declare_matching_listener(on_matching)
        # (zenoh's stub says matching_status is a bool; it is a MatchingStatus)
        if not (pub.matching_status.matching  # type: ignore[attr-defined]
                or matched.wait(args.timeout)):
            raise BallbotError(f"no replay listens on {key} within {args.timeout:g} s (is capture running with "
                               f"--source mcap for robot {robot_id(args)!r}?)")
        pub.put(codec.encode(msg))
        listener.undeclare()
        pub.undeclare()
    return 0


# --- parser ------------------------------------------------------------------------------------

def _jpeg_quality(text: str) -> int:
    q = int(text)
    if not MIN_JPEG_QUALITY <= q <= 100:
        raise argparse.ArgumentTypeError(f"{MIN_JPEG_QUALITY}..100, got {q} (lower, the pairs replayed lose what "
                                         f"stands: common/codec.py MIN_JPEG_QUALITY)")
    return q


def register(sub: argparse._SubParsersAction, common) -> None:
    from common.settings import add_settings_arguments
    from services.recorder.main import RecordSettings

    r = common(sub.add_parser("record", help="record the running pipeline to an MCAP file (Foxglove opens it; "
                                            "default: recordings/<robot>-<date>-<time>.mcap)",
                              description="Subscribe to the pipeline and write raw and rectified pairs, "
                                          "disparity, obstacles (lists, image boxes, 3D boxes), free space, "
                                          "stats, the calibration and the synthetic truth to an MCAP file. "
                                          "Ctrl-C (or SIGTERM) stops it and closes the file."))
    r.add_argument("output", metavar="OUT.mcap", nargs="?", default=None,
                   help=f"the file to write (default: {RECORDINGS}/<robot id>-<date>-<time>.mcap)")
    add_settings_arguments(r, RecordSettings)
    r.set_defaults(func=cmd_record)

    m = sub.add_parser("mcap", help="recordings: info, from-images, to-images")
    msub = m.add_subparsers(dest="mcap_command", required=True, metavar="ACTION")
    i = msub.add_parser("info", help="what a recording holds")
    i.add_argument("recording", metavar="FILE.mcap")
    i.add_argument("--json", action="store_true")
    i.set_defaults(func=cmd_info)

    f = msub.add_parser("from-images", help="two image folders -> a recording that capture --source mcap replays",
                        description="Pairs left/right images by sorted name (as capture --source images does). "
                                    "Names that are nanosecond timestamps (EuRoC) give the times; else --fps.")
    f.add_argument("left", metavar="LEFT", help="left folder or glob")
    f.add_argument("right", metavar="RIGHT", help="right folder or glob")
    f.add_argument("-o", "--output", required=True, metavar="OUT.mcap")
    f.add_argument("--calibration", default=None, metavar="CAL", help="calibration YAML or profile stored with "
                   "the pairs (replay hands it to rectify)")
    f.add_argument("--fps", type=float, default=None, help="frame rate (default: from timestamp names, else 30)")
    f.add_argument("--start-ns", type=int, default=None, help="stamp of the first pair with --fps (default 0)")
    f.add_argument("--format", choices=["png", "jpeg"], default="png", help="image format in the file (default: "
                   "png, lossless)")
    f.add_argument("--jpeg-quality", type=_jpeg_quality, default=95, help=f"with --format jpeg, "
                   f"{MIN_JPEG_QUALITY}..100 (lower, the replayed lists miss what stands: common/codec.py)")
    f.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd")
    f.set_defaults(func=cmd_from_images)

    t = msub.add_parser("to-images", help="a recording -> left/ and right/ image folders (+ calibration.yaml)")
    t.add_argument("recording", metavar="FILE.mcap")
    t.add_argument("-o", "--output", required=True, metavar="DIR")
    t.add_argument("--frames", choices=["auto", "raw", "rectified"], default="auto",
                   help="which pairs (default: raw if recorded, else rectified)")
    t.add_argument("--names", choices=["index", "stamp"], default="index",
                   help="file names: 000000.png... or the capture stamp in ns")
    t.add_argument("--ext", choices=["png", "jpg", "bmp", "tif"], default="png")
    t.set_defaults(func=cmd_to_images)

    p = common(sub.add_parser("replay", help="play, pause or step a replay (capture --source mcap)"))
    p.add_argument("action", choices=["play", "pause", "step"])
    p.add_argument("--frames", type=int, default=1, help="step: pairs to publish (default 1)")
    p.add_argument("--speed", type=float, default=None, help="new playback speed factor")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the replaying capture")
    p.set_defaults(func=cmd_replay)


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use: ballbot-vision record | mcap | replay")
