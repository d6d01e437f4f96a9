"""The ROS 2 bridge's pure parts, checked against references that are not our code: type hashes
from rosidl-generated C of a ROS 2 build, key assembly from pamoja-ros2, token builders and the
attachment parser of zenoh-ros2-sdk, Zenoh's own serializer, rosbags' CDR deserialiser."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros2 extra (rosbags) is not installed")

from common import codec
from common.errors import CalibrationError, DecodeError
from common.messages import CameraModel, DisparityMap, FreeSpace, GroundEstimate, Obstacle, ObstacleList, StereoFrame
from common.ros2 import rmw
from common.ros2.msgs import types_for
from cores import camera
from cores import ros2_convert as convert
from cores.segmentation.mount import Mount
from services.capture.ros2 import StampPairer, camera_info_topic
from services.ros2.main import Ros2Settings, mount_from, mount_moved

# RIHS01 hashes as rosidl_generator_c wrote them into a ROS 2 (Jazzy) build's *__description.c
# (vision_msgs 4.x, sensor_msgs, nav_msgs, visualization_msgs, tf2_msgs, std_msgs).
ROS_BUILD_HASHES = {
    "vision_msgs/msg/Detection3DArray": "793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018",
    "vision_msgs/msg/Detection3D": "ddd703be132ab0b69d33121f1bb034132bfbb3b0ac5f9fb1516005ba1c8a265b",
    "vision_msgs/msg/BoundingBox3D": "bbb73a65c163d7f9bb29009c7bde9f7faa576bd2d23299c4511d19230dab4698",
    "vision_msgs/msg/ObjectHypothesis": "51da43cec11c01957a64d1e05a24acd18aae7745ec30b74348ad5f6d634f7f90",
    "vision_msgs/msg/ObjectHypothesisWithPose": "41c12344c0396c48b81df12467c192d99b2a0eb1463c5c37194e4223251c80bc",
    "sensor_msgs/msg/Image": "d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CameraInfo": "b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
    "sensor_msgs/msg/PointCloud2": "9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5",
    "nav_msgs/msg/OccupancyGrid": "8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
    "visualization_msgs/msg/Marker": "45b13ccf791f225962bf74e746f9644518855d783a6f42ba0cc14fde2b4f3ce0",
    "std_msgs/msg/Header": "f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
}

STAMP = 1_700_000_000_123_456_789


@pytest.fixture(scope="module")
def jazzy():
    return types_for("jazzy")


def test_type_hashes_equal_a_ros_builds(jazzy):
    for typename, digest in ROS_BUILD_HASHES.items():
        assert jazzy.type_hash(typename) == "RIHS01_" + digest, typename
    assert types_for("humble").type_hash("vision_msgs/msg/Detection3DArray") == "TypeHashNotSupported"


def test_data_key_and_names_match_pamoja():
    ros2 = pytest.importorskip("pamoja.ros2", reason="pamoja-ros2 not installed")
    t = types_for("jazzy")
    for topic, typename in (("/ballbot/obstacles/detections", "vision_msgs/msg/Detection3DArray"),
                            ("/tf_static", "tf2_msgs/msg/TFMessage")):
        h = t.type_hash(typename)
        assert rmw.topic_key(7, topic, rmw.dds_type_name(typename), h) == ros2.entity_key(7, topic, typename, h)
        assert rmw.dds_type_name(typename) == ros2.dds_type_name(typename)
        assert rmw.mangle(topic) == ros2.percent_mangle(topic)


def test_tokens_match_zenoh_ros2_sdk_builders():
    sdk = pytest.importorskip("zenoh_ros2_sdk.keyexpr", reason="zenoh-ros2-sdk not installed")
    from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
    from zenoh_ros2_sdk.qos import QosProfile

    zid = "71801838037ade111371991bc9060fe9"
    for ns in ("/", "/robot1"):
        node = NodeEntity(domain_id=3, session_id=zid, node_id=0, node_name="ballbot_vision", namespace=ns)
        assert rmw.node_token(3, zid, 0, ns, "ballbot_vision") == sdk.node_liveliness_keyexpr(node)
        # the SDK elides QoS fields against its own default (depth 10); rmw_zenoh's default depth is 42
        sdk_qos = QosProfile(history_depth=10).encode(default=QosProfile(history_depth=42))
        ep = EndpointEntity(node=node, entity_id=4, kind=EntityKind.PUBLISHER, name="/robot1/obstacles/points",
                            dds_type_name="sensor_msgs::msg::dds_::PointCloud2_", type_hash="RIHS01_ab", qos=sdk_qos)
        ours = rmw.endpoint_token("MP", 3, zid, 0, 4, ns, "ballbot_vision", "/robot1/obstacles/points",
                                  "sensor_msgs::msg::dds_::PointCloud2_", "RIHS01_ab", rmw.Qos(depth=10).keyexpr())
        assert ours == sdk.endpoint_liveliness_keyexpr(ep)


def _qos_from_keyexpr(text: str) -> dict:
    """rmw_zenoh's keyexpr_to_qos (liveliness_utils.cpp) restated: empty fields take its defaults."""
    rel, dur, hist, deadline, lifespan, live = text.split(":")
    kind, depth = hist.split(",")
    assert len(deadline.split(",")) == 2 and len(lifespan.split(",")) == 2 and len(live.split(",")) == 3
    return {"reliability": int(rel or 1), "durability": int(dur or 2), "history": int(kind or 1),
            "depth": int(depth or 42)}


