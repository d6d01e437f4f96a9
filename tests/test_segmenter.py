"""Segmenter cores on analytic disparity maps (floor plane + fronto-parallel boxes), the camera
mount, settings, bad input, and the offline `obstacles` command on rendered images."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest

from common import codec
from common.errors import DecodeError
from common.messages import CameraModel, DisparityMap, GroundEstimate, Image
from common.settings import MountSettings
from cores import camera
from cores.segmentation import depth_split, layers, regions, seed
from cores.segmentation.builder import ObstacleBuilder
from cores.segmentation.mount import FloorPlane, Mount
from cores.segmentation.settings import SegmenterSettings

MODEL = camera.RectifiedModel(640, 480, 665.0, 320.0, 240.0, 0.1)
FB = MODEL.focal_px * MODEL.baseline_m


def floor_plane(mount: Mount) -> FloorPlane:
    return FloorPlane.from_normal(mount.down_camera, mount.height_m, MODEL.focal_px, MODEL.cx, MODEL.cy,
                                  MODEL.baseline_m)


SCENE_MOUNT = Mount(1.0, 15.0)  # the synthetic scene's camera


def scene(boxes=(), mount: Mount = SCENE_MOUNT, wall_m: float = 5.0, noise: float = 0.08,
          holes: float = 0.03, seed_: int = 0, band: bool = True) -> np.ndarray:
    """Disparity (H, W) float32 of a floor seen from `mount`, a wall at wall_m, and boxes standing on
    the floor: (u0, u1, z_m, height_px) columns u0..u1 at depth z, bottom where the floor is at z.
    band: block matching's blind left band left unmeasured."""
    rng = np.random.default_rng(seed_)
    v, u = np.mgrid[0:MODEL.height, 0:MODEL.width].astype(np.float32)
    fp = floor_plane(mount)
    d = np.maximum(fp.disparity(u, v), FB / wall_m).astype(np.float32)
    for u0, u1, z, h_px in boxes:
        dz = FB / z
        # bottom row: where the floor's disparity equals the box's (solve along the middle column)
        col = int((u0 + u1) / 2)
        rows = np.nonzero(fp.disparity(np.float32(col), np.arange(MODEL.height, dtype=np.float32)) <= dz)[0]
        bottom = int(rows.max()) if rows.size else MODEL.height
        d[max(0, bottom - h_px):bottom, max(0, u0):min(MODEL.width, u1)] = dz
    d += rng.normal(0, noise, d.shape).astype(np.float32)
    d[rng.random(d.shape) < holes] = np.nan
    if band:
        d[:, :70] = np.nan  # block matching has no match in the left num_disparities columns
    return d


def _mounted(m: Mount) -> MountSettings:
    return MountSettings(height_m=m.height_m, pitch_deg=m.pitch_deg, yaw_deg=m.yaw_deg, roll_deg=m.roll_deg,
                         x_m=m.x_m, y_m=m.y_m)


def _depths(dets):
    return sorted(round(float(x.position_m[2]), 1) for x in dets)


# --- layers ----------------------------------------------------------------------------------

def test_layers_separates_objects_touching_in_the_image_at_different_depths():
    d = scene([(200, 330, 1.8, 150), (330, 470, 2.5, 200)])  # share the column 330
    dets = layers.segment(d, MODEL, SegmenterSettings())
    assert _depths(dets) == [1.8, 2.5]
    near = min(dets, key=lambda x: x.position_m[2])
    assert abs(near.position_m[2] - 1.8) < 0.03
    assert near.bbox_px[0] <= 202 and near.bbox_px[2] >= 328
    assert 0.9 < near.confidence <= 1.0
    # the thesis's single threshold merges them (or loses one)
    assert len(seed.segment(d, MODEL, SegmenterSettings(method="seed"))) < 2


def test_layers_separates_things_one_behind_the_other_less_than_a_disparity_pixel_apart():
    """Two boxes 0.6 m apart in depth 6.5 m away, the far one half hidden: under a pixel of
    disparity apart, so the column-disparity grid joins them; the depth-layer split parts them."""
    d = scene([(300, 380, 6.5, 120), (360, 430, 7.1, 130)], wall_m=12.0, holes=0.0)
    cfg = SegmenterSettings(max_range_m=10.0)
    assert _depths(layers.segment(d, MODEL, cfg)) == [6.5, 7.1]
    assert len(layers.segment(d, MODEL, cfg.model_copy(update={"layer_valley_ratio": 0.0}))) == 1


def _grouped(*parts):
    """Grouped pixels as _group gives them, one group: parts of (rows, cols, disparity per pixel)."""
    ys, xs, dv = [], [], []
    for rows, cols, disp in parts:
        yy, xx = np.meshgrid(np.asarray(rows), np.asarray(cols), indexing="ij")
        ys.append(yy.ravel())
        xs.append(xx.ravel())
        dv.append(np.broadcast_to(np.asarray(disp, np.float32), yy.shape).ravel())
    ys, xs, dv = (np.concatenate(a) for a in (ys, xs, dv))
    return ys, xs, dv, np.ones(ys.size, np.int32)


def _layers_of(ys, xs, dv, lab):
    out = depth_split.split_layers(ys, xs, dv, lab, SegmenterSettings(max_range_m=10.0), MODEL, 2)[0]
    return {int(k): (float(np.median(dv[out == k])), int((out == k).sum())) for k in np.unique(out) if k > 0}


def test_the_depth_layer_split_parts_a_person_behind_another_and_keeps_a_table_and_a_torso_whole():
    rows = np.arange(50, 200)
    # a person (d 12 px, 5.5 m) with one 0.5 m behind (d 11 px) beside them, and the ramp block
    # matching draws across the occlusion between them: three columns of in-between disparities
    ramp = [(rows, [139], 11.75), (rows, [140], 11.5), (rows, [141], 11.25)]
    queue = _layers_of(*_grouped((rows, np.arange(100, 139), 12.0), *ramp, (rows, np.arange(142, 165), 11.0)))
    assert sorted(round(v[0]) for v in queue.values()) == [11, 12]
    assert sum(v[1] for v in queue.values()) == rows.size * (39 + 23)  # the ramp's pixels are dropped
    # a table 2 m away: front legs and apron (d 33), back legs (d 25), and the top between them,
    # row by row from the back edge to the front across the table's whole width
    top = [([80 + k], np.arange(100, 200), 25.0 + k) for k in range(9)]
    table = _layers_of(*_grouped((np.arange(90, 200), np.r_[100:106, 194:200], 33.0), (np.arange(92, 106),
                                 np.arange(100, 200), 33.0), (np.arange(90, 150), np.r_[110:114, 186:190], 25.0),
                                 *top))
    assert len(table) == 1
    # a person's torso 6 cm before their legs (d 34 and 33): one person
    assert len(_layers_of(*_grouped((np.arange(50, 120), np.arange(100, 140), 34.0),
                                    (np.arange(120, 200), np.arange(104, 136), 33.0)))) == 1


def test_a_few_wide_rows_of_the_valley_do_not_keep_two_things_one_behind_the_other_whole():
    """A person (d 12) and a person 0.5 m behind (d 11) joined by the ramp along the near one's side
    (3 px a row, 150 rows) and, in 30 rows, by a surface reaching back between them (a table's
    rail, 80 px a row). The ramp is what most of the valley's rows hold: two things.
    A valley wide in most of its rows (a table's top between its legs) still keeps one whole."""
    rows = np.arange(50, 200)
    ramp = [(rows, [139], 11.75), (rows, [140], 11.5), (rows, [141], 11.25)]
    rail = [(np.arange(150, 180), [142 + k], 11.9 - 0.01 * k) for k in range(80)]  # receding: depth along it
    two = _layers_of(*_grouped((rows, np.arange(100, 139), 12.0), *ramp, *rail, (rows, np.arange(222, 262), 11.0)))
    assert sorted(round(v[0]) for v in two.values()) == [11, 12]


def test_the_depth_layer_split_keeps_a_surface_resting_on_the_far_side_s_top_whole():
    """A table's front (d 12) and its back leg (d 11) joined through a thin valley of in-between
    depths: split when the valley runs down beside the leg at its heights (the ramp of an
    occlusion), kept whole when the valley lies right on top of the leg, in its columns and less
    than 0.25 m above it (the table's side rail seen end-on, resting on the leg)."""
    cfg = SegmenterSettings(max_range_m=10.0)
    near = (np.arange(50, 200), np.arange(100, 139), 12.0)
    leg = (np.arange(120, 200), np.arange(142, 165), 11.0)

    def parts(valley, height_of):
        ys, xs, dv, lab = _grouped(near, *valley, leg)
        heights = None if height_of is None else height_of(ys, xs)
        out = depth_split.split_layers(ys, xs, dv, lab, cfg, MODEL, 2, heights)[0]
        return np.unique(out[out > 0]).size

    floor_up = lambda ys, xs: (200 - ys) * 0.01  # noqa: E731 - the leg's top (row 120) is 0.8 m high
    beside = [(np.arange(120, 200), [139], 11.75), (np.arange(120, 200), [140], 11.5),
              (np.arange(120, 200), [141], 11.25)]
    assert parts(beside, None) == 2 and parts(beside, floor_up) == 2
    rail = [(np.arange(104, 120), np.arange(142, 146), 11.75), (np.arange(104, 120), np.arange(146, 150), 11.5),
            (np.arange(104, 120), np.arange(150, 154), 11.25)]
    assert parts(rail, None) == 2 and parts(rail, floor_up) == 1


def test_the_depth_layer_split_keeps_a_table_s_legs_below_its_top_with_a_person_behind():
    """A table 1.85 m away (top and apron d 36) with its back legs (d 35) below the top, and a person
    0.9 m behind it (d 24) in the same group, joined by the ramp down the top's side. The legs'
    depths lie in the valley between the two, in rows of their own below the top: beyond a ramp's
    reach of it (layer_bridge_px, 12 working rows) they are the table's (the sway: dropped as the
    ramp, the table's box ended at its top). The ramp beside the top is still dropped."""
    top = (np.arange(50, 66), np.arange(150, 250), 36.0)
    legs = (np.arange(66, 101), np.r_[152:157, 240:245], 35.0)
    person = (np.arange(20, 101), np.arange(262, 301), 24.0)
    ramp = [(np.arange(50, 66), [250 + k], 34.0 - 3.0 * k) for k in range(3)]
    ys, xs, dv, lab = _grouped(top, legs, *ramp, person)
    out = depth_split.split_layers(ys, xs, dv, lab, SegmenterSettings(max_range_m=10.0), MODEL, 2)[0]
    table, behind = out[(dv == 36.0)], out[dv == 24.0]
    assert np.unique(table).size == 1 and np.unique(behind).size == 1 and table[0] != behind[0] > 0
    assert np.all(out[(dv == 35.0) & (ys > 65 + 12)] == table[0])  # the legs: the table's,
    assert ys[out == table[0]].max() == 100  # down to their feet
    assert np.all(out[(dv < 35.0) & (dv > 24.0)] == 0)  # the ramp: dropped


def test_the_disparity_along_the_ground_is_one_depth_for_an_upright_face_at_any_pitch():
    """ground_disparity: with the camera level it is the disparity; pitched 20 deg down, an upright
    face D m ahead (its disparity grows down the image, as its points come nearer along the optical
    axis) is fB / D in every row."""
    ys, xs = np.meshgrid(np.arange(0, 240), np.arange(0, 320), indexing="ij")
    ys, xs = ys.ravel(), xs.ravel()
    level = Mount(1.0, 0.0, 0.0, 0.0)
    dv = np.full(ys.size, 20.0, np.float32)
    np.testing.assert_allclose(depth_split.ground_disparity(ys, xs, dv, level.down_camera, MODEL, 2), dv, rtol=1e-6)
    pitched = Mount(1.2, 20.0, 0.0, 0.0)
    n = pitched.down_camera
    fwd = np.array([0.0, 0.0, 1.0]) - n[2] * n
    fwd /= np.linalg.norm(fwd)
    ray = np.stack([(xs * 2 - MODEL.cx) / MODEL.focal_px, (ys * 2 - MODEL.cy) / MODEL.focal_px, np.ones(ys.size)], 1)
    z = 4.0 / (ray @ fwd)  # the optical-axis depth of an upright face 4 m ahead along the ground
    along = depth_split.ground_disparity(ys, xs, (FB / z).astype(np.float32), n, MODEL, 2)
    assert np.ptp(FB / z) > 1.5  # 20 deg down: over 1.5 px of disparity from its top row to its bottom
    np.testing.assert_allclose(along, FB / 4.0, rtol=1e-4)


def test_flanked_tells_an_occlusion_ramp_from_a_rail_reaching_back():
    """A ramp runs between the two sides in its rows: each of its pixels has both within reach in its
    own row. A rail reaching back from the near side to the far one, seen end-on, runs down the image
    beside neither."""
    near = _grouped((np.arange(50, 200), np.arange(100, 139), 12.0))
    far = _grouped((np.arange(50, 200), np.arange(142, 165), 11.0))
    ramp = _grouped((np.arange(50, 200), [139, 140, 141], 11.5))
    rail = _grouped(*[([120 + k], [150 + k], 11.5) for k in range(60)])
    for valley, want in ((ramp, 1.0), (rail, 0.0)):
        ys = np.concatenate([near[0], far[0], valley[0]])
        xs = np.concatenate([near[1], far[1], valley[1]])
        i_near = np.arange(near[0].size)
        i_far = near[0].size + np.arange(far[0].size)
        band = near[0].size + far[0].size + np.arange(valley[0].size)
        got = depth_split.flanked(ys, xs, band, i_near, i_far, 12.0)
        assert abs(got - want) < 0.05, (got, want)


