"""Our messages as ROS 2 messages, and ROS 2 camera messages as images and calibrations. Pure:
numpy and pydantic models in, rosbags message objects out (or back); no Zenoh.

Frames. The camera frame is the rectified left camera, optical (x right, y down, z forward, m),
the ROS `*_optical_frame` convention (REP 103/105), so camera-frame data is published in it
unchanged. The base frame is REP 103 (x forward, y left, z up); /tf_static links the two.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from common import codec
from common.errors import CalibrationError, DecodeError
from common.messages import DisparityMap, FreeSpace, Obstacle, ObstacleList, StereoFrame
from common.ros2.msgs import RosTypes
from cores import camera
from cores.segmentation.mount import Mount

# sensor_msgs/PointField datatypes
FLOAT32, UINT32 = 7, 6


def ros_time(t: RosTypes, stamp_ns: int) -> Any:
    return t.new("builtin_interfaces/msg/Time", sec=int(stamp_ns // 1_000_000_000),
                 nanosec=int(stamp_ns % 1_000_000_000))


def stamp_ns(time_msg: Any) -> int:
    return int(time_msg.sec) * 1_000_000_000 + int(time_msg.nanosec)


def header(t: RosTypes, stamp: int, frame_id: str) -> Any:
    return t.new("std_msgs/msg/Header", stamp=ros_time(t, stamp), frame_id=frame_id)


def _point(t: RosTypes, p) -> Any:
    return t.new("geometry_msgs/msg/Point", x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _pose(t: RosTypes, p, quat=(0.0, 0.0, 0.0, 1.0)) -> Any:
    q = t.new("geometry_msgs/msg/Quaternion", x=float(quat[0]), y=float(quat[1]), z=float(quat[2]), w=float(quat[3]))
    return t.new("geometry_msgs/msg/Pose", position=_point(t, p), orientation=q)


def _vec(t: RosTypes, v) -> Any:
    return t.new("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))


# --- obstacles ----------------------------------------------------------------------------------

CLASS_ID = "obstacle"


def detections(t: RosTypes, msg: ObstacleList, frame_id: str) -> Any:
    """vision_msgs/Detection3DArray in the camera frame: one Detection3D per obstacle, `id` the
    track id, bbox centre = 3D centroid, bbox size = extent (m), one hypothesis 'obstacle' whose
    score is the obstacle's confidence and whose pose is the centroid."""
    hdr = header(t, msg.stamp_ns, frame_id)
    out = []
    for o in msg.obstacles:
        hyp = t.new("vision_msgs/msg/ObjectHypothesisWithPose",
                    hypothesis=t.new("vision_msgs/msg/ObjectHypothesis", class_id=CLASS_ID, score=float(o.confidence)),
                    pose=t.new("geometry_msgs/msg/PoseWithCovariance", pose=_pose(t, o.position_m)))
        bbox = t.new("vision_msgs/msg/BoundingBox3D", center=_pose(t, o.position_m), size=_vec(t, o.size_m))
        out.append(t.new("vision_msgs/msg/Detection3D", header=hdr, results=[hyp], bbox=bbox, id=str(o.id)))
    return t.new("vision_msgs/msg/Detection3DArray", header=hdr, detections=out)


# diagnostic_msgs/DiagnosticStatus levels
DIAG_OK, DIAG_WARN, DIAG_STALE = 0, 1, 3


