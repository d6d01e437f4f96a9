"""Other tools' calibration files, in and out, and a human-readable summary of any calibration.

* OpenCV's ``stereo_calib`` sample: ``intrinsics.yml`` (M1 D1 M2 D2) and ``extrinsics.yml``
  (R T, plus R1 R2 P1 P2 Q that we ignore and re-derive), cv::FileStorage YAML. T is in the unit
  the sample was given for the square size; ``units_m`` scales it to metres. The sample writes no
  image size, so one must be given unless the file has one (image_width/image_height,
  imageSize or image_size).
* ROS ``camera_info`` YAML pairs (camera_calibration_parsers): camera_matrix,
  distortion_coefficients, rectification_matrix, projection_matrix. The stereo pose follows from
  the rectification: R_i rotates camera i into the common rectified frame and P_i = K'[I | t_i]
  with t_i = K'^-1 P_i[:, 3] (for the right camera t = (-B, 0, 0), i.e. P2[0,3] = -fx' B): a point
  X in the rectified reference frame is R_i X_i = X + t_i in camera i. So R2 X_right - t2 =
  R1 X_left - t1, hence R = R2^T R1 and T = R2^T (t2 - t1).
* Kalibr's camchain YAML (``camchain.yaml``, ``camchain-imucam.yaml``): per camera ``camN`` with
  camera_model pinhole, intrinsics [fu fv cu cv], distortion_model radtan with distortion_coeffs
  [k1 k2 p1 p2], resolution [w h], and for N >= 1 ``T_cn_cnm1``, the pose that maps camera N-1's
  points into camera N's: X_cn = T_cn_cnm1 X_cnm1 (so for cam1 it is OpenCV's R, T directly). A
  chain without T_cn_cnm1 but with T_cam_imu per camera gives T_c1_c0 = T_c1_imu inv(T_c0_imu).
* EuRoC's per-camera ``sensor.yaml`` (cam0_sensor.yaml, cam1_sensor.yaml): the same intrinsics and
  distortion (distortion_model radial-tangential, distortion_coefficients), ``resolution``, and
  ``T_BS``, the camera's pose in the body frame: X_B = T_BS X_cam. Hence
  T_cam1_cam0 = inv(T_BS_cam1) T_BS_cam0.

No CLI and no Zenoh here.
"""
from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from common.errors import BallbotError, CalibrationError, FileError
from common.files import parse_yaml, read_text, read_yaml
from cores import camera

# --- OpenCV stereo_calib ------------------------------------------------------------------------


def _fs_open(path: Path) -> Any:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # OpenCV's parser raises either for text it cannot parse
        raise CalibrationError(f"{path}: not a calibration format this command knows ({KNOWN_FORMATS})") from None
    if not fs.isOpened():
        raise CalibrationError(f"{path}: not a calibration format this command knows ({KNOWN_FORMATS})")
    return fs


def _fs_mat(fs: Any, key: str, path: Path, shape: tuple[int, ...] | None = None) -> np.ndarray | None:
    node = fs.getNode(key)
    if node.empty():
        return None
    try:
        m = node.mat()
    except (cv2.error, SystemError) as e:  # an !!opencv-matrix without dt, or whose data do not fill it
        why = ("no 'dt' (element type)" if "dt.empty" in str(e) else
               "its 'data' do not hold rows x cols numbers" if "nelems" in str(e) else
               "rows, cols, dt and data expected")
        raise CalibrationError(f"{path}: field '{key}' is not a readable OpenCV matrix: {why}") from None
    if m is None:
        raise CalibrationError(f"{path}: field '{key}' is not a matrix")
    m = np.asarray(m, dtype=np.float64)
    if shape is not None and m.size != int(np.prod(shape)):
        raise CalibrationError(f"{path}: field '{key}' has {m.size} numbers, expected {int(np.prod(shape))}")
    return m.reshape(shape) if shape is not None else m


def _fs_size(fs: Any, path: Path) -> tuple[int, int] | None:
    def side(v: float, key: str) -> int:
        if not math.isfinite(v) or v != round(v):
            raise CalibrationError(f"{path}: field '{key}' must be a whole number of pixels, got {v}")
        return int(v)

    w, h = fs.getNode("image_width"), fs.getNode("image_height")
    if not w.empty() and not h.empty():
        return side(w.real(), "image_width"), side(h.real(), "image_height")
    for key in ("imageSize", "image_size"):
        n = fs.getNode(key)
        if not n.empty():
            if n.isSeq() and n.size() == 2:
                return side(n.at(0).real(), key), side(n.at(1).real(), key)
            m = _fs_mat(fs, key, path)
            if m is not None and m.size == 2:
                return side(float(m.ravel()[0]), key), side(float(m.ravel()[1]), key)
    return None