def test_a_valley_the_optical_axis_hides_is_found_along_the_ground_if_it_is_a_ramp():
    """Two upright people 4.3 and 4.9 m away along the ground seen from a camera pitched 20 deg down:
    along the optical axis each person spans a range of disparity (their feet nearer than their
    heads), so the two ranges meet and no valley splits them; along the ground (split_layers given the floor's normal)
    each is one depth and the ramp between them is a valley. A rail reaching back from one to the
    other, in rows where neither is seen, instead of a ramp keeps them one (a table's legs and the
    side rail between them, seen end-on)."""
    cfg = SegmenterSettings(max_range_m=10.0)
    n = Mount(1.2, 20.0, 0.0, 0.0).down_camera
    fwd = np.array([0.0, 0.0, 1.0]) - n[2] * n
    fwd /= np.linalg.norm(fwd)

    def upright(rows, cols, dist):
        yy, xx = np.meshgrid(np.asarray(rows), np.asarray(cols), indexing="ij")
        ray = np.stack([(xx * 2 - MODEL.cx) / MODEL.focal_px, (yy * 2 - MODEL.cy) / MODEL.focal_px,
                        np.ones(yy.shape)], -1)
        return rows, cols, (FB * (ray @ fwd) / dist).astype(np.float32)

    rows = np.arange(10, 150)
    front, back = upright(rows, np.arange(100, 139), 4.3), upright(rows, np.arange(142, 165), 4.9)
    ramp = [upright(rows, [139 + k], 4.3 + 0.15 * (k + 1)) for k in range(3)]
    rail = [upright([152 + k // 2], [110 + k], 4.3 + 0.01 * k) for k in range(60)]  # below both, receding
    for valley, parts in ((ramp, 2), (rail, 1)):
        ys, xs, dv, lab = _grouped(front, *valley, back)
        axis = depth_split.split_layers(ys, xs, dv, lab, cfg, MODEL, 2)[0]
        assert np.unique(axis[axis > 0]).size == 1
        out = depth_split.split_layers(ys, xs, dv, lab, cfg, MODEL, 2, normal=n)[0]
        assert np.unique(out[out > 0]).size == parts


def test_depth_layers_of_one_group_are_not_joined_again_but_a_fence_s_stretches_are():
    """Regions whose extents come within merge_gap_depth_m along the view join (the stretches of a
    fence the matcher left out), unless the depth-layer split made them two (one behind the other)."""
    def region(z0, z1, groups=frozenset(), cols=(0, 10)):
        x, y, z = np.meshgrid(np.linspace(-1.0, -0.8, 5), np.linspace(-0.5, 0.5, 11), np.linspace(z0, z1, 11))
        pts = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
        return regions.Region(pts, pts.min(0), pts.max(0), (cols[0], 0, cols[1], 10), 100, 100,
                              np.full(len(pts), FB / z0), 0, groups)

    # a fence's stretches recede side by side in the image
    fence = regions.merge_close([region(5.0, 5.5, cols=(0, 10)), region(5.7, 6.2, cols=(10, 16))], 0.12, 0.25)
    assert len(fence) == 1
    people = regions.merge_close([region(5.0, 5.5, frozenset({7})), region(5.7, 6.2, frozenset({7}))], 0.12, 0.25)
    assert len(people) == 2
    touching = regions.merge_close([region(5.0, 5.5, frozenset({7})), region(5.55, 6.2, frozenset({7}))], 0.12, 0.25)
    assert len(touching) == 1


def _box_points(x0, x1, y0, y1, z0, z1, n=6):
    x, y, z = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n), np.linspace(z0, z1, n))
    return np.stack([x.ravel(), y.ravel(), z.ravel()], 1)


def test_a_person_walking_behind_a_table_is_not_joined_to_it_by_their_boxes():
    """A table (its top, and a back leg at its left) and a person 0.1 m behind its back leg, to the
    right of it: their boxes come within merge_gap_m, in the same image columns, but nothing of
    them does (the top ends 0.35 m before the person, the leg 0.2 m to their left). The occluder
    and what it hides are two; the same boxes side by side in the image (a fence's stretches)
    are one."""
    def region(pts, cols):
        return regions.Region(pts, pts.min(0), pts.max(0), (cols[0], 0, cols[1], 10), 100, 100,
                              FB / pts[:, 2], 0, frozenset())

    table = np.concatenate([_box_points(0.5, 0.92, 0.0, 0.02, 1.9, 2.3), _box_points(0.5, 0.53, 0.0, 0.7, 2.5, 2.56)])
    person = _box_points(0.75, 1.06, -0.96, 0.7, 2.65, 2.9)
    assert len(regions.merge_close([region(table, (220, 320)), region(person, (240, 300))], 0.12, 0.25)) == 2
    assert len(regions.merge_close([region(table, (220, 320)), region(person, (320, 380))], 0.12, 0.25)) == 1


def test_things_joined_only_by_something_low_are_cut_apart_and_stay_apart():
    """On the column-disparity grid, two tall things (cores) joined by a band of low cells (a kerb
    or a snow bank along the street) are cut between them, each low cell to its nearest core; one
    tall thing with a low thing beside it, or low things alone, are not cut; the pieces of a cut
    are not joined again by merge_close although they touch."""
    from cores.segmentation.cells import group_cells

    cells = np.zeros((20, 60), np.uint8)
    cells[10, 5:55] = 1  # the kerb
    tall = np.zeros_like(cells)
    tall[8:11, 5:15] = tall[8:11, 40:50] = 1  # a car and a hedge on it
    cells |= tall
    labels, cut_from = group_cells(cells, tall)
    car, hedge, kerb_near_car, kerb_near_hedge = labels[9, 10], labels[9, 45], labels[10, 20], labels[10, 36]
    assert car != hedge and kerb_near_car == car and kerb_near_hedge == hedge
    assert cut_from[int(car)] == cut_from[int(hedge)]
    one_core = tall.copy()
    one_core[8:11, 40:50] = 0
    labels, cut_from = group_cells(cells, one_core)
    assert len(np.unique(labels[cells > 0])) == 1 and not cut_from
    labels, cut_from = group_cells(cells, None)  # no heights (no ground): touching cells are one
    assert len(np.unique(labels[cells > 0])) == 1 and not cut_from

    def region(pts, cuts):
        return regions.Region(pts, pts.min(0), pts.max(0), (0, 0, 10, 10), 100, 100, FB / pts[:, 2], 0,
                              frozenset(), frozenset(cuts))

    a, b = _box_points(1.0, 2.0, 0.0, 1.0, 5.0, 6.0), _box_points(2.05, 3.0, 0.0, 1.0, 5.0, 6.0)
    assert len(regions.merge_close([region(a, {3}), region(b, {3})], 0.12, 0.25)) == 2
    assert len(regions.merge_close([region(a, {3}), region(b, {4})], 0.12, 0.25)) == 1


def test_a_leg_whose_top_is_hidden_a_little_below_the_table_top_is_dropped_at_the_image_edge():
    """A table reaching out of the image on the right, its back leg at that edge behind its top:
    the leg's own top is hidden 8 working rows below the top's lower edge (the top seen from 0.9 m
    up has depth), nothing of the table frames it on the right. The nearer table stands in the way:
    the leg is no obstacle of its own (sway frame 25)."""
    step = 2

    def region(pts):
        u = pts[:, 0] / pts[:, 2] * MODEL.focal_px + MODEL.cx
        v = pts[:, 1] / pts[:, 2] * MODEL.focal_px + MODEL.cy
        box = (int(u.min() / step), int(v.min() / step), int(u.max() / step) + 1, int(v.max() / step) + 1)
        area = (box[2] - box[0]) * (box[3] - box[1])
        return regions.Region(pts, np.percentile(pts, 2, 0), np.percentile(pts, 98, 0), box, area, area,
                              FB / pts[:, 2], 0)

    top = _box_points(0.5, 1.2, 0.1, 0.1, 2.5, 2.52, n=30)
    front_leg = _box_points(0.5, 0.53, 0.1, 0.9, 2.5, 2.52, n=30)
    table = region(np.concatenate([top, front_leg]))
    back_leg = region(_box_points(1.05, 1.1, 0.2, 0.9, 3.0, 3.03, n=20))
    assert table.bbox[2] >= MODEL.width // step - 1  # the table reaches the image's right edge
    assert not regions.encloses(table, back_leg, MODEL, step)
    assert back_leg.bbox[1] - 9 <= int(0.1 / 2.5 * MODEL.focal_px / step + MODEL.cy / step) <= back_leg.bbox[1] - 7
    kept = regions.absorb_contained([table, back_leg], 0.12, MODEL, step)
    assert len(kept) == 1 and kept[0] is table


def test_layers_keeps_an_object_cut_by_the_image_border():
    d = scene([(560, 700, 2.0, 200)])
    dets = layers.segment(d, MODEL, SegmenterSettings())
    assert _depths(dets) == [2.0]
    assert dets[0].bbox_px[2] == MODEL.width
    assert seed.segment(d, MODEL, SegmenterSettings(method="seed")) == []  # the thesis clears the border


def test_a_near_object_left_of_where_its_partner_leaves_the_right_image_is_flagged_cut():
    """A matcher without a fixed blind band (dense pads the pair) measures the far wall up to the
    image's left side, but left of x = d nothing at disparity d has a partner in the right image: a
    crate 1.5 m away (44 px) from x = 0 is measured from about x = 44 on. Its left side is cut there,
    though the map's first measured column is 0 (low-faces, dense: unflagged). A box 3 m away whose
    left side is in view is not cut."""
    d = scene([(0, 200, 1.5, 200), (300, 420, 3.0, 150)], band=False)
    near = d[:, :int(FB / 1.5)]
    near[near > FB / 1.6] = np.nan  # the crate's pixels without a partner
    dets = sorted(layers.segment(d, MODEL, SegmenterSettings()), key=lambda o: o.distance_m)
    assert _depths(dets) == [1.5, 3.0], [(o.distance_m, o.bbox_px) for o in dets]
    assert dets[0].cut[0] and dets[0].bbox_px[0] <= int(FB / 1.5) + 4, dets[0]
    assert not any(dets[1].cut), dets[1]


def test_an_object_whose_first_columns_after_x_d_are_lost_is_still_flagged_cut():
    """dense lists a person cut by the image's left side as pieces; the lower one began at x 54, 4.6 px
    right of x = d (49.4 px: its first columns had too little confidence), past a rule of two working
    columns, and was not flagged cut (people-border). The median filter eats its reach into an edge
    beside no data, and the working grid rounds by a column: that far right of x = d is still cut."""
    d = scene([(0, 200, 1.5, 200), (300, 420, 3.0, 150)], band=False)
    x_d = int(FB / 1.5)
    near = d[:, :x_d + 5]
    near[near > FB / 1.6] = np.nan  # no partner, then 5 columns not measured
    dets = sorted(layers.segment(d, MODEL, SegmenterSettings()), key=lambda o: o.distance_m)
    assert _depths(dets) == [1.5, 3.0], [(o.distance_m, o.bbox_px) for o in dets]
    assert dets[0].bbox_px[0] > x_d + 4, dets[0]  # past the old rule's reach
    assert dets[0].cut[0], dets[0]
    assert not any(dets[1].cut), dets[1]


def test_seed_says_when_what_stands_in_range_is_not_in_its_list():
    """The thesis drops what touches the image border, what is under its area opening and what lies
    beyond its Otsu threshold: such a list names standing-not-listed, never a list that reads "nothing
    else there"."""
    def listed(boxes):
        lst = ObstacleBuilder(SegmenterSettings(method="seed")).process(scene(boxes), MODEL, t_s=0, seq=0,
                                                                         stamp_ns=0).obstacles
        return _depths(lst.obstacles), lst.degraded

    assert listed([(250, 390, 2.0, 150)]) == ([2.0], [])
    assert listed([(560, 700, 2.0, 200)]) == ([], ["standing-not-listed"])  # cut by the border, cleared
    assert listed([(560, 700, 2.0, 200), (250, 390, 2.0, 150)]) == ([2.0], ["standing-not-listed"])
    # a small box behind a near one (under 3 % of the image, and on the far side of Otsu's threshold) is
    # dropped; as large and it is kept
    assert listed([(150, 300, 2.0, 100), (400, 520, 2.9, 80)]) == ([2.0], ["standing-not-listed"])
    assert listed([(200, 300, 2.0, 150), (400, 560, 2.9, 150)]) == ([2.0, 2.9], [])


@pytest.mark.parametrize("prior", [Mount(1.0, 15.0), Mount(1.12, 12.0, roll_deg=2.0), None],
                         ids=["exact-mount", "wrong-mount", "no-mount"])
def test_layers_removes_the_floor_with_or_without_a_good_mount(prior):
    d = scene([(250, 390, 2.2, 180)])
    fl = []
    dets = layers.segment(d, MODEL, SegmenterSettings(), floor_out=fl, mount=prior)
    assert _depths(dets) == [2.2]
    assert fl[0] is not None and abs(fl[0].height_m - 1.0) < 0.05
    n, h = fl[0].normal_height(MODEL.focal_px, MODEL.cx, MODEL.cy, MODEL.baseline_m)
    assert np.degrees(np.arccos(n @ Mount(1.0, 15.0).down_camera)) < 1.0


def test_layers_fits_a_tilted_floor_when_the_robot_rolls():
    true = Mount(1.0, 15.0, roll_deg=4.0)
    d = scene([(250, 390, 2.2, 180)], mount=true)
    fl = []
    dets = layers.segment(d, MODEL, SegmenterSettings(), floor_out=fl)
    assert _depths(dets) == [2.2]
    n, _ = fl[0].normal_height(MODEL.focal_px, MODEL.cx, MODEL.cy, MODEL.baseline_m)
    assert np.degrees(np.arccos(n @ true.down_camera)) < 0.5


def test_floor_only_and_far_things_give_nothing():
    assert layers.segment(scene([]), MODEL, SegmenterSettings()) == []
    assert layers.segment(scene([(250, 390, 4.8, 100)]), MODEL, SegmenterSettings()) == []  # beyond 4.5 m


def test_minimum_size_is_in_metres():
    # 12 px at 1.2 m is 2 cm wide: dropped; 40 px at 4 m is 24 cm: kept
    d = scene([(300, 312, 1.2, 12), (400, 440, 4.0, 60)])
    dets = layers.segment(d, MODEL, SegmenterSettings())
    assert _depths(dets) == [4.0]
    assert 0.15 < dets[0].size_m[0] < 0.35


def test_bad_input_gives_no_obstacles_and_a_size_mismatch_raises():
    cfg = SegmenterSettings()
    h, w = MODEL.height, MODEL.width
    for d in (np.full((h, w), np.nan, np.float32), np.zeros((h, w), np.float32),
              np.full((h, w), np.inf, np.float32), -np.ones((h, w), np.float32)):
        assert layers.segment(d, MODEL, cfg) == []
        assert seed.segment(d, MODEL, SegmenterSettings(method="seed")) == []
    with pytest.raises(ValueError, match="camera model"):
        layers.segment(np.zeros((10, 10), np.float32), MODEL, cfg)
    empty = ObstacleBuilder(SegmenterSettings()).process(np.zeros((0, 0), np.float32), MODEL, t_s=0.0, seq=0,
                                                         stamp_ns=0)
    assert empty.obstacles.obstacles == [] and "no-valid-disparity" in empty.obstacles.degraded


def test_edge_refinement_snaps_the_box_to_intensity_edges():
    d = scene([(250, 390, 2.0, 180)], noise=0.0, holes=0.0)
    img = np.full(d.shape, 60, np.uint8)
    img[:, 247:393] = 200
    dets = layers.segment(d, MODEL, SegmenterSettings(edge_refine=True), image=img)
    assert len(dets) == 1
    x0, _, x1, _ = dets[0].bbox_px
    assert abs(x0 - 247) <= 1 and abs(x1 - 393) <= 1


# --- mount -----------------------------------------------------------------------------------

def test_mount_matches_the_height_pitch_transform_and_rep103():
    m = Mount(1.0, 15.0)
    c, s = np.cos(np.radians(15.0)), np.sin(np.radians(15.0))
    for x, y, z in ([0.3, -0.2, 2.0], [1.0, 2.0, 3.0]):
        # pitched down by 15 degrees: forward is z c - y s, left is -x, up is h - z s - y c
        assert np.allclose(m.to_base(np.array([x, y, z])), [z * c - y * s, -x, 1.0 - z * s - y * c])
    # straight ahead on the optical axis, camera level: forward in the base frame
    level = Mount(0.5, 0.0)
    assert np.allclose(level.to_base([0, 0, 2.0]), [2.0, 0, 0.5])
    assert np.allclose(level.to_base([1.0, 0, 0]), [0, -1.0, 0.5])  # camera x (right) = base -y
    assert np.allclose(level.to_base([0, 1.0, 0]), [0, 0, -0.5])  # camera y (down) = base -z
    # yaw 90 deg left: the camera looks along base +y; offset moves the origin
    m = Mount(0.5, 0.0, yaw_deg=90.0, x_m=0.2, y_m=-0.1)
    assert np.allclose(m.to_base([0, 0, 1.0]), [0.2, 0.9, 0.5])
    # roll: positive tilts the right side down
    r = Mount(1.0, 0.0, roll_deg=10.0)
    assert r.to_base([1.0, 0, 0])[2] < 1.0


def test_floor_plane_round_trip():
    m = Mount(1.3, 20.0, roll_deg=3.0)
    fp = floor_plane(m)
    n, h = fp.normal_height(MODEL.focal_px, MODEL.cx, MODEL.cy, MODEL.baseline_m)
    assert abs(h - 1.3) < 1e-9 and np.allclose(n, m.down_camera)
    # a floor pixel's disparity puts its point on the floor
    u, v = 400.0, 420.0
    z = FB / fp.disparity(u, v)
    p = np.array([(u - MODEL.cx) * z / MODEL.focal_px, (v - MODEL.cy) * z / MODEL.focal_px, z])
    assert abs(m.to_base(p)[2]) < 1e-9


# --- settings and the service core -------------------------------------------------------------

def test_settings_default_to_layers_and_seed_can_reproduce_the_thesis():
    s = SegmenterSettings()
    assert s.method == "layers" and s.range_m == 4.5
    thesis = SegmenterSettings(method="seed", floor_removal=False)
    assert thesis.range_m == 3.0
    assert Mount.of(MountSettings()) is None  # no silent mount: the ground is estimated
    assert (Mount.of(MountSettings(height_m=1.0, pitch_deg=15.0, roll_deg=2.0, x_m=0.1))
            == Mount(1.0, 15.0, 0.0, 2.0, 0.1, 0.0))


def test_a_lean_about_the_configured_pivot_carries_the_camera_over_the_floor():
    """A ballbot leans about its ball: with mount.pivot_height_m, the mount of a frame is where the
    lean the ground shows (pitch and roll against the configured, upright ones) carries the camera,
    as the simulator moves it (sim.CameraMotion, its own code); without, the camera turns on the spot."""
    import sim as S
    from cores.segmentation.ground import frame_mount
    from evaluation.synthetic import mount_from_T

    upright = MountSettings(height_m=0.9, pitch_deg=8.0, pivot_height_m=0.15)
    motion = S.CameraMotion(pitch_deg=(S.Wave(6.0, 0.5, 90.0),), roll_deg=(S.Wave(-4.0, 0.5, 90.0),),
                            pivot_height_m=0.15)
    R, o = motion.camera_in_base(0.0, 0.9, 8.0)  # leaning 6 deg forward and 4 deg to the left
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, o
    true = mount_from_T(T)
    seen = GroundEstimate(height_m=true.height_m, pitch_deg=true.pitch_deg, roll_deg=true.roll_deg,
                          source="fitted", inlier_fraction=1.0, confidence=1.0)
    m, source = frame_mount(seen, upright)
    assert source == "ground" and m.height_m == true.height_m
    assert abs(m.x_m - true.x_m) < 1e-9 and abs(m.y_m - true.y_m) < 1e-9
    assert true.x_m > 0.07 and true.y_m > 0.04  # forward by 0.75 sin(6 deg), left by about 0.75 sin(4 deg)
    m0, _ = frame_mount(seen, upright.model_copy(update={"pivot_height_m": None}))
    assert (m0.x_m, m0.y_m) == (0.0, 0.0)
    upright_seen = GroundEstimate(height_m=0.9, pitch_deg=8.0, roll_deg=0.0, source="fitted", inlier_fraction=1.0,
                                  confidence=1.0)
    assert frame_mount(upright_seen, upright.model_copy(update={"x_m": 0.05}))[0].x_m == pytest.approx(0.05)


def test_a_balancing_robot_s_upright_mount_comes_from_the_data_not_a_guessed_one(caplog):
    """A ballbot leans about upright all the time: its upright mount, from which the lean about the
    pivot is measured, is the ground's average over time (Upright), starting at the configured
    mount. The sway scene's lean (pitch 6 deg at 0.6 Hz and 4 at 1.9, roll 7 at 0.5 and 3 at 1.4)
    about a ball 0.15 m up, the camera 0.9 m high and pitched 8 deg, each frame's ground exact: a
    mount guessed 8 deg off in pitch or roll placed the camera 10 cm off over the floor in every
    frame; after 15 s it is placed within 2 cm, and said once. A mount measured right stays within 1.5 cm."""
    import logging

    import sim as S
    from cores.segmentation.ground import Upright, frame_mount
    from evaluation.synthetic import mount_from_T

    motion = S.CameraMotion(pitch_deg=(S.Wave(6.0, 0.6), S.Wave(4.0, 1.9, 40.0)),
                            roll_deg=(S.Wave(7.0, 0.5, 90.0), S.Wave(3.0, 1.4, 200.0)), pivot_height_m=0.15)

    def placed(configured: MountSettings) -> tuple[np.ndarray, np.ndarray]:
        """Per frame at 15 fps over 20 s: the camera's x, y error with the data's upright and with
        the configured one, m."""
        upright = Upright(Mount.of(configured))
        ours, theirs = [], []
        for t in np.arange(0.0, 20.0, 1 / 15):
            R, o = motion.camera_in_base(float(t), 0.9, 8.0)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, o
            true = mount_from_T(T)
            seen = GroundEstimate(height_m=true.height_m, pitch_deg=true.pitch_deg, roll_deg=true.roll_deg,
                                  source="fitted", inlier_fraction=1.0, confidence=1.0)
            upright.update(seen, float(t))
            for out, m in ((ours, frame_mount(seen, configured, upright.mount(configured))[0]),
                           (theirs, frame_mount(seen, configured)[0])):
                out.append(np.hypot(m.x_m - true.x_m, m.y_m - true.y_m))
        return np.array(ours), np.array(theirs)

    late = slice(15 * 15, None)  # the last 5 s
    for guess in ({"pitch_deg": 16.0}, {"pitch_deg": 0.0}, {"roll_deg": 8.0}):
        with caplog.at_level(logging.WARNING, logger="ballbot"):
            caplog.clear()
            ours, theirs = placed(MountSettings(height_m=0.9, pivot_height_m=0.15, **{"pitch_deg": 8.0, **guess}))
        assert np.median(theirs) > 0.09, (guess, np.median(theirs))
        assert ours[late].max() < 0.02, (guess, ours[late].max())
        assert sum("the robot leans about" in r.getMessage() for r in caplog.records) == 1, caplog.text
    with caplog.at_level(logging.WARNING, logger="ballbot"):
        caplog.clear()
        ours, theirs = placed(MountSettings(height_m=0.9, pitch_deg=8.0, pivot_height_m=0.15))
    assert ours.max() < 0.015 and theirs.max() < 1e-6, (ours.max(), theirs.max())
    assert "the robot leans about" not in caplog.text
    # none configured: the lean is measured from the data's average too (before, the camera stayed put)
    upright = Upright(None)
    assert upright.mount(MountSettings(pivot_height_m=0.15)) is None
    assert ObstacleBuilder(SegmenterSettings(), MountSettings(pivot_height_m=0.15)).upright is not None
    assert ObstacleBuilder(SegmenterSettings(), MountSettings(height_m=0.9)).upright is None


def _message(d: np.ndarray, model=MODEL, width=None) -> DisparityMap:
    raw = np.where(np.isfinite(d), np.round(d * 16), -16).astype(np.int16)
    cam = CameraModel(width=model.width, height=model.height, focal_px=model.focal_px, cx=model.cx, cy=model.cy,
                      baseline_m=model.baseline_m, Q=[float(x) for x in model.Q.ravel()])
    return DisparityMap(robot_id="t", seq=1, stamp_ns=time.time_ns(),
                        image=Image(width=width or raw.shape[1], height=raw.shape[0], dtype="int16",
                                    data=raw.tobytes()), scale=16.0, invalid_value=-16, min_disparity=0,
                        num_disparities=64, camera=cam, method="bm")


def test_builder_publishes_every_field_and_the_base_frame():
    b = ObstacleBuilder(SegmenterSettings(), MountSettings(height_m=1.0, pitch_deg=15.0))
    msg = _message(scene([(200, 330, 1.8, 150), (330, 470, 2.5, 200)]))
    out = b.process_message(msg).obstacles
    assert out.method == "layers" and len(out.obstacles) == 2
    near, far = out.obstacles  # nearest first
    assert near.distance_m < far.distance_m
    assert near.id != far.id and near.confidence > 0.8 and near.area_px > 1000
    assert abs(near.disparity_px - FB / 1.8) < 0.3
    base = np.array(near.position_base_m)
    g = out.ground  # fitted to the map's floor, near the configured mount; the base frame is the fitted one's
    assert g.source == "fitted" and abs(g.height_m - 1.0) < 0.03 and abs(g.pitch_deg - 15.0) < 0.5
    assert np.allclose(base, Mount(g.height_m, g.pitch_deg, 0.0, g.roll_deg).to_base(near.position_m))
    assert 1.6 < base[0] < 2.0 and base[2] > 0.05  # ahead, above the floor
    # the same scene again: the same ids, no velocity
    again = b.process_message(msg).obstacles
    assert [o.id for o in again.obstacles] == [near.id, far.id]
    assert np.linalg.norm(again.obstacles[0].velocity_mps) < 0.05


def test_builder_on_bad_maps():
    b = ObstacleBuilder(SegmenterSettings())
    msg = _message(np.full((MODEL.height, MODEL.width), np.nan, np.float32))
    assert b.process_message(msg).obstacles.obstacles == []
    bad = _message(np.zeros((MODEL.height, MODEL.width - 10), np.float32))
    with pytest.raises(DecodeError, match="camera model"):
        b.decode(bad)
    small = codec.image_from_array(np.zeros((MODEL.height, MODEL.width - 2), np.uint8))
    with pytest.raises(DecodeError, match="flat mask is"):
        b.decode(msg.model_copy(update={"flat": small}))
    flat = np.zeros((MODEL.height, MODEL.width), np.uint8)
    flat[:, :7] = 255
    got = b.decode(msg.model_copy(update={"flat": codec.image_from_array(flat)}))[3]
    assert got.dtype == bool and got[:, :7].all() and not got[:, 7:].any()


# --- the offline command -----------------------------------------------------------------------

def test_obstacles_command_on_rendered_images(tmp_path, capsys):
    import cv2

    from ballbot_vision.cli import main
    from sim import Scene, SyntheticWorld

    rig = camera.load_calibration("lifecam-studio")
    world = SyntheticWorld(Scene.builtin("touching"), rig, camera.rectify_rig(rig), seed=0)
    left, right = world.render(0.0)
    cv2.imwrite(str(tmp_path / "left.png"), left)
    cv2.imwrite(str(tmp_path / "right.png"), right)
    assert main(["obstacles", str(tmp_path / "left.png"), str(tmp_path / "right.png"),
                 "--calibration", "lifecam-studio", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    truth = world.truth(0.0)
    assert len(doc["obstacles"]) == len(truth) == 2
    for t in truth:
        o = min(doc["obstacles"], key=lambda o: np.linalg.norm(np.array(o["position_m"]) - t.visible_centroid_m))
        assert np.linalg.norm(np.array(o["position_m"]) - t.visible_centroid_m) < 0.05 * t.visible_centroid_m[2]
    assert main(["obstacles", str(tmp_path / "left.png"), str(tmp_path / "right.png"),
                 "--calibration", "lifecam-studio", "--method", "seed"]) == 0
    assert "seed" in capsys.readouterr().out
    assert main(["obstacles", str(tmp_path / "left.png"), str(tmp_path / "nope.png"),
                 "--calibration", "lifecam-studio"]) == 2
    assert "nope.png" in capsys.readouterr().err


# --- the ground every frame, the height band, free space (issue: real scenes) ----------------------

def _frame(d, cfg, ground=None, mount=None):
    from cores.segmentation.ground import GroundEstimator
    return layers.segment_frame(d, MODEL, cfg, ground=ground or GroundEstimator(cfg, mount))


@pytest.mark.parametrize("mount", [Mount(1.0, 15.0), Mount(0.6, 25.0, roll_deg=4.0), Mount(1.6, 6.0, roll_deg=-2.0)])
def test_ground_is_estimated_without_a_mount(mount):
    fr = _frame(scene([(250, 390, 2.0, 120)], mount=mount, wall_m=6.0), SegmenterSettings())
    g = fr.ground
    assert g.source == "fitted" and g.inlier_fraction > 0.3
    assert abs(g.height_m - mount.height_m) < 0.02 * mount.height_m
    assert abs(g.pitch_deg - mount.pitch_deg) < 0.3 and abs(g.roll_deg - mount.roll_deg) < 0.3
    assert _depths(fr.detections) == [2.0]


def test_a_wrong_mount_and_a_swaying_camera_still_remove_the_floor():
    from cores.segmentation.ground import GroundEstimator

    cfg = SegmenterSettings()
    ground = GroundEstimator(cfg, Mount(1.0, 20.0))  # told 5 degrees wrong
    for k in range(12):  # a ballbot sways: pitch 15 +- 4 degrees, roll +- 2, frame to frame
        truth = Mount(1.0, 15.0 + 4.0 * np.sin(k), roll_deg=2.0 * np.cos(k))
        fr = _frame(scene([(250, 390, 2.0, 120)], mount=truth, seed_=k), cfg, ground)
        assert fr.ground.source == "fitted", k
        assert abs(fr.ground.pitch_deg - truth.pitch_deg) < 0.4 and abs(fr.ground.roll_deg - truth.roll_deg) < 0.4
        assert _depths(fr.detections) == [2.0], (k, _depths(fr.detections))  # no floor patches


def test_a_swaying_camera_close_to_furniture_never_takes_the_furniture_for_the_floor():
    from cores.segmentation.ground import TRUSTED, GroundEstimator

    cfg = SegmenterSettings()
    ground = GroundEstimator(cfg)
    for k in range(12):  # a balancing robot leans by up to 5 degrees a frame
        truth = Mount(1.0, 12.0 + 8.0 * np.sin(0.7 * k), roll_deg=6.0 * np.cos(0.7 * k))
        # then it drives up to furniture that fills the view but for a strip of floor under it
        boxes = [(250, 390, 2.5, 120)] if k < 8 else [(70, 330, 2.2, 400), (330, 640, 2.4, 400)]
        fr = _frame(scene(boxes, mount=truth, seed_=k), cfg, ground)
        g = fr.ground
        off = abs(g.pitch_deg - truth.pitch_deg) > 2.0 or abs(g.height_m - truth.height_m) > 0.1
        # a ground off the floor is at most the last frames' carried on, and said to be so
        assert not off or (g.source == "tracked" and k < 10), (k, g)
        assert g.confidence < TRUSTED or abs(g.pitch_deg - truth.pitch_deg) < 4.0, (k, g)
        assert _depths(fr.detections) == ([2.5] if k < 8 else [2.3]), (k, _depths(fr.detections))
    assert g.source == "fitted" and abs(g.pitch_deg - truth.pitch_deg) < 1.5  # the strip of floor, found again


def test_without_a_floor_in_view_the_last_ground_stands_in_then_none():
    from cores.segmentation.ground import GroundEstimator

    cfg = SegmenterSettings()
    ground = GroundEstimator(cfg)
    assert _frame(scene([]), cfg, ground).ground.source == "fitted"
    wall = np.full((MODEL.height, MODEL.width), FB / 2.0, np.float32)  # a wall fills the view
    assert _frame(wall, cfg, ground).ground.source == "tracked"
    assert _frame(wall, cfg).ground.source == "none"  # no history, no mount: said so


CAR = camera.RectifiedModel(640, 480, 665.0, 320.0, 240.0, 0.5)  # a car's wide rig: it measures out to ~20 m


def _road(mount: Mount, seed_: int, range_m: float | None = None) -> np.ndarray:
    """CAR's disparity of a road seen from `mount`, with low lumps of snow along it (0.13 m) and
    matching noise; range_m: the map gated there, as a matcher with a vision-range gate gives it."""
    rng = np.random.default_rng(seed_)
    fb = CAR.focal_px * CAR.baseline_m
    v, u = np.mgrid[0:CAR.height, 0:CAR.width].astype(np.float32)
    fp = FloorPlane.from_normal(mount.down_camera, mount.height_m, CAR.focal_px, CAR.cx, CAR.cy, CAR.baseline_m)
    d = fp.disparity(u, v).astype(np.float32)
    d[d < fb / 60] = np.nan  # the sky
    for u0 in range(80, 260, 40):
        dd = fp.disparity(np.float32(u0 + 10), np.arange(CAR.height, dtype=np.float32))
        r = int(np.nonzero((dd > fb / 3.9) & (dd < fb / 3.4))[0].max())
        d[r - 25:r, u0:u0 + 25] = dd[r]
    d += rng.normal(0, 0.3, d.shape).astype(np.float32)
    d[:, :64] = np.nan
    return d if range_m is None else np.where(d >= fb / range_m, d, np.nan)


def test_a_range_that_shows_a_strip_of_road_takes_the_ground_from_the_road_beyond():
    """A car's camera (1.6 m, 6 deg down) sees the road from 3.3 m: with a 3.8 m range, a strip
    whose plane pivots between pitch and height. The map goes on (the matcher has no range gate):
    the road beyond the range, as far as the rig measures, gives the ground as a full view does."""
    from cores.segmentation.ground import TRUSTED

    truth = Mount(1.6, 6.0)
    builder = ObstacleBuilder(SegmenterSettings(max_range_m=3.8), MountSettings())
    for k in range(3):
        lst = builder.process(_road(truth, k), CAR, t_s=0.1 * k, seq=k, stamp_ns=k).obstacles
        g = lst.ground
        assert g.source == "fitted" and g.confidence >= TRUSTED and not lst.degraded, (k, g, lst.degraded)
        assert abs(g.height_m - truth.height_m) < 0.01 and abs(g.pitch_deg - truth.pitch_deg) < 0.1, (k, g)
        assert abs(g.roll_deg) < 0.1, (k, g)


def test_a_range_nearer_than_the_floor_in_view_says_so():
    """With a 3 m range the car's camera sees none of the road inside it (it starts at 3.3 m): the
    ground comes from the road beyond, and every list says low things in the range are out of view;
    with 3.8 m the near strip is in view and nothing is flagged."""
    for range_m, flagged in ((3.0, True), (3.8, False)):
        builder = ObstacleBuilder(SegmenterSettings(max_range_m=range_m), MountSettings())
        for k in range(2):
            lst = builder.process(_road(Mount(1.6, 6.0), k), CAR, t_s=0.1 * k, seq=k, stamp_ns=k).obstacles
            assert lst.ground.source == "fitted" and abs(lst.ground.pitch_deg - 6.0) < 0.1, (range_m, lst.ground)
            assert ("floor-out-of-view" in lst.degraded) == flagged and len(lst.degraded) == flagged, \
                (range_m, lst.degraded)


def test_a_strip_of_road_alone_is_a_ground_not_to_be_trusted():
    """The same strip with nothing beyond it (a map gated to the range): whatever plane fits it, the
    list says its ground is uncertain."""
    builder = ObstacleBuilder(SegmenterSettings(max_range_m=3.8), MountSettings())
    for k in range(3):
        lst = builder.process(_road(Mount(1.6, 6.0), k, range_m=3.8), CAR, t_s=0.1 * k, seq=k, stamp_ns=k).obstacles
        assert lst.ground.source == "fitted" and "ground-uncertain" in lst.degraded, (k, lst.ground)
    # a strip of road twice as deep in view is a ground to trust
    builder = ObstacleBuilder(SegmenterSettings(max_range_m=8.0), MountSettings())
    lst = builder.process(_road(Mount(1.6, 6.0), 0, range_m=8.0), CAR, t_s=0.0, seq=0, stamp_ns=0).obstacles
    assert not lst.degraded and abs(lst.ground.pitch_deg - 6.0) < 0.3, lst.ground


def test_markings_are_floor_canopy_is_above_the_robot_and_only_standing_things_are_obstacles():
    mount = Mount(1.0, 0.0)  # level: the top rows see 1.8 m above the camera at 5 m
    d = scene([(400, 520, 2.5, 150)], mount=mount, wall_m=9.0)
    fp = floor_plane(mount)
    v, u = np.mgrid[0:MODEL.height, 0:MODEL.width].astype(np.float32)
    flat = fp.disparity(u, v) * (1 / (1 - 0.05 / 1.0))  # a patch 5 cm above the floor: a mat, a marking
    d[330:400, 150:300] = flat[330:400, 150:300]
    # a canopy more than 2.6 m above the floor, 5 m ahead: rows where a point at depth 5 m is that high
    z = 5.0
    rows = [r for r in range(MODEL.height) if 1.0 - (r - MODEL.cy) / MODEL.focal_px * z > 2.6]
    assert rows
    d[min(rows):max(rows) + 1, 100:600] = FB / z
    fr = _frame(d, SegmenterSettings(max_range_m=6.0))
    assert _depths(fr.detections) == [2.5]
    tall = _frame(d, SegmenterSettings(max_range_m=6.0, robot_height_m=5.0))
    assert 5.0 in [round(float(x.position_m[2]), 1) for x in tall.detections]  # a taller robot hits it


def test_free_space_is_free_up_to_the_obstacle_occupied_at_it_unknown_behind():
    from cores.segmentation import freespace
    from cores.segmentation.ground import frame_mount

    cfg = SegmenterSettings(freespace_resolution_m=0.1)
    fr = _frame(scene([(250, 390, 2.0, 200)], wall_m=6.0), cfg)
    m, source = frame_mount(fr.ground, MountSettings())
    assert source == "ground"
    g = freespace.occupancy(fr.floor_points, fr.points, m, MODEL, cfg.range_m, cfg.freespace_resolution_m)

    def cell(x, y):
        return g.cells[int((y - g.origin_m[1]) / g.resolution_m), int((x - g.origin_m[0]) / g.resolution_m)]

    box_x = float(m.to_base(fr.detections[0].position_m)[0])
    assert 1.7 < box_x < 2.2
    assert cell(1.5, 0.0) == 0 and cell(1.7, 0.0) == 0  # floor between the camera's near edge (1.43 m) and the box
    assert cell(box_x, 0.0) == 100  # the box
    assert cell(3.5, 0.0) == -1  # behind it: not seen
    assert cell(3.5, -1.3) == 0 and cell(3.5, 1.3) == 0  # beside it, the floor is seen out to the wall
    assert cell(1.0, 0.0) == -1  # under the camera, below its field of view


def test_a_gap_too_narrow_to_pass_between_two_things_stops_the_free_space_at_the_nearer():
    from cores.segmentation import freespace

    d = np.zeros(40, np.float32)
    d[5:10], d[17:22] = 20.0, 25.0  # two things, 7 columns apart
    d[30] = 30.0  # a speck: no thing of its own
    # 0.5 column per px of disparity: the 7 columns pass at a disparity of 14 or less
    closed = freespace.spread_sides(d, 0, 0.5)
    assert (closed[10:17] == 25.0).all() and (closed[22:30] == 0).all() and closed[30] == 30.0
    assert (freespace.spread_sides(d, 0, 0.3) == d).all()  # 7 columns are 0.3 * 20 = 6 too many: a way through
    sides = freespace.spread_sides(d, 2, 0.0)
    assert (sides[3:5] == 20.0).all() and (sides[10:12] == 20.0).all() and sides[12] == 0 and sides[31] == 0


def test_builder_publishes_ground_free_space_and_confirms_tracks():
    b = ObstacleBuilder(SegmenterSettings(track_confirm_m=3, track_confirm_n=5))
    d = scene([(250, 390, 2.0, 150)])
    outs = [b.process(d, MODEL, t_s=k / 15, seq=k, stamp_ns=k) for k in range(4)]
    confirmed = [r.obstacles.obstacles[0].confirmed for r in outs]
    assert confirmed == [False, False, True, True]  # seen in 3 of the last 5 frames
    last = outs[-1]
    assert last.obstacles.ground.source == "fitted" and last.obstacles.velocity_reference == "camera"
    fs = last.freespace
    cells = np.frombuffer(fs.cells, np.int8)
    assert fs.frame_id == "base" and cells.size == fs.width * fs.height and (cells == 0).any() and (cells == 100).any()
    assert last.obstacles.obstacles[0].position_base_m is not None
    # the thesis's method removes the floor the ground estimator finds, as layers does: with no mount, or
    # with one 8 deg and 30 % off (its prior), the same ground and the same box; no free space (seed has none)
    for mount in (None, MountSettings(height_m=SCENE_MOUNT.height_m * 1.3, pitch_deg=SCENE_MOUNT.pitch_deg + 8)):
        lst = ObstacleBuilder(SegmenterSettings(method="seed"), mount).process(d, MODEL, t_s=0, seq=0, stamp_ns=0)
        g = lst.obstacles.ground
        assert lst.freespace is None and lst.obstacles.degraded == [] and g.source == "fitted", lst.obstacles
        assert abs(g.height_m - SCENE_MOUNT.height_m) < 0.05 and abs(g.pitch_deg - SCENE_MOUNT.pitch_deg) < 1.0
        (o,) = lst.obstacles.obstacles
        assert o.distance_m == pytest.approx(2.0, abs=0.1)
    # fit_floor false: the configured mount, trusted as far as a mount measured once can be
    mounted = ObstacleBuilder(SegmenterSettings(method="seed", fit_floor=False),
                              MountSettings(height_m=SCENE_MOUNT.height_m, pitch_deg=SCENE_MOUNT.pitch_deg))
    lst = mounted.process(d, MODEL, t_s=0, seq=0, stamp_ns=0).obstacles
    assert lst.degraded == [] and lst.ground.source == "prior" and lst.ground.confidence >= 0.3
    assert ObstacleBuilder(SegmenterSettings(method="seed", fit_floor=False)).process(
        d, MODEL, t_s=0, seq=0, stamp_ns=0).obstacles.degraded == ["no-ground"]  # and no mount: said so
    thesis = ObstacleBuilder(SegmenterSettings(method="seed", floor_removal=False), MountSettings(height_m=1.0))
    assert thesis.process(d, MODEL, t_s=0, seq=0, stamp_ns=0).obstacles.degraded == ["no-ground"]
    # layers without floor removal: the floor stands up with the box on it, one obstacle at neither's place
    unfloored = ObstacleBuilder(SegmenterSettings(floor_removal=False), MountSettings(height_m=1.0, pitch_deg=15.0))
    assert unfloored.process(d, MODEL, t_s=0, seq=0, stamp_ns=0).obstacles.degraded == ["no-ground"]


def test_a_tracked_object_seen_in_pieces_stays_one_obstacle_and_a_newcomer_beside_it_does_not_join():
    """A wide low cabinet 3 m away is tracked; then the matcher loses a stretch in its middle (two
    pieces 0.2 m apart across the view, too far for merge_gap_m): it is still one obstacle with its
    id, while a box stepping up 0.3 m beside it is an obstacle of its own."""
    mount = Mount(1.0, 15.0)

    def frame(gap: bool, newcomer: bool) -> np.ndarray:
        d = scene([(200, 470, 3.0, 80)] + ([(510, 560, 3.0, 120)] if newcomer else []), holes=0.0)
        if gap:
            d[:, 320:360] = scene(holes=0.0)[:, 320:360]  # the floor and wall behind show through
        return d

    for merge in (True, False):
        b = ObstacleBuilder(SegmenterSettings(track_merge_fragments=merge), _mounted(mount))
        outs = [b.process(frame(k >= 4, k >= 5), MODEL, t_s=k / 15, seq=k, stamp_ns=k) for k in range(7)]
        first = outs[0].obstacles.obstacles
        assert len(first) == 1
        for r in outs[4:]:
            obs = sorted(r.obstacles.obstacles, key=lambda o: o.bbox_px[0])
            if merge:
                assert obs[0].id == first[0].id and obs[0].bbox_px[0] <= 202 and obs[0].bbox_px[2] >= 468
                assert len(obs) == (2 if r.obstacles.seq >= 5 else 1)
                if len(obs) == 2:
                    assert obs[1].id != obs[0].id and obs[1].bbox_px[0] >= 500
            else:  # without: the pieces are two obstacles (what the tracker is given to hold together)
                assert sum(o.bbox_px[2] <= 470 for o in obs) == 2


def test_a_thin_piece_wholly_inside_a_tracked_footprint_joins_it():
    """A table tracked with its legs; this frame its back leg, 3 cm deep on the ground, is seen apart
    from its front, right at the back edge of the table's footprint: it is a piece of the table, not
    a thing of its own (the sway scene's table split so in 2 frames). A post 0.3 m behind the
    footprint stays apart."""
    from cores.segmentation.builder import _footprint
    from cores.segmentation.seed import Detection
    from cores.segmentation.tracking import Track

    mount = Mount(1.0, 10.0)
    b = ObstacleBuilder(SegmenterSettings(), _mounted(mount))
    R = mount.R_base_camera

    def piece(x0, x1, y0, y1):  # points of a piece standing on the footprint x0..x1, y0..y1 (base)
        g = np.stack(np.meshgrid(np.linspace(x0, x1, 12), np.linspace(y0, y1, 12), np.linspace(0.1, 0.7, 5)),
                     -1).reshape(-1, 3)
        cam = (g - mount.origin_base) @ R  # base -> camera
        c = cam.mean(0)
        return Detection(c, np.ptp(cam, 0), float(np.linalg.norm(c)), (0, 0, 10, 10), 100, 30.0, 1.0), cam

    b.tracker.tracks = [Track(7, np.array([2.3, -0.1, 0.4]), last_seen_s=0.0, confirmed=True,
                              box=np.array([[2.0, -0.5], [2.6, 0.3]]))]
    front, leg, post = piece(2.0, 2.1, -0.5, 0.3), piece(2.57, 2.60, -0.45, -0.40), piece(2.9, 2.93, 0.0, 0.05)
    dets, points = zip(front, leg, post)
    fps = [_footprint(mount, p) for p in points]
    out, _, _ = b._merge_fragments(list(dets), list(points), fps, mount, MODEL, 0.1)
    assert len(out) == 2  # the table (front and leg) and the post
    assert sorted(round(float(d.size_m[2]), 1) for d in out)[-1] >= 0.5  # the table reaches back to its leg


def test_odometry_gives_velocities_over_the_ground():
    from common.messages import Odometry

    b = ObstacleBuilder(SegmenterSettings(), MountSettings(height_m=1.0, pitch_deg=15.0))
    speed, fps = 0.6, 15.0
    ids = set()
    for k in range(20):  # the robot drives at 0.6 m/s towards a box standing still
        z = 3.0 - speed * k / fps
        cols = int(70 / z * 2.0)
        d = scene([(320 - cols, 320 + cols, z, int(250 / z))], wall_m=8.0, seed_=k)
        odo = Odometry(robot_id="r", seq=k, stamp_ns=k, linear_mps=(speed, 0.0, 0.0))
        res = b.process(d, MODEL, t_s=k / fps, seq=k, stamp_ns=k, odometry=odo)
        (o,) = res.obstacles.obstacles
        ids.add(o.id)
    assert res.obstacles.velocity_reference == "ground" and len(ids) == 1
    assert np.linalg.norm(o.velocity_base_mps) < 0.15, o.velocity_base_mps  # it stands still
    still = ObstacleBuilder(SegmenterSettings(), MountSettings(height_m=1.0, pitch_deg=15.0))
    for k in range(20):  # without odometry: relative to the robot, it approaches at the robot's speed
        z = 3.0 - speed * k / fps
        cols = int(70 / z * 2.0)
        res = still.process(scene([(320 - cols, 320 + cols, z, int(250 / z))], wall_m=8.0, seed_=k), MODEL,
                            t_s=k / fps, seq=k, stamp_ns=k)
    (o,) = res.obstacles.obstacles
    assert res.obstacles.velocity_reference == "camera" and o.velocity_base_mps[0] == pytest.approx(-speed, abs=0.15)


def test_a_forged_odometry_message_cannot_poison_the_tracks():
    import msgpack

    from common import codec
    from common.messages import Odometry

    good = Odometry(robot_id="r", seq=1, stamp_ns=1, linear_mps=(0.5, 0.0, 0.0))
    for bad in ((float("nan"), 0.0, 0.0), (float("inf"), 0.0, 0.0), (1e300, 0.0, 0.0)):
        doc = good.model_dump()
        doc["linear_mps"] = bad
        with pytest.raises(DecodeError):
            codec.decode(msgpack.packb(doc, use_bin_type=True), Odometry)
    # and the builder carries on with the tracks it had
    b = ObstacleBuilder(SegmenterSettings())
    d = scene([(250, 390, 2.0, 150)])
    first = b.process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0, odometry=good)
    later = b.process(d, MODEL, t_s=0.1, seq=1, stamp_ns=1, odometry=good)
    assert [o.id for o in later.obstacles.obstacles] == [o.id for o in first.obstacles.obstacles]
    assert all(np.isfinite(o.velocity_mps).all() for o in later.obstacles.obstacles)


def test_a_camera_model_with_a_nan_or_infinite_number_is_refused_at_decode():
    import msgpack

    from common import codec

    msg = _message(scene([(250, 390, 2.0, 150)]))
    for field, value in (("cx", float("nan")), ("focal_px", float("inf")), ("baseline_m", float("nan"))):
        doc = msg.model_dump()
        doc["camera"][field] = value
        with pytest.raises(DecodeError, match=f"camera.{field}"):
            codec.decode(msgpack.packb(doc, use_bin_type=True), DisparityMap)


# --- issue 20: a mount is a prior, ranges that fit, lists that say what they cannot vouch for ------

@pytest.mark.parametrize("told", [dict(height_m=1.5, pitch_deg=15.0),  # height 50 % off
                                  dict(height_m=1.0, pitch_deg=-5.0),  # pitch 20 deg off
                                  dict(height_m=0.5, pitch_deg=15.0, roll_deg=15.0)])
def test_a_wrong_mount_is_a_prior_not_a_cage(told, caplog):
    truth = Mount(1.0, 15.0)
    b = ObstacleBuilder(SegmenterSettings(), MountSettings(**told))
    for k in range(3):
        out = b.process_message(_message(scene([(250, 390, 2.0, 120)], mount=truth, seed_=k))).obstacles
        g = out.ground
        assert g.source == "fitted" and abs(g.height_m - 1.0) < 0.03 and abs(g.pitch_deg - 15.0) < 0.5, (k, g)
        assert g.prior_height_m == told["height_m"] and g.prior_pitch_deg == told["pitch_deg"]
        # the list says where it put the camera: the data's ground, not the configured mount
        assert out.mount.source == "ground" and out.mount.height_m == g.height_m
        assert g.prior_agrees is False and g.confidence >= 0.3 and out.degraded == []
        assert _depths([type("D", (), {"position_m": o.position_m})() for o in out.obstacles]) == [2.0]
    assert sum("disagrees with the configured mount" in r.message for r in caplog.records) == 1  # once


@pytest.mark.parametrize("method", ["layers", "seed"])
def test_a_mount_chosen_over_fitting_is_checked_against_the_floor_in_the_data(method, caplog):
    """fit_floor false: the configured mount is the floor, as the user chose. Measured right, the
    lists are trusted; 3 deg steeper than the camera really is, the mount's floor lies over the real
    one (0.13 m at 2.5 m: what stands lower than that is lost): every list says mount-disagrees, and
    not one looks fresh and clear; logged once."""
    truth = Mount(1.0, 15.0)
    box = [(150, 470, 2.5, 80)]  # 0.3 m high at 2.5 m, 8 % of the image (seed's area opening)
    for told, low_box in ((dict(height_m=1.0, pitch_deg=15.0), True), (dict(height_m=1.0, pitch_deg=18.0), False)):
        caplog.clear()
        b = ObstacleBuilder(SegmenterSettings(method=method, fit_floor=False, min_height_m=0.1, max_range_m=4.0),
                            MountSettings(**told))
        for k in range(4):
            out = b.process_message(_message(scene(box, mount=truth, seed_=k))).obstacles
            g = out.ground
            assert g.source == "prior" and g.pitch_deg == pytest.approx(told["pitch_deg"], abs=1e-6)
            if low_box:
                assert out.degraded == [] and g.prior_agrees is True and g.confidence >= 0.3, (k, out.degraded)
                assert [round(o.distance_m, 1) for o in out.obstacles] == [2.5]
            else:
                assert "mount-disagrees" in out.degraded and g.prior_agrees is False and g.confidence < 0.3, k
        said = sum("every such list says mount-disagrees" in r.message for r in caplog.records)
        assert said == (0 if low_box else 1)


def test_lists_say_when_the_search_cannot_reach_the_range_or_there_is_no_ground():
    d = scene([(250, 390, 2.0, 120)])
    ok = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0, search=(0, 144))
    assert ok.obstacles.degraded == [] and ok.obstacles.ground.confidence >= 0.3
    assert ok.obstacles.range_m == (1.0, 4.5)  # what "looked and saw nothing" covers: the vision range
    # ... and the bearings: left of x = 144 the right camera does not see what stands 0.46 m away
    left, right = ok.obstacles.bearing_deg
    assert left == pytest.approx(np.degrees(np.arctan((144 - 320) / 665)), abs=1e-6)
    assert right == pytest.approx(np.degrees(np.arctan(319 / 665)), abs=1e-6)
    no_search = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0)
    assert no_search.obstacles.bearing_deg is None  # not said
    # 16 px reach no nearer than f*B/15 = 4.4 m: a 3 m range is out of reach, whatever the map holds
    b = ObstacleBuilder(SegmenterSettings(max_range_m=3.0))
    lst = b.process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0, search=(0, 16)).obstacles
    assert "range-unreachable" in lst.degraded and b.reach.unreachable and "do not overlap" in b.reach.message
    # 32 px reach no nearer than f*B/31 = 2.1 m: the default range starts at 1 m, and an obstacle at 1.5 m
    # would not be measured (block matching aliases it farther): the box at 3 m is found, and every list
    # says the near part was not looked at
    far = scene([(250, 390, 3.0, 80)])
    far[far > 31] = np.nan  # what a 0..31 px search gives (decode() makes the rest invalid)
    b = ObstacleBuilder(SegmenterSettings())
    for k in range(2):
        lst = b.process(far, MODEL, t_s=k / 15, seq=k, stamp_ns=0, search=(0, 32)).obstacles
        assert lst.degraded == ["near-unmeasured"] and not b.reach.unreachable, lst.degraded
        assert _depths([type("D", (), {"position_m": o.position_m})() for o in lst.obstacles]) == [3.0]
    assert f"nothing nearer than {FB / 31:.2f} m" in b.reach.message and "near-unmeasured" in b.reach.message
    # the nearest depth a few cm beyond min_range_m (the thesis's 64 px on its rig for 1 m) is no news
    assert ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0,
                                                        search=(0, int(FB / 1.2) + 1)).obstacles.degraded == []
    wall = np.full((MODEL.height, MODEL.width), FB / 2.0, np.float32)  # no floor in view, no history, no mount
    lst = ObstacleBuilder(SegmenterSettings()).process(wall, MODEL, t_s=0.0, seq=0, stamp_ns=0).obstacles
    assert lst.ground.source == "none" and lst.ground.confidence == 0.0 and "no-ground" in lst.degraded


