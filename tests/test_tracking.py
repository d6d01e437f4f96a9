"""Tracker: stable ids, velocities, short occlusions bridged, long ones not, no swaps on crossing."""
from __future__ import annotations

import numpy as np

from cores.segmentation.tracking import Tracker


def _walk(p0, v, t):
    return np.asarray(p0, float) + np.asarray(v, float) * t


def test_ids_stable_and_velocity_converges_with_noise():
    rng = np.random.default_rng(0)
    tr = Tracker()
    ids = set()
    for k in range(40):
        t = k / 15
        p = _walk([1.0, 0.2, 3.0], [-0.5, 0.0, -0.6], t) + rng.normal(0, 0.01, 3)
        (track,) = tr.update([p], t)
        ids.add(track.id)
    assert ids == {1}
    assert np.allclose(track.velocity, [-0.5, 0.0, -0.6], atol=0.12), track.velocity


def test_static_objects_keep_ids_and_near_zero_velocity():
    rng = np.random.default_rng(1)
    tr = Tracker()
    a, b = np.array([-0.4, 0.2, 1.8]), np.array([0.5, 0.0, 2.4])
    for k in range(30):
        ta, tb = tr.update([b + rng.normal(0, 0.01, 3), a + rng.normal(0, 0.01, 3)] if k % 2 else
                           [a + rng.normal(0, 0.01, 3), b + rng.normal(0, 0.01, 3)], k / 30)
        if k % 2:
            ta, tb = tb, ta
        assert (ta.id, tb.id) == (1, 2)
    assert np.linalg.norm(ta.velocity) < 0.1 and np.linalg.norm(tb.velocity) < 0.1


def test_short_occlusion_keeps_the_id_long_one_does_not():
    tr = Tracker(timeout_s=1.0)
    v = np.array([0.8, 0.0, 0.0])
    for k in range(10):
        (first,) = tr.update([_walk([0, 0, 2.5], v, k / 15)], k / 15)
    for k in range(10, 22):  # 0.8 s unseen (behind something), still walking
        tr.update([], k / 15)
    (back,) = tr.update([_walk([0, 0, 2.5], v, 22 / 15)], 22 / 15)
    assert back.id == first.id
    for k in range(23, 45):  # 1.4 s unseen: dropped
        tr.update([], k / 15)
    (new,) = tr.update([_walk([0, 0, 2.5], v, 45 / 15)], 45 / 15)
    assert new.id != first.id
    assert all(t.id != first.id for t in tr.tracks)


def test_crossing_objects_do_not_swap_ids():
    tr = Tracker()
    ids = None
    for k in range(30):
        t = k / 15
        a = _walk([-1.0, 0.0, 2.5], [1.0, 0.0, 0.0], t)
        b = _walk([1.0, 0.0, 2.9], [-1.0, 0.0, 0.0], t)
        ta, tb = tr.update([a, b], t)
        if ids is None:
            ids = (ta.id, tb.id)
        assert (ta.id, tb.id) == ids, k


def test_new_object_far_from_tracks_gets_a_new_id():
    tr = Tracker(gate_m=0.6)
    (a,) = tr.update([np.array([0.0, 0.0, 2.0])], 0.0)
    a2, b = tr.update([np.array([0.0, 0.0, 2.0]), np.array([1.5, 0.0, 2.0])], 0.1)
    assert a2.id == a.id and b.id != a.id
    assert tr.update([], 0.2) == []


def test_a_track_is_confirmed_after_m_of_the_last_n_frames_and_a_fluke_never():
    tr = Tracker(confirm_m=3, confirm_n=5)
    a, fluke = np.array([0.0, 0.0, 2.0]), np.array([1.5, 0.0, 3.0])
    seen = [True, False, True, False, True, True]
    states = []
    for k, s in enumerate(seen):
        tracks = tr.update(([a] if s else []) + ([fluke] if k == 0 else []), k / 15)
        if s:
            states.append(tracks[0].confirmed)
    assert states == [False, False, True, True]  # the 3rd sighting within 5 frames confirms
    assert not any(t.confirmed for t in tr.tracks if t.id != 1)


def test_move_carries_tracks_by_the_robots_own_motion():
    tr = Tracker()
    tr.ground_plane = True
    box = np.array([[1.8, -0.2], [2.2, 0.2]])
    (t0,) = tr.update([np.array([2.0, 0.0, 0.3])], 0.0, [box])
    # the robot drives 0.8 m forward and turns 90 degrees left: the object is now 1.2 m to its right
    R = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # rotation by -90 deg about z
    tr.move(R, -R @ np.array([0.8, 0.0, 0.0]))
    assert np.allclose(tr.tracks[0].position, [0.0, -1.2, 0.3])
    assert np.allclose(tr.tracks[0].box, [[-0.2, -1.4], [0.2, -1.0]])
    (t1,) = tr.update([np.array([0.0, -1.2, 0.3])], 0.1, [np.array([[-0.2, -1.4], [0.2, -1.0]])])
    assert t1.id == t0.id and np.linalg.norm(t1.velocity) < 1e-6


def _fp(x0, x1, y0, y1):
    return np.array([[x0, y0], [x1, y1]], float)


def test_a_fence_seen_with_more_or_less_of_it_keeps_its_id_and_stands_still():
    """In the base frame, by footprints: a fence along the road 6 m long is seen next as a 2.5 m
    stretch at one end (its centroid 1.75 m away), then whole again. It is the same thing: its id
    stays and the sliding centroid is not taken for motion; a post 1 m beyond the fence's end is
    another thing."""
    tr = Tracker()
    tr.ground_plane = True
    whole = (np.array([7.0, 3.0, 0.6]), _fp(4.0, 10.0, 2.9, 3.1))
    part = (np.array([5.25, 3.0, 0.6]), _fp(4.0, 6.5, 2.9, 3.1))
    post = (np.array([11.0, 3.0, 0.6]), _fp(10.9, 11.1, 2.9, 3.1))
    ids = set()
    for k, (p, box) in enumerate([whole, whole, part, whole, part, part, whole]):
        seen = tr.update([p, post[0]] if k >= 3 else [p], k / 10, [box, post[1]] if k >= 3 else [box])
        ids.add(seen[0].id)
        if k >= 3:
            assert seen[1].id != seen[0].id
    assert len(ids) == 1
    assert np.linalg.norm(tr.tracks[0].velocity) < 0.5, tr.tracks[0].velocity


def test_a_new_track_starts_still_and_a_walker_is_picked_up_by_the_gain():
    """Two centroids 0.1 s apart, 5 cm apart (the noise of a centroid 3 m away) are no speed of
    0.5 m/s: a new track starts at zero velocity and the second sighting pulls it by the Kalman
    gain only part of the way; a person walking at 1 m/s is measured within a second."""
    tr = Tracker()
    (a,) = tr.update([np.array([0.0, 0.0, 3.0])], 0.0)
    (a,) = tr.update([np.array([0.05, 0.0, 3.0])], 0.1)
    assert np.linalg.norm(a.velocity) < 0.4
    tr = Tracker()
    for k in range(12):
        (w,) = tr.update([np.array([-1.0 + 0.1 * k, 0.0, 3.0])], k / 10)
    assert abs(w.velocity[0] - 1.0) < 0.2, w.velocity
