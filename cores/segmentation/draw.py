"""One frame of the segmenter's output drawn over the rectified left image, for people.

    draw_frame(image, obstacles, model, freespace=None, mount=None) -> (H, W, 3) uint8 BGR

What is drawn:
- the free-space grid on the ground: every pixel whose viewing ray meets the ground plane inside the
  grid takes its cell's colour, translucent: free (0) green, occupied (100) red, unknown (-1) left
  as it is. The ground plane is the one of `mount` (ground.frame_mount: the mount the segmenter used
  for the frame; by default the list's ground estimate without yaw or offsets), so a cell is drawn
  where that ground puts it, and no pixel is drawn twice;
- every obstacle's box (bbox_px: x0, y0 inclusive, x1, y1 exclusive), with "#id distance" above it:
  confirmed tracks solid and thick in CONFIRMED colour, unconfirmed ones thin and dashed in
  UNCONFIRMED colour;
- a caption along the top edge: seq, number of obstacles (confirmed), and the ground estimate
  (height, pitch, roll, source).
The picture has the image's size; nothing here reads files or keeps state.

    draw_truths(picture, truths) draws, for a scenario with known answers (eval --draw), each true
obstacle's box: TRUTH (thin, dashed) when some obstacle was matched to it, MISSED (solid, labelled
"missed") when none was.
"""
from __future__ import annotations

import cv2
import numpy as np

from common.messages import FreeSpace, ObstacleList
from cores import camera
from cores.segmentation.mount import Mount

