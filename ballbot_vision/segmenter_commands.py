"""`obstacles`, `eval` (synthetic, or `--real DIR`), `mount estimate` and `bench-segmenter`: the
segmenter's offline commands (registered through cli.py's COMMAND_MODULES hook). The work is done by
services/segmenter/{main,layers,seed,eval,real_eval,mount_estimate,draw}.py and bench/segmenter.py;
this module only parses and prints."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from common.errors import BallbotError


def _out(text: str = "") -> None:
    print(text, flush=True)


def _read(path: Path, rectifier=None):
    """One image file; with a rectifier, also checked against the calibrated size, naming the file."""
    from common.files import read_image

    img = read_image(path)
    if rectifier is not None:
        rectifier.check_size(img, str(path))
    return img


def _segmenter_settings(args: argparse.Namespace):
    from common.settings import load_settings
    from cores.segmentation.settings import SegmenterSettings

    return load_settings(SegmenterSettings, getattr(args, "config", None), args)


def _mount_settings(args: argparse.Namespace):
    """The camera on the robot: the `mount:` section of --config, BALLBOT_MOUNT_*, --mount-* (as the
    services read it)."""
    from common.settings import MountSettings, load_settings

    return load_settings(MountSettings, getattr(args, "config", None), args, prefix="mount-")


# --- obstacles ---------------------------------------------------------------------------------

def format_obstacles(msg, header: str = "") -> str:
    """An ObstacleList as the `obstacles` command prints it: the header with where the list looked
    and what keeps it from being a full view (as `watch` says them), then a row per obstacle."""
    from ballbot_vision.watch import looked_at, track_note

    lines = [header + looked_at(msg) + "".join(f"  {w}" for w in msg.warnings())]
    if not msg.obstacles:
        lines.append("  (no obstacles)")
        return "\n".join(lines)
    lines.append(f"  {'id':>3} {'x m':>7} {'y m':>7} {'z m':>7} {'dist m':>7} {'w m':>6} {'h m':>6} {'d m':>6} "
                 f"{'disp px':>8} {'area px':>8} {'conf':>5} {'vx,vy,vz m/s':>17}  bbox px{'':14} "
                 f"base x,y,z m{'':8}  track")
    for o in msg.obstacles:
        base = ("" if o.position_base_m is None else " ".join(f"{v:6.2f}" for v in o.position_base_m))
        bbox = ",".join(str(v) for v in o.bbox_px)
        vel = " ".join(f"{v:5.2f}" for v in o.velocity_mps)
        lines.append(f"  {o.id:>3} {o.position_m[0]:7.3f} {o.position_m[1]:7.3f} {o.position_m[2]:7.3f} "
                     f"{o.distance_m:7.3f} {o.size_m[0]:6.2f} {o.size_m[1]:6.2f} {o.size_m[2]:6.2f} "
                     f"{o.disparity_px:8.2f} {o.area_px:8d} {o.confidence:5.2f} {vel:>17}  {bbox:20} {base:20}  "
                     f"{track_note(o)}")
    return "\n".join(lines)


def format_ground(ground) -> str:
    if ground is None:
        return "  ground: unknown"
    inl = f", {ground.inlier_fraction:.0%} inliers" if ground.inlier_fraction else ""
    return (f"  ground: camera {ground.height_m:.2f} m above it, pitch {ground.pitch_deg:+.1f} deg, "
            f"roll {ground.roll_deg:+.1f} deg ({ground.source}{inl})")


def format_freespace(fs) -> str:
    import numpy as np

    if fs is None:
        return "  free space: none"
    cells = np.frombuffer(fs.cells, np.int8)
    a = fs.resolution_m ** 2
    free, occ = int(np.count_nonzero(cells == 0)), int(np.count_nonzero(cells == 100))
    return (f"  free space: {fs.width}x{fs.height} cells of {fs.resolution_m:g} m from base ({fs.origin_m[0]:g}, "
            f"{fs.origin_m[1]:g}) m: {free} free ({free * a:.1f} m^2), {occ} occupied ({occ * a:.1f} m^2), "
            f"{cells.size - free - occ} unknown")


def _obstacles_matcher_settings(args: argparse.Namespace):
    """The disparity settings for `obstacles`: as configured, with the search range following the
    calibration (num_disparities auto) unless one was set."""
    from common.settings import load_settings
    from cores.matching.config import MatcherConfig

    over = {k: v for k, v in REAL_DISPARITY_DEFAULTS.items() if k not in _explicit(MatcherConfig, args)}
    return load_settings(MatcherConfig, getattr(args, "config", None), args, prefix="disparity-", **over)


def _warn_reach(pipe) -> None:
    """Say at the start, on stderr, when the disparity search (or its range gate) cannot measure all,
    the near or the far part of the segmenter's vision range: the lists then carry
    "range-unreachable" (or "near-unmeasured", "far-unmeasured")."""
    from cores.matching.config import gate_for_range

    cfg = pipe.matching.config.resolved(pipe.model.focal_px, pipe.model.baseline_m, pipe.model.width)
    gate = gate_for_range(cfg.max_range_m, pipe.model.focal_px, pipe.model.baseline_m)
    reach = pipe.builder.check_search(pipe.model, cfg.min_disparity, cfg.num_disparities, quiet=True, gate_px=gate)
    if reach.message:
        print(f"warning: {reach.message}", file=sys.stderr, flush=True)


def _warn_recording_reach(rec, seg, disp, alpha: float) -> None:
    from cores.calibration.rectify import Rectifier
    from cores.matching.config import gate_for_range
    from cores.segmentation.builder import search_reach

    model = Rectifier(rec.calibration, alpha).model
    cfg = disp.resolved(model.focal_px, model.baseline_m, model.width)
    gate = gate_for_range(cfg.max_range_m, model.focal_px, model.baseline_m)
    reach = search_reach(model, cfg.min_disparity, cfg.num_disparities, seg, gate)
    if reach.message:
        print(f"warning: {reach.message}", file=sys.stderr, flush=True)


def _write_picture(path: Path, picture) -> None:
    from common.files import output_folder, write_image

    output_folder(path.parent, "--draw")
    write_image(path, picture, "--draw")


def cmd_obstacles(args: argparse.Namespace) -> int:
    from common.files import check_pair, list_images, pair_images
    from cores import camera
    from cores.pipeline import Pipeline
    from cores.segmentation.draw import draw_frame

    settings = _segmenter_settings(args)
    skipped: list[BallbotError] = []  # the folders' unreadable pairs
    if args.left.lower().endswith(".mcap"):  # a recording: its pairs, times and (by default) calibration
        from cores.recording_reader import offline_pairs

        pairs, cal = offline_pairs(args.left, args.calibration)
    elif args.right is None or args.calibration is None:
        raise BallbotError("obstacles: image pairs need LEFT, RIGHT and --calibration (a recording: FILE.mcap)")
    else:
        cal = camera.load_calibration(args.calibration)
        file_pairs = pair_images(list_images(args.left, "LEFT"), list_images(args.right, "RIGHT"))

        def read_pairs():
            for k, (lp, rp) in enumerate(file_pairs):
                try:
                    left, right = _read(lp, pipe.rectifier), _read(rp, pipe.rectifier)
                    check_pair(left, right, str(lp), str(rp))
                except BallbotError as e:
                    # one unreadable pair costs that pair, as in a recording: the folder goes on (its time
                    # stays the file's place, so the tracks see the gap); nothing read at all is the error
                    if len(file_pairs) == 1:
                        raise
                    skipped.append(e)
                    print(f"ballbot-vision: warning: {e}; pair skipped", file=sys.stderr, flush=True)
                    continue
                yield lp, rp, left, right, k / args.fps, k  # seq: the pair's place in the folders
        pairs = read_pairs()
    pipe = Pipeline(cal, _obstacles_matcher_settings(args), settings, alpha=args.alpha, mount=_mount_settings(args))
    _warn_reach(pipe)
    draw_dir = Path(args.draw) if args.draw else None
    done = 0
    for lp, rp, left, right, stamp_s, seq in pairs:
        done += 1
        # a list's seq is its pair's (a skipped pair leaves its number out): a recording's seq, a folder's place
        frame = pipe.process(left, right, t_s=stamp_s, seq=seq, stamp_ns=int(stamp_s * 1e9), names=(str(lp), str(rp)))
        result, msg = frame.result, frame.result.obstacles
        if draw_dir is not None:
            name = lp.stem if isinstance(lp, Path) else f"{Path(args.left).stem}_{msg.seq:06d}"  # a recording's pair
            _write_picture(draw_dir / f"{name}.png", draw_frame(frame.left, msg, pipe.model, result.freespace))
        if args.json:
            doc = json.loads(msg.model_dump_json())
            doc["left"], doc["right"] = str(lp), str(rp)
            _out(json.dumps(doc))
        else:
            _out(format_obstacles(msg, f"{lp} {rp}: {settings.method}, {frame.segment_ms:.1f} ms (camera frame: x "
                                       f"right, y down, z forward): {len(msg.obstacles)} obstacle(s)"))
            _out(format_ground(msg.ground))
            _out(format_freespace(result.freespace))
            if msg.degraded:
                _out(f"  degraded: {', '.join(msg.degraded)}")
    if skipped:
        if done == 0:
            raise BallbotError(f"obstacles: none of the {len(skipped)} pairs could be read (named above)")
        print(f"ballbot-vision: warning: {len(skipped)} of {len(skipped) + done} pair(s) could not be read and "
              f"were skipped (named above)", file=sys.stderr, flush=True)
    return 0


# --- eval --------------------------------------------------------------------------------------

def cmd_eval(args: argparse.Namespace) -> int:
    if args.real:
        return cmd_eval_real(args)
    from common.settings import flags_given
    from cores.segmentation.settings import SegmenterSettings

    given = flags_given(SegmenterSettings, args)
    if given:
        raise BallbotError(f"eval: {', '.join(SegmenterSettings.flag(k) for k in given)}: the segmenter's settings go "
                           "with --real DIR (the synthetic scenarios set their own per method)")
    from evaluation import synthetic as E

    scenarios = args.scenarios or E.default_scenarios()
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
                        mount_error=error, true_ground=args.true_ground, draw_dir=args.draw)
    if args.json:
        _out(json.dumps(E.result_to_json(result), indent=2))
    else:
        _out(E.format_table(result))
        _out("\nerrors against the centroid of each obstacle's surface visible to the matcher; "
             "depth % for truths at 0.5-4 m; vel err after 4 frames of a track")
    return 0


# Settings for real recordings where the user set none (flag, environment or --config): a car's or a
# room's range rather than a small robot's, and a search range that follows the calibration (64 px
# ends at 5.8 m on Karlsruhe: nearer parked cars saturate it).
REAL_SEGMENTER_DEFAULTS: dict[str, Any] = {"max_range_m": 30.0}
REAL_DISPARITY_DEFAULTS: dict[str, Any] = {"num_disparities": "auto"}


def _explicit(cls, args: argparse.Namespace) -> set[str]:
    """Fields of settings model `cls` set by a flag, an environment variable or the --config file."""
    import os

    from common.settings import flags_given, read_config_section

    keys = set(flags_given(cls, args))
    keys |= {n for n in cls.model_fields if os.environ.get(cls.env_var(n))}
    config = getattr(args, "config", None)
    if config:
        keys |= set(read_config_section(config, cls.section))
    return keys


def _real_settings(args: argparse.Namespace, **forced):
    """(segmenter settings, disparity settings, {field: note} of the recording defaults applied)."""
    from common.settings import load_settings
    from cores.matching.config import MatcherConfig
    from cores.segmentation.settings import SegmenterSettings

    seg_over = {k: v for k, v in REAL_SEGMENTER_DEFAULTS.items() if k not in _explicit(SegmenterSettings, args)}
    seg_over.update(forced)
    disp_over = {k: v for k, v in REAL_DISPARITY_DEFAULTS.items() if k not in _explicit(MatcherConfig, args)}
    seg = load_settings(SegmenterSettings, getattr(args, "config", None), args, **seg_over)
    disp = load_settings(MatcherConfig, getattr(args, "config", None), args, prefix="disparity-", **disp_over)
    applied = {**{f"segmenter {k}": v for k, v in seg_over.items() if k not in forced},
               **{f"disparity {k}": v for k, v in disp_over.items()}}
    return seg, disp, applied


def _method_override(args: argparse.Namespace) -> dict:
    from cores.segmentation.settings import METHODS

    if not args.method:
        return {}
    if len(args.method) != 1 or args.method[0] not in METHODS:
        raise BallbotError(f"eval --real: --method takes one segmenter method ({', '.join(METHODS)}), "
                           f"got {', '.join(args.method)}")
    return {"method": args.method[0]}


def _describe_defaults(applied: dict) -> str:
    if not applied:
        return ""
    shown = ", ".join(f"{k} {'null' if v is None else v}" for k, v in applied.items())
    return f"recording defaults (none configured): {shown}"


def cmd_eval_real(args: argparse.Namespace) -> int:
    from evaluation import real as R
    from evaluation import recordings

    if args.scenarios:
        raise BallbotError("eval --real DIR runs a recording; leave out the scenario names")
    if args.true_ground:
        raise BallbotError("eval --real: --true-ground needs a synthetic scenario (a recording has no true ground)")
    seg, disp, applied = _real_settings(args, **_method_override(args))
    rec = recordings.open_recording(args.real, fps=args.fps or 10.0)
    if args.frames is not None and args.frames < 1:
        raise BallbotError(f"--frames {args.frames}: at least 1")
    on_frame = None
    if not args.json:
        _out(f"eval --real {rec.root}: {min(args.frames or len(rec.pairs), len(rec.pairs))} of {len(rec.pairs)} pairs")
        if applied:
            _out(_describe_defaults(applied))
        on_frame = lambda fr: _out(R.format_frame(fr))  # noqa: E731
    _warn_recording_reach(rec, seg, disp, args.alpha)
    report = R.evaluate_recording(rec, seg, disp, frames=args.frames, draw_dir=args.draw, alpha=args.alpha,
                                  mount=_mount_settings(args),
                                  on_frame=on_frame)
    if args.json:
        doc = R.report_to_json(report)
        doc["recording_defaults"] = {k: v for k, v in applied.items()}
        _out(json.dumps(doc, indent=2))
    else:
        _out(R.format_report(report))
    return 0


# --- mount estimate ----------------------------------------------------------------------------

def cmd_mount_estimate(args: argparse.Namespace) -> int:
    from cores.segmentation.mount_estimate import estimate_from_grounds, format_estimate, merge_into_config
    from evaluation import real as R
    from evaluation import recordings

    if args.real:
        if args.left or args.right:
            raise BallbotError("mount estimate: give either LEFT RIGHT --calibration CAL or --real DIR")
        rec = recordings.open_recording(args.real, fps=10.0)
    elif not (args.left and args.right and args.calibration):
        raise BallbotError("mount estimate: give LEFT RIGHT --calibration CAL (folders, globs or files), "
                           "or --real DIR (a recording folder)")
    else:
        rec = recordings.recording_from_files(args.left, args.right, args.calibration)
    if args.frames < 1:
        raise BallbotError(f"--frames {args.frames}: at least 1")
    seg, disp, applied = _real_settings(args)  # no mount: the ground is what is measured
    if applied and not args.json:
        _out(_describe_defaults(applied))
    grounds = []
    for pf in R.process_recording(rec, seg, disp, frames=args.frames, alpha=args.alpha):
        grounds.append(pf.result.obstacles.ground)
    est = estimate_from_grounds(grounds)
    if args.json:
        doc = {"frames": est.frames, "fitted": est.fitted, "sources": est.sources, **est.settings_values(),
               "spread": est.spread}
        _out(json.dumps(doc, indent=2))
    else:
        _out(format_estimate(est))
    if args.write:
        kept = merge_into_config(args.write, est.settings_values())
        msg = f"wrote {', '.join(f'{k} {v}' for k, v in est.settings_values().items())} to {args.write} (mount:)"
        if not kept:
            msg += "; the file was rewritten from its content (its comments are gone)"
        print(msg, file=sys.stderr if args.json else sys.stdout, flush=True)
    return 0


# --- bench-segmenter ---------------------------------------------------------------------------

def cmd_bench_segmenter(args: argparse.Namespace) -> int:
    from bench.segmenter import bench_segmenter, format_bench

    result = bench_segmenter(args.scenario, args.method or None, args.repeat, real=args.real,
                             real_pairs=args.real_pairs, real_max_range_m=args.real_max_range)
    _out(json.dumps(result, indent=2) if args.json else format_bench(result))
    return 0


# --- parser ------------------------------------------------------------------------------------

def _matcher_args(p: argparse.ArgumentParser) -> None:
    """The disparity stage's settings, named as everywhere else with the stage in front
    (`--disparity-method sgbm`: `disparity --method`, BALLBOT_DISPARITY_METHOD, `disparity: {method}`)."""
    from common.settings import add_settings_arguments
    from cores.matching.config import MatcherConfig

    add_settings_arguments(p, MatcherConfig, prefix="disparity-",
                           title="disparity settings (the 'disparity' section of --config FILE, or the "
                                 "environment variable shown)")


def _matcher_settings(args: argparse.Namespace):
    from common.settings import load_settings
    from cores.matching.config import MatcherConfig

    return load_settings(MatcherConfig, getattr(args, "config", None), args, prefix="disparity-")


def register(sub: argparse._SubParsersAction, common) -> None:
    from common.settings import MountSettings, add_settings_arguments
    from cores.segmentation.settings import SegmenterSettings

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
    o.add_argument("--draw", default=None, metavar="DIR", help="also write one picture per pair into DIR, named "
                   "after the left image: boxes with track id and distance, free space, ground")
    _matcher_args(o)
    add_settings_arguments(o, SegmenterSettings)
    add_settings_arguments(o, MountSettings, prefix="mount-")
    o.set_defaults(func=cmd_obstacles)

    e = sub.add_parser("eval", help="synthetic scenarios with ground truth -> detection and position-error report; "
                                    "--real DIR: a real recording -> label-free figures",
                       description="Render the built-in scenarios, run them through the real rectify, "
                                   "disparity and segmenter cores, and score each method against the truth. "
                                   "With --real DIR: run a real recording (left/ right/ calibration.yaml "
                                   "[insdata.txt], or EuRoC cam0/ cam1/ with their sensor yamls) through the "
                                   "same cores and report label-free figures: obstacles per frame, flat "
                                   "obstacles (judged against an independent v-disparity road profile), track "
                                   "life, ground estimates, time per frame.")
    e.add_argument("scenarios", nargs="*", metavar="SCENARIO", help="built-in scenario names or YAML files "
                   "(default: all built-in but the slow ones, e.g. sway)")
    e.add_argument("--method", action="append", metavar="M",
                   help="seed (the thesis), seed+floor, layers; repeat for several (default: all three)")
    e.add_argument("--json", action="store_true")
    e.add_argument("--frames", type=int, default=None, help="frames per scenario (default: 3 static, 45 moving); "
                   "--real: the first N pairs (default: all)")
    e.add_argument("--fps", type=float, default=None, help="scene frame rate (default: 15); --real: the "
                   "recording's, where neither insdata.txt nor image names give stamps (default: 10)")
    e.add_argument("--seed", type=int, default=0, help="texture and noise seed")
    g = e.add_argument_group("mount error", "tell the segmenter a wrong camera mount (a balancing robot leans)")
    g.add_argument("--mount-pitch-error", type=float, default=0.0, metavar="DEG")
    g.add_argument("--mount-roll-error", type=float, default=0.0, metavar="DEG")
    g.add_argument("--mount-height-error", type=float, default=0.0, metavar="M")
    g.add_argument("--true-ground", action="store_true", help="give the segmenter each frame's true ground "
                   "instead of its estimate: segmentation and tracking apart from ground estimation")
    r = e.add_argument_group("real recordings")
    r.add_argument("--real", default=None, metavar="DIR", help="a recording folder instead of the scenarios")
    r.add_argument("--alpha", type=float, default=0.0, help="--real: rectification alpha for a raw rig (default: 0)")
    e.add_argument("--draw", default=None, metavar="OUT",
                   help="one picture per frame into OUT: a scenario's as <scenario>-<method>-<frame>.png, with "
                        "the truths it is scored on (dashed cyan: matched; orange: missed); --real: one per pair, "
                        "named after the left image")
    e.add_argument("--config", default=None, metavar="FILE", help="YAML with 'segmenter' and 'disparity' sections")
    _matcher_args(e)
    add_settings_arguments(e, SegmenterSettings, exclude=("method",),
                           title="segmenter settings for --real (the 'segmenter' section of --config FILE, or "
                                 "the environment variable shown; --method picks the method; unset, a recording "
                                 "runs with max_range_m 30)")
    add_settings_arguments(e, MountSettings, prefix="mount-", title="the camera mount for --real (the 'mount' "
                           "section of --config FILE, or the environment variable shown; unset: the ground is "
                           "fitted every frame)")
    e.set_defaults(func=cmd_eval)

    m = sub.add_parser("mount", help="the camera mount: estimate height, pitch and roll from recorded pairs")
    ms = m.add_subparsers(dest="mount_command", required=True, metavar="ACTION")
    me = ms.add_parser("estimate", help="pairs -> camera height above the floor, pitch, roll (median of "
                                        "the frames whose ground was fitted)",
                       description="Run the pairs through rectify, disparity and the segmenter with no mount "
                                   "configured, take the median of the per-frame ground planes fitted to the "
                                   "disparity, print height, pitch and roll with their spread, and with --write "
                                   "set them in the 'mount' section of a config file.")
    me.add_argument("left", metavar="LEFT", nargs="?", help="left images: folder, glob or file")
    me.add_argument("right", metavar="RIGHT", nargs="?", help="right images: folder, glob or file")
    me.add_argument("--calibration", metavar="CAL", help="calibration YAML or profile (with LEFT RIGHT)")
    me.add_argument("--real", default=None, metavar="DIR", help="a recording folder instead of LEFT RIGHT "
                    "--calibration (layouts as eval --real)")
    me.add_argument("--frames", type=int, default=20, help="pairs to use, from the first (default: 20)")
    me.add_argument("--write", default=None, metavar="CONFIG.yaml", help="set height_m, pitch_deg and roll_deg "
                    "in this file's 'mount' section (created if missing; the rest is kept)")
    me.add_argument("--alpha", type=float, default=0.0, help="rectification alpha for a raw rig (default: 0)")
    me.add_argument("--json", action="store_true")
    me.add_argument("--config", default=None, metavar="FILE", help="YAML with 'segmenter' and 'disparity' "
                    "sections (its 'mount' section is what is measured: ignored)")
    _matcher_args(me)
    add_settings_arguments(me, SegmenterSettings,
                           title="segmenter settings (unset: max_range_m 30; the mount is what is estimated)")
    me.set_defaults(func=cmd_mount_estimate)

    b = sub.add_parser("bench-segmenter", help="segmentation time per frame for each method",
                       description="Time each segmentation method on disparity maps of a synthetic scenario "
                                   "(and of a real recording with --real), beside the default matcher's time "
                                   "on the same pairs in the same run.")
    b.add_argument("--scenario", default="two-boxes")
    b.add_argument("--method", action="append", metavar="M", help="seed or layers (default: all)")
    b.add_argument("--repeat", type=int, default=50, help="timed runs per method")
    b.add_argument("--real", metavar="DIR", default=None,
                   help="also a recording: DIR/left, DIR/right and DIR/calibration.yaml (e.g. "
                        "../shared/data/real/karlsruhe-0023); matched with the default matcher, then segmented")
    b.add_argument("--real-pairs", type=int, default=1, metavar="N", help="the first N pairs of --real (default 1)")
    b.add_argument("--real-max-range", type=float, default=20.0, metavar="M",
                   help="segmenter range on --real, m (default 20: a street seen from a car)")
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench_segmenter)


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use: ballbot-vision obstacles | eval | mount estimate | bench-segmenter")
