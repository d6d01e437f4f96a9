"""Foxglove message schemas (JSON encoding) and builders from this project's messages. Pure: no
Zenoh, no file I/O.

A recording opens in Foxglove with no plugin because every channel uses a schema Foxglove knows
by name (`foxglove.CompressedImage`, `foxglove.ImageAnnotations`, ...), encoded as `jsonschema`,
with `json` messages; bytes fields are base64 strings, as Foxglove's JSON convention has it. The
schemas below describe the fields we write (Foxglove reads a message by its schema's name).

Frames: "camera" is the rectified left camera (x right, y down, z forward, m); "camera_raw" the
unrectified left camera; "base" the robot base (REP 103), present when the mount is known.
"""
from __future__ import annotations

import base64
from typing import Any

from common.messages import CameraModel, FreeSpace, GroundTruth, ObstacleList

# -- schema building blocks ------------------------------------------------------------------------

_NUM = {"type": "number"}
_INT = {"type": "integer"}
_STR = {"type": "string"}
_BYTES = {"type": "string", "contentEncoding": "base64"}
_TIME = {"type": "object", "title": "time", "properties": {"sec": {"type": "integer", "minimum": 0},
                                                            "nsec": {"type": "integer", "minimum": 0,
                                                                     "maximum": 999_999_999}}}
_DURATION = {"type": "object", "title": "duration", "properties": {"sec": _INT, "nsec": _INT}}


def _obj(title: str, **props: Any) -> dict:
    return {"title": title, "type": "object", "properties": props}


def _arr(items: dict) -> dict:
    return {"type": "array", "items": items}


_COLOR = _obj("foxglove.Color", r=_NUM, g=_NUM, b=_NUM, a=_NUM)
_POINT2 = _obj("foxglove.Point2", x=_NUM, y=_NUM)
_VEC3 = _obj("foxglove.Vector3", x=_NUM, y=_NUM, z=_NUM)
_QUAT = _obj("foxglove.Quaternion", x=_NUM, y=_NUM, z=_NUM, w=_NUM)
_POSE = _obj("foxglove.Pose", position=_VEC3, orientation=_QUAT)
_KV = _obj("foxglove.KeyValuePair", key=_STR, value=_STR)

SCHEMAS: dict[str, dict] = {
    "foxglove.CompressedImage": _obj("foxglove.CompressedImage", timestamp=_TIME, frame_id=_STR, data=_BYTES,
                                     format=_STR),
    "foxglove.CameraCalibration": _obj("foxglove.CameraCalibration", timestamp=_TIME, frame_id=_STR, width=_INT,
                                       height=_INT, distortion_model=_STR, D=_arr(_NUM), K=_arr(_NUM),
                                       R=_arr(_NUM), P=_arr(_NUM)),
    "foxglove.ImageAnnotations": _obj(
        "foxglove.ImageAnnotations",
        circles=_arr(_obj("foxglove.CircleAnnotation", timestamp=_TIME, position=_POINT2, diameter=_NUM,
                          thickness=_NUM, fill_color=_COLOR, outline_color=_COLOR)),
        points=_arr(_obj("foxglove.PointsAnnotation", timestamp=_TIME, type=_INT, points=_arr(_POINT2),
                         outline_color=_COLOR, outline_colors=_arr(_COLOR), fill_color=_COLOR, thickness=_NUM)),
        texts=_arr(_obj("foxglove.TextAnnotation", timestamp=_TIME, position=_POINT2, text=_STR, font_size=_NUM,
                        text_color=_COLOR, background_color=_COLOR))),
    "foxglove.SceneUpdate": _obj(
        "foxglove.SceneUpdate",
        deletions=_arr(_obj("foxglove.SceneEntityDeletion", timestamp=_TIME, type=_INT, id=_STR)),
        entities=_arr(_obj("foxglove.SceneEntity", timestamp=_TIME, frame_id=_STR, id=_STR, lifetime=_DURATION,
                           frame_locked={"type": "boolean"}, metadata=_arr(_KV),
                           arrows=_arr({"type": "object"}), spheres=_arr({"type": "object"}),
                           cylinders=_arr({"type": "object"}), lines=_arr({"type": "object"}),
                           triangles=_arr({"type": "object"}), models=_arr({"type": "object"}),
                           cubes=_arr(_obj("foxglove.CubePrimitive", pose=_POSE, size=_VEC3, color=_COLOR)),
                           texts=_arr(_obj("foxglove.TextPrimitive", pose=_POSE, billboard={"type": "boolean"},
                                           font_size=_NUM, scale_invariant={"type": "boolean"}, color=_COLOR,
                                           text=_STR))))),
    "foxglove.Grid": _obj("foxglove.Grid", timestamp=_TIME, frame_id=_STR, pose=_POSE, column_count=_INT,
                          cell_size=_obj("foxglove.Vector2", x=_NUM, y=_NUM), row_stride=_INT, cell_stride=_INT,
                          fields=_arr(_obj("foxglove.PackedElementField", name=_STR, offset=_INT, type=_INT)),
                          data=_BYTES),
    "foxglove.FrameTransform": _obj("foxglove.FrameTransform", timestamp=_TIME, parent_frame_id=_STR,
                                    child_frame_id=_STR, translation=_VEC3, rotation=_QUAT),
}

