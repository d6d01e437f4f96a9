"""What every process of ballbot-vision shares: the one key table (keys), the messages and their
codec, errors, file reading, settings, message signing, the Zenoh session and the Node loop every
service runs in, and ROS 2's wire format over Zenoh (ros2/).

Importing this package first holds OpenCV's decoders to this program's size limits (files.py's
MAX_IMAGE_SIDE and MAX_IMAGE_PIXELS): OpenCV reads them once, when cv2 is loaded, and its default
allows a gigapixel. A value the user set wins."""
import os as _os

_os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", "40000000")
_os.environ.setdefault("OPENCV_IO_MAX_IMAGE_WIDTH", "16384")
_os.environ.setdefault("OPENCV_IO_MAX_IMAGE_HEIGHT", "16384")
