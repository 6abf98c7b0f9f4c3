"""Hand-eye calibration: where the camera sits on the robot flange, or in the robot base frame.

Two mountings, one equation. Each sample pairs a robot flange pose ``T_base_flange_i`` (robot
controller) with the pose of a calibration board seen by the camera,
``T_cam_board_i`` (from the board corners and the intrinsics, or given directly):

- eye-in-hand (camera on the flange, board fixed in the cell): unknown ``X = T_flange_camera``;
  the board pose ``T_base_board = T_base_flange_i @ X @ T_cam_board_i`` is the same for all i.
- eye-to-hand (camera fixed, board carried by the flange): unknown ``X = T_base_camera``;
  ``T_flange_board = T_flange_base_i @ X @ T_cam_board_i`` is the same for all i.

So both are ``T_anchor_board = P_i @ X @ T_cam_board_i`` with ``P_i = T_base_flange_i`` (anchor =
base) or ``P_i = T_flange_base_i`` (anchor = flange). Between two samples this is the classic
``A X = X B`` (``A = P_j^-1 P_i``, ``B = B_j B_i^-1``). In OpenCV's ``calibrateHandEye`` terms
the ``P_i`` are "gripper2base" -- for eye-to-hand that means the *inverted* robot poses, and what
it calls "cam2gripper" is then ``T_base_camera``.

Pipeline of :func:`calibrate_hand_eye`:

1. motion checks on the robot poses: no rotation at all is an error; consecutive samples that
   rotate less than ``min_rotation_deg``, and relative rotations all about nearly one axis
   (then the translation of X along that axis is not determined), are warnings;
2. every linear AX = XB solver (Tsai, Park, Horaud, Andreff, Daniilidis); for each, the
   consensus board pose (chordal mean of the ``P_i X B_i``) and its residual;
3. Levenberg-Marquardt from the linear solution with the lowest residual, over the 12 unknowns
   (X and the board pose, 6 each). The default objective (``likelihood``, :class:`_Likelihood`)
   treats both the images and the robot as noisy: each sample's residual is the 6-vector
   between its measured and predicted board pose, weighted by the board pose's covariance from
   its corners plus the robot pose noise carried into the camera frame; the robot noise is the
   most likely one on a grid. With an exact robot this is the pixel objective, with a noisy
   one it does not bend X to absorb the robot's error. Alternatives: ``pixels`` (reprojection
   error of every corner through :class:`~vgripd.geometry.camera_model.CameraModel`, robot exact),
   ``poses`` (unweighted board-pose residuals: translation mm plus rotation rad times the
   median camera-board distance; the only choice for samples without corners), ``none``;
4. per-sample residuals: reprojection RMS and how far that sample's implied board pose
   ``P_i X B_i`` lies from the consensus (deg, mm); samples far above the median are flagged;
5. stability: the refinement repeated leaving out one sample at a time; the spread of X (largest
   and standard deviation of the rotation angle in deg and the translation in mm against the
   full solution) is what the result would move by if one sample were missing.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from vgripd.errors import CalibrationError, ConvergenceError, ConversionError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import (
    check_transform,
    invert_transform,
    make_transform,
    matrix_from_quat,
    matrix_from_rotvec,
    rotation_angle,
)
from vgripd.geometry.vendors import convention, transform_from_vendor

FloatArray = npt.NDArray[np.float64]
#: What the Levenberg-Marquardt loop moves: (Y, C) for hand-eye, (T,) for a board pose.
State = tuple[FloatArray, ...]

MODES = ("eye-in-hand", "eye-to-hand")
#: What the refinement may minimise (see calibrate_hand_eye).
OBJECTIVES = ("auto", "likelihood", "pixels", "poses", "none")
#: Above this reprojection RMS (px) the pixel objective's result is not trusted: the robot
#: poses (or the intrinsics) carry the larger error.
MAX_PIXEL_RMS = 1.0
#: Estimated robot pose noise (per axis) above which the result warns about the robot poses.
ROBOT_WARN_DEG, ROBOT_WARN_MM = 0.1, 1.0
MIN_SAMPLES = 3  # two independent motions (three poses) are the least AX = XB can solve
FEW_SAMPLES = 8  # below this, one bad sample moves the result a lot
#: No pair of samples rotating more than this (deg): the rotation of X is not observable.
NO_ROTATION_DEG = 0.5
#: Relative rotation axes within this angle (deg) of one direction count as parallel.
PARALLEL_AXES_DEG = 5.0
#: A sample is an outlier when its residual exceeds this multiple of the median ...
OUTLIER_FACTOR = 3.0
#: ... and these floors (px for corner data; deg, mm for pose data).
OUTLIER_FLOOR_PX = 0.5
OUTLIER_FLOOR_DEG = 0.2
OUTLIER_FLOOR_MM = 2.0


@dataclass
class Sample:
    """One robot pose and what the camera saw there.

    Attributes
    ----------
    T_base_flange : (4, 4) flange pose in the robot base frame, mm (from the controller).
    T_cam_board : (4, 4) board pose in the camera frame, mm; None until measured from ``px``.
    image : name of the image (for messages), or "".
    obj : (N, 3) board points in the board frame, mm (None when only the pose is known).
    px : (N, 2) their detected pixels (OpenCV convention).
    number : the sample's number in messages and residuals (its place in the samples file when
        some are left out); None: its position in the list given.
    """

    T_base_flange: FloatArray
    T_cam_board: FloatArray | None = None
    image: str = ""
    obj: FloatArray | None = None
    px: FloatArray | None = None
    number: int | None = None

    @property
    def has_pixels(self) -> bool:
        return self.obj is not None and self.px is not None


@dataclass
class LinearSolution:
    """One OpenCV solver's X, the consensus board pose it implies and its residuals.

    ``rms_px`` is None for pose-only data; ``rotation_deg`` / ``translation_mm`` are the RMS
    over samples of the implied board pose's distance from the consensus. ``error`` says why
    the solver gave no usable answer (then the matrices are NaN).
    """

    T: FloatArray
    T_anchor_board: FloatArray
    rms_px: float | None
    rotation_deg: float
    translation_mm: float
    cost: float
    error: str = ""


@dataclass
class SampleResidual:
    """Residuals of one sample under the final solution."""

    sample: int
    image: str
    rms_px: float | None
    rotation_deg: float
    translation_mm: float
    outlier: bool = False


@dataclass
class Stability:
    """Spread of X over the leave-one-out solutions (against the all-samples solution)."""

    rotation_deg: float  # largest rotation angle between a leave-one-out X and X
    translation_mm: float  # largest translation difference, mm
    rotation_deg_std: float  # RMS of those angles
    translation_mm_std: float  # RMS of those distances
    worst_sample: int  # the sample whose removal moves X most (translation)


@dataclass
class HandEyeResult:
    """Outcome of :func:`calibrate_hand_eye`.

    ``T`` is ``T_flange_camera`` (eye-in-hand) or ``T_base_camera`` (eye-to-hand);
    ``T_anchor_board`` is ``T_base_board`` resp. ``T_flange_board``. ``solver`` is "refined"
    (started from ``start``) or, without refinement, the chosen linear solver.
    ``residuals_px`` holds the (N, 2) residuals (observed - projected) per sample (corner data).
    """

    mode: str
    T: FloatArray
    T_anchor_board: FloatArray
    solver: str
    start: str
    solvers: dict[str, LinearSolution]
    rms_px: float | None
    per_sample: list[SampleResidual]
    stability: Stability | None
    warnings: list[str] = field(default_factory=list)
    residuals_px: list[FloatArray] = field(default_factory=list)
    #: likelihood objective: the corner noise (px per coordinate, from the images' own pose
    #: fits) and the robot pose noise found most likely (deg, mm per axis); else None
    sigma_px: float | None = None
    robot_sigma: tuple[float, float] | None = None

    @property
    def transform_name(self) -> str:
        return "T_flange_camera" if self.mode == "eye-in-hand" else "T_base_camera"

    @property
    def board_name(self) -> str:
        return "T_base_board" if self.mode == "eye-in-hand" else "T_flange_board"


# ---------------------------------------------------------------------- small helpers
def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise CalibrationError(f"hand-eye mode {mode!r}: expected one of {', '.join(MODES)}")


def _number(samples: Sequence[Sample], i: int) -> int:
    n = samples[i].number
    return i if n is None else n


def _label(samples: Sequence[Sample], i: int) -> str:
    return f"sample {_number(samples, i)}" + (f" ({samples[i].image})" if samples[i].image
                                              else "")


def _exp(step: FloatArray) -> FloatArray:
    """4x4 transform of a 6-vector (rotation vector rad, translation mm); Rodrigues' formula
    written out, as the refinement calls it thousands of times with known-good input."""
    x, y, z = (float(v) for v in step[:3])
    theta = math.sqrt(x * x + y * y + z * z)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    T = np.eye(4)
    if theta < 1e-12:
        T[:3, :3] += K
    else:
        T[:3, :3] += (math.sin(theta) / theta) * K + ((1.0 - math.cos(theta)) / theta**2) * (K @ K)
    T[:3, 3] = step[3:]
    return T


def _project_rotation(M: FloatArray) -> FloatArray:
    """Nearest rotation (Frobenius) to a 3x3 matrix: the chordal mean of summed rotations."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)) or 1.0)])
    out: FloatArray = U @ D @ Vt
    return out