def test_qos_string_reads_back_as_rmw_zenoh_reads_it():
    assert rmw.Qos().keyexpr() == "::,10:,:,:,,"
    assert _qos_from_keyexpr(rmw.Qos(reliability="best_effort", depth=5).keyexpr()) == \
        {"reliability": 2, "durability": 2, "history": 1, "depth": 5}
    assert _qos_from_keyexpr(rmw.Qos(durability="transient_local", depth=1).keyexpr()) == \
        {"reliability": 1, "durability": 1, "history": 1, "depth": 1}
    assert _qos_from_keyexpr(rmw.Qos(depth=42).keyexpr())["depth"] == 42


@pytest.mark.parametrize("distro,size", [("jazzy", 16), ("humble", 24)])
def test_attachment_reads_with_zenohs_own_deserializer(distro, size):
    import zenoh
    from zenoh.ext import Int64, UInt8, z_deserialize

    token = "@ros2_lv/0/abc/0/1/MP/%/%/n/%t/std_msgs::msg::dds_::String_/TypeHashNotSupported/::,10:,:,:,,"
    gid = rmw.gid(token, rmw.distro(distro).gid_size)
    raw = rmw.encode_attachment(41, STAMP, gid)
    seq, ts, g = z_deserialize(tuple[Int64, Int64, list[UInt8]], zenoh.ZBytes(raw))
    assert (seq, ts, bytes(g)) == (41, STAMP, gid) and len(gid) == size
    assert rmw.decode_attachment(raw) == (41, STAMP, gid)
    # the GID is the token's XXH3-128, low half first; padding (Humble) is zero
    import xxhash

    assert gid[:16] == xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")
    assert gid[16:] == bytes(size - 16)


def test_attachment_reads_with_zenoh_ros2_sdk():
    att = pytest.importorskip("zenoh_ros2_sdk.attachment", reason="zenoh-ros2-sdk not installed")
    a = att.Attachment.from_bytes(rmw.encode_attachment(3, STAMP, bytes(range(16))))
    assert (a.sequence_id, a.timestamp_ns, a.gid) == (3, STAMP, bytes(range(16)))


@pytest.mark.parametrize("raw,what", [(b"\x01" * 10, "shorter"), (b"\x00" * 16 + b"\x10" + b"\x00" * 3, "announced"),
                                      (b"\x00" * 16 + b"\xff\xff\xff\xff\xff", "LEB128")])
def test_bad_attachments_are_named(raw, what):
    with pytest.raises(rmw.AttachmentError, match=what):
        rmw.decode_attachment(raw)


@pytest.mark.parametrize("name,ns,err", [("obstacles", "/2robot", "namespace"), ("bad topic", "/", "topic"),
                                         ("a//b", "/", "topic"), ("a/", "/", "topic"), ("~/x", "/", "private"),
                                         ("a__b", "/", "topic")])