def test_lists_say_when_the_search_or_its_gate_cannot_reach_the_far_part_of_the_range():
    """A min_disparity of 32 px measures nothing farther than f*B/32 = 2.1 m; the default range runs
    to 4.5 m. The lists had said nothing: the box at 3 m was simply not there (or aliased nearer),
    and an empty list read as a clear way to 4.5 m. Now every list says far-unmeasured, as a search
    that misses the near part says near-unmeasured; the matcher's vision range gate (gate_px) counts
    as the same; a few centimetres short of the range's end is no news."""
    d = scene([(250, 390, 1.5, 120), (400, 560, 3.0, 80)])
    cut = np.where(d >= 32, d, np.nan).astype(np.float32)  # what a 32..175 px search gives
    b = ObstacleBuilder(SegmenterSettings())
    for k in range(2):
        lst = b.process(cut, MODEL, t_s=k / 15, seq=k, stamp_ns=0, search=(32, 144)).obstacles
        assert lst.degraded == ["far-unmeasured"] and not b.reach.unreachable, lst.degraded
        dist = [round(o.distance_m, 1) for o in lst.obstacles]
        assert 1.5 in dist and max(dist) <= round(FB / 32, 1), dist  # the box at 3 m is in no list
        # and the distances the list says it looked at end where the search does ("looked and saw
        # nothing" up to 4.5 m was the lie)
        assert lst.range_m == pytest.approx((1.0, FB / 32)), lst.range_m
    assert f"nothing farther than {FB / 32:.2f} m is measured" in b.reach.message
    assert "far-unmeasured" in b.reach.message and "lower min_disparity" in b.reach.message
    # the same through the disparity stage's gate (max_range_m 2 m), and both ends missed at once
    gated = np.where(d >= FB / 2.0, d, np.nan).astype(np.float32)
    lst = ObstacleBuilder(SegmenterSettings()).process(gated, MODEL, t_s=0.0, seq=0, stamp_ns=0, search=(0, 144),
                                                       gate_px=FB / 2.0).obstacles
    assert lst.degraded == ["far-unmeasured"], lst.degraded
    both = ObstacleBuilder(SegmenterSettings())
    lst = both.process(gated, MODEL, t_s=0.0, seq=0, stamp_ns=0, search=(0, 32), gate_px=FB / 2.0).obstacles
    assert lst.degraded == ["near-unmeasured", "far-unmeasured"], lst.degraded
    assert lst.range_m == pytest.approx((FB / 31, 2.0)), lst.range_m
    assert "nothing nearer than" in both.reach.message and "the disparity stage's max_range_m" in both.reach.message
    # the search reaching 4.4 m of a 4.5 m range: no news; an unreachable range is still said as such
    for search, gate, said in (((15, 144), 0.0, []), ((0, 144), FB / 4.4, []), ((0, 144), FB / 0.5, None)):
        lst = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0, search=search,
                                                           gate_px=gate).obstacles
        assert ("range-unreachable" in lst.degraded) if said is None else lst.degraded == said, (search, gate)
        assert lst.range_m == (1.0, 4.5), (search, gate, lst.range_m)  # no reason said: the whole range


