"""Plain data out of vgripd values: JSON-ready structures and TOML text.

Used by the recorder, the calibration tools' result files and the CLIs' ``--json`` output.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np


def jsonable(value: Any) -> Any:
    """Plain JSON data for numpy arrays/scalars, enums, mappings, tuples and paths."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Enum):
        return value.name
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def _toml_key(key: str) -> str:
    return key if _BARE_KEY.fullmatch(key) else json.dumps(key)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # JSON string escapes are valid TOML basic-string escapes
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def _is_table_array(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def toml_from_dict(data: Mapping[str, Any]) -> str:
    """TOML text for JSON-like data (no None): tables as ``[a.b]``, lists of tables as
    ``[[a]]`` with inline tables inside. ``tomllib.loads`` gives ``data`` back."""
    lines: list[str] = []

    def table(d: Mapping[str, Any], path: tuple[str, ...]) -> None:
        if path:
            lines.append(f"\n[{'.'.join(map(_toml_key, path))}]")
        nested = {k: v for k, v in d.items() if isinstance(v, dict) or _is_table_array(v)}
        lines.extend(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in d.items() if k not in nested)
        for k, v in nested.items():
            if isinstance(v, dict):
                table(v, (*path, k))
                continue
            for item in v:
                lines.append(f"\n[[{'.'.join(map(_toml_key, (*path, k)))}]]")
                lines.extend(f"{_toml_key(ik)} = {_toml_value(iv)}" for ik, iv in item.items())

    table(data, ())
    return "\n".join(lines).lstrip("\n") + "\n"
