"""Rectification check: after rectification a scene point lies on the same row in both images, so
the vertical offset |dy| of matched features measures how good the calibration is.

ORB features, brute-force Hamming matching kept only if mutual best (cross-check) and clearly
better than the second best (Lowe's ratio test). No CLI and no Zenoh here.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from common.errors import BallbotError
from common.messages import ClippedTiles, FrameChecks, NearField, RowAlignment
from cores import camera
from cores.calibration.near import NearCheck
from cores.matching.disparity import FrozenInput


@dataclass(frozen=True)
class RowCheck:
    matches: int
    median_dy: float  # px
    p95_dy: float  # px
    median_disparity: float  # px, x_left - x_right
    candidates: int = 0  # matches before the epipolar (RANSAC) filter
    reversed_share: float = 0.0  # of the matches over 1 px off zero disparity, the share below -1 px

    def format(self) -> str:
        return (f"rectification check: {self.matches} ORB matches (of {self.candidates} before RANSAC), "
                f"vertical offset |dy| median "
                f"{self.median_dy:.3f} px, 95th percentile {self.p95_dy:.3f} px "
                f"(median disparity {self.median_disparity:.1f} px)")


def _gray(a: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(a, cv2.COLOR_BGR2GRAY) if a.ndim == 3 else a


def _refine_by_correlation(left: np.ndarray, right: np.ndarray, a: np.ndarray, half: int = 5, search: int = 3,
                           min_score: float = 0.8) -> np.ndarray:
    """ORB keypoints sit on integer pixels of their pyramid level. Re-measure each match by
    correlating an 11x11 patch of the left image around the left point over +-3 px around the
    right point, with a parabola through the peak in x and y; the left point stays where it is.
    Matches whose patch is flat, ambiguous or at a border are dropped."""
    L, R = left.astype(np.float32), right.astype(np.float32)
    h, w = L.shape
    out = []
    for (xl, yl), (xr, yr) in a:
        il, jl, ir, jr = int(round(yl)), int(round(xl)), int(round(yr)), int(round(xr))
        m = half + search + 1
        if not (m <= il < h - m and m <= jl < w - m and m <= ir < h - m and m <= jr < w - m):
            continue
        tpl = L[il - half:il + half + 1, jl - half:jl + half + 1]
        if float(tpl.std()) < 2.0:
            continue
        win = R[ir - half - search:ir + half + search + 1, jr - half - search:jr + half + search + 1]
        res = cv2.matchTemplate(win, tpl, cv2.TM_CCOEFF_NORMED)
        _, score, _, (px, py) = cv2.minMaxLoc(res)
        if score < min_score or not (0 < px < res.shape[1] - 1 and 0 < py < res.shape[0] - 1):
            continue

        def vertex(c_m: float, c_0: float, c_p: float) -> float:
            den = c_m - 2 * c_0 + c_p
            return 0.0 if den >= 0 else 0.5 * (c_m - c_p) / den

        sx = vertex(res[py, px - 1], res[py, px], res[py, px + 1])
        sy = vertex(res[py - 1, px], res[py, px], res[py + 1, px])
        # the patch centre sits at (jl, il) in the left image; in the right image at:
        out.append(((jl, il), (jr + px - search + sx, ir + py - search + sy)))
    return np.asarray(out, dtype=np.float64).reshape(-1, 2, 2)


def row_alignment(left: np.ndarray, right: np.ndarray, n_features: int = 4000, ratio: float = 0.8,
                  min_matches: int = 8, ransac_px: float = 2.0,
                  subpixel: bool = True, max_refined: int | None = None, levels: int = 8) -> RowCheck:
    """left, right: a rectified pair (H, W) or (H, W, 3), uint8 -> |dy| statistics of matches.
    max_refined: refine (and measure) at most this many matches, spread over all of them (the
    refinement is most of the cost; a median of 100 is as good as one of 1000); levels: ORB's
    pyramid levels."""
    orb = cv2.ORB.create(nfeatures=n_features, nlevels=levels)
    kl, dl = orb.detectAndCompute(_gray(left), None)
    kr, dr = orb.detectAndCompute(_gray(right), None)
    if dl is None or dr is None or len(kl) < 2 or len(kr) < 2:
        raise BallbotError("rectification check: too few ORB features (a textureless pair?)")
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    fwd = bf.knnMatch(dl, dr, k=2)
    back = {m[0].queryIdx: m[0].trainIdx for m in bf.knnMatch(dr, dl, k=2) if m}
    pts = []
    for m in fwd:
        if len(m) < 2:
            continue
        best, second = m
        if best.distance >= ratio * second.distance:
            continue
        if back.get(best.trainIdx) != best.queryIdx:
            continue
        pts.append((kl[best.queryIdx].pt, kr[best.trainIdx].pt))
    if len(pts) < min_matches:
        raise BallbotError(f"rectification check: only {len(pts)} ORB matches survive the cross-check and "
                           f"ratio test (need {min_matches})")
    a = np.asarray(pts, dtype=np.float64)
    # Repetitive texture (a chessboard!) passes both tests with wrong partners; keep the matches
    # consistent with one epipolar geometry (RANSAC on F). This assumes nothing about rows, so a
    # bad rectification still shows up in |dy|.
    F, inl = cv2.findFundamentalMat(a[:, 0], a[:, 1], cv2.FM_RANSAC, ransac_px, 0.999)
    if F is not None and inl is not None and int(inl.sum()) >= min_matches:
        a = a[inl.ravel().astype(bool)]
    if max_refined is not None and len(a) > max_refined:
        a = a[np.linspace(0, len(a) - 1, max_refined).astype(int)]
    if subpixel:
        a = _refine_by_correlation(_gray(left), _gray(right), a)
        if len(a) < min_matches:
            raise BallbotError(f"rectification check: only {len(a)} matches could be refined to sub-pixel "
                               f"(need {min_matches})")
    dy = np.abs(a[:, 0, 1] - a[:, 1, 1])
    d = a[:, 0, 0] - a[:, 1, 0]
    return RowCheck(len(a), float(np.median(dy)), float(np.percentile(dy, 95)), float(np.median(d)), len(pts),
                    reversed_share(d))


SWAP_MIN_MATCHES = 10
SWAPPED_SHARE = 0.5  # a reversed_share over it: the pair is swapped. Measured: 0-0.10 on the real recordings and
                     # every shipped scene the right way round, 0.88-1.0 swapped


def reversed_share(d: np.ndarray) -> float:
    """Of matched features' disparities (x_left - x_right, px) those over 1 px off zero, the share
    below -1 px; 0 with fewer than SWAP_MIN_MATCHES of them. A rectified pair puts infinity at zero
    disparity and everything nearer to the right in the left image, so the share is about 0 (RANSAC
    lets few wrong partners through); with the cameras swapped (cables, or the devices' order) it is
    about 1. A scene all far away (|d| <= 1 px) says nothing either way, and has nothing near to
    misplace."""
    off = d[np.abs(d) > 1.0]
    return float(np.mean(off < 0)) if off.size >= SWAP_MIN_MATCHES else 0.0


class RowMonitor:
    """The live rectification check (rectify runs it on the stream; cores/pipeline.py offline): a
    camera knocked on the rig, a loose lens or a calibration of another rig moves the right image
    off the left's rows; swapped cameras put what is near farther left in the left image than in
    the right (`reversed_share`). Block matching then finds fewer and wrong matches, and nothing else says
    why. Every `interval_s` of stream time one rectified pair is checked (row_alignment with fewer
    features: 10-14 ms of one core), and `latest` is what every later frame carries (StereoFrame.rows,
    DisparityMap.rows), so each list can say `rows-misaligned` (cores/segmentation/builder.py).

    A pair with too few features (a bare wall, darkness) leaves the last result in place: what was
    measured misaligned stays so until a check says otherwise."""

    def __init__(self, interval_s: float = 1.0, tolerance_px: float = 0.5, n_features: int = 300,
                 max_refined: int = 60):
        self.interval_s = interval_s
        self.tolerance_px = tolerance_px
        self.n_features = n_features
        self.max_refined = max_refined
        self.latest: RowAlignment | None = None
        self.checks = 0
        self.failed = 0
        self.epoch = 0
        self._last_t: float | None = None

    def due(self, t_s: float) -> bool:
        """Whether a pair at t_s (s, a clock that never goes backwards) is to be checked."""
        return self.interval_s > 0 and (self._last_t is None or t_s - self._last_t >= self.interval_s)

    def take(self, t_s: float) -> int | None:
        """For a checker off the stream's path: if a pair at t_s is due, the next is due only
        interval_s later (whether this one is checked or dropped) -> the epoch to check it under;
        None when not due."""
        if not self.due(t_s):
            return None
        self._last_t = t_s
        return self.epoch

    def reset(self) -> None:
        """A new calibration: what was measured was another rectification's; the next pair is due."""
        self.epoch += 1
        self.latest, self._last_t = None, None

    def check(self, left: np.ndarray, right: np.ndarray, t_s: float, stamp_ns: int,
              epoch: int | None = None) -> RowAlignment | None:
        """Check one rectified pair (captured at stamp_ns) -> the latest result. A pair taken under
        an older epoch (the calibration changed meanwhile) is not counted."""
        if epoch is None:
            self._last_t = t_s
        try:
            c = row_alignment(left, right, n_features=self.n_features, max_refined=self.max_refined, levels=1,
                              min_matches=20)
        except BallbotError:
            self.failed += 1
            return self.latest
        if epoch is not None and epoch != self.epoch:
            return self.latest
        self.checks += 1
        self.latest = RowAlignment(offset_px=min(c.median_dy, 1000.0), p95_px=min(c.p95_dy, 1000.0),
                                   matches=c.matches, tolerance_px=self.tolerance_px, checked_ns=stamp_ns,
                                   reversed_share=c.reversed_share)
        return self.latest

    def observe(self, left: np.ndarray, right: np.ndarray, t_s: float, stamp_ns: int) -> RowAlignment | None:
        """Check the pair if one is due -> the latest result (for a stream checked in line)."""
        return self.check(left, right, t_s, stamp_ns) if self.due(t_s) else self.latest


Camera = Literal["left", "right"]


def _cameras(left: bool, right: bool) -> list[Camera]:
    out: list[Camera] = []
    if left:
        out.append("left")
    if right:
        out.append("right")
    return out


def tile_texture(image: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """(H, W[, 3]) uint8 -> (rows, cols) float32: mean |d/dx| + |d/dy| (Sobel) over each tile of a
    cols x rows grid, on the picture shrunk to 8 x 8 pixels a tile (a quarter of a millisecond)."""
    cols, rows = grid
    small = cv2.resize(image, (cols * 8, rows * 8), interpolation=cv2.INTER_AREA)
    if small.ndim == 3:
        small = cv2.cvtColor(small, cv2.COLOR_BGR2GRAY)
    gx = cv2.convertScaleAbs(cv2.Sobel(small, cv2.CV_16S, 1, 0, ksize=3))
    gy = cv2.convertScaleAbs(cv2.Sobel(small, cv2.CV_16S, 0, 1, ksize=3))
    return cv2.resize(cv2.add(gx, gy).astype(np.float32), (cols, rows), interpolation=cv2.INTER_AREA)


def tile_sharpness(image: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """(H, W[, 3]) uint8 -> (rows, cols) float32: mean |d/dx| (Sobel, saturated at 255) over each tile
    of a cols x rows grid at full resolution: the fine detail a blur takes away (a smudge of grease on
    the lens), which tile_texture, on the picture shrunk, keeps. Horizontal only: what the matcher
    matches on (0.25 ms at 640 x 480)."""
    g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    gx = cv2.convertScaleAbs(cv2.Sobel(g, cv2.CV_16S, 1, 0, ksize=3))
    return cv2.resize(gx, grid, interpolation=cv2.INTER_AREA).astype(np.float32)


class BlockedView:
    """Whether part of one camera's view is blocked: a finger, a sticker, a lens cap half on, glare, a
    splash of mud. The other camera sees the scene there, so its picture has texture where the
    blocked one has none; the matcher measures nothing there and the list was missing what stood in
    it, unflagged (karlsruhe, a dark blob over a sixth of the right image: a parked car 17 m ahead
    gone from the list). Both pictures are cut into a GRID of tiles; a tile of one is blocked when
    its texture is under RATIO of the other's, and the other's is over MIN_TEXTURE, where the other
    picture can show it: a scene point at column x on the left lies at x - d on the right, so a
    right tile is compared with the flatter of the left's tile and the one to its right (and a left
    tile with the right's and the one to its left), and a near thing seen in different tiles by the
    two cameras does not count. A camera whose blocked tiles cover SHARE of its picture is blocked,
    from the first pair it is seen in: a finger on the lens when the robot starts, or a splash, hides
    what stands there from that pair on (the verdict had waited frozen_after_s, 0.5 s: the street's
    first six lists, at 10 pairs/s, with a finger over a third of the left picture missed what it hid
    and said nothing; no pair of either recording comes near SHARE, so the wait guarded against
    nothing). Measured on the recordings: at most 4.2 % of the tiles (karlsruhe) and 5.2 %
    (euroc: its window saturates in one camera only) by what one camera sees and the other does not;
    none on the synthetic scenes; the blob above, 13.5-15.6 %. A blurred patch (a smudge of grease)
    keeps too much of that texture to be told this way, yet the matcher loses what is behind it
    (two-boxes, bm, a Gaussian blur of sigma 4 px over a quarter of the right picture: the box 2.3 m
    away gone from the list, unflagged). So a tile is blocked too where its fine detail (tile_sharpness,
    at full resolution) is under BLUR_RATIO of the other's, relative to the median of that ratio over
    the textured tiles: one camera's exposure or contrast, which scales the whole picture's detail,
    cancels (the right picture at 0.4 of its brightness: no tile). Measured, flat or blurred: at most
    4.7 % of the tiles (karlsruhe) and 6.2 % (euroc); a smudge of sigma 3-4 px over a quarter of one
    picture, 13-26 % (sigma 2 px, where the matcher still keeps both boxes: 3-11 %). A smudge over
    most of a picture moves that median itself and is not told so (nor a lens out of focus). Looked at every
    EVERY_S at most (its cost: two pictures shrunk and their detail, 1.3 ms)."""

    GRID = (16, 12)
    RATIO = 0.25
    BLUR_RATIO = 0.4
    MIN_TEXTURE = 8.0  # grey levels / px of |gradient|: a textured tile
    SHARE = 0.1
    EVERY_S = 0.1

    def __init__(self) -> None:
        self._last_s: float | None = None
        self._blocked = (False, False)  # per camera, at the last look

    def blocked(self, left: np.ndarray, right: np.ndarray, t_s: float) -> list[Camera]:
        """The cameras whose view is blocked, as the last look (at most EVERY_S before t_s, s, a clock
        that never goes backwards) found it."""
        if self._last_s is None or t_s - self._last_s >= self.EVERY_S or t_s < self._last_s:
            self._last_s = t_s
            left_share, right_share = self.shares(left, right)
            self._blocked = (left_share >= self.SHARE, right_share >= self.SHARE)
        return _cameras(*self._blocked)

    @classmethod
    def shares(cls, left: np.ndarray, right: np.ndarray) -> tuple[float, float]:
        """(left, right): the share of each picture's tiles blocked, flat or blurred, now."""
        # the other camera's where each tile's scene lies in its picture (the flatter of two tiles)
        def right_there(a: np.ndarray) -> np.ndarray:
            return np.minimum(a, np.concatenate([a[:, :1], a[:, :-1]], 1))

        def left_there(a: np.ndarray) -> np.ndarray:
            return np.minimum(a, np.concatenate([a[:, 1:], a[:, -1:]], 1))
        tl, tr = tile_texture(left, cls.GRID), tile_texture(right, cls.GRID)
        sl, sr = tile_sharpness(left, cls.GRID), tile_sharpness(right, cls.GRID)
        out = []
        for own, other, own_s, other_s in ((tl, right_there(tr), sl, right_there(sr)),
                                           (tr, left_there(tl), sr, left_there(sl))):
            textured = other > cls.MIN_TEXTURE
            detail = own_s / np.maximum(other_s, np.float32(1e-3))
            usual = float(np.median(detail[textured])) if textured.any() else 1.0
            blocked = (own < cls.RATIO * other) | (detail < cls.BLUR_RATIO * usual)
            out.append(float((blocked & textured).mean()))
        return out[0], out[1]


# a pixel at this grey level or over is clipped: the sensor saw white, nothing of the scene
CLIP_LEVEL = 250
CLIPPED_GRID = (32, 24)  # tiles across, down
# A white patch is at infinity when the pixels clipped in one camera only are at most this share of
# those clipped in both: glare's disc lies at the same place in both pictures; a white thing at
# disparity D and W px wide is clipped in one camera only over 2 D for W - D in both (the street's
# backlit bus-shelter poster 4 m away: 3.5). Measured: nothing below the floor's horizon passes on
# either recording, a glare disc does (docs/architecture.md, washed-out).
AT_INFINITY = 0.2
STRIPS = 12  # the picture is cut into this many bands before patches are told apart: see clipped_tiles


def clipped_tiles(left: np.ndarray, right: np.ndarray, grid: tuple[int, int] = CLIPPED_GRID) -> ClippedTiles:
    """The rectified pair -> per tile of a grid (cols, rows), the share of its pixels clipped white
    in both pictures at the same place, in patches that lie at infinity (AT_INFINITY): the sun or a
    lamp ahead, glare over both lenses, the sky. A white thing near enough to sit apart in the two
    pictures (a backlit poster, snow on the kerb) does not count: its outline differs. The patches
    are cut into STRIPS bands first, so a glare disc that touches the sky, whose outline the trees
    and roofs in front of it make differ, is judged by its own band's outline. One camera alone
    clipped (a window it sees brighter) is BlockedView's. 0.3 ms at 640 x 480."""
    # every 4th pixel of every 4th row: a glare's patch is large, and the full size costs 2 ms at 640 x 480
    gl, gr = (np.ascontiguousarray(_gray(a)[::4, ::4]) for a in (left, right))
    _, both = cv2.threshold(cv2.min(gl, gr), CLIP_LEVEL - 1, 255, cv2.THRESH_BINARY)
    _, either = cv2.threshold(cv2.max(gl, gr), CLIP_LEVEL - 1, 255, cv2.THRESH_BINARY)
    either[::max(1, either.shape[0] // STRIPS)] = 0
    n, patch, stats, _ = cv2.connectedComponentsWithStats(either, connectivity=8)
    in_both = np.bincount(patch[both > 0], minlength=n)
    at_infinity = stats[:, cv2.CC_STAT_AREA] - in_both <= AT_INFINITY * in_both
    at_infinity[0] = False  # the background: not clipped
    white = np.where(at_infinity[patch] & (both > 0), np.uint8(255), np.uint8(0))
    tiles = cv2.resize(white, grid, interpolation=cv2.INTER_AREA)
    return ClippedTiles(width=grid[0], height=grid[1], data=tiles.tobytes())


def picture_noise(image: np.ndarray) -> float:
    """The picture's sensor noise, grey levels (the sigma of a Gaussian noise): the median absolute
    response to a 3x3 mask that cancels every plane of grey (Immerkaer 1996: [1 -2 1; -2 4 -2;
    1 -2 1], of norm 6 on pure noise), on every 4th pixel of every 8th row. The median, not the
    mean: edges and texture answer too, but on few of the pixels (the Karlsruhe street and the
    EuRoC room in daylight: 1.2-1.7). 0.2 ms at 640 x 480."""
    g = _gray(image)
    if g.dtype != np.uint8:  # in grey levels of 8 bits, whatever the camera gives (a 16-bit one: / 257)
        scale = 255.0 / 65535.0 if g.dtype == np.uint16 else 1.0
        g = np.clip(np.nan_to_num(g.astype(np.float32) * scale), 0, 255).astype(np.uint8)
    h, w = g.shape
    if h < 3 or w < 3:
        return 0.0

    def at(dy: int, dx: int) -> np.ndarray:  # the sampled pixels' neighbours, widened only once sampled
        return g[dy:h - 2 + dy:8, dx:w - 2 + dx:4].astype(np.int16)
    a = np.abs((at(0, 0) + at(0, 2) + at(2, 0) + at(2, 2)) - 2 * (at(0, 1) + at(1, 0) + at(1, 2) + at(2, 1))
               + 4 * at(1, 1))
    counts = np.cumsum(np.bincount(a.ravel()))
    return float(np.searchsorted(counts, counts[-1] / 2)) / (0.6745 * 6.0)


class PairChecks:
    """rectify's live checks of one stream of pairs, as the rectify service and the in-process
    pipeline (cores/pipeline.py) both run them: the rows (RowMonitor), each camera's picture
    against its last ones (FrozenInput: one camera hung while the other is live leaves the maps
    changing, so the segmenter's input-frozen cannot see it, and they are wrong wherever anything
    moved), against the other camera's (BlockedView: a finger on one lens), and the rectified pair
    over a wide coarse search (NearCheck: what stands nearer than the vision range).
    -> the FrameChecks each frame and its map carry."""

    def __init__(self, row_check_s: float = 1.0, max_row_offset_px: float = 0.5, frozen_after_s: float = 0.5,
                 near_check: bool = True):
        self.rows = RowMonitor(row_check_s, max_row_offset_px)
        self.frozen_after_s = frozen_after_s
        self._pictures = (FrozenInput(frozen_after_s), FrozenInput(frozen_after_s))
        self._view = BlockedView()
        self._near = NearCheck() if near_check else None

    def fresh(self) -> PairChecks:
        """The same checks for another stream, with nothing seen yet."""
        return PairChecks(self.rows.interval_s, self.rows.tolerance_px, self.frozen_after_s, self._near is not None)

    def near_field(self, left: np.ndarray, right: np.ndarray, view: camera.RectifiedModel | None = None
                   ) -> NearField | None:
        """The rectified pair's coarse wide disparity map (cores/calibration/near.py); None when off.
        view: the rectified camera (what part of each picture its camera saw)."""
        return self._near.field(left, right, view) if self._near is not None else None

    def clipped(self, left: np.ndarray, right: np.ndarray) -> ClippedTiles:
        """The rectified pair's tiles clipped white in both cameras (clipped_tiles)."""
        return clipped_tiles(left, right)

    def noise(self, left: np.ndarray, right: np.ndarray) -> float:
        """The raw pair's sensor noise, grey levels: the noisier camera's (picture_noise). Raw: the
        rectifying remap interpolates, which smooths noise by up to 3x (the EuRoC room at 20 % of its
        light: 7.4 grey levels raw, 2.2 rectified), so the rectified pair would not tell dusk."""
        return max(picture_noise(left), picture_noise(right))

    def pictures(self, left: np.ndarray, right: np.ndarray, t_s: float) -> tuple[list[Camera], list[Camera]]:
        """(the cameras whose raw picture has not changed for over frozen_after_s, those whose view is
        blocked) at t_s (s, a clock that never goes backwards)."""
        left_stuck = self._pictures[0].frozen(left, t_s)  # both look at every pair: each keeps its history
        right_stuck = self._pictures[1].frozen(right, t_s)
        return _cameras(left_stuck, right_stuck), self._view.blocked(left, right, t_s)

    def frame(self, left: np.ndarray, right: np.ndarray, t_s: float,
              rectify: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
              view: camera.RectifiedModel, rows: Callable[[np.ndarray, np.ndarray], None]
              ) -> tuple[np.ndarray, np.ndarray, FrameChecks]:
        """rectify's frame path, as the rectify service and the in-process pipeline both run it: the
        raw pair's checks (frozen, blocked: on the stream's clock t_s; the sensor noise: the remap's
        interpolation smooths it, by up to 3x), `rectify` (raw -> rectified pair of the camera
        `view`), the rectified pair handed to `rows` (the row check, which each runs off its frame
        path; not for a frozen camera's pair, which is of two moments), its near field and clipped
        tiles. -> (rectified left, right, the FrameChecks the pair and its map carry)."""
        stuck, blocked = self.pictures(left, right, t_s)
        noise = self.noise(left, right)
        left, right = rectify(left, right)
        if not stuck:
            rows(left, right)
        near = self.near_field(left, right, view)
        return left, right, self.message(stuck, blocked, near, self.clipped(left, right), noise)

    def message(self, frozen: list[Camera], blocked: list[Camera] | None = None,
                near: NearField | None = None, clipped: ClippedTiles | None = None,
                noise: float | None = None) -> FrameChecks:
        return FrameChecks(rows=self.rows.latest, frozen=frozen, blocked=blocked or [], near=near, clipped=clipped,
                           noise_grey=None if noise is None else round(min(noise, 255.0), 2))
