"""What the synthetic world holds: obstacles (`Box`, compounds of `Part`s, static or moving on a
path), the floor and back wall, the camera on its robot and how it moves and sways
(`CameraMotion`), and the scenario file format they are read from (scenarios/*.yaml), validated
with errors that name the field. Frames and conventions: see world.py."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationError, model_validator

from common.errors import ConfigError

SCENARIO_DIR = Path(__file__).with_name("scenarios")

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
    blank: its faces are one even grey (a painted cabinet, a white door, a plain van's side): nothing
        for a matcher to match inside them, only their outline against what is around.
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
    blank: bool = False
    path: list[tuple[float, float]] | None = None
    speed_mps: float = 0.0
    loop: bool = True
    face_motion: bool = False
    parts: list[Part] | None = None

    def __post_init__(self) -> None:
        center = tuple(float(c) for c in self.center)
        if self.parts:
            lo, hi = self._local_extent()
            size: tuple[float, ...] = (float(hi[1] - lo[1]), float(hi[2] - lo[2]), float(hi[0] - lo[0]))
        elif self.size is None:
            raise ConfigError(f"object '{self.name}': needs 'size' or 'parts'")
        else:
            size = tuple(float(s) for s in self.size)
        if len(center) != 3 or len(size) != 3:
            raise ConfigError(f"object '{self.name}': center needs 3 numbers and size 3 numbers")
        self.center, self.size = (center[0], center[1], center[2]), (size[0], size[1], size[2])
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
        return [Part((0.0, 0.0, 0.0), self.extent, 0.0, self.name)]

    @property
    def extent(self) -> tuple[float, float, float]:
        """size, which construction always fills in (a compound's from its parts)."""
        if self.size is None:
            raise ConfigError(f"object '{self.name}': needs 'size' or 'parts'")
        return self.size

    def _local_extent(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned extent (lo, hi) (3,) of the union of the parts, object frame, m."""
        pts = np.concatenate([box_corners(np.asarray(p.offset, float), math.radians(p.yaw_deg),
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


def rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def box_corners(center: np.ndarray, yaw: float, size: np.ndarray) -> np.ndarray:
    """(8, 3) corners of a box with size (w, h, d) (local y, z, x extents), yawed about z."""
    w, h, d = size
    sx, sy, sz = np.meshgrid([-d / 2, d / 2], [-w / 2, w / 2], [-h / 2, h / 2], indexing="ij")
    local = np.stack([sx.ravel(), sy.ravel(), sz.ravel()], 1)
    return local @ rot_z(yaw).T + center


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


# optical (x right, y down, z forward) -> body (x forward, y left, z up)
_BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_axes(pitch_deg: float, roll_deg: float) -> np.ndarray:
    """(3, 3) base-frame coordinates of the optical axes (x right, y down, z forward) of a camera
    pitched down by pitch_deg and rolled (right side down) by roll_deg: Ry(pitch) Rx(roll) as in
    the segmenter's Mount (yaw 0)."""
    return rot_y(math.radians(pitch_deg)) @ rot_x(math.radians(roll_deg)) @ _BODY_FROM_OPTICAL


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
    # (x_m, depth_m): the floor falls away by depth_m beyond world x = x_m, across the whole view (a
    # curb or a platform's edge, stairs down); None: one flat floor
    floor_drop: tuple[float, float] | None = None

    @classmethod
    def default(cls) -> Scene:
        """The two-boxes scene: camera 1.0 m high, 15 deg down; box-a (0.5 x 0.6 x 0.3 m) 1.8 m
        ahead, 0.35 m left; box-b (0.4 x 0.8 x 0.3 m) 2.4 m ahead, 0.5 m right; wall at 5 m."""
        return cls.builtin("two-boxes")

    @classmethod
    def builtin(cls, name: str) -> Scene:
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
    def from_yaml(cls, path: str | Path) -> Scene:
        """Load a scenario file; errors name the file, the object and the field."""
        from common.errors import FileError
        from common.files import read_yaml

        try:
            doc = read_yaml(path, "scenario")
        except FileError as e:  # missing, empty, binary, not YAML: one line naming the file
            raise ConfigError(str(e)) from None
        return cls.from_dict(doc, where=str(path), default_name=Path(path).stem)

    @classmethod
    def from_dict(cls, doc: Any, where: str = "scenario", default_name: str = "") -> Scene:
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
                    range_m=d.range_m, default_eval=d.default_eval,
                    floor_drop=(d.floor_drop.x_m, d.floor_drop.depth_m) if d.floor_drop is not None else None)
        for b in scene.boxes:
            if b.center[0] - b.extent[2] / 2 >= scene.wall_distance_m:
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
    blank: bool = False
    path: PathDoc | None = None

    @model_validator(mode="after")
    def _shape(self) -> ObjectDoc:
        if self.size is not None and self.parts is not None:
            raise ValueError("give either 'size' or 'parts', not both")
        if self.size is None and self.parts is None:
            raise ValueError("missing field 'size' (or 'parts' for a compound object)")
        if self.position is None and self.path is None:
            raise ValueError("missing field 'position'")
        return self

    def box(self) -> Box:
        path = [(w[0], w[1]) for w in self.path.waypoints] if self.path else None
        if self.position is not None:
            pos = list(self.position)
        elif path:
            pos = list(path[0])
        else:  # _shape refuses this already
            raise ValueError("missing field 'position'")
        if len(pos) == 2:
            # a compound (no size) stands on its origin; a simple box on its bottom face
            pos.append(0.0 if self.size is None else self.size[1] / 2.0)
        parts = [Part(_three(p.offset), _three(p.size), p.yaw_deg, p.name) for p in self.parts] if self.parts else None
        return Box(name=self.name, kind=self.kind, center=_three(pos), size=_three(self.size) if self.size else None,
                   yaw_deg=self.yaw_deg, texture_seed=self.texture_seed, blank=self.blank, path=path,
                   speed_mps=self.path.speed_mps if self.path else 0.0, loop=self.path.loop if self.path else True,
                   face_motion=self.path.face_motion if self.path else False, parts=parts)


def _three(v: list[float]) -> tuple[float, float, float]:
    """A validated list of 3 numbers as the tuple the geometry takes."""
    x, y, z = v
    return x, y, z


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


class FloorDropDoc(_Doc):
    """`floor_drop:` the floor beyond world x = x_m lies depth_m lower (a curb down, a platform's edge)."""

    x_m: Annotated[float, Strict(), Field(ge=0.3, le=100, allow_inf_nan=False)]
    depth_m: Annotated[float, Strict(), Field(gt=0, le=10, allow_inf_nan=False)]


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
    floor_drop: FloorDropDoc | None = None

    @model_validator(mode="after")
    def _unique(self) -> SceneDoc:
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            raise ValueError(f"object names must be unique, got {names}")
        return self

    @model_validator(mode="after")
    def _sway_in_bounds(self) -> SceneDoc:
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
        loc, node = list(err["loc"]), doc
        parts: list[str] = []
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
