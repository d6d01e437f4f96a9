"""`ballbot-vision watch`: what a planner would see on ballbot/obstacles/**."""
from __future__ import annotations

import queue
import sys
import time

from common import codec
from common.errors import DecodeError
from common.keys import OBSTACLES_ALL, topic
from common.messages import Obstacle, ObstacleList
from common.zenoh_session import DEFAULT_ROUTER, ZenohOptions, open_session


def looked_at(msg: ObstacleList) -> str:
    """Where the list looked (" at 1-30.0 m, -27..+46 deg"; "" if it does not say): an empty list
    means nothing stands there, and says nothing of elsewhere."""
    looked = "" if msg.range_m is None else f" at {msg.range_m[0]:.3g}-{msg.range_m[1]:.1f} m"
    if msg.bearing_deg is not None:
        looked += f", {msg.bearing_deg[0]:+.0f}..{msg.bearing_deg[1]:+.0f} deg"
    return looked


def track_note(o: Obstacle) -> str:
    """How far an obstacle's track and shape can be taken as they are."""
    return (f"{o.track_frames} frame{'' if o.track_frames == 1 else 's'}{'' if o.confirmed else ', unconfirmed'}"
            f"{', cut by the view' if o.truncated else ''}")


def format_table(msg: ObstacleList) -> str:
    age_ms = (time.time_ns() - msg.stamp_ns) / 1e6
    head = (f"robot {msg.robot_id}  seq {msg.seq}  age {age_ms:6.1f} ms  {len(msg.obstacles)} obstacle(s)"
            f"{looked_at(msg)}" + "".join(f"  {w}" for w in msg.warnings()))
    g = msg.ground
    ground = ("ground: unknown (no floor removed)" if g is None or g.source == "none" else
              f"ground: camera {g.height_m:.2f} m above it, pitch {g.pitch_deg:+.1f} deg, roll {g.roll_deg:+.1f} deg "
              f"({g.source})")
    velocities = "over the ground" if msg.velocity_reference == "ground" else "relative to the robot"
    lines = [head, f"{ground}; velocities {velocities}",
             f"{'id':>4} {'x m':>7} {'y m':>7} {'z m':>7} {'dist m':>7} {'w x h x d m':>17} "
             f"{'vx,vz m/s':>11} {'disp px':>8} {'conf':>5}  track"]
    for o in msg.obstacles:
        x, y, z = o.position_m
        w, h, d = o.size_m
        track = track_note(o)
        lines.append(f"{o.id:>4} {x:7.2f} {y:7.2f} {z:7.2f} {o.distance_m:7.2f} {w:5.2f}x{h:5.2f}x{d:5.2f} "
                     f"{o.velocity_mps[0]:5.2f},{o.velocity_mps[2]:5.2f} {o.disparity_px:8.2f} {o.confidence:5.2f}  "
                     f"{track}")
    return "\n".join(lines)


def quiet_hint(key: str, waited_s: float, opts: ZenohOptions) -> str:
    """What to do when nothing arrives: whether anything runs is what `status` tells."""
    own_connect = opts.connect and opts.connect != [DEFAULT_ROUTER]
    where = " ".join(f"--connect {e}" for e in opts.connect) if own_connect else ""
    return (f"nothing published on {key} for {waited_s:.0f} s; still waiting. Is the pipeline running "
            f"(`ballbot-vision up`)? `ballbot-vision status{(' ' + where) if where else ''}` shows every running "
            f"service and what is wrong.")


def watch(opts: ZenohOptions, robot: str | None, as_json: bool, count: int, timeout_s: float,
          hint_after_s: float = 5.0) -> int:
    inbox: queue.Queue[bytes] = queue.Queue(maxsize=256)

    def on_sample(sample) -> None:
        payload = sample.payload.to_bytes()
        try:
            inbox.put_nowait(payload)
        except queue.Full:  # a stalled terminal must not grow memory: drop the oldest
            try:
                inbox.get_nowait()
            except queue.Empty:
                pass
            inbox.put_nowait(payload)

    key = topic("obstacles").key(robot) if robot else OBSTACLES_ALL
    seen = 0
    tty = sys.stdout.isatty() and not as_json
    with open_session(opts) as session:
        session.declare_subscriber(key, on_sample)
        if not as_json:
            print(f"watching {key} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        last = time.monotonic()
        hinted = False
        while count <= 0 or seen < count:
            try:
                payload = inbox.get(timeout=0.2)
            except queue.Empty:
                quiet = time.monotonic() - last
                if timeout_s and quiet > timeout_s:
                    print(f"no obstacle list on {key} within {timeout_s:g} s", file=sys.stderr)
                    return 1
                if not hinted and seen == 0 and quiet >= hint_after_s:
                    # once, on stderr: a planner reading --json from stdout is not disturbed
                    print(quiet_hint(key, quiet, opts), file=sys.stderr, flush=True)
                    hinted = True
                continue
            try:
                msg = codec.decode(payload, ObstacleList)
            except DecodeError as e:
                print(f"skipped a bad message: {e}", file=sys.stderr)
                continue
            last = time.monotonic()
            seen += 1
            if as_json:
                print(msg.model_dump_json(), flush=True)
            else:
                print(("\x1b[H\x1b[2J" if tty else "") + format_table(msg), flush=True)
    return 0
