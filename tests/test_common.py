"""Unit tests of common/: codec, key table, settings. No network."""
from __future__ import annotations

import re
from pathlib import Path

import msgpack
import numpy as np
import pytest

from common import codec, keys
from common.errors import ConfigError, DecodeError
from common.messages import SCHEMA_VERSION, FreeSpace, Image, ObstacleList, StereoFrame
from common.settings import load_settings
from cores.segmentation.settings import SegmenterSettings

REPO = Path(__file__).resolve().parent.parent


def frame(**kw) -> StereoFrame:
    img = codec.image_from_array(np.arange(12, dtype=np.uint8).reshape(3, 4))
    return StereoFrame(robot_id="r1", seq=7, stamp_ns=123, left=img, right=img, **kw)


def test_roundtrip_keeps_every_field():
    f = frame(source="synthetic")
    back = codec.decode(codec.encode(f), StereoFrame)
    assert back == f
    assert np.array_equal(codec.array_from_image(back.left), np.arange(12, dtype=np.uint8).reshape(3, 4))


@pytest.mark.parametrize("encoding", ["png", "jpeg"])
def test_compressed_images_roundtrip(encoding):
    rng = np.random.default_rng(0)
    a = cv2_blur(rng.integers(0, 255, (48, 64), dtype=np.uint8))
    img = codec.image_from_array(a, encoding, jpeg_quality=95)
    back = codec.array_from_image(img)
    assert back.shape == a.shape and back.dtype == a.dtype
    if encoding == "png":
        assert np.array_equal(back, a)
    else:
        assert np.abs(back.astype(int) - a).mean() < 3


def cv2_blur(a):
    import cv2
    return cv2.GaussianBlur(a, (5, 5), 1.0)


def test_garbage_wrong_version_and_missing_fields_are_decode_errors():
    with pytest.raises(DecodeError, match="not msgpack|expected a map"):
        codec.decode(b"\xc1\xc1garbage", StereoFrame)
    doc = frame().model_dump()
    doc["schema_version"] = SCHEMA_VERSION + 1
    with pytest.raises(DecodeError, match=f"schema_version {SCHEMA_VERSION + 1}"):
        codec.decode(msgpack.packb(doc), StereoFrame)
    doc["schema_version"] = SCHEMA_VERSION
    del doc["left"]
    with pytest.raises(DecodeError, match="StereoFrame.left"):
        codec.decode(msgpack.packb(doc), StereoFrame)


def test_a_disparity_map_whose_search_no_matcher_makes_is_a_decode_error():
    """Where a list looked (range_m, bearing_deg) is read off the map's search: a map saying it searched
    0..10^6 px (a buggy or forged producer; the dispatcher refuses it from a worker, the segmenter takes
    it from an unsigned peer) put the list's bearings at one column, and the list, with every obstacle
    of the real search in it and no degraded reason, passed for a full view."""
    from common.messages import CameraModel, DisparityMap

    cam = CameraModel(width=64, height=48, focal_px=60.0, cx=32.0, cy=24.0, baseline_m=0.1, Q=[0.0] * 16)
    honest = DisparityMap(robot_id="r", seq=1, stamp_ns=1, image=codec.image_from_array(np.zeros((48, 64), np.int16)),
                          scale=16.0, invalid_value=-16.0, min_disparity=0, num_disparities=64, camera=cam, method="bm")
    assert codec.decode(codec.encode(honest), DisparityMap).num_disparities == 64
    for field, value, says in (("num_disparities", 10 ** 6, "less than or equal to 512"),
                               ("num_disparities", 40, "multiple of 16"), ("num_disparities", 0, "greater than"),
                               ("min_disparity", -10 ** 6, "greater than or equal to -256"),
                               ("min_disparity", 600, "less than or equal to 256")):
        doc = honest.model_dump()
        doc[field] = value
        with pytest.raises(DecodeError, match=f"DisparityMap.{field}: .*{says}"):
            codec.decode(msgpack.packb(doc), DisparityMap)


def test_image_payload_that_does_not_match_its_size_is_named():
    img = Image(width=640, height=480, data=b"\x00" * 100)
    with pytest.raises(DecodeError, match="left: 100 bytes for a 640x480x1 uint8 image, expected 307200"):
        codec.array_from_image(img, "left")
    bad_png = Image(width=4, height=3, encoding="png", data=b"not a png")
    with pytest.raises(DecodeError, match="does not decode"):
        codec.array_from_image(bad_png)


def test_image_dtype_names_and_byte_order():
    for dt in ("uint8", "uint16", "int16", "float32"):
        a = np.arange(12, dtype=dt).reshape(3, 4)
        img = codec.image_from_array(a)
        assert img.dtype == dt and np.array_equal(codec.array_from_image(img), a)
    # Big-endian pixels are not what the message says (native little-endian): refused, not mislabelled.
    with pytest.raises(Exception, match="dtype"):
        codec.image_from_array(np.arange(12, dtype=">u2").reshape(3, 4))