def trust(t: RosTypes, msg: ObstacleList, name: str) -> Any:
    """diagnostic_msgs/DiagnosticArray (for /diagnostics) saying how far an obstacle list can be
    trusted, which a Detection3DArray cannot: OK (an empty list means "looked and saw nothing"),
    WARN with the reasons in `degraded` (never take an empty list as a clear way), STALE (the input
    stopped or fell behind). name: the status's name (the node's); hardware_id: the robot."""
    if msg.stale:
        level, text = DIAG_STALE, "stale: the input stopped or fell behind; slow down or stop"
    elif msg.degraded:
        level, text = DIAG_WARN, (f"degraded: {', '.join(msg.degraded)}; an empty list is not a clear way")
    else:
        level, text = DIAG_OK, "trusted: an empty list means looked and saw nothing"
    g = msg.ground
    pairs = [("seq", str(msg.seq)), ("stamp_ns", str(msg.stamp_ns)), ("obstacles", str(len(msg.obstacles))),
             ("degraded", ",".join(msg.degraded)), ("stale", str(msg.stale).lower()),
             ("valid_fraction", f"{msg.valid_fraction:.3f}"),
             ("range_m", "" if msg.range_m is None else f"{msg.range_m[0]:.2f}-{msg.range_m[1]:.2f}"),
             ("bearing_deg", "" if msg.bearing_deg is None else f"{msg.bearing_deg[0]:.1f}..{msg.bearing_deg[1]:.1f}"),
             ("ground_source", g.source if g is not None else "none"),
             ("ground_confidence", f"{g.confidence:.2f}" if g is not None else "0.00")]
    status = t.new("diagnostic_msgs/msg/DiagnosticStatus", level=level, name=name, message=text,
                   hardware_id=msg.robot_id,
                   values=[t.new("diagnostic_msgs/msg/KeyValue", key=k, value=v) for k, v in pairs])
    return t.new("diagnostic_msgs/msg/DiagnosticArray", header=header(t, msg.stamp_ns, ""), status=[status])


