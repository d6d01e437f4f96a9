"""Per-service settings: one pydantic model each, with defaults, ranges and descriptions. The
model is the one source of truth: the service's core consumes it directly, and every flag, its
help text and its environment variable are generated from it.

Where a value comes from, lowest to highest priority: the model's default, the service's section
of `--config FILE` (YAML: `capture: {rate_hz: 15}`), the environment variable
BALLBOT_<SERVICE>_<FIELD> (e.g. BALLBOT_CAPTURE_RATE_HZ=15), and the command-line flag
(`--rate-hz 15`).

Text from the environment or a flag is converted by the field's own type with pydantic's
coercion (`--camera-left 010` is device 10, `--lr-check yes` is True), never guessed as YAML
(where 010 is octal 8 and `no` is False). Fields that take a list or a mapping take JSON
(`--foo '[1, 2]'`); a field that may be unset takes `null` (or `none`). A bool flag alone means
true (`--lr-check`).

This module stays light (pydantic and PyYAML only): `run router` and `healthcheck` import it.
"""
from __future__ import annotations

import argparse
import os
import re
import types
import typing
from typing import Any, ClassVar, TypeVar

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from common.errors import ConfigError

S = TypeVar("S", bound="ServiceSettings")

NULL_WORDS = ("null", "none")


class ServiceSettings(BaseModel):
    """Base of every service's settings. `section` names the service: its `--config` section and
    the middle of its environment variables. An offline command that runs a service's core takes
    the model of that core's settings only (e.g. the matcher's, without the worker pool's)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)
    section: ClassVar[str] = ""

    @classmethod
    def env_var(cls, field: str) -> str:
        return f"BALLBOT_{cls.section.upper()}_{field.upper()}"

    @classmethod
    def flag(cls, field: str, prefix: str = "") -> str:
        return "--" + (prefix + field).replace("_", "-")


class MountSettings(ServiceSettings):
    """The camera on the robot: where the rectified left camera sits on the robot base (REP 103, see
    cores/segmentation/mount.py for the frames and angles). One top-level section, `mount:`, read by
    every service (env BALLBOT_MOUNT_*, flags --mount-*): a prior, never a cage: the segmenter fits
    the ground every frame and trusts the data where they disagree (and says so); yaw and the
    offsets, which the ground cannot tell, are taken as configured. The full mount used for a list
    travels with it (ObstacleList.mount), so the ROS 2 bridge, the recorder, the pictures and
    Foxglove place things where the segmenter did."""

    section = "mount"
    height_m: float | None = Field(None, gt=0, le=20, description="camera height above the floor, m (null: "
                                   "unknown: the ground is estimated from the disparity every frame; "
                                   "`ballbot-vision mount estimate` measures it)")
    pitch_deg: float = Field(0.0, ge=-90, le=90, description="camera pitch, positive looking down")
    roll_deg: float = Field(0.0, ge=-90, le=90, description="camera roll, positive right side down")
    yaw_deg: float = Field(0.0, ge=-180, le=180, description="camera yaw on the robot, positive to the left")
    x_m: float = Field(0.0, ge=-10, le=10, description="camera position ahead of the base origin, m")
    y_m: float = Field(0.0, ge=-10, le=10, description="camera position left of the base origin, m")
    pivot_height_m: float | None = Field(None, ge=0, le=20, description="a balancing robot leans about this "
                                         "point on the base z axis (a ballbot's ball centre), m: the lean the "
                                         "ground shows carries the camera over the floor, by (height - pivot) "
                                         "sin(lean), the lean measured from the robot's upright: the ground's "
                                         "average over the last seconds, starting at the height, pitch and roll "
                                         "above; null: the camera turns on the spot")


# A setting that moved: (section, old field) -> where it is now. Named in the error, not ignored.
MOVED = {(section, f"mount_{f}"): f"mount.{f}" for section in ("segmenter", "ros2")
         for f in ("height_m", "pitch_deg", "roll_deg", "yaw_deg", "x_m", "y_m")}


def _allows_none(annotation: Any) -> bool:
    if annotation is None or annotation is type(None):
        return True
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _allows_none(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return any(_allows_none(a) for a in typing.get_args(annotation))
    return annotation is Any


def _is_bool(annotation: Any) -> bool:
    if typing.get_origin(annotation) is typing.Annotated:
        annotation = typing.get_args(annotation)[0]
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return len(args) == 1 and _is_bool(args[0])
    return annotation is bool


_ADAPTERS: dict[tuple[type, str], TypeAdapter] = {}


def _adapter(cls: type[ServiceSettings], name: str) -> TypeAdapter:
    key = (cls, name)
    if key not in _ADAPTERS:
        f = cls.model_fields[name]
        if f.annotation is None:  # pydantic fills it in for every declared field
            raise TypeError(f"{cls.__name__}.{name}: a settings field without a type")
        # a type built at run time, which a static checker cannot follow
        field_type: Any = typing.Annotated[f.annotation, *f.metadata] if f.metadata else f.annotation
        _ADAPTERS[key] = TypeAdapter(field_type)
    return _ADAPTERS[key]


def parse_text(cls: type[ServiceSettings], name: str, text: str) -> Any:
    """One setting given as text (a flag or an environment variable) -> a value of the field's
    type, by pydantic's string coercion; JSON for lists, mappings and numeric choices; `null` or
    `none` for a field that may be unset. Raises ValueError with pydantic's message."""
    f = cls.model_fields[name]
    if text.strip().lower() in NULL_WORDS and _allows_none(f.annotation):
        return None
    adapter = _adapter(cls, name)
    try:
        return adapter.validate_strings(text)
    except ValidationError as first:
        try:  # [1, 2], {"a": 1}, a Literal[1, 3, 5] given as "3"
            return adapter.validate_json(text)
        except ValidationError:
            raise ValueError("; ".join(e["msg"] for e in first.errors())) from None


