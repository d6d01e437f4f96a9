"""Calibration files, the built-in rig profiles, and the rectified camera model.

A calibration is either a raw rig (per camera K, distortion, image size; stereo R, T) or an
already-rectified pair (focal length, principal point, baseline). For a raw rig the rectification
(R1, R2, P1, P2, Q) is always derived here with OpenCV, never read from a file.

Conventions: OpenCV's. `R`, `T` map a point from the left camera frame to the right one,
``X_right = R @ X_left + T``, with T in metres. Camera frames are optical (x right, y down, z forward).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import CalibrationError


@dataclass(frozen=True)
class Intrinsics:
    """One camera: pinhole matrix plus OpenCV's 5-term distortion (k1, k2, p1, p2, k3)."""

    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> np.ndarray:
        return np.array(self.dist, dtype=np.float64)

    @classmethod
    def from_matrix(cls, K: np.ndarray, D: np.ndarray) -> Intrinsics:
        D = np.asarray(D, dtype=np.float64).ravel()
        d5 = np.zeros(5)
        d5[: min(5, D.size)] = D[:5]
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(K[0, 1]),
                   tuple(float(x) for x in d5))  # type: ignore[arg-type]


@dataclass(frozen=True)
class RectifiedModel:
    """The rectified left camera, which is the system's camera frame; the right camera sits at
    +baseline_m along x. Disparity d (px) gives depth Z = focal_px * baseline_m / d."""

    width: int
    height: int
    focal_px: float
    cx: float
    cy: float
    baseline_m: float
    # The outline (a polygon, px) of the part of the rectified picture each camera saw; None: all of
    # it. alpha 0 crops to what both saw; a larger alpha keeps more of the view and leaves the rest of
    # the picture black, and the seam between black and picture is an edge the two cameras draw at
    # different places: matched, it is a wall of phantom depths along the border (view_masks).
    view_left: tuple[tuple[float, float], ...] | None = None
    view_right: tuple[tuple[float, float], ...] | None = None

    @property
    def Q(self) -> np.ndarray:
        """Disparity-to-depth matrix as cv2.reprojectImageTo3D expects (right camera at +B)."""
        f, B = self.focal_px, self.baseline_m
        return np.array([[1, 0, 0, -self.cx], [0, 1, 0, -self.cy], [0, 0, 0, f], [0, 0, 1.0 / B, 0]])

    def disparity_for_depth(self, z_m: float) -> float:
        return self.focal_px * self.baseline_m / z_m


def model_of(cam: Any) -> RectifiedModel:
    """A CameraModel message (common/messages.py) -> the RectifiedModel it describes."""
    return RectifiedModel(cam.width, cam.height, cam.focal_px, cam.cx, cam.cy, cam.baseline_m,
                          view_left=_outline(cam.view_left), view_right=_outline(cam.view_right))


def _outline(points: Any) -> tuple[tuple[float, float], ...] | None:
    return None if points is None else tuple((float(x), float(y)) for x, y in points)


def view_masks(model: RectifiedModel, margin_px: int, scale: int = 1) -> tuple[np.ndarray, np.ndarray] | None:
    """(left, right) bool masks of the picture (shrunk `scale` times) that lie margin_px (px of
    that picture) or more inside what each camera saw; None when both saw every pixel. A matching
    window reaching past the outline sees the black beyond it."""
    if model.view_left is None and model.view_right is None:
        return None
    return _view_masks(model.width, model.height, model.view_left, model.view_right, margin_px, scale)


@functools.lru_cache(maxsize=8)
def _view_masks(width: int, height: int, left: tuple | None, right: tuple | None, margin_px: int,
                scale: int) -> tuple[np.ndarray, np.ndarray]:
    import cv2

    w, h = width // scale, height // scale
    kernel = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8) if margin_px > 0 else None
    out = []
    for outline in (left, right):
        m = np.full((h, w), 255, np.uint8)
        if outline is not None:
            m[:] = 0
            pts = np.round(np.asarray(outline, np.float64) / scale * 16).astype(np.int32)  # 4 fractional bits
            cv2.fillPoly(m, [pts], 255, cv2.LINE_8, shift=4)
        if outline is not None and kernel is not None:
            m = np.asarray(cv2.erode(m, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=255))
        mask = m > 0
        mask.setflags(write=False)  # cached: shared by every caller
        out.append(mask)
    return out[0], out[1]


