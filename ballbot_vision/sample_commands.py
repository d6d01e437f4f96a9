"""`ballbot-vision sample-pair DIR`: a stereo pair (or a short sequence) from the synthetic world, as
a camera would have taken it (raw, with the rig's lens distortion), with its calibration and ground
truth, so that the offline commands have data to run on before there is a real rig:

    ballbot-vision sample-pair sample/
    ballbot-vision rectify sample/left.png sample/right.png --calibration sample/calibration.yaml -o sample/rect
    ballbot-vision obstacles sample/left.png sample/right.png --calibration sample/calibration.yaml

Registered through cli.py's COMMAND_MODULES hook; the rendering is sim/world.py's.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from common.errors import BallbotError


def cmd_sample_pair(args: argparse.Namespace) -> int:
    from common.files import write_image
    from cores import camera
    from services.capture.main import truth_message
    from services.capture.sources import SyntheticSource

    if args.frames < 1:
        raise BallbotError(f"--frames {args.frames}: must be at least 1")
    if args.fps <= 0:
        raise BallbotError(f"--fps {args.fps}: must be positive")
    src = SyntheticSource(args.scenario, args.calibration, args.fps, args.seed, args.noise_sigma)
    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    sequence = args.frames > 1
    if sequence:
        (out / "left").mkdir(exist_ok=True)
        (out / "right").mkdir(exist_ok=True)
    truths = []
    for k in range(args.frames):
        pair = src.read()
        stem = f"{k:04d}" if sequence else ""
        paths = ((out / "left" / f"left{stem}.png", out / "right" / f"right{stem}.png") if sequence
                 else (out / "left.png", out / "right.png"))
        for path, img in zip(paths, (pair.left, pair.right)):
            write_image(path, img)
        msg = truth_message("sample", k, int(pair.t_s * 1e9), args.scenario, pair.truth or [])
        truths.append(json.loads(msg.model_dump_json()))
    camera.save_calibration(src.rig, out / "calibration.yaml")
    (out / "truth.json").write_text(json.dumps(truths if sequence else truths[0], indent=1))
    h, w = pair.left.shape[:2]
    what = f"{args.frames} raw pairs in {out / 'left'}/ and {out / 'right'}/" if sequence \
        else f"a raw pair {out / 'left.png'} {out / 'right.png'}"
    print(f"wrote {what} ({w}x{h}, scenario {args.scenario}, rig {src.rig.name or args.calibration}), "
          f"{out / 'calibration.yaml'} and the ground truth {out / 'truth.json'} "
          f"(camera frame: rectified left, x right, y down, z forward, m)")
    l, r = (str(out / "left"), str(out / "right")) if sequence else (str(out / "left.png"), str(out / "right.png"))
    cal = out / "calibration.yaml"
    print("try:")
    print(f"  ballbot-vision obstacles {l} {r} --calibration {cal}")
    print(f"  ballbot-vision rectify {l} {r} --calibration {cal} -o {out / 'rect'}")
    print(f"  ballbot-vision disparity {out / 'left.png' if not sequence else l + '/left0000.png'} "
          f"{out / 'right.png' if not sequence else r + '/right0000.png'} "
          f"--calibration {cal} -o {out / 'disparity.png'}")
    return 0


def register(sub: argparse._SubParsersAction, common) -> None:
    p = sub.add_parser("sample-pair", help="write a raw stereo pair of the synthetic world, its calibration and truth",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dir", metavar="DIR", help="folder to write left.png, right.png, calibration.yaml, truth.json")
    p.add_argument("--scenario", default="two-boxes", help="built-in scenario or scenario YAML (default: two-boxes)")
    p.add_argument("--frames", type=int, default=1,
                   help="pairs to write; more than 1 writes a sequence into DIR/left/ and DIR/right/ (default: 1)")
    p.add_argument("--fps", type=float, default=15.0, help="frame rate of a sequence (default: 15)")
    p.add_argument("--calibration", default="lifecam-studio", metavar="CAL",
                   help="the raw rig to render for (YAML or profile; default: lifecam-studio)")
    p.add_argument("--seed", type=int, default=0, help="texture and noise seed")
    p.add_argument("--noise-sigma", type=float, default=1.5, help="sensor noise, grey levels (default: 1.5)")
    p.set_defaults(func=cmd_sample_pair)