def test_key_table_is_the_only_place_keys_are_spelled():
    assert keys.topic("obstacles").key("robo") == "ballbot/obstacles/robo"
    assert keys.topic("stats").pattern("r") == "ballbot/r/stats/*/*"
    for t in keys.TOPICS.values():
        assert t.template.startswith("ballbot/")
        if t.public:
            assert t.template == f"ballbot/{t.name}/{{robot_id}}"
        elif t.name.startswith("pool_"):  # a fleet pool's keys, shared by its robots
            assert t.template.startswith(keys.POOL_ROOT + "{pool}/")
        else:
            assert t.template.startswith("ballbot/{robot_id}/")
    offenders = []
    for p in list((REPO / "services").rglob("*.py")) + list((REPO / "ballbot_vision").rglob("*.py")):
        for n, line in enumerate(p.read_text().splitlines(), 1):
            if re.search(r"[\"']ballbot/", line):
                offenders.append(f"{p.relative_to(REPO)}:{n}")
    assert not offenders, f"key strings spelled outside common/keys.py: {offenders}"


def test_public_obstacle_schema_has_the_contract_fields():
    props = ObstacleList.model_json_schema()["$defs"]["Obstacle"]["properties"]
    for f in ("id", "position_m", "size_m", "distance_m", "velocity_mps", "bbox_px", "area_px",
              "disparity_px", "confidence"):
        assert f in props
    top = ObstacleList.model_json_schema()["properties"]
    for f in ("schema_version", "robot_id", "seq", "stamp_ns", "publish_ns", "stale"):
        assert f in top


def test_settings_priority_default_file_env_flag(tmp_path, monkeypatch):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("segmenter:\n  max_range_m: 4.0\n  median_ksize: 3\n")
    monkeypatch.setenv("BALLBOT_SEGMENTER_MAX_RANGE_M", "2.5")
    s = load_settings(SegmenterSettings, str(cfg))
    assert s.max_range_m == 2.5 and s.median_ksize == 3 and s.min_area_fraction == 0.03
    import argparse

    from common.settings import add_settings_arguments
    parser = argparse.ArgumentParser()
    add_settings_arguments(parser, SegmenterSettings)
    s = load_settings(SegmenterSettings, str(cfg), parser.parse_args(["--max-range-m", "1.5"]))
    assert s.max_range_m == 1.5


def test_bad_settings_name_where_the_value_came_from(tmp_path, monkeypatch):
    monkeypatch.setenv("BALLBOT_SEGMENTER_MAX_RANGE_M", "-1")
    with pytest.raises(ConfigError, match="BALLBOT_SEGMENTER_MAX_RANGE_M"):
        load_settings(SegmenterSettings)
    monkeypatch.delenv("BALLBOT_SEGMENTER_MAX_RANGE_M")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("segmenter:\n  no_such_setting: 1\n")
    with pytest.raises(ConfigError, match="segmenter.no_such_setting"):
        load_settings(SegmenterSettings, str(cfg))


def test_inbox_keeps_the_newest_by_capture_stamp_and_counts_what_it_drops():
    from common.inbox import Inbox
    inbox = Inbox(keys.topic("disparity"))
    inbox.offer(b"t20", 20)
    inbox.offer(b"t10", 10)  # a slow worker's older result must not replace the newer one
    assert inbox.take(0.01) == b"t20"
    inbox.offer(b"t15", 15)  # older than what was already processed
    assert inbox.take(0.01) is None
    inbox.offer(b"t30", 30)
    inbox.offer(b"t40", 40)
    assert inbox.take(0.01) == b"t40"
    assert (inbox.received, inbox.late, inbox.overwritten) == (5, 2, 1)
    inbox.offer(b"foreign", None)  # no stamp attached: plain newest-wins
    assert inbox.take(0.01) == b"foreign"


def test_freespace_round_trips_on_the_wire_and_as_json():
    import json

    grid = np.full((4, 6), -1, np.int8)
    grid[1:3, 2:5] = 0
    grid[2, 4] = 100
    msg = FreeSpace(robot_id="r", seq=3, stamp_ns=5, publish_ns=6, resolution_m=0.1, width=6, height=4,
                    origin_m=(0.0, -0.2), cells=grid.tobytes())
    back = codec.decode(codec.encode(msg), FreeSpace)
    assert np.array_equal(np.frombuffer(back.cells, np.int8).reshape(4, 6), grid)
    doc = json.loads(msg.model_dump_json())  # cells travel as base64 in JSON
    assert FreeSpace.model_validate_json(json.dumps(doc)).cells == msg.cells
    schema = FreeSpace.model_json_schema()
    assert "FreeSpace" in json.dumps(schema) or schema["title"] == "FreeSpace"


