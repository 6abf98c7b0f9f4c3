"""The linear AX = XB solvers (Tsai, Park, Horaud, Andreff, Daniilidis) and the motion checks
that say whether the robot poses can determine X at all.

Written here rather than called from OpenCV: opencv-python 5.0.0.93 ships without the
``calibrateHandEye`` binding (opencv/opencv#29565), and these are short. Every solver works on
the relative motions of all sample pairs, ``A X = X B`` with ``A = P_j^-1 P_i`` and
``B = B_j B_i^-1`` (see the package docstring for ``P_i`` and ``B_i``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from vgripd.calib.handeye.samples import FloatArray, Sample, anchor_poses, label, number
from vgripd.errors import CalibrationError, DegenerateInputError
from vgripd.geometry.transforms import (
    check_transform,
    invert_transforms,
    make_transform,
    matrices_from_quats,
    project_rotation,
    quat_conjugate,
    quat_multiply,
    quats_from_matrices,
    rotvecs_from_matrices,
    skew,
)

MIN_SAMPLES = 3  # two independent motions (three poses) are the least AX = XB can solve
FEW_SAMPLES = 8  # below this, one bad sample moves the result a lot
#: No pair of samples rotating more than this (deg): the rotation of X is not observable.
NO_ROTATION_DEG = 0.5
#: Relative rotation axes within this angle (deg) of one direction count as parallel.
PARALLEL_AXES_DEG = 5.0


# ---------------------------------------------------------------------- motion checks
def check_motion(samples: Sequence[Sample], mode: str,
                 min_rotation_deg: float = 5.0) -> list[str]:
    """Warnings about the robot motions; CalibrationError when they cannot determine X.

    Raises
    ------
    CalibrationError
        fewer than ``MIN_SAMPLES`` samples, or no two samples rotated against each other by
        more than ``NO_ROTATION_DEG`` (identical orientations: X's rotation is not observable).
    """
    n = len(samples)
    if n < MIN_SAMPLES:
        raise CalibrationError(
            f"hand-eye needs at least {MIN_SAMPLES} samples (robot poses with the board seen), "
            f"got {n}")
    warnings = []
    if n < FEW_SAMPLES:
        warnings.append(f"only {n} samples; {FEW_SAMPLES} or more with varied rotations make "
                        "the result less sensitive to one bad sample")
    q = quats_from_matrices(anchor_poses(samples, mode)[:, :3, :3])
    i, j = np.triu_indices(n, 1)
    rel = quat_multiply(quat_conjugate(q[i]), q[j])  # rotation of P_i^-1 P_j, mount frame
    s = np.linalg.norm(rel[:, 1:], axis=1)
    angle = np.degrees(2.0 * np.arctan2(s, np.abs(rel[:, 0])))
    best = int(np.argmax(angle))
    if angle[best] <= NO_ROTATION_DEG:
        raise CalibrationError(
            f"hand-eye: the robot poses barely rotate (largest relative rotation "
            f"{angle[best]:.3g} deg, between {label(samples, int(i[best]))} and "
            f"{label(samples, int(j[best]))}); rotate the flange about at least two "
            "different axes between samples")
    consecutive = np.flatnonzero((j == i + 1) & (angle < min_rotation_deg))
    if consecutive.size:
        shown = ", ".join(f"{number(samples, int(i[k]))}-{number(samples, int(j[k]))} "
                          f"({angle[k]:.2g} deg)" for k in consecutive[:5])
        more = f" and {consecutive.size - 5} more" if consecutive.size > 5 else ""
        warnings.append(
            f"{consecutive.size} consecutive sample pair(s) rotate less than "
            f"{min_rotation_deg:g} deg: {shown}{more}; such pairs add little and their noise "
            "weighs heavily in the linear solvers")
    useful = angle >= min_rotation_deg
    if not useful.any():
        warnings.append(f"no two samples rotate by {min_rotation_deg:g} deg or more against "
                        "each other; the result is poorly determined")
    else:
        axes = rel[useful, 1:] / s[useful, None]
        scatter = axes.T @ axes
        lam = np.linalg.eigvalsh(scatter)  # ascending
        spread = math.degrees(math.atan(math.sqrt(max(lam[1], 0.0) / lam[2])))
        if spread < PARALLEL_AXES_DEG:
            axis = np.linalg.eigh(scatter)[1][:, 2]
            frame = "flange" if mode == "eye-in-hand" else "base"
            warnings.append(
                f"all relative rotations are about nearly the same axis ({frame} frame "
                f"direction {np.round(axis, 3).tolist()}, spread {spread:.2g} deg): the "
                "translation along it is not determined; rotate about other axes too")
    return warnings


# ---------------------------------------------------------------------- linear solvers
def _motions(P: FloatArray, B: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(m, 4, 4) A and B of all pairs i < j."""
    i, j = np.triu_indices(len(P), 1)
    return invert_transforms(P[j]) @ P[i], B[j] @ invert_transforms(B[i])


def _translation(A: FloatArray, Bm: FloatArray, R: FloatArray) -> FloatArray:
    """t_X from (R_A - I) t_X = R_X t_B - t_A, least squares over all motions."""
    lhs = (A[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    rhs = (Bm[:, :3, 3] @ R.T - A[:, :3, 3]).reshape(-1)
    return np.asarray(np.linalg.lstsq(lhs, rhs, rcond=None)[0], dtype=np.float64)


def _rotation_tsai(A: FloatArray, Bm: FloatArray) -> FloatArray:
    """Tsai & Lenz (1989): modified Rodrigues vectors 2 sin(theta/2) * axis; the rotation's
    vector p solves [pA + pB]x p' = pB - pA with p = 2 p' / sqrt(1 + |p'|^2)."""
    pa = 2.0 * quats_from_matrices(A[:, :3, :3])[:, 1:]  # w >= 0: angles in [0, pi]
    pb = 2.0 * quats_from_matrices(Bm[:, :3, :3])[:, 1:]
    prime = np.asarray(np.linalg.lstsq(skew(pa + pb).reshape(-1, 3), (pb - pa).reshape(-1),
                                       rcond=None)[0], dtype=np.float64)
    p = 2.0 * prime / math.sqrt(1.0 + float(prime @ prime))
    n2 = float(p @ p)
    R = ((1.0 - n2 / 2.0) * np.eye(3)
         + 0.5 * (np.outer(p, p) + math.sqrt(max(4.0 - n2, 0.0)) * skew(p)))
    return project_rotation(R)


def _rotation_park(A: FloatArray, Bm: FloatArray) -> FloatArray:
    """Park & Martin (1994): R_A R_X = R_X R_B means alpha = R_X beta for the rotation vectors
    alpha = log R_A, beta = log R_B; R_X is the rotation nearest sum alpha beta^T (the
    orthogonal Procrustes solution, Park's (M^T M)^(-1/2) M^T with M = sum beta alpha^T)."""
    M = np.einsum("ki,kj->ij", rotvecs_from_matrices(A[:, :3, :3]),
                  rotvecs_from_matrices(Bm[:, :3, :3]))
    return project_rotation(M)


def _quat_left(q: FloatArray) -> FloatArray:
    """(m, 4, 4) matrices L(q) with q * p = L(q) p (w, x, y, z)."""
    w, x, y, z = q.T
    return np.stack([np.stack([w, -x, -y, -z], 1), np.stack([x, w, -z, y], 1),
                     np.stack([y, z, w, -x], 1), np.stack([z, -y, x, w], 1)], axis=1)


def _quat_right(q: FloatArray) -> FloatArray:
    """(m, 4, 4) matrices R(q) with p * q = R(q) p (w, x, y, z)."""
    w, x, y, z = q.T
    return np.stack([np.stack([w, -x, -y, -z], 1), np.stack([x, w, z, -y], 1),
                     np.stack([y, -z, w, x], 1), np.stack([z, y, -x, w], 1)], axis=1)


def _rotation_horaud(A: FloatArray, Bm: FloatArray) -> FloatArray:
    """Horaud & Dornaika (1995), rotation part: q_A * q_X = q_X * q_B is linear in q_X; q_X is
    the unit vector minimising the stacked equations (smallest eigenvector)."""
    qa, qb = quats_from_matrices(A[:, :3, :3]), quats_from_matrices(Bm[:, :3, :3])
    M = (_quat_left(qa) - _quat_right(qb)).reshape(-1, 4)
    q = np.linalg.eigh(M.T @ M)[1][:, 0]
    return matrices_from_quats(q / np.linalg.norm(q))


def _rotation_andreff(A: FloatArray, Bm: FloatArray) -> FloatArray:
    """Andreff, Horaud & Espiau (2001): R_A R_X R_B^T = R_X is linear in vec(R_X):
    (I - R_A kron R_B) vec(R_X) = 0; the null vector, rescaled and projected onto SO(3)."""
    K = np.eye(9) - np.einsum("kij,klm->kiljm", A[:, :3, :3], Bm[:, :3, :3]).reshape(-1, 9, 9)
    v = np.linalg.svd(K.reshape(-1, 9), full_matrices=False)[2][-1].reshape(3, 3)
    return project_rotation(v * np.sign(np.linalg.det(v)))


def _solve_daniilidis(A: FloatArray, Bm: FloatArray) -> FloatArray:
    """Daniilidis (1999): rotation and translation together as a unit dual quaternion.

    Each motion gives 6 linear equations in the 8 numbers (q, q') of X; the solution lies in
    the span of the two smallest right singular vectors, fixed by |q| = 1 and q . q' = 0.
    """
    def dual(T: FloatArray) -> tuple[FloatArray, FloatArray]:
        q = quats_from_matrices(T[:, :3, :3])
        tq = np.concatenate([np.zeros((len(T), 1)), T[:, :3, 3]], axis=1)
        return q, 0.5 * quat_multiply(tq, q)

    qa, da = dual(A)
    qb, db = dual(Bm)
    flip = np.sign(qa[:, :1] * qb[:, :1]) + (qa[:, :1] * qb[:, :1] == 0)  # same scalar sign
    qb, db = qb * flip, db * flip
    m = len(A)
    S = np.zeros((m, 6, 8))
    S[:, :3, 0] = qa[:, 1:] - qb[:, 1:]
    S[:, :3, 1:4] = skew(qa[:, 1:] + qb[:, 1:])
    S[:, 3:, 0] = da[:, 1:] - db[:, 1:]
    S[:, 3:, 1:4] = skew(da[:, 1:] + db[:, 1:])
    S[:, 3:, 4:] = S[:, :3, :4]
    V = np.linalg.svd(S.reshape(-1, 8), full_matrices=False)[2]
    (u1, v1), (u2, v2) = (V[6, :4], V[6, 4:]), (V[7, :4], V[7, 4:])
    # lambda1 v7 + lambda2 v8 with s = lambda1 / lambda2: s^2 u1.v1 + s (u1.v2 + u2.v1) + u2.v2 = 0
    roots = np.roots([u1 @ v1, u1 @ v2 + u2 @ v1, u2 @ v2])
    roots = roots[np.isreal(roots)].real
    if roots.size == 0:
        raise CalibrationError("daniilidis: no real solution (motions too noisy or degenerate)")
    norms = [s * s * (u1 @ u1) + 2 * s * (u1 @ u2) + u2 @ u2 for s in roots]
    k = int(np.argmax(norms))
    l2 = 1.0 / math.sqrt(norms[k])
    l1 = roots[k] * l2
    q, d = l1 * u1 + l2 * u2, l1 * v1 + l2 * v2
    t = 2.0 * quat_multiply(d, quat_conjugate(q))[1:]
    return make_transform(matrices_from_quats(q / np.linalg.norm(q)), t)


_ROTATION_SOLVERS: dict[str, Callable[[FloatArray, FloatArray], FloatArray]] = {
    "tsai": _rotation_tsai,
    "park": _rotation_park,
    "horaud": _rotation_horaud,
    "andreff": _rotation_andreff,
}
#: The linear AX = XB solvers, in the order they are tried (ties go to the earlier one).
SOLVERS = (*_ROTATION_SOLVERS, "daniilidis")


def solve_linear(P: FloatArray, B: FloatArray, method: str) -> FloatArray:
    """X of ``P_i X B_i = const`` (all i) with one linear solver of ``SOLVERS``.

    Raises CalibrationError (starting with the solver's name) when it gives no rigid transform.
    """
    A, Bm = _motions(P, B)
    try:
        if method == "daniilidis":
            X = _solve_daniilidis(A, Bm)
        else:
            R = _ROTATION_SOLVERS[method](A, Bm)
            X = make_transform(R, _translation(A, Bm, R))
        return check_transform(X, method)
    except (DegenerateInputError, np.linalg.LinAlgError) as err:
        raise CalibrationError(f"{method}: no usable solution ({err})") from None
