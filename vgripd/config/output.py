"""``[output]`` (what the robot receives, in which vendor's convention) and ``[limits]`` (the
safety gates a found pose passes before it is published)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from vgripd.config.common import Model
from vgripd.geometry.vendors import VENDORS


class OutputConfig(Model):
    """What the robot receives, in one vendor's convention.

    ``mode = "offset"``: the base-frame correction ``T_offset`` (the robot applies it to its
    own taught grip). ``mode = "grip"``: the absolute grip pose ``T_offset @ G`` with ``G`` =
    ``reference.grip`` (taught with ``vgripd teach --grip``; see docs/teach.md).
    """

    vendor: str = "kuka"
    mode: Literal["offset", "grip"] = "offset"

    @field_validator("vendor")
    @classmethod
    def _known_vendor(cls, vendor: str) -> str:
        if vendor not in VENDORS:
            raise ValueError(f"unknown vendor {vendor!r} (known: {', '.join(sorted(VENDORS))})")
        return vendor


class LimitsConfig(Model):
    """Safety gates applied before anything is published (found pose against the taught one).

    ``max_translation_mm``: how far one point P of the object may have moved between the
    taught reference and the found pose (``|T_base_obj @ P - T_base_obj_ref @ P|``), not the
    length of the base-frame offset's translation (which adds the lever arm of any rotation
    about the robot base). P is ``point_mm`` (object frame) when set, else ``point``:
    ``"origin"`` (the object frame's origin), ``"centroid"`` (of the model points) or
    ``"grip"`` (the position of ``reference.grip``); unset = ``"origin"`` for a CAD object,
    ``"centroid"`` for ``object.definition = "reference"`` (whose origin is the robot base's).
    ``max_rotation_deg``: the angle of the object's rotation between reference and found pose.
    ``workspace_min_mm``/``workspace_max_mm``: a box in the robot base frame that every model
    point of the found object must lie in (both or neither; unset = no box check).
    See docs/pipeline.md, "Limits".
    """

    max_translation_mm: float = Field(default=50.0, gt=0)
    max_rotation_deg: float = Field(default=10.0, gt=0)
    point: Literal["origin", "centroid", "grip"] | None = None
    point_mm: tuple[float, float, float] | None = None
    workspace_min_mm: tuple[float, float, float] | None = None
    workspace_max_mm: tuple[float, float, float] | None = None

    @model_validator(mode="after")
    def _box(self) -> LimitsConfig:
        if self.point is not None and self.point_mm is not None:
            raise ValueError("give either point or point_mm (the point whose displacement "
                             "max_translation_mm limits), not both")
        lo, hi = self.workspace_min_mm, self.workspace_max_mm
        if (lo is None) != (hi is None):
            raise ValueError("workspace_min_mm and workspace_max_mm go together")
        if lo is not None and hi is not None and not all(
            a < b for a, b in zip(lo, hi, strict=True)
        ):
            raise ValueError(
                f"workspace_min_mm {list(lo)} must be below workspace_max_mm {list(hi)}"
            )
        return self
