"""The algorithms of ballbot-vision, one library: numpy in, numpy or a model out.

Nothing here imports Zenoh or a service (import-linter holds that, see pyproject.toml): every core is
usable in-process by the services, the offline commands, the evaluations and the benchmarks alike.

    camera          raw rigs, rectified models, the built-in profiles
    calibration/    chessboard calibration, calibration files, rectification, checks
    matching/       disparity matchers (bm, sgbm, dense) and the disparity map helpers
    segmentation/   ground, obstacles, tracking, free space, the camera mount, pictures
    recording       the MCAP recording format;  foxglove: Foxglove messages (Foxglove's SDK), recorded and live
    ros2_convert    our messages as ROS 2 messages and back
"""
import common  # noqa: F401,E402  (first: OpenCV's image size limits, before anything loads cv2)
