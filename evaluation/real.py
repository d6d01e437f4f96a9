"""Label-free evaluation of the segmenter on a real recording, through the real cores:

    image files -> Rectifier -> matcher (the disparity settings' method) -> ObstacleBuilder.process

A recording is a folder in one of two layouts (see ../shared/data/real/README.md):
- `left/` and `right/` image folders (paired by name, else in order) and `calibration.yaml` (this
  program's format), optionally `insdata.txt` (INS poses, one line per pair: odometry and stamps);
- EuRoC: `cam0/` and `cam1/` (or `cam0/data/`, `cam1/data/`) and the two sensor yamls
  (`cam0_sensor.yaml` + `cam1_sensor.yaml`, or `cam0/sensor.yaml` + `cam1/sensor.yaml`), imported
  in-process as `calibration import` does; the raw pairs are rectified. Image names that are
  nanosecond stamps give the frame times.

Without labels the figures are what a wrong segmenter cannot hide:
- obstacles per frame (median, max);
- flat obstacles: the share of obstacles with nothing higher than FLAT_HEIGHT_M above the road,
  judged with a ground model independent of the segmenter's (RoadProfile: a v-disparity line fitted
  per frame); a pixel's height above the road is cos(pitch) (v_road(d) - v) B / d, and an obstacle
  is flat when the 95th percentile height of its pixels (those in its box within a tolerance of
  its disparity) is below FLAT_HEIGHT_M;
- track life: the share of obstacle sightings within NEAR_M whose track id is seen in at least
  LONG_TRACK_FRAMES frames of the run, and the median number of frames a track id is seen in;
- the segmenter's ground estimates (height, pitch, roll: median and 10th-90th percentile; sources),
  beside the independent road profile's height and pitch;
- segmentation time per frame (ObstacleBuilder.process only; matching is reported apart).

insdata.txt (Karlsruhe; the column convention is inferred and checked against the data, see
read_insdata): timestamp ns, latitude deg, longitude deg, altitude m, x m (east), y m (north),
z m (up, equal to the altitude), roll rad, pitch rad, yaw rad (heading, counter-clockwise from x =
east). Checked: the displacement between lines agrees with latitude/longitude (x with east, y with
north, ~1.26 m and -0.10 m per 0.1 s at the start); the direction of travel atan2(dy, dx) matches
yaw within 1 deg; the speed is ~12.4 m/s falling to ~9 m/s, forward. The pitch column is not
usable (a constant ~2.07 rad, one line -0.001): it is not read.
"""
from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from common.errors import BallbotError
from common.messages import GroundEstimate, Odometry
from common.settings import MountSettings
from cores import camera
from cores.matching.opencv import Match
from cores.segmentation.builder import FrameResult

FLAT_HEIGHT_M = 0.25  # an obstacle nothing of which stands higher above the road is flat
NEAR_M = 20.0  # the track-life figure counts obstacles this near
LONG_TRACK_FRAMES = 5
JUMP_M, JUMP_NEAR_M = 2.0, 12.0  # a track's ground position moving this far between sightings this near
# vision range for recordings when none is configured (the segmenter's default is a small robot's)
REAL_MAX_RANGE_M = 30.0
# Targets of issue 10, set for the Karlsruhe recording: (figure, comparison, value)
TARGETS = {"median_obstacles_per_frame": ("<=", 25.0), "flat_fraction": ("<=", 0.05),
           "near_long_track_fraction": (">=", 0.80)}
INSDATA_COLUMNS = ("stamp_ns", "lat_deg", "lon_deg", "alt_m", "x_east_m", "y_north_m", "z_up_m",
                   "roll_rad", "pitch_rad", "yaw_rad")
_NS_STAMP = re.compile(r"^\d{16,20}$")


# --- the recording -------------------------------------------------------------------------------

@dataclass
class Recording:
    root: Path
    pairs: list[tuple[Path, Path]]
    calibration: camera.Calibration
    calibration_source: str
    stamps_s: list[float]  # per pair, seconds (relative clock)
    stamps_from: str  # where the stamps came from
    odometry: list[Odometry] | None = None  # per pair, base frame

    @property
    def name(self) -> str:
        return self.root.name


def _first(root: Path, *names: str) -> Path | None:
    return next((root / n for n in names if (root / n).exists()), None)


