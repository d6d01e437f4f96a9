"""A deterministic synthetic stereo world with exact ground truth: the default capture source.

A ray-cast renderer (numpy + OpenCV, no Zenoh) of a textured floor, a textured back wall and box
obstacles (simple boxes or compounds of boxes, static or moving along a path), seen by a calibrated
raw stereo rig (`camera.RawRig`). The raw images carry the rig's real lens distortion, so they go
through the same rectification as a real camera's; the ground truth is given in the system's camera
frame (the rectified left camera, see DESIGN.md).

Frames
------
world: fixed to the floor, x forward, y left, z up, metres. The floor is z = 0; the back wall is
    the plane x = wall_distance_m. Objects and their paths are given in it.
base (the robot base frame, REP 103): on the floor under the robot, x along its heading, y left,
    z up; never tilted. Without `camera_motion` it is the world frame at all times. With it, the
    robot drives (a constant speed along its heading and a constant turn rate from a start pose)
    and the base frame moves with it.
left camera: in the base frame at (0, 0, camera_height_m), looking along +x, pitched down by
    camera_pitch_deg (positive = looking down), no roll; optical convention (x right, y down,
    z forward). With `camera_motion` its sway (a balancing robot leans) adds sums of sinusoids to
    its pitch, roll and height, in the convention of the segmenter's Mount (yaw about base z, then
    pitch, then roll: the camera keeps its heading); with a pivot, the lean turns the camera about
    a point on the base z axis (a ballbot's ball) and so also moves it over the floor.
right camera: OpenCV convention, ``X_right = R @ X_left + T``.
rectified (the camera frame of every message): ``X_rect = R1 @ X_left``.

Objects
-------
A `Box` is an obstacle: one oriented box, or a compound of `Part` boxes (a chair, a person) that is
still ONE obstacle in the ground truth. Sizes are (w, h, d) = (extent along the object's local y,
z, x), i.e. width across, height, depth along the viewing direction when yaw = 0.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Sequence

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationError, model_validator

from cores import camera
from common.errors import ConfigError

SCENARIO_DIR = Path(__file__).with_name("scenarios")

# --- texture ---------------------------------------------------------------------------------------

TEX_SIZE = 1024  # texels per side; the texture tiles (wraps) in both directions
TEXELS_PER_M = 200.0  # 5 mm texels at scale 1: features of 1-3 cm, i.e. several pixels at 1-5 m
_N_LEVELS = 5  # prefiltered copies, level l blurred over ~2**l texels (a full-resolution mip chain)
_MAX_TAPS = 8  # anisotropic filtering: samples along a footprint's long axis
_LIGHT_DIR = np.array([-0.5, 0.4, 1.0]) / np.linalg.norm([-0.5, 0.4, 1.0])  # world, towards the light
_AMBIENT = 0.45  # shade = texture * (ambient + (1 - ambient) * max(0, n . light))


def _periodic_blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur with wrap-around borders (via FFT), so the texture tiles without seams."""
    if sigma <= 0:
        return a.astype(np.float32)
    fy = np.fft.fftfreq(a.shape[0]).astype(np.float32)
    fx = np.fft.rfftfreq(a.shape[1]).astype(np.float32)
    g = np.exp(np.float32(-2.0 * (math.pi * sigma) ** 2) * (fy[:, None] ** 2 + fx[None, :] ** 2))
    return np.fft.irfft2(np.fft.rfft2(a.astype(np.float32)) * g, s=a.shape).astype(np.float32)


@functools.lru_cache(maxsize=4)
def texture_pyramid(seed: int = 0) -> tuple[np.ndarray, ...]:
    """The shared surface texture and its prefiltered copies.

    Level 0 is a TEX_SIZE x TEX_SIZE multi-octave noise, high contrast (mean 128, std ~55, clipped
    to 0..255 and quantised to uint8 values); level l is level 0 blurred over ~2**l texels, same size.
    Returns float32 arrays (grey levels). Deterministic for `seed`.
    """
    rng = np.random.default_rng([seed, 0x7E47])
    acc = np.zeros((TEX_SIZE, TEX_SIZE), np.float64)
    # fine octaves dominate so block matching finds texture at every distance; coarse ones vary
    # the local mean so surfaces do not look like uniform grey noise
    for sigma, amp in ((1.0, 1.3), (2.0, 1.0), (4.0, 0.7), (10.0, 0.4), (32.0, 0.3)):
        o = _periodic_blur(rng.standard_normal((TEX_SIZE, TEX_SIZE)), sigma)
        acc += amp * (o - o.mean()) / o.std()
    acc = (acc - acc.mean()) / acc.std()
    base = np.clip(np.round(128.0 + 55.0 * acc), 0, 255).astype(np.uint8).astype(np.float32)
    levels = [base] + [_periodic_blur(base, 0.45 * 2.0 ** lv) for lv in range(1, _N_LEVELS)]
    for lv in levels:
        lv.setflags(write=False)
    return tuple(levels)