def test_bad_ros_names_are_refused(name, ns, err):
    with pytest.raises(rmw.RosNameError, match=err):
        rmw.resolve_topic(name, ns)


def test_names_resolve_as_ros_does():
    assert rmw.resolve_topic("obstacles/points", "/robot1") == "/robot1/obstacles/points"
    assert rmw.resolve_topic("/tf_static", "/robot1") == "/tf_static"
    assert rmw.topic_key(0, "/robot1/obstacles/points", "T", "H") == "0/robot1/obstacles/points/T/H"
    assert rmw.ros_type_from_dds("sensor_msgs::msg::dds_::Image_") == "sensor_msgs/msg/Image"
    assert rmw.ros_type_from_dds("nonsense") is None
    with pytest.raises(Exception, match="node_name"):
        Ros2Settings(node_name="has-dash")
    assert Ros2Settings(namespace="robot1").namespace == "/robot1"


# --- converters ---------------------------------------------------------------------------------

def _obstacles(ground: GroundEstimate | None = None) -> ObstacleList:
    return ObstacleList(robot_id="r", seq=5, stamp_ns=STAMP, publish_ns=STAMP + 10, stale=False, ground=ground,
                        obstacles=[Obstacle(id=7, position_m=(0.2, 0.1, 2.0), size_m=(0.4, 0.5, 0.3), distance_m=1.85,
                                            bbox_px=(300, 200, 400, 300), area_px=9000, disparity_px=30.0,
                                            confidence=0.8),
                                   Obstacle(id=9, position_m=(-0.5, 0.0, 3.0), size_m=(0.2, 0.2, 0.2), distance_m=2.9,
                                            bbox_px=(100, 220, 130, 250), area_px=800, disparity_px=20.0,
                                            confidence=0.5, confirmed=False)])


def _roundtrip(t, msg):
    raw = t.serialize(msg)
    assert raw[:4] == b"\x00\x01\x00\x00"  # CDR little endian encapsulation header
    return t.deserialize(raw, msg.__msgtype__)


def test_detections_and_markers_carry_ids_positions_sizes(jazzy):
    d = _roundtrip(jazzy, convert.detections(jazzy, _obstacles(), "cam"))
    assert d.header.frame_id == "cam" and convert.stamp_ns(d.header.stamp) == STAMP
    assert [x.id for x in d.detections] == ["7", "9"]
    b = d.detections[0].bbox
    assert (b.center.position.x, b.center.position.y, b.center.position.z) == (0.2, 0.1, 2.0)
    assert (b.size.x, b.size.y, b.size.z) == (0.4, 0.5, 0.3) and b.center.orientation.w == 1.0
    assert d.detections[0].results[0].hypothesis.score == pytest.approx(0.8)
    m = _roundtrip(jazzy, convert.markers(jazzy, _obstacles(), "cam", 0.5))
    assert m.markers[0].action == 3  # DELETEALL first
    cubes = [x for x in m.markers if x.ns == "obstacles" and x.type == 1]
    assert [c.id for c in cubes] == [7, 9] and cubes[0].lifetime.nanosec == 500_000_000
    assert any(x.text == "7: 1.85 m" for x in m.markers)


