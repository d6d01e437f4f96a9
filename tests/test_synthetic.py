"""The synthetic stereo world: images, determinism, and agreement between renderer, rig and truth."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

import sim as S
from common.errors import ConfigError
from cores import camera


@pytest.fixture(scope="module")
def rig() -> camera.RawRig:
    return camera.load_calibration("lifecam-studio")


@pytest.fixture(scope="module")
def rect(rig) -> camera.Rectification:
    return camera.rectify_rig(rig, 0.0)


_WORLDS: dict = {}


def _world(name: str, rig, rect, **kw) -> S.SyntheticWorld:
    """One world per (scenario, settings) for the whole module: building one costs ~0.5 s."""
    key = (name, tuple(sorted(kw.items())))
    if key not in _WORLDS:
        _WORLDS[key] = S.SyntheticWorld(S.Scene.builtin(name), rig, rect, **kw)
    return _WORLDS[key]


@pytest.fixture(scope="module")
def world(rig, rect) -> S.SyntheticWorld:
    return _world("two-boxes", rig, rect)


@pytest.fixture(scope="module")
def clean_world(rig, rect) -> S.SyntheticWorld:
    return _world("two-boxes", rig, rect, noise_sigma=0.0)


def _local_std(img: np.ndarray, k: int = 7) -> np.ndarray:
    f = img.astype(np.float32)
    m = cv2.blur(f, (k, k))
    return np.sqrt(np.maximum(cv2.blur(f * f, (k, k)) - m * m, 0.0))


def _rectified(world: S.SyntheticWorld, rig, rect, left, right):
    size = rig.image_size
    out = []
    for cam, R, P, img in ((rig.left, rect.R1, rect.P1, left), (rig.right, rect.R2, rect.P2, right)):
        mx, my = cv2.initUndistortRectifyMap(cam.K, cam.D, R, P, size, cv2.CV_32FC1)
        out.append(cv2.remap(img.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=np.nan))
    return out


def _world_to_rect(scene: S.Scene, rect) -> tuple[np.ndarray, np.ndarray]:
    """Independent derivation of the world -> rectified transform from height and pitch."""
    p = math.radians(scene.camera_pitch_deg)
    # a world point's left-camera coordinates: x = -y_w, then pitch the (forward, down) pair
    def to_left(Xw):
        d = np.asarray(Xw, float) - [0.0, 0.0, scene.camera_height_m]
        fwd, down = d[..., 0], -d[..., 2]
        return np.stack([-d[..., 1], math.cos(p) * down - math.sin(p) * fwd,
                         math.cos(p) * fwd + math.sin(p) * down], -1)
    R = np.stack([to_left(e + np.array([0, 0, scene.camera_height_m])) for e in np.eye(3)], 1)
    t = to_left(np.zeros(3))
    return rect.R1 @ R, rect.R1 @ t


# --- images ------------------------------------------------------------------------------------------

def test_images_shape_dtype_and_texture(world, rig):
    left, right = world.render()
    w, h = rig.image_size
    for img in (left, right):
        assert img.shape == (h, w) and img.dtype == np.uint8
        s = _local_std(img)[4:-4, 4:-4]
        # floor, wall and boxes fill the view; every 7x7 window must be textured enough to match
        assert np.percentile(s, 0.5) > 6.0, np.percentile(s, [0.1, 0.5, 1])
        assert 60 < img.mean() < 170


def test_deterministic_for_a_seed(world, rig, rect):
    again = S.SyntheticWorld(S.Scene.default(), rig, rect, seed=0)
    other = S.SyntheticWorld(S.Scene.default(), rig, rect, seed=1)
    a, b, c = world.render(0.0), again.render(0.0), other.render(0.0)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])


def test_noise_is_per_frame_and_small(world, clean_world):
    l0, _ = world.render(0.0)
    l1, _ = world.render(1 / 30)
    clean, _ = clean_world.render(0.0)
    assert not np.array_equal(l0, l1)
    diff = l0.astype(float) - clean
    assert 0.8 < diff.std() < 2.5 and abs(diff.mean()) < 0.2
    assert np.array_equal(world.render(1 / 30)[0], l1)  # same t, same noise


def test_static_scene_is_cached(world):
    assert world.is_static()
    world.render(0.0)
    import time
    t0 = time.perf_counter()
    for k in range(5):
        world.render(k / 30)
    assert (time.perf_counter() - t0) / 5 < 0.05


def test_default_scene_layout(world, rect):
    """Both boxes entirely inside the rectified left image with margin, not overlapping."""
    tr = {o.name: o for o in world.truth()}
    assert set(tr) == {"box-a", "box-b"}
    w, h = rect.model.width, rect.model.height
    boxes = []
    for o in tr.values():
        x0, y0, x1, y1 = o.bbox_px
        assert x0 >= 20 and y0 >= 20 and x1 <= w - 21 and y1 <= h - 21, (o.name, o.bbox_px)
        boxes.append(o.bbox_px)
    (a0, _, a1, _), (b0, _, b1, _) = sorted(boxes)
    assert a1 < b0
    ids = world.obstacle_ids()
    assert ids.dtype == np.int16 and set(np.unique(ids)) == {-1, 0, 1}


# --- truth vs geometry -----------------------------------------------------------------------------

def test_truth_matches_independent_geometry(world, rect):
    scene = world.scene
    R, t = _world_to_rect(scene, rect)
    P1 = rect.P1
    for box, o in zip(scene.boxes, world.truth()):
        assert np.allclose(o.center_m, R @ np.asarray(box.center) + t, atol=1e-9)
        assert o.size_m == tuple(box.size)
        assert np.array_equal(o.velocity_mps, np.zeros(3))
        u, v, s = P1[:, :3] @ o.center_m
        x0, y0, x1, y1 = o.bbox_px
        assert x0 <= u / s <= x1 and y0 <= v / s <= y1
        # the visible surface faces the camera: nearer than the centre, within the box's reach
        half_diag = 0.5 * np.linalg.norm(box.size)
        assert o.visible_centroid_m[2] < o.center_m[2]
        assert np.linalg.norm(o.visible_centroid_m - o.center_m) < half_diag
        assert np.linalg.norm(o.center_m) - half_diag <= o.nearest_m <= np.linalg.norm(o.visible_centroid_m)
        assert o.visible_px == int((world.obstacle_ids() == scene.boxes.index(box)).sum())
    # box A's nearest visible point: its front face x = 1.65 m; its nearest point to the camera
    # lies on that plane, so its distance is at least the plane's distance from the camera
    a = world.truth()[0]
    assert a.nearest_m >= 1.65 - 1e-6


def test_true_disparity_matches_front_face_plane(world, rect):
    """At pixels of each box's front face, d = f*B/Z with Z from an analytic ray/plane hit."""
    m = rect.model
    R, t = _world_to_rect(world.scene, rect)
    disp = world.true_disparity()
    ids = world.obstacle_ids()
    assert disp.dtype == np.float32 and disp.shape == (m.height, m.width)
    assert np.isfinite(disp).all()  # floor and wall fill the view
    for i, box in enumerate(world.scene.boxes):
        c = np.asarray(box.center)
        w, h, d = box.size
        n_rect = R @ np.array([-1.0, 0, 0])  # front face normal
        p0 = R @ (c - [d / 2, 0, 0]) + t
        ys, xs = np.nonzero(ids == i)
        rays = np.stack([(xs - m.cx) / m.focal_px, (ys - m.cy) / m.focal_px, np.ones(xs.size)], 1)
        z = (n_rect @ p0) / (rays @ n_rect)  # ray (x, y, 1) * z lies on the plane
        hit_w = (rays * z[:, None] - t) @ R  # back to world
        on_face = (np.abs(hit_w[:, 1] - c[1]) < w / 2 - 0.01) & (np.abs(hit_w[:, 2] - c[2]) < h / 2 - 0.01)
        assert on_face.sum() > 1000
        expect = m.focal_px * m.baseline_m / z[on_face]
        assert np.abs(disp[ys[on_face], xs[on_face]] - expect).max() < 0.05


