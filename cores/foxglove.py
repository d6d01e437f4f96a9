"""Foxglove messages built from this project's messages with Foxglove's own SDK (`foxglove-sdk`):
the SDK's typed classes and their protobuf schemas, never hand-written ones. Used by the recording
format (cores/recording.py) and the live server (services/foxglove). Pure: no Zenoh, no file I/O.

Every builder returns an SDK message (`.encode()` gives its protobuf bytes, `type(msg).get_schema()`
its schema: name `foxglove.<Type>`, encoding `protobuf`, a FileDescriptorSet), so a recording or a
live channel opens in Foxglove with no plugin, and images travel as bytes, never base64.

Frames: "camera" is the rectified left camera (x right, y down, z forward, m); "camera_raw" the
unrectified left camera; "base" the robot base (REP 103), present when the mount is known.
"""
from __future__ import annotations

from typing import Any

from foxglove import messages as fm

from common.messages import CameraModel, CameraMount, FreeSpace, GroundTruth, ObstacleList

OBSTACLE_RGBA = (1.0, 0.55, 0.0, 1.0)  # orange boxes: detections
TRUTH_RGBA = (0.2, 0.9, 0.3, 1.0)  # green boxes: the synthetic scene's truth
WARNING_RGBA = (1.0, 0.42, 0.35, 1.0)  # red: a list that cannot vouch for its view (the viewer's colour)

# the SDK message classes by schema name (what a recording's channel names)
TYPES: dict[str, Any] = {f"foxglove.{name}": getattr(fm, name) for name in (
    "CompressedImage", "CameraCalibration", "ImageAnnotations", "SceneUpdate", "Grid", "FrameTransform")}


def timestamp(ns: int) -> fm.Timestamp:
    return fm.Timestamp(int(ns) // 1_000_000_000, int(ns) % 1_000_000_000)


def color(rgba: tuple[float, float, float, float]) -> fm.Color:
    return fm.Color(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]), a=float(rgba[3]))


def compressed_image(stamp_ns: int, frame_id: str, data: bytes, fmt: str) -> fm.CompressedImage:
    """fmt: 'jpeg' or 'png'; data: the encoded image's bytes as they are."""
    return fm.CompressedImage(timestamp=timestamp(stamp_ns), frame_id=frame_id, data=bytes(data), format=fmt)


def camera_calibration(stamp_ns: int, cam: CameraModel, frame_id: str = "camera") -> fm.CameraCalibration:
    """The rectified left camera: no distortion, P = K | 0 (Foxglove projects 3D boxes with P)."""
    f, cx, cy = float(cam.focal_px), float(cam.cx), float(cam.cy)
    return fm.CameraCalibration(timestamp=timestamp(stamp_ns), frame_id=frame_id, width=cam.width, height=cam.height,
                                distortion_model="plumb_bob", D=[0.0] * 5, K=[f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0],
                                R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                                P=[f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0])


def _box(stamp: fm.Timestamp, bbox: tuple[int, int, int, int], rgba) -> fm.PointsAnnotation:
    x0, y0, x1, y1 = (float(v) for v in bbox)
    return fm.PointsAnnotation(timestamp=stamp, type=fm.PointsAnnotationType.LineLoop,
                               points=[fm.Point2(x=x0, y=y0), fm.Point2(x=x1, y=y0), fm.Point2(x=x1, y=y1),
                                       fm.Point2(x=x0, y=y1)],
                               outline_color=color(rgba), fill_color=color((0, 0, 0, 0)), thickness=2.0)


def _label(stamp: fm.Timestamp, x: float, y: float, text: str, rgba) -> fm.TextAnnotation:
    return fm.TextAnnotation(timestamp=stamp, position=fm.Point2(x=float(x), y=float(max(y, 14.0))), text=text,
                             font_size=14.0, text_color=color((0, 0, 0, 1)), background_color=color(rgba))


def obstacle_annotations(msg: ObstacleList) -> fm.ImageAnnotations:
    """Each obstacle's box, `#id d.dd m` label, on the rectified left image; over a list that is stale
    or degraded, a red line at the top saying so (an image with no box would read as a clear way)."""
    stamp = timestamp(msg.stamp_ns)
    texts = [_label(stamp, o.bbox_px[0], o.bbox_px[1] - 3, f"#{o.id} {o.distance_m:.2f} m", OBSTACLE_RGBA)
             for o in msg.obstacles]
    warnings = msg.warnings()
    if warnings:
        texts.append(_label(stamp, 4.0, 18.0, " ".join(warnings), WARNING_RGBA))
    return fm.ImageAnnotations(timestamp=stamp, points=[_box(stamp, o.bbox_px, OBSTACLE_RGBA) for o in msg.obstacles],
                               texts=texts)


def truth_annotations(msg: GroundTruth) -> fm.ImageAnnotations:
    stamp = timestamp(msg.stamp_ns)
    shown = [(t, t.bbox_px) for t in msg.obstacles if t.bbox_px is not None]
    return fm.ImageAnnotations(
        timestamp=stamp, points=[_box(stamp, bbox, TRUTH_RGBA) for _, bbox in shown],
        texts=[_label(stamp, bbox[0], bbox[3] + 16, f"{t.name} {t.nearest_m:.2f} m", TRUTH_RGBA)
               for t, bbox in shown])


def _identity() -> fm.Quaternion:
    return fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


