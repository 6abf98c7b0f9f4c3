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


# ---------------------------------------------------------------------- stacked helpers
# Vectorised over any leading axes and unchecked: the callers (the hand-eye solvers and
# refinements, Horn's method) pass rotations they built themselves and call these on stacks,
# often thousands of times, where the validating one-at-a-time functions above would cost more
# than the arithmetic. Same conventions: (w, x, y, z) quaternions, rotation vectors in rad,
# 6-vectors ``(rotation vector, translation)``.

#: Below this angle (rad) the series of the Rodrigues / Jacobian coefficients are used.
_SERIES_ANGLE = 1e-2


def skew(v: Any) -> FloatArray:
    """Cross-product matrices ``[v]x`` (``[v]x @ u == v x u``) of (..., 3) vectors, (..., 3, 3)."""
    a = np.asarray(v, dtype=np.float64)
    out = np.zeros((*a.shape[:-1], 3, 3))
    x, y, z = a[..., 0], a[..., 1], a[..., 2]
    out[..., 0, 1], out[..., 0, 2] = -z, y
    out[..., 1, 0], out[..., 1, 2] = z, -x
    out[..., 2, 0], out[..., 2, 1] = -y, x
    return out


def vee(M: Any) -> FloatArray:
    """The vector of the antisymmetric part of (..., 3, 3) matrices: ``vee(skew(v)) == v``; for
    a rotation by ``angle`` about unit ``axis`` it is ``axis * sin(angle)``."""
    a = np.asarray(M, dtype=np.float64)
    return 0.5 * np.stack([a[..., 2, 1] - a[..., 1, 2], a[..., 0, 2] - a[..., 2, 0],
                           a[..., 1, 0] - a[..., 0, 1]], axis=-1)


