"""The four services as separate OS processes talking Zenoh over loopback, started the way a user
starts them (`ballbot-vision up`), checked against the synthetic scene's ground truth."""
from __future__ import annotations

import importlib
import json
import re
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import Collector, cli, pid_alive

from common import codec
from common.keys import TOPICS, topic
from common.messages import FreeSpace, GroundTruth, Image, ObstacleList, Odometry, ServiceStats, StereoFrame
from common.supervisor import SERVICES

pytestmark = pytest.mark.system


def table_disagrees(service: str, subscribes: list[str], publishes: list[str]) -> list[str]:
    """Where a service's real subscriptions and publications disagree with common/keys.py's table."""
    out = []
    for name in publishes:
        producers = TOPICS[name].producer.split(", ")
        if service not in producers and "every service" not in producers:
            out.append(f"{service} publishes {name}, whose producer is {TOPICS[name].producer}")
    for name in subscribes:
        consumers = TOPICS[name].consumers
        if service not in consumers and "anyone" not in consumers:
            out.append(f"{service} subscribes to {name}, whose consumers are {', '.join(consumers)}")
    return out


def match_truth(obstacles, truth: GroundTruth):
    """Pair every true obstacle with the nearest detection (3D); returns (truth, detection|None)."""
    out = []
    for t in truth.obstacles:
        c = np.array(t.visible_centroid_m)
        best = min(obstacles, key=lambda o: np.linalg.norm(np.array(o.position_m) - c), default=None)
        out.append((t, best))
    return out


def test_up_publishes_obstacles_matching_ground_truth_and_stops_cleanly(up):
    truths = Collector(GroundTruth)
    with up.session() as s:
        s.declare_subscriber(topic("truth").key(up.robot_id), truths)
        # what a user types in a second shell
        watch = subprocess.run(cli("watch", "--connect", up.endpoint, "--count", "6", "--json", "--timeout", "60"),
                               capture_output=True, text=True, timeout=120)
        assert watch.returncode == 0, watch.stderr
        lists = [ObstacleList.model_validate(json.loads(line)) for line in watch.stdout.splitlines()]
        assert len(lists) == 6
        assert truths.wait_for(lambda items: {t.seq for t in items} >= {m.seq for m in lists}, 30)
        by_seq = {t.seq: t for t in truths.items}
        for msg in lists:
            truth = by_seq[msg.seq]
            assert len(msg.obstacles) == len(truth.obstacles), msg.model_dump_json()
            for t, o in match_truth(msg.obstacles, truth):
                err = np.linalg.norm(np.array(o.position_m) - np.array(t.visible_centroid_m))
                dist = np.linalg.norm(t.visible_centroid_m)
                assert err <= 0.05 * dist, f"{t.name}: {o.position_m} vs {t.visible_centroid_m} ({err:.3f} m)"
        # A running pipeline is fresh: three fresh lists in a row. The first lists may be stale
        # while the processes warm up, and on a busy machine for a while longer: wait for them
        # (generous deadline) rather than expect them among the first six.
        obstacles = Collector(ObstacleList)
        s.declare_subscriber(topic("obstacles").key(up.robot_id), obstacles)

        fresh: list = []

        def three_fresh(items) -> bool:
            if len(items) >= 3 and not any(m.stale for m in items[-3:]):
                fresh[:] = items[-3:]
            return bool(fresh)

        assert obstacles.wait_for(three_fresh, 120), \
            f"no three fresh lists in a row: {[(m.seq, m.stale) for m in obstacles.items[-10:]]}"
        ids = [sorted(o.id for o in m.obstacles) for m in fresh]
        assert ids[0] == ids[-1], "track ids must be stable on a static scene"
        # no mount is configured: the ground is estimated from the disparity (the scene's camera: 1 m, 15 deg)
        g = fresh[-1].ground
        assert g.source == "fitted" and abs(g.height_m - 1.0) < 0.05 and abs(g.pitch_deg - 15.0) < 1.0, g
        # free space next to the obstacle list, on the public key a planner subscribes to
        grids = Collector(FreeSpace)
        s.declare_subscriber("ballbot/freespace/**", grids)
        assert grids.wait_for(lambda items: len(items) >= 2, 60), "no free-space grid published"
        cells = np.frombuffer(grids.items[-1].cells, np.int8)
        assert (cells == 0).sum() > 100 and (cells == 100).any() and grids.items[-1].ground.source == "fitted"
        # odometry (the robot standing still) turns velocities into velocities over the ground
        odo = s.declare_publisher(topic("odometry").key(up.robot_id))

        def over_ground(items) -> bool:
            odo.put(codec.encode(Odometry(robot_id=up.robot_id, seq=0, stamp_ns=time.time_ns(),
                                          linear_mps=(0.0, 0.0, 0.0), source="test")))
            return bool(items) and items[-1].velocity_reference == "ground"
        assert obstacles.wait_for(over_ground, 60), "odometry was not used"

        code, doc, _ = status_of(up)
        # 0: healthy; 3: something degraded (a loaded machine may make a list stale): named in the summary
        assert code == (0 if doc["pipeline"]["health"] == "ok" else 3), doc["pipeline"]
        names = {i["name"] for i in doc["instances"]}
        assert {"capture", "rectify", "dispatcher", "segmenter"} <= names
        assert all(i["rate_hz"] > 0 for i in doc["instances"] if i["service"] != "router")
        assert all(i["health"] in ("ok", "starting") for i in doc["instances"]), doc
        dispatcher = next(i for i in doc["instances"] if i["name"] == "dispatcher")
        assert dispatcher["status"].startswith("ok"), "one host computing onboard is the normal case"
        assert all(i["in_Bps"] > 0 for i in doc["instances"] if i["name"] in ("rectify", "dispatcher", "segmenter"))
        # what each process really subscribes to and publishes (its Node records it) is what the key
        # table says it does
        uses = {i["service"]: i for i in doc["instances"]}
        assert set(uses["segmenter"]["subscribes"]) >= {"disparity", "odometry"}
        assert set(uses["segmenter"]["publishes"]) >= {"obstacles", "freespace"}
        for inst in doc["instances"]:
            assert not table_disagrees(inst["service"], inst["subscribes"], inst["publishes"]), inst
            # and what its module declares in its first lines (SUBSCRIBES / PUBLISHES) covers it
            if inst["service"] in SERVICES:
                m = importlib.import_module(SERVICES[inst["service"]][0])
                assert set(inst["subscribes"]) <= set(m.SUBSCRIBES), (inst["service"], inst["subscribes"])
                assert set(inst["publishes"]) - {"stats", "alive"} <= set(m.PUBLISHES), \
                    (inst["service"], inst["publishes"])

    pids = up.child_pids()
    assert set(pids) == {"router", "capture", "rectify", "disparity", "segmenter"}
    took = up.stop()
    assert up.proc.returncode == 0
    print(f"up stopped in {took:.2f} s")
    assert "killing it" not in up.log_path.read_text(), "a service had to be killed: it did not stop on SIGTERM"
    deadline = time.monotonic() + 5
    while any(pid_alive(p) for p in pids.values()) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [n for n, p in pids.items() if pid_alive(p)], "orphan service processes"


