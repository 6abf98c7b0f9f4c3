"""Rigid transforms and rotation conventions.

Naming convention: ``T_a_b`` is the pose of frame ``b`` expressed in frame ``a`` (a 4x4 float64
homogeneous matrix, translation in mm), so that a point maps as ``p_a = T_a_b @ p_b`` and poses
chain by matching inner names: ``T_a_c = T_a_b @ T_b_c`` (the chapter writes ``_A T^B``).
Rotations are 3x3 orthonormal matrices with determinant +1; angles are radians everywhere in
this module (degrees exist only in ``vgripd.geometry.vendors``).

Euler sequences use scipy's spelling: three axis letters, upper case = intrinsic (rotations
about the moving axes, ``"ZYX"``: R = Rz(a) Ry(b) Rx(c)), lower case = extrinsic (about the fixed
axes in the order given, ``"xyz"``: R = Rz(c) Ry(b) Rx(a)). At gimbal lock the first and third
angles are not separable; the convention here is third angle = 0, and the returned triple
rebuilds the same matrix.

Quaternions are unit ``(w, x, y, z)`` (``scalar_first=True``) or ``(x, y, z, w)``, with the
canonical sign ``w >= 0`` on output (q and -q are the same rotation).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from vgripd.errors import DegenerateInputError

FloatArray = npt.NDArray[np.float64]

#: Largest deviation of R^T R from identity accepted as a rotation (inputs parsed from text).
ROTATION_TOL = 1e-6
#: Largest deviation of |q| from 1 accepted (and then normalised away).
QUAT_NORM_TOL = 1e-6
#: Below this, the axis of the first Euler angle is considered aligned with the third (gimbal lock).
GIMBAL_TOL = 1e-12

_AXES = {"x": 0, "y": 1, "z": 2}
_EYE = np.eye(3)


# ---------------------------------------------------------------------- validation
def check_rotation(R: Any, what: str = "rotation", tol: float = ROTATION_TOL) -> FloatArray:
    """Return ``R`` as a (3, 3) float64 array after checking it is a proper rotation.

    Raises
    ------
    DegenerateInputError
        naming ``what`` if R has the wrong shape, is not finite, is not orthonormal within
        ``tol`` (max abs entry of R^T R - I) or is a reflection (det -1).
    """
    M = np.asarray(R, dtype=np.float64)
    if M.shape != (3, 3):
        raise DegenerateInputError(f"{what}: expected a (3, 3) rotation, got shape {M.shape}")
    if not np.isfinite(M).all():
        raise DegenerateInputError(f"{what}: rotation matrix contains NaN or inf")
    err = float(np.abs(M.T @ M - _EYE).max())
    if err > tol:
        raise DegenerateInputError(
            f"{what}: not orthonormal (max |R^T R - I| = {err:.3g} > {tol:g})")
    if np.linalg.det(M) < 0:
        raise DegenerateInputError(f"{what}: determinant is -1 (a reflection, not a rotation)")
    return M


def check_transform(T: Any, what: str = "transform", tol: float = ROTATION_TOL) -> FloatArray:
    """Return ``T`` as a (4, 4) float64 array after checking it is a rigid transform."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4):
        raise DegenerateInputError(f"{what}: expected a (4, 4) transform, got shape {M.shape}")
    if not np.isfinite(M).all():
        raise DegenerateInputError(f"{what}: transform contains NaN or inf")
    if np.abs(M[3] - (0.0, 0.0, 0.0, 1.0)).max() > tol:
        raise DegenerateInputError(f"{what}: last row must be [0, 0, 0, 1], got {M[3].tolist()}")
    check_rotation(M[:3, :3], what, tol)
    return M


# ---------------------------------------------------------------------- transforms
def make_transform(R: Any, t: Any) -> FloatArray:
    """(4, 4) transform from a (3, 3) rotation and a (3,) translation (mm)."""
    Rm = check_rotation(R, "make_transform: R")
    tv = np.asarray(t, dtype=np.float64).reshape(-1)
    if tv.shape != (3,) or not np.isfinite(tv).all():
        raise DegenerateInputError(f"make_transform: t must be 3 finite numbers, got {tv.tolist()}")
    T = np.eye(4)
    T[:3, :3] = Rm
    T[:3, 3] = tv
    return T