def seen_by_both(d: np.ndarray, scale: float, seen_left: np.ndarray, seen_right: np.ndarray) -> np.ndarray:
    """Per pixel of a disparity map (px * scale, fixed point): whether it is in seen_left and its
    partner in the right picture (x - d, rounded) in seen_right (masks of view_masks)."""
    import cv2

    h, w = d.shape
    cols = np.arange(w, dtype=np.float32)[None, :] - d.astype(np.float32) * np.float32(1.0 / scale)
    rows = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    partner = cv2.remap(seen_right.view(np.uint8), cols, np.ascontiguousarray(rows), cv2.INTER_NEAREST,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return seen_left & (partner > 0)


@dataclass(frozen=True)
class RawRig:
    """A stereo pair as calibrated: two cameras and the pose of the right one wrt the left."""

    image_size: tuple[int, int]  # width, height
    left: Intrinsics
    right: Intrinsics
    R: np.ndarray  # 3x3, right wrt left
    T: np.ndarray  # 3, metres
    name: str = ""

    def __post_init__(self) -> None:
        _check_rotation(self.R, "R")
        T = np.asarray(self.T, dtype=np.float64).ravel()
        if T.shape != (3,) or not np.all(np.isfinite(T)):
            raise CalibrationError("T: expected 3 finite numbers (metres)")
        if np.linalg.norm(T) <= 1e-6:
            raise CalibrationError("T: the baseline is zero")
        _check_baseline(float(np.linalg.norm(T)), "T")
        object.__setattr__(self, "T", T)
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64))

    @property
    def rectified(self) -> bool:
        return False


# The longest baseline of a plausible rig (a truck's cameras sit under 2 m apart). A calibration in mm
# or cm read as metres would otherwise put everything 100-1000 times farther: past the vision range,
# every list empty and unflagged.
MAX_BASELINE_M = 5.0


def _check_baseline(b_m: float, where: str) -> None:
    if b_m > MAX_BASELINE_M:
        raise CalibrationError(f"{where}: a baseline of {b_m:g} m (over {MAX_BASELINE_M:g} m): calibrations are in "
                               f"metres; one in millimetres or centimetres must be divided by 1000 or 100")


@dataclass(frozen=True)
class RectifiedRig:
    """An already-rectified pair (ZED, KITTI, a folder of rectified images)."""

    model: RectifiedModel
    name: str = ""

    def __post_init__(self) -> None:
        _check_baseline(self.model.baseline_m, "baseline")

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.model.width, self.model.height)

    @property
    def rectified(self) -> bool:
        return True


Calibration = RawRig | RectifiedRig


@dataclass(frozen=True)
class Rectification:
    """What OpenCV's stereoRectify derives from a raw rig; R1/R2 rotate each camera into the
    common rectified frame, P1/P2 project from it."""

    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray
    model: RectifiedModel


def _check_rotation(R: Any, field: str) -> None:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise CalibrationError(f"{field}: expected a 3x3 matrix of finite numbers")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or abs(np.linalg.det(R) - 1.0) > 1e-4:
        raise CalibrationError(f"{field}: not a rotation matrix (R R^T != I or det != 1)")


def rectify_rig(rig: RawRig, alpha: float = 0.0) -> Rectification:
    """Derive the rectification. alpha=0 crops to valid pixels only, 1 keeps every source pixel."""
    import cv2

    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(
        rig.left.K, rig.left.D, rig.right.K, rig.right.D, rig.image_size, rig.R, rig.T.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha,
    )
    f = float(P1[0, 0])
    baseline = float(-P2[0, 3] / P2[0, 0])
    if baseline <= 0:
        raise CalibrationError("T: the right camera must sit to the right of the left one (T[0] < 0)")
    model = RectifiedModel(rig.image_size[0], rig.image_size[1], f, float(P1[0, 2]), float(P1[1, 2]), baseline)
    return Rectification(R1, R2, P1, P2, Q, model)


# --- built-in profiles -------------------------------------------------------------------------

