"""One stream of disparity maps -> obstacle lists and free space (the segmenter's core, no Zenoh):
ObstacleBuilder carries the ground estimate and the tracks from frame to frame; the segmenter
service (services/segmenter) feeds it the maps it receives, the offline commands, the evaluations
and the benchmarks feed it theirs."""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from common import codec
from common.errors import DecodeError
from common.messages import DisparityMap, FrameChecks, FreeSpace, Obstacle, ObstacleList, Odometry
from common.settings import MountSettings
from cores import camera
from cores.calibration.check import SWAPPED_SHARE
from cores.calibration.near import CONTRADICTED_SHARE, contradicted, map_cells
from cores.matching.disparity import FrozenInput, RecentValid, searched_range, to_float
from cores.segmentation import freespace, layers, seed, stats
from cores.segmentation.blank import MEASURED
from cores.segmentation.ground import TRUSTED, GroundEstimator, Upright, frame_mount
from cores.segmentation.mount import FloorPlane, Mount
from cores.segmentation.near import UNLISTED_SHARE, NearStanding, near_standing, unlisted_standing
from cores.segmentation.seed import Detection
from cores.segmentation.settings import SegmenterSettings
from cores.segmentation.tracking import Tracker
from cores.segmentation.washout import WASHED_OUT, washed_out_share

log = logging.getLogger("ballbot")

# A map measuring less of the image than this saw nothing it could vouch for: the list says so.
MIN_VALID_FRACTION = 0.01
# ... and less than this too little to vouch for what it did not list: "little-measured". The dark comes
# on slowly (dusk, a corridor with the lights off), too slowly for valid-collapse, and the matcher
# measures less and less while the list empties. The street darkened to 8 % of its light (sensor noise
# as a camera's gain brings it up): bm measured 5-6 % of the picture and listed 9 of its 18 things;
# at 4 %, 1-2 % measured, empty lists, and until now no reason at all (mount configured, fit_floor
# false). The recordings in daylight measure 27-30 % (the street, bm: sky and plain road) and more;
# every shipped scene 48 % or more, whatever the matcher.
LITTLE_MEASURED = 0.10
# Dusk before that: the camera's gain brings the pictures up with their noise, and block matching's
# texture and uniqueness tests reject more of them long before the map measures under a tenth. The street
# at 20 % of its light (noise 7.7 grey levels, cores/calibration/check.py picture_noise): bm measured 15 %
# and found 58 % of what it found within 15 m in daylight, half its lists saying nothing; at 15 % (9.9
# grey levels), 36 % with 5 lists of 14 saying nothing; at 30 % (5.4), 85 %. Daylight's pictures, the
# street's, the room's and the synthetic scenes', are at 1.2-2.0. Noisier than this: "noisy".
NOISY_GREY = 6.0
# A map measuring less than half of what the maps of the last 2 s measured (a covered lens, glare, a
# broken matcher) is flagged "valid-collapse" until it is no longer a sudden change (cores/matching/disparity.py).
COLLAPSE_FACTOR, COLLAPSE_WINDOW_S, COLLAPSE_WARMUP_FRAMES = 0.5, 2.0, 5


def measured_share(disparity: np.ndarray, confidence: np.ndarray | None, min_confidence: int = MEASURED,
                   flat: np.ndarray | None = None) -> float:
    """The share of the picture the matcher measured and the segmenter uses: a valid disparity, and
    where the matcher gives a confidence, at least min_confidence (the segmenter's, never below
    blank.MEASURED), and where it says which windows were too plain to decide their match (flat:
    sgbm carries a disparity into them from around them), not those. `dense` fills every pixel its
    measurements reach, so its valid share stays near 1 in the dark as in daylight, and only its
    confidence tells what it saw: the street in daylight 0.41-0.44 of the picture at 200 (the
    segmenter's default), at 4 % of the light 0.05."""
    valid = disparity > 0  # NaN compares false
    if confidence is not None and confidence.shape == disparity.shape:
        valid &= confidence >= max(MEASURED, min_confidence)
    if flat is not None and flat.shape == disparity.shape:
        valid &= ~flat
    return float(np.count_nonzero(valid)) / max(1, disparity.size)


