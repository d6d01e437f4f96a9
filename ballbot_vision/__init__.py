"""ballbot-vision: stereo obstacle detection as Zenoh microservices."""
import os as _os

# OpenCV reads its decoders' size limits once, when cv2 is loaded (its default allows a gigapixel):
# hold them to this program's, common/files.py's MAX_IMAGE_SIDE and MAX_IMAGE_PIXELS, so that an
# oversized image is refused before OpenCV allocates it. Every import of ours runs this first; a
# value the user set wins.
_os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", "40000000")
_os.environ.setdefault("OPENCV_IO_MAX_IMAGE_WIDTH", "16384")
_os.environ.setdefault("OPENCV_IO_MAX_IMAGE_HEIGHT", "16384")