def _lifecam_studio() -> RawRig:
    import cv2

    om = np.array([0.00026, 0.00426, -0.00106])
    R, _ = cv2.Rodrigues(om)
    return RawRig(
        image_size=(640, 480),
        left=Intrinsics(644.66377, 643.44653, 299.62051, 238.17653, 0.0, (-0.01557, 0.06445, -0.00456, -0.00842, 0.0)),
        right=Intrinsics(646.13434, 646.10041, 302.35729, 245.68957, 0.0, (-0.02068, 0.09349, -0.00615, -0.00943, 0.0)),
        R=R,
        T=np.array([-99.44854, -0.53398, 2.09170]) / 1000.0,
        name="lifecam-studio",
    )


PROFILES = {"lifecam-studio": _lifecam_studio}


# --- YAML ----------------------------------------------------------------------------------------

def _num(doc: dict, key: str, where: str) -> float:
    if key not in doc:
        raise CalibrationError(f"{where}: missing field '{key}'")
    try:
        v = float(doc[key])
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: field '{key}' must be a number, got {doc[key]!r}") from None
    if not np.isfinite(v):
        raise CalibrationError(f"{where}: field '{key}' must be finite")
    return v


def _vec(doc: dict, key: str, n: int, where: str) -> np.ndarray:
    if key not in doc:
        raise CalibrationError(f"{where}: missing field '{key}'")
    try:
        a = np.asarray(doc[key], dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: field '{key}' must be a list of numbers") from None
    if a.size != n or not np.all(np.isfinite(a)):
        raise CalibrationError(f"{where}: field '{key}' must hold {n} finite numbers, got {a.size}")
    return a


def _size(doc: dict, where: str) -> tuple[int, int]:
    from common.errors import FileError
    from common.files import check_image_size

    s = _vec(doc, "image_size", 2, where)
    if np.any(s <= 0) or np.any(s != np.round(s)):
        raise CalibrationError(f"{where}: field 'image_size' must be two positive integers [width, height]")
    try:  # remap tables for 200000x200000 pixels would ask for ~240 GB
        check_image_size(int(s[0]), int(s[1]), f"{where}: field 'image_size'")
    except FileError as e:
        raise CalibrationError(str(e)) from None
    return int(s[0]), int(s[1])


def _outline_field(doc: dict, key: str, where: str) -> tuple[tuple[float, float], ...] | None:
    """An optional outline of a rectified calibration (what a camera saw of the rectified picture,
    RectifiedModel.view_left / view_right: a recording of pairs rectified with alpha > 0 keeps it)."""
    if doc.get(key) is None:
        return None
    try:
        a = np.asarray(doc[key], dtype=np.float64)
    except (TypeError, ValueError):
        a = np.empty(0)
    if a.ndim != 2 or a.shape[1] != 2 or len(a) < 3 or not np.isfinite(a).all() or np.abs(a).max() > 65536:
        raise CalibrationError(f"{where}: field '{key}' must be a list of 3 or more [x, y] points (px)")
    return tuple((float(x), float(y)) for x, y in a)


def calibration_from_dict(doc: Any, where: str = "calibration") -> Calibration:
    if not isinstance(doc, dict):
        raise CalibrationError(f"{where}: expected a mapping at the top level")
    name = str(doc.get("name", ""))
    if doc.get("rectified", False):
        w, h = _size(doc, where)
        pp = _vec(doc, "principal_point", 2, where)
        f = _num(doc, "focal_px", where)
        B = _num(doc, "baseline_m", where)
        if f <= 0:
            raise CalibrationError(f"{where}: field 'focal_px' must be positive")
        if B <= 0:
            raise CalibrationError(f"{where}: field 'baseline_m' must be positive")
        _check_baseline(B, f"{where}: field 'baseline_m'")
        views = [_outline_field(doc, k, where) for k in ("view_left", "view_right")]
        return RectifiedRig(RectifiedModel(w, h, f, float(pp[0]), float(pp[1]), B, *views), name)
    size = _size(doc, where)
    cams = []
    for side in ("left", "right"):
        c = doc.get(side)
        at = f"{where}: {side}"
        if not isinstance(c, dict):
            raise CalibrationError(f"{where}: missing section '{side}'")
        K = _vec(c, "K", 9, at).reshape(3, 3)
        if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(f"{at}: field 'K' is not a camera matrix [[fx,s,cx],[0,fy,cy],[0,0,1]]")
        D = _vec(c, "distortion", 5, at)
        if "image_size" in c and _size(c, at) != size:
            raise CalibrationError(f"{at}: field 'image_size' {_size(c, at)} differs from the rig's {size}")
        cams.append(Intrinsics.from_matrix(K, D))
    R = _vec(doc, "R", 9, where).reshape(3, 3)
    T = _vec(doc, "T", 3, where)
    try:
        return RawRig(size, cams[0], cams[1], R, T, name)
    except CalibrationError as e:
        raise CalibrationError(f"{where}: {e}") from None


def calibration_to_dict(cal: Calibration) -> dict:
    if isinstance(cal, RectifiedRig):
        m = cal.model
        doc = {"name": cal.name, "rectified": True, "image_size": [m.width, m.height], "focal_px": m.focal_px,
               "principal_point": [m.cx, m.cy], "baseline_m": m.baseline_m}
        doc.update({k: [list(p) for p in v] for k, v in (("view_left", m.view_left), ("view_right", m.view_right))
                    if v is not None})
        return doc
    out: dict[str, Any] = {"name": cal.name, "rectified": False, "image_size": list(cal.image_size)}
    for side, c in (("left", cal.left), ("right", cal.right)):
        out[side] = {"K": [float(x) for x in c.K.ravel()], "distortion": [float(x) for x in c.dist]}
    out["R"] = [float(x) for x in cal.R.ravel()]
    out["T"] = [float(x) for x in cal.T]
    return out


# Fields that only other tools' calibration files have: their presence earns a hint to import.
_FOREIGN_FIELDS = {"M1": "OpenCV stereo_calib", "camera_matrix": "ROS camera_info", "cam0": "Kalibr camchain",
                   "T_BS": "EuRoC sensor.yaml", "intrinsics": "Kalibr/EuRoC"}


def load_calibration(spec: str | Path) -> Calibration:
    """A built-in profile name (e.g. ``lifecam-studio``) or a path to a calibration YAML. A missing,
    empty or binary file is a FileError, another tool's format a CalibrationError that says how to
    import it, both in one line."""
    from common.errors import FileError
    from common.files import read_yaml

    s = str(spec)
    if s in PROFILES:
        return PROFILES[s]()
    if not Path(s).expanduser().exists():
        raise CalibrationError(f"calibration {s}: no such file or folder, nor a built-in profile "
                               f"(profiles: {', '.join(sorted(PROFILES))})")
    try:
        doc = read_yaml(s, "calibration")
    except FileError as e:
        if "not valid YAML" in str(e) and _looks_like_opencv(s):
            raise CalibrationError(f"calibration {s}: an OpenCV FileStorage file, not this program's calibration "
                                   f"YAML; convert it with: ballbot-vision calibration import {s} ... -o rig.yaml"
                                   ) from None
        raise
    if isinstance(doc, dict) and not {"rectified", "left", "K"} & set(doc):
        foreign = [tool for key, tool in _FOREIGN_FIELDS.items() if key in doc]
        if foreign:
            raise CalibrationError(f"calibration {s}: a {foreign[0]} file, not this program's calibration YAML; "
                                   f"convert it with: ballbot-vision calibration import {s} ... -o rig.yaml")
    return calibration_from_dict(doc, where=s)


def load_raw_rig(spec: str | Path) -> RawRig:
    """load_calibration, for a use that needs the raw rig (lenses, R, T): a rectified one is refused."""
    cal = load_calibration(spec)
    if not isinstance(cal, RawRig):
        raise CalibrationError(f"calibration {spec}: already rectified; this needs the raw rig")
    return cal


def _looks_like_opencv(path: str) -> bool:
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.startswith(b"%YAML:1.0") or b"!!opencv-matrix" in head


def validate_calibration(cal: Calibration, where: str) -> Calibration:
    """Exactly the checks the loader makes (finite positive focal lengths, a rotation, a baseline,
    a possible image size, ...), on a calibration about to be written: nothing is written that
    load_calibration would refuse."""
    return calibration_from_dict(calibration_to_dict(cal), where=where)


def save_calibration(cal: Calibration, path: str | Path) -> None:
    """Write the calibration YAML; refuses (CalibrationError) what the loader would refuse."""
    import yaml

    validate_calibration(cal, f"refusing to write {path}")
    Path(path).write_text(yaml.safe_dump(calibration_to_dict(cal), sort_keys=False))


def rectified_model(cal: Calibration, alpha: float = 0.0) -> RectifiedModel:
    return cal.model if isinstance(cal, RectifiedRig) else rectify_rig(cal, alpha).model