def obstacle_scene(msg: ObstacleList) -> fm.SceneUpdate:
    """3D boxes in the camera frame (axis-aligned with it: size_m is the extent along camera x, y, z).
    Every update replaces the previous one (a delete-all first), so vanished tracks disappear."""
    stamp = timestamp(msg.stamp_ns)
    entities = []
    for o in msg.obstacles:
        x, y, z = (float(v) for v in o.position_m)
        sx, sy, sz = (float(v) for v in o.size_m)
        cube = fm.CubePrimitive(pose=fm.Pose(position=fm.Vector3(x=x, y=y, z=z), orientation=_identity()),
                                size=fm.Vector3(x=sx, y=sy, z=sz), color=color(OBSTACLE_RGBA[:3] + (0.5,)))
        label = fm.TextPrimitive(pose=fm.Pose(position=fm.Vector3(x=x, y=y - sy / 2 - 0.1, z=z),
                                              orientation=_identity()),
                                 billboard=True, font_size=14.0, scale_invariant=True, color=color((1, 1, 1, 1)),
                                 text=f"#{o.id} {o.distance_m:.2f} m")
        entities.append(fm.SceneEntity(timestamp=stamp, frame_id="camera", id=f"obstacle-{o.id}",
                                       lifetime=fm.Duration(0, 0), cubes=[cube], texts=[label]))
    return fm.SceneUpdate(deletions=[fm.SceneEntityDeletion(timestamp=stamp, type=fm.SceneEntityDeletionType.All)],
                          entities=entities)


def freespace_grid(msg: FreeSpace) -> fm.Grid:
    """The occupancy grid as a foxglove.Grid in the base frame: one int8 field `occupancy`
    (-1 unknown, 0 free, 100 occupied); FreeSpace's row/col layout is already Foxglove's
    (columns along x, rows along y, from the corner at origin_m)."""
    ox, oy = (float(v) for v in msg.origin_m)
    r = float(msg.resolution_m)
    return fm.Grid(timestamp=timestamp(msg.stamp_ns), frame_id="base",
                   pose=fm.Pose(position=fm.Vector3(x=ox, y=oy, z=0.0), orientation=_identity()),
                   column_count=msg.width, cell_size=fm.Vector2(x=r, y=r), row_stride=msg.width, cell_stride=1,
                   fields=[fm.PackedElementField(name="occupancy", offset=0,
                                                 type=fm.PackedElementFieldNumericType.Int8)],
                   data=bytes(msg.cells))


def base_to_camera(stamp_ns: int, camera_mount: CameraMount) -> fm.FrameTransform:
    """base -> camera: where the segmenter placed the camera for this list (ObstacleList.mount:
    conventions of segmentation/mount.py)."""
    from scipy.spatial.transform import Rotation

    from cores.segmentation.mount import Mount

    mount = Mount.of(camera_mount)
    if mount is None:  # (a CameraMount always has a height: only settings may lack one)
        raise ValueError("base_to_camera: a mount without a camera height")
    q = Rotation.from_matrix(mount.R_base_camera).as_quat()  # x, y, z, w
    x, y, z = (float(v) for v in mount.origin_base)
    return fm.FrameTransform(timestamp=timestamp(stamp_ns), parent_frame_id="base", child_frame_id="camera",
                             translation=fm.Vector3(x=x, y=y, z=z),
                             rotation=fm.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


class ProtobufDecoder:
    """Decodes Foxglove messages by the schema a recording or a live server carries with them
    (the FileDescriptorSet of a `protobuf` schema), with Google's protobuf runtime: what a reader
    of the file or a client of the server would do, without trusting our own builders."""

    def __init__(self) -> None:
        self._classes: dict[tuple[str, bytes], Any] = {}

    def message_class(self, name: str, schema_data: bytes):
        key = (name, bytes(schema_data))
        if key not in self._classes:
            from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

            pool = descriptor_pool.DescriptorPool()
            for f in descriptor_pb2.FileDescriptorSet.FromString(bytes(schema_data)).file:
                pool.Add(f)
            self._classes[key] = message_factory.GetMessageClass(pool.FindMessageTypeByName(name))
        return self._classes[key]

    def decode(self, name: str, schema_data: bytes, data: bytes):
        return self.message_class(name, schema_data).FromString(bytes(data))


def ground_scene(msg: ObstacleList, size_m: float = 10.0) -> fm.SceneUpdate:
    """The ground the segmenter found for this list: a translucent square on the floor plane of the
    base frame (z = 0, in front of the robot), labelled with the camera's height, pitch and roll over
    it and where they came from; an empty update (delete-all only) when no ground is known."""
    stamp = timestamp(msg.stamp_ns)
    deletions = [fm.SceneEntityDeletion(timestamp=stamp, type=fm.SceneEntityDeletionType.All)]
    g = msg.ground
    if g is None or g.source == "none":
        return fm.SceneUpdate(deletions=deletions)
    floor = fm.CubePrimitive(pose=fm.Pose(position=fm.Vector3(x=size_m / 2, y=0.0, z=-0.005), orientation=_identity()),
                             size=fm.Vector3(x=size_m, y=size_m, z=0.01), color=color((0.3, 0.6, 1.0, 0.25)))
    label = fm.TextPrimitive(pose=fm.Pose(position=fm.Vector3(x=1.0, y=0.0, z=0.05), orientation=_identity()),
                             billboard=True, font_size=14.0, scale_invariant=True, color=color((1, 1, 1, 1)),
                             text=f"ground ({g.source}): camera {g.height_m:.2f} m above, "
                                  f"pitch {g.pitch_deg:+.1f} deg, roll {g.roll_deg:+.1f} deg")
    return fm.SceneUpdate(deletions=deletions, entities=[
        fm.SceneEntity(timestamp=stamp, frame_id="base", id="ground", lifetime=fm.Duration(0, 0), cubes=[floor],
                       texts=[label])])