@dataclass(frozen=True)
class Reach:
    """Whether a disparity search (min_disparity, num_disparities px, and the matcher's vision range
    gate) can measure the segmenter's vision range (min_range_m..range_m) with this camera:
    `unreachable` when the two do not overlap at all (every list from such a map says
    "range-unreachable"); `near_unmeasured` when the search misses the near part of the range (every
    list says "near-unmeasured": what stands that near is not measured, and block matching aliases it
    to a farther false depth); `far_unmeasured` when it misses the far part (every list says
    "far-unmeasured": what stands farther is in no list, and matching aliases it to a nearer false
    depth); `message` says which."""

    unreachable: bool
    message: str
    near_unmeasured: bool = False
    far_unmeasured: bool = False
    near_m: float = 0.0  # the nearest and farthest depth the search measures, m
    far_m: float = math.inf

    def looked_at(self, lo: float, hi: float) -> tuple[float, float]:
        """The part of the vision range lo..hi (m) a list from such a map looked at: where it says
        near- or far-unmeasured, what the search measures of it ("looked and saw nothing" covers no
        more); else lo..hi (a few centimetres short is no news)."""
        if self.unreachable:
            return lo, hi
        return (max(lo, self.near_m) if self.near_unmeasured else lo,
                min(hi, self.far_m) if self.far_unmeasured else hi)


def view_bearings(model: camera.RectifiedModel, min_disparity: int, num_disparities: int) -> tuple[float, float]:
    """The bearings (deg from the optical axis, positive right) of the leftmost and rightmost columns
    a search (min_disparity, num_disparities px) measures at every distance it reaches: left of
    x = min_disparity + num_disparities the right camera does not see what stands at the nearest of
    them (bm and sgbm leave that band unmatched at any distance; dense, and bm and sgbm with
    match_band, match it only where the partner is in view). On the Karlsruhe car's rig, 320 px of
    1344: 18.5 deg of its 92."""
    left = float(np.clip(min_disparity + num_disparities, 0, model.width - 1))

    def bearing(u: float) -> float:
        return float(np.degrees(np.arctan2(u - model.cx, model.focal_px)))
    return bearing(left), bearing(model.width - 1.0)


# How far beyond min_range_m the nearest depth the search measures may lie before the lists say
# "near-unmeasured": a few centimetres short is no news (the Karlsruhe car's `auto` search, capped at a
# quarter of the image width, measures from 1.15 m for a 1 m range); 1 m short of a 1 m range is a
# blind spot where a robot meets its obstacles. The same factor short of the range's far end: "far-unmeasured".
NEAR_SLACK = 1.25


def search_reach(model: camera.RectifiedModel, min_disparity: int, num_disparities: int,
                 settings: SegmenterSettings, gate_px: float = 0.0) -> Reach:
    """gate_px: the matcher's vision range gate (DisparityMap.gate_px; 0: none), which drops what lies
    farther, like a larger min_disparity."""
    fB = model.focal_px * abs(model.baseline_m)
    d_max = min_disparity + num_disparities - 1  # largest disparity searched: the nearest depth measured
    d_min = max(float(min_disparity), float(gate_px))  # smallest kept: the farthest depth measured
    near_m = fB / d_max if d_max > 0 else float("inf")
    far_m = fB / d_min if d_min > 0 else float("inf")
    lo, hi = settings.min_range_m, settings.range_for(model)
    gated = gate_px > max(0, min_disparity)
    gate = f", gated at {gate_px:.1f} px (the disparity stage's max_range_m)" if gated else ""
    search = (f"the disparity search ({min_disparity}..{d_max} px{gate} with f*B = {fB:.1f} px m) measures "
              f"{near_m:.2f} m" + (f"..{far_m:.2f} m" if math.isfinite(far_m) else " and farther"))
    if near_m > hi or far_m < lo:
        return Reach(True, f"{search}, the segmenter's vision range is {lo:g}..{hi:g} m: they do not overlap, "
                           "nothing in view can be measured; raise num_disparities (auto: from the calibration "
                           "and min_range_m) or change the range")
    near = near_m > NEAR_SLACK * lo
    far = far_m * NEAR_SLACK < hi
    said = []
    if near:
        said.append(f"nothing nearer than {near_m:.2f} m is measured, though the vision range starts at {lo:g} m, "
                    f"so every list says near-unmeasured (raise num_disparities, or num_disparities auto; or "
                    f"min_range_m to {near_m:.2f} m if nothing nearer matters)")
    if far:
        lower = "lower min_disparity" + (", or raise or unset the disparity stage's max_range_m" if gated else "")
        said.append(f"nothing farther than {far_m:.2f} m is measured, though the vision range reaches {hi:g} m, "
                    f"so every list says far-unmeasured ({lower}; or the segmenter's max_range_m to {far_m:.2f} m "
                    f"if nothing farther matters)")
    if said:
        return Reach(False, f"{search}: " + "; and ".join(said), near_unmeasured=near, far_unmeasured=far,
                     near_m=near_m, far_m=far_m)
    return Reach(False, "", near_m=near_m, far_m=far_m)