def _put_bad_inputs(session, robot_id: str, key: str) -> None:
    pub = session.declare_publisher(key)
    pub.put(b"\x00garbage\xff" * 10)
    good = StereoFrame(robot_id=robot_id, seq=10**9, stamp_ns=time.time_ns(),
                       left=Image(width=640, height=480, data=b"\x00" * 640 * 480),
                       right=Image(width=640, height=480, data=b"\x00" * 640 * 480))
    doc = good.model_dump()
    doc["schema_version"] = 99
    import msgpack
    pub.put(msgpack.packb(doc, use_bin_type=True))
    wrong_size = good.model_copy(update={"left": Image(width=320, height=240, data=b"\x00" * 100)})
    pub.put(codec.encode(wrong_size))
    small = good.model_copy(update={"left": Image(width=320, height=240, data=b"\x00" * 320 * 240),
                                    "right": Image(width=320, height=240, data=b"\x00" * 320 * 240)})
    pub.put(codec.encode(small))
    pub.undeclare()


def test_bad_messages_are_logged_counted_and_dropped(up):
    stats = Collector(ServiceStats)
    obstacles = Collector(ObstacleList)
    with up.session() as s:
        s.declare_subscriber(topic("stats").pattern(up.robot_id), stats)
        s.declare_subscriber(topic("obstacles").key(up.robot_id), obstacles)
        assert obstacles.wait_for(lambda items: len(items) >= 2, 60), "pipeline did not start"
        inputs = {"rectify": "frames_raw", "disparity": "frames_rect", "segmenter": "disparity"}

        def counted(items):
            latest = {}
            for st in items:
                latest[st.service] = st
            # the segmenter takes only maps signed by `up`'s dispatcher: anyone else's are refused
            # before decoding, counted as unsigned
            return {svc for svc in inputs
                    if svc in latest and latest[svc].decode_errors + latest[svc].errors
                    + latest[svc].extra.get("in_disparity_unsigned", 0) > 0}

        # Inputs are newest-wins: a real frame may overwrite a bad one before it is read, so keep
        # offering bad payloads until each service has counted some.
        deadline = time.monotonic() + 60
        while counted(list(stats.items)) != set(inputs) and time.monotonic() < deadline:
            for svc in set(inputs) - counted(list(stats.items)):
                _put_bad_inputs(s, up.robot_id, topic(inputs[svc]).key(up.robot_id))
            stats.wait_for(lambda items: False, 0.3)
        assert counted(list(stats.items)) == set(inputs), \
            [(st.service, st.decode_errors, st.errors) for st in stats.items[-8:]]
        n = len(obstacles.items)
        assert obstacles.wait_for(lambda items: len(items) >= n + 5, 30), "pipeline stopped after bad input"
    assert up.proc.poll() is None
    assert "dropped" in up.log_path.read_text()


