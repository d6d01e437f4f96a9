"""Label-free evaluation of the segmenter on a real recording, through the real cores:

    image files -> Rectifier -> matcher (the disparity settings' method) -> ObstacleBuilder.process

The recordings (folders of pairs with a calibration) are read by evaluation/recordings.py; the
independent road model that judges flatness is evaluation/road_profile.py.

Without labels the figures are what a wrong segmenter cannot hide:
- obstacles per frame (median, max);
- flat obstacles: the share of obstacles with nothing higher than FLAT_HEIGHT_M above the road,
  judged with a ground model independent of the segmenter's (RoadProfile: a v-disparity line fitted
  per frame); a pixel's height above the road is cos(pitch) (v_road(d) - v) B / d, and an obstacle
  is flat when the 95th percentile height of its pixels (those in its box within a tolerance of
  its disparity) is below FLAT_HEIGHT_M;
- track life: the share of obstacle sightings within NEAR_M whose track id is seen in at least
  LONG_TRACK_FRAMES frames of the run, and the median number of frames a track id is seen in; and
  the same share leaving out short tracks the run's ends or the edge of the view cut short (what
  the tracker lost, not what the camera saw briefly);
- the segmenter's ground estimates (height, pitch, roll: median and 10th-90th percentile; sources),
  beside the independent road profile's height and pitch;
- segmentation time per frame (ObstacleBuilder.process only; matching is reported apart).
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from common.errors import BallbotError
from common.messages import GroundEstimate
from common.settings import MountSettings
from cores import camera
from cores.matching.opencv import Match
from cores.segmentation.builder import FrameResult
from evaluation.recordings import Recording
from evaluation.road_profile import fit_road_profile, obstacle_height_p95

FLAT_HEIGHT_M = 0.25  # an obstacle nothing of which stands higher above the road is flat
NEAR_M = 20.0  # the track-life figure counts obstacles this near
LONG_TRACK_FRAMES = 5
JUMP_M, JUMP_NEAR_M = 2.0, 12.0  # a track's ground position moving this far between sightings this near
RESTART_M, RESTART_FRAMES = 1.0, 3  # a new track this near a lost one, this soon after: the tracker lost it
# vision range for recordings when none is configured (the segmenter's default is a small robot's)
REAL_MAX_RANGE_M = 30.0
# Targets of issue 10, set for the Karlsruhe recording: (figure, comparison, value)
TARGETS = {"median_obstacles_per_frame": ("<=", 25.0), "flat_fraction": ("<=", 0.05),
           "near_long_track_fraction": (">=", 0.80)}


# --- the run -------------------------------------------------------------------------------------------

@dataclass
class ObstacleRecord:
    id: int
    distance_m: float
    confirmed: bool
    height_p95_m: float | None  # above the independent road profile; None: not judged
    flat: bool | None
    world_xy: tuple[float, float] | None = None  # where it stands, odometry-integrated ground frame (odometry only)
    speed_mps: float | None = None  # |velocity over the ground| (odometry only)
    whole: bool = True  # not truncated by the edge of the view
    track_frames: int = 1


@dataclass
class FrameRecord:
    seq: int
    left: str
    obstacles: list[ObstacleRecord]
    ground: dict | None  # GroundEstimate fields
    road: dict | None  # RoadProfile height_m, pitch_deg, support
    segment_ms: float
    match_ms: float
    saturated: float
    freespace_free: int = 0
    freespace_occupied: int = 0
    degraded: list[str] = field(default_factory=list)  # the list's reasons it cannot be trusted


@dataclass
class RealReport:
    recording: str
    calibration: str
    stamps: str
    odometry: bool
    frames: list[FrameRecord]
    settings: dict = field(default_factory=dict)
    figures: dict = field(default_factory=dict)
    pictures: str | None = None


def _ground_dict(g: GroundEstimate | None) -> dict | None:
    return None if g is None else g.model_dump()


@dataclass
class ProcessedFrame:
    """One pair through the cores: the rectified left image, the float disparity (px, NaN invalid),
    the matcher's result and the segmenter's FrameResult, with the times spent."""

    seq: int
    left_path: Path
    left: np.ndarray
    disparity: np.ndarray
    match: Match
    result: FrameResult
    model: camera.RectifiedModel
    segment_ms: float
    match_ms: float
    gate_px: float = 0.0  # the matcher's vision range gate (StageResult.gate_px)


def process_recording(rec: Recording, seg_settings, matcher_cfg, frames: int | None = None,
                      alpha: float = 0.0, mount: MountSettings | None = None) -> Iterator[ProcessedFrame]:
    """The first `frames` pairs (None: all) of the recording through the pipeline the services run
    (cores/pipeline.py: rectify, the matcher of `matcher_cfg` with num_disparities auto resolved for
    this camera and its range gate, one ObstacleBuilder whose tracks carry over from pair to pair;
    the matcher's confidence and the recording's odometry, where there are any, are passed on)."""
    from common.files import check_pair, read_image
    from cores.pipeline import Pipeline

    pipe = Pipeline(rec.calibration, matcher_cfg, seg_settings, alpha=alpha, mount=mount)
    n = len(rec.pairs) if frames is None else min(frames, len(rec.pairs))
    if n <= 0:
        raise BallbotError(f"{rec.root}: no pairs to process")
    for k in range(n):
        lp, rp = rec.pairs[k]
        left, right = read_image(lp), read_image(rp)
        check_pair(left, right, str(lp), str(rp))
        t_s = rec.stamps_s[k]
        odo = rec.odometry[k] if rec.odometry is not None else None
        f = pipe.process(left, right, t_s=t_s, seq=k, stamp_ns=int(round(t_s * 1e9)), odometry=odo,
                         names=(str(lp), str(rp)))
        yield ProcessedFrame(k, lp, f.left, f.disparity, f.stage.match, f.result, pipe.model, f.segment_ms,
                             f.match_ms, f.stage.gate_px)


def evaluate_recording(rec: Recording, seg_settings, matcher_cfg, frames: int | None = None,
                       draw_dir: str | Path | None = None, alpha: float = 0.0,
                       on_frame: Callable[[FrameRecord], None] | None = None,
                       mount: MountSettings | None = None) -> RealReport:
    """Run the first `frames` pairs (None: all) of the recording (process_recording) and judge each
    frame's obstacles; with draw_dir, one picture per pair (draw.draw_frame) named after the left image."""

    from common.files import output_folder, write_image
    from cores.segmentation.draw import draw_frame

    out = None if draw_dir is None else output_folder(draw_dir, "--draw")
    report = RealReport(rec.name, rec.calibration_source, rec.stamps_from, rec.odometry is not None, [],
                        pictures=str(out) if out else None)
    report.settings = {"segmenter": seg_settings.model_dump(), "disparity": None, "range_m": seg_settings.range_m,
                       "mount": (mount or MountSettings()).model_dump()}
    pose = np.zeros(3)  # x, y, yaw of the base frame in the first frame's, from the odometry
    last_t = None
    for pf in process_recording(rec, seg_settings, matcher_cfg, frames, alpha, mount):
        if report.settings["disparity"] is None:
            from cores.segmentation.builder import search_reach

            cfg = matcher_cfg.resolved(pf.model.focal_px, pf.model.baseline_m, pf.model.width)
            report.settings["disparity"] = cfg.model_dump()
            report.settings["search_warning"] = search_reach(pf.model, cfg.min_disparity, cfg.num_disparities,
                                                             seg_settings, pf.gate_px).message
        result, d = pf.result, pf.disparity
        road = fit_road_profile(d, pf.model)
        obs = []
        odo = rec.odometry[pf.seq] if rec.odometry is not None else None
        t_s = rec.stamps_s[pf.seq]
        if odo is not None and last_t is not None:
            dt = t_s - last_t
            pose[2] += odo.angular_radps[2] * dt
            c, s = np.cos(pose[2]), np.sin(pose[2])
            pose[:2] += np.array([[c, -s], [s, c]]) @ np.asarray(odo.linear_mps[:2], float) * dt
        last_t = t_s
        c, s = np.cos(pose[2]), np.sin(pose[2])
        for o in result.obstacles.obstacles:
            h95 = obstacle_height_p95(d, o.bbox_px, o.disparity_px, road) if road is not None else None
            world = speed = None
            if odo is not None and o.position_base_m is not None:
                w = pose[:2] + np.array([[c, -s], [s, c]]) @ np.asarray(o.position_base_m[:2], float)
                world = (float(w[0]), float(w[1]))
                if o.velocity_base_mps is not None:
                    speed = float(np.hypot(*o.velocity_base_mps[:2]))
            obs.append(ObstacleRecord(o.id, o.distance_m, o.confirmed, h95,
                                      None if h95 is None else bool(h95 < FLAT_HEIGHT_M), world, speed,
                                      not o.truncated, o.track_frames))
        fr = FrameRecord(pf.seq, pf.left_path.name, obs, _ground_dict(result.obstacles.ground),
                         None if road is None else {"height_m": road.height_m, "pitch_deg": road.pitch_deg,
                                                    "support": road.support},
                         pf.segment_ms, pf.match_ms, pf.match.saturated, degraded=list(result.obstacles.degraded))
        if result.freespace is not None:
            cells = np.frombuffer(result.freespace.cells, np.int8)
            fr.freespace_free = int(np.count_nonzero(cells == 0))
            fr.freespace_occupied = int(np.count_nonzero(cells == 100))
        report.frames.append(fr)
        if out is not None:
            pic = draw_frame(pf.left, result.obstacles, pf.model, result.freespace)  # the list's own mount
            write_image(out / f"{pf.left_path.stem}.png", pic, "--draw")
        if on_frame is not None:
            on_frame(fr)
    report.figures = figures(report.frames)
    return report


