"""Calibrations published by the robot's own services are signed, so rectify can tell them from
anyone else's on the network: an HMAC-SHA256 with a secret the robot's services share
(BALLBOT_CALIBRATION_KEY; `ballbot-vision up` makes a fresh one per run for its services, a
deployment sets one for all its containers). No key: nothing is signed and nothing verifies."""
from __future__ import annotations

import hashlib
import hmac
import os

from common.messages import CalibrationUpdate

KEY_ENV = "BALLBOT_CALIBRATION_KEY"


def calibration_key() -> bytes | None:
    key = os.environ.get(KEY_ENV, "")
    return key.encode() if key else None


def _digest(msg: CalibrationUpdate, key: bytes) -> str:
    head = f"{msg.robot_id}\n{msg.stamp_ns}\n{msg.source}\n".encode()
    return hmac.new(key, head + msg.yaml.encode(), hashlib.sha256).hexdigest()


def sign(msg: CalibrationUpdate, key: bytes | None = None) -> CalibrationUpdate:
    """msg with its signature (unchanged when there is no key)."""
    key = key if key is not None else calibration_key()
    if key:
        msg.signature = _digest(msg, key)
    return msg


def signed(msg: CalibrationUpdate, key: bytes | None = None) -> bool:
    key = key if key is not None else calibration_key()
    return bool(key) and bool(msg.signature) and hmac.compare_digest(msg.signature, _digest(msg, key))