def test_up_stops_with_status_2_when_a_service_rejects_its_settings(tmp_path):
    from helpers import Up
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("segmenter:\n  max_range_m: -3\n")
    u = Up(extra_env={"BALLBOT_CONFIG": str(cfg)})
    try:
        assert u.proc.wait(60) == 2
    finally:
        u.stop()
    assert "max_range_m" in u.log_path.read_text()


def lists_saying(u, reason: str) -> list[ObstacleList]:
    """The lists of `up` u until three in a row say `reason` (generous deadline) -> all seen."""
    with u.session() as s:
        lists = Collector(ObstacleList)
        s.declare_subscriber(topic("obstacles").key(u.robot_id), lists)

        def said(items) -> bool:
            return len(items) >= 3 and all(reason in m.degraded for m in items[-3:])
        assert lists.wait_for(said, 120), [(m.seq, m.degraded) for m in lists.items[-10:]] + \
            [u.log_path.read_text()[-3000:]]
        return list(lists.items)


def status_of(u) -> tuple[int, dict, dict]:
    """`status --json` on `up` u, as a user runs it -> (exit code, the whole document, the segmenter's row)."""
    status = subprocess.run(cli("status", "--connect", u.endpoint, "--json", "--wait", "2.5"),
                            capture_output=True, text=True, timeout=60)
    assert status.stdout, status.stderr
    doc = json.loads(status.stdout)
    return status.returncode, doc, next(i for i in doc["instances"] if i["name"] == "segmenter")


def test_a_mount_chosen_over_fitting_and_measured_wrong_is_said_everywhere(tmp_path):
    """fit_floor false with the camera's pitch taped 4 deg off (the scene's camera: 1 m, 15 deg): what a
    planner reads (`watch`) says mount-disagrees on every list, with the distances it looked at, and
    `status` says the pipeline is degraded (exit 3), naming it."""
    from helpers import Up
    cfg = tmp_path / "taped.yaml"
    cfg.write_text("mount:\n  height_m: 1.0\n  pitch_deg: 19.0\nsegmenter:\n  fit_floor: false\n")
    u = Up(extra_env={"BALLBOT_CONFIG": str(cfg)})
    try:
        watch = subprocess.run(cli("watch", "--connect", u.endpoint, "--count", "8", "--json", "--timeout", "90"),
                               capture_output=True, text=True, timeout=150)
        assert watch.returncode == 0, watch.stderr + u.log_path.read_text()
        lists = [ObstacleList.model_validate(json.loads(line)) for line in watch.stdout.splitlines()]
        # the first lists may come before any ground was fitted to check the mount by (then unchecked)
        checked = [m for m in lists if m.ground is not None and m.ground.prior_agrees is not None]
        assert checked and all("mount-disagrees" in m.degraded for m in checked), [(m.seq, m.degraded) for m in lists]
        assert all(m.range_m == (1.0, 4.5) and m.ground.source == "prior" for m in lists)
        # the bearings looked at: the disparity search's band at the left side is not among them
        assert all(m.bearing_deg is not None and -45 < m.bearing_deg[0] < -15 < 15 < m.bearing_deg[1] for m in lists)
        code, _, seg = status_of(u)
        assert code == 3 and seg["status"].startswith("mount-disagrees"), seg
        assert "says mount-disagrees" in u.log_path.read_text()  # the segmenter's warning, once, at the start
    finally:
        u.stop()