# foxglove.PointsAnnotationType / SceneEntityDeletionType / NumericType values we use
LINE_LOOP = 2
DELETE_ALL = 1
NUMERIC_INT8 = 2

OBSTACLE_RGBA = (1.0, 0.55, 0.0, 1.0)  # orange boxes: detections
TRUTH_RGBA = (0.2, 0.9, 0.3, 1.0)  # green boxes: the synthetic scene's truth


def timestamp(ns: int) -> dict:
    return {"sec": int(ns) // 1_000_000_000, "nsec": int(ns) % 1_000_000_000}


def color(rgba: tuple[float, float, float, float]) -> dict:
    return {"r": rgba[0], "g": rgba[1], "b": rgba[2], "a": rgba[3]}


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def compressed_image(stamp_ns: int, frame_id: str, data: bytes, fmt: str) -> dict:
    """fmt: 'jpeg' or 'png'."""
    return {"timestamp": timestamp(stamp_ns), "frame_id": frame_id, "data": b64(data), "format": fmt}


def camera_calibration(stamp_ns: int, cam: CameraModel, frame_id: str = "camera") -> dict:
    """The rectified left camera: no distortion, P = K | 0 (Foxglove projects 3D boxes with P)."""
    f, cx, cy = cam.focal_px, cam.cx, cam.cy
    return {"timestamp": timestamp(stamp_ns), "frame_id": frame_id, "width": cam.width, "height": cam.height,
            "distortion_model": "plumb_bob", "D": [0.0] * 5, "K": [f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0],
            "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "P": [f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0]}


def _box(stamp: dict, bbox: tuple[int, int, int, int], rgba) -> dict:
    x0, y0, x1, y1 = (float(v) for v in bbox)
    return {"timestamp": stamp, "type": LINE_LOOP, "points": [{"x": x0, "y": y0}, {"x": x1, "y": y0},
                                                               {"x": x1, "y": y1}, {"x": x0, "y": y1}],
            "outline_color": color(rgba), "outline_colors": [], "fill_color": color((0, 0, 0, 0)), "thickness": 2.0}


def _label(stamp: dict, x: float, y: float, text: str, rgba) -> dict:
    return {"timestamp": stamp, "position": {"x": float(x), "y": float(max(y, 14.0))}, "text": text,
            "font_size": 14.0, "text_color": color((0, 0, 0, 1)), "background_color": color(rgba)}


def obstacle_annotations(msg: ObstacleList) -> dict:
    """Each obstacle's box, `#id d.dd m` label, on the rectified left image."""
    stamp = timestamp(msg.stamp_ns)
    points, texts = [], []
    for o in msg.obstacles:
        points.append(_box(stamp, o.bbox_px, OBSTACLE_RGBA))
        texts.append(_label(stamp, o.bbox_px[0], o.bbox_px[1] - 3, f"#{o.id} {o.distance_m:.2f} m", OBSTACLE_RGBA))
    return {"circles": [], "points": points, "texts": texts}


def truth_annotations(msg: GroundTruth) -> dict:
    stamp = timestamp(msg.stamp_ns)
    shown = [t for t in msg.obstacles if t.bbox_px is not None]
    return {"circles": [], "points": [_box(stamp, t.bbox_px, TRUTH_RGBA) for t in shown],
            "texts": [_label(stamp, t.bbox_px[0], t.bbox_px[3] + 16, f"{t.name} {t.nearest_m:.2f} m", TRUTH_RGBA)
                      for t in shown]}


def _entity(stamp: dict, frame_id: str, id_: str, cubes: list, texts: list) -> dict:
    return {"timestamp": stamp, "frame_id": frame_id, "id": id_, "lifetime": {"sec": 0, "nsec": 0},
            "frame_locked": False, "metadata": [], "arrows": [], "cubes": cubes, "spheres": [], "cylinders": [],
            "lines": [], "triangles": [], "texts": texts, "models": []}


_IDENTITY = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}


def obstacle_scene(msg: ObstacleList) -> dict:
    """3D boxes in the camera frame (axis-aligned with it: size_m is the extent along camera x, y, z).
    Every update replaces the previous one (a DELETE_ALL first), so vanished tracks disappear."""
    stamp = timestamp(msg.stamp_ns)
    entities = []
    for o in msg.obstacles:
        x, y, z = o.position_m
        pose = {"position": {"x": x, "y": y, "z": z}, "orientation": _IDENTITY}
        cube = {"pose": pose, "size": dict(zip("xyz", o.size_m)), "color": color(OBSTACLE_RGBA[:3] + (0.5,))}
        label = {"pose": {"position": {"x": x, "y": y - o.size_m[1] / 2 - 0.1, "z": z}, "orientation": _IDENTITY},
                 "billboard": True, "font_size": 14.0, "scale_invariant": True, "color": color((1, 1, 1, 1)),
                 "text": f"#{o.id} {o.distance_m:.2f} m"}
        entities.append(_entity(stamp, "camera", f"obstacle-{o.id}", [cube], [label]))
    return {"deletions": [{"timestamp": stamp, "type": DELETE_ALL, "id": ""}], "entities": entities}


def freespace_grid(msg: FreeSpace) -> dict:
    """The occupancy grid as a foxglove.Grid in the base frame: one int8 field `occupancy`
    (-1 unknown, 0 free, 100 occupied); FreeSpace's row/col layout is already Foxglove's
    (columns along x, rows along y, from the corner at origin_m)."""
    ox, oy = msg.origin_m
    return {"timestamp": timestamp(msg.stamp_ns), "frame_id": "base",
            "pose": {"position": {"x": ox, "y": oy, "z": 0.0}, "orientation": _IDENTITY},
            "column_count": msg.width, "cell_size": {"x": msg.resolution_m, "y": msg.resolution_m},
            "row_stride": msg.width, "cell_stride": 1,
            "fields": [{"name": "occupancy", "offset": 0, "type": NUMERIC_INT8}], "data": b64(msg.cells)}


def base_to_camera(stamp_ns: int, height_m: float, pitch_deg: float, roll_deg: float) -> dict:
    """foxglove.FrameTransform base -> camera: the camera `height_m` above the base origin, pitched
    and rolled as the segmenter's ground estimate says (conventions of segmentation/mount.py)."""
    from scipy.spatial.transform import Rotation

    from cores.segmentation.mount import Mount

    mount = Mount(height_m=height_m, pitch_deg=pitch_deg, roll_deg=roll_deg)
    q = Rotation.from_matrix(mount.R_base_camera).as_quat()  # x, y, z, w
    x, y, z = (float(v) for v in mount.origin_base)
    return {"timestamp": timestamp(stamp_ns), "parent_frame_id": "base", "child_frame_id": "camera",
            "translation": {"x": x, "y": y, "z": z},
            "rotation": {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}}