def floor_in_view(floor: FloorPlane, model: camera.RectifiedModel, range_m: float) -> bool:
    """Whether the camera sees any of the floor within range_m: the nearest floor in view lies at the
    image's bottom edge (at a corner: the floor's disparity is linear along the row). A car's camera
    1.6 m up, pitched 6 deg down, sees the road from 4.3 m: with a 3 m range, nothing low in the range
    can be in view, and an empty list would say so only by accident."""
    bottom = floor.b * (model.height - 1.0) + floor.c
    nearest = bottom + max(0.0, floor.a * (model.width - 1.0))
    return bool(nearest >= model.focal_px * abs(model.baseline_m) / range_m)


@dataclass
class FrameResult:
    """One frame's output: the public obstacle list, the free-space grid (None without a ground or
    for seed) and the disparity-space floor plane used (None: no floor removed)."""

    obstacles: ObstacleList
    freespace: FreeSpace | None
    floor: FloorPlane | None


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class ObstacleBuilder:
    """Disparity -> ground, obstacles, tracks and free space (pure: no Zenoh). Stateful: the ground
    estimate and the tracks carry over from frame to frame, so feed it one stream in order."""

    def __init__(self, settings: SegmenterSettings, mount: MountSettings | None = None):
        """mount: the `mount:` settings (None: none configured): the ground's prior, and the yaw and
        offsets of the base frame."""
        self.settings = settings
        self.configured = mount or MountSettings()
        self.mount = Mount.of(self.configured)
        self.ground = GroundEstimator(settings, self.mount)
        # a balancing robot (a pivot configured): the upright mount its lean is measured from, from the data
        self.upright = Upright(self.mount) if self.configured.pivot_height_m is not None else None
        self.tracker = Tracker(settings.track_gate_m, settings.track_timeout_s,
                               max_speed_mps=settings.track_max_speed_mps, confirm_m=settings.track_confirm_m,
                               confirm_n=settings.track_confirm_n)
        self._track_frame = ""  # "base" or "camera": the frame the tracks are kept in
        self._last_t: float | None = None
        self.recent_valid = RecentValid(COLLAPSE_WINDOW_S, COLLAPSE_FACTOR, COLLAPSE_WARMUP_FRAMES)
        self.frozen_input = FrozenInput(settings.stale_after_s)
        self.reach = Reach(False, "")  # of the last map's disparity search
        self.checks: FrameChecks | None = None  # rectify's checks, as the last map carried them
        self.near: NearStanding | None = None  # what of the last map's near field stands nearer than the range
        self.contradicted = 0.0  # the largest patch of the last map its near field sees nearer (near.contradicted)
        self.unlisted = 0.0  # ... the near field sees standing, unmeasured and in no obstacle (unlisted_standing)
        self.washed_out = 0.0  # the share of the last map's floor in range clipped white in both cameras
        self._reach_logged: set[str] = set()

    def check_search(self, model: camera.RectifiedModel, min_disparity: int, num_disparities: int,
                     quiet: bool = False, gate_px: float = 0.0) -> Reach:
        """The disparity search of a map (and its range gate) against the vision range; each new
        finding is logged once (quiet: the caller says it itself)."""
        reach = search_reach(model, min_disparity, num_disparities, self.settings, gate_px)
        if reach.message and reach.message not in self._reach_logged:
            self._reach_logged.add(reach.message)
            if not quiet:
                log.warning("segmenter: %s", reach.message)
        self.reach = reach
        return reach

    def decode(self, msg: DisparityMap
               ) -> tuple[np.ndarray, camera.RectifiedModel, np.ndarray | None, np.ndarray | None]:
        """A disparity message -> (disparity px float32 with NaN invalid, camera model, confidence,
        flat (bool)). Values outside the range the map says was searched, NaN and inf are invalid,
        never depth."""
        if (msg.image.width, msg.image.height) != (msg.camera.width, msg.camera.height):
            raise DecodeError(f"disparity image is {msg.image.width}x{msg.image.height}, its camera model "
                              f"{msg.camera.width}x{msg.camera.height}")
        raw = codec.array_from_image(msg.image, "disparity")
        side = codec.side_images(msg)
        confidence, flat = side.get("confidence"), side.get("flat mask")
        d = to_float(raw, msg.scale, msg.invalid_value, searched_range(msg.min_disparity, msg.num_disparities))
        return d, camera.model_of(msg.camera), confidence, None if flat is None else flat > 0

    def segment(self, disparity: np.ndarray, model: camera.RectifiedModel, confidence: np.ndarray | None = None,
                image: np.ndarray | None = None, flat: np.ndarray | None = None,
                search: tuple[int, int] | None = None) -> layers.LayersFrame:
        cfg = self.settings
        if disparity.size == 0:
            return layers.LayersFrame([], [], None, None, np.zeros((0, 3)))
        if cfg.method == "seed":
            # the floor seed removes is the ground estimator's, as layers': a configured mount is its prior,
            # never a cage (a mount 8 deg off had turned the floor into obstacles, or eaten what stood on it)
            floor, estimate = (layers.estimate_ground(disparity, model, cfg, self.ground, confidence)
                               if cfg.floor_removal else (None, None))
            dets, unlisted = seed.segment_frame(disparity, model, cfg, floor)
            return layers.LayersFrame(dets, [], floor, estimate, np.zeros((0, 3)), unlisted)
        return layers.segment_frame(disparity, model, cfg, ground=self.ground, confidence=confidence, image=image,
                                    flat=flat, search=search)

    def _ego_motion(self, odometry: Odometry | None, t_s: float) -> bool:
        """Carry the tracks into this frame's base frame by the robot's own motion since the last
        frame. -> True when odometry was used (velocities are then over the ground, not relative to
        the robot)."""
        dt = None if self._last_t is None else t_s - self._last_t
        if odometry is None or dt is None or not 0 <= dt <= self.settings.odometry_timeout_s * 4:
            return False
        R = _rz(-odometry.angular_radps[2] * dt)
        self.tracker.move(R, -R @ (np.asarray(odometry.linear_mps, float) * dt))
        return True

    def _merge_fragments(self, dets: list[Detection], points: list[np.ndarray], fps: list[np.ndarray], mount: Mount,
                         model: camera.RectifiedModel, t_s: float
                         ) -> tuple[list[Detection], list[np.ndarray], list[np.ndarray]]:
        """Pieces of one tracked object put back together: a confirmed track that stood somewhere
        in the last frame still stands there, so detections whose footprints lie (mostly) inside
        its predicted footprint are its parts, seen apart this frame because the matcher lost a
        texture-poor stretch of it (a fence along the road, a hedge). One object each frame keeps
        its id and its centroid, where its pieces would be tracks that flicker. Only what lies
        inside the footprint is joined: a person stepping up beside a tracked one, or standing
        behind them, is outside it. fps: the detections' footprints (_footprint); -> (detections,
        points, footprints) with each group of pieces as one."""
        live = [tr for tr in self.tracker.tracks
                if tr.confirmed and tr.box is not None and t_s - tr.last_seen_s <= 0.25]
        if not live or len(dets) < 2:
            return dets, points, fps
        tb = np.array([tr.predicted_box(t_s) for tr in live])  # (T, 2, 2)
        # how far its footprint's edges may be off: the stereo noise where it stands, its own motion
        # since it was seen, a few centimetres of the percentiles' jitter. Stereo's noise is in the
        # range, along the line of sight (the bearing of a pixel is exact): padded by it across the line
        # of sight too, a person 9.5 m away took in the one standing 0.3 m beside them (0.35 m of noise)
        pad = np.empty((len(live), 2))
        for i, tr in enumerate(live):
            sight = np.asarray(tr.position[:2], float) - mount.origin_base[:2]
            sight = np.abs(sight) / max(float(np.linalg.norm(sight)), 1e-6)
            pad[i] = (np.sqrt(self.tracker.measurement_var(tr.position)) * sight
                      + float(np.linalg.norm(tr.velocity[:2])) * (t_s - tr.last_seen_s) + 0.05)
        lo, hi = tb[:, 0] - pad, tb[:, 1] + pad  # (T, 2)
        F = np.array(fps)  # (D, 2, 2)
        # a footprint thinner than 5 cm (a leg, a post seen from its front) is taken as 5 cm about its
        # centre, its interval with it: floored in the ratio alone, a table's back leg 3 cm deep lying
        # wholly inside the table's footprint counted 0.6 inside and stood apart as a thing of its own
        ext = np.maximum(F[:, 1] - F[:, 0], 0.05)  # (D, 2)
        mid = 0.5 * (F[:, 0] + F[:, 1])
        f_lo, f_hi = mid - 0.5 * ext, mid + 0.5 * ext
        overlap = np.clip(np.minimum(hi[:, None], f_hi[None]) - np.maximum(lo[:, None], f_lo[None]), 0, None)
        inside = np.prod(overlap / ext[None], axis=2)  # (T, D): share of each footprint inside each track's
        # a piece belongs to the tightest confirmed track around it: a table with a track of its own
        # is not a piece of a person who stood behind it in one frame
        size = np.prod(hi - lo, axis=1)
        cand = np.where(inside >= 0.7, size[:, None], np.inf)
        owner = np.where(np.isfinite(cand.min(0)), cand.argmin(0), -1)
        groups: dict[int, list[int]] = {}
        for di, ti in enumerate(owner.tolist()):
            if ti >= 0:
                groups.setdefault(ti, []).append(di)
        merged = {g[0]: g for g in groups.values() if len(g) > 1}
        if not merged:
            return dets, points, fps
        drop = {di for g in merged.values() for di in g[1:]}
        out_d, out_p, out_f = [], [], []
        for di, (d, p, f) in enumerate(zip(dets, points, fps)):
            if di in drop:
                continue
            if di in merged:
                d, p = layers.merge_detections([dets[k] for k in merged[di]], [points[k] for k in merged[di]], model)
                f = _footprint(mount, p)
            out_d.append(d)
            out_p.append(p)
            out_f.append(f)
        return out_d, out_p, out_f

    def process(self, disparity: np.ndarray, model: camera.RectifiedModel, *, t_s: float, seq: int, stamp_ns: int,
                robot_id: str = "offline", confidence: np.ndarray | None = None, odometry: Odometry | None = None,
                image: np.ndarray | None = None, stale: bool = False,
                stages: dict[str, int] | None = None, search: tuple[int, int] | None = None,
                checks: FrameChecks | None = None, gate_px: float = 0.0, flat: np.ndarray | None = None) -> FrameResult:
        """disparity: (H, W) float32 px, NaN = invalid, matching `model`; t_s: the frame's time on a
        clock that never goes backwards (the service: Node.frame_time_s; offline: the capture time);
        odometry: the robot's motion at this frame, if known (velocities are then over the ground);
        flat: (H, W) bool, where the matcher's window was too plain to decide its match (Match.flat).

        The list says how far it can be trusted: valid_fraction is the share of the image with a
        measurement; degraded names why an empty list would not mean "nothing there"
        ("input-frozen": the map has not changed, bit for bit, for over stale_after_s: the camera
        repeats an old picture with fresh stamps; "no-valid-disparity": under 1 % measured;
        "little-measured": under 10 % (too dark, fog, a plain wall filling the view);
        "valid-collapse": under half of what the frames of the last 2 s measured;
        "range-unreachable": the map's search, `search` = its (min_disparity, num_disparities),
        cannot measure the vision range; "near-unmeasured": it cannot measure the near part of it;
        "far-unmeasured": it, or the matcher's vision range gate `gate_px` (DisparityMap.gate_px),
        cannot measure the far part of it (search_reach); "no-ground" / "ground-uncertain": nothing or
        too little told the floor from what stands on it; "mount-disagrees": fit_floor is false and
        the configured mount's floor is off the floor the data show; "rows-misaligned": rectify's
        last live check (`checks.rows`) found the pair's rows apart by more than its tolerance (the
        calibration no longer fits the rig: the map measures less, and wrongly); "cameras-swapped":
        that check found most features at negative disparity (the left and right cameras exchanged:
        the map is of a mirror scene, its obstacles are not there and what is there is not
        measured); "camera-frozen": one camera's
        picture has not changed for over rectify's frozen_after_s (`checks.frozen`: its driver
        repeats a buffer; with the other live the map changes, and is wrong wherever anything
        moved); "view-blocked": part of
        one camera's view is flat where the other's has texture (`checks.blocked`: a finger on the
        lens; nothing there is measured); "nearer-than-range": rectify's coarse wide search
        (`checks.near`) finds over 1.2 % of the picture standing nearer than min_range_m (a person
        stepping up to the camera: the matcher's search does not reach it, and it blocks the view of
        the range); "map-contradicted": the map puts farther, over CONTRADICTED_SHARE of the picture
        or more, what that coarse look at the same pair sees nearer (cores/calibration/near.py: a
        worker that erased what stands, or answered with an old map; the list is not of this view);
        "washed-out": rectify's clipped tiles (`checks.clipped`) cover over
        WASHED_OUT of the floor within the range (a floor the list vouches for) with white at
        infinity in both cameras (the sun or a lamp low ahead: nothing there is measured, and what
        stands there is in no list); "noisy": rectify's estimate of the pictures' sensor noise
        (`checks.noise_grey`) is over NOISY_GREY grey levels (low light brought up by the gain: the
        matcher rejects more and more of what is there);
        "floor-out-of-view": the floor within the vision range is below the camera's view;
        "standing-not-listed": something standing in range, of min_area_m2 frontal area, is in no
        obstacle: seed's border clearing, area opening or Otsu threshold dropped it; or, by any method,
        rectify's near field sees something standing in range, over UNLISTED_SHARE of the picture, where
        the map measured nothing and no obstacle lies (a worker that emptied what stands))."""
        cfg = self.settings
        reach = self.check_search(model, *search, gate_px=gate_px) if search is not None else Reach(False, "")
        if disparity.dtype.kind == "f":
            inf = np.isinf(disparity)
            if inf.any():  # an infinite disparity is no measurement (nor a point at zero distance)
                disparity = np.where(inf, np.float32(np.nan), disparity)
        frame = self.segment(disparity, model, confidence, image, flat, search)
        if self.upright is not None:
            self.upright.update(frame.ground, t_s)
        mount, mount_source = frame_mount(frame.ground, self.configured,
                                          None if self.upright is None else self.upright.mount(self.configured))
        track_frame = "base" if mount is not None else "camera"
        if track_frame != self._track_frame:
            self.tracker.clear()  # positions of one frame mean nothing in the other
            self._track_frame = track_frame
        over_ground = track_frame == "base" and self._ego_motion(odometry, t_s)
        self._last_t = t_s
        dets, points = frame.detections, frame.points
        fps = [_footprint(mount, pts) for pts in points] if mount is not None and len(points) == len(dets) else None
        if fps is not None and mount is not None and cfg.track_merge_fragments:
            dets, points, fps = self._merge_fragments(dets, points, fps, mount, model, t_s)
        positions = [mount.to_base(d.position_m) if mount is not None else np.asarray(d.position_m, float)
                     for d in dets]
        self.tracker.depth_scale = model.focal_px * model.baseline_m
        self.tracker.ground_plane = track_frame == "base"
        boxes = None
        if mount is not None:
            boxes = fps if fps is not None else \
                [np.array([p[:2] - 0.5 * np.asarray(d.size_m)[[2, 0]], p[:2] + 0.5 * np.asarray(d.size_m)[[2, 0]]])
                 for d, p in zip(dets, positions)]
        edges = [None if d.edges is None else (mount.to_base(d.edges) if mount is not None else d.edges) for d in dets]
        tracks = self.tracker.update(positions, t_s, boxes, cuts=[d.cut for d in dets], edges=edges)
        obstacles = []
        for det, tr, pos in zip(dets, tracks, positions):
            if mount is not None:
                v_base = tr.velocity
                v_cam = mount.R_base_camera.T @ v_base
                base, vbase = _vec(pos), _vec(v_base)
            else:
                v_cam, base, vbase = tr.velocity, None, None
            obstacles.append(Obstacle(
                id=tr.id, position_m=_vec(det.position_m), size_m=_vec(det.size_m),
                distance_m=max(0.0, float(det.distance_m)), velocity_mps=_vec(v_cam), bbox_px=det.bbox_px,
                area_px=det.area_px, disparity_px=float(det.disparity_px),
                confidence=float(min(1.0, max(0.0, det.confidence))), position_base_m=base, velocity_base_mps=vbase,
                confirmed=tr.confirmed, track_frames=tr.hits, truncated=det.truncated))
        obstacles.sort(key=lambda o: o.distance_m)
        now = time.time_ns()
        valid_fraction = measured_share(disparity, confidence, cfg.min_confidence, flat)
        degraded = []
        # a map that measured nothing is the same as the last one whatever the camera does (a live
        # camera whose matcher keeps nothing gave input-frozen beside no-valid-disparity, sending a
        # reader to a driver that was fine): only maps with something in them tell a stuck picture
        if valid_fraction >= MIN_VALID_FRACTION and self.frozen_input.frozen(disparity, t_s):
            degraded.append("input-frozen")  # fresh stamps on an old picture: the world it shows is not now's
        if valid_fraction < MIN_VALID_FRACTION:
            degraded.append("no-valid-disparity")
        else:
            if self.recent_valid.collapsed(valid_fraction, t_s):
                degraded.append("valid-collapse")
            if valid_fraction < LITTLE_MEASURED:
                degraded.append("little-measured")  # most of the view unmeasured: an empty list is not a clear way
        self.recent_valid.add(valid_fraction, t_s)
        self.checks = checks
        # a camera frozen: the last row check may have compared pictures of two moments (before the freeze
        # was declared), whose features say nothing of the rig; the list says camera-frozen
        rows = checks.rows if checks is not None and not checks.frozen else None
        if rows is not None and rows.offset_px > rows.tolerance_px:
            degraded.append("rows-misaligned")
        swapped = rows is not None and rows.reversed_share > SWAPPED_SHARE
        if swapped:
            degraded.append("cameras-swapped")  # the map is of the mirror scene: what it lists is not there
        if checks is not None and checks.frozen:
            degraded.append("camera-frozen")
        if checks is not None and checks.blocked:
            degraded.append("view-blocked")
        self.near = None
        self.contradicted = self.unlisted = 0.0
        if checks is not None and checks.near is not None and not swapped:  # else a mirror scene's near field
            self.near = near_standing(checks.near, model, frame.floor, cfg.min_range_m, cfg.min_height_m)
            if self.near.blocks:
                degraded.append("nearer-than-range")  # the view of the range is blocked, not clear
            cells = map_cells(disparity, checks.near) if search is not None else None
            if cells is not None and search is not None:
                search_max, band = search[0] + search[1] - 1, search[0] + search[1]
                self.contradicted = contradicted(cells, search_max, band)
                if self.contradicted >= CONTRADICTED_SHARE:
                    degraded.append("map-contradicted")  # farther than the robot's own look sees: not this view
                if frame.floor is not None:
                    far_px = max(float(search[0]), float(gate_px), model.focal_px * model.baseline_m /
                                 cfg.range_for(model))
                    self.unlisted = unlisted_standing(cells, frame.floor, [o.bbox_px for o in obstacles], far_px,
                                                      search_max, band, cfg.min_height_m, cfg.robot_height_m)
        if reach.unreachable:
            degraded.append("range-unreachable")
        else:
            if reach.near_unmeasured:
                degraded.append("near-unmeasured")
            if reach.far_unmeasured:
                degraded.append("far-unmeasured")
        if not cfg.floor_removal or (cfg.method == "seed" and frame.floor is None):
            # no floor removed: a textured floor in range is one region with what stands on it (the thesis's
            # method then clears both at the border; layers reports road and car as one obstacle, at neither's
            # place)
            degraded.append("no-ground")
        else:
            if frame.unlisted or self.unlisted >= UNLISTED_SHARE:
                degraded.append("standing-not-listed")
            g = frame.ground
            if g is None or g.source == "none":
                degraded.append("no-ground")  # nothing told floor from obstacle: what stands low is not known
            elif g.source == "prior" and g.prior_agrees is False:
                degraded.append("mount-disagrees")  # fit_floor false, and the data's floor is elsewhere
            elif g.confidence < TRUSTED:
                degraded.append("ground-uncertain")
            if frame.floor is not None and not floor_in_view(frame.floor, model, cfg.range_for(model)):
                degraded.append("floor-out-of-view")
        self.washed_out = 0.0
        floor_known = not {"no-ground", "ground-uncertain", "mount-disagrees"} & set(degraded)
        if checks is not None and checks.clipped is not None and frame.floor is not None and floor_known:
            # where the floor lies in the picture, by a floor the list can vouch for (a floor fitted
            # metres off puts the sky in the range, whose white is no glare)
            self.washed_out = washed_out_share(checks.clipped, model, frame.floor, cfg.min_range_m,
                                               cfg.range_for(model))
            if self.washed_out > WASHED_OUT:
                degraded.append("washed-out")  # white in both cameras where the path lies: not seen, not clear
        if checks is not None and checks.noise_grey is not None and checks.noise_grey > NOISY_GREY:
            degraded.append("noisy")  # dusk's gain: the matcher misses more and more of what stands there
        out = ObstacleList(robot_id=robot_id, seq=seq, stamp_ns=stamp_ns, stages=dict(stages or {}), publish_ns=now,
                           stale=stale, degraded=degraded, valid_fraction=valid_fraction, method=cfg.method,
                           range_m=reach.looked_at(cfg.min_range_m, cfg.range_for(model)),
                           bearing_deg=None if search is None else view_bearings(model, *search),
                           obstacles=obstacles, ground=frame.ground,
                           mount=None if mount is None else mount.message(mount_source),
                           velocity_reference="ground" if over_ground else "camera")
        free = None
        if cfg.freespace and mount is not None and frame.floor is not None and cfg.method == "layers":
            grid = freespace.occupancy(frame.floor_points, frame.points, mount, model, cfg.range_for(model),
                                       cfg.freespace_resolution_m)
            if degraded or stale:
                # a list that cannot vouch for its view cannot vouch for a clear way either (the floor near
                # the robot unmeasured, the floor plane a guess, late input): what stands stays occupied,
                # nothing is claimed free; FreeSpace has no flag of its own, and a costmap clears free cells
                grid.cells[grid.cells == freespace.FREE] = freespace.UNKNOWN
            free = FreeSpace(robot_id=robot_id, seq=seq, stamp_ns=stamp_ns, stages=dict(stages or {}), publish_ns=now,
                             resolution_m=grid.resolution_m, width=grid.width, height=grid.height,
                             origin_m=(float(grid.origin_m[0]), float(grid.origin_m[1])), cells=grid.cells.tobytes(),
                             ground=frame.ground, mount=out.mount)
        return FrameResult(out, free, frame.floor)

    def process_message(self, msg: DisparityMap, *, stale: bool = False, t_s: float | None = None,
                        odometry: Odometry | None = None) -> FrameResult:
        """A disparity message -> its FrameResult (t_s: None takes the capture stamp)."""
        disparity, model, confidence, flat = self.decode(msg)
        return self.process(disparity, model, t_s=msg.stamp_ns / 1e9 if t_s is None else t_s, seq=msg.seq,
                            stamp_ns=msg.stamp_ns, robot_id=msg.robot_id, confidence=confidence, odometry=odometry,
                            stale=stale, stages=msg.stages, search=(msg.min_disparity, msg.num_disparities),
                            checks=msg.checks, gate_px=msg.gate_px, flat=flat)


def _footprint(mount: Mount, points_camera: np.ndarray) -> np.ndarray:
    """(2, 2) lo, hi of an obstacle's points on the ground (base x, y; 2nd-98th percentile)."""
    p = mount.to_base(points_camera[::max(1, len(points_camera) // 1000)])
    return stats.percentile(p[:, :2], [2, 98])


def _vec(v) -> tuple[float, float, float]:
    return tuple(float(x) for x in v)  # type: ignore[return-value]
