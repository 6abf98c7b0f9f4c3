"""Robot-vendor pose conventions: the only place where units change.

Inside vgripd a pose is a 4x4 ``T_a_b`` in millimetres (see ``vgripd.geometry.transforms``). Robot
controllers want six or seven numbers in their own field order, length unit (mm or m) and
rotation convention (Euler angles in degrees in some sequence, a unit quaternion, a rotation
vector in radians). ``CONVENTIONS`` tabulates them; ``transform_from_vendor`` and
``vendor_from_transform`` convert, validating everything a human or a PLC might get wrong.

Euler sequences use scipy's spelling (upper case intrinsic, lower case extrinsic; see
``vgripd.geometry.transforms``). KUKA's A, B, C (intrinsic Z, Y', X'') and FANUC's W, P, R (about
the fixed
X, Y, Z) are the same matrix ``Rz Ry Rx`` with the angles listed in opposite orders. At gimbal
lock the angle applied first to the tool (KUKA C, FANUC W, Kawasaki T, ...) is returned as 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from vgripd.errors import ConversionError, DegenerateInputError
from vgripd.geometry.transforms import (
    check_transform,
    euler_from_matrix,
    matrix_from_euler,
    matrix_from_quat,
    matrix_from_rotvec,
    project_rotation,
    quat_from_matrix,
    rotvec_from_matrix,
)
from vgripd.types import RobotTarget

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Convention:
    """How one vendor writes a pose.

    ``fields`` are in the vendor's usual order; the first three are the position.
    ``rotation``: ``"euler"`` (three angles in ``angle_unit`` in sequence ``euler_seq``),
    ``"quat"`` (w, x, y, z), ``"rotvec"`` (axis * angle in ``angle_unit``) or ``"matrix"``
    (all 16 entries of the 4x4, row-major).
    """

    name: str
    fields: tuple[str, ...]
    length_unit: Literal["mm", "m"]
    rotation: Literal["euler", "quat", "rotvec", "matrix"]
    angle_unit: Literal["deg", "rad", ""] = "deg"
    euler_seq: str = ""
    summary: str = ""

    @property
    def length_scale(self) -> float:
        """Vendor length unit in mm (1 for mm, 1000 for m)."""
        return 1000.0 if self.length_unit == "m" else 1.0


def _euler(name: str, angles: tuple[str, str, str], seq: str, summary: str) -> Convention:
    return Convention(name, ("X", "Y", "Z", *angles), "mm", "euler", "deg", seq, summary)


CONVENTIONS: dict[str, Convention] = {c.name: c for c in (
    _euler("kuka", ("A", "B", "C"), "ZYX", "A, B, C deg, intrinsic Z, Y', X'': Rz(A) Ry(B) Rx(C)"),
    Convention("abb", ("x", "y", "z", "q1", "q2", "q3", "q4"), "mm", "quat", "",
               summary="unit quaternion q1..q4 = w, x, y, z (scalar first)"),
    _euler("fanuc", ("W", "P", "R"), "xyz", "W, P, R deg about fixed X, Y, Z: Rz(R) Ry(P) Rx(W)"),
    _euler("yaskawa", ("Rx", "Ry", "Rz"), "xyz", "Rx, Ry, Rz deg about fixed X, Y, Z"),
    Convention("ur", ("x", "y", "z", "rx", "ry", "rz"), "m", "rotvec", "rad",
               summary="m; rotation vector rx, ry, rz = axis * angle, rad"),
    _euler("staubli", ("Rx", "Ry", "Rz"), "XYZ", "Rx, Ry, Rz deg, intrinsic X, Y', Z''"),
    _euler("kawasaki", ("O", "A", "T"), "ZYZ", "O, A, T deg, intrinsic Z, Y', Z''"),
    _euler("comau", ("A", "E", "R"), "ZYZ", "A, E, R deg, intrinsic Z, Y', Z''"),
    _euler("denso", ("RX", "RY", "RZ"), "xyz", "RX, RY, RZ deg about fixed X, Y, Z"),
    _euler("epson", ("U", "V", "W"), "ZYX", "U, V, W deg, intrinsic Z, Y', X''"),
    _euler("nachi", ("RZ", "RY", "RX"), "ZYX", "RZ, RY, RX deg, intrinsic Z, Y', X''"),
    Convention("matrix", tuple(f"m{r}{c}" for r in range(4) for c in range(4)), "mm", "matrix",
               "", summary="4x4 homogeneous transform, row-major, mm"),
)}

#: Names accepted by the functions below, in table order.
VENDORS: list[str] = list(CONVENTIONS)


def convention(name: str) -> Convention:
    """The convention called ``name`` (case-insensitive); ConversionError names the known ones."""
    conv = CONVENTIONS.get(str(name).strip().lower())
    if conv is None:
        raise ConversionError(f"unknown vendor convention {name!r} (known: {', '.join(VENDORS)})")
    return conv


def _numbers(conv: Convention, values: Sequence[Any]) -> list[float]:
    if len(values) != len(conv.fields):
        raise ConversionError(
            f"{conv.name}: expected {len(conv.fields)} values ({' '.join(conv.fields)}), "
            f"got {len(values)}")
    out = []
    for field, v in zip(conv.fields, values, strict=True):
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise ConversionError(f"{conv.name}: {field} = {v!r} is not a number") from None
        if not math.isfinite(x):
            raise ConversionError(f"{conv.name}: {field} = {v!r} is not finite")
        out.append(x)
    return out


def _to_rad(conv: Convention, angles: Sequence[float]) -> list[float]:
    return [math.radians(a) for a in angles] if conv.angle_unit == "deg" else list(angles)


def transform_from_vendor(name: str, values: Sequence[Any]) -> FloatArray:
    """The 4x4 transform (mm) of a pose written in a vendor's convention.

    Raises
    ------
    ConversionError
        unknown name; wrong number of values (names expected and got); a value that is not a
        finite number (names the field); a quaternion whose norm is off 1 by more than 1e-6
        (closer ones are normalised); a matrix that is not a rigid transform.
    """
    conv = convention(name)
    v = _numbers(conv, values)
    try:
        if conv.rotation == "matrix":
            T = check_transform(np.array(v).reshape(4, 4), f"{conv.name}")
            # Text with ~9 digits is not exactly orthonormal: snap to the nearest rotation.
            T = T.copy()
            T[:3, :3] = project_rotation(T[:3, :3])
            return T
        if conv.rotation == "quat":
            R = matrix_from_quat(v[3:], scalar_first=True)
        elif conv.rotation == "rotvec":
            R = matrix_from_rotvec(_to_rad(conv, v[3:]))
        else:
            R = matrix_from_euler(conv.euler_seq, _to_rad(conv, v[3:]))
    except DegenerateInputError as err:
        raise ConversionError(f"{conv.name}: {err}") from None
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.array(v[:3]) * conv.length_scale
    return T


def vendor_from_transform(name: str, T: Any) -> tuple[float, ...]:
    """A 4x4 transform (mm) as the vendor's numbers, in its field order and units.

    Quaternions come with w >= 0; Euler angles in (-180, 180] deg with the middle angle in
    [-90, 90] (Tait-Bryan) or [0, 180] (Z-Y-Z); rotation vectors with angle in [0, pi].
    """
    conv = convention(name)
    try:
        M = check_transform(T, f"{conv.name}: transform")
        R = M[:3, :3]
        if conv.rotation == "matrix":
            return tuple(float(x) + 0.0 for x in M.reshape(-1))
        if conv.rotation == "quat":
            rot = [float(x) for x in quat_from_matrix(R)]
        elif conv.rotation == "rotvec":
            rot = [float(x) for x in rotvec_from_matrix(R)]
        else:
            rot = list(euler_from_matrix(conv.euler_seq, R))
    except DegenerateInputError as err:
        raise ConversionError(str(err)) from None
    if conv.angle_unit == "deg":
        rot = [math.degrees(a) for a in rot]
    pos = [float(x) / conv.length_scale for x in M[:3, 3]]
    # "+ 0.0" turns -0.0 into 0.0, so printed values do not show a spurious sign.
    return tuple(x + 0.0 for x in (*pos, *rot))


def target_from_transform(name: str, T: Any) -> RobotTarget:
    """``vendor_from_transform`` packed with the vendor's field names."""
    conv = convention(name)
    return RobotTarget(conv.name, conv.fields, vendor_from_transform(conv.name, T))