def project_rotation(M: Any) -> FloatArray:
    """The rotation nearest (Frobenius norm) to each (..., 3, 3) matrix: ``U diag(1, 1, d) V^T``
    from its SVD, ``d = det(U V^T)`` so that the result is never a reflection. Of a sum of
    rotations this is their chordal mean."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    d = np.where(np.linalg.det(U @ Vt) < 0, -1.0, 1.0)
    out: FloatArray = (U * np.stack([np.ones_like(d), np.ones_like(d), d], axis=-1)[..., None, :]
                       ) @ Vt
    return out


def quat_multiply(a: Any, b: Any) -> FloatArray:
    """Hamilton products ``a * b`` of (..., 4) quaternions (w, x, y, z); the rotation of the
    product is ``R(a) @ R(b)``."""
    p = np.asarray(a, dtype=np.float64)
    q = np.asarray(b, dtype=np.float64)
    w = p[..., :1] * q[..., :1] - (p[..., 1:] * q[..., 1:]).sum(axis=-1, keepdims=True)
    v = p[..., :1] * q[..., 1:] + q[..., :1] * p[..., 1:] + np.cross(p[..., 1:], q[..., 1:])
    return np.concatenate([w, v], axis=-1)


def quat_conjugate(q: Any) -> FloatArray:
    """Conjugates of (..., 4) quaternions (w, x, y, z): the inverse rotations of unit ones."""
    out: FloatArray = np.asarray(q, dtype=np.float64) * np.array([1.0, -1.0, -1.0, -1.0])
    return out


def _canonical_quats(q: FloatArray) -> FloatArray:
    """Sign rule of :func:`quat_from_matrix` on (..., 4): w > 0, or for w == 0 the first
    non-zero of x, y, z positive."""
    first = np.take_along_axis(q[..., 1:], np.argmax(q[..., 1:] != 0, axis=-1)[..., None],
                               axis=-1)[..., 0]
    lead = np.where(q[..., 0] != 0, q[..., 0], first)
    out: FloatArray = q * np.where(lead < 0, -1.0, 1.0)[..., None]
    return out


def quats_from_matrices(R: Any) -> FloatArray:
    """Unit quaternions (..., 4) (w, x, y, z) of (..., 3, 3) rotations, with the canonical sign
    of :func:`quat_from_matrix`.

    The eigenvector of the largest eigenvalue of Bar-Itzhack's symmetric 4x4 matrix: accurate
    at every angle, and for a matrix slightly off orthonormal (a product of measured rotations)
    the quaternion of the nearest rotation.
    """
    M = np.asarray(R, dtype=np.float64)
    xx, xy, xz = M[..., 0, 0], M[..., 0, 1], M[..., 0, 2]
    yx, yy, yz = M[..., 1, 0], M[..., 1, 1], M[..., 1, 2]
    zx, zy, zz = M[..., 2, 0], M[..., 2, 1], M[..., 2, 2]
    K = np.stack([
        np.stack([xx - yy - zz, yx + xy, zx + xz, zy - yz], axis=-1),
        np.stack([yx + xy, yy - xx - zz, zy + yz, xz - zx], axis=-1),
        np.stack([zx + xz, zy + yz, zz - xx - yy, yx - xy], axis=-1),
        np.stack([zy - yz, xz - zx, yx - xy, xx + yy + zz], axis=-1)], axis=-2) / 3.0
    v = np.linalg.eigh(K)[1][..., :, 3]  # (x, y, z, w)
    return _canonical_quats(np.concatenate([v[..., 3:], v[..., :3]], axis=-1))


def matrices_from_quats(q: Any) -> FloatArray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) (w, x, y, z); the norm is not
    checked (see :func:`matrix_from_quat` for parsed input)."""
    a = np.asarray(q, dtype=np.float64)
    w, x, y, z = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def matrices_from_rotvecs(v: Any) -> FloatArray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (axis * angle, rad): the
    exponential map of SO(3), Rodrigues' formula ``I + sin(t)/t K + (1 - cos t)/t^2 K^2`` with
    both coefficients written through ``np.sinc`` (exact at t = 0)."""
    a = np.asarray(v, dtype=np.float64)
    theta = np.linalg.norm(a, axis=-1)[..., None, None]
    K = skew(a)
    half = np.sinc(theta / (2.0 * np.pi))
    out: FloatArray = np.eye(3) + np.sinc(theta / np.pi) * K + 0.5 * half * half * (K @ K)
    return out


def rotation_angles(R: Any) -> FloatArray:
    """Angles in [0, pi] (rad) of (..., 3, 3) rotations: ``atan2(|vee R|, (trace R - 1) / 2)``,
    accurate at both ends (the sine carries small angles, the cosine angles near pi)."""
    M = np.asarray(R, dtype=np.float64)
    out: FloatArray = np.arctan2(np.linalg.norm(vee(M), axis=-1),
                                 (np.trace(M, axis1=-2, axis2=-1) - 1.0) / 2.0)
    return out


def rotvecs_from_matrices(R: Any) -> FloatArray:
    """Rotation vectors (..., 3), angle in [0, pi], of (..., 3, 3) rotations: the logarithm of
    SO(3). Up to 90 deg the axis is the antisymmetric part's direction; beyond, where that part
    shrinks to nothing at pi, it is the dominant column of the symmetric part
    ``(R + R^T) / 2 - cos(angle) I = (1 - cos(angle)) axis axis^T``, signed by the
    antisymmetric part. At exactly pi the sign of the axis is arbitrary."""
    M = np.asarray(R, dtype=np.float64)
    w = vee(M)
    s = np.linalg.norm(w, axis=-1)
    c = (np.trace(M, axis1=-2, axis2=-1) - 1.0) / 2.0
    theta = np.arctan2(s, c)
    # theta / sin(theta) -> 1 at 0; only used where c >= 0, so s > 0 unless theta == 0.
    scale = np.where(s > 0, theta / np.where(s > 0, s, 1.0), 1.0)
    out: FloatArray = w * scale[..., None]
    wide = c < 0
    if np.any(wide):
        S = 0.5 * (M[wide] + np.swapaxes(M[wide], -1, -2)) - c[wide][:, None, None] * np.eye(3)
        diag = np.diagonal(S, axis1=-2, axis2=-1)
        k = np.argmax(diag, axis=-1)
        col = np.take_along_axis(S, k[:, None, None], axis=-1)[..., 0]
        pick = np.take_along_axis(diag, k[:, None], axis=-1)[:, 0]
        axis = col / np.sqrt(pick * (1.0 - c[wide]))[:, None]
        axis *= np.where((axis * w[wide]).sum(axis=-1) < 0, -1.0, 1.0)[:, None]
        out[wide] = axis * theta[wide][:, None]
    return out


def transforms_from_vectors(v: Any) -> FloatArray:
    """(..., 4, 4) transforms of (..., 6) vectors ``(rotation vector rad, translation)``.

    The rotation is SO(3)'s exponential, the translation is taken as is (not the screw motion
    of SE(3)'s exponential): the small-motion parametrisation of the refinements, whose
    inverse is :func:`vectors_from_transforms`.
    """
    a = np.asarray(v, dtype=np.float64)
    out = np.zeros((*a.shape[:-1], 4, 4))
    out[..., :3, :3] = matrices_from_rotvecs(a[..., :3])
    out[..., :3, 3] = a[..., 3:]
    out[..., 3, 3] = 1.0
    return out


def vectors_from_transforms(T: Any) -> FloatArray:
    """(..., 6) vectors ``(rotation vector rad, translation)`` of (..., 4, 4) transforms; the
    inverse of :func:`transforms_from_vectors`."""
    M = np.asarray(T, dtype=np.float64)
    return np.concatenate([rotvecs_from_matrices(M[..., :3, :3]), M[..., :3, 3]], axis=-1)


def invert_transforms(T: Any) -> FloatArray:
    """:func:`invert_transform` of a (..., 4, 4) stack (R^T, -R^T t)."""
    M = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(M)
    Rt = np.swapaxes(M[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ M[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def adjoint(T: Any) -> FloatArray:
    """(..., 6, 6) adjoint maps of (..., 4, 4) transforms ``T_a_b``: a small motion
    ``(rotation rad, translation)`` expressed in frame b, ``T_a_b @ exp(d) @ T_b_a``, is the
    motion ``adjoint(T_a_b) @ d`` expressed in frame a (to first order)."""
    M = np.asarray(T, dtype=np.float64)
    R, t = M[..., :3, :3], M[..., :3, 3]
    out = np.zeros((*M.shape[:-2], 6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = skew(t) @ R
    return out


def _jacobian_coefficients(theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(1 - cos t) / t^2``, ``(t - sin t) / t^3`` and ``(1 - (t/2) cot(t/2)) / t^2`` of
    SO(3)'s Jacobians, with their series below ``_SERIES_ANGLE``."""
    t = np.where(theta < _SERIES_ANGLE, _SERIES_ANGLE, theta)  # keeps the unused branch finite
    t2 = theta * theta
    half = np.sinc(theta / (2.0 * np.pi))
    b = 0.5 * half * half
    c = np.where(theta < _SERIES_ANGLE, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0,
                 (t - np.sin(t)) / t**3)
    d = np.where(theta < _SERIES_ANGLE, 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
                 (1.0 - 0.5 * t * np.cos(0.5 * t) / np.sin(0.5 * t)) / (t * t))
    return b, c, d


