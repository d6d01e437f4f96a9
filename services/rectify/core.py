"""Rectification core: maps computed once from a calibration, then two remaps per pair.

No Zenoh here; the service (main.py) and the offline `rectify` command share this.
"""
from __future__ import annotations

import cv2
import numpy as np

from ...common import camera
from ...common.errors import BallbotError
from ...common.messages import CameraModel


def camera_model_message(m: camera.RectifiedModel) -> CameraModel:
    return CameraModel(width=m.width, height=m.height, focal_px=m.focal_px, cx=m.cx, cy=m.cy,
                       baseline_m=m.baseline_m, Q=[float(x) for x in m.Q.ravel()])


class Rectifier:
    """Undistort and rectify stereo pairs so that epipolar lines are image rows.

    For a raw rig the maps come from cv2.stereoRectify + initUndistortRectifyMap (fixed-point maps,
    the fastest remap); an already-rectified rig passes images through after a size check.
    """

    def __init__(self, calibration: camera.Calibration, alpha: float = 0.0,
                 interpolation: int = cv2.INTER_LINEAR):
        self.calibration = calibration
        self.size = calibration.image_size
        self.interpolation = interpolation
        if isinstance(calibration, camera.RectifiedRig):
            self.rectification = None
            self.model = calibration.model
            self._maps = None
        else:
            r = camera.rectify_rig(calibration, alpha)
            self.rectification = r
            self.model = r.model
            m1 = cv2.initUndistortRectifyMap(calibration.left.K, calibration.left.D, r.R1, r.P1, self.size, cv2.CV_16SC2)
            m2 = cv2.initUndistortRectifyMap(calibration.right.K, calibration.right.D, r.R2, r.P2, self.size, cv2.CV_16SC2)
            self._maps = (m1, m2)
        self.model_message = camera_model_message(self.model)

    def check_size(self, image: np.ndarray, name: str) -> None:
        h, w = image.shape[:2]
        if (w, h) != tuple(self.size):
            raise BallbotError(f"{name}: image is {w}x{h}, the calibration '{self.calibration.name or '?'}' "
                               f"is for {self.size[0]}x{self.size[1]}")

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """left, right: (H, W) or (H, W, 3) images of the calibrated size -> rectified, same dtype."""
        self.check_size(left, "left")
        self.check_size(right, "right")
        if self._maps is None:
            return left, right
        (l1, l2), (r1, r2) = self._maps
        return (cv2.remap(left, l1, l2, self.interpolation, borderMode=cv2.BORDER_CONSTANT),
                cv2.remap(right, r1, r2, self.interpolation, borderMode=cv2.BORDER_CONSTANT))