def test_watch_table_says_where_the_ground_is_and_which_tracks_to_trust():
    from ballbot_vision.watch import format_table
    from common.messages import GroundEstimate, Obstacle, ObstacleList

    o = Obstacle(id=3, position_m=(0.1, 0.2, 2.0), size_m=(0.5, 0.6, 0.3), distance_m=1.9, bbox_px=(1, 2, 3, 4),
                 area_px=10, disparity_px=30.0, confidence=0.9, confirmed=False, track_frames=2, truncated=True)
    msg = ObstacleList(robot_id="r", seq=1, stamp_ns=0, publish_ns=0, stale=False, obstacles=[o],
                       ground=GroundEstimate(height_m=1.0, pitch_deg=15.0, roll_deg=0.5, source="fitted"),
                       velocity_reference="ground")
    text = format_table(msg)
    assert "camera 1.00 m above it, pitch +15.0 deg, roll +0.5 deg (fitted)" in text
    assert "velocities over the ground" in text and "2 frames, unconfirmed, cut by the view" in text
    assert "ground: unknown" in format_table(msg.model_copy(update={"ground": None}))
    assert "STALE" not in text and "NOT A FULL VIEW" not in text
    head = format_table(msg.model_copy(update={"degraded": ["near-unmeasured", "ground-uncertain"],
                                                "stale": True})).splitlines()[0]
    assert head.endswith("1 obstacle(s)  STALE  NOT A FULL VIEW: near-unmeasured, ground-uncertain"), head
    # the offline `obstacles` command says the same of its lists: where it looked, and what it could not vouch for
    from ballbot_vision.segmenter_commands import format_obstacles

    empty = msg.model_copy(update={"obstacles": [], "degraded": ["nearer-than-range"], "range_m": (1.0, 30.0),
                                   "bearing_deg": (-26.4, 46.2)})
    text = format_obstacles(empty, "L R: layers: 0 obstacle(s)")
    assert text.splitlines() == ["L R: layers: 0 obstacle(s) at 1-30.0 m, -26..+46 deg  NOT A FULL VIEW: "
                                 "nearer-than-range", "  (no obstacles)"], text
    assert format_obstacles(msg).splitlines()[-1].endswith("2 frames, unconfirmed, cut by the view")


def test_status_verdict_is_degraded_while_the_segmenters_lists_are():
    """`status` exits 3 (degraded) while the obstacle lists say they cannot vouch for their view, not only
    while they are stale: a search that misses the near range had been "healthy", exit 0."""
    from ballbot_vision.status import verdict

    def seg(status: str) -> dict:
        return {"service": "segmenter", "name": "segmenter", "status": status, "health": "ok", "rate_hz": 15.0,
                "age_ms_p50": 40.0}

    assert verdict([seg("ok")], []) == ("ok", "obstacles at 15.0 Hz, 40 ms after capture")
    assert verdict([seg("ok (disparity maps unauthenticated: no KEY)")], [])[0] == "ok"
    for status in ("stale: input too old", "near-unmeasured: the disparity search ...",
                   "degraded lists: ground-uncertain"):
        level, text = verdict([seg(status)], [])
        assert level == "degraded" and text == f"obstacles {status}", (status, text)


def test_a_list_says_the_bearings_it_looked_at_and_a_forged_one_is_a_decode_error():
    lst = ObstacleList(robot_id="r", seq=1, stamp_ns=1, publish_ns=1, stale=False, bearing_deg=(-21.0, 25.6))
    assert codec.decode(codec.encode(lst), ObstacleList).bearing_deg == (-21.0, 25.6)
    for bad in ([float("nan"), 25.6], [-21.0, 91.0], [25.6, -21.0], [1.0]):
        doc = lst.model_dump()
        doc["bearing_deg"] = bad
        with pytest.raises(DecodeError, match="ObstacleList.bearing_deg"):
            codec.decode(msgpack.packb(doc), ObstacleList)


def test_a_list_says_the_distances_it_looked_at_and_a_forged_range_is_a_decode_error():
    lst = ObstacleList(robot_id="r", seq=1, stamp_ns=1, publish_ns=1, stale=False, range_m=(1.0, 4.5))
    assert codec.decode(codec.encode(lst), ObstacleList).range_m == (1.0, 4.5)
    for bad in ([float("nan"), 4.5], [1.0, float("inf")], [-1.0, 4.5], [1.0]):
        doc = lst.model_dump()
        doc["range_m"] = bad
        with pytest.raises(DecodeError, match="ObstacleList.range_m"):
            codec.decode(msgpack.packb(doc), ObstacleList)