def test_diagnostics_say_how_far_each_list_can_be_trusted(jazzy):
    """An empty Detection3DArray reads as a clear way: /diagnostics says whether it is one."""
    def status(**change):
        lst = ObstacleList(robot_id="r", seq=5, stamp_ns=STAMP, publish_ns=STAMP, stale=False, obstacles=[],
                           valid_fraction=0.4, range_m=(1.0, 4.5), bearing_deg=(-20.4, 26.2),
                           ground=GroundEstimate(height_m=1.0, pitch_deg=15.0, roll_deg=0.0, source="fitted",
                                                 confidence=0.8))
        a = _roundtrip(jazzy, convert.trust(jazzy, lst.model_copy(update=change), "/ballbot_vision: obstacles"))
        assert convert.stamp_ns(a.header.stamp) == STAMP and len(a.status) == 1
        s = a.status[0]
        assert s.name == "/ballbot_vision: obstacles" and s.hardware_id == "r"
        return s.level, s.message, {kv.key: kv.value for kv in s.values}

    level, text, kv = status()
    assert level == 0 and "looked and saw nothing" in text
    assert kv == {"seq": "5", "stamp_ns": str(STAMP), "obstacles": "0", "degraded": "", "stale": "false",
                  "valid_fraction": "0.400", "range_m": "1.00-4.50", "bearing_deg": "-20.4..26.2",
                  "ground_source": "fitted",
                  "ground_confidence": "0.80"}
    level, text, kv = status(degraded=["near-unmeasured", "ground-uncertain"])
    assert level == 1 and "near-unmeasured, ground-uncertain" in text and "not a clear way" in text
    assert kv["degraded"] == "near-unmeasured,ground-uncertain"
    level, text, kv = status(stale=True, degraded=["ground-uncertain"])
    assert level == 3 and text.startswith("stale") and kv["stale"] == "true"


def _disparity_with_boxes() -> DisparityMap:
    f, B, cx, cy = 500.0, 0.1, 320.0, 240.0
    d = np.zeros((480, 640), np.float32)
    d[200:300, 310:400] = f * B / 2.0  # a wall at z = 2 m inside obstacle 7's box ...
    d[200:210, 310:400] = f * B / 6.0  # ... with background at 6 m in its top rows
    raw = np.round(d * 16).astype(np.int16)
    model = CameraModel(width=640, height=480, focal_px=f, cx=cx, cy=cy, baseline_m=B,
                        Q=[float(x) for x in camera.RectifiedModel(640, 480, f, cx, cy, B).Q.ravel()])
    return DisparityMap(robot_id="r", seq=5, stamp_ns=STAMP, image=codec.image_from_array(raw), scale=16.0,
                        invalid_value=0, min_disparity=0, num_disparities=64, camera=model, method="bm")


def test_obstacle_points_keep_only_what_lies_in_the_3d_box(jazzy):
    pts, ids = convert.obstacle_points(_disparity_with_boxes(), _obstacles(), margin_m=0.05)
    assert len(pts) == 90 * 90 and set(ids.tolist()) == {7}  # the 6 m rows are not the obstacle's
    assert np.allclose(pts[:, 2], 2.0, atol=1e-3)
    pc = _roundtrip(jazzy, convert.point_cloud(jazzy, pts, ids, STAMP, "cam"))
    rec = np.frombuffer(bytes(pc.data), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("id", "<u4")])
    assert pc.width == len(pts) and pc.point_step == 16 and [f.name for f in pc.fields] == ["x", "y", "z", "id"]
    assert np.allclose(rec["z"], pts[:, 2]) and set(rec["id"].tolist()) == {7}
    few, _ = convert.obstacle_points(_disparity_with_boxes(), _obstacles(), max_points=100)
    assert len(few) == 100


def test_image_and_camera_info_of_a_rectified_frame(jazzy):
    left = (np.arange(480 * 640 * 3) % 251).astype(np.uint8).reshape(480, 640, 3)
    model = CameraModel(width=640, height=480, focal_px=600.0, cx=310.0, cy=230.0, baseline_m=0.1, Q=[0.0] * 16)
    fr = StereoFrame(robot_id="r", seq=1, stamp_ns=STAMP, left=codec.image_from_array(left, "png"),
                     right=codec.image_from_array(left), camera=model)
    img, info = (_roundtrip(jazzy, m) for m in convert.image(jazzy, fr, "cam"))
    assert (img.encoding, img.width, img.height, img.step) == ("bgr8", 640, 480, 1920)
    assert np.array_equal(convert.array_from_ros_image(img, "t"), left)
    assert list(info.p) == [600, 0, 310, 0, 0, 600, 230, 0, 0, 0, 1, 0] and list(info.d) == [0] * 5
    with pytest.raises(DecodeError, match="camera model"):
        convert.image(jazzy, fr.model_copy(update={"camera": None}), "cam")


