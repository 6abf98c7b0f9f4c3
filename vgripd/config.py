"""The TOML configuration, validated by pydantic.

Every model forbids unknown keys, so a typo is an error naming its field path
(``calibration.left.fx: Input should be greater than 0``). Driver sections carry a ``type``
plus options that the chosen driver validates against its own model (``vgripd.registry``).

Ownership of the sections (one room per job):
- ``camera``, ``calibration``, ``object``, ``vision``, ``output``: the vision pipeline.
- ``daemon``, ``links``, ``limits``, ``record``: the service and its robot links.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from vgripd.errors import ConfigError


class Model(BaseModel):
    """Base of every config model: unknown keys are errors, values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class DriverSection(BaseModel):
    """``type = "name"`` plus driver-specific options (validated by the driver's own model)."""

    model_config = ConfigDict(extra="allow", frozen=True)
    type: str

    def options(self) -> dict[str, Any]:
        return dict(self.model_extra or {})


class OutputConfig(Model):
    """What the robot receives: the offset in one vendor's convention."""

    vendor: str = "kuka"


class LimitsConfig(Model):
    """Safety gates applied before anything is published (offset against the taught reference)."""

    max_translation_mm: float = Field(50.0, gt=0)
    max_rotation_deg: float = Field(10.0, gt=0)


class DaemonConfig(Model):
    job_timeout_s: float = Field(10.0, gt=0)
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"


class Config(Model):
    """The whole file. Sections are filled in by their owners (see module docstring)."""

    camera: DriverSection = DriverSection(type="synthetic")
    output: OutputConfig = OutputConfig()
    limits: LimitsConfig = LimitsConfig()
    daemon: DaemonConfig = DaemonConfig()
    links: tuple[DriverSection, ...] = ()


def format_validation_error(err: ValidationError, source: str) -> str:
    """One line per problem: ``source: field.path: message``."""
    lines = []
    for e in err.errors():
        path = ".".join(str(p) for p in e["loc"]) or "<root>"
        lines.append(f"{source}: {path}: {e['msg']}")
    return "\n".join(lines)


def config_from_dict(data: dict[str, Any], source: str = "<config>") -> Config:
    try:
        return Config.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(err, source)) from None


def load_config(path: str | Path) -> Config:
    """Read and validate a TOML config file; every failure is a ``ConfigError``."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{p}: cannot read config: {err.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: not valid TOML: {err}") from None
    return config_from_dict(data, str(p))
