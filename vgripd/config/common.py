"""What every section of the config shares: the base ``Model`` (unknown keys are errors,
values immutable, numbers finite), a pose in one of its two forms, and the ``allow`` list of a
server surface."""

from __future__ import annotations

import ipaddress
from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator, model_validator

from vgripd.errors import DegenerateInputError
from vgripd.geometry.transforms import check_transform


class Model(BaseModel):
    """Base of every config model: unknown keys are errors, values are immutable, and numbers
    are finite (TOML can spell ``inf`` and ``nan``; no setting means either)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _allow_entry(entry: str) -> str:
    """One ``allow`` entry: an address (``10.0.0.5``) or a network (``10.0.1.0/24``). Judged
    here, once, so a typo is a config error naming ``...allow.<index>``, not an open door."""
    try:
        ipaddress.ip_network(entry.strip(), strict=False)
    except ValueError:
        raise ValueError(f"{entry!r} is not an IP address or network (e.g. \"10.0.0.5\" or "
                         f"\"10.0.1.0/24\")") from None
    return entry.strip()


#: ``allow = ["10.0.0.5", "10.0.1.0/24"]`` of a server surface (a link or the web view): other
#: client addresses are closed at accept (vgripd.service.links.gate); unset = every address. An
#: empty list is refused (it would lock every client out).
AllowList = Annotated[list[Annotated[str, AfterValidator(_allow_entry)]], Field(min_length=1)] \
    | None


def is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name other than localhost may resolve to anything
        return False


Vec3 = tuple[float, float, float]
_Row4 = tuple[float, float, float, float]
_Matrix4 = tuple[_Row4, _Row4, _Row4, _Row4]


class PoseConfig(Model):
    """A rigid transform ``T_a_b`` (pose of frame b in frame a, mm and rad), in exactly one form.

    Either ``translation_mm = [x, y, z]`` with ``rotvec_rad = [rx, ry, rz]`` (axis * angle,
    default no rotation), or ``matrix = [[4 rows of 4]]`` (homogeneous, last row 0 0 0 1).
    """

    translation_mm: Vec3 | None = None
    rotvec_rad: Vec3 | None = None
    matrix: _Matrix4 | None = None

    @field_validator("matrix")
    @classmethod
    def _rigid(cls, m: _Matrix4 | None) -> _Matrix4 | None:
        if m is not None:
            try:
                check_transform(m, "matrix")
            except DegenerateInputError as err:
                raise ValueError(str(err)) from None
        return m

    def translation(self) -> tuple[float, float, float]:
        """Where frame b's origin is in frame a (mm), whichever form was given."""
        if self.matrix is not None:
            return (self.matrix[0][3], self.matrix[1][3], self.matrix[2][3])
        assert self.translation_mm is not None  # _one_form
        return (self.translation_mm[0], self.translation_mm[1], self.translation_mm[2])

    @model_validator(mode="after")
    def _one_form(self) -> PoseConfig:
        if self.matrix is not None:
            if self.translation_mm is not None or self.rotvec_rad is not None:
                raise ValueError("give either matrix or translation_mm/rotvec_rad, not both")
        elif self.translation_mm is None:
            raise ValueError("pose needs translation_mm (with optional rotvec_rad) or matrix")
        return self