@pytest.mark.parametrize("method", ["layers", "seed"])
def test_a_vision_range_from_zero_keeps_everything_near_and_says_the_search_cannot_reach_it(method):
    """min_range_m 0 is a valid setting (ge=0): it once divided by zero on every map, so the service
    errored on each one and published nothing. Now the box is found, and every list says that no
    search measures down to 0 m."""
    d = scene([(250, 390, 2.0, 120)])
    b = ObstacleBuilder(SegmenterSettings(method=method, min_range_m=0.0, floor_removal=True))
    for k in range(2):
        lst = b.process(d, MODEL, t_s=k / 15, seq=k, stamp_ns=0, search=(0, 144)).obstacles
        # (the list looked at what the search measures: from f*B/143 px)
        assert "near-unmeasured" in lst.degraded
        assert lst.range_m == pytest.approx((FB / 143, 4.5 if method == "layers" else 3.0)), lst.range_m
    if method == "layers":
        assert _depths([type("D", (), {"position_m": o.position_m})() for o in lst.obstacles]) == [2.0]


def test_free_space_claims_no_clear_way_beside_a_list_that_cannot_vouch_for_its_view():
    """The grid marked free the floor from the image's bottom edge out, measured or not: beside a list
    saying near-unmeasured it told a planner the near floor was clear. Now a degraded (or stale) list's
    grid keeps what stands occupied and claims nothing free."""
    d = scene([(250, 390, 3.0, 80)])

    def cells(search, stale=False):
        fs = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0, search=search,
                                                          stale=stale).freespace
        return np.frombuffer(fs.cells, np.int8)

    trusted = cells((0, 144))
    assert (trusted == 0).sum() > 100 and (trusted == 100).any()
    for c in (cells((0, 32)), cells((0, 144), stale=True)):  # near-unmeasured; late input
        assert not (c == 0).any() and np.array_equal(c == 100, trusted == 100)


