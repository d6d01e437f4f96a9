"""The recordings `eval --real`, `mount estimate` and the ground matrix read.

A recording is a folder in one of two layouts (see ../shared/data/real/README.md):
- `left/` and `right/` image folders (paired by name, else in order) and `calibration.yaml` (this
  program's format), optionally `insdata.txt` (INS poses, one line per pair: odometry and stamps);
- EuRoC: `cam0/` and `cam1/` (or `cam0/data/`, `cam1/data/`) and the two sensor yamls
  (`cam0_sensor.yaml` + `cam1_sensor.yaml`, or `cam0/sensor.yaml` + `cam1/sensor.yaml`), imported
  in-process as `calibration import` does; the raw pairs are rectified. Image names that are
  nanosecond stamps give the frame times.

insdata.txt (Karlsruhe; the column convention is inferred and checked against the data, see
read_insdata): timestamp ns, latitude deg, longitude deg, altitude m, x m (east), y m (north),
z m (up, equal to the altitude), roll rad, pitch rad, yaw rad (heading, counter-clockwise from x =
east). Checked: the displacement between lines agrees with latitude/longitude (x with east, y with
north, ~1.26 m and -0.10 m per 0.1 s at the start); the direction of travel atan2(dy, dx) matches
yaw within 1 deg; the speed is ~12.4 m/s falling to ~9 m/s, forward. The pitch column is not
usable (a constant ~2.07 rad, one line -0.001): it is not read.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.errors import BallbotError
from common.messages import Odometry
from cores import camera

INSDATA_COLUMNS = ("stamp_ns", "lat_deg", "lon_deg", "alt_m", "x_east_m", "y_north_m", "z_up_m",
                   "roll_rad", "pitch_rad", "yaw_rad")
_NS_STAMP = re.compile(r"^\d{16,20}$")


@dataclass
class Recording:
    root: Path
    pairs: list[tuple[Path, Path]]
    calibration: camera.Calibration
    calibration_source: str
    stamps_s: list[float]  # per pair, seconds (relative clock)
    stamps_from: str  # where the stamps came from
    odometry: list[Odometry] | None = None  # per pair, base frame

    @property
    def name(self) -> str:
        return self.root.name


def _first(root: Path, *names: str) -> Path | None:
    return next((root / n for n in names if (root / n).exists()), None)


def open_recording(root: str | Path, fps: float = 10.0) -> Recording:
    """A recording folder (layouts in the module doc) -> its pairs, calibration, stamps, odometry."""
    from common.files import list_images, pair_images
    from cores.calibration.formats import import_files

    root = Path(root).expanduser()
    if not root.is_dir():
        raise BallbotError(f"--real {root}: not a folder")
    left_dir = _first(root, "left", "cam0/data", "cam0")
    right_dir = _first(root, "right", "cam1/data", "cam1")
    if left_dir is None or right_dir is None:
        raise BallbotError(f"--real {root}: expected left/ and right/ (with calibration.yaml) or EuRoC's cam0/ "
                           "and cam1/ (with their sensor yamls)")
    pairs = pair_images(list_images(str(left_dir), "left images"), list_images(str(right_dir), "right images"))
    cal_file = _first(root, "calibration.yaml", "calibration.yml")
    sensors = [_first(root, f"cam{k}_sensor.yaml", f"cam{k}/sensor.yaml") for k in (0, 1)]
    if cal_file is not None:
        cal, cal_source = camera.load_calibration(cal_file), cal_file.name
    elif sensors[0] is not None and sensors[1] is not None:
        cal = import_files([str(s) for s in sensors], name=root.name)
        cal_source = f"{sensors[0].relative_to(root)} + {sensors[1].relative_to(root)} (EuRoC, imported)"
    else:
        raise BallbotError(f"--real {root}: no calibration.yaml and no EuRoC cam0/cam1 sensor yamls")
    rec = Recording(root, pairs, cal, cal_source, [k / fps for k in range(len(pairs))], f"{fps:g} fps (--fps)")
    ins = root / "insdata.txt"
    stems = [p.stem for p, _ in pairs]
    if ins.exists():
        poses = read_insdata(ins)
        if len(poses) != len(pairs):
            raise BallbotError(f"{ins}: {len(poses)} poses for {len(pairs)} pairs (expected one line per pair)")
        rec.stamps_s = list((poses[:, 0] - poses[0, 0]) / 1e9)
        rec.stamps_from = "insdata.txt"
        rec.odometry = odometry_from_poses(poses)
    elif stems and all(_NS_STAMP.match(s) for s in stems):
        t0 = int(stems[0])
        rec.stamps_s = [(int(s) - t0) / 1e9 for s in stems]
        rec.stamps_from = "image names (ns)"
    return rec


def recording_from_files(left: str, right: str, calibration: str, fps: float = 10.0) -> Recording:
    """LEFT and RIGHT (folders, globs or files, paired as everywhere) with a calibration -> a Recording
    (stamps from nanosecond image names, else `fps`; no odometry)."""
    from common.files import list_images, pair_images

    pairs = pair_images(list_images(left, "LEFT"), list_images(right, "RIGHT"))
    rec = Recording(Path(left), pairs, camera.load_calibration(calibration), str(calibration),
                    [k / fps for k in range(len(pairs))], f"{fps:g} fps (--fps)")
    stems = [p.stem for p, _ in pairs]
    if stems and all(_NS_STAMP.match(s) for s in stems):
        rec.stamps_s = [(int(s) - int(stems[0])) / 1e9 for s in stems]
        rec.stamps_from = "image names (ns)"
    return rec


def read_insdata(path: str | Path) -> np.ndarray:
    """(N, 10) float64, columns INSDATA_COLUMNS (module doc). Refuses a file whose positions and
    headings disagree with that convention (the direction of travel within 10 deg of yaw)."""
    try:
        a = np.loadtxt(path, ndmin=2)
    except ValueError as e:
        raise BallbotError(f"{path}: not a table of numbers ({e})") from None
    if a.shape[1] != len(INSDATA_COLUMNS):
        raise BallbotError(f"{path}: {a.shape[1]} columns, expected {len(INSDATA_COLUMNS)} "
                           f"({', '.join(INSDATA_COLUMNS)})")
    if len(a) >= 2:
        step = np.hypot(np.diff(a[:, 4]), np.diff(a[:, 5]))
        moving = step > 0.05
        if moving.any():
            travel = np.arctan2(np.diff(a[:, 5]), np.diff(a[:, 4]))[moving]
            off = np.angle(np.exp(1j * (travel - a[:-1, 9][moving])))
            if np.median(np.abs(off)) > math.radians(10):
                raise BallbotError(f"{path}: the direction of travel differs from the yaw column by "
                                   f"{math.degrees(float(np.median(np.abs(off)))):.0f} deg: not the expected "
                                   f"convention ({', '.join(INSDATA_COLUMNS)})")
    return a


def odometry_from_poses(poses: np.ndarray, robot_id: str = "offline") -> list[Odometry]:
    """INS poses (read_insdata) -> per line the base-frame motion: linear velocity (x forward along
    the heading, y left; z 0: the vehicle moves along the road, the base frame's plane) from the
    positions by central differences, angular velocity (0, 0, yaw rate) from the unwrapped yaw."""
    t = (poses[:, 0] - poses[0, 0]) / 1e9
    yaw = np.unwrap(poses[:, 9])
    if len(poses) < 2:
        return [Odometry(robot_id=robot_id, seq=0, stamp_ns=int(poses[0, 0]), linear_mps=(0.0, 0.0, 0.0),
                         source="insdata.txt")]
    ve, vn = np.gradient(poses[:, 4], t), np.gradient(poses[:, 5], t)
    rate = np.gradient(yaw, t)
    fwd = np.cos(yaw) * ve + np.sin(yaw) * vn
    left = -np.sin(yaw) * ve + np.cos(yaw) * vn
    return [Odometry(robot_id=robot_id, seq=k, stamp_ns=int(poses[k, 0]),
                     linear_mps=(float(fwd[k]), float(left[k]), 0.0), angular_radps=(0.0, 0.0, float(rate[k])),
                     source="insdata.txt") for k in range(len(poses))]