# --- figures -------------------------------------------------------------------------------------------

def _meets(value, op: str, target: float) -> bool | None:
    """Whether a figure meets its target (None: nothing measured)."""
    if not isinstance(value, (int, float)):
        return None
    return value <= target if op == "<=" else value >= target


def _stats(values: list[float]) -> dict | None:
    if not values:
        return None
    a = np.asarray(values, float)
    return {"median": float(np.median(a)), "p10": float(np.percentile(a, 10)), "p90": float(np.percentile(a, 90)),
            "n": int(a.size)}


def figures(frames: list[FrameRecord]) -> dict:
    counts = [len(f.obstacles) for f in frames]
    all_obs = [o for f in frames for o in f.obstacles]
    judged = [o for o in all_obs if o.flat is not None]
    seen: dict[int, int] = {}
    for f in frames:
        for i in {o.id for o in f.obstacles}:
            seen[i] = seen.get(i, 0) + 1
    near = [o for o in all_obs if o.distance_m <= NEAR_M]
    # a short track that was already there in the first frame or still there in the last may have
    # lived longer than the run shows (censored): the run's length, not the tracker, cut it short. So
    # may one whose first or last sighting was cut by the edge of the view (truncated: the image's
    # side, the matcher's blind band, the range): it came into view or left it, and the camera, not
    # the tracker, saw it so briefly (the street at 14 m/s: a post 3 m to the left is in view from
    # about 11 m to 7 m, 4 frames)
    first: dict[int, int] = {}
    last_k: dict[int, int] = {}
    first_cut: dict[int, bool] = {}  # its first sighting truncated
    last_cut: dict[int, bool] = {}  # its last sighting truncated
    for k, f in enumerate(frames):
        for o in f.obstacles:
            if o.id not in first:
                first[o.id] = k
                first_cut[o.id] = not o.whole
            last_k[o.id] = k
            last_cut[o.id] = not o.whole
    judged_life = [o for o in near if seen[o.id] >= LONG_TRACK_FRAMES
                   or (first[o.id] > 0 and last_k[o.id] < len(frames) - 1
                       and not first_cut[o.id] and not last_cut[o.id])]
    # track quality over the ground (with odometry): how often a track's ground position jumps more
    # than JUMP_M between consecutive sightings within JUMP_NEAR_M (a different object took its id,
    # or its detection changed shape), and, on a street that mostly stands still, the speed of whole
    # confirmed obstacles tracked for LONG_TRACK_FRAMES frames (their velocity error)
    last: dict[int, ObstacleRecord] = {}
    steps = []
    for f in frames:
        for o in f.obstacles:
            prev = last.get(o.id)
            if prev is not None and prev.world_xy and o.world_xy and max(prev.distance_m, o.distance_m) <= JUMP_NEAR_M:
                steps.append(float(np.hypot(o.world_xy[0] - prev.world_xy[0], o.world_xy[1] - prev.world_xy[1])))
            last[o.id] = o
    # what the tracker lost: a near track born (after the first frame) within RESTART_M over the
    # ground of where another was last seen in the RESTART_FRAMES frames before, the same thing
    # under a new id (odometry needed)
    restarts, births = 0, 0
    seen_at: dict[int, tuple[int, tuple[float, float]]] = {}
    for k, f in enumerate(frames):
        for o in f.obstacles:
            if first[o.id] == k and k > 0 and o.distance_m <= NEAR_M and o.world_xy:
                births += 1
                restarts += any(k - RESTART_FRAMES <= kl < k and np.hypot(xy[0] - o.world_xy[0], xy[1] - o.world_xy[1])
                                < RESTART_M and last_k[i] == kl for i, (kl, xy) in seen_at.items())
        for o in f.obstacles:
            if o.world_xy:
                seen_at[o.id] = (k, o.world_xy)
    speeds = [o.speed_mps for o in all_obs if o.speed_mps is not None and o.whole and o.confirmed
              and o.track_frames >= LONG_TRACK_FRAMES and o.distance_m <= NEAR_M]
    grounds = [f.ground for f in frames if f.ground is not None]
    sources: dict[str, int] = {}
    for g in grounds:
        sources[g["source"]] = sources.get(g["source"], 0) + 1
    fitted = [g for g in grounds if g["source"] in ("fitted", "tracked")]
    degraded: dict[str, int] = {}
    for f in frames:
        for reason in f.degraded:
            degraded[reason] = degraded.get(reason, 0) + 1
    roads = [f.road for f in frames if f.road is not None]
    out = {
        "frames": len(frames),
        "obstacles": len(all_obs),
        "median_obstacles_per_frame": float(np.median(counts)) if counts else 0.0,
        "max_obstacles_per_frame": int(max(counts)) if counts else 0,
        "confirmed_fraction": (sum(o.confirmed for o in all_obs) / len(all_obs)) if all_obs else None,
        "flat_fraction": (sum(bool(o.flat) for o in judged) / len(judged)) if judged else None,
        "flat_judged": len(judged),
        "near_obstacles": len(near),
        "near_long_track_fraction": (sum(seen[o.id] >= LONG_TRACK_FRAMES for o in near) / len(near)) if near else None,
        "near_confirmed_long_track_fraction": (sum(seen[o.id] >= LONG_TRACK_FRAMES for o in near if o.confirmed)
                                               / max(1, sum(o.confirmed for o in near))) if near else None,
        "near_long_track_fraction_uncensored": (sum(seen[o.id] >= LONG_TRACK_FRAMES for o in judged_life)
                                                / len(judged_life)) if judged_life else None,
        "near_censored": len(near) - len(judged_life),
        "tracks": len(seen),
        "median_track_frames": float(np.median(list(seen.values()))) if seen else None,
        "track_jump_fraction": (sum(x > JUMP_M for x in steps) / len(steps)) if steps else None,
        "track_steps": len(steps),
        "track_restart_fraction": (restarts / births) if births else None,
        "near_births": births,
        "static_speed_mps": _stats(speeds),
        "ground_sources": sources,
        "ground_confidence": _stats([g.get("confidence", 0.0) for g in grounds]),
        "degraded_frames": degraded,
        "ground_height_m": _stats([g["height_m"] for g in fitted]),
        "ground_pitch_deg": _stats([g["pitch_deg"] for g in fitted]),
        "ground_roll_deg": _stats([g["roll_deg"] for g in fitted]),
        "road_profile_frames": len(roads),
        "road_height_m": _stats([r["height_m"] for r in roads]),
        "road_pitch_deg": _stats([r["pitch_deg"] for r in roads]),
        "segment_ms": _stats([f.segment_ms for f in frames]),
        "match_ms": _stats([f.match_ms for f in frames]),
        "saturated_max": max((f.saturated for f in frames), default=0.0),
    }
    out["targets"] = {name: {"value": out[name], "target": f"{op} {val:g}", "met": _meets(out[name], op, val)}
                      for name, (op, val) in TARGETS.items()}
    return out


