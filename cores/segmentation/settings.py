"""The segmenter's settings: one pydantic model, the only place its defaults live. The service, the
offline commands and the cores (seed.py, layers.py) all read this model directly.

Light on purpose (pydantic only), so that importing the settings does not import OpenCV or the
cores. The camera mount is not here: it is the `mount:` section every service reads
(common/settings.py MountSettings).
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from common.settings import ServiceSettings

METHODS = ("layers", "seed")
# The thesis's 3 m vision range for seed; the default method's own range.
DEFAULT_RANGE_M = {"seed": 3.0, "layers": 4.5}
# Unset, layers' range grows with the rig out to where it still measures this disparity (depth to
# about 6 % per px): 4.5 m stays for a small robot's rig, a car's wide baseline sees ~23 m.
FAR_DISPARITY_PX = 16.0

# The bounds of the settings that decide what is an obstacle (floor_margin_m, ground_noise_px,
# min_height_m, min_size_m, min_area_m2, min_cell_height_m) and that group and merge it (group_bin_px,
# merge_gap_m, merge_gap_depth_m) are where the lists still hold what a robot must avoid: each at an
# end, and the deciding ones all at once, miss at most 4 things more than the defaults on the 15 scenes
# and on the sway (45 frames of a swaying robot among people and furniture; a cut person's arm, a leg
# behind a box, people side by side 0.2 m apart: tests/test_eval.py runs them), and list the street. Past them the lists
# emptied or thinned with no degraded reason: min_height_m 5, min_area_m2 100 or min_cell_height_m 5
# left 14-15 of 15 street lists empty; min_cell_height_m 0.2 lost 66 of the scenes' 222 things (the
# walking person in 13 frames), min_area_m2 0.1 lost 13; min_height_m 0.3, floor_margin_m 0.3, or the
# margin at 0.2 with cells of 0.1 m, lost the thesis's 0.25 m toolbox (its standing points must fill a
# cell above the margin); under floor_margin_m 0.04 the floor's own noise stood and blank-faces' plain
# walls were in no list; ground_noise_px 5 lost 3 on the sway, 10 the toolbox. group_bin_px 0.001 lost
# half the scenes' things (0.1: a third), 4 lost 39 of the sway's 223; merge_gap_m 0.3 and
# merge_gap_depth_m 0.5 joined the sway's people to the furniture beside and behind them (6 and 14
# things in no list of their own; at 10 m every list held one obstacle); min_cell_height_m 0 joined
# all that stands on the sway into a few blobs (recall 0.06; from 0.01 the default's). The depth split
# likewise (layer_*): where it never split (valley ratio 0, sides of 100 m^2 or 100 m apart, no
# bridge, no range) the sway's people stood merged with the furniture before or behind them in 27
# sightings and people one behind another were one obstacle; from valley ratio 0.15, sides of 0.06 m^2,
# 0.5 m apart, bridges of 16 px and a 10 m range each alone misses at most 2 more (all at once 10 more
# on the sway: not bounded together).
# min_pixels is a floor for noise, in pixels, so it is judged where things are far and small: on the
# street (no labels) by the confirmed obstacles within 10 m, which are real (131 sightings in 40
# frames at the default 12). To 24 every one of them is kept (the lists 16.5 a frame against 18: specks
# of snow and twigs go) and the 15 scenes and the sway are unchanged; at 50 11 of them go unsaid, at
# 400 54 (5 a frame left), and at 100000 every list was empty and said nothing.


class SegmenterSettings(ServiceSettings):
    section = "segmenter"
    method: Literal["layers", "seed"] = Field(
        "layers", description="layers: depth-aware regions, floor plane, border objects kept; "
                              "seed: the thesis's Otsu pipeline")
    max_range_m: float | None = Field(None, gt=0, le=100, description="vision range; farther pixels are ignored "
                                      "(null: the method's own, seed 3 m as in the thesis, layers 4.5 m)")
    min_range_m: float = Field(1.0, ge=0, le=10, description="nearer pixels are ignored, m (the disparity "
                               "search's default reach; a search that cannot reach twice this is warned about)")
    median_ksize: Literal[1, 3, 5] | None = Field(
        None, description="median filter size, px of the grid the method works on (seed: at least 3); null: "
                          "seed 5, layers about 10 px of the full-resolution map (5 at downsample 1 or 2, 3 at 4)")
    floor_removal: bool = Field(True, description="remove the floor (false reproduces the thesis with seed)")
    floor_margin_m: float = Field(0.08, ge=0.04, le=0.15, description="points this close to the floor are floor")
    ground_noise_px: float = Field(0.5, ge=0, le=2, description="layers: a point must stand this much disparity "
                                   "above the floor's too (matching noise on a far road is metres of height)")
    robot_height_m: float = Field(2.0, gt=0, le=20, description="layers: points higher above the floor than this "
                                  "(canopy, ceilings, signs over the road) are not obstacles; above min_height_m "
                                  "and floor_margin_m")
    min_height_m: float = Field(0.2, ge=0, le=0.2, description="layers: an obstacle's top must be this far above "
                                "the floor (lower things: lane markings, shadows, mats)")
    # seed
    min_area_fraction: float = Field(0.03, ge=0, le=1, description="seed: area opening, fraction of the image")
    close_radius_px: int = Field(3, ge=0, le=50, description="seed: morphological closing radius, px")
    clear_border: bool = Field(True, description="seed: drop regions touching the image border (the thesis)")
    # layers
    fit_floor: bool = Field(True, description="layers: fit the floor plane to the disparity (mount as prior/fallback)")
    max_tilt_deg: float = Field(15.0, ge=0, le=90, description="layers: a fitted floor tilted more than this "
                                "(or 30 % of the height) from the configured mount's disagrees with it: logged once, "
                                "published as GroundEstimate.prior_agrees false; the data are used either way")
    ground_step_deg: float = Field(8.0, ge=0, le=90, description="layers: a floor candidate tilted this much "
                                   "from the last frames' ground gets no share of the bonus for agreeing with them")
    ground_smoothing: float = Field(0.3, gt=0, le=1, description="layers: weight of a new fit in the smoothed "
                                    "ground estimate")
    ground_reinit_frames: int = Field(8, ge=1, le=1000, description="layers: for this many frames in a row "
                                      "without an acceptable fit the last frames' ground stands in (tracked), then "
                                      "the configured mount or none")
    step_px: float = Field(0.6, ge=0, le=50, description="layers: neighbours differing by more than "
                           "step_px + step_rel * d belong to different objects")
    step_rel: float = Field(0.03, ge=0, le=1, description="layers: relative part of the similarity tolerance")
    min_size_m: float = Field(0.08, ge=0, le=0.3, description="layers: smallest obstacle extent, m")
    min_area_m2: float = Field(0.006, ge=0, le=0.02, description="layers: smallest frontal area, m^2")
    min_pixels: int = Field(12, ge=1, le=24, description="layers: smallest region, pixels at the working resolution "
                            "(at most 24: more drops real things far away, unsaid)")
    merge_gap_m: float = Field(0.12, ge=0, le=0.2, description="layers: regions whose 3D extents come this close "
                               "are one object")
    merge_gap_depth_m: float = Field(0.25, ge=0, le=0.3, description="layers: ... and this close along the view "
                                     "(depth): a fence or a wall along the road seen obliquely, whose texture-poor "
                                     "stretches the matcher leaves out, is one object; keep it below the gap that "
                                     "separates people one behind another")
    group_bin_px: float = Field(1.0, ge=0.5, le=2, description="layers: disparity bin of the column-disparity "
                                "grid that groups standing points into objects, px")
    min_cell_height_m: float = Field(0.05, ge=0.01, le=0.1, description="layers: a column-disparity cell is occupied "
                                     "when its standing points cover this much height")
    layer_valley_ratio: float = Field(0.25, ge=0.15, le=1, description="layers: a grouped object whose "
                                      "disparity histogram has a valley this much lower than its two peaks is two "
                                      "things one behind the other and is split there")
    layer_min_area_m2: float = Field(0.04, ge=0, le=0.06, description="layers: each side of such a split holds at "
                                     "least this much surface, m^2 (a hand held out is part of its person)")
    layer_gap_m: float = Field(0.3, ge=0, le=0.5, description="layers: ... and the two sides' depths (the "
                               "histogram's peaks) are at least this far apart, m (a torso before the legs is one "
                               "person)")
    layer_bridge_px: float = Field(24.0, ge=16, le=1000, description="layers: ... and the valley's pixels are at "
                                   "most this wide along an image row, px (the ramp block matching draws across an "
                                   "occlusion; a table top spans the whole table and keeps it whole)")
    layer_split_range_m: float = Field(20.0, ge=10, le=100, description="layers: things farther than this are not "
                                       "split by depth (a far street's facades, hedges and shelters would fall "
                                       "apart into panels)")
    min_confidence: int = Field(200, ge=0, le=255, description="pixels whose disparity confidence (when the matcher "
                                "gives one, e.g. dense) is below this are not used: dense fills every hole "
                                "smoothly, and filled pixels would join neighbouring objects into one")
    # free space
    freespace: bool = Field(True, description="publish the free-space grid (needs a ground estimate)")
    freespace_resolution_m: float = Field(0.1, gt=0, le=10, description="free-space cell size, m")
    near_field_m: float = Field(6.0, ge=0, le=100, description="layers: within this distance what the matcher "
                                "cannot measure is still an obstacle: a blank face (where the floor seen ends, "
                                "nothing measured stands there and the image above is unmeasured up past the "
                                "horizon: a plain wall, door or cabinet) and a drop (the floor falling away by "
                                "min_drop_m or more: a curb, stairs down); farther, a road fading under the sky and "
                                "a road's own camber look the same (0: neither)")
    min_drop_m: float = Field(0.15, ge=0.02, le=10, description="layers: floor this far below the ground (beyond "
                              "the stereo noise and the ground's doubt there) within near_field_m is a drop, listed "
                              "as an obstacle where the robot would roll off")
    fill_to_floor: bool = Field(True, description="layers: extend objects standing on the floor down to it")
    downsample: Literal[1, 2, 4] = Field(2, description="layers: work on every n-th pixel")
    edge_refine: bool = Field(False, description="layers: snap boxes to intensity edges "
                                                 "(needs the image; off in the service)")
    # tracking
    # At most 0.9 m: farther, one thing's id passes to another (the street's tracks jumping more than 2 m
    # between sightings: 3.0 % at 0.9, 5.6 % at 1.0, 24-26 % at 3-100 m), and at 100 m the confirmed
    # tracks' footprints, carried to wherever their ids went, joined the street's things into lumps (13
    # obstacles a frame for 18) with parked cars moving at 6 m/s, nothing said
    track_gate_m: float = Field(0.6, gt=0, le=0.9, description="max distance between a track and its next "
                                "detection, m (at most 0.9: farther, ids pass between things)")
    # At most 10 s, as the other times: a track is kept while unseen for this long, so at a day the tracks of
    # every thing ever passed stayed, each frame's association growing with them (the street: 37 new
    # tracks a second), and a track's gate grows with the time it is unseen (track_max_speed_mps)
    track_timeout_s: float = Field(1.0, gt=0, le=10, description="a track unseen this long is dropped (at most 10 s)")
    track_confirm_m: int = Field(3, ge=1, le=100, description="a track is confirmed when seen in M ...")
    track_confirm_n: int = Field(5, ge=1, le=100, description="... of the last N frames")
    track_max_speed_mps: float = Field(2.5, gt=0, le=100, description="fastest obstacle over the ground (gates "
                                       "association across dropouts)")
    track_merge_fragments: bool = Field(True, description="detections lying inside where a confirmed track "
                                        "stood in the last frame are one obstacle (a fence whose texture-poor "
                                        "stretches the matcher leaves out stays whole)")
    # At most 10 s, as rectify's frozen_after_s: how long a list may follow a stopped or repeating input
    # without saying so (at an hour, a hung camera's fresh-stamped maps gave an hour of lists that looked
    # fresh; a robot at 1 m/s is 10 m on by then)
    odometry_timeout_s: float = Field(0.5, gt=0, le=10, description="odometry older than this is not used")
    stale_after_s: float = Field(0.5, gt=0, le=10, description="input older than this (or none for this long) is "
                                 "stale; maps unchanged for this long are input-frozen")

    @model_validator(mode="after")
    def _room_to_stand(self) -> SegmenterSettings:
        # points stand from floor_margin_m to robot_height_m above the floor, and an obstacle's top is at
        # least min_height_m up: a robot lower than either has nothing that could be an obstacle (robot
        # height 0.001 m: every street list empty, unflagged)
        low = max(self.min_height_m, self.floor_margin_m)
        if self.robot_height_m <= low:
            raise ValueError(f"robot_height_m ({self.robot_height_m:g} m) must be above min_height_m "
                             f"({self.min_height_m:g} m) and floor_margin_m ({self.floor_margin_m:g} m): "
                             f"nothing between the floor and the robot's top could be an obstacle")
        return self

    @property
    def range_m(self) -> float:
        """The configured range, or the method's own (without a camera to fit it to)."""
        return self.max_range_m if self.max_range_m is not None else DEFAULT_RANGE_M[self.method]

    @property
    def median_px(self) -> int:
        """The median filter's size (median_ksize, or the method's own). layers at downsample 4: 3, as
        a 5 px filter there spans 20 px of the map and wiped out the side block matching measures of a
        plain face (low-faces, bm: the cabinet in no list, unflagged, in every frame)."""
        if self.median_ksize is not None:
            return self.median_ksize
        return 3 if self.method == "layers" and self.downsample >= 4 else 5

    def range_for(self, model) -> float:
        """The vision range for this camera (a RectifiedModel): the configured one, or the method's
        own, for layers at least as far as the rig measures FAR_DISPARITY_PX."""
        if self.max_range_m is not None or self.method != "layers":
            return self.range_m
        return max(self.range_m, model.focal_px * abs(model.baseline_m) / FAR_DISPARITY_PX)