def test_occupancy_grid_keeps_the_freespace_layout(jazzy):
    cells = np.array([-1, 0, 100, 0, 0, -1], np.int8)
    fs = FreeSpace(robot_id="r", seq=1, stamp_ns=STAMP, publish_ns=STAMP, resolution_m=0.05, width=3, height=2,
                   origin_m=(0.2, -0.05), cells=cells.tobytes())
    g = _roundtrip(jazzy, convert.occupancy_grid(jazzy, fs, "base_link"))
    assert (g.info.width, g.info.height, g.info.resolution) == (3, 2, pytest.approx(0.05))
    assert (g.info.origin.position.x, g.info.origin.position.y) == (0.2, -0.05)
    assert np.array_equal(g.data, cells) and g.header.frame_id == "base_link"
    with pytest.raises(DecodeError, match="6 cells|cells for"):
        convert.occupancy_grid(jazzy, fs.model_copy(update={"width": 4}), "base_link")


def test_tf_static_maps_camera_points_as_the_mount_does(jazzy):
    from scipy.spatial.transform import Rotation

    mount = Mount(height_m=0.9, pitch_deg=20.0, yaw_deg=10.0, roll_deg=-3.0, x_m=0.1, y_m=0.02)
    tf = _roundtrip(jazzy, convert.tf_static(jazzy, mount, STAMP, "base_link", "cam"))
    ts = tf.transforms[0]
    assert (ts.header.frame_id, ts.child_frame_id) == ("base_link", "cam")
    q = ts.transform.rotation
    t = ts.transform.translation
    p_cam = np.array([0.3, -0.2, 2.5])
    p_base = Rotation.from_quat([q.x, q.y, q.z, q.w]).apply(p_cam) + [t.x, t.y, t.z]
    assert np.allclose(p_base, mount.to_base(p_cam), atol=1e-9)


def test_mount_is_the_one_the_list_carries_else_the_configured_one():
    from common.messages import CameraMount
    from common.settings import MountSettings

    s, configured = Ros2Settings(), MountSettings(yaw_deg=5.0)
    assert mount_from(_obstacles(), configured) is None  # nothing known yet
    lst = _obstacles().model_copy(update={"mount": CameraMount(height_m=1.1, pitch_deg=12.0, roll_deg=1.0,
                                                               yaw_deg=5.0, source="ground")})
    m = mount_from(lst, configured)
    assert (m.height_m, m.pitch_deg, m.roll_deg, m.yaw_deg) == (1.1, 12.0, 1.0, 5.0)
    assert mount_from(_obstacles(), MountSettings(height_m=0.8, pitch_deg=10.0)).height_m == 0.8
    assert mount_moved(None, m, s) and not mount_moved(m, m, s)
    assert mount_moved(m, Mount(1.1, 14.0, 5.0, 1.0), s)


# --- the other way: ROS camera messages in ---------------------------------------------------------

def _ros_image(t, a: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False):
    rows = a.reshape(a.shape[0], -1).view(np.uint8) if a.dtype != np.uint8 else a.reshape(a.shape[0], -1)
    if bigendian:
        rows = a.astype(">u2").reshape(a.shape[0], -1).view(np.uint8)
    data = np.concatenate([rows, np.zeros((a.shape[0], pad), np.uint8)], axis=1)
    return t.new("sensor_msgs/msg/Image", height=a.shape[0], width=a.shape[1], encoding=encoding,
                 is_bigendian=int(bigendian), step=data.shape[1], data=data.ravel())


def test_ros_images_decode_with_padding_colour_order_and_endianness(jazzy):
    import cv2

    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 255, (6, 8, 3), dtype=np.uint8)
    rgb = bgr[..., ::-1].copy()
    assert np.array_equal(convert.array_from_ros_image(_ros_image(jazzy, rgb, "rgb8", pad=4), "t"), bgr)
    mono16 = rng.integers(0, 65535, (5, 7), dtype=np.uint16)
    assert np.array_equal(convert.array_from_ros_image(_ros_image(jazzy, mono16, "mono16", bigendian=True), "t"),
                          mono16)
    yuyv = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_YUY2) if hasattr(cv2, "COLOR_BGR2YUV_YUY2") else None
    if yuyv is not None:
        out = convert.array_from_ros_image(_ros_image(jazzy, yuyv.reshape(6, 8, 2), "yuv422_yuy2"), "t")
        assert out.shape == (6, 8, 3)
    ok, jpg = cv2.imencode(".png", bgr)
    comp = jazzy.new("sensor_msgs/msg/CompressedImage", format="bgr8; png compressed bgr8", data=jpg.ravel())
    assert np.array_equal(convert.array_from_compressed(comp, "t"), bgr)