def report_to_json(report: RealReport) -> dict:
    return asdict(report)


def _fmt_stats(s: dict | None, unit: str, digits: int = 2) -> str:
    if s is None:
        return "-"
    return f"{s['median']:.{digits}f} {unit} (p10 {s['p10']:.{digits}f}, p90 {s['p90']:.{digits}f}, n {s['n']})"


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:.1%}"


def format_report(report: RealReport) -> str:
    f = report.figures
    seg = report.settings.get("segmenter", {})
    disp = report.settings.get("disparity", {})
    t = f["targets"]

    def target(name: str) -> str:
        v = t[name]
        mark = "-" if v["met"] is None else ("met" if v["met"] else "NOT met")
        return f"[target {v['target']} (Karlsruhe): {mark}]"

    m = report.settings.get("mount") or {}
    mount = ("unknown (fitted per frame)" if m.get("height_m") is None else
             f"h {m['height_m']} m, pitch {m['pitch_deg']} deg, roll {m['roll_deg']} deg")
    lines = [
        f"recording {report.recording}: {f['frames']} frame(s); calibration {report.calibration}; "
        f"stamps from {report.stamps}; odometry {'insdata.txt' if report.odometry else 'none'}",
        f"segmenter {seg.get('method')}, range {seg.get('min_range_m')}..{report.settings.get('range_m')} m, "
        f"mount {mount}; disparity {disp.get('method')}, {disp.get('num_disparities')} px searched",
        f"  obstacles per frame      median {f['median_obstacles_per_frame']:g}, max {f['max_obstacles_per_frame']}"
        f"  {target('median_obstacles_per_frame')}",
        f"  flat (p95 < {FLAT_HEIGHT_M} m above road) {_pct(f['flat_fraction'])} of {f['flat_judged']} judged "
        f"(of {f['obstacles']})  {target('flat_fraction')}",
        f"  near (<= {NEAR_M:g} m) in tracks seen >= {LONG_TRACK_FRAMES} frames  {_pct(f['near_long_track_fraction'])} "
        f"of {f['near_obstacles']}  {target('near_long_track_fraction')}; of the confirmed ones "
        f"{_pct(f['near_confirmed_long_track_fraction'])}; leaving out the {f['near_censored']} of short tracks "
        f"cut short by the run's first or last frame or by the edge of the view (first or last sighting "
        f"truncated) {_pct(f['near_long_track_fraction_uncensored'])}",
        f"  tracks {f['tracks']}, median frames per track {f['median_track_frames']}, "
        f"confirmed {_pct(f['confirmed_fraction'])} of sightings",
        f"  track jumps > {JUMP_M:g} m over the ground (within {JUMP_NEAR_M:g} m)  "
        f"{_pct(f['track_jump_fraction'])} of {f['track_steps']} steps (odometry needed)",
        f"  tracks lost and restarted (a near track born within {RESTART_M:g} m over the ground of one last "
        f"seen in the {RESTART_FRAMES} frames before)  {_pct(f['track_restart_fraction'])} of {f['near_births']} "
        f"births (odometry needed)",
        f"  speed over the ground of whole confirmed tracks (a parked street: the velocity error)  "
        f"{_fmt_stats(f['static_speed_mps'], 'm/s', 1)}",
        f"  ground (segmenter)       sources {f['ground_sources'] or '-'}; confidence "
        f"{_fmt_stats(f.get('ground_confidence'), '')}",
        f"  degraded lists           {f.get('degraded_frames') or 'none'}",
        f"    height {_fmt_stats(f['ground_height_m'], 'm')}",
        f"    pitch  {_fmt_stats(f['ground_pitch_deg'], 'deg')}",
        f"    roll   {_fmt_stats(f['ground_roll_deg'], 'deg')}",
        f"  road profile (independent v-disparity fit, {f['road_profile_frames']} frames)",
        f"    height {_fmt_stats(f['road_height_m'], 'm')}",
        f"    pitch  {_fmt_stats(f['road_pitch_deg'], 'deg')}",
        f"  segmentation {_fmt_stats(f['segment_ms'], 'ms', 1)}; matching {_fmt_stats(f['match_ms'], 'ms', 1)}",
    ]
    if report.settings.get("search_warning"):
        lines.append(f"  warning: {report.settings['search_warning']}")
    if f["saturated_max"] > 0.01:
        lines.append(f"  warning: up to {f['saturated_max']:.1%} of matched pixels at the top of the disparity search "
                     "range: nearer things than it covers (raise --disparity-num-disparities)")
    if report.pictures:
        lines.append(f"  pictures: {report.pictures}/")
    return "\n".join(lines)


def format_frame(fr: FrameRecord) -> str:
    g = fr.ground
    ground = "-" if g is None else f"h {g['height_m']:.2f} p {g['pitch_deg']:+.1f} r {g['roll_deg']:+.1f} {g['source']}"
    flat = sum(bool(o.flat) for o in fr.obstacles)
    return (f"  {fr.seq:3d} {fr.left}: {len(fr.obstacles):3d} obstacles ({flat} flat), ground {ground}, "
            f"{fr.segment_ms:.0f} ms")