def test_a_camera_repeating_one_picture_is_said_by_every_list_and_by_status(tmp_path):
    """The synthetic camera made to deliver one pair over and over (`preload: 1`, as a hung driver
    repeats its last buffer with fresh stamps): the lists are fresh by their stamps, but after
    stale_after_s each says input-frozen, and `status` says degraded (exit 3), naming it."""
    from helpers import Up
    cfg = tmp_path / "stuck.yaml"
    cfg.write_text("capture:\n  preload: 1\n")
    u = Up(extra_env={"BALLBOT_CONFIG": str(cfg)})
    try:
        lists = lists_saying(u, "input-frozen")
        # fresh stamps (bar a list a busy machine made late): only the pictures tell
        assert any("input-frozen" in m.degraded and not m.stale for m in lists)
        code, _, seg = status_of(u)
        assert code == 3 and seg["status"].startswith("input-frozen"), seg
    finally:
        u.stop()


def test_a_calibration_that_no_longer_fits_the_rig_is_said_by_every_list_and_by_status(tmp_path):
    """rectify given the scene's rig with the right camera's principal point 2 px low (what a knocked
    camera does to a calibration that was right): the pairs it makes are 2 px apart in rows. Its live
    check finds it off the frame path; every list after says rows-misaligned, `status` says degraded
    (exit 3) naming it, and rectify's stats carry the offset it measured."""
    import yaml
    from helpers import Up

    from cores import camera
    doc = camera.calibration_to_dict(camera.load_calibration("lifecam-studio"))
    doc["right"]["K"][5] += 2.0
    cal = tmp_path / "knocked.yaml"
    cal.write_text(yaml.safe_dump(doc))
    u = Up(extra_env={"BALLBOT_RECTIFY_CALIBRATION": str(cal)})
    try:
        lists_saying(u, "rows-misaligned")
        code, doc, seg = status_of(u)
        assert code == 3 and seg["status"].startswith("rows-misaligned"), seg
        assert "calibration check" in seg["status"]
        rect = next(i for i in doc["instances"] if i["name"] == "rectify")
        assert 1.5 < rect["extra"]["row_offset_px"] < 2.5, rect
        assert "rectified rows misaligned" in u.log_path.read_text()
    finally:
        u.stop()


def test_swapped_cameras_are_said_by_every_list_by_status_and_by_rectify(tmp_path):
    """The scene's pairs from image folders with the cables exchanged (the right camera's pictures as
    the left): rows still align, so only where the features lie tells. Every list says
    cameras-swapped, `status` says degraded (exit 3) naming it, rectify warns once."""
    import cv2
    from helpers import Up

    from services.capture.sources import SyntheticSource
    src = SyntheticSource("person-walking", "lifecam-studio", 15.0)
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
    for k in range(6):
        pair = src.read()
        cv2.imwrite(str(tmp_path / "left" / f"{k:03d}.png"), pair.right)
        cv2.imwrite(str(tmp_path / "right" / f"{k:03d}.png"), pair.left)
    u = Up(extra_env={"BALLBOT_CAPTURE_SOURCE": "images", "BALLBOT_CAPTURE_LOOP": "true",
                      "BALLBOT_CAPTURE_IMAGES_LEFT": str(tmp_path / "left"),
                      "BALLBOT_CAPTURE_IMAGES_RIGHT": str(tmp_path / "right"),
                      "BALLBOT_RECTIFY_CALIBRATION": "lifecam-studio"})
    try:
        lists_saying(u, "cameras-swapped")
        code, doc, seg = status_of(u)
        assert code == 3 and seg["status"].startswith("cameras-swapped"), seg
        rect = next(i for i in doc["instances"] if i["name"] == "rectify")
        assert rect["extra"]["reversed_share"] > 0.9, rect
        assert u.log_path.read_text().count("cameras swapped:") == 1
    finally:
        u.stop()


