"""The synthetic world: scenes of boxes, people and furniture on a textured floor, rendered for a
stereo rig with its lens distortion, with ground truth for every pair. scene.py: what a scene holds
and its file format (the shipped scenarios are in scenarios/); texture.py: the surfaces; world.py:
the renderer and the truth (SyntheticWorld); raycast.py: the rays, boxes and shading it renders with."""
import common  # noqa: F401  (first: OpenCV's image size limits, before anything loads cv2)
from sim.scene import Box, CameraMotion, Part, Scene, Wave, list_builtin_scenarios
from sim.world import ObstacleTruth, SyntheticWorld

__all__ = ["Box", "CameraMotion", "ObstacleTruth", "Part", "Scene", "SyntheticWorld", "Wave", "list_builtin_scenarios"]