def add_settings_arguments(p: argparse.ArgumentParser, cls: type[ServiceSettings], *, prefix: str = "",
                           title: str | None = None, exclude: tuple[str, ...] = ()) -> None:
    """One flag per field of `cls` (`--rate-hz`), documented from the model. In a command that runs
    several stages, `prefix` marks the settings of the stages that are not the command's own
    (`obstacles --disparity-method sgbm` beside the segmenter's `--method`); load them with the same
    prefix. Values land in per-section attributes, so two models never share a flag's value. `exclude`:
    fields the command sets itself (no flag)."""
    g = p.add_argument_group(title or f"{cls.section} settings (also the '{cls.section}' section of --config "
                                      f"FILE, or the environment variable shown)")
    for name, f in cls.model_fields.items():
        if name in exclude:
            continue
        default = f.get_default(call_default_factory=True)
        kw: dict[str, Any] = {"nargs": "?", "const": "true", "metavar": "BOOL"} if _is_bool(f.annotation) \
            else {"metavar": "V"}
        g.add_argument(cls.flag(name, prefix), dest=_dest(cls, name), default=argparse.SUPPRESS,
                       # argparse %-formats help texts: a "50 %" in a description is text, not a format
                       help=f"{f.description or ''} (default: {_show(default)}) [{cls.env_var(name)}]"
                       .replace("%", "%%"),
                       **kw)


def _dest(cls: type[ServiceSettings], name: str) -> str:
    return f"set_{cls.section}__{name}"