def test_walls_beside_the_way_filling_most_of_the_view_never_become_the_ground():
    """A corridor: walls 0.8 m to either side, parallel to the heading, cover more pixels than the
    floor between them; the ground is still the floor, from no mount and from a mount 50 % too high."""
    truth = Mount(1.0, 5.0)
    v, u = np.mgrid[0:MODEL.height, 0:MODEL.width].astype(np.float32)
    floor_d = floor_plane(truth).disparity(u, v)
    x = (u - MODEL.cx) / MODEL.focal_px  # a wall at lateral offset w is seen at depth w / |x|: d = B |x| f / w
    wall_d = MODEL.baseline_m * np.abs(x) * MODEL.focal_px / 0.8
    d = np.maximum(floor_d, wall_d).astype(np.float32)  # whichever is nearer along the ray
    d[d < FB / 8.0] = np.nan  # nothing beyond 8 m
    d += np.random.default_rng(0).normal(0, 0.08, d.shape).astype(np.float32)
    wall = np.isfinite(d) & (wall_d > floor_d)
    assert np.count_nonzero(wall) > np.count_nonzero(np.isfinite(d) & ~wall)  # more wall than floor in view
    for told in (None, Mount(1.5, 5.0)):
        g = _frame(d, SegmenterSettings(max_range_m=8.0), mount=told).ground
        assert g.source == "fitted" and abs(g.height_m - 1.0) < 0.05 and abs(g.pitch_deg - 5.0) < 1.0, (told, g)
        assert abs(g.roll_deg) < 1.0