def _dist5(D: np.ndarray, where: str) -> np.ndarray:
    D = np.asarray(D, dtype=np.float64).ravel()
    if D.size < 4:
        raise CalibrationError(f"{where}: expected at least 4 distortion coefficients (k1 k2 p1 p2), got {D.size}")
    if D.size > 5 and np.any(np.abs(D[5:]) > 1e-12):
        raise CalibrationError(f"{where}: {D.size} distortion coefficients with non-zero terms beyond k3 "
                               "(rational/thin-prism models are not supported; recalibrate with the 5-term model)")
    out = np.zeros(5)
    out[:min(5, D.size)] = D[:5]
    return out


def read_stereo_calib(paths: Sequence[str | Path], units_m: float = 1.0, image_size: tuple[int, int] | None = None,
                      name: str = "") -> camera.RawRig:
    """The intrinsics.yml + extrinsics.yml pair of OpenCV's stereo_calib sample (either order, or
    one file holding all of M1 D1 M2 D2 R T)."""
    found: dict[str, tuple[np.ndarray, Path]] = {}
    size = image_size
    for p in map(Path, paths):
        read_text(p)  # missing, empty or binary: one clear line, before OpenCV's parser sees it
        fs = _fs_open(p)
        try:
            for key, shape in (("M1", (3, 3)), ("D1", None), ("M2", (3, 3)), ("D2", None), ("R", (3, 3)), ("T", (3,))):
                m = _fs_mat(fs, key, p, shape)
                if m is not None:
                    found[key] = (m, p)
            if size is None:
                size = _fs_size(fs, p)
        finally:
            fs.release()
    missing = [k for k in ("M1", "D1", "M2", "D2", "R", "T") if k not in found]
    if len(missing) == 6:
        raise CalibrationError(f"{', '.join(map(str, paths))}: not a calibration format this command knows "
                               f"({KNOWN_FORMATS})")
    if missing:
        raise CalibrationError(f"{', '.join(map(str, paths))}: missing field(s) {', '.join(missing)} "
                               "(expected the intrinsics.yml and extrinsics.yml of OpenCV's stereo_calib)")
    if size is None:
        raise CalibrationError(f"{', '.join(map(str, paths))}: no image size in the files (the stereo_calib "
                               "sample writes none); give it with --image-size WIDTHxHEIGHT")
    if not (units_m > 0):
        raise CalibrationError(f"--units-m {units_m}: must be positive")
    left = camera.Intrinsics.from_matrix(found["M1"][0], _dist5(found["D1"][0], f"{found['D1'][1]}: D1"))
    right = camera.Intrinsics.from_matrix(found["M2"][0], _dist5(found["D2"][0], f"{found['D2'][1]}: D2"))
    try:
        return camera.RawRig(tuple(size), left, right, found["R"][0], found["T"][0] * units_m,  # type: ignore[arg-type]
                             name or Path(str(paths[0])).stem)
    except CalibrationError as e:
        raise CalibrationError(f"{found['R'][1]}: {e}") from None


