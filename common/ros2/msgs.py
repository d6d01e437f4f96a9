"""ROS 2 message types and CDR, from rosbags: its typestores for Humble and Jazzy, plus the
vision_msgs definitions rosbags does not ship (registered from their .msg text, vision_msgs 4.x as
both distros release it). `RosTypes.new()` builds a message with every field not given at its ROS
default, so converters name only what they fill in.

CDR: rosbags' serialize_cdr writes the 4-byte encapsulation header (00 01 00 00: CDR, little
endian) and the plain XCDR1 body that rmw_zenoh's Fast-CDR typesupport writes and reads.
"""
from __future__ import annotations

from functools import cache
from typing import Any

import numpy as np

from common.ros2.rmw import TYPE_HASH_NOT_SUPPORTED, Distro, dds_type_name, distro

# vision_msgs 4.x (the ROS 2 Humble and Jazzy releases). Comments dropped: they change neither the
# wire format nor the RIHS01 hash.
VISION_MSGS = {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose":
        "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n",
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D":
        "std_msgs/Header header\nObjectHypothesisWithPose[] results\nBoundingBox3D bbox\nstring id\n",
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nDetection3D[] detections\n",
}

_NUMPY = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
          "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32, "int64": np.int64,
          "uint64": np.uint64, "float32": np.float32, "float64": np.float64}


class RosTypes:
    """The message types of one ROS distro."""

    def __init__(self, distro_name: str):
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.distro: Distro = distro(distro_name)
        store = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}[self.distro.name]
        self.store = get_typestore(store)
        types: dict = {}
        for name, text in VISION_MSGS.items():
            types.update(get_types_from_msg(text, name))
        self.store.register(types)

    def has(self, typename: str) -> bool:
        return typename in self.store.fielddefs

    def type_hash(self, typename: str) -> str:
        """What goes in the key and the tokens: RIHS01_<sha256> (Jazzy) or TypeHashNotSupported (Humble)."""
        return self.store.hash_rihs01(typename) if self.distro.type_hashes else TYPE_HASH_NOT_SUPPORTED

    def dds_type(self, typename: str) -> str:
        return dds_type_name(typename)

    def serialize(self, msg: Any) -> bytes:
        return bytes(self.store.serialize_cdr(msg, msg.__msgtype__))

    def deserialize(self, raw: bytes, typename: str) -> Any:
        return self.store.deserialize_cdr(raw, typename)

    def new(self, typename: str, **fields: Any) -> Any:
        """A message of `typename`; fields not given take ROS defaults (0, '', empty, nested defaults)."""
        _, defs = self.store.fielddefs[typename]
        values = {}
        for name, desc in defs:
            values[name] = fields.pop(name) if name in fields else self._default(desc)
        if fields:
            raise TypeError(f"{typename} has no field(s) {', '.join(fields)}")
        return self.store.types[typename](**values)

    def _default(self, desc: Any) -> Any:
        from rosbags.typesys.base import Nodetype

        kind, rest = desc
        if kind == Nodetype.BASE:
            t = rest[0]
            return "" if t == "string" else False if t == "bool" else 0.0 if t.startswith("float") else 0
        if kind == Nodetype.NAME:
            return self.new(rest)
        (sub_kind, sub), count = rest
        if sub_kind == Nodetype.BASE and sub[0] in _NUMPY:
            return np.zeros(count if kind == Nodetype.ARRAY else 0, dtype=_NUMPY[sub[0]])
        n = count if kind == Nodetype.ARRAY else 0
        return [self._default((sub_kind, sub)) for _ in range(n)]


@cache
def types_for(distro_name: str) -> RosTypes:
    return RosTypes(distro_name)