def test_someone_standing_nearer_than_the_range_is_said_by_every_list_and_by_status(tmp_path):
    """A person-sized box walks up to the camera and stops 0.3 m from it, nearer than the vision range
    (1-4.5 m) and beyond the matcher's search: every list from then on says nearer-than-range, and
    `status` names it with the distance rectify's coarse search measured."""
    from helpers import Up
    from test_near import APPROACH

    scene = tmp_path / "approach.yaml"
    scene.write_text(APPROACH)
    u = Up(extra_env={"BALLBOT_CAPTURE_SCENARIO": str(scene)})
    try:
        lists_saying(u, "nearer-than-range")
        code, doc, seg = status_of(u)
        assert code == 3 and seg["status"].startswith("nearer-than-range"), seg
        at = float(re.search(r"at about ([0-9.]+) m", seg["status"]).group(1))
        assert 0.2 < at < 1.0, seg["status"]  # walking in, or standing at 0.3 m
    finally:
        u.stop()


def test_the_scene_as_rendered_is_aligned_and_its_lists_do_not_say_otherwise(up):
    """The same check on the rig the scene renders: well under the tolerance, nothing said."""
    with up.session() as s:
        frames = Collector(StereoFrame)
        s.declare_subscriber(topic("frames_rect").key(up.robot_id), frames)
        assert frames.wait_for(lambda items: any(f.checks.rows is not None for f in items), 60)
        rows = next(f.checks.rows for f in frames.items if f.checks.rows is not None)
        assert rows.offset_px < 0.2 and rows.matches >= 50, rows
        assert all(f.checks.frozen == [] for f in frames.items)
    lists = subprocess.run(cli("watch", "--connect", up.endpoint, "--count", "4", "--json", "--timeout", "60"),
                           capture_output=True, text=True, timeout=120)
    assert not any("rows-misaligned" in json.loads(line)["degraded"] for line in lists.stdout.splitlines())


