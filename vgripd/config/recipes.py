"""``[recipes.N]``: a name and overlays of the per-object sections (docs/recipes.md)."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from vgripd.configbase import MAX_RECIPE

#: The sections a recipe may overlay (``[recipes.N.<section>]``): what differs from one object
#: to the next. Everything else (camera, calibration, links, daemon, ...) belongs to the cell.
RECIPE_SECTIONS: tuple[str, ...] = ("object", "vision", "reference", "limits", "output",
                                    "picking")
#: Sections a recipe replaces as a whole instead of key by key: another object is another
#: object (its name and definition are not inherited from the top-level one).
RECIPE_WHOLE_SECTIONS: tuple[str, ...] = ("object",)
#: Longest recipe name (characters).
MAX_RECIPE_NAME = 64


RecipeNumber = Annotated[int, Field(ge=1, le=MAX_RECIPE)]


class RecipeConfig(BaseModel):
    """``[recipes.N]``: a ``name`` and overlays of the ``RECIPE_SECTIONS`` (raw tables here;
    they are judged as part of the recipe's effective config, ``Config.for_recipe``).

    Overlay rule, per section: the keys a recipe gives replace the same keys of the top-level
    section, the others are inherited (one level deep: a list or a table such as
    ``reference.T_base_obj`` is replaced as a whole). ``[recipes.N.object]`` replaces the
    top-level object as a whole (``RECIPE_WHOLE_SECTIONS``), and a recipe with its own object
    inherits no reference: its ``[recipes.N.reference]`` is all it has (none = not taught yet,
    its jobs answer NOT_CALIBRATED), since the top-level reference was taught on another
    object; for the same reason it inherits no ``picking.pick_points`` (grip points of the
    other object), while ``max_objects`` and ``order`` are inherited.
    """

    model_config = ConfigDict(extra="allow", frozen=True)
    # Shown in every log line of its jobs, the status line, the web view's header and a
    # metric label: one short line.
    name: str = Field(min_length=1, max_length=MAX_RECIPE_NAME)

    @field_validator("name")
    @classmethod
    def _one_line(cls, value: str) -> str:
        if any(ord(c) < 32 or ord(c) == 127 for c in value):
            raise ValueError(f"{value!r}: a recipe name is one line without control "
                             "characters (it appears in log lines and the status)")
        return value

    @model_validator(mode="after")
    def _known_sections(self) -> RecipeConfig:
        for key, value in (self.model_extra or {}).items():
            if key not in RECIPE_SECTIONS:
                raise ValueError(f"{key!r} cannot be set per recipe (a recipe may set name and "
                                 f"{', '.join(RECIPE_SECTIONS)}; the rest belongs to the cell)")
            if not isinstance(value, dict):
                raise ValueError(f"{key} must be a table ([recipes.N.{key}])")
        return self

    def sections(self) -> dict[str, dict[str, Any]]:
        """The overlaid sections, by name."""
        return {k: v for k, v in (self.model_extra or {}).items() if k in RECIPE_SECTIONS}


def unknown_recipe(number: int, known: tuple[int, ...]) -> str:
    """The message for a recipe number that is not configured."""
    return (f"recipe {number} is not configured (configured: "
            f"{', '.join(str(n) for n in known)}; 0 = the top-level config)")