@pytest.mark.parametrize("change,err", [({"encoding": "32FC4"}, "not supported"), ({"step": 3}, "step"),
                                        ({"height": 50}, "bytes of data")])
def test_bad_ros_images_are_named(jazzy, change, err):
    msg = _ros_image(jazzy, np.zeros((4, 4), np.uint8), "mono8")
    for k, v in change.items():
        setattr(msg, k, v)
    with pytest.raises(DecodeError, match=err):
        convert.array_from_ros_image(msg, "/cam/left/image_raw")
    with pytest.raises(DecodeError, match="does not decode"):
        convert.array_from_compressed(jazzy.new("sensor_msgs/msg/CompressedImage", format="jpeg",
                                                data=np.arange(50, dtype=np.uint8)), "/x/compressed")


def camera_infos(t, rig: camera.RawRig):
    """The CameraInfo pair camera_calibration's stereo calibrator would publish for a rig."""
    r = camera.rectify_rig(rig)
    out = []
    for cam, R, P in ((rig.left, r.R1, r.P1), (rig.right, r.R2, r.P2)):
        out.append(t.new("sensor_msgs/msg/CameraInfo", width=rig.image_size[0], height=rig.image_size[1],
                         distortion_model="plumb_bob", d=cam.D.copy(), k=cam.K.ravel().copy(), r=R.ravel().copy(),
                         p=P.ravel().copy()))
    return out


def test_calibration_from_camera_infos_recovers_the_rig(jazzy):
    rig = camera.load_calibration("lifecam-studio")
    left, right = camera_infos(jazzy, rig)
    got = convert.calibration_from_camera_infos(left, right, rectified=False)
    assert np.allclose(got.R, rig.R, atol=1e-9) and np.allclose(got.T, rig.T, atol=1e-9)
    assert np.allclose(got.left.K, rig.left.K) and np.allclose(got.right.D, rig.right.D)
    rect = convert.calibration_from_camera_infos(left, right, rectified=True)
    assert rect.model.baseline_m == pytest.approx(np.linalg.norm(rig.T), rel=1e-3)
    bad = jazzy.new("sensor_msgs/msg/CameraInfo", width=640, height=480)
    with pytest.raises(CalibrationError, match="camera matrix"):
        convert.calibration_from_camera_infos(bad, right, rectified=False)
    with pytest.raises(CalibrationError, match="baseline"):
        convert.calibration_from_camera_infos(left, left, rectified=True)
    small = camera_infos(jazzy, rig)[1]
    small.width = 320
    with pytest.raises(CalibrationError, match="size"):
        convert.calibration_from_camera_infos(left, small, rectified=False)


def test_stamp_pairer_pairs_within_the_skew_and_drops_the_rest():
    p = StampPairer(max_skew_ns=5_000_000)
    assert p.offer("left", 100_000_000, "L1") is None
    pair = p.offer("right", 102_000_000, "R1")
    assert (pair[0].value, pair[1].value) == ("L1", "R1")
    assert p.offer("left", 200_000_000, "L2") is None
    assert p.offer("left", 233_000_000, "L3") is None       # L2's partner never came
    pair = p.offer("right", 234_000_000, "R3")
    assert (pair[0].value, pair[1].value) == ("L3", "R3") and p.unpaired == 1
    assert p.offer("right", 150_000_000, "late") is None and p.unpaired == 2  # older than a pair made
    assert p.offer("right", 300_000_000, "R4") is None and p.offer("left", 320_000_000, "L5") is None


def test_camera_info_beside_the_image_topic():
    assert camera_info_topic("/stereo/left/image_raw") == "/stereo/left/camera_info"
    assert camera_info_topic("/stereo/left/image_raw/compressed") == "/stereo/left/camera_info"
