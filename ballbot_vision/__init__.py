"""ballbot-vision: stereo obstacle detection as Zenoh microservices. This package is the command
line (`ballbot-vision`, cli.py); the services, cores, simulator and evaluations are packages of
their own beside it (see README's map)."""
import common  # noqa: F401  (first: OpenCV's image size limits, before anything loads cv2)
