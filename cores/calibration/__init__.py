"""Stereo calibration and rectification: chessboard calibration (calibrate), calibration files of
other tools (formats), rectification maps (rectify), the row check of a rectified pair (check) and
which chessboard views a live calibration still needs (views)."""