KARLSRUHE = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "karlsruhe-0023"


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
def test_a_finger_on_one_lens_is_said_by_every_list_and_by_status(tmp_path):
    """The street through `up` from image folders, a dark disc over a sixth of every right picture (a
    finger on the lens): nothing there is measured, and a car 17 m ahead had gone from the lists
    unflagged. Every list says view-blocked, `status` names the right camera (exit 3), and
    rectify's log says what it saw."""
    import cv2
    from helpers import Up
    left, right = tmp_path / "left", tmp_path / "right"
    left.mkdir()
    right.mkdir()
    pairs = zip(sorted((KARLSRUHE / "left").glob("*.png")), sorted((KARLSRUHE / "right").glob("*.png")))
    for lp, rp in list(pairs)[:10]:
        (left / lp.name).symlink_to(lp)
        img = cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE)
        h, w = img.shape
        cv2.circle(img, (w * 3 // 4, h * 2 // 3), h // 2, 20, -1)
        cv2.imwrite(str(right / rp.name), img)
    cfg = tmp_path / "street.yaml"
    cfg.write_text(f"capture:\n  source: images\n  images_left: {left}\n  images_right: {right}\n  loop: true\n"
                   f"  rate_hz: 10\nrectify:\n  calibration: {KARLSRUHE / 'calibration.yaml'}\n")
    u = Up(extra_env={"BALLBOT_CONFIG": str(cfg)})
    try:
        lists_saying(u, "view-blocked")
        code, _, seg = status_of(u)
        assert code == 3 and seg["status"].startswith("view-blocked: part of the right camera's view"), seg
        assert "part of the right camera's view is flat" in u.log_path.read_text()
    finally:
        u.stop()


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
def test_the_street_at_dusk_is_said_by_every_list_and_by_status(tmp_path):
    """The street through `up` at 4 % of its light, the cameras' gain bringing it back up with their
    noise, the mount configured and fit_floor false (no ground fit to fail): the matcher measures 1-2 %
    of the picture and the lists had emptied with nothing said. Every list says little-measured, and
    `status` says how much was measured (exit 3)."""
    import cv2
    from helpers import Up
    from test_little_measured import dusk
    rng = np.random.default_rng(0)
    folders = {side: tmp_path / side for side in ("left", "right")}
    for side, pattern in (("left", "I1_*.png"), ("right", "I2_*.png")):
        folders[side].mkdir()
        for p in sorted((KARLSRUHE / side).glob(pattern))[:10]:
            cv2.imwrite(str(folders[side] / p.name), dusk(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), 0.04, rng))
    cfg = tmp_path / "dusk.yaml"
    cfg.write_text(f"capture:\n  source: images\n  images_left: {folders['left']}\n  images_right: "
                   f"{folders['right']}\n  loop: true\n  rate_hz: 10\nrectify:\n  calibration: "
                   f"{KARLSRUHE / 'calibration.yaml'}\nmount:\n  height_m: 1.64\n  pitch_deg: 6.0\n"
                   f"segmenter:\n  fit_floor: false\n")
    u = Up(extra_env={"BALLBOT_CONFIG": str(cfg)})
    try:
        lists = lists_saying(u, "little-measured")
        # every list, from the first: the dark never looked like a clear way (the last three alone say little)
        assert all({"little-measured", "no-valid-disparity"} & set(m.degraded) for m in lists), \
            [(m.seq, m.valid_fraction, m.degraded) for m in lists]
        # rectify's noise estimate of the same pictures, through the services: noisy as well
        assert all("noisy" in m.degraded for m in lists), [(m.seq, m.degraded) for m in lists]
        code, _, seg = status_of(u)
        assert code == 3 and seg["status"].startswith("little-measured: the disparity map measured "), seg
    finally:
        u.stop()


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
def test_the_sun_low_ahead_is_said_by_every_list_and_by_status(tmp_path):
    """The street through `up` with the defaults and a saturated disc over the parked cars on its
    right, in both cameras (the sun low ahead): the cars in it went missing and no list said so.
    rectify's clipped tiles travel with the pair and its map; every list says washed-out, and
    `status` says how much of the floor was white (exit 3)."""
    import cv2
    from helpers import Up
    from test_washout import glare
    folders = {side: tmp_path / side for side in ("left", "right")}
    for side, pattern in (("left", "I1_*.png"), ("right", "I2_*.png")):
        folders[side].mkdir()
        for p in sorted((KARLSRUHE / side).glob(pattern))[:10]:
            image = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            h, w = image.shape
            cv2.imwrite(str(folders[side] / p.name), glare(image, 0.75 * w, 0.4 * h, 0.25 * h))
    cfg = tmp_path / "sun.yaml"
    cfg.write_text(f"capture:\n  source: images\n  images_left: {folders['left']}\n  images_right: "
                   f"{folders['right']}\n  loop: true\n  rate_hz: 10\nrectify:\n  calibration: "
                   f"{KARLSRUHE / 'calibration.yaml'}\n")
    u = Up(extra_env={"BALLBOT_CONFIG": str(cfg)})
    try:
        lists = lists_saying(u, "washed-out")
        # every list: none looked like a clear way (the first, before any floor was fitted, says no-ground)
        assert all(m.degraded for m in lists) and all("washed-out" in m.degraded for m in lists[1:]), \
            [(m.seq, m.degraded) for m in lists]
        code, _, seg = status_of(u)
        assert code == 3 and seg["status"].startswith("washed-out: "), seg
        assert "of the floor within the vision range is clipped white in both cameras" in seg["status"]
    finally:
        u.stop()


@pytest.mark.skipif(not (KARLSRUHE / "calibration.yaml").exists(), reason="../shared/data/real/karlsruhe-0023 absent")
def test_one_camera_whose_driver_hung_is_said_by_every_list_and_by_status(tmp_path):
    """The street through `up` from image folders, with the right camera repeating its first picture
    while the left goes on (a hung driver of one camera of two): the maps keep changing, so nothing
    else tells; every list says camera-frozen, and `status` names the right camera (exit 3)."""
    from helpers import Up
    left, right = tmp_path / "left", tmp_path / "right"
    left.mkdir()
    right.mkdir()
    first_right = sorted((KARLSRUHE / "right").glob("*.png"))[0]
    for lp, rp in zip(sorted((KARLSRUHE / "left").glob("*.png")), sorted((KARLSRUHE / "right").glob("*.png"))):
        (left / lp.name).symlink_to(lp)
        (right / rp.name).symlink_to(first_right)
    cfg = tmp_path / "street.yaml"
    cfg.write_text(f"capture:\n  source: images\n  images_left: {left}\n  images_right: {right}\n  loop: true\n"
                   f"  rate_hz: 10\nrectify:\n  calibration: {KARLSRUHE / 'calibration.yaml'}\n")
    u = Up(extra_env={"BALLBOT_CONFIG": str(cfg)})
    try:
        lists = lists_saying(u, "camera-frozen")
        assert not any("input-frozen" in m.degraded for m in lists)  # the maps changed all along
        code, _, seg = status_of(u)
        assert code == 3 and seg["status"].startswith("camera-frozen: the right camera"), seg
        assert "the right camera's picture has not changed" in u.log_path.read_text()
    finally:
        u.stop()
