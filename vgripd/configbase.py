"""The bottom of the configuration: what both the config model (``vgripd.config``) and the
driver registry (``vgripd.registry``) need, so that neither imports the other to get it.

``DriverSection`` is a ``[camera]`` or ``[[links]]`` section as the config holds it (a ``type``
plus options the driver validates); ``format_validation_error`` turns a pydantic error into the
``source: field.path: message`` lines every config error is shown as. ``vgripd.config``
re-exports all of it.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

#: pydantic error type of a refused combination of fields: its message names every field
#: involved, so it is shown without a field path (``format_validation_error``).
COMBINATION = "combination"
#: pydantic error type of a recipe whose effective config is invalid: its message is one line
#: per problem, each starting with the full field path (``recipes.2.vision.downscale: ...``).
RECIPE_PROBLEMS = "recipe_problems"

#: pydantic error type of a refused combination whose message is one line per problem, each
#: starting with the field it is about (``object.features[3]: marker id 7 of ... is used
#: twice``): shown as it is, blamed on the file that set that field.
PLACED = "placed"

#: Highest recipe number: the RECIPE register is one 16-bit word.
MAX_RECIPE = 65535


class DriverSection(BaseModel):
    """``type = "name"`` plus driver-specific options (validated by the driver's own model)."""

    model_config = ConfigDict(extra="allow", frozen=True)
    type: str

    def options(self) -> dict[str, Any]:
        return dict(self.model_extra or {})


def format_validation_error(
    err: ValidationError, source: str, owner: dict[str, str] | None = None
) -> str:
    """One line per problem: ``source: field.path: message``.

    ``owner`` maps leaf field paths to the file that set them (includes); a problem is blamed
    on the file that set the field, or the one that set something below it.
    """
    lines = []
    for e in err.errors():
        path = ".".join(str(p) for p in e["loc"]) or "<root>"
        if e["type"] == COMBINATION:
            # The message names its fields; blame the file that set the links.
            where = (owner or {}).get("links", source)
            lines += [f"{where}: {line}" for line in e["msg"].splitlines()]
            continue
        if e["type"] in (RECIPE_PROBLEMS, PLACED):  # each line starts with its field path
            lines += [f"{_blame(line.split(':', 1)[0], source, owner)}: {line}"
                      for line in e["msg"].splitlines()]
            continue
        if path.startswith("recipes.") and path.endswith(".[key]"):
            path = path.removesuffix(".[key]")
            e["msg"] = f"{e['msg']} (a recipe number is 1 .. {MAX_RECIPE}; 0 is the top level)"
        lines.append(f"{_blame(path, source, owner)}: {path}: {e['msg']}")
    return "\n".join(lines)


def _blame(path: str, source: str, owner: dict[str, str] | None) -> str:
    """The file that set ``path`` (or something below or above it); ``source`` if none."""
    for key, file in (owner or {}).items():
        if key == path or key.startswith(path + ".") or path.startswith(key + "."):
            return file
    return source