def write_stereo_calib(rig: camera.RawRig, intrinsics: str | Path, extrinsics: str | Path, units_m: float = 1.0,
                       alpha: float = 0.0) -> None:
    """The stereo_calib sample's pair (T divided by units_m; R1 R2 P1 P2 Q as stereoRectify gives
    them; the image size is added as image_width / image_height, which the sample ignores)."""
    r = camera.rectify_rig(rig, alpha)
    fs = cv2.FileStorage(str(intrinsics), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", int(rig.image_size[0]))
    fs.write("image_height", int(rig.image_size[1]))
    fs.write("M1", rig.left.K)
    fs.write("D1", rig.left.D.reshape(1, 5))
    fs.write("M2", rig.right.K)
    fs.write("D2", rig.right.D.reshape(1, 5))
    fs.release()
    fs = cv2.FileStorage(str(extrinsics), cv2.FILE_STORAGE_WRITE)
    fs.write("R", rig.R)
    fs.write("T", (rig.T / units_m).reshape(3, 1))
    for k in ("R1", "R2", "P1", "P2", "Q"):
        fs.write(k, getattr(r, k))
    fs.release()


# --- ROS camera_info ----------------------------------------------------------------------------

def _ros_mat(doc: dict, key: str, rows: int, cols: int | None, where: str) -> np.ndarray:
    if key not in doc:
        raise CalibrationError(f"{where}: missing field '{key}'")
    v = doc[key]
    data = v.get("data") if isinstance(v, dict) else v
    try:
        a = np.asarray(data, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: field '{key}' must hold numbers") from None
    if cols is None:
        return a
    if a.size != rows * cols or not np.all(np.isfinite(a)):
        raise CalibrationError(f"{where}: field '{key}' must hold {rows}x{cols} finite numbers, got {a.size}")
    return a.reshape(rows, cols)


def _read_ros_one(path: Path) -> dict:
    doc = read_yaml(path)
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: expected a ROS camera_info mapping")
    where = str(path)
    model = str(doc.get("distortion_model", "plumb_bob"))
    if model not in ("plumb_bob", "rational_polynomial"):
        raise CalibrationError(f"{where}: distortion_model '{model}' is not supported (plumb_bob)")
    for k in ("image_width", "image_height"):
        if k not in doc:
            raise CalibrationError(f"{where}: missing field '{k}'")
    return {
        "size": (int(doc["image_width"]), int(doc["image_height"])),
        "K": _ros_mat(doc, "camera_matrix", 3, 3, where),
        "D": _dist5(_ros_mat(doc, "distortion_coefficients", 1, None, where), f"{where}: distortion_coefficients"),
        "R": _ros_mat(doc, "rectification_matrix", 3, 3, where),
        "P": _ros_mat(doc, "projection_matrix", 3, 4, where),
        "name": str(doc.get("camera_name", path.stem)),
        "where": where,
    }


def is_ros_camera_info(path: str | Path) -> bool:
    try:
        doc = read_yaml(path)
    except BallbotError:
        return False
    return isinstance(doc, dict) and "camera_matrix" in doc and "projection_matrix" in doc


def rig_from_ros_cameras(a: dict, b: dict, name: str, fields: tuple[str, str] = ("rectification_matrix",
                                                                                 "projection_matrix")) -> camera.RawRig:
    """A raw rig from the two cameras of a ROS stereo calibration (camera_info files, or
    sensor_msgs/CameraInfo messages): each camera's K and distortion, and the right camera's pose
    from both cameras' rectification R and projection P (P = K' [I | t] in the rectified frame, so
    t = K'^-1 P[:, 3]). a, b: {"size", "K", "D", "R", "P", "where"}; fields: how the caller's
    format names R and P, for the errors."""
    r_field, p_field = fields
    if a["size"] != b["size"]:
        raise CalibrationError(f"{b['where']}: image size {b['size']} differs from {a['where']}'s {a['size']}")
    t = []
    for c in (a, b):
        camera._check_rotation(c["R"], f"{c['where']}: {r_field}")
        KP = c["P"][:, :3]
        if abs(np.linalg.det(KP)) < 1e-9:
            raise CalibrationError(f"{c['where']}: field '{p_field}' has a singular left 3x3 block")
        t.append(np.linalg.solve(KP, c["P"][:, 3]))
    R = b["R"].T @ a["R"]
    T = b["R"].T @ (t[1] - t[0])
    if np.linalg.norm(T) < 1e-9:
        raise CalibrationError(f"{b['where']}: field '{p_field}' has no baseline (P[0,3] = -fx*B is 0); "
                               "is this the right camera of a stereo pair?")
    try:
        return camera.RawRig(a["size"], camera.Intrinsics.from_matrix(a["K"], a["D"]),
                             camera.Intrinsics.from_matrix(b["K"], b["D"]), R, T, name)
    except CalibrationError as e:
        raise CalibrationError(f"{a['where']}, {b['where']}: {e}") from None


def read_ros_pair(left: str | Path, right: str | Path, name: str = "") -> camera.RawRig:
    a, b = _read_ros_one(Path(left)), _read_ros_one(Path(right))
    return rig_from_ros_cameras(a, b, name or a["name"])


def write_ros_pair(rig: camera.RawRig, left: str | Path, right: str | Path, alpha: float = 0.0) -> None:
    r = camera.rectify_rig(rig, alpha)
    for path, cam, R, P, side in ((left, rig.left, r.R1, r.P1, "left"), (right, rig.right, r.R2, r.P2, "right")):
        doc = {
            "image_width": int(rig.image_size[0]), "image_height": int(rig.image_size[1]),
            "camera_name": f"{rig.name or 'stereo'}/{side}",
            "camera_matrix": {"rows": 3, "cols": 3, "data": [float(x) for x in cam.K.ravel()]},
            "distortion_model": "plumb_bob",
            "distortion_coefficients": {"rows": 1, "cols": 5, "data": [float(x) for x in cam.D]},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": [float(x) for x in R.ravel()]},
            "projection_matrix": {"rows": 3, "cols": 4, "data": [float(x) for x in P.ravel()]},
        }
        Path(path).write_text(yaml.safe_dump(doc, sort_keys=False))


# --- Kalibr camchain / EuRoC sensor.yaml --------------------------------------------------------

KNOWN_FORMATS = ("OpenCV stereo_calib intrinsics.yml + extrinsics.yml, ROS camera_info left.yaml + right.yaml, "
                 "Kalibr camchain.yaml, EuRoC cam0/sensor.yaml + cam1/sensor.yaml")

# Kalibr's and EuRoC's names for OpenCV's 4/5-term radial-tangential model.
_RADTAN = ("radtan", "radial-tangential", "plumb_bob")


def _numbers(v: Any, n: int | None, where: str, field: str) -> np.ndarray:
    data = v.get("data") if isinstance(v, dict) else v
    try:
        a = np.asarray(data, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: field '{field}' must hold numbers") from None
    if (n is not None and a.size != n) or not np.all(np.isfinite(a)):
        raise CalibrationError(f"{where}: field '{field}' must hold {n} finite numbers, got {a.size}")
    return a


def _pose(doc: dict, field: str, where: str) -> np.ndarray:
    """A 4x4 rigid transform, as a nested list (Kalibr) or {rows, cols, data} (EuRoC)."""
    T = _numbers(doc[field], 16, where, field).reshape(4, 4)
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{where}: field '{field}' is not a rigid transform (last row must be 0 0 0 1)")
    camera._check_rotation(T[:3, :3], f"{where}: field '{field}'")
    return T


def _kalibr_camera(doc: Any, where: str) -> tuple[camera.Intrinsics, tuple[int, int]]:
    """One camera of a camchain or an EuRoC sensor.yaml -> intrinsics and (width, height)."""
    if not isinstance(doc, dict):
        raise CalibrationError(f"{where}: expected a mapping with camera_model, intrinsics, distortion")
    model = str(doc.get("camera_model", "pinhole"))
    if model != "pinhole":
        raise CalibrationError(f"{where}: camera_model '{model}' is not supported (pinhole only; "
                               "recalibrate the rig with Kalibr's pinhole-radtan model)")
    for field in ("intrinsics", "resolution"):
        if field not in doc:
            raise CalibrationError(f"{where}: missing field '{field}'")
    fu, fv, cu, cv = _numbers(doc["intrinsics"], 4, where, "intrinsics")
    if fu <= 0 or fv <= 0:
        raise CalibrationError(f"{where}: field 'intrinsics' [fu, fv, cu, cv] needs positive focal lengths, "
                               f"got fu={fu:g} fv={fv:g}")
    w, h = _numbers(doc["resolution"], 2, where, "resolution")
    if w <= 0 or h <= 0 or w != round(w) or h != round(h):
        raise CalibrationError(f"{where}: field 'resolution' must be two positive integers [width, height]")
    dm = str(doc.get("distortion_model", "radtan"))
    key = "distortion_coeffs" if "distortion_coeffs" in doc else "distortion_coefficients"
    if dm == "none":
        dist = np.zeros(5)
    elif dm in _RADTAN:
        if key not in doc:
            raise CalibrationError(f"{where}: missing field 'distortion_coeffs' (or 'distortion_coefficients')")
        d = _numbers(doc[key], None, where, key)
        if d.size not in (4, 5):
            raise CalibrationError(f"{where}: field '{key}' must hold 4 numbers (k1 k2 p1 p2), got {d.size}")
        dist = np.zeros(5)
        dist[:d.size] = d
    else:
        raise CalibrationError(f"{where}: distortion_model '{dm}' is not supported (radtan / radial-tangential; "
                               "equidistant is a fisheye model: recalibrate with pinhole-radtan)")
    return camera.Intrinsics(float(fu), float(fv), float(cu), float(cv), 0.0,
                             tuple(float(x) for x in dist)), (int(w), int(h))  # type: ignore[arg-type]


def is_kalibr_camchain(doc: Any) -> bool:
    return isinstance(doc, dict) and isinstance(doc.get("cam0"), dict) and "intrinsics" in doc["cam0"]


def is_euroc_sensor(doc: Any) -> bool:
    return isinstance(doc, dict) and "intrinsics" in doc and "T_BS" in doc


def _rig(where: str, left: tuple, right: tuple, T_right_left: np.ndarray, name: str) -> camera.RawRig:
    (kl, size_l), (kr, size_r) = left, right
    if size_l != size_r:
        raise CalibrationError(f"{where}: the cameras' resolutions differ ({size_l[0]}x{size_l[1]} and "
                               f"{size_r[0]}x{size_r[1]}); a stereo pair needs one image size")
    try:
        return camera.RawRig(size_l, kl, kr, T_right_left[:3, :3], T_right_left[:3, 3], name)
    except CalibrationError as e:
        raise CalibrationError(f"{where}: {e}") from None


def read_kalibr_camchain(path: str | Path, cameras: tuple[str, str] = ("cam0", "cam1"), name: str = "",
                         doc: Any = None) -> camera.RawRig:
    """A Kalibr camchain: `cameras` (left, right) of the chain, by default cam0 and cam1."""
    where = str(path)
    doc = read_yaml(path) if doc is None else doc
    if not is_kalibr_camchain(doc):
        raise CalibrationError(f"{where}: not a Kalibr camchain (no cam0 with intrinsics)")
    chain = [k for k in sorted(doc, key=lambda k: int(k[3:]) if k[3:].isdigit() else 1 << 30)
             if re.fullmatch(r"cam\d+", str(k))]
    for c in cameras:
        if c not in chain:
            raise CalibrationError(f"{where}: no camera '{c}' (the chain has {', '.join(chain)})")
    # every camera's pose relative to cam0: T_cn_c0 = T_cn_cnm1 ... T_c1_c0
    to_c0: dict[str, np.ndarray] = {chain[0]: np.eye(4)}
    use_imu = any("T_cn_cnm1" not in doc[c] for c in chain[1:])
    for prev, cur in zip(chain, chain[1:]):
        w = f"{where}: {cur}"
        if not use_imu:
            to_c0[cur] = _pose(doc[cur], "T_cn_cnm1", w) @ to_c0[prev]
        elif all("T_cam_imu" in doc[c] for c in (chain[0], cur)):
            to_c0[cur] = _pose(doc[cur], "T_cam_imu", w) @ np.linalg.inv(_pose(doc[chain[0]], "T_cam_imu", where))
        else:
            raise CalibrationError(f"{w}: missing field 'T_cn_cnm1' (the pose relative to the previous camera)")
    left, right = cameras
    T = to_c0[right] @ np.linalg.inv(to_c0[left])
    return _rig(f"{where} ({left}, {right})", _kalibr_camera(doc[left], f"{where}: {left}"),
                _kalibr_camera(doc[right], f"{where}: {right}"), T, name or Path(where).stem)


def read_euroc_pair(left: str | Path, right: str | Path, name: str = "", docs: tuple[Any, Any] | None = None
                    ) -> camera.RawRig:
    """Two EuRoC sensor.yaml files, left camera (cam0) first."""
    a, b = docs if docs is not None else (read_yaml(left), read_yaml(right))
    for doc, path in ((a, left), (b, right)):
        if not is_euroc_sensor(doc):
            raise CalibrationError(f"{path}: not an EuRoC camera sensor.yaml (needs intrinsics and T_BS)")
    T = np.linalg.inv(_pose(b, "T_BS", str(right))) @ _pose(a, "T_BS", str(left))
    return _rig(f"{left}, {right}", _kalibr_camera(a, str(left)), _kalibr_camera(b, str(right)), T,
                name or Path(str(left)).parent.name or "euroc")


# --- any of them --------------------------------------------------------------------------------

def _peek_yaml(path: str) -> Any:
    """The parsed YAML document, or None when the file is not plain YAML (OpenCV FileStorage's
    !!opencv-matrix tags). Missing, empty and binary files raise FileError here."""
    text = read_text(path)
    try:
        return parse_yaml(text, path)
    except FileError as e:
        if "not valid YAML" in str(e):
            return None
        raise  # hostile YAML: aliases that expand too far, too deep nesting


def import_files(files: list[str], units_m: float = 1.0, image_size: tuple[int, int] | None = None,
                 name: str = "", cameras: tuple[str, str] | None = None) -> camera.RawRig:
    """Another tool's calibration -> a raw rig, validated as the loader validates: two ROS
    camera_info files (left first, or named *left* / *right*), one Kalibr camchain (`cameras`
    picks the pair, default cam0 cam1), two EuRoC sensor.yaml files (left first), or the
    stereo_calib pair."""
    if not files:
        raise CalibrationError(f"calibration import: give the files to import ({KNOWN_FORMATS})")
    docs = [_peek_yaml(f) for f in files]
    where = ", ".join(files)
    if any(is_kalibr_camchain(d) for d in docs):
        if len(files) != 1:
            raise CalibrationError(f"{where}: a Kalibr camchain holds the whole rig: give that one file")
        rig = read_kalibr_camchain(files[0], cameras or ("cam0", "cam1"), name, docs[0])
    elif cameras:
        raise CalibrationError("--cameras picks two cameras of a Kalibr camchain; "
                               f"{where} is not one")
    elif any(is_euroc_sensor(d) for d in docs):
        if len(files) != 2:
            raise CalibrationError(f"{where}: EuRoC sensor.yaml: expected two files, left (cam0) then right (cam1), "
                                   f"got {len(files)}")
        rig = read_euroc_pair(files[0], files[1], name, (docs[0], docs[1]))
    elif any(isinstance(d, dict) and "camera_matrix" in d and "projection_matrix" in d for d in docs):
        if len(files) != 2:
            raise CalibrationError(f"ROS camera_info: expected exactly two files (left and right), got {len(files)}")
        a, b = files
        if "right" in Path(a).name.lower() and "left" in Path(b).name.lower():
            a, b = b, a
        rig = read_ros_pair(a, b, name)
    else:
        rig = read_stereo_calib(files, units_m, image_size, name)
    camera.validate_calibration(rig, where)
    return rig


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in str(text).lower().split("x"))
    except ValueError:
        raise CalibrationError(f"image size {text!r}: expected WIDTHxHEIGHT, e.g. 640x480") from None
    if w <= 0 or h <= 0:
        raise CalibrationError(f"image size {text!r}: must be positive")
    return w, h


def describe(cal: camera.Calibration, depth_range: tuple[float, float] | None = (0.5, 3.0), alpha: float = 0.0
             ) -> str:
    """The calibration in the thesis's (Bouguet's) notation: f, cc, kc per camera, om and T (mm)."""
    lines = [f"calibration: {cal.name or '(unnamed)'}  image {cal.image_size[0]}x{cal.image_size[1]}"]
    if isinstance(cal, camera.RectifiedRig):
        m = cal.model
        lines += ["already rectified:",
                  f"  f = {m.focal_px:.5f} px   cc = [ {m.cx:.5f}  {m.cy:.5f} ]   "
                  f"baseline = {m.baseline_m * 1000:.5f} mm"]
    else:
        for title, c in (("left", cal.left), ("right", cal.right)):
            lines += [f"{title}:",
                      f"  f  = [ {c.fx:.5f}  {c.fy:.5f} ]",
                      f"  cc = [ {c.cx:.5f}  {c.cy:.5f} ]",
                      f"  alpha_c (skew) = {c.skew / c.fx:.5f}   (K[0,1] = {c.skew:.5f} px, "
                      f"angle of pixel axes {90.0 - math.degrees(math.atan(c.skew / c.fx)):.5f} deg)",
                      "  kc = [ " + "  ".join(f"{d:.5f}" for d in c.dist) + " ]"]
        om = cv2.Rodrigues(cal.R)[0].ravel()
        T = cal.T * 1000
        lines += ["right camera wrt left (X_right = R X_left + T):",
                  f"  om = [ {om[0]:.5f}  {om[1]:.5f}  {om[2]:.5f} ]  (Rodrigues, rad; "
                  f"{math.degrees(float(np.linalg.norm(om))):.4f} deg)",
                  "  R  = " + " / ".join("[ " + "  ".join(f"{x:+.6f}" for x in row) + " ]" for row in cal.R),
                  f"  T  = [ {T[0]:.5f}  {T[1]:.5f}  {T[2]:.5f} ] mm  (|T| = {np.linalg.norm(T):.5f} mm)"]
    m = camera.rectified_model(cal, alpha)
    lines += [f"rectified (alpha {alpha:g}): f = {m.focal_px:.5f} px, baseline = {m.baseline_m * 1000:.5f} mm, "
              f"cc = [ {m.cx:.5f}  {m.cy:.5f} ]"]
    if depth_range:
        near, far = depth_range
        lines.append(f"  depth {near:g}..{far:g} m -> disparity {m.disparity_for_depth(far):.1f}.."
                     f"{m.disparity_for_depth(near):.1f} px")
    return "\n".join(lines)
