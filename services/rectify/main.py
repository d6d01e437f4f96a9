"""rectify: frames_raw -> frames_rect (with the rectified camera model)."""
from __future__ import annotations

from pydantic import Field

from ...common import camera, codec
from ...common.messages import StereoFrame
from ...common.node import Node
from ...common.settings import ServiceSettings
from .core import Rectifier

SUBSCRIBES = ["frames_raw"]
PUBLISHES = ["frames_rect"]


class RectifySettings(ServiceSettings):
    section = "rectify"
    calibration: str = Field("lifecam-studio", description="calibration YAML or built-in profile")
    alpha: float = Field(0.0, ge=0.0, le=1.0, description="0: crop to valid pixels, 1: keep all source pixels")


def run(node: Node, settings: RectifySettings) -> None:
    rectifier = Rectifier(camera.load_calibration(settings.calibration), settings.alpha)
    inbox = node.latest("frames_raw")
    out = node.publisher("frames_rect")
    for msg in node.receive(inbox):
        with node.processing(msg):
            left = codec.array_from_image(msg.left, "left")
            right = codec.array_from_image(msg.right, "right")
            rl, rr = rectifier.rectify(left, right)
            out.put(StereoFrame(robot_id=msg.robot_id, seq=msg.seq, stamp_ns=msg.stamp_ns, stages=msg.stages,
                                left=codec.image_from_array(rl), right=codec.image_from_array(rr),
                                camera=rectifier.model_message, source=msg.source))
