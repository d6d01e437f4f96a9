"""Live chessboard collection for `ballbot-vision calibrate --live`: which views to keep and what is
still missing. Pure functions of corner positions: no Zenoh, no files (the command's loop does those).

A view (the board found in both images) is kept when it differs from every view kept so far: its
board centre moved, its apparent size changed, or its tilt changed. Coverage is tracked on a grid
of image cells (3x3: top-left .. bottom-right) in both images, and over four tilts, named after the
side of the board turned AWAY from the camera: "left", "right", "up" (top edge away), "down".
Tilt is measured from foreshortening: an edge farther from the camera looks shorter. With the
board's opposite outer edges at depths Z1 and Z2, log(len1 / len2) = log(Z2 / Z1) ~ tan(tilt) * w / f,
w being the board's apparent extent across those edges in pixels; f is not known before the
calibration, so a nominal focal length of one image width (a 53 degree field of view, typical of
webcams) stands in. The angle is rough (within ~20 % for fields of view of 40..70 degrees) but
independent of the board's distance, which is all the binning needs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# Thresholds of "sufficiently different" and of a tilt that counts.
MIN_CENTRE_MOVE = 0.08   # of the image diagonal
MIN_SIZE_CHANGE = 0.25   # |log(area ratio)|
MIN_TILT_CHANGE = 0.20   # rad (about 11 degrees), either axis
TILT_BIN = 0.25          # rad (about 14 degrees): a tilt beyond this counts as "left", "up", ...

TILTS = ("left", "right", "up", "down")


def cell_names(grid: int = 3) -> list[list[str]]:
    """Names of the grid cells, [row][col]: 3x3 -> top-left, top, top-right, left, centre, ..."""
    if grid == 3:
        rows, cols = ("top", "", "bottom"), ("left", "", "right")
        return [["-".join(p for p in (r, c) if p) or "centre" for c in cols] for r in rows]
    return [[f"r{r}c{c}" for c in range(grid)] for r in range(grid)]


@dataclass(frozen=True)
class BoardView:
    """What matters about one board detection in one image."""

    centre: tuple[float, float]  # pixels
    area: float                  # pixels^2 of the outer-corner quadrilateral
    tilt_x: float                # rad, about the vertical axis: > 0 when the right side is farther
    tilt_y: float                # rad, about the horizontal axis: > 0 when the bottom side is farther
    cells: frozenset[tuple[int, int]]  # (row, col) grid cells holding at least one corner

    @property
    def tilts(self) -> set[str]:
        out = set()
        if self.tilt_x > TILT_BIN:
            out.add("right")
        elif self.tilt_x < -TILT_BIN:
            out.add("left")
        if self.tilt_y > TILT_BIN:
            out.add("down")
        elif self.tilt_y < -TILT_BIN:
            out.add("up")
        return out


def describe_board(corners: np.ndarray, pattern: tuple[int, int], image_size: tuple[int, int],
                   grid: int = 3) -> BoardView:
    """corners: (N, 1, 2) or (N, 2) as findChessboardCorners orders them (row by row, `pattern`
    = (cols, rows)); image_size = (w, h)."""
    cols, rows = pattern
    w, h = image_size
    c = np.asarray(corners, np.float64).reshape(rows, cols, 2)
    quad = np.array([c[0, 0], c[0, -1], c[-1, -1], c[-1, 0]])
    x, y = quad[:, 0], quad[:, 1]
    area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    # The four outer edges; which pair is vertical in the image decides left/right vs top/bottom
    # (the detector may number the board from any corner).
    edges_a = (c[:, 0], c[:, -1])   # first and last column
    edges_b = (c[0, :], c[-1, :])   # first and last row

    def length(e: np.ndarray) -> float:
        return float(np.linalg.norm(e[-1] - e[0]))

    def is_vertical(pair) -> bool:
        d = pair[0][-1] - pair[0][0]
        return abs(d[1]) >= abs(d[0])

    vert, horiz = (edges_a, edges_b) if is_vertical(edges_a) else (edges_b, edges_a)
    left, right = sorted(vert, key=lambda e: float(e[:, 0].mean()))
    top, bottom = sorted(horiz, key=lambda e: float(e[:, 1].mean()))
    f = float(w)  # nominal focal length (see the module docstring)
    width = 0.5 * (length(top) + length(bottom))
    height = 0.5 * (length(left) + length(right))
    tilt_x = math.atan(math.log(max(length(left), 1e-6) / max(length(right), 1e-6)) * f / max(width, 1e-6))
    tilt_y = math.atan(math.log(max(length(top), 1e-6) / max(length(bottom), 1e-6)) * f / max(height, 1e-6))
    pts = c.reshape(-1, 2)
    ci = np.clip((pts[:, 0] * grid // w).astype(int), 0, grid - 1)
    ri = np.clip((pts[:, 1] * grid // h).astype(int), 0, grid - 1)
    cells = frozenset(zip(ri.tolist(), ci.tolist()))
    centre = (float(pts[:, 0].mean()), float(pts[:, 1].mean()))
    return BoardView(centre, area, tilt_x, tilt_y, cells)


def differs(a: BoardView, b: BoardView, image_size: tuple[int, int]) -> str | None:
    """Why view a is sufficiently different from b ("moved", "size", "tilt"), or None."""
    diag = math.hypot(*image_size)
    if math.hypot(a.centre[0] - b.centre[0], a.centre[1] - b.centre[1]) > MIN_CENTRE_MOVE * diag:
        return "moved"
    if abs(math.log(max(a.area, 1e-6) / max(b.area, 1e-6))) > MIN_SIZE_CHANGE:
        return "size"
    if max(abs(a.tilt_x - b.tilt_x), abs(a.tilt_y - b.tilt_y)) > MIN_TILT_CHANGE:
        return "tilt"
    return None


@dataclass
class Coverage:
    """The views accepted so far and what they cover. consider() decides on a new view."""

    pattern: tuple[int, int]
    image_size: tuple[int, int]
    grid: int = 3
    views: list[tuple[BoardView, BoardView]] = field(default_factory=list)  # (left, right) per view

    def consider(self, left_corners: np.ndarray, right_corners: np.ndarray) -> tuple[bool, str]:
        """Accept (and record) the view if it differs from every accepted one. Returns (accepted,
        reason): the first view is "first"; else "moved" / "size" / "tilt", or why it was refused."""
        lv = describe_board(left_corners, self.pattern, self.image_size, self.grid)
        rv = describe_board(right_corners, self.pattern, self.image_size, self.grid)
        if not self.views:
            self.views.append((lv, rv))
            return True, "first"
        reasons = []
        for al, _ in self.views:
            why = differs(lv, al, self.image_size)
            if why is None:
                return False, "too similar to an accepted view"
            reasons.append(why)
        self.views.append((lv, rv))
        # the reason against the most similar view: the one that needed the weakest argument
        order = {"tilt": 0, "size": 1, "moved": 2}
        return True, min(reasons, key=order.__getitem__)

    def covered_cells(self) -> set[tuple[int, int]]:
        """Cells holding board corners in the left AND the right image (in any views)."""
        left = set().union(*(v[0].cells for v in self.views)) if self.views else set()
        right = set().union(*(v[1].cells for v in self.views)) if self.views else set()
        return left & right

    def missing_cells(self) -> list[str]:
        names = cell_names(self.grid)
        got = self.covered_cells()
        return [names[r][c] for r in range(self.grid) for c in range(self.grid) if (r, c) not in got]

    def missing_tilts(self) -> list[str]:
        seen = set().union(*(v[0].tilts for v in self.views)) if self.views else set()
        return [t for t in TILTS if t not in seen]

    def summary(self) -> str:
        cells = self.missing_cells()
        tilts = self.missing_tilts()
        return (f"missing: {', '.join(cells) if cells else 'none'}; "
                f"tilts: {', '.join(tilts) if tilts else 'all seen'}")
