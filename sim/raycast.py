"""The ray-casting pieces the synthetic world renders with (numpy + OpenCV): a camera's rays
(through a lens's distortion, or a pinhole's), the slab test of rays against an oriented box, the
per-pixel layers a view renders into, and the Lambert shading of a face. World frame and
conventions: world.py."""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from sim.texture import AMBIENT, LIGHT_DIR


@dataclass
class View:
    """A camera's rays: origin (3,) and unit directions (N, 3) float32, both in the world frame,
    one per pixel, row-major; plus what `window` needs to bound an object in the image."""

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
class Layer:
    """A rendered view: per pixel the hit distance t (m along the unit ray), shade (grey levels)
    and obstacle index (-1 = floor/wall); (N,) arrays."""

    t: np.ndarray
    shade: np.ndarray
    obj: np.ndarray

    def copy(self) -> Layer:
        return Layer(self.t.copy(), self.shade.copy(), self.obj.copy())


@dataclass
class PlacedPart:
    obj: int
    center: np.ndarray  # (3,) world
    yaw: float
    half: np.ndarray  # (3,) half extents along local x, y, z
    tex: np.ndarray  # (6, 5) texture parameters of the faces -x, +x, -y, +y, -z, +z
    light: np.ndarray  # (6,) Lambert factor per face


def undistorted_rays(K: np.ndarray, D: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Unit ray (N, 3) float64 in the camera frame through the centre of every pixel of the raw
    (distorted) image, row-major. Read-only, shared between worlds of the same camera."""
    return _undistorted_rays_cached(tuple(np.asarray(K, float).ravel()), tuple(np.asarray(D, float).ravel()),
                                    tuple(size))


@functools.lru_cache(maxsize=8)
def _undistorted_rays_cached(K_values: tuple, D_values: tuple, size: tuple[int, int]) -> np.ndarray:
    # (tuples: the cache's keys)
    K, D = np.array(K_values).reshape(3, 3), np.array(D_values)
    w, h = size
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([xs.ravel(), ys.ravel()], 1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    xy = cv2.undistortPoints(pix, K, D, criteria=crit).reshape(-1, 2)
    d = np.concatenate([xy, np.ones((xy.shape[0], 1))], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d.setflags(write=False)
    return d


def pinhole_rays(f: float, cx: float, cy: float, size: tuple[int, int]) -> np.ndarray:
    w, h = size
    xs, ys = np.meshgrid((np.arange(w) - cx) / f, (np.arange(h) - cy) / f)
    d = np.stack([xs.ravel(), ys.ravel(), np.ones(w * h)], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def intersect_box(origin: np.ndarray, dirs: np.ndarray, p: PlacedPart):
    """Slab test of unit rays `dirs` (n, 3) from `origin` (world) against an oriented box.

    Returns (hits, t, face, u, v, du, dv, cos_i) for the rays that hit (the camera is never inside):
    their indices into `dirs`, distance t (m), entry face (index into FACE_NORMALS), the hit's
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
class Cam:
    """One view of the rig, independent of where the rig is: unit rays (N, 3) in its own frame,
    rotation R_left_cam (its axes in left-camera coordinates) and centre (left-camera coordinates),
    pinhole K, shaded or geometry only, and the window slack (see View.slack_px)."""

    dirs: np.ndarray
    R_left_cam: np.ndarray
    center_left: np.ndarray
    K: np.ndarray
    shaded: bool
    slack_px: float = 2.0

    def __post_init__(self) -> None:
        self.dirs32 = np.ascontiguousarray(self.dirs, np.float32)  # a moving camera turns them every frame


FACE_NORMALS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], float)


def lambert(normal_world: np.ndarray) -> float:
    return float(AMBIENT + (1.0 - AMBIENT) * max(0.0, float(np.dot(normal_world, LIGHT_DIR))))