def open_recording(root: str | Path, fps: float = 10.0) -> Recording:
    """A recording folder (layouts in the module doc) -> its pairs, calibration, stamps, odometry."""
    from common.files import list_images, pair_images
    from cores.calibration.formats import import_files

    root = Path(root).expanduser()
    if not root.is_dir():
        raise BallbotError(f"--real {root}: not a folder")
    left_dir = _first(root, "left", "cam0/data", "cam0")
    right_dir = _first(root, "right", "cam1/data", "cam1")
    if left_dir is None or right_dir is None:
        raise BallbotError(f"--real {root}: expected left/ and right/ (with calibration.yaml) or EuRoC's cam0/ "
                           "and cam1/ (with their sensor yamls)")
    pairs = pair_images(list_images(str(left_dir), "left images"), list_images(str(right_dir), "right images"))
    cal_file = _first(root, "calibration.yaml", "calibration.yml")
    sensors = [_first(root, f"cam{k}_sensor.yaml", f"cam{k}/sensor.yaml") for k in (0, 1)]
    if cal_file is not None:
        cal, cal_source = camera.load_calibration(cal_file), cal_file.name
    elif sensors[0] is not None and sensors[1] is not None:
        cal = import_files([str(s) for s in sensors], name=root.name)
        cal_source = f"{sensors[0].relative_to(root)} + {sensors[1].relative_to(root)} (EuRoC, imported)"
    else:
        raise BallbotError(f"--real {root}: no calibration.yaml and no EuRoC cam0/cam1 sensor yamls")
    rec = Recording(root, pairs, cal, cal_source, [k / fps for k in range(len(pairs))], f"{fps:g} fps (--fps)")
    ins = root / "insdata.txt"
    stems = [p.stem for p, _ in pairs]
    if ins.exists():
        poses = read_insdata(ins)
        if len(poses) != len(pairs):
            raise BallbotError(f"{ins}: {len(poses)} poses for {len(pairs)} pairs (expected one line per pair)")
        rec.stamps_s = list((poses[:, 0] - poses[0, 0]) / 1e9)
        rec.stamps_from = "insdata.txt"
        rec.odometry = odometry_from_poses(poses)
    elif stems and all(_NS_STAMP.match(s) for s in stems):
        t0 = int(stems[0])
        rec.stamps_s = [(int(s) - t0) / 1e9 for s in stems]
        rec.stamps_from = "image names (ns)"
    return rec


def recording_from_files(left: str, right: str, calibration: str, fps: float = 10.0) -> Recording:
    """LEFT and RIGHT (folders, globs or files, paired as everywhere) with a calibration -> a Recording
    (stamps from nanosecond image names, else `fps`; no odometry)."""
    from common.files import list_images, pair_images

    pairs = pair_images(list_images(left, "LEFT"), list_images(right, "RIGHT"))
    rec = Recording(Path(left), pairs, camera.load_calibration(calibration), str(calibration),
                    [k / fps for k in range(len(pairs))], f"{fps:g} fps (--fps)")
    stems = [p.stem for p, _ in pairs]
    if stems and all(_NS_STAMP.match(s) for s in stems):
        rec.stamps_s = [(int(s) - int(stems[0])) / 1e9 for s in stems]
        rec.stamps_from = "image names (ns)"
    return rec


def read_insdata(path: str | Path) -> np.ndarray:
    """(N, 10) float64, columns INSDATA_COLUMNS (module doc). Refuses a file whose positions and
    headings disagree with that convention (the direction of travel within 10 deg of yaw)."""
    try:
        a = np.loadtxt(path, ndmin=2)
    except ValueError as e:
        raise BallbotError(f"{path}: not a table of numbers ({e})") from None
    if a.shape[1] != len(INSDATA_COLUMNS):
        raise BallbotError(f"{path}: {a.shape[1]} columns, expected {len(INSDATA_COLUMNS)} "
                           f"({', '.join(INSDATA_COLUMNS)})")
    if len(a) >= 2:
        step = np.hypot(np.diff(a[:, 4]), np.diff(a[:, 5]))
        moving = step > 0.05
        if moving.any():
            travel = np.arctan2(np.diff(a[:, 5]), np.diff(a[:, 4]))[moving]
            off = np.angle(np.exp(1j * (travel - a[:-1, 9][moving])))
            if np.median(np.abs(off)) > math.radians(10):
                raise BallbotError(f"{path}: the direction of travel differs from the yaw column by "
                                   f"{math.degrees(float(np.median(np.abs(off)))):.0f} deg: not the expected "
                                   f"convention ({', '.join(INSDATA_COLUMNS)})")
    return a


