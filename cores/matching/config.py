"""The matching settings: one pydantic model (MatcherConfig) that the cores consume directly and the
disparity service's settings extend (main.DisparitySettings). Defaults live here and nowhere else.
No OpenCV import, so reading settings (`--help`, config files) stays light.
"""
from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from common.errors import BallbotError
from common.messages import MAX_MIN_DISPARITY, MAX_NUM_DISPARITIES
from common.settings import ServiceSettings

SCALE = 16.0

# Per-method default matching window (block_size = 0 picks these): the thesis's 15 px SAD window for
# bm; 5 px for sgbm, whose smoothness terms do the aggregation (better than OpenCV's 3 on Middlebury);
# 3 px for dense, whose edge-aware fill does the rest (3 keeps object edges sharpest).
DEFAULT_BLOCK = {"bm": 15, "sgbm": 5, "dense": 3}
# ... and the smallest window each may be given: below it the lists missed what stands and did not say
# so (sway scene, 45 frames of a swaying robot among people and furniture: bm at 5 px freed the floor
# under the chair and the table in 4 frames and missed 4 more things, low-faces' crate and cabinet in
# every frame of the 15 scenes; sgbm at 1 px 7 more misses; dense at 1 px 2 more), where from these
# windows on the misses are the defaults' (bm 7 and 9; sgbm 3: one more on the sway). OpenCV takes bm from 5.
MIN_BLOCK = {"bm": 7, "sgbm": 3, "dense": 3}
# Per-method semi-global variant (sgbm_mode auto): dense uses 3-way, faster than 5 paths and as good
# on the Middlebury pairs (`bench accuracy`).
DEFAULT_SGBM_MODE = {"bm": "sgbm", "sgbm": "sgbm", "dense": "3way"}
# Search-range saturation: valid pixels within TOP_BAND_PX of the largest disparity searched. More
# than SATURATION_WARN of them means nearer things exist than the range covers (measured: <= 0.3 %
# with a range covering the scene, 2-20 % with one too small).
TOP_BAND_PX = 2.0
SATURATION_WARN = 0.01
AUTO_WIDTH_SHARE = 4  # num_disparities auto searches at most a quarter of the image width


def _auto_needs_camera() -> BallbotError:
    return BallbotError("num_disparities auto needs the camera's focal length and baseline: give a "
                        "calibration (or a rectified camera model), or set num_disparities in px")


