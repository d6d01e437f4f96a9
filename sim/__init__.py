"""The synthetic world: scenes of boxes, people and furniture on a textured floor, rendered for a
stereo rig with its lens distortion, with ground truth for every pair (synthetic); the shipped
scenarios are in scenarios/."""
import common  # noqa: F401,E402  (first: OpenCV's image size limits, before anything loads cv2)
