"""Refinement: the least-squares engine (scipy's Levenberg-Marquardt over small motions of
rigid transforms, with analytic Jacobians) and the two plain objectives of the hand-eye
refinement, the corners' reprojection error (``pixels``) and unweighted board-pose residuals
(``poses``). The maximum-likelihood objective is in :mod:`.likelihood`.

State of the hand-eye refinement: ``(Y, C)`` with ``Y = X^-1`` (camera from mount frame) and
``C = T_anchor_board``, so the predicted board pose is ``M_i = Y @ Q_i @ C`` with
``Q_i = P_i^-1``. ``Y`` moves by a small motion on the left (in the camera frame), ``C`` on the
right (in the board frame).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from vgripd.calib.handeye.samples import FloatArray, Sample, anchor_poses, board_poses
from vgripd.errors import CalibrationError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import (
    invert_transform,
    invert_transforms,
    left_jacobians,
    matrices_from_rotvecs,
    skew,
    transforms_from_vectors,
    vee,
)

#: How a transform of the state moves: "left" ``exp(d) @ T`` (d in T's parent frame) or
#: "right" ``T @ exp(d)`` (d in T's own frame); ``exp`` is ``transforms_from_vectors``.
SIDES = ("left", "right")
#: Stopping tolerances of the least-squares solver (relative cost decrease, relative step,
#: gradient); the hand-written Levenberg-Marquardt this replaced stopped at 1e-12 relative
#: cost decrease as well.
TOLERANCE = 1e-12
MAX_EVALUATIONS = 200
#: Residual given to a trial step that puts a board corner behind the camera: far worse than
#: any real fit, so the solver shrinks its step.
BEHIND_PX = 1e6

Residual = Callable[[Sequence[FloatArray]], FloatArray]
Jacobian = Callable[[Sequence[FloatArray]], FloatArray]


def _chart(x: FloatArray, sides: Sequence[str]) -> FloatArray:
    """d(motion)/dx: the parameters ``x`` (6 per transform) of ``exp(x) @ T0`` /
    ``T0 @ exp(x)`` against a small motion of the current transform on the same side."""
    n = len(sides)
    G = np.zeros((6 * n, 6 * n))
    for k, side in enumerate(sides):
        a = x[6 * k:6 * k + 6]
        g = G[6 * k:6 * k + 6, 6 * k:6 * k + 6]
        if side == "left":  # exp(d) exp(a) = exp(a + da): d = (J_l dw, dt + [t] J_l dw)
            Jl = left_jacobians(a[:3])
            g[:3, :3] = Jl
            g[3:, :3] = skew(a[3:]) @ Jl
            g[3:, 3:] = np.eye(3)
        else:  # exp(a) exp(d) = exp(a + da): d = (J_r dw, R_a^T dt)
            g[:3, :3] = left_jacobians(-a[:3])
            g[3:, 3:] = matrices_from_rotvecs(a[:3]).T
    return G


def minimise(residual: Residual, jacobian: Jacobian, start: Sequence[FloatArray],
             sides: Sequence[str]) -> tuple[list[FloatArray], bool]:
    """Least squares over small motions of the transforms ``start`` (see ``SIDES``).

    ``residual(state)`` gives the residual vector of a list of transforms; ``jacobian(state)``
    its derivative (m, 6 k) against small motions of each transform on its side, rotation
    (rad) before translation. scipy's MINPACK Levenberg-Marquardt (scaled by the Jacobian's
    columns, so rad and mm parameters are treated alike) moves parameters ``x`` of
    ``exp(x) @ T0`` / ``T0 @ exp(x)``; the motion Jacobian is mapped onto ``x`` through SO(3)'s
    left and right Jacobians. Returns the transforms and whether the solver met its
    tolerances (False: it stopped at ``MAX_EVALUATIONS``).
    """
    T0 = [np.asarray(T, dtype=np.float64) for T in start]

    def state(x: FloatArray) -> list[FloatArray]:
        out = []
        for k, (T, side) in enumerate(zip(T0, sides, strict=True)):
            E = transforms_from_vectors(x[6 * k:6 * k + 6])
            out.append(E @ T if side == "left" else T @ E)
        return out

    def fun(x: FloatArray) -> FloatArray:
        return residual(state(x))

    def jac(x: FloatArray) -> FloatArray:
        out: FloatArray = jacobian(state(x)) @ _chart(x, sides)
        return out

    x0 = np.zeros(6 * len(T0))
    r0 = fun(x0)
    if float(r0 @ r0) == 0.0:
        return T0, True
    from scipy.optimize import least_squares  # on first use: a daemon that never solves
    # here starts without it (scipy.optimize is the largest import of a start)
    sol = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", ftol=TOLERANCE,
                        xtol=TOLERANCE, gtol=TOLERANCE, max_nfev=MAX_EVALUATIONS)
    return state(sol.x), bool(sol.status > 0)


def projection_jacobian(camera: CameraModel, pts: FloatArray) -> FloatArray:
    """(N, 2, 3) derivative of the projected pixels against the camera-frame points
    (central differences, steps 1e-6 of each point's depth, in one ``project`` call, so
    whatever distortion model the camera implements is honoured)."""
    n = len(pts)
    h = 1e-6 * np.abs(pts[:, 2])
    step = h[:, None, None] * np.eye(3)
    moved = np.concatenate([pts[:, None, :] + step, pts[:, None, :] - step], axis=1)
    proj = camera.project(moved.reshape(-1, 3)).reshape(n, 6, 2)
    out: FloatArray = ((proj[:, :3] - proj[:, 3:]).transpose(0, 2, 1)
                       / (2.0 * h)[:, None, None])
    return out


def point_motion_jacobian(pts: FloatArray) -> FloatArray:
    """(N, 3, 6) derivative of points against a small motion of their frame on the left:
    ``p' = exp(w) p + v`` gives ``[-[p]x, I]``."""
    out = np.zeros((len(pts), 3, 6))
    out[:, :, :3] = -skew(pts)
    out[:, :, 3:] = np.eye(3)
    return out