def _show(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return str(v).lower()
    return str(v)


def flags_given(cls: type[ServiceSettings], args: argparse.Namespace | None) -> dict[str, str]:
    """{field: text} of the flags of `cls` given on the command line."""
    if args is None:
        return {}
    out = {}
    for name in cls.model_fields:
        if hasattr(args, _dest(cls, name)):
            out[name] = getattr(args, _dest(cls, name))
    return out


# Every top-level section a `--config` file may have: each service's (its settings' `section`) and the
# camera mount every service reads (DESIGN: one top-level `mount:` section). A section not in this
# list is a typo (`captur:`) that would otherwise be ignored in silence; tests/test_settings.py checks
# that every settings model's section is here.
KNOWN_SECTIONS = ("capture", "rectify", "disparity", "segmenter", "mount", "record", "viewer", "foxglove", "ros2")


def check_sections(config_file: str, doc: dict) -> None:
    """Raise a ConfigError naming each unknown top-level section, the closest known one and the known ones."""
    import difflib

    unknown = [str(k) for k in doc if str(k) not in KNOWN_SECTIONS]
    if not unknown:
        return
    parts = []
    for k in unknown:
        close = difflib.get_close_matches(k, KNOWN_SECTIONS, n=1)
        parts.append(f"'{k}'" + (f" (did you mean '{close[0]}'?)" if close else ""))
    raise ConfigError(f"{config_file}: unknown section{'s' if len(parts) > 1 else ''} {', '.join(parts)}; "
                      f"the known sections are {', '.join(KNOWN_SECTIONS)}")


def read_config_section(config_file: str, section: str) -> dict[str, Any]:
    """The mapping under `section` in a `--config` YAML file ({} when absent). A file with a section
    no service reads (a misspelled `captur:`) is refused, naming the known ones."""
    from common.errors import FileError
    from common.files import read_yaml

    try:  # missing, empty, binary or hostile files in the wording every command uses
        doc = read_yaml(config_file, "config")
    except FileError as e:
        if "the file is empty" not in str(e):
            raise ConfigError(str(e)) from None
        doc = None
    doc = doc or {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{config_file}: expected a mapping of service sections (capture:, rectify:, ...)")
    check_sections(config_file, doc)
    sec = doc.get(section) or {}
    if not isinstance(sec, dict):
        raise ConfigError(f"{config_file}: section '{section}' must be a mapping")
    return sec


def load_settings(cls: type[S], config_file: str | None = None, args: argparse.Namespace | None = None,
                  prefix: str = "", **overrides: Any) -> S:
    """The settings of one service from defaults, config file, environment and flags (in rising
    priority), validated; a ConfigError names each bad value and where it came from."""
    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    problems: list[str] = []
    if config_file:
        for k, v in read_config_section(config_file, cls.section).items():
            values[k] = v
            sources[k] = f"{config_file}: {cls.section}.{k}"
    texts: dict[str, tuple[str, str]] = {}
    for k in list(values):
        if (cls.section, k) in MOVED:
            new = MOVED[cls.section, k]
            problems.append(f"{sources[k]}: moved to {new} (the `{new.split('.')[0]}:` "
                            f"section, read by every service)")
            values.pop(k)
    for (section, old), new in MOVED.items():
        if section == cls.section and os.environ.get(f"BALLBOT_{section.upper()}_{old.upper()}"):
            problems.append(f"environment variable BALLBOT_{section.upper()}_{old.upper()}: moved to "
                            f"BALLBOT_{new.replace('.', '_').upper()}")
    for name in cls.model_fields:
        env = os.environ.get(cls.env_var(name))
        if env:  # an empty variable (common in compose files) means "not set"
            texts[name] = (env, f"environment variable {cls.env_var(name)}")
    for name, text in flags_given(cls, args).items():
        texts[name] = (text, cls.flag(name, prefix))
    for name, (text, where) in texts.items():
        sources[name] = where
        try:
            values[name] = parse_text(cls, name, text)
        except ValueError as e:
            problems.append(f"{where}: {e} (got {text!r})")
            values.pop(name, None)
    for k, v in overrides.items():
        values[k] = v
        sources[k] = "argument"
    if not problems:
        try:
            return cls.model_validate(values)
        except ValidationError as e:
            for err in e.errors():
                field = str(err["loc"][0]) if err["loc"] else ""
                where = sources.get(field, f"{cls.section}.{field}" if field else cls.section)
                got = f" (got {err['input']!r})" if "input" in err and not isinstance(err["input"], dict) else ""
                msg = err["msg"].removeprefix("Value error, ")
                if not field:  # a rule across fields: say where each one it names was set
                    given = [sources[k] for k in cls.model_fields if k in sources and re.search(rf"\b{k}\b", msg)]
                    got = f" (set by {', '.join(given)})" if given else ""
                problems.append(f"{where}: {msg}{got}")
    raise ConfigError(f"invalid {cls.section} settings:\n  " + "\n  ".join(problems))