def _anchor_poses(samples: Sequence[Sample], mode: str) -> FloatArray:
    """The ``P_i`` of the module docstring, (n, 4, 4)."""
    P = np.stack([s.T_base_flange for s in samples])
    if mode == "eye-to-hand":
        P = np.stack([invert_transform(T) for T in P])
    return P


def _board_poses(samples: Sequence[Sample]) -> FloatArray:
    B = [s.T_cam_board for s in samples]
    if any(b is None for b in B):
        raise CalibrationError("hand-eye: a sample has no board pose (measure it first)")
    return np.stack([np.asarray(b) for b in B])


def consensus_board(P: FloatArray, B: FloatArray, X: FloatArray) -> FloatArray:
    """The board pose in the anchor frame that the samples agree on for a given X: the chordal
    mean of the rotations and the mean of the translations of ``P_i @ X @ B_i``."""
    C = P @ X @ B
    return make_transform(_project_rotation(C[:, :3, :3].sum(axis=0)), C[:, :3, 3].mean(axis=0))


def _inconsistency(P: FloatArray, B: FloatArray, X: FloatArray,
                   C: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per sample: angle (deg) and distance (mm) of the implied board pose from ``C``."""
    Ci = P @ X @ B
    D = np.swapaxes(Ci[:, :3, :3], 1, 2) @ C[:3, :3]
    cos = np.clip((np.trace(D, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    # arccos is inaccurate near 0; the sine from the antisymmetric part is exact there.
    sin = np.linalg.norm(_vee(D), axis=1)
    deg = np.degrees(np.arctan2(sin, cos))
    mm = np.linalg.norm(Ci[:, :3, 3] - C[:3, 3], axis=1)
    return deg, mm


def _vee(D: FloatArray) -> FloatArray:
    """(n, 3) axis * sin(angle) of (n, 3, 3) rotations (half the antisymmetric part)."""
    return 0.5 * np.stack([D[:, 2, 1] - D[:, 1, 2], D[:, 0, 2] - D[:, 2, 0],
                           D[:, 1, 0] - D[:, 0, 1]], axis=1)


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
    P = _anchor_poses(samples, mode)
    q = _quats(P[:, :3, :3])
    i, j = np.triu_indices(n, 1)
    rel = _quat_mul(_quat_conj(q[i]), q[j])  # rotation of P_i^-1 P_j, in the mount frame
    s = np.linalg.norm(rel[:, 1:], axis=1)
    angle = np.degrees(2.0 * np.arctan2(s, np.abs(rel[:, 0])))
    best = int(np.argmax(angle))
    if angle[best] <= NO_ROTATION_DEG:
        raise CalibrationError(
            f"hand-eye: the robot poses barely rotate (largest relative rotation "
            f"{angle[best]:.3g} deg, between {_label(samples, int(i[best]))} and "
            f"{_label(samples, int(j[best]))}); rotate the flange about at least two "
            "different axes between samples")
    consecutive = np.flatnonzero((j == i + 1) & (angle < min_rotation_deg))
    if consecutive.size:
        shown = ", ".join(f"{_number(samples, int(i[k]))}-{_number(samples, int(j[k]))} "
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


def _quat_conj(q: FloatArray) -> FloatArray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _quat_mul(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton products of (n, 4) quaternions (w, x, y, z)."""
    w = a[:, 0] * b[:, 0] - (a[:, 1:] * b[:, 1:]).sum(axis=1)
    v = a[:, :1] * b[:, 1:] + b[:, :1] * a[:, 1:] + np.cross(a[:, 1:], b[:, 1:])
    return np.concatenate([w[:, None], v], axis=1)


# ---------------------------------------------------------------------- linear solvers
# Written here rather than called from OpenCV: opencv-python 5.0.0.93 ships without the
# calibrateHandEye binding (opencv/opencv#29565), and these are short. Every solver works on
# the relative motions of all sample pairs, A X = X B with A = P_j^-1 P_i, B = B_j B_i^-1.


def _motions(P: FloatArray, B: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(m, 4, 4) A and B of all pairs i < j."""
    i, j = np.triu_indices(len(P), 1)
    A = np.linalg.inv(P[j]) @ P[i]
    Bm = B[j] @ np.linalg.inv(B[i])
    return A, Bm


def _skew(v: FloatArray) -> FloatArray:
    """(m, 3, 3) cross-product matrices of (m, 3) vectors."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], axis=1)


def _quats(R: FloatArray) -> FloatArray:
    """(m, 4) unit quaternions (w, x, y, z), w >= 0, of (m, 3, 3) rotations, vectorised: the
    eigenvector of the largest eigenvalue of Bar-Itzhack's symmetric 4x4 matrix (accurate at
    every angle, and the nearest quaternion when R is slightly off orthonormal)."""
    xx, xy, xz, yx, yy, yz, zx, zy, zz = R.reshape(-1, 9).T
    K = np.stack([
        np.stack([xx - yy - zz, yx + xy, zx + xz, zy - yz], 1),
        np.stack([yx + xy, yy - xx - zz, zy + yz, xz - zx], 1),
        np.stack([zx + xz, zy + yz, zz - xx - yy, yx - xy], 1),
        np.stack([zy - yz, xz - zx, yx - xy, xx + yy + zz], 1)], axis=1) / 3.0
    v = np.linalg.eigh(K)[1][:, :, 3]  # (x, y, z, w)
    q = np.concatenate([v[:, 3:], v[:, :3]], axis=1)
    out: FloatArray = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    return out


def _log(R: FloatArray) -> FloatArray:
    """(m, 3) rotation vectors of (m, 3, 3) rotations."""
    q = _quats(R)
    s = np.linalg.norm(q[:, 1:], axis=1)
    theta: FloatArray = 2.0 * np.arctan2(s, q[:, 0])
    scale = np.where(s > 1e-300, theta / np.maximum(s, 1e-300), 2.0)
    out: FloatArray = q[:, 1:] * scale[:, None]
    return out


def _translation(A: FloatArray, Bm: FloatArray, R: FloatArray) -> FloatArray:
    """t_X from (R_A - I) t_X = R_X t_B - t_A, least squares over all motions."""
    lhs = (A[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    rhs = (Bm[:, :3, 3] @ R.T - A[:, :3, 3]).reshape(-1)
    return np.asarray(np.linalg.lstsq(lhs, rhs, rcond=None)[0], dtype=np.float64)


def _rotation_tsai(A: FloatArray, Bm: FloatArray) -> FloatArray:
    """Tsai & Lenz (1989): modified Rodrigues vectors 2 sin(theta/2) * axis; the rotation's
    vector p solves [pA + pB]x p' = pB - pA with p = 2 p' / sqrt(1 + |p'|^2)."""
    def rodrigues(R: FloatArray) -> FloatArray:
        q = _quats(R)
        out: FloatArray = 2.0 * q[:, 1:] * np.sign(q[:, :1] + (q[:, :1] == 0))
        return out

    pa, pb = rodrigues(A[:, :3, :3]), rodrigues(Bm[:, :3, :3])
    prime = np.asarray(np.linalg.lstsq(_skew(pa + pb).reshape(-1, 3), (pb - pa).reshape(-1),
                                       rcond=None)[0], dtype=np.float64)
    p = 2.0 * prime / math.sqrt(1.0 + float(prime @ prime))
    n2 = float(p @ p)
    R = ((1.0 - n2 / 2.0) * np.eye(3)
         + 0.5 * (np.outer(p, p) + math.sqrt(max(4.0 - n2, 0.0)) * _skew(p[None])[0]))
    return _project_rotation(R)


def _rotation_park(A: FloatArray, Bm: FloatArray) -> FloatArray:
    """Park & Martin (1994): R_A R_X = R_X R_B means alpha = R_X beta for the rotation vectors
    alpha = log R_A, beta = log R_B; R_X is the rotation nearest sum alpha beta^T (the
    orthogonal Procrustes solution, Park's (M^T M)^(-1/2) M^T with M = sum beta alpha^T)."""
    M = np.einsum("ki,kj->ij", _log(Bm[:, :3, :3]), _log(A[:, :3, :3]))
    return _project_rotation(M.T)


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
    qa, qb = _quats(A[:, :3, :3]), _quats(Bm[:, :3, :3])
    M = (_quat_left(qa) - _quat_right(qb)).reshape(-1, 4)
    q = np.linalg.eigh(M.T @ M)[1][:, 0]
    return matrix_from_quat(q / np.linalg.norm(q))


def _rotation_andreff(A: FloatArray, Bm: FloatArray) -> FloatArray:
    """Andreff, Horaud & Espiau (2001): R_A R_X R_B^T = R_X is linear in vec(R_X):
    (I - R_A kron R_B) vec(R_X) = 0; the null vector, rescaled and projected onto SO(3)."""
    K = np.eye(9) - np.einsum("kij,klm->kiljm", A[:, :3, :3], Bm[:, :3, :3]).reshape(-1, 9, 9)
    v = np.linalg.svd(K.reshape(-1, 9), full_matrices=False)[2][-1].reshape(3, 3)
    return _project_rotation(v * np.sign(np.linalg.det(v)))


def _solve_daniilidis(A: FloatArray, Bm: FloatArray) -> FloatArray:
    """Daniilidis (1999): rotation and translation together as a unit dual quaternion.

    Each motion gives 6 linear equations in the 8 numbers (q, q') of X; the solution lies in
    the span of the two smallest right singular vectors, fixed by |q| = 1 and q . q' = 0.
    """
    def dual(T: FloatArray) -> tuple[FloatArray, FloatArray]:
        q = _quats(T[:, :3, :3])
        tq = np.concatenate([np.zeros((len(T), 1)), T[:, :3, 3]], axis=1)
        return q, 0.5 * np.einsum("kij,kj->ki", _quat_left(tq), q)

    qa, da = dual(A)
    qb, db = dual(Bm)
    flip = np.sign(qa[:, :1] * qb[:, :1]) + (qa[:, :1] * qb[:, :1] == 0)  # same scalar sign
    qb, db = qb * flip, db * flip
    m = len(A)
    S = np.zeros((m, 6, 8))
    S[:, :3, 0] = qa[:, 1:] - qb[:, 1:]
    S[:, :3, 1:4] = _skew(qa[:, 1:] + qb[:, 1:])
    S[:, 3:, 0] = da[:, 1:] - db[:, 1:]
    S[:, 3:, 1:4] = _skew(da[:, 1:] + db[:, 1:])
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
    t = 2.0 * _quat_mul(d[None], _quat_conj(q[None]))[0, 1:]
    return make_transform(matrix_from_quat(q / np.linalg.norm(q)), t)


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


# ---------------------------------------------------------------------- refinement
class _Problem:
    """The samples in the arrays the residual functions need.

    State: ``(Y, C)`` with ``Y = X^-1`` (camera from mount frame) and ``C = T_anchor_board``,
    so the predicted board pose is ``T_cam_board_i = Y @ Q_i @ C`` with ``Q_i = P_i^-1``.
    """

    def __init__(self, samples: Sequence[Sample], mode: str, camera: CameraModel | None,
                 pixels: bool = True):
        self.mode = mode
        self.P = _anchor_poses(samples, mode)
        self.Q = np.stack([invert_transform(p) for p in self.P])
        self.B = _board_poses(samples)
        self.pixels = pixels and camera is not None and all(s.has_pixels for s in samples)
        self.camera = camera
        if self.pixels:
            self.counts = [len(s.px) for s in samples if s.px is not None]
            self.index = np.repeat(np.arange(len(samples)), self.counts)
            self.obj = np.concatenate([s.obj for s in samples if s.obj is not None])
            self.px = np.concatenate([s.px for s in samples if s.px is not None])
        # mm per rad: a rotation error of the board pose counts as the displacement it causes
        # at the distance of the board.
        self.weight = float(np.median(np.linalg.norm(self.B[:, :3, 3], axis=1)))

    def residual(self, state: State) -> FloatArray | None:
        """Residual vector, or None where a board corner falls behind the camera."""
        Y, C = state
        M = Y @ self.Q @ C  # predicted T_cam_board, (n, 4, 4)
        if not self.pixels:
            D = np.swapaxes(self.B[:, :3, :3], 1, 2) @ M[:, :3, :3]
            rot = self.weight * _vee(D)
            out: FloatArray = np.concatenate([rot, M[:, :3, 3] - self.B[:, :3, 3]], axis=1)
            return out.ravel()
        Mk = M[self.index]
        pts = np.einsum("kij,kj->ki", Mk[:, :3, :3], self.obj) + Mk[:, :3, 3]
        if (pts[:, 2] <= 0).any():
            return None
        assert self.camera is not None
        res: FloatArray = (self.px - self.camera.project(pts)).ravel()
        return res

    def pixel_residuals(self, state: State) -> list[FloatArray]:
        """Per sample (N, 2) observed - projected, px."""
        r = self.residual(state)
        if r is None:
            raise CalibrationError("hand-eye: a board corner projects behind the camera")
        return np.split(r.reshape(-1, 2), np.cumsum(self.counts)[:-1])

    def cost(self, X: FloatArray, C: FloatArray) -> float:
        r = self.residual((invert_transform(X), C))
        return math.inf if r is None else float(r @ r)


def _update(state: State, step: FloatArray) -> State:
    """Small motion of the camera frame (Y on the left) and of the board frame (C on the
    right); rotation parts in rad, translation parts in mm."""
    Y, C = state
    return _exp(step[:6]) @ Y, C @ _exp(step[6:])


# central-difference steps: rad for the rotation parts, mm for the translation parts
_STEPS = np.array([1e-6] * 3 + [1e-4] * 3 + [1e-6] * 3 + [1e-4] * 3)


def _levenberg_marquardt(
    residual: Callable[[State], FloatArray | None],
    update: Callable[[State, FloatArray], State],
    state: State,
    steps: FloatArray,
    max_iter: int = 100,
) -> tuple[State, bool]:
    """Minimise |residual|^2 over the motion parameters of ``update``.

    The Jacobian is taken by central differences with ``steps`` (one column per parameter,
    cheap next to the O(samples x corners) residual); the damping is Marquardt's (scaled by
    diag(J^T J), so rad and mm parameters are treated alike). ``residual`` returns None where
    the model is undefined (a point behind the camera), which a trial step treats as worse.
    Returns the state and whether it converged.
    """
    r = residual(state)
    if r is None:
        raise CalibrationError("hand-eye: a board corner lies behind the camera at the start")
    cost = float(r @ r)
    mu = 1e-3
    for _ in range(max_iter):
        cols = []
        for k, h in enumerate(steps):
            e = np.zeros(len(steps))
            e[k] = h
            rp, rm = residual(update(state, e)), residual(update(state, -e))
            if rp is None or rm is None:
                raise CalibrationError("hand-eye: a board corner lies on the camera plane")
            cols.append((rp - rm) / (2.0 * h))
        J = np.stack(cols, axis=1)
        H = J.T @ J
        g = J.T @ r
        damp = np.diag(H) + 1e-12 * float(np.diag(H).max())
        while True:
            step = np.linalg.solve(H + mu * np.diag(damp), -g)
            trial = update(state, step)
            r_new = residual(trial)
            cost_new = math.inf if r_new is None else float(r_new @ r_new)
            if cost_new <= cost:
                break
            mu *= 10.0
            if mu > 1e12:  # no step lowers the cost: this is the minimum
                return state, True
        assert r_new is not None
        done = cost - cost_new <= 1e-12 * cost + 1e-30 or float(np.abs(step).max()) < 1e-12
        state, r, cost = trial, r_new, cost_new
        mu = max(mu / 10.0, 1e-12)
        if done:
            return state, True
    return state, False


def refine(problem: _Problem, X: FloatArray, C: FloatArray,
           ) -> tuple[FloatArray, FloatArray, bool]:
    """X and the board pose minimising the reprojection (or pose) residual, from (X, C)."""
    (Y, C), converged = _levenberg_marquardt(problem.residual, _update,
                                             (invert_transform(X), C), _STEPS)
    return invert_transform(Y), C, converged


# ---------------------------------------------------------------------- likelihood objective
#: Robot pose noise levels (one standard deviation per axis, flange frame) among which the
#: "likelihood" objective picks the most likely; the smallest mean "exact".
ROBOT_SIGMA_DEG = (1e-4, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0)
ROBOT_SIGMA_MM = (1e-3, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0)


def _adjoint(T: FloatArray) -> FloatArray:
    """(n, 6, 6) maps of a small motion (rotation rad, translation mm) in the frame of the
    (n, 4, 4) transforms ``T`` to the same motion in their parent frame, to first order."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    out = np.zeros((len(T), 6, 6))
    out[:, :3, :3] = R
    out[:, 3:, 3:] = R
    out[:, 3:, :3] = _skew(t) @ R
    return out


def _small_log(D: FloatArray) -> FloatArray:
    """(n, 6) (rotation vector, translation) of (n, 4, 4) transforms with rotations below pi."""
    w = _vee(D[:, :3, :3])
    s = np.linalg.norm(w, axis=1)
    angle = np.arctan2(s, (np.trace(D[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0)
    scale = np.where(s > 1e-12, angle / np.maximum(s, 1e-300), 1.0)
    out: FloatArray = np.concatenate([w * scale[:, None], D[:, :3, 3]], axis=1)
    return out


class _Likelihood:
    """Hand-eye as a maximum-likelihood problem with noise in the images *and* the robot.

    The measurements are the board poses ``B_i`` (from the corners, :func:`board_pose`), each
    with its covariance ``s^2 (J_i^T J_i)^-1`` (``J_i``: the pixels' Jacobian with respect to a
    small motion of the board in the camera frame; ``s^2``: the corner noise pooled over every
    image's own PnP fit, which no robot error reaches). The reported robot poses get Gaussian
    noise of ``sigma_deg`` / ``sigma_mm`` per axis in the flange frame, which reaches the
    predicted board pose ``Y Q_i C`` through the adjoint of ``Y`` (eye-in-hand) or ``Y Q_i``
    (eye-to-hand). The residual of a sample is the 6-vector between predicted and measured
    board pose, whitened by the sum of both covariances. With the robot exact this is, to first
    order, the pixel objective; with robot noise it stops the fit from bending X to absorb it.
    The robot noise is chosen by profile likelihood among ``ROBOT_SIGMA_*``.
    """

    def __init__(self, problem: _Problem, cov_board: FloatArray, sigma_px: float):
        self.problem = problem
        self.Binv = np.stack([invert_transform(b) for b in problem.B])
        #: (n, 6, 6) covariance of each board pose from its corners
        self.cov_board = cov_board
        #: corner noise, px per coordinate (pooled over the images' own pose fits)
        self.sigma_px = sigma_px

    @classmethod
    def from_corners(cls, problem: _Problem, samples: Sequence[Sample],
                     camera: CameraModel) -> _Likelihood:
        """Board-pose covariances from each sample's corners and the pooled corner noise."""
        info, ssr, dof = [], 0.0, 0
        for s, B in zip(samples, problem.B, strict=True):
            assert s.obj is not None
            assert s.px is not None
            J, r = _board_jacobian(s.obj, s.px, B, camera)
            info.append(J.T @ J)
            ssr += float(r @ r)
            dof += len(r) - 6
        if dof <= 0:
            raise CalibrationError("hand-eye: too few corners per image to weigh the board poses")
        sigma_px = math.sqrt(ssr / dof)
        try:
            cov = sigma_px**2 * np.linalg.inv(np.stack(info))
        except np.linalg.LinAlgError:
            raise CalibrationError("hand-eye: a board pose is not determined by its corners "
                                   "(too few or collinear)") from None
        return cls(problem, cov, sigma_px)

    def without(self, k: int, problem: _Problem) -> _Likelihood:
        """The same weights without sample k; ``problem`` holds the other samples."""
        return _Likelihood(problem, np.delete(self.cov_board, k, axis=0), self.sigma_px)

    def _whitening(self, Y: FloatArray, sigma_deg: float,
                   sigma_mm: float) -> tuple[FloatArray, float]:
        """(n, 6, 6) inverse Cholesky factors of the samples' covariances, and their summed
        log determinant."""
        p = self.problem
        A = _adjoint(np.broadcast_to(Y, p.Q.shape) if p.mode == "eye-in-hand" else Y @ p.Q)
        robot = np.array([math.radians(sigma_deg)] * 3 + [sigma_mm] * 3) ** 2
        S = self.cov_board + (A * robot) @ np.swapaxes(A, 1, 2)
        L = np.linalg.cholesky(S)
        logdet = 2.0 * float(np.log(np.diagonal(L, axis1=1, axis2=2)).sum())
        return np.linalg.inv(L), logdet

    def fit(self, X: FloatArray, C: FloatArray, sigma_deg: float, sigma_mm: float,
            passes: int = 2) -> tuple[FloatArray, FloatArray, float, bool]:
        """X and the board pose maximising the likelihood for this robot noise, from (X, C);
        the weights follow X (``passes`` times). Returns X, C, -2 log-likelihood (up to a
        constant), converged."""
        Q, Binv = self.problem.Q, self.Binv
        state: State = (invert_transform(X), C)
        converged, nll = False, math.inf
        for _ in range(passes):
            W, logdet = self._whitening(state[0], sigma_deg, sigma_mm)

            def residual(st: State, W: FloatArray = W) -> FloatArray:
                e = _small_log(st[0] @ Q @ st[1] @ Binv)
                out: FloatArray = np.einsum("nij,nj->ni", W, e).ravel()
                return out

            state, converged = _levenberg_marquardt(residual, _update, state, _STEPS)
            r = residual(state)
            nll = float(r @ r) + logdet
        return invert_transform(state[0]), state[1], nll, converged

    def solve(self, X: FloatArray, C: FloatArray,
              ) -> tuple[FloatArray, FloatArray, bool, tuple[float, float]]:
        """The most likely robot noise among ``ROBOT_SIGMA_*`` and the fit under it: X, C,
        converged, (sigma_deg, sigma_mm)."""
        best: tuple[float, float, float] | None = None
        Xw, Cw = X, C
        for sigma_deg in ROBOT_SIGMA_DEG:
            for sigma_mm in ROBOT_SIGMA_MM:
                Xw, Cw, nll, _ = self.fit(Xw, Cw, sigma_deg, sigma_mm, passes=1)
                if best is None or nll < best[0]:
                    best = (nll, sigma_deg, sigma_mm)
        assert best is not None
        X, C, _, converged = self.fit(X, C, best[1], best[2])
        return X, C, converged, (best[1], best[2])


def _board_jacobian(obj: FloatArray, px: FloatArray, B: FloatArray, camera: CameraModel,
                    ) -> tuple[FloatArray, FloatArray]:
    """(2N, 6) Jacobian of the projected corners with respect to a small motion of the board
    in the camera frame (central differences, as the refinement's), and the (2N,) residual
    observed - projected at ``B``."""
    pts = obj @ B[:3, :3].T + B[:3, 3]
    moved = []
    for k, h in enumerate(_STEPS[:6]):
        for sign in (1.0, -1.0):
            e = np.zeros(6)
            e[k] = sign * h
            E = _exp(e)
            moved.append(pts @ E[:3, :3].T + E[:3, 3])
    proj = camera.project(np.concatenate([pts, *moved])).reshape(13, -1, 2)
    J = ((proj[1::2] - proj[2::2]).reshape(6, -1) / (2.0 * _STEPS[:6, None])).T
    return J, (px - proj[0]).ravel()


# ---------------------------------------------------------------------- board poses
#: A second planar pose fitting within this factor of the best (and of 0.1 px) is ambiguous.
AMBIGUITY_RATIO = 2.0


def board_pose(obj: FloatArray, px: FloatArray, camera: CameraModel,
               ) -> tuple[FloatArray, float, bool]:
    """``T_cam_board`` of a planar board (z = 0) from its corners: the better of the two IPPE
    poses (OpenCV, on undistorted coordinates) refined on the pixel error with the camera
    model; returns the pose, its RMS (px) and whether the other pose fits about as well
    (ambiguous)."""
    norm = camera.undistort(px)
    _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
        np.ascontiguousarray(obj).reshape(-1, 1, 3), np.ascontiguousarray(norm).reshape(-1, 1, 2),
        np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)

    def residual(state: State) -> FloatArray | None:
        pts = obj @ state[0][:3, :3].T + state[0][:3, 3]
        if (pts[:, 2] <= 0).any():
            return None
        out: FloatArray = (camera.project(pts) - px).ravel()
        return out

    starts = []
    for rv, tv in zip(rvecs, tvecs, strict=True):
        T0 = make_transform(matrix_from_rotvec(np.ravel(rv)), np.ravel(tv))
        r0 = residual((T0,))
        if r0 is not None:
            starts.append((math.sqrt(float(r0 @ r0) / len(px)), T0))
    if not starts:
        raise DegenerateInputError("the board lies behind the camera in every candidate pose")
    starts.sort(key=lambda f: f[0])
    # IPPE's poses are near their minima already: refine the better one only, and call the
    # board ambiguous when the other fits about as well even unrefined.
    (T,), _ = _levenberg_marquardt(residual, lambda st, s: (_exp(s) @ st[0],), (starts[0][1],),
                                   _STEPS[:6])
    r = residual((T,))
    assert r is not None
    rms = math.sqrt(float(r @ r) / len(px))
    ambiguous = len(starts) > 1 and transform_error(starts[1][1], T)[0] > 0.1 and (
        starts[1][0] < AMBIGUITY_RATIO * max(rms, 0.1))
    return T, rms, ambiguous


def measure_board_poses(samples: Sequence[Sample], camera: CameraModel) -> list[str]:
    """Fill ``T_cam_board`` of samples that have corners (:func:`board_pose`).

    Returns warnings for ambiguous planar poses; CalibrationError names the sample."""
    warnings = []
    for i, s in enumerate(samples):
        if s.T_cam_board is not None or s.obj is None or s.px is None:
            continue
        try:
            s.T_cam_board, _, ambiguous = board_pose(s.obj, s.px, camera)
        except (DegenerateInputError, ConvergenceError, cv2.error) as err:
            raise CalibrationError(f"hand-eye: {_label(samples, i)}: board pose: {err}") from None
        if ambiguous:
            warnings.append(f"{_label(samples, i)}: the board pose is ambiguous (board seen "
                            "small or nearly face-on); tilt the board more")
    return warnings


def calibrate_hand_eye(
    samples: Sequence[Sample],
    mode: str,
    camera: CameraModel | None = None,
    *,
    min_rotation_deg: float = 5.0,
    objective: str = "auto",
    stability: bool = True,
) -> HandEyeResult:
    """Solve X from the samples (see the module docstring for the steps).

    Parameters
    ----------
    samples : robot poses with board corners (then ``camera`` is needed) or board poses.
    mode : "eye-in-hand" or "eye-to-hand".
    camera : intrinsics of the images; None when the samples carry board poses only.
    min_rotation_deg : consecutive samples rotating less than this are reported.
    objective : what the refinement minimises: "likelihood" (board poses weighted by their
        pixel uncertainty plus an estimated robot pose noise, :class:`_Likelihood`), "pixels"
        (reprojection error of the corners, robot taken as exact), "poses" (board-pose
        residuals, unweighted), "none" (keep the best linear solution) or "auto": likelihood
        with corner data, poses without.

    Raises
    ------
    CalibrationError
        bad mode, too few samples, no rotation, a sample without corners and board pose,
        every linear solver failing.
    """
    _check_mode(mode)
    if objective not in OBJECTIVES:
        raise CalibrationError(f"hand-eye objective {objective!r}: expected one of "
                               f"{', '.join(OBJECTIVES)}")
    for i, s in enumerate(samples):
        check = s.T_cam_board if s.T_cam_board is not None else np.eye(4)
        try:
            check_transform(s.T_base_flange, "T_base_flange")
            check_transform(check, "T_cam_board")
        except DegenerateInputError as err:
            raise CalibrationError(f"hand-eye: {_label(samples, i)}: {err}") from None
        if s.T_cam_board is None and not (s.has_pixels and camera is not None):
            raise CalibrationError(f"hand-eye: {_label(samples, i)}: no board pose, and no "
                                   "corners with intrinsics to measure it")
    warnings = check_motion(samples, mode, min_rotation_deg)
    if camera is not None:
        warnings += measure_board_poses(samples, camera)
    problem = _Problem(samples, mode, camera)

    solvers: dict[str, LinearSolution] = {}
    for name in SOLVERS:
        solvers[name] = _linear_solution(problem, name)
    usable = {k: v for k, v in solvers.items() if not v.error}
    if not usable:
        raise CalibrationError("hand-eye: every linear solver failed: " + "; ".join(
            f"{v.error}" for v in solvers.values()))
    for sol in solvers.values():
        if sol.error:
            warnings.append(f"solver {sol.error}")
    start = min(usable, key=lambda k: usable[k].cost)
    X0, C0 = usable[start].T, usable[start].T_anchor_board
    X, C, solver = X0, C0, start
    if objective == "auto":
        objective = "likelihood" if problem.pixels else "poses"
    if objective in ("likelihood", "pixels") and not problem.pixels:
        raise CalibrationError(f"hand-eye objective {objective!r} needs board corners and "
                               "intrinsics; these samples carry board poses only")
    sigma_px = robot_sigma = likelihood = None
    if objective == "likelihood":
        assert camera is not None
        likelihood = _Likelihood.from_corners(problem, samples, camera)
        X, C, converged, robot_sigma = likelihood.solve(X0, C0)
        sigma_px = likelihood.sigma_px
        if robot_sigma[0] > ROBOT_WARN_DEG or robot_sigma[1] > ROBOT_WARN_MM:
            warnings.append(
                f"the robot poses disagree with the images by about {robot_sigma[0]:g} deg and "
                f"{robot_sigma[1]:g} mm per axis (most likely noise; the corners' own noise is "
                f"{sigma_px:.2f} px): check the robot's accuracy, that each pose was read after "
                "the robot settled, and the intrinsics")
    elif objective == "pixels":
        X, C, converged = refine(problem, X0, C0)
        rms = math.sqrt(problem.cost(X, C) / len(problem.px))
        if rms > MAX_PIXEL_RMS:
            warnings.append(
                f"reprojection RMS {rms:.2f} px with the robot poses taken as exact: far above "
                "corner noise, so the robot poses (or the intrinsics) carry the larger error "
                "and the pixel fit bends X to absorb it; use --objective likelihood")
    elif objective == "poses":
        X, C, converged = refine(_Problem(samples, mode, camera, pixels=False), X0, C0)
    if objective != "none":
        solver = f"refined-{objective}"
    if solver.startswith("refined") and not converged:
        warnings.append("refinement stopped at its iteration limit; the result may not be "
                        "the best fit")

    per_sample, residuals_px, rms_px = _per_sample(problem, samples, X, C)
    outliers = [(k, r) for k, r in enumerate(per_sample) if r.outlier]
    if outliers:
        warnings.append(
            "outlier sample(s): " + ", ".join(
                _label(samples, k) + (f" {r.rms_px:.2f} px" if r.rms_px is not None else "")
                + f" {r.rotation_deg:.2f} deg {r.translation_mm:.1f} mm" for k, r in outliers)
            + "; check the robot pose and image of each (wrong order, motion blur, pose read "
              "before the robot settled), or solve again without them (--samples FILE "
              f"--exclude {','.join(str(r.sample) for _, r in outliers)})")
    stab = None
    if stability and len(samples) > MIN_SAMPLES:
        how = start if objective == "none" else objective
        stab = _leave_one_out(samples, mode, camera, X, C, how, likelihood, robot_sigma)
    return HandEyeResult(mode, X, C, solver, start, solvers, rms_px, per_sample, stab,
                         warnings, residuals_px, sigma_px, robot_sigma)


def _linear_solution(problem: _Problem, name: str) -> LinearSolution:
    nan = np.full((4, 4), np.nan)
    try:
        X = solve_linear(problem.P, problem.B, name)
    except CalibrationError as err:
        return LinearSolution(nan, nan, None, math.nan, math.nan, math.inf, str(err))
    C = consensus_board(problem.P, problem.B, X)
    deg, mm = _inconsistency(problem.P, problem.B, X, C)
    cost = problem.cost(X, C)
    rms_px = None
    if problem.pixels:
        rms_px = math.sqrt(cost / len(problem.px)) if math.isfinite(cost) else math.inf
    return LinearSolution(X, C, rms_px, float(np.sqrt((deg**2).mean())),
                          float(np.sqrt((mm**2).mean())), cost)


def _per_sample(problem: _Problem, samples: Sequence[Sample], X: FloatArray, C: FloatArray,
                ) -> tuple[list[SampleResidual], list[FloatArray], float | None]:
    deg, mm = _inconsistency(problem.P, problem.B, X, C)
    residuals: list[FloatArray] = []
    rms_px = None
    per_rms: list[float | None] = [None] * len(samples)
    if problem.pixels:
        residuals = problem.pixel_residuals((invert_transform(X), C))
        per_rms = [float(np.sqrt((r**2).sum(axis=1).mean())) for r in residuals]
        all_r = np.concatenate(residuals)
        rms_px = float(np.sqrt((all_r**2).sum(axis=1).mean()))
        px_arr = np.array(per_rms, dtype=float)
        flags = _outliers(px_arr, OUTLIER_FLOOR_PX)
    else:
        flags = _outliers(deg, OUTLIER_FLOOR_DEG) | _outliers(mm, OUTLIER_FLOOR_MM)
    out = [SampleResidual(_number(samples, i), s.image, per_rms[i], float(deg[i]), float(mm[i]),
                          bool(flags[i]))
           for i, s in enumerate(samples)]
    return out, residuals, rms_px


def _outliers(values: FloatArray, floor: float) -> npt.NDArray[np.bool_]:
    """Values above OUTLIER_FACTOR times the median of all and above ``floor``."""
    med = float(np.median(values))
    flags: npt.NDArray[np.bool_] = (values > OUTLIER_FACTOR * med) & (values > floor)
    return flags


def _leave_one_out(samples: Sequence[Sample], mode: str, camera: CameraModel | None,
                   X: FloatArray, C: FloatArray, how: str,
                   likelihood: _Likelihood | None = None,
                   robot_sigma: tuple[float, float] | None = None) -> Stability:
    """Re-solve without each sample in turn, the way X was found (``how``: "likelihood" with
    the weights and robot noise found on all samples, "pixels", "poses" or a linear solver's
    name);
    refinements start from the full solution (one basin, so they converge in a few steps)."""
    deg, mm = [], []
    for k in range(len(samples)):
        subset = [s for i, s in enumerate(samples) if i != k]
        problem = _Problem(subset, mode, camera, pixels=how in ("pixels", "likelihood"))
        if how == "likelihood":
            assert likelihood is not None
            assert robot_sigma is not None
            Xk = likelihood.without(k, problem).fit(X, C, *robot_sigma)[0]
        elif how in ("pixels", "poses"):
            Xk, _, _ = refine(problem, X, C)
        else:
            Xk = solve_linear(problem.P, problem.B, how)
        deg.append(math.degrees(rotation_angle(Xk[:3, :3].T @ X[:3, :3])))
        mm.append(float(np.linalg.norm(Xk[:3, 3] - X[:3, 3])))
    d, m = np.array(deg), np.array(mm)
    return Stability(float(d.max()), float(m.max()), float(np.sqrt((d**2).mean())),
                     float(np.sqrt((m**2).mean())), _number(samples, int(np.argmax(m))))


# ---------------------------------------------------------------------- synthetic data
def synthetic_samples(
    mode: str,
    X: FloatArray,
    T_anchor_board: FloatArray,
    camera: CameraModel,
    object_points: FloatArray,
    n: int = 15,
    *,
    rng: np.random.Generator,
    noise_px: float = 0.0,
    robot_noise_deg: float = 0.0,
    robot_noise_mm: float = 0.0,
    tilt_deg: float = 30.0,
    distance_mm: tuple[float, float] = (400.0, 700.0),
) -> list[Sample]:
    """Samples with known truth, for tests and benchmarks.

    Each view puts the board centre on the optical axis at a random distance, tilted by up to
    ``tilt_deg`` about random axes in the board plane and rolled freely; the robot pose that
    produces it follows from X and the board pose. Pixels get Gaussian noise ``noise_px`` (per
    coordinate); the robot poses reported get rotation noise ``robot_noise_deg`` (per axis) and
    translation noise ``robot_noise_mm`` (per axis) after the pixels were made.
    """
    _check_mode(mode)
    centre = object_points.mean(axis=0)
    out = []
    for i in range(n):
        roll = rng.uniform(-math.pi, math.pi)
        tilt_axis = rng.normal(size=2)
        tilt = math.radians(rng.uniform(-tilt_deg, tilt_deg))
        R = matrix_from_rotvec([0.0, 0.0, roll]) @ matrix_from_rotvec(
            np.array([*tilt_axis / np.linalg.norm(tilt_axis), 0.0]) * tilt)
        depth = rng.uniform(*distance_mm)
        B = make_transform(R, np.array([0.0, 0.0, depth]) - R @ centre)  # T_cam_board
        P = T_anchor_board @ invert_transform(B) @ invert_transform(X)
        T_base_flange = P if mode == "eye-in-hand" else invert_transform(P)
        px = camera.project(object_points @ B[:3, :3].T + B[:3, 3])
        px = px + rng.normal(scale=noise_px, size=px.shape) if noise_px else px
        if robot_noise_deg or robot_noise_mm:
            noise = np.concatenate([np.radians(rng.normal(scale=robot_noise_deg, size=3)),
                                    rng.normal(scale=robot_noise_mm, size=3)])
            T_base_flange = T_base_flange @ _exp(noise)
        out.append(Sample(T_base_flange, None, f"synthetic-{i:02d}", object_points.copy(), px))
    return out


def transform_error(T: FloatArray, T_true: FloatArray) -> tuple[float, float]:
    """(rotation angle deg, translation distance mm) between two transforms."""
    return (math.degrees(rotation_angle(T[:3, :3].T @ T_true[:3, :3])),
            float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])))


# ---------------------------------------------------------------------- files
SAMPLES_FORMAT = "vgripd-handeye-samples/1"


def read_poses(path: str | Path, pose_format: str) -> list[FloatArray]:
    """Robot flange poses ``T_base_flange`` (mm) from a text file, one pose per line.

    Each line holds the numbers of one pose in ``pose_format``'s field order and units as
    ``vgripd.geometry.vendors`` defines them (e.g. kuka: X Y Z mm, A B C deg; ur: x y z m, rx ry rz
    rad;
    matrix: 16 numbers row-major, mm), separated by spaces and/or commas. ``#`` starts a
    comment; blank lines are skipped. CalibrationError names ``file:line`` for a bad line.
    """
    p = Path(path)
    try:
        convention(pose_format)
    except ConversionError as err:
        raise CalibrationError(f"--pose-format: {err}") from None
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise CalibrationError(f"{p}: cannot read robot poses: {err}") from None
    poses = []
    for number, line in enumerate(text.splitlines(), start=1):
        values = line.split("#", 1)[0].replace(",", " ").split()
        if not values:
            continue
        try:
            poses.append(transform_from_vendor(pose_format, values))
        except ConversionError as err:
            raise CalibrationError(f"{p}:{number}: {err}") from None
    if not poses:
        raise CalibrationError(f"{p}: no robot poses (one pose per line, '#' for comments)")
    return poses


def save_samples(path: str | Path, samples: Sequence[Sample], mode: str, board: str | None,
                 camera: CameraModel | None) -> Path:
    """Write the samples as JSON so that a calibration can be solved again without the robot
    and the images: robot poses as 4x4 (mm), the detected corners (board points ``obj_mm`` and
    their pixels ``px``) or, for pose-only samples, ``T_cam_board``; plus mode, board spec (for
    information) and intrinsics."""
    entries: list[dict[str, Any]] = []
    for s in samples:
        entry: dict[str, Any] = {"image": s.image, "T_base_flange": s.T_base_flange.tolist()}
        if s.obj is not None and s.px is not None:
            entry["obj_mm"] = s.obj.tolist()
            entry["px"] = s.px.tolist()
        else:
            if s.T_cam_board is None:
                raise CalibrationError(f"{s.image}: sample has neither corners nor a board pose")
            entry["T_cam_board"] = s.T_cam_board.tolist()
        entries.append(entry)
    data = {"format": SAMPLES_FORMAT, "mode": mode, "board": board,
            "camera": None if camera is None else dataclasses.asdict(camera),
            "units": "mm, px (OpenCV convention)", "samples": entries}
    p = Path(path)
    try:
        p.write_text(json.dumps(data, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    except (OSError, ValueError) as err:
        raise CalibrationError(f"{p}: cannot write samples: {err}") from None
    return p


def load_samples(path: str | Path,
                 ) -> tuple[str, str | None, CameraModel | None, list[Sample]]:
    """Read :func:`save_samples`' file: (mode, board spec, camera, samples)."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CalibrationError(f"{p}: cannot read samples: {err}") from None
    if not isinstance(data, dict) or data.get("format") != SAMPLES_FORMAT:
        raise CalibrationError(f"{p}: not a hand-eye samples file (format must be "
                               f"{SAMPLES_FORMAT!r})")
    mode, board = data.get("mode"), data.get("board")
    _check_mode(str(mode))
    try:
        camera = None if data.get("camera") is None else CameraModel(**data["camera"])
    except (TypeError, DegenerateInputError) as err:
        raise CalibrationError(f"{p}: camera: {err}") from None
    samples = []
    for i, e in enumerate(data.get("samples", [])):
        where = f"{p}: samples[{i}]"
        try:
            T = check_transform(e["T_base_flange"], "T_base_flange")
            if "px" in e:
                obj = np.asarray(e["obj_mm"], dtype=np.float64).reshape(-1, 3)
                px = np.asarray(e["px"], dtype=np.float64).reshape(-1, 2)
                if len(obj) != len(px) or len(px) < 4:
                    raise CalibrationError(f"{where}: need at least 4 corners with as many "
                                           f"obj_mm as px, got {len(obj)} and {len(px)}")
                samples.append(Sample(T, None, str(e.get("image", "")), obj, px))
            else:
                B = check_transform(e["T_cam_board"], "T_cam_board")
                samples.append(Sample(T, B, str(e.get("image", ""))))
        except (KeyError, TypeError, ValueError, DegenerateInputError) as err:
            raise CalibrationError(f"{where}: {type(err).__name__}: {err}") from None
    return str(mode), board, camera, samples