# ---------------------------------------------------------------------- the plain objectives
class Problem:
    """The samples in the arrays the residual functions need (see the module docstring)."""

    def __init__(self, samples: Sequence[Sample], mode: str, camera: CameraModel | None,
                 pixels: bool = True):
        self.mode = mode
        self.P = anchor_poses(samples, mode)
        self.Q = invert_transforms(self.P)
        self.B = board_poses(samples)
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

    def predicted(self, state: Sequence[FloatArray]) -> FloatArray:
        """(n, 4, 4) predicted ``T_cam_board``."""
        Y, C = state
        out: FloatArray = Y @ self.Q @ C
        return out

    def _corners(self, M: FloatArray) -> tuple[FloatArray, FloatArray]:
        Mk = M[self.index]
        return Mk, np.einsum("kij,kj->ki", Mk[:, :3, :3], self.obj) + Mk[:, :3, 3]

    def residual(self, state: Sequence[FloatArray]) -> FloatArray:
        """Pixels: observed - projected corners (``BEHIND_PX`` everywhere when a corner falls
        behind the camera); poses: per sample the rotation (``weight`` * axis sin angle) and
        the translation (mm) of the predicted board pose from the measured one."""
        M = self.predicted(state)
        if not self.pixels:
            rot = self.weight * vee(np.swapaxes(self.B[:, :3, :3], 1, 2) @ M[:, :3, :3])
            out: FloatArray = np.concatenate([rot, M[:, :3, 3] - self.B[:, :3, 3]], axis=1)
            return out.ravel()
        _, pts = self._corners(M)
        if (pts[:, 2] <= 0).any():
            return np.full(2 * len(pts), BEHIND_PX)
        assert self.camera is not None
        res: FloatArray = (self.px - self.camera.project(pts)).ravel()
        return res

    def jacobian(self, state: Sequence[FloatArray]) -> FloatArray:
        """(m, 12) derivative of :meth:`residual` against a small motion of Y (left) and of C
        (right)."""
        M = self.predicted(state)
        if not self.pixels:
            D = np.swapaxes(self.B[:, :3, :3], 1, 2) @ M[:, :3, :3]
            tr = np.trace(D, axis1=1, axis2=2)
            # vee of the antisymmetric part of [u] D is (tr D I - D) u / 2
            dvee = 0.5 * (tr[:, None, None] * np.eye(3) - D) @ np.swapaxes(
                self.B[:, :3, :3], 1, 2)
            J = np.zeros((len(M), 6, 12))
            J[:, :3, :3] = self.weight * dvee
            J[:, :3, 6:9] = self.weight * dvee @ M[:, :3, :3]
            J[:, 3:, :3] = -skew(M[:, :3, 3])
            J[:, 3:, 3:6] = np.eye(3)
            J[:, 3:, 9:] = M[:, :3, :3]
            return J.reshape(-1, 12)
        assert self.camera is not None
        Mk, pts = self._corners(M)
        Jp = projection_jacobian(self.camera, pts)
        Jm = np.zeros((len(pts), 3, 12))
        Jm[:, :, :6] = point_motion_jacobian(pts)
        # p = R_M (exp(w) obj + v) + t_M: [-R_M [obj]x, R_M]
        Jm[:, :, 6:9] = -Mk[:, :3, :3] @ skew(self.obj)
        Jm[:, :, 9:] = Mk[:, :3, :3]
        out: FloatArray = -(Jp @ Jm).reshape(-1, 12)
        return out

    def pixel_residuals(self, state: Sequence[FloatArray]) -> list[FloatArray]:
        """Per sample (N, 2) observed - projected, px."""
        r = self.residual(state)
        if (r == BEHIND_PX).all():
            raise CalibrationError("hand-eye: a board corner projects behind the camera")
        return np.split(r.reshape(-1, 2), np.cumsum(self.counts)[:-1])

    def cost(self, X: FloatArray, C: FloatArray) -> float:
        """Sum of squared residuals at (X, C); inf when a corner falls behind the camera."""
        r = self.residual((invert_transform(X), C))
        if self.pixels and (r == BEHIND_PX).all():
            return math.inf
        return float(r @ r)


#: The hand-eye state's transforms (Y, C) move on these sides.
STATE_SIDES = ("left", "right")


def refine(problem: Problem, X: FloatArray, C: FloatArray,
           ) -> tuple[FloatArray, FloatArray, bool]:
    """X and the board pose minimising the reprojection (or pose) residual, from (X, C);
    returns X, C and whether the solver converged."""
    start = (invert_transform(X), C)
    if problem.cost(X, C) == math.inf:
        raise CalibrationError("hand-eye: a board corner lies behind the camera at the start")
    (Y, C), converged = minimise(problem.residual, problem.jacobian, start, STATE_SIDES)
    return invert_transform(Y), C, converged
