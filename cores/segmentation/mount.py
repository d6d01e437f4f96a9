"""The camera mount: where the rectified left camera sits on the robot, and what follows from it
(the base-frame transform and the floor plane as the camera sees it).

Frames
------
camera: the rectified left camera, optical (x right, y down, z forward), metres.
base: the robot base frame, REP 103 (x forward, y left, z up), origin on the floor.
The camera sits at (x_m, y_m, height_m) in the base frame. Its orientation is yaw (about base z,
positive turning left), then pitch (about the new y, positive looking DOWN, as in REP 103), then
roll (about the new x, positive tilting the right side down).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from common.messages import CameraMount
from common.settings import MountSettings

# optical (x right, y down, z forward) -> body (x forward, y left, z up)
_BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


@dataclass(frozen=True)
class Mount:
    """One camera mount (defaults nowhere but in MountSettings: a height and a pitch are always said)."""

    height_m: float
    pitch_deg: float
    yaw_deg: float = 0.0
    roll_deg: float = 0.0
    x_m: float = 0.0
    y_m: float = 0.0

    @cached_property
    def R_base_camera(self) -> np.ndarray:
        """(3, 3): base-frame coordinates of a camera-frame vector."""
        r = (_rz(np.deg2rad(self.yaw_deg)) @ _ry(np.deg2rad(self.pitch_deg)) @ _rx(np.deg2rad(self.roll_deg)))
        return r @ _BODY_FROM_OPTICAL

    @property
    def origin_base(self) -> np.ndarray:
        return np.array([self.x_m, self.y_m, self.height_m])

    @cached_property
    def _origin(self) -> np.ndarray:
        return self.origin_base

    def to_base(self, p_camera: np.ndarray) -> np.ndarray:
        """(..., 3) camera-frame points (m) -> (..., 3) base-frame points (m)."""
        # the product by the transposed view as it is (a contiguous copy of it gives other last
        # bits); the offset added in place: a second large array costs more than the product
        out = np.asarray(p_camera, float) @ self.R_base_camera.T
        out += self._origin
        return out

    def vector_to_base(self, v_camera: np.ndarray) -> np.ndarray:
        """(..., 3) camera-frame vectors (velocities) -> base frame."""
        return np.asarray(v_camera, float) @ self.R_base_camera.T

    @property
    def down_camera(self) -> np.ndarray:
        """(3,) unit vector pointing at the floor (base -z), in the camera frame."""
        return self.R_base_camera.T @ np.array([0.0, 0.0, -1.0])

    def message(self, source: str) -> CameraMount:
        return CameraMount(height_m=self.height_m, pitch_deg=self.pitch_deg, roll_deg=self.roll_deg,
                           yaw_deg=self.yaw_deg, x_m=self.x_m, y_m=self.y_m, source=source)

    def leaned(self, height_m: float, pitch_deg: float, roll_deg: float, pivot_height_m: float) -> Mount:
        """This mount (the robot upright) with the camera at the height, pitch and roll a ground
        estimate found, reached by the robot leaning about the point pivot_height_m up the base z axis
        (a ballbot on its ball): the lean that turns the camera also carries it over the floor, which
        the ground cannot show. The height is the one measured."""
        now = Mount(height_m, pitch_deg, self.yaw_deg, roll_deg, self.x_m, self.y_m)
        lean = now.R_base_camera @ self.R_base_camera.T
        pivot = np.array([0.0, 0.0, pivot_height_m])
        x, y, _ = pivot + lean @ (self.origin_base - pivot)
        return Mount(height_m, pitch_deg, self.yaw_deg, roll_deg, float(x), float(y))

    @classmethod
    def of(cls, m: CameraMount | MountSettings | None) -> Mount | None:
        """The mount a list carries (ObstacleList.mount) or the one configured (`mount:`; None when its
        height is unknown)."""
        if m is None or m.height_m is None:
            return None
        return cls(m.height_m, m.pitch_deg, m.yaw_deg, m.roll_deg, m.x_m, m.y_m)


@dataclass(frozen=True)
class FloorPlane:
    """The floor in disparity space: a plane d = a u + b v + c over the rectified left image
    (u, v in px, d in px), with the camera's height above it. Derived from a unit normal n (camera
    frame, pointing at the floor) and height h: d_floor = f B (n . ray) / h, ray = ((u-cx)/f, (v-cy)/f, 1).
    A pixel's point lies h (1 - d_floor / d) above the floor."""

    a: float
    b: float
    c: float
    height_m: float
    fitted: bool = False
    inliers: int = 0

    @classmethod
    def from_normal(cls, n: np.ndarray, height_m: float, f: float, cx: float, cy: float, B: float,
                    fitted: bool = False, inliers: int = 0) -> FloorPlane:
        n = np.asarray(n, float) / np.linalg.norm(n)
        a = B * n[0] / height_m
        b = B * n[1] / height_m
        c = f * B * n[2] / height_m - a * cx - b * cy
        return cls(float(a), float(b), float(c), float(height_m), fitted, inliers)

    def normal_height(self, f: float, cx: float, cy: float, B: float) -> tuple[np.ndarray, float]:
        """(unit normal (3,) camera frame, camera height m) of this plane."""
        k = np.array([self.a, self.b, (self.c + self.a * cx + self.b * cy) / f])  # = B n / h
        norm = float(np.linalg.norm(k))
        return k / norm, B / norm

    def disparity(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self.a * u + self.b * v + self.c