def _color(t: RosTypes, o: Obstacle) -> Any:
    r, g, b, a = (0.95, 0.25, 0.1, 0.6) if o.confirmed else (0.95, 0.8, 0.1, 0.35)
    return t.new("std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=a)


def markers(t: RosTypes, msg: ObstacleList, frame_id: str, lifetime_s: float) -> Any:
    """visualization_msgs/MarkerArray for rviz: DELETEALL first (tracks that ended vanish), then
    per obstacle a CUBE (ns 'obstacles', id = track id; red when confirmed, yellow while not) and a
    TEXT_VIEW_FACING label 'id: distance m' above it (ns 'labels')."""
    hdr = header(t, msg.stamp_ns, frame_id)
    life = t.new("builtin_interfaces/msg/Duration", sec=int(lifetime_s), nanosec=int((lifetime_s % 1) * 1e9))
    out = [t.new("visualization_msgs/msg/Marker", header=hdr, ns="obstacles", id=0, action=3)]
    for o in msg.obstacles:
        out.append(t.new("visualization_msgs/msg/Marker", header=hdr, ns="obstacles", id=int(o.id), type=1,
                         action=0, pose=_pose(t, o.position_m), scale=_vec(t, np.maximum(o.size_m, 0.01)),
                         color=_color(t, o), lifetime=life))
        above = (o.position_m[0], o.position_m[1] - o.size_m[1] / 2 - 0.08, o.position_m[2])  # optical y is down
        out.append(t.new("visualization_msgs/msg/Marker", header=hdr, ns="labels", id=int(o.id), type=9, action=0,
                         pose=_pose(t, above), scale=_vec(t, (0.0, 0.0, 0.1)),
                         color=t.new("std_msgs/msg/ColorRGBA", r=1.0, g=1.0, b=1.0, a=0.9), lifetime=life,
                         text=f"{o.id}: {o.distance_m:.2f} m"))
    return t.new("visualization_msgs/msg/MarkerArray", markers=out)


def obstacle_points(disparity: DisparityMap, msg: ObstacleList, margin_m: float = 0.05,
                    max_points: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """The 3D points of each obstacle: pixels of the disparity map inside its image box whose
    point lies inside its 3D box (centroid +- size/2, widened by margin_m), camera frame.
    Returns (N, 3) float32 points (m) and (N,) uint32 track ids; at most max_points, evenly
    thinned."""
    d = codec.array_from_image(disparity.image, "disparity").astype(np.float32)
    valid = d != disparity.invalid_value
    d = d / disparity.scale
    cam = disparity.camera
    pts, ids = [], []
    for o in msg.obstacles:
        x0, y0, x1, y1 = (int(v) for v in o.bbox_px)
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, d.shape[1]), min(y1, d.shape[0])
        if x1 <= x0 or y1 <= y0:
            continue
        sub, ok = d[y0:y1, x0:x1], valid[y0:y1, x0:x1] & (d[y0:y1, x0:x1] > 0)
        v, u = np.nonzero(ok)
        if not v.size:
            continue
        z = cam.focal_px * cam.baseline_m / sub[v, u]
        x = (u + x0 - cam.cx) * z / cam.focal_px
        y = (v + y0 - cam.cy) * z / cam.focal_px
        p = np.stack([x, y, z], axis=1)
        lo = np.asarray(o.position_m) - np.asarray(o.size_m) / 2 - margin_m
        hi = np.asarray(o.position_m) + np.asarray(o.size_m) / 2 + margin_m
        p = p[np.all((p >= lo) & (p <= hi), axis=1)]
        pts.append(p.astype(np.float32))
        ids.append(np.full(len(p), o.id, np.uint32))
    if not pts:
        return np.zeros((0, 3), np.float32), np.zeros(0, np.uint32)
    p, i = np.concatenate(pts), np.concatenate(ids)
    if len(p) > max_points:
        keep = np.linspace(0, len(p) - 1, max_points).astype(int)
        p, i = p[keep], i[keep]
    return p, i


def point_cloud(t: RosTypes, points: np.ndarray, ids: np.ndarray, stamp: int, frame_id: str) -> Any:
    """sensor_msgs/PointCloud2, unordered (height 1), fields x, y, z (float32, m) and id (uint32,
    the obstacle's track id), 16 bytes per point, little endian."""
    rec = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("id", "<u4")])
    if len(points):
        rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
        rec["id"] = ids
    fields = [t.new("sensor_msgs/msg/PointField", name=n, offset=off, datatype=dt, count=1)
              for n, off, dt in (("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("id", 12, UINT32))]
    return t.new("sensor_msgs/msg/PointCloud2", header=header(t, stamp, frame_id), height=1, width=len(points),
                 fields=fields, is_bigendian=False, point_step=16, row_step=16 * len(points),
                 data=np.frombuffer(rec.tobytes(), np.uint8), is_dense=True)


# --- camera -------------------------------------------------------------------------------------

_ENCODINGS = {(1, "uint8"): "mono8", (3, "uint8"): "bgr8", (1, "uint16"): "mono16", (1, "float32"): "32FC1",
              (1, "int16"): "16SC1"}


def image(t: RosTypes, frame: StereoFrame, frame_id: str) -> tuple[Any, Any]:
    """The rectified left image of a rectified StereoFrame as sensor_msgs/Image, with its
    sensor_msgs/CameraInfo: a rectified pinhole camera, so K = [f 0 cx; 0 f cy; 0 0 1], no
    distortion, R = I and P = [K | 0]."""
    if frame.camera is None:
        raise DecodeError("image: the frame carries no camera model (not a rectified frame)")
    a = np.ascontiguousarray(codec.array_from_image(frame.left, "left"))
    channels = 1 if a.ndim == 2 else a.shape[2]
    enc = _ENCODINGS.get((channels, str(a.dtype)))
    if enc is None:
        raise DecodeError(f"image: no ROS encoding for {channels}-channel {a.dtype} images")
    hdr = header(t, frame.stamp_ns, frame_id)
    img = t.new("sensor_msgs/msg/Image", header=hdr, height=a.shape[0], width=a.shape[1], encoding=enc,
                is_bigendian=0, step=a.strides[0], data=np.frombuffer(a.tobytes(), np.uint8))
    c = frame.camera
    K = np.array([c.focal_px, 0, c.cx, 0, c.focal_px, c.cy, 0, 0, 1], np.float64)
    P = np.array([c.focal_px, 0, c.cx, 0, 0, c.focal_px, c.cy, 0, 0, 0, 1, 0], np.float64)
    info = t.new("sensor_msgs/msg/CameraInfo", header=hdr, height=c.height, width=c.width,
                 distortion_model="plumb_bob", d=np.zeros(5), k=K, r=np.eye(3).ravel(), p=P)
    return img, info


def occupancy_grid(t: RosTypes, fs: FreeSpace, frame_id: str) -> Any:
    """nav_msgs/OccupancyGrid from FreeSpace: same layout (row = y, column = x, origin at the outer
    corner of cell (0, 0), -1 unknown / 0 free / 100 occupied), base frame."""
    n = fs.width * fs.height
    if len(fs.cells) != n:
        raise DecodeError(f"freespace: {len(fs.cells)} cells for a {fs.width}x{fs.height} grid")
    info = t.new("nav_msgs/msg/MapMetaData", map_load_time=ros_time(t, fs.stamp_ns), resolution=float(fs.resolution_m),
                 width=fs.width, height=fs.height, origin=_pose(t, (fs.origin_m[0], fs.origin_m[1], 0.0)))
    return t.new("nav_msgs/msg/OccupancyGrid", header=header(t, fs.stamp_ns, frame_id), info=info,
                 data=np.frombuffer(fs.cells, np.int8).copy())


def tf_static(t: RosTypes, mount: Mount, stamp: int, base_frame: str, camera_frame: str) -> Any:
    """tf2_msgs/TFMessage with base_frame -> camera_frame (the optical frame) from the mount."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(mount.R_base_camera).as_quat()  # x, y, z, w
    tr = t.new("geometry_msgs/msg/Transform", translation=_vec(t, mount.origin_base),
               rotation=t.new("geometry_msgs/msg/Quaternion",
                              x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
    ts = t.new("geometry_msgs/msg/TransformStamped", header=header(t, stamp, base_frame),
               child_frame_id=camera_frame, transform=tr)
    return t.new("tf2_msgs/msg/TFMessage", transforms=[ts])


# --- the other way: ROS camera messages in ------------------------------------------------------

def array_from_ros_image(msg: Any, where: str) -> np.ndarray:
    """sensor_msgs/Image -> (H, W) grey or (H, W, 3) BGR array (uint8, or uint16 for mono16).
    Raises DecodeError naming the topic (`where`) and what is wrong."""
    import cv2

    h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), str(msg.encoding).lower()
    layouts = {"mono8": (1, np.uint8), "8uc1": (1, np.uint8), "mono16": (1, np.uint16), "16uc1": (1, np.uint16),
               "bgr8": (3, np.uint8), "rgb8": (3, np.uint8), "8uc3": (3, np.uint8), "bgra8": (4, np.uint8),
               "rgba8": (4, np.uint8), "yuv422": (2, np.uint8), "uyvy": (2, np.uint8), "yuv422_yuy2": (2, np.uint8),
               "yuyv": (2, np.uint8), "bayer_rggb8": (1, np.uint8), "bayer_bggr8": (1, np.uint8),
               "bayer_gbrg8": (1, np.uint8), "bayer_grbg8": (1, np.uint8)}
    if enc not in layouts:
        raise DecodeError(f"{where}: image encoding {msg.encoding!r} is not supported "
                          f"({', '.join(sorted(layouts))})")
    ch, dt = layouts[enc]
    row = w * ch * np.dtype(dt).itemsize
    if h <= 0 or w <= 0 or step < row:
        raise DecodeError(f"{where}: {w}x{h} {enc} image with step {step} (a row needs {row} bytes)")
    data = np.asarray(msg.data, np.uint8)
    if data.size < step * h:
        raise DecodeError(f"{where}: {data.size} bytes of data for {h} rows of {step} bytes")
    rows = data[: step * h].reshape(h, step)[:, :row]
    a = np.ascontiguousarray(rows).view(np.dtype(dt).newbyteorder(">" if msg.is_bigendian else "<"))
    a = a.astype(dt, copy=False).reshape((h, w, ch) if ch > 1 else (h, w))
    if enc in ("rgb8",):
        return cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
    if enc == "bgra8":
        return cv2.cvtColor(a, cv2.COLOR_BGRA2BGR)
    if enc == "rgba8":
        return cv2.cvtColor(a, cv2.COLOR_RGBA2BGR)
    if enc in ("yuv422", "uyvy"):
        return cv2.cvtColor(a, cv2.COLOR_YUV2BGR_UYVY)
    if enc in ("yuv422_yuy2", "yuyv"):
        return cv2.cvtColor(a, cv2.COLOR_YUV2BGR_YUY2)
    if enc.startswith("bayer_"):
        code = {"rggb8": cv2.COLOR_BayerRG2BGR, "bggr8": cv2.COLOR_BayerBG2BGR, "gbrg8": cv2.COLOR_BayerGB2BGR,
                "grbg8": cv2.COLOR_BayerGR2BGR}[enc[6:]]
        return cv2.cvtColor(a, code)
    return a


def array_from_compressed(msg: Any, where: str) -> np.ndarray:
    """sensor_msgs/CompressedImage (jpeg or png, as image_transport's compressed plugin sends)
    -> (H, W) grey or (H, W, 3) BGR array."""
    import cv2

    data = np.asarray(msg.data, np.uint8)
    a = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if a is None:
        raise DecodeError(f"{where}: compressed image ({msg.format!r}, {data.size} bytes) does not decode")
    if a.ndim == 3 and a.shape[2] == 4:
        a = cv2.cvtColor(a, cv2.COLOR_BGRA2BGR)
    if a.ndim == 3 and "rgb8" in str(msg.format).split(";")[0]:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)  # image_transport wrote an rgb8 image's bytes as they were
    return a


def _camera_info(msg: Any, where: str) -> dict:
    model = str(msg.distortion_model) or "plumb_bob"
    d = np.asarray(msg.d, np.float64).ravel()
    if model not in ("plumb_bob", "rational_polynomial") and np.any(d != 0):
        raise CalibrationError(f"{where}: distortion model {model!r} is not supported (plumb_bob)")
    K, R, P = (np.asarray(getattr(msg, f), np.float64).reshape(shape) for f, shape in
               (("k", (3, 3)), ("r", (3, 3)), ("p", (3, 4))))
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(P))) or K[0, 0] <= 0 or P[0, 0] <= 0:
        raise CalibrationError(f"{where}: CameraInfo without a camera matrix (K or P is zero or not finite)")
    if int(msg.width) <= 0 or int(msg.height) <= 0:
        raise CalibrationError(f"{where}: CameraInfo with image size {msg.width}x{msg.height}")
    if np.allclose(R, 0):
        R = np.eye(3)
    return {"size": (int(msg.width), int(msg.height)), "K": K, "D": d, "R": R, "P": P, "where": where}


def calibration_from_camera_infos(left: Any, right: Any, rectified: bool,
                                  where: str = "CameraInfo") -> camera.Calibration:
    """A stereo calibration from the left and right sensor_msgs/CameraInfo, as
    camera_calibration's stereo calibrator writes them: rectified=True for image_rect topics (only
    the projection matrices count: f, cx, cy and baseline = -P_right[0,3] / P_right[0,0]); otherwise
    a raw rig: each camera's K and distortion, and the right camera's pose from R and P of both."""
    a, b = _camera_info(left, f"{where} left"), _camera_info(right, f"{where} right")
    if a["size"] != b["size"]:
        raise CalibrationError(f"{where}: left image size {a['size']} differs from right {b['size']}")
    Pl, Pr = a["P"], b["P"]
    if rectified:
        baseline = -Pr[0, 3] / Pr[0, 0]
        if not baseline > 0:
            raise CalibrationError(f"{where} right: P[0,3] = {Pr[0, 3]:g} gives no positive baseline "
                                   "(-fx * baseline expected for the right camera)")
        model = camera.RectifiedModel(a["size"][0], a["size"][1], float(Pl[0, 0]), float(Pl[0, 2]), float(Pl[1, 2]),
                                      float(baseline))
        return camera.RectifiedRig(model, name="ros2 camera_info")
    from cores.calibration.formats import rig_from_ros_cameras

    return rig_from_ros_cameras(a, b, "ros2 camera_info", fields=("R", "P"))