def test_what_stands_behind_is_dropped_only_when_seen_through_the_nearer_object():
    """A region behind a nearer one and inside its box is seen through it (a car's window) when the
    nearer one frames it; a person standing behind a chair, seen above and beside its back, is not."""

    def region(pix, z):  # pix: (n, 2) working-resolution (x, y); step 1
        pix = np.asarray(pix, float)
        pts = np.stack([(pix[:, 0] - MODEL.cx) * z / MODEL.focal_px, (pix[:, 1] - MODEL.cy) * z / MODEL.focal_px,
                        np.full(len(pix), z)], 1)
        lo, hi = np.percentile(pts, [2, 98], axis=0)
        x0, y0 = pix.min(0).astype(int)
        x1, y1 = pix.max(0).astype(int) + 1
        return regions.Region(pts, lo, hi, (x0, y0, x1, y1), len(pix), len(pix), np.full(len(pix), FB / z))

    ys, xs = np.mgrid[100:300, 200:400]
    body = (ys >= 200) | (ys < 120) | (xs < 220) | (xs >= 380)  # a car: a window in its upper half
    car = region(np.stack([xs[body], ys[body]], 1), 3.0)
    ys, xs = np.mgrid[130:190, 240:360]
    behind = region(np.stack([xs.ravel(), ys.ravel()], 1), 8.0)
    assert regions.encloses(car, behind, MODEL, 1)
    assert len(regions.absorb_contained([car, behind], 0.12, MODEL, 1)) == 1
    ys, xs = np.mgrid[20:400, 100:400]
    # legs out at both sides, a seat across, its back reaching up on the right
    chair = ((ys > 200) & ((xs < 110) | (xs >= 390))) | ((ys > 200) & (ys < 220)) | (xs >= 300)
    chair = region(np.stack([xs[chair], ys[chair]], 1), 2.0)
    ys, xs = np.mgrid[20:180, 110:200]
    person = region(np.stack([xs.ravel(), ys.ravel()], 1), 3.2)
    assert not regions.encloses(chair, person, MODEL, 1)
    assert len(regions.absorb_contained([chair, person], 0.12, MODEL, 1)) == 2
    # seen between a person's legs, standing on the floor seen there (filled to it), its top seen: a
    # crate of its own; a table's back leg under its top, the top hiding its upper end: dropped
    ys, xs = np.mgrid[20:400, 200:400]
    walker = (ys < 200) | (xs < 260) | (xs >= 340)
    walker = region(np.stack([xs[walker], ys[walker]], 1), 2.6)
    ys, xs = np.mgrid[300:390, 270:330]
    crate = region(np.stack([xs.ravel(), ys.ravel()], 1), 3.4)
    assert regions.encloses(walker, crate, MODEL, 1)
    assert len(regions.absorb_contained([walker, crate], 0.12, MODEL, 1)) == 1  # no foot on the floor seen
    crate.filled = 40
    assert len(regions.absorb_contained([walker, crate], 0.12, MODEL, 1)) == 2
    ys, xs = np.mgrid[100:300, 100:500]
    table = (ys < 130) | (xs < 120) | (xs >= 480)
    table = region(np.stack([xs[table], ys[table]], 1), 2.0)
    ys, xs = np.mgrid[130:280, 300:310]
    leg = region(np.stack([xs.ravel(), ys.ravel()], 1), 2.5)
    leg.filled = 20
    assert len(regions.absorb_contained([table, leg], 0.12, MODEL, 1)) == 1
    # a back leg beside the front leg at the table's end, under its top (not framed by the table:
    # nothing of it to the leg's right), is under it all the same, also when the layer split cut it
    # from the table's group
    ys, xs = np.mgrid[100:300, 100:500]
    table = region(np.stack([xs[(ys < 130) | (xs >= 480)], ys[(ys < 130) | (xs >= 480)]], 1), 2.0)
    ys, xs = np.mgrid[130:280, 460:472]
    leg = region(np.stack([xs.ravel(), ys.ravel()], 1), 2.5)
    leg.filled = 20
    assert not regions.encloses(table, leg, MODEL, 1)
    assert len(regions.absorb_contained([table, leg], 0.12, MODEL, 1)) == 1
    table.groups = leg.groups = frozenset({7})
    assert len(regions.absorb_contained([table, leg], 0.12, MODEL, 1)) == 1


