"""Vendor pose conventions against scipy's Rotation (tests only) and hand-worked numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vgripd.errors import ConversionError
from vgripd.geometry.vendors import (
    CONVENTIONS,
    VENDORS,
    target_from_transform,
    transform_from_vendor,
    vendor_from_transform,
)
from vgripd.types import RobotTarget

S2 = math.sqrt(0.5)  # cos 45 deg = sin 45 deg = 0.70710678...

# scipy oracle for each convention: Euler sequence (scipy spelling) or the special kinds.
SCIPY_KIND = {
    "kuka": "ZYX", "fanuc": "xyz", "yaskawa": "xyz", "denso": "xyz", "staubli": "XYZ",
    "kawasaki": "ZYZ", "comau": "ZYZ", "epson": "ZYX", "nachi": "ZYX", "abb": "quat", "ur": "rotvec",
}


def scipy_rotation(name: str, numbers: np.ndarray) -> Rotation:
    kind = SCIPY_KIND[name]
    if kind == "quat":
        return Rotation.from_quat(numbers, scalar_first=True)
    if kind == "rotvec":
        return Rotation.from_rotvec(numbers)
    return Rotation.from_euler(kind, numbers, degrees=True)


def scipy_numbers(name: str, rot: Rotation) -> np.ndarray:
    kind = SCIPY_KIND[name]
    if kind == "quat":
        return rot.as_quat(canonical=True, scalar_first=True)
    if kind == "rotvec":
        return rot.as_rotvec()
    return rot.as_euler(kind, degrees=True)


def test_table_covers_every_vendor_of_the_interfaces_table() -> None:
    assert set(VENDORS) == set(SCIPY_KIND) | {"matrix"}
    assert CONVENTIONS["kuka"].fields == ("X", "Y", "Z", "A", "B", "C")
    assert CONVENTIONS["fanuc"].fields == ("X", "Y", "Z", "W", "P", "R")
    assert CONVENTIONS["abb"].fields == ("x", "y", "z", "q1", "q2", "q3", "q4")
    assert (CONVENTIONS["ur"].length_unit, CONVENTIONS["ur"].angle_unit) == ("m", "rad")
    assert len(CONVENTIONS["matrix"].fields) == 16


@pytest.mark.parametrize("name", sorted(SCIPY_KIND))
def test_each_convention_against_scipy(name: str) -> None:
    rng = np.random.default_rng([ord(ch) for ch in name])
    rots = Rotation.random(200, random_state=rng)
    pos_mm = rng.uniform(-2000, 2000, (200, 3))
    scale = 1000.0 if name == "ur" else 1.0
    worst_to, worst_from = 0.0, 0.0
    for rot, p in zip(rots, pos_mm, strict=True):
        rot_values = scipy_numbers(name, rot)
        values = (*(p / scale), *rot_values)
        T = transform_from_vendor(name, values)
        worst_to = max(worst_to, np.abs(T[:3, :3] - scipy_rotation(name, rot_values).as_matrix()).max(),
                       np.abs(T[:3, 3] - p).max() * 1e-3)
        ours = np.array(vendor_from_transform(name, T))
        worst_from = max(worst_from, np.abs(ours - np.array(values)).max())
    print(f"ORACLE vendor {name} vs scipy: to matrix {worst_to:.3g}, to vendor numbers {worst_from:.3g} "
          f"({CONVENTIONS[name].angle_unit or 'unit'}, {CONVENTIONS[name].length_unit})")
    assert worst_to < 1e-12
    assert worst_from < 1e-9


@pytest.mark.parametrize("src", VENDORS)
@pytest.mark.parametrize("dst", VENDORS)
def test_cross_conversion_round_trips(src: str, dst: str) -> None:
    rot = Rotation.from_euler("ZYX", [37.0, -61.0, 122.0], degrees=True)
    T = np.eye(4)
    T[:3, :3] = rot.as_matrix()
    T[:3, 3] = [512.5, -33.25, 1210.0]
    there = vendor_from_transform(dst, transform_from_vendor(src, vendor_from_transform(src, T)))
    assert np.abs(transform_from_vendor(dst, there) - T).max() < 1e-9


# ---- hand-worked numbers -------------------------------------------------------------------
def test_kuka_a90_by_hand() -> None:
    # KUKA A=90, B=C=0 is Rz(90) = [[0,-1,0],[1,0,0],[0,0,1]]: 90 deg about z.
    T = transform_from_vendor("kuka", (100, -20, 300, 90, 0, 0))
    assert np.allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    # ABB: q = (cos(90/2), sin(90/2) * (0, 0, 1)) = (0.7071068, 0, 0, 0.7071068).
    assert np.allclose(vendor_from_transform("abb", T), (100, -20, 300, S2, 0, 0, S2), atol=1e-12)
    # UR: mm -> m (100 mm = 0.1 m), rotation vector = angle * axis = (0, 0, pi/2 = 1.5707963).
    assert np.allclose(vendor_from_transform("ur", T), (0.1, -0.02, 0.3, 0, 0, math.pi / 2), atol=1e-12)
    # FANUC: R = Rz(R) Ry(P) Rx(W) is KUKA's matrix with W = C, P = B, R = A: (0, 0, 90).
    assert np.allclose(vendor_from_transform("fanuc", T), (100, -20, 300, 0, 0, 90), atol=1e-12)


def test_kuka_b90_is_gimbal_lock_by_hand() -> None:
    # B=90: Ry(90) = [[0,0,1],[0,1,0],[-1,0,0]]; q = (cos45, 0, sin45, 0); UR (0, pi/2, 0).
    T = transform_from_vendor("kuka", (0, 0, 0, 0, 90, 0))
    assert np.allclose(vendor_from_transform("abb", T), (0, 0, 0, S2, 0, S2, 0), atol=1e-12)
    assert np.allclose(vendor_from_transform("ur", T), (0, 0, 0, 0, math.pi / 2, 0), atol=1e-12)
    # Lock: only A - C is defined; the convention returns C = 0 (FANUC: W = 0).
    assert np.allclose(vendor_from_transform("kuka", T), (0, 0, 0, 0, 90, 0), atol=1e-9)
    # A=30, C=10 at B=90 is the same matrix as A=20, C=0 (Rz(a) Ry(90) Rx(c) depends on a - c).
    T2 = transform_from_vendor("kuka", (0, 0, 0, 30, 90, 10))
    kuka = vendor_from_transform("kuka", T2)
    assert np.allclose(kuka, (0, 0, 0, 20, 90, 0), atol=1e-9)
    assert kuka[5] == 0.0
    assert vendor_from_transform("fanuc", T2)[3] == 0.0


def test_kuka_a90_c90_is_120_deg_about_111_by_hand() -> None:
    # Rz(90) Rx(90) = [[0,-1,0],[1,0,0],[0,0,1]] @ [[1,0,0],[0,0,-1],[0,1,0]] = [[0,0,1],[1,0,0],[0,1,0]]:
    # x -> y -> z -> x, a 120 deg turn about (1,1,1)/sqrt(3).
    T = transform_from_vendor("kuka", (1, 2, 3, 90, 0, 90))
    assert np.allclose(T[:3, :3], [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-15)
    # ABB: w = cos 60 = 0.5, vector = sin 60 / sqrt(3) * (1,1,1) = 0.5 * (1,1,1).
    assert np.allclose(vendor_from_transform("abb", T), (1, 2, 3, 0.5, 0.5, 0.5, 0.5), atol=1e-12)
    # UR: (2 pi / 3) / sqrt(3) = 2.0943951 / 1.7320508 = 1.2091996 on each axis; 1 mm = 0.001 m.
    assert np.allclose(vendor_from_transform("ur", T), (0.001, 0.002, 0.003, 1.2091996, 1.2091996, 1.2091996),
                       atol=1e-7)
    assert np.allclose(vendor_from_transform("fanuc", T), (1, 2, 3, 90, 0, 90), atol=1e-12)
    # Staubli Rx(a) Ry(b) Rz(c): R[0,2] = sin b = 1, b = 90 (lock, c = 0); then
    # Rx(a) Ry(90) = [[0,0,1],[sa,ca,0],[-ca,sa,0]] = R needs sa = 1: a = 90.  -> (90, 90, 0)
    assert np.allclose(vendor_from_transform("staubli", T), (1, 2, 3, 90, 90, 0), atol=1e-9)
    # Kawasaki Rz(O) Ry(A) Rz(T): column z = (cO sA, sO sA, cA) = (1, 0, 0) -> A = 90, O = 0;
    # row z = (-sA cT, sA sT, cA) = (0, 1, 0) -> T = 90.  -> (0, 90, 90)
    assert np.allclose(vendor_from_transform("kawasaki", T), (1, 2, 3, 0, 90, 90), atol=1e-9)
    # And back from ABB's numbers.
    assert np.allclose(vendor_from_transform("kuka", transform_from_vendor("abb", (1, 2, 3, .5, .5, .5, .5))),
                       (1, 2, 3, 90, 0, 90), atol=1e-12)


def test_half_turn_by_hand() -> None:
    # KUKA C=180: Rx(180) = diag(1,-1,-1); q = (0, 1, 0, 0); UR (pi, 0, 0); FANUC W=180.
    T = transform_from_vendor("kuka", (0, 0, 0, 0, 0, 180))
    assert np.allclose(vendor_from_transform("abb", T), (0, 0, 0, 0, 1, 0, 0), atol=1e-12)
    assert np.allclose(vendor_from_transform("ur", T), (0, 0, 0, math.pi, 0, 0), atol=1e-12)
    assert np.allclose(np.abs(vendor_from_transform("fanuc", T)), (0, 0, 0, 180, 0, 0), atol=1e-12)


def test_target_from_transform() -> None:
    target = target_from_transform("UR", transform_from_vendor("kuka", (100, 0, 0, 0, 0, 0)))
    assert target == RobotTarget("ur", ("x", "y", "z", "rx", "ry", "rz"), (0.1, 0.0, 0.0, 0.0, 0.0, 0.0))


def test_matrix_convention_row_major_mm() -> None:
    T = transform_from_vendor("kuka", (10, 20, 30, 15, -25, 35))
    values = vendor_from_transform("matrix", T)
    assert (values[3], values[7], values[11], values[12:]) == (10.0, 20.0, 30.0, (0, 0, 0, 1))
    # 9-digit text is not exactly orthonormal: accepted and snapped to the nearest rotation.
    rounded = [float(f"{v:.9g}") for v in values]
    back = transform_from_vendor("matrix", rounded)
    assert np.abs(back[:3, :3].T @ back[:3, :3] - np.eye(3)).max() < 1e-15
    assert np.abs(back - T).max() < 1e-8


# ---- validation ----------------------------------------------------------------------------
@pytest.mark.parametrize(("name", "values", "message"), [
    ("kuka", (1, 2, 3, 4, 5), r"kuka: expected 6 values \(X Y Z A B C\), got 5"),
    ("abb", (1, 2, 3, 1, 0, 0), r"abb: expected 7 values .* got 6"),
    ("kuka", (1, 2, 3, "x", 5, 6), r"A = 'x' is not a number"),
    ("kuka", (1, 2, float("nan"), 4, 5, 6), r"Z = nan is not finite"),
    ("ur", (1, 2, 3, float("inf"), 0, 0), r"rx = inf is not finite"),
    ("abb", (0, 0, 0, 0.5, 0.5, 0.5, 0.6), r"not unit length: \|q\| = 1.0535"),
    ("abb", (0, 0, 0, 0, 0, 0, 0), r"not unit length"),
    ("matrix", (1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1), r"matrix: .*reflection"),
    ("matrix", (2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1), r"not orthonormal"),
    ("matrix", (1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 1, 1), r"last row"),
    ("kukka", (1, 2, 3, 4, 5, 6), r"unknown vendor convention 'kukka' \(known: kuka, abb"),
])
def test_bad_input_raises_conversion_error(name: str, values: tuple, message: str) -> None:
    with pytest.raises(ConversionError, match=message):
        transform_from_vendor(name, values)


def test_nearly_unit_quaternion_is_normalised() -> None:
    q = np.array([S2, 0, 0, S2]) * (1 + 9e-7)
    T = transform_from_vendor("abb", (0, 0, 0, *q))
    assert np.allclose(vendor_from_transform("abb", T)[3:], (S2, 0, 0, S2), atol=1e-15)


def test_vendor_from_bad_transform_raises_conversion_error() -> None:
    with pytest.raises(ConversionError, match="not orthonormal"):
        vendor_from_transform("kuka", np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(ConversionError, match="NaN"):
        vendor_from_transform("abb", np.full((4, 4), np.nan))
