"""Rigid transforms and rotation conventions against scipy's Rotation (tests only) and by property.

Max abs errors against scipy are printed with an ORACLE prefix (``pytest -s``).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from vgripd.errors import DegenerateInputError
from vgripd.geometry.transforms import (
    adjoint,
    check_rotation,
    check_transform,
    compose,
    euler_from_matrix,
    euler_zyx_from_matrix,
    inverse_left_jacobians,
    invert_transform,
    invert_transforms,
    left_jacobians,
    make_transform,
    matrices_from_quats,
    matrices_from_rotvecs,
    matrix_from_euler,
    matrix_from_euler_zyx,
    matrix_from_quat,
    matrix_from_rotvec,
    pose_error,
    pose_errors,
    project_rotation,
    quat_conjugate,
    quat_from_matrix,
    quat_multiply,
    quats_from_matrices,
    rotation_angle,
    rotation_angles,
    rotvec_from_matrix,
    rotvecs_from_matrices,
    skew,
    solve_loop,
    transform_points,
    transforms_from_vectors,
    vectors_from_transforms,
    vee,
)

RNG = np.random.default_rng(20240601)
RANDOM_ROTATIONS = Rotation.random(300, random_state=RNG)

TAIT_BRYAN = ["".join(p) for p in itertools.permutations("XYZ")]
PROPER = [a + b + a for a in "XYZ" for b in "XYZ" if a != b]
ALL_SEQS = [s for seq in TAIT_BRYAN + PROPER for s in (seq, seq.lower())]

angle = st.floats(-math.pi, math.pi, allow_nan=False)
unit_quat = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3).map(lambda q: np.array(q) / np.linalg.norm(q))
# Middle angles at and around gimbal lock, including +-1e-9 rad off it.
near_lock = st.sampled_from([0.0, 1e-9, -1e-9, 1e-13, 1e-6]).flatmap(
    lambda d: st.sampled_from([math.pi / 2 + d, -math.pi / 2 + d, math.pi / 2 - d, -math.pi / 2 - d]))


@pytest.mark.parametrize("seq", ALL_SEQS)
def test_euler_against_scipy_all_sequences(seq: str) -> None:
    mats = RANDOM_ROTATIONS.as_matrix()
    ref_angles = RANDOM_ROTATIONS.as_euler(seq)
    err_m = max(np.abs(matrix_from_euler(seq, a) - m).max() for a, m in zip(ref_angles, mats, strict=True))
    err_a = max(np.abs(np.array(euler_from_matrix(seq, m)) - a).max() for a, m in zip(ref_angles, mats, strict=True))
    print(f"ORACLE euler {seq} vs scipy: matrix max abs {err_m:.3g}, angles max abs {err_a:.3g} rad")
    assert err_m < 1e-14
    assert err_a < 1e-12


def test_zyx_is_kuka_rz_ry_rx_by_hand() -> None:
    # A = 90 deg about Z only: x -> y, y -> -x.
    assert np.allclose(matrix_from_euler_zyx(math.pi / 2, 0, 0), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-16)
    # B = 90 deg about Y: z -> x.
    assert np.allclose(matrix_from_euler_zyx(0, math.pi / 2, 0) @ [0, 0, 1], [1, 0, 0], atol=1e-16)
    # Intrinsic Z then Y': Rz(90) Ry(90) sends z to Rz(90) x = y.
    assert np.allclose(matrix_from_euler_zyx(math.pi / 2, math.pi / 2, 0) @ [0, 0, 1], [0, 1, 0], atol=1e-16)
    # Extrinsic xyz with (c, b, a) is the same matrix as intrinsic ZYX with (a, b, c).
    assert np.allclose(matrix_from_euler("xyz", (0.3, -0.2, 1.1)), matrix_from_euler_zyx(1.1, -0.2, 0.3), atol=0)


@pytest.mark.parametrize(("seq", "middle"), [
    ("ZYX", math.pi / 2), ("ZYX", -math.pi / 2), ("XYZ", math.pi / 2), ("XYZ", -math.pi / 2),
    ("ZYZ", 0.0), ("ZYZ", math.pi),
])
def test_gimbal_lock_returns_third_angle_zero_and_same_matrix(seq: str, middle: float) -> None:
    R = matrix_from_euler(seq, (0.7, middle, -0.4))
    a, b, c = euler_from_matrix(seq, R)
    assert c == 0.0
    assert abs(b - middle) < 1e-7
    assert np.abs(matrix_from_euler(seq, (a, b, c)) - R).max() < 1e-15
    # Extrinsic: the reversed intrinsic sequence, so the FIRST angle is the zero one.
    ext = seq[::-1].lower()
    c2, b2, a2 = euler_from_matrix(ext, R)
    assert (a2, b2, c2) == (a, b, c)


@settings(max_examples=100, deadline=None)
@given(a=angle, b=near_lock, c=angle)
def test_zyx_round_trip_near_gimbal_lock(a: float, b: float, c: float) -> None:
    R = matrix_from_euler_zyx(a, b, c)
    back = matrix_from_euler_zyx(*euler_zyx_from_matrix(R))
    assert np.abs(back - R).max() < 1e-11


@settings(max_examples=100, deadline=None)
@given(seq=st.sampled_from(["ZYX", "XYZ", "ZYZ", "xyz"]), a=angle, b=angle, c=angle)
def test_euler_round_trip_any_angles(seq: str, a: float, b: float, c: float) -> None:
    R = matrix_from_euler(seq, (a, b, c))
    back = matrix_from_euler(seq, euler_from_matrix(seq, R))
    assert np.abs(back - R).max() < 1e-12
    ref = Rotation.from_euler(seq, [a, b, c]).as_matrix()
    assert np.abs(R - ref).max() < 1e-14


@settings(max_examples=100, deadline=None)
@given(a=angle, d=st.sampled_from([0.0, 1e-9, -1e-9, 1e-12]), c=angle, first=st.booleans())
def test_zyz_round_trip_near_lock(a: float, d: float, c: float, first: bool) -> None:
    b = abs(d) if first else math.pi - abs(d)
    R = matrix_from_euler("ZYZ", (a, b, c))
    assert np.abs(matrix_from_euler("ZYZ", euler_from_matrix("ZYZ", R)) - R).max() < 1e-11


def test_bad_euler_sequences() -> None:
    for seq in ("ZZX", "ZyX", "ABC", "ZY", "xyzx"):
        with pytest.raises(DegenerateInputError, match="Euler sequence"):
            matrix_from_euler(seq, (0, 0, 0))


def test_quaternions_against_scipy() -> None:
    mats = RANDOM_ROTATIONS.as_matrix()
    q_first = RANDOM_ROTATIONS.as_quat(canonical=True, scalar_first=True)
    q_last = RANDOM_ROTATIONS.as_quat(canonical=True, scalar_first=False)
    e1 = max(np.abs(quat_from_matrix(m) - q).max() for m, q in zip(mats, q_first, strict=True))
    e2 = max(np.abs(quat_from_matrix(m, scalar_first=False) - q).max() for m, q in zip(mats, q_last, strict=True))
    e3 = max(np.abs(matrix_from_quat(q) - m).max() for m, q in zip(mats, q_first, strict=True))
    e4 = max(np.abs(matrix_from_quat(q, scalar_first=False) - m).max() for m, q in zip(mats, q_last, strict=True))
    print(f"ORACLE quaternion vs scipy: from matrix {max(e1, e2):.3g}, to matrix {max(e3, e4):.3g}")
    assert max(e1, e2, e3, e4) < 1e-14


@settings(max_examples=100, deadline=None)
@given(q=unit_quat)
def test_q_and_minus_q_are_the_same_rotation_and_sign_is_canonical(q: np.ndarray) -> None:
    R = matrix_from_quat(q)
    assert np.abs(R - matrix_from_quat(-q)).max() < 1e-15
    back = quat_from_matrix(R)
    assert back[0] >= 0
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-12


def test_quaternion_norm_tolerance() -> None:
    q = np.array([0.5, 0.5, 0.5, 0.5])
    assert np.allclose(matrix_from_quat(q * (1 + 5e-7)), matrix_from_quat(q), atol=1e-15)
    with pytest.raises(DegenerateInputError, match="not unit length"):
        matrix_from_quat(q * 1.01)
    with pytest.raises(DegenerateInputError, match="4 finite"):
        matrix_from_quat([1, 0, 0, np.nan])


def test_quaternion_at_half_turn_has_canonical_sign() -> None:
    # 180 deg about -x: w = 0, the vector part sign is fixed by its first non-zero entry.
    R = np.diag([1.0, -1.0, -1.0])
    assert np.array_equal(quat_from_matrix(R), [0.0, 1.0, 0.0, 0.0])


def test_rotvec_against_scipy_including_tiny_and_near_pi() -> None:
    axes = RNG.normal(size=(58, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.r_[0.0, 1e-15, 1e-9, 1e-6, RNG.uniform(0, math.pi, 48), math.pi - 1e-6,
                   math.pi - 1e-9, math.pi - 1e-12, math.pi - 1e-15, math.pi, math.pi]
    worst_to, worst_from = 0.0, 0.0
    for ax, th in zip(axes, angles, strict=True):
        v = ax * th
        ref = Rotation.from_rotvec(v)
        worst_to = max(worst_to, np.abs(matrix_from_rotvec(v) - ref.as_matrix()).max())
        back = rotvec_from_matrix(ref.as_matrix())
        # At exactly pi, v and -v are the same rotation.
        d = min(np.abs(back - v).max(), np.abs(back + v).max()) if th > math.pi - 1e-6 else np.abs(back - v).max()
        worst_from = max(worst_from, d)
        assert abs(rotation_angle(ref.as_matrix()) - ref.magnitude()) < 1e-9
    print(f"ORACLE rotvec vs scipy: to matrix {worst_to:.3g}, from matrix {worst_from:.3g} rad")
    assert worst_to < 1e-15
    assert worst_from < 1e-12


def test_rotation_angle_is_accurate_at_small_angles() -> None:
    # acos((trace - 1) / 2) would give 0 here; the quaternion route keeps the digits.
    assert abs(rotation_angle(matrix_from_rotvec([1e-9, 0, 0])) - 1e-9) < 1e-20
    assert abs(rotation_angle(matrix_from_rotvec([0, 0, math.pi])) - math.pi) < 1e-15


@settings(max_examples=100, deadline=None)
@given(q1=unit_quat, q2=unit_quat, t1=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
       t2=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3))
def test_compose_invert_and_points(q1: np.ndarray, q2: np.ndarray, t1: list[float], t2: list[float]) -> None:
    T_a_b = make_transform(matrix_from_quat(q1), t1)
    T_b_c = make_transform(matrix_from_quat(q2), t2)
    p_c = np.array([[1.0, 2.0, 3.0], [-40.0, 5.0, 600.0]])
    T_a_c = compose(T_a_b, T_b_c)
    assert np.abs(transform_points(T_a_c, p_c) - transform_points(T_a_b, transform_points(T_b_c, p_c))).max() < 1e-9
    assert np.abs(compose(T_a_b, invert_transform(T_a_b)) - np.eye(4)).max() < 1e-10  # |t| up to 1e3 mm
    assert np.abs(invert_transform(T_a_b) - np.linalg.inv(T_a_b)).max() < 1e-9
    # scipy composes rotations the same way (r1 * r2 applies r2 first).
    ref = (Rotation.from_quat(q1, scalar_first=True) * Rotation.from_quat(q2, scalar_first=True)).as_matrix()
    assert np.abs(T_a_c[:3, :3] - ref).max() < 1e-14


def test_solve_loop_chapter_fig6() -> None:
    rots = Rotation.random(3, random_state=RNG).as_matrix()
    T_A_B = make_transform(rots[0], [100.0, 0.0, 50.0])
    T_B_C = make_transform(rots[1], [0.0, -30.0, 10.0])
    T_A_D = make_transform(rots[2], [500.0, 200.0, 0.0])
    known = {("A", "B"): T_A_B, ("B", "C"): T_B_C, ("A", "D"): T_A_D}
    # Loop ABC: T_A_C = T_A_B T_B_C; loop ABCD: T_D_C = (T_A_D)^-1 T_A_B T_B_C (np.linalg.inv as oracle).
    assert np.abs(solve_loop(known, "A", "C") - T_A_B @ T_B_C).max() < 1e-12
    assert np.abs(solve_loop(known, "D", "C") - np.linalg.inv(T_A_D) @ T_A_B @ T_B_C).max() < 1e-12
    assert np.abs(solve_loop(known, "C", "D") - np.linalg.inv(np.linalg.inv(T_A_D) @ T_A_B @ T_B_C)).max() < 1e-12
    assert np.array_equal(solve_loop(known, "B", "B"), np.eye(4))
    with pytest.raises(DegenerateInputError, match="no chain .* 'A' to 'E'"):
        solve_loop(known, "A", "E")
    bad = dict(known)
    bad["B", "C"] = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(DegenerateInputError, match="T_B_C.*reflection"):
        solve_loop(bad, "A", "C")


def test_validation_messages() -> None:
    with pytest.raises(DegenerateInputError, match="flange: .*reflection"):
        check_rotation(np.diag([1.0, 1.0, -1.0]), "flange")
    with pytest.raises(DegenerateInputError, match="not orthonormal"):
        check_rotation(np.diag([1.0, 1.0, 1.01]))
    with pytest.raises(DegenerateInputError, match="NaN"):
        check_rotation(np.full((3, 3), np.nan))
    with pytest.raises(DegenerateInputError, match=r"\(3, 3\)"):
        check_rotation(np.eye(4))
    with pytest.raises(DegenerateInputError, match="last row"):
        check_transform(np.r_[np.eye(4)[:3], [[0, 0, 1, 1]]])
    with pytest.raises(DegenerateInputError, match="t must be 3 finite"):
        make_transform(np.eye(3), [1.0, np.inf, 0.0])
    with pytest.raises(DegenerateInputError, match=r"\(n, 3\)"):
        transform_points(np.eye(4), np.zeros(3))


# ---------------------------------------------------------------------- stacked helpers
# Angles from exactly 0 to exactly pi, with the ends where naive formulas lose digits.
EDGE_ANGLES = [0.0, 1e-15, 1e-12, 1e-9, 1e-6, 1e-3, 0.01, math.pi / 2, math.pi - 1e-3,
               math.pi - 1e-6, math.pi - 1e-9, math.pi - 1e-12, math.pi]
rotation_angle_st = st.one_of(st.sampled_from(EDGE_ANGLES), st.floats(0.0, math.pi))
axis_st = st.lists(st.floats(-1, 1, allow_nan=False), min_size=3, max_size=3).filter(
    lambda v: np.linalg.norm(v) > 1e-3).map(lambda v: np.array(v) / np.linalg.norm(v))
rotvecs_st = st.lists(st.tuples(axis_st, rotation_angle_st), min_size=1, max_size=8).map(
    lambda pairs: np.array([a * t for a, t in pairs]))


def _same_rotvec(a: np.ndarray, b: np.ndarray) -> float:
    """Largest difference of rotation vectors, where at pi v and -v are the same rotation."""
    d = np.abs(a - b).max(axis=-1)
    at_pi = np.linalg.norm(b, axis=-1) > math.pi - 1e-6
    return float(np.where(at_pi, np.minimum(d, np.abs(a + b).max(axis=-1)), d).max())


@settings(max_examples=200, deadline=None)
@given(v=rotvecs_st)
def test_stacked_rotvecs_and_matrices_against_scipy(v: np.ndarray) -> None:
    ref = Rotation.from_rotvec(v)
    R = ref.as_matrix()
    assert np.abs(matrices_from_rotvecs(v) - R).max() < 4e-15
    assert _same_rotvec(rotvecs_from_matrices(R), v) < 1e-12
    assert np.abs(rotation_angles(R) - ref.magnitude()).max() < 1e-12
    # the stacked functions agree with the one-at-a-time ones row by row
    for vk, Rk in zip(v, R, strict=True):
        assert np.abs(matrices_from_rotvecs(vk) - matrix_from_rotvec(vk)).max() < 4e-15
        assert _same_rotvec(rotvecs_from_matrices(Rk), rotvec_from_matrix(Rk)) < 1e-12


@settings(max_examples=200, deadline=None)
@given(v=rotvecs_st)
def test_stacked_quaternions_against_scipy(v: np.ndarray) -> None:
    ref = Rotation.from_rotvec(v)
    R = ref.as_matrix()
    q = quats_from_matrices(R)
    want = ref.as_quat(scalar_first=True)
    want *= np.where(want[:, :1] < 0, -1.0, 1.0)
    at_pi = np.abs(want[:, 0]) < 1e-9  # w ~ 0: q and -q are both canonical up to rounding
    d = np.abs(q - want).max(axis=1)
    d = np.where(at_pi, np.minimum(d, np.abs(q + want).max(axis=1)), d)
    assert d.max() < 1e-12
    assert np.all(q[:, 0] >= 0)
    assert np.abs(matrices_from_quats(q) - R).max() < 1e-12
    for qk, Rk in zip(q, R, strict=True):
        if not abs(qk[0]) < 1e-9:
            assert np.abs(qk - quat_from_matrix(Rk)).max() < 1e-12
    # products and conjugates: R(a * b) = R(a) R(b), R(conj a) = R(a)^T
    a, b = q, q[::-1]
    assert np.abs(matrices_from_quats(quat_multiply(a, b)) - R @ R[::-1]).max() < 1e-12
    assert np.abs(matrices_from_quats(quat_conjugate(a)) - np.swapaxes(R, 1, 2)).max() < 4e-15
    prod = (ref * ref[::-1]).as_quat(scalar_first=True)
    mine = quat_multiply(a, b)
    assert np.abs(np.abs((mine * prod).sum(axis=1)) - 1.0).max() < 1e-12  # same up to sign


def test_quaternion_at_half_turn_has_canonical_sign_stacked() -> None:
    R = np.stack([np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0])])
    assert np.array_equal(quats_from_matrices(R), [[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


@settings(max_examples=100, deadline=None)
@given(v=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3).map(np.array),
       w=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3).map(np.array))
def test_skew_vee(v: np.ndarray, w: np.ndarray) -> None:
    K = skew(v)
    assert np.array_equal(K, -K.T)
    assert np.allclose(K @ w, np.cross(v, w), rtol=1e-12, atol=1e-9)
    assert np.array_equal(vee(K), v)
    assert np.array_equal(skew(np.stack([v, w])), np.stack([K, skew(w)]))


@settings(max_examples=100, deadline=None)
@given(v=rotvecs_st)
def test_vee_of_a_rotation_is_axis_times_sine(v: np.ndarray) -> None:
    theta = np.linalg.norm(v, axis=1, keepdims=True)
    axis = np.where(theta > 0, v / np.where(theta > 0, theta, 1.0), 0.0)
    R = Rotation.from_rotvec(v).as_matrix()
    assert np.abs(vee(R) - axis * np.sin(theta)).max() < 4e-15


def test_project_rotation_is_the_nearest_rotation() -> None:
    R = RANDOM_ROTATIONS.as_matrix()[:50]
    noisy = R + RNG.normal(scale=1e-3, size=R.shape)
    P = project_rotation(noisy)
    assert np.abs(np.swapaxes(P, 1, 2) @ P - np.eye(3)).max() < 1e-14
    assert np.all(np.linalg.det(P) > 0)
    assert np.abs(P - R).max() < 1e-2
    # a reflection is mapped to a rotation, never to itself
    assert np.linalg.det(project_rotation(np.diag([1.0, 1.0, -1.0]))) > 0
    # of summed rotations: the chordal mean (scipy's Rotation.mean minimises the same)
    group = RANDOM_ROTATIONS[:1] * Rotation.from_rotvec(RNG.normal(scale=0.1, size=(20, 3)))
    mean = project_rotation(group.as_matrix().sum(axis=0))
    assert np.abs(mean - group.mean().as_matrix()).max() < 1e-12
    for Rk in R[:5]:
        assert np.abs(project_rotation(Rk) - Rk).max() < 4e-15


@settings(max_examples=100, deadline=None)
@given(v=rotvecs_st, t=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3).map(np.array))
def test_transforms_from_vectors_round_trip(v: np.ndarray, t: np.ndarray) -> None:
    vec = np.concatenate([v, np.broadcast_to(t, v.shape)], axis=1)
    T = transforms_from_vectors(vec)
    assert np.abs(T[:, :3, :3] - Rotation.from_rotvec(v).as_matrix()).max() < 4e-15
    assert np.array_equal(T[:, :3, 3], vec[:, 3:])
    assert np.array_equal(T[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (len(v), 4)))
    back = vectors_from_transforms(T)
    assert _same_rotvec(back[:, :3], v) < 1e-12
    assert np.array_equal(back[:, 3:], vec[:, 3:])
    inv = invert_transforms(T)
    for Tk, Ik in zip(T, inv, strict=True):
        assert np.abs(Ik - invert_transform(Tk)).max() < 1e-12


@settings(max_examples=100, deadline=None)
@given(v=rotvecs_st.filter(lambda v: np.linalg.norm(v, axis=1).max() < math.pi - 1e-3),
       seed=st.integers(0, 2**31))
def test_so3_jacobians_by_finite_differences(v: np.ndarray, seed: int) -> None:
    """exp(v + e) = exp(J_l(v) e) exp(v) to first order, and J_l^-1 is the inverse."""
    e = np.random.default_rng(seed).normal(size=v.shape) * 1e-7
    J = left_jacobians(v)
    lhs = Rotation.from_rotvec(v + e).as_matrix()
    rhs = Rotation.from_rotvec(np.einsum("nij,nj->ni", J, e)).as_matrix() @ Rotation.from_rotvec(
        v).as_matrix()
    assert np.abs(lhs - rhs).max() < 1e-13
    assert np.abs(inverse_left_jacobians(v) @ J - np.eye(3)).max() < 1e-12
    # the right Jacobian: exp(v + e) = exp(v) exp(J_l(-v) e)
    rhs = Rotation.from_rotvec(v).as_matrix() @ Rotation.from_rotvec(
        np.einsum("nij,nj->ni", left_jacobians(-v), e)).as_matrix()
    assert np.abs(lhs - rhs).max() < 1e-13


def test_adjoint_moves_a_small_motion_between_frames() -> None:
    T = make_transform(RANDOM_ROTATIONS[0].as_matrix(), [120.0, -40.0, 300.0])
    d = np.array([1e-6, -2e-6, 3e-6, 1e-4, 2e-4, -1e-4])
    lhs = T @ transforms_from_vectors(d) @ invert_transform(T)
    rhs = transforms_from_vectors(adjoint(T) @ d)
    # first order: what is left is |t| |w|^2 ~ 300 mm * 1e-11
    assert np.abs(lhs - rhs).max() < 1e-8
    assert np.abs(lhs - rhs).max() < 1e-3 * np.abs(lhs - np.eye(4)).max()


@settings(max_examples=100, deadline=None)
@given(v=rotvecs_st, t=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3).map(np.array))
def test_pose_errors_is_pose_error_of_a_stack(v: np.ndarray, t: np.ndarray) -> None:
    T = transforms_from_vectors(np.concatenate([v, np.broadcast_to(t, v.shape)], axis=1))
    ref = make_transform(RANDOM_ROTATIONS[1].as_matrix(), [1.0, 2.0, 3.0])
    mm, deg = pose_errors(T, ref)
    for k, Tk in enumerate(T):
        one = pose_error(Tk, ref)
        assert abs(mm[k] - one[0]) < 1e-12
        assert abs(deg[k] - one[1]) < 1e-9
    mm, deg = pose_errors(T, T)
    assert np.all(mm == 0)
    assert np.all(deg < 1e-12)