def test_a_small_thing_beyond_an_empty_stretch_of_depth_is_split_from_the_group_a_hand_is_not():
    """A group holding a person (2000 px at 3.3 m) and a table's back leg 0.5 m nearer (150 px: less
    than layer_min_area_m2 of surface) with no pixel at the depths between: two things. The same
    small part joined by pixels at every depth between (an arm held out to a hand) stays one."""
    cfg = SegmenterSettings()
    rng = np.random.default_rng(0)
    person = np.full(2000, FB / 3.3) + rng.normal(0, 0.1, 2000)
    leg = np.full(150, FB / 2.8) + rng.normal(0, 0.1, 150)

    def split(d):
        d = d.astype(np.float32)
        ys, xs = np.arange(d.size) // 40, np.arange(d.size) % 40
        lab, family = depth_split.split_layers(ys, xs, d, np.ones(d.size, np.int32), cfg, MODEL, 2)
        return np.unique(lab[lab > 0]).size

    assert split(np.concatenate([person, leg])) == 2
    arm = np.linspace(FB / 3.3, FB / 2.8, 60)
    assert split(np.concatenate([person, arm, leg])) == 1


# --- blank faces -----------------------------------------------------------------------------------

def blank_face(u0: int, u1: int, z_m: float, d: np.ndarray | None = None) -> np.ndarray:
    """A plain face standing on the floor at z_m over columns u0..u1, taller than the camera: block
    matching measures nothing of it (NaN from its foot to the image's top) and nothing behind it."""
    d = scene() if d is None else d.copy()
    fp = floor_plane(SCENE_MOUNT)
    col = (u0 + u1) // 2
    rows = np.nonzero(fp.disparity(np.float32(col), np.arange(MODEL.height, dtype=np.float32)) <= FB / z_m)[0]
    d[:int(rows.max()) + 1, u0:u1] = np.nan
    return d


def ahead_of(z_m: float) -> float:
    """How far ahead over the floor blank_face's face stands (its foot at camera depth z_m in the
    middle column): the camera looks 15 deg down, so an upright face's nearest point is this far."""
    pitch = np.radians(SCENE_MOUNT.pitch_deg)
    y = (SCENE_MOUNT.height_m - z_m * np.sin(pitch)) / np.cos(pitch)  # the foot: (0, y, z_m) on the floor
    return float(z_m * np.cos(pitch) - y * np.sin(pitch))


def test_a_plain_face_the_matcher_cannot_measure_is_an_obstacle_at_its_foot():
    """A cabinet with nothing inside to match: the floor seen up to its foot, nothing above, past the
    horizon. It is listed where it stands, with the confidence of what was measured of it (none)."""
    d = blank_face(200, 420, 2.2)
    lst = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0).obstacles
    assert len(lst.obstacles) == 1 and lst.degraded == [], lst.model_dump_json()
    o = lst.obstacles[0]
    assert abs(o.distance_m - ahead_of(2.2)) < 0.1 and o.confidence < 0.1 and o.size_m[1] > 0.8
    assert 190 <= o.bbox_px[0] <= 210 and 410 <= o.bbox_px[2] <= 430
    # the same map without the step (what the list said before: nothing, unflagged)
    off = ObstacleBuilder(SegmenterSettings(near_field_m=0)).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0)
    assert off.obstacles.obstacles == [] and off.obstacles.degraded == []


def test_a_plain_face_seen_from_a_pitched_camera_stands_upright_over_its_foot():
    """The scene's camera looks 15 deg down. A face as tall as the camera, its foot at camera depth
    2.2 m, stands 2.01 m ahead over the floor, and so do its upper rows: nearer along the optical axis
    than its foot. Its foot's disparity in every row leaned it back: listed 2.16 m ahead, its nearest
    point 2.19 m away."""
    d = blank_face(200, 420, 2.2)
    ahead = ahead_of(2.2)
    mount = MountSettings(height_m=SCENE_MOUNT.height_m, pitch_deg=SCENE_MOUNT.pitch_deg)
    lst = ObstacleBuilder(SegmenterSettings(), mount).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0).obstacles
    assert len(lst.obstacles) == 1, lst.model_dump_json()
    o = lst.obstacles[0]
    assert abs(o.position_base_m[0] - ahead) < 0.05 and abs(o.distance_m - ahead) < 0.05, \
        (ahead, o.position_base_m, o.distance_m)


def test_a_plain_face_with_a_matchers_noise_on_it_nearer_than_its_foot_is_still_found():
    """sgbm makes blobs of a plain wall's sensor noise, at any depth: measured 1-3 % of a wall across
    the view 2 m ahead, at 1.2-2.9 m. Blobs nearer than the face's foot, with the floor seen beyond
    them, do not stop the floor there, so they do not explain its end: the face is still found (before,
    the nearest thing standing in a column explained the floor's end wherever it stood)."""
    d = blank_face(200, 420, 2.2)
    for u0, v0, z in ((230, 60, 1.4), (300, 120, 1.6), (360, 40, 1.3), (400, 150, 1.5)):
        d[v0:v0 + 14, u0:u0 + 14] = FB / z  # 14 px blobs in the air, nearer than the face
    lst = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0).obstacles
    faces = [o for o in lst.obstacles if abs(o.distance_m - ahead_of(2.2)) < 0.15 and o.size_m[1] > 0.8]
    assert faces and sum(o.bbox_px[2] - o.bbox_px[0] for o in faces) > 150, \
        [(o.position_m, o.bbox_px) for o in lst.obstacles]


@pytest.mark.parametrize("case", ["floor patch", "narrow", "beyond within", "something measured behind"])
def test_what_is_not_a_blank_face_is_left_alone(case):
    """Unmeasured floor between seen floor, a gap narrower than 0.3 m, a stretch farther than
    near_field_m (a road fading under the sky) and a floor ending at something measured
    just behind it: no obstacle is made of them."""
    cfg = SegmenterSettings()
    if case == "floor patch":  # a smooth stretch of floor from 2 to 3 m, floor seen again beyond it
        d = scene()
        fp = floor_plane(SCENE_MOUNT)
        v, u = np.mgrid[0:MODEL.height, 0:MODEL.width].astype(np.float32)
        fd = fp.disparity(u, v)
        d[(fd < FB / 2.0) & (fd > FB / 3.0) & (u > 200) & (u < 420)] = np.nan
    elif case == "narrow":
        d = blank_face(300, 320, 2.2)  # 20 px at 2.2 m: 6.6 cm
    elif case == "beyond within":
        d = blank_face(200, 420, 3.0)
        cfg = SegmenterSettings(near_field_m=2.5)
    else:
        d = blank_face(200, 420, 2.2, scene([(200, 420, 2.6, 200)]))  # the box behind shows above the blank
        d[:150, 200:420] = FB / 2.6
    lst = ObstacleBuilder(cfg).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0).obstacles
    # (the box standing behind at 2.6 m is an obstacle of its own)
    made = [o for o in lst.obstacles if o.position_m[2] < (2.5 if case == "something measured behind" else 4.5)]
    assert made == [], [(o.position_m, o.bbox_px) for o in lst.obstacles]


def low_face(top_edge_disparity: float | None, z_m: float = 2.2, height_m: float = 0.5, u0: int = 200,
             u1: int = 420, seed_: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A plain box height_m tall standing at z_m over columns u0..u1, as dense gives it: the floor
    beyond it in view above it; inside it nothing but a few doubted matches (confidence 150, under
    min_confidence) scattered 1 px around its depth; its top edge a doubted row at
    top_edge_disparity (None: no top edge). -> (disparity, confidence)."""
    rng = np.random.default_rng(seed_)
    d = scene()
    conf = np.full(d.shape, 255, np.uint8)
    fp = floor_plane(SCENE_MOUNT)
    col = (u0 + u1) // 2
    rows = np.arange(MODEL.height, dtype=np.float32)
    foot = int(np.nonzero(fp.disparity(np.float32(col), rows) <= FB / z_m)[0].max())
    top = foot - int(round(height_m * MODEL.focal_px / z_m))  # a vertical face: its height over z in pixels
    d[top:foot + 1, u0:u1] = np.nan
    conf[top:foot + 1, u0:u1] = 20  # dense's fill
    inside = rng.random((foot + 1 - top, u1 - u0)) < 0.03
    d[top:foot + 1, u0:u1][inside] = FB / z_m + rng.normal(0, 1.0, int(inside.sum()))
    conf[top:foot + 1, u0:u1][inside] = 150
    if top_edge_disparity is not None:
        d[top:top + 2, u0:u1] = top_edge_disparity
        conf[top:top + 2, u0:u1] = 150
    return d, conf


def test_a_plain_face_lower_than_the_camera_is_an_obstacle_by_its_doubted_top_edge():
    """dense gives a plain box 0.5 m high what it gives every depth edge, a low confidence: the
    segmenter sets its pixels aside and sees floor up to its foot and again beyond it. The doubted
    matches inside it and along its top, at the foot's depth, make it an obstacle there, as tall as
    its top edge; before, the list was empty and unflagged."""
    d, conf = low_face(FB / 2.2)
    lst = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0,
                                                       confidence=conf).obstacles
    assert len(lst.obstacles) == 1 and lst.degraded == [], lst.model_dump_json()
    o = lst.obstacles[0]
    assert abs(o.position_m[2] - 2.2) < 0.15 and 0.35 < o.size_m[1] < 0.65, o
    assert 190 <= o.bbox_px[0] <= 210 and 410 <= o.bbox_px[2] <= 430


def test_a_plain_low_face_behind_a_patch_of_floor_the_matcher_missed_is_still_found():
    """A dark rug 1.85-2.35 m ahead, in front of a plain box at 3 m: the matcher measures nothing of
    it, a stretch without floor tall enough to hide a thing min_height_m tall, the floor seen beyond it
    up to the box. The face's foot is looked for at the column's lowest such stretches, not the lowest
    alone: that was the rug's, above which nothing stands at its depth, and the box was in no list,
    unflagged."""
    d, conf = low_face(FB / 3.0, z_m=3.0)
    fp = floor_plane(SCENE_MOUNT)
    rows = np.arange(MODEL.height, dtype=np.float32)
    near, far = (int(np.nonzero(fp.disparity(np.float32(310), rows) <= FB / z)[0].max()) for z in (1.85, 2.35))
    d[far:near, 150:470] = np.nan
    lst = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0,
                                                       confidence=conf).obstacles
    faces = [o for o in lst.obstacles if abs(o.position_m[2] - 3.0) < 0.2]
    assert len(faces) == 1 and faces[0].bbox_px[2] - faces[0].bbox_px[0] > 180, lst.model_dump_json()


@pytest.mark.parametrize("case", ["no top edge", "edge at the floor beyond", "too low"])
def test_an_unmeasured_stretch_of_floor_is_no_low_face(case):
    """What the rule must not take for a low face: a stretch with no top edge measured at all (dense
    saw nothing to go by: a patch of floor looks the same), one whose edge is at the depth of the floor
    beyond it (a plain mat ends there), and a face under min_height_m (0.2 m)."""
    if case == "no top edge":
        d, conf = low_face(None)
    elif case == "edge at the floor beyond":
        d, conf = low_face(FB / 3.2)
    else:
        d, conf = low_face(FB / 2.2, height_m=0.12)
    lst = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0,
                                                       confidence=conf).obstacles
    assert [o for o in lst.obstacles if o.position_m[2] < 4.5] == [], lst.model_dump_json()


def outlined_face(sliver_m: float | None, z_m: float = 2.2, height_m: float = 0.8, u0: int = 200,
                  u1: int = 420) -> np.ndarray:
    """A plain cabinet height_m tall at z_m over columns u0..u1 as block matching gives it: nothing
    measured inside; above it the floor beyond, whose texture its top edge takes; its left side
    against what is beside it measured at its depth, sliver_m tall (None: not at all)."""
    d = scene()
    fp = floor_plane(SCENE_MOUNT)
    rows = np.arange(MODEL.height, dtype=np.float32)
    foot = int(np.nonzero(fp.disparity(np.float32((u0 + u1) // 2), rows) <= FB / z_m)[0].max())
    d[foot - int(round(height_m * MODEL.focal_px / z_m)):foot + 1, u0:u1] = np.nan
    if sliver_m is not None:
        d[foot - int(round(sliver_m * MODEL.focal_px / z_m)):foot + 1, u0 - 8:u0] = FB / z_m
    return d


def test_a_plain_face_whose_top_edge_takes_the_depth_beyond_is_found_by_its_outline():
    """Block matching measures no top edge of a plain cabinet (the edge takes the depth of the
    textured floor or wall beyond it) but measures its side: the list held a sliver 8 px wide at its
    left edge, 0.4 m off the cabinet's centre. A run of floor stops at one depth beside such a sliver,
    plain up to its height, is one face: the obstacle spans the cabinet, as tall as the sliver."""
    for sliver_m in (0.8, 0.4):
        lst = ObstacleBuilder(SegmenterSettings()).process(outlined_face(sliver_m), MODEL, t_s=0.0, seq=0,
                                                           stamp_ns=0).obstacles
        near = [o for o in lst.obstacles if o.position_m[2] < 4.5]
        assert len(near) == 1 and lst.degraded == [], lst.model_dump_json()
        o = near[0]
        assert abs(o.position_m[2] - 2.2) < 0.15 and abs(o.size_m[1] - sliver_m) < 0.15, o
        assert 185 <= o.bbox_px[0] <= 200 and 410 <= o.bbox_px[2] <= 430, o


@pytest.mark.parametrize("case", ["no outline", "outline too low", "floor patch beside a pole"])
def test_a_sliver_beside_an_unmeasured_stretch_makes_no_face_of_what_is_not_one(case):
    """The outline rule's negatives: the same cabinet without its side measured (nothing to go by:
    a patch of floor looks the same), a side under min_height_m, and a plain stretch of floor from 2
    to 3 m whose near end meets a pole 1 m tall: the floor beyond the stretch is measured within the
    pole's height, so the stretch is no face (the pole stays an obstacle of its own)."""
    if case == "no outline":
        d = outlined_face(None)
    elif case == "outline too low":
        d = outlined_face(0.12)
    else:
        d = scene()
        fp = floor_plane(SCENE_MOUNT)
        v, u = np.mgrid[0:MODEL.height, 0:MODEL.width].astype(np.float32)
        fd = fp.disparity(u, v)
        d[(fd < FB / 2.0) & (fd > FB / 3.0) & (u > 200) & (u < 420)] = np.nan
        foot = int(np.nonzero(fp.disparity(np.float32(200), v[:, 0]) <= FB / 2.0)[0].max())
        d[foot - int(round(1.0 * MODEL.focal_px / 2.0)):foot + 1, 192:200] = FB / 2.0
    lst = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0).obstacles
    assert [o for o in lst.obstacles if o.position_m[2] < 4.5 and o.bbox_px[2] > 230] == [], lst.model_dump_json()


