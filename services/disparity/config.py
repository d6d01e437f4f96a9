"""The matching settings: one pydantic model (MatcherConfig) that the cores consume directly and the
disparity service's settings extend (main.DisparitySettings). Defaults live here and nowhere else.
No OpenCV import, so reading settings (`--help`, config files) stays light.
"""
from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from ...common.settings import ServiceSettings

SCALE = 16.0

# Per-method default matching window (block_size = 0 picks these): the thesis's 15 px SAD window for
# bm; 5 px for sgbm, whose smoothness terms do the aggregation (better than OpenCV's 3 on Middlebury).
DEFAULT_BLOCK = {"bm": 15, "sgbm": 5}


class MatcherConfig(ServiceSettings):
    """Matching settings (the `disparity` section of a config file). Disparities and windows in px,
    ranges in metres. Defaults live here and nowhere else."""

    section = "disparity"

    method: Literal["bm", "sgbm"] = Field("bm", description="bm: block matching, SAD (the thesis); sgbm: semi-global")
    num_disparities: Annotated[int, Field(ge=16, le=512, multiple_of=16)] = Field(
        64, description="disparity search range, px (a multiple of 16)")
    min_disparity: int = Field(0, ge=-256, le=256, description="smallest disparity searched, px")
    block_size: int = Field(0, ge=0, le=255, description="matching window, odd, px (0: bm 15, sgbm 5)")
    uniqueness_ratio: int = Field(10, ge=0, le=100, description="reject matches not this percent better than the next")
    texture_threshold: int = Field(10, ge=0, description="bm: reject windows with less texture")
    speckle_window: int = Field(100, ge=0, description="max size of speckles removed, px (0: off)")
    speckle_range: int = Field(2, ge=0, description="max disparity variation within a speckle, px")
    prefilter: Literal["xsobel", "normalized"] = Field("xsobel", description="bm pre-filter")
    prefilter_size: int = Field(9, ge=5, le=255, description="bm normalized pre-filter window, odd, px")
    prefilter_cap: int = Field(31, ge=1, le=63, description="pre-filter clipping")
    p1: int = Field(0, ge=0, description="sgbm smoothness penalty for +-1 px changes (0: 8*block^2)")
    p2: int = Field(0, ge=0, description="sgbm penalty for larger changes (0: 32*block^2)")
    disp12_max_diff: int = Field(1, ge=-1, description="sgbm's internal left-right check, px (-1: off)")
    sgbm_mode: Literal["sgbm", "hh", "3way", "hh4"] = Field("sgbm", description="sgbm variant (hh: 8 paths)")
    lr_check: bool = Field(False, description="left-right consistency check (doubles matching time)")
    lr_max_diff: float = Field(1.0, ge=0, description="max left/right disagreement, px")
    subpixel: bool = Field(True, description="1/16 px output; false rounds to whole px")
    max_range_m: float = Field(0.0, ge=0, description="vision range gate, m (disparity >= f*B/range; 0: off)")
    threads: int = Field(0, ge=0, le=64, description="OpenCV threads for matching (0: one per core)")

    @model_validator(mode="after")
    def _combinations(self) -> "MatcherConfig":
        b = self.block
        if b % 2 == 0:
            raise ValueError(f"block_size: must be odd, got {self.block_size}")
        if self.method == "bm" and not 5 <= b <= 255:
            raise ValueError(f"block_size: block matching needs 5..255, got {b}")
        if self.method == "bm" and self.prefilter_size % 2 == 0:
            raise ValueError(f"prefilter_size: must be odd, got {self.prefilter_size}")
        if self.p2 and self.p1 and self.p2 <= self.p1:
            raise ValueError(f"p2 ({self.p2}) must be greater than p1 ({self.p1})")
        return self

    @property
    def block(self) -> int:
        return self.block_size or DEFAULT_BLOCK[self.method]

    @property
    def invalid_value(self) -> int:
        return (self.min_disparity - 1) * int(SCALE)


def gate_for_range(max_range_m: float | None, focal_px: float, baseline_m: float) -> float:
    """Smallest disparity (px) inside the vision range: d = f * B / Z. None or <= 0: no gate."""
    if not max_range_m or max_range_m <= 0:
        return 0.0
    return focal_px * baseline_m / max_range_m