def invert_transform(T: Any) -> FloatArray:
    """``T_b_a`` from ``T_a_b`` (uses R^T, not a general matrix inverse)."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4):
        raise DegenerateInputError(f"invert_transform: expected (4, 4), got {M.shape}")
    out = np.eye(4)
    out[:3, :3] = M[:3, :3].T
    out[:3, 3] = -M[:3, :3].T @ M[:3, 3]
    return out


def compose(*Ts: Any) -> FloatArray:
    """Product of transforms left to right: ``compose(T_a_b, T_b_c, T_c_d) = T_a_d``."""
    if not Ts:
        raise DegenerateInputError("compose: need at least one transform")
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    if out.shape != (4, 4):
        raise DegenerateInputError(f"compose: expected (4, 4) transforms, got {out.shape}")
    return out


def transform_points(T: Any, pts: Any) -> FloatArray:
    """Map (n, 3) points from frame b to frame a with ``T_a_b``: ``p_a = R p_b + t``."""
    M = np.asarray(T, dtype=np.float64)
    P = np.asarray(pts, dtype=np.float64)
    if M.shape != (4, 4):
        raise DegenerateInputError(f"transform_points: expected a (4, 4) transform, got {M.shape}")
    if P.ndim != 2 or P.shape[1] != 3:
        raise DegenerateInputError(f"transform_points: expected (n, 3) points, got {P.shape}")
    return P @ M[:3, :3].T + M[:3, 3]


def solve_loop(known: Mapping[tuple[str, str], Any], a: str, b: str) -> FloatArray:
    """The one unknown transform ``T_a_b`` of a closed loop of known transforms (chapter Fig. 6).

    ``known`` maps frame pairs ``(x, y)`` to ``T_x_y``; each can be walked in either direction
    (``T_y_x`` is its inverse). The shortest chain of known transforms from ``a`` to ``b`` closes
    the loop, and ``T_a_b`` is their product. The chapter's example, with ``T_A_B``, ``T_B_C``
    and ``T_A_D`` known: ``solve_loop(known, "D", "C")`` walks D -> A -> B -> C and returns
    ``inv(T_A_D) @ T_A_B @ T_B_C``.

    Raises
    ------
    DegenerateInputError
        if no chain connects ``a`` to ``b`` (the message lists the frames reachable from ``a``),
        or a transform on the chain is not rigid.
    """
    neighbours: dict[str, list[str]] = {}
    for x, y in known:
        neighbours.setdefault(x, []).append(y)
        neighbours.setdefault(y, []).append(x)
    # Breadth-first search gives the shortest chain, so the fewest measured transforms multiply.
    came: dict[str, str] = {}
    queue = deque([a])
    while queue and b not in came and b != a:
        f = queue.popleft()
        for g in neighbours.get(f, []):
            if g != a and g not in came:
                came[g] = f
                queue.append(g)
    if b != a and b not in came:
        raise DegenerateInputError(
            f"solve_loop: no chain of known transforms from {a!r} to {b!r}; "
            f"frames reachable from {a!r}: {sorted({a, *came})}")
    chain: list[FloatArray] = []
    f = b
    while f != a:
        prev = came[f]
        if (prev, f) in known:
            chain.append(check_transform(known[prev, f], f"solve_loop: T_{prev}_{f}"))
        else:
            chain.append(invert_transform(
                check_transform(known[f, prev], f"solve_loop: T_{f}_{prev}")))
        f = prev
    return compose(np.eye(4), *reversed(chain))


# ---------------------------------------------------------------------- elementary rotations
def _axis_matrix(axis: int, angle: float) -> FloatArray:
    """Rotation by ``angle`` (rad) about coordinate axis 0, 1 or 2."""
    c, s = math.cos(angle), math.sin(angle)
    l, m = (axis + 1) % 3, (axis + 2) % 3
    R = np.eye(3)
    R[l, l] = c
    R[m, m] = c
    R[m, l] = s
    R[l, m] = -s
    return R


def _angle_about(axis: int, R: FloatArray) -> float:
    """Angle of a rotation known to be about coordinate ``axis`` (inverse of ``_axis_matrix``)."""
    l, m = (axis + 1) % 3, (axis + 2) % 3
    return math.atan2(R[m, l] - R[l, m], R[l, l] + R[m, m])


def _cross_at(u: FloatArray, v: FloatArray, i: int) -> float:
    """Component i of the cross product u x v (np.cross is slow for single 3-vectors)."""
    j, k = (i + 1) % 3, (i + 2) % 3
    return float(u[j] * v[k] - u[k] * v[j])


def _cross(u: FloatArray, v: FloatArray) -> FloatArray:
    return np.array([_cross_at(u, v, 0), _cross_at(u, v, 1), _cross_at(u, v, 2)])


def _parse_seq(seq: str) -> tuple[tuple[int, int, int], bool]:
    """Axis indices of an Euler sequence and whether it is extrinsic (lower case)."""
    if (len(seq) != 3 or not (seq.isupper() or seq.islower())
            or any(ch not in _AXES for ch in seq.lower())):
        raise DegenerateInputError(
            f"Euler sequence {seq!r}: expected 3 letters from x, y, z, all upper case (intrinsic) "
            "or all lower case (extrinsic)")
    i, j, k = (_AXES[ch] for ch in seq.lower())
    if i == j or j == k:
        raise DegenerateInputError(f"Euler sequence {seq!r}: consecutive axes must differ")
    return (i, j, k), seq.islower()


def matrix_from_euler(seq: str, angles: Sequence[float]) -> FloatArray:
    """Rotation matrix from three Euler angles (rad) in sequence ``seq`` (see module docstring).

    ``matrix_from_euler("ZYX", (a, b, c)) = Rz(a) Ry(b) Rx(c)``;
    ``matrix_from_euler("xyz", (a, b, c)) = Rz(c) Ry(b) Rx(a)``.
    """
    (i, j, k), extrinsic = _parse_seq(seq)
    a, b, c = (float(v) for v in angles)
    if extrinsic:  # about fixed i, j, k in turn == about moving k, j, i
        (i, k), (a, c) = (k, i), (c, a)
    return _axis_matrix(i, a) @ _axis_matrix(j, b) @ _axis_matrix(k, c)


def euler_from_matrix(seq: str, R: Any) -> tuple[float, float, float]:
    """Euler angles (rad) of a rotation in sequence ``seq``; inverse of ``matrix_from_euler``.

    The middle angle is in [-pi/2, pi/2] for Tait-Bryan sequences (three different axes) and in
    [0, pi] for proper Euler sequences (first axis = last axis); the others in (-pi, pi].
    At gimbal lock (middle angle +-pi/2, resp. 0 or pi) the third angle (the first one for
    extrinsic sequences, which are the reversed intrinsic ones) is set to 0 and the other two
    still rebuild ``R``.
    """
    (i, j, k), extrinsic = _parse_seq(seq)
    if extrinsic:
        i, k = k, i
    M = check_rotation(R, f"euler_from_matrix({seq!r})")
    e = _EYE
    # R e_k = Ri(a) Rj(b) e_k does not depend on c. Its part perpendicular to axis i is
    # Ri(a) applied to a reference direction (e_k for Tait-Bryan, e_j x e_i for proper Euler)
    # scaled by cos b resp. sin b >= 0, so a is the angle from that reference about axis i.
    v = M[:, k]
    ref = e[k] if i != k else _cross(e[j], e[i])
    sin_part = _cross_at(ref, v, i)
    cos_part = float(ref @ v)
    if math.hypot(sin_part, cos_part) > GIMBAL_TOL:
        a = math.atan2(sin_part, cos_part)
        w = _axis_matrix(i, a).T @ v  # = Rj(b) e_k
        b = math.atan2(_cross_at(e[k], w, j), float(e[k] @ w))
        # c from what is left, so that the triple rebuilds M even where a is ill-conditioned.
        c = _angle_about(k, (_axis_matrix(i, a) @ _axis_matrix(j, b)).T @ M)
    else:
        # Gimbal lock: axes i and k are aligned; take c = 0, then M = Ri(a) Rj(b) and
        # M e_j = Ri(a) e_j fixes a.
        u = M[:, j]
        a = math.atan2(_cross_at(e[j], u, i), float(e[j] @ u))
        b = _angle_about(j, _axis_matrix(i, a).T @ M)
        c = 0.0
    return (c, b, a) if extrinsic else (a, b, c)


def matrix_from_euler_zyx(a: float, b: float, c: float) -> FloatArray:
    """``Rz(a) Ry(b) Rx(c)`` (rad): KUKA's A, B, C (intrinsic Z, Y', X'')."""
    return matrix_from_euler("ZYX", (a, b, c))


def euler_zyx_from_matrix(R: Any) -> tuple[float, float, float]:
    """``(a, b, c)`` (rad), ``R = Rz(a) Ry(b) Rx(c)``, b in [-pi/2, pi/2]; c = 0 at b = +-pi/2."""
    return euler_from_matrix("ZYX", R)


# ---------------------------------------------------------------------- quaternions
def _quat_wxyz(q: Any, scalar_first: bool) -> FloatArray:
    qv = np.asarray(q, dtype=np.float64).reshape(-1)
    if qv.shape != (4,) or not np.isfinite(qv).all():
        raise DegenerateInputError(f"quaternion: expected 4 finite numbers, got {qv.tolist()}")
    if not scalar_first:
        qv = np.roll(qv, 1)
    n = float(np.linalg.norm(qv))
    if abs(n - 1.0) > QUAT_NORM_TOL:
        raise DegenerateInputError(
            f"quaternion {qv.tolist()} (w, x, y, z) is not unit length: |q| = {n:.9g}")
    return qv / n


def matrix_from_quat(q: Any, scalar_first: bool = True) -> FloatArray:
    """Rotation matrix of a unit quaternion, (w, x, y, z) or (x, y, z, w).

    A norm within ``QUAT_NORM_TOL`` of 1 is normalised away (rounding in transmitted values);
    anything further off is an error, because silently normalising would hide corrupt input.
    """
    w, x, y, z = _quat_wxyz(q, scalar_first)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quat_from_matrix(R: Any, scalar_first: bool = True) -> FloatArray:
    """Unit quaternion (4,) of a rotation, with canonical sign.

    Shepperd's method: start from the largest of w, x, y, z so no component is computed from a
    small difference (accurate near 0 and near pi). Canonical sign: w >= 0, and for w == 0 the
    first non-zero of x, y, z positive.
    """
    M = check_rotation(R, "quat_from_matrix")
    tr = M[0, 0] + M[1, 1] + M[2, 2]
    cand = (tr, M[0, 0], M[1, 1], M[2, 2])
    best = int(np.argmax(cand))
    if best == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [s / 4, (M[2, 1] - M[1, 2]) / s, (M[0, 2] - M[2, 0]) / s, (M[1, 0] - M[0, 1]) / s]
    else:
        i = best - 1
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + M[i, i] - M[j, j] - M[k, k], 0.0))
        q = [0.0] * 4
        q[0] = (M[k, j] - M[j, k]) / s
        q[1 + i] = s / 4
        q[1 + j] = (M[j, i] + M[i, j]) / s
        q[1 + k] = (M[k, i] + M[i, k]) / s
    qa = np.array(q)
    qa /= np.linalg.norm(qa)
    nz = qa[np.nonzero(qa)]
    if nz.size and nz[0] < 0:
        qa = -qa
    return qa if scalar_first else np.roll(qa, -1)


# ---------------------------------------------------------------------- rotation vectors
def matrix_from_rotvec(v: Any) -> FloatArray:
    """Rotation matrix of a rotation vector (axis * angle, rad); exact for tiny angles."""
    vv = np.asarray(v, dtype=np.float64).reshape(-1)
    if vv.shape != (3,) or not np.isfinite(vv).all():
        raise DegenerateInputError(f"rotation vector: expected 3 finite numbers, got {vv.tolist()}")
    theta = float(np.linalg.norm(vv))
    # sin(theta/2)/theta written with np.sinc, which is exact at theta = 0.
    half_sinc = 0.5 * float(np.sinc(theta / (2.0 * math.pi)))
    q = np.concatenate(([math.cos(theta / 2.0)], vv * half_sinc))
    return matrix_from_quat(q / np.linalg.norm(q))


def rotvec_from_matrix(R: Any) -> FloatArray:
    """Rotation vector (3,) of a rotation, angle in [0, pi]; via the quaternion, so it is accurate
    near 0 (no 0/0) and near pi (no loss of the axis from a tiny antisymmetric part)."""
    w, x, y, z = quat_from_matrix(R)
    s = math.sqrt(x * x + y * y + z * z)
    theta = 2.0 * math.atan2(s, w)
    # theta / sin(theta/2) -> 2 as theta -> 0; s = sin(theta/2).
    scale = theta / s if s > 1e-300 else 2.0
    return np.array([x, y, z]) * scale


def rotation_angle(R: Any) -> float:
    """Angle of a rotation in [0, pi] (rad), accurate at both ends (unlike acos of the trace)."""
    w, x, y, z = quat_from_matrix(R)
    return 2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), abs(w))


def pose_error(T: Any, T_ref: Any) -> tuple[float, float]:
    """How far pose ``T`` is from ``T_ref``: (translation distance, rotation angle in degrees).

    The distance is in the transforms' length unit (mm inside vgripd); the angle is that of the
    relative rotation ``R_ref^T R``. The one pose-error measure of the project: tests, benches,
    the demo and the calibration reports all use it.
    """
    A = np.asarray(T, dtype=float)
    B = np.asarray(T_ref, dtype=float)
    return (float(np.linalg.norm(A[:3, 3] - B[:3, 3])),
            math.degrees(rotation_angle(B[:3, :3].T @ A[:3, :3])))
