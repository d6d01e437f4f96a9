"""`mount estimate`: the camera mount (height above the floor, pitch, roll) from the data itself.

The segmenter runs with no mount configured (mount.height_m null: it fits the ground in every frame
without a prior); the frames whose ground estimate is `fitted` vote, and the median of each of
height, pitch and roll is the estimate (with the 10th-90th percentile spread, to judge it).
`merge_into_config` writes the three values into the `mount:` section of a YAML config (the one
section every service reads),
keeping the rest of the file (its comments too, where the section is written in block style).
"""
from __future__ import annotations

import copy
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.errors import BallbotError, ConfigError

MOUNT_FIELDS = ("height_m", "pitch_deg", "roll_deg")
SECTION = "mount"


@dataclass
class MountEstimate:
    frames: int  # frames run
    fitted: int  # frames whose ground was fitted
    height_m: float
    pitch_deg: float
    roll_deg: float
    spread: dict[str, tuple[float, float]] = field(default_factory=dict)  # field -> (p10, p90)
    sources: dict[str, int] = field(default_factory=dict)

    def settings_values(self) -> dict[str, float]:
        return {"height_m": round(self.height_m, 3), "pitch_deg": round(self.pitch_deg, 2),
                "roll_deg": round(self.roll_deg, 2)}


def estimate_from_grounds(grounds: list, frames: int | None = None) -> MountEstimate:
    """grounds: one GroundEstimate (or None) per frame -> the median of the fitted ones. Raises
    BallbotError naming what the frames gave when none was fitted."""
    frames = len(grounds) if frames is None else frames
    sources: dict[str, int] = {}
    for g in grounds:
        key = "no estimate" if g is None else g.source
        sources[key] = sources.get(key, 0) + 1
    fitted = [g for g in grounds if g is not None and g.source == "fitted"]
    if not fitted:
        got = ", ".join(f"{k} {v}" for k, v in sources.items()) or "nothing"
        raise BallbotError(f"mount estimate: none of the {frames} frame(s) gave a fitted ground plane (got: {got}); "
                           "the floor must fill a good part of the lower image, textured enough to match, within "
                           "the vision range (--max-range-m) and the disparity search range "
                           "(--disparity-num-disparities); check the calibration, or try more --frames")
    a = {k: np.array([getattr(g, k) for g in fitted], float) for k in ("height_m", "pitch_deg", "roll_deg")}
    return MountEstimate(frames, len(fitted), float(np.median(a["height_m"])), float(np.median(a["pitch_deg"])),
                         float(np.median(a["roll_deg"])),
                         {k: (float(np.percentile(v, 10)), float(np.percentile(v, 90))) for k, v in a.items()},
                         sources)


def format_estimate(e: MountEstimate) -> str:
    s = e.spread
    return "\n".join([
        f"mount (the config's `mount:` section) from {e.fitted} of {e.frames} frame(s) with a fitted ground "
        f"(ground sources: {', '.join(f'{k} {v}' for k, v in e.sources.items())})",
        f"  height_m:  {e.height_m:.3f}   (p10 {s['height_m'][0]:.3f}, p90 {s['height_m'][1]:.3f})",
        f"  pitch_deg: {e.pitch_deg:.2f}   (p10 {s['pitch_deg'][0]:.2f}, p90 {s['pitch_deg'][1]:.2f}; "
        "positive looking down)",
        f"  roll_deg:  {e.roll_deg:.2f}   (p10 {s['roll_deg'][0]:.2f}, p90 {s['roll_deg'][1]:.2f}; "
        "positive right side down)",
    ])


# --- writing the config --------------------------------------------------------------------------

def _yaml_value(v: float) -> str:
    return repr(float(v))


def _merge_text(text: str, values: dict[str, float]) -> str:
    """`values` set in the block-style top-level `mount:` section of `text` (lines edited in
    place, missing keys added under the header; no section: one appended). The caller checks the
    result parses to what it should."""
    lines = text.splitlines()
    header = next((i for i, ln in enumerate(lines)
                   if ln.split("#", 1)[0].rstrip() == f"{SECTION}:"), None)
    if header is None:
        if any(ln.startswith(f"{SECTION}:") for ln in lines):
            return ""  # the section in flow style: the caller rewrites the file (a second one would shadow it)
        block = [f"{SECTION}:"] + [f"  {k}: {_yaml_value(v)}" for k, v in values.items()]
        sep = [""] if lines and lines[-1].strip() else []
        return "\n".join(lines + sep + block) + "\n"
    end = header + 1
    indent = None
    while end < len(lines) and (not lines[end].strip() or lines[end][:1] in (" ", "\t", "#")):
        ln = lines[end]
        if indent is None and ln.strip() and not ln.lstrip().startswith("#"):
            indent = ln[: len(ln) - len(ln.lstrip())]
        end += 1
    indent = indent or "  "
    missing = dict(values)
    for i in range(header + 1, end):
        for k in list(missing):
            if lines[i].startswith(f"{indent}{k}:"):
                lines[i] = f"{indent}{k}: {_yaml_value(missing.pop(k))}"
    new = [f"{indent}{k}: {_yaml_value(v)}" for k, v in missing.items()]
    last = max([i for i in range(header + 1, end) if lines[i].strip() and not lines[i].lstrip().startswith("#")],
               default=header)  # new keys go after the section's last entry
    return "\n".join(lines[: last + 1] + new + lines[last + 1:]) + "\n"


def merge_into_config(path: str | Path, values: dict[str, float]) -> bool:
    """Set `values` (mount settings) in the `mount:` section of the YAML config at `path` (created if
    missing), keeping the rest of the file. The section, with the values, must be valid mount
    settings, else ConfigError and nothing is written. -> True when the file's text was
    edited in place (comments kept), False when it had to be rewritten from its parsed content (a
    flow-style or otherwise unusual section: comments lost)."""
    import yaml

    from common.settings import MountSettings

    path = Path(path)
    text = path.read_text() if path.exists() else ""
    try:
        doc = yaml.safe_load(text) if text.strip() else {}
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML: {e}") from None
    doc = doc or {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: expected a mapping of sections (mount:, segmenter:, disparity:, ...)")
    section = doc.get(SECTION) or {}
    if not isinstance(section, dict):
        raise ConfigError(f"{path}: section '{SECTION}' must be a mapping")
    expected = copy.deepcopy(doc)
    expected[SECTION] = {**section, **values}
    try:
        MountSettings.model_validate(expected[SECTION])
    except Exception as e:  # pydantic's ValidationError: name the values
        raise ConfigError(f"{path}: the {SECTION} section with {values} would not be valid: {e}") from None
    new_text, in_place = _merge_text(text, values), True
    try:
        ok = bool(new_text) and yaml.safe_load(new_text) == expected
    except yaml.YAMLError:
        ok = False
    if not ok:
        new_text, in_place = yaml.safe_dump(expected, sort_keys=False), False
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(new_text)
    os.replace(tmp, path)
    return in_place