# BGR
CONFIRMED = (0, 255, 255)  # yellow
UNCONFIRMED = (255, 0, 255)  # magenta
FREE = (0, 200, 0)
OCCUPIED = (0, 0, 255)
FREE_ALPHA = 0.35
OCCUPIED_ALPHA = 0.45
TRUTH = (255, 255, 0)  # cyan
MISSED = (0, 140, 255)  # orange
CAPTION_PX = 18  # height of the caption band
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def to_bgr(image: np.ndarray) -> np.ndarray:
    """(H, W) grey or (H, W, 1 | 3) BGR uint8 -> a new (H, W, 3) uint8 BGR image."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"draw: expected an 8-bit image, got {img.dtype}")
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
        return cv2.cvtColor(img.reshape(img.shape[:2]), cv2.COLOR_GRAY2BGR)
    if img.ndim == 3 and img.shape[2] == 3:
        return img.copy()
    raise ValueError(f"draw: expected (H, W) or (H, W, 3), got shape {img.shape}")


def ground_cells(freespace: FreeSpace, mount: Mount, model: camera.RectifiedModel,
                 max_range_m: float = 200.0) -> np.ndarray:
    """(H, W) int16 per pixel of the rectified left image: the value of the free-space cell its
    viewing ray meets the ground (base z = 0) in, or -2 where the ray misses the grid, looks above
    the horizon or meets the ground farther than max_range_m."""
    h, w = model.height, model.width
    u = (np.arange(w, dtype=np.float64) - model.cx) / model.focal_px
    v = (np.arange(h, dtype=np.float64) - model.cy) / model.focal_px
    R = mount.R_base_camera
    # base-frame ray of pixel (v, u) = R @ (u, v, 1) = R[:, 0] u + R[:, 1] v + R[:, 2]
    ray = (R[:, 0][None, None, :] * u[None, :, None] + R[:, 1][None, None, :] * v[:, None, None]
           + R[:, 2][None, None, :])
    o = mount.origin_base
    down = ray[..., 2] < -1e-9
    t = np.where(down, -o[2] / np.where(down, ray[..., 2], -1.0), np.inf)
    x = o[0] + t * ray[..., 0]
    y = o[1] + t * ray[..., 1]
    res = freespace.resolution_m
    col = np.floor((x - freespace.origin_m[0]) / res)
    row = np.floor((y - freespace.origin_m[1]) / res)
    hit = down & (t * np.linalg.norm(ray, axis=-1) <= max_range_m) & (col >= 0) & (col < freespace.width) \
        & (row >= 0) & (row < freespace.height)
    grid = np.frombuffer(freespace.cells, dtype=np.int8).reshape(freespace.height, freespace.width)
    out = np.full((h, w), -2, np.int16)
    out[hit] = grid[row[hit].astype(np.intp), col[hit].astype(np.intp)]
    return out


def _blend(img: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int], alpha: float) -> None:
    if mask.any():
        px = img[mask].astype(np.float32)
        img[mask] = (px * (1 - alpha) + np.asarray(colour, np.float32) * alpha).round().astype(np.uint8)


def _dashed_rect(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, colour, dash: int = 6) -> None:
    for a in range(x0, x1 + 1, 2 * dash):
        b = min(a + dash - 1, x1)
        cv2.line(img, (a, y0), (b, y0), colour, 1)
        cv2.line(img, (a, y1), (b, y1), colour, 1)
    for a in range(y0, y1 + 1, 2 * dash):
        b = min(a + dash - 1, y1)
        cv2.line(img, (x0, a), (x0, b), colour, 1)
        cv2.line(img, (x1, a), (x1, b), colour, 1)


def _label(img: np.ndarray, text: str, x: int, y: int, colour, scale: float = 0.4, top: int = 0) -> None:
    """text with its baseline at y (moved inside the image, below row `top`), on a dark patch for legibility."""
    (tw, th), base = cv2.getTextSize(text, _FONT, scale, 1)
    h, w = img.shape[:2]
    x = int(min(max(0, x), max(0, w - tw - 2)))
    y = int(min(max(top + th + 2, y), h - base - 1))
    img[max(0, y - th - 2):min(h, y + base + 1), x:min(w, x + tw + 2)] //= 3
    cv2.putText(img, text, (x + 1, y), _FONT, scale, colour, 1, cv2.LINE_AA)


def caption(obstacles: ObstacleList) -> str:
    n = len(obstacles.obstacles)
    confirmed = sum(o.confirmed for o in obstacles.obstacles)
    g = obstacles.ground
    ground = ("ground: unknown" if g is None else
              f"ground: h {g.height_m:.2f} m  pitch {g.pitch_deg:+.1f} deg  roll {g.roll_deg:+.1f} deg  {g.source}"
              + (f" ({g.inlier_fraction:.0%} inliers)" if g.inlier_fraction else ""))
    # a picture of a degraded list with no box must not read as a clear way either
    return f"seq {obstacles.seq}  {n} obstacle(s), {confirmed} confirmed  {ground}" + \
        "".join(f"  {w}" for w in obstacles.warnings())


def draw_frame(image: np.ndarray, obstacles: ObstacleList, model: camera.RectifiedModel,
               freespace: FreeSpace | None = None, mount: Mount | None = None) -> np.ndarray:
    """image: the rectified left image, (H, W) grey or (H, W, 3) BGR uint8, the size of `model`.
    obstacles: the frame's list (camera frame); freespace: its grid (base frame) or None; mount: the
    camera on the base for projecting the grid (None: the one the list carries, ObstacleList.mount;
    none either: the grid is not drawn). -> (H, W, 3) uint8 BGR, a new array."""
    img = to_bgr(image)
    h, w = img.shape[:2]
    if (w, h) != (model.width, model.height):
        raise ValueError(f"draw: image is {w}x{h}, the camera model {model.width}x{model.height}")
    if mount is None:
        mount = Mount.of(obstacles.mount)
    if freespace is not None and mount is not None:
        cells = ground_cells(freespace, mount, model)
        _blend(img, cells == 0, FREE, FREE_ALPHA)
        _blend(img, cells == 100, OCCUPIED, OCCUPIED_ALPHA)
    # farthest first, so the nearest box and label are drawn on top
    for o in sorted(obstacles.obstacles, key=lambda o: -o.distance_m):
        x0, y0, x1, y1 = o.bbox_px
        x0, y0 = int(np.clip(x0, 0, w - 1)), int(np.clip(y0, 0, h - 1))
        x1, y1 = int(np.clip(x1 - 1, x0, w - 1)), int(np.clip(y1 - 1, y0, h - 1))
        if o.confirmed:
            cv2.rectangle(img, (x0, y0), (x1, y1), CONFIRMED, 2)
        else:
            _dashed_rect(img, x0, y0, x1, y1, UNCONFIRMED)
        _label(img, f"#{o.id} {o.distance_m:.1f}m", x0, y0 - 3, CONFIRMED if o.confirmed else UNCONFIRMED,
               top=min(CAPTION_PX, h) + 1)
    band = min(CAPTION_PX, h)
    img[:band] //= 3
    cv2.putText(img, caption(obstacles), (4, band - 5), _FONT, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def draw_truths(picture: np.ndarray, truths: list[tuple[str, tuple[int, int, int, int], bool]]) -> np.ndarray:
    """picture: draw_frame's output (changed in place and returned). truths: (name, bbox_px (x0, y0,
    x1, y1, inclusive), matched) of each true obstacle the frame is scored on."""
    h, w = picture.shape[:2]
    for name, (x0, y0, x1, y1), matched in truths:
        x0, x1 = int(np.clip(x0, 0, w - 1)), int(np.clip(x1, 0, w - 1))
        y0, y1 = int(np.clip(y0, 0, h - 1)), int(np.clip(y1, 0, h - 1))
        if matched:
            _dashed_rect(picture, x0, y0, x1, y1, TRUTH, dash=3)
            _label(picture, name, x0, y1 + 12, TRUTH, scale=0.35)
        else:
            cv2.rectangle(picture, (x0, y0), (x1, y1), MISSED, 1)
            _label(picture, f"missed {name}", x0, y1 + 12, MISSED, scale=0.35)
    return picture