def crate_below(side_m: float | None, resume_m: float = 3.0, z_m: float = 1.3, u0: int = 150,
                u1: int = 400, post_m: float | None = None) -> tuple[np.ndarray, float]:
    """A plain crate z_m ahead over columns u0..u1, its foot below the image, as block matching gives
    it: nothing measured from the image's bottom edge up to the floor seen again beyond its top (the
    floor's row at resume_m); its right side against the floor beside it measured at its depth,
    side_m tall from the bottom edge (None: not at all), and above it a post post_m away (None: none).
    -> (disparity, the height from the bottom edge to the floor seen again, m at z_m)."""
    d = scene()
    fp = floor_plane(SCENE_MOUNT)
    rows = np.arange(MODEL.height, dtype=np.float32)
    resume = int(np.nonzero(fp.disparity(np.float32((u0 + u1) // 2), rows) <= FB / resume_m)[0].max())
    d[resume:, u0:u1] = np.nan
    if side_m is not None:
        top = max(0, MODEL.height - int(round(side_m * MODEL.focal_px / z_m)))
        d[top:, u1:u1 + 8] = FB / z_m
        if post_m is not None:  # above the side: a post farther away, standing behind the crate
            d[max(0, top - 80):top, u1:u1 + 8] = FB / post_m
    return d, (MODEL.height - resume) * z_m / MODEL.focal_px


def test_a_plain_crate_whose_foot_is_below_the_image_is_found_by_its_side():
    """The low-faces crate as block matching gives it (its foot just below the image, its faces and
    top unmeasured, the floor seen again beyond it): the list held a sliver 8 px wide at its right
    side, too narrow to list, or nothing. The sliver stands nearer than the floor at the bottom edge
    and the floor is seen again near its top: the stretch beside it is one face at its depth. A post
    2 m away seen above the side is no part of it (farther than the floor at the bottom edge)."""
    _, visible_m = crate_below(None)
    # the side measured up to the floor seen again, or short of it; with the post above it
    for side_m, post_m in ((visible_m, None), (0.65 * visible_m, None), (visible_m, 2.0)):
        d, _ = crate_below(side_m, post_m=post_m)
        lst = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0).obstacles
        near = [o for o in lst.obstacles if o.position_m[2] < 1.8]
        assert len(near) == 1 and lst.degraded == [], lst.model_dump_json()
        o = near[0]
        assert abs(o.position_m[2] - 1.3) < 0.1, o
        assert o.bbox_px[0] <= 160 and o.bbox_px[2] >= 400 and o.bbox_px[3] == MODEL.height, o


def test_the_band_without_a_partner_in_the_right_image_is_no_plain_face():
    """Left of x = d nothing at disparity d has a partner in the right image, so a matcher without a
    fixed blind band (dense) leaves a strip as wide as the baseline unmeasured beside anything near
    the image's left side. With the street rig's 0.57 m baseline that strip beside a railing 4 m away
    passed for a plain face (karlsruhe, dense: every few frames). Here: a 0.5 m baseline, a post 1.2 m
    away (nearer than the floor at the bottom edge) reaching the bottom edge, the floor measured elsewhere."""
    wide = camera.RectifiedModel(640, 480, 665.0, 320.0, 240.0, 0.5)
    fb = wide.focal_px * wide.baseline_m
    fp = FloorPlane.from_normal(SCENE_MOUNT.down_camera, SCENE_MOUNT.height_m, wide.focal_px, wide.cx, wide.cy,
                                wide.baseline_m)
    v, u = np.mgrid[0:wide.height, 0:wide.width].astype(np.float32)
    d = np.maximum(fp.disparity(u, v), fb / 5.0).astype(np.float32)
    d += np.random.default_rng(0).normal(0, 0.08, d.shape).astype(np.float32)
    band = int(fb / 1.2)  # 277 px: 0.5 m at 1.2 m
    d[:, band:band + 10] = np.where(v[:, band:band + 10] > 200, fb / 1.2, d[:, band:band + 10])
    d[:, :band] = np.where(d[:, :band] > fb / 5.0 + 1, np.nan, d[:, :band])  # near pixels without a partner
    lst = ObstacleBuilder(SegmenterSettings()).process(d, wide, t_s=0.0, seq=0, stamp_ns=0).obstacles
    assert [o for o in lst.obstacles if o.position_m[2] < 3.0 and o.bbox_px[0] < band - 40] == [], lst.model_dump_json()


@pytest.mark.parametrize("case", ["no side", "pole beside smooth road", "low thing under a long stretch",
                                  "sliver off the bottom"])
def test_an_unmeasured_stretch_at_the_bottom_edge_is_no_face_without_a_side_that_says_so(case):
    """A smooth road leaves the floor unmeasured from the image's bottom edge in most columns
    (karlsruhe, bm), so the stretch alone is no face: not without a side measured; not beside a pole
    1.5 m tall (the road beyond the stretch is measured within its height); not beside a thing 0.25 m
    tall under a stretch that runs on to the floor at 4 m (the floor is seen again far above its top);
    not beside a sliver that ends 0.25 m above the bottom edge (its foot is in view: rules 1 and 2's
    case)."""
    if case == "no side":
        d, _ = crate_below(None)
    elif case == "pole beside smooth road":
        d, _ = crate_below(1.5)
    elif case == "low thing under a long stretch":
        d, _ = crate_below(0.25, resume_m=4.0)
    else:  # from the floor seen again down to 0.25 m above the bottom edge
        d, visible_m = crate_below(None, resume_m=4.0)
        d[MODEL.height - int(visible_m * MODEL.focal_px / 1.3):MODEL.height - int(0.25 * MODEL.focal_px / 1.3),
          400:408] = FB / 1.3
    lst = ObstacleBuilder(SegmenterSettings()).process(d, MODEL, t_s=0.0, seq=0, stamp_ns=0).obstacles
    assert [o for o in lst.obstacles if o.bbox_px[0] < 300 and o.bbox_px[2] > 250] == [], lst.model_dump_json()


def test_free_space_does_not_run_through_a_plain_crate_the_matcher_left_unmeasured():
    """The low-faces scene, rendered (bm): a plain crate 0.35 m high 1.6 m ahead, its foot below the
    image. Block matching measures nothing of its faces, and sees the floor beyond it. Counting the
    floor between points seen as seen made the crate free space; within near_field_m a stretch tall
    enough to hide min_height_m is no longer bridged. Beside the crate the floor stays free."""
    import sim
    from cores.matching.config import MatcherConfig
    from cores.pipeline import Pipeline
    from sim.scene import Scene

    def free_cells(**settings):
        rig = camera.load_raw_rig("lifecam-studio")
        pipe = Pipeline(rig, MatcherConfig(method="bm"), SegmenterSettings(**settings))
        world = sim.SyntheticWorld(Scene.builtin("low-faces"), rig, pipe.rectifier.rectification, seed=0)
        g = pipe.process(*world.render(0.0), t_s=0.0, seq=0).result.freespace
        cells = np.frombuffer(g.cells, np.int8).reshape(g.height, g.width)
        xs = g.origin_m[0] + (np.arange(g.width) + 0.5) * g.resolution_m
        ys = g.origin_m[1] + (np.arange(g.height) + 0.5) * g.resolution_m

        def free(x0, x1, y0, y1):
            return int((cells[np.ix_((ys > y0) & (ys < y1), (xs > x0) & (xs < x1))] == 0).sum())
        return free(1.65, 1.95, 0.25, 0.65), free(1.65, 2.5, -0.6, -0.2)  # the crate's top, the floor right of it

    crate, beside = free_cells()
    assert crate == 0 and beside > 10, (crate, beside)
    crate_before, _ = free_cells(near_field_m=0)  # every stretch bridged, as before
    assert crate_before > 10


# --- drops -----------------------------------------------------------------------------------------

def curb(depth_m: float, at_m: float = 2.5, frames: int = 3, **settings):
    """The rendered scene of a curb: the floor beyond world x = at_m lies depth_m lower (camera 1 m up,
    15 deg down, wall at 5 m, a box on the near side), through the pipeline the services run (bm).
    -> the last pair's FrameResult and the x (base, m) of the farthest free cell."""
    import sim
    from cores.matching.config import MatcherConfig
    from cores.pipeline import Pipeline
    from sim.scene import Scene

    scene = Scene.from_dict({"name": "curb", "camera_height_m": 1.0, "camera_pitch_deg": 15.0,
                             "floor_drop": {"x_m": at_m, "depth_m": depth_m},
                             "objects": [{"name": "box", "size": [0.4, 0.5, 0.3], "position": [1.8, 0.6],
                                          "texture_seed": 5}]})
    rig = camera.load_raw_rig("lifecam-studio")
    pipe = Pipeline(rig, MatcherConfig(method="bm"), SegmenterSettings(**settings))
    world = sim.SyntheticWorld(scene, rig, pipe.rectifier.rectification, seed=0)
    for k in range(frames):
        r = pipe.process(*world.render(k / 15), t_s=k / 15, seq=k).result
    g = r.freespace
    cells = np.frombuffer(g.cells, np.int8).reshape(g.height, g.width)
    xs = g.origin_m[0] + (np.arange(g.width) + 0.5) * g.resolution_m
    free = xs[(cells == 0).any(0)]
    return r, (float(free.max()) if free.size else 0.0), cells, xs


def test_floor_falling_away_is_an_obstacle_where_the_robot_would_roll_off_and_no_free_space():
    """A curb 0.2 m down 2.5 m ahead (rendered): the lower floor beyond it counted as floor seen (down
    to 0.42 m below), so the free space ran on past the edge and the list held the box alone. Now
    an obstacle lies on the ground over the drop, from its edge, and nothing beyond the edge is free."""
    r, free_to, cells, xs = curb(0.2)
    assert r.obstacles.degraded == []  # a list that vouches for its view, and its free space
    drops = [o for o in r.obstacles.obstacles if o.position_base_m[0] > 2.2]
    assert len(drops) == 1, r.obstacles.model_dump_json()
    o = drops[0]
    assert 2.4 < o.position_base_m[0] - o.size_m[2] / 2 < 2.7 and o.size_m[0] > 1.0
    assert abs(o.position_base_m[2]) < 0.15  # on the ground, over the hole
    assert 2.0 < free_to < 2.6 and (cells[:, (xs > 2.6) & (xs < 3.0)] == 100).any()
    # without looking for drops (what the list said before): the box alone, and free space past the edge
    off, free_off, _, _ = curb(0.2, near_field_m=0)
    assert off.obstacles.degraded == [] and free_off > 3.0
    assert [o.position_base_m[0] < 2.2 for o in off.obstacles.obstacles] == [True]


@pytest.mark.parametrize("depth_m, near_field_m", [(0.05, 6.0), (0.3, 2.0)])
def test_a_floor_within_the_noise_or_a_drop_beyond_the_near_field_is_no_obstacle(depth_m, near_field_m):
    """5 cm lower is a floor's unevenness and the matcher's noise; beyond near_field_m a road's own
    camber puts it as low (the street: hundreds of pixels 0.15 m below at 13-20 m)."""
    r, _, _, _ = curb(depth_m, near_field_m=near_field_m)
    assert [o.position_base_m[0] < 2.2 for o in r.obstacles.obstacles] == [True], r.obstacles.model_dump_json()
