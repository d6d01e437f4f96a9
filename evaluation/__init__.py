"""Evaluations through the real cores: the synthetic scenarios against their ground truth
(synthetic, `ballbot-vision eval`) and label-free figures on real recordings (real, `eval --real`)."""
import common  # noqa: F401,E402  (first: OpenCV's image size limits, before anything loads cv2)
