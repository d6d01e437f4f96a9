"""Calibrations are configuration: rectify takes one at run time only when it is signed with a
secret the robot's services share (an HMAC-SHA256), so nobody else on the network can rewrite the
robot's distances. Where the secret comes from, first found wins:
  BALLBOT_CALIBRATION_KEY        the key itself (a deployment sets one for all its containers);
  BALLBOT_CALIBRATION_KEY_FILE   a file holding it (first line);
  the per-run key file of `up`   `ballbot-vision up` makes a fresh key per run, hands it to its
                                 services and keeps it (mode 0600) in run_key_path(robot_id), so the
                                 local CLI of the same user (`calibration publish`, `calibrate
                                 --publish`) can sign; it is removed when `up` stops.
No key: nothing is signed and nothing verifies (rectify then takes no run-time calibration)."""
from __future__ import annotations

import hashlib
import hmac
import os
import re
from pathlib import Path

from common.messages import CalibrationUpdate

KEY_ENV = "BALLBOT_CALIBRATION_KEY"
KEY_FILE_ENV = "BALLBOT_CALIBRATION_KEY_FILE"


def run_key_path(robot_id: str) -> Path:
    """Where `up` keeps its per-run key for robot_id: the user's runtime folder (private to the
    user, emptied at logout), else ~/.cache."""
    base = os.environ.get("XDG_RUNTIME_DIR") or str(Path.home() / ".cache")
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", robot_id)
    return Path(base) / "ballbot-vision" / f"calibration-key-{safe}"


def read_key_file(path: str | os.PathLike) -> bytes:
    """The key in a key file (its first line); raises OSError or ValueError naming the file."""
    text = Path(path).read_text().strip().splitlines()
    key = text[0].strip() if text else ""
    if not key:
        raise ValueError(f"{path}: the calibration key file is empty")
    return key.encode()


def write_run_key(robot_id: str, key: str) -> Path:
    """`up`: keep this run's key where the local CLI finds it, readable by this user only."""
    path = run_key_path(robot_id)
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key + "\n")
    os.chmod(path, 0o600)  # an older file with wider rights keeps them through O_TRUNC
    return path


def remove_run_key(robot_id: str, key: str) -> None:
    """`up` stopping: remove its key file, unless another `up` of the same robot id wrote its own since."""
    path = run_key_path(robot_id)
    try:
        if read_key_file(path) == key.encode():
            path.unlink()
    except (OSError, ValueError):
        pass


def calibration_key(robot_id: str | None = None) -> bytes | None:
    """The robot's calibration key from the environment; with robot_id, also `up`'s per-run file."""
    key = os.environ.get(KEY_ENV, "")
    if key:
        return key.encode()
    path = os.environ.get(KEY_FILE_ENV, "")
    if path:
        from common.errors import ConfigError

        try:
            return read_key_file(path)
        except OSError as e:
            raise ConfigError(f"{KEY_FILE_ENV}: {path}: {e.strerror or e}") from None
        except ValueError as e:
            raise ConfigError(f"{KEY_FILE_ENV}: {e}") from None
    if robot_id is not None:
        try:
            return read_key_file(run_key_path(robot_id))
        except (OSError, ValueError):
            return None
    return None


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
    if not key or not msg.signature:
        return False
    return hmac.compare_digest(msg.signature, _digest(msg, key))
