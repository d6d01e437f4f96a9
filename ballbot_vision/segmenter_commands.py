"""`obstacles`, `eval` and `bench-segmenter`: the segmenter's offline commands (registered through
cli.py's COMMAND_MODULES hook). The work is done by services/segmenter/{main,layers,seed,eval}.py
and bench/segmenter.py; this module only parses and prints."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .common.errors import BallbotError


def _out(text: str = "") -> None:
    print(text, flush=True)


def _read(path: Path, rectifier=None):
    """One image file; with a rectifier, also checked against the calibrated size, naming the file."""
    from .common.files import read_image

    img = read_image(path)
    if rectifier is not None:
        rectifier.check_size(img, str(path))
    return img


def _segmenter_settings(args: argparse.Namespace):
    from .common.settings import load_settings
    from .services.segmenter.main import SegmenterSettings

    return load_settings(SegmenterSettings, getattr(args, "config", None), args)


# --- obstacles ---------------------------------------------------------------------------------

def format_obstacles(obstacles, header: str = "") -> str:
    lines = [header] if header else []
    if not obstacles:
        lines.append("  (no obstacles)")
        return "\n".join(lines)
    lines.append(f"  {'id':>3} {'x m':>7} {'y m':>7} {'z m':>7} {'dist m':>7} {'w m':>6} {'h m':>6} {'d m':>6} "
                 f"{'disp px':>8} {'area px':>8} {'conf':>5} {'vx,vy,vz m/s':>17}  bbox px{'':14} base x,y,z m")
    for o in obstacles:
        base = ("" if o.position_base_m is None else " ".join(f"{v:6.2f}" for v in o.position_base_m))
        bbox = ",".join(str(v) for v in o.bbox_px)
        vel = " ".join(f"{v:5.2f}" for v in o.velocity_mps)
        lines.append(f"  {o.id:>3} {o.position_m[0]:7.3f} {o.position_m[1]:7.3f} {o.position_m[2]:7.3f} "
                     f"{o.distance_m:7.3f} {o.size_m[0]:6.2f} {o.size_m[1]:6.2f} {o.size_m[2]:6.2f} "
                     f"{o.disparity_px:8.2f} {o.area_px:8d} {o.confidence:5.2f} {vel:>17}  {bbox:20} {base}")
    return "\n".join(lines)


def cmd_obstacles(args: argparse.Namespace) -> int:
    import time

    from .common import camera
    from .common.disparity import to_float
    from .common.files import check_pair, list_images, pair_images
    from .services.disparity.matchers import SCALE, StereoMatcher
    from .services.rectify.core import Rectifier
    from .services.segmenter.main import ObstacleBuilder

    settings = _segmenter_settings(args)
    if args.left.lower().endswith(".mcap"):  # a recording: its pairs, times and (by default) calibration
        from .services.recorder.recording import offline_pairs

        pairs, cal = offline_pairs(args.left, args.calibration)
    elif args.right is None or args.calibration is None:
        raise BallbotError("obstacles: image pairs need LEFT, RIGHT and --calibration (a recording: FILE.mcap)")
    else:
        cal = camera.load_calibration(args.calibration)
        file_pairs = pair_images(list_images(args.left, "LEFT"), list_images(args.right, "RIGHT"))

        def read_pairs():
            for k, (lp, rp) in enumerate(file_pairs):
                left, right = _read(lp, rect), _read(rp, rect)
                check_pair(left, right, str(lp), str(rp))
                yield lp, rp, left, right, k / args.fps
        pairs = read_pairs()
    rect = Rectifier(cal, args.alpha)
    mcfg = _matcher_settings(args)
    stereo = StereoMatcher(mcfg)
    builder = ObstacleBuilder(settings)
    for k, (lp, rp, left, right, stamp_s) in enumerate(pairs):
        left, right = rect.rectify(left, right)
        d = to_float(stereo.compute(left, right), SCALE, mcfg.invalid_value)
        t0 = time.perf_counter()
        result = builder.process(d, rect.model, t_s=stamp_s, seq=k, stamp_ns=int(stamp_s * 1e9), image=left)
        ms = (time.perf_counter() - t0) * 1e3
        obstacles = result.obstacles.obstacles
        if args.json:
            doc = json.loads(result.obstacles.model_dump_json())
            doc["left"], doc["right"] = str(lp), str(rp)
            _out(json.dumps(doc))
        else:
            _out(format_obstacles(obstacles, f"{lp} {rp}: {len(obstacles)} obstacle(s), {settings.method}, "
                                             f"{ms:.1f} ms (camera frame: x right, y down, z forward)"))
    return 0


# --- eval --------------------------------------------------------------------------------------

def cmd_eval(args: argparse.Namespace) -> int:
    from .services.capture.synthetic import list_builtin_scenarios
    from .services.segmenter import eval as E

    scenarios = args.scenarios or list_builtin_scenarios()
    methods = args.method or E.DEFAULT_METHODS
    for m in methods:
        if m not in E.METHODS:
            raise BallbotError(f"--method {m}: unknown (known: {', '.join(E.METHODS)})")
    matcher = _matcher_settings(args)
    if not args.json:
        _out(f"eval: {', '.join(scenarios)}; methods {', '.join(methods)}; disparity {matcher.method}")
    error = {"pitch_deg": args.mount_pitch_error, "roll_deg": args.mount_roll_error,
             "height_m": args.mount_height_error}
    result = E.evaluate(scenarios, methods, frames=args.frames, fps=args.fps, seed=args.seed, matcher=matcher,
                        mount_error=error)
    if args.json:
        _out(json.dumps(E.result_to_json(result), indent=2))
    else:
        _out(E.format_table(result))
        _out("\nerrors against the centroid of each obstacle's surface visible to the matcher; "
             "depth % for truths at 0.5-4 m; vel err after 4 frames of a track")
    return 0


# --- bench-segmenter ---------------------------------------------------------------------------

def cmd_bench_segmenter(args: argparse.Namespace) -> int:
    from .bench.segmenter import bench_segmenter, format_bench

    result = bench_segmenter(args.scenario, args.method or None, args.repeat)
    _out(json.dumps(result, indent=2) if args.json else format_bench(result))
    return 0


# --- parser ------------------------------------------------------------------------------------

def _matcher_args(p: argparse.ArgumentParser) -> None:
    """The disparity stage's settings, named as everywhere else with the stage in front
    (`--disparity-method sgbm`: `disparity --method`, BALLBOT_DISPARITY_METHOD, `disparity: {method}`)."""
    from .common.settings import add_settings_arguments
    from .services.disparity.config import MatcherConfig

    add_settings_arguments(p, MatcherConfig, prefix="disparity-",
                           title="disparity settings (the 'disparity' section of --config FILE, or the "
                                 "environment variable shown)")


def _matcher_settings(args: argparse.Namespace):
    from .common.settings import load_settings
    from .services.disparity.config import MatcherConfig

    return load_settings(MatcherConfig, getattr(args, "config", None), args, prefix="disparity-")


def register(sub: argparse._SubParsersAction, common) -> None:
    from .common.settings import add_settings_arguments
    from .services.segmenter.main import SegmenterSettings

    o = sub.add_parser("obstacles", help="offline: image pairs -> rectify, disparity, obstacles",
                       description="Rectify, match and segment one image pair or two folders (a sequence, "
                                   "tracked as frames FPS apart) in-process, and print the obstacles.")
    o.add_argument("left", metavar="LEFT", help="left image, glob or folder; or a recording FILE.mcap")
    o.add_argument("right", metavar="RIGHT", nargs="?", help="right image, glob or folder")
    o.add_argument("--calibration", metavar="CAL", help="calibration YAML or profile (a recording: its own)")
    o.add_argument("--alpha", type=float, default=0.0, help="rectification alpha (default: 0)")
    o.add_argument("--json", action="store_true", help="one ObstacleList JSON object per pair")
    o.add_argument("--fps", type=float, default=15.0, help="frame rate of a sequence, for velocities")
    o.add_argument("--config", default=None, metavar="FILE", help="YAML with 'segmenter' and 'disparity' sections")
    _matcher_args(o)
    add_settings_arguments(o, SegmenterSettings)
    o.set_defaults(func=cmd_obstacles)

    e = sub.add_parser("eval", help="synthetic scenarios with ground truth -> detection and position-error report",
                       description="Render the built-in scenarios, run them through the real rectify, "
                                   "disparity and segmenter cores, and score each method against the truth.")
    e.add_argument("scenarios", nargs="*", metavar="SCENARIO", help="built-in scenario names or YAML files "
                   "(default: all built-in)")
    e.add_argument("--method", action="append", metavar="M",
                   help="seed (the thesis), seed+floor, layers; repeat for several (default: all three)")
    e.add_argument("--json", action="store_true")
    e.add_argument("--frames", type=int, default=None, help="frames per scenario (default: 3 static, 45 moving)")
    e.add_argument("--fps", type=float, default=None, help="scene frame rate (default: 15)")
    e.add_argument("--seed", type=int, default=0, help="texture and noise seed")
    g = e.add_argument_group("mount error", "tell the segmenter a wrong camera mount (a balancing robot leans)")
    g.add_argument("--mount-pitch-error", type=float, default=0.0, metavar="DEG")
    g.add_argument("--mount-roll-error", type=float, default=0.0, metavar="DEG")
    g.add_argument("--mount-height-error", type=float, default=0.0, metavar="M")
    _matcher_args(e)
    e.set_defaults(func=cmd_eval)

    b = sub.add_parser("bench-segmenter", help="segmentation time per frame for each method",
                       description="Time each segmentation method on disparity maps of a synthetic scenario.")
    b.add_argument("--scenario", default="two-boxes")
    b.add_argument("--method", action="append", metavar="M", help="seed or layers (default: both)")
    b.add_argument("--repeat", type=int, default=50, help="timed runs per method")
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench_segmenter)


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use: ballbot-vision obstacles | eval | bench-segmenter")
