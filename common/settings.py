"""Per-service settings: one pydantic model each, with defaults, ranges and descriptions.

Where a value comes from, lowest to highest priority: the model's default, the service's section
of `--config FILE` (YAML: `capture: {rate_hz: 15}`), the environment variable
BALLBOT_<SERVICE>_<FIELD> (e.g. BALLBOT_CAPTURE_RATE_HZ=15), and the command-line flag
(`--rate-hz 15`). Every flag is generated from the model, so `run SERVICE --help` documents them.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from .errors import ConfigError

S = TypeVar("S", bound="ServiceSettings")


class ServiceSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)
    section: ClassVar[str] = ""

    @classmethod
    def env_var(cls, field: str) -> str:
        return f"BALLBOT_{cls.section.upper()}_{field.upper()}"


def add_settings_arguments(p: argparse.ArgumentParser, cls: type[ServiceSettings]) -> None:
    g = p.add_argument_group(f"{cls.section} settings (also --config FILE section '{cls.section}', or env)")
    for name, f in cls.model_fields.items():
        default = f.default if f.default_factory is None else f.default_factory()
        g.add_argument("--" + name.replace("_", "-"), dest=f"set_{name}", default=argparse.SUPPRESS,
                       metavar="V", help=f"{f.description or ''} (default: {default}) [{cls.env_var(name)}]")


def _parse_scalar(text: str) -> Any:
    """'15' -> 15, 'true' -> True, '[1, 2]' -> [1, 2]; anything else stays a string."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def load_settings(cls: type[S], config_file: str | None = None, args: argparse.Namespace | None = None,
                  **overrides: Any) -> S:
    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    if config_file:
        path = Path(config_file)
        try:
            doc = yaml.safe_load(path.read_text()) or {}
        except (OSError, yaml.YAMLError) as e:
            raise ConfigError(f"{config_file}: cannot read config: {e}") from None
        if not isinstance(doc, dict):
            raise ConfigError(f"{config_file}: expected a mapping of service sections")
        section = doc.get(cls.section) or {}
        if not isinstance(section, dict):
            raise ConfigError(f"{config_file}: section '{cls.section}' must be a mapping")
        for k, v in section.items():
            values[k] = v
            sources[k] = f"{config_file}: {cls.section}.{k}"
    for name in cls.model_fields:
        env = os.environ.get(cls.env_var(name))
        if env:  # an empty variable (common in compose files) means "not set"
            values[name] = _parse_scalar(env)
            sources[name] = f"environment variable {cls.env_var(name)}"
    if args is not None:
        for name in cls.model_fields:
            if hasattr(args, f"set_{name}"):
                values[name] = _parse_scalar(getattr(args, f"set_{name}"))
                sources[name] = "--" + name.replace("_", "-")
    for k, v in overrides.items():
        values[k] = v
        sources[k] = "argument"
    try:
        return cls.model_validate(values)
    except ValidationError as e:
        lines = []
        for err in e.errors():
            field = str(err["loc"][0]) if err["loc"] else "?"
            lines.append(f"{sources.get(field, cls.section + '.' + field)}: {err['msg']}"
                         + (f" (got {err['input']!r})" if "input" in err and not isinstance(err["input"], dict) else ""))
        raise ConfigError(f"invalid {cls.section} settings:\n  " + "\n  ".join(lines)) from None