def odometry_from_poses(poses: np.ndarray, robot_id: str = "offline") -> list[Odometry]:
    """INS poses (read_insdata) -> per line the base-frame motion: linear velocity (x forward along
    the heading, y left; z 0: the vehicle moves along the road, the base frame's plane) from the
    positions by central differences, angular velocity (0, 0, yaw rate) from the unwrapped yaw."""
    t = (poses[:, 0] - poses[0, 0]) / 1e9
    yaw = np.unwrap(poses[:, 9])
    if len(poses) < 2:
        return [Odometry(robot_id=robot_id, seq=0, stamp_ns=int(poses[0, 0]), linear_mps=(0.0, 0.0, 0.0),
                         source="insdata.txt")]
    ve, vn = np.gradient(poses[:, 4], t), np.gradient(poses[:, 5], t)
    rate = np.gradient(yaw, t)
    fwd = np.cos(yaw) * ve + np.sin(yaw) * vn
    left = -np.sin(yaw) * ve + np.cos(yaw) * vn
    return [Odometry(robot_id=robot_id, seq=k, stamp_ns=int(poses[k, 0]),
                     linear_mps=(float(fwd[k]), float(left[k]), 0.0), angular_radps=(0.0, 0.0, float(rate[k])),
                     source="insdata.txt") for k in range(len(poses))]


# --- the independent ground model ------------------------------------------------------------------