def _matchable(disp: np.ndarray) -> np.ndarray:
    """Pixels of the rectified left image seen by the right camera too, away from depth edges."""
    h, w = disp.shape
    xr = np.arange(w, dtype=np.float32)[None, :] - disp  # where each pixel lands in the right image
    # occluded: a pixel further right lands at or left of it (a nearer surface covers it)
    right_min = np.minimum.accumulate(xr[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([right_min[:, 1:], np.full((h, 1), np.inf, np.float32)], 1)
    k3 = np.ones((3, 3), np.uint8)
    jump = cv2.dilate(disp, k3) - cv2.erode(disp, k3)  # the floor's slope is ~0.1 px/row; edges jump
    smooth = cv2.erode((jump < 1.0).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    return smooth & (right_min > xr - 0.5)


@pytest.mark.parametrize("name,t", [("two-boxes", 0.0), ("chair", 0.0), ("person-walking", 1.3), ("sway", 0.8)])
def test_rectified_pair_agrees_with_true_disparity(name, t, rig, rect):
    """Rectify the rendered raw pair with OpenCV: the right image sampled at x - true disparity
    must reproduce the left one, and visibly less so 0.25 px off. This proves renderer, lens
    distortion, rig and ground truth agree (for moving objects too)."""
    world = _world(name, rig, rect, noise_sigma=0.0)
    left, right = world.render(t)
    rl, rr = _rectified(world, rig, rect, left, right)
    disp = world.true_disparity(t)
    ids = world.obstacle_ids(t)
    h, w = disp.shape
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    mask = _matchable(disp)
    regions = {"floor": (ids == -1) & (ys > 300), "wall": (ids == -1) & (ys < 100)}
    if name == "sway":  # people and furniture fill the top of the view; the far wall shows only in slivers
        regions.pop("wall")
        regions["floor"] = (ids == -1) & (ys > 420)  # rolled 10 deg: the floor far off is grazing
    regions.update({b.name: ids == i for i, b in enumerate(world.scene.boxes)})
    errs = {}
    for shift in (0.0, 0.25, 1.0):
        warped = cv2.remap(rr, xs - disp - shift, ys, cv2.INTER_LINEAR, borderValue=np.nan)
        ok = mask & np.isfinite(warped) & np.isfinite(rl)
        e = np.abs(warped - rl)
        errs[shift] = {k: float(e[ok & sel].mean()) for k, sel in regions.items() if (ok & sel).sum() > 500}
    assert ok.sum() > 0.7 * h * w
    assert set(errs[0.0]) == set(regions), errs  # every region was checked
    for region, e0 in errs[0.0].items():
        # the floor is slanted and finely textured, so resampling costs it most
        assert e0 < (3.0 if region == "floor" else 2.0), errs
        assert errs[0.25][region] > 1.4 * e0 and errs[1.0][region] > 3.0 * e0, errs


def test_subpixel_matches_agree_with_true_disparity(clean_world, rig, rect):
    """Patches on the boxes, floor and wall, matched along the rectified row to subpixel precision,
    land at the true disparity."""
    left, right = clean_world.render()
    rl, rr = (np.nan_to_num(x) for x in _rectified(clean_world, rig, rect, left, right))
    disp = clean_world.true_disparity()
    ids = clean_world.obstacle_ids()
    tr = clean_world.truth()
    pts = []
    for o in tr:
        x0, y0, x1, y1 = o.bbox_px
        pts += [((x0 + x1) // 2 + dx, (y0 + y1) // 2 + dy) for dx in (-20, 0, 20) for dy in (-20, 0, 20)]
    pts += [(300, 60), (500, 100), (150, 150), (320, 400), (560, 440)]  # wall and floor
    r = 7
    errors = []
    for x, y in pts:
        patch_ids = ids[y - r:y + r + 1, x - r:x + r + 1]
        assert (patch_ids == patch_ids[0, 0]).all()
        d = float(disp[y, x])
        lo = int(x - d) - 6
        strip = rr[y - r:y + r + 1, lo - r:lo + 13 + r]
        score = cv2.matchTemplate(strip, rl[y - r:y + r + 1, x - r:x + r + 1], cv2.TM_CCOEFF_NORMED)[0]
        k = int(np.argmax(score))
        assert 0 < k < score.size - 1 and score[k] > 0.8, (x, y, score.max())
        a, b, c = score[k - 1], score[k], score[k + 1]
        sub = k + 0.5 * (a - c) / (a - 2 * b + c)
        errors.append(x - (lo + sub) - d)
    errors = np.abs(np.array(errors))
    assert np.median(errors) < 0.1 and errors.max() < 0.2, errors.round(3)


# --- scenarios ---------------------------------------------------------------------------------------

def test_builtin_scenarios_listed():
    assert S.list_builtin_scenarios() == ["blank-faces", "border", "border-right", "chair", "low-faces", "occlusion",
                                          "people-border", "people-queue", "people-queue-far", "people-side",
                                          "people-side-far", "person-walking", "sway", "sway-pivot", "toolbox",
                                          "touching", "two-boxes"]
    with pytest.raises(ConfigError, match="no-such-scene.*built-in: blank-faces, border, border-right, chair"):
        S.Scene.builtin("no-such-scene")


def test_default_scene_numbers():
    sc = S.Scene.default()
    assert (sc.name, sc.camera_height_m, sc.camera_pitch_deg, sc.wall_distance_m) == ("two-boxes", 1.0, 15.0, 5.0)
    a, b = sc.boxes
    assert (a.name, a.center, a.size) == ("box-a", (1.8, 0.35, 0.3), (0.5, 0.6, 0.3))
    assert (b.name, b.center, b.size) == ("box-b", (2.4, -0.5, 0.4), (0.4, 0.8, 0.3))


# occlusion hides its person on purpose (tests/test_occlusion.py)
@pytest.mark.parametrize("name", ["two-boxes", "toolbox", "chair", "person-walking", "touching", "border",
                                  "border-right"])
def test_every_scenario_shows_every_obstacle(name, rig, rect):
    world = _world(name, rig, rect)
    times = [0.0] if world.is_static() else list(np.arange(0.0, 6.0, 0.5))
    w, h = rect.model.width, rect.model.height
    for t in times:
        left, right = world.render(t)
        assert left.shape == (h, w) and right.dtype == np.uint8
        for o in world.truth(t):
            assert o.visible_px > 500, (name, t, o.name, o.visible_px)
            assert np.all(np.isfinite(o.visible_centroid_m)) and o.nearest_m > 0.5


def test_compound_objects_are_one_obstacle(rig, rect):
    world = _world("chair", rig, rect)
    (chair,) = world.truth()
    assert chair.kind == "chair"
    assert np.allclose(chair.size_m, (0.44, 0.945, 0.42))  # union of seat, back and legs
    ids = world.obstacle_ids()
    assert chair.visible_px == int((ids == 0).sum())
    # thin legs: floor shows between them, inside the chair's bbox
    x0, y0, x1, y1 = chair.bbox_px
    assert (ids[y0:y1 + 1, x0:x1 + 1] == -1).mean() > 0.2


def test_touching_boxes_overlap_in_the_image(rig, rect):
    world = _world("touching", rig, rect)
    near, far = world.truth()
    (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = near.bbox_px, far.bbox_px
    assert ax0 < bx1 and bx0 < ax1 and ay0 < by1 and by0 < ay1  # the bboxes intersect
    assert far.center_m[2] - near.center_m[2] > 0.5
    ids = world.obstacle_ids()
    # the near box hides part of the far one: some rows go straight from one to the other
    touching = (ids[:, :-1] == 0) & (ids[:, 1:] == 1)
    assert touching.sum() > 20


def test_border_object_is_cut(rig, rect):
    world = _world("border", rig, rect)
    (o,) = world.truth()
    assert o.bbox_px[0] == 0
    u = rect.P1[0, 0] * o.center_m[0] / o.center_m[2] + rect.P1[0, 2]
    assert u < 0  # the centre itself is outside the image


# --- moving objects --------------------------------------------------------------------------------

def test_moving_truth(rig, rect):
    world = _world("person-walking", rig, rect)
    assert not world.is_static()
    (p0,) = world.truth(0.5)
    (p1,) = world.truth(0.6)
    assert p0.kind == "person" and np.isclose(p0.size_m[1], 1.75)
    assert np.isclose(np.linalg.norm(p0.velocity_mps), 0.8)
    # velocity (rectified frame) is the derivative of the centre
    assert np.allclose((p1.center_m - p0.center_m) / 0.1, p0.velocity_mps, atol=1e-6)
    assert not np.array_equal(world.render(0.5)[0], world.render(0.6)[0])
    assert p0.bbox_px != p1.bbox_px
    # back and forth: the path is closed, so the person comes back
    period = 2 * np.hypot(1.5, 1.3) / 0.8
    (pp,) = world.truth(0.5 + period)
    assert np.allclose(pp.center_m, p0.center_m, atol=1e-9)
    (back,) = world.truth(0.5 + period / 2)
    assert np.dot(back.velocity_mps, p0.velocity_mps) < 0


def test_moving_render_is_deterministic_and_prerender_matches(rig, rect):
    a = _world("person-walking", rig, rect)
    b = S.SyntheticWorld(S.Scene.builtin("person-walking"), rig, rect)
    b.prerender([0.4, 0.8])
    for t in (0.4, 0.8):
        assert all(np.array_equal(x, y) for x, y in zip(a.render(t), b.render(t)))
        ta, tb = a.truth(t), b.truth(t)
        assert ta[0].bbox_px == tb[0].bbox_px and np.allclose(ta[0].center_m, tb[0].center_m)


def test_box_path_stops_without_loop():
    box = S.Box("b", "box", (0, 0, 0.2), (0.4, 0.4, 0.4), path=[(1.0, 0.0), (2.0, 0.0)], speed_mps=0.5, loop=False)
    c, _, v = box.pose(1.0)
    assert np.allclose(c, (1.5, 0.0, 0.2)) and np.allclose(v, (0.5, 0, 0))
    c, _, v = box.pose(10.0)
    assert np.allclose(c, (2.0, 0.0, 0.2)) and np.allclose(v, 0)


# --- a moving, swaying camera ------------------------------------------------------------------------

def _mount_angles(R_base_cam: np.ndarray) -> tuple[float, float, float]:
    """(pitch, roll, yaw) deg of optical axes given in the base frame, from the axes themselves: the
    optical axis z points forward-down by the pitch, the image's x axis (right) dips by the roll."""
    fwd, right = R_base_cam[:, 2], R_base_cam[:, 0]
    pitch = math.degrees(math.asin(-fwd[2]))
    yaw = math.degrees(math.atan2(fwd[1], fwd[0]))
    # the roll tilts the image's x axis out of the horizontal plane: down on the right is positive
    roll = math.degrees(math.asin(-right[2] / math.cos(math.radians(pitch))))
    return pitch, roll, yaw


def test_swaying_camera_pose_follows_the_scenario(rig, rect):
    """The sway scenario's camera: pitch and roll are the mount's plus the declared sinusoids, the
    heading stays the robot's, the height bobs, and the robot drives its arc over the floor."""
    world = _world("sway", rig, rect)
    sc = world.scene
    m = sc.camera_motion
    assert not world.is_static() and sc.camera_moves()
    R1 = np.asarray(rect.R1, float)
    for t in (0.0, 0.37, 1.1, 2.5):
        T = world.T_base_rect(t)
        R_left = T[:3, :3] @ R1  # the (unrectified) left camera's axes, whose pitch and roll the scene sets
        pitch, roll, yaw = _mount_angles(R_left)
        def wave(ws, t=t):
            return sum(w.amplitude * math.sin(2 * math.pi * w.frequency_hz * t + math.radians(w.phase_deg)) for w in ws)
        dp, dr, dh = wave(m.pitch_deg), wave(m.roll_deg), wave(m.height_m)
        assert pitch == pytest.approx(sc.camera_pitch_deg + dp, abs=1e-6)
        assert roll == pytest.approx(dr, abs=1e-6)
        assert yaw == pytest.approx(0.0, abs=1e-6)
        assert np.allclose(T[:3, 3], (0.0, 0.0, sc.camera_height_m + dh))
        # the base frame drives along an arc: speed 0.25 m/s, turning 3 deg/s
        Tw = world.T_world_base(t)
        heading = math.radians(3.0 * t)
        assert math.atan2(Tw[1, 0], Tw[0, 0]) == pytest.approx(heading, abs=1e-9)
        r = 0.25 / math.radians(3.0)
        assert np.allclose(Tw[:2, 3], (r * math.sin(heading), r * (1 - math.cos(heading))), atol=1e-9)
    lin, ang = world.odometry(1.0)
    assert np.allclose(lin, (0.25, 0, 0)) and np.allclose(ang, (0, 0, math.radians(3.0)))
    # the sway really is +-10 deg at 0.5-2 Hz
    assert sum(w.amplitude for w in m.pitch_deg) == 10.0 and sum(w.amplitude for w in m.roll_deg) == 10.0
    assert all(0.5 <= w.frequency_hz <= 2.0 for w in m.pitch_deg + m.roll_deg)


def test_swaying_camera_renders_the_floor_and_objects_where_the_truth_says(rig, rect):
    """The renderer and the pose chain agree: every floor pixel of the rectified view, taken to the
    world by the camera's pose at that instant, lies on the floor (z = 0); what stands still keeps
    its world position and its base-frame truth is the world's seen from the robot."""
    world = _world("sway", rig, rect)
    m = rect.model
    ids0 = None
    for t in (0.2, 1.4):
        depth = world.true_depth(t)
        ids = world.obstacle_ids(t)
        h, w = depth.shape
        u, v = np.meshgrid((np.arange(w) - m.cx) / m.focal_px, (np.arange(h) - m.cy) / m.focal_px)
        pts = np.stack([u, v, np.ones_like(u)], -1) * depth[..., None]
        T = world.T_world_rect_at(t)
        pw = pts @ T[:3, :3].T + T[:3, 3]
        floor = (ids == -1) & np.isfinite(depth) & (pw[..., 0] < world.scene.wall_distance_m - 0.01)
        assert floor.sum() > 20000
        assert np.abs(pw[..., 2][floor]).max() < 1e-3
        Tb = np.linalg.inv(world.T_world_base(t))
        for o, b in zip(world.truth(t), world.scene.boxes):
            origin, yaw, _ = b.pose(t)
            center_w = origin + S.scene.rot_z(yaw) @ b.local_center()
            assert np.allclose(T[:3, :3] @ o.center_m + T[:3, 3], center_w, atol=1e-9)
            assert np.allclose(o.center_base_m, Tb[:3, :3] @ center_w + Tb[:3, 3], atol=1e-9)
            assert o.static == b.is_static()
        if ids0 is not None:
            assert (ids0 != ids).mean() > 0.05  # the view moved
        ids0 = ids


def test_a_lean_about_a_pivot_carries_the_camera_over_the_floor():
    """With pivot_height_m the sway is a lean of the robot about a point under the camera (a
    ballbot's ball): leaning forward by a degree moves the camera forward by (h - pivot) sin(a)
    and down by (h - pivot) (1 - cos(a)); without a pivot the camera turns on the spot."""
    lean = S.CameraMotion(pitch_deg=(S.Wave(5.0, 0.5, 90.0),), pivot_height_m=0.2)
    R, o = lean.camera_in_base(0.0, 1.0, 10.0)  # sin(90 deg) = 1: leaning 5 deg forward
    a = math.radians(5.0)
    assert np.allclose(o, (0.8 * math.sin(a), 0.0, 0.2 + 0.8 * math.cos(a)))
    assert _mount_angles(R)[0] == pytest.approx(15.0)
    R2, o2 = S.CameraMotion(pitch_deg=(S.Wave(5.0, 0.5, 90.0),)).camera_in_base(0.0, 1.0, 10.0)
    assert np.allclose(o2, (0, 0, 1.0)) and np.allclose(R, R2)


# --- scenario files ----------------------------------------------------------------------------------

_GOOD = """
name: mine
camera_height_m: 0.8
camera_pitch_deg: 10
objects:
  - name: crate
    kind: box
    size: [0.3, 0.3, 0.3]
    position: [2.0, 0.0, 0.5]
"""


def test_yaml_round_trip(tmp_path):
    f = tmp_path / "mine.yaml"
    f.write_text(_GOOD)
    sc = S.Scene.from_yaml(f)
    assert (sc.name, sc.camera_height_m, sc.camera_pitch_deg, sc.wall_distance_m) == ("mine", 0.8, 10.0, 5.0)
    assert sc.boxes[0].center == (2.0, 0.0, 0.5)  # [x, y, z] is the centre, not on the floor
    assert S.Scene.builtin(str(f)).boxes[0].name == "crate"  # a file path works where a name does


@pytest.mark.parametrize("edit,message", [
    (("    size: [0.3, 0.3, 0.3]\n", ""), r"objects\[0\] \('crate'\): missing field 'size'"),
    (("  - name: crate\n", "  - kind: box\n"), r"objects\[0\]: missing field 'name'"),
    (("    position: [2.0, 0.0, 0.5]\n", ""), r"objects\[0\] \('crate'\): missing field 'position'"),
    (("camera_height_m: 0.8", "camera_height_m: high"), r": field 'camera_height_m': .*valid number \(got 'high'\)"),
    (("camera_height_m: 0.8", "camera_height_m: '0.8'"), r"field 'camera_height_m': .*valid number \(got '0.8'\)"),
    (("camera_height_m: 0.8", "camera_height_m: true"), r"field 'camera_height_m': .*valid number \(got True\)"),
    (("camera_pitch_deg: 10", "camera_pitch_deg: 75"), r"field 'camera_pitch_deg': .*less than or equal to 60"),
    (("size: [0.3, 0.3, 0.3]", "size: [0.3, 0.3]"), r"\('crate'\): field 'size': .*at least 3 items"),
    (("size: [0.3, 0.3, 0.3]", "size: [0.3, -0.3, 0.3]"), r"field 'size' item 1: .*greater than 0"),
    (("size: [0.3, 0.3, 0.3]", "size: [0.3, .nan, 0.3]"), r"field 'size' item 1: .*finite number"),
    (("    kind: box\n", "    kind: box\n    colour: red\n"), r"\('crate'\): unknown field 'colour'"),
    (("    position: [2.0, 0.0, 0.5]\n", "    position: [2.0, 0.0]\n    path: {waypoints: [[1, 0]], speed_mps: 1}\n"),
     r"path: field 'waypoints': .*at least 2 items"),
    (("    position: [2.0, 0.0, 0.5]\n", "    position: [2.0, 0.0]\n    path: {waypoints: [[1, 0], [2, 0]]}\n"),
     r"path: missing field 'speed_mps'"),
    (("    size: [0.3, 0.3, 0.3]\n", "    size: [0.3, 0.3, 0.3]\n    parts: [{offset: [0, 0, 0], size: [1, 1, 1]}]\n"),
     r"either 'size' or 'parts'"),
    (("    size: [0.3, 0.3, 0.3]\n", "    parts: [{offset: [0, 0], size: [1, 1, 1]}]\n"),
     r"objects\[0\] \('crate'\): parts\[0\]: field 'offset': .*at least 3 items"),
    (("name: mine\n", "name: mine\nwall_distance_m: 1.5\n"), r"'crate' stands behind the wall"),
    (("name: mine\n", "name: mine\ncamera_motion: {pitch_deg: [{amplitude: 60, frequency_hz: 1}]}\n"),
     r"camera_motion: camera_pitch_deg 10 and the pitch_deg amplitudes reach 70 deg \(at most 60\)"),
    (("name: mine\n", "name: mine\ncamera_motion: {roll_deg: [{amplitude: 5, frequency_hz: 0}]}\n"),
     r"camera_motion: roll_deg\[0\]: field 'frequency_hz': .*greater than 0"),
    (("name: mine\n", "name: mine\ncamera_motion: {height_m: [{amplitude: 0.8, frequency_hz: 1}]}\n"),
     r"take the camera down to 0 m"),
    (("name: mine\n", "name: mine\ncamera_motion: {pivot_height_m: 0.9}\n"), r"pivot_height_m 0.9 must be below"),
    (("name: mine\n", "name: mine\ncamera_motion: {sway: 3}\n"), r"camera_motion: unknown field 'sway'"),
    (("name: mine\n", "name: mine\ncamera_motion: {start: [0, 0]}\n"), r"camera_motion: field 'start': .*at least 3"),
    (("name: mine\n", "name: mine\nrange_m: 0.1\n"), r"field 'range_m': .*greater than or equal to 0.5"),
])
def test_yaml_errors_name_file_and_field(tmp_path, edit, message):
    f = tmp_path / "bad.yaml"
    assert edit[0] in _GOOD
    f.write_text(_GOOD.replace(*edit))
    with pytest.raises(ConfigError, match=message) as e:
        S.Scene.from_yaml(f)
    assert str(f) in str(e.value)


def test_yaml_not_a_mapping_or_not_yaml(tmp_path):
    f = tmp_path / "x.yaml"
    f.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        S.Scene.from_yaml(f)
    f.write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        S.Scene.from_yaml(f)
    with pytest.raises(ConfigError, match="missing.yaml: no such file"):
        S.Scene.from_yaml(tmp_path / "missing.yaml")
    f.write_bytes(bytes(range(256)))
    with pytest.raises(ConfigError, match="binary data"):
        S.Scene.from_yaml(f)
