"""Driver registry: a config ``type`` name -> the class that implements it, imported lazily.

A missing optional SDK breaks only the driver that needs it, with a clear ``DriverError``.
``vgripd`` reaches ``drivers/`` only through this table.
"""

from __future__ import annotations

import importlib
from typing import Any

from pydantic import ValidationError

from vgripd.config import DriverSection, format_validation_error
from vgripd.errors import ConfigError, DriverError

CAMERAS: dict[str, str] = {
    "replay": "drivers.cameras.replay:ReplayCamera",
    "synthetic": "drivers.cameras.synthetic:SyntheticCamera",
    "opencv": "drivers.cameras.opencv:OpenCVCamera",
    "genicam": "drivers.cameras.genicam:GenICamCamera",
}

LINKS: dict[str, str] = {
    "modbus_server": "drivers.links.modbus_server:ModbusServerLink",
    "modbus_client": "drivers.links.modbus_client:ModbusClientLink",
    "modbus_rtu": "drivers.links.modbus_rtu:ModbusRtuLink",
    "ur_rtde": "drivers.links.ur_rtde:URRtdeLink",
}


def load_class(table: dict[str, str], kind: str, type_name: str) -> type[Any]:
    try:
        target = table[type_name]
    except KeyError:
        known = ", ".join(sorted(table))
        raise ConfigError(f"unknown {kind} type {type_name!r} (known: {known})") from None
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise DriverError(f"{kind} driver {type_name!r} is not available: {err}") from None
    cls: type[Any] = getattr(module, attr)
    return cls


def validate_options(cls: type[Any], section: DriverSection, where: str) -> Any:
    """Validate a section's options against ``cls.Options`` (a pydantic model)."""
    try:
        return cls.Options.model_validate(section.options())
    except ValidationError as err:
        raise ConfigError(format_validation_error(err, where)) from None