@dataclass(frozen=True)
class RoadProfile:
    """The road in v-disparity: d = slope * (v - horizon_v) on the rectified left image (a flat road
    without roll seen by a camera pitched by theta: slope = B cos(theta) / h, horizon_v = cy - f tan(theta)).
    Independent of the segmenter's ground fit: a robust line in the lower image's d-vs-v histogram."""

    slope: float  # px of disparity per image row
    horizon_v: float  # row, px
    support: float  # share of the lower image's valid pixels on the line
    focal_px: float
    cy: float
    baseline_m: float

    @property
    def pitch_deg(self) -> float:
        return math.degrees(math.atan2(self.cy - self.horizon_v, self.focal_px))

    @property
    def height_m(self) -> float:
        return self.baseline_m * math.cos(math.radians(self.pitch_deg)) / self.slope

    def road_row(self, d: np.ndarray) -> np.ndarray:
        return self.horizon_v + np.asarray(d) / self.slope

    def height_above(self, v: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Height (m) above the road of pixels at rows v with disparities d (> 0)."""
        d = np.asarray(d, np.float64)
        return math.cos(math.radians(self.pitch_deg)) * (self.road_row(d) - v) * self.baseline_m / d


def fit_road_profile(disparity: np.ndarray, model: camera.RectifiedModel, min_height_m: float = 0.1,
                     max_height_m: float = 10.0, hypotheses: int = 300, seed: int = 0) -> RoadProfile | None:
    """disparity: (H, W) float px, NaN invalid. The v-disparity histogram of the lower half of the
    image (1 px disparity bins), then RANSAC over lines through two of its occupied cells (drawn by
    count) whose slope puts the camera min_height_m..max_height_m above the road, scored by the pixel
    count within 1 px + 3 % of the line; refined by count-weighted least squares on the inliers.
    None: too few valid pixels or no line with 5 % support."""
    h, w = disparity.shape
    v0 = h // 2
    d = disparity[v0:]
    ok = np.isfinite(d) & (d > 0.5)
    if np.count_nonzero(ok) < 200:
        return None
    rows = np.broadcast_to(np.arange(v0, h)[:, None], d.shape)[ok]
    bins = np.round(d[ok]).astype(np.int64)
    nd = int(bins.max()) + 1
    hist = np.bincount((rows - v0) * nd + bins, minlength=(h - v0) * nd).reshape(h - v0, nd).astype(np.float64)
    hist[:, 0] = 0
    vv, dd = np.nonzero(hist)
    cnt = hist[vv, dd]
    vv = vv + v0
    total = float(cnt.sum())
    B = model.baseline_m
    lo, hi = B / max_height_m, B / min_height_m
    rng = np.random.default_rng(seed)
    p = cnt / total
    i = rng.choice(len(cnt), size=hypotheses, p=p)
    j = rng.choice(len(cnt), size=hypotheses, p=p)
    dv = (vv[j] - vv[i]).astype(np.float64)
    good = np.abs(dv) >= 2
    slope = np.where(good, (dd[j] - dd[i]) / np.where(good, dv, 1.0), 0.0)
    good &= (slope >= lo) & (slope <= hi)
    if not good.any():
        return None
    slope = slope[good]
    hv = vv[i][good] - dd[i][good] / slope  # the horizon row of each candidate line

    def inliers(s: float, v_h: float) -> np.ndarray:
        pred = s * (vv - v_h)
        return (pred > 0) & (np.abs(dd - pred) <= 1.0 + 0.03 * pred)

    scores = [cnt[inliers(s, v_h)].sum() for s, v_h in zip(slope, hv)]
    k = int(np.argmax(scores))
    s, v_h = float(slope[k]), float(hv[k])
    for _ in range(3):
        m = inliers(s, v_h)
        if m.sum() < 3:
            return None
        wts, x, y = cnt[m], vv[m].astype(np.float64), dd[m].astype(np.float64)
        xm, ym = np.average(x, weights=wts), np.average(y, weights=wts)
        var = np.average((x - xm) ** 2, weights=wts)
        if var <= 0:
            return None
        s_new = float(np.average((x - xm) * (y - ym), weights=wts) / var)
        if not lo <= s_new <= hi:
            break
        s, v_h = s_new, float(xm - ym / s_new)
    support = float(cnt[inliers(s, v_h)].sum() / total)
    if support < 0.05:
        return None
    return RoadProfile(s, v_h, support, model.focal_px, model.cy, B)


def obstacle_height_p95(disparity: np.ndarray, bbox: tuple[int, int, int, int], disparity_px: float,
                        road: RoadProfile, rel_tol: float = 0.1, min_pixels: int = 10) -> float | None:
    """95th percentile height (m) above the road of the obstacle's pixels: those in its box whose
    disparity is within max(1 px, rel_tol * d) of its own. None with fewer than min_pixels."""
    h, w = disparity.shape
    x0, y0, x1, y1 = bbox
    x0, x1 = max(0, x0), min(w, x1)
    y0, y1 = max(0, y0), min(h, y1)
    if x1 <= x0 or y1 <= y0:
        return None
    box = disparity[y0:y1, x0:x1]
    tol = max(1.0, rel_tol * disparity_px)
    m = np.isfinite(box) & (box > 0.5) & (np.abs(box - disparity_px) <= tol)
    if np.count_nonzero(m) < min_pixels:
        return None
    v = np.broadcast_to(np.arange(y0, y1)[:, None], box.shape)[m]
    return float(np.percentile(road.height_above(v, box[m]), 95))


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
                             f.match_ms)


def evaluate_recording(rec: Recording, seg_settings, matcher_cfg, frames: int | None = None,
                       draw_dir: str | Path | None = None, alpha: float = 0.0,
                       on_frame: Callable[[FrameRecord], None] | None = None,
                       mount: MountSettings | None = None) -> RealReport:
    """Run the first `frames` pairs (None: all) of the recording (process_recording) and judge each
    frame's obstacles; with draw_dir, one picture per pair (draw.draw_frame) named after the left image."""
    import cv2

    from common.errors import path_error
    from cores.segmentation.draw import draw_frame

    out = None
    if draw_dir is not None:
        out = Path(draw_dir)
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise BallbotError(f"--draw {out}: {path_error(e)}") from None
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
                                                             seg_settings).message
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
            path = out / f"{pf.left_path.stem}.png"
            if not cv2.imwrite(str(path), pic):
                raise BallbotError(f"{path}: cannot write")
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
    # lived longer than the run shows (censored): the run's length, not the tracker, cut it short
    first: dict[int, int] = {}
    last_k: dict[int, int] = {}
    for k, f in enumerate(frames):
        for o in f.obstacles:
            first.setdefault(o.id, k)
            last_k[o.id] = k
    judged_life = [o for o in near if seen[o.id] >= LONG_TRACK_FRAMES
                   or (first[o.id] > 0 and last_k[o.id] < len(frames) - 1)]
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
        f"cut by the run's first or last frame {_pct(f['near_long_track_fraction_uncensored'])}",
        f"  tracks {f['tracks']}, median frames per track {f['median_track_frames']}, "
        f"confirmed {_pct(f['confirmed_fraction'])} of sightings",
        f"  track jumps > {JUMP_M:g} m over the ground (within {JUMP_NEAR_M:g} m)  "
        f"{_pct(f['track_jump_fraction'])} of {f['track_steps']} steps (odometry needed)",
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
