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
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from cores import camera
from sim.raycast import (
    FACE_NORMALS,
    Cam,
    Layer,
    PlacedPart,
    View,
    intersect_box,
    lambert,
    pinhole_rays,
    undistorted_rays,
)
from sim.scene import Box, Scene, box_corners, camera_axes, rot_z
from sim.texture import SurfaceTexture, sample_texture, texture_pyramid

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
        rect_dirs = pinhole_rays(m.focal_px, m.cx, m.cy, (m.width, m.height))
        K_rect = np.array([[m.focal_px, 0.0, m.cx], [0.0, m.focal_px, m.cy], [0.0, 0.0, 1.0]])
        # per view (0 left, 1 right, 2 rectified left): its rays in its own frame, its rotation and
        # centre relative to the left camera, its pinhole K, and whether it is shaded
        self._cams = [
            Cam(undistorted_rays(rig.left.K, rig.left.D, rig.image_size), np.eye(3), np.zeros(3), rig.left.K, True),
            Cam(undistorted_rays(rig.right.K, rig.right.D, rig.image_size), Rl.T, -Rl.T @ Tl, rig.right.K, True),
            Cam(rect_dirs, R1.T, np.zeros(3), K_rect, False),
        ]
        for c in self._cams:
            # lens distortion moves pixels off their pinhole position; objects are bounded in the
            # image by pinhole projection, so widen their windows by the largest such offset
            pin = c.dirs[:, :2] / c.dirs[:, 2:] @ c.K[:2, :2].T + c.K[:2, 2]
            xs, ys = np.meshgrid(np.arange(w), np.arange(h))
            c.slack_px = float(np.abs(pin - np.stack([xs.ravel(), ys.ravel()], 1)).max()) + 2.0
        self._rect_dirs = rect_dirs.astype(np.float32)  # the rectified view's rays in the rectified frame
        self._rect_shape = (m.height, m.width)
        self._view_cache: dict[tuple[int, float], View] = {}
        # the pose at t = 0 (the only one of a camera that does not move): world frame
        self.R_world_left, self.origin_left = self.left_pose(0.0)
        self.R_world_rect = self.R_world_left @ R1.T
        self._left, self._right, self._rect = (self._make_view(k, 0.0) for k in range(3))

        self._floor_tex = SurfaceTexture.from_seed(scene.floor_texture_seed, seed)
        self._wall_tex = SurfaceTexture.from_seed(scene.wall_texture_seed, seed)

        def face(b: Box, j: int, f: int) -> np.ndarray:
            return (SurfaceTexture.blank() if b.blank else SurfaceTexture.from_seed(b.texture_seed, j, f, seed)).params

        self._part_tex = [[np.stack([face(b, j, f) for f in range(6)]) for j in range(len(b.part_list()))]
                          for b in scene.boxes]
        self._static_objs = [i for i, b in enumerate(scene.boxes) if b.is_static()]
        self._moving_objs = [i for i, b in enumerate(scene.boxes) if not b.is_static()]
        self._static_layers: dict[int, Layer] = {}
        self._frame_cache: dict[tuple[int, float], Layer] = {}
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
            T[:3, :3] = rot_z(yaw)
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
            center_w = origin_b + rot_z(yaw) @ b.local_center()
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

    def _make_view(self, which: int, t: float) -> View:
        c = self._cams[which]
        R_wl, o_wl = self.left_pose(t)
        R_world_cam = R_wl @ c.R_left_cam
        dw = c.dirs32 @ R_world_cam.T.astype(np.float32)
        K = c.K
        return View(o_wl + R_wl @ c.center_left, dw, self.shape, 1.0 / K[0, 0], c.shaded, R_world_cam.T, K,
                     c.slack_px)

    def _view(self, which: int, t: float = 0.0) -> View:
        if not self.scene.camera_moves():
            return (self._left, self._right, self._rect)[which]
        key = (which, float(t))
        if key not in self._view_cache:
            if len(self._view_cache) > 6:
                self._view_cache.clear()
            self._view_cache[key] = self._make_view(which, float(t))
        return self._view_cache[key]

    def _layer(self, which: int, t: float) -> Layer:
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

    def _background(self, v: View) -> Layer:
        """Floor and wall: every ray in the field of view hits one of them."""
        o, d = v.origin, v.dirs
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.where(d[:, 2] < 0, -o[2] / d[:, 2], np.inf)
            if self.scene.floor_drop is not None:  # past the edge the ray goes on down to the lower floor
                x_edge, depth = self.scene.floor_drop
                past = o[0] + t_floor * d[:, 0] > x_edge
                t_floor = np.where(past, (-depth - o[2]) / d[:, 2], t_floor)
            t_wall = np.where(d[:, 0] > 0, (self.scene.wall_distance_m - o[0]) / d[:, 0], np.inf)
        floor = t_floor < t_wall
        t = np.minimum(t_floor, t_wall).astype(np.float32)
        shade = np.zeros(t.shape, np.float32)
        if not v.shaded:
            return Layer(t, shade, np.full(t.shape, -1, np.int16))
        wall = ~floor & np.isfinite(t)
        for mask, tex, normal, uv_axes in ((floor, self._floor_tex, np.array([0.0, 0.0, 1.0]), (0, 1)),
                                           (wall, self._wall_tex, np.array([-1.0, 0.0, 0.0]), (1, 2))):
            idx = np.flatnonzero(mask)
            if not idx.size:
                continue
            ti = t[idx]
            p = o + ti[:, None] * d[idx]
            cos_i = np.abs(d[idx] @ normal.astype(np.float32))
            di = d[idx]
            shade[idx] = self._shade(p[:, uv_axes[0]], p[:, uv_axes[1]], ti, di[:, uv_axes[0]], di[:, uv_axes[1]],
                                     cos_i, v.pix_angle, tex.params[None]) * lambert(normal)
        return Layer(t, shade, np.full(t.shape, -1, np.int16))

    def _shade(self, u, v, t, dir_u, dir_v, cos_i, pix_angle, tex: np.ndarray) -> np.ndarray:
        """Texture value at surface coordinates (u, v) m, for rays of length t (m) whose unit direction
        has components dir_u, dir_v along the surface axes and |cos| cos_i to its normal; tex: (n, 5)
        or (1, 5) each pixel's surface parameters (`SurfaceTexture.params`)."""
        minor = t * pix_angle
        major = minor / np.maximum(cos_i, 0.05)
        norm = np.maximum(np.hypot(dir_u, dir_v), 1e-9)
        return sample_texture(self._levels, u, v, minor.astype(np.float32), major.astype(np.float32),
                       dir_u / norm, dir_v / norm, np.broadcast_to(tex, (u.shape[0], 5)))

    def footprints(self, t: float, z_from: float, z_to: float) -> list[list[np.ndarray]]:
        """Per obstacle, the ground outlines ((4, 2) corners, robot base frame (x, y), m) of its parts
        that reach from z_from to z_to above the floor anywhere (what stands in the way of a robot
        that tall), at time t."""
        T = np.linalg.inv(self.T_world_base(t))
        out = []
        for i in range(len(self.scene.boxes)):
            polys = []
            for p in self._placed_parts(i, t):
                if p.center[2] - p.half[2] > z_to or p.center[2] + p.half[2] < z_from:
                    continue
                local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], float) * p.half[:2]  # along x = depth d
                world = local @ rot_z(p.yaw)[:2, :2].T + p.center[:2]
                polys.append(world @ T[:2, :2].T + T[:2, 3])
            out.append(polys)
        return out

    def _placed_parts(self, i: int, t: float) -> list[PlacedPart]:
        """Obstacle i's parts posed at time t."""
        b = self.scene.boxes[i]
        origin, yaw, _ = b.pose(t)
        Rz = rot_z(yaw)
        out = []
        for j, part in enumerate(b.part_list()):
            pyaw = yaw + math.radians(part.yaw_deg)
            w, h, d = part.size
            normals = FACE_NORMALS @ rot_z(pyaw).T
            out.append(PlacedPart(
                obj=i, center=origin + Rz @ np.asarray(part.offset, float), yaw=pyaw,
                half=np.array([d, w, h]) / 2.0, tex=self._part_tex[i][j],
                light=np.array([lambert(n) for n in normals], np.float32)))
        return out

    def _draw(self, v_: View, layer: Layer, i: int, t: float) -> None:
        """Z-buffer obstacle i's parts into `layer` (in place)."""
        h, w = v_.shape
        dirs2, t2, shade2, obj2 = (a.reshape(h, w, -1) if a.ndim == 2 else a.reshape(h, w)
                                   for a in (v_.dirs, layer.t, layer.shade, layer.obj))
        found = []
        for p in self._placed_parts(i, t):
            # only rays in the part's image window are tested: slices are views, no gathers
            win = v_.window(box_corners(p.center, p.yaw, np.array([p.half[1], p.half[2], p.half[0]]) * 2))
            if win is None:
                continue
            y0, y1, x0, x1 = win
            hits, tt, face, u, v, du, dv, cos_i = intersect_box(v_.origin, dirs2[y0:y1, x0:x1].reshape(-1, 3), p)
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