class MatcherConfig(ServiceSettings):
    """Matching settings (the `disparity` section of a config file). Disparities and windows in px,
    ranges in metres. Defaults live here and nowhere else."""

    section = "disparity"

    method: Literal["bm", "sgbm", "dense"] = Field(
        "bm", description="bm: block matching, SAD (the thesis, fast); sgbm: semi-global; dense: semi-global "
        "+ edge-aware fill, a disparity and a confidence for every pixel (for offboard workers)")
    num_disparities: Annotated[int, Field(ge=16, le=MAX_NUM_DISPARITIES, multiple_of=16)] | Literal["auto"] = Field(
        "auto", description="disparity search range, px (a multiple of 16), or auto: from the calibration, "
        "covering everything farther than min_range_m (at most a quarter of the image width)")
    min_range_m: float = Field(1.0, gt=0, description="num_disparities auto: about the nearest distance the "
                               "search reaches, m (f*B/min_range_m px, to the nearest 16: 64 px on the thesis's "
                               "rig, as it searched; nearer costs matching time and a wider unmatched band at the "
                               "left border)")
    min_disparity: int = Field(0, ge=-MAX_MIN_DISPARITY, le=MAX_MIN_DISPARITY,
                               description="smallest disparity searched, px")
    block_size: int = Field(0, ge=0, le=255, description="matching window, odd, px (0: bm 15, sgbm 5, dense 3; "
                            "at least bm 7, sgbm and dense 3)")
    # 30 at most: higher, the matcher keeps so little of what stands that things leave the lists with no
    # reason said (the 15 scenes against the 3 silent misses at 10: dense 4 at 50 and 9 at 75; sgbm 8 at 99
    # and the free space under the chair; bm and sgbm held to 75). And OpenCV's 3-way SGBM divides by
    # 100 - uniqueness_ratio: 100 killed it (SIGFPE)
    uniqueness_ratio: int = Field(10, ge=0, le=30, description="reject matches not this percent better than the "
                                  "next (at most 30: more rejects true matches of what stands)")
    texture_threshold: int = Field(10, ge=0, description="bm: reject windows with less texture")
    speckle_window: int = Field(100, ge=0, description="max size of speckles removed, px (0: off)")
    speckle_range: int = Field(2, ge=0, description="max disparity variation within a speckle, px")
    prefilter: Literal["xsobel", "normalized"] = Field("xsobel", description="bm pre-filter")
    prefilter_size: int = Field(9, ge=5, le=255, description="bm normalized pre-filter window, odd, px")
    prefilter_cap: int = Field(31, ge=1, le=63, description="pre-filter clipping")
    p1: int = Field(0, ge=0, description="sgbm/dense smoothness penalty for +-1 px changes (0: 8*block^2)")
    p2: int = Field(0, ge=0, description="sgbm/dense penalty for larger changes (0: 32*block^2)")
    disp12_max_diff: int = Field(1, ge=-1, description="sgbm/dense (and bm with match_band) internal left-right "
                                 "check, px (-1: off)")
    sgbm_mode: Literal["auto", "sgbm", "hh", "3way", "hh4"] = Field(
        "auto", description="semi-global variant (auto: sgbm 5 paths, dense 3way; hh: full 8 paths)")
    lr_check: bool = Field(False, description="bm/sgbm: left-right check on a second, mirrored match (doubles "
                           "matching time, and the search's width more: the mirrored pair is padded so that the "
                           "right edge is checked too)")
    # The two sub-pixel estimates of one match disagree by their own noise: at 0 px the check dropped two
    # thirds of the map and low-faces' boxes with them, lists unflagged (the 15 scenes: 20 silent misses;
    # 1/16 px: 1); from 0.5 px (bm and sgbm) the same lists as at 1 px
    lr_max_diff: float = Field(1.0, ge=0.5, le=64.0, description="max left/right disagreement, px (at least 0.5: "
                               "closer than that, sub-pixel noise fails true matches)")
    match_band: bool = Field(False, description="bm/sgbm: match the left band (x < min_disparity + num_disparities) "
                             "OpenCV leaves unmatched too, on the pair padded on the left, as dense always does, "
                             "wherever a pixel's partner is in the right image (more matching time: the band's "
                             "width over the rest's)")
    fill_lambda: float = Field(8000.0, gt=0, description="dense: smoothness of the edge-aware fill (fast global "
                               "smoother lambda)")
    fill_sigma_color: float = Field(1.5, gt=0, description="dense: grey-level difference (0..255) at which the "
                                    "fill stops spreading across an edge")
    subpixel: bool = Field(True, description="1/16 px output; false rounds to whole px")
    max_range_m: float = Field(0.0, ge=0, description="vision range gate, m (disparity >= f*B/range; 0: off)")
    threads: int = Field(0, ge=0, le=64, description="OpenCV threads for matching (0: one per core)")

    @model_validator(mode="after")
    def _combinations(self) -> MatcherConfig:
        b = self.block
        if b % 2 == 0:
            raise ValueError(f"block_size: must be odd, got {self.block_size}")
        if not MIN_BLOCK[self.method] <= b <= 255:
            raise ValueError(f"block_size: {self.method} needs {MIN_BLOCK[self.method]}..255 (smaller windows miss "
                             f"what stands and the lists do not say so), got {b}")
        if self.method == "bm" and self.prefilter_size % 2 == 0:
            raise ValueError(f"prefilter_size: must be odd, got {self.prefilter_size}")
        if self.p2 and self.p1 and self.p2 <= self.p1:
            raise ValueError(f"p2 ({self.p2}) must be greater than p1 ({self.p1})")
        return self

    @property
    def block(self) -> int:
        return self.block_size or DEFAULT_BLOCK[self.method]

    @property
    def mode(self) -> str:
        """The semi-global variant in use (sgbm_mode, or the method's default for auto)."""
        return DEFAULT_SGBM_MODE[self.method] if self.sgbm_mode == "auto" else self.sgbm_mode

    @property
    def invalid_value(self) -> int:
        return (self.min_disparity - 1) * int(SCALE)

    @property
    def max_disparity(self) -> int:
        """Largest disparity searched, px (needs a resolved num_disparities)."""
        return self.min_disparity + self.fixed_num_disparities - 1

    def check_width(self, width: int) -> None:
        """An image must be wider than the search range plus the block: narrower, OpenCV's SGBM stops
        with an assertion and BM and dense return a map of nothing but guesses. Raises a BallbotError
        in one line saying what to change."""
        need = self.max_disparity + self.block
        if width <= need:
            raise BallbotError(
                f"the image is {width} px wide, too narrow for the search range: {self.method} searches disparities "
                f"{self.min_disparity}..{self.max_disparity} px with a {self.block} px block, so the image must be "
                f"wider than {need} px (set --num-disparities to at most "
                f"{max(16, (width - self.block - self.min_disparity) // 16 * 16)}, or auto with a calibration)")

    @property
    def fixed_num_disparities(self) -> int:
        if self.num_disparities == "auto":
            raise _auto_needs_camera()
        return self.num_disparities

    def resolved(self, focal_px: float | None, baseline_m: float | None, width: int | None = None) -> MatcherConfig:
        """These settings with num_disparities auto turned into px for this camera (self if fixed)."""
        if self.num_disparities != "auto":
            return self
        if not focal_px or not baseline_m:
            raise _auto_needs_camera()
        # capped so that the image stays wider than the search range plus the block (check_width)
        room = None if width is None else width - self.block - self.min_disparity + 1
        n = auto_num_disparities(focal_px, baseline_m, self.min_range_m, self.min_disparity, room)
        return self.model_copy(update={"num_disparities": n})


def auto_num_disparities(focal_px: float, baseline_m: float, min_range_m: float, min_disparity: int = 0,
                         width: int | None = None) -> int:
    """The search range (px): the multiple of 16 nearest to what reaches d = f * B / min_range_m from
    min_disparity (so it reaches about min_range_m, within 8 px: the thesis's 64 px on its rig for
    1 m, where rounding up would widen the unmatched band at the left border for 5 cm), capped at
    512 and, with `width`, at a quarter of the image width: block matching measures nothing in the
    left num_disparities columns, so a wide-baseline rig (a car's) would trade a third of its view
    for the last metre in front of it."""
    d_near = focal_px * abs(baseline_m) / min_range_m
    n = max(16, round((d_near - min_disparity + 1) / 16) * 16)
    cap = (MAX_NUM_DISPARITIES if width is None
           else max(16, min(MAX_NUM_DISPARITIES, width // AUTO_WIDTH_SHARE // 16 * 16)))
    return min(n, cap)


def gate_for_range(max_range_m: float | None, focal_px: float, baseline_m: float) -> float:
    """Smallest disparity (px) inside the vision range: d = f * |B| / Z. None or <= 0: no gate (0)."""
    if not max_range_m or max_range_m <= 0:
        return 0.0
    return focal_px * abs(baseline_m) / max_range_m