def _remap_1d(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Bilinear samples of `img` at n points (cv2.remap limits maps to < 32767 rows/cols)."""
    n = mx.size
    cols = 1024
    rows = -(-n // cols)
    mx2 = np.zeros(rows * cols, np.float32)
    my2 = np.zeros(rows * cols, np.float32)
    mx2[:n], my2[:n] = mx, my
    mx2, my2 = mx2.reshape(rows, cols), my2.reshape(rows, cols)
    return cv2.remap(img, mx2, my2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP).ravel()[:n]


@dataclass(frozen=True)
class _SurfaceTex:
    """How one surface samples the shared texture: texels = scale * rot @ uv_m + offset."""

    scale: float
    cos: float
    sin: float
    off_u: float
    off_v: float

    @property
    def params(self) -> np.ndarray:
        """(5,) float32: scale, cos, sin, off_u, off_v, as `_sample` takes them."""
        return np.array([self.scale, self.cos, self.sin, self.off_u, self.off_v], np.float32)

    @classmethod
    def from_seed(cls, *seed: int) -> "_SurfaceTex":
        rng = np.random.default_rng([*seed, 0x5EED])
        a = rng.uniform(0, 2 * math.pi)
        return cls(TEXELS_PER_M * float(rng.uniform(0.8, 1.25)), math.cos(a), math.sin(a),
                   float(rng.uniform(0, TEX_SIZE)), float(rng.uniform(0, TEX_SIZE)))


def _sample(levels: Sequence[np.ndarray], u: np.ndarray, v: np.ndarray, minor_m: np.ndarray,
            major_m: np.ndarray, au: np.ndarray, av: np.ndarray, tex: np.ndarray) -> np.ndarray:
    """Filtered texture lookup: surface coordinates (m) -> grey level, float32 (n,).

    Each pixel's footprint on the surface is an ellipse, `minor_m` across and `major_m` along the
    unit surface direction (au, av) (the slant direction). The prefilter level follows the minor
    axis and up to _MAX_TAPS samples are averaged along the major axis (anisotropic filtering): a
    grazing floor would otherwise alias, and aliasing differs between the two cameras.
    tex: (n, 5) per-pixel surface parameters (scale, cos, sin, off_u, off_v).
    """
    n_taps = np.clip(np.ceil(major_m / np.maximum(minor_m, 1e-9) - 0.25), 1, _MAX_TAPS).astype(np.int32)
    # sorted by tap count, the pixels needing a k-th tap are a prefix: slices instead of gathers
    order = np.argsort(-n_taps, kind="stable")
    n_taps = n_taps[order]
    u, v, au, av, major_m = (np.asarray(a, np.float32)[order] for a in (u, v, au, av, major_m))
    tex = tex[order]
    scale, cs, sn, ou, ov = (tex[:, k] for k in range(5))
    lev = np.clip(np.log2(np.maximum(minor_m[order] * scale, 1e-6)), 0.0, _N_LEVELS - 1.0)
    counts = np.bincount(n_taps, minlength=_MAX_TAPS + 1)
    acc = np.zeros(u.shape, np.float32)
    for k in range(_MAX_TAPS):
        c = int(counts[k + 1:].sum())
        if c == 0:
            break
        off = ((k + 0.5) / n_taps[:c] - 0.5) * major_m[:c]
        uk, vk = u[:c] + off * au[:c], v[:c] + off * av[:c]
        tu = np.mod(scale[:c] * (cs[:c] * uk - sn[:c] * vk) + ou[:c], TEX_SIZE)
        tv = np.mod(scale[:c] * (sn[:c] * uk + cs[:c] * vk) + ov[:c], TEX_SIZE)
        acc[:c] += _trilinear(levels, tu, tv, lev[:c])
    out = np.empty_like(acc)
    out[order] = acc / n_taps
    return out


def _trilinear(levels: Sequence[np.ndarray], tu: np.ndarray, tv: np.ndarray, lev: np.ndarray) -> np.ndarray:
    """Bilinear samples at texel coordinates (tu, tv), blended between prefilter levels `lev`."""
    i0 = np.minimum(lev.astype(np.int32), _N_LEVELS - 2)
    w1 = (lev - i0).astype(np.float32)
    out = np.zeros(tu.shape, np.float32)
    for lv in range(_N_LEVELS):
        lo, hi = i0 == lv, (i0 + 1 == lv) & (w1 > 0)  # most pixels need one level only
        m = lo | hi
        if not m.any():
            continue
        out[m] += np.where(lo[m], 1.0 - w1[m], w1[m]) * _remap_1d(levels[lv], tu[m], tv[m])
    return out


# --- scene description -----------------------------------------------------------------------------

@dataclass
class Part:
    """One box of a compound object, in the object's local frame (x forward, y left, z up).

    offset: (3,) m, part centre relative to the object's origin. size: (w, h, d) m. yaw_deg: about z.
    """

    offset: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw_deg: float = 0.0
    name: str = ""


@dataclass
class Box:
    """An obstacle: an oriented box standing in the world, or a compound of `parts`.

    center: (3,) world m. For a simple box, its centre (z = h/2 when standing on the floor). For a
        compound, the object's origin (normally on the floor); parts are placed relative to it and
        `size` is derived: the extents of the union of the parts in the object frame.
    size: (w, h, d) m. yaw_deg: rotation about world z (counter-clockwise seen from above).
    texture_seed: picks each face's texture offset, scale and rotation.
    path: optional world waypoints [(x, y), ...] (m) followed at `speed_mps`; the object's (x, y) is
        the path position at time t (its z stays center[2]); `loop` closes the path back to the
        first waypoint, otherwise the object stops at the last one. `face_motion` turns the object's
        local +x into the direction of travel (plus yaw_deg).
    """

    name: str
    kind: str
    center: tuple[float, float, float]
    size: tuple[float, float, float] | None = None
    yaw_deg: float = 0.0
    texture_seed: int = 0
    path: list[tuple[float, float]] | None = None
    speed_mps: float = 0.0
    loop: bool = True
    face_motion: bool = False
    parts: list[Part] | None = None

    def __post_init__(self) -> None:
        self.center = tuple(float(c) for c in self.center)  # type: ignore[assignment]
        if self.parts:
            lo, hi = self._local_extent()
            self.size = (float(hi[1] - lo[1]), float(hi[2] - lo[2]), float(hi[0] - lo[0]))
        elif self.size is None:
            raise ConfigError(f"object '{self.name}': needs 'size' or 'parts'")
        else:
            self.size = tuple(float(s) for s in self.size)  # type: ignore[assignment]
        if len(self.center) != 3 or len(self.size) != 3:
            raise ConfigError(f"object '{self.name}': center needs 3 numbers and size 3 numbers")
        if min(self.size) <= 0:
            raise ConfigError(f"object '{self.name}': size must be positive, got {self.size}")
        if self.path is not None:
            self.path = [(float(p[0]), float(p[1])) for p in self.path]
            if len(self.path) < 2 or self.speed_mps <= 0:
                raise ConfigError(f"object '{self.name}': a path needs >= 2 waypoints and speed_mps > 0")

    # geometry ------------------------------------------------------------------------------------
    def part_list(self) -> list[Part]:
        """The boxes that make up the object (a simple box is one part at offset 0)."""
        if self.parts:
            return list(self.parts)
        return [Part((0.0, 0.0, 0.0), self.size, 0.0, self.name)]  # type: ignore[arg-type]

    def _local_extent(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned extent (lo, hi) (3,) of the union of the parts, object frame, m."""
        pts = np.concatenate([_box_corners(np.asarray(p.offset, float), math.radians(p.yaw_deg),
                                           np.asarray(p.size, float)) for p in self.part_list()])
        return pts.min(0), pts.max(0)

    def is_static(self) -> bool:
        return self.path is None

    def pose(self, t: float) -> tuple[np.ndarray, float, np.ndarray]:
        """(origin (3,) world m, yaw rad, velocity (3,) world m/s) at time t (s)."""
        c = np.asarray(self.center, float)
        yaw = math.radians(self.yaw_deg)
        if self.path is None:
            return c, yaw, np.zeros(3)
        pts = np.asarray(self.path, float)
        if self.loop:
            pts = np.vstack([pts, pts[:1]])
        seg = np.diff(pts, axis=0)
        lens = np.linalg.norm(seg, axis=1)
        total = float(lens.sum())
        s = max(t, 0.0) * self.speed_mps
        s = s % total if self.loop else min(s, total)
        cum = np.concatenate([[0.0], np.cumsum(lens)])
        i = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
        while lens[i] <= 0 and i + 1 < len(seg):
            i += 1
        direction = seg[i] / max(lens[i], 1e-12)
        xy = pts[i] + direction * (s - cum[i])
        moving = self.loop or s < total
        vel = np.array([*(direction * self.speed_mps), 0.0]) if moving else np.zeros(3)
        if self.face_motion:
            yaw += math.atan2(direction[1], direction[0])
        return np.array([xy[0], xy[1], c[2]]), yaw, vel

    def local_center(self) -> np.ndarray:
        """Centre of the union extent in the object frame (0 for a simple box), m."""
        lo, hi = self._local_extent()
        return (lo + hi) / 2.0


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _box_corners(center: np.ndarray, yaw: float, size: np.ndarray) -> np.ndarray:
    """(8, 3) corners of a box with size (w, h, d) (local y, z, x extents), yawed about z."""
    w, h, d = size
    sx, sy, sz = np.meshgrid([-d / 2, d / 2], [-w / 2, w / 2], [-h / 2, h / 2], indexing="ij")
    local = np.stack([sx.ravel(), sy.ravel(), sz.ravel()], 1)
    return local @ _rot_z(yaw).T + center


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


# optical (x right, y down, z forward) -> body (x forward, y left, z up)
_BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_axes(pitch_deg: float, roll_deg: float) -> np.ndarray:
    """(3, 3) base-frame coordinates of the optical axes (x right, y down, z forward) of a camera
    pitched down by pitch_deg and rolled (right side down) by roll_deg: Ry(pitch) Rx(roll) as in
    the segmenter's Mount (yaw 0)."""
    return _rot_y(math.radians(pitch_deg)) @ _rot_x(math.radians(roll_deg)) @ _BODY_FROM_OPTICAL


@dataclass(frozen=True)
class Wave:
    """amplitude * sin(2 pi frequency_hz t + phase): one component of a sway."""

    amplitude: float
    frequency_hz: float
    phase_deg: float = 0.0

    def at(self, t: float) -> float:
        return self.amplitude * math.sin(2.0 * math.pi * self.frequency_hz * t + math.radians(self.phase_deg))


@dataclass
class CameraMotion:
    """How the camera moves: the robot drives and the camera sways on it (a balancing ballbot).

    start: (x m, y m, heading deg) of the base frame in the world at t = 0. speed_mps: along the
    heading; yaw_rate_deg_s: turning (counter-clockwise), both constant: a straight line or an arc.
    pitch_deg, roll_deg: sinusoids added to the camera's pitch (positive looking down) and roll
    (positive right side down); height_m: added to its height. pivot_height_m: None, the camera
    turns about its own centre; else the sway is a lean of the robot about the point this high on
    the base z axis (a ballbot's ball centre), which carries the camera over the floor too.
    """

    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    speed_mps: float = 0.0
    yaw_rate_deg_s: float = 0.0
    pitch_deg: tuple[Wave, ...] = ()
    roll_deg: tuple[Wave, ...] = ()
    height_m: tuple[Wave, ...] = ()
    pivot_height_m: float | None = None

    def base_pose(self, t: float) -> tuple[float, float, float]:
        """(x m, y m, heading rad) of the base frame in the world at time t (s)."""
        x0, y0, h0 = self.start[0], self.start[1], math.radians(self.start[2])
        w = math.radians(self.yaw_rate_deg_s)
        if abs(w) < 1e-9:
            return x0 + self.speed_mps * t * math.cos(h0), y0 + self.speed_mps * t * math.sin(h0), h0
        h = h0 + w * t
        r = self.speed_mps / w
        return x0 + r * (math.sin(h) - math.sin(h0)), y0 - r * (math.cos(h) - math.cos(h0)), h

    def sway(self, t: float) -> tuple[float, float, float]:
        """(pitch deg, roll deg, height m) added to the camera's mount at time t (s)."""
        return (sum(w.at(t) for w in self.pitch_deg), sum(w.at(t) for w in self.roll_deg),
                sum(w.at(t) for w in self.height_m))

    def camera_in_base(self, t: float, height_m: float, pitch_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """(R (3, 3): base coordinates of the left camera's optical axes, origin (3,) base m) at t
        for a camera mounted height_m high and pitched pitch_deg when the robot stands upright."""
        dp, dr, dh = self.sway(t)
        R = camera_axes(pitch_deg + dp, dr)
        origin = np.array([0.0, 0.0, height_m + dh])
        if self.pivot_height_m is not None:
            lean = R @ camera_axes(pitch_deg, 0.0).T
            pivot = np.array([0.0, 0.0, self.pivot_height_m])
            origin = pivot + lean @ (origin - pivot)
        return R, origin

    def twist(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(linear (3,) m/s, angular (3,) rad/s) of the base frame in its own axes: odometry."""
        return np.array([self.speed_mps, 0.0, 0.0]), np.array([0.0, 0.0, math.radians(self.yaw_rate_deg_s)])


@dataclass
class Scene:
    """A world to render: camera mount, floor, back wall and obstacles (world frame, metres)."""

    name: str
    camera_height_m: float = 1.0
    camera_pitch_deg: float = 15.0
    boxes: list[Box] = field(default_factory=list)
    wall_distance_m: float = 5.0
    noise_sigma: float = 1.5  # grey levels, sensor noise added per frame
    floor_texture_seed: int = 1
    wall_texture_seed: int = 2
    description: str = ""
    camera_motion: CameraMotion | None = None  # None: the camera stands still at its mount
    range_m: float | None = None  # the vision range the scenario is meant for (None: the segmenter's own)
    default_eval: bool = True  # part of `eval` without scenario names (false: run it by name)

    @classmethod
    def default(cls) -> "Scene":
        """The two-boxes scene: camera 1.0 m high, 15 deg down; box-a (0.5 x 0.6 x 0.3 m) 1.8 m
        ahead, 0.35 m left; box-b (0.4 x 0.8 x 0.3 m) 2.4 m ahead, 0.5 m right; wall at 5 m."""
        return cls.builtin("two-boxes")

    @classmethod
    def builtin(cls, name: str) -> "Scene":
        """A shipped scenario by name (see `list_builtin_scenarios`); a path to a scenario YAML
        file is accepted too, so one setting can name either."""
        path = SCENARIO_DIR / f"{name}.yaml"
        if path.is_file():
            return cls.from_yaml(path)
        if str(name).endswith((".yaml", ".yml")) and Path(name).is_file():
            return cls.from_yaml(name)
        raise ConfigError(f"scenario {name}: no such file or folder, nor a built-in scenario "
                          f"(built-in: {', '.join(list_builtin_scenarios())})")

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Scene":
        """Load a scenario file; errors name the file, the object and the field."""
        from common.errors import FileError
        from common.files import read_yaml

        try:
            doc = read_yaml(path, "scenario")
        except FileError as e:  # missing, empty, binary, not YAML: one line naming the file
            raise ConfigError(str(e)) from None
        return cls.from_dict(doc, where=str(path), default_name=Path(path).stem)

    @classmethod
    def from_dict(cls, doc: Any, where: str = "scenario", default_name: str = "") -> "Scene":
        """Build a scene from a parsed scenario document (the YAML format, see scenarios/*.yaml and
        SceneDoc): validated by pydantic, every error naming where, which object and which field."""
        if not isinstance(doc, dict):
            raise ConfigError(f"{where}: expected a mapping, got {type(doc).__name__}")
        if default_name and doc.get("name") is None:
            doc = {**doc, "name": default_name}
        try:
            d = SceneDoc.model_validate(doc)
        except ValidationError as e:
            raise ConfigError(_scene_errors(e, doc, where)) from None
        scene = cls(name=d.name, description=d.description, camera_height_m=d.camera_height_m,
                    camera_pitch_deg=d.camera_pitch_deg, wall_distance_m=d.wall_distance_m,
                    noise_sigma=d.noise_sigma, floor_texture_seed=d.floor_texture_seed,
                    wall_texture_seed=d.wall_texture_seed, boxes=[o.box() for o in d.objects],
                    camera_motion=d.camera_motion.motion() if d.camera_motion is not None else None,
                    range_m=d.range_m, default_eval=d.default_eval)
        for b in scene.boxes:
            if b.center[0] - b.size[2] / 2 >= scene.wall_distance_m:
                raise ConfigError(f"{where}: object '{b.name}' stands behind the wall")
        return scene

    def is_static(self) -> bool:
        """Nothing moves: neither the objects nor the camera (a static scene is rendered once)."""
        return self.camera_motion is None and all(b.is_static() for b in self.boxes)

    def camera_moves(self) -> bool:
        return self.camera_motion is not None


def list_builtin_scenarios() -> list[str]:
    """Names of the shipped scenarios (services/capture/scenarios/*.yaml)."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


# --- the scenario file format (scenarios/*.yaml), validated ------------------------------------------

_Num = Annotated[float, Strict(), Field(allow_inf_nan=False)]  # a YAML number (int or float), not "1" or true
_Int = Annotated[int, Strict()]
_Positive = Annotated[float, Strict(), Field(gt=0, allow_inf_nan=False)]
_Vec2 = Annotated[list[_Num], Field(min_length=2, max_length=2)]
_Vec3 = Annotated[list[_Num], Field(min_length=3, max_length=3)]
_Size = Annotated[list[_Positive], Field(min_length=3, max_length=3)]


class _Doc(BaseModel):
    model_config = ConfigDict(extra="forbid", coerce_numbers_to_str=True)


class PartDoc(_Doc):
    """One box of a compound object, object frame: offset [x, y, z] m, size [w, h, d] m."""

    offset: _Vec3
    size: _Size
    yaw_deg: _Num = 0.0
    name: str = ""


class PathDoc(_Doc):
    """Waypoints [[x, y], ...] (world, m) followed at speed_mps; loop back to the first or stop."""

    waypoints: Annotated[list[_Vec2], Field(min_length=2)]
    speed_mps: Annotated[float, Strict(), Field(gt=0, allow_inf_nan=False)]
    loop: Annotated[bool, Strict()] = True
    face_motion: Annotated[bool, Strict()] = False


class ObjectDoc(_Doc):
    """One entry of `objects:`: a box (`size`) or a compound (`parts`). position [x, y] stands the
    object on the floor; [x, y, z] gives its centre (simple box) or origin (compound) explicitly;
    with a path and no position it starts at the first waypoint."""

    name: str
    kind: str = "box"
    position: Annotated[list[_Num], Field(min_length=2, max_length=3)] | None = None
    size: _Size | None = None
    parts: Annotated[list[PartDoc], Field(min_length=1)] | None = None
    yaw_deg: _Num = 0.0
    texture_seed: _Int = 0
    path: PathDoc | None = None

    @model_validator(mode="after")
    def _shape(self) -> "ObjectDoc":
        if self.size is not None and self.parts is not None:
            raise ValueError("give either 'size' or 'parts', not both")
        if self.size is None and self.parts is None:
            raise ValueError("missing field 'size' (or 'parts' for a compound object)")
        if self.position is None and self.path is None:
            raise ValueError("missing field 'position'")
        return self

    def box(self) -> Box:
        path = [tuple(w) for w in self.path.waypoints] if self.path else None
        pos = tuple(self.position) if self.position is not None else path[0]  # type: ignore[index]
        if len(pos) == 2:
            z = 0.0 if self.parts else self.size[1] / 2.0  # type: ignore[index]
            pos = (pos[0], pos[1], z)
        parts = [Part(tuple(p.offset), tuple(p.size), p.yaw_deg, p.name) for p in self.parts] if self.parts else None
        return Box(name=self.name, kind=self.kind, center=pos, size=tuple(self.size) if self.size else None,
                   yaw_deg=self.yaw_deg, texture_seed=self.texture_seed, path=path,
                   speed_mps=self.path.speed_mps if self.path else 0.0, loop=self.path.loop if self.path else True,
                   face_motion=self.path.face_motion if self.path else False, parts=parts)  # type: ignore[arg-type]


class WaveDoc(_Doc):
    """One sinusoid of a sway: amplitude (deg or m) * sin(2 pi frequency_hz t + phase_deg)."""

    amplitude: Annotated[float, Strict(), Field(ge=0, allow_inf_nan=False)]
    frequency_hz: Annotated[float, Strict(), Field(gt=0, le=30, allow_inf_nan=False)]
    phase_deg: _Num = 0.0


class CameraMotionDoc(_Doc):
    """`camera_motion:` the robot drives from `start` [x, y, heading deg] at speed_mps, turning at
    yaw_rate_deg_s, and the camera sways on it: sinusoids added to its pitch, roll (deg) and height
    (m), about its own centre or, with pivot_height_m, about a point that high under it."""

    start: Annotated[list[_Num], Field(min_length=3, max_length=3)] = [0.0, 0.0, 0.0]
    speed_mps: Annotated[float, Strict(), Field(ge=0, le=10, allow_inf_nan=False)] = 0.0
    yaw_rate_deg_s: Annotated[float, Strict(), Field(ge=-180, le=180, allow_inf_nan=False)] = 0.0
    pitch_deg: list[WaveDoc] = []
    roll_deg: list[WaveDoc] = []
    height_m: list[WaveDoc] = []
    pivot_height_m: Annotated[float, Strict(), Field(ge=0, allow_inf_nan=False)] | None = None

    def motion(self) -> CameraMotion:
        def waves(ws: list[WaveDoc]) -> tuple[Wave, ...]:
            return tuple(Wave(w.amplitude, w.frequency_hz, w.phase_deg) for w in ws)

        return CameraMotion((self.start[0], self.start[1], self.start[2]), self.speed_mps, self.yaw_rate_deg_s,
                            waves(self.pitch_deg), waves(self.roll_deg), waves(self.height_m), self.pivot_height_m)


class SceneDoc(_Doc):
    """A scenario file: camera mount, floor, wall, noise, and the obstacles (world frame, m)."""

    name: str
    description: str = ""
    camera_height_m: Annotated[float, Strict(), Field(ge=0.05, allow_inf_nan=False)] = 1.0
    camera_pitch_deg: Annotated[float, Strict(), Field(ge=-60.0, le=60.0)] = 15.0
    wall_distance_m: Annotated[float, Strict(), Field(ge=0.5, allow_inf_nan=False)] = 5.0
    noise_sigma: Annotated[float, Strict(), Field(ge=0.0, le=50.0)] = 1.5
    floor_texture_seed: _Int = 1
    wall_texture_seed: _Int = 2
    objects: list[ObjectDoc]
    camera_motion: CameraMotionDoc | None = None
    # the vision range the scenario is meant for: eval runs the segmenter with it and expects what
    # it holds (None: the segmenter's own range)
    range_m: Annotated[float, Strict(), Field(ge=0.5, le=100, allow_inf_nan=False)] | None = None
    # part of `eval` without scenario names; false for one too slow to render for every run
    default_eval: Annotated[bool, Strict()] = True

    @model_validator(mode="after")
    def _unique(self) -> "SceneDoc":
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            raise ValueError(f"object names must be unique, got {names}")
        return self

    @model_validator(mode="after")
    def _sway_in_bounds(self) -> "SceneDoc":
        m = self.camera_motion
        if m is None:
            return self
        pitch = abs(self.camera_pitch_deg) + sum(w.amplitude for w in m.pitch_deg)
        if pitch > 60.0:
            raise ValueError(f"camera_motion: camera_pitch_deg {self.camera_pitch_deg:g} and the pitch_deg "
                             f"amplitudes reach {pitch:g} deg (at most 60)")
        roll = sum(w.amplitude for w in m.roll_deg)
        if roll > 45.0:
            raise ValueError(f"camera_motion: the roll_deg amplitudes add up to {roll:g} deg (at most 45)")
        low = self.camera_height_m - sum(w.amplitude for w in m.height_m)
        if low < 0.05:
            raise ValueError(f"camera_motion: the height_m amplitudes take the camera down to {low:g} m "
                             f"(camera_height_m {self.camera_height_m:g}; at least 0.05 m)")
        if m.pivot_height_m is not None and m.pivot_height_m >= low:
            raise ValueError(f"camera_motion: pivot_height_m {m.pivot_height_m:g} must be below the camera "
                             f"(lowest {low:g} m)")
        return self


def _scene_errors(e: ValidationError, doc: Any, where: str) -> str:
    """pydantic's errors in the scenario file's words: file, object (by index and name), field."""
    out = []
    for err in e.errors():
        loc, node, parts = list(err["loc"]), doc, []
        field_name = None
        for i, key in enumerate(loc):
            if isinstance(key, int):
                name = node[key].get("name") if isinstance(node, list) and key < len(node) and \
                    isinstance(node[key], dict) else None
                parts[-1] = f"{parts[-1]}[{key}]" + (f" ('{name}')" if name else "")
                node = node[key] if isinstance(node, list) and key < len(node) else None
            elif i == len(loc) - 1 or (i == len(loc) - 2 and isinstance(loc[-1], int) and key not in
                                         ("objects", "parts")):
                field_name = f"'{key}'" + (f" item {loc[-1]}" if i == len(loc) - 2 else "")
                break
            else:
                parts.append(str(key))
                node = node.get(key) if isinstance(node, dict) else None
        at = ": ".join(parts)
        msg = err["msg"].removeprefix("Value error, ")
        got = err.get("input")
        if err["type"] == "missing":
            text = f"missing field {field_name}"
        elif err["type"] == "extra_forbidden":
            text = f"unknown field {field_name}"
        elif field_name:
            shown = f" (got {got!r})" if not isinstance(got, (dict, list)) else ""
            text = f"field {field_name}: {msg}{shown}"
        else:
            text = msg
        out.append(f"{where}: {at + ': ' if at else ''}{text}")
    return "; ".join(out)


# --- ground truth ------------------------------------------------------------------------------------

@dataclass
class ObstacleTruth:
    """One obstacle's ground truth at one time, in the RECTIFIED LEFT CAMERA frame (x right, y down,
    z forward, m).

    center_m: (3,) centre of the object's (union) box. size_m: (w, h, d) m, the object's own extents
    (width across, height, depth) in the world. visible_centroid_m: (3,) mean of the surface points
    seen by the rectified left image's pixels (NaN if none). nearest_m: min Euclidean distance of
    those points to the camera (NaN if none). visible_px: pixel count in the rectified left image.
    bbox_px: (x0, y0, x1, y1) inclusive pixel bounds in the rectified left image, None if not visible.
    velocity_mps: (3,) m/s, over the floor (not relative to a driving robot), in camera axes.
    center_base_m, visible_centroid_base_m, velocity_base_mps: the same in the robot base frame
    (REP 103, on the floor under the robot, not tilted by the camera's sway).
    static: the object stands still in the world.
    """

    name: str
    kind: str
    center_m: np.ndarray
    size_m: tuple[float, float, float]
    visible_centroid_m: np.ndarray
    nearest_m: float
    visible_px: int
    bbox_px: tuple[int, int, int, int] | None
    velocity_mps: np.ndarray
    center_base_m: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    visible_centroid_base_m: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    velocity_base_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    static: bool = True


# --- rendering ---------------------------------------------------------------------------------------

@dataclass
class _View:
    """A camera's rays: origin (3,) and unit directions (N, 3) float32, both in the world frame,
    one per pixel, row-major; plus what `_window` needs to bound an object in the image."""

    origin: np.ndarray
    dirs: np.ndarray
    shape: tuple[int, int]  # H, W
    pix_angle: float  # rad per pixel, for texture prefiltering
    shaded: bool  # False: geometry only (the ground-truth view needs no image)
    R_cam_world: np.ndarray  # 3x3, world -> camera rotation
    K: np.ndarray  # 3x3 pinhole part of the camera
    slack_px: float  # max distance between a pixel and the pinhole projection of its ray, + margin

    def window(self, corners_world: np.ndarray) -> tuple[int, int, int, int] | None:
        """Pixel rectangle (y0, y1, x0, x1), end-exclusive, holding every ray that can hit the
        convex hull of `corners_world` (k, 3); None if it is outside the image."""
        h, w = self.shape
        X = (corners_world - self.origin) @ self.R_cam_world.T
        if np.any(X[:, 2] < 0.05):  # near or behind the camera: no safe projection, test all rays
            return 0, h, 0, w
        uv = (X[:, :2] / X[:, 2:]) @ self.K[:2, :2].T + self.K[:2, 2]
        x0 = max(int(math.floor(uv[:, 0].min() - self.slack_px)), 0)
        x1 = min(int(math.ceil(uv[:, 0].max() + self.slack_px)) + 1, w)
        y0 = max(int(math.floor(uv[:, 1].min() - self.slack_px)), 0)
        y1 = min(int(math.ceil(uv[:, 1].max() + self.slack_px)) + 1, h)
        return (y0, y1, x0, x1) if x0 < x1 and y0 < y1 else None


@dataclass
class _Layer:
    """A rendered view: per pixel the hit distance t (m along the unit ray), shade (grey levels)
    and obstacle index (-1 = floor/wall); (N,) arrays."""

    t: np.ndarray
    shade: np.ndarray
    obj: np.ndarray

    def copy(self) -> "_Layer":
        return _Layer(self.t.copy(), self.shade.copy(), self.obj.copy())


@dataclass
class _PlacedPart:
    obj: int
    center: np.ndarray  # (3,) world
    yaw: float
    half: np.ndarray  # (3,) half extents along local x, y, z
    tex: np.ndarray  # (6, 5) texture parameters of the faces -x, +x, -y, +y, -z, +z
    light: np.ndarray  # (6,) Lambert factor per face


def _undistorted_rays(K: np.ndarray, D: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Unit ray (N, 3) float64 in the camera frame through the centre of every pixel of the raw
    (distorted) image, row-major. Read-only, shared between worlds of the same camera."""
    return _undistorted_rays_cached(tuple(np.asarray(K, float).ravel()), tuple(np.asarray(D, float).ravel()),
                                    tuple(size))


@functools.lru_cache(maxsize=8)
def _undistorted_rays_cached(K: tuple, D: tuple, size: tuple[int, int]) -> np.ndarray:
    K, D = np.array(K).reshape(3, 3), np.array(D)
    w, h = size
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([xs.ravel(), ys.ravel()], 1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    xy = cv2.undistortPoints(pix, K, D, criteria=crit).reshape(-1, 2)
    d = np.concatenate([xy, np.ones((xy.shape[0], 1))], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d.setflags(write=False)
    return d


def _pinhole_rays(f: float, cx: float, cy: float, size: tuple[int, int]) -> np.ndarray:
    w, h = size
    xs, ys = np.meshgrid((np.arange(w) - cx) / f, (np.arange(h) - cy) / f)
    d = np.stack([xs.ravel(), ys.ravel(), np.ones(w * h)], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _intersect_box(origin: np.ndarray, dirs: np.ndarray, p: _PlacedPart):
    """Slab test of unit rays `dirs` (n, 3) from `origin` (world) against an oriented box.

    Returns (hits, t, face, u, v, du, dv, cos_i) for the rays that hit (the camera is never inside):
    their indices into `dirs`, distance t (m), entry face (index into _FACE_NORMALS), the hit's
    surface coordinates (u, v) on that face (m, part frame), the ray direction's components along
    u and v, and |cos| of its angle to the face normal; all (k,) arrays.
    """
    c, s = math.cos(p.yaw), math.sin(p.yaw)
    o = origin - p.center
    ol = (c * o[0] + s * o[1], -s * o[0] + c * o[1], o[2])
    dl = (c * dirs[:, 0] + s * dirs[:, 1], -s * dirs[:, 0] + c * dirs[:, 1], np.ascontiguousarray(dirs[:, 2]))
    n = dirs.shape[0]
    tnear = np.full(n, -np.inf, np.float32)
    tfar = np.full(n, np.inf, np.float32)
    axis = np.zeros(n, np.int8)
    with np.errstate(divide="ignore", invalid="ignore"):
        for a in range(3):
            inv = np.float32(1.0) / dl[a]
            t1 = (np.float32(-p.half[a] - ol[a])) * inv
            t2 = (np.float32(p.half[a] - ol[a])) * inv
            lo = np.minimum(t1, t2)
            nearer = lo > tnear  # NaN (a ray in a slab's plane) never updates
            tnear = np.where(nearer, lo, tnear)
            axis[nearer] = a
            tfar = np.minimum(tfar, np.maximum(t1, t2))
    hits = np.flatnonzero((tnear <= tfar) & (tnear > 1e-4))
    t, axis = tnear[hits], axis[hits]
    d = [x[hits] for x in dl]
    local = [ol[k] + t * d[k] for k in range(3)]
    dax = np.where(axis == 0, d[0], np.where(axis == 1, d[1], d[2]))
    face = 2 * axis.astype(np.int64) + (dax < 0)  # entered through the face whose normal opposes the ray
    # each face is spanned by the two other local axes: x-faces by (y, z), y-faces (x, z), z-faces (x, y)
    u = np.where(axis == 0, local[1], local[0])
    v = np.where(axis == 2, local[1], local[2])
    du = np.where(axis == 0, d[1], d[0])
    dv = np.where(axis == 2, d[1], d[2])
    return hits, t, face, u, v, du, dv, np.abs(dax)


@dataclass
class _Cam:
    """One view of the rig, independent of where the rig is: unit rays (N, 3) in its own frame,
    rotation R_left_cam (its axes in left-camera coordinates) and centre (left-camera coordinates),
    pinhole K, shaded or geometry only, and the window slack (see _View.slack_px)."""

    dirs: np.ndarray
    R_left_cam: np.ndarray
    center_left: np.ndarray
    K: np.ndarray
    shaded: bool
    slack_px: float = 2.0

    def __post_init__(self) -> None:
        self.dirs32 = np.ascontiguousarray(self.dirs, np.float32)  # a moving camera turns them every frame


class SyntheticWorld:
    """Renders a `Scene` for a raw stereo rig, with ground truth in the rectified left frame.

    rig: the raw rig whose images are rendered (distortion included). rect: its rectification
    (`camera.rectify_rig(rig, alpha)`), which defines the ground-truth frame and images.
    seed: texture and sensor-noise seed. noise_sigma: grey levels per pixel per frame (None = the
    scene's). blur_sigma: Gaussian optical blur, px. Everything is deterministic for these and t.

    Cost: floor, wall and static objects are ray-cast once per camera; a frame then casts only the
    moving objects' rays (their image windows). A static scene is rendered once and each frame only
    adds its noise. A moving camera (scene.camera_motion) casts every ray every frame.

    Poses: `left_pose(t)` (world), `T_world_base(t)`, `T_base_rect(t)` (the rectified camera on the
    robot, what a ground estimate measures), `T_world_rect_at(t)`, `odometry(t)`.
    """

    def __init__(self, scene: Scene, rig: camera.RawRig, rect: camera.Rectification, seed: int = 0,
                 noise_sigma: float | None = None, blur_sigma: float = 0.6) -> None:
        if not isinstance(rig, camera.RawRig):
            raise camera.CalibrationError("the synthetic world needs a raw rig (K, D, R, T), not a rectified one")
        self.scene = scene
        self.blur_sigma = float(blur_sigma)
        self.rig = rig
        self.rect = rect
        self.seed = seed
        self.noise_sigma = float(scene.noise_sigma if noise_sigma is None else noise_sigma)
        self._levels = texture_pyramid(seed)
        w, h = rig.image_size
        self.shape = (h, w)

        R1 = np.asarray(rect.R1, float)
        Rl, Tl = np.asarray(rig.R, float), np.asarray(rig.T, float)
        m = rect.model
        rect_dirs = _pinhole_rays(m.focal_px, m.cx, m.cy, (m.width, m.height))
        K_rect = np.array([[m.focal_px, 0.0, m.cx], [0.0, m.focal_px, m.cy], [0.0, 0.0, 1.0]])
        # per view (0 left, 1 right, 2 rectified left): its rays in its own frame, its rotation and
        # centre relative to the left camera, its pinhole K, and whether it is shaded
        self._cams = [
            _Cam(_undistorted_rays(rig.left.K, rig.left.D, rig.image_size), np.eye(3), np.zeros(3), rig.left.K, True),
            _Cam(_undistorted_rays(rig.right.K, rig.right.D, rig.image_size), Rl.T, -Rl.T @ Tl, rig.right.K, True),
            _Cam(rect_dirs, R1.T, np.zeros(3), K_rect, False),
        ]
        for c in self._cams:
            # lens distortion moves pixels off their pinhole position; objects are bounded in the
            # image by pinhole projection, so widen their windows by the largest such offset
            pin = c.dirs[:, :2] / c.dirs[:, 2:] @ c.K[:2, :2].T + c.K[:2, 2]
            xs, ys = np.meshgrid(np.arange(w), np.arange(h))
            c.slack_px = float(np.abs(pin - np.stack([xs.ravel(), ys.ravel()], 1)).max()) + 2.0
        self._rect_dirs = rect_dirs.astype(np.float32)  # the rectified view's rays in the rectified frame
        self._rect_shape = (m.height, m.width)
        self._view_cache: dict[tuple[int, float], _View] = {}
        # the pose at t = 0 (the only one of a camera that does not move): world frame
        self.R_world_left, self.origin_left = self.left_pose(0.0)
        self.R_world_rect = self.R_world_left @ R1.T
        self._left, self._right, self._rect = (self._make_view(k, 0.0) for k in range(3))

        self._floor_tex = _SurfaceTex.from_seed(scene.floor_texture_seed, seed)
        self._wall_tex = _SurfaceTex.from_seed(scene.wall_texture_seed, seed)
        self._part_tex = [[np.stack([_SurfaceTex.from_seed(b.texture_seed, j, f, seed).params for f in range(6)])
                           for j in range(len(b.part_list()))] for b in scene.boxes]
        self._static_objs = [i for i, b in enumerate(scene.boxes) if b.is_static()]
        self._moving_objs = [i for i, b in enumerate(scene.boxes) if not b.is_static()]
        self._static_layers: dict[int, _Layer] = {}
        self._frame_cache: dict[tuple[int, float], _Layer] = {}
        self._truth_cache: dict[float, list[ObstacleTruth]] = {}
        self._prerendered: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self._truth_prerendered: dict[float, list[ObstacleTruth]] = {}
        self._disp_cache: dict[float, np.ndarray] = {}

        rng = np.random.default_rng([seed, 0x401CE])
        pad = 64  # per-frame noise = a window of a larger seeded field at a per-frame offset
        self._noise = [(self.noise_sigma * rng.standard_normal((h + pad, w + pad))).astype(np.float32)
                       for _ in range(2)]
        self._noise_pad = pad
        self._clean: tuple[np.ndarray, np.ndarray] | None = None

    # public API ------------------------------------------------------------------------------------
    def is_static(self) -> bool:
        return self.scene.is_static()

    def left_pose(self, t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(R (3, 3): world coordinates of the left camera's optical axes, centre (3,) world m) at t."""
        T = self.T_world_base(t)
        R_b, o_b = self._left_in_base(t)
        return T[:3, :3] @ R_b, T[:3, :3] @ o_b + T[:3, 3]

    def T_world_base(self, t: float = 0.0) -> np.ndarray:
        """4x4: the robot base frame (on the floor under the robot, never tilted) -> world, at t."""
        T = np.eye(4)
        m = self.scene.camera_motion
        if m is not None:
            x, y, yaw = m.base_pose(float(t))
            T[:3, :3] = _rot_z(yaw)
            T[:2, 3] = (x, y)
        return T

    def T_base_rect(self, t: float = 0.0) -> np.ndarray:
        """4x4: the rectified left camera frame -> the robot base frame at t (the camera's true
        mount at that instant: what a ground estimate should find)."""
        R_b, o_b = self._left_in_base(t)
        T = np.eye(4)
        T[:3, :3] = R_b @ np.asarray(self.rect.R1, float).T
        T[:3, 3] = o_b
        return T

    def T_base_rect_upright(self) -> np.ndarray:
        """4x4: the rectified left camera frame -> the base frame of the robot standing upright
        (no sway): the camera mount a configuration file would give."""
        sc = self.scene
        T = np.eye(4)
        T[:3, :3] = camera_axes(sc.camera_pitch_deg, 0.0) @ np.asarray(self.rect.R1, float).T
        T[:3, 3] = (0.0, 0.0, sc.camera_height_m)
        return T

    def T_world_rect_at(self, t: float = 0.0) -> np.ndarray:
        """4x4: the rectified left camera frame -> the world frame at t."""
        return self.T_world_base(t) @ self.T_base_rect(t)

    def odometry(self, t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(linear (3,) m/s, angular (3,) rad/s) of the robot base in its own axes at t (zero when
        the camera does not move)."""
        m = self.scene.camera_motion
        return m.twist(float(t)) if m is not None else (np.zeros(3), np.zeros(3))

    def _left_in_base(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        sc = self.scene
        if sc.camera_motion is None:
            return camera_axes(sc.camera_pitch_deg, 0.0), np.array([0.0, 0.0, sc.camera_height_m])
        return sc.camera_motion.camera_in_base(float(t), sc.camera_height_m, sc.camera_pitch_deg)

    def render(self, t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The raw (distorted) left and right images at time t (s): uint8 (H, W) each."""
        if self.is_static():
            if self._clean is None:
                self._clean = self._render_clean(0.0)
            clean = self._clean
        else:
            clean = self._prerendered.get(float(t)) or self._render_clean(t)
        return self._add_noise(clean[0], t, 0), self._add_noise(clean[1], t, 1)

    def prerender(self, times: Sequence[float]) -> None:
        """Render the (noise-free) pairs and the truth for `times` (s) now, and keep them: render(t)
        and truth(t) at those exact times then cost a copy plus the noise. ~2.5 MB per time."""
        for t in times:
            if not self.is_static():
                self._prerendered[float(t)] = self._render_clean(float(t))
            self._truth_prerendered[0.0 if self.is_static() else float(t)] = self._compute_truth(float(t))

    def truth(self, t: float = 0.0) -> list[ObstacleTruth]:
        """Ground truth of every obstacle at time t, in scene order, rectified left frame."""
        key = 0.0 if self.is_static() else float(t)
        if key in self._truth_prerendered:
            self._truth_cache[key] = self._truth_prerendered[key]
        elif key not in self._truth_cache:
            if len(self._truth_cache) > 8:
                self._truth_cache.clear()
            self._truth_cache[key] = self._compute_truth(key)
        return [dataclasses.replace(o, center_m=o.center_m.copy(), visible_centroid_m=o.visible_centroid_m.copy(),
                                    velocity_mps=o.velocity_mps.copy(), center_base_m=o.center_base_m.copy(),
                                    visible_centroid_base_m=o.visible_centroid_base_m.copy(),
                                    velocity_base_mps=o.velocity_base_mps.copy()) for o in self._truth_cache[key]]

    def _compute_truth(self, t: float) -> list[ObstacleTruth]:
        layer = self._layer(2, t)
        w = self._rect_shape[1]
        T_wr = self.T_world_rect_at(t)
        R_rect_world, origin = T_wr[:3, :3].T, T_wr[:3, 3]
        T_br = self.T_base_rect(t)
        out = []
        for i, b in enumerate(self.scene.boxes):
            origin_b, yaw, vel = b.pose(t)
            center_w = origin_b + _rot_z(yaw) @ b.local_center()
            center = R_rect_world @ (center_w - origin)
            idx = np.flatnonzero(layer.obj == i)
            if idx.size:
                # rectified frame, origin = the left camera centre
                ti = layer.t[idx]
                centroid = (ti[:, None] * self._rect_dirs[idx]).mean(0, dtype=np.float64)
                nearest = float(ti.min())  # unit rays from the camera centre: t is the distance
                ys, xs = np.divmod(idx, w)
                bbox: tuple[int, int, int, int] | None = (int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max()))
            else:
                centroid, nearest, bbox = np.full(3, np.nan), float("nan"), None
            to_base = lambda p: T_br[:3, :3] @ p + T_br[:3, 3]  # noqa: E731
            out.append(ObstacleTruth(b.name, b.kind, center, tuple(b.size), centroid, nearest,  # type: ignore[arg-type]
                                     int(idx.size), bbox, R_rect_world @ vel, to_base(center), to_base(centroid),
                                     T_br[:3, :3] @ (R_rect_world @ vel), b.is_static()))
        return out

    def true_disparity(self, t: float = 0.0) -> np.ndarray:
        """Exact disparity f*B/Z of the rectified left image at time t: float32 (H, W) px,
        NaN where the ray hits no surface. Z is along the rectified optical axis."""
        key = 0.0 if self.is_static() else float(t)
        if key not in self._disp_cache:
            if len(self._disp_cache) > 8:
                self._disp_cache.clear()
            z = self._layer(2, key).t * self._rect_dirs[:, 2]
            m = self.rect.model
            with np.errstate(divide="ignore"):
                d = np.where(np.isfinite(z) & (z > 0), m.focal_px * m.baseline_m / z, np.nan)
            self._disp_cache[key] = d.astype(np.float32).reshape(self._rect_shape)
        return self._disp_cache[key].copy()

    def true_depth(self, t: float = 0.0) -> np.ndarray:
        """Z (m, along the rectified optical axis) of the rectified left image: float32 (H, W), NaN = none."""
        z = self._layer(2, t).t * self._rect_dirs[:, 2]
        return np.where(np.isfinite(z), z, np.nan).astype(np.float32).reshape(self._rect_shape)

    def obstacle_ids(self, t: float = 0.0) -> np.ndarray:
        """Index into scene.boxes of the obstacle seen at each rectified left pixel, -1 = floor or
        wall: int16 (H, W)."""
        return self._layer(2, t).obj.reshape(self._rect_shape).copy()

    @property
    def T_world_rect(self) -> np.ndarray:
        """4x4 transform from the rectified left camera frame to the world frame at t = 0 (the robot
        base frame of a camera that does not move; see T_world_rect_at, T_base_rect)."""
        return self.T_world_rect_at(0.0)

    # internals -------------------------------------------------------------------------------------
    def _add_noise(self, clean: np.ndarray, t: float, cam: int) -> np.ndarray:
        if self.noise_sigma <= 0:
            out = clean
        else:
            k = (int(round(t * 1000.0)) * 2654435761 + cam * 97) & 0xFFFFFFFF
            pad = self._noise_pad
            oy, ox = (k >> 8) % pad, (k >> 20) % pad
            h, w = clean.shape
            out = clean + self._noise[cam][oy:oy + h, ox:ox + w]
        return np.clip(out, 0.0, 255.0).astype(np.uint8)

    def _render_clean(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.shape
        out = []
        for cam in (0, 1):
            img = self._layer(cam, t).shade.reshape(h, w)
            if self.blur_sigma > 0:
                # lens/sensor blur: real optics are soft; razor-sharp near-Nyquist texture would
                # make every sub-pixel resampling (rectification) disagree between the two views
                img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma, borderType=cv2.BORDER_REPLICATE)
            out.append(img + np.float32(0.5))  # +0.5: the uint8 conversion truncates
        return out[0], out[1]

    def _make_view(self, which: int, t: float) -> _View:
        c = self._cams[which]
        R_wl, o_wl = self.left_pose(t)
        R_world_cam = R_wl @ c.R_left_cam
        dw = c.dirs32 @ R_world_cam.T.astype(np.float32)
        K = c.K
        return _View(o_wl + R_wl @ c.center_left, dw, self.shape, 1.0 / K[0, 0], c.shaded, R_world_cam.T, K,
                     c.slack_px)

    def _view(self, which: int, t: float = 0.0) -> _View:
        if not self.scene.camera_moves():
            return (self._left, self._right, self._rect)[which]
        key = (which, float(t))
        if key not in self._view_cache:
            if len(self._view_cache) > 6:
                self._view_cache.clear()
            self._view_cache[key] = self._make_view(which, float(t))
        return self._view_cache[key]

    def _layer(self, which: int, t: float) -> _Layer:
        """Depth, shade and obstacle index of view `which` (0 left, 1 right, 2 rectified left)."""
        if self.scene.camera_moves():
            # everything moves in the image: floor, wall and every object are cast for each frame
            key = (which, float(t))
            if key not in self._frame_cache:
                if len(self._frame_cache) > 6:
                    self._frame_cache.clear()
                v = self._view(which, t)
                layer = self._background(v)
                for i in range(len(self.scene.boxes)):
                    self._draw(v, layer, i, t)
                self._frame_cache[key] = layer
            return self._frame_cache[key]
        if which not in self._static_layers:
            base = self._background(self._view(which))
            for i in self._static_objs:
                self._draw(self._view(which), base, i, 0.0)
            self._static_layers[which] = base
        if not self._moving_objs:
            return self._static_layers[which]
        key = (which, float(t))
        if key not in self._frame_cache:
            if len(self._frame_cache) > 6:
                self._frame_cache.clear()
            layer = self._static_layers[which].copy()
            for i in self._moving_objs:
                self._draw(self._view(which), layer, i, t)
            self._frame_cache[key] = layer
        return self._frame_cache[key]

    def _background(self, v: _View) -> _Layer:
        """Floor and wall: every ray in the field of view hits one of them."""
        o, d = v.origin, v.dirs
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.where(d[:, 2] < 0, -o[2] / d[:, 2], np.inf)
            t_wall = np.where(d[:, 0] > 0, (self.scene.wall_distance_m - o[0]) / d[:, 0], np.inf)
        floor = t_floor < t_wall
        t = np.minimum(t_floor, t_wall).astype(np.float32)
        shade = np.zeros(t.shape, np.float32)
        if not v.shaded:
            return _Layer(t, shade, np.full(t.shape, -1, np.int16))
        for mask, tex, normal, uv_axes in ((floor, self._floor_tex, np.array([0.0, 0.0, 1.0]), (0, 1)),
                                           (~floor & np.isfinite(t), self._wall_tex, np.array([-1.0, 0.0, 0.0]), (1, 2))):
            idx = np.flatnonzero(mask)
            if not idx.size:
                continue
            ti = t[idx]
            p = o + ti[:, None] * d[idx]
            cos_i = np.abs(d[idx] @ normal.astype(np.float32))
            di = d[idx]
            shade[idx] = self._shade(p[:, uv_axes[0]], p[:, uv_axes[1]], ti, di[:, uv_axes[0]], di[:, uv_axes[1]],
                                     cos_i, v.pix_angle, tex.params[None]) * _lambert(normal)
        return _Layer(t, shade, np.full(t.shape, -1, np.int16))

    def _shade(self, u, v, t, dir_u, dir_v, cos_i, pix_angle, tex: np.ndarray) -> np.ndarray:
        """Texture value at surface coordinates (u, v) m, for rays of length t (m) whose unit direction
        has components dir_u, dir_v along the surface axes and |cos| cos_i to its normal; tex: (n, 5)
        or (1, 5) each pixel's surface parameters (`_SurfaceTex.params`)."""
        minor = t * pix_angle
        major = minor / np.maximum(cos_i, 0.05)
        norm = np.maximum(np.hypot(dir_u, dir_v), 1e-9)
        return _sample(self._levels, u, v, minor.astype(np.float32), major.astype(np.float32),
                       dir_u / norm, dir_v / norm, np.broadcast_to(tex, (u.shape[0], 5)))

    def _placed_parts(self, i: int, t: float) -> list[_PlacedPart]:
        """Obstacle i's parts posed at time t."""
        b = self.scene.boxes[i]
        origin, yaw, _ = b.pose(t)
        Rz = _rot_z(yaw)
        out = []
        for j, part in enumerate(b.part_list()):
            pyaw = yaw + math.radians(part.yaw_deg)
            w, h, d = part.size
            normals = _FACE_NORMALS @ _rot_z(pyaw).T
            out.append(_PlacedPart(
                obj=i, center=origin + Rz @ np.asarray(part.offset, float), yaw=pyaw,
                half=np.array([d, w, h]) / 2.0, tex=self._part_tex[i][j],
                light=np.array([_lambert(n) for n in normals], np.float32)))
        return out

    def _draw(self, v_: _View, layer: _Layer, i: int, t: float) -> None:
        """Z-buffer obstacle i's parts into `layer` (in place)."""
        h, w = v_.shape
        dirs2, t2, shade2, obj2 = (a.reshape(h, w, -1) if a.ndim == 2 else a.reshape(h, w)
                                   for a in (v_.dirs, layer.t, layer.shade, layer.obj))
        found = []
        for p in self._placed_parts(i, t):
            # only rays in the part's image window are tested: slices are views, no gathers
            win = v_.window(_box_corners(p.center, p.yaw, np.array([p.half[1], p.half[2], p.half[0]]) * 2))
            if win is None:
                continue
            y0, y1, x0, x1 = win
            hits, tt, face, u, v, du, dv, cos_i = _intersect_box(v_.origin, dirs2[y0:y1, x0:x1].reshape(-1, 3), p)
            r, c = np.divmod(hits, x1 - x0)
            r += y0
            c += x0
            nearer = tt < t2[r, c]
            if not nearer.any():
                continue
            r, c, tt, face = r[nearer], c[nearer], tt[nearer], face[nearer]
            t2[r, c] = tt
            obj2[r, c] = i
            if v_.shaded:
                found.append((r, c, tt, u[nearer], v[nearer], du[nearer], dv[nearer], cos_i[nearer],
                              p.tex[face], p.light[face]))
        if not found:
            return
        # shade once per object, only what is still in front after all its parts were drawn
        r, c, tt, u, v, du, dv, cos_i, tex, light = (np.concatenate(x) for x in zip(*found))
        keep = t2[r, c] == tt
        r, c = r[keep], c[keep]
        shade2[r, c] = self._shade(u[keep], v[keep], tt[keep], du[keep], dv[keep], cos_i[keep], v_.pix_angle,
                                   tex[keep]) * light[keep]


_FACE_NORMALS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], float)


def _lambert(normal_world: np.ndarray) -> float:
    return float(_AMBIENT + (1.0 - _AMBIENT) * max(0.0, float(np.dot(normal_world, _LIGHT_DIR))))