def left_jacobians(v: Any) -> FloatArray:
    """(..., 3, 3) left Jacobians of SO(3) at rotation vectors (..., 3):
    ``matrix_from_rotvec(v + e) = matrix_from_rotvec(J e) @ matrix_from_rotvec(v)`` to first
    order in ``e``. The right Jacobian is ``left_jacobians(-v)``."""
    a = np.asarray(v, dtype=np.float64)
    b, c, _ = _jacobian_coefficients(np.linalg.norm(a, axis=-1)[..., None, None])
    K = skew(a)
    out: FloatArray = np.eye(3) + b * K + c * (K @ K)
    return out


def inverse_left_jacobians(v: Any) -> FloatArray:
    """Inverses of :func:`left_jacobians` (..., 3, 3): how the rotation vector of
    ``matrix_from_rotvec(e) @ R`` changes with a small ``e`` (``v`` = rotation vector of R,
    angle below pi)."""
    a = np.asarray(v, dtype=np.float64)
    _, _, d = _jacobian_coefficients(np.linalg.norm(a, axis=-1)[..., None, None])
    K = skew(a)
    out: FloatArray = np.eye(3) - 0.5 * K + d * (K @ K)
    return out


def pose_errors(T: Any, T_ref: Any) -> tuple[FloatArray, FloatArray]:
    """:func:`pose_error` of stacks: (..., 4, 4) poses against (..., 4, 4) references
    (broadcast); returns (translation distances, rotation angles in degrees)."""
    A = np.asarray(T, dtype=np.float64)
    B = np.asarray(T_ref, dtype=np.float64)
    mm: FloatArray = np.linalg.norm(A[..., :3, 3] - B[..., :3, 3], axis=-1)
    deg: FloatArray = np.degrees(rotation_angles(np.swapaxes(B[..., :3, :3], -1, -2)
                                                 @ A[..., :3, :3]))
    return mm, deg
